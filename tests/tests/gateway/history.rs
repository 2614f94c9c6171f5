//! The history through a real gateway: what a consumer reads back is what the live stream
//! carried, byte for byte; a recalibration is replayed with the record in force or the latest;
//! a consumer that was away or slow loses nothing; retention holds the size cap.
//!
//! - `replay_in_force_is_byte_for_byte_the_live_stream`: split mode with tilt, the frequency
//!   detector, gaps and a duplicate, over three minutes of signal (three checkpoints); the
//!   history's answer for a range starting mid-way equals the live batches.
//! - `a_recalibration_is_replayed_in_force_or_with_the_latest`
//! - `a_follower_loses_nothing_across_an_outage`: twenty sensors; a follower stops for a while
//!   and resumes from its last sequence numbers; together its two runs handed over exactly what
//!   an uninterrupted follower did, once each, in order, byte for byte.
//! - `a_sensor_that_falls_silent_while_the_follower_is_stalled_is_caught_up`: the heartbeats
//!   that named its last batches were lost with them; a jump in their numbering makes the
//!   follower read on from where every sensor not named was left (issue 27).
//! - `a_node_that_restarts_its_numbering_is_followed_by_time`: a follower stalled across a node
//!   restart hands over the old run's tail and the new run's start once each, in order, and a
//!   follower resumed from a saved position goes on from the right run (issue 27).
//! - `retention_holds_the_size_cap_and_counts_what_it_deleted`
//! - `bad_history_queries_are_refused_by_name`
//! - `a_version_number_over_a_wildcard_is_refused_whole`: one sensor without the version makes
//!   the whole query one error, with no batches of the sensors that have it.
//! - `the_history_survives_kill_9_within_its_durability_rule`: a gateway in a process of its own
//!   killed four times mid-stream; every batch published more than 1.5 s before a kill is kept.
//! - `a_consumer_beyond_the_site_router_recovers_a_30_s_cut`: a real `zenohd` between the
//!   building and a follower, stopped for 30 s.

use std::collections::BTreeMap;
use std::f64::consts::PI;
use std::sync::atomic::Ordering::Relaxed;
use std::time::Duration;

use triax_client::follow::Position;
use triax_client::{history::fetch, Delivery, FollowOptions, Follower, HistoryRequest};
use triax_gateway::{CorrectionMode, SensorSettings};
use triax_protocol::batch::{flags, BatchHeader, CorrectedBatch, RawBatch};
use triax_protocol::messages::Heartbeat;
use triax_protocol::messages::{PushAck, PushOutcome};
use triax_protocol::record::sample;
use triax_protocol::signing::{sign, LabSigningKey};
use triax_protocol::{from_json, to_json, BuildingId, Key, SensorId};

use super::status;
use crate::util::*;

fn b(id: &str) -> BuildingId {
    BuildingId::new(id).unwrap()
}

fn s(id: &str) -> SensorId {
    SensorId::new(id).unwrap()
}

/// Batch `seq` of a 100 Hz node sending `n` samples a batch: sway at 1.3 Hz, a slow tilt, and
/// from batch 100 on a 30 Hz vibration the record's band does not cover.
fn swaying(sensor: &str, seq: u64, n: usize) -> Vec<u8> {
    let samples = (0..n)
        .map(|i| {
            let t = (seq as usize * n + i) as f64 / 100.0;
            let vib = if seq >= 100 {
                0.3 * (2.0 * PI * 30.0 * t).sin()
            } else {
                0.0
            };
            [
                (0.2 * (2.0 * PI * 1.3 * t).sin() + vib) as f32,
                (0.01 * t / 100.0) as f32,
                (0.981 + 0.001 * (2.0 * PI * 0.05 * t).sin()) as f32,
            ]
        })
        .collect();
    raw(sensor, seq, samples)
}

