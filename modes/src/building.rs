//! One building: its windows, identification, tracker, and what each window publishes. Pure
//! and synchronous (the service calls [`identify_window`] off its loop).

use std::collections::{BTreeMap, VecDeque};

use nalgebra::Complex;
use serde::{Deserialize, Serialize};
use time::OffsetDateTime;
use triax_client::follow::Position;
use triax_modal::track::{Baseline, Track};
use triax_modal::{
    identify, ChainUncertainty, Direction, Estimate, Identification, ModalError, ModeObservation,
    ModeTracker, ShapePool, ShiftVerdict, TrackUpdate,
};
use triax_protocol::messages::{
    Alert, AlertKind, AlertLevel, BuildingModes, ModalCusum, ModalDirection, ModalEstimate,
    ModalSensorCheck, ModalSensorCoverage, ModalVerdict, ModeReport, ModeShapeComponent,
    PooledShapeComponent, PooledShapeReport, UnquantifiedModeReport,
};
use triax_protocol::{BuildingId, CorrectedBatch, SensorId, JSON_FORMAT_VERSION};

use crate::config::BuildingConfig;
use crate::grid::{ClosedWindow, Gatherer};

/// Temperature readings kept per building: two days of one a minute.
const MAX_TEMPERATURES: usize = 2 * 24 * 60;

/// Unit of a `modal_shift` alert's value and threshold: the frequency's drop, %.
pub const UNIT_PERCENT: &str = "%";

/// What a building keeps across a restart.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct BuildingState {
    /// Windows below this index were identified.
    pub next_index: Option<i64>,
    /// Per sensor, the last batch wholly inside an identified window: `[sequence, timestamp_ns]`.
    pub positions: BTreeMap<String, (u64, i64)>,
    pub tracks: Vec<TrackState>,
    /// Lines in the current record file.
    pub record_lines: u64,
}

/// A track as saved: its baseline is fitted again from its training observations.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TrackState {
    pub id: usize,
    pub direction: Direction,
    pub last_frequency_hz: f64,
    /// `[re, im]` per component.
    pub last_shape: Vec<[f64; 2]>,
    /// The running mean of the matched shapes, `[re, im]` per component (empty: none saved).
    #[serde(default)]
    pub mean_shape: Vec<[f64; 2]>,
    /// The running mean square of the frequency's change between matched windows, Hz².
    #[serde(default)]
    pub step_variance_hz2: f64,
    #[serde(default)]
    pub steps: usize,
    pub training_frequencies_hz: Vec<f64>,
    pub training_regressors: Vec<Vec<f64>>,
    pub observations: usize,
    pub block: Vec<(f64, f64, Vec<f64>)>,
    /// The sequential test's statistics (a drop, a rise).
    #[serde(default)]
    pub cusum_down: f64,
    #[serde(default)]
    pub cusum_up: f64,
}

impl TrackState {
    fn of(t: &Track) -> TrackState {
        TrackState {
            id: t.id,
            direction: t.direction,
            last_frequency_hz: t.last_frequency_hz,
            last_shape: t.last_shape.iter().map(|c| [c.re, c.im]).collect(),
            mean_shape: t.mean_shape.iter().map(|c| [c.re, c.im]).collect(),
            step_variance_hz2: t.step_variance_hz2,
            steps: t.steps,
            training_frequencies_hz: t.training_frequencies_hz.clone(),
            training_regressors: t.training_regressors.clone(),
            observations: t.observations,
            block: t.block.clone(),
            cusum_down: t.cusum_down,
            cusum_up: t.cusum_up,
        }
    }

    fn track(&self, training_windows: usize) -> Track {
        let baseline = (self.training_frequencies_hz.len() >= training_windows)
            .then(|| Baseline::fit(&self.training_frequencies_hz, &self.training_regressors))
            .flatten();
        Track {
            id: self.id,
            direction: self.direction,
            last_frequency_hz: self.last_frequency_hz,
            last_shape: self
                .last_shape
                .iter()
                .map(|c| Complex::new(c[0], c[1]))
                .collect(),
            mean_shape: self
                .mean_shape
                .iter()
                .map(|c| Complex::new(c[0], c[1]))
                .collect(),
            step_variance_hz2: self.step_variance_hz2,
            steps: self.steps,
            training_frequencies_hz: self.training_frequencies_hz.clone(),
            training_regressors: self.training_regressors.clone(),
            baseline,
            observations: self.observations,
            block: self.block.clone(),
            cusum_down: self.cusum_down,
            cusum_up: self.cusum_up,
        }
    }
}

