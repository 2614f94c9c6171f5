//! History queries: `triax/<building>/history/<sensor>` answered from the history, each kept
//! batch corrected again (PROTOCOL.md §5.1).
//!
//! A replay starts from the checkpoint the history holds before the first batch wanted: the
//! sensor's correction state as the worker had it then ([`SensorKernel::restore`]). Every batch
//! from there on goes through [`correct_judged`], the live path's own function, with the
//! verdict the worker gave it and the calibration it used, so with `calibration=in_force` the
//! bytes are the live stream's. With `latest` or a version number, the same filter memory meets
//! another record; a sensor with no checkpoint kept before the range (its oldest data, once
//! retention took the rest) starts from a fresh state.
//!
//! Every later checkpoint the scan meets is restored too, not only the first. Within one run of
//! the gateway it equals the replay's own state; but the live kernel starts afresh when the
//! gateway restarts (or forgets a sensor and meets it again), and goes on from a batch the
//! history could not keep, and the checkpoint the worker writes then is the only record of it.
//! So a batch's replay depends on the checkpoint before it and the batches between, exactly as
//! its live correction did, wherever the query starts.
//!
//! Queries run on blocking threads, at most [`CONCURRENT_QUERIES`] at a time (others wait):
//! a burst of queries takes at most that many threads from correction. Replies travel at the
//! priority the querier gave its query (PROTOCOL.md advises a low one).

use std::collections::HashMap;
use std::sync::Arc;

use tokio::task::JoinHandle;
use triax_calibration::corrector::Corrector;
use triax_calibration_store::Store;
use triax_history::{Block, Query};
use triax_protocol::batch::BatchHeader;
use triax_protocol::keys::{self, Stream};
use triax_protocol::provenance::{check_nonce, digest, Digest, Seal};
use triax_protocol::{BuildingId, Key, RawBatchView, SensorId};
use zenoh::key_expr::KeyExpr;
use zenoh::Wait;

use super::{Context, Task};
use crate::error::{zenoh_err, GatewayError};
use crate::sample_path::{correct_judged, suspect_flag, Scratch, SensorKernel, Sink};
use crate::shutdown::Shutdown;
use crate::state::{SensorTable, Signer};

/// History queries served at the same time.
pub const CONCURRENT_QUERIES: usize = 2;
/// Default and largest `limit`.
pub const DEFAULT_LIMIT: usize = 10_000;
pub const MAX_LIMIT: usize = 100_000;
/// Longest a query waits for what the workers queued to be flushed.
const SYNC_TIMEOUT: std::time::Duration = std::time::Duration::from_secs(2);

/// Which record corrects the replayed batches.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Calibration {
    /// The record each batch was corrected with when it arrived.
    InForce,
    /// The sensor's newest record.
    Latest,
    Version(u64),
}

/// A history query's parameters.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct HistoryQuery {
    pub from_ns: Option<i64>,
    pub to_ns: Option<i64>,
    pub from_seq: Option<u64>,
    pub to_seq: Option<u64>,
    pub limit: usize,
    /// Continue after this sensor's batch of this arrival number.
    pub after: Option<(SensorId, u64)>,
    pub calibration: Calibration,
    /// Asked for: the answer is sealed, the seals bound to it (PROTOCOL.md §6).
    pub nonce: Option<String>,
}

