//! Covariance-driven stochastic subspace identification (SSI-COV; Peeters & De Roeck,
//! "Reference-based stochastic subspace identification for output-only modal analysis",
//! Mechanical Systems and Signal Processing 13(6), 1999).
//!
//! The output correlations with a set of reference channels, `R_k = E[y(t+k)·y_ref(t)ᵀ]`,
//! are those of a linear system, `R_k = C·A^(k−1)·G`. Stacked into the block Toeplitz matrix
//!
//! ```text
//!         ⎡ R_i     R_(i−1) … R_1 ⎤
//! T_1|i = ⎢ R_(i+1) R_i     … R_2 ⎥ = O_i · C_i^ref
//!         ⎣ R_(2i−1)        … R_i ⎦
//! ```
//!
//! it factors into the observability matrix `O_i = [C; C·A; …; C·A^(i−1)]` and a reversed
//! controllability matrix; its SVD truncated at order `n` gives `O_i = U_n·S_n^½`, `C` is the
//! first block row and `A` solves `O_up·A = O_down` (the observability matrix without its last,
//! resp. first, block row) in the least-squares sense. One QR of `O_up` at the largest order
//! serves every order, since the QR of a matrix's first `n` columns is the first `n` columns of
//! its QR. The eigenvalues `μ` of `A` give the continuous poles `λ = f_s·ln μ`, hence the
//! frequency `|λ|/2π` and damping ratio `−Re λ/|λ|`, and its eigenvectors `ψ` the mode shapes
//! `C·ψ`.
//!
//! **Missing samples.** The correlations are sums over pairs of samples in which both samples
//! are valid, divided by the number of such pairs ([`Correlations`]): an unbiased estimate of
//! each `R_k` whatever the pattern of gaps, at the cost of a little more variance where pairs
//! are missing. Sums and counts are kept per block of the window, so that the correlations of
//! the window with one block left out (the jackknife of [`crate::uncertainty`]) are exact
//! differences, not re-computations.

use nalgebra::{Complex, DMatrix, DVector};

use crate::error::ModalError;
use crate::window::Channels;

/// Correlation sums and pair counts per block of the window, lag and channel pair.
#[derive(Debug, Clone)]
pub struct Correlations {
    pub max_lag: usize,
    pub channels: usize,
    pub references: Vec<usize>,
    pub blocks: usize,
    sums: Vec<f64>,
    counts: Vec<f64>,
}

/// A dot product with four accumulators, so that the compiler can keep four lanes busy.
fn dot(a: &[f64], b: &[f64]) -> f64 {
    let n = a.len().min(b.len());
    let (a, b) = (&a[..n], &b[..n]);
    let mut acc = [0.0f64; 4];
    let chunks = n / 4;
    for c in 0..chunks {
        let j = 4 * c;
        acc[0] += a[j] * b[j];
        acc[1] += a[j + 1] * b[j + 1];
        acc[2] += a[j + 2] * b[j + 2];
        acc[3] += a[j + 3] * b[j + 3];
    }
    let mut total = (acc[0] + acc[1]) + (acc[2] + acc[3]);
    for j in 4 * chunks..n {
        total += a[j] * b[j];
    }
    total
}

impl Correlations {
    /// Sums `y_a(t+k)·y_b(t)` over valid pairs, for lags `1..=max_lag`, every channel `a` and
    /// reference `b`, with `t` in each of `blocks` equal blocks of the window (a pair belongs to
    /// the block of its earlier sample, so the blocks' sums add up to the window's).
    pub fn compute(
        channels: &Channels,
        references: &[usize],
        max_lag: usize,
        blocks: usize,
    ) -> Result<Correlations, ModalError> {
        let n = channels.len();
        let l = channels.data.len();
        let r = references.len();
        if blocks == 0 || n < blocks * (4 * max_lag).max(1) {
            return Err(ModalError::TooShort {
                samples: n,
                blocks,
                max_lag,
            });
        }
        let size = blocks * (max_lag + 1) * l * r;
        let mut sums = vec![0.0; size];
        let mut counts = vec![0.0; size];
        for block in 0..blocks {
            let t0 = block * n / blocks;
            let t1 = (block + 1) * n / blocks;
            for k in 1..=max_lag {
                let end = t1.min(n - k);
                if end <= t0 {
                    continue;
                }
                for a in 0..l {
                    let later = &channels.data[a][t0 + k..end + k];
                    let later_mask = &channels.mask[a][t0 + k..end + k];
                    for (j, &b) in references.iter().enumerate() {
                        let at = ((block * (max_lag + 1) + k) * l + a) * r + j;
                        sums[at] = dot(later, &channels.data[b][t0..end]);
                        counts[at] = if channels.complete[a] && channels.complete[b] {
                            (end - t0) as f64
                        } else {
                            dot(later_mask, &channels.mask[b][t0..end])
                        };
                    }
                }
            }
        }
        Ok(Correlations {
            max_lag,
            channels: l,
            references: references.to_vec(),
            blocks,
            sums,
            counts,
        })
    }

