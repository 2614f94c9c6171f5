//! Judging an estimate against a limit with a guard band, as the alerting service judges
//! (ISO/IEC 17025 §7.8.6; `triax-alert`'s rule), and the building's tag.
//!
//! For a limit not to be exceeded from below, with the decision's factor `k`:
//!
//! - `exceeded` when `value − k·u > threshold`: even the interval's lower end is beyond it;
//! - `possible` when `value − k·u ≤ threshold < value + k·u`: the interval reaches it;
//! - `below` when `value + k·u ≤ threshold`.
//!
//! **False alarms.** `k` is Student's one-sided quantile at the estimate's ν for the probability
//! `α` a limit is allowed to say `exceeded` when the truth is exactly at it: with Gaussian
//! errors, `P(exceeded | truth = threshold) = α`, and less when the truth is below. A limit
//! judged over several items (every storey, every floor) shares its `α` among them by Šidák,
//! `α_item = 1 − (1 − α)^(1/m)`, so the limit as a whole says `exceeded` falsely with
//! probability at most `α` when every item is at the threshold. **Power.** A truth `d·u` beyond
//! the threshold is `exceeded` with probability `Φ(d − k)`: 85 % at `d = 3` for `k = 1.96`, 97.9 %
//! at `d = 4`; no rule with `α = 2.5 %` can do better at one estimate (Neyman–Pearson).

use serde::{Deserialize, Serialize};

use crate::estimate::{one_sided_factor, Estimate};

/// The three outcomes.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Verdict {
    Below,
    Possible,
    Exceeded,
}

/// `exceeded`, `possible` or `below` for `estimate` against `threshold` at factor `k`; none when
/// the estimate is not a number.
pub fn judge(estimate: &Estimate, k: f64, threshold: f64) -> Option<Verdict> {
    let (v, u) = (estimate.value, estimate.standard_uncertainty);
    if !(v.is_finite() && u.is_finite() && u >= 0.0) {
        return None;
    }
    Some(if v - k * u > threshold {
        Verdict::Exceeded
    } else if v + k * u > threshold {
        Verdict::Possible
    } else {
        Verdict::Below
    })
}

/// The per-item false-alarm probability that keeps `m` items together at `alpha` (Šidák).
pub fn per_item_alpha(alpha: f64, m: usize) -> f64 {
    1.0 - (1.0 - alpha).powf(1.0 / m.max(1) as f64)
}

/// The decision's factor for `estimate` when `m` items share `alpha`.
pub fn decision_factor(estimate: &Estimate, alpha: f64, m: usize) -> f64 {
    one_sided_factor(estimate.dof, per_item_alpha(alpha, m))
}

/// A building's state after an event.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Tag {
    Green,
    Yellow,
    Red,
}

/// What a limit's verdict makes the building: `exceeded` the limit's own severity, `possible`
/// yellow, `below` green.
pub fn tag_of(verdict: Verdict, severity: Tag) -> Tag {
    match verdict {
        Verdict::Exceeded => severity,
        Verdict::Possible => Tag::Yellow,
        Verdict::Below => Tag::Green,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::Rng;

    fn e(value: f64, u: f64) -> Estimate {
        Estimate {
            value,
            standard_uncertainty: u,
            dof: f64::INFINITY,
            coverage_factor: 1.96,
            coverage_probability: 0.95,
        }
    }

    #[test]
    fn three_regimes_and_not_a_number() {
        assert_eq!(judge(&e(1.3, 0.1), 1.96, 1.0), Some(Verdict::Exceeded));
        assert_eq!(judge(&e(1.1, 0.1), 1.96, 1.0), Some(Verdict::Possible));
        assert_eq!(judge(&e(0.9, 0.1), 1.96, 1.0), Some(Verdict::Possible));
        assert_eq!(judge(&e(0.7, 0.1), 1.96, 1.0), Some(Verdict::Below));
        assert_eq!(judge(&e(f64::NAN, 0.1), 1.96, 1.0), None);
        assert_eq!(tag_of(Verdict::Exceeded, Tag::Red), Tag::Red);
        assert_eq!(tag_of(Verdict::Possible, Tag::Red), Tag::Yellow);
        assert_eq!(tag_of(Verdict::Possible, Tag::Yellow), Tag::Yellow);
        assert_eq!(tag_of(Verdict::Below, Tag::Red), Tag::Green);
    }

    #[test]
    fn sidak_by_hand_and_the_false_alarm_rate_measured() {
        assert!((per_item_alpha(0.025, 1) - 0.025).abs() < 1e-15);
        // 1 − 0.975^(1/4) = 0.006309…
        assert!((per_item_alpha(0.025, 4) - 0.006_309_2).abs() < 1e-6);
        assert!((decision_factor(&e(0.0, 1.0), 0.025, 1) - 1.96).abs() < 1e-3);
        // Four items at the threshold, unit normal errors: the limit says `exceeded` in
        // 2.5 % of cases.
        let mut rng = Rng::new(3);
        let trials = 200_000;
        let k = decision_factor(&e(0.0, 1.0), 0.025, 4);
        let mut any = 0;
        for _ in 0..trials {
            any += usize::from(
                (0..4).any(|_| judge(&e(rng.normal(), 1.0), k, 0.0) == Some(Verdict::Exceeded)),
            );
        }
        let rate = any as f64 / trials as f64;
        assert!((rate - 0.025).abs() < 0.0015, "{rate}");
    }
}
