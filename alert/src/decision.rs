//! The decision rule: a measured value with its standard uncertainty against a threshold, with a
//! guard band of k·u (ISO/IEC 17025 §7.8.6, "decision rule").
//!
//! For a limit that must not be exceeded from below (`Direction::Above`):
//!
//! - `exceeded` when `value − k·u > threshold`: even the lower end of the coverage interval is
//!   above the threshold;
//! - `possible` when `value − k·u ≤ threshold < value + k·u`: the interval straddles it;
//! - no alert when `value + k·u ≤ threshold`.
//!
//! `Direction::Below` (a dominant frequency that must not drop) is the mirror image. Every alert
//! carries [`rule_text`] in its statement, so an operator reading one alert knows how it was
//! decided.

use triax_protocol::messages::AlertLevel;

/// Which side of the threshold is the alarming one.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Direction {
    /// Alarm when the value rises above the threshold (peak, RMS, tilt change, frequency cap).
    Above,
    /// Alarm when the value falls below the threshold (a natural frequency that drops).
    Below,
}

/// A threshold and its alarming side.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Limit {
    pub threshold: f64,
    pub direction: Direction,
}

/// A value with its standard uncertainty (k = 1), in the unit of the quantity.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Estimate {
    pub value: f64,
    pub standard_uncertainty: f64,
}

/// Applies the guard-band rule. `k` is the coverage factor of the interval.
///
/// A non-finite value or uncertainty decides nothing: an interval that is not a number cannot be
/// placed relative to a threshold.
pub fn decide(estimate: Estimate, k: f64, limit: Limit) -> Option<AlertLevel> {
    let Estimate {
        value,
        standard_uncertainty: u,
    } = estimate;
    if !(value.is_finite() && u.is_finite() && u >= 0.0) {
        return None;
    }
    let lower = value - k * u;
    let upper = value + k * u;
    let t = limit.threshold;
    match limit.direction {
        Direction::Above if lower > t => Some(AlertLevel::Exceeded),
        Direction::Above if upper > t => Some(AlertLevel::Possible),
        Direction::Below if upper < t => Some(AlertLevel::Exceeded),
        Direction::Below if lower < t => Some(AlertLevel::Possible),
        _ => None,
    }
}

/// Severity order of decision levels, for escalation: `possible` < `exceeded`.
pub fn severity(level: AlertLevel) -> u8 {
    match level {
        AlertLevel::Possible => 1,
        AlertLevel::Exceeded => 2,
        AlertLevel::Stale => 0,
    }
}

/// The rule in words, as quoted in every threshold alert.
pub fn rule_text(direction: Direction) -> &'static str {
    match direction {
        Direction::Above => {
            "Decision rule (guard band k·u): `exceeded` when value − k·u > threshold; \
             `possible` when the interval [value − k·u, value + k·u] contains the threshold; \
             no alert when value + k·u ≤ threshold."
        }
        Direction::Below => {
            "Decision rule (guard band k·u): `exceeded` when value + k·u < threshold; \
             `possible` when the interval [value − k·u, value + k·u] contains the threshold; \
             no alert when value − k·u ≥ threshold."
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn e(value: f64, u: f64) -> Estimate {
        Estimate {
            value,
            standard_uncertainty: u,
        }
    }

    const ABOVE_1: Limit = Limit {
        threshold: 1.0,
        direction: Direction::Above,
    };
    const BELOW_1: Limit = Limit {
        threshold: 1.0,
        direction: Direction::Below,
    };

    #[test]
    fn three_regimes_above() {
        assert_eq!(
            decide(e(1.3, 0.1), 2.0, ABOVE_1),
            Some(AlertLevel::Exceeded)
        );
        assert_eq!(
            decide(e(1.1, 0.1), 2.0, ABOVE_1),
            Some(AlertLevel::Possible)
        );
        assert_eq!(
            decide(e(0.9, 0.1), 2.0, ABOVE_1),
            Some(AlertLevel::Possible)
        );
        assert_eq!(decide(e(0.7, 0.1), 2.0, ABOVE_1), None);
        // The guard band is what separates `exceeded` from a bare comparison.
        assert_eq!(
            decide(e(1.15, 0.1), 2.0, ABOVE_1),
            Some(AlertLevel::Possible)
        );
        assert_eq!(
            decide(e(1.15, 0.1), 1.0, ABOVE_1),
            Some(AlertLevel::Exceeded)
        );
    }

    #[test]
    fn three_regimes_below() {
        assert_eq!(
            decide(e(0.7, 0.1), 2.0, BELOW_1),
            Some(AlertLevel::Exceeded)
        );
        assert_eq!(
            decide(e(0.9, 0.1), 2.0, BELOW_1),
            Some(AlertLevel::Possible)
        );
        assert_eq!(decide(e(1.3, 0.1), 2.0, BELOW_1), None);
    }

    #[test]
    fn not_a_number_decides_nothing() {
        assert_eq!(decide(e(f64::NAN, 0.1), 2.0, ABOVE_1), None);
        assert_eq!(decide(e(5.0, f64::NAN), 2.0, ABOVE_1), None);
        assert_eq!(decide(e(5.0, f64::INFINITY), 2.0, ABOVE_1), None);
    }
}
