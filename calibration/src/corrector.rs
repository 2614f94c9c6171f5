//! The correction model: a calibration record turned into per-sensor correctors.
//!
//! For an output vector `V` a [`SetCorrector`] returns `a = S⁻¹·V + q` in m/s² and, per axis,
//! the standard uncertainty of `a` by the law of propagation of uncertainty (JCGM 100, the GUM),
//! from three independent contributions:
//!
//! 1. the parameters: `Σ_a = J·Σ_θ·Jᵀ` with `θ = (S row-major, q)` and `J = ∂a/∂θ`. Since
//!    `d(S⁻¹) = −S⁻¹·dS·S⁻¹`, `∂a_k/∂S_ij = −(S⁻¹)_ki·a′_j` with `a′ = S⁻¹·V`, and
//!    `∂a_k/∂q_m = δ_km`;
//! 2. the output noise `Σ_V` stated in the record: `S⁻¹·Σ_V·S⁻ᵀ`;
//! 3. the set's stated `uncertainty_mps2`, as independent per-axis variances.
//!
//! Row k of `J` is linear in `x = (a′₀, a′₁, a′₂, 1)`, so the variance of `a_k` is a quadratic
//! form `xᵀ·M_k·x` whose 4×4 matrix `M_k` is computed once, when the record is loaded. The sample
//! path then costs ten multiply-adds per axis for full covariance propagation, with no matrix
//! product and no allocation.
//!
//! # Degrees of freedom
//!
//! A contribution whose variance was estimated from data (the parameter covariance from a fit's
//! residuals, the output noise from a recording) carries degrees of freedom ν, which the record
//! may state; an unstated ν is infinite. Per sample and axis the effective ν of the sum is the
//! Welch–Satterthwaite `ν_eff = u⁴ / Σ u_i⁴/ν_i` over the three contributions, and the coverage
//! factor is Student's t at ν_eff and the set's coverage probability
//! ([`SetCorrector::coverage_factor_at`]). A set that states no ν at all keeps the coverage
//! factor it states, as records always did.
//!
//! # Temperature
//!
//! A record with a [`TemperatureModel`] is corrected per batch at the batch's temperature:
//! [`SetCorrector::at_temperature`] returns the set with `S⁻¹·diag(1/(1 + c_g·ΔT))` in place of
//! `S⁻¹`, `q + c_q·ΔT` in place of `q`, and the coefficients' covariance added to the parameter
//! part. With `a′` the scaled output, `∂a_k/∂c_q,m = ΔT·δ_km` and
//! `∂a_k/∂c_g,j = −ΔT·(S⁻¹)_kj·(S·a′)_j`, so that part is again a quadratic form in `(a′, 1)`,
//! scaled by ΔT² and precomputed at load: the sample path costs what it did. Its degrees of
//! freedom join the parameter part's as the smaller of the two, which only lowers ν_eff.
//!
//! Everything that can be wrong with a record is found when it is loaded
//! ([`Corrector::from_record`]): wrong shape or non-finite values (by
//! [`CalibrationRecord::validate`]), a sensitivity matrix with condition number above
//! [`MAX_CONDITION_NUMBER`], a covariance that is not positive semi-definite, and values so
//! large or so uniformly zero that a corrected sample within the domain would carry a standard
//! uncertainty that is not finite or below [`MIN_UNCERTAINTY_MPS2`] (the sample path keeps its
//! quadratic forms in f32, so 10³⁹ is already infinite there). Correction itself cannot fail;
//! non-finite outputs give non-finite accelerations, which the caller flags.

use std::sync::Arc;

use nalgebra::{Matrix3, SMatrix, SymmetricEigen};
use triax_protocol::record::{
    CalibrationRecord, CalibrationSet, Domain, RecordError, SetKind, TemperatureModel,
};
use triax_protocol::SensorId;

use crate::student::{CoverageTable, DEFAULT_COVERAGE_PROBABILITY};

/// Largest accepted condition number (2-norm) of a sensitivity matrix.
///
/// A MEMS sensitivity matrix is diagonally dominant, with a condition number near 1 (1.1 for the
/// matrices of the reference paper). A matrix at 10³ would amplify output noise and errors a
/// thousandfold along its weak direction: such a record is a fitting or typing mistake.
pub const MAX_CONDITION_NUMBER: f64 = 1e3;

/// Smallest standard uncertainty a corrected sample may carry: no calibration knows an
/// acceleration to a nanometre per second squared, and a stated 0 would claim exactness.
pub const MIN_UNCERTAINTY_MPS2: f64 = 1e-9;

/// Largest standard uncertainty a corrected sample within the domain may carry: 10⁸ g says
/// nothing, and the corrected stream carries u as an f32, which ends at 3.4·10³⁸.
pub const MAX_UNCERTAINTY_MPS2: f64 = 1e9;

/// Tolerance, relative to the largest eigenvalue, for a covariance eigenvalue below zero
/// (round-off of a JSON round trip).
const PSD_TOLERANCE: f64 = 1e-9;

/// Why a record cannot be loaded into a corrector.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum LoadError {
    #[error(transparent)]
    Invalid(#[from] RecordError),
    #[error(
        "sensor {sensor_id}, version {version}: {set}.sensitivity is near-singular: condition \
         number {condition:.3e} exceeds {MAX_CONDITION_NUMBER:e}"
    )]
    IllConditioned {
        sensor_id: SensorId,
        version: u64,
        set: &'static str,
        condition: f64,
    },
    #[error(
        "sensor {sensor_id}, version {version}: {set}.covariance is not positive semi-definite \
         (eigenvalue {min_eigenvalue:e})"
    )]
    CovarianceNotPositive {
        sensor_id: SensorId,
        version: u64,
        set: &'static str,
        min_eigenvalue: f64,
    },
    #[error(
        "sensor {sensor_id}, version {version}: {set} gives a standard uncertainty of {u_mps2:e} \
         m/s² on axis {axis} at acceleration {at_mps2:?} m/s²{temperature}, within its domain: \
         a corrected sample must carry a u from {MIN_UNCERTAINTY_MPS2:e} to \
         {MAX_UNCERTAINTY_MPS2:e} m/s² (covariance, uncertainty_mps2, sensor.output_noise or the \
         temperature model too large, or all zero)"
    )]
    UncertaintyOutOfRange {
        sensor_id: SensorId,
        version: u64,
        set: &'static str,
        axis: usize,
        at_mps2: [f64; 3],
        /// ", at 35 °C" when found through the temperature model, else empty.
        temperature: String,
        u_mps2: f64,
    },
}

/// A corrected sample: specific force and its per-axis standard uncertainty (k = 1).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Corrected {
    pub accel_mps2: [f64; 3],
    pub uncertainty_mps2: [f64; 3],
}

/// Coefficients of a symmetric quadratic form in `x = (x₀, x₁, x₂, x₃)`:
/// `c[0]x₀² + c[1]x₁² + c[2]x₂² + c[3]x₃² + c[4]x₀x₁ + c[5]x₀x₂ + c[6]x₀x₃ + c[7]x₁x₂ + c[8]x₁x₃
/// + c[9]x₂x₃` (off-diagonal terms already doubled).
///
/// Stored in f32, evaluated in f64. A gateway holds two sets of six forms for each of its
/// sensors, and f32 halves them; a coefficient then carries a relative error below 6·10⁻⁸, so a
/// variance does too unless its terms cancel, and even a thousandfold cancellation (a parameter
/// correlation far beyond what a fit produces) leaves the uncertainty right to 10⁻⁴ of itself,
/// where two significant digits are what an uncertainty is quoted to.
type QuadForm = [f32; 10];

