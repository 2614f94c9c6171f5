//! Correction shards: each owns a share of the sensors (by a hash of the id), corrects their
//! raw batches with [`SensorKernel`] and publishes the corrected batch and, for inclinometers,
//! the tilt stream. Under [`Overload::DropOldest`](crate::config::Overload) a shard belongs to
//! a worker thread that pops its batches from its [`Inbox`]; under `Backpressure` Zenoh's
//! receive thread runs it directly, behind a mutex.
//!
//! A sensor always lands on the same shard, so its batches are corrected in order and its
//! state (sequence tracker, filter memory, output keys) is touched by one thread at a time.
//! Events name their sensor in a field rather than in a span: a span per sensor would cost
//! every sensor a registry entry for the rare event.

use std::collections::HashMap;
use std::sync::atomic::Ordering::Relaxed;
use std::sync::{Arc, Mutex};

use triax_calibration::corrector::Corrector;
use triax_calibration_store::Store;
use triax_health::monitor::SensorHealth;
use triax_protocol::batch::{corrected_len, flags};
use triax_protocol::messages::TiltSample;
use triax_protocol::provenance::digest;
use triax_protocol::{
    to_json, BuildingId, InlineId, Key, Mode, RawBatchView, SensorId, SetKind, JSON_FORMAT_VERSION,
};
use zenoh::key_expr::KeyExpr;
use zenoh::qos::{CongestionControl, Priority};
use zenoh::Wait;

use super::health::{self, HealthFeed};
use super::history::{self, CHECKPOINT_INTERVAL_BATCHES, CHECKPOINT_INTERVAL_NS};
use super::inbox::{Inbox, Next};
use super::kernel::{BatchOutcome, Scratch, SensorKernel};
use super::late::{Holes, LateRun, Need, Request};
use super::outbox::{Outbox, Outgoing};
use super::seal::SealQueue;
use super::sequence::{SequenceTracker, Verdict};
use crate::clock::now_ns;
use crate::config::CorrectionMode;
use crate::state::{GatewayCounters, GroupSlot, SensorEntry, SensorTable, Signer};

/// A raw batch as it arrived: its sensor (the key's last chunk, checked at intake) and its
/// payload, copied out of Zenoh's receive buffer.
///
/// Why a copy: a Zenoh sample holds the whole buffer its link read it into (48 KiB), and
/// Zenoh keeps one for each link; a sample held past the link's next read (until the end of
/// its burst, or in a worker's inbox) had Zenoh allocate and zero a fresh buffer for that read,
/// 500 a second at a building's pace, and a full inbox could hold a buffer per batch
/// (BENCHMARKS.md, "A tenth look"). A batch's copy is its own size, about 150 bytes.
#[derive(Debug)]
pub struct Arrival {
    pub sensor: InlineId,
    pub payload: Box<[u8]>,
}

/// What every worker shares.
pub struct Shared {
    pub building: BuildingId,
    pub session: zenoh::Session,
    pub table: Arc<SensorTable>,
    pub counters: Arc<GatewayCounters>,
    /// [`crate::Config::declared_keys_max`].
    pub declared_keys_max: usize,
    /// [`crate::Config::declared_keys_idle`].
    pub declared_keys_idle_ns: i64,
    /// Where corrected batches are kept; none when the history is off.
    pub history: Option<Arc<history::Sink>>,
    /// The calibration store: the health checks mark suspect records in it (rarely: once per
    /// record at most), never read on the sample path.
    pub store: Arc<Store>,
    /// None: health checks off.
    pub health: Option<health::Reporting>,
    /// Where gaps are reported for backfill; none when it is off.
    pub backfill: Option<Holes>,
    /// Where corrected batches wait for the end of their receive burst.
    pub outbox: Arc<Outbox>,
    /// Signs the tilt samples and health reports put from here.
    pub signer: Arc<Signer>,
    /// Where the late batches' digests go to be sealed; None when nothing is signed.
    pub seals: Option<Arc<SealQueue>>,
}

/// A place in the `declared_keys_max` budget, given back when dropped.
struct Place(Arc<GatewayCounters>);

impl Drop for Place {
    fn drop(&mut self) {
        self.0.declared_keys.fetch_sub(1, Relaxed);
    }
}

/// A key a sensor uses: declared while the budget lasts, plain after. Dropping a declared key
/// undeclares it (Zenoh's own drop) and then gives its place back.
enum SensorKey {
    Declared {
        key: KeyExpr<'static>,
        _place: Place,
    },
    Plain(KeyExpr<'static>),
}

impl SensorKey {
    fn key_expr(&self) -> &KeyExpr<'static> {
        match self {
            SensorKey::Declared { key, .. } | SensorKey::Plain(key) => key,
        }
    }

    fn is_declared(&self) -> bool {
        matches!(self, SensorKey::Declared { .. })
    }
}

impl Shared {
    /// Takes `n` places in the declared-key budget at once, or none: a sensor's keys are
    /// declared together or not at all.
    fn reserve(&self, n: usize) -> Option<Vec<Place>> {
        if self.counters.keys_undeclared.load(Relaxed) {
            return None;
        }
        self.counters
            .declared_keys
            .fetch_update(Relaxed, Relaxed, |taken| {
                (taken + n <= self.declared_keys_max).then_some(taken + n)
            })
            .ok()?;
        Some((0..n).map(|_| Place(self.counters.clone())).collect())
    }

