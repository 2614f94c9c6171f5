//! Strong-motion parameters of one sensor, per building direction, each with its standard
//! uncertainty and coverage factor.
//!
//! Every parameter is of the processed record ([`crate::process`]: baseline removed,
//! band-passed with zero phase, in the building frame), as strong-motion processing defines
//! them (PEER, COSMOS): the band's corners are part of the definition, and the truth a parameter
//! estimates is the same parameter of the true motion through the same band.
//!
//! | parameter | definition | noise |
//! |---|---|---|
//! | PGA | `max |b(t)|` over the samples | bootstrap ([`crate::peaks`]) |
//! | RotD50, RotD100 of PGA | median, max over θ of `max |cos θ b_x + sin θ b_y|` | bootstrap |
//! | PGV, PGD | peaks of the trapezoidal integrals of `b` | first order |
//! | Arias intensity | `π/(2g)·Σ (b² − σ²)·Δt` over the record (σ² the band-passed noise) | first order and the squares' variance |
//! | CAV | `Σ |b|·Δt` over the record | SIMEX (below) |
//! | D5–95 | time from 5 % to 95 % of the cumulative Arias intensity (linear between samples) | first order through the crossings |
//! | PSA(T) | `ω²·max|u|` of the 5 %-damped oscillator ([`crate::oscillator`]), per direction and RotD50/100 | first order |
//!
//! CAV's noise term: noise adds `E|s + n| − |s|` to every sample, 0.80σ where there is no
//! motion and `σ²/(2|s|)` where the motion is strong; no estimator of `|s|` is unbiased, so the
//! bias is extrapolated away by SIMEX over whole noise records, linearly in the noise's
//! deviation, which is exact where there is no motion, the part that matters (where the motion
//! is strong the bias, second order in the noise, is left: `σ²/|s|` per sample, against a
//! calibration part of the gain's fraction of `|s|`) ([`crate::peaks::simex`]).
//!
//! Calibration: first order in the sensitivity's nine entries with the record's covariance
//! ([`crate::process`]), at the record's ν; noise at its own ν; `k` from Welch–Satterthwaite.

use nalgebra::{DMatrix, Vector3};
use serde::Deserialize;

use crate::estimate::{Budget, Estimate, DEFAULT_COVERAGE_PROBABILITY};
use crate::filter::BandConfig;
use crate::oscillator::{Oscillator, STANDARD_PERIODS_S};
use crate::peaks::{
    angle_direction, bootstrap, by_magnitude, draws as draws_of, rotd, rotd_peaks, simex,
    Extrapolant, PeakNoise, SIMEX_REPLICATES,
};
use crate::process::{axis, integrate_adjoint, Processed, Term};
use crate::rng::Rng;

/// Standard gravity, m/s² (Arias intensity's `g`).
pub const STANDARD_GRAVITY_MPS2: f64 = 9.806_65;

/// How parameters are computed.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ParameterConfig {
    pub band: BandConfig,
    /// Oscillator periods, s.
    pub periods_s: Vec<f64>,
    /// Oscillator damping ratio.
    pub damping: f64,
    /// Noise draws for the sample peaks' bootstrap.
    pub bootstrap_draws: usize,
    pub coverage_probability: f64,
}

impl Default for ParameterConfig {
    fn default() -> Self {
        ParameterConfig {
            band: BandConfig::default(),
            periods_s: STANDARD_PERIODS_S.to_vec(),
            damping: 0.05,
            bootstrap_draws: 40,
            coverage_probability: DEFAULT_COVERAGE_PROBABILITY,
        }
    }
}

/// A parameter's estimate, and for a peak when (and for a rotated component at which angle) it
/// occurred.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Value {
    pub estimate: Estimate,
    /// Time of the peak, s from the reference instant.
    pub at_s: Option<f64>,
    /// Angle of the rotated horizontal component, degrees from building `x` towards `y`.
    pub angle_deg: Option<f64>,
}

impl Value {
    fn of(estimate: Estimate) -> Value {
        Value {
            estimate,
            at_s: None,
            angle_deg: None,
        }
    }
}

/// One building direction's parameters.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AxisParameters {
    /// Peak acceleration, m/s².
    pub pga: Value,
    /// Peak velocity, m/s.
    pub pgv: Value,
    /// Peak displacement, m.
    pub pgd: Value,
    /// Arias intensity, m/s.
    pub arias: Value,
    /// Cumulative absolute velocity, m/s.
    pub cav: Value,
    /// Significant duration D5–95, s; none when the record's Arias intensity is not positive.
    pub d5_95: Option<Value>,
}

