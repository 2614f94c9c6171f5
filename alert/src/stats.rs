//! Window statistics of a sensor's acceleration, each with its standard uncertainty: peak,
//! RMS and dominant frequency. Pure functions on a window's samples.
//!
//! # What each value estimates
//!
//! The **motion**, not the sampled record: the acceleration the sensor underwent, above the
//! vibration baseline ([`crate::highpass`]), between the samples as well as at them, without the
//! sensor's noise. Three things separate a window's samples from that motion, and each is
//! corrected or counted:
//!
//! - **Noise on a maximum.** The largest of n noisy samples is biased upward, and by more the
//!   more samples lie near the top: with 30 samples within two noise deviations of a sway's
//!   crest, the sampled maximum reads about two deviations high. The previous rule (the peak
//!   sample's own u) raised false `exceeded` on a quarter of the windows whose true peak sat at
//!   the limit.
//! - **The window's cut.** A window mean is not the baseline when the window holds part of a
//!   cycle; the vibration is the high-passed stream instead, the same whatever the window.
//! - **Between samples.** The crest of a 5 Hz sway sampled at 100 Hz can fall between samples
//!   and read 1.2 % low.
//!
//! # Two estimators
//!
//! Per axis, a window is first fitted with one sinusoid plus offset and trend
//! ([`crate::sinefit`]). When the fit is adequate (its residual is white noise), the window is a
//! single sway and the fit gives all three statistics with least-squares uncertainties that
//! cover the truth about 95 % of the time at k = 2: the peak is the amplitude, the RMS that of
//! the fitted sinusoid over the window's sample times, the frequency the fitted one. Fitting
//! every sample of the window averages the noise instead of picking its largest excursion.
//!
//! Otherwise (several modes, a transient, broadband motion) the statistics come from the
//! samples of the high-passed stream, with bounds that hold whatever the motion:
//!
//! - **Peak**: `D = max |v_i|` over the axis's samples, σ its noise (below). The true peak
//!   of the sampled motion is at least `D − q·σ`, with `q = Φ⁻¹(Φ(k)^(1/C))` the quantile of the
//!   largest of C standard normals and C the number of samples within 4σ of D, any of which
//!   could be the noisy maximum: one-sided, this errs with probability at most 1 − Φ(k) even
//!   when all C sit exactly at the crest. It is at most `D + k·σ` (the sample at the true
//!   crest was no more than kσ low), plus the crest between samples: the larger of the rise
//!   of the parabola through the largest sample and its neighbours and `D·(1/cos(π·f/f_s) − 1)`
//!   for a sine at the axis's spectral peak f with its crest half a sample off. Value and u are the centre of this interval
//!   and its half-width over k. Conservative: the interval covers more than 95 % when fewer
//!   samples compete for the maximum.
//! - **RMS**: `√(mean v² − σ²)`, the noise's contribution removed; u from the variance of a
//!   mean of squares, `(4r²σ² + 2σ⁴)/n`, and of the σ² estimate, `2·2.63·σ⁴/n` (the fourth
//!   difference's autocorrelation).
//! - **Dominant frequency**: the highest bin of the summed power spectra of the three
//!   high-passed, Hann-tapered axes (zero-padded to a power of two m, DC excluded); the line
//!   lies within half a bin, `u = (f_s/m)/√12`.
//!
//! # Noise and calibration
//!
//! σ of each axis is measured, not assumed: fourth differences of the high-passed samples,
//! `mean((Δ⁴v)²)/70`, which cancel motion well below the sample rate; it is capped at the mean
//! stated u of the axis, which bounds it. Calibration errors (gain, cross-axis) are common to
//! every sample of a window and do not average away; [`Propagation::noise_share`] (η) says
//! which share of each sample's stated variance is noise, and `√(1 − η)·ū` is added as such a
//! common error: to the peak whole, to the RMS scaled by `mean|v| / r` (a gain error moves
//! every sample in proportion). η = 0, the default, takes all of u as common: an upper bound.
//! Frequencies are not moved by amplitude errors.

use crate::decision::Estimate;
use crate::highpass::Response;
use crate::sinefit::{self, SineFit};
use triax_client::normal;

/// How a window's per-sample uncertainties combine; see the module documentation.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Propagation {
    /// Share (0..=1) of each sample's stated variance that is noise.
    pub noise_share: f64,
}

/// One sample of a window.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Point {
    /// Position on the window's sample grid: 0 for its first sample time.
    pub index: u32,
    pub accel_mps2: [f32; 3],
    /// The high-passed acceleration ([`crate::highpass`]).
    pub vibration_mps2: [f32; 3],
    pub uncertainty_mps2: [f32; 3],
}

/// What to compute, and from when a statistic matters.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Request {
    pub sample_rate_hz: f64,
    /// Sample times in the window, present or not.
    pub grid_len: u32,
    pub propagation: Propagation,
    /// Coverage factor of the intervals.
    pub k: f64,
    /// Peak and RMS are estimated only when a cheap upper bound reaches these; None: not
    /// wanted. A statistic that cannot reach its threshold decides nothing.
    pub peak_threshold: Option<f64>,
    pub rms_threshold: Option<f64>,
    pub frequency: bool,
    /// The vibration baseline's response, which a fitted sway is carried through; None: the
    /// values are the motion as it is.
    pub highpass: Option<Response>,
}