    /// `key` declared to Zenoh in the place given, so that Zenoh keeps its routes.
    fn declare(&self, key: &Key, place: Place) -> zenoh::Result<SensorKey> {
        // Dropped on error, the place goes back to the budget.
        let key = self.session.declare_keyexpr(key.to_string()).wait()?;
        Ok(SensorKey::Declared { key, _place: place })
    }

    /// From now on every key is used undeclared (see [`Shard::reassign_keys`]).
    fn turn_keys_undeclared(&self) {
        if !self.counters.keys_undeclared.swap(true, Relaxed) {
            tracing::warn!(
                budget_keys = self.declared_keys_max,
                "more streaming sensors than declared_keys_mib holds: every key is used \
                 undeclared from now on (a partly declared gateway is the slowest; raise the \
                 budget to declare them all)"
            );
        }
    }
}

/// Which worker serves a sensor: FNV-1a of its id, so the choice is stable and cheap.
pub fn shard(sensor: &str, n_workers: usize) -> usize {
    let mut h: u64 = 0xcbf2_9ce4_8422_2325;
    for b in sensor.bytes() {
        h ^= u64::from(b);
        h = h.wrapping_mul(0x0100_0000_01b3);
    }
    (h % n_workers.max(1) as u64) as usize
}

/// The keys a sensor uses on Zenoh.
struct SensorKeys {
    /// The sensor's raw key, declared on the gateway's own session while the budget lasts.
    /// Not used to receive: holding it keeps a routing entry for the key, so Zenoh looks up the
    /// route of each incoming batch instead of matching the key against every subscription
    /// again, which it does for a key sent in full (as a node's publisher does unless it
    /// declared the key itself). That matching was a quarter of the gateway's CPU per batch
    /// (BENCHMARKS.md).
    input_route: Option<SensorKey>,
    corrected: SensorKey,
    /// Only for inclinometers.
    tilt: Option<SensorKey>,
    /// Whether these keys may be declared: not while the sensor is on probation (see
    /// `crate::state` (admission)), so that ids a flood names once take no place in the budget.
    declared: bool,
}

impl SensorKeys {
    /// Whether any of these keys holds a place in the declared-key budget.
    fn holds_places(&self) -> bool {
        self.input_route.is_some()
            || self.corrected.is_declared()
            || self.tilt.as_ref().is_some_and(SensorKey::is_declared)
    }

    fn new(shared: &Shared, entry: &SensorEntry, declare: bool) -> zenoh::Result<SensorKeys> {
        let (b, id) = (&shared.building, &entry.id);
        let needed = 2 + usize::from(entry.settings.tilt);
        let mut places = if declare {
            shared.reserve(needed)
        } else {
            None
        };
        let mut key = |k: Key| match places.as_mut().and_then(Vec::pop) {
            Some(place) => shared.declare(&k, place),
            None => KeyExpr::try_from(k.to_string()).map(SensorKey::Plain),
        };
        let input = key(Key::Raw(b.clone(), id.clone()))?;
        let keys = SensorKeys {
            input_route: input.is_declared().then_some(input),
            corrected: key(Key::Corrected(b.clone(), id.clone()))?,
            tilt: match entry.settings.tilt {
                true => Some(key(Key::Tilt(b.clone(), id.clone()))?),
                false => None,
            },
            declared: declare,
        };
        entry
            .counters
            .keys_declared
            .store(keys.holds_places(), Relaxed);
        Ok(keys)
    }
}

struct SensorState {
    entry: Arc<SensorEntry>,
    keys: SensorKeys,
    sequence: SequenceTracker,
    kernel: SensorKernel,
    next_tilt_ns: i64,
    /// Version of the last batch, to log changes once.
    last_version: Option<u64>,
    /// When the history is next owed a checkpoint, by the sensor's clock, and batches since
    /// the last one.
    next_checkpoint_ns: i64,
    since_checkpoint: u32,
    health: HealthFeed,
    /// The co-located pairs the sensor is in (field health).
    pairs: Vec<Arc<GroupSlot>>,
}

/// A sensor's state in its shard's table, with where the parts it holds apart were at its
/// last batch.
///
/// At a building's pace a sensor's state has left the cache since its last batch, and its
/// parts hang on one another: the table's slot names the state, the state its entry, the
/// entry its corrector. Loaded as the code reaches each, every one waits for the one before.
/// The slot keeps their addresses as of the last batch, so that one look at the slot asks
/// for all of them at once (BENCHMARKS.md, "A fourth look" and "A sixth look").
struct Slot {
    state: Box<SensorState>,
    /// Addresses and sizes, hints for [`prefetch_bytes`] only and never read through: a part
    /// replaced since (a new corrector, a new monitor) costs one useless load, not a fault.
    apart: [(usize, usize); 5],
}

impl Slot {
    /// A slot with no hints yet: its first batch, which made it, notes them at its end.
    fn new(state: SensorState) -> Slot {
        Slot {
            state: Box::new(state),
            apart: [(0, 0); 5],
        }
    }

