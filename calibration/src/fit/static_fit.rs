//! Static calibration: the mechanical arm of section 3.1 of the paper.
//!
//! Each orientation gives the local gravity vector in the sensor frame (the reference) and the
//! sensor's mean output there. All twelve parameters come from one linear least-squares fit
//! (see the parent module); at least four orientations that do not lie in one plane are needed.
//! The result carries the residuals, the parameter covariance and the paper's ±g check: the
//! largest deviation of the corrected output from the reference, both in-sample and, when there
//! are orientations to spare, leaving each orientation out of its own fit (a fairer figure, since
//! in-sample residuals shrink as the fit absorbs them).

use nalgebra::Vector3;

use super::linear::fit_affine;
use super::{rms, Calibration, FitError};

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
    /// Residual degrees of freedom (orientations − 4); with none, the covariance is zero.
    pub dof: usize,
    /// Observations the caller should read, e.g. a covariance that could not be estimated.
    pub warnings: Vec<String>,
}

/// Fits S and q to the orientations.
pub fn fit_static(observations: &[StaticObservation]) -> Result<StaticFit, FitError> {
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
    let calibration = fit.calibration;
    let residuals_mps2: Vec<_> = observations
        .iter()
        .map(|o| calibration.correct(&o.output) - o.reference_mps2)
        .collect();
    let (max_deviation_orientation, max_deviation_mps2) = largest(&residuals_mps2);
    let mut warnings = Vec::new();
    if fit.dof == 0 {
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
        warnings,
    })
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
