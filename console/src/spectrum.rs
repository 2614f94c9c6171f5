//! Power spectral density per axis (Welch) with its confidence band, for the spectrum view.
//!
//! The structure's modes are peaks in the spectrum of its vibration. Welch's method: the span is
//! cut into segments of `n` samples (a power of two) overlapping by half, each with its mean
//! removed and a Hann window applied; the one-sided periodograms `2·|X(f)|²/(fs·Σw²)` (DC and
//! Nyquist not doubled) are averaged. Segments never straddle a break in the stream (a jump in
//! time or in sample rate): each run of contiguous samples gives its own segments.
//!
//! **The band.** An average of K periodograms is taken as χ²-distributed with ν = 2K degrees of
//! freedom, so the true PSD lies in [ν·P/χ²(ν, 0.975), ν·P/χ²(ν, 0.025)] with 95 % probability.
//! The χ² quantiles are Wilson and Hilferty's (within 1 % of the exact ones for ν ≥ 10). Half
//! overlap with a Hann window makes neighbouring segments slightly correlated, so the band is a
//! little narrow (the equivalent ν is about 0.9·2K for many segments): read it as indicative.
//! The band says how well the average pins the spectrum of this stretch of motion, not the
//! calibration's uncertainty of the amplitudes, which scales every bin alike.

use serde::Serialize;
use triax_client::normal::quantile;
use triax_client::spectrum::fft_in_place;
use triax_protocol::batch::CorrectedBatch;

/// Most samples the spectrum keeps (an hour at about 280 Hz).
pub const MAX_SAMPLES: usize = 1_000_000;
/// Longest segment.
pub const MAX_SEGMENT: usize = 16_384;
/// Shortest segment.
pub const MIN_SEGMENT: usize = 64;
/// Longest segment of a spectrogram: 513 frequencies per column keeps its answer within a
/// few hundred kilobytes at the most columns.
pub const MAX_SPECTROGRAM_SEGMENT: usize = 1024;
/// Columns of a spectrogram when not asked, and the most.
pub const DEFAULT_COLUMNS: usize = 200;
pub const MAX_COLUMNS: usize = 1000;

/// Why no spectrum.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum SpectrumError {
    #[error("no run of {need} contiguous samples in the span (the longest has {longest})")]
    TooShort { need: usize, longest: usize },
    #[error("segment of {0} samples: must be a power of two from {MIN_SEGMENT} to {MAX_SEGMENT}")]
    Segment(usize),
    #[error("segment of {0} samples: must be a power of two from {MIN_SEGMENT} to {MAX_SPECTROGRAM_SEGMENT}")]
    SpectrogramSegment(usize),
}

/// The spectrum of one axis.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct AxisSpectrum {
    /// Per frequency, (m/s²)²/Hz.
    pub psd: Vec<f64>,
    pub lo: Vec<f64>,
    pub hi: Vec<f64>,
    /// The frequency of the largest PSD above the lowest bins (the mean's leakage), Hz.
    pub peak_hz: Option<f64>,
}

/// The answer of `/api/spectrum`.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Spectrum {
    pub sample_rate_hz: f64,
    pub segment_samples: usize,
    pub segments: usize,
    /// ν = 2·segments.
    pub degrees_of_freedom: usize,
    pub coverage: f64,
    pub resolution_hz: f64,
    pub samples_used: usize,
    pub frequencies_hz: Vec<f64>,
    /// x, y, z.
    pub axes: Vec<AxisSpectrum>,
    pub unit: &'static str,
}

/// Collects the samples of a span as runs of contiguous samples.
#[derive(Debug, Default)]
pub struct Collector {
    from_ns: i64,
    to_ns: i64,
    runs: Vec<Run>,
    samples: usize,
}

#[derive(Debug)]
struct Run {
    rate_hz: f64,
    /// Time of the run's first sample.
    start_ns: f64,
    next_ns: f64,
    values: [Vec<f32>; 3],
}

impl Collector {
    pub fn new(from_ns: i64, to_ns: i64) -> Collector {
        Collector {
            from_ns,
            to_ns,
            ..Collector::default()
        }
    }