/// One building followed by the service.
#[derive(Debug, Clone)]
pub struct Building {
    pub id: BuildingId,
    pub config: BuildingConfig,
    pub gatherer: Gatherer,
    pub tracker: ModeTracker,
    temperatures: VecDeque<(i64, f64)>,
    pub record_lines: u64,
    /// Per track, its last windows' shapes (`triax_modal::pool`); afresh after a restart.
    pools: std::collections::HashMap<usize, ShapePool>,
}

/// Windows a track's shape is pooled over: a day of 30-minute windows.
pub const POOLED_WINDOWS: usize = 48;

/// What one window gives: the message to publish and keep, and the alerts to sign.
#[derive(Debug, Clone)]
pub struct Outcome {
    pub modes: BuildingModes,
    pub alerts: Vec<Alert>,
}

/// Identifies a closed window (the costly step: a fraction of a second to seconds).
pub fn identify_window(
    config: &BuildingConfig,
    closed: &ClosedWindow,
) -> Result<Identification, ModalError> {
    identify(&config.model, &closed.window, &config.ssi)
}

fn estimate(e: &Estimate) -> ModalEstimate {
    ModalEstimate {
        value: e.value,
        standard_uncertainty: e.standard_uncertainty,
        dof: e.dof,
        coverage_factor: e.coverage_factor,
        coverage_probability: e.coverage_probability,
    }
}

fn direction(d: Direction) -> ModalDirection {
    match d {
        Direction::X => ModalDirection::X,
        Direction::Y => ModalDirection::Y,
        Direction::Z => ModalDirection::Z,
    }
}

fn verdict(v: ShiftVerdict) -> ModalVerdict {
    match v {
        ShiftVerdict::Training => ModalVerdict::Training,
        ShiftVerdict::Normal => ModalVerdict::Normal,
        ShiftVerdict::Possible => ModalVerdict::Possible,
        ShiftVerdict::Shift => ModalVerdict::Shift,
    }
}

impl Building {
    pub fn new(id: BuildingId, config: BuildingConfig, state: Option<&BuildingState>) -> Self {
        let chain = config.chain.unwrap_or(ChainUncertainty::NONE);
        let mut gatherer = Gatherer::new(
            &config.model,
            config.window_s,
            config.alignment_tolerance,
            config.close_after_s,
            chain,
        );
        let tracker_config = config.tracker_per_track();
        let mut tracker = ModeTracker::new(tracker_config.clone());
        let mut record_lines = 0;
        if let Some(state) = state {
            if let Some(next) = state.next_index {
                let positions = state
                    .positions
                    .iter()
                    .filter_map(|(s, &(sequence, timestamp_ns))| {
                        Some((
                            SensorId::new(s.clone()).ok()?,
                            Position {
                                sequence,
                                timestamp_ns,
                            },
                        ))
                    })
                    .collect();
                gatherer.resume_from(next, &positions);
            }
            tracker.tracks = state
                .tracks
                .iter()
                .map(|t| t.track(tracker_config.training_windows))
                .collect();
            record_lines = state.record_lines;
        }
        Building {
            id,
            config,
            gatherer,
            tracker,
            temperatures: VecDeque::new(),
            record_lines,
            pools: std::collections::HashMap::new(),
        }
    }

    /// The state as gathered now: every closed window counted as identified.
    pub fn state(&self) -> BuildingState {
        let next = self.gatherer.next_index();
        self.state_with(
            (next != i64::MIN).then_some(next),
            &self.gatherer.positions(),
        )
    }

    /// The state to save once `closed` is concluded: the windows after it, closed or not, are
    /// still to be identified.
    pub fn state_after(&self, closed: &ClosedWindow) -> BuildingState {
        self.state_with(Some(closed.index + 1), &closed.resume)
    }

    fn state_with(
        &self,
        next_index: Option<i64>,
        positions: &BTreeMap<SensorId, Position>,
    ) -> BuildingState {
        BuildingState {
            next_index,
            positions: positions
                .iter()
                .map(|(s, p)| (s.to_string(), (p.sequence, p.timestamp_ns)))
                .collect(),
            tracks: self.tracker.tracks.iter().map(TrackState::of).collect(),
            record_lines: self.record_lines,
        }
    }

