//! One building's live state, with no network in it: each sensor's stream put back in order
//! (holes waited for), fed to the detector, and the events that closed held until their
//! window's data are in.
//!
//! **Order.** The follower hands a sensor's batches over in the order the gateway corrected
//! them, except that a hole the gateway fills from a node's buffer arrives later, flagged
//! `late`. A stream here is released to the detector in time order only: a batch that does not
//! follow the last released one by number waits, with those after it, until the hole's batches
//! arrive or `hole_wait_s` of the service's clock have passed (then the detector sees a break,
//! and an open event stays open across it: [`triax_strongmotion::detect`]). So an event during
//! a gateway's restart is detected once, from the data the gateway kept and filled.
//!
//! **When.** Sensors are released at their own pace; the detector judges an instant once every
//! sensor that is reporting has been released past it (the watermark), and a sensor silent for
//! `silent_after_s` stops holding it back. A closed event's report waits until the watermark
//! passes its window's end (`post_event_s` after the event), or `hole_wait_s` more than that
//! by the service's clock.

use std::collections::{BTreeMap, HashMap, VecDeque};
use std::sync::Arc;

use triax_client::follow::Position;
use triax_protocol::batch::{flags, CorrectedBatch};
use triax_protocol::{BuildingId, SensorId};
use triax_strongmotion::detect::{Coincidence, DetectedEvent};

use crate::config::BuildingConfig;

/// Quality flags that leave a sample unusable for an event (the others are caveats).
pub const UNUSABLE: u16 = flags::UNCALIBRATED | flags::NON_FINITE_INPUT | flags::CLIPPED;
/// Flags a batch may carry that say nothing of its samples' quality.
pub const STREAM_ONLY: u16 = flags::SEQUENCE_GAP | flags::LATE;

/// How much history of released batches a stream remembers for resuming, s of sensor time.
const KEEP_POSITIONS_S: f64 = 1800.0;

struct Stream {
    /// Batches waiting to be released, by first sample's time.
    waiting: BTreeMap<i64, CorrectedBatch>,
    /// The last released batch: sequence, first and end times.
    last: Option<(u64, i64, i64)>,
    /// Since when (service clock) the earliest waiting batch has waited for a hole.
    hole_since_s: Option<f64>,
    last_seen_s: Option<f64>,
    /// Released batches' positions, oldest first.
    positions: VecDeque<Position>,
}

/// An event closed by the detector, waiting for its window's data.
#[derive(Debug, Clone, PartialEq)]
pub struct Pending {
    pub event: DetectedEvent,
    pub window_start_ns: i64,
    pub window_end_ns: i64,
    pub closed_at_s: f64,
}

/// The live state of one building.
pub struct Building {
    pub id: BuildingId,
    pub config: Arc<BuildingConfig>,
    pub sensors: Vec<SensorId>,
    index: HashMap<SensorId, usize>,
    streams: Vec<Stream>,
    pub detector: Coincidence,
    pub pending: Vec<Pending>,
    /// Batches of sensors not in the building's model, skipped.
    pub unknown_batches: u64,
}

fn end_ns(b: &CorrectedBatch) -> i64 {
    b.header.timestamp_ns + (b.samples.len() as f64 * 1e9 / b.header.sample_rate_hz) as i64
}

impl Building {
    pub fn new(id: BuildingId, config: Arc<BuildingConfig>) -> Building {
        let sensors: Vec<SensorId> = config
            .model
            .sensors
            .iter()
            .filter_map(|s| SensorId::new(s.sensor_id.clone()).ok())
            .collect();
        let index = sensors
            .iter()
            .enumerate()
            .map(|(i, s)| (s.clone(), i))
            .collect();
        let streams = sensors
            .iter()
            .map(|_| Stream {
                waiting: BTreeMap::new(),
                last: None,
                hole_since_s: None,
                last_seen_s: None,
                positions: VecDeque::new(),
            })
            .collect();
        Building {
            id,
            detector: Coincidence::new(&config.detector, sensors.len()),
            config,
            sensors,
            index,
            streams,
            pending: Vec::new(),
            unknown_batches: 0,
        }
    }

    /// Takes a batch from the follower at `now_s` (service clock).
    pub fn on_batch(&mut self, batch: CorrectedBatch, now_s: f64) {
        let Some(&i) = self.index.get(&batch.header.sensor_id) else {
            self.unknown_batches += 1;
            return;
        };
        let s = &mut self.streams[i];
        s.last_seen_s = Some(now_s);
        if batch.batch_flags & flags::DUPLICATE != 0 {
            return;
        }
        if let Some((_, _, end)) = s.last {
            if batch.header.timestamp_ns < end {
                return;
            }
        }
        s.waiting.insert(batch.header.timestamp_ns, batch);
        self.release(i, now_s);
    }

