//! The sample path, the gateway's hot path in one place: a raw batch from Zenoh's receive
//! callback to its corrected batch on the wire and in the history's queue.
//!
//! ```text
//! triax/<b>/raw/* ─► intake (the receive burst, per shard) ─► the shard, in place, or its
//!   inbox and worker thread (worker: sequence, kernel: correct and flag, tilt, health feed)
//!   ─► outbox, at the burst's end ─► triax/<b>/corrected/<s>, triax/<b>/tilt/<s>
//!   └► history's queue (a writer thread of its own syncs it)
//! ```
//!
//! Read bottom up: `filter` and `tilt` (the kernel's filters), `kernel` (one batch corrected,
//! allocation-free), `sequence`, `burst` and `inbox` (mechanisms), `outbox`, `history` and
//! `health` (where a corrected batch goes), `worker` (a shard: one sensor's batch from its
//! arrival to those three), `late` (the backfill's way in and out), `intake` (the receive
//! callback). [`SamplePath`] starts and stops them.
//!
//! Architecture invariant: what lies outside uses this module's face only (the items
//! re-exported here), never a part of it by its path; nothing here imports a service or the
//! composition in `lib.rs`. A service that feeds the path is handed in as a value: the
//! backfill's queue comes in as [`Holes`], and its batches go back through [`LateDoor`].

mod burst;
mod filter;
mod health;
mod history;
mod inbox;
mod intake;
mod kernel;
mod late;
mod outbox;
mod seal;
mod sequence;
mod tilt;
mod worker;

use std::sync::Arc;

use triax_calibration_store::Store;
use triax_protocol::SensorId;

pub use health::suspect_flag;
pub use history::{open as open_history, Recorder, Sink, SinkCounters, Verdict};
pub use kernel::{BatchOutcome, Scratch, SensorKernel};
pub use late::{Holes, LateRun, Need, Request};
pub use tilt::{tilt, LowBandError};
pub use worker::{correct_judged, shard, SHUTDOWN_DRAIN};

use health::Reporting;
use inbox::Inbox;
use worker::{Arrival, Shards, Shared};

use crate::config::Config;
use crate::error::GatewayError;
use crate::state::{GatewayCounters, SensorTable, Signer};

/// What the sample path is given: the state it reads and writes, and where it hands what it
/// does not do itself.
pub struct Parts {
    pub signer: Arc<Signer>,
    pub table: Arc<SensorTable>,
    pub counters: Arc<GatewayCounters>,
    /// The health checks mark suspect records in it (once per record at most), never read on
    /// the sample path.
    pub store: Arc<Store>,
    /// The history's writer; none when the history is off.
    pub recorder: Option<Recorder>,
    /// The backfill's queue; none when the backfill is off.
    pub holes: Option<Holes>,
}

/// The running sample path.
pub struct SamplePath {
    shared: Arc<worker::Shared>,
    subscriber: Option<zenoh::pubsub::Subscriber<()>>,
    /// Drop-oldest only: the receive bursts' queues, the workers' inboxes and threads.
    queues: Option<Arc<intake::Queues>>,
    inboxes: Arc<Vec<Arc<Inbox<Arrival>>>>,
    shards: worker::Shards,
    workers: Vec<std::thread::JoinHandle<()>>,
    recorder: Option<Recorder>,
    sealer: Option<seal::Sealer>,
}

impl SamplePath {
    /// Subscribes to the building's raw streams; batches taken before [`Self::start_workers`]
    /// wait in the inboxes.
    pub async fn start(
        config: &Config,
        session: &zenoh::Session,
        parts: Parts,
    ) -> Result<SamplePath, GatewayError> {
        let Parts {
            signer,
            table,
            counters,
            store,
            recorder,
            holes,
        } = parts;
        let sealer = match signer.signs() {
            true => Some(
                seal::Sealer::start(
                    session.clone(),
                    &config.building,
                    signer.clone(),
                    config.provenance.seal_interval,
                    counters.clone(),
                )
                .map_err(|e| GatewayError::Task(format!("starting the sealer thread: {e}")))?,
            ),
            false => None,
        };
        let shared = Arc::new(worker::Shared {
            building: config.building.clone(),
            session: session.clone(),
            table,
            counters: counters.clone(),
            declared_keys_max: config.declared_keys_max,
            declared_keys_idle_ns: config.declared_keys_idle.as_nanos().min(i64::MAX as u128)
                as i64,
            history: recorder.as_ref().map(|r| r.sink.clone()),
            store,
            health: config.health.as_ref().map(|h| Reporting {
                publish_interval_ns: (h.publish_interval_s * 1e9) as i64,
                clock_watch_ms: h.clock_watch_ms,
            }),
            backfill: holes,
            outbox: outbox::Outbox::new(
                session.clone(),
                counters.clone(),
                sealer.as_ref().map(|s| s.queue.clone()),
            ),
            seals: sealer.as_ref().map(|s| s.queue.clone()),
            signer,
        });
        let intake::Started {
            inboxes,
            shards,
            queues,
            subscriber,
        } = intake::start(config, session, &counters, &shared).await?;
        Ok(SamplePath {
            shared,
            subscriber: Some(subscriber),
            queues,
            inboxes,
            shards,
            workers: Vec::new(),
            recorder,
            sealer,
        })
    }