/// How a statistic was estimated, for the alert's statement.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Method {
    /// From the fitted sinusoid.
    Sine { frequency_hz: f64, noise_mps2: f64 },
    /// From the samples: `candidates` of them within 4σ of the largest.
    Samples { noise_mps2: f64, candidates: usize },
}

/// A statistic, the axis (0 = x, 1 = y, 2 = z) it was found on, and how.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AxisEstimate {
    pub estimate: Estimate,
    pub axis: usize,
    pub method: Method,
}

/// Statistics of one window; None for what was not asked for or cannot reach its threshold.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct WindowStats {
    pub n_samples: usize,
    /// Largest RMS of the high-passed axes, noise included: whether there is motion at all.
    pub vibration_rms_mps2: f64,
    pub peak: Option<AxisEstimate>,
    pub rms: Option<AxisEstimate>,
    pub dominant_frequency: Option<AxisEstimate>,
}

/// Fewest samples from which a dominant frequency is worth reporting.
pub const MIN_FREQUENCY_SAMPLES: usize = 16;

/// Highest frequency, as a share of the sample rate, that the sinusoid fit speaks for: above
/// it a crest can hide between samples by more than 30 %.
const SINE_MAX_RATE_SHARE: f64 = 0.25;

/// Axis names for statements.
pub const AXIS_NAMES: [&str; 3] = ["x", "y", "z"];

/// One axis of a window, gathered once.
struct AxisData {
    index: Vec<u32>,
    accel: Vec<f64>,
    vibration: Vec<f64>,
    mean_u: f64,
    /// Measured noise, capped at `mean_u`.
    noise: f64,
    /// Measured noise uncapped, and how many fourth differences it rests on; None with too
    /// few.
    noise_measured: Option<(f64, usize)>,
    /// Largest |v| and where.
    peak: f64,
    peak_at: usize,
    mean_square: f64,
    mean_abs: f64,
    /// Half the range of the acceleration itself: what the sinusoid fit, which does not use the
    /// high-passed values, can see.
    accel_half_range: f64,
    /// Spectral peak of this axis: (frequency, power).
    spectral_peak: (f64, f64),
    /// The sinusoid search: None before it ran, then its outcome.
    fit: Option<Option<(f64, Option<SineFit>)>>,
}

