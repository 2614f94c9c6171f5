//! The low-rate JSON messages: signed calibration pushes and their acknowledgements, registry
//! catch-up requests, gateway status, tilt, alerts.

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};
use time::OffsetDateTime;

use crate::batch::Mode;
use crate::json::{from_json, JsonError, JsonMessage};
use crate::keys::{BuildingId, SensorId};
use crate::record::CalibrationRecord;

/// Signature algorithm of [`SignedRecord`].
pub const SIGNATURE_ALGORITHM: &str = "ed25519";

/// Prefix of every signed message, so a signature made for a record can never be taken for a
/// signature of anything else.
pub const SIGNING_CONTEXT: &[u8] = b"triax calibration record v1\0";

/// A calibration record signed by a lab key.
///
/// The record travels as the exact JSON text that was signed (`record_json`), so no
/// canonicalisation is needed: the verifier checks the signature over
/// `SIGNING_CONTEXT ‖ record_json` bytes, then parses the same bytes.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SignedRecord {
    pub format_version: u32,
    /// Always [`SIGNATURE_ALGORITHM`].
    pub algorithm: String,
    /// Signer's public key, 32 bytes in lowercase hex.
    pub public_key_hex: String,
    /// The record's JSON, byte for byte as signed.
    pub record_json: String,
    /// Signature, 64 bytes in lowercase hex.
    pub signature_hex: String,
}

impl JsonMessage for SignedRecord {
    const WHAT: &'static str = "signed calibration record";
    fn format_version(&self) -> u32 {
        self.format_version
    }
}

impl SignedRecord {
    /// The bytes a signature covers.
    pub fn signing_message(record_json: &str) -> Vec<u8> {
        let mut m = SIGNING_CONTEXT.to_vec();
        m.extend_from_slice(record_json.as_bytes());
        m
    }

    /// Parses the enclosed record. Call only after the signature was verified.
    pub fn record(&self) -> Result<CalibrationRecord, JsonError> {
        from_json(self.record_json.as_bytes())
    }
}

/// A gateway's answer to a calibration push.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PushAck {
    pub format_version: u32,
    pub building: BuildingId,
    pub sensor_id: SensorId,
    /// Which gateway answered.
    pub gateway: String,
    pub outcome: PushOutcome,
    #[serde(with = "time::serde::rfc3339")]
    pub at: OffsetDateTime,
}

impl JsonMessage for PushAck {
    const WHAT: &'static str = "push acknowledgement";
    fn format_version(&self) -> u32 {
        self.format_version
    }
}

/// Accepted (the version is durable and in force) or refused with a reason.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(tag = "status", rename_all = "snake_case", deny_unknown_fields)]
pub enum PushOutcome {
    Accepted {
        version: u64,
        /// The same version with the same content was already stored (an idempotent retry).
        already_stored: bool,
    },
    Refused {
        reason: RefusalReason,
        detail: String,
    },
}

/// Why a push was refused.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum RefusalReason {
    /// The payload is not a signed record.
    Malformed,
    /// The signing key is not among the gateway's trusted lab keys.
    UnknownKey,
    /// The signature does not verify.
    BadSignature,
    /// The record does not load into a corrector.
    InvalidRecord,
    /// The record's sensor is not the sensor in the key.
    WrongSensor,
    /// Older version, or same version with other content: a replay or a rollback.
    StaleVersion,
    /// The record could not be made durable.
    StoreFailure,
}

/// A gateway's catch-up request, the payload of a query on
/// `triax/<building>/calibration/registry`.
///
/// The registry answers with one reply per [`SignedRecord`] of the building's sensors that is
/// newer than `have` says: every version above `have[sensor]`, or every version of a sensor the
/// gateway does not list, in increasing version order per sensor.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RegistryRequest {
    pub format_version: u32,
    /// The version in force for each sensor the gateway has a calibration for.
    #[serde(default)]
    pub have: BTreeMap<SensorId, u64>,
}

impl JsonMessage for RegistryRequest {
    const WHAT: &'static str = "registry request";
    fn format_version(&self) -> u32 {
        self.format_version
    }
}

/// Per-sensor state reported by a gateway.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SensorStatus {
    pub sensor_id: SensorId,
    #[serde(
        default,
        with = "time::serde::rfc3339::option",
        skip_serializing_if = "Option::is_none"
    )]
    pub last_seen: Option<OffsetDateTime>,
    pub batches: u64,
    pub samples: u64,
    /// Batches that came after a jump in sequence numbers.
    pub gaps: u64,
    /// Sequence numbers lost in those jumps.
    pub missing_batches: u64,
    /// Batches fetched from the node's buffer and published flagged `late` (§5.4).
    #[serde(default)]
    pub late_batches: u64,
    pub duplicates: u64,
    /// Malformed payloads on this sensor's key.
    pub rejects: u64,
    /// Samples published with any quality flag set.
    pub flagged_samples: u64,
    /// Whether the sensor's keys are declared to Zenoh (`declared_keys_mib`): a sensor
    /// streaming undeclared costs the gateway more CPU per batch.
    #[serde(default)]
    pub keys_declared: bool,
    /// Version in force; none when uncalibrated.
    pub calibration_version: Option<u64>,
    pub mode: Mode,
    /// Validity of the record in force (absent when uncalibrated; `valid_until` also when the
    /// record is valid until superseded), so that a console can warn before expiry.
    #[serde(
        default,
        with = "time::serde::rfc3339::option",
        skip_serializing_if = "Option::is_none"
    )]
    pub valid_from: Option<OffsetDateTime>,
    #[serde(
        default,
        with = "time::serde::rfc3339::option",
        skip_serializing_if = "Option::is_none"
    )]
    pub valid_until: Option<OffsetDateTime>,
    /// The verdict of the sensor's latest calibration health report (§3.9); absent before the
    /// first or when the gateway's health checks are off.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub health: Option<HealthVerdict>,
    /// While the record in force is suspect: samples stamped at or after this time carry
    /// `calibration_suspect`, ns.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub suspect_from_ns: Option<i64>,
    /// The record in force, only in the answer to a one-sensor query (`sensor=<id>`): the
    /// certificate an operator reads (lab, certificate, validity, domain).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub calibration_record: Option<Box<CalibrationRecord>>,
}

