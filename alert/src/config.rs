//! Alerting configuration: one TOML file, read and checked once at start into a [`Config`].
//!
//! ```toml
//! window_s = 10.0              # sliding window of every statistic, by the sensors' clocks
//! coverage_factor = 2.0        # k of the guard band
//! stale_after_s = 30.0         # no data for this long: a `stale` alert
//! repeat_interval_s = 60.0     # the same alert (kind and level) at most once per interval
//! noise_share = 0.0            # share of each sample's stated variance that is noise
//! suspect_relative_uncertainty = 0.05  # calibration_suspect samples: u widened by this share of the value
//! highpass_hz = 0.1            # vibration baseline: high pass corner (2nd-order Butterworth)
//! tilt_baseline_samples = 10   # clean tilt samples averaged into the baseline
//! frequency_min_rms_mps2 = 0.005  # below this RMS the dominant frequency is noise: not judged
//! watch_all_buildings = false  # also watch buildings not listed, with [defaults]
//!
//! [zenoh]
//! mode = "peer"                # or "client"
//! connect = ["tcp/192.168.1.10:7447"]
//! listen = []
//! multicast_scouting = true
//! # config_file = "zenoh.json5"
//!
//! [defaults]                   # limits of every sensor unless overridden
//! pga_mps2 = 2.0
//!
//! [buildings.hq]               # a building to watch; its limits override [defaults]
//! rms_mps2 = 0.3
//! frequency_below_hz = 1.8     # alert when the dominant frequency drops below
//!
//! [buildings.hq.sensors.acc-01]   # a sensor's own limits; listed sensors are expected,
//! pga_mps2 = 0.8                  # so they go stale even if they never sent anything
//! tilt_change_deg = 0.05
//! ```
//!
//! Limits: `pga_mps2`, `rms_mps2` (m/s², of the motion above the baseline), `tilt_change_deg` (largest of roll and
//! pitch change from the baseline), `frequency_below_hz` and `frequency_above_hz`. A limit left
//! out is not checked. Unknown fields are refused, so a misspelt limit is an error rather than a
//! silently unchecked one.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use serde::Deserialize;
pub use triax_net::{ConfigError, ZenohMode, ZenohSettings};
use triax_protocol::provenance::GatewayKeys;
use triax_protocol::{BuildingId, SensorId};

use crate::decision::{Direction, Limit};

/// Limits of one sensor, every one optional.
#[derive(Debug, Clone, Copy, Default, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Limits {
    pub pga_mps2: Option<f64>,
    pub rms_mps2: Option<f64>,
    pub tilt_change_deg: Option<f64>,
    pub frequency_below_hz: Option<f64>,
    pub frequency_above_hz: Option<f64>,
}

impl Limits {
    /// `self`, with every unset limit taken from `base`.
    pub fn over(self, base: Limits) -> Limits {
        Limits {
            pga_mps2: self.pga_mps2.or(base.pga_mps2),
            rms_mps2: self.rms_mps2.or(base.rms_mps2),
            tilt_change_deg: self.tilt_change_deg.or(base.tilt_change_deg),
            frequency_below_hz: self.frequency_below_hz.or(base.frequency_below_hz),
            frequency_above_hz: self.frequency_above_hz.or(base.frequency_above_hz),
        }
    }

    pub fn pga(&self) -> Option<Limit> {
        self.pga_mps2.map(above)
    }
    pub fn rms(&self) -> Option<Limit> {
        self.rms_mps2.map(above)
    }
    pub fn tilt_change(&self) -> Option<Limit> {
        self.tilt_change_deg.map(above)
    }
    /// Both frequency limits that are set.
    pub fn frequency(&self) -> impl Iterator<Item = Limit> {
        let below = self.frequency_below_hz.map(|threshold| Limit {
            threshold,
            direction: Direction::Below,
        });
        below.into_iter().chain(self.frequency_above_hz.map(above))
    }

    fn validate(&self, at: &str) -> Result<(), ConfigError> {
        for (name, v) in [
            ("pga_mps2", self.pga_mps2),
            ("rms_mps2", self.rms_mps2),
            ("tilt_change_deg", self.tilt_change_deg),
            ("frequency_below_hz", self.frequency_below_hz),
            ("frequency_above_hz", self.frequency_above_hz),
        ] {
            if let Some(v) = v {
                if !(v.is_finite() && v > 0.0) {
                    return Err(ConfigError::invalid(
                        format!("{at}.{name}"),
                        "must be finite and > 0",
                    ));
                }
            }
        }
        Ok(())
    }
}

