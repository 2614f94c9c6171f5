//! Least-squares fit of one sinusoid, with offset and linear trend, to one axis of a window:
//! the four-parameter sine fit of IEEE Std 1057 with a trend term, for windows whose motion is
//! a single sway.
//!
//! Model, with `m` the sample's grid index and `τ = (m − o)/N` (o an origin, N a scale: the
//! window's first index and its length for a window fitted afresh):
//! `y(m) = a·cos ω(m − o) + b·sin ω(m − o) + c + d·τ`. For a given ω the model is linear in
//! `(a, b, c, d)`; ω is found by a golden-section search of the residual sum of squares within
//! one spectral bin either side of the spectrum's peak, then refined by Gauss–Newton steps on
//! the variable projection. The offset and trend absorb what is left of the baseline, so the
//! fit is independent of where the window cuts the cycles.
//!
//! **Moments.** Everything the fit needs at one ω is a sum over the samples: with the features
//! `φ = (cos, sin, 1, τ, τ·cos, τ·sin, y)`, the 7 × 7 moments `Σ φφᵀ` give `XᵀX`, `Xᵀy`,
//! `yᵀy` (so the residual sum of squares `yᵀy − βᵀXᵀy`), the derivative in ω and its
//! projections; and over runs of five consecutive samples, the fourth difference `d` of y with
//! `Σd², Σd·cos, Σd·sin, Σcos², Σcos·sin, Σsin²` at each run's middle sample give the
//! residual's fourth differences (the model's trend has none, and a sinusoid's is the same
//! sinusoid times `16·sin⁴(ω/2)`, shifted to the run's middle). [`Moments`] can be added to
//! and taken from sample by sample, so a window sliding at a fixed ω is fitted at the cost of
//! the samples that enter and leave it ([`crate::monitor`]'s sway tracker).
//!
//! Uncertainties are the least-squares covariance, with the noise variance `s²` estimated from
//! the residuals (ν = n − 5, large for any window worth judging):
//! `var(ω) = s² / (g⊥ᵀg⊥)`, with `g = ∂y/∂ω` and `g⊥` its part orthogonal to the linear
//! columns `X`; `Cov(a, b, c, d) = s²·(XᵀX)⁻¹ + w·wᵀ·var(ω)`, `w = (XᵀX)⁻¹Xᵀg`. The amplitude
//! `√(a² + b²)` has the variance `hᵀ·Cov·h` with `h = (a, b, 0, 0)/amplitude` (ω's share comes
//! in through w). A Monte Carlo of sines in white noise gives 94–97 % coverage at k = 2 for the
//! amplitude and the frequency (module tests and the monitor's Monte Carlo).
//!
//! **Off the optimum.** At an ω that is not the optimum, the Gauss–Newton step
//! `g⊥ᵀr / g⊥ᵀg⊥` says how far it is, and `ω + step` is the frequency reported. The sinusoid
//! is carried there too, to first order in the step, by `dβ/dω = (XᵀX)⁻¹(X′ᵀr − Xᵀg)`
//! (`X′ = ∂X/∂ω`, r the residual; from the same moments), in amplitude and phase since (a, b)
//! mostly turns with ω (`carried`). In a window of whole and part cycles with a trend the
//! amplitude does depend on ω to first order; carried, the fit held at an ω a few u(ω) away is
//! the optimum's to second order in the step, within a bound it states
//! ([`AtOmega::carry_error_u`]), and its uncertainties and adequacy tests are the optimum's to a
//! small fraction of themselves.
//!
//! **Adequacy.** The fit speaks for the motion only when the residual is noise. Noise is white
//! sample to sample; motion the model missed is not. So the residual's variance `s²` is compared
//! with its short-scale variance from fourth differences, `σ_d² = mean((Δ⁴r)²)/70`, which
//! ignores slow content: for white noise the ratio `R = s²/σ_d²` is 1 with a standard deviation
//! of `√(3.25/n)` (from the autocorrelation of the difference filter). A ratio above
//! `1 + 3·√(3.25/n)` means missed motion, and the window is judged from its samples instead.
//! What passes is counted anyway: `max(s² − σ_d²·(1 + 2·√(3.25/n)), 0)` is added to the
//! variance of the peak as unmodelled motion. White motion would pass that test (its residual is
//! white too), so the residual must also be no larger than the sensor's noise can be: `s²` at
//! most `(1 + 4·√(2/n))` times the square of the stated u, which bounds the noise.

use nalgebra::{Matrix2, Matrix4, SMatrix, Vector2, Vector4};

use crate::highpass::Response;

/// A fit judged adequate, in the window's units and Hz.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SineFit {
    pub frequency_hz: f64,
    pub frequency_u_hz: f64,
    /// Amplitude of the sinusoid: the peak of the motion it describes.
    pub amplitude: f64,
    pub amplitude_u: f64,
    /// RMS of the fitted sinusoid (without offset and trend) over every sample time of the
    /// window, present or not.
    pub rms: f64,
    pub rms_u: f64,
    /// Residual standard deviation `s`: the noise the fit saw.
    pub noise_sd: f64,
    /// Standard deviation of motion the model missed but the adequacy test let pass.
    pub unmodelled_sd: f64,
}

/// Fewest cycles in the window for a fit: below, sinusoid and trend cannot be told apart.
const MIN_CYCLES: f64 = 1.5;
/// Golden-section steps: the bracket shrinks to 0.618²⁰ ≈ 7·10⁻⁵ of two bins before the
/// Gauss–Newton steps, which converge quadratically from there.
const GOLDEN_STEPS: usize = 20;
const NEWTON_STEPS: usize = 3;