impl HistoryQuery {
    /// Reads the selector's parameters; the error names the parameter and what is wrong.
    pub fn parse<'a>(
        parameters: impl IntoIterator<Item = (&'a str, &'a str)>,
    ) -> Result<HistoryQuery, String> {
        let mut q = HistoryQuery {
            from_ns: None,
            to_ns: None,
            from_seq: None,
            to_seq: None,
            limit: DEFAULT_LIMIT,
            after: None,
            calibration: Calibration::InForce,
            nonce: None,
        };
        fn number<T: std::str::FromStr>(name: &str, value: &str) -> Result<T, String> {
            value
                .parse::<T>()
                .map_err(|_| format!("history query: {name}: {value:?} is not a whole number"))
        }
        for (name, value) in parameters {
            match name {
                "from_ns" => q.from_ns = Some(number(name, value)?),
                "to_ns" => q.to_ns = Some(number(name, value)?),
                "from_seq" => q.from_seq = Some(number(name, value)?),
                "to_seq" => q.to_seq = Some(number(name, value)?),
                "limit" => {
                    q.limit = number(name, value)?;
                    if !(1..=MAX_LIMIT).contains(&q.limit) {
                        return Err(format!(
                            "history query: limit: {value} is outside 1..={MAX_LIMIT}"
                        ));
                    }
                }
                "after" => {
                    let bad = || {
                        format!("history query: after: {value:?} is not a cursor <sensor>:<position> from a reply")
                    };
                    let (s, p) = value.rsplit_once(':').ok_or_else(bad)?;
                    let sensor = SensorId::new(s).map_err(|_| bad())?;
                    q.after = Some((sensor, p.parse().map_err(|_| bad())?));
                }
                "calibration" => {
                    q.calibration = match value {
                        "in_force" => Calibration::InForce,
                        "latest" => Calibration::Latest,
                        v => match v.parse::<u64>() {
                            Ok(n) if n >= 1 => Calibration::Version(n),
                            _ => {
                                return Err(format!(
                                    "history query: calibration: {value:?} is not in_force, latest or a version number ≥ 1"
                                ))
                            }
                        },
                    }
                }
                "nonce" => {
                    check_nonce(value).map_err(|e| format!("history query: {e}"))?;
                    q.nonce = Some(value.to_owned());
                }
                other => {
                    return Err(format!(
                        "history query: unknown parameter {other:?} (known: from_ns, to_ns, from_seq, to_seq, limit, after, calibration, nonce)"
                    ))
                }
            }
        }
        Ok(q)
    }

    /// The storage query for one sensor.
    fn for_sensor(&self, sensor: &SensorId) -> Query {
        Query {
            sensor: sensor.clone(),
            from_ns: self.from_ns,
            to_ns: self.to_ns,
            from_seq: self.from_seq,
            to_seq: self.to_seq,
            after_arrival: self
                .after
                .as_ref()
                .filter(|(s, _)| s == sensor)
                .map(|(_, a)| *a),
        }
    }
}

/// What replays need.
pub struct ReplayContext {
    pub building: BuildingId,
    pub table: Arc<SensorTable>,
    pub store: Arc<Store>,
    pub sink: Arc<Sink>,
    pub signer: Arc<Signer>,
}

/// The correctors of one replay, by version: each record is read and loaded once.
struct Correctors<'a> {
    store: &'a Store,
    sensor: &'a SensorId,
    loaded: HashMap<u64, Option<Arc<Corrector>>>,
    latest: Option<Option<u64>>,
    /// Per version, the time its `calibration_suspect` starts, if it was found suspect.
    suspect: HashMap<u64, Option<i64>>,
}

impl Correctors<'_> {
    fn version(&mut self, v: u64) -> Result<Option<Arc<Corrector>>, String> {
        if v == 0 {
            return Ok(None);
        }
        if let Some(c) = self.loaded.get(&v) {
            return Ok(c.clone());
        }
        let record = self
            .store
            .get(self.sensor, v)
            .map_err(|e| format!("calibration store: {e}"))?;
        let c = match record {
            Some(r) => Some(Arc::new(
                Corrector::from_record(&r).map_err(|e| format!("record {v}: {e}"))?,
            )),
            None => None,
        };
        self.loaded.insert(v, c.clone());
        Ok(c)
    }

    /// The flag a batch corrected with version `v` at `timestamp_ns` carries on every sample:
    /// the live path's rule ([`crate::sample_path::suspect_flag`]) on the store's mark.
    fn suspect_flag(&mut self, v: u64, timestamp_ns: i64) -> Result<u16, String> {
        if v == 0 {
            return Ok(0);
        }
        let from_ns = match self.suspect.get(&v) {
            Some(f) => *f,
            None => {
                let f = self
                    .store
                    .suspect_from(self.sensor, v)
                    .map_err(|e| format!("calibration store: {e}"))?;
                self.suspect.insert(v, f);
                f
            }
        };
        Ok(suspect_flag(from_ns.map(|f| (v, f)), Some(v), timestamp_ns))
    }

    fn latest(&mut self) -> Result<u64, String> {
        if self.latest.is_none() {
            self.latest = Some(
                self.store
                    .current_version(self.sensor)
                    .map_err(|e| format!("calibration store: {e}"))?,
            );
        }
        Ok(self.latest.flatten().unwrap_or(0))
    }
}

