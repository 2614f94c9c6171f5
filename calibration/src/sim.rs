//! A simulated calibration bench with known truth.
//!
//! Produces what the lab reads — the static orientations, a bench description, encoder and
//! sensor recordings at several mount angles, spacer-block readings — together with the truth
//! behind them (sensor parameters, true specific force at every sample), so that tests can
//! measure how close a fit comes and whether its stated uncertainty is honest.
//!
//! The defaults follow the paper's rig: r = 112.7 mm, a 1.6 Hz sine, a 1 kHz encoder, 10 static
//! orientations, and a sensor like eqs. (9)–(12). Output units are volts: the paper's matrices
//! divided by 100 give a sensitivity of about 0.1 V/(m/s²) (≈ 1 V/g) and a zero-g output near
//! 2.4 V, like an analog MEMS part on a 5 V supply. The paper's static matrix (9) has negative
//! main sensitivities and its dynamic one (11) positive; a sensor cannot change sign with
//! frequency, so (9) and (10) are negated here.
//!
//! The sensor may respond to the constant part of its input (ā, the mean over a recording: the
//! gravity components and the mean centripetal term) with `S_S` and offset `q_S` and to the
//! varying part with `S_D`: `V = S_S·(ā − q_S) + S_D·(a − ā) + noise`. With `S_D = S_S` it is
//! exactly the model of eq. (1).
//!
//! The table is not perfect either: its motion has a small third harmonic (the reversals of
//! Figure 5) and an amplitude that wanders slowly from cycle to cycle (Figure 7); the encoder
//! quantises θ to its counts per revolution. The stated radius can be given an error.
//!
//! Pure: returns data, writes no file; the random generator is seeded.

use std::f64::consts::PI;

use nalgebra::{Matrix3, Vector3};

use crate::fit::dynamic::{specific_force, Bench, Recording};
use crate::fit::reference::{MotionLaw, ReferenceMethod};
use crate::fit::static_fit::{reference_from_angles, StaticObservation};

/// The simulated sensor.
#[derive(Debug, Clone, PartialEq)]
pub struct SensorTruth {
    /// Response to the constant part of the input, V/(m/s²).
    pub static_sensitivity: Matrix3<f64>,
    /// Offset q_S, m/s².
    pub static_offset_mps2: Vector3<f64>,
    /// Response to the varying part, V/(m/s²).
    pub dynamic_sensitivity: Matrix3<f64>,
    /// Standard deviation of the white output noise per sample, V.
    pub noise_v: Vector3<f64>,
    /// Drift of the offset with temperature, m/s² per °C, around [`REFERENCE_C`].
    pub offset_drift_mps2_per_c: Vector3<f64>,
    /// Relative drift of each output channel's gain per °C, around [`REFERENCE_C`].
    pub gain_drift_per_c: Vector3<f64>,
}

/// The temperature at which [`SensorTruth`]'s S and q hold, °C; the rotary table runs at it.
pub const REFERENCE_C: f64 = 21.0;

impl SensorTruth {
    /// A sensor like the paper's: (9) and (10) negated, (11), all divided by 100 for volts.
    pub fn paper() -> Self {
        Self {
            static_sensitivity: Matrix3::new(
                9.863, 0.006070, 0.04011, 0.1964, 9.936, 0.03548, -0.7081, -0.03142, 9.863,
            ) / 100.0,
            static_offset_mps2: Vector3::new(-24.32, -24.03, -26.68),
            dynamic_sensitivity: Matrix3::new(
                9.948, 0.2576, -0.3657, -0.5342, 10.97, -0.6611, -0.4454, 1.614, 10.83,
            ) / 100.0,
            noise_v: Vector3::repeat(0.005),
            offset_drift_mps2_per_c: Vector3::zeros(),
            gain_drift_per_c: Vector3::zeros(),
        }
    }

    /// The paper's sensor with a thermal drift typical of cheap MEMS parts: offsets of a few
    /// tenths of a milli-g per °C and gains of a few hundred ppm per °C.
    pub fn drifting() -> Self {
        Self {
            offset_drift_mps2_per_c: Vector3::new(0.004, -0.003, 0.005),
            gain_drift_per_c: Vector3::new(2e-4, -1.5e-4, 3e-4),
            ..Self::matched()
        }
    }

    /// Noise-free output at temperature `temperature_c` for a sensor at rest reading `a`:
    /// `V = diag(1 + c_g·ΔT)·S_S·(a − q_S − c_q·ΔT)`.
    pub fn output_at(&self, a_mps2: &Vector3<f64>, temperature_c: f64) -> Vector3<f64> {
        let dt = temperature_c - REFERENCE_C;
        let v = self.static_sensitivity
            * (a_mps2 - self.static_offset_mps2 - self.offset_drift_mps2_per_c * dt);
        v.component_mul(&self.gain_drift_per_c.map(|c| 1.0 + c * dt))
    }

