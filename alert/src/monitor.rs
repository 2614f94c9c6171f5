//! The alerting logic, per sensor: sliding windows, tilt baselines, decisions, rate limiting and
//! staleness. Pure and synchronous: decoded messages and the current time go in, alerts come
//! out, so every rule can be tested with a scripted stream and no network.
//!
//! Times: windows follow the samples' own timestamps (the sensor's clock), so a late batch is
//! judged on what it measured; staleness and rate limiting follow the wall-clock `now` the
//! caller passes in, since they are about when data *arrives*.
//!
//! Quality flags: a sample is *clean* when it has no flag, *usable* when its value and
//! uncertainty are finite and it is calibrated (an uncalibrated value is a raw output, not m/s²,
//! and is never judged at all). Each statistic is decided twice: on the clean samples, and on
//! every usable sample. The second decision is capped at `possible`, so flagged samples never
//! raise `exceeded` on their own; the alert's statement says which samples it rests on.
//!
//! Batches flagged `duplicate` repeat or precede data already seen and are left out of the
//! window entirely; `sequence_gap` marks every sample of its batch, and a window that is not
//! all clean has its dominant frequency judged only as flagged (a hole breaks the spectrum).

use std::collections::{BTreeMap, BTreeSet, HashMap, VecDeque};

use time::OffsetDateTime;
use triax_protocol::messages::{
    Alert, AlertKind, AlertLevel, JudgedLevel, SensorJudgement, TiltSample,
};
use triax_protocol::{flags, BuildingId, CorrectedBatch, CorrectedSample, SensorId};

use crate::config::{Config, Limits, Settings};
use crate::decision::{decide, rule_text, severity, Direction, Estimate, Limit};
use crate::highpass::HighPass;
use crate::stats::{window_stats, Method, Point, Propagation, Request, WindowStats, AXIS_NAMES};
use bounds::{SlidingMax, WindowBounds};
use sway::SwayTracker;

/// Most samples one sensor's window holds; a longer window is shortened to its newest samples.
/// About 7 MB a sensor, four minutes at 1 kHz.
pub const MAX_WINDOW_SAMPLES: usize = 1 << 18;

/// Unit strings of alerts.
pub const UNIT_MPS2: &str = "m/s^2";
pub const UNIT_HZ: &str = "Hz";
pub const UNIT_DEG: &str = "deg";
pub const UNIT_S: &str = "s";

type SensorKey = (BuildingId, SensorId);

/// Which samples a decision rests on.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Basis {
    Clean,
    /// Includes flagged samples; capped at `possible`.
    Flagged,
}

#[derive(Debug, Clone, Copy)]
struct Judgement {
    level: AlertLevel,
    estimate: Estimate,
    basis: Basis,
    limit: Limit,
}

/// The last alert sent for one kind, for rate limiting.
#[derive(Debug, Clone, Copy)]
struct Sent {
    level: AlertLevel,
    at: OffsetDateTime,
    suppressed: u32,
}

#[derive(Debug, Clone, Copy)]
/// A window's sample, flat: 48 bytes where a `CorrectedSample` inside would make 56 (its own
/// padding), and the window holds ten thousand sensors' worth.
struct TimedSample {
    t_ns: i64,
    accel_mps2: [f32; 3],
    uncertainty_mps2: [f32; 3],
    /// The high-passed acceleration; NaN for a sample that is not usable.
    vibration: [f32; 3],
    flags: u16,
    /// See [`usable`], decided once.
    usable: bool,
    /// Whether the high pass had settled when this sample went through it.
    settled: bool,
}

#[derive(Debug, Clone, Copy)]
struct TiltBaseline {
    roll_deg: Estimate,
    pitch_deg: Estimate,
    /// The largest coverage factor of the samples behind it.
    k: f64,
}

#[derive(Debug, Default)]
struct TiltState {
    calibration_version: Option<u64>,
    baseline: Option<TiltBaseline>,
    collecting: Vec<TiltSample>,
    window: VecDeque<TiltSample>,
}

#[derive(Debug)]
struct SensorState {
    limits: Limits,
    window: VecDeque<TimedSample>,
    sample_rate_hz: f64,
    /// The vibration baseline, restarted with the window; None until the first usable sample.
    highpass: Option<HighPass>,
    /// Calibration version of the samples in the window.
    calibration_version: Option<u64>,
    /// Running bounds of the window's usable samples: a quiet window is seen to be quiet
    /// without looking at it again.
    bounds: WindowBounds,
    /// The single-sway fit of the window, kept up to date while the window is near a limit.
    sway: SwayTracker,
    /// Largest coverage factor of the batches in the window, by each batch's last sample.
    k_max: SlidingMax,
    /// First sample time and sequence number of each batch with samples in the window, oldest
    /// first: what an alert names as the batches it judged.
    batches: VecDeque<(i64, u64)>,
    /// Wall-clock arrival of the last message; None before the first.
    last_data: Option<OffsetDateTime>,
    /// When watching began: the reference for a sensor that never sent anything.
    watched_since: OffsetDateTime,
    tilt: TiltState,
    sent: HashMap<AlertKind, Sent>,
    /// The latest judgement of the acceleration window, for the service's status.
    last: LastJudged,
    span: tracing::Span,
}