    /// The correlation matrices `R_k` (channels × references) for `k = 0..=max_lag` (`R_0`
    /// unused, zero), from every block or from every block but `left_out`.
    pub fn matrices(&self, left_out: Option<usize>) -> Result<Vec<DMatrix<f64>>, ModalError> {
        let l = self.channels;
        let r = self.references.len();
        let mut out = vec![DMatrix::zeros(l, r); self.max_lag + 1];
        for (k, matrix) in out.iter_mut().enumerate().skip(1) {
            for a in 0..l {
                for j in 0..r {
                    let mut sum = 0.0;
                    let mut count = 0.0;
                    for block in (0..self.blocks).filter(|&b| Some(b) != left_out) {
                        let at = ((block * (self.max_lag + 1) + k) * l + a) * r + j;
                        sum += self.sums[at];
                        count += self.counts[at];
                    }
                    if count < 1.0 {
                        return Err(ModalError::EmptyCorrelation {
                            block: left_out.unwrap_or(usize::MAX),
                            channel: a,
                            lag: k,
                        });
                    }
                    matrix[(a, j)] = sum / count;
                }
            }
        }
        Ok(out)
    }
}

/// The block Toeplitz matrix `T_1|i` of the module's documentation, from `R_1 … R_(2i−1)`.
pub fn toeplitz(correlations: &[DMatrix<f64>], block_rows: usize) -> DMatrix<f64> {
    let l = correlations[1].nrows();
    let r = correlations[1].ncols();
    let i = block_rows;
    let mut t = DMatrix::zeros(l * i, r * i);
    for p in 0..i {
        for q in 0..i {
            t.view_mut((p * l, q * r), (l, r))
                .copy_from(&correlations[i + p - q]);
        }
    }
    t
}

/// A pole of the identified system at one model order.
#[derive(Debug, Clone, PartialEq)]
pub struct Pole {
    pub order: usize,
    pub frequency_hz: f64,
    pub damping_ratio: f64,
    /// `C·ψ`, not normalised.
    pub shape: Vec<Complex<f64>>,
}

/// The subspace of one Toeplitz matrix, ready to give the system at any order up to its
/// largest.
#[derive(Debug, Clone)]
pub struct Subspace {
    channels: usize,
    max_order: usize,
    sample_rate_hz: f64,
    /// First block row of `O` at the largest order (channels × max_order).
    c_full: DMatrix<f64>,
    /// `R` of the QR of `O_up` (max_order × max_order).
    r_up: DMatrix<f64>,
    /// `Qᵀ·O_down` (max_order × max_order).
    q_down: DMatrix<f64>,
    pub singular_values: Vec<f64>,
}

impl Subspace {
    pub fn new(
        toeplitz: &DMatrix<f64>,
        channels: usize,
        max_order: usize,
        sample_rate_hz: f64,
    ) -> Result<Subspace, ModalError> {
        let rows = toeplitz.nrows();
        let max_order = max_order.min(toeplitz.ncols()).min(rows - channels);
        let svd = toeplitz.clone().svd(true, false);
        let u = svd
            .u
            .ok_or(ModalError::Numerical("SVD of the Toeplitz matrix"))?;
        let mut order: Vec<usize> = (0..svd.singular_values.len()).collect();
        order.sort_by(|&a, &b| svd.singular_values[b].total_cmp(&svd.singular_values[a]));
        let singular_values: Vec<f64> = order.iter().map(|&j| svd.singular_values[j]).collect();
        let mut o = DMatrix::zeros(rows, max_order);
        for (col, &j) in order.iter().take(max_order).enumerate() {
            let scale = svd.singular_values[j].max(0.0).sqrt();
            o.column_mut(col).copy_from(&(u.column(j) * scale));
        }
        let o_up = o.rows(0, rows - channels).into_owned();
        let o_down = o.rows(channels, rows - channels).into_owned();
        let qr = o_up.qr();
        let q = qr.q();
        let r_up = qr.r();
        let q_down = q.transpose() * o_down;
        Ok(Subspace {
            channels,
            max_order,
            sample_rate_hz,
            c_full: o.rows(0, channels).into_owned(),
            r_up,
            q_down,
            singular_values,
        })
    }

    pub fn max_order(&self) -> usize {
        self.max_order
    }

