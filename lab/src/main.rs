//! `triax-lab`: the calibration lab's command line. Parses arguments, reads the clock, calls
//! `triax_lab::commands` and writes what they return, only once they have succeeded.
//!
//! ```text
//! triax-lab fit --sensor S1 --static static.csv --bench bench.toml --out record.json [--report r.html]
//! triax-lab static --static static.csv
//! triax-lab dynamic --bench bench.toml [--reference harmonic] [--points 20]
//! triax-lab radius --input spacers.csv
//! triax-lab apply --record record.json --set dynamic --input data.csv --out corrected.csv
//! triax-lab simulate --out-dir DIR [--seed 2015] [--duration-s 10]
//! triax-lab store --store-dir DIR list|show|history|export|import …
//! triax-lab keygen --out DIR                         # DIR/lab.key (0600), DIR/lab.pub
//! triax-lab push --key lab.key --registry REG --building B [--building B2] rec.json|DIR… [-e tcp/router:7447]
//! triax-lab serve --key lab.key --registry REG [-e tcp/router:7447]
//! triax-lab assign --registry REG --sensor S [--building B…]   # or --show
//! ```

use std::path::{Path, PathBuf};
use std::time::Duration;

use anyhow::Context;
use clap::{Parser, Subcommand, ValueEnum};
use time::OffsetDateTime;
use triax_calibration::fit::ArmAngleUncertainty;
use triax_calibration::fit::ReferenceMethod;
use triax_calibration::sim::{SensorTruth, SimConfig};
use triax_calibration_store::cli::{self as store_cli, StoreCommand};
use triax_calibration_store::Store;
use triax_lab::commands::{
    default_certificate_id, dynamic_summary, parse_set, run_apply, run_dynamic, run_fit,
    run_radius, run_simulate, run_static, run_tables, static_summary, tables_summary, FitOptions,
};
use triax_lab::due;
use triax_lab::keypair;
use triax_lab::net::zenoh_config;
use triax_lab::push::{push_all, render, Push};
use triax_lab::record::RecordMeta;
use triax_lab::registry::{Recorded, Registry};
use triax_net::ZenohArgs;
use triax_protocol::messages::{HealthVerdict, SensorHealthReport};
use triax_protocol::record::CalibrationRecord;
use triax_protocol::{from_json, BuildingId, SensorId};

#[derive(Parser)]
#[command(
    name = "triax-lab",
    version,
    about = "Static and dynamic calibration of three-axis accelerometers"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Clone, Copy, ValueEnum)]
enum Reference {
    FiniteDifference,
    MotionLaw,
    SavitzkyGolay,
    Harmonic,
}

impl From<Reference> for ReferenceMethod {
    fn from(r: Reference) -> Self {
        match r {
            Reference::FiniteDifference => ReferenceMethod::FiniteDifference,
            Reference::MotionLaw => ReferenceMethod::MotionLaw,
            Reference::SavitzkyGolay => ReferenceMethod::SavitzkyGolay,
            Reference::Harmonic => ReferenceMethod::Harmonic,
        }
    }
}

/// What the operator knows of the static arm's angles (a Type B statement).
#[derive(clap::Args)]
struct ArmArgs {
    /// Standard uncertainty of each of the arm's two angles (roll, pitch), degrees. Pooled with
    /// the residuals, it gives the static covariance more degrees of freedom than the
    /// orientations alone (N − 4); without it the residuals alone speak.
    #[arg(long, value_name = "DEG")]
    arm_angle_uncertainty_deg: Option<f64>,
    /// Degrees of freedom of that statement: ½·(u/Δu)², e.g. 50 when u is known to ±10 %.
    #[arg(
        long,
        value_name = "NU",
        default_value_t = 50.0,
        requires = "arm_angle_uncertainty_deg"
    )]
    arm_angle_dof: f64,
}

impl ArmArgs {
    fn statement(&self) -> Option<ArmAngleUncertainty> {
        self.arm_angle_uncertainty_deg
            .map(|angle_deg| ArmAngleUncertainty {
                angle_deg,
                dof: self.arm_angle_dof,
            })
    }
}

