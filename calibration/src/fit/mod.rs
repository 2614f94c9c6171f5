//! Estimation of the sensitivity matrix `S` and offset `q` from bench data.
//!
//! Both benches of the paper lead to the same linear problem. The model `a = S⁻¹·V + q` is
//! equivalent to
//!
//! ```text
//! V = S·a + c,   c = −S·q
//! ```
//!
//! which is linear in the twelve numbers `(S, c)`: each pair of a reference specific force `a`
//! and an output `V` gives three equations. [`static_fit`] takes the pairs from the mechanical
//! arm (gravity only), [`dynamic`] from the rotary table (gravity plus tangential and centripetal
//! acceleration, with the angular rate and acceleration estimated from the encoder by one of the
//! methods in [`reference`]). Both solve the stacked system by a singular value decomposition and
//! map the least-squares covariance of `(S, c)` to the covariance of `(S, q)` that a calibration
//! record carries (S row-major, then q).
//!
//! [`repeatability`] is the paper's uncertainty evaluation (calibration sets from single cycles,
//! cycle-to-cycle variability of the reference, the radius) and says which parts go into a
//! record's `uncertainty_mps2`; [`radius`] is the spacer-block estimate of the radius, eqs.
//! (4)–(8); [`tables`] computes the paper's comparison tables.
//!
//! Everything here is pure computation on slices: no files, no clock.

pub mod dynamic;
mod linear;
pub mod radius;
pub mod reference;
pub mod repeatability;
pub mod static_fit;
pub mod tables;
pub mod thermal;

use nalgebra::{Matrix3, SMatrix, Vector3};
use thiserror::Error;

pub use dynamic::{fit_dynamic, Bench, DynamicFit, Recording};
pub use radius::{fit_radius, RadiusFit};
pub use reference::{MotionLaw, ReferenceMethod};
pub use repeatability::UncertaintyBudget;
pub use static_fit::{
    fit_static, fit_static_with, reference_from_angles, ArmAngleUncertainty, StaticFit,
    StaticObservation,
};

/// Covariance of the twelve calibration parameters, ordered S row-major (S_xx, S_xy, …, S_zz)
/// then q (q_x, q_y, q_z); units (output/(m/s²))², output·m/s²·/(m/s²) and (m/s²)².
pub type ParameterCovariance = SMatrix<f64, 12, 12>;

/// Why a fit could not be made. Every message says what is missing or wrong in terms of the
/// inputs, so that the lab can pass it on unchanged.
#[derive(Debug, Clone, PartialEq, Error)]
pub enum FitError {
    /// Fewer pairs than the four that twelve unknowns need.
    #[error(
        "{found} orientation(s) given; at least 4 are needed to identify the 12 parameters \
         (each orientation gives 3 equations)"
    )]
    TooFewOrientations { found: usize },
    /// The reference vectors lie in one plane, so one direction of S is not observed.
    #[error(
        "the reference specific forces do not span three dimensions: they all lie in the plane \
         {normal_x:.3}·a_x + {normal_y:.3}·a_y + {normal_z:.3}·a_z = {level_mps2:.3} m/s²; add an \
         orientation off that plane (for instance one whose reference points along \
         ({normal_x:.3}, {normal_y:.3}, {normal_z:.3}))"
    )]
    ReferencesDegenerate {
        normal_x: f64,
        normal_y: f64,
        normal_z: f64,
        level_mps2: f64,
    },
    /// A value in the input is NaN or infinite.
    #[error("{what} {index}: value is not a finite number")]
    NonFinite { what: &'static str, index: usize },
    /// The fitted sensitivity matrix cannot be inverted, so `q = −S⁻¹·c` is undefined.
    #[error(
        "the fitted sensitivity matrix is singular: the outputs do not respond to all three axes"
    )]
    SingularSensitivity,
    /// The dynamic recordings together do not identify the twelve parameters.
    #[error("the recordings cannot identify all 12 parameters: {explanation}")]
    RankDeficient { explanation: String },
    /// A problem with one recording; `sample` counts from 0 in the order given.
    #[error("recording {recording}, sample {sample}: {problem}")]
    Recording {
        recording: String,
        sample: usize,
        problem: String,
    },
    /// A bench description that makes no physical sense.
    #[error("bench: {0}")]
    Bench(String),
    /// Spacer-block data that cannot give a radius.
    #[error("radius: {0}")]
    Radius(String),
    /// Static runs at several temperatures that cannot give a temperature model.
    #[error("temperature: {0}")]
    Temperature(String),
}

