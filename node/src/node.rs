//! The running node: a sampling thread, a keeper thread that numbers, buffers and hands on each
//! batch, a publishing thread, and the buffer's queryable.
//!
//! ```text
//! source ──▶ sampler thread (batcher) ──try_send──▶ keeper thread: number (durably reserved),
//!    encode, append to the ring, fdatasync every second ──try_send──▶ publisher thread:
//!    put triax/<b>/raw/<s> (congestion control: block)
//! query triax/<b>/buffer/<s>?… ──▶ blocking task: ring.read_range ──▶ one reply per batch
//! ```
//!
//! The sampler never waits on anything but its source: both hand-offs are bounded queues it
//! or the keeper only ever `try_send`s to. A full publishing queue (the network is slower than
//! the sensor) skips the live put; the batch is in the ring, and the gateway's gap query
//! fetches it. A batch is in the ring before it is published, so whatever a gateway saw can be
//! asked for again.

use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::mpsc::{self, RecvTimeoutError, TrySendError};
use std::sync::Arc;
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use triax_protocol::batch::{BatchHeader, RawBatch};
use triax_protocol::{BuildingId, Key, SensorId};
use zenoh::qos::CongestionControl;
use zenoh::Wait;

use crate::batcher::{Batcher, Pending};
use crate::buffer::{BufferQuery, BufferStatus};
use crate::ring::{Ring, RingConfig, RingError};
use crate::source::{Source, SourceError};

/// How the node runs.
#[derive(Debug, Clone)]
pub struct NodeConfig {
    pub building: BuildingId,
    pub sensor: SensorId,
    pub batch_samples: usize,
    pub ring: RingConfig,
    /// Standard uncertainty of the node's clock against UTC, ns (stated, not measured).
    pub clock_uncertainty_ns: f64,
    /// How often the ring is synced to disk.
    pub sync_interval: Duration,
    /// Batches waiting for the keeper, and for the publisher, at most.
    pub queue_batches: usize,
}

