//! Mode shapes against the truth over many windows (ignored; release): the close pairs.

use nalgebra::Complex;
use triax_modal::sim::SimBuilding;
use triax_modal::ssi::{mac, normalise};
use triax_modal::{identify, Direction, Estimate, Mode, ShapeComponent, ShapePool, SsiConfig};

use crate::util::{find, true_shape_like};

fn var(name: &str, default: f64) -> f64 {
    std::env::var(name)
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(default)
}

fn quantile(sorted: &[f64], q: f64) -> f64 {
    sorted[((sorted.len() - 1) as f64 * q).round() as usize]
}

/// `WINDOWS` (200) windows of 30 minutes (`MINUTES`) of the five-storey building, `y` stiffer
/// by `RATIO` (1.03: every mode of `x` has one of `y` 1.5 % above it): per mode, the MAC of the
/// mode shape (the in-phase parts) with the truth, its median, 5th percentile and minimum and the
/// share of windows at 0.99 or above; the same for the complex shape (quadrature parts kept),
/// for comparison; how much of the shape's energy is in the other direction (the close pair's
/// mixing); and the share of in-phase components whose stated 95 % interval holds the truth,
/// the mode's own direction and the other (truth 0) apart. Then the shape pooled over `POOL`
/// (48) consecutive windows ([`ShapePool`]), in independent blocks: its MAC with the truth and
/// the share of its components whose interval holds the truth. Asserted: median MAC at least
/// 0.99 for every mode, component coverage at least 90 % in each direction, and every pooled
/// shape at MAC 0.99 or above.
///
/// `cargo test --release -p triax-modal --test modal close_pair_shapes -- --ignored --nocapture`
#[test]
#[ignore]
fn close_pair_shapes() {
    let windows = var("WINDOWS", 200.0) as u64;
    let mut building = SimBuilding::five_storey(5);
    building.frame.stiffness_ratio_y = var("RATIO", 1.03);
    let t = building.frame.reference_temperature_c;
    let config = SsiConfig::default();
    let truths: Vec<_> = [Direction::X, Direction::Y]
        .into_iter()
        .flat_map(|d| building.frame.direction_modes(d, t).into_iter().take(3))
        .collect();
    let n = truths.len();
    let mut in_phase = vec![Vec::new(); n];
    let mut complex = vec![Vec::new(); n];
    let mut leak = vec![Vec::new(); n];
    let mut own = vec![(0usize, 0usize); n];
    let mut other = vec![(0usize, 0usize); n];
    let pool_windows = var("POOL", 48.0) as usize;
    let mut pools: Vec<ShapePool> = (0..n).map(|_| ShapePool::new(pool_windows)).collect();
    let mut pooled_mac = vec![Vec::new(); n];
    let mut pooled_cover = vec![(0usize, 0usize); n];
    for w in 0..windows {
        let window = building.simulate(t, 60.0 * var("MINUTES", 30.0), 0, 1000 + w);
        let id = identify(&building.model, &window, &config).unwrap();
        for (j, truth) in truths.iter().enumerate() {
            let Some((mode, m)) = find(&building, &id, truth) else {
                continue;
            };
            in_phase[j].push(m);
            pools[j].push(mode);
            if pools[j].len() == pool_windows {
                let pooled = pools[j].pooled(mode, 0.95).unwrap();
                let truth_shape: Vec<Complex<f64>> = building
                    .true_shape(truth, &id.channels)
                    .into_iter()
                    .map(|v| Complex::new(v, 0.0))
                    .collect();
                let truth_shape = normalise(&truth_shape, pooled.reference_component);
                let values: Vec<Complex<f64>> = pooled
                    .shape
                    .iter()
                    .map(|c| Complex::new(c.real.value, 0.0))
                    .collect();
                pooled_mac[j].push(mac(&values, &truth_shape));
                for (c, component) in pooled.shape.iter().enumerate() {
                    if c != pooled.reference_component {
                        pooled_cover[j].0 += usize::from(component.real.covers(truth_shape[c].re));
                        pooled_cover[j].1 += 1;
                    }
                }
                // Independent blocks: the next pool starts empty.
                pools[j] = ShapePool::new(pool_windows);
            }
            let shape = true_shape_like(&building, &id, truth, mode);
            complex[j].push(mac(&mode.shape_values(), &shape));
            let values = mode.shape_values();
            let total: f64 = values.iter().map(|v| v.norm_sqr()).sum();
            let across: f64 = values
                .iter()
                .zip(&mode.shape)
                .filter(|(_, c)| c.direction != truth.direction)
                .map(|(v, _)| v.norm_sqr())
                .sum();
            leak[j].push(across / total);
            for (c, component) in mode.shape.iter().enumerate() {
                if c == mode.reference_component {
                    continue;
                }
                let tally = if component.direction == truth.direction {
                    &mut own[j]
                } else {
                    &mut other[j]
                };
                tally.0 += usize::from(component.real.covers(shape[c].re));
                tally.1 += 1;
            }
        }
    }
    let mut failures = Vec::new();
    println!(
        "mode: found | mode shape MAC median, 5 %, min, share ≥ 0.99 | complex MAC median, 5 %, \
         min | energy across median, max | in-phase coverage own, other direction"
    );
    for (j, truth) in truths.iter().enumerate() {
        let (mut a, mut b, mut l) = (in_phase[j].clone(), complex[j].clone(), leak[j].clone());
        a.sort_by(f64::total_cmp);
        b.sort_by(f64::total_cmp);
        l.sort_by(f64::total_cmp);
        let share = a.iter().filter(|&&m| m >= 0.99).count() as f64 / a.len() as f64;
        let own_cov = own[j].0 as f64 / own[j].1.max(1) as f64;
        let other_cov = other[j].0 as f64 / other[j].1.max(1) as f64;
        println!(
            "{:?}{} {:.3} Hz: {}/{windows} | {:.4} {:.4} {:.4} {:.3} | {:.4} {:.4} {:.4} | {:.4} \
             {:.4} | {:.3} {:.3}",
            truth.direction,
            truth.number,
            truth.frequency_hz,
            a.len(),
            quantile(&a, 0.5),
            quantile(&a, 0.05),
            a[0],
            share,
            quantile(&b, 0.5),
            quantile(&b, 0.05),
            b[0],
            quantile(&l, 0.5),
            l[l.len() - 1],
            own_cov,
            other_cov
        );
        let mut p = pooled_mac[j].clone();
        p.sort_by(f64::total_cmp);
        if let Some(min) = p.first() {
            println!(
                "   pooled over {pool_windows} windows: {} blocks, MAC min {min:.5}, median {:.5}; \
                 components covered {}/{}",
                p.len(),
                quantile(&p, 0.5),
                pooled_cover[j].0,
                pooled_cover[j].1
            );
            if *min < 0.99 {
                failures.push(format!("{:?}{} pooled", truth.direction, truth.number));
            }
        }
        if quantile(&a, 0.5) < 0.99 || own_cov < 0.9 || other_cov < 0.9 {
            failures.push(format!("{:?}{}", truth.direction, truth.number));
        }
    }
    assert!(failures.is_empty(), "{failures:?}");
}