impl AxisData {
    fn gather(points: &[Point], j: usize) -> AxisData {
        let n = points.len() as f64;
        let index: Vec<u32> = points.iter().map(|p| p.index).collect();
        let accel: Vec<f64> = points.iter().map(|p| f64::from(p.accel_mps2[j])).collect();
        let vibration: Vec<f64> = points
            .iter()
            .map(|p| f64::from(p.vibration_mps2[j]))
            .collect();
        let mean_u = points
            .iter()
            .map(|p| f64::from(p.uncertainty_mps2[j]))
            .sum::<f64>()
            / n;
        let (peak_at, peak) = vibration
            .iter()
            .map(|v| v.abs())
            .enumerate()
            .fold((0, -1.0), |m, (i, v)| if v > m.1 { (i, v) } else { m });
        let noise_measured =
            fourth_difference_variance(&index, &vibration).map(|(var, runs)| (var.sqrt(), runs));
        let noise = noise_measured.map_or(mean_u, |(sd, _)| sd.min(mean_u));
        let (lo, hi) = accel
            .iter()
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(l, h), a| {
                (l.min(*a), h.max(*a))
            });
        AxisData {
            accel_half_range: 0.5 * (hi - lo),
            mean_square: vibration.iter().map(|v| v * v).sum::<f64>() / n,
            mean_abs: vibration.iter().map(|v| v.abs()).sum::<f64>() / n,
            index,
            accel,
            vibration,
            mean_u,
            noise,
            noise_measured,
            peak,
            peak_at,
            spectral_peak: (0.0, 0.0),
            fit: None,
        }
    }

    /// The sinusoid search of this axis, computed once: the ω it ended at and the fit if
    /// adequate. The fit is to the acceleration itself (its offset and trend take the
    /// baseline's place, and a change of motion leaves no filter transient in it) and is then
    /// carried through the high pass's response at its frequency, so that it describes the
    /// motion above the baseline as the high-passed samples do.
    fn search(&mut self, request: &Request, bin_hz: f64) -> Option<(f64, Option<SineFit>)> {
        if self.fit.is_none() {
            let start_hz = self.spectral_peak.0;
            let rate = request.sample_rate_hz;
            let found = (start_hz > 0.0 && start_hz <= SINE_MAX_RATE_SHARE * rate)
                .then(|| {
                    let axis = sinefit::Axis {
                        index: &self.index,
                        value: &self.accel,
                        grid_len: request.grid_len,
                    };
                    sinefit::search(&axis, rate, start_hz, bin_hz, self.mean_u, request.highpass)
                })
                .flatten()
                .map(|(omega, f)| {
                    (
                        omega,
                        f.filter(|f| f.frequency_hz <= SINE_MAX_RATE_SHARE * rate),
                    )
                });
            self.fit = Some(found);
        }
        self.fit.flatten()
    }

    /// The sinusoid fit of this axis, computed once; None when not adequate.
    fn fit(&mut self, request: &Request, bin_hz: f64) -> Option<SineFit> {
        self.search(request, bin_hz).and_then(|(_, f)| f)
    }

    /// Cheap upper bound on the upper end `value + k·u` of anything the peak estimators can
    /// return. The sample bound's upper end is at most D + kσ + crest + k·ū, with the crest at
    /// most D (a quarter of the parabola's curvature, itself at most 4D); the fit's amplitude
    /// is at most the half range over cos(π/4) (a crest half a sample off at a quarter of the
    /// rate, the highest frequency it fits), plus a few u of noise.
    fn peak_bound(&self, k: f64) -> f64 {
        upper_bound(self.peak.max(self.accel_half_range), k, self.mean_u)
    }

    /// The same for the RMS: the samples' RMS with noise is at least the estimate, the fitted
    /// sinusoid's RMS at most its amplitude.
    fn rms_bound(&self, k: f64) -> f64 {
        upper_bound(
            self.mean_square.sqrt().max(self.accel_half_range),
            k,
            self.mean_u,
        )
    }

    /// Noise for the lower end of a peak from the samples: never less than the stated
    /// noise (`√η·ū`), nor than what this window measures, taken at its upper confidence limit.
    /// This path is taken exactly when a window's residual is too loud for one sway, so the
    /// window's own noise is what its largest sample carries; the capped estimate would let
    /// such windows raise `exceeded` more often than 1 − Φ(k).
    fn lower_end_noise(&self, k: f64, p: Propagation) -> f64 {
        let stated = p.noise_share.clamp(0.0, 1.0).sqrt() * self.mean_u;
        let measured = self.noise_measured.map_or(0.0, |(sd, runs)| {
            // The σ² estimate's relative standard deviation is √(5.26/n), σ's half of it.
            sd * (1.0 + 0.5 * k * (5.26 / runs as f64).sqrt())
        });
        self.noise.max(stated).max(measured)
    }

    /// Peak interval (lower, upper) from the samples; see the module documentation.
    fn sample_peak_interval(&self, k: f64, rate_hz: f64, p: Propagation) -> (f64, f64, usize) {
        let sigma = self.noise;
        let sigma_low = self.lower_end_noise(k, p);
        let candidates = self
            .vibration
            .iter()
            .filter(|v| v.abs() >= self.peak - 4.0 * sigma_low)
            .count()
            .max(1);
        let q = normal::max_upper_quantile(normal::cdf(-k), candidates);
        let lower = self.peak - q * sigma_low;
        let upper = self.peak + k * sigma + self.crest_between_samples(rate_hz);
        (lower, upper, candidates)
    }

    /// How far the motion's crest can rise above the largest sample: the larger of the rise of
    /// the parabola through that sample and its neighbours (the local shape) and of a sine at
    /// the axis's spectral peak (at most a quarter of the rate) whose crest falls half a sample
    /// off the grid, `D·(1/cos(π·f/f_s) − 1)` (the parabola alone reads 12 % low at a quarter
    /// of the rate).
    fn crest_between_samples(&self, rate_hz: f64) -> f64 {
        // Above a quarter of the rate a crest between samples is not bounded by three samples
        // (PROTOCOL.md §3.6 says so); the node's anti-alias filter keeps content below it.
        let f = self.spectral_peak.0.min(0.25 * rate_hz);
        let sine = self.peak * (1.0 / (std::f64::consts::PI * f / rate_hz).cos() - 1.0);
        let i = self.peak_at;
        let (Some(&before), Some(&after)) = (
            i.checked_sub(1).and_then(|b| self.index.get(b)),
            self.index.get(i + 1),
        ) else {
            return sine;
        };
        if before + 1 != self.index[i] || self.index[i] + 1 != after {
            return sine;
        }
        let sign = self.vibration[i].signum();
        let (y0, ym, yp) = (
            self.peak,
            sign * self.vibration[i - 1],
            sign * self.vibration[i + 1],
        );
        let curvature = 2.0 * y0 - ym - yp;
        if curvature <= 0.0 {
            return sine;
        }
        // The vertex lies within half a sample of the largest one when that is a crest; the
        // rise is then at most a quarter of the curvature.
        let parabola = ((yp - ym).powi(2) / (8.0 * curvature)).min(0.25 * curvature);
        parabola.max(sine)
    }
}

/// The cheap bound of [`AxisData::peak_bound`] and [`AxisData::rms_bound`] from the size of the
/// samples (`level`: their largest |vibration|, half range or RMS) and their u: twice the size
/// (a crest at most as high again) and a few u of noise and calibration. The monitor's running
/// bounds use it too.
pub fn upper_bound(level: f64, k: f64, u: f64) -> f64 {
    2.0 * level + (2.0 * k + 5.0) * u
}

