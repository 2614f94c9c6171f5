//! One sensor's record made ready for its parameters, and the first-order propagation every
//! smooth parameter's uncertainty goes through.
//!
//! **Processing.** The pre-event mean of each axis (the baseline: gravity, offsets) is taken off,
//! invalid samples are set to it (zero after), the record is padded and band-passed
//! ([`crate::filter`]) in the sensor's axes, turned into the building frame by the mounting
//! (`b = R·y`), and integrated to velocity and displacement by the trapezoidal rule over the
//! padded record.
//!
//! **The error model.** A corrected sample is `a = S⁻¹·V + q` with the record's `S` and `q`,
//! while the sensor's truth is `S + Δ`: so `a − a_true = S⁻¹Δ·(a_true − q) + const` plus white
//! noise `n` (the record's output noise through `S⁻¹`, and its stated uncertainty, taken as
//! independent from sample to sample). The baseline and the band-pass remove constants, and
//! every step is linear, so the processed record's error is, exactly to first order,
//!
//! ```text
//! δb(t) = R·S⁻¹·Δ·y(t) + R·(M n)(t),
//! ```
//!
//! `y` the processed record in the sensor's axes and `M` the band-pass. A parameter whose
//! first-order change is `δP = Σ_p Σ_t s_p(t)·w_pᵀ δb(t)` (directions `w_p`, weights `s_p` over
//! the padded record) then has
//!
//! - a calibration part `gᵀ Σ_S g` with `g = vec((R S⁻¹)ᵀ · Σ_p w_p (Σ_t s_p(t) y(t))ᵀ)`, `Σ_S`
//!   the record's covariance of the nine entries of `S`, at the record's ν;
//! - a noise part `Σ_pq w_pᵀ Σ_b w_q ⟨M s_p, M s_q⟩` over the record's samples (`M` is
//!   symmetric, and noise exists only where samples do), `Σ_b = R Σ_n Rᵀ`, at the noise's ν.
//!
//! Gain errors and cross-axis errors both live in `Δ` with their covariance; a gain error
//! scales a parameter, a cross-axis error mixes in the other axes' motion at the same instant,
//! which the formula carries whatever the motion.

use nalgebra::{Matrix3, SMatrix, Vector3};

use crate::filter::{BandConfig, BandError, BandPass};

/// What a sensor's calibration record says about the error of its corrected samples.
#[derive(Debug, Clone, PartialEq)]
pub struct SensorCalibration {
    /// `S` of the set the samples were corrected with, output unit per m/s², rows.
    pub sensitivity: [[f64; 3]; 3],
    /// Covariance of `(S₀₀, S₀₁, S₀₂, S₁₀, …, S₂₂)`; none when the record states none.
    pub sensitivity_covariance: Option<[[f64; 9]; 9]>,
    /// Its degrees of freedom (infinite when not stated).
    pub covariance_dof: f64,
    /// Covariance of the white error of one corrected sample in the sensor's axes, (m/s²)²:
    /// `S⁻¹·diag(output_noise²)·S⁻ᵀ + diag(uncertainty_mps2²)`.
    pub noise_covariance: [[f64; 3]; 3],
    /// Its degrees of freedom (the smaller stated, or infinite).
    pub noise_dof: f64,
}

impl SensorCalibration {
    /// A calibration with no parameter uncertainty and white noise of `noise_mps2` per axis.
    pub fn noise_only(sensitivity: [[f64; 3]; 3], noise_mps2: f64) -> SensorCalibration {
        let v = noise_mps2 * noise_mps2;
        SensorCalibration {
            sensitivity,
            sensitivity_covariance: None,
            covariance_dof: f64::INFINITY,
            noise_covariance: [[v, 0.0, 0.0], [0.0, v, 0.0], [0.0, 0.0, v]],
            noise_dof: f64::INFINITY,
        }
    }
}

/// One sensor's corrected samples over an event's window, on the sensor's own time grid.
#[derive(Debug, Clone, PartialEq)]
pub struct SensorRecord {
    pub sensor_id: String,
    /// Floor number (0: ground floor; may be negative below ground).
    pub floor: i32,
    /// Height above the ground floor, m.
    pub height_m: f64,
    /// Rows of the rotation from the sensor's axes into the building frame (`x`, `y`
    /// horizontal, `z` up).
    pub mounting: [[f64; 3]; 3],
    /// Time of the first sample, s, relative to the event's reference instant.
    pub start_s: f64,
    pub sample_rate_hz: f64,
    /// Corrected acceleration in the sensor's axes, m/s² (gravity included).
    pub accel_mps2: Vec<[f64; 3]>,
    /// Whether each sample is usable: present, finite, calibrated, not clipped.
    pub valid: Vec<bool>,
    /// Some usable samples carried quality flags that leave their uncertainty less assured
    /// (outside the calibrated band or amplitude, an expired or suspect record): decisions on
    /// this sensor's values go no further than `possible`.
    pub flagged: bool,
    pub calibration: SensorCalibration,
}

