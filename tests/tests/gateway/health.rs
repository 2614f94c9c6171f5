//! Field calibration health through a real gateway (PROTOCOL.md §3.9, §2.3 bit 9).
//!
//! Two sensors calibrated on the simulated bench stream three minutes of sensor time, faster
//! than real time; one channel of one of them freezes after a minute. The frozen sensor's
//! health turns `suspect` within a minute of sensor time, its samples carry
//! `calibration_suspect` from the time its report states (and not before), the healthy one
//! stays `ok` and unflagged; the health queryable, status and metrics agree. The flag
//! outlives a restart of the gateway, ends when a new record is in force, and the history's
//! replay reproduces it.

use std::collections::BTreeMap;

use triax_client::{history::fetch, HistoryRequest};
use triax_gateway::HealthSettings;
use triax_health::sim::{calibrate, field_sensor_truth, Fault, FieldConfig, FieldSensor, EPOCH_NS};
use triax_protocol::batch::{flags, BatchHeader, CorrectedBatch, RawBatch};
use triax_protocol::messages::{HealthVerdict, SensorHealthReport};
use triax_protocol::{from_json, BuildingId, SensorId};

use super::status;
use super::util::*;

const BUILDING: &str = "hhealth";
const OK: &str = "hs-ok";
const STUCK: &str = "hs-stuck";
const SECOND_NS: i64 = 1_000_000_000;

/// One sensor in the field: the simulator, and the batches it has sent.
struct Node {
    id: &'static str,
    field: FieldSensor,
    sequence: u64,
}

impl Node {
    fn new(id: &'static str, seed: u64, start_ns: i64) -> Node {
        let config = FieldConfig {
            seed,
            start_ns,
            start_hour: 12.0,
            // A second a batch: three minutes of sensor time in 180 batches.
            batch_samples: 100,
            ..FieldConfig::default()
        };
        Node {
            id,
            field: FieldSensor::new(field_sensor_truth(), config),
            sequence: 0,
        }
    }

    fn next(&mut self) -> Vec<u8> {
        let mut samples = Vec::new();
        let info = self.field.next_batch(&mut samples);
        let batch = RawBatch {
            header: BatchHeader {
                sensor_id: SensorId::new(self.id).unwrap(),
                sequence: self.sequence,
                timestamp_ns: info.timestamp_ns,
                sample_rate_hz: info.sample_rate_hz,
            },
            temperature_c: info.temperature_c,
            samples,
        };
        self.sequence += 1;
        batch.encode()
    }
}

type Received = std::sync::Arc<std::sync::Mutex<Vec<Vec<u8>>>>;

/// Collects every payload on `key` into a shared list.
async fn gather(
    session: &zenoh::Session,
    key: String,
) -> (zenoh::pubsub::Subscriber<()>, Received) {
    let got: Received = Default::default();
    let g = got.clone();
    let sub = session
        .declare_subscriber(key)
        .callback(move |s| g.lock().unwrap().push(s.payload().to_bytes().to_vec()))
        .await
        .unwrap();
    (sub, got)
}

fn reports(got: &Received, sensor: &str) -> Vec<SensorHealthReport> {
    got.lock()
        .unwrap()
        .iter()
        .map(|p| from_json::<SensorHealthReport>(p).expect("health report decodes"))
        .filter(|r| r.sensor_id.as_str() == sensor)
        .collect()
}

/// Waits until batch `sequence` of every sensor of `sensors` has been published.
async fn wait_published(corrected: &Received, sensors: &[&str], sequence: u64) {
    wait_until(
        &format!("batch {sequence} of {sensors:?} published"),
        || {
            sensors.iter().all(|s| {
                batches(corrected, s)
                    .iter()
                    .any(|(b, _)| b.header.sequence == sequence)
            })
        },
    )
    .await;
}

fn batches(got: &Received, sensor: &str) -> Vec<(CorrectedBatch, Vec<u8>)> {
    got.lock()
        .unwrap()
        .iter()
        .map(|p| (CorrectedBatch::decode(p).unwrap(), p.clone()))
        .filter(|(b, _)| b.header.sensor_id.as_str() == sensor)
        .collect()
}

