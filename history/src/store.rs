//! The history directory: its segments, the writer that appends to the newest, readers, and
//! retention.

use std::collections::{BTreeSet, HashMap, VecDeque};
use std::fs::File;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering::Relaxed};
use std::sync::{Arc, Mutex, RwLock};
use std::time::{Duration, Instant, SystemTime};

use triax_protocol::{InlineId, SensorId};

use crate::block::{BlockBuilder, BlockSummary, Kept};
use crate::owner::{self, Owner, OwnerCheck};
use crate::segment::{self, IndexEntry, SegmentWriter};
use crate::HistoryError;

/// Where and how much to keep.
#[derive(Debug, Clone, PartialEq)]
pub struct HistoryConfig {
    pub dir: PathBuf,
    /// Most bytes on disk, logs and indexes; the oldest segments go first.
    pub max_bytes: u64,
    /// Oldest data kept, by the time its segment was last written.
    pub retention: Duration,
    /// A segment is closed and a new one started past this size...
    pub segment_bytes: u64,
    /// ... or this age.
    pub segment_age: Duration,
    /// Whom the history belongs to: recorded when it is created, and a history recording
    /// another building is refused. None: neither recorded nor checked (tools and benches that
    /// read any history).
    pub owner: Option<Owner>,
    /// Long runs of a log go to the disk directly (`O_DIRECT`) where the file system allows
    /// ([`crate::append`]); otherwise, and when false, through the page cache.
    pub direct_io: bool,
}

impl HistoryConfig {
    /// 30 days, 20 GiB, 32 MiB or 1 h segments, direct writes.
    pub fn new(dir: impl Into<PathBuf>) -> HistoryConfig {
        HistoryConfig {
            dir: dir.into(),
            max_bytes: 20 << 30,
            retention: Duration::from_secs(30 * 86_400),
            segment_bytes: 32 << 20,
            segment_age: Duration::from_secs(3600),
            owner: None,
            direct_io: true,
        }
    }

    /// The same, for `owner`'s history only.
    pub fn owned_by(mut self, owner: Owner) -> HistoryConfig {
        self.owner = Some(owner);
        self
    }
}

/// Running totals, for status and metrics.
#[derive(Debug, Default)]
pub struct HistoryCounters {
    pub written_batches: AtomicU64,
    pub written_samples: AtomicU64,
    pub written_blocks: AtomicU64,
    /// Bytes of logs written past the page cache (`O_DIRECT`, [`crate::append`]).
    pub direct_bytes: AtomicU64,
    pub flushes: AtomicU64,
    pub deleted_segments: AtomicU64,
    pub deleted_bytes: AtomicU64,
    /// Blocks that failed their CRC when read.
    pub damaged_blocks: AtomicU64,
    pub write_errors: AtomicU64,
}

/// What the history holds now.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct HistoryStats {
    pub bytes: u64,
    pub segments: usize,
    /// First-sample time of the oldest batch kept (none when empty).
    pub oldest_ns: Option<i64>,
    pub newest_ns: Option<i64>,
}

/// A segment as readers see it.
#[derive(Debug)]
struct Segment {
    id: u64,
    log_path: PathBuf,
    bytes: u64,
    /// Range of every block's first-sample times and arrival numbers; empty ranges when the
    /// segment holds nothing yet.
    min_ts: i64,
    max_ts: i64,
    first_arrival: u64,
    last_arrival: u64,
    modified: SystemTime,
    /// The segment being written keeps its entries here; closed ones read theirs from disk.
    live: Option<Vec<IndexEntry>>,
    /// A closed segment's sensors, as bits of [`Members`]' numbering: a search for a sensor's
    /// blocks skips the segments without it, their index unread.
    members: Vec<u64>,
}

/// One numbering of the sensors the history holds (by [`segment::sensor_hash`]), for the closed
/// segments' bits: one bit a sensor a segment (1.25 KB a segment for 10 000 sensors, where a
/// list of hashes would be eight bytes each).
#[derive(Debug, Default)]
struct Members {
    bit_of: HashMap<u64, u32>,
}

impl Members {
    /// The bits of `hashes`, numbering those new to the history.
    fn bits(&mut self, hashes: impl IntoIterator<Item = u64>) -> Vec<u64> {
        let mut bits = Vec::new();
        for h in hashes {
            let next = self.bit_of.len() as u32;
            let bit = *self.bit_of.entry(h).or_insert(next) as usize;
            if bits.len() <= bit / 64 {
                bits.resize(bit / 64 + 1, 0);
            }
            bits[bit / 64] |= 1 << (bit % 64);
        }
        bits.shrink_to_fit();
        bits
    }

    fn bit(&self, hash: u64) -> Option<u32> {
        self.bit_of.get(&hash).copied()
    }
}

fn has_bit(bits: &[u64], bit: u32) -> bool {
    bits.get(bit as usize / 64)
        .is_some_and(|w| w & (1 << (bit % 64)) != 0)
}