    /// A corrected batch, at `now_s` by the service's clock (any monotonic origin).
    pub fn on_batch(
        &mut self,
        batch: &CorrectedBatch,
        recovered: bool,
        now_s: f64,
    ) -> Vec<ClosedWindow> {
        self.gatherer.add(batch, recovered, now_s)
    }

    /// Closes the windows whose wait for silent sensors is over.
    pub fn tick(&mut self, now_s: f64) -> Vec<ClosedWindow> {
        self.gatherer.tick(now_s)
    }

    /// A temperature reading of the configured source, by its own clock.
    pub fn on_temperature(&mut self, timestamp_ns: i64, temperature_c: f64) {
        if !temperature_c.is_finite() {
            return;
        }
        if self.temperatures.len() >= MAX_TEMPERATURES {
            self.temperatures.pop_front();
        }
        self.temperatures.push_back((timestamp_ns, temperature_c));
    }

    /// Mean of the readings inside `[start, end)`.
    fn mean_temperature(&self, start_ns: i64, end_ns: i64) -> Option<f64> {
        let inside: Vec<f64> = self
            .temperatures
            .iter()
            .filter(|(t, _)| (start_ns..end_ns).contains(t))
            .map(|&(_, c)| c)
            .collect();
        (!inside.is_empty()).then(|| inside.iter().sum::<f64>() / inside.len() as f64)
    }

    /// Tracks the window's modes and writes what it publishes. `temperature_c` overrides the
    /// configured source (a caller that has the window's temperature by other means).
    pub fn conclude(
        &mut self,
        closed: &ClosedWindow,
        result: Result<Identification, ModalError>,
        temperature_c: Option<f64>,
        now: OffsetDateTime,
    ) -> Outcome {
        let tolerance = self.config.alignment_tolerance;
        let result = result.map_err(|e| refusal(&e, &closed.coverage, tolerance));
        self.conclude_with(closed, result, temperature_c, now)
    }

    /// A window whose identification could not run to its end (the identification thread
    /// panicked): published and recorded as refused, saying so.
    pub fn conclude_failed(
        &mut self,
        closed: &ClosedWindow,
        reason: String,
        now: OffsetDateTime,
    ) -> Outcome {
        self.conclude_with(closed, Err(reason), None, now)
    }

