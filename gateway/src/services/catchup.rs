//! Catch-up from the lab's registry: what was pushed while the gateway was offline reaches it
//! when it comes back, with no operator action.
//!
//! The gateway queries `triax/<building>/calibration/registry` with a [`RegistryRequest`]
//! listing the version in force for each sensor it has a calibration for. The registry replies
//! once per signed record the gateway lacks; each goes through [`Updater::apply`] exactly like a
//! push (trusted key, signature, valid record, newer version, durable before in force).
//!
//! When: at start, until the registry has answered once, and then every
//! `calibration.catchup_interval_s`. At start the registry may not be reachable yet (nodes, lab
//! and gateway started together as peers, or the site link still coming up), and an empty
//! answer cannot be told from no registry at all; so the gateway watches whether a registry's
//! queryable matches the key (Zenoh's matching status) and asks as soon as one does, retrying a
//! failed round after [`START_BACKOFF_MIN`], doubling up to [`START_BACKOFF_MAX`]. It logs once
//! that the registry is not reachable, and again when it answers.
//!
//! The replies share one key, so the query asks for no consolidation (Zenoh would otherwise keep
//! only the latest reply per key).

use std::sync::Arc;
use std::time::Duration;

use tokio::task::JoinHandle;
use triax_protocol::messages::{PushOutcome, RegistryRequest, SignedRecord};
use triax_protocol::{from_json, to_json, Key, SensorId, JSON_FORMAT_VERSION};
use zenoh::query::ConsolidationMode;

use super::push::{Source, Updater};
use super::{Context, Task};
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

/// First wait before asking a registry that did not answer at start again...
pub const START_BACKOFF_MIN: Duration = Duration::from_millis(200);
/// ... doubling up to this.
pub const START_BACKOFF_MAX: Duration = Duration::from_secs(10);

/// Asks until one round succeeds with a registry there to answer it: as soon as a registry's
/// queryable matches, and again after a growing backoff while none does or a round fails.
/// Returns the report of the round that succeeded; none if `shutdown` came first.
async fn first_round(
    session: &zenoh::Session,
    updater: &Updater,
    timeout: Duration,
    shutdown: &mut Shutdown,
) -> Option<CatchUpReport> {
    let key = Key::CalibrationRegistry(updater.building().clone()).to_string();
    let querier = match session.declare_querier(&key).await {
        Ok(q) => Some(q),
        Err(e) => {
            tracing::warn!(cause = %e, "cannot watch for the lab's registry; asking blind");
            None
        }
    };
    let listener = match &querier {
        Some(q) => q.matching_listener().await.ok(),
        None => None,
    };
    let mut backoff = START_BACKOFF_MIN;
    let mut said_unreachable = false;
    loop {
        if registry_matches(&querier).await {
            match catch_up(session, updater, timeout).await {
                Ok(r) => {
                    if said_unreachable {
                        tracing::info!(registry = %key, "the lab's registry answered");
                    }
                    return Some(r);
                }
                Err(e) => tracing::warn!(cause = %e, retry_in = ?backoff, "catch-up failed"),
            }
        } else if !said_unreachable {
            tracing::warn!(registry = %key,
                "the lab's registry is not reachable yet: catching up as soon as it is");
            said_unreachable = true;
        }
        let arrived = async {
            match &listener {
                Some(l) => {
                    let _ = l.recv_async().await;
                }
                None => std::future::pending().await,
            }
        };
        tokio::select! {
            _ = tokio::time::sleep(backoff) => {}
            _ = arrived => {}
            _ = shutdown.recv() => return None,
        }
        backoff = (backoff * 2).min(START_BACKOFF_MAX);
    }
}

/// Logs what a round did; true when the registry holds more than one round takes.
fn log_round(updater: &Updater, round: &Result<CatchUpReport, CatchUpError>) -> bool {
    match round {
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
    }
}

/// Catches up at start (until the registry has answered once) and then every `interval` (only
/// at start when `None`), until `shutdown`.
pub(crate) fn spawn(
    session: zenoh::Session,
    updater: Arc<Updater>,
    interval: Option<Duration>,
    timeout: Duration,
    mut shutdown: Shutdown,
) -> JoinHandle<()> {
    tokio::spawn(async move {
        let Some(first) = first_round(&session, &updater, timeout, &mut shutdown).await else {
            return;
        };
        let mut more = log_round(&updater, &Ok(first));
        loop {
            if !more {
                let Some(interval) = interval else { return };
                tokio::select! {
                    _ = tokio::time::sleep(interval) => {}
                    _ = shutdown.recv() => return,
                }
            }
            let round = tokio::select! {
                r = catch_up(&session, &updater, timeout) => r,
                _ = shutdown.recv() => return,
            };
            more = log_round(&updater, &round);
        }
    })
}

/// Whether a registry's queryable matches `key`: that the registry is reachable.
async fn registry_matches(querier: &Option<zenoh::query::Querier<'_>>) -> bool {
    match querier {
        Some(q) => q.matching_status().await.map_or(true, |m| m.matching()),
        None => true,
    }
}

/// Starts the periodic catch-up with the lab's registry (`[calibration] catchup_interval_s`).
pub fn start(ctx: &Context, updater: &Arc<Updater>) -> Task {
    let c = &ctx.config.calibration;
    spawn(
        ctx.session.clone(),
        updater.clone(),
        c.catchup_interval,
        c.catchup_timeout,
        ctx.shutdown.clone(),
    )
}
