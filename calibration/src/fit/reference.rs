//! Angular rate and angular acceleration of the rotary table, from the encoder.
//!
//! The dynamic reference needs θ̇ and θ̈ at every sample; the encoder gives θ only, quantised.
//! Four estimators:
//!
//! - `finite-difference`: the paper's "real reference", central differences applied twice.
//!   Quantisation noise is amplified by 1/Δt², which is the noise the paper's Figure 5 shows.
//! - `motion-law`: the paper's "theoretical reference", the commanded sine
//!   `θ = θ₀ + A·sin(2πf·t + φ)` with the commanded `A` and `f`. The recording has no common
//!   time origin with the controller, so `θ₀` and `φ` are taken from a least-squares fit of the
//!   encoder signal at the commanded frequency; the amplitude stays the commanded one.
//! - `savitzky-golay`: a local polynomial (degree 4) fitted over a sliding window of about a
//!   tenth of a cycle each side and differentiated; needs a uniform sample rate.
//! - `harmonic`: for each cycle, θ over that cycle and half a cycle either side is fitted by a
//!   constant, a linear drift and the first five harmonics of the motion frequency, and the fit
//!   is differentiated analytically. Windowing per cycle follows slow changes of amplitude
//!   that a single global fit would average away.
//!
//! Samples near the ends of a recording where a method has no full window are marked invalid
//! (`Kinematics::valid`).

use std::ops::Range;

use nalgebra::{DMatrix, DVector, Matrix3, Vector3};

use super::FitError;

/// Number of harmonics of the motion frequency in the `harmonic` estimator; the bench's
/// motion reversals excite low harmonics, five leave margin without fitting noise.
pub const HARMONICS: usize = 5;

/// Polynomial degree of the Savitzky–Golay estimator. For the second derivative, degrees 4
/// and 5 give the same filter; 4 keeps the bias of a sine over a tenth of a cycle below 10⁻³.
pub const SAVITZKY_GOLAY_DEGREE: usize = 4;

/// Half window of the Savitzky–Golay estimator as a fraction of a cycle.
pub const SAVITZKY_GOLAY_HALF_WINDOW_CYCLES: f64 = 0.1;

/// Largest relative deviation of a sampling interval from the median before the sample rate is
/// called inconsistent.
pub const SAMPLE_RATE_TOLERANCE: f64 = 0.1;

/// How θ̇ and θ̈ are obtained from the encoder.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum ReferenceMethod {
    FiniteDifference,
    MotionLaw,
    SavitzkyGolay,
    Harmonic,
}

impl ReferenceMethod {
    /// All methods, the paper's two first.
    pub const ALL: [ReferenceMethod; 4] = [
        ReferenceMethod::FiniteDifference,
        ReferenceMethod::MotionLaw,
        ReferenceMethod::SavitzkyGolay,
        ReferenceMethod::Harmonic,
    ];

    /// The name used in bench files and on the command line.
    pub fn name(self) -> &'static str {
        match self {
            ReferenceMethod::FiniteDifference => "finite-difference",
            ReferenceMethod::MotionLaw => "motion-law",
            ReferenceMethod::SavitzkyGolay => "savitzky-golay",
            ReferenceMethod::Harmonic => "harmonic",
        }
    }

    /// Parses a name as written by [`ReferenceMethod::name`].
    pub fn from_name(name: &str) -> Option<Self> {
        Self::ALL.into_iter().find(|m| m.name() == name)
    }
}

impl std::fmt::Display for ReferenceMethod {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// The commanded motion: a sine of the table angle.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MotionLaw {
    pub frequency_hz: f64,
    pub amplitude_rad: f64,
}

impl MotionLaw {
    pub fn period_s(&self) -> f64 {
        1.0 / self.frequency_hz
    }

    fn omega(&self) -> f64 {
        2.0 * std::f64::consts::PI * self.frequency_hz
    }
}

/// θ̇ and θ̈ per sample. Entries outside `valid` are zero and must not be used.
#[derive(Debug, Clone, PartialEq)]
pub struct Kinematics {
    pub theta_dot_radps: Vec<f64>,
    pub theta_ddot_radps2: Vec<f64>,
    pub valid: Range<usize>,
}

