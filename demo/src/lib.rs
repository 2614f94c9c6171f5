//! The demo building: a gateway, simulated sensor nodes and a live summary on one machine
//! (`triax-demo`, the README's quick start).
//!
//! It starts the gateway on a loopback port with a temporary store, a fleet of simulated sensor
//! nodes and a monitor, all real Zenoh sessions:
//!
//! - each node has a known true sensitivity `S` and offset `q` and measures a known motion:
//!   gravity seen through a slowly drifting tilt, building sway at 1–5 Hz, and white output
//!   noise, sampled at 100 Hz and published in batches of 50;
//! - the calibration records loaded into the store are the lab's estimates of `S` and `q`:
//!   the truth plus an error drawn from the covariance the record states, so the stated
//!   uncertainty is honest;
//! - one inclinometer runs in split mode with a tilt stream, and its true sensitivity differs
//!   between quasi-static and vibration use, as the reference paper found; its offsets and
//!   gains also drift with temperature, which swings ±10 °C through a day compressed into
//!   [`DAY_S`] seconds, and its record carries the lab's temperature model: the summary shows
//!   its tilt error with the model and without it;
//! - one node loses a batch now and then (gaps), one sends a malformed payload now and then,
//!   and one has no calibration at all (flagged `uncalibrated`);
//! - the monitor subscribes to the corrected and tilt streams, compares every sample with the
//!   truth at its timestamp and prints, per sensor, the corrected value, its uncertainty, the
//!   error against the truth and the share of samples within the k = 2 interval.

use std::collections::BTreeMap;
use std::f64::consts::PI;
use std::io::IsTerminal;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use rand_distr::StandardNormal;
use triax_calibration_store::Store;
use triax_protocol::batch::{flags, BatchHeader, CorrectedBatch, Mode, RawBatch};
use triax_protocol::keys::{self, Stream};
use triax_protocol::messages::{GatewayStatus, TiltSample};
use triax_protocol::record::{sample, CalibrationRecord, TemperatureModel};
use triax_protocol::{from_json, BuildingId, Key, SensorId};

use triax_gateway::clock::now_ns;
use triax_gateway::{Config, CorrectionMode, Gateway, GatewayError, SensorSettings};

/// Standard gravity, m/s².
const G_MPS2: f64 = 9.806_65;
/// Sample rate of the simulated nodes.
pub const SAMPLE_RATE_HZ: f64 = 100.0;
/// Samples per batch.
pub const BATCH_SAMPLES: usize = 50;
/// Output noise of the simulated sensors, in output units (V).
const OUTPUT_NOISE: f64 = 0.002;
/// A day of the demo, seconds: the thermal inclinometer's temperature swings ±10 °C around
/// 21 °C over it.
pub const DAY_S: f64 = 600.0;
/// Mean and swing of the thermal inclinometer's day, °C.
const DAY_MEAN_C: f64 = 21.0;
const DAY_SWING_C: f64 = 10.0;

/// How a simulated sensor drifts with temperature, around [`DAY_MEAN_C`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ThermalDrift {
    /// m/s² per °C.
    pub offset_mps2_per_c: [f64; 3],
    /// Relative gain change per °C, per output channel.
    pub gain_per_c: [f64; 3],
}

/// Demo options.
#[derive(Debug, Clone)]
pub struct DemoOptions {
    /// Calibrated sensor nodes besides the inclinometer and the uncalibrated one.
    pub sensors: usize,
    /// Stop after this long; none: until shutdown.
    pub duration: Option<Duration>,
    /// Time between summaries.
    pub refresh: Duration,
    pub seed: u64,
    /// Zenoh endpoint the demo's gateway listens on (loopback), so that another program of the
    /// same process can join; none: a free port.
    pub endpoint: Option<String>,
    /// A line the live summary shows under its title (the console's address).
    pub banner: Option<String>,
}

impl Default for DemoOptions {
    fn default() -> Self {
        DemoOptions {
            sensors: 4,
            duration: None,
            refresh: Duration::from_secs(1),
            seed: 2015,
            endpoint: None,
            banner: None,
        }
    }
}

