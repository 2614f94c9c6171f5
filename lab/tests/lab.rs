//! The lab end to end, on simulated benches written to temporary directories.
//!
//! Index:
//! - `fit_*`, `apply_*`: the happy path, record loaded by the gateway's corrector;
//! - `stated_uncertainty_*`: coverage of the true errors at k = 2 on fresh data;
//! - `bad_*`: every kind of bad input gives a message naming file, line and problem, and the
//!   binary writes no output file;
//! - `bundled_sample_data_fits`: lab/data works as shipped.

use std::path::{Path, PathBuf};
use std::process::Command;

use time::OffsetDateTime;
use triax_calibration::corrector::Corrector;
use triax_calibration::fit::ArmAngleUncertainty;
use triax_calibration::sim::{simulate, SensorTruth, SimConfig};
use triax_lab::commands::{run_apply, run_dynamic, run_fit, run_simulate, FitOptions};
use triax_lab::record::RecordMeta;
use triax_protocol::record::{CalibrationRecord, SetKind};
use triax_protocol::{from_json, SensorId};

fn write_sim(dir: &Path, config: &SimConfig) {
    let (_, files) = run_simulate(config);
    for (rel, contents) in files {
        let path = dir.join(rel);
        std::fs::create_dir_all(path.parent().unwrap()).unwrap();
        std::fs::write(path, contents).unwrap();
    }
}

fn short_config(seed: u64, sensor: SensorTruth) -> SimConfig {
    SimConfig {
        seed,
        sensor,
        duration_s: 5.0,
        ..SimConfig::default()
    }
}

fn options(report: bool) -> FitOptions {
    FitOptions {
        gravity_mps2: 9.80665,
        arm: None,
        reference: None,
        points_per_cycle: None,
        report,
        meta: RecordMeta {
            sensor_id: SensorId::new("S1").unwrap(),
            version: 1,
            issued_at: OffsetDateTime::from_unix_timestamp(1_767_225_600).unwrap(),
            lab_name: "test lab".into(),
            certificate_id: "T-1".into(),
            output_unit: "V".into(),
        },
    }
}

#[test]
fn fit_writes_a_record_the_corrector_loads_and_a_report() {
    let dir = tempfile::tempdir().unwrap();
    write_sim(dir.path(), &short_config(11, SensorTruth::paper()));
    let out = run_fit(
        &dir.path().join("static.csv"),
        &dir.path().join("bench.toml"),
        &options(true),
    )
    .unwrap();
    let record: CalibrationRecord = from_json(&out.json).unwrap();
    assert_eq!(record, out.record);
    Corrector::from_record(&record).unwrap();
    assert!(record.static_set.covariance.is_some() && record.dynamic.covariance.is_some());
    assert_eq!(record.static_set.n_points, 10);
    assert_eq!(record.dynamic.domain.frequency_max_hz, 1.6);
    let html = out.report_html.unwrap();
    assert!(html.contains("<svg") && html.contains("Table 1"));
    // The only URL is the SVG namespace, which is a name and never fetched.
    assert!(html
        .replace("http://www.w3.org/2000/svg", "")
        .find("http")
        .is_none());
    assert!(!html.contains("<script"), "no scripts, no network");
    assert!(out.summary.contains("±g check"));
}

#[test]
fn apply_corrects_every_row_with_the_gateway_corrector() {
    let dir = tempfile::tempdir().unwrap();
    write_sim(dir.path(), &short_config(12, SensorTruth::matched()));
    let out = run_fit(
        &dir.path().join("static.csv"),
        &dir.path().join("bench.toml"),
        &options(false),
    )
    .unwrap();
    let record_path = dir.path().join("record.json");
    std::fs::write(&record_path, &out.json).unwrap();
    let input = dir.path().join("recordings/alpha045_1.csv");
    let (csv, rows) = run_apply(&record_path, SetKind::Dynamic, &input).unwrap();
    assert_eq!(rows, 5000);
    let mut lines = csv.lines();
    assert_eq!(lines.next(), Some("t_s,ax,ay,az,ux,uy,uz"));
    let first: Vec<f64> = lines
        .next()
        .unwrap()
        .split(',')
        .map(|x| x.parse().unwrap())
        .collect();
    assert_eq!(first.len(), 7);
    // At α = 45° and rest-ish start, |a| is near g and the uncertainties are small positives.
    assert!(first[4] > 0.0 && first[4] < 1.0);
}

