//! Buildings with known modes, driven by broadband forces on every floor and seen by sensors
//! with their own calibration errors, mountings, clock offsets and noise.
//!
//! **The shear frame** ([`ShearFrame`]). Floor `j` (1…n) has mass `m_j`; storey `j` (between
//! floors `j−1` and `j`, floor 0 the ground) has stiffness `k_j` in `x` and
//! `k_j · stiffness_ratio_y` in `y`, so the two directions have close modes (a ratio of 1.03
//! puts them 1.5 % apart). The modes solve the generalised eigenproblem `K·φ = ω²·M·φ`
//! (through `M^(−½)·K·M^(−½)`, symmetric), with mass-normalised shapes; damping is modal, `ζ`
//! per mode. Temperature scales every stiffness by `(1 + β·(T − T_ref))²`, so every frequency
//! by `1 + β·(T − T_ref)` with `β = frequency_change_per_c`; damage lowers one storey's
//! stiffness in one direction.
//!
//! **The plan frame** ([`PlanFrame`]). Each floor moves in plan: `x`, `y` at its centre of
//! mass and a turn `θ` about the vertical, with mass `m` and moment of inertia `J` (a
//! rectangle's `m·(a² + b²)/12`). Storey `j` resists with `k_x`, `k_y` at its centre of
//! stiffness, `e = (e_x, e_y)` from the centre of mass, and `k_θ` about it: for the storey's
//! drift `d = (d_x, d_y, d_θ)` its energy is
//! `½·k_x·(d_x − e_y·d_θ)² + ½·k_y·(d_y + e_x·d_θ)² + ½·k_θ·d_θ²`, so an eccentric
//! building's modes couple sway and torsion. A point `p` of
//! floor `j` moves by `(x_j − θ_j·(p_y − c_y), y_j + θ_j·(p_x − c_x))`, `c` the centre of mass:
//! sensors away from it see the torsional modes. Modes are classified by where their modal
//! mass is (`x`, `y` or torsion) and numbered within their kind. Temperature and damage act as
//! in the shear frame (a damaged storey loses a share of its stiffness in `x`, `y` and
//! torsion alike).
//!
//! **The response, exactly.** Each mode is a second-order system in its modal coordinate,
//! `η̈ + 2ζω·η̇ + ω²·η = φᵀ·f`. The floor forces `f` (and torques, for a plan frame) are white
//! and held over each sample interval (zero-order hold), so the discrete system
//! `x(t+τ) = e^(A·τ)·x(t) + A⁻¹(e^(A·τ) − I)·B·u` with the matrix exponential is exact, not an
//! integration scheme, and the acceleration `η̈ = φᵀ·f − 2ζω·η̇ − ω²·η` is evaluated at any
//! instant, which is how a node's clock offset is rendered: its samples are the motion at
//! `t + δt`, not `t` (whole sample periods of it by taking another step's motion, the rest
//! within the step). The modes' truth is the same eigen-decomposition the response is computed
//! from.
//!
//! **The sensors.** A sensor on floor `j` whose true mounting is `R` reads, in its own axes,
//! `(I + E)·Rᵀ·(a(t + δt) + g·ẑ) + noise`, where `a` is its point's acceleration in the
//! building frame, `g` the gravity the corrected streams carry as specific force (0 unless
//! [`SimConfig::gravity_mps2`] says), `E` its residual calibration error (diagonal: relative
//! gain errors; off-diagonal: cross-axis terms), drawn once per sensor from the chain's stated
//! standard uncertainties, `δt` its clock offset, drawn from the stated time-stamp uncertainty
//! (or set), and the noise white. `R` is the building model's declared mounting unless
//! [`SimBuilding::true_mounting`] is changed: a misdeclared sensor.
//!
//! Pure and seeded: the same building and seed give the same samples.

use nalgebra::{DMatrix, Matrix2, Matrix3, SymmetricEigen, Vector2, Vector3};
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

/// Where a mode's modal mass is: sway in `x`, sway in `y`, or torsion about the vertical.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum ModeKind {
    X,
    Y,
    Torsion,
}

