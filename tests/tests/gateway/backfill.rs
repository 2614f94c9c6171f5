//! Backfill from the node's buffer (PROTOCOL.md §2.3 `late`, §5.4): batches a link cut or the
//! gateway's own downtime cost are fetched, corrected as the live path would have corrected
//! them, kept in the history and published flagged `late`.
//!
//! The node here is the test's own session: it publishes raw batches and answers
//! `triax/<b>/buffer/<s>?from_seq;to_seq` from what it sent, as §5.4 says (`triax-node`'s own
//! buffer is tested in `node/tests/node.rs`). Not publishing a stretch is a link cut, exactly.
//!
//! - `a_cut_link_is_filled_late_as_live_and_replays_exactly`: a split-mode and a dynamic sensor
//!   lose 30 batches each on the link; the gateway fetches them, publishes them `late` with the
//!   bytes an uninterrupted gateway published (but for the flag), the history holds every batch
//!   once, and a replay gives back every published byte, late and live.
//! - `replies_lost_on_the_way_are_asked_again`: an answer that lacks a batch (lost on a busy
//!   link) is followed by a query for what is still missing.
//! - `what_a_gateway_missed_while_down_is_fetched_when_it_starts`: batches sent while the
//!   gateway was stopped reach its history after the restart, once each, and replay exactly.

use std::collections::HashMap;
use std::f64::consts::PI;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use triax_client::follow::{FollowOptions, Follower};
use triax_client::{history::fetch, HistoryRequest};
use triax_gateway::{CorrectionMode, SensorSettings};
use triax_protocol::batch::{flags, CorrectedBatch};
use triax_protocol::record::sample;
use triax_protocol::{BuildingId, SensorId};

use super::status;
use super::util::*;

const SPLIT: &str = "bf-split";
const DYNAMIC: &str = "bf-dyn";
const BATCH: usize = 10;

/// Batch `seq`: sway in band, a slow tilt and gravity, a function of time alone.
fn signal(sensor: &str, seq: u64) -> Vec<u8> {
    let samples = (0..BATCH)
        .map(|i| {
            let t = (seq as usize * BATCH + i) as f64 / 100.0;
            [
                (0.2 * (2.0 * PI * 1.3 * t).sin()) as f32,
                (0.05 * (2.0 * PI * 0.07 * t).sin()) as f32,
                (0.981 + 0.01 * (2.0 * PI * 0.2 * t).sin()) as f32,
            ]
        })
        .collect();
    raw(sensor, seq, samples)
}

/// Every corrected payload published on `building`'s corrected keys, in arrival order.
type Published = Arc<Mutex<Vec<Vec<u8>>>>;

async fn subscribe(
    session: &zenoh::Session,
    building: &str,
) -> (Published, zenoh::pubsub::Subscriber<()>) {
    let out: Published = Default::default();
    let o = out.clone();
    let sub = session
        .declare_subscriber(format!("triax/{building}/corrected/*"))
        .callback(move |s| o.lock().unwrap().push(s.payload().to_bytes().to_vec()))
        .await
        .unwrap();
    (out, sub)
}

fn decoded(p: &Published) -> Vec<(Vec<u8>, CorrectedBatch)> {
    p.lock()
        .unwrap()
        .iter()
        .map(|b| (b.clone(), CorrectedBatch::decode(b).unwrap()))
        .collect()
}

/// The history's replay (record in force) of `sensor`, payloads in the history's order.
async fn replay(session: &zenoh::Session, building: &str, sensor: &str) -> Vec<Vec<u8>> {
    let request = HistoryRequest::sensor(
        &BuildingId::new(building).unwrap(),
        &SensorId::new(sensor).unwrap(),
    );
    let mut out = Vec::new();
    fetch(session, &request, TIMEOUT, &mut |b| {
        out.push(b.payload.clone())
    })
    .await
    .unwrap();
    out
}

fn settings(config: &mut triax_gateway::Config) {
    config.sensors.insert(
        SensorId::new(SPLIT).unwrap(),
        SensorSettings {
            mode: CorrectionMode::Split,
            ..SensorSettings::default()
        },
    );
}

/// Waits until the gateway of `building` counts `n` late batches published (a subscriber on a
/// busy machine may lose some: they go with drop congestion control, as live ones do).
async fn wait_late_published(session: &zenoh::Session, building: &str, n: u64) {
    wait_until_async(
        &format!("{n} late batches published in {building}"),
        || async {
            // Polled from a gateway's start on: no answer yet is not late batches yet.
            try_status(session, building)
                .await
                .and_then(|s| s.backfill)
                .is_some_and(|b| b.late_batches >= n)
        },
    )
    .await;
}

