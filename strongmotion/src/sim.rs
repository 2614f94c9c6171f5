//! A building with known truth: a shear frame in `x` and `y` whose linear response to a ground
//! motion is computed exactly, seen by sensors with calibration errors, clock offsets and noise.
//!
//! - The frame: `n` storeys of mass `m` and storey stiffnesses `k_i` (`y` a ratio stiffer than
//!   `x`), classical damping `ζ` in every mode; modes from the symmetric eigenproblem of
//!   `M^{-1/2} K M^{-1/2}`, participation `Γ_r = φ_rᵀM·1 / φ_rᵀMφ_r`.
//! - The response: every mode `q_r̈ + 2ζω_r q̇_r + ω_r² q_r = −Γ_r a_g(t)` by the oscillator's
//!   exact step for an input linear between samples ([`crate::oscillator`]); relative
//!   displacement `u = Σ φ_r q_r` and absolute acceleration `ü + a_g = −Σ φ_r(2ζω_r q̇_r + ω_r²
//!   q_r)` (the modes are complete, `Σ φ_r Γ_r = 1`), at the samples, with no approximation.
//!   Vertically the frame is rigid: every floor moves with the ground.
//! - The ground motion ([`GroundMotion::synthetic`]): white noise through a Kanai–Tajimi filter
//!   (the absolute acceleration of a soil oscillator, `f_g`, `ζ_g`) under a Saragoni–Hart
//!   envelope, three components (vertical two thirds of the horizontal), optionally with a
//!   long-period velocity pulse, scaled to a peak; its content below 0.05 Hz removed by a
//!   zero-phase high pass so that the ground comes to rest.
//! - Sensors: a floor, a mounting turned about the vertical, a calibration record (sensitivity,
//!   its covariance, output noise) and a truth that differs from it by a draw from that
//!   covariance; the corrected samples are `S⁻¹·S_true·(a_sensor − q_true) + q` plus white noise
//!   through `S⁻¹`, stamped `δ` off (the motion at `t + δ`, to first order `a + δ·ȧ`).

use nalgebra::{DMatrix, Matrix3, SMatrix};

use crate::filter::{BandConfig, BandPass};
use crate::oscillator::Oscillator;
use crate::process::{SensorCalibration, SensorRecord};
use crate::rng::Rng;

/// A shear frame.
#[derive(Debug, Clone, PartialEq)]
pub struct ShearFrame {
    pub storeys: usize,
    pub storey_height_m: f64,
    pub mass_kg: f64,
    /// Storey stiffnesses in `x`, bottom first, N/m.
    pub stiffness_x_n_per_m: Vec<f64>,
    /// `y` stiffnesses over `x`'s.
    pub y_ratio: f64,
    pub damping: f64,
}

/// One direction's modes.
#[derive(Debug, Clone, PartialEq)]
pub struct Modes {
    pub omega: Vec<f64>,
    /// `shapes[r][floor − 1]`.
    pub shapes: Vec<Vec<f64>>,
    pub participation: Vec<f64>,
}

impl ShearFrame {
    /// Six storeys of 3.5 m, fundamental near 1 Hz in `x`, `y` 30 % stiffer, 5 % damping.
    pub fn six_storey() -> ShearFrame {
        let n = 6;
        let mass_kg = 2.0e5;
        // Stiffness falling off with height, scaled to a 1 Hz fundamental below.
        let shape: Vec<f64> = (0..n).map(|i| 1.0 - 0.08 * i as f64).collect();
        let mut f = ShearFrame {
            storeys: n,
            storey_height_m: 3.5,
            mass_kg,
            stiffness_x_n_per_m: shape.clone(),
            y_ratio: 1.3,
            damping: 0.05,
        };
        let w1 = f.modes(0).omega[0];
        let scale = (2.0 * std::f64::consts::PI / w1).powi(2);
        f.stiffness_x_n_per_m = shape.iter().map(|k| k * scale).collect();
        f
    }

