//! The hostile-input campaign, outside the default run (it takes minutes):
//!
//! ```text
//! cargo test --release -p triax-tests --test gateway -- --ignored hostile_campaign --nocapture
//! ```
//!
//! `TRIAX_HOSTILE_PAYLOADS` (default 1 000 000) hostile messages against one gateway, from a
//! seeded generator (`TRIAX_HOSTILE_SEED`, default 1): random and truncated bytes, bit-flipped
//! and non-finite batches, huge payloads, puts on wildcard keys, floods of new ids, pushes that
//! are garbage or signed by a key the gateway does not trust, a registry that answers garbage and
//! forgeries, status queries with random parameters. A good sensor streams all along.
//!
//! It prints the gateway's counters by reason and fails on a crash (the gateway runs in this
//! process), on any accepted forgery, on any unflagged corrected sample whose value or
//! uncertainty is not finite or whose uncertainty is zero, and on a lost batch of the good
//! sensor.

use std::sync::atomic::{AtomicU64, Ordering::Relaxed};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use triax_protocol::batch::{flags, BatchHeader, CorrectedBatch, RawBatch};
use triax_protocol::record::sample;
use triax_protocol::signing::{sign, LabSigningKey};
use triax_protocol::{to_json, SensorId};

use super::status;
use crate::util::*;

const BUILDING: &str = "hx";

fn env_u64(name: &str, default: u64) -> u64 {
    std::env::var(name)
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(default)
}

fn batch(sensor: &str, sequence: u64, samples: Vec<[f32; 3]>) -> Vec<u8> {
    RawBatch {
        header: BatchHeader {
            sensor_id: SensorId::new(sensor).expect("campaign ids are valid"),
            sequence,
            // Random sequence numbers may be huge: the time wraps rather than overflows.
            timestamp_ns: 1_800_000_000_000_000_000i64
                .wrapping_add((sequence as i64).wrapping_mul(100_000_000)),
            sample_rate_hz: 100.0,
        },
        temperature_c: None,
        samples,
    }
    .encode()
}