/// One period of the response spectrum.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SpectralOrdinate {
    pub period_s: f64,
    /// Within what the band supports: `T ≤ 1/(1.25·low_hz)` and `1/T ≤ high_hz`.
    pub usable: bool,
    /// Pseudo-spectral acceleration per building direction, m/s².
    pub axes: [Value; 3],
    pub rotd50: Value,
    pub rotd100: Value,
}

/// Everything one sensor's record says.
#[derive(Debug, Clone, PartialEq)]
pub struct SensorParameters {
    pub sensor_id: String,
    pub floor: i32,
    pub height_m: f64,
    /// Building `x`, `y`, `z`.
    pub axes: [AxisParameters; 3],
    pub pga_rotd50: Value,
    pub pga_rotd100: Value,
    pub spectrum: Vec<SpectralOrdinate>,
    pub samples: usize,
    pub invalid_samples: usize,
    /// The record's flag ([`crate::process::SensorRecord::flagged`]).
    pub flagged: bool,
    pub pre_event_baseline: bool,
    /// Standard deviation of one band-passed noise sample per direction, m/s².
    pub noise_mps2: [f64; 3],
    pub bootstrap_candidates: usize,
}

fn peak(x: &[f64]) -> (usize, f64) {
    x.iter().enumerate().fold(
        (0, 0.0),
        |(bi, bv), (i, v)| if v.abs() > bv { (i, v.abs()) } else { (bi, bv) },
    )
}

fn sign(v: f64) -> f64 {
    if v < 0.0 {
        -1.0
    } else {
        1.0
    }
}

/// Calibration and noise variances into an estimate.
fn estimate(p: &Processed, value: f64, cal: f64, noise: f64, probability: f64) -> Estimate {
    let mut b = Budget::new();
    b.add(cal, p.covariance_dof).add(noise, p.noise_dof);
    b.estimate(value, probability)
}

/// The band-pass kernel's `Σ_lag ρ(lag)²`: how much more variance a sum of squared
/// band-passed noise samples has than of white ones.
fn squares_factor(p: &Processed) -> f64 {
    let k = &p.kernel;
    let r0: f64 = k.iter().map(|v| v * v).sum();
    if r0 == 0.0 {
        return 1.0;
    }
    let mut total = 0.0;
    for lag in 0..k.len() {
        let r: f64 = k.iter().zip(k.iter().skip(lag)).map(|(a, b)| a * b).sum();
        total += if lag == 0 {
            1.0
        } else {
            2.0 * (r / r0).powi(2)
        };
    }
    total
}

/// First time the cumulative `cum` (at record samples, after the sample) reaches `level`,
/// linear between samples, as a fractional sample position (`-1` is the instant before the
/// first sample, where the cumulative is 0); none if it never does.
fn crossing(cum: &[f64], level: f64) -> Option<(usize, f64)> {
    let mut prev = 0.0;
    for (k, &c) in cum.iter().enumerate() {
        if c >= level {
            let frac = if c > prev {
                (level - prev) / (c - prev)
            } else {
                1.0
            };
            return Some((k, k as f64 - 1.0 + frac.clamp(0.0, 1.0)));
        }
        prev = c;
    }
    None
}

/// Noise records CAV's extrapolation draws.
const CAV_DRAWS: usize = 24;

/// Crests considered when a smooth peak has rivals.
const MAX_CRESTS: usize = 40;

