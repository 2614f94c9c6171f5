//! A building with known modes: an n-storey shear frame swaying in the building's `x` and `y`,
//! driven by broadband forces on every floor, seen by sensors with their own calibration
//! errors, clock offsets and noise.
//!
//! **The frame.** Floor `j` (1…n) has mass `m_j`; storey `j` (between floors `j−1` and `j`,
//! floor 0 the ground) has stiffness `k_j` in `x` and `k_j · stiffness_ratio_y` in `y`, so the
//! two directions have close modes (a ratio of 1.03 puts them 1.5 % apart). The modes solve
//! the generalised eigenproblem `K·φ = ω²·M·φ` (through `M^(−½)·K·M^(−½)`, symmetric), with
//! mass-normalised shapes; damping is modal, `ζ` per mode. Temperature scales every stiffness
//! by `(1 + β·(T − T_ref))²`, so every frequency by `1 + β·(T − T_ref)` with
//! `β = frequency_change_per_c`; damage lowers one storey's stiffness in one direction.
//!
//! **The response, exactly.** Each mode is a second-order system in its modal coordinate,
//! `η̈ + 2ζω·η̇ + ω²·η = φᵀ·f`. The floor forces `f` are white and held over each sample
//! interval (zero-order hold), so the discrete system `x(t+τ) = e^(A·τ)·x(t) + A⁻¹(e^(A·τ) − I)·B·u`
//! with the matrix exponential is exact, not an integration scheme, and the acceleration
//! `η̈ = φᵀ·f − 2ζω·η̇ − ω²·η` is evaluated at any instant within the interval, which is how a
//! node's clock offset is rendered: its samples are the motion at `t + δt`, not `t`. The
//! modes' truth is the same eigen-decomposition the response is computed from.
//!
//! **The sensors.** A sensor on floor `j` mounted with rotation `R` reads, in its own axes,
//! `(I + E)·Rᵀ·a(t + δt) + noise`, where `a` is the floor's acceleration in the building frame,
//! `E` its residual calibration error (diagonal: relative gain errors; off-diagonal:
//! cross-axis terms), drawn once per sensor from the chain's stated standard uncertainties,
//! `δt` its clock offset, drawn from the stated time-stamp uncertainty, and the noise white.
//!
//! Pure and seeded: the same building and seed give the same samples.

use nalgebra::{DMatrix, Matrix2, Matrix3, SymmetricEigen, Vector2};
use rand::rngs::SmallRng;
use rand::{Rng, SeedableRng};
use rand_distr::StandardNormal;
use serde::{Deserialize, Serialize};

use crate::model::{rotation_about_z, BuildingModel, Direction, SensorPlacement};
use crate::window::{ChainUncertainty, ChannelId, SensorSeries, Window};

/// A shear frame's properties.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ShearFrame {
    /// Mass of floors 1…n, kg.
    pub floor_mass_kg: Vec<f64>,
    /// Stiffness of storeys 1…n in `x`, N/m.
    pub storey_stiffness_x_n_per_m: Vec<f64>,
    /// `y` stiffness over `x` stiffness, every storey.
    pub stiffness_ratio_y: f64,
    /// Modal damping ratio of mode 1…n, the same in both directions.
    pub damping_ratio: Vec<f64>,
    /// Relative change of every frequency per °C.
    pub frequency_change_per_c: f64,
    pub reference_temperature_c: f64,
    /// Storeys that lost stiffness: (direction, storey 1…n, fraction lost).
    pub damage: Vec<(Direction, usize, f64)>,
}

/// A mode of the frame.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TrueMode {
    pub direction: Direction,
    /// 1 for the fundamental of its direction.
    pub number: usize,
    pub frequency_hz: f64,
    pub damping_ratio: f64,
    /// Mass-normalised displacement of floors 1…n.
    pub floor_shape: Vec<f64>,
}

impl ShearFrame {
    /// `storeys` equal floors and storeys, stiffness set so that the `x` fundamental is
    /// `fundamental_hz` (for a uniform shear frame, `ω₁ = 2·√(k/m)·sin(π/(2(2n+1)))`).
    pub fn uniform(
        storeys: usize,
        fundamental_hz: f64,
        stiffness_ratio_y: f64,
        damping_ratio: f64,
    ) -> ShearFrame {
        let mass_kg = 5.0e5;
        let s = (std::f64::consts::PI / (2.0 * (2 * storeys + 1) as f64)).sin();
        let omega = 2.0 * std::f64::consts::PI * fundamental_hz;
        let k = mass_kg * (omega / (2.0 * s)).powi(2);
        ShearFrame {
            floor_mass_kg: vec![mass_kg; storeys],
            storey_stiffness_x_n_per_m: vec![k; storeys],
            stiffness_ratio_y,
            damping_ratio: vec![damping_ratio; storeys],
            frequency_change_per_c: 0.0,
            reference_temperature_c: 20.0,
            damage: Vec::new(),
        }
    }

