//! The noise parts against a Monte Carlo of the same record: a weak 2 Hz sine (ten noise
//! deviations at its crest, where a dozen samples are within one deviation of the peak), noise
//! drawn afresh each time; the truth is the noise-free record's parameters. A steady sine is
//! the hardest case for a peak: every crest is a candidate (the ties regime, where the noise
//! picks the luckiest one), so the figures here bound what a strong event, whose peak stands
//! out, needs.

use std::f64::consts::PI;

use triax_strongmotion::filter::BandConfig;
use triax_strongmotion::parameters::{sensor_parameters, ParameterConfig, SensorParameters};
use triax_strongmotion::process::{Processed, SensorCalibration};
use triax_strongmotion::rng::Rng;

use crate::util::*;

fn motion(t: f64) -> [f64; 3] {
    let ramp = |x: f64| 0.5 - 0.5 * (PI * x.clamp(0.0, 1.0)).cos();
    let env = ramp((t - 6.0) / 2.0) * ramp((16.0 - t) / 2.0);
    let s = (2.0 * PI * 2.0 * t).sin();
    let c = (2.0 * PI * 3.1 * t + 0.4).sin();
    [0.02 * env * s, 0.012 * env * c, 0.008 * env * s]
}

fn config() -> ParameterConfig {
    ParameterConfig {
        band: BandConfig {
            low_hz: 0.2,
            high_hz: Some(30.0),
            order: 4,
        },
        periods_s: vec![0.5],
        ..ParameterConfig::default()
    }
}

fn parameters(noise_sd: f64, rng: Option<&mut Rng>) -> SensorParameters {
    let s = IDENTITY.map(|r| r.map(|v| 0.1 * v));
    let cal = SensorCalibration::noise_only(s, noise_sd);
    let mut rec = record(100.0, 0.0, 22.0, motion, cal);
    if let Some(rng) = rng {
        for a in &mut rec.accel_mps2 {
            for v in a.iter_mut() {
                *v += 0.002 * rng.normal();
            }
        }
    }
    let p = Processed::new(&rec, &config().band, 5.0).unwrap();
    sensor_parameters(&p, &config(), 3)
}

/// Each value with a name, from a sensor's parameters.
fn values(p: &SensorParameters) -> Vec<(&'static str, triax_strongmotion::estimate::Estimate)> {
    let x = &p.axes[0];
    vec![
        ("PGA x", x.pga.estimate),
        ("PGA y", p.axes[1].pga.estimate),
        ("PGA z", p.axes[2].pga.estimate),
        ("PGA RotD50", p.pga_rotd50.estimate),
        ("PGA RotD100", p.pga_rotd100.estimate),
        ("PGV x", x.pgv.estimate),
        ("PGD x", x.pgd.estimate),
        ("Arias x", x.arias.estimate),
        ("CAV x", x.cav.estimate),
        ("D5-95 x", x.d5_95.unwrap().estimate),
        ("PSA(0.5) x", p.spectrum[0].axes[0].estimate),
        ("PSA(0.5) RotD50", p.spectrum[0].rotd50.estimate),
    ]
}

/// Runs the record `runs` times; per value its name, coverage, bias and spread in stated u.
fn monte_carlo(runs: usize, seed: u64) -> Vec<(&'static str, f64, f64, f64)> {
    let truth = parameters(0.0, None);
    let truth = values(&truth);
    let mut rng = Rng::new(seed);
    let mut inside = vec![0usize; truth.len()];
    let mut errors: Vec<Vec<f64>> = vec![Vec::new(); truth.len()];
    let mut stated = vec![0.0; truth.len()];
    for _ in 0..runs {
        let measured = parameters(0.002, Some(&mut rng));
        for (j, (_, e)) in values(&measured).iter().enumerate() {
            inside[j] += usize::from(e.covers(truth[j].1.value));
            errors[j].push(e.value - truth[j].1.value);
            stated[j] += e.standard_uncertainty / runs as f64;
        }
    }
    truth
        .iter()
        .enumerate()
        .map(|(j, (name, _))| {
            let n = runs as f64;
            let mean = errors[j].iter().sum::<f64>() / n;
            let sd = (errors[j].iter().map(|e| (e - mean).powi(2)).sum::<f64>() / (n - 1.0)).sqrt();
            (
                *name,
                inside[j] as f64 / n,
                mean / stated[j],
                sd / stated[j],
            )
        })
        .collect()
}

fn table(rows: &[(&str, f64, f64, f64)]) -> String {
    rows.iter()
        .map(|(name, c, b, s)| {
            format!(
                "{name}: coverage {:.1} %, bias {b:+.2} u, sd/u {s:.3}\n",
                100.0 * c
            )
        })
        .collect()
}

/// CAV's extrapolation is made for strong events (the Monte Carlo of whole events holds it to
/// 93–97 %); on a steady sine ten noise deviations high it overcorrects, and this test holds it
/// only to what it does there (BENCHMARKS.md has the figure).
fn floor(name: &str, strict: f64) -> f64 {
    if name.starts_with("CAV") {
        0.55
    } else {
        strict
    }
}

/// The short version: no value's interval is badly short, none badly biased.
#[test]
fn noise_parts_hold_in_a_short_monte_carlo() {
    let rows = monte_carlo(40, 11);
    let bad = rows.iter().any(|(name, c, b, _)| {
        *c < floor(name, 0.8) || (b.abs() > 1.5 && !name.starts_with("CAV"))
    });
    assert!(!bad, "{}", table(&rows));
}

/// The long version (`cargo test --release -p triax-strongmotion -- --ignored noise`): the
/// intervals hold 90–100 % of the truths (sample RotD, whose median over angles SIMEX
/// overcorrects a little here, from 84 %), and no stated u is over twice the spread.
#[test]
#[ignore]
fn noise_parts_hold_in_a_monte_carlo() {
    let rows = monte_carlo(400, 12);
    println!("{}", table(&rows));
    let bad = rows.iter().any(|(name, c, _, s)| {
        let floor = if name.starts_with("PGA RotD") {
            0.84
        } else {
            0.90
        };
        *c < floor || *s < 0.5 || *s > 1.25
    });
    assert!(!bad, "{}", table(&rows));
}