impl Segment {
    fn absorb(&mut self, e: &IndexEntry) {
        let s = &e.summary;
        if self.min_ts > self.max_ts {
            self.first_arrival = s.first_arrival;
        }
        self.min_ts = self.min_ts.min(s.min_ts);
        self.max_ts = self.max_ts.max(s.max_ts);
        self.last_arrival = self.last_arrival.max(s.last_arrival);
        self.bytes += u64::from(e.frame_len) + segment::ENTRY_BYTES as u64;
    }

    fn empty(id: u64, dir: &Path) -> Segment {
        Segment {
            id,
            log_path: segment::log_path(dir, id),
            bytes: 0,
            min_ts: i64::MAX,
            max_ts: i64::MIN,
            first_arrival: 0,
            last_arrival: 0,
            modified: SystemTime::now(),
            live: None,
            members: Vec::new(),
        }
    }

    fn is_empty(&self) -> bool {
        self.min_ts > self.max_ts
    }

    fn meta(&self, sensors: Vec<SensorId>) -> segment::SegmentMeta {
        segment::SegmentMeta {
            min_ts: self.min_ts,
            max_ts: self.max_ts,
            first_arrival: self.first_arrival,
            last_arrival: self.last_arrival,
            sensors,
        }
    }
}

/// Closed segments' indexes most recently read, by segment: each grouped by sensor.
const INDEX_CACHE: usize = 8;
type SensorIndex = HashMap<u64, Vec<IndexEntry>>;

/// A history directory, shared by its writer and its readers.
#[derive(Debug)]
pub struct History {
    config: HistoryConfig,
    segments: RwLock<Vec<Segment>>,
    index_cache: Mutex<VecDeque<(u64, Arc<SensorIndex>)>>,
    /// Every sensor with batches kept (and perhaps some whose batches retention removed).
    sensors: RwLock<BTreeSet<SensorId>>,
    /// The numbering of the closed segments' [`Segment::members`].
    members: RwLock<Members>,
    pub counters: HistoryCounters,
    /// Held for the history's life: one gateway per directory.
    _lock: File,
}

/// What [`History::open`] found and made of the directory.
#[derive(Debug)]
pub struct Opened {
    pub history: Arc<History>,
    pub writer: Writer,
    /// Bytes cut from a torn end of the newest segment, and index entries rebuilt from its log.
    pub cut_bytes: u64,
    pub rescanned_blocks: usize,
    pub segments: usize,
    /// Whether the owner was recorded now, found, or adopted.
    pub owner: OwnerCheck,
}