    pub fn storeys(&self) -> usize {
        self.floor_mass_kg.len()
    }

    /// The stiffness matrix of one direction at a temperature.
    pub fn stiffness(&self, direction: Direction, temperature_c: f64) -> DMatrix<f64> {
        let n = self.storeys();
        let thermal = (1.0
            + self.frequency_change_per_c * (temperature_c - self.reference_temperature_c))
            .powi(2);
        let ratio = if direction == Direction::Y {
            self.stiffness_ratio_y
        } else {
            1.0
        };
        let storey: Vec<f64> = (0..n)
            .map(|j| {
                let loss: f64 = self
                    .damage
                    .iter()
                    .filter(|(d, s, _)| *d == direction && *s == j + 1)
                    .map(|(_, _, f)| f)
                    .sum();
                self.storey_stiffness_x_n_per_m[j] * ratio * thermal * (1.0 - loss)
            })
            .collect();
        let mut k = DMatrix::zeros(n, n);
        for j in 0..n {
            k[(j, j)] += storey[j];
            if j + 1 < n {
                k[(j, j)] += storey[j + 1];
                k[(j, j + 1)] -= storey[j + 1];
                k[(j + 1, j)] -= storey[j + 1];
            }
        }
        k
    }

    /// The modes of one direction, by increasing frequency.
    pub fn direction_modes(&self, direction: Direction, temperature_c: f64) -> Vec<TrueMode> {
        let n = self.storeys();
        let k = self.stiffness(direction, temperature_c);
        let inv_sqrt_m: Vec<f64> = self.floor_mass_kg.iter().map(|m| 1.0 / m.sqrt()).collect();
        let l = DMatrix::from_fn(n, n, |i, j| inv_sqrt_m[i] * k[(i, j)] * inv_sqrt_m[j]);
        let eigen = SymmetricEigen::new(l);
        let mut order: Vec<usize> = (0..n).collect();
        order.sort_by(|&a, &b| eigen.eigenvalues[a].total_cmp(&eigen.eigenvalues[b]));
        order
            .iter()
            .enumerate()
            .map(|(number, &j)| {
                let omega = eigen.eigenvalues[j].max(0.0).sqrt();
                let mut shape: Vec<f64> = (0..n)
                    .map(|i| eigen.eigenvectors[(i, j)] * inv_sqrt_m[i])
                    .collect();
                // Sign convention: the top floor moves positively.
                if shape[n - 1] < 0.0 {
                    shape.iter_mut().for_each(|v| *v = -*v);
                }
                TrueMode {
                    direction,
                    number: number + 1,
                    frequency_hz: omega / (2.0 * std::f64::consts::PI),
                    damping_ratio: self.damping_ratio[number],
                    floor_shape: shape,
                }
            })
            .collect()
    }

    /// Every mode of both directions, by increasing frequency.
    pub fn modes(&self, temperature_c: f64) -> Vec<TrueMode> {
        let mut all = self.direction_modes(Direction::X, temperature_c);
        all.extend(self.direction_modes(Direction::Y, temperature_c));
        all.sort_by(|a, b| a.frequency_hz.total_cmp(&b.frequency_hz));
        all
    }
}

/// A sensor's true residual errors in the simulation.
#[derive(Debug, Clone, PartialEq)]
pub struct SensorErrors {
    /// `E`: relative gain errors on the diagonal, cross-axis terms off it.
    pub error: Matrix3<f64>,
    /// The node's clock offset: its sample stamped `t` is the motion at `t + time_offset_s`.
    pub time_offset_s: f64,
}

/// How the building is sensed.
#[derive(Debug, Clone, PartialEq)]
pub struct SimConfig {
    pub sample_rate_hz: f64,
    /// Standard deviation of each floor's white force in each direction, held per sample, N.
    pub force_std_n: f64,
    /// White noise of each sensor axis, m/s².
    pub noise_std_mps2: f64,
    /// Stated chain uncertainty of every sensor; the true errors are drawn from it.
    pub chain: ChainUncertainty,
}

impl Default for SimConfig {
    fn default() -> Self {
        SimConfig {
            sample_rate_hz: 100.0,
            force_std_n: 2.0e4,
            noise_std_mps2: 0.002,
            chain: ChainUncertainty {
                gain_relative_u: [0.003; 3],
                cross_axis_u: 0.002,
                dof: 50.0,
                timestamp_u_s: 0.001,
            },
        }
    }
}

/// A simulated building: frame, sensors and their true errors.
#[derive(Debug, Clone)]
pub struct SimBuilding {
    pub frame: ShearFrame,
    pub model: BuildingModel,
    pub errors: Vec<SensorErrors>,
    pub config: SimConfig,
}

