//! Calibration mathematics for three-axis accelerometers.
//!
//! The model is eq. (1) of D'Emilia, Gaspari, Natale, *Dynamic calibration uncertainty of
//! three-axis low frequency accelerometers*, Acta IMEKO 4(4), 2015:
//!
//! ```text
//! a = S⁻¹ · V + q
//! ```
//!
//! with `V` the sensor's three outputs, `S` the 3×3 sensitivity matrix (main sensitivities on the
//! diagonal, cross-sensitivities off it), `q` the offset in m/s² and `a` the specific force in
//! m/s². [`corrector`] applies a calibration record to samples with GUM uncertainty;
//! [`fit`] estimates `S` and `q` from bench data; [`sim`] makes bench data with known truth;
//! [`student`] turns degrees of freedom into coverage factors.
//!
//! Architecture invariant: this crate is pure. No I/O, no async, no clock: every time is passed
//! in, so that every function can be tested with no runtime, disk or network.

pub mod corrector;
pub mod fit;
pub mod sim;
pub mod student;
