//! Running bounds of a sensor's window, kept sample by sample so that a batch costs what it
//! carries rather than what the window holds: most windows of a fleet are quiet, and these
//! bounds show it without looking at the window again.
//!
//! Per axis, over the window's usable samples: the largest |high-passed value| and the largest
//! and smallest acceleration and the largest stated u (monotone deques: each sample enters and
//! leaves once), and the sum of squares of the high-passed values. From them,
//! [`WindowBounds::peak_bound`] and [`WindowBounds::rms_bound`] bound anything the estimators of
//! [`crate::stats`] can return, as its own gate does but with the largest u rather than the
//! mean: the bound then holds for any subset of the samples, the clean ones included.

use std::collections::VecDeque;

use crate::stats::{upper_bound, AxisSummary};

/// Sliding maximum over samples that leave in the order they entered.
#[derive(Debug, Default, Clone)]
pub(super) struct SlidingMax {
    /// (time, value), values decreasing from the front.
    entries: VecDeque<(i64, f64)>,
}

impl SlidingMax {
    pub(super) fn push(&mut self, t_ns: i64, value: f64) {
        while self.entries.back().is_some_and(|&(_, v)| v <= value) {
            self.entries.pop_back();
        }
        self.entries.push_back((t_ns, value));
    }

    /// Forgets what entered at or before `t_ns`.
    pub(super) fn evict_through(&mut self, t_ns: i64) {
        while self.entries.front().is_some_and(|&(t, _)| t <= t_ns) {
            self.entries.pop_front();
        }
    }

    pub(super) fn max(&self) -> Option<f64> {
        self.entries.front().map(|&(_, v)| v)
    }
}

#[derive(Debug, Default, Clone)]
struct AxisBounds {
    abs_vibration: SlidingMax,
    accel_max: SlidingMax,
    /// Of −a: the smallest acceleration.
    accel_min: SlidingMax,
    sum_sq_vibration: f64,
    /// Sums of |vibration| and of u: the means the estimators use.
    sum_abs_vibration: f64,
    sum_u: f64,
    u_max: SlidingMax,
}

/// The running bounds of one window.
#[derive(Debug, Default, Clone)]
pub(super) struct WindowBounds {
    axes: [AxisBounds; 3],
    count: usize,
    /// Usable samples with a flag: while there are any, the clean ones are a subset whose RMS
    /// the RMS of all does not bound.
    flagged: usize,
}

impl WindowBounds {
    /// A usable sample entered the window.
    pub(super) fn push(
        &mut self,
        t_ns: i64,
        accel: [f32; 3],
        vibration: [f32; 3],
        u: [f32; 3],
        flagged: bool,
    ) {
        self.count += 1;
        self.flagged += usize::from(flagged);
        for (j, axis) in self.axes.iter_mut().enumerate() {
            let (a, v) = (f64::from(accel[j]), f64::from(vibration[j]));
            axis.abs_vibration.push(t_ns, v.abs());
            axis.accel_max.push(t_ns, a);
            axis.accel_min.push(t_ns, -a);
            axis.sum_sq_vibration += v * v;
            axis.sum_abs_vibration += v.abs();
            axis.sum_u += f64::from(u[j]);
            axis.u_max.push(t_ns, f64::from(u[j]));
        }
    }

    /// A usable sample, pushed before, left the window.
    pub(super) fn pop(&mut self, t_ns: i64, vibration: [f32; 3], u: [f32; 3], flagged: bool) {
        self.count = self.count.saturating_sub(1);
        self.flagged = self.flagged.saturating_sub(usize::from(flagged));
        for (j, axis) in self.axes.iter_mut().enumerate() {
            axis.abs_vibration.evict_through(t_ns);
            axis.accel_max.evict_through(t_ns);
            axis.accel_min.evict_through(t_ns);
            axis.u_max.evict_through(t_ns);
            let v = f64::from(vibration[j]);
            // A sum that goes up and down by the same values drifts only by rounding; never
            // below 0.
            axis.sum_sq_vibration = (axis.sum_sq_vibration - v * v).max(0.0);
            axis.sum_abs_vibration = (axis.sum_abs_vibration - v.abs()).max(0.0);
            axis.sum_u = (axis.sum_u - f64::from(u[j])).max(0.0);
            if self.count == 0 {
                axis.sum_sq_vibration = 0.0;
                axis.sum_abs_vibration = 0.0;
                axis.sum_u = 0.0;
            }
        }
    }

