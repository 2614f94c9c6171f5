//! The Python client (`examples/python/triax_client.py`, written from PROTOCOL.md alone) against
//! the Rust implementation, through a real gateway on loopback:
//!
//! Python `simulate` ──raw──▶ `triax_gateway::run` ──corrected──▶ Python `subscribe --json`
//!
//! while a Rust session decodes the same raw and corrected payloads. Every value Python encoded
//! must be what Rust decodes from the raw stream, and every corrected value Python decoded must
//! be bit for bit what `CorrectedBatch::decode` reads.
//!
//! `a_killed_python_follower_resumes_and_loses_nothing`: twenty sensors stream; one Python
//! `follow --out` runs throughout, another is killed with SIGKILL, stays down 10 s and is
//! started again on its file. Both files end holding every batch once, in order, byte for byte
//! the same.
//!
//! `a_python_follower_takes_late_batches_once`: a link cut of 30 batches per sensor, filled by
//! the gateway from the node's buffer once the follower has met the hole: the follower's file
//! holds every batch once, the hole's flagged `late`.
//!
//! `a_parquet_export_reads_back_identically_in_pandas`: a gateway's history, fetched and
//! written by `triax_client::parquet` (what `triax-export parquet` does), read by pandas with
//! pyarrow: every row, bit for bit, and the units in the file's metadata.
//!
//! Needs a Python interpreter with `eclipse-zenoh`, `pandas` and `pyarrow` installed, named by
//! `TRIAX_PYTHON` (`scripts/test` sets it up); without it the tests fail and say so.

mod util;

#[path = "python_client/exports.rs"]
mod exports;

use std::collections::BTreeMap;
use std::io::{BufRead, BufReader};
use std::path::PathBuf;
use std::process::{Child, Command, Stdio};
use std::time::Duration;

use serde_json::Value;
use triax_calibration_store::Store;
use triax_protocol::record::sample;
use triax_protocol::{BuildingId, CorrectedBatch, Key, Mode, RawBatch, SensorId};
use util::{free_port, wait_for_listener};

const BUILDING: &str = "pyb";
const SENSOR: &str = "py-01";
/// 2026-06-01T00:00:00Z: inside the sample record's validity, whatever the machine's clock says.
const START_NS: i64 = 1_780_272_000_000_000_000;
const BATCHES_SENT: usize = 12;
const BATCHES_CHECKED: usize = 6;

fn script() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../examples/python/triax_client.py")
}

/// Kills the child when the test ends early, so a failed assertion leaves no process behind.
struct Reaped(Child);

impl Drop for Reaped {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// Starts the client; its stdout lines arrive on the returned channel.
fn python(python: &str, args: &[String]) -> (Reaped, std::sync::mpsc::Receiver<String>) {
    let mut child = Command::new(python)
        .arg(script())
        .args(args)
        .stdout(Stdio::piped())
        .stderr(Stdio::inherit())
        .spawn()
        .unwrap_or_else(|e| panic!("cannot start {python}: {e}"));
    let stdout = child.stdout.take().unwrap();
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        for line in BufReader::new(stdout).lines().map_while(Result::ok) {
            if tx.send(line).is_err() {
                break;
            }
        }
    });
    (Reaped(child), rx)
}

/// Runs `script` (which reads files with pyarrow) with `args` under `py`.
///
/// pyarrow 18 can abort in the interpreter's teardown ("terminate called without an active
/// exception", apache/arrow#34314), after the script has done its work and printed: 3 runs in
/// 700 of the Parquet reader here. The script is followed by an exit that skips the teardown
/// (0 aborts in 1 000 runs), so the script's own errors still fail the run and the teardown's
/// cannot.
fn run_pyarrow_script(py: &str, script: &str, args: &[&std::ffi::OsStr]) -> std::process::Output {
    let script = format!("{script}\nimport os, sys\nsys.stdout.flush()\nos._exit(0)\n");
    Command::new(py)
        .args(["-c", &script])
        .args(args)
        .output()
        .unwrap_or_else(|e| panic!("cannot run {py}: {e}"))
}

/// The Python that `scripts/test` set up with `eclipse-zenoh`.
fn python_interpreter() -> String {
    std::env::var("TRIAX_PYTHON").unwrap_or_else(|_| {
        panic!(
            "TRIAX_PYTHON is not set: run the tests with scripts/test, which makes a Python \
             environment with eclipse-zenoh under target/pyenv and names it"
        )
    })
}

fn next_line(rx: &std::sync::mpsc::Receiver<String>, what: &str) -> Value {
    let line = rx
        .recv_timeout(Duration::from_secs(30))
        .unwrap_or_else(|e| panic!("no {what} from the Python client within 30 s: {e}"));
    serde_json::from_str(&line).unwrap_or_else(|e| panic!("{what}: {e}: {line}"))
}

