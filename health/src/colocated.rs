//! Co-located sensors: each axis's gain ratio from the ambient vibration, which reaches the
//! horizontal axes that gravity cannot.
//!
//! Two sensors on the same part of a structure see the same motion at low frequency. With
//! `x` sensor A's corrected reading along one of its axes and `y` sensor B's along the same
//! direction (B's readings turned into A's frame by the declared mounting `R`, `y = (R·a_B)_i`),
//! the frequency response between them in a band is B's gain relative to A's. Per segment of
//! `segment_s`, Hann-windowed, the DFT at the band's bins (Goertzel's recurrence, referred to a
//! common time grid so that the two nodes' sampling phases do not matter) gives the auto- and
//! cross-spectra; over `estimate_s` of segments the ratio is (Bendat & Piersol's H₁, its
//! denominator less the record's white noise, which would bias it low by `N/S`):
//!
//! ```text
//! r = Re Σ G_xy / (Σ G_xx − N_x),   γ² = |Σ G_xy|² / (Σ G_xx · Σ G_yy)
//! u(r)/r = √(1 − γ²) / (|γ|·√(2·n_d))       (Bendat & Piersol, eq. 9.73)
//! ```
//!
//! with `n_d` the independent averages: segments times bins over 1.5 (a Hann window's
//! equivalent noise bandwidth, in bins). That count takes segments and bins as independent,
//! which a lightly damped mode is not (it rings for longer than a segment, in less than a bin):
//! at 2 % damping the formula alone came out 25 % low against the estimates' spread. So the
//! uncertainty is the larger of it and a delete-one jackknife over twenty sub-spans of the
//! estimate (ν = 19 when the jackknife rules). The record's noise, taken out of the
//! denominator, is an estimate with the record's ν: its uncertainty is added. Bins enter an
//! estimate where the previous estimate showed motion at least as strong as the noise (all bins
//! at first): a noise-only bin adds to the denominator's noise and to its uncertainty, nothing
//! to the ratio, and choosing on earlier data keeps the choice independent of this estimate's
//! noise. The real part, because co-located readings are
//! in phase: the sensors' time stamps must agree to better than a millisecond (a 1 ms offset
//! costs 0.05 % at 5 Hz).
//!
//! **Absolute:** `r − 1` against `√(u(r)² + u²_A + u²_B)`, `u_A` and `u_B` the relative gain
//! uncertainties of the two records' dynamic sets along the axis (`−dᵀ·S⁻¹·δS·d` for unit
//! motion along `d`, from each record's 12×12 covariance), `watch` and `suspect` beyond
//! Student's t at the absolute probabilities and the Welch–Satterthwaite ν.
//! **Relative:** after `baseline_s` of estimates, the baseline (their weighted mean) holds both
//! calibrations' errors, which then cancel; each later estimate's `d = r − r₀` feeds a
//! two-sided CUSUM designed for `shift` (a relative gain change), as in [`crate::cusum`].
//!
//! Cost: per sample of each sensor, a window value and two multiply-adds per bin and axis
//! (63 bins·axes for the default 1–5 Hz band in 5 s segments: about 130 operations), no
//! allocation; the buffers are made once.

use nalgebra::{Complex, Matrix3, Vector3};
use triax_calibration::corrector::{Corrector, SetCorrector};
use triax_calibration::student::{welch_satterthwaite, MAX_DOF};
use triax_protocol::record::{CalibrationRecord, SetKind};

use crate::config::HealthError;
use crate::cusum::{Sequential, Thresholds, Verdict};
use crate::gravity_check::Looks;
use crate::report::{TestReport, Unjudged};

/// Completed segments a sensor may hold while the other catches up.
const PENDING: usize = 8;

/// Sub-spans of an estimate for its jackknife.
const JACKKNIFE: usize = 20;

/// A pair's settings.
#[derive(Debug, Clone, PartialEq)]
pub struct PairConfig {
    /// Band the ratio is estimated in, Hz: the structure's modes, where the motion stands well
    /// above the sensors' noise.
    pub band_hz: [f64; 2],
    pub segment_s: f64,
    /// B's axes in A's frame: `a_A = mounting · a_B` for the same motion.
    pub mounting: [[f64; 3]; 3],
    /// Span of segments one estimate averages, s.
    pub estimate_s: f64,
    /// Estimates whose coherence is below this are too quiet to judge (left out).
    pub min_coherence: f64,
    /// Sensor time of estimates the relative test's baseline takes, s.
    pub baseline_s: f64,
    /// Relative gain change the relative test is designed for.
    pub shift: f64,
    pub watch_arl_days: f64,
    pub suspect_arl_days: f64,
    pub absolute_watch_probability: f64,
    pub absolute_suspect_probability: f64,
    /// Sequential and absolute tests sharing each sensor's false-alarm budget (the larger of
    /// the two sensors' counts): the relative tests' run lengths are multiplied by the first,
    /// the absolute tests' probabilities divided by the second.
    pub shared_sequential_tests: u32,
    pub shared_absolute_tests: u32,
    /// Estimates before the absolute test's first look.
    pub absolute_min_estimates: u32,
}

impl Default for PairConfig {
    fn default() -> Self {
        PairConfig {
            band_hz: [1.0, 5.0],
            segment_s: 5.0,
            mounting: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
            estimate_s: 3600.0,
            min_coherence: 0.5,
            baseline_s: 86_400.0,
            shift: 0.005,
            watch_arl_days: 30.0,
            suspect_arl_days: 10_000.0,
            absolute_watch_probability: 0.99,
            absolute_suspect_probability: 0.999,
            shared_sequential_tests: 7,
            shared_absolute_tests: 4,
            absolute_min_estimates: 6,
        }
    }
}

