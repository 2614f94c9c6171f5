//! Coverage factors from Student's t distribution, for uncertainties whose variance was itself
//! estimated (JCGM 100, Annex G).
//!
//! An uncertainty `u` estimated with ν degrees of freedom gives an interval `y ± k·u` that
//! covers the true value with probability `p` only when `k` is the two-sided `p` quantile of
//! Student's t with ν degrees of freedom: 2.45 for ν = 6 at 95 %, where the normal
//! distribution says 1.96. Several contributions with their own ν combine into an effective
//! ν by the Welch–Satterthwaite formula ([`welch_satterthwaite`]); JCGM 100 G.4.1 then
//! truncates ν to the next lower integer, which this module does too.
//!
//! The quantile is computed exactly for integer ν: with `t = √ν·tan θ`, the density of θ is
//! proportional to `cos^(ν−1) θ`, so `P(|T| ≤ t) = ∫₀^θ cos^(ν−1) φ dφ / W(ν−1)` with `W` the
//! Wallis integral. Both integrals follow from one recurrence, and Newton's method on θ
//! converges from any start because the integral is increasing and concave in θ.
//!
//! The gateway needs `k` once per batch, so [`CoverageTable`] holds the factors on a grid of ν
//! computed once per coverage probability; a ν between grid points takes the factor of the
//! grid point below it, which overstates `k` (the safe side) by at most 0.5 %, and ν above
//! [`MAX_DOF`] is taken as [`MAX_DOF`], which overstates it by less than 0.02 %.

use std::sync::{Arc, Mutex, OnceLock};

/// Largest degrees of freedom the tables distinguish; more counts as this many.
pub const MAX_DOF: u32 = 10_000;

/// Distinct coverage probabilities whose tables are kept for sharing; a record asking for yet
/// another gets a table of its own, so that no sequence of records can grow the cache.
const MAX_SHARED_TABLES: usize = 64;

/// Coverage probability assumed when a record states none.
pub const DEFAULT_COVERAGE_PROBABILITY: f64 = 0.95;

/// The ν of [`CoverageTable`]: every integer to 30, then steps that keep neighbouring factors
/// within 0.5 % of each other.
const GRID: [u32; 58] = [
    1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15, 16, 17, 18, 19, 20, 21, 22, 23, 24, 25, 26,
    27, 28, 29, 30, 32, 34, 36, 38, 40, 45, 50, 55, 60, 70, 80, 90, 100, 120, 140, 160, 200, 250,
    300, 400, 500, 700, 1000, 1500, 2000, 3000, 5000, 10_000,
];

/// `∫₀^θ cos^n φ dφ` and the Wallis integral `∫₀^{π/2} cos^n φ dφ`, by the recurrence
/// `I_n = cos^(n−1)θ·sin θ / n + (n−1)/n · I_(n−2)`.
fn cos_power_integrals(n: u32, theta: f64) -> (f64, f64) {
    let (s, c) = theta.sin_cos();
    // Start from n = 0 or n = 1 according to parity.
    let (mut i, mut w, mut m, mut c_pow) = if n.is_multiple_of(2) {
        (theta, std::f64::consts::FRAC_PI_2, 0u32, 1.0)
    } else {
        (s, 1.0, 1u32, c)
    };
    // c_pow holds cos^m θ.
    while m < n {
        m += 2;
        let mf = f64::from(m);
        // cos^(m−1) θ = cos^(m−2) θ · cos θ.
        i = c_pow * c * s / mf + (mf - 1.0) / mf * i;
        w *= (mf - 1.0) / mf;
        c_pow *= c * c;
    }
    (i, w)
}

/// The two-sided `p` quantile of Student's t with `nu` degrees of freedom: the `t` with
/// `P(|T| ≤ t) = p`. `nu` at least 1, `p` in (0, 1).
pub fn t_quantile(nu: u32, p: f64) -> f64 {
    debug_assert!(nu >= 1 && p > 0.0 && p < 1.0);
    let n = nu.max(1) - 1;
    let (_, wallis) = cos_power_integrals(n, 0.0);
    let mut theta = std::f64::consts::FRAC_PI_4;
    for _ in 0..100 {
        let (integral, _) = cos_power_integrals(n, theta);
        let f = integral / wallis - p;
        let slope = theta.cos().powi(n as i32) / wallis;
        let step = f / slope;
        // Concave and increasing: every step lands left of the root or on it, never past π/2.
        theta = (theta - step).clamp(0.0, std::f64::consts::FRAC_PI_2 * (1.0 - 1e-15));
        if step.abs() <= 1e-15 * theta.max(1e-300) {
            break;
        }
    }
    f64::from(nu).sqrt() * theta.tan()
}

/// Effective degrees of freedom of `Σ u_i²` by Welch–Satterthwaite, from the variances and
/// the reciprocals of their degrees of freedom (0 for infinitely many): `(Σ u_i²)² / Σ u_i⁴/ν_i`.
/// Infinite when no contribution has finite ν.
pub fn welch_satterthwaite(parts: &[(f64, f64)]) -> f64 {
    let total: f64 = parts.iter().map(|(var, _)| var).sum();
    let denominator: f64 = parts.iter().map(|(var, inv)| var * var * inv).sum();
    if denominator > 0.0 {
        total * total / denominator
    } else {
        f64::INFINITY
    }
}

/// Coverage factors on a grid of ν for one coverage probability; cheap to look up.
#[derive(Debug, Clone, PartialEq)]
pub struct CoverageTable {
    probability: f64,
    factors: [f64; GRID.len()],
}

