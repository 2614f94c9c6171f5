//! Trends beyond an hour: per-minute aggregates of one sensor's corrected stream.
//!
//! A day at 100 Hz is 8.6 million samples per axis, which no page should receive; the trend
//! view draws one point per minute instead. Per minute (aligned on whole minutes since the Unix
//! epoch, by the sensor's clock) and axis: the mean, the RMS about that mean (the vibration,
//! gravity and offsets left out), the peak |a − mean|, the largest k·u, and the dominant
//! frequency from the zero crossings of a − mean on the axis with the largest RMS (half the
//! crossings per second: exact for one sinusoid, a rough "main frequency" otherwise; the
//! spectrum view says more). These are computed as batches stream past, so a minute costs a
//! few operations per sample and nothing is kept but the aggregates.
//!
//! [`TrendCache`] keeps the whole minutes already computed per sensor (at most
//! [`MAX_CACHED_MINUTES`] per sensor, [`MAX_CACHED_SENSORS`] sensors), so a trend read again,
//! or extended, reads from the gateway's history only the minutes it lacks.

use std::collections::{BTreeMap, HashMap};

use serde::Serialize;
use triax_protocol::batch::CorrectedBatch;
use triax_protocol::{BuildingId, SensorId};

/// One minute, in ns.
pub const MINUTE_NS: i64 = 60_000_000_000;
/// Longest trend asked for: seven days.
pub const MAX_TREND_SPAN_NS: i64 = 7 * 86_400 * 1_000_000_000;
/// Minutes kept per sensor (seven days).
pub const MAX_CACHED_MINUTES: usize = 7 * 1440;
/// Sensors whose minutes are kept.
pub const MAX_CACHED_SENSORS: usize = 32;

/// One minute's aggregates, sent as a flat object.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Minute {
    /// Start of the minute, ns since the Unix epoch.
    pub start_ns: i64,
    pub samples: u32,
    /// Samples carrying any quality flag.
    pub flagged: u32,
    pub mean_mps2: [f32; 3],
    pub rms_mps2: [f32; 3],
    pub peak_mps2: [f32; 3],
    /// The largest expanded uncertainty k·u of the minute, per axis (NaN when uncalibrated).
    pub max_ku_mps2: [f32; 3],
    /// From the zero crossings of a − mean on the axis of largest RMS; None below two
    /// crossings.
    pub dominant_hz: Option<f32>,
}

/// Accumulates one minute: sums for mean and RMS, and the samples' deviations for the peak
/// and the crossings, taken against the minute's mean once the minute is whole.
#[derive(Debug, Default)]
struct Open {
    start_ns: i64,
    samples: u32,
    flagged: u32,
    values: [Vec<f32>; 3],
    max_ku: [f32; 3],
    first_t_ns: i64,
    last_t_ns: i64,
}

impl Open {
    fn new(start_ns: i64) -> Open {
        Open {
            start_ns,
            max_ku: [f32::NAN; 3],
            ..Open::default()
        }
    }

    fn close(self) -> Minute {
        let n = self.values[0].len().max(1) as f64;
        let mut mean = [0f32; 3];
        let mut rms = [0f32; 3];
        let mut peak = [0f32; 3];
        for axis in 0..3 {
            let v = &self.values[axis];
            let m = v.iter().map(|x| f64::from(*x)).sum::<f64>() / n;
            let var = v.iter().map(|x| (f64::from(*x) - m).powi(2)).sum::<f64>() / n;
            mean[axis] = m as f32;
            rms[axis] = var.sqrt() as f32;
            peak[axis] = v
                .iter()
                .map(|x| (f64::from(*x) - m).abs())
                .fold(0.0, f64::max) as f32;
        }
        let main = (0..3)
            .max_by(|a, b| rms[*a].total_cmp(&rms[*b]))
            .unwrap_or(0);
        let m = mean[main];
        let crossings = self.values[main]
            .windows(2)
            .filter(|w| (w[0] - m) * (w[1] - m) < 0.0)
            .count();
        let span_s = (self.last_t_ns - self.first_t_ns) as f64 / 1e9;
        let dominant_hz =
            (crossings >= 2 && span_s > 0.0).then(|| (crossings as f64 / (2.0 * span_s)) as f32);
        Minute {
            start_ns: self.start_ns,
            samples: self.samples,
            flagged: self.flagged,
            mean_mps2: mean,
            rms_mps2: rms,
            peak_mps2: peak,
            max_ku_mps2: self.max_ku,
            dominant_hz,
        }
    }
}

