//! `triax-events`: reads the configuration, installs logging and runs the event-report service
//! until Ctrl-C.
//!
//! ```text
//! triax-events --config events.toml
//! triax-events --config events.toml --connect tcp/127.0.0.1:7447 --no-multicast-scouting
//! ```

use std::path::PathBuf;

use anyhow::Context;
use clap::Parser;
use triax_events::Config;
use triax_net::ZenohArgs;

#[derive(Debug, Parser)]
#[command(name = "triax-events", version, about)]
struct Args {
    /// TOML configuration: per building its sensors (floor, height, mounting), detection,
    /// processing and limits (README, "Event reports").
    #[arg(long, short, env = "TRIAX_EVENTS_CONFIG")]
    config: PathBuf,
    #[command(flatten)]
    zenoh: ZenohArgs,
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
    args.zenoh.apply_to(&mut config.zenoh);
    config
        .zenoh
        .validate()
        .context("command-line Zenoh options")?;
    tracing::info!(buildings = config.buildings.len(), "starting");
    triax_events::run(config, async {
        // If the signal handler cannot be installed, run until killed rather than not at all.
        if tokio::signal::ctrl_c().await.is_err() {
            std::future::pending::<()>().await;
        }
    })
    .await
    .context("event-report service")?;
    Ok(())
}