/// A fitted calibration: `a = S⁻¹·V + q` with the covariance of its twelve parameters.
///
/// The inverse of `S` is kept because every correction needs it and `S` never changes after
/// the fit.
#[derive(Debug, Clone, PartialEq)]
pub struct Calibration {
    sensitivity: Matrix3<f64>,
    sensitivity_inv: Matrix3<f64>,
    offset_mps2: Vector3<f64>,
    covariance: ParameterCovariance,
}

impl Calibration {
    /// Builds a calibration; fails when `S` is singular.
    pub fn new(
        sensitivity: Matrix3<f64>,
        offset_mps2: Vector3<f64>,
        covariance: ParameterCovariance,
    ) -> Result<Self, FitError> {
        let sensitivity_inv = sensitivity
            .try_inverse()
            .ok_or(FitError::SingularSensitivity)?;
        Ok(Self {
            sensitivity,
            sensitivity_inv,
            offset_mps2,
            covariance,
        })
    }

    /// `S`, in output units per m/s².
    pub fn sensitivity(&self) -> &Matrix3<f64> {
        &self.sensitivity
    }

    /// `S⁻¹`, in m/s² per output unit.
    pub fn sensitivity_inv(&self) -> &Matrix3<f64> {
        &self.sensitivity_inv
    }

    /// `q`, in m/s².
    pub fn offset_mps2(&self) -> &Vector3<f64> {
        &self.offset_mps2
    }

    /// Covariance of (S row-major, q).
    pub fn covariance(&self) -> &ParameterCovariance {
        &self.covariance
    }

    /// Returns a copy whose covariance is multiplied by `factor`.
    pub fn with_covariance_scaled(&self, factor: f64) -> Self {
        Self {
            covariance: self.covariance * factor,
            ..self.clone()
        }
    }

    /// The specific force for one output sample, eq. (1).
    pub fn correct(&self, output: &Vector3<f64>) -> Vector3<f64> {
        self.sensitivity_inv * output + self.offset_mps2
    }

    /// ∂a/∂(S row-major, q) at one output sample, for propagating the parameter covariance.
    ///
    /// With `u = S⁻¹·V`, ∂a/∂S_ik = −(S⁻¹)_{·i}·u_k and ∂a/∂q = I.
    pub fn jacobian(&self, output: &Vector3<f64>) -> SMatrix<f64, 3, 12> {
        let u = self.sensitivity_inv * output;
        let mut jac = SMatrix::<f64, 3, 12>::zeros();
        for i in 0..3 {
            for k in 0..3 {
                for row in 0..3 {
                    jac[(row, 3 * i + k)] = -self.sensitivity_inv[(row, i)] * u[k];
                }
            }
        }
        for row in 0..3 {
            jac[(row, 9 + row)] = 1.0;
        }
        jac
    }

    /// Standard uncertainty per axis of the corrected output due to the parameter covariance
    /// alone (GUM law of propagation, first order).
    pub fn parameter_uncertainty_mps2(&self, output: &Vector3<f64>) -> Vector3<f64> {
        let jac = self.jacobian(output);
        let cov = jac * self.covariance * jac.transpose();
        Vector3::new(
            cov[(0, 0)].max(0.0).sqrt(),
            cov[(1, 1)].max(0.0).sqrt(),
            cov[(2, 2)].max(0.0).sqrt(),
        )
    }
}

/// Root mean square per axis of a set of vectors; zero for an empty set.
pub fn rms(values: impl IntoIterator<Item = Vector3<f64>>) -> Vector3<f64> {
    let mut sum = Vector3::zeros();
    let mut count = 0usize;
    for v in values {
        sum += v.component_mul(&v);
        count += 1;
    }
    if count == 0 {
        return sum;
    }
    (sum / count as f64).map(f64::sqrt)
}