impl PairConfig {
    /// Refuses settings that would make the estimate meaningless, by field.
    pub fn validate(&self) -> Result<(), HealthError> {
        let bad =
            |field: &'static str, problem: String| Err(HealthError::Config { field, problem });
        let [low, high] = self.band_hz;
        if !(low > 0.0 && high > low && high.is_finite()) {
            return bad(
                "band_hz",
                format!("{low} to {high} Hz is not a band above 0"),
            );
        }
        if !(self.segment_s.is_finite() && self.segment_s * low >= 2.0) {
            return bad(
                "segment_s",
                format!(
                    "{} s holds fewer than two periods of {low} Hz",
                    self.segment_s
                ),
            );
        }
        if !(self.estimate_s.is_finite() && self.estimate_s >= 10.0 * self.segment_s) {
            return bad(
                "estimate_s",
                format!("{} s is fewer than ten segments", self.estimate_s),
            );
        }
        let m = &self.mounting;
        for i in 0..3 {
            for j in 0..3 {
                let dot: f64 = (0..3).map(|k| m[i][k] * m[j][k]).sum();
                let want = if i == j { 1.0 } else { 0.0 };
                let orthonormal = (dot - want).abs() < 1e-6;
                if !orthonormal {
                    return bad(
                        "mounting",
                        format!("{m:?} is not a rotation (rows {i} and {j} give {dot})"),
                    );
                }
            }
        }
        let positive = [
            ("baseline_s", self.baseline_s),
            ("shift", self.shift),
            ("watch_arl_days", self.watch_arl_days),
            ("suspect_arl_days", self.suspect_arl_days),
        ];
        for (field, v) in positive {
            if !(v.is_finite() && v > 0.0) {
                return bad(field, format!("{v} must be finite and above 0"));
            }
        }
        if !(0.0..1.0).contains(&self.min_coherence) {
            return bad(
                "min_coherence",
                format!("{} is not in 0 to 1", self.min_coherence),
            );
        }
        Ok(())
    }
}

/// One sensor's DFT at the band's bins over the current segment.
#[derive(Debug, Clone)]
pub(crate) struct Segment {
    /// Goertzel states (s₁, s₂) per axis and bin, `3 × bins`.
    state: Vec<[f64; 2]>,
    /// 2·cos ω per bin, ω the bin's angle per sample.
    coefficient: Vec<f64>,
    frequency_hz: Vec<f64>,
    index: Option<i64>,
    first_ns: i64,
    n: u32,
    /// Samples in a whole segment.
    len: u32,
    sum_w2: f64,
    /// Expected time of the next sample, ns; a break drops the segment.
    next_ns: i64,
    sample_rate_hz: f64,
}

/// A completed segment's spectra.
#[derive(Debug, Clone)]
pub(crate) struct Spectrum {
    pub(crate) index: i64,
    /// X per axis and bin, referred to the segment's grid start.
    pub(crate) x: Vec<[f64; 2]>,
    pub(crate) sum_w2: f64,
}

#[derive(Debug, Clone)]
struct Side {
    segment: Segment,
    pending: Vec<Spectrum>,
    /// Spectrum buffers to reuse, so that a segment's end allocates nothing once running.
    spare: Vec<Vec<[f64; 2]>>,
    /// White-noise variance of the corrected reading per axis (of A's frame), (m/s²)², and the
    /// reciprocal of its ν (the record's `output_noise_dof`).
    noise_var: [f64; 3],
    noise_inv_dof: f64,
    /// Relative gain variance per axis of A's frame, and the reciprocal of its ν.
    gain_var: [f64; 3],
    gain_inv_dof: f64,
}

/// The spectra accumulated over an estimate: A's cross-spectral matrix `Σ conj(xᵢ)·xₖ`, A's
/// with B's `Σ conj(xᵢ)·yⱼ`, B's auto-spectra, and the record's noise A's diagonal holds.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Sums {
    gaa: [[Complex<f64>; 3]; 3],
    gab: [[Complex<f64>; 3]; 3],
    gbb: [f64; 3],
    noise: [f64; 3],
}

impl Default for Sums {
    fn default() -> Self {
        let zero = Complex::new(0.0, 0.0);
        Sums {
            gaa: [[zero; 3]; 3],
            gab: [[zero; 3]; 3],
            gbb: [0.0; 3],
            noise: [0.0; 3],
        }
    }
}

impl Sums {
    fn add(&mut self, o: &Sums, sign: f64) {
        for i in 0..3 {
            for k in 0..3 {
                self.gaa[i][k] += o.gaa[i][k] * sign;
                self.gab[i][k] += o.gab[i][k] * sign;
            }
            self.gbb[i] += sign * o.gbb[i];
            self.noise[i] += sign * o.noise[i];
        }
    }

    /// A's axes whose motion in these spectra stands at least as high as their noise.
    fn active(&self) -> [bool; 3] {
        [0, 1, 2].map(|i| self.gaa[i][i].re - self.noise[i] >= self.noise[i].max(f64::MIN_POSITIVE))
    }