impl ModeKind {
    /// The building direction of a sway mode; none for torsion.
    pub fn direction(self) -> Option<Direction> {
        match self {
            ModeKind::X => Some(Direction::X),
            ModeKind::Y => Some(Direction::Y),
            ModeKind::Torsion => None,
        }
    }
}

/// A mode of a building whose floors move in plan.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PlanMode {
    pub kind: ModeKind,
    /// 1 for the lowest of its kind.
    pub number: usize,
    pub frequency_hz: f64,
    pub damping_ratio: f64,
    /// Mass-normalised motion of floors 1…n: `[x m, y m, θ rad]` at the structure's reference
    /// point ([`Structure::reference_point_m`]).
    pub floor_motion: Vec<[f64; 3]>,
}

/// What the simulator needs of a structure.
pub trait Structure {
    fn storeys(&self) -> usize;
    /// Every mode, in the order the simulator drives them, at a temperature.
    fn plan_modes(&self, temperature_c: f64) -> Vec<PlanMode>;
    /// Whether floors turn, so that torques are drawn besides forces.
    fn torsional(&self) -> bool;
    /// The plan point whose motion is a floor's `x` and `y` (the centre of mass), m.
    fn reference_point_m(&self) -> [f64; 2];
    /// Standard deviation of each floor's torque over that of its forces, m.
    fn torque_arm_m(&self) -> f64;
}

impl Structure for ShearFrame {
    fn storeys(&self) -> usize {
        self.floor_mass_kg.len()
    }

    /// `x`'s modes by frequency, then `y`'s.
    fn plan_modes(&self, temperature_c: f64) -> Vec<PlanMode> {
        let mut out = Vec::new();
        for (direction, kind, axis) in [
            (Direction::X, ModeKind::X, 0),
            (Direction::Y, ModeKind::Y, 1),
        ] {
            for m in self.direction_modes(direction, temperature_c) {
                out.push(PlanMode {
                    kind,
                    number: m.number,
                    frequency_hz: m.frequency_hz,
                    damping_ratio: m.damping_ratio,
                    floor_motion: m
                        .floor_shape
                        .iter()
                        .map(|&v| {
                            let mut motion = [0.0; 3];
                            motion[axis] = v;
                            motion
                        })
                        .collect(),
                });
            }
        }
        out
    }

    fn torsional(&self) -> bool {
        false
    }

    fn reference_point_m(&self) -> [f64; 2] {
        [0.0, 0.0]
    }

    fn torque_arm_m(&self) -> f64 {
        0.0
    }
}

/// A building whose floors sway in `x` and `y` and turn about the vertical (the module's
/// documentation).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PlanFrame {
    /// Mass of floors 1…n, kg.
    pub floor_mass_kg: Vec<f64>,
    /// Moment of inertia of floors 1…n about the vertical through their centre of mass, kg·m².
    pub floor_inertia_kg_m2: Vec<f64>,
    /// The floors' centre of mass in plan, building frame, m.
    pub centre_of_mass_m: [f64; 2],
    /// Stiffness of storeys 1…n in `x` and `y`, N/m, and about the vertical, N·m/rad.
    pub storey_stiffness_x_n_per_m: Vec<f64>,
    pub storey_stiffness_y_n_per_m: Vec<f64>,
    pub storey_stiffness_torsion_n_m_per_rad: Vec<f64>,
    /// The storeys' centre of stiffness relative to the centre of mass, m.
    pub eccentricity_m: [f64; 2],
    /// Modal damping ratio of every mode by increasing frequency (the last repeats).
    pub damping_ratio: Vec<f64>,
    /// Relative change of every frequency per °C.
    pub frequency_change_per_c: f64,
    pub reference_temperature_c: f64,
    /// Storeys that lost stiffness: (storey 1…n, fraction lost in `x`, `y` and torsion).
    pub damage: Vec<(usize, f64)>,
    /// Standard deviation of each floor's torque over that of its forces, m.
    pub torque_arm_m: f64,
}

