//! What the field health checks keep outside a sensor's worker: the seed a record brings when
//! it is installed (its monitor, handed to the worker through the sensor's entry) and the
//! co-located groups (pairs, and groups of three), each shared by the workers of its sensors. The per-batch feed is the
//! sample path's (`sample_path::health`), the health queryable a service
//! (`services::health`).

use std::collections::HashMap;
use std::sync::{Arc, Mutex};

use triax_health::colocated::{ColocatedPair, PairConfig};
use triax_health::huddle::{ColocatedTriple, TripleConfig};
use triax_health::report::TestReport;
use triax_health::SensorHealth;
use triax_protocol::record::CalibrationRecord;
use triax_protocol::SensorId;

use crate::config::{ColocatedSettings, TripleSettings};

/// What a record brings to the health checks when it is installed: its sensor's monitor, and
/// the record itself when the sensor is in a co-located pair (the pair's check needs both
/// records; the gateway keeps no other record in memory).
#[derive(Debug, Default)]
pub struct HealthSeed {
    pub monitor: Option<SensorHealth>,
    pub record: Option<Arc<CalibrationRecord>>,
}

/// One declared group of co-located sensors, a pair or three, shared by the workers of its
/// sensors.
#[derive(Debug)]
pub struct GroupSlot {
    /// A, B (and C).
    members: Vec<SensorId>,
    kind: GroupKind,
    state: Mutex<GroupState>,
}

#[derive(Debug, Clone)]
enum GroupKind {
    Pair(PairConfig),
    Triple(TripleConfig),
}

#[derive(Debug)]
enum Check {
    Pair(Box<ColocatedPair>),
    Triple(Box<ColocatedTriple>),
}

#[derive(Debug, Default)]
struct GroupState {
    /// The records in force of the members.
    records: [Option<Arc<CalibrationRecord>>; 3],
    /// The check for those records; made when all are known.
    check: Option<Check>,
    /// The records' versions the check was refused for (logged once).
    refused: Option<[u64; 3]>,
}

/// A group's tests as one of its sensors reports them: name, axis, the peer it names, the test.
#[derive(Debug, Clone)]
pub struct GroupTests {
    pub tests: Vec<(&'static str, usize, SensorId, TestReport)>,
}

impl GroupSlot {
    fn lock(&self) -> std::sync::MutexGuard<'_, GroupState> {
        // Replaced whole or fed a batch at a time: a consistent check after any panic.
        self.state.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Which member `sensor` is: 0 for A, 1 for B, 2 for C.
    fn side(&self, sensor: &SensorId) -> usize {
        self.members.iter().position(|m| m == sensor).unwrap_or(0)
    }

    /// A new record of one of the members: the group's check starts afresh.
    pub fn set_record(&self, record: Arc<CalibrationRecord>) {
        let side = self.side(&record.sensor_id);
        let mut s = self.lock();
        s.records[side] = Some(record);
        s.check = None;
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
        match self.ready(&mut s) {
            Some(Check::Pair(pair)) if side == 0 => {
                pair.feed_a(timestamp_ns, sample_rate_hz, accel_mps2)
            }
            Some(Check::Pair(pair)) => pair.feed_b(timestamp_ns, sample_rate_hz, accel_mps2),
            Some(Check::Triple(t)) => t.feed(side, timestamp_ns, sample_rate_hz, accel_mps2),
            None => {}
        }
    }

