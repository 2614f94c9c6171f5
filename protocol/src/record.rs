//! The calibration record: one sensor's static and dynamic calibration, as a certificate.
//!
//! A record is what the lab issues and the gateway applies. Its JSON form is documented field by
//! field in PROTOCOL.md; the fields follow what an ISO/IEC 17025 calibration certificate states
//! (issuer, unique identification, method, reference and traceability, number of points, date,
//! conditions, results with their expanded uncertainty and coverage factor, validity).
//!
//! [`CalibrationRecord::validate`] checks everything that can be checked without linear algebra
//! (finite numbers, ranges, time window, covariance symmetry). Conditioning and positive
//! semi-definiteness are checked where the record is turned into a corrector.

use serde::{Deserialize, Serialize};
use time::OffsetDateTime;

use crate::json::{JsonMessage, JSON_FORMAT_VERSION};
use crate::keys::SensorId;

/// Number of calibration parameters: the 9 entries of S (row-major) then the 3 of q.
pub const N_PARAMS: usize = 12;

/// Largest record version: 2⁵³ − 1, the largest integer every JSON reader holds exactly.
pub const MAX_VERSION: u64 = (1 << 53) - 1;

/// Accepted range of a set's coverage factor k.
pub const MIN_COVERAGE_FACTOR: f64 = 0.1;
pub const MAX_COVERAGE_FACTOR: f64 = 10.0;

/// Accepted range of a set's coverage probability.
pub const MIN_COVERAGE_PROBABILITY: f64 = 0.5;
pub const MAX_COVERAGE_PROBABILITY: f64 = 0.999;

/// Smallest accepted degrees of freedom.
pub const MIN_DOF: f64 = 1.0;

/// One sensor's calibration.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CalibrationRecord {
    /// JSON format version, [`JSON_FORMAT_VERSION`].
    pub format_version: u32,
    pub sensor_id: SensorId,
    /// Strictly increasing per sensor; a rollback is a new version with old parameters.
    pub version: u64,
    /// When the lab issued this record (RFC 3339).
    #[serde(with = "time::serde::rfc3339")]
    pub issued_at: OffsetDateTime,
    /// Start of validity (RFC 3339).
    #[serde(with = "time::serde::rfc3339")]
    pub valid_from: OffsetDateTime,
    /// End of validity (RFC 3339); none means until superseded.
    #[serde(
        default,
        with = "time::serde::rfc3339::option",
        skip_serializing_if = "Option::is_none"
    )]
    pub valid_until: Option<OffsetDateTime>,
    pub lab: Lab,
    pub certificate: Certificate,
    pub sensor: SensorInfo,
    /// Set for quasi-static use (inclination): from the multi-orientation gravity bench.
    #[serde(rename = "static")]
    pub static_set: CalibrationSet,
    /// Set for vibration: from the rotary table.
    pub dynamic: CalibrationSet,
    /// First-order temperature correction of both sets, when the lab measured at two or more
    /// temperatures; none means the sets hold whatever the temperature.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub temperature: Option<TemperatureModel>,
}

/// How the sensor's offset and gains move with its temperature, to first order:
/// `V(T) = (1 + c_g·ΔT)·V(T₀)` per output channel and `q(T) = q + c_q·ΔT`, with
/// `ΔT = T − reference_c`. The gateway corrects a batch that carries `temperature_c` as
/// `a = S⁻¹·(V / (1 + c_g·ΔT)) + q + c_q·ΔT`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TemperatureModel {
    /// Temperature at which both sets' S and q hold, °C.
    pub reference_c: f64,
    /// Lowest and highest temperature the lab measured at, °C.
    pub range_c: [f64; 2],
    /// c_q: change of the offset q per °C, per axis, m/s² per °C.
    pub offset_mps2_per_c: [f64; 3],
    /// c_g: relative change of each output channel's gain per °C; none means not measured
    /// (taken as 0 with no uncertainty).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub gain_per_c: Option<[f64; 3]>,
    /// Covariance of (c_q x, y, z, c_g x, y, z), an array of six rows of six; the c_g part is
    /// zero when `gain_per_c` is absent.
    pub covariance: [[f64; 6]; 6],
    /// Degrees of freedom of `covariance`; none means infinitely many.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub covariance_dof: Option<f64>,
}

