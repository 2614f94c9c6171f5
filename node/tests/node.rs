//! `triax-node` as a process, against a real Zenoh session on loopback (multicast scouting
//! off): what it publishes, what its buffer answers, across clean stops and `kill -9`.
//!
//! - `publishes_and_answers_from_its_buffer_across_restarts`: the raw batches a subscriber
//!   receives are, byte for byte, what a buffer query returns for their range; after SIGTERM
//!   and a restart the numbers continue without a gap and the old batches are still served;
//!   after `kill -9` every batch received live is still served and no number is used twice.
//! - `a_csv_source_is_kept_whole_and_the_node_stops_at_its_end`
//! - `help_is_the_readme_s`: `--help` is the text the README shows.
//! - `cost_at_100_hz` (ignored; `cargo test --release -p triax-node --test node -- --ignored
//!   --nocapture`): CPU and disk writes of a node at 100 Hz, for BENCHMARKS.md.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use triax_node::source::now_ns;
use triax_node::BufferStatus;
use triax_protocol::batch::RawBatchView;
use zenoh::query::ConsolidationMode;

const BIN: &str = env!("CARGO_BIN_EXE_triax-node");
/// The one deadline every wait here has: only a real failure reaches it.
const TIMEOUT: Duration = Duration::from_secs(60);
const RAW_KEY: &str = "triax/hq/raw/acc-01";
const BUFFER_KEY: &str = "triax/hq/buffer/acc-01";

/// A node process, killed when the test ends however it ends; its log kept in a file.
struct Node {
    child: Option<Child>,
    log: PathBuf,
}

impl Node {
    fn start(dir: &Path, endpoint: &str, run: u32, extra: &[&str]) -> Node {
        let log = dir.join(format!("node-{run}.log"));
        let child = Command::new(BIN)
            .args([
                "--building",
                "hq",
                "--sensor",
                "acc-01",
                "--source",
                "sim",
                "--buffer-dir",
            ])
            .arg(dir.join("buffer"))
            .args([
                "--connect",
                endpoint,
                "--no-multicast-scouting",
                "--clock-uncertainty-us",
                "1500",
                "--sim-seed",
            ])
            .arg(run.to_string())
            .args(extra)
            .env_remove("TRIAX_LOG")
            .stdout(Stdio::null())
            .stderr(std::fs::File::create(&log).unwrap())
            .spawn()
            .expect("triax-node starts");
        Node {
            child: Some(child),
            log,
        }
    }

    fn log(&self) -> String {
        std::fs::read_to_string(&self.log).unwrap_or_default()
    }

    fn signal(&self, sig: libc::c_int) {
        let pid = self.child.as_ref().unwrap().id() as libc::pid_t;
        // SAFETY: a signal to our own child, which has not been waited for yet.
        assert_eq!(unsafe { libc::kill(pid, sig) }, 0);
    }