fn f64_list(v: &Value) -> Vec<f64> {
    v.as_array()
        .unwrap()
        .iter()
        // null stands for a non-finite value in the client's JSON.
        .map(|x| x.as_f64().unwrap_or(f64::NAN))
        .collect()
}

fn same_f32(python: f64, rust: f32) -> bool {
    (python.is_nan() && rust.is_nan()) || python == f64::from(rust)
}

#[tokio::test(flavor = "multi_thread")]
async fn python_client_round_trips_through_a_gateway() {
    let py = python_interpreter();

    // A gateway whose store already holds the sensor's calibration.
    let dir = tempfile::tempdir().unwrap();
    let store_path = dir.path().join("store");
    {
        let store = Store::open(&store_path).unwrap();
        store
            .put(&sample::record(SENSOR, 1))
            .unwrap()
            .expect("sample record is accepted");
    }
    let port = free_port();
    let endpoint = format!("tcp/127.0.0.1:{port}");
    let config = triax_gateway::Config::for_tests(BUILDING, &store_path, vec![endpoint.clone()]);
    let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
    let gateway = tokio::spawn(triax_gateway::run(config, async {
        let _ = stopped.await;
    }));

    wait_for_listener(port).await;

    // A Rust consumer beside the Python one.
    let mut zc = zenoh::Config::default();
    zc.insert_json5("mode", "\"peer\"").unwrap();
    zc.insert_json5("connect/endpoints", &format!("[\"{endpoint}\"]"))
        .unwrap();
    zc.insert_json5("scouting/multicast/enabled", "false")
        .unwrap();
    let session = zenoh::open(zc).await.unwrap();
    let b = BuildingId::new(BUILDING).unwrap();
    let s = SensorId::new(SENSOR).unwrap();
    let raw_sub = session
        .declare_subscriber(Key::Raw(b.clone(), s.clone()).to_string())
        .await
        .unwrap();
    let corrected_sub = session
        .declare_subscriber(Key::Corrected(b, s).to_string())
        .await
        .unwrap();

    let common = |cmd: &str| -> Vec<String> {
        [
            cmd,
            "--building",
            BUILDING,
            "--sensor",
            SENSOR,
            "--connect",
            &endpoint,
            "--no-multicast",
            "--json",
        ]
        .map(String::from)
        .to_vec()
    };
    let mut sub_args = common("subscribe");
    sub_args
        .extend(["--count", &BATCHES_CHECKED.to_string(), "--timeout-s", "30"].map(String::from));
    let (mut subscriber, sub_lines) = python(&py, &sub_args);
    let ready = next_line(&sub_lines, "ready line");
    assert_eq!(ready["event"], "ready", "{ready}");

    let mut sim_args = common("simulate");
    sim_args.extend(
        [
            "--count",
            &BATCHES_SENT.to_string(),
            "--batch-samples",
            "20",
            "--interval-s",
            "0.1",
            "--start-ns",
            &START_NS.to_string(),
            "--temperature-c",
            "21.5",
            "--warmup-s",
            "1.5",
        ]
        .map(String::from),
    );
    let (mut simulator, sim_lines) = python(&py, &sim_args);

    // What Python says it sent, and what Python decoded.
    let mut sent = BTreeMap::new();
    for _ in 0..BATCHES_SENT {
        let v = next_line(&sim_lines, "simulated batch");
        sent.insert(v["sequence"].as_u64().unwrap(), v);
    }
    let mut decoded = BTreeMap::new();
    for _ in 0..BATCHES_CHECKED {
        let v = next_line(&sub_lines, "decoded batch");
        decoded.insert(v["sequence"].as_u64().unwrap(), v);
    }
    assert!(simulator.0.wait().unwrap().success(), "simulator failed");
    assert!(subscriber.0.wait().unwrap().success(), "subscriber failed");

    // What Rust decoded of the same streams.
    let mut raw = BTreeMap::new();
    while let Ok(Some(sample)) = raw_sub.try_recv() {
        let r = RawBatch::decode(&sample.payload().to_bytes()).expect("Python's raw batch decodes");
        raw.insert(r.header.sequence, r);
    }
    // Every corrected batch Python decoded, as Rust reads it: live where this session's link
    // kept up, from the history otherwise (byte for byte what the live stream carried, §5.1):
    // the live stream drops for a consumer that falls behind, as a loaded machine makes it.
    let last = *decoded.keys().max().expect("batches decoded");
    util::wait_history_holds(&session, BUILDING, SENSOR, last).await;
    let mut corrected = BTreeMap::new();
    while let Ok(Some(sample)) = corrected_sub.try_recv() {
        let c = CorrectedBatch::decode(&sample.payload().to_bytes()).unwrap();
        corrected.insert(c.header.sequence, c);
    }
    for &seq in decoded.keys() {
        if corrected.contains_key(&seq) {
            continue;
        }
        let mut request = triax_client::HistoryRequest::sensor(
            &BuildingId::new(BUILDING).unwrap(),
            &SensorId::new(SENSOR).unwrap(),
        );
        (request.from_seq, request.to_seq) = (Some(seq), Some(seq));
        triax_client::history::fetch(&session, &request, util::TIMEOUT, &mut |r| {
            corrected.insert(seq, r.batch);
        })
        .await
        .expect("the history answers");
    }
    assert!(
        decoded.keys().all(|k| corrected.contains_key(k)),
        "Rust sees every corrected batch Python decoded"
    );

    // Python encoder ⇄ Rust decoder.
    assert!(!raw.is_empty(), "no raw batch reached the Rust session");
    for (seq, r) in &raw {
        let p = &sent[seq];
        assert_eq!(p["timestamp_ns"].as_i64().unwrap(), r.header.timestamp_ns);
        assert_eq!(
            p["sample_rate_hz"].as_f64().unwrap(),
            r.header.sample_rate_hz
        );
        assert_eq!(r.header.sensor_id.as_str(), SENSOR);
        assert_eq!(r.temperature_c, Some(21.5));
        let ps = p["samples"].as_array().unwrap();
        assert_eq!(ps.len(), r.samples.len());
        for (pv, rv) in ps.iter().zip(&r.samples) {
            let pv = f64_list(pv);
            for j in 0..3 {
                assert!(same_f32(pv[j], rv[j]), "raw seq {seq}: {pv:?} vs {rv:?}");
            }
        }
    }

    // Rust encoder (the gateway) ⇄ Python decoder.
    for (seq, p) in &decoded {
        let c = &corrected[seq];
        assert_eq!(p["sensor_id"], SENSOR);
        assert_eq!(p["timestamp_ns"].as_i64().unwrap(), c.header.timestamp_ns);
        assert_eq!(
            p["sample_rate_hz"].as_f64().unwrap(),
            c.header.sample_rate_hz
        );
        assert_eq!(p["batch_flags"].as_u64().unwrap(), u64::from(c.batch_flags));
        assert_eq!(
            p["calibration_version"].as_u64().unwrap(),
            c.info.calibration_version
        );
        assert_eq!(c.info.calibration_version, 1, "the stored record was used");
        assert_eq!(c.info.mode, Mode::Dynamic);
        assert_eq!(p["mode"], "dynamic");
        assert!(same_f32(
            p["coverage_factor"].as_f64().unwrap(),
            c.info.coverage_factor
        ));
        let ps = p["samples"].as_array().unwrap();
        assert_eq!(ps.len(), c.samples.len());
        for (i, (pv, cv)) in ps.iter().zip(&c.samples).enumerate() {
            let a = f64_list(&pv["accel_mps2"]);
            let u = f64_list(&pv["uncertainty_mps2"]);
            for j in 0..3 {
                assert!(
                    same_f32(a[j], cv.accel_mps2[j]) && same_f32(u[j], cv.uncertainty_mps2[j]),
                    "corrected seq {seq} sample {i}: python a={a:?} u={u:?}, rust {cv:?}"
                );
            }
            assert_eq!(pv["flags"].as_u64().unwrap(), u64::from(cv.flags));
            // Calibrated values, not raw outputs: gravity reads about 9.81 m/s² on z.
            assert!((cv.accel_mps2[2] - 9.81).abs() < 0.5, "{cv:?}");
            assert!(cv
                .uncertainty_mps2
                .iter()
                .all(|u| u.is_finite() && *u > 0.0));
        }
    }

    println!(
        "checked {} raw batch(es) Python encoded and {} corrected batch(es) Python decoded",
        raw.len(),
        decoded.len()
    );
    drop((raw_sub, corrected_sub));
    session.close().await.unwrap();
    stop.send(()).unwrap();
    tokio::time::timeout(util::TIMEOUT, gateway)
        .await
        .expect("gateway stops on shutdown")
        .unwrap()
        .unwrap();
}

