//! Building a calibration record from the fits.
//!
//! What goes into each set's `uncertainty_mps2` (the corrector adds it in quadrature to the
//! propagated parameter covariance and to the stated output noise, so each contribution must
//! appear once):
//!
//! - static set: zero. Its random parameter error, including the arm's angle errors that show
//!   up in the residuals, is in `covariance`; the sample noise is `sensor.output_noise`.
//!
//! Degrees of freedom, so that the gateway's coverage factors are Student's t (JCGM 100 G):
//! the static covariance has the fit's residual ν (N − 4, plus the arm statement's when one is
//! given); the dynamic covariance has N − 4 over all its points, or K − 1 when the
//! repeatability of K one-cycle sets scaled it up, since then K sets are what it rests on;
//! `uncertainty_mps2` has the Welch–Satterthwaite ν of the radius (a Type B value taken as
//! exact) and the lack of fit; the output noise has the ν of its second-difference estimate.
//! Each set's `coverage_factor` is Student's t at [`COVERAGE_PROBABILITY`] for its
//! covariance's ν: the k of the parameters' expanded uncertainties.
//! - dynamic set: √(u_r² + u_lof²), the radius and lack-of-fit contributions of
//!   [`triax_calibration::fit::repeatability`]. Repeatability is represented by `covariance`
//!   (which is scaled up when the observed repeatability exceeds what it predicts) and the
//!   reference variability by the residuals behind it.

use nalgebra::Vector3;
use time::OffsetDateTime;
use triax_calibration::fit::repeatability::UncertaintyBudget;
use triax_calibration::fit::{Bench, Calibration, DynamicFit, StaticFit, StaticObservation};
use triax_calibration::student::{t_quantile, welch_satterthwaite, MAX_DOF};
use triax_protocol::record::{
    CalibrationRecord, CalibrationSet, Certificate, Domain, Lab, SensorInfo, TemperatureModel,
};
use triax_protocol::{SensorId, JSON_FORMAT_VERSION};

/// Who and when, everything the fits do not know.
#[derive(Debug, Clone)]
pub struct RecordMeta {
    pub sensor_id: SensorId,
    pub version: u64,
    pub issued_at: OffsetDateTime,
    pub lab_name: String,
    pub certificate_id: String,
    pub output_unit: String,
}

/// Coverage probability the record states for every set.
pub const COVERAGE_PROBABILITY: f64 = 0.95;

/// Student's t at [`COVERAGE_PROBABILITY`] for `nu` degrees of freedom, truncated to an
/// integer as JCGM 100 G.4.1 does.
pub fn coverage_factor(nu: f64) -> f64 {
    t_quantile(
        nu.clamp(1.0, f64::from(MAX_DOF)) as u32,
        COVERAGE_PROBABILITY,
    )
}

/// The degrees of freedom of one set, each `None` for infinitely many.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SetDof {
    pub covariance: Option<f64>,
    pub uncertainty: Option<f64>,
}

fn covariance_rows(cal: &Calibration) -> Box<[[f64; 12]; 12]> {
    let c = cal.covariance();
    let mut rows = [[0.0; 12]; 12];
    for (i, row) in rows.iter_mut().enumerate() {
        for (j, cell) in row.iter_mut().enumerate() {
            // Exact symmetry, which the record validation demands.
            *cell = 0.5 * (c[(i, j)] + c[(j, i)]);
        }
    }
    Box::new(rows)
}

#[allow(clippy::too_many_arguments)]
fn set(
    cal: &Calibration,
    uncertainty_mps2: Vector3<f64>,
    dof: SetDof,
    domain: Domain,
    method: String,
    reference: String,
    n_points: usize,
    calibrated_at: OffsetDateTime,
) -> CalibrationSet {
    let s = cal.sensitivity();
    let q = cal.offset_mps2();
    CalibrationSet {
        sensitivity: [
            [s[(0, 0)], s[(0, 1)], s[(0, 2)]],
            [s[(1, 0)], s[(1, 1)], s[(1, 2)]],
            [s[(2, 0)], s[(2, 1)], s[(2, 2)]],
        ],
        offset: [q.x, q.y, q.z],
        uncertainty_mps2: [uncertainty_mps2.x, uncertainty_mps2.y, uncertainty_mps2.z],
        uncertainty_dof: dof.uncertainty,
        covariance: Some(covariance_rows(cal)),
        covariance_dof: dof.covariance,
        coverage_factor: coverage_factor(dof.covariance.unwrap_or(f64::INFINITY)),
        coverage_probability: Some(COVERAGE_PROBABILITY),
        domain,
        method,
        reference,
        n_points: n_points.min(u32::MAX as usize) as u32,
        calibrated_at,
    }
}

