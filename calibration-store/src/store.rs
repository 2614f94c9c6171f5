//! The store: one sled database holding every version of every sensor's calibration record.
//!
//! All writes go through [`Store::put`] (or [`Store::put_all`]), which validates the record by
//! loading it into a corrector, applies the version rules, writes the record and the
//! current-version index in one sled transaction and flushes before returning. Reads decode
//! each entry on its own, so one corrupt entry is reported and skipped without hiding the rest.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::Mutex;
use std::time::{Duration, Instant};

use sled::transaction::{ConflictableTransactionError, TransactionError, Transactional};
use time::OffsetDateTime;
use tracing::{debug, warn};
use triax_calibration::corrector::{Corrector, LoadError};
use triax_protocol::record::CalibrationRecord;
use triax_protocol::{from_json, to_json, SensorId};

use crate::error::{db_error, CorruptEntry, Rejection, StoreError};
use crate::keys;

/// Layout version of the database, stored in it. Bump it when keys or values change meaning;
/// a build refuses a store whose schema is newer than its own.
pub const SCHEMA_VERSION: u32 = 1;

/// What a successful `put` did.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PutOutcome {
    /// The record was new and is now durable.
    Stored,
    /// The same version with the same content was already stored; nothing was written.
    AlreadyStored,
    /// The same version was stored but unreadable; the valid record replaced the corrupt entry.
    Repaired,
}

/// A read that skipped corrupt entries: the answer from the readable ones, and what was skipped.
#[derive(Debug, Clone, PartialEq)]
pub struct Scan<T> {
    pub value: T,
    /// Entries that could not be decoded, by tree and key. Each is also logged as a warning.
    pub skipped: Vec<CorruptEntry>,
}

impl<T> Scan<T> {
    fn new(value: T) -> Self {
        Scan {
            value,
            skipped: Vec::new(),
        }
    }
}

/// A current record and the corrector it loads into, from [`Store::load_current`].
#[derive(Debug, Clone)]
pub struct Loaded {
    pub sensor_id: SensorId,
    pub version: u64,
    pub corrector: Result<Corrector, LoadError>,
}

/// Records decoded per step when loading every current record.
const LOAD_CHUNK: usize = 1024;

/// Below this many items, spawning threads costs more than it saves.
const MIN_PARALLEL_ITEMS: usize = 256;

/// `items.iter().map(f)`, split over the available cores; order is kept.
fn parallel_map<I: Sync, O: Send>(items: &[I], f: impl Fn(&I) -> O + Sync) -> Vec<O> {
    let threads = std::thread::available_parallelism().map_or(1, |n| n.get().min(16));
    if threads == 1 || items.len() < MIN_PARALLEL_ITEMS {
        return items.iter().map(f).collect();
    }
    let chunk_len = items.len().div_ceil(threads);
    let f = &f;
    std::thread::scope(|scope| {
        let workers: Vec<_> = items
            .chunks(chunk_len)
            .map(|chunk| scope.spawn(move || chunk.iter().map(f).collect::<Vec<O>>()))
            .collect();
        workers
            .into_iter()
            // A worker fails only by panicking; the panic is carried on in this thread.
            .flat_map(|w| {
                w.join()
                    .unwrap_or_else(|panic| std::panic::resume_unwind(panic))
            })
            .collect()
    })
}

/// A sensor and the version of its current record.
#[derive(Debug, Clone, PartialEq, Eq, PartialOrd, Ord)]
pub struct SensorVersion {
    pub sensor_id: SensorId,
    pub version: u64,
}

/// A record the field health checks found suspect ([`Store::mark_suspect`]).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct SuspectMark {
    pub sensor_id: SensorId,
    pub version: u64,
    /// Samples corrected with the record and stamped at or after this time carry
    /// `calibration_suspect`, ns.
    pub flagged_from_ns: i64,
}

