//! The uncertainty of each identified parameter: the statistical part by a delete-one-block
//! jackknife, the measurement chain's part by first-order propagation into the shapes.
//!
//! **Statistical.** The window is cut into `nb` blocks (12 by default, at least 10) and the
//! correlations are kept per block ([`crate::ssi::Correlations`]). Replicate `j` is the whole
//! identification at the mode's own model order on the correlations of every block but `j`,
//! and the mode is found in it by frequency and MAC. The jackknife variance
//! `(nb−1)/nb · Σ (θ_j − θ̄)²` has `nb − 1` degrees of freedom, and the coverage factor is
//! Student's `t` at `nb − 1`.
//!
//! Why this resampling: an SSI estimate is a smooth function of the correlation matrices, and
//! those are means over the window, nearly means over its blocks; for such a function the
//! jackknife variance is asymptotically the first-order (delta-method) variance with the
//! blocks' sample covariance, which is what Reynders, Pintelon & De Roeck (MSSP 22, 2008)
//! propagate analytically. Blocks are minutes long, a building's correlation time a few seconds
//! (`1/(2π·ζ·f)`: 8 s at 1 Hz and 2 %), so blocks are nearly independent. Each replicate uses
//! eleven twelfths of the data, not a twelfth: identifying short blocks separately would bias
//! damping (a few hundred cycles per block) and lose weak modes, and the spread of short-block
//! estimates would then describe a different estimator than the one reported.
//!
//! **Measurement chain.** A corrected sample is still off by the calibration's residual error:
//! each axis's gain by a relative `δg` (standard uncertainty `gain_relative_u`), each of the
//! six cross-axis terms by `ε` (`cross_axis_u`); and a node's time stamps are off the others' by
//! `δt` (`timestamp_u_s`). A mode seen through sensor `s` is `φ_s = R_s·(I + E_s)·R_sᵀ·φ_true`
//! and, delayed by `δt`, turned in phase by `2π·f·δt`. None of these moves a frequency or a
//! damping ratio (they scale or delay whole channels, which the poles do not see); each moves
//! the shape. The shape's sensitivity to each source is taken by perturbing the estimated
//! shape by one standard uncertainty of that source and normalising again (first order, exact
//! for the normalisation), and the sources' contributions add in quadrature: they are
//! independent sensors and axes. A source of the reference component moves every other
//! component, since all are ratios to it.
//!
//! **Combined.** For shape components, `u² = u_stat² + u_chain²` with Welch–Satterthwaite
//! degrees of freedom (`nb − 1` for the statistical part, the records' `dof` for the chain's)
//! and `k` from Student's `t` at them, rounded down.

use nalgebra::{Complex, Matrix3, Vector3};
use serde::{Deserialize, Serialize};
use triax_calibration::student::{t_quantile, welch_satterthwaite};

use crate::window::Channels;

/// A value with its standard uncertainty, degrees of freedom and the coverage interval it
/// claims: `value ± coverage_factor · standard_uncertainty` contains the true value with
/// probability `coverage_probability`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Estimate {
    pub value: f64,
    pub standard_uncertainty: f64,
    pub dof: f64,
    pub coverage_factor: f64,
    pub coverage_probability: f64,
}

/// Degrees of freedom beyond which Student's t is the normal distribution to 10⁻⁴.
const NU_NORMAL: f64 = 10_000.0;

/// Student's `t` coverage factor for `dof` degrees of freedom (rounded down, never up, so the
/// interval is at least as wide as it should be).
pub fn coverage_factor(dof: f64, probability: f64) -> f64 {
    let nu = if dof.is_finite() {
        dof.clamp(1.0, NU_NORMAL)
    } else {
        NU_NORMAL
    };
    t_quantile(nu.floor() as u32, probability)
}

impl Estimate {
    pub fn new(value: f64, standard_uncertainty: f64, dof: f64, probability: f64) -> Estimate {
        Estimate {
            value,
            standard_uncertainty,
            dof,
            coverage_factor: coverage_factor(dof, probability),
            coverage_probability: probability,
        }
    }

    /// Half-width of the coverage interval.
    pub fn expanded_uncertainty(&self) -> f64 {
        self.coverage_factor * self.standard_uncertainty
    }

    /// Whether `truth` is inside the coverage interval.
    pub fn covers(&self, truth: f64) -> bool {
        (truth - self.value).abs() <= self.expanded_uncertainty()
    }
}