/// Fourth-difference estimate of white-noise variance over runs of five consecutive grid
/// indices, and how many runs; None with fewer than 16 such runs.
fn fourth_difference_variance(index: &[u32], v: &[f64]) -> Option<(f64, usize)> {
    let (mut sum, mut count) = (0.0, 0usize);
    for w in 0..index.len().saturating_sub(4) {
        if index[w + 4] == index[w] + 4 {
            let d = v[w] - 4.0 * v[w + 1] + 6.0 * v[w + 2] - 4.0 * v[w + 3] + v[w + 4];
            sum += d * d;
            count += 1;
        }
    }
    (count >= 16).then(|| (sum / (70.0 * count as f64), count))
}

/// An interval [lower, upper] with a common error of standard uncertainty `common_u` added, as
/// an estimate whose `value ± k·u` is the widened interval.
fn centred(lower: f64, upper: f64, common_u: f64, k: f64) -> Estimate {
    let half = 0.5 * (upper - lower);
    Estimate {
        value: 0.5 * (lower + upper),
        standard_uncertainty: (half * half / (k * k) + common_u * common_u).sqrt(),
    }
}

/// Statistics of a window's `points` (sorted by index, every value finite). None when empty.
pub fn window_stats(points: &[Point], request: &Request) -> Option<WindowStats> {
    if points.is_empty() {
        return None;
    }
    let n = points.len();
    let k = request.k;
    let mut axes: [AxisData; 3] = [0, 1, 2].map(|j| AxisData::gather(points, j));

    let vibration_rms_mps2 = axes
        .iter()
        .map(|a| a.mean_square.sqrt())
        .fold(0.0, f64::max);
    let wants_peak = request
        .peak_threshold
        .is_some_and(|t| axes.iter().any(|a| a.peak_bound(k) >= t));
    let wants_rms = request
        .rms_threshold
        .is_some_and(|t| axes.iter().any(|a| a.rms_bound(k) >= t));
    let wants_frequency = request.frequency && n >= MIN_FREQUENCY_SAMPLES;
    if !(wants_peak || wants_rms || wants_frequency) {
        return Some(WindowStats {
            n_samples: n,
            vibration_rms_mps2,
            peak: None,
            rms: None,
            dominant_frequency: None,
        });
    }

    let (summed_peak_hz, bin_hz) = spectral_peaks(&mut axes, request.sample_rate_hz);
    let peak = wants_peak.then(|| peak_estimate(&mut axes, request, bin_hz));
    let rms = wants_rms.then(|| rms_estimate(&mut axes, request, bin_hz));
    let dominant_frequency = wants_frequency.then(|| {
        let strongest = (0..3)
            .max_by(|&a, &b| axes[a].spectral_peak.1.total_cmp(&axes[b].spectral_peak.1))
            .unwrap_or(0);
        let noise_mps2 = axes[strongest].noise;
        match axes[strongest].fit(request, bin_hz) {
            Some(f) => AxisEstimate {
                estimate: Estimate {
                    value: f.frequency_hz,
                    standard_uncertainty: f.frequency_u_hz,
                },
                axis: strongest,
                method: Method::Sine {
                    frequency_hz: f.frequency_hz,
                    noise_mps2: f.noise_sd,
                },
            },
            None => AxisEstimate {
                estimate: Estimate {
                    value: summed_peak_hz,
                    standard_uncertainty: bin_hz / 12f64.sqrt(),
                },
                axis: strongest,
                method: Method::Samples {
                    noise_mps2,
                    candidates: n,
                },
            },
        }
    });
    Some(WindowStats {
        n_samples: n,
        vibration_rms_mps2,
        peak,
        rms,
        dominant_frequency,
    })
}

/// What the estimators need of one axis besides its fit and its samples' largest value: from
/// the window's samples, or from the monitor's running sums of them.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AxisSummary {
    /// Largest |high-passed value|.
    pub peak: f64,
    /// Half the range of the acceleration, and its largest |value|.
    pub half_range: f64,
    pub largest_accel: f64,
    /// Mean stated u.
    pub mean_u: f64,
    /// Mean square and mean absolute high-passed value.
    pub mean_square: f64,
    pub mean_abs: f64,
}

impl AxisSummary {
    /// See [`AxisData::peak_bound`].
    fn peak_bound(&self, k: f64) -> f64 {
        upper_bound(self.peak.max(self.half_range), k, self.mean_u)
    }

    /// See [`AxisData::rms_bound`].
    fn rms_bound(&self, k: f64) -> f64 {
        upper_bound(self.mean_square.sqrt().max(self.half_range), k, self.mean_u)
    }

    /// The common (calibration) part of u, by the noise share.
    fn common_u(&self, p: Propagation) -> f64 {
        (1.0 - p.noise_share.clamp(0.0, 1.0)).sqrt() * self.mean_u
    }
}

impl AxisData {
    fn summary(&self) -> AxisSummary {
        AxisSummary {
            peak: self.peak,
            half_range: self.accel_half_range,
            largest_accel: self.accel.iter().fold(0.0f64, |m, a| m.max(a.abs())),
            mean_u: self.mean_u,
            mean_square: self.mean_square,
            mean_abs: self.mean_abs,
        }
    }
}