/// Largest accepted |c_q|, m/s² per °C: a hundred times what cheap MEMS parts drift.
pub const MAX_OFFSET_MPS2_PER_C: f64 = 0.5;
/// Largest accepted |c_g|, per °C (1 % per °C).
pub const MAX_GAIN_PER_C: f64 = 0.01;

impl JsonMessage for CalibrationRecord {
    const WHAT: &'static str = "calibration record";
    fn format_version(&self) -> u32 {
        self.format_version
    }
}

/// The issuing laboratory.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Lab {
    pub name: String,
    /// Accreditation body and number, when accredited.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub accreditation: Option<String>,
    /// Person who authorised the certificate.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub approved_by: Option<String>,
}

/// Certificate identification and conditions.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Certificate {
    /// Unique certificate number.
    pub id: String,
    /// Ambient temperature during calibration, °C.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub temperature_c: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub notes: Option<String>,
}

/// The sensor as calibrated.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SensorInfo {
    /// Unit of the raw outputs V ("V", "count", "mV"…); S is in this unit per m/s².
    pub output_unit: String,
    /// Standard deviation of one output sample at rest, per axis, in the output unit.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub output_noise: Option<[f64; 3]>,
    /// Degrees of freedom of `output_noise`; none means infinitely many (a known value).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub output_noise_dof: Option<f64>,
    /// |V| at or above which an output is clipped, in the output unit.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub output_full_scale: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub model: Option<String>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub serial: Option<String>,
}

/// One set of eq. (1) parameters with its uncertainty and where it applies.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CalibrationSet {
    /// S, row-major, output unit per m/s²: V = S·(a − q).
    pub sensitivity: [[f64; 3]; 3],
    /// q, m/s².
    pub offset: [f64; 3],
    /// Per-axis standard uncertainty (k = 1) of a corrected value, m/s², from the contributions
    /// the covariance does not represent (repeatability of the reference, radius, model error).
    pub uncertainty_mps2: [f64; 3],
    /// Degrees of freedom of `uncertainty_mps2`; none means infinitely many.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub uncertainty_dof: Option<f64>,
    /// Covariance of the 12 parameters (S row-major, then q), in their units.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub covariance: Option<Box<[[f64; N_PARAMS]; N_PARAMS]>>,
    /// Degrees of freedom of `covariance` (for a least-squares fit, the residual degrees of
    /// freedom); none means infinitely many.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub covariance_dof: Option<f64>,
    /// Coverage factor stated with the expanded uncertainty of the parameters (2 for ≈95 %
    /// with infinite degrees of freedom; Student's t at `coverage_probability` otherwise).
    pub coverage_factor: f64,
    /// Coverage probability the gateway's intervals aim at when the set states degrees of
    /// freedom; none means 0.95.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub coverage_probability: Option<f64>,
    pub domain: Domain,
    /// Calibration method ("static multi-orientation least squares", …).
    pub method: String,
    /// Reference standard and its traceability.
    pub reference: String,
    /// Number of points (orientations, or samples) the fit used.
    pub n_points: u32,
    /// Date of the measurements (RFC 3339).
    #[serde(with = "time::serde::rfc3339")]
    pub calibrated_at: OffsetDateTime,
}

/// Where a set was shown to hold: amplitudes and frequencies the calibration data covered.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Domain {
    /// Largest |a| per axis covered, m/s².
    pub amplitude_max_mps2: f64,
    pub frequency_min_hz: f64,
    pub frequency_max_hz: f64,
}

/// What is wrong with a record, and where.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("sensor {sensor_id}, version {version}: {field}: {problem}")]
pub struct RecordError {
    pub sensor_id: String,
    pub version: u64,
    /// Path of the field, e.g. `dynamic.covariance[3][4]`.
    pub field: String,
    pub problem: String,
}

impl CalibrationRecord {
    /// The set a mode uses.
    pub fn set(&self, which: SetKind) -> &CalibrationSet {
        match which {
            SetKind::Static => &self.static_set,
            SetKind::Dynamic => &self.dynamic,
        }
    }