    fn prefetch(&self) {
        prefetch_bytes(
            std::ptr::from_ref::<SensorState>(&self.state) as usize,
            std::mem::size_of::<SensorState>(),
        );
        for &(at, bytes) in &self.apart {
            prefetch_bytes(at, bytes);
        }
    }

    /// Notes where the state's parts are now, for the next batch's [`Slot::prefetch`].
    fn remember_apart(&mut self) {
        fn part<T>(value: Option<&T>) -> (usize, usize) {
            value.map_or((0, 0), |v| {
                (std::ptr::from_ref(v) as usize, std::mem::size_of::<T>())
            })
        }
        let s = &*self.state;
        let key = s.keys.corrected.key_expr().as_str();
        let corrector = s.entry.corrector_guard();
        // Its head and the set the sensor's mode corrects with; both sets in split mode.
        let (head, set) = match (corrector.as_deref(), s.entry.settings.mode) {
            (None, _) => ((0, 0), (0, 0)),
            (Some(c), CorrectionMode::Split) => (part(Some(c)), (0, 0)),
            (Some(c), mode) => {
                let kind = match mode {
                    CorrectionMode::Static => SetKind::Static,
                    _ => SetKind::Dynamic,
                };
                let at = std::ptr::from_ref(c) as usize;
                ((at, Corrector::HEAD_BYTES), part(Some(c.set(kind))))
            }
        };
        self.apart = [
            part(Some(&*s.entry)),
            head,
            set,
            // Its first bytes only: the rest waits for a block's end.
            s.health.monitor().map_or((0, 0), |m| {
                (
                    std::ptr::from_ref(m) as usize,
                    SensorHealth::PER_BATCH_BYTES,
                )
            }),
            // The key's text, and the reference count just before it that publishing it
            // increments.
            ((key.as_ptr() as usize).saturating_sub(16), key.len() + 16),
        ];
    }
}

impl std::ops::Deref for Slot {
    type Target = SensorState;

    fn deref(&self) -> &SensorState {
        &self.state
    }
}

impl std::ops::DerefMut for Slot {
    fn deref_mut(&mut self) -> &mut SensorState {
        &mut self.state
    }
}

/// Longest a worker goes on correcting its queued batches after the shutdown fired.
pub const SHUTDOWN_DRAIN: std::time::Duration = std::time::Duration::from_secs(2);

/// The sensors of one shard, and the working memory their batches share.
#[derive(Default)]
pub struct Shard {
    /// foldhash rather than the standard SipHash: two lookups a batch, of a few bytes each.
    /// Its seed is random per table and the table is bounded ([`SensorTable`]), so ids chosen
    /// to collide cost a flooding node no more than its own batches.
    sensors: HashMap<InlineId, Slot, foldhash::fast::RandomState>,
    scratch: Scratch,
    /// Batches handled since the last sweep for forgotten sensors.
    since_sweep: u32,
    last_sweep: Option<std::time::Instant>,
    /// Since when streaming sensors of this worker wait for room in the declared-key budget.
    waiting_since: Option<std::time::Instant>,
}

/// How many batches ahead of its turn a burst's batch has its sensor's state asked for
/// ([`Shard::handle_burst`]): a state is about a dozen lines, and the processor tracks a few
/// dozen misses at once.
const BURST_AHEAD: usize = 4;

/// One shard per worker, shared by the worker and the receive threads.
pub type Shards = Arc<Vec<Arc<Mutex<Shard>>>>;

/// Batches between two looks at the clock for a sweep.
const SWEEP_CHECK_BATCHES: u32 = 256;
/// Least time between two sweeps of a shard.
const SWEEP_INTERVAL: std::time::Duration = std::time::Duration::from_secs(1);

/// The shard, whoever held it last: a panic while handling (a bug) leaves at most one sensor's
/// filter memory mid-batch, and the shard still serves its other sensors.
pub fn lock_shard(shard: &Mutex<Shard>) -> std::sync::MutexGuard<'_, Shard> {
    shard.lock().unwrap_or_else(|p| p.into_inner())
}

/// Runs one worker, on a thread of its own, until its inbox closes; then corrects what is
/// still queued, for at most the drain time given to [`Inbox::close`] ([`SHUTDOWN_DRAIN`]),
/// and counts the rest as dropped.
///
/// A thread and not an async task: publishing blocks while a consumer is slow (Zenoh's
/// blocking congestion control), and a task blocked so would hold a thread of the runtime
/// that serves status, metrics and calibration pushes.
///
/// The shard is shared with the receive thread, which corrects a sparse batch in place when
/// the inbox is empty ([`Inbox::try_claim`]); the inbox's claim keeps the two apart and in
/// order, so the lock on the shard is never waited for but during a sweep.
pub fn run(
    index: usize,
    inbox: Arc<Inbox<Arrival>>,
    shard: Arc<Mutex<Shard>>,
    shared: Arc<Shared>,
) {
    tracing::debug!(worker = index, "worker started");
    let mut abandoned = 0u64;
    loop {
        match inbox.take_or_idle(Some(SWEEP_INTERVAL)) {
            Next::Item(arrival) => {
                lock_shard(&shard).handle(&shared, &arrival);
                inbox.release();
            }
            Next::Idle => {
                lock_shard(&shard).sweep(&shared);
                shared.outbox.flush();
            }
            Next::Late(_) => {
                shared.counters.dropped.fetch_add(1, Relaxed);
                abandoned += 1;
                inbox.release();
            }
            Next::Closed => break,
        }
    }
    let shard = lock_shard(&shard);
    if abandoned > 0 {
        tracing::warn!(
            worker = index,
            abandoned,
            "queued batches dropped at shutdown"
        );
    }
    tracing::debug!(
        worker = index,
        sensors = shard.sensors.len(),
        "worker stopped"
    );
}

