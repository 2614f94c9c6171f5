//! Nothing lost from the sensor's first sample: real `triax-node`s (in this process, simulated
//! sensors at 100 Hz, their buffers on disk) behind a TCP link the test can cut, a `zenohd`
//! router, a gateway in a process of its own, and a §5.2 consumer (`triax_client::Follower`).
//! Faults, in turn: the nodes' link cut, the gateway killed (SIGKILL) and started again, the
//! router restarted, one node's link cut with two clean restarts of the gateway during the
//! cut, and the consumer killed and restarted from its saved positions and holes while the
//! gateway fills the holes a cut made. After each, the consumer must hold every batch the nodes made so far;
//! at the end, every batch is in the history once and in the consumer once, and each copy the
//! consumer holds is the history's replay byte for byte, but for the batches a kill caught
//! between publishing and the history's flush (the consumer has them live; the restarted
//! gateway fetched them again from the buffer, so the history has them flagged `late`): those
//! must agree sample for sample, their flags but for `late`.
//!
//! - `every_batch_arrives_once_across_cuts_kills_and_router_restarts`: one fault of each kind.
//! - `fault_campaign` (ignored; minutes): `TRIAX_FAULT_ROUNDS` rounds (default 100) of the
//!   three, `TRIAX_FAULT_DOWN_S` seconds down each (default 2); prints the figures BENCHMARKS.md
//!   quotes: `cargo test --release -p triax-tests --test gateway -- --ignored fault_campaign
//!   --nocapture`.

use std::collections::{BTreeMap, HashMap};
use std::process::Child;

use std::sync::atomic::{AtomicBool, Ordering::Relaxed};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};
use triax_test_support::child::Entry;

use tokio::net::{TcpListener, TcpStream};
use tokio::sync::oneshot;
use triax_client::follow::{FollowOptions, Follower, Hole, Position};
use triax_client::{history::fetch, HistoryRequest};
use triax_net::{ZenohMode, ZenohSettings};
use triax_node::{NodeConfig, RingConfig, SimSource, Summary};
use triax_protocol::batch::{flags, CorrectedBatch};
use triax_protocol::record::sample;
use triax_protocol::{BuildingId, SensorId};

use super::util::*;

const BUILDING: &str = "hfl";
const SENSORS: [&str; 3] = ["fl-a", "fl-b", "fl-c"];
const CHILD_ENV: [&str; 3] = [
    "TRIAX_TEST_FAULTS_BUILDING",
    "TRIAX_TEST_FAULTS_STORE",
    "TRIAX_TEST_FAULTS_CONNECT",
];

/// Not a test: the gateway of the fault tests in a process of its own (so that it can be
/// killed), started with `--ignored --exact` and the environment of [`CHILD_ENV`].
#[test]
#[ignore = "a child process entry point, started by the fault tests"]
fn fault_gateway_process() {
    let [building, store, connect] =
        CHILD_ENV.map(|k| std::env::var(k).unwrap_or_else(|_| panic!("{k} is set by the parent")));
    let mut cfg = triax_gateway::Config::for_tests(&building, std::path::Path::new(&store), vec![]);
    cfg.zenoh.connect = vec![connect];
    run_gateway_until_stdin_closes(cfg);
}

/// A TCP link between the nodes and the router that the test can cut: while cut, every
/// connection is closed and new ones are refused.
struct Link {
    endpoint: String,
    down: Arc<AtomicBool>,
    open: Arc<Mutex<Vec<tokio::task::AbortHandle>>>,
}