/// A fitted sway's peak interval, before the common part: amplitude ± k·u, u with the
/// unmodelled motion.
fn fit_peak_interval(f: &SineFit, k: f64) -> (f64, f64, Method) {
    let u = f.amplitude_u.hypot(f.unmodelled_sd);
    (
        f.amplitude - k * u,
        f.amplitude + k * u,
        Method::Sine {
            frequency_hz: f.frequency_hz,
            noise_mps2: f.noise_sd,
        },
    )
}

/// A fitted sway's RMS: (value, u of the fit, the common part's scale mean|v|/RMS, method).
fn fit_rms(f: &SineFit, s: &AxisSummary) -> (f64, f64, f64, Method) {
    let r = f.rms;
    let gain_like = if r > 0.0 {
        s.mean_abs / s.mean_square.sqrt().max(r)
    } else {
        1.0
    };
    (
        r,
        f.rms_u,
        gain_like,
        Method::Sine {
            frequency_hz: f.frequency_hz,
            noise_mps2: f.noise_sd,
        },
    )
}

/// The peak over the axes, from each axis's interval before the common part (`interval`,
/// asked only of axes that can matter); None when `interval` has none for such an axis.
fn peak_estimate_with(
    summaries: &[AxisSummary; 3],
    request: &Request,
    mut interval: impl FnMut(usize) -> Option<(f64, f64, Method)>,
) -> Option<AxisEstimate> {
    let k = request.k;
    let mut best: Option<(f64, f64, f64, usize, Method)> = None;
    for (j, summary) in summaries.iter().enumerate() {
        // An axis whose bound is below the others' lower ends cannot be the peak.
        if best.is_some_and(|b| summary.peak_bound(k) < b.0) {
            continue;
        }
        let (lower, upper, method) = interval(j)?;
        let e = centred(lower, upper, summary.common_u(request.propagation), k);
        let (lo, hi) = (
            e.value - k * e.standard_uncertainty,
            e.value + k * e.standard_uncertainty,
        );
        // The largest of three peaks lies within [max of lower ends, max of upper ends].
        best = Some(match best {
            None => (lo, hi, e.value, j, method),
            Some(b) => {
                let (lo_max, hi_max) = (b.0.max(lo), b.1.max(hi));
                let (axis_j, m) = if e.value > b.2 {
                    (j, method)
                } else {
                    (b.3, b.4)
                };
                (lo_max, hi_max, e.value.max(b.2), axis_j, m)
            }
        });
    }
    best.map(|(lo, hi, _, axis, method)| AxisEstimate {
        estimate: centred(lo, hi, 0.0, k),
        axis,
        method,
    })
}

/// The RMS of the axis where it is largest, from each axis's (value, u, common part's scale,
/// method) (`rms`, asked only of axes that can be the largest); None when `rms` has none for
/// such an axis.
fn rms_estimate_with(
    summaries: &[AxisSummary; 3],
    request: &Request,
    mut rms: impl FnMut(usize) -> Option<(f64, f64, f64, Method)>,
) -> Option<AxisEstimate> {
    let mut best: Option<AxisEstimate> = None;
    for (j, summary) in summaries.iter().enumerate() {
        // The bound is above any value this axis can have: below the best, it cannot win.
        if best.is_some_and(|b| summary.rms_bound(request.k) < b.estimate.value) {
            continue;
        }
        let (value, u, gain_like, method) = rms(j)?;
        let common = summary.common_u(request.propagation);
        let e = AxisEstimate {
            estimate: Estimate {
                value,
                standard_uncertainty: u.hypot(common * gain_like),
            },
            axis: j,
            method,
        };
        if best.is_none_or(|b| e.estimate.value > b.estimate.value) {
            best = Some(e);
        }
    }
    best
}

fn peak_estimate(axes: &mut [AxisData; 3], request: &Request, bin_hz: f64) -> AxisEstimate {
    let k = request.k;
    let summaries = [0, 1, 2].map(|j| axes[j].summary());
    let estimate = peak_estimate_with(&summaries, request, |j| {
        let axis = &mut axes[j];
        Some(match axis.fit(request, bin_hz) {
            Some(f) => fit_peak_interval(&f, k),
            None => {
                let (lower, upper, candidates) =
                    axis.sample_peak_interval(k, request.sample_rate_hz, request.propagation);
                (
                    lower,
                    upper,
                    Method::Samples {
                        noise_mps2: axis.noise,
                        candidates,
                    },
                )
            }
        })
    });
    // Every axis has an interval, and the first always runs: the estimate is there.
    estimate.unwrap_or(AxisEstimate {
        estimate: centred(0.0, 0.0, 0.0, k),
        axis: 0,
        method: Method::Samples {
            noise_mps2: 0.0,
            candidates: 0,
        },
    })
}

