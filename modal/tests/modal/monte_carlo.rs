//! Long known-truth runs (ignored; release): coverage over many windows and the cost of one.

use std::time::Instant;

use triax_modal::sim::SimBuilding;
use triax_modal::{identify, Direction, SsiConfig};

use crate::util::{find, true_shape_like};

/// 600 windows (`WINDOWS` to change) of 30 minutes of the five-storey building (the same
/// building, independent forces and noise): the share of windows whose stated 95 % interval
/// holds the truth, per mode, for frequency, damping and the shape's in-phase components.
/// Asserted: each of the first three modes of each direction found in at least 99 % of the
/// windows, and its frequency covered in 93–97 % of those. Over 200 windows a share's binomial standard
/// deviation is 1.5 %, so that band is ±1.3σ and a right interval fails it one time in five
/// per mode; over 600 it is ±2.2σ.
///
/// `cargo test --release -p triax-modal --test modal coverage -- --ignored --nocapture`
#[test]
#[ignore]
fn coverage() {
    let windows: u64 = std::env::var("WINDOWS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(600);
    let building = SimBuilding::five_storey(5);
    let temperature_c = building.frame.reference_temperature_c;
    let config = SsiConfig::default();
    let truths: Vec<_> = [Direction::X, Direction::Y]
        .into_iter()
        .flat_map(|d| {
            building
                .frame
                .direction_modes(d, temperature_c)
                .into_iter()
                .take(3)
        })
        .collect();
    let n = truths.len();
    let (mut found, mut f_in, mut z_in) = (vec![0usize; n], vec![0usize; n], vec![0usize; n]);
    let (mut shape_in, mut shape_total) = (vec![0usize; n], vec![0usize; n]);
    let mut worst_error = vec![0.0f64; n];
    let mut min_mac = vec![1.0f64; n];
    let mut mean_z_bias = vec![0.0f64; n];
    for w in 0..windows {
        let window = building.simulate(temperature_c, 1800.0, 0, 1000 + w);
        let identification = identify(&building.model, &window, &config).unwrap();
        for (j, truth) in truths.iter().enumerate() {
            let Some((mode, mac)) = find(&building, &identification, truth) else {
                continue;
            };
            found[j] += 1;
            f_in[j] += usize::from(mode.frequency_hz.covers(truth.frequency_hz));
            z_in[j] += usize::from(mode.damping_ratio.covers(truth.damping_ratio));
            mean_z_bias[j] += mode.damping_ratio.value - truth.damping_ratio;
            let error = (mode.frequency_hz.value - truth.frequency_hz).abs() / truth.frequency_hz;
            worst_error[j] = worst_error[j].max(error);
            min_mac[j] = min_mac[j].min(mac);
            let shape = true_shape_like(&building, &identification, truth, mode);
            for (c, component) in mode.shape.iter().enumerate() {
                if c != mode.reference_component && shape[c].re.abs() > 0.05 {
                    shape_total[j] += 1;
                    shape_in[j] += usize::from(component.real.covers(shape[c].re));
                }
            }
        }
    }
    let mut failures = Vec::new();
    for (j, truth) in truths.iter().enumerate() {
        let share = |k: usize| k as f64 / found[j].max(1) as f64;
        println!(
            "{:?}{} {:.3} Hz: found {}/{windows}, frequency covered {:.3}, damping covered {:.3} \
             (mean bias {:+.5}), shape components covered {:.3}, worst error {:.3} %, min MAC {:.4}",
            truth.direction,
            truth.number,
            truth.frequency_hz,
            found[j],
            share(f_in[j]),
            share(z_in[j]),
            mean_z_bias[j] / found[j].max(1) as f64,
            shape_in[j] as f64 / shape_total[j].max(1) as f64,
            100.0 * worst_error[j],
            min_mac[j]
        );
        if (found[j] as f64) < 0.99 * windows as f64 || !(0.93..=0.97).contains(&share(f_in[j])) {
            failures.push(format!("{:?}{}", truth.direction, truth.number));
        }
    }
    assert!(
        failures.is_empty(),
        "frequency coverage outside 93–97 % for {failures:?}"
    );
}

/// The cost of one 30-minute window of twelve channels at 100 Hz (six sensors, x and y), with
/// the default configuration: printed, not asserted.
///
/// `cargo test --release -p triax-modal --test modal cost -- --ignored --nocapture`
#[test]
#[ignore]
fn cost_of_a_window() {
    let building = SimBuilding::five_storey(6);
    let window = building.simulate(20.0, 1800.0, 0, 1);
    let config = SsiConfig::default();
    let _ = identify(&building.model, &window, &config).unwrap();
    let runs = 5;
    let start = Instant::now();
    for _ in 0..runs {
        let _ = identify(&building.model, &window, &config).unwrap();
    }
    println!(
        "one 30-minute window, 12 channels at 100 Hz: {:.3} s (mean of {runs})",
        start.elapsed().as_secs_f64() / runs as f64
    );
}

/// One window's modes against the truth, printed: `SEED`, `MINUTES`, `LIGHT=1` for the light
/// configuration of the default tests.
///
/// `cargo test --release -p triax-modal --test modal diagnose -- --ignored --nocapture`
#[test]
#[ignore]
fn diagnose() {
    let var = |name: &str, default: u64| {
        std::env::var(name)
            .ok()
            .and_then(|v| v.parse().ok())
            .unwrap_or(default)
    };
    let building = SimBuilding::five_storey(var("BUILDING", 11));
    let temperature_c = building.frame.reference_temperature_c;
    let window = building.simulate(
        temperature_c,
        60.0 * var("MINUTES", 30) as f64,
        0,
        var("SEED", 3),
    );
    let config = if var("LIGHT", 0) == 1 {
        crate::identification::light_config()
    } else {
        SsiConfig::default()
    };
    let start = Instant::now();
    let identification = identify(&building.model, &window, &config).unwrap();
    println!("{:?}, i = {}", start.elapsed(), identification.block_rows);
    println!(
        "{}",
        crate::util::summary(&building, &identification, temperature_c)
    );
    for m in &identification.modes {
        println!(
            "{:.4} Hz {:?} order {} stable at {}",
            m.frequency_hz.value, m.direction, m.order, m.stable_orders
        );
    }
    println!("unquantified: {:?}", identification.unquantified);
    if var("DIAGRAM", 0) == 1 {
        for p in identification
            .diagram
            .iter()
            .filter(|p| p.frequency_hz < 1.1)
        {
            println!(
                "{:3} {:.4} {:.4} {:?}",
                p.order, p.frequency_hz, p.damping_ratio, p.stability
            );
        }
    }
}
