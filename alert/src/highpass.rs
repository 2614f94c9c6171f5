//! The vibration baseline: a causal second-order Butterworth high pass per axis, run over the
//! whole stream rather than over each window, so that the baseline does not depend on where a
//! window cuts the cycles.
//!
//! Demeaning each window by its own mean made the baseline move with the window's start: a
//! window holding 5.2 cycles of a 1.3 Hz sway has a mean that is not the static level, and its
//! demeaned peak read 3.6 % high (18 % in the short windows after start). The high pass removes
//! gravity, offsets and slow drift whatever the window, with a known response: content at `f`
//! passes with gain `|H(f)| = 1 / √(1 + (f_c/f)⁴)`, within 0.1 % of 1 above `4.8·f_c` and
//! within 10⁻⁴ above `8.5·f_c`.
//!
//! The filter starts in its steady state for the first sample, as if the stream had been
//! constant before. The start is then wrong by the motion at that instant, an error that decays
//! as `exp(−ζ·2π·f_c·t)` with ζ = 1/√2: after [`settle_s`] it is below 0.1 % of the motion's
//! amplitude, and only windows whose every sample came after that are judged.

/// Time after a (re)start beyond which the start-up transient is below 10⁻³ of its initial
/// size: `ln(1000) / (ζ·2π·f_c)`.
pub fn settle_s(cutoff_hz: f64) -> f64 {
    1000f64.ln() / (std::f64::consts::FRAC_1_SQRT_2 * 2.0 * std::f64::consts::PI * cutoff_hz)
}

/// The corner a filter for `cutoff_hz` has at `rate_hz`: clamped below a quarter of the rate,
/// where the design still holds.
pub fn corner_hz(cutoff_hz: f64, rate_hz: f64) -> f64 {
    cutoff_hz.min(0.25 * rate_hz)
}

/// The filter's gain at `frequency_hz`, as designed (the analogue prototype; the bilinear
/// transform is prewarped at the cutoff, so the two agree there and closely below fs/4).
pub fn gain(cutoff_hz: f64, frequency_hz: f64) -> f64 {
    1.0 / (1.0 + (cutoff_hz / frequency_hz).powi(4)).sqrt()
}

/// The filter's complex response, for carrying a sinusoid fitted to the unfiltered
/// acceleration through it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Response {
    b0: f64,
    a1: f64,
    a2: f64,
}

impl Response {
    /// `H(e^{iω}) = b0·(1 − e^{−iω})² / (1 + a1·e^{−iω} + a2·e^{−2iω})` at ω (rad per
    /// sample), as (gain, phase in rad): a steady sinusoid at ω leaves the filter scaled by the
    /// gain and advanced by the phase. Exact for the digital filter, not its analogue
    /// prototype.
    pub fn at(&self, omega: f64) -> (f64, f64) {
        let (s1, c1) = (-omega).sin_cos();
        let (s2, c2) = (-2.0 * omega).sin_cos();
        // Numerator b0·(1 − 2z⁻¹ + z⁻²), denominator 1 + a1·z⁻¹ + a2·z⁻², z⁻¹ = e^{−iω}.
        let (nr, ni) = (self.b0 * (1.0 - 2.0 * c1 + c2), self.b0 * (-2.0 * s1 + s2));
        let (dr, di) = (
            1.0 + self.a1 * c1 + self.a2 * c2,
            self.a1 * s1 + self.a2 * s2,
        );
        let d2 = dr * dr + di * di;
        let (re, im) = ((nr * dr + ni * di) / d2, (ni * dr - nr * di) / d2);
        (re.hypot(im), im.atan2(re))
    }
}

/// Three axes of the high pass, in transposed direct form II.
#[derive(Debug, Clone)]
pub struct HighPass {
    b0: f64,
    a1: f64,
    a2: f64,
    /// Per axis: the two delay elements; None before the first sample.
    state: Option<[[f64; 2]; 3]>,
    samples: u64,
    settle_samples: u64,
}

impl HighPass {
    /// A filter with cutoff `cutoff_hz` for samples at `rate_hz`, at its [`corner_hz`].
    pub fn new(cutoff_hz: f64, rate_hz: f64) -> HighPass {
        let fc = corner_hz(cutoff_hz, rate_hz);
        let k = (std::f64::consts::PI * fc / rate_hz).tan();
        let norm = 1.0 / (1.0 + std::f64::consts::SQRT_2 * k + k * k);
        HighPass {
            b0: norm,
            a1: 2.0 * (k * k - 1.0) * norm,
            a2: (1.0 - std::f64::consts::SQRT_2 * k + k * k) * norm,
            state: None,
            samples: 0,
            settle_samples: (settle_s(fc) * rate_hz).ceil() as u64,
        }
    }

