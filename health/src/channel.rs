//! Channel health, per output channel and per block: dead or stuck, noise above the stated
//! output noise, spikes.
//!
//! - **Dead or stuck.** A block in which the channel never changed, was not finite for more
//!   than half its samples, or whose second-difference noise fell below `dead_variance_ratio`
//!   of the stated noise variance. For a healthy channel the last has probability
//!   `P(χ²_ν < ν·ratio)`, below 10⁻⁴⁰ for a one-second block at 100 Hz (ν = 51, ratio 0.01): a
//!   dead block is evidence enough, and `suspect` follows after `stuck_s` of them in a row.
//! - **Noise.** The block's second-difference variance `σ̂²`, with ν = 72/140 of its count, is
//!   a χ²_ν/ν multiple of the true variance. The log-likelihood ratio of variance `ρ·σ²_ref`
//!   against `σ²_ref` is `Λ = ν/2·((1 − 1/ρ)·σ̂²/σ²_ref − ln ρ)`, ρ the design ratio squared;
//!   `σ²_ref` is the record's `output_noise` squared at its upper 99.9 % confidence limit for
//!   the record's `output_noise_dof` (Wilson–Hilferty), so that a lab that happened to
//!   measure the noise low does not make a healthy sensor look noisy. Blocks in strong motion
//!   are not judged for noise.
//! - **Spikes.** The block's isolated spikes ([`crate::block`]) are Poisson with the allowed
//!   rate λ₀ in control; `Λ = k·ln F − (F − 1)·λ₀` for a rate F times higher.

use crate::block::ChannelBlock;
use crate::config::HealthConfig;
use crate::cusum::{Sequential, Thresholds, Verdict};
use crate::report::TestReport;

/// Standard normal quantile at 0.001, for the stated noise's upper confidence limit.
const Z_0_001: f64 = -3.090_232_306_167_813_5;

/// Upper 99.9 % confidence factor of a variance estimated with `dof` degrees of freedom:
/// `ν / χ²_ν(0.001)`, with the Wilson–Hilferty approximation of the χ² quantile. 1 for
/// infinitely many.
pub fn variance_upper_factor(dof: Option<f64>) -> f64 {
    let Some(nu) = dof.filter(|nu| nu.is_finite()) else {
        return 1.0;
    };
    let nu = nu.max(1.0);
    let c = 2.0 / (9.0 * nu);
    let cube = (1.0 - c + Z_0_001 * c.sqrt()).max(1e-3);
    1.0 / cube.powi(3)
}

/// The settings a channel's tests share, derived once per sensor.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct ChannelDesign {
    pub thresholds: Thresholds,
    pub stuck_s: f64,
    pub dead_ratio: f64,
    /// ln ρ and 1 − 1/ρ of the noise test.
    pub noise_ln_rho: f64,
    pub noise_slope: f64,
    pub spike_rate0_per_s: f64,
    pub spike_factor: f64,
    /// EWMA weights per block of the noise (ten minutes) and spike (one hour) statistics.
    pub noise_lambda: f64,
    pub spike_lambda: f64,
}

impl ChannelDesign {
    pub fn new(config: &HealthConfig) -> ChannelDesign {
        let blocks_per_day = 86_400.0 / config.block_s;
        let rho = config.noise_design_ratio.powi(2);
        ChannelDesign {
            thresholds: Thresholds::from_arl(
                config.watch_arl_days * blocks_per_day,
                config.suspect_arl_days * blocks_per_day,
                1,
            ),
            stuck_s: config.stuck_s,
            dead_ratio: config.dead_variance_ratio,
            noise_ln_rho: rho.ln(),
            noise_slope: 1.0 - 1.0 / rho,
            spike_rate0_per_s: config.spike_allowed_per_hour / 3600.0,
            spike_factor: config.spike_design_factor,
            noise_lambda: (config.block_s / 600.0).min(1.0),
            spike_lambda: (config.block_s / 3600.0).min(1.0),
        }
    }
}

/// One output channel's tests.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct ChannelHealth {
    /// The record's noise variance, output unit², and the one the noise test holds it to.
    stated_var: Option<f64>,
    reference_var: Option<f64>,
    stated_inv_dof: f64,
    blocks: u64,
    dead_run_s: f64,
    dead_since_ns: Option<i64>,
    stuck_since_ns: Option<i64>,
    last_block_s: f64,
    noise: Sequential,
    noise_ratio_ewma: f64,
    noise_dof_ewma: f64,
    noise_blocks: u64,
    spikes: Sequential,
    spike_rate_ewma: f64,
    spike_blocks: u64,
}