    fn conclude_with(
        &mut self,
        closed: &ClosedWindow,
        result: Result<Identification, String>,
        temperature_c: Option<f64>,
        now: OffsetDateTime,
    ) -> Outcome {
        let start_ns = closed.window.start_timestamp_ns;
        let temperature_c = temperature_c.or_else(|| {
            self.config
                .temperature_key
                .as_ref()
                .and_then(|_| self.mean_temperature(start_ns, closed.end_ns))
        });
        let wants_temperature = self.config.temperature_key.is_some();
        let regressors: Vec<f64> = temperature_c.into_iter().collect();
        let mut modes = BuildingModes {
            format_version: JSON_FORMAT_VERSION,
            building: self.id.clone(),
            window_start_ns: start_ns,
            window_end_ns: closed.end_ns,
            sample_rate_hz: closed.window.sample_rate_hz,
            identification_rate_hz: 0.0,
            sensors: closed.coverage.clone(),
            temperature_c,
            regressors: regressors.clone(),
            tracked: false,
            modes: Vec::new(),
            unquantified: Vec::new(),
            refused: None,
            warnings: coverage_warnings(&closed.coverage, self.config.alignment_tolerance),
            late: closed.late,
            identified_at: now,
        };
        let identification = match result {
            Ok(i) => i,
            Err(reason) => {
                modes.refused = Some(reason);
                return Outcome {
                    modes,
                    alerts: Vec::new(),
                };
            }
        };
        modes
            .warnings
            .extend(identification.warnings.iter().map(ToString::to_string));
        for check in &identification.checks {
            for finding in &check.findings {
                // A pair's finding names both of its sensors: said once.
                if !modes.warnings.contains(finding) {
                    modes.warnings.push(finding.clone());
                }
            }
            if let Some(c) = modes
                .sensors
                .iter_mut()
                .find(|c| c.sensor_id.as_str() == check.sensor_id)
            {
                c.check = Some(ModalSensorCheck {
                    tilt_deg: check.tilt_deg.as_ref().map(estimate),
                    plan_rotation_deg: check.plan_rotation_deg.as_ref().map(estimate),
                    time_offset_s: check.time_offset_s.as_ref().map(estimate),
                    findings: check.findings.clone(),
                });
            }
        }
        let suspect: Vec<&str> = closed
            .coverage
            .iter()
            .filter(|c| c.calibration_suspect > 0)
            .map(|c| c.sensor_id.as_str())
            .collect();
        modes.identification_rate_hz = identification.sample_rate_hz;
        modes.unquantified = identification
            .unquantified
            .iter()
            .map(|u| UnquantifiedModeReport {
                frequency_hz: u.frequency_hz,
                damping_ratio: u.damping_ratio,
                replicates: u.replicates,
            })
            .collect();
        // A configured source that gave nothing in the window: the baseline's regressors would
        // change length, so the window is published but not tracked.
        let track = !(wants_temperature && temperature_c.is_none());
        if !track {
            modes.warnings.push(
                "the temperature source (temperature_key) gave no reading inside the window: \
                 identified and published, not tracked"
                    .into(),
            );
        }
        let updates: Vec<Option<TrackUpdate>> = if track {
            let observations: Vec<ModeObservation> = identification
                .modes
                .iter()
                .map(ModeObservation::from)
                .collect();
            self.tracker
                .update(&observations, &regressors)
                .into_iter()
                .map(Some)
                .collect()
        } else {
            vec![None; identification.modes.len()]
        };
        modes.tracked = track;
        let alerting = self.alerting_tracks();
        let mut alerts = Vec::new();
        for (mode, update) in identification.modes.iter().zip(&updates) {
            let shape: Vec<ModeShapeComponent> = mode
                .shape
                .iter()
                .filter_map(|c| {
                    Some(ModeShapeComponent {
                        sensor_id: SensorId::new(c.sensor_id.clone()).ok()?,
                        direction: direction(c.direction),
                        real: estimate(&c.real),
                        imag: estimate(&c.imag),
                        calibration_suspect: suspect.contains(&c.sensor_id.as_str()),
                    })
                })
                .collect();
            let pooled_shape = update.as_ref().and_then(|u| {
                let pool = self
                    .pools
                    .entry(u.track)
                    .or_insert_with(|| ShapePool::new(POOLED_WINDOWS));
                pool.push(mode);
                let pooled = pool.pooled(mode, mode.frequency_hz.coverage_probability)?;
                Some(PooledShapeReport {
                    windows: pooled.windows,
                    reference_component: pooled.reference_component,
                    shape: pooled
                        .shape
                        .iter()
                        .filter_map(|c| {
                            Some(PooledShapeComponent {
                                sensor_id: SensorId::new(c.sensor_id.clone()).ok()?,
                                direction: direction(c.direction),
                                real: estimate(&c.real),
                                calibration_suspect: suspect.contains(&c.sensor_id.as_str()),
                            })
                        })
                        .collect(),
                })
            });
            let report = ModeReport {
                pooled_shape,
                track: update.as_ref().map(|u| u.track as u64),
                direction: direction(mode.direction),
                frequency_hz: estimate(&mode.frequency_hz),
                damping_ratio: estimate(&mode.damping_ratio),
                reference_component: mode.reference_component,
                order: mode.order,
                stable_orders: mode.stable_orders,
                replicates: mode.replicates,
                predicted_hz: update.as_ref().and_then(|u| u.predicted_hz),
                residual_relative: update
                    .as_ref()
                    .and_then(|u| u.residual_relative.as_ref().map(estimate)),
                verdict: update.as_ref().map(|u| verdict(u.verdict)),
                block_mean_relative: update
                    .as_ref()
                    .and_then(|u| u.block_mean_relative.as_ref().map(estimate)),
                block_verdict: update.as_ref().and_then(|u| u.block_verdict.map(verdict)),
                normal_coverage_factor: update.as_ref().and_then(|u| u.normal_factor),
                cusum: update.as_ref().and_then(|u| {
                    Some(ModalCusum {
                        statistic: u.cusum?,
                        threshold: u.cusum_threshold?,
                        verdict: verdict(u.cusum_verdict?),
                    })
                }),
                shape,
            };
            if let Some(u) = update {
                if alerting.contains(&u.track) {
                    alerts.extend(self.shift_alerts(
                        closed,
                        &report,
                        u,
                        !regressors.is_empty(),
                        now,
                    ));
                }
            }
            modes.modes.push(report);
        }
        Outcome { modes, alerts }
    }

