//! `triax-modes`: reads the configuration, installs logging and runs the building-modes service
//! until Ctrl-C.
//!
//! ```text
//! triax-modes --config modes.toml
//! triax-modes --config modes.toml --connect tcp/127.0.0.1:7447 --no-multicast-scouting
//! triax-modes export --record state/hq --out hq-modes.parquet
//! ```
//!
//! `export` writes a building's modes record (every identification kept under
//! `<state_dir>/<building>/`) as Parquet, one row per mode per window
//! ([`triax_client::modes_parquet`]); it needs no configuration and no Zenoh.

use std::path::{Path, PathBuf};

use anyhow::Context;
use clap::Parser;
use triax_modes::Config;
use triax_net::ZenohArgs;

#[derive(Debug, Parser)]
#[command(name = "triax-modes", version, about)]
struct Args {
    /// TOML configuration: per building its sensors (floor, height, mounting), window, tracker.
    #[arg(long, short, env = "TRIAX_MODES_CONFIG")]
    config: Option<PathBuf>,
    #[command(flatten)]
    zenoh: ZenohArgs,
    #[command(subcommand)]
    command: Option<Command>,
}

#[derive(Debug, clap::Subcommand)]
enum Command {
    /// Writes a building's modes record as Parquet, one row per mode per window.
    Export {
        /// The building's record directory: `<state_dir>/<building>`.
        #[arg(long)]
        record: PathBuf,
        /// The Parquet file to write (replaced whole, or left as it was on failure).
        #[arg(long)]
        out: PathBuf,
    },
}

/// Writes the record in `record` to `out`, whole or not at all; returns the rows written.
fn export(record: &Path, out: &Path) -> anyhow::Result<u64> {
    let windows = triax_modes::record::read(record)
        .with_context(|| format!("reading the record in {}", record.display()))?;
    anyhow::ensure!(
        !windows.is_empty(),
        "no identification in {} (expected {} or {})",
        record.display(),
        triax_modes::record::RECORD_FILE,
        triax_modes::record::ROTATED_FILE
    );
    // A window identified twice (a crash between the record and the state) counts once: the
    // last line of a window_start_ns is the one that stands.
    let mut by_start = std::collections::BTreeMap::new();
    for w in windows {
        by_start.insert(w.window_start_ns, w);
    }
    let dir = match out.parent() {
        Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
        _ => PathBuf::from("."),
    };
    let tmp = tempfile::NamedTempFile::new_in(&dir)
        .with_context(|| format!("creating a file in {}", dir.display()))?;
    let mut writer = triax_client::modes_parquet::ModesParquetWriter::new(tmp.as_file())?;
    for w in by_start.values() {
        writer.push(w);
    }
    let rows = writer.finish()?;
    tmp.as_file().sync_all()?;
    tmp.persist(out)
        .with_context(|| format!("writing {}", out.display()))?;
    Ok(rows)
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
    if let Some(Command::Export { record, out }) = &args.command {
        let rows = export(record, out)?;
        println!("{rows} modes written to {}", out.display());
        return Ok(());
    }
    let path = args
        .config
        .context("--config (or TRIAX_MODES_CONFIG) is required to run the service")?;
    let mut config =
        Config::from_file(&path).with_context(|| format!("loading {}", path.display()))?;
    args.zenoh.apply_to(&mut config.zenoh);
    config
        .zenoh
        .validate()
        .context("command-line Zenoh options")?;
    tracing::info!(buildings = config.buildings.len(), "starting");
    triax_modes::run(config, async {
        // If the signal handler cannot be installed, run until killed rather than not at all.
        if tokio::signal::ctrl_c().await.is_err() {
            std::future::pending::<()>().await;
        }
    })
    .await
    .context("building-modes service")?;
    Ok(())
}
