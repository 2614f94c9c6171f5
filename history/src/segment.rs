//! Segment files: a log of framed blocks and an index of fixed-size entries, one per block.
//!
//! ```text
//! <id>.log   frame*      frame = len:u32 crc32:u32 block(len bytes)      (little-endian)
//! <id>.idx   entry*      entry = 72 bytes, see `IndexEntry`
//! ```
//!
//! The writer appends a group of frames, syncs the log (`fdatasync`), then appends their index
//! entries. So the index never names a block that is not durable; after a crash it may lag the
//! log, or end in a torn entry. Opening checks the index (entries contiguous from offset 0, within
//! the log), keeps its valid prefix, and scans the log from there, checking each frame's CRC: the
//! log is cut after the last whole frame and the index rebuilt to match. A block damaged later
//! (bit rot) fails its CRC when read and is reported, never served.

use std::fs::{File, OpenOptions};
use std::io::{Read, Write};
use std::os::unix::fs::FileExt;
use std::path::{Path, PathBuf};

use triax_protocol::SensorId;

use crate::append::{Appender, Stage};
use crate::block::{Block, BlockSummary};
use crate::HistoryError;

pub use crate::block::FRAME_HEADER;
/// Bytes of an index entry.
pub const ENTRY_BYTES: usize = 72;
/// Largest block accepted when reading: a length past this is damage.
pub const MAX_BLOCK_BYTES: u32 = 64 << 20;

/// What the index keeps of one block.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct IndexEntry {
    /// Where the frame starts in the log.
    pub offset: u64,
    /// The frame's length, header included.
    pub frame_len: u32,
    /// FNV-1a of the sensor id (the block names the sensor; this finds it without reading).
    pub sensor_hash: u64,
    pub summary: BlockSummary,
}

impl IndexEntry {
    pub fn end(&self) -> u64 {
        self.offset + u64::from(self.frame_len)
    }

    fn encode(&self, out: &mut Vec<u8>) {
        let s = &self.summary;
        out.extend_from_slice(&self.offset.to_le_bytes());
        out.extend_from_slice(&self.frame_len.to_le_bytes());
        out.extend_from_slice(&u16::from(s.checkpoint).to_le_bytes());
        // Capped: a block of more than 65 535 batches is not written (see the writer).
        out.extend_from_slice(&(s.n_records.min(u32::from(u16::MAX)) as u16).to_le_bytes());
        out.extend_from_slice(&self.sensor_hash.to_le_bytes());
        out.extend_from_slice(&s.min_ts.to_le_bytes());
        out.extend_from_slice(&s.max_ts.to_le_bytes());
        out.extend_from_slice(&s.min_seq.to_le_bytes());
        out.extend_from_slice(&s.max_seq.to_le_bytes());
        out.extend_from_slice(&s.first_arrival.to_le_bytes());
        out.extend_from_slice(&s.last_arrival.to_le_bytes());
    }

    fn decode(b: &[u8; ENTRY_BYTES]) -> IndexEntry {
        let u64_at = |i: usize| {
            let mut a = [0u8; 8];
            a.copy_from_slice(&b[i..i + 8]);
            u64::from_le_bytes(a)
        };
        let u16_at = |i: usize| u16::from_le_bytes([b[i], b[i + 1]]);
        IndexEntry {
            offset: u64_at(0),
            frame_len: u32::from_le_bytes([b[8], b[9], b[10], b[11]]),
            sensor_hash: u64_at(16),
            summary: BlockSummary {
                checkpoint: u16_at(12) & 1 != 0,
                n_records: u32::from(u16_at(14)),
                min_ts: u64_at(24) as i64,
                max_ts: u64_at(32) as i64,
                min_seq: u64_at(40),
                max_seq: u64_at(48),
                first_arrival: u64_at(56),
                last_arrival: u64_at(64),
            },
        }
    }
}

/// FNV-1a of a sensor id.
pub fn sensor_hash(id: &str) -> u64 {
    let mut h: u64 = 0xcbf2_9ce4_8422_2325;
    for b in id.bytes() {
        h ^= u64::from(b);
        h = h.wrapping_mul(0x0100_0000_01b3);
    }
    h
}

pub fn log_path(dir: &Path, id: u64) -> PathBuf {
    dir.join(format!("{id:016}.log"))
}

pub fn idx_path(dir: &Path, id: u64) -> PathBuf {
    dir.join(format!("{id:016}.idx"))
}

