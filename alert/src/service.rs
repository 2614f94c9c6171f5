//! The thin Zenoh layer around [`Monitor`]: follow, decode, feed, publish, log, remember.
//!
//! Corrected streams come through a follower per building ([`Fleet::follow_into`], all into one
//! queue of the monitor's), which loses nothing the gateway's history holds (PROTOCOL.md §5.2):
//! a stretch this service missed (it was slow, partitioned from the building, or restarted) is
//! read back from the history and fed to the monitor in order before the live batch that showed
//! the gap, so every window is judged on complete data, and an alert raised from such data says
//! it is late. The last sequence number handled per sensor is kept in `state_path` (written
//! every [`STATE_PERIOD`] and at shutdown), with how many batches before it the baseline filter
//! needs to settle and the window to fill: a restarted service
//! reads those batches again without judging them (they were judged before it stopped), then
//! judges what follows as if it had never stopped. With `watch_all_buildings`, buildings are
//! found by their gateways' heartbeats.
//!
//! Tilt samples are not kept in the histories; they arrive through a plain subscription whose
//! callback only copies into a bounded channel (`try_send`, counted when full). One task owns the
//! [`Monitor`] and does everything else but sign and put the alerts it finds, which a second
//! task does in the order they were found; the window state needs no lock.

use std::collections::{BTreeMap, BTreeSet};
use std::future::Future;
use std::path::Path;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::Duration;

use time::OffsetDateTime;
use tokio::sync::mpsc;
use triax_client::{Delivery, Fleet, FollowOptions, Following};
use triax_protocol::keys::{all_buildings, all_sensors, Stream};
use triax_protocol::messages::{Alert, AlertingStatus, TiltSample};
use triax_protocol::provenance::verify_message;
use triax_protocol::signing::{sign_alert, to_hex, LabSigningKey};
use triax_protocol::{from_json, to_json, BuildingId, CorrectedBatch, Key, SensorId};

use crate::config::Config;
use crate::monitor::Monitor;

/// Messages waiting for the monitor: corrected batches (one queue for every building), and
/// apart, tilt samples and buildings found.
pub const INBOX_CAPACITY: usize = 4096;
/// How often the resume state is written.
pub const STATE_PERIOD: Duration = Duration::from_secs(1);