impl History {
    /// Opens (creating it if missing) the history in `config.dir`, brings its newest segment to
    /// a consistent state after a crash, and starts a new segment for writing.
    pub fn open(config: HistoryConfig) -> Result<Opened, HistoryError> {
        let dir = config.dir.clone();
        let io = |action, source| HistoryError::Io {
            action,
            path: dir.clone(),
            source,
        };
        std::fs::create_dir_all(&dir).map_err(|e| io("create the directory", e))?;
        // Checked before the lock too: a gateway pointed at another building's history hears
        // whose it is, not merely that it is in use, and nothing is written into it.
        if let Some(o) = &config.owner {
            owner::refuse_foreign(&dir, o)?;
        }
        let lock = File::options()
            .create(true)
            .truncate(false)
            .write(true)
            .open(dir.join("LOCK"))
            .map_err(|e| io("open the lock file", e))?;
        if !triax_lockfile::try_lock_exclusive(&lock).map_err(|e| io("lock", e))? {
            return Err(HistoryError::Locked { path: dir.clone() });
        }
        let mut ids = Vec::new();
        for entry in std::fs::read_dir(&dir).map_err(|e| io("list", e))? {
            let entry = entry.map_err(|e| io("list", e))?;
            if let Some(id) = entry.file_name().to_str().and_then(segment::parse_log_name) {
                ids.push(id);
            }
        }
        ids.sort_unstable();
        // Under the lock, before recovery writes anything: no other writer can record another
        // owner between the check and the write.
        let owner_check = match &config.owner {
            Some(o) => owner::claim(&dir, o, !ids.is_empty())?,
            None => OwnerCheck::Unchecked,
        };
        let mut segments = Vec::with_capacity(ids.len() + 1);
        let mut sensors = BTreeSet::new();
        let mut members = Members::default();
        let (mut cut_bytes, mut rescanned_blocks) = (0, 0);
        for (i, &id) in ids.iter().enumerate() {
            let mut seg = Segment::empty(id, &dir);
            let newest = i + 1 == ids.len();
            // A closed segment's meta file says what opening needs; only the newest segment
            // can have been cut short (older ones were closed whole), and a segment closed by a
            // crash has no meta file yet: those are read and their meta written.
            let meta = match (newest, segment::read_meta(&dir, id)) {
                (false, Some(meta)) => meta,
                _ => {
                    let entries = if newest {
                        let r = segment::recover(&dir, id)?;
                        cut_bytes = r.cut_bytes;
                        rescanned_blocks = r.rescanned;
                        r.entries
                    } else {
                        segment::read_index(&dir, id)?
                    };
                    entries.iter().for_each(|e| seg.absorb(e));
                    let meta = seg.meta(segment::sensors_from_blocks(&dir, id, &entries)?);
                    segment::write_meta(&dir, id, &meta)?;
                    meta
                }
            };
            seg.min_ts = meta.min_ts;
            seg.max_ts = meta.max_ts;
            seg.first_arrival = meta.first_arrival;
            seg.last_arrival = meta.last_arrival;
            let size = |p: &Path| std::fs::metadata(p).map_or(0, |m| m.len());
            seg.bytes = size(&seg.log_path) + size(&segment::idx_path(&dir, id));
            seg.members = members.bits(
                meta.sensors
                    .iter()
                    .map(|s| segment::sensor_hash(s.as_str())),
            );
            sensors.extend(meta.sensors);
            seg.modified = std::fs::metadata(&seg.log_path)
                .and_then(|m| m.modified())
                .unwrap_or_else(|_| SystemTime::now());
            segments.push(seg);
        }
        let next_arrival = segments
            .iter()
            .filter(|s| !s.is_empty())
            .map(|s| s.last_arrival + 1)
            .max()
            .unwrap_or(0);
        let next_id = ids.last().map_or(1, |id| id + 1);
        let writer_segment = SegmentWriter::create(&dir, next_id, config.direct_io, None)?;
        let mut active = Segment::empty(next_id, &dir);
        active.live = Some(Vec::new());
        segments.push(active);
        let n_segments = segments.len();
        let history = Arc::new(History {
            config,
            segments: RwLock::new(segments),
            index_cache: Mutex::new(VecDeque::new()),
            sensors: RwLock::new(sensors),
            members: RwLock::new(members),
            counters: HistoryCounters::default(),
            _lock: lock,
        });
        let writer = Writer {
            history: history.clone(),
            segment: Some(writer_segment),
            segment_started: Instant::now(),
            sensors: HashMap::default(),
            ready: Vec::new(),
            ready_bytes: 0,
            failed: None,
            next_arrival,
            spare: Vec::new(),
        };
        Ok(Opened {
            history,
            writer,
            cut_bytes,
            rescanned_blocks,
            segments: n_segments,
            owner: owner_check,
        })
    }

    pub fn config(&self) -> &HistoryConfig {
        &self.config
    }

    /// Every sensor with batches kept, in id order.
    pub fn sensors(&self) -> Vec<SensorId> {
        self.sensors
            .read()
            .unwrap_or_else(|p| p.into_inner())
            .iter()
            .cloned()
            .collect()
    }

    pub fn stats(&self) -> HistoryStats {
        let segs = self.read();
        let filled = || segs.iter().filter(|s| !s.is_empty());
        HistoryStats {
            bytes: segs.iter().map(|s| s.bytes).sum(),
            segments: segs.len(),
            oldest_ns: filled().map(|s| s.min_ts).min(),
            newest_ns: filled().map(|s| s.max_ts).max(),
        }
    }

