//! The gateway's side of the history ([`triax_history`]): what the correction workers hand
//! over, the writer thread that keeps it, and the durability rule.
//!
//! The sample path never waits for the disk. A worker, once it has corrected a batch, offers
//! its samples, the sequence verdict, the calibration version used and, when one is due, a
//! checkpoint of the sensor's correction state, to a bounded queue ([`Sink::offer`]): one copy
//! of the samples into a shared buffer, no allocation, and Zenoh's receive buffer is not held.
//! When the queue is full the batch is not kept, and counted (`history.dropped_batches`). The
//! writer thread takes the whole queue, gathers each sensor's batches into a block, and
//! flushes: it writes and syncs (`fdatasync`) every `flush_interval` (one second by default),
//! so a batch is durable at most one interval, plus one sync, after it was corrected. It wakes
//! for that, for a query's sync, or when [`DRAIN_BATCHES`] or a sixteenth of the queue's bytes
//! are waiting ([`Sink::offer`] wakes it then, once): not on a timer of its own. It used to
//! take the queue every 20 ms, and those fifty wake-ups a second were most of its cost at a
//! building's pace, and most of a host's running a hundred gateways (BENCHMARKS.md). A history
//! query first asks for a flush of everything queued so far ([`Sink::sync`]), so a consumer
//! that noticed a gap finds the batches it missed even if they arrived a moment ago.

use std::ops::Range;
use std::path::Path;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering::Relaxed};
use std::sync::{Arc, Condvar, Mutex};
use std::time::{Duration, Instant};

pub use triax_history::Verdict;
use triax_history::{History, Kept, Writer};
use triax_protocol::messages::HistoryStatus;
use triax_protocol::{InlineId, RawBatchView};

use crate::config::{default_history_path, Config, LEGACY_HISTORY_DIR};
use crate::error::GatewayError;

/// Batches queued that wake the writer before its flush is due, whatever their bytes (each
/// entry costs about as much again as a 10-sample batch's samples): a few wake-ups a second at
/// 10 000 batches a second, and half a megabyte waiting.
pub const DRAIN_BATCHES: usize = 2048;

/// A checkpoint of a sensor's correction state is kept at least this often, by the sensor's
/// clock: a replay starts from the checkpoint before the first batch it serves.
pub const CHECKPOINT_INTERVAL_NS: i64 = 60_000_000_000;
/// ... or after this many batches, whatever the clock says.
pub const CHECKPOINT_INTERVAL_BATCHES: u32 = 6000;

/// The batches waiting for the writer: their samples and checkpoints in one buffer, and what
/// the history keeps of each beside it. The writer takes it whole and hands back an empty one.
#[derive(Default)]
struct Pending {
    bytes: Vec<u8>,
    batches: Vec<Waiting>,
}

/// One batch in [`Pending`]: its samples and checkpoint are ranges of the buffer.
struct Waiting {
    /// In place: the writer looks its sensor up by it, and a reference to the sensor's entry
    /// would be one more line for it to fetch, and for the sensor's next batch to fetch back.
    sensor: InlineId,
    kept: Kept<Range<usize>>,
    checkpoint: Option<Range<usize>>,
}

impl Pending {
    /// Empties it, keeping its memory up to a few times what the writer lets gather: a
    /// buffer that shrank and grew again whenever the writer took it late would be fresh
    /// pages to fault in each time (it is mapped, above the allocator's threshold), the costly
    /// part of writing on a virtual machine (BENCHMARKS.md, "History on and off").
    fn clear(&mut self, drain_bytes: usize) {
        self.bytes.clear();
        self.batches.clear();
        // After a spike (a disk that stalled), give the memory back.
        if self.bytes.capacity() > 8 * drain_bytes {
            self.bytes.shrink_to(2 * drain_bytes);
        }
        if self.batches.capacity() > 8 * DRAIN_BATCHES {
            self.batches.shrink_to(2 * DRAIN_BATCHES);
        }
    }
}

