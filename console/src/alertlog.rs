//! The console's alert log: every alert it received, the operators' acknowledgements and
//! silences, kept across restarts in one append-only JSON-lines file.
//!
//! Each line is one event: `{"alert": {id, key, received_at, payload}}` with the payload as it
//! arrived (the signed envelope, PROTOCOL.md §3.6), `{"ack": {id, by, at, note}}`,
//! `{"silence": {...}}` or `{"lift": {id, by, at}}`. The payload is kept rather than the
//! verdict, so that a restarted console verifies every alert again against the keys it is
//! given now: trust is never read back from a file.
//!
//! Bounded: at most `max_alerts` alerts, none older than `retention`; when over, the oldest
//! alert that is not verified goes first, so a flood of forged alerts cannot push a verified
//! one out. The file is rewritten (to a temporary file, then renamed over) once it holds twice
//! as many lines as are worth keeping. A line that does not parse (the last one, torn by a
//! crash) is skipped with a warning naming the file and line. Lines are written through at
//! once but not synced: a console restart loses nothing; a power cut may lose the last ones.

use std::collections::VecDeque;
use std::fs::{File, OpenOptions};
use std::io::{BufRead, BufReader, Write};
use std::path::{Path, PathBuf};
use std::time::Duration;

use serde::{Deserialize, Serialize};
use time::OffsetDateTime;
use triax_protocol::messages::{AlertKind, AlertLevel};
use triax_protocol::{BuildingId, SensorId};

use crate::fleet::AlertEntry;

/// The log's file name in the state directory.
pub const FILE_NAME: &str = "alerts.jsonl";
/// Alerts kept by default.
pub const DEFAULT_MAX_ALERTS: usize = 10_000;
/// How long an alert is kept by default (90 days).
pub const DEFAULT_RETENTION: Duration = Duration::from_secs(90 * 86_400);
/// Longest operator name (`by`), in characters.
pub const MAX_BY_CHARS: usize = 64;
/// Longest note or reason, in characters.
pub const MAX_NOTE_CHARS: usize = 1000;
/// Longest silence.
pub const MAX_SILENCE: Duration = Duration::from_secs(7 * 86_400);
/// Silences kept (active and lifted or expired ones still listed).
pub const MAX_SILENCES: usize = 1000;

/// Who acknowledged an alert, when, and why.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Ack {
    pub by: String,
    #[serde(with = "time::serde::rfc3339")]
    pub at: OffsetDateTime,
    #[serde(default)]
    pub note: String,
}

/// Alerts of a building (one sensor or all, one kind or all) marked silenced while it lasts.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Silence {
    pub id: u64,
    pub building: BuildingId,
    /// None: every sensor of the building.
    pub sensor: Option<SensorId>,
    /// None: every kind.
    pub kind: Option<AlertKind>,
    #[serde(with = "time::serde::rfc3339")]
    pub from: OffsetDateTime,
    #[serde(with = "time::serde::rfc3339")]
    pub until: OffsetDateTime,
    pub by: String,
    #[serde(default)]
    pub reason: String,
    /// Lifted before `until`: who and when.
    #[serde(default)]
    pub lifted: Option<Ack>,
}

impl Silence {
    fn active_at(&self, t: OffsetDateTime) -> bool {
        self.lifted.is_none() && self.from <= t && t < self.until
    }

    fn covers(&self, e: &AlertEntry) -> bool {
        self.building == e.alert.building
            && self.sensor.as_ref().is_none_or(|s| *s == e.alert.sensor_id)
            && self.kind.is_none_or(|k| k == e.alert.kind)
    }
}

/// One line of the file.
#[derive(Debug, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
enum Line {
    Alert {
        id: u64,
        key: String,
        #[serde(with = "time::serde::rfc3339")]
        received_at: OffsetDateTime,
        payload: String,
    },
    Ack {
        id: u64,
        #[serde(flatten)]
        ack: Ack,
    },
    Silence(Silence),
    Lift {
        id: u64,
        #[serde(flatten)]
        ack: Ack,
    },
}

/// An alert as the log keeps it.
#[derive(Debug, Clone)]
pub struct Logged {
    pub key: String,
    pub payload: String,
    pub entry: AlertEntry,
    pub ack: Option<Ack>,
    /// The silence that covered it when it arrived.
    pub silenced_by: Option<u64>,
}

/// An alert as `/api/alerts` answers it: the alert, its trust, and what operators did.
#[derive(Debug, Clone, Serialize)]
pub struct AlertView {
    #[serde(flatten)]
    pub entry: AlertEntry,
    pub ack: Option<Ack>,
    pub silenced_by: Option<u64>,
}