impl Link {
    async fn to(router: &str) -> Link {
        let target = router.trim_start_matches("tcp/").to_owned();
        let listener = TcpListener::bind("127.0.0.1:0").await.unwrap();
        let endpoint = format!("tcp/{}", listener.local_addr().unwrap());
        let down = Arc::new(AtomicBool::new(false));
        let open: Arc<Mutex<Vec<tokio::task::AbortHandle>>> = Arc::default();
        let (d, o) = (down.clone(), open.clone());
        tokio::spawn(async move {
            loop {
                let Ok((mut inbound, _)) = listener.accept().await else {
                    return;
                };
                if d.load(Relaxed) {
                    continue;
                }
                let Ok(mut outbound) = TcpStream::connect(&target).await else {
                    continue;
                };
                let task = tokio::spawn(async move {
                    let _ = tokio::io::copy_bidirectional(&mut inbound, &mut outbound).await;
                });
                o.lock().unwrap().push(task.abort_handle());
            }
        });
        Link {
            endpoint,
            down,
            open,
        }
    }

    fn cut(&self) {
        self.down.store(true, Relaxed);
        for task in self.open.lock().unwrap().drain(..) {
            task.abort();
        }
    }

    fn restore(&self) {
        self.down.store(false, Relaxed);
    }
}

/// A directory removed when the run passes (on drop after the asserts), kept when it fails.
struct TempPath(std::path::PathBuf);

impl TempPath {
    fn path(&self) -> &std::path::Path {
        &self.0
    }
}

impl Drop for TempPath {
    fn drop(&mut self) {
        if !std::thread::panicking() {
            let _ = std::fs::remove_dir_all(&self.0);
        }
    }
}

/// What the consumer handed over, per sensor: (sequence, payload), in order.
type Handed = Arc<Mutex<HashMap<String, Vec<(u64, Vec<u8>)>>>>;

/// What the consumer saves after each batch it takes, as a consumer that restarts must (§5.2
/// step 5): per sensor its position and its holes, and how many late batches it took.
#[derive(Default)]
struct Saved {
    positions: BTreeMap<SensorId, Position>,
    holes: BTreeMap<SensorId, Vec<Hole>>,
    late: u64,
}

/// Starts a follower resumed from `saved`, and the consumer that takes its batches into
/// `handed` and saves after each one, under the same lock: a kill leaves them agreeing.
async fn consume(
    consumer: &zenoh::Session,
    handed: &Handed,
    saved: &Arc<Mutex<Saved>>,
) -> tokio::task::JoinHandle<()> {
    let mut options = FollowOptions::new(BuildingId::new(BUILDING).unwrap());
    options.new_sensors_from_ns = Some(i64::MIN);
    {
        let s = saved.lock().unwrap();
        options.resume_at = s.positions.clone();
        options.resume_holes = s.holes.clone();
    }
    let mut follower = Follower::start(consumer, options).await.unwrap();
    let (h, s) = (handed.clone(), saved.clone());
    tokio::spawn(async move {
        while let Some(d) = follower.next().await {
            let mut handed = h.lock().unwrap();
            let mut saved = s.lock().unwrap();
            let sensor = d.batch.header.sensor_id.clone();
            saved.positions.insert(sensor.clone(), d.position());
            saved.holes.insert(sensor.clone(), d.holes.clone());
            saved.late += u64::from(d.batch.batch_flags & flags::LATE != 0);
            handed
                .entry(sensor.to_string())
                .or_default()
                .push((d.batch.header.sequence, d.payload));
        }
    })
}

/// The highest number the consumer holds of `sensor`.
fn newest(handed: &Handed, sensor: &str) -> Option<u64> {
    handed
        .lock()
        .unwrap()
        .get(sensor)
        .and_then(|got| got.iter().map(|(seq, _)| *seq).max())
}

/// Whether the consumer holds every number below `next` of `sensor`.
fn holds_all(handed: &Handed, sensor: &str, next: u64) -> bool {
    let h = handed.lock().unwrap();
    let Some(got) = h.get(sensor) else {
        return next == 0;
    };
    let mut seen = vec![false; next as usize];
    for (seq, _) in got {
        if let Some(s) = seen.get_mut(*seq as usize) {
            *s = true;
        }
    }
    seen.iter().all(|s| *s)
}