/// Every sample of `b` carries `calibration_suspect`, or none does.
fn suspect(b: &CorrectedBatch) -> bool {
    let on = b
        .samples
        .iter()
        .filter(|s| s.flags & flags::CALIBRATION_SUSPECT != 0)
        .count();
    assert!(
        on == 0 || on == b.samples.len(),
        "#{}: {on} of {} samples flagged suspect",
        b.header.sequence,
        b.samples.len()
    );
    assert_eq!(on > 0, b.batch_flags & flags::CALIBRATION_SUSPECT != 0);
    on > 0
}

async fn send(session: &zenoh::Session, nodes: &mut [Node], batches: usize) {
    let mut publishers = Vec::new();
    for n in nodes.iter() {
        let p = session
            .declare_publisher(key_raw(BUILDING, n.id))
            .congestion_control(zenoh::qos::CongestionControl::Block)
            .await
            .unwrap();
        wait_matching(&p).await;
        publishers.push(p);
    }
    for _ in 0..batches {
        for (n, p) in nodes.iter_mut().zip(&publishers) {
            p.put(n.next()).await.unwrap();
        }
    }
}

async fn health_query(session: &zenoh::Session, selector: &str) -> Vec<Result<Vec<u8>, String>> {
    let replies = session
        .get(selector)
        .timeout(std::time::Duration::from_secs(5))
        .await
        .unwrap();
    let mut out = Vec::new();
    while let Ok(r) = replies.recv_async().await {
        out.push(match r.result() {
            Ok(s) => Ok(s.payload().to_bytes().to_vec()),
            Err(e) => Err(String::from_utf8_lossy(&e.payload().to_bytes()).into_owned()),
        });
    }
    out
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_frozen_channel_makes_its_record_suspect_and_flags_its_samples() {
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("store");
    let truth = field_sensor_truth();
    let record = |id: &str, seed: u64, version: u64| {
        let mut r = calibrate(&truth, seed, id).unwrap();
        r.version = version;
        r
    };
    seed_store(&store, &[record(OK, 11, 1), record(STUCK, 12, 1)]);
    let mut cfg = config(BUILDING, &store);
    cfg.health = Some(HealthSettings {
        publish_interval_s: 10.0,
        // Sensor time runs far ahead of the gateway's clock here.
        clock_watch_ms: None,
        ..HealthSettings::default()
    });
    let gateway = start(cfg.clone()).await;
    let session = client(&gateway.endpoint).await;
    let (_hs, health) = gather(&session, format!("triax/{BUILDING}/health/*")).await;
    let (_cs, corrected) = gather(&session, format!("triax/{BUILDING}/corrected/*")).await;

    let fault_ns = EPOCH_NS + 60 * SECOND_NS + 250_000_000;
    let mut nodes = [Node::new(OK, 1, EPOCH_NS), Node::new(STUCK, 2, EPOCH_NS)];
    nodes[1].field.inject(fault_ns, Fault::Stuck { channel: 1 });
    // Three minutes of sensor time, thirty seconds at a time: each stretch arrives before the
    // next is sent, so no queue on the way overflows whatever the machine's pace.
    for _ in 0..6 {
        send(&session, &mut nodes, 30).await;
        let last = nodes[0].sequence - 1;
        wait_published(&corrected, &[OK, STUCK], last).await;
    }
    wait_until("a suspect report", || {
        reports(&health, STUCK)
            .iter()
            .any(|r| r.verdict == HealthVerdict::Suspect)
    })
    .await;

    // The report: suspect on the frozen channel's stuck test, within a minute, flagged from
    // the end of the batch that decided.
    let first_suspect = reports(&health, STUCK)
        .into_iter()
        .find(|r| r.verdict == HealthVerdict::Suspect)
        .unwrap();
    let flagged_from = first_suspect
        .flagged_from_ns
        .expect("a suspect report says from when");
    let delay_s = (flagged_from - fault_ns) as f64 * 1e-9;
    assert!(
        (0.0..=60.0).contains(&delay_s),
        "flagged {delay_s} s after the fault"
    );
    let stuck = first_suspect
        .tests
        .iter()
        .find(|t| t.verdict == HealthVerdict::Suspect)
        .unwrap();
    assert_eq!((stuck.test.as_str(), stuck.channel), ("stuck", Some(1)));
    assert_eq!(stuck.unit, "s");
    assert!(first_suspect.suspect_since_ns.unwrap() >= fault_ns);
    assert_eq!(first_suspect.calibration_version, 1);
    assert!(
        first_suspect.quality.availability > 0.999,
        "{:?}",
        first_suspect.quality
    );

    // The samples: flagged exactly from that time on.
    let stuck_batches = batches(&corrected, STUCK);
    assert_eq!(stuck_batches.len(), 180);
    for (b, _) in &stuck_batches {
        assert_eq!(
            suspect(b),
            b.header.timestamp_ns >= flagged_from,
            "#{} at {}",
            b.header.sequence,
            b.header.timestamp_ns
        );
    }
    // The healthy sensor: never flagged, reports all ok, one every 10 s of sensor time.
    assert!(batches(&corrected, OK).iter().all(|(b, _)| !suspect(b)));
    let ok_reports = reports(&health, OK);
    let verdicts: Vec<_> = ok_reports.iter().map(|r| r.verdict).collect();
    assert!(
        verdicts.iter().all(|v| *v == HealthVerdict::Ok),
        "{verdicts:?}"
    );
    assert!(
        (17..=19).contains(&ok_reports.len()),
        "{} reports",
        ok_reports.len()
    );

    // The queryable: the suspect sensor alone at verdict=suspect, both without; a bad
    // parameter is refused by name.
    let only = health_query(
        &session,
        &format!("triax/{BUILDING}/health/*?verdict=suspect"),
    )
    .await;
    assert_eq!(only.len(), 1, "{only:?}");
    let r: SensorHealthReport = from_json(only[0].as_ref().unwrap()).unwrap();
    assert_eq!(
        (r.sensor_id.as_str(), r.flagged_from_ns),
        (STUCK, Some(flagged_from))
    );
    assert_eq!(
        health_query(&session, &format!("triax/{BUILDING}/health/*"))
            .await
            .len(),
        2
    );
    let bad = health_query(&session, &format!("triax/{BUILDING}/health/{OK}?level=x")).await;
    assert!(
        matches!(bad.as_slice(), [Err(e)] if e.contains("\"level\"")),
        "{bad:?}"
    );
    // Status.
    let s = status(&session, BUILDING).await;
    let of = |id: &str| {
        s.sensors
            .iter()
            .find(|x| x.sensor_id.as_str() == id)
            .unwrap()
            .clone()
    };
    assert_eq!(of(STUCK).health, Some(HealthVerdict::Suspect));
    assert_eq!(of(STUCK).suspect_from_ns, Some(flagged_from));
    assert_eq!(
        (of(OK).health, of(OK).suspect_from_ns),
        (Some(HealthVerdict::Ok), None)
    );

    // The lab's `due`: across buildings, the suspect sensor with its evidence.
    let (due, problems) = triax_lab::due::gather(
        &session,
        &[],
        HealthVerdict::Watch,
        std::time::Duration::from_secs(5),
    )
    .await
    .unwrap();
    assert!(problems.is_empty(), "{problems:?}");
    assert_eq!(due.len(), 1);
    assert_eq!(triax_lab::due::due_count(&due), 1);
    let table = triax_lab::due::render(&due, &problems);
    assert!(
        table.contains(STUCK) && table.contains("stuck[1]"),
        "{table}"
    );

    // A restart: the latch holds with fresh tests, on healthy data too.
    gateway.stop().await;
    let gateway = start(cfg.clone()).await;
    let session = client(&gateway.endpoint).await;
    let (_cs2, after) = gather(&session, format!("triax/{BUILDING}/corrected/*")).await;
    let resume_ns = EPOCH_NS + 200 * SECOND_NS;
    let mut healed = [Node::new(STUCK, 3, resume_ns)];
    healed[0].sequence = 200;
    send(&session, &mut healed, 20).await;
    wait_until("the batches after the restart", || {
        batches(&after, STUCK).len() == 20
    })
    .await;
    assert!(batches(&after, STUCK).iter().all(|(b, _)| suspect(b)));

    // The replay of version 1 reproduces the live bytes, flags included; with the latest
    // record (the same one here) too.
    let b = BuildingId::new(BUILDING).unwrap();
    let sensor = SensorId::new(STUCK).unwrap();
    let mut kept: BTreeMap<u64, Vec<u8>> = BTreeMap::new();
    fetch(
        &session,
        &HistoryRequest::sensor(&b, &sensor),
        TIMEOUT,
        &mut |r| {
            kept.insert(r.batch.header.sequence, r.payload);
        },
    )
    .await
    .unwrap();
    let live: Vec<_> = stuck_batches
        .iter()
        .chain(&batches(&after, STUCK))
        .cloned()
        .collect();
    let compared = live
        .iter()
        .filter(|(l, payload)| {
            kept.get(&l.header.sequence)
                .map(|k| assert!(k == payload, "replay of #{} differs", l.header.sequence))
                .is_some()
        })
        .count();
    assert!(compared >= 190, "{compared} batches compared");

    // A new record ends the flag; replays with it carry none, with version 1 still do.
    gateway.stop().await;
    seed_store(&store, &[record(STUCK, 13, 2)]);
    let gateway = start(cfg).await;
    let session = client(&gateway.endpoint).await;
    let (_cs3, renewed) = gather(&session, format!("triax/{BUILDING}/corrected/*")).await;
    let mut again = [Node::new(STUCK, 4, resume_ns + 30 * SECOND_NS)];
    again[0].sequence = 230;
    send(&session, &mut again, 10).await;
    wait_until("the batches under version 2", || {
        batches(&renewed, STUCK).len() == 10
    })
    .await;
    assert!(batches(&renewed, STUCK).iter().all(|(b, _)| !suspect(b)));
    let mut latest = HistoryRequest::sensor(&b, &sensor);
    latest.calibration = Some("latest".into());
    latest.to_ns = Some(resume_ns);
    let mut replayed = 0;
    fetch(&session, &latest, TIMEOUT, &mut |r| {
        assert!(!suspect(&r.batch), "re-corrected with version 2");
        assert_eq!(r.batch.info.calibration_version, 2);
        replayed += 1;
    })
    .await
    .unwrap();
    assert!(replayed >= 170, "{replayed}");
    gateway.stop().await;
}

/// Two co-located sensors share the building's motion; B's x channel reads 5 % high against
/// its record (a part changed after its calibration). Within one estimate (five minutes here)
/// the pair's `colocated_absolute` test on x is `suspect` in both sensors' reports, naming the
/// other as `peer`; y and z are not; both records are marked and their samples flagged, since
/// a pair alone cannot tell which of its two changed.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_co_located_pair_finds_a_horizontal_gain_change() {
    const A: &str = "hp-a";
    const B: &str = "hp-b";
    const PAIR: &str = "hhealth-pair";
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("store");
    let truth = field_sensor_truth();
    let mut ra = calibrate(&truth, 21, A).unwrap();
    let mut rb = calibrate(&truth, 22, B).unwrap();
    ra.version = 1;
    rb.version = 1;
    seed_store(&store, &[ra, rb]);
    let mut cfg = config(PAIR, &store);
    let toml = format!(
        "[health]\nclock_watch_ms = 0\n[[health.colocated]]\na = \"{A}\"\nb = \"{B}\"\nestimate_s = 300\nabsolute_min_estimates = 1\n"
    );
    let parsed = triax_gateway::config::FileConfig::parse(&toml, std::path::Path::new("pair.toml"))
        .unwrap()
        .into_config()
        .unwrap();
    cfg.health = parsed.health;
    let gateway = start(cfg).await;
    let session = client(&gateway.endpoint).await;
    let (_hs, health) = gather(&session, format!("triax/{PAIR}/health/*")).await;
    let (_cs, corrected) = gather(&session, format!("triax/{PAIR}/corrected/*")).await;

    let field = |seed| FieldConfig {
        seed,
        start_hour: 12.0,
        batch_samples: 100,
        ..FieldConfig::default()
    };
    let mut a = FieldSensor::new(truth.clone(), field(5));
    let mut b = FieldSensor::new(truth.clone(), field(6));
    b.inject(
        EPOCH_NS,
        Fault::GainStep {
            channel: 0,
            relative: 0.05,
        },
    );
    let mut motion = triax_health::sim::Vibration::new(7, 100.0);
    let mut publishers = Vec::new();
    for id in [A, B] {
        let p = session
            .declare_publisher(key_raw(PAIR, id))
            .congestion_control(zenoh::qos::CongestionControl::Block)
            .await
            .unwrap();
        wait_matching(&p).await;
        publishers.push(p);
    }
    let (mut shared, mut samples) = (Vec::new(), Vec::new());
    const BATCHES: u64 = 420;
    const STRETCH: u64 = 20;
    for sequence in 0..BATCHES {
        motion.batch(0.02, 100, &mut shared);
        for (id, (sensor, p)) in [A, B]
            .iter()
            .zip([&mut a, &mut b].into_iter().zip(&publishers))
        {
            let info = sensor.next_batch_with(&mut samples, &shared);
            let batch = RawBatch {
                header: BatchHeader {
                    sensor_id: SensorId::new(*id).unwrap(),
                    sequence,
                    timestamp_ns: info.timestamp_ns,
                    sample_rate_hz: info.sample_rate_hz,
                },
                temperature_c: info.temperature_c,
                samples: samples.clone(),
            };
            p.put(batch.encode()).await.unwrap();
        }
        // Live sensors arrive together; a burst compresses minutes into milliseconds, and
        // one sensor's worker may then run ahead of the other's by more than the pair holds
        // (8 segments, 40 s). Both are let through a stretch before the next one is sent.
        if (sequence + 1) % STRETCH == 0 || sequence + 1 == BATCHES {
            wait_published(&corrected, &[A, B], sequence).await;
        }
    }
    wait_until("both sensors reported suspect", || {
        [A, B].iter().all(|s| {
            reports(&health, s)
                .iter()
                .any(|r| r.verdict == HealthVerdict::Suspect)
        })
    })
    .await;
    for (me, peer) in [(A, B), (B, A)] {
        let r = reports(&health, me)
            .into_iter()
            .find(|r| r.verdict == HealthVerdict::Suspect)
            .unwrap();
        let pair: Vec<_> = r.tests.iter().filter(|t| t.peer.is_some()).collect();
        assert_eq!(pair.len(), 6, "absolute and relative per axis: {pair:?}");
        assert!(pair
            .iter()
            .all(|t| t.peer.as_ref().unwrap().as_str() == peer));
        let suspect_tests: Vec<_> = r
            .tests
            .iter()
            .filter(|t| t.verdict == HealthVerdict::Suspect)
            .map(|t| (t.test.as_str(), t.channel))
            .collect();
        assert_eq!(
            suspect_tests,
            [("colocated_absolute", Some(0))],
            "{me}: {:?}",
            r.tests
        );
        let x = pair
            .iter()
            .find(|t| t.test == "colocated_absolute" && t.channel == Some(0))
            .unwrap();
        let d = x.statistic.unwrap();
        assert!(
            (d - 0.05).abs() < 5.0 * x.uncertainty.unwrap(),
            "{me}: r − 1 = {d}"
        );
        assert_eq!(
            r.suspect_since_ns, x.since_ns,
            "{me}: the pair's evidence dates it"
        );
        let flagged_from = r.flagged_from_ns.unwrap();
        assert!(batches(&corrected, me)
            .iter()
            .all(|(b, _)| suspect(b) == (b.header.timestamp_ns >= flagged_from)));
    }
    gateway.stop().await;
}
