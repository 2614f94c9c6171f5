//! Tracking modes across windows, regressing out the environment, and deciding on a shift.
//!
//! **Matching.** Each window's modes are matched one to one to the tracks by shape first: a
//! mode may join a track when its frequency is within `frequency_tolerance` (10 %) of the
//! track's last frequency and its MAC with the track's last shape is at least `mac_min` (0.8);
//! among those, pairs are taken by decreasing MAC. Close modes in `x` and `y` (a few % apart)
//! have nearly orthogonal shapes, so the MAC keeps them apart where a frequency rule would
//! swap them as the temperature moves both. A mode that matches no track starts one.
//!
//! **Environment.** A track's first `training_windows` observations fit the baseline
//! `f = b₀ + b₁·x₁ + … + b_p·x_p` by ordinary least squares, where `x` are the regressors given
//! with every window: the nodes' mean `temperature_c` first, and any other the operator has
//! (a lagged or a daily-mean temperature for a building whose stiffness lags the air, humidity,
//! wind speed for amplitude dependence): give them in the same order to every call of
//! [`ModeTracker::update`], and the design grows by a column each. The baseline is then frozen:
//! a slow change after training is not learnt as environment. The residual variance `s²`
//! (with `ν = N − p − 1` degrees of freedom) holds everything the regressors do not explain,
//! the identification's own scatter included.
//!
//! **Decision.** For a new window, the relative residual `r = (f − f̂)/f̂` has the standard
//! uncertainty of a prediction, `u² = s²·(1 + x₀ᵀ(XᵀX)⁻¹x₀)/f̂²`, Student's t with ν degrees of
//! freedom under no change. The guard band of the alerting service (`k·u`, ISO/IEC 17025
//! §7.8.6) is applied to it against `threshold_relative`, for a drop (a loss of stiffness
//! lowers frequencies) or both sides: `shift` when even the near end of `r ± k·u` is beyond the
//! threshold, `possible` when the interval reaches it. Two tests share the stated yearly
//! false-alarm budget half and half: the single window (an abrupt change, seen at once) and the
//! mean of each block of `average_windows` consecutive windows (a small change: a day of
//! windows averages the identification's scatter down by √48, while the baseline's own error,
//! shared by the block, is kept). `k` is Student's quantile at the per-test false-alarm
//! probability `α`: `P(shift | no change) ≤ P(T_ν > k) = α` per test and track (equality at
//! threshold 0). This holds for residuals independent from window to window; an environmental
//! effect the regressors miss makes them correlated, and a Monte Carlo (the crate's tests)
//! measures the rate that results.

use nalgebra::{Complex, DMatrix, DVector};
use serde::{Deserialize, Serialize};

use crate::identify::Mode;
use crate::model::Direction;
use crate::ssi::mac;
use crate::uncertainty::Estimate;

/// Settings of the tracker.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct TrackerConfig {
    pub frequency_tolerance: f64,
    pub mac_min: f64,
    /// Observations that fit a track's baseline.
    pub training_windows: usize,
    /// Stated rate of false `shift` verdicts per track.
    pub false_alarms_per_year: f64,
    /// Windows per year (17 532 for 30-minute windows).
    pub windows_per_year: f64,
    /// Relative frequency change that matters (0: any significant change).
    pub threshold_relative: f64,
    /// Judge drops only (`false`: rises too).
    pub drops_only: bool,
    /// Windows averaged by the block-mean test (48: a day of 30-minute windows).
    pub average_windows: usize,
}

impl Default for TrackerConfig {
    fn default() -> Self {
        TrackerConfig {
            frequency_tolerance: 0.10,
            mac_min: 0.8,
            training_windows: 336,
            false_alarms_per_year: 1.0,
            windows_per_year: 365.25 * 48.0,
            threshold_relative: 0.0,
            drops_only: true,
            average_windows: 48,
        }
    }
}

impl TrackerConfig {
    /// The per-test false-alarm probability of the single-window test: half the yearly budget
    /// over the windows of a year.
    pub fn window_false_alarm_probability(&self) -> f64 {
        0.5 * self.false_alarms_per_year / self.windows_per_year
    }

    /// The per-test false-alarm probability of the block-mean test: the other half over the
    /// blocks of a year.
    pub fn block_false_alarm_probability(&self) -> f64 {
        0.5 * self.false_alarms_per_year * self.average_windows.max(1) as f64
            / self.windows_per_year
    }

    /// The two-sided coverage probability whose factor is the guard band for a per-test
    /// false-alarm probability `alpha` (one-sided when only drops are judged).
    fn coverage_probability(&self, alpha: f64) -> f64 {
        let alpha = alpha.clamp(1e-12, 0.25);
        if self.drops_only {
            1.0 - 2.0 * alpha
        } else {
            1.0 - alpha
        }
    }
}

/// What the tracker needs of an identified mode.
#[derive(Debug, Clone, PartialEq)]
pub struct ModeObservation {
    pub frequency_hz: Estimate,
    pub shape: Vec<Complex<f64>>,
    pub direction: Direction,
}

