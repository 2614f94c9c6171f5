//! The thin Zenoh layer around [`Building`]: follow, gather, identify, track, publish, record,
//! sign, remember.
//!
//! Corrected streams come through one [`Fleet`] subscription and a follower per building,
//! which reads back from the gateway's history whatever this service missed (PROTOCOL.md
//! §5.2). After each window the building's state is written to `<state_dir>/<building>/
//! state.json`, whole or not at all: the next window's index, per sensor the last batch wholly
//! inside an identified window (a restarted service resumes its follower there, so the window
//! it was filling is filled again from the history), and the tracks with their training
//! observations.
//!
//! **Identification off the loop.** Every building's windows close at the same instants (their
//! boundaries are multiples of `window_s` since the epoch), and a window takes a fraction of a
//! second to identify: a loop that waited for each would stand still for all of a fleet's
//! windows at once, while the followers' queues overflowed. So closed windows go to one
//! identification thread through a queue of [`IDENTIFY_QUEUE`] windows, taken in the order they
//! closed, and the loop goes on gathering; a building's windows are concluded (tracked,
//! published, recorded, saved) in order as their results come back. The state saved after a
//! window is the one as that window closed, so a window still queued at a stop is gathered
//! again from the history after the restart. One thread: a fleet's identifications take one
//! core at most; when the queue is full (the thread cannot keep up), the loop waits, and the
//! followers' own gap filling makes up for what Zenoh then drops.

use std::collections::BTreeMap;
use std::future::Future;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use time::OffsetDateTime;
use tokio::sync::mpsc;
use triax_client::{Delivery, Fleet, FollowOptions};
use triax_protocol::messages::Alert;
use triax_protocol::provenance::sign_message;
use triax_protocol::signing::{sign_alert, LabSigningKey};
use triax_protocol::{to_json, BuildingId, Key};
use zenoh::qos::CongestionControl;

use crate::building::{identify_window, Building, BuildingState};
use triax_modal::{Identification, ModalError};

use crate::config::{BuildingConfig, Config};
use crate::grid::ClosedWindow;

/// Messages waiting for the loop.
pub const INBOX_CAPACITY: usize = 4096;
/// Closed windows waiting for the identification thread.
pub const IDENTIFY_QUEUE: usize = 256;

/// A reading of a building's temperature source, as JSON on its configured key:
/// `{"timestamp_ns": …, "temperature_c": …}`.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TemperatureReading {
    /// ns since the Unix epoch, on the clock the sensors' batches are stamped with.
    pub timestamp_ns: i64,
    pub temperature_c: f64,
}

/// Why the service could not run.
#[derive(Debug, thiserror::Error)]
pub enum ServiceError {
    #[error(transparent)]
    ZenohConfig(#[from] triax_net::ZenohConfigError),
    #[error("zenoh: {what}: {message}")]
    Zenoh { what: &'static str, message: String },
    #[error("state file {path}: {message}")]
    State { path: String, message: String },
    #[error(transparent)]
    SigningKey(#[from] triax_alert::ServiceError),
    #[error("identification thread: {0}")]
    Thread(String),
}

fn zenoh_error(what: &'static str) -> impl FnOnce(zenoh::Error) -> ServiceError {
    move |e| ServiceError::Zenoh {
        what,
        message: e.to_string(),
    }
}

enum Inbound {
    Corrected(BuildingId, Delivery),
    Temperature(BuildingId, Vec<u8>),
}

/// A closed window on its way to the identification thread.
struct Job {
    building: BuildingId,
    config: Arc<BuildingConfig>,
    closed: ClosedWindow,
}

/// A window back from the identification thread; `result` is none if it panicked.
struct Identified {
    building: BuildingId,
    closed: ClosedWindow,
    result: Option<Result<Identification, ModalError>>,
}

/// The identification thread: takes jobs in order until the loop stops sending or receiving.
fn spawn_identifier(
) -> Result<(mpsc::Sender<Job>, mpsc::UnboundedReceiver<Identified>), ServiceError> {
    let (job_tx, mut job_rx) = mpsc::channel::<Job>(IDENTIFY_QUEUE);
    let (done_tx, done_rx) = mpsc::unbounded_channel::<Identified>();
    std::thread::Builder::new()
        .name("triax-identify".into())
        .spawn(move || {
            while let Some(job) = job_rx.blocking_recv() {
                let result = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
                    identify_window(&job.config, &job.closed)
                }))
                .ok();
                let done = Identified {
                    building: job.building,
                    closed: job.closed,
                    result,
                };
                if done_tx.send(done).is_err() {
                    return;
                }
            }
        })
        .map_err(|e| ServiceError::Thread(e.to_string()))?;
    Ok((job_tx, done_rx))
}

