//! `triax-gateway`: the building gateway service. Parses flags, installs logging, and hands
//! over to the library ([`triax_gateway::run`], or the demo).
//!
//! ```text
//! triax-gateway                          # serve with defaults (building `hq`)
//! triax-gateway -c gateway.toml          # serve with a config file
//! triax-gateway --demo                   # an embedded building with simulated sensors, and
//!                                        # the operators' console on http://127.0.0.1:9760/
//! triax-gateway --demo --demo-duration-s 20
//! triax-gateway store list               # inspect the calibration store (gateway stopped)
//! ```

use std::time::Duration;

use anyhow::Context;
use clap::Parser;
use triax_calibration_store::cli::StoreCommand;
use triax_calibration_store::Store;
use triax_gateway::demo::{self, DemoOptions};
use triax_gateway::ConfigArgs;
use triax_net::{ZenohMode, ZenohSettings};
use triax_protocol::BuildingId;

/// Corrects the Zenoh sensor streams of one building in real time, with tagged uncertainty.
#[derive(Debug, Parser)]
#[command(name = "triax-gateway", version)]
struct Cli {
    #[command(flatten)]
    config: ConfigArgs,
    /// Run an embedded demo building: the gateway, simulated sensor nodes, a live summary.
    #[arg(long)]
    demo: bool,
    /// Calibrated accelerometers in the demo (plus an inclinometer and an uncalibrated node).
    #[arg(long, default_value_t = 4, requires = "demo")]
    demo_sensors: usize,
    /// Stop the demo after this many seconds (default: run until Ctrl-C).
    #[arg(long, requires = "demo")]
    demo_duration_s: Option<f64>,
    /// Address of the operators' console the demo starts (loopback only).
    #[arg(long, default_value = triax_console::DEFAULT_LISTEN, requires = "demo")]
    console_listen: std::net::SocketAddr,
    /// Start the demo without the console.
    #[arg(long, requires = "demo")]
    no_console: bool,
    /// Log filter (tracing env-filter syntax); default `info`, `warn` in the demo.
    #[arg(long, env = "TRIAX_LOG")]
    log: Option<String>,
    #[command(subcommand)]
    command: Option<Command>,
}

#[derive(Debug, clap::Subcommand)]
enum Command {
    /// Inspect, back up and restore the calibration store (while the gateway is stopped).
    Store {
        #[command(subcommand)]
        command: StoreCommand,
    },
}

/// The operators' console on the demo building: its own Zenoh session, connected to the
/// demo's gateway like any client.
struct DemoConsole {
    url: String,
    stop: tokio::sync::oneshot::Sender<()>,
    task: tokio::task::JoinHandle<anyhow::Result<()>>,
}

impl DemoConsole {
    async fn start(endpoint: &str, listen: std::net::SocketAddr) -> anyhow::Result<DemoConsole> {
        anyhow::ensure!(
            listen.ip().is_loopback(),
            "--console-listen {listen} is not a loopback address: the console has no authentication \
             (run triax-console --allow-remote for that)"
        );
        let listener = tokio::net::TcpListener::bind(listen).await.with_context(|| {
            format!("the console cannot listen on {listen}: choose another --console-listen, or --no-console")
        })?;
        let url = triax_console::url(listener.local_addr().context("the console's address")?);
        // Listening nowhere: the console only reads from the demo's gateway, and a listening
        // peer would let anyone who reaches it publish (forged alerts) into its session.
        let zenoh = triax_net::outbound_config(&ZenohSettings::loopback(
            ZenohMode::Peer,
            vec![],
            vec![endpoint.to_owned()],
        ))
        .context("the console's Zenoh configuration")?;
        let options = triax_console::ConsoleOptions {
            // A literal of valid characters.
            buildings: vec![BuildingId::new("demo").expect("literal building id is valid")],
            ..triax_console::ConsoleOptions::default()
        };
        let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
        let task = tokio::spawn(async move {
            // Opened here: the session waits for the demo's gateway to listen.
            let session = zenoh::open(zenoh)
                .await
                .map_err(|e| anyhow::anyhow!("the console's Zenoh session: {e}"))?;
            triax_console::serve(session.clone(), listener, options, async {
                let _ = stopped.await;
            })
            .await?;
            let _ = session.close().await;
            Ok(())
        });
        Ok(DemoConsole { url, stop, task })
    }

    async fn stop(self) -> anyhow::Result<()> {
        let _ = self.stop.send(());
        match tokio::time::timeout(Duration::from_secs(5), self.task).await {
            Ok(Ok(r)) => r,
            Ok(Err(e)) => Err(anyhow::anyhow!("the console failed: {e}")),
            Err(_) => Err(anyhow::anyhow!("the console did not stop in 5 s")),
        }
    }
}

/// Completes on SIGINT or SIGTERM.
async fn shutdown_signal() {
    #[cfg(unix)]
    {
        use tokio::signal::unix::{signal, SignalKind};
        match signal(SignalKind::terminate()) {
            Ok(mut term) => {
                tokio::select! {
                    _ = tokio::signal::ctrl_c() => {}
                    _ = term.recv() => {}
                }
            }
            Err(e) => {
                tracing::warn!(cause = %e, "no SIGTERM handler; Ctrl-C only");
                let _ = tokio::signal::ctrl_c().await;
            }
        }
    }
    #[cfg(not(unix))]
    {
        let _ = tokio::signal::ctrl_c().await;
    }
}

fn main() -> anyhow::Result<()> {
    // Before any thread exists: the allocator's settings are process-wide.
    triax_gateway::memory::configure_allocator();
    let cli = Cli::parse();
    let default_log = if cli.demo { "warn" } else { "info" };
    triax_gateway::init_logging(cli.log.as_deref().unwrap_or(default_log))
        .context("--log is not a valid filter")?;

    let config = cli.config.load().context("configuration refused")?;

    if let Some(Command::Store { command }) = &cli.command {
        let store = Store::open(&config.store_path)
            .with_context(|| format!("opening {}", config.store_path.display()))?;
        triax_calibration_store::cli::run(&store, command, &mut std::io::stdout().lock())?;
        return Ok(());
    }

    // Zenoh needs the multi-thread runtime.
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .context("starting the tokio runtime")?;
    runtime.block_on(async {
        if cli.demo {
            let mut opts = DemoOptions {
                sensors: cli.demo_sensors,
                duration: match cli.demo_duration_s {
                    None => None,
                    Some(s) => Some(
                        Duration::try_from_secs_f64(s)
                            .ok()
                            .filter(|d| !d.is_zero())
                            .with_context(|| {
                                format!("--demo-duration-s {s} is not a positive number of seconds")
                            })?,
                    ),
                },
                ..DemoOptions::default()
            };
            let console = if cli.no_console {
                None
            } else {
                let port = triax_net::free_loopback_port()
                    .context("a loopback port for the demo's gateway")?;
                let endpoint = format!("tcp/127.0.0.1:{port}");
                let console = DemoConsole::start(&endpoint, cli.console_listen).await?;
                println!("Triax console: {}", console.url);
                opts.endpoint = Some(endpoint);
                opts.banner = Some(format!("console: {}", console.url));
                Some(console)
            };
            let report = demo::run(config, opts, shutdown_signal()).await;
            if let Some(c) = console {
                c.stop().await?;
            }
            report?;
        } else {
            triax_gateway::run(config, shutdown_signal()).await?;
        }
        Ok(())
    })
}
