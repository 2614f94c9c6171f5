//! Gateway tests with real Zenoh sessions on loopback: a gateway started from the library with
//! a real sled store in a temporary directory, simulated sensor nodes publishing raw batches,
//! and subscribers reading the corrected and tilt streams, the status queryable and the
//! metrics endpoint.
//!
//! - `corrected_values_match_the_truth_within_their_uncertainty`: a node whose true S and q
//!   differ from the record by errors drawn from the record's covariance, with output noise;
//!   the corrected values fall within the tagged k = 2 interval at the expected rate.
//! - `uncalibrated_sensor_is_published_flagged_and_counted`: no record: raw values pass through
//!   flagged `uncalibrated`, mode none, NaN uncertainty; counted in status and metrics.
//! - `sensors_past_the_declared_key_budget_publish_undeclared`: with room for one sensor's
//!   keys, three sensors' streams all arrive.
//! - `declared_keys_move_from_a_silent_sensor_to_a_streaming_one`,
//!   `more_streaming_sensors_than_the_key_budget_turn_every_key_undeclared`: the budget follows
//!   the streaming sensors, all or nothing.
//! - `shutdown_publishes_every_batch_already_received`: stopping right after a burst still
//!   corrects and publishes what was queued, and the history keeps all of it.
//! - `status_is_paged_and_bad_parameters_are_refused_by_name`
//! - `malformed_payloads_are_counted_and_the_stream_goes_on`
//! - `gaps_and_duplicates_are_flagged_and_counted`
//! - `restart_keeps_calibrations`: stop, start again on the same store, same version in force.
//! - `split_mode_and_tilt_stream`: split mode recovers a motion whose static and vibration
//!   sensitivities differ; the tilt stream's angles match the truth within their uncertainty.
//! - `alerting`: `triax-alert` resumes from its state through the history after a restart.
//! - `alert_mc` (ignored by default): a Monte Carlo of `triax-alert`'s published alerts with
//!   known truth: false `exceeded` at the limit, coverage, the sample-bound path, low
//!   frequencies, and the latency the service adds at 100 sensors.
//! - `catchup`: a registry that arrives after the gateway is caught up with within seconds.
//! - `console`: the operators' console in headless Chromium against a demo building; what it
//!   refuses; the one-sensor status it reads the calibration record from.
//! - `backfill`: a link cut and the gateway's own downtime filled from the node's buffer,
//!   published `late` with the bytes an uninterrupted gateway published, kept once, replayed.
//! - `faults`: real nodes behind a link that is cut, a gateway killed, a router restarted:
//!   every batch in the history once and in a §5.2 consumer once.
//! - `hardening`: wildcard keys, numbering jumps, floods of new ids.
//! - `campaign` (ignored by default): a million hostile messages against one gateway.
//! - `health`: a frozen channel makes its record `suspect` and flags its samples from the
//!   reported time, through a restart and until a new record; replays reproduce the flag.
//! - `history`: replay byte for byte, recalibration in force or latest, losing nothing across an
//!   outage, retention.
//! - `provenance`: a hostile peer's relayed, altered, replayed and self-sealed batches and its
//!   history and status answers, refused by a verifying follower and history read.
//! - `replay_restart`: the history byte for byte the live stream across clean stops and kills of
//!   the gateway (split-mode and dynamic sensors).
//! - `modes`: `triax-modes` identifies a simulated five-storey building's first three modes of
//!   each direction from a 30-minute window streamed through the gateway faster than real time,
//!   and after a restart the window it missed, from the history.
//! - `tilt`: 300 inclinometers ramping at 0.01–0.2 °/s under sway: the truth at each tilt
//!   sample's instant lies within ±k·u at the stated rate.

