//! Our segment log (`triax-history`) against fjall (an LSM-tree store) on the gateway's
//! workload: `S` sensors at 100 Hz sending 10-sample batches, synced to disk once per second of
//! data, then read back one sensor at a time, trimmed by retention, and killed mid-write.
//!
//! ```text
//! engines-bench [--sensors 1000] [--seconds 120] [--open-gib 0]
//! ```
//!
//! Prints one table; every figure is from this run, so the ratios hold on a noisy machine.

use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use fjall::{Database, KeyspaceCreateOptions, PersistMode};
use rand::{Rng, SeedableRng};
use triax_history::{Block, History, HistoryConfig, Kept, Query, Verdict};
use triax_protocol::SensorId;

const RATE_HZ: f64 = 100.0;
const BATCH: usize = 10;
const BATCH_NS: i64 = 100_000_000;
const T0_NS: i64 = 1_800_000_000_000_000_000;

struct Args {
    sensors: usize,
    seconds: u64,
    open_gib: u64,
}

fn args() -> Args {
    let mut a = Args {
        sensors: 1000,
        seconds: 120,
        open_gib: 0,
    };
    let mut it = std::env::args().skip(1);
    while let Some(flag) = it.next() {
        let mut value = || it.next().and_then(|v| v.parse().ok()).expect("a number");
        match flag.as_str() {
            "--sensors" => a.sensors = value() as usize,
            "--seconds" => a.seconds = value(),
            "--open-gib" => a.open_gib = value(),
            "--child-own" | "--child-fjall" => {}
            _ => {
                eprintln!("usage: engines-bench [--sensors N] [--seconds S] [--open-gib G]");
                std::process::exit(2);
            }
        }
    }
    a
}

/// Outputs of a MEMS node: gravity on z, a 1.3 Hz sway, noise, in volts at 0.1 V per m/s².
fn samples(rng: &mut rand::rngs::StdRng, sensor: usize, seq: u64) -> Vec<u8> {
    let mut out = Vec::with_capacity(BATCH * 12);
    for i in 0..BATCH {
        let t = (seq as usize * BATCH + i) as f64 / RATE_HZ;
        let sway = 0.02 * (2.0 * std::f64::consts::PI * 1.3 * t + sensor as f64).sin();
        for v in [sway, 0.001, 0.981] {
            let noisy = (v + 1e-4 * rng.gen::<f64>()) as f32;
            out.extend_from_slice(&noisy.to_le_bytes());
        }
    }
    out
}

fn id(i: usize) -> SensorId {
    SensorId::new(format!("acc-{i:05}")).expect("valid id")
}

fn dir_bytes(p: &Path) -> u64 {
    let mut total = 0;
    for e in std::fs::read_dir(p).expect("dir") {
        let e = e.expect("entry");
        let m = e.metadata().expect("metadata");
        total += if m.is_dir() { dir_bytes(&e.path()) } else { m.len() };
    }
    total
}

/// What one engine did.
#[derive(Default)]
struct Figures {
    write_batches_per_s: f64,
    bytes_per_sample: f64,
    bytes_per_sample_compacted: Option<f64>,
    read_samples_per_s: f64,
    retention_s: f64,
    bytes_after_retention: u64,
}

fn fjall_key(sensor: usize, seq: u64) -> [u8; 12] {
    let mut k = [0u8; 12];
    k[..4].copy_from_slice(&(sensor as u32).to_be_bytes());
    k[4..].copy_from_slice(&seq.to_be_bytes());
    k
}

fn fjall_value(seq: u64, samples: &[u8]) -> Vec<u8> {
    let mut v = Vec::with_capacity(25 + samples.len());
    v.extend_from_slice(&(T0_NS + seq as i64 * BATCH_NS).to_le_bytes());
    v.extend_from_slice(&RATE_HZ.to_le_bytes());
    v.extend_from_slice(&1u64.to_le_bytes());
    v.push(0);
    v.extend_from_slice(samples);
    v
}

