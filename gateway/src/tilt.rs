//! Inclination from the low band of the static-corrected output, with propagated uncertainty.
//!
//! The raw outputs go through a second-order Butterworth low pass (`tilt_cutoff_hz`, 0.1 Hz by
//! default, which takes building sway at 1–5 Hz down at least a hundredfold); since the
//! correction is affine, correcting the low-passed output equals low-passing the corrected one.
//! From `a = S_s⁻¹·V_lp + q_s`:
//!
//! ```text
//! roll  = atan2(a_y, a_z)
//! pitch = atan2(a_x, √(a_y² + a_z²))
//! ```
//!
//! the lab's convention (README, static input): pitch is the elevation of the x axis above the
//! horizontal, roll the rotation about it that raises y, so a = g·(sin pitch, sin roll·cos pitch,
//! cos roll·cos pitch). Where an angle is undefined (roll with the x axis vertical) its
//! uncertainty is reported as [`UNDEFINED_UNCERTAINTY_DEG`].
//!
//! and the standard uncertainties are `√(J·Σ_a·Jᵀ)` with `Σ_a` the full 3×3 covariance of `a`
//! from the static set ([`SetCorrector::covariance`], parameters, noise and stated part) and
//! `J` the gradient of each angle. The noise term is the per-sample noise, which the low pass
//! reduces: the stated uncertainty is conservative on that account.

use triax_calibration::corrector::SetCorrector;

/// Angles and their standard uncertainties, degrees.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Tilt {
    pub roll_deg: f64,
    pub pitch_deg: f64,
    pub roll_uncertainty_deg: f64,
    pub pitch_uncertainty_deg: f64,
}

/// Uncertainty reported for an angle that is undefined at the sample: the widest an angle can
/// be wrong. (JSON has no infinity.)
pub const UNDEFINED_UNCERTAINTY_DEG: f64 = 180.0;

/// Standard uncertainty in degrees of an angle with gradient `j` (per m/s²).
fn angle_uncertainty_deg(j: [f64; 3], c: &[[f64; 3]; 3]) -> f64 {
    let mut v = 0.0;
    for k in 0..3 {
        for l in 0..3 {
            v += j[k] * c[k][l] * j[l];
        }
    }
    if v.is_finite() {
        // Round-off can take a zero variance a hair below zero.
        v.max(0.0)
            .sqrt()
            .to_degrees()
            .min(UNDEFINED_UNCERTAINTY_DEG)
    } else {
        UNDEFINED_UNCERTAINTY_DEG
    }
}

/// Tilt of the static-corrected, low-passed output `output_lp`.
pub fn tilt(static_set: &SetCorrector, output_lp: [f64; 3]) -> Tilt {
    let a = static_set.accel(output_lp);
    let cov = static_set.covariance(output_lp);
    let [ax, ay, az] = a;
    let r2 = ay * ay + az * az;
    let r = r2.sqrt();
    let n2 = ax * ax + r2;
    let roll = ay.atan2(az);
    let pitch = ax.atan2(r);
    // At r = 0 (x axis vertical) roll is undefined: the gradients are not finite.
    let j_roll = [0.0, az / r2, -ay / r2];
    let j_pitch = [r / n2, -ax * ay / (r * n2), -ax * az / (r * n2)];
    Tilt {
        roll_deg: roll.to_degrees(),
        pitch_deg: pitch.to_degrees(),
        roll_uncertainty_deg: angle_uncertainty_deg(j_roll, &cov),
        pitch_uncertainty_deg: angle_uncertainty_deg(j_pitch, &cov),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use triax_calibration::corrector::Corrector;
    use triax_protocol::record::{sample, SetKind};

    #[test]
    fn angles_and_uncertainty_agree_with_finite_differences() {
        let mut r = sample::record("t", 1);
        r.static_set.sensitivity = [[0.1, 0.0, 0.0], [0.0, 0.1, 0.0], [0.0, 0.0, 0.1]];
        r.static_set.offset = [0.0; 3];
        let c = Corrector::from_record(&r).unwrap();
        let set = c.set(SetKind::Static);
        let g: f64 = 9.81;
        let (roll, pitch) = (5f64.to_radians(), -3f64.to_radians());
        let a = [
            g * pitch.sin(),
            g * pitch.cos() * roll.sin(),
            g * pitch.cos() * roll.cos(),
        ];
        let v = a.map(|x| x * 0.1);
        let t = tilt(set, v);
        assert!((t.roll_deg - 5.0).abs() < 1e-9, "{t:?}");
        assert!((t.pitch_deg + 3.0).abs() < 1e-9, "{t:?}");
        // Axis-independent noise u per axis: u_roll ≈ u / (g cos pitch) rad.
        let u = set.correct(v).uncertainty_mps2;
        let expect = (u[1].max(u[2]) / (g * pitch.cos())).to_degrees();
        assert!(t.roll_uncertainty_deg > 0.5 * expect && t.roll_uncertainty_deg < 2.0 * expect);
        assert!(t.pitch_uncertainty_deg > 0.0);
        // Finite differences of the pitch against the gradient's direction: raising x raises
        // pitch.
        let up = tilt(set, [v[0] + 1e-4, v[1], v[2]]);
        assert!(up.pitch_deg > t.pitch_deg);
    }

    #[test]
    fn an_undefined_roll_has_the_widest_uncertainty() {
        let mut r = sample::record("t", 1);
        r.static_set.sensitivity = [[0.1, 0.0, 0.0], [0.0, 0.1, 0.0], [0.0, 0.0, 0.1]];
        r.static_set.offset = [0.0; 3];
        let c = Corrector::from_record(&r).unwrap();
        // x straight up: a = (g, 0, 0).
        let t = tilt(c.set(SetKind::Static), [0.981, 0.0, 0.0]);
        assert!((t.pitch_deg - 90.0).abs() < 1e-9, "{t:?}");
        assert_eq!(t.roll_uncertainty_deg, UNDEFINED_UNCERTAINTY_DEG);
    }
}
