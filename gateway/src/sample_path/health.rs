//! Field calibration health, fed by the workers: every batch corrected with a record goes to
//! that record's [`SensorHealth`] monitor (the statistics live in `triax-health`), and the
//! gateway does three things with what the monitor says:
//!
//! - **reports** the sensor's health on `triax/<b>/health/<s>` ([`SensorHealthReport`]) every
//!   `publish_interval_s` of sensor time and at once when the verdict changes, and keeps the
//!   latest for the health queryable, status and metrics;
//! - **latches** a `suspect` record: the first time a monitor says `suspect`, the record is
//!   marked in the calibration store (durable before the next batch is corrected) with the time
//!   its flag starts, the end of the batch that decided;
//! - **flags** every sample of that record stamped at or after that time `calibration_suspect`,
//!   until another record is in force. The rule depends only on the mark in the store, the
//!   batch's record and its time stamp, so the history's replay applies the same rule and
//!   reproduces the live bytes, across restarts and kills; the tests themselves start afresh
//!   after a restart, the latch does not.
//!
//! The monitor for a record is made where the record is at hand (loading the store, accepting
//! a push) and handed to the sensor's worker through its entry (`state::health`): the gateway
//! keeps correctors, never records, in memory. The health queryable is a service
//! (`services::health`).

use std::sync::Arc;
use time::OffsetDateTime;

use triax_calibration::corrector::Corrector;
use triax_calibration_store::Store;
use triax_health::report::{HealthReport, TestReport};
use triax_health::{SensorHealth, Verdict};
use triax_protocol::batch::flags;
use triax_protocol::messages::{HealthTest, HealthVerdict, SensorHealthReport, StreamQuality};
use triax_protocol::{to_json, BuildingId, RawBatchView, JSON_FORMAT_VERSION};

use super::history::Verdict as SequenceVerdict;
use crate::state::{GroupSlot, GroupTests, SensorEntry};

/// What the workers need of the health settings.
#[derive(Debug, Clone, Copy)]
pub struct Reporting {
    pub publish_interval_ns: i64,
    /// [`crate::config::HealthSettings::clock_watch_ms`].
    pub clock_watch_ms: Option<f64>,
}

/// One sensor's health, as its worker keeps it.
#[derive(Debug, Default)]
pub struct HealthFeed {
    monitor: Option<Box<SensorHealth>>,
    /// The record found suspect, and the time its flag starts from.
    latch: Option<(u64, i64)>,
    /// Sensor time of the next periodic report.
    next_report_ns: i64,
    /// Blocks the monitor had judged when it was last asked for its verdict.
    blocks_seen: u64,
    /// The verdict last reported.
    reported: Option<HealthVerdict>,
    /// The record in force when no monitor was found for it.
    seedless: Option<u64>,
    quality: Quality,
}

/// The stream's quality since the monitor started, and its latency since the last report.
#[derive(Debug, Default, Clone, Copy)]
struct Quality {
    samples: u64,
    first_ns: Option<i64>,
    end_ns: i64,
    gaps: u64,
    rate_hz: f64,
    latency_min_ms: Option<f64>,
    latency_max_ms: Option<f64>,
}

impl HealthFeed {
    /// The monitor of the record in force, once there is one.
    pub fn monitor(&self) -> Option<&SensorHealth> {
        self.monitor.as_deref()
    }

    /// The feed of a sensor whose record `latch` names was found suspect before (the store's
    /// mark, loaded at start).
    pub fn new(latch: Option<(u64, i64)>) -> HealthFeed {
        HealthFeed {
            latch,
            next_report_ns: i64::MIN,
            ..HealthFeed::default()
        }
    }

    /// The flag a batch of `version` stamped `timestamp_ns` carries on every sample.
    pub fn flag(&self, version: Option<u64>, timestamp_ns: i64) -> u16 {
        suspect_flag(self.latch, version, timestamp_ns)
    }