/// Checks that the time axis is usable: finite, strictly increasing and, when `uniform` is
/// asked for, with every interval within [`SAMPLE_RATE_TOLERANCE`] of the median interval.
/// Errors name the first offending sample.
pub fn check_time_axis(recording: &str, t_s: &[f64], uniform: bool) -> Result<(), FitError> {
    let bad = |sample: usize, problem: String| FitError::Recording {
        recording: recording.to_string(),
        sample,
        problem,
    };
    if let Some(i) = t_s.iter().position(|t| !t.is_finite()) {
        return Err(bad(i, "time is not a finite number".into()));
    }
    for i in 1..t_s.len() {
        if t_s[i] <= t_s[i - 1] {
            return Err(bad(
                i,
                format!(
                    "time does not increase ({} s after {} s)",
                    t_s[i],
                    t_s[i - 1]
                ),
            ));
        }
    }
    if uniform && t_s.len() >= 2 {
        // The median interval is the nominal one: a single glitch cannot shift it, so the
        // message points at the glitch and not at its neighbours.
        let mut intervals: Vec<f64> = t_s.windows(2).map(|w| w[1] - w[0]).collect();
        intervals.sort_by(f64::total_cmp);
        let nominal_dt = intervals[intervals.len() / 2];
        for i in 1..t_s.len() {
            let dt = t_s[i] - t_s[i - 1];
            if ((dt - nominal_dt) / nominal_dt).abs() > SAMPLE_RATE_TOLERANCE {
                return Err(bad(
                    i,
                    format!(
                        "inconsistent sample rate: interval {:.6} s where the recording's usual \
                         interval is {:.6} s",
                        dt, nominal_dt
                    ),
                ));
            }
        }
    }
    Ok(())
}

/// Estimates θ̇ and θ̈ by `method`. `t_s` must be checked with [`check_time_axis`] first
/// (uniform for `savitzky-golay`); too short a recording is an error.
pub fn kinematics(
    method: ReferenceMethod,
    recording: &str,
    t_s: &[f64],
    theta_rad: &[f64],
    motion: &MotionLaw,
) -> Result<Kinematics, FitError> {
    debug_assert_eq!(t_s.len(), theta_rad.len());
    let n = t_s.len();
    let too_short = |needed: usize| FitError::Recording {
        recording: recording.to_string(),
        sample: n.saturating_sub(1),
        problem: format!(
            "too few points: {n} samples, the {} reference needs at least {needed}",
            method.name()
        ),
    };
    match method {
        ReferenceMethod::FiniteDifference => {
            if n < 3 {
                return Err(too_short(3));
            }
            let mut dot = vec![0.0; n];
            let mut ddot = vec![0.0; n];
            for i in 1..n - 1 {
                let h1 = t_s[i] - t_s[i - 1];
                let h2 = t_s[i + 1] - t_s[i];
                let s1 = (theta_rad[i] - theta_rad[i - 1]) / h1;
                let s2 = (theta_rad[i + 1] - theta_rad[i]) / h2;
                // Weighted so that the estimate is exact for a parabola on uneven spacing.
                dot[i] = (s1 * h2 + s2 * h1) / (h1 + h2);
                ddot[i] = 2.0 * (s2 - s1) / (h1 + h2);
            }
            Ok(Kinematics {
                theta_dot_radps: dot,
                theta_ddot_radps2: ddot,
                valid: 1..n - 1,
            })
        }
        ReferenceMethod::MotionLaw => {
            if n < 3 {
                return Err(too_short(3));
            }
            let omega = motion.omega();
            // θ ≈ c₀ + a·sin ωt + b·cos ωt; normal equations are well conditioned over whole
            // cycles and this is only 3×3.
            let mut gram = Matrix3::zeros();
            let mut rhs = Vector3::zeros();
            for (&t, &theta) in t_s.iter().zip(theta_rad) {
                let basis = Vector3::new(1.0, (omega * t).sin(), (omega * t).cos());
                gram += basis * basis.transpose();
                rhs += basis * theta;
            }
            let coef = gram.lu().solve(&rhs).ok_or_else(|| too_short(3))?;
            let phase = coef.z.atan2(coef.y);
            let amp = motion.amplitude_rad;
            let dot = t_s
                .iter()
                .map(|&t| amp * omega * (omega * t + phase).cos())
                .collect();
            let ddot = t_s
                .iter()
                .map(|&t| -amp * omega * omega * (omega * t + phase).sin())
                .collect();
            Ok(Kinematics {
                theta_dot_radps: dot,
                theta_ddot_radps2: ddot,
                valid: 0..n,
            })
        }
        ReferenceMethod::SavitzkyGolay => {
            let dt = if n >= 2 {
                (t_s[n - 1] - t_s[0]) / (n - 1) as f64
            } else {
                return Err(too_short(2 * 4 + 1));
            };
            let samples_per_cycle = motion.period_s() / dt;
            // The float-to-int cast saturates; a window longer than the recording (a motion far
            // slower than the recording is long) is refused before any arithmetic can overflow.
            let half = ((SAVITZKY_GOLAY_HALF_WINDOW_CYCLES * samples_per_cycle).round() as usize)
                .max(SAVITZKY_GOLAY_DEGREE)
                .min(n);
            if n < 2 * half + 1 {
                return Err(too_short(2 * half + 1));
            }
            let (w1, w2) = savitzky_golay_weights(half, SAVITZKY_GOLAY_DEGREE, dt);
            let mut dot = vec![0.0; n];
            let mut ddot = vec![0.0; n];
            for i in half..n - half {
                let window = &theta_rad[i - half..=i + half];
                let mut d1 = 0.0;
                let mut d2 = 0.0;
                for (k, &th) in window.iter().enumerate() {
                    d1 += w1[k] * th;
                    d2 += w2[k] * th;
                }
                dot[i] = d1;
                ddot[i] = d2;
            }
            Ok(Kinematics {
                theta_dot_radps: dot,
                theta_ddot_radps2: ddot,
                valid: half..n - half,
            })
        }
        ReferenceMethod::Harmonic => harmonic(recording, t_s, theta_rad, motion, &too_short),
    }
}

