//! Pushing signed records to buildings and collecting the gateways' acknowledgements.
//!
//! One push is a Zenoh query on `triax/<building>/calibration/push/<sensor>` whose payload is
//! the [`SignedRecord`]. It targets every matching queryable (a building may run more than one
//! gateway) with no consolidation (the acknowledgements share one key), and waits until every
//! gateway has answered or the timeout has passed. Pushes to several buildings and of several
//! records go out concurrently.
//!
//! A gateway that is offline does not answer: the push reports it, and the gateway gets the
//! record from the registry when it comes back (see `registry`, `serve`).

use std::fmt::Write;
use std::time::{Duration, Instant};

use tokio::task::JoinSet;
use triax_protocol::messages::{PushAck, PushOutcome, SignedRecord};
use triax_protocol::record::CalibrationRecord;
use triax_protocol::signing::{sign, LabSigningKey};
use triax_protocol::{from_json, to_json, BuildingId, JsonError, Key, SensorId};
use zenoh::query::{ConsolidationMode, QueryTarget};

/// A signed record ready to push.
#[derive(Debug, Clone)]
pub struct Push {
    pub sensor: SensorId,
    pub version: u64,
    pub signed: SignedRecord,
}

impl Push {
    /// Signs `record` with the lab key.
    pub fn sign(record: &CalibrationRecord, key: &LabSigningKey) -> Push {
        Push {
            sensor: record.sensor_id.clone(),
            version: record.version,
            signed: sign(record, key),
        }
    }

    /// An envelope signed earlier (sensor and version are read from it, unverified).
    pub fn from_signed(signed: SignedRecord) -> Result<Push, JsonError> {
        let r = signed.record()?;
        Ok(Push {
            sensor: r.sensor_id,
            version: r.version,
            signed,
        })
    }
}

/// Why a push could not be sent at all.
#[derive(Debug, thiserror::Error)]
#[error("push to {key}: {message}")]
pub struct PushError {
    pub key: String,
    pub message: String,
}

/// What came back from one building for one record.
#[derive(Debug, Clone)]
pub struct PushReport {
    pub building: BuildingId,
    pub sensor: SensorId,
    pub version: u64,
    /// One per gateway that answered.
    pub acks: Vec<PushAck>,
    /// Error replies and replies that were not acknowledgements.
    pub errors: Vec<String>,
    /// From sending the query to the last acknowledgement.
    pub elapsed_to_last_ack: Duration,
}

impl PushReport {
    /// At least `min_acks` gateways answered, all of them accepted, and nothing else came back.
    pub fn is_success(&self, min_acks: usize) -> bool {
        self.acks.len() >= min_acks.max(1)
            && self.errors.is_empty()
            && self
                .acks
                .iter()
                .all(|a| matches!(a.outcome, PushOutcome::Accepted { .. }))
    }
}

/// Pushes one record to one building and waits for every gateway's answer (or `timeout`).
pub async fn push_one(
    session: &zenoh::Session,
    building: &BuildingId,
    push: &Push,
    timeout: Duration,
) -> Result<PushReport, PushError> {
    let key = Key::CalibrationPush(building.clone(), push.sensor.clone()).to_string();
    let start = Instant::now();
    let replies = session
        .get(&key)
        .payload(to_json(&push.signed))
        .target(QueryTarget::All)
        .consolidation(ConsolidationMode::None)
        .timeout(timeout)
        .await
        .map_err(|e| PushError {
            key: key.clone(),
            message: e.to_string(),
        })?;
    let mut report = PushReport {
        building: building.clone(),
        sensor: push.sensor.clone(),
        version: push.version,
        acks: Vec::new(),
        errors: Vec::new(),
        elapsed_to_last_ack: Duration::ZERO,
    };
    while let Ok(reply) = replies.recv_async().await {
        match reply.result() {
            Ok(sample) => match from_json::<PushAck>(&sample.payload().to_bytes()) {
                Ok(ack) => {
                    report.elapsed_to_last_ack = start.elapsed();
                    report.acks.push(ack);
                }
                Err(e) => report
                    .errors
                    .push(format!("unreadable acknowledgement: {e}")),
            },
            Err(e) => report.errors.push(format!(
                "error reply: {}",
                String::from_utf8_lossy(&e.payload().to_bytes())
            )),
        }
    }
    tracing::debug!(key = %key, acks = report.acks.len(), elapsed_ms = report.elapsed_to_last_ack.as_secs_f64() * 1e3, "push answered");
    Ok(report)
}

/// Pushes every record to every building, concurrently; reports in building then input order.
pub async fn push_all(
    session: &zenoh::Session,
    buildings: &[BuildingId],
    pushes: &[Push],
    timeout: Duration,
) -> Result<Vec<PushReport>, PushError> {
    let mut set = JoinSet::new();
    for (bi, building) in buildings.iter().enumerate() {
        for (pi, push) in pushes.iter().enumerate() {
            let (session, building, push) = (session.clone(), building.clone(), push.clone());
            set.spawn(async move {
                let r = push_one(&session, &building, &push, timeout).await;
                ((bi, pi), r)
            });
        }
    }
    let mut out = Vec::with_capacity(set.len());
    while let Some(joined) = set.join_next().await {
        let (at, r) = joined.map_err(|e| PushError {
            key: "(task)".into(),
            message: e.to_string(),
        })?;
        out.push((at, r?));
    }
    out.sort_by_key(|(at, _)| *at);
    Ok(out.into_iter().map(|(_, r)| r).collect())
}

/// One line per gateway answer (or missing answer), and whether everything succeeded.
pub fn render(reports: &[PushReport], min_acks: usize, timeout: Duration) -> (String, bool) {
    let mut text = String::new();
    let mut ok = true;
    for r in reports {
        // Ids as &str: their Display ignores width.
        let head = format!(
            "{:<16} {:<20} v{:<6}",
            r.building.as_str(),
            r.sensor.as_str(),
            r.version
        );
        for a in &r.acks {
            let verdict = match &a.outcome {
                PushOutcome::Accepted {
                    already_stored: false,
                    ..
                } => "accepted".to_owned(),
                PushOutcome::Accepted {
                    already_stored: true,
                    ..
                } => "accepted (already stored)".to_owned(),
                PushOutcome::Refused { reason, detail } => {
                    // The reason's wire name, as in PROTOCOL.md §3.3.
                    let name = serde_json::to_value(reason)
                        .ok()
                        .and_then(|v| v.as_str().map(str::to_owned))
                        .unwrap_or_else(|| format!("{reason:?}"));
                    format!("REFUSED {name}: {detail}")
                }
            };
            // Infallible: writing to a String.
            let _ = writeln!(text, "{head} {:<24} {verdict}", a.gateway);
        }
        for e in &r.errors {
            let _ = writeln!(text, "{head} {:<24} ERROR {e}", "?");
        }
        if r.acks.len() < min_acks.max(1) {
            let _ = writeln!(
                text,
                "{head} {:<24} NOT ACKNOWLEDGED: {} of {} gateway(s) answered within {:.1} s; the \
                 registry has the record and an offline gateway catches up when it returns",
                "?",
                r.acks.len(),
                min_acks.max(1),
                timeout.as_secs_f64()
            );
        }
        ok &= r.is_success(min_acks);
    }
    (text, ok)
}
