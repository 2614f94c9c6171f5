//! The report message (PROTOCOL.md §3.11) made from an event's analysis, and revised when the
//! first modes window after the event arrives.

use time::OffsetDateTime;
use triax_protocol::event::{
    EventAxis, EventDrift, EventFrequencyDrop, EventLimit, EventModeFrequency, EventModes,
    EventParameter, EventProcessing, EventReport, EventSensor, EventSpectralOrdinate, EventTag,
    EventTilt, EventVerdict, EventVibration,
};
use triax_protocol::messages::{BuildingModes, ModalDirection, ModalEstimate};
use triax_protocol::{BuildingId, EventId, SensorId};
use triax_strongmotion::decision::{Tag, Verdict};
use triax_strongmotion::estimate::{Budget, Estimate};
use triax_strongmotion::event::{
    judge_limits, EventAnalysis, FrequencyDrop, LimitJudgement, Quantity,
};
use triax_strongmotion::parameters::Value;

use crate::building::Pending;
use crate::config::BuildingConfig;
use crate::gather::Gathered;

/// An estimate on the wire, its time made absolute.
pub fn parameter(v: &Value, origin_ns: i64) -> EventParameter {
    EventParameter {
        value: v.estimate.value,
        standard_uncertainty: v.estimate.standard_uncertainty,
        dof: v.estimate.dof,
        coverage_factor: v.estimate.coverage_factor,
        coverage_probability: v.estimate.coverage_probability,
        at_ns: v.at_s.map(|s| origin_ns + (s * 1e9).round() as i64),
        angle_deg: v.angle_deg,
    }
}

fn bare(e: &Estimate) -> EventParameter {
    EventParameter {
        value: e.value,
        standard_uncertainty: e.standard_uncertainty,
        dof: e.dof,
        coverage_factor: e.coverage_factor,
        coverage_probability: e.coverage_probability,
        at_ns: None,
        angle_deg: None,
    }
}

fn modal(e: &Estimate) -> ModalEstimate {
    ModalEstimate {
        value: e.value,
        standard_uncertainty: e.standard_uncertainty,
        dof: e.dof,
        coverage_factor: e.coverage_factor,
        coverage_probability: e.coverage_probability,
    }
}

pub fn tag(t: Tag) -> EventTag {
    match t {
        Tag::Green => EventTag::Green,
        Tag::Yellow => EventTag::Yellow,
        Tag::Red => EventTag::Red,
    }
}

fn verdict(v: Verdict) -> EventVerdict {
    match v {
        Verdict::Below => EventVerdict::Below,
        Verdict::Possible => EventVerdict::Possible,
        Verdict::Exceeded => EventVerdict::Exceeded,
    }
}

const DIRECTIONS: [ModalDirection; 3] = [ModalDirection::X, ModalDirection::Y, ModalDirection::Z];

/// A limit's judgement on the wire.
pub fn limit(j: &LimitJudgement) -> EventLimit {
    EventLimit {
        name: j.name.clone(),
        quantity: j.quantity.name().to_owned(),
        threshold: j.threshold,
        unit: j.quantity.unit().to_owned(),
        severity: tag(j.severity),
        verdict: j.verdict.map(verdict),
        item: j.item.as_ref().map(|i| i.label.clone()),
        value: j.item.as_ref().map(|i| bare(&i.estimate)),
        bias_bound: j.item.as_ref().map_or(0.0, |i| i.bias_bound),
        decision_factor: j.decision_factor.is_finite().then_some(j.decision_factor),
        false_exceeded_probability: j.false_exceeded_probability,
        items: j.items as u64,
        tag: tag(j.tag),
    }
}

/// The fundamental of each horizontal direction in a modes window: its lowest-frequency mode.
pub fn fundamentals(w: &BuildingModes) -> Vec<EventModeFrequency> {
    [ModalDirection::X, ModalDirection::Y]
        .iter()
        .filter_map(|d| {
            w.modes
                .iter()
                .filter(|m| m.direction == *d)
                .min_by(|a, b| a.frequency_hz.value.total_cmp(&b.frequency_hz.value))
                .map(|m| EventModeFrequency {
                    direction: *d,
                    track: m.track,
                    window_start_ns: w.window_start_ns,
                    frequency_hz: m.frequency_hz,
                })
        })
        .collect()
}

/// The drop of each fundamental from `before` to `after`, %: `100·(f_b − f_a)/f_b`, first order,
/// ν by Welch–Satterthwaite, `k` at the estimates' coverage.
pub fn drops(
    before: &[EventModeFrequency],
    after: &[EventModeFrequency],
) -> Vec<EventFrequencyDrop> {
    before
        .iter()
        .filter_map(|b| {
            let a = after
                .iter()
                .find(|a| a.track.is_some() && a.track == b.track)
                .or_else(|| after.iter().find(|a| a.direction == b.direction))?;
            let (fb, fa) = (b.frequency_hz.value, a.frequency_hz.value);
            if fb <= 0.0 {
                return None;
            }
            let mut budget = Budget::new();
            budget
                .add(
                    (100.0 * fa / (fb * fb) * b.frequency_hz.standard_uncertainty).powi(2),
                    b.frequency_hz.dof,
                )
                .add(
                    (100.0 / fb * a.frequency_hz.standard_uncertainty).powi(2),
                    a.frequency_hz.dof,
                );
            let e = budget.estimate(100.0 * (fb - fa) / fb, b.frequency_hz.coverage_probability);
            Some(EventFrequencyDrop {
                direction: b.direction,
                track: b.track,
                drop_percent: modal(&e),
            })
        })
        .collect()
}