/// Savitzky–Golay weights for the first and second derivative at the window centre.
fn savitzky_golay_weights(half: usize, degree: usize, dt: f64) -> (Vec<f64>, Vec<f64>) {
    let len = 2 * half + 1;
    let cols = degree + 1;
    // Abscissa scaled to [−1, 1] keeps the Vandermonde matrix well conditioned.
    let mut vander = DMatrix::<f64>::zeros(len, cols);
    for k in 0..len {
        let x = (k as f64 - half as f64) / half as f64;
        let mut p = 1.0;
        for j in 0..cols {
            vander[(k, j)] = p;
            p *= x;
        }
    }
    let pinv = (vander.transpose() * &vander)
        .try_inverse()
        .map(|g| g * vander.transpose());
    // The Gram matrix of distinct abscissae with len > degree is positive definite.
    let pinv = pinv.expect("Vandermonde Gram matrix of distinct points is invertible");
    let h = half as f64 * dt;
    let w1 = (0..len).map(|k| pinv[(1, k)] / h).collect();
    let w2 = (0..len).map(|k| 2.0 * pinv[(2, k)] / (h * h)).collect();
    (w1, w2)
}

fn harmonic(
    recording: &str,
    t_s: &[f64],
    theta_rad: &[f64],
    motion: &MotionLaw,
    too_short: &dyn Fn(usize) -> FitError,
) -> Result<Kinematics, FitError> {
    let n = t_s.len();
    let params = 2 + 2 * HARMONICS;
    // Each window needs several samples per parameter; the highest harmonic needs more than
    // two samples per period.
    if n < 4 * params {
        return Err(too_short(4 * params));
    }
    let period = motion.period_s();
    let omega = motion.omega();
    let t0 = t_s[0];
    let duration = t_s[n - 1] - t0;
    let cycles = (duration / period).ceil().max(1.0) as usize;
    let mut dot = vec![0.0; n];
    let mut ddot = vec![0.0; n];
    let mut start = 0usize;
    for cycle in 0..cycles {
        let c_begin = t0 + cycle as f64 * period;
        let c_end = c_begin + period;
        let end = if cycle + 1 == cycles {
            n
        } else {
            start + t_s[start..].partition_point(|&t| t < c_end)
        };
        if start >= end {
            continue;
        }
        let w_lo = t_s.partition_point(|&t| t < c_begin - 0.5 * period);
        let w_hi = t_s.partition_point(|&t| t <= c_end + 0.5 * period);
        let rows = w_hi - w_lo;
        if rows < 2 * params {
            return Err(FitError::Recording {
                recording: recording.to_string(),
                sample: start,
                problem: format!(
                    "too few points: {rows} samples around cycle {cycle}, the harmonic \
                     reference needs {}",
                    2 * params
                ),
            });
        }
        let centre = 0.5 * (c_begin + c_end);
        let half_span = period;
        let mut design = DMatrix::<f64>::zeros(rows, params);
        let mut target = DVector::<f64>::zeros(rows);
        for (row, i) in (w_lo..w_hi).enumerate() {
            let tau = t_s[i] - centre;
            design[(row, 0)] = 1.0;
            design[(row, 1)] = tau / half_span;
            for h in 1..=HARMONICS {
                let arg = h as f64 * omega * tau;
                design[(row, 2 * h)] = arg.cos();
                design[(row, 2 * h + 1)] = arg.sin();
            }
            target[row] = theta_rad[i];
        }
        let qr = design.qr();
        qr.q_tr_mul(&mut target);
        let r = qr.r();
        let coef = r
            .solve_upper_triangular(&target.rows(0, params).into_owned())
            .ok_or_else(|| too_short(4 * params))?;
        for i in start..end {
            let tau = t_s[i] - centre;
            let mut d1 = coef[1] / half_span;
            let mut d2 = 0.0;
            for h in 1..=HARMONICS {
                let w = h as f64 * omega;
                let (s, c) = (w * tau).sin_cos();
                let (a, b) = (coef[2 * h], coef[2 * h + 1]);
                d1 += w * (-a * s + b * c);
                d2 += -w * w * (a * c + b * s);
            }
            dot[i] = d1;
            ddot[i] = d2;
        }
        start = end;
    }
    Ok(Kinematics {
        theta_dot_radps: dot,
        theta_ddot_radps2: ddot,
        valid: 0..n,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sine(n: usize, dt: f64, motion: &MotionLaw) -> (Vec<f64>, Vec<f64>) {
        let w = motion.omega();
        let t: Vec<f64> = (0..n).map(|i| i as f64 * dt).collect();
        let th = t
            .iter()
            .map(|&t| 0.2 + motion.amplitude_rad * (w * t + 0.3).sin())
            .collect();
        (t, th)
    }

    /// On a clean sine every estimator must reproduce the analytic derivatives closely.
    #[test]
    fn all_methods_differentiate_a_clean_sine() {
        let motion = MotionLaw {
            frequency_hz: 1.6,
            amplitude_rad: 0.5,
        };
        let (t, th) = sine(4000, 1e-3, &motion);
        let w = motion.omega();
        for method in ReferenceMethod::ALL {
            let k = kinematics(method, "clean", &t, &th, &motion).unwrap();
            let mut worst: f64 = 0.0;
            for i in k.valid.clone() {
                let exact = -motion.amplitude_rad * w * w * (w * t[i] + 0.3).sin();
                worst = worst.max((k.theta_ddot_radps2[i] - exact).abs());
            }
            let peak = motion.amplitude_rad * w * w;
            assert!(worst < 1e-3 * peak, "{method}: worst {worst} of {peak}");
        }
    }

    /// A parabola θ = t² has θ̈ = 2 exactly; central differences on uneven spacing must keep it.
    #[test]
    fn finite_difference_is_exact_on_a_parabola_with_uneven_steps() {
        let t = [0.0, 0.1, 0.25, 0.3, 0.5];
        let th: Vec<f64> = t.iter().map(|t| t * t).collect();
        let motion = MotionLaw {
            frequency_hz: 1.0,
            amplitude_rad: 1.0,
        };
        let k = kinematics(ReferenceMethod::FiniteDifference, "p", &t, &th, &motion).unwrap();
        for i in k.valid.clone() {
            assert!((k.theta_ddot_radps2[i] - 2.0).abs() < 1e-12);
            assert!((k.theta_dot_radps[i] - 2.0 * t[i]).abs() < 1e-12);
        }
    }

    #[test]
    fn uneven_sampling_is_named() {
        let t = [0.0, 0.001, 0.002, 0.0035, 0.0045];
        let err = check_time_axis("r.csv", &t, true).unwrap_err();
        assert!(
            matches!(err, FitError::Recording { sample: 3, .. }),
            "{err}"
        );
        let t = [0.0, 0.001, 0.001];
        let err = check_time_axis("r.csv", &t, false).unwrap_err();
        assert!(err.to_string().contains("does not increase"));
    }
}
