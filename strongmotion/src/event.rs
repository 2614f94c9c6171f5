//! One building's event, whole: every sensor's parameters, the storeys' drift, the sensors'
//! residual tilt, the DIN 4150-3 evaluation, and the configured limits judged.

use serde::Deserialize;

use crate::decision::{decision_factor, judge, tag_of, Tag, Verdict};
use crate::din4150::{
    dominant_frequency, foundation_mmps, top_floor_long_mmps, top_floor_short_mmps, BuildingClass,
};
use crate::drift::{storey_drifts, StoreyDrift};
use crate::estimate::{Budget, Estimate};
use crate::filter::BandConfig;
use crate::parameters::{sensor_parameters, ParameterConfig, SensorParameters, Value};
use crate::process::{axis, integrate_adjoint, ProcessError, Processed, SensorRecord};
use crate::tilt::{residual_tilt, ResidualTilt};

/// How an event is analysed.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct EventConfig {
    pub parameters: ParameterConfig,
    /// Standard uncertainty of a sensor's time stamps against the others', s.
    pub clock_uncertainty_s: f64,
    /// After the event's end, seconds before the tilt's "after" stretch begins (the coda).
    pub tilt_settle_s: f64,
    /// DIN 4150-3's band: velocity between these corners, Hz (high: at most 0.4 of the rate).
    pub din_low_hz: f64,
    pub din_high_hz: f64,
}

impl Default for EventConfig {
    fn default() -> Self {
        EventConfig {
            parameters: ParameterConfig::default(),
            clock_uncertainty_s: 0.000_5,
            tilt_settle_s: 10.0,
            din_low_hz: 1.0,
            din_high_hz: 80.0,
        }
    }
}

/// The event's span, s from the reference instant.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct EventSpan {
    pub start_s: f64,
    pub end_s: f64,
}

/// A sensor's DIN 4150-3 velocities: per building direction the peak velocity (mm/s) in the
/// standard's band and its dominant frequency (Hz).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DinVelocity {
    pub peak_mmps: [Value; 3],
    pub frequency_hz: [Option<Estimate>; 3],
}

/// A sensor's tilt, where both stretches had data.
#[derive(Debug, Clone, PartialEq)]
pub struct SensorTilt {
    pub sensor_id: String,
    pub tilt: ResidualTilt,
}

/// Everything an event's records say.
#[derive(Debug, Clone, PartialEq)]
pub struct EventAnalysis {
    pub sensors: Vec<SensorParameters>,
    pub din: Vec<DinVelocity>,
    pub drifts: Vec<StoreyDrift>,
    /// Sensors the drift had to leave out (another sample rate).
    pub drift_left_out: Vec<String>,
    pub tilts: Vec<SensorTilt>,
}

