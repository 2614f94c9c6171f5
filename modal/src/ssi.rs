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
        self.matrices_of(|b| Some(b) != left_out, left_out.unwrap_or(usize::MAX))
    }

    /// The correlation matrices from the blocks `keep` takes; `label` names the set in an
    /// error.
    pub fn matrices_of(
        &self,
        keep: impl Fn(usize) -> bool,
        label: usize,
    ) -> Result<Vec<DMatrix<f64>>, ModalError> {
        let l = self.channels;
        let r = self.references.len();
        let mut out = vec![DMatrix::zeros(l, r); self.max_lag + 1];
        for (k, matrix) in out.iter_mut().enumerate().skip(1) {
            for a in 0..l {
                for j in 0..r {
                    let mut sum = 0.0;
                    let mut count = 0.0;
                    for block in (0..self.blocks).filter(|&b| keep(b)) {
                        let at = ((block * (self.max_lag + 1) + k) * l + a) * r + j;
                        sum += self.sums[at];
                        count += self.counts[at];
                    }
                    if count < 1.0 {
                        return Err(ModalError::EmptyCorrelation {
                            block: label,
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
    toeplitz_of(correlations, block_rows, block_rows)
}

/// The block Toeplitz matrix of `rows` block rows and `columns` block columns, from
/// `R_1 … R_(rows+columns−1)`: block `(p, q)` is `R_(columns+p−q)`. It factors as
/// `O_rows · C_columns^ref` whatever the split; the rows give the observability matrix, and
/// the columns only need to span the model order.
pub fn toeplitz_of(correlations: &[DMatrix<f64>], rows: usize, columns: usize) -> DMatrix<f64> {
    let l = correlations[1].nrows();
    let r = correlations[1].ncols();
    let mut t = DMatrix::zeros(l * rows, r * columns);
    for p in 0..rows {
        for q in 0..columns {
            t.view_mut((p * l, q * r), (l, r))
                .copy_from(&correlations[columns + p - q]);
        }
    }
    t
}

/// The size of a Toeplitz matrix's estimation error: the largest singular value of half the
/// difference of the matrices of two halves of the window's blocks (the first half against
/// the second, and the odd blocks against the even: the larger of the two, so that a window
/// whose excitation changed halfway counts its change as noise). `(T_A − T_B)/2` has the
/// error variance of `(T_A + T_B)/2 = T̂`, and by Weyl's inequality every singular value of
/// `T̂` above `‖T̂ − T‖` is one of a non-zero singular value of `T`: the count of those is a
/// lower bound of the system's order that the data resolve.
pub fn noise_floor(
    correlations: &Correlations,
    rows: usize,
    columns: usize,
) -> Result<f64, ModalError> {
    let nb = correlations.blocks;
    let mut floor: f64 = 0.0;
    let splits: [&dyn Fn(usize) -> bool; 2] = [&|b| b < nb / 2, &|b| b % 2 == 0];
    for first in splits {
        let a = toeplitz_of(&correlations.matrices_of(first, usize::MAX)?, rows, columns);
        let b = toeplitz_of(
            &correlations.matrices_of(|k| !first(k), usize::MAX)?,
            rows,
            columns,
        );
        floor = floor.max(spectral_norm(&((a - b) * 0.5)));
    }
    Ok(floor)
}

/// The largest singular value of `d`, by power iteration on `DᵀD` from a fixed start (to a
/// few per cent: it only sets a floor).
pub fn spectral_norm(d: &DMatrix<f64>) -> f64 {
    let mut v = DVector::from_fn(d.ncols(), |i, _| {
        1.0 + 0.37 * ((i * 7919) % 101) as f64 / 101.0
    });
    let mut sigma = 0.0;
    for _ in 0..40 {
        let norm = v.norm();
        if !(norm > 0.0 && norm.is_finite()) {
            return 0.0;
        }
        v /= norm;
        let u = d * &v;
        sigma = u.norm();
        v = d.transpose() * u;
    }
    sigma
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
        let schur = nalgebra::linalg::Schur::try_new(a, 1e-12, 10_000)
            .ok_or(ModalError::Numerical("Schur decomposition of A"))?;
        let eigenvalues = schur.complex_eigenvalues();
        // A = Q·T·Qᵀ with T quasi-triangular (so Hessenberg): an eigenvector of A is Q times
        // one of T, found in O(n²) each.
        let (q, t) = schur.unpack();
        let mut poles = Vec::new();
        for mu in eigenvalues.iter() {
            if mu.im <= 1e-12 || mu.norm() >= 1.0 || mu.norm() <= 0.0 {
                continue;
            }
            let lambda = mu.ln() * self.sample_rate_hz;
            let omega = lambda.norm();
            let w = hessenberg_eigenvector(&t, *mu)?;
            // C·Q·w: the shape.
            let psi: Vec<Complex<f64>> = (0..q.nrows())
                .map(|row| (0..w.len()).map(|k| w[k] * q[(row, k)]).sum())
                .collect();
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

/// The eigenvector of an upper Hessenberg `h` for its eigenvalue `mu`, by inverse iteration
/// with a shift a hair off `mu`. Two steps suffice: the shift is 10⁻¹⁰ from the eigenvalue
/// and any other eigenvalue is far further. Each step is one Hessenberg elimination with
/// partial pivoting, O(n²).
fn hessenberg_eigenvector(
    h: &DMatrix<f64>,
    mu: Complex<f64>,
) -> Result<Vec<Complex<f64>>, ModalError> {
    let n = h.nrows();
    let shift = mu + Complex::new(1e-10, 1e-10) * mu.norm().max(1e-3);
    let zero = Complex::new(0.0, 0.0);
    // Row-major copy of H − shift·I; entries below the subdiagonal are zero and never read.
    let mut lu = vec![zero; n * n];
    for i in 0..n {
        for j in i.saturating_sub(1)..n {
            lu[i * n + j] = Complex::new(h[(i, j)], 0.0) - if i == j { shift } else { zero };
        }
    }
    // Eliminate the subdiagonal once, recording each step's pivot and multiplier.
    let mut swapped = vec![false; n];
    let mut multiplier = vec![zero; n];
    for k in 0..n.saturating_sub(1) {
        if lu[(k + 1) * n + k].norm() > lu[k * n + k].norm() {
            for j in k..n {
                lu.swap(k * n + j, (k + 1) * n + j);
            }
            swapped[k] = true;
        }
        let pivot = lu[k * n + k];
        if pivot.norm() == 0.0 {
            return Err(ModalError::Numerical("inverse iteration"));
        }
        let m = lu[(k + 1) * n + k] / pivot;
        multiplier[k] = m;
        for j in k..n {
            let v = lu[k * n + j];
            lu[(k + 1) * n + j] -= m * v;
        }
    }
    // A start with no special relation to any eigenvector.
    let mut v: Vec<Complex<f64>> = (0..n)
        .map(|i| Complex::new(1.0 + 0.1 * i as f64, 0.3))
        .collect();
    for _ in 0..2 {
        for k in 0..n.saturating_sub(1) {
            if swapped[k] {
                v.swap(k, k + 1);
            }
            let vk = v[k];
            v[k + 1] -= multiplier[k] * vk;
        }
        for i in (0..n).rev() {
            let mut sum = v[i];
            for j in i + 1..n {
                sum -= lu[i * n + j] * v[j];
            }
            let d = lu[i * n + i];
            if d.norm() == 0.0 {
                return Err(ModalError::Numerical("inverse iteration"));
            }
            v[i] = sum / d;
        }
        let norm = v.iter().map(|x| x.norm_sqr()).sum::<f64>().sqrt();
        if !(norm.is_finite() && norm > 0.0) {
            return Err(ModalError::Numerical("inverse iteration"));
        }
        v.iter_mut().for_each(|x| *x /= norm);
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