/// The numbers below `next` the consumer lacks, as ranges.
fn missing(handed: &Handed, sensor: &str, next: u64) -> Vec<std::ops::RangeInclusive<u64>> {
    let h = handed.lock().unwrap();
    let mut seen = vec![false; next as usize];
    for (seq, _) in h.get(sensor).into_iter().flatten() {
        if let Some(s) = seen.get_mut(*seq as usize) {
            *s = true;
        }
    }
    ranges((0..next).filter(|&i| !seen[i as usize]))
}

fn ranges(numbers: impl Iterator<Item = u64>) -> Vec<std::ops::RangeInclusive<u64>> {
    let mut out: Vec<std::ops::RangeInclusive<u64>> = Vec::new();
    for n in numbers {
        match out.last_mut() {
            Some(r) if *r.end() + 1 == n => *r = *r.start()..=n,
            _ => out.push(n..=n),
        }
    }
    out
}

/// The numbers below `next` the gateway's history lacks, as ranges.
async fn missing_in_history(
    session: &zenoh::Session,
    sensor: &str,
    next: u64,
) -> Vec<std::ops::RangeInclusive<u64>> {
    let mut request = HistoryRequest::sensor(
        &BuildingId::new(BUILDING).unwrap(),
        &SensorId::new(sensor).unwrap(),
    );
    request.to_seq = Some(next.saturating_sub(1));
    let mut kept = vec![false; next as usize];
    let _ = fetch(session, &request, TIMEOUT, &mut |r| {
        if let Some(k) = kept.get_mut(r.batch.header.sequence as usize) {
            *k = true;
        }
    })
    .await;
    ranges((0..next).filter(|&i| !kept[i as usize]))
}

/// The gateway's backfill counters and its sensors' gaps, for a failure's message.
async fn gateway_counters(session: &zenoh::Session) -> String {
    let Ok(replies) = session
        .get(format!("triax/{BUILDING}/status"))
        .timeout(Duration::from_secs(5))
        .await
    else {
        return "no status".into();
    };
    match replies
        .recv_async()
        .await
        .ok()
        .and_then(|r| r.result().ok().cloned())
    {
        Some(sample) => String::from_utf8_lossy(&sample.payload().to_bytes()).into_owned(),
        None => "no status".into(),
    }
}