/// Per axis: the fraction of samples whose true error lies within k = 2 stated uncertainties,
/// and the ratio of the RMS stated uncertainty to the RMS true error (1 for an exact
/// statement about normal errors).
fn coverage(sensor: SensorTruth) -> ([f64; 3], [f64; 3]) {
    let cal_dir = tempfile::tempdir().unwrap();
    write_sim(cal_dir.path(), &short_config(21, sensor.clone()));
    let out = run_fit(
        &cal_dir.path().join("static.csv"),
        &cal_dir.path().join("bench.toml"),
        &options(false),
    )
    .unwrap();
    let corrector = Corrector::from_record(&out.record).unwrap();
    let set = corrector.set(SetKind::Dynamic);
    // Fresh data from the same sensor: new noise, new motion phases.
    let fresh = simulate(&short_config(22, sensor));
    let mut inside = [0usize; 3];
    let mut err_sq = [0.0; 3];
    let mut u_sq = [0.0; 3];
    let mut total = 0usize;
    for (rec, truth) in fresh.recordings.iter().zip(&fresh.truth_mps2) {
        for (v, a) in rec.output.iter().zip(truth) {
            let c = set.correct([v.x, v.y, v.z]);
            for axis in 0..3 {
                let err = c.accel_mps2[axis] - a[axis];
                if err.abs() <= 2.0 * c.uncertainty_mps2[axis] {
                    inside[axis] += 1;
                }
                err_sq[axis] += err * err;
                u_sq[axis] += c.uncertainty_mps2[axis].powi(2);
            }
            total += 1;
        }
    }
    (
        inside.map(|n| n as f64 / total as f64),
        [0, 1, 2].map(|k| (u_sq[k] / err_sq[k]).sqrt()),
    )
}

#[test]
fn stated_uncertainty_covers_about_95_percent_of_true_errors() {
    let (cov, ratio) = coverage(SensorTruth::matched());
    eprintln!("eq. (1) sensor: coverage {cov:?}, u/error {ratio:?}");
    for axis in 0..3 {
        assert!(
            (0.93..=0.99).contains(&cov[axis]),
            "axis {axis}: coverage {cov:?}"
        );
        assert!(
            (0.9..=1.3).contains(&ratio[axis]),
            "axis {axis}: u/error {ratio:?}"
        );
    }
}

#[test]
fn stated_uncertainty_still_covers_when_the_sensor_departs_from_eq1() {
    // The paper's sensor answers the varying part with another matrix: the lack-of-fit term
    // must keep the coverage at or above 95 %. The error is then partly systematic and
    // bounded, so k = 2 can cover nearly all of it; the stated uncertainty must still not
    // exceed the RMS error by much.
    let (cov, ratio) = coverage(SensorTruth::paper());
    eprintln!("paper's sensor: coverage {cov:?}, u/error {ratio:?}");
    for axis in 0..3 {
        assert!(
            (0.93..=1.0).contains(&cov[axis]),
            "axis {axis}: coverage {cov:?}"
        );
        assert!(
            (0.9..=1.6).contains(&ratio[axis]),
            "axis {axis}: u/error {ratio:?}"
        );
    }
}

// ---------------------------------------------------------------------------------------------
// Bad input.

fn expect_err(result: Result<impl Sized, triax_lab::LabError>) -> String {
    match result {
        Ok(_) => panic!("bad input accepted"),
        Err(e) => e.to_string(),
    }
}

/// A bench with two short recordings whose CSV text the test can spoil.
fn spoilable_bench(dir: &Path) -> PathBuf {
    write_sim(dir, &short_config(31, SensorTruth::matched()));
    dir.join("bench.toml")
}

fn spoil_recording(dir: &Path, edit: impl Fn(&mut Vec<String>)) -> PathBuf {
    let path = dir.join("recordings/alpha045_1.csv");
    let mut lines: Vec<String> = std::fs::read_to_string(&path)
        .unwrap()
        .lines()
        .map(str::to_string)
        .collect();
    edit(&mut lines);
    std::fs::write(&path, lines.join("\n") + "\n").unwrap();
    path
}

