//! The correction kernel alone, on one core: samples per second with full covariance
//! propagation.
//!
//! - `set_correct`: `SetCorrector::correct` over 100 samples (S⁻¹·V + q and the per-axis
//!   uncertainty from the full 12×12 parameter covariance, noise and stated parts).
//! - `batch/<mode>`: the gateway's whole per-batch path for a 100-sample batch: read from the
//!   payload, correct, flag (clipping, amplitude, expiry, frequency detector), write the corrected
//!   batch into a reused buffer.
//! - `batch/<mode>_dof`: the same with a record that states degrees of freedom, so that every
//!   sample's Welch–Satterthwaite ν is found and the batch's k looked up from it.
//! - `batch/static_temperature`: `static_dof` with a temperature model and a batch that carries
//!   its temperature, so that both sets are taken to it first.
//! - `building/<what>/<n>`: a building's pace, 10-sample batches taken from `n` sensors in turn,
//!   each with its own corrector, kernel and health monitor, as the gateway holds them: the
//!   per-batch cost with one sensor's state hot in the cache against a thousand's cold.
//!   `kernel`: the correction path as above; `kernel+health`: and the health checks' feed.
//!
//! Run: `cargo bench -p triax-gateway --bench kernel`.

use criterion::measurement::WallTime;
use criterion::{
    black_box, criterion_group, criterion_main, BenchmarkGroup, Criterion, Throughput,
};
use triax_calibration::corrector::Corrector;
use triax_gateway::sample_path::{Scratch, SensorKernel};
use triax_gateway::{CorrectionMode, SensorSettings};
use triax_protocol::batch::{BatchHeader, RawBatch};
use triax_protocol::record::{sample, CalibrationRecord, SetKind, TemperatureModel};
use triax_protocol::{RawBatchView, SensorId};

const N: usize = 100;

/// A record whose sets carry a dense, positive-definite parameter covariance.
fn record() -> CalibrationRecord {
    let mut r = sample::record("bench", 1);
    let mut cov = [[0.0; 12]; 12];
    for (i, row) in cov.iter_mut().enumerate() {
        for (j, c) in row.iter_mut().enumerate() {
            // exp(-|i-j|) correlations, scaled: positive definite (a Kac–Murdock–Szegő matrix).
            *c = 1e-8 * 0.5f64.powi((i as i32 - j as i32).abs());
        }
    }
    r.static_set.covariance = Some(Box::new(cov));
    r.dynamic.covariance = Some(Box::new(cov));
    r
}

fn outputs() -> Vec<[f32; 3]> {
    (0..N)
        .map(|i| {
            let t = i as f32 / 100.0;
            [
                0.03 * (12.0 * t).sin(),
                0.02 * (20.0 * t).cos(),
                0.98 + 0.005 * (7.0 * t).sin(),
            ]
        })
        .collect()
}

/// Times one encoded batch through a kernel with `settings`, parsed each time as the worker
/// parses it.
fn bench_batch(
    g: &mut BenchmarkGroup<'_, WallTime>,
    name: &str,
    settings: SensorSettings,
    corrector: &Corrector,
    payload: &[u8],
    scratch: &mut Scratch,
) {
    let mut kernel = SensorKernel::new(settings);
    let mut out = Vec::with_capacity(4096);
    g.bench_function(name, |b| {
        b.iter(|| {
            out.clear();
            // Encoded by the protocol's own encoder.
            let view = RawBatchView::parse(black_box(payload)).expect("valid batch");
            black_box(kernel.correct_batch(&view, Some(corrector), 0, scratch, &mut out));
        })
    });
}

/// The settings of a sensor corrected in `mode`; split mode serves as an inclinometer.
fn in_mode(mode: CorrectionMode) -> SensorSettings {
    SensorSettings {
        mode,
        tilt: mode == CorrectionMode::Split,
        ..SensorSettings::default()
    }
}