    /// Waits for the process to exit; its status.
    async fn wait(&mut self) -> std::process::ExitStatus {
        let deadline = Instant::now() + TIMEOUT;
        let child = self.child.as_mut().unwrap();
        loop {
            if let Some(status) = child.try_wait().unwrap() {
                self.child = None;
                return status;
            }
            assert!(
                Instant::now() < deadline,
                "the node did not exit:\n{}",
                self.log()
            );
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
    }
}

impl Drop for Node {
    fn drop(&mut self) {
        if let Some(c) = &mut self.child {
            let _ = c.kill();
            let _ = c.wait();
        }
    }
}

/// A peer listening on a loopback port that nodes connect to.
async fn listening_session() -> (zenoh::Session, String) {
    let port = triax_net::free_loopback_port().unwrap();
    let endpoint = format!("tcp/127.0.0.1:{port}");
    let mut c = zenoh::Config::default();
    for (k, v) in [
        ("mode", "\"peer\"".to_owned()),
        ("listen/endpoints", format!("[\"{endpoint}\"]")),
        ("scouting/multicast/enabled", "false".to_owned()),
    ] {
        c.insert_json5(k, &v).unwrap();
    }
    (zenoh::open(c).await.unwrap(), endpoint)
}

type Subscriber =
    zenoh::pubsub::Subscriber<zenoh::handlers::FifoChannelHandler<zenoh::sample::Sample>>;

/// Receives live batches until one numbered at least `until` arrives; by sequence number.
/// Batches stamped before `since_ns` are an earlier run's, still on their way: skipped.
async fn receive_until(
    sub: &Subscriber,
    node: &Node,
    since_ns: i64,
    until: u64,
    got: &mut BTreeMap<u64, Vec<u8>>,
) -> u64 {
    let deadline = tokio::time::Instant::now() + TIMEOUT;
    loop {
        let s = tokio::time::timeout_at(deadline, sub.recv_async())
            .await
            .unwrap_or_else(|_| panic!("no live batch {until} in time:\n{}", node.log()))
            .unwrap();
        let bytes = s.payload().to_bytes().to_vec();
        let header = RawBatchView::parse(&bytes).expect("a raw batch").header;
        if header.timestamp_ns < since_ns {
            continue;
        }
        let seq = header.sequence;
        got.insert(seq, bytes);
        if seq >= until {
            return seq;
        }
    }
}

/// The buffer's answer for `from..=to`.
async fn buffer(session: &zenoh::Session, from: u64, to: u64) -> Vec<(u64, Vec<u8>)> {
    let replies = session
        .get(format!("{BUFFER_KEY}?from_seq={from};to_seq={to}"))
        .consolidation(ConsolidationMode::None)
        .timeout(TIMEOUT)
        .await
        .unwrap();
    let mut out = Vec::new();
    while let Ok(r) = replies.recv_async().await {
        let s = r.result().expect("a batch, not an error");
        assert_eq!(s.key_expr().as_str(), BUFFER_KEY);
        let bytes = s.payload().to_bytes().to_vec();
        let seq = RawBatchView::parse(&bytes)
            .expect("a raw batch")
            .header
            .sequence;
        out.push((seq, bytes));
    }
    out
}

async fn status(session: &zenoh::Session) -> BufferStatus {
    let replies = session
        .get(format!("{BUFFER_KEY}?status"))
        .timeout(TIMEOUT)
        .await
        .unwrap();
    let r = replies.recv_async().await.expect("a status reply");
    let s = r.result().expect("a status, not an error");
    serde_json::from_slice(&s.payload().to_bytes()).expect("status JSON")
}

async fn error_of(session: &zenoh::Session, params: &str) -> String {
    let replies = session
        .get(format!("{BUFFER_KEY}?{params}"))
        .timeout(TIMEOUT)
        .await
        .unwrap();
    let r = replies.recv_async().await.expect("a reply");
    let e = r.result().expect_err("an error reply");
    String::from_utf8(e.payload().to_bytes().to_vec()).unwrap()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn publishes_and_answers_from_its_buffer_across_restarts() {
    let dir = tempfile::tempdir().unwrap();
    let (session, endpoint) = listening_session().await;
    let sub = session.declare_subscriber(RAW_KEY).await.unwrap();

    // First run: live batches, and the buffer's answer for their range, byte for byte.
    let since = now_ns();
    let mut node = Node::start(dir.path(), &endpoint, 1, &[]);
    let mut live = BTreeMap::new();
    let first_seen = receive_until(&sub, &node, since, 0, &mut live).await;
    receive_until(&sub, &node, since, first_seen + 15, &mut live).await;
    let (&lo, &hi) = (live.keys().next().unwrap(), live.keys().last().unwrap());
    let answer = buffer(&session, lo, hi).await;
    let want: Vec<(u64, Vec<u8>)> = live.iter().map(|(s, b)| (*s, b.clone())).collect();
    assert_eq!(answer.len(), want.len(), "one reply per batch in range");
    assert!(
        answer == want,
        "the buffer answers the live bytes, in order"
    );
    // Batches sent before the subscription reached the node are held too, from 0.
    let early = buffer(&session, 0, hi).await;
    assert_eq!(
        early.iter().map(|b| b.0).collect::<Vec<_>>(),
        (0..=hi).collect::<Vec<_>>()
    );
    let mut all: BTreeMap<u64, Vec<u8>> = early.into_iter().collect();

    let st = status(&session).await;
    assert_eq!((st.building.as_str(), st.sensor.as_str()), ("hq", "acc-01"));
    assert_eq!(st.oldest_sequence, Some(0));
    assert!(st.newest_sequence >= Some(hi));
    assert_eq!(st.capacity_batches, 36_000);
    assert_eq!(st.clock_uncertainty_ns, 1.5e6);
    assert!(st.bytes > 0 && st.batches > hi);

    for (params, want) in [
        ("from_seq=3", "buffer query: to_seq: missing"),
        (
            "from_seq=3;to_seq=x",
            "buffer query: to_seq: \"x\" is not a whole number",
        ),
        ("from_seq=0;to_seq=100000", "spans 100001 batches"),
        ("from_seq=0;to_seq=1;limit=2", "unknown parameter \"limit\""),
    ] {
        let e = error_of(&session, params).await;
        assert!(e.contains(want), "{params}: {e}");
    }
    // Beyond what is held: nothing, not an error.
    assert!(buffer(&session, hi + 1_000_000, hi + 1_000_010)
        .await
        .is_empty());

    // A clean stop, then a restart: the numbers go on without a gap, the old batches stay.
    node.signal(libc::SIGTERM);
    let exit = node.wait().await;
    assert!(exit.success(), "{exit:?}\n{}", node.log());
    assert!(
        node.log().contains("node stopped, buffer flushed"),
        "{}",
        node.log()
    );
    assert!(
        buffer(&session, 0, hi).await.is_empty(),
        "the stopped node answers nothing"
    );

    let since = now_ns();
    let mut node = Node::start(dir.path(), &endpoint, 2, &[]);
    let mut live2 = BTreeMap::new();
    let seen = receive_until(&sub, &node, since, 0, &mut live2).await;
    receive_until(&sub, &node, since, seen + 5, &mut live2).await;
    let newest = *live2.keys().last().unwrap();
    let answer = buffer(&session, 0, newest).await;
    let seqs: Vec<u64> = answer.iter().map(|b| b.0).collect();
    assert_eq!(
        seqs,
        (0..=newest).collect::<Vec<_>>(),
        "no gap across a clean restart"
    );
    for (seq, bytes) in &answer {
        if let Some(before) = all.get(seq) {
            assert!(bytes == before, "batch {seq} changed across the restart");
        }
        if let Some(l) = live2.get(seq) {
            assert!(bytes == l, "batch {seq} differs from what was published");
        }
    }
    all.extend(answer);

    // kill -9: every batch published is still served, and no number is used again.
    node.signal(libc::SIGKILL);
    node.wait().await;
    let since = now_ns();
    let mut node = Node::start(dir.path(), &endpoint, 3, &[]);
    let mut live3 = BTreeMap::new();
    let first_after_kill = receive_until(&sub, &node, since, 0, &mut live3).await;
    let killed_at = *live2.keys().last().unwrap();
    assert!(
        first_after_kill > killed_at,
        "numbers continue past the kill: {first_after_kill} after {killed_at}"
    );
    let answer: BTreeMap<u64, Vec<u8>> = buffer(&session, 0, first_after_kill)
        .await
        .into_iter()
        .collect();
    for (seq, bytes) in all.iter().chain(live2.iter()).chain(live.iter()) {
        let held = answer
            .get(seq)
            .unwrap_or_else(|| panic!("batch {seq} lost across the kill:\n{}", node.log()));
        assert!(held == bytes, "batch {seq} changed across the kill");
    }
    assert_eq!(answer.get(&first_after_kill), live3.get(&first_after_kill));
    node.signal(libc::SIGTERM);
    assert!(node.wait().await.success(), "{}", node.log());
    session.close().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_csv_source_is_kept_whole_and_the_node_stops_at_its_end() {
    let dir = tempfile::tempdir().unwrap();
    let csv = dir.path().join("in.csv");
    let t0 = 1_800_000_000_000_000_000i64;
    let mut text = String::from("t_ns,vx,vy,vz\n");
    for i in 0..25 {
        // 100 Hz, with two samples missing after the 12th.
        let k = if i < 12 { i } else { i + 2 };
        text.push_str(&format!("{},{i},0.5,-1\n", t0 + k * 10_000_000));
    }
    std::fs::write(&csv, text).unwrap();
    let buffer_dir = dir.path().join("buffer");
    let out = Command::new(BIN)
        .args(["--building", "hq", "--sensor", "acc-01", "--source"])
        .arg(format!("csv:{}", csv.display()))
        .arg("--buffer-dir")
        .arg(&buffer_dir)
        .args(["--no-multicast-scouting", "--log", "warn"])
        .env_remove("TRIAX_LOG")
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );

    let ring = triax_node::Ring::open(triax_node::RingConfig {
        dir: buffer_dir,
        building: "hq".parse().unwrap(),
        sensor: "acc-01".parse().unwrap(),
        capacity_batches: 100,
        segment_batches: 100,
    })
    .unwrap();
    let mut batches = Vec::new();
    ring.read_range(0, 100, |_, p| {
        let v = RawBatchView::parse(p).unwrap();
        batches.push((
            v.header.sequence,
            v.header.timestamp_ns,
            v.samples().map(|s| s[0]).collect::<Vec<f32>>(),
        ));
        true
    })
    .unwrap();
    let xs = |r: std::ops::Range<u32>| r.map(|i| i as f32).collect::<Vec<_>>();
    assert_eq!(
        batches,
        vec![
            (0, t0, xs(0..10)),
            // Cut at the missing samples, so that each batch's grid is true.
            (1, t0 + 100_000_000, xs(10..12)),
            (2, t0 + 140_000_000, xs(12..22)),
            // The rest, short, at the end of the input.
            (3, t0 + 240_000_000, xs(22..25)),
        ]
    );
    assert_eq!(ring.stats().next_sequence, 4);
}

#[test]
fn help_is_the_readme_s() {
    let out = Command::new(BIN)
        .arg("--help")
        .env_clear()
        .output()
        .unwrap();
    assert!(out.status.success());
    let help = String::from_utf8(out.stdout).unwrap();
    let readme =
        std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/../README.md")).unwrap();
    let start = "```text\n$ triax-node --help\n";
    let at = readme
        .find(start)
        .expect("the README shows triax-node --help")
        + start.len();
    let shown = &readme[at..at + readme[at..].find("```").unwrap()];
    // Markdown keeps no trailing blanks: compare line by line without them.
    let lines = |t: &str| t.lines().map(str::trim_end).collect::<Vec<_>>().join("\n");
    assert_eq!(
        lines(shown),
        lines(&help),
        "README's triax-node --help is not the binary's"
    );
}

/// CPU time (user + system, clock ticks) of `pid`.
fn cpu_ticks(pid: u32) -> u64 {
    let stat = std::fs::read_to_string(format!("/proc/{pid}/stat")).unwrap();
    // Fields after the command name (which may hold spaces), from field 3 on.
    let rest = &stat[stat.rfind(')').unwrap() + 2..];
    let f: Vec<&str> = rest.split_whitespace().collect();
    f[11].parse::<u64>().unwrap() + f[12].parse::<u64>().unwrap()
}

/// (`write_bytes`, `syscw`) of `pid`: bytes sent to the block layer, and write calls.
fn io_counters(pid: u32) -> (u64, u64) {
    let io = std::fs::read_to_string(format!("/proc/{pid}/io")).unwrap();
    let get = |k: &str| {
        io.lines()
            .find_map(|l| l.strip_prefix(k))
            .unwrap()
            .trim()
            .parse::<u64>()
            .unwrap()
    };
    (get("write_bytes:"), get("syscw:"))
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
#[ignore = "two minutes of wall time; run for BENCHMARKS.md"]
async fn cost_at_100_hz() {
    for sync_s in ["1", "10"] {
        measure_cost(sync_s).await;
    }
}

/// A minute of a node at 100 Hz with batches of 10, its buffer synced every `sync_s`.
async fn measure_cost(sync_s: &str) {
    let dir = tempfile::tempdir().unwrap();
    let (session, endpoint) = listening_session().await;
    let sub = session.declare_subscriber(RAW_KEY).await.unwrap();
    let since = now_ns();
    let node = Node::start(
        dir.path(),
        &endpoint,
        1,
        &["--log", "warn", "--sync-interval-s", sync_s],
    );
    let mut live = BTreeMap::new();
    let first = receive_until(&sub, &node, since, 0, &mut live).await;
    // Start measuring once the node runs steadily.
    receive_until(&sub, &node, since, first + 20, &mut live).await;
    let pid = node.child.as_ref().unwrap().id();
    let (t0, c0, (w0, s0)) = (Instant::now(), cpu_ticks(pid), io_counters(pid));
    let n0 = live.len();
    receive_until(&sub, &node, since, first + 620, &mut live).await;
    let (t1, c1, (w1, s1)) = (Instant::now(), cpu_ticks(pid), io_counters(pid));
    let secs = (t1 - t0).as_secs_f64();
    // SAFETY: sysconf only reads a constant.
    let hz = unsafe { libc::sysconf(libc::_SC_CLK_TCK) } as f64;
    let per_hour = 3600.0 / secs;
    let st = status(&session).await;
    println!(
        "sync every {sync_s} s, {secs:.1} s, {} batches received: CPU {:.2} % of one core; \
         written to the block layer {:.1} MB/h; {:.0} write calls/h (buffer and socket); \
         buffer {} bytes for {} batches ({:.1} B/batch, {:.2} MB/h of data)",
        live.len() - n0,
        100.0 * (c1 - c0) as f64 / hz / secs,
        (w1 - w0) as f64 * per_hour / 1e6,
        (s1 - s0) as f64 * per_hour,
        st.bytes,
        st.batches,
        st.bytes as f64 / st.batches as f64,
        st.bytes as f64 / st.batches as f64 * 36_000.0 / 1e6,
    );
    drop(node);
    session.close().await.unwrap();
}
