//! The lab's commands as functions: inputs are paths and options, outputs are the bytes to
//! write and the text to print. The binary does the writing, after a command has fully
//! succeeded, so a failure never leaves an output file behind.

use std::fmt::Write;
use std::path::{Path, PathBuf};

use nalgebra::{Matrix3, Vector3};
use time::OffsetDateTime;
use triax_calibration::corrector::{Corrector, TemperatureCheck};
use triax_calibration::fit::dynamic::{fit_with, Bench};
use triax_calibration::fit::repeatability::{evaluate, UncertaintyBudget};
use triax_calibration::fit::tables::{
    compare_references, rms_against_reference, rms_vs_points, PointsRow, ReferenceComparison,
    RmsFigure,
};
use triax_calibration::fit::thermal::fit_thermal;
use triax_calibration::fit::{
    fit_radius, fit_static_with, ArmAngleUncertainty, DynamicFit, RadiusFit, ReferenceMethod,
    StaticFit, StaticObservation,
};
use triax_calibration::sim::{simulate, SimBench, SimConfig};
use triax_protocol::record::{CalibrationRecord, SetKind, TemperatureModel};
use triax_protocol::{from_json, to_json_pretty};

use crate::input::{read_bench, read_output_series, read_spacers, read_static, LoadedBench};
use crate::record::{
    build_record, coverage_factor, dynamic_dof, dynamic_set, static_set, RecordMeta,
    COVERAGE_PROBABILITY,
};
use crate::report::{render, Report};
use crate::LabError;

/// Numbers of points per cycle in Table 1, as in the paper.
pub const TABLE1_POINTS: [usize; 5] = [14, 21, 28, 35, 42];

/// The static step.
pub struct StaticResult {
    pub path: PathBuf,
    /// The rows the static set was fitted to: all of them, or the reference run's when the
    /// file has runs at several temperatures.
    pub observations: Vec<StaticObservation>,
    pub fit: StaticFit,
    /// The temperature of the rows the set was fitted to, when the file says.
    pub temperature_c: Option<f64>,
    /// Runs at several temperatures: the model, and the runs' temperatures and sizes.
    pub thermal: Option<(TemperatureModel, Vec<(f64, usize)>)>,
}

pub fn run_static(
    path: &Path,
    gravity_mps2: f64,
    arm: Option<ArmAngleUncertainty>,
) -> Result<StaticResult, LabError> {
    let rows = read_static(path, gravity_mps2)?;
    let fit_error = |source| LabError::Fit {
        file: path.to_path_buf(),
        source,
    };
    let Some(temperatures_c) = rows.temperatures_c else {
        let fit = fit_static_with(&rows.observations, arm).map_err(fit_error)?;
        return Ok(StaticResult {
            path: path.to_path_buf(),
            observations: rows.observations,
            fit,
            temperature_c: None,
            thermal: None,
        });
    };
    let t = fit_thermal(&rows.observations, &temperatures_c, arm).map_err(fit_error)?;
    let reference = &t.runs[t.reference];
    Ok(StaticResult {
        path: path.to_path_buf(),
        observations: reference
            .rows
            .iter()
            .map(|&i| rows.observations[i])
            .collect(),
        fit: t.reference_fit,
        temperature_c: Some(reference.temperature_c),
        thermal: t.model.map(|m| {
            let runs = t
                .runs
                .iter()
                .map(|r| (r.temperature_c, r.rows.len()))
                .collect();
            (m, runs)
        }),
    })
}

/// The dynamic step with its uncertainty budget.
pub struct DynamicResult {
    pub loaded: LoadedBench,
    pub fit: DynamicFit,
    pub budget: UncertaintyBudget,
}

impl DynamicResult {
    pub fn bench(&self) -> &Bench {
        &self.loaded.bench
    }
}

