//! One sensor's health monitor: raw batches in, a [`HealthReport`] out.
//!
//! The gateway hands every batch it corrects to [`SensorHealth::feed`] (the raw outputs as the
//! batch carries them, its first sample's time, its rate and its temperature) and reads
//! [`SensorHealth::report`] when it publishes health. A monitor judges one calibration record:
//! when a new record comes into force the gateway makes a new monitor, so that every verdict,
//! the relative test's baseline and a latched `suspect` belong to the record they judge.
//!
//! The stream is cut into blocks of `block_s`; a break in it (a time stamp other than the
//! previous batch's end, a new sample rate) drops the partial block and starts afresh, so no
//! statistic ever spans a gap. Duplicates are the gateway's to leave out.
//!
//! Per block, the vibration is judged from the data: the covariance of the outputs through
//! S⁻¹, less the white noise the block's own second differences show, is the vibration's
//! power (3-D). Below `quiet_vibration_mps2` the block is quiet and joins the gravity check;
//! the comparison allows five standard deviations of the power's estimate on a still sensor,
//! so that a still sensor's blocks are all quiet and a noisy one's are not mistaken for
//! motion. The channels' noise is read apart from the blocks, on segments of its own
//! ([`crate::noise`]), where the motion is not.

use triax_calibration::corrector::Corrector;
use triax_protocol::record::{CalibrationRecord, SetKind};
use triax_protocol::{RawBatchView, SensorId};

use crate::block::{BlockAccumulator, BlockSummary};
use crate::channel::{ChannelDesign, ChannelHealth};
use crate::config::{HealthConfig, HealthError};
use crate::cusum::Verdict;
use crate::gravity_check::{GravityCheck, GravityObservation, StaticModel};
use crate::noise::{FloorWindow, Segmenter, SEGMENT, WINDOW_SEGMENTS};
use crate::report::{HealthReport, Unjudged};

#[derive(Debug, Clone, Copy, PartialEq)]
struct Stream {
    sample_rate_hz: f64,
    block_len: u32,
    /// Expected time of the next batch's first sample, ns.
    next_ns: i64,
}

/// The health of one sensor under one calibration record.
///
/// Laid out as declared, what every batch touches first: a batch reads and writes a few
/// hundred bytes of a monitor's 3.3 KB, the rest is read once a block, and a caller that
/// loads a monitor ahead of a batch (the gateway, at a building's pace, where a monitor has
/// left the cache since its sensor's last batch) asks for [`SensorHealth::PER_BATCH_BYTES`]
/// from its start.
#[derive(Debug, Clone)]
#[repr(C)]
pub struct SensorHealth {
    // Every batch.
    version: u64,
    blocks: u64,
    stream: Option<Stream>,
    acc: BlockAccumulator,
    /// None when the record states no output noise (the noise test is not judged).
    segments: Option<Segmenter>,
    // A break in the stream, a block's end, a segment's end, a report.
    sensor_id: SensorId,
    block_s: f64,
    quiet_var: f64,
    spike_sigma: f64,
    windows: Option<Box<[FloorWindow; 3]>>,
    design: ChannelDesign,
    channels: [ChannelHealth; 3],
    gravity: GravityCheck,
    discontinuities: u64,
    last_observation: Option<GravityObservation>,
}

impl SensorHealth {
    /// How many bytes from a monitor's start a batch of up to a block touches: the record's
    /// version, the block count, the stream's expectation, the block's running sums and the
    /// noise segments being filled.
    pub const PER_BATCH_BYTES: usize =
        std::mem::offset_of!(SensorHealth, segments) + std::mem::size_of::<Option<Segmenter>>();

    /// A monitor for `record`, which it loads into a corrector of its own.
    pub fn new(record: &CalibrationRecord, config: &HealthConfig) -> Result<Self, HealthError> {
        let corrector = Corrector::from_record(record)?;
        Self::with_corrector(record, &corrector, config)
    }