fn component(sensor: &str, value: f64, statistical_u: f64, chain_variance: f64) -> ShapeComponent {
    let u = (statistical_u.powi(2) + chain_variance).sqrt();
    ShapeComponent {
        sensor_id: sensor.into(),
        direction: Direction::X,
        real: Estimate::new(value, u, 11.0, 0.95),
        imag: Estimate::new(0.0, 0.01, 11.0, 0.95),
        chain_variance_real: chain_variance,
        chain_variance_imag: 0.0,
    }
}

fn two_component_mode(shape: Vec<ShapeComponent>, reference_component: usize) -> Mode {
    Mode {
        frequency_hz: Estimate::new(1.0, 0.001, 11.0, 0.95),
        damping_ratio: Estimate::new(0.02, 0.002, 11.0, 0.95),
        shape,
        reference_component,
        direction: Direction::X,
        order: 20,
        stable_orders: 10,
        replicates: 12,
    }
}

/// The pool against its formulas: each component the inverse-variance weighted mean of the
/// windows' (statistical variance), `u_stat² = 1/Σw`, the chain's variance kept whole (the
/// windows' mean, not divided by their number), a window normalised to another component
/// brought to the pool's reference, and the oldest window dropped beyond the capacity.
#[test]
fn pooled_shape_is_the_weighted_mean_with_the_chain_kept_whole() {
    let mut pool = ShapePool::new(3);
    let a = two_component_mode(
        vec![
            component("roof", 1.0, 0.0, 0.0),
            component("mid", 0.5, 0.1, 1e-4),
        ],
        0,
    );
    let b = two_component_mode(
        vec![
            component("roof", 1.0, 0.0, 0.0),
            component("mid", 0.7, 0.2, 1e-4),
        ],
        0,
    );
    pool.push(&a);
    pool.push(&b);
    let pooled = pool.pooled(&a, 0.95).unwrap();
    assert_eq!(pooled.reference_component, 0);
    assert_eq!(pooled.windows, 2);
    assert_eq!(pooled.shape[0].real.value, 1.0);
    let mid = pooled.shape[1].real;
    let weights = 1.0 / 0.01 + 1.0 / 0.04;
    assert!((mid.value - (0.5 / 0.01 + 0.7 / 0.04) / weights).abs() < 1e-12);
    assert!((mid.standard_uncertainty.powi(2) - (1.0 / weights + 1e-4)).abs() < 1e-12);
    assert_eq!(pooled.shape[1].sensor_id, "mid");
    // A window normalised to "mid" (roof 2.0 there): roof-relative, mid is 0.5.
    let c = two_component_mode(
        vec![
            component("roof", 2.0, 0.0, 0.0),
            component("mid", 1.0, 0.0, 0.0),
        ],
        1,
    );
    pool.push(&c);
    pool.push(&c);
    let pooled = pool.pooled(&a, 0.95).unwrap();
    assert_eq!(pooled.windows, 3, "capacity");
    assert!(
        (pooled.shape[1].real.value - (0.7 / 0.04 + 2.0 * 0.5) / (1.0 / 0.04 + 2.0)).abs() < 1e-12,
        "{pooled:?}"
    );
}
