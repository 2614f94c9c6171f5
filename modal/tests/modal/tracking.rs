//! The tracker on synthetic mode series: known frequencies, temperature effect and scatter.

use nalgebra::Complex;
use rand::rngs::SmallRng;
use rand::{Rng, SeedableRng};
use rand_distr::StandardNormal;
use triax_modal::track::{ModeObservation, ModeTracker, ShiftVerdict, TrackerConfig};
use triax_modal::{Direction, Estimate};

/// Two close modes, x at 1.00 Hz and y at 1.015 Hz, with orthogonal shapes, both moving by
/// −0.15 %/°C, observed with relative scatter `sigma`.
fn observations(
    temperature_c: f64,
    sigma: f64,
    drop: f64,
    rng: &mut SmallRng,
) -> Vec<ModeObservation> {
    let thermal = 1.0 - 0.0015 * (temperature_c - 20.0);
    let shape = |x: f64, y: f64| {
        vec![
            Complex::new(x, 0.0),
            Complex::new(y, 0.0),
            Complex::new(0.5 * x, 0.0),
            Complex::new(0.5 * y, 0.0),
        ]
    };
    let mut out = Vec::new();
    for (f0, direction, s) in [
        (1.0, Direction::X, shape(1.0, 0.02)),
        (1.015, Direction::Y, shape(-0.03, 1.0)),
    ] {
        let f_true = f0
            * thermal
            * if direction == Direction::X {
                1.0 - drop
            } else {
                1.0
            };
        let noise: f64 = rng.sample(StandardNormal);
        let f = f_true * (1.0 + sigma * noise);
        out.push(ModeObservation {
            frequency_hz: Estimate::new(f, sigma * f, 11.0, 0.95),
            shape: s,
            direction,
        });
    }
    // Present them in a different order each window: matching must not rely on it.
    if rng.gen_bool(0.5) {
        out.reverse();
    }
    out
}

fn temperature(window: usize) -> f64 {
    // A day of 48 windows at ±8 °C and a slow seasonal drift.
    let day = window as f64 / 48.0;
    15.0 + 8.0 * (2.0 * std::f64::consts::PI * day).sin()
        + 5.0 * (2.0 * std::f64::consts::PI * day / 60.0).sin()
}

#[test]
fn close_modes_keep_their_tracks_as_temperature_moves_both() {
    let mut rng = SmallRng::seed_from_u64(1);
    let mut tracker = ModeTracker::new(TrackerConfig {
        training_windows: 96,
        ..TrackerConfig::default()
    });
    let mut track_of = std::collections::HashMap::new();
    for w in 0..400 {
        let updates = tracker.update(
            &observations(temperature(w), 0.001, 0.0, &mut rng),
            &[temperature(w)],
        );
        for u in updates {
            let first = *track_of.entry(u.direction).or_insert(u.track);
            assert_eq!(u.track, first, "window {w}");
        }
    }
    assert_eq!(tracker.tracks.len(), 2);
    let x = tracker
        .tracks
        .iter()
        .find(|t| t.direction == Direction::X)
        .expect("x tracked");
    let baseline = x.baseline.as_ref().expect("trained");
    let slope = baseline.coefficients[1];
    assert!((slope - (-0.0015)).abs() < 0.0002, "slope {slope} Hz/°C");
}