/// A node's next sequence number, from its buffer's status.
async fn next_sequence(session: &zenoh::Session, sensor: &str) -> Option<u64> {
    let replies = session
        .get(format!("triax/{BUILDING}/buffer/{sensor}?status"))
        .timeout(Duration::from_secs(2))
        .await
        .ok()?;
    let reply = replies.recv_async().await.ok()?;
    let status: serde_json::Value =
        serde_json::from_slice(&reply.result().ok()?.payload().to_bytes()).ok()?;
    status["next_sequence"].as_u64()
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
enum Fault {
    Cut,
    Kill,
    Router,
    /// The first node's link cut, and the gateway stopped cleanly and started again twice while
    /// it is: each start opens a history segment that holds the other nodes and nothing of the
    /// first, and the backfill must still find what the history holds of it from before.
    CutRestarts,
    /// Every link cut, and the consumer killed and restarted from what it saved while the
    /// gateway fills the holes: it must take the late batches still to come and those that
    /// came while it was away, once each.
    ConsumerKill,
}

/// The figures of a run.
#[derive(Debug, Default)]
struct Figures {
    /// Per kind: faults, and seconds from the end of each to the consumer holding everything.
    catch_up_s: BTreeMap<&'static str, Vec<f64>>,
    batches: u64,
    /// Batches the consumer holds live whose history copy was fetched late after a kill.
    refetched_after_kill: u64,
    late_batches: u64,
}

async fn run_faults(rounds: usize, down: Duration) -> Figures {
    let dir = tempfile::tempdir().unwrap();
    // Kept for a failed run's gateway logs.
    let dir = dir.keep();
    let dir = TempPath(dir);
    let store = dir.path().join("store");
    seed_store(&store, &SENSORS.map(|s| sample::record(s, 1)));
    let mut router = Router::start().await;
    // The first node has a link of its own, which a fault may cut while the others stream on.
    let link = Link::to(&router.endpoint).await;
    let lone = Link::to(&router.endpoint).await;
    let consumer = {
        let settings =
            ZenohSettings::loopback(ZenohMode::Client, vec![], vec![router.endpoint.clone()]);
        zenoh::open(triax_net::outbound_config(&settings).unwrap())
            .await
            .unwrap()
    };
    let log_of = |run: usize| dir.path().join(format!("gateway-{run}.log"));
    let mut runs = 0usize;
    let router_endpoint = router.endpoint.clone();
    let start_gateway = |runs: &mut usize| {
        let log = log_of(*runs);
        *runs += 1;
        Entry::new("faults::fault_gateway_process")
            .env(CHILD_ENV[0], BUILDING)
            .env(CHILD_ENV[1], &store)
            .env(CHILD_ENV[2], &router_endpoint)
            .log_to(&log)
            .spawn()
    };
    let answering = |session: zenoh::Session| async move {
        wait_until_async("the gateway to answer its status", || async {
            let Ok(replies) = session
                .get(format!("triax/{BUILDING}/status"))
                .timeout(Duration::from_millis(500))
                .await
            else {
                return false;
            };
            replies.recv_async().await.is_ok_and(|r| r.result().is_ok())
        })
        .await;
    };
    let mut gateway: Child = start_gateway(&mut runs);
    answering(consumer.clone()).await;

    let handed: Handed = Arc::default();
    let saved: Arc<Mutex<Saved>> = Arc::default();
    let mut collector = consume(&consumer, &handed, &saved).await;

    // The nodes, each with its own session through its link.
    let mut nodes: Vec<(oneshot::Sender<()>, tokio::task::JoinHandle<Summary>)> = Vec::new();
    for (i, s) in SENSORS.iter().enumerate() {
        let settings = ZenohSettings::loopback(
            ZenohMode::Client,
            vec![],
            vec![if i == 0 {
                lone.endpoint.clone()
            } else {
                link.endpoint.clone()
            }],
        );
        let session = zenoh::open(triax_net::outbound_config(&settings).unwrap())
            .await
            .unwrap();
        let (b, id) = (
            BuildingId::new(BUILDING).unwrap(),
            SensorId::new(*s).unwrap(),
        );
        let config = NodeConfig {
            ring: RingConfig::for_span(
                dir.path().join(format!("buffer-{s}")),
                b.clone(),
                id.clone(),
                3600.0,
                100.0,
                10,
            ),
            building: b,
            sensor: id,
            batch_samples: 10,
            clock_uncertainty_ns: 1e6,
            sync_interval: Duration::from_secs(1),
            queue_batches: 1024,
        };
        let (stop, stopped) = oneshot::channel::<()>();
        let task = tokio::spawn(async move {
            let source = Box::new(SimSource::new(100.0, 7 + i as u64));
            let summary = triax_node::run(config, source, session.clone(), async {
                let _ = stopped.await;
            })
            .await
            .expect("the node runs");
            let _ = session.close().await;
            summary
        });
        nodes.push((stop, task));
    }

    let mut figures = Figures::default();
    let caught_up = |consumer: zenoh::Session, handed: Handed| async move {
        let mut wanted = Vec::new();
        for s in SENSORS {
            let deadline = Instant::now() + TIMEOUT;
            let next = loop {
                if let Some(n) = next_sequence(&consumer, s).await {
                    break n;
                }
                assert!(
                    Instant::now() < deadline,
                    "node {s} did not answer its status"
                );
            };
            wanted.push((s, next));
        }
        for (s, next) in wanted {
            let deadline = Instant::now() + TIMEOUT;
            while !holds_all(&handed, s, next) {
                if Instant::now() > deadline {
                    panic!(
                        "the consumer lacks {s} {:?} below #{next}; the history lacks {:?}; {}",
                        missing(&handed, s, next),
                        missing_in_history(&consumer, s, next).await,
                        gateway_counters(&consumer).await
                    );
                }
                tokio::time::sleep(Duration::from_millis(5)).await;
            }
        }
    };
    caught_up(consumer.clone(), handed.clone()).await;
    for round in 0..rounds {
        for fault in [
            Fault::Cut,
            Fault::Kill,
            Fault::Router,
            Fault::CutRestarts,
            Fault::ConsumerKill,
        ] {
            match fault {
                Fault::Cut => {
                    link.cut();
                    lone.cut();
                    tokio::time::sleep(down).await;
                    link.restore();
                    lone.restore();
                }
                Fault::Kill => {
                    gateway.kill().unwrap();
                    gateway.wait().unwrap();
                    tokio::time::sleep(down).await;
                    gateway = start_gateway(&mut runs);
                    answering(consumer.clone()).await;
                }
                Fault::Router => router.restart_after(down).await,
                Fault::ConsumerKill => {
                    link.cut();
                    lone.cut();
                    tokio::time::sleep(down).await;
                    let late = saved.lock().unwrap().late;
                    link.restore();
                    lone.restore();
                    // Killed while the gateway fills the holes the cut made: once the first
                    // late batch is taken, the others still to come.
                    wait_until("a late batch taken", || saved.lock().unwrap().late > late).await;
                    collector.abort();
                    let _ = collector.await;
                    collector = consume(&consumer, &handed, &saved).await;
                }
                Fault::CutRestarts => {
                    lone.cut();
                    for _ in 0..2 {
                        let status = triax_test_support::child::stop_cleanly(&mut gateway);
                        assert!(status.success(), "the gateway stopped cleanly: {status}");
                        let before = newest(&handed, SENSORS[1]);
                        gateway = start_gateway(&mut runs);
                        answering(consumer.clone()).await;
                        // The new run's segment holds the streaming nodes before it stops.
                        wait_until("a streaming node's batch through the new run", || {
                            newest(&handed, SENSORS[1]) > before
                        })
                        .await;
                    }
                    tokio::time::sleep(down).await;
                    lone.restore();
                }
            }
            let back = Instant::now();
            caught_up(consumer.clone(), handed.clone()).await;
            let name = match fault {
                Fault::Cut => "link cut",
                Fault::Kill => "gateway kill -9",
                Fault::Router => "router restart",
                Fault::CutRestarts => "link cut, two restarts during it",
                Fault::ConsumerKill => "consumer killed during a backfill",
            };
            figures
                .catch_up_s
                .entry(name)
                .or_default()
                .push(back.elapsed().as_secs_f64());
        }
        if rounds > 1 {
            eprintln!("round {} of {rounds} done", round + 1);
        }
    }

    // Stop the nodes; every number each made is then known.
    let mut made = Vec::new();
    for ((stop, task), s) in nodes.into_iter().zip(SENSORS) {
        let _ = stop.send(());
        let summary = tokio::time::timeout(TIMEOUT, task).await.unwrap().unwrap();
        assert_eq!(summary.first_sequence, Some(0), "{s}");
        made.push((s, summary.next_sequence));
    }
    for &(s, next) in &made {
        wait_until(&format!("the consumer to hold {s} below #{next}"), || {
            holds_all(&handed, s, next)
        })
        .await;
        wait_history_holds(&consumer, BUILDING, s, next - 1).await;
    }
    collector.abort();
    let handed = handed.lock().unwrap().clone();
    for &(s, next) in &made {
        let mut request = HistoryRequest::sensor(
            &BuildingId::new(BUILDING).unwrap(),
            &SensorId::new(s).unwrap(),
        );
        request.to_seq = Some(next - 1);
        let mut kept: HashMap<u64, Vec<Vec<u8>>> = HashMap::new();
        fetch(&consumer, &request, TIMEOUT, &mut |r| {
            kept.entry(r.batch.header.sequence)
                .or_default()
                .push(r.payload)
        })
        .await
        .unwrap();
        let got = &handed[s];
        let mut count: HashMap<u64, usize> = HashMap::new();
        for (seq, _) in got {
            *count.entry(*seq).or_default() += 1;
        }
        let wrong: Vec<(u64, usize)> = (0..next)
            .map(|seq| (seq, kept.get(&seq).map_or(0, Vec::len)))
            .filter(|(_, n)| *n != 1)
            .collect();
        assert!(
            wrong.is_empty(),
            "{s}: kept other than once in the history (number, times): {wrong:?} of {next}; \
             gateway logs in {}",
            dir.path().display()
        );
        for seq in 0..next {
            assert_eq!(count.get(&seq), Some(&1), "{s} #{seq}: handed over once");
        }
        assert_eq!(
            got.len() as u64,
            next,
            "{s}: nothing beyond what the node made"
        );
        for (seq, payload) in got {
            let replay = &kept[seq][0];
            if payload == replay {
                continue;
            }
            let (live, late) = (
                CorrectedBatch::decode(payload).unwrap(),
                CorrectedBatch::decode(replay).unwrap(),
            );
            assert!(
                late.batch_flags & flags::LATE != 0 && live.batch_flags & flags::LATE == 0,
                "{s} #{seq}: the consumer's copy differs from the replay"
            );
            assert_eq!(
                live.samples, late.samples,
                "{s} #{seq}: values of a re-fetched batch"
            );
            assert_eq!(
                live.batch_flags,
                late.batch_flags & !flags::LATE,
                "{s} #{seq}"
            );
            figures.refetched_after_kill += 1;
        }
        figures.batches += next;
    }
    let _ = gateway.kill();
    let _ = gateway.wait();
    figures.late_batches = handed
        .values()
        .flatten()
        .filter(|(_, p)| CorrectedBatch::decode(p).is_ok_and(|b| b.batch_flags & flags::LATE != 0))
        .count() as u64;
    figures
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_batch_arrives_once_across_cuts_kills_and_router_restarts() {
    let figures = run_faults(1, Duration::from_secs(2)).await;
    assert!(
        figures.late_batches > 0,
        "the faults cost the live stream something: {figures:?}"
    );
    eprintln!("{figures:?}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
#[ignore = "minutes: a campaign of faults; BENCHMARKS.md quotes it"]
async fn fault_campaign() {
    let env = |k: &str, default: f64| {
        std::env::var(k)
            .ok()
            .and_then(|v| v.parse::<f64>().ok())
            .unwrap_or(default)
    };
    let rounds = env("TRIAX_FAULT_ROUNDS", 100.0) as usize;
    let down = Duration::from_secs_f64(env("TRIAX_FAULT_DOWN_S", 2.0));
    let started = Instant::now();
    let figures = run_faults(rounds, down).await;
    println!(
        "{rounds} rounds, {:.0} s down each, {:.0} s in all: {} batches of {} sensors, 0 lost, \
         0 duplicated; {} handed over late; {} re-fetched after a kill",
        down.as_secs_f64(),
        started.elapsed().as_secs_f64(),
        figures.batches,
        SENSORS.len(),
        figures.late_batches,
        figures.refetched_after_kill
    );
    for (kind, times) in &figures.catch_up_s {
        let mut t = times.clone();
        t.sort_by(f64::total_cmp);
        println!(
            "{kind}: {} faults; consumer whole again after median {:.2} s, max {:.2} s",
            t.len(),
            t[t.len() / 2],
            t[t.len() - 1]
        );
    }
}
