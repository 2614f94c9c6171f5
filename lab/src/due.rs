//! Sensors due for recalibration, across buildings: what the gateways' field health checks say
//! (PROTOCOL.md §3.9), gathered from their health queryables and listed with the evidence.
//!
//! A sensor is *due* when its record in force is `suspect`; a sensor at `watch` is listed so
//! that the lab can plan, but is not due. The evidence of a report is every test that is not
//! `ok`: its statistic with its standard uncertainty and unit, and since when.

use std::time::Duration;

use time::OffsetDateTime;
use triax_protocol::messages::{HealthVerdict, SensorHealthReport};
use triax_protocol::{from_json, BuildingId};

/// Why the gathering failed.
#[derive(Debug, thiserror::Error)]
pub enum DueError {
    #[error("health query {selector}: {cause}")]
    Query { selector: String, cause: String },
}

/// A gateway's refusal or an unreadable reply, kept to be shown: one bad gateway does not hide
/// the others' answers.
#[derive(Debug, Clone, PartialEq)]
pub struct Problem {
    pub key: Option<String>,
    pub problem: String,
}

/// The health reports of the sensors at `least` or worse in `buildings` (none: every
/// building), sorted worst first, then by building and sensor.
pub async fn gather(
    session: &zenoh::Session,
    buildings: &[BuildingId],
    least: HealthVerdict,
    timeout: Duration,
) -> Result<(Vec<SensorHealthReport>, Vec<Problem>), DueError> {
    let selectors: Vec<String> = if buildings.is_empty() {
        vec![format!("triax/*/health/*?verdict={}", least.as_str())]
    } else {
        buildings
            .iter()
            .map(|b| format!("triax/{b}/health/*?verdict={}", least.as_str()))
            .collect()
    };
    let mut reports = Vec::new();
    let mut problems = Vec::new();
    for selector in selectors {
        let replies = session
            .get(selector.as_str())
            .timeout(timeout)
            .await
            .map_err(|e| DueError::Query {
                selector: selector.clone(),
                cause: e.to_string(),
            })?;
        while let Ok(reply) = replies.recv_async().await {
            match reply.result() {
                Ok(sample) => {
                    let key = sample.key_expr().as_str().to_owned();
                    match from_json::<SensorHealthReport>(&sample.payload().to_bytes()) {
                        Ok(r) => reports.push(r),
                        Err(e) => problems.push(Problem {
                            key: Some(key),
                            problem: e.to_string(),
                        }),
                    }
                }
                Err(e) => problems.push(Problem {
                    key: None,
                    problem: String::from_utf8_lossy(&e.payload().to_bytes()).into_owned(),
                }),
            }
        }
    }
    reports.sort_by(|a, b| {
        b.verdict
            .cmp(&a.verdict)
            .then_with(|| a.building.cmp(&b.building))
            .then_with(|| a.sensor_id.cmp(&b.sensor_id))
    });
    // A building reached through two routes answers twice.
    reports.dedup_by(|a, b| a.building == b.building && a.sensor_id == b.sensor_id);
    Ok((reports, problems))
}

fn time_of(ns: i64) -> String {
    OffsetDateTime::from_unix_timestamp_nanos(i128::from(ns))
        .ok()
        .and_then(|t| {
            t.format(&time::format_description::well_known::Rfc3339)
                .ok()
        })
        .unwrap_or_else(|| format!("{ns} ns"))
}

/// Decimals that show an uncertainty `u` to two significant digits (4 for 0.001 to 0.0099),
/// and its statistic to the same place: a small uncertainty is never printed as 0.
fn decimals(u: f64) -> usize {
    if !(u.is_finite() && u > 0.0) {
        return 4;
    }
    (1.0 - u.log10().floor()).clamp(0.0, 12.0) as usize
}

/// Whether a test judges the calibration itself (gains, offsets), not the channels.
fn judges_calibration(test: &str) -> bool {
    test.starts_with("gravity_") || test.starts_with("colocated_")
}

