//! Following a building's corrected streams without losing a batch (PROTOCOL.md §5.2).
//!
//! The gateway publishes the live stream with drop congestion control: a consumer that falls
//! behind loses batches on its own link. A [`Follower`] keeps, per sensor, the [`Position`] of
//! the last batch it handed over (its sequence number and its first sample's time) and, before
//! handing over a batch that does not follow on from it, reads from the history what lies
//! between. The history is asked by time (`from_ns`, `to_ns`), not by sequence number: a node
//! that restarts numbers its batches from 0 again, and a range of numbers then also matches its
//! earlier run. Batches come out per sensor in the order the gateway corrected them, each once:
//! byte for byte what an uninterrupted subscriber received, except that a batch flagged
//! `duplicate` (a repeat of one already handed over) is passed on as it arrives live and never
//! read back.
//!
//! What reveals a loss:
//! - a live batch that is not the next in line (by number, and by time: no room for a whole
//!   batch between the two);
//! - the gateway's heartbeat, which names each active sensor's last published batch: a lost
//!   *last* batch, after which the sensor fell silent;
//! - heartbeats lost in turn (a jump in their numbering, a restarted gateway's, or the first one
//!   seen): a sensor that fell silent meanwhile is named in none the follower received, so the
//!   history is read on from the position of every sensor the heartbeat does not name.
//!
//! Started with the positions a consumer saved ([`FollowOptions::resume_at`]), it first reads
//! what the consumer missed while it was away. A sensor it has no position for is followed from
//! [`FollowOptions::new_sensors_from_ns`] (by default the moment it starts), its first batches
//! read from the history if they were lost.
//!
//! What the history does not hold (lost before the gateway, or past retention) cannot be
//! recovered: where the numbering shows it, it is counted ([`FollowerCounters::unrecoverable`]).
//!
//! **Late batches.** A gateway fills a hole from the node's buffer after later batches went
//! out (PROTOCOL.md §2.3 `late`, §5.4), and keeps the late batches in its history after them.
//! So history answers are taken in time order, and the follower remembers, per sensor, the
//! holes the numbering showed (at most [`MAX_HOLES`], the oldest forgotten first): a live
//! batch flagged `late` inside one is handed over (`late` batches go out after later ones),
//! the history read for any late batch lost before it, and the hole shrinks; one behind the
//! position outside every hole was handed over already, and one ahead of the position is
//! taken in line as a live batch is (the live batch that would have shown its hole was lost).
//! A heartbeat's `late_timestamp_ns` inside a hole reads the history up to it: late batches
//! lost on the link, the last ones of a hole included.

use std::collections::{BTreeMap, HashMap};
use std::sync::atomic::{AtomicU64, Ordering::Relaxed};
use std::sync::Arc;
use std::time::Duration;

use tokio::sync::mpsc;
use triax_protocol::batch::{flags, CorrectedBatch};
use triax_protocol::keys::{self, Stream};
use triax_protocol::messages::Heartbeat;
use triax_protocol::provenance::{
    digest, verify_message, Digest, Freshness, GatewayKeys, Seal, SealBook,
};
use triax_protocol::{from_json, BuildingId, Key, SensorId};

use crate::history::{fetch, HistoryRequest};
use crate::{zenoh_err, ClientError};

/// Where a sensor's stream was left: the last batch handed over. Its time orders a sensor's
/// batches across restarts of the node, where sequence numbers start again from 0.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct Position {
    pub sequence: u64,
    /// The batch's first sample, ns since the Unix epoch, by the node's clock.
    pub timestamp_ns: i64,
}

impl Position {
    pub fn of(batch: &CorrectedBatch) -> Position {
        Position {
            sequence: batch.header.sequence,
            timestamp_ns: batch.header.timestamp_ns,
        }
    }
}

/// What to follow, and from where.
#[derive(Debug, Clone)]
pub struct FollowOptions {
    pub building: BuildingId,
    /// The last batch handled per sensor before a restart ([`Delivery::position`]): what
    /// follows it is read from the history first.
    pub resume_at: BTreeMap<SensorId, Position>,
    /// The holes saved with each position ([`Delivery::holes`]): late batches that filled them
    /// while the consumer was away are read from the history first, and those still to come
    /// are taken when they arrive. Without them a restarted follower drops every late batch
    /// behind its positions, as one it has.
    pub resume_holes: BTreeMap<SensorId, Vec<Hole>>,
    /// The last sequence number alone, as older saved state has it: placed in time through the
    /// history (the newest kept batch with that number), then followed as [`Self::resume_at`].
    /// Wrong only if the node restarted while the consumer was away and its new run passed
    /// that number again (or the batch is past retention: then read by number); save
    /// positions instead.
    pub resume_after: BTreeMap<SensorId, u64>,
    /// A sensor in neither map is followed from this time on (ns since the Unix epoch, by the
    /// node's clock): batches of it from then on are handed over, the first ones from the
    /// history if they were lost. `None`: the moment the follower starts. `Some(i64::MIN)`:
    /// everything the history holds of a sensor met for the first time.
    pub new_sensors_from_ns: Option<i64>,
    /// How long one history query may take.
    pub query_timeout: Duration,
    /// Live batches (and heartbeats) the follower holds while it reads the history or its
    /// consumer is busy, and batches handed over that wait for the consumer (at most 1024);
    /// beyond that live batches are dropped, and read back from the history when the next
    /// batch or heartbeat shows what is missing.
    pub buffer_batches: usize,
    /// Whether batches flagged `late` (holes a gateway filled from a node's buffer, after later
    /// batches) are handed over. True by default; a consumer that judges the present (alerting,
    /// a window of the live stream) turns it off and reads them from the history when it wants.
    pub late_batches: bool,
    /// The gateway keys [`Follower::start`] verifies with (see [`Fleet::start`]); a fleet's
    /// followers use the fleet's. `None` by default: everything is taken on trust.
    pub trusted: Option<Arc<GatewayKeys>>,
}