/// Carried from ω to the optimum to first order, a fit is off by the amplitude's curvature in
/// ω over the step: A″ ≈ −A·N²/12 over N sample times (their spread about their mean), which
/// is `(1/√48)·(step/u(ω))²·u(ω)·N` of the amplitude's u. The factor measured is 0.145 in
/// windows of many cycles and up to 0.24 in windows of 2–3 cycles with a trend (over phases,
/// at 400 and 1 000 samples; `the_carried_fit_is_off_by_its_curvature` prints it for its
/// windows); this bounds it.
const CARRY_CURVATURE: f64 = 0.25;

/// The most the step may turn the sinusoid by over the window (rad) for the fit to be carried:
/// the expansion in the step holds while that phase is small. Where u(ω) is large (motion
/// barely above the noise) the curvature's bound alone would let it grow.
const MAX_CARRY_PHASE: f64 = 0.1;

/// Indices of the features φ.
const COS: usize = 0;
const SIN: usize = 1;
const ONE: usize = 2;
const TAU: usize = 3;
const TAU_COS: usize = 4;
const TAU_SIN: usize = 5;
const Y: usize = 6;

/// Sums over a window's samples at one ω; see the module documentation.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Moments {
    /// `Σ φᵢφⱼ` for i ≤ j.
    m: [[f64; 7]; 7],
    /// Over runs of five consecutive samples, d the run's fourth difference and (cos, sin) at
    /// its middle sample: `Σd², Σd·cos, Σd·sin, Σcos², Σcos·sin, Σsin²`.
    runs: [f64; 6],
    run_count: i64,
    count: i64,
}

impl Moments {
    /// Adds (`sign = 1.0`) or takes away (`−1.0`) one sample: y at `τ`, with (cos, sin) of
    /// ω(m − o).
    pub fn sample(&mut self, sign: f64, tau: f64, cos: f64, sin: f64, y: f64) {
        let phi = [cos, sin, 1.0, tau, tau * cos, tau * sin, y];
        // Constant bounds, so that the 28 products unroll: this runs for every sample that
        // enters or leaves a tracked window.
        for (i, row) in self.m.iter_mut().enumerate() {
            let w = sign * phi[i];
            for (mij, pj) in row[i..].iter_mut().zip(&phi[i..]) {
                *mij += w * pj;
            }
        }
        self.count += sign as i64;
    }

    /// Adds or takes away one run of five consecutive samples: `d` its fourth difference,
    /// (cos, sin) at its middle sample.
    pub fn run(&mut self, sign: f64, d: f64, cos: f64, sin: f64) {
        for (r, v) in
            self.runs
                .iter_mut()
                .zip([d * d, d * cos, d * sin, cos * cos, cos * sin, sin * sin])
        {
            *r += sign * v;
        }
        self.run_count += sign as i64;
    }

    /// Samples summed.
    pub fn count(&self) -> usize {
        self.count.max(0) as usize
    }

    fn at(&self, i: usize, j: usize) -> f64 {
        if i <= j {
            self.m[i][j]
        } else {
            self.m[j][i]
        }
    }

    /// The same sums with their origin moved `shift` samples on, at ω (`turn` = ω·shift) and
    /// scale N (`d` = shift/N): at the new origin each sample's cos and sin are the old ones
    /// turned back by `turn` and τ is less by `d`, so every feature is a fixed linear map T of
    /// the old ones and the sums are T·M·Tᵀ (the runs' sums turn alike). Exact but for
    /// rounding, and a 7 × 7 product in place of a pass over the window.
    pub fn moved(&self, turn: f64, d: f64) -> Moments {
        let (s, c) = turn.sin_cos();
        #[rustfmt::skip]
        let t = SMatrix::<f64, 7, 7>::from_row_slice(&[
            c,      s,      0.0, 0.0, 0.0, 0.0, 0.0,
            -s,     c,      0.0, 0.0, 0.0, 0.0, 0.0,
            0.0,    0.0,    1.0, 0.0, 0.0, 0.0, 0.0,
            0.0,    0.0,    -d,  1.0, 0.0, 0.0, 0.0,
            -d * c, -d * s, 0.0, 0.0, c,   s,   0.0,
            d * s,  -d * c, 0.0, 0.0, -s,  c,   0.0,
            0.0,    0.0,    0.0, 0.0, 0.0, 0.0, 1.0,
        ]);
        let old = SMatrix::<f64, 7, 7>::from_fn(|i, j| self.at(i, j));
        let new = t * old * t.transpose();
        let mut m = [[0.0; 7]; 7];
        for (i, row) in m.iter_mut().enumerate() {
            for (j, mij) in row.iter_mut().enumerate().skip(i) {
                *mij = new[(i, j)];
            }
        }
        let [dd, dc, ds, cc, cs, ss] = self.runs;
        let runs = [
            dd,
            c * dc + s * ds,
            c * ds - s * dc,
            c * c * cc + 2.0 * c * s * cs + s * s * ss,
            c * s * (ss - cc) + (c * c - s * s) * cs,
            s * s * cc - 2.0 * c * s * cs + c * c * ss,
        ];
        Moments {
            m,
            runs,
            run_count: self.run_count,
            count: self.count,
        }
    }

    fn xtx(&self) -> Matrix4<f64> {
        Matrix4::from_fn(|i, j| self.at(i, j))
    }

    fn xty(&self) -> Vector4<f64> {
        Vector4::from_fn(|i, _| self.at(i, Y))
    }

