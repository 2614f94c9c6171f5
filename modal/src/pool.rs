//! A mode's shape pooled over consecutive windows: what a window cannot resolve, a day can.
//!
//! **Why.** Two modes a few per cent apart in frequency, with bandwidths (`2ζf`, 4 % at 2 %
//! damping) wider than their separation, are resolved by one window as a pair: the plane their
//! two shapes span is well determined, the split of that plane into the two shapes is not. A
//! window's estimate of each shape leaks into the other's by a random share that shrinks with
//! the data (ARCHITECTURE.md, "Building modes": the five-storey building's close fundamentals
//! reach a MAC of 0.995 with the truth in the median 30-minute window, 0.83 in the worst of
//! 192; four times the data cuts the mean `1 − MAC` 2.3 to 2.8-fold; modes 14 % apart reach
//! 0.998 in every window). The leakage has zero mean from window to window, and a shape does not move with
//! temperature (a uniform change of stiffness scales every frequency and keeps every shape),
//! so the remedy is more data for the shape, not another measure: the mode shape of a track
//! is the weighted mean of its last windows' shapes.
//!
//! **How.** Each window's in-phase shape (`Mode::shape_in_phase`) is brought to the pool's
//! reference component (the first window's) by dividing by its value there, with the
//! first-order variance of a ratio. Each component is the inverse-variance weighted mean of
//! the windows' values, weighted by their statistical variance (the jackknife's: a window whose
//! pair was poorly split says so and counts less), `u_stat² = 1/Σ wⱼ` with `Σ νⱼ` degrees of
//! freedom. The measurement chain's variance does not average down, since the same sensors
//! with the same calibration errors saw every window: the windows' mean chain variance is
//! added whole, with Welch–Satterthwaite degrees of freedom ([`crate::uncertainty::combine`]).

use std::collections::VecDeque;

use serde::{Deserialize, Serialize};

use crate::identify::Mode;
use crate::model::Direction;
use crate::uncertainty::{combine, Estimate};

/// One window's shape, on the pool's reference: per component (value, statistical variance,
/// chain variance), and the window's statistical and chain degrees of freedom.
#[derive(Debug, Clone, PartialEq)]
struct Entry {
    components: Vec<(f64, f64, f64)>,
    statistical_dof: f64,
    chain_dof: f64,
}

/// The last `capacity` windows' shapes of one mode.
#[derive(Debug, Clone, PartialEq)]
pub struct ShapePool {
    capacity: usize,
    reference: Option<usize>,
    entries: VecDeque<Entry>,
}

/// A pooled shape component.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PooledComponent {
    pub sensor_id: String,
    pub direction: Direction,
    /// In-phase amplitude relative to the reference component, with the pooled uncertainty.
    pub real: Estimate,
}

/// A mode shape pooled over windows.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PooledShape {
    pub shape: Vec<PooledComponent>,
    pub reference_component: usize,
    /// Windows pooled.
    pub windows: usize,
}

impl ShapePool {
    /// A pool of the last `capacity` windows (48: a day of 30-minute windows).
    pub fn new(capacity: usize) -> ShapePool {
        ShapePool {
            capacity: capacity.max(1),
            reference: None,
            entries: VecDeque::new(),
        }
    }

    /// Windows held.
    pub fn len(&self) -> usize {
        self.entries.len()
    }

    pub fn is_empty(&self) -> bool {
        self.entries.is_empty()
    }

    /// Adds a window's estimate of the mode; a shape on other channels than the pool's (a
    /// sensor added or left out) starts the pool again, since components no longer correspond.
    pub fn push(&mut self, mode: &Mode) {
        let n = mode.shape.len();
        let same_channels = self.entries.front().is_none_or(|e| e.components.len() == n);
        if !same_channels || self.reference.is_none_or(|r| r >= n) {
            self.entries.clear();
            self.reference = Some(mode.reference_component);
        }
        let reference = self.reference.unwrap_or(mode.reference_component);
        let part = |c: usize| {
            let s = &mode.shape[c];
            let total = s.real.standard_uncertainty.powi(2);
            let chain = s.chain_variance_real.min(total);
            (s.real.value, total - chain, chain)
        };
        let (r, r_stat, r_chain) = part(reference);
        if !(r.is_finite() && r.abs() > 0.0) {
            return;
        }
        let components = (0..n)
            .map(|c| {
                let (x, stat, chain) = part(c);
                if c == reference {
                    return (1.0, 0.0, 0.0);
                }
                // x/r to first order: var = (var x + (x/r)²·var r)/r².
                let ratio = x / r;
                (
                    ratio,
                    (stat + ratio * ratio * r_stat) / (r * r),
                    (chain + ratio * ratio * r_chain) / (r * r),
                )
            })
            .collect();
        let statistical_dof = mode.frequency_hz.dof;
        // A component keeps only its combined ν: the smallest stands for the chain's (it is
        // near the records' ν when the chain dominates, and the chain is then what matters).
        let chain_dof = mode
            .shape
            .iter()
            .map(|s| s.real.dof)
            .fold(f64::INFINITY, f64::min)
            .max(1.0);
        self.entries.push_back(Entry {
            components,
            statistical_dof,
            chain_dof,
        });
        while self.entries.len() > self.capacity {
            self.entries.pop_front();
        }
    }

    /// The pooled shape, with intervals at `coverage_probability`; `None` when empty. `mode`
    /// names the components (any window's estimate of the mode: the ids are the channels').
    pub fn pooled(&self, mode: &Mode, coverage_probability: f64) -> Option<PooledShape> {
        let reference = self.reference?;
        let first = self.entries.front()?;
        let m = self.entries.len() as f64;
        let statistical_dof: f64 = self.entries.iter().map(|e| e.statistical_dof).sum();
        let chain_dof = self
            .entries
            .iter()
            .map(|e| e.chain_dof)
            .fold(f64::INFINITY, f64::min);
        let shape = (0..first.components.len())
            .map(|c| {
                let (mut weights, mut sum, mut chain) = (0.0, 0.0, 0.0);
                for e in &self.entries {
                    let (x, stat, ch) = e.components[c];
                    // A variance of zero is the reference component's (exactly 1): any weight.
                    let w = if stat > 0.0 { 1.0 / stat } else { 1.0 };
                    weights += w;
                    sum += w * x;
                    chain += ch / m;
                }
                let value = sum / weights;
                let real = if c == reference {
                    Estimate::new(1.0, 0.0, f64::INFINITY, coverage_probability)
                } else {
                    combine(
                        value,
                        1.0 / weights,
                        statistical_dof,
                        chain,
                        chain_dof,
                        coverage_probability,
                    )
                };
                PooledComponent {
                    sensor_id: mode.shape[c].sensor_id.clone(),
                    direction: mode.shape[c].direction,
                    real,
                }
            })
            .collect();
        Some(PooledShape {
            shape,
            reference_component: reference,
            windows: self.entries.len(),
        })
    }
}
