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
//! The table's own lock guards only membership (a sensor appearing), and is never held across an
//! await.

use std::collections::HashMap;
use std::sync::atomic::{AtomicI64, AtomicU64, AtomicUsize, Ordering::Relaxed};
use std::sync::{Arc, RwLock};

use arc_swap::ArcSwapOption;
use time::OffsetDateTime;
use triax_calibration::corrector::Corrector;
use triax_protocol::messages::SensorStatus;
use triax_protocol::{Mode, SensorId};

use crate::config::{Config, SensorSettings};

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
}

/// One sensor as the gateway knows it.
#[derive(Debug)]
pub struct SensorEntry {
    pub id: SensorId,
    pub settings: SensorSettings,
    corrector: ArcSwapOption<Corrector>,
    pub counters: SensorCounters,
}

impl SensorEntry {
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
        let version = self.calibration_version();
        SensorStatus {
            sensor_id: self.id.clone(),
            last_seen: (last != 0)
                .then(|| OffsetDateTime::from_unix_timestamp_nanos(i128::from(last)).ok())
                .flatten(),
            batches: c.batches.load(Relaxed),
            samples: c.samples.load(Relaxed),
            gaps: c.gaps.load(Relaxed),
            missing_batches: c.missing_batches.load(Relaxed),
            duplicates: c.duplicates.load(Relaxed),
            rejects: c.rejects.load(Relaxed),
            flagged_samples: c.flagged_samples.load(Relaxed),
            calibration_version: version,
            mode: if version.is_some() {
                self.settings.mode.wire()
            } else {
                Mode::None
            },
        }
    }
}

/// Every sensor known to the gateway: loaded from the store, or seen on the network.
#[derive(Debug)]
pub struct SensorTable {
    config: Arc<Config>,
    sensors: RwLock<HashMap<SensorId, Arc<SensorEntry>>>,
}

impl SensorTable {
    pub fn new(config: Arc<Config>) -> SensorTable {
        SensorTable {
            config,
            sensors: RwLock::new(HashMap::new()),
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
        let mut map = self.sensors.write().unwrap_or_else(|p| p.into_inner());
        map.entry(id.clone())
            .or_insert_with(|| {
                Arc::new(SensorEntry {
                    id: id.clone(),
                    settings: self.config.sensor(id.as_str()).clone(),
                    corrector: ArcSwapOption::empty(),
                    counters: SensorCounters::default(),
                })
            })
            .clone()
    }

    /// The entry of a sensor seen on the network: created on first sight while the table holds
    /// fewer than `max_sensors`; none for a new id past that bound. Calibrated sensors always
    /// have their entry (made by [`install`](Self::install)).
    pub fn seen(&self, id: &SensorId) -> Option<Arc<SensorEntry>> {
        if let Some(e) = self.get(id) {
            return Some(e);
        }
        (self.len() < self.config.max_sensors).then(|| self.entry(id))
    }

    /// Puts `corrector` in force for its sensor from the next batch on; returns the version it
    /// replaced. The caller has already made the record durable.
    pub fn install(&self, corrector: Corrector) -> Option<u64> {
        let entry = self.entry(corrector.sensor_id());
        let old = entry.corrector.swap(Some(Arc::new(corrector)));
        old.map(|c| c.version())
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
        // single insert), so a poisoned lock is safe to keep using.
        self.sensors.read().unwrap_or_else(|p| p.into_inner())
    }
}

/// Gateway-wide counters.
#[derive(Debug, Default)]
pub struct GatewayCounters {
    /// Raw payloads taken from Zenoh, before any check. Each is then corrected and published,
    /// skipped and counted (`malformed`, `over_capacity`), or dropped and counted (`dropped`).
    pub received_batches: AtomicU64,
    /// Payloads that did not decode, on any key.
    pub malformed: AtomicU64,
    /// Raw batches dropped from a full queue (drop-oldest); shared with the inboxes.
    pub dropped: Arc<AtomicU64>,
    pub published_batches: AtomicU64,
    pub publish_errors: AtomicU64,
    pub tilt_samples: AtomicU64,
    pub pushes_accepted: AtomicU64,
    pub pushes_refused: AtomicU64,
    /// Raw batches skipped because they came from a new sensor id past `max_sensors`.
    pub over_capacity: AtomicU64,
    /// Sensors whose stream a worker has taken on since start (each holds its correction state
    /// and its publisher keys).
    pub sensors_online: AtomicU64,
    /// Keys declared to Zenoh, raw and output (at most `declared_keys_max`).
    pub declared_keys: AtomicUsize,
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
        assert_eq!(t.install(c1), None);
        let held = e.corrector().unwrap();
        let c2 = Corrector::from_record(&sample::record("s", 2)).unwrap();
        assert_eq!(t.install(c2), Some(1));
        assert_eq!(held.version(), 1, "a batch in flight keeps its snapshot");
        assert_eq!(e.calibration_version(), Some(2));
        assert_eq!(t.versions(), [(id, 2)]);
    }

    #[test]
    fn the_table_is_bounded_for_unknown_sensors_only() {
        let mut config = Config::for_tests("b", std::path::Path::new("/nonexistent"), vec![]);
        config.max_sensors = 2;
        let t = SensorTable::new(Arc::new(config));
        let id = |s: &str| SensorId::new(s).unwrap();
        assert!(t.seen(&id("a")).is_some());
        assert!(t.seen(&id("b")).is_some());
        assert!(t.seen(&id("c")).is_none(), "a third unknown id is refused");
        assert!(t.seen(&id("a")).is_some(), "known ids still pass");
        // A calibration always gets its entry: it comes signed from the lab.
        t.install(Corrector::from_record(&sample::record("c", 1)).unwrap());
        assert_eq!(t.len(), 3);
        assert!(t.seen(&id("c")).is_some());
    }
}