/// Replays one sensor's batches for `q`, handing each wanted one (its corrected payload and
/// arrival number) to `emit` until `emit` says stop. Returns how many were handed over.
pub fn replay(
    ctx: &ReplayContext,
    sensor: &SensorId,
    q: &HistoryQuery,
    emit: &mut dyn FnMut(&[u8], u64) -> bool,
) -> Result<usize, String> {
    let history = &ctx.sink.history;
    let query = q.for_sensor(sensor);
    let mut scan = history.scan(&query).map_err(|e| e.to_string())?;
    let mut correctors = Correctors {
        store: &ctx.store,
        sensor,
        loaded: HashMap::new(),
        latest: None,
        suspect: HashMap::new(),
    };
    if let Calibration::Version(v) = q.calibration {
        if correctors.version(v)?.is_none() {
            return Err(format!(
                "history query: calibration: sensor {sensor} has no version {v}"
            ));
        }
    }
    let mut kernel: Option<SensorKernel> = None;
    let (mut out, mut scratch) = (Vec::new(), Scratch::default());
    let mut emitted = 0;
    while let Some(block) = scan.next_block() {
        let bytes = match block {
            Ok(b) => b.bytes,
            Err(e) => {
                history.count_damaged();
                tracing::error!(sensor = %sensor, cause = %e, "history block skipped");
                continue;
            }
        };
        let block = match Block::decode(&bytes) {
            Ok(b) if &b.sensor == sensor => b,
            // Another sensor whose id hashes alike.
            Ok(_) => continue,
            Err(e) => {
                history.count_damaged();
                tracing::error!(sensor = %sensor, cause = %e, "history block does not decode");
                continue;
            }
        };
        // A checkpoint of an older format (a gateway before an upgrade) does not restore: the
        // state so far is the best there is, or a fresh one at the start.
        if let Some(restored) = block.checkpoint.and_then(SensorKernel::restore) {
            kernel = Some(restored);
        }
        let kernel = kernel.get_or_insert_with(|| SensorKernel::new(ctx.table.settings_of(sensor)));
        for k in &block.kept {
            let version = match q.calibration {
                Calibration::InForce => k.calibration_version,
                Calibration::Latest => correctors.latest()?,
                Calibration::Version(v) => v,
            };
            let corrector = correctors.version(version)?;
            let suspect = correctors.suspect_flag(version, k.timestamp_ns)?;
            let header = BatchHeader {
                sensor_id: sensor.clone(),
                sequence: k.sequence,
                timestamp_ns: k.timestamp_ns,
                sample_rate_hz: k.sample_rate_hz,
            };
            // Kept from a batch the worker parsed: its parts are valid.
            let Ok(view) = RawBatchView::from_parts(header, k.temperature_c, k.samples) else {
                continue;
            };
            out.clear();
            correct_judged(
                kernel,
                &view,
                corrector.as_deref(),
                k.verdict,
                suspect,
                &mut scratch,
                &mut out,
            );
            if query.matches(k) {
                emitted += 1;
                if !emit(&out, k.arrival) {
                    return Ok(emitted);
                }
            }
        }
    }
    Ok(emitted)
}

