//! Strong motion in buildings, with stated uncertainty: what an event did to a building and how
//! sure the numbers are.
//!
//! - [`detect`]: STA/LTA and level triggers per sensor (with a guard band), and several
//!   sensors agreeing ([`detect::Coincidence`]), on the sensors' own time;
//! - [`filter`]: the zero-phase Butterworth band-pass every parameter is defined after, and
//!   its symmetric operator (what noise propagation rests on);
//! - [`oscillator`]: the 5 %-damped oscillator, exact for input linear between samples
//!   (Nigam & Jennings);
//! - [`process`]: a sensor's record baseline-corrected, band-passed, in the building frame,
//!   integrated, with the first-order error model of its calibration (the nine sensitivities'
//!   covariance) and its noise;
//! - [`parameters`]: per sensor and building direction PGA, PGV, PGD, Arias intensity, CAV,
//!   D5–95, PSA at the standard periods, RotD50/RotD100, each an [`estimate::Estimate`]
//!   (value, standard uncertainty, ν, `k`, coverage); [`peaks`]: peaks of sampled records and
//!   SIMEX for peaks with rivals;
//! - [`drift`]: inter-storey drift ratios with a bound on what the band-pass loses;
//!   [`tilt`]: residual tilt from quiet stretches before and after;
//! - [`decision`]: the guard band (`below`, `possible`, `exceeded`) with a stated false
//!   `exceeded` probability, and the building's tag; [`din4150`]: DIN 4150-3's curves;
//! - [`event`]: all of it for one building's event, and its limits judged;
//! - [`sim`]: a shear frame whose response to a synthetic ground motion is exact, and sensors
//!   with calibration errors, clock offsets and noise: known truth for the Monte Carlo.
//!
//! **Figures** (`tests/strongmotion/monte_carlo.rs`, BENCHMARKS.md): over simulated events of
//! a six-storey frame seen by six sensors, every kind of parameter's truth inside its stated
//! 95 % interval in 93–97 % of cases; `exceeded` with the truth at a limit 2.5 % of the time or
//! less.
//!
//! Architecture invariant: pure. No I/O, no async, no clock: times are the records' own,
//! relative to an instant the caller chooses. Every random draw (the simulator's, the peaks'
//! bootstrap) comes from [`rng::Rng`] with a seed the caller gives, so an analysis is
//! reproducible bit for bit.

pub mod decision;
pub mod detect;
pub mod din4150;
pub mod drift;
pub mod estimate;
pub mod event;
pub mod filter;
pub mod oscillator;
pub mod parameters;
pub mod peaks;
pub mod process;
pub mod rng;
pub mod sim;
pub mod tilt;
