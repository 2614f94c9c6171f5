//! The gateway's in-memory table of sensors: for each, the calibration snapshot in force, its
//! processing settings and its counters.
//!
//! The sample path reads a sensor's corrector once per batch with [`SensorEntry::corrector`], a
//! lock-free load of an `Arc<Corrector>`: the whole batch is corrected with that one snapshot.
//! [`SensorTable::install`] swaps a sensor's snapshot atomically, so a calibration update (a
//! push from the lab) takes effect from the next batch, never halfway through one, and never
//! waits for or blocks the sample path. The store is not touched here: whoever installs a
//! corrector has made its record durable first.
//!
//! The table's own lock guards only membership (a sensor appearing or being forgotten), and is
//! never held across an await.
//!
//! # Admission
//!
//! Anyone who can put on a raw key can name a new sensor, so new ids are admitted by a rule
//! a flood cannot turn against real nodes:
//! - a sensor with a calibration always has its entry (the lab signed it) and is never
//!   forgotten;
//! - a new uncalibrated id is admitted *on probation*; once it sends a second batch it is
//!   *established*. While the table holds `max_sensors` entries, a new id takes the place of the
//!   oldest probationary entry, so ids that send one batch and vanish (a flood of random ids)
//!   only ever displace each other, and a real node, which sends again within a second, is
//!   established before the flood can reach it. Only when every entry is calibrated or
//!   established is a new id refused (`over_capacity`);
//! - an uncalibrated sensor silent for `unknown_sensor_expiry_s` is forgotten
//!   ([`SensorTable::expire_idle`]), so what a flood admitted ages out.
//!
//! A forgotten entry is marked ([`SensorEntry::is_evicted`]); the worker holding its correction
//! state drops it at its next sweep, which also gives back its declared Zenoh keys.

use std::collections::{HashMap, VecDeque};
use std::sync::atomic::{AtomicBool, AtomicI64, AtomicU64, AtomicU8, Ordering::Relaxed};
use std::sync::{Arc, Mutex, RwLock};

use arc_swap::ArcSwapOption;
use time::OffsetDateTime;
use triax_calibration::corrector::Corrector;
use triax_health::SensorHealth;
use triax_protocol::messages::{HealthVerdict, SensorStatus};
use triax_protocol::record::CalibrationRecord;
use triax_protocol::{Mode, SensorId};

use super::health::{GroupSlot, Groups, HealthSeed};
use crate::clock::now_ns;
use crate::config::{Config, SensorSettings};
use crate::sync::lock;

/// Counters of one sensor. Relaxed atomics: each is an independent tally read for reports.
#[derive(Debug, Default)]
pub struct SensorCounters {
    pub batches: AtomicU64,
    pub samples: AtomicU64,
    pub gaps: AtomicU64,
    pub missing_batches: AtomicU64,
    pub duplicates: AtomicU64,
    pub restarts: AtomicU64,
    pub rejects: AtomicU64,
    pub flagged_samples: AtomicU64,
    pub uncalibrated_samples: AtomicU64,
    /// Receive time of the last batch, ns since the Unix epoch; 0 before the first.
    pub last_seen_ns: AtomicI64,
    /// The last corrected batch published: its sequence number and first-sample time, and when
    /// it was published (ns since the Unix epoch, 0 before the first), for the heartbeat.
    pub last_published_sequence: AtomicU64,
    pub last_published_timestamp_ns: AtomicI64,
    pub last_published_ns: AtomicI64,
    /// The last late batch published (a backfill): its number and first-sample time, and when
    /// (0 before the first), for the heartbeat; and how many.
    pub late_sequence: AtomicU64,
    pub late_timestamp_ns: AtomicI64,
    pub late_published_ns: AtomicI64,
    pub late_batches: AtomicU64,
    /// Whether the worker holds the sensor's keys declared (see `worker::SensorKeys`).
    pub keys_declared: AtomicBool,
}

