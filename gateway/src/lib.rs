//! The Triax building gateway: subscribes to every raw sensor stream of one building over Zenoh,
//! corrects each sample with the sensor's calibration, tags it with its uncertainty, quality
//! flags and the calibration version, and publishes it.
//!
//! The entry point is [`run`] (or [`Gateway::start`] then [`Gateway::run_until`]): it takes a
//! validated [`Config`] and a shutdown future, so a test can start a gateway on a loopback port
//! and stop it at will. The `triax-gateway` binary only parses arguments, installs logging and
//! hands over.
//!
//! Data flow:
//!
//! ```text
//! triax/<b>/raw/* ─► Zenoh callback ─► intake: the receive burst, per shard ─► the shard,
//!   in place, or its Inbox (bounded, drop-oldest) and worker thread: sequence, SensorKernel
//!   (correct, flags), tilt ─► outbox, at the burst's end ─► triax/<b>/corrected/<s>
//!   (under backpressure the callback runs the shard itself)       triax/<b>/tilt/<s>
//! triax/<b>/status ◄─ queryable (GatewayStatus JSON)      http://<metrics>/metrics (Prometheus)
//! triax/<b>/calibration/push/* ◄─ queryable: verify, store, swap, ack ─► calibration/ack/<s>
//! triax/<b>/calibration/registry ─► query at start and periodically (catch-up)
//! ```
//!
//! - [`config`]: TOML file, flags, environment; refused with field and reason.
//! - [`sensors`]: the in-memory table of sensors, with each one's corrector snapshot, swapped
//!   atomically between batches ([`SensorTable::install`]).
//! - [`kernel`]: the allocation-free sample path; the mode rules and the frequency detector.
//! - [`tilt`], [`sequence`], [`filter`], [`inbox`], `intake`, [`outbox`], `burst`: its parts.
//! - [`worker`], [`status`], [`metrics`], [`shutdown`]: the service around it.
//! - [`memory`]: keeping the resident set near what is used (10 000 sensors in under 50 MB).
//! - [`push`], [`catchup`]: signed calibration updates from the lab, pushed or caught up.
//! - [`demo`]: an embedded building with simulated sensor nodes.
//!
//! Architecture invariant: the sample path never touches the store. Calibrations are read from
//! the store at start (and, later, on an accepted update) and live in [`SensorTable`]; the store
//! is used from blocking tasks only.

pub mod backfill;
mod burst;
pub mod catchup;
pub mod config;
pub mod demo;
pub mod filter;
pub mod health;
pub mod heartbeat;
pub mod history;
pub mod inbox;
mod intake;
pub mod kernel;
pub mod memory;
pub mod metrics;
pub mod outbox;
pub mod push;
pub mod replay;
pub mod sensors;
pub mod sequence;
pub mod shutdown;
pub mod status;
pub mod tilt;
pub mod worker;

use std::future::Future;
use std::net::SocketAddr;
use std::path::Path;
use std::sync::atomic::Ordering::Relaxed;
use std::sync::Arc;

use time::OffsetDateTime;
use tokio::task::JoinHandle;
use triax_calibration::corrector::Corrector;
use triax_calibration_store::{Store, StoreError};
use triax_protocol::signing::TrustedKeys;
use triax_protocol::{to_json, Key};

pub use catchup::{CatchUpError, CatchUpReport};
pub use config::{
    CalibrationSettings, Config, ConfigArgs, ConfigError, CorrectionMode, HealthSettings, Overload,
    SensorSettings,
};
pub use sensors::{GatewayCounters, SensorTable};

use inbox::Inbox;
use shutdown::ShutdownTrigger;