/// Why the demo failed.
#[derive(Debug, thiserror::Error)]
pub enum DemoError {
    #[error(transparent)]
    Gateway(#[from] GatewayError),
    #[error("demo store: {0}")]
    Store(String),
    #[error("demo zenoh session: {0}")]
    Zenoh(String),
    #[error("demo self-check failed: {0}")]
    Check(String),
}

/// One simulated sensor node: the truth, and what the lab certified.
#[derive(Debug, Clone)]
pub struct SimSensor {
    pub id: SensorId,
    /// True sensitivity for quasi-static signals (gravity, tilt), V per m/s².
    pub s_static: [[f64; 3]; 3],
    /// True sensitivity for vibration.
    pub s_dynamic: [[f64; 3]; 3],
    pub q_mps2: [f64; 3],
    /// Mean tilt, radians (roll, pitch).
    pub tilt0_rad: [f64; 2],
    /// Sway: per horizontal axis, (frequency Hz, amplitude m/s², phase rad).
    pub sway: [(f64, f64, f64); 3],
    pub record: Option<CalibrationRecord>,
    pub settings: SensorSettings,
    /// Publish every n-th batch as a malformed payload (0: never).
    pub malformed_every: u64,
    /// Skip every n-th batch (0: never).
    pub lose_every: u64,
    /// Drift with temperature; none: the sensor is at 21 °C all day.
    pub thermal: Option<ThermalDrift>,
}

impl SimSensor {
    /// True roll and pitch at `t_s` seconds: the mean tilt plus a slow drift.
    pub fn tilt_at(&self, t_s: f64) -> [f64; 2] {
        let drift = 0.05f64.to_radians() * (2.0 * PI * t_s / 120.0).sin();
        [self.tilt0_rad[0] + drift, self.tilt0_rad[1] - 0.5 * drift]
    }

    /// The quasi-static part of the true specific force (gravity through the tilt).
    fn static_part(&self, t_s: f64) -> [f64; 3] {
        let [roll, pitch] = self.tilt_at(t_s);
        [
            G_MPS2 * pitch.sin(),
            G_MPS2 * pitch.cos() * roll.sin(),
            G_MPS2 * pitch.cos() * roll.cos(),
        ]
    }

    fn sway_part(&self, t_s: f64) -> [f64; 3] {
        self.sway
            .map(|(f, a, phi)| a * (2.0 * PI * f * t_s + phi).sin())
    }

    /// True specific force at `t_s`, m/s².
    pub fn truth_at(&self, t_s: f64) -> [f64; 3] {
        let s = self.static_part(t_s);
        let w = self.sway_part(t_s);
        [s[0] + w[0], s[1] + w[1], s[2] + w[2]]
    }

    /// The node's batch number `sequence`, the first sent at `t0_ns`, with output noise.
    pub fn batch(&self, sequence: u64, t0_ns: i64, rng: &mut StdRng) -> RawBatch {
        let period_s = BATCH_SAMPLES as f64 / SAMPLE_RATE_HZ;
        let t_first = sequence as f64 * period_s;
        let samples = (0..BATCH_SAMPLES)
            .map(|i| {
                let v = self.outputs_at(t_first + i as f64 / SAMPLE_RATE_HZ);
                v.map(|x| (x + OUTPUT_NOISE * rng.sample::<f64, _>(StandardNormal)) as f32)
            })
            .collect();
        RawBatch {
            header: BatchHeader {
                sensor_id: self.id.clone(),
                sequence,
                timestamp_ns: t0_ns + (t_first * 1e9) as i64,
                sample_rate_hz: SAMPLE_RATE_HZ,
            },
            temperature_c: Some(self.temperature_at(t_first) as f32),
            samples,
        }
    }

    /// The sensor's temperature at `t_s`, °C.
    pub fn temperature_at(&self, t_s: f64) -> f64 {
        match self.thermal {
            Some(_) => DAY_MEAN_C + DAY_SWING_C * (2.0 * PI * t_s / DAY_S).sin(),
            None => DAY_MEAN_C,
        }
    }

    /// Noise-free outputs at `t_s`.
    fn outputs_at(&self, t_s: f64) -> [f64; 3] {
        self.outputs_of(self.static_part(t_s), self.sway_part(t_s), t_s)
    }

    /// Noise-free outputs for a quasi-static part `s` and a sway `w` at the temperature of
    /// `t_s`: `diag(1 + c_g·ΔT)·(S_s·(s − q − c_q·ΔT) + S_d·w)`.
    fn outputs_of(&self, s: [f64; 3], w: [f64; 3], t_s: f64) -> [f64; 3] {
        let dt = self.temperature_at(t_s) - DAY_MEAN_C;
        let drift = self.thermal.unwrap_or(ThermalDrift {
            offset_mps2_per_c: [0.0; 3],
            gain_per_c: [0.0; 3],
        });
        let d = [0, 1, 2].map(|k| s[k] - self.q_mps2[k] - drift.offset_mps2_per_c[k] * dt);
        let mut v = [0.0; 3];
        for (i, vi) in v.iter_mut().enumerate() {
            for j in 0..3 {
                *vi += self.s_static[i][j] * d[j] + self.s_dynamic[i][j] * w[j];
            }
            *vi *= 1.0 + drift.gain_per_c[i] * dt;
        }
        v
    }

