use std::f64::consts::PI;

use triax_strongmotion::filter::BandConfig;
use triax_strongmotion::parameters::{sensor_parameters, ParameterConfig, STANDARD_GRAVITY_MPS2};
use triax_strongmotion::process::{Processed, SensorCalibration};

use crate::util::*;

/// Ramps of the sine's envelope, s: Hann-shaped and slow against its 2 Hz, so that the burst
/// has nothing below the band's corner (its velocity and displacement oscillate about 0).
const RAMP_S: f64 = 4.0;

/// A 2 Hz sine of 1.5 m/s² on x from 10 s to 30 s with Hann ramps, after 10 s of rest, and
/// half of it on y: motion along atan(½) = 26.6° from x.
fn sine(t: f64) -> [f64; 3] {
    let (a, f) = (1.5, 2.0);
    let x = a * envelope(t) * (2.0 * PI * f * t).sin();
    [x, 0.5 * x, 0.0]
}

fn envelope(t: f64) -> f64 {
    let ramp = |x: f64| 0.5 - 0.5 * (PI * x.clamp(0.0, 1.0)).cos();
    ramp((t - 10.0) / RAMP_S) * ramp((30.0 - t) / RAMP_S)
}

/// `∫₀ˣ ramp²`: 3x/8 − (R/2π)·sin(πx/R) + (R/16π)·sin(2πx/R).
fn ramp_energy(x: f64) -> f64 {
    let r = RAMP_S;
    0.375 * x - 0.5 * r / PI * (PI * x / r).sin()
        + 0.125 * r / (2.0 * PI) * (2.0 * PI * x / r).sin()
}

fn config() -> ParameterConfig {
    ParameterConfig {
        band: BandConfig {
            low_hz: 0.1,
            high_hz: Some(40.0),
            order: 4,
        },
        periods_s: vec![0.5, 2.0],
        ..ParameterConfig::default()
    }
}

