//! Shared helpers: matching identified modes to the simulator's truth.

use std::fmt::Write;

use nalgebra::Complex;
use triax_modal::sim::{SimBuilding, TrueMode};
use triax_modal::ssi::{mac, normalise};
use triax_modal::{Identification, Mode};

fn true_shape(
    building: &SimBuilding,
    identification: &Identification,
    truth: &TrueMode,
) -> Vec<Complex<f64>> {
    building
        .true_shape(truth, &identification.channels)
        .into_iter()
        .map(|v| Complex::new(v, 0.0))
        .collect()
}

/// The identified mode that is a true mode: best MAC among modes within 3 % in frequency.
pub fn find<'a>(
    building: &SimBuilding,
    identification: &'a Identification,
    truth: &TrueMode,
) -> Option<(&'a Mode, f64)> {
    let shape = true_shape(building, identification, truth);
    identification
        .modes
        .iter()
        .filter(|m| (m.frequency_hz.value - truth.frequency_hz).abs() < 0.03 * truth.frequency_hz)
        .map(|m| (m, mac(&m.shape_in_phase(), &shape)))
        .filter(|(_, mac)| *mac > 0.5)
        .max_by(|a, b| a.1.total_cmp(&b.1))
}

/// The true shape normalised like the mode's (its reference component is 1).
pub fn true_shape_like(
    building: &SimBuilding,
    identification: &Identification,
    truth: &TrueMode,
    mode: &Mode,
) -> Vec<Complex<f64>> {
    normalise(
        &true_shape(building, identification, truth),
        mode.reference_component,
    )
}

/// A table of the truth against what was found, for failing tests' output.
pub fn summary(
    building: &SimBuilding,
    identification: &Identification,
    temperature_c: f64,
) -> String {
    let mut out = String::new();
    for truth in building.frame.modes(temperature_c) {
        let _ = write!(
            out,
            "{:?}{} f {:.4} Hz ζ {:.4}: ",
            truth.direction, truth.number, truth.frequency_hz, truth.damping_ratio
        );
        match find(building, identification, &truth) {
            Some((m, mac)) => {
                let _ = writeln!(
                    out,
                    "{:.4} ± {:.4} Hz, ζ {:.4} ± {:.4}, MAC {:.4}",
                    m.frequency_hz.value,
                    m.frequency_hz.standard_uncertainty,
                    m.damping_ratio.value,
                    m.damping_ratio.standard_uncertainty,
                    mac
                );
            }
            None => {
                let _ = writeln!(out, "not found");
            }
        }
    }
    out
}

/// The 1 − MAC a shape's stated standard uncertainties lead one to expect: the in-phase
/// components' variances over the shape's squared norm.
pub fn expected_mac_loss(mode: &Mode) -> f64 {
    let variance: f64 = mode
        .shape
        .iter()
        .map(|c| c.real.standard_uncertainty.powi(2))
        .sum();
    let norm: f64 = mode.shape_in_phase().iter().map(|v| v.norm_sqr()).sum();
    variance / norm
}