/// What opening needs of a closed segment, kept beside it so that opening reads this small file
/// rather than the segment's whole index: its ranges and its sensors.
#[derive(Debug, Clone, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct SegmentMeta {
    /// Range of the first-sample times of its batches (min > max when it holds none).
    pub min_ts: i64,
    pub max_ts: i64,
    pub first_arrival: u64,
    pub last_arrival: u64,
    pub sensors: Vec<SensorId>,
}

pub fn meta_path(dir: &Path, id: u64) -> PathBuf {
    dir.join(format!("{id:016}.meta"))
}

/// A closed segment's meta file; none if it is missing or unreadable (the caller rebuilds it).
pub fn read_meta(dir: &Path, id: u64) -> Option<SegmentMeta> {
    let bytes = std::fs::read(meta_path(dir, id)).ok()?;
    serde_json::from_slice(&bytes).ok()
}

/// Writes a closed segment's meta file, whole or not at all.
pub fn write_meta(dir: &Path, id: u64, meta: &SegmentMeta) -> Result<(), HistoryError> {
    let path = meta_path(dir, id);
    let tmp = path.with_extension("meta.tmp");
    // Plain numbers and ids always serialise.
    let body = serde_json::to_vec(meta).expect("segment meta serialises");
    std::fs::write(&tmp, body).map_err(io("write a segment's meta", &tmp))?;
    std::fs::rename(&tmp, &path).map_err(io("write a segment's meta", &path))
}

/// The sensors of a segment's blocks, from one block header per sensor.
pub fn sensors_from_blocks(
    dir: &Path,
    id: u64,
    entries: &[IndexEntry],
) -> Result<Vec<SensorId>, HistoryError> {
    let lp = log_path(dir, id);
    let log = File::open(&lp).map_err(io("open a log", &lp))?;
    let mut seen = std::collections::HashSet::new();
    let mut ids = Vec::new();
    for e in entries {
        if !seen.insert(e.sensor_hash) {
            continue;
        }
        // Frame header, block version, id length, id.
        let mut head = vec![0u8; (FRAME_HEADER + 2 + 64).min(e.frame_len as usize)];
        log.read_exact_at(&mut head, e.offset)
            .map_err(io("read a block header", &lp))?;
        let id = head
            .get(FRAME_HEADER + 1)
            .and_then(|&n| head.get(FRAME_HEADER + 2..FRAME_HEADER + 2 + usize::from(n)))
            .and_then(|b| std::str::from_utf8(b).ok())
            .and_then(|s| SensorId::new(s).ok());
        ids.extend(id);
    }
    ids.sort();
    ids.dedup();
    Ok(ids)
}

/// The segment id of a log file name, if it is one.
pub fn parse_log_name(name: &str) -> Option<u64> {
    let stem = name.strip_suffix(".log")?;
    (stem.len() == 16 && stem.bytes().all(|b| b.is_ascii_digit()))
        .then(|| stem.parse().ok())
        .flatten()
}

fn io<'p>(
    action: &'static str,
    path: &'p Path,
) -> impl FnOnce(std::io::Error) -> HistoryError + 'p {
    move |source| HistoryError::Io {
        action,
        path: path.to_owned(),
        source,
    }
}

/// Reads the frame at `entry` from `log` and checks its CRC.
pub fn read_frame(log: &File, path: &Path, entry: &IndexEntry) -> Result<Vec<u8>, HistoryError> {
    let mut frame = vec![0u8; entry.frame_len as usize];
    log.read_exact_at(&mut frame, entry.offset)
        .map_err(io("read a block", path))?;
    check_frame(&frame).ok_or_else(|| HistoryError::Damaged {
        path: path.to_owned(),
        offset: entry.offset,
        reason: "length or CRC does not match".into(),
    })?;
    frame.drain(..FRAME_HEADER);
    Ok(frame)
}

/// The body of a whole frame whose CRC matches; none otherwise.
fn check_frame(frame: &[u8]) -> Option<&[u8]> {
    let (head, body) = frame.split_at_checked(FRAME_HEADER)?;
    let len = u32::from_le_bytes([head[0], head[1], head[2], head[3]]) as usize;
    let crc = u32::from_le_bytes([head[4], head[5], head[6], head[7]]);
    (len == body.len() && crc32fast::hash(body) == crc).then_some(body)
}

/// A segment brought back to a consistent state: its index entries, and how much was cut.
#[derive(Debug)]
pub struct Recovered {
    pub entries: Vec<IndexEntry>,
    pub log_bytes: u64,
    /// Bytes cut from the end of the log (a torn write).
    pub cut_bytes: u64,
    /// Entries rebuilt by scanning the log.
    pub rescanned: usize,
}

