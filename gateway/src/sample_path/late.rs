//! What the sample path and the backfill exchange, without either knowing the other's inside:
//! a shard reports what its sensor missed ([`Request`]) into a queue it was handed ([`Holes`],
//! the backfill's, never waited on), and the backfill hands the batches it fetched back
//! through `LateDoor` (`sample_path`'s face), which corrects them under the shard's lock with
//! the hole's own kernel ([`LateRun`]).

use std::sync::atomic::Ordering::Relaxed;
use std::sync::Arc;

use tokio::sync::mpsc;
use triax_protocol::SensorId;

use super::kernel::SensorKernel;
use crate::state::BackfillCounters;

/// What a shard asks for.
#[derive(Debug)]
pub enum Need {
    /// A live batch numbered past the next: `from_seq..=to_seq` are missing, between the
    /// batches starting at `after_ns` and at `before_ns`; `state` is the sensor's kernel
    /// before the gap.
    Gap {
        from_seq: u64,
        to_seq: u64,
        after_ns: i64,
        before_ns: i64,
        state: Vec<u8>,
    },
    /// The first batch of the sensor since the gateway started: what the history lacks
    /// before it.
    First { sequence: u64, timestamp_ns: i64 },
}

/// A sensor's [`Need`].
#[derive(Debug)]
pub struct Request {
    pub sensor: SensorId,
    pub need: Need,
}

/// A shard's end of the backfill's queue: never waits; a request the queue cannot take is
/// counted (`refused`) and the hole stays a hole.
#[derive(Debug, Clone)]
pub struct Holes {
    tx: mpsc::Sender<Request>,
    counters: Arc<BackfillCounters>,
}

impl Holes {
    pub fn new(tx: mpsc::Sender<Request>, counters: Arc<BackfillCounters>) -> Holes {
        Holes { tx, counters }
    }

    pub fn report(&self, request: Request) {
        if self.tx.try_send(request).is_err() {
            self.counters.refused.fetch_add(1, Relaxed);
        }
    }

    pub fn counters(&self) -> &Arc<BackfillCounters> {
        &self.counters
    }
}

/// A hole being filled: its own kernel, the number expected next, and whether the next late
/// batch kept owes the history a checkpoint.
pub struct LateRun {
    pub kernel: SensorKernel,
    pub expected: u64,
    pub checkpoint_due: bool,
}
