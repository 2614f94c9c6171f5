//! The damped single-degree-of-freedom oscillator of response spectra, solved exactly for an
//! input that is linear between samples (Nigam & Jennings, BSSA 59(2), 1969).
//!
//! For `ü + 2ζω u̇ + ω² u = −a(t)` with `a` linear over a step, `a = a_i + r·s`, the response is a
//! particular solution `u_p = −(a_i + r s)/ω² + 2ζr/ω³` plus the free motion from what is left
//! of the initial state. So with `Φ = exp(F Δt)`, `F = [[0, 1], [−ω², −2ζω]]`,
//!
//! ```text
//! x_{i+1} = Φ·(x_i − x_p(0)) + x_p(Δt),   x = (u, u̇),
//! x_p(0) = (−a_i/ω² + 2ζr/ω³, −r/ω²),  x_p(Δt) = (−a_{i+1}/ω² + 2ζr/ω³, −r/ω²),  r = (a_{i+1} − a_i)/Δt,
//! ```
//!
//! with no approximation at any step length. The pseudo-spectral acceleration is `ω²·max|u|`.

/// Periods at which spectra are reported, s: 0.05 to 10 s, the ordinates ground-motion models
/// are commonly given at.
pub const STANDARD_PERIODS_S: [f64; 18] = [
    0.05, 0.075, 0.1, 0.15, 0.2, 0.25, 0.3, 0.4, 0.5, 0.75, 1.0, 1.5, 2.0, 3.0, 4.0, 5.0, 7.5, 10.0,
];

/// One oscillator at one sample interval.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Oscillator {
    pub period_s: f64,
    pub damping: f64,
    pub omega: f64,
    dt: f64,
    phi: [[f64; 2]; 2],
}

impl Oscillator {
    /// `damping` in (0, 1): the oscillator is underdamped.
    pub fn new(period_s: f64, damping: f64, dt: f64) -> Oscillator {
        let omega = 2.0 * std::f64::consts::PI / period_s;
        let wd = omega * (1.0 - damping * damping).sqrt();
        let e = (-damping * omega * dt).exp();
        let (s, c) = (wd * dt).sin_cos();
        let zw = damping * omega / wd;
        let phi = [
            [e * (c + zw * s), e * s / wd],
            [-e * omega * omega * s / wd, e * (c - zw * s)],
        ];
        Oscillator {
            period_s,
            damping,
            omega,
            dt,
            phi,
        }
    }

    /// Relative displacement `u` at every sample, from rest, under base acceleration `a`.
    pub fn displacement(&self, a: &[f64]) -> Vec<f64> {
        self.response(a).0
    }

    /// Relative displacement and velocity at every sample, from rest.
    pub fn response(&self, a: &[f64]) -> (Vec<f64>, Vec<f64>) {
        let mut out = vec![0.0; a.len()];
        let mut vel = vec![0.0; a.len()];
        let w2 = self.omega * self.omega;
        let w3 = w2 * self.omega;
        let (mut u, mut v) = (0.0, 0.0);
        let p = &self.phi;
        for i in 0..a.len().saturating_sub(1) {
            let r = (a[i + 1] - a[i]) / self.dt;
            let du = u - (-a[i] / w2 + 2.0 * self.damping * r / w3);
            let dv = v + r / w2;
            u = p[0][0] * du + p[0][1] * dv + (-a[i + 1] / w2 + 2.0 * self.damping * r / w3);
            v = p[1][0] * du + p[1][1] * dv - r / w2;
            out[i + 1] = u;
            vel[i + 1] = v;
        }
        (out, vel)
    }

    /// Pseudo-acceleration `ω²·u` at every sample.
    pub fn pseudo_acceleration(&self, a: &[f64]) -> Vec<f64> {
        let w2 = self.omega * self.omega;
        let mut u = self.displacement(a);
        u.iter_mut().for_each(|x| *x *= w2);
        u
    }