    fn read(&self) -> std::sync::RwLockReadGuard<'_, Vec<Segment>> {
        // Every update is a push, a pop or a field write: a poisoned list is still consistent.
        self.segments.read().unwrap_or_else(|p| p.into_inner())
    }

    fn write(&self) -> std::sync::RwLockWriteGuard<'_, Vec<Segment>> {
        self.segments.write().unwrap_or_else(|p| p.into_inner())
    }

    /// The index of a closed segment, grouped by sensor, from the cache or from disk.
    fn sensor_index(&self, id: u64) -> Result<Arc<SensorIndex>, HistoryError> {
        let cache = self.index_cache.lock().unwrap_or_else(|p| p.into_inner());
        if let Some((_, idx)) = cache.iter().find(|(i, _)| *i == id) {
            return Ok(idx.clone());
        }
        drop(cache);
        let mut by_sensor: SensorIndex = HashMap::new();
        for e in segment::read_index(&self.config.dir, id)? {
            by_sensor.entry(e.sensor_hash).or_default().push(e);
        }
        let idx = Arc::new(by_sensor);
        let mut cache = self.index_cache.lock().unwrap_or_else(|p| p.into_inner());
        cache.push_front((id, idx.clone()));
        cache.truncate(INDEX_CACHE);
        Ok(idx)
    }

    /// The blocks to read for `query`: from the last checkpoint of the sensor at or before its
    /// first matching block (or the sensor's oldest kept block, if it has no checkpoint before)
    /// to its last block that may match, in the order they were written.
    pub fn scan(&self, query: &Query) -> Result<Scan, HistoryError> {
        let hash = segment::sensor_hash(query.sensor.as_str());
        // Segment ids, paths, whether each may hold a match, and the live segment's entries.
        struct Seen {
            id: u64,
            path: PathBuf,
            may_match: bool,
            live: Option<Vec<IndexEntry>>,
        }
        let seen: Vec<Seen> = self
            .read()
            .iter()
            .map(|s| Seen {
                id: s.id,
                path: s.log_path.clone(),
                may_match: !s.is_empty() && query.may_match_segment(s),
                live: s.live.as_ref().map(|entries| {
                    entries
                        .iter()
                        .filter(|e| e.sensor_hash == hash)
                        .copied()
                        .collect()
                }),
            })
            .collect();
        let entries_of = |s: &Seen| -> Result<Vec<IndexEntry>, HistoryError> {
            match &s.live {
                Some(e) => Ok(e.clone()),
                None => Ok(self
                    .sensor_index(s.id)?
                    .get(&hash)
                    .cloned()
                    .unwrap_or_default()),
            }
        };
        let (Some(first), Some(last)) = (
            seen.iter().position(|s| s.may_match),
            seen.iter().rposition(|s| s.may_match),
        ) else {
            return Ok(Scan::empty());
        };
        // Every block of the sensor from the first segment that may match to the last.
        let mut blocks: Vec<(usize, IndexEntry)> = Vec::new();
        for (i, s) in seen.iter().enumerate().take(last + 1).skip(first) {
            blocks.extend(entries_of(s)?.into_iter().map(|e| (i, e)));
        }
        let Some(first_match) = blocks.iter().position(|(_, e)| query.may_match(&e.summary)) else {
            return Ok(Scan::empty());
        };
        let last_match = blocks
            .iter()
            .rposition(|(_, e)| query.may_match(&e.summary))
            .unwrap_or(first_match);
        blocks.truncate(last_match + 1);
        blocks.drain(..first_match);
        // Back to the checkpoint the replay starts from: in the block itself or before it.
        let mut before: Vec<(usize, IndexEntry)> = Vec::new();
        if !blocks[0].1.summary.checkpoint {
            let mut found = false;
            'back: for i in (0..=blocks[0].0).rev() {
                let mut earlier = entries_of(&seen[i])?;
                if i == blocks[0].0 {
                    earlier.retain(|e| e.offset < blocks[0].1.offset);
                }
                for e in earlier.into_iter().rev() {
                    let checkpoint = e.summary.checkpoint;
                    before.push((i, e));
                    if checkpoint {
                        found = true;
                        break 'back;
                    }
                }
            }
            if !found {
                // No checkpoint kept before: the replay starts cold at the first match.
                before.clear();
            }
        }
        before.reverse();
        before.extend(blocks);
        let segments: Vec<(u64, PathBuf)> = seen.into_iter().map(|s| (s.id, s.path)).collect();
        Ok(Scan {
            blocks: before
                .into_iter()
                .map(|(i, e)| (segments[i].0, segments[i].1.clone(), e))
                .collect(),
            next: 0,
            open: None,
        })
    }

    /// The runs of sequence numbers of `sensor` kept before arrival number `before_arrival`,
    /// among its batches numbered at least `from_seq` and stamped before `before_ns`: sorted,
    /// merged, each with the first sample's time of its first and last batch. A gateway that
    /// starts asks this of each sensor it meets (with the first arrival number of its own run)
    /// to find every hole its history has in the span a node's buffer can still fill: the one
    /// its downtime left, and any a kill left (batches fetched late, not yet flushed).
    ///
    /// Reads index entries back from the newest segment, skipping the segments that hold none
    /// of the sensor's blocks (a gateway that started while the sensor was cut off wrote one of
    /// those), until one holds its blocks but none numbered at or above `from_seq`; and reads
    /// only the blocks whose numbers are not one run already.
    pub fn kept_runs(
        &self,
        sensor: &SensorId,
        before_arrival: u64,
        from_seq: u64,
        before_ns: i64,
    ) -> Result<Vec<SeqRun>, HistoryError> {
        let hash = segment::sensor_hash(sensor.as_str());
        let bit = self
            .members
            .read()
            .unwrap_or_else(|p| p.into_inner())
            .bit(hash);
        let seen: Vec<(u64, PathBuf, Option<Vec<IndexEntry>>)> = self
            .read()
            .iter()
            .filter(|s| !s.is_empty() && s.first_arrival < before_arrival)
            .filter(|s| s.live.is_some() || bit.is_some_and(|b| has_bit(&s.members, b)))
            .map(|s| {
                let live = s.live.as_ref().map(|entries| {
                    entries
                        .iter()
                        .filter(|e| e.sensor_hash == hash)
                        .copied()
                        .collect()
                });
                (s.id, s.log_path.clone(), live)
            })
            .collect();
        let mut runs: Vec<SeqRun> = Vec::new();
        for (id, path, live) in seen.into_iter().rev() {
            let entries = match live {
                Some(e) => e,
                None => self
                    .sensor_index(id)?
                    .get(&hash)
                    .cloned()
                    .unwrap_or_default(),
            };
            // Whether the segment holds blocks of the sensor from before, and any of them in
            // the span: one that holds only older numbers ends the search.
            let (mut before, mut any) = (false, false);
            for e in entries {
                let b = &e.summary;
                if b.first_arrival >= before_arrival || b.min_ts >= before_ns {
                    continue;
                }
                before = true;
                if b.max_seq < from_seq {
                    continue;
                }
                any = true;
                let whole = b.max_seq - b.min_seq + 1 == u64::from(b.n_records)
                    && b.last_arrival < before_arrival
                    && b.max_ts < before_ns;
                if whole {
                    // One run in order: its ends are its first and last batch.
                    runs.push(SeqRun {
                        first_seq: b.min_seq,
                        first_ns: b.min_ts,
                        last_seq: b.max_seq,
                        last_ns: b.max_ts,
                    });
                    continue;
                }
                let offset = e.offset;
                let mut scan = Scan {
                    blocks: vec![(id, path.clone(), e)],
                    next: 0,
                    open: None,
                };
                let Some(block) = scan.next_block() else {
                    continue;
                };
                let bytes = block?.bytes;
                let block = crate::Block::decode(&bytes).map_err(|e| HistoryError::Damaged {
                    path: path.clone(),
                    offset,
                    reason: e.to_string(),
                })?;
                if &block.sensor != sensor {
                    // Another sensor whose id hashes alike.
                    continue;
                }
                runs.extend(
                    block
                        .kept
                        .iter()
                        .filter(|k| {
                            k.arrival < before_arrival
                                && k.sequence >= from_seq
                                && k.timestamp_ns < before_ns
                        })
                        .map(|k| SeqRun {
                            first_seq: k.sequence,
                            first_ns: k.timestamp_ns,
                            last_seq: k.sequence,
                            last_ns: k.timestamp_ns,
                        }),
                );
            }
            if before && !any {
                break;
            }
        }
        runs.sort_by_key(|r| r.first_seq);
        let mut merged: Vec<SeqRun> = Vec::with_capacity(runs.len());
        for r in runs {
            match merged.last_mut() {
                Some(m) if r.first_seq <= m.last_seq.saturating_add(1) => {
                    if r.last_seq > m.last_seq {
                        m.last_seq = r.last_seq;
                        m.last_ns = r.last_ns;
                    }
                }
                _ => merged.push(r),
            }
        }
        Ok(merged)
    }

    /// Records a block that failed its check when read.
    pub fn count_damaged(&self) {
        self.counters.damaged_blocks.fetch_add(1, Relaxed);
    }

    /// Deletes closed segments past the size or the age limit, oldest first; returns how many.
    fn enforce_retention(&self) -> usize {
        let now = SystemTime::now();
        let mut deleted = 0;
        loop {
            let victim = {
                let segs = self.read();
                let total: u64 = segs.iter().map(|s| s.bytes).sum();
                let oldest = match segs.first() {
                    Some(s) if s.live.is_none() => s,
                    _ => break,
                };
                let too_old = now
                    .duration_since(oldest.modified)
                    .is_ok_and(|age| age > self.config.retention);
                if total <= self.config.max_bytes && !too_old {
                    break;
                }
                (oldest.id, oldest.bytes)
            };
            let (id, bytes) = victim;
            let dir = &self.config.dir;
            let removed = [
                segment::log_path(dir, id),
                segment::idx_path(dir, id),
                segment::meta_path(dir, id),
            ]
            .iter()
            .map(std::fs::remove_file)
            .all(|r| r.is_ok() || r.is_err_and(|e| e.kind() == std::io::ErrorKind::NotFound));
            if !removed {
                self.counters.write_errors.fetch_add(1, Relaxed);
                break;
            }
            self.write().retain(|s| s.id != id);
            let mut cache = self.index_cache.lock().unwrap_or_else(|p| p.into_inner());
            cache.retain(|(i, _)| *i != id);
            self.counters.deleted_segments.fetch_add(1, Relaxed);
            self.counters.deleted_bytes.fetch_add(bytes, Relaxed);
            deleted += 1;
        }
        deleted
    }
}