/// Folds batches, in the gateway's order, into whole minutes over `[from_ns, to_ns)`.
#[derive(Debug)]
pub struct TrendAggregator {
    from_ns: i64,
    to_ns: i64,
    open: Option<Open>,
    done: Vec<Minute>,
}

impl TrendAggregator {
    /// `from_ns` and `to_ns` are rounded out to whole minutes.
    pub fn new(from_ns: i64, to_ns: i64) -> TrendAggregator {
        TrendAggregator {
            from_ns: from_ns.div_euclid(MINUTE_NS) * MINUTE_NS,
            to_ns: (to_ns + MINUTE_NS - 1).div_euclid(MINUTE_NS) * MINUTE_NS,
            open: None,
            done: Vec::new(),
        }
    }

    pub fn push(&mut self, batch: &CorrectedBatch) {
        let h = &batch.header;
        let period_ns = 1e9 / h.sample_rate_hz;
        let k = batch.info.coverage_factor;
        for (i, s) in batch.samples.iter().enumerate() {
            let t = h.timestamp_ns.saturating_add((i as f64 * period_ns) as i64);
            if t < self.from_ns || t >= self.to_ns || !s.accel_mps2.iter().all(|a| a.is_finite()) {
                continue;
            }
            let start = t.div_euclid(MINUTE_NS) * MINUTE_NS;
            match &self.open {
                Some(o) if o.start_ns == start => {}
                // A batch from before the open minute (a duplicate, a restart): not this trend's.
                Some(o) if start < o.start_ns => continue,
                _ => {
                    if let Some(o) = self.open.take() {
                        self.done.push(o.close());
                    }
                    let mut o = Open::new(start);
                    o.first_t_ns = t;
                    self.open = Some(o);
                }
            }
            let Some(o) = self.open.as_mut() else {
                continue;
            };
            o.samples += 1;
            o.flagged += u32::from(s.flags != 0 || batch.batch_flags != 0);
            o.last_t_ns = t;
            for axis in 0..3 {
                o.values[axis].push(s.accel_mps2[axis]);
                let ku = k * s.uncertainty_mps2[axis];
                if ku.is_finite() && (o.max_ku[axis].is_nan() || ku > o.max_ku[axis]) {
                    o.max_ku[axis] = ku;
                }
            }
        }
    }

    /// The minutes, oldest first; `whole_before_ns`: minutes ending after it are left open
    /// (not returned), since more of them may still come.
    pub fn finish(mut self, whole_before_ns: i64) -> Vec<Minute> {
        if let Some(o) = self.open.take() {
            if o.start_ns + MINUTE_NS <= whole_before_ns {
                self.done.push(o.close());
            }
        }
        self.done
    }
}

/// Whole minutes already computed, per sensor.
#[derive(Debug, Default)]
pub struct TrendCache {
    sensors: HashMap<(BuildingId, SensorId), (u64, BTreeMap<i64, Minute>)>,
    clock: u64,
}

impl TrendCache {
    /// The cached minutes in `[from_ns, to_ns)` and the ranges missing from them, merged.
    pub fn lookup(
        &mut self,
        b: &BuildingId,
        s: &SensorId,
        from_ns: i64,
        to_ns: i64,
    ) -> (Vec<Minute>, Vec<(i64, i64)>) {
        let from = from_ns.div_euclid(MINUTE_NS) * MINUTE_NS;
        let empty = BTreeMap::new();
        self.clock += 1;
        let clock = self.clock;
        let minutes = match self.sensors.get_mut(&(b.clone(), s.clone())) {
            Some((used, m)) => {
                *used = clock;
                &*m
            }
            None => &empty,
        };
        let mut have = Vec::new();
        let mut missing: Vec<(i64, i64)> = Vec::new();
        let mut t = from;
        while t < to_ns {
            match minutes.get(&t) {
                Some(m) => have.push(*m),
                None => match missing.last_mut() {
                    Some((_, end)) if *end == t => *end = t + MINUTE_NS,
                    _ => missing.push((t, t + MINUTE_NS)),
                },
            }
            t += MINUTE_NS;
        }
        (have, missing)
    }

