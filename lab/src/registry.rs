//! The lab's registry: every record the lab has issued, and which buildings each sensor is
//! assigned to. `triax-lab push` writes it, `triax-lab serve` answers catch-up requests from it.
//!
//! A registry is a directory:
//!
//! ```text
//! DIR/store/              a calibration store (triax-calibration-store): every version of
//!                         every sensor, validated, versions only increasing, durable
//! DIR/assignments.json    {"format_version": 1, "sensors": {"acc-01": ["hq"], …}}
//! ```
//!
//! Records are kept unsigned; the registry server signs each one with the lab key when it serves
//! it (see `serve`). Ed25519 signatures are deterministic, so a record served on catch-up is
//! byte for byte the envelope that was pushed.
//!
//! **Assignment.** A sensor is served to a building only if it is assigned to it. `push
//! --building B` adds B to the assignment of each sensor it pushes; it never removes one and
//! never touches another building's sensors, so a push for A cannot change what B receives.
//! `assign` replaces a sensor's buildings (a sensor that moved). Sensor ids are unique across the
//! registry (PROTOCOL.md §1), so one map from sensor to buildings is enough.
//!
//! **Sharing.** The store's directory lock is the registry's lock. Every operation opens the
//! registry, does its work and closes it, waiting a few seconds if another process holds it, so
//! `serve` and `push` can run side by side on one machine. The assignment file is replaced
//! atomically (written aside, synced, renamed, directory synced) while the lock is held.
//!
//! Nothing here is async: callers on a runtime use `spawn_blocking`.

use std::collections::{BTreeMap, BTreeSet};
use std::io::Write;
use std::path::{Path, PathBuf};
use std::time::Duration;

use serde::{Deserialize, Serialize};
use triax_calibration_store::{PutOutcome, Rejection, Store, StoreError};
use triax_protocol::record::CalibrationRecord;
use triax_protocol::{BuildingId, SensorId};

/// Name of the store directory inside a registry.
pub const STORE_DIR: &str = "store";
/// Name of the assignment file inside a registry.
pub const ASSIGNMENTS_FILE: &str = "assignments.json";

/// How long an operation waits for another process to release the registry.
const LOCK_WAIT: Duration = Duration::from_secs(10);

/// Why a registry operation failed.
#[derive(Debug, thiserror::Error)]
pub enum RegistryError {
    #[error("registry {dir}: {source}")]
    Store {
        dir: PathBuf,
        #[source]
        source: StoreError,
    },
    #[error("registry {path}: {action}: {source}")]
    File {
        path: PathBuf,
        action: &'static str,
        #[source]
        source: std::io::Error,
    },
    #[error("registry {path}: {problem}")]
    Assignments { path: PathBuf, problem: String },
}

/// Which buildings each sensor is assigned to.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Assignments {
    pub format_version: u32,
    pub sensors: BTreeMap<SensorId, BTreeSet<BuildingId>>,
}

impl Assignments {
    /// Sensors assigned to `building`.
    pub fn sensors_of(&self, building: &BuildingId) -> BTreeSet<SensorId> {
        self.sensors
            .iter()
            .filter(|(_, b)| b.contains(building))
            .map(|(s, _)| s.clone())
            .collect()
    }
}

/// What the registry did with a record given to [`Registry::record`].
#[derive(Debug, Clone, PartialEq)]
pub enum Recorded {
    /// Stored now, or already stored with identical content; assigned to the buildings.
    Accepted { already_stored: bool },
    /// Refused by the store's rules (invalid, stale, or a used version with other content);
    /// not assigned anywhere.
    Refused(Rejection),
}

/// A registry directory. Cheap: it holds only the path; each operation opens and closes.
#[derive(Debug, Clone)]
pub struct Registry {
    dir: PathBuf,
}

impl Registry {
    pub fn new(dir: impl Into<PathBuf>) -> Registry {
        Registry { dir: dir.into() }
    }

    pub fn dir(&self) -> &Path {
        &self.dir
    }

    fn assignments_path(&self) -> PathBuf {
        self.dir.join(ASSIGNMENTS_FILE)
    }

