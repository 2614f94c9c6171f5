//! Operators' annotations: a stretch of time on a building (or one of its sensors) with a note,
//! by whom and when ("crane lift 10:20–10:45", "sensor moved"), kept across restarts in an
//! append-only JSON-lines file beside the alert log, shown on every plot of that building and
//! exported as CSV.
//!
//! Each line is `{"annotation": {...}}` or `{"delete": {id, by, at}}`. Bounded by
//! [`MAX_ANNOTATIONS`] (the oldest go first); the file is rewritten (a temporary file renamed
//! over it) once it holds twice the lines worth keeping. A line that does not parse is skipped
//! with a warning naming the file and line.
//!
//! `source` says who made one: `operator` for every annotation made here. `event_report` is
//! kept for the marks an event-report service will publish; the console makes none yet, and the
//! page draws such marks apart from the operators' own.

use std::collections::VecDeque;
use std::fs::{File, OpenOptions};
use std::io::{BufRead, BufReader, Write};
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};
use time::OffsetDateTime;
use triax_protocol::{BuildingId, SensorId};

use crate::alertlog::{operator_text, FieldError};

/// The file's name in the state directory.
pub const FILE_NAME: &str = "annotations.jsonl";
/// Annotations kept.
pub const MAX_ANNOTATIONS: usize = 10_000;
/// Longest note, in characters.
pub const MAX_TEXT_CHARS: usize = 500;
/// Longest stretch one annotation covers (30 days).
pub const MAX_SPAN_NS: i64 = 30 * 86_400 * 1_000_000_000;
/// Annotations one answer lists at most.
pub const MAX_LISTED: usize = 1000;

/// Who deleted an annotation, and when.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Deletion {
    pub by: String,
    #[serde(with = "time::serde::rfc3339")]
    pub at: OffsetDateTime,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Annotation {
    pub id: u64,
    pub building: BuildingId,
    /// None: the whole building.
    pub sensor: Option<SensorId>,
    pub from_ns: i64,
    pub to_ns: i64,
    pub text: String,
    pub by: String,
    #[serde(with = "time::serde::rfc3339")]
    pub at: OffsetDateTime,
    /// `operator` (made here), or `event_report` (reserved for the event-report service).
    pub source: String,
}

#[derive(Debug, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
enum Line {
    Annotation(Annotation),
    Delete {
        id: u64,
        #[serde(flatten)]
        deletion: Deletion,
    },
}

#[derive(Debug, thiserror::Error)]
#[error("annotations {path}: {source}")]
pub struct AnnotationsError {
    pub path: PathBuf,
    #[source]
    pub source: std::io::Error,
}

/// The annotations. Not thread-safe by itself.
#[derive(Debug, Default)]
pub struct Annotations {
    path: Option<PathBuf>,
    file: Option<File>,
    /// Oldest first.
    kept: VecDeque<Annotation>,
    next_id: u64,
    lines_in_file: usize,
}

impl Annotations {
    pub fn in_memory() -> Annotations {
        Annotations {
            next_id: 1,
            ..Annotations::default()
        }
    }

    /// Opens (or creates) the file in `dir` and reads it back.
    pub fn open(dir: &Path) -> Result<Annotations, AnnotationsError> {
        let path = dir.join(FILE_NAME);
        let io = |source| AnnotationsError {
            path: path.clone(),
            source,
        };
        std::fs::create_dir_all(dir).map_err(io)?;
        let mut a = Annotations::in_memory();
        let mut lines = 0;
        match File::open(&path) {
            Ok(f) => {
                for (i, line) in BufReader::new(f).lines().enumerate() {
                    let line = line.map_err(io)?;
                    if line.trim().is_empty() {
                        continue;
                    }
                    lines += 1;
                    match serde_json::from_str::<Line>(&line) {
                        Ok(Line::Annotation(x)) => {
                            a.next_id = a.next_id.max(x.id + 1);
                            a.kept.push_back(x);
                        }
                        Ok(Line::Delete { id, .. }) => a.kept.retain(|x| x.id != id),
                        Err(e) => tracing::warn!(
                            file = %path.display(), line = i + 1, cause = %e,
                            "annotation line skipped"
                        ),
                    }
                }
            }
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => {}
            Err(e) => return Err(io(e)),
        }
        while a.kept.len() > MAX_ANNOTATIONS {
            a.kept.pop_front();
        }
        a.file = Some(
            OpenOptions::new()
                .create(true)
                .append(true)
                .open(&path)
                .map_err(io)?,
        );
        a.path = Some(path);
        a.lines_in_file = lines;
        Ok(a)
    }

