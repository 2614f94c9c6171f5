//! The alerting service through real Zenoh sessions on loopback: corrected batches in, alerts out
//! on the alert keys, in JSON, as a consumer sees them.

use std::time::Duration;

use triax_alert::config::{Config, ZenohMode, ZenohSettings};
use triax_protocol::keys::{all_buildings, Stream};
use triax_protocol::messages::{Alert, AlertKind, AlertLevel, AlertingStatus, JudgedLevel};
use triax_protocol::signing::{read_alert, to_hex, LabSigningKey, TrustedKeys};
use triax_protocol::{
    from_json, BatchHeader, BuildingId, CorrectedBatch, CorrectedSample, CorrectionInfo, Key, Mode,
    SensorId,
};

/// The service's signing key in these tests.
fn service_key() -> LabSigningKey {
    LabSigningKey::from_bytes(&[9; 32])
}

/// An alert as a consumer that trusts the service reads it: signed, and verified.
fn verified(payload: &[u8]) -> Alert {
    let trusted = TrustedKeys::new(vec![service_key().verifying_key()]);
    let (alert, trust) = read_alert(payload, &trusted).expect("an alert");
    assert!(trust.is_verified(), "{trust:?}");
    alert
}

const RATE_HZ: f64 = 100.0;
const BATCH: usize = 10;

/// The site peer listens on a port reserved by [`triax_net::free_loopback_port`]; the service
/// under test listens on `tcp/127.0.0.1:0` and connects to it.
fn free_port() -> u16 {
    triax_net::free_loopback_port().unwrap()
}

fn settings(listen: &str, connect: Vec<String>) -> ZenohSettings {
    ZenohSettings::loopback(ZenohMode::Peer, vec![listen.into()], connect)
}

fn batch(sequence: u64, amplitude_mps2: f64) -> CorrectedBatch {
    let start = sequence as usize * BATCH;
    CorrectedBatch {
        header: BatchHeader {
            sensor_id: SensorId::new("acc-01").unwrap(),
            sequence,
            timestamp_ns: 1_800_000_000_000_000_000 + (start as f64 * 1e9 / RATE_HZ) as i64,
            sample_rate_hz: RATE_HZ,
        },
        batch_flags: 0,
        info: CorrectionInfo {
            calibration_version: 3,
            mode: Mode::Dynamic,
            coverage_factor: 2.0,
        },
        samples: (0..BATCH)
            .map(|i| {
                let t = (start + i) as f64 / RATE_HZ;
                let x = amplitude_mps2 * (2.0 * std::f64::consts::PI * 2.0 * t).sin();
                CorrectedSample {
                    accel_mps2: [x as f32, 0.0, 9.81],
                    uncertainty_mps2: [0.02; 3],
                    flags: 0,
                }
            })
            .collect(),
    }
}

/// Publishes a regime until an alert of `kind` arrives; returns it. Alerts of other kinds that
/// arrive meanwhile go to `others`: the silent sensor's stale alert comes when it comes.
async fn publish_until(
    site: &zenoh::Session,
    alerts: &zenoh::pubsub::Subscriber<zenoh::handlers::FifoChannelHandler<zenoh::sample::Sample>>,
    sequence: &mut u64,
    amplitude_mps2: f64,
    kind: AlertKind,
    others: &mut Vec<Alert>,
) -> Alert {
    let key = Key::Corrected(
        BuildingId::new("hq").unwrap(),
        SensorId::new("acc-01").unwrap(),
    )
    .to_string();
    let deadline = tokio::time::Instant::now() + Duration::from_secs(60);
    loop {
        assert!(
            tokio::time::Instant::now() < deadline,
            "no {kind:?} alert within 60 s at amplitude {amplitude_mps2}"
        );
        *sequence += 1;
        site.put(&key, batch(*sequence, amplitude_mps2).encode())
            .await
            .unwrap();
        tokio::time::sleep(Duration::from_millis(20)).await;
        while let Ok(Some(sample)) = alerts.try_recv() {
            let alert = verified(&sample.payload().to_bytes());
            assert_eq!(
                sample.key_expr().as_str(),
                Key::Alert(alert.building.clone(), alert.sensor_id.clone()).to_string()
            );
            if alert.kind == kind {
                return alert;
            }
            others.push(alert);
        }
    }
}