/// One sensor as the gateway knows it.
#[derive(Debug)]
pub struct SensorEntry {
    pub id: SensorId,
    pub settings: SensorSettings,
    corrector: ArcSwapOption<Corrector>,
    pub counters: SensorCounters,
    /// Set when the table forgets the sensor: whoever holds the entry lets it go.
    evicted: AtomicBool,
    /// The field health monitor made for the record last installed, until the sensor's worker
    /// takes it (at its next batch corrected with that record); none when health is off.
    health_seed: Mutex<Option<Box<SensorHealth>>>,
    /// The record found suspect and when its flag starts (see `sample_path::health`): loaded from
    /// the store at start, set by the sensor's worker when it latches.
    suspect: Mutex<Option<(u64, i64)>>,
    /// The latest health report, JSON as published, for the health queryable.
    health_report: ArcSwapOption<Vec<u8>>,
    /// Its verdict (0 ok, 1 watch, 2 suspect; [`NO_HEALTH`] before the first), for status
    /// and metrics.
    health_verdict: AtomicU8,
}

/// [`SensorEntry::health_verdict`] before the sensor's first health report.
pub const NO_HEALTH: u8 = u8::MAX;

impl SensorEntry {
    pub(crate) fn new(id: SensorId, settings: SensorSettings) -> SensorEntry {
        SensorEntry {
            id,
            settings,
            corrector: ArcSwapOption::empty(),
            counters: SensorCounters::default(),
            evicted: AtomicBool::new(false),
            health_seed: Mutex::new(None),
            suspect: Mutex::new(None),
            health_report: ArcSwapOption::empty(),
            health_verdict: AtomicU8::new(NO_HEALTH),
        }
    }

    /// The health monitor for `version`, if the last install made one for it.
    pub fn take_health_seed(&self, version: u64) -> Option<Box<SensorHealth>> {
        let mut seed = lock(&self.health_seed);
        match seed.as_ref() {
            Some(h) if h.version() == version => seed.take(),
            _ => None,
        }
    }

    /// The record found suspect and the time its flag starts from.
    pub fn suspect(&self) -> Option<(u64, i64)> {
        *lock(&self.suspect)
    }

    pub fn set_suspect(&self, version: u64, flagged_from_ns: i64) {
        *lock(&self.suspect) = Some((version, flagged_from_ns));
    }

    /// Keeps `json` as the sensor's latest health report.
    pub fn set_health_report(&self, json: Vec<u8>, verdict: HealthVerdict) {
        self.health_report.store(Some(Arc::new(json)));
        self.health_verdict.store(verdict as u8, Relaxed);
    }

    pub fn health_report(&self) -> Option<Arc<Vec<u8>>> {
        self.health_report.load_full()
    }

    /// The latest health report's verdict; none before the first.
    pub fn health_verdict(&self) -> Option<HealthVerdict> {
        match self.health_verdict.load(Relaxed) {
            0 => Some(HealthVerdict::Ok),
            1 => Some(HealthVerdict::Watch),
            2 => Some(HealthVerdict::Suspect),
            _ => None,
        }
    }

    /// Records a corrected batch published at `published_ns` (ns since the Unix epoch), for
    /// the heartbeat.
    pub fn note_published(&self, sequence: u64, timestamp_ns: i64, published_ns: i64) {
        let c = &self.counters;
        c.last_published_sequence.store(sequence, Relaxed);
        c.last_published_timestamp_ns.store(timestamp_ns, Relaxed);
        c.last_published_ns.store(published_ns, Relaxed);
    }

    pub fn note_late(&self, sequence: u64, timestamp_ns: i64) {
        let c = &self.counters;
        c.late_sequence.store(sequence, Relaxed);
        c.late_timestamp_ns.store(timestamp_ns, Relaxed);
        c.late_published_ns.store(now_ns(), Relaxed);
        c.late_batches.fetch_add(1, Relaxed);
    }

    /// Whether the table has forgotten this entry (see the module doc).
    pub fn is_evicted(&self) -> bool {
        self.evicted.load(Relaxed)
    }

    fn is_calibrated(&self) -> bool {
        self.corrector.load().is_some()
    }

    /// The corrector in force, if any, borrowed: for a look, not to hold.
    pub fn corrector_guard(&self) -> arc_swap::Guard<Option<Arc<Corrector>>> {
        self.corrector.load()
    }