pub fn run_dynamic(
    bench_path: &Path,
    reference: Option<ReferenceMethod>,
    points_per_cycle: Option<usize>,
) -> Result<DynamicResult, LabError> {
    let mut loaded = read_bench(bench_path, reference)?;
    if let Some(n) = points_per_cycle {
        loaded.bench.points_per_cycle = n;
    }
    let recordings = loaded.recordings();
    let bench = &loaded.bench;
    let fit = fit_with(bench, &recordings, bench.reference, bench.points_per_cycle)
        .map_err(|e| loaded.locate(e))?;
    let budget = evaluate(bench, &recordings, &fit).map_err(|e| loaded.locate(e))?;
    Ok(DynamicResult {
        loaded,
        fit,
        budget,
    })
}

/// The comparison tables of the paper, for the report.
pub struct Tables {
    pub points: Vec<PointsRow>,
    pub dynamic_set: RmsFigure,
    pub static_set: Option<RmsFigure>,
    pub references: ReferenceComparison,
}

pub fn run_tables(
    dynamic: &DynamicResult,
    static_fit: Option<&StaticFit>,
) -> Result<Tables, LabError> {
    let recordings = dynamic.loaded.recordings();
    let bench = dynamic.bench();
    let shortest = dynamic
        .fit
        .prepared
        .iter()
        .flat_map(|p| p.cycles.iter().map(|c| c.len()))
        .min()
        .unwrap_or(0);
    let ns: Vec<usize> = TABLE1_POINTS
        .iter()
        .copied()
        .filter(|&n| n <= shortest)
        .collect();
    let points = rms_vs_points(bench, &recordings, &ns).map_err(|e| dynamic.loaded.locate(e))?;
    let dynamic_set =
        rms_against_reference(&dynamic.fit.calibration, &recordings, &dynamic.fit.prepared);
    let static_set = static_fit
        .map(|s| rms_against_reference(&s.calibration, &recordings, &dynamic.fit.prepared));
    let references =
        compare_references(bench, &recordings).map_err(|e| dynamic.loaded.locate(e))?;
    Ok(Tables {
        points,
        dynamic_set,
        static_set,
        references,
    })
}

/// What `fit` produces.
pub struct FitOutput {
    pub record: CalibrationRecord,
    pub json: Vec<u8>,
    pub summary: String,
    pub report_html: Option<String>,
}

/// Options of `fit` beyond the input paths.
pub struct FitOptions {
    pub gravity_mps2: f64,
    /// The operator's statement of the static arm's angle uncertainty, if any.
    pub arm: Option<ArmAngleUncertainty>,
    pub reference: Option<ReferenceMethod>,
    pub points_per_cycle: Option<usize>,
    pub report: bool,
    pub meta: RecordMeta,
}

/// Static and dynamic fit, the record, the summary and optionally the report.
pub fn run_fit(
    static_path: &Path,
    bench_path: &Path,
    options: &FitOptions,
) -> Result<FitOutput, LabError> {
    let stat = run_static(static_path, options.gravity_mps2, options.arm)?;
    let dynamic = run_dynamic(bench_path, options.reference, options.points_per_cycle)?;
    let at = options.meta.issued_at;
    let alphas: Vec<f64> = dynamic
        .loaded
        .recordings
        .iter()
        .map(|r| r.recording.alpha_deg)
        .collect();
    let record = build_record(
        &options.meta,
        static_set(&stat.fit, &stat.observations, options.gravity_mps2, at),
        dynamic_set(&dynamic.fit, &dynamic.budget, dynamic.bench(), &alphas, at),
        dynamic.fit.output_noise,
        dynamic.fit.output_noise_dof,
        stat.temperature_c,
        stat.thermal.as_ref().map(|(m, _)| m.clone()),
    );
    record
        .validate()
        .map_err(triax_calibration::corrector::LoadError::from)?;
    // The same check the gateway makes when it loads the record.
    Corrector::from_record(&record)?;
    let tables = if options.report {
        Some(run_tables(&dynamic, Some(&stat.fit))?)
    } else {
        None
    };
    let mut summary = static_summary(&stat);
    summary.push_str(&dynamic_summary(&dynamic));
    if let Some(t) = &tables {
        summary.push_str(&tables_summary(t));
    }
    let report_html = tables.as_ref().map(|t| {
        render(&Report {
            sensor_id: options.meta.sensor_id.as_str(),
            issued_at: at,
            stat: Some(&stat),
            dynamic: &dynamic,
            tables: t,
        })
    });
    Ok(FitOutput {
        json: to_json_pretty(&record),
        record,
        summary,
        report_html,
    })
}

