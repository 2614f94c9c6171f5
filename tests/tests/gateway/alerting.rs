//! `triax-alert` through a real gateway: stopped while the building shakes, it reads what it
//! missed from the gateway's history when it starts again, judges it, and says the alert is late.

use std::time::Duration;

use triax_alert::config::Config as AlertConfig;
use triax_net::{ZenohMode, ZenohSettings};
use triax_protocol::messages::{Alert, AlertKind, AlertLevel};
use triax_protocol::record::sample;
use triax_protocol::signing::{read_alert, TrustedKeys};

use crate::util::*;

/// The last sequence number the alert service's resume state says it judged for a sensor.
fn judged(state: &std::path::Path, building: &str, sensor: &str) -> Option<u64> {
    let text = std::fs::read_to_string(state).ok()?;
    let v: serde_json::Value = serde_json::from_str(&text).ok()?;
    let p = &v[building][sensor];
    p["judged"].as_u64().or(p.as_u64())
}

/// Outputs of the sample record for a 2 Hz sway of `amp` on x (its dynamic set: unit gain).
fn sway(seq: u64, amp: f32) -> Vec<u8> {
    let samples = (0..10)
        .map(|i| {
            let t = (seq * 10 + i) as f32 / 100.0;
            [
                amp * (2.0 * std::f32::consts::PI * 2.0 * t).sin(),
                0.0,
                0.981,
            ]
        })
        .collect();
    raw("al-1", seq, samples)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_restarted_alert_service_judges_what_it_missed_and_says_it_is_late() {
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("store");
    seed_store(&store, &[sample::record("al-1", 1)]);
    let gw = start(config("ha1", &store)).await;
    let node = client(&gw.endpoint).await;
    let alerts = node.declare_subscriber("triax/ha1/alert/*").await.unwrap();
    let publisher = blocking_publisher(&node, key_raw("ha1", "al-1")).await;
    let state = dir.path().join("alert-state.json");
    // The service makes its key on first start; the consumer trusts what it wrote beside it.
    let key_file = dir.path().join("alert.key");
    let alert_config = || {
        let mut c = AlertConfig::from_toml(
            "window_s = 1.0\nstale_after_s = 60.0\nrepeat_interval_s = 0.0\n\
             [buildings.ha1.sensors.al-1]\npga_mps2 = 0.5\n",
        )
        .unwrap();
        c.zenoh = ZenohSettings::loopback(ZenohMode::Peer, vec![], vec![gw.endpoint.clone()]);
        c.state_path = Some(state.clone());
        c.signing_key_file = Some(key_file.clone());
        c
    };
    let run = |c: AlertConfig| {
        let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
        let task = tokio::spawn(triax_alert::run(c, async {
            let _ = stopped.await;
        }));
        (stop, task)
    };
    let (stop, task) = run(alert_config());
    let mut seq = 0;
    // Quiet, live, until the service has judged the sensor and written where it is: it
    // subscribes in its own time, and only a remembered position makes the restart read back.
    let deadline = tokio::time::Instant::now() + TIMEOUT;
    while judged(&state, "ha1", "al-1").is_none() {
        assert!(
            tokio::time::Instant::now() < deadline,
            "the alert service never recorded a position for al-1"
        );
        publisher.put(sway(seq, 0.05)).await.unwrap();
        seq += 1;
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    stop.send(()).unwrap();
    task.await.unwrap().unwrap();
    let judged_before = judged(&state, "ha1", "al-1").expect("the resume state is kept");
    // While it is down: a strong sway, then quiet again.
    let first_missed = seq;
    for amp in [0.9, 0.05] {
        for _ in 0..150 {
            publisher.put(sway(seq, amp)).await.unwrap();
            seq += 1;
        }
    }
    assert!(judged_before < first_missed);
    // Every missed batch is in the gateway's history before the service comes back, so that
    // none of the sway can reach it live: what it judges, it reads back.
    wait_history_holds(&node, "ha1", "al-1", seq - 1).await;
    while alerts.try_recv().unwrap().is_some() {}
    let public = std::fs::read_to_string(dir.path().join("alert.key.pub")).unwrap();
    let trusted = TrustedKeys::from_hex(&[public]).unwrap();
    let (stop, task) = run(alert_config());
    let deadline = tokio::time::Instant::now() + TIMEOUT;
    let late: Alert = loop {
        let left = deadline.saturating_duration_since(tokio::time::Instant::now());
        let s = tokio::time::timeout(left, alerts.recv_async())
            .await
            .expect("an alert on the missed stretch")
            .unwrap();
        let (a, trust) = read_alert(&s.payload().to_bytes(), &trusted).unwrap();
        assert!(trust.is_verified(), "{trust:?}");
        if a.kind == AlertKind::PeakAcceleration && a.level == AlertLevel::Exceeded {
            break a;
        }
    };
    assert!(late.late, "{late:?}");
    assert!(late.statement.contains("Raised late"), "{}", late.statement);
    assert!(late.value > 0.5, "{late:?}");
    // It names what it judged: a window inside the missed stretch, by time and by batch.
    let (first, last) = (late.first_sequence.unwrap(), late.last_sequence.unwrap());
    assert!(
        first >= first_missed && last < seq && first < last,
        "{late:?}"
    );
    let t = |s: u64| 1_800_000_000_000_000_000 + s as i64 * 100_000_000;
    assert!(late.window_start_ns.unwrap() >= t(first), "{late:?}");
    assert!(late.window_end_ns.unwrap() < t(last + 1), "{late:?}");
    stop.send(()).unwrap();
    task.await.unwrap().unwrap();
    node.close().await.unwrap();
    gw.stop().await;
}