#[path = "gateway/alert_mc.rs"]
mod alert_mc;
#[path = "gateway/alerting.rs"]
mod alerting;
#[path = "gateway/backfill.rs"]
mod backfill;
#[path = "gateway/campaign.rs"]
mod campaign;
#[path = "gateway/catchup.rs"]
mod catchup;
#[path = "gateway/console.rs"]
mod console;
#[path = "gateway/faults.rs"]
mod faults;
#[path = "gateway/hardening.rs"]
mod hardening;
#[path = "gateway/health.rs"]
mod health;
#[path = "gateway/history.rs"]
mod history;
#[path = "gateway/history_owner.rs"]
mod history_owner;
#[path = "gateway/intervals.rs"]
mod intervals;
#[path = "gateway/modes.rs"]
mod modes;
#[path = "gateway/modes_mc.rs"]
mod modes_mc;
#[path = "gateway/provenance.rs"]
mod provenance;
#[path = "gateway/replay_restart.rs"]
mod replay_restart;
#[path = "gateway/tilt.rs"]
mod tilt;
mod util;

use std::f64::consts::PI;

use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use rand_distr::StandardNormal;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use triax_gateway::{CorrectionMode, SensorSettings};
use triax_protocol::batch::{flags, Mode};
use triax_protocol::messages::{GatewayStatus, TiltSample};
use triax_protocol::record::{sample, CalibrationRecord};
use triax_protocol::{from_json, BuildingId, Key, SensorId};
use util::*;

async fn metrics(addr: std::net::SocketAddr) -> String {
    let mut s = tokio::net::TcpStream::connect(addr)
        .await
        .expect("metrics connect");
    s.write_all(b"GET /metrics HTTP/1.1\r\nHost: x\r\n\r\n")
        .await
        .unwrap();
    let mut body = String::new();
    s.read_to_string(&mut body).await.unwrap();
    assert!(body.starts_with("HTTP/1.1 200 OK"), "{body}");
    body
}

/// A record with a stated diagonal covariance and output noise.
fn record_with_covariance(id: &str, version: u64, sd_s: f64, sd_q: f64) -> CalibrationRecord {
    let mut r = sample::record(id, version);
    r.sensor.output_noise = Some([0.001; 3]);
    for set in [&mut r.static_set, &mut r.dynamic] {
        let mut cov = [[0.0; 12]; 12];
        for (i, row) in cov.iter_mut().enumerate() {
            row[i] = if i < 9 { sd_s * sd_s } else { sd_q * sd_q };
        }
        set.covariance = Some(Box::new(cov));
    }
    r
}

