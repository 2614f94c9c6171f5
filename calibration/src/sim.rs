//! Bench simulator.
