//! The operators' console: the fleet at a glance, each sensor's corrected stream with its
//! uncertainty band, and the alerts, in a browser.
//!
//! The console joins Zenoh like any client and only reads the site: it subscribes to the gateways'
//! heartbeats and to the alerts, polls the gateways' status, and, for a sensor someone is
//! looking at, subscribes to its corrected and tilt streams and queries its history. It never
//! puts. It serves one page, by default on 127.0.0.1, that draws what the server has already
//! decimated (min/max per pixel column, see [`buckets`]), pushed as Server-Sent Events.
//!
//! ```no_run
//! # async fn run() -> Result<(), Box<dyn std::error::Error + Send + Sync>> {
//! let session = zenoh::open(zenoh::Config::default()).await?;
//! let listener = tokio::net::TcpListener::bind("127.0.0.1:9760").await?;
//! let options = triax_console::ConsoleOptions::default();
//! triax_console::serve(session, listener, options, tokio::signal::ctrl_c()).await?;
//! # Ok(()) }
//! ```
//!
//! Module map: [`server`] (routes), [`http`] (requests, responses, events), [`fleet`] (what is
//! known of the buildings, gateways, sensors and alerts), [`live`] (the streams being watched),
//! [`buckets`] (decimation), [`modes`] (the buildings' modes heard), [`operators`] (accounts,
//! roles, sessions), [`notify`] (notifications), [`process`] (filtered and integrated views),
//! [`annotations`], [`helicorder`] (the day view's per-second store); the page itself is in
//! `src/assets/`.

pub mod alertlog;
pub mod annotations;
pub mod buckets;
pub mod fleet;
pub mod helicorder;
pub mod http;
pub mod live;
pub mod modes;
pub mod notify;
pub mod operators;
pub mod process;
pub mod provenance;
pub mod server;
pub mod spectrum;
pub mod trend;

use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;

use tokio::net::TcpListener;
use tokio::sync::{watch, Semaphore};
use triax_protocol::BuildingId;

use crate::fleet::{Fleet, FleetOptions};
use crate::live::Feeds;
use crate::server::Context;
use triax_protocol::provenance::GatewayKeys;
use triax_protocol::signing::TrustedKeys;

/// Default address of the page.
pub const DEFAULT_LISTEN: &str = "127.0.0.1:9760";

/// How the console runs.
#[derive(Debug, Clone)]
pub struct ConsoleOptions {
    /// Buildings to watch; empty: every building that answers a status query or sends a
    /// heartbeat or an alert.
    pub buildings: Vec<BuildingId>,
    /// Time between status polls of the gateways.
    pub status_interval: Duration,
    /// Warn this long before a calibration record's `valid_until`.
    pub expiry_warning: Duration,
    /// Serve on a non-loopback address, and answer requests for any host name. The console
    /// has no authentication: whoever reaches the port sees the fleet.
    pub allow_remote: bool,
    /// Connections served at once; as many more are answered 503, and any beyond those are
    /// closed unanswered.
    pub max_connections: usize,
    /// Live event streams (open pages) at once; more get 503.
    pub max_streams: usize,
    /// History views read at once; more get 503.
    pub max_history_queries: usize,
    /// How long one history page may take.
    pub history_timeout: Duration,
    /// The alerting services' public keys (PROTOCOL.md §3.6): only an alert signed by one of
    /// them is shown as a verdict.
    pub trusted_alert_keys: TrustedKeys,
    /// The buildings' gateway keys (PROTOCOL.md §6): with them, only what a building's
    /// gateway signed or sealed is shown, and only keyed buildings are watched. None: every
    /// message is taken on trust ([`provenance`]).
    pub gateway_keys: Option<Arc<GatewayKeys>>,
    /// Where the alert log is kept ([`alertlog::FILE_NAME`] in it); None: in memory only.
    pub state_dir: Option<std::path::PathBuf>,
    /// Alerts the log keeps at most.
    pub max_logged_alerts: usize,
    /// How long the log keeps an alert.
    pub alert_retention: Duration,
    /// The operators' accounts file ([`operators`]); none: no accounts (read-only, open on
    /// loopback).
    pub operators_file: Option<std::path::PathBuf>,
    /// A request header that a reverse proxy in front of the console sets to the operator's
    /// name (`X-Remote-User`); trusted as it comes, so only with the console on loopback
    /// behind that proxy.
    pub identity_header: Option<String>,
    /// The site's time zone: quiet hours and rota shifts are in it, and the page offers it
    /// beside UTC.
    pub time_zone: Option<SiteTimeZone>,
    /// Where notifications go ([`notify`]); none: nowhere.
    pub notify: Option<notify::Config>,
}

