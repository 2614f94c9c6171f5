//! The gateway under a consumer that stalls, with real Zenoh sessions on loopback and a real
//! store.
//!
//! - `backpressure_slows_the_nodes_instead_of_dropping`: a consumer stalls for a second under
//!   each overload policy: drop-oldest drops (counted), backpressure delivers every batch in
//!   order and drops none.
//! - `status_answers_while_a_stalled_consumer_blocks_every_worker`: both workers wait on a
//!   stalled consumer; status queries are still answered.
//! - `a_dropped_gateway_leaves_no_worker_thread`: dropped without a shutdown, its worker
//!   threads still end.
//!
//! A binary of its own, its tests one at a time: Zenoh runs every session's receive callbacks
//! on one pool of two threads per process, and a stalled consumer's callback holds one of them,
//! as a backpressure gateway's blocked publish holds another. In separate processes, as
//! deployed, they would not share threads; in one, two such tests at once could leave no thread
//! to read the very link that would end the stall.

mod util;

use std::sync::atomic::Ordering::Relaxed;
use std::sync::{Arc, Mutex, OnceLock};
use std::time::{Duration, Instant};

use tokio::sync::Mutex as AsyncMutex;
use triax_gateway::{Gateway, Overload};
use triax_protocol::batch::CorrectedBatch;
use triax_protocol::record::sample;
use triax_protocol::{BuildingId, Key};
use util::*;
use zenoh::Wait;

/// Held by each test for its whole run.
static ONE_AT_A_TIME: AsyncMutex<()> = AsyncMutex::const_new(());