/// The static set.
pub fn static_set(
    fit: &StaticFit,
    observations: &[StaticObservation],
    gravity_mps2: f64,
    calibrated_at: OffsetDateTime,
) -> CalibrationSet {
    let amplitude = observations
        .iter()
        .map(|o| o.reference_mps2.amax())
        .fold(0.0, f64::max);
    set(
        &fit.calibration,
        Vector3::zeros(),
        SetDof {
            // With no residual and no arm statement the covariance is zero: nothing to weigh.
            covariance: (fit.covariance_dof >= 1.0).then_some(fit.covariance_dof),
            uncertainty: None,
        },
        Domain {
            amplitude_max_mps2: amplitude.max(f64::MIN_POSITIVE),
            frequency_min_hz: 0.0,
            frequency_max_hz: 0.0,
        },
        format!(
            "static multi-orientation linear least squares of V = S·a + c (12 parameters, SVD), \
             {} orientations",
            fit.residuals_mps2.len()
        ),
        format!("local gravity, g = {gravity_mps2} m/s², orientations set by the mechanical arm"),
        fit.residuals_mps2.len(),
        calibrated_at,
    )
}

/// The dynamic set, with the budget's (possibly inflated) covariance.
pub fn dynamic_set(
    fit: &DynamicFit,
    budget: &UncertaintyBudget,
    bench: &Bench,
    alphas_deg: &[f64],
    calibrated_at: OffsetDateTime,
) -> CalibrationSet {
    let angles: Vec<String> = alphas_deg.iter().map(|a| format!("{a}°")).collect();
    set(
        &budget.calibration,
        budget.combined_mps2,
        dynamic_dof(fit, budget),
        Domain {
            amplitude_max_mps2: budget.max_abs_mps2.max(),
            frequency_min_hz: bench.motion.frequency_hz,
            frequency_max_hz: bench.motion.frequency_hz,
        },
        format!(
            "rotary table linear least squares of V = S·a + c, {} points per cycle, {} cycles, \
             mount angles {}",
            fit.points_per_cycle,
            fit.cycles.iter().sum::<usize>(),
            angles.join(", ")
        ),
        format!(
            "rotary table encoder, {} reference, r = {} m (u = {} m), g = {} m/s², sine \
             {} Hz, {} rad",
            fit.method,
            bench.radius_m,
            bench.radius_uncertainty_m,
            bench.gravity_mps2,
            bench.motion.frequency_hz,
            bench.motion.amplitude_rad
        ),
        fit.n_points,
        calibrated_at,
    )
}

/// Degrees of freedom of the dynamic set (see the module's documentation).
pub fn dynamic_dof(fit: &DynamicFit, budget: &UncertaintyBudget) -> SetDof {
    let covariance = if budget.covariance_inflation > 1.0 {
        budget.sets.saturating_sub(1).max(1) as f64
    } else {
        fit.n_points.saturating_sub(4).max(1) as f64
    };
    // Per axis, the radius (exact) and the lack of fit (ν from its cells); the smallest ν of
    // the three axes speaks for all.
    let uncertainty = (0..3)
        .map(|k| {
            let radius = budget.radius_mps2[k].powi(2);
            let lof = budget.lack_of_fit_mps2[k].powi(2);
            welch_satterthwaite(&[(radius, 0.0), (lof, 1.0 / fit.lack_of_fit_dof)])
        })
        .fold(f64::INFINITY, f64::min);
    SetDof {
        covariance: Some(covariance),
        uncertainty: uncertainty.is_finite().then_some(uncertainty),
    }
}

/// The full record with both sets.
pub fn build_record(
    meta: &RecordMeta,
    static_set: CalibrationSet,
    dynamic_set: CalibrationSet,
    output_noise: Vector3<f64>,
    output_noise_dof: f64,
    temperature_c: Option<f64>,
    temperature: Option<TemperatureModel>,
) -> CalibrationRecord {
    CalibrationRecord {
        format_version: JSON_FORMAT_VERSION,
        sensor_id: meta.sensor_id.clone(),
        version: meta.version,
        issued_at: meta.issued_at,
        valid_from: meta.issued_at,
        valid_until: None,
        lab: Lab {
            name: meta.lab_name.clone(),
            accreditation: None,
            approved_by: None,
        },
        certificate: Certificate {
            id: meta.certificate_id.clone(),
            temperature_c,
            notes: None,
        },
        sensor: SensorInfo {
            output_unit: meta.output_unit.clone(),
            output_noise: Some([output_noise.x, output_noise.y, output_noise.z]),
            output_noise_dof: Some(output_noise_dof),
            output_full_scale: None,
            model: None,
            serial: None,
        },
        static_set,
        dynamic: dynamic_set,
        temperature,
    }
}