    pub fn push(&mut self, batch: &CorrectedBatch) {
        let h = &batch.header;
        let period_ns = 1e9 / h.sample_rate_hz;
        for (i, s) in batch.samples.iter().enumerate() {
            if self.samples >= MAX_SAMPLES {
                return;
            }
            let t = h.timestamp_ns as f64 + i as f64 * period_ns;
            if t < self.from_ns as f64 || t >= self.to_ns as f64 {
                continue;
            }
            if !s.accel_mps2.iter().all(|a| a.is_finite()) {
                // A hole: the run ends here.
                if let Some(r) = self.runs.last_mut() {
                    r.next_ns = f64::NEG_INFINITY;
                }
                continue;
            }
            let continues = self.runs.last().is_some_and(|r| {
                r.rate_hz == h.sample_rate_hz && (t - r.next_ns).abs() <= 0.5 * period_ns
            });
            if !continues {
                self.runs.push(Run {
                    rate_hz: h.sample_rate_hz,
                    start_ns: t,
                    next_ns: t,
                    values: Default::default(),
                });
            }
            if let Some(r) = self.runs.last_mut() {
                for axis in 0..3 {
                    r.values[axis].push(s.accel_mps2[axis]);
                }
                r.next_ns = t + period_ns;
            }
            self.samples += 1;
        }
    }

    /// The runs of contiguous samples gathered, in time order: each its sample rate, the time
    /// of its first sample (ns) and its values per axis.
    pub fn runs(&self) -> impl Iterator<Item = (f64, f64, &[Vec<f32>; 3])> {
        self.runs.iter().map(|r| (r.rate_hz, r.start_ns, &r.values))
    }

    /// Welch's estimate with segments of `segment` samples (None: the longest power of two
    /// that gives at least 8 segments over the longest run, within the limits), at the most
    /// common sample rate.
    pub fn finish(self, segment: Option<usize>) -> Result<Spectrum, SpectrumError> {
        if let Some(n) = segment {
            if !n.is_power_of_two() || !(MIN_SEGMENT..=MAX_SEGMENT).contains(&n) {
                return Err(SpectrumError::Segment(n));
            }
        }
        let Some((fs, runs)) = self.main_rate() else {
            return Err(SpectrumError::TooShort {
                need: segment.unwrap_or(MIN_SEGMENT),
                longest: 0,
            });
        };
        let longest = runs.iter().map(|r| r.values[0].len()).max().unwrap_or(0);
        let n = match segment {
            Some(n) => n,
            None => {
                // 4.5 segment lengths hold 8 half-overlapping segments.
                let fit = (longest as f64 / 4.5) as usize;
                let p = if fit == 0 { 0 } else { 1usize << fit.ilog2() };
                p.clamp(MIN_SEGMENT, MAX_SEGMENT)
            }
        };
        if longest < n {
            return Err(SpectrumError::TooShort { need: n, longest });
        }
        let window = hann(n);
        let bins = n / 2 + 1;
        let mut sums = vec![vec![0f64; bins]; 3];
        let mut segments = 0;
        let mut buf = vec![(0f64, 0f64); n];
        for r in &runs {
            let len = r.values[0].len();
            let mut start = 0;
            while start + n <= len {
                for (axis, sum) in sums.iter_mut().enumerate() {
                    let seg = &r.values[axis][start..start + n];
                    add_periodogram(seg, &window, fs, &mut buf, sum);
                }
                segments += 1;
                start += n / 2;
            }
        }
        let dof = 2 * segments;
        let (q_lo, q_hi) = (
            chi2_quantile(dof as f64, 0.025),
            chi2_quantile(dof as f64, 0.975),
        );
        let frequencies_hz: Vec<f64> = (0..bins).map(|k| k as f64 * fs / n as f64).collect();
        let axes = sums
            .into_iter()
            .map(|sum| {
                let psd: Vec<f64> = sum.iter().map(|s| s / segments as f64).collect();
                let lo = psd.iter().map(|p| dof as f64 * p / q_hi).collect();
                let hi = psd.iter().map(|p| dof as f64 * p / q_lo).collect();
                // Bins 0 and 1 carry what is left of the segment's mean through the window.
                let peak_hz = psd
                    .iter()
                    .enumerate()
                    .skip(2)
                    .max_by(|a, b| a.1.total_cmp(b.1))
                    .filter(|(_, p)| **p > 0.0)
                    .map(|(k, _)| frequencies_hz[k]);
                AxisSpectrum {
                    psd,
                    lo,
                    hi,
                    peak_hz,
                }
            })
            .collect();
        Ok(Spectrum {
            sample_rate_hz: fs,
            segment_samples: n,
            segments,
            degrees_of_freedom: dof,
            coverage: 0.95,
            resolution_hz: fs / n as f64,
            samples_used: runs.iter().map(|r| r.values[0].len()).sum(),
            frequencies_hz,
            axes,
            unit: "(m/s²)²/Hz",
        })
    }
}

