//! The service's configuration: per building its sensors (floor, height, mounting), how events
//! are detected, how they are processed, and the limits they are judged against.
//!
//! ```toml
//! state_dir = "/var/lib/triax-events"
//! signing_key_file = "/etc/triax/events.key"
//!
//! [buildings.hq]
//! pre_event_s = 20.0
//! post_event_s = 20.0
//!
//! [[buildings.hq.limits]]
//! name = "immediate occupancy"
//! quantity = "drift_ratio"
//! threshold = 0.005
//! severity = "yellow"
//!
//! [[buildings.hq.sensors]]
//! sensor_id = "hq-f0"
//! floor = 0
//! height_m = 0.0
//! mounting = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]
//! ```

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use serde::Deserialize;
use triax_modal::{BuildingModel, SensorPlacement};
use triax_protocol::provenance::GatewayKeys;
use triax_protocol::{BuildingId, SensorId};
use triax_strongmotion::decision::Tag;
use triax_strongmotion::detect::DetectorConfig;
use triax_strongmotion::din4150::BuildingClass;
use triax_strongmotion::event::{EventConfig, Limit, Quantity};
use triax_strongmotion::filter::BandPass;

pub use triax_net::{ConfigError, ZenohMode, ZenohSettings};

/// Everything the service needs.
#[derive(Debug, Clone)]
pub struct Config {
    pub zenoh: ZenohSettings,
    pub buildings: BTreeMap<BuildingId, BuildingConfig>,
    /// Per building `<state_dir>/<building>/`: the resume state, and one directory per event
    /// with its report, page and data. None: nothing kept (reports are published only).
    pub state_dir: Option<PathBuf>,
    /// The Ed25519 key every report is signed with.
    pub signing_key_file: Option<PathBuf>,
    /// `[gateways]`: per building, the gateway key its data must be sealed with (PROTOCOL.md
    /// §6). None (no table): everything is taken on trust.
    pub gateway_keys: Option<Arc<GatewayKeys>>,
    /// The miniSEED network code of the events' data.
    pub network: String,
}

/// One building.
#[derive(Debug, Clone)]
pub struct BuildingConfig {
    pub model: BuildingModel,
    pub detector: DetectorConfig,
    pub processing: EventConfig,
    /// Seconds of data taken before the event's start and after its end.
    pub pre_event_s: f64,
    pub post_event_s: f64,
    /// How long (s, service clock) a sensor's stream waits for a hole to be filled (the
    /// gateway's backfill) before detection goes on across it.
    pub hole_wait_s: f64,
    /// A sensor silent this long (s, service clock) no longer holds detection back.
    pub silent_after_s: f64,
    /// A sample is placed on its sensor's grid when within this fraction of a period of a grid
    /// point; further off it is left out.
    pub alignment_tolerance: f64,
    /// The false `exceeded` probability each limit is allowed when the truth is at it.
    pub false_exceeded_probability: f64,
    /// The building's fundamental per direction (x, y), Hz, when known; else from the modes
    /// service's last window, else from the event.
    pub fundamental_hz: [Option<f64>; 2],
    pub limits: Vec<Limit>,
}

impl Config {
    pub fn from_file(path: &Path) -> Result<Config, ConfigError> {
        triax_net::read_toml::<FileConfig>(path)?.into_config()
    }

    pub fn from_toml(text: &str) -> Result<Config, ConfigError> {
        triax_net::parse_toml::<FileConfig>(text, Path::new("<text>"))?.into_config()
    }
}