/// A gateway's status, answered on `triax/<building>/status`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct GatewayStatus {
    pub format_version: u32,
    pub building: BuildingId,
    pub gateway: String,
    #[serde(with = "time::serde::rfc3339")]
    pub started_at: OffsetDateTime,
    #[serde(with = "time::serde::rfc3339")]
    pub reported_at: OffsetDateTime,
    /// Payloads that did not decode, on any key.
    pub malformed: u64,
    /// Corrected batches not published because the publisher fell behind (drop-oldest).
    pub dropped: u64,
    pub pushes_accepted: u64,
    pub pushes_refused: u64,
    /// Raw payloads on a key that is not a concrete raw key of this building, by reason
    /// (`wildcard`, `other_building`, `malformed`): counted and skipped.
    #[serde(default)]
    pub refused_keys: BTreeMap<String, u64>,
    /// Raw batches skipped because they came from a new sensor id while the sensor table was
    /// full of calibrated and established sensors.
    #[serde(default)]
    pub over_capacity: u64,
    /// New uncalibrated sensor ids admitted; probationary ones that gave their place to a newer
    /// id; uncalibrated ones forgotten after a silence.
    #[serde(default)]
    pub admitted_sensors: u64,
    #[serde(default)]
    pub displaced_sensors: u64,
    #[serde(default)]
    pub expired_sensors: u64,
    /// The gateway's history of raw batches; absent when it keeps none.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub history: Option<HistoryStatus>,
    /// Gaps filled from the nodes' buffers; absent when backfill is off.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub backfill: Option<BackfillStatus>,
    /// Sensors the gateway knows; `sensors` is the page the query asked for.
    #[serde(default)]
    pub total_sensors: u64,
    /// Where the next page starts (the `offset` of the next query); absent on the last page.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub next_offset: Option<u64>,
    /// Sorted by id.
    pub sensors: Vec<SensorStatus>,
}

/// What a gateway's backfill has done since the gateway started (PROTOCOL.md §5.4).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct BackfillStatus {
    /// Queries sent to nodes' buffers.
    pub queries: u64,
    /// Batches the gaps (and the gateway's own downtime) asked for.
    pub wanted_batches: u64,
    /// Batches received, corrected and published flagged `late`.
    pub late_batches: u64,
    /// Replies that were not a batch of the hole asked for: counted and skipped.
    pub rejected_replies: u64,
    /// Queries that ended in an error or timed out.
    pub failed_queries: u64,
    /// Gaps not asked for: the backfill's queue was full.
    pub refused_requests: u64,
}

/// What a gateway's history holds and has done since the gateway started.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct HistoryStatus {
    /// On disk now, logs and indexes.
    pub bytes: u64,
    pub max_bytes: u64,
    pub retention_s: u64,
    pub segments: u64,
    /// First-sample times of the oldest and newest batches kept; absent when empty.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub oldest_ns: Option<i64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub newest_ns: Option<i64>,
    /// Batches kept since start.
    pub written_batches: u64,
    /// Batches not kept: the writer's queue was full (the disk did not keep up).
    pub dropped_batches: u64,
    /// Batches waiting for the writer now.
    pub queued_batches: u64,
    /// Segments and bytes removed by retention since start.
    pub deleted_segments: u64,
    pub deleted_bytes: u64,
    /// Blocks that failed their check when read (never served).
    pub damaged_blocks: u64,
    /// Flushes that failed (their batches are lost).
    pub write_errors: u64,
}

impl JsonMessage for GatewayStatus {
    const WHAT: &'static str = "gateway status";
    // About 300 bytes a sensor; a gateway sends at most 5000 a reply, and pages the rest.
    const MAX_BYTES: usize = 8 << 20;
    fn format_version(&self) -> u32 {
        self.format_version
    }
}

/// What a gateway says every second on `triax/<building>/heartbeat`: it is alive, and the last
/// batch it published per active sensor, so that a consumer notices a lost last batch.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Heartbeat {
    pub format_version: u32,
    pub building: BuildingId,
    pub gateway: String,
    /// Heartbeats since the gateway started; a jump means some were lost.
    pub sequence: u64,
    #[serde(with = "time::serde::rfc3339")]
    pub at: OffsetDateTime,
    /// Sensors with a batch published in the last 10 s.
    pub sensors: BTreeMap<SensorId, HeartbeatSensor>,
}