pub(crate) fn reject(shared: &Shared, sensor: &str, cause: &dyn std::fmt::Display) {
    shared.counters.malformed.fetch_add(1, Relaxed);
    // The key was checked at intake (`keys::raw_sensor_of`); only an id past the table's bound has
    // no entry, and is counted gateway-wide only.
    let Some(entry) = SensorId::new(sensor)
        .ok()
        .and_then(|id| shared.table.seen(&id))
    else {
        return;
    };
    let n = entry.counters.rejects.fetch_add(1, Relaxed) + 1;
    // First and then every thousandth: a broken node must not flood the log.
    if n == 1 || n % 1000 == 0 {
        tracing::warn!(sensor, rejects = n, cause = %cause, "malformed raw batch skipped");
    }
}

impl Shard {
    /// Corrects and publishes a receive burst's batches of this shard, in order, each
    /// sensor's state asked for [`BURST_AHEAD`] batches before its turn, so that its loads
    /// overlap with the correction of the batches before it.
    pub fn handle_burst(&mut self, shared: &Shared, arrivals: &[Arrival]) {
        for arrival in arrivals.iter().take(BURST_AHEAD) {
            self.prefetch(arrival);
        }
        for (i, arrival) in arrivals.iter().enumerate() {
            if let Some(ahead) = arrivals.get(i + BURST_AHEAD) {
                self.prefetch(ahead);
            }
            self.handle(shared, arrival);
        }
    }

    fn prefetch(&self, arrival: &Arrival) {
        if let Some(slot) = self.sensors.get(arrival.sensor.as_bytes()) {
            slot.prefetch();
        }
    }

    /// Corrects and publishes one raw batch; a bad one is counted and skipped. The batch's key
    /// is a concrete raw key of the building, checked at intake.
    pub fn handle(&mut self, shared: &Shared, arrival: &Arrival) {
        self.sweep_now_and_then(shared);
        let Shard {
            sensors, scratch, ..
        } = self;
        let sensor = arrival.sensor.as_str();
        // Looked up before the payload is parsed, so that the state loads meanwhile; asked for
        // before the eviction flag is read, so that the flag's load is not waited for alone.
        let known = sensors.get(sensor.as_bytes()).is_some_and(|slot| {
            slot.prefetch();
            !slot.entry.is_evicted()
        });
        let view = match RawBatchView::parse(&arrival.payload) {
            Ok(v) => v,
            Err(e) => return reject(shared, sensor, &e),
        };
        if view.header.sensor_id.as_str() != sensor {
            let cause = format!("payload names sensor {}", view.header.sensor_id);
            return reject(shared, sensor, &cause);
        }
        if !known {
            let Some(entry) = shared.table.seen(&view.header.sensor_id) else {
                let n = shared.counters.over_capacity.fetch_add(1, Relaxed) + 1;
                if n == 1 || n % 1000 == 0 {
                    tracing::warn!(
                        sensor,
                        skipped = n,
                        max_sensors = shared.table.max_sensors(),
                        "sensor table full of calibrated and established sensors: batch from a new sensor skipped"
                    );
                }
                return;
            };
            match SensorState::new(shared, entry) {
                Ok(s) => {
                    sensors.insert(InlineId::new(&s.entry.id), Slot::new(s));
                    shared.counters.sensors_online.fetch_add(1, Relaxed);
                }
                Err(e) => {
                    shared.counters.publish_errors.fetch_add(1, Relaxed);
                    tracing::error!(sensor, cause = %e, "cannot make the sensor's keys");
                    return;
                }
            }
        }
        // Inserted just above when missing.
        let slot = sensors
            .get_mut(sensor.as_bytes())
            .expect("sensor state exists");
        let state = &mut **slot;
        let corrected = state.correct(shared, &view, scratch);
        if let Err(e) = state.establish(shared) {
            tracing::warn!(sensor, cause = %e, "cannot declare the sensor's keys: used undeclared");
        }
        if let Some(sink) = &shared.history {
            let kept = sink.offer(
                &arrival.sensor,
                &view,
                corrected.verdict,
                corrected.calibration_version,
                corrected.checkpoint.as_deref(),
            );
            if !kept {
                // This batch moved the filters, and a replay will not see it: the next batch
                // kept carries the state after it, so that its replay is what is published.
                state.owe_checkpoint();
            }
        }
        shared.outbox.send(Outgoing {
            key: state.keys.corrected.key_expr().clone(),
            payload: corrected.payload,
            entry: state.entry.clone(),
            sequence: view.header.sequence,
            timestamp_ns: view.header.timestamp_ns,
        });
        if let (Some(json), Some(key)) = (corrected.tilt, &state.keys.tilt) {
            let put = shared
                .session
                .put(key.key_expr(), &json[..])
                .attachment(shared.signer.attachment(key.key_expr().as_str(), "", &json));
            match put.congestion_control(CongestionControl::Drop).wait() {
                Ok(()) => {
                    shared.counters.tilt_samples.fetch_add(1, Relaxed);
                }
                Err(e) => tracing::warn!(sensor, cause = %e, "tilt sample not published"),
            }
        }
        if let Some(json) = corrected.health {
            // Rare (a report every `publish_interval_s` of sensor time): a plain key. A lost
            // report is not lost knowledge: the health queryable answers with the latest.
            let key = Key::Health(shared.building.clone(), state.entry.id.clone()).to_string();
            let put = shared
                .session
                .put(&key, &json[..])
                .attachment(shared.signer.attachment(&key, "", &json));
            if let Err(e) = put.congestion_control(CongestionControl::Drop).wait() {
                tracing::warn!(sensor, cause = %e, "health report not published");
            }
        }
        slot.remember_apart();
    }

