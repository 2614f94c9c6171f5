//! Known-truth tests of the health checks: simulated sensors calibrated by the simulated lab,
//! in a building with a temperature cycle and vibration, with faults injected at known times.
//!
//! - `detection`: each fault found, within its target, by the test meant to find it, and a
//!   healthy sensor left `ok` (compressed days, so that the default run stays short);
//! - `colocated`: a pair's gain ratio against the truth;
//! - `monte_carlo` (ignored: minutes in release): false-alarm rates over a thousand
//!   sensor-days, detection delays over real days, the absolute test's coverage over many
//!   calibrations, the run-length bounds, and the cost per sample. Each test's doc comment
//!   says how to run it.

mod colocated;
mod detection;
mod field;
mod monte_carlo;
mod util;