fn quad_form(m: &SMatrix<f64, 4, 4>) -> QuadForm {
    // Only the symmetric part matters to a quadratic form.
    let s = |i: usize, j: usize| m[(i, j)] + m[(j, i)];
    [
        m[(0, 0)],
        m[(1, 1)],
        m[(2, 2)],
        m[(3, 3)],
        s(0, 1),
        s(0, 2),
        s(0, 3),
        s(1, 2),
        s(1, 3),
        s(2, 3),
    ]
    .map(|c| c as f32)
}

/// Evaluates a quadratic form at `(x₀, x₁, x₂, w)`.
#[inline(always)]
fn eval(c: &QuadForm, x: [f64; 3], w: f64) -> f64 {
    let c = c.map(f64::from);
    let [x0, x1, x2] = x;
    x0 * (c[0] * x0 + c[4] * x1 + c[5] * x2 + c[6] * w)
        + x1 * (c[1] * x1 + c[7] * x2 + c[8] * w)
        + x2 * (c[2] * x2 + c[9] * w)
        + c[3] * w * w
}

/// One calibration set ready to apply.
///
/// Laid out as written, its temperature model first: a batch corrected with the other set still
/// asks this one whether the record models temperature (see [`Corrector::HEAD_BYTES`]).
#[derive(Debug, Clone, PartialEq)]
#[repr(C)]
pub struct SetCorrector {
    /// The record's temperature model for this set; `None` without one, and in a set already
    /// taken to a temperature.
    thermal: Option<Arc<Thermal>>,
    s_inv: [[f64; 3]; 3],
    offset_mps2: [f64; 3],
    /// Parameter part of Cov(a_k, a_l) as a quadratic form in (a′, 1), for k ≤ l, indexed by
    /// [`pair`].
    param_cov: [QuadForm; 6],
    /// Noise and stated contributions, which do not depend on the sample: Cov(a_k, a_l).
    const_cov: [[f64; 3]; 3],
    /// The two parts of `const_cov` kept apart for filtered quantities, which reduce the white
    /// output noise (V², per output channel) but not the stated part (per axis, (m/s²)²).
    output_noise_var: [f64; 3],
    stated_var: [f64; 3],
    /// Reciprocal degrees of freedom of the three contributions, 0 for infinitely many.
    inv_dof: InverseDof,
    /// `u_noise⁴/ν_noise + u_stated⁴/ν_stated` per axis: the constant part of the
    /// Welch–Satterthwaite denominator.
    const_ws: [f64; 3],
    domain: Domain,
    coverage_factor: f64,
    /// Student's t factors at the set's coverage probability; `None` when the set states no
    /// degrees of freedom, and its own coverage factor applies.
    coverage_table: Option<Arc<CoverageTable>>,
    kind: SetKind,
}

/// A temperature model applied to one set (see the module's documentation).
#[derive(Debug, Clone, PartialEq)]
struct Thermal {
    reference_c: f64,
    range_c: [f64; 2],
    offset_per_c: [f64; 3],
    gain_per_c: [f64; 3],
    /// The coefficients' part of Cov(a_k, a_l) per °C² of ΔT², as forms in (a′, 1).
    forms: [QuadForm; 6],
    inv_dof: f64,
}

/// Where a batch's temperature stands against a record's temperature model.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum TemperatureCheck {
    /// The record has no temperature model: nothing to do.
    NotModelled,
    /// Inside the calibrated range: corrected for it.
    Inside,
    /// Outside the calibrated range: corrected by extrapolation, and flagged.
    Outside,
    /// The record needs a temperature and the batch has none (or a non-finite one): not
    /// corrected for temperature, and flagged.
    Missing,
}

/// Reciprocals of the degrees of freedom of a set's three contributions (0: infinitely many).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct InverseDof {
    pub parameters: f64,
    pub noise: f64,
    pub stated: f64,
}

/// The covariance of a low-passed `a` by contribution, each 3×3, so that a caller can weigh
/// their degrees of freedom: see [`SetCorrector::covariance_filtered_parts`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CovarianceParts {
    pub parameters: [[f64; 3]; 3],
    pub stated: [[f64; 3]; 3],
    pub noise: [[f64; 3]; 3],
    /// What the caller added beyond the truth of the low band; known, infinite ν.
    pub extra: [[f64; 3]; 3],
}

impl CovarianceParts {
    pub fn total(&self) -> [[f64; 3]; 3] {
        let mut c = [[0.0; 3]; 3];
        for (k, row) in c.iter_mut().enumerate() {
            for (l, cell) in row.iter_mut().enumerate() {
                *cell =
                    self.parameters[k][l] + self.stated[k][l] + self.noise[k][l] + self.extra[k][l];
            }
        }
        c
    }
}

fn inverse(dof: Option<f64>) -> f64 {
    dof.map_or(0.0, |nu| 1.0 / nu)
}

/// The most negative eigenvalue of `sigma`, if it is below zero beyond round-off.
///
/// A Cholesky factorisation of `sigma` nudged by the tolerance settles almost every record at a
/// fraction of the cost of an eigendecomposition, which matters when a gateway loads ten thousand
/// records at start; the eigenvalues are computed only to describe a refusal.
fn negative_eigenvalue(sigma: &SMatrix<f64, 12, 12>) -> Option<f64> {
    let max_variance = sigma.diagonal().max().max(0.0);
    let nudge = PSD_TOLERANCE * max_variance;
    let nudged = sigma + SMatrix::<f64, 12, 12>::identity() * nudge;
    if max_variance > 0.0 && nudged.cholesky().is_some() {
        return None;
    }
    let eigenvalues = SymmetricEigen::new(*sigma).eigenvalues;
    let max = eigenvalues.max().max(0.0);
    let min = eigenvalues.min();
    (min < -PSD_TOLERANCE * max.max(f64::MIN_POSITIVE)).then_some(min)
}

/// Index of the (k, l) entry of a symmetric 3×3 matrix stored as its upper triangle.
#[inline(always)]
const fn pair(k: usize, l: usize) -> usize {
    let (k, l) = if k <= l { (k, l) } else { (l, k) };
    match (k, l) {
        (0, 0) => 0,
        (1, 1) => 1,
        (2, 2) => 2,
        (0, 1) => 3,
        (0, 2) => 4,
        _ => 5,
    }
}