#[derive(Subcommand)]
enum Command {
    /// Static and dynamic fit: writes a full calibration record and prints a summary.
    Fit {
        #[arg(long)]
        sensor: String,
        /// Static CSV: ax_ref,ay_ref,az_ref,vx,vy,vz (or roll_deg,pitch_deg,vx,vy,vz).
        #[arg(long = "static")]
        static_csv: PathBuf,
        /// Bench TOML naming the recordings.
        #[arg(long)]
        bench: PathBuf,
        /// The calibration record (JSON) to write.
        #[arg(long)]
        out: PathBuf,
        /// Also write a self-contained HTML report.
        #[arg(long)]
        report: Option<PathBuf>,
        /// Local gravity for roll_deg/pitch_deg static files, m/s².
        #[arg(long, default_value_t = 9.80665)]
        gravity: f64,
        #[command(flatten)]
        arm: ArmArgs,
        /// Overrides the bench file's reference method.
        #[arg(long, value_enum)]
        reference: Option<Reference>,
        /// Overrides the bench file's points_per_cycle.
        #[arg(long)]
        points: Option<usize>,
        /// Record version (strictly increasing per sensor).
        #[arg(long = "record-version", default_value_t = 1)]
        record_version: u64,
        #[arg(long, default_value = "Triax calibration lab")]
        lab_name: String,
        /// Certificate id; default TRIAX-<sensor>-<version>-<date>.
        #[arg(long)]
        certificate: Option<String>,
        /// Unit of the sensor outputs.
        #[arg(long, default_value = "V")]
        output_unit: String,
        /// The record the new one replaces (JSON): the summary and the report compare the two,
        /// parameter by parameter (see `compare`).
        #[arg(long, value_name = "FILE")]
        previous: Option<PathBuf>,
        /// A field health report of the previous record (PROTOCOL.md §3.9, one report or the
        /// JSON array `due --json` prints): its relative gravity test against the two records'
        /// prediction of it. Needs --previous.
        #[arg(long, value_name = "FILE", requires = "previous")]
        field_health: Option<PathBuf>,
    },
    /// Compares a sensor's new record with the one it replaces, parameter by parameter, and
    /// with the drift the field saw under the old one (its relative gravity test): what the lab
    /// measured against what the gateway's checks estimated. Exit status 0; 4 when the field's
    /// estimate and the lab's prediction disagree (|z| > 2).
    Compare {
        /// The record the new one replaces (JSON).
        #[arg(long, value_name = "FILE")]
        previous: PathBuf,
        /// The new record (JSON).
        #[arg(long, value_name = "FILE")]
        record: PathBuf,
        /// A field health report of the previous record (PROTOCOL.md §3.9, one report or the
        /// JSON array `due --json` prints).
        #[arg(long, value_name = "FILE")]
        field_health: Option<PathBuf>,
        /// Also write the comparison as an HTML section.
        #[arg(long, value_name = "FILE")]
        report: Option<PathBuf>,
    },
    /// Static fit only: prints S, q, their uncertainties, residuals and the ±g check.
    Static {
        #[arg(long = "static")]
        static_csv: PathBuf,
        #[arg(long, default_value_t = 9.80665)]
        gravity: f64,
        #[command(flatten)]
        arm: ArmArgs,
    },
    /// Dynamic fit only: prints S, q, the uncertainty budget and the comparison tables.
    Dynamic {
        #[arg(long)]
        bench: PathBuf,
        #[arg(long, value_enum)]
        reference: Option<Reference>,
        #[arg(long)]
        points: Option<usize>,
        /// Skip the comparison tables (which refit several times).
        #[arg(long)]
        no_tables: bool,
    },
    /// Radius of the sensing element from spacer blocks: CSV delta_r_mm,output.
    Radius {
        #[arg(long)]
        input: PathBuf,
    },
    /// A calibration record as a Digital Calibration Certificate (PTB DCC 3, D-SI 2 quantities):
    /// both sets' S and q with expanded uncertainties, the 12×12 covariances, the coverage
    /// factors and probability, methods, references and conditions (README.md).
    Dcc {
        /// The calibration record (JSON), as `fit` writes it.
        #[arg(long)]
        record: PathBuf,
        /// The DCC XML to write.
        #[arg(long)]
        out: PathBuf,
        /// ISO 3166-1 alpha-2 code of the lab's country (a record does not say); ZZ is the
        /// user-assigned "unknown".
        #[arg(long, default_value = "ZZ")]
        country: String,
        /// The lab's contact e-mail address for the certificate; without it the certificate
        /// names none (DCC 3.2.1 allows that, not an empty address).
        #[arg(long)]
        email: Option<String>,
    },
    /// Offline correction of t_s,vx,vy,vz data (and an optional temperature_c column) with the
    /// gateway's corrector: writes t_s,ax,ay,az,ux,uy,uz, plus outside_temperature (0 or 1)
    /// when the record has a temperature model.
    Apply {
        #[arg(long)]
        record: PathBuf,
        /// static or dynamic.
        #[arg(long)]
        set: String,
        #[arg(long)]
        input: PathBuf,
        #[arg(long)]
        out: PathBuf,
    },
    /// Writes a simulated bench with known truth: static.csv, bench.toml, recordings/,
    /// spacers.csv, truth.toml.
    Simulate {
        #[arg(long)]
        out_dir: PathBuf,
        #[arg(long, default_value_t = 2015)]
        seed: u64,
        #[arg(long, default_value_t = 10.0)]
        duration_s: f64,
        /// Mount angles, degrees.
        #[arg(long, value_delimiter = ',', default_values_t = [0.0, 45.0, 90.0, 135.0])]
        alphas: Vec<f64>,
        /// A sensor that follows eq. (1) exactly (same response to constant and varying input).
        #[arg(long)]
        matched: bool,
        /// A sensor whose offsets and gains drift with temperature (follows eq. (1) at 21 °C);
        /// its drift is in truth.toml.
        #[arg(long, conflicts_with = "matched")]
        thermal_drift: bool,
        /// Run the static bench at each of these temperatures, °C (comma-separated): static.csv
        /// gains a temperature_c column. Default: one run at 21 °C, no column.
        #[arg(long, value_delimiter = ',', value_name = "C,C,…")]
        static_temperatures: Vec<f64>,
        #[arg(long, value_enum, default_value = "savitzky-golay")]
        reference: Reference,
    },
    /// Makes the lab's Ed25519 key pair: DIR/lab.key (secret, mode 0600) and DIR/lab.pub
    /// (the public key gateways list in `calibration.trusted_lab_keys`).
    Keygen {
        #[arg(long, value_name = "DIR")]
        out: PathBuf,
    },
    /// Signs records, records them in the registry, pushes them to every gateway of each
    /// building and prints each gateway's answer. Exits non-zero if any record was refused (by
    /// the registry or a gateway) or not acknowledged in time.
    Push {
        /// The lab's secret key file (from `keygen`).
        #[arg(long, value_name = "FILE")]
        key: PathBuf,
        /// The lab's registry directory: every pushed record is stored there first, so an
        /// offline gateway catches up from it.
        #[arg(long, value_name = "DIR", env = "TRIAX_REGISTRY")]
        registry: PathBuf,
        /// Building to push to (repeat for several); its sensors are assigned to it.
        #[arg(long = "building", required = true, value_name = "B")]
        buildings: Vec<String>,
        /// Seconds to wait for the gateways' acknowledgements.
        #[arg(long, default_value_t = 5.0)]
        timeout_s: f64,
        /// Gateways expected to acknowledge, per building and record.
        #[arg(long, default_value_t = 1)]
        min_acks: usize,
        #[command(flatten)]
        zenoh: ZenohArgs,
        /// Record files (JSON), or directories of them (every *.json, not recursive).
        #[arg(required = true, value_name = "RECORD|DIR")]
        records: Vec<PathBuf>,
    },
    /// Runs the lab's registry: answers gateways' catch-up queries with every newer record of
    /// their building, signed with the lab key. Runs until Ctrl-C or SIGTERM.
    Serve {
        #[arg(long, value_name = "FILE")]
        key: PathBuf,
        #[arg(long, value_name = "DIR", env = "TRIAX_REGISTRY")]
        registry: PathBuf,
        #[command(flatten)]
        zenoh: ZenohArgs,
    },
    /// Sets the buildings a sensor is served to (a sensor that moved), or shows every
    /// assignment.
    Assign {
        #[arg(long, value_name = "DIR", env = "TRIAX_REGISTRY")]
        registry: PathBuf,
        #[arg(long, required_unless_present = "show")]
        sensor: Option<String>,
        /// Building (repeat for several; none: the sensor is served to no building).
        #[arg(long = "building", value_name = "B")]
        buildings: Vec<String>,
        /// Print every assignment.
        #[arg(long, conflicts_with_all = ["sensor", "buildings"])]
        show: bool,
    },
    /// Lists the sensors due for recalibration: those whose record in force the buildings'
    /// gateways found `suspect` in the field (PROTOCOL.md §3.9), with the evidence; `--watch`
    /// adds those under watch. Exit status 0 when none is due, 3 when at least one is.
    Due {
        /// Building to ask (repeat for several; none: every building that answers).
        #[arg(long = "building", value_name = "B")]
        buildings: Vec<String>,
        /// Also list sensors whose verdict is `watch`.
        #[arg(long)]
        watch: bool,
        /// Also list sensors whose calibration nothing has checked yet (no quiet minute, no
        /// local gravity, no co-located pair: `calibration_checked` false), with why.
        #[arg(long)]
        unchecked: bool,
        /// Print the gateways' reports as a JSON array instead of the table.
        #[arg(long)]
        json: bool,
        /// Seconds to wait for the gateways' answers.
        #[arg(long, default_value_t = 5.0)]
        timeout_s: f64,
        #[command(flatten)]
        zenoh: ZenohArgs,
    },
    /// Inspects, backs up or restores the lab's registry of issued records.
    Store {
        /// Registry directory (a calibration store).
        #[arg(long, value_name = "DIR")]
        store_dir: PathBuf,
        #[command(subcommand)]
        command: StoreCommand,
    },
}