/// Checks a segment's index against its log, rebuilds what the index lacks, and cuts a torn
/// tail. Rewrites the files only when something was wrong.
pub fn recover(dir: &Path, id: u64) -> Result<Recovered, HistoryError> {
    let (lp, ip) = (log_path(dir, id), idx_path(dir, id));
    let log = OpenOptions::new()
        .read(true)
        .write(true)
        .open(&lp)
        .map_err(io("open a log", &lp))?;
    let log_len = log.metadata().map_err(io("stat a log", &lp))?.len();
    let mut idx_bytes = Vec::new();
    match File::open(&ip) {
        Ok(mut f) => {
            f.read_to_end(&mut idx_bytes)
                .map_err(io("read an index", &ip))?;
        }
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {}
        Err(e) => return Err(io("open an index", &ip)(e)),
    }
    let mut entries = Vec::with_capacity(idx_bytes.len() / ENTRY_BYTES);
    let mut end = 0u64;
    for chunk in idx_bytes.chunks_exact(ENTRY_BYTES) {
        // Cannot fail: chunks_exact yields ENTRY_BYTES-long slices.
        let e = IndexEntry::decode(chunk.try_into().expect("entry-sized chunk"));
        let sane = e.offset == end
            && e.frame_len as usize > FRAME_HEADER
            && e.frame_len <= MAX_BLOCK_BYTES
            && e.end() <= log_len;
        if !sane {
            break;
        }
        end = e.end();
        entries.push(e);
    }
    let indexed = entries.len();
    let index_whole = indexed * ENTRY_BYTES == idx_bytes.len();
    // Whatever the index does not cover is scanned frame by frame.
    let mut offset = end;
    while offset + FRAME_HEADER as u64 <= log_len {
        let mut head = [0u8; FRAME_HEADER];
        log.read_exact_at(&mut head, offset)
            .map_err(io("read a frame", &lp))?;
        let len = u32::from_le_bytes([head[0], head[1], head[2], head[3]]);
        let frame_len = FRAME_HEADER as u64 + u64::from(len);
        if len > MAX_BLOCK_BYTES || offset + frame_len > log_len {
            break;
        }
        let mut frame = vec![0u8; frame_len as usize];
        log.read_exact_at(&mut frame, offset)
            .map_err(io("read a frame", &lp))?;
        let Some(body) = check_frame(&frame) else {
            break;
        };
        let Ok(block) = Block::decode(body) else {
            break;
        };
        entries.push(entry_of(&block, offset, frame_len as u32));
        offset += frame_len;
    }
    let cut_bytes = log_len - offset;
    if cut_bytes > 0 {
        log.set_len(offset).map_err(io("cut a torn log", &lp))?;
        log.sync_all().map_err(io("sync a log", &lp))?;
    }
    let rescanned = entries.len() - indexed;
    if rescanned > 0 || !index_whole {
        let mut out = Vec::with_capacity(entries.len() * ENTRY_BYTES);
        for e in &entries {
            e.encode(&mut out);
        }
        let tmp = ip.with_extension("idx.tmp");
        std::fs::write(&tmp, &out).map_err(io("write an index", &tmp))?;
        std::fs::rename(&tmp, &ip).map_err(io("replace an index", &ip))?;
    }
    Ok(Recovered {
        entries,
        log_bytes: offset,
        cut_bytes,
        rescanned,
    })
}

/// The index entry of a decoded block.
fn entry_of(block: &Block<'_>, offset: u64, frame_len: u32) -> IndexEntry {
    let mut s = BlockSummary {
        checkpoint: block.checkpoint.is_some(),
        n_records: block.kept.len().min(u32::MAX as usize) as u32,
        min_ts: i64::MAX,
        max_ts: i64::MIN,
        min_seq: u64::MAX,
        max_seq: 0,
        first_arrival: block.kept.first().map_or(0, |k| k.arrival),
        last_arrival: block.kept.last().map_or(0, |k| k.arrival),
    };
    for k in &block.kept {
        s.min_ts = s.min_ts.min(k.timestamp_ns);
        s.max_ts = s.max_ts.max(k.timestamp_ns);
        s.min_seq = s.min_seq.min(k.sequence);
        s.max_seq = s.max_seq.max(k.sequence);
    }
    IndexEntry {
        offset,
        frame_len,
        sensor_hash: sensor_hash(block.sensor.as_str()),
        summary: s,
    }
}

