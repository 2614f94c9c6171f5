//! Static calibration: the mechanical arm of section 3.1 of the paper.
//!
//! Each orientation gives the local gravity vector in the sensor frame (the reference) and the
//! sensor's mean output there. All twelve parameters come from one linear least-squares fit
//! (see the parent module); at least four orientations that do not lie in one plane are needed.
//! The result carries the residuals, the parameter covariance and the paper's ±g check: the
//! largest deviation of the corrected output from the reference, both in-sample and, when there
//! are orientations to spare, leaving each orientation out of its own fit (a fairer figure, since
//! in-sample residuals shrink as the fit absorbs them).
//!
//! # Degrees of freedom
//!
//! The covariance comes from the residuals, estimated with N − 4 degrees of freedom: 6 for the
//! usual ten orientations, where Student's t asks for k = 2.45 rather than 1.96. An operator
//! who knows how well the arm sets its angles can say so ([`ArmAngleUncertainty`], a Type B
//! statement with degrees of freedom of its own). The arm's angle errors tilt the true gravity
//! vector away from the nominal one, which is what drives the residuals, so the statement
//! predicts each orientation's output error covariance `Σ_B,j = S·Σ_a,j·Sᵀ`, with `Σ_a,j` the
//! covariance of orientation j's reference under independent roll and pitch errors. The two
//! estimates are pooled, weighted by their degrees of freedom, `ν = ν_A + ν_B`:
//! `Cov = (ν_A·Σ_A ⊗ G + ν_B·Σ_j Σ_B,j ⊗ G·x_j·x_jᵀ·G) / ν` with `G = (XᵀX)⁻¹`. The second
//! term is the exact covariance of least squares under the arm's errors, which differ by
//! orientation (none along gravity, all across it); the residuals' single `Σ_A` averages them,
//! and understates the error near the orientations that the arm perturbs most, such as level.
//! The noise of the orientation means is left to the residual part: averaged over a thousand
//! samples it is far below what a tenth of a degree of arm error does.

use nalgebra::{Matrix3, Vector3, Vector4};

use super::linear::{fit_affine, parameter_covariance_of};
use super::{rms, Calibration, FitError};

/// What the operator knows of the arm: the standard uncertainty of each of its two angles
/// (roll and pitch, independent), with the degrees of freedom of that statement (JCGM 100
/// G.4.2: ν ≈ ½·(u/Δu)², so a value known to ±10 % has ν = 50).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ArmAngleUncertainty {
    pub angle_deg: f64,
    pub dof: f64,
}

/// One orientation of the arm.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StaticObservation {
    /// Specific force in the sensor frame, m/s² (at rest: +g along the upward direction).
    pub reference_mps2: Vector3<f64>,
    /// Mean sensor output at this orientation, in the sensor's output unit.
    pub output: Vector3<f64>,
}

/// A static fit and its diagnostics.
#[derive(Debug, Clone)]
pub struct StaticFit {
    pub calibration: Calibration,
    /// Corrected output minus reference, one per orientation, m/s².
    pub residuals_mps2: Vec<Vector3<f64>>,
    pub residual_rms_mps2: Vector3<f64>,
    /// The ±g check: largest |corrected − reference| over orientations and axes, m/s².
    pub max_deviation_mps2: f64,
    /// Orientation (0-based) where that deviation occurs.
    pub max_deviation_orientation: usize,
    /// The same check with each orientation predicted by a fit that did not see it; `None`
    /// with fewer than five orientations.
    pub leave_one_out_max_deviation_mps2: Option<f64>,
    /// Residual degrees of freedom (orientations − 4); with none, the covariance is zero
    /// unless the arm's angle uncertainty is stated.
    pub dof: usize,
    /// Degrees of freedom of the covariance: `dof`, plus the arm statement's when stated.
    pub covariance_dof: f64,
    /// Observations the caller should read, e.g. a covariance that could not be estimated.
    pub warnings: Vec<String>,
}

/// Fits S and q to the orientations, with the covariance from the residuals alone.
pub fn fit_static(observations: &[StaticObservation]) -> Result<StaticFit, FitError> {
    fit_static_with(observations, None)
}

