//! What a Triax consumer needs beyond the wire formats of `triax-protocol`: reading a gateway's
//! history ([`history`]), and following a building's corrected streams without losing a batch
//! ([`Follower`]), by the recipe of PROTOCOL.md §5.2.
//!
//! Async, on whatever runtime the caller runs Zenoh with; no runtime of its own.

pub mod export;
pub mod follow;
pub mod history;
pub mod modes_parquet;
pub mod mseed;
pub mod normal;
pub mod parquet;
pub mod spectrum;
pub mod stationxml;
mod whole;

pub use follow::{Delivery, Fleet, FollowOptions, Follower, FollowerCounters, Following};
pub use history::{HistoryRequest, Recovered};

/// Why a consumer could not do what it was asked.
#[derive(Debug, thiserror::Error)]
pub enum ClientError {
    #[error("zenoh: {action}: {message}")]
    Zenoh {
        action: &'static str,
        message: String,
    },
    #[error("history query {selector}: {message}")]
    History { selector: String, message: String },
}

fn zenoh_err(action: &'static str) -> impl FnOnce(zenoh::Error) -> ClientError {
    move |e| ClientError::Zenoh {
        action,
        message: triax_net::zenoh_cause(&*e),
    }
}