/// What the latest batch's window came to, whether or not it raised an alert.
#[derive(Debug, Clone, Default)]
struct LastJudged {
    /// When a window was last judged, by the service's clock.
    at: Option<OffsetDateTime>,
    window_ns: Option<(i64, i64)>,
    sequences: Option<(u64, u64)>,
    /// The latest batch's window was not judged: not whole, or the baseline still settling.
    waiting: bool,
    levels: BTreeMap<AlertKind, JudgedLevel>,
}

/// A window's alerts, and what it came to per kind; None when it was not judged.
struct Evaluation {
    alerts: Vec<Alert>,
    judged: Option<Judged>,
}

struct Judged {
    window_ns: (i64, i64),
    sequences: Option<(u64, u64)>,
    levels: BTreeMap<AlertKind, JudgedLevel>,
}

/// A kind's outcome: its judgement's level, `below` when it was estimated and judged below the
/// limit, `not_judged` when there was nothing to judge.
fn outcome(j: Option<&Judgement>, estimated: bool) -> JudgedLevel {
    match j.map(|j| j.level) {
        Some(AlertLevel::Exceeded) => JudgedLevel::Exceeded,
        Some(AlertLevel::Possible | AlertLevel::Stale) => JudgedLevel::Possible,
        None if estimated => JudgedLevel::Below,
        None => JudgedLevel::NotJudged,
    }
}

impl SensorState {
    fn new(key: &SensorKey, limits: Limits, now: OffsetDateTime) -> Self {
        SensorState {
            limits,
            window: VecDeque::new(),
            sample_rate_hz: 0.0,
            highpass: None,
            calibration_version: None,
            bounds: WindowBounds::default(),
            sway: SwayTracker::default(),
            k_max: SlidingMax::default(),
            batches: VecDeque::new(),
            last_data: None,
            watched_since: now,
            tilt: TiltState::default(),
            sent: HashMap::new(),
            last: LastJudged::default(),
            span: tracing::info_span!("sensor", building = %key.0, sensor = %key.1),
        }
    }

    /// Drops the window's oldest sample, and it from the running bounds.
    fn forget_oldest(&mut self) {
        self.sway.on_pop(&self.window);
        if let Some(old) = self.window.pop_front() {
            if old.usable {
                self.bounds.pop(
                    old.t_ns,
                    old.vibration,
                    old.uncertainty_mps2,
                    flagged(old.flags),
                );
            }
            self.k_max.evict_through(old.t_ns);
        }
        // A batch stays while its successor starts after the window's first sample.
        if let Some(front_ns) = self.window.front().map(|s| s.t_ns) {
            while self.batches.len() > 1 && self.batches[1].0 <= front_ns {
                self.batches.pop_front();
            }
        }
    }

    fn data_arrived(&mut self, now: OffsetDateTime) {
        if self.sent.remove(&AlertKind::Stale).is_some() {
            tracing::info!(parent: &self.span, "data again after a stale alert");
        }
        self.last_data = Some(now);
    }
}

/// Every watched sensor's state.
#[derive(Debug)]
pub struct Monitor {
    config: Config,
    sensors: BTreeMap<SensorKey, SensorState>,
}

/// Whether a sample's flags keep it from being judged clean. `calibration_suspect` alone does
/// not: such a sample's uncertainty is widened instead
/// ([`crate::config::Settings::suspect_relative_uncertainty`]), so that a field health verdict
/// never silences a sensor's alerts.
fn flagged(flags: u16) -> bool {
    flags & !flags::CALIBRATION_SUSPECT != 0
}

fn usable(s: &CorrectedSample) -> bool {
    s.flags & (flags::UNCALIBRATED | flags::NON_FINITE_INPUT) == 0
        && s.accel_mps2.iter().all(|a| a.is_finite())
        && s.uncertainty_mps2
            .iter()
            .all(|u| u.is_finite() && *u >= 0.0)
}

fn tilt_usable(t: &TiltSample) -> bool {
    t.flags & (flags::UNCALIBRATED | flags::NON_FINITE_INPUT) == 0
        && [
            t.roll_deg,
            t.pitch_deg,
            t.roll_uncertainty_deg,
            t.pitch_uncertainty_deg,
        ]
        .iter()
        .all(|v| v.is_finite())
}

/// The more severe of two judgements; the clean one on a tie.
fn worse(a: Option<Judgement>, b: Option<Judgement>) -> Option<Judgement> {
    match (a, b) {
        (Some(a), Some(b)) if severity(b.level) > severity(a.level) => Some(b),
        (Some(a), _) => Some(a),
        (None, b) => b,
    }
}

/// Decides on clean samples, and on all usable samples capped at `possible`.
fn judge(
    k: f64,
    limit: Limit,
    clean: Option<Estimate>,
    flagged: Option<Estimate>,
) -> Option<Judgement> {
    let on = |e: Option<Estimate>, basis| {
        e.and_then(|estimate| {
            decide(estimate, k, limit).map(|level| Judgement {
                level: if basis == Basis::Flagged {
                    AlertLevel::Possible
                } else {
                    level
                },
                estimate,
                basis,
                limit,
            })
        })
    };
    worse(on(clean, Basis::Clean), on(flagged, Basis::Flagged))
}

/// What a window's alerts have in common.
struct Context<'a> {
    key: &'a SensorKey,
    k: f64,
    window_s: f64,
    /// First and last sample time judged, ns.
    window_ns: (i64, i64),
    /// Sequence numbers of the batches holding them; none for tilt.
    sequences: Option<(u64, u64)>,
    flagged_fraction: f64,
    flag_bits: u16,
    /// The widening of `calibration_suspect` samples judged as clean; none where they are not
    /// (tilt).
    suspect_widening: Option<f64>,
    now: OffsetDateTime,
}