/// Reads a whole index file (a sealed segment's, which recovery made whole).
pub fn read_index(dir: &Path, id: u64) -> Result<Vec<IndexEntry>, HistoryError> {
    let ip = idx_path(dir, id);
    let bytes = std::fs::read(&ip).map_err(io("read an index", &ip))?;
    Ok(bytes
        .chunks_exact(ENTRY_BYTES)
        // Cannot fail: chunks_exact yields ENTRY_BYTES-long slices.
        .map(|c| IndexEntry::decode(c.try_into().expect("entry-sized chunk")))
        .collect())
}

/// Lets the page cache go of a closed segment's log (see [`crate::os::drop_cached`]).
pub fn drop_cached(dir: &Path, id: u64) {
    if let Ok(log) = File::open(log_path(dir, id)) {
        let len = log.metadata().map_or(0, |m| m.len());
        crate::os::drop_cached(&log, 0, len);
    }
}

/// The segment being written.
#[derive(Debug)]
pub struct SegmentWriter {
    pub id: u64,
    log: Appender,
    idx: File,
    log_path: PathBuf,
    idx_path: PathBuf,
    /// Bytes of the log that are durable and indexed.
    pub log_bytes: u64,
    pub idx_bytes: u64,
    /// Blocks written since the last sync: durable and indexed at the next.
    unsynced: Vec<IndexEntry>,
}

impl SegmentWriter {
    /// Creates segment `id` (its files must not exist). Long runs of its log go to the disk
    /// directly when `direct` and the file system allow ([`crate::append`]), staged in `stage`
    /// if the previous segment hands its own on.
    pub fn create(
        dir: &Path,
        id: u64,
        direct: bool,
        stage: Option<Stage>,
    ) -> Result<SegmentWriter, HistoryError> {
        let (lp, ip) = (log_path(dir, id), idx_path(dir, id));
        let open = |p: &Path| {
            OpenOptions::new()
                .create_new(true)
                .append(true)
                .open(p)
                .map_err(io("create a segment file", p))
        };
        let log = Appender::new(open(&lp)?, &lp, direct, stage);
        let idx = open(&ip)?;
        // The directory entry itself must survive a crash.
        File::open(dir)
            .and_then(|d| d.sync_all())
            .map_err(io("sync the history directory", dir))?;
        Ok(SegmentWriter {
            id,
            log,
            idx,
            log_path: lp,
            idx_path: ip,
            log_bytes: 0,
            idx_bytes: 0,
            unsynced: Vec::new(),
        })
    }

    /// The log's staging buffer, for the next segment (after a [`sync`](Self::sync)).
    pub fn take_stage(&mut self) -> Option<Stage> {
        self.log.take_stage()
    }

    /// Bytes of the log written directly since the last call.
    pub fn take_direct_bytes(&mut self) -> u64 {
        self.log.take_direct_bytes()
    }

    /// Appends framed blocks (as [`crate::block::BlockBuilder::finish`] made them), not yet
    /// durable: [`sync`](Self::sync) makes them so, and indexes them.
    pub fn write(
        &mut self,
        frames: &[Vec<u8>],
        blocks: &[(u64, u32, BlockSummary)],
    ) -> Result<(), HistoryError> {
        let mut offset = self.log.appended();
        self.log
            .append(frames)
            .map_err(io("append to a log", &self.log_path))?;
        for &(sensor_hash, frame_len, summary) in blocks {
            self.unsynced.push(IndexEntry {
                offset,
                frame_len,
                sensor_hash,
                summary,
            });
            offset += u64::from(frame_len);
        }
        Ok(())
    }

    /// Makes every block written durable, then indexes them. Returns their entries; with none
    /// written since the last sync, touches nothing.
    pub fn sync(&mut self) -> Result<Vec<IndexEntry>, HistoryError> {
        if self.unsynced.is_empty() {
            return Ok(Vec::new());
        }
        self.log
            .finish()
            .map_err(io("append to a log", &self.log_path))?;
        self.log
            .sync_data()
            .map_err(io("sync a log", &self.log_path))?;
        let entries = std::mem::take(&mut self.unsynced);
        let mut out = Vec::with_capacity(entries.len() * ENTRY_BYTES);
        for e in &entries {
            e.encode(&mut out);
        }
        self.log_bytes = self.log.appended();
        self.idx
            .write_all(&out)
            .map_err(io("append to an index", &self.idx_path))?;
        self.idx_bytes += out.len() as u64;
        Ok(entries)
    }
}