/// One run of a consumer that stalls for `STALL` at its first batch while a node sends `n`
/// batches of 1000 samples, far more than Zenoh's queues and the sockets hold. Returns the
/// sequence numbers the consumer got, in order, and the gateway's drop count.
async fn stalled_consumer(overload: Overload, building: &str, n: u64) -> (Vec<u64>, u64) {
    const STALL: Duration = Duration::from_secs(1);
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("store");
    seed_store(&store, &[sample::record("stall", 1)]);
    let mut cfg = config(building, &store);
    cfg.overload = overload;
    cfg.workers = 1;
    cfg.queue_capacity_batches = 1;
    let endpoint = cfg.zenoh.listen[0].clone();
    let gateway = Gateway::start(cfg).await.unwrap();
    let counters = gateway.counters().clone();
    let session = client(&endpoint).await;
    let got = Arc::new(Mutex::new(Vec::new()));
    let g = got.clone();
    let open_at = OnceLock::new();
    let _sub = session
        .declare_subscriber(key_corrected(building, "stall"))
        .callback(move |sample| {
            let open_at = *open_at.get_or_init(|| Instant::now() + STALL);
            if let Some(wait) = open_at.checked_duration_since(Instant::now()) {
                std::thread::sleep(wait);
            }
            let batch = CorrectedBatch::decode(&sample.payload().to_bytes()).unwrap();
            g.lock().unwrap().push(batch.header.sequence);
        })
        .await
        .unwrap();
    let publisher = blocking_publisher(&session, key_raw(building, "stall")).await;
    for seq in 0..n {
        publisher
            .put(raw("stall", seq, vec![[0.1, -0.2, 0.98]; 1000]))
            .await
            .unwrap();
    }
    // Everything sent is either delivered or counted as dropped.
    wait_until("every batch delivered or counted as dropped", || {
        got.lock().unwrap().len() as u64 + counters.dropped.load(Relaxed) == n
    })
    .await;
    gateway.run_until(async {}).await.unwrap();
    session.close().await.unwrap();
    let sequences = got.lock().unwrap().clone();
    (sequences, counters.dropped.load(Relaxed))
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn backpressure_slows_the_nodes_instead_of_dropping() {
    let _alone = ONE_AT_A_TIME.lock().await;
    let n = 600;
    // The same stall under drop-oldest, with a one-batch queue: batches are dropped, so the
    // stall does overload the gateway.
    let (sequences, dropped) = stalled_consumer(Overload::DropOldest, "o1", n).await;
    assert!(dropped > 0, "{} delivered, none dropped", sequences.len());
    assert!(sequences.windows(2).all(|w| w[0] < w[1]), "in order");
    let (sequences, dropped) = stalled_consumer(Overload::Backpressure, "o2", n).await;
    assert_eq!(dropped, 0);
    assert_eq!(
        sequences,
        (0..n).collect::<Vec<_>>(),
        "every batch, in order"
    );
}

/// A stalled consumer holds up the corrected publishes, and with them every worker. Status,
/// metrics and pushes are served by the async runtime, which the workers must not take down
/// with them: here two workers (as many as the test runtime's threads, were they its tasks)
/// wait on the stall, and a status query is still answered during it.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn status_answers_while_a_stalled_consumer_blocks_every_worker() {
    let _alone = ONE_AT_A_TIME.lock().await;
    // One sensor on each of the two workers (by the hash of the id).
    let ids = ["stall-a", "stall-b"];
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("store");
    seed_store(&store, &ids.map(|id| sample::record(id, 1)));
    let mut cfg = config("o3", &store);
    cfg.workers = 2;
    let endpoint = cfg.zenoh.listen[0].clone();
    let gateway = Gateway::start(cfg).await.unwrap();
    let counters = gateway.counters().clone();
    // The stalled consumer has a session of its own, so that the nodes and the status query
    // do not share its stalled link. It stalls until the test is done asking (or 20 s).
    let consumer = client(&endpoint).await;
    let gate = Arc::new((Mutex::new(false), std::sync::Condvar::new()));
    let g = gate.clone();
    let _sub = consumer
        .declare_subscriber("triax/o3/corrected/*")
        .callback(move |_| {
            let (open, cv) = &*g;
            let guard = open.lock().unwrap();
            let _open = cv
                .wait_timeout_while(guard, Duration::from_secs(20), |open| !*open)
                .unwrap();
        })
        .await
        .unwrap();
    let session = client(&endpoint).await;
    let mut publishers = Vec::new();
    for id in ids {
        publishers.push(blocking_publisher(&session, key_raw("o3", id)).await);
    }
    // Far more than Zenoh's queues and the sockets hold.
    let per_sensor = 300;
    for seq in 0..per_sensor {
        for (id, p) in ids.iter().zip(&publishers) {
            p.put(raw(id, seq, vec![[0.1, -0.2, 0.98]; 1000]))
                .await
                .unwrap();
        }
    }
    // Both workers are waiting once publishing has stopped short of what they were given.
    let mut last = u64::MAX;
    loop {
        tokio::time::sleep(Duration::from_millis(500)).await;
        let now = counters.published_batches.load(Relaxed);
        if now == last {
            break;
        }
        last = now;
    }
    assert!(
        last < 2 * per_sensor,
        "the stall held up publishing ({last} published)"
    );
    // Asked from a thread of its own with a deadline of its own: were the runtime blocked,
    // its timers would be too.
    let querier = session.clone();
    let answered = std::thread::spawn(move || {
        let replies = querier
            .get(Key::Status(BuildingId::new("o3").unwrap()).to_string())
            .timeout(Duration::from_secs(2))
            .wait()
            .unwrap();
        let reply = replies.recv_timeout(Duration::from_secs(2)).unwrap();
        reply.map(|r| r.result().is_ok())
    })
    .join()
    .unwrap();
    let still_stalled = counters.published_batches.load(Relaxed) == last;
    {
        let (open, cv) = &*gate;
        *open.lock().unwrap() = true;
        cv.notify_all();
    }
    assert_eq!(answered, Some(true), "status answered");
    assert!(still_stalled, "answered during the stall");
    gateway.run_until(async {}).await.unwrap();
    session.close().await.unwrap();
    consumer.close().await.unwrap();
}

/// Threads of this process whose name starts with `prefix`.
fn threads_named(prefix: &str) -> usize {
    std::fs::read_dir("/proc/self/task")
        .unwrap()
        .filter_map(|t| std::fs::read_to_string(t.ok()?.path().join("comm")).ok())
        .filter(|name| name.starts_with(prefix))
        .count()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_dropped_gateway_leaves_no_worker_thread() {
    let _alone = ONE_AT_A_TIME.lock().await;
    let dir = tempfile::tempdir().unwrap();
    let mut cfg = config("o4", &dir.path().join("store"));
    cfg.workers = 2;
    let gateway = Gateway::start(cfg).await.unwrap();
    // A thread takes its name once it runs.
    wait_until("two worker threads", || threads_named("triax-worker") == 2).await;
    drop(gateway);
    wait_until("the worker threads to end", || {
        threads_named("triax-worker") == 0
    })
    .await;
}