    /// B's response to A along axis `j` by the multiple-input H₁ over the `active` axes of A
    /// (the others held out): the row of `(G_AA − N)⁻¹·G_AB`, and its multiple coherence. The
    /// ratio is `H_jj`; correlated motion along other axes (a transient's direction, a
    /// diagonal mode) goes to their terms instead of biasing it through the records' cross-axis
    /// errors.
    fn response(&self, j: usize, active: [bool; 3]) -> Option<(Complex<f64>, f64)> {
        if !active[j] {
            return None;
        }
        let one = Complex::new(1.0, 0.0);
        let zero = Complex::new(0.0, 0.0);
        let m = Matrix3::from_fn(|i, k| match (active[i], active[k]) {
            (true, true) => self.gaa[i][k] - if i == k { one * self.noise[i] } else { zero },
            _ if i == k => one,
            _ => zero,
        });
        let rhs = Vector3::from_fn(|i, _| if active[i] { self.gab[i][j] } else { zero });
        let h = m.lu().solve(&rhs)?;
        // γ² = g^H·(G_AA)⁻¹·g / G_BB with the uncorrected G_AA, as the coherence is defined.
        let m_raw = Matrix3::from_fn(|i, k| match (active[i], active[k]) {
            (true, true) => self.gaa[i][k],
            _ if i == k => one,
            _ => zero,
        });
        let explained = m_raw.lu().solve(&rhs)?;
        let num: Complex<f64> = (0..3).map(|i| rhs[i].conj() * explained[i]).sum();
        let coherence_sq = (num.re / self.gbb[j].max(f64::MIN_POSITIVE)).clamp(0.0, 1.0);
        Some((h[j], coherence_sq))
    }
}

/// One estimate of B's gain relative to A's along one axis.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GainRatio {
    pub end_ns: i64,
    pub ratio: f64,
    /// Standard uncertainty of `ratio` from the finite averages: the larger of Bendat &
    /// Piersol's and the jackknife's, and its degrees of freedom.
    pub uncertainty: f64,
    pub dof: f64,
    /// Bendat & Piersol's random error alone, for comparison.
    pub bendat_piersol: f64,
    /// The parts of `uncertainty`: the estimate's own random error (and its ν), which averages
    /// down over estimates, and the record's noise taken out of A's auto-spectrum, which is
    /// the same error in every estimate under the record and does not.
    pub random: f64,
    pub random_dof: f64,
    pub noise_reference: f64,
    pub coherence_sq: f64,
    pub averages: f64,
}

#[derive(Debug, Clone)]
struct AxisTest {
    latest: Option<GainRatio>,
    absolute: Option<(f64, f64, f64)>,
    absolute_suspect_since_ns: Option<i64>,
    looks: Looks,
    /// Σw, Σw·r and Σw·ν⁻¹ of every estimate so far, w = 1/u², and the first's time.
    all_w: f64,
    all_wr: f64,
    all_w2_inv_dof: f64,
    /// Σw·(the noise reference's part of u), averaged as one error, not down.
    all_noise_w: f64,
    all_first_ns: Option<i64>,
    baseline_w: f64,
    baseline_wr: f64,
    baseline_first_ns: Option<i64>,
    baseline: Option<(f64, f64)>,
    seq: Sequential,
    excursion: (f64, f64),
    latest_d: Option<(f64, f64)>,
    estimates: u64,
}

/// The gain-ratio check of a pair of co-located sensors, each under one record.
#[derive(Debug, Clone)]
pub struct ColocatedPair {
    config: PairConfig,
    bins: usize,
    a: Side,
    b: Side,
    sums: Sums,
    /// The same sums per sub-span, for the jackknife.
    parts: Vec<Sums>,
    /// Per bin: whether it enters the estimate (chosen on the previous estimate's data); per
    /// axis and bin, A's auto-spectrum over this one, to choose the next.
    use_bin: Vec<bool>,
    bin_gxx: Vec<f64>,
    /// Σ of the window's squares over this estimate's segments.
    sum_w2: f64,
    segments: u32,
    segments_per_estimate: u32,
    axes: [AxisTest; 3],
    /// Segments one batch completed, handed on once the batch is in (reused).
    completed: Vec<Spectrum>,
}

impl Segment {
    /// A segment for the bins of `band_hz` in segments of `segment_s`.
    pub(crate) fn for_band(band_hz: [f64; 2], segment_s: f64) -> Segment {
        let first = (band_hz[0] * segment_s).ceil() as usize;
        let last = (band_hz[1] * segment_s).floor() as usize;
        let mut seg = Segment::new(last.saturating_sub(first) + 1);
        for (k, f) in (first..=last).enumerate() {
            seg.frequency_hz[k] = f as f64 / segment_s;
        }
        seg
    }

    /// Bins per axis.
    pub(crate) fn bins(&self) -> usize {
        self.frequency_hz.len()
    }

    pub(crate) fn new(bins: usize) -> Segment {
        Segment {
            state: vec![[0.0; 2]; 3 * bins],
            coefficient: vec![0.0; bins],
            frequency_hz: vec![0.0; bins],
            index: None,
            first_ns: 0,
            n: 0,
            len: 0,
            sum_w2: 0.0,
            next_ns: 0,
            sample_rate_hz: 0.0,
        }
    }
}

impl Segment {
    fn open(&mut self, index: i64, t_ns: i64, sample_rate_hz: f64, segment_s: f64) {
        self.index = Some(index);
        self.first_ns = t_ns;
        self.n = 0;
        self.len = (segment_s * sample_rate_hz).round() as u32;
        self.sum_w2 = 0.0;
        self.next_ns = t_ns;
        self.sample_rate_hz = sample_rate_hz;
        for (c, f) in self.coefficient.iter_mut().zip(&self.frequency_hz) {
            *c = 2.0 * (2.0 * std::f64::consts::PI * f / sample_rate_hz).cos();
        }
        for s in &mut self.state {
            *s = [0.0; 2];
        }
    }

