//! The gateway's history: every raw batch it corrected, kept on disk as received, with what is
//! needed to correct it again exactly as it was (the calibration version in force, the sequence
//! verdict, and checkpoints of the correction state), for a bounded age and size.
//!
//! # Layout
//!
//! A directory of segments ([`segment`]), each a log of CRC-framed [`block`]s and an index of
//! fixed-size entries. A block holds a run of one sensor's batches (at most one flush interval
//! of them, one second by default), so reading one sensor touches only its own blocks; a steady
//! stream costs its samples (12 bytes each) plus about five bytes per batch and 72 per block.
//! Segments roll at a size or an age; retention deletes whole segments, oldest first.
//!
//! # Guarantees
//!
//! - [`Writer::flush`] returns after the blocks it wrote are on disk (`fdatasync`) and indexed;
//!   the gateway flushes at least once a second, so a kill loses at most the last second.
//! - After a crash at any moment, opening keeps every block flushed before it, whole, and cuts a
//!   torn tail; the index is rebuilt from the log where it lags.
//! - A block is served only if its CRC matches: a damaged block is reported, never decoded.
//! - Arrival numbers increase across restarts: they order batches as the gateway received them.
//! - A history opened for an [`Owner`] serves that building only: the building is recorded at
//!   creation and a history recording another is refused at open ([`HistoryError::Foreign`]).
//!
//! # Concurrency
//!
//! One [`Writer`] appends; any number of readers ([`History::scan`]) read at the same time. The
//! writer publishes a block to readers only after it is durable. A segment deleted by retention
//! while a reader holds it open stays readable to that reader (Unix semantics).
//!
//! Pure storage: no Zenoh, no async runtime, no knowledge of correction. The gateway's
//! `history` module owns the writer thread and the replay.

pub mod append;
pub mod block;
pub mod os;
mod owner;
pub mod segment;
mod store;
pub mod varint;

pub use block::{Block, BlockError, Kept, Verdict};
pub use owner::{read_owner, Owner, OwnerCheck, OWNER_FILE};
pub use segment::IndexEntry;
pub use store::{
    History, HistoryConfig, HistoryCounters, HistoryStats, Opened, Query, Scan, ScannedBlock,
    SeqRun, Writer,
};

use std::path::PathBuf;

use triax_protocol::BuildingId;

/// What went wrong with a history.
#[derive(Debug, thiserror::Error)]
pub enum HistoryError {
    #[error("history {path}: {action}: {source}")]
    Io {
        action: &'static str,
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("history {path}: damaged block at byte {offset}: {reason}")]
    Damaged {
        path: PathBuf,
        offset: u64,
        reason: String,
    },
    #[error("history {path} is in use by another process")]
    Locked { path: PathBuf },
    /// The history records another building than the one opening it.
    #[error(
        "history {path} belongs to building {recorded} (created by gateway {recorded_gateway_name:?}), \
         not to building {configured}: a history serves only the building it was created for"
    )]
    Foreign {
        path: PathBuf,
        recorded: BuildingId,
        recorded_gateway_name: String,
        configured: BuildingId,
    },
    #[error("history {path}: the owner file cannot be read: {reason}")]
    OwnerUnreadable { path: PathBuf, reason: String },
    #[error("history setting {field}: {reason}")]
    Config { field: &'static str, reason: String },
}
