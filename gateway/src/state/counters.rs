//! Counters of the gateway as a whole and of its backfill, for status and metrics. Relaxed
//! atomics: each is an independent tally read for reports.

use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering::Relaxed};
use std::sync::Arc;

use triax_protocol::keys::RawKeyRefusal;

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
    /// Seals put over the published batches (PROTOCOL.md §6).
    pub seals: AtomicU64,
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
    /// Set once streaming sensors waited for declared keys longer than `declared_keys_idle`:
    /// from then on every key is used undeclared (logged once).
    pub keys_undeclared: AtomicBool,
    /// Payloads on the raw subscription whose key is not a concrete raw key of this building,
    /// by [`RawKeyRefusal`] (in the order of [`RawKeyRefusal::ALL`]).
    pub refused_keys: [AtomicU64; 3],
}

impl GatewayCounters {
    /// The counters of a gateway that loaded `calibrations` records and may declare
    /// `declared_keys_max` keys.
    ///
    /// A store that already holds more calibrated sensors than the key budget can declare
    /// starts undeclared: waiting to find out would spend minutes partly declared, the slowest
    /// state (see `sample_path::worker::Shard::reassign_keys`). Only for a building of a
    /// thousand sensors or more, where that state costs several times more per batch
    /// (BENCHMARKS.md); below, the budget's patience decides.
    pub fn at_start(calibrations: usize, declared_keys_max: usize) -> GatewayCounters {
        let counters = GatewayCounters::default();
        if calibrations >= 1000 && calibrations.saturating_mul(2) > declared_keys_max {
            counters.keys_undeclared.store(true, Relaxed);
            tracing::info!(
                calibrations,
                budget_keys = declared_keys_max,
                "more calibrated sensors than declared_keys_mib holds: keys are used undeclared"
            );
        }
        counters
    }

    /// Counts a payload refused for its key; returns how many were refused for that reason.
    pub fn refuse_key(&self, reason: RawKeyRefusal) -> u64 {
        self.refused_keys[reason as usize].fetch_add(1, Relaxed) + 1
    }

    /// Payloads refused for `reason` so far.
    pub fn refused_keys(&self, reason: RawKeyRefusal) -> u64 {
        self.refused_keys[reason as usize].load(Relaxed)
    }
}

/// The backfill's counters, for status and metrics.
#[derive(Debug, Default)]
pub struct BackfillCounters {
    /// Queries sent to nodes' buffers.
    pub queries: AtomicU64,
    /// Batches the gaps and restarts asked for.
    pub wanted_batches: AtomicU64,
    /// Late batches corrected and published.
    pub late_batches: AtomicU64,
    /// Replies that were not a batch of the hole asked for (or came for a forgotten sensor).
    pub rejected: AtomicU64,
    /// Queries that ended in an error or timed out (what they brought is kept).
    pub failed_queries: AtomicU64,
    /// Requests the queue could not take.
    pub refused: AtomicU64,
}

impl BackfillCounters {
    pub fn status(&self) -> triax_protocol::messages::BackfillStatus {
        triax_protocol::messages::BackfillStatus {
            queries: self.queries.load(Relaxed),
            wanted_batches: self.wanted_batches.load(Relaxed),
            late_batches: self.late_batches.load(Relaxed),
            rejected_replies: self.rejected.load(Relaxed),
            failed_queries: self.failed_queries.load(Relaxed),
            refused_requests: self.refused.load(Relaxed),
        }
    }
}
