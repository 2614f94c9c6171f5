//! A day at a glance: the helicorder (drum) view of one channel, built from stored per-second
//! minima and maxima so that it stays fast.
//!
//! Each second of a sensor's stream, once whole, is kept as its minimum and maximum per axis,
//! the union of its samples' flags and its sample count ([`Second`]: 28 bytes, 2.4 MB a
//! sensor-day); a second with no sample is a gap. A helicorder of 24 hours reads from the
//! gateway's history only the seconds the cache lacks, so a second look, or one a minute later,
//! reads a minute. The cache holds at most [`MAX_CACHED_SECONDS`] seconds over all sensors
//! (8 sensor-days), the sensor looked at least recently going first.

use std::collections::{BTreeMap, HashMap, VecDeque};

use serde::Serialize;
use triax_protocol::batch::CorrectedBatch;
use triax_protocol::{BuildingId, SensorId};

pub const SECOND_NS: i64 = 1_000_000_000;
/// Longest helicorder, 24 hours.
pub const MAX_SPAN_NS: i64 = 24 * 3600 * SECOND_NS;
/// Seconds kept over all sensors.
pub const MAX_CACHED_SECONDS: usize = 8 * 86_400;
/// Values are sent as whole multiples of this, m/s² (1 µm/s²).
pub const SCALE_MPS2: f64 = 1e-6;

/// One second of one sensor.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Second {
    pub min_mps2: [f32; 3],
    pub max_mps2: [f32; 3],
    pub flags: u16,
    pub samples: u16,
}

/// Folds batches into seconds over `[from_ns, to_ns)`.
#[derive(Debug)]
pub struct SecondsBuilder {
    from_s: i64,
    to_s: i64,
    seconds: BTreeMap<i64, Second>,
}

impl SecondsBuilder {
    pub fn new(from_ns: i64, to_ns: i64) -> SecondsBuilder {
        SecondsBuilder {
            from_s: from_ns.div_euclid(SECOND_NS),
            to_s: to_ns.div_euclid(SECOND_NS),
            seconds: BTreeMap::new(),
        }
    }

    pub fn push(&mut self, batch: &CorrectedBatch) {
        let h = &batch.header;
        let period_ns = 1e9 / h.sample_rate_hz;
        for (i, s) in batch.samples.iter().enumerate() {
            let t = h.timestamp_ns.saturating_add((i as f64 * period_ns) as i64);
            let sec = t.div_euclid(SECOND_NS);
            if sec < self.from_s || sec >= self.to_s {
                continue;
            }
            if !s.accel_mps2.iter().all(|a| a.is_finite()) {
                continue;
            }
            let e = self.seconds.entry(sec).or_insert(Second {
                min_mps2: [f32::INFINITY; 3],
                max_mps2: [f32::NEG_INFINITY; 3],
                flags: 0,
                samples: 0,
            });
            for k in 0..3 {
                e.min_mps2[k] = e.min_mps2[k].min(s.accel_mps2[k]);
                e.max_mps2[k] = e.max_mps2[k].max(s.accel_mps2[k]);
            }
            e.flags |= s.flags | batch.batch_flags;
            e.samples = e.samples.saturating_add(1);
        }
    }

    pub fn finish(self) -> BTreeMap<i64, Second> {
        self.seconds
    }
}

#[derive(Debug, Default)]
struct Cached {
    seconds: BTreeMap<i64, Second>,
    /// Ranges of whole seconds read, `[from, to)`, sorted and apart.
    covered: Vec<(i64, i64)>,
}

impl Cached {
    fn missing(&self, from: i64, to: i64) -> Vec<(i64, i64)> {
        let mut out = Vec::new();
        let mut at = from;
        for &(a, b) in &self.covered {
            if b <= at {
                continue;
            }
            if a >= to {
                break;
            }
            if a > at {
                out.push((at, a));
            }
            at = at.max(b);
        }
        if at < to {
            out.push((at, to));
        }
        out
    }

    fn cover(&mut self, from: i64, to: i64) {
        if to <= from {
            return;
        }
        self.covered.push((from, to));
        self.covered.sort();
        let mut merged: Vec<(i64, i64)> = Vec::new();
        for (a, b) in self.covered.drain(..) {
            match merged.last_mut() {
                Some(last) if a <= last.1 => last.1 = last.1.max(b),
                _ => merged.push((a, b)),
            }
        }
        self.covered = merged;
    }
}

/// The per-second store of the sensors looked at.
#[derive(Debug, Default)]
pub struct SecondsCache {
    sensors: HashMap<(BuildingId, SensorId), Cached>,
    /// Least recently used first.
    order: VecDeque<(BuildingId, SensorId)>,
}

