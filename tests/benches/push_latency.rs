//! Push → new version in force on every gateway of a building, on loopback.
//!
//! A `zenohd` router, the lab (a client of it) and two gateways of one building (clients too,
//! each with its own sled store on disk). Each of `TRIAX_BENCH_PUSHES` pushes (default 50)
//! signs a new version of one sensor, queries the building's push key, and is timed until the
//! last of the two acknowledgements arrives. An acknowledgement is sent only after the record
//! is durable (flushed) and its corrector swapped in, so that time is "in force on every
//! gateway"; the bench also checks both gateways' tables after each push. Prints median, p90
//! and max in milliseconds.
//!
//! Then two phases at scale:
//! - **Start-up**: a gateway whose store holds `TRIAX_BENCH_STARTUP_SENSORS` calibrations
//!   (default 10 000, with full covariances), timed from `Gateway::start` to the first corrected
//!   batch of a node that was already publishing.
//! - **A push of many records to many gateways**: `TRIAX_BENCH_SCALE_RECORDS` records (default
//!   1 000, one per sensor) pushed at once (`push_all`, as `triax-lab push` does) to
//!   `TRIAX_BENCH_SCALE_GATEWAYS` gateways of one building (default 10), all clients of the
//!   router; timed until every record is acknowledged by every gateway.
//!
//! `cargo bench -p triax-tests --bench push_latency` (needs `zenohd` 1.10 on PATH).

use std::time::Duration;

use triax_gateway::{Config, Gateway};
use triax_lab::push::{push_all, push_one, Push};
use triax_protocol::messages::PushOutcome;
use triax_protocol::record::sample;
use triax_protocol::signing::LabSigningKey;
use triax_protocol::BuildingId;

#[path = "../tests/util.rs"]
mod util;

use util::Router;

const GATEWAYS: usize = 2;

fn env_or(name: &str, default: usize) -> usize {
    std::env::var(name)
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(default)
}

fn main() {
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .expect("tokio runtime starts");
    runtime.block_on(run(env_or("TRIAX_BENCH_PUSHES", 50)));
    runtime.block_on(startup(env_or("TRIAX_BENCH_STARTUP_SENSORS", 10_000)));
    runtime.block_on(at_scale(
        env_or("TRIAX_BENCH_SCALE_RECORDS", 1000),
        env_or("TRIAX_BENCH_SCALE_GATEWAYS", 10),
    ));
}

/// A record with a full covariance, as the lab writes them.
fn full_record(sensor: &str, version: u64) -> triax_protocol::CalibrationRecord {
    let mut r = sample::record(sensor, version);
    let mut cov = [[0.0; 12]; 12];
    for (i, row) in cov.iter_mut().enumerate() {
        row[i] = if i < 9 { 1e-8 } else { 1e-6 };
        if i > 0 {
            row[i - 1] = 1e-10;
        }
        if i + 1 < 12 {
            row[i + 1] = 1e-10;
        }
    }
    for set in [&mut r.static_set, &mut r.dynamic] {
        set.covariance = Some(Box::new(cov));
    }
    r
}