    /// What the estimators need of each axis, as [`crate::stats`] would gather it from the
    /// same samples.
    pub(super) fn summaries(&self) -> [AxisSummary; 3] {
        let n = self.count.max(1) as f64;
        self.axes.each_ref().map(|a| AxisSummary {
            peak: a.abs_vibration.max().unwrap_or(0.0),
            half_range: Self::half_range(a),
            largest_accel: match (a.accel_max.max(), a.accel_min.max()) {
                (Some(hi), Some(neg_lo)) => hi.abs().max(neg_lo.abs()),
                _ => 0.0,
            },
            mean_u: a.sum_u / n,
            mean_square: a.sum_sq_vibration / n,
            mean_abs: a.sum_abs_vibration / n,
        })
    }

    pub(super) fn clear(&mut self) {
        *self = WindowBounds::default();
    }

    fn per_axis(&self, f: impl Fn(&AxisBounds, f64) -> f64) -> f64 {
        if self.count == 0 {
            return 0.0;
        }
        let n = self.count as f64;
        self.axes.iter().map(|a| f(a, n)).fold(0.0, f64::max)
    }

    fn half_range(a: &AxisBounds) -> f64 {
        match (a.accel_max.max(), a.accel_min.max()) {
            (Some(hi), Some(neg_lo)) => 0.5 * (hi + neg_lo),
            _ => 0.0,
        }
    }

    /// At least any peak the estimators can return from these samples (`stats::peak_bound`).
    pub(super) fn peak_bound(&self, k: f64) -> f64 {
        self.per_axis(|a, _| {
            let peak = a.abs_vibration.max().unwrap_or(0.0);
            upper_bound(
                peak.max(Self::half_range(a)),
                k,
                a.u_max.max().unwrap_or(0.0),
            )
        })
    }

    /// At least any RMS the estimators can return (`stats::rms_bound`; the half range bounds
    /// the standard deviation). With flagged samples in the window the clean ones are judged
    /// apart, and only the largest |vibration| bounds their RMS.
    pub(super) fn rms_bound(&self, k: f64) -> f64 {
        self.per_axis(|a, n| {
            let mut rms = (a.sum_sq_vibration / n).sqrt();
            if self.flagged > 0 {
                rms = rms.max(a.abs_vibration.max().unwrap_or(0.0));
            }
            upper_bound(
                rms.max(Self::half_range(a)),
                k,
                a.u_max.max().unwrap_or(0.0),
            )
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The running bounds equal bounds computed afresh over the window, as it slides.
    #[test]
    fn matches_a_recomputation_while_sliding() {
        let mut b = WindowBounds::default();
        let mut window: VecDeque<(i64, [f32; 3], [f32; 3])> = VecDeque::new();
        let len = 50;
        for i in 0..400i64 {
            let x = ((i as f64) * 0.37).sin() as f32 * (1.0 + (i % 7) as f32);
            let accel = [x + 0.5, -x, 9.81];
            let vibration = [x, -x, 0.01 * (i % 3) as f32];
            let u = [0.01 + 0.001 * (i % 5) as f32; 3];
            b.push(i, accel, vibration, u, false);
            window.push_back((i, accel, vibration));
            if window.len() > len {
                let (t, _, v) = window.pop_front().unwrap();
                b.pop(t, v, u_at(t), false);
            }
            let n = window.len() as f64;
            let mut peak_expected = 0.0f64;
            let mut rms_expected = 0.0f64;
            for j in 0..3 {
                let peak = window
                    .iter()
                    .map(|w| f64::from(w.2[j]).abs())
                    .fold(0.0, f64::max);
                let hi = window
                    .iter()
                    .map(|w| f64::from(w.1[j]))
                    .fold(f64::MIN, f64::max);
                let lo = window
                    .iter()
                    .map(|w| f64::from(w.1[j]))
                    .fold(f64::MAX, f64::min);
                let max_u = window
                    .iter()
                    .map(|w| f64::from(u_at(w.0)[j]))
                    .fold(0.0, f64::max);
                let rms = (window
                    .iter()
                    .map(|w| f64::from(w.2[j]).powi(2))
                    .sum::<f64>()
                    / n)
                    .sqrt();
                let half = 0.5 * (hi - lo);
                peak_expected = peak_expected.max(2.0 * peak.max(half) + 9.0 * max_u);
                rms_expected = rms_expected.max(2.0 * rms.max(half) + 9.0 * max_u);
            }
            assert!((b.peak_bound(2.0) - peak_expected).abs() < 1e-9, "at {i}");
            assert!((b.rms_bound(2.0) - rms_expected).abs() < 1e-9, "at {i}");
        }
        // A flagged sample in the window: the largest |vibration| joins the RMS bound.
        let before = b.rms_bound(2.0);
        b.push(400, [0.0; 3], [0.0; 3], [0.01; 3], true);
        assert!(b.rms_bound(2.0) > before);
        b.clear();
        assert_eq!(b.peak_bound(2.0), 0.0);
    }

    fn u_at(i: i64) -> [f32; 3] {
        [0.01 + 0.001 * (i % 5) as f32; 3]
    }
}
