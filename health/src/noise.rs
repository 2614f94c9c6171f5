//! A channel's own noise, told apart from the building's motion.
//!
//! Motion only adds power, so every estimate of a channel's noise is an upper bound on it;
//! what matters is how tight the bound is while the building moves. Broadband ambient, machine
//! tones and transients reach every estimator of the raw stream (the second differences the
//! block sums keep pass 10–50 Hz almost whole), so the noise is read where the motion is not:
//!
//! 1. **Spectrum.** The second differences `V[i] − 2V[i−1] + V[i−2]` (which push a structure's
//!    low-frequency content far down, so that none leaks) are cut into segments of
//!    [`SEGMENT`] samples, Hann-windowed, and their periodogram taken at the [`BINS`] bins, every
//!    other one from an eighth of the sample rate to 0.44 of it (bins two apart are nearly
//!    independent under a Hann window). Each bin's power is divided by what white noise at the
//!    reference level gives there (the exact expectation through the second difference and the
//!    window), so that a healthy channel's normalised powers are unit exponentials.
//! 2. **Transients out.** A segment whose median normalised power exceeds [`LOUD`] is a
//!    transient (a door, a vehicle, a lift) and is left out, counted.
//! 3. **Time.** Over a window of [`WINDOW_SEGMENTS`] segments, each bin's level is the median
//!    over the window's kept segments: a transient the loudness test missed moves a median by
//!    one rank, not by its size.
//! 4. **Frequency.** The window's floor is the lowest bin level: motion in some bins (tones, a
//!    band-limited ambient, footfall harmonics) leaves it standing on the others. Its ratio to
//!    what white noise at the reference gives for the same count (`floor_ratio`, the median of
//!    the lowest of eleven medians, from the exact distribution of an exponential sample's
//!    median) is 1 for a healthy channel at the reference level, and exactly the variance ratio
//!    for a noisier one: the statistic is a scale family.
//! 5. **Support.** A sensor's own noise is white: it sets every bin the motion leaves alone at
//!    one level, within the scatter of a median of exponentials (a known log-variance). A floor
//!    that [`SUPPORT`] bins or more share, within [`SUPPORT_SIGMAS`] of that scatter, is the
//!    sensor's (tones and band-limited motion lift the other bins); a floor that fewer share is
//!    the motion's low point, the window is **masked**, and a high floor there says nothing.
//!    Motion white over the whole band at a level above the noise cannot be told from noise by
//!    one sensor: it is then read as noise, and what the noise test makes of it is held back
//!    by its confirmation (a finding must last `confirm_s`, through a night's quiet).
//!
//! A window is `fine` when its floor is at most [`NoiseDesign::high_ratio`] (whether flat or
//! not: the floor bounds the noise from above), `high` when above it and flat, `masked`
//! otherwise. [`crate::channel`] turns the windows into verdicts.
//!
//! Cost: per sample, one second difference and a store; per segment, 11 bins by 64 samples of
//! multiply-adds (22 a sample) and a sort of eleven; per window, eleven medians of at most 64
//! bytes. Memory: a segment of `f32` for the three channels (0.8 KB, sample-major, so that a
//! batch writes one run of it) and per channel a window of one byte per bin and segment (the
//! log power in sixteenths, 0.7 KB).

use std::f64::consts::PI;
use std::sync::LazyLock;

/// Second differences a segment holds.
pub const SEGMENT: usize = 64;
/// The bins judged: every other one from `SEGMENT/8` to `0.44·SEGMENT`.
pub const BINS: [usize; 11] = [8, 10, 12, 14, 16, 18, 20, 22, 24, 26, 28];
/// Segments a window takes.
pub const WINDOW_SEGMENTS: usize = 64;
/// A segment whose median normalised power exceeds this is a transient.
pub const LOUD: f64 = 16.0;
/// Fewest kept segments a window needs to be judged.
pub const MIN_KEPT: usize = WINDOW_SEGMENTS / 2;

