//! Window statistics of a sensor's acceleration, each with its propagated standard uncertainty:
//! peak (PGA), RMS and dominant frequency. Pure functions on slices of samples.
//!
//! All three work on the *demeaned* signal `d_ij = a_ij − ā_j` (sample i, axis j, `ā_j` the
//! window mean of axis j): the mean holds gravity and the static offset, which are tilt's
//! business, not vibration's.
//!
//! # Uncertainty propagation (JCGM 100, linear)
//!
//! Each sample carries a per-axis standard uncertainty `u_ij` that mixes two kinds of error the
//! stream does not separate: calibration-parameter errors (gain, cross-axis, offset, stated
//! model error), which are the same for every sample of a window — **fully correlated** — and
//! output noise, **independent** from sample to sample. [`Propagation::noise_share`] (η) is the
//! share of each `u_ij²` treated as independent noise; the rest, `(1 − η)·u_ij²`, as fully
//! correlated. The default η = 0 treats everything as correlated, which is an upper bound for any
//! real split (Minkowski: `Σ|c_i|u_i ≥ √((Σ|c_i|u_c,i)² + Σc_i²u_n,i²)` whenever
//! `u_i² = u_c,i² + u_n,i²`).
//!
//! - **Peak** `PGA = max_ij |d_ij|`; `u(PGA) = u_i*j*`, the uncertainty of the sample and axis at
//!   the peak. The subtracted mean averages N samples, so its noise is `u/√N` and its offset part
//!   cancels the sample's own; keeping the sample's full `u` errs on the safe side. Not included:
//!   the sampled peak can miss the true one between two samples (small when the sample rate is
//!   ten times the frequencies of interest).
//! - **RMS** per axis `r_j = √(Σ_i d_ij² / N)`, reported for the axis with the largest RMS. The
//!   sensitivities are `c_i = ∂r/∂a_i = d_i / (N·r)` (the mean's own derivative sums to zero).
//!   Correlated part: the errors move together with the sign that increases `r` most (a gain
//!   error does exactly that), `u_c = √(1 − η)·Σ_i |c_i|·u_i`. Independent part:
//!   `u_n² = η·Σ_i c_i²·u_i²`. `u(r) = √(u_c² + u_n²)`. When `r` is 0 the derivative does not
//!   exist; `u(r)` is then the mean `u`, the RMS an error of that size would produce.
//! - **Dominant frequency**: the highest bin of the summed power spectra of the three demeaned,
//!   Hann-windowed axes (zero-padded to a power of two, DC excluded). Its uncertainty comes from
//!   the window length `T = N / f_s`: the spectral line can lie anywhere within ±1/(2T) of the
//!   bin, a rectangular distribution, so `u(f) = 1 / (T·√12)`. Amplitude errors scale the
//!   spectrum but do not move its peak, so they add nothing to first order.

use triax_protocol::CorrectedSample;

use crate::decision::Estimate;

/// How a window's per-sample uncertainties combine; see the module documentation.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Propagation {
    /// Share (0..=1) of each sample's variance treated as independent noise.
    pub noise_share: f64,
}

/// A statistic and the axis (0 = x, 1 = y, 2 = z) it was found on.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AxisEstimate {
    pub estimate: Estimate,
    pub axis: usize,
}

/// Statistics of one window.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct WindowStats {
    pub n_samples: usize,
    pub peak: AxisEstimate,
    pub rms: AxisEstimate,
    /// None when fewer than [`MIN_FREQUENCY_SAMPLES`] samples.
    pub dominant_frequency: Option<Estimate>,
}

/// Fewest samples from which a dominant frequency is worth reporting.
pub const MIN_FREQUENCY_SAMPLES: usize = 16;

/// Axis names for statements.
pub const AXIS_NAMES: [&str; 3] = ["x", "y", "z"];

fn means(samples: &[CorrectedSample]) -> [f64; 3] {
    let mut m = [0.0; 3];
    for s in samples {
        for (mj, a) in m.iter_mut().zip(s.accel_mps2) {
            *mj += f64::from(a);
        }
    }
    m.map(|x| x / samples.len() as f64)
}