    /// Adds a sample at `place` (0 to 1) in its segment of the common grid.
    #[inline]
    fn push(&mut self, v: [f64; 3], t_ns: i64, period_ns: f64, place: f64) {
        // Hann by the sample's time on the grid, so that every sensor weighs the same instants
        // alike whatever its sampling phase.
        let w = 0.5 - 0.5 * (2.0 * std::f64::consts::PI * place).cos();
        self.sum_w2 += w * w;
        let bins = self.coefficient.len();
        for (axis, x) in v.iter().enumerate() {
            let x = w * x;
            let states = &mut self.state[axis * bins..(axis + 1) * bins];
            for (s, c) in states.iter_mut().zip(&self.coefficient) {
                let next = x + c * s[0] - s[1];
                s[1] = s[0];
                s[0] = next;
            }
        }
        self.n += 1;
        self.next_ns = t_ns + period_ns.round() as i64;
    }

    /// The segment's spectrum, into `x`, if it is whole (at least 95 % of its samples);
    /// otherwise `x` back.
    fn close(
        &mut self,
        index: i64,
        segment_ns: i64,
        mut x: Vec<[f64; 2]>,
    ) -> Result<Spectrum, Vec<[f64; 2]>> {
        self.index = None;
        if 20 * self.n < 19 * self.len || self.n < 2 {
            return Err(x);
        }
        let bins = self.coefficient.len();
        let n = f64::from(self.n);
        let grid_ns = index * segment_ns;
        let offset_s = (self.first_ns - grid_ns) as f64 * 1e-9;
        x.resize(3 * bins, [0.0; 2]);
        for axis in 0..3 {
            for k in 0..bins {
                let f = self.frequency_hz[k];
                let w = 2.0 * std::f64::consts::PI * f / self.sample_rate_hz;
                let [s1, s2] = self.state[axis * bins + k];
                // y = s₁ − e^{−iω}·s₂ = Σ x_m e^{iω(n−1−m)}; X = e^{−iω(n−1)}·y, then referred
                // from the first sample's time to the grid's: e^{−i2πf·offset}.
                let y = [s1 - w.cos() * s2, w.sin() * s2];
                let phase = -w * (n - 1.0) - 2.0 * std::f64::consts::PI * f * offset_s;
                let (sin, cos) = phase.sin_cos();
                x[axis * bins + k] = [y[0] * cos - y[1] * sin, y[0] * sin + y[1] * cos];
            }
        }
        Ok(Spectrum {
            index,
            x,
            sum_w2: self.sum_w2,
        })
    }
}

/// Feeds one sensor's corrected readings, turned into the common frame by `turn` (none: its
/// frame is it), into its segments on the common grid of `segment_s`; every segment it
/// completes whole goes to `done`. A break in the stream drops the segment it falls in.
#[allow(clippy::too_many_arguments)]
pub(crate) fn feed_segments(
    seg: &mut Segment,
    spare: &mut Vec<Vec<[f64; 2]>>,
    segment_s: f64,
    turn: Option<&[[f64; 3]; 3]>,
    timestamp_ns: i64,
    sample_rate_hz: f64,
    accel: &[[f64; 3]],
    mut done: impl FnMut(Spectrum),
) {
    if !(sample_rate_hz.is_finite() && sample_rate_hz > 0.0) {
        return;
    }
    let segment_ns = (segment_s * 1e9).round() as i64;
    let period_ns = 1e9 / sample_rate_hz;
    for (i, a) in accel.iter().enumerate() {
        let t = timestamp_ns + (i as f64 * period_ns).round() as i64;
        let v = match turn {
            None => *a,
            Some(m) => [0, 1, 2].map(|r| m[r][0] * a[0] + m[r][1] * a[1] + m[r][2] * a[2]),
        };
        let index = t.div_euclid(segment_ns);
        let broke = seg.index.is_some()
            && (seg.sample_rate_hz != sample_rate_hz
                || ((t - seg.next_ns) as f64).abs() > 0.5 * period_ns);
        if seg.index != Some(index) || broke {
            if let (false, Some(finished)) = (broke, seg.index) {
                let buffer = spare.pop().unwrap_or_default();
                match seg.close(finished, segment_ns, buffer) {
                    Ok(spectrum) => done(spectrum),
                    Err(buffer) => spare.push(buffer),
                }
            }
            seg.open(index, t, sample_rate_hz, segment_s);
        }
        let place = (t - index * segment_ns) as f64 / segment_ns as f64;
        seg.push(v, t, period_ns, place);
    }
}

/// Relative gain variance along unit `d` of a reading through `record`'s dynamic set (`set`,
/// loaded from it), turned by `turn` (B into A's frame), and the reciprocal of its ν.
pub(crate) fn gain_variance(
    record: &CalibrationRecord,
    set: &SetCorrector,
    turn: &[[f64; 3]; 3],
) -> ([f64; 3], f64) {
    let columns = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]].map(|e| set.scale(e));
    let s_inv = [0, 1, 2].map(|k| [0, 1, 2].map(|j| columns[j][k]));
    let set = record.set(SetKind::Dynamic);
    let mut out = [0.0; 3];
    for (axis, var) in out.iter_mut().enumerate() {
        // The direction, in this sensor's frame, of axis `axis` of A's frame.
        let d = [turn[axis][0], turn[axis][1], turn[axis][2]];
        let dt_s_inv = [0, 1, 2].map(|j| (0..3).map(|k| d[k] * s_inv[k][j]).sum::<f64>());
        let c = |p: usize| dt_s_inv[p / 3] * d[p % 3];
        if let Some(cov) = &set.covariance {
            for p in 0..9 {
                for q in 0..9 {
                    *var += c(p) * cov[p][q] * c(q);
                }
            }
        }
    }
    (out, set.covariance_dof.map_or(0.0, |nu| 1.0 / nu))
}