impl Collector {
    /// The rate with the most samples, and the runs at it.
    fn main_rate(&self) -> Option<(f64, Vec<&Run>)> {
        let mut rates: Vec<(f64, usize)> = Vec::new();
        for r in &self.runs {
            match rates.iter_mut().find(|(f, _)| *f == r.rate_hz) {
                Some((_, n)) => *n += r.values[0].len(),
                None => rates.push((r.rate_hz, r.values[0].len())),
            }
        }
        let &(fs, _) = rates.iter().max_by_key(|(_, n)| *n)?;
        Some((fs, self.runs.iter().filter(|r| r.rate_hz == fs).collect()))
    }

    /// A spectrogram of one axis (0 = x, 1 = y, 2 = z) over `[from_ns, to_ns)` in about
    /// `columns` columns of time: per column, the Welch average of the half-overlapping
    /// segments whose middle falls in it. The segment (None: the longest power of two that
    /// fits a column, so that every column of unbroken stream has a segment) is from
    /// [`MIN_SEGMENT`] to [`MAX_SPECTROGRAM_SEGMENT`]; a column is never shorter than
    /// [`MIN_SEGMENT`] samples, so a short span has fewer columns.
    pub fn spectrogram(
        self,
        axis: usize,
        segment: Option<usize>,
        columns: usize,
    ) -> Result<Spectrogram, SpectrumError> {
        if let Some(n) = segment {
            if !n.is_power_of_two() || !(MIN_SEGMENT..=MAX_SPECTROGRAM_SEGMENT).contains(&n) {
                return Err(SpectrumError::SpectrogramSegment(n));
            }
        }
        let Some((fs, runs)) = self.main_rate() else {
            return Err(SpectrumError::TooShort {
                need: segment.unwrap_or(MIN_SEGMENT),
                longest: 0,
            });
        };
        let span_ns = (self.to_ns - self.from_ns).max(1);
        let shortest_column_ns = (MIN_SEGMENT as f64 * 1e9 / fs).ceil() as i64;
        let column_ns = (span_ns / columns.max(1) as i64).max(shortest_column_ns);
        let columns = usize::try_from((span_ns + column_ns - 1) / column_ns).unwrap_or(1);
        let n = match segment {
            Some(n) => n,
            None => {
                let fit = (column_ns as f64 * fs / 1e9) as usize;
                (1usize << fit.max(1).ilog2()).clamp(MIN_SEGMENT, MAX_SPECTROGRAM_SEGMENT)
            }
        };
        let longest = runs.iter().map(|r| r.values[0].len()).max().unwrap_or(0);
        if longest < n {
            return Err(SpectrumError::TooShort { need: n, longest });
        }
        let window = hann(n);
        let bins = n / 2 + 1;
        let mut sums = vec![vec![0f64; bins]; columns];
        let mut counts = vec![0usize; columns];
        let mut buf = vec![(0f64, 0f64); n];
        let period_ns = 1e9 / fs;
        for r in &runs {
            let values = &r.values[axis.min(2)];
            let mut start = 0;
            while start + n <= values.len() {
                let middle_ns = r.start_ns + (start as f64 + n as f64 / 2.0) * period_ns;
                let c = ((middle_ns - self.from_ns as f64) / column_ns as f64).floor();
                if c >= 0.0 && (c as usize) < columns {
                    let c = c as usize;
                    add_periodogram(
                        &values[start..start + n],
                        &window,
                        fs,
                        &mut buf,
                        &mut sums[c],
                    );
                    counts[c] += 1;
                }
                start += n / 2;
            }
        }
        let frequencies_hz: Vec<f64> = (0..bins).map(|k| k as f64 * fs / n as f64).collect();
        // The mean over columns finds a tone that lasts, not one loud instant.
        let mut mean = vec![0f64; bins];
        let filled = counts.iter().filter(|c| **c > 0).count().max(1) as f64;
        let db = sums
            .iter()
            .zip(&counts)
            .map(|(sum, &count)| {
                (count > 0).then(|| {
                    sum.iter()
                        .zip(mean.iter_mut())
                        .map(|(s, m)| {
                            let psd = s / count as f64;
                            *m += psd / filled;
                            // A tenth of a decibel is finer than any colour map shows.
                            ((10.0 * psd.max(1e-30).log10()) * 10.0).round() as f32 / 10.0
                        })
                        .collect()
                })
            })
            .collect();
        let peak_hz = mean
            .iter()
            .enumerate()
            .skip(2)
            .max_by(|a, b| a.1.total_cmp(b.1))
            .filter(|(_, p)| **p > 0.0)
            .map(|(k, _)| frequencies_hz[k]);
        Ok(Spectrogram {
            axis: ["x", "y", "z"][axis.min(2)],
            sample_rate_hz: fs,
            segment_samples: n,
            resolution_hz: fs / n as f64,
            from_ns: self.from_ns,
            to_ns: self.to_ns,
            column_ns,
            frequencies_hz,
            segments: counts,
            psd_db: db,
            peak_hz,
            unit: "dB re 1 (m/s²)²/Hz",
        })
    }
}