    /// The corrector in force, if any: load once per batch.
    pub fn corrector(&self) -> Option<Arc<Corrector>> {
        self.corrector.load_full()
    }

    pub fn calibration_version(&self) -> Option<u64> {
        self.corrector.load().as_ref().map(|c| c.version())
    }

    pub fn status(&self) -> SensorStatus {
        let c = &self.counters;
        let last = c.last_seen_ns.load(Relaxed);
        let corrector = self.corrector.load();
        let version = corrector.as_ref().map(|c| c.version());
        let at = |ns: i128| OffsetDateTime::from_unix_timestamp_nanos(ns).ok();
        SensorStatus {
            sensor_id: self.id.clone(),
            last_seen: (last != 0)
                .then(|| OffsetDateTime::from_unix_timestamp_nanos(i128::from(last)).ok())
                .flatten(),
            batches: c.batches.load(Relaxed),
            samples: c.samples.load(Relaxed),
            gaps: c.gaps.load(Relaxed),
            missing_batches: c.missing_batches.load(Relaxed),
            late_batches: c.late_batches.load(Relaxed),
            duplicates: c.duplicates.load(Relaxed),
            rejects: c.rejects.load(Relaxed),
            flagged_samples: c.flagged_samples.load(Relaxed),
            keys_declared: c.keys_declared.load(Relaxed),
            calibration_version: version,
            mode: if version.is_some() {
                self.settings.mode.wire()
            } else {
                Mode::None
            },
            valid_from: corrector.as_ref().and_then(|c| at(c.valid_from_ns())),
            valid_until: corrector
                .as_ref()
                .and_then(|c| c.valid_until_ns())
                .and_then(at),
            health: self.health_verdict(),
            suspect_from_ns: self
                .suspect()
                .filter(|&(v, _)| Some(v) == version)
                .map(|(_, t)| t),
            calibration_record: None,
        }
    }
}

/// Most probationary entries looked at to admit one new id. Established entries met on the way
/// leave the probation queue for good, so the work is constant per admission on average.
const EVICTION_SCAN: usize = 64;

/// Batches after which an uncalibrated sensor is established (see the module doc).
pub const ESTABLISHED_BATCHES: u64 = 2;

/// What admission and expiry did, since start.
#[derive(Debug, Default)]
pub struct AdmissionCounters {
    /// New uncalibrated ids admitted.
    pub admitted: AtomicU64,
    /// Probationary entries that gave their place to a new id.
    pub displaced: AtomicU64,
    /// Uncalibrated entries forgotten after `unknown_sensor_expiry_s` of silence.
    pub expired: AtomicU64,
}

/// Every sensor known to the gateway: loaded from the store, or seen on the network.
#[derive(Debug)]
pub struct SensorTable {
    config: Arc<Config>,
    sensors: RwLock<HashMap<SensorId, Arc<SensorEntry>>>,
    /// Uncalibrated ids in admission order that may not be established yet; the oldest gives
    /// way first. An id can be here after it was established, calibrated or forgotten: that is
    /// checked when it reaches the front.
    probation: Mutex<VecDeque<SensorId>>,
    pub admission: AdmissionCounters,
    /// The declared co-located pairs (field health).
    pairs: Groups,
}

impl SensorTable {
    pub fn new(config: Arc<Config>) -> SensorTable {
        let pairs = config
            .health
            .as_ref()
            .map_or_else(Groups::default, |h| Groups::new(&h.colocated, &h.triples));
        SensorTable {
            config,
            pairs,
            sensors: RwLock::new(HashMap::new()),
            probation: Mutex::new(VecDeque::new()),
            admission: AdmissionCounters::default(),
        }
    }

    /// The sensor's entry, if the table has it.
    pub fn get(&self, id: &SensorId) -> Option<Arc<SensorEntry>> {
        self.read().get(id).cloned()
    }