    /// Feeds one batch corrected with `corrector` (none: uncalibrated, not judged) whose
    /// sequence the gateway judged `sequence`; returns a report to publish when one is due.
    #[allow(clippy::too_many_arguments)]
    pub fn observe(
        &mut self,
        building: &BuildingId,
        store: &Store,
        entry: &SensorEntry,
        corrector: Option<&Corrector>,
        view: &RawBatchView<'_>,
        sequence: SequenceVerdict,
        received_ns: i64,
        reporting: Reporting,
        pairs: &[Arc<GroupSlot>],
    ) -> Option<Vec<u8>> {
        let version = corrector?.version();
        if self.monitor.as_ref().is_none_or(|m| m.version() != version) {
            // A record without a monitor (checks off, or it could not be judged) is looked
            // for once, not on every batch.
            if self.seedless == Some(version) {
                return None;
            }
            self.monitor = entry.take_health_seed(version);
            if self.monitor.is_none() {
                self.seedless = Some(version);
                return None;
            }
            self.blocks_seen = 0;
            self.reported = None;
            self.quality = Quality::default();
            self.next_report_ns = i64::MIN;
        }
        let monitor = self.monitor.as_mut()?;
        let h = &view.header;
        let n = view.len();
        let end_ns = h
            .timestamp_ns
            .saturating_add((n as f64 * 1e9 / h.sample_rate_hz).round() as i64);
        match sequence {
            // Old signal: the checks judge the stream in time order.
            SequenceVerdict::Duplicate | SequenceVerdict::Late | SequenceVerdict::LateGap => {
                return None
            }
            SequenceVerdict::Gap | SequenceVerdict::Restart => monitor.break_stream(),
            SequenceVerdict::InOrder => {}
        }
        monitor.feed_view(view);
        self.quality.note(view, end_ns, sequence, received_ns);

        let blocks = monitor.blocks();
        let decided = blocks != self.blocks_seen;
        self.blocks_seen = blocks;
        let due = end_ns >= self.next_report_ns;
        if !(decided || due) {
            return None;
        }
        let report = monitor.report();
        let pair_tests: Vec<GroupTests> = pairs
            .iter()
            .filter_map(|p| p.tests_for(&entry.id, version))
            .collect();
        let clock = self.quality.clock_test(reporting.clock_watch_ms);
        let tested = pair_tests
            .iter()
            .flat_map(|p| &p.tests)
            .map(|(_, _, _, t)| t.verdict)
            .fold(report.verdict, Verdict::max);
        if tested == Verdict::Suspect && self.latch.is_none_or(|(v, _)| v != version) {
            self.latch = Some((version, latch(store, entry, version, end_ns)));
        }
        let latched = self.latch.filter(|&(v, _)| v == version).map(|(_, t)| t);
        let verdict = if latched.is_some() {
            HealthVerdict::Suspect
        } else {
            wire(tested).max(clock.verdict)
        };
        if !(due || self.reported != Some(verdict)) {
            return None;
        }
        self.reported = Some(verdict);
        self.next_report_ns = end_ns.saturating_add(reporting.publish_interval_ns);
        let mut message = message(
            building,
            entry,
            version,
            verdict,
            latched,
            &report,
            &self.quality,
        );
        message.tests.push(clock);
        message.gravity_direction = monitor.last_gravity_observation().map(|o| o.direction);
        for (name, axis, peer, t) in pair_tests.iter().flat_map(|p| &p.tests) {
            let mut t = test(name, Some(*axis), t);
            t.peer = Some(peer.clone());
            message.tests.push(t);
        }
        if message
            .tests
            .iter()
            .any(|t| t.judged && (t.test.starts_with("colocated_") || t.test == "triple_gain"))
        {
            message.calibration_checked = Some(true);
        }
        // The earliest start of any suspect test's evidence, the pairs' included.
        message.suspect_since_ns = message
            .tests
            .iter()
            .filter(|t| t.verdict == HealthVerdict::Suspect)
            .filter_map(|t| t.since_ns)
            .min();
        self.quality.latency_min_ms = None;
        self.quality.latency_max_ms = None;
        let json = to_json(&message);
        entry.set_health_report(json.clone(), verdict);
        Some(json)
    }
}