/// Consecutive sequence numbers a history holds of one sensor ([`History::kept_runs`]), with
/// the first sample's time of the first and of the last.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct SeqRun {
    pub first_seq: u64,
    pub first_ns: i64,
    pub last_seq: u64,
    pub last_ns: i64,
}

/// Which batches of one sensor a reader wants.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Query {
    pub sensor: SensorId,
    /// First-sample time in `[from_ns, to_ns)`.
    pub from_ns: Option<i64>,
    pub to_ns: Option<i64>,
    /// Sequence number in `[from_seq, to_seq]`.
    pub from_seq: Option<u64>,
    pub to_seq: Option<u64>,
    /// Only batches that arrived after this one.
    pub after_arrival: Option<u64>,
}

impl Query {
    /// Every batch of `sensor`.
    pub fn all(sensor: SensorId) -> Query {
        Query {
            sensor,
            from_ns: None,
            to_ns: None,
            from_seq: None,
            to_seq: None,
            after_arrival: None,
        }
    }

    /// Whether one batch is wanted.
    pub fn matches<S>(&self, k: &Kept<S>) -> bool {
        self.from_ns.is_none_or(|f| k.timestamp_ns >= f)
            && self.to_ns.is_none_or(|t| k.timestamp_ns < t)
            && self.from_seq.is_none_or(|f| k.sequence >= f)
            && self.to_seq.is_none_or(|t| k.sequence <= t)
            && self.after_arrival.is_none_or(|a| k.arrival > a)
    }

