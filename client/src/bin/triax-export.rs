//! `triax-export`: a building's history, read from its gateway over Zenoh, written to a file
//! for analysis tools.
//!
//! ```text
//! triax-export parquet --connect tcp/127.0.0.1:7447 --building hq --sensor acc-01 \
//!     --from 2026-11-24T00:00:00Z --to 2026-11-25T00:00:00Z --out acc-01.parquet
//! ```
//!
//! ```text
//! triax-export sds --connect tcp/127.0.0.1:7447 --building hq --out archive --records records/
//! ```
//!
//! The gateway answers from its history (PROTOCOL.md §5.1): each batch corrected with the
//! record in force at its time unless `--calibration latest` or a version number is given.

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::time::{Duration, Instant};

use anyhow::{bail, Context, Result};
use clap::Parser;
use time::format_description::well_known::Rfc3339;
use time::OffsetDateTime;
use triax_client::history::fetch;
use triax_client::mseed::SdsWriter;
use triax_client::parquet::ParquetWriter;
use triax_client::stationxml::stationxml;
use triax_client::HistoryRequest;
use triax_protocol::record::CalibrationRecord;
use triax_protocol::{from_json, BuildingId};

#[derive(Debug, Parser)]
#[command(
    version,
    about = "Export a Triax gateway's history (corrected samples) to a file"
)]
struct Args {
    #[command(subcommand)]
    format: Format,
}

#[derive(Debug, clap::Subcommand)]
enum Format {
    /// One row per sample: time, sensor, sequence, acceleration and uncertainty per axis (m/s²),
    /// coverage factor, flags, calibration version, mode (the schema is in the file's metadata
    /// and in README.md).
    Parquet(Export),
    /// miniSEED 2 day files in an SDS tree under --out, nine channels per sensor (axes in m/s²
    /// at location 00, their standard uncertainties at U0, the flags at Q0; README.md), and
    /// with --records a StationXML file beside them.
    Sds(Sds),
}

#[derive(Debug, clap::Args)]
struct Export {
    /// Zenoh endpoint of the gateway or of a router that reaches it (repeatable).
    #[arg(long, required = true)]
    connect: Vec<String>,
    /// Building whose gateway keeps the history.
    #[arg(long)]
    building: String,
    /// A sensor id, or `*` for every sensor of the building.
    #[arg(long, default_value = "*")]
    sensor: String,
    /// Batches whose first sample is at or after this time, RFC 3339 (e.g.
    /// 2026-11-24T00:00:00Z); default: the oldest kept.
    #[arg(long)]
    from: Option<String>,
    /// Batches whose first sample is before this time, RFC 3339; default: no bound.
    #[arg(long)]
    to: Option<String>,
    /// `in_force` (the record each batch was corrected with), `latest`, or a version number.
    #[arg(long, default_value = "in_force")]
    calibration: String,
    /// Output: the file (parquet, overwritten) or the SDS root directory (sds, appended to).
    #[arg(long)]
    out: PathBuf,
    /// Seconds one page of the history query may take.
    #[arg(long, default_value_t = 30.0)]
    timeout_s: f64,
}

#[derive(Debug, clap::Args)]
struct Sds {
    #[command(flatten)]
    export: Export,
    /// FDSN network code: 1 or 2 letters or digits.
    #[arg(long, default_value = "XX")]
    network: String,
    /// A sensor's station code, SENSOR=CODE (repeatable); default: the sensor id's letters and
    /// digits, upper case, first five.
    #[arg(long = "station", value_name = "SENSOR=CODE")]
    stations: Vec<String>,
    /// Calibration records (JSON files, or directories of them, not recursive) for the
    /// StationXML file `<out>/<NETWORK>.<building>.xml`, one epoch per version; none: no
    /// StationXML.
    #[arg(long = "records", value_name = "FILE|DIR")]
    records: Vec<PathBuf>,
}

fn time_ns(what: &str, v: &Option<String>) -> Result<Option<i64>> {
    v.as_deref()
        .map(|s| {
            let t = OffsetDateTime::parse(s, &Rfc3339)
                .with_context(|| format!("--{what} {s:?} is not an RFC 3339 time"))?;
            i64::try_from(t.unix_timestamp_nanos())
                .with_context(|| format!("--{what} {s:?} is out of range"))
        })
        .transpose()
}

/// The request and a session to the gateway, from the common arguments.
async fn connect(a: &Export) -> Result<(HistoryRequest, zenoh::Session)> {
    let building = BuildingId::new(&a.building)
        .map_err(|e| anyhow::anyhow!("--building {:?}: {e}", a.building))?;
    if !(a.timeout_s.is_finite() && a.timeout_s > 0.0) {
        bail!(
            "--timeout-s {} is not a positive number of seconds",
            a.timeout_s
        );
    }
    let request = HistoryRequest {
        building,
        sensors: a.sensor.clone(),
        from_ns: time_ns("from", &a.from)?,
        to_ns: time_ns("to", &a.to)?,
        from_seq: None,
        to_seq: None,
        calibration: Some(a.calibration.clone()),
    };
    let mut config = zenoh::Config::default();
    let endpoints = serde_json::to_string(&a.connect).context("--connect")?;
    for (k, v) in [
        ("mode", "\"client\"".to_owned()),
        ("connect/endpoints", endpoints),
        ("scouting/multicast/enabled", "false".to_owned()),
    ] {
        config
            .insert_json5(k, &v)
            .map_err(|e| anyhow::anyhow!("zenoh setting {k}: {e}"))?;
    }
    let session = zenoh::open(config)
        .await
        .map_err(|e| anyhow::anyhow!("cannot reach {:?}: {e}", a.connect))?;
    Ok((request, session))
}