fn write_file(path: &Path, contents: &[u8]) -> anyhow::Result<()> {
    if let Some(dir) = path.parent() {
        if !dir.as_os_str().is_empty() {
            std::fs::create_dir_all(dir)
                .with_context(|| format!("creating directory {}", dir.display()))?;
        }
    }
    std::fs::write(path, contents).with_context(|| format!("writing {}", path.display()))
}

/// Writes a new file that must not exist yet, readable by its owner only when `private`.
fn write_new_key_file(path: &Path, text: &str, private: bool) -> anyhow::Result<()> {
    use std::io::Write;
    let mut options = std::fs::OpenOptions::new();
    options.write(true).create_new(true);
    #[cfg(unix)]
    {
        use std::os::unix::fs::OpenOptionsExt;
        options.mode(if private { 0o600 } else { 0o644 });
    }
    #[cfg(not(unix))]
    let _ = private;
    let mut f = options.open(path).with_context(|| {
        format!(
            "creating {} (an existing key is never overwritten)",
            path.display()
        )
    })?;
    f.write_all(text.as_bytes())
        .and_then(|()| f.sync_all())
        .with_context(|| format!("writing {}", path.display()))
}

/// The comparison of `new` with the record in `previous`, and with the report of it in
/// `field_health` (one report, or an array of them of which the one for that record is taken).
fn comparison(
    previous: &Path,
    new: &CalibrationRecord,
    field_health: Option<&Path>,
) -> anyhow::Result<triax_lab::compare::Comparison> {
    let old = read_records(&[previous.to_path_buf()])?
        .pop()
        .context("no record read")?;
    let report = match field_health {
        None => None,
        Some(path) => {
            let bytes =
                std::fs::read(path).with_context(|| format!("reading {}", path.display()))?;
            let value: serde_json::Value = serde_json::from_slice(&bytes)
                .with_context(|| format!("{} is not JSON", path.display()))?;
            let candidates = match value {
                serde_json::Value::Array(items) => items,
                one => vec![one],
            };
            let mut found = None;
            for (i, v) in candidates.into_iter().enumerate() {
                let r: SensorHealthReport =
                    from_json(v.to_string().as_bytes()).with_context(|| {
                        format!(
                            "{} item {i} is not a health report (PROTOCOL.md §3.9)",
                            path.display()
                        )
                    })?;
                if r.sensor_id == old.sensor_id && r.calibration_version == old.version {
                    found = Some(r);
                }
            }
            Some(found.with_context(|| {
                format!(
                    "{} holds no report of {} version {}",
                    path.display(),
                    old.sensor_id,
                    old.version
                )
            })?)
        }
    };
    Ok(triax_lab::compare::compare(&old, new, report.as_ref())?)
}

