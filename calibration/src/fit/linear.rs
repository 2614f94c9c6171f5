//! The least-squares core shared by the static and the dynamic fit.
//!
//! Solves `V_i = S·a_i + c` for all pairs at once. Row `j` of the system is the same design
//! `[a_x a_y a_z 1]` for every output axis, so the problem is a multivariate regression with a
//! single N×4 design matrix `X`: `B = X⁺·Y` with `B` 4×3 (`B[l][j] = S_jl`, `B[3][j] = c_j`).
//! `X` is decomposed by SVD after scaling its columns to unit norm, which both keeps the
//! solution accurate and makes the rank test (smallest over largest singular value) independent
//! of units.
//!
//! Covariance: with `Σ` the 3×3 covariance of the output residuals (estimated from the residuals
//! with N−4 degrees of freedom, so correlated noise between channels is kept),
//! `Cov(B_{·j}, B_{·k}) = Σ_jk·(XᵀX)⁻¹`. It is then mapped to (S, q) with the Jacobian of
//! `q = −S⁻¹·c`: `dq = −S⁻¹·(dS·q + dc)`.

use nalgebra::{DMatrix, Matrix3, Matrix4, SMatrix, Vector3, Vector4};

use super::{Calibration, FitError, ParameterCovariance};

/// Ratio of smallest to largest singular value (of the column-scaled design) below which the
/// references are taken to lie in a plane. Exact degeneracy (one mount angle, coplanar
/// orientations) gives ratios near 1e-16; any real spread gives more than 1e-4.
const RANK_TOLERANCE: f64 = 1e-8;

/// The result of one affine least-squares fit.
#[derive(Debug, Clone)]
pub(crate) struct AffineFit {
    pub calibration: Calibration,
    /// Residual covariance of the outputs, output units².
    pub residual_cov: Matrix3<f64>,
    /// Degrees of freedom of the residuals (N − 4).
    pub dof: usize,
    /// `(XᵀX)⁻¹` of the design `[a_x a_y a_z 1]`, for leverages and for
    /// [`parameter_covariance`] with another residual covariance.
    pub gram_inv: Matrix4<f64>,
}

/// Why the design could not be solved.
#[derive(Debug, Clone, PartialEq)]
pub(crate) enum AffineFailure {
    TooFew(usize),
    /// The references satisfy `normal·a = level`; `normal` has unit length.
    Degenerate {
        normal: Vector3<f64>,
        level: f64,
    },
    Singular,
}

impl From<AffineFailure> for FitError {
    fn from(failure: AffineFailure) -> Self {
        match failure {
            AffineFailure::TooFew(found) => FitError::TooFewOrientations { found },
            AffineFailure::Degenerate { normal, level } => FitError::ReferencesDegenerate {
                normal_x: normal.x,
                normal_y: normal.y,
                normal_z: normal.z,
                level_mps2: level,
            },
            AffineFailure::Singular => FitError::SingularSensitivity,
        }
    }
}

