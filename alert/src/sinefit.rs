//! Least-squares fit of one sinusoid, with offset and linear trend, to one axis of a window:
//! the four-parameter sine fit of IEEE Std 1057 with a trend term, for windows whose motion is
//! a single sway.
//!
//! Model, with `t` the sample's index from the window's centre:
//! `y(t) = a·cos ωt + b·sin ωt + c + d·t/n`. For a given ω the model is linear in `(a, b, c, d)`;
//! ω is found by a golden-section search of the residual sum of squares within one spectral bin
//! either side of the spectrum's peak, then refined by Gauss–Newton steps on the variable
//! projection. The offset and trend absorb gravity, offsets and slow drift, so the fit needs no
//! baseline and is independent of where the window cuts the cycles.
//!
//! Uncertainties are the least-squares covariance, with the noise variance `s²` estimated from
//! the residuals (ν = n − 5, large for any window worth judging):
//! `var(ω) = s² / (g⊥ᵀg⊥)`, with `g = ∂y/∂ω` and `g⊥` its part orthogonal to the linear
//! columns `X`; `Cov(a, b, c, d) = s²·(XᵀX)⁻¹ + w·wᵀ·var(ω)`, `w = (XᵀX)⁻¹Xᵀg`. The amplitude
//! `√(a² + b²)` does not depend on ω to first order at the optimum, so its variance is
//! `hᵀ·Cov·h` with `h = (a, b, 0, 0)/amplitude`. A Monte Carlo of sines in white noise gives
//! 94–97 % coverage at k = 2 for the amplitude and the frequency (module tests and the
//! monitor's Monte Carlo).
//!
//! **Adequacy.** The fit speaks for the motion only when the residual is noise. Noise is white
//! sample to sample; motion the model missed is not. So the residual's variance `s²` is compared
//! with its short-scale variance from fourth differences, `σ_d² = mean((Δ⁴r)²)/70`, which
//! ignores slow content: for white noise the ratio `R = s²/σ_d²` is 1 with a standard deviation
//! of `√(3.25/n)` (from the autocorrelation of the difference filter). A ratio above
//! `1 + 3·√(3.25/n)` means missed motion, and the window is judged from its samples instead.
//! What passes is counted anyway: `max(s² − σ_d²·(1 + 2·√(3.25/n)), 0)` is added to the
//! variance of the peak as unmodelled motion. White motion would pass that test (its residual is
//! white too), so the residual must also be no larger than the sensor's noise can be: `s²` at
//! most `(1 + 4·√(2/n))` times the square of the stated u, which bounds the noise.

use nalgebra::{Matrix4, Vector4};

/// A fit judged adequate, in the window's units and Hz.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SineFit {
    pub frequency_hz: f64,
    pub frequency_u_hz: f64,
    /// Amplitude of the sinusoid: the peak of the motion it describes.
    pub amplitude: f64,
    pub amplitude_u: f64,
    /// RMS of the fitted sinusoid (without offset and trend) over every sample time of the
    /// window, present or not.
    pub rms: f64,
    pub rms_u: f64,
    /// Residual standard deviation `s`: the noise the fit saw.
    pub noise_sd: f64,
    /// Standard deviation of motion the model missed but the adequacy test let pass.
    pub unmodelled_sd: f64,
}

/// Fewest cycles in the window for a fit: below, sinusoid and trend cannot be told apart.
const MIN_CYCLES: f64 = 1.5;
/// Golden-section steps: the bracket shrinks to 0.618²⁰ ≈ 7·10⁻⁵ of two bins before the
/// Gauss–Newton steps, which converge quadratically from there.
const GOLDEN_STEPS: usize = 20;
const NEWTON_STEPS: usize = 3;

/// Sums over the samples for one ω: `XᵀX` and `Xᵀy`.
struct Sums {
    xtx: Matrix4<f64>,
    xty: Vector4<f64>,
}