fn fmt_vec(v: &Vector3<f64>, precision: usize) -> String {
    format!(
        "{:>10.p$} {:>10.p$} {:>10.p$}",
        v.x,
        v.y,
        v.z,
        p = precision
    )
}

fn fmt_matrix(m: &Matrix3<f64>) -> String {
    let mut s = String::new();
    for i in 0..3 {
        let _ = writeln!(
            s,
            "    [{:>11.6} {:>11.6} {:>11.6}]",
            m[(i, 0)],
            m[(i, 1)],
            m[(i, 2)]
        );
    }
    s
}

/// Standard uncertainties of S (3×3) and q from a calibration's covariance.
pub fn parameter_sigmas(cal: &triax_calibration::fit::Calibration) -> (Matrix3<f64>, Vector3<f64>) {
    let c = cal.covariance();
    let s = Matrix3::from_fn(|i, j| c[(3 * i + j, 3 * i + j)].max(0.0).sqrt());
    let q = Vector3::from_fn(|i, _| c[(9 + i, 9 + i)].max(0.0).sqrt());
    (s, q)
}

pub fn static_summary(stat: &StaticResult) -> String {
    let fit = &stat.fit;
    let cal = &fit.calibration;
    let (s_sigma, q_sigma) = parameter_sigmas(cal);
    let mut s = String::new();
    let _ = writeln!(
        s,
        "Static calibration ({} orientations, {} residual degrees of freedom)",
        fit.residuals_mps2.len(),
        fit.dof
    );
    let _ = writeln!(
        s,
        "  covariance: ν = {:.0}, k = {:.3} at {:.0} %",
        fit.covariance_dof,
        coverage_factor(fit.covariance_dof),
        COVERAGE_PROBABILITY * 100.0
    );
    let _ = write!(s, "  S [output/(m/s²)]:\n{}", fmt_matrix(cal.sensitivity()));
    let _ = write!(s, "  u(S):\n{}", fmt_matrix(&s_sigma));
    let _ = writeln!(s, "  q [m/s²]:      {}", fmt_vec(cal.offset_mps2(), 4));
    let _ = writeln!(s, "  u(q) [m/s²]:   {}", fmt_vec(&q_sigma, 4));
    let _ = writeln!(s, "  residual RMS:  {}", fmt_vec(&fit.residual_rms_mps2, 4));
    let _ = writeln!(
        s,
        "  ±g check: largest |corrected − reference| = {:.4} m/s² (orientation {})",
        fit.max_deviation_mps2,
        fit.max_deviation_orientation + 1
    );
    if let Some(loo) = fit.leave_one_out_max_deviation_mps2 {
        let _ = writeln!(
            s,
            "  ±g check, each orientation left out of its fit: {loo:.4} m/s²"
        );
    }
    for w in &fit.warnings {
        let _ = writeln!(s, "  warning: {w}");
    }
    if let Some(w) = low_dof_warning(fit) {
        let _ = writeln!(s, "  warning: {w}");
    }
    if let Some((m, runs)) = &stat.thermal {
        let list: Vec<String> = runs
            .iter()
            .map(|(t, n)| format!("{t:.1} °C ({n} rows)"))
            .collect();
        let _ = writeln!(
            s,
            "  temperature: runs at {}; reference {:.1} °C; ν = {}",
            list.join(", "),
            m.reference_c,
            m.covariance_dof
                .map_or("∞".to_string(), |nu| format!("{nu:.0}"))
        );
        let u = |i: usize| m.covariance[i][i].max(0.0).sqrt();
        let _ = writeln!(
            s,
            "    offset drift [m/s² per °C]: {}   u: {}",
            fmt_vec(&Vector3::from(m.offset_mps2_per_c), 6),
            fmt_vec(&Vector3::new(u(0), u(1), u(2)), 6)
        );
        if let Some(g) = m.gain_per_c {
            let _ = writeln!(
                s,
                "    gain drift [per °C]:        {}   u: {}",
                fmt_vec(&Vector3::from(g), 7),
                fmt_vec(&Vector3::new(u(3), u(4), u(5)), 7)
            );
        }
    }
    s
}

