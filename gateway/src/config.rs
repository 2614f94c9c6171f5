//! Gateway configuration: a TOML file, command-line flags and environment variables, merged and
//! checked once at start into a [`Config`].
//!
//! Precedence, highest first: flags, environment variables (`TRIAX_*`), the TOML file, built-in
//! defaults. Every default works on one machine with no file at all: building `hq`, an
//! embedded Zenoh peer with multicast scouting, a store in `./triax-store`, metrics on
//! `127.0.0.1:9750`. A bad value is refused with its field and the reason
//! ([`ConfigError::Invalid`]); an unknown field in the file is refused too, so a typo never
//! silently falls back to a default.

use std::collections::BTreeMap;
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::time::Duration;

use serde::{Deserialize, Serialize};
use triax_health::colocated::PairConfig;
use triax_health::{HealthConfig, HealthError, LocalGravity};
pub use triax_net::{ConfigError, ZenohArgs, ZenohMode, ZenohSettings};
use triax_protocol::signing::{public_key_from_hex, LabPublicKey};
use triax_protocol::{BuildingId, Mode, SensorId};

/// Default bound on the sensors one gateway tracks.
pub const DEFAULT_MAX_SENSORS: usize = 100_000;

/// Default of [`Config::unknown_sensor_expiry`], seconds.
pub const DEFAULT_UNKNOWN_SENSOR_EXPIRY_S: f64 = 300.0;
/// Default of [`Config::declared_keys_idle`], seconds.
pub const DEFAULT_DECLARED_KEYS_IDLE_S: f64 = 60.0;

/// Default of `declared_keys_mib`: Zenoh routing state for about 5 800 keys, 2 900 sensors.
/// Not more: with 10 000 keys declared (5 000 sensors), Zenoh 1.10 spent 110 µs of CPU per
/// batch and the gateway fell behind, against 13 µs with every key undeclared (BENCHMARKS.md);
/// up to 3 500 sensors, declared keys are the cheaper (8–9 µs).
pub const DEFAULT_DECLARED_KEYS_MIB: f64 = 16.0;

/// What one declared key costs in Zenoh 1.10's routing state, measured (BENCHMARKS.md: the
/// gateway's resident set with 2000 sensors, all keys declared and none).
pub const DECLARED_KEY_BYTES: usize = 2900;

/// Default metrics endpoint.
pub const DEFAULT_METRICS_LISTEN: &str = "127.0.0.1:9750";

/// Default time between catch-up requests to the lab's registry.
pub const DEFAULT_CATCHUP_INTERVAL_S: f64 = 60.0;

/// Default time a catch-up request waits for the registry's replies.
pub const DEFAULT_CATCHUP_TIMEOUT_S: f64 = 5.0;

/// What the gateway does when raw batches come faster than it corrects and publishes them:
/// when it is overloaded, or when a consumer is slow (publishing waits, under Zenoh's blocking
/// congestion control, until the consumer's queue has room).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "kebab-case")]
pub enum Overload {
    /// Queue raw batches per worker, at most `queue_capacity_batches`, and drop the oldest
    /// when full, counted: fresh data before complete data, for live monitoring. Zenoh's
    /// receive threads never wait for the correction or for a consumer.
    #[default]
    DropOldest,
    /// Correct and publish on Zenoh's receive thread, with no queue: when the gateway or a
    /// consumer cannot keep up, Zenoh's flow control slows the sensor nodes, whose own
    /// congestion control then holds or drops their batches. The gateway drops nothing. No
    /// hand-over between threads, so the least CPU and latency per batch and the highest
    /// throughput (BENCHMARKS.md); a slow consumer slows every stream of the gateway. The
    /// correction runs on the receive thread of the link a batch came in on, so a gateway fed
    /// through one router link corrects on one core (a building's load is a few percent of
    /// one).
    Backpressure,
}

/// How a sensor's stream is corrected.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum CorrectionMode {
    /// The static set: quasi-static use (inclination, slow drift).
    Static,
    /// The dynamic set: vibration.
    Dynamic,
    /// Static set below the crossover, dynamic set above it.
    Split,
}

impl CorrectionMode {
    /// The mode byte of corrected batches.
    pub fn wire(self) -> Mode {
        match self {
            CorrectionMode::Static => Mode::Static,
            CorrectionMode::Dynamic => Mode::Dynamic,
            CorrectionMode::Split => Mode::Split,
        }
    }
}

/// Where and how much history the gateway keeps (`[history]`).
#[derive(Debug, Clone, PartialEq)]
pub struct HistorySettings {
    pub path: PathBuf,
    pub retention: Duration,
    pub max_bytes: u64,
    pub segment_bytes: u64,
    /// Longest a corrected batch waits before it is on disk.
    pub flush_interval: Duration,
    /// Bytes of samples waiting for the writer before further batches are not kept (counted).
    pub queue_bytes: usize,
    /// Long runs of the log written past the page cache (`O_DIRECT`) where the file system
    /// allows (`triax_history::append`).
    pub direct_io: bool,
}

impl HistorySettings {
    /// The history's settings, for `building`'s history only (see `triax_history::Owner`).
    pub fn history_config(
        &self,
        building: &BuildingId,
        gateway_name: &str,
    ) -> triax_history::HistoryConfig {
        let mut c = triax_history::HistoryConfig::new(&self.path).owned_by(triax_history::Owner {
            building: building.clone(),
            gateway_name: gateway_name.to_owned(),
        });
        c.max_bytes = self.max_bytes;
        c.retention = self.retention;
        c.segment_bytes = self.segment_bytes;
        c.direct_io = self.direct_io;
        c
    }
}

/// Where the history of `building` lives when `[history] path` is not set: beside the store,
/// named for the building, so that gateways of two buildings whose stores share a folder never
/// share a history.
pub fn default_history_path(store_path: &Path, building: &BuildingId) -> PathBuf {
    store_path
        .parent()
        .unwrap_or(Path::new(""))
        .join(format!("triax-history-{building}"))
}

/// The default history directory before it was named for the building: one per folder of
/// stores, which a second building's gateway took for its own. Only looked for at start, to
/// point at a history left there.
pub const LEGACY_HISTORY_DIR: &str = "triax-history";

/// Per-sensor processing settings.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SensorSettings {
    pub mode: CorrectionMode,
    /// Crossover of split mode.
    pub crossover_hz: f64,
    /// Publish a tilt stream (the sensor serves as an inclinometer).
    pub tilt: bool,
    /// Corner of the tilt low pass.
    pub tilt_cutoff_hz: f64,
    /// Time between tilt samples, by the sensor's clock.
    pub tilt_interval_s: f64,
    /// Smallest out-of-band RMS that raises `outside_frequency`.
    pub frequency_floor_mps2: f64,
}

impl Default for SensorSettings {
    fn default() -> Self {
        SensorSettings {
            mode: CorrectionMode::Dynamic,
            crossover_hz: 0.5,
            tilt: false,
            tilt_cutoff_hz: 0.1,
            tilt_interval_s: 1.0,
            frequency_floor_mps2: 0.01,
        }
    }
}

/// Calibration updates: whom to trust, how often to ask the lab's registry.
#[derive(Debug, Clone, PartialEq)]
pub struct CalibrationSettings {
    /// Lab public keys whose signed records the gateway accepts. Empty: every push and every
    /// registry record is refused with `unknown_key`.
    pub trusted_lab_keys: Vec<LabPublicKey>,
    /// Time between catch-up requests after the one at start; `None`: only at start.
    pub catchup_interval: Option<Duration>,
    /// How long one catch-up request waits for the registry's replies.
    pub catchup_timeout: Duration,
}

