//! The sample path: one raw batch in, one corrected batch out, for one sensor.
//!
//! [`SensorKernel::correct_batch`] reads samples straight from the payload
//! ([`RawBatchView`]), corrects them with the sensor's [`Corrector`] snapshot and appends them
//! to a caller-owned buffer through [`CorrectedBatchWriter`]. It allocates nothing per sample, takes
//! no lock and does no I/O; its only state is the per-sensor filter memory kept in
//! [`SensorKernel`], which survives a calibration swap.
//!
//! # Modes
//!
//! - `static`: `a = S_s⁻¹·V + q_s`, uncertainty from the static set.
//! - `dynamic`: `a = S_d⁻¹·V + q_d`, uncertainty from the dynamic set.
//! - `split`: a complementary crossover at `crossover_hz`. `V_low` is `V` through a
//!   second-order Butterworth low pass and `V_high = V − V_low`, so the two bands sum to `V`
//!   exactly. Then `a = (S_s⁻¹·V_low + q_s) + S_d⁻¹·V_high`: the static set (and its offset,
//!   which is a DC quantity) carries the low band, only the dynamic set's `S⁻¹` the rest. The
//!   variance per axis is `u_s²(V_low) + u_d,S²(V_high) + max(c_s, c_d)`: the static set's full
//!   parameter variance at `V_low`, the dynamic set's sensitivity-only parameter variance at
//!   `V_high` ([`SetCorrector::scale_param_variance`]), the two sets taken as independent (they
//!   come from different benches), and the constant part (output noise and stated uncertainty,
//!   [`SetCorrector::constant_variance`]) counted once, from whichever set states more, because
//!   the noise is one physical noise and the stated parts are alternatives, not additions.
//!
//! # Quality flags
//!
//! Per sample: `non_finite_input` (the corrected value and its uncertainty are NaN), `clipped`
//! (an output at the sensor's full scale), `outside_amplitude` (|a| on an axis above the
//! domain's `amplitude_max_mps2`; in split mode each band against its own set).
//! On every sample of a batch: `uncalibrated`, `calibration_expired` (the batch's timestamp is
//! outside `valid_from..valid_until`), `outside_frequency` (see below).
//! On the batch only: `sequence_gap` and `duplicate`, decided by the caller.
//!
//! # Frequency detector
//!
//! Each batch, the outputs go through a fourth-order Butterworth high pass at 1.25 × the
//! domain's `frequency_max_hz` (its state carried across batches) and, when the domain's
//! `frequency_min_hz` is above zero, a fourth-order low pass at `frequency_min_hz / 1.25`. The
//! filtered outputs are mapped to m/s² through `S⁻¹` and their RMS over the batch is compared,
//! per axis, with `max(k·u_c, frequency_floor_mps2)`, where `u_c` is the set's constant standard
//! uncertainty (noise and stated part) and `k` its coverage factor. Above it on any axis, every
//! sample of the batch is flagged `outside_frequency`.
//!
//! Why this rule: correcting out-of-band content with in-band parameters errs by at most that
//! content's amplitude (even a sensitivity off by 100 %), so content below the expanded
//! uncertainty cannot hurt, and white output noise alone (whose RMS is below `u_c`) never trips
//! the flag. The 1.25 margin and the fourth order keep in-band sway near the band edge from
//! leaking (a 5 Hz sway through the 12.5 Hz high pass is attenuated 40-fold). The high pass,
//! which every calibrated sensor runs on every sample, works in f32 with the three axes in the
//! lanes of one SIMD register ([`HighPass4x32`]): a threshold test needs no more, and it costs
//! about a third of what three f64 axes did. The upper check is skipped when its corner cannot
//! be realised (above 0.45 × the sample rate: the band reaches Nyquist, nothing can be above it).
//!
//! The lower check concerns varying content below the band, not the constant part: gravity and
//! the offsets (0 Hz) are inside every calibrated domain, since the static bench measures them
//! and the rotary table's recordings hold gravity's components too. So the outputs first go
//! through a second-order high pass at [`CONSTANT_BELOW_HZ`] (or a tenth of the lower corner,
//! if that is lower), which takes out gravity and anything slower than about 100 s, and then
//! through the fourth-order low pass at `frequency_min_hz / 1.25`. When that corner cannot be
//! realised (a band starting at or above 0.45 × 1.25 × the sample rate, e.g. 60–5000 Hz sampled
//! at 100 Hz), every varying component the stream can carry lies below the band, and the
//! check takes all of it (the high pass alone).
//! In split mode the band checked is the static set's minimum to the dynamic set's maximum.
//! After a sequence gap or a node restart the detector starts afresh (the jump across the
//! missing stretch is not signal), and duplicate batches bypass it.

use serde::{Deserialize, Serialize};
use triax_calibration::corrector::{Corrector, SetCorrector, TemperatureCheck, Validity};
use triax_protocol::batch::{flags, CorrectedBatchWriter, CorrectedSample, CorrectionInfo, Mode};
use triax_protocol::record::SetKind;
use triax_protocol::RawBatchView;

use super::filter::{realisable, Biquad3, Butterworth4, Coefficients, HighPass4x32, Lanes};
use super::tilt::{tilt, LowBandError, Tilt, TiltFilter};
use crate::config::{CorrectionMode, SensorSettings};

/// Temperatures a sensor can report, °C; others never enter the tilt's temperature filter.
const PLAUSIBLE_TEMPERATURE_C: std::ops::RangeInclusive<f64> = -273.15..=1000.0;

/// Margin between the record's band edge and the detector's corner.
pub const FREQUENCY_MARGIN: f64 = 1.25;

/// Format of [`SensorKernel::checkpoint`]: changes whenever the kernel's state changes shape.
const CHECKPOINT_FORMAT: u8 = 4;

/// Content slower than this is the constant part of the signal (gravity, offsets, drift over
/// minutes), which every calibrated domain includes: the lower band check ignores it.
pub const CONSTANT_BELOW_HZ: f64 = 0.01;

/// Coverage factor stamped on uncalibrated batches, whose uncertainties are NaN anyway; the wire
/// format wants a positive number.
const UNCALIBRATED_COVERAGE: f32 = 2.0;

/// What a batch came to, for counters and the tilt stream.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct BatchOutcome {
    pub batch_flags: u16,
    pub mode: Mode,
    pub calibration_version: u64,
    /// Samples whose flags, with the batch's, are not zero.
    pub n_flagged: u32,
}

