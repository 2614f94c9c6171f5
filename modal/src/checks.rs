//! Checks of the building model against the data: each sensor's declared mounting and each
//! node's clock, from the window itself.
//!
//! **Tilt, from gravity.** The corrected streams are specific force in the sensor's axes, so
//! their static part (the window's mean over valid samples) is gravity, `+g` along the
//! building's vertical. Through the declared mounting `R` it should point up: the angle
//! between `R·ḡ` and `z` is the sensor's tilt beyond its declared one. A sensor turned only in
//! plan (about the vertical) shows none: gravity cannot see a turn about itself. Its
//! uncertainty is the measurement chain's cross-axis term (a misalignment of the axes, rad)
//! and the window's own scatter (a delete-one-block jackknife of the mean); the record's offset
//! is not in the chain, so a tilt below a few tenths of a degree is not told from an offset.
//! Streams whose static part is not gravity (its magnitude more than 10 % off 9.81 m/s²) are
//! not checked.
//!
//! **Plan rotation, from the floor's rigid motion.** A floor is rigid in its plane: every point
//! `p` of it moves by `u + θ·(−(p_y − c_y), p_x − c_x)`, a translation `u` and a turn `θ` about
//! its sensors' centroid `c`. With two or more sensors on a floor their `2n` building-frame
//! channels carry three motions, so `2n − 3` combinations of them are zero whatever the
//! building does; a sensor turned in plan by `β` beyond its declared mounting breaks them. The
//! turns `β_s` that best restore them minimise `J(β) = tr(P·D(β)·M·D(β)ᵀ)`, `M` the channels'
//! second moment over the window, `D(β)` the block-diagonal rotations `Rot(β_s)` and `P` the
//! projector onto the complement of the rigid motions (found per sensor on a 1° grid, then
//! refined, in sweeps until nothing moves). Turning every sensor of a floor by 180° is again a
//! rigid motion, so a floor's common turn is known modulo 180° (the smaller is taken), and any
//! common turn at all only through the floor's torsion: when the data cannot place it, the
//! pair's relative turn still can, and a pair that disagrees is named together. A sensor alone
//! on its floor is not checked in plan. Uncertainty by the delete-one-block jackknife (`M` is
//! kept per block), ν = blocks − 1.
//!
//! **Clock offset, from the modes' phases.** A node whose stamps are `δt` off the others' turns
//! every component of its channels in every mode by `2π·f·δt`: `imag/real` of component `c` of
//! mode `k` is `2π·f_k·(δt_s(c) − δt_s(ref k))`, `s(ref k)` the sensor of the mode's reference
//! component, for a classically damped building. Weighted least squares over every quantified
//! mode's components (weights from their statistical uncertainties; the phase taken modulo a
//! half turn, `atan(imag/real)`) gives each node's offset up to a common one, set by the median
//! node being on time (so the median node's offset is 0 exactly, and the others' uncertainty
//! includes its). Two close modes leak into each other with a complex coefficient, which looks
//! like a phase: components of a mode with a partner within 3 % in frequency are left out.
//!
//! A sensor is **named** (a finding in words) when the whole interval of its estimate at a
//! false-naming probability of 10⁻³ per sensor and window lies beyond what it is allowed:
//! `mounting_tolerance_deg` for tilt and plan turns, and for the clock `k₉₅` times the stated
//! time-stamp uncertainty of its chain.

use nalgebra::{DMatrix, Matrix2, Vector3};
use serde::{Deserialize, Serialize};

use crate::identify::Mode;
use crate::model::{BuildingModel, Direction};
use crate::uncertainty::{coverage_factor, jackknife_variance, Estimate};
use crate::window::{Channels, Window};

/// False-naming probability of each check, per sensor and window.
pub const FALSE_NAMING_PROBABILITY: f64 = 1e-3;
/// Standard gravity, m/s²: the static part is gravity when its magnitude is within 10 % of it.
const GRAVITY_MPS2: f64 = 9.806_65;
/// Modes closer than this share of their frequency leak into each other's phases.
const PARTNER_SHARE: f64 = 0.03;

