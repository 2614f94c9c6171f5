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
//! `cargo bench -p triax-tests --bench push_latency` (needs `zenohd` 1.10 on PATH).

use std::time::Duration;

use triax_gateway::{Config, Gateway};
use triax_lab::push::{push_one, Push};
use triax_protocol::messages::PushOutcome;
use triax_protocol::record::sample;
use triax_protocol::signing::LabSigningKey;
use triax_protocol::BuildingId;

#[path = "../tests/util.rs"]
mod util;

use util::Router;

const GATEWAYS: usize = 2;

fn main() {
    let pushes: usize = std::env::var("TRIAX_BENCH_PUSHES")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(50);
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .expect("tokio runtime starts");
    runtime.block_on(run(pushes));
}

async fn run(pushes: usize) {
    let router = Router::start().await;

    let key = LabSigningKey::from_bytes(&[7; 32]);
    let dir = tempfile::tempdir().expect("temporary directory");
    let mut tables = Vec::new();
    let mut stops = Vec::new();
    for i in 0..GATEWAYS {
        let mut c = Config::for_tests("bench", &dir.path().join(format!("gw{i}")), vec![]);
        c.gateway_name = format!("gw-bench-{i}");
        c.zenoh = router.client_settings();
        c.calibration.trusted_lab_keys = vec![key.verifying_key()];
        c.calibration.catchup_interval = None;
        let gw = Gateway::start(c).await.expect("gateway starts");
        tables.push(gw.sensors().clone());
        let (tx, rx) = tokio::sync::oneshot::channel::<()>();
        stops.push((
            tx,
            tokio::spawn(gw.run_until(async move {
                let _ = rx.await;
            })),
        ));
    }
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
        for t in &tables {
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
    for (tx, task) in stops {
        let _ = tx.send(());
        let _ = task.await;
    }
    drop(router);
}