/// One axis of a window: the samples' grid indices (increasing, holes allowed), their values,
/// and the grid's length.
pub struct Axis<'a> {
    pub index: &'a [u32],
    pub value: &'a [f64],
    pub grid_len: u32,
}

impl Axis<'_> {
    fn centre(&self) -> f64 {
        (f64::from(self.grid_len) - 1.0) / 2.0
    }

    /// Calls `f(i, t, cos ωt, sin ωt)` for every sample, rotating rather than calling sin_cos
    /// per sample (the grid is regular; holes are skipped over).
    fn each(&self, omega: f64, mut f: impl FnMut(usize, f64, f64, f64)) {
        let Some(&first) = self.index.first() else {
            return;
        };
        let centre = self.centre();
        let (s0, c0) = (omega * (f64::from(first) - centre)).sin_cos();
        let (sw, cw) = omega.sin_cos();
        let (mut c, mut s) = (c0, s0);
        let mut at = first;
        for (i, &k) in self.index.iter().enumerate() {
            while at < k {
                (c, s) = (c * cw - s * sw, s * cw + c * sw);
                at += 1;
            }
            f(i, f64::from(k) - centre, c, s);
        }
    }

    fn sums(&self, omega: f64) -> Sums {
        let scale = 1.0 / f64::from(self.grid_len.max(1));
        let mut xtx = Matrix4::zeros();
        let mut xty = Vector4::zeros();
        self.each(omega, |i, t, c, s| {
            let x = columns(t * scale, c, s);
            xtx += x * x.transpose();
            xty += x * self.value[i];
        });
        Sums { xtx, xty }
    }

    /// The linear parameters and residual sum of squares at ω; None if singular.
    fn solve(&self, omega: f64) -> Option<(Vector4<f64>, Matrix4<f64>, f64)> {
        let Sums { xtx, xty } = self.sums(omega);
        let inv = xtx.cholesky()?.inverse();
        let beta = inv * xty;
        let scale = 1.0 / f64::from(self.grid_len.max(1));
        let mut rss = 0.0;
        self.each(omega, |i, t, c, s| {
            let r = self.value[i] - model(&beta, t * scale, c, s);
            rss += r * r;
        });
        Some((beta, inv, rss))
    }

    /// `g = ∂y/∂ω` projected: returns (gᵀr, Xᵀg, gᵀg).
    fn omega_terms(&self, omega: f64, beta: &Vector4<f64>) -> (f64, Vector4<f64>, f64) {
        let scale = 1.0 / f64::from(self.grid_len.max(1));
        let (mut gr, mut xg, mut gg) = (0.0, Vector4::zeros(), 0.0);
        self.each(omega, |i, t, c, s| {
            let g = t * (-beta[0] * s + beta[1] * c);
            let r = self.value[i] - model(beta, t * scale, c, s);
            gr += g * r;
            gg += g * g;
            xg += columns(t * scale, c, s) * g;
        });
        (gr, xg, gg)
    }

    /// Fourth-difference estimate of the residual's white-noise variance, over runs of five
    /// consecutive grid indices; None when there are too few.
    fn short_scale_variance(&self, omega: f64, beta: &Vector4<f64>) -> Option<f64> {
        let scale = 1.0 / f64::from(self.grid_len.max(1));
        let mut last: [(u32, f64); 5] = [(u32::MAX, 0.0); 5];
        let (mut sum, mut count) = (0.0, 0usize);
        self.each(omega, |i, t, c, s| {
            let r = self.value[i] - model(beta, t * scale, c, s);
            last.rotate_left(1);
            last[4] = (self.index[i], r);
            let consecutive = (0..4).all(|m| last[m].0.wrapping_add(1) == last[m + 1].0);
            if consecutive {
                let d = last[0].1 - 4.0 * last[1].1 + 6.0 * last[2].1 - 4.0 * last[3].1 + last[4].1;
                sum += d * d;
                count += 1;
            }
        });
        (count >= 16).then(|| sum / (70.0 * count as f64))
    }

    /// RMS of `a·cos ωt + b·sin ωt` over the whole grid, and its gradient in (a, b).
    fn grid_rms(&self, omega: f64, a: f64, b: f64) -> (f64, [f64; 2]) {
        let grid: Vec<u32> = (0..self.grid_len).collect();
        let full = Axis {
            index: &grid,
            value: &[],
            grid_len: self.grid_len,
        };
        let (mut cc, mut cs, mut ss) = (0.0, 0.0, 0.0);
        full.each(omega, |_, _, c, s| {
            cc += c * c;
            cs += c * s;
            ss += s * s;
        });
        let n = f64::from(self.grid_len.max(1));
        let rms = ((a * a * cc + 2.0 * a * b * cs + b * b * ss) / n)
            .max(0.0)
            .sqrt();
        if rms == 0.0 {
            return (0.0, [0.0, 0.0]);
        }
        (
            rms,
            [(a * cc + b * cs) / (n * rms), (a * cs + b * ss) / (n * rms)],
        )
    }
}

