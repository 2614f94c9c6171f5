//! `triax-alert`: reads the configuration, installs logging and runs the alerting service until
//! Ctrl-C.
//!
//! ```text
//! triax-alert --config alert.toml
//! triax-alert --config alert.toml --connect tcp/127.0.0.1:7447 --no-multicast-scouting
//! ```

use std::path::PathBuf;

use anyhow::Context;
use clap::Parser;
use triax_alert::config::{Config, ZenohMode};

#[derive(Debug, Parser)]
#[command(name = "triax-alert", version, about)]
struct Args {
    /// TOML configuration: thresholds per building and sensor, window, staleness.
    #[arg(long, short, env = "TRIAX_ALERT_CONFIG")]
    config: PathBuf,
    /// Zenoh mode, over the file's.
    #[arg(long, value_enum)]
    mode: Option<ZenohMode>,
    /// Zenoh endpoints to connect to (repeatable), replacing the file's.
    #[arg(long)]
    connect: Vec<String>,
    /// Zenoh endpoints to listen on (repeatable), replacing the file's.
    #[arg(long)]
    listen: Vec<String>,
    /// Turn off Zenoh multicast scouting.
    #[arg(long)]
    no_multicast_scouting: bool,
}

#[tokio::main]
async fn main() -> anyhow::Result<()> {
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info")),
        )
        .init();
    let args = Args::parse();
    let mut config = Config::from_file(&args.config)
        .with_context(|| format!("loading {}", args.config.display()))?;
    if args.mode.is_some() {
        config.zenoh.mode = args.mode;
    }
    if !args.connect.is_empty() {
        config.zenoh.connect = args.connect;
    }
    if !args.listen.is_empty() {
        config.zenoh.listen = args.listen;
    }
    if args.no_multicast_scouting {
        config.zenoh.multicast_scouting = Some(false);
    }
    tracing::info!(
        buildings = config.buildings.len(),
        watch_all_buildings = config.watch_all_buildings,
        window_s = config.settings.window_s,
        coverage_factor = config.settings.coverage_factor,
        "starting"
    );
    triax_alert::run(config, async {
        // If the signal handler cannot be installed, run until killed rather than not at all.
        if tokio::signal::ctrl_c().await.is_err() {
            std::future::pending::<()>().await;
        }
    })
    .await
    .context("alerting service")?;
    Ok(())
}
