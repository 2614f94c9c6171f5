//! The acausal band-pass every strong-motion parameter is computed after: Butterworth high and
//! low passes (bilinear transform, corners prewarped), run forward and then backward over the
//! record padded with zeros, so that its phase is zero and its gain is the single pass's
//! squared:
//!
//! ```text
//! G(f) = |H_hp(f)|² · |H_lp(f)|²,  |H_hp(f)|² = 1 / (1 + (tan(π f_lo/f_s) / tan(π f/f_s))^(2n)),
//!                                   |H_lp(f)|² = 1 / (1 + (tan(π f/f_s) / tan(π f_hi/f_s))^(2n))
//! ```
//!
//! (`n` the order of each pass; `G` is ½ at each corner.) The padding is `1.5·n/f_lo` seconds on
//! each side (the PEER practice), long enough for the filter's response to a record's ends to
//! die out inside it; the processed record is the padded one, so velocity and displacement
//! integrated from it return to rest.
//!
//! As an operator on the padded record the filter is a matrix `M = J·F·J·F` (`F` the causal
//! cascade, `J` time reversal), and `M` is symmetric, since the transpose of a causal filter
//! with zero initial state is `J·F·J`. So the influence of one input sample on any linear
//! functional of the output is the filter applied to the functional's weights, which is how
//! noise is propagated ([`crate::process`]).

use serde::Deserialize;
use thiserror::Error;

/// One second-order section, `(b0 + b1 z⁻¹ + b2 z⁻²) / (1 + a1 z⁻¹ + a2 z⁻²)`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Biquad {
    pub b: [f64; 3],
    pub a: [f64; 2],
}

impl Biquad {
    /// Runs the section over `x` in place, from rest (transposed direct form II).
    pub fn run(&self, x: &mut [f64]) {
        let (mut z1, mut z2) = (0.0, 0.0);
        let [b0, b1, b2] = self.b;
        let [a1, a2] = self.a;
        for v in x.iter_mut() {
            let input = *v;
            let y = b0 * input + z1;
            z1 = b1 * input - a1 * y + z2;
            z2 = b2 * input - a2 * y;
            *v = y;
        }
    }

    /// `|H(e^{iω})|²` at `f` for sample rate `fs`.
    pub fn power_gain(&self, f: f64, fs: f64) -> f64 {
        let w = 2.0 * std::f64::consts::PI * f / fs;
        let (c1, s1, c2, s2) = (w.cos(), w.sin(), (2.0 * w).cos(), (2.0 * w).sin());
        let num_re = self.b[0] + self.b[1] * c1 + self.b[2] * c2;
        let num_im = -(self.b[1] * s1 + self.b[2] * s2);
        let den_re = 1.0 + self.a[0] * c1 + self.a[1] * c2;
        let den_im = -(self.a[0] * s1 + self.a[1] * s2);
        (num_re * num_re + num_im * num_im) / (den_re * den_re + den_im * den_im)
    }
}

/// Which pass.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Pass {
    High,
    Low,
}

/// The sections of an even-order Butterworth pass at corner `fc` for sample rate `fs`.
pub fn butterworth(pass: Pass, order: usize, fc: f64, fs: f64) -> Vec<Biquad> {
    // Bilinear transform s = 2fs(1 − z⁻¹)/(1 + z⁻¹), the corner prewarped: with c = 1/tan(π fc/fs)
    // a normalised section 1/(s'² + a s' + 1) (a = 2 sin θ_k) becomes
    // (1 + z⁻¹)² / ((c² + ac + 1) + (2 − 2c²) z⁻¹ + (c² − ac + 1) z⁻²), and its high-pass twin
    // has c²(1 − z⁻¹)² on top.
    let c = 1.0 / (std::f64::consts::PI * fc / fs).tan();
    (0..order / 2)
        .map(|k| {
            let theta = std::f64::consts::PI * (2 * k + 1) as f64 / (2 * order) as f64;
            let a = 2.0 * theta.sin();
            let d0 = c * c + a * c + 1.0;
            let a1 = (2.0 - 2.0 * c * c) / d0;
            let a2 = (c * c - a * c + 1.0) / d0;
            let b = match pass {
                Pass::Low => [1.0 / d0, 2.0 / d0, 1.0 / d0],
                Pass::High => [c * c / d0, -2.0 * c * c / d0, c * c / d0],
            };
            Biquad { b, a: [a1, a2] }
        })
        .collect()
}

/// The band's corners and order, as configured.
#[derive(Debug, Clone, Copy, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct BandConfig {
    /// High-pass corner, Hz (gain ½ there).
    pub low_hz: f64,
    /// Low-pass corner, Hz; none: 0.4 of the sample rate.
    pub high_hz: Option<f64>,
    /// Order of each pass (even, 2 to 8); the zero-phase filter has twice the roll-off.
    pub order: usize,
}