/// A site's time zone by its IANA name, read from the system's time zone database.
#[derive(Debug, Clone)]
pub struct SiteTimeZone {
    name: String,
    tz: jiff::tz::TimeZone,
}

impl SiteTimeZone {
    /// The zone named `name` (`Europe/Zurich`); an error says why there is none.
    pub fn get(name: &str) -> Result<SiteTimeZone, ConsoleError> {
        let tz = jiff::tz::TimeZone::get(name).map_err(|e| ConsoleError::Option {
            field: "time_zone",
            reason: format!("{name:?} is not a time zone of this system's database: {e}"),
        })?;
        Ok(SiteTimeZone {
            name: name.to_owned(),
            tz,
        })
    }

    pub fn name(&self) -> &str {
        &self.name
    }

    /// The wall-clock time of day at `t_ns` (ns since the Unix epoch), as minutes after
    /// midnight, and the day of the week (Monday 1 to Sunday 7).
    pub fn minute_of_day(&self, t_ns: i64) -> (u32, u8) {
        let ts = jiff::Timestamp::from_nanosecond(i128::from(t_ns)).unwrap_or_default();
        let z = ts.to_zoned(self.tz.clone());
        (
            u32::from(z.hour() as u8) * 60 + u32::from(z.minute() as u8),
            z.weekday().to_monday_one_offset() as u8,
        )
    }
}

impl Default for ConsoleOptions {
    fn default() -> Self {
        ConsoleOptions {
            buildings: Vec::new(),
            status_interval: Duration::from_secs(2),
            expiry_warning: Duration::from_secs(30 * 86_400),
            allow_remote: false,
            max_connections: 64,
            max_streams: 16,
            max_history_queries: 2,
            history_timeout: Duration::from_secs(20),
            trusted_alert_keys: TrustedKeys::default(),
            gateway_keys: None,
            state_dir: None,
            max_logged_alerts: alertlog::DEFAULT_MAX_ALERTS,
            alert_retention: alertlog::DEFAULT_RETENTION,
            operators_file: None,
            identity_header: None,
            time_zone: None,
            notify: None,
        }
    }
}

