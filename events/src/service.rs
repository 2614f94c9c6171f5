//! The Zenoh side: follow the buildings, detect, fetch each event's window from the history,
//! analyse, sign, publish, write the files, answer queries, remember.
//!
//! - **Following.** One [`Fleet`] subscription and a follower per building, with late batches
//!   (a gateway's backfill) handed over: [`crate::building::Building`] puts each stream back in
//!   order and waits for its holes. Resumed after a restart from the positions saved, which lie
//!   before whatever was not yet reported, so the detector sees it again.
//! - **Reports.** An event whose window's data are in goes to the report worker, one event at a
//!   time in the order they closed: the window read from the gateway's history (late batches
//!   included, asked for again if its end is not kept yet), the calibration record in force of
//!   each sensor from the gateway's status (`sensor=<id>`), the analysis on a blocking thread,
//!   then the files, then the signed report put on `triax/<building>/event/<id>` with block
//!   congestion control. An event overlapping one already reported (the same event seen again
//!   after a restart) is not reported twice.
//! - **Revisions.** When the first modes window after an event arrives on
//!   `triax/<building>/modes`, the report is revised with the fundamentals after it, their drop
//!   and the frequency limits, and put again with its revision number one higher.
//! - **Queries.** `triax/<building>/events` answers the list of events, newest first;
//!   `triax/<building>/event/<id>` (or a wildcard id) the latest signed report of each event
//!   its key names.

use std::collections::{BTreeMap, HashMap, VecDeque};
use std::future::Future;
use std::path::PathBuf;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use time::OffsetDateTime;
use tokio::sync::mpsc;
use triax_client::history::{fetch, HistoryRequest};
use triax_client::{Fleet, FollowOptions};
use triax_protocol::batch::CorrectedBatch;
use triax_protocol::event::{EventList, EventModes, EventReport, EventSummary, SignedEvent};
use triax_protocol::messages::{BuildingModes, GatewayStatus};
use triax_protocol::record::CalibrationRecord;
use triax_protocol::signing::{sign_event, LabSigningKey};
use triax_protocol::{from_json, to_json, BuildingId, EventId, Key, SensorId};
use triax_strongmotion::event::{analyse, EventSpan};
use zenoh::qos::CongestionControl;

use crate::building::{Building, Pending};
use crate::config::{BuildingConfig, Config};
use crate::files;
use crate::gather::{calibration_from_samples, calibration_of, gather, Gathered};
use crate::html::{page, SeriesPlot, COLUMNS};
use crate::report::{self, fundamentals, ReportContext};
use crate::state::{self, BuildingState, SavedPosition};

/// Messages waiting for the loop.
pub const INBOX_CAPACITY: usize = 4096;
/// Modes windows kept per building (the last four hours of 30-minute windows).
pub const MODES_KEPT: usize = 8;
/// Events a list answers at most, and reports kept in memory per building.
pub const LIST_MAX: usize = 1000;
pub const REPORTS_IN_MEMORY: usize = 64;
/// Reports a wildcard query on event keys answers at most (the newest).
pub const WILDCARD_REPLIES: usize = 16;

