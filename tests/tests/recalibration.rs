//! Recalibration across many buildings, through a real `zenohd` router on loopback: the lab
//! (registry server and pushes, as library calls), gateways of several buildings and simulated
//! sensor nodes, all Zenoh clients of the router, multicast scouting off.
//!
//! - `pushes_reach_their_building_only_and_swap_between_batches`: a building with two gateways
//!   and one with one; each push is acknowledged by every gateway of its building and changes
//!   nothing elsewhere. While a sensor node streams, a new version is pushed: no batch is lost,
//!   every batch is corrected wholly with one version (its values match that version's
//!   correction), versions never go back, and every batch sent after the acknowledgement carries
//!   the new version.
//! - `gateway_stopped_during_a_push_catches_up_after_restart`: the push finds no gateway and
//!   says so; the gateway, restarted on its store, gets the record from the registry with no
//!   operator action.
//! - `forged_replayed_and_invalid_pushes_are_refused_with_their_reason`: tampered signature,
//!   untrusted key, replay of an older version, another record under a used version, a record
//!   for another sensor, an invalid record; each refused with its reason, counted, and copied on
//!   the ack key; an identical re-push is accepted as already stored; the version in force stays.
//!
//! Needs `zenohd` 1.10 on PATH (`cargo install zenohd --version 1.10.2 --locked`; CI installs
//! it). Without it the tests fail and say so.

mod util;

use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Arc;
use std::time::Duration;

use tokio::sync::oneshot;
use tokio::task::JoinHandle;
use triax_calibration::corrector::Corrector;
use triax_gateway::{Config, Gateway, GatewayCounters, SensorTable};
use triax_lab::push::{push_all, push_one, Push, PushReport};
use triax_lab::registry::{Recorded, Registry};
use triax_lab::serve::RegistryServer;
use triax_protocol::batch::flags;
use triax_protocol::messages::{PushAck, PushOutcome, RefusalReason};
use triax_protocol::record::{sample, CalibrationRecord, SetKind};
use triax_protocol::signing::{sign, LabSigningKey};
use triax_protocol::{from_json, BuildingId, CorrectedBatch, Key, SensorId};
use util::{raw, Router, TIMEOUT};
use zenoh::qos::CongestionControl;

/// How long a push waits for acknowledgements when no gateway is expected to answer.
const SHORT_TIMEOUT: Duration = Duration::from_secs(1);

/// A Zenoh client of the router.
async fn client(router: &Router) -> zenoh::Session {
    let config = router
        .client_settings()
        .to_config()
        .expect("valid client config");
    zenoh::open(config).await.expect("client session opens")
}

fn lab_key() -> LabSigningKey {
    LabSigningKey::from_bytes(&[7; 32])
}

fn b(id: &str) -> BuildingId {
    BuildingId::new(id).unwrap()
}

fn s(id: &str) -> SensorId {
    SensorId::new(id).unwrap()
}

/// The sample record with its offsets moved by `shift_mps2`, so versions are told apart by
/// their corrected values.
fn record(sensor: &str, version: u64, shift_mps2: f64) -> CalibrationRecord {
    let mut r = sample::record(sensor, version);
    for set in [&mut r.static_set, &mut r.dynamic] {
        for q in &mut set.offset {
            *q += shift_mps2;
        }
    }
    r
}

/// A gateway of `building`, client of the router, trusting the lab key, asking the registry
/// every `catchup_s` seconds.
struct Gw {
    table: Arc<SensorTable>,
    counters: Arc<GatewayCounters>,
    stop: Option<oneshot::Sender<()>>,
    task: JoinHandle<Result<(), triax_gateway::GatewayError>>,
}

fn gateway_config(
    router: &Router,
    building: &str,
    name: &str,
    store: &std::path::Path,
    catchup_s: f64,
) -> Config {
    let mut c = Config::for_tests(building, store, vec![]);
    c.gateway_name = name.to_owned();
    c.zenoh = router.client_settings();
    c.calibration.trusted_lab_keys = vec![lab_key().verifying_key()];
    c.calibration.catchup_interval = Some(Duration::from_secs_f64(catchup_s));
    c.calibration.catchup_timeout = Duration::from_secs(2);
    c.workers = 1;
    c
}