/// Batches per sensor in a `follow --out` file: (sequence, payload hex), in file order.
fn followed(path: &std::path::Path) -> BTreeMap<String, Vec<(u64, String)>> {
    let mut out: BTreeMap<String, Vec<(u64, String)>> = BTreeMap::new();
    let text = std::fs::read_to_string(path).unwrap_or_default();
    for line in text.lines() {
        let Ok(v) = serde_json::from_str::<Value>(line) else {
            continue; // a line cut short by the kill, removed when the follower resumes
        };
        out.entry(v["sensor_id"].as_str().unwrap().to_owned())
            .or_default()
            .push((
                v["sequence"].as_u64().unwrap(),
                v["payload_hex"].as_str().unwrap().to_owned(),
            ));
    }
    out
}

/// The setting of the Python follower's tests: twenty calibrated sensors behind a gateway on
/// loopback, a node that publishes them a round at a time, and `follow --out` processes.
struct FollowSite {
    py: String,
    endpoint: String,
    building: String,
    ids: Vec<String>,
    node: zenoh::Session,
    publishers: Vec<zenoh::pubsub::Publisher<'static>>,
    /// The first round's time; set by [`FollowSite::begin`].
    t0_ns: i64,
    stop: tokio::sync::oneshot::Sender<()>,
    gateway: tokio::task::JoinHandle<Result<(), triax_gateway::GatewayError>>,
}