impl FollowOptions {
    pub fn new(building: BuildingId) -> FollowOptions {
        FollowOptions {
            building,
            resume_at: BTreeMap::new(),
            resume_holes: BTreeMap::new(),
            resume_after: BTreeMap::new(),
            new_sensors_from_ns: None,
            query_timeout: Duration::from_secs(10),
            buffer_batches: 4096,
            late_batches: true,
            trusted: None,
        }
    }
}

/// One batch handed to the consumer.
#[derive(Debug, Clone, PartialEq)]
pub struct Delivery {
    /// The building followed: deliveries of many buildings may share one channel
    /// ([`Fleet::follow_into`]).
    pub building: BuildingId,
    pub payload: Vec<u8>,
    pub batch: CorrectedBatch,
    /// Read from the history rather than taken live.
    pub recovered: bool,
    /// The sensor's holes after this batch (oldest first, at most [`MAX_HOLES`]): numbers
    /// missing behind its position that a gateway may still fill late. Saved with
    /// [`Delivery::position`], they are what a restarted follower needs to take those batches
    /// ([`FollowOptions::resume_holes`]).
    pub holes: Vec<Hole>,
    /// The sensor's position after this batch: a `late` or `duplicate` batch leaves it where
    /// it was.
    mark: Position,
}

impl Delivery {
    /// What to save to resume after this batch ([`FollowOptions::resume_at`]), with
    /// [`Delivery::holes`].
    pub fn position(&self) -> Position {
        self.mark
    }
}

/// What the follower did.
#[derive(Debug, Default)]
pub struct FollowerCounters {
    pub live: AtomicU64,
    pub recovered: AtomicU64,
    /// Batches flagged `late` handed over, live or from the history.
    pub late: AtomicU64,
    /// Batches the numbering said were missing that the history did not have.
    pub unrecoverable: AtomicU64,
    pub history_queries: AtomicU64,
    pub history_errors: AtomicU64,
    /// Live batches dropped because no verified seal listed them in time (PROTOCOL.md §6): a
    /// peer's forgeries, or the gateway's batches whose seal was lost (those come back from
    /// the history).
    pub unverified: AtomicU64,
    /// Seals and heartbeats refused: unsigned, signed by a key not trusted, altered, replayed.
    pub refused: AtomicU64,
}

/// A building's corrected batches, none lost that the history holds.
pub struct Follower {
    rx: mpsc::Receiver<Delivery>,
    following: Following,
    /// Keeps the subscriptions of a follower started alone.
    _fleet: Option<Fleet>,
}

/// What a building's follower is told by the subscriptions, in arrival order.
enum Event {
    /// A corrected batch, and its digest when the fleet verifies.
    Live(Vec<u8>, Option<Digest>),
    /// A heartbeat and its attachment.
    Beat(Vec<u8>, Option<Vec<u8>>),
    Seal {
        key: String,
        payload: Vec<u8>,
        attachment: Option<Vec<u8>>,
    },
}

/// How long a live batch waits for the seal that lists it before it is dropped as unverified.
/// A gateway seals at least every `seal_interval_ms` (1 ms by default) once it has published.
pub const SEAL_WAIT: Duration = Duration::from_secs(2);

/// What a verifying follower keeps: whom it trusts, and the batches waiting for their seal.
struct Verifier {
    trusted: Arc<GatewayKeys>,
    book: SealBook<Vec<u8>>,
    fresh: Freshness,
}

type Routes = Arc<std::sync::RwLock<HashMap<BuildingId, mpsc::Sender<Event>>>>;

/// One subscription to the corrected streams and heartbeats of every building (or of one), shared
/// by the followers of many buildings.
///
/// Why: Zenoh matches every incoming sample against every subscription of the session, so a
/// service following a hundred buildings with a subscription each paid for a hundred key
/// matches per batch (at 100 000 batches/s, more than a core). One wildcard subscription and a
/// map lookup by the key's building chunk cost one.
pub struct Fleet {
    session: zenoh::Session,
    routes: Routes,
    trusted: Option<Arc<GatewayKeys>>,
    _live: zenoh::pubsub::Subscriber<()>,
    _beats: zenoh::pubsub::Subscriber<()>,
    _seals: Option<zenoh::pubsub::Subscriber<()>>,
}