fn strong_drops(d: &[EventFrequencyDrop]) -> Vec<FrequencyDrop> {
    d.iter()
        .map(|x| FrequencyDrop {
            label: format!(
                "fundamental {}",
                match x.direction {
                    ModalDirection::X => "x",
                    ModalDirection::Y => "y",
                    ModalDirection::Z => "z",
                }
            ),
            drop_percent: Estimate {
                value: x.drop_percent.value,
                standard_uncertainty: x.drop_percent.standard_uncertainty,
                dof: x.drop_percent.dof,
                coverage_factor: x.drop_percent.coverage_factor,
                coverage_probability: x.drop_percent.coverage_probability,
            },
        })
        .collect()
}

/// Everything the report is made of besides the analysis.
pub struct ReportContext<'a> {
    pub building: &'a BuildingId,
    pub config: &'a BuildingConfig,
    pub pending: &'a Pending,
    pub event_id: EventId,
    pub gathered: &'a [Gathered],
    pub sensor_ids: &'a [SensorId],
    pub modes: EventModes,
    pub caveats: Vec<String>,
    pub files: Vec<String>,
    pub late: bool,
    pub now: OffsetDateTime,
}

/// The first report of an event.
pub fn build(analysis: &EventAnalysis, cx: ReportContext<'_>) -> EventReport {
    let origin = cx.pending.window_start_ns;
    let (judged, t, drivers) = judge_limits(
        analysis,
        &cx.config.limits,
        &strong_drops(&cx.modes.drops),
        cx.config.false_exceeded_probability,
    );
    let sensors = analysis
        .sensors
        .iter()
        .zip(&analysis.din)
        .zip(cx.gathered)
        .map(|((s, din), g)| {
            let axes = (0..3)
                .map(|k| {
                    let a = &s.axes[k];
                    EventAxis {
                        direction: DIRECTIONS[k],
                        pga_mps2: parameter(&a.pga, origin),
                        pgv_mps: parameter(&a.pgv, origin),
                        pgd_m: parameter(&a.pgd, origin),
                        arias_mps: parameter(&a.arias, origin),
                        cav_mps: parameter(&a.cav, origin),
                        d5_95_s: a.d5_95.as_ref().map(|v| parameter(v, origin)),
                    }
                })
                .collect();
            let tilt = analysis
                .tilts
                .iter()
                .find(|t| t.sensor_id == s.sensor_id)
                .map(|t| {
                    let x = &t.tilt;
                    EventTilt {
                        roll_before_deg: x.roll_before_deg,
                        pitch_before_deg: x.pitch_before_deg,
                        roll_after_deg: x.roll_after_deg,
                        pitch_after_deg: x.pitch_after_deg,
                        roll_change_deg: bare(&x.roll_change_deg),
                        pitch_change_deg: bare(&x.pitch_change_deg),
                    }
                });
            EventSensor {
                // The analysis is of the configured sensors, whose ids were validated.
                sensor_id: SensorId::new(s.sensor_id.clone())
                    .unwrap_or_else(|_| cx.sensor_ids[0].clone()),
                floor: s.floor,
                height_m: s.height_m,
                calibration_versions: g.calibration_versions.clone(),
                samples: s.samples as u64,
                invalid_samples: s.invalid_samples as u64,
                noise_mps2: s.noise_mps2,
                axes,
                pga_rotd50_mps2: parameter(&s.pga_rotd50, origin),
                pga_rotd100_mps2: parameter(&s.pga_rotd100, origin),
                spectrum: s
                    .spectrum
                    .iter()
                    .map(|o| EventSpectralOrdinate {
                        period_s: o.period_s,
                        usable: o.usable,
                        x: parameter(&o.axes[0], origin),
                        y: parameter(&o.axes[1], origin),
                        z: parameter(&o.axes[2], origin),
                        rotd50: parameter(&o.rotd50, origin),
                        rotd100: parameter(&o.rotd100, origin),
                    })
                    .collect(),
                vibration: (0..3)
                    .map(|k| EventVibration {
                        direction: DIRECTIONS[k],
                        peak_velocity_mmps: parameter(&din.peak_mmps[k], origin),
                        dominant_frequency_hz: din.frequency_hz[k].as_ref().map(bare),
                    })
                    .collect(),
                tilt,
            }
        })
        .collect();
    let ids = |v: &[String]| {
        v.iter()
            .filter_map(|s| SensorId::new(s.clone()).ok())
            .collect()
    };
    let drifts = analysis
        .drifts
        .iter()
        .map(|d| EventDrift {
            lower_floor: d.lower_floor,
            upper_floor: d.upper_floor,
            storey_height_m: d.storey_height_m,
            direction: DIRECTIONS[d.direction],
            lower_sensors: ids(&d.lower_sensors),
            upper_sensors: ids(&d.upper_sensors),
            drift_ratio: parameter(&d.drift_ratio, origin),
            bias_bound: d.bias_bound,
            bias_below_band: d.bias_below_band,
            bias_band_gain: d.bias_band_gain,
            bias_integration: d.bias_integration,
            bias_alignment: d.bias_alignment,
            fundamental_hz: d.fundamental_hz,
            fundamental_from_event: d.fundamental_from_event,
        })
        .collect();
    let p = &cx.config.processing;
    let rate = cx
        .gathered
        .first()
        .map_or(100.0, |g| g.record.sample_rate_hz);
    let band_high_hz = p.parameters.band.high_hz.unwrap_or(0.4 * rate);
    let e = &cx.pending.event;
    EventReport {
        format_version: triax_protocol::JSON_FORMAT_VERSION,
        building: cx.building.clone(),
        event_id: cx.event_id,
        revision: 1,
        revision_reason: "first".into(),
        start_ns: e.start_ns,
        end_ns: e.end_ns,
        coincidence_ns: e.coincidence_ns,
        truncated: e.truncated,
        window_start_ns: cx.pending.window_start_ns,
        window_end_ns: cx.pending.window_end_ns,
        triggered_sensors: e
            .sensors
            .iter()
            .filter_map(|&i| cx.sensor_ids.get(i).cloned())
            .collect(),
        tag: tag(t),
        drivers,
        limits: judged.iter().map(limit).collect(),
        sensors,
        drifts,
        modes: cx.modes,
        processing: EventProcessing {
            band_low_hz: p.parameters.band.low_hz,
            band_high_hz,
            band_order: p.parameters.band.order as u32,
            damping: p.parameters.damping,
            coverage_probability: p.parameters.coverage_probability,
            false_exceeded_probability: cx.config.false_exceeded_probability,
            clock_uncertainty_s: p.clock_uncertainty_s,
            din_low_hz: p.din_low_hz,
            din_high_hz: p.din_high_hz,
            pre_event_s: cx.config.pre_event_s,
            post_event_s: cx.config.post_event_s,
        },
        files: cx.files,
        caveats: cx.caveats,
        late: cx.late,
        reported_at: cx.now,
    }
}