/// Analyses an event from its sensors' records (`records[i]` gives `sensors[i]`);
/// `fundamental_hz` is the building's first mode per direction if known (for the drift's
/// bound); `seed` fixes the bootstraps.
pub fn analyse(
    records: &[SensorRecord],
    span: EventSpan,
    fundamental_hz: [Option<f64>; 2],
    config: &EventConfig,
    seed: u64,
) -> Result<EventAnalysis, ProcessError> {
    let mut processed = Vec::with_capacity(records.len());
    let mut sensors = Vec::with_capacity(records.len());
    let mut din = Vec::with_capacity(records.len());
    let mut tilts = Vec::new();
    let prob = config.parameters.coverage_probability;
    for (j, r) in records.iter().enumerate() {
        let p = Processed::new(r, &config.parameters.band, span.start_s)?;
        sensors.push(sensor_parameters(
            &p,
            &config.parameters,
            seed.wrapping_mul(0x9E37_79B9).wrapping_add(j as u64),
        ));
        processed.push(p);
        // DIN's own band; its velocity peaks to first order.
        let band = BandConfig {
            low_hz: config.din_low_hz,
            high_hz: Some(config.din_high_hz.min(0.4 * r.sample_rate_hz)),
            order: 4,
        };
        let q = Processed::new(r, &band, span.start_s)?;
        let velocity: [(Value, Option<Estimate>); 3] = std::array::from_fn(|k| {
            let v = &q.vel_b[k];
            let (i, d) = v.iter().enumerate().fold((0, 0.0f64), |(bi, bv), (i, x)| {
                if x.abs() > bv {
                    (i, x.abs())
                } else {
                    (bi, bv)
                }
            });
            let sign = if v[i] < 0.0 { -1.0 } else { 1.0 };
            let terms = [(axis(k), integrate_adjoint(&q.delta(i, sign), q.dt))];
            let (cal, noise) = q.covariance(&terms, &terms);
            let mut b = Budget::new();
            b.add(cal, q.covariance_dof).add(noise, q.noise_dof);
            let peak = Value {
                estimate: b.estimate(d, prob).scaled(1000.0),
                at_s: Some(q.time_s(i)),
                angle_deg: None,
            };
            let f = dominant_frequency(v, i, q.dt, noise.max(0.0).sqrt()).map(|(f, u)| {
                let mut b = Budget::new();
                b.add(u * u, q.noise_dof);
                b.estimate(f, prob)
            });
            (peak, f)
        });
        din.push(DinVelocity {
            peak_mmps: velocity.map(|x| x.0),
            frequency_hz: velocity.map(|x| x.1),
        });
        // Tilt: the valid samples before the event, and after it has settled.
        let settle = span.end_s + config.tilt_settle_s;
        let (mut before, mut after) = (Vec::new(), Vec::new());
        for i in 0..r.len() {
            if !r.valid[i] {
                continue;
            }
            let t = r.time_s(i);
            if t < span.start_s {
                before.push(r.accel_mps2[i]);
            } else if t >= settle {
                after.push(r.accel_mps2[i]);
            }
        }
        if let Some(tilt) = residual_tilt(&before, &after, None, prob) {
            tilts.push(SensorTilt {
                sensor_id: r.sensor_id.clone(),
                tilt,
            });
        }
    }
    let mut heights: Vec<(String, f64)> = records
        .iter()
        .map(|r| (r.sensor_id.clone(), r.height_m))
        .collect();
    heights.sort_by(|a, b| a.1.total_cmp(&b.1));
    let (drifts, drift_left_out) =
        storey_drifts(&processed, config.clock_uncertainty_s, fundamental_hz, prob);
    Ok(EventAnalysis {
        sensors,
        din,
        drifts,
        drift_left_out,
        tilts,
    })
}

/// What a limit is on.
#[derive(Debug, Clone, Copy, PartialEq, Deserialize)]
#[serde(rename_all = "snake_case", tag = "quantity")]
pub enum Quantity {
    /// Inter-storey drift ratio, every storey and direction (dimensionless); the band-pass's
    /// bias bound widens the interval.
    DriftRatio,
    /// Peak floor acceleration, the horizontal RotD100 of every sensor, m/s².
    PeakFloorAcceleration,
    /// Peak floor acceleration, vertical, every sensor, m/s².
    PeakVerticalAcceleration,
    /// Peak floor velocity, horizontal, every sensor and direction, m/s.
    PeakFloorVelocity,
    /// Pseudo-spectral acceleration RotD50 at a period (one of the configured ones), every
    /// sensor, m/s².
    PsaRotd50 { period_s: f64 },
    /// Residual tilt, the larger of roll's and pitch's change, every sensor, degrees.
    ResidualTilt,
    /// Drop of a mode's frequency after the event against before, % (positive: lower).
    FrequencyDrop,
    /// DIN 4150-3, foundation (lowest floor), every direction: the peak velocity over the
    /// class's curve at its dominant frequency (a ratio; the threshold is 1).
    Din4150Foundation { class: BuildingClass },
    /// DIN 4150-3, top floor, horizontal, short-term value (ratio).
    Din4150TopFloor { class: BuildingClass },
    /// DIN 4150-3, top floor, horizontal, long-term value (ratio).
    Din4150TopFloorLongTerm { class: BuildingClass },
}

