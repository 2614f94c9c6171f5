//! A hostile peer on the building's network: a Zenoh session of its own, with its own Ed25519
//! key, that relays the gateway's batches altered (77 m/s², numbers moved ahead), replays them
//! unaltered, seals its forgeries with its own key, puts heartbeats, and answers every history
//! and status query, with heartbeats and status answers of its own (another gateway name, a
//! phantom sensor, a building that does not exist). Against a real gateway and a real node:
//!
//! - `a_verifying_follower_hands_over_the_gateways_batches_and_nothing_of_the_peers`: every
//!   genuine batch once, in order, byte for byte what the history holds; no forged one; the
//!   forgeries counted; a history read that verifies holds no forged reply, one that does not
//!   is shown to (the attack reaches the consumer); the gateway's status reply verifies
//!   for the query's nonce, the peer's does not.
//! - `a_verifying_console_shows_the_gateways_data_and_nothing_of_the_peers`: two consoles on
//!   the site, one holding the gateway's key: the one on trust draws the 77 m/s², lists the
//!   phantom building and gateway and exports the peer's history answer (the attack is real);
//!   the verifying one draws only the genuine stream, lists only the keyed building with its
//!   gateway's name and its sensor, exports every genuine sample once and nothing else, and
//!   counts what it dropped; of three modes windows (the modal service's, the peer's signed
//!   with its own key, the peer's unsigned) it keeps the service's only.

use std::collections::BTreeSet;
use std::sync::atomic::Ordering::Relaxed;
use std::sync::Arc;
use std::time::Duration;

use triax_client::{history::fetch, FollowOptions, Follower, HistoryRequest};
use triax_net::keys::public_path;
use triax_protocol::batch::CorrectedBatch;
use triax_protocol::messages::{BuildingModes, GatewayStatus, Heartbeat};
use triax_protocol::provenance::{digest, sign_message, verify_message, GatewayKeys, Seal};
use triax_protocol::record::sample;
use triax_protocol::signing::{public_key_from_hex, TrustedKeys};
use triax_protocol::{from_json, to_json, BuildingId, Key, SensorId};
use zenoh::query::ConsolidationMode;
use zenoh::sample::Locality;
use zenoh::Wait;

use crate::util::*;

fn b(id: &str) -> BuildingId {
    BuildingId::new(id).unwrap()
}

/// Sequence numbers the peer moves its forgeries by.
const AHEAD: u64 = 1_000_000;

/// A building that does not exist, whose gateway the peer plays.
const GHOST: &str = "ghost";
/// The gateway name the peer's status answers and heartbeats give.
const FORGED_GATEWAY: &str = "forged-gw";

fn now_ns() -> i64 {
    triax_console::live::wall_clock_ns()
}

/// The peer's own key.
fn peer_key() -> ed25519_dalek::SigningKey {
    ed25519_dalek::SigningKey::from_bytes(&[9; 32])
}

/// The hostile peer: a session of its own that listens (the consumers connect to it) and
/// connects to the gateway, with its own Ed25519 key.
struct HostilePeer {
    session: zenoh::Session,
    endpoint: String,
    /// Corrected batches it put: each relayed batch twice (altered, and replayed as it was).
    forged: Arc<std::sync::atomic::AtomicU64>,
    asking: tokio::task::JoinHandle<()>,
    _handles: (
        zenoh::pubsub::Subscriber<()>,
        zenoh::query::Queryable<()>,
        zenoh::query::Queryable<()>,
        zenoh::pubsub::Subscriber<()>,
    ),
}

