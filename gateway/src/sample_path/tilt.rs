//! Inclination from the low band of the static-corrected output, with propagated uncertainty.
//!
//! The raw outputs go through a second-order Butterworth low pass (`tilt_cutoff_hz`, 0.1 Hz by
//! default, which takes building sway at 1–5 Hz down at least a hundredfold); since the
//! correction is affine, correcting the low-passed output equals low-passing the corrected one.
//! From `a = S_s⁻¹·V_lp + q_s`:
//!
//! ```text
//! roll  = atan2(a_y, a_z)
//! pitch = atan2(a_x, √(a_y² + a_z²))
//! ```
//!
//! the lab's convention (README, static input): pitch is the elevation of the x axis above the
//! horizontal, roll the rotation about it that raises y, so a = g·(sin pitch, sin roll·cos pitch,
//! cos roll·cos pitch). Where an angle is undefined (roll with the x axis vertical) its
//! uncertainty is reported as [`UNDEFINED_UNCERTAINTY_DEG`].
//!
//! and the standard uncertainties are `√(J·Σ_a·Jᵀ)` with `Σ_a` the full 3×3 covariance of `a`
//! from the static set ([`SetCorrector::covariance_filtered`]: parameters, stated part, noise) and
//! `J` the gradient of each angle.
//!
//! ## What a tilt sample describes
//!
//! The low pass delays the low band by its group delay at DC, `τ = √2/(2π·fc)` (2.25 s at
//! 0.1 Hz): a building that heels over at a steady rate comes out of the filter exactly τ
//! late. A tilt sample is therefore stamped with the instant its value describes, the time of
//! the last sample behind it minus τ, and the lag costs nothing at a steady rate. What the
//! filter does not render exactly is added to the covariance of the low-passed output, per
//! channel, before it goes through `S⁻¹` and the angles' gradients ([`TiltFilter`]):
//!
//! - the white output noise, scaled by the filter's noise gain Σh² (0.0022 at 0.1 Hz and
//!   100 samples/s) rather than taken whole;
//! - the ripple the filter lets through (sway at a hundredth of its amplitude at ten times the
//!   corner): the mean square of the filtered output about a straight line over the last
//!   second;
//! - a change of rate, which the filter renders only after a transient of a few seconds: τ
//!   times the change of the filtered output's slope between consecutive seconds, held with
//!   the filter's own decay `exp(−ζω·t)`, which bounds that transient.
//!
//! Nothing is published until the filter has settled from its start: `ln(100)/(ζω)` of data
//! (10.4 s at 0.1 Hz), by which time what the start left in the filter is below 1 %.

use serde::{Deserialize, Serialize};
use triax_calibration::corrector::{CovarianceParts, InverseDof, SetCorrector};
use triax_calibration::student::welch_satterthwaite;

use super::filter::{Biquad3, Coefficients};

/// Angles and their standard uncertainties, degrees.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Tilt {
    pub roll_deg: f64,
    pub pitch_deg: f64,
    pub roll_uncertainty_deg: f64,
    pub pitch_uncertainty_deg: f64,
    /// For both angles: Student's t at the smaller of their Welch–Satterthwaite effective
    /// degrees of freedom, or the set's own factor when it states none.
    pub coverage_factor: f64,
}

/// Uncertainty reported for an angle that is undefined at the sample: the widest an angle can
/// be wrong. (JSON has no infinity.)
pub const UNDEFINED_UNCERTAINTY_DEG: f64 = 180.0;

/// Variance of an angle with gradient `j` (per m/s²) under covariance `c`, rad².
fn angle_variance(j: [f64; 3], c: &[[f64; 3]; 3]) -> f64 {
    let mut v = 0.0;
    for k in 0..3 {
        for l in 0..3 {
            v += j[k] * c[k][l] * j[l];
        }
    }
    v
}

/// Effective degrees of freedom of an angle with gradient `j`: Welch–Satterthwaite over the
/// contributions of `parts`.
fn angle_dof(j: [f64; 3], parts: &CovarianceParts, inv: InverseDof) -> f64 {
    welch_satterthwaite(&[
        (angle_variance(j, &parts.parameters), inv.parameters),
        (angle_variance(j, &parts.stated), inv.stated),
        (angle_variance(j, &parts.noise), inv.noise),
        (angle_variance(j, &parts.extra), 0.0),
    ])
}

/// Standard uncertainty in degrees of an angle with gradient `j` (per m/s²).
fn angle_uncertainty_deg(j: [f64; 3], c: &[[f64; 3]; 3]) -> f64 {
    let v = angle_variance(j, c);
    if v.is_finite() {
        // Round-off can take a zero variance a hair below zero.
        v.max(0.0)
            .sqrt()
            .to_degrees()
            .min(UNDEFINED_UNCERTAINTY_DEG)
    } else {
        UNDEFINED_UNCERTAINTY_DEG
    }
}