fn bench(c: &mut Criterion) {
    let r = record();
    // A sample record with a positive-definite covariance: it loads.
    let corrector = Corrector::from_record(&r).expect("bench record loads");
    let v: Vec<[f64; 3]> = outputs().iter().map(|s| s.map(f64::from)).collect();

    let mut scratch = Scratch::default();
    let mut g = c.benchmark_group("kernel");
    g.throughput(Throughput::Elements(N as u64));
    let set = corrector.set(SetKind::Dynamic);
    g.bench_function("set_correct", |b| {
        b.iter(|| {
            let mut acc = 0.0;
            for x in &v {
                let out = set.correct(black_box(*x));
                acc += out.accel_mps2[0] + out.uncertainty_mps2[2];
            }
            black_box(acc)
        })
    });

    let payload = RawBatch {
        header: BatchHeader {
            // A literal of valid characters.
            sensor_id: SensorId::new("bench").expect("literal id"),
            sequence: 1,
            timestamp_ns: 1_800_000_000_000_000_000,
            sample_rate_hz: 100.0,
        },
        temperature_c: None,
        samples: outputs(),
    }
    .encode();
    for mode in [
        CorrectionMode::Static,
        CorrectionMode::Dynamic,
        CorrectionMode::Split,
    ] {
        let name = format!("batch/{mode:?}").to_lowercase();
        bench_batch(
            &mut g,
            &name,
            in_mode(mode),
            &corrector,
            &payload,
            &mut scratch,
        );
    }
    // The same with degrees of freedom stated: ν per sample, k per batch.
    let mut with_dof = r.clone();
    with_dof.static_set.covariance_dof = Some(6.0);
    with_dof.dynamic.covariance_dof = Some(1196.0);
    with_dof.dynamic.uncertainty_dof = Some(76.0);
    with_dof.sensor.output_noise_dof = Some(20_000.0);
    let with_dof = Corrector::from_record(&with_dof).expect("bench record loads");
    for mode in [CorrectionMode::Static, CorrectionMode::Split] {
        let name = format!("batch/{mode:?}_dof").to_lowercase();
        bench_batch(
            &mut g,
            &name,
            in_mode(mode),
            &with_dof,
            &payload,
            &mut scratch,
        );
    }
    // The same at a temperature, with the record's temperature model.
    let mut thermal = r.clone();
    thermal.static_set.covariance_dof = Some(6.0);
    thermal.sensor.output_noise_dof = Some(20_000.0);
    let mut t_cov = [[0.0; 6]; 6];
    for (i, row) in t_cov.iter_mut().enumerate() {
        row[i] = if i < 3 { 1e-8 } else { 1e-10 };
    }
    thermal.temperature = Some(TemperatureModel {
        reference_c: 21.0,
        range_c: [5.0, 37.0],
        offset_mps2_per_c: [0.004, -0.003, 0.005],
        gain_per_c: Some([2e-4, -1.5e-4, 3e-4]),
        covariance: t_cov,
        covariance_dof: Some(22.0),
    });
    let thermal = Corrector::from_record(&thermal).expect("bench record loads");
    let warm_payload = RawBatch {
        temperature_c: Some(28.5),
        ..RawBatch::decode(&payload).expect("valid batch")
    }
    .encode();
    bench_batch(
        &mut g,
        "batch/static_temperature",
        in_mode(CorrectionMode::Static),
        &thermal,
        &warm_payload,
        &mut scratch,
    );
    // The same without the frequency detector: a band reaching Nyquist leaves nothing to detect.
    let mut wide = r.clone();
    wide.dynamic.domain.frequency_max_hz = 50.0;
    let wide = Corrector::from_record(&wide).expect("bench record loads");
    bench_batch(
        &mut g,
        "batch/dynamic_no_detector",
        SensorSettings::default(),
        &wide,
        &payload,
        &mut scratch,
    );
    g.finish();
}

/// One sensor of the building group: what the gateway keeps per sensor for these steps.
struct BuildingSensor {
    corrector: std::sync::Arc<Corrector>,
    kernel: SensorKernel,
    health: triax_health::SensorHealth,
    payload: Vec<u8>,
    timestamp_ns: i64,
}

/// Samples in a building's batch.
const BUILDING_N: usize = 10;

fn building(c: &mut Criterion) {
    let r = record();
    let config = triax_health::HealthConfig::default();
    let mut g = c.benchmark_group("building");
    g.throughput(Throughput::Elements(1));
    for n in [1usize, 1000, 10_000] {
        let id = SensorId::new("bench").expect("literal id");
        let mut sensors: Vec<BuildingSensor> = (0..n)
            .map(|_| {
                // Loaded one by one, as the gateway's store does: separate allocations.
                let corrector = Corrector::from_record(&r).expect("bench record loads");
                let health = triax_health::SensorHealth::with_corrector(&r, &corrector, &config)
                    .expect("bench record is judged");
                let payload = RawBatch {
                    header: BatchHeader {
                        sensor_id: id.clone(),
                        sequence: 1,
                        timestamp_ns: 1_800_000_000_000_000_000,
                        sample_rate_hz: 100.0,
                    },
                    temperature_c: None,
                    samples: outputs()[..BUILDING_N].to_vec(),
                }
                .encode();
                BuildingSensor {
                    corrector: std::sync::Arc::new(corrector),
                    kernel: SensorKernel::new(SensorSettings::default()),
                    health,
                    payload,
                    timestamp_ns: 1_800_000_000_000_000_000,
                }
            })
            .collect();
        // The first sample's time sits after the prefix's id and sequence (PROTOCOL.md §2).
        let ts_at = 7 + id.as_str().len() + 8;
        let mut scratch = Scratch::default();
        let mut out = Vec::with_capacity(4096);
        for with_health in [false, true] {
            let what = if with_health {
                "kernel+health"
            } else {
                "kernel"
            };
            let mut i = 0;
            g.bench_function(format!("{what}/{n}"), |b| {
                b.iter(|| {
                    let s = &mut sensors[i];
                    i = (i + 1) % n;
                    // Each sensor's stream goes on where its last batch ended.
                    s.timestamp_ns += 100_000_000;
                    s.payload[ts_at..ts_at + 8].copy_from_slice(&s.timestamp_ns.to_le_bytes());
                    out.clear();
                    let view = RawBatchView::parse(&s.payload).expect("valid batch");
                    let corrector = s.corrector.clone();
                    black_box(s.kernel.correct_batch(
                        &view,
                        Some(&corrector),
                        0,
                        &mut scratch,
                        &mut out,
                    ));
                    if with_health {
                        s.health.feed_view(&view);
                    }
                })
            });
        }
    }
    g.finish();
}

criterion_group!(benches, bench, building);
criterion_main!(benches);