/// What the corrected stream showed that it must not.
#[derive(Default)]
struct Watch {
    batches: AtomicU64,
    bad_samples: AtomicU64,
    good_sequences: Mutex<Vec<u64>>,
    first_bad: Mutex<Option<String>>,
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
#[ignore = "minutes long: run with --ignored (see the module's documentation)"]
async fn hostile_campaign() {
    let total = env_u64("TRIAX_HOSTILE_PAYLOADS", 1_000_000);
    let mut rng = StdRng::seed_from_u64(env_u64("TRIAX_HOSTILE_SEED", 1));
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("store");
    seed_store(&store, &[sample::record("good", 1)]);
    let trusted = LabSigningKey::from_bytes(&[7; 32]);
    let forger = LabSigningKey::from_bytes(&[9; 32]);
    let mut cfg = config(BUILDING, &store);
    cfg.calibration.trusted_lab_keys = vec![trusted.verifying_key()];
    cfg.calibration.catchup_interval = Some(Duration::from_secs(1));
    cfg.calibration.catchup_timeout = Duration::from_millis(500);
    let gw = start(cfg).await;
    let session = client(&gw.endpoint).await;

    let watch = Arc::new(Watch::default());
    let w = watch.clone();
    let _sub = session
        .declare_subscriber(format!("triax/{BUILDING}/corrected/*"))
        .callback(move |s| {
            let Ok(b) = CorrectedBatch::decode(&s.payload().to_bytes()) else {
                return;
            };
            w.batches.fetch_add(1, Relaxed);
            if b.header.sensor_id.as_str() == "good" {
                w.good_sequences.lock().unwrap().push(b.header.sequence);
            }
            for s in &b.samples {
                let clean = (s.flags | b.batch_flags) & !flags::DUPLICATE == 0;
                let honest = s.accel_mps2.iter().all(|a| a.is_finite())
                    && s.uncertainty_mps2.iter().all(|u| u.is_finite() && *u > 0.0);
                if clean && !honest {
                    w.bad_samples.fetch_add(1, Relaxed);
                    w.first_bad
                        .lock()
                        .unwrap()
                        .get_or_insert_with(|| format!("{b:?}"));
                }
            }
        })
        .await
        .unwrap();
    // A hostile registry: garbage, and records signed by a key the gateway does not trust.
    let forged_registry = to_json(&sign(&sample::record("good", 99), &forger));
    let _registry = session
        .declare_queryable(format!("triax/{BUILDING}/calibration/registry"))
        .callback(move |q| {
            use zenoh::Wait;
            let _ = q
                .reply(q.key_expr().clone(), forged_registry.clone())
                .wait();
            let _ = q
                .reply(q.key_expr().clone(), b"\xff{not json".to_vec())
                .wait();
        })
        .await
        .unwrap();
    let good = blocking_publisher(&session, key_raw(BUILDING, "good")).await;

    let wildcards = [
        "triax/*/raw/good".to_owned(),
        format!("triax/{BUILDING}/raw/*"),
        "**/raw/good".to_owned(),
        "triax/**".to_owned(),
    ];
    let valid = |rng: &mut StdRng| -> Vec<[f32; 3]> {
        (0..rng.gen_range(1..50))
            .map(|_| [rng.gen_range(-1.0..1.0), 0.0, 0.98])
            .collect()
    };
    let started = Instant::now();
    let (mut good_seq, mut sent) = (0u64, [0u64; 9]);
    for i in 0..total {
        if i % 1000 == 0 {
            good.put(batch("good", good_seq, vec![[0.01, -0.02, 0.98]; 10]))
                .await
                .unwrap();
            good_seq += 1;
        }
        let id = format!("h{}", rng.gen_range(0..200_000u32));
        let kind = rng.gen_range(0..100u32);
        let (category, key, payload): (usize, String, Vec<u8>) = match kind {
            0..=19 => {
                let n = rng.gen_range(0..256);
                (
                    0,
                    key_raw(BUILDING, &id),
                    (0..n).map(|_| rng.gen()).collect(),
                )
            }
            20..=34 => {
                let mut b = batch(&id, rng.gen(), valid(&mut rng));
                let cut = rng.gen_range(0..b.len());
                b.truncate(cut);
                (1, key_raw(BUILDING, &id), b)
            }
            35..=54 => {
                let mut b = batch(&id, rng.gen_range(0..1000), valid(&mut rng));
                for _ in 0..rng.gen_range(1..4) {
                    let at = rng.gen_range(0..b.len());
                    b[at] ^= 1 << rng.gen_range(0..8);
                }
                (2, key_raw(BUILDING, &id), b)
            }
            55..=69 => {
                let specials = [f32::NAN, f32::INFINITY, f32::NEG_INFINITY, f32::MAX, 1e30];
                let samples = (0..rng.gen_range(1..50))
                    .map(|_| [0, 1, 2].map(|_| specials[rng.gen_range(0..specials.len())]))
                    .collect();
                (3, key_raw(BUILDING, &id), batch(&id, rng.gen(), samples))
            }
            70..=79 => {
                let key = wildcards[rng.gen_range(0..wildcards.len())].clone();
                (4, key, batch("good", rng.gen(), valid(&mut rng)))
            }
            80..=94 => (5, key_raw(BUILDING, &id), Vec::new()),
            _ if i % 10_000 == 0 => {
                let n = rng.gen_range(1 << 20..4 << 20);
                (6, key_raw(BUILDING, &id), vec![rng.gen(); n])
            }
            95..=97 => {
                // Pushes: every other one a forgery, the rest garbage.
                let payload = if rng.gen_bool(0.5) {
                    to_json(&sign(&sample::record("good", rng.gen_range(2..5)), &forger))
                } else {
                    (0..rng.gen_range(0..300)).map(|_| rng.gen()).collect()
                };
                let key = format!("triax/{BUILDING}/calibration/push/good");
                let replies = session
                    .get(&key)
                    .payload(payload)
                    .timeout(Duration::from_millis(200))
                    .await
                    .unwrap();
                while replies.recv_async().await.is_ok() {}
                sent[7] += 1;
                continue;
            }
            _ => {
                let params: String = (0..rng.gen_range(0..40))
                    .map(|_| char::from(rng.gen_range(32u8..127)))
                    .collect();
                let replies = session
                    .get(format!("triax/{BUILDING}/status?{params}"))
                    .timeout(Duration::from_millis(200))
                    .await;
                if let Ok(replies) = replies {
                    while replies.recv_async().await.is_ok() {}
                }
                sent[8] += 1;
                continue;
            }
        };
        // Refused synchronously by Zenoh (a key expression it cannot parse) counts as sent.
        let _ = session.put(key, payload).await;
        sent[category] += 1;
    }
    // Let the last batches through, then read what the gateway says.
    tokio::time::sleep(Duration::from_secs(2)).await;
    let st = status(&session, BUILDING).await;
    let good_status = st.sensors.iter().find(|s| s.sensor_id.as_str() == "good");
    let names = [
        "random bytes",
        "truncated batches",
        "bit-flipped batches",
        "non-finite batches",
        "wildcard puts",
        "empty puts (id flood)",
        "1–4 MiB payloads",
        "pushes (garbage or forged)",
        "status queries",
    ];
    println!(
        "hostile campaign: {} messages in {:.1} s",
        sent.iter().sum::<u64>(),
        started.elapsed().as_secs_f64()
    );
    for (n, c) in names.iter().zip(sent) {
        println!("  sent {n}: {c}");
    }
    println!(
        "  gateway: malformed {}, refused_keys {:?}, pushes accepted {} / refused {}, \
         over_capacity {}, admitted {}, displaced {}, expired {}, dropped {}",
        st.malformed,
        st.refused_keys,
        st.pushes_accepted,
        st.pushes_refused,
        st.over_capacity,
        st.admitted_sensors,
        st.displaced_sensors,
        st.expired_sensors,
        st.dropped
    );
    println!(
        "  corrected batches seen {}, unflagged samples with a non-finite value or a zero or \
         non-finite uncertainty: {}",
        watch.batches.load(Relaxed),
        watch.bad_samples.load(Relaxed)
    );

    assert_eq!(st.pushes_accepted, 0, "a forgery was accepted");
    let good_status = good_status.expect("the good sensor is known");
    assert_eq!(good_status.calibration_version, Some(1), "{good_status:?}");
    assert_eq!(
        watch.bad_samples.load(Relaxed),
        0,
        "first: {:?}",
        watch.first_bad.lock().unwrap()
    );
    let mut got = watch.good_sequences.lock().unwrap().clone();
    got.sort_unstable();
    got.dedup();
    assert_eq!(
        got,
        (0..good_seq).collect::<Vec<_>>(),
        "the good sensor lost batches"
    );
    assert_eq!(good_status.gaps, 0, "{good_status:?}");
    session.close().await.unwrap();
    gw.stop().await;
}