impl ChannelHealth {
    pub fn new(
        design: &ChannelDesign,
        stated_noise: Option<f64>,
        stated_dof: Option<f64>,
    ) -> ChannelHealth {
        let stated_var = stated_noise.filter(|s| *s > 0.0).map(|s| s * s);
        ChannelHealth {
            stated_var,
            reference_var: stated_var.map(|v| v * variance_upper_factor(stated_dof)),
            stated_inv_dof: stated_dof.map_or(0.0, |nu| 1.0 / nu),
            blocks: 0,
            dead_run_s: 0.0,
            dead_since_ns: None,
            stuck_since_ns: None,
            last_block_s: 0.0,
            noise: Sequential::new(design.thresholds),
            noise_ratio_ewma: f64::NAN,
            noise_dof_ewma: 0.0,
            noise_blocks: 0,
            spikes: Sequential::new(design.thresholds),
            spike_rate_ewma: 0.0,
            spike_blocks: 0,
        }
    }

    /// The threshold of spike candidates in the next block: the configured number of
    /// second-difference standard deviations of the larger of the stated and the last
    /// measured noise.
    pub fn spike_threshold(&self, sigmas: f64, measured_var: Option<f64>) -> f64 {
        let var = match (self.stated_var, measured_var) {
            (Some(s), Some(m)) => s.max(m),
            (Some(v), None) | (None, Some(v)) => v,
            (None, None) => return f64::INFINITY,
        };
        sigmas * (6.0 * var).sqrt()
    }

    /// Whether the block shows a dead channel.
    pub fn is_dead(&self, b: &ChannelBlock, block_n: u32, dead_ratio: f64) -> bool {
        if 2 * b.n_finite < block_n {
            return true;
        }
        if b.n_finite >= 2 && b.n_changes == 0 {
            return true;
        }
        match (self.stated_var, b.noise_var()) {
            (Some(stated), Some(var)) if b.d2_count >= 10 => var < dead_ratio * stated,
            _ => false,
        }
    }

    /// Judges one block; `judge_noise` is false in strong motion. Spikes are judged in any
    /// motion: a block's spike raises its variance, so gating them on it would hide them, and
    /// motion makes bursts, not isolated spikes. Returns whether the channel was dead.
    pub fn on_block(
        &mut self,
        design: &ChannelDesign,
        b: &ChannelBlock,
        block_n: u32,
        end_ns: i64,
        duration_s: f64,
        judge_noise: bool,
    ) -> bool {
        self.blocks += 1;
        self.last_block_s = duration_s;
        let dead = self.is_dead(b, block_n, design.dead_ratio);
        if dead {
            let start_ns = end_ns - (duration_s * 1e9) as i64;
            let since = *self.dead_since_ns.get_or_insert(start_ns);
            self.dead_run_s += duration_s;
            // The run is counted in whole blocks, which a float sum can leave a hair short.
            if self.dead_run_s >= design.stuck_s * (1.0 - 1e-9) {
                self.stuck_since_ns.get_or_insert(since);
            }
            return true;
        }
        self.dead_run_s = 0.0;
        self.dead_since_ns = None;
        if let (true, Some(reference), Some(stated), Some(var)) = (
            judge_noise,
            self.reference_var,
            self.stated_var,
            b.noise_var(),
        ) {
            if b.d2_count >= 10 {
                let nu = b.noise_dof();
                let llr = 0.5 * nu * (design.noise_slope * var / reference - design.noise_ln_rho);
                self.noise.update_one_sided(llr, end_ns);
                let ratio = var / stated;
                let lambda = design.noise_lambda;
                if self.noise_blocks == 0 {
                    self.noise_ratio_ewma = ratio;
                    self.noise_dof_ewma = nu;
                } else {
                    self.noise_ratio_ewma += lambda * (ratio - self.noise_ratio_ewma);
                    // Degrees of freedom of an EWMA of χ² variates: ν·(2 − λ)/λ at most, and
                    // no more than the blocks so far hold.
                    self.noise_dof_ewma =
                        (self.noise_dof_ewma + nu).min(nu * (2.0 - lambda) / lambda);
                }
                self.noise_blocks += 1;
            }
        }
        let lambda0 = design.spike_rate0_per_s * duration_s;
        let f = design.spike_factor;
        let k = f64::from(b.spikes);
        self.spikes
            .update_one_sided(k * f.ln() - (f - 1.0) * lambda0, end_ns);
        let rate = k * 3600.0 / duration_s;
        if self.spike_blocks == 0 {
            self.spike_rate_ewma = rate;
        } else {
            self.spike_rate_ewma += design.spike_lambda * (rate - self.spike_rate_ewma);
        }
        self.spike_blocks += 1;
        false
    }

    pub fn stuck_report(&self) -> TestReport {
        let verdict = if self.stuck_since_ns.is_some() {
            Verdict::Suspect
        } else if self.dead_run_s > 0.0 {
            Verdict::Watch
        } else {
            Verdict::Ok
        };
        TestReport {
            verdict,
            judged: self.blocks > 0,
            statistic: self.dead_run_s,
            uncertainty: self.last_block_s,
            since_ns: match verdict {
                Verdict::Suspect => self.stuck_since_ns,
                Verdict::Watch => self.dead_since_ns,
                Verdict::Ok => None,
            },
            evidence_nats: 0.0,
            observations: self.blocks,
        }
    }

