//! Tests of `triax-strongmotion` against hand-computed values and known truth.
//!
//! - `parameters`: a sine of known amplitude and frequency, and a calibration whose only
//!   uncertainty is one gain or one cross-axis term: every parameter and its calibration part
//!   by hand; the noise parts against a Monte Carlo of the same record.

mod monte_carlo;
mod noise;
mod parameters;
mod util;
