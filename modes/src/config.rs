//! The service's configuration: per building, its model, window, identification and tracker
//! settings, the measurement chain's uncertainty and where temperature comes from.
//!
//! ```toml
//! state_dir = "/var/lib/triax-modes"
//! signing_key_file = "/etc/triax/modes.key"
//!
//! [buildings.hq]
//! window_s = 1800.0
//! temperature_key = "site/hq/air_temperature"
//!
//! [buildings.hq.chain]
//! gain_relative_u = [0.003, 0.003, 0.003]
//! cross_axis_u = 0.002
//! dof = 50.0
//! timestamp_u_s = 0.001
//!
//! [[buildings.hq.sensors]]
//! sensor_id = "roof-a"
//! floor = 5
//! height_m = 17.5
//! mounting = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]
//! ```

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use serde::Deserialize;
use triax_modal::{BuildingModel, ChainUncertainty, SensorPlacement, SsiConfig, TrackerConfig};
use triax_protocol::provenance::GatewayKeys;
use triax_protocol::BuildingId;

pub use triax_net::{ConfigError, ZenohMode, ZenohSettings};

/// Seconds in a (Julian) year: the tracker's false-alarm budget is per year.
pub const YEAR_S: f64 = 365.25 * 86_400.0;

/// Everything the service needs.
#[derive(Debug, Clone)]
pub struct Config {
    pub zenoh: ZenohSettings,
    pub buildings: BTreeMap<BuildingId, BuildingConfig>,
    /// Per building, `<state_dir>/<building>/`: the resume state and the record of every
    /// identification. None: nothing kept (tests, trials).
    pub state_dir: Option<PathBuf>,
    /// The Ed25519 key every `modal_shift` alert is signed with (as `triax-alert`'s).
    pub signing_key_file: Option<PathBuf>,
    /// `[gateways]`: per building, the gateway key its data must be sealed with (PROTOCOL.md
    /// §6). None (no table): everything is taken on trust.
    pub gateway_keys: Option<Arc<GatewayKeys>>,
}

/// One building.
#[derive(Debug, Clone)]
pub struct BuildingConfig {
    pub model: BuildingModel,
    /// Window length, s, on the sensors' clocks; windows start at multiples of it since the
    /// Unix epoch.
    pub window_s: f64,
    /// A sample is put on the window's grid when it is within this fraction of a sample period
    /// of a grid point; further off, it is left out (`misaligned`).
    pub alignment_tolerance: f64,
    /// A window is identified once every sensor has passed its end, or this long (s, by the
    /// service's clock) after the first did: the others' missing samples are then gaps.
    pub close_after_s: f64,
    /// What the measurement chain adds to the shapes, the same for every sensor; none given:
    /// shapes carry their statistical uncertainty only (said in the log at start).
    pub chain: Option<ChainUncertainty>,
    pub ssi: SsiConfig,
    /// `false_alarms_per_year` is the building's, shared by its alerting tracks;
    /// `windows_per_year` and `average_windows` (a day) follow from `window_s`.
    pub tracker: TrackerConfig,
    /// The lowest this many tracks of each direction may raise `modal_shift`.
    pub alert_modes_per_direction: usize,
    /// A Zenoh key expression carrying the building's temperature (`TemperatureReading` JSON);
    /// none: the tracker has no regressor and the baseline is a constant.
    pub temperature_key: Option<String>,
    /// Identifications kept in the record file before it is rotated (one older file kept).
    pub record_max_windows: u64,
}