/// A calibration store on disk. Cheap to share across threads (`Arc<Store>`); every method
/// blocks on disk I/O, so async callers use `spawn_blocking`.
pub struct Store {
    path: PathBuf,
    db: sled::Db,
    records: sled::Tree,
    current: sled::Tree,
    suspect: sled::Tree,
    /// Serializes writers: a put reads the current version and then writes, and the version
    /// rules hold only if no other put for the sensor slips in between. Calibration updates are
    /// rare (per sensor, a few a year), so one lock for the whole store costs nothing, and sled
    /// keeps other processes out with its own file lock.
    write_lock: Mutex<()>,
}

impl std::fmt::Debug for Store {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Store").field("path", &self.path).finish()
    }
}

fn corrupt(tree: &'static str, key: String, problem: impl Into<String>) -> CorruptEntry {
    let entry = CorruptEntry {
        tree,
        key,
        problem: problem.into(),
    };
    warn!(tree = entry.tree, key = %entry.key, problem = %entry.problem, "skipping corrupt entry");
    entry
}

/// A time stamp as the suspect tree keeps it; a value of another length (damage) reads as the
/// earliest time, so that a damaged mark flags more, never less.
fn decode_ns(v: &[u8]) -> i64 {
    <[u8; 8]>::try_from(v).map_or(i64::MIN, i64::from_be_bytes)
}

/// Decodes one entry of the records tree and checks it is filed under its own sensor and
/// version, so a record can never answer for another.
fn decode_record(key: &[u8], value: &[u8]) -> Result<CalibrationRecord, CorruptEntry> {
    let (sensor_id, version) = keys::parse_record_key(key)
        .map_err(|p| corrupt(keys::RECORDS_TREE, keys::escape(key), p))?;
    let shown = || format!("{sensor_id} v{version}");
    let record: CalibrationRecord =
        from_json(value).map_err(|e| corrupt(keys::RECORDS_TREE, shown(), e.to_string()))?;
    if record.sensor_id != sensor_id || record.version != version {
        return Err(corrupt(
            keys::RECORDS_TREE,
            shown(),
            format!(
                "holds the record of sensor {} version {}",
                record.sensor_id, record.version
            ),
        ));
    }
    Ok(record)
}

/// Whether `at` falls in the record's validity window `[valid_from, valid_until)`.
pub fn in_force_at(record: &CalibrationRecord, at: OffsetDateTime) -> bool {
    record.valid_from <= at && record.valid_until.is_none_or(|until| at < until)
}

/// Page cache of the underlying database.
const CACHE_CAPACITY_BYTES: u64 = 16 << 20;

/// How long [`Store::open`] waits for a lock held by a holder that is closing.
pub const DEFAULT_LOCK_WAIT: Duration = Duration::from_secs(3);

impl Store {
    /// Opens the store at `path`, creating it if the directory holds none.
    ///
    /// Refuses a store written with a newer [`SCHEMA_VERSION`], a directory whose sled database
    /// holds records but no schema version, and a store another process holds open. A lock still
    /// held after [`DEFAULT_LOCK_WAIT`] is [`StoreError::Locked`]: sled releases its directory
    /// lock from a background thread shortly after the last handle is dropped, so a restart in
    /// the same process, or right after the previous process exited, can find it briefly held.
    pub fn open(path: impl AsRef<Path>) -> Result<Store, StoreError> {
        Store::open_waiting(path, DEFAULT_LOCK_WAIT)
    }

    /// [`Store::open`], waiting up to `lock_wait` for another holder to close.
    pub fn open_waiting(path: impl AsRef<Path>, lock_wait: Duration) -> Result<Store, StoreError> {
        let deadline = Instant::now() + lock_wait;
        loop {
            match Store::open_once(path.as_ref()) {
                Err(StoreError::Locked { .. }) if Instant::now() < deadline => {
                    std::thread::sleep(Duration::from_millis(20));
                }
                other => return other,
            }
        }
    }