    /// Whether a block may hold a wanted batch.
    fn may_match(&self, s: &BlockSummary) -> bool {
        self.from_ns.is_none_or(|f| s.max_ts >= f)
            && self.to_ns.is_none_or(|t| s.min_ts < t)
            && self.from_seq.is_none_or(|f| s.max_seq >= f)
            && self.to_seq.is_none_or(|t| s.min_seq <= t)
            && self.after_arrival.is_none_or(|a| s.last_arrival > a)
    }

    fn may_match_segment(&self, s: &Segment) -> bool {
        self.from_ns.is_none_or(|f| s.max_ts >= f)
            && self.to_ns.is_none_or(|t| s.min_ts < t)
            && self.after_arrival.is_none_or(|a| s.last_arrival > a)
    }
}

/// The blocks of one query, read one at a time.
#[derive(Debug)]
pub struct Scan {
    blocks: Vec<(u64, PathBuf, IndexEntry)>,
    next: usize,
    open: Option<(u64, File)>,
}

/// One block of a scan, checked and ready to decode with [`crate::Block::decode`].
#[derive(Debug)]
pub struct ScannedBlock {
    pub bytes: Vec<u8>,
    pub entry: IndexEntry,
}

impl Scan {
    fn empty() -> Scan {
        Scan {
            blocks: Vec::new(),
            next: 0,
            open: None,
        }
    }

    /// Blocks left to read.
    pub fn remaining(&self) -> usize {
        self.blocks.len() - self.next
    }

    /// The next block; an error for a block that cannot be read or fails its CRC (the scan goes
    /// on with the next one).
    pub fn next_block(&mut self) -> Option<Result<ScannedBlock, HistoryError>> {
        let (id, path, entry) = self.blocks.get(self.next)?.clone();
        self.next += 1;
        if self.open.as_ref().is_none_or(|(open_id, _)| *open_id != id) {
            match File::open(&path) {
                Ok(f) => self.open = Some((id, f)),
                Err(source) => {
                    return Some(Err(HistoryError::Io {
                        action: "open a log",
                        path,
                        source,
                    }))
                }
            }
        }
        // Set just above.
        let (_, file) = self.open.as_ref().expect("log is open");
        Some(segment::read_frame(file, &path, &entry).map(|bytes| ScannedBlock { bytes, entry }))
    }
}

/// Largest block: a sensor's pending batches are closed into a block past this many bytes...
const BLOCK_BYTES_MAX: usize = 1 << 20;
/// ... or this many batches (the index keeps the count in 16 bits).
const BLOCK_BATCHES_MAX: u32 = 60_000;

/// Closed blocks waiting past this many bytes are written before the flush (not synced): a
/// heavy stream then holds a stage's worth of closed blocks in memory, not a flush interval's.
const WRITE_AHEAD_BYTES: usize = crate::append::STAGE_BYTES;

/// Appends to the history: batches gather per sensor in memory and go to disk, one block per
/// sensor, at each [`flush`](Self::flush).
#[derive(Debug)]
pub struct Writer {
    history: Arc<History>,
    segment: Option<SegmentWriter>,
    segment_started: Instant,
    /// The sensors of the segment being written, with their open blocks: the segment's
    /// `.sensors` file at its roll. Looked up every batch, so keyed in place and with a quick
    /// hash (its seed is random per table, and the gateway bounds its sensors); a sensor stays
    /// from its first batch of the segment to the segment's roll, so that a flush does not make
    /// it a stranger again a second later.
    sensors: HashMap<InlineId, SegmentSensor, foldhash::fast::RandomState>,
    /// Blocks closed before the flush (a checkpoint or the size limit started a new one), by
    /// their sensor's [`segment::sensor_hash`].
    ready: Vec<(u64, BlockBuilder)>,
    /// Their bytes: past [`WRITE_AHEAD_BYTES`] they are written ahead of the flush.
    ready_bytes: usize,
    /// A write ahead of the flush failed: the flush reports it.
    failed: Option<HistoryError>,
    next_arrival: u64,
    /// Buffers of blocks already written, for the next ones: a block a second per sensor would
    /// otherwise be an allocation (and, for large ones, a fresh mapping to fault in) each.
    spare: Vec<Vec<u8>>,
}