/// Reads record files and every *.json of directories, sorted by sensor then version so that
/// the registry accepts several versions of one sensor in one go.
fn read_records(paths: &[PathBuf]) -> anyhow::Result<Vec<CalibrationRecord>> {
    let mut files = Vec::new();
    for p in paths {
        if p.is_dir() {
            let mut found: Vec<PathBuf> = std::fs::read_dir(p)
                .with_context(|| format!("reading directory {}", p.display()))?
                .filter_map(|e| e.ok().map(|e| e.path()))
                .filter(|f| f.is_file() && f.extension().is_some_and(|x| x == "json"))
                .collect();
            found.sort();
            if found.is_empty() {
                anyhow::bail!("{} holds no *.json record", p.display());
            }
            files.extend(found);
        } else {
            files.push(p.clone());
        }
    }
    let mut records = Vec::with_capacity(files.len());
    for f in &files {
        let bytes = std::fs::read(f).with_context(|| format!("reading {}", f.display()))?;
        let record: CalibrationRecord = from_json(&bytes)
            .with_context(|| format!("{} is not a calibration record", f.display()))?;
        records.push(record);
    }
    records.sort_by(|a, b| (&a.sensor_id, a.version).cmp(&(&b.sensor_id, b.version)));
    Ok(records)
}

