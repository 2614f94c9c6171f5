//! The example Zenoh configurations under deploy/zenoh/ are valid for the Zenoh this workspace
//! builds with: each parses with `zenoh::Config::from_file`, and the settings the deployment
//! guide relies on (mode, no multicast scouting, mTLS, access control on) are what they say.
//!
//! `only_the_labs_certificate_can_push_through_the_site_router`: the shipped site router run by
//! a real `zenohd` with certificates the test makes (`rcgen`): the lab's certificate pushes; the
//! same signed push from another certificate of the same CA or from the building LAN reaches no
//! gateway; the LAN's raw and corrected streams flow.

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
            "site-router.json5"
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
    for name in ["site-router.json5", "lab-router.json5"] {
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
    for name in ["gateway-client.json5", "lab-client.json5"] {
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
    let mut c = zenoh::Config::default();
    let path = |f: String| format!("\"{}\"", dir.join(f).display());
    for (k, v) in [
        ("mode", "\"client\"".to_owned()),
        (
            "connect/endpoints",
            format!("[\"tls/127.0.0.1:{tls_port}\"]"),
        ),
        ("scouting/multicast/enabled", "false".to_owned()),
        (
            "transport/link/tls/root_ca_certificate",
            path("ca.pem".into()),
        ),
        ("transport/link/tls/enable_mtls", "true".to_owned()),
        (
            "transport/link/tls/connect_certificate",
            path(format!("{name}.pem")),
        ),
        (
            "transport/link/tls/connect_private_key",
            path(format!("{name}.key")),
        ),
    ] {
        c.insert_json5(k, &v).expect("valid zenoh setting");
    }
    zenoh::open(c).await.expect("TLS client session opens")
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
    let mut router = std::process::Command::new("zenohd")
        .arg("-c")
        .arg(&config)
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::null())
        .spawn()
        .expect("zenohd on PATH (scripts/test installs it)");
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
    let gateway = Gateway::start(gw_config).await.expect("gateway starts");
    let table = gateway.sensors().clone();
    let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
    let task = tokio::spawn(gateway.run_until(async move {
        let _ = stopped.await;
    }));
    let version = || {
        table
            .versions()
            .into_iter()
            .find_map(|(id, v)| (id.as_str() == "d-1").then_some(v))
    };

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
    let deadline = tokio::time::Instant::now() + util::TIMEOUT;
    let v1 = Push::sign(&sample::record("d-1", 1), &lab_key);
    loop {
        let report = push_one(&lab, &building, &v1, Duration::from_secs(2))
            .await
            .unwrap();
        if !report.acks.is_empty() {
            break;
        }
        assert!(
            tokio::time::Instant::now() < deadline,
            "the lab's push never reached the gateway: {:?}",
            report.errors
        );
    }
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
    let _ = stop.send(());
    let _ = tokio::time::timeout(util::TIMEOUT, task).await;
    let _ = router.kill();
    let _ = router.wait();
}
