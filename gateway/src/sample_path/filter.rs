//! Second-order IIR sections (biquads) over three axes, for the crossover, the tilt low pass and
//! the frequency-domain detector.
//!
//! Designs are Butterworth by the bilinear transform with pre-warping, in transposed direct
//! form II, which keeps two state values per axis and is well behaved in f64 at the low corner
//! frequencies used here (0.1 Hz at 100 Hz sampling). The exception is the detector's high pass,
//! [`HighPass4x32`], in f32 lanes: its corner is near the band's top, where f32 is well behaved,
//! and it runs on every sample of every calibrated sensor.
//!
//! A filter starts in the steady state of its first input ([`Biquad3::prime`]) rather than at
//! zero, so a sensor that joins with 9.81 m/s² on one axis does not ring for seconds.

use std::f64::consts::{FRAC_1_SQRT_2, PI};

use serde::{Deserialize, Serialize};

/// Q of the two sections of a fourth-order Butterworth filter.
const BUTTERWORTH4_Q: [f64; 2] = [0.541_196_100_146_197, 1.306_562_964_876_376_4];

/// Coefficients of one section, normalised so that `a0 = 1`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Coefficients {
    b: [f64; 3],
    a: [f64; 2],
    /// Gain at DC by design (1 for a low pass, 0 for a high pass); computing it from the
    /// coefficients loses digits at low corners.
    dc: f64,
}

impl Coefficients {
    fn design(cutoff_hz: f64, sample_rate_hz: f64, q: f64, high_pass: bool) -> Coefficients {
        let k = (PI * cutoff_hz / sample_rate_hz).tan();
        let norm = 1.0 / (1.0 + k / q + k * k);
        let a = [2.0 * (k * k - 1.0) * norm, (1.0 - k / q + k * k) * norm];
        let b0 = if high_pass { norm } else { k * k * norm };
        let b1 = if high_pass { -2.0 * b0 } else { 2.0 * b0 };
        Coefficients {
            b: [b0, b1, b0],
            a,
            dc: if high_pass { 0.0 } else { 1.0 },
        }
    }

    /// Second-order Butterworth low pass.
    pub fn low_pass(cutoff_hz: f64, sample_rate_hz: f64) -> Coefficients {
        Self::design(cutoff_hz, sample_rate_hz, FRAC_1_SQRT_2, false)
    }

    /// Group delay at DC, in samples: a ramp comes out of the filter this much later, exactly,
    /// once the start has faded (for a low pass; the DC gain must not be zero).
    pub fn dc_delay_samples(&self) -> f64 {
        let [b0, b1, b2] = self.b;
        let [a1, a2] = self.a;
        (b1 + 2.0 * b2) / (b0 + b1 + b2) - (a1 + 2.0 * a2) / (1.0 + a1 + a2)
    }

    /// Σh² of the impulse response: the share of a white input's variance the filter passes.
    pub fn noise_gain(&self) -> f64 {
        // The response decays as |pole|ⁿ: stop once the state is 1e-7 of the response's norm
        // (the tail's energy is then ~1e-12 of the total at the slowest corners), or at a bound
        // far beyond any corner this gateway designs.
        let mut f = Biquad3::new(*self);
        f.primed = true;
        let mut energy = 0.0;
        let mut x = 1.0;
        for n in 0..10_000_000u32 {
            let y = f.step([x, 0.0, 0.0])[0];
            x = 0.0;
            energy += y * y;
            if n > 16 && f.s1[0].abs() + f.s2[0].abs() < 1e-7 * energy.sqrt() {
                break;
            }
        }
        energy
    }

    /// Second-order Butterworth high pass.
    pub fn high_pass(cutoff_hz: f64, sample_rate_hz: f64) -> Coefficients {
        Self::design(cutoff_hz, sample_rate_hz, FRAC_1_SQRT_2, true)
    }
}

