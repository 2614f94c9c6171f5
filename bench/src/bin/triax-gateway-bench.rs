//! `triax-gateway-bench`: end-to-end throughput, latency and memory of the gateway on loopback.
//!
//! Three Zenoh sessions on 127.0.0.1 TCP: a publisher playing `--sensors` sensor nodes with
//! 100-sample batches and a subscriber, both in this process, and the system under test in a
//! process of its own, as it is deployed (its own runtime and threads, the service binary's
//! allocator setting and logging). The system under test is, in turn:
//!
//! - `relay`: a plain relay, the baseline the gateway's target is set against: subscribes to
//!   the raw streams and re-publishes the same bytes on the corrected keys from the Zenoh
//!   callback, no decoding, no correction;
//! - `keyed-relay`: the same relay, but it declares each sensor's raw and corrected keys on
//!   first sight, as the gateway does, so that Zenoh keeps their routes. It shows what moving
//!   the bytes costs when Zenoh's routing is cached on both sides: the gateway against it is
//!   the cost of the correction and nothing else;
//! - `keyed-relay-corrected`: the keyed relay publishing, instead of the bytes it received, a
//!   corrected batch of the same samples (values copied, no uncertainty, no flags, no
//!   calibration): what the protocol's larger output (26 bytes a sample against 12) costs in
//!   Zenoh and the kernel, so that the gateway's own work shows apart from it;
//! - `gateway`: the Triax gateway from the library, with a calibration (full covariance) for
//!   every sensor in a temporary store, with the default overload policy (drop-oldest
//!   queues between Zenoh's receive thread and the correction workers);
//! - `gateway-backpressure`: the same with `overload = "backpressure"`: corrected on Zenoh's
//!   receive thread, no queue;
//! - `gateway-no-history`: the default gateway with its history off: what keeping every batch
//!   on disk costs, in the same run;
//! - `gateway-no-health`: the default gateway with its field health checks off: what they
//!   cost, in the same run;
//! - `gateway-unsigned`: the default gateway signing nothing and putting no seals
//!   (`[provenance] sign = false`): what provenance (PROTOCOL.md §6) costs, in the same run;
//! - `gateway-again`: the default gateway a second time, a process of its own like the first:
//!   an A/A control. Its ratios to `gateway` within a round are what two processes of the
//!   same binary differ by, the resolution of every other ratio of that round. With
//!   `--again-exe` it runs from another build of this bench instead: an A/B of two builds,
//!   paired round by round.
//!
//! For each:
//!
//! - unpaced: publish as fast as Zenoh accepts for `--seconds` and count the samples the
//!   subscriber receives per second. The relay pushes back (it publishes from the receive
//!   callback), so the publisher slows to its pace; the gateway sheds load (drop-oldest), so
//!   the publisher goes faster than the gateway carries and the CPU they share is partly spent
//!   on batches that are then dropped;
//! - zero loss: throughput as RFC 2544 defines it for a device, the highest offered load
//!   carried without loss, by bisection over paced trials of `--trial-seconds`. This is the
//!   figure the gateway/relay target is read against: it compares what each sustains, not how
//!   each behaves past its limit;
//! - paced (gateway only): the relay's unpaced capacity offered, and what arrives;
//! - CPU: a fixed load below both capacities (`--cpu-samples-per-s`), and the CPU time each
//!   process spends per batch (from /proc): the cost of the gateway over the relay, per batch,
//!   with little of the scheduling noise of a saturated two-core machine;
//! - latency: publish at a fixed rate (`--latency-batches-per-s`) and record, per batch, the
//!   time from just before the raw publish (stamped in the batch header) to its arrival at the
//!   subscriber: p50 and p99.
//!
//! The subscriber decodes in full what it receives.
//!
//! Two variables of the bench's environment serve experiments: `TRIAX_BENCH_DECLARED_KEYS_MAX`
//! (the gateway's declared-key budget) and `TRIAX_BENCH_RELAY_WORK_NS` (the relays busy for
//! that long before each put, as a gateway's correction spaces its puts).
//!
//! Then the memory check: the gateway alone with `--rss-sensors` calibrations; the publisher
//! sends a batch per sensor per second (a building's pace) for three rounds and on until every
//! sensor is online; once the gateway has settled, its resident set (`VmRSS`, and the peak
//! `VmHWM`) is read from /proc.
//!
//! Run in release: `cargo run --release -p triax-bench --bin triax-gateway-bench`.

use std::sync::atomic::{AtomicU64, Ordering::Relaxed};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use anyhow::{bail, Context, Result};

use clap::Parser;
use triax_bench::signal as bench_signal;
use triax_calibration_store::Store;
use triax_gateway::clock::now_ns;
use triax_gateway::{Config, Gateway, Overload};
use triax_protocol::batch::{
    BatchHeader, CorrectedBatch, CorrectedBatchWriter, CorrectedSample, CorrectionInfo, RawBatch,
    RawBatchView,
};
use triax_protocol::keys::{self, Stream};
use triax_protocol::record::{sample, CalibrationRecord};
use triax_protocol::{BuildingId, Key, SensorId};
use triax_test_support::proc::{
    context_switches, cpu_seconds, per_thread_group, proc_status_kib, thread_counters, ThreadGroup,
};
use zenoh::qos::CongestionControl;
use zenoh::Wait;

#[derive(Debug, Clone, Parser)]
#[command(name = "triax-gateway-bench")]
struct Args {
    /// Length of each throughput and latency phase.
    #[arg(long, default_value_t = 5.0)]
    seconds: f64,
    /// Simulated sensor nodes in the throughput and latency phases.
    #[arg(long, default_value_t = 10)]
    sensors: usize,
    /// Batch rate of the latency phase (all sensors together).
    #[arg(long, default_value_t = 1000.0)]
    latency_batches_per_s: f64,
    /// Also offer this load (samples/s) paced, and report what arrives (default: the relay's
    /// measured capacity, for the gateway).
    #[arg(long)]
    paced_samples_per_s: Option<f64>,
    /// Length of each trial of the zero-loss throughput search.
    #[arg(long, default_value_t = 2.0)]
    trial_seconds: f64,
    /// Offered load (samples/s) of the CPU phase, the same for both systems: below either's
    /// capacity, so both deliver all of it and what differs is the CPU they spend on it.
    #[arg(long, default_value_t = 5_000_000.0)]
    cpu_samples_per_s: f64,
    /// Sensors in the memory check (0: skip it).
    #[arg(long, default_value_t = 10_000)]
    rss_sensors: usize,
    /// The building profile: for each of these sensor counts, that many nodes each sending a
    /// 10-sample batch every 100 ms (100 Hz), every node's publisher declaring its key; empty to
    /// skip it (e.g. `--building-sensors 100,1000,5000`).
    #[arg(long, value_delimiter = ',')]
    building_sensors: Vec<usize>,
    /// Rounds of the throughput phases and of the building profile: every system (at every
    /// sensor count) in turn, each round's ratios reported, then their range. The building
    /// profile runs every other round's systems in reverse order.
    #[arg(long, default_value_t = 1)]
    rounds: usize,
    /// Skip the throughput and latency phases (run only the building profile and the memory
    /// check).
    #[arg(long)]
    no_throughput: bool,
    /// Only these systems (comma-separated names, e.g. `gateway,gateway-no-history`); the
    /// comparisons that need a missing one are left out.
    #[arg(long, value_delimiter = ',', value_enum)]
    systems: Vec<System>,
    /// Run `gateway-again` from this executable, another build of this bench: each round then
    /// pairs two builds of the gateway (an A/B), beside the A/A spread of earlier runs.
    #[arg(long)]
    again_exe: Option<std::path::PathBuf>,
    /// Internal: run as the system under test, in its own process.
    #[arg(long, hide = true, value_enum)]
    serve: Option<System>,
    #[arg(long, hide = true)]
    store: Option<std::path::PathBuf>,
    #[arg(long, hide = true)]
    port: Option<u16>,
}