impl Fleet {
    /// Subscribes to the corrected streams and heartbeats of `building`, or of every building
    /// when none is given. Nothing is followed until [`Fleet::follow`].
    ///
    /// With `trusted` keys, the followers hand over only batches a seal signed by their
    /// building's gateway lists, and act only on heartbeats it signed (PROTOCOL.md §6); a
    /// building with no key trusted then gets nothing. `None`: everything is taken on trust.
    pub async fn start(
        session: &zenoh::Session,
        building: Option<&BuildingId>,
        trusted: Option<Arc<GatewayKeys>>,
    ) -> Result<Fleet, ClientError> {
        let routes: Routes = Arc::default();
        let (live_expr, beat_expr, seal_expr) = match building {
            Some(b) => (
                keys::all_sensors(b, Stream::Corrected),
                Key::Heartbeat(b.clone()).to_string(),
                Key::Seal(b.clone()).to_string(),
            ),
            None => (
                keys::all_buildings(Stream::Corrected),
                "triax/*/heartbeat".to_owned(),
                "triax/*/seal".to_owned(),
            ),
        };
        let verifying = trusted.is_some();
        let live: fn(&zenoh::sample::Sample) -> Event = if verifying {
            |s| {
                let payload = s.payload().to_bytes().into_owned();
                let d = digest(s.key_expr().as_str(), &[], &payload);
                Event::Live(payload, Some(d))
            }
        } else {
            |s| Event::Live(s.payload().to_bytes().into_owned(), None)
        };
        let beat: fn(&zenoh::sample::Sample) -> Event = |s| {
            Event::Beat(
                s.payload().to_bytes().into_owned(),
                s.attachment().map(|a| a.to_bytes().into_owned()),
            )
        };
        let seal: fn(&zenoh::sample::Sample) -> Event = |s| Event::Seal {
            key: s.key_expr().as_str().to_owned(),
            payload: s.payload().to_bytes().into_owned(),
            attachment: s.attachment().map(|a| a.to_bytes().into_owned()),
        };
        let route = |routes: Routes, wrap: fn(&zenoh::sample::Sample) -> Event| {
            move |sample: zenoh::sample::Sample| {
                // `triax/<building>/…`: the second chunk.
                let Some(b) = sample.key_expr().as_str().split('/').nth(1) else {
                    return;
                };
                let Ok(b) = BuildingId::new(b) else { return };
                let tx = routes
                    .read()
                    .unwrap_or_else(|p| p.into_inner())
                    .get(&b)
                    .cloned();
                // A follower that cannot keep up loses the batch here and reads it back from
                // the history when the next one shows the gap; Zenoh's thread never waits.
                if let Some(tx) = tx {
                    let _ = tx.try_send(wrap(&sample));
                }
            }
        };
        let live = session
            .declare_subscriber(live_expr)
            .callback(route(routes.clone(), live))
            .await
            .map_err(zenoh_err("subscribe to corrected streams"))?;
        let beats = session
            .declare_subscriber(beat_expr)
            .callback(route(routes.clone(), beat))
            .await
            .map_err(zenoh_err("subscribe to heartbeats"))?;
        let seals = match verifying {
            true => Some(
                session
                    .declare_subscriber(seal_expr)
                    .callback(route(routes.clone(), seal))
                    .await
                    .map_err(zenoh_err("subscribe to seals"))?,
            ),
            false => None,
        };
        Ok(Fleet {
            session: session.clone(),
            routes,
            trusted,
            _live: live,
            _beats: beats,
            _seals: seals,
        })
    }

    /// Starts following `options.building`: reads what `options.resume_at` (and
    /// `resume_after`) say was missed, then the live stream. A building the subscription does
    /// not cover gets nothing.
    pub fn follow(&self, options: FollowOptions) -> Follower {
        let (tx, rx) = mpsc::channel(options.buffer_batches.clamp(1, 1024));
        let following = self.follow_into(options, tx);
        Follower {
            rx,
            following,
            _fleet: None,
        }
    }

    /// Follows like [`Fleet::follow`], but hands every delivery to `tx`, which the followers of
    /// other buildings may share (each [`Delivery`] names its building): a consumer of many
    /// buildings reads one queue, with no task of its own per building forwarding a
    /// [`Follower`] into it (a hand-over and a queue of 1 024 batches less per building). A
    /// full `tx` holds the follower back as a full [`Follower`] does.
    pub fn follow_into(&self, options: FollowOptions, tx: mpsc::Sender<Delivery>) -> Following {
        let (events_tx, mut events) = mpsc::channel(options.buffer_batches.max(1));
        self.routes
            .write()
            .unwrap_or_else(|p| p.into_inner())
            .insert(options.building.clone(), events_tx);
        let counters = Arc::new(FollowerCounters::default());
        let mut state = State {
            session: self.session.clone(),
            new_sensors_from_ns: options.new_sensors_from_ns.unwrap_or_else(now_ns),
            marks: options
                .resume_at
                .iter()
                .map(|(s, p)| (s.clone(), Mark::at(*p)))
                .collect(),
            beats: HashMap::new(),
            holes: options
                .resume_holes
                .iter()
                .filter(|(_, h)| !h.is_empty())
                .map(|(s, h)| (s.clone(), h[h.len().saturating_sub(MAX_HOLES)..].to_vec()))
                .collect(),
            options,
            tx,
            counters: counters.clone(),
            verifier: self.trusted.clone().map(|trusted| Verifier {
                trusted,
                book: SealBook::new(SEAL_WAIT.as_nanos() as i64, 65_536),
                fresh: Freshness::default(),
            }),
        };
        let task = tokio::spawn(async move {
            if !state.resume().await {
                return;
            }
            let verifying = state.verifier.is_some();
            let mut expiry = tokio::time::interval(SEAL_WAIT / 4);
            expiry.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
            loop {
                let event = tokio::select! {
                    e = events.recv() => match e {
                        Some(e) => e,
                        None => return,
                    },
                    _ = expiry.tick(), if verifying => {
                        state.expire_unsealed();
                        continue;
                    }
                };
                let open = match event {
                    Event::Live(payload, None) => state.live(payload).await,
                    Event::Live(payload, Some(d)) => state.offer(d, payload).await,
                    Event::Beat(payload, attachment) => {
                        if state.beat_is_genuine(&payload, attachment.as_deref()) {
                            state.heartbeat(&payload).await
                        } else {
                            true
                        }
                    }
                    Event::Seal {
                        key,
                        payload,
                        attachment,
                    } => state.seal(&key, &payload, attachment.as_deref()).await,
                };
                if !open {
                    return;
                }
            }
        });
        Following { counters, task }
    }
}