/// Filters designed for one sample rate and one calibration version.
///
/// A gateway keeps one per sensor, ten thousand of them, so what most sensors lack stays out
/// of line: the crossover (split mode only), the tilt low pass (inclinometers only) and the
/// detector's low pass (records with a lower band edge). What every calibrated sensor has, the
/// detector's high pass, stays inline.
#[derive(Debug, Clone, Serialize, Deserialize)]
struct Design {
    sample_rate_hz: f64,
    version: u64,
    crossover: Option<Box<Biquad3>>,
    detector: Option<Detector>,
    tilt: Option<Box<TiltFilter>>,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
struct Detector {
    high: Option<HighPass4x32>,
    low: Option<Box<LowBand>>,
    threshold_mps2: [f64; 3],
}

/// The varying content below the band: the constant part removed, then the low pass (none when
/// its corner cannot be realised: then all varying content is below the band).
///
/// The constant part is learned before anything is judged. A filter primed on the first sample
/// would take that instant's sway for the constant part and read it as slow content until it
/// decayed, tens of seconds at 0.01 Hz: measured, a strong sway against a band from 0.5 Hz was
/// flagged for up to 70 s after every start. So a cold detector first averages
/// [`LEARN_PERIODS`] periods of the band's lower edge (the mean of an in-band sway over T is
/// within `A/(π·f·T)` of the constant part), primes on that mean, and only then judges. A gap
/// or a node restart keeps what was learned: the constant part does not change across a gap,
/// and a filter at 0.01 Hz barely moves with a sway's phase jump. The low pass after it starts
/// again from zero (the mean of what it is fed) after the learning and after every gap, and is
/// judged only once its own start has faded ([`SETTLE_PERIODS`] periods of its corner): a
/// sine switched on at a random phase rings in it for a few seconds.
#[derive(Debug, Clone, Serialize, Deserialize)]
struct LowBand {
    constant: Biquad3,
    low: Option<Butterworth4>,
    /// Samples the constant part is learned over.
    learn_samples: u32,
    /// While learning: the sum of the finite samples so far and their count.
    learning: Option<([f64; 3], u32)>,
    /// Samples the low pass needs after a fresh start, and those still to go.
    settle_samples: u32,
    settling: u32,
}

/// Periods of the low pass's corner it runs unjudged after starting from zero.
const SETTLE_PERIODS: f64 = 2.0;

/// Periods of the band's lower edge a cold detector averages before judging content below it.
const LEARN_PERIODS: f64 = 20.0;

impl LowBand {
    #[inline(always)]
    fn step(&mut self, v: [f64; 3]) -> [f64; 3] {
        let y = self.constant.step(v);
        match self.low.as_mut() {
            Some(l) => l.step(y),
            None => y,
        }
    }

    /// Learns from a batch while the constant part is not known yet; true once it is (the
    /// batch that completes the learning is not judged).
    fn learned(&mut self, samples: impl Iterator<Item = [f64; 3]>) -> bool {
        if self.constant.is_primed() && self.learning.is_none() {
            return true;
        }
        let (mut sum, mut n) = self.learning.unwrap_or(([0.0; 3], 0));
        for v in samples {
            for k in 0..3 {
                sum[k] += v[k];
            }
            n += 1;
        }
        if n < self.learn_samples {
            self.learning = Some((sum, n));
            return false;
        }
        self.constant.prime(sum.map(|s| s / f64::from(n)));
        self.learning = None;
        self.restart_low();
        false
    }

    /// After a gap: the low pass starts again from zero; the constant part stays.
    fn discontinuity(&mut self) {
        if self.learning.is_none() && self.constant.is_primed() {
            self.restart_low();
        }
    }

    fn restart_low(&mut self) {
        if let Some(l) = self.low.as_mut() {
            l.prime([0.0; 3]);
            self.settling = self.settle_samples;
        }
    }

    /// Filters one sample; whether it is judged (the low pass has settled).
    #[inline(always)]
    fn judged_step(&mut self, v: [f64; 3]) -> Option<[f64; 3]> {
        let y = self.step(v);
        if self.settling > 0 {
            self.settling -= 1;
            return None;
        }
        Some(y)
    }
}

/// Low-passed outputs and flags since the last tilt estimate.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct TiltState {
    /// Low-passed raw outputs at the end of the last batch.
    pub output_lp: [f64; 3],
    pub flags: u16,
    /// The instant `output_lp` describes: the last sample's time less the filter's delay.
    pub timestamp_ns: i64,
    /// Once the low pass has settled from its start (see [`mod@super::tilt`]).
    pub ready: bool,
    pub low_band: LowBandError,
    /// The sensor's temperature through the tilt's low pass, for a record that corrects for
    /// it. Not checkpointed: the filter is, and every batch sets this from it.
    #[serde(skip)]
    pub temperature_c: Option<f64>,
}

impl TiltState {
    /// The tilt estimate from this state with `corrector`'s static set, taken to the
    /// low-passed temperature when the record models temperature.
    pub fn estimate(&self, corrector: &Corrector) -> Tilt {
        let base = corrector.set(SetKind::Static);
        let warm = self.temperature_c.and_then(|c| base.at_temperature(c));
        tilt(
            warm.as_ref().unwrap_or(base),
            self.output_lp,
            &self.low_band,
        )
    }
}

/// Per-sensor memory of the sample path.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct SensorKernel {
    settings: SensorSettings,
    design: Option<Design>,
    tilt: TiltState,
}

fn s_inv(set: &SetCorrector) -> [[f64; 3]; 3] {
    let cols = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]].map(|e| set.scale(e));
    let mut m = [[0.0; 3]; 3];
    for (j, col) in cols.iter().enumerate() {
        for (i, row) in m.iter_mut().enumerate() {
            row[j] = col[i];
        }
    }
    m
}

#[inline(always)]
fn to_f32(v: [f64; 3]) -> [f32; 3] {
    [v[0] as f32, v[1] as f32, v[2] as f32]
}

#[inline(always)]
fn finite(v: [f64; 3]) -> bool {
    v[0].is_finite() && v[1].is_finite() && v[2].is_finite()
}

const NAN3: [f32; 3] = [f32::NAN; 3];

impl SensorKernel {
    pub fn new(settings: SensorSettings) -> SensorKernel {
        SensorKernel {
            settings,
            design: None,
            tilt: TiltState {
                output_lp: [0.0; 3],
                flags: 0,
                timestamp_ns: 0,
                ready: false,
                low_band: LowBandError::default(),
                temperature_c: None,
            },
        }
    }

    pub fn settings(&self) -> &SensorSettings {
        &self.settings
    }

    /// Appends the kernel's whole state (settings, filter memory, designs) to `out`, for the
    /// history's checkpoints: a kernel restored from it corrects the batches that follow into
    /// the same bytes as this one does.
    pub fn checkpoint(&self, out: &mut Vec<u8>) {
        out.push(CHECKPOINT_FORMAT);
        // Serialising plain data into a Vec cannot fail.
        let bytes = postcard::to_allocvec(self).expect("kernel state serialises");
        out.extend_from_slice(&bytes);
    }

    /// A kernel as [`checkpoint`](Self::checkpoint) saved it; `None` if the bytes are not a
    /// checkpoint of this format (an older build's, or damage).
    pub fn restore(bytes: &[u8]) -> Option<SensorKernel> {
        match bytes.split_first() {
            Some((&CHECKPOINT_FORMAT, rest)) => postcard::from_bytes(rest).ok(),
            _ => None,
        }
    }

    /// Wire mode this sensor's batches carry when calibrated.
    pub fn mode(&self) -> Mode {
        self.settings.mode.wire()
    }

    /// State for the tilt stream; `ready` once a calibrated batch went through the low pass.
    pub fn tilt_state(&self) -> &TiltState {
        &self.tilt
    }

    /// Tells the kernel that samples were lost or the node restarted: the frequency detector's
    /// high band and the low pass of its lower band start afresh, so the jump between the old
    /// and the new signal is not taken for out-of-band content; the constant part it learned
    /// stays ([`LowBand`]). (The low passes keep their state: a jump fades from them smoothly.)
    pub fn discontinuity(&mut self) {
        if let Some(d) = self.design.as_mut().and_then(|d| d.detector.as_mut()) {
            if let Some(h) = d.high.as_mut() {
                h.reset();
            }
            if let Some(l) = d.low.as_mut() {
                l.discontinuity();
            }
        }
    }

    /// Clears the flags gathered for the next tilt estimate.
    pub fn tilt_published(&mut self) {
        self.tilt.flags = 0;
    }