/// What the checks found for one sensor.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SensorCheck {
    pub sensor_id: String,
    /// The angle between the building's vertical and the sensor's gravity through its declared
    /// mounting, degrees; none when the streams carry no gravity.
    pub tilt_deg: Option<Estimate>,
    /// The sensor's turn in plan beyond its declared mounting (counter-clockwise seen from
    /// above), degrees, from its floor's rigid motion; none when alone on its floor.
    pub plan_rotation_deg: Option<Estimate>,
    /// The node's clock offset against the building's median node, s (its sample stamped `t`
    /// is the motion at `t + offset`); none without modes to read it from.
    pub time_offset_s: Option<Estimate>,
    /// Each finding that names the sensor, in words.
    pub findings: Vec<String>,
}

/// Settings of the checks.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct CheckOptions {
    /// A tilt or plan turn beyond the declared mounting up to this is accepted, degrees.
    pub mounting_tolerance_deg: f64,
}

impl Default for CheckOptions {
    fn default() -> Self {
        CheckOptions {
            mounting_tolerance_deg: 3.0,
        }
    }
}

/// Every check, per sensor of the window, in the window's order.
pub fn check_model(
    model: &BuildingModel,
    window: &Window,
    channels: &Channels,
    modes: &[Mode],
    blocks: usize,
    options: &CheckOptions,
) -> Vec<SensorCheck> {
    let mut out: Vec<SensorCheck> = window
        .sensors
        .iter()
        .map(|s| SensorCheck {
            sensor_id: s.sensor_id.clone(),
            tilt_deg: None,
            plan_rotation_deg: None,
            time_offset_s: None,
            findings: Vec::new(),
        })
        .collect();
    let nb = blocks.max(2);
    let k_name = coverage_factor((nb - 1) as f64, 1.0 - FALSE_NAMING_PROBABILITY);
    let tolerance = options.mounting_tolerance_deg.abs();
    for (check, series) in out.iter_mut().zip(&window.sensors) {
        let Some(index) = model.sensor_index(&series.sensor_id) else {
            continue;
        };
        if let Some(tilt) = tilt(model, index, series, nb) {
            if tilt.value - k_name * tilt.standard_uncertainty > tolerance {
                check.findings.push(format!(
                    "sensor {}: tilted {:.1}° ± {:.1}° from its declared mounting (gravity \
                     through the declared mounting is off the building's vertical, beyond the \
                     {tolerance}° allowed): its mounting is not as declared",
                    series.sensor_id,
                    tilt.value,
                    tilt.expanded_uncertainty()
                ));
            }
            check.tilt_deg = Some(tilt);
        }
    }
    plan_rotations(model, channels, nb, k_name, tolerance, &mut out);
    clock_offsets(channels, modes, k_name, &mut out);
    out
}

