//! What a building states about its sensors' health checks, and the errors of this crate.

use thiserror::Error;
use triax_calibration::corrector::LoadError;

use crate::gravity::LocalGravity;

/// Why a health monitor cannot be made.
#[derive(Debug, Clone, PartialEq, Error)]
pub enum HealthError {
    #[error("health configuration: {field}: {problem}")]
    Config {
        field: &'static str,
        problem: String,
    },
    #[error(transparent)]
    Calibration(#[from] LoadError),
    #[error(
        "the corrector is sensor {corrector_sensor} version {corrector_version}, the record \
         sensor {record_sensor} version {record_version}: a monitor judges one record"
    )]
    Mismatch {
        corrector_sensor: String,
        corrector_version: u64,
        record_sensor: String,
        record_version: u64,
    },
}

/// The checks' settings. [`Default`] gives the values the documentation states.
#[derive(Debug, Clone, PartialEq)]
pub struct HealthConfig {
    /// Length of a block, s: the unit every channel test judges and quiet is decided on.
    pub block_s: f64,
    /// RMS of the vibration (3-D, beyond the white output noise the block shows) below which a
    /// block is quiet, m/s².
    pub quiet_vibration_mps2: f64,
    /// Consecutive quiet time that makes one gravity observation, s.
    pub stretch_s: f64,
    /// The building's gravity; none: the absolute test is not judged.
    pub local_gravity: Option<LocalGravity>,
    /// Standard deviation of a healthy sensor's quiet reading from stretch to stretch beyond
    /// its white noise (bias instability, unmodelled slow effects), m/s²: added to every
    /// observation's uncertainty in both gravity tests.
    pub stability_mps2: f64,
    /// Change of the quiet reading's magnitude the relative test is designed to detect, m/s².
    /// It tolerates sustained changes below about half of it.
    pub relative_shift_mps2: f64,
    /// Quiet stretches, and sensor time since the first of them, that the relative test's
    /// baseline takes after a calibration comes into force (both must be reached): a day, so
    /// that the baseline spans the day's temperature cycle.
    pub baseline_stretches: u32,
    pub baseline_s: f64,
    /// Quiet stretches before the absolute test is judged.
    pub absolute_min_stretches: u32,
    /// Coverage probabilities whose Student's t bound the absolute test's `watch` and
    /// `suspect`: a healthy sensor with an honest record is `suspect` with probability
    /// `1 − absolute_suspect_probability` over a calibration's life.
    pub absolute_watch_probability: f64,
    pub absolute_suspect_probability: f64,
    /// Design average run lengths to a false `watch` and a false `suspect` of a healthy
    /// sensor, days of data, every sequential test together (Lorden's bound: the real ones are
    /// longer): each of the sensor's sequential tests (spikes on three channels, the relative
    /// gravity test, three relative co-located tests per pair) is given this times their
    /// number.
    pub watch_arl_days: f64,
    pub suspect_arl_days: f64,
    /// Co-located pairs this sensor is in: their tests share its budget.
    pub colocated_pairs: u32,
    /// Time a channel must be dead (constant, not finite, or with a second-difference noise
    /// below `dead_variance_ratio` of its stated noise variance) to be `suspect`, s.
    pub stuck_s: f64,
    pub dead_variance_ratio: f64,
    /// Ratio of the noise's standard deviation to the stated output noise (at its upper
    /// 99.9 % limit) that the noise test is designed to find: a window is `high` when its
    /// floor's variance exceeds this ratio (the geometric middle between 1 and its square),
    /// so noise ×√2 for the default 2.
    pub noise_design_ratio: f64,
    /// Consecutive `high` noise windows that make `watch`.
    pub noise_watch_windows: u32,
    /// How long a channel's noise or spike test must hold its finding, without a window or a
    /// block that clears it, before it is `suspect`, s: long enough to hold a night, when a
    /// building's motion leaves a channel's own noise to be seen.
    pub confirm_s: f64,
    /// A sample whose second difference exceeds this many standard deviations of the
    /// second differences (√6 σ for white noise σ) starts a spike candidate.
    pub spike_threshold_sigma: f64,
    /// Isolated spikes a healthy sensor may show, per hour (impacts on the structure, ESD):
    /// the spike test's in-control rate.
    pub spike_allowed_per_hour: f64,
    /// Multiple of that rate the spike test is designed to detect.
    pub spike_design_factor: f64,
}