/// Log-power quantisation: `q = round((ln r + LOG_OFFSET)·LOG_STEPS)`, clamped to a byte.
const LOG_OFFSET: f64 = 4.0;
const LOG_STEPS: f64 = 32.0;

/// The per-bin window of a Hann taper times the DFT's cosine and sine, and each bin's
/// expected power for unit white noise through the second difference.
struct Tables {
    /// In `f32`, summed in eight lanes: the sums vectorise, and a power estimate needs no
    /// more than single precision.
    cos: [[f32; SEGMENT]; BINS.len()],
    sin: [[f32; SEGMENT]; BINS.len()],
    white: [f64; BINS.len()],
    /// Per kept count `n` (index `n − MIN_KEPT`): the floor's median for white noise and the
    /// standard deviation of a bin level's logarithm.
    floor_median: Vec<f64>,
    bin_log_sd: Vec<f64>,
}

static TABLES: LazyLock<Tables> = LazyLock::new(|| {
    let hann = |n: usize| 0.5 - 0.5 * (2.0 * PI * (n as f64 + 0.5) / SEGMENT as f64).cos();
    let mut cos = [[0.0; SEGMENT]; BINS.len()];
    let mut sin = [[0.0; SEGMENT]; BINS.len()];
    let mut white = [0.0; BINS.len()];
    for (b, &k) in BINS.iter().enumerate() {
        let omega = 2.0 * PI * k as f64 / SEGMENT as f64;
        for n in 0..SEGMENT {
            cos[b][n] = (hann(n) * (omega * n as f64).cos()) as f32;
            sin[b][n] = (hann(n) * (omega * n as f64).sin()) as f32;
        }
        // E|Σ wₙdₙe^{−iωn}|² = Σₙ Σₘ wₙwₘ R(n − m) cos ω(n − m), R the second difference's
        // autocovariance for unit white noise: 6, −4, 1 at lags 0, 1, 2.
        let r = |lag: usize| match lag {
            0 => 6.0,
            1 => -4.0,
            2 => 1.0,
            _ => 0.0,
        };
        let mut e = 0.0;
        for n in 0..SEGMENT {
            for m in n.saturating_sub(2)..(n + 3).min(SEGMENT) {
                e += hann(n) * hann(m) * r(n.abs_diff(m)) * (omega * (n as f64 - m as f64)).cos();
            }
        }
        white[b] = e;
    }
    let counts = MIN_KEPT..=WINDOW_SEGMENTS;
    let floor_median = counts.clone().map(floor_median_for).collect();
    let bin_log_sd = counts.map(bin_log_sd_for).collect();
    Tables {
        cos,
        sin,
        white,
        floor_median,
        bin_log_sd,
    }
});

/// `P(X₍ⱼ₎ ≤ x)` for the `j`-th smallest of `n` unit exponentials: at least `j` of them below
/// `x`, a binomial tail with `p = 1 − e^{−x}`.
fn order_cdf(j: usize, n: usize, x: f64) -> f64 {
    let p = -(-x).exp_m1();
    let q = 1.0 - p;
    // Σ_{i<j} C(n,i) pⁱ qⁿ⁻ⁱ, in logs so that n = 64 keeps its precision.
    let mut below = 0.0;
    let mut log_c = 0.0;
    for i in 0..j {
        if i > 0 {
            log_c += ((n - i + 1) as f64).ln() - (i as f64).ln();
        }
        let log_term = log_c + i as f64 * p.ln() + (n - i) as f64 * q.ln();
        below += log_term.exp();
    }
    (1.0 - below).clamp(0.0, 1.0)
}