#[test]
fn bad_missing_column_is_named() {
    let dir = tempfile::tempdir().unwrap();
    let bench = spoilable_bench(dir.path());
    spoil_recording(dir.path(), |l| l[0] = "t_s,theta_rad,vx,vy,vw".into());
    let msg = expect_err(run_dynamic(&bench, None, None));
    assert!(msg.contains("alpha045_1.csv, line 1"), "{msg}");
    assert!(msg.contains("missing column(s) vz"), "{msg}");
}

#[test]
fn bad_non_numeric_cell_is_named() {
    let dir = tempfile::tempdir().unwrap();
    let bench = spoilable_bench(dir.path());
    spoil_recording(dir.path(), |l| l[4] = "0.003,0.1,abc,2.4,2.6".into());
    let msg = expect_err(run_dynamic(&bench, None, None));
    assert!(
        msg.contains("alpha045_1.csv, line 5, column vx: 'abc' is not a number"),
        "{msg}"
    );
}

#[test]
fn bad_nan_is_named() {
    let dir = tempfile::tempdir().unwrap();
    let bench = spoilable_bench(dir.path());
    spoil_recording(dir.path(), |l| l[7] = "0.006,NaN,2.4,2.4,2.6".into());
    let msg = expect_err(run_dynamic(&bench, None, None));
    assert!(
        msg.contains("line 8, column theta_rad: 'NaN' is not a finite number"),
        "{msg}"
    );
}

#[test]
fn bad_time_that_does_not_increase_is_named() {
    let dir = tempfile::tempdir().unwrap();
    let bench = spoilable_bench(dir.path());
    spoil_recording(dir.path(), |l| {
        let fields: Vec<String> = l[10].split(',').map(str::to_string).collect();
        l[11] = format!("{},{}", fields[0], fields[1..].join(","));
    });
    let msg = expect_err(run_dynamic(&bench, None, None));
    assert!(msg.contains("alpha045_1.csv, line 12"), "{msg}");
    assert!(msg.contains("time does not increase"), "{msg}");
}

#[test]
fn bad_inconsistent_sample_rate_is_named() {
    let dir = tempfile::tempdir().unwrap();
    let bench = spoilable_bench(dir.path());
    // Drop line 101: one interval of 2 ms among 1 ms ones.
    spoil_recording(dir.path(), |l| {
        l.remove(100);
    });
    let msg = expect_err(run_dynamic(&bench, None, None));
    assert!(msg.contains("alpha045_1.csv, line 101"), "{msg}");
    assert!(msg.contains("inconsistent sample rate"), "{msg}");
}

#[test]
fn bad_too_few_points_is_named() {
    let dir = tempfile::tempdir().unwrap();
    let bench = spoilable_bench(dir.path());
    spoil_recording(dir.path(), |l| l.truncate(801));
    let msg = expect_err(run_dynamic(&bench, None, None));
    assert!(msg.contains("alpha045_1.csv, line 801"), "{msg}");
    assert!(msg.contains("too few points"), "{msg}");
}

#[test]
fn bad_bench_files_are_named_with_their_line() {
    let dir = tempfile::tempdir().unwrap();
    let bench = spoilable_bench(dir.path());
    let text = std::fs::read_to_string(&bench).unwrap();

    std::fs::write(&bench, text.replace("law = \"sine\"", "law = \"sawtooth\"")).unwrap();
    let msg = expect_err(run_dynamic(&bench, None, None));
    assert!(msg.contains("bench.toml, line 9"), "{msg}");
    assert!(msg.contains("'sawtooth' is not supported"), "{msg}");

    std::fs::write(&bench, text.replace("radius_m = 0.1127", "radius_m = ")).unwrap();
    let msg = expect_err(run_dynamic(&bench, None, None));
    assert!(msg.contains("bench.toml, line 2"), "{msg}");

    let spline: String = text
        .lines()
        .map(|l| {
            if l.starts_with("reference =") {
                "reference = \"spline\"\n".to_string()
            } else {
                format!("{l}\n")
            }
        })
        .collect();
    std::fs::write(&bench, spline).unwrap();
    let msg = expect_err(run_dynamic(&bench, None, None));
    assert!(
        msg.contains("line 6") && msg.contains("unknown reference 'spline'"),
        "{msg}"
    );

    std::fs::write(&bench, text.replace("alpha090_2.csv", "missing.csv")).unwrap();
    let msg = expect_err(run_dynamic(&bench, None, None));
    assert!(msg.contains("missing.csv does not exist"), "{msg}");

    let msg = expect_err(run_dynamic(&dir.path().join("nope.toml"), None, None));
    assert!(msg.contains("nope.toml: cannot read"), "{msg}");
}

