//! Known-truth tests of the building-mode identification, in one binary.
//!
//! - `closed_form`: the simulator's modes against hand-computed ones, the model's validation,
//!   the uncertainty's parts against their formulas;
//! - `identification`: SSI-COV on simulated windows of the five-storey building against the
//!   frame's exact modes, with and without gaps;
//! - `tracking`: matching, the environmental baseline and the shift rule on synthetic series
//!   with a known false-alarm probability;
//! - `monte_carlo` (ignored: minutes in release): coverage of the stated intervals over 200
//!   windows, the cost of a 30-minute window, and a shift found under a temperature cycle.
//!   Run with `cargo test --release -p triax-modal --test modal -- --ignored --nocapture`.

mod buildings;
mod closed_form;
mod identification;
mod monte_carlo;
mod pyoma2;
mod shapes;
mod tracking;
mod util;
