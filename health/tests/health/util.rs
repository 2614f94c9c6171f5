//! Shared helpers: a calibrated simulated sensor in the field with its monitor.

use triax_health::sim::{calibrate, field_sensor_truth, Fault, FieldConfig, FieldSensor};
use triax_health::{HealthConfig, HealthReport, SensorHealth};
use triax_protocol::record::CalibrationRecord;

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