fn above(threshold: f64) -> Limit {
    Limit {
        threshold,
        direction: Direction::Above,
    }
}

/// Default of [`Config::state_path`], under the user's state directory
/// (`$XDG_STATE_HOME`, else `$HOME/.local/state`), as services keep state.
pub const DEFAULT_STATE_PATH: &str = "triax-alert/state.json";

/// The default state path; in the working directory only when neither `XDG_STATE_HOME` nor
/// `HOME` is set (a bare container).
pub fn default_state_path() -> PathBuf {
    let var = |k| {
        std::env::var_os(k)
            .filter(|v| !v.is_empty())
            .map(PathBuf::from)
    };
    match (var("XDG_STATE_HOME"), var("HOME")) {
        (Some(x), _) => x.join(DEFAULT_STATE_PATH),
        (None, Some(h)) => h.join(".local/state").join(DEFAULT_STATE_PATH),
        (None, None) => PathBuf::from("triax-alert-state.json"),
    }
}

/// Settings of the window and decision logic, shared by every sensor.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Settings {
    pub window_s: f64,
    pub coverage_factor: f64,
    pub stale_after_s: f64,
    pub repeat_interval_s: f64,
    pub noise_share: f64,
    /// A sample flagged `calibration_suspect` (only that) is judged as a clean one whose
    /// standard uncertainty is widened, in quadrature, by this share of its value: the field
    /// health checks found its record off by more than it states, by the fraction of a percent
    /// to a few percent they detect, so a motion far beyond a limit still exceeds it.
    pub suspect_relative_uncertainty: f64,
    /// Corner of the high pass that takes the baseline out of the acceleration
    /// ([`crate::highpass`]).
    pub highpass_hz: f64,
    pub tilt_baseline_samples: usize,
    pub frequency_min_rms_mps2: f64,
}

impl Default for Settings {
    fn default() -> Self {
        Settings {
            window_s: 10.0,
            coverage_factor: 2.0,
            stale_after_s: 30.0,
            repeat_interval_s: 60.0,
            noise_share: 0.0,
            suspect_relative_uncertainty: 0.05,
            highpass_hz: 0.1,
            tilt_baseline_samples: 10,
            frequency_min_rms_mps2: 0.005,
        }
    }
}

/// One watched building.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Building {
    /// Over [`Config::defaults`].
    pub limits: Limits,
    /// Sensor limits, over the building's; every listed sensor is expected.
    pub sensors: BTreeMap<SensorId, Limits>,
}

/// A validated configuration.
#[derive(Debug, Clone, PartialEq)]
pub struct Config {
    pub settings: Settings,
    pub zenoh: ZenohSettings,
    pub defaults: Limits,
    pub buildings: BTreeMap<BuildingId, Building>,
    /// Subscribe to every building, with [`Config::defaults`] for unlisted ones.
    pub watch_all_buildings: bool,
    /// Where the last sequence number handled per sensor is kept, so that after a restart the
    /// service reads what it missed from the gateways' histories; none: start afresh.
    pub state_path: Option<PathBuf>,
    /// The service's Ed25519 secret key (64 hex characters), with which every alert is signed;
    /// created with its `.pub` beside it when the file does not exist. None: a key made for
    /// this run only, which consumers cannot have configured.
    pub signing_key_file: Option<PathBuf>,
    /// `[gateways]`: per building, the gateway key whose seals and signatures make data the
    /// gateway's (PROTOCOL.md §6). None (no table): everything is taken on trust, and alerts
    /// may be signed for what any peer put.
    pub gateway_keys: Option<Arc<GatewayKeys>>,
}

impl Config {
    /// Limits in force for a sensor; None when its building is not watched.
    pub fn limits(&self, building: &BuildingId, sensor: &SensorId) -> Option<Limits> {
        match self.buildings.get(building) {
            Some(b) => {
                let building_limits = b.limits.over(self.defaults);
                Some(
                    b.sensors
                        .get(sensor)
                        .map_or(building_limits, |s| s.over(building_limits)),
                )
            }
            None if self.watch_all_buildings => Some(self.defaults),
            None => None,
        }
    }

