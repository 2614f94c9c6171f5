//! Backfill: the batches a sequence gap or the gateway's own downtime cost, fetched from the
//! sensor node's buffer (`triax/<b>/buffer/<s>`, PROTOCOL.md §5.4), corrected as the live path
//! would have corrected them, kept in the history and published flagged `late` (§2.3).
//!
//! **What asks.** A sensor's worker, without waiting: on a live batch judged a gap, for the
//! numbers between the last accepted batch and it, with the kernel's state before the gap; and
//! on the first batch the gateway meets of a sensor after it started, for every hole the history
//! it inherited has in the span a buffer can fill (found here, off the sample path, from the
//! runs of numbers it kept before this run: [`triax_history::History::kept_runs`]): what the
//! downtime cost, and what a kill cost a fill under way; for a sensor new to the history, the
//! numbers below its first batch. A request the queue cannot take is counted
//! (`backfill.refused_requests` in status) and the hole stays a hole.
//!
//! **How.** One request at a time per sensor, [`CONCURRENT`] sensors at once, each on a blocking
//! thread: a Zenoh query at `DataLow` priority, so the replies queue behind live data, with no
//! consolidation. Replies are checked (the sensor's key, a raw batch that parses, the sensor
//! its header names, a number inside the range and above the last taken, a time strictly
//! between the batches around the hole) and anything else is counted
//! (`backfill.rejected_replies`) and skipped. What an answer lacked is asked again while the
//! last answer brought something ([`ATTEMPTS`]), and all fills together go at most
//! `[backfill] max_batches_per_s`, so that an outage's return does not crowd out the live
//! stream. Batches are corrected in chunks of [`CHUNK`] under the shard's lock
//! (`sample_path::LateDoor`) and published after it, so that a live batch waits
//! for at most one chunk's correction, with a kernel of their own restored from the state
//! before the gap (a cold one after the gateway's restart, as the live path was then): the live
//! kernel is not touched, and the live stream goes on while a hole fills.
//!
//! **Replays.** The first late batch of each chunk carries a checkpoint of the late kernel,
//! and the next live batch one of the live kernel: the history holds runs of two kinds, each
//! starting from its own state, and a replay, which restores every checkpoint it meets, gives
//! back what was published for both (`tests/tests/gateway/backfill.rs`).

use std::collections::{HashSet, VecDeque};
use std::sync::atomic::{AtomicU64, Ordering::Relaxed};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use tokio::sync::mpsc;
use triax_history::History;
use triax_protocol::{BuildingId, Key, RawBatchView, SensorId};
use zenoh::qos::{CongestionControl, Priority};
use zenoh::query::ConsolidationMode;
use zenoh::Wait;

use super::{Context as Services, Task};
use crate::config::BackfillSettings;
use crate::sample_path::SamplePath;
use crate::sample_path::{Holes, LateDoor, LateRun, Need, Request, SensorKernel};
use crate::shutdown::Shutdown;
use crate::state::{BackfillCounters, SensorTable};

/// Sensors whose holes are filled at the same time.
pub const CONCURRENT: usize = 4;
/// Late batches corrected per hold of the shard's lock.
pub const CHUNK: usize = 16;
/// Requests waiting for a free slot; more are refused and counted.
pub const QUEUE: usize = 8192;
/// Requests of one sensor waiting; more are refused and counted (a node whose numbering jumps
/// at every batch must not fill the queue with its holes).
pub const PER_SENSOR: usize = 8;

/// Spaces late batches at most `per_s` a second, all fills together.
#[derive(Debug)]
struct Pace {
    per_s: f64,
    next: Mutex<std::time::Instant>,
}

impl Pace {
    /// Waits until `n` more batches are within the rate.
    fn take(&self, n: usize) {
        let due = {
            let mut next = self.next.lock().unwrap_or_else(|p| p.into_inner());
            let now = std::time::Instant::now();
            let start = (*next).max(now);
            *next = start + Duration::from_secs_f64(n as f64 / self.per_s);
            start
        };
        if let Some(wait) = due.checked_duration_since(std::time::Instant::now()) {
            std::thread::sleep(wait);
        }
    }
}

/// The backfill's queue: the shards' end, to hand to the sample path, and the backfill's.
pub fn channel() -> (Holes, mpsc::Receiver<Request>) {
    let (tx, rx) = mpsc::channel(QUEUE);
    (Holes::new(tx, Arc::new(BackfillCounters::default())), rx)
}

/// What [`run`] needs.
pub struct Context {
    pub building: BuildingId,
    pub session: zenoh::Session,
    pub table: Arc<SensorTable>,
    /// Where fetched batches go back into the sample path.
    pub door: LateDoor,
    pub counters: Arc<BackfillCounters>,
    /// The history and the first arrival number of this run, for [`Need::First`].
    pub history: Option<(Arc<History>, u64)>,
    pub settings: BackfillSettings,
}

