//! Following a building's corrected streams without losing a batch (PROTOCOL.md §5.2).
//!
//! The gateway publishes the live stream with drop congestion control: a consumer that falls
//! behind loses batches on its own link. A [`Follower`] notices, per sensor, a jump in sequence
//! numbers and fetches exactly what it missed from the history before handing over the batch
//! that showed the gap; it reads the gateway's heartbeat to notice a lost *last* batch; and,
//! started with the last sequence numbers a consumer handled before it stopped, it first reads
//! what the consumer missed while it was away. Batches come out per sensor in the order the
//! gateway corrected them, each once: byte for byte what an uninterrupted subscriber received.
//!
//! What the history does not hold (lost before the gateway, or past retention) cannot be
//! recovered: it is counted ([`FollowerCounters::unrecoverable`]), and the live batch after
//! such a stretch carries `sequence_gap` anyway.

use std::collections::{BTreeMap, HashMap};
use std::sync::atomic::{AtomicU64, Ordering::Relaxed};
use std::sync::Arc;
use std::time::Duration;

use tokio::sync::mpsc;
use triax_protocol::batch::{flags, CorrectedBatch};
use triax_protocol::keys::{self, Stream};
use triax_protocol::messages::Heartbeat;
use triax_protocol::{from_json, BuildingId, Key, SensorId};

use crate::history::{fetch, HistoryRequest};
use crate::{zenoh_err, ClientError};

/// A sequence number this far below the last one is a node restart, not a late batch (the
/// gateway's own rule).
const RESTART_BACKWARDS: u64 = 1024;

/// What to follow, and from where.
#[derive(Debug, Clone)]
pub struct FollowOptions {
    pub building: BuildingId,
    /// The last sequence number handled per sensor before a restart: what follows it is read
    /// from the history first. Empty: start with the live stream.
    pub resume_after: BTreeMap<SensorId, u64>,
    /// How long one history query may take.
    pub query_timeout: Duration,
    /// Live batches (and heartbeats) the follower holds while it reads the history or its
    /// consumer is busy; beyond that they are dropped, and read back from the history when the
    /// next batch or heartbeat shows what is missing.
    pub buffer_batches: usize,
}

impl FollowOptions {
    pub fn new(building: BuildingId) -> FollowOptions {
        FollowOptions {
            building,
            resume_after: BTreeMap::new(),
            query_timeout: Duration::from_secs(10),
            buffer_batches: 4096,
        }
    }
}

/// One batch handed to the consumer.
#[derive(Debug, Clone, PartialEq)]
pub struct Delivery {
    pub payload: Vec<u8>,
    pub batch: CorrectedBatch,
    /// Read from the history rather than taken live.
    pub recovered: bool,
}

/// What the follower did.
#[derive(Debug, Default)]
pub struct FollowerCounters {
    pub live: AtomicU64,
    pub recovered: AtomicU64,
    /// Batches a gap or a heartbeat said were missing that the history did not have.
    pub unrecoverable: AtomicU64,
    pub history_queries: AtomicU64,
    pub history_errors: AtomicU64,
}

/// A building's corrected batches, none lost that the history holds.
pub struct Follower {
    rx: mpsc::Receiver<Delivery>,
    counters: Arc<FollowerCounters>,
    task: tokio::task::JoinHandle<()>,
    /// Keeps the subscriptions of a follower started alone.
    _fleet: Option<Fleet>,
}

/// What a building's follower is told by the subscriptions, in arrival order.
enum Event {
    Live(Vec<u8>),
    Beat(Vec<u8>),
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
    _live: zenoh::pubsub::Subscriber<()>,
    _beats: zenoh::pubsub::Subscriber<()>,
}

impl Fleet {
    /// Subscribes to the corrected streams and heartbeats of `building`, or of every building
    /// when none is given. Nothing is followed until [`Fleet::follow`].
    pub async fn start(
        session: &zenoh::Session,
        building: Option<&BuildingId>,
    ) -> Result<Fleet, ClientError> {
        let routes: Routes = Arc::default();
        let (live_expr, beat_expr) = match building {
            Some(b) => (
                keys::all_sensors(b, Stream::Corrected),
                Key::Heartbeat(b.clone()).to_string(),
            ),
            None => (
                keys::all_buildings(Stream::Corrected),
                "triax/*/heartbeat".to_owned(),
            ),
        };
        let route = |routes: Routes, wrap: fn(Vec<u8>) -> Event| {
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
                    let _ = tx.try_send(wrap(sample.payload().to_bytes().into_owned()));
                }
            }
        };
        let live = session
            .declare_subscriber(live_expr)
            .callback(route(routes.clone(), Event::Live))
            .await
            .map_err(zenoh_err("subscribe to corrected streams"))?;
        let beats = session
            .declare_subscriber(beat_expr)
            .callback(route(routes.clone(), Event::Beat))
            .await
            .map_err(zenoh_err("subscribe to heartbeats"))?;
        Ok(Fleet {
            session: session.clone(),
            routes,
            _live: live,
            _beats: beats,
        })
    }

    /// Starts following `options.building`: reads what `options.resume_after` says was missed,
    /// then the live stream. A building the subscription does not cover gets nothing.
    pub fn follow(&self, options: FollowOptions) -> Follower {
        let (events_tx, mut events) = mpsc::channel(options.buffer_batches.max(1));
        self.routes
            .write()
            .unwrap_or_else(|p| p.into_inner())
            .insert(options.building.clone(), events_tx);
        let (tx, rx) = mpsc::channel(1024);
        let counters = Arc::new(FollowerCounters::default());
        let mut state = State {
            session: self.session.clone(),
            options: options.clone(),
            last: options.resume_after.clone().into_iter().collect(),
            tx,
            counters: counters.clone(),
        };
        let task = tokio::spawn(async move {
            let resumed: Vec<(SensorId, u64)> =
                state.last.iter().map(|(s, l)| (s.clone(), *l)).collect();
            for (sensor, last) in resumed {
                if !state.recover(&sensor, last + 1, None).await {
                    return;
                }
            }
            while let Some(event) = events.recv().await {
                let open = match event {
                    Event::Live(payload) => state.live(payload).await,
                    Event::Beat(payload) => state.heartbeat(&payload).await,
                };
                if !open {
                    return;
                }
            }
        });
        Follower {
            rx,
            counters,
            task,
            _fleet: None,
        }
    }
}

