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
    /// Observations judged (blocks, or quiet stretches for the gravity tests).
    pub observations: u64,
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
    /// Per output channel: standard deviation of the white noise over the last ten minutes,
    /// as a ratio to the record's `output_noise`.
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