    /// The paper's static parameters for both parts of the input: eq. (1) holds exactly.
    pub fn matched() -> Self {
        let paper = Self::paper();
        Self {
            dynamic_sensitivity: paper.static_sensitivity,
            ..paper
        }
    }

    /// Noise-free output for an input whose constant part is `constant_mps2`.
    pub fn output(&self, constant_mps2: &Vector3<f64>, input_mps2: &Vector3<f64>) -> Vector3<f64> {
        self.static_sensitivity * (constant_mps2 - self.static_offset_mps2)
            + self.dynamic_sensitivity * (input_mps2 - constant_mps2)
    }
}

/// Everything the simulator can vary.
#[derive(Debug, Clone, PartialEq)]
pub struct SimConfig {
    pub seed: u64,
    pub sensor: SensorTruth,
    /// True distance of the sensing element from the axis.
    pub radius_m: f64,
    /// Stated in the bench file; `radius_m + radius_error_m` is what the bench file says.
    pub radius_uncertainty_m: f64,
    pub radius_error_m: f64,
    pub gravity_mps2: f64,
    pub frequency_hz: f64,
    pub amplitude_rad: f64,
    pub sample_rate_hz: f64,
    pub duration_s: f64,
    pub alphas_deg: Vec<f64>,
    pub counts_per_rev: u64,
    /// Third-harmonic amplitude of θ relative to the fundamental.
    pub third_harmonic: f64,
    /// Peak relative wander of the amplitude over cycles.
    pub amplitude_wander: f64,
    pub static_orientations: usize,
    /// Standard deviation of the arm's angle errors, degrees.
    pub static_angle_error_deg: f64,
    /// Samples averaged per static orientation.
    pub static_samples: usize,
    /// Temperatures of the static runs, °C: every orientation is measured at each. Empty: one
    /// run at [`REFERENCE_C`], with no temperature column.
    pub static_temperatures_c: Vec<f64>,
    pub points_per_cycle: usize,
    pub reference: ReferenceMethod,
    /// Spacer-block thicknesses, mm.
    pub spacers_mm: Vec<f64>,
    /// Noise of one spacer-block reading, V.
    pub spacer_noise_v: f64,
}

impl Default for SimConfig {
    fn default() -> Self {
        Self {
            seed: 2015,
            sensor: SensorTruth::paper(),
            radius_m: 0.1127,
            radius_uncertainty_m: 0.0005,
            radius_error_m: 0.0,
            gravity_mps2: 9.80665,
            frequency_hz: 1.6,
            amplitude_rad: 0.55,
            sample_rate_hz: 1000.0,
            duration_s: 10.0,
            alphas_deg: vec![0.0, 45.0, 90.0, 135.0],
            counts_per_rev: 1 << 20,
            third_harmonic: 0.01,
            amplitude_wander: 0.005,
            static_orientations: 10,
            static_angle_error_deg: 0.2,
            static_samples: 1000,
            static_temperatures_c: Vec::new(),
            points_per_cycle: 20,
            reference: ReferenceMethod::FiniteDifference,
            spacers_mm: (0..=8).map(|i| 5.0 * i as f64).collect(),
            spacer_noise_v: 0.0005,
        }
    }
}

/// The simulator's output: lab inputs plus the truth.
#[derive(Debug, Clone)]
pub struct SimBench {
    pub config: SimConfig,
    /// Nominal reference (what the arm was set to) and mean output per orientation.
    pub static_observations: Vec<StaticObservation>,
    /// Nominal (roll_deg, pitch_deg) of each orientation.
    pub static_angles_deg: Vec<(f64, f64)>,
    /// True reference of each orientation (nominal plus the arm's angle error).
    pub static_truth_mps2: Vec<Vector3<f64>>,
    /// Temperature of each static row, when the config asks for several runs.
    pub static_temperatures_c: Option<Vec<f64>>,
    pub bench: Bench,
    pub recordings: Vec<Recording>,
    /// True specific force at every sample of every recording.
    pub truth_mps2: Vec<Vec<Vector3<f64>>>,
    /// (Δr in mm, reading in V) per spacer block.
    pub spacers: Vec<(f64, f64)>,
}

