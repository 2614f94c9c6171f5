//! Versioned, durable calibration records on sled.
//!
//! A [`Store`] keeps every version of every sensor's
//! [`CalibrationRecord`](triax_protocol::record::CalibrationRecord). The gateway keeps one per
//! building, holding what it applies; the lab keeps one as its registry of everything it has
//! issued. The API is synchronous and has no sled type in it: async callers wrap calls in
//! `spawn_blocking`.
//!
//! ```
//! use triax_calibration_store::{PutOutcome, Rejection, Store};
//! use triax_protocol::record::sample;
//! # fn main() -> Result<(), Box<dyn std::error::Error>> {
//! let dir = tempfile::tempdir()?;
//! let store = Store::open(dir.path())?;
//! let record = sample::record("s1", 2);
//! assert_eq!(store.put(&record)?, Ok(PutOutcome::Stored));
//! assert_eq!(store.put(&record)?, Ok(PutOutcome::AlreadyStored));
//! assert!(matches!(
//!     store.put(&sample::record("s1", 1))?,
//!     Err(Rejection::Stale { current: 2, .. })
//! ));
//! assert_eq!(store.current(&record.sensor_id)?, Some(record));
//! # Ok(())
//! # }
//! ```
//!
//! # Rules
//!
//! - A record is stored only if it loads into a corrector (shape, finite values,
//!   well-conditioned sensitivity, positive semi-definite covariance); otherwise
//!   [`Rejection::Invalid`] says why.
//! - A sensor's versions only go up: a put is accepted if its version is above the current one.
//!   A version already stored with identical content is an idempotent success
//!   ([`PutOutcome::AlreadyStored`]); with other content it is refused ([`Rejection::Conflict`]);
//!   an older version not stored is refused ([`Rejection::Stale`]).
//! - The record in force at a time is the newest version whose window `[valid_from,
//!   valid_until)` contains it ([`Store::at`]), as StationXML channel epochs.
//!
//! # Durability guarantees
//!
//! - [`Store::put`] returns success only after the record is written to the database's log
//!   and the log is flushed (sled's `flush`: the written range is synced, with
//!   `sync_file_range` on Linux and `fsync` elsewhere); this holds for
//!   [`PutOutcome::AlreadyStored`] too. [`Store::put_all`] and [`Store::import`] flush once,
//!   before returning; every record they report as accepted is then durable.
//! - A record and its current-version index entry are written in one sled transaction: after
//!   a crash at any moment both are visible or neither is. No partially written record is ever
//!   visible.
//! - After the process is killed at any moment (`kill -9` included), the store reopens with
//!   every record whose put returned, byte for byte. This is tested by killing a writing child
//!   process at random moments and checking every acknowledged record after reopening.
//! - A put that returned an error, or was interrupted, may or may not be stored. Retrying it
//!   is safe: the retry is either stored or reported as already stored.
//! - Against power loss, the guarantee is sled 0.34's for a flushed log: on Linux its
//!   `sync_file_range` does not flush the drive's volatile write cache, so a store on a drive
//!   without power-loss protection can lose the last writes. Keep exports for recovery.
//! - Stored records are never changed or deleted, with one exception: an entry that can no
//!   longer be decoded is replaced by a valid record of the same sensor and version when one is
//!   put ([`PutOutcome::Repaired`]).
//! - One process at a time: sled locks the directory, and a second opener gets
//!   [`StoreError::Locked`]. Within the process, every read sees every put that has returned.
//! - [`Store::export`] writes each file under a temporary name, syncs it and renames it, then
//!   syncs the directory: an interrupted export leaves complete files (and perhaps a `.tmp`).
//!
//! # Layout and schema
//!
//! Keys are big-endian so that sled's order is sensor id then version (see the `keys` module).
//! The database stores its [`SCHEMA_VERSION`]; a store written by a newer schema is refused
//! with [`StoreError::NewerSchema`]. An entry that cannot be decoded is reported by tree and key
//! ([`CorruptEntry`]) and skipped by reads over many entries ([`Scan::skipped`]); reading that
//! one entry is an error. Nothing in this crate panics on what it reads from disk.
//!
//! Architecture invariant: this crate knows nothing of the network or of async runtimes; the
//! gateway and the lab decide when to read and write.

mod error;
mod keys;
mod store;
mod transfer;

pub mod cli;

pub use error::{CorruptEntry, Rejection, StoreError};
pub use store::{
    in_force_at, Loaded, PutOutcome, Scan, SensorVersion, Store, SuspectMark, SCHEMA_VERSION,
};
pub use transfer::{export_file_name, ExportReport, FileOutcome, ImportReport, ImportedFile};
