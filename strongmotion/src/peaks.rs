//! Peaks of sampled records: per direction, and over every horizontal direction (RotD, Boore
//! 2010: the peak of `cos θ·x(t) + sin θ·y(t)` for θ in 0°…179° by 1°, its median `RotD50` and
//! maximum `RotD100`).
//!
//! **Noise on a peak of samples.** The largest of several noisy samples is biased upwards when
//! several of them are near the crest (the noise picks the luckiest), and its error is not the
//! noise of one sample; neither is first-order. So a peak of the band-passed acceleration is
//! judged by a parametric bootstrap: the samples that could be the peak in some draw (within
//! seven noise standard deviations of it) get `draws` sets of band-passed noise with the
//! record's covariance (across axes, `Σ_b`; in time, the band-pass kernel's autocorrelation),
//! the peak is taken again in each at several noise levels, and the bias is extrapolated to no
//! noise by SIMEX ([`simex`]); the spread of the draws is its standard uncertainty. Smooth peaks (velocity,
//! displacement, oscillator responses) have one candidate per crest, their noise correlated as
//! the filter and the integration make it; when a single crest stands out they are first order
//! ([`crate::process`]), when several are within reach of the noise the same SIMEX applies.

use nalgebra::{DMatrix, Matrix3, Vector3};

use crate::process::Processed;
use crate::rng::Rng;

/// Angles of the rotated horizontal components.
pub const ROTD_ANGLES: usize = 180;

/// The peak of each rotated horizontal component: `(peak, padded index)` per angle θ_k = k°,
/// over the samples `order` names, sorted by decreasing `√(x² + y²)` (a sample no larger than
/// an angle's best so far cannot beat it, which ends that angle's search).
pub fn rotd_peaks(x: &[f64], y: &[f64], order: &[usize]) -> Vec<(f64, usize)> {
    (0..ROTD_ANGLES)
        .map(|k| {
            let (s, c) = (k as f64 * std::f64::consts::PI / ROTD_ANGLES as f64).sin_cos();
            let mut best = (0.0f64, order.first().copied().unwrap_or(0));
            for &i in order {
                // Squared, against the best squared: no root per sample.
                if x[i] * x[i] + y[i] * y[i] <= best.0 * best.0 {
                    break;
                }
                let v = (c * x[i] + s * y[i]).abs();
                if v > best.0 {
                    best = (v, i);
                }
            }
            best
        })
        .collect()
}

/// Indices of `0..x.len()` sorted by decreasing horizontal magnitude.
pub fn by_magnitude(x: &[f64], y: &[f64]) -> Vec<usize> {
    // Squared magnitudes computed once: a comparator that took roots ran 20 times slower.
    let key: Vec<f64> = x.iter().zip(y).map(|(a, b)| a * a + b * b).collect();
    let mut order: Vec<usize> = (0..x.len()).collect();
    order.sort_unstable_by(|&a, &b| key[b].total_cmp(&key[a]));
    order
}

/// The median and the maximum of per-angle peaks, with the angles (one or two) each comes from.
pub struct RotD {
    pub rotd50: f64,
    /// The two angles whose mean is the median (the 90th and 91st of 180 sorted).
    pub median_angles: [usize; 2],
    pub rotd100: f64,
    pub max_angle: usize,
}

pub fn rotd(peaks: &[(f64, usize)]) -> RotD {
    let mut sorted: Vec<usize> = (0..peaks.len()).collect();
    sorted.sort_by(|&a, &b| peaks[a].0.total_cmp(&peaks[b].0));
    let half = peaks.len() / 2;
    let median_angles = [sorted[half - 1], sorted[half]];
    let max_angle = sorted[peaks.len() - 1];
    RotD {
        rotd50: 0.5 * (peaks[median_angles[0]].0 + peaks[median_angles[1]].0),
        median_angles,
        rotd100: peaks[max_angle].0,
        max_angle,
    }
}

/// Unit vector of the rotated horizontal component at angle index `k`.
pub fn angle_direction(k: usize) -> Vector3<f64> {
    let (s, c) = (k as f64 * std::f64::consts::PI / ROTD_ANGLES as f64).sin_cos();
    Vector3::new(c, s, 0.0)
}

/// Noise levels SIMEX adds, as multiples of the noise's variance.
pub const SIMEX_LEVELS: [f64; 4] = [0.5, 1.0, 2.0, 3.0];

/// How SIMEX extrapolates, in `τ = √(1 + λ)` (the noise's deviation relative to the record's).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Extrapolant {
    /// `a + b·τ`: exact for the largest of many tied candidates (it grows as their spread) and
    /// for one standing out (it does not grow).
    Linear,
    /// `a + b·τ + c·τ²`: also exact where noise adds a smooth bias of its variance (the
    /// absolute value of a signal well above the noise, whose bias is `τ²σ²/(2|s|)`).
    Quadratic,
}