#[test]
fn bad_single_mount_angle_names_what_is_missing() {
    let dir = tempfile::tempdir().unwrap();
    let bench = spoilable_bench(dir.path());
    let text = std::fs::read_to_string(&bench).unwrap();
    let text = text
        .replace("alpha_deg = 45", "alpha_deg = 0")
        .replace("alpha_deg = 90", "alpha_deg = 0")
        .replace("alpha_deg = 135", "alpha_deg = 0");
    std::fs::write(&bench, text).unwrap();
    let msg = expect_err(run_dynamic(&bench, None, None));
    assert!(msg.contains("another alpha_deg"), "{msg}");
}

#[test]
fn bad_static_file_is_named_and_the_binary_writes_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let bench = spoilable_bench(dir.path());
    let static_csv = dir.path().join("static.csv");
    let text = std::fs::read_to_string(&static_csv).unwrap();
    let mut lines: Vec<&str> = text.lines().collect();
    lines.truncate(4); // header and 3 orientations
    std::fs::write(&static_csv, lines.join("\n")).unwrap();
    let out = dir.path().join("record.json");
    let report = dir.path().join("report.html");
    let run = Command::new(env!("CARGO_BIN_EXE_triax-lab"))
        .args(["fit", "--sensor", "S1", "--static"])
        .arg(&static_csv)
        .arg("--bench")
        .arg(&bench)
        .arg("--out")
        .arg(&out)
        .arg("--report")
        .arg(&report)
        .output()
        .unwrap();
    assert!(!run.status.success());
    let stderr = String::from_utf8_lossy(&run.stderr);
    assert!(
        stderr.contains("static.csv") && stderr.contains("at least 4"),
        "{stderr}"
    );
    assert!(!out.exists() && !report.exists());

    // A header without the reference columns.
    std::fs::write(&static_csv, "vx,vy,vz\n1,2,3\n").unwrap();
    let msg = expect_err(triax_lab::commands::run_static(&static_csv, 9.80665, None));
    assert!(
        msg.contains("static.csv, line 1: missing column(s) ax_ref, ay_ref, az_ref"),
        "{msg}"
    );
}

#[test]
fn bad_apply_input_is_named_and_nothing_is_written() {
    let dir = tempfile::tempdir().unwrap();
    let input = dir.path().join("data.csv");
    std::fs::write(&input, "t_s,vx,vy,vz\n0,1,2,3\n0.001,1,x,3\n").unwrap();
    let record = dir.path().join("record.json");
    std::fs::write(
        &record,
        triax_protocol::to_json_pretty(&triax_protocol::record::sample::record("S1", 1)),
    )
    .unwrap();
    let out = dir.path().join("corrected.csv");
    let run = Command::new(env!("CARGO_BIN_EXE_triax-lab"))
        .args(["apply", "--set", "static", "--record"])
        .arg(&record)
        .arg("--input")
        .arg(&input)
        .arg("--out")
        .arg(&out)
        .output()
        .unwrap();
    assert!(!run.status.success());
    let stderr = String::from_utf8_lossy(&run.stderr);
    assert!(
        stderr.contains("data.csv, line 3, column vy: 'x' is not a number"),
        "{stderr}"
    );
    assert!(!out.exists());
}