impl SetCorrector {
    fn new(
        record: &CalibrationRecord,
        kind: SetKind,
        name: &'static str,
    ) -> Result<SetCorrector, LoadError> {
        let set: &CalibrationSet = record.set(kind);
        let s = Matrix3::from_fn(|i, j| set.sensitivity[i][j]);
        let sv = s.singular_values();
        let condition = sv.max() / sv.min();
        // A zero matrix gives NaN, refused like an infinite condition number.
        if condition.is_nan() || condition > MAX_CONDITION_NUMBER {
            return Err(LoadError::IllConditioned {
                sensor_id: record.sensor_id.clone(),
                version: record.version,
                set: name,
                condition,
            });
        }
        // Invertible: its condition number is finite.
        let s_inv = s
            .try_inverse()
            .expect("well-conditioned matrix is invertible");

        let mut param_cov = [[0.0f32; 10]; 6];
        if let Some(cov) = &set.covariance {
            let sigma = SMatrix::<f64, 12, 12>::from_fn(|i, j| cov[i][j]);
            if let Some(min_eigenvalue) = negative_eigenvalue(&sigma) {
                return Err(LoadError::CovarianceNotPositive {
                    sensor_id: record.sensor_id.clone(),
                    version: record.version,
                    set: name,
                    min_eigenvalue,
                });
            }
            // B_k maps x = (a′, 1) to row k of J: J_k = xᵀ·B_k.
            let b = |k: usize| {
                let mut m = SMatrix::<f64, 4, 12>::zeros();
                for j in 0..3 {
                    for i in 0..3 {
                        m[(j, 3 * i + j)] = -s_inv[(k, i)];
                    }
                }
                m[(3, 9 + k)] = 1.0;
                m
            };
            for k in 0..3 {
                for l in k..3 {
                    let m = b(k) * sigma * b(l).transpose();
                    param_cov[pair(k, l)] = quad_form(&m);
                }
            }
        }

        let mut const_cov = Matrix3::zeros();
        let output_noise_var = record
            .sensor
            .output_noise
            .unwrap_or([0.0; 3])
            .map(|n| n * n);
        if let Some(noise) = record.sensor.output_noise {
            let sigma_v = Matrix3::from_diagonal(&noise.map(|n| n * n).into());
            const_cov += s_inv * sigma_v * s_inv.transpose();
        }
        let noise_var_mps2 = [0, 1, 2].map(|k| const_cov[(k, k)]);
        let stated_var = set.uncertainty_mps2.map(|u| u * u);
        for k in 0..3 {
            const_cov[(k, k)] += stated_var[k];
        }
        let inv_dof = InverseDof {
            parameters: inverse(set.covariance_dof),
            noise: inverse(record.sensor.output_noise_dof),
            stated: inverse(set.uncertainty_dof),
        };
        let const_ws = [0, 1, 2].map(|k| {
            noise_var_mps2[k].powi(2) * inv_dof.noise + stated_var[k].powi(2) * inv_dof.stated
        });
        let states_dof = set.covariance_dof.is_some()
            || set.uncertainty_dof.is_some()
            || record.sensor.output_noise_dof.is_some()
            || record
                .temperature
                .as_ref()
                .is_some_and(|t| t.covariance_dof.is_some());
        let coverage_table = states_dof.then(|| {
            CoverageTable::shared(
                set.coverage_probability
                    .unwrap_or(DEFAULT_COVERAGE_PROBABILITY),
            )
        });

        if let Some(t) = &record.temperature {
            let sigma = SMatrix::<f64, 6, 6>::from_fn(|i, j| t.covariance[i][j]);
            let eigenvalues = SymmetricEigen::new(sigma).eigenvalues;
            let (min, max) = (eigenvalues.min(), eigenvalues.max().max(0.0));
            if min < -PSD_TOLERANCE * max.max(f64::MIN_POSITIVE) {
                return Err(LoadError::CovarianceNotPositive {
                    sensor_id: record.sensor_id.clone(),
                    version: record.version,
                    set: "temperature",
                    min_eigenvalue: min,
                });
            }
        }
        let thermal = record
            .temperature
            .as_ref()
            .map(|t| Arc::new(Thermal::new(t, &s, &s_inv)));

        Ok(SetCorrector {
            kind,
            s_inv: s_inv.transpose().into(),
            offset_mps2: set.offset,
            param_cov,
            const_cov: const_cov.transpose().into(),
            output_noise_var,
            stated_var,
            inv_dof,
            const_ws,
            domain: set.domain,
            coverage_factor: set.coverage_factor,
            coverage_table,
            thermal,
        })
    }

    /// Whether the record corrects for temperature, and where `temperature_c` stands.
    pub fn temperature_check(&self, temperature_c: Option<f64>) -> TemperatureCheck {
        match (&self.thermal, temperature_c.filter(|t| t.is_finite())) {
            (None, _) => TemperatureCheck::NotModelled,
            (Some(_), None) => TemperatureCheck::Missing,
            (Some(t), Some(c)) if (t.range_c[0]..=t.range_c[1]).contains(&c) => {
                TemperatureCheck::Inside
            }
            (Some(_), Some(_)) => TemperatureCheck::Outside,
        }
    }

    /// The set at a sensor temperature of `temperature_c` (see the module's documentation);
    /// `None` when the record has no temperature model, or the temperature is not finite or
    /// lies more than one calibrated span beyond the calibrated range, or would change a gain
    /// by more than half: a first-order model says nothing that far out, and a hostile
    /// temperature must not divide by a gain of zero.
    pub fn at_temperature(&self, temperature_c: f64) -> Option<SetCorrector> {
        let t = self.thermal.as_ref()?;
        let [low, high] = t.range_c;
        let span = high - low;
        if !(temperature_c >= low - span && temperature_c <= high + span) {
            return None;
        }
        let dt = temperature_c - t.reference_c;
        if t.gain_per_c.iter().any(|g| (g * dt).abs() > 0.5) {
            return None;
        }
        let mut set = SetCorrector {
            thermal: None,
            ..self.clone()
        };
        for (row, s_row) in set.s_inv.iter_mut().zip(&self.s_inv) {
            for j in 0..3 {
                row[j] = s_row[j] / (1.0 + t.gain_per_c[j] * dt);
            }
        }
        for k in 0..3 {
            set.offset_mps2[k] += t.offset_per_c[k] * dt;
        }
        let dt2 = (dt * dt) as f32;
        for (form, extra) in set.param_cov.iter_mut().zip(&t.forms) {
            for (c, e) in form.iter_mut().zip(extra) {
                *c += e * dt2;
            }
        }
        set.inv_dof.parameters = set.inv_dof.parameters.max(t.inv_dof);
        Some(set)
    }

    /// Whether the set states degrees of freedom, so that its coverage factor depends on the
    /// sample ([`coverage_factor_at`](Self::coverage_factor_at)).
    pub fn states_dof(&self) -> bool {
        self.coverage_table.is_some()
    }

    /// The coverage factor for an interval with `nu_eff` effective degrees of freedom:
    /// Student's t at the set's coverage probability, ν truncated to the integer below as
    /// JCGM 100 G.4.1 does (and a little further on a coarse grid above 30, always to the
    /// larger factor). A set that states no degrees of freedom returns its own factor.
    #[inline]
    pub fn coverage_factor_at(&self, nu_eff: f64) -> f64 {
        match &self.coverage_table {
            Some(table) => table.factor(nu_eff),
            None => self.coverage_factor,
        }
    }

    pub fn inverse_dof(&self) -> InverseDof {
        self.inv_dof
    }

    /// `u_noise⁴/ν_noise + u_stated⁴/ν_stated` per axis, (m/s²)⁴.
    pub fn constant_ws(&self) -> [f64; 3] {
        self.const_ws
    }

    /// [`correct_variance`](Self::correct_variance) and, per axis, the Welch–Satterthwaite
    /// denominator `Σ u_i⁴/ν_i` of that variance, so that `ν_eff = variance² / denominator`.
    #[inline(always)]
    pub fn correct_with_dof(&self, v: [f64; 3]) -> ([f64; 3], [f64; 3], [f64; 3]) {
        let scaled = self.scale(v);
        let mut accel_mps2 = [0.0; 3];
        let mut variance = [0.0; 3];
        let mut ws = [0.0; 3];
        for k in 0..3 {
            accel_mps2[k] = scaled[k] + self.offset_mps2[k];
            let param = eval(&self.param_cov[k], scaled, 1.0);
            variance[k] = param + self.const_cov[k][k];
            ws[k] = param * param * self.inv_dof.parameters + self.const_ws[k];
        }
        (accel_mps2, variance, ws)
    }

    pub fn kind(&self) -> SetKind {
        self.kind
    }

    pub fn domain(&self) -> &Domain {
        &self.domain
    }

    pub fn coverage_factor(&self) -> f64 {
        self.coverage_factor
    }

    /// `S⁻¹·v`: the part of the correction that scales, without the offset.
    #[inline(always)]
    pub fn scale(&self, v: [f64; 3]) -> [f64; 3] {
        let m = &self.s_inv;
        [
            m[0][0] * v[0] + m[0][1] * v[1] + m[0][2] * v[2],
            m[1][0] * v[0] + m[1][1] * v[1] + m[1][2] * v[2],
            m[2][0] * v[0] + m[2][1] * v[1] + m[2][2] * v[2],
        ]
    }