/// Why the service could not run.
#[derive(Debug, thiserror::Error)]
pub enum ServiceError {
    #[error(transparent)]
    ZenohConfig(#[from] triax_net::ZenohConfigError),
    #[error("zenoh: {what}: {message}")]
    Zenoh { what: &'static str, message: String },
    #[error("state file {path}: {message}")]
    State { path: String, message: String },
    #[error("signing key file {path}: {message}")]
    SigningKey { path: String, message: String },
}

/// The key every alert is signed with: read from `path`, or created there (with the public key
/// in `<path>.pub`) when the file does not exist; without a path, one for this run only.
pub fn signing_key(path: Option<&Path>) -> Result<LabSigningKey, ServiceError> {
    let Some(path) = path else {
        let key = LabSigningKey::generate(&mut rand::rngs::OsRng);
        tracing::warn!(
            public_key = %to_hex(key.verifying_key().as_bytes()),
            "no signing_key_file: alerts are signed with a key made for this run, which no \
             consumer can trust; set signing_key_file and give consumers its .pub"
        );
        return Ok(key);
    };
    let (key, origin) =
        triax_net::keys::signing_key(path).map_err(|e| ServiceError::SigningKey {
            path: path.display().to_string(),
            message: e.to_string(),
        })?;
    let public = to_hex(key.verifying_key().as_bytes());
    match origin {
        triax_net::keys::Origin::Read => {
            tracing::info!(path = %path.display(), public_key = %public, "signing alerts")
        }
        triax_net::keys::Origin::Made => {
            tracing::warn!(path = %path.display(), public_key = %public,
            "created a signing key: give consumers its public key (the .pub beside it)")
        }
    }
    Ok(key)
}

fn zenoh_error(what: &'static str) -> impl FnOnce(zenoh::Error) -> ServiceError {
    move |e| ServiceError::Zenoh {
        what,
        message: e.to_string(),
    }
}

enum Inbound {
    Tilt {
        key: String,
        payload: Vec<u8>,
        attachment: Option<Vec<u8>>,
    },
    /// A gateway's heartbeat named a building not followed yet.
    Building(BuildingId),
}

/// Where a sensor's stream was left.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(untagged)]
enum Position {
    /// The last sequence number handled, and how many batches before it a restarted service
    /// reads again to settle the baseline filter and fill the window.
    WithLeadIn { judged: u64, lead_in_batches: u64 },
    /// A state file written before lead-ins: the sequence number alone.
    Judged(u64),
}

impl Position {
    fn judged(self) -> u64 {
        match self {
            Position::WithLeadIn { judged, .. } | Position::Judged(judged) => judged,
        }
    }

    /// Where the history is read from on a restart.
    fn resume_after(self) -> u64 {
        match self {
            Position::WithLeadIn {
                judged,
                lead_in_batches,
            } => judged.saturating_sub(lead_in_batches),
            Position::Judged(judged) => judged,
        }
    }
}

/// The last position per building and sensor.
type Positions = BTreeMap<BuildingId, BTreeMap<SensorId, Position>>;

/// Most batches read again on a restart, whatever the stream's batches: bounds the history a
/// restart reads per sensor.
const MAX_LEAD_IN_BATCHES: u64 = 100_000;

/// Batches of this stream's size that span the baseline's settling and a whole window.
fn lead_in_batches(config: &Config, batch: &CorrectedBatch) -> u64 {
    let s = &config.settings;
    let batch_s = batch.samples.len() as f64 / batch.header.sample_rate_hz;
    let corner_hz = crate::highpass::corner_hz(s.highpass_hz, batch.header.sample_rate_hz);
    let span_s = crate::highpass::settle_s(corner_hz) + s.window_s;
    // An empty batch says nothing of the stream's pace.
    if batch_s.is_nan() || batch_s <= 0.0 {
        return MAX_LEAD_IN_BATCHES;
    }
    ((span_s / batch_s).ceil() as u64 + 1).min(MAX_LEAD_IN_BATCHES)
}

fn resume_points(positions: &Positions, building: &BuildingId) -> BTreeMap<SensorId, u64> {
    positions
        .get(building)
        .map(|sensors| {
            sensors
                .iter()
                .map(|(s, p)| (s.clone(), p.resume_after()))
                .collect()
        })
        .unwrap_or_default()
}

/// Reads the resume state; none if the file does not exist.
fn load_state(path: &Path) -> Result<Positions, ServiceError> {
    let bad = |message: String| ServiceError::State {
        path: path.display().to_string(),
        message,
    };
    match std::fs::read(path) {
        Ok(bytes) => serde_json::from_slice(&bytes).map_err(|e| bad(e.to_string())),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(Positions::new()),
        Err(e) => Err(bad(e.to_string())),
    }
}

/// Writes the resume state whole or not at all (a new file renamed over the old).
fn save_state(path: &Path, positions: &Positions) -> std::io::Result<()> {
    if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir)?;
    }
    let tmp = path.with_extension("tmp");
    // A map of ids to numbers always serialises.
    let body = serde_json::to_vec(positions).expect("positions serialise");
    std::fs::write(&tmp, body)?;
    std::fs::rename(&tmp, path)
}

/// Follows one building: every delivery goes to the monitor's queue of corrected batches,
/// shared by every building, waiting for room (a full queue slows the follower, whose own
/// gap-filling makes up for what Zenoh then drops).
fn follow(
    fleet: &Fleet,
    building: BuildingId,
    resume: BTreeMap<SensorId, u64>,
    tx: mpsc::Sender<Delivery>,
) -> Following {
    let mut options = FollowOptions::new(building.clone());
    options.resume_after = resume;
    // Alerts judge the present: a hole filled late is in the history for review.
    options.late_batches = false;
    tracing::info!(building = %building, "following corrected streams");
    fleet.follow_into(options, tx)
}

/// Where the service is in each stream, and what a restart judged before.
struct Progress {
    positions: Positions,
    /// Batches up to these sequence numbers were judged before the restart: they only prime.
    judged_before: BTreeMap<(BuildingId, SensorId), u64>,
}