impl Default for HealthConfig {
    fn default() -> Self {
        HealthConfig {
            block_s: 1.0,
            quiet_vibration_mps2: 0.01,
            stretch_s: 60.0,
            local_gravity: None,
            stability_mps2: 2e-4,
            relative_shift_mps2: 0.005,
            baseline_stretches: 60,
            baseline_s: 86_400.0,
            absolute_min_stretches: 10,
            absolute_watch_probability: 0.99,
            absolute_suspect_probability: 0.999,
            watch_arl_days: 30.0,
            suspect_arl_days: 10_000.0,
            colocated_pairs: 0,
            stuck_s: 10.0,
            dead_variance_ratio: 0.01,
            noise_design_ratio: 2.0,
            noise_watch_windows: 2,
            confirm_s: 86_400.0,
            spike_threshold_sigma: 8.0,
            spike_allowed_per_hour: 1.0,
            spike_design_factor: 20.0,
        }
    }
}

impl HealthConfig {
    /// Refuses settings that would make a test meaningless, by field.
    pub fn validate(&self) -> Result<(), HealthError> {
        let bad =
            |field: &'static str, problem: String| Err(HealthError::Config { field, problem });
        let positive: [(&'static str, f64); 12] = [
            ("block_s", self.block_s),
            ("quiet_vibration_mps2", self.quiet_vibration_mps2),
            ("stretch_s", self.stretch_s),
            ("relative_shift_mps2", self.relative_shift_mps2),
            ("baseline_s", self.baseline_s),
            ("watch_arl_days", self.watch_arl_days),
            ("suspect_arl_days", self.suspect_arl_days),
            ("stuck_s", self.stuck_s),
            ("confirm_s", self.confirm_s),
            ("spike_threshold_sigma", self.spike_threshold_sigma),
            ("spike_allowed_per_hour", self.spike_allowed_per_hour),
            ("dead_variance_ratio", self.dead_variance_ratio),
        ];
        for (field, value) in positive {
            if !(value.is_finite() && value > 0.0) {
                return bad(field, format!("{value} must be finite and above 0"));
            }
        }
        if !(self.stability_mps2.is_finite() && self.stability_mps2 >= 0.0) {
            return bad(
                "stability_mps2",
                format!("{} must be finite and at least 0", self.stability_mps2),
            );
        }
        if !(0.01..=60.0).contains(&self.block_s) {
            return bad(
                "block_s",
                format!("{} s is outside 0.01 to 60 s", self.block_s),
            );
        }
        if self.stretch_s < 10.0 * self.block_s {
            return bad(
                "stretch_s",
                format!(
                    "{} s holds fewer than 10 blocks of {} s: its noise could not be estimated",
                    self.stretch_s, self.block_s
                ),
            );
        }
        if self.noise_watch_windows == 0 {
            return bad("noise_watch_windows", "0 must be at least 1".into());
        }
        if self.watch_arl_days > self.suspect_arl_days {
            return bad(
                "watch_arl_days",
                format!(
                    "{} is above suspect_arl_days {}: watch must come before suspect",
                    self.watch_arl_days, self.suspect_arl_days
                ),
            );
        }
        let p = (
            self.absolute_watch_probability,
            self.absolute_suspect_probability,
        );
        if !(0.5 <= p.0 && p.0 <= p.1 && p.1 < 1.0) {
            return bad(
                "absolute_suspect_probability",
                format!(
                    "watch {} and suspect {}: need 0.5 ≤ watch ≤ suspect < 1",
                    p.0, p.1
                ),
            );
        }
        if !(self.noise_design_ratio.is_finite() && self.noise_design_ratio > 1.0) {
            return bad(
                "noise_design_ratio",
                format!("{} must be above 1", self.noise_design_ratio),
            );
        }
        if !(self.spike_design_factor.is_finite() && self.spike_design_factor > 1.0) {
            return bad(
                "spike_design_factor",
                format!("{} must be above 1", self.spike_design_factor),
            );
        }
        if self.dead_variance_ratio >= 0.25 {
            return bad(
                "dead_variance_ratio",
                format!(
                    "{} would call a channel dead at half its stated noise",
                    self.dead_variance_ratio
                ),
            );
        }
        if self.baseline_stretches < 2 {
            return bad(
                "baseline_stretches",
                format!("{} cannot fit a level and a slope", self.baseline_stretches),
            );
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn defaults_are_valid_and_refusals_name_the_field() {
        HealthConfig::default().validate().unwrap();
        let c = HealthConfig {
            block_s: 0.0,
            ..HealthConfig::default()
        };
        assert!(c.validate().unwrap_err().to_string().contains("block_s"));
        let c = HealthConfig {
            stretch_s: 5.0,
            ..HealthConfig::default()
        };
        assert!(c.validate().unwrap_err().to_string().contains("stretch_s"));
        let c = HealthConfig {
            noise_design_ratio: 1.0,
            ..HealthConfig::default()
        };
        assert!(c
            .validate()
            .unwrap_err()
            .to_string()
            .contains("noise_design_ratio"));
        let c = HealthConfig {
            absolute_suspect_probability: 1.0,
            ..HealthConfig::default()
        };
        assert!(c.validate().is_err());
    }
}