/// Jackknife mean and variance of replicates `θ_j` (`(m−1)/m · Σ (θ_j − θ̄)²`).
pub fn jackknife_variance(replicates: &[f64]) -> f64 {
    let m = replicates.len() as f64;
    if m < 2.0 {
        return f64::NAN;
    }
    let mean = replicates.iter().sum::<f64>() / m;
    (m - 1.0) / m * replicates.iter().map(|x| (x - mean).powi(2)).sum::<f64>()
}

/// Variance of each shape component's real and imaginary parts from the measurement chain,
/// and the smallest degrees of freedom among the records that moved it: `(var_re, var_im, ν)`
/// per channel. Giving the chain's whole variance the smallest ν of its sources understates
/// its Welch–Satterthwaite degrees of freedom, so the coverage factor errs wide.
///
/// `shape` is the raw (unnormalised) estimate on `channels`' channels; `reference` is the
/// component the reported shape is normalised to; `frequency_hz` turns time-stamp errors into
/// phase.
pub fn chain_variances(
    channels: &Channels,
    shape: &[Complex<f64>],
    reference: usize,
    frequency_hz: f64,
) -> Vec<(f64, f64, f64)> {
    let base = crate::ssi::normalise(shape, reference);
    let mut out = vec![(0.0, 0.0, f64::INFINITY); shape.len()];
    let mut add = |perturbed: &[Complex<f64>], dof: f64| {
        let moved = crate::ssi::normalise(perturbed, reference);
        for (c, (m, b)) in moved.iter().zip(&base).enumerate() {
            let d = m - b;
            let (re, im) = (d.re * d.re, d.im * d.im);
            out[c].0 += re;
            out[c].1 += im;
            if re + im > 0.0 {
                out[c].2 = out[c].2.min(dof);
            }
        }
    };
    let sensors: Vec<usize> = {
        let mut s = channels.sensor_index.clone();
        s.sort_unstable();
        s.dedup();
        s
    };
    for &sensor in &sensors {
        let chain = channels.chains[sensor];
        let r: Matrix3<f64> = channels.rotations[sensor];
        let own: Vec<usize> = (0..channels.ids.len())
            .filter(|&c| channels.sensor_index[c] == sensor)
            .collect();
        // The motion at the sensor in the building frame; directions that are not channels
        // (the vertical, for a sway mode) are taken as still.
        let mut building = [Complex::new(0.0, 0.0); 3];
        for &c in &own {
            building[channels.ids[c].direction.index()] = shape[c];
        }
        let rt = r.transpose();
        let sensor_axes: Vec<Complex<f64>> = (0..3)
            .map(|j| (0..3).map(|k| building[k] * rt[(j, k)]).sum())
            .collect();
        let perturb = |axis: usize, amount: Complex<f64>| {
            // δa = amount along sensor axis `axis`, seen in the building frame.
            let column: Vector3<f64> = r.column(axis).into_owned();
            let mut p = shape.to_vec();
            for &c in &own {
                p[c] += amount * column[channels.ids[c].direction.index()];
            }
            p
        };
        for axis in 0..3 {
            let u = chain.gain_relative_u[axis];
            if u > 0.0 {
                add(&perturb(axis, sensor_axes[axis] * u), chain.dof);
            }
            if chain.cross_axis_u > 0.0 {
                for (other, &value) in sensor_axes.iter().enumerate() {
                    if other != axis {
                        add(&perturb(axis, value * chain.cross_axis_u), chain.dof);
                    }
                }
            }
        }
        if chain.timestamp_u_s > 0.0 {
            let turn = Complex::from_polar(
                1.0,
                2.0 * std::f64::consts::PI * frequency_hz * chain.timestamp_u_s,
            );
            let mut p = shape.to_vec();
            for &c in &own {
                p[c] *= turn;
            }
            add(&p, chain.dof);
        }
    }
    out
}

/// Combines a statistical and a chain variance into an estimate (Welch–Satterthwaite).
pub fn combine(
    value: f64,
    statistical_variance: f64,
    statistical_dof: f64,
    chain_variance: f64,
    chain_dof: f64,
    probability: f64,
) -> Estimate {
    let inverse = |nu: f64| {
        if nu.is_finite() && nu > 0.0 {
            1.0 / nu
        } else {
            0.0
        }
    };
    let nu = welch_satterthwaite(&[
        (statistical_variance, inverse(statistical_dof)),
        (chain_variance, inverse(chain_dof)),
    ]);
    Estimate::new(
        value,
        (statistical_variance + chain_variance).sqrt(),
        nu,
        probability,
    )
}