    /// Starts one worker thread per inbox (none under backpressure); on failure, closes every
    /// inbox so that the threads already started end.
    pub fn start_workers(&mut self) -> Result<(), GatewayError> {
        for (i, (inbox, shard)) in self.inboxes.iter().zip(self.shards.iter()).enumerate() {
            let (inbox, shard, shared) = (inbox.clone(), shard.clone(), self.shared.clone());
            let spawned = std::thread::Builder::new()
                .name(format!("triax-worker-{i}"))
                .spawn(move || worker::run(i, inbox, shard, shared));
            match spawned {
                Ok(worker) => self.workers.push(worker),
                Err(e) => {
                    self.close_inboxes(std::time::Instant::now());
                    return Err(GatewayError::Task(format!(
                        "starting worker thread {i}: {e}"
                    )));
                }
            }
        }
        Ok(())
    }

    /// Where corrected batches are kept; none when the history is off.
    pub fn history(&self) -> Option<&Arc<Sink>> {
        self.shared.history.as_ref()
    }

    /// The backfill's way back in.
    pub fn late_door(&self) -> LateDoor {
        LateDoor {
            shared: self.shared.clone(),
            shards: self.shards.clone(),
        }
    }

    /// Raw batches waiting in the workers' inboxes, now.
    pub fn queued(&self) -> Arc<dyn Fn() -> usize + Send + Sync> {
        let inboxes = self.inboxes.clone();
        Arc::new(move || inboxes.iter().map(|b| b.len()).sum())
    }

    /// Takes no more batches: the subscription goes (a batch still in Zenoh's hands after
    /// that finds its inbox closed and is counted as dropped), what the last burst left
    /// waiting goes to the shards, and the workers correct what is queued for at most
    /// [`SHUTDOWN_DRAIN`] more.
    pub fn stop_intake(&mut self) {
        drop(self.subscriber.take());
        // What the last burst left waiting, should its task not have run: to the shards
        // while their inboxes still take it.
        if let Some(queues) = &self.queues {
            queues.hand_over();
        }
        self.close_inboxes(std::time::Instant::now() + SHUTDOWN_DRAIN);
    }

    /// Waits for the workers to end, publishes what the last bursts left waiting, and closes
    /// the history once it has kept what they handed over.
    pub async fn finish(mut self) -> Result<(), GatewayError> {
        if self.subscriber.is_some() {
            self.stop_intake();
        }
        let workers = std::mem::take(&mut self.workers);
        let joined = tokio::task::spawn_blocking(move || {
            workers
                .into_iter()
                .map(|w| w.join())
                .filter(Result::is_err)
                .count()
        })
        .await
        .map_err(|e| GatewayError::Task(e.to_string()))?;
        if joined > 0 {
            tracing::error!(workers = joined, "worker threads ended abnormally");
        }
        // What the last bursts left waiting, should their tasks not have run.
        self.shared.outbox.flush();
        if let Some(sealer) = self.sealer.as_mut() {
            sealer.finish();
        }
        if let Some(mut recorder) = self.recorder.take() {
            let sink = recorder.sink.clone();
            tokio::task::spawn_blocking(move || recorder.stop())
                .await
                .map_err(|e| GatewayError::Task(e.to_string()))?;
            let c = &sink.counters;
            tracing::info!(
                offered = c.offered.load(std::sync::atomic::Ordering::Relaxed),
                not_kept = c.dropped.load(std::sync::atomic::Ordering::Relaxed),
                written = sink
                    .history
                    .counters
                    .written_batches
                    .load(std::sync::atomic::Ordering::Relaxed),
                "history closed"
            );
        }
        Ok(())
    }

    /// Closes every worker's inbox: its worker stops once it has taken what is queued, until
    /// `drain_until`.
    fn close_inboxes(&self, drain_until: std::time::Instant) {
        for inbox in self.inboxes.iter() {
            inbox.close(drain_until);
        }
    }
}

/// The sample path's door for late batches.
#[derive(Clone)]
pub struct LateDoor {
    shared: Arc<Shared>,
    shards: Shards,
}

impl LateDoor {
    /// Corrects `batches` of `sensor` (in sequence order, checked by the caller) with `run`'s
    /// kernel under its shard's lock, keeps them in the history, and publishes them flagged
    /// late once the lock is released, so that a live batch waits for at most one call's
    /// correction; returns how many were published, or none when the sensor has no state in
    /// its shard any more (forgotten meanwhile).
    pub fn correct_and_publish(
        &self,
        sensor: &SensorId,
        run: &mut LateRun,
        batches: &[Vec<u8>],
    ) -> Option<usize> {
        let shard = &self.shards[worker::shard(sensor.as_str(), self.shards.len())];
        let late = worker::lock_shard(shard).correct_late(&self.shared, sensor, run, batches)?;
        Some(worker::publish_late(&self.shared, late))
    }
}

impl Drop for SamplePath {
    /// A path dropped without [`SamplePath::finish`] still lets its worker threads end (what
    /// they hold queued is counted as dropped). After `finish` they have ended.
    fn drop(&mut self) {
        self.close_inboxes(std::time::Instant::now());
    }
}
