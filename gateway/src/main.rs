//! `triax-gateway`: the building gateway service. Parses flags, installs logging, and hands
//! over to the library ([`triax_gateway::run`]).
//!
//! ```text
//! triax-gateway                          # serve with defaults (building `hq`)
//! triax-gateway -c gateway.toml          # serve with a config file
//! triax-gateway store list               # inspect the calibration store (gateway stopped)
//! ```
//!
//! The demo building is a program of its own, `triax-demo`.

use anyhow::Context;
use clap::Parser;
use triax_calibration_store::cli::StoreCommand;
use triax_calibration_store::Store;
use triax_gateway::ConfigArgs;

/// Corrects the Zenoh sensor streams of one building in real time, with tagged uncertainty.
#[derive(Debug, Parser)]
#[command(name = "triax-gateway", version)]
struct Cli {
    #[command(flatten)]
    config: ConfigArgs,
    /// Log filter (tracing env-filter syntax); default `info`.
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
    triax_gateway::init_logging(cli.log.as_deref().unwrap_or("info"))
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
    runtime.block_on(triax_gateway::run(config, shutdown_signal()))?;
    Ok(())
}