/// A five-storey building, fundamental 1 Hz in `x` and 1.5 % higher in `y` (3 % stiffer), 2 %
/// damping, six sensors on floors 1 to 5 (two on the roof), each turned in plan by its own
/// angle: twelve horizontal channels.
pub fn five_storey_model() -> (ShearFrame, BuildingModel) {
    let frame = ShearFrame::uniform(5, 1.0, 1.03, 0.02);
    let angles_deg: [f64; 6] = [0.0, 90.0, 30.0, -45.0, 180.0, 10.0];
    let floors = [1u32, 2, 3, 4, 5, 5];
    let sensors = floors
        .iter()
        .zip(angles_deg)
        .enumerate()
        .map(|(i, (&floor, angle))| SensorPlacement {
            sensor_id: format!("s{}", i + 1),
            floor,
            height_m: 3.5 * f64::from(floor),
            position_m: [2.0 * i as f64, 1.0],
            mounting: rotation_about_z(angle.to_radians()),
        })
        .collect();
    // The sensors' ids are distinct and the mountings rotations: the model is valid.
    let model = BuildingModel::new("sim", sensors).expect("the simulated model is valid");
    (frame, model)
}

impl SimBuilding {
    /// A building with its sensors' true errors drawn from `config.chain` with `seed`.
    pub fn new(
        frame: ShearFrame,
        model: BuildingModel,
        config: SimConfig,
        seed: u64,
    ) -> SimBuilding {
        let mut rng = SmallRng::seed_from_u64(seed);
        let chain = config.chain;
        let errors = model
            .sensors
            .iter()
            .map(|_| {
                let mut e = Matrix3::zeros();
                for i in 0..3 {
                    for j in 0..3 {
                        let z: f64 = rng.sample(StandardNormal);
                        e[(i, j)] = if i == j {
                            z * chain.gain_relative_u[i]
                        } else {
                            z * chain.cross_axis_u
                        };
                    }
                }
                let z: f64 = rng.sample(StandardNormal);
                SensorErrors {
                    error: e,
                    time_offset_s: z * chain.timestamp_u_s,
                }
            })
            .collect();
        SimBuilding {
            frame,
            model,
            errors,
            config,
        }
    }

    /// The five-storey building of [`five_storey_model`] with default sensing.
    pub fn five_storey(seed: u64) -> SimBuilding {
        let (frame, model) = five_storey_model();
        SimBuilding::new(frame, model, SimConfig::default(), seed)
    }

    /// A mode's true shape on the given channels (building frame; the vertical is still).
    pub fn true_shape(&self, mode: &TrueMode, channels: &[ChannelId]) -> Vec<f64> {
        channels
            .iter()
            .map(|c| {
                let floor = self
                    .model
                    .sensor_index(&c.sensor_id)
                    .map_or(0, |i| self.model.sensors[i].floor as usize);
                if c.direction != mode.direction || floor == 0 {
                    0.0
                } else {
                    mode.floor_shape[floor - 1]
                }
            })
            .collect()
    }