/// The evidence of a report: each test that is not `ok`, as `test[channel] statistic ± u unit
/// (verdict since time)`; for a sensor whose calibration nothing has checked, each test of
/// the calibration and why it is not judged.
pub fn evidence(r: &SensorHealthReport) -> Vec<String> {
    let mut lines = verdicts(r);
    if r.calibration_checked == Some(false) {
        lines.extend(
            r.tests
                .iter()
                .filter(|t| judges_calibration(&t.test) && !t.judged)
                .map(|t| {
                    format!(
                        "{} not judged: {} ({} observations)",
                        t.test,
                        t.reason.as_deref().unwrap_or("no reason given"),
                        t.observations
                    )
                }),
        );
    }
    lines
}

/// Whether `r` is listed for `least` (sensors at that verdict or worse) and `unchecked`
/// (also sensors whose calibration nothing has checked).
pub fn listed(r: &SensorHealthReport, least: HealthVerdict, unchecked: bool) -> bool {
    r.verdict >= least || (unchecked && r.calibration_checked == Some(false))
}

fn verdicts(r: &SensorHealthReport) -> Vec<String> {
    r.tests
        .iter()
        .filter(|t| t.verdict != HealthVerdict::Ok)
        .map(|t| {
            let name = match t.channel {
                Some(c) => format!("{}[{c}]", t.test),
                None => t.test.clone(),
            };
            let value = match (t.statistic, t.uncertainty) {
                (Some(s), Some(u)) => {
                    let d = decimals(u);
                    format!("{s:.d$} ± {u:.d$} {}", t.unit)
                }
                (Some(s), None) => format!("{s:.4} {}", t.unit),
                _ => "no statistic".to_owned(),
            };
            let since = t
                .since_ns
                .map(|s| format!(" since {}", time_of(s)))
                .unwrap_or_default();
            format!("{name} {value} ({}{since})", t.verdict.as_str())
        })
        .collect()
}

/// The table `triax-lab due` prints: one line per sensor, then its evidence indented.
pub fn render(reports: &[SensorHealthReport], problems: &[Problem]) -> String {
    let mut out = String::new();
    if reports.is_empty() {
        out.push_str("no sensor is due for recalibration or under watch\n");
    } else {
        out.push_str(&format!(
            "{:<16} {:<20} {:>8} {:<8} {:<7} {}\n",
            "BUILDING", "SENSOR", "VERSION", "VERDICT", "CHECKED", "FLAGGED FROM"
        ));
    }
    for r in reports {
        let flagged = r
            .flagged_from_ns
            .map(time_of)
            .unwrap_or_else(|| "-".to_owned());
        let checked = match r.calibration_checked {
            Some(true) => "yes",
            Some(false) => "no",
            None => "-",
        };
        out.push_str(&format!(
            "{:<16} {:<20} {:>8} {:<8} {:<7} {}\n",
            r.building.as_str(),
            r.sensor_id.as_str(),
            r.calibration_version,
            r.verdict.as_str(),
            checked,
            flagged
        ));
        for e in evidence(r) {
            out.push_str(&format!("    {e}\n"));
        }
    }
    for p in problems {
        out.push_str(&format!(
            "problem: {}{}\n",
            p.key
                .as_deref()
                .map(|k| format!("{k}: "))
                .unwrap_or_default(),
            p.problem
        ));
    }
    out
}

/// Sensors whose record is `suspect`: due.
pub fn due_count(reports: &[SensorHealthReport]) -> usize {
    reports
        .iter()
        .filter(|r| r.verdict == HealthVerdict::Suspect)
        .count()
}

#[cfg(test)]
mod tests {
    use super::*;
    use triax_protocol::messages::{HealthTest, StreamQuality};
    use triax_protocol::{SensorId, JSON_FORMAT_VERSION};