/// The weights of the least-squares intercept at `τ = 0` of `model` over the points at `taus`:
/// the extrapolated value is `Σ c_j·value_j`.
fn intercept_weights(taus: &[f64], model: Extrapolant) -> Vec<f64> {
    let columns = match model {
        Extrapolant::Linear => 2,
        Extrapolant::Quadratic => 3,
    };
    let a = DMatrix::from_fn(taus.len(), columns, |r, c| taus[r].powi(c as i32));
    let ata = a.transpose() * &a;
    match ata.try_inverse() {
        Some(inv) => {
            let row = inv.row(0) * a.transpose();
            row.iter().copied().collect()
        }
        None => {
            let mut w = vec![0.0; taus.len()];
            w[0] = 1.0;
            w
        }
    }
}

/// Simulation–extrapolation (Cook & Stefanski 1994) of functionals of noisy values.
///
/// `eval` maps values to the functionals; `base` are the measured values and `noise` draws of
/// their noise. Each functional is evaluated at `base` (noise variance 1×) and, as the mean
/// over the draws, at `base + √λ·noise` (variance `1 + λ`), and the `model` fitted to the five
/// points is extrapolated to no noise (`τ = 0`). The plug-in bootstrap (one level) removes
/// only `√2 − 1` of a tie's bias; the extrapolation removes it.
///
/// The estimate's noise: the spread of the whole procedure over `replicates` (records
/// `base + e/√2`, `e` a fresh draw of the noise, each extrapolated with the same draws), times
/// `√2`: to first order that is the estimate's own variance, the correction's variability
/// included, and half the noise keeps each replicate's ties those of the record; plus the
/// variance the finite number of draws leaves in the extrapolation. With no replicates, the
/// spread over the draws of the extrapolation's weighted sum.
/// Returns per functional the bias `value − estimate` and the noise's standard uncertainty.
pub fn simex(
    base: &[f64],
    noise: &[Vec<f64>],
    replicates: &[Vec<f64>],
    model: Extrapolant,
    eval: &mut dyn FnMut(&[f64]) -> Vec<f64>,
) -> Vec<(f64, f64)> {
    let taus: Vec<f64> = std::iter::once(1.0)
        .chain(SIMEX_LEVELS.iter().map(|l| (1.0 + l).sqrt()))
        .collect();
    let c = intercept_weights(&taus, model);
    let draws = noise.len().max(1) as f64;
    let mut x = base.to_vec();
    // Per functional: the measured value, the extrapolation, and the variance the finite draws
    // leave in it (the replicates share the draws, so their spread cannot show it).
    let mut extrapolated = |origin: &[f64], eval: &mut dyn FnMut(&[f64]) -> Vec<f64>| {
        let measured = eval(origin);
        let k = measured.len();
        let (mut sum, mut sq) = (vec![0.0; k], vec![0.0; k]);
        for z in noise {
            let mut g = vec![0.0; k];
            for (l, lambda) in SIMEX_LEVELS.iter().enumerate() {
                let scale = lambda.sqrt();
                for ((xi, bi), zi) in x.iter_mut().zip(origin).zip(z) {
                    *xi = bi + scale * zi;
                }
                for (gj, fj) in g.iter_mut().zip(eval(&x)) {
                    *gj += c[l + 1] * fj;
                }
            }
            for j in 0..k {
                sum[j] += g[j];
                sq[j] += g[j] * g[j];
            }
        }
        (0..k)
            .map(|j| {
                let mean = sum[j] / draws;
                let var = ((sq[j] / draws - mean * mean) * draws / (draws - 1.0).max(1.0)).max(0.0);
                (measured[j], c[0] * measured[j] + mean, var / draws, var)
            })
            .collect::<Vec<_>>()
    };
    let at_base = extrapolated(base, eval);
    if replicates.len() < 2 {
        // Without replicates: the draws' own spread, the noise of one record seen at the
        // extrapolation's weights.
        return at_base
            .iter()
            .map(|(m, a, mc, spread)| (m - a, (spread + mc).sqrt()))
            .collect();
    }
    let k = at_base.len();
    let (mut sum, mut sq) = (vec![0.0; k], vec![0.0; k]);
    let mut shifted = base.to_vec();
    for e in replicates {
        for ((si, bi), ei) in shifted.iter_mut().zip(base).zip(e) {
            *si = bi + ei * std::f64::consts::FRAC_1_SQRT_2;
        }
        for (j, (_, a, _, _)) in extrapolated(&shifted, eval).iter().enumerate() {
            sum[j] += a;
            sq[j] += a * a;
        }
    }
    let r = replicates.len() as f64;
    at_base
        .iter()
        .enumerate()
        .map(|(j, (m, a, mc, _))| {
            let mean = sum[j] / r;
            let var = ((sq[j] / r - mean * mean) * r / (r - 1.0)).max(0.0);
            (m - a, (2.0 * var + mc).sqrt())
        })
        .collect()
}