impl ColocatedPair {
    /// A pair check for sensor A under `record_a` and sensor B under `record_b`.
    pub fn new(
        record_a: &CalibrationRecord,
        record_b: &CalibrationRecord,
        config: &PairConfig,
    ) -> Result<ColocatedPair, HealthError> {
        config.validate()?;
        let first = (config.band_hz[0] * config.segment_s).ceil() as usize;
        let last = (config.band_hz[1] * config.segment_s).floor() as usize;
        let bins = last.saturating_sub(first) + 1;
        let identity = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
        let m = config.mounting;
        // B's reading of A's axis i is row i of the mounting: its direction in B's frame.
        let side =
            |record: &CalibrationRecord, turn: &[[f64; 3]; 3]| -> Result<Side, HealthError> {
                let corrector = Corrector::from_record(record)?;
                let noise = corrector
                    .set(SetKind::Dynamic)
                    .covariance_filtered_parts([0.0; 3], 1.0, [0.0; 3])
                    .noise;
                let mut noise_var = [0.0; 3];
                for (i, nv) in noise_var.iter_mut().enumerate() {
                    for j in 0..3 {
                        for k in 0..3 {
                            *nv += turn[i][j] * noise[j][k] * turn[i][k];
                        }
                    }
                }
                let (gain_var, gain_inv_dof) =
                    gain_variance(record, corrector.set(SetKind::Dynamic), turn);
                Ok(Side {
                    segment: Segment::new(bins),
                    pending: Vec::with_capacity(PENDING + 1),
                    spare: (0..PENDING + 1).map(|_| vec![[0.0; 2]; 3 * bins]).collect(),
                    noise_var,
                    noise_inv_dof: record.sensor.output_noise_dof.map_or(0.0, |nu| 1.0 / nu),
                    gain_var,
                    gain_inv_dof,
                })
            };
        let per_day = 86_400.0 / config.estimate_s;
        let tests = f64::from(config.shared_sequential_tests.max(1));
        let thresholds = Thresholds::from_arl(
            config.watch_arl_days * tests * per_day,
            config.suspect_arl_days * tests * per_day,
            2,
        );
        let absolute = f64::from(config.shared_absolute_tests.max(1));
        let looks = Looks::new(
            u64::from(config.absolute_min_estimates),
            (1.0 - config.absolute_watch_probability) / absolute,
            (1.0 - config.absolute_suspect_probability) / absolute,
        );
        let axis = || AxisTest {
            latest: None,
            absolute: None,
            absolute_suspect_since_ns: None,
            looks,
            all_w: 0.0,
            all_wr: 0.0,
            all_w2_inv_dof: 0.0,
            all_noise_w: 0.0,
            all_first_ns: None,
            baseline_w: 0.0,
            baseline_wr: 0.0,
            baseline_first_ns: None,
            baseline: None,
            seq: Sequential::new(thresholds),
            excursion: (0.0, 0.0),
            latest_d: None,
            estimates: 0,
        };
        let mut pair = ColocatedPair {
            bins,
            a: side(record_a, &identity)?,
            b: side(record_b, &m)?,
            sums: Sums::default(),
            parts: vec![Sums::default(); JACKKNIFE],
            use_bin: vec![true; bins],
            bin_gxx: vec![0.0; 3 * bins],
            sum_w2: 0.0,
            segments: 0,
            segments_per_estimate: (config.estimate_s / config.segment_s).round() as u32,
            axes: [axis(), axis(), axis()],
            completed: Vec::with_capacity(2),
            config: config.clone(),
        };
        for side in [&mut pair.a, &mut pair.b] {
            for (k, f) in (first..=last).enumerate() {
                side.segment.frequency_hz[k] = f as f64 / config.segment_s;
            }
        }
        Ok(pair)
    }

    /// Sensor A's corrected readings (m/s², its frame), the first at `timestamp_ns`.
    pub fn feed_a(&mut self, timestamp_ns: i64, sample_rate_hz: f64, accel_mps2: &[[f64; 3]]) {
        self.feed(true, timestamp_ns, sample_rate_hz, accel_mps2);
    }

    /// Sensor B's corrected readings (m/s², its own frame: the mounting turns them).
    pub fn feed_b(&mut self, timestamp_ns: i64, sample_rate_hz: f64, accel_mps2: &[[f64; 3]]) {
        self.feed(false, timestamp_ns, sample_rate_hz, accel_mps2);
    }

    fn feed(&mut self, is_a: bool, timestamp_ns: i64, sample_rate_hz: f64, accel: &[[f64; 3]]) {
        let mut completed = std::mem::take(&mut self.completed);
        let side = if is_a { &mut self.a } else { &mut self.b };
        let turn = (!is_a).then_some(&self.config.mounting);
        feed_segments(
            &mut side.segment,
            &mut side.spare,
            self.config.segment_s,
            turn,
            timestamp_ns,
            sample_rate_hz,
            accel,
            |spectrum| completed.push(spectrum),
        );
        for spectrum in completed.drain(..) {
            self.complete(is_a, spectrum);
        }
        self.completed = completed;
    }

