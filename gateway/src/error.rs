//! Why a gateway could not start, or stopped.

use std::net::SocketAddr;

use triax_calibration_store::StoreError;

use crate::config::ConfigError;

/// Why the gateway could not start or stopped.
#[derive(Debug, thiserror::Error)]
pub enum GatewayError {
    #[error(transparent)]
    Config(#[from] ConfigError),
    #[error(transparent)]
    ZenohConfig(#[from] triax_net::ZenohConfigError),
    #[error("calibration store {path}: {source}")]
    Store {
        path: std::path::PathBuf,
        #[source]
        source: StoreError,
    },
    #[error("zenoh: {action}: {message}")]
    Zenoh {
        action: &'static str,
        message: String,
    },
    #[error("metrics endpoint {addr}: {source}")]
    Metrics {
        addr: SocketAddr,
        #[source]
        source: std::io::Error,
    },
    #[error("a gateway task failed: {0}")]
    Task(String),
    #[error(transparent)]
    History(#[from] triax_history::HistoryError),
    #[error("{0}")]
    Key(String),
}

pub(crate) fn zenoh_err(action: &'static str) -> impl FnOnce(zenoh::Error) -> GatewayError {
    move |e| GatewayError::Zenoh {
        action,
        message: e.to_string(),
    }
}
