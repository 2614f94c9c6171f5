//! Live feeds: one sensor's corrected stream and tilt, kept for the last minutes while at least
//! one page watches it.
//!
//! A feed subscribes to `triax/<b>/corrected/<s>` and `triax/<b>/tilt/<s>` when the first page
//! opens the sensor and undeclares both when the last one leaves, so the console carries only
//! the streams someone looks at, whatever the size of the fleet. On opening, it reads the last
//! [`KEEP_NS`] from the gateway's history, so a page shows the recent past at once rather than
//! an empty plot that fills. Each feed keeps the batches of the last [`KEEP_NS`] by the
//! sensor's clock, at most [`MAX_SAMPLES`] samples, and the tilt samples of the same span;
//! pages decimate from it ([`crate::buckets`]).

use std::collections::{HashMap, VecDeque};
use std::sync::{Arc, Mutex, MutexGuard, Weak};

use triax_protocol::batch::CorrectedBatch;
use triax_protocol::messages::TiltSample;
use triax_protocol::provenance::digest;
use triax_protocol::{from_json, BuildingId, Key, SensorId};

use triax_client::HistoryRequest;

use crate::buckets::{Aggregator, RangeError, View};
use crate::provenance::{Provenance, SealWatch};

pub fn wall_clock_ns() -> i64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| i64::try_from(d.as_nanos()).unwrap_or(i64::MAX))
}

/// Span of stream a feed keeps, by the sensor's clock.
pub const KEEP_NS: i64 = 600 * 1_000_000_000;
/// Most samples a feed keeps (10 minutes at about 330 Hz).
pub const MAX_SAMPLES: usize = 200_000;
/// Most tilt samples a feed keeps.
pub const MAX_TILT: usize = 1200;

#[derive(Default)]
struct Ring {
    batches: VecDeque<Arc<CorrectedBatch>>,
    samples: usize,
    tilt: VecDeque<TiltSample>,
    /// Corrected payloads and tilt samples that did not decode or named another sensor.
    malformed: u64,
    /// Times older batches were put in front (the history read on opening).
    prepends: u64,
    /// Batches pushed since the feed opened: the newest `arrivals - n` are at the back.
    arrivals: u64,
}

fn end_ns(b: &CorrectedBatch) -> i64 {
    let n = b.samples.len() as f64;
    b.header
        .timestamp_ns
        .saturating_add((n * 1e9 / b.header.sample_rate_hz) as i64)
}

impl Ring {
    fn push(&mut self, b: CorrectedBatch) {
        self.arrivals += 1;
        let newest = end_ns(&b);
        self.samples += b.samples.len();
        self.batches.push_back(Arc::new(b));
        while let Some(old) = self.batches.front() {
            let too_old = end_ns(old) < newest.saturating_sub(KEEP_NS);
            if !(too_old || self.samples > MAX_SAMPLES) || self.batches.len() == 1 {
                break;
            }
            self.samples -= old.samples.len();
            self.batches.pop_front();
        }
    }

    /// Puts batches read from the history in front of the live ones: those that ended before
    /// the first live batch began, in the order given (the gateway's).
    fn prepend(&mut self, older: Vec<CorrectedBatch>) {
        let first_ns = self.batches.front().map(|b| b.header.timestamp_ns);
        let keep: Vec<CorrectedBatch> = older
            .into_iter()
            .filter(|b| first_ns.is_none_or(|f| end_ns(b) <= f))
            .collect();
        if keep.is_empty() {
            return;
        }
        let newest = self
            .batches
            .back()
            .map_or_else(|| keep.last().map_or(0, end_ns), |b| end_ns(b));
        for b in keep.into_iter().rev() {
            if end_ns(&b) < newest.saturating_sub(KEEP_NS)
                || self.samples + b.samples.len() > MAX_SAMPLES
            {
                break;
            }
            self.samples += b.samples.len();
            self.batches.push_front(Arc::new(b));
        }
        self.prepends += 1;
    }

    fn push_tilt(&mut self, t: TiltSample) {
        let cutoff = t.timestamp_ns.saturating_sub(KEEP_NS);
        self.tilt.push_back(t);
        while self.tilt.len() > MAX_TILT
            || self.tilt.front().is_some_and(|f| f.timestamp_ns < cutoff)
        {
            self.tilt.pop_front();
        }
    }
}

/// One sensor's live stream, shared by every page that watches it.
pub struct Feed {
    pub building: BuildingId,
    pub sensor: SensorId,
    ring: Arc<Mutex<Ring>>,
    _corrected: zenoh::pubsub::Subscriber<()>,
    _tilt: zenoh::pubsub::Subscriber<()>,
    /// The building's seals, while the console verifies its gateway.
    _seals: Option<Arc<SealWatch>>,
}

