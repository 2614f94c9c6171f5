//! Decimation of one sensor's corrected stream for a plot.
//!
//! A browser cannot draw, nor a link carry, every sample of a hundred sensors at 100 Hz; nor
//! does a plot need them: a pixel column shows at most the span of the values that fall in it.
//! So the console cuts time into buckets of `bucket_ns` (about one pixel column), aligned on
//! multiples of `bucket_ns` since the Unix epoch so that a bucket sent twice is the same bucket,
//! and keeps per bucket and axis:
//!
//! - the smallest and largest corrected value (the min/max envelope: a spike in one sample is
//!   still drawn);
//! - the band edges, min(a − k·u) and max(a + k·u), k being the batch's coverage factor;
//! - the union of the samples' flags, so a flagged sample stays visible at any zoom;
//! - whether the stream broke just before the bucket (a gap), so that the plot does not draw a
//!   line across it.
//!
//! A gap is a jump in sequence numbers, a batch the gateway flagged `sequence_gap`, or a time
//! jump (a batch starting more than 1.5 sample periods after the previous one ended); a batch
//! starting before the previous one ended is a restart of the node's clock. Duplicates
//! (`duplicate`) are drawn but do not move the stream's position.
//!
//! Memory is bounded by the number of buckets ([`MAX_BUCKETS`]), whatever the number of
//! samples pushed: the same code serves a live window and an hour read from the history.

use std::collections::BTreeSet;

use serde::ser::{Serialize, SerializeSeq, Serializer};
use triax_protocol::batch::{flags, CorrectedBatch, Mode};

/// Most buckets in one aggregation (a wide screen's pixel columns).
pub const MAX_BUCKETS: usize = 4096;

/// Why the stream broke.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum GapCause {
    /// Batches missing by sequence number (or flagged `sequence_gap` by the gateway).
    Sequence,
    /// No samples for longer than the sample period allows.
    Time,
    /// The node's clock went back: it restarted.
    Restart,
}

/// A break in the stream, from the end of the last batch before it to the start of the next.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
pub struct Gap {
    pub start_ns: i64,
    pub end_ns: i64,
    pub cause: GapCause,
}

/// One bucket's summary. Axis values are NaN where no finite value fell in the bucket
/// (serialised as `null`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Bucket {
    /// `floor(t_ns / bucket_ns)` of the samples in it.
    pub index: i64,
    pub samples: u32,
    pub flags: u16,
    /// The stream broke just before this bucket's first sample.
    pub gap_before: bool,
    pub min_mps2: [f32; 3],
    pub max_mps2: [f32; 3],
    /// min(a − k·u) and max(a + k·u) per axis; NaN when uncalibrated.
    pub band_lo_mps2: [f32; 3],
    pub band_hi_mps2: [f32; 3],
}

impl Bucket {
    fn empty(index: i64) -> Bucket {
        Bucket {
            index,
            samples: 0,
            flags: 0,
            gap_before: false,
            min_mps2: [f32::INFINITY; 3],
            max_mps2: [f32::NEG_INFINITY; 3],
            band_lo_mps2: [f32::INFINITY; 3],
            band_hi_mps2: [f32::NEG_INFINITY; 3],
        }
    }

    fn finite_or_nan(x: f32) -> f32 {
        if x.is_finite() {
            x
        } else {
            f32::NAN
        }
    }
}

/// A bucket is sent as one flat array, the smallest form a browser parses quickly:
/// `[index, samples, flags, gap_before (0|1), x_min, x_max, y_min, y_max, z_min, z_max,
/// x_lo, x_hi, y_lo, y_hi, z_lo, z_hi]`, with `null` for a missing value.
impl Serialize for Bucket {
    fn serialize<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        let mut seq = s.serialize_seq(Some(16))?;
        seq.serialize_element(&self.index)?;
        seq.serialize_element(&self.samples)?;
        seq.serialize_element(&self.flags)?;
        seq.serialize_element(&u8::from(self.gap_before))?;
        for axis in 0..3 {
            seq.serialize_element(&Bucket::finite_or_nan(self.min_mps2[axis]))?;
            seq.serialize_element(&Bucket::finite_or_nan(self.max_mps2[axis]))?;
        }
        for axis in 0..3 {
            seq.serialize_element(&Bucket::finite_or_nan(self.band_lo_mps2[axis]))?;
            seq.serialize_element(&Bucket::finite_or_nan(self.band_hi_mps2[axis]))?;
        }
        seq.end()
    }
}

