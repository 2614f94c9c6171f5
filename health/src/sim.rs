//! Sensors in a building with known truth: a lab calibration of a simulated sensor, then the
//! sensor in the field, through a day's temperature cycle and the building's vibration, with
//! faults injected at known times.
//!
//! **The lab.** The calibration crate's bench simulator ([`triax_calibration::sim`]) measures
//! the static orientations at three temperatures (6, 21 and 36 °C) with the arm's 0.2° angle
//! errors; the lab's own fits ([`fit_thermal`], with the arm's uncertainty stated) give the
//! static set, its 12×12 covariance and degrees of freedom, and the temperature model; the
//! output noise is the lab's second-difference estimate on the rotary-table recordings. So a
//! record's errors are a real fit's errors, and its uncertainty is what the lab would state. The
//! dynamic set is the static one (the simulated sensor is matched: one S for all frequencies);
//! health checks read the static set and the noise.
//!
//! **The field.** `V = diag(1 + c_g·ΔT)·(S·(g·û + v) − S·(q + c_q·ΔT)) + noise`, with the
//! sensor's true coefficients, `û` its attitude, `v` the building's vibration: two lightly
//! damped modes (1.3 and 4.1 Hz, 2 % damping) driven by white noise, louder by day (06:00 to
//! 22:00) than by night. The temperature follows a sine of ±`temperature_swing_c` over the day,
//! and the node reports it with 0.05 °C of noise.
//!
//! Pure and seeded: the same configuration gives the same samples.

use std::f64::consts::PI;

use nalgebra::{Matrix3, Vector3};
use rand::rngs::SmallRng;
use rand::{Rng, SeedableRng};
use rand_distr::StandardNormal;
use time::OffsetDateTime;
use triax_calibration::fit::dynamic::{output_noise, output_noise_dof};
use triax_calibration::fit::static_fit::ArmAngleUncertainty;
use triax_calibration::fit::thermal::fit_thermal;
use triax_calibration::fit::FitError;
use triax_calibration::sim::{simulate, SensorTruth, SimConfig, REFERENCE_C};
use triax_calibration::student::t_quantile;
use triax_protocol::record::{
    CalibrationRecord, CalibrationSet, Certificate, Domain, Lab, SensorInfo,
};
use triax_protocol::{SensorId, JSON_FORMAT_VERSION};

pub use crate::motion::{FieldMotion, Motion};

/// Temperatures of the lab's static runs, °C.
pub const LAB_TEMPERATURES_C: [f64; 3] = [6.0, REFERENCE_C, 36.0];

/// 2026-01-01T00:00:00Z, when simulated records come into force, ns.
pub const EPOCH_NS: i64 = 1_767_225_600_000_000_000;

/// A MEMS part like the paper's, with the thermal drift of cheap parts and 1 mV of white noise
/// per sample (about 1 mg at its 0.1 V per m/s²).
pub fn field_sensor_truth() -> SensorTruth {
    SensorTruth {
        noise_v: Vector3::repeat(0.001),
        ..SensorTruth::drifting()
    }
}

/// The same part with `noise_v` of white noise per sample and channel instead (0.2 mV is
/// about 0.2 mg, a better part's).
pub fn field_sensor_truth_with_noise(noise_v: f64) -> SensorTruth {
    SensorTruth {
        noise_v: Vector3::repeat(noise_v),
        ..field_sensor_truth()
    }
}