/// Whether a corner frequency can be realised at a sample rate: strictly inside (0, 0.45·fs),
/// away from the Nyquist frequency where the bilinear warp makes the design meaningless.
pub fn realisable(cutoff_hz: f64, sample_rate_hz: f64) -> bool {
    cutoff_hz.is_finite() && cutoff_hz > 0.0 && cutoff_hz < 0.45 * sample_rate_hz
}

/// One biquad section applied to three axes with shared coefficients.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Biquad3 {
    c: Coefficients,
    s1: [f64; 3],
    s2: [f64; 3],
    primed: bool,
}

impl Biquad3 {
    pub fn new(c: Coefficients) -> Biquad3 {
        Biquad3 {
            c,
            s1: [0.0; 3],
            s2: [0.0; 3],
            primed: false,
        }
    }

    /// Sets the state to the steady state for a constant input `x`.
    pub fn prime(&mut self, x: [f64; 3]) {
        let g = self.c.dc;
        for (k, &xk) in x.iter().enumerate() {
            let y = g * xk;
            self.s2[k] = self.c.b[2] * xk - self.c.a[1] * y;
            self.s1[k] = y - self.c.b[0] * xk;
        }
        self.primed = true;
    }

    pub fn is_primed(&self) -> bool {
        self.primed
    }

    pub fn coefficients(&self) -> &Coefficients {
        &self.c
    }

    /// Filters one finite sample. Callers never pass NaN or infinity: one would poison the state
    /// for good.
    #[inline(always)]
    pub fn step(&mut self, x: [f64; 3]) -> [f64; 3] {
        if !self.primed {
            self.prime(x);
        }
        let Coefficients { b, a, .. } = self.c;
        let mut y = [0.0; 3];
        for k in 0..3 {
            y[k] = b[0] * x[k] + self.s1[k];
            self.s1[k] = b[1] * x[k] - a[0] * y[k] + self.s2[k];
            self.s2[k] = b[2] * x[k] - a[1] * y[k];
        }
        y
    }
}

/// A fourth-order Butterworth filter, high or low pass (two cascaded sections).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Butterworth4 {
    sections: [Biquad3; 2],
}

impl Butterworth4 {
    #[cfg(test)]
    pub fn high_pass(cutoff_hz: f64, sample_rate_hz: f64) -> Butterworth4 {
        Butterworth4::new(cutoff_hz, sample_rate_hz, true)
    }

    pub fn low_pass(cutoff_hz: f64, sample_rate_hz: f64) -> Butterworth4 {
        Butterworth4::new(cutoff_hz, sample_rate_hz, false)
    }

    fn new(cutoff_hz: f64, sample_rate_hz: f64, high: bool) -> Butterworth4 {
        Butterworth4 {
            sections: BUTTERWORTH4_Q
                .map(|q| Biquad3::new(Coefficients::design(cutoff_hz, sample_rate_hz, q, high))),
        }
    }

    #[inline(always)]
    pub fn step(&mut self, x: [f64; 3]) -> [f64; 3] {
        let y = self.sections[0].step(x);
        self.sections[1].step(y)
    }

    /// Sets the state to the steady state for a constant input `x`.
    pub fn prime(&mut self, x: [f64; 3]) {
        self.sections[0].prime(x);
        let g = self.sections[0].coefficients().dc;
        self.sections[1].prime(x.map(|v| g * v));
    }
}

/// Three axes in the first three lanes of four, so that one SIMD register holds a quantity for
/// every axis (the fourth lane idles at zero).
pub type Lanes = [f32; 4];

/// A fourth-order Butterworth high pass in f32 over [`Lanes`], for the frequency detector,
/// which runs on every sample of every batch: four f32 lanes take one SSE instruction where
/// three f64 axes take three, and the detector only compares an RMS with a threshold.
///
/// Why f32 is enough: the input is taken relative to the first sample (`origin`),
/// which a high pass cannot tell from the true input (its gain at DC is zero, and that start
/// is its steady state), so the state holds the signal's variation and not gravity's 1 g, and
/// the round-off stays some 10⁻⁷ of that variation. The sections are the same transposed
/// direct form II as [`Biquad3`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct HighPass4x32 {
    /// Per section: b0, b1, b2, a1, a2.
    c: [[f32; 5]; 2],
    s1: [Lanes; 2],
    s2: [Lanes; 2],
    origin: Lanes,
    primed: bool,
}