/// What the last batch said about the correction.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct Correction {
    pub mode: Mode,
    pub calibration_version: u64,
    pub coverage_factor: f32,
    pub sample_rate_hz: f64,
}

/// The decimated view of a time range, ready to send.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct View {
    pub bucket_ns: i64,
    pub from_ns: i64,
    pub to_ns: i64,
    /// Buckets holding at least one sample, in index order.
    pub buckets: Vec<Bucket>,
    pub gaps: Vec<Gap>,
    /// Batches that had at least one sample in the range.
    pub batches: u64,
    /// Calibration versions of those batches (more than one: a recalibration in the range).
    pub calibration_versions: Vec<u64>,
    /// The correction of the last batch pushed, if any.
    pub correction: Option<Correction>,
    /// End of the last sample pushed (its time plus one period), ns.
    pub end_ns: Option<i64>,
}

#[derive(Debug, Clone, Copy)]
struct Position {
    sequence: u64,
    end_ns: i64,
    period_ns: f64,
}

/// Folds batches, in the order the gateway published them, into buckets over `[from_ns,
/// to_ns)`. Batches before the range still count for gap detection.
#[derive(Debug)]
pub struct Aggregator {
    bucket_ns: i64,
    from_ns: i64,
    to_ns: i64,
    first_index: i64,
    slots: Vec<Bucket>,
    prev: Option<Position>,
    gaps: Vec<Gap>,
    batches: u64,
    versions: BTreeSet<u64>,
    correction: Option<Correction>,
    end_ns: Option<i64>,
}

/// Why an aggregation was refused.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum RangeError {
    #[error("the range is empty: from {from_ns} is not before to {to_ns}")]
    Empty { from_ns: i64, to_ns: i64 },
    #[error("bucket width {bucket_ns} ns is not positive")]
    BucketWidth { bucket_ns: i64 },
    #[error("the range needs {needed} buckets; at most {MAX_BUCKETS}")]
    TooManyBuckets { needed: i64 },
}

impl Aggregator {
    pub fn new(from_ns: i64, to_ns: i64, bucket_ns: i64) -> Result<Aggregator, RangeError> {
        if from_ns >= to_ns {
            return Err(RangeError::Empty { from_ns, to_ns });
        }
        if bucket_ns <= 0 {
            return Err(RangeError::BucketWidth { bucket_ns });
        }
        let first_index = from_ns.div_euclid(bucket_ns);
        let last_index = (to_ns - 1).div_euclid(bucket_ns);
        let needed = last_index - first_index + 1;
        if needed > MAX_BUCKETS as i64 {
            return Err(RangeError::TooManyBuckets { needed });
        }
        Ok(Aggregator {
            bucket_ns,
            from_ns,
            to_ns,
            first_index,
            slots: (first_index..=last_index).map(Bucket::empty).collect(),
            prev: None,
            gaps: Vec::new(),
            batches: 0,
            versions: BTreeSet::new(),
            correction: None,
            end_ns: None,
        })
    }

    fn slot(&mut self, t_ns: i64) -> Option<&mut Bucket> {
        if t_ns < self.from_ns || t_ns >= self.to_ns {
            return None;
        }
        let i = t_ns.div_euclid(self.bucket_ns) - self.first_index;
        self.slots.get_mut(usize::try_from(i).ok()?)
    }

    /// A late batch over `[start_ns, end_ns)`: a sequence gap it starts (within half a period)
    /// now starts after it; one it fills whole is gone.
    fn fill_gap(&mut self, start_ns: i64, end_ns: i64, period_ns: f64) {
        for g in &mut self.gaps {
            let starts_it = (start_ns as f64) <= g.start_ns as f64 + 0.5 * period_ns;
            if g.cause == GapCause::Sequence && starts_it && end_ns > g.start_ns {
                g.start_ns = end_ns.min(g.end_ns);
            }
        }
        self.gaps
            .retain(|g| g.cause != GapCause::Sequence || g.start_ns < g.end_ns);
    }

