//! `store` subcommands shared by the gateway's and the lab's binaries: list, show, history,
//! export and import, with output for people.
//!
//! The binaries mount [`StoreCommand`] as a clap subcommand, open the store themselves (they
//! know where it lives) and call [`run`]. Output goes to any writer, so tests read it back.
//! sled locks a store to one process: these commands run while the gateway or lab service that
//! owns the store is stopped, or else fail with [`StoreError::Locked`].

use std::io::{self, Write};
use std::path::PathBuf;

use time::format_description::well_known::Rfc3339;
use time::OffsetDateTime;
use triax_protocol::record::CalibrationRecord;
use triax_protocol::{to_json_pretty, SensorId};

use crate::error::{CorruptEntry, StoreError};
use crate::store::{PutOutcome, Store};
use crate::transfer::FileOutcome;

/// Inspect, back up and restore the calibration store.
#[derive(Debug, Clone, PartialEq, clap::Subcommand)]
pub enum StoreCommand {
    /// List every sensor with its current version and validity window.
    List,
    /// Print a sensor's record as JSON: the current one, a given version, or the one in force
    /// at a time.
    Show {
        sensor: SensorId,
        /// This version instead of the current one.
        #[arg(long, conflicts_with = "at")]
        version: Option<u64>,
        /// The version in force at this time (RFC 3339, e.g. 2026-03-01T12:00:00Z).
        #[arg(long, value_parser = parse_rfc3339)]
        at: Option<OffsetDateTime>,
    },
    /// List every version of a sensor, oldest first.
    History { sensor: SensorId },
    /// Write every version of every sensor to a directory, one JSON file per record.
    Export { dir: PathBuf },
    /// Store every JSON record of a directory, under the same rules as a push.
    Import { dir: PathBuf },
}

fn parse_rfc3339(s: &str) -> Result<OffsetDateTime, String> {
    OffsetDateTime::parse(s, &Rfc3339).map_err(|e| format!("not an RFC 3339 time: {e}"))
}