/// Fits S and q to the orientations; with `arm`, the covariance pools the residuals with what
/// the arm's angle uncertainty predicts (see the module's documentation).
pub fn fit_static_with(
    observations: &[StaticObservation],
    arm: Option<ArmAngleUncertainty>,
) -> Result<StaticFit, FitError> {
    if let Some(a) = arm {
        if !(a.angle_deg.is_finite() && a.angle_deg > 0.0 && a.dof.is_finite() && a.dof >= 1.0) {
            return Err(FitError::Bench(format!(
                "arm angle uncertainty {}° with {} degrees of freedom: need a positive angle \
                 and at least 1 degree of freedom",
                a.angle_deg, a.dof
            )));
        }
    }
    for (index, obs) in observations.iter().enumerate() {
        if !obs.reference_mps2.iter().all(|x| x.is_finite()) {
            return Err(FitError::NonFinite {
                what: "reference of orientation",
                index,
            });
        }
        if !obs.output.iter().all(|x| x.is_finite()) {
            return Err(FitError::NonFinite {
                what: "output of orientation",
                index,
            });
        }
    }
    let refs: Vec<_> = observations.iter().map(|o| o.reference_mps2).collect();
    let outs: Vec<_> = observations.iter().map(|o| o.output).collect();
    let fit = fit_affine(&refs, &outs, None)?;
    let (calibration, covariance_dof) = match arm {
        None => (fit.calibration.clone(), fit.dof as f64),
        Some(arm) => {
            let nu_a = fit.dof as f64;
            let nu = nu_a + arm.dof;
            let s = fit.calibration.sensitivity();
            let mut terms = vec![(fit.residual_cov * (nu_a / nu), fit.gram_inv)];
            for a in &refs {
                let gx = fit.gram_inv * Vector4::new(a.x, a.y, a.z, 1.0);
                let sigma = s * reference_cov(a, arm) * s.transpose();
                terms.push((sigma * (arm.dof / nu), gx * gx.transpose()));
            }
            let c = &fit.calibration;
            let cov = parameter_covariance_of(&terms, c.sensitivity_inv(), c.offset_mps2());
            let calibration = Calibration::new(*c.sensitivity(), *c.offset_mps2(), cov)?;
            (calibration, nu_a + arm.dof)
        }
    };
    let residuals_mps2: Vec<_> = observations
        .iter()
        .map(|o| calibration.correct(&o.output) - o.reference_mps2)
        .collect();
    let (max_deviation_orientation, max_deviation_mps2) = largest(&residuals_mps2);
    let mut warnings = Vec::new();
    if fit.dof == 0 && arm.is_none() {
        warnings.push(
            "exactly 4 orientations leave no residual degrees of freedom: the parameter \
             covariance cannot be estimated and is reported as zero; measure more orientations"
                .to_string(),
        );
    }
    let leave_one_out_max_deviation_mps2 = if observations.len() >= 5 {
        let mut worst: f64 = 0.0;
        for skip in 0..observations.len() {
            let r: Vec<_> = refs
                .iter()
                .enumerate()
                .filter_map(|(i, a)| (i != skip).then_some(*a))
                .collect();
            let v: Vec<_> = outs
                .iter()
                .enumerate()
                .filter_map(|(i, a)| (i != skip).then_some(*a))
                .collect();
            match fit_affine(&r, &v, None) {
                Ok(sub) => {
                    let dev = sub.calibration.correct(&outs[skip]) - refs[skip];
                    worst = worst.max(dev.amax());
                }
                Err(_) => {
                    // Without this orientation the rest is degenerate: it cannot be predicted.
                    worst = f64::INFINITY;
                }
            }
        }
        Some(worst)
    } else {
        None
    };
    Ok(StaticFit {
        residual_rms_mps2: rms(residuals_mps2.iter().copied()),
        calibration,
        residuals_mps2,
        max_deviation_mps2,
        max_deviation_orientation,
        leave_one_out_max_deviation_mps2,
        dof: fit.dof,
        covariance_dof,
        warnings,
    })
}

/// Covariance of an orientation's reference (m/s²)² under independent errors of the arm's
/// roll and pitch: `u²·(J_r·J_rᵀ + J_p·J_pᵀ)` with `J` the derivatives of
/// [`reference_from_angles`].
fn reference_cov(a: &Vector3<f64>, arm: ArmAngleUncertainty) -> Matrix3<f64> {
    let u_rad = arm.angle_deg.to_radians();
    let g = a.norm();
    let (roll_deg, pitch_deg) = angles_from_reference(a);
    let (sr, cr) = roll_deg.to_radians().sin_cos();
    let (sp, cp) = pitch_deg.to_radians().sin_cos();
    let d_pitch = g * Vector3::new(cp, -sr * sp, -cr * sp);
    let d_roll = g * Vector3::new(0.0, cr * cp, -sr * cp);
    (d_pitch * d_pitch.transpose() + d_roll * d_roll.transpose()) * (u_rad * u_rad)
}