#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
struct FileConfig {
    state_dir: Option<PathBuf>,
    signing_key_file: Option<PathBuf>,
    #[serde(default)]
    gateways: BTreeMap<String, String>,
    network: Option<String>,
    #[serde(default)]
    zenoh: ZenohSettings,
    #[serde(default)]
    buildings: BTreeMap<String, FileBuilding>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct FileBuilding {
    #[serde(default)]
    detector: DetectorConfig,
    #[serde(default)]
    processing: EventConfig,
    pre_event_s: Option<f64>,
    post_event_s: Option<f64>,
    hole_wait_s: Option<f64>,
    silent_after_s: Option<f64>,
    alignment_tolerance: Option<f64>,
    false_exceeded_probability: Option<f64>,
    fundamental_hz: Option<[f64; 2]>,
    #[serde(default)]
    limits: Vec<FileLimit>,
    sensors: Vec<SensorPlacement>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct FileLimit {
    name: String,
    quantity: String,
    threshold: Option<f64>,
    severity: String,
    period_s: Option<f64>,
    class: Option<u8>,
}

/// Quantities a limit can be on, as named in the configuration.
pub const QUANTITIES: [&str; 10] = [
    "drift_ratio",
    "peak_floor_acceleration",
    "peak_vertical_acceleration",
    "peak_floor_velocity",
    "psa_rotd50",
    "residual_tilt",
    "frequency_drop",
    "din4150_foundation",
    "din4150_top_floor",
    "din4150_top_floor_long_term",
];

fn limit(l: FileLimit, at: &dyn Fn(&str) -> String, periods: &[f64]) -> Result<Limit, ConfigError> {
    let class = || -> Result<BuildingClass, ConfigError> {
        match l.class {
            Some(1) => Ok(BuildingClass::Line1),
            Some(2) => Ok(BuildingClass::Line2),
            Some(3) => Ok(BuildingClass::Line3),
            Some(c) => Err(ConfigError::invalid(
                at("class"),
                format!("{c}: must be 1, 2 or 3"),
            )),
            None => Err(ConfigError::invalid(
                at("class"),
                "required for a DIN 4150-3 limit (1, 2 or 3)",
            )),
        }
    };
    let quantity = match l.quantity.as_str() {
        "drift_ratio" => Quantity::DriftRatio,
        "peak_floor_acceleration" => Quantity::PeakFloorAcceleration,
        "peak_vertical_acceleration" => Quantity::PeakVerticalAcceleration,
        "peak_floor_velocity" => Quantity::PeakFloorVelocity,
        "psa_rotd50" => {
            let p = l
                .period_s
                .ok_or_else(|| ConfigError::invalid(at("period_s"), "required for psa_rotd50"))?;
            if !periods.iter().any(|q| (q - p).abs() < 1e-9) {
                return Err(ConfigError::invalid(
                    at("period_s"),
                    format!("{p} s is not among processing.parameters.periods_s {periods:?}"),
                ));
            }
            Quantity::PsaRotd50 { period_s: p }
        }
        "residual_tilt" => Quantity::ResidualTilt,
        "frequency_drop" => Quantity::FrequencyDrop,
        "din4150_foundation" => Quantity::Din4150Foundation { class: class()? },
        "din4150_top_floor" => Quantity::Din4150TopFloor { class: class()? },
        "din4150_top_floor_long_term" => Quantity::Din4150TopFloorLongTerm { class: class()? },
        other => {
            return Err(ConfigError::invalid(
                at("quantity"),
                format!("{other:?} is not one of {}", QUANTITIES.join(", ")),
            ))
        }
    };
    let din = matches!(
        quantity,
        Quantity::Din4150Foundation { .. }
            | Quantity::Din4150TopFloor { .. }
            | Quantity::Din4150TopFloorLongTerm { .. }
    );
    let threshold = match (l.threshold, din) {
        (Some(t), false) if t.is_finite() => t,
        (Some(t), false) => {
            return Err(ConfigError::invalid(
                at("threshold"),
                format!("{t} is not a number"),
            ))
        }
        (None, false) => return Err(ConfigError::invalid(at("threshold"), "required")),
        (None, true) => 1.0,
        (Some(_), true) => return Err(ConfigError::invalid(
            at("threshold"),
            "a DIN 4150-3 limit's threshold is the standard's curve (the ratio 1): leave it out",
        )),
    };
    let severity = match l.severity.as_str() {
        "yellow" => Tag::Yellow,
        "red" => Tag::Red,
        other => {
            return Err(ConfigError::invalid(
                at("severity"),
                format!("{other:?}: must be \"yellow\" or \"red\""),
            ))
        }
    };
    if l.name.trim().is_empty() {
        return Err(ConfigError::invalid(at("name"), "is empty"));
    }
    Ok(Limit {
        name: l.name,
        quantity,
        threshold,
        severity,
    })
}

impl FileConfig {
    fn into_config(self) -> Result<Config, ConfigError> {
        self.zenoh.validate()?;
        let network = self.network.unwrap_or_else(|| "TX".to_owned());
        if !(1..=2).contains(&network.len()) || !network.bytes().all(|b| b.is_ascii_alphanumeric())
        {
            return Err(ConfigError::invalid(
                "network",
                format!("{network:?}: one or two letters or digits"),
            ));
        }
        let mut buildings = BTreeMap::new();
        for (name, b) in self.buildings {
            let at = |field: &str| format!("buildings.{name}.{field}");
            let id = BuildingId::new(name.clone())
                .map_err(|e| ConfigError::invalid(format!("buildings.{name}"), e.to_string()))?;
            let model = BuildingModel::new(name.clone(), b.sensors)
                .map_err(|e| ConfigError::invalid(at("sensors"), e.to_string()))?;
            for s in &model.sensors {
                SensorId::new(s.sensor_id.clone())
                    .map_err(|e| ConfigError::invalid(at("sensors"), e.to_string()))?;
            }
            b.detector
                .check()
                .map_err(|e| ConfigError::invalid(at("detector"), e))?;
            if b.detector.min_sensors > model.sensors.len() {
                return Err(ConfigError::invalid(
                    at("detector.min_sensors"),
                    format!(
                        "{} is more than the building's {} sensors",
                        b.detector.min_sensors,
                        model.sensors.len()
                    ),
                ));
            }
            let p = &b.processing;
            // The band must be buildable at any rate a sensor may stream (checked again per
            // record); here, at 100 Hz, what a configuration mistake looks like.
            let probe_rate = 100.0;
            if let Err(e) = BandPass::new(&p.parameters.band, probe_rate) {
                return Err(ConfigError::invalid(
                    at("processing.parameters.band"),
                    e.to_string(),
                ));
            }
            let checks = [
                (
                    "processing.parameters.damping",
                    p.parameters.damping > 0.0 && p.parameters.damping < 1.0,
                    "must be in (0, 1)",
                ),
                (
                    "processing.parameters.coverage_probability",
                    p.parameters.coverage_probability > 0.5
                        && p.parameters.coverage_probability < 1.0,
                    "must be in (0.5, 1)",
                ),
                (
                    "processing.parameters.periods_s",
                    !p.parameters.periods_s.is_empty()
                        && p.parameters
                            .periods_s
                            .iter()
                            .all(|t| t.is_finite() && *t > 0.0),
                    "must be positive numbers, at least one",
                ),
                (
                    "processing.parameters.bootstrap_draws",
                    p.parameters.bootstrap_draws <= 10_000,
                    "must be at most 10000",
                ),
                (
                    "processing.clock_uncertainty_s",
                    p.clock_uncertainty_s.is_finite() && p.clock_uncertainty_s >= 0.0,
                    "must be ≥ 0",
                ),
                (
                    "processing.tilt_settle_s",
                    p.tilt_settle_s.is_finite() && p.tilt_settle_s >= 0.0,
                    "must be ≥ 0",
                ),
                (
                    "processing.din_low_hz",
                    p.din_low_hz > 0.0 && p.din_low_hz < p.din_high_hz,
                    "must be > 0 and below processing.din_high_hz",
                ),
            ];
            if let Some((field, _, why)) = checks.iter().find(|(_, ok, _)| !ok) {
                return Err(ConfigError::invalid(at(field), *why));
            }
            let seconds =
                |v: Option<f64>, default: f64, field: &str, max: f64| -> Result<f64, ConfigError> {
                    let v = v.unwrap_or(default);
                    if v.is_finite() && v >= 0.0 && v <= max {
                        Ok(v)
                    } else {
                        Err(ConfigError::invalid(
                            at(field),
                            format!("{v}: must be in [0, {max}] s"),
                        ))
                    }
                };
            let pre_event_s = seconds(b.pre_event_s, 20.0, "pre_event_s", 600.0)?;
            let post_event_s = seconds(b.post_event_s, 20.0, "post_event_s", 600.0)?;
            if pre_event_s < 2.0 {
                return Err(ConfigError::invalid(
                    at("pre_event_s"),
                    "must be at least 2 s: the baseline and the tilt's before are taken there",
                ));
            }
            let hole_wait_s = seconds(b.hole_wait_s, 20.0, "hole_wait_s", 3600.0)?;
            let silent_after_s = seconds(b.silent_after_s, 30.0, "silent_after_s", 3600.0)?;
            let alignment_tolerance = b.alignment_tolerance.unwrap_or(0.1);
            if !(0.0..0.5).contains(&alignment_tolerance) {
                return Err(ConfigError::invalid(
                    at("alignment_tolerance"),
                    "must be in [0, 0.5) of a sample period",
                ));
            }
            let alpha = b.false_exceeded_probability.unwrap_or(0.025);
            if !(alpha > 0.0 && alpha < 0.5) {
                return Err(ConfigError::invalid(
                    at("false_exceeded_probability"),
                    "must be in (0, 0.5)",
                ));
            }
            let fundamental_hz = match b.fundamental_hz {
                Some(f) if f.iter().all(|v| v.is_finite() && *v > 0.0) => [Some(f[0]), Some(f[1])],
                Some(_) => {
                    return Err(ConfigError::invalid(
                        at("fundamental_hz"),
                        "must be two positive frequencies, x then y",
                    ))
                }
                None => [None, None],
            };
            let mut limits = Vec::new();
            for (i, l) in b.limits.into_iter().enumerate() {
                let at_limit = |field: &str| format!("buildings.{name}.limits[{i}].{field}");
                limits.push(limit(l, &at_limit, &p.parameters.periods_s)?);
            }
            buildings.insert(
                id,
                BuildingConfig {
                    model,
                    detector: b.detector,
                    processing: b.processing,
                    pre_event_s,
                    post_event_s,
                    hole_wait_s,
                    silent_after_s,
                    alignment_tolerance,
                    false_exceeded_probability: alpha,
                    fundamental_hz,
                    limits,
                },
            );
        }
        if buildings.is_empty() {
            return Err(ConfigError::invalid("buildings", "no building configured"));
        }
        Ok(Config {
            zenoh: self.zenoh,
            buildings,
            state_dir: self.state_dir,
            signing_key_file: self.signing_key_file,
            gateway_keys: triax_net::keys::trusted_gateways(&self.gateways)?,
            network: network.to_ascii_uppercase(),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const SENSORS: &str =
        "[[buildings.hq.sensors]]\nsensor_id = \"f0\"\nfloor = 0\nheight_m = 0.0\n\
        mounting = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]\n\
        [[buildings.hq.sensors]]\nsensor_id = \"f5\"\nfloor = 5\nheight_m = 17.5\n\
        mounting = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]\n";

    #[test]
    fn defaults_and_the_example() {
        let c = Config::from_toml(&format!("[buildings.hq]\n{SENSORS}")).unwrap();
        let b = &c.buildings[&BuildingId::new("hq").unwrap()];
        assert_eq!(
            (b.pre_event_s, b.post_event_s, b.hole_wait_s),
            (20.0, 20.0, 20.0)
        );
        assert_eq!(b.detector.min_sensors, 2);
        assert_eq!(b.processing.parameters.band.low_hz, 0.1);
        assert_eq!(c.network, "TX");
        let c = Config::from_toml(include_str!("../events.example.toml")).unwrap();
        let b = &c.buildings[&BuildingId::new("hq").unwrap()];
        assert!(b.limits.len() >= 4);
    }

    #[test]
    fn mistakes_are_named() {
        let cases = [
            ("[[buildings.hq.limits]]\nname = \"x\"\nquantity = \"drift\"\nthreshold = 1.0\nseverity = \"red\"\n", "limits[0].quantity"),
            ("[[buildings.hq.limits]]\nname = \"x\"\nquantity = \"drift_ratio\"\nseverity = \"red\"\n", "limits[0].threshold"),
            ("[[buildings.hq.limits]]\nname = \"x\"\nquantity = \"drift_ratio\"\nthreshold = 1.0\nseverity = \"orange\"\n", "limits[0].severity"),
            ("[[buildings.hq.limits]]\nname = \"x\"\nquantity = \"din4150_foundation\"\nseverity = \"red\"\n", "limits[0].class"),
            ("[[buildings.hq.limits]]\nname = \"x\"\nquantity = \"psa_rotd50\"\nthreshold = 1.0\nperiod_s = 0.33\nseverity = \"red\"\n", "limits[0].period_s"),
            ("[buildings.hq.detector]\nmin_sensors = 5\n", "detector.min_sensors"),
            ("[buildings.hq.detector]\ntrigger_ratio = 1.0\n", "detector"),
            ("[buildings.hq.processing.parameters.band]\norder = 3\n", "processing.parameters.band"),
        ];
        for (extra, field) in cases {
            let text = format!("[buildings.hq]\n{SENSORS}{extra}");
            let e = Config::from_toml(&text).unwrap_err().to_string();
            assert!(e.contains(field), "{field}: {e}");
        }
        let e = Config::from_toml("[buildings.hq]\npre_event_s = 1.0\n".to_string().as_str())
            .unwrap_err()
            .to_string();
        assert!(e.contains("sensors") || e.contains("pre_event_s"), "{e}");
    }
}
