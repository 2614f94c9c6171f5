//! The paper's comparison tables, computed on any bench data.
//!
//! - Table 1: RMS of (corrected − reference) per axis as a function of the number of points
//!   per cycle `n`.
//! - Tables 2 and 3: the same RMS for the dynamic and for the static calibration on the same
//!   dynamic data, absolute and relative to the amplitude.
//! - Reference methods against each other: RMS of the difference between each pair of
//!   reference estimates, and the RMS each method's own fit leaves.
//!
//! Every RMS is over all samples where the reference is valid, not only the calibration
//! points, as the paper evaluates "during the oscillation period".

use nalgebra::Vector3;

use super::dynamic::{fit_with, Bench, Prepared, Recording};
use super::reference::ReferenceMethod;
use super::{rms, Calibration, FitError};

/// One row of Table 1.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PointsRow {
    pub points_per_cycle: usize,
    pub rms_mps2: Vector3<f64>,
}

/// Table 1 for the bench's reference method.
pub fn rms_vs_points(
    bench: &Bench,
    recordings: &[Recording],
    points: &[usize],
) -> Result<Vec<PointsRow>, FitError> {
    points
        .iter()
        .map(|&n| {
            let fit = fit_with(bench, recordings, bench.reference, n)?;
            Ok(PointsRow {
                points_per_cycle: n,
                rms_mps2: fit.residual_rms_mps2,
            })
        })
        .collect()
}

/// An RMS figure, absolute and relative to the amplitude (half peak-to-peak of the reference).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RmsFigure {
    pub rms_mps2: Vector3<f64>,
    pub relative: Vector3<f64>,
}

/// RMS of (corrected by `calibration` − reference) over the valid samples of the prepared
/// recordings (Tables 2 and 3).
pub fn rms_against_reference(
    calibration: &Calibration,
    recordings: &[Recording],
    prepared: &[Prepared],
) -> RmsFigure {
    let rms_mps2 = rms(recordings.iter().zip(prepared).flat_map(|(rec, prep)| {
        prep.valid()
            .map(|i| calibration.correct(&rec.output[i]) - prep.reference_mps2[i])
    }));
    let mut lo = Vector3::repeat(f64::INFINITY);
    let mut hi = Vector3::repeat(f64::NEG_INFINITY);
    let mut amplitude = Vector3::zeros();
    for prep in prepared {
        for a in &prep.reference_mps2[prep.valid()] {
            lo = lo.inf(a);
            hi = hi.sup(a);
        }
        amplitude += (hi - lo) * 0.5;
        lo = Vector3::repeat(f64::INFINITY);
        hi = Vector3::repeat(f64::NEG_INFINITY);
    }
    amplitude /= prepared.len().max(1) as f64;
    RmsFigure {
        rms_mps2,
        relative: rms_mps2.zip_map(&amplitude, |r, a| if a > 0.0 { r / a } else { 0.0 }),
    }
}

/// The reference methods compared with each other on the same recordings.
#[derive(Debug, Clone)]
pub struct ReferenceComparison {
    pub methods: Vec<ReferenceMethod>,
    /// `pairwise_rms_mps2[i][j]`: RMS of (reference by i − reference by j) over the samples
    /// valid for both.
    pub pairwise_rms_mps2: Vec<Vec<Vector3<f64>>>,
    /// RMS of (corrected − own reference) of each method's own fit.
    pub fit_rms_mps2: Vec<Vector3<f64>>,
    /// Each method's calibration.
    pub calibrations: Vec<Calibration>,
}

/// Fits with every reference method and compares them.
pub fn compare_references(
    bench: &Bench,
    recordings: &[Recording],
) -> Result<ReferenceComparison, FitError> {
    let methods: Vec<_> = ReferenceMethod::ALL.to_vec();
    let fits = methods
        .iter()
        .map(|&m| fit_with(bench, recordings, m, bench.points_per_cycle))
        .collect::<Result<Vec<_>, _>>()?;
    let mut pairwise = vec![vec![Vector3::zeros(); methods.len()]; methods.len()];
    for i in 0..fits.len() {
        for j in 0..fits.len() {
            if i == j {
                continue;
            }
            pairwise[i][j] =
                rms(fits[i]
                    .prepared
                    .iter()
                    .zip(&fits[j].prepared)
                    .flat_map(|(a, b)| {
                        let lo = a.valid().start.max(b.valid().start);
                        let hi = a.valid().end.min(b.valid().end);
                        (lo..hi).map(move |k| a.reference_mps2[k] - b.reference_mps2[k])
                    }));
        }
    }
    Ok(ReferenceComparison {
        methods,
        pairwise_rms_mps2: pairwise,
        fit_rms_mps2: fits.iter().map(|f| f.residual_rms_mps2).collect(),
        calibrations: fits.into_iter().map(|f| f.calibration).collect(),
    })
}