/// Fits `V = S·a + c` to the pairs `(references[i], outputs[i])`.
///
/// `noise_prior` replaces the residual covariance when there are no residual degrees of freedom
/// (exactly four pairs); without it the covariance is then zero.
pub(crate) fn fit_affine(
    references: &[Vector3<f64>],
    outputs: &[Vector3<f64>],
    noise_prior: Option<Matrix3<f64>>,
) -> Result<AffineFit, AffineFailure> {
    debug_assert_eq!(references.len(), outputs.len());
    let n = references.len();
    if n < 4 {
        return Err(AffineFailure::TooFew(n));
    }
    let mut design = DMatrix::<f64>::zeros(n, 4);
    let mut targets = DMatrix::<f64>::zeros(n, 3);
    for (row, (a, v)) in references.iter().zip(outputs).enumerate() {
        design[(row, 0)] = a.x;
        design[(row, 1)] = a.y;
        design[(row, 2)] = a.z;
        design[(row, 3)] = 1.0;
        targets[(row, 0)] = v.x;
        targets[(row, 1)] = v.y;
        targets[(row, 2)] = v.z;
    }
    let mut scale = Vector4::zeros();
    for col in 0..4 {
        let norm = design.column(col).norm();
        // A zero column (an axis never excited) is caught by the rank test below.
        scale[col] = if norm > 0.0 { 1.0 / norm } else { 1.0 };
        design.column_mut(col).scale_mut(scale[col]);
    }
    let svd = design.svd(true, true);
    let sigma = &svd.singular_values;
    let sigma_max = sigma.max();
    let (min_index, sigma_min) = sigma.argmin();
    // Both factors were requested from `svd` above, so they are present.
    let u = svd.u.as_ref().expect("u requested");
    let v_t = svd.v_t.as_ref().expect("v_t requested");
    if sigma_max.is_nan() || sigma_max <= 0.0 || sigma_min / sigma_max < RANK_TOLERANCE {
        // The null vector w (in unscaled units) satisfies X·w ≈ 0: w_xyz·a + w_1 = 0.
        let w_scaled = v_t.row(min_index).transpose();
        let w = w_scaled.component_mul(&DMatrix::from_column_slice(4, 1, scale.as_slice()));
        let normal = Vector3::new(w[0], w[1], w[2]);
        let norm = normal.norm();
        let (normal, level) = if norm > 0.0 {
            (normal / norm, -w[3] / norm)
        } else {
            (Vector3::zeros(), 0.0)
        };
        return Err(AffineFailure::Degenerate { normal, level });
    }
    // B' = V·Σ⁻¹·Uᵀ·Y in scaled units, then B = D·B'.
    let uty = u.transpose() * &targets;
    let mut coeffs_scaled = DMatrix::<f64>::zeros(4, 3);
    for k in 0..4 {
        let row = uty.row(k) / sigma[k];
        for l in 0..4 {
            for j in 0..3 {
                coeffs_scaled[(l, j)] += v_t[(k, l)] * row[j];
            }
        }
    }
    let mut gram_inv = Matrix4::<f64>::zeros();
    for l in 0..4 {
        for m in 0..4 {
            let mut acc = 0.0;
            for k in 0..4 {
                acc += v_t[(k, l)] * v_t[(k, m)] / (sigma[k] * sigma[k]);
            }
            gram_inv[(l, m)] = acc * scale[l] * scale[m];
        }
    }
    let mut sensitivity = Matrix3::zeros();
    let mut c = Vector3::zeros();
    for j in 0..3 {
        for l in 0..3 {
            sensitivity[(j, l)] = coeffs_scaled[(l, j)] * scale[l];
        }
        c[j] = coeffs_scaled[(3, j)] * scale[3];
    }
    let sensitivity_inv = sensitivity.try_inverse().ok_or(AffineFailure::Singular)?;
    let offset = -(sensitivity_inv * c);

    let mut residual_sum = Matrix3::zeros();
    for (a, v) in references.iter().zip(outputs) {
        let r = v - (sensitivity * a + c);
        residual_sum += r * r.transpose();
    }
    let dof = n - 4;
    let residual_cov = if dof > 0 {
        residual_sum / dof as f64
    } else {
        noise_prior.unwrap_or_else(Matrix3::zeros)
    };

    let cov = parameter_covariance(&residual_cov, &gram_inv, &sensitivity_inv, &offset);
    let calibration =
        Calibration::new(sensitivity, offset, cov).map_err(|_| AffineFailure::Singular)?;
    Ok(AffineFit {
        calibration,
        residual_cov,
        dof,
        gram_inv,
    })
}

/// Covariance of (S row-major, q) from the residual covariance of the outputs: that of
/// `(S, c)` is `Σ ⊗ (XᵀX)⁻¹`, mapped through the Jacobian of `q = −S⁻¹·c`.
pub(crate) fn parameter_covariance(
    residual_cov: &Matrix3<f64>,
    gram_inv: &Matrix4<f64>,
    sensitivity_inv: &Matrix3<f64>,
    offset: &Vector3<f64>,
) -> ParameterCovariance {
    parameter_covariance_of(&[(*residual_cov, *gram_inv)], sensitivity_inv, offset)
}