    /// Modes of direction 0 (`x`) or 1 (`y`), by increasing frequency.
    pub fn modes(&self, direction: usize) -> Modes {
        let n = self.storeys;
        let ratio = if direction == 1 { self.y_ratio } else { 1.0 };
        let k: Vec<f64> = self.stiffness_x_n_per_m.iter().map(|v| v * ratio).collect();
        let mut stiffness = DMatrix::zeros(n, n);
        for i in 0..n {
            stiffness[(i, i)] += k[i];
            if i + 1 < n {
                stiffness[(i, i)] += k[i + 1];
                stiffness[(i, i + 1)] -= k[i + 1];
                stiffness[(i + 1, i)] -= k[i + 1];
            }
        }
        let a = stiffness / self.mass_kg;
        let eigen = a.symmetric_eigen();
        let mut order: Vec<usize> = (0..n).collect();
        order.sort_by(|&i, &j| eigen.eigenvalues[i].total_cmp(&eigen.eigenvalues[j]));
        let mut omega = Vec::new();
        let mut shapes = Vec::new();
        let mut participation = Vec::new();
        for r in order {
            omega.push(eigen.eigenvalues[r].max(0.0).sqrt());
            let phi: Vec<f64> = eigen.eigenvectors.column(r).iter().copied().collect();
            // Uniform mass: Γ = Σφ / Σφ².
            let g = phi.iter().sum::<f64>() / phi.iter().map(|v| v * v).sum::<f64>();
            shapes.push(phi);
            participation.push(g);
        }
        Modes {
            omega,
            shapes,
            participation,
        }
    }

    /// Exact response to `ground`: per floor 0..=storeys (0 the ground) the absolute
    /// acceleration (x, y, z), and the relative displacement (x, y).
    pub fn respond(&self, ground: &GroundMotion) -> Response {
        let n = ground.accel_mps2.len();
        let floors = self.storeys + 1;
        let mut accel = vec![vec![[0.0; 3]; n]; floors];
        let mut disp = vec![vec![[0.0; 2]; n]; floors];
        for (i, g) in ground.accel_mps2.iter().enumerate() {
            for f in accel.iter_mut() {
                f[i][2] = g[2];
            }
            accel[0][i][0] = g[0];
            accel[0][i][1] = g[1];
        }
        for d in 0..2 {
            let modes = self.modes(d);
            let input: Vec<f64> = ground.accel_mps2.iter().map(|a| a[d]).collect();
            for r in 0..self.storeys {
                let w = modes.omega[r];
                let osc = Oscillator::new(2.0 * std::f64::consts::PI / w, self.damping, ground.dt);
                let (u, v) = osc.response(&input);
                let g = modes.participation[r];
                for (floor, phi) in modes.shapes[r].iter().enumerate() {
                    for i in 0..n {
                        let q = g * u[i];
                        let qd = g * v[i];
                        disp[floor + 1][i][d] += phi * q;
                        accel[floor + 1][i][d] -= phi * (2.0 * self.damping * w * qd + w * w * q);
                    }
                }
            }
        }
        Response {
            accel_mps2: accel,
            displacement_m: disp,
            dt: ground.dt,
        }
    }
}

/// A frame's response at the samples.
#[derive(Debug, Clone, PartialEq)]
pub struct Response {
    /// `[floor][sample]`, building frame, gravity not included.
    pub accel_mps2: Vec<Vec<[f64; 3]>>,
    /// `[floor][sample]`, relative to the ground, x and y.
    pub displacement_m: Vec<Vec<[f64; 2]>>,
    pub dt: f64,
}

impl Response {
    /// The true inter-storey drift ratio between floors `lower` and `upper` in `direction`:
    /// `max |u_upper − u_lower| / h` over samples `from..to`.
    pub fn drift_ratio(
        &self,
        lower: usize,
        upper: usize,
        direction: usize,
        h: f64,
        span: std::ops::Range<usize>,
    ) -> f64 {
        span.map(|i| {
            (self.displacement_m[upper][i][direction] - self.displacement_m[lower][i][direction])
                .abs()
        })
        .fold(0.0, f64::max)
            / h
    }
}

/// A ground motion at the samples.
#[derive(Debug, Clone, PartialEq)]
pub struct GroundMotion {
    pub accel_mps2: Vec<[f64; 3]>,
    pub dt: f64,
}

/// What a synthetic ground motion is made of.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GroundMotionSpec {
    /// Seconds of rest before the motion, of motion (the envelope's span), and after.
    pub quiet_before_s: f64,
    pub duration_s: f64,
    pub quiet_after_s: f64,
    /// Peak horizontal acceleration the first component is scaled to, m/s².
    pub peak_mps2: f64,
    /// Kanai–Tajimi soil frequency and damping.
    pub soil_hz: f64,
    pub soil_damping: f64,
    /// A velocity pulse's period (s) and its peak acceleration relative to `peak_mps2`.
    pub pulse: Option<(f64, f64)>,
}