/// A building followed into a shared queue ([`Fleet::follow_into`]); following stops when it
/// is dropped.
pub struct Following {
    counters: Arc<FollowerCounters>,
    task: tokio::task::JoinHandle<()>,
}

impl Following {
    pub fn counters(&self) -> &FollowerCounters {
        &self.counters
    }
}

impl Drop for Following {
    fn drop(&mut self) {
        self.task.abort();
    }
}

impl Follower {
    /// Subscribes to the building's corrected streams and heartbeat, reads what
    /// `options.resume_at` says was missed, and starts following. (For many buildings, one
    /// [`Fleet`] serves them all.)
    pub async fn start(
        session: &zenoh::Session,
        options: FollowOptions,
    ) -> Result<Follower, ClientError> {
        let fleet = Fleet::start(session, Some(&options.building), options.trusted.clone()).await?;
        let mut follower = fleet.follow(options);
        follower._fleet = Some(fleet);
        Ok(follower)
    }

    /// The next batch; none once the session closed.
    pub async fn next(&mut self) -> Option<Delivery> {
        self.rx.recv().await
    }

    pub fn counters(&self) -> &FollowerCounters {
        self.following.counters()
    }
}

/// Now, ns since the Unix epoch, by this machine's clock.
fn now_ns() -> i64 {
    let d = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .unwrap_or_default();
    i64::try_from(d.as_nanos()).unwrap_or(i64::MAX)
}

/// The last batch handed over for a sensor (not counting duplicates), and where it ended.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Mark {
    position: Position,
    /// Its first sample's time plus its duration: the node's next batch starts about here.
    end_ns: i64,
}

impl Mark {
    fn of(batch: &CorrectedBatch) -> Mark {
        let position = Position::of(batch);
        Mark {
            position,
            end_ns: position.timestamp_ns.saturating_add(duration_ns(batch)),
        }
    }

    /// A saved position, whose batch's duration is not known.
    fn at(position: Position) -> Mark {
        Mark {
            position,
            end_ns: position.timestamp_ns,
        }
    }

    /// The history's lower bound for what follows this batch.
    fn after_ns(&self) -> i64 {
        self.position.timestamp_ns.saturating_add(1)
    }
}

/// How long a batch lasts: its sample count over its rate (finite and positive once decoded).
fn duration_ns(batch: &CorrectedBatch) -> i64 {
    (batch.samples.len() as f64 * 1e9 / batch.header.sample_rate_hz) as i64
}

fn is_duplicate(batch: &CorrectedBatch) -> bool {
    batch.batch_flags & flags::DUPLICATE != 0
}

fn is_late(batch: &CorrectedBatch) -> bool {
    batch.batch_flags & flags::LATE != 0
}

/// Holes remembered per sensor.
pub const MAX_HOLES: usize = 64;

/// Batches the numbering says are missing between two handed over: a gateway may still fill
/// them late. `after` is the last handed over below the hole, `before` the first above.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct Hole {
    pub after: Position,
    pub before: Position,
}

impl Hole {
    /// The hole between two batches handed over one after the other, if numbers lie between.
    fn between(after: Position, before: Position) -> Option<Hole> {
        (before.sequence > after.sequence.saturating_add(1)
            && before.timestamp_ns > after.timestamp_ns)
            .then_some(Hole { after, before })
    }

    fn holds(&self, timestamp_ns: i64) -> bool {
        self.after.timestamp_ns < timestamp_ns && timestamp_ns < self.before.timestamp_ns
    }
}

/// What to do with a live batch.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Next {
    Deliver,
    /// Handed over already, from the history.
    Skip,
    /// Read the history from `from_ns` up to this batch first: something may lie between.
    Recover {
        from_ns: i64,
    },
}

/// Judges a live batch against the sensor's mark, or, for a sensor without one, the time from
/// which new sensors are followed.
fn judge(mark: Option<&Mark>, new_sensors_from_ns: i64, batch: &CorrectedBatch) -> Next {
    if is_duplicate(batch) {
        // A repeat: it moves nothing, and is passed on as the live stream carries it.
        return Next::Deliver;
    }
    let h = &batch.header;
    let duration_ns = i128::from(duration_ns(batch).max(1));
    match mark {
        None => {
            // Room for a whole batch between the start and this one: earlier ones may be lost.
            let room = i128::from(h.timestamp_ns) - i128::from(new_sensors_from_ns) >= duration_ns;
            if room {
                Next::Recover {
                    from_ns: new_sensors_from_ns,
                }
            } else {
                Next::Deliver
            }
        }
        Some(m) if h.timestamp_ns <= m.position.timestamp_ns => Next::Skip,
        Some(m) => {
            // Next by number and by time: a node restarted in between could have numbered a
            // new run up to the same number, but not without the time to send it.
            let next = h.sequence == m.position.sequence.wrapping_add(1)
                && i128::from(h.timestamp_ns) - i128::from(m.end_ns) < duration_ns;
            if next {
                Next::Deliver
            } else {
                Next::Recover {
                    from_ns: m.after_ns(),
                }
            }
        }
    }
}

