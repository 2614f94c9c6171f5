//! Strong motion in buildings, with stated uncertainty.
pub mod decision;
pub mod detect;
pub mod din4150;
pub mod estimate;
pub mod filter;
pub mod oscillator;
pub mod parameters;
pub mod peaks;
pub mod process;
pub mod rng;