impl GroundMotion {
    /// A synthetic record at `rate_hz` (see the module's doc).
    pub fn synthetic(spec: &GroundMotionSpec, rate_hz: f64, rng: &mut Rng) -> GroundMotion {
        let dt = 1.0 / rate_hz;
        let n = ((spec.quiet_before_s + spec.duration_s + spec.quiet_after_s) * rate_hz) as usize;
        let soil = Oscillator::new(1.0 / spec.soil_hz, spec.soil_damping, dt);
        let w = soil.omega;
        let t0 = spec.quiet_before_s;
        // Saragoni–Hart: t^b·e^(−ct), its peak at 30 % of the span, down to 5 % at its end.
        let (peak_at, end) = (0.3 * spec.duration_s, spec.duration_s);
        let b = -(0.05f64).ln() / ((end / peak_at) - 1.0 - (end / peak_at).ln());
        let c = b / peak_at;
        let envelope = |t: f64| {
            if t <= 0.0 || t >= end {
                0.0
            } else {
                (t / peak_at).powf(b) * (-c * (t - peak_at)).exp()
            }
        };
        let mut comps: Vec<Vec<f64>> = (0..3)
            .map(|_| {
                let white: Vec<f64> = (0..n)
                    .map(|i| envelope(i as f64 * dt - t0) * rng.normal())
                    .collect();
                let (u, v) = soil.response(&white);
                // The soil's absolute acceleration: −(2ζω u̇ + ω² u).
                (0..n)
                    .map(|i| -(2.0 * spec.soil_damping * w * v[i] + w * w * u[i]))
                    .collect()
            })
            .collect();
        if let Some((period, share)) = spec.pulse {
            // A Gabor-like pulse in velocity, centred at the envelope's peak, along x.
            let wp = 2.0 * std::f64::consts::PI / period;
            let tc = t0 + peak_at;
            for (i, v) in comps[0].iter_mut().enumerate() {
                let s = i as f64 * dt - tc;
                let g = (-(s / (1.2 * period)).powi(2)).exp();
                *v += share * g * (wp * s).cos();
            }
        }
        let settle = BandPass::new(
            &BandConfig {
                low_hz: 0.05,
                high_hz: Some(0.45 * rate_hz),
                order: 2,
            },
            rate_hz,
        )
        .expect("fixed band");
        for comp in comps.iter_mut() {
            let f = settle.filter(comp);
            *comp = f[settle.pad..settle.pad + n].to_vec();
        }
        let peak = |x: &[f64]| x.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        let p0 = peak(&comps[0]).max(1e-300);
        let p1 = peak(&comps[1]).max(1e-300);
        let p2 = peak(&comps[2]).max(1e-300);
        let scale = [
            spec.peak_mps2 / p0,
            0.8 * spec.peak_mps2 / p1,
            0.6 * spec.peak_mps2 / p2,
        ];
        GroundMotion {
            accel_mps2: (0..n)
                .map(|i| std::array::from_fn(|k| comps[k][i] * scale[k]))
                .collect(),
            dt,
        }
    }
}

/// A sensor of the simulated building.
#[derive(Debug, Clone, PartialEq)]
pub struct SimSensor {
    pub sensor_id: String,
    pub floor: usize,
    /// Turned about the vertical by this, rad.
    pub azimuth_rad: f64,
    pub calibration: SensorCalibration,
    /// The offset the record states, m/s².
    pub offset_mps2: [f64; 3],
    /// Output noise per channel (output unit).
    pub output_noise: f64,
}

