//! `triax-demo`: the demo building on one machine: the gateway for building `demo` with an
//! embedded Zenoh peer, simulated sensor nodes, a live summary, and the operators' console
//! on it (README, "Quick start").
//!
//! ```text
//! triax-demo                         # until Ctrl-C; console on http://127.0.0.1:9760/
//! triax-demo --duration-s 20         # 20 s, then fails unless 90 % of samples lie within k = 2
//! triax-demo --sensors 8 --no-console
//! ```

use std::time::Duration;

use anyhow::Context;
use clap::Parser;
use triax_demo::DemoOptions;
use triax_gateway::ConfigArgs;
use triax_net::{ZenohMode, ZenohSettings};
use triax_protocol::BuildingId;

/// Runs a demo building: the gateway, simulated sensor nodes, a live summary and the console.
#[derive(Debug, Parser)]
#[command(name = "triax-demo", version)]
struct Cli {
    /// The gateway's settings; the demo sets its building, name, store, history path and Zenoh
    /// endpoints itself.
    #[command(flatten)]
    config: ConfigArgs,
    /// Calibrated accelerometers in the demo (plus an inclinometer and an uncalibrated node).
    #[arg(long, default_value_t = 4)]
    sensors: usize,
    /// Stop after this many seconds, then fail unless 90 % of calibrated samples lie within
    /// k = 2 of the truth (default: run until Ctrl-C).
    #[arg(long)]
    duration_s: Option<f64>,
    /// Address of the operators' console the demo starts (loopback only).
    #[arg(long, default_value = triax_console::DEFAULT_LISTEN)]
    console_listen: std::net::SocketAddr,
    /// Start the demo without the console.
    #[arg(long)]
    no_console: bool,
    /// Log filter (tracing env-filter syntax); default `warn`.
    #[arg(long, env = "TRIAX_LOG")]
    log: Option<String>,
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
    triax_gateway::init_logging(cli.log.as_deref().unwrap_or("warn"))
        .context("--log is not a valid filter")?;
    let config = cli.config.load().context("configuration refused")?;
    let duration = match cli.duration_s {
        None => None,
        Some(s) => Some(
            Duration::try_from_secs_f64(s)
                .ok()
                .filter(|d| !d.is_zero())
                .with_context(|| format!("--duration-s {s} is not a positive number of seconds"))?,
        ),
    };
    // Zenoh needs the multi-thread runtime.
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .context("starting the tokio runtime")?;
    runtime.block_on(async {
        let mut opts = DemoOptions {
            sensors: cli.sensors,
            duration,
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
        let report = triax_demo::run(config, opts, shutdown_signal()).await;
        if let Some(c) = console {
            c.stop().await?;
        }
        report?;
        Ok(())
    })
}
