//! What the console knows of the fleet: the buildings and their gateways (heartbeats, status
//! answers), each sensor's last status, and the latest alerts; and the Zenoh side that keeps it
//! current (subscriptions to heartbeats and alerts, a status poll).
//!
//! The console only reads: it subscribes and queries, and never puts. Everything it keeps is
//! bounded: buildings ([`MAX_BUILDINGS`]), alerts ([`MAX_ALERTS`]), the sensors listed per
//! building (one status page, at most 5000 sensors), and per building a few checkpoints of the
//! sensors' counters, from which the share of flagged samples over the last minute is taken
//! ([`FLAGGED_SPAN`]).

use std::collections::{BTreeMap, VecDeque};
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::{Duration, Instant};

use serde::Serialize;
use time::OffsetDateTime;
use triax_protocol::batch::Mode;
use triax_protocol::keys::{self, Stream};
use triax_protocol::messages::{
    Alert, AlertKind, AlertLevel, GatewayStatus, HealthVerdict, Heartbeat, HistoryStatus,
    SensorStatus,
};
use triax_protocol::signing::{read_alert, AlertTrust, TrustedKeys};
use triax_protocol::{from_json, BuildingId, Key, SensorId};
use zenoh::query::ConsolidationMode;

use crate::alertlog::{self, AlertLog};
use crate::provenance::{Provenance, ProvenanceView};

/// Most buildings tracked; further ids heard are counted and ignored.
pub const MAX_BUILDINGS: usize = 1000;
/// Alerts kept, newest first.
pub const MAX_ALERTS: usize = 1000;
/// Alerts in each fleet snapshot (the rest at `/api/alerts`).
pub const ALERTS_IN_SNAPSHOT: usize = 100;
/// Sensors per status page asked for (the gateway's own cap).
pub const STATUS_PAGE: usize = 5000;
/// A gateway is up while its last heartbeat is younger than this (heartbeats are 1 s apart).
pub const HEARTBEAT_FRESH: Duration = Duration::from_secs(3);
/// A sensor whose last batch is older than this, by its gateway's clock, is silent.
pub const SILENT_AFTER: Duration = Duration::from_secs(10);
/// A calibrated sensor is `flagged` when more than this share of its samples over the recent
/// span carry a quality flag. Below it, a sensor that loses one batch in ten (each batch after
/// a gap is flagged whole) still reads `gaps`, not `flagged`.
pub const FLAGGED_ABOVE: f64 = 0.2;
/// The recent span over which the flagged share is taken, by the gateway's clock: from the
/// newest checkpoint at least this old to the latest status answer.
pub const FLAGGED_SPAN: Duration = Duration::from_secs(60);
/// Time between checkpoints of the counters: the span is [`FLAGGED_SPAN`] plus at most this
/// (and one status interval), with no more than six checkpoints kept per building.
pub const CHECKPOINT_EVERY: Duration = Duration::from_secs(15);

/// How the fleet is watched.
#[derive(Debug, Clone)]
pub struct FleetOptions {
    /// Buildings to watch; empty: every building heard of (heartbeats, status answers, alerts).
    pub buildings: Vec<BuildingId>,
    /// Time between status polls.
    pub status_interval: Duration,
    /// Warn this long before a calibration's `valid_until`.
    pub expiry_warning: Duration,
    /// The alerting services' public keys: only an alert signed by one of them is a verdict.
    pub trusted_alert_keys: TrustedKeys,
    /// What is checked of the gateways' heartbeats and status answers.
    pub provenance: Arc<Provenance>,
}

/// What the console holds of one alert.
#[derive(Debug, Clone, Serialize)]
pub struct AlertEntry {
    /// The console's own number for it, kept across restarts by the alert log.
    pub id: u64,
    #[serde(flatten)]
    pub alert: Alert,
    #[serde(with = "time::serde::rfc3339")]
    pub received_at: OffsetDateTime,
    /// `verified` (signed by a trusted alerting key: a verdict), `unknown_key`,
    /// `bad_signature` or `unsigned` (PROTOCOL.md §3.6): shown, never as a verdict.
    pub trust: &'static str,
    /// The key that signed it, when signed.
    pub signed_by: Option<String>,
}

impl AlertEntry {
    pub fn verified(&self) -> bool {
        self.trust == "verified"
    }
}

#[derive(Debug, Default)]
struct BuildingState {
    gateway: Option<String>,
    heartbeat: Option<(Instant, Heartbeat)>,
    status: Option<(Instant, GatewayStatus)>,
    status_error: Option<String>,
    latest_alerts: BTreeMap<SensorId, SensorAlerts>,
    counters: CounterHistory,
    /// Per sensor, the flagged share as of the latest status answer.
    flagged: BTreeMap<SensorId, FlaggedShare>,
}

/// The share of a sensor's samples that carry a quality flag over a span.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct FlaggedShare {
    /// `flagged / samples`, from 0 to 1.
    pub share: f64,
    pub samples: u64,
    pub flagged: u64,
    /// Length of the span by the gateway's clock; none: since the gateway started (until the
    /// console has heard the gateway for [`FLAGGED_SPAN`]).
    pub span_s: Option<f64>,
}

impl FlaggedShare {
    /// The share of `flagged` among `samples`; none without samples.
    pub fn of(samples: u64, flagged: u64, span_s: Option<f64>) -> Option<FlaggedShare> {
        (samples > 0).then(|| FlaggedShare {
            share: flagged.min(samples) as f64 / samples as f64,
            samples,
            flagged,
            span_s,
        })
    }
}

/// The sensors' sample counters at one status answer.
#[derive(Debug)]
struct Checkpoint {
    reported_at: OffsetDateTime,
    /// Per sensor, `(samples, flagged_samples)`.
    counts: BTreeMap<SensorId, (u64, u64)>,
}

/// Checkpoints of one gateway's counters, oldest first: the front is the newest one at least
/// [`FLAGGED_SPAN`] older than the latest answer, once there is one.
#[derive(Debug, Default)]
struct CounterHistory {
    started_at: Option<OffsetDateTime>,
    checkpoints: VecDeque<Checkpoint>,
}

impl CounterHistory {
    /// Each sensor's flagged share over the recent span as of `status`, which is then kept as
    /// a checkpoint if the last one is [`CHECKPOINT_EVERY`] old.
    fn update(&mut self, status: &GatewayStatus) -> BTreeMap<SensorId, FlaggedShare> {
        let now = status.reported_at;
        let restarted = self.started_at != Some(status.started_at);
        let clock_back = self.checkpoints.back().is_some_and(|c| c.reported_at > now);
        if restarted || clock_back {
            // Counters start again at zero, or the gateway's clock no longer orders them.
            self.checkpoints.clear();
            self.started_at = Some(status.started_at);
        }
        let span = time::Duration::try_from(FLAGGED_SPAN).unwrap_or(time::Duration::MINUTE);
        while self.checkpoints.len() >= 2 && self.checkpoints[1].reported_at <= now - span {
            self.checkpoints.pop_front();
        }
        // Until a checkpoint is the span old, the counts since the gateway started: a shorter
        // span would judge a sensor on a handful of batches.
        let base = self
            .checkpoints
            .front()
            .filter(|c| c.reported_at <= now - span);
        let shares = status
            .sensors
            .iter()
            .filter_map(|s| {
                let since = base.and_then(|b| {
                    let &(samples, flagged) = b.counts.get(&s.sensor_id)?;
                    // A counter that went back belongs to another run: fall back to it whole.
                    (samples <= s.samples && flagged <= s.flagged_samples).then_some((
                        samples,
                        flagged,
                        (now - b.reported_at).as_seconds_f64(),
                    ))
                });
                let share = match since {
                    Some((samples, flagged, span_s)) => FlaggedShare::of(
                        s.samples - samples,
                        s.flagged_samples - flagged,
                        Some(span_s),
                    ),
                    None => FlaggedShare::of(s.samples, s.flagged_samples, None),
                };
                Some((s.sensor_id.clone(), share?))
            })
            .collect();
        let every = time::Duration::try_from(CHECKPOINT_EVERY).unwrap_or(time::Duration::MINUTE);
        if self
            .checkpoints
            .back()
            .is_none_or(|c| c.reported_at <= now - every)
        {
            self.checkpoints.push_back(Checkpoint {
                reported_at: now,
                counts: status
                    .sensors
                    .iter()
                    .map(|s| (s.sensor_id.clone(), (s.samples, s.flagged_samples)))
                    .collect(),
            });
        }
        shares
    }
}