fn run_own(a: &Args, dir: &Path) -> Figures {
    let mut f = Figures::default();
    let mut rng = rand::rngs::StdRng::seed_from_u64(1);
    let ids: Vec<SensorId> = (0..a.sensors).map(id).collect();
    let mut config = HistoryConfig::new(dir);
    config.max_bytes = u64::MAX;
    let opened = History::open(config).expect("open");
    let (history, mut writer) = (opened.history, opened.writer);
    let data: Vec<Vec<u8>> = (0..a.sensors).map(|s| samples(&mut rng, s, 0)).collect();
    let start = Instant::now();
    let batches_per_s = 10;
    for second in 0..a.seconds {
        for b in 0..batches_per_s {
            let seq = second * batches_per_s + b;
            for (s, sid) in ids.iter().enumerate() {
                let kept = Kept {
                    arrival: 0,
                    sequence: seq,
                    timestamp_ns: T0_NS + seq as i64 * BATCH_NS,
                    sample_rate_hz: RATE_HZ,
                    temperature_c: None,
                    calibration_version: 1,
                    verdict: Verdict::InOrder,
                    samples: &data[s][..],
                };
                let ck = (seq % 600 == 0).then_some(&[0u8; 400][..]);
                writer.append(sid, kept, ck);
            }
        }
        writer.flush().expect("flush");
    }
    let elapsed = start.elapsed().as_secs_f64();
    let n_batches = a.seconds * 10 * a.sensors as u64;
    f.write_batches_per_s = n_batches as f64 / elapsed;
    f.bytes_per_sample = dir_bytes(dir) as f64 / (n_batches * BATCH as u64) as f64;
    // Range reads: one sensor's whole stretch, decoded to f32, for 20 sensors.
    let start = Instant::now();
    let mut n_samples = 0u64;
    let mut sum = 0f32;
    for s in (0..a.sensors).step_by((a.sensors / 20).max(1)) {
        let mut scan = history.scan(&Query::all(id(s))).expect("scan");
        while let Some(b) = scan.next_block() {
            let b = b.expect("block");
            let block = Block::decode(&b.bytes).expect("decode");
            for k in &block.kept {
                for c in k.samples.chunks_exact(4) {
                    sum += f32::from_le_bytes([c[0], c[1], c[2], c[3]]);
                }
                n_samples += k.n_samples() as u64;
            }
        }
    }
    f.read_samples_per_s = n_samples as f64 / start.elapsed().as_secs_f64();
    std::hint::black_box(sum);
    // Retention to half the size.
    drop(writer);
    drop(history);
    let half = dir_bytes(dir) / 2;
    let mut config = HistoryConfig::new(dir);
    config.max_bytes = half;
    let start = Instant::now();
    let mut opened = History::open(config).expect("reopen");
    opened.writer.flush().expect("flush applies retention");
    f.retention_s = start.elapsed().as_secs_f64();
    f.bytes_after_retention = dir_bytes(dir);
    f
}

fn run_fjall(a: &Args, dir: &Path) -> Figures {
    let mut f = Figures::default();
    let mut rng = rand::rngs::StdRng::seed_from_u64(1);
    let db = Database::builder(dir).open().expect("open fjall");
    let ks = db
        .keyspace("history", KeyspaceCreateOptions::default)
        .expect("keyspace");
    let data: Vec<Vec<u8>> = (0..a.sensors).map(|s| samples(&mut rng, s, 0)).collect();
    let start = Instant::now();
    for second in 0..a.seconds {
        let mut batch = db.batch();
        for b in 0..10 {
            let seq = second * 10 + b;
            for (s, d) in data.iter().enumerate() {
                batch.insert(&ks, fjall_key(s, seq), fjall_value(seq, d));
            }
        }
        batch.commit().expect("commit");
        db.persist(PersistMode::SyncData).expect("persist");
    }
    let elapsed = start.elapsed().as_secs_f64();
    let n_batches = a.seconds * 10 * a.sensors as u64;
    f.write_batches_per_s = n_batches as f64 / elapsed;
    let samples_total = (n_batches * BATCH as u64) as f64;
    f.bytes_per_sample = dir_bytes(dir) as f64 / samples_total;
    let start = Instant::now();
    let mut n_samples = 0u64;
    let mut sum = 0f32;
    for s in (0..a.sensors).step_by((a.sensors / 20).max(1)) {
        for kv in ks.range(fjall_key(s, 0)..fjall_key(s + 1, 0)) {
            let v = kv.value().expect("value");
            for c in v[25..].chunks_exact(4) {
                sum += f32::from_le_bytes([c[0], c[1], c[2], c[3]]);
            }
            n_samples += BATCH as u64;
        }
    }
    f.read_samples_per_s = n_samples as f64 / start.elapsed().as_secs_f64();
    std::hint::black_box(sum);
    ks.major_compact().expect("compact");
    f.bytes_per_sample_compacted = Some(dir_bytes(dir) as f64 / samples_total);
    // Retention: the oldest half of every sensor's keys, removed, and compacted away.
    let start = Instant::now();
    let mut batch = db.batch();
    for s in 0..a.sensors {
        for seq in 0..a.seconds * 10 / 2 {
            batch.remove(&ks, fjall_key(s, seq));
        }
    }
    batch.commit().expect("commit");
    db.persist(PersistMode::SyncData).expect("persist");
    ks.major_compact().expect("compact");
    f.retention_s = start.elapsed().as_secs_f64();
    f.bytes_after_retention = dir_bytes(dir);
    f
}

