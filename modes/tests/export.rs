//! `triax-modes export`: a modes record as Parquet, read back with pyarrow in the Python that
//! `TRIAX_PYTHON` names (`scripts/test` makes it); without it the test fails and says so.

use std::process::Command;

use time::OffsetDateTime;
use triax_protocol::messages::{
    BuildingModes, ModalDirection, ModalEstimate, ModalVerdict, ModeReport, ModeShapeComponent,
};
use triax_protocol::{BuildingId, SensorId};

fn python() -> String {
    std::env::var("TRIAX_PYTHON").unwrap_or_else(|_| {
        panic!(
            "TRIAX_PYTHON is not set: run the tests with scripts/test, which makes a Python \
             with pyarrow (examples/python/requirements.txt)"
        )
    })
}

fn estimate(value: f64, u: f64, dof: f64) -> ModalEstimate {
    ModalEstimate {
        value,
        standard_uncertainty: u,
        dof,
        coverage_factor: 2.201,
        coverage_probability: 0.95,
    }
}

fn mode(track: Option<u64>, frequency_hz: f64, roof_real: f64, lower_real: f64) -> ModeReport {
    let component = |sensor: &str, real: f64| ModeShapeComponent {
        sensor_id: SensorId::new(sensor).unwrap(),
        direction: ModalDirection::X,
        real: estimate(real, 0.01, 30.0),
        imag: estimate(0.002, 0.004, f64::INFINITY),
        calibration_suspect: false,
    };
    ModeReport {
        track,
        direction: ModalDirection::X,
        frequency_hz: estimate(frequency_hz, 0.0012, 11.0),
        damping_ratio: estimate(0.021, 0.002, 11.0),
        shape: vec![component("roof", roof_real), component("mid", lower_real)],
        reference_component: 0,
        pooled_shape: None,
        order: 24,
        stable_orders: 12,
        replicates: 12,
        predicted_hz: track.map(|_| 1.001),
        residual_relative: track.map(|_| estimate(-0.001, 0.0008, 335.0)),
        verdict: track.map(|_| ModalVerdict::Normal),
        block_mean_relative: None,
        block_verdict: None,
        normal_coverage_factor: None,
        cusum: None,
    }
}

fn window(start_ns: i64, modes: Vec<ModeReport>, refused: Option<&str>) -> BuildingModes {
    BuildingModes {
        format_version: triax_protocol::JSON_FORMAT_VERSION,
        building: BuildingId::new("hq").unwrap(),
        window_start_ns: start_ns,
        window_end_ns: start_ns + 1_800_000_000_000,
        sample_rate_hz: 100.0,
        identification_rate_hz: 25.0,
        sensors: Vec::new(),
        temperature_c: Some(14.5),
        regressors: vec![14.5],
        tracked: refused.is_none(),
        modes,
        unquantified: Vec::new(),
        refused: refused.map(str::to_owned),
        warnings: Vec::new(),
        late: false,
        identified_at: OffsetDateTime::UNIX_EPOCH,
    }
}

const T0: i64 = 1_800_000_000_000_000_000;