fn lock(ring: &Mutex<Ring>) -> MutexGuard<'_, Ring> {
    // Pushes and reads cannot panic halfway.
    ring.lock().unwrap_or_else(|p| p.into_inner())
}

impl Feed {
    /// End of the newest batch, by the sensor's clock.
    pub fn newest_end_ns(&self) -> Option<i64> {
        lock(&self.ring).batches.back().map(|b| end_ns(b))
    }

    /// Decimates `[from_ns, to_ns)` into buckets of `bucket_ns`.
    pub fn view(&self, from_ns: i64, to_ns: i64, bucket_ns: i64) -> Result<View, RangeError> {
        let mut agg = Aggregator::new(from_ns, to_ns, bucket_ns)?;
        // Copy the references out so that aggregation runs without the lock that Zenoh's
        // receive thread needs to push.
        let batches: Vec<Arc<CorrectedBatch>> = {
            let r = lock(&self.ring);
            // One batch before the range, for gap detection at its start.
            let first = r.batches.partition_point(|b| end_ns(b) <= from_ns);
            r.batches
                .iter()
                .skip(first.saturating_sub(1))
                .cloned()
                .collect()
        };
        for b in &batches {
            agg.push(b);
        }
        Ok(agg.finish())
    }

    /// Tilt samples newer than `after_ns`.
    pub fn tilt_after(&self, after_ns: i64) -> Vec<TiltSample> {
        let r = lock(&self.ring);
        r.tilt
            .iter()
            .filter(|t| t.timestamp_ns > after_ns)
            .cloned()
            .collect()
    }

    /// How many batches have arrived, and the earliest start among those that arrived after
    /// the first `seen` of them (None if none did, or all are gone from the buffer): where a
    /// page that has everything up to `seen` must be sent from, a late batch included.
    pub fn arrivals_since(&self, seen: u64) -> (u64, Option<i64>) {
        let r = lock(&self.ring);
        let new = usize::try_from(r.arrivals.saturating_sub(seen)).unwrap_or(usize::MAX);
        let earliest = r
            .batches
            .iter()
            .rev()
            .take(new)
            .map(|b| b.header.timestamp_ns)
            .min();
        (r.arrivals, earliest)
    }

    pub fn malformed(&self) -> u64 {
        lock(&self.ring).malformed
    }

    /// Changes when older data was put in front: a page then needs its whole window again.
    pub fn prepends(&self) -> u64 {
        lock(&self.ring).prepends
    }
}

/// The feeds being watched, each alive while a page holds it.
pub struct Feeds {
    session: zenoh::Session,
    /// How long the history read on opening may take.
    timeout: std::time::Duration,
    feeds: Mutex<HashMap<(BuildingId, SensorId), Weak<Feed>>>,
    provenance: Arc<Provenance>,
}

/// Pushes a corrected payload to a feed's ring, if it decodes and names the feed's sensor.
fn push_corrected(ring: &Mutex<Ring>, expected: &SensorId, payload: &[u8]) {
    let mut g = lock(ring);
    match CorrectedBatch::decode(payload) {
        Ok(b) if b.header.sensor_id == *expected => g.push(b),
        _ => g.malformed += 1,
    }
}

impl Feeds {
    pub fn new(
        session: zenoh::Session,
        timeout: std::time::Duration,
        provenance: Arc<Provenance>,
    ) -> Feeds {
        Feeds {
            session,
            timeout,
            feeds: Mutex::new(HashMap::new()),
            provenance,
        }
    }

