//! What the console's decimation costs and what it sends: `cargo bench -p triax-console`.
//!
//! - aggregation rate: one hour of a 100 Hz sensor (360 000 samples in batches of 50) into
//!   1000 buckets, as a history view does; samples per second on one core;
//! - a live page: the first frame (30 s window, 1000 buckets) and a steady frame (what a 250 ms
//!   tick re-sends: the last 2 s plus what is new), in bytes of JSON, and the time to build one;
//! - a hundred sensors at 100 Hz watched at once: the CPU share of building their frames.
//!
//! Each figure is the median of 15 runs, with the smallest and largest.

use std::time::Instant;

use triax_console::buckets::Aggregator;
use triax_protocol::batch::{CorrectedBatch, CorrectedSample};
use triax_protocol::SensorId;

const T0: i64 = 1_800_000_000_000_000_000;

fn batches(seconds: usize) -> Vec<CorrectedBatch> {
    let id = SensorId::new("bench-01").expect("literal id is valid");
    (0..seconds * 2)
        .map(|seq| {
            triax_protocol::batch::sample::dynamic(
                id.clone(),
                seq as u64,
                T0 + seq as i64 * 500_000_000,
                100.0,
                (0..50)
                    .map(|i| {
                        let t = (seq * 50 + i) as f32 / 100.0;
                        CorrectedSample {
                            accel_mps2: [(t * 7.0).sin() * 0.2, (t * 3.0).cos() * 0.1, 9.81],
                            uncertainty_mps2: [0.004; 3],
                            flags: 0,
                        }
                    })
                    .collect(),
            )
        })
        .collect()
}

fn stats(mut v: Vec<f64>) -> (f64, f64, f64) {
    v.sort_by(f64::total_cmp);
    (v[v.len() / 2], v[0], v[v.len() - 1])
}

fn view_json(b: &[CorrectedBatch], from_ns: i64, to_ns: i64, bucket_ns: i64) -> String {
    let mut a = Aggregator::new(from_ns, to_ns, bucket_ns).expect("a valid range");
    for x in b {
        a.push(x);
    }
    serde_json::to_string(&a.finish()).expect("a view serialises")
}

fn main() {
    let hour = batches(3600);
    let samples = 3600.0 * 100.0;
    let mut rates = Vec::new();
    for _ in 0..15 {
        let start = Instant::now();
        let mut a = Aggregator::new(T0, T0 + 3_600_000_000_000, 3_600_000_000).expect("range");
        for b in &hour {
            a.push(b);
        }
        std::hint::black_box(a.finish());
        rates.push(samples / start.elapsed().as_secs_f64());
    }
    let (m, lo, hi) = stats(rates);
    println!(
        "aggregation, 1 h at 100 Hz into 1000 buckets: {:.1} M samples/s (range {:.1}-{:.1})",
        m / 1e6,
        lo / 1e6,
        hi / 1e6
    );

    // A live page: 30 s over 1000 columns; the feed holds 10 minutes.
    let ten = batches(600);
    let end = T0 + 600_000_000_000;
    let span = 30_000_000_000;
    let bucket = span / 1000;
    let first = view_json(&ten[ten.len() - 62..], end - span, end, bucket);
    let steady = view_json(&ten[ten.len() - 6..], end - 2_250_000_000, end, bucket);
    let mut times = Vec::new();
    for _ in 0..15 {
        let start = Instant::now();
        for _ in 0..100 {
            std::hint::black_box(view_json(
                &ten[ten.len() - 6..],
                end - 2_250_000_000,
                end,
                bucket,
            ));
        }
        times.push(start.elapsed().as_secs_f64() / 100.0);
    }
    let (m, lo, hi) = stats(times);
    println!(
        "live page, 30 s over 1000 columns: first frame {} bytes, steady frame {} bytes (4 a second: {:.0} KiB/s)",
        first.len(),
        steady.len(),
        steady.len() as f64 * 4.0 / 1024.0
    );
    println!(
        "steady frame built in {:.1} us (range {:.1}-{:.1}); 100 sensors watched at 4 frames/s: {:.2} % of one core",
        m * 1e6,
        lo * 1e6,
        hi * 1e6,
        m * 400.0 * 100.0
    );
}
