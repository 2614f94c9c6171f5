//! The example Zenoh configurations under deploy/zenoh/ are valid for the Zenoh this workspace
//! builds with: each parses with `zenoh::Config::from_file`, and the settings the deployment
//! guide relies on (mode, no multicast scouting, mTLS, access control on) are what they say.
//!
//! `only_the_labs_certificate_can_push_through_the_site_router`: the shipped site router run by
//! a real `zenohd` with certificates the test makes (`rcgen`): the lab's certificate pushes; the
//! same signed push from another certificate of the same CA or from the building LAN reaches no
//! gateway; the LAN's raw and corrected streams flow.
//!
//! `every_identity_does_what_it_may_and_nothing_else`: the shipped secured site router (every
//! party over mTLS, identified by its certificate): lab, gateway, node, consumer and alerting
//! each do their part; each is refused what belongs to another.

mod util;

use std::path::{Path, PathBuf};
use std::time::Duration;

use rcgen::{BasicConstraints, CertificateParams, DnType, IsCa, Issuer, KeyPair};
use triax_gateway::{Config, Gateway};
use triax_lab::push::{push_one, Push};
use triax_protocol::record::sample;
use triax_protocol::signing::LabSigningKey;
use triax_protocol::{BuildingId, Key};

fn deploy_dir() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../deploy/zenoh")
}