/// Degrees of freedom below which the static set's k is more than 10 % above the normal
/// distribution's (t = 2.16 at ν = 13 against 1.96).
pub const LOW_DOF: f64 = 13.0;

/// Says when the static covariance rests on few degrees of freedom, and what would help.
pub fn low_dof_warning(fit: &StaticFit) -> Option<String> {
    if fit.covariance_dof >= LOW_DOF || fit.dof == 0 {
        return None;
    }
    let missing = (LOW_DOF - fit.covariance_dof).ceil() as usize;
    Some(format!(
        "the static covariance has only {:.0} degrees of freedom, so every interval that rests \
         on it needs k = {:.2} rather than 1.96 at 95 %; {} orientations (not in one plane) \
         would give ν = {:.0} (k = {:.2}), or state the arm's angle uncertainty \
         (--arm-angle-uncertainty-deg) to pool it with the residuals",
        fit.covariance_dof,
        coverage_factor(fit.covariance_dof),
        fit.residuals_mps2.len() + missing,
        fit.covariance_dof + missing as f64,
        coverage_factor(fit.covariance_dof + missing as f64),
    ))
}

pub fn dynamic_summary(d: &DynamicResult) -> String {
    let fit = &d.fit;
    let b = &d.budget;
    let cal = &b.calibration;
    let (s_sigma, q_sigma) = parameter_sigmas(cal);
    let mut s = String::new();
    let _ = writeln!(
        s,
        "\nDynamic calibration ({} reference, n = {} points per cycle, {} points from {} \
         recordings)",
        fit.method,
        fit.points_per_cycle,
        fit.n_points,
        fit.cycles.len()
    );
    let dof = dynamic_dof(fit, b);
    let nu_cov = dof.covariance.unwrap_or(f64::INFINITY);
    let _ = writeln!(
        s,
        "  covariance: ν = {nu_cov:.0}, k = {:.3} at {:.0} %; uncertainty_mps2: ν = {}",
        coverage_factor(nu_cov),
        COVERAGE_PROBABILITY * 100.0,
        dof.uncertainty
            .map_or("∞".to_string(), |nu| format!("{nu:.0}"))
    );
    let _ = write!(s, "  S [output/(m/s²)]:\n{}", fmt_matrix(cal.sensitivity()));
    let _ = write!(s, "  u(S):\n{}", fmt_matrix(&s_sigma));
    let _ = writeln!(s, "  q [m/s²]:      {}", fmt_vec(cal.offset_mps2(), 4));
    let _ = writeln!(s, "  u(q) [m/s²]:   {}", fmt_vec(&q_sigma, 4));
    let _ = writeln!(
        s,
        "  RMS(corrected − reference) [m/s²]: {}",
        fmt_vec(&fit.residual_rms_mps2, 4)
    );
    let _ = writeln!(s, "  Uncertainty (k = 1), per axis x y z:");
    let _ = writeln!(
        s,
        "    repeatability, {} one-cycle sets [m/s²]: {}   [% of amplitude] {}",
        b.sets,
        fmt_vec(&b.repeatability.mps2, 4),
        fmt_vec(&b.repeatability.percent, 2)
    );
    let _ = writeln!(
        s,
        "    reference variability over cycles [m/s²]: {}   [% of amplitude] {}",
        fmt_vec(&b.reference_variability.mps2, 4),
        fmt_vec(&b.reference_variability.percent, 2)
    );
    let _ = writeln!(
        s,
        "    radius u(r) [m/s²]:                        {}",
        fmt_vec(&b.radius_mps2, 4)
    );
    let _ = writeln!(
        s,
        "    lack of fit [m/s²]:                        {}",
        fmt_vec(&b.lack_of_fit_mps2, 4)
    );
    let _ = writeln!(
        s,
        "    parameters (covariance) [m/s²]:            {}",
        fmt_vec(&b.parameter_mps2, 4)
    );
    let _ = writeln!(
        s,
        "    output noise [m/s²]:                       {}",
        fmt_vec(&fit.output_noise_mps2, 4)
    );
    let _ = writeln!(
        s,
        "    uncertainty_mps2 in the record:            {}",
        fmt_vec(&b.combined_mps2, 4)
    );
    if b.covariance_inflation > 1.0 {
        let _ = writeln!(
            s,
            "    covariance scaled by {:.2}: the observed repeatability exceeds the least-squares \
             prediction {}",
            b.covariance_inflation,
            fmt_vec(&b.predicted_repeatability_mps2, 4)
        );
    }
    let _ = writeln!(
        s,
        "  Domain: |a| up to {:.2} m/s², {} Hz",
        b.max_abs_mps2.max(),
        d.bench().motion.frequency_hz
    );
    s
}

