//! The event service's messages (PROTOCOL.md §3.11): a building's event report, signed as
//! alerts are, and the list of a building's events its queryable answers.

use serde::{Deserialize, Serialize};
use time::OffsetDateTime;

use crate::json::JsonMessage;
use crate::keys::{BuildingId, EventId, SensorId};
use crate::messages::{ModalDirection, ModalEstimate};

/// What an event service's signature covers: these bytes, then the report's JSON.
pub const EVENT_SIGNING_CONTEXT: &[u8] = b"triax event v1\0";

/// A report as published: its JSON text exactly as signed, with the event service's Ed25519
/// signature over `EVENT_SIGNING_CONTEXT ‖ event_json`.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SignedEvent {
    pub format_version: u32,
    /// Always `ed25519`.
    pub algorithm: String,
    pub public_key_hex: String,
    /// The report's JSON, byte for byte as signed.
    pub event_json: String,
    pub signature_hex: String,
}

impl JsonMessage for SignedEvent {
    const WHAT: &'static str = "signed event";
    fn format_version(&self) -> u32 {
        self.format_version
    }
}

impl SignedEvent {
    /// The bytes a signature covers.
    pub fn signing_message(event_json: &str) -> Vec<u8> {
        let mut m = EVENT_SIGNING_CONTEXT.to_vec();
        m.extend_from_slice(event_json.as_bytes());
        m
    }
}

/// A building's state after an event.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum EventTag {
    Green,
    Yellow,
    Red,
}

/// A limit's verdict.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum EventVerdict {
    Below,
    Possible,
    Exceeded,
}

/// JSON has no infinity: an infinite ν travels as `null` and comes back infinite.
mod finite_or_null {
    use serde::{Deserialize, Deserializer, Serializer};

    pub fn serialize<S: Serializer>(v: &f64, s: S) -> Result<S::Ok, S::Error> {
        if v.is_finite() {
            s.serialize_f64(*v)
        } else {
            s.serialize_none()
        }
    }

    pub fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<f64, D::Error> {
        Ok(Option::<f64>::deserialize(d)?.unwrap_or(f64::INFINITY))
    }
}

/// A parameter: `value ± coverage_factor·standard_uncertainty` holds the truth with probability
/// `coverage_probability`; `dof` null when infinite; for a peak the instant it occurred and,
/// for a rotated component, its angle.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EventParameter {
    pub value: f64,
    pub standard_uncertainty: f64,
    #[serde(with = "finite_or_null")]
    pub dof: f64,
    pub coverage_factor: f64,
    pub coverage_probability: f64,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub at_ns: Option<i64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub angle_deg: Option<f64>,
}

/// One building direction's parameters at one sensor.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EventAxis {
    pub direction: ModalDirection,
    pub pga_mps2: EventParameter,
    pub pgv_mps: EventParameter,
    pub pgd_m: EventParameter,
    pub arias_mps: EventParameter,
    pub cav_mps: EventParameter,
    /// Absent when the record's Arias intensity is not positive.
    pub d5_95_s: Option<EventParameter>,
}

/// One period of a sensor's 5 %-damped pseudo-spectral acceleration, m/s².
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EventSpectralOrdinate {
    pub period_s: f64,
    /// Within what the band supports.
    pub usable: bool,
    pub x: EventParameter,
    pub y: EventParameter,
    pub z: EventParameter,
    pub rotd50: EventParameter,
    pub rotd100: EventParameter,
}

/// DIN 4150-3's peak component velocity in one direction, mm/s, and its dominant frequency, Hz.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EventVibration {
    pub direction: ModalDirection,
    pub peak_velocity_mmps: EventParameter,
    pub dominant_frequency_hz: Option<EventParameter>,
}

/// A sensor's residual tilt, degrees.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EventTilt {
    pub roll_before_deg: f64,
    pub pitch_before_deg: f64,
    pub roll_after_deg: f64,
    pub pitch_after_deg: f64,
    pub roll_change_deg: EventParameter,
    pub pitch_change_deg: EventParameter,
}

/// Everything one sensor's record says of the event.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EventSensor {
    pub sensor_id: SensorId,
    pub floor: i32,
    pub height_m: f64,
    pub calibration_versions: Vec<u64>,
    /// Grid points of the window, and those without a usable sample (flagged, missing, off the
    /// grid): set to the baseline, and the sensor's values `flagged`.
    pub samples: u64,
    pub invalid_samples: u64,
    /// Standard deviation of one band-passed noise sample per direction (x, y, z), m/s².
    pub noise_mps2: [f64; 3],
    pub axes: Vec<EventAxis>,
    pub pga_rotd50_mps2: EventParameter,
    pub pga_rotd100_mps2: EventParameter,
    pub spectrum: Vec<EventSpectralOrdinate>,
    pub vibration: Vec<EventVibration>,
    pub tilt: Option<EventTilt>,
}