/// Start-up to streaming with `sensors` calibrations in the store.
async fn startup(sensors: usize) {
    let router = Router::start().await;
    let dir = tempfile::tempdir().expect("temporary directory");
    let store_path = dir.path().join("store");
    {
        let store = triax_calibration_store::Store::open(&store_path).expect("store opens");
        for i in 0..sensors {
            store
                .put(&full_record(&format!("s-{i}"), 1))
                .expect("store works")
                .expect("record accepted");
        }
    }
    let node = zenoh::open(router.client_settings().to_config().expect("client config"))
        .await
        .expect("node session opens");
    let corrected = node
        .declare_subscriber("triax/boot/corrected/s-0")
        .await
        .expect("subscriber");
    let mut c = Config::for_tests("boot", &store_path, vec![]);
    c.zenoh = router.client_settings();
    c.calibration.catchup_interval = None;
    // The node streams before the gateway is there, as a building's nodes do after a restart.
    let stop_node = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
    let streaming = {
        let (node, stop) = (node.clone(), stop_node.clone());
        tokio::spawn(async move {
            let mut seq = 0;
            while !stop.load(std::sync::atomic::Ordering::Relaxed) {
                let _ = node
                    .put(
                        "triax/boot/raw/s-0",
                        util::raw("s-0", seq, vec![[0.0, 0.0, 0.981]; 10]),
                    )
                    .await;
                seq += 1;
                tokio::time::sleep(Duration::from_millis(5)).await;
            }
        })
    };
    tokio::time::sleep(Duration::from_millis(300)).await;
    let start = std::time::Instant::now();
    let gw = Gateway::start(c).await.expect("gateway starts");
    let started = start.elapsed();
    let (tx, rx) = tokio::sync::oneshot::channel::<()>();
    let task = tokio::spawn(gw.run_until(async move {
        let _ = rx.await;
    }));
    let first = corrected
        .recv_async()
        .await
        .expect("a corrected batch after start-up");
    let streaming_after = start.elapsed();
    let batch = triax_protocol::CorrectedBatch::decode(&first.payload().to_bytes())
        .expect("a corrected batch");
    assert_eq!(
        batch.info.calibration_version, 1,
        "corrected with its record"
    );
    println!(
        "start-up with {sensors} calibrations (full covariances) in the store: Gateway::start \
         {:.0} ms, first corrected batch of a streaming node {:.0} ms after the start",
        started.as_secs_f64() * 1e3,
        streaming_after.as_secs_f64() * 1e3
    );
    stop_node.store(true, std::sync::atomic::Ordering::Relaxed);
    let _ = streaming.await;
    let _ = node.close().await;
    let _ = tx.send(());
    let _ = task.await;
    drop(router);
}

