//! Inter-storey drift ratio between instrumented floors: the peak of the relative
//! displacement of two floors over the height between them, per building direction.
//!
//! A floor's displacement is the mean of its sensors' band-passed displacements in the
//! building frame ([`crate::process`]); the drift of a storey pair is their difference, and
//! its ratio `max_t |D_upper(t) − D_lower(t)| / h`. Its uncertainty, first order, adds every
//! sensor's calibration and noise parts (independent sensors) and the clocks': a sensor whose
//! stamps are off by `δ` shows its floor's motion `δ` late, an error `v(t*)·δ` (the floor's
//! absolute velocity), `δ` of standard deviation `clock_uncertainty_s`.
//!
//! **What the band-pass loses, as a bound.** The value estimates the drift of the band-passed
//! motion; the storey's true drift differs by what the band removed, bounded (`bias_bound`,
//! same unit as the ratio) by the sum of:
//!
//! - *below the band:* relative displacement at frequencies well below the fundamental is
//!   quasi-static, `K·a_g(t)` with `K` the storey's flexibility under the ground's acceleration
//!   `a_g`. For a building whose first mode dominates, `K ≤ 1.6·ρ/ω₁²` (1.6 bounds the first
//!   mode's participation at the top, `Γφ`, for shear and flexural buildings; `ρ` the storey's
//!   share of the top's drift over the bottom, measured in the event; `ω₁` the fundamental,
//!   from the modes service or the event's own top-to-bottom drift). `a_g`'s part below the
//!   band is the lowest floor's acceleration through the band's complement (its low pass at
//!   the low corner, [`crate::filter::BandPass::low_band`]): its peak, noise and all, bounds it;
//! - *the band's gain at the fundamental:* `(1/G(f₁) − 1)·value`;
//! - *the trapezoidal integration:* twice integrated, a component of frequency `f` comes out
//!   `(2πfΔt)²/6` low, so at most `Δt²/6` times twice the peak relative acceleration;
//! - *sensors off each other's grid:* the part of a sample period `δ` by which two floors'
//!   grids differ (known from their time stamps), times the peak relative velocity.

use crate::din4150::dominant_frequency;
use crate::estimate::Budget;
use crate::parameters::Value;
use crate::process::{axis, integrate_adjoint, Processed};

/// The first mode's participation at the top is below this for shear and flexural buildings.
pub const PARTICIPATION_BOUND: f64 = 1.6;

/// One storey pair in one direction.
#[derive(Debug, Clone, PartialEq)]
pub struct StoreyDrift {
    pub lower_floor: i32,
    pub upper_floor: i32,
    /// Between the two floors' mean sensor heights, m.
    pub storey_height_m: f64,
    /// 0 for `x`, 1 for `y`.
    pub direction: usize,
    pub lower_sensors: Vec<String>,
    pub upper_sensors: Vec<String>,
    /// The band-passed drift ratio (dimensionless) and when its peak was.
    pub drift_ratio: Value,
    /// Bound on |true drift ratio − band-passed one| (dimensionless), and its parts.
    pub bias_bound: f64,
    pub bias_below_band: f64,
    pub bias_band_gain: f64,
    pub bias_integration: f64,
    pub bias_alignment: f64,
    /// The fundamental the bound used, Hz, and whether it was measured in this event.
    pub fundamental_hz: f64,
    pub fundamental_from_event: bool,
    /// A sensor of either floor was flagged.
    pub flagged: bool,
}

struct Floor {
    floor: i32,
    height_m: f64,
    members: Vec<(usize, isize)>,
}