    /// Checks ranges, finiteness, the validity window and covariance symmetry.
    pub fn validate(&self) -> Result<(), RecordError> {
        let err = |field: &str, problem: String| RecordError {
            sensor_id: self.sensor_id.to_string(),
            version: self.version,
            field: field.to_owned(),
            problem,
        };
        if self.format_version != JSON_FORMAT_VERSION {
            return Err(err(
                "format_version",
                format!("{} is not {JSON_FORMAT_VERSION}", self.format_version),
            ));
        }
        if self.version == 0 {
            return Err(err("version", "must be at least 1".into()));
        }
        if self.version > MAX_VERSION {
            return Err(err(
                "version",
                format!(
                    "{} is above {MAX_VERSION} (2⁵³ − 1): JSON readers that hold numbers as \
                     doubles would misread it, and no later version could follow it",
                    self.version
                ),
            ));
        }
        if let Some(until) = self.valid_until {
            if until <= self.valid_from {
                return Err(err(
                    "valid_until",
                    format!("{until} is not after valid_from {}", self.valid_from),
                ));
            }
        }
        if let Some(noise) = self.sensor.output_noise {
            for (i, n) in noise.iter().enumerate() {
                if !(n.is_finite() && *n >= 0.0) {
                    return Err(err(
                        &format!("sensor.output_noise[{i}]"),
                        format!("{n} is not a finite non-negative number"),
                    ));
                }
            }
        }
        if let Some(nu) = self.sensor.output_noise_dof {
            check_dof(nu).map_err(|problem| err("sensor.output_noise_dof", problem))?;
        }
        if let Some(fs) = self.sensor.output_full_scale {
            if !(fs.is_finite() && fs > 0.0) {
                return Err(err(
                    "sensor.output_full_scale",
                    format!("{fs} is not a positive finite number"),
                ));
            }
        }
        for (name, set) in [("static", &self.static_set), ("dynamic", &self.dynamic)] {
            set.validate()
                .map_err(|(field, problem)| err(&format!("{name}.{field}"), problem))?;
        }
        if let Some(t) = &self.temperature {
            t.validate()
                .map_err(|(field, problem)| err(&format!("temperature.{field}"), problem))?;
        }
        Ok(())
    }
}

impl TemperatureModel {
    fn validate(&self) -> Result<(), (String, String)> {
        let [low, high] = self.range_c;
        if !(low.is_finite() && high.is_finite() && low < high) {
            return Err((
                "range_c".into(),
                format!("[{low}, {high}] is not a finite range with min < max"),
            ));
        }
        if !(self.reference_c.is_finite() && (low..=high).contains(&self.reference_c)) {
            return Err((
                "reference_c".into(),
                format!("{} is not inside range_c [{low}, {high}]", self.reference_c),
            ));
        }
        for (i, c) in self.offset_mps2_per_c.iter().enumerate() {
            if !(c.is_finite() && c.abs() <= MAX_OFFSET_MPS2_PER_C) {
                return Err((
                    format!("offset_mps2_per_c[{i}]"),
                    format!("{c} is not a finite number within ±{MAX_OFFSET_MPS2_PER_C}"),
                ));
            }
        }
        for (i, c) in self.gain_per_c.iter().flatten().enumerate() {
            if !(c.is_finite() && c.abs() <= MAX_GAIN_PER_C) {
                return Err((
                    format!("gain_per_c[{i}]"),
                    format!("{c} is not a finite number within ±{MAX_GAIN_PER_C}"),
                ));
            }
        }
        for i in 0..6 {
            for j in 0..6 {
                let (v, w) = (self.covariance[i][j], self.covariance[j][i]);
                if !v.is_finite() {
                    return Err((
                        format!("covariance[{i}][{j}]"),
                        format!("{v} is not finite"),
                    ));
                }
                if (v - w).abs() > 1e-9 * v.abs().max(w.abs()) {
                    return Err((
                        format!("covariance[{i}][{j}]"),
                        format!("{v} differs from covariance[{j}][{i}] = {w}: not symmetric"),
                    ));
                }
            }
            if self.covariance[i][i] < 0.0 {
                return Err((
                    format!("covariance[{i}][{i}]"),
                    format!("variance {} is negative", self.covariance[i][i]),
                ));
            }
            if i >= 3 && self.gain_per_c.is_none() && self.covariance[i][i] != 0.0 {
                return Err((
                    format!("covariance[{i}][{i}]"),
                    "the gain part must be zero when gain_per_c is absent".into(),
                ));
            }
        }
        if let Some(nu) = self.covariance_dof {
            check_dof(nu).map_err(|problem| ("covariance_dof".to_string(), problem))?;
        }
        Ok(())
    }
}