impl Progress {
    fn new(positions: Positions) -> Progress {
        let judged_before = positions
            .iter()
            .flat_map(|(b, sensors)| {
                sensors
                    .iter()
                    .map(move |(s, p)| ((b.clone(), s.clone()), p.judged()))
            })
            .collect();
        Progress {
            positions,
            judged_before,
        }
    }

    /// Feeds one corrected batch to the monitor: primes it with a batch judged before a
    /// restart, judges any other, and remembers where the stream is.
    fn judge(&mut self, monitor: &mut Monitor, config: &Config, d: &Delivery) -> Vec<Alert> {
        let h = &d.batch.header;
        let building = &d.building;
        if !self.judged_before.is_empty() {
            let key = (building.clone(), h.sensor_id.clone());
            if let Some(&judged) = self.judged_before.get(&key) {
                if d.recovered && h.sequence <= judged {
                    monitor.prime(building, &d.batch, OffsetDateTime::now_utc());
                    return Vec::new();
                }
                self.judged_before.remove(&key);
            }
        }
        let position = Position::WithLeadIn {
            judged: h.sequence,
            lead_in_batches: lead_in_batches(config, &d.batch),
        };
        // In place for a known sensor: no ids to copy per batch.
        match self
            .positions
            .get_mut(building)
            .and_then(|sensors| sensors.get_mut(&h.sensor_id))
        {
            Some(p) => *p = position,
            None => {
                self.positions
                    .entry(building.clone())
                    .or_default()
                    .insert(h.sensor_id.clone(), position);
            }
        }
        let mut alerts = monitor.on_corrected(building, &d.batch, OffsetDateTime::now_utc());
        if d.recovered {
            alerts.iter_mut().for_each(mark_late);
        }
        alerts
    }
}