impl SensorRecord {
    pub fn len(&self) -> usize {
        self.accel_mps2.len()
    }

    pub fn is_empty(&self) -> bool {
        self.accel_mps2.is_empty()
    }

    pub fn dt(&self) -> f64 {
        1.0 / self.sample_rate_hz
    }

    /// Time of sample `i`, s from the reference instant.
    pub fn time_s(&self, i: usize) -> f64 {
        self.start_s + i as f64 / self.sample_rate_hz
    }
}

/// Why a record cannot be processed.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ProcessError {
    #[error("sensor {sensor}: {source}")]
    Band {
        sensor: String,
        #[source]
        source: BandError,
    },
    #[error("sensor {sensor}: {what}")]
    Record { sensor: String, what: String },
}

/// Half-length of the band-pass kernel kept for the peaks' noise (samples each side).
pub const KERNEL_HALF: usize = 128;

/// A record band-passed, in the building frame, with what its errors need.
#[derive(Debug, Clone)]
pub struct Processed {
    pub sensor_id: String,
    pub floor: i32,
    pub height_m: f64,
    pub dt: f64,
    /// Samples of the record; the processed arrays are `pad + n + pad` long.
    pub n: usize,
    pub pad: usize,
    /// Time of padded sample 0, s from the reference instant.
    pub origin_s: f64,
    pub rotation: Matrix3<f64>,
    /// `R·S⁻¹`: how a sensitivity error `Δ` maps the sensor-frame record into a building-frame
    /// error.
    pub error_map: Matrix3<f64>,
    /// Band-passed acceleration in the sensor's axes (`y`) and in the building frame (`b`),
    /// velocity and displacement of both, padded.
    pub y: [Vec<f64>; 3],
    pub b: [Vec<f64>; 3],
    pub vel_y: [Vec<f64>; 3],
    pub vel_b: [Vec<f64>; 3],
    pub disp_y: [Vec<f64>; 3],
    pub disp_b: [Vec<f64>; 3],
    /// The unfiltered, baseline-removed acceleration in the building frame (record only).
    pub raw_b: [Vec<f64>; 3],
    pub band: BandPass,
    /// The band-pass's kernel, ±[`KERNEL_HALF`], scaled to the whole kernel's energy.
    pub kernel: Vec<f64>,
    /// The whole kernel's energy: band-passed white noise of variance σ² has σ² times it.
    pub kernel_energy: f64,
    pub sensitivity_covariance: Option<SMatrix<f64, 9, 9>>,
    pub covariance_dof: f64,
    /// Noise covariance in the building frame, per sample before filtering.
    pub noise_b: Matrix3<f64>,
    pub noise_dof: f64,
    pub invalid: usize,
    pub flagged: bool,
    /// The baseline was the mean of the pre-event samples (false: of the whole record).
    pub pre_event_baseline: bool,
}

/// One term of a linear functional: a building-frame direction and weights over the padded
/// record.
pub type Term = (Vector3<f64>, Vec<f64>);

pub(crate) fn rows_to_matrix(m: &[[f64; 3]; 3]) -> Matrix3<f64> {
    Matrix3::new(
        m[0][0], m[0][1], m[0][2], m[1][0], m[1][1], m[1][2], m[2][0], m[2][1], m[2][2],
    )
}

/// Trapezoidal running integral from rest.
pub fn integrate(x: &[f64], dt: f64) -> Vec<f64> {
    let mut out = vec![0.0; x.len()];
    for i in 1..x.len() {
        out[i] = out[i - 1] + 0.5 * dt * (x[i - 1] + x[i]);
    }
    out
}

/// The transpose of [`integrate`]: weights on the integral turned into weights on its input.
pub fn integrate_adjoint(w: &[f64], dt: f64) -> Vec<f64> {
    // v_k = dt·(x_0/2 + x_1 + … + x_{k−1} + x_k/2) for k ≥ 1, so ∂v_k/∂x_i is dt/2 at i = 0 and
    // i = k, dt in between.
    let n = w.len();
    let mut out = vec![0.0; n];
    let mut tail = 0.0; // Σ_{k > i} w_k
    for i in (0..n).rev() {
        out[i] = dt * (tail + if i > 0 { 0.5 * w[i] } else { 0.0 });
        if i == 0 {
            out[0] = dt * 0.5 * tail;
        }
        tail += w[i];
    }
    out
}