impl HighPass4x32 {
    pub fn new(cutoff_hz: f64, sample_rate_hz: f64) -> HighPass4x32 {
        let c = BUTTERWORTH4_Q.map(|q| {
            let c = Coefficients::design(cutoff_hz, sample_rate_hz, q, true);
            [c.b[0], c.b[1], c.b[2], c.a[0], c.a[1]].map(|x| x as f32)
        });
        HighPass4x32 {
            c,
            s1: [[0.0; 4]; 2],
            s2: [[0.0; 4]; 2],
            origin: [0.0; 4],
            primed: false,
        }
    }

    /// Forgets the past: the next sample primes the filter again.
    pub fn reset(&mut self) {
        self.primed = false;
    }

    /// Filters one finite sample (the same contract as [`Biquad3::step`]).
    #[cfg(test)]
    pub fn step(&mut self, x: Lanes) -> Lanes {
        let mut y = [x];
        self.filter_in_place(&mut y);
        y[0]
    }

    /// Replaces finite samples, in order, by their filtered values. The state is copied to
    /// locals for the loop, where the compiler keeps it in registers rather than store it
    /// back on every sample.
    pub fn filter_in_place(&mut self, samples: &mut [Lanes]) {
        let Some(&first) = samples.first() else {
            return;
        };
        if !self.primed {
            // The steady state of a constant input, relative to itself: all zero.
            self.origin = first;
            self.s1 = [[0.0; 4]; 2];
            self.s2 = [[0.0; 4]; 2];
            self.primed = true;
        }
        let (origin, c) = (self.origin, self.c);
        let (mut s1, mut s2) = (self.s1, self.s2);
        for v in samples {
            let mut y = [0.0; 4];
            for k in 0..4 {
                y[k] = v[k] - origin[k];
            }
            for (sec, [b0, b1, b2, a1, a2]) in c.into_iter().enumerate() {
                let x = y;
                // The terms that do not wait for y are summed first: the recursion's
                // critical path is then one multiply and one subtraction per section.
                for k in 0..4 {
                    y[k] = b0 * x[k] + s1[sec][k];
                    s1[sec][k] = (b1 * x[k] + s2[sec][k]) - a1 * y[k];
                    s2[sec][k] = b2 * x[k] - a2 * y[k];
                }
            }
            *v = y;
        }
        (self.s1, self.s2) = (s1, s2);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Steady-state amplitude of the filter's response to a unit sine.
    fn gain(mut f: impl FnMut([f64; 3]) -> [f64; 3], freq_hz: f64, fs: f64) -> f64 {
        let n = (fs * 40.0) as usize;
        let mut peak: f64 = 0.0;
        for i in 0..n {
            let x = (2.0 * PI * freq_hz * i as f64 / fs).sin();
            let y = f([x, 0.0, 0.0]);
            if i > n / 2 {
                peak = peak.max(y[0].abs());
            }
        }
        peak
    }

    /// A second-order Butterworth low pass delays a ramp by √2/(2π·fc) (analog prototype; the
    /// bilinear design at fc ≪ fs differs by a hair), and passes 2·ENBW/fs of white noise's
    /// variance with ENBW = fc·(π/4)/sin(π/4) (the Butterworth noise bandwidth for order 2).
    #[test]
    fn low_pass_delay_and_noise_gain_match_the_analog_prototype() {
        let (fc, fs) = (0.1, 100.0);
        let c = Coefficients::low_pass(fc, fs);
        let delay_s = c.dc_delay_samples() / fs;
        let expect_s = 2f64.sqrt() / (2.0 * PI * fc);
        assert!(
            (delay_s - expect_s).abs() < 1e-4 * expect_s,
            "{delay_s} vs {expect_s}"
        );
        let enbw_hz = fc * (PI / 4.0) / (PI / 4.0).sin();
        let expect_gain = 2.0 * enbw_hz / fs;
        let gain = c.noise_gain();
        assert!(
            (gain - expect_gain).abs() < 1e-3 * expect_gain,
            "{gain} vs {expect_gain}"
        );

        // And by simulation: a ramp, once the start has faded, lags by exactly that delay.
        let mut f = Biquad3::new(c);
        let rate = 0.3;
        let mut lag_s = 0.0;
        for i in 0..(60.0 * fs) as usize {
            let t = i as f64 / fs;
            let y = f.step([rate * t, 0.0, 0.0])[0];
            lag_s = t - y / rate;
        }
        assert!((lag_s - delay_s).abs() < 1e-6, "{lag_s} vs {delay_s}");
    }

    #[test]
    fn butterworth_responses() {
        let fs = 100.0;
        let mut lp = Biquad3::new(Coefficients::low_pass(1.0, fs));
        assert!((gain(|x| lp.step(x), 0.1, fs) - 1.0).abs() < 0.01);
        let mut lp = Biquad3::new(Coefficients::low_pass(1.0, fs));
        assert!((gain(|x| lp.step(x), 1.0, fs) - FRAC_1_SQRT_2).abs() < 0.01);
        let mut lp = Biquad3::new(Coefficients::low_pass(1.0, fs));
        assert!(gain(|x| lp.step(x), 10.0, fs) < 0.011);

        let mut hp = Butterworth4::high_pass(12.5, fs);
        assert!(
            gain(|x| hp.step(x), 5.0, fs) < 0.03,
            "in-band sway is rejected"
        );
        let mut hp = Butterworth4::high_pass(12.5, fs);
        assert!(gain(|x| hp.step(x), 30.0, fs) > 0.95);
        let mut lp4 = Butterworth4::low_pass(0.4, fs);
        assert!(gain(|x| lp4.step(x), 2.0, fs) < 0.002);
    }

    /// The f32 detector filter follows the f64 one to within f32 round-off of the signal's
    /// variation, even on top of 1 g.
    #[test]
    fn f32_high_pass_matches_f64() {
        let fs = 100.0;
        let mut wide = Butterworth4::high_pass(12.5, fs);
        let mut narrow = HighPass4x32::new(12.5, fs);
        let mut worst: f64 = 0.0;
        for i in 0..2000 {
            let t = i as f64 / fs;
            let x = [
                0.01 * (2.0 * PI * 3.0 * t).sin() + 0.002 * (2.0 * PI * 31.0 * t).sin(),
                0.005 * (2.0 * PI * 22.0 * t).cos(),
                9.81 + 0.001 * (2.0 * PI * 40.0 * t).sin(),
            ];
            // Both from the same f32 input, as on the wire: what differs is the arithmetic.
            let x32 = x.map(|v| v as f32);
            let y64 = wide.step(x32.map(f64::from));
            let y32 = narrow.step([x32[0], x32[1], x32[2], 0.0]);
            for k in 0..3 {
                worst = worst.max((y64[k] - f64::from(y32[k])).abs());
            }
            assert_eq!(y32[3], 0.0, "the idle lane stays zero");
        }
        // Relative to the 0.01 signal, 10⁻⁵: far below any threshold the detector uses.
        assert!(worst < 1e-7, "worst difference {worst:e}");
    }

    #[test]
    fn priming_removes_the_start_transient() {
        let mut lp = Biquad3::new(Coefficients::low_pass(0.1, 100.0));
        let y = lp.step([0.0, 0.0, 9.81]);
        assert!((y[2] - 9.81).abs() < 1e-12);
        let mut hp = Butterworth4::high_pass(12.5, 100.0);
        let y = hp.step([0.0, 0.0, 9.81]);
        assert!(y[2].abs() < 1e-12);
    }
}