fn motion(t: f64) -> [f64; 3] {
    [
        0.3 * (2.0 * PI * 2.0 * t).sin(),
        0.2 * (2.0 * PI * 3.3 * t + 1.0).sin(),
        9.81 + 0.05 * (2.0 * PI * 1.1 * t).sin(),
    ]
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn corrected_values_match_the_truth_within_their_uncertainty() {
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("store");
    let (sd_s, sd_q) = (1e-4, 0.004);
    let record = record_with_covariance("acc-1", 3, sd_s, sd_q);
    seed_store(&store, std::slice::from_ref(&record));
    let mut rng = StdRng::seed_from_u64(5);
    let mut normal = move || rng.sample::<f64, _>(StandardNormal);
    // The truth is the record's dynamic set off by errors drawn from its stated covariance.
    let s_true = record
        .dynamic
        .sensitivity
        .map(|r| r.map(|x| x + sd_s * normal()));
    let q_true = record.dynamic.offset.map(|x| x + sd_q * normal());

    let gw = start(config("b1", &store)).await;
    let session = client(&gw.endpoint).await;
    let sub = session
        .declare_subscriber(key_corrected("b1", "acc-1"))
        .await
        .unwrap();
    let publisher = session
        .declare_publisher(key_raw("b1", "acc-1"))
        .await
        .unwrap();
    wait_matching(&publisher).await;

    let n_batches = 20;
    for seq in 0..n_batches {
        let samples = (0..50)
            .map(|i| {
                let t = (seq * 50 + i) as f64 / 100.0;
                outputs(&s_true, &q_true, motion(t)).map(|v| (v + 0.001 * normal()) as f32)
            })
            .collect();
        publisher.put(raw("acc-1", seq, samples)).await.unwrap();
    }
    let batches = collect(&sub, n_batches as usize).await;
    let (mut n, mut within, mut worst) = (0, 0, 0f64);
    for (seq, b) in batches.iter().enumerate() {
        assert_eq!(b.header.sequence, seq as u64);
        assert_eq!(b.info.calibration_version, 3);
        assert_eq!(b.info.mode, Mode::Dynamic);
        assert_eq!(b.batch_flags, 0, "{:?}", flags::names(b.batch_flags));
        for (i, s) in b.samples.iter().enumerate() {
            let truth = motion((seq * 50 + i) as f64 / 100.0);
            for (k, truth_k) in truth.iter().enumerate() {
                let u = f64::from(s.uncertainty_mps2[k]);
                assert!(u > 0.0 && u < 0.05, "u = {u}");
                let z = (f64::from(s.accel_mps2[k]) - truth_k).abs() / u;
                n += 1;
                within += usize::from(z <= 2.0);
                worst = worst.max(z);
            }
        }
    }
    let share = within as f64 / n as f64;
    assert!(share > 0.9, "{:.1} % within k = 2", 100.0 * share);
    assert!(worst < 5.0, "an error of {worst:.1} u");
    session.close().await.unwrap();
    gw.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn uncalibrated_sensor_is_published_flagged_and_counted() {
    let dir = tempfile::tempdir().unwrap();
    let mut cfg = config("b2", &dir.path().join("store"));
    cfg.metrics_listen = Some("127.0.0.1:0".parse().unwrap());
    let gw = start(cfg).await;
    let session = client(&gw.endpoint).await;
    let sub = session
        .declare_subscriber(key_corrected("b2", "new-1"))
        .await
        .unwrap();
    let publisher = session
        .declare_publisher(key_raw("b2", "new-1"))
        .await
        .unwrap();
    wait_matching(&publisher).await;
    for seq in 0..3 {
        publisher
            .put(raw("new-1", seq, vec![[0.1, -0.2, 0.98]; 50]))
            .await
            .unwrap();
    }
    for b in collect(&sub, 3).await {
        assert_eq!(b.info.mode, Mode::None);
        assert_eq!(b.info.calibration_version, 0);
        assert_eq!(b.batch_flags, flags::UNCALIBRATED);
        for s in &b.samples {
            assert_eq!(s.accel_mps2, [0.1, -0.2, 0.98], "raw values pass through");
            assert!(s.uncertainty_mps2.iter().all(|u| u.is_nan()));
            assert_eq!(s.flags, flags::UNCALIBRATED);
        }
    }
    let st = status(&session, "b2").await;
    let s = st
        .sensors
        .iter()
        .find(|s| s.sensor_id.as_str() == "new-1")
        .expect("sensor in status");
    assert_eq!(s.calibration_version, None);
    assert_eq!(s.mode, Mode::None);
    assert_eq!((s.batches, s.samples, s.flagged_samples), (3, 150, 150));
    assert!(s.last_seen.is_some());
    let page = metrics(gw.metrics.expect("metrics enabled")).await;
    assert!(
        page.contains("triax_sensor_uncalibrated_samples_total{sensor=\"new-1\"} 150"),
        "{page}"
    );
    assert!(
        page.contains("triax_gateway_uncalibrated_sensors 1"),
        "{page}"
    );
    session.close().await.unwrap();
    gw.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sensors_past_the_declared_key_budget_publish_undeclared() {
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("store");
    // Only calibrated sensors' keys are declared.
    seed_store(
        &store,
        &["u-1", "u-2", "u-3"].map(|id| sample::record(id, 1)),
    );
    let mut cfg = config("b8", &store);
    cfg.metrics_listen = Some("127.0.0.1:0".parse().unwrap());
    // Room for one sensor's two keys (a sensor's keys are declared together or not at all).
    cfg.declared_keys_max = 2;
    let gw = start(cfg).await;
    let session = client(&gw.endpoint).await;
    let sub = session
        .declare_subscriber("triax/b8/corrected/*")
        .await
        .unwrap();
    let ids = ["u-1", "u-2", "u-3"];
    // Two batches each; the first sensor takes the room, the others publish undeclared.
    for id in ids {
        let publisher = session.declare_publisher(key_raw("b8", id)).await.unwrap();
        wait_matching(&publisher).await;
        for seq in 0..2 {
            publisher
                .put(raw(id, seq, vec![[0.1, -0.2, 0.98]; 10]))
                .await
                .unwrap();
        }
    }
    let mut got: Vec<String> = collect(&sub, 6)
        .await
        .into_iter()
        .map(|b| b.header.sensor_id.to_string())
        .collect();
    got.sort();
    got.dedup();
    assert_eq!(got, ids, "declared or not, every sensor's stream arrives");
    let page = metrics(gw.metrics.expect("metrics enabled")).await;
    assert!(page.contains("triax_gateway_declared_keys 2\n"), "{page}");
    assert!(page.contains("triax_gateway_sensors_online 3\n"), "{page}");
    assert!(page.contains("process_resident_memory_bytes "), "{page}");
    session.close().await.unwrap();
    gw.stop().await;
}

/// Room for one sensor's two keys: the first sensor takes them; once it falls silent for
/// `declared_keys_idle`, it gives them back and the sensor that kept streaming undeclared
/// takes them, even with the two sensors on different workers.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn declared_keys_move_from_a_silent_sensor_to_a_streaming_one() {
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("store");
    seed_store(
        &store,
        &["silent", "streaming"].map(|id| sample::record(id, 1)),
    );
    let mut cfg = config("b8k", &store);
    cfg.declared_keys_max = 2;
    let idle = std::time::Duration::from_millis(3000);
    cfg.declared_keys_idle = idle;
    cfg.workers = 2;
    assert_ne!(
        triax_gateway::sample_path::shard("silent", 2),
        triax_gateway::sample_path::shard("streaming", 2),
        "the two sensors are meant for different workers"
    );
    let gw = start(cfg).await;
    let session = client(&gw.endpoint).await;
    // Calibrated: its keys are declared with its first batch.
    let send = |id: &'static str, seq: u64| {
        let session = session.clone();
        async move {
            session
                .put(
                    key_raw("b8k", id),
                    raw(id, seq, vec![[0.1, -0.2, 0.98]; 10]),
                )
                .await
                .unwrap();
        }
    };
    let declared = |id: &'static str| {
        let session = session.clone();
        async move {
            let st = status(&session, "b8k").await;
            st.sensors
                .iter()
                .find(|s| s.sensor_id.as_str() == id)
                .map(|s| s.keys_declared)
        }
    };
    let mut seq = 0;
    while declared("silent").await != Some(true) {
        send("silent", seq).await;
        seq += 1;
        assert!(seq < 2000, "the silent sensor never declared its keys");
        tokio::time::sleep(std::time::Duration::from_millis(2)).await;
    }
    let fell_silent = std::time::Instant::now();
    for i in 0..20 {
        send("streaming", i).await;
    }
    wait_until_async("the streaming sensor is seen", || async {
        declared("streaming").await.is_some()
    })
    .await;
    let streaming = declared("streaming").await;
    // Only while the first is not yet idle: on a stalled machine it may already have moved.
    if fell_silent.elapsed() < idle {
        assert_eq!(streaming, Some(false), "no room yet");
    }
    // The first falls silent; the second keeps streaming.
    let mut i = 20;
    let deadline = tokio::time::Instant::now() + TIMEOUT;
    while declared("streaming").await != Some(true) {
        assert!(
            tokio::time::Instant::now() < deadline,
            "the silent sensor's keys never went to the streaming one"
        );
        send("streaming", i).await;
        i += 1;
        tokio::time::sleep(std::time::Duration::from_millis(20)).await;
    }
    assert_eq!(declared("silent").await, Some(false));
    session.close().await.unwrap();
    gw.stop().await;
}