impl HostilePeer {
    async fn start(gateway: &str) -> HostilePeer {
        // The peer hears the gateway and is heard by the consumer, as any session on the LAN.
        let peer_endpoint = format!("tcp/127.0.0.1:{}", free_port());
        let peer = {
            let mut c = zenoh::Config::default();
            for (k, v) in [
                ("mode", "\"peer\"".to_owned()),
                ("scouting/multicast/enabled", "false".to_owned()),
                ("listen/endpoints", format!("[\"{peer_endpoint}\"]")),
                ("connect/endpoints", format!("[\"{gateway}\"]")),
            ] {
                c.insert_json5(k, &v).unwrap();
            }
            zenoh::open(c).await.unwrap()
        };
        // The peer's own key: its seals and answers are well signed, by the wrong key.
        let peer_key = peer_key();
        let forged = Arc::new(std::sync::atomic::AtomicU64::new(0));
        let last_genuine: Arc<std::sync::Mutex<Option<Vec<u8>>>> = Arc::default();
        let relay = {
            let (p, forged, peer_key) = (peer.clone(), forged.clone(), peer_key.clone());
            let last = last_genuine.clone();
            let relayed = std::sync::Mutex::new(BTreeSet::new());
            peer.declare_subscriber("triax/pv/corrected/*")
                .callback(move |s| {
                    let key = s.key_expr().as_str().to_owned();
                    let genuine = s.payload().to_bytes().into_owned();
                    let Ok(mut batch) = CorrectedBatch::decode(&genuine) else {
                        return;
                    };
                    // Once each: the sessions between pass its relays on, back to it too.
                    if batch.header.sequence >= AHEAD
                        || !relayed.lock().unwrap().insert(batch.header.sequence)
                    {
                        return;
                    }
                    *last.lock().unwrap() = Some(genuine.clone());
                    // As if the node had gone on: numbers and times moved ahead together.
                    batch.header.sequence += AHEAD;
                    batch.header.timestamp_ns += AHEAD as i64 * 100_000_000;
                    for x in &mut batch.samples {
                        x.accel_mps2 = [77.0, 77.0, 77.0];
                    }
                    let fake = batch.encode();
                    let seal = Seal {
                        sequence: 0,
                        digests: vec![digest(&key, &[], &fake)],
                    }
                    .encode();
                    let signed = sign_message(&peer_key, "triax/pv/seal", "", i64::MAX, &seal);
                    // Not to its own subscriber, which would relay its relays.
                    let put =
                        |k: String, v: Vec<u8>| p.put(k, v).allowed_destination(Locality::Remote);
                    // The replay first: the forgery is then the newest a viewer has.
                    let put = put(key.clone(), genuine)
                        .wait()
                        .and_then(|()| put(key.clone(), fake).wait())
                        .and_then(|()| {
                            put("triax/pv/seal".into(), seal)
                                .attachment(signed.to_vec())
                                .wait()
                        });
                    if put.is_ok() {
                        forged.fetch_add(2, Relaxed);
                    }
                })
                .await
                .unwrap()
        };
        // Every history and status query answered too, the history with a forged batch.
        let history_answers = {
            let peer_key = peer_key.clone();
            let last = last_genuine.clone();
            peer.declare_queryable("triax/pv/history/*")
                .callback(move |q| {
                    let Some(genuine) = last.lock().unwrap().clone() else {
                        return;
                    };
                    let mut batch = CorrectedBatch::decode(&genuine).unwrap();
                    batch.header.sequence = AHEAD;
                    let fake = batch.encode();
                    let cursor = "pv-1:999999";
                    let key = "triax/pv/history/pv-1";
                    let _ = q.reply(key, fake.clone()).attachment(cursor).wait();
                    // As a gateway would, a seal when a nonce asks for one.
                    if let Some(nonce) = q.parameters().get("nonce") {
                        let seal = Seal {
                            sequence: 0,
                            digests: vec![digest(key, cursor.as_bytes(), &fake)],
                        }
                        .encode();
                        let signed = sign_message(&peer_key, key, nonce, 0, &seal);
                        let _ = q.reply(key, seal).attachment(signed.to_vec()).wait();
                    }
                })
                .await
                .unwrap()
        };
        // The gateway's status and heartbeat, altered: another gateway name, a phantom sensor, and
        // the same again for a building that does not exist; signed with the peer's key.
        let last_status: Arc<std::sync::Mutex<Option<GatewayStatus>>> = Arc::default();
        let status_answers = {
            let (peer_key, last) = (peer_key.clone(), last_status.clone());
            peer.declare_queryable("triax/*/status")
                .callback(move |q| {
                    let nonce = q.parameters().get("nonce").unwrap_or_default().to_owned();
                    let Some(genuine) = last.lock().unwrap().clone() else {
                        let body = b"{\"forged\": true}".to_vec();
                        let signed = sign_message(&peer_key, "triax/pv/status", &nonce, 0, &body);
                        let _ = q
                            .reply("triax/pv/status", body)
                            .attachment(signed.to_vec())
                            .wait();
                        return;
                    };
                    for building in ["pv", GHOST] {
                        let mut st = genuine.clone();
                        st.building = b(building);
                        st.gateway = FORGED_GATEWAY.into();
                        let mut phantom = st.sensors[0].clone();
                        phantom.sensor_id = SensorId::new("phantom-1").unwrap();
                        st.sensors.push(phantom);
                        let key = Key::Status(b(building)).to_string();
                        let body = to_json(&st);
                        let signed = sign_message(&peer_key, &key, &nonce, now_ns(), &body);
                        let _ = q.reply(key, body).attachment(signed.to_vec()).wait();
                    }
                })
                .await
                .unwrap()
        };
        let beats = {
            let (p, peer_key) = (peer.clone(), peer_key.clone());
            peer.declare_subscriber("triax/pv/heartbeat")
                .callback(move |s| {
                    let Ok(genuine) = from_json::<Heartbeat>(&s.payload().to_bytes()) else {
                        return;
                    };
                    if genuine.gateway == FORGED_GATEWAY {
                        return;
                    }
                    for building in ["pv", GHOST] {
                        let mut hb = genuine.clone();
                        hb.building = b(building);
                        hb.gateway = FORGED_GATEWAY.into();
                        let key = Key::Heartbeat(b(building)).to_string();
                        let body = to_json(&hb);
                        let signed = sign_message(&peer_key, &key, "", now_ns(), &body);
                        let _ = p
                            .put(key, body)
                            .attachment(signed.to_vec())
                            .allowed_destination(Locality::Remote)
                            .wait();
                    }
                })
                .await
                .unwrap()
        };
        // What the peer's status answers are made of: the gateway's own, asked for now and then.
        let asking = {
            let (p, last) = (peer.clone(), last_status.clone());
            tokio::spawn(async move {
                loop {
                    if let Ok(replies) = p
                        .get("triax/pv/status")
                        .allowed_destination(Locality::Remote)
                        .timeout(Duration::from_secs(1))
                        .await
                    {
                        while let Ok(r) = replies.recv_async().await {
                            if let Ok(st) = r.result().map_err(|_| ()).and_then(|s| {
                                from_json::<GatewayStatus>(&s.payload().to_bytes()).map_err(|_| ())
                            }) {
                                if st.gateway != FORGED_GATEWAY && !st.sensors.is_empty() {
                                    *last.lock().unwrap() = Some(st);
                                }
                            }
                        }
                    }
                    tokio::time::sleep(Duration::from_millis(300)).await;
                }
            })
        };
        HostilePeer {
            session: peer,
            endpoint: peer_endpoint,
            forged,
            asking,
            _handles: (relay, history_answers, status_answers, beats),
        }
    }