/// The tilt low pass and what it knows of its own errors (see the module's documentation).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TiltFilter {
    lp: Biquad3,
    sample_rate_hz: f64,
    delay_s: f64,
    noise_gain: f64,
    /// Samples through the filter since it was primed, up to `settle_samples`.
    seen: u64,
    settle_samples: u64,
    /// `exp(−ζω·1 s)`: how much of a rate change's transient is left a second later.
    decay_per_block: f64,
    block_len: u32,
    block: Block,
    last_slope: Option<[f64; 3]>,
    /// Per channel: ripple about a line in the last whole second, V².
    ripple_var: [f64; 3],
    /// Per channel: the decaying envelope of slope changes, V/s.
    rate_change: [f64; 3],
    /// The sensor's temperature through the same low pass (lane 0) and its latest output, so
    /// that a record's temperature model is applied at the temperature of the instant the tilt
    /// describes.
    temperature: Option<(Biquad3, f64)>,
}

/// Sums for a least-squares line through one second of filtered output, taken relative to
/// the block's first value so that a 2.4 V level does not swamp a microvolt ripple.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
struct Block {
    n: u32,
    y0: [f64; 3],
    sy: [f64; 3],
    siy: [f64; 3],
    syy: [f64; 3],
}

/// What the tilt estimate needs from the filter at the moment of publishing.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct LowBandError {
    pub noise_gain: f64,
    /// Variance per output channel beyond the noise: ripple and unfollowed rate change, V².
    pub extra_output_var: [f64; 3],
}

impl TiltFilter {
    pub fn new(cutoff_hz: f64, sample_rate_hz: f64) -> TiltFilter {
        let c = Coefficients::low_pass(cutoff_hz, sample_rate_hz);
        // Butterworth: ζ = 1/√2; the start's transient decays as exp(−ζω·t).
        let decay_rate = std::f64::consts::FRAC_1_SQRT_2 * 2.0 * std::f64::consts::PI * cutoff_hz;
        TiltFilter {
            lp: Biquad3::new(c),
            sample_rate_hz,
            delay_s: c.dc_delay_samples() / sample_rate_hz,
            noise_gain: c.noise_gain(),
            seen: 0,
            settle_samples: ((100f64).ln() / decay_rate * sample_rate_hz).ceil() as u64,
            decay_per_block: (-decay_rate).exp(),
            block_len: sample_rate_hz.round().max(2.0) as u32,
            block: Block::default(),
            last_slope: None,
            ripple_var: [0.0; 3],
            rate_change: [0.0; 3],
            temperature: None,
        }
    }

    /// Takes a batch's temperature through the low pass, once per sample it stood for.
    pub fn step_temperature(&mut self, temperature_c: f64, samples: usize) {
        let c = *self.lp.coefficients();
        let (lp, out) = self
            .temperature
            .get_or_insert_with(|| (Biquad3::new(c), temperature_c));
        for _ in 0..samples {
            *out = lp.step([temperature_c; 3])[0];
        }
    }

    /// The low-passed temperature, °C: that of the instant the filtered outputs describe.
    pub fn temperature_c(&self) -> Option<f64> {
        self.temperature.as_ref().map(|(_, t)| *t)
    }

    pub fn is_primed(&self) -> bool {
        self.lp.is_primed()
    }

    pub fn prime(&mut self, x: [f64; 3]) {
        self.lp.prime(x);
    }

    /// Whether the start has faded from the filter (below 1 %).
    pub fn settled(&self) -> bool {
        self.seen >= self.settle_samples
    }

    /// The filter's delay at DC, ns: a tilt sample describes this long before its last input.
    pub fn delay_ns(&self) -> i64 {
        (self.delay_s * 1e9).round() as i64
    }

    pub fn error(&self) -> LowBandError {
        LowBandError {
            noise_gain: self.noise_gain,
            extra_output_var: [0, 1, 2]
                .map(|k| self.ripple_var[k] + (self.delay_s * self.rate_change[k]).powi(2)),
        }
    }

    /// Filters one finite sample (callers never pass NaN: it would poison the state).
    #[inline]
    pub fn step(&mut self, x: [f64; 3]) -> [f64; 3] {
        let y = self.lp.step(x);
        self.seen = (self.seen + 1).min(self.settle_samples);
        let b = &mut self.block;
        if b.n == 0 {
            b.y0 = y;
        }
        let i = f64::from(b.n);
        for (k, yk) in y.iter().enumerate() {
            let d = yk - b.y0[k];
            b.sy[k] += d;
            b.siy[k] += i * d;
            b.syy[k] += d * d;
        }
        b.n += 1;
        if b.n == self.block_len {
            self.close_block();
        }
        y
    }