impl From<&Mode> for ModeObservation {
    fn from(mode: &Mode) -> Self {
        ModeObservation {
            frequency_hz: mode.frequency_hz,
            shape: mode.shape_in_phase(),
            direction: mode.direction,
        }
    }
}

/// The environmental baseline of a track.
#[derive(Debug, Clone, PartialEq)]
pub struct Baseline {
    /// `b₀, b₁, …`: Hz, Hz per unit of each regressor.
    pub coefficients: DVector<f64>,
    /// `(XᵀX)⁻¹` of the training design.
    pub design_inverse: DMatrix<f64>,
    /// Residual variance `s²`, Hz².
    pub residual_variance_hz2: f64,
    pub dof: f64,
}

impl Baseline {
    /// Fits `f = b·[1, x…]` to training observations; `None` when the design is singular (a
    /// regressor that did not vary) or there are too few.
    pub fn fit(frequencies_hz: &[f64], regressors: &[Vec<f64>]) -> Option<Baseline> {
        let n = frequencies_hz.len();
        let p = regressors.first().map_or(0, Vec::len) + 1;
        if n <= p + 1 || regressors.len() != n || regressors.iter().any(|x| x.len() + 1 != p) {
            return None;
        }
        let x = DMatrix::from_fn(n, p, |i, j| if j == 0 { 1.0 } else { regressors[i][j - 1] });
        let y = DVector::from_column_slice(frequencies_hz);
        let xtx = x.transpose() * &x;
        let design_inverse = xtx.try_inverse()?;
        let coefficients = &design_inverse * x.transpose() * &y;
        let residuals = &y - &x * &coefficients;
        let dof = (n - p) as f64;
        Some(Baseline {
            coefficients,
            design_inverse,
            residual_variance_hz2: residuals.norm_squared() / dof,
            dof,
        })
    }

    /// The frequency predicted at `regressors` and the standard uncertainty of a new
    /// observation about it, Hz.
    pub fn predict(&self, regressors: &[f64]) -> (f64, f64) {
        let x0 = DVector::from_fn(self.coefficients.len(), |j, _| {
            if j == 0 {
                1.0
            } else {
                regressors.get(j - 1).copied().unwrap_or(0.0)
            }
        });
        let value = self.coefficients.dot(&x0);
        let leverage = (x0.transpose() * &self.design_inverse * &x0)[(0, 0)];
        (
            value,
            (self.residual_variance_hz2 * (1.0 + leverage)).sqrt(),
        )
    }

    /// The mean relative residual of a block of `(frequency, prediction, regressors)` and its
    /// standard uncertainty: the windows' own scatter averages down (`s²/m`), the baseline's
    /// error does not, since every window of the block shares it (`x̄ᵀ(XᵀX)⁻¹x̄·s²`).
    pub fn block_mean(&self, block: &[(f64, f64, Vec<f64>)]) -> (f64, f64) {
        let m = block.len() as f64;
        let p = self.coefficients.len();
        let mean_f = block.iter().map(|b| b.0).sum::<f64>() / m;
        let mean_pred = block.iter().map(|b| b.1).sum::<f64>() / m;
        let x_bar = DVector::from_fn(p, |j, _| {
            if j == 0 {
                1.0
            } else {
                block
                    .iter()
                    .map(|b| b.2.get(j - 1).copied().unwrap_or(0.0))
                    .sum::<f64>()
                    / m
            }
        });
        let leverage = (x_bar.transpose() * &self.design_inverse * &x_bar)[(0, 0)];
        let u = (self.residual_variance_hz2 * (1.0 / m + leverage)).sqrt();
        ((mean_f - mean_pred) / mean_pred, u / mean_pred)
    }
}

/// The verdict on a window for one track.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ShiftVerdict {
    /// The baseline is still being learnt.
    Training,
    /// The residual's interval is on the safe side of the threshold.
    Normal,
    /// The interval reaches beyond the threshold.
    Possible,
    /// The whole interval is beyond the threshold: a `modal_shift`.
    Shift,
}

/// One track's result for one window.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TrackUpdate {
    pub track: usize,
    pub direction: Direction,
    pub frequency_hz: Estimate,
    /// The baseline's prediction, Hz, once trained.
    pub predicted_hz: Option<f64>,
    /// `(f − f̂)/f̂` with its standard uncertainty, dof and the guard band's k.
    pub residual_relative: Option<Estimate>,
    pub verdict: ShiftVerdict,
    /// When this window completes a block of `average_windows`: the block's mean relative
    /// residual and its verdict.
    pub block_mean_relative: Option<Estimate>,
    pub block_verdict: Option<ShiftVerdict>,
}

/// A mode followed across windows.
#[derive(Debug, Clone, PartialEq)]
pub struct Track {
    pub id: usize,
    pub direction: Direction,
    pub last_frequency_hz: f64,
    pub last_shape: Vec<Complex<f64>>,
    pub training_frequencies_hz: Vec<f64>,
    pub training_regressors: Vec<Vec<f64>>,
    pub baseline: Option<Baseline>,
    pub observations: usize,
    /// The current block's (frequency, prediction, regressors).
    pub block: Vec<(f64, f64, Vec<f64>)>,
}

