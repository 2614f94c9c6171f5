//! Uncertainty of a dynamic calibration (section 3.2.4 of the paper), and what of it goes into
//! a calibration record.
//!
//! Figures evaluated, per axis, in m/s² and as % of the amplitude (half the peak-to-peak of the
//! reference over a cycle, averaged over recordings):
//!
//! - **Repeatability** (the paper's method): K calibration sets, set k fitted from the points of
//!   cycle k of every recording; each set corrects the same cycle (the middle one) of every
//!   recording; the standard deviation across sets, averaged over the cycle.
//! - **Reference variability**: the reference folded over the cycles of each recording; the
//!   standard deviation across cycles at each phase, averaged over the cycle.
//! - **Radius**: `u(r)/r` times the RMS of the motion part of the reference (the gravity part
//!   does not depend on r).
//! - **Lack of fit**: see [`super::dynamic::fit_with`].
//!
//! What goes where, so that a corrector that adds the propagated covariance, the record's
//! `uncertainty_mps2` and the output noise in quadrature counts nothing twice:
//!
//! - The covariance holds the random parameter error. Repeatability is a Type A view of that
//!   same error (for a one-cycle set), so it is not added; it is used as a check instead: when
//!   the observed repeatability exceeds, beyond sampling scatter, what the covariance predicts
//!   for a one-cycle set, the covariance is scaled up by the squared ratio.
//! - Reference variability is partly estimator noise, which already drives the residuals and so
//!   the covariance, and partly real cycle-to-cycle variation of the motion, which the sensor
//!   sees too and is no error of the corrected output. It is reported, not added.
//! - `uncertainty_mps2` = √(radius² + lack of fit²): the two systematic contributions no
//!   amount of averaging removes and that the covariance does not represent.
//! - The output noise (in the record's noise field) is the sensor's own sample noise.

use nalgebra::Vector3;

use super::dynamic::{cycle_points, motion_part, Bench, DynamicFit, Recording};
use super::linear::fit_affine;
use super::{rms, Calibration, FitError};

/// A figure per axis, absolute and relative to the amplitude.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AxisFigure {
    pub mps2: Vector3<f64>,
    pub percent: Vector3<f64>,
}

/// The evaluated uncertainty contributions of a dynamic fit.
#[derive(Debug, Clone)]
pub struct UncertaintyBudget {
    /// Number of one-cycle calibration sets (K).
    pub sets: usize,
    pub repeatability: AxisFigure,
    /// What the (uninflated) covariance predicts for the repeatability of one-cycle sets.
    pub predicted_repeatability_mps2: Vector3<f64>,
    pub reference_variability: AxisFigure,
    pub radius_mps2: Vector3<f64>,
    pub lack_of_fit_mps2: Vector3<f64>,
    /// Factor applied to the covariance (1 when the check passed).
    pub covariance_inflation: f64,
    /// RMS over the evaluation cycle of the parameter part of the uncertainty, after inflation.
    pub parameter_mps2: Vector3<f64>,
    /// Half peak-to-peak of the reference over a cycle, mean over recordings.
    pub amplitude_mps2: Vector3<f64>,
    /// Goes into the record's `uncertainty_mps2`.
    pub combined_mps2: Vector3<f64>,
    /// The fit's calibration with the inflated covariance: the one to put in the record.
    pub calibration: Calibration,
    /// Domain actually covered: the largest |reference| per axis over all valid samples.
    pub max_abs_mps2: Vector3<f64>,
}