/// Calibrates `truth` on the simulated bench with lab seed `seed`: the record a lab would
/// issue for it (see the module's documentation).
pub fn calibrate(
    truth: &SensorTruth,
    seed: u64,
    sensor_id: &str,
) -> Result<CalibrationRecord, FitError> {
    let config = SimConfig {
        seed,
        sensor: truth.clone(),
        static_temperatures_c: LAB_TEMPERATURES_C.to_vec(),
        // The recordings only give the output noise here: short ones do.
        duration_s: 2.0,
        ..SimConfig::default()
    };
    let bench = simulate(&config);
    let temperatures = bench
        .static_temperatures_c
        .clone()
        .unwrap_or_else(|| vec![REFERENCE_C; bench.static_observations.len()]);
    let arm = ArmAngleUncertainty {
        angle_deg: config.static_angle_error_deg,
        dof: 50.0,
    };
    let thermal = fit_thermal(&bench.static_observations, &temperatures, Some(arm))?;
    let fit = &thermal.reference_fit;
    let cal = &fit.calibration;
    let s = cal.sensitivity();
    let q = cal.offset_mps2();
    let c = cal.covariance();
    let mut covariance = [[0.0; 12]; 12];
    for (i, row) in covariance.iter_mut().enumerate() {
        for (j, cell) in row.iter_mut().enumerate() {
            *cell = 0.5 * (c[(i, j)] + c[(j, i)]);
        }
    }
    let nu = fit.covariance_dof;
    let at = OffsetDateTime::from_unix_timestamp_nanos(i128::from(EPOCH_NS))
        .map_err(|e| FitError::Bench(format!("epoch: {e}")))?;
    let static_set = CalibrationSet {
        sensitivity: [0, 1, 2].map(|i| [0, 1, 2].map(|j| s[(i, j)])),
        offset: [q.x, q.y, q.z],
        uncertainty_mps2: [0.0; 3],
        uncertainty_dof: None,
        covariance: Some(Box::new(covariance)),
        covariance_dof: Some(nu),
        coverage_factor: t_quantile(nu.clamp(1.0, 1e4) as u32, 0.95),
        coverage_probability: Some(0.95),
        domain: Domain {
            amplitude_max_mps2: 20.0,
            frequency_min_hz: 0.0,
            frequency_max_hz: 10.0,
        },
        method: "static multi-orientation least squares (simulated bench)".into(),
        reference: format!("simulated arm, g = {} m/s²", config.gravity_mps2),
        n_points: fit.residuals_mps2.len() as u32,
        calibrated_at: at,
    };
    let noise = output_noise(&bench.recordings);
    let id = SensorId::new(sensor_id)
        .map_err(|e| FitError::Bench(format!("sensor id {sensor_id:?}: {e}")))?;
    Ok(CalibrationRecord {
        format_version: JSON_FORMAT_VERSION,
        sensor_id: id,
        version: 1,
        issued_at: at,
        valid_from: at,
        valid_until: None,
        lab: Lab {
            name: "simulated lab".into(),
            accreditation: None,
            approved_by: None,
        },
        certificate: Certificate {
            id: format!("SIM-{sensor_id}-{seed}"),
            temperature_c: Some(REFERENCE_C),
            notes: None,
        },
        sensor: SensorInfo {
            output_unit: "V".into(),
            output_noise: Some([noise.x, noise.y, noise.z]),
            output_noise_dof: Some(output_noise_dof(&bench.recordings)),
            output_full_scale: None,
            model: None,
            serial: None,
        },
        dynamic: CalibrationSet {
            method: "the static set (simulated matched sensor)".into(),
            ..static_set.clone()
        },
        static_set,
        temperature: thermal.model,
    })
}

/// The field around one sensor.
#[derive(Debug, Clone, PartialEq)]
pub struct FieldConfig {
    pub seed: u64,
    pub sample_rate_hz: f64,
    pub batch_samples: usize,
    /// Time of the first sample, ns.
    pub start_ns: i64,
    /// The site's true gravity, m/s².
    pub gravity_mps2: f64,
    /// The upward direction in the sensor's frame (normalised on use).
    pub up: [f64; 3],
    pub temperature_mean_c: f64,
    pub temperature_swing_c: f64,
    /// Length of a day, s: 86 400, or less to compress a day's cycle of temperature and
    /// vibration into a shorter test.
    pub day_s: f64,
    /// Hour of the day of the first sample.
    pub start_hour: f64,
    /// Hour of the day of the warmest moment.
    pub warmest_hour: f64,
    pub temperature_noise_c: f64,
    /// RMS of the building modes' vibration per axis by day and by night, m/s².
    pub vibration_day_mps2: f64,
    pub vibration_night_mps2: f64,
    /// Everything else the building does (ambient, machinery, footfall, transients).
    pub motion: FieldMotion,
}