    /// The linear parameters, `(XᵀX)⁻¹` and the residual sum of squares; None if singular.
    fn solve(&self) -> Option<(Vector4<f64>, Matrix4<f64>, f64)> {
        let inv = self.xtx().cholesky()?.inverse();
        let xty = self.xty();
        let beta = inv * xty;
        let rss = (self.at(Y, Y) - beta.dot(&xty)).max(0.0);
        Some((beta, inv, rss))
    }

    /// The sums of ω's derivative at the linear parameters `beta`, with `scale` = N; see
    /// [`OmegaTerms`].
    fn omega_terms(&self, beta: &Vector4<f64>, scale: f64) -> OmegaTerms {
        let (a, b) = (beta[0], beta[1]);
        // Σ (m − o)·sin·f and Σ (m − o)·cos·f for a feature f: N·Σ τ·sin·f, N·Σ τ·cos·f.
        let sin_with = |f: usize| scale * self.at(TAU_SIN, f);
        let cos_with = |f: usize| scale * self.at(TAU_COS, f);
        // X′ᵀf: X′'s columns are −(m − o)·sin and (m − o)·cos (the offset and trend do not
        // depend on ω); gᵀf = βᵀX′ᵀf.
        let x_prime = |f: usize| Vector4::new(-sin_with(f), cos_with(f), 0.0, 0.0);
        let xg = Vector4::new(
            beta.dot(&x_prime(COS)),
            beta.dot(&x_prime(SIN)),
            beta.dot(&x_prime(ONE)),
            beta.dot(&x_prime(TAU)),
        );
        let gg = scale
            * scale
            * (a * a * self.at(TAU_SIN, TAU_SIN) - 2.0 * a * b * self.at(TAU_COS, TAU_SIN)
                + b * b * self.at(TAU_COS, TAU_COS));
        // X′ᵀr = X′ᵀy − X′ᵀX·β, column by column of X.
        let x_prime_x = [COS, SIN, ONE, TAU].map(x_prime);
        let xr = x_prime(Y)
            - x_prime_x
                .iter()
                .zip(beta.iter())
                .map(|(col, beta_k)| col * *beta_k)
                .sum::<Vector4<f64>>();
        OmegaTerms {
            gr: beta.dot(&xr),
            xg,
            gg,
            xr,
        }
    }

    /// `mean((Δ⁴r)²)/70` from the runs, for the model `(a, b)` at ω; None with under 16 runs.
    fn short_scale_variance(&self, omega: f64, a: f64, b: f64) -> Option<f64> {
        if self.run_count < 16 {
            return None;
        }
        let gain = 16.0 * (0.5 * omega).sin().powi(4);
        let [dd, dc, ds, cc, cs, ss] = self.runs;
        let sum = dd - 2.0 * gain * (a * dc + b * ds)
            + gain * gain * (a * a * cc + 2.0 * a * b * cs + b * b * ss);
        Some(sum.max(0.0) / (70.0 * self.run_count as f64))
    }
}

/// What the fit needs of the derivative in ω at the linear parameters β = (a, b, c, d), as sums
/// over the window: with `X′ = ∂X/∂ω`, `g = X′β = (m − o)·(−a·sin + b·cos)` the model's
/// derivative and `r = y − Xβ` the residual.
struct OmegaTerms {
    /// `gᵀr`: the Gauss–Newton step's numerator.
    gr: f64,
    /// `Xᵀg`.
    xg: Vector4<f64>,
    /// `gᵀg`.
    gg: f64,
    /// `X′ᵀr`.
    xr: Vector4<f64>,
}

/// Where a window's samples lie relative to the moments' origin o and scale N.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Geometry {
    pub rate_hz: f64,
    /// N: `τ = (m − o)/N`.
    pub scale: f64,
    /// The window's first sample time, `m − o` (present or not).
    pub grid_start: f64,
    /// Sample times in the window, present or not.
    pub grid_len: u32,
    /// Largest |y| of the window.
    pub largest: f64,
    /// A filter the fitted sinusoid is carried through (the vibration baseline's high pass);
    /// None: the sinusoid as fitted.
    pub highpass: Option<Response>,
}

impl Geometry {
    /// `Σcos², Σcos·sin, Σsin²` of ω(m − o) over every sample time of the window, in closed
    /// form: with `θ = 2ω`, `Σ e^{iθm}` over L consecutive m is
    /// `e^{iθ(m₀ + (L−1)/2)}·sin(θL/2)/sin(θ/2)`.
    fn grid_squares(&self, omega: f64) -> (f64, f64, f64) {
        let l = f64::from(self.grid_len);
        // ω is at most half the rate (π), and at least 1.5 cycles over the window: sin ω
        // is not 0.
        let dirichlet = (omega * l).sin() / omega.sin();
        let phase = 2.0 * omega * (self.grid_start + 0.5 * (l - 1.0));
        let (re, im) = (dirichlet * phase.cos(), dirichlet * phase.sin());
        (0.5 * (l + re), 0.5 * im, 0.5 * (l - re))
    }

    /// RMS of `a·cos + b·sin` over the window's sample times, and its gradient in (a, b).
    fn grid_rms(&self, omega: f64, a: f64, b: f64) -> (f64, [f64; 2]) {
        let (cc, cs, ss) = self.grid_squares(omega);
        let n = f64::from(self.grid_len.max(1));
        let rms = ((a * a * cc + 2.0 * a * b * cs + b * b * ss) / n)
            .max(0.0)
            .sqrt();
        if rms == 0.0 {
            return (0.0, [0.0, 0.0]);
        }
        (
            rms,
            [(a * cc + b * cs) / (n * rms), (a * cs + b * ss) / (n * rms)],
        )
    }
}