/// Replicate records for [`simex`]'s own variance.
pub const SIMEX_REPLICATES: usize = 12;

/// Draws of a Gaussian vector with covariance `L·Lᵀ`.
pub fn draws(l: &DMatrix<f64>, n: usize, rng: &mut Rng) -> Vec<Vec<f64>> {
    let dim = l.nrows();
    (0..n)
        .map(|_| {
            let z = nalgebra::DVector::from_fn(dim, |_, _| rng.normal());
            (l * z).iter().copied().collect()
        })
        .collect()
}

/// What the bootstrap says of each sample peak of the band-passed acceleration: the bias to
/// take off and the noise's standard uncertainty, for `x`, `y`, `z`, RotD50 and RotD100.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PeakNoise {
    pub bias: [f64; 5],
    pub standard_uncertainty: [f64; 5],
    /// Candidate samples drawn (all peaks together).
    pub candidates: usize,
}

/// The candidates are capped: past this many the lowest are left out (a record whose peak is
/// within six noise deviations of this many samples is noise-dominated anyway).
pub const MAX_CANDIDATES: usize = 240;

/// The bootstrap of the sample peaks of `p`'s band-passed acceleration, whose measured values
/// are `measured` (`x`, `y`, `z` peaks, RotD50, RotD100), with `draws` noise sets from `seed`,
/// extrapolated by [`simex`]. `rotd_floor` is the lower of the two angles' peaks the median is
/// the mean of: every angle at or above it is searched over all the samples that could be its
/// peak in a draw.
pub fn bootstrap(
    p: &Processed,
    measured: [f64; 5],
    rotd_floor: f64,
    draws: usize,
    seed: u64,
) -> PeakNoise {
    let none = PeakNoise {
        bias: [0.0; 5],
        standard_uncertainty: [0.0; 5],
        candidates: 0,
    };
    let r0 = p.kernel_energy;
    let sd: [f64; 3] = std::array::from_fn(|k| (p.noise_b[(k, k)] * r0).max(0.0).sqrt());
    if draws < 2 || sd.iter().all(|s| *s == 0.0) {
        return none;
    }
    let horizontal_sd = {
        let h = p.noise_b.fixed_view::<2, 2>(0, 0).symmetric_eigenvalues();
        (h.max().max(0.0) * r0).sqrt()
    };
    // Seven deviations: SIMEX draws at up to four times the noise's variance.
    let margin = 7.0;
    let b = &p.b;
    let len = p.len_padded();
    // Which samples could be each peak's in some draw.
    let mut wanted = vec![0u8; len];
    for i in 0..len {
        for k in 0..3 {
            if b[k][i].abs() >= measured[k] - margin * sd[k] {
                wanted[i] |= 1 << k;
            }
        }
        if b[0][i].hypot(b[1][i]) >= rotd_floor - margin * horizontal_sd {
            wanted[i] |= 1 << 3;
        }
    }
    let mut candidates: Vec<usize> = (0..len).filter(|&i| wanted[i] != 0).collect();
    if candidates.len() > MAX_CANDIDATES {
        candidates.sort_by(|&a, &c| {
            let m = |i: usize| b[0][i].hypot(b[1][i]).max(b[2][i].abs());
            m(c).total_cmp(&m(a))
        });
        candidates.truncate(MAX_CANDIDATES);
        candidates.sort_unstable();
    }
    let c = candidates.len();
    // Noise at the candidates: Σ_b ⊗ R, R(i, j) the kernel's autocorrelation at |i − j|.
    let half = p.kernel.len() / 2;
    let autocorrelation: Vec<f64> = (0..=2 * half)
        .map(|lag| {
            p.kernel
                .iter()
                .zip(p.kernel.iter().skip(lag))
                .map(|(a, b)| a * b)
                .sum()
        })
        .collect();
    let r = DMatrix::from_fn(c, c, |i, j| {
        let lag = candidates[i].abs_diff(candidates[j]);
        let v = autocorrelation.get(lag).copied().unwrap_or(0.0);
        if i == j {
            v * (1.0 + 1e-9)
        } else {
            v
        }
    });
    let Some(lr) = r.cholesky().map(|ch| ch.l()) else {
        return none;
    };
    let lb = symmetric_root(&p.noise_b);
    let mut rng = Rng::new(seed);
    // Candidate-major, three components each.
    let mut draw = || -> Vec<f64> {
        let z = DMatrix::from_fn(c, 3, |_, _| rng.normal());
        let n = &lr * z * lb.transpose();
        (0..3 * c).map(|q| n[(q / 3, q % 3)]).collect()
    };
    let noise: Vec<Vec<f64>> = (0..draws).map(|_| draw()).collect();
    let replicates: Vec<Vec<f64>> = (0..SIMEX_REPLICATES).map(|_| draw()).collect();
    let base: Vec<f64> = candidates
        .iter()
        .flat_map(|&i| [b[0][i], b[1][i], b[2][i]])
        .collect();
    let horizontal: Vec<usize> = (0..c)
        .filter(|&j| wanted[candidates[j]] & (1 << 3) != 0)
        .collect();
    let mut order: Vec<usize> = Vec::with_capacity(c);
    let (mut hx, mut hy, mut key) = (vec![0.0; c], vec![0.0; c], vec![0.0; c]);
    let mut eval = |x: &[f64]| -> Vec<f64> {
        let mut peaks = vec![0.0f64; 5];
        for (j, &i) in candidates.iter().enumerate() {
            for k in 0..3 {
                if wanted[i] & (1 << k) != 0 {
                    peaks[k] = peaks[k].max(x[3 * j + k].abs());
                }
            }
            hx[j] = x[3 * j];
            hy[j] = x[3 * j + 1];
        }
        order.clear();
        order.extend_from_slice(&horizontal);
        for &j in &horizontal {
            key[j] = hx[j] * hx[j] + hy[j] * hy[j];
        }
        order.sort_unstable_by(|&a, &q| key[q].total_cmp(&key[a]));
        if !order.is_empty() {
            let rd = rotd(&rotd_peaks(&hx, &hy, &order));
            peaks[3] = rd.rotd50;
            peaks[4] = rd.rotd100;
        }
        peaks
    };
    let out = simex(&base, &noise, &replicates, Extrapolant::Linear, &mut eval);
    PeakNoise {
        bias: std::array::from_fn(|k| out[k].0),
        standard_uncertainty: std::array::from_fn(|k| out[k].1),
        candidates: c,
    }
}