    /// Sensors listed in the file: watched for staleness from the start.
    pub fn expected_sensors(&self) -> impl Iterator<Item = (&BuildingId, &SensorId)> {
        self.buildings
            .iter()
            .flat_map(|(b, bc)| bc.sensors.keys().map(move |s| (b, s)))
    }

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
    window_s: Option<f64>,
    coverage_factor: Option<f64>,
    stale_after_s: Option<f64>,
    repeat_interval_s: Option<f64>,
    noise_share: Option<f64>,
    suspect_relative_uncertainty: Option<f64>,
    highpass_hz: Option<f64>,
    tilt_baseline_samples: Option<usize>,
    frequency_min_rms_mps2: Option<f64>,
    #[serde(default)]
    watch_all_buildings: bool,
    state_path: Option<PathBuf>,
    signing_key_file: Option<PathBuf>,
    #[serde(default)]
    gateways: BTreeMap<String, String>,
    #[serde(default)]
    zenoh: ZenohSettings,
    #[serde(default)]
    defaults: Limits,
    #[serde(default)]
    buildings: BTreeMap<String, FileBuilding>,
}

/// A building's table: its own limits beside its sensors' (serde's `flatten` cannot be combined
/// with `deny_unknown_fields`, so the limit fields are repeated here).
#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
struct FileBuilding {
    pga_mps2: Option<f64>,
    rms_mps2: Option<f64>,
    tilt_change_deg: Option<f64>,
    frequency_below_hz: Option<f64>,
    frequency_above_hz: Option<f64>,
    #[serde(default)]
    sensors: BTreeMap<String, Limits>,
}