    fn open_once(path: &Path) -> Result<Store, StoreError> {
        let path = path.to_path_buf();
        // sled's default page cache is 1 GiB; records are read once at start and on catch-up,
        // so a small cache keeps a gateway with 10 000 sensors within its memory budget.
        let db = sled::Config::new()
            .path(&path)
            .cache_capacity(CACHE_CAPACITY_BYTES)
            .open()
            .map_err(|e| {
                let message = e.to_string();
                // sled reports its file lock only in the message of an I/O error.
                if message.contains("could not acquire lock") {
                    StoreError::Locked { path: path.clone() }
                } else {
                    match db_error("open", e) {
                        StoreError::Io { source, .. } => StoreError::File {
                            action: "open calibration store",
                            path: path.clone(),
                            source,
                        },
                        other => other,
                    }
                }
            })?;
        let tree = |name: &str| db.open_tree(name).map_err(|e| db_error("open tree", e));
        let meta = tree(keys::META_TREE)?;
        let records = tree(keys::RECORDS_TREE)?;
        let current = tree(keys::CURRENT_TREE)?;
        let suspect = tree(keys::SUSPECT_TREE)?;

        let not_a_store = |reason: String| StoreError::NotAStore {
            path: path.clone(),
            reason,
        };
        match meta
            .get(keys::SCHEMA_VERSION_KEY)
            .map_err(|e| db_error("read schema version", e))?
        {
            Some(value) => match keys::decode_schema_version(&value) {
                Ok(SCHEMA_VERSION) => {}
                Ok(found) if found > SCHEMA_VERSION => {
                    return Err(StoreError::NewerSchema {
                        path,
                        found,
                        supported: SCHEMA_VERSION,
                    })
                }
                Ok(found) => {
                    return Err(not_a_store(format!(
                        "schema version {found} was never written by Triax"
                    )))
                }
                Err(problem) => return Err(not_a_store(problem)),
            },
            None if records.is_empty() && current.is_empty() => {
                meta.insert(
                    keys::SCHEMA_VERSION_KEY,
                    &keys::encode_schema_version(SCHEMA_VERSION),
                )
                .map_err(|e| db_error("write schema version", e))?;
                // Durable before any record, so no record is ever on disk without it.
                db.flush().map_err(|e| db_error("flush", e))?;
            }
            None => {
                return Err(not_a_store(
                    "it holds records but no schema version".to_owned(),
                ))
            }
        }
        debug!(path = %path.display(), "opened calibration store");
        Ok(Store {
            path,
            db,
            records,
            current,
            suspect,
            write_lock: Mutex::new(()),
        })
    }

    /// The directory the store lives in.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Validates and stores a record; returns once it is durable on disk.
    ///
    /// The record must load into a corrector. Its version must be greater than the sensor's
    /// current version, or already in the sensor's history with identical content (an
    /// idempotent retry, [`PutOutcome::AlreadyStored`]). A version in the history with other
    /// content is a [`Rejection::Conflict`]; an older version not in it a [`Rejection::Stale`].
    pub fn put(
        &self,
        record: &CalibrationRecord,
    ) -> Result<Result<PutOutcome, Rejection>, StoreError> {
        let outcome = self.put_unflushed(record)?;
        // Flushing after AlreadyStored too: the identical record may have been written by a
        // concurrent put that has not flushed yet, and this caller is promised durability.
        if outcome.is_ok() {
            self.flush()?;
        }
        Ok(outcome)
    }