impl CalibrationSet {
    fn validate(&self) -> Result<(), (String, String)> {
        let finite = |field: String, v: f64| {
            if v.is_finite() {
                Ok(())
            } else {
                Err((field, format!("{v} is not finite")))
            }
        };
        for (i, row) in self.sensitivity.iter().enumerate() {
            for (j, v) in row.iter().enumerate() {
                finite(format!("sensitivity[{i}][{j}]"), *v)?;
            }
        }
        for (i, v) in self.offset.iter().enumerate() {
            finite(format!("offset[{i}]"), *v)?;
        }
        for (i, u) in self.uncertainty_mps2.iter().enumerate() {
            if !(u.is_finite() && *u >= 0.0) {
                return Err((
                    format!("uncertainty_mps2[{i}]"),
                    format!("{u} is not a finite non-negative number"),
                ));
            }
        }
        // The corrected stream carries k as an f32; a range also keeps typos out.
        if !(MIN_COVERAGE_FACTOR..=MAX_COVERAGE_FACTOR).contains(&self.coverage_factor) {
            return Err((
                "coverage_factor".into(),
                format!(
                    "{} is outside {MIN_COVERAGE_FACTOR}..={MAX_COVERAGE_FACTOR}",
                    self.coverage_factor
                ),
            ));
        }
        for (field, dof) in [
            ("uncertainty_dof", self.uncertainty_dof),
            ("covariance_dof", self.covariance_dof),
        ] {
            if let Some(nu) = dof {
                check_dof(nu).map_err(|problem| (field.to_string(), problem))?;
            }
        }
        if let Some(p) = self.coverage_probability {
            if !(MIN_COVERAGE_PROBABILITY..=MAX_COVERAGE_PROBABILITY).contains(&p) {
                return Err((
                    "coverage_probability".into(),
                    format!(
                        "{p} is outside {MIN_COVERAGE_PROBABILITY}..={MAX_COVERAGE_PROBABILITY}"
                    ),
                ));
            }
        }
        let d = &self.domain;
        if !(d.amplitude_max_mps2.is_finite() && d.amplitude_max_mps2 > 0.0) {
            return Err((
                "domain.amplitude_max_mps2".into(),
                format!("{} is not a positive finite number", d.amplitude_max_mps2),
            ));
        }
        if !(d.frequency_min_hz.is_finite()
            && d.frequency_max_hz.is_finite()
            && d.frequency_min_hz >= 0.0
            && d.frequency_min_hz <= d.frequency_max_hz)
        {
            return Err((
                "domain".into(),
                format!(
                    "frequency band {}..{} Hz is not 0 <= min <= max",
                    d.frequency_min_hz, d.frequency_max_hz
                ),
            ));
        }
        if self.n_points == 0 {
            return Err(("n_points".into(), "must be at least 1".into()));
        }
        if let Some(cov) = &self.covariance {
            for i in 0..N_PARAMS {
                for j in 0..N_PARAMS {
                    let v = cov[i][j];
                    finite(format!("covariance[{i}][{j}]"), v)?;
                    let w = cov[j][i];
                    let scale = v.abs().max(w.abs());
                    if (v - w).abs() > 1e-9 * scale {
                        return Err((
                            format!("covariance[{i}][{j}]"),
                            format!("{v} differs from covariance[{j}][{i}] = {w}: not symmetric"),
                        ));
                    }
                }
                if cov[i][i] < 0.0 {
                    return Err((
                        format!("covariance[{i}][{i}]"),
                        format!("variance {} is negative", cov[i][i]),
                    ));
                }
            }
        }
        Ok(())
    }
}