/// The last batch published for one sensor.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct HeartbeatSensor {
    pub last_sequence: u64,
    pub last_timestamp_ns: i64,
    /// The last batch published flagged `late` (a backfill), when one was in the last 10 s:
    /// its number and first-sample time.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub late_sequence: Option<u64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub late_timestamp_ns: Option<i64>,
}

impl JsonMessage for Heartbeat {
    const WHAT: &'static str = "heartbeat";
    // About 70 bytes a sensor: room for a gateway's 100 000.
    const MAX_BYTES: usize = 8 << 20;
    fn format_version(&self) -> u32 {
        self.format_version
    }
}

/// Inclination from the low band of a sensor's static-corrected output.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TiltSample {
    pub format_version: u32,
    pub sensor_id: SensorId,
    /// Time of the estimate, ns since the Unix epoch.
    pub timestamp_ns: i64,
    /// Rotation about x: atan2(a_y, a_z), degrees.
    pub roll_deg: f64,
    /// Elevation of the x axis above the horizontal: atan2(a_x, √(a_y² + a_z²)), degrees.
    pub pitch_deg: f64,
    /// Standard uncertainties (k = 1), degrees.
    pub roll_uncertainty_deg: f64,
    pub pitch_uncertainty_deg: f64,
    pub coverage_factor: f64,
    pub calibration_version: u64,
    /// [`crate::batch::flags`] bits of the samples behind this estimate.
    pub flags: u16,
}

impl JsonMessage for TiltSample {
    const WHAT: &'static str = "tilt sample";
    fn format_version(&self) -> u32 {
        self.format_version
    }
}

/// What an alert is about.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum AlertKind {
    PeakAcceleration,
    RmsAcceleration,
    DominantFrequency,
    TiltChange,
    Stale,
    /// A building mode's frequency moved beyond what the environment explains (the modal
    /// service, §3.10).
    ModalShift,
}

/// Decision under uncertainty, ISO/IEC 17025 §7.8.6 style with a guard band of k·u.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum AlertLevel {
    /// The lower bound of the k-interval is above the threshold.
    Exceeded,
    /// The k-interval straddles the threshold.
    Possible,
    /// No data from the sensor for longer than allowed.
    Stale,
}

/// An alert, published on `triax/<building>/alert/<sensor>`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Alert {
    pub format_version: u32,
    pub building: BuildingId,
    pub sensor_id: SensorId,
    pub kind: AlertKind,
    pub level: AlertLevel,
    /// Measured value and its standard uncertainty, in `unit`.
    pub value: f64,
    pub standard_uncertainty: f64,
    pub coverage_factor: f64,
    pub threshold: f64,
    pub unit: String,
    pub window_s: f64,
    /// Fraction of the window's samples that carried quality flags.
    pub flagged_fraction: f64,
    /// The decision rule and any caveat, in words.
    pub statement: String,
    #[serde(with = "time::serde::rfc3339")]
    pub at: OffsetDateTime,
    /// Raised late: the data it judged came from the gateway's history, after an outage or a
    /// partition kept it from the alerting service. Absent (false) for alerts on live data.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub late: bool,
    /// The judged window, by the sensor's clock: its first and last sample's (or tilt
    /// sample's) time, ns since the Unix epoch. Absent on `stale` alerts.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub window_start_ns: Option<i64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub window_end_ns: Option<i64>,
    /// Sequence numbers of the corrected batches holding the window's first and last sample.
    /// Absent on `stale` and `tilt_change` alerts (tilt samples carry none).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub first_sequence: Option<u64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub last_sequence: Option<u64>,
}

impl JsonMessage for Alert {
    const WHAT: &'static str = "alert";
    fn format_version(&self) -> u32 {
        self.format_version
    }
}

/// Answer of an alerting service to a query on `triax/<building>/alerting`: what it last
/// judged of each sensor of the building, so that "judged, below every limit" can be told from
/// "not judged" (a judgement below every limit publishes no alert).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AlertingStatus {
    pub format_version: u32,
    pub building: BuildingId,
    /// The service's alert-signing public key (hex): which service answers.
    pub public_key_hex: String,
    #[serde(with = "time::serde::rfc3339")]
    pub reported_at: OffsetDateTime,
    /// Sensors the service watches in this building, by id.
    pub sensors: Vec<SensorJudgement>,
}

impl JsonMessage for AlertingStatus {
    const WHAT: &'static str = "alerting status";
    fn format_version(&self) -> u32 {
        self.format_version
    }
}

/// One sensor's latest judgement of its acceleration window.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SensorJudgement {
    pub sensor_id: SensorId,
    /// When the service last received data of this sensor, by its clock.
    #[serde(with = "time::serde::rfc3339::option")]
    pub last_data_at: Option<OffsetDateTime>,
    /// When the window was last judged, by the service's clock; absent before the first.
    #[serde(with = "time::serde::rfc3339::option")]
    pub judged_at: Option<OffsetDateTime>,
    /// The judged window (as in an alert, §3.6).
    pub window_start_ns: Option<i64>,
    pub window_end_ns: Option<i64>,
    pub first_sequence: Option<u64>,
    pub last_sequence: Option<u64>,
    /// Why the latest batch's window was not judged, if it was not: `settling` (the window is
    /// not whole, or the baseline filter has not settled before its first sample).
    pub waiting: Option<String>,
    /// Per kind with a limit: `below` (judged, no alert), `possible` or `exceeded` (before
    /// rate limiting), or `not_judged` (no estimate: e.g. a quiet window's frequency).
    pub levels: BTreeMap<AlertKind, JudgedLevel>,
}