    /// A monitor for `record` using the corrector the gateway already loaded from it.
    pub fn with_corrector(
        record: &CalibrationRecord,
        corrector: &Corrector,
        config: &HealthConfig,
    ) -> Result<Self, HealthError> {
        config.validate()?;
        if corrector.sensor_id() != &record.sensor_id || corrector.version() != record.version {
            return Err(HealthError::Mismatch {
                corrector_sensor: corrector.sensor_id().to_string(),
                corrector_version: corrector.version(),
                record_sensor: record.sensor_id.to_string(),
                record_version: record.version,
            });
        }
        // Spikes on three channels and the relative gravity test, and three relative tests a
        // pair: one budget.
        let sequential = 4 + 3 * config.colocated_pairs;
        let design = ChannelDesign::new(config, sequential);
        let noise = record.sensor.output_noise;
        let dof = record.sensor.output_noise_dof;
        let channels = [0, 1, 2].map(|j| ChannelHealth::new(&design, noise.map(|n| n[j]), dof));
        let references = [0, 1, 2].map(|j| channels[j].reference_var());
        let windows = match references {
            [Some(a), Some(b), Some(c)] => Some(Box::new([
                FloorWindow::new(a),
                FloorWindow::new(b),
                FloorWindow::new(c),
            ])),
            _ => None,
        };
        let model = StaticModel::new(record, corrector.set(SetKind::Static));
        let mut acc =
            BlockAccumulator::new(record.sensor.output_full_scale.unwrap_or(f64::INFINITY));
        acc.set_spike_thresholds(
            [0, 1, 2].map(|j| channels[j].spike_threshold(config.spike_threshold_sigma, None)),
        );
        Ok(SensorHealth {
            sensor_id: record.sensor_id.clone(),
            version: record.version,
            block_s: config.block_s,
            quiet_var: config.quiet_vibration_mps2.powi(2),
            spike_sigma: config.spike_threshold_sigma,
            design,
            channels,
            gravity: GravityCheck::new(model, config, sequential),
            acc,
            segments: windows.as_ref().map(|_| Default::default()),
            windows,
            stream: None,
            blocks: 0,
            discontinuities: 0,
            last_observation: None,
        })
    }

    pub fn sensor_id(&self) -> &SensorId {
        &self.sensor_id
    }

    /// The version of the record this monitor judges.
    pub fn version(&self) -> u64 {
        self.version
    }

    /// One raw batch as the wire carries it: `samples` is 12 bytes per sample, three
    /// little-endian f32 outputs (PROTOCOL.md §2.1). A trailing partial sample is ignored.
    pub fn feed(
        &mut self,
        timestamp_ns: i64,
        sample_rate_hz: f64,
        temperature_c: Option<f32>,
        samples: &[u8],
    ) {
        let chunks = samples.chunks_exact(12);
        let n = chunks.len();
        let decoded = chunks.map(|c| {
            [
                f32::from_le_bytes([c[0], c[1], c[2], c[3]]),
                f32::from_le_bytes([c[4], c[5], c[6], c[7]]),
                f32::from_le_bytes([c[8], c[9], c[10], c[11]]),
            ]
        });
        self.feed_iter(timestamp_ns, sample_rate_hz, temperature_c, n, decoded);
    }

    /// One raw batch, decoded in place by the protocol.
    pub fn feed_view(&mut self, batch: &RawBatchView<'_>) {
        self.feed(
            batch.header.timestamp_ns,
            batch.header.sample_rate_hz,
            batch.temperature_c,
            batch.sample_bytes(),
        );
    }

    /// One batch of outputs as numbers.
    pub fn feed_samples(
        &mut self,
        timestamp_ns: i64,
        sample_rate_hz: f64,
        temperature_c: Option<f32>,
        samples: &[[f32; 3]],
    ) {
        self.feed_iter(
            timestamp_ns,
            sample_rate_hz,
            temperature_c,
            samples.len(),
            samples.iter().copied(),
        );
    }

    /// Tells the monitor that the stream broke before the next batch (the gateway saw a
    /// sequence gap it could not tell from the time stamps).
    pub fn break_stream(&mut self) {
        if self.stream.take().is_some() {
            self.discontinuities += 1;
        }
        self.acc.discard();
        if let Some(segments) = &mut self.segments {
            segments.break_run();
        }
        self.gravity.interrupt();
    }