/// A sensor's latest verdict, and the latest claim no trusted key vouches for when it came
/// after: a claim is shown beside the verdict, never instead of it.
#[derive(Debug, Default, Clone)]
pub struct SensorAlerts {
    pub verified: Option<AlertEntry>,
    pub unverified: Option<AlertEntry>,
}

impl SensorAlerts {
    fn received_at(&self) -> Option<OffsetDateTime> {
        [&self.verified, &self.unverified]
            .into_iter()
            .flatten()
            .map(|e| e.received_at)
            .max()
    }

    /// The verdict, else the claim.
    fn shown(&self) -> Option<&AlertEntry> {
        self.verified.as_ref().or(self.unverified.as_ref())
    }

    /// The claim, when it is newer than the verdict (or there is none).
    fn claim(&self) -> Option<&AlertEntry> {
        match (&self.verified, &self.unverified) {
            (Some(v), Some(u)) if u.id > v.id => Some(u),
            (None, u) => u.as_ref(),
            _ => None,
        }
    }
}

/// What makes two verified alerts the same verdict: a replay of a signed alert verifies again,
/// and is one alert, not two.
#[derive(Debug, Clone, PartialEq, Eq, Hash)]
struct Verdict {
    building: BuildingId,
    sensor: SensorId,
    kind: AlertKind,
    level: AlertLevel,
    at_ns: i128,
    window_ns: (Option<i64>, Option<i64>),
    value_bits: u64,
}

impl Verdict {
    fn of(a: &Alert) -> Verdict {
        Verdict {
            building: a.building.clone(),
            sensor: a.sensor_id.clone(),
            kind: a.kind,
            level: a.level,
            at_ns: a.at.unix_timestamp_nanos(),
            window_ns: (a.window_start_ns, a.window_end_ns),
            value_bits: a.value.to_bits(),
        }
    }
}

/// Verified verdicts remembered to recognise their replays: more than the alert log keeps.
pub const VERDICTS_REMEMBERED: usize = 2 * alertlog::DEFAULT_MAX_ALERTS;

/// Verdicts seen, oldest first out.
#[derive(Debug, Default)]
struct Seen {
    set: std::collections::HashSet<Verdict>,
    order: VecDeque<Verdict>,
}

impl Seen {
    /// False when `v` was seen before.
    fn insert(&mut self, v: Verdict) -> bool {
        if !self.set.insert(v.clone()) {
            return false;
        }
        self.order.push_back(v);
        while self.order.len() > VERDICTS_REMEMBERED {
            if let Some(old) = self.order.pop_front() {
                self.set.remove(&old);
            }
        }
        true
    }
}

#[derive(Debug, Default)]
struct State {
    buildings: BTreeMap<BuildingId, BuildingState>,
    alerts: VecDeque<AlertEntry>,
    alerts_total: u64,
    /// Verified alerts received again (replays), neither logged nor counted as new.
    repeated_alerts: u64,
    verdicts: Seen,
    malformed_messages: u64,
    ignored_buildings: u64,
    log: Option<AlertLog>,
    /// Alerts read back from the alert log on start.
    alerts_restored: u64,
}

/// The fleet as the console sees it. Zenoh callbacks write it; page requests read snapshots.
pub struct Fleet {
    options: FleetOptions,
    state: Mutex<State>,
    /// Where verified alerts worth telling go, once notifications run.
    notifier: std::sync::OnceLock<crate::notify::Notifier>,
}

impl Fleet {
    /// A fleet whose alerts are kept in memory only.
    pub fn new(options: FleetOptions) -> Fleet {
        Fleet::with_alert_log(
            options,
            AlertLog::in_memory(alertlog::DEFAULT_MAX_ALERTS, alertlog::DEFAULT_RETENTION),
        )
    }

    /// A fleet that keeps its alerts in `log`, and starts with the alerts it holds, each
    /// verified again against this fleet's trusted keys.
    pub fn with_alert_log(options: FleetOptions, mut log: AlertLog) -> Fleet {
        let mut state = State::default();
        for b in &options.buildings {
            state.buildings.insert(b.clone(), BuildingState::default());
        }
        let fleet = Fleet {
            options,
            state: Mutex::new(state),
            notifier: std::sync::OnceLock::new(),
        };
        for p in log.take_pending() {
            match fleet.decode_alert(&p.key, p.payload.as_bytes(), p.received_at) {
                Ok(mut entry) => {
                    entry.id = p.id;
                    let mut st = fleet.lock();
                    if entry.verified() {
                        st.verdicts.insert(Verdict::of(&entry.alert));
                    }
                    if fleet
                        .building(&mut st, &entry.alert.building.clone())
                        .is_some()
                    {
                        fleet.keep_alert(&mut st, entry.clone(), false);
                        drop(st);
                        log.restore(p, entry);
                    }
                }
                Err(why) => {
                    tracing::warn!(id = p.id, key = p.key, why, "logged alert not restored")
                }
            }
        }
        log.restored();
        fleet.lock().log = Some(log);
        fleet
    }