    fn design_for<'d>(
        slot: &'d mut Option<Design>,
        s: &SensorSettings,
        sample_rate_hz: f64,
        corrector: &Corrector,
    ) -> &'d mut Design {
        let version = corrector.version();
        let fresh = match slot {
            Some(d) => d.sample_rate_hz != sample_rate_hz || d.version != version,
            None => true,
        };
        if fresh {
            // Keep filter memory when only the version changed at the same rate: a hot swap
            // must not restart the crossover or the tilt low pass.
            let keep = slot.take().filter(|d| d.sample_rate_hz == sample_rate_hz);
            let crossover = match s.mode {
                CorrectionMode::Split => {
                    keep.as_ref().and_then(|d| d.crossover.clone()).or_else(|| {
                        realisable(s.crossover_hz, sample_rate_hz).then(|| {
                            Box::new(Biquad3::new(Coefficients::low_pass(
                                s.crossover_hz,
                                sample_rate_hz,
                            )))
                        })
                    })
                }
                _ => None,
            };
            let tilt = if s.tilt {
                keep.as_ref().and_then(|d| d.tilt.clone()).or_else(|| {
                    realisable(s.tilt_cutoff_hz, sample_rate_hz)
                        .then(|| Box::new(TiltFilter::new(s.tilt_cutoff_hz, sample_rate_hz)))
                })
            } else {
                None
            };
            let detector = detector(s, corrector, sample_rate_hz);
            *slot = Some(Design {
                sample_rate_hz,
                version,
                crossover,
                detector,
                tilt,
            });
        }
        // Set just above when absent.
        slot.as_mut().expect("design was just made")
    }

    /// Corrects one batch into `out` (appended; `out` is not cleared).
    ///
    /// `corrector` is the snapshot in force for the whole batch (none: uncalibrated);
    /// `stream_flags` are the conditions found by the caller: batch-level ones (gap,
    /// duplicate) on the batch, others (`calibration_suspect`) on every sample;
    /// `scratch` is the caller's reusable working memory.
    pub fn correct_batch(
        &mut self,
        raw: &RawBatchView<'_>,
        corrector: Option<&Corrector>,
        stream_flags: u16,
        scratch: &mut Scratch,
        out: &mut Vec<u8>,
    ) -> BatchOutcome {
        match corrector {
            None => uncalibrated(raw, stream_flags, out),
            Some(c) => self.calibrated(raw, c, stream_flags, scratch, out),
        }
    }

    fn calibrated(
        &mut self,
        raw: &RawBatchView<'_>,
        c: &Corrector,
        stream_flags: u16,
        scratch: &mut Scratch,
        out: &mut Vec<u8>,
    ) -> BatchOutcome {
        let n = raw.len();
        let mode = self.settings.mode;
        let design = Self::design_for(
            &mut self.design,
            &self.settings,
            raw.header.sample_rate_hz,
            c,
        );
        // Separate passes over a decoded copy: each loop stays small enough for the compiler
        // to inline the correction and for the CPU to overlap consecutive samples.
        scratch.load(raw);

        // Start the low passes from the first batch's mean rather than its first sample, which
        // carries that instant's sway and would take several time constants to fade.
        let unprimed = design.tilt.as_ref().is_some_and(|f| !f.is_primed())
            || design.crossover.as_ref().is_some_and(|f| !f.is_primed());
        if unprimed {
            if let Some(mean) = mean_of_finite(&scratch.v) {
                if let Some(f) = design.crossover.as_mut().filter(|f| !f.is_primed()) {
                    f.prime(mean);
                }
                if let Some(f) = design.tilt.as_mut().filter(|f| !f.is_primed()) {
                    f.prime(mean);
                }
            }
        }

        // The caller's sample conditions (`calibration_suspect`) go on every sample.
        let mut common = stream_flags & !flags::BATCH_ONLY;
        if c.validity_at(raw.header.timestamp_ns) != Validity::Valid {
            common |= flags::CALIBRATION_EXPIRED;
        }
        // A duplicate is an old stretch of signal: it would corrupt the detector's memory.
        let in_sequence = stream_flags & flags::DUPLICATE == 0;
        if let Some(d) = design.detector.as_mut().filter(|_| in_sequence) {
            if d.out_of_band(&scratch.v, &mut scratch.lanes, band_sets(mode, c)) {
                common |= flags::OUTSIDE_FREQUENCY;
            }
        }
        let temperature_c = raw.temperature_c.map(f64::from);
        if let Some(t) = design.tilt.as_mut().filter(|_| in_sequence) {
            let mut last = None;
            for (i, v) in scratch.v.iter().enumerate().filter(|(_, v)| finite(**v)) {
                self.tilt.output_lp = t.step(*v);
                last = Some(i);
            }
            // A temperature no sensor can have (a hostile node's 1e38) would overflow the
            // filter's state and poison it for good: it is passed over, like a missing one.
            let temperature = temperature_c.filter(|t| PLAUSIBLE_TEMPERATURE_C.contains(t));
            if let (Some(temp), true) = (temperature, c.models_temperature()) {
                t.step_temperature(temp, n);
            }
            self.tilt.temperature_c = t.temperature_c();
            if let Some(i) = last {
                self.tilt.ready = t.settled();
                self.tilt.low_band = t.error();
                let at_ns = i as f64 / raw.header.sample_rate_hz * 1e9;
                self.tilt.timestamp_ns = raw
                    .header
                    .timestamp_ns
                    .saturating_add(at_ns as i64)
                    .saturating_sub(t.delay_ns());
            }
        }

        // Temperature: both sets taken to the batch's, when the record models it.
        let static_base = c.set(SetKind::Static);
        match static_base.temperature_check(temperature_c) {
            TemperatureCheck::Outside | TemperatureCheck::Missing => {
                common |= flags::OUTSIDE_TEMPERATURE
            }
            TemperatureCheck::Inside | TemperatureCheck::NotModelled => {}
        }
        let warm = temperature_c.and_then(|t| {
            Some((
                static_base.at_temperature(t)?,
                c.set(SetKind::Dynamic).at_temperature(t)?,
            ))
        });
        let (static_set, dynamic_set) = match &warm {
            Some((s, d)) => (s, d),
            None => (static_base, c.set(SetKind::Dynamic)),
        };
        // Corrected values and per-sample flags into the scratch arrays, and the batch's
        // coverage factor: the largest of its samples', so that every interval is at least
        // right.
        let coverage = match mode {
            CorrectionMode::Static | CorrectionMode::Dynamic => {
                let set = if mode == CorrectionMode::Static {
                    static_set
                } else {
                    dynamic_set
                };
                let coverage = if set.states_dof() {
                    let worst =
                        correct_all_with_dof(set, &scratch.v, &mut scratch.a, &mut scratch.u);
                    set.coverage_factor_at(1.0 / worst)
                } else {
                    correct_all(set, &scratch.v, &mut scratch.a, &mut scratch.u);
                    set.coverage_factor()
                };
                flag_all(c, set.domain().amplitude_max_mps2, scratch);
                coverage
            }
            CorrectionMode::Split => {
                // A duplicate is corrected through the crossover as it stands, which then
                // forgets it: old signal must not shift the low band of the live stream.
                let saved = design
                    .crossover
                    .as_deref()
                    .cloned()
                    .filter(|_| !in_sequence);
                // Without a realisable crossover everything is low band.
                for i in 0..n {
                    let v = scratch.v[i];
                    scratch.low[i] = match design.crossover.as_mut() {
                        Some(x) if finite(v) => x.step(v),
                        _ => v,
                    };
                }
                if let (Some(saved), Some(x)) = (saved, design.crossover.as_mut()) {
                    **x = saved;
                }
                let worst = split_all(static_set, dynamic_set, scratch);
                for i in 0..n {
                    if c.is_clipped(scratch.v[i]) {
                        scratch.f[i] |= flags::CLIPPED;
                    }
                }
                let nu = 1.0 / worst;
                static_set
                    .coverage_factor_at(nu)
                    .max(dynamic_set.coverage_factor_at(nu))
            }
        };

        let info = CorrectionInfo {
            calibration_version: c.version(),
            mode: mode.wire(),
            coverage_factor: coverage as f32,
        };
        let w = CorrectedBatchWriter::begin(out, &raw.header, info, n);
        let (batch_flags, n_flagged) = write_all(w, scratch, common, stream_flags);

        if self.settings.tilt && in_sequence {
            self.tilt.flags |= batch_flags;
        }
        BatchOutcome {
            batch_flags,
            mode: mode.wire(),
            calibration_version: c.version(),
            n_flagged,
        }
    }
}

