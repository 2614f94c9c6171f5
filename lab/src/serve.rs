//! The registry server: answers catch-up queries on `triax/*/calibration/registry` with every
//! record of the asking building's sensors newer than what the gateway says it has, each signed
//! with the lab key as it is served (PROTOCOL.md §3.7).
//!
//! Signing at serve time keeps the registry a plain calibration store (records validated and
//! versioned by the same rules as a gateway's) and means every record served is signed by the
//! key the lab uses today. Ed25519 is deterministic, so a record served is byte for byte the
//! envelope that `push` sent; a gateway that already has it answers `already_stored`.
//!
//! Each query opens the registry for the time of one read (see `registry`), so `push` can write
//! to it while the server runs.

use std::future::Future;
use std::sync::Arc;

use triax_protocol::messages::RegistryRequest;
use triax_protocol::signing::{sign, LabSigningKey};
use triax_protocol::{from_json, keys, to_json, Key, JSON_FORMAT_VERSION};

use crate::registry::Registry;

/// Why the server could not start.
#[derive(Debug, thiserror::Error)]
#[error("registry server: {action}: {message}")]
pub struct ServeError {
    pub action: &'static str,
    pub message: String,
}

/// A registry server running on a session.
pub struct RegistryServer {
    task: tokio::task::JoinHandle<()>,
    stop: tokio::sync::watch::Sender<bool>,
}

impl RegistryServer {
    /// Declares the queryable and starts answering.
    pub async fn start(
        session: &zenoh::Session,
        registry: Registry,
        key: LabSigningKey,
    ) -> Result<RegistryServer, ServeError> {
        let queryable = session
            .declare_queryable(keys::all_registries())
            .await
            .map_err(|e| ServeError {
                action: "declare the registry queryable",
                message: e.to_string(),
            })?;
        let (stop, mut stopped) = tokio::sync::watch::channel(false);
        let ctx = Arc::new((registry, key));
        let task = tokio::spawn(async move {
            loop {
                let query = tokio::select! {
                    q = queryable.recv_async() => match q { Ok(q) => q, Err(_) => break },
                    _ = stopped.wait_for(|s| *s) => break,
                };
                // One task per query: a slow read must not hold up the next gateway.
                let ctx = ctx.clone();
                tokio::spawn(async move { answer(&ctx.0, &ctx.1, query).await });
            }
        });
        tracing::info!(key_expr = %keys::all_registries(), "registry serving");
        Ok(RegistryServer { task, stop })
    }

    /// Stops answering and undeclares the queryable.
    pub async fn stop(self) {
        self.stop.send_replace(true);
        if let Err(e) = self.task.await {
            tracing::error!(cause = %e, "registry server task ended abnormally");
        }
    }
}

/// Serves until `shutdown` completes.
pub async fn serve(
    session: &zenoh::Session,
    registry: Registry,
    key: LabSigningKey,
    shutdown: impl Future,
) -> Result<(), ServeError> {
    let server = RegistryServer::start(session, registry, key).await?;
    shutdown.await;
    server.stop().await;
    Ok(())
}

async fn answer(registry: &Registry, key: &LabSigningKey, query: zenoh::query::Query) {
    let building = match Key::parse(query.key_expr().as_str()) {
        Ok(Key::CalibrationRegistry(b)) => b,
        other => {
            let detail = match other {
                Err(e) => e.to_string(),
                Ok(k) => format!("{k} is not a registry key"),
            };
            tracing::warn!(key = %query.key_expr(), %detail, "registry query refused");
            let _ = query.reply_err(detail).await;
            return;
        }
    };
    let request = match query.payload() {
        None => RegistryRequest {
            format_version: JSON_FORMAT_VERSION,
            have: Default::default(),
        },
        Some(p) => match from_json::<RegistryRequest>(&p.to_bytes()) {
            Ok(r) => r,
            Err(e) => {
                tracing::warn!(building = %building, cause = %e, "registry request refused");
                let _ = query.reply_err(e.to_string()).await;
                return;
            }
        },
    };
    let reg = registry.clone();
    let b = building.clone();
    let found = tokio::task::spawn_blocking(move || reg.newer_for(&b, &request.have)).await;
    let records = match found {
        Ok(Ok(r)) => r,
        Ok(Err(e)) => {
            tracing::error!(building = %building, cause = %e, "registry read failed");
            let _ = query.reply_err(format!("registry read failed: {e}")).await;
            return;
        }
        Err(e) => {
            tracing::error!(building = %building, cause = %e, "registry task failed");
            let _ = query.reply_err("registry read failed").await;
            return;
        }
    };
    let reply_key = Key::CalibrationRegistry(building.clone()).to_string();
    for record in &records {
        let body = to_json(&sign(record, key));
        if let Err(e) = query.reply(&reply_key, body).await {
            tracing::warn!(building = %building, cause = %e, "registry reply failed");
            return;
        }
    }
    if records.is_empty() {
        tracing::debug!(building = %building, "registry request answered: nothing newer");
    } else {
        tracing::info!(building = %building, served = records.len(), "registry request answered");
    }
}
