//! What the field health checks keep outside a sensor's worker: the seed a record brings when
//! it is installed (its monitor, handed to the worker through the sensor's entry) and the
//! co-located pairs, each shared by the workers of its two sensors. The per-batch feed is the
//! sample path's (`sample_path::health`), the health queryable a service
//! (`services::health`).

use std::collections::HashMap;
use std::sync::{Arc, Mutex};

use triax_health::colocated::{ColocatedPair, PairConfig};
use triax_health::report::TestReport;
use triax_health::SensorHealth;
use triax_protocol::record::CalibrationRecord;
use triax_protocol::SensorId;

use crate::config::ColocatedSettings;

/// What a record brings to the health checks when it is installed: its sensor's monitor, and
/// the record itself when the sensor is in a co-located pair (the pair's check needs both
/// records; the gateway keeps no other record in memory).
#[derive(Debug, Default)]
pub struct HealthSeed {
    pub monitor: Option<SensorHealth>,
    pub record: Option<Arc<CalibrationRecord>>,
}

/// One declared co-located pair, shared by the workers of its two sensors.
#[derive(Debug)]
pub struct PairSlot {
    pub a: SensorId,
    pub b: SensorId,
    config: PairConfig,
    state: Mutex<PairState>,
}

#[derive(Debug, Default)]
struct PairState {
    /// The records in force of A and B.
    records: [Option<Arc<CalibrationRecord>>; 2],
    /// The check for those two records; made when both are known.
    pair: Option<ColocatedPair>,
    /// The records' versions the check was refused for (logged once).
    refused: Option<(u64, u64)>,
}

/// A pair's tests as one of its sensors reports them.
#[derive(Debug, Clone)]
pub struct PairTests {
    pub peer: SensorId,
    pub absolute: [TestReport; 3],
    pub relative: [TestReport; 3],
}

impl PairSlot {
    fn lock(&self) -> std::sync::MutexGuard<'_, PairState> {
        // Replaced whole or fed a batch at a time: a consistent pair after any panic.
        self.state.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Which side `sensor` is: 0 for A, 1 for B.
    fn side(&self, sensor: &SensorId) -> usize {
        usize::from(sensor == &self.b)
    }

    /// A new record of one of the two sensors: the pair's check starts afresh.
    pub fn set_record(&self, record: Arc<CalibrationRecord>) {
        let side = self.side(&record.sensor_id);
        let mut s = self.lock();
        s.records[side] = Some(record);
        s.pair = None;
    }

    /// Feeds `sensor`'s corrected readings of a batch corrected with `version`.
    pub fn feed(
        &self,
        sensor: &SensorId,
        version: u64,
        timestamp_ns: i64,
        sample_rate_hz: f64,
        accel_mps2: &[[f64; 3]],
    ) {
        let side = self.side(sensor);
        let mut s = self.lock();
        if s.records[side].as_ref().map(|r| r.version) != Some(version) {
            return;
        }
        let Some(pair) = self.ready(&mut s) else {
            return;
        };
        if side == 0 {
            pair.feed_a(timestamp_ns, sample_rate_hz, accel_mps2);
        } else {
            pair.feed_b(timestamp_ns, sample_rate_hz, accel_mps2);
        }
    }

    /// The pair's check for the records in force, made on first need.
    fn ready<'s>(&self, s: &'s mut PairState) -> Option<&'s mut ColocatedPair> {
        if s.pair.is_none() {
            let (Some(ra), Some(rb)) = (&s.records[0], &s.records[1]) else {
                return None;
            };
            let versions = (ra.version, rb.version);
            if s.refused == Some(versions) {
                return None;
            }
            match ColocatedPair::new(ra, rb, &self.config) {
                Ok(p) => s.pair = Some(p),
                Err(e) => {
                    tracing::error!(a = %self.a, b = %self.b, cause = %e,
                        "no co-located check for this pair's records");
                    s.refused = Some(versions);
                    return None;
                }
            }
        }
        s.pair.as_mut()
    }

    /// The pair's tests for `sensor`'s report, when its record `version` is the one judged.
    pub fn tests_for(&self, sensor: &SensorId, version: u64) -> Option<PairTests> {
        let side = self.side(sensor);
        let s = self.lock();
        if s.records[side].as_ref().map(|r| r.version) != Some(version) {
            return None;
        }
        let pair = s.pair.as_ref()?;
        Some(PairTests {
            peer: if side == 0 {
                self.b.clone()
            } else {
                self.a.clone()
            },
            absolute: pair.absolute_report(),
            relative: pair.relative_report(),
        })
    }
}

/// Every declared pair, by sensor.
#[derive(Debug, Default)]
pub struct Pairs {
    by_sensor: HashMap<SensorId, Vec<Arc<PairSlot>>>,
}

impl Pairs {
    pub fn new(settings: &[ColocatedSettings]) -> Pairs {
        let mut by_sensor: HashMap<SensorId, Vec<Arc<PairSlot>>> = HashMap::new();
        for p in settings {
            let slot = Arc::new(PairSlot {
                a: p.a.clone(),
                b: p.b.clone(),
                config: p.pair.clone(),
                state: Mutex::new(PairState::default()),
            });
            for id in [&p.a, &p.b] {
                by_sensor.entry(id.clone()).or_default().push(slot.clone());
            }
        }
        Pairs { by_sensor }
    }

    /// The pairs `sensor` is in.
    pub fn of(&self, sensor: &SensorId) -> &[Arc<PairSlot>] {
        self.by_sensor.get(sensor).map_or(&[], Vec::as_slice)
    }
}