/// The peak of a smooth series along `w` (`series` its values over the padded record,
/// `weights(i)` the weights on `b` of its value at `i`), first order when it stands out, by
/// SIMEX over the crests within seven of its noise deviations when others are
/// ([`crate::peaks::simex`]). `correlation(i, j)`, when given, is `⟨M s_i, M s_j⟩` of the unit
/// weights at `i` and `j` (a stationary shortcut for a time-invariant series); otherwise the
/// weights are filtered one by one.
#[allow(clippy::too_many_arguments)]
fn smooth_peak_value(
    p: &Processed,
    series: &[f64],
    w: Vector3<f64>,
    weights: &dyn Fn(usize, f64) -> Vec<f64>,
    correlation: Option<&dyn Fn(usize, usize) -> f64>,
    probability: f64,
    draws: usize,
    seed: u64,
) -> Value {
    let (i, d) = peak(series);
    let terms = [(w, weights(i, sign(series[i])))];
    let along = (w.transpose() * p.noise_b * w)[(0, 0)];
    let (cal, noise) = match correlation {
        Some(r) => (
            p.calibration_variance(&terms),
            if p.has_noise() { along * r(i, i) } else { 0.0 },
        ),
        None => p.covariance(&terms, &terms),
    };
    let sd = noise.max(0.0).sqrt();
    let at_s = Some(p.time_s(i));
    let first_order = Value {
        estimate: estimate(p, d, cal, noise, probability),
        at_s,
        angle_deg: None,
    };
    if sd == 0.0 || draws < 2 {
        return first_order;
    }
    let mut crests: Vec<usize> = (1..series.len() - 1)
        .filter(|&j| {
            let a = series[j].abs();
            a >= series[j - 1].abs() && a >= series[j + 1].abs() && a >= d - 7.0 * sd
        })
        .collect();
    if !crests.contains(&i) {
        crests.push(i);
    }
    if crests.len() < 2 {
        return first_order;
    }
    crests.sort_by(|&a, &b| series[b].abs().total_cmp(&series[a].abs()));
    crests.truncate(MAX_CRESTS);
    let c = crests.len();
    let cov = match correlation {
        Some(r) => DMatrix::from_fn(c, c, |a, b| {
            along * r(crests[a], crests[b]) * if a == b { 1.0 + 1e-9 } else { 1.0 }
        }),
        None => {
            let filtered: Vec<Vec<f64>> = crests
                .iter()
                .map(|&j| {
                    let mut m = weights(j, 1.0);
                    p.band.apply(&mut m);
                    m[p.record_span()].to_vec()
                })
                .collect();
            DMatrix::from_fn(c, c, |a, b| {
                let v: f64 = filtered[a]
                    .iter()
                    .zip(&filtered[b])
                    .map(|(x, y)| x * y)
                    .sum();
                along * v * if a == b { 1.0 + 1e-9 } else { 1.0 }
            })
        }
    };
    let Some(l) = cov.cholesky().map(|ch| ch.l()) else {
        return first_order;
    };
    let mut rng = Rng::new(seed);
    let noise_draws = draws_of(&l, draws, &mut rng);
    let replicates = draws_of(&l, SIMEX_REPLICATES, &mut rng);
    let base: Vec<f64> = crests.iter().map(|&j| series[j]).collect();
    let out = simex(
        &base,
        &noise_draws,
        &replicates,
        Extrapolant::Linear,
        &mut |x: &[f64]| vec![x.iter().fold(0.0f64, |m, v| m.max(v.abs()))],
    );
    let (bias, spread) = out[0];
    Value {
        estimate: estimate(p, d - bias, cal, spread * spread, probability),
        at_s,
        angle_deg: None,
    }
}