/// Serves history queries until shutdown.
pub async fn serve(
    session: zenoh::Session,
    ctx: Arc<ReplayContext>,
    mut shutdown: Shutdown,
) -> zenoh::Result<JoinHandle<()>> {
    let queryable = session
        .declare_queryable(keys::all_sensors(&ctx.building, Stream::History))
        .await?;
    let permits = Arc::new(tokio::sync::Semaphore::new(CONCURRENT_QUERIES));
    Ok(tokio::spawn(async move {
        loop {
            let query = tokio::select! {
                q = queryable.recv_async() => match q { Ok(q) => q, Err(_) => break },
                _ = shutdown.recv() => break,
            };
            // Closed only when the gateway stops.
            let Ok(permit) = permits.clone().acquire_owned().await else {
                break;
            };
            let ctx = ctx.clone();
            tokio::task::spawn_blocking(move || {
                answer(&ctx, &query);
                drop(permit);
            });
        }
    }))
}

/// Why `sensor` cannot be replayed with its version `v`, if it cannot.
fn lacks_version(ctx: &ReplayContext, sensor: &SensorId, v: u64) -> Option<String> {
    match ctx.store.get(sensor, v) {
        Ok(Some(_)) => None,
        Ok(None) => Some(format!(
            "history query: calibration: sensor {sensor} has no version {v}"
        )),
        Err(e) => Some(format!("calibration store: {e}")),
    }
}

/// Answers one query; runs on a blocking thread.
fn answer(ctx: &ReplayContext, query: &zenoh::query::Query) {
    let q = match HistoryQuery::parse(query.parameters().iter()) {
        Ok(q) => q,
        Err(problem) => {
            if let Err(e) = query.reply_err(problem).wait() {
                tracing::warn!(cause = %e, "history error reply failed");
            }
            return;
        }
    };
    if !ctx.sink.sync(SYNC_TIMEOUT) {
        tracing::warn!("history query: recent batches not yet on disk; answering with what is");
    }
    let wanted = query.key_expr().clone();
    let mut sensors: Vec<SensorId> = ctx.sink.history.sensors();
    sensors.retain(|s| {
        let key = Key::History(ctx.building.clone(), s.clone()).to_string();
        KeyExpr::try_from(key).is_ok_and(|k| wanted.intersects(&k))
    });
    if let Some((after, _)) = &q.after {
        sensors.retain(|s| s >= after);
    }
    // A version number names a record of each sensor: a query over many sensors of which one
    // lacks it is refused whole, before any batch, rather than answered up to that sensor.
    if let Calibration::Version(v) = q.calibration {
        if let Some(problem) = sensors.iter().find_map(|s| lacks_version(ctx, s, v)) {
            if let Err(e) = query.reply_err(problem).wait() {
                tracing::warn!(cause = %e, "history error reply failed");
            }
            return;
        }
    }
    let mut left = q.limit;
    // Asked with a nonce, each sensor's batches are followed by seals over them.
    let mut sealing = q
        .nonce
        .as_deref()
        .filter(|_| ctx.signer.signs())
        .map(|nonce| AnswerSeals::new(&ctx.signer, nonce));
    for sensor in &sensors {
        let key = Key::History(ctx.building.clone(), sensor.clone()).to_string();
        let mut failed = None;
        let mut emit = |payload: &[u8], arrival: u64| {
            let cursor = format!("{sensor}:{arrival}");
            if let Some(s) = sealing.as_mut() {
                s.add(digest(&key, cursor.as_bytes(), payload));
            }
            let sent = query
                .reply(&key, payload.to_vec())
                .attachment(cursor)
                .wait()
                .map_err(|e| e.to_string())
                .and_then(|()| match sealing.as_mut() {
                    Some(s) if s.full() => s.send(query, &key),
                    _ => Ok(()),
                });
            if let Err(e) = sent {
                failed = Some(e);
                return false;
            }
            left -= 1;
            left > 0
        };
        let replayed = replay(ctx, sensor, &q, &mut emit);
        if let (Some(s), None) = (sealing.as_mut(), &failed) {
            if let Err(e) = s.send(query, &key) {
                failed = Some(e);
            }
        }
        match replayed {
            Ok(_) => {}
            Err(problem) => {
                if let Err(e) = query.reply_err(problem).wait() {
                    tracing::warn!(cause = %e, "history error reply failed");
                }
                return;
            }
        }
        if let Some(cause) = failed {
            tracing::warn!(sensor = %sensor, cause, "history reply failed: the querier is gone");
            return;
        }
        if left == 0 {
            return;
        }
    }
}