/// [`Context`] with what the fills share.
struct Filling {
    ctx: Context,
    pace: Option<Pace>,
}

impl std::ops::Deref for Filling {
    type Target = Context;
    fn deref(&self) -> &Context {
        &self.ctx
    }
}

/// Starts the backfill over the queue `requests` (the other end of the [`Holes`] the sample
/// path was given, whose counters are `counters`).
pub fn start(
    ctx: &Services,
    path: &SamplePath,
    settings: BackfillSettings,
    counters: Arc<BackfillCounters>,
    requests: mpsc::Receiver<Request>,
) -> Task {
    let backfill = Context {
        building: ctx.config.building.clone(),
        session: ctx.session.clone(),
        table: ctx.table.clone(),
        door: path.late_door(),
        counters,
        history: path
            .history()
            .map(|sink| (sink.history.clone(), sink.first_arrival)),
        settings,
    };
    tokio::spawn(run(backfill, requests, ctx.shutdown.clone()))
}

/// Serves requests until shutdown: at most one per sensor and [`CONCURRENT`] in all at a time.
pub async fn run(ctx: Context, mut rx: mpsc::Receiver<Request>, mut shutdown: Shutdown) {
    let pace = ctx.settings.max_batches_per_s.map(|per_s| Pace {
        per_s,
        next: Mutex::new(std::time::Instant::now()),
    });
    let ctx = Arc::new(Filling { ctx, pace });
    let mut waiting: VecDeque<Request> = VecDeque::new();
    let mut busy: HashSet<SensorId> = HashSet::new();
    let mut running = tokio::task::JoinSet::new();
    loop {
        // Start what can start, in order of asking; a sensor's requests keep their order.
        let mut i = 0;
        while running.len() < CONCURRENT && i < waiting.len() {
            if busy.contains(&waiting[i].sensor) {
                i += 1;
                continue;
            }
            let Some(request) = waiting.remove(i) else {
                break;
            };
            busy.insert(request.sensor.clone());
            let ctx = ctx.clone();
            running.spawn_blocking(move || {
                let sensor = request.sensor.clone();
                fill(&ctx, request);
                sensor
            });
        }
        tokio::select! {
            r = rx.recv() => match r {
                Some(r) => {
                    let same = waiting.iter().filter(|w| w.sensor == r.sensor).count();
                    if same < PER_SENSOR {
                        waiting.push_back(r);
                    } else {
                        ctx.counters.refused.fetch_add(1, Relaxed);
                    }
                }
                None => break,
            },
            Some(done) = running.join_next(), if !running.is_empty() => {
                match done {
                    Ok(sensor) => { busy.remove(&sensor); }
                    Err(e) => {
                        // A panic in a fill (a bug): its sensor stays busy, the others go on.
                        tracing::error!(cause = %e, "backfill task failed");
                    }
                }
            }
            _ = shutdown.recv() => break,
        }
    }
    // Fills under way end with their query's timeout at worst; they hold no lock across it.
    running.detach_all();
}

/// One hole: what to ask, and the state its batches start from.
struct Hole {
    from_seq: u64,
    to_seq: u64,
    after_ns: i64,
    before_ns: i64,
    /// None: a fresh kernel.
    state: Option<Vec<u8>>,
}

/// The holes a request asks to fill, oldest first.
fn holes_of(ctx: &Context, sensor: &SensorId, need: Need) -> Vec<Hole> {
    match need {
        Need::Gap {
            from_seq,
            to_seq,
            after_ns,
            before_ns,
            state,
        } => vec![Hole {
            from_seq,
            to_seq,
            after_ns,
            before_ns,
            state: Some(state),
        }],
        Need::First {
            sequence,
            timestamp_ns,
        } => {
            let Some((history, first_arrival)) = ctx.history.as_ref() else {
                return Vec::new();
            };
            let from_seq = sequence.saturating_sub(ctx.settings.max_batches);
            let runs = match history.kept_runs(sensor, *first_arrival, from_seq, timestamp_ns) {
                Ok(runs) => runs,
                Err(e) => {
                    tracing::warn!(sensor = %sensor, cause = %e, "backfill: history unreadable; the holes stay");
                    return Vec::new();
                }
            };
            // Below the first run the history holds (within the span a buffer keeps), between
            // the runs, and from the last to this batch: a node's first seconds, before its
            // link reached the gateway (and late batches of them a kill did not let the history
            // keep), what the gateway's downtime cost, and what a kill cost a fill under way. A
            // node that numbered afresh (not a `triax-node`) holds nothing below this batch's
            // number, and a history that holds the whole span starts its first run at its edge.
            let first_seq = runs.first().map_or(sequence, |r| r.first_seq);
            let first_ns = runs.first().map_or(timestamp_ns, |r| r.first_ns);
            let mut holes = Vec::new();
            if first_seq > from_seq && first_seq <= sequence {
                holes.push(Hole {
                    from_seq,
                    to_seq: first_seq - 1,
                    after_ns: i64::MIN,
                    before_ns: first_ns,
                    state: None,
                });
            }
            for (i, run) in runs.iter().enumerate() {
                let (to_seq, before_ns) = match runs.get(i + 1) {
                    Some(next) => (next.first_seq - 1, next.first_ns),
                    None => (sequence.saturating_sub(1), timestamp_ns),
                };
                if run.last_seq < to_seq && run.last_seq < sequence && run.last_ns < before_ns {
                    holes.push(Hole {
                        from_seq: run.last_seq + 1,
                        to_seq,
                        after_ns: run.last_ns,
                        before_ns,
                        state: None,
                    });
                }
            }
            holes
        }
    }
}