#[test]
fn bundled_sample_data_fits() {
    let data = Path::new(env!("CARGO_MANIFEST_DIR")).join("data");
    let out = run_fit(
        &data.join("static.csv"),
        &data.join("bench.toml"),
        &options(false),
    )
    .unwrap();
    Corrector::from_record(&out.record).unwrap();
    // ν and k per set, in the record and in the summary: 10 orientations leave ν = 6, where
    // Student's t says 2.447 at 95 %.
    let r = &out.record;
    assert_eq!(r.static_set.covariance_dof, Some(6.0));
    assert!((r.static_set.coverage_factor - 2.447).abs() < 1e-3);
    assert_eq!(r.static_set.coverage_probability, Some(0.95));
    let nu_d = r.dynamic.covariance_dof.expect("dynamic ν");
    assert!(nu_d > 100.0, "{nu_d}");
    assert!(r.sensor.output_noise_dof.expect("noise ν") > 1000.0);
    assert!(
        out.summary.contains("covariance: ν = 6, k = 2.447 at 95 %"),
        "{}",
        out.summary
    );
    assert!(
        out.summary
            .contains(&format!("covariance: ν = {nu_d:.0}, k = 1.9")),
        "{}",
        out.summary
    );
    assert!(out.summary.contains("only 6 degrees of freedom"));
    // Stating the arm's angle uncertainty pools it in: ν = 6 + 50.
    let pooled = run_fit(
        &data.join("static.csv"),
        &data.join("bench.toml"),
        &FitOptions {
            arm: Some(ArmAngleUncertainty {
                angle_deg: 0.2,
                dof: 50.0,
            }),
            ..options(false)
        },
    )
    .unwrap();
    assert_eq!(pooled.record.static_set.covariance_dof, Some(56.0));
    assert!(!pooled.summary.contains("only"), "{}", pooled.summary);
}

/// Static runs at 6, 21 and 36 °C of a drifting sensor: the record carries a temperature model
/// whose coefficients are the simulator's within 3u, with the reference run's temperature on
/// the certificate, and the gateway's corrector takes it.
#[test]
fn runs_at_several_temperatures_give_a_temperature_model() {
    let dir = tempfile::tempdir().unwrap();
    let config = SimConfig {
        static_temperatures_c: vec![6.0, 21.0, 36.0],
        ..short_config(31, SensorTruth::drifting())
    };
    write_sim(dir.path(), &config);
    let out = run_fit(
        &dir.path().join("static.csv"),
        &dir.path().join("bench.toml"),
        &options(false),
    )
    .unwrap();
    let r = &out.record;
    assert_eq!(r.certificate.temperature_c, Some(21.0));
    let m = r.temperature.as_ref().expect("a temperature model");
    assert_eq!((m.reference_c, m.range_c), (21.0, [6.0, 36.0]));
    let truth = &config.sensor;
    for k in 0..3 {
        let err = m.offset_mps2_per_c[k] - truth.offset_drift_mps2_per_c[k];
        assert!(
            err.abs() < 3.0 * m.covariance[k][k].sqrt(),
            "c_q[{k}] off by {err}"
        );
        let err = m.gain_per_c.unwrap()[k] - truth.gain_drift_per_c[k];
        let u = m.covariance[3 + k][3 + k].sqrt();
        assert!(err.abs() < 3.0 * u, "c_g[{k}] off by {err}");
    }
    assert!(
        out.summary
            .contains("temperature: runs at 6.0 °C (10 rows)"),
        "{}",
        out.summary
    );
    let c = Corrector::from_record(r).unwrap();
    assert!(c.set(SetKind::Static).at_temperature(30.0).is_some());

    // `apply` with a temperature column: the sensor level at 30 °C reads g on z within its
    // interval and unflagged; at 100 °C (beyond one span past 6–36 °C) it is not corrected
    // for temperature and says so.
    let record_path = dir.path().join("record.json");
    std::fs::write(&record_path, &out.json).unwrap();
    let level = nalgebra::Vector3::new(0.0, 0.0, 9.80665);
    let mut input = String::from("t_s,vx,vy,vz,temperature_c\n");
    for (i, t) in [30.0, 100.0].iter().enumerate() {
        let v = truth.output_at(&level, *t);
        input.push_str(&format!("{i},{},{},{},{t}\n", v.x, v.y, v.z));
    }
    let input_path = dir.path().join("warm.csv");
    std::fs::write(&input_path, input).unwrap();
    let (csv, rows) = run_apply(&record_path, SetKind::Static, &input_path).unwrap();
    assert_eq!(rows, 2);
    let lines: Vec<Vec<f64>> = csv
        .lines()
        .skip(1)
        .map(|l| l.split(',').map(|x| x.parse().unwrap()).collect())
        .collect();
    assert!(csv.starts_with("t_s,ax,ay,az,ux,uy,uz,outside_temperature\n"));
    let k = r.static_set.coverage_factor;
    for axis in 0..3 {
        let err = lines[0][1 + axis] - level[axis];
        assert!(err.abs() < k * lines[0][4 + axis], "axis {axis}: {err}");
    }
    assert_eq!((lines[0][7], lines[1][7]), (0.0, 1.0));
}