    /// Keeps whole minutes read; `read` are the ranges they were read over, so that a minute
    /// with no sample in them is remembered as empty too.
    pub fn store(&mut self, b: &BuildingId, s: &SensorId, minutes: &[Minute]) {
        let key = (b.clone(), s.clone());
        if !self.sensors.contains_key(&key) && self.sensors.len() >= MAX_CACHED_SENSORS {
            if let Some(oldest) = self
                .sensors
                .iter()
                .min_by_key(|(_, (used, _))| *used)
                .map(|(k, _)| k.clone())
            {
                self.sensors.remove(&oldest);
            }
        }
        let (_, cached) = self.sensors.entry(key).or_default();
        for m in minutes {
            cached.insert(m.start_ns, *m);
        }
        while cached.len() > MAX_CACHED_MINUTES {
            cached.pop_first();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use triax_protocol::batch::CorrectedSample;

    const T0: i64 = 1_800_000_000 * 1_000_000_000 / MINUTE_NS * MINUTE_NS;

    /// Two minutes at 100 Hz of a 2 Hz sine of amplitude 0.3 on x over 9.8 on z.
    fn batches() -> Vec<CorrectedBatch> {
        (0..240)
            .map(|b| {
                triax_protocol::batch::sample::dynamic(
                    SensorId::new("s").unwrap(),
                    b,
                    T0 + b as i64 * 500_000_000,
                    100.0,
                    (0..50)
                        .map(|i| {
                            let t = (b as f64 * 50.0 + i as f64) / 100.0;
                            CorrectedSample {
                                accel_mps2: [
                                    (0.3 * (2.0 * std::f64::consts::PI * 2.0 * t + 0.1).sin())
                                        as f32,
                                    0.0,
                                    9.8,
                                ],
                                uncertainty_mps2: [0.01; 3],
                                flags: u16::from(b == 0 && i == 0),
                            }
                        })
                        .collect(),
                )
            })
            .collect()
    }

    #[test]
    fn a_sine_by_the_minute() {
        let mut a = TrendAggregator::new(T0, T0 + 2 * MINUTE_NS);
        for b in batches() {
            a.push(&b);
        }
        let m = a.finish(i64::MAX);
        assert_eq!(m.len(), 2);
        assert_eq!(m[0].start_ns, T0);
        assert_eq!(m[0].samples, 6000);
        assert_eq!(m[0].flagged, 1);
        assert!((m[0].rms_mps2[0] - 0.3 / 2f32.sqrt()).abs() < 1e-3, "{m:?}");
        assert!((m[0].peak_mps2[0] - 0.3).abs() < 2e-3, "{m:?}");
        assert!((m[0].mean_mps2[2] - 9.8).abs() < 1e-5);
        assert_eq!(m[0].rms_mps2[2], 0.0);
        assert!((m[0].dominant_hz.unwrap() - 2.0).abs() < 0.02, "{m:?}");
        assert_eq!(m[0].max_ku_mps2, [0.02; 3]);
    }

    #[test]
    fn an_unfinished_minute_is_left_out_and_the_cache_knows_what_it_lacks() {
        let mut a = TrendAggregator::new(T0, T0 + 2 * MINUTE_NS);
        for b in batches().into_iter().take(150) {
            a.push(&b);
        }
        let m = a.finish(T0 + MINUTE_NS + 1);
        assert_eq!(m.len(), 1);
        let (b, s) = (BuildingId::new("hq").unwrap(), SensorId::new("s").unwrap());
        let mut cache = TrendCache::default();
        cache.store(&b, &s, &m);
        let (have, missing) = cache.lookup(&b, &s, T0, T0 + 3 * MINUTE_NS);
        assert_eq!(have, m);
        assert_eq!(missing, [(T0 + MINUTE_NS, T0 + 3 * MINUTE_NS)]);
    }
}