/// Why the service could not run.
#[derive(Debug, thiserror::Error)]
pub enum ServiceError {
    #[error(transparent)]
    ZenohConfig(#[from] triax_net::ZenohConfigError),
    #[error("zenoh: {what}: {message}")]
    Zenoh { what: &'static str, message: String },
    #[error(transparent)]
    State(#[from] state::StateError),
    #[error(transparent)]
    SigningKey(#[from] triax_alert::ServiceError),
}

fn zenoh_error(what: &'static str) -> impl FnOnce(zenoh::Error) -> ServiceError {
    move |e| ServiceError::Zenoh {
        what,
        message: e.to_string(),
    }
}

enum Inbound {
    Corrected(BuildingId, CorrectedBatch),
    Modes(BuildingId, Box<BuildingModes>),
}

/// A job for the report worker.
enum Job {
    Report {
        building: BuildingId,
        config: Arc<BuildingConfig>,
        pending: Pending,
        event_id: EventId,
        modes: Vec<BuildingModes>,
    },
    Revise {
        building: BuildingId,
        config: Arc<BuildingConfig>,
        event_id: EventId,
        after: Box<BuildingModes>,
    },
}

/// What the worker did.
struct Done {
    building: BuildingId,
    report: EventReport,
    signed: Vec<u8>,
}

/// What the queryables read: per building its events and its latest reports.
#[derive(Default)]
struct Published {
    events: Vec<EventSummary>,
    reports: VecDeque<(EventId, Vec<u8>)>,
}

type Shared = Arc<Mutex<BTreeMap<BuildingId, Published>>>;

struct Worker {
    session: zenoh::Session,
    signing: LabSigningKey,
    state_dir: Option<PathBuf>,
    network: String,
    records: HashMap<(SensorId, u64), CalibrationRecord>,
    /// Reports by event, for revisions when nothing is kept on disk.
    memory: HashMap<(BuildingId, EventId), (EventReport, Vec<SeriesPlot>)>,
}

/// Runs the service until `shutdown` completes.
pub async fn run(config: Config, shutdown: impl Future<Output = ()>) -> Result<(), ServiceError> {
    let signing = triax_alert::service::signing_key(config.signing_key_file.as_deref())?;
    let public_key_hex = triax_protocol::signing::to_hex(signing.verifying_key().as_bytes());
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
    let shared: Shared = Arc::default();
    let mut buildings: BTreeMap<BuildingId, Building> = BTreeMap::new();
    let mut states: BTreeMap<BuildingId, BuildingState> = BTreeMap::new();
    let mut tasks = Vec::new();
    let mut subscribers = Vec::new();
    for (id, bc) in &config.buildings {
        let st = match &config.state_dir {
            Some(dir) => state::load(dir, id)?,
            None => BuildingState::default(),
        };
        let p = Published {
            events: st.events.clone(),
            ..Published::default()
        };
        shared
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .insert(id.clone(), p);
        let mut options = FollowOptions::new(id.clone());
        options.resume_at = st.positions();
        tracing::info!(building = %id, resume = options.resume_at.len(), reported = st.events.len(), "following corrected streams");
        let mut follower = fleet.follow(options);
        let (tx_f, b) = (tx.clone(), id.clone());
        tasks.push(tokio::spawn(async move {
            while let Some(d) = follower.next().await {
                if tx_f
                    .send(Inbound::Corrected(b.clone(), d.batch))
                    .await
                    .is_err()
                {
                    return;
                }
            }
        }));
        let (tx_m, b) = (tx.clone(), id.clone());
        let sub = session
            .declare_subscriber(Key::Modes(id.clone()).to_string())
            .callback(move |sample| {
                match from_json::<BuildingModes>(&sample.payload().to_bytes()) {
                    Ok(m) => {
                        let _ = tx_m.try_send(Inbound::Modes(b.clone(), Box::new(m)));
                    }
                    Err(e) => tracing::warn!(building = %b, cause = %e, "malformed modes window"),
                }
            })
            .await
            .map_err(zenoh_error("subscribe to the modes"))?;
        subscribers.push(sub);
        buildings.insert(id.clone(), Building::new(id.clone(), Arc::new(bc.clone())));
        states.insert(id.clone(), st);
    }
    drop(tx);
    let list_expr = match &only {
        Some(b) => triax_protocol::keys::all_event_lists(Some(b)),
        None => triax_protocol::keys::all_event_lists(None),
    };
    let event_expr = triax_protocol::keys::all_events(only.as_ref());
    let lists = session
        .declare_queryable(list_expr)
        .await
        .map_err(zenoh_error("declare the events queryable"))?;
    let reports = session
        .declare_queryable(event_expr)
        .await
        .map_err(zenoh_error("declare the event queryable"))?;
    let (job_tx, job_rx) = mpsc::channel::<Job>(256);
    let (done_tx, mut done_rx) = mpsc::unbounded_channel::<Done>();
    let worker = Worker {
        session: session.clone(),
        signing: signing.clone(),
        state_dir: config.state_dir.clone(),
        network: config.network.clone(),
        records: HashMap::new(),
        memory: HashMap::new(),
    };
    tasks.push(tokio::spawn(work(worker, job_rx, done_tx)));
    let mut modes: BTreeMap<BuildingId, VecDeque<BuildingModes>> = BTreeMap::new();
    let mut in_flight: Vec<(BuildingId, i64, i64)> = Vec::new();
    let started = tokio::time::Instant::now();
    let mut tick = tokio::time::interval(Duration::from_millis(250));
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    let mut save_tick = tokio::time::interval(Duration::from_secs(10));
    tokio::pin!(shutdown);
    loop {
        tokio::select! {
            _ = &mut shutdown => break,
            msg = rx.recv() => {
                let Some(msg) = msg else { break };
                let now_s = started.elapsed().as_secs_f64();
                match msg {
                    Inbound::Corrected(b, batch) => {
                        if let Some(building) = buildings.get_mut(&b) {
                            building.on_batch(batch, now_s);
                        }
                    }
                    Inbound::Modes(b, m) => {
                        let Some(bc) = config.buildings.get(&b) else { continue };
                        // A window identified after an event, the first after it: revise.
                        if let Some(st) = states.get_mut(&b) {
                            if m.refused.is_none() {
                                for e in st.events.iter() {
                                    if m.window_start_ns >= e.end_ns && !st.modes_after.contains(&e.event_id)
                                        && !modes.get(&b).is_some_and(|q| q.iter().any(|w| w.window_start_ns >= e.end_ns && w.refused.is_none()))
                                    {
                                        st.modes_after.push(e.event_id.clone());
                                        let _ = job_tx.send(Job::Revise {
                                            building: b.clone(),
                                            config: Arc::new(bc.clone()),
                                            event_id: e.event_id.clone(),
                                            after: m.clone(),
                                        }).await;
                                    }
                                }
                            }
                        }
                        let q = modes.entry(b).or_default();
                        q.retain(|w| w.window_start_ns != m.window_start_ns);
                        q.push_back(*m);
                        while q.len() > MODES_KEPT {
                            q.pop_front();
                        }
                    }
                }
            }
            done = done_rx.recv() => {
                let Some(done) = done else { break };
                in_flight.retain(|(b, s, _)| !(b == &done.building && *s == done.report.start_ns));
                let summary = state::summary(&done.report);
                if let Some(st) = states.get_mut(&done.building) {
                    st.events.retain(|e| e.event_id != summary.event_id);
                    st.events.push(summary.clone());
                    st.events.sort_by_key(|e| e.start_ns);
                    if let (Some(dir), Some(building)) = (&config.state_dir, buildings.get(&done.building)) {
                        save_state(dir, building, st, started.elapsed().as_secs_f64());
                    }
                }
                let mut guard = shared.lock().unwrap_or_else(|e| e.into_inner());
                if let Some(p) = guard.get_mut(&done.building) {
                    p.events.retain(|e| e.event_id != summary.event_id);
                    p.events.push(summary);
                    p.events.sort_by_key(|e| e.start_ns);
                    p.reports.retain(|(id, _)| id != &done.report.event_id);
                    p.reports.push_back((done.report.event_id.clone(), done.signed));
                    while p.reports.len() > REPORTS_IN_MEMORY {
                        p.reports.pop_front();
                    }
                }
            }
            Ok(query) = lists.recv_async() => answer_list(&shared, &query, &public_key_hex).await,
            Ok(query) = reports.recv_async() => answer_reports(&shared, &query, config.state_dir.as_deref()).await,
            _ = save_tick.tick() => {
                if let Some(dir) = &config.state_dir {
                    let now_s = started.elapsed().as_secs_f64();
                    for (id, building) in &buildings {
                        if let Some(st) = states.get_mut(id) {
                            save_state(dir, building, st, now_s);
                        }
                    }
                }
            }
            _ = tick.tick() => {
                let now_s = started.elapsed().as_secs_f64();
                for (id, building) in buildings.iter_mut() {
                    for pending in building.tick(now_s) {
                        let e = &pending.event;
                        let reported = states.get(id).is_some_and(|st| st.events.iter().any(|r| r.start_ns < e.end_ns && e.start_ns < r.end_ns));
                        let queued = in_flight.iter().any(|(b, s, end)| b == id && *s < e.end_ns && e.start_ns < *end);
                        if reported || queued {
                            tracing::info!(building = %id, start_ns = e.start_ns, "event already reported");
                            continue;
                        }
                        in_flight.push((id.clone(), e.start_ns, e.end_ns));
                        tracing::info!(building = %id, start_ns = e.start_ns, end_ns = e.end_ns, sensors = e.sensors.len(), "event closed");
                        let job = Job::Report {
                            building: id.clone(),
                            config: building.config.clone(),
                            event_id: report::event_id(e.start_ns),
                            pending,
                            modes: modes.get(id).map(|q| q.iter().cloned().collect()).unwrap_or_default(),
                        };
                        if job_tx.send(job).await.is_err() {
                            tracing::error!("the report worker stopped");
                        }
                    }
                }
            }
        }
    }
    if let Some(dir) = &config.state_dir {
        let now_s = started.elapsed().as_secs_f64();
        for (id, building) in &buildings {
            if let Some(st) = states.get_mut(id) {
                save_state(dir, building, st, now_s);
            }
        }
    }
    for t in &tasks {
        t.abort();
    }
    drop(subscribers);
    session
        .close()
        .await
        .map_err(zenoh_error("close session"))?;
    tracing::info!("stopped");
    Ok(())
}

fn save_state(dir: &std::path::Path, building: &Building, st: &mut BuildingState, now_s: f64) {
    let positions = building.resume_positions(now_s);
    for (s, p) in positions {
        st.resume.insert(
            s,
            SavedPosition {
                sequence: p.sequence,
                timestamp_ns: p.timestamp_ns,
            },
        );
    }
    if let Err(e) = state::save(dir, &building.id, st) {
        tracing::error!(building = %building.id, cause = %e, "state not written");
    }
}

async fn answer_list(shared: &Shared, query: &zenoh::query::Query, public_key_hex: &str) {
    if !query.parameters().is_empty() {
        let _ = query
            .reply_err(format!(
                "events query: unknown parameter in {:?} (the list takes none)",
                query.parameters().as_str()
            ))
            .await;
        return;
    }
    let wanted = query.key_expr().clone();
    let lists: Vec<(String, EventList)> = {
        let guard = shared.lock().unwrap_or_else(|e| e.into_inner());
        guard
            .iter()
            .filter_map(|(b, p)| {
                let key = Key::Events(b.clone()).to_string();
                let k = zenoh::key_expr::KeyExpr::try_from(key.as_str()).ok()?;
                wanted.intersects(&k).then(|| {
                    let mut events: Vec<EventSummary> =
                        p.events.iter().rev().take(LIST_MAX).cloned().collect();
                    events.sort_by_key(|e| std::cmp::Reverse(e.start_ns));
                    (
                        key.clone(),
                        EventList {
                            format_version: triax_protocol::JSON_FORMAT_VERSION,
                            building: b.clone(),
                            public_key_hex: public_key_hex.to_owned(),
                            reported_at: OffsetDateTime::now_utc(),
                            events,
                        },
                    )
                })
            })
            .collect()
    };
    for (key, list) in lists {
        if let Err(e) = query.reply(&key, to_json(&list)).await {
            tracing::warn!(key = %key, cause = %e, "events reply failed");
        }
    }
}

async fn answer_reports(
    shared: &Shared,
    query: &zenoh::query::Query,
    state_dir: Option<&std::path::Path>,
) {
    if !query.parameters().is_empty() {
        let _ = query
            .reply_err(format!(
                "event query: unknown parameter in {:?} (the query takes none)",
                query.parameters().as_str()
            ))
            .await;
        return;
    }
    let wanted = query.key_expr().clone();
    let replies: Vec<(String, Option<Vec<u8>>, BuildingId, EventId)> = {
        let guard = shared.lock().unwrap_or_else(|e| e.into_inner());
        let mut out = Vec::new();
        for (b, p) in guard.iter() {
            let mut matched = 0;
            for e in p.events.iter().rev() {
                let key = Key::Event(b.clone(), e.event_id.clone()).to_string();
                let Ok(k) = zenoh::key_expr::KeyExpr::try_from(key.as_str()) else {
                    continue;
                };
                if !wanted.intersects(&k) {
                    continue;
                }
                matched += 1;
                if matched > WILDCARD_REPLIES {
                    break;
                }
                let cached = p
                    .reports
                    .iter()
                    .find(|(id, _)| id == &e.event_id)
                    .map(|(_, s)| s.clone());
                out.push((key, cached, b.clone(), e.event_id.clone()));
            }
        }
        out
    };
    for (key, cached, b, id) in replies {
        let body = match cached {
            Some(body) => Some(body),
            None => state_dir.and_then(|d| {
                std::fs::read(state::event_dir(d, &b, &id).join(files::REPORT_JSON)).ok()
            }),
        };
        let Some(body) = body else { continue };
        if let Err(e) = query.reply(&key, body).await {
            tracing::warn!(key = %key, cause = %e, "event reply failed");
        }
    }
}

async fn work(mut w: Worker, mut jobs: mpsc::Receiver<Job>, done: mpsc::UnboundedSender<Done>) {
    while let Some(job) = jobs.recv().await {
        let result = match job {
            Job::Report {
                building,
                config,
                pending,
                event_id,
                modes,
            } => w.report(building, config, pending, event_id, modes).await,
            Job::Revise {
                building,
                config,
                event_id,
                after,
            } => w.revise(building, config, event_id, *after).await,
        };
        match result {
            Ok(d) => {
                if done.send(d).is_err() {
                    return;
                }
            }
            Err(e) => tracing::error!(cause = %e, "report not made"),
        }
    }
}

/// The floors' acceleration for the page: x and y of the building frame, baseline removed, a
/// min and max per column.
fn plots(gathered: &[Gathered], window_s: f64) -> Vec<SeriesPlot> {
    let column_s = window_s / COLUMNS as f64;
    let mut out: Vec<SeriesPlot> = gathered
        .iter()
        .map(|g| {
            let r = &g.record;
            let m = r.mounting;
            let valid: Vec<usize> = (0..r.len()).filter(|&i| r.valid[i]).collect();
            let mean = valid.iter().fold([0.0; 3], |acc, &i| {
                std::array::from_fn(|k| acc[k] + r.accel_mps2[i][k] / valid.len().max(1) as f64)
            });
            let mut x = vec![[f64::INFINITY, f64::NEG_INFINITY]; COLUMNS];
            let mut y = x.clone();
            for &i in &valid {
                let a: [f64; 3] = std::array::from_fn(|k| r.accel_mps2[i][k] - mean[k]);
                let bx = m[0][0] * a[0] + m[0][1] * a[1] + m[0][2] * a[2];
                let by = m[1][0] * a[0] + m[1][1] * a[1] + m[1][2] * a[2];
                let c = ((r.time_s(i) / column_s) as usize).min(COLUMNS - 1);
                x[c] = [x[c][0].min(bx), x[c][1].max(bx)];
                y[c] = [y[c][0].min(by), y[c][1].max(by)];
            }
            for v in x.iter_mut().chain(y.iter_mut()) {
                if !v[0].is_finite() {
                    *v = [0.0, 0.0];
                }
            }
            SeriesPlot {
                sensor_id: r.sensor_id.clone(),
                floor: r.floor,
                start_s: 0.0,
                column_s,
                x,
                y,
            }
        })
        .collect();
    out.sort_by_key(|p| std::cmp::Reverse(p.floor));
    out
}

impl Worker {
    /// The record in force of `sensor` at `version`, from the gateway's status.
    async fn record(
        &mut self,
        building: &BuildingId,
        sensor: &SensorId,
        version: u64,
    ) -> Option<CalibrationRecord> {
        if let Some(r) = self.records.get(&(sensor.clone(), version)) {
            return Some(r.clone());
        }
        let selector = format!("{}?sensor={}", Key::Status(building.clone()), sensor);
        let replies = self
            .session
            .get(&selector)
            .timeout(Duration::from_secs(10))
            .await
            .ok()?;
        while let Ok(reply) = replies.recv_async().await {
            let Ok(sample) = reply.result() else { continue };
            let Ok(status) = from_json::<GatewayStatus>(&sample.payload().to_bytes()) else {
                continue;
            };
            if let Some(rec) = status
                .sensors
                .iter()
                .find(|s| &s.sensor_id == sensor)
                .and_then(|s| s.calibration_record.clone())
            {
                self.records
                    .insert((sensor.clone(), rec.version), (*rec).clone());
                if rec.version == version {
                    return Some(*rec);
                }
            }
        }
        None
    }

    /// The window's batches of every sensor, asked for again (up to three times, a second
    /// apart) while some sensor's kept data end before the window does.
    async fn window(
        &self,
        building: &BuildingId,
        pending: &Pending,
        sensors: &[SensorId],
    ) -> BTreeMap<SensorId, Vec<CorrectedBatch>> {
        let mut by_sensor: BTreeMap<SensorId, Vec<CorrectedBatch>> = BTreeMap::new();
        for attempt in 0..4 {
            by_sensor.clear();
            let request = HistoryRequest {
                building: building.clone(),
                sensors: "*".into(),
                // A batch starting before the window may hold its first samples.
                from_ns: Some(pending.window_start_ns - 60_000_000_000),
                to_ns: Some(pending.window_end_ns),
                from_seq: None,
                to_seq: None,
                calibration: None,
                trusted: None,
            };
            let mut each = |r: triax_client::Recovered| {
                by_sensor
                    .entry(r.batch.header.sensor_id.clone())
                    .or_default()
                    .push(r.batch);
            };
            if let Err(e) = fetch(&self.session, &request, Duration::from_secs(30), &mut each).await
            {
                tracing::warn!(building = %building, cause = %e, "history query for an event failed");
            }
            let short = sensors.iter().any(|s| {
                by_sensor.get(s).is_none_or(|b| {
                    b.iter()
                        .map(|x| {
                            x.header.timestamp_ns
                                + (x.samples.len() as f64 * 1e9 / x.header.sample_rate_hz) as i64
                        })
                        .max()
                        .is_none_or(|end| end < pending.window_end_ns - 1_000_000_000)
                })
            });
            if !short || attempt == 3 {
                break;
            }
            tokio::time::sleep(Duration::from_secs(1)).await;
        }
        by_sensor
    }

    async fn report(
        &mut self,
        building: BuildingId,
        config: Arc<BuildingConfig>,
        pending: Pending,
        event_id: EventId,
        modes: Vec<BuildingModes>,
    ) -> Result<Done, String> {
        let sensors: Vec<SensorId> = config
            .model
            .sensors
            .iter()
            .filter_map(|s| SensorId::new(s.sensor_id.clone()).ok())
            .collect();
        let batches = self.window(&building, &pending, &sensors).await;
        let late = batches
            .values()
            .flatten()
            .any(|b| b.batch_flags & triax_protocol::flags::LATE != 0);
        let mut caveats = Vec::new();
        let mut gathered = Vec::new();
        let mut records_used = Vec::new();
        for (placement, id) in config.model.sensors.iter().zip(&sensors) {
            let list = batches.get(id).map(Vec::as_slice).unwrap_or(&[]);
            let Some(mut g) = gather(
                placement,
                list,
                pending.window_start_ns,
                pending.window_end_ns,
                config.alignment_tolerance,
            ) else {
                caveats.push(format!("sensor {id}: no data in the window; left out"));
                continue;
            };
            let version = g.calibration_versions.first().copied().unwrap_or(0);
            let mode = g
                .modes
                .first()
                .copied()
                .unwrap_or(triax_protocol::batch::Mode::Dynamic);
            if g.calibration_versions.len() > 1 {
                caveats.push(format!(
                    "sensor {id}: corrected with versions {:?} in the window; the first one's uncertainty is used",
                    g.calibration_versions
                ));
            }
            match self.record(&building, id, version).await {
                Some(rec) => {
                    g.record.calibration = calibration_of(&rec, mode);
                    records_used.push(rec);
                }
                None => {
                    g.record.calibration = calibration_from_samples(list);
                    caveats.push(format!(
                        "sensor {id}: calibration record version {version} not available from the gateway: its \
                         samples' own uncertainty is taken as noise, and no calibration part is counted"
                    ));
                }
            }
            if g.missing + g.misaligned + g.unusable > 0 {
                caveats.push(format!(
                    "sensor {id}: {} grid points missing, {} samples off the grid, {} unusable (flagged uncalibrated, non-finite or clipped)",
                    g.missing, g.misaligned, g.unusable
                ));
            }
            if g.caveat_flags != 0 {
                caveats.push(format!(
                    "sensor {id}: samples flagged {}: its decisions go no further than possible",
                    triax_protocol::flags::names(g.caveat_flags).join(", ")
                ));
            }
            gathered.push(g);
        }
        if gathered.is_empty() {
            return Err(format!(
                "building {building}: event {event_id}: no sensor has data in the window"
            ));
        }
        // The modes window before: the last one wholly before the event.
        let before = modes
            .iter()
            .filter(|w| w.window_end_ns <= pending.event.start_ns && w.refused.is_none())
            .max_by_key(|w| w.window_start_ns);
        let after = modes
            .iter()
            .filter(|w| w.window_start_ns >= pending.event.end_ns && w.refused.is_none())
            .min_by_key(|w| w.window_start_ns);
        let mut event_modes = EventModes {
            before: before.map(fundamentals).unwrap_or_default(),
            ..EventModes::default()
        };
        if let Some(a) = after {
            event_modes.after = fundamentals(a);
            event_modes.drops = report::drops(&event_modes.before, &event_modes.after);
        }
        let mut fundamental_hz = config.fundamental_hz;
        for (k, d) in [
            triax_protocol::messages::ModalDirection::X,
            triax_protocol::messages::ModalDirection::Y,
        ]
        .iter()
        .enumerate()
        {
            if fundamental_hz[k].is_none() {
                fundamental_hz[k] = event_modes
                    .before
                    .iter()
                    .find(|m| m.direction == *d)
                    .map(|m| m.frequency_hz.value);
            }
        }
        let span = EventSpan {
            start_s: (pending.event.start_ns - pending.window_start_ns) as f64 * 1e-9,
            end_s: (pending.event.end_ns - pending.window_start_ns) as f64 * 1e-9,
        };
        let records: Vec<_> = gathered.iter().map(|g| g.record.clone()).collect();
        let processing = config.processing.clone();
        let seed = pending.event.start_ns as u64;
        let analysis = tokio::task::spawn_blocking(move || {
            analyse(&records, span, fundamental_hz, &processing, seed)
        })
        .await
        .map_err(|e| format!("the analysis panicked: {e}"))?
        .map_err(|e| e.to_string())?;
        let window_s = (pending.window_end_ns - pending.window_start_ns) as f64 * 1e-9;
        let series = plots(&gathered, window_s);
        let mut names = vec![
            files::REPORT_HTML.to_owned(),
            files::PARAMETERS_CSV.to_owned(),
            files::PARAMETERS_PARQUET.to_owned(),
        ];
        if self.state_dir.is_some() {
            names.extend([files::SDS_DIR.to_owned(), files::STATIONXML.to_owned()]);
        } else {
            names.clear();
        }
        let r = report::build(
            &analysis,
            ReportContext {
                building: &building,
                config: &config,
                pending: &pending,
                event_id: event_id.clone(),
                gathered: &gathered,
                sensor_ids: &sensors,
                modes: event_modes,
                caveats,
                files: names,
                late,
                now: OffsetDateTime::now_utc(),
            },
        );
        if let Some(root) = &self.state_dir {
            let dir = state::event_dir(root, &building, &event_id);
            self.write_data(&building, &dir, &batches, &records_used)?;
        }
        let d = self.publish(&building, r, series).await?;
        tracing::warn!(building = %building, event = %event_id, tag = ?d.report.tag, drivers = ?d.report.drivers, "event reported");
        Ok(d)
    }

    /// The window's data as miniSEED and StationXML.
    fn write_data(
        &self,
        building: &BuildingId,
        dir: &std::path::Path,
        batches: &BTreeMap<SensorId, Vec<CorrectedBatch>>,
        records: &[CalibrationRecord],
    ) -> Result<(), String> {
        let sds = dir.join(files::SDS_DIR);
        std::fs::create_dir_all(&sds).map_err(|e| format!("{}: {e}", sds.display()))?;
        let mut writer = triax_client::mseed::SdsWriter::new(&sds, &self.network, BTreeMap::new())
            .map_err(|e| e.to_string())?;
        let mut rates = BTreeMap::new();
        for (sensor, list) in batches {
            let mut list: Vec<&CorrectedBatch> = list.iter().collect();
            list.sort_by_key(|b| b.header.timestamp_ns);
            for b in list {
                rates.insert(sensor.clone(), b.header.sample_rate_hz);
                writer.push(b).map_err(|e| e.to_string())?;
            }
        }
        let staged = writer.stage().map_err(|e| e.to_string())?;
        let xml = triax_client::stationxml::stationxml(
            &self.network,
            building,
            staged.stations(),
            &rates,
            staged.runs(),
            records,
            OffsetDateTime::now_utc(),
        );
        staged.commit().map_err(|e| e.to_string())?;
        match xml {
            Ok(xml) => files::write_whole(&dir.join(files::STATIONXML), xml.as_bytes())
                .map_err(|e| e.to_string())?,
            Err(e) => tracing::warn!(cause = %e, "no StationXML: a record is missing"),
        }
        Ok(())
    }

    /// Signs, writes the report's files and puts it.
    async fn publish(
        &mut self,
        building: &BuildingId,
        r: EventReport,
        series: Vec<SeriesPlot>,
    ) -> Result<Done, String> {
        let signed: SignedEvent = sign_event(&r, &self.signing);
        let signed_bytes = to_json(&signed);
        if let Some(root) = &self.state_dir {
            let dir = state::event_dir(root, building, &r.event_id);
            let rows = files::rows(&r);
            let write = |name: &str, bytes: &[u8]| {
                files::write_whole(&dir.join(name), bytes)
                    .map_err(|e| format!("{}: {e}", dir.join(name).display()))
            };
            write(
                files::PLOT_JSON,
                &serde_json::to_vec(&series).map_err(|e| e.to_string())?,
            )?;
            write(files::REPORT_HTML, page(&r, &series).as_bytes())?;
            write(files::PARAMETERS_CSV, files::csv(&r, &rows).as_bytes())?;
            write(
                files::PARAMETERS_PARQUET,
                &files::parquet(&r, &rows).map_err(|e| e.to_string())?,
            )?;
            // Kept before it is published: whoever hears it can read it back.
            write(files::REPORT_JSON, &signed_bytes)?;
        } else {
            self.memory
                .insert((building.clone(), r.event_id.clone()), (r.clone(), series));
        }
        let key = Key::Event(building.clone(), r.event_id.clone()).to_string();
        let put = self
            .session
            .put(&key, signed_bytes.clone())
            .congestion_control(CongestionControl::Block);
        if let Err(e) = put.await {
            tracing::error!(key = %key, cause = %e, "event not published");
        }
        Ok(Done {
            building: building.clone(),
            report: r,
            signed: signed_bytes,
        })
    }

    async fn revise(
        &mut self,
        building: BuildingId,
        config: Arc<BuildingConfig>,
        event_id: EventId,
        after: BuildingModes,
    ) -> Result<Done, String> {
        let (old, series) = match &self.state_dir {
            Some(root) => {
                let dir = state::event_dir(root, &building, &event_id);
                let signed = std::fs::read(dir.join(files::REPORT_JSON))
                    .map_err(|e| format!("{}: {e}", dir.display()))?;
                let signed: SignedEvent = from_json(&signed).map_err(|e| e.to_string())?;
                let report: EventReport =
                    from_json(signed.event_json.as_bytes()).map_err(|e| e.to_string())?;
                let series: Vec<SeriesPlot> = std::fs::read(dir.join(files::PLOT_JSON))
                    .ok()
                    .and_then(|b| serde_json::from_slice(&b).ok())
                    .unwrap_or_default();
                (report, series)
            }
            None => self
                .memory
                .get(&(building.clone(), event_id.clone()))
                .cloned()
                .ok_or_else(|| format!("event {event_id}: no report to revise"))?,
        };
        if !old.modes.after.is_empty() {
            return Err(format!("event {event_id}: already has its modes after"));
        }
        let r = report::with_modes_after(&old, &after, &config, OffsetDateTime::now_utc());
        tracing::info!(building = %building, event = %event_id, revision = r.revision, "report revised with the modes after");
        self.publish(&building, r, series).await
    }
}