    /// The tracks that may alert: per direction, the lowest `alert_modes_per_direction` of
    /// those with a baseline.
    fn alerting_tracks(&self) -> Vec<usize> {
        let mut out = Vec::new();
        for d in &self.config.ssi.channels.directions {
            let mut trained: Vec<&Track> = self
                .tracker
                .tracks
                .iter()
                .filter(|t| t.direction == *d && t.baseline.is_some())
                .collect();
            trained.sort_by(|a, b| a.last_frequency_hz.total_cmp(&b.last_frequency_hz));
            out.extend(
                trained
                    .iter()
                    .take(self.config.alert_modes_per_direction)
                    .map(|t| t.id),
            );
        }
        out
    }

    fn shift_alerts(
        &self,
        closed: &ClosedWindow,
        report: &ModeReport,
        update: &TrackUpdate,
        with_temperature: bool,
        now: OffsetDateTime,
    ) -> Vec<Alert> {
        let tracker = &self.tracker.config;
        let reference = report
            .shape
            .get(report.reference_component)
            .map(|c| c.sensor_id.clone())
            .or_else(|| closed.coverage.first().map(|c| c.sensor_id.clone()));
        let Some(sensor_id) = reference else {
            return Vec::new();
        };
        let valid: u64 = closed
            .coverage
            .iter()
            .map(|c| c.samples - c.flagged - c.missing - c.misaligned)
            .sum();
        let all: u64 = closed.coverage.iter().map(|c| c.samples).sum();
        let flagged_fraction = if all == 0 {
            1.0
        } else {
            1.0 - valid as f64 / all as f64
        };
        let mut alerts = Vec::new();
        let window_ns = (self.config.window_s * 1e9) as i64;
        let mut raise = |residual: &Estimate, windows: usize, test: &str, rate: String| {
            let span_ns = window_ns.saturating_mul(windows as i64);
            alerts.push(Alert {
                format_version: JSON_FORMAT_VERSION,
                building: self.id.clone(),
                sensor_id: sensor_id.clone(),
                kind: AlertKind::ModalShift,
                level: AlertLevel::Exceeded,
                value: -100.0 * residual.value,
                standard_uncertainty: 100.0 * residual.standard_uncertainty,
                coverage_factor: residual.coverage_factor,
                threshold: 100.0 * tracker.threshold_relative,
                unit: UNIT_PERCENT.into(),
                window_s: self.config.window_s * windows as f64,
                flagged_fraction,
                statement: format!(
                    "Track {} ({:?}, {:.4} Hz): frequency {:.3} % below its environmental \
                     baseline{} (k = {:.2}, ν = {:.0}), by the {test}{}. {rate}, the \
                     building's budget {} false modal_shift a year shared by its {} alerting \
                     tracks. The reference sensor of the mode's shape names the alert.",
                    update.track,
                    update.direction,
                    report.frequency_hz.value,
                    -100.0 * residual.value,
                    if with_temperature {
                        " (temperature regressed out)"
                    } else {
                        " (no temperature source: the baseline is a constant)"
                    },
                    residual.coverage_factor,
                    residual.dof,
                    if test.starts_with("sequential") {
                        String::new()
                    } else {
                        format!(
                            "; drop beyond {:.3} % even at the interval's near end",
                            100.0 * tracker.threshold_relative
                        )
                    },
                    self.config.tracker.false_alarms_per_year,
                    self.config.alert_modes_per_direction
                        * self.config.ssi.channels.directions.len(),
                ),
                at: now,
                late: closed.late,
                window_start_ns: Some(closed.end_ns.saturating_sub(span_ns)),
                window_end_ns: Some(closed.end_ns),
                first_sequence: None,
                last_sequence: None,
            });
        };
        if update.verdict == ShiftVerdict::Shift {
            if let Some(r) = &update.residual_relative {
                raise(
                    r,
                    1,
                    "single-window test",
                    format!(
                        "False-alarm probability of this test {:.2e} per window",
                        tracker.window_false_alarm_probability()
                    ),
                );
            }
        }
        if update.block_verdict == Some(ShiftVerdict::Shift) {
            if let Some(r) = &update.block_mean_relative {
                raise(
                    r,
                    tracker.average_windows.max(1),
                    "block-mean test",
                    format!(
                        "False-alarm probability of this test {:.2e} per block",
                        tracker.block_false_alarm_probability()
                    ),
                );
            }
        }
        if update.cusum_verdict == Some(ShiftVerdict::Shift) {
            if let (Some(r), Some(h)) = (&update.residual_relative, update.cusum_threshold) {
                raise(
                    r,
                    1,
                    "sequential (CUSUM) test",
                    format!(
                        "Its CUSUM of the residuals, tuned to a drop of {} standard \
                         uncertainties, reached h = {h:.2}: mean run length to a false alarm at \
                         least {:.0} windows (Lorden's bound e^h)",
                        tracker.cusum_shift,
                        h.exp()
                    ),
                );
            }
        }
        alerts
    }
}