/// The outcome of one kind's judgement.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum JudgedLevel {
    Below,
    Possible,
    Exceeded,
    NotJudged,
}

/// What an alerting service's signature covers: these bytes, then the alert's JSON.
pub const ALERT_SIGNING_CONTEXT: &[u8] = b"triax alert v1\0";

/// An alert as published: its JSON text exactly as signed, with the alerting service's Ed25519
/// signature over `ALERT_SIGNING_CONTEXT ‖ alert_json`. Anyone who can reach a building's key
/// space can put a JSON alert there; only the holder of the service's key can sign one.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SignedAlert {
    pub format_version: u32,
    /// Always [`SIGNATURE_ALGORITHM`].
    pub algorithm: String,
    /// The alerting service's public key, 32 bytes in lowercase hex.
    pub public_key_hex: String,
    /// The alert's JSON, byte for byte as signed.
    pub alert_json: String,
    /// Signature, 64 bytes in lowercase hex.
    pub signature_hex: String,
}

impl JsonMessage for SignedAlert {
    const WHAT: &'static str = "signed alert";
    fn format_version(&self) -> u32 {
        self.format_version
    }
}

impl SignedAlert {
    /// The bytes a signature covers.
    pub fn signing_message(alert_json: &str) -> Vec<u8> {
        let mut m = ALERT_SIGNING_CONTEXT.to_vec();
        m.extend_from_slice(alert_json.as_bytes());
        m
    }
}

/// A value with its standard uncertainty, degrees of freedom and the interval it claims:
/// `value ± coverage_factor · standard_uncertainty` holds the truth with probability
/// `coverage_probability`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ModalEstimate {
    pub value: f64,
    pub standard_uncertainty: f64,
    /// Degrees of freedom; `null` in JSON when infinite.
    #[serde(with = "finite_or_null")]
    pub dof: f64,
    pub coverage_factor: f64,
    pub coverage_probability: f64,
}

/// JSON has no infinity: an infinite (or NaN) number travels as `null` and comes back infinite.
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

/// A horizontal (or vertical) direction of a building's frame (`z` up).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum ModalDirection {
    X,
    Y,
    Z,
}

/// The tracker's judgement of a mode's frequency against its environmental baseline.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ModalVerdict {
    /// The track's baseline is still being fitted.
    Training,
    /// The residual's interval is clear of the threshold.
    Normal,
    /// The residual's interval reaches the threshold.
    Possible,
    /// Even the near end of the residual's interval is beyond the threshold.
    Shift,
}

/// One component of a mode shape: one sensor's motion along one direction, relative to the
/// shape's reference component (exactly 1).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ModeShapeComponent {
    pub sensor_id: SensorId,
    pub direction: ModalDirection,
    /// In-phase part.
    pub real: ModalEstimate,
    /// Quadrature part.
    pub imag: ModalEstimate,
    /// Some of the sensor's samples in the window were flagged `calibration_suspect` (§2.3):
    /// its gain may be off, which moves this component but no frequency or damping.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub calibration_suspect: bool,
}

/// A track's mode shape pooled over windows: each in-phase component relative to the
/// reference component, the inverse-variance weighted mean of the windows', with the windows'
/// statistical uncertainty averaged down and the measurement chain's kept whole.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PooledShapeReport {
    /// Windows pooled.
    pub windows: usize,
    pub reference_component: usize,
    pub shape: Vec<PooledShapeComponent>,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PooledShapeComponent {
    pub sensor_id: SensorId,
    pub direction: ModalDirection,
    pub real: ModalEstimate,
    /// The sensor's samples were flagged `calibration_suspect` in this window.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub calibration_suspect: bool,
}

/// One identified mode, with its track's judgement.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ModeReport {
    /// The track the mode joined (stable across windows and restarts); absent when the window
    /// was not tracked.
    pub track: Option<u64>,
    /// Direction carrying most of the shape's energy.
    pub direction: ModalDirection,
    pub frequency_hz: ModalEstimate,
    /// Fraction of critical damping.
    pub damping_ratio: ModalEstimate,
    pub shape: Vec<ModeShapeComponent>,
    /// Index in `shape` of the component the shape is normalised to.
    pub reference_component: usize,
    /// The track's shape pooled over its last windows (this one included): what a window
    /// cannot resolve of two close modes, a day of windows can. Absent for an untracked mode.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub pooled_shape: Option<PooledShapeReport>,
    /// Model order of the representative pole, orders it was stable at, and jackknife
    /// replicates it was found in.
    pub order: usize,
    pub stable_orders: usize,
    pub replicates: usize,
    /// The baseline's frequency at this window's regressors, Hz; absent while training.
    pub predicted_hz: Option<f64>,
    /// `(f − predicted) / predicted` with a prediction's uncertainty and the guard band's
    /// coverage; absent while training.
    pub residual_relative: Option<ModalEstimate>,
    pub verdict: Option<ModalVerdict>,
    /// The mean relative residual of the block of windows this window completed, and its
    /// verdict; absent except on a block's last window.
    pub block_mean_relative: Option<ModalEstimate>,
    pub block_verdict: Option<ModalVerdict>,
    /// The coverage factor of the prediction interval that bounds `normal`; absent while
    /// training.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub normal_coverage_factor: Option<f64>,
    /// The sequential (CUSUM) test after this window; absent while training.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub cusum: Option<ModalCusum>,
}