impl CoverageTable {
    /// The table for `probability`, shared between all callers that ask for the same one.
    pub fn shared(probability: f64) -> Arc<CoverageTable> {
        static TABLES: OnceLock<Mutex<Vec<Arc<CoverageTable>>>> = OnceLock::new();
        let tables = TABLES.get_or_init(|| Mutex::new(Vec::new()));
        // A poisoned lock only means another thread panicked while pushing: the list is intact.
        let mut tables = tables.lock().unwrap_or_else(|e| e.into_inner());
        if let Some(t) = tables.iter().find(|t| t.probability == probability) {
            return t.clone();
        }
        let table = Arc::new(CoverageTable {
            probability,
            factors: GRID.map(|nu| t_quantile(nu, probability)),
        });
        if tables.len() < MAX_SHARED_TABLES {
            tables.push(table.clone());
        }
        table
    }

    pub fn probability(&self) -> f64 {
        self.probability
    }

    /// `k` for `nu` effective degrees of freedom: the factor at the largest grid point not
    /// above `nu` (at ν = 1 below one degree of freedom).
    #[inline]
    pub fn factor(&self, nu: f64) -> f64 {
        let nu = if nu.is_nan() { 1.0 } else { nu };
        let index = GRID.partition_point(|&g| f64::from(g) <= nu);
        self.factors[index.saturating_sub(1)]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Two-sided 95 % and 99 % points from printed tables of Student's t.
    #[test]
    fn quantiles_match_printed_tables() {
        let table_95 = [
            (1, 12.706),
            (2, 4.303),
            (3, 3.182),
            (4, 2.776),
            (5, 2.571),
            (6, 2.447),
            (7, 2.365),
            (10, 2.228),
            (20, 2.086),
            (30, 2.042),
            (60, 2.000),
            (120, 1.980),
        ];
        for (nu, t) in table_95 {
            let got = t_quantile(nu, 0.95);
            assert!((got - t).abs() < 6e-4, "ν = {nu}: {got} against {t}");
        }
        for (nu, t) in [(1, 63.657), (5, 4.032), (6, 3.707), (30, 2.750)] {
            let got = t_quantile(nu, 0.99);
            assert!((got - t).abs() < 6e-4, "ν = {nu}: {got} against {t}");
        }
        // Large ν approaches the normal 1.959964.
        assert!((t_quantile(10_000, 0.95) - 1.959964).abs() < 4e-4);
        // Closed forms: ν = 1 is Cauchy, ν = 2 has t = p·√(2 / (1 − p²)).
        let p: f64 = 0.9545;
        assert!((t_quantile(1, p) - (std::f64::consts::FRAC_PI_2 * p).tan()).abs() < 1e-9);
        assert!((t_quantile(2, p) - p * (2.0 / (1.0 - p * p)).sqrt()).abs() < 1e-9);
    }

    /// An independent check of the distribution itself: T = Z / √(χ²_ν / ν) sampled directly.
    #[test]
    fn quantile_covers_what_sampled_t_variates_say() {
        use rand::{Rng, SeedableRng};
        use rand_distr::StandardNormal;
        let mut rng = rand::rngs::StdRng::seed_from_u64(7);
        for nu in [3u32, 6, 15] {
            let k = t_quantile(nu, 0.95);
            let n = 40_000;
            let inside = (0..n)
                .filter(|_| {
                    let z: f64 = rng.sample(StandardNormal);
                    let chi2: f64 = (0..nu)
                        .map(|_| rng.sample::<f64, _>(StandardNormal).powi(2))
                        .sum();
                    (z / (chi2 / f64::from(nu)).sqrt()).abs() <= k
                })
                .count();
            let share = inside as f64 / n as f64;
            // Binomial standard error at 40 000 draws is 0.0011.
            assert!((share - 0.95).abs() < 0.004, "ν = {nu}: {share}");
        }
    }

    #[test]
    fn table_rounds_down_to_the_safe_side() {
        let t = CoverageTable::shared(0.95);
        assert_eq!(t.factor(6.0), t_quantile(6, 0.95));
        assert_eq!(t.factor(6.9), t_quantile(6, 0.95));
        assert_eq!(t.factor(0.3), t_quantile(1, 0.95));
        assert_eq!(t.factor(f64::INFINITY), t_quantile(MAX_DOF, 0.95));
        for nu in [31.0, 47.0, 130.0, 650.0, 4000.0, 1e7] {
            let exact = t_quantile((nu as u32).min(MAX_DOF), 0.95);
            let k = t.factor(nu);
            assert!(
                k >= exact && k <= exact * 1.005,
                "ν = {nu}: {k} against {exact}"
            );
        }
        assert!(Arc::ptr_eq(&t, &CoverageTable::shared(0.95)));
    }

    #[test]
    fn welch_satterthwaite_by_hand() {
        // u₁² = 1 with ν = 6, u₂² = 1 with ν = ∞: ν = 2² / (1/6) = 24.
        assert_eq!(welch_satterthwaite(&[(1.0, 1.0 / 6.0), (1.0, 0.0)]), 24.0);
        // Equal parts with equal ν add their ν.
        assert!((welch_satterthwaite(&[(2.0, 0.1), (2.0, 0.1)]) - 20.0).abs() < 1e-12);
        assert_eq!(welch_satterthwaite(&[(1.0, 0.0)]), f64::INFINITY);
    }
}
