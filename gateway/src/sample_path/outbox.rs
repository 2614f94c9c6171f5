//! Corrected batches published at the end of a receive burst rather than one by one.
//!
//! Zenoh's receive thread hands the gateway every batch of one socket read in turn. Put as
//! each is corrected, the batches reach the transmit thread spaced by the correction, and it
//! wakes and sends them one segment at a time; a relay that does no work in between has them
//! all in one segment. So a batch corrected on a receive thread waits in the outbox, and a
//! task queued on that thread's runtime publishes the outbox once the thread has gone through
//! the read: Tokio runs a task spawned from a worker when the running one yields, and the
//! receive task yields when its socket has nothing more (BENCHMARKS.md, "A fifth look").
//!
//! Invariants: a sensor's batches leave in the order they were corrected (one [`Burst`]
//! queue, taken whole and published under its lock); at most [`BURST_MAX`](burst::BURST_MAX)
//! batches wait, for at most one burst (the worker's idle sweep and the gateway's stop publish
//! what a task never took); a batch corrected off a multi-threaded Tokio runtime (on a
//! correction worker's thread) is published at once, behind what waits, unless a task already
//! queued, or a burst being corrected ([`Outbox::gathered`], the intake's), will take it with
//! the rest. The queue keeps its room; the task is the one allocation a burst costs (the
//! corrected payload already is one a batch).

use std::sync::atomic::Ordering::Relaxed;
use std::sync::Arc;
use std::time::Instant;

use triax_protocol::provenance::digest;
use zenoh::key_expr::KeyExpr;
use zenoh::qos::CongestionControl;
use zenoh::Wait;

use super::burst::{self, Burst, Pushed};
use super::inbox;
use super::seal::SealQueue;
use crate::clock::now_ns;
use crate::state::{GatewayCounters, SensorEntry};

/// One corrected batch, and what its publication updates.
pub struct Outgoing {
    pub key: KeyExpr<'static>,
    pub payload: Vec<u8>,
    pub entry: Arc<SensorEntry>,
    pub sequence: u64,
    pub timestamp_ns: i64,
}

/// Batches waiting for the end of their receive burst.
pub struct Outbox {
    session: zenoh::Session,
    counters: Arc<GatewayCounters>,
    /// One queue: a sensor's batches are published in the order they were corrected.
    waiting: Burst<Outgoing>,
    /// Where the digests of what was put go to be sealed; None when nothing is signed.
    seals: Option<Arc<SealQueue>>,
}

impl Outbox {
    pub fn new(
        session: zenoh::Session,
        counters: Arc<GatewayCounters>,
        seals: Option<Arc<SealQueue>>,
    ) -> Arc<Outbox> {
        Arc::new(Outbox {
            session,
            counters,
            waiting: Burst::new(1),
            seals,
        })
    }

    /// Publishes `out` at the end of the current receive burst, or now (behind whatever
    /// waits) when [`BURST_MAX`](burst::BURST_MAX) batches wait, or when no task is queued and the caller is
    /// not on a multi-threaded runtime to queue one.
    pub fn send(self: &Arc<Self>, out: Outgoing) {
        match self.waiting.push(0, out) {
            Pushed::Waits => {}
            Pushed::Full => self.flush(),
            Pushed::First => match burst::runtime() {
                Some(runtime) => {
                    let outbox = self.clone();
                    runtime.spawn(async move {
                        // Cleared before the queue is taken: a batch added after the take
                        // queues a new task.
                        outbox.waiting.task_started();
                        let started = Instant::now();
                        outbox.flush();
                        // Publishing is part of correcting in place: a worker's batch is
                        // published by the worker.
                        inbox::receive_budget_spent(started, Instant::now());
                    });
                }
                None => {
                    self.waiting.task_started();
                    self.flush();
                }
            },
        }
    }

    /// Runs `f` and then publishes every waiting batch: what `f` corrects leaves together,
    /// and no task is queued for it. Meanwhile a worker's batch waits for this flush rather
    /// than go alone.
    pub fn gathered<R>(&self, f: impl FnOnce() -> R) -> R {
        let ours = self.waiting.announce();
        let r = f();
        if ours {
            self.waiting.task_started();
        }
        self.flush();
        r
    }

    /// Publishes every waiting batch, in order.
    pub fn flush(&self) {
        self.waiting.take(|_, batches| {
            // One look at the clock for the lot: they leave within microseconds of one another.
            let published_ns = now_ns();
            match &self.seals {
                None => {
                    for out in batches.drain(..) {
                        self.publish(out, published_ns);
                    }
                }
                Some(seals) => {
                    // One push for the burst: the sealer's lock is taken once.
                    let mut digests = Vec::with_capacity(batches.len());
                    for out in batches.drain(..) {
                        let d = digest(out.key.as_str(), &[], &out.payload);
                        if self.publish(out, published_ns) {
                            digests.push(d);
                        }
                    }
                    seals.push(digests);
                }
            }
        });
    }