#[tokio::test(flavor = "multi_thread")]
async fn alerts_travel_over_zenoh_with_their_decision_and_staleness() {
    let port = free_port();
    let site = zenoh::open(
        settings(&format!("tcp/127.0.0.1:{port}"), vec![])
            .to_config()
            .unwrap(),
    )
    .await
    .unwrap();
    let alerts = site
        .declare_subscriber(all_buildings(Stream::Alert))
        .await
        .unwrap();

    let mut config = Config::from_toml(
        "window_s = 1.0\nstale_after_s = 1.0\nrepeat_interval_s = 30.0\nhighpass_hz = 1.0\n\
         [buildings.hq.sensors.acc-01]\npga_mps2 = 0.5\n\
         [buildings.hq.sensors.acc-02]\n",
    )
    .unwrap();
    config.zenoh = settings("tcp/127.0.0.1:0", vec![format!("tcp/127.0.0.1:{port}")]);
    config.state_path = None;
    let key_dir = tempfile::tempdir().unwrap();
    let key_file = key_dir.path().join("alert.key");
    std::fs::write(&key_file, to_hex(&service_key().to_bytes())).unwrap();
    config.signing_key_file = Some(key_file);
    let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
    let service = tokio::spawn(triax_alert::run(config, async {
        let _ = stopped.await;
    }));

    let mut sequence = 0;
    let mut others = Vec::new();
    // [0.45, 0.53] m/s² straddles 0.5.
    let possible = publish_until(
        &site,
        &alerts,
        &mut sequence,
        0.49,
        AlertKind::PeakAcceleration,
        &mut others,
    )
    .await;
    assert_eq!(possible.level, AlertLevel::Possible, "{possible:?}");
    assert_eq!(possible.building.as_str(), "hq");
    assert_eq!(possible.coverage_factor, 2.0);
    // [0.76, 0.84] m/s² is above it.
    let exceeded = publish_until(
        &site,
        &alerts,
        &mut sequence,
        0.8,
        AlertKind::PeakAcceleration,
        &mut others,
    )
    .await;
    assert_eq!(exceeded.level, AlertLevel::Exceeded, "{exceeded:?}");
    assert!(exceeded.value - 2.0 * exceeded.standard_uncertainty > exceeded.threshold);
    assert!(exceeded.statement.contains("value − k·u > threshold"));
    let last_put = time::OffsetDateTime::now_utc();
    // It names the batches it judged, and the service's status says what it last judged of
    // every sensor, alert or not (PROTOCOL.md §3.8).
    assert!(exceeded.last_sequence.unwrap() <= sequence, "{exceeded:?}");
    let deadline = tokio::time::Instant::now() + Duration::from_secs(60);
    let status = loop {
        assert!(
            tokio::time::Instant::now() < deadline,
            "the status never named batch {sequence}"
        );
        let replies = site.get("triax/hq/alerting").await.unwrap();
        let reply = replies.recv_async().await.expect("the service answers");
        let st: AlertingStatus = from_json(&reply.result().unwrap().payload().to_bytes()).unwrap();
        let done = st
            .sensors
            .iter()
            .any(|s| s.sensor_id.as_str() == "acc-01" && s.last_sequence == Some(sequence));
        if done {
            break st;
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    };
    assert_eq!(
        status.public_key_hex,
        to_hex(service_key().verifying_key().as_bytes())
    );
    let acc01 = &status.sensors[0];
    assert_eq!(acc01.sensor_id.as_str(), "acc-01");
    assert!(
        acc01.judged_at.is_some() && acc01.waiting.is_none(),
        "{acc01:?}"
    );
    assert_eq!(
        acc01.levels.get(&AlertKind::PeakAcceleration),
        Some(&JudgedLevel::Exceeded),
        "{acc01:?}"
    );
    assert!(acc01.window_end_ns.unwrap() > acc01.window_start_ns.unwrap());
    let acc02 = &status.sensors[1];
    assert_eq!(acc02.sensor_id.as_str(), "acc-02");
    assert!(
        acc02.judged_at.is_none() && acc02.last_data_at.is_none(),
        "{acc02:?}"
    );

    // Silence: both the sensor that spoke and the expected one that never did go stale. The
    // one that never spoke may have gone stale while the other was still speaking; the one that
    // spoke counts only from after its last batch.
    let mut stale = std::collections::BTreeSet::new();
    let judge = |alert: Alert, stale: &mut std::collections::BTreeSet<String>| {
        if alert.kind == AlertKind::Stale {
            assert_eq!(alert.level, AlertLevel::Stale);
            assert!(alert.value > 1.0 && alert.threshold == 1.0, "{alert:?}");
            if alert.sensor_id.as_str() == "acc-02" || alert.at > last_put {
                stale.insert(alert.sensor_id.to_string());
            }
        }
    };
    for alert in others {
        judge(alert, &mut stale);
    }
    let deadline = tokio::time::Instant::now() + Duration::from_secs(60);
    while stale.len() < 2 {
        let left = deadline.saturating_duration_since(tokio::time::Instant::now());
        let sample = tokio::time::timeout(left, alerts.recv_async())
            .await
            .expect("stale alerts within 60 s")
            .unwrap();
        judge(verified(&sample.payload().to_bytes()), &mut stale);
    }
    assert_eq!(stale.into_iter().collect::<Vec<_>>(), ["acc-01", "acc-02"]);

    stop.send(()).unwrap();
    tokio::time::timeout(Duration::from_secs(60), service)
        .await
        .expect("service stops on shutdown")
        .unwrap()
        .unwrap();
    site.close().await.unwrap();
}