    async fn stop(self) {
        self.asking.abort();
        drop(self._handles);
        self.session.close().await.unwrap();
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_verifying_follower_hands_over_the_gateways_batches_and_nothing_of_the_peers() {
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("store");
    seed_store(&store, &[sample::record("pv-1", 1)]);
    let cfg = config("pv", &store);
    let key_file = cfg.provenance.key_file.clone();
    let gw = start(cfg).await;
    let public = std::fs::read_to_string(public_path(&key_file)).expect("the gateway made its key");
    let mut keys = GatewayKeys::new();
    keys.trust(b("pv"), public_key_from_hex(&public).unwrap());
    let trusted = Arc::new(keys);

    let peer = HostilePeer::start(&gw.endpoint).await;
    let node = client(&gw.endpoint).await;
    let consumer = client_of(&[&gw.endpoint, &peer.endpoint]).await;
    let forged = peer.forged.clone();
    let mut options = FollowOptions::new(b("pv"));
    options.trusted = Some(trusted.clone());
    let mut follower = Follower::start(&consumer, options).await.unwrap();
    let publisher = blocking_publisher(&node, key_raw("pv", "pv-1")).await;
    let n = 60u64;
    let stream = tokio::spawn(async move {
        for seq in 0..n {
            publisher
                .put(raw("pv-1", seq, vec![[0.01, 0.0, 0.981]; 10]))
                .await
                .unwrap();
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
        publisher
    });
    let mut got = Vec::new();
    while got.len() < n as usize {
        let d = tokio::time::timeout(TIMEOUT, follower.next())
            .await
            .expect("the genuine batches arrive")
            .expect("the follower runs");
        assert!(
            d.batch.header.sequence < AHEAD,
            "a forged batch was handed over: {:?}",
            d.batch.header
        );
        assert!(d.batch.samples.iter().all(|s| s.accel_mps2[0] != 77.0));
        got.push(d);
    }
    stream.await.unwrap();
    let sequences: Vec<u64> = got.iter().map(|d| d.batch.header.sequence).collect();
    assert_eq!(sequences, (0..n).collect::<Vec<_>>(), "each once, in order");
    assert!(forged.load(Relaxed) > 0, "the peer relayed forgeries");
    // Each forgery (altered, or replayed unaltered) waits for a seal of the gateway's in vain.
    let counters = follower.counters();
    wait_until("the forgeries are counted", || {
        counters.unverified.load(Relaxed) + counters.refused.load(Relaxed) >= forged.load(Relaxed)
    })
    .await;

    // The history, read with and without verifying.
    let mut request = HistoryRequest::sensor(&b("pv"), &SensorId::new("pv-1").unwrap());
    let read = |request: HistoryRequest| {
        let consumer = consumer.clone();
        async move {
            let mut seqs = BTreeSet::new();
            let mut payloads = Vec::new();
            fetch(&consumer, &request, TIMEOUT, &mut |r| {
                seqs.insert(r.batch.header.sequence);
                payloads.push(r.payload);
            })
            .await
            .expect("the history answers");
            (seqs, payloads)
        }
    };
    let (unverified, _) = read(request.clone()).await;
    assert!(
        unverified.contains(&AHEAD),
        "without keys the peer's answer is taken: the attack reaches the consumer"
    );
    request.trusted = Some(trusted.clone());
    let (verified, payloads) = read(request).await;
    assert_eq!(verified, (0..n).collect::<BTreeSet<_>>());
    assert_eq!(
        payloads,
        got.iter().map(|d| d.payload.clone()).collect::<Vec<_>>(),
        "the sealed history is byte for byte what was handed over live"
    );

    // Status: the gateway's reply verifies for the nonce asked with; the peer's does not.
    let nonce = "n0nce-42";
    let replies = consumer
        .get(format!("{}?nonce={nonce}", Key::Status(b("pv"))))
        .consolidation(ConsolidationMode::None)
        .timeout(TIMEOUT)
        .await
        .unwrap();
    // A set: a query may reach the peer by two routes (directly, and relayed by the gateway).
    let mut verdicts = BTreeSet::new();
    while let Ok(reply) = replies.recv_async().await {
        let s = reply.result().expect("status replies");
        let payload = s.payload().to_bytes();
        let attachment = s.attachment().map(|a| a.to_bytes().into_owned());
        let v = verify_message(
            &trusted,
            s.key_expr().as_str(),
            nonce,
            &payload,
            attachment.as_deref(),
        );
        verdicts.insert(v.map(|_| ()).map_err(|e| e.reason()));
    }
    assert_eq!(
        verdicts,
        BTreeSet::from([Ok(()), Err("unknown_key")]),
        "{verdicts:?}"
    );

    for s in [node, consumer] {
        s.close().await.unwrap();
    }
    peer.stop().await;
    gw.stop().await;
}

/// A console on a session that reaches the gateway and the peer, holding `keys` (or none: on
/// trust).
async fn console(
    connect: &[&str],
    keys: Option<Arc<GatewayKeys>>,
    alert_keys: TrustedKeys,
) -> (
    std::net::SocketAddr,
    tokio::sync::oneshot::Sender<()>,
    tokio::task::JoinHandle<Result<(), triax_console::ConsoleError>>,
    zenoh::Session,
) {
    let session = client_of(connect).await;
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = listener.local_addr().unwrap();
    let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
    let options = triax_console::ConsoleOptions {
        status_interval: Duration::from_millis(500),
        gateway_keys: keys,
        trusted_alert_keys: alert_keys,
        ..triax_console::ConsoleOptions::default()
    };
    let task = tokio::spawn(triax_console::serve(
        session.clone(),
        listener,
        options,
        async {
            let _ = stopped.await;
        },
    ));
    (addr, stop, task, session)
}

/// A GET's body (the console answers `Connection: close`).
async fn http_get(addr: std::net::SocketAddr, path: &str) -> String {
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let mut s = tokio::net::TcpStream::connect(addr).await.unwrap();
    s.write_all(format!("GET {path} HTTP/1.1\r\nHost: {addr}\r\n\r\n").as_bytes())
        .await
        .unwrap();
    let mut out = Vec::new();
    tokio::time::timeout(TIMEOUT, s.read_to_end(&mut out))
        .await
        .expect("the console answers")
        .unwrap();
    let text = String::from_utf8_lossy(&out).into_owned();
    assert!(text.starts_with("HTTP/1.1 200"), "{path}: {text}");
    text.split_once("\r\n\r\n")
        .map(|(_, b)| b.to_owned())
        .unwrap_or_default()
}

/// What a page's live view of one sensor has drawn: frames, and the largest |a| of any bucket.
#[derive(Debug, Default)]
struct Drawn {
    frames: u64,
    largest_mps2: f64,
}

/// Opens the live view of `pv-1` as a page does, and folds each `live` frame into `drawn`.
fn watch_live(
    addr: std::net::SocketAddr,
    drawn: Arc<std::sync::Mutex<Drawn>>,
) -> tokio::task::JoinHandle<()> {
    use tokio::io::{AsyncBufReadExt, AsyncWriteExt};
    tokio::spawn(async move {
        let mut s = tokio::net::TcpStream::connect(addr).await.unwrap();
        let path = "/events?building=pv&sensor=pv-1&span_s=60";
        s.write_all(format!("GET {path} HTTP/1.1\r\nHost: {addr}\r\n\r\n").as_bytes())
            .await
            .unwrap();
        let mut lines = tokio::io::BufReader::new(s).lines();
        let mut live = false;
        while let Ok(Some(line)) = lines.next_line().await {
            if let Some(event) = line.strip_prefix("event: ") {
                live = event == "live";
            } else if let (true, Some(data)) = (live, line.strip_prefix("data: ")) {
                let frame: serde_json::Value = serde_json::from_str(data).unwrap();
                // A bucket is [index, samples, flags, gap, min x, max x, min y, max y, min z,
                // max z, then the band].
                let largest = frame["view"]["buckets"]
                    .as_array()
                    .into_iter()
                    .flatten()
                    .filter_map(|b| b.as_array().and_then(|b| b.get(4..10)).map(<[_]>::to_vec))
                    .flatten()
                    .filter_map(|x| x.as_f64())
                    .fold(0.0f64, |m, x| m.max(x.abs()));
                let mut d = drawn.lock().unwrap();
                d.frames += 1;
                d.largest_mps2 = d.largest_mps2.max(largest);
            }
        }
    })
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_verifying_console_shows_the_gateways_data_and_nothing_of_the_peers() {
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("store");
    seed_store(&store, &[sample::record("pv-1", 1)]);
    let cfg = config("pv", &store);
    let key_file = cfg.provenance.key_file.clone();
    let gateway_name = cfg.gateway_name.clone();
    let gw = start(cfg).await;
    let public = std::fs::read_to_string(public_path(&key_file)).expect("the gateway made its key");
    let mut keys = GatewayKeys::new();
    keys.trust(b("pv"), public_key_from_hex(&public).unwrap());
    let trusted = Arc::new(keys);
    let peer = HostilePeer::start(&gw.endpoint).await;
    let node = client(&gw.endpoint).await;
    // Two consoles on the same site: one holds the gateway's key, the other takes all on trust.
    // The modal service listens, and the consoles connect to it (peers do not relay).
    let service_endpoint = format!("tcp/127.0.0.1:{}", free_port());
    let service = listening_peer(&service_endpoint).await;
    let site = [
        gw.endpoint.as_str(),
        peer.endpoint.as_str(),
        service_endpoint.as_str(),
    ];
    // The modal service's key, which signs its windows as it signs its alerts.
    let service_key = ed25519_dalek::SigningKey::from_bytes(&[5; 32]);
    let alert_keys = TrustedKeys::new(vec![service_key.verifying_key()]);
    let (verifying, stop_v, task_v, session_v) = console(&site, Some(trusted), alert_keys).await;
    let (on_trust, stop_t, task_t, session_t) = console(&site, None, TrustedKeys::default()).await;
    let fleet = |addr| async move {
        serde_json::from_str::<serde_json::Value>(&http_get(addr, "/api/fleet").await).unwrap()
    };
    let names = |f: &serde_json::Value| -> BTreeSet<String> {
        f["buildings"]
            .as_array()
            .into_iter()
            .flatten()
            .map(|b| {
                format!(
                    "{}@{}",
                    b["building"].as_str().unwrap(),
                    b["gateway"].as_str().unwrap_or("-")
                )
            })
            .collect()
    };
    wait_until_async("the verifying console hears the gateway", || async {
        fleet(verifying).await["buildings"][0]["state"] == "up"
    })
    .await;
    let drawn_v = Arc::new(std::sync::Mutex::new(Drawn::default()));
    let drawn_t = Arc::new(std::sync::Mutex::new(Drawn::default()));
    let pages = [
        watch_live(verifying, drawn_v.clone()),
        watch_live(on_trust, drawn_t.clone()),
    ];

    let publisher = blocking_publisher(&node, key_raw("pv", "pv-1")).await;
    let n = 60u64;
    let batch = |seq| raw("pv-1", seq, vec![[0.01, 0.0, 0.981]; 10]);
    // The pages watch once both have drawn a batch; what the peer put before may have come
    // before their subscriptions.
    publisher.put(batch(0)).await.unwrap();
    wait_until("both pages draw", || {
        drawn_v.lock().unwrap().frames > 0 && drawn_t.lock().unwrap().frames > 0
    })
    .await;
    let forged_before = peer.forged.load(Relaxed);
    for seq in 1..n {
        publisher.put(batch(seq)).await.unwrap();
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    // The attack reaches a console that does not verify: the peer's 77 m/s² is drawn, and its
    // phantom building and gateway are listed.
    wait_until("the console on trust draws the forgeries", || {
        drawn_t.lock().unwrap().largest_mps2 >= 77.0
    })
    .await;
    wait_until_async(
        "the console on trust lists the peer's inventions",
        || async {
            let n = names(&fleet(on_trust).await);
            n.iter().any(|x| x.starts_with("ghost@"))
                && n.iter().any(|x| x.ends_with(FORGED_GATEWAY))
        },
    )
    .await;
    // The verifying console drops every forged batch once its seal wait is over.
    wait_until_async("the verifying console drops the peer's batches", || async {
        let f = fleet(verifying).await;
        let unsealed = f["provenance"]["refused"]["unsealed"].as_u64().unwrap_or(0);
        unsealed >= peer.forged.load(Relaxed) - forged_before
    })
    .await;
    let drawn = std::mem::take(&mut *drawn_v.lock().unwrap());
    assert!(
        drawn.frames > 0,
        "the verifying console draws the live stream"
    );
    assert!(
        (5.0..20.0).contains(&drawn.largest_mps2),
        "only the genuine stream (about 9.7 m/s² corrected) is drawn: {drawn:?}"
    );
    let f = fleet(verifying).await;
    assert_eq!(
        names(&f),
        BTreeSet::from([format!("pv@{gateway_name}")]),
        "only the keyed building, with its gateway's name: {f}"
    );
    let sensors: Vec<&str> = f["buildings"][0]["sensors"]
        .as_array()
        .unwrap()
        .iter()
        .map(|s| s["sensor_id"].as_str().unwrap())
        .collect();
    assert_eq!(sensors, ["pv-1"], "no phantom sensor");
    assert_eq!(f["provenance"]["verifying"], true);
    assert!(
        f["provenance"]["refused"]["unknown_key"]
            .as_u64()
            .unwrap_or(0)
            > 0,
        "the peer's heartbeats and status answers are counted: {}",
        f["provenance"]
    );

    // The export reads the history: the verifying console's holds the genuine samples only.
    let from_ns = 1_800_000_000_000_000_000i64;
    let csv_path = format!(
        "/api/export.csv?building=pv&sensor=pv-1&from_ns={from_ns}&to_ns={}",
        from_ns + 3_600_000_000_000
    );
    let csv = http_get(verifying, &csv_path).await;
    let rows: Vec<&str> = csv.lines().skip(1).collect();
    assert_eq!(rows.len(), n as usize * 10, "every genuine sample once");
    let forged_row = format!(",{AHEAD},");
    assert!(
        rows.iter().all(|r| !r.contains(&forged_row)),
        "no forged batch exported"
    );
    let csv = http_get(on_trust, &csv_path).await;
    assert!(
        csv.contains(&forged_row),
        "on trust, the peer's history answer is exported"
    );

    // A modes window from the service, and one from the peer (signed with its own key, then
    // unsigned): the verifying console keeps the service's only.
    let window = |reason: &str| {
        to_json(&BuildingModes {
            format_version: triax_protocol::JSON_FORMAT_VERSION,
            building: b("pv"),
            window_start_ns: from_ns,
            window_end_ns: from_ns + 1_800_000_000_000,
            sample_rate_hz: 100.0,
            identification_rate_hz: 0.0,
            sensors: Vec::new(),
            temperature_c: None,
            regressors: Vec::new(),
            tracked: false,
            modes: Vec::new(),
            unquantified: Vec::new(),
            refused: Some(reason.into()),
            warnings: Vec::new(),
            late: false,
            identified_at: time::OffsetDateTime::UNIX_EPOCH,
        })
    };
    let modes_key = Key::Modes(b("pv")).to_string();
    let genuine = window("genuine");
    let signed = sign_message(&service_key, &modes_key, "", now_ns(), &genuine);
    service
        .put(&modes_key, genuine)
        .attachment(signed.to_vec())
        .await
        .unwrap();
    let modes = |addr| async move {
        serde_json::from_str::<serde_json::Value>(&http_get(addr, "/api/modes?building=pv").await)
            .unwrap()
    };
    for addr in [verifying, on_trust] {
        wait_until_async("both consoles hold the service's window", || async {
            modes(addr).await["last_refusal"]["reason"] == "genuine"
        })
        .await;
    }
    let forged = window("forged");
    let signed = sign_message(&peer_key(), &modes_key, "", now_ns(), &forged);
    peer.session
        .put(&modes_key, forged.clone())
        .attachment(signed.to_vec())
        .await
        .unwrap();
    peer.session.put(&modes_key, forged).await.unwrap();
    wait_until_async("on trust, a forgery replaces the window", || async {
        modes(on_trust).await["last_refusal"]["reason"] == "forged"
    })
    .await;
    wait_until_async("the verifying console drops the peer's windows", || async {
        modes(verifying).await["unverified"].as_u64() >= Some(2)
    })
    .await;
    let m = modes(verifying).await;
    assert_eq!(m["windows"], 1, "{m}");
    assert_eq!(m["last_refusal"]["reason"], "genuine", "{m}");
    assert_eq!(m["verifying"], true);
    service.close().await.unwrap();

    for p in pages {
        p.abort();
    }
    for (stop, task) in [(stop_v, task_v), (stop_t, task_t)] {
        let _ = stop.send(());
        task.await.unwrap().unwrap();
    }
    for s in [node, session_v, session_t] {
        s.close().await.unwrap();
    }
    peer.stop().await;
    gw.stop().await;
}