/// The `x` at which an increasing `cdf` reaches `target`, by bisection on a log scale.
fn quantile(target: f64, cdf: impl Fn(f64) -> f64) -> f64 {
    let (mut lo, mut hi) = (1e-6f64.ln(), 1e3f64.ln());
    for _ in 0..80 {
        let mid = 0.5 * (lo + hi);
        if cdf(mid.exp()) < target {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    (0.5 * (lo + hi)).exp()
}

/// The window median's rank among `n` kept segments (the lower median).
fn median_rank(n: usize) -> usize {
    n.div_ceil(2)
}

/// `P(the r-th lowest of m ≤ x)` for m independent variables of distribution `F(x) = f`: at
/// least `r` of them below, a binomial tail.
fn rank_cdf(r: usize, m: usize, f: f64) -> f64 {
    let f = f.clamp(0.0, 1.0);
    let mut below = 0.0;
    let mut c = 1.0;
    for i in 0..r {
        if i > 0 {
            c *= (m - i + 1) as f64 / i as f64;
        }
        below += c * f.powi(i as i32) * (1.0 - f).powi((m - i) as i32);
    }
    (1.0 - below).clamp(0.0, 1.0)
}

/// The median of the floor (the [`FLOOR_RANK`]-th lowest of eleven independent bin levels,
/// each the median of `n` unit exponentials).
fn floor_median_for(n: usize) -> f64 {
    let j = median_rank(n);
    quantile(0.5, |x| {
        rank_cdf(FLOOR_RANK, BINS.len(), order_cdf(j, n, x))
    })
}

/// The standard deviation of a bin level's logarithm, from its quantiles at ±1σ of a normal.
fn bin_log_sd_for(n: usize) -> f64 {
    let j = median_rank(n);
    let low = quantile(0.158_655_253_931_457, |x| order_cdf(j, n, x));
    let high = quantile(0.841_344_746_068_543, |x| order_cdf(j, n, x));
    0.5 * (high.ln() - low.ln())
}

/// The floor is this lowest of the bin levels (1: the lowest): the second, so that one bin
/// low by chance does not set it.
pub const FLOOR_RANK: usize = 2;

/// Bins that must share a floor, within [`SUPPORT_SIGMAS`] of a bin level's log spread above
/// the lowest, for it to be the sensor's.
pub const SUPPORT: usize = 4;
pub const SUPPORT_SIGMAS: f64 = 3.0;

/// The noise test's settings, derived once per sensor.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct NoiseDesign {
    /// Variance ratio to the reference above which a flat window is `high`: the geometric
    /// middle between 1 and the design ratio squared (the design ratio itself).
    pub high_ratio: f64,
    /// Consecutive `high` windows that make `watch`.
    pub watch_windows: u32,
    /// How long every judged window must have been `high` for `suspect`, ns.
    pub confirm_ns: i64,
}

/// What one window said.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum WindowState {
    /// The floor is at most the `high` ratio: the noise is no louder than that.
    Fine,
    /// The floor is above it and the bins agree: the channel is louder.
    High,
    /// The floor is above it and the bins disagree: motion, not noise.
    Masked,
    /// Too few quiet segments (transients most of the window).
    Loud,
}

/// A finished window.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct NoiseWindow {
    pub end_ns: i64,
    pub state: WindowState,
    /// The floor's variance ratio to the reference, and the standard deviation of its log.
    pub ratio: f64,
    pub log_sd: f64,
    /// Bins within [`SUPPORT_SIGMAS`] of the floor (11 for white noise, fewer under motion),
    /// and the kept segments.
    pub support: u32,
    pub kept: u32,
}

/// The three channels' segment being filled, sample by sample: what every sample touches,
/// laid out sample-major so that a batch writes one run of bytes.
#[derive(Debug, Clone)]
#[repr(C)]
pub struct Segmenter {
    len: u8,
    valid: u8,
    prev: [[f64; 3]; 2],
    /// The segment's second differences, per sample the three channels'.
    d2: [[f32; 3]; SEGMENT],
}

impl Default for Segmenter {
    fn default() -> Self {
        Segmenter {
            d2: [[0.0; 3]; SEGMENT],
            len: 0,
            valid: 0,
            prev: [[0.0; 3]; 2],
        }
    }
}

impl Segmenter {
    /// Bytes from the start that every sample may touch besides its own slot of `d2`.
    pub const HEAD_BYTES: usize = std::mem::offset_of!(Segmenter, d2);

    /// Forgets the samples before a break. A window's segments stay (each was whole).
    pub fn break_run(&mut self) {
        self.valid = 0;
        self.len = 0;
    }