    /// Puts several records in order with one flush at the end, for imports and catch-up: each
    /// gets its own outcome, and all stored ones are durable when this returns. Records of one
    /// sensor must come in increasing version order to be accepted.
    pub fn put_all<'a>(
        &self,
        records: impl IntoIterator<Item = &'a CalibrationRecord>,
    ) -> Result<Vec<Result<PutOutcome, Rejection>>, StoreError> {
        let outcomes = records
            .into_iter()
            .map(|r| self.put_unflushed(r))
            .collect::<Result<Vec<_>, _>>()?;
        // Unconditional for the reason given in `put`; it costs little when nothing is dirty.
        self.flush()?;
        Ok(outcomes)
    }

    /// Records that the field health checks found `version` of `sensor_id` suspect, and that its
    /// samples stamped at or after `flagged_from_ns` carry the flag; durable when this returns.
    /// The first mark of a record stands: marking it again returns the time already stored.
    pub fn mark_suspect(
        &self,
        sensor_id: &SensorId,
        version: u64,
        flagged_from_ns: i64,
    ) -> Result<i64, StoreError> {
        let key = keys::record_key(sensor_id, version);
        let swapped = self
            .suspect
            .compare_and_swap(
                &key,
                None as Option<&[u8]>,
                Some(&flagged_from_ns.to_be_bytes()[..]),
            )
            .map_err(|e| db_error("mark suspect", e))?;
        let stored = match swapped {
            Ok(()) => flagged_from_ns,
            Err(e) => e.current.as_deref().map_or(flagged_from_ns, decode_ns),
        };
        self.flush()?;
        Ok(stored)
    }

    /// When `version` of `sensor_id` was found suspect (see [`Store::mark_suspect`]).
    pub fn suspect_from(
        &self,
        sensor_id: &SensorId,
        version: u64,
    ) -> Result<Option<i64>, StoreError> {
        Ok(self
            .suspect
            .get(keys::record_key(sensor_id, version))
            .map_err(|e| db_error("read suspect", e))?
            .map(|v| decode_ns(&v)))
    }

    /// Every record found suspect, by sensor then version.
    /// An entry that does not decode is skipped and listed.
    pub fn suspects(&self) -> Result<Scan<Vec<SuspectMark>>, StoreError> {
        let mut scan = Scan::new(Vec::new());
        for entry in self.suspect.iter() {
            let (k, v) = entry.map_err(|e| db_error("read suspect", e))?;
            match keys::parse_record_key(&k) {
                Ok((sensor_id, version)) if v.len() == 8 => scan.value.push(SuspectMark {
                    sensor_id,
                    version,
                    flagged_from_ns: decode_ns(&v),
                }),
                Ok(_) => scan.skipped.push(corrupt(
                    keys::SUSPECT_TREE,
                    keys::escape(&k),
                    format!("value is {} bytes, not 8", v.len()),
                )),
                Err(p) => scan
                    .skipped
                    .push(corrupt(keys::SUSPECT_TREE, keys::escape(&k), p)),
            }
        }
        Ok(scan)
    }

    /// Makes every write so far durable. `put`, `put_all` and `import` already do this before
    /// returning; a service calls it once more on shutdown.
    pub fn flush(&self) -> Result<(), StoreError> {
        self.db.flush().map_err(|e| db_error("flush", e))?;
        Ok(())
    }

    fn put_unflushed(
        &self,
        record: &CalibrationRecord,
    ) -> Result<Result<PutOutcome, Rejection>, StoreError> {
        // Validation first and outside the lock: it is the expensive part (an SVD and an
        // eigendecomposition) and needs nothing from the disk.
        if let Err(e) = Corrector::from_record(record) {
            return Ok(Err(Rejection::Invalid(e)));
        }
        let sensor_id = &record.sensor_id;
        let version = record.version;
        let record_key = keys::record_key(sensor_id, version);

        // A poisoned lock only means another put panicked; the database itself is consistent
        // (sled transactions are atomic), so the guard is still good to use.
        let _guard = self
            .write_lock
            .lock()
            .unwrap_or_else(|poisoned| poisoned.into_inner());

        let repairing = match self
            .records
            .get(&record_key)
            .map_err(|e| db_error("read record", e))?
        {
            Some(stored) => match decode_record(&record_key, &stored) {
                Ok(stored) if stored == *record => return Ok(Ok(PutOutcome::AlreadyStored)),
                Ok(_) => {
                    return Ok(Err(Rejection::Conflict {
                        sensor_id: sensor_id.clone(),
                        version,
                    }))
                }
                // Replacing an unreadable entry with the valid record of the same key loses
                // nothing and is how an operator repairs a store from an export.
                Err(_) => true,
            },
            None => false,
        };
        let current = self.current_version_of(sensor_id)?.value;
        if !repairing {
            if let Some(current) = current {
                if version <= current {
                    return Ok(Err(Rejection::Stale {
                        sensor_id: sensor_id.clone(),
                        version,
                        current,
                    }));
                }
            }
        }
        let new_current = current.map_or(version, |c| c.max(version));

        let value = to_json(record);
        let current_key = keys::current_key(sensor_id);
        let current_value = keys::encode_version(new_current);
        (&self.records, &self.current)
            .transaction(|(records, current)| {
                records.insert(record_key.as_slice(), value.as_slice())?;
                current.insert(current_key.as_slice(), &current_value)?;
                Ok::<_, ConflictableTransactionError<()>>(())
            })
            .map_err(|e| match e {
                TransactionError::Storage(e) => db_error("write record", e),
                // The closure above never aborts.
                TransactionError::Abort(()) => StoreError::Io {
                    action: "write record",
                    source: std::io::Error::other("transaction aborted"),
                },
            })?;
        debug!(sensor = %sensor_id, version, repairing, "stored calibration record");
        Ok(Ok(if repairing {
            PutOutcome::Repaired
        } else {
            PutOutcome::Stored
        }))
    }

    /// The current version of a sensor from the index, or from the records themselves when the
    /// index entry is unreadable (the index is only a shortcut to the newest record key).
    fn current_version_of(&self, sensor_id: &SensorId) -> Result<Scan<Option<u64>>, StoreError> {
        let value = self
            .current
            .get(keys::current_key(sensor_id))
            .map_err(|e| db_error("read current version", e))?;
        match value {
            None => Ok(Scan::new(None)),
            Some(v) => match keys::decode_version(&v) {
                Ok(version) => Ok(Scan::new(Some(version))),
                Err(problem) => {
                    let entry = corrupt(keys::CURRENT_TREE, sensor_id.to_string(), problem);
                    let newest = self.newest_version_in_records(sensor_id)?;
                    Ok(Scan {
                        value: newest,
                        skipped: vec![entry],
                    })
                }
            },
        }
    }

    fn newest_version_in_records(&self, sensor_id: &SensorId) -> Result<Option<u64>, StoreError> {
        let last = self
            .records
            .scan_prefix(keys::sensor_prefix(sensor_id))
            .next_back()
            .transpose()
            .map_err(|e| db_error("scan records", e))?;
        Ok(last.and_then(|(key, _)| keys::parse_record_key(&key).ok().map(|(_, v)| v)))
    }

    /// One version of a sensor's record; `Err(Corrupt)` if that entry cannot be decoded.
    pub fn get(
        &self,
        sensor_id: &SensorId,
        version: u64,
    ) -> Result<Option<CalibrationRecord>, StoreError> {
        let key = keys::record_key(sensor_id, version);
        match self
            .records
            .get(&key)
            .map_err(|e| db_error("read record", e))?
        {
            None => Ok(None),
            Some(value) => decode_record(&key, &value)
                .map(Some)
                .map_err(StoreError::Corrupt),
        }
    }

    /// The version of the sensor's current (highest-version) record, whether or not that
    /// record is still readable: what a newer put must exceed.
    pub fn current_version(&self, sensor_id: &SensorId) -> Result<Option<u64>, StoreError> {
        Ok(self.current_version_of(sensor_id)?.value)
    }

    /// The sensor's current (highest-version) record, whatever its validity window.
    ///
    /// An unreadable index entry is logged and worked around; an unreadable current record is
    /// `Err(Corrupt)`, because answering with an older version would silently apply a
    /// superseded calibration.
    pub fn current(&self, sensor_id: &SensorId) -> Result<Option<CalibrationRecord>, StoreError> {
        match self.current_version_of(sensor_id)?.value {
            None => Ok(None),
            Some(version) => match self.get(sensor_id, version)? {
                Some(record) => Ok(Some(record)),
                None => Err(StoreError::Corrupt(corrupt(
                    keys::CURRENT_TREE,
                    sensor_id.to_string(),
                    format!("index names version {version}, which is not stored"),
                ))),
            },
        }
    }

    /// The record in force at `at`: the newest version whose window `[valid_from, valid_until)`
    /// contains it, as a StationXML channel epoch. Unreadable versions are skipped and listed.
    pub fn at(
        &self,
        sensor_id: &SensorId,
        at: OffsetDateTime,
    ) -> Result<Scan<Option<CalibrationRecord>>, StoreError> {
        let mut scan = Scan::new(None);
        for entry in self
            .records
            .scan_prefix(keys::sensor_prefix(sensor_id))
            .rev()
        {
            let (key, value) = entry.map_err(|e| db_error("scan records", e))?;
            match decode_record(&key, &value) {
                Ok(record) if in_force_at(&record, at) => {
                    scan.value = Some(record);
                    break;
                }
                Ok(_) => {}
                Err(skipped) => scan.skipped.push(skipped),
            }
        }
        Ok(scan)
    }

    /// Every stored version of a sensor, oldest first.
    pub fn history(
        &self,
        sensor_id: &SensorId,
    ) -> Result<Scan<Vec<CalibrationRecord>>, StoreError> {
        self.decode_range(self.records.scan_prefix(keys::sensor_prefix(sensor_id)))
    }

    fn decode_range(&self, iter: sled::Iter) -> Result<Scan<Vec<CalibrationRecord>>, StoreError> {
        let mut scan = Scan::new(Vec::new());
        for entry in iter {
            let (key, value) = entry.map_err(|e| db_error("scan records", e))?;
            match decode_record(&key, &value) {
                Ok(record) => scan.value.push(record),
                Err(skipped) => scan.skipped.push(skipped),
            }
        }
        Ok(scan)
    }

    /// Every version of every sensor, by sensor id then version.
    pub fn all_records(&self) -> Result<Scan<Vec<CalibrationRecord>>, StoreError> {
        self.decode_range(self.records.iter())
    }

    /// Every sensor with its current version, by sensor id.
    pub fn list(&self) -> Result<Scan<Vec<SensorVersion>>, StoreError> {
        let mut scan = Scan::new(Vec::new());
        for entry in self.current.iter() {
            let (key, value) = entry.map_err(|e| db_error("scan current versions", e))?;
            let sensor_id = match keys::parse_current_key(&key) {
                Ok(id) => id,
                Err(problem) => {
                    scan.skipped
                        .push(corrupt(keys::CURRENT_TREE, keys::escape(&key), problem));
                    continue;
                }
            };
            let version = match keys::decode_version(&value) {
                Ok(version) => Some(version),
                Err(problem) => {
                    scan.skipped
                        .push(corrupt(keys::CURRENT_TREE, sensor_id.to_string(), problem));
                    self.newest_version_in_records(&sensor_id)?
                }
            };
            if let Some(version) = version {
                scan.value.push(SensorVersion { sensor_id, version });
            }
        }
        Ok(scan)
    }

    /// The current record of every sensor, by sensor id. A sensor whose current record is
    /// unreadable is skipped and listed, not replaced by an older version. Decoding runs on
    /// every core.
    pub fn current_records(&self) -> Result<Scan<Vec<CalibrationRecord>>, StoreError> {
        self.map_current(|record| record)
    }

    /// What a gateway does at start: the current record of every sensor loaded into a
    /// corrector, decoding and loading on every core. A record that no longer loads (stored by
    /// a build with looser checks) comes with its [`LoadError`] rather than being dropped.
    pub fn load_current(&self) -> Result<Scan<Vec<Loaded>>, StoreError> {
        // The record itself is dropped as soon as its corrector is built: a gateway with ten
        // thousand sensors keeps only the correctors, never every record at once.
        self.map_current(|record| Loaded {
            corrector: Corrector::from_record(&record),
            sensor_id: record.sensor_id,
            version: record.version,
        })
    }

    /// Reads every current entry, then decodes and maps them in parallel, a chunk at a time so
    /// that at most [`LOAD_CHUNK`] encoded records are held at once: a caller keeps what it
    /// derives from each record, not the records.
    pub fn map_current<T: Send>(
        &self,
        f: impl Fn(CalibrationRecord) -> T + Sync,
    ) -> Result<Scan<Vec<T>>, StoreError> {
        let listed = self.list()?;
        let mut skipped = listed.skipped;
        let mut value = Vec::with_capacity(listed.value.len());
        let mut raw = Vec::with_capacity(LOAD_CHUNK.min(listed.value.len()));
        for chunk in listed.value.chunks(LOAD_CHUNK) {
            raw.clear();
            for SensorVersion { sensor_id, version } in chunk {
                let key = keys::record_key(sensor_id, *version);
                match self
                    .records
                    .get(&key)
                    .map_err(|e| db_error("read record", e))?
                {
                    Some(v) => raw.push((key, v)),
                    None => skipped.push(corrupt(
                        keys::CURRENT_TREE,
                        sensor_id.to_string(),
                        format!("index names version {version}, which is not stored"),
                    )),
                }
            }
            for item in parallel_map(&raw, |(key, v)| decode_record(key, v).map(&f)) {
                match item {
                    Ok(item) => value.push(item),
                    Err(entry) => skipped.push(entry),
                }
            }
        }
        Ok(Scan { value, skipped })
    }

    /// Every record newer than what a peer has: for each sensor in the store, the versions above
    /// `known[sensor]`, or all its versions when the peer does not know the sensor. Sorted by
    /// sensor then version, so putting them in order on the peer is accepted. Sensors the peer
    /// knows and the store does not are ignored.
    pub fn newer_than(
        &self,
        known: &BTreeMap<SensorId, u64>,
    ) -> Result<Scan<Vec<CalibrationRecord>>, StoreError> {
        let listed = self.list()?;
        let mut scan = Scan {
            value: Vec::new(),
            skipped: listed.skipped,
        };
        for SensorVersion { sensor_id, version } in listed.value {
            let have = known.get(&sensor_id).copied().unwrap_or(0);
            if version <= have {
                continue;
            }
            // have < version ≤ u64::MAX, so have + 1 cannot overflow.
            let from = keys::record_key(&sensor_id, have + 1);
            let to = keys::record_key(&sensor_id, u64::MAX);
            let part = self.decode_range(self.records.range(from..=to))?;
            scan.value.extend(part.value);
            scan.skipped.extend(part.skipped);
        }
        Ok(scan)
    }

    /// Decodes every entry and checks the index against the records: each sensor's index entry
    /// names its highest stored version. Returns every problem found; empty means consistent.
    pub fn check(&self) -> Result<Vec<CorruptEntry>, StoreError> {
        let mut problems = Vec::new();
        let mut newest: BTreeMap<SensorId, u64> = BTreeMap::new();
        for entry in self.records.iter() {
            let (key, value) = entry.map_err(|e| db_error("scan records", e))?;
            match decode_record(&key, &value) {
                Ok(record) => {
                    newest.insert(record.sensor_id, record.version);
                }
                Err(entry) => {
                    problems.push(entry);
                    if let Ok((sensor_id, version)) = keys::parse_record_key(&key) {
                        newest.insert(sensor_id, version);
                    }
                }
            }
        }
        let listed = self.list()?;
        problems.extend(listed.skipped);
        let indexed: BTreeMap<SensorId, u64> = listed
            .value
            .into_iter()
            .map(|sv| (sv.sensor_id, sv.version))
            .collect();
        for (sensor_id, &version) in &newest {
            if indexed.get(sensor_id) != Some(&version) {
                problems.push(corrupt(
                    keys::CURRENT_TREE,
                    sensor_id.to_string(),
                    format!(
                        "index says {:?}, highest stored version is {version}",
                        indexed.get(sensor_id)
                    ),
                ));
            }
        }
        for (sensor_id, version) in &indexed {
            if !newest.contains_key(sensor_id) {
                problems.push(corrupt(
                    keys::CURRENT_TREE,
                    sensor_id.to_string(),
                    format!("index names version {version} of a sensor with no records"),
                ));
            }
        }
        Ok(problems)
    }
}

// The gateway shares one store between its tasks (`Arc<Store>` with `spawn_blocking`).
const _: fn() = || {
    fn shared<T: Send + Sync>() {}
    shared::<Store>();
};