/// Statistics of `samples`, taken as consecutive at `sample_rate_hz`. None when empty.
///
/// Callers pass only usable samples (finite values and uncertainties).
pub fn window_stats(
    samples: &[CorrectedSample],
    sample_rate_hz: f64,
    propagation: Propagation,
    with_frequency: bool,
) -> Option<WindowStats> {
    if samples.is_empty() {
        return None;
    }
    let n = samples.len();
    let mean = means(samples);
    let d = |s: &CorrectedSample, j: usize| f64::from(s.accel_mps2[j]) - mean[j];
    let u = |s: &CorrectedSample, j: usize| f64::from(s.uncertainty_mps2[j]);

    let mut peak = AxisEstimate {
        estimate: Estimate {
            value: -1.0,
            standard_uncertainty: 0.0,
        },
        axis: 0,
    };
    let mut sum_sq = [0.0f64; 3];
    for s in samples {
        for (j, sum) in sum_sq.iter_mut().enumerate() {
            let dj = d(s, j);
            *sum += dj * dj;
            if dj.abs() > peak.estimate.value {
                peak = AxisEstimate {
                    estimate: Estimate {
                        value: dj.abs(),
                        standard_uncertainty: u(s, j),
                    },
                    axis: j,
                };
            }
        }
    }

    let rms_axis = (0..3)
        .max_by(|&a, &b| sum_sq[a].total_cmp(&sum_sq[b]))
        .unwrap_or(0);
    let r = (sum_sq[rms_axis] / n as f64).sqrt();
    let eta = propagation.noise_share.clamp(0.0, 1.0);
    let rms_u = if r > 0.0 {
        let (mut correlated, mut independent_sq) = (0.0, 0.0);
        for s in samples {
            let c = d(s, rms_axis) / (n as f64 * r);
            let ui = u(s, rms_axis);
            correlated += c.abs() * ui;
            independent_sq += c * c * ui * ui;
        }
        ((1.0 - eta) * correlated * correlated + eta * independent_sq).sqrt()
    } else {
        samples.iter().map(|s| u(s, rms_axis)).sum::<f64>() / n as f64
    };
    let rms = AxisEstimate {
        estimate: Estimate {
            value: r,
            standard_uncertainty: rms_u,
        },
        axis: rms_axis,
    };

    // The spectrum is most of the cost of a window: only for sensors with a frequency limit.
    let dominant_frequency = (with_frequency && n >= MIN_FREQUENCY_SAMPLES).then(|| {
        let window_s = n as f64 / sample_rate_hz;
        Estimate {
            value: dominant_frequency_hz(samples, &mean, sample_rate_hz),
            standard_uncertainty: 1.0 / (window_s * 12f64.sqrt()),
        }
    });

    Some(WindowStats {
        n_samples: n,
        peak,
        rms,
        dominant_frequency,
    })
}

/// Frequency of the highest non-DC bin of the summed power spectra of the three axes.
fn dominant_frequency_hz(samples: &[CorrectedSample], mean: &[f64; 3], sample_rate_hz: f64) -> f64 {
    let n = samples.len();
    let m = n.next_power_of_two();
    let mut power = vec![0.0f64; m / 2 + 1];
    let mut buf = vec![(0.0f64, 0.0f64); m];
    for (j, mean_j) in mean.iter().enumerate() {
        for (i, slot) in buf.iter_mut().enumerate() {
            *slot = match samples.get(i) {
                Some(s) => {
                    // Hann taper: a window edge would otherwise smear power into every bin.
                    let w =
                        0.5 - 0.5 * (2.0 * std::f64::consts::PI * i as f64 / (n - 1) as f64).cos();
                    ((f64::from(s.accel_mps2[j]) - mean_j) * w, 0.0)
                }
                None => (0.0, 0.0),
            };
        }
        fft_in_place(&mut buf);
        for (p, &(re, im)) in power.iter_mut().zip(&buf) {
            *p += re * re + im * im;
        }
    }
    let bin = (1..power.len())
        .max_by(|&a, &b| power[a].total_cmp(&power[b]))
        .unwrap_or(1);
    bin as f64 * sample_rate_hz / m as f64
}