/// Runs the alerting service until `shutdown` completes.
///
/// Opens a Zenoh session from `config.zenoh`, follows the corrected streams and subscribes to
/// the tilt streams of the watched buildings, publishes every alert on
/// `triax/<building>/alert/<sensor>` and logs it.
pub async fn run(config: Config, shutdown: impl Future<Output = ()>) -> Result<(), ServiceError> {
    let mut progress = Progress::new(match &config.state_path {
        Some(p) => load_state(p)?,
        None => Positions::new(),
    });
    let signing = signing_key(config.signing_key_file.as_deref())?;
    let session = zenoh::open(config.zenoh.to_config()?)
        .await
        .map_err(zenoh_error("open session"))?;
    let (tx, mut rx) = mpsc::channel::<Inbound>(INBOX_CAPACITY);
    let dropped = Arc::new(AtomicU64::new(0));
    let mut subscribers = Vec::new();
    // One subscription, for the same reason as the corrected streams' (`Fleet`); buildings not
    // watched are filtered out here.
    let (tilt_expr, watched): (String, Option<BTreeSet<String>>) =
        match (config.watch_all_buildings, config.buildings.keys().next()) {
            (false, Some(b)) if config.buildings.len() == 1 => (all_sensors(b, Stream::Tilt), None),
            (false, _) => (
                all_buildings(Stream::Tilt),
                Some(config.buildings.keys().map(|b| b.to_string()).collect()),
            ),
            (true, _) => (all_buildings(Stream::Tilt), None),
        };
    {
        let expr = tilt_expr;
        let (tx, dropped) = (tx.clone(), dropped.clone());
        let sub = session
            .declare_subscriber(expr.clone())
            .callback(move |sample| {
                let key = sample.key_expr().as_str();
                if let Some(w) = &watched {
                    if !key.split('/').nth(1).is_some_and(|b| w.contains(b)) {
                        return;
                    }
                }
                let msg = Inbound::Tilt {
                    key: sample.key_expr().as_str().to_owned(),
                    payload: sample.payload().to_bytes().into_owned(),
                    attachment: sample.attachment().map(|a| a.to_bytes().into_owned()),
                };
                if tx.try_send(msg).is_err() {
                    dropped.fetch_add(1, Ordering::Relaxed);
                }
            })
            .await
            .map_err(zenoh_error("declare subscriber"))?;
        tracing::info!(key_expr = %expr, "subscribed");
        subscribers.push(sub);
    }
    if config.watch_all_buildings {
        let tx = tx.clone();
        let sub = session
            .declare_subscriber("triax/*/heartbeat")
            .callback(move |sample| {
                if let Ok(Key::Heartbeat(b)) = Key::parse(sample.key_expr().as_str()) {
                    let _ = tx.try_send(Inbound::Building(b));
                }
            })
            .await
            .map_err(zenoh_error("declare subscriber"))?;
        subscribers.push(sub);
    }
    // One subscription for every followed building: a subscription each would have Zenoh
    // match every batch against all of them (`triax_client::Fleet`).
    let only = (!config.watch_all_buildings && config.buildings.len() == 1)
        .then(|| config.buildings.keys().next().cloned())
        .flatten();
    if config.gateway_keys.is_none() {
        tracing::warn!(
            "no [gateways] keys: batches and tilt from any peer are judged as the gateway's"
        );
    }
    let fleet = Fleet::start(&session, only.as_ref(), config.gateway_keys.clone())
        .await
        .map_err(|e| ServiceError::Zenoh {
            what: "follow the buildings",
            message: e.to_string(),
        })?;
    let mut followed: BTreeSet<BuildingId> = BTreeSet::new();
    let mut followers = Vec::new();
    // Buildings listed, and buildings the state remembers when watching all.
    let mut initial: BTreeSet<BuildingId> = config.buildings.keys().cloned().collect();
    if config.watch_all_buildings {
        initial.extend(progress.positions.keys().cloned());
    }
    let (deliveries_tx, mut deliveries) = mpsc::channel::<Delivery>(INBOX_CAPACITY);
    for b in initial {
        let resume = resume_points(&progress.positions, &b);
        followers.push(follow(&fleet, b.clone(), resume, deliveries_tx.clone()));
        followed.insert(b);
    }

    let status = declare_status(&session, &config).await?;
    let public_key_hex = to_hex(signing.verifying_key().as_bytes());
    let mut monitor = Monitor::new(config.clone(), OffsetDateTime::now_utc());
    let mut tick = tokio::time::interval(stale_check_period(&config));
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    let mut save = tokio::time::interval(STATE_PERIOD);
    save.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    let mut reported_dropped = 0;
    let (publisher, publishing) = spawn_publisher(session.clone(), signing);
    tokio::pin!(shutdown);
    loop {
        let alerts = tokio::select! {
            _ = &mut shutdown => break,
            d = deliveries.recv() => match d {
                Some(d) => progress.judge(&mut monitor, &config, &d),
                // The sender here keeps the channel open.
                None => break,
            },
            msg = rx.recv() => match msg {
                Some(Inbound::Building(b)) => {
                    // A heartbeat any peer can put: with keys, only a building one is trusted
                    // for is followed.
                    let trusted = config
                        .gateway_keys
                        .as_ref()
                        .is_none_or(|k| !k.keys(&b).is_empty());
                    if trusted && followed.insert(b.clone()) {
                        let resume = resume_points(&progress.positions, &b);
                        followers.push(follow(&fleet, b, resume, deliveries_tx.clone()));
                    }
                    Vec::new()
                }
                Some(Inbound::Tilt { key, payload, attachment }) => {
                    let genuine = config.gateway_keys.as_ref().is_none_or(|k| {
                        verify_message(k, &key, "", &payload, attachment.as_deref()).is_ok()
                    });
                    if genuine {
                        on_tilt(&mut monitor, &key, &payload)
                    } else {
                        tracing::debug!(key, "a tilt sample not signed by its gateway skipped");
                        Vec::new()
                    }
                }
                // The sender here keeps the channel open.
                None => break,
            },
            _ = tick.tick() => {
                let now_dropped = dropped.load(Ordering::Relaxed);
                if now_dropped > reported_dropped {
                    tracing::warn!(dropped = now_dropped, "inbox full: tilt samples dropped");
                    reported_dropped = now_dropped;
                }
                monitor.check_stale(OffsetDateTime::now_utc())
            }
            q = status.recv_async() => {
                if let Ok(q) = q {
                    answer_status(&monitor, &q, &public_key_hex).await;
                }
                Vec::new()
            }
            _ = save.tick() => {
                if let Some(p) = &config.state_path {
                    if let Err(e) = save_state(p, &progress.positions) {
                        tracing::warn!(path = %p.display(), cause = %e, "resume state not written");
                    }
                }
                Vec::new()
            }
        };
        for alert in alerts {
            if publisher.send(alert).await.is_err() {
                tracing::error!("the alert publisher stopped");
            }
        }
    }
    drop(followers);
    // Every alert judged goes out before the session closes.
    drop(publisher);
    if let Err(e) = publishing.await {
        tracing::error!(cause = %e, "the alert publisher failed");
    }
    if let Some(p) = &config.state_path {
        if let Err(e) = save_state(p, &progress.positions) {
            tracing::warn!(path = %p.display(), cause = %e, "resume state not written");
        }
    }
    drop(subscribers);
    session
        .close()
        .await
        .map_err(zenoh_error("close session"))?;
    tracing::info!("stopped");
    Ok(())
}