/// Runs the simulation.
pub fn simulate(config: &SimConfig) -> SimBench {
    let mut rng = Rng::new(config.seed);
    let sensor = &config.sensor;

    let one_run = [REFERENCE_C];
    let runs: &[f64] = if config.static_temperatures_c.is_empty() {
        &one_run
    } else {
        &config.static_temperatures_c
    };
    let attitudes = static_attitudes(config.static_orientations);
    let mut nominal = Vec::new();
    let mut static_observations = Vec::new();
    let mut static_truth_mps2 = Vec::new();
    let mut temperatures = Vec::new();
    let averaged_noise = sensor.noise_v / (config.static_samples.max(1) as f64).sqrt();
    // The arm returns to the same positions in every run: its angle errors belong to the
    // position, not to the run.
    let mut actuals = Vec::with_capacity(attitudes.len());
    for (run, &temperature_c) in runs.iter().enumerate() {
        for (position, &(roll, pitch)) in attitudes.iter().enumerate() {
            if run == 0 {
                let err = config.static_angle_error_deg;
                actuals.push(reference_from_angles(
                    roll + err * rng.normal(),
                    pitch + err * rng.normal(),
                    config.gravity_mps2,
                ));
            }
            let actual = actuals[position];
            let noise = averaged_noise.map(|s| s * rng.normal());
            let output = if temperature_c == REFERENCE_C {
                sensor.output(&actual, &actual)
            } else {
                sensor.output_at(&actual, temperature_c)
            };
            static_observations.push(StaticObservation {
                reference_mps2: reference_from_angles(roll, pitch, config.gravity_mps2),
                output: output + noise,
            });
            static_truth_mps2.push(actual);
            nominal.push((roll, pitch));
            temperatures.push(temperature_c);
        }
    }

    let bench = Bench {
        radius_m: config.radius_m + config.radius_error_m,
        radius_uncertainty_m: config.radius_uncertainty_m,
        gravity_mps2: config.gravity_mps2,
        points_per_cycle: config.points_per_cycle,
        reference: config.reference,
        motion: MotionLaw {
            frequency_hz: config.frequency_hz,
            amplitude_rad: config.amplitude_rad,
        },
    };

    let n = (config.duration_s * config.sample_rate_hz).round() as usize;
    let dt = 1.0 / config.sample_rate_hz;
    let count_rad = 2.0 * PI / config.counts_per_rev as f64;
    let mut recordings = Vec::new();
    let mut truth_mps2 = Vec::new();
    for (index, &alpha_deg) in config.alphas_deg.iter().enumerate() {
        let motion = TableMotion::random(config, &mut rng);
        let alpha = alpha_deg.to_radians();
        let t_s: Vec<f64> = (0..n).map(|i| i as f64 * dt).collect();
        let truth: Vec<Vector3<f64>> = t_s
            .iter()
            .map(|&t| {
                let (_, w, dw) = motion.at(t);
                specific_force(alpha, config.radius_m, config.gravity_mps2, w, dw)
            })
            .collect();
        let constant = truth.iter().fold(Vector3::zeros(), |a, b| a + b) / n.max(1) as f64;
        let theta_rad = t_s
            .iter()
            .map(|&t| (motion.at(t).0 / count_rad).round() * count_rad)
            .collect();
        let output = truth
            .iter()
            .map(|a| sensor.output(&constant, a) + sensor.noise_v.map(|s| s * rng.normal()))
            .collect();
        recordings.push(Recording {
            name: format!("alpha{:03}_{index}.csv", alpha_deg.round() as i64),
            alpha_deg,
            t_s,
            theta_rad,
            output,
        });
        truth_mps2.push(truth);
    }

    // Spacer blocks: amplitude of the z output at the peak rate, offset-free.
    let peak_rate = config.amplitude_rad * 2.0 * PI * config.frequency_hz;
    let spacers = config
        .spacers_mm
        .iter()
        .map(|&d| {
            let accel = (config.radius_m + d * 1e-3) * peak_rate * peak_rate;
            let reading =
                sensor.dynamic_sensitivity[(2, 2)] * accel + config.spacer_noise_v * rng.normal();
            (d, reading)
        })
        .collect();

    SimBench {
        config: config.clone(),
        static_observations,
        static_angles_deg: nominal,
        static_truth_mps2,
        static_temperatures_c: (!config.static_temperatures_c.is_empty()).then_some(temperatures),
        bench,
        recordings,
        truth_mps2,
        spacers,
    }
}

/// `count` attitudes spread over the sphere: the six ±axis ones first, then diagonals.
fn static_attitudes(count: usize) -> Vec<(f64, f64)> {
    let diagonal = 35.264_389_682_754_654; // asin(1/√3): the pitch of a cube diagonal
    let list = [
        (0.0, 0.0),
        (180.0, 0.0),
        (90.0, 0.0),
        (-90.0, 0.0),
        (0.0, 90.0),
        (0.0, -90.0),
        (45.0, diagonal),
        (135.0, -diagonal),
        (-45.0, -diagonal),
        (-135.0, diagonal),
        (45.0, -diagonal),
        (135.0, diagonal),
        (-45.0, diagonal),
        (-135.0, -diagonal),
    ];
    (0..count)
        .map(|i| {
            if i < list.len() {
                list[i]
            } else {
                // Beyond the list: a spiral of further attitudes.
                let k = i as f64;
                ((k * 137.5) % 360.0 - 180.0, ((k * 0.7).sin() * 80.0))
            }
        })
        .collect()
}

