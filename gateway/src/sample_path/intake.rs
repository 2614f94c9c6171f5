//! Raw batches from Zenoh's receive callback to their sensors' shards.
//!
//! Under backpressure the callback runs the sensor's shard itself. Under drop-oldest (the
//! default) a batch arriving on a receive thread waits for the end of its receive burst, as the
//! corrected batches wait in the [`outbox`](super::outbox): a task queued on that thread's
//! runtime then hands the burst over shard by shard. A shard whose inbox is empty and free is
//! claimed once for all its batches of the burst and corrected in place
//! ([`Shard::handle_burst`](super::worker::Shard::handle_burst)), within the receive thread's
//! [`ReceiveBudget`](super::inbox::ReceiveBudget); otherwise its batches join its inbox for the
//! worker.
//!
//! Why wait: at a building's pace every batch finds its sensor's state out of the cache, and
//! handled one by one as it arrived, each batch waited for its own loads. A burst known whole
//! lets each sensor's state be asked for while the batches before it are corrected, and the
//! claims, locks and clock reads are paid once a shard and burst instead of once a batch
//! (BENCHMARKS.md, "An eighth look"). Measured in both orders against handling each batch as
//! it arrived, the bench finds no difference in CPU at a building's pace ("A ninth look").
//!
//! Invariants: a sensor's batches reach its shard in the order they arrived (a [`Burst`]
//! queue per shard, and an inbox that holds a shard's earlier batches keeps its later ones); at
//! most [`BURST_MAX`](burst::BURST_MAX) batches wait, for at most one burst; a batch that
//! arrives off a multi-threaded Tokio runtime (a local put, on its caller's thread) is handed
//! over at once with whatever waits; at the gateway's stop what waits is handed over before the
//! inboxes close ([`Queues::hand_over`]).

use std::sync::atomic::Ordering::Relaxed;
use std::sync::Arc;
use std::time::Instant;

use triax_protocol::batch::MAX_RAW_BATCH_BYTES;
use triax_protocol::keys::{self, InlineId, Stream};
use zenoh::bytes::ZBytes;

use super::burst::{self, Burst, Pushed};
use super::inbox::{self, Inbox};
use super::worker::{self, Arrival, Shards};
use crate::config::{Config, Overload};
use crate::error::{zenoh_err, GatewayError};
use crate::state::GatewayCounters;

/// A copy of a raw batch out of Zenoh's receive buffer (see [`Arrival`] for why).
fn copy(sensor: InlineId, payload: &ZBytes) -> Arrival {
    Arrival {
        sensor,
        payload: payload.to_bytes().into(),
    }
}

/// Where Zenoh's receive callback puts a raw batch, by [`Overload`] policy.
pub(crate) enum Intake {
    /// Drop-oldest: the burst's queues, handed to the shards at its end.
    Queues(Arc<Queues>),
    /// Backpressure: the sensor's shard, always run right here on the receive thread.
    Shards(Shards, Arc<worker::Shared>),
}

impl Intake {
    /// Hands a batch to its sensor's shard: a copy of it, unless it is longer than any raw
    /// batch can be (counted as malformed and skipped, never copied).
    fn take(&self, sensor: InlineId, payload: &ZBytes) {
        if payload.len() > MAX_RAW_BATCH_BYTES {
            let shared = match self {
                Intake::Queues(queues) => &queues.shared,
                Intake::Shards(_, shared) => shared,
            };
            let cause = format!(
                "payload of {} bytes, longer than the largest raw batch ({MAX_RAW_BATCH_BYTES})",
                payload.len()
            );
            return worker::reject(shared, sensor.as_str(), &cause);
        }
        let arrival = copy(sensor, payload);
        let sensor = arrival.sensor.as_str();
        match self {
            Intake::Queues(queues) => {
                let i = worker::shard(sensor, queues.inboxes.len());
                queues.take(i, arrival);
            }
            Intake::Shards(shards, shared) => {
                let i = worker::shard(sensor, shards.len());
                worker::lock_shard(&shards[i]).handle(shared, &arrival);
            }
        }
    }
}

/// The drop-oldest intake: each shard's inbox, and the batches of the current burst.
pub(crate) struct Queues {
    inboxes: Arc<Vec<Arc<Inbox<Arrival>>>>,
    shards: Shards,
    shared: Arc<worker::Shared>,
    burst: Burst<Arrival>,
}

