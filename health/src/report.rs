//! What a monitor says about a sensor: a verdict per test with its evidence.

use crate::cusum::Verdict;

/// One test's state. `statistic` and `uncertainty` are in the unit its field documents in
/// [`HealthReport`]; `uncertainty` is a standard uncertainty (k = 1).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TestReport {
    pub verdict: Verdict,
    /// Whether the test has had the data it needs; a test not yet judged is `ok`.
    pub judged: bool,
    pub statistic: f64,
    pub uncertainty: f64,
    /// Since when the verdict holds (`watch`, `suspect`), ns.
    pub since_ns: Option<i64>,
    /// The sequential test's accumulated log-likelihood ratio, nats (0 for tests that are
    /// not sequential).
    pub evidence_nats: f64,
    /// Observations judged (blocks, or quiet stretches for the gravity tests, noise
    /// windows, pair estimates).
    pub observations: u64,
    /// Why the test is not judged yet, while `judged` is false (a fixed vocabulary:
    /// [`Unjudged`]).
    pub reason: Option<Unjudged>,
    /// Noise windows left unjudged because the building's motion masked the floor, and
    /// because transients filled them (noise tests only; 0 for the others).
    pub masked: u64,
    pub loud: u64,
}

/// Why a test has not been judged.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Unjudged {
    /// The building gave the sensor no quiet minute yet (gravity tests).
    NoQuietStretch,
    /// Fewer quiet minutes than the absolute test's first look needs.
    FewQuietStretches,
    /// The gateway was given no local gravity (absolute gravity test).
    NoLocalGravity,
    /// The relative test's baseline is still being taken.
    Baseline,
    /// The record states no output noise.
    NoStatedNoise,
    /// Every noise window so far was masked by motion or filled with transients.
    Masked,
    /// No batch yet.
    NoData,
    /// No estimate of the pair yet (too little coherent motion in its band, or too little
    /// time).
    NoEstimate,
}

impl Unjudged {
    pub fn as_str(self) -> &'static str {
        match self {
            Unjudged::NoQuietStretch => "no_quiet_stretch",
            Unjudged::FewQuietStretches => "few_quiet_stretches",
            Unjudged::NoLocalGravity => "no_local_gravity",
            Unjudged::Baseline => "baseline",
            Unjudged::NoStatedNoise => "no_stated_noise",
            Unjudged::Masked => "masked",
            Unjudged::NoData => "no_data",
            Unjudged::NoEstimate => "no_estimate",
        }
    }
}

impl TestReport {
    pub(crate) fn pending() -> TestReport {
        TestReport {
            verdict: Verdict::Ok,
            judged: false,
            statistic: f64::NAN,
            uncertainty: f64::NAN,
            since_ns: None,
            evidence_nats: 0.0,
            observations: 0,
            reason: Some(Unjudged::NoData),
            masked: 0,
            loud: 0,
        }
    }

    /// Not judged, for `reason`.
    pub(crate) fn unjudged(reason: Unjudged) -> TestReport {
        TestReport {
            reason: Some(reason),
            ..TestReport::pending()
        }
    }
}

/// A sensor's health under one calibration record.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HealthReport {
    /// The worst verdict of the tests.
    pub verdict: Verdict,
    /// The earliest start of a `suspect` verdict: from then on the sensor's samples are not
    /// to be trusted as the record states them.
    pub suspect_since_ns: Option<i64>,
    /// Magnitude of the quiet reading through the static set minus local gravity, m/s².
    pub gravity_absolute: TestReport,
    /// Magnitude of the quiet reading minus its baseline since the record came into force,
    /// m/s² (the uncertainty includes the baseline's).
    pub gravity_relative: TestReport,
    /// Per output channel: how long the channel has been dead, s (the uncertainty is one block).
    pub stuck: [TestReport; 3],
    /// Per output channel: the noise floor of the last judged window (the channel's own noise
    /// or less), as a ratio of standard deviations to the record's `output_noise`.
    pub noise: [TestReport; 3],
    /// Per output channel: isolated spikes per hour over the last hour.
    pub spikes: [TestReport; 3],
    /// Blocks judged, quiet stretches used, and breaks in the stream (gaps, restarts, rate
    /// changes) since the monitor started.
    pub blocks: u64,
    pub quiet_stretches: u64,
    pub discontinuities: u64,
}

impl HealthReport {
    /// Whether the calibration itself (gains and offsets, not the channels' behaviour) has
    /// been checked: a gravity or co-located test judged. `ok` without it means nothing was
    /// found because nothing could be looked at.
    pub fn calibration_checked(&self) -> bool {
        self.gravity_absolute.judged || self.gravity_relative.judged
    }

    /// Every test, named, for a caller that lists them.
    pub fn tests(&self) -> [(&'static str, Option<usize>, &TestReport); 11] {
        [
            ("gravity_absolute", None, &self.gravity_absolute),
            ("gravity_relative", None, &self.gravity_relative),
            ("stuck", Some(0), &self.stuck[0]),
            ("stuck", Some(1), &self.stuck[1]),
            ("stuck", Some(2), &self.stuck[2]),
            ("noise", Some(0), &self.noise[0]),
            ("noise", Some(1), &self.noise[1]),
            ("noise", Some(2), &self.noise[2]),
            ("spikes", Some(0), &self.spikes[0]),
            ("spikes", Some(1), &self.spikes[1]),
            ("spikes", Some(2), &self.spikes[2]),
        ]
    }
}