    /// The sensor's entry, created (uncalibrated) on first sight.
    pub fn entry(&self, id: &SensorId) -> Arc<SensorEntry> {
        if let Some(e) = self.get(id) {
            return e;
        }
        let mut map = self.write();
        map.entry(id.clone())
            .or_insert_with(|| {
                Arc::new(SensorEntry::new(
                    id.clone(),
                    self.config.sensor(id.as_str()).clone(),
                ))
            })
            .clone()
    }

    /// The entry of a sensor seen on the network, admitted by the rule of the module doc; none
    /// when the table is full of calibrated and established sensors. Calibrated sensors always
    /// have their entry (made by [`install`](Self::install)).
    pub fn seen(&self, id: &SensorId) -> Option<Arc<SensorEntry>> {
        if let Some(e) = self.get(id) {
            return Some(e);
        }
        let mut map = self.write();
        if let Some(e) = map.get(id) {
            return Some(e.clone());
        }
        let mut probation = self.probation.lock().unwrap_or_else(|p| p.into_inner());
        if map.len() >= self.config.max_sensors && !self.displace_one(&mut map, &mut probation) {
            return None;
        }
        let entry = Arc::new(SensorEntry::new(
            id.clone(),
            self.config.sensor(id.as_str()).clone(),
        ));
        // Silent from now on counts from admission, not from the epoch.
        entry.counters.last_seen_ns.store(now_ns(), Relaxed);
        map.insert(id.clone(), entry.clone());
        probation.push_back(id.clone());
        self.admission.admitted.fetch_add(1, Relaxed);
        Some(entry)
    }

    /// Forgets the oldest entry still on probation; false if none is within reach.
    fn displace_one(
        &self,
        map: &mut HashMap<SensorId, Arc<SensorEntry>>,
        probation: &mut VecDeque<SensorId>,
    ) -> bool {
        for _ in 0..EVICTION_SCAN {
            let Some(candidate) = probation.pop_front() else {
                return false;
            };
            let Some(e) = map.get(&candidate) else {
                continue; // already forgotten
            };
            if e.is_calibrated() || e.counters.batches.load(Relaxed) >= ESTABLISHED_BATCHES {
                continue; // established: off probation for good
            }
            if let Some(e) = map.remove(&candidate) {
                e.evicted.store(true, Relaxed);
                self.admission.displaced.fetch_add(1, Relaxed);
                return true;
            }
        }
        false
    }

    /// Forgets every uncalibrated sensor silent since before `now_ns − unknown_sensor_expiry`;
    /// returns how many. Called periodically; the scan holds the read lock, the removal the write
    /// lock, each briefly.
    pub fn expire_idle(&self, now_ns: i64) -> usize {
        let expiry_ns =
            i64::try_from(self.config.unknown_sensor_expiry.as_nanos()).unwrap_or(i64::MAX);
        let cutoff_ns = now_ns.saturating_sub(expiry_ns);
        let idle = |e: &SensorEntry| {
            !e.is_calibrated() && e.counters.last_seen_ns.load(Relaxed) < cutoff_ns
        };
        let stale: Vec<SensorId> = self
            .read()
            .values()
            .filter(|e| idle(e))
            .map(|e| e.id.clone())
            .collect();
        if stale.is_empty() {
            return 0;
        }
        let mut map = self.write();
        let mut n = 0;
        for id in stale {
            // Checked again: the sensor may have spoken or been calibrated meanwhile.
            if map.get(&id).is_some_and(|e| idle(e)) {
                if let Some(e) = map.remove(&id) {
                    e.evicted.store(true, Relaxed);
                    n += 1;
                }
            }
        }
        if map.capacity() > 4 * map.len().max(1024) {
            map.shrink_to_fit();
        }
        drop(map);
        // Lock order, as in `seen`: the map, then the probation queue.
        let map = self.read();
        let mut probation = self.probation.lock().unwrap_or_else(|p| p.into_inner());
        probation.retain(|id| map.contains_key(id));
        if probation.capacity() > 4 * probation.len().max(1024) {
            probation.shrink_to_fit();
        }
        self.admission.expired.fetch_add(n as u64, Relaxed);
        n
    }