    fn lock(&self) -> MutexGuard<'_, State> {
        // Updates are field writes that cannot panic halfway.
        self.state.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// The building's entry, if it is watched (or may be discovered) and there is room.
    fn building<'a>(&self, s: &'a mut State, b: &BuildingId) -> Option<&'a mut BuildingState> {
        if !s.buildings.contains_key(b) {
            if !self.options.buildings.is_empty() {
                return None;
            }
            if s.buildings.len() >= MAX_BUILDINGS {
                s.ignored_buildings += 1;
                return None;
            }
            s.buildings.insert(b.clone(), BuildingState::default());
        }
        s.buildings.get_mut(b)
    }

    /// A payload that did not decode, or whose key and content disagree.
    pub fn malformed(&self, key: &str, why: &str) {
        tracing::debug!(key, why, "message skipped");
        self.lock().malformed_messages += 1;
    }

    /// A heartbeat put on `key`, with the attachment that signs it.
    pub fn heartbeat(&self, key: &str, payload: &[u8], attachment: Option<&[u8]>) {
        if !self.options.provenance.put(key, payload, attachment) {
            return;
        }
        let hb = match (Key::parse(key), from_json::<Heartbeat>(payload)) {
            (Ok(Key::Heartbeat(b)), Ok(hb)) if hb.building == b => hb,
            (_, Err(e)) => return self.malformed(key, &e.to_string()),
            _ => return self.malformed(key, "key and heartbeat disagree"),
        };
        let mut s = self.lock();
        if let Some(st) = self.building(&mut s, &hb.building.clone()) {
            st.gateway = Some(hb.gateway.clone());
            st.heartbeat = Some((Instant::now(), hb));
        }
    }

    pub fn status(&self, status: GatewayStatus) {
        let mut s = self.lock();
        if let Some(st) = self.building(&mut s, &status.building.clone()) {
            st.gateway = Some(status.gateway.clone());
            st.status_error = None;
            st.flagged = st.counters.update(&status);
            st.status = Some((Instant::now(), status));
        }
    }

    pub fn status_error(&self, building: &BuildingId, message: String) {
        let mut s = self.lock();
        if let Some(st) = self.building(&mut s, building) {
            st.status_error = Some(message);
        }
    }

    fn decode_alert(
        &self,
        key: &str,
        payload: &[u8],
        received_at: OffsetDateTime,
    ) -> Result<AlertEntry, String> {
        let read = read_alert(payload, &self.options.trusted_alert_keys);
        let (alert, trust) = match (Key::parse(key), read) {
            (Ok(Key::Alert(b, s)), Ok((a, t))) if a.building == b && a.sensor_id == s => (a, t),
            (_, Err(e)) => return Err(e.to_string()),
            _ => return Err("key and alert disagree".into()),
        };
        let signed_by = match &trust {
            AlertTrust::Verified { public_key_hex }
            | AlertTrust::UnknownKey { public_key_hex }
            | AlertTrust::BadSignature { public_key_hex } => Some(public_key_hex.clone()),
            AlertTrust::Unsigned => None,
        };
        Ok(AlertEntry {
            id: 0,
            alert,
            received_at,
            trust: trust.name(),
            signed_by,
        })
    }

    pub fn alert(&self, key: &str, payload: &[u8]) {
        let mut entry = match self.decode_alert(key, payload, OffsetDateTime::now_utc()) {
            Ok(e) => e,
            Err(why) => return self.malformed(key, &why),
        };
        let mut s = self.lock();
        if self
            .building(&mut s, &entry.alert.building.clone())
            .is_none()
        {
            return;
        }
        if entry.verified() && !s.verdicts.insert(Verdict::of(&entry.alert)) {
            s.repeated_alerts += 1;
            return;
        }
        let silenced = match &mut s.log {
            Some(log) => log.record(key, payload, &mut entry),
            None => None,
        };
        let notice = (silenced.is_none() && entry.verified())
            .then(|| alert_notice(&entry))
            .flatten();
        self.keep_alert(&mut s, entry, true);
        drop(s);
        if let (Some(n), Some(notifier)) = (notice, self.notifier.get()) {
            notifier.put(n);
        }
    }

    /// Notifications from now on go to `notifier` (set once).
    pub fn notify_to(&self, notifier: crate::notify::Notifier) {
        let _ = self.notifier.set(notifier);
    }

    /// Puts an alert of a watched building in the fleet's view.
    fn keep_alert(&self, s: &mut State, entry: AlertEntry, new: bool) {
        let Some(st) = self.building(s, &entry.alert.building.clone()) else {
            return;
        };
        // Bounded by the sensors that alerted, themselves bounded by the ids' alphabet only:
        // keep the map no larger than the alert log.
        if st.latest_alerts.len() >= MAX_ALERTS
            && !st.latest_alerts.contains_key(&entry.alert.sensor_id)
        {
            if let Some(oldest) = st
                .latest_alerts
                .iter()
                .min_by_key(|(_, e)| e.received_at())
                .map(|(k, _)| k.clone())
            {
                st.latest_alerts.remove(&oldest);
            }
        }
        let latest = st
            .latest_alerts
            .entry(entry.alert.sensor_id.clone())
            .or_default();
        match entry.verified() {
            true => latest.verified = Some(entry.clone()),
            false => latest.unverified = Some(entry.clone()),
        }
        s.alerts.push_front(entry);
        // Past the bound, claims go first: a flood of unverified alerts never pushes a verdict
        // out.
        while s.alerts.len() > MAX_ALERTS {
            match s.alerts.iter().rposition(|a| !a.verified()) {
                Some(i) => {
                    s.alerts.remove(i);
                }
                None => {
                    s.alerts.pop_back();
                }
            }
        }
        if new {
            s.alerts_total += 1;
        } else {
            s.alerts_restored += 1;
        }
    }

    /// Runs `f` on the alert log.
    pub fn with_log<T>(&self, f: impl FnOnce(&mut AlertLog) -> T) -> T {
        let mut s = self.lock();
        // Only missing while `with_alert_log` builds the fleet, which calls nothing here.
        let log = s.log.get_or_insert_with(|| {
            AlertLog::in_memory(alertlog::DEFAULT_MAX_ALERTS, alertlog::DEFAULT_RETENTION)
        });
        f(log)
    }

    /// Buildings whose status is polled one by one (the watched list), or none to poll with a
    /// wildcard.
    pub fn configured_buildings(&self) -> &[BuildingId] {
        &self.options.buildings
    }

    /// What the console checks of the gateways' messages.
    pub fn provenance(&self) -> &Arc<Provenance> {
        &self.options.provenance
    }

    /// The latest alerts held for the fleet view (at most [`MAX_ALERTS`]), newest first.
    pub fn alerts(&self) -> Vec<AlertEntry> {
        self.lock().alerts.iter().cloned().collect()
    }

    /// One building's view with every sensor's counters (`/api/fleet?building=`), or only
    /// `sensor`'s row; none if the building is not tracked.
    pub fn building_snapshot(
        &self,
        b: &BuildingId,
        sensor: Option<&SensorId>,
    ) -> Option<BuildingView> {
        let now = Instant::now();
        let wall = OffsetDateTime::now_utc();
        let s = self.lock();
        let st = s.buildings.get(b)?;
        let mut v = self.building_view(b, st, now, wall);
        if let Some(id) = sensor {
            v.sensors.retain(|x| &x.sensor_id == id);
        }
        Some(v)
    }

    /// The fleet event's form of the fleet: what changes seldom (states, calibration, the
    /// latest alert), none of the counters that move with every status answer.
    pub fn brief(&self) -> Brief {
        let snap = self.snapshot_with(ALERTS_IN_SNAPSHOT);
        Brief::of(&snap)
    }

    /// What the fleet view shows, now.
    pub fn snapshot(&self) -> Snapshot {
        self.snapshot_with(ALERTS_IN_SNAPSHOT)
    }

    fn snapshot_with(&self, alerts: usize) -> Snapshot {
        let now = Instant::now();
        let wall = OffsetDateTime::now_utc();
        let s = self.lock();
        let buildings = s
            .buildings
            .iter()
            .map(|(id, b)| self.building_view(id, b, now, wall))
            .collect();
        Snapshot {
            now: wall,
            buildings,
            alerts: s.alerts.iter().take(alerts).cloned().collect(),
            alerts_total: s.alerts_total,
            alerts_restored: s.alerts_restored,
            alerts_open: s.log.as_ref().map_or(0, |l| l.open_count()),
            malformed_messages: s.malformed_messages,
            repeated_alerts: s.repeated_alerts,
            ignored_buildings: s.ignored_buildings,
            provenance: self.options.provenance.view(),
            expiry_warning_days: self.options.expiry_warning.as_secs_f64() / 86_400.0,
        }
    }

    fn building_view(
        &self,
        id: &BuildingId,
        b: &BuildingState,
        now: Instant,
        wall: OffsetDateTime,
    ) -> BuildingView {
        let heartbeat_age = b.heartbeat.as_ref().map(|(t, _)| now - *t);
        let status_age = b.status.as_ref().map(|(t, _)| now - *t);
        let state = self.state_of(b, now);
        let last_heard = [heartbeat_age, status_age].into_iter().flatten().min();
        let status = b.status.as_ref().map(|(_, s)| s);
        let mut sensors: Vec<SensorView> = status
            .map(|st| {
                st.sensors
                    .iter()
                    .map(|s| {
                        sensor_view(
                            s,
                            st.reported_at,
                            status_age.unwrap_or_default(),
                            wall,
                            self.options.expiry_warning,
                            b.latest_alerts
                                .get(&s.sensor_id)
                                .cloned()
                                .unwrap_or_default(),
                            b.flagged.get(&s.sensor_id).copied(),
                        )
                    })
                    .collect()
            })
            .unwrap_or_default();
        // Sensors that alerted but are not in the status (yet): still shown.
        for (sid, a) in &b.latest_alerts {
            if !sensors.iter().any(|s| &s.sensor_id == sid) {
                sensors.push(SensorView::alert_only(sid.clone(), a));
            }
        }
        sensors.sort_by(|a, b| a.sensor_id.cmp(&b.sensor_id));
        // Each sensor's states are sorted worst first.
        let worst_state = sensors
            .iter()
            .filter_map(|s| s.states.first())
            .min()
            .copied();
        BuildingView {
            building: id.clone(),
            gateway: b.gateway.clone(),
            state,
            last_heard_s: last_heard.map(|d| d.as_secs_f64()),
            heartbeat_sequence: b.heartbeat.as_ref().map(|(_, h)| h.sequence),
            status_error: b.status_error.clone(),
            started_at: status.map(|s| s.started_at),
            reported_at: status.map(|s| s.reported_at),
            malformed: status.map(|s| s.malformed),
            dropped: status.map(|s| s.dropped),
            history: status.and_then(|s| s.history.clone()),
            total_sensors: status.map(|s| s.total_sensors),
            worst_state,
            sensors,
        }
    }

    fn state_of(&self, b: &BuildingState, now: Instant) -> GatewayState {
        let heartbeat_age = b.heartbeat.as_ref().map(|(t, _)| now - *t);
        let status_age = b.status.as_ref().map(|(t, _)| now - *t);
        // Without heartbeats (an older gateway), a status answer within two polls will do.
        let status_fresh = 2 * self.options.status_interval + Duration::from_secs(1);
        match (heartbeat_age, status_age) {
            (Some(h), _) if h <= HEARTBEAT_FRESH => GatewayState::Up,
            (None, Some(s)) if s <= status_fresh => GatewayState::Up,
            (None, None) => GatewayState::Unknown,
            _ => GatewayState::Down,
        }
    }

    /// Whether the building's gateway is heard now.
    pub fn gateway_state(&self, b: &BuildingId) -> GatewayState {
        let s = self.lock();
        s.buildings.get(b).map_or(GatewayState::Unknown, |st| {
            self.state_of(st, Instant::now())
        })
    }
}

