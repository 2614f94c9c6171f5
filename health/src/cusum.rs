//! Sequential verdicts: Page's CUSUM on log-likelihood ratios, with thresholds set from a
//! design false-alarm rate.
//!
//! Each test turns an observation into the log-likelihood ratio `Λ = ln p₁(x)/p₀(x)` of "the
//! calibration no longer holds" (the design alternative, p₁) against "it holds" (p₀), and keeps
//! `S = max(0, S + Λ)`. The verdict is `watch` while `S` is at or above the watch threshold and
//! `suspect` from the moment it reaches the suspect threshold; `suspect` then holds until the
//! test is replaced (a new calibration in force), since a calibration that was once found not to
//! hold is not trusted again on the strength of later quiet data.
//!
//! **False-alarm rate.** For a CUSUM on exact log-likelihood ratios, the average run length to a
//! false alarm is at least `e^h` observations (Lorden 1971, from Wald's inequality: an SPRT under
//! p₀ reaches `h` with probability at most `e^{−h}`); a two-sided test is two such CUSUMs, each
//! given half the rate. [`Thresholds::from_arl`] sets `h = ln(sides · ARL)`. The bound is
//! conservative: [`gaussian_arl`] (Siegmund's approximation) gives the run lengths a Gaussian
//! statistic actually has, and the tests measure them by Monte Carlo.
//!
//! **Since when.** The start of the CUSUM's current excursion (the first observation after it
//! last stood at zero) is the maximum-likelihood change point for a step, and is what a verdict
//! reports as its start.

/// A test's verdict, worst last so that `max` combines them.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub enum Verdict {
    Ok,
    Watch,
    Suspect,
}

impl Verdict {
    pub fn as_str(self) -> &'static str {
        match self {
            Verdict::Ok => "ok",
            Verdict::Watch => "watch",
            Verdict::Suspect => "suspect",
        }
    }
}

/// The two thresholds of a sequential test, in nats of accumulated log-likelihood ratio.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Thresholds {
    pub watch: f64,
    pub suspect: f64,
}

impl Thresholds {
    /// Thresholds whose average run length to a false alarm is at least `watch_arl_obs` and
    /// `suspect_arl_obs` observations, for a test made of `sides` one-sided CUSUMs (Lorden's
    /// bound, `h = ln(sides · ARL)`).
    pub fn from_arl(watch_arl_obs: f64, suspect_arl_obs: f64, sides: u32) -> Thresholds {
        let sides = f64::from(sides.max(1));
        Thresholds {
            watch: (sides * watch_arl_obs.max(1.0)).ln(),
            suspect: (sides * suspect_arl_obs.max(1.0)).ln(),
        }
    }
}

/// One one-sided CUSUM: `S = max(0, S + Λ)`.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Cusum {
    s: f64,
    /// Start of the current excursion above zero, ns.
    since_ns: Option<i64>,
}

impl Cusum {
    /// Adds one observation's log-likelihood ratio, observed at `timestamp_ns`.
    #[inline]
    pub fn update(&mut self, llr: f64, timestamp_ns: i64) {
        // A NaN ratio would stick in S forever: such an observation carries no evidence.
        if llr.is_nan() {
            return;
        }
        let before = self.s;
        self.s = (self.s + llr).max(0.0);
        if self.s == 0.0 {
            self.since_ns = None;
        } else if before == 0.0 {
            self.since_ns = Some(timestamp_ns);
        }
    }

    pub fn value(&self) -> f64 {
        self.s
    }

    pub fn since_ns(&self) -> Option<i64> {
        self.since_ns
    }
}

/// A sequential test: one or two CUSUMs, thresholds, and a latched `suspect`.
#[derive(Debug, Clone, PartialEq)]
pub struct Sequential {
    thresholds: Thresholds,
    up: Cusum,
    down: Cusum,
    /// When `suspect` was first reached: the start of the excursion that reached it.
    suspect_since_ns: Option<i64>,
    observations: u64,
}

impl Sequential {
    pub fn new(thresholds: Thresholds) -> Sequential {
        Sequential {
            thresholds,
            up: Cusum::default(),
            down: Cusum::default(),
            suspect_since_ns: None,
            observations: 0,
        }
    }

