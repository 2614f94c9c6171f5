//! `triax-export`: a building's history, read from its gateway over Zenoh, written to files for
//! analysis tools (Parquet; miniSEED in an SDS tree with StationXML).
//!
//! Everything that can be checked is checked before the first byte is written: the arguments,
//! the records, that a gateway of the building answers and keeps a history. The output then
//! appears whole or not at all: a Parquet file is written beside its target and renamed over it
//! once complete; an SDS export is staged inside the root and merged file by file
//! ([`crate::mseed`]). A failed or killed export leaves what was there before.
//!
//! Exit status ([`ExportError::exit_code`]): 0 written, 1 an error (named), 2 bad usage
//! (from the argument parser), 3 nothing in the range (no file written).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use time::format_description::well_known::Rfc3339;
use time::OffsetDateTime;
use triax_net::{ZenohArgs, ZenohMode};
use triax_protocol::messages::GatewayStatus;
use triax_protocol::record::CalibrationRecord;
use triax_protocol::{from_json, BuildingId, Key, SensorId};

use crate::history::{any_kept, fetch};
use crate::mseed::{MseedError, SdsWriter};
use crate::parquet::{ParquetExportError, ParquetWriter};
use crate::stationxml::{stationxml, StationXmlError};
use crate::HistoryRequest;

/// Exit status of an export that found nothing in its range.
pub const EXIT_EMPTY: u8 = 3;

/// What every subcommand's help ends with.
const AFTER_HELP: &str = "Zenoh: a client of the --connect endpoints unless --zenoh-mode or a \
    --zenoh-config file says otherwise; listening on no endpoint unless --listen or the file \
    names one.\n\nExit status: 0 written; 1 an error, named on standard error (nothing \
    written, any earlier output left as it was); 2 bad usage; 3 nothing kept in the range (no \
    file written).";

#[derive(Debug, clap::Parser)]
#[command(
    name = "triax-export",
    version,
    about = "Export a Triax gateway's history (corrected samples) to files",
    after_help = AFTER_HELP
)]
pub struct Cli {
    #[command(subcommand)]
    pub format: Format,
}

impl Cli {
    /// Parses command-line arguments, the program name first.
    pub fn try_from_args<I, T>(args: I) -> Result<Cli, clap::Error>
    where
        I: IntoIterator<Item = T>,
        T: Into<std::ffi::OsString> + Clone,
    {
        <Cli as clap::Parser>::try_parse_from(args)
    }
}

#[derive(Debug, clap::Subcommand)]
pub enum Format {
    /// One row per sample: time, sensor, sequence, acceleration and uncertainty per axis (m/s²),
    /// coverage factor, flags, calibration version, mode (the schema is in the file's metadata
    /// and in README.md).
    #[command(after_help = AFTER_HELP)]
    Parquet(Export),
    /// miniSEED 2 day files in an SDS tree under --out, nine channels per calibrated sensor
    /// (axes in m/s² at location 00, their standard uncertainties at U0, the flags at Q0;
    /// README.md), and with --records a StationXML file beside them.
    #[command(after_help = AFTER_HELP)]
    Sds(Sds),
}

#[derive(Debug, clap::Args)]
pub struct Export {
    #[command(flatten)]
    pub zenoh: ZenohArgs,
    /// Building whose gateway keeps the history.
    #[arg(long)]
    pub building: String,
    /// A sensor id, or a key-expression chunk such as `*` (every sensor of the building) or
    /// `acc-$*` (ids starting with `acc-`).
    #[arg(long, default_value = "*")]
    pub sensor: String,
    /// Batches whose first sample is at or after this time, RFC 3339 (e.g.
    /// 2026-11-24T00:00:00Z); default: the oldest kept.
    #[arg(long)]
    pub from: Option<String>,
    /// Batches whose first sample is before this time, RFC 3339; default: no bound.
    #[arg(long)]
    pub to: Option<String>,
    /// `in_force` (the record each batch was corrected with), `latest`, or a version number.
    #[arg(long, default_value = "in_force")]
    pub calibration: String,
    /// Output: the Parquet file (replaced whole once complete) or the SDS root directory
    /// (created if absent; the export merged into it).
    #[arg(long)]
    pub out: PathBuf,
    /// Seconds the gateway's status query and each page of the history query may take.
    #[arg(long, default_value_t = 30.0)]
    pub timeout_s: f64,
}