    fn write(&mut self, line: &Line) {
        let Some(f) = &mut self.file else { return };
        let Ok(mut text) = serde_json::to_string(line) else {
            return;
        };
        text.push('\n');
        if let Err(e) = f.write_all(text.as_bytes()) {
            tracing::error!(cause = %e, "annotation not written");
        }
        self.lines_in_file += 1;
        if self.lines_in_file > 2 * self.kept.len() + 100 {
            self.compact();
        }
    }

    fn compact(&mut self) {
        let Some(path) = self.path.clone() else {
            return;
        };
        let tmp = path.with_extension("jsonl.tmp");
        let mut text = String::new();
        for a in &self.kept {
            if let Ok(t) = serde_json::to_string(&Line::Annotation(a.clone())) {
                text.push_str(&t);
                text.push('\n');
            }
        }
        let done = (|| -> std::io::Result<File> {
            let mut f = File::create(&tmp)?;
            f.write_all(text.as_bytes())?;
            f.sync_all()?;
            std::fs::rename(&tmp, &path)?;
            OpenOptions::new().append(true).open(&path)
        })();
        match done {
            Ok(f) => {
                self.file = Some(f);
                self.lines_in_file = self.kept.len();
            }
            Err(e) => tracing::error!(cause = %e, "annotations not compacted; appending still"),
        }
    }

    /// Adds an annotation by `by`.
    #[allow(clippy::too_many_arguments)]
    pub fn add(
        &mut self,
        building: BuildingId,
        sensor: Option<SensorId>,
        from_ns: i64,
        to_ns: i64,
        text: &str,
        by: &str,
        now: OffsetDateTime,
    ) -> Result<Annotation, FieldError> {
        let text = operator_text("text", text, MAX_TEXT_CHARS, true)?;
        if from_ns < 0 || to_ns < from_ns || to_ns - from_ns > MAX_SPAN_NS {
            return Err(FieldError {
                field: "to_ns",
                reason: format!(
                    "from_ns {from_ns} to to_ns {to_ns} is not a stretch of 0 to {} days",
                    MAX_SPAN_NS / 86_400_000_000_000
                ),
            });
        }
        let a = Annotation {
            id: self.next_id,
            building,
            sensor,
            from_ns,
            to_ns,
            text,
            by: by.to_owned(),
            at: now,
            source: "operator".into(),
        };
        self.next_id += 1;
        self.kept.push_back(a.clone());
        while self.kept.len() > MAX_ANNOTATIONS {
            self.kept.pop_front();
        }
        self.write(&Line::Annotation(a.clone()));
        Ok(a)
    }

    /// Deletes annotation `id`: its author may, and an admin (`any`).
    pub fn delete(
        &mut self,
        id: u64,
        by: &str,
        any: bool,
        now: OffsetDateTime,
    ) -> Result<Annotation, FieldError> {
        let Some(i) = self.kept.iter().position(|a| a.id == id) else {
            return Err(FieldError {
                field: "id",
                reason: format!("no annotation {id} is kept"),
            });
        };
        if !any && self.kept[i].by != by {
            return Err(FieldError {
                field: "id",
                reason: format!(
                    "annotation {id} is {:?}'s: only its author or an admin removes it",
                    self.kept[i].by
                ),
            });
        }
        let Some(a) = self.kept.remove(i) else {
            unreachable!("position found above")
        };
        self.write(&Line::Delete {
            id,
            deletion: Deletion {
                by: by.to_owned(),
                at: now,
            },
        });
        Ok(a)
    }