impl Default for CalibrationSettings {
    fn default() -> Self {
        CalibrationSettings {
            trusted_lab_keys: Vec::new(),
            catchup_interval: Some(Duration::from_secs_f64(DEFAULT_CATCHUP_INTERVAL_S)),
            catchup_timeout: Duration::from_secs_f64(DEFAULT_CATCHUP_TIMEOUT_S),
        }
    }
}

/// A validated configuration.
#[derive(Debug, Clone, PartialEq)]
pub struct Config {
    pub building: BuildingId,
    /// Name reported in status and acknowledgements.
    pub gateway_name: String,
    pub store_path: PathBuf,
    /// Correction workers; sensors are spread over them by id.
    pub workers: usize,
    /// Raw batches waiting per worker before the oldest is dropped.
    pub queue_capacity_batches: usize,
    /// Drop-oldest queues, or correction on Zenoh's receive threads with backpressure.
    pub overload: Overload,
    /// Most sensors the gateway tracks; batches from further, uncalibrated ids are counted and
    /// skipped, so a misbehaving network cannot grow the gateway's memory without bound.
    pub max_sensors: usize,
    /// How long an uncalibrated sensor may stay silent before the gateway forgets it (its
    /// counters and correction state); calibrated sensors are never forgotten.
    pub unknown_sensor_expiry: Duration,
    /// Most keys declared to Zenoh: a sensor's raw key (its input) and its output keys
    /// (corrected, tilt), declared together for calibrated sensors as they come online (never
    /// for uncalibrated ids, which anyone can make up), all or nothing: a store of 1 000 or
    /// more calibrated sensors, more than the budget holds, starts undeclared, and streaming
    /// sensors left waiting for room past the patience of `worker::Shard::reassign_keys` turn
    /// every key undeclared. Set in bytes (`declared_keys_mib`), at [`DECLARED_KEY_BYTES`] a
    /// key.
    ///
    /// Why declare: Zenoh keeps the routes of a declared key, while the route of an undeclared
    /// one is worked out again for every batch that uses it, by matching the key against every
    /// declared one. So a gateway whose keys are partly declared is the worst case: at 1000
    /// sensors with half their keys declared, a batch cost 73 µs of CPU, against 13–16 µs with
    /// all declared or none (BENCHMARKS.md). Why a bound: each key costs its routing state, and
    /// a network that names new sensors must not grow the gateway's memory without bound.
    pub declared_keys_max: usize,
    /// A sensor silent this long gives its declared keys back to the budget, where a sensor
    /// streaming on undeclared keys takes them; it declares them again when it speaks.
    pub declared_keys_idle: Duration,
    pub zenoh: ZenohSettings,
    pub calibration: CalibrationSettings,
    /// None: no history is kept (and history queries are not answered).
    pub history: Option<HistorySettings>,
    /// None: no metrics endpoint.
    pub metrics_listen: Option<SocketAddr>,
    /// None: no field health checks (no `calibration_suspect`, no health reports).
    pub health: Option<HealthSettings>,
    /// None: gaps are not filled from the nodes' buffers.
    pub backfill: Option<BackfillSettings>,
    /// How the gateway signs what it says (PROTOCOL.md §6).
    pub provenance: ProvenanceSettings,
    /// Settings of sensors not listed in `sensors`.
    pub defaults: SensorSettings,
    pub sensors: BTreeMap<SensorId, SensorSettings>,
}

/// The gateway's signing key and seals (PROTOCOL.md §6).
#[derive(Debug, Clone, PartialEq)]
pub struct ProvenanceSettings {
    /// The gateway's Ed25519 secret key, 64 hex characters. Made at first start when missing,
    /// with its public key beside it in `<key_file>.pub`, which consumers are given.
    pub key_file: PathBuf,
    /// Shortest time between two seals over the live corrected batches.
    pub seal_interval: Duration,
    /// Off: nothing is signed and no seal is put (only to measure what signing costs: every
    /// consumer that verifies then refuses all of the gateway's messages).
    pub sign: bool,
}

/// Default `[provenance] seal_interval_ms`.
pub const DEFAULT_SEAL_INTERVAL_MS: f64 = 1.0;

/// Where the gateway's key lives when `[provenance] key_file` is not set: beside the store,
/// named for the building.
pub fn default_key_file(store_path: &Path, building: &BuildingId) -> PathBuf {
    store_path
        .parent()
        .unwrap_or(Path::new(""))
        .join(format!("triax-gateway-{building}.key"))
}

impl Config {
    /// Settings in force for a sensor.
    pub fn sensor(&self, id: &str) -> &SensorSettings {
        // Looked up once per sensor, when it first appears; a linear scan of the (short) list of
        // overrides would do as well, but ids are validated so the map lookup is exact.
        SensorId::new(id)
            .ok()
            .and_then(|s| self.sensors.get(&s))
            .unwrap_or(&self.defaults)
    }

    /// A configuration for tests and embedding: defaults, the given building and store, an
    /// embedded peer with no scouting that listens on `listen`, no metrics endpoint, and no
    /// field health checks: tests stream made-up signals, often without the white noise every
    /// real sensor has, which the checks rightly take for a dead channel (turn them on with
    /// `health = Some(HealthSettings::default())`).
    ///
    /// # Panics
    /// If `building` is not a valid building id: callers pass literals.
    pub fn for_tests(building: &str, store_path: &Path, listen: Vec<String>) -> Config {
        // The empty file is the built-in defaults, which the unit tests check are valid.
        let mut c = FileConfig::default()
            .into_config()
            .expect("built-in defaults are valid");
        // Documented panic: the caller's literal is a bug if invalid.
        c.building = BuildingId::new(building).expect("test building ids are valid");
        c.gateway_name = format!("triax-gateway-{building}");
        c.store_path = store_path.to_owned();
        if let Some(h) = c.history.as_mut() {
            h.path = store_path.with_extension("history");
        }
        c.zenoh.listen = listen;
        c.zenoh.multicast_scouting = Some(false);
        c.metrics_listen = None;
        c.health = None;
        c.provenance.key_file = store_path.with_extension("key");
        c
    }
}

/// The TOML file, every field optional.
#[derive(Debug, Clone, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FileConfig {
    pub building: Option<String>,
    pub gateway_name: Option<String>,
    pub store_path: Option<PathBuf>,
    pub workers: Option<usize>,
    pub queue_capacity_batches: Option<usize>,
    pub overload: Option<Overload>,
    pub max_sensors: Option<usize>,
    pub unknown_sensor_expiry_s: Option<f64>,
    pub declared_keys_mib: Option<f64>,
    pub declared_keys_idle_s: Option<f64>,
    #[serde(default)]
    pub zenoh: ZenohSettings,
    #[serde(default)]
    pub calibration: FileCalibration,
    #[serde(default)]
    pub history: FileHistory,
    #[serde(default)]
    pub metrics: FileMetrics,
    #[serde(default)]
    pub health: FileHealth,
    #[serde(default)]
    pub backfill: FileBackfill,
    #[serde(default)]
    pub provenance: FileProvenance,
    #[serde(default)]
    pub defaults: FileSensor,
    #[serde(default)]
    pub sensors: BTreeMap<String, FileSensor>,
}

#[derive(Debug, Clone, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FileProvenance {
    pub key_file: Option<PathBuf>,
    pub seal_interval_ms: Option<f64>,
    pub sign: Option<bool>,
}

#[derive(Debug, Clone, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FileCalibration {
    /// Trusted lab public keys, 64 hex characters each.
    pub trusted_lab_keys: Option<Vec<String>>,
    /// Files holding one trusted lab public key each (as written by `triax-lab keygen`).
    pub trusted_lab_key_files: Option<Vec<PathBuf>>,
    /// Seconds between catch-up requests; 0: only at start.
    pub catchup_interval_s: Option<f64>,
    /// Seconds a catch-up request waits for the registry.
    pub catchup_timeout_s: Option<f64>,
}