impl PlanFrame {
    /// `storeys` equal floors of `floor_mass_kg` over a rectangular plan `plan_m` (`a` along
    /// `x`, `b` along `y`, the centre of mass at its middle) and equal storeys whose centre of
    /// stiffness is `eccentricity_m` off it, stiffnesses set so that the lowest `x`, `y` and
    /// torsional modes are at `fundamentals_hz` (found by rescaling each stiffness until the
    /// coupled modes are there to 10⁻¹⁰), and every mode damped by `damping_ratio`.
    pub fn tuned(
        storeys: usize,
        floor_mass_kg: f64,
        plan_m: [f64; 2],
        fundamentals_hz: [f64; 3],
        eccentricity_m: [f64; 2],
        damping_ratio: f64,
    ) -> PlanFrame {
        let inertia = floor_mass_kg * (plan_m[0].powi(2) + plan_m[1].powi(2)) / 12.0;
        let s = (std::f64::consts::PI / (2.0 * (2 * storeys + 1) as f64)).sin();
        let uniform =
            |mass: f64, f: f64| mass * (2.0 * std::f64::consts::PI * f / (2.0 * s)).powi(2);
        let mut frame = PlanFrame {
            floor_mass_kg: vec![floor_mass_kg; storeys],
            floor_inertia_kg_m2: vec![inertia; storeys],
            centre_of_mass_m: [0.5 * plan_m[0], 0.5 * plan_m[1]],
            storey_stiffness_x_n_per_m: vec![uniform(floor_mass_kg, fundamentals_hz[0]); storeys],
            storey_stiffness_y_n_per_m: vec![uniform(floor_mass_kg, fundamentals_hz[1]); storeys],
            storey_stiffness_torsion_n_m_per_rad: vec![
                uniform(inertia, fundamentals_hz[2]);
                storeys
            ],
            eccentricity_m,
            damping_ratio: vec![damping_ratio],
            frequency_change_per_c: 0.0,
            reference_temperature_c: 20.0,
            damage: Vec::new(),
            torque_arm_m: (inertia / floor_mass_kg).sqrt(),
        };
        for _ in 0..200 {
            let modes = frame.plan_modes(frame.reference_temperature_c);
            let mut worst: f64 = 0.0;
            for (kind, target) in [ModeKind::X, ModeKind::Y, ModeKind::Torsion]
                .into_iter()
                .zip(fundamentals_hz)
            {
                let Some(m) = modes.iter().find(|m| m.kind == kind) else {
                    continue;
                };
                let scale = (target / m.frequency_hz).powi(2);
                worst = worst.max((scale - 1.0).abs());
                let k = match kind {
                    ModeKind::X => &mut frame.storey_stiffness_x_n_per_m,
                    ModeKind::Y => &mut frame.storey_stiffness_y_n_per_m,
                    ModeKind::Torsion => &mut frame.storey_stiffness_torsion_n_m_per_rad,
                };
                k.iter_mut().for_each(|v| *v *= scale);
            }
            if worst < 1e-10 {
                break;
            }
        }
        frame
    }

    /// The stiffness matrix at a temperature, degrees of freedom `[x₁…x_n, y₁…y_n, θ₁…θ_n]`.
    pub fn stiffness(&self, temperature_c: f64) -> DMatrix<f64> {
        let n = self.floor_mass_kg.len();
        let thermal = (1.0
            + self.frequency_change_per_c * (temperature_c - self.reference_temperature_c))
            .powi(2);
        let [ex, ey] = self.eccentricity_m;
        let mut k = DMatrix::zeros(3 * n, 3 * n);
        for j in 0..n {
            let loss: f64 = self
                .damage
                .iter()
                .filter(|(s, _)| *s == j + 1)
                .map(|(_, f)| f)
                .sum();
            let scale = thermal * (1.0 - loss);
            let kx = self.storey_stiffness_x_n_per_m[j] * scale;
            let ky = self.storey_stiffness_y_n_per_m[j] * scale;
            let kt = self.storey_stiffness_torsion_n_m_per_rad[j] * scale;
            // The storey's 3×3 stiffness on its drift (d_x, d_y, d_θ), from its energy.
            let storey = Matrix3::new(
                kx,
                0.0,
                -kx * ey,
                0.0,
                ky,
                ky * ex,
                -kx * ey,
                ky * ex,
                kt + kx * ey * ey + ky * ex * ex,
            );
            // Drift of storey j is u_j − u_(j−1); the ground (j = 0) does not move.
            let dofs = |floor: usize| [floor, n + floor, 2 * n + floor];
            let upper = dofs(j);
            for a in 0..3 {
                for b in 0..3 {
                    k[(upper[a], upper[b])] += storey[(a, b)];
                    if j > 0 {
                        let lower = dofs(j - 1);
                        k[(lower[a], lower[b])] += storey[(a, b)];
                        k[(upper[a], lower[b])] -= storey[(a, b)];
                        k[(lower[a], upper[b])] -= storey[(a, b)];
                    }
                }
            }
        }
        k
    }
}