    fn report(sensor: &str, verdict: HealthVerdict) -> SensorHealthReport {
        SensorHealthReport {
            format_version: JSON_FORMAT_VERSION,
            building: BuildingId::new("hq").unwrap(),
            sensor_id: SensorId::new(sensor).unwrap(),
            calibration_version: 4,
            verdict,
            suspect_since_ns: None,
            flagged_from_ns: (verdict == HealthVerdict::Suspect)
                .then_some(1_800_000_000_000_000_000),
            reported_at: OffsetDateTime::UNIX_EPOCH,
            data_until_ns: None,
            blocks: 0,
            quiet_stretches: 0,
            discontinuities: 0,
            calibration_checked: Some(true),
            gravity_direction: None,
            tests: vec![HealthTest {
                test: "gravity_relative".into(),
                channel: None,
                peer: None,
                verdict,
                judged: true,
                statistic: Some(0.012_34),
                uncertainty: Some(0.001),
                unit: "m/s^2".into(),
                since_ns: Some(1_800_000_000_000_000_000),
                evidence_nats: 12.0,
                observations: 70,
                reason: None,
                masked: None,
                loud: None,
            }],
            quality: StreamQuality {
                samples: 0,
                availability: 1.0,
                gaps: 0,
                latency_min_ms: None,
                latency_max_ms: None,
            },
        }
    }

    #[test]
    fn the_table_names_the_sensor_its_verdict_and_the_evidence() {
        let reports = [
            report("acc-07", HealthVerdict::Suspect),
            report("acc-02", HealthVerdict::Watch),
        ];
        let text = render(
            &reports,
            &[Problem {
                key: None,
                problem: "health query: verdict: \"x\" is not ok, watch or suspect".into(),
            }],
        );
        let lines: Vec<&str> = text.lines().collect();
        assert!(lines[0].starts_with("BUILDING") && lines[0].contains("CHECKED"));
        assert!(
            lines[1].contains("acc-07") && lines[1].contains("suspect"),
            "{text}"
        );
        assert!(lines[1].contains("2027-01-15T08:00:00Z"), "{text}");
        assert_eq!(
            lines[2].trim(),
            "gravity_relative 0.0123 ± 0.0010 m/s^2 (suspect since 2027-01-15T08:00:00Z)"
        );
        assert!(lines[3].contains("acc-02") && lines[3].contains("watch"));
        assert!(lines[5].starts_with("problem: health query: verdict"));
        assert_eq!(due_count(&reports), 1);
        assert_eq!(
            render(&[], &[]),
            "no sensor is due for recalibration or under watch\n"
        );
    }

    /// A tiny uncertainty keeps its digits; an unchecked sensor says what could not be
    /// judged and why, and is listed only when asked for.
    #[test]
    fn small_uncertainties_and_unchecked_sensors() {
        let mut r = report("acc-09", HealthVerdict::Watch);
        r.tests[0].statistic = Some(0.000_123_4);
        r.tests[0].uncertainty = Some(0.000_015);
        assert_eq!(
            evidence(&r)[0],
            "gravity_relative 0.000123 ± 0.000015 m/s^2 (watch since 2027-01-15T08:00:00Z)"
        );
        let mut quiet = report("acc-10", HealthVerdict::Ok);
        quiet.calibration_checked = Some(false);
        quiet.tests[0].judged = false;
        quiet.tests[0].verdict = HealthVerdict::Ok;
        quiet.tests[0].reason = Some("no_quiet_stretch".into());
        quiet.tests[0].observations = 0;
        assert_eq!(
            evidence(&quiet),
            ["gravity_relative not judged: no_quiet_stretch (0 observations)"]
        );
        assert!(!listed(&quiet, HealthVerdict::Watch, false));
        assert!(listed(&quiet, HealthVerdict::Watch, true));
        assert!(render(&[quiet], &[])
            .lines()
            .nth(1)
            .unwrap()
            .contains(" no "));
    }
}