#[derive(Debug, Clone, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FileHistory {
    pub enabled: Option<bool>,
    pub path: Option<PathBuf>,
    pub retention_days: Option<f64>,
    pub max_gib: Option<f64>,
    pub segment_mib: Option<f64>,
    pub flush_interval_ms: Option<f64>,
    pub queue_mib: Option<f64>,
    pub direct_io: Option<bool>,
}

/// `[backfill]`: gaps filled from the nodes' buffers (README, "The sensor node").
#[derive(Debug, Clone, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FileBackfill {
    pub enabled: Option<bool>,
    pub timeout_s: Option<f64>,
    pub max_batches: Option<u64>,
    pub max_batches_per_s: Option<f64>,
}

/// The backfill's settings (`[backfill]`).
#[derive(Debug, Clone, PartialEq)]
pub struct BackfillSettings {
    /// Longest one query may take.
    pub timeout: Duration,
    /// Most batches asked for one hole: the newest of a longer one.
    pub max_batches: u64,
    /// Most late batches corrected and published a second, all holes together; none: as fast
    /// as they come. A building's outage returns as one burst, and the live stream shares the
    /// gateway's cores with it.
    pub max_batches_per_s: Option<f64>,
}

/// Default `[backfill] timeout_s` and `max_batches` (an hour of 10-sample batches at 100 Hz,
/// `triax-node`'s default buffer).
pub const DEFAULT_BACKFILL_TIMEOUT_S: f64 = 60.0;
pub const DEFAULT_BACKFILL_MAX_BATCHES: u64 = 36_000;
/// Default `[backfill] max_batches_per_s`: a 60 s outage of 100 sensors at 10 batches a second
/// fills in 6 s.
pub const DEFAULT_BACKFILL_MAX_BATCHES_PER_S: f64 = 10_000.0;

fn backfill_settings(b: FileBackfill) -> Result<Option<BackfillSettings>, ConfigError> {
    if !b.enabled.unwrap_or(true) {
        return Ok(None);
    }
    let timeout = duration_in(
        "backfill.timeout_s",
        b.timeout_s.unwrap_or(DEFAULT_BACKFILL_TIMEOUT_S),
        0.1..=3600.0,
    )?;
    let max_batches = b.max_batches.unwrap_or(DEFAULT_BACKFILL_MAX_BATCHES);
    if !(1..=1_000_000).contains(&max_batches) {
        return Err(ConfigError::invalid(
            "backfill.max_batches",
            format!("{max_batches} is outside 1..=1000000"),
        ));
    }
    let per_s = b
        .max_batches_per_s
        .unwrap_or(DEFAULT_BACKFILL_MAX_BATCHES_PER_S);
    if !(per_s.is_finite() && (0.0..=10_000_000.0).contains(&per_s)) {
        return Err(ConfigError::invalid(
            "backfill.max_batches_per_s",
            format!("{per_s} is outside 0..=10000000 (0: no limit)"),
        ));
    }
    Ok(Some(BackfillSettings {
        timeout,
        max_batches,
        max_batches_per_s: (per_s > 0.0).then_some(per_s),
    }))
}

#[derive(Debug, Clone, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FileMetrics {
    pub enabled: Option<bool>,
    pub listen: Option<String>,
}

/// `[health]`: the field calibration health checks (README, "Calibration health in the
/// field"). Every field optional.
#[derive(Debug, Clone, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FileHealth {
    pub enabled: Option<bool>,
    pub publish_interval_s: Option<f64>,
    /// Local gravity, measured or looked up, with its standard uncertainty; or, instead, the
    /// site's latitude and height for normal gravity. Neither: the absolute gravity test is
    /// not judged.
    pub gravity_mps2: Option<f64>,
    pub gravity_uncertainty_mps2: Option<f64>,
    pub latitude_deg: Option<f64>,
    pub height_m: Option<f64>,
    pub quiet_vibration_mps2: Option<f64>,
    pub stretch_s: Option<f64>,
    pub stability_mps2: Option<f64>,
    pub relative_shift_mps2: Option<f64>,
    pub stuck_s: Option<f64>,
    pub noise_design_ratio: Option<f64>,
    pub noise_watch_windows: Option<u32>,
    pub confirm_s: Option<f64>,
    pub watch_arl_days: Option<f64>,
    pub suspect_arl_days: Option<f64>,
    /// Latency bound beyond which a node's clock is reported at `watch`, ms.
    pub clock_watch_ms: Option<f64>,
    /// Pairs of co-located sensors (`[[health.colocated]]`).
    pub colocated: Option<Vec<FileColocated>>,
    /// Groups of three co-located sensors (`[[health.triple]]`).
    pub triple: Option<Vec<FileTriple>>,
}

/// `[[health.triple]]`: three sensors on the same part of the structure.
#[derive(Debug, Clone, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FileTriple {
    pub sensors: [String; 3],
    /// B's and C's axes in A's frame, rows (`a_A = mounting · a_X`); default the identity.
    pub mountings: Option<[[[f64; 3]; 3]; 2]>,
    pub band_hz: Option<[f64; 2]>,
    pub segment_s: Option<f64>,
    pub estimate_s: Option<f64>,
    pub min_coherence: Option<f64>,
}

/// A declared group of three co-located sensors.
#[derive(Debug, Clone, PartialEq)]
pub struct TripleSettings {
    pub sensors: [SensorId; 3],
    pub triple: triax_health::huddle::TripleConfig,
}

/// `[[health.colocated]]`: two sensors on the same part of the structure.
#[derive(Debug, Clone, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FileColocated {
    pub a: String,
    pub b: String,
    /// B's axes in A's frame, rows: `a_A = mounting · a_B`; default the identity.
    pub mounting: Option<[[f64; 3]; 3]>,
    pub band_hz: Option<[f64; 2]>,
    pub segment_s: Option<f64>,
    pub estimate_s: Option<f64>,
    pub baseline_s: Option<f64>,
    pub shift: Option<f64>,
    pub min_coherence: Option<f64>,
    /// Estimates before the absolute test's first look.
    pub absolute_min_estimates: Option<u32>,
}

/// A declared co-located pair.
#[derive(Debug, Clone, PartialEq)]
pub struct ColocatedSettings {
    pub a: SensorId,
    pub b: SensorId,
    pub pair: PairConfig,
}

/// The field health checks as configured.
#[derive(Debug, Clone, PartialEq)]
pub struct HealthSettings {
    pub checks: HealthConfig,
    /// Sensor time between a sensor's health reports (a changed verdict is reported at once).
    pub publish_interval_s: f64,
    /// `|latency|` (arrival minus the last sample's time stamp) beyond which the `clock` test
    /// says `watch`, ms; none: the clock is not judged (data replayed or simulated faster than
    /// real time is never on time).
    pub clock_watch_ms: Option<f64>,
    pub colocated: Vec<ColocatedSettings>,
    pub triples: Vec<TripleSettings>,
}

/// Default [`HealthSettings::clock_watch_ms`].
pub const DEFAULT_CLOCK_WATCH_MS: f64 = 1000.0;

impl Default for HealthSettings {
    /// What an empty `[health]` gives.
    fn default() -> Self {
        HealthSettings {
            checks: HealthConfig::default(),
            publish_interval_s: DEFAULT_HEALTH_PUBLISH_INTERVAL_S,
            clock_watch_ms: Some(DEFAULT_CLOCK_WATCH_MS),
            colocated: Vec::new(),
            triples: Vec::new(),
        }
    }
}