/// Computes every parameter of `p`; `seed` fixes the bootstrap's draws.
pub fn sensor_parameters(p: &Processed, config: &ParameterConfig, seed: u64) -> SensorParameters {
    let prob = config.coverage_probability;
    let dt = p.dt;
    let span = p.record_span();
    let n_pad = p.len_padded();
    // Sample peaks of the band-passed acceleration: x, y, z, then the rotated ones.
    let peaks_b: [(usize, f64); 3] = std::array::from_fn(|k| peak(&p.b[k]));
    let order = by_magnitude(&p.b[0], &p.b[1]);
    let per_angle = rotd_peaks(&p.b[0], &p.b[1], &order);
    let rd = rotd(&per_angle);
    let measured = [
        peaks_b[0].1,
        peaks_b[1].1,
        peaks_b[2].1,
        rd.rotd50,
        rd.rotd100,
    ];
    let noise: PeakNoise = bootstrap(
        p,
        measured,
        per_angle[rd.median_angles[0]].0,
        config.bootstrap_draws,
        seed,
    );
    let rotated_term = |angle: usize, weight: f64| -> Term {
        let i = per_angle[angle].1;
        let w = angle_direction(angle);
        let v = w[0] * p.b[0][i] + w[1] * p.b[1][i];
        (w, p.delta(i, weight * sign(v)))
    };
    let sample_peak = |k: usize| -> Value {
        let (i, d) = peaks_b[k];
        let terms = [(axis(k), p.delta(i, sign(p.b[k][i])))];
        let (cal, _) = p.covariance(&terms, &terms);
        let value = d - noise.bias[k];
        let u2 = noise.standard_uncertainty[k].powi(2);
        Value {
            estimate: estimate(p, value, cal, u2, prob),
            at_s: Some(p.time_s(i)),
            angle_deg: None,
        }
    };
    let pga_rotd100 = {
        let terms = [rotated_term(rd.max_angle, 1.0)];
        let (cal, _) = p.covariance(&terms, &terms);
        Value {
            estimate: estimate(
                p,
                rd.rotd100 - noise.bias[4],
                cal,
                noise.standard_uncertainty[4].powi(2),
                prob,
            ),
            at_s: Some(p.time_s(per_angle[rd.max_angle].1)),
            angle_deg: Some(rd.max_angle as f64),
        }
    };
    let pga_rotd50 = {
        let terms = rd.median_angles.map(|a| rotated_term(a, 0.5));
        let (cal, _) = p.covariance(&terms, &terms);
        Value {
            estimate: estimate(
                p,
                rd.rotd50 - noise.bias[3],
                cal,
                noise.standard_uncertainty[3].powi(2),
                prob,
            ),
            at_s: Some(p.time_s(per_angle[rd.median_angles[1]].1)),
            angle_deg: Some(rd.median_angles[1] as f64),
        }
    };
    let c_arias = std::f64::consts::PI / (2.0 * STANDARD_GRAVITY_MPS2);
    // CAV's noise records: band-passed unit white noise over the record, shared by the three
    // directions (each is judged alone, so their draws may be the same), scaled per direction.
    let unit_noise: (Vec<Vec<f64>>, Vec<Vec<f64>>) = if p.has_noise() && config.bootstrap_draws >= 2
    {
        let mut rng = Rng::new(seed ^ 0xCA7);
        let mut draw = || -> Vec<f64> {
            let mut x = vec![0.0; n_pad];
            for v in &mut x[span.clone()] {
                *v = rng.normal();
            }
            p.band.apply(&mut x);
            x[span.clone()].to_vec()
        };
        let noise = (0..CAV_DRAWS).map(|_| draw()).collect();
        let replicates = (0..SIMEX_REPLICATES).map(|_| draw()).collect();
        (noise, replicates)
    } else {
        (Vec::new(), Vec::new())
    };
    let rho2 = squares_factor(p);
    let axes: [AxisParameters; 3] = std::array::from_fn(|k| {
        let w = axis(k);
        let sigma2 = p.noise_variance_along(&w);
        let smooth_peak = |series: &[f64], adjoint_steps: usize, salt: u64| -> Value {
            let weights = |i: usize, weight: f64| {
                let mut s = p.delta(i, weight);
                for _ in 0..adjoint_steps {
                    s = integrate_adjoint(&s, dt);
                }
                s
            };
            smooth_peak_value(
                p,
                series,
                w,
                &weights,
                None,
                prob,
                config.bootstrap_draws,
                seed ^ (salt << 8 | k as u64),
            )
        };
        let b = &p.b[k];
        // Arias intensity and its cumulative over the record.
        let mut cum = Vec::with_capacity(p.n);
        let mut total = 0.0;
        for &v in &b[span.clone()] {
            total += c_arias * dt * (v * v - sigma2);
            cum.push(total);
        }
        let arias_weights = |factor: &dyn Fn(usize) -> f64| -> Vec<f64> {
            let mut s = vec![0.0; n_pad];
            for (j, i) in span.clone().enumerate() {
                s[i] = 2.0 * c_arias * dt * b[i] * factor(j);
            }
            s
        };
        let squares_variance =
            |sum_factor2: f64| (c_arias * dt).powi(2) * 2.0 * sigma2 * sigma2 * rho2 * sum_factor2;
        let arias = {
            let terms = [(w, arias_weights(&|_| 1.0))];
            let (cal, lin) = p.covariance(&terms, &terms);
            Value::of(estimate(
                p,
                total,
                cal,
                lin + squares_variance(p.n as f64),
                prob,
            ))
        };
        // CAV, the noise's contribution to |b| extrapolated away (SIMEX over whole records).
        let cav = {
            let rec = &b[span.clone()];
            let measured: f64 = rec.iter().map(|v| v.abs()).sum::<f64>() * dt;
            let mut s = vec![0.0; n_pad];
            for i in span.clone() {
                s[i] = sign(b[i]) * dt;
            }
            let terms = [(w, s)];
            let (cal, first_order_noise) = p.covariance(&terms, &terms);
            if sigma2 > 0.0 && !unit_noise.0.is_empty() {
                let along = (w.transpose() * p.noise_b * w)[(0, 0)].max(0.0).sqrt();
                let scale = |set: &Vec<Vec<f64>>| -> Vec<Vec<f64>> {
                    set.iter()
                        .map(|x| x.iter().map(|v| v * along).collect())
                        .collect()
                };
                let (noise, replicates) = (scale(&unit_noise.0), scale(&unit_noise.1));
                let mut cav_of = |x: &[f64]| vec![x.iter().map(|v| v.abs()).sum::<f64>() * dt];
                let (quadratic, sd) = simex(
                    rec,
                    &noise,
                    &replicates,
                    Extrapolant::Quadratic,
                    &mut cav_of,
                )[0];
                let (linear, _) =
                    simex(rec, &noise, &replicates, Extrapolant::Linear, &mut cav_of)[0];
                // Where the motion is comparable to the noise, no polynomial in the noise's
                // deviation reaches back to zero noise (the curve is flat below it): both
                // extrapolants stop short, the linear one about twice as far as the quadratic.
                // So the estimate goes past the quadratic by their difference, and half of it is
                // taken as a standard uncertainty of the extrapolant.
                let value = measured - quadratic - (quadratic - linear);
                let extrapolant = 0.5 * (quadratic - linear);
                Value::of(estimate(
                    p,
                    value,
                    cal,
                    sd * sd + extrapolant * extrapolant,
                    prob,
                ))
            } else {
                Value::of(estimate(p, measured, cal, first_order_noise, prob))
            }
        };
        let d5_95 = (total > 0.0)
            .then(|| {
                let (k5, x5) = crossing(&cum, 0.05 * total)?;
                let (k95, x95) = crossing(&cum, 0.95 * total)?;
                // δ_p = p·δI_T − δI(t_p): weights p − (share of the sample before the crossing).
                let weights = |p_level: f64, k: usize, x: f64| {
                    let frac = x - (k as f64 - 1.0);
                    arias_weights(&move |j: usize| {
                        let before = if j < k {
                            1.0
                        } else if j == k {
                            frac
                        } else {
                            0.0
                        };
                        p_level - before
                    })
                };
                let (w5, w95) = (weights(0.05, k5, x5), weights(0.95, k95, x95));
                let t5 = [(w, w5)];
                let t95 = [(w, w95)];
                let (c55, n55) = p.covariance(&t5, &t5);
                let (c99, n99) = p.covariance(&t95, &t95);
                let (c59, n59) = p.covariance(&t5, &t95);
                let sq = |pl: f64, k: usize| {
                    squares_variance(pl * pl * (p.n - k) as f64 + (1.0 - pl).powi(2) * k as f64)
                };
                let (n55, n99) = (n55 + sq(0.05, k5), n99 + sq(0.95, k95));
                // Time per unit of cumulative intensity, as a secant over ±1 u of the level.
                let tau = |level: f64, var: f64, x: f64| {
                    let u = var.max(0.0).sqrt();
                    let at = |l: f64| {
                        crossing(&cum, l)
                            .map(|(_, x)| x)
                            .unwrap_or(p.n as f64 - 1.0)
                    };
                    if u > 0.0 {
                        dt * (at(level + u) - at((level - u).max(0.0))) / (2.0 * u)
                    } else {
                        let k = x.ceil() as usize;
                        let prev = if k == 0 { 0.0 } else { cum[k - 1] };
                        dt / (cum[k.min(cum.len() - 1)] - prev).max(f64::MIN_POSITIVE)
                    }
                };
                let tau5 = tau(0.05 * total, c55 + n55, x5);
                let tau95 = tau(0.95 * total, c99 + n99, x95);
                let cal = tau95 * tau95 * c99 + tau5 * tau5 * c55 - 2.0 * tau5 * tau95 * c59;
                let noise = tau95 * tau95 * n99 + tau5 * tau5 * n55 - 2.0 * tau5 * tau95 * n59;
                Some(Value {
                    estimate: estimate(p, (x95 - x5) * dt, cal.max(0.0), noise.max(0.0), prob),
                    at_s: Some(p.time_s(p.pad) + x5 * dt),
                    angle_deg: None,
                })
            })
            .flatten();
        AxisParameters {
            pga: sample_peak(k),
            pgv: smooth_peak(&p.vel_b[k], 1, 1),
            pgd: smooth_peak(&p.disp_b[k], 2, 2),
            arias,
            cav,
            d5_95,
        }
    });
    let spectrum = config
        .periods_s
        .iter()
        .enumerate()
        .map(|(j, &period_s)| spectral_ordinate(p, period_s, config, seed ^ ((j as u64 + 3) << 16)))
        .collect();
    SensorParameters {
        sensor_id: p.sensor_id.clone(),
        floor: p.floor,
        height_m: p.height_m,
        axes,
        pga_rotd50,
        pga_rotd100,
        spectrum,
        samples: p.n,
        invalid_samples: p.invalid,
        flagged: p.flagged,
        pre_event_baseline: p.pre_event_baseline,
        noise_mps2: std::array::from_fn(|k| p.noise_variance_along(&axis(k)).sqrt()),
        bootstrap_candidates: noise.candidates,
    }
}