/// Decoded samples and per-sample results of the batch in hand, reused from batch to batch so
/// the sample path allocates nothing once the largest batch has been seen. One per worker, not
/// per sensor: it holds nothing between batches.
#[derive(Debug, Clone, Default)]
pub struct Scratch {
    v: Vec<[f64; 3]>,
    low: Vec<[f64; 3]>,
    a: Vec<[f64; 3]>,
    u: Vec<[f64; 3]>,
    f: Vec<u16>,
    /// The frequency detector's f32 lanes.
    lanes: Vec<Lanes>,
}

impl Scratch {
    /// The last calibrated batch's corrected accelerations, m/s².
    pub fn corrected(&self) -> &[[f64; 3]] {
        &self.a
    }

    fn load(&mut self, raw: &RawBatchView<'_>) {
        let n = raw.len();
        raw.samples_f64_into(&mut self.v);
        for buf in [&mut self.low, &mut self.a, &mut self.u] {
            buf.resize(n, [0.0; 3]);
        }
        self.f.clear();
        self.f.resize(n, 0);
    }
}

/// The correction proper, over a whole batch. Kept apart so that the compiler inlines
/// `SetCorrector::correct` into a tight loop. Non-finite inputs give non-finite results, which
/// the caller replaces.
#[inline(never)]
fn correct_all(set: &SetCorrector, v: &[[f64; 3]], a: &mut [[f64; 3]], u: &mut [[f64; 3]]) {
    for ((v, a), u) in v.iter().zip(a.iter_mut()).zip(u.iter_mut()) {
        let r = set.correct(*v);
        *a = r.accel_mps2;
        *u = r.uncertainty_mps2;
    }
}

/// [`correct_all`] for a set that states degrees of freedom; returns the largest `1/ν_eff`
/// of the batch (0 when every contribution has infinitely many).
///
/// Per axis the constant part `c` and its Welch–Satterthwaite term `w` are the same for every
/// sample, so `ν_eff(p) = (p + c)² / (p²/ν_p + w)` depends on the sample only through its
/// parameter variance `p`, and `dν/dp ∝ (p + c)·(w − c·p/ν_p)`: it rises, then falls. Its
/// minimum over the batch is therefore at the smallest or the largest `p`, and the loop only
/// tracks those, which costs two comparisons per axis and sample instead of a ν each.
#[inline(never)]
fn correct_all_with_dof(
    set: &SetCorrector,
    v: &[[f64; 3]],
    a: &mut [[f64; 3]],
    u: &mut [[f64; 3]],
) -> f64 {
    let mut low = [f64::INFINITY; 3];
    let mut high = [f64::NEG_INFINITY; 3];
    for ((v, a), u) in v.iter().zip(a.iter_mut()).zip(u.iter_mut()) {
        let (accel, var) = set.correct_variance(*v);
        *a = accel;
        for k in 0..3 {
            // Round-off can take a zero variance a hair below zero.
            u[k] = var[k].max(0.0).sqrt();
            // NaN (a non-finite sample) compares false and is passed over.
            low[k] = if var[k] < low[k] { var[k] } else { low[k] };
            high[k] = if var[k] > high[k] { var[k] } else { high[k] };
        }
    }
    let c = set.constant_variance();
    let w = set.constant_ws();
    let inv_p = set.inverse_dof().parameters;
    let mut worst: f64 = 0.0;
    for k in 0..3 {
        for var in [low[k], high[k]].into_iter().filter(|v| v.is_finite()) {
            let p = (var - c[k]).max(0.0);
            let ratio = (p * p * inv_p + w[k]) / (var * var);
            // NaN (a zero variance) is passed over by `max`.
            worst = worst.max(ratio);
        }
    }
    worst
}

/// Per-sample flags of static or dynamic mode: clipped outputs, and accelerations above the
/// set's amplitude domain.
#[inline(never)]
fn flag_all(c: &Corrector, amplitude_max_mps2: f64, s: &mut Scratch) {
    for ((f, v), a) in s.f.iter_mut().zip(&s.v).zip(&s.a) {
        let mut bits = 0;
        if c.is_clipped(*v) {
            bits |= flags::CLIPPED;
        }
        if a.iter().any(|a| a.abs() > amplitude_max_mps2) {
            bits |= flags::OUTSIDE_AMPLITUDE;
        }
        *f = bits;
    }
}

/// Writes the samples with their flags and those common to the batch (`common` on every
/// sample, `stream_flags` on the batch); returns the batch's flags and how many samples carry
/// any.
#[inline(never)]
fn write_all(
    mut w: CorrectedBatchWriter<'_>,
    s: &Scratch,
    common: u16,
    stream_flags: u16,
) -> (u16, u32) {
    let mut union = common;
    let mut n_flagged = 0u32;
    for (((v, a), u), f) in s.v.iter().zip(&s.a).zip(&s.u).zip(&s.f) {
        let sample = if finite(*v) {
            CorrectedSample {
                accel_mps2: to_f32(*a),
                uncertainty_mps2: to_f32(*u),
                flags: common | f,
            }
        } else {
            CorrectedSample {
                accel_mps2: NAN3,
                uncertainty_mps2: NAN3,
                flags: common | flags::NON_FINITE_INPUT,
            }
        };
        union |= sample.flags;
        n_flagged += u32::from((sample.flags | stream_flags) != 0);
        w.push(&sample);
    }
    let batch_flags = union | stream_flags;
    w.finish(batch_flags);
    (batch_flags, n_flagged)
}

/// Split mode over a whole batch, from `scratch.v` and its low band `scratch.low`. Returns the
/// largest `1/ν_eff` of the batch, as [`correct_all_with_dof`] does (0 when neither set states
/// degrees of freedom).
#[inline(never)]
fn split_all(static_set: &SetCorrector, dynamic_set: &SetCorrector, s: &mut Scratch) -> f64 {
    let amp_s = static_set.domain().amplitude_max_mps2;
    let amp_d = dynamic_set.domain().amplitude_max_mps2;
    let const_s = static_set.constant_variance();
    let const_d = dynamic_set.constant_variance();
    // Constant part counted once: the larger of the two sets' statements, with its ν.
    let extra = [0, 1, 2].map(|k| (const_d[k] - const_s[k]).max(0.0));
    let (ws_s, ws_d) = (static_set.constant_ws(), dynamic_set.constant_ws());
    let const_ws = [0, 1, 2].map(|k| {
        if const_d[k] > const_s[k] {
            ws_d[k]
        } else {
            ws_s[k]
        }
    });
    let inv_s = static_set.inverse_dof().parameters;
    let inv_d = dynamic_set.inverse_dof().parameters;
    let mut worst: f64 = 0.0;
    for i in 0..s.v.len() {
        let (v, low) = (s.v[i], s.low[i]);
        let high = [v[0] - low[0], v[1] - low[1], v[2] - low[2]];
        let (al, var_l) = static_set.correct_variance(low);
        let ah = dynamic_set.scale(high);
        let vh = dynamic_set.scale_param_variance(high);
        let mut f = 0;
        for k in 0..3 {
            s.a[i][k] = al[k] + ah[k];
            // Round-off can take a zero variance a hair below zero.
            let var = var_l[k].max(0.0) + vh[k] + extra[k];
            s.u[i][k] = var.sqrt();
            let param_s = (var_l[k] - const_s[k]).max(0.0);
            let ws = param_s * param_s * inv_s + vh[k] * vh[k] * inv_d + const_ws[k];
            worst = worst.max(ws / (var * var));
            if al[k].abs() > amp_s || ah[k].abs() > amp_d {
                f |= flags::OUTSIDE_AMPLITUDE;
            }
        }
        s.f[i] = f;
    }
    worst
}