fn rms_estimate(axes: &mut [AxisData; 3], request: &Request, bin_hz: f64) -> AxisEstimate {
    let summaries = [0, 1, 2].map(|j| axes[j].summary());
    let estimate = rms_estimate_with(&summaries, request, |j| {
        let axis = &mut axes[j];
        Some(match axis.fit(request, bin_hz) {
            Some(f) => fit_rms(&f, &summaries[j]),
            None => {
                let n = axis.vibration.len() as f64;
                let s2 = axis.noise * axis.noise;
                let r2 = (axis.mean_square - s2).max(0.0);
                let r = r2.sqrt();
                let var_r2 = (4.0 * r2 * s2 + 2.0 * s2 * s2) / n + 2.0 * 2.63 * s2 * s2 / n;
                // Near zero the derivative of √ blows up; √(u(r²)) bounds u(r) there.
                let u_noise = if r > 0.0 {
                    (var_r2.sqrt() / (2.0 * r)).min(var_r2.sqrt().sqrt())
                } else {
                    var_r2.sqrt().sqrt()
                };
                let gain_like = if axis.mean_square > 0.0 {
                    axis.mean_abs / axis.mean_square.sqrt()
                } else {
                    1.0
                };
                (
                    r,
                    u_noise,
                    gain_like,
                    Method::Samples {
                        noise_mps2: axis.noise,
                        candidates: axis.vibration.len(),
                    },
                )
            }
        })
    });
    // Every axis has a value, and the first always runs: the estimate is there.
    estimate.unwrap_or(AxisEstimate {
        estimate: Estimate {
            value: 0.0,
            standard_uncertainty: 0.0,
        },
        axis: 0,
        method: Method::Samples {
            noise_mps2: 0.0,
            candidates: 0,
        },
    })
}

/// Peak and RMS of a window whose swaying axes are fitted already (the monitor's sway
/// tracker): the same estimates as [`window_stats`], from the axes' `summaries` and `fit(j)`,
/// which is asked only of axes that can reach a threshold or be the largest. None when such an
/// axis has no adequate fit, or a frequency is wanted: then [`window_stats`] decides.
pub fn stats_from_fits(
    summaries: &[AxisSummary; 3],
    n_samples: usize,
    request: &Request,
    mut fit: impl FnMut(usize) -> Option<SineFit>,
) -> Option<WindowStats> {
    let k = request.k;
    if request.frequency && n_samples >= MIN_FREQUENCY_SAMPLES {
        return None;
    }
    let wants_peak = request
        .peak_threshold
        .is_some_and(|t| summaries.iter().any(|a| a.peak_bound(k) >= t));
    let wants_rms = request
        .rms_threshold
        .is_some_and(|t| summaries.iter().any(|a| a.rms_bound(k) >= t));
    let peak = if wants_peak {
        Some(peak_estimate_with(summaries, request, |j| {
            fit(j).map(|f| fit_peak_interval(&f, k))
        })?)
    } else {
        None
    };
    let rms = if wants_rms {
        Some(rms_estimate_with(summaries, request, |j| {
            fit(j).map(|f| fit_rms(&f, &summaries[j]))
        })?)
    } else {
        None
    };
    Some(WindowStats {
        n_samples,
        vibration_rms_mps2: summaries
            .iter()
            .map(|a| a.mean_square.sqrt())
            .fold(0.0, f64::max),
        peak,
        rms,
        dominant_frequency: None,
    })
}

/// Where the sinusoid search of each axis of `points` converged (ω in rad per sample), for
/// axes whose fit there is adequate: the frequencies a sway tracker starts from.
pub fn sway_frequencies(points: &[Point], request: &Request) -> [Option<f64>; 3] {
    if points.len() < MIN_FREQUENCY_SAMPLES {
        return [None; 3];
    }
    let mut axes: [AxisData; 3] = [0, 1, 2].map(|j| AxisData::gather(points, j));
    let (_, bin_hz) = spectral_peaks(&mut axes, request.sample_rate_hz);
    [0, 1, 2].map(|j| {
        axes[j]
            .search(request, bin_hz)
            .and_then(|(omega, f)| f.map(|_| omega))
    })
}

