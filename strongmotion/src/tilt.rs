//! Residual tilt: the change of a sensor's inclination from before an event to after it, from
//! the mean corrected acceleration over a quiet stretch on either side.
//!
//! The angles follow the lab's convention (PROTOCOL.md §3.5): `roll = atan2(a_y, a_z)`,
//! `pitch = atan2(a_x, √(a_y² + a_z²))`. Each stretch is cut into blocks; the mean vector's
//! covariance is the block means' scatter over the number of blocks (ν = blocks − 1), which
//! counts the noise and whatever vibration is left (a coda, ambient motion) as they are, slow
//! or not; it goes through the angles' gradient. The calibration's offsets and cross-axis terms
//! are the same on both sides under one record and cancel in the difference (a gain error
//! scales the change by its own small fraction); when the record changed between the two
//! stretches, each side's stated per-sample uncertainty is added whole, as a systematic error.

use nalgebra::{Matrix3, RowVector3, Vector3};

use crate::estimate::{Budget, Estimate};

/// Blocks each stretch is cut into.
pub const TILT_BLOCKS: usize = 10;

/// Inclination before and after, and the change with its uncertainty, degrees.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ResidualTilt {
    pub roll_before_deg: f64,
    pub pitch_before_deg: f64,
    pub roll_after_deg: f64,
    pub pitch_after_deg: f64,
    pub roll_change_deg: Estimate,
    pub pitch_change_deg: Estimate,
    /// The larger of the two changes by magnitude, with its uncertainty (what a limit judges).
    pub change_deg: Estimate,
}

struct Stretch {
    mean: Vector3<f64>,
    covariance: Matrix3<f64>,
}

fn stretch(samples: &[[f64; 3]]) -> Option<Stretch> {
    let n = samples.len() / TILT_BLOCKS;
    if n == 0 {
        return None;
    }
    let means: Vec<Vector3<f64>> = (0..TILT_BLOCKS)
        .map(|b| {
            samples[b * n..(b + 1) * n]
                .iter()
                .fold(Vector3::zeros(), |m, a| m + Vector3::from(*a))
                / n as f64
        })
        .collect();
    let mean = means.iter().sum::<Vector3<f64>>() / TILT_BLOCKS as f64;
    let scatter = means
        .iter()
        .map(|m| (m - mean) * (m - mean).transpose())
        .sum::<Matrix3<f64>>()
        / (TILT_BLOCKS - 1) as f64;
    Some(Stretch {
        mean,
        covariance: scatter / TILT_BLOCKS as f64,
    })
}

/// Roll and pitch (rad) and their gradients with respect to the acceleration.
fn angles(a: &Vector3<f64>) -> ((f64, RowVector3<f64>), (f64, RowVector3<f64>)) {
    let (x, y, z) = (a[0], a[1], a[2]);
    let r2 = y * y + z * z;
    let r = r2.sqrt();
    let rho2 = x * x + r2;
    let roll = (y.atan2(z), RowVector3::new(0.0, z / r2, -y / r2));
    let pitch = (
        x.atan2(r),
        RowVector3::new(r / rho2, -x * y / (r * rho2), -x * z / (r * rho2)),
    );
    (roll, pitch)
}

/// The residual tilt from the valid samples before and after (sensor axes, m/s²);
/// `systematic_u` is each side's mean stated standard uncertainty per axis when the two were
/// corrected with different records, none when with the same.
pub fn residual_tilt(
    before: &[[f64; 3]],
    after: &[[f64; 3]],
    systematic_u: Option<([f64; 3], [f64; 3])>,
    probability: f64,
) -> Option<ResidualTilt> {
    let (b, a) = (stretch(before)?, stretch(after)?);
    let ((rb, grb), (pb, gpb)) = angles(&b.mean);
    let ((ra, gra), (pa, gpa)) = angles(&a.mean);
    let nu = (TILT_BLOCKS - 1) as f64;
    let deg = 180.0 / std::f64::consts::PI;
    let change = |g_before: &RowVector3<f64>, g_after: &RowVector3<f64>, value: f64| {
        let mut budget = Budget::new();
        budget
            .add((g_before * b.covariance * g_before.transpose())[(0, 0)], nu)
            .add((g_after * a.covariance * g_after.transpose())[(0, 0)], nu);
        if let Some((ub, ua)) = systematic_u {
            let sb = Matrix3::from_diagonal(&Vector3::from(ub.map(|v| v * v)));
            let sa = Matrix3::from_diagonal(&Vector3::from(ua.map(|v| v * v)));
            budget
                .add(
                    (g_before * sb * g_before.transpose())[(0, 0)],
                    f64::INFINITY,
                )
                .add((g_after * sa * g_after.transpose())[(0, 0)], f64::INFINITY);
        }
        budget.estimate(value, probability).scaled(deg)
    };
    let roll_change_deg = change(&grb, &gra, ra - rb);
    let pitch_change_deg = change(&gpb, &gpa, pa - pb);
    let larger = |e: &Estimate| Estimate {
        value: e.value.abs(),
        ..*e
    };
    let change_deg = if roll_change_deg.value.abs() >= pitch_change_deg.value.abs() {
        larger(&roll_change_deg)
    } else {
        larger(&pitch_change_deg)
    };
    Some(ResidualTilt {
        roll_before_deg: rb * deg,
        pitch_before_deg: pb * deg,
        roll_after_deg: ra * deg,
        pitch_after_deg: pa * deg,
        roll_change_deg,
        pitch_change_deg,
        change_deg,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::Rng;

    /// Gravity at roll `r` and pitch `p` (rad): a = g·(sin p, sin r·cos p, cos r·cos p).
    fn gravity(r: f64, p: f64) -> [f64; 3] {
        let g = 9.81;
        [g * p.sin(), g * r.sin() * p.cos(), g * r.cos() * p.cos()]
    }

    #[test]
    fn a_known_tilt_is_found_within_its_interval() {
        let (r0, p0) = (0.01, -0.02);
        let (dr, dp) = (0.002, 0.0005); // 0.115° and 0.029°
        let mut rng = Rng::new(9);
        let mut inside = 0;
        let runs = 400;
        for _ in 0..runs {
            // Noise and a slow sway that does not average away within a block.
            let phase = rng.range(0.0, std::f64::consts::TAU);
            let sample = |i: usize, r: f64, p: f64, rng: &mut Rng| {
                let g = gravity(r, p);
                let sway = 0.003 * (i as f64 * 0.005 + phase).sin();
                [
                    g[0] + sway + 0.002 * rng.normal(),
                    g[1] + 0.002 * rng.normal(),
                    g[2] + 0.002 * rng.normal(),
                ]
            };
            let before: Vec<_> = (0..2000).map(|i| sample(i, r0, p0, &mut rng)).collect();
            let after: Vec<_> = (0..2000)
                .map(|i| sample(i, r0 + dr, p0 + dp, &mut rng))
                .collect();
            let t = residual_tilt(&before, &after, None, 0.95).unwrap();
            inside += usize::from(t.roll_change_deg.covers(dr.to_degrees()));
            assert!((t.roll_before_deg - r0.to_degrees()).abs() < 0.01);
            assert!((t.pitch_after_deg - (p0 + dp).to_degrees()).abs() < 0.01);
            assert!(
                t.roll_change_deg.coverage_factor > 2.0,
                "ν = 18 at most: t > 2.0"
            );
        }
        let share = inside as f64 / runs as f64;
        assert!((0.92..=0.98).contains(&share), "{share}");
    }
}