/// A record's sensitivity `0.1·(I + small cross-axis)` V per m/s², its covariance from a
/// relative gain uncertainty and an absolute cross-axis one, ν = `dof`.
pub fn calibration(
    gain_relative_u: f64,
    cross_axis_u: f64,
    output_noise: f64,
    dof: f64,
) -> SensorCalibration {
    let s = [
        [0.1, 0.0002, -0.0001],
        [0.0003, 0.101, 0.0002],
        [-0.0002, 0.0001, 0.099],
    ];
    let mut cov = [[0.0; 9]; 9];
    for (i, row) in s.iter().enumerate() {
        for j in 0..3 {
            let k = 3 * i + j;
            let u = if i == j {
                gain_relative_u
            } else {
                cross_axis_u
            };
            cov[k][k] = (u * row[i]).powi(2);
        }
    }
    let sm = crate::process::rows_to_matrix(&s);
    let si = sm.try_inverse().expect("invertible");
    let noise = si * Matrix3::from_diagonal_element(output_noise * output_noise) * si.transpose();
    SensorCalibration {
        sensitivity: s,
        sensitivity_covariance: Some(cov),
        covariance_dof: dof,
        noise_covariance: std::array::from_fn(|i| std::array::from_fn(|j| noise[(i, j)])),
        noise_dof: f64::INFINITY,
    }
}

/// The mounting of a sensor turned by `azimuth` about the vertical (rows, sensor → building).
pub fn mounting(azimuth: f64) -> [[f64; 3]; 3] {
    let (s, c) = azimuth.sin_cos();
    [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]
}