/// The flag rule of the module doc, shared by the live path and the replay.
pub fn suspect_flag(latch: Option<(u64, i64)>, version: Option<u64>, timestamp_ns: i64) -> u16 {
    match (latch, version) {
        (Some((v, from_ns)), Some(version)) if v == version && timestamp_ns >= from_ns => {
            flags::CALIBRATION_SUSPECT
        }
        _ => 0,
    }
}

/// Marks `version` suspect in the store from `from_ns`; returns the time the store holds (an
/// earlier mark stands). A store that cannot write still flags from `from_ns` live, and says
/// that replays will not.
fn latch(store: &Store, entry: &SensorEntry, version: u64, from_ns: i64) -> i64 {
    let from_ns = match store.mark_suspect(&entry.id, version, from_ns) {
        Ok(stored) => stored,
        Err(e) => {
            tracing::error!(sensor = %entry.id, version, cause = %e,
                "cannot mark the record suspect in the store: replays will lack calibration_suspect");
            from_ns
        }
    };
    tracing::warn!(sensor = %entry.id, version, flagged_from_ns = from_ns,
        "calibration suspect: samples flagged calibration_suspect until a new record is in force");
    entry.set_suspect(version, from_ns);
    from_ns
}

impl Quality {
    fn note(
        &mut self,
        view: &RawBatchView<'_>,
        end_ns: i64,
        sequence: SequenceVerdict,
        received_ns: i64,
    ) {
        self.samples += view.len() as u64;
        self.first_ns.get_or_insert(view.header.timestamp_ns);
        self.end_ns = self.end_ns.max(end_ns);
        self.rate_hz = view.header.sample_rate_hz;
        if sequence == SequenceVerdict::Gap {
            self.gaps += 1;
        }
        let period_ns = 1e9 / view.header.sample_rate_hz;
        let last_sample_ns = end_ns as f64 - period_ns;
        let latency_ms = (received_ns as f64 - last_sample_ns) / 1e6;
        self.latency_min_ms = Some(
            self.latency_min_ms
                .map_or(latency_ms, |m| m.min(latency_ms)),
        );
        self.latency_max_ms = Some(
            self.latency_max_ms
                .map_or(latency_ms, |m| m.max(latency_ms)),
        );
    }
}

impl Quality {
    /// The `clock` test: the smallest latency since the last report, the best estimate of the
    /// node's clock offset from the gateway's plus the link's least delay. Never `suspect`: a
    /// clock off does not make the calibration wrong, only the time stamps.
    fn clock_test(&self, watch_ms: Option<f64>) -> HealthTest {
        let off = match (self.latency_min_ms, watch_ms) {
            (Some(l), Some(w)) => l.abs() > w,
            _ => false,
        };
        HealthTest {
            test: "clock".to_owned(),
            channel: None,
            peer: None,
            verdict: if off {
                HealthVerdict::Watch
            } else {
                HealthVerdict::Ok
            },
            judged: self.latency_min_ms.is_some() && watch_ms.is_some(),
            statistic: self.latency_min_ms,
            uncertainty: None,
            unit: "ms".to_owned(),
            since_ns: None,
            evidence_nats: 0.0,
            observations: 0,
            reason: match (watch_ms, self.latency_min_ms) {
                (None, _) => Some("off".to_owned()),
                (_, None) => Some("no_data".to_owned()),
                _ => None,
            },
            masked: None,
            loud: None,
        }
    }
}

fn wire(v: Verdict) -> HealthVerdict {
    match v {
        Verdict::Ok => HealthVerdict::Ok,
        Verdict::Watch => HealthVerdict::Watch,
        Verdict::Suspect => HealthVerdict::Suspect,
    }
}

fn finite(x: f64) -> Option<f64> {
    x.is_finite().then_some(x)
}

