//! Tilt while the building moves: inclinometers whose roll and pitch ramp at 0.01–0.2 °/s
//! under building sway, through a real gateway.
//!
//! Each simulated sensor has its own error drawn from its record's stated uncertainty (the
//! record's offset is wrong by e ~ N(0, u²) per axis) and white output noise at the record's
//! level, so the stated interval of every tilt sample is put to the test: the truth at the
//! instant a sample says it describes must lie within ±k·u of it at the stated rate. A tilt
//! that lags the ramp by the low pass's 2.25 s, or that is stamped with its batch's end, misses
//! its interval on nearly every ramping sample.

use std::collections::HashMap;
use std::time::Duration;

use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use rand_distr::StandardNormal;
use triax_gateway::{CorrectionMode, Overload, SensorSettings};
use triax_protocol::batch::{BatchHeader, RawBatch};
use triax_protocol::messages::TiltSample;
use triax_protocol::record::sample;
use triax_protocol::{from_json, SensorId};

use super::util::*;

const SENSORS: usize = 300;
const RATE_HZ: f64 = 50.0;
const BATCH: usize = 25;
const DURATION_S: f64 = 40.0;
const EPOCH_NS: i64 = 1_800_000_000_000_000_000;
const G: f64 = 9.81;

/// One simulated inclinometer: a level, a ramp that starts at `ramp_from_s`, sway, and its own
/// calibration error.
struct Node {
    id: String,
    roll0_deg: f64,
    pitch0_deg: f64,
    roll_rate_dps: f64,
    pitch_rate_dps: f64,
    ramp_from_s: f64,
    sway_hz: f64,
    sway_mps2: f64,
    offset_error_mps2: [f64; 3],
}

impl Node {
    fn angles_deg(&self, t_s: f64) -> (f64, f64) {
        let ramp_s = (t_s - self.ramp_from_s).max(0.0);
        (
            self.roll0_deg + self.roll_rate_dps * ramp_s,
            self.pitch0_deg + self.pitch_rate_dps * ramp_s,
        )
    }

    fn accel_mps2(&self, t_s: f64) -> [f64; 3] {
        let (roll, pitch) = self.angles_deg(t_s);
        let (roll, pitch) = (roll.to_radians(), pitch.to_radians());
        let w = 2.0 * std::f64::consts::PI * self.sway_hz * t_s;
        [
            G * pitch.sin() + self.sway_mps2 * w.sin(),
            G * pitch.cos() * roll.sin() + 0.7 * self.sway_mps2 * (1.3 * w).cos(),
            G * pitch.cos() * roll.cos(),
        ]
    }
}

