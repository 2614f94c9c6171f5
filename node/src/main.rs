//! `triax-node`: a sensor node. Parses flags, opens the source and the Zenoh session, and hands
//! over to [`triax_node::run`] until SIGTERM, Ctrl-C or the end of a CSV source.
//!
//! ```text
//! triax-node --building hq --sensor acc-01 --source sim --buffer-dir /var/lib/triax-node
//! triax-node --building hq --sensor acc-01 --source adxl355:/dev/spidev0.0 --rate-hz 125 \
//!     --buffer-dir /var/lib/triax-node --connect tcp/gateway:7447
//! producer | triax-node --building hq --sensor acc-01 --source csv:- --buffer-dir buf
//! ```

use std::path::PathBuf;
use std::time::Duration;

use anyhow::Context;
use clap::Parser;
use triax_net::ZenohArgs;
use triax_node::adxl355::{Adxl355, Adxl355Source, Range};
use triax_node::spidev::{SpiBus, DEFAULT_SPEED_HZ};
use triax_node::{CsvSource, NodeConfig, RingConfig, SimSource, Source};
use triax_protocol::batch::MAX_SAMPLES;
use triax_protocol::{BuildingId, SensorId};

/// A Triax sensor node: reads an accelerometer, publishes raw batches on
/// triax/<building>/raw/<sensor>, and keeps every batch sent in an on-disk buffer that answers
/// triax/<building>/buffer/<sensor> queries.
#[derive(Debug, Parser)]
#[command(name = "triax-node", version)]
// The node reaches out (`outbound_config`): say so where the shared flag is described.
#[command(mut_arg("listen", |a| a
    .help("Zenoh endpoint to listen on, e.g. tcp/0.0.0.0:7447 (repeat or comma-separate). \
           Default: none, the node only connects (--connect, or multicast scouting), unless a \
           --zenoh-config file lists listen endpoints")))]
struct Cli {
    /// Building id (A-Z a-z 0-9 _ -).
    #[arg(long, env = "TRIAX_BUILDING")]
    building: BuildingId,
    /// Sensor id (A-Z a-z 0-9 _ -), unique in the lab's registry.
    #[arg(long, env = "TRIAX_SENSOR")]
    sensor: SensorId,
    /// Where samples come from: `sim` (simulated, in g), `csv:<path>` (`csv:-` for standard
    /// input; lines `vx,vy,vz` at --rate-hz, or `t_ns,vx,vy,vz`), or `adxl355:<spidev>` (e.g.
    /// adxl355:/dev/spidev0.0, outputs in g).
    #[arg(long, value_name = "SOURCE")]
    source: SourceSpec,
    /// Directory of the buffer (one per sensor; created if missing).
    #[arg(long, value_name = "DIR", env = "TRIAX_NODE_BUFFER_DIR")]
    buffer_dir: PathBuf,
    /// Output data rate, Hz. Default 100; 125 for adxl355, whose rates are 4000/2^k Hz.
    #[arg(long)]
    rate_hz: Option<f64>,
    /// Samples per batch (1 to 16384).
    #[arg(long, default_value_t = 10)]
    batch_samples: usize,
    /// Hours of batches the buffer keeps at least (up to 5 % more on disk).
    #[arg(long, default_value_t = 1.0)]
    buffer_hours: f64,
    /// Standard uncertainty of this node's clock against UTC, microseconds, as the node's
    /// time service states it (chrony: root dispersion + root delay / 2; a PTP servo: its
    /// offset's spread). Reported in the buffer's status.
    #[arg(long, default_value_t = 10_000.0)]
    clock_uncertainty_us: f64,
    /// Seconds between syncs of the buffer to disk (what a power cut may lose; a kill loses
    /// nothing).
    #[arg(long, default_value_t = 1.0)]
    sync_interval_s: f64,
    /// Seed of the simulated source's noise.
    #[arg(long, default_value_t = 1)]
    sim_seed: u64,
    /// ADXL355 measurement range, ±g: 2, 4 or 8.
    #[arg(long, value_enum, default_value = "2")]
    adxl355_range_g: RangeG,
    #[command(flatten)]
    zenoh: ZenohArgs,
    /// Log filter (tracing env-filter syntax).
    #[arg(long, env = "TRIAX_LOG", default_value = "info")]
    log: String,
}

#[derive(Debug, Clone, Copy, clap::ValueEnum)]
enum RangeG {
    #[value(name = "2")]
    G2,
    #[value(name = "4")]
    G4,
    #[value(name = "8")]
    G8,
}

#[derive(Debug, Clone)]
enum SourceSpec {
    Sim,
    Csv(String),
    Adxl355(PathBuf),
}

impl std::str::FromStr for SourceSpec {
    type Err = String;