/// Mean of the finite samples.
fn mean_of_finite(v: &[[f64; 3]]) -> Option<[f64; 3]> {
    let mut sum = [0.0; 3];
    let mut n = 0usize;
    for v in v.iter().filter(|v| finite(**v)) {
        for k in 0..3 {
            sum[k] += v[k];
        }
        n += 1;
    }
    (n > 0).then(|| sum.map(|s| s / n as f64))
}

fn uncalibrated(raw: &RawBatchView<'_>, stream_flags: u16, out: &mut Vec<u8>) -> BatchOutcome {
    let n = raw.len();
    let info = CorrectionInfo {
        calibration_version: 0,
        mode: Mode::None,
        coverage_factor: UNCALIBRATED_COVERAGE,
    };
    let mut w = CorrectedBatchWriter::begin(out, &raw.header, info, n);
    let mut union = flags::UNCALIBRATED;
    for i in 0..n {
        let v = raw.sample(i);
        let mut f = flags::UNCALIBRATED;
        let accel_mps2 = if v.iter().all(|x| x.is_finite()) {
            v
        } else {
            f |= flags::NON_FINITE_INPUT;
            NAN3
        };
        union |= f;
        w.push(&CorrectedSample {
            accel_mps2,
            uncertainty_mps2: NAN3,
            flags: f,
        });
    }
    let batch_flags = union | stream_flags;
    w.finish(batch_flags);
    BatchOutcome {
        batch_flags,
        mode: Mode::None,
        calibration_version: 0,
        n_flagged: n as u32,
    }
}

/// The sets whose band edges the detector checks, low edge first: in split mode the static
/// set's lower edge and the dynamic set's upper one.
fn band_sets(mode: CorrectionMode, c: &Corrector) -> (&SetCorrector, &SetCorrector) {
    match mode {
        CorrectionMode::Static => (c.set(SetKind::Static), c.set(SetKind::Static)),
        CorrectionMode::Dynamic => (c.set(SetKind::Dynamic), c.set(SetKind::Dynamic)),
        CorrectionMode::Split => (c.set(SetKind::Static), c.set(SetKind::Dynamic)),
    }
}

fn detector(s: &SensorSettings, c: &Corrector, sample_rate_hz: f64) -> Option<Detector> {
    let (low_set, high_set) = band_sets(s.mode, c);
    let high_hz = high_set.domain().frequency_max_hz * FREQUENCY_MARGIN;
    let low_hz = low_set.domain().frequency_min_hz / FREQUENCY_MARGIN;
    let high =
        realisable(high_hz, sample_rate_hz).then(|| HighPass4x32::new(high_hz, sample_rate_hz));
    let constant_hz = CONSTANT_BELOW_HZ.min(low_hz / 10.0);
    let low = (low_set.domain().frequency_min_hz > 0.0 && realisable(constant_hz, sample_rate_hz))
        .then(|| {
            Box::new(LowBand {
                constant: Biquad3::new(Coefficients::high_pass(constant_hz, sample_rate_hz)),
                low: realisable(low_hz, sample_rate_hz)
                    .then(|| Butterworth4::low_pass(low_hz, sample_rate_hz)),
                learn_samples: (LEARN_PERIODS * sample_rate_hz / low_set.domain().frequency_min_hz)
                    .ceil()
                    .clamp(1.0, f64::from(u32::MAX)) as u32,
                learning: None,
                settle_samples: if realisable(low_hz, sample_rate_hz) {
                    (SETTLE_PERIODS * sample_rate_hz / low_hz).ceil() as u32
                } else {
                    0
                },
                settling: 0,
            })
        });
    if high.is_none() && low.is_none() {
        return None;
    }
    let threshold_mps2 = [0, 1, 2].map(|k| {
        let set_u = |set: &SetCorrector| {
            let var = set.constant_variance()[k];
            let nu = var * var / set.constant_ws()[k];
            set.coverage_factor_at(nu) * var.sqrt()
        };
        set_u(low_set)
            .max(set_u(high_set))
            .max(s.frequency_floor_mps2)
    });
    Some(Detector {
        high,
        low,
        threshold_mps2,
    })
}

/// Second moments of filtered outputs, upper triangle: xx, yy, zz, xy, xz, yz.
#[derive(Default)]
struct Moments([f64; 6]);

impl Moments {
    #[inline(always)]
    fn add(&mut self, y: [f64; 3]) {
        let m = &mut self.0;
        m[0] += y[0] * y[0];
        m[1] += y[1] * y[1];
        m[2] += y[2] * y[2];
        m[3] += y[0] * y[1];
        m[4] += y[0] * y[2];
        m[5] += y[1] * y[2];
    }

    /// Whether the mean square of `S⁻¹·y` exceeds `threshold²` on any axis.
    fn exceeds(&self, n: usize, s_inv: &[[f64; 3]; 3], threshold: &[f64; 3]) -> bool {
        if n == 0 {
            return false;
        }
        let m = &self.0;
        let full = [[m[0], m[3], m[4]], [m[3], m[1], m[5]], [m[4], m[5], m[2]]];
        (0..3).any(|k| {
            let mut ms = 0.0;
            for i in 0..3 {
                for j in 0..3 {
                    ms += s_inv[k][i] * s_inv[k][j] * full[i][j];
                }
            }
            ms / n as f64 > threshold[k] * threshold[k]
        })
    }
}