impl SecondsCache {
    fn touch(&mut self, key: &(BuildingId, SensorId)) {
        self.order.retain(|k| k != key);
        self.order.push_back(key.clone());
    }

    /// The second ranges `[from_s, to_s)` not yet read for this sensor.
    pub fn missing(
        &mut self,
        b: &BuildingId,
        s: &SensorId,
        from_s: i64,
        to_s: i64,
    ) -> Vec<(i64, i64)> {
        let key = (b.clone(), s.clone());
        self.touch(&key);
        self.sensors
            .get(&key)
            .map_or_else(|| vec![(from_s, to_s)], |c| c.missing(from_s, to_s))
    }

    /// Keeps what was read of `[from_s, to_s)`; only seconds before `whole_before_s` are
    /// marked as read (later ones may still be filling).
    pub fn store(
        &mut self,
        b: &BuildingId,
        s: &SensorId,
        from_s: i64,
        to_s: i64,
        whole_before_s: i64,
        seconds: BTreeMap<i64, Second>,
    ) {
        let key = (b.clone(), s.clone());
        let c = self.sensors.entry(key.clone()).or_default();
        let end = to_s.min(whole_before_s);
        for (k, v) in seconds {
            if k < end {
                c.seconds.insert(k, v);
            }
        }
        c.cover(from_s, end);
        self.touch(&key);
        self.bound();
    }

    fn bound(&mut self) {
        let total = |m: &HashMap<_, Cached>| m.values().map(|c| c.seconds.len()).sum::<usize>();
        while total(&self.sensors) > MAX_CACHED_SECONDS && self.order.len() > 1 {
            if let Some(oldest) = self.order.pop_front() {
                self.sensors.remove(&oldest);
            }
        }
        // One sensor alone over the bound: drop its oldest seconds, and say they are unread.
        if let Some(key) = self.order.back().cloned() {
            if let Some(c) = self.sensors.get_mut(&key) {
                while c.seconds.len() > MAX_CACHED_SECONDS {
                    if let Some((&k, _)) = c.seconds.iter().next() {
                        c.seconds.remove(&k);
                        c.covered.retain(|r| r.1 > k + 1);
                        if let Some(first) = c.covered.first_mut() {
                            first.0 = first.0.max(k + 1);
                        }
                    }
                }
            }
        }
    }

    /// The seconds kept of `[from_s, to_s)` for this sensor (what is not: a gap or unread).
    pub fn get(
        &self,
        b: &BuildingId,
        s: &SensorId,
        from_s: i64,
        to_s: i64,
    ) -> BTreeMap<i64, Second> {
        self.sensors
            .get(&(b.clone(), s.clone()))
            .map(|c| {
                c.seconds
                    .range(from_s..to_s)
                    .map(|(k, v)| (*k, *v))
                    .collect()
            })
            .unwrap_or_default()
    }

    pub fn cached_seconds(&self) -> usize {
        self.sensors.values().map(|c| c.seconds.len()).sum()
    }
}

/// A helicorder, ready to send: rows of seconds, each `[min, max]` of `a − mean` as whole
/// multiples of [`SCALE_MPS2`], null where no sample fell.
#[derive(Debug, Serialize)]
pub struct Drum {
    pub axis: &'static str,
    pub from_ns: i64,
    pub to_ns: i64,
    pub row_ns: i64,
    pub rows: usize,
    /// One column a second.
    pub column_ns: i64,
    pub columns: usize,
    /// The mean taken out (the middle of the seconds' ranges, averaged), m/s².
    pub mean_mps2: f64,
    pub scale_mps2: f64,
    /// Per row, `2 × columns` values: min and max of each second, or null.
    pub data: Vec<Vec<Option<i64>>>,
    /// Per row, `[column, flags]` of the seconds with a flag.
    pub flags: Vec<Vec<[u32; 2]>>,
    /// Seconds with no sample.
    pub gap_seconds: usize,
}