type StatusQueryable =
    zenoh::query::Queryable<zenoh::handlers::FifoChannelHandler<zenoh::query::Query>>;

/// The queryable on `triax/<building>/alerting` of the watched buildings (PROTOCOL.md §3.8).
async fn declare_status(
    session: &zenoh::Session,
    config: &Config,
) -> Result<StatusQueryable, ServiceError> {
    let expr = match (config.watch_all_buildings, config.buildings.keys().next()) {
        (false, Some(b)) if config.buildings.len() == 1 => Key::Alerting(b.clone()).to_string(),
        _ => "triax/*/alerting".to_owned(),
    };
    session
        .declare_queryable(expr)
        .await
        .map_err(zenoh_error("declare the status queryable"))
}

/// Answers a status query: one reply per watched building its key expression names.
async fn answer_status(monitor: &Monitor, query: &zenoh::query::Query, public_key_hex: &str) {
    let wanted = query.key_expr().clone();
    for b in monitor.buildings() {
        let key = Key::Alerting(b.clone()).to_string();
        let Ok(k) = zenoh::key_expr::KeyExpr::try_from(key.as_str()) else {
            continue;
        };
        if !wanted.intersects(&k) {
            continue;
        }
        let status = AlertingStatus {
            format_version: triax_protocol::JSON_FORMAT_VERSION,
            building: b.clone(),
            public_key_hex: public_key_hex.to_owned(),
            reported_at: OffsetDateTime::now_utc(),
            sensors: monitor.judgements(&b),
        };
        if let Err(e) = query.reply(&key, to_json(&status)).await {
            tracing::warn!(key = %key, cause = %e, "status reply failed");
        }
    }
}

/// How often staleness is checked: often enough to report within a quarter of the allowance.
fn stale_check_period(config: &Config) -> Duration {
    Duration::from_secs_f64((config.settings.stale_after_s / 4.0).clamp(0.05, 5.0))
}

/// An alert judged on data read back from the history says so.
fn mark_late(alert: &mut Alert) {
    alert.late = true;
    alert.statement.push_str(
        " Raised late: the data it judged was read back from the gateway's history after an \
         outage or a partition.",
    );
}

fn on_tilt(monitor: &mut Monitor, key: &str, payload: &[u8]) -> Vec<Alert> {
    let now = OffsetDateTime::now_utc();
    let (building, sensor) = match Key::parse(key) {
        Ok(Key::Tilt(b, s)) => (b, s),
        Ok(other) => {
            tracing::warn!(key = %other, "unexpected key on a subscription");
            return Vec::new();
        }
        Err(e) => {
            tracing::warn!(key, cause = %e, "not a Triax key");
            return Vec::new();
        }
    };
    match from_json::<TiltSample>(payload) {
        Ok(tilt) if tilt.sensor_id == sensor => monitor.on_tilt(&building, &tilt, now),
        Ok(tilt) => {
            tracing::warn!(key, sample_sensor = %tilt.sensor_id,
                "tilt sample names another sensor than its key: ignored");
            Vec::new()
        }
        Err(e) => {
            tracing::warn!(key, cause = %e, "malformed tilt sample");
            Vec::new()
        }
    }
}