    /// The sensor's feed, subscribing if no page watches it yet.
    pub async fn open(&self, building: &BuildingId, sensor: &SensorId) -> zenoh::Result<Arc<Feed>> {
        let id = (building.clone(), sensor.clone());
        if let Some(f) = self.lock().get(&id).and_then(Weak::upgrade) {
            return Ok(f);
        }
        let ring = Arc::new(Mutex::new(Ring::default()));
        let seals = self.provenance.seal_watch(&self.session, building).await?;
        let (r, expected, w) = (ring.clone(), sensor.clone(), seals.clone());
        let corrected = self
            .session
            .declare_subscriber(Key::Corrected(building.clone(), sensor.clone()).to_string())
            .callback(move |sample| {
                let payload = sample.payload().to_bytes();
                match &w {
                    None => push_corrected(&r, &expected, &payload),
                    Some(w) => {
                        let (r, expected) = (r.clone(), expected.clone());
                        let d = digest(sample.key_expr().as_str(), &[], &payload);
                        let owned = payload.into_owned();
                        w.offer(d, Box::new(move || push_corrected(&r, &expected, &owned)));
                    }
                }
            })
            .await?;
        let (r, expected, p) = (ring.clone(), sensor.clone(), self.provenance.clone());
        let tilt = self
            .session
            .declare_subscriber(Key::Tilt(building.clone(), sensor.clone()).to_string())
            .callback(move |sample| {
                let payload = sample.payload().to_bytes();
                let attachment = sample.attachment().map(|a| a.to_bytes());
                if !p.put(sample.key_expr().as_str(), &payload, attachment.as_deref()) {
                    return;
                }
                let mut g = lock(&r);
                match from_json::<TiltSample>(&payload) {
                    Ok(t) if t.sensor_id == expected => g.push_tilt(t),
                    _ => g.malformed += 1,
                }
            })
            .await?;
        let feed = Arc::new(Feed {
            building: building.clone(),
            sensor: sensor.clone(),
            ring,
            _corrected: corrected,
            _tilt: tilt,
            _seals: seals,
        });
        let mut map = self.lock();
        // Another page may have opened it meanwhile: keep one.
        if let Some(f) = map.get(&id).and_then(Weak::upgrade) {
            return Ok(f);
        }
        map.retain(|_, w| w.strong_count() > 0);
        map.insert(id, Arc::downgrade(&feed));
        drop(map);
        // The recent past, from the history, while the live stream already flows.
        let mut request = HistoryRequest::sensor(building, sensor);
        request.from_ns = Some(wall_clock_ns().saturating_sub(KEEP_NS));
        request.trusted = self.provenance.keys().cloned();
        let (session, ring, timeout) = (self.session.clone(), feed.ring.clone(), self.timeout);
        tokio::spawn(async move {
            let mut older = Vec::new();
            let fetched = triax_client::history::fetch(&session, &request, timeout, &mut |r| {
                older.push(r.batch)
            })
            .await;
            if let Err(e) = fetched {
                tracing::debug!(cause = %e, "no history for the live view");
            }
            lock(&ring).prepend(older);
        });
        Ok(feed)
    }

    fn lock(&self) -> MutexGuard<'_, HashMap<(BuildingId, SensorId), Weak<Feed>>> {
        // Inserts and removals cannot panic halfway.
        self.feeds.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Sensors watched now.
    pub fn watched(&self) -> usize {
        self.lock()
            .values()
            .filter(|w| w.strong_count() > 0)
            .count()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use triax_protocol::batch::CorrectedSample;

    fn batch(seq: u64, n: usize) -> CorrectedBatch {
        triax_protocol::batch::sample::dynamic(
            SensorId::new("s").unwrap(),
            seq,
            seq as i64 * n as i64 * 10_000_000,
            100.0,
            vec![
                CorrectedSample {
                    accel_mps2: [0.0; 3],
                    uncertainty_mps2: [0.0; 3],
                    flags: 0
                };
                n
            ],
        )
    }

    #[test]
    fn history_goes_in_front_of_the_live_batches_without_overlap() {
        let mut r = Ring::default();
        for seq in 10..12 {
            r.push(batch(seq, 50));
        }
        // The history also holds 10 and 11, which arrived live meanwhile.
        r.prepend((0..12).map(|seq| batch(seq, 50)).collect());
        let seqs: Vec<u64> = r.batches.iter().map(|b| b.header.sequence).collect();
        assert_eq!(seqs, (0..12).collect::<Vec<_>>());
        assert_eq!(r.samples, 12 * 50);
        assert_eq!(r.prepends, 1);
    }

    #[test]
    fn the_ring_keeps_ten_minutes_and_a_sample_budget() {
        let mut r = Ring::default();
        // 0.5 s batches for 15 minutes.
        for seq in 0..1800 {
            r.push(batch(seq, 50));
        }
        let span =
            end_ns(r.batches.back().unwrap()) - r.batches.front().unwrap().header.timestamp_ns;
        assert!(
            (KEEP_NS - 500_000_000..=KEEP_NS + 500_000_000).contains(&span),
            "{span}"
        );
        let mut r = Ring::default();
        for seq in 0..100 {
            r.push(batch(seq, 16_384));
        }
        assert!(r.samples <= MAX_SAMPLES, "{}", r.samples);
        assert_eq!(
            r.samples,
            r.batches.iter().map(|b| b.samples.len()).sum::<usize>()
        );
    }
}