/// Fills a request's holes: query, check, correct in chunks; then asks again, up to
/// [`ATTEMPTS`] times in all, for numbers still missing, as long as the last round brought
/// something (a reply lost on a busy link comes again; a number the buffer does not hold does
/// not). Runs on a blocking thread.
fn fill(ctx: &Filling, request: Request) {
    let Request { sensor, need } = request;
    let mut holes = holes_of(ctx, &sensor, need);
    for _ in 0..ATTEMPTS {
        let mut left = Vec::new();
        let mut got = 0;
        for hole in holes {
            let filled = fill_hole(ctx, &sensor, hole);
            got += filled.received;
            left.extend(filled.missing);
        }
        if left.is_empty() || got == 0 {
            return;
        }
        holes = left;
    }
}

/// Queries for one hole, in all: the first and the retries of what is still missing.
pub const ATTEMPTS: usize = 3;

/// What a query for one hole brought.
struct Filled {
    received: usize,
    /// Numbers still missing, as holes of their own (with no state: a retried stretch starts
    /// its filters afresh, and its first batch carries `sequence_gap` if numbers before it
    /// were filled already).
    missing: Vec<Hole>,
}

fn fill_hole(ctx: &Filling, sensor: &SensorId, mut hole: Hole) -> Filled {
    let c = &ctx.counters;
    if hole.from_seq > hole.to_seq {
        return Filled {
            received: 0,
            missing: Vec::new(),
        };
    }
    let wanted = hole.to_seq - hole.from_seq + 1;
    if wanted > ctx.settings.max_batches {
        hole.from_seq = hole.to_seq + 1 - ctx.settings.max_batches;
    }
    let wanted = hole.to_seq - hole.from_seq + 1;
    c.wanted_batches.fetch_add(wanted, Relaxed);
    let key = Key::Buffer(ctx.building.clone(), sensor.clone()).to_string();
    let selector = format!("from_seq={};to_seq={}", hole.from_seq, hole.to_seq);
    c.queries.fetch_add(1, Relaxed);
    // Zenoh's receive thread hands replies over and never waits: a full queue would stall the
    // live stream on the same link. Room for every batch asked (at most `max_batches`) and a
    // few errors; a node that sends more is cut off, counted.
    let (tx, replies) = std::sync::mpsc::sync_channel(wanted as usize + 16);
    let overflow = Arc::new(AtomicU64::new(0));
    let o = overflow.clone();
    let sent = ask(ctx, &key, &selector, move |reply| {
        if tx.try_send(reply).is_err() {
            o.fetch_add(1, Relaxed);
        }
    });
    if let Err(e) = sent {
        c.failed_queries.fetch_add(1, Relaxed);
        tracing::warn!(sensor = %sensor, cause = %e, "backfill query not sent");
        return Filled {
            received: 0,
            missing: Vec::new(),
        };
    }
    let settings = ctx.table.settings_of(sensor);
    let kernel = match hole.state.as_deref() {
        Some(bytes) => SensorKernel::restore(bytes).unwrap_or_else(|| SensorKernel::new(settings)),
        None => SensorKernel::new(settings),
    };
    let mut run = LateRun {
        kernel,
        expected: hole.from_seq,
        checkpoint_due: true,
    };
    let mut chunk: Vec<Vec<u8>> = Vec::with_capacity(CHUNK);
    let mut errors = 0u64;
    // The last batch taken (number and time): where the next must lie beyond, and the edge of
    // what is still missing.
    let mut last: Option<(u64, i64)> = None;
    let mut missing = Vec::new();
    let flush = |chunk: &mut Vec<Vec<u8>>, run: &mut LateRun| {
        if chunk.is_empty() {
            return;
        }
        if let Some(pace) = &ctx.pace {
            pace.take(chunk.len());
        }
        match ctx.door.correct_and_publish(sensor, run, chunk) {
            Some(published) => {
                c.late_batches.fetch_add(published as u64, Relaxed);
            }
            // The sensor was forgotten meanwhile.
            None => {
                c.rejected.fetch_add(chunk.len() as u64, Relaxed);
            }
        }
        chunk.clear();
    };
    let mut received = 0;
    // Ends when Zenoh drops the callback: the query's end.
    while let Ok(reply) = replies.recv() {
        let sample = match reply.result() {
            Ok(s) => s,
            Err(e) => {
                errors += 1;
                tracing::warn!(sensor = %sensor, cause = %String::from_utf8_lossy(&e.payload().to_bytes()), "backfill: the buffer answered an error");
                continue;
            }
        };
        let payload = sample.payload().to_bytes();
        let after = last.map_or((hole.from_seq, hole.after_ns), |(seq, ts)| (seq + 1, ts));
        // The sensor's key, a raw batch of that sensor, numbered and stamped after the last
        // one taken and inside the hole.
        let batch = RawBatchView::parse(&payload)
            .ok()
            .filter(|v| &v.header.sensor_id == sensor && sample.key_expr().as_str() == key)
            .map(|v| (v.header.sequence, v.header.timestamp_ns))
            .filter(|&(seq, ts)| {
                (after.0..=hole.to_seq).contains(&seq) && ts > after.1 && ts < hole.before_ns
            });
        let Some((seq, ts)) = batch else {
            c.rejected.fetch_add(1, Relaxed);
            continue;
        };
        if seq > after.0 {
            missing.push(Hole {
                from_seq: after.0,
                to_seq: seq - 1,
                after_ns: after.1,
                before_ns: ts,
                state: None,
            });
        }
        last = Some((seq, ts));
        received += 1;
        chunk.push(payload.into_owned());
        if chunk.len() == CHUNK {
            flush(&mut chunk, &mut run);
        }
    }
    flush(&mut chunk, &mut run);
    let (next_seq, after_ns) = last.map_or((hole.from_seq, hole.after_ns), |(s, t)| (s + 1, t));
    if next_seq <= hole.to_seq {
        missing.push(Hole {
            from_seq: next_seq,
            to_seq: hole.to_seq,
            after_ns,
            before_ns: hole.before_ns,
            state: None,
        });
    }
    let cut_off = overflow.load(Relaxed);
    c.rejected.fetch_add(cut_off, Relaxed);
    if errors > 0 {
        c.failed_queries.fetch_add(1, Relaxed);
    }
    tracing::debug!(sensor = %sensor, from_seq = hole.from_seq, to_seq = hole.to_seq, received, cut_off, "backfill query done");
    Filled { received, missing }
}

