//! The node's buffer: every raw batch it sent, as published, in a bounded ring of append-only
//! segment files, served back by sequence number.
//!
//! # Layout
//!
//! A directory holding:
//! - `NODE`: the building and sensor the ring belongs to (JSON), written once at creation; a
//!   ring of another sensor or building is refused at open, since its batches would be served
//!   under the wrong key.
//! - `LOCK`: held with `flock` for the ring's life, so two nodes never write one directory.
//! - `SEQUENCE`: the lowest sequence number that may be used next, replaced atomically. Numbers
//!   are reserved ahead, [`RESERVE_STRIDE`] at a time, and written exactly at a clean close, so
//!   a number once published is never used again for other samples, even after a `kill -9` or
//!   a power cut that lost the ring's unsynced tail.
//! - `seg-<first sequence, 20 digits>.ring`: an 8-byte magic, then records
//!   `len: u32 | crc32: u32 | sequence: u64 | payload (len bytes)`, little-endian, the CRC over
//!   the sequence's 8 bytes and the payload. The payload is the raw batch exactly as published.
//!
//! # Guarantees
//!
//! - A record is appended with one `write` before its batch is handed to the publisher: a
//!   process killed after publishing a batch has it in the page cache, so it survives a
//!   `kill -9`; [`Ring::sync`] (`fdatasync`, called every second by the node) bounds what a
//!   power cut loses.
//! - Opening scans every segment, keeps each record whose CRC matches and whose payload is a
//!   raw batch, and cuts the last segment at its first bad record (a torn tail).
//! - The ring holds at least the last `capacity_batches` batches appended: the oldest segment
//!   is deleted only when the others hold that many, so disk use is bounded by
//!   `capacity_batches + segment_batches` records.
//! - A record is served only after its CRC matched again on reading.

use std::collections::VecDeque;
use std::fs::{File, OpenOptions};
use std::io::Write;
use std::os::unix::fs::FileExt;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex, MutexGuard};

use serde::{Deserialize, Serialize};
use triax_protocol::batch::RawBatchView;
use triax_protocol::{BuildingId, SensorId};

/// First bytes of every segment file.
pub const SEGMENT_MAGIC: [u8; 8] = *b"TXRING01";
/// Bytes before a record's payload.
pub const RECORD_HEADER: usize = 16;
/// Sequence numbers reserved ahead of use: one small durable write per this many batches
/// (100 s at 10 batches a second), and at most this many numbers skipped after a crash.
pub const RESERVE_STRIDE: u64 = 1000;
/// A payload longer than this is damage, not a batch (the largest raw batch is about 197 KB).
const MAX_PAYLOAD: u32 = 1 << 20;

#[derive(Debug, thiserror::Error)]
pub enum RingError {
    #[error("buffer {path}: {action}: {source}")]
    Io {
        action: &'static str,
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("buffer {path} is in use by another process")]
    Locked { path: PathBuf },
    #[error(
        "buffer {path} belongs to building {building}, sensor {sensor}, not to building \
         {want_building}, sensor {want_sensor}: give each sensor its own --buffer-dir"
    )]
    Foreign {
        path: PathBuf,
        building: String,
        sensor: String,
        want_building: String,
        want_sensor: String,
    },
    #[error("buffer {path}: {problem}")]
    Damaged { path: PathBuf, problem: String },
    #[error("buffer: sequence {got} appended where {expected} was next")]
    OutOfOrder { got: u64, expected: u64 },
}

fn io<'a>(action: &'static str, path: &'a Path) -> impl FnOnce(std::io::Error) -> RingError + 'a {
    move |source| RingError::Io {
        action,
        path: path.to_owned(),
        source,
    }
}

/// How a ring is opened.
#[derive(Debug, Clone)]
pub struct RingConfig {
    pub dir: PathBuf,
    pub building: BuildingId,
    pub sensor: SensorId,
    /// Batches the ring holds at least (the newest ones).
    pub capacity_batches: u64,
    /// Batches per segment file; the ring deletes a whole segment at a time.
    pub segment_batches: u64,
}

impl RingConfig {
    /// A ring holding `span_s` seconds of batches of `batch_samples` at `rate_hz`, in about
    /// twenty segments (so it holds up to 5 % more than asked).
    pub fn for_span(
        dir: PathBuf,
        building: BuildingId,
        sensor: SensorId,
        span_s: f64,
        rate_hz: f64,
        batch_samples: usize,
    ) -> RingConfig {
        let capacity_batches = (span_s * rate_hz / batch_samples as f64).ceil().max(1.0) as u64;
        RingConfig {
            dir,
            building,
            sensor,
            capacity_batches,
            segment_batches: capacity_batches.div_ceil(20).max(1),
        }
    }
}