/// One storey pair's drift ratio in one direction.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EventDrift {
    pub lower_floor: i32,
    pub upper_floor: i32,
    pub storey_height_m: f64,
    pub direction: ModalDirection,
    pub lower_sensors: Vec<SensorId>,
    pub upper_sensors: Vec<SensorId>,
    /// The band-passed drift ratio (dimensionless).
    pub drift_ratio: EventParameter,
    /// Bound on the true (unfiltered) drift ratio's distance from the band-passed one, and its
    /// parts (PROTOCOL.md §3.11).
    pub bias_bound: f64,
    pub bias_below_band: f64,
    pub bias_band_gain: f64,
    pub bias_integration: f64,
    pub bias_alignment: f64,
    pub fundamental_hz: f64,
    pub fundamental_from_event: bool,
}

/// A mode's frequency in a modes window (§3.10).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EventModeFrequency {
    pub direction: ModalDirection,
    pub track: Option<u64>,
    pub window_start_ns: i64,
    pub frequency_hz: ModalEstimate,
}

/// A mode's frequency drop from the window before the event to the first one after, %.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EventFrequencyDrop {
    pub direction: ModalDirection,
    pub track: Option<u64>,
    pub drop_percent: ModalEstimate,
}

/// The building's modes around the event, from the modes service.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EventModes {
    /// The fundamental of each direction in the last window wholly before the event.
    pub before: Vec<EventModeFrequency>,
    /// The same in the first window wholly after it; empty until that window arrives.
    pub after: Vec<EventModeFrequency>,
    pub drops: Vec<EventFrequencyDrop>,
}

/// A configured limit's judgement.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EventLimit {
    pub name: String,
    pub quantity: String,
    pub threshold: f64,
    pub unit: String,
    pub severity: EventTag,
    /// Null when no item could be judged.
    pub verdict: Option<EventVerdict>,
    /// The item that decides it (the worst verdict), its estimate and bias bound.
    pub item: Option<String>,
    pub value: Option<EventParameter>,
    pub bias_bound: f64,
    pub decision_factor: Option<f64>,
    pub false_exceeded_probability: f64,
    pub items: u64,
    pub tag: EventTag,
}

/// How the report was computed.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EventProcessing {
    pub band_low_hz: f64,
    pub band_high_hz: f64,
    pub band_order: u32,
    pub damping: f64,
    pub coverage_probability: f64,
    pub false_exceeded_probability: f64,
    pub clock_uncertainty_s: f64,
    pub din_low_hz: f64,
    pub din_high_hz: f64,
    pub pre_event_s: f64,
    pub post_event_s: f64,
}

/// One building's event, published signed on `triax/<building>/event/<event_id>`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EventReport {
    pub format_version: u32,
    pub building: BuildingId,
    pub event_id: EventId,
    /// 1 for the first report; a later one replaces it whole.
    pub revision: u32,
    /// `first`, or why it was revised: `modes_after` (the first modes window after the event).
    pub revision_reason: String,
    pub start_ns: i64,
    pub end_ns: i64,
    pub coincidence_ns: i64,
    pub truncated: bool,
    pub window_start_ns: i64,
    pub window_end_ns: i64,
    pub triggered_sensors: Vec<SensorId>,
    pub tag: EventTag,
    pub drivers: Vec<String>,
    pub limits: Vec<EventLimit>,
    pub sensors: Vec<EventSensor>,
    pub drifts: Vec<EventDrift>,
    pub modes: EventModes,
    pub processing: EventProcessing,
    /// Files the service wrote beside the report, relative to the event's directory.
    pub files: Vec<String>,
    pub caveats: Vec<String>,
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub late: bool,
    #[serde(with = "time::serde::rfc3339")]
    pub reported_at: OffsetDateTime,
}

impl JsonMessage for EventReport {
    const WHAT: &'static str = "event report";
    fn format_version(&self) -> u32 {
        self.format_version
    }
}

/// One line of a building's list of events.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EventSummary {
    pub event_id: EventId,
    pub revision: u32,
    pub start_ns: i64,
    pub end_ns: i64,
    pub tag: EventTag,
    pub drivers: Vec<String>,
    /// The largest horizontal RotD100 PGA of any sensor, m/s², and the largest drift ratio.
    pub peak_floor_acceleration_mps2: Option<f64>,
    pub max_drift_ratio: Option<f64>,
    #[serde(with = "time::serde::rfc3339")]
    pub reported_at: OffsetDateTime,
}

/// The answer to a query on `triax/<building>/events`: the building's events, newest first.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EventList {
    pub format_version: u32,
    pub building: BuildingId,
    /// The event service's signing key (hex): which service answers.
    pub public_key_hex: String,
    #[serde(with = "time::serde::rfc3339")]
    pub reported_at: OffsetDateTime,
    pub events: Vec<EventSummary>,
}

impl JsonMessage for EventList {
    const WHAT: &'static str = "event list";
    fn format_version(&self) -> u32 {
        self.format_version
    }
}

/// A small valid report, for tests and examples across the workspace.
pub mod sample {
    use super::*;

    fn p(value: f64, u: f64) -> EventParameter {
        EventParameter {
            value,
            standard_uncertainty: u,
            dof: f64::INFINITY,
            coverage_factor: 1.96,
            coverage_probability: 0.95,
            at_ns: None,
            angle_deg: None,
        }
    }

