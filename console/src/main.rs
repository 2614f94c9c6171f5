//! `triax-console`: the operators' console. Parses flags, joins Zenoh, binds the page's address
//! and hands over to [`triax_console::serve`] until Ctrl-C.
//!
//! ```text
//! triax-console                                         # every building found, page on 127.0.0.1:9760
//! triax-console --connect tcp/site-router:7447 --zenoh-mode client --buildings hq,annex
//! triax-console --listen localhost:9760                 # a name is resolved (loopback only)
//! triax-console --listen 0.0.0.0:9760 --allow-remote    # logins only with operator accounts
//! printf '%s\n' "$PASSWORD" | triax-console operator add alice --role operate
//! triax-console operator list
//! ```

use std::time::Duration;

use anyhow::Context;
use clap::Parser;
use triax_console::{ConsoleError, ConsoleOptions, DEFAULT_LISTEN};
use triax_net::ZenohArgs;
use triax_protocol::signing::TrustedKeys;
use triax_protocol::BuildingId;

/// The operators' console: the fleet, each sensor's corrected stream with its uncertainty band,
/// and the alerts, in a browser. Reads only; never publishes.
#[derive(Debug, Parser)]
#[command(name = "triax-console", version)]
// Here `--listen` is the page's address; Zenoh's own listen endpoint is `--zenoh-listen`.
#[command(mut_arg("listen", |a| a
    .long("zenoh-listen")
    .env("TRIAX_CONSOLE_ZENOH_LISTEN")
    .help("Zenoh endpoint to listen on, e.g. tcp/127.0.0.1:7448 (repeat or comma-separate). \
           Default: none, the console only connects (--connect, or multicast scouting), unless \
           a --zenoh-config file lists listen endpoints")))]