    fn close_block(&mut self) {
        let b = std::mem::take(&mut self.block);
        let n = f64::from(b.n);
        // Σi and Σi² over i = 0..n−1, centred.
        let si = n * (n - 1.0) / 2.0;
        let sxx = (n - 1.0) * n * (n + 1.0) / 12.0;
        let slope = [0, 1, 2].map(|k| {
            let sxy = b.siy[k] - si * b.sy[k] / n;
            let syy = b.syy[k] - b.sy[k] * b.sy[k] / n;
            self.ripple_var[k] = ((syy - sxy * sxy / sxx) / n).max(0.0);
            sxy / sxx * self.sample_rate_hz
        });
        if let Some(last) = self.last_slope {
            for k in 0..3 {
                let change = (slope[k] - last[k]).abs();
                self.rate_change[k] = change.max(self.rate_change[k] * self.decay_per_block);
            }
        }
        self.last_slope = Some(slope);
    }
}

/// Tilt of the static-corrected, low-passed output `output_lp`, with the filter's own errors.
pub fn tilt(static_set: &SetCorrector, output_lp: [f64; 3], low_band: &LowBandError) -> Tilt {
    let a = static_set.accel(output_lp);
    let parts = static_set.covariance_filtered_parts(
        output_lp,
        low_band.noise_gain,
        low_band.extra_output_var,
    );
    let cov = parts.total();
    let [ax, ay, az] = a;
    let r2 = ay * ay + az * az;
    let r = r2.sqrt();
    let n2 = ax * ax + r2;
    let roll = ay.atan2(az);
    let pitch = ax.atan2(r);
    // At r = 0 (x axis vertical) roll is undefined: the gradients are not finite.
    let j_roll = [0.0, az / r2, -ay / r2];
    let j_pitch = [r / n2, -ax * ay / (r * n2), -ax * az / (r * n2)];
    Tilt {
        roll_deg: roll.to_degrees(),
        pitch_deg: pitch.to_degrees(),
        roll_uncertainty_deg: angle_uncertainty_deg(j_roll, &cov),
        pitch_uncertainty_deg: angle_uncertainty_deg(j_pitch, &cov),
        coverage_factor: if static_set.states_dof() {
            let inv = static_set.inverse_dof();
            // An undefined angle (NaN ν; its uncertainty already says 180°) is passed over;
            // with both undefined, the factor is that of ν = 1.
            let nu = angle_dof(j_roll, &parts, inv).min(angle_dof(j_pitch, &parts, inv));
            static_set.coverage_factor_at(nu)
        } else {
            static_set.coverage_factor()
        },
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use triax_calibration::corrector::Corrector;
    use triax_protocol::record::{sample, SetKind};

    /// A single sample's errors: the noise whole, nothing else.
    const UNFILTERED: LowBandError = LowBandError {
        noise_gain: 1.0,
        extra_output_var: [0.0; 3],
    };

    #[test]
    fn angles_and_uncertainty_agree_with_finite_differences() {
        let mut r = sample::record("t", 1);
        r.static_set.sensitivity = [[0.1, 0.0, 0.0], [0.0, 0.1, 0.0], [0.0, 0.0, 0.1]];
        r.static_set.offset = [0.0; 3];
        let c = Corrector::from_record(&r).unwrap();
        let set = c.set(SetKind::Static);
        let g: f64 = 9.81;
        let (roll, pitch) = (5f64.to_radians(), -3f64.to_radians());
        let a = [
            g * pitch.sin(),
            g * pitch.cos() * roll.sin(),
            g * pitch.cos() * roll.cos(),
        ];
        let v = a.map(|x| x * 0.1);
        let t = tilt(set, v, &UNFILTERED);
        assert!((t.roll_deg - 5.0).abs() < 1e-9, "{t:?}");
        assert!((t.pitch_deg + 3.0).abs() < 1e-9, "{t:?}");
        // Axis-independent noise u per axis: u_roll ≈ u / (g cos pitch) rad.
        let u = set.correct(v).uncertainty_mps2;
        let expect = (u[1].max(u[2]) / (g * pitch.cos())).to_degrees();
        assert!(t.roll_uncertainty_deg > 0.5 * expect && t.roll_uncertainty_deg < 2.0 * expect);
        assert!(t.pitch_uncertainty_deg > 0.0);
        // Finite differences of the pitch against the gradient's direction: raising x raises
        // pitch.
        let up = tilt(set, [v[0] + 1e-4, v[1], v[2]], &UNFILTERED);
        assert!(up.pitch_deg > t.pitch_deg);
    }

    #[test]
    fn an_undefined_roll_has_the_widest_uncertainty() {
        let mut r = sample::record("t", 1);
        r.static_set.sensitivity = [[0.1, 0.0, 0.0], [0.0, 0.1, 0.0], [0.0, 0.0, 0.1]];
        r.static_set.offset = [0.0; 3];
        let c = Corrector::from_record(&r).unwrap();
        // x straight up: a = (g, 0, 0).
        let t = tilt(c.set(SetKind::Static), [0.981, 0.0, 0.0], &UNFILTERED);
        assert!((t.pitch_deg - 90.0).abs() < 1e-9, "{t:?}");
        assert_eq!(t.roll_uncertainty_deg, UNDEFINED_UNCERTAINTY_DEG);
    }
}