    /// An event of `building` with one sensor and one limit, `yellow` from a possible drift.
    pub fn report(building: &str, event_id: &str) -> EventReport {
        let sensor = SensorId::new("roof").expect("valid");
        let axis = |direction| EventAxis {
            direction,
            pga_mps2: p(1.2, 0.01),
            pgv_mps: p(0.08, 0.001),
            pgd_m: p(0.01, 0.0002),
            arias_mps: p(0.3, 0.002),
            cav_mps: p(4.0, 0.02),
            d5_95_s: Some(p(12.0, 0.05)),
        };
        EventReport {
            format_version: crate::json::JSON_FORMAT_VERSION,
            // Callers pass literal ids; a bad one is a bug in the caller's test.
            building: BuildingId::new(building).expect("valid building id"),
            event_id: EventId::new(event_id).expect("valid event id"),
            revision: 1,
            revision_reason: "first".into(),
            start_ns: 1_800_000_000_000_000_000,
            end_ns: 1_800_000_030_000_000_000,
            coincidence_ns: 1_800_000_000_500_000_000,
            truncated: false,
            window_start_ns: 1_799_999_980_000_000_000,
            window_end_ns: 1_800_000_050_000_000_000,
            triggered_sensors: vec![sensor.clone()],
            tag: EventTag::Yellow,
            drivers: vec!["immediate occupancy".into()],
            limits: vec![EventLimit {
                name: "immediate occupancy".into(),
                quantity: "drift_ratio".into(),
                threshold: 0.005,
                unit: "1".into(),
                severity: EventTag::Red,
                verdict: Some(EventVerdict::Possible),
                item: Some("storey 0–5 x".into()),
                value: Some(p(0.0049, 0.0001)),
                bias_bound: 0.000_01,
                decision_factor: Some(1.96),
                false_exceeded_probability: 0.025,
                items: 2,
                tag: EventTag::Yellow,
            }],
            sensors: vec![EventSensor {
                sensor_id: sensor,
                floor: 5,
                height_m: 17.5,
                calibration_versions: vec![3],
                samples: 7000,
                invalid_samples: 0,
                noise_mps2: [0.002; 3],
                axes: vec![
                    axis(ModalDirection::X),
                    axis(ModalDirection::Y),
                    axis(ModalDirection::Z),
                ],
                pga_rotd50_mps2: p(1.0, 0.01),
                pga_rotd100_mps2: p(1.3, 0.01),
                spectrum: vec![EventSpectralOrdinate {
                    period_s: 1.0,
                    usable: true,
                    x: p(3.0, 0.02),
                    y: p(2.0, 0.02),
                    z: p(0.5, 0.01),
                    rotd50: p(2.5, 0.02),
                    rotd100: p(3.1, 0.02),
                }],
                vibration: vec![],
                tilt: None,
            }],
            drifts: vec![],
            modes: EventModes::default(),
            processing: EventProcessing {
                band_low_hz: 0.1,
                band_high_hz: 40.0,
                band_order: 4,
                damping: 0.05,
                coverage_probability: 0.95,
                false_exceeded_probability: 0.025,
                clock_uncertainty_s: 0.0005,
                din_low_hz: 1.0,
                din_high_hz: 80.0,
                pre_event_s: 20.0,
                post_event_s: 20.0,
            },
            files: vec!["report.html".into()],
            caveats: vec![],
            late: false,
            reported_at: OffsetDateTime::from_unix_timestamp(1_800_000_060).expect("in range"),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::json::{from_json, to_json};
    use crate::signing::{read_event, sign_event, AlertTrust, TrustedKeys};

    #[test]
    fn a_report_round_trips_signed_and_a_forgery_says_so() {
        let r = sample::report("hq", "20270115T080112Z");
        let back: EventReport = from_json(&to_json(&r)).unwrap();
        assert_eq!(back, r);
        let text = String::from_utf8(to_json(&r)).unwrap();
        assert!(text.contains("\"dof\":null"), "infinite ν travels as null");
        let key = ed25519_dalek::SigningKey::from_bytes(&[7; 32]);
        let trusted = TrustedKeys::new(vec![key.verifying_key()]);
        let signed = sign_event(&r, &key);
        let (got, trust) = read_event(&to_json(&signed), &trusted).unwrap();
        assert_eq!(got, r);
        assert!(trust.is_verified());
        let (_, trust) = read_event(&to_json(&signed), &TrustedKeys::default()).unwrap();
        assert!(matches!(trust, AlertTrust::UnknownKey { .. }));
        let mut forged = signed.clone();
        forged.event_json = forged.event_json.replace("\"yellow\"", "\"green\"");
        let (got, trust) = read_event(&to_json(&forged), &trusted).unwrap();
        assert_eq!(got.tag, EventTag::Green);
        assert!(matches!(trust, AlertTrust::BadSignature { .. }));
        let (_, trust) = read_event(&to_json(&r), &trusted).unwrap();
        assert_eq!(trust, AlertTrust::Unsigned);
        // A report signed as an alert would be does not verify as an event.
        assert!(from_json::<SignedEvent>(b"{\"format_version\":1}").is_err());
    }
}