const SAMPLES_PER_BATCH: usize = 100;
const BUILDING: &str = "bench";

fn building() -> BuildingId {
    // A literal of valid characters.
    BuildingId::new(BUILDING).expect("literal id is valid")
}

fn sensor_id(i: usize) -> SensorId {
    // `s` and five digits: always a valid id.
    SensorId::new(format!("s{i:05}")).expect("generated ids are valid")
}

fn record(i: usize) -> CalibrationRecord {
    let mut r = sample::record(sensor_id(i).as_str(), 1);
    let mut cov = [[0.0; 12]; 12];
    for (a, row) in cov.iter_mut().enumerate() {
        for (b, c) in row.iter_mut().enumerate() {
            *c = 1e-8 * 0.5f64.powi((a as i32 - b as i32).abs());
        }
    }
    r.static_set.covariance = Some(Box::new(cov));
    r.dynamic.covariance = Some(Box::new(cov));
    r
}

fn seed_store(path: &std::path::Path, n: usize) -> Result<()> {
    let store = Store::open(path)?;
    let records: Vec<_> = (0..n).map(record).collect();
    for outcome in store.put_all(&records)? {
        if let Err(e) = outcome {
            bail!("bench record refused: {e}");
        }
    }
    Ok(())
}

async fn session(listen: Option<&str>, connect: Option<&str>) -> Result<zenoh::Session> {
    let mut c = zenoh::Config::default();
    let list = |e: Option<&str>| e.map_or("[]".to_owned(), |e| format!("[\"{e}\"]"));
    for (k, v) in [
        ("mode", "\"peer\"".to_owned()),
        ("listen/endpoints", list(listen)),
        ("connect/endpoints", list(connect)),
        ("scouting/multicast/enabled", "false".to_owned()),
    ] {
        c.insert_json5(k, &v).map_err(|e| anyhow::anyhow!("{e}"))?;
    }
    zenoh::open(c).await.map_err(|e| anyhow::anyhow!("{e}"))
}

fn raw_batch(sensor: &SensorId, sequence: u64, samples: &[[f32; 3]]) -> Vec<u8> {
    RawBatch {
        header: BatchHeader {
            sensor_id: sensor.clone(),
            sequence,
            timestamp_ns: now_ns(),
            sample_rate_hz: 100.0,
        },
        temperature_c: None,
        samples: samples.to_vec(),
    }
    .encode()
}

/// A building node's batch `sequence` ([`bench_signal::healthy_batch`]), its time stamps
/// following on from batch to batch.
fn building_batch(sensor: &SensorId, sequence: u64, rng: &mut rand::rngs::StdRng) -> Vec<u8> {
    const EPOCH_NS: i64 = 1_800_000_000_000_000_000;
    let timestamp_ns = EPOCH_NS + sequence as i64 * (BUILDING_BATCH as i64) * 10_000_000;
    bench_signal::healthy_batch(sensor, sequence, timestamp_ns, BUILDING_BATCH, 100.0, rng)
}

fn outputs() -> Vec<[f32; 3]> {
    (0..SAMPLES_PER_BATCH)
        .map(|i| {
            let t = i as f32 / 100.0;
            [0.03 * (12.0 * t).sin(), 0.02 * (20.0 * t).cos(), 0.98]
        })
        .collect()
}

/// What the subscriber saw.
#[derive(Default)]
struct Received {
    samples: AtomicU64,
    latencies_ns: Mutex<Vec<i64>>,
    record_latency: std::sync::atomic::AtomicBool,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
enum System {
    Relay,
    KeyedRelay,
    KeyedRelayCorrected,
    Gateway,
    GatewayBackpressure,
    GatewayNoHistory,
    GatewayNoHealth,
    GatewayUnsigned,
    /// The gateway again, a second process of the same binary and settings: its ratio to
    /// `gateway` in one round is the spread between two processes, the bench's own resolution
    /// (an A/A control).
    GatewayAgain,
}

impl System {
    /// A relay: no store, no gateway.
    fn is_relay(self) -> bool {
        matches!(
            self,
            System::Relay | System::KeyedRelay | System::KeyedRelayCorrected
        )
    }

    /// Whether what it publishes is a corrected batch (else the raw batch it received).
    fn publishes_corrected(self) -> bool {
        !matches!(self, System::Relay | System::KeyedRelay)
    }

    fn name(self) -> &'static str {
        match self {
            System::Relay => "relay",
            System::KeyedRelay => "keyed-relay",
            System::KeyedRelayCorrected => "keyed-relay-corrected",
            System::Gateway => "gateway",
            System::GatewayBackpressure => "gateway-backpressure",
            System::GatewayNoHistory => "gateway-no-history",
            System::GatewayNoHealth => "gateway-no-health",
            System::GatewayUnsigned => "gateway-unsigned",
            System::GatewayAgain => "gateway-again",
        }
    }
}

struct PhaseResult {
    samples_per_s: f64,
    /// Delivered at the paced offered load, if one was set.
    paced_samples_per_s: Option<f64>,
    sent_samples_per_s: f64,
    p50_us: f64,
    p99_us: f64,
    n_latency: usize,
    cpu: CpuPerBatch,
    /// Throughput as RFC 2544 defines it: the highest load carried without loss.
    zero_loss_samples_per_s: f64,
}

/// CPU time per delivered batch at the CPU phase's fixed load, µs.
#[derive(Debug, Clone)]
struct CpuPerBatch {
    /// The system under test's process.
    server_us: f64,
    /// This process: the publisher and the subscriber.
    bench_us: f64,
    /// Fraction of the offered batches delivered (1 when the load is below capacity).
    delivered: f64,
    /// Context switches of the system under test's threads per batch: each is a thread
    /// that slept and was woken.
    server_switches: f64,
    /// The system under test's threads, by name.
    threads: Vec<ThreadGroup>,
}

fn percentile(sorted: &[i64], p: f64) -> f64 {
    if sorted.is_empty() {
        return f64::NAN;
    }
    let i = ((sorted.len() - 1) as f64 * p).round() as usize;
    sorted[i] as f64 / 1e3
}