    /// Adds one batch: samples inside the range go into their buckets; every batch but a
    /// duplicate or a late one moves the stream's position, which is what gaps are judged
    /// against.
    pub fn push(&mut self, batch: &CorrectedBatch) {
        let h = &batch.header;
        let period_ns = 1e9 / h.sample_rate_hz;
        let n = batch.samples.len();
        let start_ns = h.timestamp_ns;
        let end_ns = start_ns.saturating_add((n as f64 * period_ns) as i64);
        let duplicate = batch.batch_flags & flags::DUPLICATE != 0;
        // A hole the gateway filled from the node's buffer, after later batches: it goes where
        // its time says and closes what it fills of a gap; it is not the stream's position.
        let late = batch.batch_flags & flags::LATE != 0;
        let gap = match (self.prev, duplicate || late) {
            (_, true) => None,
            (Some(p), false) => {
                let slack_ns = 1.5 * p.period_ns.max(period_ns);
                if (start_ns as f64) < p.end_ns as f64 - 0.5 * p.period_ns {
                    Some((p.end_ns.min(start_ns), GapCause::Restart))
                } else if h.sequence > p.sequence.saturating_add(1)
                    || batch.batch_flags & flags::SEQUENCE_GAP != 0
                {
                    Some((p.end_ns, GapCause::Sequence))
                } else if (start_ns - p.end_ns) as f64 > slack_ns {
                    Some((p.end_ns, GapCause::Time))
                } else {
                    None
                }
            }
            // Nothing before it in view: the gap starts before the range.
            (None, false) if batch.batch_flags & flags::SEQUENCE_GAP != 0 => {
                Some((start_ns, GapCause::Sequence))
            }
            (None, false) => None,
        };
        if late {
            self.fill_gap(start_ns, end_ns, period_ns);
        } else if !duplicate {
            self.prev = Some(Position {
                sequence: h.sequence,
                end_ns,
                period_ns,
            });
        }
        if end_ns <= self.from_ns || start_ns >= self.to_ns {
            return;
        }
        if let Some((gap_start, cause)) = gap {
            let (s, e) = (gap_start.max(self.from_ns), start_ns.min(self.to_ns));
            if s < e || cause == GapCause::Restart {
                self.gaps.push(Gap {
                    start_ns: s,
                    end_ns: e.max(s),
                    cause,
                });
            }
            if let Some(b) = self.slot(start_ns) {
                b.gap_before = true;
            }
        }
        let k = batch.info.coverage_factor;
        let batch_only = batch.batch_flags & (flags::DUPLICATE | flags::SEQUENCE_GAP);
        let mut in_range = false;
        for (i, s) in batch.samples.iter().enumerate() {
            let t = start_ns.saturating_add((i as f64 * period_ns) as i64);
            let Some(b) = self.slot(t) else { continue };
            in_range = true;
            b.samples += 1;
            b.flags |= s.flags | (batch_only & if i == 0 { !0 } else { flags::DUPLICATE });
            for axis in 0..3 {
                let a = s.accel_mps2[axis];
                if !a.is_finite() {
                    continue;
                }
                b.min_mps2[axis] = b.min_mps2[axis].min(a);
                b.max_mps2[axis] = b.max_mps2[axis].max(a);
                let half = k * s.uncertainty_mps2[axis];
                if half.is_finite() {
                    b.band_lo_mps2[axis] = b.band_lo_mps2[axis].min(a - half);
                    b.band_hi_mps2[axis] = b.band_hi_mps2[axis].max(a + half);
                }
            }
        }
        if in_range {
            self.batches += 1;
            self.versions.insert(batch.info.calibration_version);
            self.correction = Some(Correction {
                mode: batch.info.mode,
                calibration_version: batch.info.calibration_version,
                coverage_factor: k,
                sample_rate_hz: h.sample_rate_hz,
            });
            self.end_ns = Some(self.end_ns.map_or(end_ns, |e| e.max(end_ns)));
        }
    }