fn building_ids(names: &[String]) -> anyhow::Result<Vec<BuildingId>> {
    names
        .iter()
        .map(|b| BuildingId::new(b.as_str()).map_err(|e| anyhow::anyhow!("--building {b}: {e}")))
        .collect()
}

fn init_logging(default: &str) -> anyhow::Result<()> {
    let text = std::env::var("TRIAX_LOG").unwrap_or_else(|_| default.to_owned());
    let filter =
        tracing_subscriber::EnvFilter::try_new(text).context("TRIAX_LOG is not a valid filter")?;
    tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr)
        .init();
    Ok(())
}

fn runtime() -> anyhow::Result<tokio::runtime::Runtime> {
    // Zenoh needs the multi-thread runtime.
    tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .context("starting the tokio runtime")
}

/// Completes on SIGINT or SIGTERM.
async fn shutdown_signal() {
    #[cfg(unix)]
    {
        use tokio::signal::unix::{signal, SignalKind};
        if let Ok(mut term) = signal(SignalKind::terminate()) {
            tokio::select! {
                _ = tokio::signal::ctrl_c() => {}
                _ = term.recv() => {}
            }
            return;
        }
    }
    let _ = tokio::signal::ctrl_c().await;
}

#[allow(clippy::too_many_arguments)]
fn run_push(
    key: &Path,
    registry: PathBuf,
    buildings: &[String],
    timeout_s: f64,
    min_acks: usize,
    zenoh: &ZenohArgs,
    paths: &[PathBuf],
) -> anyhow::Result<bool> {
    if !(timeout_s.is_finite() && timeout_s > 0.0) {
        anyhow::bail!("--timeout-s must be a positive number of seconds");
    }
    let timeout = Duration::from_secs_f64(timeout_s);
    let key = keypair::read_secret(key)?;
    let buildings = building_ids(buildings)?;
    let records = read_records(paths)?;
    let registry = Registry::new(registry);
    let recorded = registry.record(&records, &buildings)?;
    let mut ok = true;
    let mut pushes = Vec::new();
    for (record, outcome) in records.iter().zip(recorded) {
        match outcome {
            Recorded::Accepted { .. } => pushes.push(Push::sign(record, &key)),
            Recorded::Refused(why) => {
                ok = false;
                println!(
                    "{:<16} {:<20} v{:<6} {:<24} REFUSED by the registry, not pushed: {why}",
                    "-",
                    record.sensor_id.as_str(),
                    record.version,
                    registry.dir().display()
                );
            }
        }
    }
    if pushes.is_empty() {
        return Ok(false);
    }
    let config = zenoh_config(zenoh)?;
    let reports = runtime()?.block_on(async {
        let session = zenoh::open(config)
            .await
            .map_err(|e| anyhow::anyhow!("opening the zenoh session: {e}"))?;
        let reports = push_all(&session, &buildings, &pushes, timeout).await;
        if let Err(e) = session.close().await {
            tracing::warn!(cause = %e, "zenoh session did not close cleanly");
        }
        anyhow::Ok(reports?)
    })?;
    let (text, all_ok) = render(&reports, min_acks, timeout);
    print!("{text}");
    Ok(ok && all_ok)
}