impl Queues {
    fn take(self: &Arc<Self>, shard: usize, arrival: Arrival) {
        match self.burst.push(shard, arrival) {
            Pushed::Waits => {}
            Pushed::Full => self.hand_over(),
            Pushed::First => match burst::runtime() {
                Some(runtime) => {
                    let queues = self.clone();
                    runtime.spawn(async move {
                        // Cleared before the burst is taken: a batch added after the take
                        // queues a new task.
                        queues.burst.task_started();
                        queues.hand_over();
                    });
                }
                None => {
                    self.burst.task_started();
                    self.hand_over();
                }
            },
        }
    }

    /// Hands every waiting batch to its shard: corrected here when the shard's inbox is free
    /// and this thread's budget allows, else queued for its worker; then publishes what was
    /// corrected.
    pub fn hand_over(&self) {
        let outbox = &self.shared.outbox;
        let mut started = Instant::now();
        outbox.gathered(|| {
            self.burst.take(|i, arrivals| {
                if inbox::receive_budget_allows(started) && self.inboxes[i].try_claim() {
                    worker::lock_shard(&self.shards[i]).handle_burst(&self.shared, arrivals);
                    self.inboxes[i].release();
                    let ended = Instant::now();
                    inbox::receive_budget_spent(started, ended);
                    started = ended;
                } else {
                    for arrival in arrivals.drain(..) {
                        self.inboxes[i].push(arrival);
                    }
                }
            });
        });
        // Publishing is part of correcting in place: a worker's batch is published by the
        // worker.
        inbox::receive_budget_spent(started, Instant::now());
    }
}

/// Counts a raw payload whose key is not a concrete raw key of this building (a wildcard put
/// reaches every building's subscription) and skips it; logs the first of each reason and then
/// every thousandth.
fn refuse_key(counters: &GatewayCounters, reason: keys::RawKeyRefusal, key: &str) {
    let n = counters.refuse_key(reason);
    if n == 1 || n % 1000 == 0 {
        tracing::warn!(
            key,
            reason = reason.as_str(),
            refused = n,
            "raw payload on a key that is not one of this building's sensors skipped"
        );
    }
}

/// What [`start`] sets up.
pub(crate) struct Started {
    /// One per worker; none under backpressure.
    pub inboxes: Arc<Vec<Arc<Inbox<Arrival>>>>,
    pub shards: Shards,
    /// Drop-oldest only.
    pub queues: Option<Arc<Queues>>,
    pub subscriber: zenoh::pubsub::Subscriber<()>,
}

/// The worker inboxes (drop-oldest) or the shards (backpressure), and the raw subscription
/// that feeds them.
pub(crate) async fn start(
    config: &Config,
    session: &zenoh::Session,
    counters: &Arc<GatewayCounters>,
    shared: &Arc<worker::Shared>,
) -> Result<Started, GatewayError> {
    // Under backpressure nothing is queued: the receive callback runs the shards itself.
    let n_inboxes = match config.overload {
        Overload::DropOldest => config.workers,
        Overload::Backpressure => 0,
    };
    let inboxes: Arc<Vec<Arc<Inbox<Arrival>>>> = Arc::new(
        (0..n_inboxes)
            .map(|_| {
                Arc::new(Inbox::new(
                    config.queue_capacity_batches,
                    counters.dropped.clone(),
                ))
            })
            .collect(),
    );
    let shards: Shards = Arc::new((0..config.workers).map(|_| Default::default()).collect());
    let (intake, queues) = match config.overload {
        Overload::DropOldest => {
            let queues = Arc::new(Queues {
                inboxes: inboxes.clone(),
                shards: shards.clone(),
                shared: shared.clone(),
                burst: Burst::new(inboxes.len()),
            });
            (Intake::Queues(queues.clone()), Some(queues))
        }
        Overload::Backpressure => (Intake::Shards(shards.clone(), shared.clone()), None),
    };
    let received = counters.clone();
    let building = config.building.clone();
    let subscriber = session
        .declare_subscriber(keys::all_sensors(&config.building, Stream::Raw))
        .callback(move |sample: zenoh::sample::Sample| {
            received.received_batches.fetch_add(1, Relaxed);
            let key = sample.key_expr().as_str();
            // A chunk `raw_sensor_of` accepts is a valid id, which `InlineId::parse` takes.
            match keys::raw_sensor_of(key, &building).map(InlineId::parse) {
                Ok(Some(sensor)) => intake.take(sensor, sample.payload()),
                Ok(None) => refuse_key(&received, keys::RawKeyRefusal::Malformed, key),
                Err(reason) => refuse_key(&received, reason, key),
            }
        })
        .await
        .map_err(zenoh_err("subscribe to raw streams"))?;
    Ok(Started {
        inboxes,
        shards,
        queues,
        subscriber,
    })
}