/// The general form: the covariance of `(S, c)` is `Σ_t Σ_t ⊗ W_t` over `terms` `(Σ_t, W_t)`.
/// Homoscedastic residuals are the single term `(Σ, (XᵀX)⁻¹)`; residuals whose covariance
/// `Σ_j` differs by row are the sandwich, one term `(Σ_j, G·x_j·x_jᵀ·G)` per row with
/// `G = (XᵀX)⁻¹`.
pub(crate) fn parameter_covariance_of(
    terms: &[(Matrix3<f64>, Matrix4<f64>)],
    sensitivity_inv: &Matrix3<f64>,
    offset: &Vector3<f64>,
) -> ParameterCovariance {
    // Covariance of θ = (S row-major, c).
    let index = |axis: usize, coeff: usize| {
        if coeff < 3 {
            3 * axis + coeff
        } else {
            9 + axis
        }
    };
    let mut cov_sc = ParameterCovariance::zeros();
    for (sigma, weight) in terms {
        for j in 0..3 {
            for k in 0..3 {
                for l in 0..4 {
                    for m in 0..4 {
                        cov_sc[(index(j, l), index(k, m))] += sigma[(j, k)] * weight[(l, m)];
                    }
                }
            }
        }
    }
    // Jacobian of (S, q) with respect to (S, c).
    let mut jac = SMatrix::<f64, 12, 12>::zeros();
    for p in 0..9 {
        jac[(p, p)] = 1.0;
    }
    for m in 0..3 {
        for i in 0..3 {
            for k in 0..3 {
                jac[(9 + m, 3 * i + k)] = -sensitivity_inv[(m, i)] * offset[k];
            }
            jac[(9 + m, 9 + i)] = -sensitivity_inv[(m, i)];
        }
    }
    let cov = jac * cov_sc * jac.transpose();
    (cov + cov.transpose()) * 0.5
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Four orientations along the axes and one diagonal, exact outputs: the fit must
    /// return the generating S and q to rounding, with zero residual covariance.
    #[test]
    fn exact_data_gives_exact_parameters() {
        let s = Matrix3::new(0.1, 0.002, -0.001, 0.003, 0.098, 0.0, -0.002, 0.001, 0.102);
        let q = Vector3::new(0.3, -0.2, 0.5);
        let refs = [
            Vector3::new(9.8, 0.0, 0.0),
            Vector3::new(0.0, 9.8, 0.0),
            Vector3::new(0.0, 0.0, 9.8),
            Vector3::new(-5.658, -5.658, -5.658),
            Vector3::new(0.0, 0.0, -9.8),
        ];
        let outs: Vec<_> = refs.iter().map(|a| s * (a - q)).collect();
        let fit = fit_affine(&refs, &outs, None).unwrap();
        assert!((fit.calibration.sensitivity() - s).amax() < 1e-12);
        assert!((fit.calibration.offset_mps2() - q).amax() < 1e-9);
        assert!(fit.residual_cov.amax() < 1e-20);
    }

    /// Hand-computed case: the six ±g orientations, S = identity, q = 0, and an error on V_x
    /// that is orthogonal to every design column, so the estimate stays exact while the
    /// residual variance and the covariance follow in closed form.
    #[test]
    fn covariance_matches_closed_form() {
        // Design: a ∈ {±g e_x, ±g e_y, ±g e_z}; XᵀX = diag(2g², 2g², 2g², 6).
        let g = 10.0;
        let refs = [
            Vector3::new(g, 0.0, 0.0),
            Vector3::new(-g, 0.0, 0.0),
            Vector3::new(0.0, g, 0.0),
            Vector3::new(0.0, -g, 0.0),
            Vector3::new(0.0, 0.0, g),
            Vector3::new(0.0, 0.0, -g),
        ];
        let d = 0.01;
        let e = [d, d, -d, -d, 0.0, 0.0];
        let outs: Vec<_> = refs
            .iter()
            .zip(e)
            .map(|(a, ex)| a + Vector3::new(ex, 0.0, 0.0))
            .collect();
        let fit = fit_affine(&refs, &outs, None).unwrap();
        // e is orthogonal to all four columns, so the estimate is exact S = I, c = 0 and the
        // residual variance is Σe²/(6−4) = 4d²/2 = 2d².
        assert!((fit.calibration.sensitivity() - Matrix3::identity()).amax() < 1e-12);
        assert!((fit.residual_cov[(0, 0)] - 2.0 * d * d).abs() < 1e-15);
        let cov = fit.calibration.covariance();
        // Var(S_xx) = 2d² / (2g²); Var(q_x) = Var(c_x) = 2d² / 6 since q = −c when S = I, q = 0.
        assert!((cov[(0, 0)] - 2.0 * d * d / (2.0 * g * g)).abs() < 1e-18);
        assert!((cov[(9, 9)] - 2.0 * d * d / 6.0).abs() < 1e-15);
        assert!(cov[(4, 4)].abs() < 1e-25);
    }

    #[test]
    fn coplanar_references_are_refused_with_the_plane() {
        let refs = [
            Vector3::new(9.8, 0.0, 0.0),
            Vector3::new(0.0, 9.8, 0.0),
            Vector3::new(-9.8, 0.0, 0.0),
            Vector3::new(0.0, -9.8, 0.0),
            Vector3::new(6.93, 6.93, 0.0),
        ];
        let outs: Vec<_> = refs.iter().map(|a| a * 0.1).collect();
        match fit_affine(&refs, &outs, None) {
            Err(AffineFailure::Degenerate { normal, level }) => {
                assert!((normal.z.abs() - 1.0).abs() < 1e-9, "normal {normal:?}");
                assert!(level.abs() < 1e-9);
            }
            other => panic!("expected degenerate, got {other:?}"),
        }
    }
}