/// The answer of `/api/spectrogram`: one axis's PSD per column of time.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Spectrogram {
    pub axis: &'static str,
    pub sample_rate_hz: f64,
    pub segment_samples: usize,
    pub resolution_hz: f64,
    pub from_ns: i64,
    pub to_ns: i64,
    /// Column `i` covers `[from_ns + i·column_ns, from_ns + (i+1)·column_ns)`.
    pub column_ns: i64,
    pub frequencies_hz: Vec<f64>,
    /// Segments averaged per column.
    pub segments: Vec<usize>,
    /// Per column, per frequency, 10·log10(PSD / 1 (m/s²)²/Hz) to 0.1 dB; null where no
    /// segment fell (a break in the stream).
    pub psd_db: Vec<Option<Vec<f32>>>,
    /// The frequency of the largest PSD averaged over the columns, above the lowest two bins.
    pub peak_hz: Option<f64>,
    pub unit: &'static str,
}

/// The Hann window of `n` samples (periodic, as Welch's segments want).
fn hann(n: usize) -> Vec<f64> {
    (0..n)
        .map(|i| 0.5 - 0.5 * (2.0 * std::f64::consts::PI * i as f64 / n as f64).cos())
        .collect()
}

/// Adds the one-sided periodogram `2·|X(f)|²/(fs·Σw²)` of `seg` (its mean removed, windowed)
/// to `sum`; DC and Nyquist are not doubled, having no negative twin.
fn add_periodogram(seg: &[f32], window: &[f64], fs: f64, buf: &mut [(f64, f64)], sum: &mut [f64]) {
    let n = seg.len();
    let w2: f64 = window.iter().map(|w| w * w).sum();
    let mean = seg.iter().map(|x| f64::from(*x)).sum::<f64>() / n as f64;
    for i in 0..n {
        buf[i] = ((f64::from(seg[i]) - mean) * window[i], 0.0);
    }
    fft_in_place(buf);
    for (k, s) in sum.iter_mut().enumerate() {
        let (re, im) = buf[k];
        let p = re * re + im * im;
        let one_sided = if k == 0 || k == n / 2 { 1.0 } else { 2.0 };
        *s += one_sided * p / (fs * w2);
    }
}

/// The p-quantile of χ² with ν degrees of freedom (Wilson–Hilferty).
pub fn chi2_quantile(nu: f64, p: f64) -> f64 {
    let z = quantile(p);
    let a = 2.0 / (9.0 * nu);
    (nu * (1.0 - a + z * a.sqrt()).powi(3)).max(f64::MIN_POSITIVE)
}

#[cfg(test)]
mod tests {
    use super::*;
    use triax_protocol::batch::CorrectedSample;
    use triax_protocol::SensorId;

    const T0: i64 = 1_800_000_000_000_000_000;

    fn batches(seconds: usize, x: impl Fn(f64) -> f64) -> Vec<CorrectedBatch> {
        (0..seconds * 2)
            .map(|b| {
                triax_protocol::batch::sample::dynamic(
                    SensorId::new("s").unwrap(),
                    b as u64,
                    T0 + b as i64 * 500_000_000,
                    100.0,
                    (0..50)
                        .map(|i| CorrectedSample {
                            accel_mps2: [x((b * 50 + i) as f64 / 100.0) as f32, 0.0, 9.8],
                            uncertainty_mps2: [0.01; 3],
                            flags: 0,
                        })
                        .collect(),
                )
            })
            .collect()
    }

