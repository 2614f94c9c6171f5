//! Tracking modes across windows, regressing out the environment, and deciding on a shift.
//!
//! **Matching.** A track's shape is the running mean of the in-phase shapes of the modes it
//! matched (each of unit norm, turned to the mean's phase, over the last `shape_windows`), so
//! that one poor window does not become the shape the next is compared with. Its frequency
//! scatter is its own: the running mean square of the change from one matched window to the next
//! (a prior of 1 % of the frequency counts for two windows, floored at 0.1 %). Each window's
//! modes are assigned one to one to the tracks at the least total cost (a small assignment),
//! `z²/band² + (1 − MAC)/(1 − mac_min)`, where `z` is the frequency's distance from the track's
//! last, in the track's scatter, and the MAC is with the track's shape. A pair may be taken when
//! the frequency is within `frequency_tolerance` (10 %) of the track's last and the MAC is at
//! least `mac_min` (0.8). Tracks that have followed their mode for `shape_windows` are assigned
//! first, younger ones then the modes left: a mode identified twice in a window starts a track
//! with the second, which then gets windows only when the established track has one already.
//! Close modes in `x` and `y` (a few % apart) have nearly orthogonal shapes, so the MAC keeps
//! them apart where a frequency rule would swap them as the temperature moves both. A mode left
//! over may then still join a track of its direction that got no mode in this window when its
//! frequency is within the track's band (`|z| ≤ frequency_band`) and its MAC is at least
//! `mac_min_in_band` (a window whose shape is poor for the mode, not another mode); only a mode
//! no track can take starts one.
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
//! freedom under no change. With `τ = threshold_relative`, the smallest drop that matters (0:
//! any), and for a drop (a loss of stiffness lowers frequencies; both sides with
//! `drops_only = false`):
//!
//! - `normal`: `r + k_n·u ≥ −τ`, the frequency is inside the environmental model's own
//!   prediction interval at `normal_probability` (95 %, two-sided, `k_n` Student's at ν),
//!   widened by `τ`: so a healthy building reads `normal` in 97.5 % of windows when only drops
//!   are judged (95 % when both sides are), whatever `τ`;
//! - `shift`: `r + k·u < −τ`, even the near end of the alarm interval is beyond `τ` (the
//!   guard band of the alerting service, ISO/IEC 17025 §7.8.6), `k` Student's quantile at the
//!   test's false-alarm probability `α`: `P(shift | no change) ≤ α`;
//! - `possible`: in between: outside the prediction interval, not beyond the alarm's.
//!
//! Three tests share the stated yearly false-alarm budget in thirds: the single window (an
//! abrupt change, seen at once), the mean of each block of `average_windows` consecutive
//! windows (a small change: a day of windows averages the identification's scatter down by
//! √48, while the baseline's own error, shared by the block, is kept), and a sequential test,
//! Page's CUSUM of the standardised residuals' log-likelihood ratio for a drop of
//! `cusum_shift` standard uncertainties against none (`ℓ = −δ·z − δ²/2` with
//! `z = (r + τ)/u`, `S = max(0, S + ℓ)`), which accumulates a persistent small drop window by
//! window instead of waiting for a block to end: `shift` when `S ≥ h = ln(A)`, and by Lorden's
//! bound the mean run length to a false alarm is at least `e^h = A`, set to the windows the
//! test's share of the budget allows (`3·windows_per_year / false_alarms_per_year`); `S`
//! starts again from 0 after a `shift`. A drop of `d` standard uncertainties is found after
//! about `h/(δ·d − δ²/2)` windows. Each holds for residuals independent from window to
//! window; an environmental effect the regressors miss makes them correlated, and a Monte Carlo
//! (the crate's tests) measures the rate that results.

use nalgebra::{Complex, DMatrix, DVector};
use serde::{Deserialize, Serialize};

use crate::identify::Mode;
use crate::model::Direction;
use crate::ssi::mac;
use crate::uncertainty::{coverage_factor, Estimate};