    /// Roll and pitch, degrees, that the record's static set without its temperature model
    /// would read at `t_s` (noise-free, sway aside): what the temperature model saves.
    pub fn uncompensated_tilt_deg(&self, t_s: f64) -> Option<[f64; 2]> {
        let mut record = self.record.clone()?;
        record.temperature = None;
        let c = triax_calibration::corrector::Corrector::from_record(&record).ok()?;
        let v = self.outputs_of(self.static_part(t_s), [0.0; 3], t_s);
        let [ax, ay, az] = c.set(triax_protocol::record::SetKind::Static).accel(v);
        Some([
            ay.atan2(az).to_degrees(),
            ax.atan2((ay * ay + az * az).sqrt()).to_degrees(),
        ])
    }
}

fn perturbed(rng: &mut StdRng, m: [[f64; 3]; 3], sd: f64) -> [[f64; 3]; 3] {
    m.map(|row| row.map(|x| x + sd * rng.sample::<f64, _>(StandardNormal)))
}

/// A record stating parameter standard deviations `sd_s` (sensitivity) and `sd_q` (offset),
/// whose values are the truth plus errors drawn from them.
fn certify(
    rng: &mut StdRng,
    id: &str,
    truth_static: [[f64; 3]; 3],
    truth_dynamic: [[f64; 3]; 3],
    q: [f64; 3],
) -> CalibrationRecord {
    let (sd_s, sd_q) = (1e-4, 0.004);
    let mut r = sample::record(id, 1);
    r.sensor.output_noise = Some([OUTPUT_NOISE; 3]);
    r.sensor.output_full_scale = Some(4.0);
    for (set, truth) in [
        (&mut r.static_set, truth_static),
        (&mut r.dynamic, truth_dynamic),
    ] {
        set.sensitivity = perturbed(rng, truth, sd_s);
        set.offset = q.map(|x| x + sd_q * rng.sample::<f64, _>(StandardNormal));
        let mut cov = [[0.0; 12]; 12];
        for (i, row) in cov.iter_mut().enumerate() {
            row[i] = if i < 9 { sd_s * sd_s } else { sd_q * sd_q };
        }
        set.covariance = Some(Box::new(cov));
        set.uncertainty_mps2 = [0.003; 3];
        set.domain.amplitude_max_mps2 = 20.0;
    }
    r.static_set.domain.frequency_max_hz = 1.0;
    r
}

/// The lab's temperature model of a drifting sensor: the truth plus errors drawn from the
/// covariance it states, calibrated over 5–37 °C.
fn certify_temperature(rng: &mut StdRng, drift: ThermalDrift) -> TemperatureModel {
    let (sd_q, sd_g) = (1e-4, 5e-6);
    let mut covariance = [[0.0; 6]; 6];
    for (i, row) in covariance.iter_mut().enumerate() {
        row[i] = if i < 3 { sd_q * sd_q } else { sd_g * sd_g };
    }
    TemperatureModel {
        reference_c: DAY_MEAN_C,
        range_c: [5.0, 37.0],
        offset_mps2_per_c: drift
            .offset_mps2_per_c
            .map(|c| c + sd_q * rng.sample::<f64, _>(StandardNormal)),
        gain_per_c: Some(
            drift
                .gain_per_c
                .map(|c| c + sd_g * rng.sample::<f64, _>(StandardNormal)),
        ),
        covariance,
        covariance_dof: Some(22.0),
    }
}

/// Builds the fleet: `n` calibrated accelerometers, one inclinometer, one uncalibrated node.
pub fn fleet(n: usize, seed: u64) -> Vec<SimSensor> {
    let mut rng = StdRng::seed_from_u64(seed);
    let mut out = Vec::new();
    let sensor = |rng: &mut StdRng, id: String, settings: SensorSettings, calibrated: bool| {
        let gain = 0.1 * (1.0 + 0.03 * rng.gen_range(-1.0..1.0));
        let mut s = [[0.0; 3]; 3];
        for (i, row) in s.iter_mut().enumerate() {
            for (j, x) in row.iter_mut().enumerate() {
                *x = if i == j {
                    gain * (1.0 + 0.02 * rng.gen_range(-1.0..1.0))
                } else {
                    0.003 * rng.gen_range(-1.0..1.0)
                };
            }
        }
        // The split-mode inclinometer's vibration sensitivity is 1.5 % higher on every axis.
        let s_dyn = if settings.mode == CorrectionMode::Split {
            s.map(|row| row.map(|x| x * 1.015))
        } else {
            s
        };
        let q = [0, 1, 2].map(|_| 0.15 * rng.gen_range(-1.0..1.0));
        let mut sway = [(0.0, 0.0, 0.0); 3];
        for (k, w) in sway.iter_mut().enumerate() {
            let amp = if k == 2 {
                0.02
            } else {
                rng.gen_range(0.05..0.3)
            };
            *w = (rng.gen_range(1.0..5.0), amp, rng.gen_range(0.0..2.0 * PI));
        }
        let record = calibrated.then(|| certify(rng, &id, s, s_dyn, q));
        SimSensor {
            // Demo ids are literals of valid characters.
            id: SensorId::new(id).expect("demo sensor id is valid"),
            s_static: s,
            s_dynamic: s_dyn,
            q_mps2: q,
            tilt0_rad: [
                rng.gen_range(-1.0f64..1.0).to_radians(),
                rng.gen_range(-1.0f64..1.0).to_radians(),
            ],
            sway,
            record,
            settings,
            malformed_every: 0,
            lose_every: 0,
            thermal: None,
        }
    };
    for i in 0..n {
        let mode = if i % 3 == 2 {
            CorrectionMode::Static
        } else {
            CorrectionMode::Dynamic
        };
        let settings = SensorSettings {
            mode,
            ..SensorSettings::default()
        };
        out.push(sensor(
            &mut rng,
            format!("acc-{:02}", i + 1),
            settings,
            true,
        ));
    }
    let incl = SensorSettings {
        mode: CorrectionMode::Split,
        tilt: true,
        ..SensorSettings::default()
    };
    let mut inclinometer = sensor(&mut rng, "incl-01".into(), incl, true);
    let drift = ThermalDrift {
        offset_mps2_per_c: [0.004, -0.003, 0.005],
        gain_per_c: [2e-4, -1.5e-4, 3e-4],
    };
    inclinometer.thermal = Some(drift);
    if let Some(r) = inclinometer.record.as_mut() {
        r.temperature = Some(certify_temperature(&mut rng, drift));
    }
    out.push(inclinometer);
    out.push(sensor(
        &mut rng,
        "acc-new".into(),
        SensorSettings::default(),
        false,
    ));
    if let Some(s) = out.first_mut() {
        s.lose_every = 15;
    }
    if n >= 2 {
        out[1].malformed_every = 12;
    }
    out
}

/// Running comparison of one sensor's corrected stream with the truth.
#[derive(Debug, Clone, Default)]
pub struct SensorSummary {
    pub mode: Option<Mode>,
    pub version: u64,
    pub last_accel_mps2: [f32; 3],
    pub last_uncertainty_mps2: [f32; 3],
    pub last_error_mps2: [f64; 3],
    pub flags: u16,
    pub batches: u64,
    /// Calibrated, unflagged-by-value samples compared with the truth (per axis).
    pub compared: u64,
    /// Of those, within the k = 2 interval.
    pub within_k2: u64,
    pub max_abs_error_mps2: f64,
    pub tilt: Option<(TiltSample, [f64; 2])>,
    /// For a sensor that drifts with temperature: its temperature at the last tilt sample
    /// and the (roll, pitch) its record would read there without the temperature model.
    pub tilt_uncompensated: Option<(f64, [f64; 2])>,
}

type Summaries = Arc<Mutex<BTreeMap<String, SensorSummary>>>;

fn lock(s: &Summaries) -> std::sync::MutexGuard<'_, BTreeMap<String, SensorSummary>> {
    // Updates are plain field writes that cannot panic halfway.
    s.lock().unwrap_or_else(|p| p.into_inner())
}