/// The tilt of one sensor from its static part.
fn tilt(
    model: &BuildingModel,
    index: usize,
    series: &crate::window::SensorSeries,
    blocks: usize,
) -> Option<Estimate> {
    let n = series.acceleration_mps2.len();
    let mut sums = vec![(Vector3::zeros(), 0usize); blocks];
    for (m, (a, &v)) in series
        .acceleration_mps2
        .iter()
        .zip(&series.valid)
        .enumerate()
    {
        if v && a.iter().all(|x| x.is_finite()) {
            let b = (m * blocks / n.max(1)).min(blocks - 1);
            sums[b].0 += Vector3::new(a[0], a[1], a[2]);
            sums[b].1 += 1;
        }
    }
    let total: (Vector3<f64>, usize) = sums
        .iter()
        .fold((Vector3::zeros(), 0), |acc, s| (acc.0 + s.0, acc.1 + s.1));
    if total.1 == 0 || sums.iter().any(|s| s.1 == 0) {
        return None;
    }
    let r = model.sensors[index].rotation();
    let angle = |sum: Vector3<f64>| -> Option<f64> {
        let g = r * sum;
        let norm = g.norm();
        (norm > 0.0).then(|| (g[2] / norm).clamp(-1.0, 1.0).acos().to_degrees())
    };
    let mean = total.0 / total.1 as f64;
    if ((mean.norm() - GRAVITY_MPS2) / GRAVITY_MPS2).abs() > 0.1 {
        return None;
    }
    let value = angle(total.0)?;
    let replicates: Vec<f64> = (0..blocks)
        .filter_map(|b| angle(total.0 - sums[b].0))
        .collect();
    let statistical = jackknife_variance(&replicates).max(0.0);
    let chain = series.chain.cross_axis_u.to_degrees().powi(2);
    Some(crate::uncertainty::combine(
        value,
        statistical,
        (blocks - 1) as f64,
        chain,
        series.chain.dof,
        0.95,
    ))
}

fn rotation(angle_rad: f64) -> Matrix2<f64> {
    let (s, c) = angle_rad.sin_cos();
    Matrix2::new(c, -s, s, c)
}

/// `J(β)` of the module's documentation.
fn misfit(projector: &DMatrix<f64>, moment: &DMatrix<f64>, turns: &[f64]) -> f64 {
    let n = turns.len();
    let mut d = DMatrix::zeros(2 * n, 2 * n);
    for (s, &b) in turns.iter().enumerate() {
        d.view_mut((2 * s, 2 * s), (2, 2)).copy_from(&rotation(b));
    }
    (projector * &d * moment * d.transpose()).trace()
}

/// The turns that minimise the misfit, from `start`, searching each sensor's turn over
/// `±span` (rad) on a grid of `step` and refining, sweep after sweep.
fn minimise(
    projector: &DMatrix<f64>,
    moment: &DMatrix<f64>,
    start: &[f64],
    span: f64,
    step: f64,
) -> Vec<f64> {
    let mut turns = start.to_vec();
    let mut best = misfit(projector, moment, &turns);
    for _ in 0..20 {
        let before = turns.clone();
        for s in 0..turns.len() {
            let centre = turns[s];
            let steps = (span / step).ceil() as i64;
            let mut at = centre;
            for i in -steps..=steps {
                let mut trial = turns.clone();
                trial[s] = centre + i as f64 * step;
                let j = misfit(projector, moment, &trial);
                if j < best {
                    best = j;
                    at = trial[s];
                }
            }
            // Golden-section refinement within a grid step either side.
            let (mut lo, mut hi) = (at - step, at + step);
            let g = 0.5 * (5f64.sqrt() - 1.0);
            let eval = |x: f64, turns: &[f64]| {
                let mut trial = turns.to_vec();
                trial[s] = x;
                misfit(projector, moment, &trial)
            };
            for _ in 0..40 {
                let a = hi - g * (hi - lo);
                let b = lo + g * (hi - lo);
                if eval(a, &turns) < eval(b, &turns) {
                    hi = b;
                } else {
                    lo = a;
                }
            }
            let x = 0.5 * (lo + hi);
            let j = eval(x, &turns);
            turns[s] = if j < best {
                best = j;
                x
            } else {
                at
            };
        }
        let moved = turns
            .iter()
            .zip(&before)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0, f64::max);
        if moved < 1e-9 {
            break;
        }
    }
    turns
}

/// Wraps an angle into (−π, π].
fn wrap(a: f64) -> f64 {
    let t = a.rem_euclid(2.0 * std::f64::consts::PI);
    if t > std::f64::consts::PI {
        t - 2.0 * std::f64::consts::PI
    } else {
        t
    }
}