/// The child of the kill test: writes forever, syncing once a second of data, and prints the
/// number of batches made durable after each sync.
fn child(kind: &str, dir: &Path, sensors: usize) {
    let mut rng = rand::rngs::StdRng::seed_from_u64(2);
    let data: Vec<Vec<u8>> = (0..sensors).map(|s| samples(&mut rng, s, 0)).collect();
    let ids: Vec<SensorId> = (0..sensors).map(id).collect();
    let mut durable = 0u64;
    if kind == "own" {
        let opened = History::open(HistoryConfig::new(dir)).expect("open");
        let mut writer = opened.writer;
        for seq in 0.. {
            for (s, sid) in ids.iter().enumerate() {
                let kept = Kept {
                    arrival: 0,
                    sequence: seq,
                    timestamp_ns: T0_NS + seq as i64 * BATCH_NS,
                    sample_rate_hz: RATE_HZ,
                    temperature_c: None,
                    calibration_version: 1,
                    verdict: Verdict::InOrder,
                    samples: &data[s][..],
                };
                writer.append(sid, kept, None);
            }
            if seq % 10 == 9 {
                writer.flush().expect("flush");
                durable = (seq + 1) * sensors as u64;
                println!("{durable}");
            }
        }
    } else {
        let db = Database::builder(dir).open().expect("open");
        let ks = db.keyspace("history", KeyspaceCreateOptions::default).expect("ks");
        for seq in 0.. {
            for (s, d) in data.iter().enumerate() {
                ks.insert(fjall_key(s, seq), fjall_value(seq, d)).expect("insert");
            }
            if seq % 10 == 9 {
                db.persist(PersistMode::SyncData).expect("persist");
                durable = (seq + 1) * sensors as u64;
                println!("{durable}");
            }
        }
    }
    let _ = durable;
}

/// Starts a writer child, kills it after `after`, reopens: (open time, batches found, batches
/// the child had reported durable).
fn kill_and_reopen(kind: &str, dir: &Path, sensors: usize, after: Duration) -> (f64, u64, u64) {
    let mut c = Command::new(std::env::current_exe().expect("exe"))
        .args([format!("--child-{kind}"), dir.display().to_string(), sensors.to_string()])
        .stdout(Stdio::piped())
        .spawn()
        .expect("child");
    std::thread::sleep(after);
    c.kill().expect("kill");
    let out = c.wait_with_output().expect("wait");
    let reported: u64 = String::from_utf8_lossy(&out.stdout)
        .lines()
        .filter_map(|l| l.trim().parse().ok())
        .last()
        .unwrap_or(0);
    let start = Instant::now();
    if kind == "own" {
        let opened = History::open(HistoryConfig::new(dir)).expect("reopen");
        let ms = start.elapsed().as_secs_f64() * 1e3;
        let mut n = 0u64;
        for s in 0..sensors {
            let mut scan = opened.history.scan(&Query::all(id(s))).expect("scan");
            while let Some(b) = scan.next_block() {
                n += Block::decode(&b.expect("block").bytes).expect("decode").kept.len() as u64;
            }
        }
        (ms, n, reported)
    } else {
        let db = Database::builder(dir).open().expect("reopen");
        let ks = db.keyspace("history", KeyspaceCreateOptions::default).expect("ks");
        let ms = start.elapsed().as_secs_f64() * 1e3;
        (ms, ks.iter().count() as u64, reported)
    }
}

/// A child writes about `gib` GiB of history in 100-sample batches and is killed: the time to
/// open what it left.
fn open_big(gib: u64) -> (f64, u64) {
    let dir = tempfile::tempdir().expect("tempdir");
    let mut c = Command::new(std::env::current_exe().expect("exe"))
        .args(["--child-big".into(), dir.path().display().to_string(), gib.to_string()])
        .stdout(Stdio::piped())
        .spawn()
        .expect("child");
    let mut line = String::new();
    let stdout = c.stdout.as_mut().expect("piped");
    std::io::BufRead::read_line(&mut std::io::BufReader::new(stdout), &mut line).expect("read");
    c.kill().expect("kill");
    c.wait().expect("wait");
    let bytes = dir_bytes(dir.path());
    let start = Instant::now();
    let opened = History::open(HistoryConfig::new(dir.path())).expect("open");
    let ms = start.elapsed().as_secs_f64() * 1e3;
    drop(opened);
    (ms, bytes)
}