/// Every payload a subscriber received is in `replayed`: the replay gives back what was
/// published, byte for byte, late batches included.
fn all_in(received: &[Vec<u8>], replayed: &[Vec<u8>], what: &str) {
    let replayed: std::collections::HashSet<&Vec<u8>> = replayed.iter().collect();
    for p in received {
        assert!(
            replayed.contains(p),
            "{what}: a published batch the replay does not give back"
        );
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_cut_link_is_filled_late_as_live_and_replays_exactly() {
    const TOTAL: u64 = 100;
    const CUT: std::ops::RangeInclusive<u64> = 30..=59;
    let dir = tempfile::tempdir().unwrap();
    // The gateway under test, and a reference gateway that receives everything.
    let (store, reference_store) = (dir.path().join("s1"), dir.path().join("s2"));
    for s in [&store, &reference_store] {
        seed_store(s, &[sample::record(SPLIT, 1), sample::record(DYNAMIC, 1)]);
    }
    let mut c = config("hbf", &store);
    settings(&mut c);
    let gw = start(c).await;
    let mut c = config("hbfref", &reference_store);
    c.backfill = None;
    settings(&mut c);
    let reference = start(c).await;

    let endpoints = [gw.endpoint.as_str(), reference.endpoint.as_str()];
    let node = client_of(&endpoints).await;
    let buffer = Buffer::default();
    let _queryable = buffer.serve(&node, "hbf").await;
    let watcher = client_of(&endpoints).await;
    let (published, _s1) = subscribe(&watcher, "hbf").await;
    // A consumer following §5.2 from the first batch on.
    let mut options = FollowOptions::new(BuildingId::new("hbf").unwrap());
    options.new_sensors_from_ns = Some(i64::MIN);
    let mut follower = Follower::start(&watcher, options).await.unwrap();
    let mut publishers = Vec::new();
    for b in ["hbf", "hbfref"] {
        for id in [SPLIT, DYNAMIC] {
            let p = node
                .declare_publisher(key_raw(b, id))
                .congestion_control(zenoh::qos::CongestionControl::Block)
                .await
                .unwrap();
            wait_matching(&p).await;
            publishers.push((b, id, p));
        }
    }
    for seq in 0..TOTAL {
        for (b, id, p) in &publishers {
            let payload = signal(id, seq);
            if *b == "hbf" {
                buffer.keep(id, seq, &payload);
                if CUT.contains(&seq) {
                    continue;
                }
            }
            p.put(payload).await.unwrap();
        }
    }
    let cut = CUT.count();
    wait_late_published(&watcher, "hbf", 2 * cut as u64).await;
    for id in [SPLIT, DYNAMIC] {
        wait_history_holds(&watcher, "hbf", id, TOTAL - 1).await;
        wait_history_holds(&watcher, "hbfref", id, TOTAL - 1).await;
    }
    // What the gateway kept, which its replay gives back as published (checked below against
    // what a subscriber received).
    let received: Vec<Vec<u8>> = published.lock().unwrap().clone();
    let mut got = Vec::new();
    for id in [SPLIT, DYNAMIC] {
        for p in replay(&watcher, "hbf", id).await {
            let b = CorrectedBatch::decode(&p).unwrap();
            got.push((p, b));
        }
    }
    // What the uninterrupted gateway published, from its history (byte for byte its live
    // stream, `history` and `replay_restart` show; a live subscriber may lose a batch on a
    // busy machine, its history does not).
    let mut all = Vec::new();
    for id in [SPLIT, DYNAMIC] {
        for p in replay(&watcher, "hbfref", id).await {
            let b = CorrectedBatch::decode(&p).unwrap();
            all.push((p, b));
        }
    }
    for id in [SPLIT, DYNAMIC] {
        let ours: Vec<_> = got
            .iter()
            .filter(|(_, b)| b.header.sensor_id.as_str() == id)
            .collect();
        let late: Vec<_> = ours
            .iter()
            .filter(|(_, b)| b.batch_flags & flags::LATE != 0)
            .collect();
        // Every batch once; the late ones in order, the cut's numbers exactly.
        assert_eq!(ours.len() as u64, TOTAL, "{id}: every batch kept once");
        assert_eq!(
            late.iter()
                .map(|(_, b)| b.header.sequence)
                .collect::<Vec<_>>(),
            CUT.collect::<Vec<_>>(),
            "{id}: late batches"
        );
        let after_cut = ours
            .iter()
            .find(|(_, b)| b.header.sequence == CUT.end() + 1)
            .unwrap();
        assert_ne!(
            after_cut.1.batch_flags & flags::SEQUENCE_GAP,
            0,
            "{id}: the live batch after the cut shows the gap"
        );
        // A late batch is what the uninterrupted gateway published, but for the flag.
        for (_, b) in &late {
            assert_eq!(
                b.batch_flags & flags::SEQUENCE_GAP,
                0,
                "{id} #{}",
                b.header.sequence
            );
            let (_, r) = all
                .iter()
                .find(|(_, r)| {
                    r.header.sensor_id.as_str() == id && r.header.sequence == b.header.sequence
                })
                .unwrap();
            assert_eq!(
                b.samples, r.samples,
                "{id} #{}: samples as live",
                b.header.sequence
            );
            assert_eq!(
                b.batch_flags & !flags::LATE,
                r.batch_flags,
                "{id} #{}",
                b.header.sequence
            );
        }
    }
    let kept: Vec<Vec<u8>> = got.iter().map(|(p, _)| p.clone()).collect();
    all_in(&received, &kept, "hbf");
    // The follower hands over every batch once, late ones included, as published.
    let mut handed: Vec<Vec<u8>> = Vec::new();
    while handed.len() < 2 * TOTAL as usize {
        let d = tokio::time::timeout(TIMEOUT, follower.next())
            .await
            .unwrap_or_else(|_| panic!("the follower handed over {} batches", handed.len()))
            .unwrap();
        handed.push(d.payload);
    }
    let mut expected: Vec<Vec<u8>> = got.iter().map(|(p, _)| p.clone()).collect();
    expected.sort();
    handed.sort();
    assert!(
        handed == expected,
        "the follower's batches are the published ones, each once"
    );
    assert_eq!(
        follower
            .counters()
            .late
            .load(std::sync::atomic::Ordering::Relaxed),
        2 * cut as u64
    );
    let st = status(&watcher, "hbf").await;
    let b = st.backfill.expect("backfill reported");
    assert_eq!(b.late_batches, 2 * cut as u64, "{b:?}");
    assert_eq!(b.rejected_replies, 0, "{b:?}");
    for s in &st.sensors {
        assert_eq!(s.late_batches, cut as u64, "{}", s.sensor_id);
    }
    reference.stop().await;
    gw.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn what_a_gateway_missed_while_down_is_fetched_when_it_starts() {
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("store");
    seed_store(
        &store,
        &[sample::record(SPLIT, 1), sample::record(DYNAMIC, 1)],
    );
    // The node listens, so that it outlives the gateway.
    let endpoint = format!("tcp/127.0.0.1:{}", free_port());
    let node = listening_peer(&endpoint).await;
    let buffer = Buffer::default();
    let _queryable = buffer.serve(&node, "hbd").await;
    let (published, _sub) = subscribe(&node, "hbd").await;
    let gateway = || {
        let mut c = config("hbd", &store);
        c.zenoh.listen.clear();
        c.zenoh.connect = vec![endpoint.clone()];
        settings(&mut c);
        c
    };
    let mut publishers = Vec::new();
    for id in [SPLIT, DYNAMIC] {
        let p = node
            .declare_publisher(key_raw("hbd", id))
            .congestion_control(zenoh::qos::CongestionControl::Block)
            .await
            .unwrap();
        publishers.push((id, p));
    }
    let send = |seqs: std::ops::Range<u64>, live: bool| {
        let (buffer, publishers) = (&buffer, &publishers);
        async move {
            for seq in seqs {
                for (id, p) in publishers {
                    let payload = signal(id, seq);
                    buffer.keep(id, seq, &payload);
                    if live {
                        p.put(payload).await.unwrap();
                    }
                }
            }
        }
    };
    let gw = start(gateway()).await;
    for (_, p) in &publishers {
        wait_matching(p).await;
    }
    send(0..80, true).await;
    for id in [SPLIT, DYNAMIC] {
        wait_history_holds(&node, "hbd", id, 79).await;
    }
    gw.stop().await;
    // Made while no gateway runs: in the node's buffer only.
    send(80..120, false).await;
    let gw = start(gateway()).await;
    for (_, p) in &publishers {
        wait_matching(p).await;
    }
    send(120..150, true).await;
    wait_late_published(&node, "hbd", 80).await;
    for id in [SPLIT, DYNAMIC] {
        wait_history_holds(&node, "hbd", id, 149).await;
    }
    for id in [SPLIT, DYNAMIC] {
        let replayed = replay(&node, "hbd", id).await;
        let mut seqs: Vec<u64> = replayed
            .iter()
            .map(|p| CorrectedBatch::decode(p).unwrap().header.sequence)
            .collect();
        seqs.sort_unstable();
        assert_eq!(
            seqs,
            (0..150).collect::<Vec<_>>(),
            "{id}: every batch kept once"
        );
        let ours: Vec<Vec<u8>> = decoded(&published)
            .into_iter()
            .filter(|(_, b)| b.header.sensor_id.as_str() == id)
            .map(|(p, _)| p)
            .collect();
        all_in(&ours, &replayed, id);
    }
    gw.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn replies_lost_on_the_way_are_asked_again() {
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("store");
    seed_store(&store, &[sample::record(DYNAMIC, 1)]);
    let gw = start(config("hbl", &store)).await;
    let node = client(&gw.endpoint).await;
    let buffer = Buffer::default();
    let _queryable = buffer.serve(&node, "hbl").await;
    // The first answer loses its middle batch.
    buffer.lose_replies(1);
    let p = node
        .declare_publisher(key_raw("hbl", DYNAMIC))
        .congestion_control(zenoh::qos::CongestionControl::Block)
        .await
        .unwrap();
    wait_matching(&p).await;
    for seq in 0..60 {
        let payload = signal(DYNAMIC, seq);
        buffer.keep(DYNAMIC, seq, &payload);
        if !(10..40).contains(&seq) {
            p.put(payload).await.unwrap();
        }
    }
    wait_late_published(&node, "hbl", 30).await;
    wait_history_holds(&node, "hbl", DYNAMIC, 59).await;
    let mut seqs: Vec<u64> = replay(&node, "hbl", DYNAMIC)
        .await
        .iter()
        .map(|p| CorrectedBatch::decode(p).unwrap().header.sequence)
        .collect();
    seqs.sort_unstable();
    assert_eq!(seqs, (0..60).collect::<Vec<_>>(), "every batch kept once");
    let b = status(&node, "hbl").await.backfill.unwrap();
    // The hole, then the one batch still missing.
    assert_eq!(
        (b.queries, b.wanted_batches, b.late_batches),
        (2, 31, 30),
        "{b:?}"
    );
    gw.stop().await;
}

/// Backfill of an outage at a building's pace, in real time: `TRIAX_BACKFILL_SENSORS` sensors
/// (100) at 100 Hz in 10-sample batches, the node's link cut for `TRIAX_BACKFILL_OUTAGE_S`
/// (60 s) between two stretches of 20 s. Prints how long after the link's return the last late
/// batch was published, and the live stream's latency (node put to corrected batch received)
/// before the outage and while the hole filled. BENCHMARKS.md quotes it:
/// `cargo test --release -p triax-tests --test gateway -- --ignored backfill_of_an_outage
/// --nocapture`.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
#[ignore = "minutes, in real time; BENCHMARKS.md quotes it"]
async fn backfill_of_an_outage() {
    let env = |k: &str, default: u64| {
        std::env::var(k)
            .ok()
            .and_then(|v| v.parse().ok())
            .unwrap_or(default)
    };
    let (n_sensors, outage_s) = (
        env("TRIAX_BACKFILL_SENSORS", 100) as usize,
        env("TRIAX_BACKFILL_OUTAGE_S", 60),
    );
    let ids: Vec<String> = (0..n_sensors).map(|i| format!("bo-{i:03}")).collect();
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("store");
    seed_store(
        &store,
        &ids.iter().map(|s| sample::record(s, 1)).collect::<Vec<_>>(),
    );
    let gw = start(config("hbo", &store)).await;
    let node = client(&gw.endpoint).await;
    let buffer = Buffer::default();
    let _queryable = buffer.serve(&node, "hbo").await;
    let watcher = client(&gw.endpoint).await;
    // Per received corrected batch: sensor, number, late, when.
    type Seen = Arc<Mutex<Vec<(String, u64, bool, std::time::Instant)>>>;
    let seen: Seen = Arc::default();
    let s2 = seen.clone();
    let _sub = watcher
        .declare_subscriber("triax/hbo/corrected/*")
        .callback(move |s| {
            let at = std::time::Instant::now();
            if let Ok(b) = CorrectedBatch::decode(&s.payload().to_bytes()) {
                s2.lock().unwrap().push((
                    b.header.sensor_id.to_string(),
                    b.header.sequence,
                    b.batch_flags & flags::LATE != 0,
                    at,
                ));
            }
        })
        .await
        .unwrap();
    let mut publishers = Vec::new();
    for id in &ids {
        let p = node
            .declare_publisher(key_raw("hbo", id))
            .congestion_control(zenoh::qos::CongestionControl::Block)
            .await
            .unwrap();
        wait_matching(&p).await;
        publishers.push(p);
    }
    let phases = [(20u64, true), (outage_s, false), (20, true)];
    let total: u64 = phases.iter().map(|(s, _)| s * 10).sum();
    let mut put_at: HashMap<(usize, u64), std::time::Instant> = HashMap::new();
    let started = std::time::Instant::now();
    let (mut seq, mut link_back, mut cut_from) = (0u64, None, 0u64);
    let mut filled = None;
    for (seconds, live) in phases {
        if live && seq > 0 {
            link_back = Some(std::time::Instant::now());
            // When the gateway has published every late batch, by its own count (a consumer
            // on a busy link may lose some: late batches go at low priority, dropped first).
            let (watcher, want) = (watcher.clone(), outage_s * 10 * n_sensors as u64);
            filled = Some(tokio::spawn(async move {
                let back = std::time::Instant::now();
                loop {
                    let st = try_status(&watcher, "hbo").await;
                    if st
                        .and_then(|s| s.backfill)
                        .is_some_and(|b| b.late_batches >= want)
                    {
                        return back.elapsed();
                    }
                    tokio::time::sleep(Duration::from_millis(100)).await;
                }
            }));
        } else if !live {
            cut_from = seq;
        }
        for _ in 0..seconds * 10 {
            for (i, (id, p)) in ids.iter().zip(&publishers).enumerate() {
                let payload = signal(id, seq);
                buffer.keep(id, seq, &payload);
                if live {
                    put_at.insert((i, seq), std::time::Instant::now());
                    p.put(payload).await.unwrap();
                }
            }
            seq += 1;
            tokio::time::sleep_until((started + Duration::from_millis(100 * seq)).into()).await;
        }
    }
    let cut = cut_from..cut_from + outage_s * 10;
    let want_late = cut.clone().count() * n_sensors;
    let filled_s = tokio::time::timeout(TIMEOUT, filled.unwrap())
        .await
        .expect("every late batch published")
        .unwrap()
        .as_secs_f64();
    let link_back = link_back.unwrap();
    let seen = seen.lock().unwrap().clone();
    let last_late = seen
        .iter()
        .filter(|(_, _, late, _)| *late)
        .map(|(_, _, _, at)| *at)
        .max()
        .unwrap_or(link_back);
    let index: HashMap<&str, usize> = ids
        .iter()
        .enumerate()
        .map(|(i, s)| (s.as_str(), i))
        .collect();
    let latency_ms = |from: u64, to: u64| {
        let mut l: Vec<f64> = seen
            .iter()
            .filter(|(_, s, late, _)| !late && (from..to).contains(s))
            .filter_map(|(id, s, _, at)| {
                let put = put_at.get(&(index[id.as_str()], *s))?;
                Some(at.duration_since(*put).as_secs_f64() * 1e3)
            })
            .collect();
        l.sort_by(f64::total_cmp);
        let q = |p: f64| l[((l.len() - 1) as f64 * p) as usize];
        (q(0.5), q(0.99), l.len())
    };
    let back_seq = cut.end;
    let received = seen.iter().filter(|(_, _, late, _)| *late).count();
    // Live batches while the hole filled: from the link's return to the last late batch.
    let during = seen
        .iter()
        .filter(|(_, s, late, at)| !late && *s >= back_seq && *at <= last_late)
        .map(|(_, s, _, _)| *s)
        .max()
        .unwrap_or(back_seq)
        + 1;
    let before = latency_ms(50, cut.start);
    let filling = latency_ms(back_seq, during.max(back_seq + 10));
    println!(
        "{n_sensors} sensors, {outage_s} s outage ({want_late} batches): every late batch \
         published {filled_s:.2} s after the link's return ({received} received by a watcher, \
         the last {:.2} s after); live latency p50/p99 {:.2}/{:.2} ms before ({} batches), \
         {:.2}/{:.2} ms while filling ({} batches); {total} rounds",
        last_late.duration_since(link_back).as_secs_f64(),
        before.0,
        before.1,
        before.2,
        filling.0,
        filling.1,
        filling.2
    );
    let st = status(&watcher, "hbo").await;
    println!("{:?}", st.backfill);
    gw.stop().await;
}