/// Drift ratios of every pair of consecutive instrumented floors in `x` and `y`. Sensors on
/// another sample rate than the first are left out (named in the second list).
pub fn storey_drifts(
    sensors: &[Processed],
    clock_uncertainty_s: f64,
    fundamental_hz: [Option<f64>; 2],
    probability: f64,
) -> (Vec<StoreyDrift>, Vec<String>) {
    let mut left_out = Vec::new();
    let Some(reference) = sensors.first() else {
        return (Vec::new(), left_out);
    };
    let dt = reference.dt;
    // Each sensor's offset on the reference's padded grid, and what is left of a sample.
    let mut floors: Vec<Floor> = Vec::new();
    let mut residual_s = vec![0.0; sensors.len()];
    for (j, p) in sensors.iter().enumerate() {
        if (p.dt - dt).abs() > 1e-9 * dt {
            left_out.push(p.sensor_id.clone());
            continue;
        }
        let offset = (p.origin_s - reference.origin_s) / dt;
        let shift = offset.round() as isize;
        residual_s[j] = (offset - shift as f64) * dt;
        match floors.iter_mut().find(|f| f.floor == p.floor) {
            Some(f) => f.members.push((j, shift)),
            None => floors.push(Floor {
                floor: p.floor,
                height_m: 0.0,
                members: vec![(j, shift)],
            }),
        }
    }
    for f in &mut floors {
        f.height_m = f
            .members
            .iter()
            .map(|(j, _)| sensors[*j].height_m)
            .sum::<f64>()
            / f.members.len() as f64;
    }
    floors.sort_by(|a, b| a.height_m.total_cmp(&b.height_m));
    if floors.len() < 2 {
        return (Vec::new(), left_out);
    }
    // The common stretch of every member's padded record, on the reference's grid.
    let (mut lo, mut hi) = (isize::MIN, isize::MAX);
    for f in &floors {
        for &(j, shift) in &f.members {
            lo = lo.max(shift);
            hi = hi.min(shift + sensors[j].len_padded() as isize);
        }
    }
    if hi - lo < 16 {
        return (
            Vec::new(),
            sensors.iter().map(|p| p.sensor_id.clone()).collect(),
        );
    }
    let len = (hi - lo) as usize;
    let mean_of = |f: &Floor, pick: &dyn Fn(&Processed) -> &[f64]| -> Vec<f64> {
        let mut out = vec![0.0; len];
        for &(j, shift) in &f.members {
            let series = pick(&sensors[j]);
            for (i, o) in out.iter_mut().enumerate() {
                *o += series[(lo + i as isize - shift) as usize] / f.members.len() as f64;
            }
        }
        out
    };
    let peak = |x: &[f64]| {
        x.iter()
            .enumerate()
            .fold((0usize, 0.0f64), |(bi, bv), (i, v)| {
                if v.abs() > bv {
                    (i, v.abs())
                } else {
                    (bi, bv)
                }
            })
    };
    let bottom = &floors[0];
    let top = &floors[floors.len() - 1];
    let mut out = Vec::new();
    for (direction, known_fundamental) in fundamental_hz.iter().enumerate() {
        let disp = |f: &Floor| mean_of(f, &|p: &Processed| &p.disp_b[direction][..]);
        let vel = |f: &Floor| mean_of(f, &|p: &Processed| &p.vel_b[direction][..]);
        let acc = |f: &Floor| mean_of(f, &|p: &Processed| &p.b[direction][..]);
        let (d_top, d_bottom) = (disp(top), disp(bottom));
        let whole: Vec<f64> = d_top.iter().zip(&d_bottom).map(|(a, b)| a - b).collect();
        let (whole_i, whole_peak) = peak(&whole);
        let (f1, from_event) = match known_fundamental {
            Some(f) => (*f, false),
            None => (
                dominant_frequency(&whole, whole_i, dt, 0.0)
                    .map_or(reference.band.low_hz * 2.0, |x| x.0),
                true,
            ),
        };
        let omega1 = 2.0 * std::f64::consts::PI * f1;
        // The lowest floor's acceleration below the band.
        let low_band = reference.band.low_band();
        let mut a_low = vec![0.0; len];
        for &(j, shift) in &bottom.members {
            let p = &sensors[j];
            let filtered = low_band.filter(&p.raw_b[direction]);
            for (i, o) in a_low.iter_mut().enumerate() {
                let k = lo + i as isize - shift;
                if let Some(v) = filtered.get(k as usize) {
                    *o += v / bottom.members.len() as f64;
                }
            }
        }
        let a_low_peak = peak(&a_low).1;
        for pair in floors.windows(2) {
            let (lower, upper) = (&pair[0], &pair[1]);
            let h = upper.height_m - lower.height_m;
            if h <= 0.0 {
                continue;
            }
            let (du, dl) = (disp(upper), disp(lower));
            let d: Vec<f64> = du.iter().zip(&dl).map(|(a, b)| a - b).collect();
            let (t, peak_d) = peak(&d);
            let sign = if d[t] < 0.0 { -1.0 } else { 1.0 };
            let mut budget = Budget::new();
            let mut clock = 0.0;
            for (f, s) in [(upper, 1.0), (lower, -1.0)] {
                for &(j, shift) in &f.members {
                    let p = &sensors[j];
                    let local = (lo + t as isize - shift) as usize;
                    let w = sign * s / (f.members.len() as f64 * h);
                    let weights =
                        integrate_adjoint(&integrate_adjoint(&p.delta(local, w), p.dt), p.dt);
                    let terms = [(axis(direction), weights)];
                    let (cal, noise) = p.covariance(&terms, &terms);
                    budget.add(cal, p.covariance_dof).add(noise, p.noise_dof);
                    clock += (clock_uncertainty_s * p.vel_b[direction][local] * w).powi(2);
                }
            }
            budget.add(clock, f64::INFINITY);
            let value = peak_d / h;
            let rho = if whole_peak > 0.0 {
                (peak_d / whole_peak).min(1.0)
            } else {
                1.0
            };
            let below = PARTICIPATION_BOUND * rho / (omega1 * omega1) * a_low_peak / h;
            let gain = reference.band.gain(f1);
            let band_gain = if gain > 0.0 {
                (1.0 / gain - 1.0) * value
            } else {
                f64::INFINITY
            };
            let (au, al) = (acc(upper), acc(lower));
            let a_rel = peak(&au.iter().zip(&al).map(|(a, b)| a - b).collect::<Vec<_>>()).1;
            let integration = dt * dt / 6.0 * 2.0 * a_rel / h;
            let (vu, vl) = (vel(upper), vel(lower));
            let v_rel = peak(&vu.iter().zip(&vl).map(|(a, b)| a - b).collect::<Vec<_>>()).1;
            let offsets: Vec<f64> = upper
                .members
                .iter()
                .chain(&lower.members)
                .map(|(j, _)| residual_s[*j])
                .collect();
            let spread = offsets.iter().cloned().fold(f64::MIN, f64::max)
                - offsets.iter().cloned().fold(f64::MAX, f64::min);
            let alignment = spread.abs() * v_rel / h;
            let ids = |f: &Floor| {
                f.members
                    .iter()
                    .map(|(j, _)| sensors[*j].sensor_id.clone())
                    .collect()
            };
            out.push(StoreyDrift {
                lower_floor: lower.floor,
                upper_floor: upper.floor,
                storey_height_m: h,
                direction,
                lower_sensors: ids(lower),
                upper_sensors: ids(upper),
                drift_ratio: Value {
                    estimate: budget.estimate(value, probability),
                    at_s: Some(reference.time_s((lo + t as isize) as usize)),
                    angle_deg: None,
                },
                bias_bound: below + band_gain + integration + alignment,
                bias_below_band: below,
                bias_band_gain: band_gain,
                bias_integration: integration,
                bias_alignment: alignment,
                fundamental_hz: f1,
                fundamental_from_event: from_event,
                flagged: upper
                    .members
                    .iter()
                    .chain(&lower.members)
                    .any(|(j, _)| sensors[*j].flagged),
            });
        }
    }
    (out, left_out)
}