    /// The annotations of `building` that overlap `[from_ns, to_ns)`, oldest first, at most
    /// [`MAX_LISTED`]; and how many matched.
    pub fn list(
        &self,
        building: &BuildingId,
        from_ns: i64,
        to_ns: i64,
    ) -> (Vec<Annotation>, usize) {
        let all: Vec<&Annotation> = self
            .kept
            .iter()
            .filter(|a| &a.building == building && a.from_ns < to_ns && a.to_ns >= from_ns)
            .collect();
        let n = all.len();
        (all.into_iter().take(MAX_LISTED).cloned().collect(), n)
    }

    pub fn file(&self) -> Option<String> {
        self.path.as_ref().map(|p| p.display().to_string())
    }
}

/// A field of a CSV line: quoted, inner quotes doubled, and a leading `= + - @` made text so
/// that a spreadsheet does not take a note for a formula.
pub fn csv_field(s: &str) -> String {
    let guarded = if s.starts_with(['=', '+', '-', '@']) {
        format!("'{s}")
    } else {
        s.to_owned()
    };
    format!("\"{}\"", guarded.replace('"', "\"\""))
}

/// The annotations as CSV: `id,building,sensor,from_utc,to_utc,from_ns,to_ns,text,by,at,source`.
pub fn to_csv(list: &[Annotation]) -> String {
    let rfc = |ns: i64| {
        OffsetDateTime::from_unix_timestamp_nanos(i128::from(ns))
            .ok()
            .and_then(|d| {
                d.format(&time::format_description::well_known::Rfc3339)
                    .ok()
            })
            .unwrap_or_default()
    };
    let mut out =
        String::from("id,building,sensor,from_utc,to_utc,from_ns,to_ns,text,by,at,source\n");
    for a in list {
        out.push_str(&format!(
            "{},{},{},{},{},{},{},{},{},{},{}\n",
            a.id,
            a.building,
            a.sensor.as_ref().map(|s| s.as_str()).unwrap_or(""),
            rfc(a.from_ns),
            rfc(a.to_ns),
            a.from_ns,
            a.to_ns,
            csv_field(&a.text),
            csv_field(&a.by),
            a.at.format(&time::format_description::well_known::Rfc3339)
                .unwrap_or_default(),
            a.source
        ));
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn annotations_are_kept_deleted_and_read_back() {
        let dir = tempfile::tempdir().unwrap();
        let hq = BuildingId::new("hq").unwrap();
        let now = OffsetDateTime::now_utc();
        let mut a = Annotations::open(dir.path()).unwrap();
        let crane = a
            .add(hq.clone(), None, 10, 20, "crane lift", "alice", now)
            .unwrap();
        let moved = a
            .add(
                hq.clone(),
                Some(SensorId::new("acc-01").unwrap()),
                30,
                30,
                "=sensor moved",
                "bob",
                now,
            )
            .unwrap();
        assert!(a.add(hq.clone(), None, 20, 10, "x", "alice", now).is_err());
        assert!(a.add(hq.clone(), None, 1, 2, "", "alice", now).is_err());
        assert_eq!(
            a.delete(moved.id, "alice", false, now).unwrap_err().field,
            "id",
            "not her own"
        );
        drop(a);
        let mut a = Annotations::open(dir.path()).unwrap();
        assert_eq!(a.list(&hq, 0, 100).1, 2);
        assert_eq!(a.list(&hq, 21, 29).1, 0);
        a.delete(crane.id, "alice", false, now).unwrap();
        let csv = to_csv(&a.list(&hq, 0, 100).0);
        assert!(csv.contains(",\"'=sensor moved\",\"bob\","), "{csv}");
        drop(a);
        let a = Annotations::open(dir.path()).unwrap();
        assert_eq!(a.list(&hq, 0, 100).0, [moved]);
    }
}