/// Per-axis spectral peaks of the high-passed, Hann-tapered axes (stored in each axis), and the
/// frequency of the highest bin of their sum with the bin width.
fn spectral_peaks(axes: &mut [AxisData; 3], sample_rate_hz: f64) -> (f64, f64) {
    let n = axes[0].vibration.len();
    let m = n.next_power_of_two().max(2);
    let bin_hz = sample_rate_hz / m as f64;
    let mut summed = vec![0.0f64; m / 2 + 1];
    let mut buf = vec![(0.0f64, 0.0f64); m];
    for axis in axes.iter_mut() {
        for (i, slot) in buf.iter_mut().enumerate() {
            *slot = match axis.vibration.get(i) {
                Some(v) => {
                    // Hann taper: a window edge would otherwise smear power into every bin.
                    let w = 0.5
                        - 0.5
                            * (2.0 * std::f64::consts::PI * i as f64 / (n.max(2) - 1) as f64).cos();
                    (v * w, 0.0)
                }
                None => (0.0, 0.0),
            };
        }
        triax_client::spectrum::fft_in_place(&mut buf);
        let mut own = (0.0, -1.0);
        for (b, (p, &(re, im))) in summed.iter_mut().zip(&buf).enumerate() {
            let power = re * re + im * im;
            *p += power;
            if b > 0 && power > own.1 {
                own = (b as f64 * bin_hz, power);
            }
        }
        axis.spectral_peak = own;
    }
    let bin = (1..summed.len())
        .max_by(|&a, &b| summed[a].total_cmp(&summed[b]))
        .unwrap_or(1);
    (bin as f64 * bin_hz, bin_hz)
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_distr::{Distribution, Normal};

    const RATE: f64 = 100.0;
    const TAU: f64 = std::f64::consts::TAU;

    /// A window of `n` samples: x = `signal(t)`, z = gravity; the vibration is the signal
    /// itself (as if high-passed perfectly), every value with noise of deviation `sigma` and a
    /// stated u of `u`.
    fn window(
        n: u32,
        signal: impl Fn(f64) -> f64,
        sigma: f64,
        u: f32,
        rng: &mut rand::rngs::StdRng,
    ) -> Vec<Point> {
        let noise = Normal::new(0.0, sigma.max(1e-300)).expect("finite deviation");
        (0..n)
            .map(|i| {
                let t = f64::from(i) / RATE;
                let mut e = || if sigma > 0.0 { noise.sample(rng) } else { 0.0 };
                let v = [signal(t) + e(), e(), e()];
                Point {
                    index: i,
                    accel_mps2: [v[0] as f32 + 0.3, v[1] as f32, v[2] as f32 + 9.81],
                    vibration_mps2: v.map(|x| x as f32),
                    uncertainty_mps2: [u; 3],
                }
            })
            .collect()
    }

    fn request(n: u32, noise_share: f64) -> Request {
        Request {
            sample_rate_hz: RATE,
            grid_len: n,
            propagation: Propagation { noise_share },
            k: 2.0,
            peak_threshold: Some(0.0),
            rms_threshold: Some(0.0),
            frequency: true,
            highpass: None,
        }
    }

    /// Pure sines in white noise at the stated u, the limit at the true peak: in the windows
    /// where the single-sway tests reject the sine and the peak comes from the samples,
    /// `exceeded` (lower end above the truth) stays within 1 − Φ(k) plus sampling error, as on
    /// every other path. Minutes: `cargo test --release -p triax-alert -- --ignored
    /// peak_from_samples --nocapture` (TRIAX_MC_WINDOWS, default 200 000).
    #[test]
    #[ignore = "a Monte Carlo of minutes; BENCHMARKS.md and issue notes quote it"]
    fn peak_from_samples_keeps_its_false_alarm_rate() {
        let windows: usize = std::env::var("TRIAX_MC_WINDOWS")
            .ok()
            .and_then(|v| v.parse().ok())
            .unwrap_or(200_000);
        let mut rng = rand::rngs::StdRng::seed_from_u64(31);
        let (mut samples, mut samples_exceeded, mut sine, mut sine_exceeded) = (0, 0, 0, 0);
        for _ in 0..windows {
            let f = rng.gen_range(0.75..7.5);
            let phase = rng.gen_range(0.0..TAU);
            let sigma = [0.005, 0.02][rng.gen_range(0..2)];
            let w = window(
                400,
                |t| (TAU * f * t + phase).sin(),
                sigma,
                sigma as f32,
                &mut rng,
            );
            let mut r = request(400, 1.0);
            r.peak_threshold = Some(1.0);
            r.rms_threshold = None;
            r.frequency = false;
            let Some(p) = window_stats(&w, &r).and_then(|s| s.peak) else {
                continue;
            };
            let exceeded = p.estimate.value - 2.0 * p.estimate.standard_uncertainty > 1.0;
            match p.method {
                Method::Samples { .. } => {
                    samples += 1;
                    samples_exceeded += usize::from(exceeded);
                }
                Method::Sine { .. } => {
                    sine += 1;
                    sine_exceeded += usize::from(exceeded);
                }
            }
        }
        let rate = |e: usize, n: usize| e as f64 / n.max(1) as f64;
        println!(
            "from the samples: {samples_exceeded} exceeded of {samples} ({:.4}); sine fit: \
             {sine_exceeded} of {sine} ({:.4})",
            rate(samples_exceeded, samples),
            rate(sine_exceeded, sine)
        );
        // 1 − Φ(2) = 2.28 %, and three binomial standard deviations.
        let bound = |n: usize| 0.0228 + 3.0 * (0.0228 * 0.9772 / n.max(1) as f64).sqrt();
        assert!(rate(samples_exceeded, samples) <= bound(samples));
        assert!(rate(sine_exceeded, sine) <= bound(sine));
    }

    #[test]
    fn one_sway_is_fitted() {
        let mut rng = rand::rngs::StdRng::seed_from_u64(1);
        let w = window(1000, |t| 0.3 * (TAU * 2.5 * t).sin(), 0.0, 0.01, &mut rng);
        let s = window_stats(&w, &request(1000, 1.0)).expect("a window");
        let peak = s.peak.expect("wanted");
        assert_eq!(peak.axis, 0);
        assert!(matches!(peak.method, Method::Sine { .. }), "{peak:?}");
        // f32 storage of the samples leaves ~1e-8 of rounding.
        assert!((peak.estimate.value - 0.3).abs() < 1e-6, "{peak:?}");
        let rms = s.rms.expect("wanted");
        assert!(
            (rms.estimate.value - 0.3 / 2f64.sqrt()).abs() < 1e-6,
            "{rms:?}"
        );
        let f = s.dominant_frequency.expect("wanted");
        assert!((f.estimate.value - 2.5).abs() < 1e-6, "{f:?}");
        // All of u as calibration error: the peak carries the whole stated u.
        let s0 = window_stats(&w, &request(1000, 0.0)).expect("a window");
        let u0 = s0.peak.expect("wanted").estimate.standard_uncertainty;
        assert!((u0 - 0.01).abs() < 1e-4, "{u0}");
    }

    #[test]
    fn nothing_is_estimated_that_cannot_reach_its_threshold() {
        let mut rng = rand::rngs::StdRng::seed_from_u64(2);
        let w = window(400, |t| 0.1 * (TAU * 1.3 * t).sin(), 0.001, 0.001, &mut rng);
        let mut r = request(400, 1.0);
        r.peak_threshold = Some(1.0);
        r.rms_threshold = Some(1.0);
        r.frequency = false;
        let s = window_stats(&w, &r).expect("a window");
        assert!(s.peak.is_none() && s.rms.is_none() && s.dominant_frequency.is_none());
        assert!((s.vibration_rms_mps2 - 0.1 / 2f64.sqrt()).abs() < 2e-3);
        assert!(window_stats(&[], &r).is_none());
    }

    /// A crest between samples, at a frequency the fit does not speak for: the sample bound
    /// still holds the true peak, though every sample reads low.
    #[test]
    fn a_crest_between_samples_is_inside_the_bound() {
        let mut rng = rand::rngs::StdRng::seed_from_u64(3);
        // 30 Hz at 100 samples/s, crests half a sample off the grid.
        let w = window(
            400,
            |t| (TAU * 30.0 * (t + 0.005) + 0.25 * TAU).sin(),
            0.0,
            0.001,
            &mut rng,
        );
        let sampled = w
            .iter()
            .map(|p| f64::from(p.vibration_mps2[0]).abs())
            .fold(0.0, f64::max);
        assert!(sampled < 0.99, "{sampled}");
        let peak = window_stats(&w, &request(400, 1.0))
            .and_then(|s| s.peak)
            .expect("wanted");
        assert!(matches!(peak.method, Method::Samples { .. }), "{peak:?}");
        let (e, k) = (peak.estimate, 2.0);
        assert!(
            e.value - k * e.standard_uncertainty <= 1.0
                && 1.0 <= e.value + k * e.standard_uncertainty,
            "{e:?}"
        );
    }

    /// Two modes in white noise (not one sway): the sample bounds hold the true peak at least
    /// 95 % of the time and put it below the lower end at most 2.5 % of the time, and the RMS
    /// with the noise taken out covers the motion's RMS.
    #[test]
    fn broadband_bounds_cover() {
        let mut rng = rand::rngs::StdRng::seed_from_u64(4);
        let (mut trials, mut covered, mut below, mut rms_covered) = (0, 0, 0, 0);
        for _ in 0..1500 {
            let (p1, p2) = (rng.gen_range(0.0..TAU), rng.gen_range(0.0..TAU));
            let motion =
                move |t: f64| 0.8 * (TAU * 1.3 * t + p1).sin() + 0.3 * (TAU * 3.7 * t + p2).sin();
            let sigma = 0.02;
            let w = window(400, motion, sigma, sigma as f32, &mut rng);
            let s = window_stats(&w, &request(400, 1.0)).expect("a window");
            let peak = s.peak.expect("wanted");
            assert!(matches!(peak.method, Method::Samples { .. }), "{peak:?}");
            // The motion's true peak, between samples too.
            let truth = (0..40_000)
                .map(|i| motion(f64::from(i) / 10_000.0).abs())
                .fold(0.0, f64::max);
            let e = peak.estimate;
            let (lo, hi) = (
                e.value - 2.0 * e.standard_uncertainty,
                e.value + 2.0 * e.standard_uncertainty,
            );
            trials += 1;
            covered += usize::from(lo <= truth && truth <= hi);
            below += usize::from(lo > truth);
            let rms_truth = ((0..400)
                .map(|i| motion(f64::from(i) / RATE).powi(2))
                .sum::<f64>()
                / 400.0)
                .sqrt();
            let r = s.rms.expect("wanted").estimate;
            rms_covered += usize::from((r.value - rms_truth).abs() <= 2.0 * r.standard_uncertainty);
        }
        let share = |c: usize| c as f64 / trials as f64;
        assert!(share(covered) >= 0.95, "peak coverage {}", share(covered));
        assert!(
            share(below) <= 0.025,
            "truth below the interval {}",
            share(below)
        );
        assert!(
            (0.93..=0.985).contains(&share(rms_covered)),
            "RMS coverage {}",
            share(rms_covered)
        );
    }
}
