//! What can stop an identification.

use thiserror::Error;

use crate::model::{Direction, ModelError};

#[derive(Debug, Clone, PartialEq, Error)]
pub enum ModalError {
    #[error(transparent)]
    Model(#[from] ModelError),
    #[error("sample rate {0} Hz is not a positive number")]
    InvalidRate(f64),
    #[error("option {field}: {reason}")]
    InvalidOption { field: &'static str, reason: String },
    #[error("sensor {sensor_id} is not in the building model")]
    UnknownSensor { sensor_id: String },
    #[error("sensor {sensor_id} appears twice in the window")]
    DuplicateSeries { sensor_id: String },
    #[error(
        "sensor {sensor_id}: {samples} samples and {valid} validity flags, the window has {expected}"
    )]
    LengthMismatch {
        sensor_id: String,
        samples: usize,
        valid: usize,
        expected: usize,
    },
    #[error(
        "sensor {sensor_id}, direction {direction:?}: only {:.1} % of the window is usable \
         (flags, gaps and the filter's margin around them), {:.1} % required",
        100.0 * valid_fraction,
        100.0 * required
    )]
    TooMuchMissing {
        sensor_id: String,
        direction: Direction,
        valid_fraction: f64,
        required: f64,
    },
    #[error("{0} channels: identification needs at least two")]
    TooFewChannels(usize),
    #[error(
        "window too short: {samples} samples after decimation for {blocks} blocks and lags up \
         to {max_lag}"
    )]
    TooShort {
        samples: usize,
        blocks: usize,
        max_lag: usize,
    },
    #[error("block {block}: no valid pair of samples for channel {channel} at lag {lag}")]
    EmptyCorrelation {
        block: usize,
        channel: usize,
        lag: usize,
    },
    #[error("the linear algebra did not converge ({0})")]
    Numerical(&'static str),
}