    fn complete(&mut self, is_a: bool, spectrum: Spectrum) {
        let (mine, other) = if is_a {
            (&mut self.a, &mut self.b)
        } else {
            (&mut self.b, &mut self.a)
        };
        if let Some(pos) = other.pending.iter().position(|s| s.index == spectrum.index) {
            let theirs = other.pending.swap_remove(pos);
            let (xa, xb) = if is_a {
                (spectrum, theirs)
            } else {
                (theirs, spectrum)
            };
            self.combine(&xa, &xb);
            self.a.spare.push(xa.x);
            self.b.spare.push(xb.x);
            return;
        }
        // Segments the other sensor will never deliver (a gap) are dropped oldest first.
        while let Some(i) = mine.pending.iter().position(|s| s.index >= spectrum.index) {
            let stale = mine.pending.swap_remove(i);
            mine.spare.push(stale.x);
        }
        if mine.pending.len() == PENDING {
            if let Some(oldest) = (0..mine.pending.len()).min_by_key(|&i| mine.pending[i].index) {
                let stale = mine.pending.swap_remove(oldest);
                mine.spare.push(stale.x);
            }
        }
        mine.pending.push(spectrum);
    }

    fn combine(&mut self, a: &Spectrum, b: &Spectrum) {
        let bins = self.bins;
        let end_ns = (a.index + 1) * (self.config.segment_s * 1e9).round() as i64;
        let part = (self.segments as usize * JACKKNIFE / self.segments_per_estimate as usize)
            .min(JACKKNIFE - 1);
        self.sum_w2 += a.sum_w2;
        let mut s = Sums::default();
        let mut used = 0u32;
        for k in 0..bins {
            let x = [0, 1, 2].map(|axis| {
                let v = a.x[axis * bins + k];
                Complex::new(v[0], v[1])
            });
            for (axis, xi) in x.iter().enumerate() {
                self.bin_gxx[axis * bins + k] += xi.norm_sqr();
            }
            if !self.use_bin[k] {
                continue;
            }
            used += 1;
            let y = [0, 1, 2].map(|axis| {
                let v = b.x[axis * bins + k];
                Complex::new(v[0], v[1])
            });
            for i in 0..3 {
                let xc = x[i].conj();
                for l in 0..3 {
                    s.gaa[i][l] += xc * x[l];
                    s.gab[i][l] += xc * y[l];
                }
                s.gbb[i] += y[i].norm_sqr();
            }
        }
        for (axis, n) in s.noise.iter_mut().enumerate() {
            *n = self.a.noise_var[axis] * a.sum_w2 * f64::from(used);
        }
        self.sums.add(&s, 1.0);
        self.parts[part].add(&s, 1.0);
        self.segments += 1;
        if self.segments >= self.segments_per_estimate {
            self.estimate(end_ns);
        }
    }

    fn estimate(&mut self, end_ns: i64) {
        let bins = self.bins;
        let used = self.use_bin.iter().filter(|&&u| u).count();
        let averages = f64::from(self.segments) * used as f64 / 1.5;
        let s = self.sums;
        let active = s.active();
        for axis in 0..3 {
            let Some((h, coherence_sq)) = s.response(axis, active) else {
                continue;
            };
            if coherence_sq < self.config.min_coherence {
                continue;
            }
            let ratio = h.re;
            let relative = (1.0 - coherence_sq).max(0.0).sqrt()
                / (coherence_sq.sqrt() * (2.0 * averages).sqrt());
            let bendat_piersol = relative * ratio.abs();
            // Delete-one jackknife over the sub-spans that hold data, each replicate the same
            // regression on the rest.
            let mut replicates = [0.0; JACKKNIFE];
            let mut m = 0;
            for part in &self.parts {
                if part.gaa[axis][axis].re == 0.0 {
                    continue;
                }
                let mut rest = s;
                rest.add(part, -1.0);
                if let Some((h, _)) = rest.response(axis, active) {
                    replicates[m] = h.re;
                    m += 1;
                }
            }
            let jackknife = if m >= 2 {
                let mean = replicates[..m].iter().sum::<f64>() / m as f64;
                let ss: f64 = replicates[..m].iter().map(|r| (r - mean).powi(2)).sum();
                ((m as f64 - 1.0) / m as f64 * ss).sqrt()
            } else {
                f64::INFINITY
            };
            let (random, random_dof) = if jackknife > bendat_piersol {
                (jackknife, m.saturating_sub(1).max(1) as f64)
            } else {
                (bendat_piersol, 2.0 * averages)
            };
            // The record's noise, taken out of A's auto-spectrum, is itself an estimate: u(N)/N
            // = √(2/ν) moves the ratio by r·u(N)/(ΣG_xx − N).
            let noise_inv_dof = self.a.noise_inv_dof;
            let denominator = s.gaa[axis][axis].re - s.noise[axis];
            let noise = ratio.abs() * s.noise[axis] * (2.0 * noise_inv_dof).sqrt() / denominator;
            let parts = [
                (random * random, 1.0 / random_dof),
                (noise * noise, 0.5 * noise_inv_dof),
            ];
            let uncertainty = (parts[0].0 + parts[1].0).sqrt();
            let dof = welch_satterthwaite(&parts).clamp(1.0, f64::from(MAX_DOF));
            let estimate = GainRatio {
                end_ns,
                ratio,
                uncertainty,
                dof,
                bendat_piersol,
                random,
                random_dof,
                noise_reference: noise,
                coherence_sq,
                averages,
            };
            self.judge(axis, estimate);
        }
        // The next estimate takes the bins where this one's motion stood above the noise on
        // some axis (signal at least equal to it), or every bin where none did.
        let noise = self.a.noise_var.map(|v| v * self.sum_w2);
        let gxx = &self.bin_gxx;
        let moving = |k: usize| (0..3).any(|axis| gxx[axis * bins + k] >= 2.0 * noise[axis]);
        let any = (0..bins).any(moving);
        for (k, u) in self.use_bin.iter_mut().enumerate() {
            *u = !any || moving(k);
        }
        self.bin_gxx.iter_mut().for_each(|g| *g = 0.0);
        self.sum_w2 = 0.0;
        self.sums = Sums::default();
        for part in &mut self.parts {
            *part = Sums::default();
        }
        self.segments = 0;
    }