    /// Releases stream `i`'s batches that are in order, or whose hole has waited long enough.
    fn release(&mut self, i: usize, now_s: f64) {
        let hole_wait = self.config.hole_wait_s;
        loop {
            let s = &mut self.streams[i];
            let Some((&t, next)) = s.waiting.iter().next() else {
                s.hole_since_s = None;
                return;
            };
            let in_order = match s.last {
                None => true,
                Some((seq, _, end)) => {
                    next.header.sequence == seq.wrapping_add(1)
                        || t - end <= (1.5e9 / next.header.sample_rate_hz) as i64
                }
            };
            if !in_order {
                let since = *s.hole_since_s.get_or_insert(now_s);
                if now_s - since < hole_wait {
                    return;
                }
            }
            s.hole_since_s = None;
            let Some(batch) = s.waiting.remove(&t) else {
                return;
            };
            self.feed(i, &batch);
        }
    }

    fn feed(&mut self, i: usize, batch: &CorrectedBatch) {
        let h = &batch.header;
        let dt_s = 1.0 / h.sample_rate_hz;
        let k = f64::from(batch.info.coverage_factor);
        let detector = &mut self.detector.sensors[i];
        for (j, sample) in batch.samples.iter().enumerate() {
            let t = h.timestamp_ns + (j as f64 * 1e9 * dt_s) as i64;
            let usable = batch.sample_flags(j) & UNUSABLE == 0;
            let a = sample.accel_mps2.map(f64::from);
            let u = sample.uncertainty_mps2.map(f64::from);
            detector.feed(t, a, u, k, usable, dt_s);
        }
        let s = &mut self.streams[i];
        s.last = Some((h.sequence, h.timestamp_ns, end_ns(batch)));
        s.positions.push_back(Position::of(batch));
        let keep = h.timestamp_ns - (KEEP_POSITIONS_S * 1e9) as i64;
        while s.positions.front().is_some_and(|p| p.timestamp_ns < keep) && s.positions.len() > 1 {
            s.positions.pop_front();
        }
    }

    /// Up to when every reporting sensor has been released (ns), none before any data.
    pub fn watermark_ns(&self, now_s: f64) -> Option<i64> {
        self.streams
            .iter()
            .filter(|s| {
                s.last_seen_s
                    .is_some_and(|t| now_s - t <= self.config.silent_after_s)
            })
            .filter_map(|s| s.last.map(|(_, _, end)| end))
            .min()
    }

    /// Releases what waited long enough, judges up to the watermark, and returns the events
    /// whose window's data are in.
    pub fn tick(&mut self, now_s: f64) -> Vec<Pending> {
        for i in 0..self.streams.len() {
            self.release(i, now_s);
        }
        let Some(watermark) = self.watermark_ns(now_s) else {
            return self.due(now_s, None);
        };
        for event in self.detector.advance(watermark) {
            let c = &self.config;
            self.pending.push(Pending {
                window_start_ns: event.start_ns - (c.pre_event_s * 1e9) as i64,
                window_end_ns: event.end_ns + (c.post_event_s * 1e9) as i64,
                event,
                closed_at_s: now_s,
            });
        }
        self.due(now_s, Some(watermark))
    }

    fn due(&mut self, now_s: f64, watermark: Option<i64>) -> Vec<Pending> {
        let wait = self.config.post_event_s + self.config.hole_wait_s;
        let (ready, waiting): (Vec<_>, Vec<_>) = self.pending.drain(..).partition(|p| {
            watermark.is_some_and(|w| w >= p.window_end_ns) || now_s - p.closed_at_s >= wait
        });
        self.pending = waiting;
        ready
    }

