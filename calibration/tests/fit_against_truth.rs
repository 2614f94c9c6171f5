//! The lab's fits against the simulator's known truth.
//!
//! Index:
//! - static fit: recovery of S and q, ±g check;
//! - dynamic fit: recovery with a sensor that follows eq. (1) exactly, corrected output against
//!   the true specific force, rank deficiency with one mount angle;
//! - reference methods: the better estimators beat finite differences;
//! - the paper's comparison: dynamic set beats static set on dynamic data when the sensor
//!   responds differently to the varying part;
//! - radius from spacer blocks; uncertainty budget sanity.
//!
//! All data come from the seeded simulator, so every run sees the same numbers.

use nalgebra::Vector3;
use triax_calibration::fit::dynamic::{fit_with, Recording};
use triax_calibration::fit::repeatability::evaluate;
use triax_calibration::fit::tables::{compare_references, rms_against_reference, rms_vs_points};
use triax_calibration::fit::{fit_dynamic, fit_radius, fit_static, rms, FitError, ReferenceMethod};
use triax_calibration::sim::{simulate, SensorTruth, SimBench, SimConfig};

fn short(sensor: SensorTruth, seed: u64) -> SimBench {
    simulate(&SimConfig {
        seed,
        sensor,
        duration_s: 5.0,
        ..SimConfig::default()
    })
}

/// RMS over valid samples of (corrected − truth).
fn error_vs_truth(
    cal: &triax_calibration::fit::Calibration,
    recordings: &[Recording],
    truth: &[Vec<Vector3<f64>>],
) -> Vector3<f64> {
    rms(recordings
        .iter()
        .zip(truth)
        .flat_map(|(rec, tr)| rec.output.iter().zip(tr).map(|(v, a)| cal.correct(v) - a)))
}

#[test]
fn static_fit_recovers_s_and_q() {
    let sim = short(SensorTruth::paper(), 1);
    let fit = fit_static(&sim.static_observations).unwrap();
    let truth = &sim.config.sensor;
    let s_err = fit.calibration.sensitivity() - truth.static_sensitivity;
    let q_err = fit.calibration.offset_mps2() - truth.static_offset_mps2;
    // Relative to the main sensitivity (~0.1 V/(m/s²)) the arm's 0.2° angle errors allow a
    // few 10⁻³; q (extrapolated 25 m/s² from the data) about 0.1 m/s².
    assert!(s_err.amax() < 0.005 * 0.1, "S error {s_err}");
    assert!(q_err.amax() < 0.15, "q error {q_err}");
    // And the errors are consistent with the stated covariance (within 4σ).
    let cov = fit.calibration.covariance();
    for i in 0..9 {
        let sigma = cov[(i, i)].sqrt();
        assert!(
            s_err[(i / 3, i % 3)].abs() < 4.0 * sigma,
            "S[{i}] {s_err} σ {sigma}"
        );
    }
    for i in 0..3 {
        let sigma = cov[(9 + i, 9 + i)].sqrt();
        assert!(q_err[i].abs() < 4.0 * sigma, "q[{i}] {q_err} σ {sigma}");
    }
    // ±g check: the deviations are of the order of the angle errors, 0.2° · g ≈ 0.03 m/s².
    assert!(fit.max_deviation_mps2 < 0.15, "{}", fit.max_deviation_mps2);
    assert!(fit.leave_one_out_max_deviation_mps2.unwrap() >= fit.max_deviation_mps2);
    assert_eq!(fit.dof, 6);
}

#[test]
fn static_fit_refuses_coplanar_orientations() {
    let sim = short(SensorTruth::paper(), 2);
    // Orientations 0..4 are ±z and ±y: all references in the y–z plane.
    let err = fit_static(&sim.static_observations[0..4]).unwrap_err();
    match &err {
        FitError::ReferencesDegenerate { normal_x, .. } => {
            assert!((normal_x.abs() - 1.0).abs() < 1e-6, "{err}")
        }
        other => panic!("unexpected {other}"),
    }
    assert!(err.to_string().contains("do not span three dimensions"));
}

#[test]
fn dynamic_fit_recovers_s_and_q_of_an_eq1_sensor() {
    let sim = short(SensorTruth::matched(), 3);
    let truth = &sim.config.sensor;
    for method in [ReferenceMethod::SavitzkyGolay, ReferenceMethod::Harmonic] {
        let fit = fit_with(&sim.bench, &sim.recordings, method, 20).unwrap();
        let s_err = fit.calibration.sensitivity() - truth.static_sensitivity;
        let q_err = fit.calibration.offset_mps2() - truth.static_offset_mps2;
        assert!(s_err.amax() < 0.01 * 0.1, "{method}: S error {s_err}");
        assert!(q_err.amax() < 0.1, "{method}: q error {q_err}");
    }
}

#[test]
fn corrected_output_matches_the_true_specific_force() {
    let sim = short(SensorTruth::matched(), 4);
    let fit = fit_with(&sim.bench, &sim.recordings, ReferenceMethod::Harmonic, 20).unwrap();
    // Fresh data: the same sensor, new noise and new motion.
    let fresh = short(SensorTruth::matched(), 40);
    let err = error_vs_truth(&fit.calibration, &fresh.recordings, &fresh.truth_mps2);
    // The floor is the sensor noise, 5 mV / 0.1 V/(m/s²) ≈ 0.05 m/s²; the calibration adds
    // little to it.
    let noise = fit.output_noise_mps2;
    for axis in 0..3 {
        assert!(
            err[axis] < 1.2 * noise[axis],
            "axis {axis}: {err} vs noise {noise}"
        );
    }
    assert!((noise.x - 0.05).abs() < 0.005, "noise estimate {noise}");
}