    /// Corrects and keeps late batches of `sensor` (a backfill, in sequence order, checked by
    /// the backfill) with the run's own kernel; returns them corrected, to be published
    /// ([`publish_late`]) once the shard is free again, or none when the sensor has no state
    /// here any more. The live kernel and sequence tracking are not touched, nor the health
    /// checks nor the tilt stream, which speak of the present; the next live batch carries a
    /// checkpoint, since the history now holds late batches between it and the last one.
    pub fn correct_late(
        &mut self,
        shared: &Shared,
        sensor: &SensorId,
        run: &mut LateRun,
        batches: &[Vec<u8>],
    ) -> Option<LateOut> {
        let Shard {
            sensors, scratch, ..
        } = self;
        let state = sensors
            .get_mut(sensor.as_str().as_bytes())
            .filter(|s| !s.entry.is_evicted())?;
        let inline_id = InlineId::new(sensor);
        // The first of each chunk: live batches may be kept between two chunks.
        run.checkpoint_due = true;
        let mut corrected = Vec::with_capacity(batches.len());
        for payload in batches {
            let Ok(view) = RawBatchView::parse(payload) else {
                continue;
            };
            let h = &view.header;
            let verdict = if h.sequence == run.expected {
                history::Verdict::Late
            } else {
                history::Verdict::LateGap
            };
            run.expected = h.sequence.saturating_add(1);
            let checkpoint = run.checkpoint_due.then(|| {
                let mut ck = Vec::with_capacity(512);
                run.kernel.checkpoint(&mut ck);
                ck
            });
            let corrector = state.entry.corrector();
            let version = corrector.as_ref().map(|c| c.version());
            let suspect = state.health.flag(version, h.timestamp_ns);
            let mut out = Vec::with_capacity(corrected_len(sensor.as_str().len(), view.len()));
            correct_judged(
                &mut run.kernel,
                &view,
                corrector.as_deref(),
                verdict,
                suspect,
                scratch,
                &mut out,
            );
            run.checkpoint_due = false;
            if let Some(sink) = &shared.history {
                let kept = sink.offer(
                    &inline_id,
                    &view,
                    verdict,
                    version.unwrap_or(0),
                    checkpoint.as_deref(),
                );
                run.checkpoint_due = !kept;
            }
            corrected.push((h.sequence, h.timestamp_ns, out));
        }
        if !corrected.is_empty() {
            state.owe_checkpoint();
        }
        Some(LateOut {
            entry: state.entry.clone(),
            key: state.keys.corrected.key_expr().clone(),
            batches: corrected,
        })
    }

    /// Drops the state of sensors the table forgot (displaced or expired), which gives back
    /// their declared keys; at most once a [`SWEEP_INTERVAL`], the clock read every
    /// [`SWEEP_CHECK_BATCHES`] batches.
    fn sweep_now_and_then(&mut self, shared: &Shared) {
        self.since_sweep += 1;
        if self.since_sweep < SWEEP_CHECK_BATCHES {
            return;
        }
        self.since_sweep = 0;
        let now = std::time::Instant::now();
        if self
            .last_sweep
            .is_some_and(|last| now.duration_since(last) < SWEEP_INTERVAL)
        {
            return;
        }
        self.last_sweep = Some(now);
        self.sweep(shared);
    }

    /// Drops the state of every sensor the table forgot; moves declared keys from silent
    /// sensors to streaming ones.
    pub fn sweep(&mut self, shared: &Shared) {
        self.sensors.retain(|_, s| !s.entry.is_evicted());
        if self.sensors.capacity() > 4 * self.sensors.len().max(256) {
            self.sensors.shrink_to_fit();
        }
        self.reassign_keys(shared);
    }