/// Queues a building's closed windows for identification, oldest first.
async fn submit(jobs: &mpsc::Sender<Job>, building: &Building, closed: Vec<ClosedWindow>) {
    if closed.is_empty() {
        return;
    }
    let config = Arc::new(building.config.clone());
    for closed in closed {
        let job = Job {
            building: building.id.clone(),
            config: config.clone(),
            closed,
        };
        if jobs.send(job).await.is_err() {
            tracing::error!(building = %building.id, "the identification thread stopped");
        }
    }
}

fn state_path(dir: &Path, building: &BuildingId) -> PathBuf {
    dir.join(building.as_str()).join("state.json")
}

/// Reads a building's state; none if the file does not exist.
pub fn load_state(path: &Path) -> Result<Option<BuildingState>, ServiceError> {
    let bad = |message: String| ServiceError::State {
        path: path.display().to_string(),
        message,
    };
    match std::fs::read(path) {
        Ok(bytes) => serde_json::from_slice(&bytes)
            .map(Some)
            .map_err(|e| bad(e.to_string())),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(None),
        Err(e) => Err(bad(e.to_string())),
    }
}

/// Writes a building's state whole or not at all (a new file renamed over the old).
fn save_state(path: &Path, state: &BuildingState) -> std::io::Result<()> {
    if let Some(dir) = path.parent() {
        std::fs::create_dir_all(dir)?;
    }
    let tmp = path.with_extension("tmp");
    let body = serde_json::to_vec(state).map_err(std::io::Error::other)?;
    std::fs::write(&tmp, body)?;
    std::fs::File::open(&tmp)?.sync_all()?;
    std::fs::rename(&tmp, path)
}

/// Runs the service until `shutdown` completes.
pub async fn run(config: Config, shutdown: impl Future<Output = ()>) -> Result<(), ServiceError> {
    let signing = triax_alert::service::signing_key(config.signing_key_file.as_deref())?;
    let session = zenoh::open(config.zenoh.to_config()?)
        .await
        .map_err(zenoh_error("open session"))?;
    let (tx, mut rx) = mpsc::channel::<Inbound>(INBOX_CAPACITY);
    let only = (config.buildings.len() == 1)
        .then(|| config.buildings.keys().next().cloned())
        .flatten();
    let fleet = Fleet::start(&session, only.as_ref(), config.gateway_keys.clone())
        .await
        .map_err(|e| ServiceError::Zenoh {
            what: "follow the buildings",
            message: e.to_string(),
        })?;
    let mut buildings: BTreeMap<BuildingId, Building> = BTreeMap::new();
    let mut followers = Vec::new();
    let mut subscribers = Vec::new();
    for (id, bc) in &config.buildings {
        let state = match &config.state_dir {
            Some(dir) => load_state(&state_path(dir, id))?,
            None => None,
        };
        if bc.chain.is_none() {
            tracing::warn!(building = %id, "no [chain] uncertainty configured: mode shapes carry \
                their statistical uncertainty only");
        }
        if bc.temperature_key.is_none() {
            tracing::warn!(building = %id, "no temperature_key: the tracker has no regressor, \
                and a temperature swing will read as a shift");
        }
        let building = Building::new(id.clone(), bc.clone(), state.as_ref());
        let mut options = FollowOptions::new(id.clone());
        options.resume_at = building.gatherer.positions();
        if let Some(next) = state.as_ref().and_then(|s| s.next_index) {
            options.new_sensors_from_ns = Some(building.gatherer.window_start_ns(next));
        }
        tracing::info!(building = %id, resume = ?state.as_ref().and_then(|s| s.next_index),
            "following corrected streams");
        // Windows are cut from the stream in time order; a hole filled late stays a hole.
        options.late_batches = false;
        let mut follower = fleet.follow(options);
        let (tx_f, b) = (tx.clone(), id.clone());
        followers.push(tokio::spawn(async move {
            while let Some(d) = follower.next().await {
                if tx_f.send(Inbound::Corrected(b.clone(), d)).await.is_err() {
                    return;
                }
            }
        }));
        if let Some(key) = &bc.temperature_key {
            let (tx_t, b) = (tx.clone(), id.clone());
            let sub = session
                .declare_subscriber(key.clone())
                .callback(move |sample| {
                    let payload = sample.payload().to_bytes().into_owned();
                    let _ = tx_t.try_send(Inbound::Temperature(b.clone(), payload));
                })
                .await
                .map_err(zenoh_error("subscribe to a temperature source"))?;
            subscribers.push(sub);
        }
        buildings.insert(id.clone(), building);
    }
    drop(tx);
    let (jobs, mut identified) = spawn_identifier()?;
    let started = tokio::time::Instant::now();
    let mut tick = tokio::time::interval(std::time::Duration::from_secs(1));
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    tokio::pin!(shutdown);
    loop {
        let msg = tokio::select! {
            _ = &mut shutdown => break,
            msg = rx.recv() => match msg { Some(m) => m, None => break },
            done = identified.recv() => {
                // The thread lives while `jobs` does.
                let Some(done) = done else { break };
                if let Some(building) = buildings.get_mut(&done.building) {
                    conclude(&session, &config, building, done, &signing).await;
                }
                continue;
            }
            _ = tick.tick() => {
                let now_s = started.elapsed().as_secs_f64();
                for building in buildings.values_mut() {
                    let closed = building.tick(now_s);
                    submit(&jobs, building, closed).await;
                }
                continue;
            }
        };
        match msg {
            Inbound::Temperature(b, payload) => {
                match serde_json::from_slice::<TemperatureReading>(&payload) {
                    Ok(r) => {
                        if let Some(building) = buildings.get_mut(&b) {
                            building.on_temperature(r.timestamp_ns, r.temperature_c);
                        }
                    }
                    Err(e) => tracing::warn!(building = %b, cause = %e, "malformed temperature"),
                }
            }
            Inbound::Corrected(b, d) => {
                let Some(building) = buildings.get_mut(&b) else {
                    continue;
                };
                let now_s = started.elapsed().as_secs_f64();
                let closed = building.on_batch(&d.batch, d.recovered, now_s);
                submit(&jobs, building, closed).await;
            }
        }
    }
    for f in &followers {
        f.abort();
    }
    drop(subscribers);
    session
        .close()
        .await
        .map_err(zenoh_error("close session"))?;
    tracing::info!("stopped");
    Ok(())
}