    /// Where the next `samples` samples will write, as an offset from the start and a length:
    /// for a caller that loads a cold monitor ahead of a batch.
    pub fn next_slots(&self, samples: usize) -> (usize, usize) {
        let slot = std::mem::size_of::<[f32; 3]>();
        let at = Self::HEAD_BYTES + usize::from(self.len) * slot;
        (at, samples.min(SEGMENT - usize::from(self.len)) * slot)
    }

    /// One sample of the three outputs; true when it completed a segment (whose second
    /// differences [`Segmenter::channel`] gives until the next sample). A sample with a
    /// non-finite output breaks the run.
    #[inline(always)]
    pub fn push(&mut self, v: [f32; 3]) -> bool {
        let x = v.map(f64::from);
        if !x.iter().all(|x| x.is_finite()) {
            self.break_run();
            return false;
        }
        if self.valid < 2 {
            self.prev = [x, self.prev[0]];
            self.valid += 1;
            return false;
        }
        let p = self.prev;
        self.d2[usize::from(self.len)] = [0, 1, 2].map(|k| (x[k] - 2.0 * p[0][k] + p[1][k]) as f32);
        self.prev = [x, p[0]];
        self.len += 1;
        if usize::from(self.len) < SEGMENT {
            return false;
        }
        self.len = 0;
        true
    }

    /// Channel `k`'s second differences of the segment just completed.
    pub fn channel(&self, k: usize) -> [f32; SEGMENT] {
        std::array::from_fn(|n| self.d2[n][k])
    }
}

/// One channel's window of segments: touched once a segment.
#[derive(Debug, Clone)]
pub struct FloorWindow {
    /// Log powers, bin-major: `levels[b][s]` for kept segment `s`.
    levels: [[u8; WINDOW_SEGMENTS]; BINS.len()],
    kept: usize,
    segments: usize,
    /// 1/(σ²_ref · white power) per bin.
    inverse_reference: [f64; BINS.len()],
}

impl FloorWindow {
    /// A channel whose reference white-noise variance is `reference_var` (output unit²).
    pub fn new(reference_var: f64) -> FloorWindow {
        FloorWindow {
            levels: [[0; WINDOW_SEGMENTS]; BINS.len()],
            kept: 0,
            segments: 0,
            inverse_reference: TABLES.white.map(|w| 1.0 / (reference_var * w)),
        }
    }

    /// Takes a completed segment; returns the window it completed, ending at `end_ns`.
    pub fn segment(
        &mut self,
        d2: &[f32; SEGMENT],
        end_ns: i64,
        design: &NoiseDesign,
    ) -> Option<NoiseWindow> {
        let t = &*TABLES;
        let mut power = [0.0f64; BINS.len()];
        for (b, p) in power.iter_mut().enumerate() {
            let (re, im) = bin(&t.cos[b], &t.sin[b], d2);
            *p = (re * re + im * im) * self.inverse_reference[b];
        }
        self.segments += 1;
        let mut sorted = power;
        sorted.sort_unstable_by(f64::total_cmp);
        if sorted[BINS.len() / 2] <= LOUD {
            for (b, p) in power.iter().enumerate() {
                let q = ((p.max(1e-300).ln() + LOG_OFFSET) * LOG_STEPS).round();
                self.levels[b][self.kept] = q.clamp(0.0, 255.0) as u8;
            }
            self.kept += 1;
        }
        (self.segments == WINDOW_SEGMENTS).then(|| self.window(end_ns, design))
    }