/// θ(t) of one recording: wandering amplitude, a third harmonic, a random phase and origin.
struct TableMotion {
    amplitude: f64,
    omega: f64,
    phase: f64,
    origin: f64,
    third: f64,
    third_phase: f64,
    /// (relative amplitude, angular frequency, phase) of the slow amplitude wander terms.
    wander: [(f64, f64, f64); 2],
}

impl TableMotion {
    fn random(config: &SimConfig, rng: &mut Rng) -> Self {
        let each = config.amplitude_wander / 2.0;
        Self {
            amplitude: config.amplitude_rad,
            omega: 2.0 * PI * config.frequency_hz,
            phase: 2.0 * PI * rng.uniform(),
            origin: 2.0 * PI * rng.uniform(),
            third: config.third_harmonic,
            third_phase: 2.0 * PI * rng.uniform(),
            wander: [
                (each, 2.0 * PI * 0.13, 2.0 * PI * rng.uniform()),
                (each, 2.0 * PI * 0.29, 2.0 * PI * rng.uniform()),
            ],
        }
    }

    /// (θ, θ̇, θ̈) at `t`, analytically.
    fn at(&self, t: f64) -> (f64, f64, f64) {
        let (mut m, mut dm, mut ddm) = (1.0, 0.0, 0.0);
        for &(eps, nu, p) in &self.wander {
            let (s, c) = (nu * t + p).sin_cos();
            m += eps * s;
            dm += eps * nu * c;
            ddm -= eps * nu * nu * s;
        }
        let a = self.amplitude;
        let w = self.omega;
        let (s, c) = (w * t + self.phase).sin_cos();
        let (s3, c3) = (3.0 * w * t + self.third_phase).sin_cos();
        let h = a * self.third;
        let theta = self.origin + a * m * s + h * s3;
        let dtheta = a * (dm * s + m * w * c) + 3.0 * w * h * c3;
        let ddtheta = a * (ddm * s + 2.0 * dm * w * c - m * w * w * s) - 9.0 * w * w * h * s3;
        (theta, dtheta, ddtheta)
    }
}

/// SplitMix64 with Box–Muller normals: small, seedable and good enough for simulation; the
/// crate stays free of dependencies beyond nalgebra.
struct Rng {
    state: u64,
    spare: Option<f64>,
}

impl Rng {
    fn new(seed: u64) -> Self {
        Self {
            state: seed,
            spare: None,
        }
    }

    fn next_u64(&mut self) -> u64 {
        self.state = self.state.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.state;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    /// Uniform in (0, 1).
    fn uniform(&mut self) -> f64 {
        ((self.next_u64() >> 11) as f64 + 0.5) / (1u64 << 53) as f64
    }

    fn normal(&mut self) -> f64 {
        if let Some(z) = self.spare.take() {
            return z;
        }
        let r = (-2.0 * self.uniform().ln()).sqrt();
        let phi = 2.0 * PI * self.uniform();
        self.spare = Some(r * phi.sin());
        r * phi.cos()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn motion_derivatives_match_numerical_ones() {
        let config = SimConfig::default();
        let mut rng = Rng::new(7);
        let m = TableMotion::random(&config, &mut rng);
        let h = 1e-5;
        for t in [0.1, 1.3, 4.7] {
            let (_, w, dw) = m.at(t);
            let num_w = (m.at(t + h).0 - m.at(t - h).0) / (2.0 * h);
            let num_dw = (m.at(t + h).1 - m.at(t - h).1) / (2.0 * h);
            assert!((w - num_w).abs() < 1e-6, "{w} {num_w}");
            assert!((dw - num_dw).abs() < 1e-5, "{dw} {num_dw}");
        }
    }

    #[test]
    fn normals_have_unit_variance() {
        let mut rng = Rng::new(1);
        let n = 20000;
        let xs: Vec<f64> = (0..n).map(|_| rng.normal()).collect();
        let mean = xs.iter().sum::<f64>() / n as f64;
        let var = xs.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / n as f64;
        assert!(mean.abs() < 0.03 && (var - 1.0).abs() < 0.05);
    }

    #[test]
    fn same_seed_same_data() {
        let config = SimConfig {
            duration_s: 2.0,
            ..SimConfig::default()
        };
        let a = simulate(&config);
        let b = simulate(&config);
        assert_eq!(a.recordings, b.recordings);
        assert_eq!(a.static_observations, b.static_observations);
    }
}