impl FollowSite {
    async fn start(dir: &std::path::Path, building: &str, prefix: &str) -> FollowSite {
        let store_path = dir.join("store");
        let ids: Vec<String> = (0..20).map(|i| format!("{prefix}-{i:02}")).collect();
        {
            let store = Store::open(&store_path).unwrap();
            for id in &ids {
                store
                    .put(&sample::record(id, 1))
                    .unwrap()
                    .expect("accepted");
            }
        }
        let port = free_port();
        let endpoint = format!("tcp/127.0.0.1:{port}");
        let config =
            triax_gateway::Config::for_tests(building, &store_path, vec![endpoint.clone()]);
        let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
        let gateway = tokio::spawn(triax_gateway::run(config, async {
            let _ = stopped.await;
        }));
        wait_for_listener(port).await;
        let node = util::client(&endpoint).await;
        let b = BuildingId::new(building).unwrap();
        let mut publishers = Vec::new();
        for id in &ids {
            let key = Key::Raw(b.clone(), SensorId::new(id.as_str()).unwrap()).to_string();
            publishers.push(node.declare_publisher(key).await.unwrap());
        }
        FollowSite {
            py: python_interpreter(),
            endpoint,
            building: building.to_owned(),
            ids,
            node,
            publishers,
            t0_ns: 0,
            stop,
            gateway,
        }
    }

    /// A `follow --out out` process.
    fn follow(&self, out: &std::path::Path) -> Reaped {
        let child = Command::new(&self.py)
            .arg(script())
            .args([
                "follow",
                "--building",
                &self.building,
                "--connect",
                &self.endpoint,
            ])
            .args(["--no-multicast", "--out"])
            .arg(out)
            .stdout(Stdio::null())
            .stderr(Stdio::inherit())
            .spawn()
            .unwrap_or_else(|e| panic!("cannot start {}: {e}", self.py));
        Reaped(child)
    }

    /// Stamps the rounds by the wall clock from a second after now: called once the followers
    /// have started, since a follower follows a sensor it has never met from its own start on
    /// (PROTOCOL.md §5.2), reading from the history whatever came before it subscribed, however
    /// slowly it starts on a busy machine.
    fn begin(&mut self) {
        let now_ns = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .unwrap()
            .as_nanos();
        self.t0_ns = i64::try_from(now_ns).unwrap() + 1_000_000_000;
    }

    /// Round `seq`: one 100 ms batch of every sensor.
    async fn put_round(&self, seq: u64) {
        for ((_, payload), p) in self.round(seq).into_iter().zip(&self.publishers) {
            p.put(payload).await.unwrap();
        }
    }