/// The fit at one ω: how far ω is from the optimum, and the fit if it is adequate.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AtOmega {
    /// The Gauss–Newton step to the optimum (rad per sample).
    pub step: f64,
    /// Standard uncertainty of ω (rad per sample).
    pub omega_u: f64,
    /// How far the fit, carried to the optimum, may be from the optimum's own, in the
    /// amplitude's u: a bound on the second order in the step (`CARRY_CURVATURE`); infinite
    /// when the step is too long to carry the fit by.
    pub carry_error_u: f64,
    /// Judged adequate and usable (see the module documentation); its frequency is ω + step.
    pub fit: Option<SineFit>,
}

/// The fit at ω (rad per sample) from `moments`, for a window whose noise is at most
/// `noise_bound` (the stated u). None when singular or degenerate.
pub fn fit_at(
    moments: &Moments,
    omega: f64,
    geometry: &Geometry,
    noise_bound: f64,
) -> Option<AtOmega> {
    let n = moments.count();
    if n < 32 {
        return None;
    }
    let (held, inv, rss) = moments.solve()?;
    // g⊥ᵀg⊥ = gᵀg − gᵀX(XᵀX)⁻¹Xᵀg: what of ω's derivative the linear columns cannot take up.
    let perp = |t: &OmegaTerms| t.gg - (t.xg.transpose() * inv * t.xg)[0];
    let here = moments.omega_terms(&held, geometry.scale);
    let perp_here = perp(&here);
    // Not a number counts as not positive.
    if perp_here.is_nan() || perp_here <= 0.0 {
        return None;
    }
    let step = here.gr / perp_here;
    // The residual at the optimum ω + step (the variable projection's quadratic model), so
    // that a fit held at an ω near the optimum sees the noise a fit at the optimum sees.
    let s2 = (rss - step * here.gr).max(0.0) / (n - 5) as f64;
    // The sinusoid at the optimum, to first order in the step: from XᵀX·β = Xᵀy,
    // dβ/dω = (XᵀX)⁻¹(X′ᵀy − X′ᵀXβ − XᵀX′β) = (XᵀX)⁻¹(X′ᵀr − Xᵀg). The amplitude does depend
    // on ω to first order where the window holds part of a cycle and a trend; this is what
    // lets ω be held several u(ω) from the optimum.
    let optimum = omega + step;
    let beta = carried(&held, &(inv * (here.xr - here.xg)), step);
    // The covariance at the optimum, from its β. XᵀX is kept at ω: over the step it changes
    // by a relative of order a tenth of the phase the step turns over the window (10⁻³–10⁻²
    // where a fit is carried), far within what an uncertainty is known to (√(1/2ν)).
    let there = moments.omega_terms(&beta, geometry.scale);
    let perp_there = perp(&there);
    if perp_there.is_nan() || perp_there <= 0.0 {
        return None;
    }
    let var_omega = s2 / perp_there;
    let grid_len = f64::from(geometry.grid_len);
    let mut at = AtOmega {
        step,
        omega_u: var_omega.sqrt(),
        carry_error_u: if step.abs() * grid_len <= MAX_CARRY_PHASE {
            CARRY_CURVATURE * step * step * grid_len / var_omega.sqrt()
        } else {
            f64::INFINITY
        },
        fit: None,
    };
    let to_omega = std::f64::consts::TAU / geometry.rate_hz;
    let frequency_hz = optimum / to_omega;
    let cycles = frequency_hz * grid_len / geometry.rate_hz;
    if !(cycles >= MIN_CYCLES && frequency_hz < 0.5 * geometry.rate_hz && step.is_finite()) {
        return Some(at);
    }
    let w = inv * there.xg;
    let cov = inv * s2 + w * w.transpose() * var_omega;
    // The sinusoid (a, b) and its covariance, carried through the filter: a steady sinusoid
    // leaves it scaled by the gain G and advanced by the phase φ, (a', b') = T·(a, b) with
    // T = G·[[cos φ, sin φ], [−sin φ, cos φ]]. The gain's slope in ω adds G'·A·u(ω), and its
    // share to the RMS.
    let (t, gain_slope) = match geometry.highpass {
        Some(h) => {
            let (g, phi) = h.at(optimum);
            let dw = 1e-6 * optimum.max(1e-9);
            let slope = (h.at(optimum + dw).0 - h.at(optimum - dw).0) / (2.0 * dw);
            let (sin, cos) = phi.sin_cos();
            (Matrix2::new(g * cos, g * sin, -g * sin, g * cos), slope)
        }
        None => (Matrix2::identity(), 0.0),
    };
    let ab = t * Vector2::new(beta[0], beta[1]);
    let cov_ab = t * cov.fixed_view::<2, 2>(0, 0) * t.transpose();
    let amplitude = ab[0].hypot(ab[1]);
    let unfiltered = beta[0].hypot(beta[1]);
    // A sinusoid below the samples' rounding (f32: 6·10⁻⁸ of the largest value) is no sway:
    // what is fitted there is the rounding, at whatever ω it favours.
    if !(amplitude > 0.0 && amplitude.is_finite() && unfiltered > 1e-7 * geometry.largest) {
        return Some(at);
    }
    let h = ab / amplitude;
    let amplitude_var =
        (h.transpose() * cov_ab * h)[0] + (gain_slope * unfiltered).powi(2) * var_omega;

    // Adequacy: the residual must look white; see the module documentation. The runs' sums
    // are at the moments' ω, so the model's fourth differences are taken there, with β there:
    // the residual's change over the step is smooth, its fourth differences of order ω⁴ of it
    // (2·10⁻⁵ at 1 Hz sampled at 100 Hz), far below the noise's.
    let sd_ratio = (3.25 / n as f64).sqrt();
    let Some(short) = moments.short_scale_variance(omega, held[0], held[1]) else {
        return Some(at);
    };
    // An exact sinusoid leaves only the rounding of the f32 samples (6·10⁻⁸ of the largest
    // value), which is not white where the signal changes by less than a rounding step.
    let exact = s2.sqrt() <= 1e-6 * geometry.largest;
    let louder_than_noise = s2 > noise_bound * noise_bound * (1.0 + 4.0 * (2.0 / n as f64).sqrt());
    if !exact && (s2 > short * (1.0 + 3.0 * sd_ratio) || louder_than_noise) {
        return Some(at);
    }
    let unmodelled_var = (s2 - short * (1.0 + 2.0 * sd_ratio)).max(0.0);

    let (rms, grad) = geometry.grid_rms(optimum, ab[0], ab[1]);
    let g = Vector2::new(grad[0], grad[1]);
    // The RMS is proportional to the gain as the amplitude is.
    let gain = t[(0, 0)].hypot(t[(0, 1)]);
    let rms_var = (g.transpose() * cov_ab * g)[0]
        + (gain_slope / gain.max(f64::MIN_POSITIVE) * rms).powi(2) * var_omega;
    at.fit = Some(SineFit {
        frequency_hz,
        frequency_u_hz: var_omega.sqrt() / to_omega,
        amplitude,
        amplitude_u: amplitude_var.max(0.0).sqrt(),
        rms,
        rms_u: rms_var.max(0.0).sqrt(),
        noise_sd: s2.sqrt(),
        unmodelled_sd: unmodelled_var.sqrt(),
    });
    Some(at)
}