impl Default for BandConfig {
    fn default() -> Self {
        BandConfig {
            low_hz: 0.1,
            high_hz: None,
            order: 4,
        }
    }
}

/// Why a band cannot be built.
#[derive(Debug, Clone, PartialEq, Error)]
pub enum BandError {
    #[error("order {0}: must be even, from 2 to 8")]
    Order(usize),
    #[error("low_hz {low_hz}: must be > 0 and below high_hz {high_hz} Hz")]
    Corners { low_hz: f64, high_hz: f64 },
    #[error("high_hz {high_hz}: must be below the Nyquist frequency {nyquist_hz} Hz")]
    AboveNyquist { high_hz: f64, nyquist_hz: f64 },
    #[error("sample rate {0} Hz is not a finite positive number")]
    Rate(f64),
}

/// The zero-phase band-pass of one sample rate.
#[derive(Debug, Clone, PartialEq)]
pub struct BandPass {
    pub low_hz: f64,
    pub high_hz: f64,
    pub order: usize,
    pub sample_rate_hz: f64,
    sections: Vec<Biquad>,
    /// Zeros on each side of a record.
    pub pad: usize,
}

impl BandPass {
    pub fn new(config: &BandConfig, sample_rate_hz: f64) -> Result<BandPass, BandError> {
        if !(sample_rate_hz.is_finite() && sample_rate_hz > 0.0) {
            return Err(BandError::Rate(sample_rate_hz));
        }
        if !(2..=8).contains(&config.order) || config.order % 2 != 0 {
            return Err(BandError::Order(config.order));
        }
        let nyquist_hz = sample_rate_hz / 2.0;
        let high_hz = config.high_hz.unwrap_or(0.4 * sample_rate_hz);
        if !(high_hz.is_finite() && high_hz < nyquist_hz) {
            return Err(BandError::AboveNyquist {
                high_hz,
                nyquist_hz,
            });
        }
        if !(config.low_hz.is_finite() && config.low_hz > 0.0 && config.low_hz < high_hz) {
            return Err(BandError::Corners {
                low_hz: config.low_hz,
                high_hz,
            });
        }
        let mut sections = butterworth(Pass::High, config.order, config.low_hz, sample_rate_hz);
        sections.extend(butterworth(
            Pass::Low,
            config.order,
            high_hz,
            sample_rate_hz,
        ));
        let pad = (1.5 * config.order as f64 / config.low_hz * sample_rate_hz).ceil() as usize;
        Ok(BandPass {
            low_hz: config.low_hz,
            high_hz,
            order: config.order,
            sample_rate_hz,
            sections,
            pad,
        })
    }

    /// A zero-phase low pass of the same order at this band's low corner: what the band takes
    /// away below it (the two are power-complementary, `G_lp + G_hp = 1` for each pass).
    pub fn low_band(&self) -> BandPass {
        BandPass {
            sections: butterworth(Pass::Low, self.order, self.low_hz, self.sample_rate_hz),
            high_hz: self.low_hz,
            ..self.clone()
        }
    }

    /// The zero-phase gain at `f`: `|H(f)|²` of the forward pass, computed from the sections.
    pub fn gain(&self, f: f64) -> f64 {
        self.sections
            .iter()
            .map(|s| s.power_gain(f, self.sample_rate_hz))
            .product()
    }

    /// Filters a padded record in place: forward, then backward.
    pub fn apply(&self, x: &mut [f64]) {
        for s in &self.sections {
            s.run(x);
        }
        x.reverse();
        for s in &self.sections {
            s.run(x);
        }
        x.reverse();
    }

    /// The record with [`BandPass::pad`] zeros on either side, filtered.
    pub fn filter(&self, record: &[f64]) -> Vec<f64> {
        let mut x = vec![0.0; record.len() + 2 * self.pad];
        x[self.pad..self.pad + record.len()].copy_from_slice(record);
        self.apply(&mut x);
        x
    }