/// Iterative radix-2 Cooley–Tukey FFT; `buf.len()` must be a power of two.
fn fft_in_place(buf: &mut [(f64, f64)]) {
    let n = buf.len();
    debug_assert!(n.is_power_of_two());
    let mut j = 0;
    for i in 1..n {
        let mut bit = n >> 1;
        while j & bit != 0 {
            j ^= bit;
            bit >>= 1;
        }
        j |= bit;
        if i < j {
            buf.swap(i, j);
        }
    }
    let mut len = 2;
    while len <= n {
        let angle = -2.0 * std::f64::consts::PI / len as f64;
        let (w_im, w_re) = angle.sin_cos();
        for start in (0..n).step_by(len) {
            let (mut cr, mut ci) = (1.0, 0.0);
            for k in 0..len / 2 {
                let (ar, ai) = buf[start + k];
                let (br, bi) = buf[start + k + len / 2];
                let (tr, ti) = (br * cr - bi * ci, br * ci + bi * cr);
                buf[start + k] = (ar + tr, ai + ti);
                buf[start + k + len / 2] = (ar - tr, ai - ti);
                (cr, ci) = (cr * w_re - ci * w_im, cr * w_im + ci * w_re);
            }
        }
        len <<= 1;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample(a: [f32; 3], u: [f32; 3]) -> CorrectedSample {
        CorrectedSample {
            accel_mps2: a,
            uncertainty_mps2: u,
            flags: 0,
        }
    }

    fn sine(n: usize, rate_hz: f64, freq_hz: f64, amp: f64, u: f32) -> Vec<CorrectedSample> {
        (0..n)
            .map(|i| {
                let t = i as f64 / rate_hz;
                let x = amp * (2.0 * std::f64::consts::PI * freq_hz * t).sin();
                sample([x as f32, 0.0, 9.81], [u, u, u])
            })
            .collect()
    }

    const CORRELATED: Propagation = Propagation { noise_share: 0.0 };

    #[test]
    fn sine_statistics() {
        let s = sine(1000, 100.0, 2.5, 0.3, 0.01);
        let w = window_stats(&s, 100.0, CORRELATED, true).unwrap();
        assert_eq!(w.peak.axis, 0);
        assert!((w.peak.estimate.value - 0.3).abs() < 1e-3, "{w:?}");
        assert_eq!(w.peak.estimate.standard_uncertainty, 0.01f32 as f64);
        assert_eq!(w.rms.axis, 0);
        assert!((w.rms.estimate.value - 0.3 / 2f64.sqrt()).abs() < 1e-3);
        // Fully correlated, equal u: u(r) = u·mean|d| / r = u·(2√2/π) for a sine.
        let expected = 0.01 * 2.0 * 2f64.sqrt() / std::f64::consts::PI;
        assert!(
            (w.rms.estimate.standard_uncertainty - expected).abs() < 1e-4,
            "{w:?}"
        );
        let f = w.dominant_frequency.unwrap();
        // Bin spacing after zero padding is 100/1024 Hz; the 2.5 Hz line lands within one bin.
        assert!((f.value - 2.5).abs() < 0.1, "{f:?}");
        assert!((f.standard_uncertainty - 1.0 / (10.0 * 12f64.sqrt())).abs() < 1e-12);
    }

    #[test]
    fn independent_noise_shrinks_rms_uncertainty_with_n() {
        let s = sine(1000, 100.0, 2.5, 0.3, 0.01);
        let all_noise = window_stats(&s, 100.0, Propagation { noise_share: 1.0 }, true).unwrap();
        let correlated = window_stats(&s, 100.0, CORRELATED, true).unwrap();
        // Independent: u(r) ≈ u/√N; correlated does not average away.
        let u_noise = all_noise.rms.estimate.standard_uncertainty;
        assert!((u_noise - 0.01 / 1000f64.sqrt()).abs() < 2e-5, "{u_noise}");
        assert!(correlated.rms.estimate.standard_uncertainty > 10.0 * u_noise);
    }

    #[test]
    fn gravity_is_not_vibration() {
        let s = vec![sample([0.0, 0.0, 9.81], [0.01; 3]); 32];
        let w = window_stats(&s, 100.0, CORRELATED, true).unwrap();
        assert!(w.peak.estimate.value < 1e-6);
        assert_eq!(w.rms.estimate.value, 0.0);
        assert!((w.rms.estimate.standard_uncertainty - 0.01).abs() < 1e-6);
        assert!(window_stats(&[], 100.0, CORRELATED, true).is_none());
    }

    #[test]
    fn fft_matches_a_direct_dft() {
        let x: Vec<(f64, f64)> = (0..16)
            .map(|i| ((i as f64 * 0.7).sin() + 0.1 * i as f64, 0.0))
            .collect();
        let mut fast = x.clone();
        fft_in_place(&mut fast);
        for (k, &(re, im)) in fast.iter().enumerate() {
            let (mut dr, mut di) = (0.0, 0.0);
            for (i, &(xr, _)) in x.iter().enumerate() {
                let a = -2.0 * std::f64::consts::PI * (k * i) as f64 / 16.0;
                dr += xr * a.cos();
                di += xr * a.sin();
            }
            assert!((re - dr).abs() < 1e-9 && (im - di).abs() < 1e-9, "bin {k}");
        }
    }
}