/// How far a history read goes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Until {
    /// Everything kept.
    End,
    /// Up to and including this batch (the last a heartbeat names).
    Through(Position),
    /// Up to this live batch, which the caller hands over itself.
    Before(Position),
}

/// Batches the numbering says lie between `mark` and `target` (excluded), bounded, as the
/// gateway's gap count is, by what fits in the time between them; none if the numbers went
/// back (a node restart: the numbering says nothing).
fn missing_between(mark: &Mark, target: Position) -> u64 {
    let by_number = target
        .sequence
        .checked_sub(mark.position.sequence)
        .map_or(0, |d| d.saturating_sub(1));
    let duration_ns = i128::from((mark.end_ns - mark.position.timestamp_ns).max(1));
    let between_ns = (i128::from(target.timestamp_ns) - i128::from(mark.end_ns)).max(0);
    let by_clock = u64::try_from(between_ns / duration_ns + 1).unwrap_or(u64::MAX);
    by_number.min(by_clock)
}

/// Heartbeat numbers remembered per gateway; beyond this many names (a building has one
/// gateway) the memory starts afresh.
const MAX_GATEWAYS: usize = 64;

struct State {
    session: zenoh::Session,
    options: FollowOptions,
    /// [`FollowOptions::new_sensors_from_ns`], resolved.
    new_sensors_from_ns: i64,
    /// Per sensor, the last batch handed over.
    marks: HashMap<SensorId, Mark>,
    /// Per sensor, the holes behind its mark that a gateway may fill late, oldest first.
    holes: HashMap<SensorId, Vec<Hole>>,
    /// The last heartbeat number seen, per gateway.
    beats: HashMap<String, u64>,
    tx: mpsc::Sender<Delivery>,
    counters: Arc<FollowerCounters>,
    /// None: everything is taken on trust.
    verifier: Option<Verifier>,
}

impl State {
    /// A live batch of a verifying follower: handed on once a seal lists it.
    async fn offer(&mut self, digest: Digest, payload: Vec<u8>) -> bool {
        let Some(v) = self.verifier.as_mut() else {
            return self.live(payload).await;
        };
        let mut pushed_out = Vec::new();
        let now = now_ns();
        let sealed = v.book.offer(digest, payload, now, &mut pushed_out);
        v.book.expire(now, &mut pushed_out);
        self.count_unverified(pushed_out.len());
        match sealed {
            Some(p) => self.live(p).await,
            None => true,
        }
    }

    /// A seal: when it is the gateway's, the batches it lists are handed on, in its order.
    async fn seal(&mut self, key: &str, payload: &[u8], attachment: Option<&[u8]>) -> bool {
        let Some(v) = self.verifier.as_mut() else {
            return true;
        };
        let checked = verify_message(&v.trusted, key, "", payload, attachment)
            .and_then(|s| v.fresh.check(key, s.signed_at_ns));
        let seal = match checked.map(|()| Seal::decode(payload)) {
            Ok(Ok(seal)) => seal,
            Ok(Err(e)) => {
                self.counters.refused.fetch_add(1, Relaxed);
                tracing::warn!(key, cause = %e, "a signed seal that does not decode skipped");
                return true;
            }
            Err(e) => {
                self.counters.refused.fetch_add(1, Relaxed);
                tracing::debug!(key, cause = %e, "a seal refused");
                return true;
            }
        };
        let mut released = Vec::new();
        v.book.seal(&seal.digests, now_ns(), &mut released);
        for p in released {
            if !self.live(p).await {
                return false;
            }
        }
        true
    }

    /// Whether a heartbeat is one to act on: any when nothing is verified, else only the
    /// gateway's, and not a replay.
    fn beat_is_genuine(&mut self, payload: &[u8], attachment: Option<&[u8]>) -> bool {
        let Some(v) = self.verifier.as_mut() else {
            return true;
        };
        let key = Key::Heartbeat(self.options.building.clone()).to_string();
        let checked = verify_message(&v.trusted, &key, "", payload, attachment)
            .and_then(|s| v.fresh.check(&key, s.signed_at_ns));
        if let Err(e) = &checked {
            self.counters.refused.fetch_add(1, Relaxed);
            tracing::debug!(cause = %e, "a heartbeat refused");
        }
        checked.is_ok()
    }

    /// Drops what waited for a seal longer than [`SEAL_WAIT`].
    fn expire_unsealed(&mut self) {
        let Some(v) = self.verifier.as_mut() else {
            return;
        };
        let mut expired = Vec::new();
        v.book.expire(now_ns(), &mut expired);
        self.count_unverified(expired.len());
    }

    fn count_unverified(&self, n: usize) {
        if n > 0 {
            self.counters.unverified.fetch_add(n as u64, Relaxed);
            tracing::debug!(batches = n, "live batches no seal listed were dropped");
        }
    }