/// The notice a verified alert makes, if its level is one that is told (`exceeded`, `stale`).
fn alert_notice(e: &AlertEntry) -> Option<crate::notify::Notice> {
    use crate::notify::{Event, Notice};
    let a = &e.alert;
    let event = match a.level {
        AlertLevel::Exceeded => Event::Exceeded,
        AlertLevel::Stale => Event::Stale,
        AlertLevel::Possible => return None,
    };
    let kind = serde_json::to_value(a.kind)
        .ok()
        .and_then(|v| v.as_str().map(str::to_owned))
        .unwrap_or_default();
    let summary = match event {
        Event::Stale => format!("{kind}: stale, no data to judge (verified alert)"),
        _ => format!(
            "{kind} {:.4} ± {:.4} {} (k = {}) against the threshold {:.4}: {} (verified alert)",
            a.value,
            a.coverage_factor * a.standard_uncertainty,
            a.unit,
            a.coverage_factor,
            a.threshold,
            event.name()
        ),
    };
    Some(Notice {
        event,
        building: a.building.clone(),
        sensor: a.sensor_id.clone(),
        alert_id: Some(e.id),
        summary,
        statement: Some(a.statement.clone()),
        at_ns: i64::try_from(e.received_at.unix_timestamp_nanos()).unwrap_or(i64::MAX),
    })
}

/// Up: heard within the limits; down: heard before, not lately; unknown: never heard.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum GatewayState {
    Up,
    Down,
    Unknown,
}

/// Conditions an operator should see on a sensor, worst first in the page.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum SensorState {
    /// An alert at level `exceeded`.
    Exceeded,
    /// The latest alert on the sensor's key is not signed by a trusted alerting key: it
    /// claims something nobody vouches for (a forgery, or a service whose key is not
    /// configured), and is not a verdict.
    Unverified,
    /// No calibration: raw outputs flagged `uncalibrated`.
    Uncalibrated,
    /// Past the record's `valid_until`.
    Expired,
    /// Before the record's `valid_from`.
    NotYetValid,
    /// The gateway's field health checks found the record in force `suspect`: its samples
    /// carry `calibration_suspect` (PROTOCOL.md §3.9).
    CalibrationSuspect,
    /// More than [`FLAGGED_ABOVE`] of the samples over the recent span carry a quality flag
    /// (calibrated sensors only: every raw sample of an uncalibrated one is flagged).
    Flagged,
    /// Within the warning period before `valid_until`.
    Expiring,
    /// The field health checks have the sensor at `watch`.
    HealthWatch,
    /// No batch for [`SILENT_AFTER`] by the gateway's clock.
    Silent,
    /// An alert at level `possible` or `stale`.
    Alert,
    /// Batches lost before the gateway (sequence gaps).
    Gaps,
    /// Malformed payloads on the sensor's key.
    Rejects,
    /// None of the above.
    Ok,
}

/// One sensor's row.
#[derive(Debug, Clone, Serialize)]
pub struct SensorView {
    pub sensor_id: SensorId,
    pub states: Vec<SensorState>,
    #[serde(with = "time::serde::rfc3339::option")]
    pub last_seen: Option<OffsetDateTime>,
    /// Age of the last batch by the gateway's clock, at its last status answer.
    pub last_seen_age_s: Option<f64>,
    pub batches: u64,
    pub samples: u64,
    pub gaps: u64,
    pub missing_batches: u64,
    pub rejects: u64,
    pub flagged_samples: u64,
    /// Share of flagged samples over the recent span ([`FLAGGED_SPAN`]); none before any
    /// sample, or without one in the span.
    pub flagged_share: Option<FlaggedShare>,
    pub mode: Mode,
    pub calibration_version: Option<u64>,
    #[serde(with = "time::serde::rfc3339::option")]
    pub valid_from: Option<OffsetDateTime>,
    #[serde(with = "time::serde::rfc3339::option")]
    pub valid_until: Option<OffsetDateTime>,
    /// Days until `valid_until` (negative: expired).
    pub expires_in_days: Option<f64>,
    /// The latest verified alert (a verdict); without one, the latest alert no trusted key
    /// vouches for.
    pub latest_alert: Option<AlertEntry>,
    /// An alert newer than the verdict in `latest_alert` that no trusted key vouches for: shown
    /// beside the verdict, never instead of it.
    pub unverified_claim: Option<AlertEntry>,
    /// Listed in the gateway's status (false: known from an alert only).
    pub in_status: bool,
}

impl SensorView {
    fn alert_only(sensor_id: SensorId, a: &SensorAlerts) -> SensorView {
        let mut states = alert_states(a);
        if states.is_empty() {
            states.push(SensorState::Ok);
        }
        SensorView {
            sensor_id,
            states,
            last_seen: None,
            last_seen_age_s: None,
            batches: 0,
            samples: 0,
            gaps: 0,
            missing_batches: 0,
            rejects: 0,
            flagged_samples: 0,
            flagged_share: None,
            mode: Mode::None,
            calibration_version: None,
            valid_from: None,
            valid_until: None,
            expires_in_days: None,
            latest_alert: a.shown().cloned(),
            unverified_claim: a.verified.as_ref().and(a.claim()).cloned(),
            in_status: false,
        }
    }
}

/// The states of the latest verdict, and `unverified` beside them for a newer claim.
fn alert_states(a: &SensorAlerts) -> Vec<SensorState> {
    let mut states = match a.verified.as_ref().map(|v| v.alert.level) {
        Some(AlertLevel::Exceeded) => vec![SensorState::Exceeded],
        Some(AlertLevel::Possible | AlertLevel::Stale) => vec![SensorState::Alert],
        None => vec![],
    };
    if a.claim().is_some() {
        states.push(SensorState::Unverified);
    }
    states
}

/// A sensor's row from its gateway's status (`reported_at` by the gateway's clock, received
/// `status_age` ago) and the console's clock (`now`, for calibration validity, which is
/// absolute time). A sensor's age is the gateway's view plus the status's own age, so that a
/// gateway gone silent does not leave its sensors looking fresh. `flagged` is the share of
/// flagged samples over the recent span.
pub fn sensor_view(
    s: &SensorStatus,
    reported_at: OffsetDateTime,
    status_age: Duration,
    now: OffsetDateTime,
    expiry_warning: Duration,
    alerts: SensorAlerts,
    flagged: Option<FlaggedShare>,
) -> SensorView {
    let mut states = alert_states(&alerts);
    let days = |d: time::Duration| d.as_seconds_f64() / 86_400.0;
    let expires_in = s.valid_until.map(|u| u - now);
    if s.calibration_version.is_none() {
        states.push(SensorState::Uncalibrated);
    } else if expires_in.is_some_and(|d| d <= time::Duration::ZERO) {
        states.push(SensorState::Expired);
    } else if s.valid_from.is_some_and(|f| f > now) {
        states.push(SensorState::NotYetValid);
    } else if expires_in.is_some_and(|d| d.as_seconds_f64() <= expiry_warning.as_secs_f64()) {
        states.push(SensorState::Expiring);
    }
    if s.calibration_version.is_some() && flagged.is_some_and(|f| f.share > FLAGGED_ABOVE) {
        states.push(SensorState::Flagged);
    }
    match s.health {
        Some(HealthVerdict::Suspect) => states.push(SensorState::CalibrationSuspect),
        Some(HealthVerdict::Watch) => states.push(SensorState::HealthWatch),
        Some(HealthVerdict::Ok) | None => {}
    }
    let age = s.last_seen.map(|t| reported_at - t + status_age);
    if age.is_none_or(|a| a.as_seconds_f64() > SILENT_AFTER.as_secs_f64()) {
        states.push(SensorState::Silent);
    }
    if s.gaps > 0 {
        states.push(SensorState::Gaps);
    }
    if s.rejects > 0 {
        states.push(SensorState::Rejects);
    }
    if states.is_empty() {
        states.push(SensorState::Ok);
    }
    states.sort();
    SensorView {
        sensor_id: s.sensor_id.clone(),
        states,
        last_seen: s.last_seen,
        last_seen_age_s: age.map(|a| a.as_seconds_f64().max(0.0)),
        batches: s.batches,
        samples: s.samples,
        gaps: s.gaps,
        missing_batches: s.missing_batches,
        rejects: s.rejects,
        flagged_samples: s.flagged_samples,
        flagged_share: flagged,
        mode: s.mode,
        calibration_version: s.calibration_version,
        valid_from: s.valid_from,
        valid_until: s.valid_until,
        expires_in_days: expires_in.map(days),
        latest_alert: alerts.shown().cloned(),
        unverified_claim: alerts.verified.as_ref().and(alerts.claim()).cloned(),
        in_status: true,
    }
}

