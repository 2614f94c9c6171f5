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
use crate::noise::{NoiseDesign, NoiseWindow, WindowState};
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
    pub noise: NoiseDesign,
    pub spike_rate0_per_s: f64,
    pub spike_factor: f64,
    /// EWMA weight per block of the spike statistic (one hour).
    pub spike_lambda: f64,
    /// How long a channel's spike test must have stood at `watch` or above for `suspect`, ns.
    pub confirm_ns: i64,
}

impl ChannelDesign {
    /// `tests` is how many sequential tests share the sensor's false-alarm budget.
    pub fn new(config: &HealthConfig, tests: u32) -> ChannelDesign {
        let blocks_per_day = 86_400.0 / config.block_s;
        let tests = f64::from(tests.max(1));
        ChannelDesign {
            thresholds: Thresholds::from_arl(
                config.watch_arl_days * tests * blocks_per_day,
                config.suspect_arl_days * tests * blocks_per_day,
                1,
            ),
            stuck_s: config.stuck_s,
            dead_ratio: config.dead_variance_ratio,
            noise: NoiseDesign {
                high_ratio: config.noise_design_ratio,
                watch_windows: config.noise_watch_windows,
                confirm_ns: (config.confirm_s * 1e9) as i64,
            },
            spike_rate0_per_s: config.spike_allowed_per_hour / 3600.0,
            spike_factor: config.spike_design_factor,
            spike_lambda: (config.block_s / 3600.0).min(1.0),
            confirm_ns: (config.confirm_s * 1e9) as i64,
        }
    }
}

