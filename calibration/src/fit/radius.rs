//! Distance of the sensing element from the rotation axis, from spacer blocks (eqs. (4)–(8)).
//!
//! The sensor is moved outward by blocks of known thickness Δr and, for the same motion, a
//! quantity proportional to the acceleration at the sensor and free of offset is read (e.g.
//! the amplitude of the z output). Since that quantity is `k·(r₀ + Δr)`, a straight line
//! `y = m·Δr + b` gives `r₀ = b/m` (4), with the standard uncertainty
//! `s_r = √((s_b/m)² + (b·s_m/m²)²)` (5) and `s_b`, `s_m`, `s_V` from (6)–(8).

use super::FitError;

/// The fitted line and the radius, with Δr in millimetres as in the input.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RadiusFit {
    /// Slope m, output per mm.
    pub slope_per_mm: f64,
    /// Intercept b, output units.
    pub intercept: f64,
    /// s_V of eq. (8), output units.
    pub s_v: f64,
    /// s_m of eq. (7).
    pub s_slope_per_mm: f64,
    /// s_b of eq. (6).
    pub s_intercept: f64,
    /// r₀ = b/m.
    pub radius_m: f64,
    /// s_r of eq. (5).
    pub radius_uncertainty_m: f64,
    pub n_points: usize,
}

/// Fits eqs. (4)–(8) to the (Δr in mm, output) pairs.
pub fn fit_radius(points: &[(f64, f64)]) -> Result<RadiusFit, FitError> {
    let n = points.len();
    if n < 3 {
        return Err(FitError::Radius(format!(
            "{n} spacer position(s) given; at least 3 are needed to estimate the line and its \
             scatter (N − 2 degrees of freedom)"
        )));
    }
    if let Some(i) = points
        .iter()
        .position(|(d, y)| !d.is_finite() || !y.is_finite())
    {
        return Err(FitError::Radius(format!(
            "point {i}: value is not a finite number"
        )));
    }
    let nf = n as f64;
    let sum_d: f64 = points.iter().map(|p| p.0).sum();
    let sum_dd: f64 = points.iter().map(|p| p.0 * p.0).sum();
    let mean_d = sum_d / nf;
    let mean_y = points.iter().map(|p| p.1).sum::<f64>() / nf;
    // Centred sums for the line itself (better conditioned than the raw normal equations);
    // the paper's forms (6)–(7) use the raw ones, which are exact here.
    let sxx: f64 = points.iter().map(|p| (p.0 - mean_d).powi(2)).sum();
    let sxy: f64 = points.iter().map(|p| (p.0 - mean_d) * (p.1 - mean_y)).sum();
    if sxx <= 0.0 {
        return Err(FitError::Radius(
            "all spacer positions are equal: use blocks of different thickness".into(),
        ));
    }
    let slope = sxy / sxx;
    let intercept = mean_y - slope * mean_d;
    if slope == 0.0 {
        return Err(FitError::Radius(
            "the output does not change with the spacer thickness".into(),
        ));
    }
    let s_v2 = points
        .iter()
        .map(|p| (slope * p.0 + intercept - p.1).powi(2))
        .sum::<f64>()
        / (nf - 2.0);
    let denom = nf * sum_dd - sum_d * sum_d;
    let s_b2 = s_v2 * sum_dd / denom;
    let s_m2 = nf * s_v2 / denom;
    let r_mm = intercept / slope;
    let s_r_mm =
        ((s_b2.sqrt() / slope).powi(2) + (intercept / (slope * slope)).powi(2) * s_m2).sqrt();
    Ok(RadiusFit {
        slope_per_mm: slope,
        intercept,
        s_v: s_v2.sqrt(),
        s_slope_per_mm: s_m2.sqrt(),
        s_intercept: s_b2.sqrt(),
        radius_m: r_mm * 1e-3,
        radius_uncertainty_m: s_r_mm * 1e-3,
        n_points: n,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Hand-computed: y = 2·(100 + Δr) + e with e = (+1, −2, +1) at Δr = 0, 10, 20.
    /// The residual pattern is orthogonal to the line, so m = 2, b = 200, Σe² = 6 → s_V² = 6;
    /// NΣΔr² − (ΣΔr)² = 3·500 − 900 = 600; s_b² = 6·500/600 = 5; s_m² = 3·6/600 = 0.03;
    /// r = 100 mm; s_r² = 5/4 + (200/4)²·0.03 = 1.25 + 75 = 76.25.
    #[test]
    fn hand_computed_line() {
        let pts = [(0.0, 201.0), (10.0, 218.0), (20.0, 241.0)];
        let fit = fit_radius(&pts).unwrap();
        assert!((fit.slope_per_mm - 2.0).abs() < 1e-12);
        assert!((fit.intercept - 200.0).abs() < 1e-10);
        assert!((fit.s_v - 6f64.sqrt()).abs() < 1e-12);
        assert!((fit.s_intercept - 5f64.sqrt()).abs() < 1e-12);
        assert!((fit.s_slope_per_mm - 0.03f64.sqrt()).abs() < 1e-12);
        assert!((fit.radius_m - 0.1).abs() < 1e-12);
        assert!((fit.radius_uncertainty_m - 76.25f64.sqrt() * 1e-3).abs() < 1e-12);
    }

    #[test]
    fn too_few_and_constant_positions_are_refused() {
        assert!(fit_radius(&[(0.0, 1.0), (1.0, 2.0)])
            .unwrap_err()
            .to_string()
            .contains("at least 3"));
        assert!(fit_radius(&[(5.0, 1.0), (5.0, 2.0), (5.0, 3.0)])
            .unwrap_err()
            .to_string()
            .contains("different thickness"));
    }
}