/// The history's counters, as status and metrics show them.
#[derive(Debug, Default)]
pub struct SinkCounters {
    /// Batches handed to the history.
    pub offered: AtomicU64,
    /// Batches not kept because the queue was full (the disk did not keep up).
    pub dropped: AtomicU64,
    /// Batches handed to the history and then made durable or dropped: what a sync waits for.
    pub settled: AtomicU64,
}

/// The queue between the workers and the writer thread.
pub struct Sink {
    state: Mutex<SinkState>,
    wake: Condvar,
    settled: Condvar,
    /// Most bytes of samples and checkpoints waiting.
    capacity_bytes: usize,
    /// Bytes waiting that wake the writer before its flush is due: a sixteenth of the capacity.
    drain_bytes: usize,
    pub counters: SinkCounters,
    pub history: Arc<History>,
    /// The arrival number of this run's first batch: what the history held before is below.
    pub first_arrival: u64,
}

struct SinkState {
    pending: Pending,
    /// A reader waits for everything offered up to this count to be durable.
    sync_to: u64,
    closed: bool,
}

impl Sink {
    /// Offers a corrected batch of `sensor`: `view` as received, the verdict and the
    /// calibration version it was corrected with, and the correction state before it when a
    /// checkpoint was due. False (and counted) when the queue is full or closed.
    pub fn offer(
        &self,
        sensor: &InlineId,
        view: &RawBatchView<'_>,
        verdict: Verdict,
        calibration_version: u64,
        checkpoint: Option<&[u8]>,
    ) -> bool {
        self.counters.offered.fetch_add(1, Relaxed);
        let samples = view.sample_bytes();
        let mut s = self.lock();
        let room = self.capacity_bytes.saturating_sub(s.pending.bytes.len());
        if s.closed || samples.len() + checkpoint.map_or(0, <[u8]>::len) > room {
            drop(s);
            self.counters.dropped.fetch_add(1, Relaxed);
            self.counters.settled.fetch_add(1, Relaxed);
            return false;
        }
        let p = &mut s.pending;
        let checkpoint = checkpoint.map(|ck| {
            let at = p.bytes.len();
            p.bytes.extend_from_slice(ck);
            at..p.bytes.len()
        });
        let at = p.bytes.len();
        p.bytes.extend_from_slice(samples);
        let h = &view.header;
        // Wakes the writer once, as the queue crosses its mark: it takes the queue whole.
        let crossed = (p.bytes.len() >= self.drain_bytes && at < self.drain_bytes)
            || p.batches.len() + 1 == DRAIN_BATCHES;
        if crossed {
            self.wake.notify_one();
        }
        p.batches.push(Waiting {
            sensor: *sensor,
            kept: Kept {
                arrival: 0,
                sequence: h.sequence,
                timestamp_ns: h.timestamp_ns,
                sample_rate_hz: h.sample_rate_hz,
                temperature_c: view.temperature_c,
                calibration_version,
                verdict,
                samples: at..p.bytes.len(),
            },
            checkpoint,
        });
        true
    }

    /// Batches waiting for the writer.
    pub fn queued(&self) -> usize {
        self.lock().pending.batches.len()
    }

    /// Waits, at most `timeout`, until every batch offered before the call is durable (or was
    /// dropped); true if it is.
    pub fn sync(&self, timeout: Duration) -> bool {
        let target = self.counters.offered.load(Relaxed);
        let deadline = Instant::now() + timeout;
        let mut s = self.lock();
        s.sync_to = s.sync_to.max(target);
        self.wake.notify_one();
        while self.counters.settled.load(Relaxed) < target {
            let left = deadline.saturating_duration_since(Instant::now());
            if left.is_zero() || s.closed {
                return false;
            }
            s = self
                .settled
                .wait_timeout(s, left)
                .unwrap_or_else(|p| p.into_inner())
                .0;
        }
        true
    }