struct Cli {
    #[command(subcommand)]
    command: Option<Command>,
    #[command(flatten)]
    zenoh: ZenohArgs,
    /// Address of the page (HTTP), HOST:PORT with an IP address or a name (localhost:9760). A
    /// non-loopback address needs --allow-remote.
    #[arg(id = "http_listen", long = "listen", value_name = "ADDR", env = "TRIAX_CONSOLE_LISTEN", default_value = DEFAULT_LISTEN)]
    http_listen: String,
    /// Serve on a non-loopback address. Without operator accounts the console has NO
    /// authentication: anyone who reaches the port sees every building it sees.
    #[arg(long)]
    allow_remote: bool,
    /// The operators' accounts (NAME ROLE HASH a line; written by `triax-console operator
    /// add`). Once it holds an account, every page needs a login. Default: operators in the
    /// state directory.
    #[arg(
        long,
        value_name = "FILE",
        env = "TRIAX_CONSOLE_OPERATORS_FILE",
        global = true
    )]
    operators_file: Option<std::path::PathBuf>,
    /// A request header set by a reverse proxy in front of the console to the logged-in
    /// operator's name (e.g. X-Remote-User); the role is the account's of that name in the
    /// operators file, else view. Trusted as sent: only with the console on loopback behind
    /// that proxy.
    #[arg(long, value_name = "NAME", env = "TRIAX_CONSOLE_IDENTITY_HEADER")]
    identity_header: Option<String>,
    /// Notifications: a TOML file of channels (webhook, SMTP) and per-building rotas (README,
    /// "Notifications"). Default: none are sent.
    #[arg(long, value_name = "FILE", env = "TRIAX_CONSOLE_NOTIFY_CONFIG")]
    notify_config: Option<std::path::PathBuf>,
    /// The site's time zone, an IANA name (Europe/Zurich): the page offers its local time
    /// beside UTC, and quiet hours and rota shifts of notifications are in it. Default: UTC.
    #[arg(long, value_name = "ZONE", env = "TRIAX_CONSOLE_TIME_ZONE")]
    time_zone: Option<String>,
    /// Buildings to watch (comma-separated); default: every building whose gateway answers a
    /// status query or sends a heartbeat or an alert.
    #[arg(long, env = "TRIAX_CONSOLE_BUILDINGS", value_delimiter = ',')]
    buildings: Vec<BuildingId>,
    /// Seconds between status polls of the gateways.
    #[arg(long, default_value_t = 2.0)]
    status_interval_s: f64,
    /// Warn this many days before a calibration record's valid_until.
    #[arg(long, default_value_t = 30.0)]
    expiry_warning_days: f64,
    /// An alerting service's public key, 64 hex characters (repeatable, or comma-separated):
    /// only alerts it signed are shown as verdicts; any other is shown as unverified.
    #[arg(long, env = "TRIAX_TRUSTED_ALERT_KEYS", value_delimiter = ',')]
    trusted_alert_key: Vec<String>,
    /// A file holding one such key, e.g. the service's triax-alert.key.pub (repeatable).
    #[arg(long, value_name = "FILE")]
    trusted_alert_key_file: Vec<std::path::PathBuf>,
    /// A building's gateway key, BUILDING=KEY with KEY 64 hex characters or the file holding
    /// them (the gateway's triax-gateway-<building>.key.pub); repeatable, or comma-separated.
    /// With any, only keyed buildings are watched and only what their gateway signed or sealed
    /// is shown (heartbeats, status, live batches, tilt, history, exports); the rest is counted
    /// and dropped (PROTOCOL.md §6). Default: none, everything is taken on trust.
    #[arg(
        long,
        value_name = "BUILDING=KEY",
        env = "TRIAX_CONSOLE_GATEWAY_KEYS",
        value_delimiter = ','
    )]
    gateway_key: Vec<String>,
    /// Directory of the console's own state: the alert log (alerts.jsonl), which keeps the
    /// alerts received, their acknowledgements and the silences across restarts, the
    /// annotations (annotations.jsonl) and the operators' accounts (operators). Default:
    /// $XDG_STATE_HOME/triax-console, or ~/.local/state/triax-console.
    #[arg(
        long,
        value_name = "DIR",
        env = "TRIAX_CONSOLE_STATE_DIR",
        conflicts_with = "no_state",
        global = true
    )]
    state_dir: Option<std::path::PathBuf>,
    /// Keep the alert log and annotations in memory only: they start empty and are lost on exit.
    #[arg(long, global = true)]
    no_state: bool,
    /// Alerts the log keeps at most (unverified ones are dropped first).
    #[arg(long, default_value_t = triax_console::alertlog::DEFAULT_MAX_ALERTS)]
    max_logged_alerts: usize,
    /// Days the log keeps an alert.
    #[arg(long, default_value_t = 90.0)]
    alert_retention_days: f64,
    /// Log filter (tracing env-filter syntax).
    #[arg(long, env = "TRIAX_LOG", default_value = "info")]
    log: String,
}

#[derive(Debug, clap::Subcommand)]
enum Command {
    /// Manage the operators' accounts (the operators file) instead of serving.
    Operator {
        #[command(subcommand)]
        action: OperatorAction,
    },
}

#[derive(Debug, clap::Subcommand)]
enum OperatorAction {
    /// Adds an account, or replaces its role and password. The password (at least 10
    /// characters) is read as one line from standard input.
    Add {
        /// Letters, digits and . _ @ -, at most 64 characters.
        name: String,
        /// view (sees everything), operate (also acknowledges, silences, annotates) or admin
        /// (also clears a field-health latch, removes anyone's annotation).
        #[arg(long, value_parser = ["view", "operate", "admin"])]
        role: String,
        /// No password: an account that only the reverse proxy's identity header can name
        /// (--identity-header), for its role.
        #[arg(long)]
        proxy_only: bool,
    },
    /// Removes an account; its sessions end at their next request.
    Remove { name: String },
    /// Lists the accounts and their roles.
    List,
}

/// The operators file: `--operators-file`, or `operators` in the state directory.
fn operators_file(cli: &Cli) -> anyhow::Result<Option<std::path::PathBuf>> {
    if let Some(f) = &cli.operators_file {
        return Ok(Some(f.clone()));
    }
    Ok(state_dir(cli)?.map(|d| d.join(triax_console::operators::FILE_NAME)))
}

