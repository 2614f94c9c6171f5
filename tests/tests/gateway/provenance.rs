//! A hostile peer on the building's network: a Zenoh session of its own, with its own Ed25519
//! key, that relays the gateway's batches altered (77 m/s², numbers moved ahead), replays them
//! unaltered, seals its forgeries with its own key, puts heartbeats, and answers every history
//! and status query. Against a real gateway and a real node:
//!
//! - `a_verifying_follower_hands_over_the_gateways_batches_and_nothing_of_the_peers`: every
//!   genuine batch once, in order, byte for byte what the history holds; no forged one; the
//!   forgeries counted; a history read that verifies holds no forged reply, one that does not
//!   is shown to (the attack reaches the consumer); the gateway's status reply verifies
//!   for the query's nonce, the peer's does not.

use std::collections::BTreeSet;
use std::sync::atomic::Ordering::Relaxed;
use std::sync::Arc;
use std::time::Duration;

use triax_client::{history::fetch, FollowOptions, Follower, HistoryRequest};
use triax_net::keys::public_path;
use triax_protocol::batch::CorrectedBatch;
use triax_protocol::provenance::{digest, sign_message, verify_message, GatewayKeys, Seal};
use triax_protocol::record::sample;
use triax_protocol::signing::public_key_from_hex;
use triax_protocol::{BuildingId, Key, SensorId};
use zenoh::query::ConsolidationMode;
use zenoh::sample::Locality;
use zenoh::Wait;

use crate::util::*;

fn b(id: &str) -> BuildingId {
    BuildingId::new(id).unwrap()
}

/// Sequence numbers the peer moves its forgeries by.
const AHEAD: u64 = 1_000_000;

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

    // The peer hears the gateway and is heard by the consumer, as any session on the LAN.
    let peer_endpoint = format!("tcp/127.0.0.1:{}", free_port());
    let peer = {
        let mut c = zenoh::Config::default();
        for (k, v) in [
            ("mode", "\"peer\"".to_owned()),
            ("scouting/multicast/enabled", "false".to_owned()),
            ("listen/endpoints", format!("[\"{peer_endpoint}\"]")),
            ("connect/endpoints", format!("[\"{}\"]", gw.endpoint)),
        ] {
            c.insert_json5(k, &v).unwrap();
        }
        zenoh::open(c).await.unwrap()
    };
    let node = client(&gw.endpoint).await;
    let consumer = client_of(&[&gw.endpoint, &peer_endpoint]).await;
    // The peer's own key: its seals and answers are well signed, by the wrong key.
    let peer_key = ed25519_dalek::SigningKey::from_bytes(&[9; 32]);
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
                batch.header.sequence += AHEAD;
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
                let put = |k: String, v: Vec<u8>| p.put(k, v).allowed_destination(Locality::Remote);
                let put = put(key.clone(), fake)
                    .wait()
                    .and_then(|()| put(key.clone(), genuine).wait())
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
    let status_answers = {
        let peer_key = peer_key.clone();
        peer.declare_queryable("triax/pv/status")
            .callback(move |q| {
                let nonce = q.parameters().get("nonce").unwrap_or_default().to_owned();
                let body = b"{\"forged\": true}".to_vec();
                let signed = sign_message(&peer_key, "triax/pv/status", &nonce, 0, &body);
                let _ = q
                    .reply("triax/pv/status", body)
                    .attachment(signed.to_vec())
                    .wait();
            })
            .await
            .unwrap()
    };

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

    drop((relay, history_answers, status_answers));
    for s in [node, consumer, peer] {
        s.close().await.unwrap();
    }
    gw.stop().await;
}