    /// Hands one batch over; false once the consumer has gone.
    async fn deliver(&mut self, payload: Vec<u8>, batch: CorrectedBatch, recovered: bool) -> bool {
        if is_late(&batch) {
            self.counters.late.fetch_add(1, Relaxed);
        }
        let behind = self
            .marks
            .get(&batch.header.sensor_id)
            .is_some_and(|m| batch.header.timestamp_ns <= m.position.timestamp_ns);
        if is_late(&batch) && behind {
            self.fill(&batch);
        } else if !is_duplicate(&batch) {
            let mark = Mark::of(&batch);
            // In place for a known sensor: no id to copy per batch.
            match self.marks.get_mut(&batch.header.sensor_id) {
                Some(m) => {
                    if let Some(hole) = Hole::between(m.position, mark.position) {
                        let holes = self
                            .holes
                            .entry(batch.header.sensor_id.clone())
                            .or_default();
                        if holes.len() >= MAX_HOLES {
                            holes.remove(0);
                        }
                        holes.push(hole);
                    }
                    *m = mark;
                }
                None => {
                    // A sensor met for the first time, past its number 0: its earlier batches
                    // (from the time it is followed from) may still come late, if a gateway
                    // fetches a node's first seconds from its buffer.
                    if mark.position.sequence > 0
                        && mark.position.timestamp_ns > self.new_sensors_from_ns
                    {
                        self.holes.insert(
                            batch.header.sensor_id.clone(),
                            vec![Hole {
                                // Numbered so that the next is 0.
                                after: Position {
                                    sequence: u64::MAX,
                                    timestamp_ns: self.new_sensors_from_ns.saturating_sub(1),
                                },
                                before: mark.position,
                            }],
                        );
                    }
                    self.marks.insert(batch.header.sensor_id.clone(), mark);
                }
            }
        }
        let c = if recovered {
            &self.counters.recovered
        } else {
            &self.counters.live
        };
        c.fetch_add(1, Relaxed);
        let holes = self
            .holes
            .get(&batch.header.sensor_id)
            .cloned()
            .unwrap_or_default();
        let mark = self
            .marks
            .get(&batch.header.sensor_id)
            .map_or_else(|| Position::of(&batch), |m| m.position);
        self.tx
            .send(Delivery {
                building: self.options.building.clone(),
                payload,
                batch,
                recovered,
                holes,
                mark,
            })
            .await
            .is_ok()
    }

    /// Reads what the consumer missed while it was away: the late batches kept meanwhile in the
    /// holes it saved, then places the sequence numbers of `resume_after` in time, then reads
    /// every resumed sensor's history on from its mark.
    async fn resume(&mut self) -> bool {
        let saved: Vec<(SensorId, Hole)> = self
            .holes
            .iter()
            .flat_map(|(s, holes)| holes.iter().map(|h| (s.clone(), *h)))
            .collect();
        for (sensor, hole) in saved {
            // A hole a batch of an earlier one filled meanwhile is smaller now, or gone.
            let Some(now) = self.hole_of(&sensor, hole.before.timestamp_ns.saturating_sub(1))
            else {
                continue;
            };
            if !self.fill_hole(&sensor, now, Until::End).await {
                return false;
            }
        }
        let by_number: Vec<(SensorId, u64)> = self
            .options
            .resume_after
            .iter()
            .filter(|(s, _)| !self.marks.contains_key(*s))
            .map(|(s, l)| (s.clone(), *l))
            .collect();
        for (sensor, last) in by_number {
            let mut request = HistoryRequest::sensor(&self.options.building, &sensor);
            (request.from_seq, request.to_seq) = (Some(last), Some(last));
            match self.read(&sensor, &request).await.last() {
                Some(newest) => {
                    self.marks.insert(sensor, Mark::of(&newest.batch));
                }
                None => {
                    // Not kept (past retention): by number, as the saved state allows.
                    request.from_seq = Some(last.saturating_add(1));
                    request.to_seq = None;
                    if !self.hand_over(&sensor, request, Until::End).await {
                        return false;
                    }
                }
            }
        }
        let marked: Vec<(SensorId, i64)> = self
            .marks
            .iter()
            .map(|(s, m)| (s.clone(), m.after_ns()))
            .collect();
        for (sensor, from_ns) in marked {
            if !self.recover(&sensor, from_ns, Until::End).await {
                return false;
            }
        }
        true
    }

    async fn live(&mut self, payload: Vec<u8>) -> bool {
        let Ok(batch) = CorrectedBatch::decode(&payload) else {
            tracing::warn!("a corrected batch that does not decode skipped");
            return true;
        };
        let sensor = batch.header.sensor_id.clone();
        if is_late(&batch) {
            if !self.options.late_batches {
                return true;
            }
            // Behind the position, or, for a sensor not met yet, before it is followed from.
            let t = batch.header.timestamp_ns;
            let behind = self
                .marks
                .get(&sensor)
                .map_or(t < self.new_sensors_from_ns, |m| {
                    t <= m.position.timestamp_ns
                });
            if behind {
                return self.late(payload, batch).await;
            }
            // Ahead of the position: it overtook (or outlived) the live batch that would have
            // shown its hole, and is taken in line as a live batch is.
        }
        match judge(self.marks.get(&sensor), self.new_sensors_from_ns, &batch) {
            Next::Skip => true,
            Next::Deliver => self.deliver(payload, batch, false).await,
            Next::Recover { from_ns } => {
                let this = Position::of(&batch);
                if !self.recover(&sensor, from_ns, Until::Before(this)).await {
                    return false;
                }
                // Unless the history handed it over already (a node clock that went back).
                let done = self
                    .marks
                    .get(&sensor)
                    .is_some_and(|m| m.position.timestamp_ns >= this.timestamp_ns);
                done || self.deliver(payload, batch, false).await
            }
        }
    }

    /// A late batch handed over: its hole now starts after it (and is gone once full).
    fn fill(&mut self, batch: &CorrectedBatch) {
        let p = Position::of(batch);
        let Some(holes) = self.holes.get_mut(&batch.header.sensor_id) else {
            return;
        };
        if let Some(i) = holes.iter().position(|h| h.holds(p.timestamp_ns)) {
            holes[i].after = p;
            if Hole::between(p, holes[i].before).is_none() {
                holes.remove(i);
            }
        }
    }