    fn window(&mut self, end_ns: i64, design: &NoiseDesign) -> NoiseWindow {
        let kept = self.kept;
        self.kept = 0;
        self.segments = 0;
        if kept < MIN_KEPT {
            return NoiseWindow {
                end_ns,
                state: WindowState::Loud,
                ratio: f64::NAN,
                log_sd: f64::NAN,
                support: 0,
                kept: kept as u32,
            };
        }
        let t = &*TABLES;
        let j = median_rank(kept);
        let mut logs = [0.0f64; BINS.len()];
        for (b, level) in logs.iter_mut().enumerate() {
            let mut v = self.levels[b];
            let (_, nth, _) = v[..kept].select_nth_unstable(j - 1);
            *level = f64::from(*nth) / LOG_STEPS - LOG_OFFSET;
        }
        let mut sorted = logs;
        sorted.sort_unstable_by(f64::total_cmp);
        let floor = sorted[FLOOR_RANK - 1];
        let ratio = floor.exp() / t.floor_median[kept - MIN_KEPT];
        let sd = t.bin_log_sd[kept - MIN_KEPT];
        let support = logs
            .iter()
            .filter(|&&l| l <= floor + SUPPORT_SIGMAS * sd)
            .count();
        let state = if ratio <= design.high_ratio {
            WindowState::Fine
        } else if support >= SUPPORT {
            WindowState::High
        } else {
            WindowState::Masked
        };
        NoiseWindow {
            end_ns,
            state,
            ratio,
            // The floor is the second lowest of eleven: its spread is about 0.6 of one level's.
            log_sd: 0.6 * sd,
            support: support as u32,
            kept: kept as u32,
        }
    }
}

/// One channel's segmenter and window together, for a caller with one channel (a test).
#[derive(Debug, Clone)]
pub struct NoiseFloor {
    pub segmenter: Segmenter,
    pub window: FloorWindow,
}

impl NoiseFloor {
    pub fn new(reference_var: f64) -> NoiseFloor {
        NoiseFloor {
            segmenter: Segmenter::default(),
            window: FloorWindow::new(reference_var),
        }
    }

    /// One output; returns a window when this sample finished one, ending at `end_ns()`.
    pub fn push(
        &mut self,
        x: f64,
        end_ns: impl FnOnce() -> i64,
        design: &NoiseDesign,
    ) -> Option<NoiseWindow> {
        if self.segmenter.push([x as f32, 0.0, 0.0]) {
            self.window
                .segment(&self.segmenter.channel(0), end_ns(), design)
        } else {
            None
        }
    }
}

/// The Hann-windowed DFT of `d2` at one bin, from the bin's tables.
#[inline]
fn bin(cos: &[f32; SEGMENT], sin: &[f32; SEGMENT], d2: &[f32; SEGMENT]) -> (f64, f64) {
    const LANES: usize = 8;
    let (mut re, mut im) = ([0.0f32; LANES], [0.0f32; LANES]);
    for ((c, s), d) in cos
        .chunks_exact(LANES)
        .zip(sin.chunks_exact(LANES))
        .zip(d2.chunks_exact(LANES))
    {
        for l in 0..LANES {
            re[l] += c[l] * d[l];
            im[l] += s[l] * d[l];
        }
    }
    let sum = |x: [f32; LANES]| x.iter().map(|&v| f64::from(v)).sum::<f64>();
    (sum(re), sum(im))
}