impl Detector {
    /// `sets`: the sets whose `S⁻¹` maps the low and the high band to m/s², from
    /// [`band_sets`] of the corrector the detector was designed for.
    #[inline(never)]
    fn out_of_band(
        &mut self,
        samples: &[[f64; 3]],
        lanes: &mut Vec<Lanes>,
        (low_set, high_set): (&SetCorrector, &SetCorrector),
    ) -> bool {
        let finite_samples = || samples.iter().copied().filter(|v| finite(*v));
        // The high band in f32 lanes, in separate passes that each compile to a short loop:
        // narrow, filter, then the second moments (squares, and the cross products xy, xz, yz).
        let mut squares: Lanes = [0.0; 4];
        let mut products: Lanes = [0.0; 4];
        let mut n = 0usize;
        if let Some(h) = self.high.as_mut() {
            lanes.clear();
            lanes.extend(finite_samples().map(|v| [v[0] as f32, v[1] as f32, v[2] as f32, 0.0]));
            h.filter_in_place(lanes);
            for y in lanes.iter() {
                let (p, q) = ([y[0], y[0], y[1], 0.0], [y[1], y[2], y[2], 0.0]);
                for k in 0..4 {
                    squares[k] += y[k] * y[k];
                    products[k] += p[k] * q[k];
                }
            }
            n = lanes.len();
        }
        let mut low = Moments::default();
        let mut low_judged = false;
        if let Some(l) = self.low.as_mut() {
            if l.learned(finite_samples()) {
                n = 0;
                for v in finite_samples() {
                    if let Some(y) = l.judged_step(v) {
                        low.add(y);
                        n += 1;
                    }
                }
                low_judged = n > 0;
            }
        }
        let high = Moments(
            [
                squares[0],
                squares[1],
                squares[2],
                products[0],
                products[1],
                products[2],
            ]
            .map(f64::from),
        );
        (self.high.is_some() && high.exceeds(n, &s_inv(high_set), &self.threshold_mps2))
            || (low_judged && low.exceeds(n, &s_inv(low_set), &self.threshold_mps2))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::f64::consts::PI;
    use triax_protocol::batch::{BatchHeader, CorrectedBatch, RawBatch};
    use triax_protocol::record::sample;
    use triax_protocol::SensorId;

    fn settings(mode: CorrectionMode) -> SensorSettings {
        SensorSettings {
            mode,
            ..SensorSettings::default()
        }
    }

    fn batch(seq: u64, samples: Vec<[f32; 3]>) -> Vec<u8> {
        RawBatch {
            header: BatchHeader {
                sensor_id: SensorId::new("k").unwrap(),
                sequence: seq,
                timestamp_ns: 1_800_000_000_000_000_000 + seq as i64 * 500_000_000,
                sample_rate_hz: 100.0,
            },
            temperature_c: None,
            samples,
        }
        .encode()
    }

    /// Outputs a sensor with the record's own static S and q gives for acceleration `a`.
    fn outputs_for(record: &triax_protocol::CalibrationRecord, a: [f64; 3]) -> [f32; 3] {
        let s = record.static_set.sensitivity;
        let q = record.static_set.offset;
        let d = [a[0] - q[0], a[1] - q[1], a[2] - q[2]];
        [0, 1, 2].map(|i| (s[i][0] * d[0] + s[i][1] * d[1] + s[i][2] * d[2]) as f32)
    }

    fn run(k: &mut SensorKernel, c: Option<&Corrector>, bytes: &[u8]) -> CorrectedBatch {
        let view = RawBatchView::parse(bytes).unwrap();
        let mut out = Vec::new();
        k.correct_batch(&view, c, 0, &mut Scratch::default(), &mut out);
        CorrectedBatch::decode(&out).unwrap()
    }

    #[test]
    fn static_mode_recovers_the_acceleration() {
        let r = sample::record("k", 3);
        let c = Corrector::from_record(&r).unwrap();
        let mut k = SensorKernel::new(settings(CorrectionMode::Static));
        let v = outputs_for(&r, [0.3, -0.2, 9.81]);
        let out = run(&mut k, Some(&c), &batch(0, vec![v; 50]));
        assert_eq!(out.info.mode, Mode::Static);
        assert_eq!(out.info.calibration_version, 3);
        assert_eq!(out.batch_flags, 0);
        let s = out.samples[10];
        for (a, t) in s.accel_mps2.iter().zip([0.3, -0.2, 9.81]) {
            assert!((f64::from(*a) - t).abs() < 1e-4, "{s:?}");
        }
        assert!(s.uncertainty_mps2.iter().all(|u| *u > 0.0 && *u < 0.1));
    }

    /// The batch's k is Student's t at the smallest Welch–Satterthwaite ν of its samples: an
    /// offset variance of 1e-4 m²/s⁴ with ν = 6 alone gives t₆ = 2.447; adding output noise of
    /// the same variance with ν = ∞ gives ν = (2e-4)² / (1e-8/6) = 24, t₂₄ = 2.064.
    #[test]
    fn coverage_factor_follows_the_effective_degrees_of_freedom() {
        let mut r = sample::record("k", 1);
        r.static_set.sensitivity = [[0.1, 0.0, 0.0], [0.0, 0.1, 0.0], [0.0, 0.0, 0.1]];
        r.static_set.uncertainty_mps2 = [0.0; 3];
        // The same offset variance on every axis: a record that leaves an axis with no
        // uncertainty at all is refused.
        let mut cov = [[0.0; 12]; 12];
        for (i, row) in cov.iter_mut().enumerate().skip(9) {
            row[i] = 1e-4;
        }
        r.static_set.covariance = Some(Box::new(cov));
        r.static_set.covariance_dof = Some(6.0);
        r.sensor.output_noise = None;
        let k_of = |r: &triax_protocol::CalibrationRecord| {
            let c = Corrector::from_record(r).unwrap();
            let mut k = SensorKernel::new(settings(CorrectionMode::Static));
            let v = outputs_for(r, [0.3, -0.2, 9.81]);
            let mut samples = vec![v; 20];
            samples[3] = [f32::NAN; 3];
            run(&mut k, Some(&c), &batch(0, samples))
                .info
                .coverage_factor
        };
        assert!((k_of(&r) - 2.447).abs() < 1e-3, "{}", k_of(&r));
        // Noise of 0.001 V through S⁻¹ = 10: 0.01 m/s², variance 1e-4 on every axis.
        r.sensor.output_noise = Some([0.001; 3]);
        assert!((k_of(&r) - 2.064).abs() < 1e-3, "{}", k_of(&r));
        // Without stated ν the record's own factor stands.
        r.static_set.covariance_dof = None;
        assert_eq!(k_of(&r), 2.0);
    }

    /// The batch's smallest ν found from the extremes of the parameter variance equals the
    /// smallest of every sample's own ν, over random covariances, degrees of freedom and
    /// samples spread over the sphere.
    #[test]
    fn extremes_give_the_batch_its_smallest_dof() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand::rngs::StdRng::seed_from_u64(5);
        for _ in 0..200 {
            let mut r = sample::record("k", 1);
            let mut cov = [[0.0; 12]; 12];
            let scale: Vec<f64> = (0..12)
                .map(|_| 10f64.powf(rng.gen_range(-9.0..-4.0)))
                .collect();
            for i in 0..12 {
                for j in 0..12 {
                    // exp(−|i−j|/2) correlations: positive definite.
                    cov[i][j] =
                        (scale[i] * scale[j]).sqrt() * (-((i as f64 - j as f64).abs()) / 2.0).exp();
                }
            }
            r.static_set.covariance = Some(Box::new(cov));
            r.static_set.covariance_dof = Some(rng.gen_range(1.0..30.0));
            r.static_set.uncertainty_dof = Some(rng.gen_range(1.0..100.0));
            r.sensor.output_noise = Some([rng.gen_range(1e-5..1e-2); 3]);
            r.sensor.output_noise_dof = Some(rng.gen_range(1.0..1000.0));
            let c = Corrector::from_record(&r).unwrap();
            let set = c.set(SetKind::Static);
            let v: Vec<[f64; 3]> = (0..50)
                .map(|_| [0, 1, 2].map(|_| rng.gen_range(-1.2..1.2)))
                .collect();
            let (mut a, mut u) = (vec![[0.0; 3]; 50], vec![[0.0; 3]; 50]);
            let worst = correct_all_with_dof(set, &v, &mut a, &mut u);
            let brute = v
                .iter()
                .flat_map(|v| {
                    let (_, var, ws) = set.correct_with_dof(*v);
                    (0..3).map(move |k| ws[k] / (var[k] * var[k]))
                })
                .fold(0.0, f64::max);
            assert!(
                (worst - brute).abs() <= 1e-9 * brute,
                "{worst} against {brute}"
            );
        }
    }