/// Follows a building's modes from window to window.
#[derive(Debug, Clone)]
pub struct ModeTracker {
    pub config: TrackerConfig,
    pub tracks: Vec<Track>,
}

impl ModeTracker {
    pub fn new(config: TrackerConfig) -> ModeTracker {
        ModeTracker {
            config,
            tracks: Vec::new(),
        }
    }

    /// Matches a window's modes to the tracks, and judges each matched track's residual.
    /// `regressors` are the window's environmental values, temperature first (see the
    /// module's documentation).
    pub fn update(&mut self, modes: &[ModeObservation], regressors: &[f64]) -> Vec<TrackUpdate> {
        let mut pairs: Vec<(f64, usize, usize)> = Vec::new();
        for (m, mode) in modes.iter().enumerate() {
            for (t, track) in self.tracks.iter().enumerate() {
                let df = (mode.frequency_hz.value - track.last_frequency_hz).abs()
                    / track.last_frequency_hz;
                if df > self.config.frequency_tolerance
                    || mode.shape.len() != track.last_shape.len()
                {
                    continue;
                }
                let m_ac = mac(&mode.shape, &track.last_shape);
                if m_ac >= self.config.mac_min {
                    pairs.push((m_ac, m, t));
                }
            }
        }
        pairs.sort_by(|a, b| b.0.total_cmp(&a.0));
        let mut mode_taken = vec![None; modes.len()];
        let mut track_taken = vec![false; self.tracks.len()];
        for (_, m, t) in pairs {
            if mode_taken[m].is_none() && !track_taken[t] {
                mode_taken[m] = Some(t);
                track_taken[t] = true;
            }
        }
        let mut updates = Vec::new();
        for (m, mode) in modes.iter().enumerate() {
            let t = match mode_taken[m] {
                Some(t) => t,
                None => {
                    self.tracks.push(Track {
                        id: self.tracks.len(),
                        direction: mode.direction,
                        last_frequency_hz: mode.frequency_hz.value,
                        last_shape: mode.shape.clone(),
                        training_frequencies_hz: Vec::new(),
                        training_regressors: Vec::new(),
                        baseline: None,
                        observations: 0,
                        block: Vec::new(),
                    });
                    self.tracks.len() - 1
                }
            };
            updates.push(self.observe(t, mode, regressors));
        }
        updates
    }

    fn observe(&mut self, t: usize, mode: &ModeObservation, regressors: &[f64]) -> TrackUpdate {
        let config = self.config.clone();
        let track = &mut self.tracks[t];
        track.last_frequency_hz = mode.frequency_hz.value;
        track.last_shape = mode.shape.clone();
        track.observations += 1;
        let f = mode.frequency_hz.value;
        let mut update = TrackUpdate {
            track: track.id,
            direction: track.direction,
            frequency_hz: mode.frequency_hz,
            predicted_hz: None,
            residual_relative: None,
            verdict: ShiftVerdict::Training,
            block_mean_relative: None,
            block_verdict: None,
        };
        let Some(baseline) = &track.baseline else {
            track.training_frequencies_hz.push(f);
            track.training_regressors.push(regressors.to_vec());
            if track.training_frequencies_hz.len() >= config.training_windows {
                track.baseline =
                    Baseline::fit(&track.training_frequencies_hz, &track.training_regressors);
            }
            return update;
        };
        let (predicted, u) = baseline.predict(regressors);
        let p = config.coverage_probability(config.window_false_alarm_probability());
        let residual = Estimate::new((f - predicted) / predicted, u / predicted, baseline.dof, p);
        update.predicted_hz = Some(predicted);
        update.residual_relative = Some(residual);
        update.verdict = decide(&residual, config.threshold_relative, config.drops_only);
        track.block.push((f, predicted, regressors.to_vec()));
        if track.block.len() >= config.average_windows.max(1) {
            let mean = baseline.block_mean(&track.block);
            let p = config.coverage_probability(config.block_false_alarm_probability());
            let estimate = Estimate::new(mean.0, mean.1, baseline.dof, p);
            update.block_mean_relative = Some(estimate);
            update.block_verdict = Some(decide(
                &estimate,
                config.threshold_relative,
                config.drops_only,
            ));
            track.block.clear();
        }
        update
    }
}

/// The guard-band rule on a relative residual (see the module's documentation).
pub fn decide(residual: &Estimate, threshold_relative: f64, drops_only: bool) -> ShiftVerdict {
    let band = residual.expanded_uncertainty();
    if !(residual.value.is_finite() && band.is_finite()) {
        return ShiftVerdict::Possible;
    }
    let low = residual.value - band;
    let high = residual.value + band;
    let t = threshold_relative.abs();
    if high < -t || (!drops_only && low > t) {
        ShiftVerdict::Shift
    } else if low < -t || (!drops_only && high > t) {
        ShiftVerdict::Possible
    } else {
        ShiftVerdict::Normal
    }
}
