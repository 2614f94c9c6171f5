//! `triax-events`: each building's event report, from its corrected streams, with every value's
//! uncertainty and a decision.
//!
//! A consumer in the style of `triax-modes`: it follows each configured building's corrected
//! streams with [`triax_client::Fleet`] (late batches included), detects events
//! ([`building`], on `triax_strongmotion::detect`), reads each event's window back from the
//! gateway's history ([`gather`]), computes the report with `triax_strongmotion::event`
//! ([`report`]), signs it as alerts are signed and publishes it on
//! `triax/<building>/event/<id>` (PROTOCOL.md §3.11), writes its page, data and parameters
//! ([`html`], [`files`]), answers `triax/<building>/events` and the reports, and revises a
//! report when the first modes window after its event arrives. The mathematics is
//! `triax-strongmotion`'s; nothing here is mathematics.

pub mod building;
pub mod config;
pub mod files;
pub mod gather;
pub mod html;
pub mod report;
pub mod service;
pub mod state;

pub use config::{BuildingConfig, Config};
pub use service::{run, ServiceError};