    /// Where each sensor's follower should resume after a restart so that the detector sees
    /// again everything it needs for events not yet reported: the last released batch before
    /// the earliest open or pending event's window (or before the watermark), less the LTA's
    /// warm-up.
    pub fn resume_positions(&self, now_s: f64) -> BTreeMap<SensorId, Position> {
        let c = &self.config;
        let lead = ((c.detector.lta_s + c.pre_event_s + 5.0) * 1e9) as i64;
        let mut from = self.watermark_ns(now_s).unwrap_or(i64::MAX);
        if let Some(open) = self.detector.open_since_ns() {
            from = from.min(open);
        }
        for p in &self.pending {
            from = from.min(p.event.start_ns);
        }
        let from = from.saturating_sub(lead);
        let mut out = BTreeMap::new();
        for (id, s) in self.sensors.iter().zip(&self.streams) {
            if let Some(p) = s.positions.iter().rev().find(|p| p.timestamp_ns <= from) {
                out.insert(id.clone(), *p);
            } else if let Some(p) = s.positions.front() {
                out.insert(id.clone(), *p);
            }
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use triax_protocol::batch::{BatchHeader, CorrectedSample, CorrectionInfo, Mode};

    fn batch(sensor: &str, seq: u64, t0_s: f64, amplitude: f64) -> CorrectedBatch {
        let samples = (0..100)
            .map(|i| {
                let t = t0_s + i as f64 * 0.01;
                // Deterministic "noise" and a 2 Hz sway.
                let n = 0.01 * ((t * 1234.567).sin());
                let sway = amplitude * (2.0 * std::f64::consts::PI * 2.0 * t).sin();
                CorrectedSample {
                    accel_mps2: [(sway + n) as f32, n as f32, (9.81 + n) as f32],
                    uncertainty_mps2: [0.01; 3],
                    flags: 0,
                }
            })
            .collect();
        CorrectedBatch {
            header: BatchHeader {
                sensor_id: SensorId::new(sensor).unwrap(),
                sequence: seq,
                timestamp_ns: (t0_s * 1e9) as i64,
                sample_rate_hz: 100.0,
            },
            info: CorrectionInfo {
                calibration_version: 1,
                mode: Mode::Dynamic,
                coverage_factor: 2.0,
            },
            batch_flags: 0,
            samples,
        }
    }

    fn config() -> Arc<BuildingConfig> {
        let text = "[buildings.b]\n[[buildings.b.sensors]]\nsensor_id = \"a\"\nfloor = 0\nheight_m = 0.0\n\
            mounting = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]\n\
            [[buildings.b.sensors]]\nsensor_id = \"b\"\nfloor = 1\nheight_m = 3.0\n\
            mounting = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]\n";
        let c = crate::config::Config::from_toml(text).unwrap();
        Arc::new(c.buildings.values().next().unwrap().clone())
    }

    #[test]
    fn a_hole_waits_then_fills_in_order_and_the_event_is_one() {
        let mut b = Building::new(BuildingId::new("b").unwrap(), config());
        let shaking = |t: f64| if (60.0..80.0).contains(&t) { 0.5 } else { 0.0 };
        let mut ready = Vec::new();
        // Seconds 0–120 of both sensors, one second a batch; batches 65–75 of sensor a arrive
        // late (after 76–120), as a gateway's backfill sends them.
        let mut now = 0.0;
        for s in 0..120u64 {
            let t = s as f64;
            b.on_batch(batch("b", s, t, shaking(t)), now);
            if !(65..=75).contains(&s) {
                b.on_batch(batch("a", s, t, shaking(t)), now);
            }
            now += 0.05;
            ready.extend(b.tick(now));
        }
        // Sensor a is held at the hole: no event can close past it yet.
        assert!(ready.is_empty(), "{ready:?}");
        for s in 65..=75u64 {
            b.on_batch(batch("a", s, s as f64, shaking(s as f64)), now);
        }
        ready.extend(b.tick(now + 0.1));
        assert_eq!(ready.len(), 1, "{ready:?}");
        let e = &ready[0].event;
        assert!(((e.start_ns as f64) * 1e-9 - 60.0).abs() < 0.5);
        assert!(((e.end_ns as f64) * 1e-9 - 80.0) < 2.0);
        assert_eq!(e.sensors, vec![0, 1]);
        // A restart resumes before the LTA's warm-up of what is not yet judged.
        let resume = b.resume_positions(now);
        assert_eq!(resume.len(), 2);
    }

    #[test]
    fn a_hole_never_filled_is_crossed_after_the_wait() {
        let mut b = Building::new(BuildingId::new("b").unwrap(), config());
        let mut now = 0.0;
        let mut ready = Vec::new();
        for s in 0..150u64 {
            let t = s as f64;
            let amp = if (60.0..90.0).contains(&t) { 0.5 } else { 0.0 };
            // Both streams lose seconds 70–79 for good (a gateway down, nodes without buffers).
            if !(70..80).contains(&s) {
                b.on_batch(batch("a", s, t, amp), now);
                b.on_batch(batch("b", s, t, amp), now);
            }
            now += 1.0;
            ready.extend(b.tick(now));
        }
        assert_eq!(ready.len(), 1, "{ready:?}");
        let end = ready[0].event.end_ns as f64 * 1e-9;
        assert!((89.0..93.0).contains(&end), "{end}");
    }
}