/// Settings of the tracker.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct TrackerConfig {
    pub frequency_tolerance: f64,
    pub mac_min: f64,
    /// Windows over which a track's shape and frequency scatter are averaged.
    pub shape_windows: usize,
    /// A track's band: the frequency's distance from the track's last, in the track's scatter.
    pub frequency_band: f64,
    /// The least MAC with which a mode within a track's band joins it when no other mode did.
    pub mac_min_in_band: f64,
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
    /// Coverage of the prediction interval that bounds `normal` (two-sided).
    pub normal_probability: f64,
    /// The drop the sequential test is tuned to, in standard uncertainties of a prediction.
    pub cusum_shift: f64,
}

impl Default for TrackerConfig {
    fn default() -> Self {
        TrackerConfig {
            frequency_tolerance: 0.10,
            mac_min: 0.8,
            shape_windows: 48,
            frequency_band: 4.0,
            mac_min_in_band: 0.5,
            training_windows: 336,
            false_alarms_per_year: 1.0,
            windows_per_year: 365.25 * 48.0,
            threshold_relative: 0.0,
            drops_only: true,
            average_windows: 48,
            normal_probability: 0.95,
            cusum_shift: 1.5,
        }
    }
}

impl TrackerConfig {
    /// The per-test false-alarm probability of the single-window test: a third of the yearly
    /// budget over the windows of a year.
    pub fn window_false_alarm_probability(&self) -> f64 {
        self.false_alarms_per_year / (3.0 * self.windows_per_year)
    }

    /// The per-test false-alarm probability of the block-mean test: a third over the blocks of
    /// a year.
    pub fn block_false_alarm_probability(&self) -> f64 {
        self.false_alarms_per_year * self.average_windows.max(1) as f64
            / (3.0 * self.windows_per_year)
    }

    /// The sequential test's threshold `h`: the log of the mean run length to a false alarm
    /// its third of the budget allows (each side half of it when rises are judged too).
    pub fn cusum_threshold(&self) -> f64 {
        let sides = if self.drops_only { 1.0 } else { 2.0 };
        (sides * 3.0 * self.windows_per_year / self.false_alarms_per_year)
            .max(1.0)
            .ln()
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

/// The verdict on a window for one track (the module's documentation).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ShiftVerdict {
    /// The baseline is still being learnt.
    Training,
    /// Inside the environmental model's prediction interval, widened by the threshold.
    Normal,
    /// Outside the prediction interval, not beyond the alarm's.
    Possible,
    /// Beyond the alarm interval and the threshold: a `modal_shift`.
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
    /// The coverage factor of the prediction interval that bounds `normal`.
    pub normal_factor: Option<f64>,
    /// When this window completes a block of `average_windows`: the block's mean relative
    /// residual and its verdict.
    pub block_mean_relative: Option<Estimate>,
    pub block_verdict: Option<ShiftVerdict>,
    /// The sequential test after this window (the larger side's statistic), its threshold and
    /// verdict (`normal` or `shift`); none while training.
    pub cusum: Option<f64>,
    pub cusum_threshold: Option<f64>,
    pub cusum_verdict: Option<ShiftVerdict>,
}

/// A mode followed across windows.
#[derive(Debug, Clone, PartialEq)]
pub struct Track {
    pub id: usize,
    pub direction: Direction,
    pub last_frequency_hz: f64,
    pub last_shape: Vec<Complex<f64>>,
    /// The running mean of the matched in-phase shapes, of unit norm (empty: `last_shape`).
    pub mean_shape: Vec<Complex<f64>>,
    /// The running mean square of the frequency's change between matched windows, Hz².
    pub step_variance_hz2: f64,
    /// Changes averaged into `step_variance_hz2`.
    pub steps: usize,
    pub training_frequencies_hz: Vec<f64>,
    pub training_regressors: Vec<Vec<f64>>,
    pub baseline: Option<Baseline>,
    pub observations: usize,
    /// The current block's (frequency, prediction, regressors).
    pub block: Vec<(f64, f64, Vec<f64>)>,
    /// The sequential test's statistics for a drop and for a rise.
    pub cusum_down: f64,
    pub cusum_up: f64,
}

/// The prior of a track's frequency scatter, relative, and the windows it counts for.
const PRIOR_SCATTER_RELATIVE: f64 = 0.01;
const PRIOR_WINDOWS: f64 = 2.0;
/// The least frequency scatter of a track, relative.
const MIN_SCATTER_RELATIVE: f64 = 0.001;
/// The cost of a pair that may not be taken.
const EXCLUDED: f64 = 1e6;

impl Track {
    fn new(id: usize, mode: &ModeObservation) -> Track {
        Track {
            id,
            direction: mode.direction,
            last_frequency_hz: mode.frequency_hz.value,
            last_shape: mode.shape.clone(),
            mean_shape: Vec::new(),
            step_variance_hz2: 0.0,
            steps: 0,
            training_frequencies_hz: Vec::new(),
            training_regressors: Vec::new(),
            baseline: None,
            observations: 0,
            block: Vec::new(),
            cusum_down: 0.0,
            cusum_up: 0.0,
        }
    }