impl Follower {
    /// Subscribes to the building's corrected streams and heartbeat, reads what
    /// `options.resume_after` says was missed, and starts following. (For many buildings, one
    /// [`Fleet`] serves them all.)
    pub async fn start(
        session: &zenoh::Session,
        options: FollowOptions,
    ) -> Result<Follower, ClientError> {
        let fleet = Fleet::start(session, Some(&options.building)).await?;
        let mut follower = fleet.follow(options);
        follower._fleet = Some(fleet);
        Ok(follower)
    }

    /// The next batch; none once the session closed.
    pub async fn next(&mut self) -> Option<Delivery> {
        self.rx.recv().await
    }

    pub fn counters(&self) -> &FollowerCounters {
        &self.counters
    }
}

impl Drop for Follower {
    fn drop(&mut self) {
        self.task.abort();
    }
}

struct State {
    session: zenoh::Session,
    options: FollowOptions,
    /// The last sequence number handed over, per sensor.
    last: HashMap<SensorId, u64>,
    tx: mpsc::Sender<Delivery>,
    counters: Arc<FollowerCounters>,
}

impl State {
    /// Hands one batch over; false once the consumer has gone.
    async fn deliver(&mut self, payload: Vec<u8>, batch: CorrectedBatch, recovered: bool) -> bool {
        self.last
            .insert(batch.header.sensor_id.clone(), batch.header.sequence);
        let c = if recovered {
            &self.counters.recovered
        } else {
            &self.counters.live
        };
        c.fetch_add(1, Relaxed);
        self.tx
            .send(Delivery {
                payload,
                batch,
                recovered,
            })
            .await
            .is_ok()
    }

    async fn live(&mut self, payload: Vec<u8>) -> bool {
        let Ok(batch) = CorrectedBatch::decode(&payload) else {
            tracing::warn!("a corrected batch that does not decode skipped");
            return true;
        };
        let (sensor, seq) = (batch.header.sensor_id.clone(), batch.header.sequence);
        match self.last.get(&sensor).copied() {
            Some(last)
                if seq > last.saturating_add(1)
                    && !self.recover(&sensor, last + 1, Some(seq - 1)).await =>
            {
                return false;
            }
            // Already handed over from the history, unless the gateway flagged it a duplicate
            // (published, so an uninterrupted subscriber got it too) or the node restarted.
            Some(last)
                if seq <= last
                    && batch.batch_flags & flags::DUPLICATE == 0
                    && !(seq == 0 || last - seq > RESTART_BACKWARDS) =>
            {
                return true;
            }
            _ => {}
        }
        self.deliver(payload, batch, false).await
    }

    async fn heartbeat(&mut self, payload: &[u8]) -> bool {
        let Ok(beat) = from_json::<Heartbeat>(payload) else {
            tracing::warn!("a heartbeat that does not decode skipped");
            return true;
        };
        for (sensor, s) in beat.sensors {
            let Some(&last) = self.last.get(&sensor) else {
                continue;
            };
            let behind = s.last_sequence > last && s.last_sequence - last <= RESTART_BACKWARDS;
            if behind && !self.recover(&sensor, last + 1, Some(s.last_sequence)).await {
                return false;
            }
        }
        true
    }

    /// Reads `from..=to` (or everything from `from`) of `sensor` from the history and hands it
    /// over; false once the consumer has gone.
    async fn recover(&mut self, sensor: &SensorId, from: u64, to: Option<u64>) -> bool {
        let mut request = HistoryRequest::sensor(&self.options.building, sensor);
        request.from_seq = Some(from);
        request.to_seq = to;
        self.counters.history_queries.fetch_add(1, Relaxed);
        let mut got = Vec::new();
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
        if let Some(to) = to {
            let wanted = to - from + 1;
            let found = got
                .iter()
                .filter(|r| (from..=to).contains(&r.batch.header.sequence))
                .count() as u64;
            self.counters
                .unrecoverable
                .fetch_add(wanted.saturating_sub(found), Relaxed);
        }
        for r in got {
            if !self.deliver(r.payload, r.batch, true).await {
                return false;
            }
        }
        true
    }
}