async fn start_gateway(config: Config) -> Gw {
    let gateway = Gateway::start(config).await.expect("gateway starts");
    let table = gateway.sensors().clone();
    let counters = gateway.counters().clone();
    let (tx, rx) = oneshot::channel::<()>();
    let task = tokio::spawn(gateway.run_until(async move {
        let _ = rx.await;
    }));
    Gw {
        table,
        counters,
        stop: Some(tx),
        task,
    }
}

impl Gw {
    fn version(&self, sensor: &str) -> Option<u64> {
        self.table
            .versions()
            .into_iter()
            .find_map(|(id, v)| (id.as_str() == sensor).then_some(v))
    }

    async fn wait_version(&self, sensor: &str, version: u64) {
        let deadline = tokio::time::Instant::now() + TIMEOUT;
        while self.version(sensor) != Some(version) {
            assert!(
                tokio::time::Instant::now() < deadline,
                "{sensor}: version {version} not in force in time (in force: {:?})",
                self.version(sensor)
            );
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
    }

    async fn stop(mut self) {
        if let Some(s) = self.stop.take() {
            let _ = s.send(());
        }
        tokio::time::timeout(TIMEOUT, &mut self.task)
            .await
            .expect("gateway stops in time")
            .expect("gateway task does not panic")
            .expect("gateway stops cleanly");
    }
}

/// Waits until `n` push queryables of `building` are reachable from `session` (a gateway's
/// declaration travels through the router).
async fn wait_gateways(session: &zenoh::Session, building: &str, sensor: &str, n: usize) {
    let querier_key = Key::CalibrationPush(b(building), s(sensor)).to_string();
    let querier = session
        .declare_querier(querier_key)
        .target(zenoh::query::QueryTarget::All)
        .await
        .expect("querier");
    let deadline = tokio::time::Instant::now() + TIMEOUT;
    while !querier
        .matching_status()
        .await
        .expect("matching status")
        .matching()
    {
        assert!(
            tokio::time::Instant::now() < deadline,
            "no gateway of {building} reachable in time"
        );
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    // Matching says "at least one". For more, wait until `n` gateways answer a status query:
    // each declares its push queryable before its status queryable, on the same link, so the
    // router that routed the status query knows the push queryables too.
    if n > 1 {
        while status_replies(session, building).await < n {
            assert!(
                tokio::time::Instant::now() < deadline,
                "fewer than {n} gateways of {building} answered in time"
            );
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
    }
}

/// How many gateways of `building` answer a status query.
async fn status_replies(session: &zenoh::Session, building: &str) -> usize {
    let replies = session
        .get(Key::Status(b(building)).to_string())
        .target(zenoh::query::QueryTarget::All)
        .consolidation(zenoh::query::ConsolidationMode::None)
        .timeout(Duration::from_millis(500))
        .await
        .expect("status query");
    let mut n = 0;
    while let Ok(reply) = replies.recv_async().await {
        n += usize::from(reply.result().is_ok());
    }
    n
}

/// Records in the registry (assigned to the buildings), then pushes to every building.
async fn push_recorded(
    session: &zenoh::Session,
    registry: &Registry,
    buildings: &[&str],
    records: &[CalibrationRecord],
    timeout: Duration,
) -> Vec<PushReport> {
    let buildings: Vec<BuildingId> = buildings.iter().map(|x| b(x)).collect();
    let recorded = registry
        .record(records, &buildings)
        .expect("registry works");
    assert!(
        recorded
            .iter()
            .all(|r| matches!(r, Recorded::Accepted { .. })),
        "{recorded:?}"
    );
    let pushes: Vec<Push> = records.iter().map(|r| Push::sign(r, &lab_key())).collect();
    push_all(session, &buildings, &pushes, timeout)
        .await
        .expect("push sent")
}

fn accepted_by(report: &PushReport) -> Vec<String> {
    let mut names: Vec<String> = report
        .acks
        .iter()
        .map(|a| {
            assert!(
                matches!(a.outcome, PushOutcome::Accepted { .. }),
                "{}: {:?}",
                a.gateway,
                a.outcome
            );
            a.gateway.clone()
        })
        .collect();
    names.sort();
    names
}

type Subscriber =
    zenoh::pubsub::Subscriber<zenoh::handlers::FifoChannelHandler<zenoh::sample::Sample>>;

/// Receives one corrected batch.
async fn receive(sub: &Subscriber, batches: &mut Vec<CorrectedBatch>) {
    let sample = tokio::time::timeout(TIMEOUT, sub.recv_async())
        .await
        .expect("corrected batches keep coming")
        .expect("subscriber open");
    batches.push(CorrectedBatch::decode(&sample.payload().to_bytes()).expect("batch decodes"));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn pushes_reach_their_building_only_and_swap_between_batches() {
    let router = Router::start().await;
    let dir = tempfile::tempdir().unwrap();
    let registry = Registry::new(dir.path().join("registry"));
    let lab = client(&router).await;
    let server = RegistryServer::start(&lab, registry.clone(), lab_key())
        .await
        .unwrap();

    let north_a = start_gateway(gateway_config(
        &router,
        "north",
        "gw-north-a",
        &dir.path().join("na"),
        30.0,
    ))
    .await;
    let north_b = start_gateway(gateway_config(
        &router,
        "north",
        "gw-north-b",
        &dir.path().join("nb"),
        30.0,
    ))
    .await;
    let south = start_gateway(gateway_config(
        &router,
        "south",
        "gw-south",
        &dir.path().join("s"),
        30.0,
    ))
    .await;
    wait_gateways(&lab, "north", "n-1", 2).await;
    wait_gateways(&lab, "south", "s-1", 1).await;

    // Version 1 everywhere: each building's gateways, and only them, acknowledge.
    let reports = push_recorded(
        &lab,
        &registry,
        &["north"],
        &[record("n-1", 1, 0.0)],
        TIMEOUT,
    )
    .await;
    assert_eq!(accepted_by(&reports[0]), ["gw-north-a", "gw-north-b"]);
    let reports = push_recorded(
        &lab,
        &registry,
        &["south"],
        &[record("s-1", 1, 0.0)],
        TIMEOUT,
    )
    .await;
    assert_eq!(accepted_by(&reports[0]), ["gw-south"]);
    assert_eq!(north_a.version("n-1"), Some(1));
    assert_eq!(north_b.version("n-1"), Some(1));
    assert_eq!(
        south.version("n-1"),
        None,
        "north's sensor never reaches south"
    );
    assert_eq!(
        north_a.version("s-1"),
        None,
        "south's sensor never reaches north"
    );

    // A sensor node in the south streams while version 2 is pushed.
    let node = client(&router).await;
    let corrected = node
        .declare_subscriber(Key::Corrected(b("south"), s("s-1")).to_string())
        .await
        .unwrap();
    let publisher = node
        .declare_publisher(Key::Raw(b("south"), s("s-1")).to_string())
        .congestion_control(CongestionControl::Block)
        .await
        .unwrap();
    let v_out = [0.25f32, -0.5, 1.0];
    let next_seq = Arc::new(AtomicU64::new(0));
    let running = Arc::new(AtomicBool::new(true));
    let streaming = {
        let (next_seq, running) = (next_seq.clone(), running.clone());
        tokio::spawn(async move {
            while running.load(Ordering::SeqCst) {
                // Taken before the put: a batch whose number is at or above a value read after
                // the acknowledgement was sent after it.
                let seq = next_seq.fetch_add(1, Ordering::SeqCst);
                publisher
                    .put(raw("s-1", seq, vec![v_out; 20]))
                    .await
                    .unwrap();
                tokio::time::sleep(Duration::from_millis(5)).await;
            }
        })
    };
    let mut batches: Vec<CorrectedBatch> = Vec::new();
    while batches
        .iter()
        .filter(|x| x.info.calibration_version == 1)
        .count()
        < 5
    {
        receive(&corrected, &mut batches).await;
    }
    let v2 = record("s-1", 2, 0.5);
    let reports = push_recorded(
        &lab,
        &registry,
        &["south"],
        std::slice::from_ref(&v2),
        TIMEOUT,
    )
    .await;
    let boundary = next_seq.load(Ordering::SeqCst);
    assert_eq!(accepted_by(&reports[0]), ["gw-south"]);
    while batches
        .last()
        .is_none_or(|x| x.header.sequence < boundary + 20)
    {
        receive(&corrected, &mut batches).await;
    }
    running.store(false, Ordering::SeqCst);
    streaming.await.unwrap();

    let expected = |version: u64| -> [f64; 3] {
        let r = if version == 1 {
            record("s-1", 1, 0.0)
        } else {
            v2.clone()
        };
        let c = Corrector::from_record(&r).unwrap();
        c.set(SetKind::Dynamic).accel(v_out.map(f64::from))
    };
    let (e1, e2) = (expected(1), expected(2));
    assert!(
        (e1[0] - e2[0]).abs() > 0.4,
        "versions are told apart by value"
    );
    let first = batches[0].header.sequence;
    let mut last_version = 0;
    for (i, batch) in batches.iter().enumerate() {
        let seq = batch.header.sequence;
        assert_eq!(seq, first + i as u64, "no batch lost or reordered");
        assert_eq!(
            batch.batch_flags & (flags::SEQUENCE_GAP | flags::DUPLICATE),
            0,
            "batch {seq}"
        );
        let v = batch.info.calibration_version;
        assert!(v == 1 || v == 2, "batch {seq}: version {v}");
        assert!(v >= last_version, "batch {seq}: version went back to {v}");
        last_version = v;
        if seq >= boundary {
            assert_eq!(v, 2, "batch {seq} was sent after the acknowledgement");
        }
        let want = if v == 1 { e1 } else { e2 };
        for sample in &batch.samples {
            for (got, want) in sample.accel_mps2.iter().zip(want) {
                let got = f64::from(*got);
                assert!(
                    (got - want).abs() < 1e-4,
                    "batch {seq} tagged v{v} has a value of another version: {got} vs {want}"
                );
            }
        }
    }
    assert!(batches.iter().any(|x| x.info.calibration_version == 2));

    // North: version 2 of its own sensor reaches both of its gateways; south is untouched.
    let reports = push_recorded(
        &lab,
        &registry,
        &["north"],
        &[record("n-1", 2, 0.5)],
        TIMEOUT,
    )
    .await;
    assert_eq!(accepted_by(&reports[0]), ["gw-north-a", "gw-north-b"]);
    assert_eq!(north_a.version("n-1"), Some(2));
    assert_eq!(north_b.version("n-1"), Some(2));
    assert_eq!(south.version("n-1"), None);
    assert_eq!(south.version("s-1"), Some(2));
    assert_eq!(north_a.version("s-1"), None);
    assert_eq!(south.counters.pushes_refused.load(Ordering::Relaxed), 0);

    server.stop().await;
    for g in [north_a, north_b, south] {
        g.stop().await;
    }
    drop(router);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn gateway_stopped_during_a_push_catches_up_after_restart() {
    let router = Router::start().await;
    let dir = tempfile::tempdir().unwrap();
    let registry = Registry::new(dir.path().join("registry"));
    let lab = client(&router).await;
    let server = RegistryServer::start(&lab, registry.clone(), lab_key())
        .await
        .unwrap();
    let store = dir.path().join("east");
    let other = start_gateway(gateway_config(
        &router,
        "west",
        "gw-west",
        &dir.path().join("w"),
        0.5,
    ))
    .await;
    let east = start_gateway(gateway_config(&router, "east", "gw-east", &store, 0.5)).await;
    wait_gateways(&lab, "east", "e-1", 1).await;
    let reports = push_recorded(
        &lab,
        &registry,
        &["east"],
        &[record("e-1", 1, 0.0)],
        TIMEOUT,
    )
    .await;
    assert_eq!(accepted_by(&reports[0]), ["gw-east"]);
    east.stop().await;

    // Pushed while the gateway is down: nobody answers, and the push says so.
    let reports = push_recorded(
        &lab,
        &registry,
        &["east"],
        &[record("e-1", 2, 0.5), record("e-2", 1, 0.0)],
        SHORT_TIMEOUT,
    )
    .await;
    assert!(reports
        .iter()
        .all(|r| r.acks.is_empty() && !r.is_success(1)));

    // Back on the same store, it catches up from the registry by itself.
    let east = start_gateway(gateway_config(&router, "east", "gw-east", &store, 0.5)).await;
    east.wait_version("e-1", 2).await;
    east.wait_version("e-2", 1).await;
    assert_eq!(east.counters.pushes_refused.load(Ordering::Relaxed), 0);
    // Another building's gateway, asking all along, was never given east's sensors. A record
    // of its own, registered after east's, marks a catch-up round that saw east's records too.
    registry
        .record(&[record("w-1", 1, 0.0)], &[b("west")])
        .expect("registry works");
    other.wait_version("w-1", 1).await;
    assert_eq!(other.version("e-1"), None);
    assert_eq!(other.version("e-2"), None);

    server.stop().await;
    east.stop().await;
    other.stop().await;
    // The caught-up record is durable: it is in the store after the gateway stopped.
    let s = triax_calibration_store::Store::open(&store).unwrap();
    assert_eq!(
        s.current(&self::s("e-1")).unwrap().map(|r| r.version),
        Some(2)
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn forged_replayed_and_invalid_pushes_are_refused_with_their_reason() {
    let router = Router::start().await;
    let dir = tempfile::tempdir().unwrap();
    let lab = client(&router).await;
    let gw = start_gateway(gateway_config(
        &router,
        "west",
        "gw-west",
        &dir.path().join("w"),
        30.0,
    ))
    .await;
    wait_gateways(&lab, "west", "w-1", 1).await;
    let acks_copy = lab
        .declare_subscriber(Key::CalibrationAck(b("west"), s("w-1")).to_string())
        .await
        .unwrap();

    let key = lab_key();
    let v1 = sign(&record("w-1", 1, 0.0), &key);
    let v2 = sign(&record("w-1", 2, 0.5), &key);
    let push = |sensor: &str, signed: triax_protocol::messages::SignedRecord| {
        let lab = lab.clone();
        let sensor = s(sensor);
        async move {
            let p = Push::from_signed(signed).unwrap();
            let p = Push { sensor, ..p };
            let r = push_one(&lab, &b("west"), &p, TIMEOUT).await.unwrap();
            assert_eq!(r.acks.len(), 1, "{:?}", r.errors);
            r.acks[0].outcome.clone()
        }
    };
    let reason = |o: PushOutcome| match o {
        PushOutcome::Refused { reason, .. } => reason,
        other => panic!("accepted: {other:?}"),
    };
    assert!(matches!(
        push("w-1", v1.clone()).await,
        PushOutcome::Accepted {
            version: 1,
            already_stored: false
        }
    ));
    assert!(matches!(
        push("w-1", v2.clone()).await,
        PushOutcome::Accepted {
            version: 2,
            already_stored: false
        }
    ));

    let mut tampered = sign(&record("w-1", 3, 0.0), &key);
    tampered.record_json = tampered
        .record_json
        .replace("\"version\":3", "\"version\":4");
    assert_eq!(
        reason(push("w-1", tampered).await),
        RefusalReason::BadSignature
    );
    let foreign = sign(&record("w-1", 3, 0.0), &LabSigningKey::from_bytes(&[8; 32]));
    assert_eq!(
        reason(push("w-1", foreign).await),
        RefusalReason::UnknownKey
    );
    assert_eq!(
        reason(push("w-1", v1).await),
        RefusalReason::StaleVersion,
        "replay"
    );
    let other_v2 = sign(&record("w-1", 2, 0.25), &key);
    assert_eq!(
        reason(push("w-1", other_v2).await),
        RefusalReason::StaleVersion,
        "rollback under a used version"
    );
    let for_w2 = sign(&record("w-2", 3, 0.0), &key);
    assert_eq!(
        reason(push("w-1", for_w2).await),
        RefusalReason::WrongSensor
    );
    let mut singular = record("w-1", 3, 0.0);
    singular.dynamic.sensitivity = [[1.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]];
    assert_eq!(
        reason(push("w-1", sign(&singular, &key)).await),
        RefusalReason::InvalidRecord
    );
    assert_eq!(
        push("w-1", v2).await,
        PushOutcome::Accepted {
            version: 2,
            already_stored: true
        },
        "an identical re-push"
    );

    assert_eq!(gw.version("w-1"), Some(2));
    assert_eq!(gw.version("w-2"), None);
    assert_eq!(gw.counters.pushes_accepted.load(Ordering::Relaxed), 3);
    assert_eq!(gw.counters.pushes_refused.load(Ordering::Relaxed), 6);
    // Every answer is also put on the ack key, in order.
    let mut copies = Vec::new();
    while copies.len() < 9 {
        let sample = tokio::time::timeout(TIMEOUT, acks_copy.recv_async())
            .await
            .expect("every answer is copied on the ack key")
            .unwrap();
        let ack: PushAck = from_json(&sample.payload().to_bytes()).unwrap();
        assert_eq!(ack.gateway, "gw-west");
        copies.push(ack.outcome);
    }
    assert_eq!(
        copies
            .iter()
            .filter(|o| matches!(o, PushOutcome::Refused { .. }))
            .count(),
        6
    );
    gw.stop().await;
    drop(router);
}