impl Default for FieldConfig {
    fn default() -> Self {
        FieldConfig {
            seed: 1,
            sample_rate_hz: 100.0,
            batch_samples: 10,
            start_ns: EPOCH_NS,
            gravity_mps2: 9.80665,
            up: [0.02, -0.01, 1.0],
            temperature_mean_c: REFERENCE_C,
            temperature_swing_c: 10.0,
            day_s: 86_400.0,
            start_hour: 0.0,
            warmest_hour: 15.0,
            temperature_noise_c: 0.05,
            vibration_day_mps2: 0.02,
            vibration_night_mps2: 0.002,
            motion: FieldMotion::none(),
        }
    }
}

/// Something going wrong with a sensor, from a given time on.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Fault {
    /// Output channel `channel`'s sensitivity (its response to acceleration) multiplied by
    /// `1 + relative`; its zero-g output stays.
    GainStep { channel: usize, relative: f64 },
    /// The offset q of axis `axis` moved by `mps2`: the corrected reading moves by −`mps2`.
    OffsetStep { axis: usize, mps2: f64 },
    /// Output channel `channel` frozen at its last value.
    Stuck { channel: usize },
    /// Every channel's white noise multiplied by `factor`.
    Noise { factor: f64 },
    /// Single-sample spikes of `height_v` on `channel`, `per_hour` on average.
    Spikes {
        channel: usize,
        per_hour: f64,
        height_v: f64,
    },
    /// Output channel `channel`'s sensitivity drifting by `relative_per_day` a day (ageing).
    GainRamp {
        channel: usize,
        relative_per_day: f64,
    },
    /// The offset q of axis `axis` drifting by `mps2_per_day` a day.
    OffsetRamp { axis: usize, mps2_per_day: f64 },
}

/// One batch's header, as a node would send it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BatchInfo {
    pub timestamp_ns: i64,
    pub sample_rate_hz: f64,
    pub temperature_c: Option<f32>,
}

/// A lightly damped mode driven by white noise: `x = a₁x₁ + a₂x₂ + e`.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Mode {
    a1: f64,
    a2: f64,
    /// Innovation standard deviation per unit RMS of x.
    gain: f64,
    x: [[f64; 2]; 3],
}

impl Mode {
    fn new(frequency_hz: f64, damping: f64, sample_rate_hz: f64) -> Mode {
        let r = (-2.0 * PI * frequency_hz * damping / sample_rate_hz).exp();
        let a1 = 2.0 * r * (2.0 * PI * frequency_hz / sample_rate_hz).cos();
        let a2 = -r * r;
        // Stationary variance of an AR(2) per unit innovation variance.
        let var = (1.0 - a2) / ((1.0 + a2) * ((1.0 - a2).powi(2) - a1 * a1));
        Mode {
            a1,
            a2,
            gain: 1.0 / var.sqrt(),
            x: [[0.0; 2]; 3],
        }
    }

    fn step(&mut self, rms: f64, rng: &mut SmallRng) -> [f64; 3] {
        let mut out = [0.0; 3];
        for (k, x) in self.x.iter_mut().enumerate() {
            let e: f64 = rng.sample(StandardNormal);
            let next = self.a1 * x[0] + self.a2 * x[1] + self.gain * rms * e;
            x[1] = x[0];
            x[0] = next;
            out[k] = next;
        }
        out
    }
}

/// The building's vibration at a sensor: two lightly damped modes (1.3 and 4.1 Hz, 2 %
/// damping) per axis, each carrying half the power. Several sensors given the same samples are
/// co-located.
#[derive(Debug, Clone)]
pub struct Vibration {
    rng: SmallRng,
    modes: [Mode; 2],
}

impl Vibration {
    pub fn new(seed: u64, sample_rate_hz: f64) -> Vibration {
        Vibration {
            rng: SmallRng::seed_from_u64(seed),
            modes: [
                Mode::new(1.3, 0.02, sample_rate_hz),
                Mode::new(4.1, 0.02, sample_rate_hz),
            ],
        }
    }

    /// `n` samples of vibration whose RMS per axis is `rms_mps2`, into `out` (cleared first).
    pub fn batch(&mut self, rms_mps2: f64, n: usize, out: &mut Vec<[f64; 3]>) {
        out.clear();
        let each = rms_mps2 / 2f64.sqrt();
        for _ in 0..n {
            let a = self.modes[0].step(each, &mut self.rng);
            let b = self.modes[1].step(each, &mut self.rng);
            out.push([a[0] + b[0], a[1] + b[1], a[2] + b[2]]);
        }
    }
}