/// The sequential test of a track: its statistic, the threshold at which it says `shift`,
/// and its verdict (`normal` or `shift`).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ModalCusum {
    pub statistic: f64,
    pub threshold: f64,
    pub verdict: ModalVerdict,
}

/// A mode selected in the stabilisation diagram but found in too few jackknife replicates to
/// be given an uncertainty: shown, never tracked.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct UnquantifiedModeReport {
    pub frequency_hz: f64,
    pub damping_ratio: f64,
    pub replicates: usize,
}

/// How much of one sensor's stream a window could use.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ModalSensorCoverage {
    pub sensor_id: SensorId,
    /// Grid points of the window.
    pub samples: u64,
    /// Points left invalid: a quality flag on the sample, no sample (a gap), or a sample off
    /// the grid by more than the alignment tolerance (or at another rate).
    pub flagged: u64,
    pub missing: u64,
    pub misaligned: u64,
    /// Calibration versions of the batches used.
    pub calibration_versions: Vec<u64>,
    /// Points whose sample was flagged `calibration_suspect` (§2.3) and nothing else: used
    /// for identification (a gain error moves no frequency or damping), counted here and not
    /// in `flagged`.
    #[serde(default, skip_serializing_if = "is_zero")]
    pub calibration_suspect: u64,
    /// The building model checked against this window's data for the sensor; absent when the
    /// window was refused.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub check: Option<ModalSensorCheck>,
}

/// What a window's data say of one sensor's declared mounting and its node's clock.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ModalSensorCheck {
    /// Angle between the building's vertical and the sensor's gravity through its declared
    /// mounting, degrees; absent when the streams carry no gravity.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub tilt_deg: Option<ModalEstimate>,
    /// Turn in plan beyond the declared mounting, degrees, counter-clockwise seen from above,
    /// from the floor's rigid motion; absent for a sensor alone on its floor.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub plan_rotation_deg: Option<ModalEstimate>,
    /// The node's clock offset against the building's median node, s (its sample stamped `t`
    /// is the motion at `t + offset`), from the modes' phases; absent without modes.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub time_offset_s: Option<ModalEstimate>,
    /// Findings that name the sensor, in words; absent when none.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub findings: Vec<String>,
}

fn is_zero(v: &u64) -> bool {
    *v == 0
}

/// The modes of a building over one window, published on `triax/<building>/modes` by the modal
/// service and kept, one per line, in its record.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BuildingModes {
    pub format_version: u32,
    pub building: BuildingId,
    /// The window's grid: first point and the end (exclusive), ns since the Unix epoch by the
    /// sensors' clocks, and its rate, Hz.
    pub window_start_ns: i64,
    pub window_end_ns: i64,
    pub sample_rate_hz: f64,
    /// Rate identification ran at after decimation, Hz (0 when refused).
    pub identification_rate_hz: f64,
    pub sensors: Vec<ModalSensorCoverage>,
    /// Mean temperature over the window from the configured source, °C; absent when none is
    /// configured or it gave nothing in the window.
    pub temperature_c: Option<f64>,
    /// The regressors the tracker was given, temperature first (empty: none).
    pub regressors: Vec<f64>,
    /// Whether the tracker judged this window (not when refused, or when a configured
    /// regressor was missing).
    pub tracked: bool,
    pub modes: Vec<ModeReport>,
    pub unquantified: Vec<UnquantifiedModeReport>,
    /// Why the window gave no identification; absent when it did.
    pub refused: Option<String>,
    /// What degraded an identified (or refused) window, each in words naming the sensor or
    /// the setting: samples used despite a flag, sensors left out, a diagram that had not
    /// settled, a window not tracked. Absent when empty.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub warnings: Vec<String>,
    /// Some of the window's batches were read back from the gateway's history.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub late: bool,
    #[serde(with = "time::serde::rfc3339")]
    pub identified_at: OffsetDateTime,
}

impl JsonMessage for BuildingModes {
    const WHAT: &'static str = "building modes";
    fn format_version(&self) -> u32 {
        self.format_version
    }
}

/// Small, valid messages for tests and examples across the workspace.
pub mod sample {
    use super::*;