    #[test]
    fn chi_square_quantiles() {
        // Tables: χ²(20; 0.025) = 9.591, χ²(20; 0.975) = 34.170.
        assert!((chi2_quantile(20.0, 0.025) - 9.591).abs() < 0.05);
        assert!((chi2_quantile(20.0, 0.975) - 34.170).abs() < 0.05);
        assert!((quantile(0.975) - 1.959964).abs() < 1e-6);
    }

    #[test]
    fn a_sine_peaks_at_its_frequency_and_its_power_adds_up() {
        // 0.2·sin(2π·3.125 t): variance 0.02, on a bin with 1024-sample segments at 100 Hz.
        let mut c = Collector::new(T0, T0 + 120_000_000_000);
        for b in batches(120, |t| {
            0.2 * (2.0 * std::f64::consts::PI * 3.125 * t).sin()
        }) {
            c.push(&b);
        }
        let s = c.finish(Some(1024)).unwrap();
        assert_eq!(s.segment_samples, 1024);
        assert_eq!(s.segments, (12_000 - 1024) / 512 + 1);
        assert_eq!(s.degrees_of_freedom, 2 * s.segments);
        assert_eq!(s.axes[0].peak_hz, Some(3.125));
        // Parseval: the PSD integrates to the variance.
        let power: f64 = s.axes[0].psd.iter().sum::<f64>() * s.resolution_hz;
        assert!((power - 0.02).abs() < 0.001, "{power}");
        let k = (3.125 / s.resolution_hz) as usize;
        assert!(s.axes[0].lo[k] < s.axes[0].psd[k] && s.axes[0].psd[k] < s.axes[0].hi[k]);
        assert!(
            s.axes[2].psd.iter().all(|p| *p < 1e-20),
            "gravity is the mean"
        );
    }

    #[test]
    fn segments_do_not_cross_a_gap_and_bad_requests_are_named() {
        let mut all = batches(30, |t| t.sin());
        // A 5 s hole in the middle: two runs of 15 s and 10 s.
        all.drain(30..40);
        let mut c = Collector::new(T0, T0 + 30_000_000_000);
        for b in &all {
            c.push(b);
        }
        let s = c.finish(Some(512)).unwrap();
        assert_eq!(s.segments, (1500 - 512) / 256 + 1 + (1000 - 512) / 256 + 1);
        let c = Collector::new(T0, T0 + 1);
        assert!(matches!(
            c.finish(None),
            Err(SpectrumError::TooShort { .. })
        ));
        let c = Collector::new(T0, T0 + 1);
        assert_eq!(c.finish(Some(1000)), Err(SpectrumError::Segment(1000)));
    }

    #[test]
    fn a_spectrogram_follows_a_tone_that_changes() {
        // 3.125 Hz for the first minute, 6.25 Hz for the second.
        let tone = |t: f64| {
            let f = if t < 60.0 { 3.125 } else { 6.25 };
            0.1 * (2.0 * std::f64::consts::PI * f * t).sin()
        };
        let mut c = Collector::new(T0, T0 + 120_000_000_000);
        for b in batches(120, tone) {
            c.push(&b);
        }
        let g = c.spectrogram(0, None, 60).unwrap();
        assert_eq!(g.column_ns, 2_000_000_000);
        assert_eq!(g.psd_db.len(), 60);
        assert_eq!(
            g.segment_samples, 128,
            "the longest power of two in 200 samples"
        );
        let peak = |col: &[f32]| {
            let k = (2..col.len())
                .max_by(|a, b| col[*a].total_cmp(&col[*b]))
                .unwrap();
            g.frequencies_hz[k]
        };
        let early = g.psd_db[10].as_deref().unwrap();
        let late = g.psd_db[50].as_deref().unwrap();
        assert!(
            (peak(early) - 3.125).abs() <= g.resolution_hz,
            "{}",
            peak(early)
        );
        assert!(
            (peak(late) - 6.25).abs() <= g.resolution_hz,
            "{}",
            peak(late)
        );
        assert!(g.segments.iter().all(|n| *n >= 1), "{:?}", g.segments);
        assert_eq!(
            Collector::new(T0, T0 + 1).spectrogram(0, Some(2048), 10),
            Err(SpectrumError::SpectrogramSegment(2048))
        );
    }
}