pub fn tables_summary(t: &Tables) -> String {
    let mut s = String::new();
    let _ = writeln!(
        s,
        "\nTable 1: RMS(corrected − reference) vs points per cycle [m/s²]"
    );
    let _ = writeln!(s, "   n       RMS_x      RMS_y      RMS_z");
    for row in &t.points {
        let _ = writeln!(
            s,
            "  {:>3} {}",
            row.points_per_cycle,
            fmt_vec(&row.rms_mps2, 4)
        );
    }
    let _ = writeln!(
        s,
        "\nTables 2 and 3: RMS(corrected − reference) on the dynamic data"
    );
    let _ = writeln!(
        s,
        "  dynamic set: absolute {}  relative {}",
        fmt_vec(&t.dynamic_set.rms_mps2, 4),
        fmt_vec(&t.dynamic_set.relative, 3)
    );
    if let Some(st) = &t.static_set {
        let _ = writeln!(
            s,
            "  static set:  absolute {}  relative {}",
            fmt_vec(&st.rms_mps2, 4),
            fmt_vec(&st.relative, 3)
        );
    }
    let _ = writeln!(s, "\nReference methods: RMS of own fit, and RMS difference to each other (norm over axes) [m/s²]");
    let names: Vec<&str> = t.references.methods.iter().map(|m| m.name()).collect();
    let _ = writeln!(
        s,
        "  {:<18} {:>32}  {}",
        "",
        "own fit x y z",
        names.iter().map(|n| format!("{n:>18}")).collect::<String>()
    );
    for (i, m) in t.references.methods.iter().enumerate() {
        let row: String = t.references.pairwise_rms_mps2[i]
            .iter()
            .map(|v| format!("{:>18.4}", v.norm()))
            .collect();
        let _ = writeln!(
            s,
            "  {:<18} {}  {}",
            m.name(),
            fmt_vec(&t.references.fit_rms_mps2[i], 4),
            row
        );
    }
    s
}

/// The radius step.
pub fn run_radius(path: &Path) -> Result<(RadiusFit, String), LabError> {
    let points = read_spacers(path)?;
    let fit = fit_radius(&points).map_err(|source| LabError::Fit {
        file: path.to_path_buf(),
        source,
    })?;
    let summary = format!(
        "Radius from {} spacer positions (eqs. (4)–(8))\n  y = m·Δr + b: m = {:.6e} per mm \
         (s_m = {:.2e}), b = {:.6e} (s_b = {:.2e}), s_V = {:.2e}\n  r₀ = b/m = {:.6} m, \
         s_r = {:.6} m ({:.2} %)\n",
        fit.n_points,
        fit.slope_per_mm,
        fit.s_slope_per_mm,
        fit.intercept,
        fit.s_intercept,
        fit.s_v,
        fit.radius_m,
        fit.radius_uncertainty_m,
        100.0 * fit.radius_uncertainty_m / fit.radius_m
    );
    Ok((fit, summary))
}

