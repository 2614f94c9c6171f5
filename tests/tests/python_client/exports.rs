//! `triax-export` as its users run it, read back with their own tools: a building with a
//! recalibration mid-stream (the new record's `valid_from` 20 s before its push), a gap, a
//! non-finite sample, a duplicate batch, an uncalibrated sensor and a UTC midnight inside the
//! data; Parquet read with pandas and DuckDB, the SDS tree and its StationXML with ObsPy
//! (schema, `attach_response` through `remove_response`, epochs against each sample's
//! version); every documented error and exit status; and files that are whole or absent when
//! an export fails or is killed.

use std::collections::BTreeMap;
use std::ffi::OsStr;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Duration;

use serde_json::Value;
use triax_client::export::{self, Cli, ExportError, Summary};
use triax_lab::push::{push_one, Push};
use triax_protocol::record::{sample, CalibrationRecord};
use triax_protocol::signing::LabSigningKey;
use triax_protocol::{to_json, BuildingId, CorrectedBatch, RawBatch, SensorId};

use super::{python_interpreter, run_pyarrow_script, util};

/// 2027-01-15T23:59:30Z: the stream crosses UTC midnight 30 s in.
const T0_NS: i64 = 1_800_057_570_000_000_000;
const PER_BATCH: usize = 50;
const BATCH_NS: i64 = 500_000_000;
/// Batches before the push of version 2, and in all.
const BEFORE_PUSH: u64 = 80;
const ALL: u64 = 120;
const GAP_AT: u64 = 20;
const DUPLICATED: u64 = 30;
const NAN_AT: (u64, usize) = (7, 3);

fn raw_at(sensor: &str, seq: u64) -> Vec<u8> {
    let samples = (0..PER_BATCH)
        .map(|i| {
            if (seq, i) == NAN_AT {
                return [f32::NAN, 0.0, 0.98];
            }
            let t = (seq as usize * PER_BATCH + i) as f32 / 100.0;
            [
                0.02 * (7.0 * t).sin(),
                0.01 * (3.0 * t).cos(),
                0.98 + 0.001 * (11.0 * t).sin(),
            ]
        })
        .collect();
    RawBatch {
        header: triax_protocol::batch::BatchHeader {
            sensor_id: SensorId::new(sensor).unwrap(),
            sequence: seq,
            timestamp_ns: T0_NS + seq as i64 * BATCH_NS,
            sample_rate_hz: 100.0,
        },
        temperature_c: None,
        samples,
    }
    .encode()
}

/// Runs `triax-export` with these arguments (after the program name).
async fn run(args: &[&str]) -> Result<Summary, ExportError> {
    let cli = Cli::try_from_args(std::iter::once("triax-export").chain(args.iter().copied()))
        .unwrap_or_else(|e| panic!("{args:?}: {e}"));
    export::run(cli).await
}

/// The building of this module's tests: its gateway, a session, the records, the history.
struct Building {
    gw: util::Running,
    session: zenoh::Session,
    records_dir: PathBuf,
    /// `ex-1`'s history as the gateway replays it, in arrival order.
    history: Vec<CorrectedBatch>,
    v2: CalibrationRecord,
}

