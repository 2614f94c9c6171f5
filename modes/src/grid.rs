//! Corrected batches gathered into windows on one time grid per window.
//!
//! Windows start at multiples of the window length since the Unix epoch, by the sensors'
//! clocks (the batches' `timestamp_ns`). The first batch that reaches a window fixes its grid:
//! its sample rate, and its samples' phase within a sample period, so that the grid's first
//! point is the first instant at or after the window's start in that phase. Sample `i` of a
//! batch is at `timestamp_ns + i / sample_rate_hz`; it is put on the grid point nearest to it
//! when it lies within `alignment_tolerance` of a period of that point. Nothing is
//! interpolated or resampled: a sample further off (a node whose clock ticks in another phase,
//! or at another rate) is left out and counted `misaligned`, and a grid point no sample reached
//! is `missing`. A sample with a quality flag (its own, or the batch-only flags on the batch's
//! first sample: `CorrectedBatch::sample_flags`) other than those of [`USABLE_FLAGS`], or a
//! non-finite value, is `flagged`. All three are invalid for identification, which leaves them
//! out of every correlation. A sample flagged `calibration_suspect` (and nothing else that
//! matters) is used and counted apart: the field health checks doubt its gain, and a gain
//! error scales a channel, which moves its shape components but no frequency or damping.
//!
//! A window closes when every sensor of the model has delivered a sample at or past its last
//! grid point, or `close_after_s` of the service's own time (not the sensors') after the first
//! sensor passed its end: the others' silence is then a gap. Waiting by the service's clock
//! rather than by how far the first sensor has run is what lets a restart work: the follower
//! reads each sensor's missed stretch from the history in turn, so one sensor may run hours
//! ahead of the others for a few seconds. At most [`MAX_PENDING_WINDOWS`] wait; beyond, the
//! oldest closes as it is. Batches of a window already closed are dropped and counted.

use std::collections::{BTreeMap, BTreeSet};

use triax_client::follow::Position;
use triax_modal::{BuildingModel, ChainUncertainty, SensorSeries, Window};
use triax_protocol::batch::flags;
use triax_protocol::messages::ModalSensorCoverage;
use triax_protocol::{CorrectedBatch, SensorId};

const NS_PER_S: f64 = 1e9;

/// Windows open at once: a day of 30-minute windows (14 MB each for six sensors at 100 Hz).
pub const MAX_PENDING_WINDOWS: usize = 48;

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[repr(u8)]
enum Point {
    Missing = 0,
    Valid,
    /// Valid, its sample flagged `calibration_suspect` alone.
    Suspect,
    Flagged,
    Misaligned,
}

/// Flags that leave a sample usable for identification: a suspect gain moves no frequency or
/// damping (and the shapes of its sensor say so); a batch fetched late, or one after lost
/// batches, carries samples as good as any (the lost ones are `missing`).
pub const USABLE_FLAGS: u16 = flags::CALIBRATION_SUSPECT | flags::LATE | flags::SEQUENCE_GAP;

#[derive(Debug, Clone)]
struct SensorBuffer {
    acceleration_mps2: Vec<[f32; 3]>,
    points: Vec<Point>,
    calibration_versions: BTreeSet<u64>,
}

/// A window being filled.
#[derive(Debug, Clone)]
struct Pending {
    /// The grid's first point after the window's nominal start, ns (times are kept relative to
    /// the start: an f64 of ns since the epoch is only good to 256 ns).
    start_offset_ns: f64,
    rate_hz: f64,
    period_ns: f64,
    len: usize,
    sensors: Vec<SensorBuffer>,
    late: bool,
    /// When (the service's clock, s) a sensor first passed the window's end.
    first_past_s: Option<f64>,
}

/// A window ready for identification, with what each sensor gave it.
#[derive(Debug, Clone)]
pub struct ClosedWindow {
    /// Index of the window (its nominal start over the window length).
    pub index: i64,
    pub window: Window,
    pub coverage: Vec<ModalSensorCoverage>,
    pub end_ns: i64,
    /// Some of its batches were read back from the history.
    pub late: bool,
    /// Where each sensor's stream resumes once this window (and every earlier one) is
    /// identified: the [`Gatherer::positions`] as this window closed. The gatherer moves on
    /// while the window is identified, so the state saved after it must not take later ones.
    pub resume: BTreeMap<SensorId, Position>,
}

/// Gathers one building's batches into windows.
#[derive(Debug, Clone)]
pub struct Gatherer {
    sensors: Vec<SensorId>,
    window_ns: i64,
    tolerance: f64,
    close_after_s: f64,
    chain: ChainUncertainty,
    pending: BTreeMap<i64, Pending>,
    /// Windows below this index are closed.
    next_index: i64,
    /// Per sensor: the time of its newest sample.
    newest_ns: Vec<Option<i64>>,
    /// Per sensor: the last batch wholly inside a closed window (where a restart resumes), and
    /// per open window the last batch that ends in it.
    resume: Vec<Option<Position>>,
    ends_in: Vec<BTreeMap<i64, Position>>,
    /// Batches that came after their window closed, and batches of sensors not in the model.
    pub dropped_late: u64,
    pub dropped_unknown: u64,
}