/// Degrees of freedom below one describe no estimate at all; infinity is written by leaving
/// the field out.
fn check_dof(nu: f64) -> Result<(), String> {
    if nu.is_finite() && nu >= MIN_DOF {
        Ok(())
    } else {
        Err(format!(
            "{nu} is not a finite number of degrees of freedom of at least {MIN_DOF} (leave the \
             field out for infinitely many)"
        ))
    }
}

/// The two sets of a record.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum SetKind {
    Static,
    Dynamic,
}

/// Small, valid records for tests and examples across the workspace.
pub mod sample {
    use super::*;

    /// A valid record with near-identity S, in V per m/s², no covariance.
    pub fn record(sensor_id: &str, version: u64) -> CalibrationRecord {
        let t = OffsetDateTime::from_unix_timestamp(1_767_225_600) // 2026-01-01T00:00:00Z
            .expect("constant timestamp is in range");
        let set = |diagonal: [f64; 3], method: &str| CalibrationSet {
            sensitivity: [
                [diagonal[0], 0.002, -0.001],
                [0.003, diagonal[1], 0.002],
                [-0.002, 0.001, diagonal[2]],
            ],
            offset: [0.05, -0.03, 0.02],
            uncertainty_mps2: [0.01, 0.012, 0.011],
            uncertainty_dof: None,
            covariance: None,
            covariance_dof: None,
            coverage_factor: 2.0,
            coverage_probability: None,
            domain: Domain {
                amplitude_max_mps2: 20.0,
                frequency_min_hz: 0.0,
                frequency_max_hz: 10.0,
            },
            method: method.into(),
            reference: "sample".into(),
            n_points: 10,
            calibrated_at: t,
        };
        CalibrationRecord {
            format_version: JSON_FORMAT_VERSION,
            // Callers pass literal ids; a bad one is a bug in the caller's test.
            sensor_id: SensorId::new(sensor_id).expect("sample sensor id is valid"),
            version,
            issued_at: t,
            valid_from: t,
            valid_until: None,
            lab: Lab {
                name: "Triax sample lab".into(),
                accreditation: None,
                approved_by: None,
            },
            certificate: Certificate {
                id: format!("SAMPLE-{sensor_id}-{version}"),
                temperature_c: Some(21.0),
                notes: None,
            },
            sensor: SensorInfo {
                output_unit: "V".into(),
                output_noise: Some([0.001, 0.001, 0.001]),
                output_noise_dof: None,
                output_full_scale: Some(40.0),
                model: None,
                serial: None,
            },
            static_set: set(
                [0.1, 0.101, 0.099],
                "static multi-orientation least squares",
            ),
            dynamic: set([0.102, 0.103, 0.101], "rotary table least squares"),
            temperature: None,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::json::{from_json, to_json, to_json_pretty, JsonError};

    #[test]
    fn round_trip_and_validation() {
        let mut r = sample::record("s1", 3);
        r.dynamic.covariance = Some(Box::new({
            let mut c = [[0.0; 12]; 12];
            for (i, row) in c.iter_mut().enumerate() {
                row[i] = 1e-6 * (i + 1) as f64;
            }
            c[0][9] = 1e-7;
            c[9][0] = 1e-7;
            c
        }));
        r.valid_until = Some(r.valid_from + time::Duration::days(365));
        r.validate().unwrap();
        for bytes in [to_json(&r), to_json_pretty(&r)] {
            let back: CalibrationRecord = from_json(&bytes).unwrap();
            assert_eq!(back, r);
        }
    }

    #[test]
    fn validation_names_the_field() {
        let mut r = sample::record("s1", 1);
        r.dynamic.sensitivity[1][2] = f64::INFINITY;
        let e = r.validate().unwrap_err();
        assert_eq!(e.field, "dynamic.sensitivity[1][2]");

        let mut r = sample::record("s1", 1);
        r.valid_until = Some(r.valid_from);
        assert_eq!(r.validate().unwrap_err().field, "valid_until");

        let mut r = sample::record("s1", 1);
        let mut c = [[0.0; 12]; 12];
        c[2][5] = 1.0;
        r.static_set.covariance = Some(Box::new(c));
        let e = r.validate().unwrap_err();
        assert_eq!(e.field, "static.covariance[2][5]");
        assert!(e.to_string().contains("sensor s1, version 1"), "{e}");

        let mut r = sample::record("s1", 1);
        r.dynamic.coverage_factor = 1e39;
        assert_eq!(r.validate().unwrap_err().field, "dynamic.coverage_factor");

        let mut r = sample::record("s1", 1);
        r.version = 0;
        assert_eq!(r.validate().unwrap_err().field, "version");

        let mut r = sample::record("s1", 1);
        r.static_set.covariance_dof = Some(0.5);
        let e = r.validate().unwrap_err();
        assert_eq!(e.field, "static.covariance_dof");
        assert!(e.to_string().contains("leave the field out"), "{e}");
        let mut r = sample::record("s1", 1);
        r.dynamic.uncertainty_dof = Some(f64::NAN);
        assert_eq!(r.validate().unwrap_err().field, "dynamic.uncertainty_dof");
        let mut r = sample::record("s1", 1);
        r.sensor.output_noise_dof = Some(-3.0);
        assert_eq!(r.validate().unwrap_err().field, "sensor.output_noise_dof");
        let mut r = sample::record("s1", 1);
        r.temperature = Some(TemperatureModel {
            reference_c: 21.0,
            range_c: [10.0, 30.0],
            offset_mps2_per_c: [0.003, -0.002, 0.001],
            gain_per_c: None,
            covariance: [[0.0; 6]; 6],
            covariance_dof: None,
        });
        r.validate().unwrap();
        r.temperature.as_mut().unwrap().reference_c = 35.0;
        assert_eq!(r.validate().unwrap_err().field, "temperature.reference_c");
        r.temperature.as_mut().unwrap().reference_c = 21.0;
        r.temperature.as_mut().unwrap().covariance[4][4] = 1e-8;
        let e = r.validate().unwrap_err();
        assert_eq!(e.field, "temperature.covariance[4][4]");
        assert!(e.to_string().contains("gain_per_c is absent"), "{e}");
        r.temperature.as_mut().unwrap().gain_per_c = Some([0.0, 0.2, 0.0]);
        assert_eq!(r.validate().unwrap_err().field, "temperature.gain_per_c[1]");

        let mut r = sample::record("s1", 1);
        r.static_set.coverage_probability = Some(95.0);
        assert_eq!(
            r.validate().unwrap_err().field,
            "static.coverage_probability"
        );
    }

    #[test]
    fn decoding_errors_are_specific() {
        let mut v: serde_json::Value =
            serde_json::from_slice(&to_json(&sample::record("s1", 1))).unwrap();
        v["format_version"] = 2.into();
        let e = from_json::<CalibrationRecord>(&serde_json::to_vec(&v).unwrap()).unwrap_err();
        assert!(matches!(e, JsonError::UnsupportedVersion { found: 2, .. }));

        v["format_version"] = 1.into();
        v["static"]["sensitivity"][2] = serde_json::json!([1.0, 2.0]);
        let e = from_json::<CalibrationRecord>(&serde_json::to_vec(&v).unwrap()).unwrap_err();
        assert!(
            e.to_string().contains("expected an array of length 3"),
            "{e}"
        );

        v["static"]["sensitivity"][2] = serde_json::json!([1.0, 2.0, 3.0]);
        v["valid_untill"] = "2027-01-01T00:00:00Z".into();
        let e = from_json::<CalibrationRecord>(&serde_json::to_vec(&v).unwrap()).unwrap_err();
        assert!(e.to_string().contains("valid_untill"), "typo is named: {e}");

        let e = from_json::<CalibrationRecord>(br#"{"sensor_id":"x"}"#).unwrap_err();
        assert!(e.to_string().contains("format_version"), "{e}");

        let big = vec![b' '; crate::json::MAX_JSON_BYTES + 1];
        assert!(matches!(
            from_json::<CalibrationRecord>(&big),
            Err(JsonError::TooLarge { .. })
        ));
    }
}