    /// The shape a mode is compared with: the running mean, or the last for a state without.
    pub fn shape(&self) -> &[Complex<f64>] {
        if self.mean_shape.len() == self.last_shape.len() {
            &self.mean_shape
        } else {
            &self.last_shape
        }
    }

    /// The standard deviation of a window's frequency about the track's last, Hz.
    pub fn frequency_scatter_hz(&self, shape_windows: usize) -> f64 {
        let f = self.last_frequency_hz.abs();
        let n = self.steps.min(shape_windows.max(1)) as f64;
        let prior = (PRIOR_SCATTER_RELATIVE * f).powi(2);
        let variance = (PRIOR_WINDOWS * prior + n * self.step_variance_hz2) / (PRIOR_WINDOWS + n);
        variance.sqrt().max(MIN_SCATTER_RELATIVE * f)
    }

    /// Adds a matched mode's frequency and shape to the running averages.
    fn learn(&mut self, mode: &ModeObservation, shape_windows: usize) {
        let horizon = shape_windows.max(1);
        let f = mode.frequency_hz.value;
        if self.observations > 0 && f.is_finite() {
            let w = 1.0 / (self.steps + 1).min(horizon) as f64;
            let d = f - self.last_frequency_hz;
            self.step_variance_hz2 = (1.0 - w) * self.step_variance_hz2 + w * d * d;
            self.steps += 1;
        }
        let norm = mode.shape.iter().map(|c| c.norm_sqr()).sum::<f64>().sqrt();
        if !(norm > 0.0 && norm.is_finite()) {
            return;
        }
        let mut shape: Vec<Complex<f64>> = mode.shape.iter().map(|c| c / norm).collect();
        let reference = self.shape();
        let reference_norm = reference.iter().map(|c| c.norm_sqr()).sum::<f64>().sqrt();
        if reference.len() != shape.len()
            || self.observations == 0
            || reference_norm.is_nan()
            || reference_norm <= 0.0
        {
            self.mean_shape = shape;
            return;
        }
        let reference: Vec<Complex<f64>> = reference.iter().map(|c| c / reference_norm).collect();
        // Turned to the mean's phase (a sign for in-phase shapes).
        let cross: Complex<f64> = shape
            .iter()
            .zip(&reference)
            .map(|(s, m)| s.conj() * m)
            .sum();
        if cross.norm() > 0.0 {
            let turn = cross / cross.norm();
            shape.iter_mut().for_each(|s| *s *= turn);
        }
        let w = 1.0 / (self.observations + 1).min(horizon) as f64;
        let mut mean: Vec<Complex<f64>> = reference
            .iter()
            .zip(&shape)
            .map(|(m, s)| m * (1.0 - w) + s * w)
            .collect();
        let norm = mean.iter().map(|c| c.norm_sqr()).sum::<f64>().sqrt();
        if norm > 0.0 && norm.is_finite() {
            mean.iter_mut().for_each(|c| *c /= norm);
            self.mean_shape = mean;
        }
    }
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