    /// A record with an offset drift of 0.01 m/s²/°C on x around 20 °C, calibrated over
    /// 10–30 °C: at 25 °C x reads 0.05 m/s² more than at 20 °C, unflagged; at 35 °C it is
    /// extrapolated and flagged; with no temperature it is not corrected for it, and flagged.
    #[test]
    fn temperature_is_corrected_and_flagged_outside_its_range() {
        use triax_protocol::record::TemperatureModel;
        let mut r = sample::record("k", 1);
        r.temperature = Some(TemperatureModel {
            reference_c: 20.0,
            range_c: [10.0, 30.0],
            offset_mps2_per_c: [0.01, 0.0, 0.0],
            gain_per_c: None,
            covariance: [[0.0; 6]; 6],
            covariance_dof: None,
        });
        let c = Corrector::from_record(&r).unwrap();
        let v = outputs_for(&r, [0.3, -0.2, 9.81]);
        let at = |seq: u64, t: Option<f32>| {
            let bytes = RawBatch {
                temperature_c: t,
                ..RawBatch::decode(&batch(seq, vec![v; 10])).unwrap()
            }
            .encode();
            let mut k = SensorKernel::new(settings(CorrectionMode::Static));
            run(&mut k, Some(&c), &bytes)
        };
        let reference = at(0, Some(20.0));
        assert_eq!(reference.batch_flags, 0);
        assert!((reference.samples[0].accel_mps2[0] - 0.3).abs() < 1e-5);
        let warm = at(1, Some(25.0));
        assert_eq!(warm.batch_flags, 0);
        let shift = warm.samples[0].accel_mps2[0] - reference.samples[0].accel_mps2[0];
        assert!((shift - 0.05).abs() < 1e-5, "{shift}");
        let hot = at(2, Some(35.0));
        assert_eq!(hot.batch_flags, flags::OUTSIDE_TEMPERATURE);
        assert_eq!(hot.samples[3].flags, flags::OUTSIDE_TEMPERATURE);
        assert!((hot.samples[0].accel_mps2[0] - 0.45).abs() < 1e-5);
        let unknown = at(3, None);
        assert_eq!(unknown.batch_flags, flags::OUTSIDE_TEMPERATURE);
        assert_eq!(
            unknown.samples[0].accel_mps2,
            reference.samples[0].accel_mps2
        );
    }

    #[test]
    fn uncalibrated_and_non_finite_are_flagged() {
        let mut k = SensorKernel::new(settings(CorrectionMode::Dynamic));
        let out = run(
            &mut k,
            None,
            &batch(0, vec![[1.0, 2.0, 3.0], [f32::NAN, 0.0, 0.0]]),
        );
        assert_eq!(out.info.mode, Mode::None);
        assert_eq!(out.info.calibration_version, 0);
        assert_eq!(out.samples[0].accel_mps2, [1.0, 2.0, 3.0]);
        assert!(out.samples[0].uncertainty_mps2[0].is_nan());
        assert_eq!(
            out.batch_flags,
            flags::UNCALIBRATED | flags::NON_FINITE_INPUT
        );

        let r = sample::record("k", 1);
        let c = Corrector::from_record(&r).unwrap();
        let out = run(
            &mut k,
            Some(&c),
            &batch(1, vec![[1.0, 0.0, 0.0], [f32::INFINITY, 0.0, 0.0]]),
        );
        assert_eq!(out.samples[0].flags, 0);
        assert_eq!(out.samples[1].flags, flags::NON_FINITE_INPUT);
        assert!(out.samples[1].accel_mps2[0].is_nan());
    }

    #[test]
    fn split_reconstructs_when_sets_agree_and_uncertainty_combines() {
        let mut r = sample::record("k", 1);
        r.dynamic = r.static_set.clone();
        let c = Corrector::from_record(&r).unwrap();
        let mut k = SensorKernel::new(SensorSettings {
            crossover_hz: 0.5,
            ..settings(CorrectionMode::Split)
        });
        let mut s = Vec::new();
        for i in 0..500 {
            let t = i as f64 / 100.0;
            s.push(outputs_for(
                &r,
                [0.5 * (2.0 * PI * 2.0 * t).sin(), 0.1, 9.81],
            ));
        }
        let out = run(&mut k, Some(&c), &batch(0, s));
        for (i, x) in out.samples.iter().enumerate() {
            let t = i as f64 / 100.0;
            let truth = 0.5 * (2.0 * PI * 2.0 * t).sin();
            assert!((f64::from(x.accel_mps2[0]) - truth).abs() < 1e-4, "{i}");
            // With equal sets the combined uncertainty is at least the constant part and close
            // to the single-set figure.
            let single = c
                .set(SetKind::Static)
                .correct(outputs_for(&r, [truth, 0.1, 9.81]).map(f64::from));
            let u = f64::from(x.uncertainty_mps2[0]);
            assert!(
                u >= single.uncertainty_mps2[0] * 0.999 && u < single.uncertainty_mps2[0] * 1.5
            );
        }
    }

    /// A duplicate batch is old signal: it must leave the crossover and the tilt low pass as
    /// they were, so the live stream after it is corrected exactly as without it.
    #[test]
    fn duplicates_leave_filter_memory_untouched() {
        let r = sample::record("k", 1);
        let c = Corrector::from_record(&r).unwrap();
        let tilting = SensorSettings {
            crossover_hz: 0.5,
            tilt: true,
            ..settings(CorrectionMode::Split)
        };
        let wave = |seq: u64, amp: f64| -> Vec<[f32; 3]> {
            (0..50)
                .map(|i| {
                    let t = (seq as f64 * 50.0 + i as f64) / 100.0;
                    outputs_for(&r, [amp * (2.0 * PI * 0.3 * t).sin(), 0.2, 9.81])
                })
                .collect()
        };
        let step = |k: &mut SensorKernel, bytes: &[u8], stream_flags: u16| {
            let view = RawBatchView::parse(bytes).unwrap();
            let mut out = Vec::new();
            k.correct_batch(
                &view,
                Some(&c),
                stream_flags,
                &mut Scratch::default(),
                &mut out,
            );
            CorrectedBatch::decode(&out).unwrap()
        };
        let mut clean = SensorKernel::new(tilting.clone());
        let mut with_dup = SensorKernel::new(tilting);
        for k in [&mut clean, &mut with_dup] {
            step(k, &batch(0, wave(0, 1.0)), 0);
        }
        // An old batch, with very different signal, arrives again.
        let dup = step(&mut with_dup, &batch(0, wave(7, 5.0)), flags::DUPLICATE);
        assert_eq!(dup.batch_flags & flags::DUPLICATE, flags::DUPLICATE);
        let a = step(&mut clean, &batch(1, wave(1, 1.0)), 0);
        let b = step(&mut with_dup, &batch(1, wave(1, 1.0)), 0);
        assert_eq!(a, b);
        assert_eq!(clean.tilt_state(), with_dup.tilt_state());
    }

    #[test]
    fn frequency_detector_flags_out_of_band_and_ignores_sway_and_noise() {
        let r = sample::record("k", 1); // band 0..10 Hz
        let c = Corrector::from_record(&r).unwrap();
        let make = |seq: u64, f_hz: f64, amp: f64| -> Vec<[f32; 3]> {
            (0..50)
                .map(|i| {
                    let t = (seq as f64 * 50.0 + i as f64) / 100.0;
                    outputs_for(&r, [amp * (2.0 * PI * f_hz * t).sin(), 0.0, 9.81])
                })
                .collect()
        };
        let mut k = SensorKernel::new(settings(CorrectionMode::Dynamic));
        // Warm up the detector state over several batches, as in a stream.
        let mut last = 0;
        for seq in 0..6 {
            last = run(&mut k, Some(&c), &batch(seq, make(seq, 3.0, 1.0))).batch_flags;
        }
        assert_eq!(last & flags::OUTSIDE_FREQUENCY, 0, "3 Hz sway is in band");
        let mut k = SensorKernel::new(settings(CorrectionMode::Dynamic));
        for seq in 0..6 {
            last = run(&mut k, Some(&c), &batch(seq, make(seq, 30.0, 0.5))).batch_flags;
        }
        assert_ne!(
            last & flags::OUTSIDE_FREQUENCY,
            0,
            "30 Hz vibration is out of band"
        );

        // Batches 4 to 6 lost: the jump across them is not out-of-band content.
        for reset in [false, true] {
            let mut k = SensorKernel::new(settings(CorrectionMode::Dynamic));
            for seq in 0..4 {
                run(&mut k, Some(&c), &batch(seq, make(seq, 3.0, 1.0)));
            }
            if reset {
                k.discontinuity();
            }
            let f = run(&mut k, Some(&c), &batch(7, make(7, 3.3, 1.0))).batch_flags;
            assert_eq!(
                f & flags::OUTSIDE_FREQUENCY != 0,
                !reset,
                "reset {reset}: {:?}",
                flags::names(f)
            );
        }
    }