impl Gatherer {
    /// `chain` is every sensor's, the placement on the grid included.
    pub fn new(
        model: &BuildingModel,
        window_s: f64,
        alignment_tolerance: f64,
        close_after_s: f64,
        chain: ChainUncertainty,
    ) -> Gatherer {
        let sensors: Vec<SensorId> = model
            .sensors
            .iter()
            // The configuration checked every id.
            .filter_map(|s| SensorId::new(s.sensor_id.clone()).ok())
            .collect();
        let n = sensors.len();
        Gatherer {
            sensors,
            window_ns: (window_s * NS_PER_S).round() as i64,
            tolerance: alignment_tolerance,
            close_after_s,
            chain,
            pending: BTreeMap::new(),
            next_index: i64::MIN,
            newest_ns: vec![None; n],
            resume: vec![None; n],
            ends_in: vec![BTreeMap::new(); n],
            dropped_late: 0,
            dropped_unknown: 0,
        }
    }

    /// Resumes after a restart: windows below `next_index` were identified before it.
    pub fn resume_from(&mut self, next_index: i64, positions: &BTreeMap<SensorId, Position>) {
        self.next_index = next_index;
        for (i, s) in self.sensors.iter().enumerate() {
            self.resume[i] = positions.get(s).copied();
        }
    }

    /// Index of the first window not closed yet.
    pub fn next_index(&self) -> i64 {
        self.next_index
    }

    /// Start of a window, ns.
    pub fn window_start_ns(&self, index: i64) -> i64 {
        index.saturating_mul(self.window_ns)
    }

    /// Where each sensor's stream is to be resumed: after the last batch wholly inside a
    /// closed window.
    pub fn positions(&self) -> BTreeMap<SensorId, Position> {
        self.sensors
            .iter()
            .zip(&self.resume)
            .filter_map(|(s, p)| p.map(|p| (s.clone(), p)))
            .collect()
    }

    /// Takes one batch, at `now_s` by the service's clock (any monotonic origin); returns the
    /// windows it closed, oldest first.
    pub fn add(
        &mut self,
        batch: &CorrectedBatch,
        recovered: bool,
        now_s: f64,
    ) -> Vec<ClosedWindow> {
        let Some(s) = self
            .sensors
            .iter()
            .position(|id| *id == batch.header.sensor_id)
        else {
            self.dropped_unknown += 1;
            return Vec::new();
        };
        let n = batch.samples.len();
        if n == 0 {
            return Vec::new();
        }
        let rate = batch.header.sample_rate_hz;
        let ts = batch.header.timestamp_ns;
        let step_ns = NS_PER_S / rate;
        let at = |i: usize| ts.saturating_add((i as f64 * step_ns).round() as i64);
        let last_ns = at(n - 1);
        let first_index = batch.header.timestamp_ns.div_euclid(self.window_ns);
        let last_index = last_ns.div_euclid(self.window_ns);
        if self.next_index == i64::MIN {
            self.next_index = first_index;
        }
        if last_index < self.next_index {
            self.dropped_late += 1;
            return Vec::new();
        }
        let position = Position::of(batch);
        let slot = self.ends_in[s].entry(last_index).or_insert(position);
        if position.timestamp_ns >= slot.timestamp_ns {
            *slot = position;
        }
        let mut i = 0;
        while i < n {
            let t = at(i);
            let index = t.div_euclid(self.window_ns);
            let to_end_ns = (index + 1).saturating_mul(self.window_ns) - t;
            // Samples of this batch inside the window `index`.
            let count = ((to_end_ns as f64 / step_ns).ceil() as usize).clamp(1, n - i);
            if index >= self.next_index {
                self.place(s, index, batch, i, count, recovered);
            }
            i += count;
        }
        let newest = self.newest_ns[s].get_or_insert(last_ns);
        *newest = (*newest).max(last_ns);
        let window_ns = self.window_ns;
        for (&index, p) in self.pending.iter_mut() {
            if p.first_past_s.is_none() && last_ns >= (index + 1).saturating_mul(window_ns) {
                p.first_past_s = Some(now_s);
            }
        }
        self.close_ready(now_s)
    }

    /// Closes the windows whose wait for silent sensors is over.
    pub fn tick(&mut self, now_s: f64) -> Vec<ClosedWindow> {
        self.close_ready(now_s)
    }