/// Why the console could not run.
#[derive(Debug, thiserror::Error)]
pub enum ConsoleError {
    #[error(
        "refusing to serve on {addr}, which is not a loopback address: the console has no \
         authentication (allow it explicitly to serve anyway)"
    )]
    NotLoopback { addr: SocketAddr },
    #[error("console listener: {0}")]
    Listener(#[source] std::io::Error),
    #[error("the page's address {addr:?}: {source}")]
    Address {
        addr: String,
        #[source]
        source: std::io::Error,
    },
    #[error("zenoh: {action}: {message}")]
    Zenoh {
        action: &'static str,
        message: String,
    },
    #[error(transparent)]
    AlertLog(#[from] alertlog::AlertLogError),
    #[error(transparent)]
    Operators(#[from] operators::OperatorError),
    #[error("option `{field}`: {reason}")]
    Option { field: &'static str, reason: String },
}

/// Binds the page's address, `host:port`, whose host is an IP address or a name
/// (`localhost:9760`). Every address a name resolves to must be a loopback address unless
/// `allow_remote`; the first of them that binds is used (`localhost` may resolve to `::1`
/// first on a machine without IPv6).
pub async fn bind(addr: &str, allow_remote: bool) -> Result<TcpListener, ConsoleError> {
    let address_error = |source| ConsoleError::Address {
        addr: addr.to_owned(),
        source,
    };
    let addrs: Vec<SocketAddr> = tokio::net::lookup_host(addr)
        .await
        .map_err(address_error)?
        .collect();
    if let Some(wide) = addrs.iter().find(|a| !a.ip().is_loopback()) {
        if !allow_remote {
            return Err(ConsoleError::NotLoopback { addr: *wide });
        }
    }
    let mut last = None;
    for a in &addrs {
        match TcpListener::bind(a).await {
            Ok(l) => return Ok(l),
            Err(e) => last = Some(e),
        }
    }
    Err(match last {
        Some(e) => ConsoleError::Listener(e),
        None => address_error(std::io::Error::new(
            std::io::ErrorKind::NotFound,
            "resolves to no address",
        )),
    })
}

/// The page's address for a listener bound to `addr`.
pub fn url(addr: SocketAddr) -> String {
    format!("http://{addr}/")
}

/// With gateway keys, the buildings watched are the keyed ones (all of them when none are
/// named); a building named without a key is refused, as it could only show what is taken on
/// trust.
fn watched_buildings(mut options: ConsoleOptions) -> Result<ConsoleOptions, ConsoleError> {
    let Some(keys) = &options.gateway_keys else {
        return Ok(options);
    };
    if options.buildings.is_empty() {
        options.buildings = keys.buildings().cloned().collect();
        options.buildings.sort();
    }
    if let Some(b) = options.buildings.iter().find(|b| keys.keys(b).is_empty()) {
        return Err(ConsoleError::Option {
            field: "buildings",
            reason: format!(
                "building {b} is watched but no gateway key is given for it: add \
                 --gateway-key {b}=KEY, or leave it out of --buildings"
            ),
        });
    }
    Ok(options)
}

/// Serves the console on `listener` until `shutdown` completes.
///
/// Refuses a listener on a non-loopback address unless `options.allow_remote`.
pub async fn serve(
    session: zenoh::Session,
    listener: TcpListener,
    options: ConsoleOptions,
    shutdown: impl std::future::Future,
) -> Result<(), ConsoleError> {
    let addr = listener.local_addr().map_err(ConsoleError::Listener)?;
    if !addr.ip().is_loopback() && !options.allow_remote {
        return Err(ConsoleError::NotLoopback { addr });
    }
    for (field, n) in [
        ("max_connections", options.max_connections),
        ("max_streams", options.max_streams),
        ("max_history_queries", options.max_history_queries),
    ] {
        if n == 0 {
            return Err(ConsoleError::Option {
                field,
                reason: "must be at least 1".into(),
            });
        }
    }
    if options.max_logged_alerts == 0 {
        return Err(ConsoleError::Option {
            field: "max_logged_alerts",
            reason: "must be at least 1".into(),
        });
    }
    if options.status_interval.is_zero() {
        return Err(ConsoleError::Option {
            field: "status_interval",
            reason: "must be positive".into(),
        });
    }
    let options = watched_buildings(options)?;
    let provenance = Arc::new(provenance::Provenance::new(options.gateway_keys.clone()));
    let log = match &options.state_dir {
        Some(dir) => {
            alertlog::AlertLog::open(dir, options.max_logged_alerts, options.alert_retention)?
        }
        None => alertlog::AlertLog::in_memory(options.max_logged_alerts, options.alert_retention),
    };
    let fleet = Arc::new(Fleet::with_alert_log(
        FleetOptions {
            buildings: options.buildings.clone(),
            status_interval: options.status_interval,
            expiry_warning: options.expiry_warning,
            trusted_alert_keys: options.trusted_alert_keys.clone(),
            provenance: provenance.clone(),
        },
        log,
    ));
    let _watch = fleet::watch(&session, &fleet)
        .await
        .map_err(|e| ConsoleError::Zenoh {
            action: "subscribe to heartbeats and alerts",
            message: e.to_string(),
        })?;
    let modes = Arc::new(std::sync::Mutex::new(modes::ModesBook::new(
        options.buildings.clone(),
    )));
    let _modes_watch = modes::watch(&session, &modes, options.trusted_alert_keys.clone())
        .await
        .map_err(|e| ConsoleError::Zenoh {
            action: "subscribe to the buildings' modes",
            message: e.to_string(),
        })?;
    let annotations = match &options.state_dir {
        Some(dir) => annotations::Annotations::open(dir).map_err(|e| ConsoleError::Option {
            field: "state_dir",
            reason: e.to_string(),
        })?,
        None => annotations::Annotations::in_memory(),
    };
    let operators = Arc::new(operators::Operators::open(
        options.operators_file.clone(),
        options.identity_header.clone(),
    )?);
    let (stop_tx, stop_rx) = watch::channel(false);
    let poller = tokio::spawn(fleet::poll_status(
        session.clone(),
        fleet.clone(),
        options.status_interval,
        stop_rx.clone(),
    ));
    let (notifier, notify_tasks) = match options.notify.clone() {
        None => (notify::Notifier::off(), Vec::new()),
        Some(config) => {
            let f = fleet.clone();
            let acknowledged: Arc<dyn Fn(u64) -> bool + Send + Sync> =
                Arc::new(move |id| f.with_log(|l| l.is_acknowledged(id)));
            let (n, task) = notify::start(
                config,
                options.time_zone.clone(),
                acknowledged,
                stop_rx.clone(),
            );
            fleet.notify_to(n.clone());
            let watcher = tokio::spawn(watch_sensor_states(
                fleet.clone(),
                n.clone(),
                stop_rx.clone(),
            ));
            (n, vec![task, watcher])
        }
    };
    let fleet_events = Arc::new(FleetEvents::new());
    let serialiser = tokio::spawn(serialise_fleet(
        fleet.clone(),
        fleet_events.clone(),
        stop_rx.clone(),
    ));
    let connections = Arc::new(Semaphore::new(options.max_connections));
    let refusals = Arc::new(Semaphore::new(options.max_connections));
    let ctx = Arc::new(Context {
        session: session.clone(),
        fleet,
        feeds: Feeds::new(session, options.history_timeout, provenance),
        fleet_events,
        streams: Arc::new(Semaphore::new(options.max_streams)),
        history_queries: Arc::new(Semaphore::new(options.max_history_queries)),
        stop: stop_rx,
        trends: tokio::sync::Mutex::new(trend::TrendCache::default()),
        modes,
        operators,
        logins: Arc::new(Semaphore::new(server::MAX_LOGINS_AT_ONCE)),
        notifier,
        annotations: std::sync::Mutex::new(annotations),
        helicorder: tokio::sync::Mutex::new(helicorder::SecondsCache::default()),
        options,
    });
    tracing::info!(url = %url(addr), "console serving");
    tokio::pin!(shutdown);
    loop {
        let (stream, peer) = tokio::select! {
            _ = &mut shutdown => break,
            accepted = listener.accept() => match accepted {
                Ok(a) => a,
                Err(e) => {
                    // Out of descriptors, most likely: wait rather than spin.
                    tracing::warn!(cause = %e, "accept failed");
                    tokio::time::sleep(Duration::from_millis(100)).await;
                    continue;
                }
            },
        };
        if let Ok(permit) = connections.clone().try_acquire_owned() {
            tokio::spawn(server::handle(ctx.clone(), stream, permit));
        } else if let Ok(permit) = refusals.clone().try_acquire_owned() {
            tokio::spawn(server::refuse_busy(
                stream,
                ctx.options.max_connections,
                permit,
            ));
        } else {
            // Answering costs a task each; past twice the limit, the console keeps to itself.
            tracing::debug!(%peer, "connection closed: too many at once");
        }
    }
    let _ = stop_tx.send(true);
    // Let open streams see the stop and close.
    let all = u32::try_from(ctx.options.max_connections).unwrap_or(u32::MAX);
    let _ = tokio::time::timeout(Duration::from_secs(3), connections.acquire_many(all)).await;
    poller.abort();
    serialiser.abort();
    for t in notify_tasks {
        t.abort();
    }
    Ok(())
}

/// Tells when a sensor becomes `calibration_suspect` or `silent`: the fleet's states looked at
/// once a second, each sensor's first look taken as it is (a console that starts beside a
/// silent sensor does not call that news).
async fn watch_sensor_states(
    fleet: Arc<Fleet>,
    notifier: notify::Notifier,
    mut stop: watch::Receiver<bool>,
) {
    use fleet::SensorState;
    use notify::{Event, Notice};
    let mut seen: std::collections::HashMap<(BuildingId, triax_protocol::SensorId), [bool; 2]> =
        std::collections::HashMap::new();
    let mut tick = tokio::time::interval(Duration::from_secs(1));
    loop {
        tokio::select! {
            _ = tick.tick() => {}
            _ = stop.changed() => return,
        }
        let brief = fleet.brief();
        let mut now_seen = std::collections::HashMap::with_capacity(seen.len());
        for b in &brief.buildings {
            for s in &b.sensors {
                if !s.in_status {
                    continue;
                }
                let key = (b.building.building.clone(), s.sensor_id.clone());
                let is = [
                    s.states.contains(&SensorState::CalibrationSuspect),
                    s.states.contains(&SensorState::Silent),
                ];
                if let Some(was) = seen.get(&key) {
                    for (i, event) in [Event::CalibrationSuspect, Event::Silent]
                        .into_iter()
                        .enumerate()
                    {
                        if is[i] && !was[i] {
                            notifier.put(Notice {
                                event,
                                building: key.0.clone(),
                                sensor: key.1.clone(),
                                alert_id: None,
                                summary: match event {
                                    Event::Silent => "no batch for 10 s by its gateway's clock (silent)".into(),
                                    _ => "the gateway's field health checks found its record in force suspect".into(),
                                },
                                statement: None,
                                at_ns: live::wall_clock_ns(),
                            });
                        }
                    }
                }
                now_seen.insert(key, is);
            }
        }
        seen = now_seen;
    }
}

/// Deltas kept for streams that fall behind (a light stream reads every 5 s).
const DELTAS_KEPT: usize = 16;

/// The fleet events every open page shares: the brief the last delta was taken against, and
/// the latest deltas, serialised once for every page.
pub struct FleetEvents {
    shared: std::sync::Mutex<EventsState>,
    seq: watch::Sender<u64>,
}

struct EventsState {
    seq: u64,
    brief: Option<Arc<fleet::Brief>>,
    recent: std::collections::VecDeque<(u64, Arc<str>)>,
}

impl FleetEvents {
    fn new() -> FleetEvents {
        FleetEvents {
            shared: std::sync::Mutex::new(EventsState {
                seq: 0,
                brief: None,
                recent: std::collections::VecDeque::new(),
            }),
            seq: watch::channel(0).0,
        }
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, EventsState> {
        self.shared.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// A stream's start: the whole fleet as of delta `seq` (JSON, with `seq` in it), after
    /// which the stream sends the deltas from `seq + 1` on.
    pub fn start(&self, fleet: &Fleet) -> (u64, String, watch::Receiver<u64>) {
        let rx = self.seq.subscribe();
        let mut st = self.lock();
        let brief = st
            .brief
            .get_or_insert_with(|| Arc::new(fleet.brief()))
            .clone();
        let seq = st.seq;
        drop(st);
        let mut v = serde_json::to_value(&*brief).unwrap_or_default();
        v["seq"] = seq.into();
        (seq, v.to_string(), rx)
    }

    /// The deltas after `seq`, in order; none if the stream is too far behind (it then starts
    /// again with the whole fleet).
    pub fn since(&self, seq: u64) -> Option<Vec<(u64, Arc<str>)>> {
        let st = self.lock();
        if st.seq == seq {
            return Some(Vec::new());
        }
        let first = st.recent.front()?.0;
        if first > seq + 1 {
            return None;
        }
        Some(
            st.recent
                .iter()
                .filter(|(s, _)| *s > seq)
                .cloned()
                .collect(),
        )
    }

    /// Takes the next delta, if a page is open.
    fn tick(&self, fleet: &Fleet) {
        if self.seq.receiver_count() == 0 {
            // Nobody reads: the next page starts from a brief of its own time.
            self.lock().brief = None;
            return;
        }
        let brief = Arc::new(fleet.brief());
        let mut st = self.lock();
        let Some(before) = st.brief.replace(brief.clone()) else {
            return;
        };
        let seq = st.seq + 1;
        let delta = brief.delta(&before, seq);
        match serde_json::to_string(&delta) {
            Ok(text) => {
                st.recent.push_back((seq, Arc::from(text)));
                while st.recent.len() > DELTAS_KEPT {
                    st.recent.pop_front();
                }
                st.seq = seq;
                drop(st);
                let _ = self.seq.send(seq);
            }
            Err(e) => tracing::error!(cause = %e, "fleet delta does not serialise"),
        }
    }
}

/// Takes the fleet's delta once a second for the open pages (none open: nothing done).
async fn serialise_fleet(
    fleet: Arc<Fleet>,
    events: Arc<FleetEvents>,
    mut stop: watch::Receiver<bool>,
) {
    let mut tick = tokio::time::interval(Duration::from_secs(1));
    loop {
        tokio::select! {
            _ = tick.tick() => {}
            _ = stop.changed() => return,
        }
        events.tick(&fleet);
    }
}