/// `records` records pushed at once to `gateways` gateways of one building.
async fn at_scale(records: usize, gateways: usize) {
    let router = Router::start().await;
    let key = LabSigningKey::from_bytes(&[8; 32]);
    let dir = tempfile::tempdir().expect("temporary directory");
    let running = start_gateways(&router, "scale", gateways, &key, dir.path()).await;
    let tables = &running.tables;
    let lab = zenoh::open(router.client_settings().to_config().expect("client config"))
        .await
        .expect("lab session opens");
    let building = BuildingId::new("scale").expect("valid id");
    // Warm-up: every gateway answers (declarations cross the router).
    loop {
        let push = Push::sign(&full_record("warm", 1), &key);
        let r = push_one(&lab, &building, &push, Duration::from_secs(2))
            .await
            .expect("push sent");
        if r.acks.len() == gateways {
            break;
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    let pushes: Vec<Push> = (0..records)
        .map(|i| Push::sign(&full_record(&format!("p-{i}"), 1), &key))
        .collect();
    let start = std::time::Instant::now();
    let reports = push_all(&lab, &[building], &pushes, Duration::from_secs(30))
        .await
        .expect("pushes sent");
    let elapsed = start.elapsed();
    let acks: usize = reports.iter().map(|r| r.acks.len()).sum();
    let slowest = reports
        .iter()
        .map(|r| r.elapsed_to_last_ack)
        .max()
        .unwrap_or_default();
    assert_eq!(
        acks,
        records * gateways,
        "every gateway acknowledged every record"
    );
    for t in tables {
        assert_eq!(t.versions().len(), records + 1, "every record in force");
    }
    println!(
        "{records} records pushed at once to {gateways} gateways of one building through \
         zenohd: all {acks} acknowledgements in {:.2} s (the slowest push's last ack after \
         {:.2} s)",
        elapsed.as_secs_f64(),
        slowest.as_secs_f64()
    );
    let _ = lab.close().await;
    running.stop().await;
    drop(router);
}

/// Gateways of one building, clients of the router, trusting `key`.
struct Gateways {
    tables: Vec<std::sync::Arc<triax_gateway::SensorTable>>,
    stops: Vec<(tokio::sync::oneshot::Sender<()>, GatewayTask)>,
}

type GatewayTask = tokio::task::JoinHandle<Result<(), triax_gateway::GatewayError>>;

impl Gateways {
    async fn stop(self) {
        for (tx, task) in self.stops {
            let _ = tx.send(());
            let _ = task.await;
        }
    }
}

async fn start_gateways(
    router: &Router,
    building: &str,
    n: usize,
    key: &LabSigningKey,
    dir: &std::path::Path,
) -> Gateways {
    let mut g = Gateways {
        tables: Vec::new(),
        stops: Vec::new(),
    };
    for i in 0..n {
        let mut c = Config::for_tests(building, &dir.join(format!("gw{i}")), vec![]);
        c.gateway_name = format!("gw-{building}-{i}");
        c.zenoh = router.client_settings();
        c.calibration.trusted_lab_keys = vec![key.verifying_key()];
        c.calibration.catchup_interval = None;
        let gw = Gateway::start(c).await.expect("gateway starts");
        g.tables.push(gw.sensors().clone());
        let (tx, rx) = tokio::sync::oneshot::channel::<()>();
        g.stops.push((
            tx,
            tokio::spawn(gw.run_until(async move {
                let _ = rx.await;
            })),
        ));
    }
    g
}

async fn run(pushes: usize) {
    let router = Router::start().await;

    let key = LabSigningKey::from_bytes(&[7; 32]);
    let dir = tempfile::tempdir().expect("temporary directory");
    let gateways = start_gateways(&router, "bench", GATEWAYS, &key, dir.path()).await;
    let tables = &gateways.tables;
    let lab = zenoh::open(router.client_settings().to_config().expect("client config"))
        .await
        .expect("lab session opens");
    let building = BuildingId::new("bench").expect("valid id");
    // Warm-up until both gateways answer (declarations cross the router).
    let mut version = 1;
    loop {
        let push = Push::sign(&sample::record("bench-1", version), &key);
        let r = push_one(&lab, &building, &push, Duration::from_secs(2))
            .await
            .expect("push sent");
        version += 1;
        if r.acks.len() == GATEWAYS {
            break;
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }

    let mut ms = Vec::with_capacity(pushes);
    for _ in 0..pushes {
        let push = Push::sign(&sample::record("bench-1", version), &key);
        let start = std::time::Instant::now();
        let r = push_one(&lab, &building, &push, Duration::from_secs(5))
            .await
            .expect("push sent");
        // The query ends when every gateway has answered; the last ack's time is the figure.
        let elapsed = r.elapsed_to_last_ack;
        assert!(start.elapsed() >= elapsed);
        assert_eq!(r.acks.len(), GATEWAYS, "every gateway answered");
        for a in &r.acks {
            assert!(
                matches!(
                    a.outcome,
                    PushOutcome::Accepted {
                        already_stored: false,
                        ..
                    }
                ),
                "{:?}",
                a.outcome
            );
        }
        for t in tables {
            assert_eq!(
                t.versions().first().map(|(_, v)| *v),
                Some(version),
                "in force when acknowledged"
            );
        }
        ms.push(elapsed.as_secs_f64() * 1e3);
        version += 1;
    }
    ms.sort_by(f64::total_cmp);
    let pick = |q: f64| ms[((ms.len() - 1) as f64 * q).round() as usize];
    println!(
        "push -> in force on {GATEWAYS} gateways of one building, {pushes} pushes through zenohd on \
         loopback: median {:.2} ms, p90 {:.2} ms, max {:.2} ms, min {:.2} ms",
        pick(0.5),
        pick(0.9),
        ms[ms.len() - 1],
        ms[0]
    );

    let _ = lab.close().await;
    gateways.stop().await;
    drop(router);
}