/// Why a store command failed.
#[derive(Debug, thiserror::Error)]
pub enum CliError {
    #[error(transparent)]
    Store(#[from] StoreError),
    #[error("writing output: {0}")]
    Output(#[from] io::Error),
    #[error("sensor {sensor_id}: {what}")]
    NotFound { sensor_id: SensorId, what: String },
    #[error("import: {refused} of {files} files were not imported (see above)")]
    ImportIncomplete { refused: usize, files: usize },
}

/// Runs a store command, writing its report to `out`.
///
/// Corrupt entries met on the way are listed after the answer as `warning:` lines. An import
/// with refused or unreadable files prints its per-file report and then fails with
/// [`CliError::ImportIncomplete`], so scripts see a non-zero exit.
pub fn run(store: &Store, command: &StoreCommand, out: &mut dyn Write) -> Result<(), CliError> {
    match command {
        StoreCommand::List => {
            let scan = store.current_records()?;
            write_table(out, &scan.value, None)?;
            writeln!(out, "{} sensors", scan.value.len())?;
            write_skipped(out, &scan.skipped)?;
        }
        StoreCommand::Show {
            sensor,
            version,
            at,
        } => {
            let (record, skipped, what) = match (version, at) {
                (Some(v), _) => (store.get(sensor, *v)?, vec![], format!("no version {v}")),
                (None, Some(t)) => {
                    let scan = store.at(sensor, *t)?;
                    (
                        scan.value,
                        scan.skipped,
                        format!("no record in force at {}", time_text(*t)),
                    )
                }
                (None, None) => (store.current(sensor)?, vec![], "no record".to_owned()),
            };
            let Some(record) = record else {
                write_skipped(out, &skipped)?;
                return Err(CliError::NotFound {
                    sensor_id: sensor.clone(),
                    what,
                });
            };
            out.write_all(&to_json_pretty(&record))?;
            write_skipped(out, &skipped)?;
        }
        StoreCommand::History { sensor } => {
            let scan = store.history(sensor)?;
            if scan.value.is_empty() && scan.skipped.is_empty() {
                return Err(CliError::NotFound {
                    sensor_id: sensor.clone(),
                    what: "no record".to_owned(),
                });
            }
            let current = scan.value.last().map(|r| r.version);
            write_table(out, &scan.value, current)?;
            writeln!(out, "{} versions", scan.value.len())?;
            write_skipped(out, &scan.skipped)?;
        }
        StoreCommand::Export { dir } => {
            let report = store.export(dir)?;
            writeln!(
                out,
                "exported {} records to {}",
                report.files.len(),
                dir.display()
            )?;
            write_skipped(out, &report.skipped)?;
        }
        StoreCommand::Import { dir } => {
            let report = store.import(dir)?;
            let mut refused = 0;
            for file in &report.files {
                let name = file.path.file_name().map_or_else(
                    || file.path.display().to_string(),
                    |n| n.to_string_lossy().into_owned(),
                );
                match &file.outcome {
                    FileOutcome::Put(PutOutcome::Stored) => writeln!(out, "stored     {name}")?,
                    FileOutcome::Put(PutOutcome::AlreadyStored) => {
                        writeln!(out, "unchanged  {name} (already stored)")?
                    }
                    FileOutcome::Put(PutOutcome::Repaired) => {
                        writeln!(out, "repaired   {name} (replaced a corrupt entry)")?
                    }
                    FileOutcome::Rejected(why) => {
                        refused += 1;
                        writeln!(out, "refused    {name}: {why}")?
                    }
                    FileOutcome::Unreadable(why) => {
                        refused += 1;
                        writeln!(out, "unreadable {name}: {why}")?
                    }
                }
            }
            let files = report.files.len();
            writeln!(
                out,
                "imported {} of {files} files from {}",
                files - refused,
                dir.display()
            )?;
            if refused > 0 {
                return Err(CliError::ImportIncomplete { refused, files });
            }
        }
    }
    Ok(())
}

fn time_text(t: OffsetDateTime) -> String {
    // Years outside 0..=9999 have no RFC 3339 form; Display still says what the time is.
    t.format(&Rfc3339).unwrap_or_else(|_| t.to_string())
}

/// One line per record; `current` marks that version. Columns as wide as their widest entry:
/// a time to the nanosecond is 30 characters, one to the second 20.
fn write_table(
    out: &mut dyn Write,
    records: &[CalibrationRecord],
    current: Option<u64>,
) -> io::Result<()> {
    let rows: Vec<[String; 4]> = records
        .iter()
        .map(|r| {
            [
                r.sensor_id.as_str().to_owned(),
                time_text(r.issued_at),
                time_text(r.valid_from),
                r.valid_until.map_or_else(|| "-".to_owned(), time_text),
            ]
        })
        .collect();
    let width = |column: usize, title: &str| {
        rows.iter()
            .map(|row| row[column].len())
            .chain([title.len()])
            .max()
            .unwrap_or(0)
    };
    let (w_sensor, w_issued, w_from, w_until) = (
        width(0, "SENSOR"),
        width(1, "ISSUED"),
        width(2, "VALID FROM"),
        width(3, "VALID UNTIL"),
    );
    writeln!(
        out,
        "{:<w_sensor$}  {:>7}  {:<w_issued$}  {:<w_from$}  {:<w_until$}  CERTIFICATE",
        "SENSOR", "VERSION", "ISSUED", "VALID FROM", "VALID UNTIL"
    )?;
    for (r, [sensor, issued, from, until]) in records.iter().zip(&rows) {
        let mark = if Some(r.version) == current {
            "  (current)"
        } else {
            ""
        };
        writeln!(
            out,
            "{sensor:<w_sensor$}  {:>7}  {issued:<w_issued$}  {from:<w_from$}  {until:<w_until$}  {}{mark}",
            r.version, r.certificate.id
        )?;
    }
    Ok(())
}

fn write_skipped(out: &mut dyn Write, skipped: &[CorruptEntry]) -> io::Result<()> {
    for entry in skipped {
        writeln!(out, "warning: skipped {entry}")?;
    }
    Ok(())
}