/// `(a, b)` of `beta` carried by `step` along its derivative `slope` in ω, as an amplitude
/// and a phase. (a, b) mostly turns with ω, by the window's mean time from the origin per unit
/// of ω: a straight step along the turn would lengthen it by `(step·dφ/dω)²·A/2`, an error of
/// the second order about as large, at a few u(ω), as the first-order one it corrects (0.036
/// of the amplitude's u at 5 u(ω) in a window of 400 samples, against 0.049 not carried).
/// Taken as a turn, what is left is the amplitude's own curvature in ω.
fn carried(beta: &Vector4<f64>, slope: &Vector4<f64>, step: f64) -> Vector4<f64> {
    let (a, b) = (beta[0], beta[1]);
    let squared = a * a + b * b;
    if squared.is_nan() || squared == 0.0 {
        return beta + slope * step;
    }
    // With (a, b) = A·(cos φ, sin φ): dA/A = (a·da + b·db)/A², dφ = (a·db − b·da)/A².
    let stretch = 1.0 + step * (a * slope[0] + b * slope[1]) / squared;
    let (sin, cos) = (step * (a * slope[1] - b * slope[0]) / squared).sin_cos();
    Vector4::new(
        stretch * (a * cos - b * sin),
        stretch * (a * sin + b * cos),
        beta[2] + step * slope[2],
        beta[3] + step * slope[3],
    )
}

/// One axis of a window: the samples' grid indices (increasing, holes allowed), their values,
/// and the grid's length.
pub struct Axis<'a> {
    pub index: &'a [u32],
    pub value: &'a [f64],
    pub grid_len: u32,
}

impl Axis<'_> {
    /// The window's moments at ω, origin at its first sample time and scale its length; with
    /// the runs when `runs` (only the final fit needs them).
    pub fn moments(&self, omega: f64, runs: bool) -> Moments {
        let mut m = Moments::default();
        let scale = 1.0 / f64::from(self.grid_len.max(1));
        let Some(&first) = self.index.first() else {
            return m;
        };
        // Rotating rather than calling sin_cos per sample: the grid is regular; holes are
        // skipped over.
        let (s0, c0) = (omega * f64::from(first)).sin_cos();
        let (sw, cw) = omega.sin_cos();
        let (mut c, mut s) = (c0, s0);
        let mut at = first;
        // The last five samples: (index, y, cos, sin); None before there were five.
        let mut last: [Option<(u32, f64, f64, f64)>; 5] = [None; 5];
        for (&k, &y) in self.index.iter().zip(self.value) {
            while at < k {
                (c, s) = (c * cw - s * sw, s * cw + c * sw);
                at += 1;
            }
            m.sample(1.0, f64::from(k) * scale, c, s, y);
            if runs {
                last.rotate_left(1);
                last[4] = Some((k, y, c, s));
                if let [Some(l0), Some(l1), Some(l2), Some(l3), Some(l4)] = last {
                    if l4.0 - l0.0 == 4 {
                        let d = fourth_difference([l0.1, l1.1, l2.1, l3.1, l4.1]);
                        m.run(1.0, d, l2.2, l2.3);
                    }
                }
            }
        }
        m
    }

    fn geometry(&self, rate_hz: f64, highpass: Option<Response>) -> Geometry {
        Geometry {
            highpass,
            rate_hz,
            scale: f64::from(self.grid_len.max(1)),
            grid_start: 0.0,
            grid_len: self.grid_len,
            largest: self.value.iter().fold(0.0f64, |m, v| m.max(v.abs())),
        }
    }
}