    /// The group's check for the records in force, made on first need.
    fn ready<'s>(&self, s: &'s mut GroupState) -> Option<&'s mut Check> {
        if s.check.is_none() {
            let n = self.members.len();
            let records: Option<Vec<Arc<CalibrationRecord>>> =
                s.records[..n].iter().cloned().collect();
            let records = records?;
            let mut versions = [0; 3];
            for (v, r) in versions.iter_mut().zip(&records) {
                *v = r.version;
            }
            if s.refused == Some(versions) {
                return None;
            }
            let made = match &self.kind {
                GroupKind::Pair(c) => ColocatedPair::new(&records[0], &records[1], c)
                    .map(|p| Check::Pair(Box::new(p))),
                GroupKind::Triple(c) => {
                    ColocatedTriple::new([&records[0], &records[1], &records[2]], c)
                        .map(|t| Check::Triple(Box::new(t)))
                }
            };
            match made {
                Ok(c) => s.check = Some(c),
                Err(e) => {
                    tracing::error!(members = ?self.members, cause = %e,
                        "no co-located check for this group's records");
                    s.refused = Some(versions);
                    return None;
                }
            }
        }
        s.check.as_mut()
    }

    /// The group's tests for `sensor`'s report, when its record `version` is the one judged:
    /// for a pair, `colocated_absolute` and `colocated_relative` per axis naming the other
    /// sensor; for three, `triple_noise` per axis (naming A, or B for A itself) and, for B and
    /// C, `triple_gain` per axis naming A.
    pub fn tests_for(&self, sensor: &SensorId, version: u64) -> Option<GroupTests> {
        let side = self.side(sensor);
        let s = self.lock();
        if s.records[side].as_ref().map(|r| r.version) != Some(version) {
            return None;
        }
        let mut tests = Vec::new();
        match s.check.as_ref()? {
            Check::Pair(pair) => {
                let peer = self.members[1 - side.min(1)].clone();
                for (name, reports) in [
                    ("colocated_absolute", pair.absolute_report()),
                    ("colocated_relative", pair.relative_report()),
                ] {
                    for (axis, t) in reports.into_iter().enumerate() {
                        tests.push((name, axis, peer.clone(), t));
                    }
                }
            }
            Check::Triple(t) => {
                let peer = self.members[usize::from(side == 0)].clone();
                for (axis, r) in t.noise_report(side).into_iter().enumerate() {
                    tests.push(("triple_noise", axis, peer.clone(), r));
                }
                if side > 0 {
                    for (axis, r) in t.gain_report(side).into_iter().enumerate() {
                        tests.push(("triple_gain", axis, self.members[0].clone(), r));
                    }
                }
            }
        }
        Some(GroupTests { tests })
    }
}

/// Every declared group, by sensor.
#[derive(Debug, Default)]
pub struct Groups {
    by_sensor: HashMap<SensorId, Vec<Arc<GroupSlot>>>,
}

impl Groups {
    pub fn new(pairs: &[ColocatedSettings], triples: &[TripleSettings]) -> Groups {
        let mut by_sensor: HashMap<SensorId, Vec<Arc<GroupSlot>>> = HashMap::new();
        let slots = pairs
            .iter()
            .map(|p| GroupSlot {
                members: vec![p.a.clone(), p.b.clone()],
                kind: GroupKind::Pair(p.pair.clone()),
                state: Mutex::new(GroupState::default()),
            })
            .chain(triples.iter().map(|t| GroupSlot {
                members: t.sensors.to_vec(),
                kind: GroupKind::Triple(t.triple.clone()),
                state: Mutex::new(GroupState::default()),
            }));
        for slot in slots {
            let slot = Arc::new(slot);
            for id in &slot.members {
                by_sensor.entry(id.clone()).or_default().push(slot.clone());
            }
        }
        Groups { by_sensor }
    }

    /// The groups `sensor` is in.
    pub fn of(&self, sensor: &SensorId) -> &[Arc<GroupSlot>] {
        self.by_sensor.get(sensor).map_or(&[], Vec::as_slice)
    }

    /// The co-located pairs `sensor` is in: their tests share its false-alarm budget.
    pub fn pairs_of(&self, sensor: &SensorId) -> usize {
        self.of(sensor)
            .iter()
            .filter(|g| matches!(g.kind, GroupKind::Pair(_)))
            .count()
    }
}