impl Quantity {
    pub fn name(&self) -> &'static str {
        match self {
            Quantity::DriftRatio => "drift_ratio",
            Quantity::PeakFloorAcceleration => "peak_floor_acceleration",
            Quantity::PeakVerticalAcceleration => "peak_vertical_acceleration",
            Quantity::PeakFloorVelocity => "peak_floor_velocity",
            Quantity::PsaRotd50 { .. } => "psa_rotd50",
            Quantity::ResidualTilt => "residual_tilt",
            Quantity::FrequencyDrop => "frequency_drop",
            Quantity::Din4150Foundation { .. } => "din4150_foundation",
            Quantity::Din4150TopFloor { .. } => "din4150_top_floor",
            Quantity::Din4150TopFloorLongTerm { .. } => "din4150_top_floor_long_term",
        }
    }

    pub fn unit(&self) -> &'static str {
        match self {
            Quantity::DriftRatio => "1",
            Quantity::PeakFloorAcceleration
            | Quantity::PeakVerticalAcceleration
            | Quantity::PsaRotd50 { .. } => "m/s^2",
            Quantity::PeakFloorVelocity => "m/s",
            Quantity::ResidualTilt => "deg",
            Quantity::FrequencyDrop => "%",
            Quantity::Din4150Foundation { .. }
            | Quantity::Din4150TopFloor { .. }
            | Quantity::Din4150TopFloorLongTerm { .. } => "1",
        }
    }
}

/// A configured limit.
#[derive(Debug, Clone, PartialEq)]
pub struct Limit {
    pub name: String,
    pub quantity: Quantity,
    /// In the quantity's unit (1 for DIN 4150-3's ratios).
    pub threshold: f64,
    /// What `exceeded` makes the building.
    pub severity: Tag,
}

/// One item a limit judged: what it is, its estimate, and a bias bound added to the interval.
#[derive(Debug, Clone, PartialEq)]
pub struct Item {
    pub label: String,
    pub estimate: Estimate,
    pub bias_bound: f64,
    /// From flagged data: judged `possible` at most.
    pub flagged: bool,
}

/// A limit's judgement: the item that decides it (the worst verdict, then the largest
/// `(value − threshold)/u`), with its factor.
#[derive(Debug, Clone, PartialEq)]
pub struct LimitJudgement {
    pub name: String,
    pub quantity: Quantity,
    pub threshold: f64,
    pub severity: Tag,
    /// None when nothing could be judged (no item).
    pub verdict: Option<Verdict>,
    pub item: Option<Item>,
    /// The decision's one-sided factor for the deciding item, and the per-limit false
    /// `exceeded` probability it keeps (shared by `items`).
    pub decision_factor: f64,
    pub false_exceeded_probability: f64,
    pub items: usize,
    pub tag: Tag,
}

/// A mode's frequency drop, as the service computed it from the modes windows around the event.
#[derive(Debug, Clone, PartialEq)]
pub struct FrequencyDrop {
    pub label: String,
    /// Percent, positive when the frequency fell.
    pub drop_percent: Estimate,
}