fn colocated_settings(
    pairs: Vec<FileColocated>,
    arl: (f64, f64),
) -> Result<Vec<ColocatedSettings>, ConfigError> {
    let mut out: Vec<ColocatedSettings> = Vec::with_capacity(pairs.len());
    for (i, p) in pairs.into_iter().enumerate() {
        let field = |f: &str| format!("health.colocated[{i}].{f}");
        let a = SensorId::new(p.a.as_str())
            .map_err(|e| ConfigError::invalid(field("a"), e.to_string()))?;
        let b = SensorId::new(p.b.as_str())
            .map_err(|e| ConfigError::invalid(field("b"), e.to_string()))?;
        if a == b {
            return Err(ConfigError::invalid(
                field("b"),
                format!("{b} is also a: a pair is two sensors"),
            ));
        }
        if out
            .iter()
            .any(|q| (q.a == a && q.b == b) || (q.a == b && q.b == a))
        {
            return Err(ConfigError::invalid(
                field("b"),
                format!("the pair {a}, {b} is declared twice"),
            ));
        }
        let d = PairConfig::default();
        let pair = PairConfig {
            mounting: p.mounting.unwrap_or(d.mounting),
            band_hz: p.band_hz.unwrap_or(d.band_hz),
            segment_s: p.segment_s.unwrap_or(d.segment_s),
            estimate_s: p.estimate_s.unwrap_or(d.estimate_s),
            baseline_s: p.baseline_s.unwrap_or(d.baseline_s),
            shift: p.shift.unwrap_or(d.shift),
            min_coherence: p.min_coherence.unwrap_or(d.min_coherence),
            absolute_min_estimates: p
                .absolute_min_estimates
                .unwrap_or(d.absolute_min_estimates)
                .max(1),
            watch_arl_days: arl.0,
            suspect_arl_days: arl.1,
            ..d
        };
        pair.validate().map_err(|e| match e {
            HealthError::Config { field: f, problem } => ConfigError::invalid(field(f), problem),
            other => ConfigError::invalid(field("a"), other.to_string()),
        })?;
        out.push(ColocatedSettings { a, b, pair });
    }
    Ok(out)
}

fn triple_settings(triples: Vec<FileTriple>) -> Result<Vec<TripleSettings>, ConfigError> {
    let mut out: Vec<TripleSettings> = Vec::with_capacity(triples.len());
    for (i, t) in triples.into_iter().enumerate() {
        let field = |f: &str| format!("health.triple[{i}].{f}");
        let mut sensors = Vec::with_capacity(3);
        for (k, id) in t.sensors.iter().enumerate() {
            let id = SensorId::new(id.as_str()).map_err(|e| {
                ConfigError::invalid(field(&format!("sensors[{k}]")), e.to_string())
            })?;
            if sensors.contains(&id) {
                return Err(ConfigError::invalid(
                    field("sensors"),
                    format!("{id} is named twice: a group of three is three sensors"),
                ));
            }
            sensors.push(id);
        }
        let d = triax_health::huddle::TripleConfig::default();
        let triple = triax_health::huddle::TripleConfig {
            mountings: t.mountings.unwrap_or(d.mountings),
            band_hz: t.band_hz.unwrap_or(d.band_hz),
            segment_s: t.segment_s.unwrap_or(d.segment_s),
            estimate_s: t.estimate_s.unwrap_or(d.estimate_s),
            min_coherence: t.min_coherence.unwrap_or(d.min_coherence),
            ..d
        };
        triple.validate().map_err(|e| match e {
            HealthError::Config { field: f, problem } => ConfigError::invalid(field(f), problem),
            other => ConfigError::invalid(field("sensors"), other.to_string()),
        })?;
        let sensors: [SensorId; 3] = sensors
            .try_into()
            .map_err(|_| ConfigError::invalid(field("sensors"), "three sensors"))?;
        out.push(TripleSettings { sensors, triple });
    }
    Ok(out)
}

/// Gives each pair the number of tests that share its sensors' false-alarm budgets: a
/// sensor's own four sequential tests (spikes on three channels, relative gravity) and its
/// absolute gravity test, and three of each kind for every pair it is in; a pair takes the
/// larger count of its two sensors.
fn share_budgets(pairs: &mut [ColocatedSettings], gravity: bool) {
    let count = |id: &SensorId, pairs: &[ColocatedSettings]| {
        pairs.iter().filter(|p| &p.a == id || &p.b == id).count() as u32
    };
    let counts: Vec<u32> = pairs
        .iter()
        .map(|p| count(&p.a, pairs).max(count(&p.b, pairs)))
        .collect();
    for (p, n) in pairs.iter_mut().zip(counts) {
        p.pair.shared_sequential_tests = 4 + 3 * n;
        p.pair.shared_absolute_tests = u32::from(gravity) + 3 * n;
    }
}

/// Default time between a sensor's health reports, s.
pub const DEFAULT_HEALTH_PUBLISH_INTERVAL_S: f64 = 60.0;

fn health_settings(h: FileHealth) -> Result<Option<HealthSettings>, ConfigError> {
    if !h.enabled.unwrap_or(true) {
        return Ok(None);
    }
    let publish_interval_s = h
        .publish_interval_s
        .unwrap_or(DEFAULT_HEALTH_PUBLISH_INTERVAL_S);
    if !(publish_interval_s.is_finite() && (0.1..=86_400.0).contains(&publish_interval_s)) {
        return Err(ConfigError::invalid(
            "health.publish_interval_s",
            format!("{publish_interval_s} is outside 0.1..=86400"),
        ));
    }
    let local_gravity = match (
        h.gravity_mps2,
        h.gravity_uncertainty_mps2,
        h.latitude_deg,
        h.height_m,
    ) {
        (None, None, None, None) => None,
        (Some(g), Some(u), None, None) => Some(
            LocalGravity::known(g, u)
                .map_err(|e| ConfigError::invalid("health.gravity_mps2", e.to_string()))?,
        ),
        (None, None, Some(lat), height) => Some(
            LocalGravity::normal(lat, height.unwrap_or(0.0))
                .map_err(|e| ConfigError::invalid("health.latitude_deg", e.to_string()))?,
        ),
        _ => {
            return Err(ConfigError::invalid(
                "health.gravity_mps2",
                "give gravity_mps2 with gravity_uncertainty_mps2, or latitude_deg (and \
                 height_m), not both and not one without the other",
            ))
        }
    };
    let mut checks = HealthConfig {
        local_gravity,
        ..HealthConfig::default()
    };
    let overrides = [
        (&mut checks.quiet_vibration_mps2, h.quiet_vibration_mps2),
        (&mut checks.stretch_s, h.stretch_s),
        (&mut checks.stability_mps2, h.stability_mps2),
        (&mut checks.relative_shift_mps2, h.relative_shift_mps2),
        (&mut checks.stuck_s, h.stuck_s),
        (&mut checks.noise_design_ratio, h.noise_design_ratio),
        (&mut checks.watch_arl_days, h.watch_arl_days),
        (&mut checks.suspect_arl_days, h.suspect_arl_days),
    ];
    for (field, value) in overrides {
        if let Some(v) = value {
            *field = v;
        }
    }
    if let Some(v) = h.confirm_s {
        checks.confirm_s = v;
    }
    if let Some(v) = h.noise_watch_windows {
        checks.noise_watch_windows = v;
    }
    checks.validate().map_err(|e| match e {
        HealthError::Config { field, problem } => {
            ConfigError::invalid(format!("health.{field}"), problem)
        }
        other => ConfigError::invalid("health", other.to_string()),
    })?;
    let clock_watch_ms = match h.clock_watch_ms.unwrap_or(DEFAULT_CLOCK_WATCH_MS) {
        0.0 => None,
        ms if ms.is_finite() && ms > 0.0 => Some(ms),
        ms => {
            return Err(ConfigError::invalid(
                "health.clock_watch_ms",
                format!("{ms} is not a positive number of milliseconds (0: off)"),
            ))
        }
    };
    let mut colocated = colocated_settings(
        h.colocated.unwrap_or_default(),
        (checks.watch_arl_days, checks.suspect_arl_days),
    )?;
    share_budgets(&mut colocated, checks.local_gravity.is_some());
    let triples = triple_settings(h.triple.unwrap_or_default())?;
    Ok(Some(HealthSettings {
        checks,
        publish_interval_s,
        clock_watch_ms,
        colocated,
        triples,
    }))
}