/// Tracks an identified window, publishes, records, alerts and saves.
async fn conclude(
    session: &zenoh::Session,
    config: &Config,
    building: &mut Building,
    done: Identified,
    signing: &LabSigningKey,
) {
    let Identified { closed, result, .. } = done;
    let outcome = match result {
        Some(result) => building.conclude(&closed, result, None, OffsetDateTime::now_utc()),
        None => {
            tracing::error!(building = %building.id,
                window_start_ns = closed.window.start_timestamp_ns, "identification panicked");
            building.conclude_failed(
                &closed,
                "the identification failed with an internal error (a panic, in the service's \
                 log): nothing identified"
                    .into(),
                OffsetDateTime::now_utc(),
            )
        }
    };
    let m = &outcome.modes;
    tracing::info!(
        building = %building.id,
        window_start_ns = m.window_start_ns,
        modes = m.modes.len(),
        refused = m.refused.as_deref().unwrap_or(""),
        warnings = m.warnings.len(),
        tracked = m.tracked,
        late = m.late,
        "window identified"
    );
    // Kept before it is published: whoever sees it can read it back from the record.
    if let Some(root) = &config.state_dir {
        let dir = root.join(building.id.as_str());
        match crate::record::append(
            &dir,
            m,
            building.record_lines,
            building.config.record_max_windows,
        ) {
            Ok(lines) => building.record_lines = lines,
            Err(e) => tracing::error!(dir = %dir.display(), cause = %e, "record not written"),
        }
        let path = state_path(root, &building.id);
        if let Err(e) = save_state(&path, &building.state_after(&closed)) {
            tracing::error!(path = %path.display(), cause = %e, "state not written");
        }
    }
    let key = Key::Modes(building.id.clone()).to_string();
    let payload = to_json(m);
    // Signed with the service's key, as its alerts are (PROTOCOL.md §3.10, §6): a window a peer
    // puts does not verify.
    let signed_at_ns =
        i64::try_from(OffsetDateTime::now_utc().unix_timestamp_nanos()).unwrap_or(i64::MAX);
    let attachment = sign_message(signing, &key, "", signed_at_ns, &payload);
    // Zenoh's default for a put drops it when a link's queue is full: a window, a few a hour,
    // and an alert must wait instead, as `triax-alert`'s alerts do.
    let put = session
        .put(&key, payload)
        .attachment(attachment.to_vec())
        .congestion_control(CongestionControl::Block);
    if let Err(e) = put.await {
        tracing::error!(key = %key, cause = %e, "modes not published");
    }
    for alert in &outcome.alerts {
        publish_alert(session, alert, signing).await;
    }
}

async fn publish_alert(session: &zenoh::Session, alert: &Alert, key: &LabSigningKey) {
    tracing::warn!(
        building = %alert.building,
        sensor = %alert.sensor_id,
        kind = ?alert.kind,
        value = alert.value,
        standard_uncertainty = alert.standard_uncertainty,
        statement = %alert.statement,
        "alert"
    );
    let signed = sign_alert(alert, key);
    let expr = Key::Alert(alert.building.clone(), alert.sensor_id.clone()).to_string();
    let put = session
        .put(&expr, to_json(&signed))
        .congestion_control(CongestionControl::Block);
    if let Err(e) = put.await {
        tracing::error!(key = %expr, cause = %e, "alert not published");
    }
}
