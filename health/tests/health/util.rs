//! Shared helpers: a calibrated simulated sensor in the field with its monitor.

use nalgebra::{Matrix3, Vector3};
use triax_calibration::corrector::Corrector;
use triax_health::colocated::{ColocatedPair, PairConfig};
use triax_health::sim::{
    calibrate, field_sensor_truth, Fault, FieldConfig, FieldSensor, Motion, Vibration,
};
use triax_health::{HealthConfig, HealthReport, SensorHealth};
use triax_protocol::record::{CalibrationRecord, SetKind};

pub const SECOND_NS: i64 = 1_000_000_000;
pub const HOUR_NS: i64 = 3600 * SECOND_NS;

/// A field sensor, the record its lab issued, and the monitor judging it.
pub struct Run {
    pub field: FieldSensor,
    pub record: CalibrationRecord,
    pub monitor: SensorHealth,
    buf: Vec<[f32; 3]>,
    /// Time of the next batch, ns.
    pub now_ns: i64,
}

impl Run {
    /// Lab seed `seed`; the field's seed follows from it.
    pub fn new(seed: u64, field: FieldConfig, config: &HealthConfig) -> Run {
        let truth = field_sensor_truth();
        let record = calibrate(&truth, seed, "sim").expect("the simulated lab calibrates");
        Run::with_record(record, seed, field, config)
    }

    pub fn with_record(
        record: CalibrationRecord,
        seed: u64,
        field: FieldConfig,
        config: &HealthConfig,
    ) -> Run {
        let monitor = SensorHealth::new(&record, config).expect("the record loads");
        let now_ns = field.start_ns;
        let field = FieldSensor::new(
            field_sensor_truth(),
            FieldConfig {
                seed: seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) ^ 0x5EED,
                ..field
            },
        );
        Run {
            field,
            record,
            monitor,
            buf: Vec::new(),
            now_ns,
        }
    }

    pub fn inject(&mut self, at_ns: i64, fault: Fault) {
        self.field.inject(at_ns, fault);
    }

    /// Feeds the batches that start before `until_ns`, checking `stop` on the report after
    /// every second of data; returns the end of the batch after which it held.
    pub fn run_until(
        &mut self,
        until_ns: i64,
        mut stop: impl FnMut(&HealthReport) -> bool,
    ) -> Option<i64> {
        let batches_per_check = (self.field.config().sample_rate_hz
            / self.field.config().batch_samples as f64)
            .round()
            .max(1.0) as usize;
        while self.now_ns < until_ns {
            for _ in 0..batches_per_check {
                if self.now_ns >= until_ns {
                    break;
                }
                let b = self.field.next_batch(&mut self.buf);
                self.monitor.feed_samples(
                    b.timestamp_ns,
                    b.sample_rate_hz,
                    b.temperature_c,
                    &self.buf,
                );
                let period_ns = 1e9 / b.sample_rate_hz;
                self.now_ns = b.timestamp_ns + (self.buf.len() as f64 * period_ns) as i64;
            }
            if stop(&self.monitor.report()) {
                return Some(self.now_ns);
            }
        }
        None
    }

    /// Feeds batches until `until_ns`.
    pub fn run(&mut self, until_ns: i64) {
        self.run_until(until_ns, |_| false);
    }
}

/// The tests a report holds that are not `ok`, named, for failure messages.
pub fn not_ok(r: &HealthReport) -> Vec<String> {
    r.tests()
        .iter()
        .filter(|(_, _, t)| t.verdict != triax_health::Verdict::Ok)
        .map(|(name, channel, t)| {
            format!(
                "{name}{} {} {:.3e} ± {:.3e} ({} obs, {:.1} nats)",
                channel.map(|c| format!("[{c}]")).unwrap_or_default(),
                t.verdict.as_str(),
                t.statistic,
                t.uncertainty,
                t.observations,
                t.evidence_nats
            )
        })
        .collect()
}

/// Two co-located sensors (the same vibration, each its own lab record and noise) and the
/// pair check on their corrected readings, corrected as the gateway does: the dynamic set at
/// each batch's temperature.
pub struct Pair {
    pub a: FieldSensor,
    pub b: FieldSensor,
    pub records: [CalibrationRecord; 2],
    correctors: [Corrector; 2],
    pub check: ColocatedPair,
    vibration: Vibration,
    motion: Motion,
    vib: Vec<[f64; 3]>,
    raw: Vec<[f32; 3]>,
    accel: Vec<[f64; 3]>,
    pub now_ns: i64,
}

