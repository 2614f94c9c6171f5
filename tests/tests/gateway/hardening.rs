//! What a hostile or careless sender can make a gateway do: puts on wildcard key expressions
//! (which reach the raw subscription of every building they intersect), numbering that jumps by
//! 10¹⁹, and floods of new sensor ids.
//!
//! - `wildcard_and_foreign_keys_are_refused_in_every_building`: two buildings' gateways, one
//!   attacker; every wildcard put is counted by reason in both and published by neither, and a
//!   real sensor's stream and counters are untouched by puts aimed at it through wildcards.
//! - `a_numbering_jump_counts_only_what_the_clock_allows`
//! - `a_flood_of_new_ids_cannot_lock_out_a_real_node_and_ages_out`
//! - `streaming_resumes_after_a_router_restart_and_the_lost_stretch_is_a_gap`: gateway, node and
//!   consumer all clients of a real `zenohd` that is killed and started again.

use std::sync::atomic::{AtomicU64, Ordering::Relaxed};
use std::sync::Arc;
use std::time::Duration;

use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use triax_protocol::batch::{flags, CorrectedBatch, RawBatch};
use triax_protocol::record::sample;

use super::status;
use crate::util::*;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn wildcard_and_foreign_keys_are_refused_in_every_building() {
    let dir = tempfile::tempdir().unwrap();
    let store_a = dir.path().join("a");
    seed_store(&store_a, &[sample::record("good-01", 1)]);
    let gw_a = start(config("ha", &store_a)).await;
    let mut cfg_b = config("hb", &dir.path().join("b"));
    cfg_b.zenoh.connect = vec![gw_a.endpoint.clone()];
    let gw_b = start(cfg_b).await;
    let session = client_of(&[&gw_a.endpoint, &gw_b.endpoint]).await;

    let published = Arc::new(std::sync::Mutex::new(Vec::<CorrectedBatch>::new()));
    let p = published.clone();
    // Remote only: the attacker's own puts on `**/wF` and the like intersect this subscription.
    let _sub = session
        .declare_subscriber("triax/*/corrected/*")
        .allowed_origin(zenoh::sample::Locality::Remote)
        .callback(move |s| {
            let b = CorrectedBatch::decode(&s.payload().to_bytes()).expect("decodes");
            p.lock().unwrap().push(b);
        })
        .await
        .unwrap();
    // The real sensor streams in order; its subscription is matched first.
    let good = session
        .declare_publisher(key_raw("ha", "good-01"))
        .await
        .unwrap();
    wait_matching(&good).await;
    for b in ["ha", "hb"] {
        assert_eq!(status(&session, b).await.building.as_str(), b);
    }

    let wild = [
        "triax/*/raw/wA",
        "**/raw/wB",
        "triax/hb/*/wC",
        "triax/**/wE",
        "**/wF",
        "triax/*/raw/good-01",
        "triax/ha/raw/*",
    ];
    let mut rng = StdRng::seed_from_u64(13);
    let n_good = 20u64;
    for seq in 0..n_good {
        good.put(raw("good-01", seq, vec![[0.1, -0.2, 0.98]; 10]))
            .await
            .unwrap();
        for key in wild {
            let sensor = key.rsplit('/').next().unwrap();
            let sensor = if sensor.contains('*') { "wX" } else { sensor };
            let mut batch = RawBatch::decode(&raw(sensor, 0, vec![[1.0, 2.0, 3.0]; 10])).unwrap();
            batch.header.sequence = rng.gen();
            session.put(key, batch.encode()).await.unwrap();
        }
    }
    // Gateway `ha` also sees puts addressed to building hb by name through its own subscription
    // only if they intersect it; a concrete key of hb never does. Wait until every wildcard put
    // that reaches each gateway is counted.
    let refused = |b: &'static str, expected: u64| {
        let session = session.clone();
        async move {
            wait_until_async(
                &format!("{b} to refuse {expected} wildcard puts"),
                || async {
                    status(&session, b)
                        .await
                        .refused_keys
                        .get("wildcard")
                        .copied()
                        == Some(expected)
                },
            )
            .await;
        }
    };
    // Each wildcard key above intersects `triax/ha/raw/*` except `triax/hb/*/wC`; all of them
    // intersect `triax/hb/raw/*` except `triax/ha/raw/*`.
    refused("ha", n_good * 6).await;
    refused("hb", n_good * 6).await;
    wait_until("the real sensor's batches", || {
        published.lock().unwrap().len() as u64 >= n_good
    })
    .await;
    // Room for anything wrongly published to arrive.
    tokio::time::sleep(Duration::from_millis(300)).await;
    let got = published.lock().unwrap().clone();
    assert_eq!(
        got.len() as u64,
        n_good,
        "only the real sensor's batches are published: {:?}",
        got.iter()
            .map(|b| b.header.sensor_id.to_string())
            .collect::<Vec<_>>()
    );
    for (seq, b) in got.iter().enumerate() {
        assert_eq!(b.header.sensor_id.as_str(), "good-01");
        assert_eq!(b.header.sequence, seq as u64);
        assert_eq!(b.batch_flags & flags::SEQUENCE_GAP, 0);
    }
    let st = status(&session, "ha").await;
    let good_status = st
        .sensors
        .iter()
        .find(|s| s.sensor_id.as_str() == "good-01")
        .expect("good-01 listed");
    assert_eq!(
        (
            good_status.batches,
            good_status.gaps,
            good_status.missing_batches
        ),
        (n_good, 0, 0)
    );
    assert_eq!(st.total_sensors, 1, "no wildcard put made a sensor");
    assert_eq!(status(&session, "hb").await.total_sensors, 0);
    session.close().await.unwrap();
    gw_b.stop().await;
    gw_a.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_numbering_jump_counts_only_what_the_clock_allows() {
    let dir = tempfile::tempdir().unwrap();
    let gw = start(config("hj", &dir.path().join("store"))).await;
    let session = client(&gw.endpoint).await;
    let sub = session
        .declare_subscriber(key_corrected("hj", "j-1"))
        .await
        .unwrap();
    let publisher = session
        .declare_publisher(key_raw("hj", "j-1"))
        .await
        .unwrap();
    wait_matching(&publisher).await;
    // `raw` times batch s at s × 0.1 s: batch 3 follows batch 0 after two lost batches by the
    // clock, and the numbering says 10¹⁹.
    let batch = |seq: u64, at: u64| {
        let mut b = RawBatch::decode(&raw("j-1", at, vec![[0.0; 3]; 10])).unwrap();
        b.header.sequence = seq;
        b.encode()
    };
    publisher.put(batch(0, 0)).await.unwrap();
    publisher.put(batch(u64::MAX - 7, 3)).await.unwrap();
    publisher.put(batch(u64::MAX - 6, 4)).await.unwrap();
    let got = collect(&sub, 3).await;
    assert_eq!(
        got[1].batch_flags & flags::SEQUENCE_GAP,
        flags::SEQUENCE_GAP
    );
    assert_eq!(got[2].batch_flags & flags::SEQUENCE_GAP, 0);
    let st = status(&session, "hj").await;
    let s = &st.sensors[0];
    assert_eq!(
        (s.gaps, s.missing_batches),
        (1, 2 + 1),
        "two by the clock, plus one for jitter"
    );
    session.close().await.unwrap();
    gw.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_flood_of_new_ids_cannot_lock_out_a_real_node_and_ages_out() {
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("store");
    seed_store(&store, &[sample::record("cal-1", 1)]);
    let mut cfg = config("hf", &store);
    cfg.max_sensors = 1000;
    // Long enough that the real node, silent while the checks below run, is not forgotten.
    cfg.unknown_sensor_expiry = Duration::from_secs(5);
    let gw = start(cfg).await;
    let session = client(&gw.endpoint).await;
    let real = Arc::new(AtomicU64::new(0));
    let cal = Arc::new(AtomicU64::new(0));
    // Only the two real nodes' streams: the flood's own corrected batches would crowd this
    // consumer's link, and the gateway drops for a consumer that cannot keep up.
    let mut subs = Vec::new();
    for (sensor, n) in [("real-node", real.clone()), ("cal-1", cal.clone())] {
        subs.push(
            session
                .declare_subscriber(key_corrected("hf", sensor))
                .callback(move |_| {
                    n.fetch_add(1, Relaxed);
                })
                .await
                .unwrap(),
        );
    }
    let node = blocking_publisher(&session, key_raw("hf", "real-node")).await;
    let calibrated = blocking_publisher(&session, key_raw("hf", "cal-1")).await;
    let n_flood = 8000u64;
    let mut sent = 0;
    for i in 0..n_flood {
        // Each flood id sends one batch and is never heard again.
        let id = format!("flood-{i}");
        session
            .put(key_raw("hf", &id), raw(&id, 0, vec![[0.0; 3]; 1]))
            .congestion_control(zenoh::qos::CongestionControl::Block)
            .await
            .unwrap();
        // The real nodes speak once the table is full of flood ids: every 100 flood batches, as
        // a node sending ten batches a second would amid 1000 new ids a second. A worker may
        // lag another by its queue, so the margin to the table's size is wide.
        if i >= 2000 && i % 100 == 0 {
            node.put(raw("real-node", sent, vec![[0.1, 0.2, 9.8]; 10]))
                .await
                .unwrap();
            calibrated
                .put(raw("cal-1", sent, vec![[0.1, 0.2, 9.8]; 10]))
                .await
                .unwrap();
            sent += 1;
        }
    }
    let arrived = || (real.load(Relaxed), cal.load(Relaxed));
    let deadline = tokio::time::Instant::now() + TIMEOUT;
    while arrived() != (sent, sent) && tokio::time::Instant::now() < deadline {
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    assert_eq!(
        arrived(),
        (sent, sent),
        "every batch of the real nodes arrives"
    );
    // The real nodes' last batches may overtake the flood's last ones on another worker: wait
    // until every id sent has been seen, admitted or refused, before counting what became of them.
    wait_until_async("every flood id to be judged", || async {
        let st = status(&session, "hf").await;
        st.admitted_sensors + st.over_capacity > n_flood
    })
    .await;
    let st = status(&session, "hf").await;
    assert_eq!(
        st.admitted_sensors,
        n_flood + 1,
        "every flood id and the real node"
    );
    assert!(st.total_sensors <= 1000, "{} sensors", st.total_sensors);
    assert_eq!(
        st.over_capacity, 0,
        "nobody was refused: flood ids displace each other"
    );
    // Every flood id admitted has gone again, displaced by a newer one or, when the flood took
    // longer than the expiry on a slow machine, aged out: how many of each depends on the pace.
    assert!(
        st.displaced_sensors + st.expired_sensors >= n_flood + 1 - 1000,
        "displaced {}, expired {}",
        st.displaced_sensors,
        st.expired_sensors
    );
    // The real node speaks once more, so that its status is read well within the expiry.
    node.put(raw("real-node", sent, vec![[0.1, 0.2, 9.8]; 10]))
        .await
        .unwrap();
    wait_until_async("the real node's last batch", || async {
        real.load(Relaxed) == sent + 1
    })
    .await;
    let node_status = status_of(&session, "hf", "real-node").await;
    assert_eq!(
        node_status.batches,
        sent + 1,
        "the real node kept its entry and counters"
    );
    // Silence: what the flood admitted ages out; the calibrated sensor stays.
    wait_until_async("the flood's entries to expire", || async {
        status(&session, "hf").await.total_sensors == 1
    })
    .await;
    let st = status(&session, "hf").await;
    assert_eq!(st.sensors[0].sensor_id.as_str(), "cal-1");
    assert!(st.expired_sensors >= 1, "{}", st.expired_sensors);
    session.close().await.unwrap();
    gw.stop().await;
}

/// The status of one sensor.
async fn status_of(
    session: &zenoh::Session,
    b: &str,
    sensor: &str,
) -> triax_protocol::messages::SensorStatus {
    status(session, b)
        .await
        .sensors
        .into_iter()
        .find(|s| s.sensor_id.as_str() == sensor)
        .unwrap_or_else(|| panic!("{sensor} listed in {b}'s status"))
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn streaming_resumes_after_a_router_restart_and_the_lost_stretch_is_a_gap() {
    let mut router = Router::start().await;
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("store");
    seed_store(&store, &[sample::record("rr-1", 1)]);
    let mut cfg = config("rr", &store);
    cfg.zenoh = router.client_settings();
    let gw = start(cfg).await;
    let open = || async {
        zenoh::open(router.client_settings().to_config().unwrap())
            .await
            .unwrap()
    };
    let node = open().await;
    let consumer = open().await;
    let sub = consumer
        .declare_subscriber(key_corrected("rr", "rr-1"))
        .await
        .unwrap();
    let publisher = blocking_publisher(&node, key_raw("rr", "rr-1")).await;
    let got = Arc::new(std::sync::Mutex::new(Vec::<CorrectedBatch>::new()));
    let collector = {
        let got = got.clone();
        tokio::spawn(async move {
            while let Ok(s) = sub.recv_async().await {
                let b = CorrectedBatch::decode(&s.payload().to_bytes()).expect("decodes");
                got.lock().unwrap().push(b);
            }
        })
    };
    let seq = Arc::new(AtomicU64::new(0));
    let node_task = {
        let seq = seq.clone();
        tokio::spawn(async move {
            loop {
                let s = seq.fetch_add(1, Relaxed);
                // While the router is down the put fails or goes nowhere: that is the loss.
                let _ = publisher
                    .put(raw("rr-1", s, vec![[0.1, -0.2, 0.98]; 5]))
                    .await;
                tokio::time::sleep(Duration::from_millis(50)).await;
            }
        })
    };
    let received = |got: &Arc<std::sync::Mutex<Vec<CorrectedBatch>>>| got.lock().unwrap().len();
    wait_until("the stream flows through the router", || {
        received(&got) >= 10
    })
    .await;

    router.restart_after(Duration::from_secs(2)).await;
    let restarted_at = seq.load(Relaxed);
    let resumed = tokio::time::Instant::now();
    let deadline = resumed + TIMEOUT;
    loop {
        let last = got.lock().unwrap().last().map(|b| b.header.sequence);
        if last.is_some_and(|s| s >= restarted_at + 20) {
            break;
        }
        assert!(
            tokio::time::Instant::now() < deadline,
            "streaming did not resume within {TIMEOUT:?} of the router's restart (last {last:?})"
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    println!(
        "streaming resumed {:.1} s after the router came back",
        resumed.elapsed().as_secs_f64()
    );
    node_task.abort();
    let batches = got.lock().unwrap().clone();
    let seqs: Vec<u64> = batches.iter().map(|b| b.header.sequence).collect();
    let missing: u64 = seqs.windows(2).map(|w| w[1] - w[0] - 1).sum();
    assert!(
        missing > 0,
        "a 2 s outage lost nothing downstream? {seqs:?}"
    );
    // The gateway saw the node's lost stretch as a gap and flagged the batch after it. The
    // consumer may have missed that very batch (the gateway published it before the consumer's
    // own link was back): the history has it, as every batch the gateway took.
    wait_history_holds(&consumer, "rr", "rr-1", *seqs.last().unwrap()).await;
    let st = status(&consumer, "rr").await;
    let sensor = st
        .sensors
        .iter()
        .find(|s| s.sensor_id.as_str() == "rr-1")
        .unwrap();
    assert!(sensor.gaps >= 1, "{sensor:?}");
    let request = triax_client::HistoryRequest::sensor(
        &triax_protocol::BuildingId::new("rr").unwrap(),
        &triax_protocol::SensorId::new("rr-1").unwrap(),
    );
    let mut kept = Vec::new();
    triax_client::history::fetch(&consumer, &request, TIMEOUT, &mut |r| kept.push(r.batch))
        .await
        .expect("history answered");
    let kept_seqs: Vec<u64> = kept.iter().map(|b| b.header.sequence).collect();
    let flagged: Vec<u64> = kept
        .iter()
        .filter(|b| b.batch_flags & flags::SEQUENCE_GAP != 0)
        .map(|b| b.header.sequence)
        .collect();
    assert_eq!(flagged.len() as u64, sensor.gaps, "{kept_seqs:?}");
    let node_lost: u64 = kept_seqs.windows(2).map(|w| w[1] - w[0] - 1).sum();
    assert!(
        node_lost > 0,
        "the node lost nothing while the router was down? {kept_seqs:?}"
    );
    assert_eq!(sensor.missing_batches, node_lost, "{sensor:?}");
    for s in &flagged {
        let i = kept_seqs.iter().position(|k| k == s).unwrap();
        assert!(
            i > 0 && kept_seqs[i - 1] + 1 < *s,
            "flag {s} not after a hole: {kept_seqs:?}"
        );
    }
    collector.abort();
    node.close().await.unwrap();
    consumer.close().await.unwrap();
    gw.stop().await;
}