    /// The cost of giving `mode` to `track` (see the module's documentation), or `EXCLUDED`.
    fn cost(&self, mode: &ModeObservation, track: &Track, in_band: bool) -> f64 {
        let f = mode.frequency_hz.value;
        let shape = track.shape();
        if !f.is_finite() || mode.shape.len() != shape.len() {
            return EXCLUDED;
        }
        let df = (f - track.last_frequency_hz).abs() / track.last_frequency_hz;
        if df > self.config.frequency_tolerance {
            return EXCLUDED;
        }
        let band = self.config.frequency_band.max(f64::MIN_POSITIVE);
        let z =
            (f - track.last_frequency_hz) / track.frequency_scatter_hz(self.config.shape_windows);
        let m_ac = mac(&mode.shape, shape);
        let admitted = if in_band {
            mode.direction == track.direction
                && z.abs() <= band
                && m_ac >= self.config.mac_min_in_band
        } else {
            m_ac >= self.config.mac_min
        };
        if !admitted {
            return EXCLUDED;
        }
        (z / band).powi(2) + (1.0 - m_ac) / (1.0 - self.config.mac_min).max(1e-6)
    }

    /// Whether a track has followed its mode for `shape_windows`: such tracks are offered a
    /// window's modes before younger ones.
    fn established(&self, track: &Track) -> bool {
        track.observations >= self.config.shape_windows
    }

    /// Assigns the modes not yet taken to the tracks not yet taken, established or not, at the
    /// least total cost.
    fn assign(
        &self,
        modes: &[ModeObservation],
        mode_taken: &mut [Option<usize>],
        track_taken: &mut [bool],
        established: bool,
        in_band: bool,
    ) {
        let rows: Vec<usize> = (0..modes.len())
            .filter(|&m| mode_taken[m].is_none())
            .collect();
        let cols: Vec<usize> = (0..self.tracks.len())
            .filter(|&t| !track_taken[t] && self.established(&self.tracks[t]) == established)
            .collect();
        if rows.is_empty() || cols.is_empty() {
            return;
        }
        let cost: Vec<Vec<f64>> = rows
            .iter()
            .map(|&m| {
                cols.iter()
                    .map(|&t| self.cost(&modes[m], &self.tracks[t], in_band))
                    .collect()
            })
            .collect();
        for (r, c) in least_cost_assignment(&cost) {
            if cost[r][c] < EXCLUDED {
                mode_taken[rows[r]] = Some(cols[c]);
                track_taken[cols[c]] = true;
            }
        }
    }