async fn building(dir: &Path) -> Building {
    let key = LabSigningKey::from_bytes(&[7; 32]);
    let store = dir.join("store");
    let v1 = sample::record("ex-1", 1);
    util::seed_store(&store, std::slice::from_ref(&v1));
    let mut cfg = util::config("ex", &store);
    cfg.calibration.trusted_lab_keys = vec![key.verifying_key()];
    let gw = util::start(cfg).await;
    let session = util::client(&gw.endpoint).await;
    let node = util::blocking_publisher(&session, util::key_raw("ex", "ex-1")).await;
    let raw_node = util::blocking_publisher(&session, util::key_raw("ex", "ex-raw")).await;
    for seq in (0..BEFORE_PUSH).filter(|&s| s != GAP_AT) {
        node.put(raw_at("ex-1", seq)).await.unwrap();
        if seq == DUPLICATED {
            node.put(raw_at("ex-1", seq)).await.unwrap();
        }
    }
    for seq in 0..10 {
        raw_node.put(raw_at("ex-raw", seq)).await.unwrap();
    }
    util::wait_history_holds(&session, "ex", "ex-1", BEFORE_PUSH - 1).await;
    util::wait_history_holds(&session, "ex", "ex-raw", 9).await;
    // Version 2, valid from 20 s before the instant the data switch to it.
    let mut v2 = sample::record("ex-1", 2);
    v2.valid_from = time::OffsetDateTime::from_unix_timestamp_nanos(i128::from(
        T0_NS + BEFORE_PUSH as i64 * BATCH_NS - 20_000_000_000,
    ))
    .unwrap();
    let report = push_one(
        &session,
        &BuildingId::new("ex").unwrap(),
        &Push::sign(&v2, &key),
        util::TIMEOUT,
    )
    .await
    .unwrap();
    assert!(report.is_success(1), "{report:?}");
    for seq in BEFORE_PUSH..ALL {
        node.put(raw_at("ex-1", seq)).await.unwrap();
    }
    util::wait_history_holds(&session, "ex", "ex-1", ALL - 1).await;
    let records_dir = dir.join("records");
    std::fs::create_dir_all(&records_dir).unwrap();
    for r in [&v1, &v2] {
        std::fs::write(
            records_dir.join(format!("ex-1.v{}.json", r.version)),
            to_json(r),
        )
        .unwrap();
    }
    let mut history = Vec::new();
    triax_client::history::fetch(
        &session,
        &triax_client::HistoryRequest::sensor(
            &BuildingId::new("ex").unwrap(),
            &SensorId::new("ex-1").unwrap(),
        ),
        util::TIMEOUT,
        &mut |r| history.push(r.batch),
    )
    .await
    .unwrap();
    assert_eq!(
        history.len() as u64,
        ALL,
        "all but the gap, the duplicate once more"
    );
    let versions: Vec<u64> = history.iter().map(|b| b.info.calibration_version).collect();
    assert!(
        versions.contains(&1) && versions.contains(&2),
        "{versions:?}"
    );
    Building {
        gw,
        session,
        records_dir,
        history,
        v2,
    }
}

/// Reads the exports as their users would and prints what it found as JSON: the Parquet file
/// with pandas and DuckDB; the SDS tree with ObsPy's SDS client and the StationXML with
/// `read_inventory`, validated against the FDSN schema ObsPy ships, responses attached and
/// removed, and each EN1 sample of location 00 matched to the epochs that contain it.
const READ_EXPORTS: &str = r#"
import json, sys, warnings
import numpy as np
import pandas as pd
import duckdb
from obspy import read_inventory, UTCDateTime
from obspy.clients.filesystem.sds import Client
from obspy.io.stationxml.core import validate_stationxml
pq, root, xml, net, sta, t1, t2 = sys.argv[1:8]
df = pd.read_parquet(pq, engine="pyarrow")
con = duckdb.connect()
non_finite = con.execute(f"SELECT count(*) FROM read_parquet('{pq}') WHERE flags & 32 <> 0").fetchone()[0]
gap_rows = con.execute(f"SELECT count(*) FROM read_parquet('{pq}') WHERE flags & 16 <> 0").fetchone()[0]
by_version = dict(con.execute(
    f"SELECT calibration_version, count(*) FROM read_parquet('{pq}') GROUP BY 1").fetchall())
valid, errors = validate_stationxml(xml)
inv = read_inventory(xml)
st = Client(root).get_waveforms(net, sta, "*", "*", UTCDateTime(t1), UTCDateTime(t2))
st.attach_response(inv)
removed = []
for tr in st.select(location="00"):
    a = tr.copy().remove_sensitivity()
    b = tr.copy()
    b.data = b.data.astype(np.float64)
    b.remove_response(output="ACC", zero_mean=False, taper=False, water_level=None)
    finite = np.isfinite(tr.data)
    # ObsPy's deconvolution always zeroes the (zero-padded) spectrum's DC bin, which shifts
    # every sample by one constant: a unity response leaves the data otherwise as they are.
    diff = b.data - tr.data.astype(np.float64)
    removed.append({
        "id": tr.id,
        "sensitivity_same": bool(np.array_equal(a.data[finite], tr.data[finite])),
        "response_max_diff": float(np.max(np.abs(diff - np.mean(diff)))) if finite.all() else None,
    })