    pub fn finish(self) -> View {
        View {
            bucket_ns: self.bucket_ns,
            from_ns: self.from_ns,
            to_ns: self.to_ns,
            buckets: self.slots.into_iter().filter(|b| b.samples > 0).collect(),
            gaps: self.gaps,
            batches: self.batches,
            calibration_versions: self.versions.into_iter().collect(),
            correction: self.correction,
            end_ns: self.end_ns,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use triax_protocol::batch::{BatchHeader, CorrectedSample, CorrectionInfo};
    use triax_protocol::SensorId;

    const T0: i64 = 1_800_000_000_000_000_000;
    const MS: i64 = 1_000_000;

    /// A 100 Hz batch of `n` samples, sample i of axis x = `x(i)`, u = 0.01, k = 2.
    fn batch(seq: u64, start_ns: i64, n: usize, x: impl Fn(usize) -> f32) -> CorrectedBatch {
        CorrectedBatch {
            header: BatchHeader {
                sensor_id: SensorId::new("s").unwrap(),
                sequence: seq,
                timestamp_ns: start_ns,
                sample_rate_hz: 100.0,
            },
            batch_flags: 0,
            info: CorrectionInfo {
                calibration_version: 3,
                mode: Mode::Dynamic,
                coverage_factor: 2.0,
            },
            samples: (0..n)
                .map(|i| CorrectedSample {
                    accel_mps2: [x(i), 1.0, 9.8],
                    uncertainty_mps2: [0.01, 0.02, 0.03],
                    flags: 0,
                })
                .collect(),
        }
    }

    #[test]
    fn envelope_and_band_per_bucket_by_hand() {
        // 10 samples at 10 ms, buckets of 40 ms: samples 0-3, 4-7, 8-9.
        let b = batch(0, T0, 10, |i| i as f32);
        let mut a = Aggregator::new(T0, T0 + 100 * MS, 40 * MS).unwrap();
        a.push(&b);
        let v = a.finish();
        assert_eq!(v.buckets.len(), 3);
        let first = v.buckets[0];
        assert_eq!(first.index, T0 / (40 * MS));
        assert_eq!(first.samples, 4);
        assert_eq!((first.min_mps2[0], first.max_mps2[0]), (0.0, 3.0));
        assert_eq!(
            (first.band_lo_mps2[0], first.band_hi_mps2[0]),
            (-0.02, 3.02)
        );
        assert_eq!(
            (first.band_lo_mps2[2], first.band_hi_mps2[2]),
            (9.8 - 0.06, 9.8 + 0.06)
        );
        assert_eq!(v.buckets[2].samples, 2);
        assert_eq!(v.buckets[2].max_mps2[0], 9.0);
        assert!(v.gaps.is_empty());
        assert_eq!(v.batches, 1);
        assert_eq!(v.end_ns, Some(T0 + 100 * MS));
    }

    #[test]
    fn a_spike_survives_decimation() {
        // 1000 samples into 10 buckets: one sample of 50 among zeros.
        let b = batch(0, T0, 1000, |i| if i == 537 { 50.0 } else { 0.0 });
        let mut a = Aggregator::new(T0, T0 + 10_000 * MS, 1000 * MS).unwrap();
        a.push(&b);
        let v = a.finish();
        assert_eq!(v.buckets.len(), 10);
        let maxes: Vec<f32> = v.buckets.iter().map(|b| b.max_mps2[0]).collect();
        assert_eq!(maxes[5], 50.0, "{maxes:?}");
        assert_eq!(maxes.iter().filter(|&&m| m == 0.0).count(), 9);
    }

    #[test]
    fn late_batches_fill_their_gap_where_their_time_says() {
        // Batches of 50 samples (0.5 s); 1 and 2 are lost, then come late, after 3.
        let mut a = Aggregator::new(T0, T0 + 2_000 * MS, 100 * MS).unwrap();
        a.push(&batch(0, T0, 50, |_| 0.0));
        let mut after = batch(3, T0 + 1500 * MS, 50, |_| 0.0);
        after.batch_flags = flags::SEQUENCE_GAP;
        a.push(&after);
        let mut late = batch(1, T0 + 500 * MS, 50, |_| 1.0);
        late.batch_flags = flags::LATE;
        a.push(&late);
        assert_eq!(a.gaps.len(), 1, "{:?}", a.gaps);
        assert_eq!(
            a.gaps[0].start_ns,
            T0 + 1000 * MS,
            "the gap now starts after 1"
        );
        late = batch(2, T0 + 1000 * MS, 50, |_| 2.0);
        late.batch_flags = flags::LATE;
        a.push(&late);
        let v = a.finish();
        assert!(v.gaps.is_empty(), "{:?}", v.gaps);
        assert_eq!(v.buckets.len(), 20);
        assert_eq!(v.buckets[7].max_mps2[0], 1.0);
        assert_eq!(v.buckets[12].max_mps2[0], 2.0);
    }

    #[test]
    fn sequence_and_time_gaps_break_the_line() {
        // Batches of 50 samples (0.5 s). Seq 2 is lost; seq 4 comes 1 s late.
        let mut a = Aggregator::new(T0, T0 + 5_000 * MS, 100 * MS).unwrap();
        a.push(&batch(0, T0, 50, |_| 0.0));
        a.push(&batch(1, T0 + 500 * MS, 50, |_| 0.0));
        a.push(&batch(3, T0 + 1500 * MS, 50, |_| 0.0));
        a.push(&batch(4, T0 + 3000 * MS, 50, |_| 0.0));
        let v = a.finish();
        assert_eq!(
            v.gaps,
            [
                Gap {
                    start_ns: T0 + 1000 * MS,
                    end_ns: T0 + 1500 * MS,
                    cause: GapCause::Sequence
                },
                Gap {
                    start_ns: T0 + 2000 * MS,
                    end_ns: T0 + 3000 * MS,
                    cause: GapCause::Time
                }
            ]
        );
        let gap_at: Vec<i64> = v
            .buckets
            .iter()
            .filter(|b| b.gap_before)
            .map(|b| b.index * 100 * MS - T0)
            .collect();
        assert_eq!(gap_at, [1500 * MS, 3000 * MS]);
        // No bucket in the holes.
        assert_eq!(v.buckets.len(), 5 * 4);
    }

    #[test]
    fn the_gateways_gap_flag_counts_even_at_the_start_of_the_range() {
        let mut b = batch(7, T0, 50, |_| 0.0);
        b.batch_flags = flags::SEQUENCE_GAP;
        let mut a = Aggregator::new(T0, T0 + 1_000 * MS, 100 * MS).unwrap();
        a.push(&b);
        let v = a.finish();
        assert!(v.buckets[0].gap_before);
        assert_eq!(
            v.buckets[0].flags,
            flags::SEQUENCE_GAP,
            "on the first bucket only"
        );
        assert_eq!(v.buckets[1].flags, 0);
    }

    #[test]
    fn duplicates_and_restarts() {
        let mut a = Aggregator::new(T0, T0 + 3_000 * MS, 100 * MS).unwrap();
        a.push(&batch(0, T0, 50, |_| 0.0));
        let mut dup = batch(0, T0, 50, |_| 0.0);
        dup.batch_flags = flags::DUPLICATE;
        a.push(&dup);
        a.push(&batch(1, T0 + 500 * MS, 50, |_| 0.0));
        // The node restarts: sequence 0 again, clock back at T0 + 200 ms.
        a.push(&batch(0, T0 + 200 * MS, 50, |_| 0.0));
        let v = a.finish();
        assert_eq!(v.gaps.len(), 1, "{:?}", v.gaps);
        assert_eq!(v.gaps[0].cause, GapCause::Restart);
        assert!(v
            .buckets
            .iter()
            .take(5)
            .all(|b| b.flags & flags::DUPLICATE != 0));
    }

    #[test]
    fn uncalibrated_and_non_finite_values_have_no_band() {
        let mut b = batch(0, T0, 4, |i| if i == 1 { f32::NAN } else { 2.0 });
        for s in &mut b.samples {
            s.uncertainty_mps2 = [f32::NAN; 3];
            s.flags = flags::UNCALIBRATED;
        }
        b.info.mode = Mode::None;
        let mut a = Aggregator::new(T0, T0 + 40 * MS, 40 * MS).unwrap();
        a.push(&b);
        let v = a.finish();
        let json = serde_json::to_string(&v.buckets).unwrap();
        let idx = T0 / (40 * MS);
        assert_eq!(
            json,
            format!("[[{idx},4,1,0,2.0,2.0,1.0,1.0,9.8,9.8,null,null,null,null,null,null]]")
        );
    }

    #[test]
    fn samples_outside_the_range_are_left_out_and_ranges_are_checked() {
        let mut a = Aggregator::new(T0 + 100 * MS, T0 + 200 * MS, 50 * MS).unwrap();
        a.push(&batch(0, T0, 50, |i| i as f32));
        let v = a.finish();
        assert_eq!(v.buckets.iter().map(|b| b.samples).sum::<u32>(), 10);
        assert_eq!(v.buckets[0].min_mps2[0], 10.0);
        assert!(matches!(
            Aggregator::new(5, 5, 1),
            Err(RangeError::Empty { .. })
        ));
        assert!(matches!(
            Aggregator::new(0, 10, 0),
            Err(RangeError::BucketWidth { .. })
        ));
        assert!(matches!(
            Aggregator::new(0, 1_000_000, 10),
            Err(RangeError::TooManyBuckets { .. })
        ));
    }
}