/// Every batch of one history query, in the order the gateway sent them.
async fn read_history(session: &zenoh::Session, request: &HistoryRequest) -> Vec<Vec<u8>> {
    let mut out = Vec::new();
    fetch(session, request, TIMEOUT, &mut |r| out.push(r.payload))
        .await
        .expect("history query answered");
    out
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn replay_in_force_is_byte_for_byte_the_live_stream() {
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("store");
    seed_store(&store, &[sample::record("incl", 1)]);
    let mut cfg = config("hr", &store);
    cfg.sensors.insert(
        s("incl"),
        SensorSettings {
            mode: CorrectionMode::Split,
            tilt: true,
            ..SensorSettings::default()
        },
    );
    let gw = start(cfg).await;
    let session = client(&gw.endpoint).await;
    let sub = session
        .declare_subscriber(key_corrected("hr", "incl"))
        .with(zenoh::handlers::FifoChannel::new(10_000))
        .await
        .unwrap();
    let publisher = blocking_publisher(&session, key_raw("hr", "incl")).await;
    // 180 batches of one second; 20–22 lost, 50 sent twice. Paced so that the live subscriber
    // keeps up: this test compares it with the history.
    let mut sent = 0;
    for seq in 0..180u64 {
        if (20..=22).contains(&seq) {
            continue;
        }
        publisher.put(swaying("incl", seq, 100)).await.unwrap();
        sent += 1;
        if seq == 50 {
            publisher.put(swaying("incl", seq, 100)).await.unwrap();
            sent += 1;
        }
        tokio::time::sleep(Duration::from_millis(2)).await;
    }
    let mut live = Vec::new();
    while live.len() < sent {
        let s = tokio::time::timeout(TIMEOUT, sub.recv_async())
            .await
            .expect("live batches in time")
            .unwrap();
        live.push(s.payload().to_bytes().to_vec());
    }
    let decoded: Vec<CorrectedBatch> = live
        .iter()
        .map(|p| CorrectedBatch::decode(p).unwrap())
        .collect();
    // The stream exercises what the replay must reproduce.
    assert!(decoded
        .iter()
        .any(|b| b.batch_flags & flags::SEQUENCE_GAP != 0));
    assert!(decoded
        .iter()
        .any(|b| b.batch_flags & flags::DUPLICATE != 0));
    assert!(decoded
        .iter()
        .any(|b| b.batch_flags & flags::OUTSIDE_FREQUENCY != 0));
    let last = decoded.last().unwrap().header.sequence;
    wait_history_holds(&session, "hr", "incl", last).await;
    // A range starting two and a half minutes in, past two checkpoints.
    let from_ns = decoded[150].header.timestamp_ns;
    let mut request = HistoryRequest::sensor(&b("hr"), &s("incl"));
    request.from_ns = Some(from_ns);
    let kept = read_history(&session, &request).await;
    let wanted: Vec<&Vec<u8>> = live
        .iter()
        .zip(&decoded)
        .filter(|(_, d)| d.header.timestamp_ns >= from_ns)
        .map(|(p, _)| p)
        .collect();
    assert_eq!(kept.len(), wanted.len());
    for (i, (k, w)) in kept.iter().zip(wanted).enumerate() {
        assert_eq!(k, w, "batch {i} of the range differs from the live stream");
    }
    // And the whole stream, from the first checkpoint.
    let all = read_history(&session, &HistoryRequest::sensor(&b("hr"), &s("incl"))).await;
    assert_eq!(all, live);
    session.close().await.unwrap();
    gw.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_recalibration_is_replayed_in_force_or_with_the_latest() {
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("store");
    seed_store(&store, &[sample::record("rc", 1)]);
    let key = LabSigningKey::from_bytes(&[9; 32]);
    let mut cfg = config("hc", &store);
    cfg.calibration.trusted_lab_keys = vec![key.verifying_key()];
    let gw = start(cfg).await;
    let session = client(&gw.endpoint).await;
    let publisher = blocking_publisher(&session, key_raw("hc", "rc")).await;
    let push = |version: u64| {
        let session = session.clone();
        let mut record = sample::record("rc", version);
        record.dynamic.offset[0] += 0.5;
        let signed = to_json(&sign(&record, &key));
        async move {
            let replies = session
                .get(Key::CalibrationPush(b("hc"), s("rc")).to_string())
                .payload(signed)
                .timeout(TIMEOUT)
                .await
                .unwrap();
            let reply = replies.recv_async().await.unwrap();
            let ack: PushAck = from_json(&reply.result().unwrap().payload().to_bytes()).unwrap();
            assert!(
                matches!(ack.outcome, PushOutcome::Accepted { .. }),
                "{ack:?}"
            );
        }
    };
    for seq in 0..20 {
        publisher.put(swaying("rc", seq, 50)).await.unwrap();
    }
    // Every batch so far is kept before the new version goes in.
    wait_until_async("20 batches kept", || async {
        status(&session, "hc")
            .await
            .history
            .is_some_and(|h| h.written_batches == 20)
    })
    .await;
    push(2).await;
    for seq in 20..40 {
        publisher.put(swaying("rc", seq, 50)).await.unwrap();
    }
    let versions = |payloads: &[Vec<u8>]| -> Vec<u64> {
        payloads
            .iter()
            .map(|p| CorrectedBatch::decode(p).unwrap().info.calibration_version)
            .collect()
    };
    let mut request = HistoryRequest::sensor(&b("hc"), &s("rc"));
    wait_until_async("40 batches kept", || async {
        status(&session, "hc")
            .await
            .history
            .is_some_and(|h| h.written_batches == 40)
    })
    .await;
    wait_history_holds(&session, "hc", "rc", 39).await;
    let in_force = read_history(&session, &request).await;
    assert_eq!(versions(&in_force), [[1u64; 20], [2; 20]].concat());
    request.calibration = Some("latest".into());
    let latest = read_history(&session, &request).await;
    assert_eq!(versions(&latest), [2u64; 40]);
    // Corrected again with version 2, the first twenty batches move by its offset.
    let a = |p: &Vec<u8>| CorrectedBatch::decode(p).unwrap().samples[0].accel_mps2[0];
    assert!((a(&latest[0]) - a(&in_force[0]) - 0.5).abs() < 1e-5);
    assert_eq!(
        latest[20..],
        in_force[20..],
        "the same record gives the same bytes"
    );
    request.calibration = Some("1".into());
    assert_eq!(
        versions(&read_history(&session, &request).await),
        [1u64; 40]
    );
    request.calibration = Some("7".into());
    let err = fetch(&session, &request, TIMEOUT, &mut |_| {})
        .await
        .unwrap_err()
        .to_string();
    assert!(err.contains("no version 7"), "{err}");
    session.close().await.unwrap();
    gw.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_follower_loses_nothing_across_an_outage() {
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("store");
    let ids: Vec<String> = (0..20).map(|i| format!("f-{i:02}")).collect();
    seed_store(
        &store,
        &ids.iter()
            .map(|id| sample::record(id, 1))
            .collect::<Vec<_>>(),
    );
    let gw = start(config("hf2", &store)).await;
    let (node, consumer) = (client(&gw.endpoint).await, client(&gw.endpoint).await);
    let mut steady = Follower::start(&consumer, FollowOptions::new(b("hf2")))
        .await
        .unwrap();
    let mut away = Follower::start(&consumer, FollowOptions::new(b("hf2")))
        .await
        .unwrap();
    let mut publishers = Vec::new();
    for id in &ids {
        publishers.push(blocking_publisher(&node, key_raw("hf2", id)).await);
    }
    let rounds = 60u64;
    let stream = tokio::spawn(async move {
        for seq in 0..rounds {
            for (id, p) in ids.iter().zip(&publishers) {
                p.put(swaying(id, seq, 10)).await.unwrap();
            }
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
        publishers
    });
    let total = 20 * rounds as usize;
    // The away follower takes a second's worth, then stops (its consumer restarts).
    let mut got_away: Vec<Vec<u8>> = Vec::new();
    let mut last: BTreeMap<SensorId, u64> = BTreeMap::new();
    while got_away.len() < 200 {
        let d = tokio::time::timeout(TIMEOUT, away.next())
            .await
            .unwrap()
            .unwrap();
        last.insert(d.batch.header.sensor_id.clone(), d.batch.header.sequence);
        got_away.push(d.payload);
    }
    drop(away);
    tokio::time::sleep(Duration::from_secs(1)).await;
    let mut options = FollowOptions::new(b("hf2"));
    options.resume_after = last;
    let mut back = Follower::start(&consumer, options).await.unwrap();
    let mut got_steady = Vec::new();
    while got_steady.len() < total {
        let d = tokio::time::timeout(TIMEOUT, steady.next())
            .await
            .unwrap()
            .unwrap();
        got_steady.push(d.payload);
    }
    while got_away.len() < total {
        let d = tokio::time::timeout(TIMEOUT, back.next())
            .await
            .unwrap()
            .unwrap();
        got_away.push(d.payload);
    }
    stream.await.unwrap();
    assert!(
        back.counters().recovered.load(Relaxed) > 0,
        "the outage was read from the history"
    );
    // Per sensor, both hold the same batches in the same order.
    fn per_sensor(all: &[Vec<u8>]) -> BTreeMap<String, Vec<&Vec<u8>>> {
        let mut m: BTreeMap<String, Vec<&Vec<u8>>> = BTreeMap::new();
        for p in all {
            let h = CorrectedBatch::decode(p).unwrap().header;
            m.entry(h.sensor_id.to_string()).or_default().push(p);
        }
        m
    }
    let (a, c) = (per_sensor(&got_steady), per_sensor(&got_away));
    assert_eq!(a.len(), 20);
    for (sensor, batches) in &a {
        let seqs: Vec<u64> = batches
            .iter()
            .map(|p| CorrectedBatch::decode(p).unwrap().header.sequence)
            .collect();
        assert_eq!(
            seqs,
            (0..rounds).collect::<Vec<_>>(),
            "{sensor}: once each, in order"
        );
        assert_eq!(
            Some(batches),
            c.get(sensor),
            "{sensor}: the same bytes after the outage"
        );
    }
    drop((steady, back));
    node.close().await.unwrap();
    consumer.close().await.unwrap();
    gw.stop().await;
}

/// Deliveries per sensor: position and payload, in the order handed over.
#[derive(Default)]
struct Handed(BTreeMap<String, Vec<(u64, i64, Vec<u8>)>>);

impl Handed {
    fn take(&mut self, d: &Delivery) {
        let h = &d.batch.header;
        self.0.entry(h.sensor_id.to_string()).or_default().push((
            h.sequence,
            h.timestamp_ns,
            d.payload.clone(),
        ));
    }

    fn count(&self, sensor: &str) -> usize {
        self.0.get(sensor).map_or(0, Vec::len)
    }

    fn sequences(&self, sensor: &str) -> Vec<u64> {
        self.0
            .get(sensor)
            .map(|v| v.iter().map(|(s, _, _)| *s).collect())
            .unwrap_or_default()
    }
}

/// Hands over from `follower` until `done` holds of what was handed over.
async fn follow_until(
    follower: &mut Follower,
    handed: &mut Handed,
    done: impl Fn(&Handed) -> bool,
) {
    while !done(handed) {
        let Ok(d) = tokio::time::timeout(TIMEOUT, follower.next()).await else {
            let so_far: BTreeMap<&String, (usize, usize)> = handed
                .0
                .iter()
                .map(|(s, v)| {
                    let distinct: std::collections::BTreeSet<(u64, i64)> =
                        v.iter().map(|(q, t, _)| (*q, *t)).collect();
                    (s, (v.len(), distinct.len()))
                })
                .collect();
            panic!("the follower stopped short; handed over (batches, distinct): {so_far:?}");
        };
        handed.take(&d.expect("the follower runs"));
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_sensor_that_falls_silent_while_the_follower_is_stalled_is_caught_up() {
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("store");
    seed_store(
        &store,
        &[sample::record("quiet", 1), sample::record("busy", 1)],
    );
    let gw = start(config("hs", &store)).await;
    let (node, consumer) = (client(&gw.endpoint).await, client(&gw.endpoint).await);
    let mut options = FollowOptions::new(b("hs"));
    // Small buffers: a consumer that stops reading soon makes the follower drop what comes.
    options.buffer_batches = 8;
    let mut follower = Follower::start(&consumer, options).await.unwrap();
    let quiet = blocking_publisher(&node, key_raw("hs", "quiet")).await;
    let busy = blocking_publisher(&node, key_raw("hs", "busy")).await;
    let mut handed = Handed::default();
    for seq in 0..20 {
        quiet.put(swaying("quiet", seq, 10)).await.unwrap();
        busy.put(swaying("busy", seq, 10)).await.unwrap();
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    follow_until(&mut follower, &mut handed, |h| {
        h.count("quiet") == 20 && h.count("busy") == 20
    })
    .await;
    // The consumer stalls. `quiet` sends its last batches and falls silent; `busy` goes on.
    let beats = consumer
        .declare_subscriber(Key::Heartbeat(b("hs")).to_string())
        .with(zenoh::handlers::FifoChannel::new(1000))
        .await
        .unwrap();
    let quiet_end = 80u64;
    for seq in 20..quiet_end {
        quiet.put(swaying("quiet", seq, 10)).await.unwrap();
        busy.put(swaying("busy", seq, 10)).await.unwrap();
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    let stop = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
    let stopped = stop.clone();
    let streaming = tokio::spawn(async move {
        let mut seq = quiet_end;
        while !stopped.load(Relaxed) {
            busy.put(swaying("busy", seq, 10)).await.unwrap();
            seq += 1;
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
        seq
    });
    // Until the heartbeat no longer names `quiet`: every one that did went by the stalled
    // follower, which dropped them.
    loop {
        let beat = tokio::time::timeout(TIMEOUT, beats.recv_async())
            .await
            .expect("heartbeats in time")
            .unwrap();
        let beat: Heartbeat = from_json(&beat.payload().to_bytes()).unwrap();
        if !beat.sensors.contains_key(&s("quiet")) && beat.sensors.contains_key(&s("busy")) {
            break;
        }
    }
    stop.store(true, Relaxed);
    let busy_end = streaming.await.unwrap();
    // The consumer reads again: everything comes, once, in order.
    follow_until(&mut follower, &mut handed, |h| {
        h.count("quiet") >= quiet_end as usize && h.count("busy") >= busy_end as usize
    })
    .await;
    assert_eq!(
        handed.sequences("quiet"),
        (0..quiet_end).collect::<Vec<_>>()
    );
    assert_eq!(handed.sequences("busy"), (0..busy_end).collect::<Vec<_>>());
    assert_eq!(follower.counters().unrecoverable.load(Relaxed), 0);
    drop(follower);
    node.close().await.unwrap();
    consumer.close().await.unwrap();
    gw.stop().await;
}

/// Batch `seq` of run `run` of a 100 Hz node sending ten samples a batch; run 1 starts 200 s
/// after run 0, numbered from 0 again.
fn of_run(sensor: &str, run: i64, seq: u64) -> Vec<u8> {
    let t0_ns = 1_800_000_000_000_000_000 + run * 200_000_000_000;
    RawBatch {
        header: BatchHeader {
            sensor_id: s(sensor),
            sequence: seq,
            timestamp_ns: t0_ns + seq as i64 * 100_000_000,
            sample_rate_hz: 100.0,
        },
        temperature_c: None,
        samples: (0..10)
            .map(|i| {
                [
                    0.01 * i as f32,
                    (run * 1000 + seq as i64) as f32 * 1e-4,
                    0.981,
                ]
            })
            .collect(),
    }
    .encode()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_node_that_restarts_its_numbering_is_followed_by_time() {
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("store");
    seed_store(&store, &[sample::record("rn", 1)]);
    let gw = start(config("hn", &store)).await;
    let (node, consumer) = (client(&gw.endpoint).await, client(&gw.endpoint).await);
    let mut options = FollowOptions::new(b("hn"));
    options.buffer_batches = 8;
    let mut follower = Follower::start(&consumer, options).await.unwrap();
    let publisher = blocking_publisher(&node, key_raw("hn", "rn")).await;
    let mut handed = Handed::default();
    for seq in 0..30 {
        publisher.put(of_run("rn", 0, seq)).await.unwrap();
    }
    follow_until(&mut follower, &mut handed, |h| h.count("rn") == 30).await;
    // Stalled: run 0 goes on to 100, then the node restarts and numbers run 1 from 0 to 59.
    for seq in 30..100 {
        publisher.put(of_run("rn", 0, seq)).await.unwrap();
    }
    for seq in 0..60 {
        publisher.put(of_run("rn", 1, seq)).await.unwrap();
    }
    // Reading again: the heartbeat names run 1's batch 59, and the rest of run 1 comes live.
    follow_until(&mut follower, &mut handed, |h| h.count("rn") >= 160).await;
    let sent_1 = 70;
    for seq in 60..sent_1 {
        publisher.put(of_run("rn", 1, seq)).await.unwrap();
    }
    follow_until(&mut follower, &mut handed, |h| {
        h.count("rn") >= 100 + sent_1 as usize
    })
    .await;
    let expected: Vec<u64> = (0..100).chain(0..sent_1).collect();
    assert_eq!(
        handed.sequences("rn"),
        expected,
        "each run whole, once, in order"
    );
    // Byte for byte what the history holds, in its order, once it holds as many (the last
    // batches handed came live, and may be a flush ahead of the disk).
    let payloads: Vec<&Vec<u8>> = handed.0["rn"].iter().map(|(_, _, p)| p).collect();
    let request = HistoryRequest::sensor(&b("hn"), &s("rn"));
    wait_until_async("the history to hold every batch handed", || async {
        read_history(&consumer, &request).await.len() >= payloads.len()
    })
    .await;
    let kept = read_history(&consumer, &request).await;
    assert_eq!(payloads, kept.iter().collect::<Vec<_>>());
    drop(follower);
    // A follower resumed from a saved position goes on in run 1, although run 0 also had
    // that number and what follows it.
    let (sequence, timestamp_ns, _) = handed.0["rn"].last().unwrap().clone();
    for seq in sent_1..sent_1 + 10 {
        publisher.put(of_run("rn", 1, seq)).await.unwrap();
    }
    let mut last_sent = HistoryRequest::sensor(&b("hn"), &s("rn"));
    let last_ns = CorrectedBatch::decode(&kept[kept.len() - 1])
        .unwrap()
        .header
        .timestamp_ns
        + 10 * 100_000_000;
    (last_sent.from_ns, last_sent.to_ns) = (Some(last_ns), Some(last_ns + 1));
    wait_until_async("run 1's last batch kept", || async {
        triax_client::history::any_kept(&consumer, &last_sent, TIMEOUT)
            .await
            .unwrap()
    })
    .await;
    let mut options = FollowOptions::new(b("hn"));
    options.resume_at.insert(
        s("rn"),
        Position {
            sequence,
            timestamp_ns,
        },
    );
    let mut resumed = Follower::start(&consumer, options).await.unwrap();
    let mut after = Handed::default();
    follow_until(&mut resumed, &mut after, |h| h.count("rn") >= 10).await;
    assert_eq!(
        after.sequences("rn"),
        (sent_1..sent_1 + 10).collect::<Vec<_>>()
    );
    drop(resumed);
    node.close().await.unwrap();
    consumer.close().await.unwrap();
    gw.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn retention_holds_the_size_cap_and_counts_what_it_deleted() {
    let dir = tempfile::tempdir().unwrap();
    let mut cfg = config("ht", &dir.path().join("store"));
    let h = cfg.history.as_mut().unwrap();
    h.max_bytes = 256 << 10;
    h.segment_bytes = 32 << 10;
    h.flush_interval = Duration::from_millis(20);
    let history_dir = h.path.clone();
    let gw = start(cfg).await;
    let session = client(&gw.endpoint).await;
    let publisher = blocking_publisher(&session, key_raw("ht", "r")).await;
    for seq in 0..3000u64 {
        publisher
            .put(raw("r", seq, vec![[0.5, 0.25, 1.0]; 10]))
            .await
            .unwrap();
        if seq % 100 == 0 {
            tokio::time::sleep(Duration::from_millis(25)).await;
        }
    }
    wait_until_async("3000 batches kept", || async {
        status(&session, "ht")
            .await
            .history
            .is_some_and(|h| h.written_batches == 3000 && h.queued_batches == 0)
    })
    .await;
    // The last flush applies retention once it has written.
    wait_until_async("retention to hold the cap", || async {
        status(&session, "ht").await.history.is_some_and(|h| {
            h.bytes <= h.max_bytes && h.deleted_segments >= 2 && h.deleted_bytes > 0
        })
    })
    .await;
    let h = status(&session, "ht").await.history.unwrap();
    let on_disk: u64 = std::fs::read_dir(&history_dir)
        .unwrap()
        .map(|e| e.unwrap().metadata().unwrap().len())
        .sum();
    // The cap, plus the segment being written.
    assert!(
        on_disk <= h.max_bytes + (32 << 10) + 4096,
        "{on_disk} bytes on disk"
    );
    // The newest batches are there, the oldest gone.
    let kept = read_history(&session, &HistoryRequest::sensor(&b("ht"), &s("r"))).await;
    let seqs: Vec<u64> = kept
        .iter()
        .map(|p| CorrectedBatch::decode(p).unwrap().header.sequence)
        .collect();
    assert_eq!(seqs.last(), Some(&2999));
    assert!(seqs[0] > 0 && seqs.windows(2).all(|w| w[1] == w[0] + 1));
    session.close().await.unwrap();
    gw.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bad_history_queries_are_refused_by_name() {
    let dir = tempfile::tempdir().unwrap();
    let gw = start(config("hq9", &dir.path().join("store"))).await;
    let session = client(&gw.endpoint).await;
    let publisher = blocking_publisher(&session, key_raw("hq9", "q")).await;
    publisher
        .put(
            RawBatch::decode(&raw("q", 0, vec![[0.0; 3]; 5]))
                .unwrap()
                .encode(),
        )
        .await
        .unwrap();
    for (params, named) in [
        ("to_ns=soon", "to_ns"),
        ("limit=0", "limit"),
        ("calibration=newest", "calibration"),
        ("shape=round", "shape"),
    ] {
        let replies = session
            .get(format!("triax/hq9/history/q?{params}"))
            .timeout(TIMEOUT)
            .await
            .unwrap();
        let reply = replies.recv_async().await.expect("an answer");
        let err = reply.result().expect_err("refused");
        let text = String::from_utf8_lossy(&err.payload().to_bytes()).into_owned();
        assert!(text.contains(named), "{params}: {text}");
    }
    session.close().await.unwrap();
    gw.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_version_number_over_a_wildcard_is_refused_whole() {
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("store");
    seed_store(
        &store,
        &[
            sample::record("va", 1),
            sample::record("va", 2),
            sample::record("vb", 1),
        ],
    );
    let gw = start(config("hv", &store)).await;
    let session = client(&gw.endpoint).await;
    for id in ["va", "vb"] {
        let publisher = blocking_publisher(&session, key_raw("hv", id)).await;
        publisher.put(swaying(id, 0, 10)).await.unwrap();
        wait_history_holds(&session, "hv", id, 0).await;
    }
    let mut request = HistoryRequest::sensor(&b("hv"), &s("va"));
    request.sensors = "*".into();
    request.calibration = Some("2".into());
    let mut got = 0;
    let err = fetch(&session, &request, TIMEOUT, &mut |_| got += 1)
        .await
        .unwrap_err()
        .to_string();
    assert!(err.contains("vb") && err.contains("no version 2"), "{err}");
    assert_eq!(got, 0, "no batches, not even va's, which has version 2");
    request.sensors = "va".into();
    assert_eq!(read_history(&session, &request).await.len(), 1);
    session.close().await.unwrap();
    gw.stop().await;
}

/// Environment variables that make [`gateway_process`] run a gateway: its building, store and
/// the endpoint it connects to.
const CHILD_ENV: [&str; 3] = [
    "TRIAX_TEST_CHILD_BUILDING",
    "TRIAX_TEST_CHILD_STORE",
    "TRIAX_TEST_CHILD_CONNECT",
];

/// Not a test: the entry point of a gateway run in a process of its own by
/// `the_history_survives_kill_9_within_its_durability_rule`, which starts this binary with
/// `--ignored --exact` and the environment of [`CHILD_ENV`], and kills it.
#[test]
#[ignore = "a child process entry point, started by the kill -9 test"]
fn gateway_process() {
    let [building, store, connect] =
        CHILD_ENV.map(|k| std::env::var(k).unwrap_or_else(|_| panic!("{k} is set by the parent")));
    let mut cfg = triax_gateway::Config::for_tests(&building, std::path::Path::new(&store), vec![]);
    cfg.zenoh.connect = vec![connect];
    tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .unwrap()
        .block_on(triax_gateway::run(cfg, std::future::pending::<()>()))
        .unwrap();
}

/// The history after repeated SIGKILLs of the gateway while a node streams: every batch
/// published more than the durability rule's time before the kill is kept, byte for byte, and
/// no damaged batch is ever served. Prints what each kill cost.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_history_survives_kill_9_within_its_durability_rule() {
    use std::time::Instant;
    use triax_test_support::child::Entry;
    // One flush interval (1 s) plus a sync and the drain, with room for a busy machine's disk,
    // where a sync may take a second or more.
    const RULE: Duration = Duration::from_millis(3000);
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("store");
    seed_store(&store, &[sample::record("k-1", 1)]);
    // The test's own session listens; the gateway connects to it, and again after each restart.
    let port = free_port();
    let endpoint = format!("tcp/127.0.0.1:{port}");
    let session = listening_peer(&endpoint).await;
    type Live = std::sync::Arc<std::sync::Mutex<Vec<(Instant, Vec<u8>)>>>;
    let live: Live = Default::default();
    let l = live.clone();
    let _sub = session
        .declare_subscriber(key_corrected("hk", "k-1"))
        .callback(move |s| {
            l.lock()
                .unwrap()
                .push((Instant::now(), s.payload().to_bytes().to_vec()))
        })
        .await
        .unwrap();
    let publisher = session
        .declare_publisher(key_raw("hk", "k-1"))
        .await
        .unwrap();
    // A gateway process on the store, once it answers status queries.
    let start_child = || async {
        let child = Entry::new("history::gateway_process")
            .env(CHILD_ENV[0], "hk")
            .env(CHILD_ENV[1], &store)
            .env(CHILD_ENV[2], &endpoint)
            .spawn();
        wait_until_async("the gateway process to answer", || async {
            let replies = session
                .get("triax/hk/status")
                .timeout(Duration::from_millis(500))
                .await
                .unwrap();
            replies.recv_async().await.is_ok_and(|r| r.result().is_ok())
        })
        .await;
        child
    };
    let mut seq = 0u64;
    let mut lost_per_kill = Vec::new();
    let mut judged = 0;
    for kill in 0..4 {
        let mut child = start_child().await;
        wait_matching(&publisher).await;
        // Stream at 200 batches a second for 2 to 3 s, then kill mid-stream.
        let stream_for = Duration::from_millis(2000 + 300 * kill);
        let started = Instant::now();
        let mut tick = tokio::time::interval(Duration::from_millis(5));
        while started.elapsed() < stream_for {
            tick.tick().await;
            publisher.put(swaying("k-1", seq, 10)).await.unwrap();
            seq += 1;
        }
        // SIGKILL: no shutdown, no last flush.
        child.kill().unwrap();
        let killed_at = Instant::now();
        child.wait().unwrap();
        // Restarted on the same store and history: recovery cuts what is torn.
        let mut child = start_child().await;
        let kept = read_history(&session, &HistoryRequest::sensor(&b("hk"), &s("k-1"))).await;
        let st = status(&session, "hk").await;
        assert_eq!(st.history.as_ref().unwrap().damaged_blocks, 0);
        child.kill().unwrap();
        child.wait().unwrap();
        // Whatever is served decodes, and is what the live stream carried.
        let by_seq: BTreeMap<u64, &Vec<u8>> = kept
            .iter()
            .map(|p| {
                (
                    CorrectedBatch::decode(p)
                        .expect("a kept batch decodes")
                        .header
                        .sequence,
                    p,
                )
            })
            .collect();
        let live = live.lock().unwrap();
        let mut lost = 0;
        // This run's batches: earlier runs' were judged at their own kill.
        for (at, payload) in live.iter().skip(judged) {
            let seq = CorrectedBatch::decode(payload).unwrap().header.sequence;
            match by_seq.get(&seq) {
                Some(k) => assert_eq!(*k, payload, "batch {seq} kept differs from the live one"),
                None => {
                    lost += 1;
                    assert!(
                        killed_at.duration_since(*at) < RULE,
                        "kill {kill}: batch {seq}, published {:?} before the kill, is not kept",
                        killed_at.duration_since(*at)
                    );
                }
            }
        }
        judged = live.len();
        lost_per_kill.push(lost);
    }
    println!("batches lost per kill (all within {RULE:?} of it): {lost_per_kill:?}");
    session.close().await.unwrap();
}

/// The building cut from the site router for 30 s (the router stopped, then started again on
/// its port): the gateway and its node keep working on the building's side, and a follower on
/// the far side of the router recovers every batch once the link is back.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_consumer_beyond_the_site_router_recovers_a_30_s_cut() {
    let mut router = Router::start().await;
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("store");
    seed_store(
        &store,
        &[sample::record("cut-1", 1), sample::record("cut-2", 1)],
    );
    // The gateway listens for its building's nodes and reaches the site through the router.
    let mut cfg = config("hx", &store);
    cfg.zenoh.connect = vec![router.endpoint.clone()];
    let gw = start(cfg).await;
    let node = client(&gw.endpoint).await;
    let far = zenoh::open(router.client_settings().to_config().unwrap())
        .await
        .unwrap();
    let mut follower = Follower::start(&far, FollowOptions::new(b("hx")))
        .await
        .unwrap();
    let mut publishers = Vec::new();
    for id in ["cut-1", "cut-2"] {
        publishers.push((id, blocking_publisher(&node, key_raw("hx", id)).await));
    }
    // The far side sees the live stream before the cut.
    let send = |seq: u64| {
        let publishers = &publishers;
        async move {
            for (id, p) in publishers {
                p.put(swaying(id, seq, 10)).await.unwrap();
            }
        }
    };
    let mut seq = 0;
    let mut got: Vec<CorrectedBatch> = Vec::new();
    while got.len() < 20 {
        send(seq).await;
        seq += 1;
        tokio::time::sleep(Duration::from_millis(100)).await;
        while let Ok(Some(d)) =
            tokio::time::timeout(Duration::from_millis(1), follower.next()).await
        {
            got.push(d.batch);
        }
    }
    // The cut: the node goes on streaming into the building for 30 s.
    let down = Duration::from_secs(30);
    let streaming = async {
        let until = tokio::time::Instant::now() + down + Duration::from_secs(2);
        let mut seq = seq;
        while tokio::time::Instant::now() < until {
            send(seq).await;
            seq += 1;
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
        seq
    };
    let cut_at = seq;
    let (sent, ()) = tokio::join!(streaming, router.restart_after(down));
    // After the link is back, everything arrives: the stretch from the history, then live.
    let total = 2 * sent as usize;
    // Generous: on a loaded machine the router's restart and the history reads take a while.
    let deadline = tokio::time::Instant::now() + Duration::from_secs(90);
    while got.len() < total && tokio::time::Instant::now() < deadline {
        if let Ok(Some(d)) = tokio::time::timeout(Duration::from_millis(500), follower.next()).await
        {
            got.push(d.batch);
        }
    }
    for id in ["cut-1", "cut-2"] {
        let seqs: Vec<u64> = got
            .iter()
            .filter(|b| b.header.sensor_id.as_str() == id)
            .map(|b| b.header.sequence)
            .collect();
        assert_eq!(
            seqs,
            (0..sent).collect::<Vec<_>>(),
            "{id}: every batch once, in order"
        );
    }
    // 30 of the 32 s streamed after the cut were cut off, whatever pace the machine allowed.
    let streamed_after_cut = 2 * (sent - cut_at);
    let recovered = follower.counters().recovered.load(Relaxed);
    assert!(
        recovered >= streamed_after_cut * 3 / 4,
        "the cut came from the history: {recovered} of {streamed_after_cut} recovered"
    );
    drop(follower);
    far.close().await.unwrap();
    node.close().await.unwrap();
    gw.stop().await;
}
