//! Catch-up when the lab's registry comes after the gateway: peers only, no router, the registry
//! starts 2 s after the gateway. The gateway must not wait for its next periodic round
//! (`catchup_interval_s`, 60 s by default) to get what the registry holds.

use std::time::{Duration, Instant};

use triax_lab::registry::Registry;
use triax_lab::serve::RegistryServer;
use triax_protocol::record::sample;
use triax_protocol::signing::LabSigningKey;
use triax_protocol::{BuildingId, SensorId};

use super::status;
use crate::util::*;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_registry_that_arrives_late_is_caught_up_with_within_seconds() {
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("store");
    seed_store(&store, &[sample::record("late-1", 1)]);
    let key = LabSigningKey::from_bytes(&[5; 32]);
    let mut cfg = config("hl", &store);
    cfg.calibration.trusted_lab_keys = vec![key.verifying_key()];
    // The periodic round is far beyond any deadline below, so only the registry's arrival
    // can bring version 2 in.
    cfg.calibration.catchup_interval = Some(Duration::from_secs(3600));
    let gw = start(cfg).await;
    // The registry holds version 2, assigned to the building.
    let registry = Registry::new(dir.path().join("registry"));
    registry
        .record(
            &[sample::record("late-1", 2)],
            &[BuildingId::new("hl").unwrap()],
        )
        .unwrap();
    tokio::time::sleep(Duration::from_secs(2)).await;
    let lab = client(&gw.endpoint).await;
    let arrived = Instant::now();
    let server = RegistryServer::start(&lab, registry, key).await.unwrap();
    let observer = client(&gw.endpoint).await;
    // Far below the periodic round (asserted above), however loaded the machine.
    let deadline = arrived + TIMEOUT;
    loop {
        let st = status(&observer, "hl").await;
        let v = st
            .sensors
            .iter()
            .find(|s| s.sensor_id == SensorId::new("late-1").unwrap())
            .and_then(|s| s.calibration_version);
        if v == Some(2) {
            break;
        }
        assert!(
            Instant::now() < deadline,
            "version 2 not in force {:?} after the registry arrived",
            arrived.elapsed()
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    println!(
        "in force {:?} after the registry arrived",
        arrived.elapsed()
    );
    server.stop().await;
    lab.close().await.unwrap();
    observer.close().await.unwrap();
    gw.stop().await;
}