#[derive(Debug, Serialize, Deserialize)]
struct NodeFile {
    format_version: u32,
    building: String,
    sensor: String,
}

#[derive(Debug, Clone, Copy)]
struct Entry {
    sequence: u64,
    offset: u64,
    len: u32,
    timestamp_ns: i64,
}

#[derive(Debug)]
struct Segment {
    path: PathBuf,
    entries: Vec<Entry>,
    /// Bytes of the file that hold whole records.
    len: u64,
}

struct Inner {
    segments: VecDeque<Segment>,
    /// The newest segment's file, open for appending; `None` until the first append, and after
    /// a write failed (the next append starts a new segment).
    writer: Option<Arc<File>>,
    batches: u64,
    bytes: u64,
    next_sequence: u64,
    /// Numbers below this are reserved in `SEQUENCE`.
    reserved_until: u64,
    unsynced: bool,
    record: Vec<u8>,
}

/// What a ring holds.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct RingStats {
    pub oldest_sequence: Option<u64>,
    pub newest_sequence: Option<u64>,
    pub oldest_timestamp_ns: Option<i64>,
    pub newest_timestamp_ns: Option<i64>,
    pub batches: u64,
    /// Bytes of the segment files.
    pub bytes: u64,
    pub segments: usize,
    pub next_sequence: u64,
}

/// What opening found.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct Recovery {
    /// Bytes cut off the last segment (a torn tail).
    pub torn_bytes: u64,
    /// Bytes ignored in earlier segments after damage.
    pub damaged_bytes: u64,
}

/// The ring. Appends come from one thread; reads may come from any.
pub struct Ring {
    config: RingConfig,
    inner: Mutex<Inner>,
    _lock: File,
    recovery: Recovery,
}

impl Ring {
    pub fn open(config: RingConfig) -> Result<Ring, RingError> {
        let dir = config.dir.clone();
        std::fs::create_dir_all(&dir).map_err(io("create directory", &dir))?;
        let lock_path = dir.join("LOCK");
        let lock = OpenOptions::new()
            .create(true)
            .truncate(false)
            .write(true)
            .open(&lock_path)
            .map_err(io("open lock file", &lock_path))?;
        if !triax_lockfile::try_lock_exclusive(&lock).map_err(io("lock", &lock_path))? {
            return Err(RingError::Locked { path: dir });
        }
        check_owner(&config)?;

        let mut names: Vec<(u64, PathBuf)> = Vec::new();
        for e in std::fs::read_dir(&dir).map_err(io("list", &dir))? {
            let e = e.map_err(io("list", &dir))?;
            let name = e.file_name();
            let Some(first) = name.to_str().and_then(parse_segment_name) else {
                continue;
            };
            names.push((first, e.path()));
        }
        names.sort();
        let mut recovery = Recovery::default();
        let mut segments = VecDeque::new();
        let count = names.len();
        for (i, (_, path)) in names.into_iter().enumerate() {
            let last = i + 1 == count;
            let (seg, bad_bytes) = scan_segment(&path, segments.back())?;
            if bad_bytes > 0 {
                if last {
                    recovery.torn_bytes = bad_bytes;
                    let f = OpenOptions::new()
                        .write(true)
                        .open(&path)
                        .map_err(io("open to cut a torn tail", &path))?;
                    f.set_len(seg.len).map_err(io("cut a torn tail", &path))?;
                    f.sync_all().map_err(io("sync", &path))?;
                    tracing::warn!(path = %path.display(), bytes = bad_bytes, "buffer: torn tail cut");
                } else {
                    recovery.damaged_bytes += bad_bytes;
                    tracing::warn!(path = %path.display(), bytes = bad_bytes, "buffer: damaged records ignored");
                }
            }
            if seg.entries.is_empty() {
                std::fs::remove_file(&path).map_err(io("remove empty segment", &path))?;
                continue;
            }
            segments.push_back(seg);
        }
        let batches = segments.iter().map(|s| s.entries.len() as u64).sum();
        let bytes = segments.iter().map(|s| s.len).sum();
        let after_newest = segments
            .back()
            .and_then(|s| s.entries.last())
            .map_or(0, |e| e.sequence + 1);
        let reserved = read_sequence_file(&dir)?;
        let next_sequence = after_newest.max(reserved.unwrap_or(0));
        let ring = Ring {
            inner: Mutex::new(Inner {
                segments,
                writer: None,
                batches,
                bytes,
                next_sequence,
                reserved_until: next_sequence,
                unsynced: false,
                record: Vec::new(),
            }),
            config,
            _lock: lock,
            recovery,
        };
        Ok(ring)
    }