/// `y₀ − 4y₁ + 6y₂ − 4y₃ + y₄`.
pub fn fourth_difference(y: [f64; 5]) -> f64 {
    y[0] - 4.0 * y[1] + 6.0 * y[2] - 4.0 * y[3] + y[4]
}

/// Fits one sinusoid near `start_hz` (the spectrum's peak; `bin_hz` its resolution) to an axis
/// sampled at `rate_hz` whose noise is at most `noise_bound` (the stated u). None when the
/// window is too short for the frequency, the fit is singular, or it is not adequate (see the
/// module documentation).
pub fn fit(
    axis: &Axis<'_>,
    rate_hz: f64,
    start_hz: f64,
    bin_hz: f64,
    noise_bound: f64,
) -> Option<SineFit> {
    search(axis, rate_hz, start_hz, bin_hz, noise_bound, None).and_then(|(_, f)| f)
}

/// [`fit`], with the sinusoid carried through `highpass`, and the ω (rad per sample) the
/// search ended at, adequate or not; None when there is no minimum near the start.
pub fn search(
    axis: &Axis<'_>,
    rate_hz: f64,
    start_hz: f64,
    bin_hz: f64,
    noise_bound: f64,
    highpass: Option<Response>,
) -> Option<(f64, Option<SineFit>)> {
    let n = axis.index.len();
    if n < 32 || axis.value.len() != n {
        return None;
    }
    let to_omega = std::f64::consts::TAU / rate_hz;
    let (mut lo, mut hi) = (
        (start_hz - bin_hz).max(0.5 * start_hz) * to_omega,
        (start_hz + bin_hz).min(0.5 * rate_hz) * to_omega,
    );
    let bracket = hi - lo;
    let rss = |omega: f64| {
        axis.moments(omega, false)
            .solve()
            .map_or(f64::INFINITY, |(_, _, r)| r)
    };
    let golden = (5f64.sqrt() - 1.0) / 2.0;
    let (mut x1, mut x2) = (hi - golden * (hi - lo), lo + golden * (hi - lo));
    let (mut f1, mut f2) = (rss(x1), rss(x2));
    for _ in 0..GOLDEN_STEPS {
        if f1 < f2 {
            (hi, x2, f2) = (x2, x1, f1);
            x1 = hi - golden * (hi - lo);
            f1 = rss(x1);
        } else {
            (lo, x1, f1) = (x1, x2, f2);
            x2 = lo + golden * (hi - lo);
            f2 = rss(x2);
        }
    }
    let geometry = axis.geometry(rate_hz, highpass);
    let omega = newton(
        0.5 * (lo + hi),
        bracket,
        NEWTON_STEPS,
        |omega| axis.moments(omega, false),
        &geometry,
        noise_bound,
    )?;
    let at = fit_at(&axis.moments(omega, true), omega, &geometry, noise_bound)?;
    Some((omega, at.fit))
}