#[derive(Debug, Clone, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FileSensor {
    pub mode: Option<CorrectionMode>,
    pub crossover_hz: Option<f64>,
    pub tilt: Option<bool>,
    pub tilt_cutoff_hz: Option<f64>,
    pub tilt_interval_s: Option<f64>,
    pub frequency_floor_mps2: Option<f64>,
}

impl FileConfig {
    pub fn read(path: &Path) -> Result<FileConfig, ConfigError> {
        triax_net::read_toml(path)
    }

    pub fn parse(text: &str, path: &Path) -> Result<FileConfig, ConfigError> {
        triax_net::parse_toml(text, path)
    }

    /// Checks every field and fills in defaults.
    pub fn into_config(self) -> Result<Config, ConfigError> {
        let building = self.building.unwrap_or_else(|| "hq".into());
        let building = BuildingId::new(building)
            .map_err(|e| ConfigError::invalid("building", e.to_string()))?;
        let gateway_name = self
            .gateway_name
            .unwrap_or_else(|| format!("triax-gateway-{building}"));
        if gateway_name.trim().is_empty() {
            return Err(ConfigError::invalid("gateway_name", "must not be empty"));
        }
        let workers = match self.workers {
            None | Some(0) => std::thread::available_parallelism().map_or(1, |n| n.get()),
            Some(n) if n > 256 => {
                return Err(ConfigError::invalid("workers", format!("{n} is above 256")))
            }
            Some(n) => n,
        };
        let max_sensors = self.max_sensors.unwrap_or(DEFAULT_MAX_SENSORS);
        if max_sensors == 0 {
            return Err(ConfigError::invalid("max_sensors", "must be at least 1"));
        }
        let declared_keys_mib = self.declared_keys_mib.unwrap_or(DEFAULT_DECLARED_KEYS_MIB);
        if !(declared_keys_mib.is_finite() && (0.0..=65_536.0).contains(&declared_keys_mib)) {
            return Err(ConfigError::invalid(
                "declared_keys_mib",
                format!("{declared_keys_mib} is outside 0..=65536"),
            ));
        }
        let declared_keys_max =
            (declared_keys_mib * (1u64 << 20) as f64 / DECLARED_KEY_BYTES as f64) as usize;
        let declared_keys_idle = duration_in(
            "declared_keys_idle_s",
            self.declared_keys_idle_s
                .unwrap_or(DEFAULT_DECLARED_KEYS_IDLE_S),
            1.0..=86_400.0,
        )?;
        let unknown_sensor_expiry = duration_in(
            "unknown_sensor_expiry_s",
            self.unknown_sensor_expiry_s
                .unwrap_or(DEFAULT_UNKNOWN_SENSOR_EXPIRY_S),
            1.0..=1e7,
        )?;
        let queue_capacity_batches = self.queue_capacity_batches.unwrap_or(1024);
        if !(1..=1_000_000).contains(&queue_capacity_batches) {
            return Err(ConfigError::invalid(
                "queue_capacity_batches",
                format!("{queue_capacity_batches} is outside 1..=1000000"),
            ));
        }
        let zenoh = self.zenoh;
        zenoh.validate()?;
        let calibration = calibration_settings(self.calibration)?;
        let metrics_listen = if self.metrics.enabled.unwrap_or(true) {
            let text = self
                .metrics
                .listen
                .unwrap_or_else(|| DEFAULT_METRICS_LISTEN.into());
            Some(text.parse::<SocketAddr>().map_err(|e| {
                ConfigError::invalid(
                    "metrics.listen",
                    format!("{text:?} is not an address like \"127.0.0.1:9750\": {e}"),
                )
            })?)
        } else {
            None
        };
        let store_path = self
            .store_path
            .unwrap_or_else(|| PathBuf::from("triax-store"));
        let history = history_settings(self.history, &store_path, &building)?;
        let health = health_settings(self.health)?;
        let backfill = backfill_settings(self.backfill)?;
        let provenance = provenance_settings(self.provenance, &store_path, &building)?;
        let defaults = sensor_settings("defaults", self.defaults, &SensorSettings::default())?;
        let mut sensors = BTreeMap::new();
        for (id, s) in self.sensors {
            let sensor_id = SensorId::new(id.as_str())
                .map_err(|e| ConfigError::invalid(format!("sensors.{id}"), e.to_string()))?;
            let settings = sensor_settings(&format!("sensors.{id}"), s, &defaults)?;
            sensors.insert(sensor_id, settings);
        }
        Ok(Config {
            building,
            gateway_name,
            store_path,
            workers,
            queue_capacity_batches,
            overload: self.overload.unwrap_or_default(),
            max_sensors,
            unknown_sensor_expiry,
            declared_keys_max,
            declared_keys_idle,
            zenoh,
            calibration,
            history,
            metrics_listen,
            health,
            backfill,
            provenance,
            defaults,
            sensors,
        })
    }
}

fn provenance_settings(
    p: FileProvenance,
    store_path: &Path,
    building: &BuildingId,
) -> Result<ProvenanceSettings, ConfigError> {
    let interval_ms = p.seal_interval_ms.unwrap_or(DEFAULT_SEAL_INTERVAL_MS);
    // Longer than a second, a consumer would hold a second of batches before it may use them.
    if !(interval_ms.is_finite() && (0.0..=1000.0).contains(&interval_ms)) {
        return Err(ConfigError::invalid(
            "provenance.seal_interval_ms",
            format!("{interval_ms} is outside 0..=1000"),
        ));
    }
    Ok(ProvenanceSettings {
        key_file: p
            .key_file
            .unwrap_or_else(|| default_key_file(store_path, building)),
        seal_interval: Duration::from_secs_f64(interval_ms / 1000.0),
        sign: p.sign.unwrap_or(true),
    })
}

fn calibration_settings(c: FileCalibration) -> Result<CalibrationSettings, ConfigError> {
    let mut trusted_lab_keys = Vec::new();
    for (i, text) in c.trusted_lab_keys.unwrap_or_default().iter().enumerate() {
        let key = public_key_from_hex(text).map_err(|e| {
            ConfigError::invalid(format!("calibration.trusted_lab_keys[{i}]"), e.to_string())
        })?;
        trusted_lab_keys.push(key);
    }
    for (i, path) in c
        .trusted_lab_key_files
        .unwrap_or_default()
        .iter()
        .enumerate()
    {
        let field = || format!("calibration.trusted_lab_key_files[{i}]");
        let text = std::fs::read_to_string(path).map_err(|e| {
            ConfigError::invalid(field(), format!("cannot read {}: {e}", path.display()))
        })?;
        let key = public_key_from_hex(&text)
            .map_err(|e| ConfigError::invalid(field(), format!("{}: {e}", path.display())))?;
        trusted_lab_keys.push(key);
    }
    // The same key listed twice (inline and in a file) is harmless; keep one.
    let mut unique: Vec<LabPublicKey> = Vec::with_capacity(trusted_lab_keys.len());
    for k in trusted_lab_keys {
        if !unique.contains(&k) {
            unique.push(k);
        }
    }
    let seconds = |name: &str, v: f64| -> Result<f64, ConfigError> {
        // Below a millisecond is a typo; above a day, catch-up would be pointless.
        if v.is_finite() && (0.001..=86_400.0).contains(&v) {
            Ok(v)
        } else {
            Err(ConfigError::invalid(
                format!("calibration.{name}"),
                format!("{v} is not a number of seconds in 0.001..=86400"),
            ))
        }
    };
    let interval_s = c.catchup_interval_s.unwrap_or(DEFAULT_CATCHUP_INTERVAL_S);
    let catchup_interval = if interval_s == 0.0 {
        None
    } else {
        Some(Duration::from_secs_f64(seconds(
            "catchup_interval_s",
            interval_s,
        )?))
    };
    let timeout_s = c.catchup_timeout_s.unwrap_or(DEFAULT_CATCHUP_TIMEOUT_S);
    let catchup_timeout = Duration::from_secs_f64(seconds("catchup_timeout_s", timeout_s)?);
    Ok(CalibrationSettings {
        trusted_lab_keys: unique,
        catchup_interval,
        catchup_timeout,
    })
}