fn operator_command(cli: &Cli, action: &OperatorAction) -> anyhow::Result<()> {
    use triax_console::operators::{self, Account, Role};
    let path = operators_file(cli)?.context(
        "no operators file: give --operators-file FILE or --state-dir DIR (not --no-state)",
    )?;
    let mut accounts = operators::read_accounts(&path)?;
    match action {
        OperatorAction::Add {
            name,
            role,
            proxy_only,
        } => {
            operators::check_name(name).map_err(|e| anyhow::anyhow!("operator {name:?}: {e}"))?;
            let role = Role::parse(role).context("--role")?;
            let hash = if *proxy_only {
                None
            } else {
                use std::io::{BufRead, IsTerminal};
                if std::io::stdin().is_terminal() {
                    eprint!("password for {name} (echoed; or pipe it in): ");
                }
                let mut line = String::new();
                std::io::stdin()
                    .lock()
                    .read_line(&mut line)
                    .context("reading the password from standard input")?;
                let password = line.trim_end_matches(['\r', '\n']);
                Some(operators::hash_password(password)?)
            };
            let account = Account {
                name: name.clone(),
                role,
                hash,
            };
            match accounts.iter_mut().find(|a| a.name == *name) {
                Some(a) => *a = account,
                None => accounts.push(account),
            }
            operators::write_accounts(&path, &accounts)?;
            println!("operator {name} ({}) in {}", role.name(), path.display());
        }
        OperatorAction::Remove { name } => {
            let before = accounts.len();
            accounts.retain(|a| a.name != *name);
            anyhow::ensure!(
                accounts.len() < before,
                "no operator {name:?} in {}",
                path.display()
            );
            operators::write_accounts(&path, &accounts)?;
            println!("operator {name} removed from {}", path.display());
        }
        OperatorAction::List => {
            for a in &accounts {
                println!(
                    "{} {}{}",
                    a.name,
                    a.role.name(),
                    if a.hash.is_none() {
                        " (proxy only)"
                    } else {
                        ""
                    }
                );
            }
        }
    }
    Ok(())
}

fn seconds(flag: &str, s: f64) -> anyhow::Result<Duration> {
    Duration::try_from_secs_f64(s)
        .ok()
        .filter(|d| !d.is_zero())
        .with_context(|| format!("{flag} {s} is not a positive number"))
}

/// The alerting keys of `--trusted-alert-key` and `--trusted-alert-key-file`, each named when bad.
/// `--gateway-key BUILDING=KEY`, as a consumer's `[gateways]` table.
fn gateway_keys(
    cli: &Cli,
) -> anyhow::Result<Option<std::sync::Arc<triax_protocol::provenance::GatewayKeys>>> {
    let mut table = std::collections::BTreeMap::new();
    for entry in &cli.gateway_key {
        let (building, key) = entry
            .split_once('=')
            .with_context(|| format!("--gateway-key {entry:?}: not BUILDING=KEY"))?;
        anyhow::ensure!(
            table.insert(building.to_owned(), key.to_owned()).is_none(),
            "--gateway-key: building {building} given twice"
        );
    }
    if table.is_empty() {
        return Ok(None);
    }
    // Errors name the flag and the building: `--gateway-key.hq: cannot read …`.
    let keys = triax_net::keys::gateway_keys("--gateway-key", &table)
        .map_err(|e| anyhow::anyhow!("{e}"))?;
    Ok(Some(std::sync::Arc::new(keys)))
}

fn trusted_alert_keys(cli: &Cli) -> anyhow::Result<TrustedKeys> {
    let mut texts: Vec<(String, String)> = cli
        .trusted_alert_key
        .iter()
        .map(|k| ("--trusted-alert-key".to_owned(), k.clone()))
        .collect();
    for f in &cli.trusted_alert_key_file {
        let text = std::fs::read_to_string(f)
            .with_context(|| format!("--trusted-alert-key-file {}", f.display()))?;
        texts.push((format!("--trusted-alert-key-file {}", f.display()), text));
    }
    let hex: Vec<&str> = texts.iter().map(|(_, t)| t.as_str()).collect();
    TrustedKeys::from_hex(&hex).map_err(|(i, e)| anyhow::anyhow!("{}: {e}", texts[i].0))
}