fn main() -> anyhow::Result<()> {
    let cli = Cli::parse();
    match cli.command {
        Command::Fit {
            sensor,
            static_csv,
            bench,
            out,
            report,
            gravity,
            arm,
            reference,
            points,
            record_version,
            lab_name,
            certificate,
            output_unit,
            previous,
            field_health,
        } => {
            let sensor_id = SensorId::new(sensor.clone())
                .map_err(|e| anyhow::anyhow!("--sensor {sensor}: {e}"))?;
            let now = OffsetDateTime::now_utc();
            let options = FitOptions {
                gravity_mps2: gravity,
                arm: arm.statement(),
                reference: reference.map(Into::into),
                points_per_cycle: points,
                report: report.is_some(),
                meta: RecordMeta {
                    certificate_id: certificate
                        .unwrap_or_else(|| default_certificate_id(&sensor, record_version, now)),
                    sensor_id,
                    version: record_version,
                    issued_at: now,
                    lab_name,
                    output_unit,
                },
            };
            let output = run_fit(&static_csv, &bench, &options)?;
            print!("{}", output.summary);
            let comparison = match &previous {
                Some(p) => Some(comparison(p, &output.record, field_health.as_deref())?),
                None => None,
            };
            if let Some(c) = &comparison {
                print!("\n{}", triax_lab::compare::render_text(c));
            }
            write_file(&out, &output.json)?;
            println!("\nwrote {}", out.display());
            if let (Some(path), Some(mut html)) = (report, output.report_html) {
                if let Some(c) = &comparison {
                    let section = triax_lab::compare::render_html(c);
                    html = match html.rfind("</body>") {
                        Some(at) => format!("{}{section}{}", &html[..at], &html[at..]),
                        None => html + &section,
                    };
                }
                write_file(&path, html.as_bytes())?;
                println!("wrote {}", path.display());
            }
        }
        Command::Compare {
            previous,
            record,
            field_health,
            report,
        } => {
            let new = read_records(std::slice::from_ref(&record))?
                .pop()
                .context("no record read")?;
            let c = comparison(&previous, &new, field_health.as_deref())?;
            print!("{}", triax_lab::compare::render_text(&c));
            if let Some(path) = report {
                write_file(&path, triax_lab::compare::render_html(&c).as_bytes())?;
                println!("wrote {}", path.display());
            }
            if let triax_lab::compare::Field::Judged(f) = &c.field {
                if f.z.abs() > 2.0 {
                    std::process::exit(4);
                }
            }
        }
        Command::Static {
            static_csv,
            gravity,
            arm,
        } => {
            let result = run_static(&static_csv, gravity, arm.statement())?;
            print!("{}", static_summary(&result));
        }
        Command::Dynamic {
            bench,
            reference,
            points,
            no_tables,
        } => {
            let result = run_dynamic(&bench, reference.map(Into::into), points)?;
            print!("{}", dynamic_summary(&result));
            if !no_tables {
                let tables = run_tables(&result, None)?;
                print!("{}", tables_summary(&tables));
            }
        }
        Command::Radius { input } => {
            let (_, summary) = run_radius(&input)?;
            print!("{summary}");
        }
        Command::Dcc {
            record,
            out,
            country,
            email,
        } => {
            let options = triax_lab::dcc::DccOptions {
                country,
                email,
                software_release: env!("CARGO_PKG_VERSION").to_string(),
            };
            options.check()?;
            let records = read_records(std::slice::from_ref(&record))?;
            let [r] = records.as_slice() else {
                anyhow::bail!(
                    "--record {}: {} records; give one record file",
                    record.display(),
                    records.len()
                );
            };
            // dcc_xml validates the record as well as what the schema needs beyond it.
            let xml = triax_lab::dcc::dcc_xml(r, &options)
                .map_err(|e| anyhow::anyhow!("{}: {e}", record.display()))?;
            write_file(&out, xml.as_bytes())?;
            println!("wrote {}", out.display());
        }
        Command::Apply {
            record,
            set,
            input,
            out,
        } => {
            let kind = parse_set(&set)?;
            let (csv, rows) = run_apply(&record, kind, &input)?;
            write_file(&out, csv.as_bytes())?;
            println!(
                "corrected {rows} samples with the {set} set; wrote {}",
                out.display()
            );
        }
        Command::Simulate {
            out_dir,
            seed,
            duration_s,
            alphas,
            matched,
            thermal_drift,
            static_temperatures,
            reference,
        } => {
            if !(duration_s.is_finite() && duration_s > 0.0) {
                anyhow::bail!("--duration-s must be positive");
            }
            if let Some(t) = static_temperatures.iter().find(|t| !t.is_finite()) {
                anyhow::bail!("--static-temperatures: {t} is not a temperature");
            }
            let config = SimConfig {
                seed,
                duration_s,
                alphas_deg: alphas,
                sensor: if matched {
                    SensorTruth::matched()
                } else if thermal_drift {
                    SensorTruth::drifting()
                } else {
                    SensorTruth::paper()
                },
                static_temperatures_c: static_temperatures,
                reference: reference.into(),
                ..SimConfig::default()
            };
            let (_, files) = run_simulate(&config);
            for (rel, contents) in &files {
                write_file(&out_dir.join(rel), contents.as_bytes())?;
            }
            println!("wrote {} files under {}", files.len(), out_dir.display());
        }
        Command::Keygen { out } => {
            std::fs::create_dir_all(&out)
                .with_context(|| format!("creating directory {}", out.display()))?;
            let key = keypair::generate();
            let secret = out.join(keypair::SECRET_FILE);
            let public = out.join(keypair::PUBLIC_FILE);
            write_new_key_file(&secret, &keypair::secret_text(&key), true)?;
            let public_text = keypair::public_text(&key.verifying_key());
            write_new_key_file(&public, &public_text, false)?;
            println!(
                "wrote {} (secret, mode 0600) and {}",
                secret.display(),
                public.display()
            );
            println!(
                "public key (for calibration.trusted_lab_keys): {}",
                public_text.trim_end()
            );
        }
        Command::Push {
            key,
            registry,
            buildings,
            timeout_s,
            min_acks,
            zenoh,
            records,
        } => {
            init_logging("warn")?;
            if !run_push(
                &key, registry, &buildings, timeout_s, min_acks, &zenoh, &records,
            )? {
                // The table above says what failed; the exit status says that something did.
                std::process::exit(1);
            }
        }
        Command::Due {
            buildings,
            watch,
            unchecked,
            json,
            timeout_s,
            zenoh,
        } => {
            init_logging("warn")?;
            if !(timeout_s.is_finite() && timeout_s > 0.0) {
                anyhow::bail!("--timeout-s must be a positive number of seconds");
            }
            let buildings = building_ids(&buildings)?;
            let least = if watch {
                HealthVerdict::Watch
            } else {
                HealthVerdict::Suspect
            };
            // Unchecked sensors may be `ok`: every report is asked for, then chosen here.
            let ask = if unchecked { HealthVerdict::Ok } else { least };
            let config = zenoh_config(&zenoh)?;
            let (reports, problems) = runtime()?.block_on(async {
                let session = zenoh::open(config)
                    .await
                    .map_err(|e| anyhow::anyhow!("opening the zenoh session: {e}"))?;
                let found = due::gather(
                    &session,
                    &buildings,
                    ask,
                    Duration::from_secs_f64(timeout_s),
                )
                .await;
                if let Err(e) = session.close().await {
                    tracing::warn!(cause = %e, "zenoh session did not close cleanly");
                }
                anyhow::Ok(found?)
            })?;
            let reports: Vec<_> = reports
                .into_iter()
                .filter(|r| due::listed(r, least, unchecked))
                .collect();
            if json {
                println!("{}", serde_json::to_string_pretty(&reports)?);
                for p in &problems {
                    eprintln!("problem: {}", p.problem);
                }
            } else {
                print!("{}", due::render(&reports, &problems));
            }
            if due::due_count(&reports) > 0 {
                std::process::exit(3);
            }
        }
        Command::Serve {
            key,
            registry,
            zenoh,
        } => {
            init_logging("info")?;
            let key = keypair::read_secret(&key)?;
            let registry = Registry::new(registry);
            // Fails early on a registry another process cannot share or that is damaged.
            let assignments = registry.assignments()?;
            tracing::info!(registry = %registry.dir().display(), sensors = assignments.sensors.len(),
                "registry opened");
            let config = zenoh_config(&zenoh)?;
            runtime()?.block_on(async {
                let session = zenoh::open(config)
                    .await
                    .map_err(|e| anyhow::anyhow!("opening the zenoh session: {e}"))?;
                triax_lab::serve::serve(&session, registry, key, shutdown_signal()).await?;
                if let Err(e) = session.close().await {
                    tracing::warn!(cause = %e, "zenoh session did not close cleanly");
                }
                anyhow::Ok(())
            })?;
        }
        Command::Assign {
            registry,
            sensor,
            buildings,
            show,
        } => {
            let registry = Registry::new(registry);
            if show {
                for (s, b) in registry.assignments()?.sensors {
                    let list: Vec<&str> = b.iter().map(|b| b.as_str()).collect();
                    println!("{s:<20} {}", list.join(" "));
                }
            } else {
                // clap requires --sensor unless --show.
                let sensor = sensor.context("--sensor is required")?;
                let sensor = SensorId::new(sensor.as_str())
                    .map_err(|e| anyhow::anyhow!("--sensor {sensor}: {e}"))?;
                let buildings = building_ids(&buildings)?;
                let old = registry.assign(&sensor, &buildings)?;
                let names = |v: Vec<&BuildingId>| {
                    v.iter().map(|b| b.as_str()).collect::<Vec<_>>().join(" ")
                };
                println!(
                    "{sensor}: [{}] -> [{}]",
                    names(old.iter().collect()),
                    names(buildings.iter().collect())
                );
            }
        }
        Command::Store { store_dir, command } => {
            let store = Store::open(&store_dir)?;
            store_cli::run(&store, &command, &mut std::io::stdout().lock())?;
        }
    }
    Ok(())
}
