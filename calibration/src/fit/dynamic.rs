//! Dynamic calibration on the rotary table (section 3.2 of the paper).
//!
//! Geometry: the table turns about a vertical axis; at the sensor, e_t is the tangential unit
//! vector (direction of increasing θ), e_up points up, e_in points radially toward the axis.
//! The specific force is f = r·θ̈·e_t + g·e_up + r·θ̇²·e_in. With mount angle α the sensor axes
//! are x = cos α·e_t + sin α·e_up, y = sin α·e_t − cos α·e_up, z = e_in, so
//!
//! ```text
//! f_x = r·θ̈·cos α + g·sin α
//! f_y = r·θ̈·sin α − g·cos α
//! f_z = r·θ̇²
//! ```
//!
//! From each recording, `n` points per cycle of the motion are taken (equally spaced in time,
//! cycles counted from the first sample where the reference is valid); the pairs (f, V) of all
//! recordings are stacked into one least-squares fit. One mount angle alone cannot identify
//! the twelve parameters, since then `f_x·sin α − f_y·cos α = g` for every sample; this and
//! any other rank deficiency is reported in terms of the recordings.

use std::ops::Range;

use nalgebra::{Matrix3, Vector3};

use super::linear::{fit_affine, AffineFailure};
use super::reference::{check_time_axis, kinematics, Kinematics, MotionLaw, ReferenceMethod};
use super::{rms, Calibration, FitError};

/// The bench description (the TOML bench file without the recordings).
#[derive(Debug, Clone, PartialEq)]
pub struct Bench {
    pub radius_m: f64,
    /// Standard uncertainty of `radius_m`.
    pub radius_uncertainty_m: f64,
    pub gravity_mps2: f64,
    pub points_per_cycle: usize,
    pub reference: ReferenceMethod,
    pub motion: MotionLaw,
}

/// One recording at one mount angle.
#[derive(Debug, Clone, PartialEq)]
pub struct Recording {
    /// Used in messages (the lab passes the file name).
    pub name: String,
    pub alpha_deg: f64,
    pub t_s: Vec<f64>,
    pub theta_rad: Vec<f64>,
    pub output: Vec<Vector3<f64>>,
}

/// The specific force at the sensor, in the sensor frame, m/s² (see the module doc).
pub fn specific_force(
    alpha_rad: f64,
    radius_m: f64,
    gravity_mps2: f64,
    theta_dot_radps: f64,
    theta_ddot_radps2: f64,
) -> Vector3<f64> {
    let (s, c) = alpha_rad.sin_cos();
    let tangential = radius_m * theta_ddot_radps2;
    Vector3::new(
        tangential * c + gravity_mps2 * s,
        tangential * s - gravity_mps2 * c,
        radius_m * theta_dot_radps * theta_dot_radps,
    )
}

/// The part of [`specific_force`] due to the motion alone (no gravity).
pub fn motion_part(
    alpha_rad: f64,
    radius_m: f64,
    theta_dot_radps: f64,
    theta_ddot_radps2: f64,
) -> Vector3<f64> {
    specific_force(alpha_rad, radius_m, 0.0, theta_dot_radps, theta_ddot_radps2)
}

/// One recording with its reference computed.
#[derive(Debug, Clone, PartialEq)]
pub struct Prepared {
    pub kinematics: Kinematics,
    /// Reference specific force per sample; meaningful inside `kinematics.valid` only.
    pub reference_mps2: Vec<Vector3<f64>>,
    /// Sample ranges of the whole cycles inside the valid range.
    pub cycles: Vec<Range<usize>>,
}

impl Prepared {
    pub fn valid(&self) -> Range<usize> {
        self.kinematics.valid.clone()
    }
}

/// Checks a bench description for values that make no physical sense.
pub fn check_bench(bench: &Bench) -> Result<(), FitError> {
    let positive = |name: &str, v: f64| {
        if v.is_finite() && v > 0.0 {
            Ok(())
        } else {
            Err(FitError::Bench(format!(
                "{name} must be a positive number, got {v}"
            )))
        }
    };
    positive("radius_m", bench.radius_m)?;
    positive("gravity_mps2", bench.gravity_mps2)?;
    positive("motion.frequency_hz", bench.motion.frequency_hz)?;
    positive("motion.amplitude_rad", bench.motion.amplitude_rad)?;
    if !(bench.radius_uncertainty_m.is_finite() && bench.radius_uncertainty_m >= 0.0) {
        return Err(FitError::Bench(format!(
            "radius_uncertainty_m must be zero or positive, got {}",
            bench.radius_uncertainty_m
        )));
    }
    if bench.points_per_cycle < 1 {
        return Err(FitError::Bench(
            "points_per_cycle must be at least 1".into(),
        ));
    }
    Ok(())
}