    pub fn config(&self) -> &RingConfig {
        &self.config
    }

    /// What opening found and repaired.
    pub fn recovery(&self) -> Recovery {
        self.recovery
    }

    fn lock(&self) -> MutexGuard<'_, Inner> {
        // A panic under this lock leaves the index consistent (entries are pushed only after
        // their record is written), so a poisoned lock is still usable.
        self.inner.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// The sequence number of the next batch, reserved durably before it is returned.
    pub fn next_sequence(&self) -> Result<u64, RingError> {
        let mut inner = self.lock();
        let next = inner.next_sequence;
        if next >= inner.reserved_until {
            let until = next + RESERVE_STRIDE;
            write_sequence_file(&self.config.dir, until)?;
            inner.reserved_until = until;
        }
        Ok(next)
    }

    /// Appends the batch `payload` numbered `sequence`, which must be the number
    /// [`Self::next_sequence`] gave. The number is used even if the write fails.
    pub fn append(&self, sequence: u64, payload: &[u8]) -> Result<(), RingError> {
        let mut inner = self.lock();
        if sequence != inner.next_sequence {
            return Err(RingError::OutOfOrder {
                got: sequence,
                expected: inner.next_sequence,
            });
        }
        inner.next_sequence = sequence + 1;
        let view = RawBatchView::parse(payload).map_err(|e| RingError::Damaged {
            path: self.config.dir.clone(),
            problem: format!("batch {sequence} to append is not a raw batch: {e}"),
        })?;
        let timestamp_ns = view.header.timestamp_ns;
        let full = inner
            .segments
            .back()
            .is_none_or(|s| s.entries.len() as u64 >= self.config.segment_batches);
        if inner.writer.is_none() || full {
            self.roll(&mut inner, sequence)?;
        }
        let inner = &mut *inner;
        let Some(writer) = inner.writer.clone() else {
            // `roll` either set a writer or returned its error.
            unreachable!("a segment is open after roll")
        };
        inner.record.clear();
        encode_record(&mut inner.record, sequence, payload);
        // `roll` pushed the segment the writer appends to, or returned its error.
        let seg = inner
            .segments
            .back_mut()
            .expect("roll leaves a newest segment");
        let offset = seg.len;
        if let Err(source) = (&*writer).write_all(&inner.record) {
            // A part of the record may be on disk: cut it, and write on in a new segment so
            // that nothing after it is lost to a torn record.
            let _ = writer.set_len(offset);
            inner.writer = None;
            return Err(RingError::Io {
                action: "append",
                path: seg.path.clone(),
                source,
            });
        }
        seg.len += inner.record.len() as u64;
        seg.entries.push(Entry {
            sequence,
            offset,
            len: payload.len() as u32,
            timestamp_ns,
        });
        inner.batches += 1;
        inner.bytes += inner.record.len() as u64;
        inner.unsynced = true;
        Ok(())
    }

    /// Closes the newest segment (synced) and starts one at `sequence`, then deletes the oldest
    /// segments the others no longer need.
    fn roll(&self, inner: &mut Inner, sequence: u64) -> Result<(), RingError> {
        if let (Some(w), Some(seg)) = (inner.writer.take(), inner.segments.back()) {
            w.sync_data().map_err(io("sync", &seg.path))?;
        }
        inner.unsynced = false;
        let path = self.config.dir.join(segment_name(sequence));
        let mut f = OpenOptions::new()
            .create_new(true)
            .append(true)
            .open(&path)
            .map_err(io("create segment", &path))?;
        f.write_all(&SEGMENT_MAGIC)
            .map_err(io("write segment header", &path))?;
        sync_dir(&self.config.dir)?;
        inner.segments.push_back(Segment {
            path,
            entries: Vec::new(),
            len: SEGMENT_MAGIC.len() as u64,
        });
        inner.bytes += SEGMENT_MAGIC.len() as u64;
        inner.writer = Some(Arc::new(f));
        while inner.segments.len() > 1 {
            let oldest = inner.segments[0].entries.len() as u64;
            if inner.batches - oldest < self.config.capacity_batches {
                break;
            }
            let Some(old) = inner.segments.pop_front() else {
                break;
            };
            std::fs::remove_file(&old.path).map_err(io("remove oldest segment", &old.path))?;
            inner.batches -= oldest;
            inner.bytes -= old.len;
        }
        Ok(())
    }