    /// Keeps the declared-key budget on the sensors that stream, all or nothing.
    ///
    /// A sensor silent for `declared_keys_idle` gives its declared keys back (it declares them
    /// again when it speaks); a streaming sensor whose keys are plain for want of room takes the
    /// room given back, on its next batch. If streaming sensors still wait twice
    /// `declared_keys_idle` and two sweeps later, the budget cannot hold them all, and a partly
    /// declared gateway is the slowest (a batch on a plain key is matched against every declared
    /// one): then every key of every worker goes undeclared, until restart.
    fn reassign_keys(&mut self, shared: &Shared) {
        let release = |s: &mut SensorState| match SensorKeys::new(shared, &s.entry, false) {
            Ok(plain) => s.keys = plain,
            Err(e) => {
                tracing::warn!(sensor = %s.entry.id, cause = %e, "cannot release the sensor's keys")
            }
        };
        if shared.counters.keys_undeclared.load(Relaxed) {
            for s in self.sensors.values_mut().filter(|s| s.keys.holds_places()) {
                release(s);
            }
            return;
        }
        let idle_before_ns = now_ns().saturating_sub(shared.declared_keys_idle_ns);
        let silent = |s: &SensorState| s.entry.counters.last_seen_ns.load(Relaxed) < idle_before_ns;
        let waits = |s: &SensorState| s.keys.declared && !s.keys.holds_places();
        for s in self.sensors.values_mut() {
            if silent(s) && s.keys.holds_places() {
                release(s);
            }
        }
        let mut room = shared
            .declared_keys_max
            .saturating_sub(shared.counters.declared_keys.load(Relaxed));
        let mut left_waiting = false;
        for s in self.sensors.values_mut() {
            if silent(s) || !waits(s) {
                continue;
            }
            let needed = 2 + usize::from(s.entry.settings.tilt);
            if needed <= room {
                // Its next batch declares them (`establish`).
                s.keys.declared = false;
                room -= needed;
            } else {
                left_waiting = true;
            }
        }
        if !left_waiting {
            self.waiting_since = None;
            return;
        }
        // Long enough for every silent sensor to have been released by its own worker (each
        // sweeps at least once a SWEEP_INTERVAL), with room to spare.
        let patience_ns =
            2 * shared.declared_keys_idle_ns.max(0) as u128 + 2 * SWEEP_INTERVAL.as_nanos();
        let since = *self
            .waiting_since
            .get_or_insert_with(std::time::Instant::now);
        if since.elapsed().as_nanos() >= patience_ns {
            shared.turn_keys_undeclared();
            for s in self.sensors.values_mut().filter(|s| s.keys.holds_places()) {
                release(s);
            }
        }
    }
}

impl SensorState {
    fn new(shared: &Shared, entry: Arc<SensorEntry>) -> zenoh::Result<SensorState> {
        let entry_suspect = entry.suspect();
        let pairs = shared.table.groups_of(&entry.id);
        Ok(SensorState {
            kernel: SensorKernel::new(entry.settings.clone()),
            keys: SensorKeys::new(shared, &entry, false)?,
            entry,
            sequence: SequenceTracker::default(),
            next_tilt_ns: i64::MIN,
            last_version: None,
            next_checkpoint_ns: i64::MIN,
            since_checkpoint: 0,
            health: HealthFeed::new(entry_suspect),
            pairs,
        })
    }

    /// Declares the sensor's keys once it is calibrated (see [`SensorKeys`]). An uncalibrated
    /// sensor keeps plain keys however long it streams: ids anyone can make up must take no
    /// place in the budget (a flood of ids sending two batches each drove the gateway into the
    /// partly declared state, the slowest, until the budget's patience ran out).
    fn establish(&mut self, shared: &Shared) -> zenoh::Result<()> {
        if self.keys.declared {
            return Ok(());
        }
        let e = &self.entry;
        if e.calibration_version().is_none() {
            return Ok(());
        }
        // Marked first: a failure is logged once, and the sensor goes on undeclared.
        self.keys.declared = true;
        self.keys = SensorKeys::new(shared, e, true)?;
        tracing::info!(
            sensor = %e.id,
            mode = ?e.settings.mode,
            tilt = e.settings.tilt,
            calibration_version = ?e.calibration_version(),
            "sensor online"
        );
        Ok(())
    }