/// The seals of one history answer: every [`SEAL_EVERY`] batches, and after each sensor's.
struct AnswerSeals<'a> {
    signer: &'a Signer,
    nonce: &'a str,
    sequence: u64,
    digests: Vec<Digest>,
}

/// Batches a history seal covers at most: a consumer holds this many before it may use them.
const SEAL_EVERY: usize = 256;

impl<'a> AnswerSeals<'a> {
    fn new(signer: &'a Signer, nonce: &'a str) -> AnswerSeals<'a> {
        AnswerSeals {
            signer,
            nonce,
            sequence: 0,
            digests: Vec::with_capacity(SEAL_EVERY),
        }
    }

    fn add(&mut self, d: Digest) {
        self.digests.push(d);
    }

    fn full(&self) -> bool {
        self.digests.len() >= SEAL_EVERY
    }

    /// Replies with a seal over what was answered since the last one, if anything was.
    fn send(&mut self, query: &zenoh::query::Query, key: &str) -> Result<(), String> {
        if self.digests.is_empty() {
            return Ok(());
        }
        let payload = Seal {
            sequence: self.sequence,
            digests: std::mem::take(&mut self.digests),
        }
        .encode();
        self.sequence += 1;
        let reply = query
            .reply(key, payload.clone())
            .attachment(self.signer.attachment(key, self.nonce, &payload));
        reply.wait().map_err(|e| e.to_string())
    }
}

/// Starts the history queryable over what `sink`'s history holds.
pub async fn start(ctx: &Context, sink: &Arc<Sink>) -> Result<Task, GatewayError> {
    let replay = Arc::new(ReplayContext {
        building: ctx.config.building.clone(),
        table: ctx.table.clone(),
        store: ctx.store.clone(),
        sink: sink.clone(),
        signer: ctx.signer.clone(),
    });
    serve(ctx.session.clone(), replay, ctx.shutdown.clone())
        .await
        .map_err(zenoh_err("declare the history queryable"))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn parse(s: &str) -> Result<HistoryQuery, String> {
        HistoryQuery::parse(
            s.split(';')
                .filter(|p| !p.is_empty())
                .map(|p| p.split_once('=').unwrap_or((p, ""))),
        )
    }

    #[test]
    fn parameters_parse_and_bad_ones_are_named() {
        let q = parse(
            "from_ns=5;to_ns=-7;from_seq=1;to_seq=9;limit=3;after=acc-1:42;calibration=latest",
        )
        .unwrap();
        assert_eq!((q.from_ns, q.to_ns), (Some(5), Some(-7)));
        assert_eq!((q.from_seq, q.to_seq, q.limit), (Some(1), Some(9), 3));
        assert_eq!(q.after, Some((SensorId::new("acc-1").unwrap(), 42)));
        assert_eq!(q.calibration, Calibration::Latest);
        assert_eq!(
            parse("calibration=4").unwrap().calibration,
            Calibration::Version(4)
        );
        assert_eq!(parse("").unwrap().limit, DEFAULT_LIMIT);
        for (bad, named) in [
            ("to_ns=soon", "to_ns"),
            ("limit=0", "limit"),
            ("limit=100001", "limit"),
            ("after=x", "after"),
            ("after=a*b:1", "after"),
            ("calibration=0", "calibration"),
            ("calibration=newest", "calibration"),
            ("from_seq=-1", "from_seq"),
            ("colour=red", "colour"),
            ("nonce=a*b", "nonce"),
            ("nonce=", "nonce"),
        ] {
            let e = parse(bad).unwrap_err();
            assert!(e.contains(named), "{bad}: {e}");
        }
    }
}