#[test]
fn the_modes_record_exports_to_parquet_that_pyarrow_reads_back() {
    let python = python();
    let dir = tempfile::tempdir().unwrap();
    let record = dir.path().join("hq");
    let windows = [
        window(T0, vec![mode(Some(0), 1.0012, 1.0, 0.62)], None),
        window(T0 + 1_800_000_000_000, Vec::new(), Some("too much missing")),
        window(
            T0 + 3_600_000_000_000,
            vec![
                mode(Some(0), 1.0009, 1.0, 0.60),
                mode(None, 2.95, 1.0, -0.8),
            ],
            None,
        ),
    ];
    let mut lines = 0;
    for w in &windows {
        lines = triax_modes::record::append(&record, w, lines, 1000).unwrap();
    }
    // The last window identified twice (a crash before the state was saved): counted once.
    triax_modes::record::append(&record, &windows[2], lines, 1000).unwrap();
    let out = dir.path().join("modes.parquet");
    let run = Command::new(env!("CARGO_BIN_EXE_triax-modes"))
        .args(["export", "--record"])
        .arg(&record)
        .arg("--out")
        .arg(&out)
        .output()
        .unwrap();
    assert!(
        run.status.success(),
        "{}",
        String::from_utf8_lossy(&run.stderr)
    );
    assert!(String::from_utf8_lossy(&run.stdout).starts_with("3 modes written"));

    let script = r#"
import json, sys
import pyarrow.parquet as pq
f = pq.ParquetFile(sys.argv[1])
t = f.read()
meta = {k.decode(): v.decode() for k, v in f.schema_arrow.metadata.items() if k.startswith(b"triax")}
rows = t.to_pylist()
for r in rows:
    for k in ("window_start", "window_end"):
        r[k] = int(r[k].timestamp() * 1e9) if r[k] is not None else None
print(json.dumps({"meta": meta, "types": {n: str(t.schema.field(n).type) for n in t.column_names}, "rows": rows}), flush=True)
# pyarrow 18 can abort in the interpreter's teardown, after the work is done and printed
# (apache/arrow#34314): leave before it, so only the script's own errors fail the run.
import os
os._exit(0)
"#;
    let read = Command::new(&python)
        .arg("-c")
        .arg(script)
        .arg(&out)
        .output()
        .unwrap_or_else(|e| panic!("cannot run {python}: {e}"));
    assert!(
        read.status.success(),
        "pyarrow could not read the export: {}",
        String::from_utf8_lossy(&read.stderr)
    );
    let v: serde_json::Value = serde_json::from_slice(&read.stdout).unwrap();
    assert_eq!(v["meta"]["triax.format"], "triax-building-modes/1");
    assert_eq!(v["types"]["window_start"], "timestamp[ns, tz=UTC]");
    assert_eq!(v["types"]["shape_real"], "list<element: double not null>");
    let rows = v["rows"].as_array().unwrap();
    assert_eq!(
        rows.len(),
        3,
        "one row per mode; the refused window has none"
    );
    let first = &rows[0];
    assert_eq!(first["building"], "hq");
    assert_eq!(first["track"], 0);
    assert_eq!(first["direction"], "x");
    assert_eq!(first["frequency_hz"], 1.0012);
    assert_eq!(first["frequency_u_hz"], 0.0012);
    assert_eq!(first["frequency_dof"], 11.0);
    assert_eq!(first["frequency_k"], 2.201);
    assert_eq!(first["damping_ratio"], 0.021);
    assert_eq!(first["coverage_probability"], 0.95);
    assert_eq!(
        first["mac_previous"],
        serde_json::Value::Null,
        "a track's first window"
    );
    assert_eq!(first["temperature_c"], 14.5);
    assert_eq!(first["predicted_hz"], 1.001);
    assert_eq!(first["residual_relative"], -0.001);
    assert_eq!(first["verdict"], "normal");
    assert_eq!(first["block_verdict"], serde_json::Value::Null);
    assert_eq!(first["reference_sensor"], "roof");
    assert_eq!(first["shape_sensor"], serde_json::json!(["roof", "mid"]));
    assert_eq!(first["shape_real"], serde_json::json!([1.0, 0.62]));
    assert_eq!(first["shape_real_u"], serde_json::json!([0.01, 0.01]));
    assert_eq!(first["shape_imag"], serde_json::json!([0.002, 0.002]));
    assert_eq!(first["late"], false);
    let expected_start = T0 as f64;
    assert!((first["window_start"].as_f64().unwrap() - expected_start).abs() < 1e3);
    let second = &rows[1];
    // MAC of (1, 0.60) with (1, 0.62).
    let mac = (1.0f64 + 0.6 * 0.62).powi(2) / ((1.0 + 0.36) * (1.0 + 0.62 * 0.62));
    assert!((second["mac_previous"].as_f64().unwrap() - mac).abs() < 1e-12);
    let third = &rows[2];
    assert_eq!(third["track"], serde_json::Value::Null);
    assert_eq!(third["verdict"], serde_json::Value::Null);
    assert_eq!(third["shape_real"], serde_json::json!([1.0, -0.8]));

    // An empty record is an error that says where it looked.
    let empty = dir.path().join("empty");
    std::fs::create_dir_all(&empty).unwrap();
    let run = Command::new(env!("CARGO_BIN_EXE_triax-modes"))
        .args(["export", "--record"])
        .arg(&empty)
        .arg("--out")
        .arg(dir.path().join("none.parquet"))
        .output()
        .unwrap();
    assert!(!run.status.success());
    assert!(String::from_utf8_lossy(&run.stderr).contains("modes.jsonl"));
    assert!(!dir.path().join("none.parquet").exists());
}
