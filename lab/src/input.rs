//! Reading the lab's input files: numeric CSV tables and the TOML bench file.
//!
//! Every problem is reported as an [`InputError`] naming the file, the line (1-based, as an
//! editor shows it), the column where there is one, and what is wrong. Nothing here panics on
//! bad input and nothing is written.
//!
//! CSV: the first non-blank line is the header; column names are matched exactly after trimming
//! spaces; extra columns are ignored; blank lines and lines starting with `#` are skipped; no
//! quoting (the files are numbers only).

use std::collections::HashSet;
use std::fmt;
use std::path::{Path, PathBuf};

use nalgebra::Vector3;
use serde::Deserialize;
use triax_calibration::fit::dynamic::{Bench, Recording};
use triax_calibration::fit::reference::check_time_axis;
use triax_calibration::fit::{
    reference_from_angles, MotionLaw, ReferenceMethod, StaticObservation,
};

/// A problem in an input file.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub struct InputError {
    pub file: PathBuf,
    /// 1-based line; `None` for problems with the file as a whole.
    pub line: Option<usize>,
    /// Column name (CSV) or 1-based column number (TOML).
    pub column: Option<String>,
    pub problem: String,
}

impl fmt::Display for InputError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}", self.file.display())?;
        if let Some(line) = self.line {
            write!(f, ", line {line}")?;
        }
        if let Some(column) = &self.column {
            write!(f, ", column {column}")?;
        }
        write!(f, ": {}", self.problem)
    }
}

impl InputError {
    pub fn file(file: &Path, problem: impl Into<String>) -> Self {
        Self {
            file: file.to_path_buf(),
            line: None,
            column: None,
            problem: problem.into(),
        }
    }

    pub fn at(file: &Path, line: usize, column: Option<&str>, problem: impl Into<String>) -> Self {
        Self {
            file: file.to_path_buf(),
            line: Some(line),
            column: column.map(str::to_string),
            problem: problem.into(),
        }
    }
}

fn read_text(path: &Path) -> Result<String, InputError> {
    std::fs::read_to_string(path).map_err(|e| InputError::file(path, format!("cannot read: {e}")))
}

/// A CSV file split into header and rows, not yet interpreted.
#[derive(Debug, Clone)]
pub struct RawCsv {
    pub path: PathBuf,
    pub header: Vec<String>,
    pub header_line: usize,
    /// (line number, fields) of each data row.
    pub rows: Vec<(usize, Vec<String>)>,
}

/// Numeric columns taken from a CSV, with the line of each row.
#[derive(Debug, Clone)]
pub struct Table {
    pub columns: Vec<Vec<f64>>,
    pub lines: Vec<usize>,
}

impl RawCsv {
    pub fn read(path: &Path) -> Result<Self, InputError> {
        let text = read_text(path)?;
        let mut header = None;
        let mut rows = Vec::new();
        for (index, line) in text.lines().enumerate() {
            let number = index + 1;
            let trimmed = line.trim();
            if trimmed.is_empty() || trimmed.starts_with('#') {
                continue;
            }
            let fields: Vec<String> = trimmed.split(',').map(|f| f.trim().to_string()).collect();
            if header.is_none() {
                header = Some((number, fields));
            } else {
                rows.push((number, fields));
            }
        }
        let (header_line, header) =
            header.ok_or_else(|| InputError::file(path, "the file is empty: no header line"))?;
        let mut seen = HashSet::new();
        for name in &header {
            if !name.is_empty() && !seen.insert(name.as_str()) {
                return Err(InputError::at(
                    path,
                    header_line,
                    Some(name),
                    "column name appears twice in the header",
                ));
            }
        }
        Ok(Self {
            path: path.to_path_buf(),
            header,
            header_line,
            rows,
        })
    }

    pub fn has(&self, column: &str) -> bool {
        self.header.iter().any(|h| h == column)
    }