/// A simulated sensor node in the building.
#[derive(Debug, Clone)]
pub struct FieldSensor {
    config: FieldConfig,
    truth: SensorTruth,
    rng: SmallRng,
    index: u64,
    vibration: Vibration,
    motion: Motion,
    vibration_buf: Vec<[f64; 3]>,
    up: Vector3<f64>,
    faults: Vec<(i64, Fault)>,
    gain: [f64; 3],
    offset_mps2: Vector3<f64>,
    /// Ramps: per channel the gain's drift a day, per axis the offset's, from when each began.
    gain_ramps: Vec<(i64, usize, f64)>,
    offset_ramps: Vec<(i64, usize, f64)>,
    noise_factor: f64,
    stuck: [Option<f32>; 3],
    spikes: Option<(usize, f64, f64)>,
    last: [f32; 3],
}

impl FieldSensor {
    pub fn new(truth: SensorTruth, config: FieldConfig) -> FieldSensor {
        let up = Vector3::from(config.up);
        let up = up / up.norm();
        FieldSensor {
            rng: SmallRng::seed_from_u64(config.seed),
            vibration: Vibration::new(config.seed ^ 0x00B1_B2A7_10E5, config.sample_rate_hz),
            motion: Motion::new(
                config.motion.clone(),
                config.seed,
                config.sample_rate_hz,
                config.up,
            ),
            vibration_buf: Vec::with_capacity(config.batch_samples),
            truth,
            config,
            index: 0,
            up,
            faults: Vec::new(),
            gain: [1.0; 3],
            offset_mps2: Vector3::zeros(),
            gain_ramps: Vec::new(),
            offset_ramps: Vec::new(),
            noise_factor: 1.0,
            stuck: [None; 3],
            spikes: None,
            last: [0.0; 3],
        }
    }

    /// Schedules `fault` from `at_ns` on.
    pub fn inject(&mut self, at_ns: i64, fault: Fault) {
        self.faults.push((at_ns, fault));
    }

    /// Time of sample `index`, ns.
    fn time_ns(&self, index: u64) -> i64 {
        self.config.start_ns + (index as f64 * 1e9 / self.config.sample_rate_hz).round() as i64
    }

    /// Hour of the (possibly compressed) day at `t_s` seconds after the start.
    pub fn hour_at(&self, t_s: f64) -> f64 {
        (self.config.start_hour + 24.0 * t_s / self.config.day_s).rem_euclid(24.0)
    }

    /// The true temperature at `t_s` seconds after the start, °C.
    pub fn temperature_at(&self, t_s: f64) -> f64 {
        let hours = self.hour_at(t_s);
        self.config.temperature_mean_c
            + self.config.temperature_swing_c
                * (2.0 * PI * (hours - self.config.warmest_hour + 6.0) / 24.0).sin()
    }

    fn apply_faults(&mut self, now_ns: i64) {
        let mut i = 0;
        while i < self.faults.len() {
            if self.faults[i].0 > now_ns {
                i += 1;
                continue;
            }
            let (_, fault) = self.faults.swap_remove(i);
            match fault {
                Fault::GainStep { channel, relative } => self.gain[channel] *= 1.0 + relative,
                Fault::OffsetStep { axis, mps2 } => self.offset_mps2[axis] += mps2,
                Fault::Stuck { channel } => self.stuck[channel] = Some(self.last[channel]),
                Fault::Noise { factor } => self.noise_factor *= factor,
                Fault::Spikes {
                    channel,
                    per_hour,
                    height_v,
                } => self.spikes = Some((channel, per_hour, height_v)),
                Fault::GainRamp {
                    channel,
                    relative_per_day,
                } => self.gain_ramps.push((now_ns, channel, relative_per_day)),
                Fault::OffsetRamp { axis, mps2_per_day } => {
                    self.offset_ramps.push((now_ns, axis, mps2_per_day))
                }
            }
        }
    }