    fn judge(&mut self, axis: usize, e: GainRatio) {
        let (ua, ub) = (self.a.gain_var[axis], self.b.gain_var[axis]);
        let t = &mut self.axes[axis];
        t.latest = Some(e);
        t.estimates += 1;
        let random_var = e.uncertainty * e.uncertainty;
        // The absolute test judges the mean of every estimate so far: the records' errors
        // (gains, and the noise taken out) do not average away, the estimates' own do.
        let own = 1.0 / (e.random * e.random).max(f64::MIN_POSITIVE);
        t.all_w += own;
        t.all_wr += own * e.ratio;
        t.all_w2_inv_dof += own * own / e.random_dof;
        t.all_noise_w += own * e.noise_reference;
        t.all_first_ns.get_or_insert(e.end_ns);
        let mean_var = 1.0 / t.all_w;
        let noise_reference = t.all_noise_w / t.all_w;
        // ν of the weighted mean by Welch–Satterthwaite over the estimates (each contributes
        // w/W² of its variance): W²/Σ(w²/ν).
        let parts = [
            (mean_var, t.all_w2_inv_dof * mean_var * mean_var),
            (
                noise_reference * noise_reference,
                0.5 * self.a.noise_inv_dof,
            ),
            (ua, self.a.gain_inv_dof),
            (ub, self.b.gain_inv_dof),
        ];
        let var: f64 = parts.iter().map(|(v, _)| v).sum();
        let nu = welch_satterthwaite(&parts).clamp(1.0, f64::from(MAX_DOF));
        let (d, u) = (t.all_wr / t.all_w - 1.0, var.sqrt());
        t.absolute = Some((d, u, nu));
        if t.looks.due(t.estimates) && t.looks.take(d.abs() / u, nu) {
            t.absolute_suspect_since_ns = t.all_first_ns;
        }
        let w = 1.0 / random_var.max(f64::MIN_POSITIVE);
        match t.baseline {
            None => {
                let first = *t.baseline_first_ns.get_or_insert(e.end_ns);
                t.baseline_w += w;
                t.baseline_wr += w * e.ratio;
                if (e.end_ns - first) as f64 * 1e-9 + self.config.estimate_s
                    >= self.config.baseline_s
                {
                    t.baseline = Some((t.baseline_wr / t.baseline_w, 1.0 / t.baseline_w));
                }
            }
            Some((r0, var0)) => {
                let d = e.ratio - r0;
                let u = (random_var + var0).sqrt();
                let delta = self.config.shift / u;
                let z = d / u;
                t.seq.update(
                    delta * (z - delta / 2.0),
                    delta * (-z - delta / 2.0),
                    e.end_ns,
                );
                let (up, down) = t.seq.sides();
                let side = if down > up { down } else { up };
                if side > 0.0 {
                    t.excursion.0 += w;
                    t.excursion.1 += w * d;
                } else {
                    t.excursion = (0.0, 0.0);
                }
                t.latest_d = Some((d, u));
            }
        }
    }

    /// Whether axis `axis`'s relative test has its baseline.
    pub fn has_baseline(&self, axis: usize) -> bool {
        self.axes.get(axis).is_some_and(|t| t.baseline.is_some())
    }

    /// The latest estimate per axis of A's frame.
    pub fn latest(&self) -> [Option<GainRatio>; 3] {
        [0, 1, 2].map(|i| self.axes[i].latest)
    }

    /// Per axis: B's gain over A's minus 1, against the two calibrations' uncertainties.
    pub fn absolute_report(&self) -> [TestReport; 3] {
        [0, 1, 2].map(|i| {
            let t = &self.axes[i];
            let Some((d, u, _)) = t.absolute else {
                return TestReport::unjudged(Unjudged::NoEstimate);
            };
            let judged = t.looks.taken() > 0;
            let verdict = if t.absolute_suspect_since_ns.is_some() {
                Verdict::Suspect
            } else if t.looks.watch() {
                Verdict::Watch
            } else {
                Verdict::Ok
            };
            TestReport {
                verdict,
                judged,
                reason: (!judged).then_some(Unjudged::NoEstimate),
                statistic: d,
                uncertainty: u,
                since_ns: match verdict {
                    Verdict::Suspect => t.absolute_suspect_since_ns,
                    Verdict::Watch => t.latest.map(|e| e.end_ns),
                    Verdict::Ok => None,
                },
                evidence_nats: 0.0,
                observations: t.estimates,
                ..TestReport::pending()
            }
        })
    }