    /// The filter's response.
    pub fn response(&self) -> Response {
        Response {
            b0: self.b0,
            a1: self.a1,
            a2: self.a2,
        }
    }

    /// Whether the start-up transient has decayed (see the module documentation).
    pub fn settled(&self) -> bool {
        self.samples >= self.settle_samples
    }

    /// Filters one three-axis sample.
    pub fn apply(&mut self, x: [f64; 3]) -> [f64; 3] {
        // b1 = −2·b0 and b2 = b0 for a high pass: a constant input gives zero output.
        let (b0, b1, b2) = (self.b0, -2.0 * self.b0, self.b0);
        // Steady state for a constant input x0 with zero output: s1 = −b0·x0, s2 = b2·x0.
        let state = self
            .state
            .get_or_insert_with(|| x.map(|x0| [-b0 * x0, b2 * x0]));
        self.samples += 1;
        let mut y = [0.0; 3];
        for ((yj, s), xj) in y.iter_mut().zip(state.iter_mut()).zip(x) {
            *yj = b0 * xj + s[0];
            s[0] = b1 * xj - self.a1 * *yj + s[1];
            s[1] = b2 * xj - self.a2 * *yj;
        }
        y
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn run(cutoff_hz: f64, freq_hz: f64, seconds: f64, offset: f64) -> (HighPass, Vec<f64>) {
        let rate = 100.0;
        let mut hp = HighPass::new(cutoff_hz, rate);
        let out = (0..(seconds * rate) as usize)
            .map(|i| {
                let t = i as f64 / rate;
                let x = offset + (2.0 * std::f64::consts::PI * freq_hz * t).cos();
                hp.apply([x, offset, 0.0])[0]
            })
            .collect();
        (hp, out)
    }

    #[test]
    fn removes_a_constant_from_the_first_sample() {
        let (_, out) = run(0.1, 1e-9, 1.0, 9.81);
        // A cosine of ~0 Hz is 1 + 9.81, a constant: nothing passes, not even at the start.
        assert!(out.iter().all(|y| y.abs() < 1e-9), "{:?}", &out[..4]);
    }

    #[test]
    fn passes_a_sway_with_the_designed_gain_once_settled() {
        let cutoff = 0.1;
        let settle = settle_s(cutoff);
        assert!((settle - 15.548).abs() < 0.01, "{settle}");
        for freq in [0.3, 0.5, 1.3, 5.0] {
            let (hp, out) = run(cutoff, freq, settle + 20.0, 9.81);
            assert!(hp.settled());
            let tail = &out[(settle * 100.0) as usize..];
            let peak = tail.iter().fold(0.0f64, |m, y| m.max(y.abs()));
            // The designed gain, to the sampling of the peak (within cos(π f / fs) of it) and
            // the transient left at the settle time (10⁻³).
            let expected = gain(cutoff, freq);
            let sampling = 1.0 - (std::f64::consts::PI * freq / 100.0).cos();
            assert!(
                (peak - expected).abs() <= sampling + 1.2e-3,
                "{freq} Hz: peak {peak}, designed {expected}"
            );
        }
        assert!(gain(0.1, 0.48) > 0.999 && gain(0.1, 0.85) > 0.9999);
        assert!(gain(0.1, 0.45) < 0.999);
    }

    /// The response carries a sinusoid through the filter: the filtered stream, once settled,
    /// is the input's sinusoid scaled by the gain and advanced by the phase.
    #[test]
    fn the_response_is_the_filters() {
        let rate = 100.0;
        for (cutoff, freq) in [(0.1, 0.5), (1.0, 1.3), (1.0, 2.0), (0.3, 7.0)] {
            let mut hp = HighPass::new(cutoff, rate);
            let omega = 2.0 * std::f64::consts::PI * freq / rate;
            let (g, phase) = hp.response().at(omega);
            let n = ((settle_s(cutoff) * 4.0 + 10.0) * rate) as usize;
            let mut worst = 0.0f64;
            for m in 0..n {
                let x = 9.81 + 0.7 * (omega * m as f64 + 0.4).sin();
                let y = hp.apply([x; 3])[0];
                if m > n - 500 {
                    let expected = 0.7 * g * (omega * m as f64 + 0.4 + phase).sin();
                    worst = worst.max((y - expected).abs());
                }
            }
            assert!(worst < 1e-6, "{cutoff} Hz at {freq} Hz: {worst}");
            assert!((g - gain(cutoff, freq)).abs() < 2e-3, "{g}");
        }
    }

    #[test]
    fn settles_only_after_the_settle_time() {
        let mut hp = HighPass::new(1.0, 100.0);
        let n = (settle_s(1.0) * 100.0).ceil() as usize;
        for _ in 0..n - 1 {
            hp.apply([1.0; 3]);
        }
        assert!(!hp.settled());
        hp.apply([1.0; 3]);
        assert!(hp.settled());
    }
}
