//! `triax-fleet-bench`: a fleet of building gateways behind a tree of two `zenohd` routers.
//!
//! ```text
//!   consumer (triax/*/corrected/**) + querier ──▶ root zenohd ◀── leaf zenohd ◀── B gateways
//!                                                                    ▲
//!                                        sensor nodes (B × S publishers)
//! ```
//!
//! Processes: the two routers; one process holding every gateway (`--serve-gateways`: B
//! in-process gateways, each with its own Zenoh session, calibration store, history and
//! worker, sharing the process's Zenoh and async runtimes as a host running many would); and
//! this one, which plays the sensor nodes (clients of the leaf router: their raw streams cross
//! it), a fleet-wide live consumer and the history querier (clients of the root router).
//!
//! On two cores a fleet at a building's full pace (100 buildings × 100 sensors × 10 batches a
//! second: 100 000 batches a second, each crossing two routers) does not fit beside its own
//! load generator, so each sensor sends `--batches-per-s` 10-sample batches a second (1 by
//! default: 10 000 batches a second fleet-wide). Reported: every process's CPU per batch
//! (routers, gateways, the bench), the gateways' threads, what the consumer received, and the
//! fleet-wide history query `triax/*/history/acc-01?from_ns=...`: how many buildings answered
//! and how long the answer took.
//!
//! `cargo run --release -p triax-bench --bin triax-fleet-bench` (needs `zenohd` 1.10 on
//! PATH, or `--zenohd`).

use std::io::BufRead;
use std::process::{Child, Command, Stdio};
use std::sync::atomic::{AtomicU64, Ordering::Relaxed};
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::{bail, Context, Result};
use clap::Parser;

use triax_bench::signal as bench_signal;
use triax_test_support::proc::{cpu_seconds, per_thread_group, proc_status_kib, thread_counters};

use triax_calibration_store::Store;
use triax_gateway::clock::now_ns;
use triax_gateway::{Config, Gateway};
use triax_net::ZenohMode;
use triax_protocol::batch::CorrectedBatch;
use triax_protocol::record::sample;
use triax_protocol::{BuildingId, Key, SensorId};
use zenoh::qos::CongestionControl;
use zenoh::query::{ConsolidationMode, QueryTarget};

#[derive(Debug, Clone, Parser)]
#[command(name = "triax-fleet-bench")]
struct Args {
    /// Buildings, each a gateway.
    #[arg(long, default_value_t = 100)]
    buildings: usize,
    /// Sensors per building, named acc-01, acc-02, ...
    #[arg(long, default_value_t = 100)]
    sensors: usize,
    /// 10-sample batches each sensor sends a second.
    #[arg(long, default_value_t = 1.0)]
    batches_per_s: f64,
    /// Length of the measured phase.
    #[arg(long, default_value_t = 20.0)]
    seconds: f64,
    /// History queries over the fleet, one after the other, after the measured phase.
    #[arg(long, default_value_t = 5)]
    queries: usize,
    /// The router binary.
    #[arg(long, default_value = "zenohd")]
    zenohd: String,
    /// Internal: run the gateways (`B,S,leaf endpoint,directory`).
    #[arg(long, hide = true)]
    serve_gateways: Option<String>,
}

const BATCH_SAMPLES: usize = 10;
const SAMPLE_RATE_HZ: f64 = 100.0;

fn building(b: usize) -> BuildingId {
    // `b` and three digits: a valid id.
    BuildingId::new(format!("b{b:03}")).expect("generated ids are valid")
}

fn sensor(s: usize) -> SensorId {
    // `acc-` and two or more digits: a valid id.
    SensorId::new(format!("acc-{:02}", s + 1)).expect("generated ids are valid")
}

async fn client(endpoint: &str) -> Result<zenoh::Session> {
    let mut c = zenoh::Config::default();
    for (k, v) in [
        ("mode", "\"client\"".to_owned()),
        ("connect/endpoints", format!("[\"{endpoint}\"]")),
        ("scouting/multicast/enabled", "false".to_owned()),
    ] {
        c.insert_json5(k, &v).map_err(|e| anyhow::anyhow!("{e}"))?;
    }
    zenoh::open(c).await.map_err(|e| anyhow::anyhow!("{e}"))
}