/// What the demo saw, for the final line and for tests.
#[derive(Debug, Clone)]
pub struct DemoReport {
    pub sensors: BTreeMap<String, SensorSummary>,
    pub status: Option<GatewayStatus>,
}

impl DemoReport {
    /// Share of compared samples (all calibrated sensors, all axes) within k = 2.
    pub fn within_k2(&self) -> f64 {
        let (n, w) = self
            .sensors
            .values()
            .fold((0, 0), |(n, w), s| (n + s.compared, w + s.within_k2));
        if n == 0 {
            0.0
        } else {
            w as f64 / n as f64
        }
    }
}

/// Runs the demo until `opts.duration` passes or `shutdown` completes.
pub async fn run(
    base: Config,
    opts: DemoOptions,
    shutdown: impl std::future::Future,
) -> Result<DemoReport, DemoError> {
    let dir = tempfile::tempdir().map_err(|e| DemoError::Store(e.to_string()))?;
    let fleet = Arc::new(fleet(opts.sensors, opts.seed));
    let records: Vec<CalibrationRecord> = fleet.iter().filter_map(|s| s.record.clone()).collect();
    let store_path = dir.path().join("store");
    let sp = store_path.clone();
    tokio::task::spawn_blocking(move || -> Result<(), String> {
        let store = Store::open(&sp).map_err(|e| e.to_string())?;
        for r in &records {
            store
                .put(r)
                .map_err(|e| e.to_string())?
                .map_err(|e| e.to_string())?;
        }
        Ok(())
    })
    .await
    .map_err(|e| DemoError::Store(e.to_string()))?
    .map_err(DemoError::Store)?;

    let endpoint = match &opts.endpoint {
        Some(e) => e.clone(),
        None => {
            let port =
                triax_net::free_loopback_port().map_err(|e| DemoError::Zenoh(e.to_string()))?;
            format!("tcp/127.0.0.1:{port}")
        }
    };
    let mut config = base;
    // A literal of valid characters.
    config.building = BuildingId::new("demo").expect("literal building id is valid");
    config.gateway_name = "triax-gateway-demo".into();
    config.store_path = store_path;
    // The demo makes its own key, in its own folder, as a gateway does at its first start.
    config.provenance.key_file = dir.path().join("triax-gateway-demo.key");
    if let Some(h) = config.history.as_mut() {
        h.path = dir.path().join("history");
    }
    config.zenoh.listen = vec![endpoint.clone()];
    config.zenoh.connect.clear();
    config.zenoh.mode = None;
    config.zenoh.config_file = None;
    config.zenoh.multicast_scouting = Some(false);
    for s in fleet.iter() {
        config.sensors.insert(s.id.clone(), s.settings.clone());
    }
    let building = config.building.clone();
    let gateway = Gateway::start(config).await?;
    let metrics = gateway.metrics_addr();

    let mut zc = zenoh::Config::default();
    let set = |zc: &mut zenoh::Config, k: &str, v: &str| {
        zc.insert_json5(k, v)
            .map_err(|e| DemoError::Zenoh(e.to_string()))
    };
    set(&mut zc, "mode", "\"peer\"")?;
    set(&mut zc, "connect/endpoints", &format!("[\"{endpoint}\"]"))?;
    set(&mut zc, "scouting/multicast/enabled", "false")?;
    set(&mut zc, "listen/endpoints", "[]")?;
    let session = zenoh::open(zc)
        .await
        .map_err(|e| DemoError::Zenoh(e.to_string()))?;

    let summaries: Summaries = Arc::default();
    let by_id: Arc<BTreeMap<String, SimSensor>> = Arc::new(
        fleet
            .iter()
            .map(|s| (s.id.to_string(), s.clone()))
            .collect(),
    );
    let t0_ns = now_ns();
    let sums = summaries.clone();
    let truth = by_id.clone();
    let _corrected = session
        .declare_subscriber(keys::all_sensors(&building, Stream::Corrected))
        .callback(move |sample| {
            let bytes = sample.payload().to_bytes();
            if let Ok(b) = CorrectedBatch::decode(&bytes) {
                if let Some(sim) = truth.get(b.header.sensor_id.as_str()) {
                    observe(&sums, sim, &b, t0_ns);
                }
            }
        })
        .await
        .map_err(|e| DemoError::Zenoh(e.to_string()))?;
    let sums = summaries.clone();
    let truth = by_id.clone();
    let _tilt = session
        .declare_subscriber(keys::all_sensors(&building, Stream::Tilt))
        .callback(move |sample| {
            if let Ok(t) = from_json::<TiltSample>(&sample.payload().to_bytes()) {
                if let Some(sim) = truth.get(t.sensor_id.as_str()) {
                    let t_s = (t.timestamp_ns - t0_ns) as f64 * 1e-9;
                    let [r, p] = sim.tilt_at(t_s);
                    let uncompensated = sim
                        .thermal
                        .and_then(|_| sim.uncompensated_tilt_deg(t_s))
                        .map(|angles| (sim.temperature_at(t_s), angles));
                    let mut m = lock(&sums);
                    let e = m.entry(t.sensor_id.to_string()).or_default();
                    e.tilt = Some((t, [r.to_degrees(), p.to_degrees()]));
                    e.tilt_uncompensated = uncompensated;
                }
            }
        })
        .await
        .map_err(|e| DemoError::Zenoh(e.to_string()))?;

    // Give the subscriptions a moment to propagate before the nodes start.
    tokio::time::sleep(Duration::from_millis(300)).await;
    let (stop_nodes, nodes_stop) = triax_gateway::shutdown::channel();
    let mut nodes = Vec::new();
    for (i, sim) in fleet.iter().enumerate() {
        nodes.push(tokio::spawn(node(
            session.clone(),
            building.clone(),
            sim.clone(),
            t0_ns,
            opts.seed + i as u64 + 1,
            nodes_stop.clone(),
        )));
    }

    let tty = std::io::stdout().is_terminal();
    let started = std::time::Instant::now();
    let mut tick = tokio::time::interval(opts.refresh);
    tick.tick().await;
    let deadline = async {
        match opts.duration {
            Some(d) => tokio::time::sleep(d).await,
            None => std::future::pending().await,
        }
    };
    tokio::pin!(deadline);
    tokio::pin!(shutdown);
    let mut status = None;
    loop {
        tokio::select! {
            _ = &mut deadline => break,
            _ = &mut shutdown => break,
            _ = tick.tick() => {
                status = query_status(&session, &building).await.or(status);
                let text = render(&lock(&summaries), status.as_ref(), started.elapsed(), metrics, &by_id, opts.banner.as_deref());
                if tty {
                    print!("\x1b[2J\x1b[H{text}");
                } else {
                    println!("{text}");
                }
            }
        }
    }
    stop_nodes.fire();
    for n in nodes {
        let _ = n.await;
    }
    status = query_status(&session, &building).await.or(status);
    let report = DemoReport {
        sensors: lock(&summaries).clone(),
        status,
    };
    println!(
        "{}",
        render(
            &report.sensors,
            report.status.as_ref(),
            started.elapsed(),
            metrics,
            &by_id,
            opts.banner.as_deref()
        )
    );
    let _ = session.close().await;
    gateway.run_until(async {}).await?;
    drop(dir);
    let share = report.within_k2();
    println!(
        "demo: {:.1} % of calibrated samples within the k = 2 interval of the truth",
        100.0 * share
    );
    if report.sensors.values().map(|s| s.compared).sum::<u64>() > 0 && share < 0.9 {
        return Err(DemoError::Check(format!(
            "only {:.1} % of samples within k = 2",
            100.0 * share
        )));
    }
    Ok(report)
}