    /// The named columns as numbers; every cell must be a finite number.
    pub fn numeric(&self, columns: &[&str]) -> Result<Table, InputError> {
        let missing: Vec<&str> = columns.iter().copied().filter(|c| !self.has(c)).collect();
        if !missing.is_empty() {
            return Err(InputError::at(
                &self.path,
                self.header_line,
                None,
                format!(
                    "missing column(s) {}; the header has {}; expected at least {}",
                    missing.join(", "),
                    self.header.join(","),
                    columns.join(",")
                ),
            ));
        }
        let indices: Vec<usize> = columns
            .iter()
            .map(|c| self.header.iter().position(|h| h == c).unwrap_or(0))
            .collect();
        let mut out = vec![Vec::with_capacity(self.rows.len()); columns.len()];
        let mut lines = Vec::with_capacity(self.rows.len());
        for (line, fields) in &self.rows {
            for (k, &index) in indices.iter().enumerate() {
                let name = columns[k];
                let cell = fields.get(index).ok_or_else(|| {
                    InputError::at(
                        &self.path,
                        *line,
                        Some(name),
                        format!(
                            "the row has {} field(s) but the header has {}",
                            fields.len(),
                            self.header.len()
                        ),
                    )
                })?;
                let value: f64 = cell.parse().map_err(|_| {
                    InputError::at(
                        &self.path,
                        *line,
                        Some(name),
                        format!("'{cell}' is not a number"),
                    )
                })?;
                if !value.is_finite() {
                    return Err(InputError::at(
                        &self.path,
                        *line,
                        Some(name),
                        format!("'{cell}' is not a finite number"),
                    ));
                }
                out[k].push(value);
            }
            lines.push(*line);
        }
        Ok(Table {
            columns: out,
            lines,
        })
    }
}

/// The static CSV's rows.
#[derive(Debug, Clone)]
pub struct StaticRows {
    pub observations: Vec<StaticObservation>,
    /// The `temperature_c` column, when the file has one.
    pub temperatures_c: Option<Vec<f64>>,
}

/// Reads the static CSV: `ax_ref,ay_ref,az_ref,vx,vy,vz`, or `roll_deg,pitch_deg,vx,vy,vz`
/// (used only when the three reference columns are absent) with `gravity_mps2`; an optional
/// `temperature_c` column gives each row's sensor temperature, °C.
pub fn read_static(path: &Path, gravity_mps2: f64) -> Result<StaticRows, InputError> {
    let raw = RawCsv::read(path)?;
    let temperatures_c = if raw.has("temperature_c") {
        Some(raw.numeric(&["temperature_c"])?.columns.remove(0))
    } else {
        None
    };
    let outputs = ["vx", "vy", "vz"];
    let explicit = ["ax_ref", "ay_ref", "az_ref"];
    let angles = ["roll_deg", "pitch_deg"];
    let use_angles = !explicit.iter().any(|c| raw.has(c)) && angles.iter().all(|c| raw.has(c));
    let columns: Vec<&str> = if use_angles {
        angles.iter().chain(&outputs).copied().collect()
    } else {
        explicit.iter().chain(&outputs).copied().collect()
    };
    let table = raw.numeric(&columns)?;
    let c = &table.columns;
    let observations = (0..table.lines.len())
        .map(|i| {
            let reference_mps2 = if use_angles {
                reference_from_angles(c[0][i], c[1][i], gravity_mps2)
            } else {
                Vector3::new(c[0][i], c[1][i], c[2][i])
            };
            let o = if use_angles { 2 } else { 3 };
            StaticObservation {
                reference_mps2,
                output: Vector3::new(c[o][i], c[o + 1][i], c[o + 2][i]),
            }
        })
        .collect();
    Ok(StaticRows {
        observations,
        temperatures_c,
    })
}

/// A recording with the file line of each sample, so that errors found later by sample index
/// can still name the line.
#[derive(Debug, Clone)]
pub struct LoadedRecording {
    pub recording: Recording,
    pub path: PathBuf,
    pub lines: Vec<usize>,
}