    /// The history's figures, for status (and, field by field, metrics).
    pub fn status(&self) -> HistoryStatus {
        let h = &self.history;
        let stats = h.stats();
        let c = &h.counters;
        HistoryStatus {
            bytes: stats.bytes,
            max_bytes: h.config().max_bytes,
            retention_s: h.config().retention.as_secs(),
            segments: stats.segments as u64,
            oldest_ns: stats.oldest_ns,
            newest_ns: stats.newest_ns,
            written_batches: c.written_batches.load(Relaxed),
            dropped_batches: self.counters.dropped.load(Relaxed),
            queued_batches: self.queued() as u64,
            deleted_segments: c.deleted_segments.load(Relaxed),
            deleted_bytes: c.deleted_bytes.load(Relaxed),
            damaged_blocks: c.damaged_blocks.load(Relaxed),
            write_errors: c.write_errors.load(Relaxed),
        }
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, SinkState> {
        // The state is a buffer, a list and two plain fields: consistent after any panic.
        self.state.lock().unwrap_or_else(|p| p.into_inner())
    }
}

/// The writer thread.
pub struct Recorder {
    pub sink: Arc<Sink>,
    thread: Option<std::thread::JoinHandle<()>>,
    stop: Arc<AtomicBool>,
}

impl Recorder {
    /// Starts the writer thread over `writer`, with a queue of at most `capacity_bytes` of
    /// samples and checkpoints.
    pub fn start(
        writer: Writer,
        capacity_bytes: usize,
        flush_interval: Duration,
    ) -> std::io::Result<Recorder> {
        let sink = Arc::new(Sink {
            state: Mutex::new(SinkState {
                pending: Pending::default(),
                sync_to: 0,
                closed: false,
            }),
            wake: Condvar::new(),
            settled: Condvar::new(),
            capacity_bytes: capacity_bytes.max(1),
            drain_bytes: (capacity_bytes / 16).max(1),
            counters: SinkCounters::default(),
            history: writer.history().clone(),
            first_arrival: writer.next_arrival(),
        });
        let stop = Arc::new(AtomicBool::new(false));
        let (s, st) = (sink.clone(), stop.clone());
        let thread = std::thread::Builder::new()
            .name("triax-history".into())
            .spawn(move || run(writer, &s, &st, flush_interval))?;
        Ok(Recorder {
            sink,
            thread: Some(thread),
            stop,
        })
    }

