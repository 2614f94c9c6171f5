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
//! ```

use std::path::{Path, PathBuf};

use anyhow::Context;
use clap::{Parser, Subcommand, ValueEnum};
use time::OffsetDateTime;
use triax_calibration::fit::ReferenceMethod;
use triax_calibration::sim::{SensorTruth, SimConfig};
use triax_calibration_store::cli::{self as store_cli, StoreCommand};
use triax_calibration_store::Store;
use triax_lab::commands::{
    default_certificate_id, dynamic_summary, parse_set, run_apply, run_dynamic, run_fit,
    run_radius, run_simulate, run_static, run_tables, static_summary, tables_summary, FitOptions,
};
use triax_lab::record::RecordMeta;
use triax_protocol::SensorId;

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
    },
    /// Static fit only: prints S, q, their uncertainties, residuals and the ±g check.
    Static {
        #[arg(long = "static")]
        static_csv: PathBuf,
        #[arg(long, default_value_t = 9.80665)]
        gravity: f64,
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
    /// Offline correction of t_s,vx,vy,vz data with the gateway's corrector.
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
        #[arg(long, value_enum, default_value = "savitzky-golay")]
        reference: Reference,
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
            reference,
            points,
            record_version,
            lab_name,
            certificate,
            output_unit,
        } => {
            let sensor_id = SensorId::new(sensor.clone())
                .map_err(|e| anyhow::anyhow!("--sensor {sensor}: {e}"))?;
            let now = OffsetDateTime::now_utc();
            let options = FitOptions {
                gravity_mps2: gravity,
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
            write_file(&out, &output.json)?;
            println!("\nwrote {}", out.display());
            if let (Some(path), Some(html)) = (report, output.report_html) {
                write_file(&path, html.as_bytes())?;
                println!("wrote {}", path.display());
            }
        }
        Command::Static {
            static_csv,
            gravity,
        } => {
            let result = run_static(&static_csv, gravity)?;
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
            reference,
        } => {
            if !(duration_s.is_finite() && duration_s > 0.0) {
                anyhow::bail!("--duration-s must be positive");
            }
            let config = SimConfig {
                seed,
                duration_s,
                alphas_deg: alphas,
                sensor: if matched {
                    SensorTruth::matched()
                } else {
                    SensorTruth::paper()
                },
                reference: reference.into(),
                ..SimConfig::default()
            };
            let (_, files) = run_simulate(&config);
            for (rel, contents) in &files {
                write_file(&out_dir.join(rel), contents.as_bytes())?;
            }
            println!("wrote {} files under {}", files.len(), out_dir.display());
        }
        Command::Store { store_dir, command } => {
            let store = Store::open(&store_dir)?;
            store_cli::run(&store, &command, &mut std::io::stdout().lock())?;
        }
    }
    Ok(())
}