/// Offline correction of `t_s,vx,vy,vz` data with one set of a record, by the gateway's
/// corrector. Returns the CSV text `t_s,ax,ay,az,ux,uy,uz` and the number of rows.
pub fn run_apply(
    record_path: &Path,
    set: SetKind,
    input_path: &Path,
) -> Result<(String, usize), LabError> {
    let bytes = std::fs::read(record_path)
        .map_err(|e| crate::InputError::file(record_path, format!("cannot read: {e}")))?;
    let record: CalibrationRecord = from_json(&bytes).map_err(|e| LabError::Json {
        file: record_path.to_path_buf(),
        problem: e.to_string(),
    })?;
    let corrector = Corrector::from_record(&record)?;
    let set = corrector.set(set);
    let series = read_output_series(input_path)?;
    // A record with a temperature model corrects each row at its temperature and says, per
    // row, whether that was outside what the lab calibrated (PROTOCOL.md §3.1).
    let thermal = corrector.models_temperature();
    let mut out = String::with_capacity(series.t_s.len() * 80);
    out.push_str(if thermal {
        "t_s,ax,ay,az,ux,uy,uz,outside_temperature\n"
    } else {
        "t_s,ax,ay,az,ux,uy,uz\n"
    });
    for (i, (t, v)) in series.t_s.iter().zip(&series.output).enumerate() {
        let temperature = series.temperature_c.as_ref().map(|c| c[i]);
        let warm = temperature.and_then(|c| set.at_temperature(c));
        let c = warm.as_ref().unwrap_or(set).correct(*v);
        let a = c.accel_mps2;
        let u = c.uncertainty_mps2;
        let _ = write!(
            out,
            "{t},{:.6},{:.6},{:.6},{:.6},{:.6},{:.6}",
            a[0], a[1], a[2], u[0], u[1], u[2]
        );
        if thermal {
            let outside = !matches!(set.temperature_check(temperature), TemperatureCheck::Inside)
                || warm.is_none();
            let _ = write!(out, ",{}", u8::from(outside));
        }
        out.push('\n');
    }
    Ok((out, series.t_s.len()))
}