    fn feed_iter(
        &mut self,
        timestamp_ns: i64,
        sample_rate_hz: f64,
        temperature_c: Option<f32>,
        n: usize,
        mut samples: impl Iterator<Item = [f32; 3]>,
    ) {
        if n == 0 || !(sample_rate_hz.is_finite() && sample_rate_hz > 0.0) {
            return;
        }
        let period_ns = 1e9 / sample_rate_hz;
        let continuous = self.stream.is_some_and(|s| {
            s.sample_rate_hz == sample_rate_hz
                && ((timestamp_ns - s.next_ns) as f64).abs() <= 0.5 * period_ns
        });
        if !continuous {
            self.break_stream();
            let block_len = (self.block_s * sample_rate_hz).round().max(3.0) as u32;
            self.stream = Some(Stream {
                sample_rate_hz,
                block_len,
                next_ns: timestamp_ns,
            });
        }
        let Some(stream) = self.stream.as_mut() else {
            return;
        };
        stream.next_ns = timestamp_ns + (n as f64 * period_ns).round() as i64;
        let block_len = stream.block_len;
        let temperature = temperature_c.map(f64::from);
        let mut done = 0usize;
        while done < n {
            let take = ((block_len - self.acc.len()) as usize).min(n - done);
            self.acc.temperature(temperature, take as u32);
            for (i, v) in samples.by_ref().take(take).enumerate() {
                self.acc.push(v);
                if let (Some(segments), Some(windows)) = (&mut self.segments, &mut self.windows) {
                    if segments.push(v) {
                        let at_ns = timestamp_ns + ((done + i) as f64 * period_ns).round() as i64;
                        for k in 0..3 {
                            on_segment(
                                &segments.channel(k),
                                &mut windows[k],
                                &mut self.channels[k],
                                &self.design,
                                at_ns,
                                period_ns,
                            );
                        }
                    }
                }
            }
            done += take;
            if self.acc.len() == block_len {
                let end_ns = timestamp_ns + ((done - 1) as f64 * period_ns).round() as i64;
                let summary = self
                    .acc
                    .finish(end_ns, f64::from(block_len) / sample_rate_hz);
                self.on_block(&summary);
            }
        }
    }

    fn on_block(&mut self, b: &BlockSummary) {
        self.blocks += 1;
        let m = *self.gravity.model().s_inv();
        let noise = b.channels.map(|c| c.noise_var().unwrap_or(0.0));
        // Vibration power: trace of S⁻¹·(C − N)·S⁻ᵀ, and the noise's N alone.
        let mut vibration = 0.0;
        let mut noise_power = 0.0;
        for row in &m {
            for j in 0..3 {
                noise_power += row[j] * row[j] * noise[j];
                for l in 0..3 {
                    let c = b.cov_output[j][l] - if j == l { noise[j] } else { 0.0 };
                    vibration += row[j] * c * row[l];
                }
            }
        }
        let n = f64::from(b.n3.max(2));
        let nu = b
            .channels
            .iter()
            .map(|c| c.noise_dof())
            .fold(f64::INFINITY, f64::min)
            .max(1.0);
        let allowance = 5.0 * noise_power * (2.0 / (n - 1.0) + 2.0 / nu).sqrt();
        let mut any_dead = false;
        let mut clipped = 0;
        for (ch, cb) in self.channels.iter_mut().zip(&b.channels) {
            any_dead |= ch.on_block(&self.design, cb, b.n, b.end_ns, b.duration_s);
            clipped += cb.clipped;
        }
        let thresholds = [0, 1, 2]
            .map(|j| self.channels[j].spike_threshold(self.spike_sigma, b.channels[j].noise_var()));
        self.acc.set_spike_thresholds(thresholds);
        let quiet = vibration <= self.quiet_var + allowance;
        let usable = !any_dead && clipped == 0 && 10 * b.n3 >= 9 * b.n;
        if quiet && usable {
            if let Some(o) = self
                .gravity
                .quiet_block(b.end_ns, b.mean_output, b.temperature_c)
            {
                self.last_observation = Some(o);
            }
        } else {
            self.gravity.interrupt();
        }
    }

    /// Blocks judged so far: a caller that asks for a verdict only when a block was judged
    /// compares this with what it saw last.
    pub fn blocks(&self) -> u64 {
        self.blocks
    }