fn fmt_num(v: f64) -> String {
    format!("{v:.4}")
}

fn statement(
    ctx: &Context<'_>,
    kind: AlertKind,
    j: &Judgement,
    unit: &str,
    detail: &str,
) -> String {
    let Estimate {
        value,
        standard_uncertainty: u,
    } = j.estimate;
    let k = ctx.k;
    let (lo, hi) = (value - k * u, value + k * u);
    let t = j.limit.threshold;
    let side = match j.limit.direction {
        Direction::Above => "above",
        Direction::Below => "below",
    };
    let what = match kind {
        AlertKind::PeakAcceleration => "peak acceleration of the motion",
        AlertKind::RmsAcceleration => "RMS acceleration of the motion",
        AlertKind::DominantFrequency => "dominant frequency",
        AlertKind::TiltChange => "tilt change from baseline",
        AlertKind::Stale => "silence",
        // Raised by the modal service, never by this monitor; named for completeness.
        AlertKind::ModalShift => "building mode frequency",
    };
    let level = match j.level {
        AlertLevel::Exceeded => "exceeded",
        AlertLevel::Possible => "possible",
        AlertLevel::Stale => "stale",
    };
    let mut s = format!(
        "{level}: {what} {} ± {} {unit} (k = {k}: [{}, {}] {unit}) against the limit {} {unit} \
         (alarm {side}); {detail}. {}",
        fmt_num(value),
        fmt_num(k * u),
        fmt_num(lo),
        fmt_num(hi),
        fmt_num(t),
        rule_text(j.limit.direction),
    );
    let names = flags::names(ctx.flag_bits).join(", ");
    match j.basis {
        Basis::Flagged => s.push_str(&format!(
            " Decided on samples that include flagged ones ({names}; {:.1} % of the window): \
             flagged samples never raise `exceeded` on their own, so this alert is at most \
             `possible`.",
            100.0 * ctx.flagged_fraction
        )),
        Basis::Clean if ctx.flagged_fraction > 0.0 => s.push_str(&format!(
            " Decided on unflagged samples only; {:.1} % of the window was flagged ({names}) and \
             left out.",
            100.0 * ctx.flagged_fraction
        )),
        Basis::Clean => {}
    }
    if let (Some(r), true) = (
        ctx.suspect_widening,
        ctx.flag_bits & flags::CALIBRATION_SUSPECT != 0,
    ) {
        s.push_str(&format!(
            " Samples flagged calibration_suspect (the field health checks found their record \
             off) were judged as clean, the estimate's standard uncertainty widened by {:.1} % \
             of its value (suspect_relative_uncertainty).",
            100.0 * r
        ));
    }
    s
}

fn make_alert(
    ctx: &Context<'_>,
    kind: AlertKind,
    j: &Judgement,
    unit: &str,
    detail: &str,
) -> Alert {
    Alert {
        format_version: triax_protocol::JSON_FORMAT_VERSION,
        building: ctx.key.0.clone(),
        sensor_id: ctx.key.1.clone(),
        kind,
        level: j.level,
        value: j.estimate.value,
        standard_uncertainty: j.estimate.standard_uncertainty,
        coverage_factor: ctx.k,
        threshold: j.limit.threshold,
        unit: unit.into(),
        window_s: ctx.window_s,
        flagged_fraction: ctx.flagged_fraction,
        statement: statement(ctx, kind, j, unit, detail),
        at: ctx.now,
        late: false,
        window_start_ns: Some(ctx.window_ns.0),
        window_end_ns: Some(ctx.window_ns.1),
        first_sequence: ctx.sequences.map(|s| s.0),
        last_sequence: ctx.sequences.map(|s| s.1),
    }
}

/// Passes an alert unless the same kind was sent at the same or a higher level within the
/// repeat interval. An escalation (`possible` → `exceeded`) always passes.
fn rate_limit(
    sent: &mut HashMap<AlertKind, Sent>,
    mut alert: Alert,
    repeat_interval_s: f64,
    span: &tracing::Span,
) -> Option<Alert> {
    let now = alert.at;
    if let Some(prev) = sent.get_mut(&alert.kind) {
        let since_s = (now - prev.at).as_seconds_f64();
        if severity(alert.level) <= severity(prev.level) && since_s < repeat_interval_s {
            prev.suppressed += 1;
            tracing::debug!(parent: span, kind = ?alert.kind, level = ?alert.level,
                suppressed = prev.suppressed, "alert rate-limited");
            return None;
        }
        if prev.suppressed > 0 {
            alert.statement.push_str(&format!(
                " {} similar alert(s) were suppressed since the previous one at {}.",
                prev.suppressed,
                prev.at
                    .format(&time::format_description::well_known::Rfc3339)
                    .unwrap_or_default()
            ));
        }
    }
    sent.insert(
        alert.kind,
        Sent {
            level: alert.level,
            at: now,
            suppressed: 0,
        },
    );
    Some(alert)
}

impl Monitor {
    /// Starts watching; sensors listed in the configuration are expected from `now` on.
    pub fn new(config: Config, now: OffsetDateTime) -> Monitor {
        let mut sensors = BTreeMap::new();
        for (b, s) in config.expected_sensors() {
            let key = (b.clone(), s.clone());
            if let Some(limits) = config.limits(b, s) {
                sensors.insert(key.clone(), SensorState::new(&key, limits, now));
            }
        }
        Monitor { config, sensors }
    }