    /// `a = S⁻¹·v + q` without uncertainty.
    #[inline(always)]
    pub fn accel(&self, v: [f64; 3]) -> [f64; 3] {
        let a = self.scale(v);
        [
            a[0] + self.offset_mps2[0],
            a[1] + self.offset_mps2[1],
            a[2] + self.offset_mps2[2],
        ]
    }

    /// `a = S⁻¹·v + q` and its per-axis standard uncertainty, with full covariance propagation.
    #[inline(always)]
    pub fn correct(&self, v: [f64; 3]) -> Corrected {
        let (accel_mps2, variance) = self.correct_variance(v);
        Corrected {
            accel_mps2,
            // Round-off can take a zero variance a hair below zero.
            uncertainty_mps2: variance.map(|var| var.max(0.0).sqrt()),
        }
    }

    /// `a = S⁻¹·v + q` and its per-axis variance (m²/s⁴), with full covariance propagation:
    /// [`correct`](Self::correct) without the square roots, for a caller that adds variances
    /// before taking one. Round-off can leave a zero variance a hair below zero.
    #[inline(always)]
    pub fn correct_variance(&self, v: [f64; 3]) -> ([f64; 3], [f64; 3]) {
        let scaled = self.scale(v);
        let mut accel_mps2 = [0.0; 3];
        let mut variance = [0.0; 3];
        for k in 0..3 {
            accel_mps2[k] = scaled[k] + self.offset_mps2[k];
            variance[k] = eval(&self.param_cov[k], scaled, 1.0) + self.const_cov[k][k];
        }
        (accel_mps2, variance)
    }

    /// Variance of `S⁻¹·v` per axis from the parameters alone (no offset, no noise, no stated
    /// part): the contribution of a band that the offset does not reach, such as the high band
    /// of a crossover.
    #[inline]
    pub fn scale_param_variance(&self, v: [f64; 3]) -> [f64; 3] {
        let scaled = self.scale(v);
        [0, 1, 2].map(|k| eval(&self.param_cov[k], scaled, 0.0).max(0.0))
    }

    /// Stated and noise variances per axis (independent of the sample).
    pub fn constant_variance(&self) -> [f64; 3] {
        [0, 1, 2].map(|k| self.const_cov[k][k])
    }

    /// The full 3×3 covariance of a low-passed `a` at low-passed output `v`: the parameter and
    /// stated parts as for one sample, the white output noise scaled by the filter's noise gain
    /// (Σh², the share of its variance the filter passes), plus `extra_output_var` (V², per
    /// channel) for what the filter's output carries beyond the low band's truth.
    pub fn covariance_filtered(
        &self,
        v: [f64; 3],
        noise_gain: f64,
        extra_output_var: [f64; 3],
    ) -> [[f64; 3]; 3] {
        self.covariance_filtered_parts(v, noise_gain, extra_output_var)
            .total()
    }

    /// [`covariance_filtered`](Self::covariance_filtered) by contribution, for a caller that
    /// combines their degrees of freedom ([`inverse_dof`](Self::inverse_dof); the extra part
    /// is a model, with infinitely many).
    pub fn covariance_filtered_parts(
        &self,
        v: [f64; 3],
        noise_gain: f64,
        extra_output_var: [f64; 3],
    ) -> CovarianceParts {
        let scaled = self.scale(v);
        let m = &self.s_inv;
        let through = |out_var: [f64; 3]| {
            let mut c = [[0.0; 3]; 3];
            for (k, row) in c.iter_mut().enumerate() {
                for (l, cell) in row.iter_mut().enumerate() {
                    *cell = (0..3).map(|j| m[k][j] * out_var[j] * m[l][j]).sum();
                }
            }
            c
        };
        let parameters =
            [0, 1, 2].map(|k| [0, 1, 2].map(|l| eval(&self.param_cov[pair(k, l)], scaled, 1.0)));
        let mut stated = [[0.0; 3]; 3];
        for (k, row) in stated.iter_mut().enumerate() {
            row[k] = self.stated_var[k];
        }
        CovarianceParts {
            parameters,
            stated,
            noise: through(self.output_noise_var.map(|n| n * noise_gain)),
            extra: through(extra_output_var),
        }
    }

    /// The full 3×3 covariance of `a` at output `v`, for quantities that mix axes (tilt).
    pub fn covariance(&self, v: [f64; 3]) -> [[f64; 3]; 3] {
        let scaled = self.scale(v);
        let mut c = [[0.0; 3]; 3];
        for (k, row) in c.iter_mut().enumerate() {
            for (l, cell) in row.iter_mut().enumerate() {
                *cell = eval(&self.param_cov[pair(k, l)], scaled, 1.0) + self.const_cov[k][l];
            }
        }
        c
    }
}

impl Thermal {
    fn new(model: &TemperatureModel, s: &Matrix3<f64>, s_inv: &Matrix3<f64>) -> Thermal {
        let sigma = SMatrix::<f64, 6, 6>::from_fn(|i, j| model.covariance[i][j]);
        // Row k of ∂a/∂(c_q, c_g) per unit ΔT, as xᵀ·B_k with x = (a′, 1).
        let b = |k: usize| {
            let mut m = SMatrix::<f64, 4, 6>::zeros();
            m[(3, k)] = 1.0;
            for j in 0..3 {
                for i in 0..3 {
                    m[(i, 3 + j)] = -s_inv[(k, j)] * s[(j, i)];
                }
            }
            m
        };
        let mut forms = [[0.0f32; 10]; 6];
        for k in 0..3 {
            for l in k..3 {
                forms[pair(k, l)] = quad_form(&(b(k) * sigma * b(l).transpose()));
            }
        }
        Thermal {
            reference_c: model.reference_c,
            range_c: model.range_c,
            offset_per_c: model.offset_mps2_per_c,
            gain_per_c: model.gain_per_c.unwrap_or([0.0; 3]),
            forms,
            inv_dof: inverse(model.covariance_dof),
        }
    }
}

/// Whether a record is in force at a given time.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Validity {
    NotYetValid,
    Valid,
    Expired,
}

/// Refuses a set whose corrected samples could carry a standard uncertainty that is not finite
/// or below [`MIN_UNCERTAINTY_MPS2`]: probes the sample path itself at rest and at the ends of
/// the domain's amplitude along each axis and diagonal (the variance is a positive
/// semi-definite quadratic form in the acceleration plus constants, so its extremes over the
/// domain are reached at its edge, and its floor is the constant part), and, with a temperature
/// model, at the farthest temperatures the set is applied at.
fn check_uncertainty(
    record: &CalibrationRecord,
    set: &SetCorrector,
    name: &'static str,
) -> Result<(), LoadError> {
    let cal = record.set(set.kind());
    let amplitude = cal.domain.amplitude_max_mps2;
    let mut probes = vec![[0.0; 3]];
    for sign in [-1.0, 1.0] {
        for axis in 0..3 {
            let mut a = [0.0; 3];
            a[axis] = sign * amplitude;
            probes.push(a);
        }
        probes.push([sign * amplitude / 3f64.sqrt(); 3]);
    }
    let mut variants = vec![(set.clone(), String::new())];
    if let Some(t) = &record.temperature {
        let span = t.range_c[1] - t.range_c[0];
        for c in [t.range_c[0] - span, t.reference_c, t.range_c[1] + span] {
            // Beyond a gain change of a half the set is not applied at all (`at_temperature`).
            if let Some(at) = set.at_temperature(c) {
                variants.push((at, format!(", at {c} °C")));
            }
        }
    }
    for (variant, temperature) in variants {
        for a in &probes {
            // The output that reads as `a`: v = S·(a − q).
            let d = [0, 1, 2].map(|k| a[k] - variant.offset_mps2[k]);
            let v = [0, 1, 2].map(|i| (0..3).map(|j| cal.sensitivity[i][j] * d[j]).sum::<f64>());
            let (_, variance) = variant.correct_variance(v);
            for (axis, var) in variance.iter().enumerate() {
                let u = var.max(0.0).sqrt();
                if !(MIN_UNCERTAINTY_MPS2..=MAX_UNCERTAINTY_MPS2).contains(&u) {
                    return Err(LoadError::UncertaintyOutOfRange {
                        sensor_id: record.sensor_id.clone(),
                        version: record.version,
                        set: name,
                        axis,
                        at_mps2: *a,
                        temperature,
                        u_mps2: u,
                    });
                }
            }
        }
    }
    Ok(())
}