/// One building in the fleet view.
#[derive(Debug, Clone, Serialize)]
pub struct BuildingView {
    pub building: BuildingId,
    pub gateway: Option<String>,
    pub state: GatewayState,
    /// Seconds since the gateway was last heard (heartbeat or status).
    pub last_heard_s: Option<f64>,
    pub heartbeat_sequence: Option<u64>,
    /// Why the last status poll got no answer from this building.
    pub status_error: Option<String>,
    #[serde(with = "time::serde::rfc3339::option")]
    pub started_at: Option<OffsetDateTime>,
    #[serde(with = "time::serde::rfc3339::option")]
    pub reported_at: Option<OffsetDateTime>,
    pub malformed: Option<u64>,
    pub dropped: Option<u64>,
    pub history: Option<HistoryStatus>,
    pub total_sensors: Option<u64>,
    /// The worst state of its sensors (none listed: none).
    pub worst_state: Option<SensorState>,
    pub sensors: Vec<SensorView>,
}

/// The fleet view.
#[derive(Debug, Clone, Serialize)]
pub struct Snapshot {
    #[serde(with = "time::serde::rfc3339")]
    pub now: OffsetDateTime,
    pub buildings: Vec<BuildingView>,
    /// The latest alerts, newest first.
    pub alerts: Vec<AlertEntry>,
    pub alerts_total: u64,
    /// Alerts read back from the alert log on start (not in `alerts_total`).
    pub alerts_restored: u64,
    /// Alerts in the log neither acknowledged nor silenced.
    pub alerts_open: usize,
    /// Heartbeats, alerts and status answers that did not decode or contradicted their key.
    pub malformed_messages: u64,
    /// Verified alerts received again (replays of a verdict already held): not new alerts.
    pub repeated_alerts: u64,
    /// Buildings heard of beyond [`MAX_BUILDINGS`].
    pub ignored_buildings: u64,
    /// Whether the gateways' messages are verified, and what was dropped as not theirs.
    pub provenance: ProvenanceView,
    pub expiry_warning_days: f64,
}

/// A sensor in the fleet event: its states and what changes seldom.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct SensorBrief {
    pub sensor_id: SensorId,
    pub states: Vec<SensorState>,
    pub mode: Mode,
    pub calibration_version: Option<u64>,
    #[serde(with = "time::serde::rfc3339::option")]
    pub valid_until: Option<OffsetDateTime>,
    /// The latest alert's id; the alert itself is in the event that first carried it.
    pub latest_alert: Option<u64>,
    pub in_status: bool,
}

/// A building in the fleet event, without its sensors' counters (those are at
/// `/api/fleet?building=`).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct BuildingBrief {
    pub building: BuildingId,
    pub gateway: Option<String>,
    pub state: GatewayState,
    pub status_error: Option<String>,
    #[serde(with = "time::serde::rfc3339::option")]
    pub started_at: Option<OffsetDateTime>,
    pub total_sensors: Option<u64>,
    pub worst_state: Option<SensorState>,
}

/// The fleet as the fleet event carries it: per building its brief and its sensors' briefs,
/// and the latest alerts whole.
#[derive(Debug, Clone, Serialize)]
pub struct Brief {
    #[serde(with = "time::serde::rfc3339")]
    pub now: OffsetDateTime,
    pub buildings: Vec<BriefBuilding>,
    pub alerts: Vec<AlertEntry>,
    pub alerts_total: u64,
    pub alerts_restored: u64,
    pub alerts_open: usize,
    pub malformed_messages: u64,
    pub ignored_buildings: u64,
    pub provenance: ProvenanceView,
    pub expiry_warning_days: f64,
}

#[derive(Debug, Clone, Serialize)]
pub struct BriefBuilding {
    #[serde(flatten)]
    pub building: BuildingBrief,
    pub sensors: Vec<SensorBrief>,
}

impl Brief {
    pub fn of(snap: &Snapshot) -> Brief {
        Brief {
            now: snap.now,
            buildings: snap
                .buildings
                .iter()
                .map(|b| BriefBuilding {
                    building: BuildingBrief {
                        building: b.building.clone(),
                        gateway: b.gateway.clone(),
                        state: b.state,
                        status_error: b.status_error.clone(),
                        started_at: b.started_at,
                        total_sensors: b.total_sensors,
                        worst_state: b.worst_state,
                    },
                    sensors: b
                        .sensors
                        .iter()
                        .map(|s| SensorBrief {
                            sensor_id: s.sensor_id.clone(),
                            states: s.states.clone(),
                            mode: s.mode,
                            calibration_version: s.calibration_version,
                            valid_until: s.valid_until,
                            latest_alert: s.latest_alert.as_ref().map(|a| a.id),
                            in_status: s.in_status,
                        })
                        .collect(),
                })
                .collect(),
            alerts: snap.alerts.clone(),
            alerts_total: snap.alerts_total,
            alerts_restored: snap.alerts_restored,
            alerts_open: snap.alerts_open,
            malformed_messages: snap.malformed_messages,
            ignored_buildings: snap.ignored_buildings,
            provenance: snap.provenance.clone(),
            expiry_warning_days: snap.expiry_warning_days,
        }
    }

    /// What changed from `before` to `self`, as the `fleet_delta` event carries it: every value
    /// whole (not a difference), so that a delta applied to a newer state than `before` still
    /// leaves the page right.
    pub fn delta(&self, before: &Brief, seq: u64) -> Delta {
        let old: std::collections::HashMap<&BuildingId, &BriefBuilding> = before
            .buildings
            .iter()
            .map(|b| (&b.building.building, b))
            .collect();
        let mut d = Delta {
            seq,
            now: self.now,
            alerts_total: self.alerts_total,
            alerts_open: self.alerts_open,
            malformed_messages: self.malformed_messages,
            ignored_buildings: self.ignored_buildings,
            refused_messages: self.provenance.refused.values().sum(),
            buildings: Vec::new(),
            sensors: Vec::new(),
            removed_sensors: Vec::new(),
            removed_buildings: Vec::new(),
            alerts: Vec::new(),
        };
        for b in &self.buildings {
            let id = &b.building.building;
            let prev = old.get(id);
            if prev.is_none_or(|p| p.building != b.building) {
                d.buildings.push(b.building.clone());
            }
            let prev_sensors: std::collections::HashMap<&SensorId, &SensorBrief> = prev
                .map(|p| p.sensors.iter().map(|s| (&s.sensor_id, s)).collect())
                .unwrap_or_default();
            for s in &b.sensors {
                if prev_sensors.get(&s.sensor_id).is_none_or(|p| *p != s) {
                    d.sensors.push(SensorChange {
                        building: id.clone(),
                        sensor: s.clone(),
                    });
                }
            }
            if let Some(p) = prev {
                let now: std::collections::HashSet<&SensorId> =
                    b.sensors.iter().map(|s| &s.sensor_id).collect();
                for s in &p.sensors {
                    if !now.contains(&s.sensor_id) {
                        d.removed_sensors.push((id.clone(), s.sensor_id.clone()));
                    }
                }
            }
        }
        let ids: std::collections::HashSet<&BuildingId> = self
            .buildings
            .iter()
            .map(|b| &b.building.building)
            .collect();
        d.removed_buildings = before
            .buildings
            .iter()
            .map(|b| &b.building.building)
            .filter(|b| !ids.contains(b))
            .cloned()
            .collect();
        let known: std::collections::HashSet<u64> = before.alerts.iter().map(|a| a.id).collect();
        d.alerts = self
            .alerts
            .iter()
            .filter(|a| !known.contains(&a.id))
            .cloned()
            .collect();
        d
    }
}

/// A sensor whose brief changed, and its building.
#[derive(Debug, Clone, Serialize)]
pub struct SensorChange {
    pub building: BuildingId,
    #[serde(flatten)]
    pub sensor: SensorBrief,
}