    /// Puts `corrector` in force for its sensor from the next batch on, with what the health
    /// checks take from its record ([`SensorTable::health_seed`]); returns the version it
    /// replaced. The caller has already made the record durable.
    pub fn install(&self, corrector: Corrector, health: HealthSeed) -> Option<u64> {
        let entry = self.entry(corrector.sensor_id());
        // The seed first: a worker that sees the new corrector finds its monitor.
        *lock(&entry.health_seed) = health.monitor.map(Box::new);
        if let Some(record) = health.record {
            for pair in self.pairs.of(corrector.sensor_id()) {
                pair.set_record(record.clone());
            }
        }
        let old = entry.corrector.swap(Some(Arc::new(corrector)));
        old.map(|c| c.version())
    }

    /// What the health checks take from `record`, loaded as `corrector`: its monitor (none
    /// when health checks are off or the record cannot be judged: logged, and the sensor is
    /// corrected all the same), and the record itself if the sensor is in a co-located pair.
    pub fn health_seed(&self, record: &CalibrationRecord, corrector: &Corrector) -> HealthSeed {
        let Some(settings) = self.config.health.as_ref() else {
            return HealthSeed::default();
        };
        // The sensor's pairs share its false-alarm budget.
        let checks = triax_health::HealthConfig {
            colocated_pairs: self.pairs.pairs_of(&record.sensor_id) as u32,
            ..settings.checks.clone()
        };
        let monitor = match SensorHealth::with_corrector(record, corrector, &checks) {
            Ok(h) => Some(h),
            Err(e) => {
                tracing::error!(sensor = %record.sensor_id, version = record.version, cause = %e,
                    "no health checks for this record");
                None
            }
        };
        let paired = !self.pairs.of(&record.sensor_id).is_empty();
        HealthSeed {
            monitor,
            record: paired.then(|| Arc::new(record.clone())),
        }
    }

    /// The co-located pairs `sensor` is in.
    pub fn groups_of(&self, sensor: &SensorId) -> Vec<Arc<GroupSlot>> {
        self.pairs.of(sensor).to_vec()
    }

    /// Versions in force, for catch-up requests.
    pub fn versions(&self) -> Vec<(SensorId, u64)> {
        let mut v: Vec<_> = self
            .read()
            .values()
            .filter_map(|e| e.calibration_version().map(|v| (e.id.clone(), v)))
            .collect();
        v.sort();
        v
    }

    /// A snapshot of every entry, sorted by id; the lock is released before returning.
    pub fn snapshot(&self) -> Vec<Arc<SensorEntry>> {
        let mut v: Vec<_> = self.read().values().cloned().collect();
        v.sort_by(|a, b| a.id.cmp(&b.id));
        v
    }

    /// The settings a sensor has (or would have, if it came online).
    pub fn settings_of(&self, id: &SensorId) -> SensorSettings {
        self.config.sensor(id.as_str()).clone()
    }

    pub fn unknown_sensor_expiry(&self) -> std::time::Duration {
        self.config.unknown_sensor_expiry
    }

    pub fn max_sensors(&self) -> usize {
        self.config.max_sensors
    }

    pub fn len(&self) -> usize {
        self.read().len()
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    fn read(&self) -> std::sync::RwLockReadGuard<'_, HashMap<SensorId, Arc<SensorEntry>>> {
        // A panic while holding the lock leaves the map itself consistent (every mutation is a
        // single insert or remove), so a poisoned lock is safe to keep using.
        self.sensors.read().unwrap_or_else(|p| p.into_inner())
    }

    fn write(&self) -> std::sync::RwLockWriteGuard<'_, HashMap<SensorId, Arc<SensorEntry>>> {
        // As for `read`.
        self.sensors.write().unwrap_or_else(|p| p.into_inner())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use triax_protocol::record::sample;