impl Processed {
    /// Processes `record`; the baseline is the mean of its valid samples before
    /// `event_start_s` (at least a second of them), or of the whole record.
    pub fn new(
        record: &SensorRecord,
        band: &BandConfig,
        event_start_s: f64,
    ) -> Result<Processed, ProcessError> {
        let bad = |what: String| ProcessError::Record {
            sensor: record.sensor_id.clone(),
            what,
        };
        if record.valid.len() != record.len() {
            return Err(bad(format!(
                "{} validity flags for {} samples",
                record.valid.len(),
                record.len()
            )));
        }
        if record.len() < 16 {
            return Err(bad(format!("{} samples: too short a record", record.len())));
        }
        let filter =
            BandPass::new(band, record.sample_rate_hz).map_err(|source| ProcessError::Band {
                sensor: record.sensor_id.clone(),
                source,
            })?;
        let s = rows_to_matrix(&record.calibration.sensitivity);
        let s_inv = s
            .try_inverse()
            .ok_or_else(|| bad("the calibration's sensitivity is singular".into()))?;
        let rotation = rows_to_matrix(&record.mounting);
        let usable =
            |i: usize| record.valid[i] && record.accel_mps2[i].iter().all(|v| v.is_finite());
        let invalid = (0..record.len()).filter(|&i| !usable(i)).count();
        if invalid == record.len() {
            return Err(bad("no valid sample".into()));
        }
        let mut mean = [0.0; 3];
        let mut count = 0usize;
        for i in 0..record.len() {
            if usable(i) && record.time_s(i) < event_start_s {
                count += 1;
                for (m, a) in mean.iter_mut().zip(record.accel_mps2[i]) {
                    *m += a;
                }
            }
        }
        let pre_event_baseline = count as f64 * record.dt() >= 1.0;
        if !pre_event_baseline {
            (mean, count) = ([0.0; 3], 0);
            for i in (0..record.len()).filter(|&i| usable(i)) {
                count += 1;
                for (m, a) in mean.iter_mut().zip(record.accel_mps2[i]) {
                    *m += a;
                }
            }
        }
        mean.iter_mut().for_each(|m| *m /= count as f64);
        let n = record.len();
        let mut centred: [Vec<f64>; 3] = std::array::from_fn(|_| vec![0.0; n]);
        for i in (0..n).filter(|&i| usable(i)) {
            for k in 0..3 {
                centred[k][i] = record.accel_mps2[i][k] - mean[k];
            }
        }
        let dt = record.dt();
        let y: [Vec<f64>; 3] = std::array::from_fn(|k| filter.filter(&centred[k]));
        let to_building = |v: &[Vec<f64>; 3]| -> [Vec<f64>; 3] {
            let len = v[0].len();
            std::array::from_fn(|r| {
                (0..len)
                    .map(|i| {
                        rotation[(r, 0)] * v[0][i]
                            + rotation[(r, 1)] * v[1][i]
                            + rotation[(r, 2)] * v[2][i]
                    })
                    .collect()
            })
        };
        let b = to_building(&y);
        let raw_b = to_building(&centred);
        let vel_y: [Vec<f64>; 3] = std::array::from_fn(|k| integrate(&y[k], dt));
        let disp_y: [Vec<f64>; 3] = std::array::from_fn(|k| integrate(&vel_y[k], dt));
        let vel_b = to_building(&vel_y);
        let disp_b = to_building(&disp_y);
        let full = filter.kernel(filter.pad);
        let kernel_energy: f64 = full.iter().map(|v| v * v).sum();
        let mid = filter.pad;
        let mut kernel = full[mid - KERNEL_HALF..=mid + KERNEL_HALF].to_vec();
        let kept: f64 = kernel.iter().map(|v| v * v).sum();
        let scale = (kernel_energy / kept).sqrt();
        kernel.iter_mut().for_each(|v| *v *= scale);
        let noise_s = rows_to_matrix(&record.calibration.noise_covariance);
        Ok(Processed {
            sensor_id: record.sensor_id.clone(),
            floor: record.floor,
            height_m: record.height_m,
            dt,
            n,
            pad: filter.pad,
            origin_s: record.start_s - filter.pad as f64 * dt,
            rotation,
            error_map: rotation * s_inv,
            y,
            b,
            vel_y,
            vel_b,
            disp_y,
            disp_b,
            raw_b,
            band: filter,
            kernel,
            kernel_energy,
            sensitivity_covariance: record
                .calibration
                .sensitivity_covariance
                .map(|c| SMatrix::<f64, 9, 9>::from_fn(|i, j| c[i][j])),
            covariance_dof: record.calibration.covariance_dof,
            noise_b: rotation * noise_s * rotation.transpose(),
            noise_dof: record.calibration.noise_dof,
            invalid,
            flagged: record.flagged,
            pre_event_baseline,
        })
    }

