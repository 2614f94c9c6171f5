//! The Triax building gateway: subscribes to every raw sensor stream of one building over Zenoh,
//! corrects each sample with the sensor's calibration, tags it with its uncertainty, quality
//! flags and the calibration version, and publishes it.
//!
//! The entry point is [`run`] (or [`Gateway::start`] then [`Gateway::run_until`]): it takes a
//! validated [`Config`] and a shutdown future, so a test can start a gateway on a loopback port
//! and stop it at will. The `triax-gateway` binary only parses arguments, installs logging and
//! hands over.
//!
//! The crate is built in layers, read bottom up; each imports only from the layers below it,
//! and no module imports another in a circle (the test `layers` at the end of this file holds
//! both):
//!
//! 1. settings and foundations: [`config`] (plain data: TOML, flags, environment, refused with
//!    field and reason; it imports nothing of the crate), [`error`], [`shutdown`], [`clock`];
//! 2. [`state`]: the sensor table (each sensor's corrector snapshot, swapped atomically between
//!    batches, [`SensorTable::install`]), the counters, the store as the gateway holds it;
//! 3. [`sample_path`]: intake → shards → kernel → outbox and the history's queue, the hot path
//!    in one place, used from above through its face only;
//! 4. [`services`]: backfill, health queryable, replay, push, catch-up, status, metrics,
//!    heartbeat, expiry, memory, each started by a function of its own;
//! 5. this file: [`Gateway::start`] composes them, [`Gateway::run_until`] stops them.
//!
//! ```text
//! triax/<b>/raw/* ─► sample_path: intake ─► shards (sequence, kernel, tilt, health feed)
//!   ─► outbox ─► triax/<b>/corrected/<s>, triax/<b>/tilt/<s>;  └► history's queue
//! triax/<b>/status ◄─ status            http://<metrics>/metrics ◄─ metrics (Prometheus)
//! triax/<b>/calibration/push/* ◄─ push: verify, store, swap, ack ─► calibration/ack/<s>
//! triax/<b>/calibration/registry ─► catchup, at start and periodically
//! triax/<b>/history/* ◄─ replay        triax/<b>/buffer/<s> ◄─ backfill ─► late batches
//! ```
//!
//! Architecture invariant: the sample path never touches the store but to mark a record
//! suspect. Calibrations are read from the store at start (and, later, on an accepted update)
//! and live in [`SensorTable`]; the store is used from blocking tasks only.

pub mod clock;
pub mod config;
pub mod error;
pub mod sample_path;
pub mod services;
pub mod shutdown;
pub mod state;
mod sync;

#[cfg(test)]
mod layers;

use std::future::Future;
use std::net::SocketAddr;
use std::sync::atomic::Ordering::Relaxed;
use std::sync::Arc;

use time::OffsetDateTime;
use triax_calibration_store::Store;

pub use config::{
    BackfillSettings, CalibrationSettings, Config, ConfigArgs, ConfigError, CorrectionMode,
    HealthSettings, Overload, SensorSettings,
};
pub use error::GatewayError;
pub use services::catchup::{CatchUpError, CatchUpReport};
pub use services::memory;
pub use state::{GatewayCounters, SensorTable};

use error::zenoh_err;
use sample_path::{Parts, SamplePath};
use services::{backfill, catchup, expiry, health, heartbeat, metrics, push, replay, status, Task};
use shutdown::ShutdownTrigger;

/// A running gateway.
pub struct Gateway {
    config: Arc<Config>,
    session: zenoh::Session,
    store: Arc<Store>,
    table: Arc<SensorTable>,
    counters: Arc<GatewayCounters>,
    updater: Arc<push::Updater>,
    trigger: ShutdownTrigger,
    path: SamplePath,
    tasks: Vec<Task>,
    metrics_addr: Option<SocketAddr>,
    started_at: OffsetDateTime,
    /// The lock on the store (`state::store`), released last.
    _claim: std::fs::File,
}

/// Installs the binaries' logging: one line per event on stderr, filtered by `filter`
/// (tracing env-filter syntax). If a subscriber is already installed, it stays.
pub fn init_logging(filter: &str) -> Result<(), tracing_subscriber::filter::ParseError> {
    let filter = tracing_subscriber::EnvFilter::try_new(filter)?;
    // Err only when a subscriber is already installed, which is then kept.
    let _ = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr)
        .try_init();
    Ok(())
}

/// Runs a gateway until `shutdown` completes, then stops it cleanly.
pub async fn run(config: Config, shutdown: impl Future) -> Result<(), GatewayError> {
    Gateway::start(config).await?.run_until(shutdown).await
}