    pub fn config(&self) -> &Config {
        &self.config
    }

    fn settings(&self) -> Settings {
        self.config.settings
    }

    /// The state of a watched sensor, created on first contact; None for unwatched buildings.
    fn state(
        &mut self,
        building: &BuildingId,
        sensor: &SensorId,
        now: OffsetDateTime,
    ) -> Option<&mut SensorState> {
        let key = (building.clone(), sensor.clone());
        if !self.sensors.contains_key(&key) {
            let limits = self.config.limits(building, sensor)?;
            self.sensors
                .insert(key.clone(), SensorState::new(&key, limits, now));
        }
        self.sensors.get_mut(&key)
    }

    /// A corrected batch from `building` arrived at `now`.
    pub fn on_corrected(
        &mut self,
        building: &BuildingId,
        batch: &CorrectedBatch,
        now: OffsetDateTime,
    ) -> Vec<Alert> {
        self.take_corrected(building, batch, now, true)
    }

    /// A batch that was judged before (by this service before a restart): it goes into the
    /// window and the baseline filter, so that the batches after it are judged on a settled
    /// baseline and a whole window, but raises nothing.
    pub fn prime(&mut self, building: &BuildingId, batch: &CorrectedBatch, now: OffsetDateTime) {
        self.take_corrected(building, batch, now, false);
    }

    fn take_corrected(
        &mut self,
        building: &BuildingId,
        batch: &CorrectedBatch,
        now: OffsetDateTime,
        judge: bool,
    ) -> Vec<Alert> {
        let settings = self.settings();
        let sensor = batch.header.sensor_id.clone();
        let Some(state) = self.state(building, &sensor, now) else {
            return Vec::new();
        };
        let _span = state.span.clone().entered();
        state.data_arrived(now);
        if batch.batch_flags & flags::DUPLICATE != 0 {
            tracing::debug!(
                sequence = batch.header.sequence,
                "duplicate batch left out of the window"
            );
            return Vec::new();
        }
        let h = &batch.header;
        let period_ns = 1e9 / h.sample_rate_hz;
        let newest_ns = state.window.back().map(|s| s.t_ns);
        let rate_changed = (state.sample_rate_hz - h.sample_rate_hz).abs()
            > 1e-9 * h.sample_rate_hz.max(state.sample_rate_hz);
        // A new calibration moves offsets and gains: the baseline filter would ring on the step.
        let version_changed = state
            .calibration_version
            .is_some_and(|v| v != batch.info.calibration_version);
        if rate_changed || version_changed || newest_ns.is_some_and(|t| h.timestamp_ns <= t) {
            if !state.window.is_empty() {
                tracing::info!(
                    sample_rate_hz = h.sample_rate_hz,
                    timestamp_ns = h.timestamp_ns,
                    calibration_version = batch.info.calibration_version,
                    "sample rate or calibration changed, or time went back: window and baseline \
                     restarted"
                );
            }
            state.window.clear();
            state.bounds.clear();
            state.sway = SwayTracker::default();
            state.k_max = SlidingMax::default();
            state.batches.clear();
            state.highpass = None;
            state.sample_rate_hz = h.sample_rate_hz;
        }
        state.calibration_version = Some(batch.info.calibration_version);
        if !batch.samples.is_empty() {
            state.batches.push_back((h.timestamp_ns, h.sequence));
        }
        let batch_level = batch.batch_flags & flags::SEQUENCE_GAP;
        for (i, s) in batch.samples.iter().enumerate() {
            let mut sample = *s;
            sample.flags |= batch_level;
            let t_ns = h.timestamp_ns.saturating_add((i as f64 * period_ns) as i64);
            let is_usable = usable(&sample);
            let vibration = if is_usable {
                let hp = state
                    .highpass
                    .get_or_insert_with(|| HighPass::new(settings.highpass_hz, h.sample_rate_hz));
                let v = hp.apply(sample.accel_mps2.map(f64::from)).map(|v| v as f32);
                state.bounds.push(
                    t_ns,
                    sample.accel_mps2,
                    v,
                    sample.uncertainty_mps2,
                    flagged(sample.flags),
                );
                v
            } else {
                [f32::NAN; 3]
            };
            if i + 1 == batch.samples.len() {
                state
                    .k_max
                    .push(t_ns, f64::from(batch.info.coverage_factor));
            }
            state.window.push_back(TimedSample {
                t_ns,
                accel_mps2: sample.accel_mps2,
                uncertainty_mps2: sample.uncertainty_mps2,
                vibration,
                flags: sample.flags,
                usable: is_usable,
                settled: state.highpass.as_ref().is_some_and(HighPass::settled),
            });
            state.sway.on_push(&state.window, period_ns);
        }
        let window_ns = (settings.window_s * 1e9) as i64;
        if let Some(newest) = state.window.back().map(|s| s.t_ns) {
            let horizon = newest.saturating_sub(window_ns);
            while state.window.front().is_some_and(|s| s.t_ns <= horizon) {
                state.forget_oldest();
            }
        }
        while state.window.len() > MAX_WINDOW_SAMPLES {
            state.forget_oldest();
        }
        if !judge {
            return Vec::new();
        }

        let key = (building.clone(), sensor);
        let Evaluation { alerts, judged } = evaluate_window(&key, state, &settings, now);
        match judged {
            Some(j) => {
                state.last = LastJudged {
                    at: Some(now),
                    window_ns: Some(j.window_ns),
                    sequences: j.sequences,
                    waiting: false,
                    levels: j.levels,
                };
            }
            None => state.last.waiting = true,
        }
        let span = state.span.clone();
        alerts
            .into_iter()
            .filter_map(|a| rate_limit(&mut state.sent, a, settings.repeat_interval_s, &span))
            .collect()
    }