    /// The hole of `sensor` that `timestamp_ns` falls in.
    fn hole_of(&self, sensor: &SensorId, timestamp_ns: i64) -> Option<Hole> {
        self.holes
            .get(sensor)?
            .iter()
            .find(|h| h.holds(timestamp_ns))
            .copied()
    }

    /// A live batch flagged `late`: handed over if it fills a hole, after any late batch of
    /// that hole lost before it (read from the history).
    async fn late(&mut self, payload: Vec<u8>, batch: CorrectedBatch) -> bool {
        let sensor = batch.header.sensor_id.clone();
        let p = Position::of(&batch);
        let Some(hole) = self.hole_of(&sensor, p.timestamp_ns) else {
            return true;
        };
        if p.sequence != hole.after.sequence.wrapping_add(1)
            && !self.fill_hole(&sensor, hole, Until::Before(p)).await
        {
            return false;
        }
        // Unless the history handed it over already.
        if self.hole_of(&sensor, p.timestamp_ns).is_none() {
            return true;
        }
        self.deliver(payload, batch, false).await
    }

    /// Reads the history inside `hole`, up to `until`, and hands over the late batches found.
    async fn fill_hole(&mut self, sensor: &SensorId, hole: Hole, until: Until) -> bool {
        let mut request = HistoryRequest::sensor(&self.options.building, sensor);
        request.from_ns = Some(hole.after.timestamp_ns.saturating_add(1));
        request.to_ns = Some(match until {
            Until::Through(p) | Until::Before(p) => p.timestamp_ns.saturating_add(1),
            Until::End => hole.before.timestamp_ns,
        });
        for r in self.read(sensor, &request).await {
            let p = Position::of(&r.batch);
            if until == Until::Before(p) {
                break;
            }
            if is_late(&r.batch)
                && self.hole_of(sensor, p.timestamp_ns).is_some()
                && !self.deliver(r.payload, r.batch, true).await
            {
                return false;
            }
            if until == Until::Through(p) {
                break;
            }
        }
        true
    }

    async fn heartbeat(&mut self, payload: &[u8]) -> bool {
        let Ok(beat) = from_json::<Heartbeat>(payload) else {
            tracing::warn!("a heartbeat that does not decode skipped");
            return true;
        };
        if self.beats.len() >= MAX_GATEWAYS && !self.beats.contains_key(&beat.gateway) {
            self.beats.clear();
        }
        let lost_beats = match self.beats.insert(beat.gateway.clone(), beat.sequence) {
            Some(previous) => beat.sequence != previous.wrapping_add(1),
            // The first seen: what came before it is unknown.
            None => true,
        };
        for (sensor, s) in &beat.sensors {
            if let (Some(sequence), Some(timestamp_ns)) = (s.late_sequence, s.late_timestamp_ns) {
                let late = Position {
                    sequence,
                    timestamp_ns,
                };
                if let Some(hole) = self.hole_of(sensor, timestamp_ns) {
                    if !self.fill_hole(sensor, hole, Until::Through(late)).await {
                        return false;
                    }
                }
            }
            let last = Position {
                sequence: s.last_sequence,
                timestamp_ns: s.last_timestamp_ns,
            };
            let from_ns = match self.marks.get(sensor) {
                Some(m) if last.timestamp_ns > m.position.timestamp_ns => m.after_ns(),
                Some(_) => continue,
                None if last.timestamp_ns >= self.new_sensors_from_ns => self.new_sensors_from_ns,
                None => continue,
            };
            if !self.recover(sensor, from_ns, Until::Through(last)).await {
                return false;
            }
        }
        if lost_beats {
            // A sensor that fell silent while the heartbeats naming its last batches were lost
            // is named in none: read on from where every sensor not named here was left.
            let silent: Vec<(SensorId, i64)> = self
                .marks
                .iter()
                .filter(|(s, _)| !beat.sensors.contains_key(*s))
                .map(|(s, m)| (s.clone(), m.after_ns()))
                .collect();
            for (sensor, from_ns) in silent {
                if !self.recover(&sensor, from_ns, Until::End).await {
                    return false;
                }
            }
        }
        true
    }

    /// Reads `sensor`'s batches from `from_ns` on, up to `until`, and hands over each that is
    /// not handed over yet; false once the consumer has gone.
    async fn recover(&mut self, sensor: &SensorId, from_ns: i64, until: Until) -> bool {
        let mut request = HistoryRequest::sensor(&self.options.building, sensor);
        request.from_ns = Some(from_ns);
        request.to_ns = match until {
            Until::End => None,
            Until::Through(p) | Until::Before(p) => Some(p.timestamp_ns.saturating_add(1)),
        };
        self.hand_over(sensor, request, until).await
    }