/// Alerts waiting to be signed and put.
pub const PUBLISH_QUEUE: usize = 1024;

/// Signs, logs and puts alerts in the order they come, on a task of its own: a burst of
/// judgements (every sensor of a building sends its batch at the same instant) is judged while
/// the alerts already found are signed and put, on the other core, and each alert waits only
/// for those before it, not for the rest of the burst's judgements. The queue is bounded;
/// when full, judging waits (an alert is never dropped).
fn spawn_publisher(
    session: zenoh::Session,
    signing: LabSigningKey,
) -> (mpsc::Sender<Alert>, tokio::task::JoinHandle<()>) {
    let (tx, mut rx) = mpsc::channel::<Alert>(PUBLISH_QUEUE);
    let task = tokio::spawn(async move {
        while let Some(alert) = rx.recv().await {
            publish(&session, &alert, &signing).await;
        }
    });
    (tx, task)
}

async fn publish(session: &zenoh::Session, alert: &Alert, key: &LabSigningKey) {
    tracing::warn!(
        building = %alert.building,
        sensor = %alert.sensor_id,
        kind = ?alert.kind,
        level = ?alert.level,
        value = alert.value,
        standard_uncertainty = alert.standard_uncertainty,
        threshold = alert.threshold,
        unit = %alert.unit,
        late = alert.late,
        statement = %alert.statement,
        "alert"
    );
    let signed = sign_alert(alert, key);
    let expr = Key::Alert(alert.building.clone(), alert.sensor_id.clone()).to_string();
    // Zenoh's default for a put drops it when a link's queue is full: an alert must wait
    // instead, like the gateways' corrected batches.
    let put = session
        .put(&expr, to_json(&signed))
        .congestion_control(zenoh::qos::CongestionControl::Block);
    if let Err(e) = put.await {
        tracing::error!(key = %expr, cause = %e, "alert not published");
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn resume_state_reads_old_and_new_positions() {
        let old: Positions = serde_json::from_str(r#"{"hq":{"acc-01":12}}"#).unwrap();
        let hq = BuildingId::new("hq").unwrap();
        let acc = SensorId::new("acc-01").unwrap();
        assert_eq!(old[&hq][&acc], Position::Judged(12));
        assert_eq!(resume_points(&old, &hq)[&acc], 12);
        let new: Positions =
            serde_json::from_str(r#"{"hq":{"acc-01":{"judged":12,"lead_in_batches":30}}}"#)
                .unwrap();
        assert_eq!(new[&hq][&acc].judged(), 12);
        // Read again from the start of the stream when the lead-in reaches past it.
        assert_eq!(resume_points(&new, &hq)[&acc], 0);
        let back: Positions = serde_json::from_str(&serde_json::to_string(&new).unwrap()).unwrap();
        assert_eq!(back, new);
    }

    #[test]
    fn the_lead_in_spans_settling_and_a_window() {
        let config =
            Config::from_toml("window_s = 10.0\nhighpass_hz = 0.1\n[buildings.hq]\n").unwrap();
        let batch = CorrectedBatch {
            header: triax_protocol::BatchHeader {
                sensor_id: SensorId::new("acc-01").unwrap(),
                sequence: 1,
                timestamp_ns: 0,
                sample_rate_hz: 100.0,
            },
            batch_flags: 0,
            info: triax_protocol::CorrectionInfo {
                calibration_version: 1,
                mode: triax_protocol::Mode::Dynamic,
                coverage_factor: 2.0,
            },
            samples: vec![
                triax_protocol::CorrectedSample {
                    accel_mps2: [0.0; 3],
                    uncertainty_mps2: [0.01; 3],
                    flags: 0,
                };
                10
            ],
        };
        // 15.55 s of settling and 10 s of window in 0.1 s batches, and one more.
        assert_eq!(lead_in_batches(&config, &batch), 257);
    }
}