    /// Whether the batch was put.
    fn publish(&self, out: Outgoing, published_ns: i64) -> bool {
        // Drop rather than block inside Zenoh: a consumer that cannot keep up loses batches
        // on its own link, and catches up from the history; it never holds up the gateway or
        // the other consumers. The key is given up, not lent: lent, Zenoh would count it up
        // and down again.
        match self
            .session
            .put(out.key, out.payload)
            .congestion_control(CongestionControl::Drop)
            .wait()
        {
            Ok(()) => {
                self.counters.published_batches.fetch_add(1, Relaxed);
                out.entry
                    .note_published(out.sequence, out.timestamp_ns, published_ns);
                true
            }
            Err(e) => {
                self.counters.publish_errors.fetch_add(1, Relaxed);
                tracing::warn!(sensor = %out.entry.id, cause = %e, "corrected batch not published");
                false
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use std::time::Duration;

    use triax_protocol::SensorId;

    use super::*;
    use std::sync::Mutex;

    use crate::config::SensorSettings;
    use crate::sample_path::burst::BURST_MAX;
    use crate::sync::lock;

    /// A session on its own (no scouting, no listener): its own puts reach its own callback
    /// subscriber synchronously, inside `put`.
    async fn session() -> zenoh::Session {
        let mut c = zenoh::Config::default();
        for (k, v) in [
            ("mode", "\"peer\""),
            ("scouting/multicast/enabled", "false"),
            ("listen/endpoints", "[]"),
        ] {
            c.insert_json5(k, v).expect("valid zenoh setting");
        }
        zenoh::open(c).await.expect("session opens")
    }

    fn outgoing(entry: &Arc<SensorEntry>, key: &KeyExpr<'static>, sequence: u64) -> Outgoing {
        Outgoing {
            key: key.clone(),
            payload: sequence.to_le_bytes().to_vec(),
            entry: entry.clone(),
            sequence,
            timestamp_ns: sequence as i64,
        }
    }

    struct Bench {
        outbox: Arc<Outbox>,
        entry: Arc<SensorEntry>,
        key: KeyExpr<'static>,
        received: Arc<Mutex<Vec<u64>>>,
        /// Told when the batch numbered [`LAST`] arrives.
        all_arrived: Arc<tokio::sync::Notify>,
        _sub: zenoh::pubsub::Subscriber<()>,
    }

    const LAST: u64 = 3 * BURST_MAX as u64 + 9;

    async fn bench() -> Bench {
        let session = session().await;
        let received = Arc::new(Mutex::new(Vec::new()));
        let all_arrived = Arc::new(tokio::sync::Notify::new());
        let (r, done) = (received.clone(), all_arrived.clone());
        let sub = session
            .declare_subscriber("t/out")
            .callback(move |s| {
                let b = s.payload().to_bytes();
                let seq = u64::from_le_bytes(b[..8].try_into().expect("8 bytes"));
                lock(&r).push(seq);
                if seq == LAST {
                    done.notify_one();
                }
            })
            .await
            .expect("subscriber");
        let key = session.declare_keyexpr("t/out").await.expect("key");
        let counters = Arc::new(GatewayCounters::default());
        let id = SensorId::new("acc-1").expect("valid id");
        Bench {
            outbox: Outbox::new(session, counters, None),
            entry: Arc::new(SensorEntry::new(id, SensorSettings::default())),
            key,
            received,
            all_arrived,
            _sub: sub,
        }
    }

    #[test]
    fn off_a_runtime_a_batch_leaves_at_once() {
        let rt = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(1)
            .enable_all()
            .build()
            .expect("runtime");
        let b = rt.block_on(bench());
        // This thread is no runtime's: as a correction worker's.
        for seq in 0..3 {
            b.outbox.send(outgoing(&b.entry, &b.key, seq));
            assert_eq!(lock(&b.received).len(), seq as usize + 1);
        }
        assert_eq!(*lock(&b.received), [0, 1, 2]);
        assert_eq!(b.outbox.counters.published_batches.load(Relaxed), 3);
        assert_eq!(b.entry.counters.last_published_sequence.load(Relaxed), 2);
    }

    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn a_burst_waits_for_its_end_and_leaves_whole_and_in_order() {
        let b = bench().await;
        let (outbox, entry, key) = (b.outbox.clone(), b.entry.clone(), b.key.clone());
        let received = b.received.clone();
        let n = LAST + 1;
        let burst = tokio::spawn(async move {
            (0..n)
                .map(|seq| {
                    outbox.send(outgoing(&entry, &key, seq));
                    lock(&received).len()
                })
                .collect::<Vec<_>>()
        });
        let seen_during = burst.await.expect("burst task ends");
        // Nothing left before the 64th, which published all 64 (the task queued by the first
        // waits behind the burst's own); what the last ones waited for left at the end.
        let w = BURST_MAX;
        assert!(
            seen_during[..w - 1].iter().all(|&k| k == 0),
            "{seen_during:?}"
        );
        assert_eq!(seen_during[w - 1], w);
        tokio::time::timeout(Duration::from_secs(60), b.all_arrived.notified())
            .await
            .expect("the burst's tail is published once it ends");
        // The counters are counted after each put returns, so after its delivery: they are
        // checked in the test above, where the put is this thread's.
        assert_eq!(*lock(&b.received), (0..n).collect::<Vec<_>>());
    }
}