    /// A tilt sample from `building`, for the sensor in the key, arrived at `now`.
    pub fn on_tilt(
        &mut self,
        building: &BuildingId,
        tilt: &TiltSample,
        now: OffsetDateTime,
    ) -> Vec<Alert> {
        let settings = self.settings();
        let sensor = tilt.sensor_id.clone();
        let Some(state) = self.state(building, &sensor, now) else {
            return Vec::new();
        };
        let _span = state.span.clone().entered();
        state.data_arrived(now);
        let ts = &mut state.tilt;
        if ts.calibration_version != Some(tilt.calibration_version) {
            // A new calibration moves the offsets, and with them the apparent tilt: a change of
            // record is not a change of the structure, so the baseline starts over.
            if ts.calibration_version.is_some() {
                tracing::info!(
                    calibration_version = tilt.calibration_version,
                    "calibration changed: tilt baseline restarted"
                );
            }
            *ts = TiltState {
                calibration_version: Some(tilt.calibration_version),
                ..TiltState::default()
            };
        }
        let Some(baseline) = ts.baseline else {
            if tilt.flags == 0 && tilt_usable(tilt) {
                ts.collecting.push(tilt.clone());
                if ts.collecting.len() >= settings.tilt_baseline_samples {
                    let (roll_deg, pitch_deg) = tilt_means(&ts.collecting);
                    ts.baseline = Some(TiltBaseline {
                        roll_deg,
                        pitch_deg,
                        k: ts
                            .collecting
                            .iter()
                            .map(|t| t.coverage_factor)
                            .fold(0.0, f64::max),
                    });
                    ts.collecting = Vec::new();
                    tracing::info!(
                        roll_deg = roll_deg.value,
                        pitch_deg = pitch_deg.value,
                        "tilt baseline set"
                    );
                }
            }
            return Vec::new();
        };
        if ts
            .window
            .back()
            .is_some_and(|t| tilt.timestamp_ns <= t.timestamp_ns)
        {
            ts.window.clear();
        }
        ts.window.push_back(tilt.clone());
        let horizon = tilt
            .timestamp_ns
            .saturating_sub((settings.window_s * 1e9) as i64);
        while ts.window.front().is_some_and(|t| t.timestamp_ns <= horizon) {
            ts.window.pop_front();
        }
        // Bounded by count as well as by time, like the acceleration window: a sender with a
        // very high tilt rate must not grow the service's memory.
        while ts.window.len() > MAX_WINDOW_SAMPLES {
            ts.window.pop_front();
        }
        let Some(limit) = state.limits.tilt_change() else {
            return Vec::new();
        };
        let n = ts.window.len();
        let clean: Vec<TiltSample> = ts
            .window
            .iter()
            .filter(|t| t.flags == 0 && tilt_usable(t))
            .cloned()
            .collect();
        let all: Vec<TiltSample> = ts
            .window
            .iter()
            .filter(|t| tilt_usable(t))
            .cloned()
            .collect();
        let flag_bits = ts.window.iter().fold(0, |acc, t| acc | t.flags);
        let change = |set: &[TiltSample]| -> Option<(Estimate, &'static str)> {
            if set.is_empty() {
                return None;
            }
            let (roll, pitch) = tilt_means(set);
            let diff = |now: Estimate, base: Estimate| Estimate {
                value: (now.value - base.value).abs(),
                // Baseline and window share the sensor and its calibration, so their errors are
                // positively correlated; adding the variances as if independent overstates u.
                standard_uncertainty: now.standard_uncertainty.hypot(base.standard_uncertainty),
            };
            let (dr, dp) = (
                diff(roll, baseline.roll_deg),
                diff(pitch, baseline.pitch_deg),
            );
            Some(if dr.value >= dp.value {
                (dr, "roll")
            } else {
                (dp, "pitch")
            })
        };
        let clean_change = change(&clean);
        let flagged_change = (all.len() > clean.len()).then(|| change(&all)).flatten();
        // The stream's own k where it asks for more than the configured one (few degrees of
        // freedom): the decision is at least as safe as each tilt sample's interval.
        let k = ts
            .window
            .iter()
            .map(|t| t.coverage_factor)
            .fold(settings.coverage_factor.max(baseline.k), f64::max);
        let j = judge(
            k,
            limit,
            clean_change.map(|c| c.0),
            flagged_change.map(|c| c.0),
        );
        let Some(j) = j else {
            return Vec::new();
        };
        let axis = match j.basis {
            Basis::Clean => clean_change.map(|c| c.1),
            Basis::Flagged => flagged_change.map(|c| c.1),
        }
        .unwrap_or("roll");
        let key = (building.clone(), sensor);
        let ctx = Context {
            key: &key,
            k,
            window_s: window_span_s(ts.window.front(), ts.window.back()),
            window_ns: (
                ts.window
                    .front()
                    .map_or(tilt.timestamp_ns, |t| t.timestamp_ns),
                tilt.timestamp_ns,
            ),
            sequences: None,
            flagged_fraction: (n - clean.len()) as f64 / n as f64,
            flag_bits,
            suspect_widening: None,
            now,
        };
        let detail = format!(
            "largest change on {axis}, mean of {} tilt sample(s) against a baseline of {} \
             clean samples at calibration version {}; u combines window and baseline as \
             independent (conservative)",
            match j.basis {
                Basis::Clean => clean.len(),
                Basis::Flagged => all.len(),
            },
            settings.tilt_baseline_samples,
            tilt.calibration_version
        );
        let alert = make_alert(&ctx, AlertKind::TiltChange, &j, UNIT_DEG, &detail);
        let span = state.span.clone();
        rate_limit(&mut state.sent, alert, settings.repeat_interval_s, &span)
            .into_iter()
            .collect()
    }