    /// Samples of the padded arrays.
    pub fn len_padded(&self) -> usize {
        self.b[0].len()
    }

    /// Time of padded sample `i`, s from the reference instant.
    pub fn time_s(&self, i: usize) -> f64 {
        self.origin_s + i as f64 * self.dt
    }

    /// The record's samples within the padded arrays.
    pub fn record_span(&self) -> std::ops::Range<usize> {
        self.pad..self.pad + self.n
    }

    /// Variance of one band-passed noise sample along building direction `w`.
    pub fn noise_variance_along(&self, w: &Vector3<f64>) -> f64 {
        (w.transpose() * self.noise_b * w)[(0, 0)] * self.kernel_energy
    }

    /// The gradient of a functional with respect to the nine entries of `S`.
    fn gradient(&self, terms: &[Term]) -> SMatrix<f64, 9, 1> {
        let mut g = Matrix3::zeros();
        for (w, s) in terms {
            let mut ys = Vector3::zeros();
            for (i, si) in s.iter().enumerate() {
                if *si != 0.0 {
                    ys += Vector3::new(self.y[0][i], self.y[1][i], self.y[2][i]) * *si;
                }
            }
            g += w * ys.transpose();
        }
        let grad = self.error_map.transpose() * g;
        SMatrix::<f64, 9, 1>::from_fn(|k, _| grad[(k / 3, k % 3)])
    }

    /// The band-passed weights `M s`, over the record's samples only.
    fn filtered(&self, s: &[f64]) -> Vec<f64> {
        let mut m = s.to_vec();
        self.band.apply(&mut m);
        m[self.record_span()].to_vec()
    }

    /// Calibration and noise parts of the covariance of two linear functionals (their
    /// variances when `a` and `b` are the same).
    pub fn covariance(&self, a: &[Term], b: &[Term]) -> (f64, f64) {
        let cal = match &self.sensitivity_covariance {
            Some(sigma) => (self.gradient(a).transpose() * sigma * self.gradient(b))[(0, 0)],
            None => 0.0,
        };
        if self.noise_b.iter().all(|v| *v == 0.0) {
            return (cal, 0.0);
        }
        let fa: Vec<Vec<f64>> = a.iter().map(|(_, s)| self.filtered(s)).collect();
        let fb: Vec<Vec<f64>> = b.iter().map(|(_, s)| self.filtered(s)).collect();
        let mut noise = 0.0;
        for ((wp, _), mp) in a.iter().zip(&fa) {
            for ((wq, _), mq) in b.iter().zip(&fb) {
                let c = (wp.transpose() * self.noise_b * wq)[(0, 0)];
                if c != 0.0 {
                    noise += c * mp.iter().zip(mq).map(|(x, y)| x * y).sum::<f64>();
                }
            }
        }
        (cal, noise)
    }

    /// The calibration part alone of a functional's variance (no filtering).
    pub fn calibration_variance(&self, terms: &[Term]) -> f64 {
        match &self.sensitivity_covariance {
            Some(sigma) => {
                (self.gradient(terms).transpose() * sigma * self.gradient(terms))[(0, 0)]
            }
            None => 0.0,
        }
    }

    /// Whether the record states any noise.
    pub fn has_noise(&self) -> bool {
        self.noise_b.iter().any(|v| *v != 0.0)
    }

    /// A delta at padded sample `i`.
    pub fn delta(&self, i: usize, weight: f64) -> Vec<f64> {
        let mut s = vec![0.0; self.len_padded()];
        s[i] = weight;
        s
    }
}

/// Unit vector of building direction `axis` (0 `x`, 1 `y`, 2 `z`).
pub fn axis(axis: usize) -> Vector3<f64> {
    let mut w = Vector3::zeros();
    w[axis] = 1.0;
    w
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_integral_and_its_adjoint() {
        let dt = 0.1;
        let x = [1.0, 2.0, -1.0, 0.5, 3.0];
        let v = integrate(&x, dt);
        assert!((v[1] - 0.15).abs() < 1e-12);
        assert!((v[4] - 0.1 * (0.5 + 2.0 - 1.0 + 0.5 + 1.5)).abs() < 1e-12);
        let w = [0.3, -1.0, 2.0, 0.7, 1.1];
        let lhs: f64 = v.iter().zip(&w).map(|(a, b)| a * b).sum();
        let adj = integrate_adjoint(&w, dt);
        let rhs: f64 = x.iter().zip(&adj).map(|(a, b)| a * b).sum();
        assert!((lhs - rhs).abs() < 1e-12, "{lhs} vs {rhs}");
    }
}