fn rate_dps(rng: &mut StdRng) -> f64 {
    let r = rng.gen_range(0.01..0.2);
    if rng.gen_bool(0.5) {
        r
    } else {
        -r
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn tilt_covers_the_truth_while_the_building_heels_over() {
    let mut rng = StdRng::seed_from_u64(20);
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("store");
    let nodes: Vec<Node> = (0..SENSORS)
        .map(|i| Node {
            id: format!("incl-{i:03}"),
            roll0_deg: rng.gen_range(-3.0..3.0),
            pitch0_deg: rng.gen_range(-3.0..3.0),
            roll_rate_dps: rate_dps(&mut rng),
            pitch_rate_dps: rate_dps(&mut rng),
            ramp_from_s: rng.gen_range(12.0..20.0),
            sway_hz: rng.gen_range(1.0..5.0),
            sway_mps2: rng.gen_range(0.02..0.3),
            offset_error_mps2: [0.0; 3],
        })
        .collect();
    let records: Vec<_> = nodes.iter().map(|n| sample::record(&n.id, 1)).collect();
    let nodes: Vec<Node> = nodes
        .into_iter()
        .zip(&records)
        .map(|(n, r)| Node {
            offset_error_mps2: r.static_set.uncertainty_mps2.map(|u| {
                let z: f64 = rng.sample(StandardNormal);
                u * z
            }),
            ..n
        })
        .collect();
    seed_store(&store, &records);

    let mut cfg = config("tilt", &store);
    cfg.overload = Overload::Backpressure;
    for n in &nodes {
        cfg.sensors.insert(
            SensorId::new(&n.id).unwrap(),
            SensorSettings {
                mode: CorrectionMode::Static,
                tilt: true,
                tilt_interval_s: 1.0,
                ..SensorSettings::default()
            },
        );
    }
    let gw = start(cfg).await;
    let session = client(&gw.endpoint).await;
    let tilts = session
        .declare_subscriber("triax/tilt/tilt/*")
        .with(zenoh::handlers::FifoChannel::new(50_000))
        .await
        .unwrap();
    let probe = blocking_publisher(&session, key_raw("tilt", &nodes[0].id)).await;
    drop(probe);

    let noise_v = records[0]
        .sensor
        .output_noise
        .expect("sample records state their noise");
    let batches = (DURATION_S * RATE_HZ) as usize / BATCH;
    for seq in 0..batches {
        for (n, r) in nodes.iter().zip(&records) {
            let set = &r.static_set;
            let samples = (0..BATCH)
                .map(|i| {
                    let t_s = (seq * BATCH + i) as f64 / RATE_HZ;
                    // V = S·(a − q − e): corrected with the record's q, the value is off by −e.
                    let q_true = [0, 1, 2].map(|k| set.offset[k] + n.offset_error_mps2[k]);
                    let v = outputs(&set.sensitivity, &q_true, n.accel_mps2(t_s));
                    [0, 1, 2].map(|k| {
                        let z: f64 = rng.sample(StandardNormal);
                        (v[k] + noise_v[k] * z) as f32
                    })
                })
                .collect();
            let payload = RawBatch {
                header: BatchHeader {
                    sensor_id: SensorId::new(&n.id).unwrap(),
                    sequence: seq as u64,
                    timestamp_ns: EPOCH_NS + (seq * BATCH) as i64 * (1e9 / RATE_HZ) as i64,
                    sample_rate_hz: RATE_HZ,
                },
                temperature_c: None,
                samples,
            }
            .encode();
            session
                .put(key_raw("tilt", &n.id), payload)
                .congestion_control(zenoh::qos::CongestionControl::Block)
                .await
                .unwrap();
        }
    }

    // One tilt sample a second per sensor once the filter has settled; wait until every sensor
    // has reported from the stream's last few seconds.
    let by_id: HashMap<&str, &Node> = nodes.iter().map(|n| (n.id.as_str(), n)).collect();
    let end_ns = EPOCH_NS + (DURATION_S * 1e9) as i64;
    let mut samples: Vec<TiltSample> = Vec::new();
    let mut last_ns: HashMap<String, i64> = HashMap::new();
    while last_ns.len() < SENSORS || last_ns.values().any(|&t| t < end_ns - 6_000_000_000) {
        let s = tokio::time::timeout(Duration::from_secs(60), tilts.recv_async())
            .await
            .unwrap_or_else(|_| {
                panic!(
                    "tilt samples stopped: {} sensors reported, {} samples",
                    last_ns.len(),
                    samples.len()
                )
            })
            .unwrap();
        let t: TiltSample = from_json(&s.payload().to_bytes()).expect("tilt sample decodes");
        last_ns.insert(t.sensor_id.to_string(), t.timestamp_ns);
        samples.push(t);
    }

    // The low pass's start must have faded: ln(100)/(ζω) = 10.4 s at 0.1 Hz, less its 2.25 s
    // delay, is the earliest instant a sample may describe.
    let zeta_omega = std::f64::consts::FRAC_1_SQRT_2 * 2.0 * std::f64::consts::PI * 0.1;
    let settle_s = 100f64.ln() / zeta_omega;
    let delay_s = 2f64.sqrt() / (2.0 * std::f64::consts::PI * 0.1);
    let (mut inside, mut total, mut ramp_inside, mut ramp_total) = (0, 0, 0, 0);
    let mut worst_ratio: f64 = 0.0;
    for t in &samples {
        assert_eq!(t.flags, 0, "{t:?}");
        let node = by_id[t.sensor_id.as_str()];
        let t_s = (t.timestamp_ns - EPOCH_NS) as f64 / 1e9;
        assert!(
            t_s >= settle_s - delay_s - 1.0 / RATE_HZ - 1e-6,
            "a tilt sample before the low pass settled: {t:?}"
        );
        let (roll, pitch) = node.angles_deg(t_s);
        for (value, truth, u) in [
            (t.roll_deg, roll, t.roll_uncertainty_deg),
            (t.pitch_deg, pitch, t.pitch_uncertainty_deg),
        ] {
            let ratio = (value - truth).abs() / (t.coverage_factor * u);
            worst_ratio = worst_ratio.max(ratio);
            total += 1;
            inside += usize::from(ratio <= 1.0);
            if t_s > node.ramp_from_s {
                ramp_total += 1;
                ramp_inside += usize::from(ratio <= 1.0);
            }
        }
    }
    let coverage = inside as f64 / total as f64;
    let ramp_coverage = ramp_inside as f64 / ramp_total as f64;
    eprintln!(
        "tilt: {} samples, coverage {:.2} % (ramping {:.2} % of {ramp_total}), worst |e|/(k·u) {worst_ratio:.2}",
        samples.len(),
        100.0 * coverage,
        100.0 * ramp_coverage
    );
    assert!(
        ramp_total > total / 2,
        "{ramp_total} of {total} while ramping"
    );
    assert!(
        (0.93..=0.97).contains(&coverage),
        "coverage {coverage} of {total} angles"
    );
    assert!(
        (0.93..=0.975).contains(&ramp_coverage),
        "coverage while ramping {ramp_coverage} of {ramp_total} angles"
    );
    session.close().await.unwrap();
    gw.stop().await;
}