/// What made a window's points invalid, per sensor, in words: the warnings of a window that
/// was still identified (a refusal says it in `refused`).
fn coverage_warnings(coverage: &[ModalSensorCoverage], alignment_tolerance: f64) -> Vec<String> {
    let mut out = Vec::new();
    for c in coverage {
        if c.calibration_suspect > 0 {
            out.push(format!(
                "sensor {}: {} of {} grid points flagged calibration_suspect by the gateway's \
                 field health checks: used, since a gain error moves no frequency or damping; \
                 its shape components are marked calibration_suspect",
                c.sensor_id, c.calibration_suspect, c.samples
            ));
        }
        if c.misaligned > 0 {
            out.push(format!(
                "sensor {}: {} of {} grid points misaligned: {}",
                c.sensor_id,
                c.misaligned,
                c.samples,
                misaligned_cause(alignment_tolerance)
            ));
        }
    }
    out
}

fn misaligned_cause(alignment_tolerance: f64) -> String {
    format!(
        "its samples lie further than alignment_tolerance ({alignment_tolerance} of a period) \
         from the window's grid, or come at another rate (its node's clock ticks in another \
         phase or at another rate than the first sensor's), and are left out, never resampled"
    )
}

/// Why a window was refused, in words: for too little of a channel usable, the sensor's grid
/// points by cause, the largest first, so that a misaligned clock reads `misaligned`.
pub fn refusal(
    error: &ModalError,
    coverage: &[ModalSensorCoverage],
    alignment_tolerance: f64,
) -> String {
    let ModalError::TooMuchMissing {
        sensor_id,
        direction,
        valid_fraction,
        required,
    } = error
    else {
        return error.to_string();
    };
    let Some(c) = coverage.iter().find(|c| c.sensor_id.as_str() == sensor_id) else {
        return error.to_string();
    };
    let mut causes = [
        (c.misaligned, "misaligned"),
        (c.missing, "missing (no sample: a gap)"),
        (
            c.flagged,
            "flagged (a quality flag other than calibration_suspect, or a non-finite value)",
        ),
    ];
    causes.sort_by_key(|c| std::cmp::Reverse(c.0));
    let listed: Vec<String> = causes
        .iter()
        .filter(|(n, _)| *n > 0)
        .map(|(n, what)| format!("{n} {what}"))
        .collect();
    let main = if causes[0].0 > 0 {
        causes[0].1.split(' ').next().unwrap_or("invalid")
    } else {
        "lost to the decimation filter's margin around invalid stretches"
    };
    let mut text = format!(
        "sensor {sensor_id}, direction {}: {main}: only {:.1} % of the window is usable, {:.1} % \
         required; of its {} grid points {}",
        format!("{direction:?}").to_lowercase(),
        100.0 * valid_fraction,
        100.0 * required,
        c.samples,
        if listed.is_empty() {
            "none is invalid, but the filter's margins took the rest".to_string()
        } else {
            listed.join(", ")
        }
    );
    if c.misaligned > 0 && causes[0].0 == c.misaligned {
        text.push_str(": ");
        text.push_str(&misaligned_cause(alignment_tolerance));
    }
    text
}