    /// `duration_s` of samples at `temperature_c` (constant over the window), noise and forces
    /// from `seed`.
    pub fn simulate(
        &self,
        temperature_c: f64,
        duration_s: f64,
        start_timestamp_ns: i64,
        seed: u64,
    ) -> Window {
        let mut rng = SmallRng::seed_from_u64(seed);
        let fs = self.config.sample_rate_hz;
        let dt = 1.0 / fs;
        let samples = (duration_s * fs).round() as usize;
        let n = self.frame.storeys();
        let modes = [
            self.frame.direction_modes(Direction::X, temperature_c),
            self.frame.direction_modes(Direction::Y, temperature_c),
        ];
        // Offsets are rendered within the hold interval: a common delay of half a sample
        // (which no shape sees) keeps `t + δt` inside it for offsets up to ±0.45 samples.
        let instants: Vec<f64> = self
            .errors
            .iter()
            .map(|e| 0.5 * dt + e.time_offset_s.clamp(-0.45 * dt, 0.45 * dt))
            .collect();
        struct Discrete {
            step: (Matrix2<f64>, Vector2<f64>),
            at: Vec<(Matrix2<f64>, Vector2<f64>)>,
            omega: f64,
            zeta: f64,
        }
        let discretise = |omega: f64, zeta: f64, tau: f64| {
            let a = Matrix2::new(0.0, 1.0, -omega * omega, -2.0 * zeta * omega);
            let e = (a * tau).exp();
            // A is invertible for ω > 0: its determinant is ω².
            let a_inv = a.try_inverse().expect("ω > 0");
            let f = a_inv * (e - Matrix2::identity()) * Vector2::new(0.0, 1.0);
            (e, f)
        };
        let discrete: Vec<Vec<Discrete>> = modes
            .iter()
            .map(|dir| {
                dir.iter()
                    .map(|m| {
                        let omega = 2.0 * std::f64::consts::PI * m.frequency_hz;
                        Discrete {
                            step: discretise(omega, m.damping_ratio, dt),
                            at: instants
                                .iter()
                                .map(|&t| discretise(omega, m.damping_ratio, t))
                                .collect(),
                            omega,
                            zeta: m.damping_ratio,
                        }
                    })
                    .collect()
            })
            .collect();
        let sensors = &self.model.sensors;
        let readout: Vec<Matrix3<f64>> = sensors
            .iter()
            .zip(&self.errors)
            .map(|(s, e)| (Matrix3::identity() + e.error) * s.rotation().transpose())
            .collect();
        let mut state = vec![vec![Vector2::zeros(); n]; 2];
        let mut series: Vec<SensorSeries> = sensors
            .iter()
            .map(|s| SensorSeries {
                sensor_id: s.sensor_id.clone(),
                acceleration_mps2: Vec::with_capacity(samples),
                valid: vec![true; samples],
                chain: self.config.chain,
            })
            .collect();
        // A lead-in of ten time constants of the slowest mode, so the window starts stationary.
        let slowest_decay = discrete
            .iter()
            .flatten()
            .map(|d| d.zeta * d.omega)
            .fold(f64::INFINITY, f64::min);
        let lead_in = (10.0 / slowest_decay.max(1e-3) * fs).min(1.0e6) as usize;
        let mut force = vec![0.0; n];
        let mut floor_acc = vec![[0.0f64; 2]; sensors.len()];
        for step in 0..lead_in + samples {
            let mut modal_force = [vec![0.0; n], vec![0.0; n]];
            for (d, dir_modes) in modes.iter().enumerate() {
                for f in force.iter_mut() {
                    *f = self.config.force_std_n * rng.sample::<f64, _>(StandardNormal);
                }
                for (k, m) in dir_modes.iter().enumerate() {
                    modal_force[d][k] = m.floor_shape.iter().zip(&force).map(|(p, f)| p * f).sum();
                }
            }
            if step >= lead_in {
                for acc in floor_acc.iter_mut() {
                    *acc = [0.0; 2];
                }
                for d in 0..2 {
                    for k in 0..n {
                        let disc = &discrete[d][k];
                        let u = modal_force[d][k];
                        for (s, sensor) in sensors.iter().enumerate() {
                            if sensor.floor == 0 {
                                continue;
                            }
                            let (e, f) = &disc.at[s];
                            let x = e * state[d][k] + f * u;
                            let eta_dd =
                                u - 2.0 * disc.zeta * disc.omega * x[1] - disc.omega.powi(2) * x[0];
                            floor_acc[s][d] +=
                                modes[d][k].floor_shape[sensor.floor as usize - 1] * eta_dd;
                        }
                    }
                }
                for (s, out) in series.iter_mut().enumerate() {
                    let a =
                        readout[s] * nalgebra::Vector3::new(floor_acc[s][0], floor_acc[s][1], 0.0);
                    let mut sample = [0.0; 3];
                    for (axis, v) in sample.iter_mut().enumerate() {
                        *v = a[axis]
                            + self.config.noise_std_mps2 * rng.sample::<f64, _>(StandardNormal);
                    }
                    out.acceleration_mps2.push(sample);
                }
            }
            for d in 0..2 {
                for k in 0..n {
                    let (e, f) = &discrete[d][k].step;
                    state[d][k] = e * state[d][k] + f * modal_force[d][k];
                }
            }
        }
        Window {
            start_timestamp_ns,
            sample_rate_hz: fs,
            sensors: series,
        }
    }
}

/// Marks a share of each sensor's samples invalid, in gaps of `gap_samples`, at random places
/// (flagged samples and lost batches).
pub fn punch_gaps(window: &mut Window, share: f64, gap_samples: usize, seed: u64) {
    let mut rng = SmallRng::seed_from_u64(seed);
    let n = window.len();
    if n == 0 || gap_samples == 0 {
        return;
    }
    let gaps = ((share * n as f64) / gap_samples as f64).round() as usize;
    for series in &mut window.sensors {
        for _ in 0..gaps {
            let start = rng.gen_range(0..n.saturating_sub(gap_samples).max(1));
            for v in series.valid[start..(start + gap_samples).min(n)].iter_mut() {
                *v = false;
            }
            // The value under a flag is whatever the stream carried: make it wild, so a test
            // notices if it is ever read.
            for a in series.acceleration_mps2[start..(start + gap_samples).min(n)].iter_mut() {
                *a = [1.0e3; 3];
            }
        }
    }
}