    /// Matches a window's modes to the tracks, and judges each matched track's residual.
    /// `regressors` are the window's environmental values, temperature first (see the
    /// module's documentation).
    pub fn update(&mut self, modes: &[ModeObservation], regressors: &[f64]) -> Vec<TrackUpdate> {
        let mut mode_taken = vec![None; modes.len()];
        let mut track_taken = vec![false; self.tracks.len()];
        for (established, in_band) in [(true, false), (false, false), (true, true), (false, true)] {
            self.assign(
                modes,
                &mut mode_taken,
                &mut track_taken,
                established,
                in_band,
            );
        }
        let mut updates = Vec::new();
        for (m, mode) in modes.iter().enumerate() {
            let t = match mode_taken[m] {
                Some(t) => t,
                None => {
                    self.tracks.push(Track::new(self.tracks.len(), mode));
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
        track.learn(mode, config.shape_windows);
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
            normal_factor: None,
            block_mean_relative: None,
            block_verdict: None,
            cusum: None,
            cusum_threshold: None,
            cusum_verdict: None,
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
        let k_normal = coverage_factor(baseline.dof, config.normal_probability);
        update.predicted_hz = Some(predicted);
        update.residual_relative = Some(residual);
        update.normal_factor = Some(k_normal);
        update.verdict = decide(
            &residual,
            k_normal,
            config.threshold_relative,
            config.drops_only,
        );
        // The sequential test, on the residual standardised beyond the threshold.
        let delta = config.cusum_shift;
        let tau = config.threshold_relative.abs();
        let u_rel = residual.standard_uncertainty;
        if u_rel > 0.0 && residual.value.is_finite() {
            let down = (residual.value + tau) / u_rel;
            track.cusum_down = (track.cusum_down - delta * down - 0.5 * delta * delta).max(0.0);
            if !config.drops_only {
                let up = (residual.value - tau) / u_rel;
                track.cusum_up = (track.cusum_up + delta * up - 0.5 * delta * delta).max(0.0);
            }
        }
        let h = config.cusum_threshold();
        let statistic = track.cusum_down.max(track.cusum_up);
        update.cusum = Some(statistic);
        update.cusum_threshold = Some(h);
        update.cusum_verdict = Some(if statistic >= h {
            track.cusum_down = 0.0;
            track.cusum_up = 0.0;
            ShiftVerdict::Shift
        } else {
            ShiftVerdict::Normal
        });
        track.block.push((f, predicted, regressors.to_vec()));
        if track.block.len() >= config.average_windows.max(1) {
            let mean = baseline.block_mean(&track.block);
            let p = config.coverage_probability(config.block_false_alarm_probability());
            let estimate = Estimate::new(mean.0, mean.1, baseline.dof, p);
            update.block_mean_relative = Some(estimate);
            update.block_verdict = Some(decide(
                &estimate,
                coverage_factor(baseline.dof, config.normal_probability),
                config.threshold_relative,
                config.drops_only,
            ));
            track.block.clear();
        }
        update
    }
}

/// The rows' columns of least total cost in a matrix of costs (rows and columns of any
/// number): the Hungarian method on the matrix padded square with `EXCLUDED`. Pairs of
/// `EXCLUDED` cost are among those returned; the caller drops them.
fn least_cost_assignment(cost: &[Vec<f64>]) -> Vec<(usize, usize)> {
    let rows = cost.len();
    let cols = cost.first().map_or(0, Vec::len);
    let n = rows.max(cols);
    let a = |i: usize, j: usize| {
        if i < rows && j < cols {
            cost[i][j].min(EXCLUDED)
        } else {
            EXCLUDED
        }
    };
    // Potentials u (rows) and v (columns), 1-based with a dummy 0; p[j]: the row of column j.
    let mut u = vec![0.0; n + 1];
    let mut v = vec![0.0; n + 1];
    let mut p = vec![0usize; n + 1];
    let mut way = vec![0usize; n + 1];
    for i in 1..=n {
        p[0] = i;
        let mut j0 = 0;
        let mut minv = vec![f64::INFINITY; n + 1];
        let mut used = vec![false; n + 1];
        loop {
            used[j0] = true;
            let i0 = p[j0];
            let mut delta = f64::INFINITY;
            let mut j1 = 0;
            for j in 1..=n {
                if !used[j] {
                    let cur = a(i0 - 1, j - 1) - u[i0] - v[j];
                    if cur < minv[j] {
                        minv[j] = cur;
                        way[j] = j0;
                    }
                    if minv[j] < delta {
                        delta = minv[j];
                        j1 = j;
                    }
                }
            }
            for j in 0..=n {
                if used[j] {
                    u[p[j]] += delta;
                    v[j] -= delta;
                } else {
                    minv[j] -= delta;
                }
            }
            j0 = j1;
            if p[j0] == 0 {
                break;
            }
        }
        loop {
            let j1 = way[j0];
            p[j0] = p[j1];
            j0 = j1;
            if j0 == 0 {
                break;
            }
        }
    }
    (1..=n)
        .filter(|&j| p[j] >= 1 && p[j] <= rows && j <= cols)
        .map(|j| (p[j] - 1, j - 1))
        .collect()
}

/// The verdict on a relative residual (see the module's documentation): `shift` beyond the
/// alarm interval (the estimate's own `k`), `normal` inside the prediction interval of
/// coverage factor `k_normal`, both widened by the threshold, `possible` between.
pub fn decide(
    residual: &Estimate,
    k_normal: f64,
    threshold_relative: f64,
    drops_only: bool,
) -> ShiftVerdict {
    let alarm = residual.expanded_uncertainty();
    let normal = k_normal * residual.standard_uncertainty;
    let r = residual.value;
    if !(r.is_finite() && alarm.is_finite() && normal.is_finite()) {
        return ShiftVerdict::Possible;
    }
    let t = threshold_relative.abs();
    if r + alarm < -t || (!drops_only && r - alarm > t) {
        ShiftVerdict::Shift
    } else if r + normal < -t || (!drops_only && r - normal > t) {
        ShiftVerdict::Possible
    } else {
        ShiftVerdict::Normal
    }
}