    #[test]
    fn install_swaps_and_reports_the_old_version() {
        let t = SensorTable::new(Arc::new(Config::for_tests(
            "b",
            std::path::Path::new("/nonexistent"),
            vec![],
        )));
        let id = SensorId::new("s").unwrap();
        let e = t.entry(&id);
        assert!(e.corrector().is_none());
        assert_eq!(e.status().mode, Mode::None);
        let c1 = Corrector::from_record(&sample::record("s", 1)).unwrap();
        assert_eq!(t.install(c1, HealthSeed::default()), None);
        let held = e.corrector().unwrap();
        let c2 = Corrector::from_record(&sample::record("s", 2)).unwrap();
        assert_eq!(t.install(c2, HealthSeed::default()), Some(1));
        assert_eq!(held.version(), 1, "a batch in flight keeps its snapshot");
        assert_eq!(e.calibration_version(), Some(2));
        assert_eq!(t.versions(), [(id, 2)]);
    }

    fn table(max_sensors: usize) -> SensorTable {
        let mut config = Config::for_tests("b", std::path::Path::new("/nonexistent"), vec![]);
        config.max_sensors = max_sensors;
        SensorTable::new(Arc::new(config))
    }

    fn id(s: &str) -> SensorId {
        SensorId::new(s).unwrap()
    }

    /// What the worker does with a batch: counts it.
    fn batch(t: &SensorTable, s: &str) -> Option<Arc<SensorEntry>> {
        let e = t.seen(&id(s))?;
        e.counters.batches.fetch_add(1, Relaxed);
        Some(e)
    }

    #[test]
    fn the_table_is_bounded_for_unknown_sensors_only() {
        let t = table(2);
        // Established: each sent two batches.
        for s in ["a", "b", "a", "b"] {
            assert!(batch(&t, s).is_some());
        }
        assert!(batch(&t, "c").is_none(), "a third unknown id is refused");
        assert!(batch(&t, "a").is_some(), "known ids still pass");
        // A calibration always gets its entry: it comes signed from the lab.
        t.install(
            Corrector::from_record(&sample::record("c", 1)).unwrap(),
            HealthSeed::default(),
        );
        assert_eq!(t.len(), 3);
        assert!(t.seen(&id("c")).is_some());
    }

    #[test]
    fn a_flood_of_one_batch_ids_cannot_lock_out_a_real_node() {
        let t = table(100);
        t.install(
            Corrector::from_record(&sample::record("cal", 1)).unwrap(),
            HealthSeed::default(),
        );
        let mut real_node_batches = 0;
        for i in 0..10_000 {
            assert!(batch(&t, &format!("flood-{i}")).is_some(), "flood id {i}");
            // The real node sends every 50th flood batch, from the middle of the flood on.
            if i >= 5_000 && i % 50 == 0 {
                let e = batch(&t, "real-node").expect("a real node always gets through");
                real_node_batches += 1;
                assert_eq!(
                    e.counters.batches.load(Relaxed),
                    real_node_batches,
                    "established, the real node keeps its counters"
                );
            }
            assert!(t.len() <= 100);
        }
        assert!(t.seen(&id("cal")).is_some_and(|e| e.is_calibrated()));
        let displaced = t.admission.displaced.load(Relaxed);
        assert_eq!(t.admission.admitted.load(Relaxed), 10_001);
        assert_eq!(
            displaced,
            10_001 + 1 - 100,
            "admitted + calibrated − capacity"
        );
    }

    #[test]
    fn displaced_and_expired_entries_are_marked_for_their_holders() {
        let t = table(1);
        let first = t.seen(&id("x")).unwrap();
        let second = t.seen(&id("y")).unwrap();
        assert!(first.is_evicted(), "x gave its place to y");
        assert!(!second.is_evicted());
        let now = now_ns();
        assert_eq!(t.expire_idle(now), 0, "y just arrived");
        let later = now + t.config.unknown_sensor_expiry.as_nanos() as i64 + 1;
        assert_eq!(t.expire_idle(later), 1);
        assert!(second.is_evicted());
        assert!(t.is_empty());
        assert_eq!(t.admission.expired.load(Relaxed), 1);
        // A calibrated sensor is never forgotten.
        t.install(
            Corrector::from_record(&sample::record("z", 1)).unwrap(),
            HealthSeed::default(),
        );
        assert_eq!(t.expire_idle(i64::MAX), 0);
        assert_eq!(t.len(), 1);
    }
}