impl Gateway {
    /// Opens the store and the history, loads the calibrations, joins Zenoh, and starts
    /// serving: the sample path, then each service, then the workers.
    pub async fn start(config: Config) -> Result<Gateway, GatewayError> {
        let config = Arc::new(config);
        let started_at = OffsetDateTime::now_utc();
        let table = Arc::new(SensorTable::new(config.clone()));
        let opened = state::store::open(&config, &table).await?;
        services::memory::release_loading_heap().await?;
        let recorder = sample_path::open_history(&config).await?;
        let signer = Arc::new(state::Signer::load(&config.provenance)?);
        let session = zenoh::open(config.zenoh.to_publisher_config()?)
            .await
            .map_err(zenoh_err("open session"))?;
        let counters = Arc::new(GatewayCounters::at_start(
            opened.loaded,
            config.declared_keys_max,
        ));
        let (trigger, shutdown) = shutdown::channel();
        let ctx = services::Context {
            config: config.clone(),
            session: session.clone(),
            table: table.clone(),
            counters: counters.clone(),
            store: opened.store.clone(),
            signer: signer.clone(),
            started_at,
            shutdown,
        };
        let backfill = config.backfill.clone().map(|s| (s, backfill::channel()));
        let holes = backfill.as_ref().map(|(_, (holes, _))| holes.clone());
        let backfill_counters = holes.as_ref().map(|h| h.counters().clone());
        let parts = Parts {
            signer: signer.clone(),
            table: table.clone(),
            counters: counters.clone(),
            store: opened.store.clone(),
            recorder,
            holes,
        };
        let mut path = SamplePath::start(&config, &session, parts).await?;

        let mut tasks = Vec::new();
        if let Some((settings, (holes, requests))) = backfill {
            let counters = holes.counters().clone();
            tasks.push(backfill::start(&ctx, &path, settings, counters, requests));
        }
        // Pushes are taken before status is answered: a gateway that answers status takes
        // pushes too (its declarations reach the router in order).
        let (updater, pushes) = push::start(&ctx).await?;
        tasks.push(pushes);
        tasks.push(status::start(&ctx, path.history(), backfill_counters.clone()).await?);
        tasks.extend(health::start(&ctx).await?);
        if let Some(sink) = path.history() {
            tasks.push(replay::start(&ctx, sink).await?);
        }
        tasks.push(heartbeat::start(&ctx));
        tasks.push(catchup::start(&ctx, &updater));
        tasks.push(expiry::start(&ctx));
        tasks.push(services::memory::start(&ctx));
        let metrics = metrics::start(&ctx, &path, backfill_counters).await?;
        let metrics_addr = metrics.map(|(addr, task)| {
            tasks.push(task);
            addr
        });
        // Last, so that a start that fails leaves no thread behind. Batches taken meanwhile
        // wait in the inboxes.
        path.start_workers()?;
        tracing::info!(
            building = %config.building,
            gateway = %config.gateway_name,
            zid = %session.zid(),
            workers = config.workers,
            overload = ?config.overload,
            history = config.history.is_some(),
            public_key = signer.public_key_hex().as_deref().unwrap_or("none: nothing is signed"),
            "gateway running"
        );
        Ok(Gateway {
            config,
            session,
            store: opened.store,
            table,
            counters,
            updater,
            trigger,
            path,
            tasks,
            metrics_addr,
            started_at,
            _claim: opened.claim,
        })
    }

    /// Address the metrics endpoint is bound to (useful with port 0).
    pub fn metrics_addr(&self) -> Option<SocketAddr> {
        self.metrics_addr
    }

    /// The sensor table: corrector snapshots (hot swap), settings, counters.
    pub fn sensors(&self) -> &Arc<SensorTable> {
        &self.table
    }

    pub fn counters(&self) -> &Arc<GatewayCounters> {
        &self.counters
    }

    pub fn config(&self) -> &Config {
        &self.config
    }

    pub fn started_at(&self) -> OffsetDateTime {
        self.started_at
    }

    /// The Zenoh session, for components that share it.
    pub fn session(&self) -> &zenoh::Session {
        &self.session
    }

    /// The calibration store, for components that update it (from blocking tasks).
    pub fn store(&self) -> &Arc<Store> {
        &self.store
    }

    /// Asks the lab's registry for newer records now and applies them, as the periodic
    /// catch-up does.
    pub async fn catch_up(&self) -> Result<CatchUpReport, CatchUpError> {
        catchup::catch_up(
            &self.session,
            &self.updater,
            self.config.calibration.catchup_timeout,
        )
        .await
    }

    /// Serves until `shutdown` completes, then stops: no new batches, workers correct and
    /// publish what is queued (for at most [`sample_path::SHUTDOWN_DRAIN`], the rest counted as
    /// dropped; under backpressure nothing is queued), the services end, the history keeps what
    /// the workers handed over, the session closes, the store is flushed and closed.
    pub async fn run_until(self, shutdown: impl Future) -> Result<(), GatewayError> {
        shutdown.await;
        tracing::info!("shutting down");
        let Gateway {
            session,
            store,
            counters,
            trigger,
            mut path,
            tasks,
            _claim,
            ..
        } = self;
        path.stop_intake();
        trigger.fire();
        for t in tasks {
            if let Err(e) = t.await {
                tracing::error!(cause = %e, "gateway task ended abnormally");
            }
        }
        path.finish().await?;
        if let Err(e) = session.close().await {
            tracing::warn!(cause = %e, "zenoh session did not close cleanly");
        }
        // Every put is flushed when it returns; the flush here makes that explicit before the
        // last handle closes sled. Blocking I/O, so off the runtime threads.
        let flushed = tokio::task::spawn_blocking(move || {
            let flushed = store.flush();
            drop(store);
            flushed
        })
        .await
        .map_err(|e| GatewayError::Task(e.to_string()))?;
        if let Err(e) = flushed {
            tracing::error!(cause = %e, "calibration store did not flush on shutdown");
        }
        let c = &counters;
        tracing::info!(
            received = c.received_batches.load(Relaxed),
            published = c.published_batches.load(Relaxed),
            dropped = c.dropped.load(Relaxed),
            "stopped"
        );
        Ok(())
    }
}