/// Validates one recording and computes its reference by `method`.
pub fn prepare(
    bench: &Bench,
    method: ReferenceMethod,
    recording: &Recording,
) -> Result<Prepared, FitError> {
    let name = recording.name.as_str();
    let bad = |sample: usize, problem: String| FitError::Recording {
        recording: name.to_string(),
        sample,
        problem,
    };
    let n = recording.t_s.len();
    if recording.theta_rad.len() != n || recording.output.len() != n {
        return Err(bad(
            0,
            format!(
                "column lengths differ: {} times, {} angles, {} outputs",
                n,
                recording.theta_rad.len(),
                recording.output.len()
            ),
        ));
    }
    if !recording.alpha_deg.is_finite() {
        return Err(FitError::Bench(format!(
            "alpha_deg of recording {name} is not a finite number"
        )));
    }
    if let Some(i) = recording.theta_rad.iter().position(|x| !x.is_finite()) {
        return Err(bad(i, "theta_rad is not a finite number".into()));
    }
    if let Some(i) = recording
        .output
        .iter()
        .position(|v| !v.iter().all(|x| x.is_finite()))
    {
        return Err(bad(i, "an output is not a finite number".into()));
    }
    check_time_axis(name, &recording.t_s, true)?;
    let kin = kinematics(
        method,
        name,
        &recording.t_s,
        &recording.theta_rad,
        &bench.motion,
    )?;
    let alpha = recording.alpha_deg.to_radians();
    let reference_mps2: Vec<_> = kin
        .theta_dot_radps
        .iter()
        .zip(&kin.theta_ddot_radps2)
        .map(|(&w, &dw)| specific_force(alpha, bench.radius_m, bench.gravity_mps2, w, dw))
        .collect();
    let valid = kin.valid.clone();
    let t = &recording.t_s;
    let period = bench.motion.period_s();
    let mut cycles = Vec::new();
    if !valid.is_empty() {
        let t0 = t[valid.start];
        let t_last = t[valid.end - 1];
        let dt = (t[n - 1] - t[0]) / (n - 1).max(1) as f64;
        let mut k = 0usize;
        loop {
            let begin = t0 + k as f64 * period;
            let end = begin + period;
            // A cycle is whole when its last sample (one interval before `end`) is valid.
            if end - 0.5 * dt > t_last {
                break;
            }
            let lo = valid.start + t[valid.clone()].partition_point(|&x| x < begin);
            let hi = valid.start + t[valid.clone()].partition_point(|&x| x < end);
            cycles.push(lo..hi);
            k += 1;
        }
    }
    if cycles.len() < 2 {
        let duration = if n > 1 { t[n - 1] - t[0] } else { 0.0 };
        return Err(bad(
            n.saturating_sub(1),
            format!(
                "too few points: {n} samples ({duration:.3} s) hold {} whole cycle(s) of the \
                 {} Hz motion with a valid {} reference; at least 2 are needed",
                cycles.len(),
                bench.motion.frequency_hz,
                method.name()
            ),
        ));
    }
    let shortest = cycles.iter().map(|c| c.len()).min().unwrap_or(0);
    if bench.points_per_cycle > shortest {
        return Err(bad(
            0,
            format!(
                "points_per_cycle = {} exceeds the {} samples of a cycle",
                bench.points_per_cycle, shortest
            ),
        ));
    }
    Ok(Prepared {
        kinematics: kin,
        reference_mps2,
        cycles,
    })
}

/// Indices of the `n` calibration points of one cycle: the first sample at or after each of
/// `n` equally spaced instants.
pub fn cycle_points(t_s: &[f64], cycle: &Range<usize>, n: usize, period_s: f64) -> Vec<usize> {
    let begin = t_s[cycle.start];
    let slice = &t_s[cycle.clone()];
    (0..n)
        .map(|j| {
            let target = begin + j as f64 * period_s / n as f64;
            (cycle.start + slice.partition_point(|&x| x < target)).min(cycle.end - 1)
        })
        .collect()
}