async fn query_status(session: &zenoh::Session, building: &BuildingId) -> Option<GatewayStatus> {
    let replies = session
        .get(Key::Status(building.clone()).to_string())
        .timeout(Duration::from_millis(500))
        .await
        .ok()?;
    let reply = replies.recv_async().await.ok()?;
    let sample = reply.result().ok()?;
    from_json(&sample.payload().to_bytes()).ok()
}

fn observe(sums: &Summaries, sim: &SimSensor, b: &CorrectedBatch, t0_ns: i64) {
    let mut m = lock(sums);
    let e = m.entry(sim.id.to_string()).or_default();
    e.mode = Some(b.info.mode);
    e.version = b.info.calibration_version;
    e.flags = b.batch_flags;
    e.batches += 1;
    let dt = 1.0 / b.header.sample_rate_hz;
    let t_first = (b.header.timestamp_ns - t0_ns) as f64 * 1e-9;
    for (i, s) in b.samples.iter().enumerate() {
        let truth = sim.truth_at(t_first + i as f64 * dt);
        let err = [0, 1, 2].map(|k| f64::from(s.accel_mps2[k]) - truth[k]);
        if b.info.mode != Mode::None
            && s.flags & (flags::NON_FINITE_INPUT | flags::UNCALIBRATED) == 0
        {
            for (err_k, u_k) in err.iter().zip(s.uncertainty_mps2) {
                e.compared += 1;
                if err_k.abs() <= 2.0 * f64::from(u_k) {
                    e.within_k2 += 1;
                }
                e.max_abs_error_mps2 = e.max_abs_error_mps2.max(err_k.abs());
            }
        }
        e.last_accel_mps2 = s.accel_mps2;
        e.last_uncertainty_mps2 = s.uncertainty_mps2;
        e.last_error_mps2 = err;
    }
}