    pub fn noise_report(&self) -> TestReport {
        if self.noise_blocks == 0 {
            return TestReport::pending();
        }
        let ratio = self.noise_ratio_ewma.max(0.0).sqrt();
        // u(σ)/σ = ½·u(σ²)/σ² = ½·√(2/ν) for each of the measured and the stated variance.
        let relative = (0.5 / self.noise_dof_ewma + 0.5 * self.stated_inv_dof).sqrt();
        TestReport {
            verdict: self.noise.verdict(),
            judged: true,
            statistic: ratio,
            uncertainty: ratio * relative,
            since_ns: self.noise.since_ns(),
            evidence_nats: self.noise.value(),
            observations: self.noise.observations(),
        }
    }

    pub fn spike_report(&self, design: &ChannelDesign, block_s: f64) -> TestReport {
        if self.spike_blocks == 0 {
            return TestReport::pending();
        }
        let lambda = design.spike_lambda;
        // Var of a block's count × 3600/d is rate·3600/d; an EWMA keeps λ/(2 − λ) of it. With
        // no spike seen, the rate one spike in the window would give stands for it.
        let window_h = block_s * (2.0 - lambda) / lambda / 3600.0;
        let floor = 1.0 / window_h.min(self.spike_blocks as f64 * block_s / 3600.0);
        let var = self.spike_rate_ewma.max(floor) * lambda / (2.0 - lambda) * 3600.0 / block_s;
        TestReport {
            verdict: self.spikes.verdict(),
            judged: true,
            statistic: self.spike_rate_ewma,
            uncertainty: var.sqrt(),
            since_ns: self.spikes.since_ns(),
            evidence_nats: self.spikes.value(),
            observations: self.spikes.observations(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Wilson–Hilferty against tabulated χ² quantiles: χ²₁₀₀(0.001) = 61.918, so the factor is
    /// 100/61.918 = 1.6150; χ²₁₀(0.001) = 1.479, factor 6.76, where the approximation is 7 %
    /// high (on the side that holds the sensor to a larger noise).
    #[test]
    fn upper_factor_matches_chi_square_tables() {
        assert!((variance_upper_factor(Some(100.0)) - 1.6150).abs() < 0.002);
        let small = variance_upper_factor(Some(10.0));
        assert!(small > 6.76 && small < 6.76 * 1.08, "{small}");
        assert_eq!(variance_upper_factor(None), 1.0);
        let big = variance_upper_factor(Some(20_000.0));
        assert!((big - 1.0 - 3.09 * (2.0f64 / 20_000.0).sqrt()).abs() < 2e-3);
    }

    /// The noise ratio's log-likelihood by hand: ν = 72/140·100 = 51.43, ρ = 4, σ̂² = 4σ²:
    /// Λ = 25.71·(0.75·4 − ln 4) = 41.48.
    #[test]
    fn noise_llr_by_hand() {
        let config = HealthConfig::default();
        let design = ChannelDesign::new(&config);
        let mut ch = ChannelHealth::new(&design, Some(0.001), None);
        let b = ChannelBlock {
            n_finite: 100,
            n_changes: 99,
            d2_sum: 4.0 * 6.0 * 1e-6 * 100.0,
            d2_count: 100,
            ..Default::default()
        };
        ch.on_block(&design, &b, 100, 1_000_000_000, 1.0, true);
        let nu = 72.0 / 140.0 * 100.0;
        let expect = 0.5 * nu * (0.75 * 4.0 - 4f64.ln());
        assert!((ch.noise_report().evidence_nats - expect).abs() < 1e-9);
        assert!((ch.noise_report().statistic - 2.0).abs() < 1e-12);
        // Thresholds: ln(30·86400) = 14.77 and ln(10⁴·86400) = 20.58 nats.
        assert!((design.thresholds.watch - (30.0f64 * 86_400.0).ln()).abs() < 1e-12);
        assert!((design.thresholds.suspect - (1e4f64 * 86_400.0).ln()).abs() < 1e-12);
        assert_eq!(ch.noise_report().verdict, Verdict::Suspect);
        assert_eq!(ch.noise_report().since_ns, Some(1_000_000_000));
    }

    #[test]
    fn dead_by_constancy_nan_or_silence() {
        let design = ChannelDesign::new(&HealthConfig::default());
        let ch = ChannelHealth::new(&design, Some(0.001), None);
        let healthy = ChannelBlock {
            n_finite: 100,
            n_changes: 99,
            d2_sum: 6e-6 * 100.0,
            d2_count: 100,
            ..Default::default()
        };
        assert!(!ch.is_dead(&healthy, 100, 0.01));
        let constant = ChannelBlock {
            n_changes: 0,
            d2_sum: 0.0,
            ..healthy
        };
        assert!(ch.is_dead(&constant, 100, 0.01));
        let silent = ChannelBlock {
            d2_sum: 6e-6 * 100.0 * 0.009,
            ..healthy
        };
        assert!(ch.is_dead(&silent, 100, 0.01));
        let nan = ChannelBlock {
            n_finite: 49,
            ..healthy
        };
        assert!(ch.is_dead(&nan, 100, 0.01));
    }
}