    /// One observation of a one-sided test (only increases are sought).
    pub fn update_one_sided(&mut self, llr: f64, timestamp_ns: i64) {
        self.update(llr, f64::NEG_INFINITY, timestamp_ns);
    }

    /// One observation of a two-sided test: the ratios for an increase and for a decrease.
    pub fn update(&mut self, llr_up: f64, llr_down: f64, timestamp_ns: i64) {
        self.observations += 1;
        self.up.update(llr_up, timestamp_ns);
        self.down.update(llr_down, timestamp_ns);
        if self.suspect_since_ns.is_none() {
            let worst = self.worst();
            if worst.value() >= self.thresholds.suspect {
                self.suspect_since_ns = Some(worst.since_ns.unwrap_or(timestamp_ns));
            }
        }
    }

    /// Latches `suspect` from outside (a check whose evidence is not a likelihood ratio).
    pub fn latch(&mut self, since_ns: i64) {
        self.suspect_since_ns.get_or_insert(since_ns);
    }

    fn worst(&self) -> &Cusum {
        if self.down.value() > self.up.value() {
            &self.down
        } else {
            &self.up
        }
    }

    pub fn verdict(&self) -> Verdict {
        if self.suspect_since_ns.is_some() {
            Verdict::Suspect
        } else if self.worst().value() >= self.thresholds.watch {
            Verdict::Watch
        } else {
            Verdict::Ok
        }
    }

    /// Since when the verdict has held: the latch for `suspect`, the excursion's start for
    /// `watch`, none for `ok`.
    pub fn since_ns(&self) -> Option<i64> {
        match self.verdict() {
            Verdict::Suspect => self.suspect_since_ns,
            Verdict::Watch => self.worst().since_ns(),
            Verdict::Ok => None,
        }
    }

    /// The larger of the two CUSUMs, nats.
    pub fn value(&self) -> f64 {
        self.worst().value()
    }

    /// The CUSUMs for an increase and for a decrease, nats.
    pub fn sides(&self) -> (f64, f64) {
        (self.up.value(), self.down.value())
    }

    /// Whether the larger excursion is a decrease.
    pub fn is_down(&self) -> bool {
        self.down.value() > self.up.value()
    }

    /// Start of the current excursion of the larger CUSUM, if any.
    pub fn excursion_since_ns(&self) -> Option<i64> {
        self.worst().since_ns()
    }

    pub fn thresholds(&self) -> Thresholds {
        self.thresholds
    }

    pub fn observations(&self) -> u64 {
        self.observations
    }
}

/// Siegmund's approximation to the average run length of the one-sided CUSUM
/// `S = max(0, S + z − k)` with threshold `h`, for `z ~ N(μ, 1)`:
/// `ARL ≈ (e^{−2Δb} + 2Δb − 1) / (2Δ²)`, `Δ = μ − k`, `b = h + 1.166` (the 1.166 accounts for
/// the overshoot of a Gaussian walk over the boundary); `b²` at `Δ = 0`.
pub fn siegmund_arl(mu: f64, k: f64, h: f64) -> f64 {
    let delta = mu - k;
    let b = h + 1.166;
    if delta.abs() < 1e-9 {
        return b * b;
    }
    let x = 2.0 * delta * b;
    ((-x).exp() + x - 1.0) / (2.0 * delta * delta)
}