impl Pair {
    pub fn new(seed: u64, field: FieldConfig, config: &PairConfig) -> Pair {
        let truth = field_sensor_truth();
        let records = [0, 1].map(|k| {
            calibrate(&truth, seed * 2 + k, if k == 0 { "a" } else { "b" })
                .expect("the simulated lab calibrates")
        });
        let correctors = [0, 1].map(|k| Corrector::from_record(&records[k]).expect("loads"));
        let check = ColocatedPair::new(&records[0], &records[1], config).expect("a valid pair");
        let sensor = |k: u64| {
            FieldSensor::new(
                field_sensor_truth(),
                FieldConfig {
                    seed: seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) ^ (0xA11CE + k),
                    ..field.clone()
                },
            )
        };
        Pair {
            a: sensor(0),
            b: sensor(1),
            records,
            correctors,
            check,
            vibration: Vibration::new(seed ^ 0xB0_11D1, field.sample_rate_hz),
            motion: Motion::new(field.motion.clone(), seed, field.sample_rate_hz, field.up),
            vib: Vec::new(),
            raw: Vec::new(),
            accel: Vec::new(),
            now_ns: field.start_ns,
        }
    }

    fn correct(
        corrector: &Corrector,
        temperature_c: Option<f32>,
        raw: &[[f32; 3]],
        out: &mut Vec<[f64; 3]>,
    ) {
        let base = corrector.set(SetKind::Dynamic);
        let at = temperature_c.and_then(|t| base.at_temperature(f64::from(t)));
        let set = at.as_ref().unwrap_or(base);
        out.clear();
        out.extend(raw.iter().map(|v| set.accel(v.map(f64::from))));
    }

    /// Feeds both sensors until `until_ns`, checking `stop` every minute of data; returns the
    /// time it first held.
    pub fn run_until(
        &mut self,
        until_ns: i64,
        mut stop: impl FnMut(&ColocatedPair) -> bool,
    ) -> Option<i64> {
        let fs = self.a.config().sample_rate_hz;
        let n = self.a.config().batch_samples;
        let mut batches = 0u64;
        while self.now_ns < until_ns {
            let t_s = self.a.next_time_s();
            let rms = self.a.vibration_rms_at(t_s);
            self.vibration.batch(rms, n, &mut self.vib);
            self.motion.add(self.a.hour_at(t_s), &mut self.vib);
            for (k, sensor) in [&mut self.a, &mut self.b].into_iter().enumerate() {
                let info = sensor.next_batch_with(&mut self.raw, &self.vib);
                Self::correct(
                    &self.correctors[k],
                    info.temperature_c,
                    &self.raw,
                    &mut self.accel,
                );
                if k == 0 {
                    self.check.feed_a(info.timestamp_ns, fs, &self.accel);
                } else {
                    self.check.feed_b(info.timestamp_ns, fs, &self.accel);
                }
                self.now_ns = info.timestamp_ns + (n as f64 * 1e9 / fs) as i64;
            }
            batches += 1;
            if batches.is_multiple_of((60.0 * fs / n as f64) as u64) && stop(&self.check) {
                return Some(self.now_ns);
            }
        }
        None
    }

    /// B's true gain over A's along A's axis `axis`, with B's output channel gains multiplied
    /// by `gain_b`: `(Ŝ_B⁻¹·G·S)_ii / (Ŝ_A⁻¹·S)_ii` (the other axes' motion is uncorrelated
    /// with this one's and biases nothing).
    pub fn true_ratio(&self, axis: usize, gain_b: [f64; 3]) -> f64 {
        let s = field_sensor_truth().dynamic_sensitivity;
        let estimate = |r: &CalibrationRecord| {
            Matrix3::from_fn(|i, j| r.dynamic.sensitivity[i][j])
                .try_inverse()
                .expect("a loaded record inverts")
        };
        let g = Matrix3::from_diagonal(&Vector3::from(gain_b));
        let b = estimate(&self.records[1]) * g * s;
        let a = estimate(&self.records[0]) * s;
        b[(axis, axis)] / a[(axis, axis)]
    }
}