    fn from_str(s: &str) -> Result<SourceSpec, String> {
        match s.split_once(':') {
            None if s == "sim" => Ok(SourceSpec::Sim),
            Some(("csv", p)) if !p.is_empty() => Ok(SourceSpec::Csv(p.to_owned())),
            Some(("adxl355", p)) if !p.is_empty() => Ok(SourceSpec::Adxl355(p.into())),
            _ => Err(format!(
                "{s:?} is not sim, csv:<path> (csv:- for standard input) or adxl355:<spidev device>"
            )),
        }
    }
}

fn open_source(cli: &Cli, rate_hz: f64) -> anyhow::Result<Box<dyn Source>> {
    Ok(match &cli.source {
        SourceSpec::Sim => Box::new(SimSource::new(rate_hz, cli.sim_seed)),
        SourceSpec::Csv(path) => Box::new(CsvSource::open(path, rate_hz)?),
        SourceSpec::Adxl355(dev) => {
            let bus = SpiBus::open(dev, DEFAULT_SPEED_HZ)?;
            let range = match cli.adxl355_range_g {
                RangeG::G2 => Range::G2,
                RangeG::G4 => Range::G4,
                RangeG::G8 => Range::G8,
            };
            let part = Adxl355::open(bus, range, rate_hz)
                .with_context(|| format!("ADXL355 on {}", dev.display()))?;
            Box::new(Adxl355Source::new(part))
        }
    })
}

fn positive(flag: &str, v: f64) -> anyhow::Result<f64> {
    anyhow::ensure!(
        v.is_finite() && v > 0.0,
        "{flag} {v} is not a positive number"
    );
    Ok(v)
}

/// Resolves at SIGTERM or Ctrl-C.
async fn stop_signal() {
    let term = async {
        match tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()) {
            Ok(mut s) => {
                s.recv().await;
            }
            Err(e) => {
                tracing::warn!(cause = %e, "cannot watch SIGTERM; stop with Ctrl-C");
                std::future::pending::<()>().await;
            }
        }
    };
    tokio::select! {
        _ = tokio::signal::ctrl_c() => {}
        () = term => {}
    }
}

#[tokio::main(flavor = "multi_thread", worker_threads = 2)]
async fn main() -> anyhow::Result<()> {
    let cli = Cli::parse();
    tracing_subscriber::fmt()
        .with_env_filter(tracing_subscriber::EnvFilter::try_new(&cli.log).context("--log")?)
        .with_writer(std::io::stderr)
        .init();

    let default_rate = match cli.source {
        SourceSpec::Adxl355(_) => 125.0,
        _ => 100.0,
    };
    let rate_hz = positive("--rate-hz", cli.rate_hz.unwrap_or(default_rate))?;
    anyhow::ensure!(
        (1..=MAX_SAMPLES).contains(&cli.batch_samples),
        "--batch-samples {} is outside 1..={MAX_SAMPLES}",
        cli.batch_samples
    );
    let buffer_hours = positive("--buffer-hours", cli.buffer_hours)?;
    let sync_interval_s = positive("--sync-interval-s", cli.sync_interval_s)?;
    anyhow::ensure!(
        cli.clock_uncertainty_us.is_finite() && cli.clock_uncertainty_us >= 0.0,
        "--clock-uncertainty-us {} is not a number ≥ 0",
        cli.clock_uncertainty_us
    );

    let source = open_source(&cli, rate_hz)?;
    let config = NodeConfig {
        building: cli.building.clone(),
        sensor: cli.sensor.clone(),
        batch_samples: cli.batch_samples,
        ring: RingConfig::for_span(
            cli.buffer_dir.clone(),
            cli.building.clone(),
            cli.sensor.clone(),
            buffer_hours * 3600.0,
            rate_hz,
            cli.batch_samples,
        ),
        clock_uncertainty_ns: cli.clock_uncertainty_us * 1e3,
        sync_interval: Duration::from_secs_f64(sync_interval_s),
        // About 100 s of batches at 10 a second.
        queue_batches: 1024,
    };

    let zenoh_config = triax_net::outbound_config(&cli.zenoh.settings())?;
    let session = zenoh::open(zenoh_config)
        .await
        .map_err(|e| anyhow::anyhow!("zenoh: {}", triax_net::zenoh_cause(&*e)))?;

    let summary = triax_node::run(config, source, session.clone(), stop_signal()).await;
    if let Err(e) = session.close().await {
        tracing::warn!(cause = %triax_net::zenoh_cause(&*e), "zenoh session close");
    }
    let summary = summary?;
    tracing::info!(
        first_sequence = ?summary.first_sequence,
        next_sequence = summary.next_sequence,
        numbered = summary.numbered,
        published = summary.published,
        publish_skipped = summary.publish_skipped,
        dropped = summary.dropped,
        source_ended = summary.source_ended,
        "node stopped, buffer flushed"
    );
    Ok(())
}
