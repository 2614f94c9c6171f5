//! The thin Zenoh layer around [`Monitor`]: subscribe, decode, feed, publish, log.
//!
//! Zenoh delivers samples to callbacks on its own threads; each callback only copies the key and
//! payload into a bounded channel (`try_send`, counted when full), so a slow consumer never
//! blocks Zenoh's receive path and memory stays bounded. One task owns the [`Monitor`] and does
//! everything else, so the window state needs no lock.

use std::future::Future;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::Duration;

use time::OffsetDateTime;
use tokio::sync::mpsc;
use triax_protocol::keys::{all_buildings, all_sensors, Stream};
use triax_protocol::messages::{Alert, TiltSample};
use triax_protocol::{from_json, to_json, CorrectedBatch, Key};

use crate::config::Config;
use crate::monitor::Monitor;

/// Messages waiting for the monitor before new ones are dropped (and counted).
pub const INBOX_CAPACITY: usize = 4096;

/// Why the service could not run.
#[derive(Debug, thiserror::Error)]
pub enum ServiceError {
    #[error(transparent)]
    ZenohConfig(#[from] triax_net::ZenohConfigError),
    #[error("zenoh: {what}: {message}")]
    Zenoh { what: &'static str, message: String },
}

fn zenoh_error(what: &'static str) -> impl FnOnce(zenoh::Error) -> ServiceError {
    move |e| ServiceError::Zenoh {
        what,
        message: e.to_string(),
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Source {
    Corrected,
    Tilt,
}

struct Inbound {
    source: Source,
    key: String,
    payload: Vec<u8>,
}

/// Key expressions to subscribe to: per watched building, or every building.
fn subscriptions(config: &Config) -> Vec<(Source, String)> {
    let mut out = Vec::new();
    for (source, stream) in [
        (Source::Corrected, Stream::Corrected),
        (Source::Tilt, Stream::Tilt),
    ] {
        if config.watch_all_buildings {
            out.push((source, all_buildings(stream)));
        } else {
            out.extend(
                config
                    .buildings
                    .keys()
                    .map(|b| (source, all_sensors(b, stream))),
            );
        }
    }
    out
}

/// How often staleness is checked: often enough to report within a quarter of the allowance.
fn stale_check_period(config: &Config) -> Duration {
    Duration::from_secs_f64((config.settings.stale_after_s / 4.0).clamp(0.05, 5.0))
}

/// Runs the alerting service until `shutdown` completes.
///
/// Opens a Zenoh session from `config.zenoh`, subscribes to the corrected and tilt streams of
/// the watched buildings, publishes every alert on `triax/<building>/alert/<sensor>` and logs it.
pub async fn run(config: Config, shutdown: impl Future<Output = ()>) -> Result<(), ServiceError> {
    let session = zenoh::open(config.zenoh.to_config()?)
        .await
        .map_err(zenoh_error("open session"))?;
    let (tx, mut rx) = mpsc::channel::<Inbound>(INBOX_CAPACITY);
    let dropped = Arc::new(AtomicU64::new(0));
    let mut subscribers = Vec::new();
    for (source, expr) in subscriptions(&config) {
        let tx = tx.clone();
        let dropped = dropped.clone();
        let sub = session
            .declare_subscriber(expr.clone())
            .callback(move |sample| {
                let msg = Inbound {
                    source,
                    key: sample.key_expr().as_str().to_owned(),
                    payload: sample.payload().to_bytes().into_owned(),
                };
                if tx.try_send(msg).is_err() {
                    dropped.fetch_add(1, Ordering::Relaxed);
                }
            })
            .await
            .map_err(zenoh_error("declare subscriber"))?;
        tracing::info!(key_expr = %expr, "subscribed");
        subscribers.push(sub);
    }
    drop(tx);

    let mut monitor = Monitor::new(config.clone(), OffsetDateTime::now_utc());
    let mut tick = tokio::time::interval(stale_check_period(&config));
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    let mut reported_dropped = 0;
    tokio::pin!(shutdown);
    loop {
        let alerts = tokio::select! {
            _ = &mut shutdown => break,
            msg = rx.recv() => match msg {
                Some(msg) => handle(&mut monitor, msg),
                // Every sender lives in a subscriber callback; they go only with the session.
                None => break,
            },
            _ = tick.tick() => {
                let now_dropped = dropped.load(Ordering::Relaxed);
                if now_dropped > reported_dropped {
                    tracing::warn!(dropped = now_dropped, "inbox full: messages dropped");
                    reported_dropped = now_dropped;
                }
                monitor.check_stale(OffsetDateTime::now_utc())
            }
        };
        for alert in alerts {
            publish(&session, &alert).await;
        }
    }
    drop(subscribers);
    session
        .close()
        .await
        .map_err(zenoh_error("close session"))?;
    tracing::info!("stopped");
    Ok(())
}

fn handle(monitor: &mut Monitor, msg: Inbound) -> Vec<Alert> {
    let now = OffsetDateTime::now_utc();
    let key = match Key::parse(&msg.key) {
        Ok(k) => k,
        Err(e) => {
            tracing::warn!(key = %msg.key, cause = %e, "not a Triax key");
            return Vec::new();
        }
    };
    match (msg.source, key) {
        (Source::Corrected, Key::Corrected(building, sensor)) => {
            match CorrectedBatch::decode(&msg.payload) {
                Ok(batch) if batch.header.sensor_id == sensor => {
                    monitor.on_corrected(&building, &batch, now)
                }
                Ok(batch) => {
                    tracing::warn!(key = %msg.key, batch_sensor = %batch.header.sensor_id,
                        "corrected batch names another sensor than its key: ignored");
                    Vec::new()
                }
                Err(e) => {
                    tracing::warn!(key = %msg.key, cause = %e, "malformed corrected batch");
                    Vec::new()
                }
            }
        }
        (Source::Tilt, Key::Tilt(building, sensor)) => {
            match from_json::<TiltSample>(&msg.payload) {
                Ok(tilt) if tilt.sensor_id == sensor => monitor.on_tilt(&building, &tilt, now),
                Ok(tilt) => {
                    tracing::warn!(key = %msg.key, sample_sensor = %tilt.sensor_id,
                        "tilt sample names another sensor than its key: ignored");
                    Vec::new()
                }
                Err(e) => {
                    tracing::warn!(key = %msg.key, cause = %e, "malformed tilt sample");
                    Vec::new()
                }
            }
        }
        (_, other) => {
            tracing::warn!(key = %other, "unexpected key on a subscription");
            Vec::new()
        }
    }
}

async fn publish(session: &zenoh::Session, alert: &Alert) {
    let key = Key::Alert(alert.building.clone(), alert.sensor_id.clone()).to_string();
    tracing::warn!(
        building = %alert.building,
        sensor = %alert.sensor_id,
        kind = ?alert.kind,
        level = ?alert.level,
        value = alert.value,
        standard_uncertainty = alert.standard_uncertainty,
        threshold = alert.threshold,
        unit = %alert.unit,
        statement = %alert.statement,
        "alert"
    );
    if let Err(e) = session.put(&key, to_json(alert)).await {
        tracing::error!(key = %key, cause = %e, "alert not published");
    }
}