/// An alert read back from the file, to be verified again and then [`AlertLog::restore`]d.
#[derive(Debug, Clone)]
pub struct Pending {
    pub id: u64,
    pub key: String,
    pub received_at: OffsetDateTime,
    pub payload: String,
}

/// Why the log could not be opened or written.
#[derive(Debug, thiserror::Error)]
pub enum AlertLogError {
    #[error("alert log {path}: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
}

/// A refused acknowledgement or silence: the field and what is wrong with it.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("field {field:?}: {reason}")]
pub struct FieldError {
    pub field: &'static str,
    pub reason: String,
}

fn field(field: &'static str, reason: impl Into<String>) -> FieldError {
    FieldError {
        field,
        reason: reason.into(),
    }
}

/// A name or note from an operator: trimmed, no control characters, at most `max` characters.
pub fn operator_text(
    name: &'static str,
    text: &str,
    max: usize,
    required: bool,
) -> Result<String, FieldError> {
    let t = text.trim();
    if required && t.is_empty() {
        return Err(field(name, "must not be empty"));
    }
    if t.chars().count() > max {
        return Err(field(name, format!("longer than {max} characters")));
    }
    if t.chars().any(|c| c.is_control() && c != '\n') {
        return Err(field(name, "contains control characters"));
    }
    Ok(t.to_owned())
}

