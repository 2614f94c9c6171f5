//! History queries on one core, from a warm page cache: the replay of one sensor's kept batches
//! (scan from the checkpoint, read and check each block, correct every batch again through the
//! live path's own function), without the Zenoh transport of the replies.
//!
//! - `replay/<n>-sample batches`: a sensor's 20 minutes at 100 Hz kept among 10 sensors,
//!   checkpoints every 60 s, read back whole with `calibration=in_force`; throughput in samples.
//!
//! Run: `cargo bench -p triax-gateway --bench replay`.

use std::sync::Arc;

use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use triax_calibration::corrector::Corrector;
use triax_calibration_store::Store;
use triax_gateway::sample_path::{correct_judged, Recorder, Scratch, SensorKernel};
use triax_gateway::services::replay::{replay, HistoryQuery, ReplayContext};
use triax_gateway::{Config, SensorTable};
use triax_history::{History, HistoryConfig, Kept, Verdict};
use triax_protocol::batch::{BatchHeader, RawBatch};
use triax_protocol::record::sample;
use triax_protocol::{BuildingId, InlineId, RawBatchView, SensorId};

const SECONDS: u64 = 1200;
const SENSORS: usize = 10;

struct Fixture {
    _dir: tempfile::TempDir,
    ctx: ReplayContext,
    _recorder: Recorder,
}

/// Keeps `SECONDS` of every sensor's stream as the gateway would: the live kernel corrects each
/// batch and a checkpoint is kept before the first batch of every minute.
fn fixture(n: usize) -> Fixture {
    let dir = tempfile::tempdir().expect("tempdir");
    let store = Store::open(dir.path().join("store")).expect("store");
    let config = Arc::new(Config::for_tests("b", &dir.path().join("store"), vec![]));
    let mut h = HistoryConfig::new(dir.path().join("history"));
    h.max_bytes = u64::MAX;
    let opened = History::open(h).expect("history");
    let mut writer = opened.writer;
    let ids: Vec<SensorId> = (0..SENSORS)
        .map(|i| SensorId::new(format!("s{i}")).expect("id"))
        .collect();
    for id in &ids {
        store
            .put(&sample::record(id.as_str(), 1))
            .expect("store")
            .expect("accepted");
    }
    let corrector = Corrector::from_record(&sample::record("s0", 1)).expect("loads");
    let per_second = 100 / n as u64;
    let mut kernels: Vec<SensorKernel> = ids
        .iter()
        .map(|id| SensorKernel::new(config.sensor(id.as_str()).clone()))
        .collect();
    let (mut scratch, mut out, mut ck) = (Scratch::default(), Vec::new(), Vec::new());
    for seq in 0..SECONDS * per_second {
        for (id, kernel) in ids.iter().zip(&mut kernels) {
            let batch = RawBatch {
                header: BatchHeader {
                    sensor_id: id.clone(),
                    sequence: seq,
                    timestamp_ns: 1_800_000_000_000_000_000 + (seq * n as u64) as i64 * 10_000_000,
                    sample_rate_hz: 100.0,
                },
                temperature_c: None,
                samples: (0..n)
                    .map(|i| {
                        let t = (seq as usize * n + i) as f32 / 100.0;
                        [0.02 * (8.0 * t).sin(), 0.001, 0.98]
                    })
                    .collect(),
            }
            .encode();
            let view = RawBatchView::parse(&batch).expect("valid");
            let checkpoint = (seq % (60 * per_second) == 0).then(|| {
                ck.clear();
                kernel.checkpoint(&mut ck);
                ck.as_slice()
            });
            let kept = Kept {
                arrival: 0,
                sequence: seq,
                timestamp_ns: view.header.timestamp_ns,
                sample_rate_hz: 100.0,
                temperature_c: None,
                calibration_version: 1,
                verdict: Verdict::InOrder,
                samples: view.sample_bytes(),
            };
            writer.append(&InlineId::new(id), kept, checkpoint);
            out.clear();
            correct_judged(
                kernel,
                &view,
                Some(&corrector),
                Verdict::InOrder,
                0,
                &mut scratch,
                &mut out,
            );
        }
        if seq % per_second == per_second - 1 {
            writer.flush().expect("flush");
        }
    }
    writer.flush().expect("flush");
    let recorder =
        Recorder::start(writer, 1024, std::time::Duration::from_secs(1)).expect("writer");
    let ctx = ReplayContext {
        building: BuildingId::new("b").expect("id"),
        table: Arc::new(SensorTable::new(config)),
        store: Arc::new(store),
        sink: recorder.sink.clone(),
        signer: Arc::new(triax_gateway::state::Signer::off()),
    };
    Fixture {
        _dir: dir,
        ctx,
        _recorder: recorder,
    }
}

fn bench(c: &mut Criterion) {
    let mut g = c.benchmark_group("replay");
    g.sample_size(10);
    for n in [10usize, 100] {
        let f = fixture(n);
        let sensor = SensorId::new("s3").expect("id");
        let q = HistoryQuery::parse(std::iter::empty()).expect("defaults");
        g.throughput(Throughput::Elements(SECONDS * 100));
        g.bench_function(format!("{n}-sample batches"), |b| {
            b.iter(|| {
                let mut samples = 0usize;
                replay(&f.ctx, &sensor, &q, &mut |payload, _| {
                    samples += payload.len();
                    true
                })
                .expect("replays");
                samples
            })
        });
    }
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