    fn place(
        &mut self,
        s: usize,
        index: i64,
        batch: &CorrectedBatch,
        from: usize,
        count: usize,
        recovered: bool,
    ) {
        let rate = batch.header.sample_rate_hz;
        let step_ns = NS_PER_S / rate;
        let window_start = index.saturating_mul(self.window_ns);
        let t0 =
            batch.header.timestamp_ns.saturating_sub(window_start) as f64 + from as f64 * step_ns;
        let window_ns = self.window_ns as f64;
        let sensors = self.sensors.len();
        let pending = self.pending.entry(index).or_insert_with(|| {
            let phase = t0.rem_euclid(step_ns);
            let len = ((window_ns - phase) / step_ns).ceil() as usize;
            Pending {
                start_offset_ns: phase,
                rate_hz: rate,
                period_ns: step_ns,
                len,
                sensors: vec![
                    SensorBuffer {
                        acceleration_mps2: vec![[0.0; 3]; len],
                        points: vec![Point::Missing; len],
                        calibration_versions: BTreeSet::new(),
                    };
                    sensors
                ],
                late: false,
                first_past_s: None,
            }
        });
        pending.late |= recovered;
        let same_rate = (rate - pending.rate_hz).abs() <= 1e-9 * pending.rate_hz;
        let tolerance_ns = self.tolerance * pending.period_ns;
        let buffer = &mut pending.sensors[s];
        buffer
            .calibration_versions
            .insert(batch.info.calibration_version);
        for k in 0..count {
            let t = t0 + k as f64 * step_ns;
            let exact = (t - pending.start_offset_ns) / pending.period_ns;
            let m = exact.round();
            if m < 0.0 || m >= pending.len as f64 {
                continue;
            }
            let m = m as usize;
            let off_ns = (exact - m as f64).abs() * pending.period_ns;
            if !same_rate || off_ns > tolerance_ns {
                if buffer.points[m] == Point::Missing {
                    buffer.points[m] = Point::Misaligned;
                }
                continue;
            }
            let sample = &batch.samples[from + k];
            let flags = batch.sample_flags(from + k);
            let finite = sample.accel_mps2.iter().all(|v| v.is_finite());
            buffer.acceleration_mps2[m] = sample.accel_mps2;
            buffer.points[m] = if !finite || flags & !USABLE_FLAGS != 0 {
                Point::Flagged
            } else if flags & flags::CALIBRATION_SUSPECT != 0 {
                Point::Suspect
            } else {
                Point::Valid
            };
        }
    }

    /// Closes every window whose time has come.
    fn close_ready(&mut self, now_s: f64) -> Vec<ClosedWindow> {
        let mut closed = Vec::new();
        while let Some((&index, pending)) = self.pending.iter().next() {
            let start_ns = index.saturating_mul(self.window_ns);
            let last_point = pending.start_offset_ns
                + (pending.len as f64 - 1.0) * pending.period_ns
                - 0.5 * pending.period_ns;
            let all_past = self
                .newest_ns
                .iter()
                .all(|t| t.is_some_and(|t| t.saturating_sub(start_ns) as f64 >= last_point));
            let waited = pending
                .first_past_s
                .is_some_and(|t| now_s - t >= self.close_after_s);
            let too_many = self.pending.len() > MAX_PENDING_WINDOWS;
            if !(all_past || waited || too_many) {
                break;
            }
            closed.push(self.close(index));
        }
        closed
    }

    fn close(&mut self, index: i64) -> ClosedWindow {
        // Called with an index the map holds.
        let pending = self.pending.remove(&index).expect("the window is pending");
        self.next_index = index + 1;
        for (s, ends) in self.ends_in.iter_mut().enumerate() {
            let keep = ends.split_off(&(index + 1));
            if let Some((_, p)) = ends.iter().max_by_key(|(_, p)| p.timestamp_ns) {
                if self.resume[s].is_none_or(|r| p.timestamp_ns >= r.timestamp_ns) {
                    self.resume[s] = Some(*p);
                }
            }
            *ends = keep;
        }
        // The grid's placement error, uniform within the tolerance, is a time-stamp error.
        let placement_u_s = self.tolerance * pending.period_ns / NS_PER_S / 3f64.sqrt();
        let mut chain = self.chain;
        chain.timestamp_u_s = chain.timestamp_u_s.hypot(placement_u_s);
        let mut series = Vec::new();
        let mut coverage = Vec::new();
        for (id, buffer) in self.sensors.iter().zip(pending.sensors) {
            let count = |p: Point| buffer.points.iter().filter(|&&q| q == p).count() as u64;
            coverage.push(ModalSensorCoverage {
                sensor_id: id.clone(),
                samples: pending.len as u64,
                flagged: count(Point::Flagged),
                missing: count(Point::Missing),
                misaligned: count(Point::Misaligned),
                calibration_versions: buffer.calibration_versions.into_iter().collect(),
                calibration_suspect: count(Point::Suspect),
                check: None,
            });
            series.push(SensorSeries {
                sensor_id: id.to_string(),
                acceleration_mps2: buffer
                    .acceleration_mps2
                    .iter()
                    .map(|a| a.map(f64::from))
                    .collect(),
                valid: buffer
                    .points
                    .iter()
                    .map(|&p| matches!(p, Point::Valid | Point::Suspect))
                    .collect(),
                chain,
            });
        }
        ClosedWindow {
            index,
            window: Window {
                start_timestamp_ns: (index.saturating_mul(self.window_ns))
                    .saturating_add(pending.start_offset_ns.round() as i64),
                sample_rate_hz: pending.rate_hz,
                sensors: series,
            },
            coverage,
            end_ns: (index + 1).saturating_mul(self.window_ns),
            late: pending.late,
            resume: self.positions(),
        }
    }
}