/// What `/api/alerts` selects; every field optional.
#[derive(Debug, Clone, Default)]
pub struct AlertQuery {
    /// One alert by its id.
    pub id: Option<u64>,
    pub building: Option<BuildingId>,
    pub sensor: Option<SensorId>,
    pub kind: Option<AlertKind>,
    /// `exceeded`, `possible`, `stale`: verified alerts at that level; `unverified`: any alert
    /// not signed by a trusted key, whatever it claims.
    pub level: Option<LevelFilter>,
    pub state: StateFilter,
    /// On the alert's `at`, ns since the Unix epoch, `[from, to)`.
    pub from_ns: Option<i64>,
    pub to_ns: Option<i64>,
    pub limit: usize,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LevelFilter {
    Verified(AlertLevel),
    Unverified,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum StateFilter {
    #[default]
    All,
    /// Neither acknowledged nor silenced.
    Open,
    Acknowledged,
    Silenced,
}

/// The answer to a query.
#[derive(Debug, Clone, Serialize)]
pub struct QueryAnswer {
    /// Newest first, at most `limit`.
    pub alerts: Vec<AlertView>,
    /// How many alerts match (beyond `limit` too).
    pub matched: usize,
    /// How many alerts the log keeps.
    pub kept: usize,
    /// Open alerts (neither acknowledged nor silenced), all buildings.
    pub open: usize,
    pub max_alerts: usize,
    pub retention_days: f64,
    /// Where the log is kept; null: in memory only.
    pub file: Option<String>,
}

/// The log. Not thread-safe by itself: the fleet holds it under its lock.
#[derive(Debug)]
pub struct AlertLog {
    path: Option<PathBuf>,
    file: Option<File>,
    /// Oldest first.
    alerts: VecDeque<Logged>,
    silences: VecDeque<Silence>,
    next_id: u64,
    next_silence_id: u64,
    lines_in_file: usize,
    max_alerts: usize,
    retention: Duration,
    pending: Vec<Pending>,
    /// Acknowledgements read back, applied as their alerts are restored.
    pending_acks: std::collections::HashMap<u64, Ack>,
}

impl AlertLog {
    /// A log that keeps alerts in memory only (lost on restart).
    pub fn in_memory(max_alerts: usize, retention: Duration) -> AlertLog {
        AlertLog {
            path: None,
            file: None,
            alerts: VecDeque::new(),
            silences: VecDeque::new(),
            next_id: 1,
            next_silence_id: 1,
            lines_in_file: 0,
            max_alerts: max_alerts.max(1),
            retention,
            pending: Vec::new(),
            pending_acks: std::collections::HashMap::new(),
        }
    }

    /// Opens (creating it and its directory if need be) the log in `dir`. The alerts read back
    /// wait in [`AlertLog::take_pending`] to be verified again.
    pub fn open(
        dir: &Path,
        max_alerts: usize,
        retention: Duration,
    ) -> Result<AlertLog, AlertLogError> {
        let path = dir.join(FILE_NAME);
        let io = |source| AlertLogError::Io {
            path: path.clone(),
            source,
        };
        std::fs::create_dir_all(dir).map_err(io)?;
        let mut log = AlertLog::in_memory(max_alerts, retention);
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
                        Ok(Line::Alert {
                            id,
                            key,
                            received_at,
                            payload,
                        }) => {
                            log.next_id = log.next_id.max(id + 1);
                            log.pending.push(Pending {
                                id,
                                key,
                                received_at,
                                payload,
                            });
                        }
                        Ok(Line::Ack { id, ack }) => {
                            // The first acknowledgement stands.
                            log.pending_acks.entry(id).or_insert(ack);
                        }
                        Ok(Line::Silence(s)) => {
                            log.next_silence_id = log.next_silence_id.max(s.id + 1);
                            log.silences.retain(|x| x.id != s.id);
                            log.silences.push_back(s);
                        }
                        Ok(Line::Lift { id, ack }) => {
                            if let Some(s) = log.silences.iter_mut().find(|s| s.id == id) {
                                s.lifted = Some(ack);
                            }
                        }
                        Err(e) => tracing::warn!(
                            file = %path.display(), line = i + 1, cause = %e,
                            "alert log line skipped"
                        ),
                    }
                }
            }
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => {}
            Err(e) => return Err(io(e)),
        }
        let file = OpenOptions::new()
            .create(true)
            .append(true)
            .open(&path)
            .map_err(io)?;
        log.file = Some(file);
        log.path = Some(path);
        log.lines_in_file = lines;
        Ok(log)
    }

    /// The alerts read back from the file, oldest first, to verify again.
    pub fn take_pending(&mut self) -> Vec<Pending> {
        std::mem::take(&mut self.pending)
    }

    /// Puts back an alert read from the file, verified again as `entry`.
    pub fn restore(&mut self, p: Pending, entry: AlertEntry) {
        let silenced_by = self.silence_for(&entry, entry.received_at);
        self.alerts.push_back(Logged {
            key: p.key,
            payload: p.payload,
            ack: self.pending_acks.remove(&p.id),
            entry,
            silenced_by,
        });
        self.bound(OffsetDateTime::now_utc());
    }

    /// Ends a restore: acknowledgements of alerts no longer kept are dropped, and the file is
    /// rewritten if it holds much more than is kept.
    pub fn restored(&mut self) {
        self.pending_acks.clear();
        self.alerts.make_contiguous().sort_by_key(|l| l.entry.id);
        self.compact_if_needed();
    }

    fn silence_for(&self, e: &AlertEntry, t: OffsetDateTime) -> Option<u64> {
        self.silences
            .iter()
            .find(|s| s.active_at(t) && s.covers(e))
            .map(|s| s.id)
    }

    /// Records a new alert: gives it its id (written into `entry`) and appends it to the file.
    /// Returns the silence that covers it, if one does.
    pub fn record(&mut self, key: &str, payload: &[u8], entry: &mut AlertEntry) -> Option<u64> {
        entry.id = self.next_id;
        self.next_id += 1;
        let payload = String::from_utf8_lossy(payload).into_owned();
        self.write(&Line::Alert {
            id: entry.id,
            key: key.to_owned(),
            received_at: entry.received_at,
            payload: payload.clone(),
        });
        let silenced_by = self.silence_for(entry, entry.received_at);
        self.alerts.push_back(Logged {
            key: key.to_owned(),
            payload,
            entry: entry.clone(),
            ack: None,
            silenced_by,
        });
        self.bound(entry.received_at);
        self.compact_if_needed();
        silenced_by
    }

    /// Whether alert `id` is kept and acknowledged.
    pub fn is_acknowledged(&self, id: u64) -> bool {
        self.alerts
            .iter()
            .any(|l| l.entry.id == id && l.ack.is_some())
    }

    /// Drops what is past the retention or the count, unverified alerts first.
    fn bound(&mut self, now: OffsetDateTime) {
        let oldest_kept = now - self.retention;
        while self
            .alerts
            .front()
            .is_some_and(|l| l.entry.received_at < oldest_kept)
        {
            self.alerts.pop_front();
        }
        while self.alerts.len() > self.max_alerts {
            match self.alerts.iter().position(|l| !l.entry.verified()) {
                Some(i) => {
                    self.alerts.remove(i);
                }
                None => {
                    self.alerts.pop_front();
                }
            }
        }
        while self.silences.len() > MAX_SILENCES {
            match self.silences.iter().position(|s| !s.active_at(now)) {
                Some(i) => {
                    self.silences.remove(i);
                }
                None => {
                    self.silences.pop_front();
                }
            }
        }
    }

    fn write(&mut self, line: &Line) {
        let Some(file) = &mut self.file else { return };
        let mut text = match serde_json::to_string(line) {
            Ok(t) => t,
            Err(e) => {
                tracing::error!(cause = %e, "alert log line does not serialise");
                return;
            }
        };
        text.push('\n');
        // One write per line, so a crash tears at most the last one.
        if let Err(e) = file.write_all(text.as_bytes()) {
            tracing::error!(
                file = %self.path.as_deref().unwrap_or(Path::new("?")).display(),
                cause = %e,
                "alert log not written"
            );
        }
        self.lines_in_file += 1;
    }

    /// Lines worth keeping: the alerts, their acknowledgements, the silences and their lifts.
    fn lines_kept(&self) -> usize {
        self.alerts.len()
            + self.alerts.iter().filter(|l| l.ack.is_some()).count()
            + 2 * self.silences.len()
    }

    fn compact_if_needed(&mut self) {
        if self.path.is_none() || self.lines_in_file <= 2 * self.lines_kept() + 100 {
            return;
        }
        if let Err(e) = self.compact() {
            tracing::error!(cause = %e, "alert log not compacted; appending to it still");
        }
    }

    /// Rewrites the file with what is kept: a temporary file renamed over the log, so that a
    /// crash leaves either the old file or the new one.
    fn compact(&mut self) -> Result<(), AlertLogError> {
        let Some(path) = self.path.clone() else {
            return Ok(());
        };
        let tmp = path.with_extension("jsonl.tmp");
        let io = |source| AlertLogError::Io {
            path: tmp.clone(),
            source,
        };
        let mut lines = Vec::new();
        for s in &self.silences {
            let mut s = s.clone();
            let lifted = s.lifted.take();
            let id = s.id;
            lines.push(Line::Silence(s));
            if let Some(ack) = lifted {
                lines.push(Line::Lift { id, ack });
            }
        }
        for l in &self.alerts {
            lines.push(Line::Alert {
                id: l.entry.id,
                key: l.key.clone(),
                received_at: l.entry.received_at,
                payload: l.payload.clone(),
            });
            if let Some(ack) = &l.ack {
                lines.push(Line::Ack {
                    id: l.entry.id,
                    ack: ack.clone(),
                });
            }
        }
        let mut text = String::new();
        for l in &lines {
            // Our own types, string keys: they serialise.
            if let Ok(t) = serde_json::to_string(l) {
                text.push_str(&t);
                text.push('\n');
            }
        }
        let mut f = File::create(&tmp).map_err(io)?;
        f.write_all(text.as_bytes()).map_err(io)?;
        f.sync_all().map_err(io)?;
        drop(f);
        std::fs::rename(&tmp, &path).map_err(io)?;
        self.file = Some(
            OpenOptions::new()
                .append(true)
                .open(&path)
                .map_err(|source| AlertLogError::Io {
                    path: path.clone(),
                    source,
                })?,
        );
        self.lines_in_file = lines.len();
        Ok(())
    }

    /// Acknowledges the alerts `ids` by `by`. Every id must be kept; one already acknowledged
    /// keeps its first acknowledgement. Returns the ids newly acknowledged.
    pub fn acknowledge(
        &mut self,
        ids: &[u64],
        by: &str,
        note: &str,
        now: OffsetDateTime,
    ) -> Result<Vec<u64>, FieldError> {
        if ids.is_empty() {
            return Err(field("ids", "must name at least one alert"));
        }
        let by = operator_text("by", by, MAX_BY_CHARS, true)?;
        let note = operator_text("note", note, MAX_NOTE_CHARS, false)?;
        if let Some(id) = ids
            .iter()
            .find(|id| !self.alerts.iter().any(|l| l.entry.id == **id))
        {
            return Err(field("ids", format!("no alert {id} is kept")));
        }
        let ack = Ack { by, at: now, note };
        let mut done = Vec::new();
        for id in ids {
            let Some(l) = self.alerts.iter_mut().find(|l| l.entry.id == *id) else {
                continue;
            };
            if l.ack.is_none() {
                l.ack = Some(ack.clone());
                done.push(*id);
            }
        }
        for id in &done {
            self.write(&Line::Ack {
                id: *id,
                ack: ack.clone(),
            });
        }
        self.compact_if_needed();
        Ok(done)
    }

    /// Starts a silence; alerts that arrive while it lasts and match it are marked silenced.
    #[allow(clippy::too_many_arguments)]
    pub fn silence(
        &mut self,
        building: BuildingId,
        sensor: Option<SensorId>,
        kind: Option<AlertKind>,
        duration: Duration,
        by: &str,
        reason: &str,
        now: OffsetDateTime,
    ) -> Result<Silence, FieldError> {
        let by = operator_text("by", by, MAX_BY_CHARS, true)?;
        let reason = operator_text("reason", reason, MAX_NOTE_CHARS, false)?;
        if duration.is_zero() || duration > MAX_SILENCE {
            return Err(field(
                "duration_s",
                format!("must be from 1 to {} s", MAX_SILENCE.as_secs()),
            ));
        }
        let s = Silence {
            id: self.next_silence_id,
            building,
            sensor,
            kind,
            from: now,
            until: now + duration,
            by,
            reason,
            lifted: None,
        };
        self.next_silence_id += 1;
        self.write(&Line::Silence(s.clone()));
        self.silences.push_back(s.clone());
        self.bound(now);
        Ok(s)
    }

    /// Lifts an active silence.
    pub fn lift(&mut self, id: u64, by: &str, now: OffsetDateTime) -> Result<Silence, FieldError> {
        let by = operator_text("by", by, MAX_BY_CHARS, true)?;
        let Some(s) = self.silences.iter_mut().find(|s| s.id == id) else {
            return Err(field("id", format!("no silence {id} is kept")));
        };
        if !s.active_at(now) {
            return Err(field("id", format!("silence {id} is not active")));
        }
        let ack = Ack {
            by,
            at: now,
            note: String::new(),
        };
        s.lifted = Some(ack.clone());
        let s = s.clone();
        self.write(&Line::Lift { id, ack });
        Ok(s)
    }

    /// The silences kept, newest first, and whether each is active now.
    pub fn silences(&self, now: OffsetDateTime) -> Vec<serde_json::Value> {
        self.silences
            .iter()
            .rev()
            .map(|s| {
                let mut v = serde_json::to_value(s).unwrap_or_default();
                v["active"] = serde_json::Value::Bool(s.active_at(now));
                v
            })
            .collect()
    }

    pub fn query(&self, q: &AlertQuery) -> QueryAnswer {
        let mut matched = 0;
        let mut alerts = Vec::new();
        let mut open = 0;
        for l in self.alerts.iter().rev() {
            let is_open = l.ack.is_none() && l.silenced_by.is_none();
            open += usize::from(is_open);
            let a = &l.entry.alert;
            let at_ns = i64::try_from(a.at.unix_timestamp_nanos()).unwrap_or(i64::MAX);
            let keep = q.id.is_none_or(|id| id == l.entry.id)
                && q.building.as_ref().is_none_or(|b| *b == a.building)
                && q.sensor.as_ref().is_none_or(|s| *s == a.sensor_id)
                && q.kind.is_none_or(|k| k == a.kind)
                && match q.level {
                    None => true,
                    Some(LevelFilter::Unverified) => !l.entry.verified(),
                    Some(LevelFilter::Verified(level)) => l.entry.verified() && a.level == level,
                }
                && match q.state {
                    StateFilter::All => true,
                    StateFilter::Open => is_open,
                    StateFilter::Acknowledged => l.ack.is_some(),
                    StateFilter::Silenced => l.silenced_by.is_some(),
                }
                && q.from_ns.is_none_or(|f| at_ns >= f)
                && q.to_ns.is_none_or(|t| at_ns < t);
            if !keep {
                continue;
            }
            matched += 1;
            if alerts.len() < q.limit {
                alerts.push(AlertView {
                    entry: l.entry.clone(),
                    ack: l.ack.clone(),
                    silenced_by: l.silenced_by,
                });
            }
        }
        QueryAnswer {
            alerts,
            matched,
            kept: self.alerts.len(),
            open,
            max_alerts: self.max_alerts,
            retention_days: self.retention.as_secs_f64() / 86_400.0,
            file: self.path.as_ref().map(|p| p.display().to_string()),
        }
    }

    /// Alerts neither acknowledged nor silenced.
    pub fn open_count(&self) -> usize {
        self.alerts
            .iter()
            .filter(|l| l.ack.is_none() && l.silenced_by.is_none())
            .count()
    }

    /// How many alerts are kept.
    pub fn len(&self) -> usize {
        self.alerts.len()
    }

    pub fn is_empty(&self) -> bool {
        self.alerts.is_empty()
    }
}