    /// The latest quiet stretch's reduction, for a caller that shows it.
    pub fn last_gravity_observation(&self) -> Option<&GravityObservation> {
        self.last_observation.as_ref()
    }

    /// Whether the relative gravity test has its baseline.
    pub fn has_gravity_baseline(&self) -> bool {
        self.gravity.has_baseline()
    }

    pub fn report(&self) -> HealthReport {
        let gravity_absolute = self.gravity.absolute_report();
        let gravity_relative = self.gravity.relative_report();
        let stuck = [0, 1, 2].map(|j| self.channels[j].stuck_report());
        let noise = [0, 1, 2].map(|j| {
            let mut t = self.channels[j].noise_report(&self.design);
            if !t.judged {
                t.reason = Some(if self.windows.is_none() {
                    Unjudged::NoStatedNoise
                } else if t.masked + t.loud > 0 {
                    Unjudged::Masked
                } else {
                    Unjudged::NoData
                });
            }
            t
        });
        let spikes = [0, 1, 2].map(|j| self.channels[j].spike_report(&self.design, self.block_s));
        let mut report = HealthReport {
            verdict: Verdict::Ok,
            suspect_since_ns: None,
            gravity_absolute,
            gravity_relative,
            stuck,
            noise,
            spikes,
            blocks: self.blocks,
            quiet_stretches: self.gravity.stretches(),
            discontinuities: self.discontinuities,
        };
        let mut verdict = Verdict::Ok;
        let mut since: Option<i64> = None;
        for (_, _, t) in report.tests() {
            verdict = verdict.max(t.verdict);
            if t.verdict == Verdict::Suspect {
                if let Some(s) = t.since_ns {
                    since = Some(since.map_or(s, |x| x.min(s)));
                }
            }
        }
        report.verdict = verdict;
        report.suspect_since_ns = since;
        for t in [&mut report.gravity_absolute, &mut report.gravity_relative]
            .into_iter()
            .chain(&mut report.stuck)
            .chain(&mut report.noise)
            .chain(&mut report.spikes)
        {
            if t.judged {
                t.reason = None;
            }
        }
        report
    }
}

/// A channel's completed noise segment into its window, and a completed window into the
/// channel's noise test.
#[cold]
fn on_segment(
    d2: &[f32; SEGMENT],
    window: &mut FloorWindow,
    channel: &mut ChannelHealth,
    design: &ChannelDesign,
    end_ns: i64,
    period_ns: f64,
) {
    if let Some(w) = window.segment(d2, end_ns, &design.noise) {
        let duration_ns = (period_ns * (SEGMENT * WINDOW_SEGMENTS) as f64) as i64;
        channel.on_noise_window(design, &w, duration_ns);
    }
}

#[cfg(test)]
mod tests {
    use std::mem::{offset_of, size_of};

    use super::*;

    /// What a batch touches lies in the first [`SensorHealth::PER_BATCH_BYTES`], and that is a
    /// small part of the monitor: a field moved among the block-time ones would leave a
    /// caller's load ahead short of it.
    #[test]
    fn a_batch_touches_the_first_bytes_only() {
        let end = |offset: usize, size: usize| offset + size;
        for (field, last_byte) in [
            (
                "version",
                end(offset_of!(SensorHealth, version), size_of::<u64>()),
            ),
            (
                "blocks",
                end(offset_of!(SensorHealth, blocks), size_of::<u64>()),
            ),
            (
                "stream",
                end(
                    offset_of!(SensorHealth, stream),
                    size_of::<Option<Stream>>(),
                ),
            ),
            (
                "acc",
                end(offset_of!(SensorHealth, acc), size_of::<BlockAccumulator>()),
            ),
        ] {
            assert!(
                last_byte <= SensorHealth::PER_BATCH_BYTES,
                "{field} ends at {last_byte}"
            );
        }
        assert!(
            SensorHealth::PER_BATCH_BYTES * 2 < size_of::<SensorHealth>(),
            "{} of {}",
            SensorHealth::PER_BATCH_BYTES,
            size_of::<SensorHealth>()
        );
    }
}