    /// The publisher of sensor `id`.
    fn publisher(&self, id: &str) -> &zenoh::pubsub::Publisher<'static> {
        let i = self.ids.iter().position(|s| s == id).unwrap();
        &self.publishers[i]
    }

    /// Round `seq`'s raw batches, by sensor.
    fn round(&self, seq: u64) -> Vec<(String, Vec<u8>)> {
        let mut out = Vec::new();
        for id in &self.ids {
            let batch = RawBatch {
                header: triax_protocol::batch::BatchHeader {
                    sensor_id: SensorId::new(id.as_str()).unwrap(),
                    sequence: seq,
                    timestamp_ns: self.t0_ns + seq as i64 * 100_000_000,
                    sample_rate_hz: 100.0,
                },
                temperature_c: None,
                samples: (0..10)
                    .map(|i| [0.01 * i as f32, seq as f32 * 1e-3, 0.981])
                    .collect(),
            };
            out.push((id.clone(), batch.encode()));
        }
        out
    }

    /// Whether a follower's file holds a batch of every sensor.
    fn has_all(&self, f: &std::path::Path) -> bool {
        let written = followed(f);
        self.ids
            .iter()
            .all(|id| written.get(id).is_some_and(|v| !v.is_empty()))
    }

    /// The steady follower's file holds every round of every sensor once, in order, and
    /// `other`'s holds the same batches, byte for byte.
    fn assert_followed_alike(
        &self,
        steady: &std::path::Path,
        other: &std::path::Path,
        rounds: u64,
        what: &str,
    ) {
        let (a, c) = (followed(steady), followed(other));
        assert_eq!(a.len(), self.ids.len());
        for id in &self.ids {
            let seqs = |f: &BTreeMap<String, Vec<(u64, String)>>| -> Vec<u64> {
                f.get(id)
                    .map_or(vec![], |v| v.iter().map(|(s, _)| *s).collect())
            };
            assert_eq!(
                seqs(&a),
                (0..rounds).collect::<Vec<_>>(),
                "{id}: the steady follower"
            );
            assert_eq!(seqs(&a), seqs(&c), "{id}: the {what} follower, once each");
            assert!(
                a.get(id) == c.get(id),
                "{id}: the {what} follower, same bytes"
            );
        }
    }

    async fn close(self) {
        self.node.close().await.unwrap();
        self.stop.send(()).unwrap();
        tokio::time::timeout(util::TIMEOUT, self.gateway)
            .await
            .expect("gateway stops on shutdown")
            .unwrap()
            .unwrap();
    }
}

#[tokio::test(flavor = "multi_thread")]
async fn a_killed_python_follower_resumes_and_loses_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let mut site = FollowSite::start(dir.path(), "pfb", "pf").await;
    let (steady_file, away_file) = (
        dir.path().join("steady.jsonl"),
        dir.path().join("away.jsonl"),
    );
    let steady = site.follow(&steady_file);
    let mut away = site.follow(&away_file);
    site.begin();
    // At least 22 s of rounds, and on until the killed follower has been back for a while.
    let min_rounds = 220u64;
    let started = tokio::time::Instant::now();
    let mut killed_at = None;
    let mut restarted = false;
    let mut seq = 0u64;
    while seq < min_rounds || !restarted {
        assert!(
            seq < 10 * min_rounds,
            "the away follower never wrote every sensor"
        );
        site.put_round(seq).await;
        let t = started.elapsed();
        // Killed once it has written every sensor at least once, so that it has somewhere to
        // resume from for each.
        if killed_at.is_none() && t > Duration::from_secs(4) && site.has_all(&away_file) {
            // SIGKILL: no chance to finish a line or save anything.
            away.0.kill().unwrap();
            away.0.wait().unwrap();
            killed_at = Some(t);
        }
        if !restarted && killed_at.is_some_and(|k| t > k + Duration::from_secs(10)) {
            away = site.follow(&away_file);
            restarted = true;
        }
        tokio::time::sleep_until(started + Duration::from_millis(100 * (seq + 1))).await;
        seq += 1;
    }
    let rounds = seq;
    let total = site.ids.len() * rounds as usize;
    let count = |f: &std::path::Path| followed(f).values().map(Vec::len).sum::<usize>();
    let deadline = tokio::time::Instant::now() + Duration::from_secs(60);
    while (count(&steady_file) < total || count(&away_file) < total)
        && tokio::time::Instant::now() < deadline
    {
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
    let what = format!("resumed (killed at {killed_at:?})");
    site.assert_followed_alike(&steady_file, &away_file, rounds, &what);
    drop((steady, away));
    site.close().await;
}