/// A dynamic fit with its diagnostics.
#[derive(Debug, Clone)]
pub struct DynamicFit {
    pub calibration: Calibration,
    pub method: ReferenceMethod,
    pub points_per_cycle: usize,
    /// Rows of the least-squares problem.
    pub n_points: usize,
    /// Whole cycles used per recording.
    pub cycles: Vec<usize>,
    /// RMS of (corrected − reference) over all valid samples of all recordings (Table 1).
    pub residual_rms_mps2: Vector3<f64>,
    /// Mean of (corrected − reference) at each recording's calibration points.
    pub recording_bias_mps2: Vec<Vector3<f64>>,
    /// Systematic error that more data would not remove: the RMS of the residual pattern
    /// over (recording, point of the cycle), averaged over cycles, with the share of the
    /// cycle-to-cycle scatter removed (see `fit_with`).
    pub lack_of_fit_mps2: Vector3<f64>,
    /// Standard deviation of the sensor's output noise per channel, output units, estimated
    /// from second differences of the raw outputs.
    pub output_noise: Vector3<f64>,
    /// Degrees of freedom of `output_noise` ([`output_noise_dof`]).
    pub output_noise_dof: f64,
    /// Degrees of freedom of `lack_of_fit_mps2`: the residual cells less the 4 parameters
    /// per axis fitted to them.
    pub lack_of_fit_dof: f64,
    /// The same noise in m/s² (diagonal of S⁻¹·Σ·S⁻ᵀ, square-rooted).
    pub output_noise_mps2: Vector3<f64>,
    /// Residual covariance of the outputs at the calibration points, output units².
    pub residual_cov: Matrix3<f64>,
    /// The recordings with their reference, for the uncertainty evaluation and the tables.
    pub prepared: Vec<Prepared>,
}

/// Fits with the bench's reference method and points per cycle.
pub fn fit_dynamic(bench: &Bench, recordings: &[Recording]) -> Result<DynamicFit, FitError> {
    fit_with(bench, recordings, bench.reference, bench.points_per_cycle)
}

/// Fits with a given reference method and number of points per cycle.
///
/// Lack of fit: with `e_rkj` the residual (corrected − reference, m/s²) at point j of cycle k
/// of recording r, `b_rj` its mean over the K_r cycles and `s²` the pooled variance across
/// cycles, `u² = Σ_rj (b_rj² − s²/K_r) / (cells − 4)` per axis, taken as zero unless the
/// excess is significant (twice its own scatter). Noise of
/// the sensor and of the reference averages out over cycles; what stays is what a single
/// (S, q) cannot represent, such as a sensor whose response to the constant part of the input
/// (gravity, different at each α) differs from its response to the varying part, as eq. (9)
/// vs (11) of the paper suggests.
pub fn fit_with(
    bench: &Bench,
    recordings: &[Recording],
    method: ReferenceMethod,
    points_per_cycle: usize,
) -> Result<DynamicFit, FitError> {
    check_bench(bench)?;
    if recordings.is_empty() {
        return Err(FitError::RankDeficient {
            explanation: "no recordings given; at least two mount angles are needed".into(),
        });
    }
    let bench = Bench {
        points_per_cycle,
        reference: method,
        ..bench.clone()
    };
    let prepared = recordings
        .iter()
        .map(|r| prepare(&bench, method, r))
        .collect::<Result<Vec<_>, _>>()?;
    let mut refs = Vec::new();
    let mut outs = Vec::new();
    let mut spans = Vec::with_capacity(recordings.len());
    for (rec, prep) in recordings.iter().zip(&prepared) {
        let start = refs.len();
        for cycle in &prep.cycles {
            for i in cycle_points(&rec.t_s, cycle, points_per_cycle, bench.motion.period_s()) {
                refs.push(prep.reference_mps2[i]);
                outs.push(rec.output[i]);
            }
        }
        spans.push(start..refs.len());
    }
    let fit = fit_affine(&refs, &outs, None).map_err(|f| explain(f, recordings, refs.len()))?;
    let calibration = fit.calibration;

    let errors: Vec<Vector3<f64>> = refs
        .iter()
        .zip(&outs)
        .map(|(a, v)| calibration.correct(v) - a)
        .collect();
    // Systematic error pattern: the residual at point j of the cycle of recording r, averaged
    // over the cycles, minus what the cycle-to-cycle scatter alone would leave in that mean.
    let mut pattern_sq = Vector3::zeros();
    let mut within_ss = Vector3::zeros();
    let mut within_dof = 0usize;
    let mut noise_in_means = Vector3::zeros();
    let mut cells = 0usize;
    let mut recording_bias_mps2 = Vec::with_capacity(spans.len());
    for (span, prep) in spans.iter().zip(&prepared) {
        let k = prep.cycles.len();
        let rows = &errors[span.clone()];
        recording_bias_mps2
            .push(rows.iter().fold(Vector3::zeros(), |acc, e| acc + e) / rows.len().max(1) as f64);
        for j in 0..points_per_cycle {
            let cell: Vec<Vector3<f64>> = (0..k).map(|c| rows[c * points_per_cycle + j]).collect();
            let mean = cell.iter().fold(Vector3::zeros(), |acc, e| acc + e) / k as f64;
            for e in &cell {
                within_ss += (e - mean).component_mul(&(e - mean));
            }
            within_dof += k - 1;
            pattern_sq += mean.component_mul(&mean);
            noise_in_means += Vector3::repeat(1.0 / k as f64);
            cells += 1;
        }
    }
    let within_var = within_ss / within_dof.max(1) as f64;
    let expected = within_var.component_mul(&noise_in_means);
    // The sum of `cells` squared means scatters by about √(2/cells) of its expectation; an
    // excess below twice that is noise (a noisy reference such as finite differences would
    // otherwise report a spurious systematic error).
    let significant = 2.0 * (2.0 / cells.max(1) as f64).sqrt();
    // Four parameters per axis were fitted to these cells, which shrinks their spread.
    let lack_of_fit_mps2 = Vector3::from_fn(|axis, _| {
        let excess = pattern_sq[axis] - expected[axis];
        if excess > significant * expected[axis] {
            (excess / cells.saturating_sub(4).max(1) as f64).sqrt()
        } else {
            0.0
        }
    });

    let residual_rms_mps2 = rms(recordings.iter().zip(&prepared).flat_map(|(rec, prep)| {
        prep.valid()
            .map(|i| calibration.correct(&rec.output[i]) - prep.reference_mps2[i])
    }));

    let output_noise = output_noise(recordings);
    let s_inv = calibration.sensitivity_inv();
    let noise_cov_mps2 =
        s_inv * Matrix3::from_diagonal(&output_noise.map(|x| x * x)) * s_inv.transpose();
    let output_noise_mps2 = noise_cov_mps2.diagonal().map(|x| x.max(0.0).sqrt());

    Ok(DynamicFit {
        calibration,
        method,
        points_per_cycle,
        n_points: refs.len(),
        cycles: prepared.iter().map(|p| p.cycles.len()).collect(),
        residual_rms_mps2,
        recording_bias_mps2,
        lack_of_fit_mps2,
        output_noise,
        output_noise_dof: output_noise_dof(recordings),
        lack_of_fit_dof: cells.saturating_sub(4).max(1) as f64,
        output_noise_mps2,
        residual_cov: fit.residual_cov,
        prepared,
    })
}