/// A sensor of the segment being written.
#[derive(Debug)]
struct SegmentSensor {
    id: SensorId,
    /// [`segment::sensor_hash`] of the id: the index's key for its blocks.
    hash: u64,
    /// The block its batches gather in until the flush; none since.
    open: Option<BlockBuilder>,
}

impl SegmentSensor {
    /// `sensor`, new to the segment; named in the history's list of sensors too.
    fn admit(history: &History, sensor: &InlineId) -> SegmentSensor {
        let id = sensor.to_sensor_id();
        let known = history
            .sensors
            .read()
            .unwrap_or_else(|p| p.into_inner())
            .contains(&id);
        if !known {
            history
                .sensors
                .write()
                .unwrap_or_else(|p| p.into_inner())
                .insert(id.clone());
        }
        SegmentSensor {
            hash: segment::sensor_hash(id.as_str()),
            id,
            open: None,
        }
    }
}

/// Segments whose pages may stay in the page cache (those written through it, and those queries
/// read): the one being written and the ones closed just before it.
const HOT_SEGMENTS: usize = 3;

/// Most memory kept in spare block buffers.
const SPARE_BYTES: usize = 32 << 20;

impl Writer {
    pub fn history(&self) -> &Arc<History> {
        &self.history
    }

    /// Keeps one batch of `sensor` (its `arrival` is assigned here and returned). A checkpoint
    /// is the correction state before this batch: it starts a new block.
    pub fn append(
        &mut self,
        sensor: &InlineId,
        mut kept: Kept<&[u8]>,
        checkpoint: Option<&[u8]>,
    ) -> u64 {
        kept.arrival = self.next_arrival;
        self.next_arrival += 1;
        let closes = |b: &BlockBuilder| {
            checkpoint.is_some()
                || b.len() >= BLOCK_BYTES_MAX
                || b.summary.n_records >= BLOCK_BATCHES_MAX
        };
        let Writer {
            history,
            sensors,
            ready,
            ready_bytes,
            spare,
            ..
        } = self;
        let s = sensors
            .entry(*sensor)
            .or_insert_with(|| SegmentSensor::admit(history, sensor));
        match &mut s.open {
            Some(b) if !closes(b) => b.push(&kept),
            open => {
                let buf = spare.pop().unwrap_or_default();
                let mut fresh = BlockBuilder::in_buffer(buf, &s.id, checkpoint);
                fresh.push(&kept);
                if let Some(old) = open.replace(fresh) {
                    *ready_bytes += old.len();
                    ready.push((s.hash, old));
                }
            }
        }
        if self.ready_bytes >= WRITE_AHEAD_BYTES {
            self.write_ahead();
        }
        let c = &self.history.counters;
        c.written_batches.fetch_add(1, Relaxed);
        c.written_samples
            .fetch_add(kept.n_samples() as u64, Relaxed);
        kept.arrival
    }

    /// The arrival number the next batch appended will get.
    pub fn next_arrival(&self) -> u64 {
        self.next_arrival
    }

    /// Batches kept in memory, not yet on disk.
    pub fn pending_batches(&self) -> usize {
        self.sensors
            .values()
            .filter_map(|s| s.open.as_ref())
            .chain(self.ready.iter().map(|(_, b)| b))
            .map(|b| b.summary.n_records as usize)
            .sum()
    }

    /// Writes every pending block, makes it durable, publishes it to readers, then rolls the
    /// segment and applies retention when due.
    pub fn flush(&mut self) -> Result<(), HistoryError> {
        let mut blocks = std::mem::take(&mut self.ready);
        self.ready_bytes = 0;
        blocks.extend(
            self.sensors
                .values_mut()
                .filter_map(|s| Some((s.hash, s.open.take()?))),
        );
        if !blocks.is_empty() {
            self.write_blocks(blocks)?;
        }
        if let Some(seg) = self.segment.as_mut() {
            let synced = seg.sync();
            let direct = seg.take_direct_bytes();
            self.history
                .counters
                .direct_bytes
                .fetch_add(direct, Relaxed);
            self.publish(synced)?;
        }
        if let Some(e) = self.failed.take() {
            // A write ahead of this flush failed: its segment's unsynced blocks were lost with it
            // (the later ones went to a fresh segment, and are durable now).
            return Err(e);
        }
        self.history.counters.flushes.fetch_add(1, Relaxed);
        let due = self.segment.as_ref().is_none_or(|s| {
            s.log_bytes >= self.history.config.segment_bytes
                || (s.log_bytes > 0
                    && self.segment_started.elapsed() >= self.history.config.segment_age)
        });
        if due {
            self.roll()?;
        }
        self.history.enforce_retention();
        Ok(())
    }

    /// Writes the closed blocks now, durable at the next flush, which reports a failure.
    fn write_ahead(&mut self) {
        let blocks = std::mem::take(&mut self.ready);
        self.ready_bytes = 0;
        if let Err(e) = self.write_blocks(blocks) {
            self.failed = Some(e);
        }
    }