fn unit_of(test: &str) -> &'static str {
    match test {
        "gravity_absolute" | "gravity_relative" => "m/s^2",
        "stuck" => "s",
        "noise" => "ratio",
        "colocated_absolute" | "colocated_relative" | "triple_gain" => "1",
        "triple_noise" => "ratio",
        _ => "1/h",
    }
}

fn test(name: &'static str, channel: Option<usize>, t: &TestReport) -> HealthTest {
    HealthTest {
        test: name.to_owned(),
        channel: channel.map(|c| c as u8),
        peer: None,
        verdict: wire(t.verdict),
        judged: t.judged,
        statistic: finite(t.statistic),
        uncertainty: finite(t.uncertainty),
        unit: unit_of(name).to_owned(),
        since_ns: t.since_ns,
        evidence_nats: if t.evidence_nats.is_finite() {
            t.evidence_nats
        } else {
            0.0
        },
        observations: t.observations,
        reason: (!t.judged)
            .then(|| t.reason.map(|r| r.as_str().to_owned()))
            .flatten(),
        masked: (name == "noise").then_some(t.masked),
        loud: (name == "noise").then_some(t.loud),
    }
}

fn message(
    building: &BuildingId,
    entry: &SensorEntry,
    version: u64,
    verdict: HealthVerdict,
    flagged_from_ns: Option<i64>,
    report: &HealthReport,
    q: &Quality,
) -> SensorHealthReport {
    let span_ns = q.first_ns.map_or(0, |f| q.end_ns.saturating_sub(f));
    let expected = span_ns as f64 * 1e-9 * q.rate_hz;
    let availability = if expected > 0.0 {
        (q.samples as f64 / expected).min(1.0)
    } else {
        1.0
    };
    SensorHealthReport {
        format_version: JSON_FORMAT_VERSION,
        building: building.clone(),
        sensor_id: entry.id.clone(),
        calibration_version: version,
        verdict,
        suspect_since_ns: report.suspect_since_ns,
        flagged_from_ns,
        reported_at: OffsetDateTime::now_utc(),
        data_until_ns: q.first_ns.map(|_| q.end_ns),
        blocks: report.blocks,
        quiet_stretches: report.quiet_stretches,
        discontinuities: report.discontinuities,
        calibration_checked: Some(report.calibration_checked()),
        gravity_direction: None,
        tests: report
            .tests()
            .iter()
            .map(|(name, channel, t)| test(name, *channel, t))
            .collect(),
        quality: StreamQuality {
            samples: q.samples,
            availability,
            gaps: q.gaps,
            latency_min_ms: q.latency_min_ms,
            latency_max_ms: q.latency_max_ms,
        },
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_clock_is_watched_beyond_its_bound_and_never_suspect() {
        let q = |min_ms| Quality {
            latency_min_ms: min_ms,
            ..Quality::default()
        };
        assert_eq!(
            q(Some(1500.0)).clock_test(Some(1000.0)).verdict,
            HealthVerdict::Watch
        );
        assert_eq!(
            q(Some(-1500.0)).clock_test(Some(1000.0)).verdict,
            HealthVerdict::Watch
        );
        let fine = q(Some(3.0)).clock_test(Some(1000.0));
        assert_eq!(
            (fine.verdict, fine.judged, fine.statistic),
            (HealthVerdict::Ok, true, Some(3.0))
        );
        let off = q(Some(1e9)).clock_test(None);
        assert_eq!((off.verdict, off.judged), (HealthVerdict::Ok, false));
        assert!(!q(None).clock_test(Some(1000.0)).judged);
    }

    #[test]
    fn the_flag_rule_takes_the_record_and_the_time() {
        let latch = Some((3, 1_000));
        assert_eq!(
            suspect_flag(latch, Some(3), 1_000),
            flags::CALIBRATION_SUSPECT
        );
        assert_eq!(suspect_flag(latch, Some(3), 999), 0, "before the mark");
        assert_eq!(suspect_flag(latch, Some(4), 5_000), 0, "another record");
        assert_eq!(suspect_flag(latch, None, 5_000), 0, "uncalibrated");
        assert_eq!(suspect_flag(None, Some(3), 5_000), 0);
    }
}