#[derive(Debug, clap::Args)]
pub struct Sds {
    #[command(flatten)]
    pub export: Export,
    /// FDSN network code: 1 or 2 letters or digits.
    #[arg(long, default_value = "XX")]
    pub network: String,
    /// A sensor's station code, SENSOR=CODE (repeatable); default: the sensor id's letters and
    /// digits, upper case, first five.
    #[arg(long = "station", value_name = "SENSOR=CODE")]
    pub stations: Vec<String>,
    /// Calibration records (JSON files, or directories of them, not recursive) for the
    /// StationXML file `<out>/<NETWORK>.<building>.xml`: every version the exported data were
    /// corrected with must be among them. None: no StationXML.
    #[arg(long = "records", value_name = "FILE|DIR")]
    pub records: Vec<PathBuf>,
}

/// Why an export was not written.
#[derive(Debug, thiserror::Error)]
pub enum ExportError {
    #[error("{0}")]
    Usage(String),
    #[error("cannot open a Zenoh session ({endpoints}): {cause}")]
    Session { endpoints: String, cause: String },
    #[error("no gateway of building {building} answered a status query within {timeout_s} s (through {endpoints}): wrong building, or its gateway is not running or not reachable")]
    NoGateway {
        building: BuildingId,
        endpoints: String,
        timeout_s: f64,
    },
    #[error("the gateway of building {building} keeps no history (it runs with history off): there is nothing to export")]
    HistoryOff { building: BuildingId },
    #[error("sensor {sensor}: the history of building {building} holds nothing of it (an unknown sensor, or all of its data past retention)")]
    UnknownSensor {
        building: BuildingId,
        sensor: String,
    },
    #[error("nothing kept in building {building}'s history for sensor {sensor} {range}; no file written")]
    Empty {
        building: BuildingId,
        sensor: String,
        range: String,
    },
    #[error("{0}")]
    Gateway(String),
    #[error("{path}: {cause}")]
    Output { path: PathBuf, cause: String },
    #[error(transparent)]
    Sds(#[from] MseedError),
    #[error(transparent)]
    StationXml(#[from] StationXmlError),
}

impl ExportError {
    /// The process's exit status for this error.
    pub fn exit_code(&self) -> u8 {
        match self {
            ExportError::Empty { .. } => EXIT_EMPTY,
            _ => 1,
        }
    }
}

/// What an export wrote.
#[derive(Debug, Clone, Default)]
pub struct Summary {
    pub batches: usize,
    /// Samples written (Parquet rows; for SDS, samples per channel).
    pub samples: u64,
    /// Files written, with their records (SDS) or rows (Parquet).
    pub files: BTreeMap<PathBuf, u64>,
    /// Notes for the user: what was left out and why.
    pub notes: Vec<String>,
    pub elapsed: Duration,
}

/// Runs `triax-export` with its command-line arguments (the program name first); prints the
/// outcome on standard error and returns the exit status.
pub async fn main(args: impl IntoIterator<Item = std::ffi::OsString>) -> u8 {
    let cli = match Cli::try_from_args(args) {
        Ok(c) => c,
        Err(e) => {
            let _ = e.print();
            return e.exit_code().clamp(0, 255) as u8;
        }
    };
    match run(cli).await {
        Ok(s) => {
            for n in &s.notes {
                eprintln!("note: {n}");
            }
            eprintln!(
                "{} batches, {} samples, {} files written in {:.2} s",
                s.batches,
                s.samples,
                s.files.len(),
                s.elapsed.as_secs_f64()
            );
            for f in s.files.keys() {
                eprintln!("  {}", f.display());
            }
            0
        }
        Err(e) => {
            eprintln!("triax-export: {e}");
            e.exit_code()
        }
    }
}

/// Runs an export.
pub async fn run(cli: Cli) -> Result<Summary, ExportError> {
    match cli.format {
        Format::Parquet(a) => parquet(a).await,
        Format::Sds(a) => sds(a).await,
    }
}

fn time_ns(what: &str, v: &Option<String>) -> Result<Option<i64>, ExportError> {
    v.as_deref()
        .map(|s| {
            let t = OffsetDateTime::parse(s, &Rfc3339).map_err(|e| {
                ExportError::Usage(format!("--{what} {s:?} is not an RFC 3339 time: {e}"))
            })?;
            i64::try_from(t.unix_timestamp_nanos())
                .map_err(|_| ExportError::Usage(format!("--{what} {s:?} is out of range")))
        })
        .transpose()
}

/// The request the arguments describe, checked.
fn request(a: &Export) -> Result<HistoryRequest, ExportError> {
    let building = BuildingId::new(&a.building)
        .map_err(|e| ExportError::Usage(format!("--building {:?}: {e}", a.building)))?;
    if !(a.timeout_s.is_finite() && a.timeout_s > 0.0) {
        return Err(ExportError::Usage(format!(
            "--timeout-s {} is not a positive number of seconds",
            a.timeout_s
        )));
    }
    if a.sensor.is_empty() || a.sensor.contains(['/', '?', '#', ';']) {
        return Err(ExportError::Usage(format!(
            "--sensor {:?}: a sensor id or one key-expression chunk such as *",
            a.sensor
        )));
    }
    match a.calibration.as_str() {
        "in_force" | "latest" => {}
        v if v.parse::<u64>().is_ok_and(|n| n >= 1) => {}
        v => {
            return Err(ExportError::Usage(format!(
                "--calibration {v:?}: in_force, latest or a version number ≥ 1"
            )))
        }
    }
    let (from_ns, to_ns) = (time_ns("from", &a.from)?, time_ns("to", &a.to)?);
    if let (Some(f), Some(t)) = (from_ns, to_ns) {
        if f > t {
            return Err(ExportError::Usage(format!(
                "--from {} is after --to {}",
                a.from.as_deref().unwrap_or_default(),
                a.to.as_deref().unwrap_or_default()
            )));
        }
    }
    Ok(HistoryRequest {
        building,
        sensors: a.sensor.clone(),
        from_ns,
        to_ns,
        from_seq: None,
        to_seq: None,
        calibration: Some(a.calibration.clone()),
        trusted: None,
    })
}

/// A Zenoh session from the shared options: a client of the endpoints given unless told
/// otherwise, listening nowhere unless told.
async fn session(a: &ZenohArgs) -> Result<zenoh::Session, ExportError> {
    let mut settings = a.settings();
    if settings.mode.is_none() && settings.config_file.is_none() {
        settings.mode = Some(ZenohMode::Client);
    }
    let endpoints = if settings.connect.is_empty() {
        "no --connect endpoint".to_owned()
    } else {
        settings.connect.join(", ")
    };
    let config =
        triax_net::outbound_config(&settings).map_err(|e| ExportError::Usage(e.to_string()))?;
    zenoh::open(config).await.map_err(|e| ExportError::Session {
        cause: triax_net::zenoh_cause(&*e),
        endpoints,
    })
}

/// Checks that a gateway of the building answers and keeps a history.
async fn preflight(
    s: &zenoh::Session,
    a: &Export,
    r: &HistoryRequest,
) -> Result<GatewayStatus, ExportError> {
    let key = format!("{}?limit=0", Key::Status(r.building.clone()));
    let no_gateway = || ExportError::NoGateway {
        building: r.building.clone(),
        endpoints: a.zenoh.connect.join(", "),
        timeout_s: a.timeout_s,
    };
    let replies = s
        .get(&key)
        .timeout(Duration::from_secs_f64(a.timeout_s))
        .await
        .map_err(|_| no_gateway())?;
    let Ok(reply) = replies.recv_async().await else {
        return Err(no_gateway());
    };
    let status: GatewayStatus = match reply.result() {
        Ok(sample) => from_json(&sample.payload().to_bytes()).map_err(|e| {
            ExportError::Gateway(format!("the gateway's status does not read: {e}"))
        })?,
        Err(e) => {
            return Err(ExportError::Gateway(format!(
                "status query: {}",
                String::from_utf8_lossy(&e.payload().to_bytes())
            )))
        }
    };
    if status.history.is_none() {
        return Err(ExportError::HistoryOff {
            building: r.building.clone(),
        });
    }
    Ok(status)
}

/// Turns an export that found nothing into the right error: an unknown sensor, or an empty
/// range.
async fn nothing(s: &zenoh::Session, a: &Export, r: &HistoryRequest) -> ExportError {
    let all = HistoryRequest {
        from_ns: None,
        to_ns: None,
        calibration: None,
        ..r.clone()
    };
    let concrete = SensorId::new(r.sensors.as_str()).is_ok();
    let kept = any_kept(s, &all, Duration::from_secs_f64(a.timeout_s))
        .await
        .unwrap_or(true);
    if concrete && !kept {
        return ExportError::UnknownSensor {
            building: r.building.clone(),
            sensor: r.sensors.clone(),
        };
    }
    let range = match (&a.from, &a.to) {
        (None, None) => "at all".to_owned(),
        (Some(f), None) => format!("from {f}"),
        (None, Some(t)) => format!("before {t}"),
        (Some(f), Some(t)) => format!("from {f} to {t}"),
    };
    ExportError::Empty {
        building: r.building.clone(),
        sensor: r.sensors.clone(),
        range,
    }
}

/// An error writing `path`, with its cause (an I/O or Parquet error).
fn output_error<E: std::fmt::Display>(path: &Path) -> impl Fn(E) -> ExportError + '_ {
    move |e| ExportError::Output {
        path: path.to_path_buf(),
        cause: e.to_string(),
    }
}

async fn parquet(a: Export) -> Result<Summary, ExportError> {
    let request = request(&a)?;
    let started = Instant::now();
    // The file is written beside its target, so that the rename that completes it stays on
    // one file system.
    let dir = match a.out.parent() {
        Some(d) if !d.as_os_str().is_empty() => d.to_path_buf(),
        _ => PathBuf::from("."),
    };
    let name = a
        .out
        .file_name()
        .ok_or_else(|| ExportError::Usage(format!("--out {}: not a file name", a.out.display())))?
        .to_string_lossy()
        .into_owned();
    let tmp = crate::whole::temp_beside(&dir, &format!(".{name}."), ".partial")
        .map_err(output_error(&a.out))?;
    let session = session(&a.zenoh).await?;
    preflight(&session, &a, &request).await?;
    let file = tmp.reopen().map_err(output_error(&a.out))?;
    let mut writer =
        ParquetWriter::new(std::io::BufWriter::new(file)).map_err(output_error(&a.out))?;
    let mut failed: Option<ParquetExportError> = None;
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
    .map_err(|e| ExportError::Gateway(e.to_string()))?;
    if let Some(e) = failed {
        return Err(output_error(&a.out)(e));
    }
    if batches == 0 {
        let e = nothing(&session, &a, &request).await;
        let _ = session.close().await;
        return Err(e);
    }
    let _ = session.close().await;
    let rows = writer.finish().map_err(output_error(&a.out))?;
    crate::whole::commit(tmp, &a.out).map_err(output_error(&a.out))?;
    Ok(Summary {
        batches,
        samples: rows,
        files: BTreeMap::from([(a.out.clone(), rows)]),
        notes: Vec::new(),
        elapsed: started.elapsed(),
    })
}

/// `--station SENSOR=CODE` arguments as a map.
fn station_overrides(args: &[String]) -> Result<BTreeMap<String, String>, ExportError> {
    args.iter()
        .map(|s| match s.split_once('=') {
            Some((sensor, code)) if !sensor.is_empty() => {
                Ok((sensor.to_string(), code.to_string()))
            }
            _ => Err(ExportError::Usage(format!(
                "--station {s:?}: expected SENSOR=CODE"
            ))),
        })
        .collect()
}

/// Every record in the files and directories given, by name in the messages.
fn read_records(paths: &[PathBuf]) -> Result<Vec<CalibrationRecord>, ExportError> {
    let bad = |p: &Path, e: &dyn std::fmt::Display| {
        ExportError::Usage(format!("--records {}: {e}", p.display()))
    };
    let mut files = Vec::new();
    for p in paths {
        if p.is_dir() {
            let mut in_dir: Vec<PathBuf> = std::fs::read_dir(p)
                .map_err(|e| bad(p, &e))?
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
            let bytes = std::fs::read(f).map_err(|e| bad(f, &e))?;
            let r: CalibrationRecord = from_json(&bytes).map_err(|e| bad(f, &e))?;
            r.validate().map_err(|e| bad(f, &e))?;
            Ok(r)
        })
        .collect()
}

async fn sds(a: Sds) -> Result<Summary, ExportError> {
    let request = request(&a.export)?;
    let records = read_records(&a.records)?;
    let network = a.network.to_ascii_uppercase();
    let mut writer = SdsWriter::new(&a.export.out, &a.network, station_overrides(&a.stations)?)?;
    let started = Instant::now();
    let session = session(&a.export.zenoh).await?;
    preflight(&session, &a.export, &request).await?;
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
    .map_err(|e| ExportError::Gateway(e.to_string()))?;
    if let Some(e) = failed {
        return Err(e.into());
    }
    if batches == 0 {
        let e = nothing(&session, &a.export, &request).await;
        let _ = session.close().await;
        return Err(e);
    }
    let _ = session.close().await;
    let staged = writer.stage()?;
    let mut notes = Vec::new();
    for (sensor, left) in staged.left_out() {
        if left.uncalibrated_samples > 0 {
            notes.push(format!(
                "sensor {sensor}: {} uncalibrated samples (raw outputs, not m/s²) left out; \
                 `triax-export parquet` exports them, flagged",
                left.uncalibrated_samples
            ));
        }
        if left.overlapping_batches > 0 {
            notes.push(format!(
                "sensor {sensor}: {} batches left out, their instants already written \
                 (duplicates)",
                left.overlapping_batches
            ));
        }
    }
    // The StationXML is made before the archive is touched: a missing record stops the export
    // with nothing written.
    let xml = if records.is_empty() {
        None
    } else {
        Some(stationxml(
            &network,
            &request.building,
            staged.stations(),
            &rates,
            staged.runs(),
            &records,
            OffsetDateTime::now_utc(),
        )?)
    };
    let samples = staged.samples();
    let mut files: BTreeMap<PathBuf, u64> = staged
        .commit()?
        .into_iter()
        .map(|(p, n)| (p, n as u64))
        .collect();
    if let Some(xml) = xml {
        let path = a
            .export
            .out
            .join(format!("{network}.{}.xml", request.building));
        write_whole(&path, xml.as_bytes())?;
        files.insert(path, 1);
    }
    if files.is_empty() {
        notes.push("no calibrated sample in the range: no miniSEED file written".to_owned());
    }
    Ok(Summary {
        batches,
        samples,
        files,
        notes,
        elapsed: started.elapsed(),
    })
}

/// Writes `bytes` as the whole of `path` ([`crate::whole`]).
fn write_whole(path: &Path, bytes: &[u8]) -> Result<(), ExportError> {
    crate::whole::write(path, [bytes]).map_err(output_error(path))
}