/// The probability that a healthy channel at exactly the reference level gives a window above
/// `ratio` with all `WINDOW_SEGMENTS` segments kept: the design false rate of one window.
pub fn false_high_probability(ratio: f64) -> f64 {
    let n = WINDOW_SEGMENTS;
    let j = median_rank(n);
    let x = ratio * TABLES.floor_median[n - MIN_KEPT];
    1.0 - rank_cdf(FLOOR_RANK, BINS.len(), order_cdf(j, n, x))
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::rngs::SmallRng;
    use rand::{Rng, SeedableRng};
    use rand_distr::StandardNormal;

    fn design() -> NoiseDesign {
        NoiseDesign {
            high_ratio: 2.0,
            watch_windows: 2,
            confirm_ns: 0,
        }
    }

    /// The order statistic's distribution by hand: the smallest of n exponentials is
    /// exponential with rate n; the largest of two has `(1 − e^{−x})²`; the second lowest of
    /// three has `3f² − 2f³`.
    #[test]
    fn order_statistics_by_hand() {
        for f in [0.1, 0.5, 0.9] {
            assert!((rank_cdf(2, 3, f) - (3.0 * f * f - 2.0 * f * f * f)).abs() < 1e-12);
            assert!((rank_cdf(1, 11, f) - (1.0 - (1.0f64 - f).powi(11))).abs() < 1e-12);
        }
        for x in [0.01, 0.1, 0.5, 2.0] {
            assert!((order_cdf(1, 11, x) - (1.0 - (-11.0 * x).exp())).abs() < 1e-12);
            assert!((order_cdf(2, 2, x) - (1.0 - (-x).exp()).powi(2)).abs() < 1e-12);
        }
        // The median of one exponential is ln 2.
        assert!((quantile(0.5, |x| order_cdf(1, 1, x)) - 2f64.ln()).abs() < 1e-9);
    }

    /// The expected power of white noise through the second difference and the window, per
    /// bin, against the same thing measured on simulated noise.
    #[test]
    fn the_white_reference_is_what_white_noise_gives() {
        let mut rng = SmallRng::seed_from_u64(5);
        let mut d2 = [0.0f32; SEGMENT];
        let t = &*TABLES;
        let mut sums = [0.0; BINS.len()];
        let segments = 4000;
        let mut x = [0.0f64; SEGMENT + 2];
        for _ in 0..segments {
            for v in &mut x {
                *v = rng.sample(StandardNormal);
            }
            for (n, d) in d2.iter_mut().enumerate() {
                *d = (x[n + 2] - 2.0 * x[n + 1] + x[n]) as f32;
            }
            for (b, s) in sums.iter_mut().enumerate() {
                let (re, im) = bin(&t.cos[b], &t.sin[b], &d2);
                *s += re * re + im * im;
            }
        }
        for (b, s) in sums.iter().enumerate() {
            let measured = s / segments as f64;
            // An exponential's mean over 4000 has 1.6 % relative sd.
            assert!(
                (measured / t.white[b] - 1.0).abs() < 0.065,
                "bin {}: {measured} vs {}",
                BINS[b],
                t.white[b]
            );
        }
    }

    /// White noise at the reference: the floor's ratio has median 1 and the log spread the
    /// tables state; nearly every bin supports the floor; at four times the variance the ratio
    /// is 4.
    #[test]
    fn white_noise_gives_a_unit_floor_and_flat_bins() {
        let mut rng = SmallRng::seed_from_u64(11);
        let windows = |sigma: f64, count: usize, rng: &mut SmallRng| {
            let mut floor = NoiseFloor::new(1.0);
            let mut out = Vec::new();
            while out.len() < count {
                let x: f64 = rng.sample::<f64, _>(StandardNormal) * sigma;
                if let Some(w) = floor.push(x, || 0, &design()) {
                    out.push(w);
                }
            }
            out
        };
        let w = windows(1.0, 600, &mut rng);
        let mut logs: Vec<f64> = w.iter().map(|w| w.ratio.ln()).collect();
        logs.sort_by(f64::total_cmp);
        let median = logs[logs.len() / 2];
        assert!(median.abs() < 0.05, "median log ratio {median}");
        let spread = 0.5 * (logs[(0.841 * 600.0) as usize] - logs[(0.159 * 600.0) as usize]);
        let stated = w[0].log_sd;
        assert!(
            (spread / stated - 1.0).abs() < 0.25,
            "log spread {spread} vs stated {stated}"
        );
        let unsupported = w.iter().filter(|w| (w.support as usize) < SUPPORT).count();
        assert_eq!(unsupported, 0);
        let mean_support = w.iter().map(|w| f64::from(w.support)).sum::<f64>() / 600.0;
        assert!(mean_support > 9.0, "{mean_support}");
        assert!(w.iter().all(|w| w.state == WindowState::Fine));
        let loud = windows(2.0, 100, &mut rng);
        let mut logs: Vec<f64> = loud.iter().map(|w| w.ratio.ln()).collect();
        logs.sort_by(f64::total_cmp);
        assert!((logs[50] - 4f64.ln()).abs() < 0.08, "{}", logs[50].exp());
        let high = loud.iter().filter(|w| w.state == WindowState::High).count();
        assert!(high >= 98, "{high} of 100 high");
        assert!(
            false_high_probability(2.0) < 1e-10,
            "{}",
            false_high_probability(2.0)
        );
    }

    /// A loud tone leaves the floor where the noise is; a burst of transients is left out by
    /// segment; a motion whose spectrum falls steeply across the band, above the noise in
    /// every bin, has no floor enough bins share: masked.
    #[test]
    fn tones_bands_and_transients_leave_the_floor_alone() {
        let mut rng = SmallRng::seed_from_u64(12);
        let mut floor = NoiseFloor::new(1.0);
        let mut windows = Vec::new();
        let mut i = 0u64;
        while windows.len() < 50 {
            let t = i as f64;
            let mut x: f64 = rng.sample(StandardNormal);
            // A tone at 0.3 of the sample rate, 30 times the noise's amplitude.
            x += 30.0 * (2.0 * PI * 0.3 * t).sin();
            // A burst of 30 σ for 200 samples in every 4096.
            if i % 4096 < 200 {
                x += 30.0 * rng.sample::<f64, _>(StandardNormal);
            }
            i += 1;
            if let Some(w) = floor.push(x, || 0, &design()) {
                windows.push(w);
            }
        }
        let mut logs: Vec<f64> = windows.iter().map(|w| w.ratio.ln()).collect();
        logs.sort_by(f64::total_cmp);
        assert!(logs[25].abs() < 0.15, "median floor {}", logs[25].exp());
        assert!(windows.iter().all(|w| w.state == WindowState::Fine));
        assert!(windows.iter().all(|w| w.kept < WINDOW_SEGMENTS as u32));
        // A tone on every judged bin, its power over the noise's given per bin: the lowest two
        // bins at 2 and 5 times the noise, the others at 11 and 14: the floor (the second
        // lowest, 6 in all) is above the high ratio, the median under LOUD, and only two bins
        // lie within three spreads of the floor: masked. With the noise doubled and the same
        // tones on half the bins, the other bins share the floor: high.
        let tones = |excess: [f64; BINS.len()], sigma: f64, rng: &mut SmallRng| {
            let t = &*TABLES;
            let hann_sum: f64 = (0..SEGMENT)
                .map(|n| 0.5 - 0.5 * (2.0 * PI * (n as f64 + 0.5) / SEGMENT as f64).cos())
                .sum();
            let amplitude: Vec<f64> = BINS
                .iter()
                .enumerate()
                .map(|(b, &k)| {
                    let f = k as f64 / SEGMENT as f64;
                    let d2 = (4.0 * t.white[b] * excess[b]).sqrt() / hann_sum;
                    d2 / (4.0 * (PI * f).sin().powi(2))
                })
                .collect();
            let mut floor = NoiseFloor::new(1.0);
            let mut states = Vec::new();
            let mut i = 0u64;
            while states.len() < 20 {
                let mut x: f64 = sigma * rng.sample::<f64, _>(StandardNormal);
                for (b, &k) in BINS.iter().enumerate() {
                    let f = k as f64 / SEGMENT as f64;
                    x += amplitude[b] * (2.0 * PI * f * i as f64 + b as f64).sin();
                }
                i += 1;
                if let Some(w) = floor.push(x, || 0, &design()) {
                    states.push(w.state);
                }
            }
            states
        };
        let sloped = [
            2.0, 5.0, 11.0, 14.0, 14.0, 14.0, 14.0, 14.0, 14.0, 14.0, 14.0,
        ];
        let masked = tones(sloped, 1.0, &mut rng)
            .iter()
            .filter(|s| **s == WindowState::Masked)
            .count();
        let half = [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 20.0, 20.0, 20.0, 20.0, 20.0];
        let high = tones(half, 2.0, &mut rng)
            .iter()
            .filter(|s| **s == WindowState::High)
            .count();
        assert!(high >= 19, "{high} of 20 high");
        assert!(masked >= 19, "{masked} of 20 masked");
    }
}