/// The representative of a floor's turns modulo a common half turn: the one nearer the
/// declared mountings.
fn representative(turns: &[f64]) -> Vec<f64> {
    let plain: Vec<f64> = turns.iter().map(|&b| wrap(b)).collect();
    let flipped: Vec<f64> = turns
        .iter()
        .map(|&b| wrap(b + std::f64::consts::PI))
        .collect();
    let size = |v: &[f64]| v.iter().map(|b| b.abs()).sum::<f64>();
    if size(&flipped) < size(&plain) {
        flipped
    } else {
        plain
    }
}

fn plan_rotations(
    model: &BuildingModel,
    channels: &Channels,
    blocks: usize,
    k_name: f64,
    tolerance_deg: f64,
    out: &mut [SensorCheck],
) {
    // Per floor, the sensors with both horizontal channels.
    let mut floors: std::collections::BTreeMap<u32, Vec<(usize, usize, usize)>> =
        std::collections::BTreeMap::new();
    for (s, check) in out.iter().enumerate() {
        let Some(index) = model.sensor_index(&check.sensor_id) else {
            continue;
        };
        let find = |d: Direction| {
            channels
                .ids
                .iter()
                .position(|c| c.sensor_id == check.sensor_id && c.direction == d)
        };
        if let (Some(x), Some(y)) = (find(Direction::X), find(Direction::Y)) {
            floors
                .entry(model.sensors[index].floor)
                .or_default()
                .push((s, x, y));
        }
    }
    let n_samples = channels.len();
    let dof = (blocks - 1) as f64;
    for (floor, sensors) in floors {
        let n = sensors.len();
        if n < 2 || floor == 0 {
            continue;
        }
        let positions: Vec<[f64; 2]> = sensors
            .iter()
            .map(|&(s, _, _)| {
                model
                    .sensor_index(&out[s].sensor_id)
                    .map_or([0.0; 2], |i| model.sensors[i].position_m)
            })
            .collect();
        let centre = [
            positions.iter().map(|p| p[0]).sum::<f64>() / n as f64,
            positions.iter().map(|p| p[1]).sum::<f64>() / n as f64,
        ];
        let mut g = DMatrix::zeros(2 * n, 3);
        for (s, p) in positions.iter().enumerate() {
            g[(2 * s, 0)] = 1.0;
            g[(2 * s, 2)] = -(p[1] - centre[1]);
            g[(2 * s + 1, 1)] = 1.0;
            g[(2 * s + 1, 2)] = p[0] - centre[0];
        }
        let gtg = g.transpose() * &g;
        let Some(inverse) = gtg.try_inverse() else {
            continue;
        };
        let projector = DMatrix::identity(2 * n, 2 * n) - &g * inverse * g.transpose();
        // Second moments per block, over samples where every channel of the floor is valid.
        let rows: Vec<usize> = sensors.iter().flat_map(|&(_, x, y)| [x, y]).collect();
        let mut moments = vec![DMatrix::zeros(2 * n, 2 * n); blocks];
        for (b, moment) in moments.iter_mut().enumerate() {
            let (t0, t1) = (b * n_samples / blocks, (b + 1) * n_samples / blocks);
            for t in t0..t1 {
                if rows.iter().any(|&c| channels.mask[c][t] == 0.0) {
                    continue;
                }
                for (i, &a) in rows.iter().enumerate() {
                    let va = channels.data[a][t];
                    for (j, &c) in rows.iter().enumerate().skip(i) {
                        moment[(i, j)] += va * channels.data[c][t];
                    }
                }
            }
            for i in 0..2 * n {
                for j in 0..i {
                    moment[(i, j)] = moment[(j, i)];
                }
            }
        }
        let total: DMatrix<f64> = moments
            .iter()
            .fold(DMatrix::zeros(2 * n, 2 * n), |acc, m| acc + m);
        if total.trace() <= 0.0 {
            continue;
        }
        let degree = std::f64::consts::PI / 180.0;
        let turns = representative(&minimise(
            &projector,
            &total,
            &vec![0.0; n],
            std::f64::consts::PI,
            degree,
        ));
        let replicates: Vec<Vec<f64>> = (0..blocks)
            .map(|b| {
                let m = &total - &moments[b];
                let r = minimise(&projector, &m, &turns, 5.0 * degree, 0.25 * degree);
                // Each replicate on the full estimate's branch of the half turn.
                r.iter().zip(&turns).map(|(x, t)| t + wrap(x - t)).collect()
            })
            .collect();
        // The chain's cross-axis terms turn a sensor's axes by up to their size (rad): the
        // chain's part of a turn's uncertainty, with its degrees of freedom.
        let chain = |s: usize| {
            let c = &channels.chains[channels.sensor_index[sensors[s].1]];
            (c.cross_axis_u.to_degrees().powi(2), c.dof)
        };
        let estimate = |values: Vec<f64>, value: f64, chain: (f64, f64)| {
            crate::uncertainty::combine(
                value.to_degrees(),
                jackknife_variance(&values)
                    .max(0.0)
                    .to_degrees()
                    .to_degrees(),
                dof,
                chain.0,
                chain.1,
                0.95,
            )
        };
        let mut named = vec![false; n];
        for (s, &(check, _, _)) in sensors.iter().enumerate() {
            let e = estimate(
                replicates.iter().map(|r| r[s]).collect(),
                turns[s],
                chain(s),
            );
            if e.value.abs() - k_name * e.standard_uncertainty > tolerance_deg {
                named[s] = true;
                out[check].findings.push(format!(
                    "sensor {}: turned {:+.1}° ± {:.1}° in plan beyond its declared mounting \
                     (floor {floor}'s rigid motion, shared with its other sensors, beyond the \
                     {tolerance_deg}° allowed): its mounting is not as declared",
                    out[check].sensor_id,
                    e.value,
                    e.expanded_uncertainty()
                ));
            }
            out[check].plan_rotation_deg = Some(e);
        }
        // A pair that disagrees when neither alone can be told: both named together.
        for a in 0..n {
            for b in a + 1..n {
                if named[a] || named[b] {
                    continue;
                }
                let values: Vec<f64> = replicates.iter().map(|r| r[a] - r[b]).collect();
                let (ca, cb) = (chain(a), chain(b));
                let e = estimate(values, turns[a] - turns[b], (ca.0 + cb.0, ca.1.min(cb.1)));
                if e.value.abs() - k_name * e.standard_uncertainty > tolerance_deg {
                    let (ia, ib) = (sensors[a].0, sensors[b].0);
                    let text = format!(
                        "sensors {} and {} on floor {floor} disagree by {:.1}° ± {:.1}° in plan \
                         (their floor's rigid motion, beyond the {tolerance_deg}° allowed): one \
                         of them is not mounted as declared",
                        out[ia].sensor_id,
                        out[ib].sensor_id,
                        e.value.abs(),
                        e.expanded_uncertainty()
                    );
                    out[ia].findings.push(text.clone());
                    out[ib].findings.push(text);
                }
            }
        }
    }
}