/// The report revised with the first modes window after the event: the fundamentals after, the
/// drops, the frequency limits judged again, the tag and drivers again.
pub fn with_modes_after(
    report: &EventReport,
    after: &BuildingModes,
    config: &BuildingConfig,
    now: OffsetDateTime,
) -> EventReport {
    let mut r = report.clone();
    r.revision += 1;
    r.revision_reason = "modes_after".into();
    r.modes.after = fundamentals(after);
    r.modes.drops = drops(&r.modes.before, &r.modes.after);
    let frequency: Vec<_> = config
        .limits
        .iter()
        .filter(|l| l.quantity == Quantity::FrequencyDrop)
        .cloned()
        .collect();
    let empty = EventAnalysis {
        sensors: Vec::new(),
        din: Vec::new(),
        drifts: Vec::new(),
        drift_left_out: Vec::new(),
        tilts: Vec::new(),
    };
    let (judged, _, _) = judge_limits(
        &empty,
        &frequency,
        &strong_drops(&r.modes.drops),
        config.false_exceeded_probability,
    );
    for j in judged {
        if let Some(slot) = r
            .limits
            .iter_mut()
            .find(|l| l.name == j.name && l.quantity == "frequency_drop")
        {
            *slot = limit(&j);
        }
    }
    r.tag = r
        .limits
        .iter()
        .map(|l| l.tag)
        .max()
        .unwrap_or(EventTag::Green);
    r.drivers = if r.tag == EventTag::Green {
        Vec::new()
    } else {
        r.limits
            .iter()
            .filter(|l| l.tag == r.tag)
            .map(|l| l.name.clone())
            .collect()
    };
    r.reported_at = now;
    r
}

/// The event's id: its start, to the second, UTC (`20270115T080112Z`); unique in a building,
/// since two events are at least `quiet_s` apart.
pub fn event_id(start_ns: i64) -> EventId {
    let t = OffsetDateTime::from_unix_timestamp_nanos(i128::from(start_ns))
        .unwrap_or(OffsetDateTime::UNIX_EPOCH);
    let text = format!(
        "{:04}{:02}{:02}T{:02}{:02}{:02}Z",
        t.year(),
        u8::from(t.month()),
        t.day(),
        t.hour(),
        t.minute(),
        t.second()
    );
    // Digits and two letters: always a valid id.
    EventId::new(text).unwrap_or_else(|_| EventId::new("event").expect("valid"))
}
