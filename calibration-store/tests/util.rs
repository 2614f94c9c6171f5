//! Helpers shared by the integration tests.

use std::path::Path;

use tempfile::TempDir;
use triax_calibration_store::Store;
use triax_protocol::record::{sample, CalibrationRecord};
use triax_protocol::SensorId;

pub fn id(s: &str) -> SensorId {
    SensorId::new(s).unwrap()
}

/// A valid record whose content depends on sensor and version, so that a record read back
/// under the wrong key or with stale bytes would not compare equal.
pub fn record(sensor: &str, version: u64) -> CalibrationRecord {
    let mut r = sample::record(sensor, version);
    r.certificate.notes = Some(format!("{sensor} version {version}"));
    r.static_set.offset[0] += version as f64 * 1e-3;
    r
}

pub fn new_store() -> (TempDir, Store) {
    let dir = tempfile::tempdir().unwrap();
    let store = Store::open(dir.path()).unwrap();
    (dir, store)
}

/// Record key as documented in the crate's `keys` module: id, 0x00, big-endian version.
pub fn raw_record_key(sensor: &str, version: u64) -> Vec<u8> {
    let mut key = sensor.as_bytes().to_vec();
    key.push(0);
    key.extend_from_slice(&version.to_be_bytes());
    key
}

/// Writes bytes straight into a tree of a closed store, bypassing every rule.
pub fn write_raw(path: &Path, tree: &str, key: &[u8], value: &[u8]) {
    let db = open_raw(path);
    db.open_tree(tree).unwrap().insert(key, value).unwrap();
    db.flush().unwrap();
}

/// Opens the sled database under a store, waiting while the store that just closed still holds
/// its lock (sled releases it from a background thread, as `Store::open` knows).
pub fn open_raw(path: &Path) -> sled::Db {
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(10);
    loop {
        match sled::open(path) {
            Ok(db) => return db,
            Err(e)
                if e.to_string().contains("could not acquire lock")
                    && std::time::Instant::now() < deadline =>
            {
                std::thread::sleep(std::time::Duration::from_millis(20))
            }
            Err(e) => panic!("cannot open {}: {e}", path.display()),
        }
    }
}