/// Room for one sensor's keys, two sensors streaming: rather than stay partly declared (the
/// slowest state), the gateway turns every key undeclared, and both streams go on.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn more_streaming_sensors_than_the_key_budget_turn_every_key_undeclared() {
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("store");
    seed_store(&store, &["one", "two"].map(|id| sample::record(id, 1)));
    let mut cfg = config("b8u", &store);
    cfg.declared_keys_max = 2;
    cfg.declared_keys_idle = std::time::Duration::from_millis(200);
    let gw = start(cfg).await;
    let session = client(&gw.endpoint).await;
    let sub = session
        .declare_subscriber("triax/b8u/corrected/*")
        .await
        .unwrap();
    let declared = |st: &GatewayStatus| {
        let mut d: Vec<(String, bool)> = st
            .sensors
            .iter()
            .map(|s| (s.sensor_id.to_string(), s.keys_declared))
            .collect();
        d.sort();
        d
    };
    let mut seq = 0;
    let mut seen_one_declared = false;
    let deadline = tokio::time::Instant::now() + TIMEOUT;
    loop {
        for id in ["one", "two"] {
            session
                .put(
                    key_raw("b8u", id),
                    raw(id, seq, vec![[0.1, -0.2, 0.98]; 10]),
                )
                .await
                .unwrap();
        }
        seq += 1;
        tokio::time::sleep(std::time::Duration::from_millis(20)).await;
        // Drained as it goes: a full subscriber channel would hold up this process's Zenoh.
        while sub.try_recv().ok().flatten().is_some() {}
        let d = declared(&status(&session, "b8u").await);
        seen_one_declared |= d.iter().filter(|(_, k)| *k).count() == 1;
        if seen_one_declared && d.len() == 2 && d.iter().all(|(_, k)| !k) {
            break;
        }
        assert!(
            tokio::time::Instant::now() < deadline,
            "never all undeclared (one declared first: {seen_one_declared}): {d:?}"
        );
    }
    // Both streams still arrive, undeclared.
    while sub.try_recv().ok().flatten().is_some() {}
    for id in ["one", "two"] {
        session
            .put(
                key_raw("b8u", id),
                raw(id, seq, vec![[0.1, -0.2, 0.98]; 10]),
            )
            .await
            .unwrap();
    }
    let mut got: Vec<String> = collect(&sub, 2)
        .await
        .into_iter()
        .map(|b| b.header.sensor_id.to_string())
        .collect();
    got.sort();
    assert_eq!(got, ["one", "two"]);
    session.close().await.unwrap();
    gw.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn shutdown_publishes_every_batch_already_received() {
    use std::sync::atomic::{AtomicU64, Ordering::Relaxed};
    use std::sync::Arc;
    let dir = tempfile::tempdir().unwrap();
    let cfg = config("b9", &dir.path().join("store"));
    let endpoint = cfg.zenoh.listen[0].clone();
    let gateway = triax_gateway::Gateway::start(cfg).await.unwrap();
    let counters = gateway.counters().clone();
    let session = client(&endpoint).await;
    // Counted as they come, so that a full subscriber queue never pushes back on the gateway.
    let got = Arc::new(AtomicU64::new(0));
    let g = got.clone();
    let _sub = session
        .declare_subscriber(key_corrected("b9", "burst"))
        .callback(move |_| {
            g.fetch_add(1, Relaxed);
        })
        .await
        .unwrap();
    // Block: the burst must reach the gateway whole, not be thinned in the client's queue.
    let publisher = blocking_publisher(&session, key_raw("b9", "burst")).await;
    let n = 400u64;
    for seq in 0..n {
        publisher
            .put(raw("burst", seq, vec![[0.1, -0.2, 0.98]; 100]))
            .await
            .unwrap();
    }
    wait_until("every batch taken from Zenoh", || {
        counters.received_batches.load(Relaxed) == n
    })
    .await;
    // Stop at once, with batches most likely still queued.
    gateway.run_until(async {}).await.unwrap();
    let published = counters.published_batches.load(Relaxed);
    let dropped = counters.dropped.load(Relaxed);
    assert_eq!(
        published + dropped,
        n,
        "every batch received is published or counted as dropped"
    );
    assert_eq!(
        dropped, 0,
        "the queue never overflowed, so nothing was dropped"
    );
    // The live stream drops for a consumer that cannot keep up; the history keeps everything.
    assert!(got.load(Relaxed) > 0);
    let mut h = triax_history::HistoryConfig::new(dir.path().join("store.history"));
    h.max_bytes = u64::MAX;
    let history = triax_history::History::open(h).unwrap().history;
    let mut scan = history
        .scan(&triax_history::Query::all(SensorId::new("burst").unwrap()))
        .unwrap();
    let mut kept = Vec::new();
    while let Some(b) = scan.next_block() {
        let b = b.unwrap();
        let block = triax_history::Block::decode(&b.bytes).unwrap();
        kept.extend(block.kept.iter().map(|k| k.sequence));
    }
    assert_eq!(
        kept,
        (0..n).collect::<Vec<_>>(),
        "every batch is in the history"
    );
    session.close().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn status_is_paged_and_bad_parameters_are_refused_by_name() {
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("store");
    seed_store(
        &store,
        &["p-a", "p-b", "p-c"].map(|id| sample::record(id, 1)),
    );
    let gw = start(config("b10", &store)).await;
    let session = client(&gw.endpoint).await;
    let ask = |parameters: &'static str| {
        let session = session.clone();
        async move {
            let selector = format!(
                "{}?{parameters}",
                Key::Status(BuildingId::new("b10").unwrap())
            );
            let replies = session.get(selector).timeout(TIMEOUT).await.unwrap();
            let reply = tokio::time::timeout(TIMEOUT, replies.recv_async())
                .await
                .expect("answered in time")
                .expect("a reply");
            match reply.result() {
                Ok(sample) => Ok(from_json::<GatewayStatus>(&sample.payload().to_bytes()).unwrap()),
                Err(e) => Err(String::from_utf8_lossy(&e.payload().to_bytes()).into_owned()),
            }
        }
    };
    let ids = |s: &GatewayStatus| -> Vec<String> {
        s.sensors.iter().map(|s| s.sensor_id.to_string()).collect()
    };
    let first = ask("limit=2").await.unwrap();
    assert_eq!(ids(&first), ["p-a", "p-b"]);
    assert_eq!((first.total_sensors, first.next_offset), (3, Some(2)));
    let last = ask("offset=2;limit=2").await.unwrap();
    assert_eq!(ids(&last), ["p-c"]);
    assert_eq!(last.next_offset, None);
    let one = ask("sensor=p-b").await.unwrap();
    assert_eq!(ids(&one), ["p-b"]);
    let refused = ask("limit=lots").await.unwrap_err();
    assert!(
        refused.contains("limit") && refused.contains("lots"),
        "{refused}"
    );
    session.close().await.unwrap();
    gw.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn malformed_payloads_are_counted_and_the_stream_goes_on() {
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("store");
    seed_store(&store, &[sample::record("acc-1", 1)]);
    let gw = start(config("b3", &store)).await;
    let session = client(&gw.endpoint).await;
    let sub = session
        .declare_subscriber(key_corrected("b3", "acc-1"))
        .await
        .unwrap();
    let publisher = session
        .declare_publisher(key_raw("b3", "acc-1"))
        .await
        .unwrap();
    wait_matching(&publisher).await;
    let good = |seq| raw("acc-1", seq, vec![[0.0, 0.0, 0.98]; 10]);
    publisher.put(good(0)).await.unwrap();
    publisher.put(b"not a batch".to_vec()).await.unwrap();
    let mut cut = good(1);
    cut.truncate(cut.len() - 5);
    publisher.put(cut).await.unwrap();
    // A valid batch of another sensor on this sensor's key.
    publisher
        .put(raw("acc-2", 1, vec![[0.0; 3]; 10]))
        .await
        .unwrap();
    // Longer than any raw batch can be: refused before it is copied.
    let mut long = raw(
        "acc-1",
        1,
        vec![[0.0; 3]; triax_protocol::batch::MAX_SAMPLES],
    );
    long.resize(triax_protocol::batch::MAX_RAW_BATCH_BYTES + 1, 0);
    publisher.put(long).await.unwrap();
    // Longer than the gateway's session reassembles: Zenoh drops it and keeps the link. Sent
    // blocking, so that it is not this client's own queue that drops it.
    session
        .put(
            key_raw("b3", "acc-1"),
            vec![0u8; triax_net::PUBLISHER_MAX_MESSAGE_BYTES as usize + 1],
        )
        .congestion_control(zenoh::qos::CongestionControl::Block)
        .await
        .unwrap();
    publisher.put(good(1)).await.unwrap();
    publisher.put(good(2)).await.unwrap();
    let batches = collect(&sub, 3).await;
    assert_eq!(
        batches
            .iter()
            .map(|b| b.header.sequence)
            .collect::<Vec<_>>(),
        [0, 1, 2]
    );
    assert!(batches.iter().all(|b| b.batch_flags == 0));
    let st = status(&session, "b3").await;
    assert_eq!(st.malformed, 4);
    let s = st
        .sensors
        .iter()
        .find(|s| s.sensor_id.as_str() == "acc-1")
        .unwrap();
    assert_eq!(
        (s.rejects, s.batches, s.calibration_version),
        (4, 3, Some(1))
    );
    session.close().await.unwrap();
    gw.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn gaps_and_duplicates_are_flagged_and_counted() {
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("store");
    seed_store(&store, &[sample::record("acc-1", 1)]);
    let gw = start(config("b4", &store)).await;
    let session = client(&gw.endpoint).await;
    let sub = session
        .declare_subscriber(key_corrected("b4", "acc-1"))
        .await
        .unwrap();
    let publisher = session
        .declare_publisher(key_raw("b4", "acc-1"))
        .await
        .unwrap();
    wait_matching(&publisher).await;
    let order = [0, 1, 3, 3, 2, 4];
    for seq in order {
        publisher
            .put(raw("acc-1", seq, vec![[0.0, 0.0, 0.98]; 10]))
            .await
            .unwrap();
    }
    let got: Vec<(u64, u16)> = collect(&sub, order.len())
        .await
        .iter()
        .map(|b| (b.header.sequence, b.batch_flags))
        .collect();
    assert_eq!(
        got,
        [
            (0, 0),
            (1, 0),
            (3, flags::SEQUENCE_GAP),
            (3, flags::DUPLICATE),
            (2, flags::DUPLICATE),
            (4, 0)
        ]
    );
    let st = status(&session, "b4").await;
    let s = &st.sensors[0];
    assert_eq!((s.gaps, s.missing_batches, s.duplicates), (1, 1, 2));
    assert_eq!(
        s.flagged_samples, 30,
        "the gap and duplicate batches' samples"
    );
    session.close().await.unwrap();
    gw.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn restart_keeps_calibrations() {
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("store");
    seed_store(
        &store,
        &[sample::record("acc-1", 1), sample::record("acc-1", 2)],
    );
    for run in 0..2 {
        let gw = start(config("b5", &store)).await;
        let session = client(&gw.endpoint).await;
        let sub = session
            .declare_subscriber(key_corrected("b5", "acc-1"))
            .await
            .unwrap();
        let publisher = session
            .declare_publisher(key_raw("b5", "acc-1"))
            .await
            .unwrap();
        wait_matching(&publisher).await;
        publisher
            .put(raw("acc-1", 0, vec![[0.0, 0.0, 0.98]; 10]))
            .await
            .unwrap();
        let b = &collect(&sub, 1).await[0];
        assert_eq!(b.info.calibration_version, 2, "run {run}");
        assert_eq!(b.info.mode, Mode::Dynamic);
        session.close().await.unwrap();
        // Stopping releases the store's lock, or the second start would fail.
        gw.stop().await;
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn split_mode_and_tilt_stream() {
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("store");
    // The sample record's static and dynamic gains differ by 2 %.
    let record = sample::record("incl-1", 1);
    seed_store(&store, std::slice::from_ref(&record));
    let mut cfg = config("b6", &store);
    cfg.sensors.insert(
        SensorId::new("incl-1").unwrap(),
        SensorSettings {
            mode: CorrectionMode::Split,
            tilt: true,
            tilt_interval_s: 0.5,
            ..SensorSettings::default()
        },
    );
    let gw = start(cfg).await;
    let session = client(&gw.endpoint).await;
    let sub = session
        .declare_subscriber(key_corrected("b6", "incl-1"))
        .await
        .unwrap();
    let tilt_sub = session
        .declare_subscriber(
            Key::Tilt(
                BuildingId::new("b6").unwrap(),
                SensorId::new("incl-1").unwrap(),
            )
            .to_string(),
        )
        .await
        .unwrap();
    let publisher = session
        .declare_publisher(key_raw("b6", "incl-1"))
        .await
        .unwrap();
    wait_matching(&publisher).await;

    let (roll, pitch) = (2f64.to_radians(), (-1f64).to_radians());
    let g = 9.81;
    let gravity = [
        g * pitch.sin(),
        g * pitch.cos() * roll.sin(),
        g * pitch.cos() * roll.cos(),
    ];
    let sway = |t: f64| {
        [
            0.3 * (2.0 * PI * 3.0 * t).sin(),
            0.2 * (2.0 * PI * 4.0 * t).cos(),
            0.0,
        ]
    };
    let zero = [0.0; 3];
    // 20 s: the tilt low pass settles from its start in 10.4 s before its first sample.
    let n_batches = 40u64;
    for seq in 0..n_batches {
        let samples = (0..50)
            .map(|i| {
                let t = (seq * 50 + i) as f64 / 100.0;
                // Gravity through the static sensitivity, sway through the dynamic one.
                let vs = outputs(
                    &record.static_set.sensitivity,
                    &record.static_set.offset,
                    gravity,
                );
                let vd = outputs(&record.dynamic.sensitivity, &zero, sway(t));
                [0, 1, 2].map(|k| (vs[k] + vd[k]) as f32)
            })
            .collect();
        publisher.put(raw("incl-1", seq, samples)).await.unwrap();
    }
    let batches = collect(&sub, n_batches as usize).await;
    for (seq, b) in batches.iter().enumerate().skip(4) {
        assert_eq!(b.info.mode, Mode::Split);
        for (i, s) in b.samples.iter().enumerate() {
            let w = sway((seq * 50 + i) as f64 / 100.0);
            for k in 0..3 {
                let truth = gravity[k] + w[k];
                let err = (f64::from(s.accel_mps2[k]) - truth).abs();
                assert!(
                    err <= 2.0 * f64::from(s.uncertainty_mps2[k]),
                    "batch {seq} sample {i} axis {k}: error {err}"
                );
            }
        }
    }
    // Tilt every 0.5 s of sensor time once settled, each describing the instant 2.25 s (the
    // low pass's delay) before its last sample: wait for the one made at the stream's end.
    let stream_end_ns = 1_800_000_000_000_000_000 + n_batches as i64 * 500_000_000;
    let mut tilts: Vec<TiltSample> = Vec::new();
    while tilts
        .last()
        .is_none_or(|t| t.timestamp_ns < stream_end_ns - 3_000_000_000)
    {
        let s = tokio::time::timeout(TIMEOUT, tilt_sub.recv_async())
            .await
            .expect("the tilt stream reaches the end of the raw stream in time")
            .unwrap();
        tilts.push(from_json::<TiltSample>(&s.payload().to_bytes()).expect("tilt decodes"));
    }
    assert!(tilts.len() >= 16, "{} tilt samples", tilts.len());
    let last = tilts.last().unwrap();
    assert_eq!(last.calibration_version, 1);
    assert!(last.roll_uncertainty_deg > 0.0 && last.roll_uncertainty_deg < 0.5);
    assert!(
        (last.roll_deg - 2.0).abs() <= 2.0 * last.roll_uncertainty_deg,
        "{last:?}"
    );
    assert!(
        (last.pitch_deg + 1.0).abs() <= 2.0 * last.pitch_uncertainty_deg,
        "{last:?}"
    );
    session.close().await.unwrap();
    gw.stop().await;
}