impl Structure for PlanFrame {
    fn storeys(&self) -> usize {
        self.floor_mass_kg.len()
    }

    /// Every mode by increasing frequency.
    fn plan_modes(&self, temperature_c: f64) -> Vec<PlanMode> {
        let n = self.floor_mass_kg.len();
        let k = self.stiffness(temperature_c);
        let inv_sqrt_m: Vec<f64> = self
            .floor_mass_kg
            .iter()
            .chain(&self.floor_mass_kg)
            .chain(&self.floor_inertia_kg_m2)
            .map(|m| 1.0 / m.sqrt())
            .collect();
        let l = DMatrix::from_fn(3 * n, 3 * n, |i, j| {
            inv_sqrt_m[i] * k[(i, j)] * inv_sqrt_m[j]
        });
        let eigen = SymmetricEigen::new(l);
        let mut order: Vec<usize> = (0..3 * n).collect();
        order.sort_by(|&a, &b| eigen.eigenvalues[a].total_cmp(&eigen.eigenvalues[b]));
        let mut counts = [0usize; 3];
        order
            .iter()
            .enumerate()
            .map(|(index, &j)| {
                let omega = eigen.eigenvalues[j].max(0.0).sqrt();
                let dof: Vec<f64> = (0..3 * n)
                    .map(|i| eigen.eigenvectors[(i, j)] * inv_sqrt_m[i])
                    .collect();
                // Modal mass by kind: Σ m·φ² of each group (the shape is mass-normalised).
                let share = |g: usize| -> f64 {
                    (0..n)
                        .map(|f| {
                            let m = if g == 2 {
                                self.floor_inertia_kg_m2[f]
                            } else {
                                self.floor_mass_kg[f]
                            };
                            m * dof[g * n + f].powi(2)
                        })
                        .sum()
                };
                let shares = [share(0), share(1), share(2)];
                let g = (0..3)
                    .max_by(|&a, &b| shares[a].total_cmp(&shares[b]))
                    .unwrap_or(0);
                let kind = [ModeKind::X, ModeKind::Y, ModeKind::Torsion][g];
                counts[g] += 1;
                // Sign convention: the top floor's dominant part moves positively.
                let sign = if dof[g * n + n - 1] < 0.0 { -1.0 } else { 1.0 };
                PlanMode {
                    kind,
                    number: counts[g],
                    frequency_hz: omega / (2.0 * std::f64::consts::PI),
                    damping_ratio: self.damping_ratio[index.min(self.damping_ratio.len() - 1)],
                    floor_motion: (0..n)
                        .map(|f| [sign * dof[f], sign * dof[n + f], sign * dof[2 * n + f]])
                        .collect(),
                }
            })
            .collect()
    }

    fn torsional(&self) -> bool {
        true
    }

    fn reference_point_m(&self) -> [f64; 2] {
        self.centre_of_mass_m
    }

    fn torque_arm_m(&self) -> f64 {
        self.torque_arm_m
    }
}