/// A sensor's calibration, loaded and checked, ready for the sample path.
///
/// Laid out as written: what every batch reads besides the set it is corrected with lies in
/// the first [`Corrector::HEAD_BYTES`], so that a gateway about to correct a batch of a sensor
/// whose corrector has left the cache asks for those and for that set only, not for both sets
/// (1.2 KB, of which a batch in one mode reads half).
#[derive(Debug, Clone, PartialEq)]
#[repr(C)]
pub struct Corrector {
    version: u64,
    output_full_scale: f64,
    valid_from_ns: i128,
    valid_until_ns: Option<i128>,
    static_set: SetCorrector,
    dynamic: SetCorrector,
    sensor_id: SensorId,
}

// Two cache lines of the corrector's twenty.
const _: () = assert!(Corrector::HEAD_BYTES <= 128);

impl Corrector {
    /// Bytes at the start of a corrector that hold what a batch reads besides its sets: the
    /// version, the validity, the full scale and whether the record models temperature (the
    /// static set's first field).
    pub const HEAD_BYTES: usize =
        std::mem::offset_of!(Corrector, static_set) + std::mem::size_of::<Option<Arc<Thermal>>>();

    /// Checks the record and precomputes everything the sample path needs.
    pub fn from_record(record: &CalibrationRecord) -> Result<Corrector, LoadError> {
        let c = Corrector::assemble(record)?;
        for (set, name) in [(&c.static_set, "static"), (&c.dynamic, "dynamic")] {
            check_uncertainty(record, set, name)?;
        }
        Ok(c)
    }

    /// [`from_record`](Self::from_record) without the bounds on the uncertainty it gives:
    /// hand-computed tests want records whose uncertainty is zero on some axes.
    fn assemble(record: &CalibrationRecord) -> Result<Corrector, LoadError> {
        record.validate()?;
        Ok(Corrector {
            sensor_id: record.sensor_id.clone(),
            version: record.version,
            static_set: SetCorrector::new(record, SetKind::Static, "static")?,
            dynamic: SetCorrector::new(record, SetKind::Dynamic, "dynamic")?,
            valid_from_ns: record.valid_from.unix_timestamp_nanos(),
            valid_until_ns: record.valid_until.map(|t| t.unix_timestamp_nanos()),
            output_full_scale: record.sensor.output_full_scale.unwrap_or(f64::INFINITY),
        })
    }

    pub fn sensor_id(&self) -> &SensorId {
        &self.sensor_id
    }

    pub fn version(&self) -> u64 {
        self.version
    }

    /// Start of the record's validity, ns since the Unix epoch.
    pub fn valid_from_ns(&self) -> i128 {
        self.valid_from_ns
    }

    /// End of the record's validity, ns since the Unix epoch; none: until superseded.
    pub fn valid_until_ns(&self) -> Option<i128> {
        self.valid_until_ns
    }

    /// Whether the record carries a temperature model.
    pub fn models_temperature(&self) -> bool {
        self.static_set.thermal.is_some()
    }

    pub fn set(&self, kind: SetKind) -> &SetCorrector {
        match kind {
            SetKind::Static => &self.static_set,
            SetKind::Dynamic => &self.dynamic,
        }
    }

    /// Whether the record is in force at `timestamp_ns` (ns since the Unix epoch).
    pub fn validity_at(&self, timestamp_ns: i64) -> Validity {
        let t = i128::from(timestamp_ns);
        if t < self.valid_from_ns {
            Validity::NotYetValid
        } else if self.valid_until_ns.is_some_and(|until| t >= until) {
            Validity::Expired
        } else {
            Validity::Valid
        }
    }