/// `store_path`, `building`: the default history lives beside the store, in
/// `triax-history-<building>` ([`default_history_path`]).
fn history_settings(
    h: FileHistory,
    store_path: &Path,
    building: &BuildingId,
) -> Result<Option<HistorySettings>, ConfigError> {
    if !h.enabled.unwrap_or(true) {
        return Ok(None);
    }
    let within = |field: &str, v: f64, range: std::ops::RangeInclusive<f64>| {
        if v.is_finite() && range.contains(&v) {
            Ok(v)
        } else {
            Err(ConfigError::invalid(
                format!("history.{field}"),
                format!("{v} is outside {}..={}", range.start(), range.end()),
            ))
        }
    };
    let days = within(
        "retention_days",
        h.retention_days.unwrap_or(30.0),
        0.001..=36_500.0,
    )?;
    let gib = within("max_gib", h.max_gib.unwrap_or(20.0), 0.001..=1_000_000.0)?;
    let segment_mib = within(
        "segment_mib",
        h.segment_mib.unwrap_or(32.0),
        0.0625..=4096.0,
    )?;
    let flush_ms = within(
        "flush_interval_ms",
        h.flush_interval_ms.unwrap_or(1000.0),
        10.0..=60_000.0,
    )?;
    let queue_mib = within("queue_mib", h.queue_mib.unwrap_or(16.0), 0.0625..=4096.0)?;
    Ok(Some(HistorySettings {
        path: h
            .path
            .unwrap_or_else(|| default_history_path(store_path, building)),
        retention: Duration::from_secs_f64(days * 86_400.0),
        max_bytes: (gib * (1u64 << 30) as f64) as u64,
        segment_bytes: (segment_mib * (1u64 << 20) as f64) as u64,
        flush_interval: Duration::from_secs_f64(flush_ms / 1000.0),
        queue_bytes: (queue_mib * (1u64 << 20) as f64) as usize,
        direct_io: h.direct_io.unwrap_or(true),
    }))
}

/// `v` seconds as a duration, refused with `field` unless finite and within `range`.
fn duration_in(
    field: &str,
    v: f64,
    range: std::ops::RangeInclusive<f64>,
) -> Result<Duration, ConfigError> {
    if v.is_finite() && range.contains(&v) {
        Ok(Duration::from_secs_f64(v))
    } else {
        Err(ConfigError::invalid(
            field,
            format!(
                "{v} is not a number of seconds in {}..={}",
                range.start(),
                range.end()
            ),
        ))
    }
}

fn sensor_settings(
    at: &str,
    s: FileSensor,
    base: &SensorSettings,
) -> Result<SensorSettings, ConfigError> {
    let positive = |name: &str, v: Option<f64>, default: f64| -> Result<f64, ConfigError> {
        let v = v.unwrap_or(default);
        if v.is_finite() && v > 0.0 {
            Ok(v)
        } else {
            Err(ConfigError::invalid(
                format!("{at}.{name}"),
                format!("{v} is not a positive finite number"),
            ))
        }
    };
    let out = SensorSettings {
        mode: s.mode.unwrap_or(base.mode),
        crossover_hz: positive("crossover_hz", s.crossover_hz, base.crossover_hz)?,
        tilt: s.tilt.unwrap_or(base.tilt),
        tilt_cutoff_hz: positive("tilt_cutoff_hz", s.tilt_cutoff_hz, base.tilt_cutoff_hz)?,
        tilt_interval_s: positive("tilt_interval_s", s.tilt_interval_s, base.tilt_interval_s)?,
        frequency_floor_mps2: positive(
            "frequency_floor_mps2",
            s.frequency_floor_mps2,
            base.frequency_floor_mps2,
        )?,
    };
    if out.tilt_interval_s < 0.01 {
        return Err(ConfigError::invalid(
            format!("{at}.tilt_interval_s"),
            format!(
                "{} s is below 0.01 s: tilt is a slow stream",
                out.tilt_interval_s
            ),
        ));
    }
    Ok(out)
}

/// Command-line flags and their environment variables, shared by the binary and tests.
#[derive(Debug, Clone, Default, clap::Args)]
pub struct ConfigArgs {
    /// TOML configuration file.
    #[arg(long, short = 'c', env = "TRIAX_CONFIG")]
    pub config: Option<PathBuf>,
    /// Building id: the gateway serves `triax/<building>/…`.
    #[arg(long, env = "TRIAX_BUILDING")]
    pub building: Option<String>,
    /// Directory of the calibration store.
    #[arg(long, env = "TRIAX_STORE")]
    pub store: Option<PathBuf>,
    /// Directory of the history of raw batches (default `triax-history-<building>` beside the
    /// store).
    #[arg(long, env = "TRIAX_HISTORY")]
    pub history: Option<PathBuf>,
    /// Keep no history (history queries are then not answered).
    #[arg(long, env = "TRIAX_NO_HISTORY")]
    pub no_history: bool,
    #[command(flatten)]
    pub zenoh: ZenohArgs,
    /// Metrics endpoint address, e.g. 0.0.0.0:9750.
    #[arg(long, env = "TRIAX_METRICS_LISTEN")]
    pub metrics_listen: Option<String>,
    /// Serve no metrics endpoint.
    #[arg(long, env = "TRIAX_NO_METRICS")]
    pub no_metrics: bool,
    /// Correction workers (0: one per core).
    #[arg(long, env = "TRIAX_WORKERS")]
    pub workers: Option<usize>,
    /// When batches come faster than they are published: drop the oldest (queued, counted) or
    /// push back on the sensor nodes.
    #[arg(long, value_enum, env = "TRIAX_OVERLOAD")]
    pub overload: Option<Overload>,
    /// Default correction mode of sensors not listed in the file.
    #[arg(long, value_enum, env = "TRIAX_MODE")]
    pub mode: Option<CorrectionMode>,
    /// Trusted lab public key, 64 hex characters (repeat or comma-separate; replaces the file's
    /// list).
    #[arg(long, env = "TRIAX_TRUSTED_LAB_KEYS", value_delimiter = ',')]
    pub trusted_lab_key: Vec<String>,
    /// File holding a trusted lab public key (repeat or comma-separate; replaces the file's
    /// list).
    #[arg(long, env = "TRIAX_TRUSTED_LAB_KEY_FILES", value_delimiter = ',')]
    pub trusted_lab_key_file: Vec<PathBuf>,
    /// Seconds between catch-up requests to the lab's registry; 0: only at start.
    #[arg(long, env = "TRIAX_CATCHUP_INTERVAL_S")]
    pub catchup_interval_s: Option<f64>,
    /// The gateway's secret signing key (made, with `<file>.pub`, when missing; default
    /// `triax-gateway-<building>.key` beside the store).
    #[arg(long, env = "TRIAX_KEY_FILE")]
    pub key_file: Option<PathBuf>,
}

