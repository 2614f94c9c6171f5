//! A value with its standard uncertainty, its degrees of freedom and the interval it claims, and
//! the budget that makes one from independent contributions (JCGM 100: variances add, degrees of
//! freedom by Welch–Satterthwaite, `k` from Student's t at the truncated ν).

use triax_calibration::student::{t_quantile, CoverageTable, MAX_DOF};

/// Probability the intervals claim unless configured otherwise.
pub const DEFAULT_COVERAGE_PROBABILITY: f64 = 0.95;

/// `value ± coverage_factor · standard_uncertainty` holds the truth with probability
/// `coverage_probability`; `dof` is infinite when every contribution is known exactly.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Estimate {
    pub value: f64,
    pub standard_uncertainty: f64,
    pub dof: f64,
    pub coverage_factor: f64,
    pub coverage_probability: f64,
}

impl Estimate {
    /// An estimate with no uncertainty at all (a count, a configured constant).
    pub fn exact(value: f64, coverage_probability: f64) -> Estimate {
        Estimate {
            value,
            standard_uncertainty: 0.0,
            dof: f64::INFINITY,
            coverage_factor: coverage_factor(f64::INFINITY, coverage_probability),
            coverage_probability,
        }
    }

    /// Lower end of the interval.
    pub fn lower(&self) -> f64 {
        self.value - self.coverage_factor * self.standard_uncertainty
    }

    /// Upper end of the interval.
    pub fn upper(&self) -> f64 {
        self.value + self.coverage_factor * self.standard_uncertainty
    }

    /// Whether `truth` lies in the interval.
    pub fn covers(&self, truth: f64) -> bool {
        (self.lower()..=self.upper()).contains(&truth)
    }

    /// The same estimate scaled by `factor` (a change of unit).
    pub fn scaled(&self, factor: f64) -> Estimate {
        Estimate {
            value: self.value * factor,
            standard_uncertainty: self.standard_uncertainty * factor.abs(),
            ..*self
        }
    }
}

/// The two-sided coverage factor at `nu` degrees of freedom: Student's t at ν truncated to the
/// integer below (JCGM 100 G.4.1) and further down to the calibration crate's grid of ν
/// (`CoverageTable`: every integer to 30, then steps that raise `k` by at most 0.5 %), ν above
/// [`MAX_DOF`] or infinite taken as [`MAX_DOF`]. The table is computed once per probability.
pub fn coverage_factor(nu: f64, probability: f64) -> f64 {
    let nu = if nu.is_nan() { 1.0 } else { nu };
    CoverageTable::shared(probability).factor(nu.max(1.0))
}

/// [`coverage_factor`] without the grid: Student's t at ν truncated to the integer below.
pub fn exact_coverage_factor(nu: f64, probability: f64) -> f64 {
    let nu = if nu.is_nan() || nu < 1.0 {
        1
    } else if nu >= f64::from(MAX_DOF) {
        MAX_DOF
    } else {
        nu.floor() as u32
    };
    t_quantile(nu, probability)
}

/// The one-sided factor with `P(T > k) = alpha` at `nu` degrees of freedom.
pub fn one_sided_factor(nu: f64, alpha: f64) -> f64 {
    exact_coverage_factor(nu, 1.0 - 2.0 * alpha)
}

/// Independent contributions to one quantity's variance, each with its degrees of freedom.
#[derive(Debug, Clone, Default)]
pub struct Budget {
    parts: Vec<(f64, f64)>,
}

impl Budget {
    pub fn new() -> Budget {
        Budget::default()
    }

    /// Adds a variance with `dof` degrees of freedom (infinite: known exactly).
    pub fn add(&mut self, variance: f64, dof: f64) -> &mut Budget {
        if variance > 0.0 && variance.is_finite() {
            self.parts.push((variance, dof));
        } else if !variance.is_finite() {
            self.parts.push((f64::INFINITY, dof));
        }
        self
    }

    pub fn variance(&self) -> f64 {
        // A fold from +0: an empty budget is 0, not the −0 an empty `sum` gives.
        self.parts.iter().fold(0.0, |total, (v, _)| total + v)
    }

    /// Welch–Satterthwaite: `(Σ u²)² / Σ u⁴/ν`, infinite when no part has finite ν.
    pub fn dof(&self) -> f64 {
        let total = self.variance();
        let denominator: f64 = self
            .parts
            .iter()
            .filter(|(_, nu)| nu.is_finite())
            .map(|(v, nu)| v * v / nu)
            .sum();
        if denominator > 0.0 {
            total * total / denominator
        } else {
            f64::INFINITY
        }
    }

    /// The estimate of `value` with this budget's uncertainty.
    pub fn estimate(&self, value: f64, coverage_probability: f64) -> Estimate {
        let dof = self.dof();
        Estimate {
            value,
            standard_uncertainty: self.variance().sqrt(),
            dof,
            coverage_factor: coverage_factor(dof, coverage_probability),
            coverage_probability,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn welch_satterthwaite_by_hand() {
        // PROTOCOL.md §3.1's worked example: 1e-4 at ν = 6 and 1e-4 at ν = 200.
        let mut b = Budget::new();
        b.add(1e-4, 6.0).add(1e-4, 200.0);
        let e = b.estimate(1.0, 0.95);
        assert!((e.standard_uncertainty - 0.014_142_1).abs() < 1e-6);
        assert!((e.dof - 23.30).abs() < 0.01, "{}", e.dof);
        assert!(
            (e.coverage_factor - 2.069).abs() < 1e-3,
            "{}",
            e.coverage_factor
        );
        let exact = Budget::new().add(4.0, f64::INFINITY).estimate(0.0, 0.95);
        assert!(exact.dof.is_infinite());
        assert!((exact.coverage_factor - 1.960).abs() < 1e-3);
        assert!((exact.upper() - 3.92).abs() < 0.01 && exact.covers(-3.9));
        assert!((one_sided_factor(f64::INFINITY, 0.025) - 1.960).abs() < 1e-3);
        assert!((one_sided_factor(f64::INFINITY, 0.05) - 1.645).abs() < 1e-3);
    }
}