epochs = []
for cha in inv.select(station=sta, location="00", channel="EN1")[0][0]:
    version = [int(c.value.split("calibration version ")[1].split(",")[0])
               for c in cha.comments if "calibration version " in c.value][0]
    epochs.append((cha.start_date.ns, cha.end_date.ns if cha.end_date else None, version))
matched = []
for tr in st.select(location="00", channel="EN1"):
    start = tr.stats.starttime.ns
    step = int(round(1e9 / tr.stats.sampling_rate))
    for j in range(tr.stats.npts):
        t = start + j * step
        vs = [v for (s, e, v) in epochs if s <= t and (e is None or t <= e)]
        matched.append([t, vs])
traces = [{"id": tr.id, "start_ns": tr.stats.starttime.ns, "npts": tr.stats.npts,
           "data": (tr.data.view(np.uint32) if tr.data.dtype == np.float32 else tr.data).astype(np.int64).tolist()}
          for tr in st]
print(json.dumps({
    "rows": len(df), "non_finite": non_finite, "gap_rows": gap_rows,
    "by_version": {str(k): v for k, v in by_version.items()},
    "stationxml_valid": valid, "stationxml_errors": [str(e) for e in errors][:5],
    "removed": removed, "epochs": epochs, "matched": matched, "traces": traces,
    "stations": sorted({tr.stats.station for tr in st}),
}))
"#;

fn strs(v: &[String]) -> Vec<&str> {
    v.iter().map(String::as_str).collect()
}

/// Every file under `root` with its bytes.
fn tree(root: &Path) -> BTreeMap<PathBuf, Vec<u8>> {
    let mut out = BTreeMap::new();
    let mut dirs = vec![root.to_path_buf()];
    while let Some(d) = dirs.pop() {
        for e in std::fs::read_dir(&d).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() {
                dirs.push(p);
            } else {
                out.insert(
                    p.strip_prefix(root).unwrap().to_path_buf(),
                    std::fs::read(&p).unwrap(),
                );
            }
        }
    }
    out
}

