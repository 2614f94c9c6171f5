//! The building model: which sensors are where, and how each is mounted.
//!
//! The building frame is right-handed with `z` up; `x` and `y` are the plan's two principal
//! directions, the ones a shear frame sways in. A sensor's `mounting` is the rotation `R` that
//! takes a vector from the sensor's axes into the building frame (`a_building = R · a_sensor`),
//! given as three rows. It is checked to be a proper rotation (orthonormal to 10⁻⁶, determinant
//! +1): a mounting matrix that is not one is a mistake in the configuration, not a calibration.
//!
//! ```toml
//! building_id = "b1"
//!
//! [[sensors]]
//! sensor_id = "roof-a"
//! floor = 5
//! height_m = 17.5
//! position_m = [3.0, 4.0]
//! mounting = [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]
//! ```

use std::collections::HashSet;

use nalgebra::Matrix3;
use serde::Deserialize;
use thiserror::Error;

/// A horizontal direction of the building frame.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, serde::Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Direction {
    X,
    Y,
    Z,
}

impl Direction {
    /// Row of the building frame.
    pub fn index(self) -> usize {
        match self {
            Direction::X => 0,
            Direction::Y => 1,
            Direction::Z => 2,
        }
    }
}

/// One sensor of the building, as configured.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SensorPlacement {
    pub sensor_id: String,
    /// Floor number, 0 for the ground floor.
    pub floor: u32,
    /// Height of the sensor above the ground floor, m.
    pub height_m: f64,
    /// Position in plan (x, y) in the building frame, m.
    #[serde(default)]
    pub position_m: [f64; 2],
    /// Rows of the rotation from the sensor's axes into the building frame.
    pub mounting: [[f64; 3]; 3],
}

impl SensorPlacement {
    /// The mounting as a matrix.
    pub fn rotation(&self) -> Matrix3<f64> {
        let m = &self.mounting;
        Matrix3::new(
            m[0][0], m[0][1], m[0][2], m[1][0], m[1][1], m[1][2], m[2][0], m[2][1], m[2][2],
        )
    }
}

/// A building's sensors, validated ([`BuildingModel::new`] or [`BuildingModel::validate`]).
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BuildingModel {
    pub building_id: String,
    pub sensors: Vec<SensorPlacement>,
}

/// A building model that cannot be used, naming the sensor and the field.
#[derive(Debug, Clone, PartialEq, Error)]
pub enum ModelError {
    #[error("building id is empty")]
    EmptyBuildingId,
    #[error("building {0} has no sensors")]
    NoSensors(String),
    #[error("sensor #{index}: sensor_id is empty")]
    EmptySensorId { index: usize },
    #[error("sensor {sensor_id}: listed twice")]
    DuplicateSensor { sensor_id: String },
    #[error("sensor {sensor_id}: {field} is not a finite number")]
    NotFinite {
        sensor_id: String,
        field: &'static str,
    },
    #[error("sensor {sensor_id}: height_m {height_m} is negative")]
    NegativeHeight { sensor_id: String, height_m: f64 },
    #[error(
        "sensor {sensor_id}: mounting is not a rotation (|RᵀR − I| = {orthogonality_error:.2e}, \
         det = {determinant:.6}); rows must be orthonormal with determinant +1"
    )]
    NotRotation {
        sensor_id: String,
        orthogonality_error: f64,
        determinant: f64,
    },
}

/// Tolerance on `RᵀR = I`: configuration files carry six or more digits.
const ROTATION_TOLERANCE: f64 = 1e-6;

impl BuildingModel {
    /// A validated model.
    pub fn new(
        building_id: impl Into<String>,
        sensors: Vec<SensorPlacement>,
    ) -> Result<Self, ModelError> {
        let model = BuildingModel {
            building_id: building_id.into(),
            sensors,
        };
        model.validate()?;
        Ok(model)
    }

    /// Checks everything a deserialised model may get wrong.
    pub fn validate(&self) -> Result<(), ModelError> {
        if self.building_id.trim().is_empty() {
            return Err(ModelError::EmptyBuildingId);
        }
        if self.sensors.is_empty() {
            return Err(ModelError::NoSensors(self.building_id.clone()));
        }
        let mut seen = HashSet::new();
        for (index, s) in self.sensors.iter().enumerate() {
            if s.sensor_id.trim().is_empty() {
                return Err(ModelError::EmptySensorId { index });
            }
            if !seen.insert(s.sensor_id.as_str()) {
                return Err(ModelError::DuplicateSensor {
                    sensor_id: s.sensor_id.clone(),
                });
            }
            let not_finite = |field| ModelError::NotFinite {
                sensor_id: s.sensor_id.clone(),
                field,
            };
            if !s.height_m.is_finite() {
                return Err(not_finite("height_m"));
            }
            if s.height_m < 0.0 {
                return Err(ModelError::NegativeHeight {
                    sensor_id: s.sensor_id.clone(),
                    height_m: s.height_m,
                });
            }
            if !s.position_m.iter().all(|v| v.is_finite()) {
                return Err(not_finite("position_m"));
            }
            if !s.mounting.iter().flatten().all(|v| v.is_finite()) {
                return Err(not_finite("mounting"));
            }
            let r = s.rotation();
            let orthogonality_error = (r.transpose() * r - Matrix3::identity()).abs().max();
            let determinant = r.determinant();
            if orthogonality_error > ROTATION_TOLERANCE || (determinant - 1.0).abs() > 1e-5 {
                return Err(ModelError::NotRotation {
                    sensor_id: s.sensor_id.clone(),
                    orthogonality_error,
                    determinant,
                });
            }
        }
        Ok(())
    }

    /// Index of a sensor by id.
    pub fn sensor_index(&self, sensor_id: &str) -> Option<usize> {
        self.sensors.iter().position(|s| s.sensor_id == sensor_id)
    }

    /// Highest floor with a sensor.
    pub fn top_floor(&self) -> u32 {
        self.sensors.iter().map(|s| s.floor).max().unwrap_or(0)
    }
}

/// Rotation about the building's vertical by `angle_rad` (sensor axes turned in plan).
pub fn rotation_about_z(angle_rad: f64) -> [[f64; 3]; 3] {
    let (s, c) = angle_rad.sin_cos();
    [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]
}

/// Rows of a rotation matrix.
pub fn rows(m: &Matrix3<f64>) -> [[f64; 3]; 3] {
    [
        [m[(0, 0)], m[(0, 1)], m[(0, 2)]],
        [m[(1, 0)], m[(1, 1)], m[(1, 2)]],
        [m[(2, 0)], m[(2, 1)], m[(2, 2)]],
    ]
}