#[test]
fn false_alarms_occur_at_the_designed_rate_and_a_drop_is_found() {
    // A budget of 10 false shifts in 1000 windows per track (0.5 % per window, 5 % per block
    // of ten), so that the rates are measurable in a few thousand windows.
    let config = TrackerConfig {
        training_windows: 200,
        false_alarms_per_year: 10.0,
        windows_per_year: 1000.0,
        average_windows: 10,
        ..TrackerConfig::default()
    };
    let alpha_window = config.window_false_alarm_probability();
    let alpha_block = config.block_false_alarm_probability();
    // A third of the budget each: window, block mean, sequential.
    assert!((alpha_window - 0.01 / 3.0).abs() < 1e-12 && (alpha_block - 0.1 / 3.0).abs() < 1e-12);
    let run_length = config.cusum_threshold().exp();
    assert!((run_length - 300.0).abs() < 1e-6, "{run_length}");
    let mut shifts = 0usize;
    let mut judged = 0usize;
    let mut block_shifts = 0usize;
    let mut blocks = 0usize;
    let mut normal = 0usize;
    let mut cusum_shifts = 0usize;
    for seed in 0..20u64 {
        let mut rng = SmallRng::seed_from_u64(100 + seed);
        let mut tracker = ModeTracker::new(config.clone());
        for w in 0..600 {
            for u in tracker.update(
                &observations(temperature(w), 0.001, 0.0, &mut rng),
                &[temperature(w)],
            ) {
                if u.verdict != ShiftVerdict::Training {
                    judged += 1;
                    shifts += usize::from(u.verdict == ShiftVerdict::Shift);
                    normal += usize::from(u.verdict == ShiftVerdict::Normal);
                    cusum_shifts += usize::from(u.cusum_verdict == Some(ShiftVerdict::Shift));
                }
                if let Some(v) = u.block_verdict {
                    blocks += 1;
                    block_shifts += usize::from(v == ShiftVerdict::Shift);
                }
            }
        }
    }
    let rate = shifts as f64 / judged as f64;
    // Binomial: 16 000 trials at 0.5 %; allow 4σ.
    let sigma = (alpha_window * (1.0 - alpha_window) / judged as f64).sqrt();
    println!("window rate {rate:.4} (designed {alpha_window}), block rate {:.4} (designed {alpha_block}) over {blocks}", block_shifts as f64 / blocks as f64);
    assert!(
        (rate - alpha_window).abs() < 4.0 * sigma,
        "window false-alarm rate {rate}"
    );
    // `normal` inside the prediction interval: 97.5 % when only drops are judged.
    let normal_share = normal as f64 / judged as f64;
    let sigma_normal = (0.975 * 0.025 / judged as f64).sqrt();
    println!("normal {normal_share:.4}, sequential false alarms {cusum_shifts} in {judged} windows (run length ≥ {run_length})");
    assert!(
        (normal_share - 0.975).abs() < 4.0 * sigma_normal,
        "normal in {normal_share} of healthy windows"
    );
    // Lorden's bound: at most one false alarm per 300 windows on average.
    let bound = judged as f64 / run_length;
    assert!(
        (cusum_shifts as f64) <= bound + 3.0 * bound.sqrt(),
        "{cusum_shifts} sequential false alarms, bound {bound:.1}"
    );
    let block_rate = block_shifts as f64 / blocks as f64;
    let sigma_block = (alpha_block * (1.0 - alpha_block) / blocks as f64).sqrt();
    assert!(
        (block_rate - alpha_block).abs() < 4.0 * sigma_block,
        "block rate {block_rate}"
    );

    // Now with the default budget (one false shift a year), a 0.5 % drop of x, after training,
    // is found by the block mean within a block, not by the single window.
    let mut rng = SmallRng::seed_from_u64(7);
    let config = TrackerConfig {
        training_windows: 336,
        ..TrackerConfig::default()
    };
    let mut tracker = ModeTracker::new(config);
    let mut found_at = None;
    let mut sequential_at = None;
    for w in 0..336 + 96 {
        let drop = if w >= 336 { 0.005 } else { 0.0 };
        for u in tracker.update(
            &observations(temperature(w), 0.001, drop, &mut rng),
            &[temperature(w)],
        ) {
            if u.direction == Direction::Y {
                assert_ne!(
                    u.block_verdict,
                    Some(ShiftVerdict::Shift),
                    "y did not change"
                );
            }
            if u.direction == Direction::X
                && u.block_verdict == Some(ShiftVerdict::Shift)
                && found_at.is_none()
            {
                found_at = Some(w);
            }
            if u.direction == Direction::X
                && u.cusum_verdict == Some(ShiftVerdict::Shift)
                && sequential_at.is_none()
            {
                sequential_at = Some(w);
            }
            if u.direction == Direction::Y {
                assert_ne!(
                    u.cusum_verdict,
                    Some(ShiftVerdict::Shift),
                    "y did not change"
                );
            }
        }
    }
    let found_at = found_at.expect("the drop is found");
    assert!(found_at < 336 + 96, "found at window {found_at}");
    // The sequential test sees it within hours, not at a block's end: a drop of five standard
    // uncertainties, tuned to 1.5, accumulates 6.4 a window against h = ln(3·17 532) = 10.9.
    let sequential_at = sequential_at.expect("the sequential test finds the drop");
    assert!(
        (336..336 + 4).contains(&sequential_at),
        "sequential test at window {sequential_at}"
    );
}