    /// Per axis: the ratio's change since the baseline.
    pub fn relative_report(&self) -> [TestReport; 3] {
        [0, 1, 2].map(|i| {
            let t = &self.axes[i];
            let Some((d, u)) = t.latest_d else {
                return TestReport::unjudged(if t.estimates == 0 {
                    Unjudged::NoEstimate
                } else {
                    Unjudged::Baseline
                });
            };
            let (statistic, uncertainty) = match (t.excursion, t.baseline) {
                ((w, wd), Some((_, var0))) if w > 0.0 => (wd / w, (1.0 / w + var0).sqrt()),
                _ => (d, u),
            };
            TestReport {
                verdict: t.seq.verdict(),
                judged: true,
                statistic,
                uncertainty,
                since_ns: t.seq.since_ns(),
                evidence_nats: t.seq.value(),
                observations: t.seq.observations(),
                reason: None,
                ..TestReport::pending()
            }
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use triax_protocol::record::sample;

    /// A record with S = I and no output noise (its stated uncertainty keeps it loadable).
    fn unit_record(id: &str) -> CalibrationRecord {
        let mut r = sample::record(id, 1);
        for set in [&mut r.static_set, &mut r.dynamic] {
            set.sensitivity = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
            set.offset = [0.0; 3];
        }
        r.sensor.output_noise = None;
        r
    }

    /// Two tones, 1.3 and 4.1 Hz, along A's x; B is turned a quarter turn about z (its y is
    /// A's x) and reads 1.01 times as much, sampled 3 ms later than A: the ratio on x is 1.01
    /// to the Goertzel sums' round-off, at coherence 1; y and z see nothing and give no
    /// estimate.
    #[test]
    fn two_tones_give_the_ratio_by_hand() {
        let config = PairConfig {
            estimate_s: 60.0,
            // B's x is A's −y, B's y is A's x: a_A = M·a_B.
            mounting: [[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]],
            ..PairConfig::default()
        };
        let mut pair = ColocatedPair::new(&unit_record("a"), &unit_record("b"), &config).unwrap();
        let fs = 100.0;
        let motion = |t: f64| {
            0.02 * (2.0 * std::f64::consts::PI * 1.3 * t).sin()
                + 0.01 * (2.0 * std::f64::consts::PI * 4.1 * t + 0.3).cos()
        };
        let start_ns = 1_767_225_600_000_000_000i64;
        let lag_ns = 3_000_000;
        let mut a = Vec::new();
        let mut b = Vec::new();
        for batch in 0..700 {
            a.clear();
            b.clear();
            for i in 0..10 {
                let n = batch * 10 + i;
                let ta = n as f64 / fs;
                let tb = ta + lag_ns as f64 * 1e-9;
                a.push([motion(ta), 0.0, 0.0]);
                b.push([0.0, 1.01 * motion(tb), 0.0]);
            }
            let t0 = start_ns + batch * 100_000_000;
            pair.feed_a(t0, fs, &a);
            pair.feed_b(t0 + lag_ns, fs, &b);
        }
        let [x, y, z] = pair.latest();
        let x = x.expect("an estimate on x");
        assert!((x.ratio - 1.01).abs() < 1e-9, "{x:?}");
        assert!((x.coherence_sq - 1.0).abs() < 1e-9, "{x:?}");
        assert!(x.uncertainty < 1e-6, "{x:?}");
        // 12 segments of 5 s, bins 5..=25 (1–5 Hz at 0.2 Hz): 12·21/1.5 averages.
        assert_eq!(x.averages, 12.0 * 21.0 / 1.5);
        assert!(y.is_none() && z.is_none());
        let abs = pair.absolute_report();
        assert!((abs[0].statistic - 0.01).abs() < 1e-9);
        assert!(!abs[1].judged);
    }

    /// Relative gain variance by hand: S = diag(0.1), Var(S₀₀) = 10⁻⁸ gives (10⁻⁴/0.1)² = 10⁻⁶
    /// along x; through a quarter turn, B's y (A's x) takes S₁₁'s.
    #[test]
    fn gain_variance_by_hand() {
        let mut r = unit_record("g");
        r.dynamic.sensitivity = [[0.1, 0.0, 0.0], [0.0, 0.1, 0.0], [0.0, 0.0, 0.1]];
        let mut cov = [[0.0; 12]; 12];
        cov[0][0] = 1e-8;
        cov[4][4] = 4e-8;
        r.dynamic.covariance = Some(Box::new(cov));
        let c = Corrector::from_record(&r).unwrap();
        let set = c.set(SetKind::Dynamic);
        let identity = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
        let (var, _) = gain_variance(&r, set, &identity);
        assert!((var[0] - 1e-6).abs() < 1e-18 && (var[1] - 4e-6).abs() < 1e-18);
        let turn = [[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]];
        let (var, _) = gain_variance(&r, set, &turn);
        assert!((var[0] - 4e-6).abs() < 1e-18 && (var[1] - 1e-6).abs() < 1e-18);
    }

    #[test]
    fn refuses_a_mounting_that_is_not_a_rotation() {
        let config = PairConfig {
            mounting: [[1.0, 0.0, 0.0], [0.0, 2.0, 0.0], [0.0, 0.0, 1.0]],
            ..PairConfig::default()
        };
        let e = ColocatedPair::new(&unit_record("a"), &unit_record("b"), &config).unwrap_err();
        assert!(e.to_string().contains("mounting"), "{e}");
    }
}