/// Holes a link cut left, filled by the gateway from the node's buffer after later batches
/// (PROTOCOL.md §5.2 step 6): the Python follower writes every batch once, the late ones too.
#[tokio::test(flavor = "multi_thread")]
async fn a_python_follower_takes_late_batches_once() {
    let dir = tempfile::tempdir().unwrap();
    let mut site = FollowSite::start(dir.path(), "pfl", "pl").await;
    let buffer = util::Buffer::default();
    let _queryable = buffer.serve(&site.node, "pfl").await;
    buffer.pause();
    let file = dir.path().join("follow.jsonl");
    let follower = site.follow(&file);
    site.begin();
    const ROUNDS: u64 = 100;
    let cut = 30..60u64;
    let started = tokio::time::Instant::now();
    for seq in 0..ROUNDS {
        for (id, payload) in site.round(seq) {
            buffer.keep(&id, seq, &payload);
            if !cut.contains(&seq) {
                site.publisher(&id).put(payload).await.unwrap();
            }
        }
        tokio::time::sleep_until(started + Duration::from_millis(100 * (seq + 1))).await;
    }
    // The follower has met the hole (written a batch after it) before the gateway can fill
    // it: the late batches reach it live, or through the heartbeat's late_timestamp_ns.
    util::wait_until("the follower to write past the hole", || {
        let written = followed(&file);
        site.ids.iter().all(|id| {
            written
                .get(id)
                .is_some_and(|v| v.iter().any(|(s, _)| *s >= cut.end))
        })
    })
    .await;
    buffer.answer();
    let total = site.ids.len() * ROUNDS as usize;
    util::wait_until("the follower to write every batch", || {
        followed(&file).values().map(Vec::len).sum::<usize>() >= total
    })
    .await;
    let written = followed(&file);
    for id in &site.ids {
        let mut seqs: Vec<u64> = written[id].iter().map(|(s, _)| *s).collect();
        // The hole's batches are the gateway's late ones (whichever way they reached the
        // follower: live, or from the history when it read past them).
        for (seq, hex) in &written[id] {
            let bytes: Vec<u8> = (0..hex.len())
                .step_by(2)
                .map(|i| u8::from_str_radix(&hex[i..i + 2], 16).unwrap())
                .collect();
            let batch = triax_protocol::batch::CorrectedBatch::decode(&bytes).unwrap();
            let late = batch.batch_flags & triax_protocol::batch::flags::LATE != 0;
            assert_eq!(
                late,
                cut.contains(seq),
                "{id} #{seq}: flagged late exactly in the hole"
            );
        }
        seqs.sort_unstable();
        assert_eq!(
            seqs,
            (0..ROUNDS).collect::<Vec<_>>(),
            "{id}: every batch once"
        );
    }
    drop(follower);
    site.close().await;
}

/// Sends `signal` (`STOP`, `CONT`) to a child.
fn signal(child: &Child, signal: &str) {
    let sent = Command::new("kill")
        .args([format!("-{signal}"), child.id().to_string()])
        .status()
        .unwrap();
    assert!(sent.success(), "kill -{signal} failed");
}