fn load(name: &str) -> zenoh::Config {
    let path = deploy_dir().join(name);
    zenoh::Config::from_file(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

#[test]
fn every_example_config_parses() {
    let mut names: Vec<String> = std::fs::read_dir(deploy_dir())
        .expect("deploy/zenoh exists")
        .filter_map(|e| e.ok())
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .filter(|n| n.ends_with(".json5"))
        .collect();
    names.sort();
    assert_eq!(
        names,
        [
            "gateway-client.json5",
            "lab-client.json5",
            "lab-router.json5",
            "site-router-secured.json5",
            "site-router.json5",
            "tls-client.json5"
        ]
    );
    for name in &names {
        let c = load(name);
        assert_eq!(
            c.get_json("scouting/multicast/enabled").unwrap(),
            "false",
            "{name}"
        );
    }
}

#[test]
fn routers_use_mtls_and_access_control() {
    for name in [
        "site-router.json5",
        "site-router-secured.json5",
        "lab-router.json5",
    ] {
        let c = load(name);
        assert_eq!(c.get_json("mode").unwrap(), "\"router\"", "{name}");
        assert_eq!(
            c.get_json("transport/link/tls/enable_mtls").unwrap(),
            "true",
            "{name}"
        );
        assert_eq!(
            c.get_json("access_control/enabled").unwrap(),
            "true",
            "{name}"
        );
        assert_eq!(
            c.get_json("access_control/default_permission").unwrap(),
            "\"deny\"",
            "{name}"
        );
    }
    let site = load("site-router.json5")
        .get_json("access_control/subjects")
        .unwrap();
    assert!(site.contains("triax-lab"), "{site}");
    for name in [
        "gateway-client.json5",
        "lab-client.json5",
        "tls-client.json5",
    ] {
        assert_eq!(load(name).get_json("mode").unwrap(), "\"client\"", "{name}");
    }
}

/// The deployment's certificates, written under `dir`: a CA, the site router's server
/// certificate (for 127.0.0.1), and client certificates with the given common names.
fn make_certificates(dir: &Path, clients: &[&str]) {
    let mut ca_params = CertificateParams::new(Vec::<String>::new()).unwrap();
    ca_params.is_ca = IsCa::Ca(BasicConstraints::Unconstrained);
    ca_params
        .distinguished_name
        .push(DnType::CommonName, "triax test CA");
    let ca_key = KeyPair::generate().unwrap();
    let ca = ca_params.self_signed(&ca_key).unwrap();
    std::fs::write(dir.join("ca.pem"), ca.pem()).unwrap();
    let issuer = Issuer::new(ca_params, ca_key);
    let leaf = |name: &str, sans: Vec<String>| {
        let mut p = CertificateParams::new(sans).unwrap();
        p.distinguished_name.push(DnType::CommonName, name);
        let key = KeyPair::generate().unwrap();
        let cert = p.signed_by(&key, &issuer).unwrap();
        std::fs::write(dir.join(format!("{name}.pem")), cert.pem()).unwrap();
        std::fs::write(dir.join(format!("{name}.key")), key.serialize_pem()).unwrap();
    };
    leaf(
        "site-router",
        vec!["127.0.0.1".to_owned(), "localhost".to_owned()],
    );
    for c in clients {
        leaf(c, vec![(*c).to_owned()]);
    }
}

/// `deploy/zenoh/site-router-secured.json5` as shipped, with only its certificate paths and
/// listener moved to the test's directory and a loopback port.
fn secured_router_config(dir: &Path, tls_port: u16) -> PathBuf {
    let shipped = std::fs::read_to_string(deploy_dir().join("site-router-secured.json5")).unwrap();
    let listen = r#"endpoints: ["tls/0.0.0.0:7448"],"#;
    assert!(
        shipped.contains(listen),
        "the shipped listener moved: update this test"
    );
    let text = shipped
        .replace(
            listen,
            &format!(r#"endpoints: ["tls/127.0.0.1:{tls_port}"],"#),
        )
        .replace("/etc/triax/tls/", &format!("{}/", dir.display()));
    let path = dir.join("site-router-secured.json5");
    std::fs::write(&path, text).unwrap();
    path
}

/// `deploy/zenoh/site-router.json5` as shipped, with only its certificate paths and listeners
/// moved to the test's directory and loopback ports: the access control under test is the file's.
fn site_router_config(dir: &Path, lan_port: u16, tls_port: u16) -> PathBuf {
    let shipped = std::fs::read_to_string(deploy_dir().join("site-router.json5")).unwrap();
    let listen = r#"endpoints: ["tcp/0.0.0.0:7447", "udp/0.0.0.0:7447", "tls/0.0.0.0:7448"],"#;
    assert!(
        shipped.contains(listen),
        "the shipped listeners moved: update this test"
    );
    let text = shipped
        .replace(
            listen,
            &format!(r#"endpoints: ["tcp/127.0.0.1:{lan_port}", "tls/127.0.0.1:{tls_port}"],"#),
        )
        .replace("/etc/triax/tls/", &format!("{}/", dir.display()));
    let path = dir.join("site-router.json5");
    std::fs::write(&path, text).unwrap();
    path
}

/// A client session over mTLS presenting `name`'s certificate.
async fn tls_client(dir: &Path, tls_port: u16, name: &str) -> zenoh::Session {
    zenoh::open(tls_client_config(dir, tls_port, name))
        .await
        .expect("TLS client session opens")
}

/// `deploy/zenoh/tls-client.json5` as shipped, presenting `name`'s certificate from `dir`.
fn tls_client_config(dir: &Path, tls_port: u16, name: &str) -> zenoh::Config {
    let shipped = std::fs::read_to_string(deploy_dir().join("tls-client.json5")).unwrap();
    let text = shipped
        .replace(
            "tls/site-router.example.org:7448",
            &format!("tls/127.0.0.1:{tls_port}"),
        )
        .replace(
            "/etc/triax/tls/client.",
            &format!("{}/{name}.", dir.display()),
        )
        .replace("/etc/triax/tls/", &format!("{}/", dir.display()));
    let path = dir.join(format!("{name}-client.json5"));
    std::fs::write(&path, text).unwrap();
    zenoh::Config::from_file(&path).expect("the shipped TLS client configuration loads")
}

/// `zenohd` with a configuration file, killed when dropped.
struct Zenohd(std::process::Child);

impl Zenohd {
    fn start(config: &Path) -> Zenohd {
        Zenohd(
            std::process::Command::new("zenohd")
                .arg("-c")
                .arg(config)
                .stdout(std::process::Stdio::null())
                .stderr(std::process::Stdio::null())
                .spawn()
                .expect("zenohd on PATH (scripts/test installs it)"),
        )
    }
}

impl Drop for Zenohd {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// A gateway running until [`RunningGateway::stop`].
struct RunningGateway {
    table: std::sync::Arc<triax_gateway::SensorTable>,
    stop: tokio::sync::oneshot::Sender<()>,
    task: tokio::task::JoinHandle<Result<(), triax_gateway::GatewayError>>,
}

impl RunningGateway {
    async fn start(config: Config) -> RunningGateway {
        let gateway = Gateway::start(config).await.expect("gateway starts");
        let table = gateway.sensors().clone();
        let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
        let task = tokio::spawn(gateway.run_until(async move {
            let _ = stopped.await;
        }));
        RunningGateway { table, stop, task }
    }

    /// The calibration version in force for `sensor`.
    fn version_of(&self, sensor: &str) -> Option<u64> {
        self.table
            .versions()
            .into_iter()
            .find_map(|(id, v)| (id.as_str() == sensor).then_some(v))
    }

    async fn stop(self) {
        let _ = self.stop.send(());
        let _ = tokio::time::timeout(util::TIMEOUT, self.task).await;
    }
}

/// Pushes `push` from `lab` until a gateway acknowledges it (the gateway's queryable takes a
/// moment to cross the router after it starts).
async fn push_until_acknowledged(lab: &zenoh::Session, building: &BuildingId, push: &Push) {
    let deadline = tokio::time::Instant::now() + util::TIMEOUT;
    loop {
        let report = push_one(lab, building, push, Duration::from_secs(2))
            .await
            .unwrap();
        if !report.acks.is_empty() {
            return;
        }
        assert!(
            tokio::time::Instant::now() < deadline,
            "the lab's push never reached the gateway: {:?}",
            report.errors
        );
    }
}

/// A plain TCP client on the building LAN.
async fn lan_client(lan_port: u16) -> zenoh::Session {
    let mut c = zenoh::Config::default();
    for (k, v) in [
        ("mode", "\"client\"".to_owned()),
        (
            "connect/endpoints",
            format!("[\"tcp/127.0.0.1:{lan_port}\"]"),
        ),
        ("scouting/multicast/enabled", "false".to_owned()),
    ] {
        c.insert_json5(k, &v).expect("valid zenoh setting");
    }
    zenoh::open(c).await.expect("LAN client session opens")
}

/// The shipped site router, for real: only a client presenting the lab's certificate
/// (`CN=triax-lab`, from the deployment's CA) can push a calibration. The same signed push from
/// a client with another certificate of the same CA, or from the building LAN, reaches no
/// gateway; and the LAN's own traffic (raw in, corrected out) flows.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn only_the_labs_certificate_can_push_through_the_site_router() {
    let dir = tempfile::tempdir().unwrap();
    make_certificates(dir.path(), &["triax-lab", "intruder"]);
    let (lan_port, tls_port) = (util::free_port(), util::free_port());
    let config = site_router_config(dir.path(), lan_port, tls_port);
    let _router = Zenohd::start(&config);
    util::wait_for_listener(lan_port).await;
    util::wait_for_listener(tls_port).await;

    let lab_key = LabSigningKey::from_bytes(&[11; 32]);
    let mut gw_config = Config::for_tests("site", &dir.path().join("store"), vec![]);
    gw_config.zenoh = triax_net::ZenohSettings::loopback(
        triax_net::ZenohMode::Client,
        vec![],
        vec![format!("tcp/127.0.0.1:{lan_port}")],
    );
    gw_config.calibration.trusted_lab_keys = vec![lab_key.verifying_key()];
    let gateway = RunningGateway::start(gw_config).await;
    let version = || gateway.version_of("d-1");

    let building = BuildingId::new("site").unwrap();
    let lab = tls_client(dir.path(), tls_port, "triax-lab").await;
    let intruder = tls_client(dir.path(), tls_port, "intruder").await;
    let lan = lan_client(lan_port).await;
    // Both TLS clients got through the handshake (their certificates are the CA's): what stops
    // the intruder below is the access control, not the transport.
    for (who, session) in [("lab", &lab), ("intruder", &intruder)] {
        let routers: Vec<_> = session.info().routers_zid().await.collect();
        assert_eq!(
            routers.len(),
            1,
            "{who} is not connected to the site router"
        );
    }
    let denied_wait = Duration::from_secs(2);

    // The lab: accepted, and in force.
    let v1 = Push::sign(&sample::record("d-1", 1), &lab_key);
    push_until_acknowledged(&lab, &building, &v1).await;
    assert_eq!(version(), Some(1));

    // A valid signature is not enough: the same kind of push from elsewhere is not routed.
    let v2 = Push::sign(&sample::record("d-1", 2), &lab_key);
    for (who, session) in [("intruder certificate", &intruder), ("building LAN", &lan)] {
        let report = push_one(session, &building, &v2, denied_wait)
            .await
            .unwrap();
        assert!(report.acks.is_empty(), "{who}: {:?}", report.acks);
        assert_eq!(version(), Some(1), "{who} changed the calibration");
    }
    // The lab still can: the denial above is about who asks, not what is asked.
    let report = push_one(&lab, &building, &v2, util::TIMEOUT).await.unwrap();
    assert_eq!(report.acks.len(), 1, "{:?}", report.errors);
    assert_eq!(version(), Some(2));

    // The LAN's own traffic flows: a node's raw batch in, its corrected batch out.
    let sub = lan
        .declare_subscriber(Key::Corrected(building.clone(), "d-1".parse().unwrap()).to_string())
        .await
        .unwrap();
    let deadline = tokio::time::Instant::now() + util::TIMEOUT;
    let mut seq = 0;
    let corrected = loop {
        lan.put(
            Key::Raw(building.clone(), "d-1".parse().unwrap()).to_string(),
            util::raw("d-1", seq, vec![[0.0, 0.0, 0.98]; 10]),
        )
        .await
        .unwrap();
        seq += 1;
        if let Ok(Ok(s)) = tokio::time::timeout(Duration::from_millis(200), sub.recv_async()).await
        {
            break triax_protocol::CorrectedBatch::decode(&s.payload().to_bytes()).unwrap();
        }
        assert!(
            tokio::time::Instant::now() < deadline,
            "no corrected batch came back"
        );
    };
    assert_eq!(corrected.info.calibration_version, 2);

    for s in [lab, intruder, lan] {
        s.close().await.unwrap();
    }
    gateway.stop().await;
}

/// Waits `window` for anything on `sub`; returns what came.
async fn anything(
    sub: &zenoh::pubsub::Subscriber<zenoh::handlers::FifoChannelHandler<zenoh::sample::Sample>>,
    window: Duration,
) -> Vec<String> {
    let mut got = Vec::new();
    let until = tokio::time::Instant::now() + window;
    while let Ok(Ok(s)) = tokio::time::timeout_at(until, sub.recv_async()).await {
        got.push(s.key_expr().to_string());
    }
    got
}

/// A queryable on `key` that answers every query with `text`.
async fn answering(
    session: &zenoh::Session,
    key: &str,
    text: &'static str,
) -> zenoh::query::Queryable<()> {
    session
        .declare_queryable(key.to_owned())
        .callback(move |q| {
            let key = q.key_expr().clone();
            tokio::spawn(async move {
                let _ = q.reply(key, text).await;
            });
        })
        .await
        .unwrap()
}

/// Replies to a query on `selector` within `window`, asked again until someone answers (a
/// queryable declared a moment ago may not have reached the router yet), for at most
/// [`util::TIMEOUT`].
async fn replies_once_declared(
    session: &zenoh::Session,
    selector: &str,
    window: Duration,
) -> usize {
    let deadline = tokio::time::Instant::now() + util::TIMEOUT;
    loop {
        let n = replies(session, selector, window).await;
        if n > 0 || tokio::time::Instant::now() >= deadline {
            return n;
        }
    }
}

/// Replies to a query on `selector` within `window`.
async fn replies(session: &zenoh::Session, selector: &str, window: Duration) -> usize {
    let Ok(r) = session
        .get(selector)
        .consolidation(zenoh::query::ConsolidationMode::None)
        .timeout(window)
        .await
    else {
        return 0;
    };
    let mut n = 0;
    while r.recv_async().await.is_ok() {
        n += 1;
    }
    n
}

/// The shipped secured site router (`site-router-secured.json5`), for real, with every party
/// over mTLS and known by its certificate's common name. With the right identity everything
/// works: a node's raw data is corrected and reaches consumers, live and from the history; the
/// lab pushes and serves the registry, which the gateway asks; alerts reach the lab. And each
/// identity is refused what is not its part: only the lab pushes or serves the registry, nobody
/// but the gateway puts on calibration keys or publishes corrected data, a node publishes only
/// its building's raw keys, a consumer only reads.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_identity_does_what_it_may_and_nothing_else() {
    let dir = tempfile::tempdir().unwrap();
    let (lab_cn, gw_cn, node_cn, consumer_cn, alerting_cn) = (
        "triax-lab",
        "triax-gateway-north",
        "triax-node-north",
        "triax-consumer-north",
        "triax-alerting-north",
    );
    make_certificates(
        dir.path(),
        &[lab_cn, gw_cn, node_cn, consumer_cn, alerting_cn, "intruder"],
    );
    let tls_port = util::free_port();
    let config = secured_router_config(dir.path(), tls_port);
    let _router = Zenohd::start(&config);
    util::wait_for_listener(tls_port).await;

    // The gateway, through the shipped client file with its own certificate.
    let lab_key = LabSigningKey::from_bytes(&[12; 32]);
    let mut gw_config = Config::for_tests("north", &dir.path().join("store"), vec![]);
    tls_client_config(dir.path(), tls_port, gw_cn);
    gw_config.zenoh = triax_net::ZenohSettings {
        config_file: Some(dir.path().join(format!("{gw_cn}-client.json5"))),
        mode: None,
        listen: vec![],
        connect: vec![],
        multicast_scouting: None,
    };
    gw_config.calibration.trusted_lab_keys = vec![lab_key.verifying_key()];
    let gateway = RunningGateway::start(gw_config).await;
    let version = || gateway.version_of("n-1");

    let north = BuildingId::new("north").unwrap();
    let sensor: triax_protocol::SensorId = "n-1".parse().unwrap();
    let lab = tls_client(dir.path(), tls_port, lab_cn).await;
    let node = tls_client(dir.path(), tls_port, node_cn).await;
    let consumer = tls_client(dir.path(), tls_port, consumer_cn).await;
    let alerting = tls_client(dir.path(), tls_port, alerting_cn).await;
    let intruder = tls_client(dir.path(), tls_port, "intruder").await;
    let quiet = Duration::from_millis(1500);
    let raw_key = Key::Raw(north.clone(), sensor.clone()).to_string();
    let corrected_key = Key::Corrected(north.clone(), sensor.clone()).to_string();

    // The lab pushes; the gateway acknowledges and applies it.
    let acks = lab
        .declare_subscriber("triax/north/calibration/ack/*")
        .await
        .unwrap();
    let v1 = Push::sign(&sample::record("n-1", 1), &lab_key);
    push_until_acknowledged(&lab, &north, &v1).await;
    assert_eq!(version(), Some(1));
    assert!(
        !anything(&acks, quiet).await.is_empty(),
        "the gateway's acknowledgement copy reaches the lab"
    );

    // A node's raw data comes back corrected to a consumer and to the alerting service.
    // The node speaks until both have heard it: a subscription declared a moment ago may not
    // have reached the router yet.
    let live = consumer.declare_subscriber(&corrected_key).await.unwrap();
    let alerting_live = alerting.declare_subscriber(&corrected_key).await.unwrap();
    let deadline = tokio::time::Instant::now() + util::TIMEOUT;
    let mut seq = 0;
    let (mut corrected, mut alerting_heard) = (None, false);
    while corrected.is_none() || !alerting_heard {
        assert!(
            tokio::time::Instant::now() < deadline,
            "no corrected batch reached the consumer ({}) or the alerting service ({alerting_heard})",
            corrected.is_some()
        );
        node.put(&raw_key, util::raw("n-1", seq, vec![[0.0, 0.0, 0.98]; 10]))
            .await
            .unwrap();
        seq += 1;
        let wait = Duration::from_millis(200);
        if let Ok(Ok(s)) = tokio::time::timeout(wait, live.recv_async()).await {
            corrected.get_or_insert(
                triax_protocol::CorrectedBatch::decode(&s.payload().to_bytes()).unwrap(),
            );
        }
        alerting_heard |= tokio::time::timeout(wait, alerting_live.recv_async())
            .await
            .is_ok_and(|r| r.is_ok());
    }
    assert_eq!(corrected.unwrap().info.calibration_version, 1);
    drop(live);
    // ...and from the history.
    let mut kept = 0;
    triax_client::history::fetch(
        &consumer,
        &triax_client::history::HistoryRequest::sensor(&north, &sensor),
        util::TIMEOUT,
        &mut |_| kept += 1,
    )
    .await
    .expect("the consumer reads the history");
    assert!(kept >= 1, "no batch read back from the history");

    // Alerts from the alerting service reach the lab; a consumer's do not.
    // The alerting service speaks until the lab has heard it; then a consumer forges one.
    let alerts = lab.declare_subscriber("triax/north/alert/*").await.unwrap();
    let alert_key = Key::Alert(north.clone(), sensor.clone()).to_string();
    let text =
        |s: zenoh::sample::Sample| String::from_utf8_lossy(&s.payload().to_bytes()).into_owned();
    let mut seen = Vec::new();
    let deadline = tokio::time::Instant::now() + util::TIMEOUT;
    while seen.is_empty() {
        assert!(
            tokio::time::Instant::now() < deadline,
            "the alerting service's alerts never reached the lab"
        );
        alerting.put(&alert_key, "real").await.unwrap();
        if let Ok(Ok(s)) =
            tokio::time::timeout(Duration::from_millis(200), alerts.recv_async()).await
        {
            seen.push(text(s));
        }
    }
    consumer.put(&alert_key, "forged").await.unwrap();
    alerting.put(&alert_key, "real").await.unwrap();
    let until = tokio::time::Instant::now() + quiet;
    while let Ok(Ok(s)) = tokio::time::timeout_at(until, alerts.recv_async()).await {
        seen.push(text(s));
    }
    assert!(
        seen.len() >= 2 && seen.iter().all(|s| s == "real"),
        "only the alerting identity publishes alerts: {seen:?}"
    );

    // The registry: the lab serves it and the gateway's identity gets the answer; nobody else
    // can ask it, and nobody but the lab can serve it.
    let registry_key = "triax/north/calibration/registry";
    let served = answering(&lab, registry_key, "from the lab").await;
    let gateway_identity = tls_client(dir.path(), tls_port, gw_cn).await;
    assert_eq!(
        replies_once_declared(&gateway_identity, registry_key, quiet).await,
        1
    );
    for (who, s) in [
        ("node", &node),
        ("consumer", &consumer),
        ("alerting", &alerting),
        ("intruder", &intruder),
    ] {
        assert_eq!(
            replies(s, registry_key, quiet).await,
            0,
            "{who} asked the registry"
        );
    }
    drop(served);
    let fake = answering(&consumer, registry_key, "forged").await;
    tokio::time::sleep(Duration::from_millis(300)).await;
    assert_eq!(
        replies(&gateway_identity, registry_key, quiet).await,
        0,
        "a consumer served the registry"
    );
    drop(fake);

    // The node's buffer (backfill): the node serves it and the gateway's identity gets the
    // answer; nobody else can ask it, and a consumer cannot pose as a node's buffer.
    let buffer_key = Key::Buffer(north.clone(), sensor.clone()).to_string();
    let buffer = answering(&node, &buffer_key, "a raw batch").await;
    assert_eq!(
        replies_once_declared(&gateway_identity, &buffer_key, quiet).await,
        1
    );
    for (who, s) in [
        ("consumer", &consumer),
        ("alerting", &alerting),
        ("intruder", &intruder),
    ] {
        assert_eq!(
            replies(s, &buffer_key, quiet).await,
            0,
            "{who} asked a node's buffer"
        );
    }
    drop(buffer);
    let fake = answering(&consumer, &buffer_key, "forged").await;
    tokio::time::sleep(Duration::from_millis(300)).await;
    assert_eq!(
        replies(&gateway_identity, &buffer_key, quiet).await,
        0,
        "a consumer served a node's buffer"
    );
    drop(fake);

    // Pushes: a valid signature from any other identity reaches no gateway.
    let v2 = Push::sign(&sample::record("n-1", 2), &lab_key);
    for (who, s) in [
        ("node", &node),
        ("consumer", &consumer),
        ("alerting", &alerting),
        ("intruder", &intruder),
    ] {
        let report = push_one(s, &north, &v2, Duration::from_millis(800))
            .await
            .unwrap();
        assert!(report.acks.is_empty(), "{who} pushed: {:?}", report.acks);
    }
    assert_eq!(
        version(),
        Some(1),
        "a push from another identity was applied"
    );

    // Nobody but the gateway puts on calibration keys or publishes corrected data, and a node
    // publishes only its own building's raw keys; a consumer cannot even listen to raw data.
    let raw_listener = consumer
        .declare_subscriber("triax/north/raw/*")
        .await
        .unwrap();
    let forged_corrected = util::raw("n-1", 999, vec![[9.0; 3]; 10]);
    let ack_key = "triax/north/calibration/ack/n-1";
    tokio::time::sleep(Duration::from_millis(300)).await;
    for s in [&node, &consumer, &intruder] {
        s.put(ack_key, "forged ack").await.unwrap();
        s.put(&corrected_key, forged_corrected.clone())
            .await
            .unwrap();
    }
    // A consumer's raw data is not taken: no corrected batch of a sensor only it sent to.
    let c9: triax_protocol::SensorId = "c-9".parse().unwrap();
    let c9_corrected = consumer
        .declare_subscriber(Key::Corrected(north.clone(), c9.clone()).to_string())
        .await
        .unwrap();
    for s in [&consumer, &intruder] {
        for seq in 0..5 {
            s.put(
                Key::Raw(north.clone(), c9.clone()).to_string(),
                util::raw("c-9", seq, vec![[0.0, 0.0, 0.98]; 10]),
            )
            .await
            .unwrap();
        }
    }
    node.put(&raw_key, util::raw("n-1", seq, vec![[0.0, 0.0, 0.98]; 10]))
        .await
        .unwrap();
    assert!(
        anything(&acks, quiet).await.is_empty(),
        "a forged ack reached the lab"
    );
    // The alerting service (which puts no corrected data itself, so hears no local copy) gets
    // the node's real batch, and before it nothing but the gateway's batches: the forged ones
    // (raw payloads numbered 999) do not decode as corrected.
    loop {
        let s = tokio::time::timeout(util::TIMEOUT, alerting_live.recv_async())
            .await
            .expect("the node's last batch reaches the alerting service")
            .unwrap();
        let b = triax_protocol::CorrectedBatch::decode(&s.payload().to_bytes())
            .expect("forged corrected batches got through");
        assert!(b.header.sequence <= seq, "{}", b.header.sequence);
        if b.header.sequence == seq {
            break;
        }
    }
    assert!(
        anything(&c9_corrected, Duration::from_millis(10))
            .await
            .is_empty(),
        "raw data from a consumer or an intruder was corrected"
    );
    // A session hears its own puts locally; the node's raw data must not reach it.
    let heard: Vec<String> = anything(&raw_listener, Duration::from_millis(10))
        .await
        .into_iter()
        .filter(|k| !k.ends_with("/c-9"))
        .collect();
    assert!(
        heard.is_empty(),
        "a consumer heard a node's raw data: {heard:?}"
    );

    for s in [lab, node, consumer, alerting, intruder, gateway_identity] {
        s.close().await.unwrap();
    }
    gateway.stop().await;
}