/// A sensor's true residual errors in the simulation.
#[derive(Debug, Clone, PartialEq)]
pub struct SensorErrors {
    /// `E`: relative gain errors on the diagonal, cross-axis terms off it.
    pub error: Matrix3<f64>,
    /// The node's clock offset: its sample stamped `t` is the motion at `t + time_offset_s`
    /// (a node whose stamps are one period late: `−1/sample_rate_hz`).
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
    /// Gravity in the readings (specific force: `+g` along the building's `z`), m/s²; 0 leaves
    /// only the motion.
    pub gravity_mps2: f64,
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
            gravity_mps2: 0.0,
        }
    }
}

/// Standard gravity, m/s².
pub const STANDARD_GRAVITY_MPS2: f64 = 9.806_65;

/// A simulated building: structure, sensors and their true errors and mountings.
#[derive(Debug, Clone)]
pub struct SimBuilding<S = ShearFrame> {
    pub frame: S,
    pub model: BuildingModel,
    pub errors: Vec<SensorErrors>,
    /// Each sensor's true mounting (sensor axes into the building frame): the model's declared
    /// one unless a test misdeclares it.
    pub true_mounting: Vec<Matrix3<f64>>,
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

/// Sensors `(floor, plan position m, turn in plan °)` as a model, ids `s01`, `s02`, ….
fn plan_model(id: &str, storey_height_m: f64, sensors: &[(u32, [f64; 2], f64)]) -> BuildingModel {
    let sensors = sensors
        .iter()
        .enumerate()
        .map(|(i, &(floor, position_m, angle_deg))| SensorPlacement {
            sensor_id: format!("s{:02}", i + 1),
            floor,
            height_m: storey_height_m * f64::from(floor),
            position_m,
            mounting: rotation_about_z(angle_deg.to_radians()),
        })
        .collect();
    // Distinct ids and rotations about z: valid.
    BuildingModel::new(id, sensors).expect("the simulated model is valid")
}

/// A ten-storey office building: 600 t a floor over 36 × 24 m, its centre of stiffness 1.8 m
/// and 1.2 m off the centre of mass (so sway and torsion couple), lowest modes 0.85 Hz in `x`,
/// 0.90 Hz in `y` and 1.25 Hz in torsion, 1.5 % damping: 13 modes below 8 Hz. Twelve
/// three-axis sensors on floors 1–10 (two on floors 6 and 10, at opposite corners), mounted
/// at 0°, ±90°, 180° and 30° in plan.
pub fn ten_storey_model() -> (PlanFrame, BuildingModel) {
    let frame = PlanFrame::tuned(
        10,
        6.0e5,
        [36.0, 24.0],
        [0.85, 0.90, 1.25],
        [1.8, 1.2],
        0.015,
    );
    let model = plan_model(
        "tower",
        3.5,
        &[
            (1, [6.0, 4.0], 0.0),
            (2, [30.0, 20.0], 90.0),
            (3, [6.0, 20.0], -90.0),
            (4, [30.0, 4.0], 180.0),
            (5, [18.0, 12.0], 30.0),
            (6, [3.0, 3.0], 0.0),
            (6, [33.0, 21.0], 90.0),
            (7, [6.0, 4.0], 180.0),
            (8, [30.0, 20.0], -90.0),
            (9, [18.0, 20.0], 30.0),
            (10, [3.0, 3.0], 0.0),
            (10, [33.0, 21.0], 180.0),
        ],
    );
    (frame, model)
}

/// A seven-storey building long in plan: 900 t a floor over 60 × 15 m, its centre of
/// stiffness 3 m along `x` off the centre of mass, lowest modes 1.3 Hz in `x`, 1.1 Hz in `y`,
/// 1.75 Hz in torsion, 3 % damping: 9 modes below 8 Hz. Eight sensors: three on the roof (both
/// ends and the middle), two on floor 4 (both ends), one on floors 1, 2 and 6.
pub fn seven_storey_model() -> (PlanFrame, BuildingModel) {
    let frame = PlanFrame::tuned(7, 9.0e5, [60.0, 15.0], [1.3, 1.1, 1.75], [3.0, 0.5], 0.03);
    let model = plan_model(
        "long",
        4.0,
        &[
            (1, [10.0, 7.5], 90.0),
            (2, [50.0, 7.5], 0.0),
            (4, [2.0, 7.5], 180.0),
            (4, [58.0, 7.5], -90.0),
            (6, [30.0, 7.5], 30.0),
            (7, [2.0, 2.0], 0.0),
            (7, [30.0, 13.0], 90.0),
            (7, [58.0, 2.0], 180.0),
        ],
    );
    (frame, model)
}

impl SimBuilding<ShearFrame> {
    /// The five-storey building of [`five_storey_model`] with default sensing.
    pub fn five_storey(seed: u64) -> SimBuilding {
        let (frame, model) = five_storey_model();
        SimBuilding::new(frame, model, SimConfig::default(), seed)
    }
}

impl SimBuilding<PlanFrame> {
    /// The ten-storey building of [`ten_storey_model`], sampled at 50 Hz, gravity in the
    /// readings, the floors' forces at 5 kN (held per sample) and 0.2 mg of sensor noise: 3.3 to
    /// 5.5 mg RMS on each sensor's horizontal axes, most of it from the modes above 5 Hz.
    pub fn ten_storey(seed: u64) -> SimBuilding<PlanFrame> {
        let (frame, model) = ten_storey_model();
        let config = SimConfig {
            sample_rate_hz: 50.0,
            force_std_n: 5.0e3,
            gravity_mps2: STANDARD_GRAVITY_MPS2,
            ..SimConfig::default()
        };
        SimBuilding::new(frame, model, config, seed)
    }