impl BuildingConfig {
    /// The tracker's settings per track: the building's yearly budget shared equally by the
    /// tracks that may alert, and the windows of a year and of a day from the window length.
    pub fn tracker_per_track(&self) -> TrackerConfig {
        let mut t = self.tracker.clone();
        let alerting = (self.alert_modes_per_direction * self.ssi.channels.directions.len()).max(1);
        t.false_alarms_per_year = self.tracker.false_alarms_per_year / alerting as f64;
        t.windows_per_year = YEAR_S / self.window_s;
        t.average_windows = ((86_400.0 / self.window_s).round() as usize).max(1);
        t
    }
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
    #[serde(default)]
    zenoh: ZenohSettings,
    #[serde(default)]
    buildings: BTreeMap<String, FileBuilding>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct FileBuilding {
    window_s: Option<f64>,
    alignment_tolerance: Option<f64>,
    close_after_s: Option<f64>,
    chain: Option<ChainUncertainty>,
    #[serde(default)]
    ssi: SsiConfig,
    #[serde(default)]
    tracker: TrackerConfig,
    alert_modes_per_direction: Option<usize>,
    temperature_key: Option<String>,
    record_max_windows: Option<u64>,
    sensors: Vec<SensorPlacement>,
}

impl FileConfig {
    fn into_config(self) -> Result<Config, ConfigError> {
        self.zenoh.validate()?;
        let mut buildings = BTreeMap::new();
        for (name, b) in self.buildings {
            let at = |field: &str| format!("buildings.{name}.{field}");
            let id = BuildingId::new(name.clone())
                .map_err(|e| ConfigError::invalid(format!("buildings.{name}"), e.to_string()))?;
            let model = BuildingModel::new(name.clone(), b.sensors)
                .map_err(|e| ConfigError::invalid(at("sensors"), e.to_string()))?;
            for s in &model.sensors {
                triax_protocol::SensorId::new(s.sensor_id.clone())
                    .map_err(|e| ConfigError::invalid(at("sensors"), e.to_string()))?;
            }
            let window_s = b.window_s.unwrap_or(1800.0);
            // Below a minute the jackknife's blocks hold too few cycles of a 1 Hz building; a
            // day of samples per sensor is more memory than a window deserves.
            if !(window_s.is_finite() && (60.0..=86_400.0).contains(&window_s)) {
                return Err(ConfigError::invalid(
                    at("window_s"),
                    "must be in [60, 86400] s",
                ));
            }
            let alignment_tolerance = b.alignment_tolerance.unwrap_or(0.1);
            if !(0.0..0.5).contains(&alignment_tolerance) {
                return Err(ConfigError::invalid(
                    at("alignment_tolerance"),
                    "must be in [0, 0.5) of a sample period",
                ));
            }
            let close_after_s = b.close_after_s.unwrap_or(60.0);
            if !(close_after_s.is_finite() && close_after_s >= 0.0 && close_after_s <= window_s) {
                return Err(ConfigError::invalid(
                    at("close_after_s"),
                    "must be in [0, window_s] s",
                ));
            }
            if let Some(c) = &b.chain {
                let ok = c.gain_relative_u.iter().all(|u| u.is_finite() && *u >= 0.0)
                    && c.cross_axis_u.is_finite()
                    && c.cross_axis_u >= 0.0
                    && c.timestamp_u_s.is_finite()
                    && c.timestamp_u_s >= 0.0
                    && c.dof > 0.0;
                if !ok {
                    return Err(ConfigError::invalid(
                        at("chain"),
                        "uncertainties must be finite and ≥ 0, dof > 0",
                    ));
                }
            }
            if let Err(e) = b.ssi.validate() {
                let (field, reason) = match e {
                    triax_modal::ModalError::InvalidOption { field, reason } => {
                        (format!("ssi.{field}"), reason)
                    }
                    other => ("ssi".to_string(), other.to_string()),
                };
                return Err(ConfigError::invalid(at(&field), reason));
            }
            if !(b.tracker.false_alarms_per_year.is_finite()
                && b.tracker.false_alarms_per_year > 0.0)
            {
                return Err(ConfigError::invalid(
                    at("tracker.false_alarms_per_year"),
                    "must be > 0",
                ));
            }
            let t = &b.tracker;
            let matching = [
                (
                    "tracker.frequency_tolerance",
                    t.frequency_tolerance > 0.0 && t.frequency_tolerance < 1.0,
                    "must be > 0 and < 1 (a relative distance)",
                ),
                (
                    "tracker.mac_min",
                    t.mac_min > 0.0 && t.mac_min <= 1.0,
                    "must be > 0 and ≤ 1",
                ),
                (
                    "tracker.mac_min_in_band",
                    t.mac_min_in_band > 0.0 && t.mac_min_in_band <= t.mac_min,
                    "must be > 0 and ≤ tracker.mac_min",
                ),
                (
                    "tracker.frequency_band",
                    t.frequency_band.is_finite() && t.frequency_band > 0.0,
                    "must be > 0 (standard deviations of the track's scatter)",
                ),
                ("tracker.shape_windows", t.shape_windows >= 1, "must be ≥ 1"),
                (
                    "tracker.normal_probability",
                    t.normal_probability > 0.5 && t.normal_probability < 1.0,
                    "must be in (0.5, 1)",
                ),
                (
                    "tracker.cusum_shift",
                    t.cusum_shift.is_finite() && t.cusum_shift > 0.0,
                    "must be > 0 (standard uncertainties of a prediction)",
                ),
                (
                    "tracker.threshold_relative",
                    t.threshold_relative.is_finite() && (0.0..1.0).contains(&t.threshold_relative),
                    "must be in [0, 1) (a relative drop)",
                ),
            ];
            // NaN fails every comparison above, so it is refused too.
            if let Some((field, _, why)) = matching.iter().find(|(_, ok, _)| !ok) {
                return Err(ConfigError::invalid(at(field), *why));
            }
            if b.tracker.training_windows < 3 {
                return Err(ConfigError::invalid(
                    at("tracker.training_windows"),
                    "must be ≥ 3",
                ));
            }
            if let Some(k) = &b.temperature_key {
                zenoh::key_expr::KeyExpr::try_from(k.as_str())
                    .map_err(|e| ConfigError::invalid(at("temperature_key"), e.to_string()))?;
            }
            let record_max_windows = b.record_max_windows.unwrap_or(17_532);
            if record_max_windows == 0 {
                return Err(ConfigError::invalid(
                    at("record_max_windows"),
                    "must be ≥ 1",
                ));
            }
            buildings.insert(
                id,
                BuildingConfig {
                    model,
                    window_s,
                    alignment_tolerance,
                    close_after_s,
                    chain: b.chain,
                    ssi: b.ssi,
                    tracker: b.tracker,
                    alert_modes_per_direction: b.alert_modes_per_direction.unwrap_or(3),
                    temperature_key: b.temperature_key,
                    record_max_windows,
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
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const SENSOR: &str =
        "[[buildings.hq.sensors]]\nsensor_id = \"roof\"\nfloor = 5\nheight_m = 17.5\n\
        mounting = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]\n";

    #[test]
    fn defaults_and_the_budget_per_track() {
        let c = Config::from_toml(&format!("[buildings.hq]\n{SENSOR}")).unwrap();
        let b = &c.buildings[&BuildingId::new("hq").unwrap()];
        assert_eq!(b.window_s, 1800.0);
        let t = b.tracker_per_track();
        // One false shift a year per building, shared by three modes in each of x and y.
        assert!((t.false_alarms_per_year - 1.0 / 6.0).abs() < 1e-12);
        // A third of each track's for the sequential test: ARL ≥ 3·17 532·6 windows.
        assert!((t.cusum_threshold() - (3.0 * 17_532.0 * 6.0f64).ln()).abs() < 1e-9);
        assert!((t.windows_per_year - 17_532.0).abs() < 1e-9);
        assert_eq!(t.average_windows, 48);
    }

    #[test]
    fn the_example_is_valid() {
        let c = Config::from_toml(include_str!("../modes.example.toml")).unwrap();
        let b = &c.buildings[&BuildingId::new("hq").unwrap()];
        assert_eq!(b.model.sensors.len(), 2);
        assert_eq!(b.tracker.training_windows, 336);
        assert!(b.chain.is_some() && b.temperature_key.is_some());
    }

    #[test]
    fn mistakes_are_named() {
        let bad_rotation = "[buildings.hq]\n[[buildings.hq.sensors]]\nsensor_id = \"roof\"\n\
            floor = 5\nheight_m = 17.5\nmounting = [[2.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]\n";
        let e = Config::from_toml(bad_rotation).unwrap_err().to_string();
        assert!(
            e.contains("buildings.hq.sensors") && e.contains("roof"),
            "{e}"
        );
        let short = format!("[buildings.hq]\nwindow_s = 10.0\n{SENSOR}");
        let e = Config::from_toml(&short).unwrap_err().to_string();
        assert!(e.contains("window_s"), "{e}");
        let e = Config::from_toml("").unwrap_err().to_string();
        assert!(e.contains("no building"), "{e}");
        for (field, value) in [
            ("max_order", "1"),
            ("blocks", "5"),
            ("selection.mac_min", "1.5"),
            ("channels.min_valid_fraction", "0.0"),
            ("lag_span_s", "-1.0"),
        ] {
            let (table, key) = match field.rsplit_once('.') {
                Some((t, k)) => (format!("ssi.{t}"), k),
                None => ("ssi".to_string(), field),
            };
            let text = format!("[buildings.hq]\n{SENSOR}[buildings.hq.{table}]\n{key} = {value}\n");
            let e = Config::from_toml(&text).unwrap_err().to_string();
            assert!(
                e.contains(&format!("buildings.hq.ssi.{field}")),
                "{field}: {e}"
            );
        }
        // A misspelt key is refused, not ignored.
        let text = format!("[buildings.hq]\n{SENSOR}[buildings.hq.ssi]\nmax_ordr = 80\n");
        let e = Config::from_toml(&text).unwrap_err().to_string();
        assert!(e.contains("max_ordr"), "{e}");
        for (field, value) in [
            ("frequency_tolerance", "0.0"),
            ("mac_min", "1.5"),
            ("mac_min_in_band", "0.9"),
            ("frequency_band", "nan"),
            ("shape_windows", "0"),
            ("normal_probability", "1.0"),
            ("cusum_shift", "0.0"),
            ("threshold_relative", "-0.01"),
        ] {
            let text =
                format!("[buildings.hq]\n{SENSOR}[buildings.hq.tracker]\n{field} = {value}\n");
            let e = Config::from_toml(&text).unwrap_err().to_string();
            assert!(e.contains(&format!("tracker.{field}")), "{field}: {e}");
        }
    }
}