    /// The filter's response to one sample, `M e`, from `-half` to `+half` samples about it
    /// (symmetric: the filter has zero phase), taken far from any end.
    pub fn kernel(&self, half: usize) -> Vec<f64> {
        let centre = self.pad + half;
        let mut x = vec![0.0; 2 * centre + 1];
        x[centre] = 1.0;
        self.apply(&mut x);
        x[centre - half..=centre + half].to_vec()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn analog(f: f64, fc: f64, fs: f64, order: usize, pass: Pass) -> f64 {
        let (w, wc) = (
            (std::f64::consts::PI * f / fs).tan(),
            (std::f64::consts::PI * fc / fs).tan(),
        );
        let r = match pass {
            Pass::High => wc / w,
            Pass::Low => w / wc,
        };
        1.0 / (1.0 + r.powi(2 * order as i32))
    }

    #[test]
    fn sections_are_the_prewarped_butterworth() {
        let fs = 100.0;
        for pass in [Pass::High, Pass::Low] {
            for order in [2, 4, 6] {
                let fc = if pass == Pass::High { 0.1 } else { 40.0 };
                let s = butterworth(pass, order, fc, fs);
                for f in [0.02, 0.05, 0.1, 0.3, 1.0, 10.0, 30.0, 40.0, 45.0] {
                    let g: f64 = s.iter().map(|b| b.power_gain(f, fs)).product();
                    let want = analog(f, fc, fs, order, pass);
                    assert!(
                        (g - want).abs() < 1e-9 * want.max(1e-12) + 1e-12,
                        "{pass:?} {order} at {f}: {g} vs {want}"
                    );
                }
                // −3 dB at the corner.
                let g: f64 = s.iter().map(|b| b.power_gain(fc, fs)).product();
                assert!((g - 0.5).abs() < 1e-9);
            }
        }
    }

    #[test]
    fn zero_phase_gain_and_a_symmetric_operator() {
        let band = BandPass::new(&BandConfig::default(), 100.0).unwrap();
        assert_eq!(band.pad, 6000);
        assert!((band.high_hz - 40.0).abs() < 1e-12);
        assert!((band.gain(0.1) - 0.5).abs() < 1e-6);
        assert!((band.gain(5.0) - 1.0).abs() < 1e-6);
        // A sine well inside the band comes out as it went in: same amplitude, no delay.
        let n = 4000;
        let x: Vec<f64> = (0..n)
            .map(|i| (2.0 * std::f64::consts::PI * 2.0 * i as f64 / 100.0).sin())
            .collect();
        let y = band.filter(&x);
        for i in 1000..3000 {
            assert!((y[band.pad + i] - x[i]).abs() < 1e-3, "{i}");
        }
        // ⟨Mx, z⟩ = ⟨x, Mz⟩.
        let m = 3000;
        let a: Vec<f64> = (0..m).map(|i| ((i * 7919) % 101) as f64 - 50.0).collect();
        let b: Vec<f64> = (0..m).map(|i| ((i * 104_729) % 37) as f64 - 18.0).collect();
        let (mut ma, mut mb) = (a.clone(), b.clone());
        band.apply(&mut ma);
        band.apply(&mut mb);
        let l: f64 = ma.iter().zip(&b).map(|(p, q)| p * q).sum();
        let r: f64 = a.iter().zip(&mb).map(|(p, q)| p * q).sum();
        assert!((l - r).abs() < 1e-9 * l.abs().max(1.0), "{l} vs {r}");
        // The kernel is symmetric and its energy is the noise gain ∫G² df / (fs/2).
        let k = band.kernel(200);
        for j in 0..200 {
            assert!((k[j] - k[400 - j]).abs() < 1e-12);
        }
        let energy: f64 = band.kernel(6000).iter().map(|v| v * v).sum();
        let steps = 200_000;
        let integral: f64 = (0..steps)
            .map(|i| {
                let f = (i as f64 + 0.5) * 50.0 / steps as f64;
                band.gain(f).powi(2)
            })
            .sum::<f64>()
            / steps as f64;
        assert!((energy - integral).abs() < 1e-4, "{energy} vs {integral}");
    }

    #[test]
    fn the_low_band_is_the_complement() {
        let band = BandPass::new(
            &BandConfig {
                low_hz: 0.2,
                high_hz: Some(20.0),
                order: 4,
            },
            50.0,
        )
        .unwrap();
        let low = band.low_band();
        for f in [0.01, 0.1, 0.2, 0.5, 2.0] {
            let hp: f64 = butterworth(Pass::High, 4, 0.2, 50.0)
                .iter()
                .map(|b| b.power_gain(f, 50.0))
                .product();
            assert!((hp + low.gain(f) - 1.0).abs() < 1e-9, "{f}");
        }
    }

    #[test]
    fn bad_bands_are_refused_by_name() {
        let e = |c: BandConfig, fs: f64| BandPass::new(&c, fs).unwrap_err().to_string();
        let d = BandConfig::default();
        assert!(e(BandConfig { order: 3, ..d }, 100.0).contains("order 3"));
        assert!(e(BandConfig { low_hz: 0.0, ..d }, 100.0).contains("low_hz"));
        assert!(e(
            BandConfig {
                high_hz: Some(60.0),
                ..d
            },
            100.0
        )
        .contains("Nyquist"));
        assert!(e(d, f64::NAN).contains("sample rate"));
    }
}