    /// Appends blocks to the segment's log, not yet durable.
    fn write_blocks(&mut self, blocks: Vec<(u64, BlockBuilder)>) -> Result<(), HistoryError> {
        let mut frames = Vec::with_capacity(blocks.len());
        let mut meta = Vec::with_capacity(blocks.len());
        for (sensor_hash, b) in blocks {
            let (frame, summary) = b.finish();
            // Blocks are closed at 1 MiB: the length fits.
            meta.push((sensor_hash, frame.len() as u32, summary));
            frames.push(frame);
        }
        if self.segment.is_none() {
            self.roll()?;
        }
        // Present after `roll`.
        let seg = self.segment.as_mut().expect("a segment is open");
        let written = seg.write(&frames, &meta);
        self.recycle(frames);
        if let Err(e) = written {
            self.fail_segment();
            return Err(e);
        }
        Ok(())
    }

    /// Keeps written blocks' buffers for the next blocks, up to [`SPARE_BYTES`].
    fn recycle(&mut self, frames: impl IntoIterator<Item = Vec<u8>>) {
        let mut kept: usize = self.spare.iter().map(Vec::capacity).sum();
        for mut f in frames {
            if kept + f.capacity() <= SPARE_BYTES {
                kept += f.capacity();
                f.clear();
                self.spare.push(f);
            }
        }
    }

    /// Hands durable blocks to readers.
    fn publish(
        &mut self,
        synced: Result<Vec<IndexEntry>, HistoryError>,
    ) -> Result<(), HistoryError> {
        let entries = match synced {
            Ok(entries) => entries,
            Err(e) => {
                self.fail_segment();
                return Err(e);
            }
        };
        let Some(id) = self.segment.as_ref().map(|s| s.id) else {
            return Ok(());
        };
        if entries.is_empty() {
            return Ok(());
        }
        let mut segs = self.history.write();
        if let Some(s) = segs.iter_mut().find(|s| s.id == id) {
            for e in &entries {
                s.absorb(e);
            }
            s.modified = SystemTime::now();
            s.live
                .get_or_insert_with(Vec::new)
                .extend(entries.iter().copied());
        }
        self.history
            .counters
            .written_blocks
            .fetch_add(entries.len() as u64, Relaxed);
        Ok(())
    }

    /// After a failed write or sync the segment's end is unknown: it is closed (recovery cuts
    /// what is torn) and the next flush writes to a fresh one. The blocks written since the
    /// last sync are lost, and counted.
    fn fail_segment(&mut self) {
        self.history.counters.write_errors.fetch_add(1, Relaxed);
        if let Some(seg) = self.segment.take() {
            let _ = segment::recover(&self.history.config.dir, seg.id);
        }
    }

    /// Closes the segment being written and starts the next.
    fn roll(&mut self) -> Result<(), HistoryError> {
        let dir = self.history.config.dir.clone();
        let mut closing_segment = self.segment.take();
        let stage = closing_segment.as_mut().and_then(SegmentWriter::take_stage);
        let closing = closing_segment.map(|s| s.id);
        let mut closing_hashes = None;
        if let Some(id) = closing {
            closing_hashes = Some(self.sensors.values().map(|s| s.hash).collect::<Vec<u64>>());
            let mut ids: Vec<SensorId> = self.sensors.values().map(|s| s.id.clone()).collect();
            ids.sort_unstable();
            // A segment rolls after a flush, which closed every block; one still open would be
            // written to the next segment, which names its sensor then.
            self.sensors.retain(|_, s| s.open.is_some());
            let meta = self
                .history
                .read()
                .iter()
                .find(|s| s.id == id)
                .map(|s| s.meta(ids));
            if let Some(meta) = meta {
                segment::write_meta(&dir, id, &meta)?;
            }
        }
        let next_id = {
            let segs = self.history.read();
            // What the page cache holds of the newest segments stays for the queries that
            // want recent data; older ones leave it, and their pages take the next writes.
            if let Some(old) = segs.iter().rev().nth(HOT_SEGMENTS) {
                segment::drop_cached(&dir, old.id);
            }
            segs.last().map_or(1, |s| s.id + 1)
        };
        let fresh = SegmentWriter::create(&dir, next_id, self.history.config.direct_io, stage)?;
        let bits = closing_hashes.map(|hashes| {
            self.history
                .members
                .write()
                .unwrap_or_else(|p| p.into_inner())
                .bits(hashes)
        });
        let mut segs = self.history.write();
        if let Some(id) = closing {
            if let Some(s) = segs.iter_mut().find(|s| s.id == id) {
                s.live = None;
                s.members = bits.unwrap_or_default();
            }
        }
        let mut seg = Segment::empty(next_id, &dir);
        seg.live = Some(Vec::new());
        segs.push(seg);
        drop(segs);
        self.segment = Some(fresh);
        self.segment_started = Instant::now();
        Ok(())
    }
}