/// What changed in the fleet since the event before (`fleet_delta`).
#[derive(Debug, Clone, Serialize)]
pub struct Delta {
    /// One more than the delta before; a page that misses one gets the whole fleet again.
    pub seq: u64,
    #[serde(with = "time::serde::rfc3339")]
    pub now: OffsetDateTime,
    pub alerts_total: u64,
    pub alerts_open: usize,
    pub malformed_messages: u64,
    pub ignored_buildings: u64,
    /// Messages dropped as not verified, all reasons together (by reason in `/api/fleet`).
    pub refused_messages: u64,
    /// Buildings new or changed (without their sensors).
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub buildings: Vec<BuildingBrief>,
    /// Sensors new or changed.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub sensors: Vec<SensorChange>,
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub removed_sensors: Vec<(BuildingId, SensorId)>,
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub removed_buildings: Vec<BuildingId>,
    /// Alerts new since (whole, newest first).
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub alerts: Vec<AlertEntry>,
}

impl Delta {
    /// Nothing but the clock and the counters.
    pub fn is_quiet(&self) -> bool {
        self.buildings.is_empty()
            && self.sensors.is_empty()
            && self.removed_sensors.is_empty()
            && self.removed_buildings.is_empty()
            && self.alerts.is_empty()
    }
}

/// The Zenoh side: subscriptions to heartbeats and alerts (kept while the returned handles
/// live) and the status poll (runs until `stop` fires).
pub struct FleetWatch {
    _subscribers: Vec<zenoh::pubsub::Subscriber<()>>,
}

/// Subscribes to the heartbeats and alerts of the watched buildings (or of every building).
pub async fn watch(session: &zenoh::Session, fleet: &Arc<Fleet>) -> zenoh::Result<FleetWatch> {
    let mut key_exprs = Vec::new();
    if fleet.configured_buildings().is_empty() {
        key_exprs.push((keys::all_heartbeats(), true));
        key_exprs.push((keys::all_buildings(Stream::Alert), false));
    } else {
        for b in fleet.configured_buildings() {
            key_exprs.push((Key::Heartbeat(b.clone()).to_string(), true));
            key_exprs.push((keys::all_sensors(b, Stream::Alert), false));
        }
    }
    let mut subscribers = Vec::new();
    for (ke, heartbeat) in key_exprs {
        let f = fleet.clone();
        let sub = session
            .declare_subscriber(ke)
            .callback(move |sample| {
                let payload = sample.payload().to_bytes();
                let key = sample.key_expr().as_str();
                if heartbeat {
                    let attachment = sample.attachment().map(|a| a.to_bytes());
                    f.heartbeat(key, &payload, attachment.as_deref());
                } else {
                    f.alert(key, &payload);
                }
            })
            .await?;
        subscribers.push(sub);
    }
    Ok(FleetWatch {
        _subscribers: subscribers,
    })
}

/// Polls the gateways' status every `status_interval` until `stop` completes.
pub async fn poll_status(
    session: zenoh::Session,
    fleet: Arc<Fleet>,
    interval: Duration,
    mut stop: tokio::sync::watch::Receiver<bool>,
) {
    let mut tick = tokio::time::interval(interval);
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    loop {
        tokio::select! {
            _ = tick.tick() => {}
            _ = stop.changed() => return,
        }
        let timeout = interval.max(Duration::from_millis(500));
        let nonce = fleet.options.provenance.nonce();
        let params = match &nonce {
            Some(n) => format!("limit={STATUS_PAGE};nonce={n}"),
            None => format!("limit={STATUS_PAGE}"),
        };
        if fleet.configured_buildings().is_empty() {
            poll_once(
                &session,
                &fleet,
                &keys::all_statuses(),
                (&params, nonce.as_deref()),
                timeout,
                None,
            )
            .await;
        } else {
            for b in fleet.configured_buildings() {
                let key = Key::Status(b.clone()).to_string();
                let query = (params.as_str(), nonce.as_deref());
                poll_once(&session, &fleet, &key, query, timeout, Some(b)).await;
            }
        }
    }
}