    /// Puts every appended record on disk (`fdatasync`), if any is not yet.
    pub fn sync(&self) -> Result<(), RingError> {
        let (writer, path) = {
            let mut inner = self.lock();
            if !inner.unsynced {
                return Ok(());
            }
            inner.unsynced = false;
            let path = inner.segments.back().map(|s| s.path.clone());
            (inner.writer.clone(), path)
        };
        // Synced outside the lock: readers need not wait for the disk.
        if let (Some(w), Some(path)) = (writer, path) {
            w.sync_data().map_err(io("sync", &path))?;
        }
        Ok(())
    }

    /// Syncs and records the next sequence number exactly, so a clean restart continues
    /// without a gap.
    pub fn close(&self) -> Result<(), RingError> {
        self.sync()?;
        let mut inner = self.lock();
        write_sequence_file(&self.config.dir, inner.next_sequence)?;
        inner.reserved_until = inner.next_sequence;
        Ok(())
    }

    pub fn stats(&self) -> RingStats {
        let inner = self.lock();
        let first = inner.segments.front().and_then(|s| s.entries.first());
        let last = inner.segments.back().and_then(|s| s.entries.last());
        RingStats {
            oldest_sequence: first.map(|e| e.sequence),
            newest_sequence: last.map(|e| e.sequence),
            oldest_timestamp_ns: first.map(|e| e.timestamp_ns),
            newest_timestamp_ns: last.map(|e| e.timestamp_ns),
            batches: inner.batches,
            bytes: inner.bytes,
            segments: inner.segments.len(),
            next_sequence: inner.next_sequence,
        }
    }

    /// Calls `emit` with each batch held whose sequence number is in `from..=to`, in sequence
    /// order, until it returns `false`; returns how many it was given. A segment deleted since
    /// the index was read is skipped: its batches are no longer held.
    pub fn read_range(
        &self,
        from: u64,
        to: u64,
        mut emit: impl FnMut(u64, &[u8]) -> bool,
    ) -> Result<usize, RingError> {
        let plan: Vec<(PathBuf, Vec<Entry>)> = {
            let inner = self.lock();
            inner
                .segments
                .iter()
                .filter_map(|s| {
                    let lo = s.entries.partition_point(|e| e.sequence < from);
                    let hi = s.entries.partition_point(|e| e.sequence <= to);
                    (lo < hi).then(|| (s.path.clone(), s.entries[lo..hi].to_vec()))
                })
                .collect()
        };
        let mut n = 0;
        let mut buf = Vec::new();
        for (path, entries) in plan {
            let f = match File::open(&path) {
                Ok(f) => f,
                Err(e) if e.kind() == std::io::ErrorKind::NotFound => continue,
                Err(e) => return Err(io("open segment", &path)(e)),
            };
            for e in entries {
                buf.resize(RECORD_HEADER + e.len as usize, 0);
                f.read_exact_at(&mut buf, e.offset)
                    .map_err(io("read", &path))?;
                let Some((sequence, payload)) = decode_record(&buf) else {
                    return Err(RingError::Damaged {
                        path,
                        problem: format!(
                            "record of batch {} at byte {} no longer matches its CRC",
                            e.sequence, e.offset
                        ),
                    });
                };
                if sequence != e.sequence {
                    return Err(RingError::Damaged {
                        path,
                        problem: format!(
                            "byte {} holds batch {sequence}, not {}",
                            e.offset, e.sequence
                        ),
                    });
                }
                n += 1;
                if !emit(sequence, payload) {
                    return Ok(n);
                }
            }
        }
        Ok(n)
    }
}

fn segment_name(first_sequence: u64) -> String {
    format!("seg-{first_sequence:020}.ring")
}

fn parse_segment_name(name: &str) -> Option<u64> {
    let digits = name.strip_prefix("seg-")?.strip_suffix(".ring")?;
    if digits.len() != 20 || !digits.bytes().all(|b| b.is_ascii_digit()) {
        return None;
    }
    digits.parse().ok()
}