/// Evaluates the budget of a dynamic fit made from `recordings` with `bench`.
pub fn evaluate(
    bench: &Bench,
    recordings: &[Recording],
    fit: &DynamicFit,
) -> Result<UncertaintyBudget, FitError> {
    let period = bench.motion.period_s();
    let n = fit.points_per_cycle;
    let sets = fit
        .prepared
        .iter()
        .map(|p| p.cycles.len())
        .min()
        .unwrap_or(0);
    if sets < 2 {
        return Err(FitError::Bench(
            "the repeatability needs at least 2 whole cycles in every recording".into(),
        ));
    }

    // Amplitude and evaluation cycle per recording.
    let eval_cycle = sets / 2;
    let mut amplitude = Vector3::zeros();
    for prep in &fit.prepared {
        let cycle = prep.cycles[eval_cycle].clone();
        let mut lo = Vector3::repeat(f64::INFINITY);
        let mut hi = Vector3::repeat(f64::NEG_INFINITY);
        for a in &prep.reference_mps2[cycle] {
            lo = lo.inf(a);
            hi = hi.sup(a);
        }
        amplitude += (hi - lo) * 0.5;
    }
    amplitude /= fit.prepared.len() as f64;
    let percent =
        |v: Vector3<f64>| v.zip_map(&amplitude, |x, a| if a > 0.0 { 100.0 * x / a } else { 0.0 });

    // One calibration set per cycle index.
    let mut set_cals = Vec::with_capacity(sets);
    let mut set_rows = 0usize;
    for k in 0..sets {
        let mut refs = Vec::new();
        let mut outs = Vec::new();
        for (rec, prep) in recordings.iter().zip(&fit.prepared) {
            for i in cycle_points(&rec.t_s, &prep.cycles[k], n, period) {
                refs.push(prep.reference_mps2[i]);
                outs.push(rec.output[i]);
            }
        }
        set_rows = refs.len();
        // A single cycle can be degenerate where the whole was not (e.g. one point per
        // cycle); such a set is left out rather than failing the whole evaluation.
        if let Ok(f) = fit_affine(&refs, &outs, None) {
            set_cals.push(f.calibration);
        }
    }
    if set_cals.len() < 2 {
        return Err(FitError::RankDeficient {
            explanation: format!(
                "fewer than 2 of the {sets} one-cycle calibration sets could be fitted; raise \
                 points_per_cycle"
            ),
        });
    }
    let k_sets = set_cals.len() as f64;
    let rows_ratio = fit.n_points as f64 / set_rows.max(1) as f64;

    let mut observed_sum = Vector3::zeros();
    let mut predicted_sq_sum = Vector3::zeros();
    let mut eval_samples = 0usize;
    for (rec, prep) in recordings.iter().zip(&fit.prepared) {
        for i in prep.cycles[eval_cycle].clone() {
            let v = &rec.output[i];
            let corrected: Vec<Vector3<f64>> = set_cals.iter().map(|c| c.correct(v)).collect();
            let mean = corrected.iter().fold(Vector3::zeros(), |a, b| a + b) / k_sets;
            let var = corrected.iter().fold(Vector3::zeros(), |acc, c| {
                acc + (c - mean).component_mul(&(c - mean))
            }) / (k_sets - 1.0);
            observed_sum += var.map(f64::sqrt);
            let param = fit.calibration.parameter_uncertainty_mps2(v);
            predicted_sq_sum += param.component_mul(&param) * rows_ratio;
            eval_samples += 1;
        }
    }
    let m = eval_samples.max(1) as f64;
    let repeatability_mps2 = observed_sum / m;
    let predicted = (predicted_sq_sum / m).map(f64::sqrt);
    // The standard deviation of K values scatters by about 1/√(2(K−1)) relative; only a
    // ratio beyond twice that is taken as evidence that the covariance is too small.
    let threshold = 1.0 + 2.0 / (2.0 * (k_sets - 1.0)).sqrt();
    let mut inflation: f64 = 1.0;
    for axis in 0..3 {
        if predicted[axis] > 0.0 {
            let ratio = repeatability_mps2[axis] / predicted[axis];
            if ratio > threshold {
                inflation = inflation.max(ratio * ratio);
            }
        }
    }
    let calibration = fit.calibration.with_covariance_scaled(inflation);

    let mut param_sq = Vector3::zeros();
    for (rec, prep) in recordings.iter().zip(&fit.prepared) {
        for i in prep.cycles[eval_cycle].clone() {
            let p = calibration.parameter_uncertainty_mps2(&rec.output[i]);
            param_sq += p.component_mul(&p);
        }
    }
    let parameter_mps2 = (param_sq / m).map(f64::sqrt);

    // Reference variability over cycles, phase by phase.
    let mut variability_sum = Vector3::zeros();
    for prep in &fit.prepared {
        let len = prep.cycles.iter().map(|c| c.len()).min().unwrap_or(0);
        let cycles = prep.cycles.len() as f64;
        let mut per_rec = Vector3::zeros();
        for offset in 0..len {
            let values: Vec<Vector3<f64>> = prep
                .cycles
                .iter()
                .map(|c| prep.reference_mps2[c.start + offset])
                .collect();
            let mean = values.iter().fold(Vector3::zeros(), |a, b| a + b) / cycles;
            let var = values.iter().fold(Vector3::zeros(), |acc, c| {
                acc + (c - mean).component_mul(&(c - mean))
            }) / (cycles - 1.0);
            per_rec += var.map(f64::sqrt);
        }
        variability_sum += per_rec / len.max(1) as f64;
    }
    let variability_mps2 = variability_sum / fit.prepared.len() as f64;

    // Radius: a relative error of r scales the motion part of the reference.
    let motion_rms = rms(recordings
        .iter()
        .zip(&fit.prepared)
        .flat_map(|(rec, prep)| {
            let alpha = rec.alpha_deg.to_radians();
            prep.valid().map(move |i| {
                motion_part(
                    alpha,
                    bench.radius_m,
                    prep.kinematics.theta_dot_radps[i],
                    prep.kinematics.theta_ddot_radps2[i],
                )
            })
        }));
    let radius_mps2 = motion_rms * (bench.radius_uncertainty_m / bench.radius_m);

    let mut max_abs = Vector3::zeros();
    for prep in &fit.prepared {
        for a in &prep.reference_mps2[prep.valid()] {
            max_abs = max_abs.sup(&a.abs());
        }
    }

    let lack_of_fit_mps2 = fit.lack_of_fit_mps2;
    let combined_mps2 = (radius_mps2.component_mul(&radius_mps2)
        + lack_of_fit_mps2.component_mul(&lack_of_fit_mps2))
    .map(f64::sqrt);

    Ok(UncertaintyBudget {
        sets: set_cals.len(),
        repeatability: AxisFigure {
            mps2: repeatability_mps2,
            percent: percent(repeatability_mps2),
        },
        predicted_repeatability_mps2: predicted,
        reference_variability: AxisFigure {
            mps2: variability_mps2,
            percent: percent(variability_mps2),
        },
        radius_mps2,
        lack_of_fit_mps2,
        covariance_inflation: inflation,
        parameter_mps2,
        amplitude_mps2: amplitude,
        combined_mps2,
        calibration,
        max_abs_mps2: max_abs,
    })
}