/// Reads a recording CSV `t_s,theta_rad,vx,vy,vz` and checks its time axis.
pub fn read_recording(path: &Path, alpha_deg: f64) -> Result<LoadedRecording, InputError> {
    let raw = RawCsv::read(path)?;
    let table = raw.numeric(&["t_s", "theta_rad", "vx", "vy", "vz"])?;
    let c = table.columns;
    if c[0].len() < 3 {
        return Err(InputError::file(
            path,
            format!(
                "too few points: {} data row(s); a recording needs at least two whole cycles",
                c[0].len()
            ),
        ));
    }
    let name = path.display().to_string();
    check_time_axis(&name, &c[0], true).map_err(|e| map_sample_error(path, &table.lines, e))?;
    let output = (0..c[0].len())
        .map(|i| Vector3::new(c[2][i], c[3][i], c[4][i]))
        .collect();
    Ok(LoadedRecording {
        recording: Recording {
            name,
            alpha_deg,
            t_s: c[0].clone(),
            theta_rad: c[1].clone(),
            output,
        },
        path: path.to_path_buf(),
        lines: table.lines,
    })
}

/// Turns a fit error about sample `i` of a recording into one about its file line.
pub fn map_sample_error(
    path: &Path,
    lines: &[usize],
    error: triax_calibration::fit::FitError,
) -> InputError {
    match error {
        triax_calibration::fit::FitError::Recording {
            sample, problem, ..
        } => match lines.get(sample) {
            Some(&line) => InputError::at(path, line, None, problem),
            None => InputError::file(path, problem),
        },
        other => InputError::file(path, other.to_string()),
    }
}

/// A timestamped output series for `apply`: `t_s,vx,vy,vz`.
pub struct OutputSeries {
    pub t_s: Vec<f64>,
    pub output: Vec<[f64; 3]>,
    /// The optional `temperature_c` column, °C.
    pub temperature_c: Option<Vec<f64>>,
}

pub fn read_output_series(path: &Path) -> Result<OutputSeries, InputError> {
    let raw = RawCsv::read(path)?;
    let table = raw.numeric(&["t_s", "vx", "vy", "vz"])?;
    let c = table.columns;
    if c[0].is_empty() {
        return Err(InputError::file(path, "too few points: no data rows"));
    }
    check_time_axis(&path.display().to_string(), &c[0], false)
        .map_err(|e| map_sample_error(path, &table.lines, e))?;
    let temperature_c = if raw.has("temperature_c") {
        Some(raw.numeric(&["temperature_c"])?.columns.remove(0))
    } else {
        None
    };
    Ok(OutputSeries {
        output: (0..c[0].len())
            .map(|i| [c[1][i], c[2][i], c[3][i]])
            .collect(),
        t_s: c[0].clone(),
        temperature_c,
    })
}