    /// Buildings listed in the configuration or with a watched sensor, by id.
    pub fn buildings(&self) -> BTreeSet<BuildingId> {
        self.sensors
            .keys()
            .map(|(b, _)| b.clone())
            .chain(self.config.buildings.keys().cloned())
            .collect()
    }

    /// What the service last judged of each watched sensor of `building`, by id.
    pub fn judgements(&self, building: &BuildingId) -> Vec<SensorJudgement> {
        self.sensors
            .iter()
            .filter(|((b, _), _)| b == building)
            .map(|((_, sensor), st)| SensorJudgement {
                sensor_id: sensor.clone(),
                last_data_at: st.last_data,
                judged_at: st.last.at,
                window_start_ns: st.last.window_ns.map(|w| w.0),
                window_end_ns: st.last.window_ns.map(|w| w.1),
                first_sequence: st.last.sequences.map(|s| s.0),
                last_sequence: st.last.sequences.map(|s| s.1),
                waiting: st.last.waiting.then(|| "settling".to_owned()),
                levels: st.last.levels.clone(),
            })
            .collect()
    }

    /// Stale alerts for sensors silent for longer than `stale_after_s` at `now`.
    pub fn check_stale(&mut self, now: OffsetDateTime) -> Vec<Alert> {
        let settings = self.settings();
        let mut out = Vec::new();
        for (key, state) in &mut self.sensors {
            let since = state.last_data.unwrap_or(state.watched_since);
            let silent_s = (now - since).as_seconds_f64();
            if silent_s <= settings.stale_after_s {
                continue;
            }
            let statement = match state.last_data {
                Some(_) => format!(
                    "stale: no corrected or tilt data from this sensor for {silent_s:.1} s, \
                     longer than the allowed {} s. Nothing can be decided about it until data \
                     arrives again.",
                    settings.stale_after_s
                ),
                None => format!(
                    "stale: this expected sensor has sent no corrected or tilt data in the \
                     {silent_s:.1} s since watching began, longer than the allowed {} s.",
                    settings.stale_after_s
                ),
            };
            let alert = Alert {
                format_version: triax_protocol::JSON_FORMAT_VERSION,
                building: key.0.clone(),
                sensor_id: key.1.clone(),
                kind: AlertKind::Stale,
                level: AlertLevel::Stale,
                value: silent_s,
                standard_uncertainty: 0.0,
                coverage_factor: settings.coverage_factor,
                threshold: settings.stale_after_s,
                unit: UNIT_S.into(),
                window_s: settings.window_s,
                flagged_fraction: 0.0,
                statement,
                at: now,
                late: false,
                window_start_ns: None,
                window_end_ns: None,
                first_sequence: None,
                last_sequence: None,
            };
            let span = state.span.clone();
            out.extend(rate_limit(
                &mut state.sent,
                alert,
                settings.repeat_interval_s,
                &span,
            ));
        }
        out
    }
}

fn window_span_s(first: Option<&TiltSample>, last: Option<&TiltSample>) -> f64 {
    match (first, last) {
        (Some(a), Some(b)) => (b.timestamp_ns - a.timestamp_ns) as f64 / 1e9,
        _ => 0.0,
    }
}

/// Mean roll and pitch with the mean of their uncertainties: the samples share one calibration,
/// so their errors are taken as fully correlated and do not average down.
fn tilt_means(set: &[TiltSample]) -> (Estimate, Estimate) {
    let n = set.len() as f64;
    let mean = |f: fn(&TiltSample) -> f64| set.iter().map(f).sum::<f64>() / n;
    (
        Estimate {
            value: mean(|t| t.roll_deg),
            standard_uncertainty: mean(|t| t.roll_uncertainty_deg),
        },
        Estimate {
            value: mean(|t| t.pitch_deg),
            standard_uncertainty: mean(|t| t.pitch_uncertainty_deg),
        },
    )
}

