//! The performance target: fitting 60 s of 1 kHz recordings at 4 mount angles takes
//! under 1 s in release. Measures the dynamic fit and the uncertainty budget per reference
//! method on simulated data (the simulation itself is outside the timed part).
//!
//! Run with `cargo bench -p triax-lab --bench fit`.

use criterion::{criterion_group, criterion_main, Criterion};
use triax_calibration::fit::dynamic::fit_with;
use triax_calibration::fit::repeatability::evaluate;
use triax_calibration::fit::ReferenceMethod;
use triax_calibration::sim::{simulate, SimConfig};

fn dynamic_fit(c: &mut Criterion) {
    let sim = simulate(&SimConfig {
        duration_s: 60.0,
        ..SimConfig::default()
    });
    let mut group = c.benchmark_group("fit 60 s at 1 kHz, 4 angles");
    group.sample_size(10);
    for method in ReferenceMethod::ALL {
        group.bench_function(format!("{method} fit + uncertainty"), |b| {
            b.iter(|| {
                let fit = fit_with(&sim.bench, &sim.recordings, method, 20)
                    .expect("simulated data are valid");
                evaluate(&sim.bench, &sim.recordings, &fit).expect("simulated data are valid")
            })
        });
    }
    group.finish();
}

criterion_group!(benches, dynamic_fit);
criterion_main!(benches);
