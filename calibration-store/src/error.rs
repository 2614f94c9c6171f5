//! What can go wrong, in two layers, as sled does for compare-and-swap.
//!
//! [`StoreError`] is fail-stop: the disk, the lock, the schema, an entry that cannot be read.
//! [`Rejection`] is an expected answer to a `put` (the record is invalid, stale or conflicting)
//! that the caller reports to whoever sent the record and then carries on. `put` returns
//! `Result<Result<PutOutcome, Rejection>, StoreError>` so that `?` propagates only the first.

use std::fmt;
use std::io;
use std::path::PathBuf;

use triax_calibration::corrector::LoadError;
use triax_protocol::SensorId;

/// A failure of the store itself.
#[derive(Debug, thiserror::Error)]
pub enum StoreError {
    #[error(
        "calibration store at {path} is in use by another process (a running gateway or lab \
         holds it open); stop that process or work on an export"
    )]
    Locked { path: PathBuf },
    #[error(
        "calibration store at {path} has schema version {found}, written by a newer Triax; this \
         build reads schema version {supported} only: upgrade this program, or export the store \
         with the newer build and import the export here"
    )]
    NewerSchema {
        path: PathBuf,
        found: u32,
        supported: u32,
    },
    #[error("{path} is not a Triax calibration store: {reason}")]
    NotAStore { path: PathBuf, reason: String },
    #[error("calibration store: {0}")]
    Corrupt(CorruptEntry),
    #[error("calibration store: {action}: {source}")]
    Io {
        action: &'static str,
        #[source]
        source: io::Error,
    },
    #[error("{action} {path}: {source}")]
    File {
        action: &'static str,
        path: PathBuf,
        #[source]
        source: io::Error,
    },
}

/// Why a record was not stored. Nothing was written.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum Rejection {
    #[error("record does not load into a corrector: {0}")]
    Invalid(#[from] LoadError),
    #[error(
        "sensor {sensor_id}: version {version} is older than the current version {current} and \
         not in the history; a change is issued as a new, higher version"
    )]
    Stale {
        sensor_id: SensorId,
        version: u64,
        current: u64,
    },
    #[error(
        "sensor {sensor_id}: version {version} is already stored with different content; a \
         change is issued as a new, higher version"
    )]
    Conflict { sensor_id: SensorId, version: u64 },
}

/// An entry that cannot be decoded, named by tree and key so that it can be found and repaired
/// (for instance by importing the record again from an export).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct CorruptEntry {
    /// `records`, `current` or `meta`.
    pub tree: &'static str,
    /// The key, as `<sensor> v<version>` when it parses, escaped bytes otherwise.
    pub key: String,
    pub problem: String,
}

impl fmt::Display for CorruptEntry {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "corrupt entry in tree {:?} at key {}: {}",
            self.tree, self.key, self.problem
        )
    }
}

/// Maps a sled error to ours, keeping sled's types out of the API.
pub(crate) fn db_error(action: &'static str, e: sled::Error) -> StoreError {
    let source = match e {
        sled::Error::Io(e) => e,
        other => io::Error::other(other.to_string()),
    };
    StoreError::Io { action, source }
}