/// The noise test's state: windows judged and the run of `high` ones.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
struct NoiseState {
    judged: u64,
    masked: u64,
    loud: u64,
    last: Option<NoiseWindow>,
    /// Consecutive judged windows `high` (masked and loud ones neither count nor break it).
    high_run: u32,
    /// Start of the first window of the current run of `high`, ns.
    high_since_ns: Option<i64>,
    /// Windows since then, and how many of them were judged.
    span_windows: u64,
    span_judged: u64,
    suspect_since_ns: Option<i64>,
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
    noise: NoiseState,
    spikes: Sequential,
    spike_rate_ewma: f64,
    spike_blocks: u64,
    /// Since when the spike test has stood at `watch` or above, and its confirmed latch.
    spike_watch_since_ns: Option<i64>,
    spike_suspect_since_ns: Option<i64>,
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
            noise: NoiseState::default(),
            spikes: Sequential::new(design.thresholds),
            spike_rate_ewma: 0.0,
            spike_blocks: 0,
            spike_watch_since_ns: None,
            spike_suspect_since_ns: None,
        }
    }

    /// The white-noise variance the noise test holds the channel to: the record's at its upper
    /// confidence limit; none when the record states no noise.
    pub fn reference_var(&self) -> Option<f64> {
        self.reference_var
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

    /// One window of the noise floor ([`crate::noise`]).
    pub fn on_noise_window(&mut self, design: &ChannelDesign, w: &NoiseWindow, duration_ns: i64) {
        let n = &mut self.noise;
        if n.high_since_ns.is_some() {
            n.span_windows += 1;
        }
        match w.state {
            WindowState::Fine => {
                n.judged += 1;
                n.last = Some(*w);
                n.high_run = 0;
                n.high_since_ns = None;
                n.span_windows = 0;
                n.span_judged = 0;
            }
            WindowState::High => {
                n.judged += 1;
                n.last = Some(*w);
                n.high_run += 1;
                if n.high_since_ns.is_none() {
                    n.high_since_ns = Some(w.end_ns - duration_ns);
                    n.span_windows = 1;
                }
                n.span_judged += 1;
            }
            WindowState::Masked => n.masked += 1,
            WindowState::Loud => n.loud += 1,
        }
        if let (None, Some(since)) = (n.suspect_since_ns, n.high_since_ns) {
            let confirmed = w.end_ns - since >= design.noise.confirm_ns
                && 2 * n.span_judged >= n.span_windows
                && n.high_run >= design.noise.watch_windows;
            if confirmed {
                n.suspect_since_ns = Some(since);
            }
        }
    }

    /// Judges one block's stuck and spike tests. Spikes are judged in any motion: a block's
    /// spike raises its variance, so gating them on it would hide them, and motion makes
    /// bursts, not isolated spikes. Returns whether the channel was dead.
    pub fn on_block(
        &mut self,
        design: &ChannelDesign,
        b: &ChannelBlock,
        block_n: u32,
        end_ns: i64,
        duration_s: f64,
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
        let lambda0 = design.spike_rate0_per_s * duration_s;
        let f = design.spike_factor;
        let k = f64::from(b.spikes);
        self.spikes
            .update_one_sided(k * f.ln() - (f - 1.0) * lambda0, end_ns);
        // The test's latch is the confirmed one: a rate above the allowed must hold at `watch`
        // or above for `confirm_s` (a day of transients is not a faulty channel), and at
        // `suspect` at its end.
        let t = design.thresholds;
        let value = self.spikes.value();
        if value < t.watch {
            self.spike_watch_since_ns = None;
        } else {
            let since = *self
                .spike_watch_since_ns
                .get_or_insert(self.spikes.excursion_since_ns().unwrap_or(end_ns));
            if value >= t.suspect && end_ns - since >= design.confirm_ns {
                self.spike_suspect_since_ns.get_or_insert(since);
            }
        }
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
            ..TestReport::pending()
        }
    }

    pub fn noise_report(&self, design: &ChannelDesign) -> TestReport {
        let n = &self.noise;
        let (Some(last), Some(reference), Some(stated)) =
            (n.last, self.reference_var, self.stated_var)
        else {
            return TestReport {
                masked: n.masked,
                loud: n.loud,
                ..TestReport::pending()
            };
        };
        // The floor as a ratio of noise amplitudes to the record's stated noise.
        let ratio = (last.ratio * reference / stated).max(0.0).sqrt();
        // u(σ)/σ = ½·u(σ²)/σ², the floor's own and the stated noise's (√(2/ν)).
        let relative = (0.25 * last.log_sd * last.log_sd + 0.5 * self.stated_inv_dof).sqrt();
        let verdict = if n.suspect_since_ns.is_some() {
            Verdict::Suspect
        } else if n.high_run >= design.noise.watch_windows {
            Verdict::Watch
        } else {
            Verdict::Ok
        };
        TestReport {
            verdict,
            judged: true,
            statistic: ratio,
            uncertainty: ratio * relative,
            since_ns: match verdict {
                Verdict::Suspect => n.suspect_since_ns,
                Verdict::Watch => n.high_since_ns,
                Verdict::Ok => None,
            },
            evidence_nats: 0.0,
            observations: n.judged,
            reason: None,
            masked: n.masked,
            loud: n.loud,
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
        let verdict = if self.spike_suspect_since_ns.is_some() {
            Verdict::Suspect
        } else if self.spike_watch_since_ns.is_some() {
            Verdict::Watch
        } else {
            Verdict::Ok
        };
        TestReport {
            verdict,
            judged: true,
            statistic: self.spike_rate_ewma,
            uncertainty: var.sqrt(),
            since_ns: match verdict {
                Verdict::Suspect => self.spike_suspect_since_ns,
                Verdict::Watch => self.spike_watch_since_ns,
                Verdict::Ok => None,
            },
            evidence_nats: self.spikes.value(),
            observations: self.spikes.observations(),
            ..TestReport::pending()
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

    fn window(end_s: i64, state: WindowState, ratio: f64) -> NoiseWindow {
        NoiseWindow {
            end_ns: end_s * 1_000_000_000,
            state,
            ratio,
            log_sd: 0.1,
            support: 11,
            kept: 64,
        }
    }

    /// The noise verdicts from a sequence of windows of 40 s: two `high` in a row make
    /// `watch` from the first one's start; a `masked` window neither counts nor breaks the run;
    /// `fine` clears it; `suspect` only after `confirm_s` of it, dated from its start.
    #[test]
    fn noise_windows_make_watch_then_confirmed_suspect() {
        let config = HealthConfig {
            confirm_s: 400.0,
            ..HealthConfig::default()
        };
        let design = ChannelDesign::new(&config, 1);
        let mut ch = ChannelHealth::new(&design, Some(0.001), None);
        let d = 40 * 1_000_000_000;
        let feed = |ch: &mut ChannelHealth, s: i64, state, ratio| {
            ch.on_noise_window(&design, &window(s, state, ratio), d)
        };
        feed(&mut ch, 40, WindowState::Fine, 1.0);
        assert_eq!(ch.noise_report(&design).verdict, Verdict::Ok);
        feed(&mut ch, 80, WindowState::High, 4.0);
        assert_eq!(ch.noise_report(&design).verdict, Verdict::Ok);
        feed(&mut ch, 120, WindowState::Masked, 9.0);
        feed(&mut ch, 160, WindowState::High, 4.0);
        let r = ch.noise_report(&design);
        assert_eq!(r.verdict, Verdict::Watch);
        assert_eq!(r.since_ns, Some(40 * 1_000_000_000));
        assert_eq!(r.masked, 1);
        // The statistic is the floor's amplitude over the stated noise (the reference is the
        // stated one with no ν): √4.
        assert!((r.statistic - 2.0).abs() < 1e-12);
        feed(&mut ch, 200, WindowState::Fine, 1.2);
        assert_eq!(ch.noise_report(&design).verdict, Verdict::Ok);
        for s in (240..=640).step_by(40) {
            feed(&mut ch, s, WindowState::High, 4.0);
        }
        let r = ch.noise_report(&design);
        assert_eq!(r.verdict, Verdict::Suspect);
        assert_eq!(r.since_ns, Some(200 * 1_000_000_000));
        // Latched.
        feed(&mut ch, 680, WindowState::Fine, 1.0);
        assert_eq!(ch.noise_report(&design).verdict, Verdict::Suspect);
    }

    /// A span mostly masked does not confirm: half its windows must be judged.
    #[test]
    fn a_masked_span_does_not_confirm() {
        let config = HealthConfig {
            confirm_s: 400.0,
            ..HealthConfig::default()
        };
        let design = ChannelDesign::new(&config, 1);
        let mut ch = ChannelHealth::new(&design, Some(0.001), None);
        let d = 40 * 1_000_000_000;
        for (i, s) in (40..=1200).step_by(40).enumerate() {
            let state = if i % 3 == 0 {
                WindowState::High
            } else {
                WindowState::Masked
            };
            ch.on_noise_window(&design, &window(s, state, 4.0), d);
        }
        assert_eq!(ch.noise_report(&design).verdict, Verdict::Watch);
    }

    #[test]
    fn dead_by_constancy_nan_or_silence() {
        let design = ChannelDesign::new(&HealthConfig::default(), 1);
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