#[test]
fn a_sine_by_hand() {
    let s = IDENTITY.map(|r| r.map(|v| 0.1 * v));
    let mut cal = SensorCalibration::noise_only(s, 0.0);
    // Only S₀₀ uncertain, 0.3 % of it; and S₁₀, a cross-axis term, 0.002 of S₁₁.
    let mut cov = covariance_on(0, 0, (0.003 * 0.1f64).powi(2));
    cov[3][3] = (0.002 * 0.1f64).powi(2);
    cal.sensitivity_covariance = Some(cov);
    let rec = record(100.0, 0.0, 40.0, sine, cal);
    let p = Processed::new(&rec, &config().band, 9.0).unwrap();
    let r = sensor_parameters(&p, &config(), 1);
    let x = &r.axes[0];
    let (amplitude, w) = (1.5, 2.0 * PI * 2.0);
    // The crests (at 0.125 s + k/2) fall half a sample from the samples.
    let a = amplitude * (w * 0.005).cos();
    let close = |got: f64, want: f64, rel: f64, what: &str| {
        assert!(
            (got - want).abs() <= rel * want.abs(),
            "{what}: {got} against {want}"
        );
    };
    close(x.pga.estimate.value, a, 2e-3, "PGA");
    close(x.pgv.estimate.value, amplitude / w, 5e-3, "PGV");
    close(x.pgd.estimate.value, amplitude / (w * w), 1e-2, "PGD");
    // Arias: π/(2g)·A²/2 per second of full amplitude, 20 − 2R s of it, and a ramp's share
    // of squares is 3R/8.
    let seconds = 20.0 - 2.0 * RAMP_S + 2.0 * ramp_energy(RAMP_S);
    close(
        x.arias.estimate.value,
        PI / (2.0 * STANDARD_GRAVITY_MPS2) * amplitude * amplitude / 2.0 * seconds,
        2e-3,
        "Arias",
    );
    // CAV: mean |sin| is 2/π; a Hann ramp averages ½.
    close(
        x.cav.estimate.value,
        2.0 / PI * amplitude * (20.0 - RAMP_S),
        2e-3,
        "CAV",
    );
    // D5–95: symmetric, so 20 s less twice the time the ramp takes to 5 % of the whole; the
    // intensity itself rises in steps of a quarter period (sin² has ripple at 4 Hz), so each
    // crossing is known to within the eighth of a second a step takes.
    let (mut lo, mut hi) = (0.0, RAMP_S);
    for _ in 0..60 {
        let mid = 0.5 * (lo + hi);
        if ramp_energy(mid) < 0.05 * seconds {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    let d = x.d5_95.unwrap().estimate.value;
    assert!(
        (d - (20.0 - 2.0 * lo)).abs() < 0.1,
        "D5–95 {d} against {}",
        20.0 - 2.0 * lo
    );
    // At resonance (0.5 s) the 5 %-damped oscillator amplifies about 1/(2ζ) = 10 times.
    close(
        r.spectrum[0].axes[0].estimate.value,
        10.0 * amplitude,
        0.03,
        "PSA(0.5 s)",
    );
    // Motion along one line: RotD100 is its amplitude √1.25·A, at 27° (26.6° to the degree),
    // and RotD50 that times cos 45° (the median of |cos| over half a turn).
    let line = a * 1.25f64.sqrt();
    close(r.pga_rotd100.estimate.value, line, 1e-3, "RotD100");
    assert_eq!(r.pga_rotd100.angle_deg, Some(27.0));
    close(
        r.pga_rotd50.estimate.value,
        line * (PI / 4.0).cos(),
        0.02,
        "RotD50",
    );
    // The gain's 0.3 % is every peak's and intensity's relative uncertainty on x (twice for
    // Arias, a square); D5–95 does not move with a gain.
    for (v, want) in [
        (x.pga, 0.003),
        (x.pgv, 0.003),
        (x.pgd, 0.003),
        (x.cav, 0.003),
        (x.arias, 0.006),
        (r.spectrum[0].axes[0], 0.003),
    ] {
        close(
            v.estimate.standard_uncertainty / v.estimate.value,
            want,
            1e-3,
            "relative u",
        );
        assert!((v.estimate.coverage_factor - 1.96).abs() < 0.01);
    }
    assert!(x.d5_95.unwrap().estimate.standard_uncertainty < 1e-9);
    // Along the line at θ = 27° the errors are g·x·cos θ (x's gain) and c·x·sin θ (y reading
    // c of x), x = A/√1.25 there: u/RotD100 = √(g² cos²θ + c² sin²θ)/√1.25.
    let theta = 27f64.to_radians();
    let (g, c) = (0.003, 0.002);
    close(
        r.pga_rotd100.estimate.standard_uncertainty / r.pga_rotd100.estimate.value,
        (g * g * theta.cos().powi(2) + c * c * theta.sin().powi(2)).sqrt() / 1.25f64.sqrt(),
        2e-3,
        "RotD100's relative u",
    );
    // The cross-axis term S₁₀ makes y read 0.2 % of x's motion, at y's own crest: y's peak
    // (A/2) gets u = 0.002·A, and a gain error on x none.
    let y = &r.axes[1];
    close(y.pga.estimate.value, 0.5 * a, 2e-3, "PGA_y");
    close(
        y.pga.estimate.standard_uncertainty,
        0.002 * a,
        1e-3,
        "cross-axis u",
    );
    // x reading z through S₀₂ (sd 1e-5 V per m/s², 1e-4 of S₀₀): z's motion (the same sine)
    // adds 1e-4·A to x's peak, and gravity on z, a constant, nothing (the baseline takes it).
    let mut cal = SensorCalibration::noise_only(s, 0.0);
    cal.sensitivity_covariance = Some(covariance_on(0, 2, 1e-10));
    let rec = record(100.0, 0.0, 40.0, |t| [sine(t)[0], 0.0, sine(t)[0]], cal);
    let p = Processed::new(&rec, &config().band, 9.0).unwrap();
    let r = sensor_parameters(&p, &config(), 1);
    let zx = r.axes[0].pga.estimate.standard_uncertainty;
    close(zx, 1e-4 * a, 1e-3, "x from z's motion, not gravity");
}