    /// Hands over, in the history's order, the batches `request` reads that come after the
    /// sensor's mark, up to `until`; duplicates stay out (repeats of what was handed over).
    async fn hand_over(
        &mut self,
        sensor: &SensorId,
        request: HistoryRequest,
        until: Until,
    ) -> bool {
        let mut got = self.read(sensor, &request).await;
        // Late batches are kept after later ones: in time order, each fits where it belongs.
        // (Stable: a node whose clock went back keeps the order it was received in.)
        got.sort_by_key(|r| r.batch.header.timestamp_ns);
        let start = self.marks.get(sensor).copied();
        let mut found = 0u64;
        for r in got {
            if is_duplicate(&r.batch) || (is_late(&r.batch) && !self.options.late_batches) {
                continue;
            }
            let p = Position::of(&r.batch);
            if until == Until::Before(p) {
                break;
            }
            let handed = self
                .marks
                .get(sensor)
                .is_some_and(|m| p.timestamp_ns <= m.position.timestamp_ns);
            if !handed {
                if start.is_some_and(|m| p.sequence > m.position.sequence) {
                    found += 1;
                }
                if !self.deliver(r.payload, r.batch, true).await {
                    return false;
                }
            }
            if until == Until::Through(p) {
                break;
            }
        }
        let wanted = match (start, until) {
            (Some(m), Until::Before(t)) => missing_between(&m, t),
            (Some(m), Until::Through(t)) => {
                missing_between(&m, t) + u64::from(t.sequence > m.position.sequence)
            }
            _ => 0,
        };
        self.counters
            .unrecoverable
            .fetch_add(wanted.saturating_sub(found), Relaxed);
        true
    }

    /// Every batch `request` reads; none (and counted) if the query failed.
    async fn read(
        &mut self,
        sensor: &SensorId,
        request: &HistoryRequest,
    ) -> Vec<crate::history::Recovered> {
        self.counters.history_queries.fetch_add(1, Relaxed);
        let mut got = Vec::new();
        let mut request = request.clone();
        request.trusted = self.verifier.as_ref().map(|v| v.trusted.clone());
        let fetched = fetch(
            &self.session,
            &request,
            self.options.query_timeout,
            &mut |r| got.push(r),
        )
        .await;
        if let Err(e) = fetched {
            self.counters.history_errors.fetch_add(1, Relaxed);
            tracing::warn!(sensor = %sensor, cause = %e, "history query failed");
        }
        got
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use triax_protocol::batch::Mode;
    use triax_protocol::batch::{BatchHeader, CorrectedSample, CorrectionInfo};

    const SECOND: i64 = 1_000_000_000;

    /// A batch of sensor `s`: one second (10 samples at 10 Hz) starting at `t_s`.
    pub(crate) fn batch(sequence: u64, t_s: i64, batch_flags: u16) -> CorrectedBatch {
        CorrectedBatch {
            header: BatchHeader {
                sensor_id: SensorId::new("s").unwrap(),
                sequence,
                timestamp_ns: t_s * SECOND,
                sample_rate_hz: 10.0,
            },
            batch_flags,
            info: CorrectionInfo {
                calibration_version: 1,
                mode: Mode::Dynamic,
                coverage_factor: 2.0,
            },
            samples: vec![
                CorrectedSample {
                    accel_mps2: [0.0; 3],
                    uncertainty_mps2: [0.0; 3],
                    flags: 0,
                };
                10
            ],
        }
    }

    #[test]
    fn live_batches_are_judged_by_number_and_time() {
        let m = Mark::of(&batch(7, 100, 0));
        let judge = |b: &CorrectedBatch| judge(Some(&m), 0, b);
        assert_eq!(judge(&batch(8, 101, 0)), Next::Deliver);
        // A gap by number.
        assert_eq!(
            judge(&batch(10, 103, flags::SEQUENCE_GAP)),
            Next::Recover {
                from_ns: 100 * SECOND + 1
            }
        );
        // Handed over already from the history, whatever its number.
        assert_eq!(judge(&batch(7, 100, 0)), Next::Skip);
        assert_eq!(judge(&batch(3, 96, 0)), Next::Skip);
        // A restarted node: numbers from 0 (or anything lower) again, later in time.
        for seq in [0, 2, 5] {
            assert_eq!(
                judge(&batch(seq, 150, 0)),
                Next::Recover {
                    from_ns: 100 * SECOND + 1
                },
                "{seq}"
            );
        }
        // A new run that happens to reach the next number, with time for batches between.
        assert_eq!(
            judge(&batch(8, 140, 0)),
            Next::Recover {
                from_ns: 100 * SECOND + 1
            }
        );
        // A repeat moves nothing and is passed on.
        assert_eq!(judge(&batch(5, 98, flags::DUPLICATE)), Next::Deliver);
    }

    #[test]
    fn a_sensor_met_for_the_first_time_is_read_from_the_start_if_batches_fit_before() {
        let from = 100 * SECOND;
        assert_eq!(judge(None, from, &batch(40, 99, 0)), Next::Deliver);
        assert_eq!(
            judge(None, from, &batch(40, 100, 0)),
            Next::Deliver,
            "no whole batch fits before it"
        );
        assert_eq!(
            judge(None, from, &batch(41, 101, 0)),
            Next::Recover { from_ns: from }
        );
        assert_eq!(
            judge(None, i64::MIN, &batch(0, 0, 0)),
            Next::Recover { from_ns: i64::MIN }
        );
    }

    #[test]
    fn missing_batches_are_bounded_by_number_and_by_clock() {
        let m = Mark::of(&batch(7, 100, 0));
        let at = |sequence, t_s| Position {
            sequence,
            timestamp_ns: t_s * SECOND,
        };
        assert_eq!(missing_between(&m, at(10, 103)), 2);
        assert_eq!(missing_between(&m, at(8, 101)), 0);
        // A numbering jump of 10^19 a second later: what fits in that second, plus one.
        assert_eq!(missing_between(&m, at(u64::MAX - 1, 102)), 2);
        // A restart says nothing by number.
        assert_eq!(missing_between(&m, at(3, 200)), 0);
    }
}