/// Why the gateway could not start or stopped.
#[derive(Debug, thiserror::Error)]
pub enum GatewayError {
    #[error(transparent)]
    Config(#[from] ConfigError),
    #[error(transparent)]
    ZenohConfig(#[from] triax_net::ZenohConfigError),
    #[error("calibration store {path}: {source}")]
    Store {
        path: std::path::PathBuf,
        #[source]
        source: StoreError,
    },
    #[error("zenoh: {action}: {message}")]
    Zenoh {
        action: &'static str,
        message: String,
    },
    #[error("metrics endpoint {addr}: {source}")]
    Metrics {
        addr: SocketAddr,
        #[source]
        source: std::io::Error,
    },
    #[error("a gateway task failed: {0}")]
    Task(String),
    #[error(transparent)]
    History(#[from] triax_history::HistoryError),
}

fn zenoh_err(action: &'static str) -> impl FnOnce(zenoh::Error) -> GatewayError {
    move |e| GatewayError::Zenoh {
        action,
        message: e.to_string(),
    }
}

/// Closes every worker's inbox: its worker stops once it has taken what is queued, until
/// `drain_until`.
fn close_all(inboxes: &[Arc<Inbox<intake::Arrival>>], drain_until: std::time::Instant) {
    for inbox in inboxes {
        inbox.close(drain_until);
    }
}

/// Forgets uncalibrated sensors silent for `unknown_sensor_expiry_s`, checking ten times per
/// expiry period (at least every 10 s and at most every 100 ms).
async fn expire_unknown_sensors(table: Arc<SensorTable>, mut shutdown: shutdown::Shutdown) {
    let period = (table.unknown_sensor_expiry() / 10).clamp(
        std::time::Duration::from_millis(100),
        std::time::Duration::from_secs(10),
    );
    let mut tick = tokio::time::interval(period);
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    loop {
        tokio::select! {
            _ = tick.tick() => {}
            _ = shutdown.recv() => return,
        }
        let n = table.expire_idle(worker::now_ns());
        if n > 0 {
            tracing::info!(forgotten = n, "silent uncalibrated sensors forgotten");
        }
    }
}

/// A running gateway.
pub struct Gateway {
    config: Arc<Config>,
    session: zenoh::Session,
    store: Arc<Store>,
    table: Arc<SensorTable>,
    counters: Arc<GatewayCounters>,
    updater: Arc<push::Updater>,
    trigger: ShutdownTrigger,
    subscriber: Option<zenoh::pubsub::Subscriber<()>>,
    tasks: Vec<JoinHandle<()>>,
    /// Drop-oldest only: the receive bursts' queues, the workers' inboxes and threads.
    queues: Option<Arc<intake::Queues>>,
    inboxes: Arc<Vec<Arc<Inbox<intake::Arrival>>>>,
    workers: Vec<std::thread::JoinHandle<()>>,
    /// The history's writer thread; none when the history is off.
    recorder: Option<history::Recorder>,
    /// Corrected batches waiting for the end of their receive burst.
    outbox: Arc<outbox::Outbox>,
    metrics_addr: Option<SocketAddr>,
    started_at: OffsetDateTime,
    /// The lock on the store (see [`claim_store`]), released last.
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

/// Opens the store, loads every current record into the table, and returns the store opened
/// afresh with how many records loaded.
///
/// Why afresh: sled keeps every leaf it has read in its page cache, and its `cache_capacity`
/// does not bound that below a few hundred leaves (the cache is split in 256 shards, each
/// keeping at least one page). A handle that has read every record at start keeps about
/// 2 000 of them, 11 MiB for ten thousand sensors, for nothing: the gateway reads the store
/// again only for a push or a catch-up. A new handle starts with an empty cache, and sled's
/// directory lock, released in the background when the first handle closes, is waited for by
/// [`Store::open`].
async fn open_and_load(
    path: &Path,
    table: &Arc<SensorTable>,
) -> Result<(Store, usize), StoreError> {
    let task_failed = |e: tokio::task::JoinError| StoreError::Io {
        action: "load records",
        source: std::io::Error::other(e.to_string()),
    };
    let open_path = path.to_path_buf();
    let t = table.clone();
    // Each record is loaded into its corrector and health monitor, then dropped: the gateway
    // never holds every record at once.
    let (scan, suspects) = tokio::task::spawn_blocking(move || {
        let store = Store::open(&open_path)?;
        let scan = store.map_current(|record| {
            let corrector = Corrector::from_record(&record);
            let health = corrector
                .as_ref()
                .map(|c| t.health_seed(&record, c))
                .unwrap_or_default();
            (record.sensor_id, record.version, corrector, health)
        })?;
        Ok::<_, StoreError>((scan, store.suspects()?))
    })
    .await
    .map_err(task_failed)??;
    for skipped in scan.skipped.iter().chain(&suspects.skipped) {
        tracing::error!(entry = %skipped, "unreadable store entry: sensor stays uncalibrated");
    }
    let mut loaded = 0;
    for (sensor_id, version, corrector, health) in scan.value {
        match corrector {
            Ok(c) => {
                table.install(c, health);
                loaded += 1;
            }
            // The store validates on put; this is a record from an older, laxer build.
            Err(e) => tracing::error!(sensor = %sensor_id, version, cause = %e,
                "stored record does not load: sensor stays uncalibrated"),
        }
    }
    // The newest suspect mark of each sensor: older records no longer correct anything live.
    for m in suspects.value {
        if let Some(e) = table.get(&m.sensor_id) {
            e.set_suspect(m.version, m.flagged_from_ns);
        }
    }
    let open_path = path.to_path_buf();
    let store = tokio::task::spawn_blocking(move || Store::open(&open_path))
        .await
        .map_err(task_failed)??;
    Ok((store, loaded))
}

/// Holds the gateway's claim on its store for its life: a second gateway on the same store (and
/// history) is refused at start, and none can slip in while the store is closed and opened again
/// at start-up (see [`open_and_load`]).
fn claim_store(store_path: &Path) -> Result<std::fs::File, GatewayError> {
    let path = store_path.with_extension("lock");
    let io = |source| GatewayError::Store {
        path: path.clone(),
        source: StoreError::Io {
            action: "lock the store",
            source,
        },
    };
    if let Some(parent) = path.parent().filter(|p| !p.as_os_str().is_empty()) {
        std::fs::create_dir_all(parent).map_err(io)?;
    }
    let file = std::fs::File::options()
        .create(true)
        .truncate(false)
        .write(true)
        .open(&path)
        .map_err(io)?;
    match triax_history::os::try_lock_exclusive(&file) {
        Ok(true) => Ok(file),
        Ok(false) => Err(io(std::io::Error::other(
            "another gateway holds this store",
        ))),
        Err(e) => Err(io(e)),
    }
}

/// Opens the history and starts its writer thread; none when the history is off.
async fn open_history(config: &Config) -> Result<Option<history::Recorder>, GatewayError> {
    let Some(h) = config.history.clone() else {
        return Ok(None);
    };
    let history_config = h.history_config(&config.building, &config.gateway_name);
    let opened = tokio::task::spawn_blocking(move || {
        triax_history::History::open(history_config).map(|o| (o, h))
    })
    .await
    .map_err(|e| GatewayError::Task(e.to_string()))?
    .map_err(GatewayError::History)?;
    let (o, h) = opened;
    let building = config.building.as_str();
    match &o.owner {
        triax_history::OwnerCheck::Created => {
            tracing::info!(path = %h.path.display(), building, "history created for this building");
        }
        triax_history::OwnerCheck::Adopted => tracing::warn!(
            path = %h.path.display(),
            building,
            "history: made before histories recorded their building; adopted as this building's \
             (if it holds another building's batches, stop the gateway and give it another path)"
        ),
        triax_history::OwnerCheck::Confirmed {
            recorded_gateway_name: Some(name),
        } => tracing::info!(
            path = %h.path.display(),
            created_by = %name,
            "history created by this building's gateway under another name"
        ),
        triax_history::OwnerCheck::Confirmed { .. } | triax_history::OwnerCheck::Unchecked => {}
    }
    // The default used to be one `triax-history` per folder of stores; after an upgrade it is
    // not served any more, and which building's it is cannot be known, so it is only pointed at.
    let legacy = config
        .store_path
        .parent()
        .unwrap_or(Path::new(""))
        .join(crate::config::LEGACY_HISTORY_DIR);
    if h.path == crate::config::default_history_path(&config.store_path, &config.building)
        && !legacy.join(triax_history::OWNER_FILE).exists()
        && legacy.is_dir()
    {
        tracing::warn!(
            legacy = %legacy.display(),
            path = %h.path.display(),
            "history: an older history beside the store is not served; if it is this building's, \
             stop the gateway and move it to the path in use, or set [history] path to it"
        );
    }
    if o.cut_bytes > 0 || o.rescanned_blocks > 0 {
        tracing::warn!(
            cut_bytes = o.cut_bytes,
            rescanned_blocks = o.rescanned_blocks,
            "history: a torn end was cut after a crash (what was flushed is kept)"
        );
    }
    let stats = o.history.stats();
    tracing::info!(path = %h.path.display(), segments = stats.segments, bytes = stats.bytes, "history open");
    let recorder = history::Recorder::start(o.writer, h.queue_bytes, h.flush_interval)
        .map_err(|e| GatewayError::Task(format!("starting the history writer: {e}")))?;
    Ok(Some(recorder))
}

/// Answers status queries until shutdown.
async fn serve_status(
    session: &zenoh::Session,
    ctx: status::StatusContext,
    mut shutdown: shutdown::Shutdown,
) -> Result<JoinHandle<()>, GatewayError> {
    let queryable = session
        .declare_queryable(Key::Status(ctx.config.building.clone()).to_string())
        .await
        .map_err(zenoh_err("declare the status queryable"))?;
    let ctx = Arc::new(ctx);
    Ok(tokio::spawn(async move {
        loop {
            let query = tokio::select! {
                q = queryable.recv_async() => match q { Ok(q) => q, Err(_) => break },
                _ = shutdown.recv() => break,
            };
            let replied = match status::StatusQuery::parse(query.parameters().iter()) {
                Ok(q) => {
                    // A one-sensor answer reads the store.
                    let c = ctx.clone();
                    let Ok(body) =
                        tokio::task::spawn_blocking(move || to_json(&c.status(&q))).await
                    else {
                        tracing::error!("status answer panicked");
                        continue;
                    };
                    let key = Key::Status(ctx.config.building.clone()).to_string();
                    query.reply(key, body).await
                }
                Err(problem) => query.reply_err(problem).await,
            };
            if let Err(e) = replied {
                tracing::warn!(cause = %e, "status reply failed");
            }
        }
    }))
}

/// Binds the metrics endpoint and serves it until shutdown; returns the bound address.
/// The queryables a gateway answers from its own state: status, sensor health (when the
/// checks are on) and history (when it keeps one).
async fn serve_queries(
    config: &Arc<Config>,
    session: &zenoh::Session,
    shared: &Arc<worker::Shared>,
    store: &Arc<Store>,
    started_at: OffsetDateTime,
    shutdown: &shutdown::Shutdown,
) -> Result<Vec<JoinHandle<()>>, GatewayError> {
    let mut tasks = Vec::new();
    let status_ctx = status::StatusContext {
        config: config.clone(),
        table: shared.table.clone(),
        counters: shared.counters.clone(),
        history: shared.history.clone(),
        backfill: shared.backfill.as_ref().map(|a| a.counters.clone()),
        started_at,
        store: Some(store.clone()),
    };
    tasks.push(serve_status(session, status_ctx, shutdown.clone()).await?);
    if config.health.is_some() {
        let serving = health::serve(
            session,
            config.building.clone(),
            shared.table.clone(),
            shutdown.clone(),
        );
        tasks.push(
            serving
                .await
                .map_err(zenoh_err("declare the health queryable"))?,
        );
    }
    if let Some(sink) = &shared.history {
        let ctx = Arc::new(replay::ReplayContext {
            building: config.building.clone(),
            table: shared.table.clone(),
            store: store.clone(),
            sink: sink.clone(),
        });
        tasks.push(
            replay::serve(session.clone(), ctx, shutdown.clone())
                .await
                .map_err(zenoh_err("declare the history queryable"))?,
        );
    }
    Ok(tasks)
}

async fn serve_metrics(
    addr: SocketAddr,
    src: metrics::MetricsSource,
    shutdown: shutdown::Shutdown,
) -> Result<(SocketAddr, JoinHandle<()>), GatewayError> {
    let listener = tokio::net::TcpListener::bind(addr)
        .await
        .map_err(|source| GatewayError::Metrics { addr, source })?;
    let bound = listener
        .local_addr()
        .map_err(|source| GatewayError::Metrics { addr, source })?;
    tracing::info!(addr = %bound, "metrics at http://{bound}/metrics");
    Ok((bound, tokio::spawn(metrics::serve(listener, src, shutdown))))
}

/// Starts one worker thread per inbox; on failure, closes every inbox so that the threads
/// already started end.
fn start_workers(
    inboxes: &Arc<Vec<Arc<Inbox<intake::Arrival>>>>,
    shards: &worker::Shards,
    shared: &Arc<worker::Shared>,
) -> Result<Vec<std::thread::JoinHandle<()>>, GatewayError> {
    let mut workers = Vec::new();
    for (i, (inbox, shard)) in inboxes.iter().zip(shards.iter()).enumerate() {
        let (inbox, shard, shared) = (inbox.clone(), shard.clone(), shared.clone());
        let spawned = std::thread::Builder::new()
            .name(format!("triax-worker-{i}"))
            .spawn(move || worker::run(i, inbox, shard, shared));
        match spawned {
            Ok(worker) => workers.push(worker),
            Err(e) => {
                close_all(inboxes, std::time::Instant::now());
                return Err(GatewayError::Task(format!(
                    "starting worker thread {i}: {e}"
                )));
            }
        }
    }
    Ok(workers)
}

impl Gateway {
    /// Opens the store and the history, loads the calibrations, joins Zenoh, and starts
    /// serving.
    pub async fn start(config: Config) -> Result<Gateway, GatewayError> {
        let config = Arc::new(config);
        let started_at = OffsetDateTime::now_utc();
        let path = config.store_path.clone();
        let claim = claim_store(&path)?;
        let store_err = |source| GatewayError::Store {
            path: path.clone(),
            source,
        };
        let table = Arc::new(SensorTable::new(config.clone()));
        let (store, loaded) = open_and_load(&path, &table).await.map_err(store_err)?;
        let store = Arc::new(store);
        tokio::task::spawn_blocking(memory::release_free_heap)
            .await
            .map_err(|e| GatewayError::Task(e.to_string()))?;
        tracing::info!(building = %config.building, calibrations = loaded, store = %path.display(), "calibrations loaded");
        let recorder = open_history(&config).await?;

        let session = zenoh::open(config.zenoh.to_publisher_config()?)
            .await
            .map_err(zenoh_err("open session"))?;
        let counters = Arc::new(GatewayCounters::default());
        // A store that already holds more calibrated sensors than the key budget can declare
        // starts undeclared: waiting to find out would spend minutes partly declared, the
        // slowest state (see `worker::Shard::reassign_keys`). Only for a building of a thousand
        // sensors or more, where that state costs several times more per batch (BENCHMARKS.md);
        // below, the budget's patience decides.
        if loaded >= 1000 && loaded.saturating_mul(2) > config.declared_keys_max {
            counters
                .keys_undeclared
                .store(true, std::sync::atomic::Ordering::Relaxed);
            tracing::info!(
                calibrations = loaded,
                budget_keys = config.declared_keys_max,
                "more calibrated sensors than declared_keys_mib holds: keys are used undeclared"
            );
        }
        let (trigger, shutdown) = shutdown::channel();
        let (asker, backfill_requests) = backfill::channel();
        let backfill_counters = asker.counters.clone();
        let shared = Arc::new(worker::Shared {
            building: config.building.clone(),
            session: session.clone(),
            table: table.clone(),
            counters: counters.clone(),
            declared_keys_max: config.declared_keys_max,
            declared_keys_idle_ns: config.declared_keys_idle.as_nanos().min(i64::MAX as u128)
                as i64,
            history: recorder.as_ref().map(|r| r.sink.clone()),
            store: store.clone(),
            health: config.health.as_ref().map(|h| health::Reporting {
                publish_interval_ns: (h.publish_interval_s * 1e9) as i64,
                clock_watch_ms: h.clock_watch_ms,
            }),
            backfill: config.backfill.as_ref().map(|_| asker),
            outbox: outbox::Outbox::new(session.clone(), counters.clone()),
        });
        let intake::Started {
            inboxes,
            shards,
            queues,
            subscriber,
        } = intake::start(&config, &session, &counters, &shared).await?;
        let mut tasks = Vec::new();
        if let Some(settings) = config.backfill.clone() {
            let ctx = backfill::Context {
                building: config.building.clone(),
                session: session.clone(),
                shared: shared.clone(),
                shards: shards.clone(),
                counters: backfill_counters,
                history: shared
                    .history
                    .as_ref()
                    .map(|sink| (sink.history.clone(), sink.first_arrival)),
                settings,
            };
            tasks.push(tokio::spawn(backfill::run(
                ctx,
                backfill_requests,
                shutdown.clone(),
            )));
        }
        // Pushes are taken before status is answered: a gateway that answers status takes
        // pushes too (its declarations reach the router in order).
        let updater = Arc::new(push::Updater::new(
            config.building.clone(),
            config.gateway_name.clone(),
            TrustedKeys::new(config.calibration.trusted_lab_keys.clone()),
            store.clone(),
            table.clone(),
            counters.clone(),
        ));
        tasks.push(
            push::serve(session.clone(), updater.clone(), shutdown.clone())
                .await
                .map_err(zenoh_err("declare the calibration push queryable"))?,
        );
        tasks.extend(
            serve_queries(&config, &session, &shared, &store, started_at, &shutdown).await?,
        );
        tasks.push(tokio::spawn(heartbeat::run(
            session.clone(),
            config.building.clone(),
            config.gateway_name.clone(),
            table.clone(),
            shutdown.clone(),
        )));

        tasks.push(catchup::spawn(
            session.clone(),
            updater.clone(),
            config.calibration.catchup_interval,
            config.calibration.catchup_timeout,
            shutdown.clone(),
        ));
        tasks.push(tokio::spawn(expire_unknown_sensors(
            table.clone(),
            shutdown.clone(),
        )));
        tasks.push(tokio::spawn(memory::release_after_growth(
            counters.clone(),
            memory::GROWTH_SETTLE_PERIOD,
            shutdown.clone(),
        )));

        let mut metrics_addr = None;
        if let Some(addr) = config.metrics_listen {
            let boxes = inboxes.clone();
            let src = metrics::MetricsSource {
                table: table.clone(),
                counters: counters.clone(),
                history: shared.history.clone(),
                backfill: shared.backfill.as_ref().map(|a| a.counters.clone()),
                queued: Arc::new(move || boxes.iter().map(|b| b.len()).sum()),
            };
            let (bound, task) = serve_metrics(addr, src, shutdown.clone()).await?;
            metrics_addr = Some(bound);
            tasks.push(task);
        }
        // Last, so that a start that fails leaves no thread behind. Batches taken meanwhile
        // wait in the inboxes.
        let workers = start_workers(&inboxes, &shards, &shared)?;
        tracing::info!(
            building = %config.building,
            gateway = %config.gateway_name,
            zid = %session.zid(),
            workers = config.workers,
            overload = ?config.overload,
            history = config.history.is_some(),
            "gateway running"
        );
        Ok(Gateway {
            config,
            session,
            store,
            table,
            counters,
            updater,
            trigger,
            subscriber: Some(subscriber),
            tasks,
            queues,
            inboxes,
            workers,
            recorder,
            outbox: shared.outbox.clone(),
            metrics_addr,
            started_at,
            _claim: claim,
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
    /// publish what is queued (for at most [`worker::SHUTDOWN_DRAIN`], the rest counted as
    /// dropped; under backpressure nothing is queued), the session closes, the store is
    /// flushed and closed.
    pub async fn run_until(mut self, shutdown: impl Future) -> Result<(), GatewayError> {
        shutdown.await;
        tracing::info!("shutting down");
        // Stop intake first; a batch still in Zenoh's hands after that finds its inbox closed
        // and is counted as dropped.
        drop(self.subscriber.take());
        // What the last burst left waiting, should its task not have run: to the shards
        // while their inboxes still take it.
        if let Some(queues) = &self.queues {
            queues.hand_over();
        }
        close_all(
            &self.inboxes,
            std::time::Instant::now() + worker::SHUTDOWN_DRAIN,
        );
        self.trigger.fire();
        for t in self.tasks.drain(..) {
            if let Err(e) = t.await {
                tracing::error!(cause = %e, "gateway task ended abnormally");
            }
        }
        let workers = std::mem::take(&mut self.workers);
        let joined = tokio::task::spawn_blocking(move || {
            workers
                .into_iter()
                .map(|w| w.join())
                .filter(Result::is_err)
                .count()
        })
        .await
        .map_err(|e| GatewayError::Task(e.to_string()))?;
        if joined > 0 {
            tracing::error!(workers = joined, "worker threads ended abnormally");
        }
        // What the last bursts left waiting, should their tasks not have run.
        self.outbox.flush();
        // The workers have handed over their last batches: keep them.
        if let Some(mut recorder) = self.recorder.take() {
            let sink = recorder.sink.clone();
            tokio::task::spawn_blocking(move || recorder.stop())
                .await
                .map_err(|e| GatewayError::Task(e.to_string()))?;
            let c = &sink.counters;
            tracing::info!(
                offered = c.offered.load(Relaxed),
                not_kept = c.dropped.load(Relaxed),
                written = sink.history.counters.written_batches.load(Relaxed),
                "history closed"
            );
        }
        if let Err(e) = self.session.close().await {
            tracing::warn!(cause = %e, "zenoh session did not close cleanly");
        }
        let store = self.store.clone();
        let counters = self.counters.clone();
        drop(self);
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

impl Drop for Gateway {
    /// A gateway dropped without [`Gateway::run_until`] still lets its worker threads end
    /// (what they hold queued is counted as dropped). After `run_until` they have ended.
    fn drop(&mut self) {
        close_all(&self.inboxes, std::time::Instant::now());
    }
}