#[tokio::main(flavor = "multi_thread", worker_threads = 2)]
async fn main() -> Result<()> {
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_env("TRIAX_LOG")
                .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("warn")),
        )
        .with_writer(std::io::stderr)
        .init();
    match Args::parse().format {
        Format::Parquet(a) => parquet(a).await,
        Format::Sds(a) => sds(a).await,
    }
}

async fn parquet(a: Export) -> Result<()> {
    let (request, session) = connect(&a).await?;
    let file = std::fs::File::create(&a.out)
        .with_context(|| format!("cannot create {}", a.out.display()))?;
    let mut writer = ParquetWriter::new(std::io::BufWriter::new(file))?;
    let started = Instant::now();
    let mut failed = None;
    let batches = fetch(
        &session,
        &request,
        Duration::from_secs_f64(a.timeout_s),
        &mut |r| {
            if failed.is_none() {
                if let Err(e) = writer.push(&r.batch) {
                    failed = Some(e);
                }
            }
        },
    )
    .await
    .context("history query")?;
    if let Some(e) = failed {
        return Err(e).with_context(|| format!("writing {}", a.out.display()));
    }
    let rows = writer
        .finish()
        .with_context(|| format!("writing {}", a.out.display()))?;
    let _ = session.close().await;
    eprintln!(
        "{batches} batches, {rows} samples written to {} in {:.2} s",
        a.out.display(),
        started.elapsed().as_secs_f64()
    );
    Ok(())
}

/// `--station SENSOR=CODE` arguments as a map.
fn station_overrides(args: &[String]) -> Result<BTreeMap<String, String>> {
    args.iter()
        .map(|s| match s.split_once('=') {
            Some((sensor, code)) if !sensor.is_empty() => {
                Ok((sensor.to_string(), code.to_string()))
            }
            _ => bail!("--station {s:?}: expected SENSOR=CODE"),
        })
        .collect()
}

/// Every record in the files and directories given, by name in the messages.
fn read_records(paths: &[PathBuf]) -> Result<Vec<CalibrationRecord>> {
    let mut files = Vec::new();
    for p in paths {
        if p.is_dir() {
            let mut in_dir: Vec<PathBuf> = std::fs::read_dir(p)
                .with_context(|| format!("--records {}", p.display()))?
                .filter_map(|e| e.ok().map(|e| e.path()))
                .filter(|f| f.extension().is_some_and(|x| x == "json"))
                .collect();
            in_dir.sort();
            files.extend(in_dir);
        } else {
            files.push(p.clone());
        }
    }
    files
        .iter()
        .map(|f| {
            let bytes = std::fs::read(f).with_context(|| format!("--records {}", f.display()))?;
            let r: CalibrationRecord =
                from_json(&bytes).with_context(|| format!("--records {}", f.display()))?;
            r.validate()
                .with_context(|| format!("--records {}", f.display()))?;
            Ok(r)
        })
        .collect()
}

async fn sds(a: Sds) -> Result<()> {
    let records = read_records(&a.records)?;
    let mut writer = SdsWriter::new(&a.export.out, &a.network, station_overrides(&a.stations)?)?;
    let (request, session) = connect(&a.export).await?;
    let started = Instant::now();
    let mut failed = None;
    let mut rates = BTreeMap::new();
    let batches = fetch(
        &session,
        &request,
        Duration::from_secs_f64(a.export.timeout_s),
        &mut |r| {
            if failed.is_none() {
                rates.insert(
                    r.batch.header.sensor_id.clone(),
                    r.batch.header.sample_rate_hz,
                );
                if let Err(e) = writer.push(&r.batch) {
                    failed = Some(e);
                }
            }
        },
    )
    .await
    .context("history query")?;
    let _ = session.close().await;
    if let Some(e) = failed {
        return Err(e.into());
    }
    let stations = writer.stations().clone();
    let files = writer.finish()?;
    let records_written: usize = files.values().sum();
    eprintln!(
        "{batches} batches as {records_written} miniSEED records in {} files under {} in {:.2} s",
        files.len(),
        a.export.out.display(),
        started.elapsed().as_secs_f64()
    );
    if !records.is_empty() {
        let path = a.export.out.join(format!(
            "{}.{}.xml",
            a.network.to_ascii_uppercase(),
            request.building
        ));
        let xml = stationxml(
            &a.network.to_ascii_uppercase(),
            &request.building,
            &stations,
            &rates,
            &records,
            OffsetDateTime::now_utc(),
        );
        std::fs::write(&path, xml).with_context(|| format!("writing {}", path.display()))?;
        eprintln!("StationXML: {}", path.display());
    }
    Ok(())
}