fn render(
    sums: &BTreeMap<String, SensorSummary>,
    status: Option<&GatewayStatus>,
    elapsed: Duration,
    metrics: Option<std::net::SocketAddr>,
    fleet: &BTreeMap<String, SimSensor>,
    banner: Option<&str>,
) -> String {
    use std::fmt::Write as _;
    let mut o = String::new();
    let _ = writeln!(
        o,
        "Triax demo: building `demo`, {} sensor nodes at {SAMPLE_RATE_HZ} Hz, t = {:.0} s{}",
        fleet.len(),
        elapsed.as_secs_f64(),
        metrics.map_or(String::new(), |a| format!(", metrics http://{a}/metrics"))
    );
    if let Some(b) = banner {
        let _ = writeln!(o, "{b}");
    }
    let _ = writeln!(
        o,
        "{:<8} {:<7} {:>3}  {:>24}  {:>8}  {:>24}  {:>7}  {:>6}  flags",
        "sensor",
        "mode",
        "ver",
        "a (m/s²) x y z",
        "u k=1",
        "error vs truth x y z",
        "|e|max",
        "in k=2"
    );
    for (id, s) in sums {
        let mode = match s.mode {
            Some(Mode::Static) => "static",
            Some(Mode::Dynamic) => "dynamic",
            Some(Mode::Split) => "split",
            Some(Mode::None) | None => "none",
        };
        let a = s.last_accel_mps2;
        let u = s.last_uncertainty_mps2;
        // f32::max skips NaN, and an uncalibrated sensor's uncertainty is all NaN.
        let umax = if u.iter().any(|x| x.is_nan()) {
            f32::NAN
        } else {
            u.iter().fold(0f32, |m, x| m.max(*x))
        };
        let (err, emax, within) = if s.compared > 0 {
            let e = s.last_error_mps2;
            (
                format!("{:+8.4}{:+8.4}{:+8.4}", e[0], e[1], e[2]),
                format!("{:7.4}", s.max_abs_error_mps2),
                format!("{:5.1}%", 100.0 * s.within_k2 as f64 / s.compared as f64),
            )
        } else {
            ("n/a".into(), "n/a".into(), "n/a".into())
        };
        let names = flags::names(s.flags);
        let _ = writeln!(
            o,
            "{id:<8} {mode:<7} {:>3}  {:+8.3}{:+8.3}{:+8.3}  {:>8}  {err:>24}  {emax:>7}  {within:>6}  {}",
            if s.version == 0 { "-".to_string() } else { s.version.to_string() },
            a[0],
            a[1],
            a[2],
            if umax.is_nan() { "NaN".to_string() } else { format!("{umax:.4}") },
            if names.is_empty() { "-".to_string() } else { names.join(",") },
        );
        if let Some((t, [r, p])) = &s.tilt {
            let _ = writeln!(
                o,
                "{:<8} tilt: roll {:+.3}° ± {:.3}° (true {:+.3}°), pitch {:+.3}° ± {:.3}° (true {:+.3}°), u at k = 1, intervals at k = {:.2}",
                "", t.roll_deg, t.roll_uncertainty_deg, r, t.pitch_deg, t.pitch_uncertainty_deg, p, t.coverage_factor
            );
            if let Some((temperature_c, [ur, up])) = &s.tilt_uncompensated {
                let _ = writeln!(
                    o,
                    "{:<8} at {temperature_c:.1} °C: tilt error roll {:+.3}°, pitch {:+.3}° with the record's temperature model; {:+.3}°, {:+.3}° without it",
                    "", t.roll_deg - r, t.pitch_deg - p, ur - r, up - p
                );
            }
        }
    }
    if let Some(st) = status {
        let gaps: u64 = st.sensors.iter().map(|s| s.gaps).sum();
        let missing: u64 = st.sensors.iter().map(|s| s.missing_batches).sum();
        let samples: u64 = st.sensors.iter().map(|s| s.samples).sum();
        let _ = writeln!(
            o,
            "gateway status: {samples} samples, {gaps} gaps ({missing} batches lost upstream), {} malformed payloads skipped, {} dropped",
            st.malformed, st.dropped
        );
    }
    o
}