fn encode_record(out: &mut Vec<u8>, sequence: u64, payload: &[u8]) {
    let seq = sequence.to_le_bytes();
    let mut h = crc32fast::Hasher::new();
    h.update(&seq);
    h.update(payload);
    out.extend_from_slice(&(payload.len() as u32).to_le_bytes());
    out.extend_from_slice(&h.finalize().to_le_bytes());
    out.extend_from_slice(&seq);
    out.extend_from_slice(payload);
}

/// The sequence number and payload of a whole record whose CRC matches.
fn decode_record(rec: &[u8]) -> Option<(u64, &[u8])> {
    let header: &[u8; RECORD_HEADER] = rec.get(..RECORD_HEADER)?.try_into().ok()?;
    let [l0, l1, l2, l3, c0, c1, c2, c3, s @ ..] = *header;
    let len = u32::from_le_bytes([l0, l1, l2, l3]) as usize;
    let crc = u32::from_le_bytes([c0, c1, c2, c3]);
    let payload = rec.get(RECORD_HEADER..RECORD_HEADER + len)?;
    let mut h = crc32fast::Hasher::new();
    h.update(&s);
    h.update(payload);
    (h.finalize() == crc).then_some((u64::from_le_bytes(s), payload))
}

/// Reads a segment's good records; returns them and the bytes after the last good one.
fn scan_segment(path: &Path, previous: Option<&Segment>) -> Result<(Segment, u64), RingError> {
    let bytes = std::fs::read(path).map_err(io("read segment", path))?;
    let mut seg = Segment {
        path: path.to_owned(),
        entries: Vec::new(),
        len: 0,
    };
    if bytes.len() < SEGMENT_MAGIC.len() {
        // Created, header not yet written: an empty segment.
        return Ok((seg, bytes.len() as u64));
    }
    if bytes[..SEGMENT_MAGIC.len()] != SEGMENT_MAGIC {
        return Err(RingError::Damaged {
            path: path.to_owned(),
            problem: "not a buffer segment (wrong magic); move it out of the buffer directory"
                .into(),
        });
    }
    let mut last_seq = previous.and_then(|p| p.entries.last()).map(|e| e.sequence);
    let mut pos = SEGMENT_MAGIC.len();
    while pos < bytes.len() {
        let rest = &bytes[pos..];
        let Some(len) = rest
            .get(..4)
            .map(|b| u32::from_le_bytes([b[0], b[1], b[2], b[3]]))
        else {
            break;
        };
        if len > MAX_PAYLOAD {
            break;
        }
        let Some((sequence, payload)) = decode_record(rest) else {
            break;
        };
        if last_seq.is_some_and(|l| sequence <= l) {
            break;
        }
        let Ok(view) = RawBatchView::parse(payload) else {
            break;
        };
        seg.entries.push(Entry {
            sequence,
            offset: pos as u64,
            len,
            timestamp_ns: view.header.timestamp_ns,
        });
        last_seq = Some(sequence);
        pos += RECORD_HEADER + len as usize;
    }
    seg.len = pos as u64;
    Ok((seg, (bytes.len() - pos) as u64))
}

fn check_owner(config: &RingConfig) -> Result<(), RingError> {
    let path = config.dir.join("NODE");
    match std::fs::read(&path) {
        Ok(bytes) => {
            let node: NodeFile =
                serde_json::from_slice(&bytes).map_err(|e| RingError::Damaged {
                    path: path.clone(),
                    problem: format!("NODE file unreadable: {e}"),
                })?;
            if node.building != config.building.as_str() || node.sensor != config.sensor.as_str() {
                return Err(RingError::Foreign {
                    path: config.dir.clone(),
                    building: node.building,
                    sensor: node.sensor,
                    want_building: config.building.to_string(),
                    want_sensor: config.sensor.to_string(),
                });
            }
            Ok(())
        }
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
            let node = NodeFile {
                format_version: 1,
                building: config.building.to_string(),
                sensor: config.sensor.to_string(),
            };
            // Two strings and a number always serialise.
            let text = serde_json::to_vec(&node).expect("NODE serialises");
            write_atomically(&config.dir, "NODE", &text)
        }
        Err(e) => Err(io("read", &path)(e)),
    }
}

