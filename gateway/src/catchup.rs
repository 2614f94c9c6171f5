//! Catch-up from the lab's registry: what was pushed while the gateway was offline reaches it
//! when it comes back, with no operator action.
//!
//! At start and then every `calibration.catchup_interval_s`, the gateway queries
//! `triax/<building>/calibration/registry` with a [`RegistryRequest`] listing the version in
//! force for each sensor it has a calibration for. The registry replies once per signed record
//! the gateway lacks; each goes through [`Updater::apply`] exactly like a push (trusted key,
//! signature, valid record, newer version, durable before in force). A registry that does not
//! answer costs nothing but a log line: the next round asks again.
//!
//! The replies share one key, so the query asks for no consolidation (Zenoh would otherwise keep
//! only the latest reply per key).

use std::sync::Arc;
use std::time::Duration;

use tokio::task::JoinHandle;
use triax_protocol::messages::{PushOutcome, RegistryRequest, SignedRecord};
use triax_protocol::{from_json, to_json, Key, SensorId, JSON_FORMAT_VERSION};
use zenoh::query::ConsolidationMode;

use crate::push::{Source, Updater};
use crate::shutdown::Shutdown;

/// Most signed records one catch-up round holds (about 5 KiB each with full covariances).
pub const MAX_RECORDS_PER_ROUND: usize = 16_384;

/// What one catch-up round did.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct CatchUpReport {
    /// Signed records the registry served.
    pub served: usize,
    /// Records accepted and now in force (new to this gateway).
    pub applied: usize,
    /// Records accepted that the gateway already had.
    pub already_stored: usize,
    /// Records refused (each is logged with its reason).
    pub refused: usize,
    /// Replies that were not signed records, or Zenoh error replies.
    pub malformed: usize,
    /// Replies beyond [`MAX_RECORDS_PER_ROUND`], left for the next round.
    pub deferred: usize,
}

/// Why a catch-up round could not ask.
#[derive(Debug, thiserror::Error)]
#[error("catch-up query to {key}: {message}")]
pub struct CatchUpError {
    pub key: String,
    pub message: String,
}

/// One round: asks the registry, then applies what it served in sensor and version order.
pub async fn catch_up(
    session: &zenoh::Session,
    updater: &Updater,
    timeout: Duration,
) -> Result<CatchUpReport, CatchUpError> {
    let key = Key::CalibrationRegistry(updater.building().clone()).to_string();
    let request = RegistryRequest {
        format_version: JSON_FORMAT_VERSION,
        have: updater.table().versions().into_iter().collect(),
    };
    let replies = session
        .get(&key)
        .payload(to_json(&request))
        .consolidation(ConsolidationMode::None)
        .timeout(timeout)
        .await
        .map_err(|e| CatchUpError {
            key: key.clone(),
            message: e.to_string(),
        })?;
    let mut report = CatchUpReport::default();
    // Sorted, so that several versions of one sensor are stored in increasing order whatever
    // order the network delivered them in.
    // A list rather than a map: a forged reply must not displace a genuine one with the same
    // claimed sensor and version.
    let mut served: Vec<((SensorId, u64), SignedRecord)> = Vec::new();
    while let Ok(reply) = replies.recv_async().await {
        if served.len() >= MAX_RECORDS_PER_ROUND {
            // Memory stays bounded whoever answers; what is left over comes in the next round,
            // which asks from the versions applied in this one.
            report.deferred += 1;
            continue;
        }
        let signed = match reply.result() {
            Ok(sample) => from_json::<SignedRecord>(&sample.payload().to_bytes()),
            Err(e) => {
                report.malformed += 1;
                tracing::warn!(registry = %key, error = %String::from_utf8_lossy(&e.payload().to_bytes()),
                    "registry answered with an error");
                continue;
            }
        };
        match signed {
            // Ordered by the sensor and version the record claims; nothing is trusted before
            // `apply` verifies it, and a record that lies about them is refused there.
            Ok(signed) => match signed.record() {
                Ok(r) => {
                    served.push(((r.sensor_id, r.version), signed));
                }
                Err(e) => {
                    report.malformed += 1;
                    tracing::warn!(registry = %key, cause = %e, "registry served an unreadable record");
                }
            },
            Err(e) => {
                report.malformed += 1;
                tracing::warn!(registry = %key, cause = %e, "registry reply is not a signed record");
            }
        }
    }
    served.sort_by(|a, b| a.0.cmp(&b.0));
    for ((sensor, _), signed) in &served {
        report.served += 1;
        match updater.apply(Source::CatchUp, Some(sensor), signed).await {
            PushOutcome::Accepted {
                already_stored: false,
                ..
            } => report.applied += 1,
            PushOutcome::Accepted {
                already_stored: true,
                ..
            } => report.already_stored += 1,
            PushOutcome::Refused { .. } => report.refused += 1,
        }
    }
    Ok(report)
}

/// Catches up at start and then every `interval` (only at start when `None`), until
/// `shutdown`.
pub(crate) fn spawn(
    session: zenoh::Session,
    updater: Arc<Updater>,
    interval: Option<Duration>,
    timeout: Duration,
    mut shutdown: Shutdown,
) -> JoinHandle<()> {
    tokio::spawn(async move {
        loop {
            let round = tokio::select! {
                r = catch_up(&session, &updater, timeout) => r,
                _ = shutdown.recv() => return,
            };
            let more = match round {
                Ok(r) if r.applied + r.refused + r.malformed + r.deferred > 0 => {
                    tracing::info!(
                        building = %updater.building(),
                        served = r.served,
                        applied = r.applied,
                        refused = r.refused,
                        malformed = r.malformed,
                        deferred = r.deferred,
                        "caught up with the lab's registry"
                    );
                    r.deferred > 0
                }
                Ok(r) => {
                    tracing::debug!(served = r.served, "registry has nothing newer");
                    false
                }
                Err(e) => {
                    tracing::warn!(cause = %e, "catch-up failed; will ask again");
                    false
                }
            };
            if more {
                // The registry has more than one round holds: ask again at once.
                continue;
            }
            let Some(interval) = interval else { return };
            tokio::select! {
                _ = tokio::time::sleep(interval) => {}
                _ = shutdown.recv() => return,
            }
        }
    })
}