/// The files `simulate` writes, as (relative path, contents), plus the simulation itself.
pub fn run_simulate(config: &SimConfig) -> (SimBench, Vec<(PathBuf, String)>) {
    let sim = simulate(config);
    let mut files = Vec::new();

    let mut st = String::from("roll_deg,pitch_deg,ax_ref,ay_ref,az_ref,vx,vy,vz");
    st.push_str(if sim.static_temperatures_c.is_some() {
        ",temperature_c\n"
    } else {
        "\n"
    });
    for (i, (obs, (roll, pitch))) in sim
        .static_observations
        .iter()
        .zip(&sim.static_angles_deg)
        .enumerate()
    {
        let a = obs.reference_mps2;
        let v = obs.output;
        let _ = write!(
            st,
            "{roll:.4},{pitch:.4},{:.6},{:.6},{:.6},{:.7},{:.7},{:.7}",
            a.x, a.y, a.z, v.x, v.y, v.z
        );
        match &sim.static_temperatures_c {
            Some(t) => {
                let _ = writeln!(st, ",{:.2}", t[i]);
            }
            None => st.push('\n'),
        }
    }
    files.push((PathBuf::from("static.csv"), st));

    let b = &sim.bench;
    let mut bench = format!(
        "# Simulated rotary-table bench (triax-lab simulate, seed {}).\n\
         radius_m = {}\nradius_uncertainty_m = {}\ngravity_mps2 = {}\npoints_per_cycle = {}\n\
         reference = \"{}\"\n\n[motion]\nlaw = \"sine\"\nfrequency_hz = {}\namplitude_rad = {}\n",
        config.seed,
        b.radius_m,
        b.radius_uncertainty_m,
        b.gravity_mps2,
        b.points_per_cycle,
        b.reference.name(),
        b.motion.frequency_hz,
        b.motion.amplitude_rad
    );
    for rec in &sim.recordings {
        let _ = write!(
            bench,
            "\n[[recording]]\nfile = \"recordings/{}\"\nalpha_deg = {}\n",
            rec.name, rec.alpha_deg
        );
        let mut csv = String::with_capacity(rec.t_s.len() * 48);
        csv.push_str("t_s,theta_rad,vx,vy,vz\n");
        for i in 0..rec.t_s.len() {
            let v = rec.output[i];
            let _ = writeln!(
                csv,
                "{:.4},{:.7},{:.5},{:.5},{:.5}",
                rec.t_s[i], rec.theta_rad[i], v.x, v.y, v.z
            );
        }
        files.push((PathBuf::from("recordings").join(&rec.name), csv));
    }
    files.push((PathBuf::from("bench.toml"), bench));

    let mut spacers = String::from("delta_r_mm,output\n");
    for (d, y) in &sim.spacers {
        let _ = writeln!(spacers, "{d},{y:.6}");
    }
    files.push((PathBuf::from("spacers.csv"), spacers));

    let s = &sim.config.sensor;
    let row = |m: &Matrix3<f64>, i: usize| format!("[{}, {}, {}]", m[(i, 0)], m[(i, 1)], m[(i, 2)]);
    let mat = |m: &Matrix3<f64>| format!("[{}, {}, {}]", row(m, 0), row(m, 1), row(m, 2));
    let mut truth = format!(
        "# The simulated sensor and bench (what the fits should find).\n\
         static_sensitivity = {}\nstatic_offset_mps2 = [{}, {}, {}]\ndynamic_sensitivity = {}\n\
         noise_v = [{}, {}, {}]\nradius_m = {}\nstated_radius_m = {}\n",
        mat(&s.static_sensitivity),
        s.static_offset_mps2.x,
        s.static_offset_mps2.y,
        s.static_offset_mps2.z,
        mat(&s.dynamic_sensitivity),
        s.noise_v.x,
        s.noise_v.y,
        s.noise_v.z,
        sim.config.radius_m,
        sim.bench.radius_m
    );
    if s.offset_drift_mps2_per_c != Vector3::zeros() || s.gain_drift_per_c != Vector3::zeros() {
        let (q, g) = (&s.offset_drift_mps2_per_c, &s.gain_drift_per_c);
        let _ = write!(
            truth,
            "reference_c = {}\noffset_drift_mps2_per_c = [{}, {}, {}]\n\
             gain_drift_per_c = [{}, {}, {}]\n",
            triax_calibration::sim::REFERENCE_C,
            q.x,
            q.y,
            q.z,
            g.x,
            g.y,
            g.z
        );
    }
    files.push((PathBuf::from("truth.toml"), truth));
    (sim, files)
}

/// Parses a set name for `apply`.
pub fn parse_set(name: &str) -> Result<SetKind, LabError> {
    match name {
        "static" => Ok(SetKind::Static),
        "dynamic" => Ok(SetKind::Dynamic),
        other => Err(LabError::Argument(format!(
            "--set {other}: expected static or dynamic"
        ))),
    }
}

/// A record's issue time must come from the caller (the binary reads the clock).
pub fn default_certificate_id(sensor: &str, version: u64, at: OffsetDateTime) -> String {
    format!(
        "TRIAX-{sensor}-{version}-{:04}{:02}{:02}",
        at.year(),
        u8::from(at.month()),
        at.day()
    )
}