/// Peak, RMS and dominant-frequency alerts of a sensor's current window, before rate limiting,
/// and what the window came to.
fn evaluate_window(
    key: &SensorKey,
    state: &mut SensorState,
    settings: &Settings,
    now: OffsetDateTime,
) -> Evaluation {
    let waiting = || Evaluation {
        alerts: Vec::new(),
        judged: None,
    };
    let n = state.window.len();
    let (Some(first), Some(last)) = (state.window.front(), state.window.back()) else {
        return waiting();
    };
    // Only whole windows are judged, and only once the baseline filter has settled before the
    // window's first sample: a window shorter than `window_s` (the first seconds of a stream,
    // or after a restart) or one that still holds the filter's start-up transient would be
    // judged on something other than the motion.
    let period_ns = 1e9 / state.sample_rate_hz;
    let span_ns = (last.t_ns - first.t_ns) as f64 + period_ns;
    if span_ns < settings.window_s * 1e9 - 0.5 * period_ns || !first.settled {
        return waiting();
    }
    let window_ns = (first.t_ns, last.t_ns);
    let sequences = state
        .batches
        .front()
        .zip(state.batches.back())
        .map(|(a, b)| (a.1, b.1));
    // The stream's own k where it asks for more than the configured one (few degrees of
    // freedom): the decision is at least as safe as each sample's interval.
    let k = state.k_max.max().map_or(settings.coverage_factor, |k| {
        k.max(settings.coverage_factor)
    });
    let limits = &state.limits;
    // The bounds hold each sample's stated u; a calibration_suspect sample's estimate is
    // widened by a share of its value (below), which the bounds allow for here.
    let widened = 1.0 + k * settings.suspect_relative_uncertainty;
    let wanted = limits
        .pga()
        .is_some_and(|l| widened * state.bounds.peak_bound(k) >= l.threshold)
        || limits
            .rms()
            .is_some_and(|l| widened * state.bounds.rms_bound(k) >= l.threshold)
        || limits.frequency().next().is_some();
    if !wanted {
        // Far from every limit: the sway fit is not kept up to date (it is rebuilt once the
        // window comes near one again).
        state.sway.disarm();
        // Judged all the same: no estimate the window allows can reach a limit.
        let levels = [
            (AlertKind::PeakAcceleration, limits.pga().is_some()),
            (AlertKind::RmsAcceleration, limits.rms().is_some()),
        ]
        .into_iter()
        .filter(|(_, limited)| *limited)
        .map(|(kind, _)| (kind, JudgedLevel::Below))
        .collect();
        return Evaluation {
            alerts: Vec::new(),
            judged: Some(Judged {
                window_ns,
                sequences,
                levels,
            }),
        };
    }
    let grid_len = (span_ns / period_ns).round() as u32;
    let rate = state.sample_rate_hz;
    let request = Request {
        sample_rate_hz: rate,
        grid_len,
        propagation: Propagation {
            noise_share: settings.noise_share,
        },
        k,
        peak_threshold: state.limits.pga().map(|l| l.threshold),
        rms_threshold: state.limits.rms().map(|l| l.threshold),
        frequency: state.limits.frequency().next().is_some(),
        highpass: state.highpass.as_ref().map(HighPass::response),
    };
    // A window near a limit that is one clean sway is judged from the tracked fit, at the cost
    // of the batch; anything else from all its samples.
    let summaries = state.bounds.summaries();
    let tracked = state.sway.stats(&state.window, &summaries, &request);
    let (clean_stats, flagged_stats, n_clean, flag_bits) = match tracked {
        // Tracked only while every sample is clean (calibration_suspect ones with their widened
        // uncertainty).
        Some(stats) => (
            Some(stats),
            None,
            n,
            state.window.iter().fold(0, |acc, t| acc | t.flags),
        ),
        None => {
            let first_ns = first.t_ns;
            let point = |t: &TimedSample| Point {
                index: (((t.t_ns - first_ns) as f64 / period_ns).round() as u32).min(grid_len - 1),
                accel_mps2: t.accel_mps2,
                vibration_mps2: t.vibration,
                uncertainty_mps2: t.uncertainty_mps2,
            };
            let all: Vec<Point> = state
                .window
                .iter()
                .filter(|t| t.usable)
                .map(point)
                .collect();
            let clean: Vec<Point> = state
                .window
                .iter()
                .filter(|t| !flagged(t.flags) && t.usable)
                .map(point)
                .collect();
            let clean_stats = window_stats(&clean, &request);
            // Only worth a second look when flagged samples add something to the clean ones.
            let flagged_stats = if all.len() > clean.len() {
                window_stats(&all, &request)
            } else {
                None
            };
            let flag_bits = state.window.iter().fold(0, |acc, t| acc | t.flags);
            (clean_stats, flagged_stats, clean.len(), flag_bits)
        }
    };
    let ctx = Context {
        key,
        k,
        window_s: f64::from(grid_len) / rate,
        window_ns,
        sequences,
        flagged_fraction: (n - n_clean) as f64 / n as f64,
        flag_bits,
        suspect_widening: Some(settings.suspect_relative_uncertainty),
        now,
    };
    let basis_stats = |j: &Judgement| -> Option<&WindowStats> {
        match j.basis {
            Basis::Clean => clean_stats.as_ref(),
            Basis::Flagged => flagged_stats.as_ref(),
        }
    };
    let mut alerts = Vec::new();

    let mut levels = BTreeMap::new();
    // A suspect record's gain error scales every amplitude the window gives: its share is
    // added to the estimate's uncertainty (frequencies do not move with a gain).
    let suspect = flag_bits & flags::CALIBRATION_SUSPECT != 0;
    let widen = |e: Estimate| {
        if suspect {
            Estimate {
                standard_uncertainty: e
                    .standard_uncertainty
                    .hypot(settings.suspect_relative_uncertainty * e.value),
                ..e
            }
        } else {
            e
        }
    };
    if let Some(limit) = state.limits.pga() {
        let pick = |w: &WindowStats| w.peak.map(|p| widen(p.estimate));
        let (clean_e, flagged_e) = (
            clean_stats.as_ref().and_then(pick),
            flagged_stats.as_ref().and_then(pick),
        );
        let j = judge(k, limit, clean_e, flagged_e);
        levels.insert(
            AlertKind::PeakAcceleration,
            outcome(j.as_ref(), clean_e.or(flagged_e).is_some()),
        );
        if let Some(j) = j {
            let w = basis_stats(&j);
            let detail = match w.and_then(|w| w.peak.map(|p| (w.n_samples, p))) {
                Some((n, p)) => method_detail("peak", n, p.axis, p.method),
                None => String::new(),
            };
            alerts.push(make_alert(
                &ctx,
                AlertKind::PeakAcceleration,
                &j,
                UNIT_MPS2,
                &detail,
            ));
        }
    }

    if let Some(limit) = state.limits.rms() {
        let pick = |w: &WindowStats| w.rms.map(|p| widen(p.estimate));
        let (clean_e, flagged_e) = (
            clean_stats.as_ref().and_then(pick),
            flagged_stats.as_ref().and_then(pick),
        );
        let j = judge(k, limit, clean_e, flagged_e);
        levels.insert(
            AlertKind::RmsAcceleration,
            outcome(j.as_ref(), clean_e.or(flagged_e).is_some()),
        );
        if let Some(j) = j {
            let w = basis_stats(&j);
            let detail = match w.and_then(|w| w.rms.map(|p| (w.n_samples, p))) {
                Some((n, p)) => format!(
                    "{}; {:.0} % of each sample's stated variance taken as noise \
                     (noise_share), the rest as calibration error common to the window",
                    method_detail("RMS", n, p.axis, p.method),
                    100.0 * settings.noise_share
                ),
                None => String::new(),
            };
            alerts.push(make_alert(
                &ctx,
                AlertKind::RmsAcceleration,
                &j,
                UNIT_MPS2,
                &detail,
            ));
        }
    }

    // A quiet window's spectrum peak is noise; judging it would alarm on nothing.
    let frequency_of = |w: &WindowStats| {
        (w.vibration_rms_mps2 >= settings.frequency_min_rms_mps2)
            .then_some(w.dominant_frequency.map(|f| f.estimate))
            .flatten()
    };
    // A flagged sample left out of the clean set leaves a hole that distorts the spectrum.
    let clean_frequency = clean_stats
        .as_ref()
        .filter(|_| n_clean == n)
        .and_then(frequency_of);
    let flagged_frequency = if n_clean == n {
        None
    } else {
        flagged_stats.as_ref().and_then(frequency_of)
    };
    let mut frequency_judgement = None;
    for limit in state.limits.frequency() {
        frequency_judgement = worse(
            frequency_judgement,
            judge(k, limit, clean_frequency, flagged_frequency),
        );
    }
    if state.limits.frequency().next().is_some() {
        levels.insert(
            AlertKind::DominantFrequency,
            outcome(
                frequency_judgement.as_ref(),
                clean_frequency.or(flagged_frequency).is_some(),
            ),
        );
    }
    if let Some(j) = frequency_judgement {
        let detail =
            match basis_stats(&j).and_then(|w| w.dominant_frequency.map(|p| (w.n_samples, p))) {
                Some((n, p)) => method_detail("frequency", n, p.axis, p.method),
                None => String::new(),
            };
        alerts.push(make_alert(
            &ctx,
            AlertKind::DominantFrequency,
            &j,
            UNIT_HZ,
            &detail,
        ));
    }
    Evaluation {
        alerts,
        judged: Some(Judged {
            window_ns,
            sequences,
            levels,
        }),
    }
}