/// `--state-dir`, or the default under the user's state directory.
fn state_dir(cli: &Cli) -> anyhow::Result<Option<std::path::PathBuf>> {
    if cli.no_state {
        return Ok(None);
    }
    if let Some(d) = &cli.state_dir {
        return Ok(Some(d.clone()));
    }
    let base = match (std::env::var_os("XDG_STATE_HOME"), std::env::var_os("HOME")) {
        (Some(x), _) if !x.is_empty() => std::path::PathBuf::from(x),
        (_, Some(h)) if !h.is_empty() => std::path::PathBuf::from(h).join(".local/state"),
        _ => anyhow::bail!(
            "no --state-dir given and neither XDG_STATE_HOME nor HOME is set: give \
             --state-dir DIR, or --no-state to keep alerts in memory only"
        ),
    };
    Ok(Some(base.join("triax-console")))
}

#[tokio::main]
async fn main() -> anyhow::Result<()> {
    let cli = Cli::parse();
    if let Some(Command::Operator { action }) = &cli.command {
        return operator_command(&cli, action);
    }
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_new(&cli.log)
                .context("--log is not a valid filter")?,
        )
        .init();
    let options = ConsoleOptions {
        buildings: cli.buildings.clone(),
        status_interval: seconds("--status-interval-s", cli.status_interval_s)?,
        expiry_warning: seconds("--expiry-warning-days", cli.expiry_warning_days * 86_400.0)?,
        allow_remote: cli.allow_remote,
        trusted_alert_keys: trusted_alert_keys(&cli)?,
        gateway_keys: gateway_keys(&cli)?,
        state_dir: state_dir(&cli)?,
        max_logged_alerts: cli.max_logged_alerts,
        alert_retention: seconds(
            "--alert-retention-days",
            cli.alert_retention_days * 86_400.0,
        )?,
        operators_file: operators_file(&cli)?,
        identity_header: cli.identity_header.clone(),
        notify: cli
            .notify_config
            .as_deref()
            .map(triax_console::notify::Config::load)
            .transpose()?,
        time_zone: cli
            .time_zone
            .as_deref()
            .map(triax_console::SiteTimeZone::get)
            .transpose()
            .context("--time-zone")?,
        ..ConsoleOptions::default()
    };
    // Listening nowhere unless asked: the console only reads, so it has no reason to accept
    // Zenoh connections, and a listening peer lets whoever reaches it publish into its session.
    let config =
        triax_net::outbound_config(&cli.zenoh.settings()).context("command-line Zenoh options")?;
    let listener = match triax_console::bind(&cli.http_listen, cli.allow_remote).await {
        Err(ConsoleError::NotLoopback { addr }) => anyhow::bail!(
            "--listen {} is not a loopback address ({addr}); the console has no \
             authentication. Add --allow-remote to serve it anyway, or reach it through an SSH \
             tunnel.",
            cli.http_listen
        ),
        r => r.with_context(|| format!("binding --listen {}", cli.http_listen))?,
    };
    let addr = listener.local_addr().context("the page's address")?;
    let has_accounts = options
        .operators_file
        .as_deref()
        .map(triax_console::operators::read_accounts)
        .transpose()
        .context("--operators-file")?
        .is_some_and(|a| !a.is_empty());
    if !addr.ip().is_loopback() && options.identity_header.is_some() {
        eprintln!(
            "WARNING: --identity-header is trusted as sent, and the console serves on {addr}: \
             anyone who reaches this port can name themselves any operator. Serve on loopback \
             behind the proxy that sets it."
        );
    }
    if !addr.ip().is_loopback() && !has_accounts && options.identity_header.is_none() {
        eprintln!(
            "WARNING: the console serves on {addr} with NO AUTHENTICATION: anyone who can reach \
             this port sees every building, sensor and alert it sees. Put it behind a firewall, \
             a VPN or an authenticating proxy."
        );
    }
    let session = zenoh::open(config)
        .await
        .map_err(|e| anyhow::anyhow!("joining Zenoh: {e}"))?;
    println!("triax-console: {}", triax_console::url(addr));
    triax_console::serve(session.clone(), listener, options, async {
        // If the signal handler cannot be installed, run until killed rather than not at all.
        if tokio::signal::ctrl_c().await.is_err() {
            std::future::pending::<()>().await;
        }
    })
    .await
    .context("console")?;
    let _ = session.close().await;
    Ok(())
}