/// One simulated node: publishes a batch every `BATCH_SAMPLES / SAMPLE_RATE_HZ` seconds.
async fn node(
    session: zenoh::Session,
    building: BuildingId,
    sim: SimSensor,
    t0_ns: i64,
    seed: u64,
    mut stop: triax_gateway::shutdown::Shutdown,
) {
    let mut rng = StdRng::seed_from_u64(seed);
    let key = Key::Raw(building, sim.id.clone()).to_string();
    let Ok(publisher) = session.declare_publisher(key).await else {
        tracing::error!(sensor = %sim.id, "demo node cannot declare its publisher");
        return;
    };
    let period = Duration::from_secs_f64(BATCH_SAMPLES as f64 / SAMPLE_RATE_HZ);
    let mut tick = tokio::time::interval(period);
    let mut sequence = 0u64;
    loop {
        tokio::select! {
            _ = stop.recv() => return,
            _ = tick.tick() => {}
        }
        let batch = sim.batch(sequence, t0_ns, &mut rng);
        sequence += 1;
        if sim.lose_every > 0 && sequence % sim.lose_every == 0 {
            continue;
        }
        let payload = if sim.malformed_every > 0 && sequence % sim.malformed_every == 0 {
            // A truncated batch, as a flaky radio link would deliver it.
            let mut b = batch.encode();
            b.truncate(b.len() / 2);
            b
        } else {
            batch.encode()
        };
        if let Err(e) = publisher.put(payload).await {
            tracing::warn!(sensor = %sim.id, cause = %e, "demo node publish failed");
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fleet_records_load_and_match_the_truth_closely() {
        let f = fleet(3, 1);
        assert_eq!(f.len(), 5);
        for s in &f {
            if let Some(r) = &s.record {
                let c = triax_calibration::corrector::Corrector::from_record(r).unwrap();
                let v = s.outputs_at(0.0);
                let a = c.set(triax_protocol::record::SetKind::Static).correct(v);
                let t = s.static_part(0.0);
                let sw = s.sway_part(0.0);
                for k in 0..3 {
                    let truth = if s.settings.mode == CorrectionMode::Split {
                        t[k] + sw[k] * 1.015
                    } else {
                        t[k] + sw[k]
                    };
                    assert!((a.accel_mps2[k] - truth).abs() < 0.2, "{}", s.id);
                }
            }
        }
        assert!(f.iter().any(|s| s.record.is_none()));
    }

    /// The thermal inclinometer through a whole simulated day (±10 °C), sample by sample
    /// through the gateway's kernel: every second's tilt, with the record's temperature model,
    /// lies within its stated 95 % interval of the truth; the same record without the model
    /// misses it most of the day.
    #[test]
    fn tilt_holds_its_interval_through_a_day_night_cycle() {
        use triax_calibration::corrector::Corrector;
        use triax_gateway::sample_path::{Scratch, SensorKernel};
        use triax_protocol::RawBatchView;

        let f = fleet(4, 2015);
        let sim = f.iter().find(|s| s.thermal.is_some()).unwrap();
        let record = sim.record.clone().unwrap();
        let with = Corrector::from_record(&record).unwrap();
        let mut bare = record;
        bare.temperature = None;
        let without = Corrector::from_record(&bare).unwrap();
        let t0_ns = 1_800_000_000_000_000_000i64;
        let mut rng = StdRng::seed_from_u64(7);
        let mut kernels =
            [with.clone(), without.clone()].map(|c| (c, SensorKernel::new(sim.settings.clone())));
        let mut scratch = Scratch::default();
        let mut out = Vec::new();
        let batches = (DAY_S * SAMPLE_RATE_HZ) as u64 / BATCH_SAMPLES as u64;
        let mut inside = [0usize; 2];
        let mut total = 0usize;
        let mut hottest = f64::NEG_INFINITY;
        for sequence in 0..batches {
            let bytes = sim.batch(sequence, t0_ns, &mut rng).encode();
            let view = RawBatchView::parse(&bytes).unwrap();
            for (c, kernel) in kernels.iter_mut() {
                out.clear();
                kernel.correct_batch(&view, Some(c), 0, &mut scratch, &mut out);
            }
            let state = *kernels[0].1.tilt_state();
            if sequence % 2 == 1 && state.ready {
                let t_s = (state.timestamp_ns - t0_ns) as f64 * 1e-9;
                hottest = hottest.max(sim.temperature_at(t_s));
                let truth = sim.tilt_at(t_s).map(f64::to_degrees);
                total += 2;
                for (i, (c, kernel)) in kernels.iter().enumerate() {
                    let est = kernel.tilt_state().estimate(c);
                    let k = est.coverage_factor;
                    inside[i] += usize::from(
                        (est.roll_deg - truth[0]).abs() <= k * est.roll_uncertainty_deg,
                    );
                    inside[i] += usize::from(
                        (est.pitch_deg - truth[1]).abs() <= k * est.pitch_uncertainty_deg,
                    );
                }
            }
        }
        assert!(hottest > 30.9, "the day reached {hottest} °C");
        let share = inside.map(|n| n as f64 / total as f64);
        println!(
            "{total} tilt angles over a day: {:.1} % within k·u with the model, {:.1} % without",
            100.0 * share[0],
            100.0 * share[1]
        );
        assert!(
            share[0] >= 0.95,
            "with the model: {:.1} %",
            100.0 * share[0]
        );
        assert!(
            share[1] < 0.5,
            "without the model: {:.1} %",
            100.0 * share[1]
        );
    }
}