/// Gauss–Newton steps from `omega`, each on the moments at the current ω; None when a step
/// leaves `bracket` (no minimum near: not one sway) or is not a number.
pub fn newton(
    mut omega: f64,
    bracket: f64,
    steps: usize,
    moments_at: impl Fn(f64) -> Moments,
    geometry: &Geometry,
    noise_bound: f64,
) -> Option<f64> {
    for _ in 0..steps {
        let at = fit_at(&moments_at(omega), omega, geometry, noise_bound)?;
        if at.step.is_nan() || at.step.abs() > bracket {
            return None;
        }
        omega += at.step;
    }
    Some(omega)
}
#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_distr::{Distribution, Normal};

    #[test]
    fn moved_sums_are_the_sums_built_at_the_new_origin() {
        let mut rng = rand::rngs::StdRng::seed_from_u64(3);
        let noise = Normal::new(0.0, 0.01).unwrap();
        let (omega, n, shift) = (0.0817, 400u32, 437u32);
        // A window of 400 samples with a hole, from sample 437 of a stream whose sums had
        // their origin at 0.
        let index: Vec<u32> = (0..n).filter(|k| !(100..103).contains(k)).collect();
        let value: Vec<f64> = index
            .iter()
            .map(|&k| {
                let t = f64::from(k + shift);
                1.9 * (omega * t + 0.3).sin() + 0.001 * t + noise.sample(&mut rng)
            })
            .collect();
        let far: Vec<u32> = index.iter().map(|k| k + shift).collect();
        let at_old = Axis {
            index: &far,
            value: &value,
            grid_len: n,
        }
        .moments(omega, true);
        let at_new = Axis {
            index: &index,
            value: &value,
            grid_len: n,
        }
        .moments(omega, true);
        let moved = at_old.moved(omega * f64::from(shift), f64::from(shift) / f64::from(n));
        for i in 0..7 {
            for j in i..7 {
                let (a, b) = (moved.at(i, j), at_new.at(i, j));
                let size = at_new
                    .at(i, i)
                    .abs()
                    .max(at_new.at(j, j).abs())
                    .sqrt()
                    .max(1.0);
                assert!(
                    (a - b).abs() <= 1e-9 * size * size,
                    "({i}, {j}): {a} against {b}"
                );
            }
        }
        for (k, (a, b)) in moved.runs.iter().zip(&at_new.runs).enumerate() {
            assert!(
                (a - b).abs() <= 1e-9 * at_new.runs[0].abs().max(1.0),
                "run sum {k}"
            );
        }
        assert_eq!(
            (moved.count, moved.run_count),
            (at_new.count, at_new.run_count)
        );
    }

    fn sine(n: u32, rate: f64, f: f64, amp: f64, phase: f64, offset: f64) -> Vec<f64> {
        (0..n)
            .map(|i| {
                let t = f64::from(i) / rate;
                offset + amp * (2.0 * std::f64::consts::PI * f * t + phase).sin()
            })
            .collect()
    }

    /// 400 samples at 100 Hz of a sway of amplitude `amplitude` at `f` Hz on an offset and a
    /// trend, in white noise of 0.01.
    fn part_cycles_with_a_trend(seed: u64, f: f64, amplitude: f64) -> (Vec<u32>, Vec<f64>) {
        let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
        let noise = Normal::new(0.0, 0.01).expect("valid");
        let index: Vec<u32> = (0..400).collect();
        let y = sine(400, 100.0, f, amplitude, 0.4 + 1.3 * seed as f64, 0.3)
            .into_iter()
            .zip(&index)
            .map(|(v, &i)| v + 0.2 * f64::from(i) / 400.0 + noise.sample(&mut rng))
            .collect();
        (index, y)
    }

    /// dβ/dω from the moments is the derivative of the least-squares β(ω), against central
    /// differences, at an ω off the optimum.
    #[test]
    fn the_slope_in_omega_is_the_derivative_of_beta() {
        let (index, y) = part_cycles_with_a_trend(3, 1.3, 1.0);
        let axis = Axis {
            index: &index,
            value: &y,
            grid_len: 400,
        };
        let beta_at = |omega: f64| axis.moments(omega, false).solve().expect("regular").0;
        let omega = std::f64::consts::TAU * 1.31 / 100.0;
        let m = axis.moments(omega, false);
        let (beta, inv, _) = m.solve().expect("regular");
        let terms = m.omega_terms(&beta, 400.0);
        let slope = inv * (terms.xr - terms.xg);
        let h = 1e-6;
        let differences = (beta_at(omega + h) - beta_at(omega - h)) / (2.0 * h);
        assert!(
            (slope - differences).norm() < 1e-6 * slope.norm(),
            "{slope} against {differences}"
        );
    }

    /// Held a few u(ω) from the optimum, the fit is the optimum's to second order in the step,
    /// within the bound it states: amplitude and RMS within `carry_error_u` of their u (the
    /// factor of `CARRY_CURVATURE` is printed), and what the frequency's own error carries
    /// through a filter's slope. Their u and the noise agree to a fifth of the phase the step
    /// turns over the window (1 % at most here; a u is itself known to √(1/2ν), 3.5 %). β as it
    /// is at the held ω is off by more (printed). The frequency ω + step is off by a small share
    /// of the step: Gauss–Newton converges linearly, at a rate of the order of the noise over
    /// the amplitude. From 1.8 to 55 cycles in the window, strong and weak sways, through a high
    /// pass and not.
    #[test]
    fn the_carried_fit_is_off_by_its_curvature() {
        let (mut factor, mut held_off) = (0.0f64, 0.0f64);
        let highpass = crate::highpass::HighPass::new(1.0, 100.0).response();
        for (i, f) in (0..24).map(|i| (i, 0.45 * 1.16f64.powi(i))) {
            for (amplitude, highpass) in [(1.0, None), (0.1, None), (1.0, Some(highpass))] {
                let (index, y) = part_cycles_with_a_trend(i as u64, f, amplitude);
                let axis = Axis {
                    index: &index,
                    value: &y,
                    grid_len: 400,
                };
                let geometry = axis.geometry(100.0, highpass);
                let Some((optimum, Some(best))) =
                    search(&axis, 100.0, f, 100.0 / 512.0, 0.01, highpass)
                else {
                    panic!("{f} Hz, amplitude {amplitude}: not one sway");
                };
                let omega_u = best.frequency_u_hz * std::f64::consts::TAU / 100.0;
                for off in [-3.0f64, -1.0, 1.0, 3.0] {
                    let omega = optimum + off * omega_u;
                    let m = axis.moments(omega, true);
                    let at = fit_at(&m, omega, &geometry, 0.01).expect("regular");
                    let f = at.fit.expect("adequate");
                    let in_u = |a: f64, b: f64, u: f64| (a - b).abs() / u;
                    let frequency = in_u(f.frequency_hz, best.frequency_hz, best.frequency_u_hz);
                    assert!(frequency < 0.02 * off.abs(), "{f:?} against {best:?}");
                    // The frequency's own error reaches the amplitude through the filter's
                    // slope, by at most as many of its u.
                    let amplitude = in_u(f.amplitude, best.amplitude, best.amplitude_u);
                    let rms = in_u(f.rms, best.rms, best.rms_u);
                    assert!(
                        amplitude.max(rms) <= at.carry_error_u + frequency,
                        "{at:?} against {best:?}"
                    );
                    if highpass.is_none() {
                        factor = factor.max(amplitude / (off * off * omega_u * 400.0));
                    }
                    for (u, best_u) in [
                        (f.amplitude_u, best.amplitude_u),
                        (f.rms_u, best.rms_u),
                        (f.frequency_u_hz, best.frequency_u_hz),
                        (f.noise_sd, best.noise_sd),
                    ] {
                        let phase = at.step.abs() * 400.0;
                        assert!(
                            (u / best_u - 1.0).abs() < 1e-3 + 0.2 * phase,
                            "{f:?} against {best:?}"
                        );
                    }
                    if highpass.is_none() {
                        let held = m.solve().expect("regular").0;
                        held_off = held_off.max(in_u(
                            held[0].hypot(held[1]),
                            best.amplitude,
                            best.amplitude_u,
                        ));
                    }
                }
            }
        }
        println!(
            "carried: (step/u(ω))²·u(ω)·N times {factor:.3} of the amplitude's u at most; \
             β as held at up to 3 u(ω): {held_off:.4} u"
        );
    }

    #[test]
    fn an_exact_sine_is_recovered() {
        let index: Vec<u32> = (0..400).collect();
        let y = sine(400, 100.0, 1.3, 0.8, 0.4, 9.81);
        let axis = Axis {
            index: &index,
            value: &y,
            grid_len: 400,
        };
        let f = fit(&axis, 100.0, 1.25, 100.0 / 512.0, 0.01).expect("an exact sine fits");
        assert!((f.frequency_hz - 1.3).abs() < 1e-9, "{f:?}");
        assert!((f.amplitude - 0.8).abs() < 1e-9, "{f:?}");
        // 5.2 cycles: the RMS over the window is not quite amp/√2; computed directly.
        let direct = (sine(400, 100.0, 1.3, 0.8, 0.4, 0.0)
            .iter()
            .map(|v| v * v)
            .sum::<f64>()
            / 400.0)
            .sqrt();
        assert!((f.rms - direct).abs() < 1e-9, "{} vs {direct}", f.rms);
    }

    #[test]
    fn holes_in_the_grid_are_fitted_at_their_times() {
        let full = sine(400, 100.0, 2.5, 0.5, 1.0, -0.2);
        let index: Vec<u32> = (0..400).filter(|i| i % 7 != 3).collect();
        let value: Vec<f64> = index.iter().map(|&i| full[i as usize]).collect();
        let axis = Axis {
            index: &index,
            value: &value,
            grid_len: 400,
        };
        let f = fit(&axis, 100.0, 2.4, 100.0 / 512.0, 0.01).expect("fits");
        assert!((f.frequency_hz - 2.5).abs() < 1e-9 && (f.amplitude - 0.5).abs() < 1e-9);
    }

    #[test]
    fn two_tones_are_not_one_sine() {
        let index: Vec<u32> = (0..400).collect();
        let mut rng = rand::rngs::StdRng::seed_from_u64(7);
        let noise = Normal::new(0.0, 0.01).expect("valid");
        let a = sine(400, 100.0, 1.3, 1.0, 0.0, 0.0);
        let b = sine(400, 100.0, 3.7, 0.2, 0.5, 0.0);
        let y: Vec<f64> = a
            .iter()
            .zip(&b)
            .map(|(x, z)| x + z + noise.sample(&mut rng))
            .collect();
        let axis = Axis {
            index: &index,
            value: &y,
            grid_len: 400,
        };
        assert!(fit(&axis, 100.0, 1.27, 100.0 / 512.0, 0.01).is_none());
        // Below a cycle and a half the trend and the sinusoid cannot be told apart.
        let slow = sine(400, 100.0, 0.3, 1.0, 0.0, 0.0);
        let axis = Axis {
            index: &index,
            value: &slow,
            grid_len: 400,
        };
        assert!(fit(&axis, 100.0, 0.29, 100.0 / 512.0, 0.01).is_none());
        // White motion leaves a white residual, but far above the sensor's stated noise: it is
        // not a sway with a small amplitude.
        let motion = Normal::new(0.0, 0.3).expect("valid");
        let white: Vec<f64> = (0..400).map(|_| motion.sample(&mut rng)).collect();
        let axis = Axis {
            index: &index,
            value: &white,
            grid_len: 400,
        };
        assert!(fit(&axis, 100.0, 7.0, 100.0 / 512.0, 0.02).is_none());
    }

    /// Sines in white noise: the stated intervals cover amplitude and frequency about 95 % of
    /// the time, and the fit is judged adequate almost always.
    #[test]
    fn intervals_cover_in_white_noise() {
        let mut rng = rand::rngs::StdRng::seed_from_u64(11);
        let index: Vec<u32> = (0..400).collect();
        let (mut trials, mut amp_in, mut freq_in, mut refused) = (0, 0, 0, 0);
        for f_true in [0.7, 1.3, 4.1, 9.0] {
            for _ in 0..500 {
                let sigma = 0.02;
                let noise = Normal::new(0.0, sigma).expect("valid");
                let phase = rng.gen_range(0.0..std::f64::consts::TAU);
                let y: Vec<f64> = sine(400, 100.0, f_true, 1.0, phase, 3.0)
                    .into_iter()
                    .map(|v| v + noise.sample(&mut rng))
                    .collect();
                let axis = Axis {
                    index: &index,
                    value: &y,
                    grid_len: 400,
                };
                trials += 1;
                // Start from a point off the line, as the spectrum's bin would be.
                let Some(f) = fit(&axis, 100.0, f_true + 0.07, 100.0 / 512.0, sigma) else {
                    refused += 1;
                    continue;
                };
                amp_in += usize::from((f.amplitude - 1.0).abs() <= 2.0 * f.amplitude_u);
                freq_in += usize::from((f.frequency_hz - f_true).abs() <= 2.0 * f.frequency_u_hz);
            }
        }
        let fitted = (trials - refused) as f64;
        let (amp, freq) = (amp_in as f64 / fitted, freq_in as f64 / fitted);
        assert!(
            refused as f64 / (trials as f64) < 0.03,
            "{refused} of {trials} refused"
        );
        assert!((0.93..=0.975).contains(&amp), "amplitude coverage {amp}");
        assert!((0.93..=0.975).contains(&freq), "frequency coverage {freq}");
    }
}
