//! Triax alerting: thresholds on the corrected and tilt streams that use each value's
//! uncertainty instead of ignoring it.
//!
//! Per sensor, over a sliding window, the service estimates the peak (PGA), RMS and dominant
//! frequency of the motion above a high-passed baseline and the tilt change from a baseline,
//! each with a standard uncertainty that covers noise on a maximum as well as calibration
//! ([`stats`], [`monitor`]), and decides with a guard band
//! ([`decision`]): `exceeded` when the whole k-interval is beyond the threshold, `possible` when
//! it straddles it, nothing otherwise. Alerts go out as JSON on `triax/<building>/alert/<sensor>`.
//!
//! - [`config`]: the TOML file (thresholds per building and sensor, window, k, staleness).
//! - [`decision`]: the guard-band rule, pure.
//! - [`stats`]: window statistics and their uncertainties, pure; [`sinefit`] for a window that
//!   is one sway, [`highpass`] for the vibration baseline, `triax_client::normal` for the quantiles.
//! - [`monitor`]: per-sensor windows, baselines, flags, rate limiting, staleness; pure and
//!   synchronous, driven by decoded messages and a caller-supplied clock.
//! - [`service`]: the Zenoh layer, [`run`].
//!
//! Architecture invariant: everything but [`service`] is free of Zenoh, async and the clock, so
//! every decision can be tested with a scripted stream.
//!
//! Alerting is a separate service rather than a part of the gateway: it consumes only what any
//! client sees (PROTOCOL.md), it can watch many buildings at once, and a fault or restart in it
//! never touches the correction path.

pub mod config;
pub mod decision;
pub mod highpass;
pub mod monitor;
pub mod service;
pub mod sinefit;
pub mod stats;

pub use config::{Config, ConfigError};
pub use monitor::Monitor;
pub use service::{run, ServiceError};