/// The items a quantity has in `analysis`.
pub fn items(quantity: &Quantity, analysis: &EventAnalysis, drops: &[FrequencyDrop]) -> Vec<Item> {
    let item = |label: String, estimate: Estimate, flagged: bool| Item {
        label,
        estimate,
        bias_bound: 0.0,
        flagged,
    };
    let flagged_sensor = |id: &str| {
        analysis
            .sensors
            .iter()
            .any(|s| s.sensor_id == id && s.flagged)
    };
    let lowest = analysis
        .sensors
        .iter()
        .map(|s| s.height_m)
        .fold(f64::INFINITY, f64::min);
    let highest = analysis
        .sensors
        .iter()
        .map(|s| s.height_m)
        .fold(f64::NEG_INFINITY, f64::max);
    let ratio = |v: &Value, reference: f64, slope: f64, f: Option<&Estimate>| -> Estimate {
        let e = v.estimate;
        let mut b = Budget::new();
        b.add((e.standard_uncertainty / reference).powi(2), e.dof);
        if let Some(f) = f {
            b.add(
                (e.value * slope * f.standard_uncertainty / (reference * reference)).powi(2),
                f.dof,
            );
        }
        b.estimate(e.value / reference, e.coverage_probability)
    };
    match quantity {
        Quantity::DriftRatio => analysis
            .drifts
            .iter()
            .map(|d| Item {
                label: format!(
                    "storey {}–{} {}",
                    d.lower_floor,
                    d.upper_floor,
                    ["x", "y"][d.direction]
                ),
                estimate: d.drift_ratio.estimate,
                bias_bound: d.bias_bound,
                flagged: d.flagged,
            })
            .collect(),
        Quantity::PeakFloorAcceleration => analysis
            .sensors
            .iter()
            .map(|s| {
                item(
                    format!("{} horizontal (RotD100)", s.sensor_id),
                    s.pga_rotd100.estimate,
                    s.flagged,
                )
            })
            .collect(),
        Quantity::PeakVerticalAcceleration => analysis
            .sensors
            .iter()
            .map(|s| {
                item(
                    format!("{} z", s.sensor_id),
                    s.axes[2].pga.estimate,
                    s.flagged,
                )
            })
            .collect(),
        Quantity::PeakFloorVelocity => analysis
            .sensors
            .iter()
            .flat_map(|s| {
                (0..2).map(move |k| {
                    item(
                        format!("{} {}", s.sensor_id, ["x", "y"][k]),
                        s.axes[k].pgv.estimate,
                        s.flagged,
                    )
                })
            })
            .collect(),
        Quantity::PsaRotd50 { period_s } => analysis
            .sensors
            .iter()
            .filter_map(|s| {
                s.spectrum
                    .iter()
                    .find(|o| (o.period_s - period_s).abs() < 1e-9)
                    .map(|o| {
                        item(
                            format!("{} at {} s", s.sensor_id, period_s),
                            o.rotd50.estimate,
                            s.flagged,
                        )
                    })
            })
            .collect(),
        Quantity::ResidualTilt => analysis
            .tilts
            .iter()
            .map(|t| {
                item(
                    t.sensor_id.clone(),
                    t.tilt.change_deg,
                    flagged_sensor(&t.sensor_id),
                )
            })
            .collect(),
        Quantity::FrequencyDrop => drops
            .iter()
            .map(|d| item(d.label.clone(), d.drop_percent, false))
            .collect(),
        Quantity::Din4150Foundation { class } => analysis
            .sensors
            .iter()
            .zip(&analysis.din)
            .filter(|(s, _)| s.height_m <= lowest)
            .flat_map(|(s, d)| {
                (0..3).filter_map(move |k| {
                    let f = d.frequency_hz[k]?;
                    let (reference, slope) = foundation_mmps(*class, f.value);
                    Some(item(
                        format!(
                            "{} {} at {:.1} Hz",
                            s.sensor_id,
                            ["x", "y", "z"][k],
                            f.value
                        ),
                        ratio(&d.peak_mmps[k], reference, slope, Some(&f)),
                        s.flagged,
                    ))
                })
            })
            .collect(),
        Quantity::Din4150TopFloor { class } | Quantity::Din4150TopFloorLongTerm { class } => {
            let reference = if matches!(quantity, Quantity::Din4150TopFloor { .. }) {
                top_floor_short_mmps(*class)
            } else {
                top_floor_long_mmps(*class)
            };
            analysis
                .sensors
                .iter()
                .zip(&analysis.din)
                .filter(|(s, _)| s.height_m >= highest)
                .flat_map(|(s, d)| {
                    (0..2).map(move |k| {
                        item(
                            format!("{} {}", s.sensor_id, ["x", "y"][k]),
                            ratio(&d.peak_mmps[k], reference, 0.0, None),
                            s.flagged,
                        )
                    })
                })
                .collect()
        }
    }
}