    /// The ramps' gain factors and offsets at `now_ns` (a batch is short against a day).
    fn ramped(&self, now_ns: i64) -> ([f64; 3], Vector3<f64>) {
        let days = |since: i64| (now_ns - since).max(0) as f64 / 86_400e9;
        let mut gain = self.gain;
        for &(since, channel, per_day) in &self.gain_ramps {
            gain[channel] *= 1.0 + per_day * days(since);
        }
        let mut offset = self.offset_mps2;
        for &(since, axis, per_day) in &self.offset_ramps {
            offset[axis] += per_day * days(since);
        }
        (gain, offset)
    }

    /// The modes' RMS per axis at `t_s` seconds after the start, m/s²: the day's or the
    /// night's.
    pub fn vibration_rms_at(&self, t_s: f64) -> f64 {
        if (6.0..22.0).contains(&self.hour_at(t_s)) {
            self.config.vibration_day_mps2
        } else {
            self.config.vibration_night_mps2
        }
    }

    /// Time of the next batch's first sample, s after the start.
    pub fn next_time_s(&self) -> f64 {
        self.index as f64 / self.config.sample_rate_hz
    }

    /// The next batch: its samples into `out` (cleared first) and its header.
    pub fn next_batch(&mut self, out: &mut Vec<[f32; 3]>) -> BatchInfo {
        let t_s = self.next_time_s();
        let rms = self.vibration_rms_at(t_s);
        let mut vibration = std::mem::take(&mut self.vibration_buf);
        self.vibration
            .batch(rms, self.config.batch_samples, &mut vibration);
        self.motion.add(self.hour_at(t_s), &mut vibration);
        let info = self.next_batch_with(out, &vibration);
        self.vibration_buf = vibration;
        info
    }

    /// The next batch with the vibration given, one sample of it (m/s², sensor frame) per
    /// sample of the batch: co-located sensors share it.
    pub fn next_batch_with(
        &mut self,
        out: &mut Vec<[f32; 3]>,
        vibration: &[[f64; 3]],
    ) -> BatchInfo {
        out.clear();
        let first = self.index;
        let timestamp_ns = self.time_ns(first);
        self.apply_faults(timestamp_ns);
        let fs = self.config.sample_rate_hz;
        let t_s = first as f64 / fs;
        let temperature = self.temperature_at(t_s);
        let dt = temperature - REFERENCE_C;
        let truth = &self.truth;
        let s: &Matrix3<f64> = &truth.static_sensitivity;
        let thermal_gain = truth.gain_drift_per_c.map(|c| 1.0 + c * dt);
        // V = S·a + c with c = −S·q: a gain fault scales the response to acceleration, not the
        // zero-g output.
        let (gain, offset_mps2) = self.ramped(timestamp_ns);
        let v_gravity = s * (self.up * self.config.gravity_mps2);
        let v_zero =
            -(s * (truth.static_offset_mps2 + truth.offset_drift_mps2_per_c * dt + offset_mps2));
        let spike_p = self.spikes.map(|(_, per_hour, _)| per_hour / 3600.0 / fs);
        for vib in vibration {
            let response = v_gravity + truth.dynamic_sensitivity * Vector3::from(*vib);
            let mut v = [0.0f32; 3];
            for k in 0..3 {
                let noise: f64 = self.rng.sample(StandardNormal);
                let x = thermal_gain[k] * (gain[k] * response[k] + v_zero[k])
                    + self.noise_factor * truth.noise_v[k] * noise;
                v[k] = x as f32;
            }
            if let (Some((channel, _, height)), Some(p)) = (self.spikes, spike_p) {
                if self.rng.gen::<f64>() < p {
                    v[channel] += height as f32;
                }
            }
            for (x, stuck) in v.iter_mut().zip(self.stuck) {
                if let Some(value) = stuck {
                    *x = value;
                }
            }
            self.last = v;
            out.push(v);
        }
        self.index += vibration.len() as u64;
        let reading = temperature
            + self.config.temperature_noise_c * self.rng.sample::<f64, _>(StandardNormal);
        BatchInfo {
            timestamp_ns,
            sample_rate_hz: fs,
            temperature_c: Some(reading as f32),
        }
    }

    pub fn config(&self) -> &FieldConfig {
        &self.config
    }

    /// The true specific force at rest (gravity along the attitude), m/s².
    pub fn gravity_vector_mps2(&self) -> [f64; 3] {
        (self.up * self.config.gravity_mps2).into()
    }
}
