//! Building a calibration record from the fits.
//!
//! What goes into each set's `uncertainty_mps2` (the corrector adds it in quadrature to the
//! propagated parameter covariance and to the stated output noise, so each contribution must
//! appear once):
//!
//! - static set: zero. Its random parameter error, including the arm's angle errors that show
//!   up in the residuals, is in `covariance`; the sample noise is `sensor.output_noise`.
//! - dynamic set: √(u_r² + u_lof²), the radius and lack-of-fit contributions of
//!   [`triax_calibration::fit::repeatability`]. Repeatability is represented by `covariance`
//!   (which is scaled up when the observed repeatability exceeds what it predicts) and the
//!   reference variability by the residuals behind it.

use nalgebra::Vector3;
use time::OffsetDateTime;
use triax_calibration::fit::repeatability::UncertaintyBudget;
use triax_calibration::fit::{Bench, Calibration, DynamicFit, StaticFit, StaticObservation};
use triax_protocol::record::{
    CalibrationRecord, CalibrationSet, Certificate, Domain, Lab, SensorInfo,
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

/// Coverage factor stated in the record: k = 2 for about 95 % with normal errors.
pub const COVERAGE_FACTOR: f64 = 2.0;

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

fn set(
    cal: &Calibration,
    uncertainty_mps2: Vector3<f64>,
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
        covariance: Some(covariance_rows(cal)),
        coverage_factor: COVERAGE_FACTOR,
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

/// The full record with both sets.
pub fn build_record(
    meta: &RecordMeta,
    static_set: CalibrationSet,
    dynamic_set: CalibrationSet,
    output_noise: Vector3<f64>,
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
            temperature_c: None,
            notes: None,
        },
        sensor: SensorInfo {
            output_unit: meta.output_unit.clone(),
            output_noise: Some([output_noise.x, output_noise.y, output_noise.z]),
            output_full_scale: None,
            model: None,
            serial: None,
        },
        static_set,
        dynamic: dynamic_set,
    }
}