/// What one throughput phase came to.
#[derive(Debug, Clone, Copy)]
struct Trial {
    /// Arrivals inside the phase, per second.
    received_per_s: f64,
    sent_per_s: f64,
    /// Fraction of what was sent that never arrived, once queues drained.
    loss: f64,
}

/// Most loss a zero-loss trial may show: the accounting allows for nothing else.
const ZERO_LOSS_MAX: f64 = 1e-3;

/// The simulated sensor nodes: one publisher per sensor, taking turns, each with its own
/// sequence numbers.
struct Fleet<'a> {
    received: &'a Received,
    publishers: Vec<zenoh::pubsub::Publisher<'a>>,
    ids: Vec<SensorId>,
    samples: Vec<[f32; 3]>,
    seq: Vec<u64>,
    next: usize,
}

impl Fleet<'_> {
    /// Publishes the next sensor's next batch.
    async fn put_next(&mut self) -> Result<()> {
        let i = self.next % self.publishers.len();
        self.publishers[i]
            .put(raw_batch(&self.ids[i], self.seq[i], &self.samples))
            .await
            .map_err(|e| anyhow::anyhow!("{e}"))?;
        self.seq[i] += 1;
        self.next += 1;
        Ok(())
    }

    /// One throughput phase. Unpaced: as fast as Zenoh takes it. Paced: `rate` samples/s, sent
    /// in 1 ms slices.
    async fn throughput(&mut self, phase: Duration, rate: Option<f64>) -> Result<Trial> {
        let start_count = self.received.samples.load(Relaxed);
        let t0 = Instant::now();
        let mut sent = 0u64;
        while t0.elapsed() < phase {
            if let Some(rate) = rate {
                let due = (t0.elapsed().as_secs_f64() * rate) as u64;
                if sent >= due {
                    tokio::time::sleep(Duration::from_millis(1)).await;
                    continue;
                }
            }
            self.put_next().await?;
            sent += SAMPLES_PER_BATCH as u64;
        }
        let elapsed = t0.elapsed().as_secs_f64();
        // Count only arrivals inside the window.
        let got = self.received.samples.load(Relaxed) - start_count;
        // Let queues drain before the next phase: until arrivals stop for 300 ms.
        let mut last = self.received.samples.load(Relaxed);
        loop {
            tokio::time::sleep(Duration::from_millis(300)).await;
            let now = self.received.samples.load(Relaxed);
            if now == last {
                break;
            }
            last = now;
        }
        let arrived = last - start_count;
        Ok(Trial {
            received_per_s: got as f64 / elapsed,
            sent_per_s: sent as f64 / elapsed,
            loss: 1.0 - arrived as f64 / sent.max(1) as f64,
        })
    }

    /// The highest offered load (samples/s) the system carries without loss, as RFC 2544
    /// defines a device's throughput: a bisection between `low` and `high` over paced trials,
    /// where a trial passes when the publisher sent at least 99 % of the target and at most
    /// [`ZERO_LOSS_MAX`] of it was lost.
    async fn zero_loss_rate(
        &mut self,
        trial: Duration,
        mut low: f64,
        mut high: f64,
    ) -> Result<f64> {
        for _ in 0..7 {
            let rate = (low + high) / 2.0;
            let t = self.throughput(trial, Some(rate)).await?;
            if t.sent_per_s >= 0.99 * rate && t.loss <= ZERO_LOSS_MAX {
                low = rate;
            } else {
                high = rate;
            }
        }
        Ok(low)
    }
}