/// A child process killed when dropped, also on an early return.
struct Reaped(Child);

impl Drop for Reaped {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

fn router(zenohd: &str, listen_port: u16, connect: Option<u16>) -> Result<Reaped> {
    let mut cmd = Command::new(zenohd);
    cmd.args([
        "--no-multicast-scouting",
        "--listen",
        &format!("tcp/127.0.0.1:{listen_port}"),
    ]);
    if let Some(port) = connect {
        cmd.args(["--connect", &format!("tcp/127.0.0.1:{port}")]);
    }
    let child = cmd
        .env("RUST_LOG", "warn")
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .with_context(|| format!("{zenohd} (cargo install zenohd --version 1.10.2 --locked)"))?;
    let r = Reaped(child);
    let deadline = Instant::now() + Duration::from_secs(10);
    while std::net::TcpStream::connect(("127.0.0.1", listen_port)).is_err() {
        if Instant::now() > deadline {
            bail!("zenohd did not listen on {listen_port} within 10 s");
        }
        std::thread::sleep(Duration::from_millis(50));
    }
    Ok(r)
}

/// A node's batch, stamped now.
fn raw_batch(sensor: &SensorId, sequence: u64, rng: &mut rand::rngs::StdRng) -> Vec<u8> {
    bench_signal::healthy_batch(
        sensor,
        sequence,
        now_ns(),
        BATCH_SAMPLES,
        SAMPLE_RATE_HZ,
        rng,
    )
}

/// The child: every gateway, in one process; prints `ready` once all serve, then `online N`
/// (sensors online over the fleet) whenever it changes.
async fn serve_gateways(spec: &str) -> Result<()> {
    let parts: Vec<&str> = spec.splitn(4, ',').collect();
    let [b, s, leaf, dir] = parts[..] else {
        bail!("--serve-gateways B,S,endpoint,dir");
    };
    let (n_buildings, n_sensors): (usize, usize) = (b.parse()?, s.parse()?);
    let dir = std::path::Path::new(dir);
    let mut gateways = Vec::with_capacity(n_buildings);
    for b in 0..n_buildings {
        let id = building(b);
        let store_path = dir.join(format!("{id}.store"));
        let sp = store_path.clone();
        tokio::task::spawn_blocking(move || -> Result<()> {
            let store = Store::open(&sp)?;
            let records: Vec<_> = (0..n_sensors)
                .map(|s| sample::record(sensor(s).as_str(), 1))
                .collect();
            for outcome in store.put_all(&records)? {
                if let Err(e) = outcome {
                    bail!("bench record refused: {e}");
                }
            }
            Ok(())
        })
        .await??;
        let mut config = Config::for_tests(id.as_str(), &store_path, vec![]);
        config.zenoh.mode = Some(ZenohMode::Client);
        config.zenoh.connect = vec![leaf.to_owned()];
        // The service's defaults: health checks on.
        config.health = Some(triax_gateway::HealthSettings::default());
        // A hundred sensors at a second's batch each: one worker is plenty, and a host running
        // a hundred gateways has no cores to give each two.
        config.workers = 1;
        gateways.push(Gateway::start(config).await?);
    }
    println!("ready");
    let counters: Vec<_> = gateways.iter().map(|g| g.counters().clone()).collect();
    let mut online = 0;
    loop {
        tokio::time::sleep(Duration::from_millis(200)).await;
        let now: u64 = counters
            .iter()
            .map(|c| c.sensors_online.load(Relaxed))
            .sum();
        if now != online {
            println!("online {now}");
            online = now;
        }
    }
}

/// One fleet-wide history query: buildings that answered, and when the answer was complete.
async fn fleet_query(session: &zenoh::Session, from_ns: i64) -> Result<(usize, usize, f64)> {
    let t0 = Instant::now();
    let replies = session
        .get(format!("triax/*/history/acc-01?from_ns={from_ns}"))
        .target(QueryTarget::All)
        .consolidation(ConsolidationMode::None)
        .timeout(Duration::from_secs(10))
        .await
        .map_err(|e| anyhow::anyhow!("{e}"))?;
    let mut answered = std::collections::HashSet::new();
    let mut batches = 0;
    while let Ok(reply) = replies.recv_async().await {
        if let Ok(sample) = reply.result() {
            let key = sample.key_expr().as_str();
            if let Some(b) = key.split('/').nth(1) {
                answered.insert(b.to_owned());
            }
            batches += 1;
        }
    }
    Ok((answered.len(), batches, t0.elapsed().as_secs_f64()))
}

async fn run(args: &Args) -> Result<()> {
    let (nb, ns) = (args.buildings, args.sensors);
    let root_port = triax_net::free_loopback_port()?;
    let root = router(&args.zenohd, root_port, None)?;
    let leaf_port = triax_net::free_loopback_port()?;
    let leaf = router(&args.zenohd, leaf_port, Some(root_port))?;
    let leaf_endpoint = format!("tcp/127.0.0.1:{leaf_port}");
    let root_endpoint = format!("tcp/127.0.0.1:{root_port}");

    let dir = tempfile::tempdir()?;
    let t_start = Instant::now();
    let mut child = Command::new(std::env::current_exe()?)
        .arg("--serve-gateways")
        .arg(format!(
            "{nb},{ns},{leaf_endpoint},{}",
            dir.path().display()
        ))
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .context("starting the gateways")?;
    let stdout = child.stdout.take().context("the gateways' stdout")?;
    let gateways = Reaped(child);
    let gw_pid = gateways.0.id();
    let mut lines = std::io::BufReader::new(stdout).lines();
    match lines.next() {
        Some(Ok(l)) if l == "ready" => {}
        other => bail!("the gateways did not start: {other:?}"),
    }
    eprintln!(
        "{nb} gateways started in {:.1} s",
        t_start.elapsed().as_secs_f64()
    );
    let online = Arc::new(AtomicU64::new(0));
    let o = online.clone();
    std::thread::spawn(move || {
        for line in lines.map_while(Result::ok) {
            if let Some(Ok(n)) = line.strip_prefix("online ").map(str::parse) {
                o.store(n, Relaxed);
            }
        }
    });

    // The fleet-wide consumer, and the querier, on the root router.
    let consumer = client(&root_endpoint).await?;
    let received = Arc::new(AtomicU64::new(0));
    let r = received.clone();
    let _sub = consumer
        .declare_subscriber("triax/*/corrected/*")
        .callback(move |sample| {
            if CorrectedBatch::decode(&sample.payload().to_bytes()).is_ok() {
                r.fetch_add(1, Relaxed);
            }
        })
        .await
        .map_err(|e| anyhow::anyhow!("{e}"))?;
    let querier = client(&root_endpoint).await?;

    // The nodes, on the leaf router.
    let nodes = client(&leaf_endpoint).await?;
    let mut publishers = Vec::with_capacity(nb * ns);
    for b in 0..nb {
        for s in 0..ns {
            let p = nodes
                .declare_publisher(Key::Raw(building(b), sensor(s)).to_string())
                .congestion_control(CongestionControl::Block)
                .await
                .map_err(|e| anyhow::anyhow!("{e}"))?;
            publishers.push((sensor(s), p));
        }
    }
    let total = publishers.len();
    let mut seq = vec![0u64; total];
    let mut rng = <rand::rngs::StdRng as rand::SeedableRng>::seed_from_u64(1);
    let rate = total as f64 * args.batches_per_s;
    // Sends at `rate`, in 1 ms slices, for `seconds`; the batches sent.
    let mut next = 0usize;
    let mut send = async |seconds: f64| -> Result<u64> {
        let t0 = Instant::now();
        let mut sent = 0u64;
        while t0.elapsed().as_secs_f64() < seconds {
            let due = (t0.elapsed().as_secs_f64() * rate) as u64;
            while sent < due {
                let i = next % total;
                let (id, p) = &publishers[i];
                p.put(raw_batch(id, seq[i], &mut rng))
                    .await
                    .map_err(|e| anyhow::anyhow!("{e}"))?;
                seq[i] += 1;
                next += 1;
                sent += 1;
            }
            tokio::time::sleep(Duration::from_millis(1)).await;
        }
        Ok(sent)
    };
    // Warm-up: every sensor online, then a few seconds more for the keys to settle.
    let deadline = Instant::now() + Duration::from_secs(180);
    while online.load(Relaxed) < total as u64 {
        if Instant::now() > deadline {
            bail!(
                "only {} of {total} sensors online after 180 s",
                online.load(Relaxed)
            );
        }
        send(1.0).await?;
    }
    send(3.0).await?;
    eprintln!(
        "{total} sensors online after {:.1} s",
        t_start.elapsed().as_secs_f64()
    );

    let pids = [
        ("root zenohd", root.0.id()),
        ("leaf zenohd", leaf.0.id()),
        ("gateways", gw_pid),
        ("bench (nodes, consumer)", std::process::id()),
    ];
    let cpu0: Vec<f64> = pids
        .iter()
        .map(|(_, p)| cpu_seconds(*p))
        .collect::<Result<_>>()?;
    let threads0 = thread_counters(gw_pid)?;
    let got0 = received.load(Relaxed);
    let t0 = Instant::now();
    let sent = send(args.seconds).await?;
    let elapsed = t0.elapsed().as_secs_f64();
    let cpu1: Vec<f64> = pids
        .iter()
        .map(|(_, p)| cpu_seconds(*p))
        .collect::<Result<_>>()?;
    let threads1 = thread_counters(gw_pid)?;
    let batches = sent.max(1) as f64;
    // What was sent arrives within half a second at these loads; then the stream resumes
    // for the queries, as in a fleet.
    tokio::time::sleep(Duration::from_millis(500)).await;
    let got = received.load(Relaxed) - got0;

    let mut queries = Vec::new();
    for _ in 0..args.queries {
        let from_ns = now_ns() - 10_000_000_000;
        // The nodes keep sending while the query runs.
        let (answer, sending) = tokio::join!(fleet_query(&querier, from_ns), send(3.0));
        sending?;
        queries.push(answer?);
    }
    let gw_rss = proc_status_kib(gw_pid, "VmRSS:").unwrap_or(0) as f64 / 1024.0;

    println!(
        "\n## Fleet: {nb} buildings × {ns} sensors, {BATCH_SAMPLES}-sample batches, {} a second per sensor ({:.0} batches/s offered), two zenohd routers",
        args.batches_per_s,
        sent as f64 / elapsed
    );
    println!(
        "\ndelivered to the fleet-wide consumer: {:.4} of {sent} batches in {elapsed:.1} s; gateways' RSS {gw_rss:.0} MiB ({:.2} MiB a building)\n",
        got as f64 / batches,
        gw_rss / nb as f64
    );
    println!("| process | CPU µs per batch | cores |\n|---|---|---|");
    for (i, (name, _)) in pids.iter().enumerate() {
        let cpu = cpu1[i] - cpu0[i];
        println!(
            "| {name} | {:.2} | {:.3} |",
            cpu / batches * 1e6,
            cpu / elapsed
        );
    }
    println!("\nThe gateways' threads (named alike summed), per batch:\n");
    println!("| threads | CPU µs | voluntary switches | involuntary switches |\n|---|---|---|---|");
    for g in per_thread_group(&threads0, &threads1, batches)
        .iter()
        .filter(|g| g.us_per_batch >= 0.05)
    {
        println!(
            "| {} ×{} | {:.2} | {:.3} | {:.3} |",
            g.name, g.threads, g.us_per_batch, g.voluntary_per_batch, g.involuntary_per_batch
        );
    }
    println!("\nFleet-wide history queries `triax/*/history/acc-01?from_ns=<10 s ago>`, the stream running:\n");
    println!("| query | buildings answered | batches | complete after (s) |\n|---|---|---|---|");
    for (i, (answered, n, secs)) in queries.iter().enumerate() {
        println!("| {} | {answered} of {nb} | {n} | {secs:.3} |", i + 1);
    }
    drop(nodes);
    drop(gateways);
    Ok(())
}

fn main() -> Result<()> {
    let args = Args::parse();
    if args.serve_gateways.is_some() {
        // As the service binary sets itself up, before any thread exists.
        triax_gateway::memory::configure_allocator();
        triax_gateway::init_logging("warn")?;
    }
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()?;
    match &args.serve_gateways {
        Some(spec) => runtime.block_on(serve_gateways(spec)),
        None => runtime.block_on(run(&args)),
    }
}