/// Reads the spacer-block CSV `delta_r_mm,output`.
pub fn read_spacers(path: &Path) -> Result<Vec<(f64, f64)>, InputError> {
    let table = RawCsv::read(path)?.numeric(&["delta_r_mm", "output"])?;
    Ok(table.columns[0]
        .iter()
        .zip(&table.columns[1])
        .map(|(&d, &y)| (d, y))
        .collect())
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct BenchFile {
    radius_m: f64,
    radius_uncertainty_m: f64,
    #[serde(default = "default_gravity")]
    gravity_mps2: f64,
    #[serde(default = "default_points")]
    points_per_cycle: usize,
    #[serde(default = "default_reference")]
    reference: toml::Spanned<String>,
    motion: MotionFile,
    #[serde(default)]
    recording: Vec<RecordingFile>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct MotionFile {
    law: toml::Spanned<String>,
    frequency_hz: f64,
    amplitude_rad: f64,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct RecordingFile {
    file: toml::Spanned<String>,
    alpha_deg: f64,
}

fn default_gravity() -> f64 {
    9.80665
}
fn default_points() -> usize {
    20
}
fn default_reference() -> toml::Spanned<String> {
    toml::Spanned::new(0..0, "finite-difference".to_string())
}

/// A bench file with its recordings loaded.
#[derive(Debug, Clone)]
pub struct LoadedBench {
    pub bench: Bench,
    pub recordings: Vec<LoadedRecording>,
    pub path: PathBuf,
}

impl LoadedBench {
    pub fn recordings(&self) -> Vec<Recording> {
        self.recordings
            .iter()
            .map(|r| r.recording.clone())
            .collect()
    }

    /// Turns a fit error about a recording into one naming its file and line.
    pub fn locate(&self, error: triax_calibration::fit::FitError) -> crate::LabError {
        if let triax_calibration::fit::FitError::Recording { recording, .. } = &error {
            if let Some(r) = self
                .recordings
                .iter()
                .find(|r| &r.recording.name == recording)
            {
                return map_sample_error(&r.path, &r.lines, error).into();
            }
        }
        crate::LabError::Fit {
            file: self.path.clone(),
            source: error,
        }
    }
}

fn line_col(text: &str, offset: usize) -> (usize, usize) {
    let before = &text[..offset.min(text.len())];
    let line = before.matches('\n').count() + 1;
    let col = before.len() - before.rfind('\n').map_or(0, |p| p + 1) + 1;
    (line, col)
}

/// Reads a bench file and every recording it names (paths relative to the bench file).
/// `reference` overrides the file's method.
pub fn read_bench(
    path: &Path,
    reference: Option<ReferenceMethod>,
) -> Result<LoadedBench, InputError> {
    let text = read_text(path)?;
    let at_span = |span: std::ops::Range<usize>, problem: String| {
        let (line, col) = line_col(&text, span.start);
        InputError::at(path, line, Some(&col.to_string()), problem)
    };
    let file: BenchFile = toml::from_str(&text).map_err(|e| {
        let problem = e.message().to_string();
        match e.span() {
            Some(span) => at_span(span, problem),
            None => InputError::file(path, problem),
        }
    })?;
    if file.motion.law.get_ref() != "sine" {
        return Err(at_span(
            file.motion.law.span(),
            format!(
                "motion law '{}' is not supported; the only law is \"sine\"",
                file.motion.law.get_ref()
            ),
        ));
    }
    let method = match reference {
        Some(m) => m,
        None => ReferenceMethod::from_name(file.reference.get_ref()).ok_or_else(|| {
            at_span(
                file.reference.span(),
                format!(
                    "unknown reference '{}'; expected one of {}",
                    file.reference.get_ref(),
                    ReferenceMethod::ALL.map(|m| m.name()).join(", ")
                ),
            )
        })?,
    };
    let bench = Bench {
        radius_m: file.radius_m,
        radius_uncertainty_m: file.radius_uncertainty_m,
        gravity_mps2: file.gravity_mps2,
        points_per_cycle: file.points_per_cycle,
        reference: method,
        motion: MotionLaw {
            frequency_hz: file.motion.frequency_hz,
            amplitude_rad: file.motion.amplitude_rad,
        },
    };
    triax_calibration::fit::dynamic::check_bench(&bench)
        .map_err(|e| InputError::file(path, e.to_string()))?;
    if file.recording.is_empty() {
        return Err(InputError::file(
            path,
            "no [[recording]] tables: at least two recordings at different alpha_deg are needed",
        ));
    }
    let base = path.parent().unwrap_or(Path::new("."));
    let mut recordings = Vec::with_capacity(file.recording.len());
    for rec in &file.recording {
        let rec_path = base.join(rec.file.get_ref());
        if !rec_path.is_file() {
            return Err(at_span(
                rec.file.span(),
                format!("recording file {} does not exist", rec_path.display()),
            ));
        }
        recordings.push(read_recording(&rec_path, rec.alpha_deg)?);
    }
    Ok(LoadedBench {
        bench,
        recordings,
        path: path.to_path_buf(),
    })
}