/// The linear columns at one sample, `(cos ωt, sin ωt, 1, t/n)`, with `t_scaled` = t/n.
fn columns(t_scaled: f64, cos: f64, sin: f64) -> Vector4<f64> {
    Vector4::new(cos, sin, 1.0, t_scaled)
}

/// The model at one sample: `a·cos ωt + b·sin ωt + c + d·t/n`.
fn model(beta: &Vector4<f64>, t_scaled: f64, cos: f64, sin: f64) -> f64 {
    beta.dot(&columns(t_scaled, cos, sin))
}

/// Fits one sinusoid near `start_hz` (the spectrum's peak; `bin_hz` its resolution) to an axis
/// sampled at `rate_hz` whose noise is at most `noise_bound` (the stated u). None when the
/// window is too short for the frequency, the fit is singular, or it is not adequate (see the
/// module documentation).
pub fn fit(
    axis: &Axis<'_>,
    rate_hz: f64,
    start_hz: f64,
    bin_hz: f64,
    noise_bound: f64,
) -> Option<SineFit> {
    let n = axis.index.len();
    if n < 32 || axis.value.len() != n {
        return None;
    }
    let to_omega = 2.0 * std::f64::consts::PI / rate_hz;
    let (mut lo, mut hi) = (
        (start_hz - bin_hz).max(0.5 * start_hz) * to_omega,
        (start_hz + bin_hz).min(0.5 * rate_hz) * to_omega,
    );
    let bracket = hi - lo;
    let rss = |omega: f64| axis.solve(omega).map_or(f64::INFINITY, |(_, _, r)| r);
    let golden = (5f64.sqrt() - 1.0) / 2.0;
    let (mut x1, mut x2) = (hi - golden * (hi - lo), lo + golden * (hi - lo));
    let (mut f1, mut f2) = (rss(x1), rss(x2));
    for _ in 0..GOLDEN_STEPS {
        if f1 < f2 {
            (hi, x2, f2) = (x2, x1, f1);
            x1 = hi - golden * (hi - lo);
            f1 = rss(x1);
        } else {
            (lo, x1, f1) = (x1, x2, f2);
            x2 = lo + golden * (hi - lo);
            f2 = rss(x2);
        }
    }
    let mut omega = 0.5 * (lo + hi);
    for _ in 0..NEWTON_STEPS {
        let (beta, inv, _) = axis.solve(omega)?;
        let (gr, xg, gg) = axis.omega_terms(omega, &beta);
        let step = gr / (gg - (xg.transpose() * inv * xg)[0]);
        // A step beyond the searched bracket (or not a number) means no minimum near the
        // spectrum's peak: not one sway.
        if step.is_nan() || step.abs() > bracket {
            return None;
        }
        omega += step;
    }
    let (beta, inv, rss) = axis.solve(omega)?;
    let (_, xg, gg) = axis.omega_terms(omega, &beta);
    let perp = gg - (xg.transpose() * inv * xg)[0];
    let grid_s = f64::from(axis.grid_len) / rate_hz;
    let frequency_hz = omega / to_omega;
    let cycles = frequency_hz * grid_s;
    let usable = perp > 0.0 && cycles >= MIN_CYCLES && frequency_hz < 0.5 * rate_hz;
    if !usable {
        return None;
    }
    let s2 = rss / (n - 5) as f64;
    let var_omega = s2 / perp;
    let w = inv * xg;
    let cov = inv * s2 + w * w.transpose() * var_omega;
    let amplitude = beta[0].hypot(beta[1]);
    if !(amplitude > 0.0 && amplitude.is_finite()) {
        return None;
    }
    let h = Vector4::new(beta[0] / amplitude, beta[1] / amplitude, 0.0, 0.0);
    let amplitude_var = (h.transpose() * cov * h)[0];

    // Adequacy: the residual must look white; see the module documentation.
    let sd_ratio = (3.25 / n as f64).sqrt();
    let short = axis.short_scale_variance(omega, &beta)?;
    // An exact sinusoid leaves only the rounding of the f32 samples (6·10⁻⁸ of the largest
    // value), which is not white where the signal changes by less than a rounding step.
    let largest = axis.value.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    let exact = s2.sqrt() <= 1e-6 * largest;
    let louder_than_noise = s2 > noise_bound * noise_bound * (1.0 + 4.0 * (2.0 / n as f64).sqrt());
    if !exact && (s2 > short * (1.0 + 3.0 * sd_ratio) || louder_than_noise) {
        return None;
    }
    let unmodelled_var = (s2 - short * (1.0 + 2.0 * sd_ratio)).max(0.0);

    let (rms, grad) = axis.grid_rms(omega, beta[0], beta[1]);
    let g = Vector4::new(grad[0], grad[1], 0.0, 0.0);
    let rms_var = (g.transpose() * cov * g)[0];
    Some(SineFit {
        frequency_hz,
        frequency_u_hz: var_omega.sqrt() / to_omega,
        amplitude,
        amplitude_u: amplitude_var.max(0.0).sqrt(),
        rms,
        rms_u: rms_var.max(0.0).sqrt(),
        noise_sd: s2.sqrt(),
        unmodelled_sd: unmodelled_var.sqrt(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_distr::{Distribution, Normal};

    fn sine(n: u32, rate: f64, f: f64, amp: f64, phase: f64, offset: f64) -> Vec<f64> {
        (0..n)
            .map(|i| {
                let t = f64::from(i) / rate;
                offset + amp * (2.0 * std::f64::consts::PI * f * t + phase).sin()
            })
            .collect()
    }

    #[test]
    fn an_exact_sine_is_recovered() {
        let index: Vec<u32> = (0..400).collect();
        let y = sine(400, 100.0, 1.3, 0.8, 0.4, 9.81);
        let axis = Axis {
            index: &index,
            value: &y,
            grid_len: 400,
        };
        let f = fit(&axis, 100.0, 1.25, 100.0 / 512.0, 0.01).expect("an exact sine fits");
        assert!((f.frequency_hz - 1.3).abs() < 1e-9, "{f:?}");
        assert!((f.amplitude - 0.8).abs() < 1e-9, "{f:?}");
        // 5.2 cycles: the RMS over the window is not quite amp/√2; computed directly.
        let direct = (sine(400, 100.0, 1.3, 0.8, 0.4, 0.0)
            .iter()
            .map(|v| v * v)
            .sum::<f64>()
            / 400.0)
            .sqrt();
        assert!((f.rms - direct).abs() < 1e-9, "{} vs {direct}", f.rms);
    }

    #[test]
    fn holes_in_the_grid_are_fitted_at_their_times() {
        let full = sine(400, 100.0, 2.5, 0.5, 1.0, -0.2);
        let index: Vec<u32> = (0..400).filter(|i| i % 7 != 3).collect();
        let value: Vec<f64> = index.iter().map(|&i| full[i as usize]).collect();
        let axis = Axis {
            index: &index,
            value: &value,
            grid_len: 400,
        };
        let f = fit(&axis, 100.0, 2.4, 100.0 / 512.0, 0.01).expect("fits");
        assert!((f.frequency_hz - 2.5).abs() < 1e-9 && (f.amplitude - 0.5).abs() < 1e-9);
    }

    #[test]
    fn two_tones_are_not_one_sine() {
        let index: Vec<u32> = (0..400).collect();
        let mut rng = rand::rngs::StdRng::seed_from_u64(7);
        let noise = Normal::new(0.0, 0.01).expect("valid");
        let a = sine(400, 100.0, 1.3, 1.0, 0.0, 0.0);
        let b = sine(400, 100.0, 3.7, 0.2, 0.5, 0.0);
        let y: Vec<f64> = a
            .iter()
            .zip(&b)
            .map(|(x, z)| x + z + noise.sample(&mut rng))
            .collect();
        let axis = Axis {
            index: &index,
            value: &y,
            grid_len: 400,
        };
        assert!(fit(&axis, 100.0, 1.27, 100.0 / 512.0, 0.01).is_none());
        // Below a cycle and a half the trend and the sinusoid cannot be told apart.
        let slow = sine(400, 100.0, 0.3, 1.0, 0.0, 0.0);
        let axis = Axis {
            index: &index,
            value: &slow,
            grid_len: 400,
        };
        assert!(fit(&axis, 100.0, 0.29, 100.0 / 512.0, 0.01).is_none());
        // White motion leaves a white residual, but far above the sensor's stated noise: it is
        // not a sway with a small amplitude.
        let motion = Normal::new(0.0, 0.3).expect("valid");
        let white: Vec<f64> = (0..400).map(|_| motion.sample(&mut rng)).collect();
        let axis = Axis {
            index: &index,
            value: &white,
            grid_len: 400,
        };
        assert!(fit(&axis, 100.0, 7.0, 100.0 / 512.0, 0.02).is_none());
    }

    /// Sines in white noise: the stated intervals cover amplitude and frequency about 95 % of
    /// the time, and the fit is judged adequate almost always.
    #[test]
    fn intervals_cover_in_white_noise() {
        let mut rng = rand::rngs::StdRng::seed_from_u64(11);
        let index: Vec<u32> = (0..400).collect();
        let (mut trials, mut amp_in, mut freq_in, mut refused) = (0, 0, 0, 0);
        for f_true in [0.7, 1.3, 4.1, 9.0] {
            for _ in 0..500 {
                let sigma = 0.02;
                let noise = Normal::new(0.0, sigma).expect("valid");
                let phase = rng.gen_range(0.0..std::f64::consts::TAU);
                let y: Vec<f64> = sine(400, 100.0, f_true, 1.0, phase, 3.0)
                    .into_iter()
                    .map(|v| v + noise.sample(&mut rng))
                    .collect();
                let axis = Axis {
                    index: &index,
                    value: &y,
                    grid_len: 400,
                };
                trials += 1;
                // Start from a point off the line, as the spectrum's bin would be.
                let Some(f) = fit(&axis, 100.0, f_true + 0.07, 100.0 / 512.0, sigma) else {
                    refused += 1;
                    continue;
                };
                amp_in += usize::from((f.amplitude - 1.0).abs() <= 2.0 * f.amplitude_u);
                freq_in += usize::from((f.frequency_hz - f_true).abs() <= 2.0 * f.frequency_u_hz);
            }
        }
        let fitted = (trials - refused) as f64;
        let (amp, freq) = (amp_in as f64 / fitted, freq_in as f64 / fitted);
        assert!(
            refused as f64 / (trials as f64) < 0.03,
            "{refused} of {trials} refused"
        );
        assert!((0.93..=0.975).contains(&amp), "amplitude coverage {amp}");
        assert!((0.93..=0.975).contains(&freq), "frequency coverage {freq}");
    }
}