/// The corrected record a sensor gives of `response` over samples `span` (the first at
/// `start_s`): its truth drawn from its record's covariance, noise, a clock off by a draw of
/// `clock_u_s`. With `exact`, the truth itself (no error, no noise): what the parameters of
/// the true motion are computed from.
pub fn record(
    sensor: &SimSensor,
    response: &Response,
    span: std::ops::Range<usize>,
    start_s: f64,
    clock_u_s: f64,
    exact: bool,
    rng: &mut Rng,
) -> SensorRecord {
    let r = crate::process::rows_to_matrix(&mounting(sensor.azimuth_rad));
    let s = crate::process::rows_to_matrix(&sensor.calibration.sensitivity);
    let s_inv = s.try_inverse().expect("invertible");
    let delta = match (&sensor.calibration.sensitivity_covariance, exact) {
        (Some(c), false) => {
            let sigma = SMatrix::<f64, 9, 9>::from_fn(|i, j| c[i][j]);
            let l = sigma.cholesky().map(|ch| ch.l()).unwrap_or_else(|| {
                SMatrix::<f64, 9, 9>::from_fn(
                    |i, j| if i == j { sigma[(i, i)].sqrt() } else { 0.0 },
                )
            });
            let z = SMatrix::<f64, 9, 1>::from_fn(|_, _| rng.normal());
            let d = l * z;
            Matrix3::from_fn(|i, j| d[3 * i + j])
        }
        _ => Matrix3::zeros(),
    };
    let map = s_inv * (s + delta);
    let offset_error = if exact {
        [0.0; 3]
    } else {
        std::array::from_fn(|_| 0.02 * rng.normal())
    };
    let clock = if exact { 0.0 } else { clock_u_s * rng.normal() };
    let gravity = nalgebra::Vector3::new(0.0, 0.0, 9.806_65);
    let floor = &response.accel_mps2[sensor.floor];
    let dt = response.dt;
    let q = nalgebra::Vector3::from(sensor.offset_mps2);
    let q_true = q + nalgebra::Vector3::from(offset_error);
    let accel_mps2 = span
        .clone()
        .map(|i| {
            let a = nalgebra::Vector3::from(floor[i]);
            let slope = if i + 1 < floor.len() {
                (nalgebra::Vector3::from(floor[i + 1]) - a) / dt
            } else {
                nalgebra::Vector3::zeros()
            };
            let building = a + slope * clock + gravity;
            let sensor_axes = r.transpose() * building;
            let mut corrected = map * (sensor_axes - q_true) + q;
            if !exact {
                let n = nalgebra::Vector3::from_fn(|_, _| sensor.output_noise * rng.normal());
                corrected += s_inv * n;
            }
            [corrected[0], corrected[1], corrected[2]]
        })
        .collect::<Vec<_>>();
    let mut calibration = sensor.calibration.clone();
    if exact {
        calibration.sensitivity_covariance = None;
        calibration.noise_covariance = [[0.0; 3]; 3];
    }
    SensorRecord {
        sensor_id: sensor.sensor_id.clone(),
        floor: sensor.floor as i32,
        height_m: 0.0,
        mounting: mounting(sensor.azimuth_rad),
        start_s,
        sample_rate_hz: 1.0 / dt,
        valid: vec![true; accel_mps2.len()],
        flagged: false,
        accel_mps2,
        calibration,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn modes_of_the_frame_and_their_completeness() {
        let f = ShearFrame::six_storey();
        let x = f.modes(0);
        assert!((x.omega[0] / (2.0 * std::f64::consts::PI) - 1.0).abs() < 1e-9);
        let y = f.modes(1);
        assert!((y.omega[0] / x.omega[0] - 1.3f64.sqrt()).abs() < 1e-9);
        // Σ_r φ_r Γ_r = 1 at every floor: the modes are complete.
        for floor in 0..6 {
            let s: f64 = (0..6)
                .map(|r| x.shapes[r][floor] * x.participation[r])
                .sum();
            assert!((s - 1.0).abs() < 1e-9, "{s}");
        }
    }

    /// The exact response against a direct integration of the equations of motion, M ü + C u̇ +
    /// K u = −M 1 a_g, by RK4 at a hundredth of the step with the ground linear between samples.
    #[test]
    fn the_response_is_the_equations_of_motion() {
        let f = ShearFrame::six_storey();
        let mut rng = Rng::new(4);
        let spec = GroundMotionSpec {
            quiet_before_s: 1.0,
            duration_s: 6.0,
            quiet_after_s: 1.0,
            peak_mps2: 2.0,
            soil_hz: 2.5,
            soil_damping: 0.6,
            pulse: None,
        };
        let g = GroundMotion::synthetic(&spec, 100.0, &mut rng);
        let r = f.respond(&g);
        let modes = f.modes(0);
        let n = f.storeys;
        // Modal damping as a matrix: C = M Φ diag(2ζω) Φᵀ M (Φ mass-orthonormal).
        let m = f.mass_kg;
        let phi = DMatrix::from_fn(n, n, |i, r| modes.shapes[r][i] / m.sqrt());
        let c = DMatrix::from_diagonal(&nalgebra::DVector::from_iterator(
            n,
            modes.omega.iter().map(|w| 2.0 * f.damping * w),
        ));
        let damping = (&phi * c * phi.transpose()) * m * m;
        let mut k = DMatrix::zeros(n, n);
        let ks = &f.stiffness_x_n_per_m;
        for i in 0..n {
            k[(i, i)] += ks[i];
            if i + 1 < n {
                k[(i, i)] += ks[i + 1];
                k[(i, i + 1)] -= ks[i + 1];
                k[(i + 1, i)] -= ks[i + 1];
            }
        }
        let rhs = |u: &nalgebra::DVector<f64>, v: &nalgebra::DVector<f64>, ag: f64| {
            let a = -(&k * u + &damping * v) / m - nalgebra::DVector::from_element(n, ag);
            (v.clone(), a)
        };
        let (mut u, mut v) = (nalgebra::DVector::zeros(n), nalgebra::DVector::zeros(n));
        let sub = 100;
        let h = g.dt / sub as f64;
        let mut worst = 0.0f64;
        let peak = r.displacement_m[n]
            .iter()
            .fold(0.0f64, |mm, d| mm.max(d[0].abs()));
        for i in 0..g.accel_mps2.len() - 1 {
            for s in 0..sub {
                let ag =
                    |x: f64| g.accel_mps2[i][0] + (g.accel_mps2[i + 1][0] - g.accel_mps2[i][0]) * x;
                let (x0, x1) = (s as f64 / sub as f64, (s as f64 + 0.5) / sub as f64);
                let x2 = (s as f64 + 1.0) / sub as f64;
                let (k1u, k1v) = rhs(&u, &v, ag(x0));
                let (k2u, k2v) = rhs(&(&u + &k1u * (h / 2.0)), &(&v + &k1v * (h / 2.0)), ag(x1));
                let (k3u, k3v) = rhs(&(&u + &k2u * (h / 2.0)), &(&v + &k2v * (h / 2.0)), ag(x1));
                let (k4u, k4v) = rhs(&(&u + &k3u * h), &(&v + &k3v * h), ag(x2));
                u += (k1u + k2u * 2.0 + k3u * 2.0 + k4u) * (h / 6.0);
                v += (k1v + k2v * 2.0 + k3v * 2.0 + k4v) * (h / 6.0);
            }
            for floor in 0..n {
                worst = worst.max((u[floor] - r.displacement_m[floor + 1][i + 1][0]).abs());
            }
        }
        assert!(worst < 1e-6 * peak, "worst {worst} of a peak {peak}");
    }
}