impl ConfigArgs {
    /// Reads the file (if any), applies flags and environment on top, and validates.
    pub fn load(&self) -> Result<Config, ConfigError> {
        let mut file = match &self.config {
            Some(p) => FileConfig::read(p)?,
            None => FileConfig::default(),
        };
        self.apply(&mut file);
        file.into_config()
    }

    fn apply(&self, f: &mut FileConfig) {
        if let Some(b) = &self.building {
            f.building = Some(b.clone());
        }
        if let Some(s) = &self.store {
            f.store_path = Some(s.clone());
        }
        if let Some(h) = &self.history {
            f.history.path = Some(h.clone());
        }
        if self.no_history {
            f.history.enabled = Some(false);
        }
        self.zenoh.apply_to(&mut f.zenoh);
        if let Some(m) = &self.metrics_listen {
            f.metrics.listen = Some(m.clone());
        }
        if self.no_metrics {
            f.metrics.enabled = Some(false);
        }
        if let Some(w) = self.workers {
            f.workers = Some(w);
        }
        if let Some(o) = self.overload {
            f.overload = Some(o);
        }
        if let Some(m) = self.mode {
            f.defaults.mode = Some(m);
        }
        if !self.trusted_lab_key.is_empty() {
            f.calibration.trusted_lab_keys = Some(self.trusted_lab_key.clone());
        }
        if !self.trusted_lab_key_file.is_empty() {
            f.calibration.trusted_lab_key_files = Some(self.trusted_lab_key_file.clone());
        }
        if let Some(s) = self.catchup_interval_s {
            f.calibration.catchup_interval_s = Some(s);
        }
        if let Some(k) = &self.key_file {
            f.provenance.key_file = Some(k.clone());
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn parse(text: &str) -> Result<Config, ConfigError> {
        FileConfig::parse(text, Path::new("t.toml"))?.into_config()
    }

    /// The configuration README.md shows, field by field, is one the gateway takes: a field
    /// named there and not here (or a value out of range) would be refused at start.
    #[test]
    fn the_readmes_configuration_parses() {
        let readme = include_str!("../../README.md");
        let section = readme
            .find("## The gateway: `triax-gateway`")
            .expect("README has the gateway's section");
        let start = readme[section..].find("```toml\n").expect("a TOML block") + section + 8;
        let len = readme[start..].find("```").expect("the block ends");
        // The one placeholder: a lab's public key, 64 hex digits.
        let lab = triax_protocol::signing::LabSigningKey::from_bytes(&[7; 32]);
        let key = triax_protocol::signing::to_hex(lab.verifying_key().as_bytes());
        let text = readme[start..start + len].replace("<contents of lab.pub>", &key);
        let c = parse(&text).unwrap();
        let h = c.history.expect("history on");
        assert!(h.direct_io);
        assert_eq!(h.queue_bytes, 16 << 20);
    }

    /// `[health]`: on by default with no gravity; a measured gravity or a latitude; every
    /// refusal names its field.
    #[test]
    fn health_settings_parse_and_refuse_by_field() {
        let h = parse("").unwrap().health.expect("on by default");
        assert_eq!(h, HealthSettings::default());
        assert!(parse("[health]\nenabled = false").unwrap().health.is_none());
        let h =
            parse("[health]\ngravity_mps2 = 9.8061\ngravity_uncertainty_mps2 = 1e-5\nstuck_s = 20")
                .unwrap()
                .health
                .unwrap();
        let g = h.checks.local_gravity.unwrap();
        assert_eq!(
            (g.value_mps2, g.uncertainty_mps2, h.checks.stuck_s),
            (9.8061, 1e-5, 20.0)
        );
        let h = parse("[health]\nlatitude_deg = 45.0")
            .unwrap()
            .health
            .unwrap();
        let g = h.checks.local_gravity.unwrap();
        assert!((g.value_mps2 - 9.806_197_769_4).abs() < 1e-9, "{g:?}");
        let field = |text: &str| match parse(text) {
            Err(ConfigError::Invalid { field, .. }) => field,
            other => panic!("{text}: {other:?}"),
        };
        assert_eq!(
            field("[health]\ngravity_mps2 = 9.81"),
            "health.gravity_mps2"
        );
        assert_eq!(
            field("[health]\nlatitude_deg = 45.0\ngravity_mps2 = 9.81\ngravity_uncertainty_mps2 = 1e-4"),
            "health.gravity_mps2"
        );
        assert_eq!(
            field("[health]\nlatitude_deg = 95.0"),
            "health.latitude_deg"
        );
        assert_eq!(
            field("[health]\npublish_interval_s = 0"),
            "health.publish_interval_s"
        );
        assert_eq!(field("[health]\nstuck_s = -1"), "health.stuck_s");
        assert!(
            parse("[health]\nstuck = 1").is_err(),
            "unknown fields are refused"
        );
        let pair = "[[health.colocated]]\na = \"x1\"\nb = \"x2\"\n";
        let h = parse(&format!("{pair}estimate_s = 300"))
            .unwrap()
            .health
            .unwrap();
        assert_eq!(h.colocated.len(), 1);
        assert_eq!(h.colocated[0].pair.estimate_s, 300.0);
        assert_eq!(h.colocated[0].pair.mounting, PairConfig::default().mounting);
        assert_eq!(
            field("[[health.colocated]]\na = \"x1\"\nb = \"x1\""),
            "health.colocated[0].b"
        );
        assert_eq!(
            field(&format!("{pair}mounting = [[1,0,0],[0,1,0],[0,0,2]]")),
            "health.colocated[0].mounting"
        );
        assert_eq!(
            field(&format!(
                "{pair}[[health.colocated]]\na = \"x2\"\nb = \"x1\""
            )),
            "health.colocated[1].b"
        );
        // x1 is in two pairs: both pairs share its budget, 4 + 3·2 sequential tests and (local
        // gravity given) 1 + 3·2 absolute ones.
        let h = parse(&format!(
            "[health]\nlatitude_deg = 45.0\n{pair}[[health.colocated]]\na = \"x1\"\nb = \"x3\"\n"
        ))
        .unwrap()
        .health
        .unwrap();
        assert_eq!(h.colocated[0].pair.shared_sequential_tests, 10);
        assert_eq!(h.colocated[1].pair.shared_absolute_tests, 7);
        let triple = "[[health.triple]]\nsensors = [\"t1\", \"t2\", \"t3\"]\n";
        let h = parse(&format!("{triple}estimate_s = 600"))
            .unwrap()
            .health
            .unwrap();
        assert_eq!(h.triples[0].triple.estimate_s, 600.0);
        assert_eq!(
            field("[[health.triple]]\nsensors = [\"t1\", \"t2\", \"t1\"]"),
            "health.triple[0].sensors"
        );
        assert_eq!(
            field(&format!("{triple}min_coherence = 2")),
            "health.triple[0].min_coherence"
        );
        assert_eq!(field("[health]\nconfirm_s = 0"), "health.confirm_s");
        assert_eq!(
            field("[health]\nnoise_watch_windows = 0"),
            "health.noise_watch_windows"
        );
        assert_eq!(
            field("[health]\nclock_watch_ms = -1"),
            "health.clock_watch_ms"
        );
        let h = parse("[health]\nclock_watch_ms = 0")
            .unwrap()
            .health
            .unwrap();
        assert_eq!(h.clock_watch_ms, None);
        assert_eq!(
            parse("").unwrap().health.unwrap().clock_watch_ms,
            Some(DEFAULT_CLOCK_WATCH_MS)
        );
    }

    #[test]
    fn defaults_work() {
        let c = parse("").unwrap();
        assert_eq!(c.building.as_str(), "hq");
        assert_eq!(c.zenoh.mode, None);
        assert_eq!(c.metrics_listen, Some("127.0.0.1:9750".parse().unwrap()));
        assert_eq!(c.sensor("anything").mode, CorrectionMode::Dynamic);
        assert_eq!(c.overload, Overload::DropOldest);
        let c = parse("overload = \"backpressure\"").unwrap();
        assert_eq!(c.overload, Overload::Backpressure);
    }

    #[test]
    fn the_default_history_is_named_for_the_building_beside_the_store() {
        let c = parse("building = \"xb\"\nstore_path = \"/srv/triax/xb-store\"").unwrap();
        let path = c.history.map(|h| h.path);
        assert_eq!(path, Some(PathBuf::from("/srv/triax/triax-history-xb")));
        let c = parse("building = \"zz\"\nstore_path = \"/srv/triax/zz-store\"").unwrap();
        let path = c.history.map(|h| h.path);
        assert_eq!(path, Some(PathBuf::from("/srv/triax/triax-history-zz")));
        let c = parse("building = \"zz\"\n[history]\npath = \"/srv/h\"").unwrap();
        assert_eq!(c.history.map(|h| h.path), Some(PathBuf::from("/srv/h")));
    }

    #[test]
    fn the_history_writes_past_the_page_cache_unless_told_not_to() {
        let h = |text: &str| parse(text).unwrap().history.unwrap();
        assert!(h("").direct_io);
        assert!(h("[history]\ndirect_io = true").direct_io);
        let off = h("[history]\ndirect_io = false");
        assert!(!off.direct_io);
        assert!(
            !off.history_config(&BuildingId::new("hq").unwrap(), "g")
                .direct_io
        );
    }

    #[test]
    fn per_sensor_settings_inherit_defaults() {
        let c = parse(
            r#"
            building = "b2"
            [defaults]
            mode = "static"
            crossover_hz = 0.3
            [sensors.roof-1]
            mode = "split"
            tilt = true
            "#,
        )
        .unwrap();
        let s = c.sensor("roof-1");
        assert_eq!(s.mode, CorrectionMode::Split);
        assert!(s.tilt);
        assert_eq!(s.crossover_hz, 0.3);
        assert_eq!(c.sensor("other").mode, CorrectionMode::Static);
    }

    #[test]
    fn bad_values_name_the_field() {
        let e = parse("[sensors.a]\ncrossover_hz = -1.0").unwrap_err();
        assert!(
            e.to_string()
                .contains("`sensors.a.crossover_hz`: -1 is not a positive finite number"),
            "{e}"
        );
        let e = parse("building = \"a b\"").unwrap_err();
        assert!(e.to_string().contains("`building`"), "{e}");
        let e = parse("[metrics]\nlisten = \"nowhere\"").unwrap_err();
        assert!(e.to_string().contains("`metrics.listen`"), "{e}");
        let e = parse("[zenoh]\nmode = \"client\"").unwrap_err();
        assert!(e.to_string().contains("`zenoh.connect`"), "{e}");
        let e = parse("[zenoh]\nlisten = [\"7447\"]").unwrap_err();
        assert!(e.to_string().contains("`zenoh.listen[0]`"), "{e}");
        let e = parse("[defaults]\nmode = \"fast\"").unwrap_err();
        assert!(e.to_string().contains("unknown variant `fast`"), "{e}");
        let e = parse("overload = \"drop-newest\"").unwrap_err();
        assert!(
            e.to_string().contains("unknown variant `drop-newest`"),
            "{e}"
        );
        let e = parse("bulding = \"x\"").unwrap_err();
        assert!(e.to_string().contains("unknown field `bulding`"), "{e}");
    }

    #[test]
    fn trusted_keys_and_catchup_settings() {
        let c = parse("").unwrap();
        assert!(c.calibration.trusted_lab_keys.is_empty());
        assert_eq!(
            c.calibration.catchup_interval,
            Some(Duration::from_secs(60))
        );
        let key = "d75a980182b10ab7d54bfed3c964073a0ee172f3daa62325af021a68f707511a";
        let c = parse(&format!(
            "[calibration]\ntrusted_lab_keys = [\"{key}\", \"{key}\"]\ncatchup_interval_s = 0"
        ))
        .unwrap();
        assert_eq!(c.calibration.trusted_lab_keys.len(), 1);
        assert_eq!(c.calibration.catchup_interval, None);
        let e = parse("[calibration]\ntrusted_lab_keys = [\"abc\"]").unwrap_err();
        assert!(
            e.to_string().contains("`calibration.trusted_lab_keys[0]`"),
            "{e}"
        );
        let e =
            parse("[calibration]\ntrusted_lab_key_files = [\"/nonexistent/lab.pub\"]").unwrap_err();
        assert!(
            e.to_string()
                .contains("`calibration.trusted_lab_key_files[0]`: cannot read"),
            "{e}"
        );
        let e = parse("[calibration]\ncatchup_timeout_s = -1").unwrap_err();
        assert!(
            e.to_string().contains("`calibration.catchup_timeout_s`"),
            "{e}"
        );
    }

    #[test]
    fn backfill_settings_default_and_refuse_by_name() {
        let c = parse("").unwrap();
        let b = c.backfill.expect("backfill is on by default");
        assert_eq!(b.max_batches, DEFAULT_BACKFILL_MAX_BATCHES);
        assert_eq!(
            b.max_batches_per_s,
            Some(DEFAULT_BACKFILL_MAX_BATCHES_PER_S)
        );
        assert_eq!(
            b.timeout,
            Duration::from_secs_f64(DEFAULT_BACKFILL_TIMEOUT_S)
        );
        assert!(parse("[backfill]\nenabled = false")
            .unwrap()
            .backfill
            .is_none());
        let unpaced = parse("[backfill]\nmax_batches_per_s = 0").unwrap();
        assert_eq!(unpaced.backfill.unwrap().max_batches_per_s, None);
        for (bad, field) in [
            ("max_batches = 0", "backfill.max_batches"),
            ("max_batches_per_s = -1", "backfill.max_batches_per_s"),
            ("timeout_s = 0", "backfill.timeout_s"),
            ("retries = 3", "retries"),
        ] {
            let e = parse(&format!("[backfill]\n{bad}")).unwrap_err();
            assert!(e.to_string().contains(field), "{bad}: {e}");
        }
    }

    #[test]
    fn the_example_file_is_valid() {
        let c = parse(include_str!("../gateway.example.toml")).unwrap();
        assert_eq!(c.sensor("roof-incl-1").mode, CorrectionMode::Split);
        assert!(c.sensor("roof-incl-1").tilt);
        assert_eq!(c.zenoh.listen, ["tcp/0.0.0.0:7447"]);
        assert_eq!(c.defaults, SensorSettings::default());
        assert_eq!(
            c.declared_keys_max,
            (DEFAULT_DECLARED_KEYS_MIB * 1048576.0) as usize / DECLARED_KEY_BYTES
        );
    }

    #[test]
    fn flags_override_the_file() {
        let dir = std::env::temp_dir().join(format!("triax-cfg-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("g.toml");
        std::fs::write(
            &path,
            "building = \"file\"\n[zenoh]\nlisten = [\"tcp/0.0.0.0:1\"]\n",
        )
        .unwrap();
        let args = ConfigArgs {
            config: Some(path),
            building: Some("flag".into()),
            no_metrics: true,
            ..ConfigArgs::default()
        };
        let c = args.load().unwrap();
        assert_eq!(c.building.as_str(), "flag");
        assert_eq!(c.zenoh.listen, ["tcp/0.0.0.0:1"]);
        assert_eq!(c.metrics_listen, None);
        std::fs::remove_dir_all(dir).unwrap();
    }
}