#[derive(Debug, thiserror::Error)]
pub enum NodeError {
    #[error(transparent)]
    Ring(#[from] RingError),
    #[error("zenoh: {0}")]
    Zenoh(String),
    #[error("source: {0}")]
    Source(#[from] SourceError),
    #[error("cannot start the {0} thread: {1}")]
    Thread(&'static str, std::io::Error),
}

/// Counters since the start, shared by the threads and the status reply.
#[derive(Debug, Default)]
pub struct Counters {
    pub published: AtomicU64,
    pub publish_skipped: AtomicU64,
    pub publish_errors: AtomicU64,
    pub buffer_write_errors: AtomicU64,
    pub dropped: AtomicU64,
    pub time_breaks: AtomicU64,
    pub numbered: AtomicU64,
}

/// What a run did, for the log at exit.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Summary {
    pub first_sequence: Option<u64>,
    pub next_sequence: u64,
    pub numbered: u64,
    pub published: u64,
    pub publish_skipped: u64,
    pub dropped: u64,
    /// The source ended (a CSV file read to its end) rather than the node being stopped.
    pub source_ended: bool,
}

/// Queries answered at once; more wait (each is a disk read of up to 100 000 batches).
const CONCURRENT_QUERIES: usize = 2;
/// How long a stop waits for the sampler's last read, and for the publisher to drain.
const STOP_WAIT: Duration = Duration::from_secs(3);

struct Shared {
    config: NodeConfig,
    ring: Ring,
    counters: Counters,
    rate_hz: f64,
    source_stamp_uncertainty_ns: f64,
}

impl Shared {
    fn status(&self) -> BufferStatus {
        let st = self.ring.stats();
        let c = &self.counters;
        let span_s = match (st.oldest_timestamp_ns, st.newest_timestamp_ns) {
            (Some(a), Some(b)) => (b - a) as f64 / 1e9,
            _ => 0.0,
        };
        BufferStatus {
            format_version: 1,
            building: self.config.building.to_string(),
            sensor: self.config.sensor.to_string(),
            oldest_sequence: st.oldest_sequence,
            newest_sequence: st.newest_sequence,
            oldest_timestamp_ns: st.oldest_timestamp_ns,
            newest_timestamp_ns: st.newest_timestamp_ns,
            batches: st.batches,
            bytes: st.bytes,
            span_s,
            capacity_batches: self.ring.config().capacity_batches,
            next_sequence: st.next_sequence,
            sample_rate_hz: self.rate_hz,
            batch_samples: self.config.batch_samples,
            clock_uncertainty_ns: self.config.clock_uncertainty_ns,
            source_stamp_uncertainty_ns: self.source_stamp_uncertainty_ns,
            timestamp_uncertainty_ns: self
                .config
                .clock_uncertainty_ns
                .hypot(self.source_stamp_uncertainty_ns),
            published_batches: c.published.load(Ordering::Relaxed),
            publish_skipped_batches: c.publish_skipped.load(Ordering::Relaxed),
            buffer_write_errors: c.buffer_write_errors.load(Ordering::Relaxed),
            dropped_batches: c.dropped.load(Ordering::Relaxed),
            time_breaks: c.time_breaks.load(Ordering::Relaxed),
        }
    }
}

/// A batch gathered by the sampler, not yet numbered.
struct Gathered {
    pending: Pending,
    temperature_c: Option<f32>,
}

/// Runs the node until `shutdown` resolves or the source ends, then stops with everything
/// flushed: the batch being gathered is sent short, the ring synced and its next number
/// recorded, the publishing queue drained (within a few seconds).
pub async fn run(
    config: NodeConfig,
    source: Box<dyn Source>,
    session: zenoh::Session,
    shutdown: impl std::future::Future<Output = ()>,
) -> Result<Summary, NodeError> {
    let ring = Ring::open(config.ring.clone())?;
    let recovery = ring.recovery();
    let start = ring.stats();
    tracing::info!(
        building = %config.building,
        sensor = %config.sensor,
        held_batches = start.batches,
        oldest = ?start.oldest_sequence,
        next_sequence = start.next_sequence,
        torn_bytes = recovery.torn_bytes,
        "buffer opened"
    );
    let shared = Arc::new(Shared {
        rate_hz: source.rate_hz(),
        source_stamp_uncertainty_ns: source.stamp_uncertainty_ns(),
        config,
        ring,
        counters: Counters::default(),
    });
    let cfg = &shared.config;

    let publisher = session
        .declare_publisher(Key::Raw(cfg.building.clone(), cfg.sensor.clone()).to_string())
        .congestion_control(CongestionControl::Block)
        .await
        .map_err(|e| NodeError::Zenoh(triax_net::zenoh_cause(&*e)))?;
    let buffer_key = Key::Buffer(cfg.building.clone(), cfg.sensor.clone()).to_string();
    let queryable = session
        .declare_queryable(buffer_key.clone())
        .await
        .map_err(|e| NodeError::Zenoh(triax_net::zenoh_cause(&*e)))?;

    let stop = Arc::new(AtomicBool::new(false));
    let abandon = Arc::new(AtomicBool::new(false));
    let (gathered_tx, gathered_rx) = mpsc::sync_channel::<Gathered>(cfg.queue_batches);
    let (publish_tx, publish_rx) = mpsc::sync_channel::<Vec<u8>>(cfg.queue_batches);
    let (ended_tx, ended_rx) = tokio::sync::oneshot::channel::<Result<bool, SourceError>>();

    let sampler = spawn("sampler", {
        let shared = shared.clone();
        let stop = stop.clone();
        move || sample(source, &shared, &stop, gathered_tx, ended_tx)
    })?;
    let first_sequence = Arc::new(std::sync::Mutex::new(None));
    let keeper = spawn("keeper", {
        let shared = shared.clone();
        let abandon = abandon.clone();
        let first_sequence = first_sequence.clone();
        move || keep(&shared, gathered_rx, publish_tx, &abandon, &first_sequence)
    })?;
    let publishing = spawn("publisher", {
        let shared = shared.clone();
        move || {
            for payload in publish_rx {
                match publisher.put(payload).wait() {
                    Ok(()) => shared.counters.published.fetch_add(1, Ordering::Relaxed),
                    Err(e) => {
                        tracing::warn!(cause = %triax_net::zenoh_cause(&*e), "publish failed");
                        shared
                            .counters
                            .publish_errors
                            .fetch_add(1, Ordering::Relaxed)
                    }
                };
            }
        }
    })?;

    let queries = tokio::spawn({
        let shared = shared.clone();
        let permits = Arc::new(tokio::sync::Semaphore::new(CONCURRENT_QUERIES));
        async move {
            while let Ok(query) = queryable.recv_async().await {
                // Closed only when the node stops.
                let Ok(permit) = permits.clone().acquire_owned().await else {
                    break;
                };
                let shared = shared.clone();
                let key = buffer_key.clone();
                tokio::task::spawn_blocking(move || {
                    answer(&shared, &key, &query);
                    drop(permit);
                });
            }
        }
    });

    let mut source_result = Ok(false);
    tokio::pin!(shutdown);
    tokio::select! {
        () = &mut shutdown => {}
        r = ended_rx => {
            // Without a word the sampler panicked; the node stops all the same.
            if let Ok(r) = r {
                source_result = r;
            }
        }
    }
    stop.store(true, Ordering::Relaxed);
    let sampler_done = wait_thread(sampler, STOP_WAIT).await;
    if !sampler_done {
        tracing::warn!(
            "the source did not return within {STOP_WAIT:?} of the stop; its batch in progress is lost"
        );
        abandon.store(true, Ordering::Relaxed);
    }
    // The keeper ends when the sampler's queue closes (or, abandoned, at its next wake-up),
    // after closing the ring.
    let keeper_result = match tokio::task::spawn_blocking(move || keeper.join()).await {
        Ok(Ok(r)) => r,
        _ => {
            tracing::error!("the keeper thread panicked");
            Ok(())
        }
    };
    if !wait_thread(publishing, STOP_WAIT).await {
        tracing::warn!(
            "batches still queued for publishing after {STOP_WAIT:?}: they are in the buffer"
        );
    }
    queries.abort();
    let st = shared.ring.stats();
    let c = &shared.counters;
    let first = *first_sequence.lock().unwrap_or_else(|p| p.into_inner());
    let summary = Summary {
        first_sequence: first,
        next_sequence: st.next_sequence,
        numbered: c.numbered.load(Ordering::Relaxed),
        published: c.published.load(Ordering::Relaxed),
        publish_skipped: c.publish_skipped.load(Ordering::Relaxed),
        dropped: c.dropped.load(Ordering::Relaxed),
        source_ended: matches!(source_result, Ok(true)),
    };
    keeper_result?;
    source_result?;
    Ok(summary)
}

fn spawn<T: Send + 'static>(
    name: &'static str,
    f: impl FnOnce() -> T + Send + 'static,
) -> Result<JoinHandle<T>, NodeError> {
    std::thread::Builder::new()
        .name(format!("triax-node-{name}"))
        .spawn(f)
        .map_err(|e| NodeError::Thread(name, e))
}

/// Waits for a thread to finish, at most `limit`; whether it did.
async fn wait_thread<T: Send + 'static>(t: JoinHandle<T>, limit: Duration) -> bool {
    let deadline = Instant::now() + limit;
    while !t.is_finished() {
        if Instant::now() >= deadline {
            return false;
        }
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
    let _ = t.join();
    true
}

/// The sampling thread: reads the source, cuts batches, hands them to the keeper without ever
/// waiting for it. Reports through `ended` whether the source ended (Ok(true)), was stopped
/// (Ok(false)) or failed.
fn sample(
    mut source: Box<dyn Source>,
    shared: &Shared,
    stop: &AtomicBool,
    out: mpsc::SyncSender<Gathered>,
    ended: tokio::sync::oneshot::Sender<Result<bool, SourceError>>,
) {
    let mut batcher = Batcher::new(shared.config.batch_samples, source.rate_hz());
    let mut samples = Vec::new();
    let mut done = Vec::new();
    let hand_over = |pending: Pending, source: &mut Box<dyn Source>| {
        let g = Gathered {
            pending,
            temperature_c: source.temperature_c(),
        };
        match out.try_send(g) {
            Ok(()) => {}
            Err(TrySendError::Full(_)) => {
                let n = shared.counters.dropped.fetch_add(1, Ordering::Relaxed) + 1;
                if n.is_power_of_two() {
                    tracing::warn!(
                        dropped = n,
                        "the buffer's writer is behind the sensor: batches lost"
                    );
                }
            }
            // The keeper is gone only when the node stops.
            Err(TrySendError::Disconnected(_)) => {}
        }
    };
    let result = loop {
        if stop.load(Ordering::Relaxed) {
            break Ok(false);
        }
        samples.clear();
        let r = source.read(&mut samples);
        for s in samples.drain(..) {
            batcher.push(s, &mut done);
        }
        for p in done.drain(..) {
            hand_over(p, &mut source);
        }
        shared
            .counters
            .time_breaks
            .store(batcher.breaks, Ordering::Relaxed);
        match r {
            Ok(()) => {}
            Err(SourceError::End) => break Ok(true),
            Err(e) => break Err(e),
        }
    };
    if let Some(p) = batcher.flush() {
        hand_over(p, &mut source);
    }
    drop(out);
    let _ = ended.send(result);
}

/// The keeper thread: numbers each batch, appends it to the ring, then offers it to the
/// publisher; syncs the ring every `sync_interval`; at the end closes the ring.
fn keep(
    shared: &Shared,
    input: mpsc::Receiver<Gathered>,
    publish: mpsc::SyncSender<Vec<u8>>,
    abandon: &AtomicBool,
    first_sequence: &std::sync::Mutex<Option<u64>>,
) -> Result<(), RingError> {
    let cfg = &shared.config;
    let ring = &shared.ring;
    let c = &shared.counters;
    let mut last_sync = Instant::now();
    let mut batch = RawBatch {
        header: BatchHeader {
            sensor_id: cfg.sensor.clone(),
            sequence: 0,
            timestamp_ns: 0,
            sample_rate_hz: shared.rate_hz,
        },
        temperature_c: None,
        samples: Vec::new(),
    };
    loop {
        let wait = cfg.sync_interval.saturating_sub(last_sync.elapsed());
        match input.recv_timeout(wait) {
            Ok(g) => {
                // Without a durable number nothing may be published: a number used twice
                // would make two different batches one.
                let sequence = ring.next_sequence()?;
                first_sequence
                    .lock()
                    .unwrap_or_else(|p| p.into_inner())
                    .get_or_insert(sequence);
                batch.header.sequence = sequence;
                batch.header.timestamp_ns = g.pending.timestamp_ns;
                batch.temperature_c = g.temperature_c;
                batch.samples = g.pending.samples;
                let payload = batch.encode();
                c.numbered.fetch_add(1, Ordering::Relaxed);
                if let Err(e) = ring.append(sequence, &payload) {
                    let n = c.buffer_write_errors.fetch_add(1, Ordering::Relaxed) + 1;
                    if n.is_power_of_two() {
                        tracing::error!(cause = %e, errors = n, "buffer write failed; the batch is published unbuffered");
                    }
                }
                match publish.try_send(payload) {
                    Ok(()) => {}
                    Err(TrySendError::Full(_)) => {
                        c.publish_skipped.fetch_add(1, Ordering::Relaxed);
                    }
                    Err(TrySendError::Disconnected(_)) => {}
                }
            }
            Err(RecvTimeoutError::Timeout) => {}
            Err(RecvTimeoutError::Disconnected) => break,
        }
        if last_sync.elapsed() >= cfg.sync_interval {
            if let Err(e) = ring.sync() {
                tracing::error!(cause = %e, "buffer sync failed");
            }
            last_sync = Instant::now();
        }
        if abandon.load(Ordering::Relaxed) {
            // Take what the sampler handed over before it stuck, then close.
            while let Ok(g) = input.try_recv() {
                drop(g);
                c.dropped.fetch_add(1, Ordering::Relaxed);
            }
            break;
        }
    }
    ring.close()
}

/// Answers one buffer query; runs on a blocking thread.
fn answer(shared: &Shared, key: &str, query: &zenoh::query::Query) {
    let q = match BufferQuery::parse(query.parameters().iter()) {
        Ok(q) => q,
        Err(problem) => {
            if let Err(e) = query.reply_err(problem).wait() {
                tracing::warn!(cause = %e, "buffer error reply failed");
            }
            return;
        }
    };
    match q {
        BufferQuery::Status => {
            // Numbers and strings always serialise.
            let json = serde_json::to_vec(&shared.status()).expect("status serialises");
            if let Err(e) = query
                .reply(key, json)
                .encoding(zenoh::bytes::Encoding::APPLICATION_JSON)
                .wait()
            {
                tracing::warn!(cause = %e, "buffer status reply failed");
            }
        }
        BufferQuery::Range { from, to } => {
            let mut failed = None;
            let r = shared.ring.read_range(from, to, |_, payload| {
                if let Err(e) = query.reply(key, payload.to_vec()).wait() {
                    failed = Some(e.to_string());
                    return false;
                }
                true
            });
            if let Some(cause) = failed {
                tracing::warn!(cause, "buffer reply failed: the querier is gone");
                return;
            }
            if let Err(e) = r {
                tracing::error!(cause = %e, "buffer read failed");
                if let Err(e) = query.reply_err(format!("buffer: {e}")).wait() {
                    tracing::warn!(cause = %e, "buffer error reply failed");
                }
            }
        }
    }
}