/// The child of [`open_big`]: writes until `gib` GiB are on disk, says so, and waits.
fn child_big(dir: &Path, gib: u64) {
    let sensors = 100;
    let mut rng = rand::rngs::StdRng::seed_from_u64(3);
    let big: Vec<Vec<u8>> = (0..sensors)
        .map(|s| (0..10).flat_map(|k| samples(&mut rng, s, k)).collect())
        .collect();
    let opened = History::open(HistoryConfig::new(dir)).expect("open");
    let mut writer = opened.writer;
    let ids: Vec<SensorId> = (0..sensors).map(id).collect();
    let mut seq = 0u64;
    while dir_bytes(dir) < gib << 30 {
        for _ in 0..100 {
            for (s, sid) in ids.iter().enumerate() {
                let kept = Kept {
                    arrival: 0,
                    sequence: seq,
                    timestamp_ns: T0_NS + seq as i64 * 1_000_000_000,
                    sample_rate_hz: RATE_HZ,
                    temperature_c: None,
                    calibration_version: 1,
                    verdict: Verdict::InOrder,
                    samples: &big[s][..],
                };
                writer.append(sid, kept, (seq % 60 == 0).then_some(&[0u8; 400][..]));
            }
            seq += 1;
        }
        writer.flush().expect("flush");
    }
    // Unflushed batches, as a gateway has when it is killed.
    for sid in &ids {
        let kept = Kept {
            arrival: 0,
            sequence: seq,
            timestamp_ns: T0_NS + seq as i64 * 1_000_000_000,
            sample_rate_hz: RATE_HZ,
            temperature_c: None,
            calibration_version: 1,
            verdict: Verdict::InOrder,
            samples: &big[0][..],
        };
        writer.append(sid, kept, None);
    }
    println!("written");
    std::thread::sleep(Duration::from_secs(3600));
}

fn main() {
    let mut raw = std::env::args().skip(1);
    if let Some(flag) = raw.next() {
        if flag == "--child-big" {
            let dir = raw.next().expect("dir");
            let gib = raw.next().and_then(|s| s.parse().ok()).expect("gib");
            child_big(Path::new(&dir), gib);
            return;
        }
        if let Some(kind) = flag.strip_prefix("--child-") {
            let dir = raw.next().expect("dir");
            let sensors = raw.next().and_then(|s| s.parse().ok()).expect("sensors");
            child(kind, Path::new(&dir), sensors);
            return;
        }
    }
    let a = args();
    println!(
        "workload: {} sensors, 100 Hz, 10-sample batches, {} s of data ({} batches), synced once per second of data",
        a.sensors,
        a.seconds,
        a.seconds * 10 * a.sensors as u64
    );
    let d1 = tempfile::tempdir().expect("tempdir");
    let own = run_own(&a, d1.path());
    let d2 = tempfile::tempdir().expect("tempdir");
    let fj = run_fjall(&a, d2.path());
    for (name, kind, f) in [("segment log", "own", &own), ("fjall 3.1", "fjall", &fj)] {
        let kd = tempfile::tempdir().expect("tempdir");
        let (ms, found, reported) = kill_and_reopen(kind, kd.path(), a.sensors, Duration::from_millis(3500));
        let line = format!(
            "| {name} | {:.0} | {:.2} | {} | {:.1} M | {:.2} s → {:.1} MiB | {:.0} ms, {found} batches kept of {reported} reported durable |",
            f.write_batches_per_s,
            f.bytes_per_sample,
            f.bytes_per_sample_compacted.map_or("–".into(), |b| format!("{b:.2}")),
            f.read_samples_per_s / 1e6,
            f.retention_s,
            f.bytes_after_retention as f64 / (1 << 20) as f64,
            ms
        );
        if name == "segment log" {
            println!("| engine | write, batches/s | bytes/sample | after compaction | range read, samples/s | retention to half | reopen after kill -9 |");
            println!("|---|---|---|---|---|---|---|");
        }
        println!("{line}");
    }
    println!(
        "gateway's full rate at this load: {} batches/s; write headroom: segment log {:.0}×, fjall {:.0}×",
        a.sensors * 10,
        own.write_batches_per_s / (a.sensors * 10) as f64,
        fj.write_batches_per_s / (a.sensors * 10) as f64
    );
    if a.open_gib > 0 {
        let (ms, bytes) = open_big(a.open_gib);
        println!(
            "open after a kill, segment log of {:.2} GiB: {ms:.0} ms",
            bytes as f64 / (1u64 << 30) as f64
        );
    }
}