    /// The system matrices `(A, C)` at `order`.
    pub fn system(&self, order: usize) -> Result<(DMatrix<f64>, DMatrix<f64>), ModalError> {
        let n = order.min(self.max_order);
        let r = self.r_up.view((0, 0), (n, n));
        let rhs = self.q_down.view((0, 0), (n, n)).into_owned();
        let a = r
            .solve_upper_triangular(&rhs)
            .ok_or(ModalError::Numerical("O_up is rank deficient"))?;
        let c = self.c_full.columns(0, n).into_owned();
        Ok((a, c))
    }

    /// The oscillating poles at `order` (one of each complex-conjugate pair, positive
    /// frequency), sorted by frequency.
    pub fn poles(&self, order: usize) -> Result<Vec<Pole>, ModalError> {
        let (a, c) = self.system(order)?;
        let eigenvalues = nalgebra::linalg::Schur::try_new(a.clone(), 1e-12, 10_000)
            .ok_or(ModalError::Numerical("Schur decomposition of A"))?
            .complex_eigenvalues();
        let mut poles = Vec::new();
        for mu in eigenvalues.iter() {
            if mu.im <= 1e-12 || mu.norm() >= 1.0 || mu.norm() <= 0.0 {
                continue;
            }
            let lambda = mu.ln() * self.sample_rate_hz;
            let omega = lambda.norm();
            let psi = eigenvector(&a, *mu)?;
            let shape: Vec<Complex<f64>> = (0..self.channels)
                .map(|row| {
                    (0..psi.len())
                        .map(|col| psi[col] * c[(row, col)])
                        .sum::<Complex<f64>>()
                })
                .collect();
            poles.push(Pole {
                order,
                frequency_hz: omega / (2.0 * std::f64::consts::PI),
                damping_ratio: -lambda.re / omega,
                shape,
            });
        }
        poles.sort_by(|p, q| p.frequency_hz.total_cmp(&q.frequency_hz));
        Ok(poles)
    }
}

/// The eigenvector of `a` for its eigenvalue `mu`, by inverse iteration with a shift a hair
/// off `mu` (nalgebra gives general matrices' eigenvalues, not their eigenvectors). Two steps
/// suffice: the shift is 10⁻¹⁰ from the eigenvalue and any other eigenvalue is far further.
fn eigenvector(a: &DMatrix<f64>, mu: Complex<f64>) -> Result<DVector<Complex<f64>>, ModalError> {
    let n = a.nrows();
    let shift = mu + Complex::new(1e-10, 1e-10) * mu.norm().max(1e-3);
    let m = DMatrix::from_fn(n, n, |i, j| {
        let diagonal = if i == j {
            shift
        } else {
            Complex::new(0.0, 0.0)
        };
        Complex::new(a[(i, j)], 0.0) - diagonal
    });
    let lu = m.lu();
    // A start with no special relation to any eigenvector.
    let mut v = DVector::from_fn(n, |i, _| Complex::new(1.0 + 0.1 * i as f64, 0.3));
    for _ in 0..2 {
        v = lu
            .solve(&v)
            .ok_or(ModalError::Numerical("inverse iteration"))?;
        let norm = v.norm();
        if !(norm.is_finite() && norm > 0.0) {
            return Err(ModalError::Numerical("inverse iteration"));
        }
        v /= Complex::new(norm, 0.0);
    }
    Ok(v)
}

/// The modal assurance criterion of two complex shapes: `|φ₁ᴴφ₂|² / (φ₁ᴴφ₁ · φ₂ᴴφ₂)`.
pub fn mac(a: &[Complex<f64>], b: &[Complex<f64>]) -> f64 {
    let cross: Complex<f64> = a.iter().zip(b).map(|(x, y)| x.conj() * y).sum();
    let aa: f64 = a.iter().map(|x| x.norm_sqr()).sum();
    let bb: f64 = b.iter().map(|x| x.norm_sqr()).sum();
    if aa > 0.0 && bb > 0.0 {
        cross.norm_sqr() / (aa * bb)
    } else {
        0.0
    }
}

/// A shape scaled so that component `reference` is 1.
pub fn normalise(shape: &[Complex<f64>], reference: usize) -> Vec<Complex<f64>> {
    let r = shape[reference];
    if r.norm() == 0.0 {
        return shape.to_vec();
    }
    shape.iter().map(|x| x / r).collect()
}

/// Index of the component of largest modulus.
pub fn largest_component(shape: &[Complex<f64>]) -> usize {
    shape
        .iter()
        .enumerate()
        .max_by(|a, b| a.1.norm().total_cmp(&b.1.norm()))
        .map_or(0, |(i, _)| i)
}