    /// `ω²·u` at `k` samples after a unit input sample (zero on either side), `k < n`: the
    /// influence of input sample `i` on the pseudo-acceleration at `m ≥ i` is this at `m − i`
    /// (for `i ≥ 1`: the input rises from the sample before).
    pub fn impulse_response(&self, n: usize) -> Vec<f64> {
        let mut a = vec![0.0; n + 1];
        a[1] = 1.0;
        let mut r = self.pseudo_acceleration(&a);
        r.remove(0);
        r
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Matrix2, Matrix4, Vector4};

    #[test]
    fn the_step_matrix_is_the_exponential() {
        for (t, z, dt) in [(1.0, 0.05, 0.01), (0.05, 0.05, 0.01), (10.0, 0.2, 0.02)] {
            let o = Oscillator::new(t, z, dt);
            let w = o.omega;
            let f = Matrix2::new(0.0, 1.0, -w * w, -2.0 * z * w);
            let e = (f * dt).exp();
            for i in 0..2 {
                for j in 0..2 {
                    assert!((e[(i, j)] - o.phi[i][j]).abs() < 1e-10 * (1.0 + e[(i, j)].abs()));
                }
            }
        }
    }

    /// The state (u, u̇, a, r) with a' = r, r' = 0 is linear and autonomous: its exponential is an
    /// independent exact solution of the same step.
    #[test]
    fn agrees_with_the_augmented_exponential_for_any_input() {
        let (t, z, dt) = (0.4, 0.05, 0.01);
        let o = Oscillator::new(t, z, dt);
        let w = o.omega;
        let a: Vec<f64> = (0..500)
            .map(|i| ((i * 37 % 17) as f64 - 8.0) * 0.1 + (i as f64 * 0.07).sin())
            .collect();
        let u = o.displacement(&a);
        #[rustfmt::skip]
        let m = Matrix4::new(
            0.0, 1.0, 0.0, 0.0,
            -w * w, -2.0 * z * w, -1.0, 0.0,
            0.0, 0.0, 0.0, 1.0,
            0.0, 0.0, 0.0, 0.0,
        );
        let e = (m * dt).exp();
        let (mut uu, mut vv) = (0.0, 0.0);
        for i in 0..a.len() - 1 {
            let r = (a[i + 1] - a[i]) / dt;
            let x = e * Vector4::new(uu, vv, a[i], r);
            uu = x[0];
            vv = x[1];
            assert!((uu - u[i + 1]).abs() < 1e-9 * (1.0 + uu.abs()), "{i}");
        }
    }

    #[test]
    fn undamped_step_and_resonance_by_hand() {
        // A constant base acceleration a0 from rest (undamped limit): u = −a0/ω²·(1 − cos ωt),
        // so the peak pseudo-acceleration is 2·a0 at any period.
        let o = Oscillator::new(0.5, 1e-9, 0.005);
        let a = vec![1.5; 400];
        let u = o.displacement(&a);
        for (i, ui) in u.iter().enumerate() {
            let t = i as f64 * 0.005;
            let want = -1.5 / o.omega.powi(2) * (1.0 - (o.omega * t).cos());
            assert!((ui - want).abs() < 1e-9, "{i}: {ui} vs {want}");
        }
        let psa = o.pseudo_acceleration(&a);
        let peak = psa.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        assert!((peak - 3.0).abs() < 1e-3, "{peak}");
        // At resonance in steady state a sine's amplification is 1/(2ζ).
        let z = 0.05;
        let o = Oscillator::new(1.0, z, 0.01);
        let a: Vec<f64> = (0..20_000)
            .map(|i| (2.0 * std::f64::consts::PI * i as f64 * 0.01).sin())
            .collect();
        let psa = o.pseudo_acceleration(&a);
        let steady = psa[15_000..].iter().fold(0.0f64, |m, v| m.max(v.abs()));
        assert!((steady - 1.0 / (2.0 * z)).abs() < 0.01, "{steady}");
        // The impulse response is the influence of one sample.
        let h = o.impulse_response(50);
        let mut one = vec![0.0; 60];
        one[10] = 1.0;
        let r = o.pseudo_acceleration(&one);
        for k in 0..50 {
            assert!((r[10 + k] - h[k]).abs() < 1e-12);
        }
    }
}