/// Longest a fill waits for the node's buffer to be reachable: after a link comes back, the
/// node's first batch can reach the gateway before the router has passed on its buffer's
/// declaration, and a query sent then finds nobody to answer.
pub const REACH_WAIT: Duration = Duration::from_secs(2);

/// Sends the buffer query (`parameters` on `key`) once a queryable on the key is known, or
/// after [`REACH_WAIT`] without one; replies go to `callback`, which Zenoh drops at the
/// query's end.
fn ask(
    ctx: &Context,
    key: &str,
    parameters: &str,
    callback: impl Fn(zenoh::query::Reply) + Send + Sync + 'static,
) -> zenoh::Result<()> {
    // Declared only to learn whether a queryable on the key is known (a matching status).
    let querier = ctx.session.declare_querier(key.to_owned()).wait()?;
    if !querier.matching_status().wait()?.matching() {
        let listener = querier.matching_listener().wait()?;
        let deadline = std::time::Instant::now() + REACH_WAIT;
        // The status may have changed between the look and the listener.
        while !querier.matching_status().wait()?.matching() {
            match listener.recv_deadline(deadline) {
                Ok(Some(status)) if status.matching() => break,
                Ok(Some(_)) => continue,
                _ => break,
            }
        }
    }
    drop(querier);
    ctx.session
        .get(format!("{key}?{parameters}"))
        .consolidation(ConsolidationMode::None)
        .priority(Priority::DataLow)
        // Replies go at the query's congestion control: blocked, not dropped, on a busy link.
        .congestion_control(CongestionControl::Block)
        .timeout(ctx.settings.timeout)
        .callback(callback)
        .wait()
}