    /// Whether an output reached the sensor's full scale on any axis.
    #[inline(always)]
    pub fn is_clipped(&self, v: [f64; 3]) -> bool {
        v.iter().any(|x| x.abs() >= self.output_full_scale)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{SVector, Vector3};
    use rand::{rngs::StdRng, Rng, SeedableRng};
    use rand_distr::StandardNormal;
    use triax_protocol::record::sample;

    #[test]
    fn what_a_batch_reads_besides_its_set_lies_in_the_head() {
        use std::mem::{offset_of, size_of};
        let ends = [
            ("version", offset_of!(Corrector, version) + size_of::<u64>()),
            (
                "output_full_scale",
                offset_of!(Corrector, output_full_scale) + size_of::<f64>(),
            ),
            (
                "valid_from_ns",
                offset_of!(Corrector, valid_from_ns) + size_of::<i128>(),
            ),
            (
                "valid_until_ns",
                offset_of!(Corrector, valid_until_ns) + size_of::<Option<i128>>(),
            ),
            (
                "static_set.thermal",
                offset_of!(Corrector, static_set)
                    + offset_of!(SetCorrector, thermal)
                    + size_of::<Option<Arc<Thermal>>>(),
            ),
        ];
        for (field, end) in ends {
            assert!(end <= Corrector::HEAD_BYTES, "{field} ends at {end}");
        }
    }

    fn diag_record() -> CalibrationRecord {
        let mut r = sample::record("hand", 1);
        for set in [&mut r.static_set, &mut r.dynamic] {
            set.sensitivity = [[2.0, 0.0, 0.0], [0.0, 4.0, 0.0], [0.0, 0.0, 5.0]];
            set.offset = [0.1, 0.2, 0.3];
            set.uncertainty_mps2 = [0.0; 3];
            set.covariance = None;
        }
        r.sensor.output_noise = None;
        r
    }

    #[test]
    fn hand_computed_value_without_uncertainty() {
        let c = Corrector::assemble(&diag_record()).unwrap();
        let out = c.set(SetKind::Static).correct([2.0, 4.0, -5.0]);
        assert_eq!(out.accel_mps2, [1.1, 1.2, -0.7]);
        assert_eq!(out.uncertainty_mps2, [0.0; 3]);
    }

    /// Welch–Satterthwaite by hand on a diagonal S = diag(2, 4, 5): offset variance 0.01² on x
    /// with ν = 6, output noise 0.02 V (0.01 m/s² on x) with ν = 100, stated 0.01 m/s² with
    /// ν = ∞. On x each contributes 1e-4, so ν_eff = (3e-4)² / (1e-8/6 + 1e-8/100) = 50.94.
    #[test]
    fn effective_dof_by_hand() {
        use crate::student::t_quantile;
        let mut r = diag_record();
        let mut cov = [[0.0; 12]; 12];
        cov[9][9] = 1e-4;
        r.static_set.covariance = Some(Box::new(cov));
        r.static_set.covariance_dof = Some(6.0);
        r.static_set.uncertainty_mps2 = [0.01, 0.0, 0.0];
        r.sensor.output_noise = Some([0.02, 0.0, 0.0]);
        r.sensor.output_noise_dof = Some(100.0);
        let c = Corrector::assemble(&r).unwrap();
        let set = c.set(SetKind::Static);
        assert!(set.states_dof());
        let (_, var, ws) = set.correct_with_dof([1.0, 1.0, 1.0]);
        assert!((var[0] - 3e-4).abs() < 1e-11, "{var:?}");
        let nu = var[0] * var[0] / ws[0];
        assert!(
            (nu - 9e-8 / (1e-8 / 6.0 + 1e-8 / 100.0)).abs() < 1e-3,
            "{nu}"
        );
        // Truncated to 50, which is on the grid.
        assert_eq!(set.coverage_factor_at(nu), t_quantile(50, 0.95));
        // A set that states no ν keeps its own factor; the dynamic set here states none.
        r.static_set.covariance_dof = None;
        r.sensor.output_noise_dof = None;
        let c = Corrector::assemble(&r).unwrap();
        assert!(!c.set(SetKind::Static).states_dof());
        assert_eq!(c.set(SetKind::Static).coverage_factor_at(3.0), 2.0);
        // A stated probability moves k: 99 % at ν = 6.
        let mut r = diag_record();
        r.static_set.covariance_dof = Some(6.0);
        r.static_set.coverage_probability = Some(0.99);
        let c = Corrector::assemble(&r).unwrap();
        assert_eq!(
            c.set(SetKind::Static).coverage_factor_at(6.0),
            t_quantile(6, 0.99)
        );
    }

    /// PROTOCOL.md §3.1's worked example: per axis, offset variance 1e-4 with ν = 6 and output
    /// noise 0.001 V through S⁻¹ = 10 (variance 1e-4) with ν = 200: u = √2e-4 = 0.01414 m/s²,
    /// ν_eff = (2e-4)² / (1e-8/6 + 1e-8/200) = 23.30, k = t₂₃ = 2.069.
    #[test]
    fn protocol_worked_example() {
        use crate::student::t_quantile;
        let path = format!(
            "{}/../protocol/tests/golden/record_v1_dof.json",
            env!("CARGO_MANIFEST_DIR")
        );
        let text = std::fs::read(path).unwrap();
        let r: CalibrationRecord = triax_protocol::from_json(&text).unwrap();
        let c = Corrector::from_record(&r).unwrap();
        let set = c.set(SetKind::Static);
        let (_, var, ws) = set.correct_with_dof([0.0, 0.0, 0.981]);
        for k in 0..3 {
            assert!((var[k].sqrt() - 0.014142).abs() < 1e-6, "{var:?}");
            let nu = var[k] * var[k] / ws[k];
            assert!((nu - 23.30).abs() < 0.01, "{nu}");
            let k = set.coverage_factor_at(nu);
            assert_eq!(k, t_quantile(23, 0.95));
            assert!((k - 2.069).abs() < 5e-4, "{k}");
        }
    }

    /// Hand-computed on S = diag(2, 4, 5), q = (0.1, 0.2, 0.3), T₀ = 20 °C, c_q = (0.01, 0, 0)
    /// m/s²/°C, c_g = (0, 0.001, 0) /°C, Var(c_q,x) = 1e-6, Var(c_g,y) = 1e-8, at 30 °C:
    /// V = (2, 4, 5) reads V₀ = (2, 4/1.01, 5) at T₀, so a = (1.2, 1/1.01 + 0.2, 1.3); the
    /// added variances are 10²·1e-6 on x and (10·¼·4/1.01)²·1e-8 on y.
    #[test]
    fn temperature_by_hand() {
        use triax_protocol::record::TemperatureModel;
        let mut r = diag_record();
        let mut cov = [[0.0; 6]; 6];
        cov[0][0] = 1e-6;
        cov[4][4] = 1e-8;
        r.temperature = Some(TemperatureModel {
            reference_c: 20.0,
            range_c: [15.0, 35.0],
            offset_mps2_per_c: [0.01, 0.0, 0.0],
            gain_per_c: Some([0.0, 0.001, 0.0]),
            covariance: cov,
            covariance_dof: Some(4.0),
        });
        let c = Corrector::assemble(&r).unwrap();
        let set = c.set(SetKind::Static);
        assert_eq!(set.temperature_check(Some(30.0)), TemperatureCheck::Inside);
        assert_eq!(set.temperature_check(Some(40.0)), TemperatureCheck::Outside);
        assert_eq!(set.temperature_check(None), TemperatureCheck::Missing);
        assert_eq!(
            set.temperature_check(Some(f64::NAN)),
            TemperatureCheck::Missing
        );
        let warm = set.at_temperature(30.0).unwrap();
        let out = warm.correct([2.0, 4.0, 5.0]);
        let expect = [1.2, 1.0 / 1.01 + 0.2, 1.3];
        for (a, e) in out.accel_mps2.iter().zip(expect) {
            assert!((a - e).abs() < 1e-12, "{out:?}");
        }
        assert!((out.uncertainty_mps2[0] - 0.01).abs() < 1e-8, "{out:?}");
        let u_y = (10.0 * 0.25 * 4.0 / 1.01) * 1e-4;
        assert!((out.uncertainty_mps2[1] - u_y).abs() < 1e-9, "{out:?}");
        assert_eq!(out.uncertainty_mps2[2], 0.0);
        // At the reference temperature nothing changes; the coefficients' ν joins in.
        let same = set.at_temperature(20.0).unwrap();
        assert_eq!(same.correct([2.0, 4.0, 5.0]), set.correct([2.0, 4.0, 5.0]));
        assert_eq!(warm.inverse_dof().parameters, 0.25);
        assert!(
            warm.at_temperature(25.0).is_none(),
            "taken to a temperature once"
        );
        // Beyond one span (20 °C) past the range, and for a hostile value: not applied.
        assert!(set.at_temperature(54.9).is_some());
        assert!(set.at_temperature(55.1).is_none());
        assert!(set.at_temperature(f64::MAX).is_none());
        assert!(set.at_temperature(f64::NAN).is_none());
        // A covariance that is not positive semi-definite is refused by name.
        r.temperature.as_mut().unwrap().covariance[0][1] = 1e-5;
        r.temperature.as_mut().unwrap().covariance[1][0] = 1e-5;
        let e = Corrector::assemble(&r).unwrap_err();
        assert!(e.to_string().contains("temperature.covariance"), "{e}");
    }

    /// the single sample's covariance; at gain 0 the noise is gone while the stated part stays;
    /// an extra output variance goes through S⁻¹ like noise (hand-computed on a diagonal S).
    #[test]
    fn filtered_covariance_scales_only_the_noise() {
        let mut r = diag_record();
        r.static_set.uncertainty_mps2 = [0.0, 0.05, 0.0];
        r.sensor.output_noise = Some([0.02, 0.04, 0.0]);
        let c = Corrector::assemble(&r).unwrap();
        let set = c.set(SetKind::Static);
        let v = [1.0, -2.0, 3.0];
        assert_eq!(set.covariance_filtered(v, 1.0, [0.0; 3]), set.covariance(v));
        let none = set.covariance_filtered(v, 0.0, [0.0; 3]);
        assert!(none[0][0].abs() < 1e-18, "{none:?}");
        assert!((none[1][1] - 0.05f64.powi(2)).abs() < 1e-15, "{none:?}");
        let extra = set.covariance_filtered(v, 0.25, [0.0, 0.0, 1.0]);
        // x: (0.02/2)²·0.25; y: 0.05² + (0.04/4)²·0.25; z: 1/5².
        assert!((extra[0][0] - 0.25e-4).abs() < 1e-15, "{extra:?}");
        assert!(
            (extra[1][1] - (0.0025 + 0.25e-4)).abs() < 1e-15,
            "{extra:?}"
        );
        assert!((extra[2][2] - 0.04).abs() < 1e-15, "{extra:?}");
    }

    #[test]
    fn hand_computed_uncertainty() {
        // Var(S00) = σ², Var(q1) = τ², stated u = 0.05 on z, output noise 0.02 on x.
        let (sigma, tau) = (0.01, 0.03);
        let mut r = diag_record();
        let mut cov = [[0.0; 12]; 12];
        cov[0][0] = sigma * sigma;
        cov[10][10] = tau * tau;
        r.dynamic.covariance = Some(Box::new(cov));
        r.dynamic.uncertainty_mps2 = [0.0, 0.0, 0.05];
        r.sensor.output_noise = Some([0.02, 0.0, 0.0]);
        let c = Corrector::assemble(&r).unwrap();
        let out = c.set(SetKind::Dynamic).correct([6.0, 4.0, 5.0]);
        // a′₀ = 6/2 = 3; ∂a₀/∂S₀₀ = −(1/2)·3 = −1.5; noise: 0.02/2 = 0.01.
        let ux = ((1.5 * sigma).powi(2) + 0.01f64.powi(2)).sqrt();
        // The parameter part is stored in f32 (relative 6·10⁻⁸); the constant part in f64.
        assert!((out.uncertainty_mps2[0] / ux - 1.0).abs() < 1e-7, "{out:?}");
        assert!((out.uncertainty_mps2[1] / tau - 1.0).abs() < 1e-7);
        assert!((out.uncertainty_mps2[2] - 0.05).abs() < 1e-15);
        // The static set has no covariance and no stated uncertainty: only noise.
        let s = c.set(SetKind::Static).correct([6.0, 4.0, 5.0]);
        assert!((s.uncertainty_mps2[0] - 0.01).abs() < 1e-15);
        assert_eq!(s.uncertainty_mps2[1], 0.0);
    }

    #[test]
    fn refuses_near_singular_and_non_psd() {
        let mut r = diag_record();
        r.dynamic.sensitivity = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1e-4]];
        let e = Corrector::from_record(&r).unwrap_err();
        assert!(
            matches!(e, LoadError::IllConditioned { set: "dynamic", .. }),
            "{e}"
        );
        assert!(e.to_string().contains("condition number 1.000e4"), "{e}");