fn clock_offsets(channels: &Channels, modes: &[Mode], k_name: f64, out: &mut [SensorCheck]) {
    let sensors: Vec<String> = out.iter().map(|c| c.sensor_id.clone()).collect();
    let n = sensors.len();
    if n < 2 || modes.is_empty() {
        return;
    }
    let sensor_of = |c: usize| -> Option<usize> {
        sensors
            .iter()
            .position(|s| *s == channels.ids.get(c).map_or("", |id| id.sensor_id.as_str()))
    };
    // Normal equations of the weighted least squares, with a row fixing the mean offset (the
    // gauge; the median is set afterwards).
    let mut ata = DMatrix::zeros(n, n);
    let mut atb = nalgebra::DVector::zeros(n);
    let mut rows = 0usize;
    let mut dof = f64::INFINITY;
    for mode in modes {
        let f = mode.frequency_hz.value;
        if modes
            .iter()
            .any(|m| !std::ptr::eq(m, mode) && (m.frequency_hz.value - f).abs() < PARTNER_SHARE * f)
        {
            continue;
        }
        let Some(reference) = sensor_of(mode.reference_component) else {
            continue;
        };
        let omega = 2.0 * std::f64::consts::PI * f;
        for (c, component) in mode.shape.iter().enumerate() {
            let Some(s) = sensor_of(c) else {
                continue;
            };
            if s == reference {
                continue;
            }
            let re = component.real.value;
            let u_re = component.real.standard_uncertainty;
            let u_im = (component.imag.standard_uncertainty.powi(2)
                - component.chain_variance_imag)
                .max(0.0)
                .sqrt();
            if !(re.abs() > 5.0 * u_re && re.abs() > 0.05 && u_im > 0.0) {
                continue;
            }
            // The phase modulo a half turn (true shapes are real: in or against phase).
            let ratio = component.imag.value / re;
            let y = ratio.atan();
            let u_y = u_im / re.abs() / (1.0 + ratio * ratio);
            let w = 1.0 / (u_y * u_y);
            // y = ω·(τ_s − τ_ref).
            let mut a = nalgebra::DVector::zeros(n);
            a[s] = omega;
            a[reference] = -omega;
            ata += &a * a.transpose() * w;
            atb += &a * (y * w);
            rows += 1;
            dof = dof.min(component.imag.dof);
        }
    }
    if rows < n {
        return;
    }
    let scale = ata.diagonal().max().max(1.0);
    let gauge = nalgebra::DVector::from_element(n, 1.0);
    let system = &ata + &gauge * gauge.transpose() * scale;
    let Some(inverse) = system.try_inverse() else {
        return;
    };
    let tau = &inverse * &atb;
    let mut sorted: Vec<f64> = tau.iter().copied().collect();
    sorted.sort_by(f64::total_cmp);
    let median = sorted[n / 2];
    let median_sensor = (0..n).find(|&s| tau[s] == median).unwrap_or(0);
    // The covariance of the gauge-constrained solution; each offset is against the median
    // node's, itself an estimate: var(τ_s − τ_m) from the covariance.
    let covariance = &inverse * &ata * &inverse;
    let m = median_sensor;
    let k_stated = 1.96;
    for s in 0..n {
        let u = if s == m {
            0.0
        } else {
            (covariance[(s, s)] + covariance[(m, m)] - 2.0 * covariance[(s, m)])
                .max(0.0)
                .sqrt()
        };
        let e = Estimate::new(tau[s] - median, u, dof.max(1.0), 0.95);
        let stated_u = chain_timestamp_u(channels, &sensors[s]);
        let allowed = k_stated * stated_u;
        let k = coverage_factor(dof.max(1.0), 1.0 - FALSE_NAMING_PROBABILITY).max(k_name);
        if e.value.abs() - k * e.standard_uncertainty > allowed {
            out[s].findings.push(format!(
                "sensor {}: its node's clock is {:+.2} ms ± {:.2} ms off the building's (from \
                 the phase of its shape components in every mode), beyond the ±{:.2} ms its \
                 stated time-stamp uncertainty allows: its stamps are not the motion's times",
                sensors[s],
                1e3 * e.value,
                1e3 * e.expanded_uncertainty(),
                1e3 * allowed
            ));
        }
        out[s].time_offset_s = Some(e);
    }
}

/// The stated time-stamp uncertainty of a sensor's chain, s.
fn chain_timestamp_u(channels: &Channels, sensor_id: &str) -> f64 {
    channels
        .ids
        .iter()
        .position(|c| c.sensor_id == sensor_id)
        .and_then(|c| channels.chains.get(channels.sensor_index[c]))
        .map_or(0.0, |chain| chain.timestamp_u_s)
}