    /// An `exceeded` peak-acceleration alert of `sensor` in `building`, naming its window.
    pub fn alert(building: &str, sensor: &str) -> Alert {
        Alert {
            format_version: crate::json::JSON_FORMAT_VERSION,
            // Callers pass literal ids; a bad one is a bug in the caller's test.
            building: BuildingId::new(building).expect("valid building id"),
            sensor_id: SensorId::new(sensor).expect("valid sensor id"),
            kind: AlertKind::PeakAcceleration,
            level: AlertLevel::Exceeded,
            value: 2.5,
            standard_uncertainty: 0.1,
            coverage_factor: 2.0,
            threshold: 1.0,
            unit: "m/s^2".into(),
            window_s: 10.0,
            flagged_fraction: 0.0,
            statement: "exceeded".into(),
            at: OffsetDateTime::from_unix_timestamp(1_800_000_010).expect("in range"),
            late: false,
            window_start_ns: Some(1_800_000_000_000_000_000),
            window_end_ns: Some(1_800_000_009_990_000_000),
            first_sequence: Some(0),
            last_sequence: Some(99),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::json::{to_json, JSON_FORMAT_VERSION};
    use crate::record::sample;

    fn t() -> OffsetDateTime {
        OffsetDateTime::from_unix_timestamp(1_800_000_000).unwrap()
    }

    fn round_trip<T: JsonMessage + PartialEq + std::fmt::Debug>(m: &T) {
        let back: T = from_json(&to_json(m)).unwrap();
        assert_eq!(&back, m);
    }

    #[test]
    fn building_modes_round_trip_with_infinite_degrees_of_freedom_as_null() {
        let estimate = |value: f64, dof: f64| ModalEstimate {
            value,
            standard_uncertainty: 0.001,
            dof,
            coverage_factor: 2.0,
            coverage_probability: 0.95,
        };
        let modes = BuildingModes {
            format_version: JSON_FORMAT_VERSION,
            building: BuildingId::new("hq").unwrap(),
            window_start_ns: 1_800_000_000_000_000_000,
            window_end_ns: 1_800_001_800_000_000_000,
            sample_rate_hz: 100.0,
            identification_rate_hz: 25.0,
            sensors: vec![ModalSensorCoverage {
                sensor_id: SensorId::new("roof").unwrap(),
                samples: 180_000,
                flagged: 1,
                missing: 2,
                misaligned: 3,
                calibration_versions: vec![4],
                calibration_suspect: 0,
                check: None,
            }],
            temperature_c: Some(12.5),
            regressors: vec![12.5],
            tracked: true,
            modes: vec![ModeReport {
                track: Some(0),
                direction: ModalDirection::X,
                frequency_hz: estimate(1.0, 11.0),
                damping_ratio: estimate(0.02, 11.0),
                shape: vec![ModeShapeComponent {
                    sensor_id: SensorId::new("roof").unwrap(),
                    direction: ModalDirection::X,
                    real: estimate(1.0, f64::INFINITY),
                    imag: estimate(0.0, f64::INFINITY),
                    calibration_suspect: false,
                }],
                reference_component: 0,
                pooled_shape: None,
                order: 20,
                stable_orders: 10,
                replicates: 12,
                predicted_hz: Some(1.001),
                residual_relative: Some(estimate(-0.001, 334.0)),
                verdict: Some(ModalVerdict::Normal),
                block_mean_relative: None,
                block_verdict: None,
                normal_coverage_factor: Some(1.97),
                cusum: Some(ModalCusum {
                    statistic: 0.5,
                    threshold: 11.6,
                    verdict: ModalVerdict::Normal,
                }),
            }],
            unquantified: Vec::new(),
            refused: None,
            warnings: Vec::new(),
            late: false,
            identified_at: t(),
        };
        round_trip(&modes);
        let text = String::from_utf8(to_json(&modes)).unwrap();
        assert!(text.contains(r#""dof":null"#), "{text}");
        assert!(!text.contains("late"), "absent when false: {text}");
        // The optional fields added since are absent when empty, and a message without them
        // (as an older service wrote it) reads as one with them empty.
        for field in ["warnings", "calibration_suspect"] {
            assert!(!text.contains(field), "{field} absent when empty: {text}");
        }
        let mut with = modes.clone();
        with.warnings = vec!["sensor roof: used despite calibration_suspect".into()];
        with.sensors[0].calibration_suspect = 7;
        with.sensors[0].check = Some(ModalSensorCheck {
            tilt_deg: Some(estimate(0.2, 11.0)),
            plan_rotation_deg: None,
            time_offset_s: Some(estimate(-0.02, 11.0)),
            findings: vec!["sensor roof: its node's clock is -20 ms off".into()],
        });
        with.modes[0].shape[0].calibration_suspect = true;
        round_trip(&with);
        let text = String::from_utf8(to_json(&with)).unwrap();
        assert!(text.contains(r#""calibration_suspect":7"#), "{text}");
        assert!(text.contains(r#""calibration_suspect":true"#), "{text}");
    }

    #[test]
    fn every_json_message_round_trips() {
        let record_json = String::from_utf8(to_json(&sample::record("acc-1", 4))).unwrap();
        let signed = SignedRecord {
            format_version: JSON_FORMAT_VERSION,
            algorithm: SIGNATURE_ALGORITHM.into(),
            public_key_hex: "ab".repeat(32),
            record_json,
            signature_hex: "cd".repeat(64),
        };
        round_trip(&signed);
        assert_eq!(signed.record().unwrap(), sample::record("acc-1", 4));
        assert!(SignedRecord::signing_message("{}").starts_with(SIGNING_CONTEXT));

        let b = BuildingId::new("hq").unwrap();
        let s = SensorId::new("acc-1").unwrap();
        for outcome in [
            PushOutcome::Accepted {
                version: 4,
                already_stored: false,
            },
            PushOutcome::Refused {
                reason: RefusalReason::StaleVersion,
                detail: "version 3 is not newer than 4".into(),
            },
        ] {
            round_trip(&PushAck {
                format_version: JSON_FORMAT_VERSION,
                building: b.clone(),
                sensor_id: s.clone(),
                gateway: "gw-hq".into(),
                outcome,
                at: t(),
            });
        }
        round_trip(&GatewayStatus {
            format_version: JSON_FORMAT_VERSION,
            building: b.clone(),
            gateway: "gw-hq".into(),
            started_at: t(),
            reported_at: t(),
            malformed: 2,
            dropped: 0,
            pushes_accepted: 1,
            pushes_refused: 1,
            refused_keys: [("wildcard".to_owned(), 3)].into_iter().collect(),
            over_capacity: 4,
            admitted_sensors: 5,
            displaced_sensors: 6,
            expired_sensors: 7,
            backfill: Some(BackfillStatus {
                queries: 2,
                wanted_batches: 30,
                late_batches: 28,
                rejected_replies: 1,
                failed_queries: 0,
                refused_requests: 0,
            }),
            history: Some(HistoryStatus {
                bytes: 1,
                max_bytes: 2,
                retention_s: 3,
                segments: 4,
                oldest_ns: Some(5),
                newest_ns: None,
                written_batches: 6,
                dropped_batches: 7,
                queued_batches: 8,
                deleted_segments: 9,
                deleted_bytes: 10,
                damaged_blocks: 11,
                write_errors: 12,
            }),
            total_sensors: 7,
            next_offset: Some(1),
            sensors: vec![SensorStatus {
                sensor_id: s.clone(),
                last_seen: Some(t()),
                batches: 10,
                samples: 1000,
                gaps: 1,
                missing_batches: 3,
                late_batches: 2,
                duplicates: 0,
                rejects: 1,
                flagged_samples: 100,
                keys_declared: true,
                calibration_version: Some(4),
                mode: Mode::Dynamic,
                valid_from: Some(t()),
                valid_until: None,
                health: Some(HealthVerdict::Watch),
                suspect_from_ns: None,
                calibration_record: Some(Box::new(sample::record("acc-1", 4))),
            }],
        });
        round_trip(&SensorHealthReport {
            format_version: JSON_FORMAT_VERSION,
            building: BuildingId::new("hq").unwrap(),
            sensor_id: s.clone(),
            calibration_version: 3,
            verdict: HealthVerdict::Suspect,
            suspect_since_ns: Some(-5),
            flagged_from_ns: Some(7),
            reported_at: t(),
            data_until_ns: Some(9),
            blocks: 600,
            quiet_stretches: 4,
            discontinuities: 1,
            calibration_checked: Some(true),
            gravity_direction: Some([0.0, 0.6, 0.8]),
            tests: vec![HealthTest {
                test: "stuck".into(),
                channel: Some(2),
                peer: None,
                verdict: HealthVerdict::Suspect,
                judged: true,
                statistic: Some(12.0),
                uncertainty: Some(1.0),
                unit: "s".into(),
                since_ns: Some(-5),
                evidence_nats: 0.0,
                observations: 600,
                reason: None,
                masked: None,
                loud: None,
            }],
            quality: StreamQuality {
                samples: 60_000,
                availability: 0.99,
                gaps: 1,
                latency_min_ms: Some(1.5),
                latency_max_ms: None,
            },
        });
        round_trip(&TiltSample {
            format_version: JSON_FORMAT_VERSION,
            sensor_id: s.clone(),
            timestamp_ns: 5,
            roll_deg: 0.5,
            pitch_deg: -0.25,
            roll_uncertainty_deg: 0.01,
            pitch_uncertainty_deg: 0.01,
            coverage_factor: 2.0,
            calibration_version: 4,
            flags: 0,
        });
        round_trip(&Alert {
            format_version: JSON_FORMAT_VERSION,
            building: b,
            sensor_id: s,
            kind: AlertKind::PeakAcceleration,
            level: AlertLevel::Possible,
            value: 0.9,
            standard_uncertainty: 0.1,
            coverage_factor: 2.0,
            threshold: 1.0,
            unit: "m/s^2".into(),
            window_s: 10.0,
            flagged_fraction: 0.0,
            statement: "interval 0.7..1.1 straddles 1.0".into(),
            at: t(),
            late: true,
            window_start_ns: Some(1_800_000_000_000_000_000),
            window_end_ns: Some(1_800_000_009_990_000_000),
            first_sequence: Some(3),
            last_sequence: Some(22),
        });
    }

    #[test]
    fn registry_request_round_trips_and_defaults_to_nothing_known() {
        let mut have = BTreeMap::new();
        have.insert(SensorId::new("acc-1").unwrap(), 3);
        let request = RegistryRequest {
            format_version: JSON_FORMAT_VERSION,
            have,
        };
        round_trip(&request);
        let text = to_json(&request);
        assert_eq!(text, br#"{"format_version":1,"have":{"acc-1":3}}"#);
        let empty: RegistryRequest = from_json(br#"{"format_version":1}"#).unwrap();
        assert!(empty.have.is_empty());
        assert!(from_json::<RegistryRequest>(br#"{"format_version":1,"hav":{}}"#).is_err());
        assert!(from_json::<RegistryRequest>(br#"{"format_version":1,"have":{"a/b":1}}"#).is_err());
    }

    #[test]
    fn ack_json_shape_is_documented() {
        let ack = PushAck {
            format_version: 1,
            building: BuildingId::new("hq").unwrap(),
            sensor_id: SensorId::new("a").unwrap(),
            gateway: "g".into(),
            outcome: PushOutcome::Refused {
                reason: RefusalReason::BadSignature,
                detail: "x".into(),
            },
            at: t(),
        };
        let v: serde_json::Value = serde_json::from_slice(&to_json(&ack)).unwrap();
        assert_eq!(v["outcome"]["status"], "refused");
        assert_eq!(v["outcome"]["reason"], "bad_signature");
        assert_eq!(v["at"], "2027-01-15T08:00:00Z");
    }
}

/// A verdict of the calibration health checks.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum HealthVerdict {
    /// Nothing found (or not yet judged: see the test's `judged`).
    Ok,
    /// Evidence is building: the sensor deserves a look.
    Watch,
    /// The calibration no longer holds as stated: the sensor is due for recalibration.
    Suspect,
}

impl HealthVerdict {
    pub fn as_str(self) -> &'static str {
        match self {
            HealthVerdict::Ok => "ok",
            HealthVerdict::Watch => "watch",
            HealthVerdict::Suspect => "suspect",
        }
    }
}

/// A sensor's calibration health under the record in force, published by its gateway on
/// `triax/<building>/health/<sensor>` and answered by its queryable there.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SensorHealthReport {
    pub format_version: u32,
    pub building: BuildingId,
    pub sensor_id: SensorId,
    /// The record the checks judge.
    pub calibration_version: u64,
    /// The worst verdict of the tests, or `suspect` while the sensor's samples carry
    /// `calibration_suspect` (a latched verdict outlives a gateway restart; the tests do not).
    pub verdict: HealthVerdict,
    /// Start of the evidence behind the earliest `suspect` test, sensor time, ns.
    pub suspect_since_ns: Option<i64>,
    /// Samples of this record stamped at or after this time carry `calibration_suspect`
    /// (PROTOCOL.md §2.3), live and in replays, ns; absent while the record is not suspect.
    pub flagged_from_ns: Option<i64>,
    /// When the gateway made this report, by its clock.
    #[serde(with = "time::serde::rfc3339")]
    pub reported_at: OffsetDateTime,
    /// Sensor time of the last sample the checks have seen, ns.
    pub data_until_ns: Option<i64>,
    /// Blocks judged, quiet stretches used by the gravity tests, and breaks in the stream
    /// (gaps, node restarts, rate changes), since the checks started on this record.
    pub blocks: u64,
    pub quiet_stretches: u64,
    pub discontinuities: u64,
    /// Whether the calibration itself (gains and offsets) has been checked: a gravity or
    /// co-located test judged. An `ok` sensor with `false` here is one nothing could be
    /// looked at for: no quiet minute, no local gravity, no pair. Absent from reports of
    /// gateways that predate it.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub calibration_checked: Option<bool>,
    /// The direction, in the sensor's frame, of the latest quiet stretch's mean reading through
    /// the record's static set (a unit vector: where gravity points for the sensor): what the
    /// gravity tests measured along. Absent before the first quiet stretch.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub gravity_direction: Option<[f64; 3]>,
    /// Every test, in a fixed order.
    pub tests: Vec<HealthTest>,
    /// The stream's quality, as seismic networks report it.
    pub quality: StreamQuality,
}

impl JsonMessage for SensorHealthReport {
    const WHAT: &'static str = "sensor health report";
    fn format_version(&self) -> u32 {
        self.format_version
    }
}

/// One health test's state.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct HealthTest {
    /// `gravity_absolute`, `gravity_relative`, `stuck`, `noise`, `spikes`, `clock`,
    /// `colocated_absolute` or `colocated_relative`.
    pub test: String,
    /// Output channel 0, 1 or 2 for the per-channel tests, the axis of A's frame for the
    /// co-located tests; null for the others.
    pub channel: Option<u8>,
    /// The other sensor of a co-located pair (`colocated_*` tests only).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub peer: Option<SensorId>,
    pub verdict: HealthVerdict,
    /// Whether the test has had the data it needs; a test not yet judged is `ok`.
    pub judged: bool,
    /// The test's statistic, in `unit`; absent before the first judgement.
    pub statistic: Option<f64>,
    /// Its standard uncertainty (k = 1), in `unit`.
    pub uncertainty: Option<f64>,
    /// `m/s^2` (gravity), `s` (stuck), `ratio` (noise over the record's `output_noise`),
    /// `1/h` (spikes), `ms` (clock), `1` (co-located: relative gain).
    pub unit: String,
    /// Since when the verdict holds (`watch`, `suspect`), sensor time, ns.
    pub since_ns: Option<i64>,
    /// The sequential test's accumulated log-likelihood ratio, nats (0 when not sequential).
    pub evidence_nats: f64,
    /// Observations judged: blocks, or quiet stretches for the gravity tests.
    pub observations: u64,
    /// Why the test is not judged, while `judged` is false: `no_data`, `no_quiet_stretch`,
    /// `few_quiet_stretches`, `no_local_gravity`, `baseline`, `no_stated_noise`, `masked`,
    /// `no_estimate` or `off` (PROTOCOL.md §3.9). Absent once judged.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub reason: Option<String>,
    /// Noise tests only: windows left unjudged because the building's motion masked the
    /// floor, and because transients filled them.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub masked: Option<u64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub loud: Option<u64>,
}

/// A stream's quality since the checks started on the record.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct StreamQuality {
    /// Samples received, and the share of the samples the stream's span should hold that
    /// arrived (1 when none were lost; duplicates not counted).
    pub samples: u64,
    pub availability: f64,
    /// Batches that came after a jump in sequence numbers.
    pub gaps: u64,
    /// Arrival at the gateway minus the batch's last sample time, by the gateway's clock, over
    /// the batches since the previous report, ms: a node whose clock drifts shows a trend in
    /// the minimum, a slow link in the maximum. Absent before the first batch.
    pub latency_min_ms: Option<f64>,
    pub latency_max_ms: Option<f64>,
}
