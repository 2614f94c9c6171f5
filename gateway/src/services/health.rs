//! The health queryable: the latest report of each sensor, as its worker published it
//! (`triax/<b>/health/<s>`, PROTOCOL.md), for whoever asks.

use std::sync::Arc;

use triax_protocol::keys::{all_sensors, Stream};
use triax_protocol::messages::HealthVerdict;
use triax_protocol::provenance::check_nonce;
use triax_protocol::{BuildingId, Key};

use super::{Context, Task};
use crate::error::{zenoh_err, GatewayError};
use crate::shutdown::Shutdown;
use crate::state::{SensorTable, Signer};

/// Why a health query was refused.
fn parse_query<'a>(
    parameters: impl Iterator<Item = (&'a str, &'a str)>,
) -> Result<(HealthVerdict, String), String> {
    let mut least = HealthVerdict::Ok;
    let mut nonce = String::new();
    for (k, v) in parameters {
        match k {
            "nonce" => {
                check_nonce(v).map_err(|e| format!("health query: {e}"))?;
                nonce = v.to_owned();
            }
            "verdict" => {
                least = match v {
                    "ok" => HealthVerdict::Ok,
                    "watch" => HealthVerdict::Watch,
                    "suspect" => HealthVerdict::Suspect,
                    other => {
                        return Err(format!(
                            "health query: verdict: {other:?} is not ok, watch or suspect"
                        ))
                    }
                }
            }
            other => {
                return Err(format!(
                    "health query: unknown parameter {other:?} (known: verdict, nonce)"
                ))
            }
        }
    }
    Ok((least, nonce))
}

/// Answers health queries on `triax/<b>/health/*` with the latest report of every sensor whose
/// key the query's key expression matches and whose verdict is at least the query's `verdict`,
/// until shutdown.
pub async fn serve(
    session: &zenoh::Session,
    building: BuildingId,
    table: Arc<SensorTable>,
    signer: Arc<Signer>,
    mut shutdown: Shutdown,
) -> zenoh::Result<tokio::task::JoinHandle<()>> {
    let queryable = session
        .declare_queryable(all_sensors(&building, Stream::Health))
        .await?;
    Ok(tokio::spawn(async move {
        loop {
            let query = tokio::select! {
                q = queryable.recv_async() => match q { Ok(q) => q, Err(_) => break },
                _ = shutdown.recv() => break,
            };
            let (least, nonce) = match parse_query(query.parameters().iter()) {
                Ok(l) => l,
                Err(problem) => {
                    if let Err(e) = query.reply_err(problem).await {
                        tracing::warn!(cause = %e, "health error reply failed");
                    }
                    continue;
                }
            };
            for entry in table.snapshot() {
                let (Some(json), Some(verdict)) = (entry.health_report(), entry.health_verdict())
                else {
                    continue;
                };
                if verdict < least {
                    continue;
                }
                let key = Key::Health(building.clone(), entry.id.clone()).to_string();
                let Ok(k) = zenoh::key_expr::KeyExpr::try_from(key.as_str()) else {
                    continue;
                };
                if !query.key_expr().intersects(&k) {
                    continue;
                }
                let reply = query
                    .reply(k, json.to_vec())
                    .attachment(signer.attachment(&key, &nonce, &json));
                if let Err(e) = reply.await {
                    tracing::warn!(cause = %e, "health reply failed");
                    break;
                }
            }
        }
    }))
}

/// Starts the health queryable when the checks are on.
pub async fn start(ctx: &Context) -> Result<Option<Task>, GatewayError> {
    if ctx.config.health.is_none() {
        return Ok(None);
    }
    let serving = serve(
        &ctx.session,
        ctx.config.building.clone(),
        ctx.table.clone(),
        ctx.signer.clone(),
        ctx.shutdown.clone(),
    );
    Ok(Some(
        serving
            .await
            .map_err(zenoh_err("declare the health queryable"))?,
    ))
}