fn read_sequence_file(dir: &Path) -> Result<Option<u64>, RingError> {
    let path = dir.join("SEQUENCE");
    match std::fs::read_to_string(&path) {
        Ok(text) => text
            .trim()
            .parse()
            .map(Some)
            .map_err(|_| RingError::Damaged {
                path,
                problem: format!("SEQUENCE holds {:?}, not a whole number", text.trim()),
            }),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(None),
        Err(e) => Err(io("read", &path)(e)),
    }
}

fn write_sequence_file(dir: &Path, next: u64) -> Result<(), RingError> {
    write_atomically(dir, "SEQUENCE", format!("{next}\n").as_bytes())
}

/// Replaces `dir/name` with `bytes`, durably: a temporary file, synced, renamed over it.
fn write_atomically(dir: &Path, name: &str, bytes: &[u8]) -> Result<(), RingError> {
    let tmp = dir.join(format!("{name}.tmp"));
    let path = dir.join(name);
    let mut f = File::create(&tmp).map_err(io("create", &tmp))?;
    f.write_all(bytes).map_err(io("write", &tmp))?;
    f.sync_all().map_err(io("sync", &tmp))?;
    std::fs::rename(&tmp, &path).map_err(io("rename", &path))?;
    sync_dir(dir)
}

fn sync_dir(dir: &Path) -> Result<(), RingError> {
    File::open(dir)
        .and_then(|d| d.sync_all())
        .map_err(io("sync directory", dir))
}

#[cfg(test)]
mod tests {
    use super::*;
    use triax_protocol::batch::{BatchHeader, RawBatch};

    fn batch(sensor: &str, sequence: u64) -> Vec<u8> {
        RawBatch {
            header: BatchHeader {
                sensor_id: SensorId::new(sensor).unwrap(),
                sequence,
                timestamp_ns: 1_800_000_000_000_000_000 + sequence as i64 * 100_000_000,
                sample_rate_hz: 100.0,
            },
            temperature_c: Some(21.0),
            samples: (0..10)
                .map(|i| [sequence as f32, i as f32, -(i as f32)])
                .collect(),
        }
        .encode()
    }

    fn config(dir: &Path, capacity: u64, segment: u64) -> RingConfig {
        RingConfig {
            dir: dir.to_owned(),
            building: BuildingId::new("hq").unwrap(),
            sensor: SensorId::new("acc-01").unwrap(),
            capacity_batches: capacity,
            segment_batches: segment,
        }
    }

    fn push(ring: &Ring, n: u64) -> Vec<(u64, Vec<u8>)> {
        (0..n)
            .map(|_| {
                let s = ring.next_sequence().unwrap();
                let b = batch("acc-01", s);
                ring.append(s, &b).unwrap();
                (s, b)
            })
            .collect()
    }

    fn all(ring: &Ring) -> Vec<(u64, Vec<u8>)> {
        let mut out = Vec::new();
        ring.read_range(0, u64::MAX, |s, p| {
            out.push((s, p.to_vec()));
            true
        })
        .unwrap();
        out
    }

    fn segment_files(dir: &Path) -> Vec<PathBuf> {
        let mut v: Vec<PathBuf> = std::fs::read_dir(dir)
            .unwrap()
            .map(|e| e.unwrap().path())
            .filter(|p| p.extension().is_some_and(|e| e == "ring"))
            .collect();
        v.sort();
        v
    }

    #[test]
    fn wraps_around_keeping_at_least_its_capacity() {
        let dir = tempfile::tempdir().unwrap();
        let ring = Ring::open(config(dir.path(), 25, 10)).unwrap();
        let sent = push(&ring, 103);
        let held = all(&ring);
        // Whole segments of 10 go: between 25 and 35 of the newest are held.
        assert!((25..=35).contains(&held.len()), "{}", held.len());
        assert_eq!(held[..], sent[sent.len() - held.len()..]);
        assert_eq!(held.len(), 33, "segments 70.., 80.., 90.., 100..");
        let st = ring.stats();
        assert_eq!(st.oldest_sequence, Some(70));
        assert_eq!(st.newest_sequence, Some(102));
        assert_eq!(st.batches, 33);
        assert_eq!(st.segments, 4);
        let on_disk: u64 = segment_files(dir.path())
            .iter()
            .map(|p| p.metadata().unwrap().len())
            .sum();
        assert_eq!(st.bytes, on_disk);
        // A range inside, and one that reaches past both ends.
        let mut got = Vec::new();
        ring.read_range(75, 77, |s, _| {
            got.push(s);
            true
        })
        .unwrap();
        assert_eq!(got, [75, 76, 77]);
        got.clear();
        ring.read_range(0, 71, |s, _| {
            got.push(s);
            true
        })
        .unwrap();
        assert_eq!(got, [70, 71]);
    }