        let mut r = diag_record();
        r.static_set.sensitivity = [[0.0; 3]; 3];
        assert!(matches!(
            Corrector::from_record(&r),
            Err(LoadError::IllConditioned { set: "static", .. })
        ));

        let mut r = diag_record();
        let mut cov = [[0.0; 12]; 12];
        cov[0][0] = 1.0;
        cov[1][1] = 1.0;
        cov[0][1] = 2.0;
        cov[1][0] = 2.0;
        r.static_set.covariance = Some(Box::new(cov));
        let e = Corrector::from_record(&r).unwrap_err();
        assert!(matches!(e, LoadError::CovarianceNotPositive { .. }), "{e}");

        let mut r = diag_record();
        r.static_set.offset[1] = f64::NAN;
        assert!(matches!(
            Corrector::from_record(&r),
            Err(LoadError::Invalid(RecordError { ref field, .. })) if field == "static.offset[1]"
        ));
    }

    #[test]
    fn validity_window_and_clipping() {
        let mut r = diag_record();
        r.valid_until = Some(r.valid_from + time::Duration::seconds(10));
        r.sensor.output_full_scale = Some(3.0);
        let c = Corrector::assemble(&r).unwrap();
        let from = r.valid_from.unix_timestamp_nanos() as i64;
        assert_eq!(c.validity_at(from - 1), Validity::NotYetValid);
        assert_eq!(c.validity_at(from), Validity::Valid);
        assert_eq!(c.validity_at(from + 10_000_000_000), Validity::Expired);
        assert!(c.is_clipped([0.0, -3.0, 0.0]));
        assert!(!c.is_clipped([2.9, -2.9, 0.0]));
    }

    /// A random positive-definite 12×12 covariance with correlations, scaled per parameter.
    fn random_covariance(rng: &mut StdRng, s_scale: f64, q_scale: f64) -> [[f64; 12]; 12] {
        let a = SMatrix::<f64, 12, 12>::from_fn(|_, _| rng.sample::<f64, _>(StandardNormal));
        let mut c = a * a.transpose() / 12.0;
        for i in 0..12 {
            let si = if i < 9 { s_scale } else { q_scale };
            for j in 0..12 {
                let sj = if j < 9 { s_scale } else { q_scale };
                c[(i, j)] *= si * sj;
            }
        }
        let c = (c + c.transpose()) / 2.0;
        let mut out = [[0.0; 12]; 12];
        for (i, row) in out.iter_mut().enumerate() {
            for (j, cell) in row.iter_mut().enumerate() {
                *cell = c[(i, j)];
            }
        }
        out
    }

    /// The stored (f32) quadratic forms against J·Σ·Jᵀ built directly in f64, including a
    /// covariance whose gain and offset terms are correlated at −0.999, where the terms of the
    /// variance cancel most.
    #[test]
    fn f32_forms_match_direct_propagation() {
        let mut rng = StdRng::seed_from_u64(11);
        let mut correlated = [[0.0; 12]; 12];
        for (i, row) in correlated.iter_mut().enumerate() {
            row[i] = 1e-6;
        }
        // S_zz (index 8) against q_z (index 11): σ_S = 2·10⁻³, σ_q = 2·10⁻², ρ = −0.999.
        correlated[8][8] = 4e-6;
        correlated[11][11] = 4e-4;
        correlated[8][11] = -0.999 * 2e-3 * 2e-2;
        correlated[11][8] = correlated[8][11];
        let covs = [random_covariance(&mut rng, 0.004, 0.01), correlated];
        for (case, cov) in covs.into_iter().enumerate() {
            let mut r = sample::record("direct", 1);
            r.dynamic.sensitivity = [[0.98, 0.03, -0.02], [0.01, 1.05, 0.04], [-0.03, 0.02, 0.95]];
            r.dynamic.covariance = Some(Box::new(cov));
            r.dynamic.uncertainty_mps2 = [0.0; 3];
            r.sensor.output_noise = None;
            let c = Corrector::from_record(&r).unwrap();
            let set = c.set(SetKind::Dynamic);
            let s_inv = Matrix3::from_fn(|i, j| r.dynamic.sensitivity[i][j])
                .try_inverse()
                .unwrap();
            let sigma = SMatrix::<f64, 12, 12>::from_fn(|i, j| cov[i][j]);
            for v in [[0.1, -0.2, 9.3], [4.0, -3.0, 0.5], [0.0, 0.0, 0.0]] {
                let a = s_inv * Vector3::from(v);
                let mut j = SMatrix::<f64, 3, 12>::zeros();
                for k in 0..3 {
                    for i in 0..3 {
                        for m in 0..3 {
                            j[(k, 3 * i + m)] = -s_inv[(k, i)] * a[m];
                        }
                    }
                    j[(k, 9 + k)] = 1.0;
                }
                let direct = j * sigma * j.transpose();
                let stored = set.covariance(v);
                for k in 0..3 {
                    for l in 0..3 {
                        let scale = (direct[(k, k)] * direct[(l, l)]).sqrt();
                        assert!(
                            (stored[k][l] - direct[(k, l)]).abs() < 1e-6 * scale,
                            "case {case} v {v:?} [{k}][{l}]: stored {:e} direct {:e}",
                            stored[k][l],
                            direct[(k, l)]
                        );
                    }
                }
            }
        }
    }

    /// JCGM 101: draw the parameters, the output noise and the stated error, push each draw
    /// through a = S⁻¹V + q exactly, and compare the spread with the GUM propagation.
    #[test]
    fn agrees_with_monte_carlo_within_five_percent() {
        let mut rng = StdRng::seed_from_u64(7);
        let cases: [(f64, [f64; 3]); 4] = [
            (0.0, [0.5, -0.2, 9.8]),
            (0.001, [3.0, 2.0, -1.0]),
            (0.002, [-9.0, 0.5, 0.1]),
            (0.0005, [0.0, 0.0, 0.0]),
        ];
        for (case, (noise, accel_true)) in cases.into_iter().enumerate() {
            let mut r = sample::record("mc", 1);
            r.dynamic.sensitivity = [[0.98, 0.03, -0.02], [0.01, 1.05, 0.04], [-0.03, 0.02, 0.95]];
            r.dynamic.offset = [0.2, -0.1, 0.05];
            r.dynamic.uncertainty_mps2 = [0.003, 0.0, 0.006];
            let cov = random_covariance(&mut rng, 0.004, 0.01);
            r.dynamic.covariance = Some(Box::new(cov));
            r.sensor.output_noise = Some([noise, 2.0 * noise, noise]);
            let c = Corrector::from_record(&r).unwrap();
            let set = c.set(SetKind::Dynamic);

            let s = Matrix3::from_fn(|i, j| r.dynamic.sensitivity[i][j]);
            let q = Vector3::from(r.dynamic.offset);
            let v0 = s * (Vector3::from(accel_true) - q);
            let analytic = set.correct(v0.into());
            let analytic_cov = set.covariance(v0.into());

            let sigma = SMatrix::<f64, 12, 12>::from_fn(|i, j| cov[i][j]);
            let l = sigma.cholesky().unwrap().l();
            let n = 50_000;
            let mut sum = Vector3::zeros();
            let mut sum_sq = Matrix3::zeros();
            for _ in 0..n {
                let z = SVector::<f64, 12>::from_fn(|_, _| rng.sample(StandardNormal));
                let theta = l * z;
                let s_draw = s + Matrix3::from_fn(|i, j| theta[3 * i + j]);
                let q_draw = q + Vector3::new(theta[9], theta[10], theta[11]);
                let noise_v = Vector3::from_fn(|i, _| {
                    r.sensor.output_noise.unwrap()[i] * rng.sample::<f64, _>(StandardNormal)
                });
                let stated = Vector3::from_fn(|i, _| {
                    r.dynamic.uncertainty_mps2[i] * rng.sample::<f64, _>(StandardNormal)
                });
                let a = s_draw.try_inverse().unwrap() * (v0 + noise_v) + q_draw + stated;
                sum += a;
                sum_sq += a * a.transpose();
            }
            let mean = sum / n as f64;
            let mc_cov = (sum_sq - mean * mean.transpose() * n as f64) / (n as f64 - 1.0);
            for k in 0..3 {
                let mc = mc_cov[(k, k)].sqrt();
                let gum = analytic.uncertainty_mps2[k];
                assert!(
                    (gum / mc - 1.0).abs() < 0.05,
                    "case {case} axis {k}: GUM {gum:.5} vs Monte Carlo {mc:.5}"
                );
                assert!((analytic.accel_mps2[k] - accel_true[k]).abs() < 1e-9);
                for l in 0..3 {
                    let scale = (mc_cov[(k, k)] * mc_cov[(l, l)]).sqrt();
                    assert!(
                        (analytic_cov[k][l] - mc_cov[(k, l)]).abs() < 0.05 * scale,
                        "case {case} cov[{k}][{l}]: GUM {:e} vs Monte Carlo {:e}",
                        analytic_cov[k][l],
                        mc_cov[(k, l)]
                    );
                }
            }
        }
    }

    /// A record with no uncertainty at all would give samples that claim exactness: refused,
    /// by name, as are values so large the sample path's f32 forms overflow.
    #[test]
    fn refuses_zero_and_overflowing_uncertainty() {
        let zero = Corrector::from_record(&diag_record()).unwrap_err();
        assert!(
            matches!(zero, LoadError::UncertaintyOutOfRange { u_mps2, .. } if u_mps2 == 0.0),
            "{zero}"
        );
        assert!(zero.to_string().contains("from 1e-9 to 1e9 m/s²"), "{zero}");
        let mut huge = sample::record("huge", 1);
        huge.dynamic.uncertainty_mps2 = [1e39, 0.01, 0.01];
        let e = Corrector::from_record(&huge).unwrap_err();
        assert!(
            matches!(
                e,
                LoadError::UncertaintyOutOfRange {
                    set: "dynamic",
                    axis: 0,
                    ..
                }
            ),
            "{e}"
        );
        let mut noisy = sample::record("noisy", 1);
        noisy.sensor.output_noise = Some([1e300, 0.001, 0.001]);
        assert!(Corrector::from_record(&noisy).is_err());
        let mut cov = [[0.0; 12]; 12];
        for (i, row) in cov.iter_mut().enumerate() {
            row[i] = 1e300;
        }
        let mut r = sample::record("cov", 1);
        r.static_set.covariance = Some(Box::new(cov));
        assert!(matches!(
            Corrector::from_record(&r),
            Err(LoadError::UncertaintyOutOfRange { set: "static", .. })
        ));
        let mut v = sample::record("v", triax_protocol::record::MAX_VERSION + 1);
        assert!(Corrector::from_record(&v).is_err());
        v.version = triax_protocol::record::MAX_VERSION;
        assert!(Corrector::from_record(&v).is_ok());
    }

    proptest::proptest! {
        #![proptest_config(proptest::prelude::ProptestConfig::with_cases(2000))]
        /// Over records whose covariance, stated uncertainty and output noise range from zero
        /// through 10⁻³²⁰ to 10³²⁰: a record either is refused, or every sample it corrects
        /// within its domain, in either set and at any temperature it applies, carries a finite
        /// standard uncertainty of at least MIN_UNCERTAINTY_MPS2 on every axis.
        #[test]
        fn loaded_records_never_give_zero_or_infinite_uncertainty(
            cov_exp in -320i32..320,
            u_exp in -320i32..320,
            noise_exp in -320i32..320,
            parts in 0u8..8,
            a in proptest::array::uniform3(-1.0f64..1.0),
            temperature_c in -80.0f64..120.0,
            thermal_exp in -320i32..40,
        ) {
            let mut r = sample::record("prop", 1);
            let scale = |e: i32| 10f64.powi(e);
            let mut cov = [[0.0; 12]; 12];
            for (i, row) in cov.iter_mut().enumerate() {
                row[i] = scale(cov_exp) * if i < 9 { 1e-4 } else { 1.0 };
            }
            for set in [&mut r.static_set, &mut r.dynamic] {
                set.covariance = (parts & 1 != 0).then(|| Box::new(cov));
                set.uncertainty_mps2 = if parts & 2 != 0 { [scale(u_exp); 3] } else { [0.0; 3] };
            }
            r.sensor.output_noise = (parts & 4 != 0).then(|| [scale(noise_exp); 3]);
            if thermal_exp > -320 {
                let mut t_cov = [[0.0; 6]; 6];
                for (i, row) in t_cov.iter_mut().enumerate().take(3) {
                    row[i] = scale(thermal_exp);
                }
                r.temperature = Some(TemperatureModel {
                    reference_c: 20.0,
                    range_c: [10.0, 30.0],
                    offset_mps2_per_c: [1e-4; 3],
                    gain_per_c: None,
                    covariance: t_cov,
                    covariance_dof: None,
                });
            }
            let Ok(c) = Corrector::from_record(&r) else {
                return Ok(());
            };
            for kind in [SetKind::Static, SetKind::Dynamic] {
                let base = c.set(kind);
                let at = base.at_temperature(temperature_c);
                for set in std::iter::once(base).chain(at.as_ref()) {
                    let amplitude = r.set(kind).domain.amplitude_max_mps2;
                    let accel = a.map(|x| x * amplitude / 3f64.sqrt());
                    let s = r.set(kind).sensitivity;
                    let d = [0, 1, 2].map(|k| accel[k] - set.offset_mps2[k]);
                    let v = [0, 1, 2].map(|i| (0..3).map(|j| s[i][j] * d[j]).sum::<f64>());
                    for u in set.correct(v).uncertainty_mps2 {
                        proptest::prop_assert!(
                            (MIN_UNCERTAINTY_MPS2..=MAX_UNCERTAINTY_MPS2).contains(&u),
                            "u = {u} at {accel:?} ({kind:?})"
                        );
                    }
                }
            }
        }
    }
}
