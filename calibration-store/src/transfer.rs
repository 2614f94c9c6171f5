//! Export to and import from a directory of JSON records: backup, restore, and moving a
//! building's calibrations to another gateway.
//!
//! An export holds every version of every sensor, one pretty-printed record per file, named
//! `<sensor>.v<version>.json` (`.` never occurs in a sensor id, so the name is unambiguous; it
//! is only a convenience, the content is what counts). An import reads every `*.json` file of a
//! directory, in any layout of names, and puts the records through the same validation and
//! version rules as [`Store::put`], oldest version first per sensor, reporting each file.

use std::fs;
use std::io::Write as _;
use std::path::{Path, PathBuf};

use triax_protocol::json::MAX_JSON_BYTES;
use triax_protocol::record::CalibrationRecord;
use triax_protocol::{from_json, to_json_pretty};

use crate::error::{CorruptEntry, Rejection, StoreError};
use crate::store::{PutOutcome, Store};

/// What an export wrote.
#[derive(Debug, Clone, PartialEq)]
pub struct ExportReport {
    /// One file per record, in store order (sensor, then version).
    pub files: Vec<PathBuf>,
    /// Entries that could not be decoded and were left out.
    pub skipped: Vec<CorruptEntry>,
}

/// What an import did with each file.
#[derive(Debug, Clone, PartialEq)]
pub struct ImportReport {
    /// Every `*.json` file of the directory, by file name.
    pub files: Vec<ImportedFile>,
}

impl ImportReport {
    /// Whether every file was stored or already present.
    pub fn all_accepted(&self) -> bool {
        self.files
            .iter()
            .all(|f| matches!(f.outcome, FileOutcome::Put(_)))
    }
}

/// One file of an import.
#[derive(Debug, Clone, PartialEq)]
pub struct ImportedFile {
    pub path: PathBuf,
    pub outcome: FileOutcome,
}

/// What happened to one file of an import.
#[derive(Debug, Clone, PartialEq)]
pub enum FileOutcome {
    /// The record was accepted: stored, already present, or repaired.
    Put(PutOutcome),
    /// The record was read but refused by the validation or version rules.
    Rejected(Rejection),
    /// The file could not be read or is not a calibration record.
    Unreadable(String),
}

/// File name of a record in an export.
pub fn export_file_name(record: &CalibrationRecord) -> String {
    format!("{}.v{}.json", record.sensor_id, record.version)
}

fn file_error(action: &'static str, path: &Path) -> impl FnOnce(std::io::Error) -> StoreError {
    let path = path.to_path_buf();
    move |source| StoreError::File {
        action,
        path,
        source,
    }
}

/// Writes a file so that it is either absent or complete, even if the process dies midway:
/// the bytes go to a temporary name, are synced, then renamed over the final name.
fn write_file_atomically(path: &Path, bytes: &[u8]) -> Result<(), StoreError> {
    let tmp = path.with_extension("json.tmp");
    let mut file = fs::File::create(&tmp).map_err(file_error("create", &tmp))?;
    file.write_all(bytes).map_err(file_error("write", &tmp))?;
    file.sync_all().map_err(file_error("sync", &tmp))?;
    fs::rename(&tmp, path).map_err(file_error("rename into", path))?;
    Ok(())
}

impl Store {
    /// Writes every version of every sensor to `dir` (created if missing), overwriting files of
    /// the same name. Returns once every file and the directory entry are synced to disk.
    pub fn export(&self, dir: impl AsRef<Path>) -> Result<ExportReport, StoreError> {
        let dir = dir.as_ref();
        fs::create_dir_all(dir).map_err(file_error("create directory", dir))?;
        let mut report = ExportReport {
            files: Vec::new(),
            skipped: Vec::new(),
        };
        let all = self.all_records()?;
        report.skipped = all.skipped;
        for record in &all.value {
            let path = dir.join(export_file_name(record));
            write_file_atomically(&path, &to_json_pretty(record))?;
            report.files.push(path);
        }
        // The renames are durable only once the directory itself is synced.
        fs::File::open(dir)
            .and_then(|d| d.sync_all())
            .map_err(file_error("sync directory", dir))?;
        Ok(report)
    }

    /// Puts every `*.json` file of `dir` (not its subdirectories) through [`Store::put`]'s
    /// rules, each sensor's records in increasing version order, with one flush at the end.
    /// Files that cannot be read or are refused are reported and do not stop the import.
    pub fn import(&self, dir: impl AsRef<Path>) -> Result<ImportReport, StoreError> {
        let dir = dir.as_ref();
        let mut paths = Vec::new();
        for entry in fs::read_dir(dir).map_err(file_error("read directory", dir))? {
            let entry = entry.map_err(file_error("read directory", dir))?;
            let path = entry.path();
            if path.extension().is_some_and(|e| e == "json") && path.is_file() {
                paths.push(path);
            }
        }
        paths.sort();

        let mut files: Vec<ImportedFile> = Vec::with_capacity(paths.len());
        let mut records: Vec<(usize, CalibrationRecord)> = Vec::new();
        for path in paths {
            let outcome = match read_record(&path) {
                Ok(record) => {
                    records.push((files.len(), record));
                    // Replaced below, once the record has been put.
                    FileOutcome::Unreadable(String::new())
                }
                Err(problem) => FileOutcome::Unreadable(problem),
            };
            files.push(ImportedFile { path, outcome });
        }
        // Oldest first per sensor, since a version below the current one is refused.
        records.sort_by(|(_, a), (_, b)| (&a.sensor_id, a.version).cmp(&(&b.sensor_id, b.version)));
        let outcomes = self.put_all(records.iter().map(|(_, r)| r))?;
        for ((index, _), outcome) in records.iter().zip(outcomes) {
            files[*index].outcome = match outcome {
                Ok(put) => FileOutcome::Put(put),
                Err(rejection) => FileOutcome::Rejected(rejection),
            };
        }
        Ok(ImportReport { files })
    }
}

fn read_record(path: &Path) -> Result<CalibrationRecord, String> {
    let len = fs::metadata(path).map_err(|e| e.to_string())?.len();
    // Checked before reading, so a stray large file is not loaded into memory.
    if len > MAX_JSON_BYTES as u64 {
        return Err(format!(
            "file is {len} bytes; a record is at most {MAX_JSON_BYTES}"
        ));
    }
    let bytes = fs::read(path).map_err(|e| e.to_string())?;
    from_json(&bytes).map_err(|e| e.to_string())
}