/// Judges every limit; the building's tag is the worst limit's, and the drivers are the
/// limits at that tag.
pub fn judge_limits(
    analysis: &EventAnalysis,
    limits: &[Limit],
    drops: &[FrequencyDrop],
    false_exceeded_probability: f64,
) -> (Vec<LimitJudgement>, Tag, Vec<String>) {
    let mut out = Vec::new();
    for limit in limits {
        let items = items(&limit.quantity, analysis, drops);
        let m = items.len();
        let mut best: Option<(Verdict, f64, Item, f64)> = None;
        for it in items {
            let k = decision_factor(&it.estimate, false_exceeded_probability, m);
            // The bias bound widens the interval on both sides: the band may have lost motion,
            // or (integration) added a little.
            let widened = Estimate {
                standard_uncertainty: it.estimate.standard_uncertainty
                    + it.bias_bound / k.max(1e-12),
                ..it.estimate
            };
            let Some(mut v) = judge(&widened, k, limit.threshold) else {
                continue;
            };
            if it.flagged && v == Verdict::Exceeded {
                v = Verdict::Possible;
            }
            let score =
                (it.estimate.value - limit.threshold) / widened.standard_uncertainty.max(1e-300);
            let better = match &best {
                None => true,
                Some((bv, bs, _, _)) => (v, score) > (*bv, *bs),
            };
            if better {
                best = Some((v, score, it, k));
            }
        }
        let (verdict, item, k) = match best {
            Some((v, _, it, k)) => (Some(v), Some(it), k),
            None => (None, None, f64::NAN),
        };
        out.push(LimitJudgement {
            name: limit.name.clone(),
            quantity: limit.quantity,
            threshold: limit.threshold,
            severity: limit.severity,
            verdict,
            item,
            decision_factor: k,
            false_exceeded_probability,
            items: m,
            tag: verdict.map_or(Tag::Green, |v| tag_of(v, limit.severity)),
        });
    }
    let tag = out.iter().map(|j| j.tag).max().unwrap_or(Tag::Green);
    let drivers = if tag == Tag::Green {
        Vec::new()
    } else {
        out.iter()
            .filter(|j| j.tag == tag)
            .map(|j| j.name.clone())
            .collect()
    };
    (out, tag, drivers)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn analysis_with_drift(value: f64, u: f64, flagged: bool) -> EventAnalysis {
        let e = Budget::new()
            .add(u * u, f64::INFINITY)
            .estimate(value, 0.95);
        EventAnalysis {
            sensors: Vec::new(),
            din: Vec::new(),
            drifts: vec![StoreyDrift {
                lower_floor: 0,
                upper_floor: 1,
                storey_height_m: 3.5,
                direction: 0,
                lower_sensors: vec!["a".into()],
                upper_sensors: vec!["b".into()],
                drift_ratio: Value {
                    estimate: e,
                    at_s: Some(1.0),
                    angle_deg: None,
                },
                bias_bound: 0.0,
                bias_below_band: 0.0,
                bias_band_gain: 0.0,
                bias_integration: 0.0,
                bias_alignment: 0.0,
                fundamental_hz: 1.0,
                fundamental_from_event: false,
                flagged,
            }],
            drift_left_out: Vec::new(),
            tilts: Vec::new(),
        }
    }

    #[test]
    fn limits_tag_the_building_and_flags_cap_a_verdict() {
        let limits = [
            Limit {
                name: "immediate occupancy".into(),
                quantity: Quantity::DriftRatio,
                threshold: 0.005,
                severity: Tag::Yellow,
            },
            Limit {
                name: "life safety".into(),
                quantity: Quantity::DriftRatio,
                threshold: 0.015,
                severity: Tag::Red,
            },
        ];
        let (j, tag, drivers) = judge_limits(
            &analysis_with_drift(0.01, 0.0005, false),
            &limits,
            &[],
            0.025,
        );
        assert_eq!(j[0].verdict, Some(Verdict::Exceeded));
        assert_eq!(j[1].verdict, Some(Verdict::Below));
        assert_eq!(tag, Tag::Yellow);
        assert_eq!(drivers, vec!["immediate occupancy".to_string()]);
        let (_, tag, drivers) = judge_limits(
            &analysis_with_drift(0.02, 0.0005, false),
            &limits,
            &[],
            0.025,
        );
        assert_eq!((tag, drivers), (Tag::Red, vec!["life safety".to_string()]));
        // Flagged data never say `exceeded`.
        let (j, tag, _) = judge_limits(
            &analysis_with_drift(0.02, 0.0005, true),
            &limits,
            &[],
            0.025,
        );
        assert_eq!(j[1].verdict, Some(Verdict::Possible));
        assert_eq!(tag, Tag::Yellow);
        // Nothing to judge: no verdict, green.
        let none = Limit {
            name: "tilt".into(),
            quantity: Quantity::ResidualTilt,
            threshold: 0.1,
            severity: Tag::Red,
        };
        let (j, tag, drivers) =
            judge_limits(&analysis_with_drift(0.0, 0.1, false), &[none], &[], 0.025);
        assert_eq!((j[0].verdict, tag, drivers.len()), (None, Tag::Green, 0));
    }
}