impl FileConfig {
    fn into_config(self) -> Result<Config, ConfigError> {
        let d = Settings::default();
        let settings = Settings {
            window_s: self.window_s.unwrap_or(d.window_s),
            coverage_factor: self.coverage_factor.unwrap_or(d.coverage_factor),
            stale_after_s: self.stale_after_s.unwrap_or(d.stale_after_s),
            repeat_interval_s: self.repeat_interval_s.unwrap_or(d.repeat_interval_s),
            noise_share: self.noise_share.unwrap_or(d.noise_share),
            suspect_relative_uncertainty: self
                .suspect_relative_uncertainty
                .unwrap_or(d.suspect_relative_uncertainty),
            highpass_hz: self.highpass_hz.unwrap_or(d.highpass_hz),
            tilt_baseline_samples: self
                .tilt_baseline_samples
                .unwrap_or(d.tilt_baseline_samples),
            frequency_min_rms_mps2: self
                .frequency_min_rms_mps2
                .unwrap_or(d.frequency_min_rms_mps2),
        };
        let positive = |name: &str, v: f64| {
            if v.is_finite() && v > 0.0 {
                Ok(())
            } else {
                Err(ConfigError::invalid(
                    name,
                    format!("{v} must be finite and > 0"),
                ))
            }
        };
        // An hour of 1 kHz samples per sensor is already more memory than alerting deserves.
        if !(settings.window_s.is_finite()
            && settings.window_s > 0.0
            && settings.window_s <= 3600.0)
        {
            return Err(ConfigError::invalid(
                "window_s",
                "must be in (0, 3600] seconds",
            ));
        }
        positive("coverage_factor", settings.coverage_factor)?;
        positive("stale_after_s", settings.stale_after_s)?;
        if !(settings.repeat_interval_s.is_finite() && settings.repeat_interval_s >= 0.0) {
            return Err(ConfigError::invalid(
                "repeat_interval_s",
                "must be finite and ≥ 0",
            ));
        }
        if !(0.0..=1.0).contains(&settings.noise_share) {
            return Err(ConfigError::invalid("noise_share", "must be within 0..=1"));
        }
        if !(0.0..=1.0).contains(&settings.suspect_relative_uncertainty) {
            return Err(ConfigError::invalid(
                "suspect_relative_uncertainty",
                "must be within 0..=1",
            ));
        }
        // Below 0.001 Hz the filter would take half an hour to settle; above 10 Hz it would cut
        // into the sway it is meant to keep.
        if !(0.001..=10.0).contains(&settings.highpass_hz) {
            return Err(ConfigError::invalid(
                "highpass_hz",
                "must be within 0.001..=10 Hz",
            ));
        }
        if settings.tilt_baseline_samples == 0 {
            return Err(ConfigError::invalid("tilt_baseline_samples", "must be ≥ 1"));
        }
        if !(settings.frequency_min_rms_mps2.is_finite() && settings.frequency_min_rms_mps2 >= 0.0)
        {
            return Err(ConfigError::invalid(
                "frequency_min_rms_mps2",
                "must be finite and ≥ 0",
            ));
        }
        self.defaults.validate("defaults")?;

        let mut buildings = BTreeMap::new();
        for (name, fb) in self.buildings {
            let id = BuildingId::new(name.as_str())
                .map_err(|e| ConfigError::invalid("buildings", e.to_string()))?;
            let limits = Limits {
                pga_mps2: fb.pga_mps2,
                rms_mps2: fb.rms_mps2,
                tilt_change_deg: fb.tilt_change_deg,
                frequency_below_hz: fb.frequency_below_hz,
                frequency_above_hz: fb.frequency_above_hz,
            };
            limits.validate(&format!("buildings.{name}"))?;
            let mut sensors = BTreeMap::new();
            for (sensor, sl) in fb.sensors {
                let at = format!("buildings.{name}.sensors.{sensor}");
                let sid = SensorId::new(sensor.as_str())
                    .map_err(|e| ConfigError::invalid(&at, e.to_string()))?;
                sl.validate(&at)?;
                sensors.insert(sid, sl);
            }
            buildings.insert(id, Building { limits, sensors });
        }
        if buildings.is_empty() && !self.watch_all_buildings {
            return Err(ConfigError::invalid(
                "buildings",
                "no building to watch: list one under [buildings.<id>] or set watch_all_buildings",
            ));
        }
        self.zenoh.validate()?;
        Ok(Config {
            settings,
            zenoh: self.zenoh,
            defaults: self.defaults,
            buildings,
            watch_all_buildings: self.watch_all_buildings,
            // Empty: no state kept.
            state_path: match self.state_path {
                None => Some(default_state_path()),
                Some(p) if p.as_os_str().is_empty() => None,
                Some(p) => Some(p),
            },
            signing_key_file: self.signing_key_file.filter(|p| !p.as_os_str().is_empty()),
            gateway_keys: triax_net::keys::trusted_gateways(&self.gateways)?,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const EXAMPLE: &str = r#"
        window_s = 5.0
        stale_after_s = 12.0

        [zenoh]
        mode = "client"
        connect = ["tcp/127.0.0.1:7447"]

        [defaults]
        pga_mps2 = 2.0

        [buildings.hq]
        rms_mps2 = 0.3

        [buildings.hq.sensors.acc-01]
        pga_mps2 = 0.8
        tilt_change_deg = 0.05
    "#;

    #[test]
    fn limits_cascade_sensor_building_defaults() {
        let c = Config::from_toml(EXAMPLE).unwrap();
        assert_eq!(c.settings.window_s, 5.0);
        assert_eq!(c.settings.coverage_factor, 2.0, "default");
        assert_eq!(c.zenoh.mode, Some(ZenohMode::Client));
        let hq = BuildingId::new("hq").unwrap();
        let acc1 = SensorId::new("acc-01").unwrap();
        let other = SensorId::new("acc-02").unwrap();
        let l1 = c.limits(&hq, &acc1).unwrap();
        assert_eq!(l1.pga_mps2, Some(0.8));
        assert_eq!(l1.rms_mps2, Some(0.3));
        assert_eq!(l1.tilt_change_deg, Some(0.05));
        let l2 = c.limits(&hq, &other).unwrap();
        assert_eq!(l2.pga_mps2, Some(2.0));
        assert_eq!(l2.tilt_change_deg, None);
        assert!(c
            .limits(&BuildingId::new("annex").unwrap(), &acc1)
            .is_none());
        assert_eq!(c.expected_sensors().count(), 1);
    }

    #[test]
    fn the_example_file_loads() {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("alert.example.toml");
        let c = Config::from_file(&path).unwrap();
        assert_eq!(c.expected_sensors().count(), 2);
    }

    #[test]
    fn mistakes_are_refused_with_their_field() {
        for (text, field) in [
            ("[buildings.hq]\npga_mps = 1.0", "pga_mps"),
            ("coverage_factor = 0.0\n[buildings.hq]", "coverage_factor"),
            ("noise_share = 1.5\n[buildings.hq]", "noise_share"),
            ("highpass_hz = 0.0\n[buildings.hq]", "highpass_hz"),
            ("[buildings.hq.sensors.acc-01]\nrms_mps2 = -1.0", "rms_mps2"),
            ("[buildings.\"h q\"]", "buildings"),
            ("window_s = 10.0", "buildings"),
        ] {
            let err = Config::from_toml(text).unwrap_err().to_string();
            assert!(err.contains(field), "{text:?}: {err}");
        }
    }
}