    /// Takes what is queued, flushes it, and stops the thread.
    pub fn stop(&mut self) {
        self.stop.store(true, Relaxed);
        {
            let mut s = self.sink.lock();
            s.closed = true;
        }
        self.sink.wake.notify_all();
        if let Some(t) = self.thread.take() {
            if t.join().is_err() {
                tracing::error!("history writer ended abnormally");
            }
        }
    }
}

impl Drop for Recorder {
    fn drop(&mut self) {
        self.stop();
    }
}

/// Opens the history and starts its writer thread; none when the history is off.
pub async fn open(config: &Config) -> Result<Option<Recorder>, GatewayError> {
    let Some(h) = config.history.clone() else {
        return Ok(None);
    };
    let history_config = h.history_config(&config.building, &config.gateway_name);
    let opened = tokio::task::spawn_blocking(move || {
        triax_history::History::open(history_config).map(|o| (o, h))
    })
    .await
    .map_err(|e| GatewayError::Task(e.to_string()))?
    .map_err(GatewayError::History)?;
    let (o, h) = opened;
    let building = config.building.as_str();
    match &o.owner {
        triax_history::OwnerCheck::Created => {
            tracing::info!(path = %h.path.display(), building, "history created for this building");
        }
        triax_history::OwnerCheck::Adopted => tracing::warn!(
            path = %h.path.display(),
            building,
            "history: made before histories recorded their building; adopted as this building's \
             (if it holds another building's batches, stop the gateway and give it another path)"
        ),
        triax_history::OwnerCheck::Confirmed {
            recorded_gateway_name: Some(name),
        } => tracing::info!(
            path = %h.path.display(),
            created_by = %name,
            "history created by this building's gateway under another name"
        ),
        triax_history::OwnerCheck::Confirmed { .. } | triax_history::OwnerCheck::Unchecked => {}
    }
    // The default used to be one `triax-history` per folder of stores; after an upgrade it is
    // not served any more, and which building's it is cannot be known, so it is only pointed at.
    let legacy = config
        .store_path
        .parent()
        .unwrap_or(Path::new(""))
        .join(LEGACY_HISTORY_DIR);
    if h.path == default_history_path(&config.store_path, &config.building)
        && !legacy.join(triax_history::OWNER_FILE).exists()
        && legacy.is_dir()
    {
        tracing::warn!(
            legacy = %legacy.display(),
            path = %h.path.display(),
            "history: an older history beside the store is not served; if it is this building's, \
             stop the gateway and move it to the path in use, or set [history] path to it"
        );
    }
    if o.cut_bytes > 0 || o.rescanned_blocks > 0 {
        tracing::warn!(
            cut_bytes = o.cut_bytes,
            rescanned_blocks = o.rescanned_blocks,
            "history: a torn end was cut after a crash (what was flushed is kept)"
        );
    }
    let stats = o.history.stats();
    tracing::info!(path = %h.path.display(), segments = stats.segments, bytes = stats.bytes, "history open");
    let recorder = Recorder::start(o.writer, h.queue_bytes, h.flush_interval)
        .map_err(|e| GatewayError::Task(format!("starting the history writer: {e}")))?;
    Ok(Some(recorder))
}

fn run(mut writer: Writer, sink: &Sink, stop: &AtomicBool, flush_interval: Duration) {
    let mut next_flush = Instant::now() + flush_interval;
    let mut taken = Pending::default();
    let mut unflushed = 0u64;
    let mut write_errors = 0u64;
    loop {
        let (sync_wanted, closing) = {
            let mut s = sink.lock();
            // Asleep until the flush is due, a sync is asked, the queue crossed its mark
            // (`offer` wakes it then), or the sink closes.
            loop {
                let wanted = s.sync_to > sink.counters.settled.load(Relaxed);
                let full = s.pending.bytes.len() >= sink.drain_bytes
                    || s.pending.batches.len() >= DRAIN_BATCHES;
                let left = next_flush.saturating_duration_since(Instant::now());
                if s.closed || stop.load(Relaxed) || wanted || full || left.is_zero() {
                    break;
                }
                s = sink
                    .wake
                    .wait_timeout(s, left)
                    .unwrap_or_else(|p| p.into_inner())
                    .0;
            }
            std::mem::swap(&mut s.pending, &mut taken);
            (
                s.sync_to > sink.counters.settled.load(Relaxed),
                s.closed || stop.load(Relaxed),
            )
        };
        for w in &taken.batches {
            let kept = w.kept.with_samples(&taken.bytes[w.kept.samples.clone()]);
            let checkpoint = w.checkpoint.clone().map(|r| &taken.bytes[r]);
            writer.append(&w.sensor, kept, checkpoint);
            unflushed += 1;
        }
        taken.clear(sink.drain_bytes);
        let now = Instant::now();
        if now >= next_flush || sync_wanted || closing {
            if let Err(e) = writer.flush() {
                write_errors += 1;
                // First and then every hundredth: a full disk must not flood the log.
                if write_errors == 1 || write_errors % 100 == 0 {
                    tracing::error!(cause = %e, errors = write_errors, "history flush failed: batches lost");
                }
            }
            sink.counters.settled.fetch_add(unflushed, Relaxed);
            unflushed = 0;
            sink.settled.notify_all();
            next_flush = now + flush_interval;
        }
        if closing && sink.lock().pending.batches.is_empty() {
            return;
        }
    }
}