    /// A split-mode inclinometer whose record has a lower band edge: every filter the kernel
    /// has (crossover, tilt low pass, detector high pass and low band), after a few batches.
    fn busy_kernel() -> (SensorKernel, Corrector, triax_protocol::CalibrationRecord) {
        let mut r = sample::record("k", 1);
        r.dynamic.domain.frequency_min_hz = 0.5;
        // Split mode judges the lower edge on the static set.
        r.static_set.domain.frequency_min_hz = 0.5;
        let c = Corrector::from_record(&r).unwrap();
        let mut k = SensorKernel::new(SensorSettings {
            mode: CorrectionMode::Split,
            tilt: true,
            ..SensorSettings::default()
        });
        for seq in 0..5 {
            let samples = (0..50)
                .map(|i| {
                    let t = (seq * 50 + i) as f64 / 100.0;
                    outputs_for(&r, [0.3 * (2.0 * PI * 1.7 * t).sin(), 0.1, 9.81])
                })
                .collect();
            run(&mut k, Some(&c), &batch(seq, samples));
        }
        (k, c, r)
    }

    #[test]
    fn a_restored_checkpoint_corrects_the_same_bytes() {
        let (mut live, c, r) = busy_kernel();
        let mut ck = Vec::new();
        live.checkpoint(&mut ck);
        let mut restored = SensorKernel::restore(&ck).expect("restores");
        for seq in 5..40 {
            let samples: Vec<[f32; 3]> = (0..50)
                .map(|i| {
                    let t = (seq * 50 + i) as f64 / 100.0;
                    outputs_for(&r, [0.3 * (2.0 * PI * 1.7 * t).sin() + 0.2, 0.1, 9.81])
                })
                .collect();
            let b = batch(seq, samples);
            assert_eq!(
                run(&mut live, Some(&c), &b),
                run(&mut restored, Some(&c), &b)
            );
        }
        assert!(SensorKernel::restore(&ck[1..]).is_none(), "no format byte");
        assert!(SensorKernel::restore(&[]).is_none());
        assert!(SensorKernel::restore(&[CHECKPOINT_FORMAT, 0xff, 0xff]).is_none());
    }

    /// The checkpoint's layout is pinned: a kernel whose state changes shape must bump
    /// `CHECKPOINT_FORMAT`, or a replay would restore an older build's checkpoint as garbage.
    #[test]
    fn checkpoint_format_is_pinned() {
        let (k, _, _) = busy_kernel();
        let mut ck = Vec::new();
        k.checkpoint(&mut ck);
        let fnv = ck.iter().fold(0xcbf2_9ce4_8422_2325u64, |h, &b| {
            (h ^ u64::from(b)).wrapping_mul(0x0100_0000_01b3)
        });
        assert_eq!(
            (ck.len(), fnv),
            (PINNED_CHECKPOINT.0, PINNED_CHECKPOINT.1),
            "the kernel's checkpoint changed: bump CHECKPOINT_FORMAT, then pin the new layout"
        );
    }

    /// Length and FNV-1a of `busy_kernel`'s checkpoint in format [`CHECKPOINT_FORMAT`].
    const PINNED_CHECKPOINT: (usize, u64) = (988, 9_801_623_617_474_518_254);

    /// A strong in-band sway against a band from 0.5 Hz, the stream starting at any phase of
    /// it, and again after gaps: never flagged, neither while the constant part is learned
    /// nor after (a detector primed on the first sample flagged it for up to 70 s).
    #[test]
    fn a_cold_start_mid_sway_is_not_content_below_the_band() {
        let mut r = sample::record("k", 1);
        r.dynamic.domain.frequency_min_hz = 0.5;
        let c = Corrector::from_record(&r).unwrap();
        for p in 0..16 {
            let phase = f64::from(p) / 16.0 * 2.0 * PI;
            let mut k = SensorKernel::new(settings(CorrectionMode::Dynamic));
            let mut flagged = Vec::new();
            for seq in 0..400u64 {
                // Batches 200 to 204 lost.
                if (200..205).contains(&seq) {
                    continue;
                }
                if seq == 205 {
                    k.discontinuity();
                }
                let samples = (0..50)
                    .map(|i| {
                        let t = (seq as f64 * 50.0 + f64::from(i)) / 100.0;
                        outputs_for(&r, [0.5 * (2.0 * PI * 1.3 * t + phase).sin(), 0.0, 9.81])
                    })
                    .collect();
                let f = run(&mut k, Some(&c), &batch(seq, samples)).batch_flags;
                if f & flags::OUTSIDE_FREQUENCY != 0 {
                    flagged.push(seq);
                }
            }
            assert!(
                flagged.is_empty(),
                "phase {p}/16: batches {flagged:?} flagged"
            );
        }
    }

    #[test]
    fn content_below_the_band_is_flagged_and_gravity_is_not() {
        // Dynamic band `min..5000` Hz, sampled at 100 Hz (`batch` is 100 Hz).
        let run_band = |min_hz: f64, f_hz: f64, amp: f64| -> u16 {
            let mut r = sample::record("k", 1);
            r.dynamic.domain.frequency_min_hz = min_hz;
            r.dynamic.domain.frequency_max_hz = 5000.0;
            let c = Corrector::from_record(&r).unwrap();
            let mut k = SensorKernel::new(settings(CorrectionMode::Dynamic));
            let mut last = 0;
            // Past the constant part's learning: 20 periods of the lower edge (40 s at 0.5 Hz).
            for seq in 0..100 {
                let samples = (0..50)
                    .map(|i| {
                        let t = (seq as f64 * 50.0 + i as f64) / 100.0;
                        outputs_for(&r, [amp * (2.0 * PI * f_hz * t).sin(), 0.0, 9.81])
                    })
                    .collect();
                last = run(&mut k, Some(&c), &batch(seq, samples)).batch_flags;
            }
            last & flags::OUTSIDE_FREQUENCY
        };
        // Every lower edge the stream cannot realise, and one it can: a 2 Hz sway lies below.
        for min_hz in [60.0, 70.0, 1000.0, 20.0] {
            assert_ne!(run_band(min_hz, 2.0, 0.5), 0, "2 Hz sway below {min_hz} Hz");
        }
        // Gravity alone, with a lower edge: the constant part is inside every domain.
        for min_hz in [0.5, 20.0, 60.0] {
            assert_eq!(
                run_band(min_hz, 2.0, 0.0),
                0,
                "gravity, band from {min_hz} Hz"
            );
        }
        // In band.
        assert_eq!(run_band(0.5, 2.0, 0.5), 0, "2 Hz sway in 0.5–5000 Hz");
        // A slow sway below a 0.5 Hz edge.
        assert_ne!(run_band(0.5, 0.1, 0.5), 0, "0.1 Hz sway below 0.5 Hz");
    }

    #[test]
    fn expiry_clipping_and_amplitude() {
        let mut r = sample::record("k", 1);
        r.valid_until = Some(r.valid_from + time::Duration::days(1));
        r.sensor.output_full_scale = Some(2.0);
        let c = Corrector::from_record(&r).unwrap();
        let mut k = SensorKernel::new(settings(CorrectionMode::Static));
        let out = run(&mut k, Some(&c), &batch(0, vec![[2.5, 0.0, 0.98]]));
        assert_ne!(out.samples[0].flags & flags::CALIBRATION_EXPIRED, 0);
        assert_ne!(out.samples[0].flags & flags::CLIPPED, 0);
        assert_ne!(out.samples[0].flags & flags::OUTSIDE_AMPLITUDE, 0);
    }
}