/// How a statistic was estimated, in words, for the alert's statement.
fn method_detail(what: &str, n_samples: usize, axis: usize, method: Method) -> String {
    let axis = AXIS_NAMES[axis];
    match (what, method) {
        (
            "peak",
            Method::Sine {
                frequency_hz,
                noise_mps2,
            },
        ) => format!(
            "the window on axis {axis} is one sway at {frequency_hz:.3} Hz: peak = amplitude of \
             the sinusoid fitted to its {n_samples} samples (noise {noise_mps2:.4} m/s^2 left \
             over); u from the least-squares covariance"
        ),
        (
            "peak",
            Method::Samples {
                noise_mps2,
                candidates,
            },
        ) => format!(
            "largest |a| of the high-passed axis {axis} over {n_samples} samples, corrected for \
             noise on a maximum ({candidates} sample(s) within 4 noise deviations of it, noise \
             {noise_mps2:.4} m/s^2) and for a crest between samples; a bound that holds for any \
             motion"
        ),
        ("RMS", Method::Sine { frequency_hz, .. }) => format!(
            "the window on axis {axis} is one sway at {frequency_hz:.3} Hz: RMS of the fitted \
             sinusoid over the window's sample times"
        ),
        ("RMS", Method::Samples { noise_mps2, .. }) => format!(
            "RMS of the high-passed axis {axis} over {n_samples} samples with the noise \
             ({noise_mps2:.4} m/s^2) taken out"
        ),
        (_, Method::Sine { noise_mps2, .. }) => format!(
            "the window on axis {axis} is one sway: frequency of the sinusoid fitted to its \
             {n_samples} samples (noise {noise_mps2:.4} m/s^2 left over); u from the \
             least-squares covariance"
        ),
        (_, Method::Samples { .. }) => format!(
            "highest peak of the summed spectra of the three high-passed axes over {n_samples} \
             samples; u = bin/√12 (the line lies anywhere within one resolution bin)"
        ),
    }
}

mod bounds;
#[cfg(test)]
mod monte_carlo;
mod sway;
#[cfg(test)]
mod tests;