#[tokio::test(flavor = "multi_thread")]
async fn a_stalled_python_follower_catches_up_and_loses_nothing() {
    // A follower that stops reading for a while (a busy machine, a slow disk under --out) has
    // a backlog of live batches waiting and gaps to read from the history. Its subscriptions
    // must not hold Zenoh's receive thread while it reads: the history's replies come on the
    // same link, behind that backlog.
    let dir = tempfile::tempdir().unwrap();
    let mut site = FollowSite::start(dir.path(), "psb", "ps").await;
    let (steady_file, stalled_file) = (
        dir.path().join("steady.jsonl"),
        dir.path().join("stalled.jsonl"),
    );
    let mut steady = site.follow(&steady_file);
    let mut stalled = site.follow(&stalled_file);
    site.begin();
    // Stopped once it has written every sensor; continued after 40 rounds (800 batches, more
    // than a subscription's default queue of 256) and followed for 40 more.
    let (stalled_for, after) = (40u64, 40u64);
    let started = tokio::time::Instant::now();
    let mut stopped_at = None;
    let mut seq = 0u64;
    while stopped_at.is_none_or(|s| seq < s + stalled_for + after) {
        assert!(seq < 600, "the stalled follower never wrote every sensor");
        site.put_round(seq).await;
        if stopped_at.is_none() && site.has_all(&stalled_file) {
            signal(&stalled.0, "STOP");
            stopped_at = Some(seq);
        }
        if stopped_at == Some(seq.saturating_sub(stalled_for)) {
            signal(&stalled.0, "CONT");
        }
        tokio::time::sleep_until(started + Duration::from_millis(100 * (seq + 1))).await;
        seq += 1;
    }
    let rounds = seq;
    let complete = |f: &std::path::Path| {
        let written = followed(f);
        site.ids
            .iter()
            .all(|id| written.get(id).map_or(0, Vec::len) >= rounds as usize)
    };
    let deadline = tokio::time::Instant::now() + util::TIMEOUT;
    while !(complete(&steady_file) && complete(&stalled_file)) {
        for (name, child) in [("steady", &mut steady), ("stalled", &mut stalled)] {
            if let Some(status) = child.0.try_wait().unwrap() {
                panic!("the {name} follower exited: {status}");
            }
        }
        assert!(
            tokio::time::Instant::now() < deadline,
            "the stalled follower did not catch up (stopped at round {stopped_at:?} of {rounds})"
        );
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
    site.assert_followed_alike(&steady_file, &stalled_file, rounds, "stalled");
    drop((steady, stalled));
    site.close().await;
}

/// A gateway for `building` whose one sensor (record version 1) streamed `n_batches` batches of
/// 50 samples at 100 Hz, batch `skipped` left out (a gap after it) and one non-finite sample at
/// (batch, sample) `nan_at`; returns the gateway, a client session and the sensor's history as
/// the gateway answers it.
async fn streamed_history(
    dir: &std::path::Path,
    building: &str,
    sensor: &str,
    n_batches: u64,
    skipped: u64,
    nan_at: (u64, u64),
) -> (util::Running, zenoh::Session, Vec<CorrectedBatch>) {
    let store = dir.join("store");
    util::seed_store(&store, &[sample::record(sensor, 1)]);
    let gw = util::start(util::config(building, &store)).await;
    let session = util::client(&gw.endpoint).await;
    let sub = session
        .declare_subscriber(util::key_corrected(building, sensor))
        .with(zenoh::handlers::FifoChannel::new(1000))
        .await
        .unwrap();
    let publisher = util::blocking_publisher(&session, util::key_raw(building, sensor)).await;
    for seq in (0..n_batches).filter(|&s| s != skipped) {
        let samples = (0..50)
            .map(|i| {
                let t = (seq * 50 + i) as f32 / 100.0;
                if (seq, i) == nan_at {
                    [f32::NAN, 0.0, 0.98]
                } else {
                    [
                        0.03 * (9.0 * t).sin(),
                        -0.01 * t,
                        0.98 + 0.001 * (3.0 * t).cos(),
                    ]
                }
            })
            .collect();
        publisher
            .put(util::raw(sensor, seq, samples))
            .await
            .unwrap();
    }
    util::collect(&sub, n_batches as usize - 1).await;
    let last = (0..n_batches).filter(|&s| s != skipped).max().unwrap();
    util::wait_history_holds(&session, building, sensor, last).await;
    let request = triax_client::HistoryRequest::sensor(
        &BuildingId::new(building).unwrap(),
        &SensorId::new(sensor).unwrap(),
    );
    let mut batches = Vec::new();
    triax_client::history::fetch(&session, &request, util::TIMEOUT, &mut |r| {
        batches.push(r.batch)
    })
    .await
    .expect("history answered");
    (gw, session, batches)
}

/// Reads the Parquet file with pandas and prints, as JSON, every column (floats as the bits of
/// their f32, so NaN and exact values survive) and the file's `triax.units` metadata.
const READ_PARQUET: &str = r#"
import json, sys
import numpy as np
import pandas as pd
import pyarrow.parquet as pq
path = sys.argv[1]
df = pd.read_parquet(path, engine="pyarrow")
meta = pq.read_metadata(path).metadata
out = {
    "time_dtype": str(df["time"].dtype),
    "time_ns": df["time"].astype("int64").tolist(),
    "sensor_id": df["sensor_id"].tolist(),
    "sequence": df["sequence"].tolist(),
    "flags": df["flags"].astype("int64").tolist(),
    "calibration_version": df["calibration_version"].tolist(),
    "mode": df["mode"].tolist(),
    "units": meta[b"triax.units"].decode(),
}
for c in ["ax_mps2", "ay_mps2", "az_mps2", "ux_mps2", "uy_mps2", "uz_mps2", "coverage_factor"]:
    out[c] = np.asarray(df[c], dtype=np.float32).view(np.uint32).tolist()
print(json.dumps(out))
"#;

#[tokio::test(flavor = "multi_thread")]
async fn a_parquet_export_reads_back_identically_in_pandas() {
    let py = python_interpreter();
    let dir = tempfile::tempdir().unwrap();
    let n_batches = 40u64;
    // Sequence 20 skipped: a gap flag; one non-finite sample.
    let (gw, session, batches) =
        streamed_history(dir.path(), "pq", "pq-1", n_batches, 20, (7, 3)).await;
    let path = dir.path().join("pq-1.parquet");
    let mut writer =
        triax_client::parquet::ParquetWriter::new(std::fs::File::create(&path).unwrap()).unwrap();
    for b in &batches {
        writer.push(b).unwrap();
    }
    let rows = writer.finish().unwrap();
    assert_eq!(batches.len(), n_batches as usize - 1);
    assert_eq!(rows, 50 * batches.len() as u64);

    let out = run_pyarrow_script(&py, READ_PARQUET, &[path.as_os_str()]);
    assert!(
        out.status.success(),
        "pandas could not read the export: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    let v: Value = serde_json::from_slice(&out.stdout).expect("python prints JSON");
    assert_eq!(v["time_dtype"], "datetime64[ns, UTC]");
    assert!(v["units"].as_str().unwrap().contains("m/s²"));
    let col = |name: &str| v[name].as_array().unwrap().clone();
    let mut row = 0;
    let (mut gap_rows, mut nan_rows) = (0, 0);
    for b in &batches {
        for (i, s) in b.samples.iter().enumerate() {
            let t = b.header.timestamp_ns + (i as f64 * 1e9 / b.header.sample_rate_hz) as i64;
            assert_eq!(col("time_ns")[row].as_i64(), Some(t), "row {row}");
            assert_eq!(col("sensor_id")[row], "pq-1");
            assert_eq!(col("sequence")[row].as_u64(), Some(b.header.sequence));
            // The sample's own flags; the batch-only ones on the batch's first row.
            let batch_only = if i == 0 { b.batch_flags & 0x90 } else { 0 };
            let flags = u64::from(s.flags | batch_only);
            assert_eq!(col("flags")[row].as_u64(), Some(flags), "row {row}");
            gap_rows += usize::from(flags & 0x10 != 0);
            nan_rows += usize::from(s.accel_mps2[0].is_nan());
            assert_eq!(col("calibration_version")[row].as_u64(), Some(1));
            assert_eq!(col("mode")[row], "dynamic");
            for (j, name) in ["ax_mps2", "ay_mps2", "az_mps2"].iter().enumerate() {
                assert_eq!(
                    col(name)[row].as_u64(),
                    Some(u64::from(s.accel_mps2[j].to_bits()))
                );
            }
            for (j, name) in ["ux_mps2", "uy_mps2", "uz_mps2"].iter().enumerate() {
                assert_eq!(
                    col(name)[row].as_u64(),
                    Some(u64::from(s.uncertainty_mps2[j].to_bits()))
                );
            }
            assert_eq!(
                col("coverage_factor")[row].as_u64(),
                Some(u64::from(b.info.coverage_factor.to_bits()))
            );
            row += 1;
        }
    }
    assert_eq!(row, col("time_ns").len());
    assert_eq!(gap_rows, 1, "the first row of the batch after the hole");
    assert_eq!(nan_rows, 1);
    let flagged_non_finite = col("flags")
        .iter()
        .filter(|f| f.as_u64().unwrap() & 0x20 != 0)
        .count();
    assert_eq!(flagged_non_finite, 1, "only the non-finite sample says so");
    session.close().await.unwrap();
    gw.stop().await;
}

/// The Python client's `alerts`, written from PROTOCOL.md §3.6, against alerts signed by the
/// Rust side: a verified one, and the three kinds it must never take for a verdict (unsigned,
/// altered, signed by a key it does not trust).
#[tokio::test(flavor = "multi_thread")]
async fn python_verifies_alert_signatures() {
    use triax_protocol::signing::{sign_alert, to_hex, LabSigningKey};
    let py = python_interpreter();
    let port = free_port();
    let endpoint = format!("tcp/127.0.0.1:{port}");
    let session = zenoh::open(
        triax_net::ZenohSettings::loopback(
            triax_net::ZenohMode::Peer,
            vec![endpoint.clone()],
            vec![],
        )
        .to_config()
        .unwrap(),
    )
    .await
    .unwrap();
    let service = LabSigningKey::from_bytes(&[3; 32]);
    let stranger = LabSigningKey::from_bytes(&[4; 32]);
    let (_child, lines) = python(
        &py,
        &[
            "alerts",
            "--building",
            "pal",
            "--connect",
            &endpoint,
            "--no-multicast",
            "--json",
            "--count",
            "4",
            "--trusted-alert-key",
            &to_hex(service.verifying_key().as_bytes()),
        ]
        .map(String::from),
    );
    let publisher = session
        .declare_publisher("triax/pal/alert/acc-04")
        .await
        .unwrap();
    util::wait_matching(&publisher).await;
    let alert = triax_protocol::messages::sample::alert("pal", "acc-04");
    let signed = sign_alert(&alert, &service);
    let mut altered = signed.clone();
    altered.alert_json = altered.alert_json.replace("\"value\":2.5", "\"value\":9.5");
    for payload in [
        triax_protocol::to_json(&signed),
        triax_protocol::to_json(&alert),
        triax_protocol::to_json(&altered),
        triax_protocol::to_json(&sign_alert(&alert, &stranger)),
    ] {
        publisher.put(payload).await.unwrap();
    }
    let trusts: Vec<String> = (0..4)
        .map(|_| {
            let v = next_line(&lines, "an alert");
            assert_eq!(v["alert"]["sensor_id"], "acc-04", "{v}");
            v["trust"].as_str().unwrap().to_owned()
        })
        .collect();
    assert_eq!(
        trusts,
        ["verified", "unsigned", "bad_signature", "unknown_key"]
    );
    session.close().await.unwrap();
}