async fn run_system(system: System, args: &Args) -> Result<PhaseResult> {
    let port = triax_net::free_loopback_port()?;
    let endpoint = format!("tcp/127.0.0.1:{port}");
    let dir = tempfile::tempdir()?;
    let store_path = dir.path().join("store");

    let server = match system {
        System::Relay | System::KeyedRelay | System::KeyedRelayCorrected => {
            Server::spawn(system, None, port)?
        }
        System::Gateway
        | System::GatewayBackpressure
        | System::GatewayNoHistory
        | System::GatewayNoHealth
        | System::GatewayUnsigned
        | System::GatewayAgain => {
            let n = args.sensors;
            let sp = store_path.clone();
            tokio::task::spawn_blocking(move || seed_store(&sp, n)).await??;
            Server::spawn(system, Some(&store_path), port)?
        }
    };

    let received = Arc::new(Received::default());
    let sub_session = session(None, Some(&endpoint)).await?;
    let r = received.clone();
    let _sub = sub_session
        .declare_subscriber(keys::all_sensors(&building(), Stream::Corrected))
        .callback(move |sample| {
            let bytes = sample.payload().to_bytes();
            let now = now_ns();
            // The consumer decodes in full what it receives, in both systems: it shares the
            // CPU with the system under test, so it must cost the same in both runs.
            let header = if system.publishes_corrected() {
                CorrectedBatch::decode(&bytes)
                    .ok()
                    .map(|b| (b.header, b.samples.len()))
            } else {
                RawBatch::decode(&bytes)
                    .ok()
                    .map(|b| (b.header, b.samples.len()))
            };
            if let Some((h, n)) = header {
                r.samples.fetch_add(n as u64, Relaxed);
                if r.record_latency.load(Relaxed) {
                    let mut l = r.latencies_ns.lock().unwrap_or_else(|p| p.into_inner());
                    l.push(now - h.timestamp_ns);
                }
            }
        })
        .await
        .map_err(|e| anyhow::anyhow!("{e}"))?;

    let pub_session = session(None, Some(&endpoint)).await?;
    let mut publishers = Vec::new();
    for i in 0..args.sensors {
        let p = pub_session
            .declare_publisher(Key::Raw(building(), sensor_id(i)).to_string())
            .congestion_control(CongestionControl::Block)
            .await
            .map_err(|e| anyhow::anyhow!("{e}"))?;
        publishers.push(p);
    }
    let mut fleet = Fleet {
        received: &received,
        publishers,
        ids: (0..args.sensors).map(sensor_id).collect(),
        samples: outputs(),
        seq: vec![0; args.sensors],
        next: 0,
    };
    // Wait until the raw and corrected paths are both matched.
    let deadline = Instant::now() + Duration::from_secs(10);
    while received.samples.load(Relaxed) == 0 {
        if Instant::now() > deadline {
            bail!("{system:?}: nothing came through in 10 s");
        }
        for _ in 0..args.sensors {
            fleet.put_next().await?;
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    tokio::time::sleep(Duration::from_millis(200)).await;

    let phase = Duration::from_secs_f64(args.seconds);
    let unpaced = fleet.throughput(phase, None).await?;
    let (samples_per_s, sent_samples_per_s) = (unpaced.received_per_s, unpaced.sent_per_s);
    // Bisect between half of what arrived unpaced and all that was sent: a relay that pushes
    // back sends no more than it carries, a gateway that sheds load sends more.
    let zero_loss_samples_per_s = fleet
        .zero_loss_rate(
            Duration::from_secs_f64(args.trial_seconds),
            0.5 * samples_per_s,
            sent_samples_per_s * 1.05,
        )
        .await?;
    let paced_samples_per_s = match args.paced_samples_per_s {
        Some(rate) => Some(fleet.throughput(phase, Some(rate)).await?.received_per_s),
        None => None,
    };

    // CPU per batch at a fixed load that both systems carry in full.
    let (server_cpu0, bench_cpu0) = (cpu_seconds(server.pid)?, cpu_seconds(std::process::id())?);
    let switches0 = context_switches(server.pid)?;
    let threads0 = thread_counters(server.pid)?;
    let fixed = fleet
        .throughput(phase, Some(args.cpu_samples_per_s))
        .await?;
    let batches = fixed.received_per_s * phase.as_secs_f64() / SAMPLES_PER_BATCH as f64;
    let cpu = CpuPerBatch {
        server_us: (cpu_seconds(server.pid)? - server_cpu0) / batches * 1e6,
        bench_us: (cpu_seconds(std::process::id())? - bench_cpu0) / batches * 1e6,
        delivered: fixed.received_per_s / fixed.sent_per_s,
        server_switches: (context_switches(server.pid)? - switches0) as f64 / batches,
        threads: per_thread_group(&threads0, &thread_counters(server.pid)?, batches),
    };

    // Latency at a fixed rate.
    received.record_latency.store(true, Relaxed);
    let period = Duration::from_secs_f64(1.0 / args.latency_batches_per_s);
    let mut tick = tokio::time::interval(period);
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    let t0 = Instant::now();
    while t0.elapsed() < phase {
        tick.tick().await;
        fleet.put_next().await?;
    }
    tokio::time::sleep(Duration::from_millis(300)).await;
    received.record_latency.store(false, Relaxed);
    let mut lat = std::mem::take(
        &mut *received
            .latencies_ns
            .lock()
            .unwrap_or_else(|p| p.into_inner()),
    );
    lat.sort_unstable();

    drop(fleet);
    let _ = pub_session.close().await;
    let _ = sub_session.close().await;
    let dropped = server.dropped.load(Relaxed);
    if dropped > 0 {
        eprintln!("{system:?} dropped {dropped} batches (drop-oldest) during the run");
    }
    drop(server);
    Ok(PhaseResult {
        samples_per_s,
        paced_samples_per_s,
        sent_samples_per_s,
        p50_us: percentile(&lat, 0.5),
        p99_us: percentile(&lat, 0.99),
        n_latency: lat.len(),
        cpu,
        zero_loss_samples_per_s,
    })
}

/// What the building profile measured of one system at one sensor count.
struct BuildingResult {
    sensors: usize,
    offered_batches_per_s: f64,
    delivered: f64,
    server_us_per_batch: f64,
    server_cores: f64,
    switches_per_batch: f64,
    rss_mib: f64,
    bench_us_per_batch: f64,
    /// The system's threads, by name.
    threads: Vec<ThreadGroup>,
}

/// Samples in a building profile batch.
const BUILDING_BATCH: usize = 10;
/// Batches a building profile node sends a second.
const BUILDING_BATCHES_PER_S: f64 = 10.0;

/// The building profile for one system: `n` nodes at 100 Hz in 10-sample batches, each node's
/// key declared by its publisher, for `seconds`; the server's CPU and context switches per
/// batch and its resident set at the end.
async fn building_profile(system: System, n: usize, seconds: f64) -> Result<BuildingResult> {
    let port = triax_net::free_loopback_port()?;
    let endpoint = format!("tcp/127.0.0.1:{port}");
    let dir = tempfile::tempdir()?;
    let store_path = dir.path().join("store");
    let server = match system {
        System::Relay | System::KeyedRelay | System::KeyedRelayCorrected => {
            Server::spawn(system, None, port)?
        }
        _ => {
            let sp = store_path.clone();
            tokio::task::spawn_blocking(move || seed_store(&sp, n)).await??;
            Server::spawn(system, Some(&store_path), port)?
        }
    };
    let received = Arc::new(AtomicU64::new(0));
    let sub_session = session(None, Some(&endpoint)).await?;
    let r = received.clone();
    let gateway = system.publishes_corrected();
    let _sub = sub_session
        .declare_subscriber(keys::all_sensors(&building(), Stream::Corrected))
        .callback(move |sample| {
            let bytes = sample.payload().to_bytes();
            let ok = if gateway {
                CorrectedBatch::decode(&bytes).is_ok()
            } else {
                RawBatch::decode(&bytes).is_ok()
            };
            if ok {
                r.fetch_add(1, Relaxed);
            }
        })
        .await
        .map_err(|e| anyhow::anyhow!("{e}"))?;
    let pub_session = session(None, Some(&endpoint)).await?;
    let ids: Vec<SensorId> = (0..n).map(sensor_id).collect();
    let mut publishers = Vec::with_capacity(n);
    for id in &ids {
        publishers.push(
            pub_session
                .declare_publisher(Key::Raw(building(), id.clone()).to_string())
                .congestion_control(CongestionControl::Block)
                .await
                .map_err(|e| anyhow::anyhow!("{e}"))?,
        );
    }
    let mut rng = <rand::rngs::StdRng as rand::SeedableRng>::seed_from_u64(1);
    let mut seq = vec![0u64; n];
    // Every node online (and, for the gateway, established, its keys declared), then settled:
    // rounds of one batch per node until one round arrives whole. The first rounds may lose
    // batches by design: the live stream drops what overfills a consumer's link while a
    // thousand keys are being declared (a consumer reads such a loss back from the history).
    let deadline = Instant::now() + Duration::from_secs(120);
    let mut round = 0;
    loop {
        // Spread over one batch period, as the nodes send.
        let before = received.load(Relaxed);
        let t0 = Instant::now();
        for (i, p) in publishers.iter().enumerate() {
            p.put(building_batch(&ids[i], seq[i], &mut rng))
                .await
                .map_err(|e| anyhow::anyhow!("{e}"))?;
            seq[i] += 1;
            let due = Duration::from_secs_f64((i + 1) as f64 / n as f64 / BUILDING_BATCHES_PER_S);
            if let Some(ahead) = due.checked_sub(t0.elapsed()) {
                if ahead > Duration::from_millis(2) {
                    tokio::time::sleep(ahead).await;
                }
            }
        }
        // What arrives of this round arrives within a second at these loads.
        let settle = Instant::now() + Duration::from_secs(1);
        while received.load(Relaxed) - before < n as u64 && Instant::now() < settle {
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
        let arrived = received.load(Relaxed) - before;
        round += 1;
        if round >= 3 && arrived >= n as u64 {
            break;
        }
        if Instant::now() > deadline {
            bail!(
                "{system:?} with {n} sensors: no warm-up round came through whole in 120 s (round {round}: {arrived} of {n} batches arrived)"
            );
        }
    }
    eprintln!(
        "{} with {n} sensors: warm, after {round} rounds",
        system.name()
    );
    tokio::time::sleep(Duration::from_millis(500)).await;
    let rate = n as f64 * BUILDING_BATCHES_PER_S;
    let (cpu0, bench0, sw0, threads0) = (
        cpu_seconds(server.pid)?,
        cpu_seconds(std::process::id())?,
        context_switches(server.pid)?,
        thread_counters(server.pid)?,
    );
    let got0 = received.load(Relaxed);
    let t0 = Instant::now();
    let mut sent = 0u64;
    let mut next = 0usize;
    while t0.elapsed().as_secs_f64() < seconds {
        let due = (t0.elapsed().as_secs_f64() * rate) as u64;
        while sent < due {
            let i = next % n;
            publishers[i]
                .put(building_batch(&ids[i], seq[i], &mut rng))
                .await
                .map_err(|e| anyhow::anyhow!("{e}"))?;
            seq[i] += 1;
            next += 1;
            sent += 1;
        }
        tokio::time::sleep(Duration::from_millis(1)).await;
    }
    let elapsed = t0.elapsed().as_secs_f64();
    let (cpu1, bench1, sw1, threads1) = (
        cpu_seconds(server.pid)?,
        cpu_seconds(std::process::id())?,
        context_switches(server.pid)?,
        thread_counters(server.pid)?,
    );
    tokio::time::sleep(Duration::from_millis(500)).await;
    let got = received.load(Relaxed) - got0;
    let rss_mib = proc_status_kib(server.pid, "VmRSS:").unwrap_or(0) as f64 / 1024.0;
    drop(publishers);
    let _ = pub_session.close().await;
    let _ = sub_session.close().await;
    drop(server);
    let batches = sent.max(1) as f64;
    Ok(BuildingResult {
        sensors: n,
        offered_batches_per_s: sent as f64 / elapsed,
        delivered: got as f64 / batches,
        server_us_per_batch: (cpu1 - cpu0) / batches * 1e6,
        server_cores: (cpu1 - cpu0) / elapsed,
        switches_per_batch: (sw1 - sw0) as f64 / batches,
        rss_mib,
        bench_us_per_batch: (bench1 - bench0) / batches * 1e6,
        threads: per_thread_group(&threads0, &threads1, batches),
    })
}

/// The building profile's table, the per-thread breakdown, and each gateway against the keyed
/// relay (and history on against off) at the same load, round by round, with the spread.
fn report_building(results: &[(usize, System, BuildingResult)]) {
    println!(
        "\n## Building profile: nodes at 100 Hz, {BUILDING_BATCH}-sample batches, {BUILDING_BATCHES_PER_S} batches/s each, keys declared by the nodes"
    );
    println!("| round | system | sensors | batches/s offered | delivered | CPU µs/batch | cores | context switches/batch | RSS MiB | publisher + subscriber µs/batch |");
    println!("|---|---|---|---|---|---|---|---|---|---|");
    for (round, system, r) in results {
        println!(
            "| {round} | {} | {} | {:.0} | {:.4} | {:.2} | {:.3} | {:.2} | {:.1} | {:.2} |",
            system.name(),
            r.sensors,
            r.offered_batches_per_s,
            r.delivered,
            r.server_us_per_batch,
            r.server_cores,
            r.switches_per_batch,
            r.rss_mib,
            r.bench_us_per_batch
        );
    }
    println!("\nPer thread (threads named alike summed; CPU from schedstat), per batch:\n");
    println!("| round | system | sensors | threads | CPU µs | voluntary switches | involuntary switches |");
    println!("|---|---|---|---|---|---|---|");
    for (round, system, r) in results {
        for g in r.threads.iter().filter(|g| {
            g.us_per_batch >= 0.05 || g.voluntary_per_batch + g.involuntary_per_batch >= 0.005
        }) {
            println!(
                "| {round} | {} | {} | {} ×{} | {:.2} | {:.3} | {:.3} |",
                system.name(),
                r.sensors,
                g.name,
                g.threads,
                g.us_per_batch,
                g.voluntary_per_batch,
                g.involuntary_per_batch
            );
        }
    }
    // Ratios of `a` over `b` at each sensor count, round by round, and their range.
    let ratios = |a: System, b: System, what: &str| {
        let sensors: std::collections::BTreeSet<usize> =
            results.iter().map(|(_, _, r)| r.sensors).collect();
        for n in sensors {
            let mut cpu = Vec::new();
            for (round, _, on) in results.iter().filter(|(_, s, r)| *s == a && r.sensors == n) {
                let Some((_, _, off)) = results
                    .iter()
                    .find(|(x, s, r)| x == round && *s == b && r.sensors == n)
                else {
                    continue;
                };
                cpu.push(on.server_us_per_batch / off.server_us_per_batch);
            }
            if cpu.is_empty() {
                continue;
            }
            println!(
                "- {} / {} ({what}) at {n} sensors: CPU per batch {}, {} rounds)",
                a.name(),
                b.name(),
                each_and_range(&cpu),
                cpu.len()
            );
        }
    };
    println!();
    for system in [
        System::KeyedRelayCorrected,
        System::Gateway,
        System::GatewayNoHistory,
        System::GatewayNoHealth,
        System::GatewayUnsigned,
        System::GatewayBackpressure,
        System::GatewayAgain,
    ] {
        ratios(system, System::KeyedRelay, "against the floor");
    }
    ratios(
        System::Gateway,
        System::KeyedRelayCorrected,
        "against the floor of the corrected format",
    );
    ratios(
        System::Gateway,
        System::GatewayNoHistory,
        "history on / off",
    );
    ratios(System::Gateway, System::GatewayNoHealth, "health on / off");
    ratios(
        System::Gateway,
        System::GatewayUnsigned,
        "signed / unsigned",
    );
    ratios(System::GatewayAgain, System::Gateway, again_label());
}

/// A system under test in its own process, as it is deployed: its own runtime and threads.
///
/// The child prints `ready N T` once it serves (N calibrations loaded, T ms after it began to
/// start), then, for the gateway, `online N` and `dropped N` whenever those counts change.
struct Server {
    child: std::process::Child,
    pid: u32,
    start_ms: f64,
    online: Arc<AtomicU64>,
    dropped: Arc<AtomicU64>,
}

/// `--again-exe`, set once at start.
static AGAIN_EXE: std::sync::OnceLock<std::path::PathBuf> = std::sync::OnceLock::new();

/// What `gateway-again` against `gateway` measures in this run.
fn again_label() -> &'static str {
    match AGAIN_EXE.get() {
        Some(_) => "A/B, the --again-exe build over this one",
        None => "A/A, the bench's own spread",
    }
}

impl Server {
    fn spawn(system: System, store: Option<&std::path::Path>, port: u16) -> Result<Server> {
        use std::io::BufRead;
        let exe = match AGAIN_EXE.get() {
            Some(other) if system == System::GatewayAgain => other.clone(),
            _ => std::env::current_exe()?,
        };
        let mut cmd = std::process::Command::new(exe);
        cmd.arg("--serve")
            .arg(system.name())
            .arg("--port")
            .arg(port.to_string())
            .stdout(std::process::Stdio::piped())
            .stderr(std::process::Stdio::null());
        if let Some(store) = store {
            cmd.arg("--store").arg(store);
        }
        let mut child = cmd.spawn().context("starting the system under test")?;
        let pid = child.id();
        let stdout = child.stdout.take().context("child stdout")?;
        let mut reader = std::io::BufReader::new(stdout);
        let mut line = String::new();
        reader.read_line(&mut line)?;
        let Some(start_ms) = line
            .strip_prefix("ready ")
            .and_then(|rest| rest.split_whitespace().nth(1))
            .and_then(|ms| ms.parse::<f64>().ok())
        else {
            let _ = child.kill();
            let _ = child.wait();
            bail!("{system:?} did not start: {line:?}");
        };
        let online = Arc::new(AtomicU64::new(0));
        let dropped = Arc::new(AtomicU64::new(0));
        let (o, d) = (online.clone(), dropped.clone());
        std::thread::spawn(move || {
            for line in reader.lines().map_while(Result::ok) {
                let mut words = line.split_whitespace();
                let (Some(what), Some(Ok(k))) = (words.next(), words.next().map(str::parse)) else {
                    continue;
                };
                match what {
                    "online" => o.store(k, Relaxed),
                    "dropped" => d.store(k, Relaxed),
                    _ => {}
                }
            }
        });
        Ok(Server {
            child,
            pid,
            start_ms,
            online,
            dropped,
        })
    }
}

impl Drop for Server {
    /// Also on an early return with an error: no system under test outlives the bench.
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// The child side of [`Server`]: serves until killed.
async fn serve(system: System, store: Option<&std::path::Path>, port: u16) -> Result<()> {
    let endpoint = format!("tcp/127.0.0.1:{port}");
    match system {
        System::Relay | System::KeyedRelay | System::KeyedRelayCorrected => {
            let s = session(Some(&endpoint), None).await?;
            let out = s.clone();
            // Keyed: per sensor, its declared raw key (held for the routing entry) and its
            // declared output key.
            type Declared = (
                zenoh::key_expr::KeyExpr<'static>,
                zenoh::key_expr::KeyExpr<'static>,
            );
            let declared: Mutex<std::collections::HashMap<SensorId, Declared>> = Mutex::default();
            // Experiments: work of this many ns per batch before the put, as a gateway's
            // correction spaces its puts (inherited from the bench's environment).
            let work = Duration::from_nanos(
                std::env::var("TRIAX_BENCH_RELAY_WORK_NS")
                    .ok()
                    .and_then(|v| v.parse().ok())
                    .unwrap_or(0),
            );
            let _sub = s
                .declare_subscriber(keys::all_sensors(&building(), Stream::Raw))
                .callback(move |sample| {
                    // The bench's own sensor ids are valid, so the chunk parses.
                    let sensor = SensorId::new(keys::sensor_chunk(sample.key_expr().as_str()))
                        .expect("bench sensor ids are valid");
                    let target: zenoh::key_expr::KeyExpr<'static> = if system == System::Relay {
                        // Valid: built from valid ids.
                        Key::Corrected(building(), sensor)
                            .to_string()
                            .try_into()
                            .expect("valid key")
                    } else {
                        let mut map = declared.lock().unwrap_or_else(|p| p.into_inner());
                        let entry = map.entry(sensor.clone()).or_insert_with(|| {
                            let declare = |k: Key| {
                                // Declaring a valid key on an open session does not fail.
                                out.declare_keyexpr(k.to_string())
                                    .wait()
                                    .expect("declare a valid key")
                            };
                            (
                                declare(Key::Raw(building(), sensor.clone())),
                                declare(Key::Corrected(building(), sensor)),
                            )
                        });
                        entry.1.clone()
                    };
                    if !work.is_zero() {
                        let t0 = Instant::now();
                        while t0.elapsed() < work {
                            std::hint::spin_loop();
                        }
                    }
                    let payload = if system == System::KeyedRelayCorrected {
                        // The bench's own batches are valid.
                        zenoh::bytes::ZBytes::from(as_corrected(&sample.payload().to_bytes()))
                    } else {
                        sample.payload().clone()
                    };
                    let _ = out
                        .put(target, payload)
                        .congestion_control(CongestionControl::Block)
                        .wait();
                })
                .await
                .map_err(|e| anyhow::anyhow!("{e}"))?;
            println!("ready 0 0");
            std::future::pending::<()>().await;
            Ok(())
        }
        System::Gateway
        | System::GatewayBackpressure
        | System::GatewayNoHistory
        | System::GatewayNoHealth
        | System::GatewayUnsigned
        | System::GatewayAgain => {
            let store = store.context("--store")?;
            let mut config = Config::for_tests(BUILDING, store, vec![endpoint]);
            // The service's defaults: health checks on.
            config.health = Some(triax_gateway::HealthSettings::default());
            match system {
                System::GatewayBackpressure => config.overload = Overload::Backpressure,
                System::GatewayNoHistory => config.history = None,
                System::GatewayNoHealth => config.health = None,
                System::GatewayUnsigned => config.provenance.sign = false,
                _ => {}
            }
            // Experiments with the key budget (inherited from the bench's environment).
            if let Some(n) = std::env::var("TRIAX_BENCH_DECLARED_KEYS_MAX")
                .ok()
                .and_then(|v| v.parse().ok())
            {
                config.declared_keys_max = n;
            }
            let t0 = Instant::now();
            let gateway = Gateway::start(config).await?;
            println!(
                "ready {} {:.0}",
                gateway.sensors().len(),
                t0.elapsed().as_secs_f64() * 1e3
            );
            let counters = gateway.counters().clone();
            tokio::spawn(async move {
                let (mut online, mut dropped) = (0, 0);
                loop {
                    tokio::time::sleep(Duration::from_millis(100)).await;
                    let now = counters.sensors_online.load(Relaxed);
                    if now != online {
                        println!("online {now}");
                        online = now;
                    }
                    let now = counters.dropped.load(Relaxed);
                    if now != dropped {
                        println!("dropped {now}");
                        dropped = now;
                    }
                }
            });
            gateway.run_until(std::future::pending::<()>()).await?;
            Ok(())
        }
    }
}

/// A raw batch rewritten as a corrected one, as `keyed-relay-corrected` publishes it: the
/// outputs as values, uncertainties zero, no flags, no calibration.
fn as_corrected(raw: &[u8]) -> Vec<u8> {
    let view = RawBatchView::parse(raw).expect("the bench's batches are valid");
    let mut out = Vec::new();
    let info = CorrectionInfo {
        calibration_version: 0,
        mode: triax_protocol::Mode::None,
        coverage_factor: 2.0,
    };
    let mut w = CorrectedBatchWriter::begin(&mut out, &view.header, info, view.len());
    for accel_mps2 in view.samples() {
        w.push(&CorrectedSample {
            accel_mps2,
            uncertainty_mps2: [0.0; 3],
            flags: 0,
        });
    }
    w.finish(0);
    out
}

/// How long the memory check lets the gateway settle after the last batch: a few of the
/// gateway's growth-settle periods, so that its own post-growth release has run.
const RSS_SETTLE: Duration = Duration::from_secs(3);

async fn rss_check(n: usize, system: System) -> Result<()> {
    let dir = tempfile::tempdir()?;
    let store_path = dir.path().join("store");
    let sp = store_path.clone();
    tokio::task::spawn_blocking(move || seed_store(&sp, n)).await??;
    let port = triax_net::free_loopback_port()?;
    let server = Server::spawn(system, Some(&store_path), port)?;
    let (pid, start_ms, online) = (server.pid, server.start_ms, server.online.clone());
    let loaded_rss = proc_status_kib(pid, "VmRSS:").unwrap_or(0);

    let endpoint = format!("tcp/127.0.0.1:{port}");
    let pub_session = session(None, Some(&endpoint)).await?;
    let samples = outputs();
    let mut publishers = Vec::with_capacity(n);
    for i in 0..n {
        publishers.push(
            pub_session
                .declare_publisher(Key::Raw(building(), sensor_id(i)).to_string())
                .congestion_control(CongestionControl::Block)
                .await
                .map_err(|e| anyhow::anyhow!("{e}"))?,
        );
    }
    tokio::time::sleep(Duration::from_millis(500)).await;
    // At a building's own pace, every sensor sending one 100-sample batch a second (100 Hz):
    // three rounds, and more until every sensor is online (at most 30).
    let t_first = Instant::now();
    let mut rounds = 0u64;
    for round in 0..30u64 {
        if round >= 3 && online.load(Relaxed) >= n as u64 {
            break;
        }
        rounds += 1;
        let t0 = Instant::now();
        for (i, p) in publishers.iter().enumerate() {
            p.put(raw_batch(&sensor_id(i), round, &samples))
                .await
                .map_err(|e| anyhow::anyhow!("{e}"))?;
            let due = Duration::from_secs_f64((i + 1) as f64 / n as f64);
            if let Some(ahead) = due.checked_sub(t0.elapsed()) {
                if ahead > Duration::from_millis(2) {
                    tokio::time::sleep(ahead).await;
                }
            }
        }
    }
    let online_after_s = t_first.elapsed().as_secs_f64();
    let deadline = Instant::now() + Duration::from_secs(30);
    while online.load(Relaxed) < n as u64 && Instant::now() < deadline {
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    tokio::time::sleep(RSS_SETTLE).await;
    let rss = proc_status_kib(pid, "VmRSS:").unwrap_or(0);
    let hwm = proc_status_kib(pid, "VmHWM:").unwrap_or(0);
    drop(server);
    let _ = pub_session.close().await;
    let online = online.load(Relaxed);
    println!("\n## Memory: {n} sensors, each with a calibration and 3 batches of {SAMPLES_PER_BATCH} samples");
    if online < n as u64 {
        println!("(only {online} of {n} sensors came online)");
    }
    println!(
        "{online} sensors online after {rounds} rounds of one batch per sensor ({online_after_s:.1} s)\n"
    );
    println!("{}:\n| state | VmRSS (MiB) |\n|---|---|", system.name());
    println!(
        "| gateway started, {n} calibrations loaded (start-up {start_ms:.0} ms) | {:.1} |",
        loaded_rss as f64 / 1024.0
    );
    println!(
        "| {online} sensors online, settled {} s | {:.1} |",
        RSS_SETTLE.as_secs(),
        rss as f64 / 1024.0
    );
    println!("| peak (VmHWM) | {:.1} |", hwm as f64 / 1024.0);
    Ok(())
}

/// The results table, then each gateway against each baseline run.
fn report(args: &Args, paced: &Args, results: &[(System, PhaseResult)]) {
    println!(
        "| system | unpaced: received samples/s | offered | without loss (RFC 2544) | CPU µs/batch at {:.0} samples/s: system / publisher + subscriber | context switches per batch | latency p50 / p99 (µs) |",
        args.cpu_samples_per_s
    );
    println!("|---|---|---|---|---|---|---|");
    for (system, r) in results {
        let c = &r.cpu;
        println!(
            "| {} | {:.0} | {:.0} | {:.0} | {:.2} / {:.2} (delivered {:.3}) | {:.2} | {:.0} / {:.0} ({} batches) |",
            system.name(),
            r.samples_per_s,
            r.sent_samples_per_s,
            r.zero_loss_samples_per_s,
            c.server_us,
            c.bench_us,
            c.delivered,
            c.server_switches,
            r.p50_us,
            r.p99_us,
            r.n_latency
        );
    }
    println!(
        "\n(without loss: at most {:.1} % lost over {} s trials)",
        ZERO_LOSS_MAX * 100.0,
        args.trial_seconds
    );
    println!("\nCPU phase per thread of the system under test (threads named alike summed; CPU from schedstat), per batch:\n");
    println!("| system | threads | CPU µs | voluntary switches | involuntary switches |");
    println!("|---|---|---|---|---|");
    for (system, r) in results {
        for g in r.cpu.threads.iter().filter(|g| g.us_per_batch >= 0.05) {
            println!(
                "| {} | {} ×{} | {:.2} | {:.3} | {:.3} |",
                system.name(),
                g.name,
                g.threads,
                g.us_per_batch,
                g.voluntary_per_batch,
                g.involuntary_per_batch
            );
        }
    }
    let get = |s: System| results.iter().find(|(x, _)| *x == s).map(|(_, r)| r);
    let total = |c: &CpuPerBatch| c.server_us + c.bench_us;
    let paced_rate = paced.paced_samples_per_s.unwrap_or(f64::NAN);
    for system in [System::Gateway, System::GatewayBackpressure] {
        let Some(g) = get(system) else { continue };
        let name = system.name();
        if let Some(delivered) = g.paced_samples_per_s {
            println!(
                "\n{name}: at the relay's unpaced capacity, {delivered:.0} of {paced_rate:.0} samples/s offered delivered ({:.2})",
                delivered / paced_rate,
            );
        }
        for base_system in [System::Relay, System::KeyedRelay] {
            let Some(base) = get(base_system) else {
                continue;
            };
            println!(
                "- {name} / {}: unpaced {:.2}, without loss {:.2}, CPU {:+.2} µs/batch in the system under test and {:+.2} in publisher + subscriber, capacity ratio from CPU (total / total) {:.2}; added latency p50 {:+.0} µs, p99 {:+.0} µs (at {} batches/s)",
                base_system.name(),
                g.samples_per_s / base.samples_per_s,
                g.zero_loss_samples_per_s / base.zero_loss_samples_per_s,
                g.cpu.server_us - base.cpu.server_us,
                g.cpu.bench_us - base.cpu.bench_us,
                total(&base.cpu) / total(&g.cpu),
                g.p50_us - base.p50_us,
                g.p99_us - base.p99_us,
                args.latency_batches_per_s
            );
        }
    }
    if let Some(h) = on_off(results, System::Gateway, System::GatewayNoHistory) {
        println!(
            "\nhistory on / off (gateway / gateway-no-history): unpaced {:.2}, without loss {:.2}, CPU per batch {:.2}×, capacity from CPU (total / total) {:.2}; the history writer {:.2} µs a batch, {:.1} % of the gateway's CPU",
            h.unpaced, h.zero_loss, h.cpu, h.capacity_from_cpu, h.writer_us, h.writer_share * 100.0
        );
    }
    if let Some(h) = on_off(results, System::GatewayAgain, System::Gateway) {
        println!(
            "\n{} (gateway-again / gateway): unpaced {:.2}, without loss {:.2}, CPU per batch {:.2}×, capacity from CPU (total / total) {:.2}",
            again_label(),
            h.unpaced,
            h.zero_loss,
            h.cpu,
            h.capacity_from_cpu
        );
    }
}

/// One gateway against another in one round of the throughput phases: history on against
/// off, or the A/A control.
struct OnOff {
    unpaced: f64,
    zero_loss: f64,
    /// The gateway's CPU per batch, on over off.
    cpu: f64,
    /// Off's CPU per batch over on's, the system under test and the bench's own process
    /// together: the capacity the CPU leaves, as a ratio.
    capacity_from_cpu: f64,
    /// The history writer thread's CPU per batch in the first, and its share of that
    /// gateway's CPU.
    writer_us: f64,
    writer_share: f64,
}

fn on_off(results: &[(System, PhaseResult)], a: System, b: System) -> Option<OnOff> {
    let get = |s: System| results.iter().find(|(x, _)| *x == s).map(|(_, r)| r);
    let (on, off) = (get(a)?, get(b)?);
    let writer_us = on
        .cpu
        .threads
        .iter()
        .filter(|g| g.name == "triax-history")
        .map(|g| g.us_per_batch)
        .sum::<f64>();
    Some(OnOff {
        unpaced: on.samples_per_s / off.samples_per_s,
        zero_loss: on.zero_loss_samples_per_s / off.zero_loss_samples_per_s,
        cpu: on.cpu.server_us / off.cpu.server_us,
        capacity_from_cpu: (off.cpu.server_us + off.cpu.bench_us)
            / (on.cpu.server_us + on.cpu.bench_us),
        writer_us,
        writer_share: writer_us / on.cpu.server_us,
    })
}

/// `v` listed and its range, to two decimals: `1.05, 1.12 (range 1.05–1.12` (the caller closes
/// the parenthesis, after what it adds).
fn each_and_range(v: &[f64]) -> String {
    let lo = v.iter().copied().fold(f64::INFINITY, f64::min);
    let hi = v.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    let each: Vec<String> = v.iter().map(|x| format!("{x:.2}")).collect();
    format!("{} (range {lo:.2}–{hi:.2}", each.join(", "))
}

/// Each round's history on / off ratios, and the A/A control's, with their ranges.
fn report_on_off_rounds(rounds: &[Vec<(System, PhaseResult)>]) {
    for (a, b, title) in [
        (
            System::Gateway,
            System::GatewayNoHistory,
            "History on / off",
        ),
        (System::GatewayAgain, System::Gateway, again_label()),
    ] {
        let all: Vec<OnOff> = rounds.iter().filter_map(|r| on_off(r, a, b)).collect();
        if all.len() < 2 {
            continue;
        }
        let line = |what: &str, f: &dyn Fn(&OnOff) -> f64| {
            let v: Vec<f64> = all.iter().map(f).collect();
            println!("- {what}: {})", each_and_range(&v));
        };
        println!("\n## {title} over {} rounds", all.len());
        line("unpaced", &|h| h.unpaced);
        line("without loss", &|h| h.zero_loss);
        line("CPU per batch, gateway process", &|h| h.cpu);
        line("capacity from CPU (total / total)", &|h| {
            h.capacity_from_cpu
        });
        if a == System::Gateway {
            line("history writer, µs a batch", &|h| h.writer_us);
            line("history writer, % of the gateway's CPU", &|h| {
                h.writer_share * 100.0
            });
        }
    }
}

fn main() -> Result<()> {
    let args = Args::parse();
    if let Some(exe) = &args.again_exe {
        if !exe.is_file() {
            bail!("--again-exe {}: no such file", exe.display());
        }
        // Set once, here, before any server starts.
        let _ = AGAIN_EXE.set(exe.clone());
    }
    if args.serve.is_some() {
        // The system under test runs as the service does: same allocator settings, same
        // logging (to the parent's null device). Zenoh's runtimes follow `ZENOH_RUNTIME` if
        // the bench's environment sets it, for the relays and the gateways alike.
        triax_gateway::memory::configure_allocator();
        triax_gateway::init_logging("info")?;
    }
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()?;
    runtime.block_on(async {
        if let Some(system) = args.serve {
            return serve(system, args.store.as_deref(), args.port.context("--port")?).await;
        }
        if !args.no_throughput {
            println!(
                "## Throughput and latency: {} sensors, {SAMPLES_PER_BATCH}-sample batches, {} s phases, loopback TCP, the system under test in its own process",
                args.sensors, args.seconds
            );
        }
        let all = [
            System::Relay,
            System::KeyedRelay,
            System::KeyedRelayCorrected,
            System::Gateway,
            System::GatewayBackpressure,
            System::GatewayNoHistory,
            System::GatewayAgain,
            System::GatewayNoHealth,
            System::GatewayUnsigned,
        ];
        let wanted = |s: System| args.systems.is_empty() || args.systems.contains(&s);
        if !args.no_throughput {
            let mut rounds = Vec::new();
            let mut paced = args.clone();
            // Rounds of every system in turn, as for the building profile below, but always
            // in one order: the paced phase offers the load the relay, run first, carried.
            for round in 1..=args.rounds.max(1) {
                let mut results: Vec<(System, PhaseResult)> = Vec::new();
                for system in all.into_iter().filter(|s| wanted(*s)) {
                    let r = run_system(system, &paced).await?;
                    if system == System::Relay && paced.paced_samples_per_s.is_none() {
                        // The gateways are offered the relay's capacity as well.
                        paced.paced_samples_per_s = Some(r.samples_per_s);
                    }
                    results.push((system, r));
                }
                if args.rounds > 1 {
                    println!("\n### Round {round}\n");
                }
                report(&args, &paced, &results);
                rounds.push(results);
            }
            report_on_off_rounds(&rounds);
        }
        if !args.building_sensors.is_empty() {
            let mut results = Vec::new();
            // Rounds of every system in turn, so that each ratio is taken within one round,
            // minutes apart at most, whatever else loads the machine meanwhile. Every other
            // round runs them in reverse order: a build run second in its round cost a few per
            // cent more than the same build run first (BENCHMARKS.md, "A ninth look").
            for round in 1..=args.rounds.max(1) {
                // The plain relay works out routes per message: the keyed relay is the
                // baseline.
                let mut systems: Vec<System> = all
                    .into_iter()
                    .filter(|s| *s != System::Relay && wanted(*s))
                    .collect();
                if round % 2 == 0 {
                    systems.reverse();
                }
                for &n in &args.building_sensors {
                    for &system in &systems {
                        let r = building_profile(system, n, args.seconds).await?;
                        results.push((round, system, r));
                    }
                }
            }
            report_building(&results);
        }
        if args.rss_sensors > 0 {
            // The first gateway among `--systems`, else the default gateway (history on).
            let system = args
                .systems
                .iter()
                .copied()
                .find(|s| !s.is_relay())
                .unwrap_or(System::Gateway);
            rss_check(args.rss_sensors, system).await?;
        }
        Ok(())
    })
}