/// The response spectrum at one period: the oscillator over the padded band-passed record.
fn spectral_ordinate(
    p: &Processed,
    period_s: f64,
    config: &ParameterConfig,
    seed: u64,
) -> SpectralOrdinate {
    let prob = config.coverage_probability;
    let osc = Oscillator::new(period_s, config.damping, p.dt);
    let response: [Vec<f64>; 3] = std::array::from_fn(|k| osc.pseudo_acceleration(&p.b[k]));
    let h = osc.impulse_response(p.len_padded());
    // The influence of b at i on the response at m is h[m − i].
    let weights = |m: usize, weight: f64| -> Vec<f64> {
        let mut s = vec![0.0; p.len_padded()];
        for (i, si) in s.iter_mut().enumerate().take(m + 1) {
            *si = weight * h[m - i];
        }
        s
    };
    // The oscillator and the band are time-invariant: the noise of the response at m is the
    // band's output for the reversed impulse response ending at m, the same at every m away
    // from the record's ends, so one filtered copy gives every correlation (stationary, first
    // order: the padding's lack of noise is not taken off).
    let len = p.len_padded();
    let mut z = vec![0.0; len];
    for (j, hj) in h.iter().enumerate() {
        z[len - 1 - j] = *hj;
    }
    p.band.apply(&mut z);
    let zero_lag: f64 = z.iter().map(|v| v * v).sum();
    let correlation = |i: usize, j: usize| -> f64 {
        let lag = i.abs_diff(j);
        if lag == 0 {
            zero_lag
        } else if lag >= len {
            0.0
        } else {
            z[..len - lag]
                .iter()
                .zip(&z[lag..])
                .map(|(a, b)| a * b)
                .sum()
        }
    };
    let axes: [Value; 3] = std::array::from_fn(|k| {
        smooth_peak_value(
            p,
            &response[k],
            axis(k),
            &weights,
            Some(&correlation),
            prob,
            config.bootstrap_draws,
            seed ^ k as u64,
        )
    });
    let order = by_magnitude(&response[0], &response[1]);
    let per_angle = rotd_peaks(&response[0], &response[1], &order);
    let rd = rotd(&per_angle);
    // Terms (direction, peak time, weight with its sign) and their estimate.
    let term = |angle: usize, weight: f64| -> (Vector3<f64>, usize, f64) {
        let (_, m) = per_angle[angle];
        let w: Vector3<f64> = angle_direction(angle);
        let v = w[0] * response[0][m] + w[1] * response[1][m];
        (w, m, weight * sign(v))
    };
    let rotated = |value: f64, terms: &[(Vector3<f64>, usize, f64)]| -> Estimate {
        let dense: Vec<Term> = terms
            .iter()
            .map(|(w, m, c)| (*w, weights(*m, *c)))
            .collect();
        let cal = p.calibration_variance(&dense);
        let mut noise = 0.0;
        if p.has_noise() {
            for (wp, mp, cp) in terms {
                for (wq, mq, cq) in terms {
                    noise +=
                        (wp.transpose() * p.noise_b * wq)[(0, 0)] * cp * cq * correlation(*mp, *mq);
                }
            }
        }
        estimate(p, value, cal, noise, prob)
    };
    let rotd100 = Value {
        estimate: rotated(rd.rotd100, &[term(rd.max_angle, 1.0)]),
        at_s: Some(p.time_s(per_angle[rd.max_angle].1)),
        angle_deg: Some(rd.max_angle as f64),
    };
    let rotd50 = Value {
        estimate: rotated(rd.rotd50, &rd.median_angles.map(|a| term(a, 0.5))),
        at_s: Some(p.time_s(per_angle[rd.median_angles[1]].1)),
        angle_deg: Some(rd.median_angles[1] as f64),
    };
    SpectralOrdinate {
        period_s,
        usable: period_s <= 1.0 / (1.25 * p.band.low_hz) && 1.0 / period_s <= p.band.high_hz,
        axes,
        rotd50,
        rotd100,
    }
}
