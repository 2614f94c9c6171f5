//! Shared helpers: matching identified modes to the simulator's truth.

use nalgebra::Complex;
use triax_modal::sim::{SimBuilding, TrueMode};
use triax_modal::ssi::{mac, normalise};
use triax_modal::{Identification, Mode};

/// The identified mode closest to a true mode: best MAC among modes within 3 % in frequency.
pub fn find<'a>(
    building: &SimBuilding,
    identification: &'a Identification,
    truth: &TrueMode,
) -> Option<(&'a Mode, f64)> {
    let shape: Vec<Complex<f64>> = building
        .true_shape(truth, &identification.channels)
        .into_iter()
        .map(|v| Complex::new(v, 0.0))
        .collect();
    identification
        .modes
        .iter()
        .filter(|m| (m.frequency_hz.value - truth.frequency_hz).abs() < 0.03 * truth.frequency_hz)
        .map(|m| (m, mac(&m.shape_values(), &shape)))
        .max_by(|a, b| a.1.total_cmp(&b.1))
}

/// The true shape normalised like the mode's (its reference component is 1).
pub fn true_shape_like(
    building: &SimBuilding,
    identification: &Identification,
    truth: &TrueMode,
    mode: &Mode,
) -> Vec<Complex<f64>> {
    let shape: Vec<Complex<f64>> = building
        .true_shape(truth, &identification.channels)
        .into_iter()
        .map(|v| Complex::new(v, 0.0))
        .collect();
    normalise(&shape, mode.reference_component)
}