    /// The seven-storey building of [`seven_storey_model`], sampled at 100 Hz, gravity in the
    /// readings, the floors' forces at 8 kN and 0.2 mg of sensor noise: 1.7 to 4.0 mg RMS on
    /// each sensor's horizontal axes.
    pub fn seven_storey(seed: u64) -> SimBuilding<PlanFrame> {
        let (frame, model) = seven_storey_model();
        let config = SimConfig {
            force_std_n: 8.0e3,
            gravity_mps2: STANDARD_GRAVITY_MPS2,
            ..SimConfig::default()
        };
        SimBuilding::new(frame, model, config, seed)
    }
}

impl<S: Structure> SimBuilding<S> {
    /// A building with its sensors' true errors drawn from `config.chain` with `seed`.
    pub fn new(frame: S, model: BuildingModel, config: SimConfig, seed: u64) -> SimBuilding<S> {
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
        let true_mounting = model
            .sensors
            .iter()
            .map(SensorPlacement::rotation)
            .collect();
        SimBuilding {
            frame,
            model,
            errors,
            true_mounting,
            config,
        }
    }

    /// Every mode of the structure at a temperature.
    pub fn plan_modes(&self, temperature_c: f64) -> Vec<PlanMode> {
        self.frame.plan_modes(temperature_c)
    }