/// Lays out `seconds` of `[from_s, from_s + rows × row_s)` as a drum of one axis.
pub fn drum(
    seconds: &BTreeMap<i64, Second>,
    axis: usize,
    from_s: i64,
    rows: usize,
    row_s: i64,
) -> Drum {
    let name = ["x", "y", "z"][axis.min(2)];
    let (mut sum, mut n) = (0.0f64, 0usize);
    for s in seconds.values() {
        sum += (f64::from(s.min_mps2[axis]) + f64::from(s.max_mps2[axis])) / 2.0;
        n += 1;
    }
    let mean = if n > 0 { sum / n as f64 } else { 0.0 };
    let q = |v: f32| ((f64::from(v) - mean) / SCALE_MPS2).round() as i64;
    let mut data = Vec::with_capacity(rows);
    let mut flags = Vec::with_capacity(rows);
    let mut gaps = 0;
    for r in 0..rows as i64 {
        let mut row = Vec::with_capacity(2 * row_s as usize);
        let mut f = Vec::new();
        for c in 0..row_s {
            match seconds.get(&(from_s + r * row_s + c)) {
                Some(s) => {
                    row.push(Some(q(s.min_mps2[axis])));
                    row.push(Some(q(s.max_mps2[axis])));
                    if s.flags != 0 {
                        f.push([c as u32, u32::from(s.flags)]);
                    }
                }
                None => {
                    row.push(None);
                    row.push(None);
                    gaps += 1;
                }
            }
        }
        data.push(row);
        flags.push(f);
    }
    Drum {
        axis: name,
        from_ns: from_s * SECOND_NS,
        to_ns: (from_s + rows as i64 * row_s) * SECOND_NS,
        row_ns: row_s * SECOND_NS,
        rows,
        column_ns: SECOND_NS,
        columns: row_s as usize,
        mean_mps2: mean,
        scale_mps2: SCALE_MPS2,
        data,
        flags,
        gap_seconds: gaps,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use triax_protocol::batch::{BatchHeader, CorrectedSample, CorrectionInfo, Mode};

    fn batch(t0: i64, n: usize, value: impl Fn(i64) -> f32, flags: u16) -> CorrectedBatch {
        CorrectedBatch {
            header: BatchHeader {
                sensor_id: SensorId::new("s").unwrap(),
                sequence: 0,
                timestamp_ns: t0,
                sample_rate_hz: 100.0,
            },
            batch_flags: flags,
            info: CorrectionInfo {
                calibration_version: 1,
                mode: Mode::Dynamic,
                coverage_factor: 2.0,
            },
            samples: (0..n)
                .map(|i| {
                    let t = t0 + i as i64 * 10_000_000;
                    CorrectedSample {
                        accel_mps2: [value(t), 0.0, 9.81],
                        uncertainty_mps2: [0.001; 3],
                        flags: 0,
                    }
                })
                .collect(),
        }
    }

    #[test]
    fn seconds_hold_min_max_flags_and_gaps() {
        let t0 = 1_000 * SECOND_NS;
        let mut b = SecondsBuilder::new(t0, t0 + 10 * SECOND_NS);
        // Seconds 0-3 rising by 0.01 m/s² a sample; 5-6 flagged; 4 and 7-9 missing.
        b.push(&batch(
            t0,
            400,
            |t| ((t - t0) / 10_000_000) as f32 * 0.01,
            0,
        ));
        b.push(&batch(t0 + 5 * SECOND_NS, 200, |_| 1.0, 1 << 2));
        let secs = b.finish();
        assert_eq!(secs.len(), 6);
        assert_eq!(secs[&1001].min_mps2[0], 1.0);
        assert!((secs[&1001].max_mps2[0] - 1.99).abs() < 1e-6);
        assert_eq!(secs[&1001].samples, 100);
        assert_eq!(secs[&1005].flags, 1 << 2);
        let d = drum(&secs, 0, 1000, 2, 5);
        assert_eq!((d.rows, d.columns, d.gap_seconds), (2, 5, 4));
        assert_eq!(d.data[0][8], None, "second 4 is a gap");
        assert_eq!(d.flags[1], [[0, 4], [1, 4]]);
        // The mean of the seconds' middles, taken out: 6 seconds, (0.495 + 1.495 + 2.495 +
        // 3.495 + 1 + 1) / 6.
        let mean = (0.495 + 1.495 + 2.495 + 3.495 + 2.0) / 6.0;
        assert!((d.mean_mps2 - mean).abs() < 1e-6, "{}", d.mean_mps2);
        assert_eq!(
            d.data[0][0],
            Some(((0.0 - mean) / SCALE_MPS2).round() as i64)
        );
    }

    #[test]
    fn the_cache_reads_only_what_it_lacks() {
        let (b, s) = (BuildingId::new("hq").unwrap(), SensorId::new("a").unwrap());
        let mut c = SecondsCache::default();
        assert_eq!(c.missing(&b, &s, 0, 100), [(0, 100)]);
        c.store(&b, &s, 0, 100, 90, BTreeMap::new());
        assert_eq!(
            c.missing(&b, &s, 0, 100),
            [(90, 100)],
            "the last seconds may be filling"
        );
        c.store(&b, &s, 150, 200, 1000, BTreeMap::new());
        assert_eq!(c.missing(&b, &s, 0, 300), [(90, 150), (200, 300)]);
    }
}
