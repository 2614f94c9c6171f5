//! Store benchmarks: a gateway's start (open a store of 10 000 sensors × 3 versions and load
//! every current record into a corrector; target under 1 s) and one durable put.
//!
//! Run with `cargo bench -p triax-calibration-store`. The start is measured with records that
//! carry full 12×12 covariances in both sets, as the lab's do (5.4 KiB of compact JSON each,
//! a 370 MB store), and with records without covariance (the cheapest to load).

// A benchmark has nobody to hand an error to: each `expect` stops the run with its message.

use std::hint::black_box;
use std::time::Duration;

use criterion::{criterion_group, criterion_main, BatchSize, Criterion};
use tempfile::TempDir;
use triax_calibration_store::Store;
use triax_protocol::record::{sample, CalibrationRecord, N_PARAMS};

const N_SENSORS: usize = 10_000;
const N_VERSIONS: u64 = 3;

/// A sample record; with `covariance`, a full positive definite covariance in both sets.
fn record(sensor: &str, version: u64, covariance: bool) -> CalibrationRecord {
    let mut r = sample::record(sensor, version);
    if covariance {
        let mut cov = [[0.0; N_PARAMS]; N_PARAMS];
        for (i, row) in cov.iter_mut().enumerate() {
            for (j, c) in row.iter_mut().enumerate() {
                *c = if i == j {
                    1e-6 * (1.0 + i as f64 + version as f64 / 7.0)
                } else {
                    1e-9 / (1.0 + i.abs_diff(j) as f64)
                };
            }
        }
        r.static_set.covariance = Some(Box::new(cov));
        r.dynamic.covariance = Some(Box::new(cov));
    }
    r
}

fn filled_store(covariance: bool) -> TempDir {
    let dir = tempfile::tempdir().expect("temporary directory");
    let store = Store::open(dir.path()).expect("open store");
    let records: Vec<CalibrationRecord> = (1..=N_VERSIONS)
        .flat_map(|v| (0..N_SENSORS).map(move |s| record(&format!("s{s:05}"), v, covariance)))
        .collect();
    let outcomes = store.put_all(&records).expect("fill store");
    assert!(outcomes.iter().all(|o| o.is_ok()));
    dir
}

fn open_and_load(c: &mut Criterion) {
    let mut group = c.benchmark_group("gateway_start");
    group
        .sample_size(10)
        .measurement_time(Duration::from_secs(20));
    for (name, covariance) in [("full_covariance", true), ("no_covariance", false)] {
        let dir = filled_store(covariance);
        group.bench_function(
            format!("open_and_load_10k_sensors_x3_versions/{name}"),
            |b| {
                b.iter(|| {
                    let store = Store::open(dir.path()).expect("open store");
                    let loaded = store.load_current().expect("load current records");
                    assert_eq!(loaded.value.len(), N_SENSORS);
                    assert!(loaded.value.iter().all(|l| l.corrector.is_ok()));
                    black_box(loaded);
                })
            },
        );
    }
    group.finish();
}

fn put_with_flush(c: &mut Criterion) {
    let dir = tempfile::tempdir().expect("temporary directory");
    let store = Store::open(dir.path()).expect("open store");
    let mut version = 0;
    let mut group = c.benchmark_group("put");
    group.sample_size(50);
    group.bench_function("put_with_flush", |b| {
        b.iter_batched(
            || {
                version += 1;
                record("s00001", version, true)
            },
            |r| {
                let outcome = store.put(&r).expect("put");
                assert!(outcome.is_ok());
            },
            BatchSize::SmallInput,
        )
    });
    group.finish();
}

criterion_group!(benches, open_and_load, put_with_flush);
criterion_main!(benches);