/// A square root `L` of a positive semi-definite matrix, `L·Lᵀ = m`.
fn symmetric_root(m: &Matrix3<f64>) -> Matrix3<f64> {
    let e = m.symmetric_eigen();
    let d = Matrix3::from_diagonal(&e.eigenvalues.map(|v| v.max(0.0).sqrt()));
    e.eigenvectors * d
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rotd_of_a_line_and_a_circle_by_hand() {
        // Linear motion along 30°: the peak at θ is A·|cos(θ − 30°)|; RotD100 = A at 30°, and
        // the median of |cos| over 180 angles is cos 45°.
        let a = 2.0;
        let n = 400;
        let (x, y): (Vec<f64>, Vec<f64>) = (0..n)
            .map(|i| {
                let v = a * (i as f64 * 0.05).sin();
                let t = 30f64.to_radians();
                (v * t.cos(), v * t.sin())
            })
            .unzip();
        let order = by_magnitude(&x, &y);
        let r = rotd(&rotd_peaks(&x, &y, &order));
        let peak = (0..n).map(|i| x[i].hypot(y[i])).fold(0.0, f64::max);
        assert!((r.rotd100 - peak).abs() < 1e-12);
        assert_eq!(r.max_angle, 30);
        assert!((r.rotd50 - peak * 45f64.to_radians().cos()).abs() < 0.01 * peak);
        // Circular motion: every angle sees the same peak.
        let (x, y): (Vec<f64>, Vec<f64>) = (0..n)
            .map(|i| {
                let t = i as f64 * 2.0 * std::f64::consts::PI / n as f64;
                (a * t.cos(), a * t.sin())
            })
            .unzip();
        let r = rotd(&rotd_peaks(&x, &y, &by_magnitude(&x, &y)));
        assert!((r.rotd50 - a).abs() < 1e-3 && (r.rotd100 - a).abs() < 1e-9);
        // The pruned search finds what a full one finds.
        let (x, y): (Vec<f64>, Vec<f64>) = (0..n)
            .map(|i| {
                let t = i as f64 * 0.031;
                (t.sin() + 0.3 * (3.1 * t).cos(), 0.7 * (1.7 * t).sin())
            })
            .unzip();
        let fast = rotd_peaks(&x, &y, &by_magnitude(&x, &y));
        for (k, (p, _)) in fast.iter().enumerate() {
            let w = angle_direction(k);
            let full = (0..n)
                .map(|i| (w[0] * x[i] + w[1] * y[i]).abs())
                .fold(0.0, f64::max);
            assert!((p - full).abs() < 1e-12, "angle {k}");
        }
    }
}