/// White-noise standard deviation of each output channel, from second differences: for white
/// noise of variance σ², V[i+1] − 2V[i] + V[i−1] has variance 6σ², while a motion at a few hertz
/// sampled at hundreds of hertz contributes almost nothing.
pub fn output_noise(recordings: &[Recording]) -> Vector3<f64> {
    let mut sum = Vector3::zeros();
    let mut count = 0usize;
    for rec in recordings {
        for w in rec.output.windows(3) {
            let d = w[2] - 2.0 * w[1] + w[0];
            sum += d.component_mul(&d);
            count += 1;
        }
    }
    if count == 0 {
        return Vector3::zeros();
    }
    (sum / (6.0 * count as f64)).map(f64::sqrt)
}

/// Degrees of freedom of [`output_noise`]: `72/140` of the number of second differences. The
/// differences overlap, so neighbours are correlated (autocovariances 6σ², −4σ², σ²), and
/// their mean square has the variance of a χ² with `2·36n/140` degrees of freedom.
pub fn output_noise_dof(recordings: &[Recording]) -> f64 {
    let count: usize = recordings
        .iter()
        .map(|r| r.output.len().saturating_sub(2))
        .sum();
    (72.0 / 140.0 * count as f64).max(1.0)
}

/// Turns a failed design into a message about the recordings.
fn explain(failure: AffineFailure, recordings: &[Recording], rows: usize) -> FitError {
    match failure {
        AffineFailure::TooFew(found) => FitError::RankDeficient {
            explanation: format!(
                "only {found} calibration point(s) in all recordings ({rows} rows); raise \
                 points_per_cycle or record more cycles"
            ),
        },
        AffineFailure::Singular => FitError::SingularSensitivity,
        AffineFailure::Degenerate { normal, level } => {
            let mut angles: Vec<f64> = recordings
                .iter()
                .map(|r| r.alpha_deg.rem_euclid(360.0))
                .collect();
            angles.sort_by(f64::total_cmp);
            angles.dedup_by(|a, b| (*a - *b).abs() < 1e-6);
            let names: Vec<&str> = recordings.iter().map(|r| r.name.as_str()).collect();
            let explanation = if angles.len() == 1 {
                let alpha = recordings[0].alpha_deg;
                format!(
                    "all recordings ({}) were made at alpha_deg = {alpha}; with a single mount \
                     angle f_x and f_y are affine in each other (f_x·sin α − f_y·cos α = g), so \
                     the x and y columns of S cannot be told apart. Missing: a recording at \
                     another alpha_deg, best {} or {}",
                    names.join(", "),
                    alpha + 90.0,
                    alpha - 90.0
                )
            } else {
                format!(
                    "the reference specific forces of all recordings ({}) lie in the plane \
                     {:.3}·f_x + {:.3}·f_y + {:.3}·f_z = {:.3} m/s²; check that the table moved \
                     in every recording and that the alpha_deg values are right",
                    names.join(", "),
                    normal.x,
                    normal.y,
                    normal.z,
                    level
                )
            };
            FitError::RankDeficient { explanation }
        }
    }
}