#[test]
fn better_references_beat_finite_differences() {
    let sim = short(SensorTruth::matched(), 5);
    let truth = &sim.config.sensor;
    let mut reference_error = Vec::new();
    let mut s_error = Vec::new();
    for method in ReferenceMethod::ALL {
        let fit = fit_with(&sim.bench, &sim.recordings, method, 20).unwrap();
        let ref_err = rms(fit
            .prepared
            .iter()
            .zip(&sim.truth_mps2)
            .flat_map(|(p, tr)| p.valid().map(move |i| p.reference_mps2[i] - tr[i])));
        reference_error.push((method, ref_err.norm()));
        s_error.push((
            method,
            (fit.calibration.sensitivity() - truth.static_sensitivity).norm(),
        ));
    }
    let of = |list: &[(ReferenceMethod, f64)], m: ReferenceMethod| {
        list.iter().find(|(k, _)| *k == m).unwrap().1
    };
    let fd_ref = of(&reference_error, ReferenceMethod::FiniteDifference);
    let fd_s = of(&s_error, ReferenceMethod::FiniteDifference);
    for m in [ReferenceMethod::SavitzkyGolay, ReferenceMethod::Harmonic] {
        assert!(
            of(&reference_error, m) < 0.5 * fd_ref,
            "{m} reference error {reference_error:?}"
        );
        assert!(of(&s_error, m) < fd_s, "{m} S error {s_error:?}");
    }
}

#[test]
fn one_mount_angle_is_rank_deficient_and_says_what_is_missing() {
    let mut sim = short(SensorTruth::matched(), 6);
    sim.recordings.truncate(2);
    sim.recordings[1].alpha_deg = sim.recordings[0].alpha_deg;
    let err = fit_dynamic(&sim.bench, &sim.recordings).unwrap_err();
    let text = err.to_string();
    assert!(matches!(err, FitError::RankDeficient { .. }), "{text}");
    assert!(text.contains("alpha_deg = 0"), "{text}");
    assert!(text.contains("another alpha_deg"), "{text}");
    assert!(text.contains(&sim.recordings[0].name), "{text}");
}

#[test]
fn dynamic_set_beats_static_set_on_dynamic_data() {
    let sim = short(SensorTruth::paper(), 7);
    let stat = fit_static(&sim.static_observations).unwrap();
    let dynamic = fit_dynamic(&sim.bench, &sim.recordings).unwrap();
    let on_dyn = rms_against_reference(&dynamic.calibration, &sim.recordings, &dynamic.prepared);
    let on_stat = rms_against_reference(&stat.calibration, &sim.recordings, &dynamic.prepared);
    assert!(
        on_dyn.rms_mps2.norm() < on_stat.rms_mps2.norm(),
        "dynamic {} static {}",
        on_dyn.rms_mps2,
        on_stat.rms_mps2
    );
    // Against the truth as well, not only against the noisy reference.
    let dyn_true = error_vs_truth(&dynamic.calibration, &sim.recordings, &sim.truth_mps2);
    let stat_true = error_vs_truth(&stat.calibration, &sim.recordings, &sim.truth_mps2);
    assert!(dyn_true.norm() < stat_true.norm(), "{dyn_true} {stat_true}");
}

#[test]
fn radius_is_recovered_within_its_uncertainty() {
    let sim = short(SensorTruth::paper(), 8);
    let fit = fit_radius(&sim.spacers).unwrap();
    let err = fit.radius_m - sim.config.radius_m;
    assert!(err.abs() < 4.0 * fit.radius_uncertainty_m, "{fit:?}");
    assert!(fit.radius_uncertainty_m / fit.radius_m < 0.02);
}

#[test]
fn uncertainty_budget_is_sane() {
    let sim = short(SensorTruth::paper(), 9);
    let fit = fit_dynamic(&sim.bench, &sim.recordings).unwrap();
    let budget = evaluate(&sim.bench, &sim.recordings, &fit).unwrap();
    assert_eq!(budget.sets, fit.cycles.iter().copied().min().unwrap());
    for axis in 0..3 {
        assert!(budget.repeatability.mps2[axis] > 0.0);
        assert!(budget.reference_variability.mps2[axis] > 0.0);
        assert!(budget.amplitude_mps2[axis] > 0.5);
        let expected =
            (budget.radius_mps2[axis].powi(2) + budget.lack_of_fit_mps2[axis].powi(2)).sqrt();
        assert!((budget.combined_mps2[axis] - expected).abs() < 1e-12);
    }
    assert!(budget.covariance_inflation >= 1.0);
}

#[test]
fn tables_have_a_row_per_n_and_a_column_per_method() {
    let sim = short(SensorTruth::paper(), 10);
    let rows = rms_vs_points(&sim.bench, &sim.recordings, &[14, 21, 28]).unwrap();
    assert_eq!(rows.len(), 3);
    let cmp = compare_references(&sim.bench, &sim.recordings).unwrap();
    assert_eq!(cmp.methods.len(), 4);
    assert_eq!(cmp.pairwise_rms_mps2[1][0], cmp.pairwise_rms_mps2[0][1]);
}