    fn store_err(&self) -> impl FnOnce(StoreError) -> RegistryError + '_ {
        move |source| RegistryError::Store {
            dir: self.dir.clone(),
            source,
        }
    }

    /// Opens the store, waiting while another process holds it.
    fn open(&self) -> Result<Store, RegistryError> {
        let path = self.dir.join(STORE_DIR);
        std::fs::create_dir_all(&path).map_err(|source| RegistryError::File {
            path: path.clone(),
            action: "create directory",
            source,
        })?;
        // Holders keep the registry for one operation only: worth waiting for.
        Store::open_waiting(&path, LOCK_WAIT).map_err(self.store_err())
    }

    /// The assignment file, or no assignments if it does not exist yet. Call with the store
    /// open (the lock held).
    fn read_assignments(&self) -> Result<Assignments, RegistryError> {
        let path = self.assignments_path();
        let text = match std::fs::read(&path) {
            Ok(t) => t,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
                return Ok(Assignments {
                    format_version: 1,
                    sensors: BTreeMap::new(),
                })
            }
            Err(source) => {
                return Err(RegistryError::File {
                    path,
                    action: "read",
                    source,
                })
            }
        };
        let a: Assignments =
            serde_json::from_slice(&text).map_err(|e| RegistryError::Assignments {
                path: path.clone(),
                problem: e.to_string(),
            })?;
        if a.format_version != 1 {
            return Err(RegistryError::Assignments {
                path,
                problem: format!(
                    "format_version {} is not supported; this build reads 1",
                    a.format_version
                ),
            });
        }
        Ok(a)
    }

    /// Replaces the assignment file atomically. Call with the store open (the lock held).
    fn write_assignments(&self, a: &Assignments) -> Result<(), RegistryError> {
        let path = self.assignments_path();
        let tmp = self.dir.join(format!("{ASSIGNMENTS_FILE}.tmp"));
        let file_err = |path: &Path, action| {
            let path = path.to_owned();
            move |source| RegistryError::File {
                path,
                action,
                source,
            }
        };
        // A map of ids to sets of ids always serialises.
        let mut bytes = serde_json::to_vec_pretty(a).expect("assignments serialise");
        bytes.push(b'\n');
        let mut f = std::fs::File::create(&tmp).map_err(file_err(&tmp, "create"))?;
        f.write_all(&bytes).map_err(file_err(&tmp, "write"))?;
        f.sync_all().map_err(file_err(&tmp, "sync"))?;
        std::fs::rename(&tmp, &path).map_err(file_err(&path, "rename into"))?;
        std::fs::File::open(&self.dir)
            .and_then(|d| d.sync_all())
            .map_err(file_err(&self.dir, "sync directory"))?;
        Ok(())
    }

    /// Stores `records` (each sensor's in increasing version order) and assigns the sensor of
    /// each accepted one to every building in `buildings`. Returns once all of it is durable.
    pub fn record(
        &self,
        records: &[CalibrationRecord],
        buildings: &[BuildingId],
    ) -> Result<Vec<Recorded>, RegistryError> {
        let store = self.open()?;
        let outcomes = store.put_all(records).map_err(self.store_err())?;
        let mut assignments = self.read_assignments()?;
        let mut changed = false;
        let mut out = Vec::with_capacity(outcomes.len());
        for (record, outcome) in records.iter().zip(outcomes) {
            match outcome {
                Ok(o) => {
                    let set = assignments
                        .sensors
                        .entry(record.sensor_id.clone())
                        .or_default();
                    for b in buildings {
                        changed |= set.insert(b.clone());
                    }
                    out.push(Recorded::Accepted {
                        already_stored: o == PutOutcome::AlreadyStored,
                    });
                }
                Err(r) => out.push(Recorded::Refused(r)),
            }
        }
        if changed {
            self.write_assignments(&assignments)?;
        }
        Ok(out)
    }

    /// Sets the buildings of `sensor` (none: unassigned, served to nobody). Returns the
    /// previous ones.
    pub fn assign(
        &self,
        sensor: &SensorId,
        buildings: &[BuildingId],
    ) -> Result<BTreeSet<BuildingId>, RegistryError> {
        let _store = self.open()?;
        let mut a = self.read_assignments()?;
        let new: BTreeSet<BuildingId> = buildings.iter().cloned().collect();
        let old = if new.is_empty() {
            a.sensors.remove(sensor)
        } else {
            a.sensors.insert(sensor.clone(), new)
        };
        self.write_assignments(&a)?;
        Ok(old.unwrap_or_default())
    }

    /// Every assignment.
    pub fn assignments(&self) -> Result<Assignments, RegistryError> {
        let _store = self.open()?;
        self.read_assignments()
    }

    /// The records of `building`'s sensors newer than `have` (see
    /// [`Store::newer_than`]): sorted by sensor, then version.
    pub fn newer_for(
        &self,
        building: &BuildingId,
        have: &BTreeMap<SensorId, u64>,
    ) -> Result<Vec<CalibrationRecord>, RegistryError> {
        let store = self.open()?;
        let sensors = self.read_assignments()?.sensors_of(building);
        if sensors.is_empty() {
            return Ok(Vec::new());
        }
        let scan = store.newer_than(have).map_err(self.store_err())?;
        for skipped in &scan.skipped {
            tracing::error!(entry = %skipped, "registry entry unreadable: not served");
        }
        Ok(scan
            .value
            .into_iter()
            .filter(|r| sensors.contains(&r.sensor_id))
            .collect())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use triax_protocol::record::sample;

    fn b(id: &str) -> BuildingId {
        BuildingId::new(id).unwrap()
    }

    #[test]
    fn buildings_see_only_their_sensors() {
        let dir = tempfile::tempdir().unwrap();
        let reg = Registry::new(dir.path());
        let r1 = sample::record("s1", 1);
        let r2 = sample::record("s2", 1);
        assert_eq!(
            reg.record(std::slice::from_ref(&r1), &[b("A")]).unwrap(),
            [Recorded::Accepted {
                already_stored: false
            }]
        );
        reg.record(std::slice::from_ref(&r2), &[b("B")]).unwrap();
        let none = BTreeMap::new();
        assert_eq!(
            reg.newer_for(&b("A"), &none).unwrap(),
            std::slice::from_ref(&r1)
        );
        assert_eq!(
            reg.newer_for(&b("B"), &none).unwrap(),
            std::slice::from_ref(&r2)
        );
        assert!(reg.newer_for(&b("C"), &none).unwrap().is_empty());

        // A newer record pushed to A leaves B's answer unchanged.
        let r1v2 = sample::record("s1", 2);
        reg.record(std::slice::from_ref(&r1v2), &[b("A")]).unwrap();
        assert_eq!(reg.newer_for(&b("B"), &none).unwrap(), [r2]);
        let have = BTreeMap::from([(r1.sensor_id.clone(), 1)]);
        assert_eq!(reg.newer_for(&b("A"), &have).unwrap(), [r1v2]);

        // Refused records are reported and assign nothing.
        let out = reg.record(&[sample::record("s3", 1)], &[]).unwrap();
        assert!(matches!(out[0], Recorded::Accepted { .. }));
        let out = reg.record(std::slice::from_ref(&r1), &[b("C")]).unwrap();
        assert_eq!(
            out,
            [Recorded::Accepted {
                already_stored: true
            }]
        );
        let mut changed = r1;
        changed.dynamic.offset[0] += 1.0;
        let out = reg.record(&[changed], &[b("D")]).unwrap();
        assert!(matches!(
            out[0],
            Recorded::Refused(Rejection::Conflict { .. })
        ));
        let a = reg.assignments().unwrap();
        assert!(!a
            .sensors_of(&b("D"))
            .contains(&SensorId::new("s1").unwrap()));

        // A sensor that moved.
        let s1 = SensorId::new("s1").unwrap();
        let old = reg.assign(&s1, &[b("B")]).unwrap();
        assert_eq!(old, BTreeSet::from([b("A"), b("C")]));
        assert_eq!(reg.newer_for(&b("A"), &none).unwrap(), []);
        assert_eq!(reg.newer_for(&b("B"), &none).unwrap().len(), 3);
    }
}