/// Average run length, in observations, of the log-likelihood-ratio CUSUM for a Gaussian mean
/// shift designed for `design_shift` standard deviations with threshold `h_nats`, when the true
/// shift is `shift` standard deviations: the increments `δ(z − δ/2)` are `δ` times those of
/// [`siegmund_arl`] with `k = δ/2`, so the threshold in z units is `h/δ`. At `shift = 0` it is
/// the run length to a false alarm; at the design shift, the detection delay.
pub fn gaussian_arl(shift: f64, design_shift: f64, h_nats: f64) -> f64 {
    siegmund_arl(shift, design_shift / 2.0, h_nats / design_shift)
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{rngs::SmallRng, Rng, SeedableRng};
    use rand_distr::StandardNormal;

    /// Siegmund's formula evaluated by hand for k = ½, the design every textbook tabulates
    /// (exact values by Markov chain: 336 and 8.4 at h = 4, 930 and 10.4 at h = 5).
    #[test]
    fn siegmund_matches_the_tables() {
        // h = 4: b = 5.166, Δ = −½: (e^{5.166} − 5.166 − 1)/0.5 = 338.09; Δ = ½: 8.343.
        assert!((siegmund_arl(0.0, 0.5, 4.0) - 338.09).abs() < 0.01);
        assert!((siegmund_arl(1.0, 0.5, 4.0) - 8.343).abs() < 0.001);
        assert!((siegmund_arl(0.0, 0.5, 5.0) - 938.22).abs() < 0.01);
        assert!((siegmund_arl(1.0, 0.5, 5.0) - 10.336).abs() < 0.001);
        // Δ = 0: b².
        assert!((siegmund_arl(0.5, 0.5, 4.0) - 5.166f64.powi(2)).abs() < 1e-12);
    }

    /// Runs `trials` CUSUMs on N(μ, 1) with design shift δ and threshold h until they cross,
    /// returning the mean run length.
    fn simulated_arl(mu: f64, delta: f64, h: f64, trials: usize, seed: u64) -> f64 {
        let mut rng = SmallRng::seed_from_u64(seed);
        let mut total = 0u64;
        for _ in 0..trials {
            let mut c = Cusum::default();
            let mut n = 0u64;
            while c.value() < h {
                let z: f64 = rng.sample::<f64, _>(StandardNormal) + mu;
                c.update(delta * (z - delta / 2.0), n as i64);
                n += 1;
            }
            total += n;
        }
        total as f64 / trials as f64
    }

    /// The run lengths Siegmund predicts, measured: in control (δ = 1, h = 5 nats, predicted
    /// 938) within the Monte Carlo's 3σ (the run length is nearly exponential: sd ≈ mean), and
    /// at the design shift (predicted 10.3) within 5 %. Lorden's bound (ARL₀ ≥ e^h = 148)
    /// holds with room.
    #[test]
    fn run_lengths_match_siegmund_and_lordens_bound() {
        let predicted = gaussian_arl(0.0, 1.0, 5.0);
        let trials = 2000;
        let measured = simulated_arl(0.0, 1.0, 5.0, trials, 1);
        let sd = predicted / (trials as f64).sqrt();
        assert!(
            (measured - predicted).abs() < 3.0 * sd,
            "ARL₀ measured {measured:.0}, Siegmund {predicted:.0}"
        );
        assert!(measured > 5f64.exp());
        let delay = simulated_arl(1.0, 1.0, 5.0, trials, 2);
        let predicted = gaussian_arl(1.0, 1.0, 5.0);
        assert!(
            (delay / predicted - 1.0).abs() < 0.05,
            "delay measured {delay:.2}, Siegmund {predicted:.2}"
        );
    }

    #[test]
    fn thresholds_since_and_latch() {
        let t = Thresholds::from_arl(10.0, 1000.0, 2);
        assert!((t.watch - 20f64.ln()).abs() < 1e-12);
        assert!((t.suspect - 2000f64.ln()).abs() < 1e-12);
        let mut s = Sequential::new(Thresholds {
            watch: 1.0,
            suspect: 3.0,
        });
        s.update(-1.0, -1.0, 0);
        assert_eq!(s.verdict(), Verdict::Ok);
        assert_eq!(s.since_ns(), None);
        s.update(0.5, -2.0, 10);
        s.update(0.7, -2.0, 20);
        assert_eq!(s.verdict(), Verdict::Watch);
        assert_eq!(s.since_ns(), Some(10));
        s.update(-2.0, -2.0, 30);
        assert_eq!(s.verdict(), Verdict::Ok);
        s.update(-2.0, 2.0, 40);
        s.update(-2.0, 1.5, 50);
        assert_eq!(s.verdict(), Verdict::Suspect);
        assert!(s.is_down());
        assert_eq!(s.since_ns(), Some(40));
        // Latched: evidence to the contrary does not clear it.
        for t in 6..100 {
            s.update(-5.0, -5.0, t * 10);
        }
        assert_eq!(s.verdict(), Verdict::Suspect);
        assert_eq!(s.since_ns(), Some(40));
        // A NaN carries no evidence.
        let mut c = Cusum::default();
        c.update(1.0, 0);
        c.update(f64::NAN, 1);
        assert_eq!(c.value(), 1.0);
        assert_eq!(Verdict::Ok.max(Verdict::Suspect), Verdict::Suspect);
    }
}