#[tokio::test(flavor = "multi_thread")]
async fn exports_are_exactly_right_in_the_users_tools() {
    let py = python_interpreter();
    let dir = tempfile::tempdir().unwrap();
    let b = building(dir.path()).await;
    let endpoint = b.gw.endpoint.clone();
    let common = |out: &Path| -> Vec<String> {
        [
            "--connect",
            endpoint.as_str(),
            "--no-multicast-scouting",
            "--building",
            "ex",
            "--timeout-s",
            "30",
            "--out",
            out.to_str().unwrap(),
        ]
        .map(str::to_owned)
        .to_vec()
    };
    let argv = |format: &str, out: &Path, more: &[&str]| -> Vec<String> {
        let mut v = vec![format.to_owned()];
        v.extend(common(out));
        v.extend(more.iter().map(|s| s.to_string()));
        v
    };

    // Parquet of ex-1 and SDS of the whole building, with the records for StationXML.
    let pq = dir.path().join("ex-1.parquet");
    let summary = run(&strs(&argv("parquet", &pq, &["--sensor", "ex-1"])))
        .await
        .unwrap();
    assert_eq!(summary.samples, ALL * PER_BATCH as u64);
    // Readable by others, as a file written directly would be (not a temporary file's 0600).
    {
        use std::os::unix::fs::PermissionsExt;
        let mode = std::fs::metadata(&pq).unwrap().permissions().mode() & 0o777;
        assert_eq!(mode, 0o644, "{mode:o}");
    }
    let root = dir.path().join("sds");
    let records = b.records_dir.to_str().unwrap().to_owned();
    let sds_args = argv("sds", &root, &["--records", &records]);
    let summary = run(&strs(&sds_args)).await.unwrap();
    let notes = summary.notes.join("\n");
    assert!(
        notes.contains("ex-raw: 500 uncalibrated samples"),
        "{notes}"
    );
    assert!(notes.contains("ex-1: 1 batches left out"), "{notes}");
    let xml = root.join("XX.ex.xml");

    // Item 8: the same export again leaves the archive as it was.
    let once = tree(&root);
    run(&strs(&sds_args)).await.unwrap();
    let twice = tree(&root);
    let days: Vec<_> = once.keys().filter(|p| !p.ends_with("XX.ex.xml")).collect();
    assert_eq!(days.len(), 18, "nine channels over two days: {days:?}");
    for p in days {
        assert_eq!(
            once[p],
            twice[p],
            "{} changed on a second export",
            p.display()
        );
    }

    let args = [
        pq.as_os_str(),
        root.as_os_str(),
        xml.as_os_str(),
        OsStr::new("XX"),
        OsStr::new("EX1"),
        OsStr::new("2027-01-15T23:00:00Z"),
        OsStr::new("2027-01-16T01:00:00Z"),
    ];
    let out = run_pyarrow_script(&py, READ_EXPORTS, &args);
    assert!(
        out.status.success(),
        "the users' tools could not read the exports: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    let v: Value = serde_json::from_slice(&out.stdout).expect("python prints JSON");

    // Item 1: each Parquet row its own sample's flags.
    assert_eq!(v["rows"].as_u64(), Some(ALL * PER_BATCH as u64));
    assert_eq!(
        v["non_finite"].as_u64(),
        Some(1),
        "one non-finite sample, one row"
    );
    // The batch after the hole and both copies of the duplicate's batch begin with a flag.
    assert_eq!(v["gap_rows"].as_u64(), Some(1));
    let expected_by_version = |version: u64| {
        b.history
            .iter()
            .filter(|x| x.info.calibration_version == version)
            .map(|x| x.samples.len() as u64)
            .sum::<u64>()
    };
    assert_eq!(v["by_version"]["1"].as_u64(), Some(expected_by_version(1)));
    assert_eq!(v["by_version"]["2"].as_u64(), Some(expected_by_version(2)));

    // Item 4: the uncalibrated sensor is not in the SDS tree as m/s².
    assert_eq!(v["stations"], serde_json::json!(["EX1"]));

    // Item 3: ObsPy's response workflow, on a valid document.
    assert_eq!(v["stationxml_valid"], true, "{}", v["stationxml_errors"]);
    for r in v["removed"].as_array().unwrap() {
        assert_eq!(r["sensitivity_same"], true, "{r}");
        if let Some(d) = r["response_max_diff"].as_f64() {
            assert!(d < 1e-5, "{r}");
        }
    }

    // Item 2: every sample lies in exactly one epoch, that of the version that corrected it.
    let mut version_at: BTreeMap<i64, u64> = BTreeMap::new();
    let mut value_at: BTreeMap<i64, u32> = BTreeMap::new();
    let mut seen = std::collections::BTreeSet::new();
    for x in &b.history {
        if !seen.insert(x.header.sequence) {
            continue; // the duplicate: left out of miniSEED
        }
        for (i, s) in x.samples.iter().enumerate() {
            let t_ms = (x.header.timestamp_ns + i as i64 * 10_000_000) / 1_000_000;
            version_at.insert(t_ms, x.info.calibration_version);
            value_at.insert(t_ms, s.accel_mps2[0].to_bits());
        }
    }
    let matched = v["matched"].as_array().unwrap();
    assert_eq!(matched.len(), version_at.len(), "each instant once");
    for m in matched {
        let t_ms = (m[0].as_i64().unwrap() + 500_000) / 1_000_000;
        let versions: Vec<u64> = m[1]
            .as_array()
            .unwrap()
            .iter()
            .map(|x| x.as_u64().unwrap())
            .collect();
        assert_eq!(versions, vec![version_at[&t_ms]], "sample at {t_ms} ms");
    }
    // The epochs cut where the data switched, not at version 2's valid_from.
    let switch_ns = b
        .history
        .iter()
        .find(|x| x.info.calibration_version == 2)
        .unwrap()
        .header
        .timestamp_ns;
    let epochs = v["epochs"].as_array().unwrap();
    let v2_start = epochs.iter().find(|e| e[2].as_u64() == Some(2)).unwrap()[0]
        .as_i64()
        .unwrap();
    assert_eq!(v2_start, switch_ns);
    assert!(v2_start > b.v2.valid_from.unix_timestamp_nanos() as i64 + 19_000_000_000);
    // Values bit for bit at their instants, across midnight.
    for tr in v["traces"].as_array().unwrap() {
        if tr["id"] != "XX.EX1.00.EN1" {
            continue;
        }
        let start = tr["start_ns"].as_i64().unwrap();
        for (j, d) in tr["data"].as_array().unwrap().iter().enumerate() {
            let t_ms = (start + j as i64 * 10_000_000 + 500_000) / 1_000_000;
            assert_eq!(
                d.as_u64(),
                Some(u64::from(value_at[&t_ms])),
                "x at {t_ms} ms"
            );
        }
    }

    // Items 6, 11, 12: every error named, with its exit status, and no file written.
    let nothing = dir.path().join("nothing.parquet");
    let fails = [
        (
            argv("parquet", &nothing, &[])
                .into_iter()
                .map(|a| if a == "ex" { "nope".into() } else { a })
                .collect::<Vec<_>>(),
            "no gateway of building nope answered",
            1,
        ),
        (
            argv("parquet", &nothing, &["--sensor", "ghost"]),
            "sensor ghost: the history of building ex holds nothing of it",
            1,
        ),
        (
            argv(
                "parquet",
                &nothing,
                &[
                    "--from",
                    "2027-01-16T00:00:10Z",
                    "--to",
                    "2027-01-16T00:00:00Z",
                ],
            ),
            "--from 2027-01-16T00:00:10Z is after --to 2027-01-16T00:00:00Z",
            1,
        ),
        (
            argv("parquet", &nothing, &["--from", "2030-01-01T00:00:00Z"]),
            "nothing kept in building ex's history for sensor * from 2030-01-01T00:00:00Z",
            export::EXIT_EMPTY,
        ),
        (
            argv(
                "sds",
                &dir.path().join("nothing-sds"),
                &["--from", "2030-01-01T00:00:00Z"],
            ),
            "nothing kept",
            export::EXIT_EMPTY,
        ),
        (
            argv("parquet", &nothing, &["--calibration", "soon"]),
            "--calibration \"soon\"",
            1,
        ),
    ];
    for (args, says, code) in &fails {
        let e = run(&strs(args)).await.unwrap_err();
        assert!(e.to_string().contains(says), "{args:?}: {e}");
        assert_eq!(e.exit_code(), *code, "{args:?}: {e}");
    }
    assert!(!nothing.exists());
    assert!(!dir.path().join("nothing-sds").join("2030").exists());
    // An endpoint nobody listens on: named, without a source path.
    let port = util::free_port();
    let e = run(&[
        "parquet",
        "--connect",
        &format!("tcp/127.0.0.1:{port}"),
        "--building",
        "ex",
        "--out",
        nothing.to_str().unwrap(),
    ])
    .await
    .unwrap_err();
    assert!(e.to_string().contains(&format!("127.0.0.1:{port}")), "{e}");
    assert!(!e.to_string().contains(".rs:"), "{e}");
    // The shared Zenoh options: a configuration file alone reaches the gateway.
    let conf = dir.path().join("zenoh.json5");
    std::fs::write(
        &conf,
        format!(
            "{{ mode: \"client\", connect: {{ endpoints: [\"{endpoint}\"] }}, \
             scouting: {{ multicast: {{ enabled: false }} }} }}"
        ),
    )
    .unwrap();
    let via_file = dir.path().join("via-file.parquet");
    run(&[
        "parquet",
        "--zenoh-config",
        conf.to_str().unwrap(),
        "--building",
        "ex",
        "--sensor",
        "ex-1",
        "--out",
        via_file.to_str().unwrap(),
    ])
    .await
    .unwrap();
    assert_eq!(
        std::fs::read(&via_file).unwrap().len(),
        std::fs::read(&pq).unwrap().len()
    );

    // Item 7: a failed export leaves the earlier file as it was.
    let before = std::fs::read(&pq).unwrap();
    let e = run(&strs(&argv("parquet", &pq, &["--calibration", "99"])))
        .await
        .unwrap_err();
    assert!(e.to_string().contains("no version 99"), "{e}");
    assert_eq!(std::fs::read(&pq).unwrap(), before);
    let partials: Vec<_> = std::fs::read_dir(dir.path())
        .unwrap()
        .filter_map(|e| e.ok())
        .filter(|e| e.file_name().to_string_lossy().ends_with(".partial"))
        .collect();
    assert!(partials.is_empty(), "{partials:?}");

    b.session.close().await.unwrap();
    b.gw.stop().await;
}

const CHILD_ENV: [&str; 3] = [
    "TRIAX_TEST_EXPORT_ENDPOINT",
    "TRIAX_TEST_EXPORT_OUT",
    "TRIAX_TEST_EXPORT_BUILDING",
];

/// Not a test: an export in a process of its own, started and killed by
/// `a_killed_export_leaves_the_earlier_file_whole`.
#[test]
#[ignore = "a child process entry point, started by the kill test"]
fn export_process() {
    let [endpoint, out, building] =
        CHILD_ENV.map(|k| std::env::var(k).unwrap_or_else(|_| panic!("{k} is set by the parent")));
    let code = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .unwrap()
        .block_on(export::main(
            [
                "triax-export",
                "parquet",
                "--connect",
                &endpoint,
                "--building",
                &building,
                "--out",
                &out,
            ]
            .map(std::ffi::OsString::from),
        ));
    std::process::exit(i32::from(code));
}

/// SIGKILL at any moment of a Parquet export never damages the file it replaces: each kill
/// leaves either the earlier file or the complete new one, never a truncated one.
#[tokio::test(flavor = "multi_thread")]
async fn a_killed_export_leaves_the_earlier_file_whole() {
    let py = python_interpreter();
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("store");
    util::seed_store(&store, &[sample::record("kx-1", 1)]);
    let gw = util::start(util::config("kx", &store)).await;
    let session = util::client(&gw.endpoint).await;
    let node = util::blocking_publisher(&session, util::key_raw("kx", "kx-1")).await;
    let batches = 2000u64;
    for seq in 0..batches {
        node.put(util::raw("kx-1", seq, vec![[0.1, 0.2, 0.98]; 100]))
            .await
            .unwrap();
    }
    util::wait_history_holds(&session, "kx", "kx-1", batches - 1).await;
    // A whole export holds what the history holds: under drop-oldest, a gateway sent a burst
    // this size at once may have dropped some of it (counted in its status).
    let mut kept = 0u64;
    triax_client::history::fetch(
        &session,
        &triax_client::HistoryRequest::sensor(
            &triax_protocol::BuildingId::new("kx").unwrap(),
            &triax_protocol::SensorId::new("kx-1").unwrap(),
        ),
        util::TIMEOUT,
        &mut |_| kept += 1,
    )
    .await
    .unwrap();
    // Nothing is lost silently: what the history lacks is what the gateway counted dropped.
    let dropped = util::status(&session, "kx").await.dropped;
    assert_eq!(
        kept + dropped,
        batches,
        "the history holds {kept} of {batches} batches, {dropped} counted dropped"
    );
    assert!(kept > 0);
    let out = dir.path().join("kx.parquet");
    let earlier = b"an earlier export".to_vec();
    let rows = |path: &Path| -> Option<u64> {
        let o = run_pyarrow_script(
            &py,
            "import sys, pyarrow.parquet as pq; print(pq.read_metadata(sys.argv[1]).num_rows)",
            &[path.as_os_str()],
        );
        o.status
            .success()
            .then(|| String::from_utf8_lossy(&o.stdout).trim().parse().unwrap())
    };
    let mut outcomes = BTreeMap::new();
    for delay_ms in [0u64, 30, 60, 100, 150, 250, 400, 700, 1000, 3000] {
        std::fs::write(&out, &earlier).unwrap();
        let mut child = Command::new(std::env::current_exe().unwrap())
            .args([
                "--ignored",
                "--exact",
                "exports::export_process",
                "--nocapture",
            ])
            .env(CHILD_ENV[0], &gw.endpoint)
            .env(CHILD_ENV[1], &out)
            .env(CHILD_ENV[2], "kx")
            .stdout(std::process::Stdio::null())
            .stderr(std::process::Stdio::null())
            .spawn()
            .unwrap();
        tokio::time::sleep(Duration::from_millis(delay_ms)).await;
        let _ = child.kill();
        let _ = child.wait();
        let now = std::fs::read(&out).unwrap();
        let outcome = if now == earlier {
            "earlier"
        } else {
            assert_eq!(
                rows(&out),
                Some(kept * 100),
                "killed after {delay_ms} ms: the file is neither the earlier one nor whole"
            );
            "complete"
        };
        *outcomes.entry(outcome).or_insert(0) += 1;
    }
    println!("after a kill: {outcomes:?}");
    session.close().await.unwrap();
    gw.stop().await;
}

/// Export speed, for BENCHMARKS.md: 10⁶ calibrated samples (10 000 batches of 100) in a
/// gateway's history, exported to Parquet, to a fresh SDS tree, and to the same tree again
/// (the merge path); each three times, timed whole (history query, Zenoh transfer, files).
/// `cargo test --release -p triax-tests --test python_client -- --ignored export_speed
/// --nocapture`.
#[tokio::test(flavor = "multi_thread")]
#[ignore = "a benchmark: BENCHMARKS.md quotes it"]
async fn export_speed() {
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("store");
    util::seed_store(&store, &[sample::record("sp-1", 1)]);
    let gw = util::start(util::config("sp", &store)).await;
    let session = util::client(&gw.endpoint).await;
    let node = util::blocking_publisher(&session, util::key_raw("sp", "sp-1")).await;
    let batches = 10_000u64;
    for seq in 0..batches {
        let samples = (0..100)
            .map(|i| {
                let t = (seq * 100 + i) as f32 / 100.0;
                [0.02 * (7.0 * t).sin(), 0.01 * (3.0 * t).cos(), 0.98]
            })
            .collect();
        node.put(util::raw("sp-1", seq, samples)).await.unwrap();
    }
    util::wait_history_holds(&session, "sp", "sp-1", batches - 1).await;
    let endpoint = gw.endpoint.clone();
    let timed = |args: Vec<String>| async move {
        let started = std::time::Instant::now();
        let s = run(&strs(&args)).await.unwrap();
        assert_eq!(s.samples, batches * 100);
        started.elapsed().as_secs_f64()
    };
    let common = |format: &str, out: &Path| -> Vec<String> {
        [
            format,
            "--connect",
            &endpoint,
            "--building",
            "sp",
            "--out",
            out.to_str().unwrap(),
        ]
        .map(str::to_owned)
        .to_vec()
    };
    let mut rows = Vec::new();
    for i in 0..3 {
        let pq = timed(common("parquet", &dir.path().join("sp.parquet"))).await;
        let fresh_root = dir.path().join(format!("sds-{i}"));
        let fresh = timed(common("sds", &fresh_root)).await;
        let again = timed(common("sds", &fresh_root)).await;
        rows.push((pq, fresh, again));
    }
    let bytes = std::fs::metadata(dir.path().join("sp.parquet"))
        .unwrap()
        .len();
    for (pq, fresh, again) in &rows {
        println!(
            "per 10⁶ samples: parquet {pq:.2} s, sds fresh {fresh:.2} s, sds again {again:.2} s"
        );
    }
    println!("parquet: {:.1} bytes a sample", bytes as f64 / 1e6);
    session.close().await.unwrap();
    gw.stop().await;
}
