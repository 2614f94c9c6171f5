//! `triax-modes`: the building's modes, window by window, from its corrected streams.
//!
//! A consumer in the style of `triax-alert`: it follows each configured building's corrected
//! streams with [`triax_client::Fleet`] (reading back from the gateway's history whatever it
//! missed, after a restart too, from the positions it saved), gathers them into windows on one
//! time grid ([`grid`]), identifies each window with [`triax_modal::identify`], tracks the
//! modes against temperature with [`triax_modal::ModeTracker`] ([`building`]), publishes each
//! window's result on `triax/<building>/modes` (PROTOCOL.md §3.10), appends it to its record
//! ([`record`]), and signs a `modal_shift` alert when a mode's frequency drops beyond what the
//! environment explains. The identification is `triax-modal`'s; nothing here is mathematics.

pub mod building;
pub mod config;
pub mod grid;
pub mod record;
pub mod service;

pub use building::{identify_window, Building, BuildingState, Outcome};
pub use config::{BuildingConfig, Config};
pub use grid::{ClosedWindow, Gatherer};
pub use service::{run, ServiceError, TemperatureReading};