    #[test]
    fn a_restart_keeps_everything_and_continues_the_numbers() {
        let dir = tempfile::tempdir().unwrap();
        let ring = Ring::open(config(dir.path(), 100, 7)).unwrap();
        let mut sent = push(&ring, 20);
        ring.close().unwrap();
        drop(ring);
        let ring = Ring::open(config(dir.path(), 100, 7)).unwrap();
        assert_eq!(all(&ring), sent);
        assert_eq!(
            ring.next_sequence().unwrap(),
            20,
            "a clean close leaves no gap"
        );
        sent.extend(push(&ring, 5));
        assert_eq!(all(&ring), sent);

        // Without a close (kill -9): nothing is lost, and numbers move past the reservation,
        // never back over one that may have been published.
        drop(ring);
        let ring = Ring::open(config(dir.path(), 100, 7)).unwrap();
        assert_eq!(all(&ring), sent);
        let next = ring.next_sequence().unwrap();
        assert_eq!(next, 20 + RESERVE_STRIDE);
    }

    #[test]
    fn a_torn_tail_is_cut_and_the_rest_kept() {
        let dir = tempfile::tempdir().unwrap();
        let ring = Ring::open(config(dir.path(), 100, 50)).unwrap();
        let sent = push(&ring, 12);
        drop(ring);
        let seg = segment_files(dir.path()).pop().unwrap();
        let len = seg.metadata().unwrap().len();
        // Half of the last record reached the disk.
        let f = OpenOptions::new().write(true).open(&seg).unwrap();
        f.set_len(len - 40).unwrap();
        drop(f);
        let ring = Ring::open(config(dir.path(), 100, 50)).unwrap();
        assert!(ring.recovery().torn_bytes > 0);
        assert_eq!(all(&ring), sent[..11]);
        // Appends go on after the cut, and a restart reads them whole.
        let s = ring.next_sequence().unwrap();
        assert!(s > 11);
        let b = batch("acc-01", s);
        ring.append(s, &b).unwrap();
        ring.close().unwrap();
        drop(ring);
        let ring = Ring::open(config(dir.path(), 100, 50)).unwrap();
        assert_eq!(ring.recovery(), Recovery::default());
        let held = all(&ring);
        assert_eq!(held.len(), 12);
        assert_eq!(held[11], (s, b));
    }

    #[test]
    fn a_flipped_byte_ends_the_good_records() {
        let dir = tempfile::tempdir().unwrap();
        let ring = Ring::open(config(dir.path(), 100, 50)).unwrap();
        let sent = push(&ring, 5);
        drop(ring);
        let seg = segment_files(dir.path()).pop().unwrap();
        let mut bytes = std::fs::read(&seg).unwrap();
        let rec = RECORD_HEADER + sent[0].1.len();
        // A byte in the payload of the fourth record.
        bytes[SEGMENT_MAGIC.len() + 3 * rec + RECORD_HEADER + 20] ^= 0x40;
        std::fs::write(&seg, &bytes).unwrap();
        let ring = Ring::open(config(dir.path(), 100, 50)).unwrap();
        assert_eq!(all(&ring), sent[..3]);
    }

    #[test]
    fn one_node_per_directory_and_sensor() {
        let dir = tempfile::tempdir().unwrap();
        let ring = Ring::open(config(dir.path(), 100, 50)).unwrap();
        assert!(matches!(
            Ring::open(config(dir.path(), 100, 50)),
            Err(RingError::Locked { .. })
        ));
        drop(ring);
        let mut other = config(dir.path(), 100, 50);
        other.sensor = SensorId::new("acc-02").unwrap();
        let e = Ring::open(other).err().unwrap();
        assert!(e.to_string().contains("sensor acc-01"), "{e}");
    }

    #[test]
    fn a_span_sets_capacity_and_segments() {
        let c = RingConfig::for_span(
            "/x".into(),
            BuildingId::new("hq").unwrap(),
            SensorId::new("a").unwrap(),
            3600.0,
            100.0,
            10,
        );
        assert_eq!(c.capacity_batches, 36_000);
        assert_eq!(c.segment_batches, 1_800);
    }
}