    /// The synchronous part: sequence, correction, counters, tilt, and what the history keeps.
    fn correct(
        &mut self,
        shared: &Shared,
        view: &RawBatchView<'_>,
        scratch: &mut Scratch,
    ) -> Corrected {
        let duration_ns = (view.len() as f64 * 1e9 / view.header.sample_rate_hz) as i64;
        let before = self.sequence.last();
        let verdict =
            self.sequence
                .observe(view.header.sequence, view.header.timestamp_ns, duration_ns);
        // The state before this batch, which a replay restores and then feeds the same batch.
        let checkpoint = self.checkpoint_due(view.header.timestamp_ns).then(|| {
            let mut ck = Vec::with_capacity(512);
            self.kernel.checkpoint(&mut ck);
            ck
        });
        if let Some(holes) = &shared.backfill {
            self.ask_backfill(holes, view, verdict, before, checkpoint.as_deref());
        }
        let c = &self.entry.counters;
        match verdict {
            Verdict::Gap { missing } => {
                c.gaps.fetch_add(1, Relaxed);
                c.missing_batches.fetch_add(missing, Relaxed);
                tracing::debug!(sensor = %self.entry.id, sequence = view.header.sequence, missing, "sequence gap");
            }
            Verdict::Duplicate => {
                c.duplicates.fetch_add(1, Relaxed);
                tracing::debug!(sensor = %self.entry.id, sequence = view.header.sequence, "duplicate batch");
            }
            Verdict::Restart => {
                c.restarts.fetch_add(1, Relaxed);
                tracing::info!(sensor = %self.entry.id, sequence = view.header.sequence, "sensor node restarted");
            }
            Verdict::InOrder | Verdict::First => {}
        }
        // Borrowed for the batch: holding the corrector would count it up and down, on a
        // line of its own.
        let guard = self.entry.corrector_guard();
        let corrector = guard.as_deref();
        let version = corrector.map(Corrector::version);
        if version != self.last_version {
            match version {
                Some(v) => {
                    tracing::info!(sensor = %self.entry.id, calibration_version = v, "calibration in force")
                }
                None => {
                    tracing::warn!(sensor = %self.entry.id, "no calibration: publishing flagged uncalibrated")
                }
            }
            self.last_version = version;
        }
        let n = view.len();
        let mut out = Vec::with_capacity(corrected_len(view.header.sensor_id.as_str().len(), n));
        let judged = verdict.kept();
        let suspect = self.health.flag(version, view.header.timestamp_ns);
        let outcome = correct_judged(
            &mut self.kernel,
            view,
            corrector,
            judged,
            suspect,
            scratch,
            &mut out,
        );
        c.batches.fetch_add(1, Relaxed);
        c.samples.fetch_add(n as u64, Relaxed);
        c.flagged_samples
            .fetch_add(u64::from(outcome.n_flagged), Relaxed);
        if outcome.mode == Mode::None {
            c.uncalibrated_samples.fetch_add(n as u64, Relaxed);
        }
        let received_ns = now_ns();
        c.last_seen_ns.store(received_ns, Relaxed);
        let paired = !self.pairs.is_empty() && judged != history::Verdict::Duplicate;
        if let (Some(v), true) = (version, paired) {
            let accel = scratch.corrected();
            // A pair's spectra take whole, finite stretches: a batch with a lost value is a
            // break for it, as a gap is.
            if accel.len() == n && accel.iter().flatten().all(|x| x.is_finite()) {
                for pair in &self.pairs {
                    let h = &view.header;
                    pair.feed(&self.entry.id, v, h.timestamp_ns, h.sample_rate_hz, accel);
                }
            }
        }
        let health = shared.health.and_then(|reporting| {
            self.health.observe(
                &shared.building,
                &shared.store,
                &self.entry,
                corrector,
                view,
                judged,
                received_ns,
                reporting,
                &self.pairs,
            )
        });

        let mut tilt_json = None;
        if let (Some(corrector), true) = (corrector, self.keys.tilt.is_some()) {
            let t = *self.kernel.tilt_state();
            if t.ready && t.timestamp_ns >= self.next_tilt_ns {
                let est = t.estimate(corrector);
                let sample = TiltSample {
                    format_version: JSON_FORMAT_VERSION,
                    sensor_id: self.entry.id.clone(),
                    timestamp_ns: t.timestamp_ns,
                    roll_deg: est.roll_deg,
                    pitch_deg: est.pitch_deg,
                    roll_uncertainty_deg: est.roll_uncertainty_deg,
                    pitch_uncertainty_deg: est.pitch_uncertainty_deg,
                    coverage_factor: est.coverage_factor,
                    calibration_version: corrector.version(),
                    flags: t.flags,
                };
                tilt_json = Some(to_json(&sample));
                self.kernel.tilt_published();
                let interval_ns = (self.entry.settings.tilt_interval_s * 1e9) as i64;
                self.next_tilt_ns = t.timestamp_ns.saturating_add(interval_ns);
            }
        }
        Corrected {
            payload: out,
            tilt: tilt_json,
            verdict: judged,
            calibration_version: version.unwrap_or(0),
            checkpoint,
            health,
        }
    }

    /// Asks for what a gap, or the gateway's own start, cost this sensor: without waiting.
    /// `before` is the last accepted batch before this one; `checkpoint` the kernel's state
    /// before it, if one was taken for the history.
    fn ask_backfill(
        &self,
        holes: &Holes,
        view: &RawBatchView<'_>,
        verdict: Verdict,
        before: Option<(u64, i64)>,
        checkpoint: Option<&[u8]>,
    ) {
        let h = &view.header;
        let need = match (verdict, before) {
            (Verdict::Gap { .. }, Some((last_seq, after_ns))) => {
                // A new run whose first batches were lost is numbered from 0.
                let from_seq = if h.sequence > last_seq {
                    last_seq + 1
                } else {
                    0
                };
                let state = match checkpoint {
                    Some(ck) => ck.to_vec(),
                    None => {
                        let mut ck = Vec::with_capacity(512);
                        self.kernel.checkpoint(&mut ck);
                        ck
                    }
                };
                Need::Gap {
                    from_seq,
                    to_seq: h.sequence - 1,
                    after_ns,
                    before_ns: h.timestamp_ns,
                    state,
                }
            }
            (Verdict::First, _) if h.sequence > 0 => Need::First {
                sequence: h.sequence,
                timestamp_ns: h.timestamp_ns,
            },
            _ => return,
        };
        holes.report(Request {
            sensor: self.entry.id.clone(),
            need,
        });
    }

    /// Makes the next batch carry a checkpoint, whatever the interval says.
    fn owe_checkpoint(&mut self) {
        self.next_checkpoint_ns = i64::MIN;
    }