#[test]
fn a_window_whose_shape_is_poor_for_one_of_two_close_modes_stays_on_its_track() {
    // x at 1.000 Hz and y at 1.015 Hz (1.5 % apart), each window's shapes scattered about the
    // truth (MAC 0.85–1 with it), and every 25th window's x shape leaking y (MAC 0.74 with
    // the truth, 0.26 with y): compared with one window's shape, such a window started a
    // track of its own, and the two x tracks then shared the windows that followed.
    let mut rng = SmallRng::seed_from_u64(3);
    let x = [1.0, 0.02, 0.5, 0.01];
    let y = [-0.03, 1.0, -0.01, 0.5];
    let mut tracker = ModeTracker::new(TrackerConfig {
        training_windows: 96,
        ..TrackerConfig::default()
    });
    let mut track_of = std::collections::HashMap::new();
    let mut poor = 0;
    for w in 0..400 {
        let thermal = 1.0 - 0.0015 * (temperature(w) - 20.0);
        let mut modes = Vec::new();
        for (f0, direction, truth, other) in
            [(1.0, Direction::X, x, y), (1.015, Direction::Y, y, x)]
        {
            let leak = if direction == Direction::X && w % 25 == 10 {
                0.6
            } else {
                0.0
            };
            let shape: Vec<Complex<f64>> = truth
                .iter()
                .zip(other)
                .map(|(t, o)| {
                    let noise: f64 = rng.sample(StandardNormal);
                    Complex::new(t + leak * o + 0.12 * noise, 0.0)
                })
                .collect();
            let truth: Vec<Complex<f64>> = truth.iter().map(|t| Complex::new(*t, 0.0)).collect();
            let other: Vec<Complex<f64>> = other.iter().map(|o| Complex::new(*o, 0.0)).collect();
            if leak > 0.0 {
                let with_truth = triax_modal::ssi::mac(&shape, &truth);
                assert!(
                    with_truth < 0.8,
                    "window {w}: MAC {with_truth} with the truth"
                );
                assert!(triax_modal::ssi::mac(&shape, &other) < 0.5);
                poor += 1;
            }
            let noise: f64 = rng.sample(StandardNormal);
            let f = f0 * thermal * (1.0 + 0.002 * noise);
            modes.push(ModeObservation {
                frequency_hz: Estimate::new(f, 0.002 * f, 11.0, 0.95),
                shape,
                direction,
            });
        }
        if rng.gen_bool(0.5) {
            modes.reverse();
        }
        for u in tracker.update(&modes, &[temperature(w)]) {
            let first = *track_of.entry(u.direction).or_insert(u.track);
            assert_eq!(
                u.track, first,
                "window {w}: {:?} on another track",
                u.direction
            );
        }
    }
    assert!(poor >= 15);
    assert_eq!(tracker.tracks.len(), 2);
    for track in &tracker.tracks {
        assert_eq!(track.observations, 400);
        assert!(track.baseline.is_some(), "trained");
    }
}