fn largest(values: &[Vector3<f64>]) -> (usize, f64) {
    values
        .iter()
        .enumerate()
        .map(|(i, v)| (i, v.amax()))
        .fold(
            (0, 0.0),
            |best, cur| if cur.1 > best.1 { cur } else { best },
        )
}

/// The reference specific force of a sensor at rest, from its attitude.
///
/// Convention: at roll = pitch = 0 the sensor lies level with its z axis pointing up, so it
/// reads (0, 0, +g). `pitch_deg` is the elevation of the x axis above the horizontal (positive
/// raises x). `roll_deg` is then a right-handed rotation about the (pitched) x axis (positive
/// raises y). Hence `a = g·(sin pitch, sin roll·cos pitch, cos roll·cos pitch)`.
pub fn reference_from_angles(roll_deg: f64, pitch_deg: f64, gravity_mps2: f64) -> Vector3<f64> {
    let (roll, pitch) = (roll_deg.to_radians(), pitch_deg.to_radians());
    gravity_mps2
        * Vector3::new(
            pitch.sin(),
            roll.sin() * pitch.cos(),
            roll.cos() * pitch.cos(),
        )
}

/// The attitude (roll, pitch) in degrees of a gravity direction, the inverse of
/// [`reference_from_angles`] for pitch in [−90°, 90°].
pub fn angles_from_reference(reference_mps2: &Vector3<f64>) -> (f64, f64) {
    let unit = reference_mps2.normalize();
    let pitch = unit.x.clamp(-1.0, 1.0).asin();
    let roll = unit.y.atan2(unit.z);
    (roll.to_degrees(), pitch.to_degrees())
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Matrix3;

    #[test]
    fn angles_round_trip_and_level_reads_plus_g() {
        let g = 9.80665;
        let level = reference_from_angles(0.0, 0.0, g);
        assert!((level - Vector3::new(0.0, 0.0, g)).norm() < 1e-12);
        // x raised by 90°: x points up and reads +g.
        let x_up = reference_from_angles(0.0, 90.0, g);
        assert!((x_up - Vector3::new(g, 0.0, 0.0)).norm() < 1e-12);
        // roll 90°: y points up.
        let y_up = reference_from_angles(90.0, 0.0, g);
        assert!((y_up - Vector3::new(0.0, g, 0.0)).norm() < 1e-12);
        for (roll, pitch) in [(30.0, 20.0), (-120.0, -45.0), (179.0, 10.0)] {
            let (r, p) = angles_from_reference(&reference_from_angles(roll, pitch, g));
            assert!((r - roll).abs() < 1e-9 && (p - pitch).abs() < 1e-9);
        }
    }

    #[test]
    fn three_orientations_are_refused() {
        let obs: Vec<_> = (0..3)
            .map(|i| StaticObservation {
                reference_mps2: Vector3::new(i as f64, 1.0, 2.0),
                output: Vector3::new(1.0, 2.0, 3.0),
            })
            .collect();
        let err = fit_static(&obs).unwrap_err();
        assert_eq!(err, FitError::TooFewOrientations { found: 3 });
        assert!(err.to_string().contains("at least 4"));
    }

    #[test]
    fn four_orientations_fit_exactly_and_warn() {
        let g = 9.80665;
        let s = Matrix3::new(0.099, 0.001, 0.0, -0.002, 0.1, 0.003, 0.0, 0.0, 0.098);
        let q = Vector3::new(-24.3, -24.0, -26.7);
        let refs = [
            reference_from_angles(0.0, 0.0, g),
            reference_from_angles(0.0, 90.0, g),
            reference_from_angles(90.0, 0.0, g),
            reference_from_angles(180.0, 0.0, g),
        ];
        let obs: Vec<_> = refs
            .iter()
            .map(|a| StaticObservation {
                reference_mps2: *a,
                output: s * (a - q),
            })
            .collect();
        let fit = fit_static(&obs).unwrap();
        assert!((fit.calibration.sensitivity() - s).amax() < 1e-10);
        assert!((fit.calibration.offset_mps2() - q).amax() < 1e-8);
        assert_eq!(fit.dof, 0);
        assert_eq!(fit.warnings.len(), 1);
        assert!(fit.leave_one_out_max_deviation_mps2.is_none());
    }

    #[test]
    fn nan_is_refused_with_its_orientation() {
        let mut obs = vec![
            StaticObservation {
                reference_mps2: Vector3::new(0.0, 0.0, 9.8),
                output: Vector3::new(1.0, 1.0, 1.0),
            };
            5
        ];
        obs[3].output.y = f64::NAN;
        let err = fit_static(&obs).unwrap_err();
        assert_eq!(
            err,
            FitError::NonFinite {
                what: "output of orientation",
                index: 3
            }
        );
    }
}