    /// Whether the history is owed a checkpoint before the batch at `timestamp_ns`: at the
    /// sensor's first batch (its kernel is fresh, and after a restart of the gateway only this
    /// checkpoint tells a replay so), after a batch the history did not keep, then every
    /// [`CHECKPOINT_INTERVAL_NS`] of its clock or [`CHECKPOINT_INTERVAL_BATCHES`] batches,
    /// whichever comes first.
    fn checkpoint_due(&mut self, timestamp_ns: i64) -> bool {
        self.since_checkpoint = self.since_checkpoint.saturating_add(1);
        let due = timestamp_ns >= self.next_checkpoint_ns
            || self.since_checkpoint > CHECKPOINT_INTERVAL_BATCHES;
        if due {
            self.next_checkpoint_ns = timestamp_ns.saturating_add(CHECKPOINT_INTERVAL_NS);
            self.since_checkpoint = 0;
        }
        due
    }
}

/// Late batches corrected under the shard's lock, to publish after it.
pub struct LateOut {
    entry: Arc<SensorEntry>,
    key: KeyExpr<'static>,
    /// Sequence number, first sample's time, corrected payload.
    batches: Vec<(u64, i64, Vec<u8>)>,
}

/// Publishes late batches on the sensor's corrected key, behind live data on every link
/// (`DataLow`), dropped like live data for a slow consumer; returns how many were published.
/// Outside the shard's lock: a live batch waits for no late one.
pub fn publish_late(shared: &Shared, late: LateOut) -> usize {
    let mut published = 0;
    let mut digests = Vec::new();
    for (sequence, timestamp_ns, payload) in late.batches {
        let d = shared
            .seals
            .as_ref()
            .map(|_| digest(late.key.as_str(), &[], &payload));
        match shared
            .session
            .put(&late.key, payload)
            .congestion_control(CongestionControl::Drop)
            .priority(Priority::DataLow)
            .wait()
        {
            Ok(()) => {
                late.entry.note_late(sequence, timestamp_ns);
                published += 1;
                digests.extend(d);
            }
            Err(e) => {
                shared.counters.publish_errors.fetch_add(1, Relaxed);
                tracing::warn!(sensor = %late.entry.id, cause = %e, "late batch not published");
            }
        }
    }
    if let Some(seals) = &shared.seals {
        seals.push(digests);
    }
    published
}

/// A batch corrected, with what the history keeps of it.
struct Corrected {
    payload: Vec<u8>,
    tilt: Option<Vec<u8>>,
    verdict: history::Verdict,
    calibration_version: u64,
    checkpoint: Option<Vec<u8>>,
    /// A health report due, JSON.
    health: Option<Vec<u8>>,
}

/// Corrects a batch the sequence tracking judged `verdict`: a gap or a restart first resets
/// the frequency detector, and the verdict's batch flag goes on the batch; `suspect` (0 or
/// `calibration_suspect`, [`super::health::suspect_flag`]) goes on every sample. The one path
/// of both the live stream and the history's replay, so that the two agree byte for byte.
pub fn correct_judged(
    kernel: &mut SensorKernel,
    view: &RawBatchView<'_>,
    corrector: Option<&Corrector>,
    verdict: history::Verdict,
    suspect: u16,
    scratch: &mut Scratch,
    out: &mut Vec<u8>,
) -> BatchOutcome {
    let stream_flags = match verdict {
        history::Verdict::Gap => {
            kernel.discontinuity();
            flags::SEQUENCE_GAP
        }
        history::Verdict::Restart => {
            kernel.discontinuity();
            0
        }
        history::Verdict::Duplicate => flags::DUPLICATE,
        history::Verdict::InOrder => 0,
        history::Verdict::Late => flags::LATE,
        history::Verdict::LateGap => {
            kernel.discontinuity();
            flags::LATE | flags::SEQUENCE_GAP
        }
    };
    kernel.correct_batch(view, corrector, stream_flags | suspect, scratch, out)
}

/// Asks the processor to start loading the cache lines of the `bytes` bytes at `at`, at most
/// [`PREFETCH_LINES_MAX`] of them; a no-op where there is no such hint.
#[inline(always)]
fn prefetch_bytes(at: usize, bytes: usize) {
    #[cfg(target_arch = "x86_64")]
    {
        use std::arch::x86_64::{_mm_prefetch, _MM_HINT_T0};
        let start = at as *const i8;
        let lines = bytes.div_ceil(64).min(PREFETCH_LINES_MAX);
        for line in 0..lines {
            // SAFETY: a prefetch is a hint that never faults, whatever the address; SSE, the
            // only feature it needs, is part of every x86_64 processor.
            unsafe { _mm_prefetch::<_MM_HINT_T0>(start.wrapping_add(64 * line)) };
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = (at, bytes);
}

/// Lines one [`prefetch_bytes`] asks for at most: a corrector (1.2 KB) whole.
const PREFETCH_LINES_MAX: usize = 32;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn shards_are_stable_and_spread() {
        let n = 4;
        let mut counts = [0; 4];
        for i in 0..1000 {
            let s = format!("acc-{i}");
            let w = shard(&s, n);
            assert_eq!(w, shard(&s, n));
            counts[w] += 1;
        }
        assert!(counts.iter().all(|&c| c > 150), "{counts:?}");
    }
}