    /// A plan mode's true shape on the given channels: each sensor's point's motion in the
    /// building frame (the vertical is still).
    pub fn plan_shape(&self, mode: &PlanMode, channels: &[ChannelId]) -> Vec<f64> {
        let centre = self.frame.reference_point_m();
        channels
            .iter()
            .map(|c| {
                let Some(sensor) = self
                    .model
                    .sensor_index(&c.sensor_id)
                    .map(|i| &self.model.sensors[i])
                else {
                    return 0.0;
                };
                if sensor.floor == 0 {
                    return 0.0;
                }
                let [x, y, theta] = mode.floor_motion[sensor.floor as usize - 1];
                let p = sensor.position_m;
                match c.direction {
                    Direction::X => x - theta * (p[1] - centre[1]),
                    Direction::Y => y + theta * (p[0] - centre[0]),
                    Direction::Z => 0.0,
                }
            })
            .collect()
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
        let modes = self.frame.plan_modes(temperature_c);
        let groups = if self.frame.torsional() { 3 } else { 2 };
        let centre = self.frame.reference_point_m();
        // A clock offset of q whole periods and a remainder r: sample m is the motion of step
        // m + q at r within it. A common delay of half a period (which no shape sees) keeps
        // the instant 0.5·dt + r inside the step.
        let shifts: Vec<(i64, f64)> = self
            .errors
            .iter()
            .map(|e| {
                let q = (e.time_offset_s / dt).round();
                (q as i64, 0.5 * dt + (e.time_offset_s - q * dt))
            })
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
        let discrete: Vec<Discrete> = modes
            .iter()
            .map(|m| {
                let omega = 2.0 * std::f64::consts::PI * m.frequency_hz;
                Discrete {
                    step: discretise(omega, m.damping_ratio, dt),
                    at: shifts
                        .iter()
                        .map(|&(_, t)| discretise(omega, m.damping_ratio, t))
                        .collect(),
                    omega,
                    zeta: m.damping_ratio,
                }
            })
            .collect();
        let sensors = &self.model.sensors;
        // Each sensor's point's building-frame motion per unit modal acceleration of each mode.
        let participation: Vec<Vec<[f64; 2]>> = sensors
            .iter()
            .map(|sensor| {
                modes
                    .iter()
                    .map(|m| {
                        if sensor.floor == 0 {
                            return [0.0; 2];
                        }
                        let [x, y, theta] = m.floor_motion[sensor.floor as usize - 1];
                        let p = sensor.position_m;
                        [
                            x - theta * (p[1] - centre[1]),
                            y + theta * (p[0] - centre[0]),
                        ]
                    })
                    .collect()
            })
            .collect();
        let readout: Vec<Matrix3<f64>> = self
            .true_mounting
            .iter()
            .zip(&self.errors)
            .map(|(r, e)| (Matrix3::identity() + e.error) * r.transpose())
            .collect();
        let mut state = vec![Vector2::zeros(); modes.len()];
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
            .map(|d| d.zeta * d.omega)
            .fold(f64::INFINITY, f64::min);
        let lead_in = (10.0 / slowest_decay.max(1e-3) * fs).min(1.0e6) as i64;
        let earliest = shifts.iter().map(|s| s.0).min().unwrap_or(0).min(0);
        let latest = shifts.iter().map(|s| s.0).max().unwrap_or(0).max(0);
        let lead_in = lead_in.max(-earliest);
        let steps = lead_in + samples as i64 + latest;
        let arm = self.frame.torque_arm_m();
        let mut force = vec![vec![0.0; n]; groups];
        let mut modal_force = vec![0.0; modes.len()];
        for step in 0..steps {
            for (g, group) in force.iter_mut().enumerate() {
                let scale = if g == 2 {
                    self.config.force_std_n * arm
                } else {
                    self.config.force_std_n
                };
                for f in group.iter_mut() {
                    *f = scale * rng.sample::<f64, _>(StandardNormal);
                }
            }
            for (k, m) in modes.iter().enumerate() {
                modal_force[k] = (0..groups)
                    .map(|g| -> f64 {
                        m.floor_motion
                            .iter()
                            .zip(&force[g])
                            .map(|(p, f)| p[g] * f)
                            .sum()
                    })
                    .sum();
            }
            for (s, out) in series.iter_mut().enumerate() {
                let m = step - lead_in - shifts[s].0;
                if m < 0 || m >= samples as i64 {
                    continue;
                }
                let mut acc = [0.0f64; 2];
                if sensors[s].floor != 0 {
                    for (k, disc) in discrete.iter().enumerate() {
                        let u = modal_force[k];
                        let (e, f) = &disc.at[s];
                        let x = e * state[k] + f * u;
                        let eta_dd =
                            u - 2.0 * disc.zeta * disc.omega * x[1] - disc.omega.powi(2) * x[0];
                        let [px, py] = participation[s][k];
                        acc[0] += px * eta_dd;
                        acc[1] += py * eta_dd;
                    }
                }
                let a = readout[s] * Vector3::new(acc[0], acc[1], self.config.gravity_mps2);
                let mut sample = [0.0; 3];
                for (axis, v) in sample.iter_mut().enumerate() {
                    *v =
                        a[axis] + self.config.noise_std_mps2 * rng.sample::<f64, _>(StandardNormal);
                }
                out.acceleration_mps2.push(sample);
            }
            for (k, d) in discrete.iter().enumerate() {
                let (e, f) = &d.step;
                state[k] = e * state[k] + f * modal_force[k];
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