async fn poll_once(
    session: &zenoh::Session,
    fleet: &Fleet,
    key: &str,
    (params, nonce): (&str, Option<&str>),
    timeout: Duration,
    building: Option<&BuildingId>,
) {
    let replies = match session
        .get(format!("{key}?{params}"))
        .consolidation(ConsolidationMode::None)
        .timeout(timeout)
        .await
    {
        Ok(r) => r,
        Err(e) => {
            tracing::warn!(key, cause = %e, "status query failed");
            return;
        }
    };
    let mut answered = false;
    let mut refusal = None;
    while let Ok(reply) = replies.recv_async().await {
        match reply.result() {
            Ok(sample) => {
                let payload = sample.payload().to_bytes();
                let attachment = sample.attachment().map(|a| a.to_bytes());
                let key = sample.key_expr().as_str();
                if !fleet
                    .options
                    .provenance
                    .reply(key, nonce, &payload, attachment.as_deref())
                {
                    continue;
                }
                match from_json::<GatewayStatus>(&payload) {
                    Ok(st)
                        if Key::Status(st.building.clone()).to_string()
                            == sample.key_expr().as_str() =>
                    {
                        answered = true;
                        fleet.status(st)
                    }
                    Ok(_) => fleet.malformed(sample.key_expr().as_str(), "key and status disagree"),
                    Err(e) => fleet.malformed(sample.key_expr().as_str(), &e.to_string()),
                }
            }
            // An error reply carries no signature: it is shown, as what it claims, only when
            // no verified answer came.
            Err(e) => refusal = Some(String::from_utf8_lossy(&e.payload().to_bytes()).into_owned()),
        }
    }
    if let (Some(b), false) = (building, answered) {
        let message = match (refusal, fleet.options.provenance.verifying()) {
            (Some(text), false) => format!("status query refused: {text}"),
            (Some(text), true) => format!("no verified status answer; an unsigned refusal: {text}"),
            (None, false) => "no status answer".into(),
            (None, true) => "no verified status answer".into(),
        };
        fleet.status_error(b, message);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn t(s: i64) -> OffsetDateTime {
        OffsetDateTime::from_unix_timestamp(1_800_000_000 + s).unwrap()
    }

    fn status(version: Option<u64>) -> SensorStatus {
        SensorStatus {
            sensor_id: SensorId::new("acc-01").unwrap(),
            last_seen: Some(t(0)),
            batches: 10,
            samples: 500,
            gaps: 0,
            missing_batches: 0,
            late_batches: 0,
            duplicates: 0,
            rejects: 0,
            flagged_samples: 0,
            keys_declared: true,
            calibration_version: version,
            mode: if version.is_some() {
                Mode::Dynamic
            } else {
                Mode::None
            },
            valid_from: version.map(|_| t(-86_400)),
            valid_until: None,
            health: None,
            suspect_from_ns: None,
            calibration_record: None,
        }
    }

    const WARN: Duration = Duration::from_secs(30 * 86_400);

    #[test]
    fn states_from_status() {
        let v = sensor_view(
            &status(Some(1)),
            t(1),
            Duration::ZERO,
            t(1),
            WARN,
            SensorAlerts::default(),
            None,
        );
        assert_eq!(v.states, [SensorState::Ok]);
        let v = sensor_view(
            &status(None),
            t(1),
            Duration::ZERO,
            t(1),
            WARN,
            SensorAlerts::default(),
            None,
        );
        assert_eq!(v.states, [SensorState::Uncalibrated]);

        let mut s = status(Some(1));
        s.gaps = 2;
        s.rejects = 1;
        let v = sensor_view(
            &s,
            t(60),
            Duration::ZERO,
            t(1),
            WARN,
            SensorAlerts::default(),
            None,
        );
        assert_eq!(
            v.states,
            [SensorState::Silent, SensorState::Gaps, SensorState::Rejects],
            "silent by the gateway's clock: 60 s since the last batch"
        );
        assert_eq!(v.last_seen_age_s, Some(60.0));
        let v = sensor_view(
            &s,
            t(1),
            Duration::from_secs(30),
            t(1),
            WARN,
            SensorAlerts::default(),
            None,
        );
        assert_eq!(
            (v.states[0], v.last_seen_age_s),
            (SensorState::Silent, Some(31.0)),
            "a status 30 s old: its gateway went silent"
        );
    }

    #[test]
    fn validity_warns_before_expiry_and_says_expired_after() {
        let mut s = status(Some(1));
        s.valid_until = Some(t(10 * 86_400));
        let v = sensor_view(
            &s,
            t(0),
            Duration::ZERO,
            t(0),
            WARN,
            SensorAlerts::default(),
            None,
        );
        assert_eq!(v.states, [SensorState::Expiring]);
        assert!((v.expires_in_days.unwrap() - 10.0).abs() < 1e-9);
        let v = sensor_view(
            &s,
            t(0),
            Duration::ZERO,
            t(0),
            Duration::from_secs(86_400),
            SensorAlerts::default(),
            None,
        );
        assert_eq!(v.states, [SensorState::Ok], "outside a one-day warning");
        let v = sensor_view(
            &s,
            t(0),
            Duration::ZERO,
            t(10 * 86_400),
            WARN,
            SensorAlerts::default(),
            None,
        );
        assert_eq!(v.states, [SensorState::Expired]);
        s.valid_from = Some(t(5));
        s.valid_until = None;
        let v = sensor_view(
            &s,
            t(0),
            Duration::ZERO,
            t(0),
            WARN,
            SensorAlerts::default(),
            None,
        );
        assert_eq!(v.states, [SensorState::NotYetValid]);
    }

    fn gateway_status(at_s: i64, sensors: Vec<SensorStatus>) -> GatewayStatus {
        let rfc = |t: OffsetDateTime| {
            t.format(&time::format_description::well_known::Rfc3339)
                .unwrap()
        };
        serde_json::from_value(serde_json::json!({
            "format_version": 1, "building": "hq", "gateway": "gw",
            "started_at": rfc(t(-1000)), "reported_at": rfc(t(at_s)),
            "malformed": 0, "dropped": 0, "pushes_accepted": 0, "pushes_refused": 0,
            "total_sensors": sensors.len(), "sensors": sensors,
        }))
        .unwrap()
    }

    fn counted(id: &str, samples: u64, flagged: u64) -> SensorStatus {
        let mut s = status(Some(1));
        s.sensor_id = SensorId::new(id).unwrap();
        s.samples = samples;
        s.flagged_samples = flagged;
        s
    }

    #[test]
    fn the_flagged_share_is_taken_over_the_last_minute() {
        let mut h = CounterHistory::default();
        // First answer: since the gateway started (half of it flagged, long ago).
        let first = h.update(&gateway_status(0, vec![counted("a", 1000, 500)]));
        assert_eq!(first[&SensorId::new("a").unwrap()].share, 0.5);
        assert_eq!(first[&SensorId::new("a").unwrap()].span_s, None);
        // Every second 100 samples, none flagged, for two minutes: since the gateway started
        // until the console has a checkpoint a minute old, then only the last minute.
        let mut last = BTreeMap::new();
        for i in 1..=120 {
            let n = 1000 + 100 * i as u64;
            last = h.update(&gateway_status(i, vec![counted("a", n, 500)]));
            let a = last[&SensorId::new("a").unwrap()];
            if i < 60 {
                assert_eq!((a.share, a.span_s), (500.0 / n as f64, None), "at {i} s");
            } else {
                assert_eq!(a.share, 0.0, "at {i} s");
            }
        }
        let a = last[&SensorId::new("a").unwrap()];
        let span = a.span_s.unwrap();
        assert!((60.0..=75.0).contains(&span), "{span}");
        assert!(h.checkpoints.len() <= 6, "{}", h.checkpoints.len());
        // Then everything flagged: above the threshold within a checkpoint interval.
        let mut n = 1000 + 100 * 120;
        let mut f = 500;
        let mut at = 120;
        let share = loop {
            at += 1;
            n += 100;
            f += 100;
            let s = h.update(&gateway_status(at, vec![counted("a", n, f)]))
                [&SensorId::new("a").unwrap()];
            if s.share > FLAGGED_ABOVE {
                break s;
            }
        };
        assert!(at - 120 <= 20, "flagged after {} s", at - 120);
        assert!(share.share < 0.5);
        // A restart: counters from zero, counted whole again.
        let mut restarted = gateway_status(at + 1, vec![counted("a", 100, 100)]);
        restarted.started_at = t(at);
        let s = h.update(&restarted)[&SensorId::new("a").unwrap()];
        assert_eq!((s.share, s.span_s), (1.0, None));
    }

    #[test]
    fn the_gateways_health_verdict_is_a_state() {
        let view = |h| {
            let mut st = status(Some(1));
            st.health = h;
            sensor_view(
                &st,
                t(1),
                Duration::ZERO,
                t(1),
                WARN,
                SensorAlerts::default(),
                None,
            )
            .states
        };
        assert_eq!(
            view(Some(HealthVerdict::Suspect)),
            [SensorState::CalibrationSuspect]
        );
        assert_eq!(view(Some(HealthVerdict::Watch)), [SensorState::HealthWatch]);
        assert_eq!(view(Some(HealthVerdict::Ok)), [SensorState::Ok]);
        assert_eq!(view(None), [SensorState::Ok]);
    }

    #[test]
    fn a_flagged_sensor_says_so_and_its_building_takes_the_worst_state() {
        let share = |s, f| FlaggedShare::of(s, f, Some(60.0));
        let v = sensor_view(
            &status(Some(1)),
            t(1),
            Duration::ZERO,
            t(1),
            WARN,
            SensorAlerts::default(),
            share(6000, 6000),
        );
        assert_eq!(v.states, [SensorState::Flagged]);
        let v = sensor_view(
            &status(Some(1)),
            t(1),
            Duration::ZERO,
            t(1),
            WARN,
            SensorAlerts::default(),
            share(6000, 1200),
        );
        assert_eq!(v.states, [SensorState::Ok], "20 % is not above 20 %");
        let v = sensor_view(
            &status(None),
            t(1),
            Duration::ZERO,
            t(1),
            WARN,
            SensorAlerts::default(),
            share(6000, 6000),
        );
        assert_eq!(
            v.states,
            [SensorState::Uncalibrated],
            "raw outputs are flagged anyway"
        );
        assert_eq!(FlaggedShare::of(0, 0, None), None);

        let f = Fleet::new(FleetOptions {
            buildings: vec![],
            status_interval: Duration::from_secs(2),
            expiry_warning: WARN,
            trusted_alert_keys: TrustedKeys::default(),
            provenance: Arc::new(Provenance::on_trust()),
        });
        let mut st = gateway_status(0, vec![counted("a", 100, 0), counted("b", 100, 100)]);
        st.reported_at = OffsetDateTime::now_utc();
        for s in &mut st.sensors {
            s.last_seen = Some(st.reported_at);
            s.valid_from = Some(st.reported_at - time::Duration::DAY);
        }
        f.status(st);
        let snap = f.snapshot();
        let b = &snap.buildings[0];
        assert_eq!(b.sensors[0].states, [SensorState::Ok]);
        assert_eq!(b.sensors[1].states, [SensorState::Flagged]);
        assert_eq!(b.sensors[1].flagged_share.unwrap().share, 1.0);
        assert_eq!(b.worst_state, Some(SensorState::Flagged));
    }

    fn alert_json(b: &str, s: &str, level: &str, statement: &str) -> Vec<u8> {
        serde_json::to_vec(&serde_json::json!({
            "format_version": 1, "building": b, "sensor_id": s, "kind": "peak_acceleration",
            "level": level, "value": 1.2, "standard_uncertainty": 0.05, "coverage_factor": 2.0,
            "threshold": 1.0, "unit": "m/s^2", "window_s": 4.0, "flagged_fraction": 0.0,
            "statement": statement, "at": "2027-01-15T08:00:00Z"
        }))
        .unwrap()
    }

    fn service_key() -> triax_protocol::signing::LabSigningKey {
        triax_protocol::signing::LabSigningKey::from_bytes(&[21; 32])
    }

    /// `alert_json`, signed by `key` as the alerting service publishes it.
    fn signed_json(
        key: &triax_protocol::signing::LabSigningKey,
        b: &str,
        s: &str,
        level: &str,
        statement: &str,
    ) -> Vec<u8> {
        let alert: Alert = from_json(&alert_json(b, s, level, statement)).unwrap();
        triax_protocol::to_json(&triax_protocol::signing::sign_alert(&alert, key))
    }

    #[test]
    fn alerts_are_checked_against_their_key_and_bounded() {
        let f = Fleet::new(FleetOptions {
            buildings: vec![],
            status_interval: Duration::from_secs(2),
            expiry_warning: WARN,
            trusted_alert_keys: TrustedKeys::new(vec![service_key().verifying_key()]),
            provenance: Arc::new(Provenance::on_trust()),
        });
        f.alert(
            "triax/hq/alert/acc-01",
            &signed_json(&service_key(), "hq", "acc-01", "exceeded", "<b>x</b>"),
        );
        f.alert(
            "triax/hq/alert/acc-02",
            &alert_json("hq", "acc-01", "exceeded", "wrong key"),
        );
        f.alert("triax/hq/alert/acc-01", b"{not json");
        f.alert(
            "triax/hq/alert/acc-01",
            &alert_json("hq", "acc-01", "panic", "bad level"),
        );
        let snap = f.snapshot();
        assert_eq!(snap.alerts_total, 1);
        assert_eq!(snap.malformed_messages, 3);
        assert_eq!(snap.alerts[0].trust, "verified");
        assert_eq!(
            snap.alerts[0].alert.statement, "<b>x</b>",
            "kept verbatim; the page escapes"
        );
        let b = &snap.buildings[0];
        assert_eq!(b.state, GatewayState::Unknown);
        assert_eq!(b.sensors[0].states, [SensorState::Exceeded]);
        assert!(!b.sensors[0].in_status);
        // The same `exceeded` unsigned, or signed by another key: shown, never a verdict.
        let forger = triax_protocol::signing::LabSigningKey::from_bytes(&[22; 32]);
        f.alert(
            "triax/hq/alert/acc-02",
            &alert_json("hq", "acc-02", "exceeded", "unsigned"),
        );
        f.alert(
            "triax/hq/alert/acc-03",
            &signed_json(&forger, "hq", "acc-03", "exceeded", "forged"),
        );
        let snap = f.snapshot();
        let states = |id: &str| {
            snap.buildings[0]
                .sensors
                .iter()
                .find(|s| s.sensor_id.as_str() == id)
                .map(|s| s.states.clone())
                .unwrap()
        };
        assert_eq!(states("acc-02"), [SensorState::Unverified]);
        assert_eq!(states("acc-03"), [SensorState::Unverified]);
        assert_eq!(snap.alerts[0].trust, "unknown_key");
        assert_eq!(snap.alerts[1].trust, "unsigned");
        for i in 0..(MAX_ALERTS + 10) {
            f.alert(
                "triax/hq/alert/acc-01",
                &alert_json("hq", "acc-01", "possible", &i.to_string()),
            );
        }
        assert_eq!(f.alerts().len(), MAX_ALERTS);
        assert_eq!(f.alerts()[0].alert.statement, (MAX_ALERTS + 9).to_string());
    }

    #[test]
    fn a_verdict_is_neither_replayed_nor_masked_nor_flooded_out() {
        let f = Fleet::new(FleetOptions {
            buildings: vec![],
            status_interval: Duration::from_secs(2),
            expiry_warning: WARN,
            trusted_alert_keys: TrustedKeys::new(vec![service_key().verifying_key()]),
            provenance: Arc::new(Provenance::on_trust()),
        });
        let genuine = signed_json(&service_key(), "hq", "acc-01", "exceeded", "real");
        f.alert("triax/hq/alert/acc-01", &genuine);
        // A peer replays it, unaltered: it verifies, and is the same verdict.
        for _ in 0..80 {
            f.alert("triax/hq/alert/acc-01", &genuine);
        }
        let snap = f.snapshot();
        assert_eq!((snap.alerts_total, snap.repeated_alerts), (1, 80));
        assert_eq!(f.with_log(|l| l.len()), 1, "one alert in the log");
        // An unsigned claim after it: shown beside the verdict, not instead of it.
        f.alert(
            "triax/hq/alert/acc-01",
            &alert_json("hq", "acc-01", "possible", "all is well, says the peer"),
        );
        let snap = f.snapshot();
        let s = &snap.buildings[0].sensors[0];
        assert_eq!(s.states, [SensorState::Exceeded, SensorState::Unverified]);
        assert_eq!(s.latest_alert.as_ref().unwrap().alert.statement, "real");
        assert_eq!(
            s.unverified_claim.as_ref().unwrap().alert.statement,
            "all is well, says the peer"
        );
        // A flood of claims: the verdict stays in the fleet's alerts and in the log.
        for i in 0..(2 * MAX_ALERTS) {
            f.alert(
                "triax/hq/alert/acc-02",
                &alert_json("hq", "acc-02", "exceeded", &i.to_string()),
            );
        }
        assert!(f
            .alerts()
            .iter()
            .any(|a| a.verified() && a.alert.statement == "real"));
        let verified = f.with_log(|l| {
            l.query(&crate::alertlog::AlertQuery {
                level: Some(crate::alertlog::LevelFilter::Verified(AlertLevel::Exceeded)),
                limit: 10,
                ..Default::default()
            })
            .matched
        });
        assert_eq!(verified, 1);
        // A second verdict on the same sensor is new, and the latest.
        f.alert(
            "triax/hq/alert/acc-01",
            &signed_json(&service_key(), "hq", "acc-01", "possible", "later"),
        );
        let snap = f.snapshot();
        let s = &snap.buildings[0].sensors[0];
        assert_eq!(snap.alerts_total, 3 + 2 * MAX_ALERTS as u64);
        assert_eq!(s.states, [SensorState::Alert]);
        assert!(
            s.unverified_claim.is_none(),
            "the claim is older than the verdict"
        );
    }

    #[test]
    fn the_fleet_delta_carries_what_changed_and_nothing_that_only_counts() {
        let f = Fleet::new(FleetOptions {
            buildings: vec![],
            status_interval: Duration::from_secs(2),
            expiry_warning: WARN,
            trusted_alert_keys: TrustedKeys::new(vec![service_key().verifying_key()]),
            provenance: Arc::new(Provenance::on_trust()),
        });
        let answer = |samples: u64, flagged: u64| {
            let mut st = gateway_status(
                0,
                (0..100)
                    .map(|i| counted(&format!("acc-{i:03}"), samples, flagged))
                    .collect(),
            );
            st.reported_at = OffsetDateTime::now_utc();
            for s in &mut st.sensors {
                s.last_seen = Some(st.reported_at);
                s.valid_from = Some(st.reported_at - time::Duration::DAY);
            }
            st
        };
        f.status(answer(1000, 0));
        let first = f.brief();
        // Counters move, states do not: the delta is the clock and the totals.
        f.status(answer(2000, 0));
        let quiet = f.brief().delta(&first, 1);
        assert!(quiet.is_quiet(), "{quiet:?}");
        let text = serde_json::to_string(&quiet).unwrap();
        assert!(text.len() < 200, "{} bytes: {text}", text.len());
        // A sensor's state changes and an alert arrives: those, and only those.
        let before = f.brief();
        let mut st = answer(3000, 0);
        st.sensors[7].gaps = 1;
        f.status(st);
        f.alert(
            "triax/hq/alert/acc-042",
            &signed_json(&service_key(), "hq", "acc-042", "exceeded", "a verdict"),
        );
        let d = f.brief().delta(&before, 2);
        let changed: Vec<&str> = d
            .sensors
            .iter()
            .map(|c| c.sensor.sensor_id.as_str())
            .collect();
        assert_eq!(changed, ["acc-007", "acc-042"], "{d:?}");
        assert_eq!(d.sensors[0].sensor.states, [SensorState::Gaps]);
        assert_eq!(d.sensors[1].sensor.states, [SensorState::Exceeded]);
        assert_eq!(d.sensors[1].sensor.latest_alert, Some(d.alerts[0].id));
        assert_eq!(d.alerts.len(), 1);
        assert_eq!(
            d.buildings.len(),
            1,
            "its worst state changed: {:?}",
            d.buildings
        );
        assert_eq!(d.buildings[0].worst_state, Some(SensorState::Exceeded));
        // Applied to the brief before, the delta gives the brief after.
        let after = f.brief();
        assert!(after.delta(&after, 3).is_quiet());
    }

    #[test]
    fn a_watched_list_ignores_other_buildings() {
        let f = Fleet::new(FleetOptions {
            buildings: vec![BuildingId::new("hq").unwrap()],
            status_interval: Duration::from_secs(2),
            expiry_warning: WARN,
            trusted_alert_keys: TrustedKeys::default(),
            provenance: Arc::new(Provenance::on_trust()),
        });
        f.alert(
            "triax/other/alert/x",
            &alert_json("other", "x", "exceeded", "s"),
        );
        let snap = f.snapshot();
        assert_eq!(snap.buildings.len(), 1);
        assert_eq!(snap.buildings[0].building.as_str(), "hq");
        assert!(snap.buildings[0].sensors.is_empty());
    }
}
