//! The per-sample work: one pass over a block's raw outputs into the sums every test reads.
//!
//! Per channel: how many outputs were finite and how often an output differed from the one
//! before it (a stuck channel never changes), the second differences `V[i] − 2V[i−1] + V[i−2]`
//! (white noise σ gives them variance 6σ²; a structure's modes, far below the sample rate, give
//! them almost nothing: the lab's own noise estimator, `fit::dynamic::output_noise`), and
//! spike candidates among them. Across channels: the mean and covariance of the outputs, for
//! the vibration level and the gravity check.
//!
//! **Spikes.** A second difference beyond the threshold starts or extends a cluster; a cluster
//! closes after [`SPIKE_GAP`] samples without one. A single-sample outlier of height h leaves
//! +h, −2h, +h in three consecutive second differences, so a cluster no longer than
//! [`SPIKE_MAX_EXTENT`] samples is a spike (its squares are kept out of the noise estimate),
//! and a longer one is a burst of real motion or of noise (its squares go into the noise
//! estimate, the moment it is known to be one). The threshold follows the previous block's
//! measured noise when that exceeds the stated one, so that a noisy channel's ordinary samples
//! are never counted as spikes.
//!
//! Cost: about 40 floating-point operations and a few predictable branches per sample, no
//! allocation; the accumulator is a few hundred bytes.

/// Samples without a threshold crossing that close a spike cluster.
pub const SPIKE_GAP: u64 = 8;
/// Longest cluster, in samples, counted as a spike rather than a burst.
pub const SPIKE_MAX_EXTENT: u64 = 4;

#[derive(Debug, Clone, Default)]
struct ChannelAcc {
    prev1: f64,
    prev2: f64,
    /// How many of prev1, prev2 hold finite outputs of this run (0 to 2).
    valid: u8,
    n_finite: u32,
    n_changes: u32,
    d2_sum: f64,
    d2_count: u32,
    /// |second difference| above which a sample is a spike candidate, output unit.
    threshold: f64,
    cluster_open: bool,
    cluster_burst: bool,
    cluster_first: u64,
    cluster_last: u64,
    cluster_sq: f64,
    cluster_n: u32,
    spikes: u32,
    bursts: u32,
    clipped: u32,
}

impl ChannelAcc {
    #[inline(always)]
    fn push(&mut self, x: f64, index: u64, full_scale: f64) {
        if !x.is_finite() {
            self.valid = 0;
            return;
        }
        self.n_finite += 1;
        if x.abs() >= full_scale {
            self.clipped += 1;
        }
        if self.valid >= 1 && x != self.prev1 {
            self.n_changes += 1;
        }
        if self.valid >= 2 {
            let d2 = x - 2.0 * self.prev1 + self.prev2;
            let sq = d2 * d2;
            if d2.abs() > self.threshold {
                self.candidate(sq, index);
            } else {
                self.d2_sum += sq;
                self.d2_count += 1;
            }
        }
        self.prev2 = self.prev1;
        self.prev1 = x;
        self.valid = (self.valid + 1).min(2);
    }

    #[cold]
    fn candidate(&mut self, sq: f64, index: u64) {
        if self.cluster_open && index - self.cluster_last <= SPIKE_GAP {
            self.cluster_last = index;
            if self.cluster_burst {
                self.d2_sum += sq;
                self.d2_count += 1;
            } else {
                self.cluster_sq += sq;
                self.cluster_n += 1;
                if index - self.cluster_first + 1 > SPIKE_MAX_EXTENT {
                    self.cluster_burst = true;
                    self.bursts += 1;
                    self.d2_sum += self.cluster_sq;
                    self.d2_count += self.cluster_n;
                }
            }
        } else {
            self.close_cluster();
            self.cluster_open = true;
            self.cluster_burst = false;
            self.cluster_first = index;
            self.cluster_last = index;
            self.cluster_sq = sq;
            self.cluster_n = 1;
        }
    }

    fn close_cluster(&mut self) {
        if self.cluster_open && !self.cluster_burst {
            self.spikes += 1;
        }
        self.cluster_open = false;
    }

    /// Closes a cluster that has seen its gap by sample `index`.
    fn settle(&mut self, index: u64) {
        if self.cluster_open && index.saturating_sub(self.cluster_last) > SPIKE_GAP {
            self.close_cluster();
        }
    }

    fn take(&mut self) -> ChannelBlock {
        let block = ChannelBlock {
            n_finite: self.n_finite,
            n_changes: self.n_changes,
            d2_sum: self.d2_sum,
            d2_count: self.d2_count,
            spikes: self.spikes,
            bursts: self.bursts,
            clipped: self.clipped,
        };
        self.n_finite = 0;
        self.n_changes = 0;
        self.d2_sum = 0.0;
        self.d2_count = 0;
        self.spikes = 0;
        self.bursts = 0;
        self.clipped = 0;
        block
    }

    /// Forgets the samples before a discontinuity: a second difference across it would be
    /// the jump, not noise. A cluster open at the break is closed as it stands.
    fn break_run(&mut self) {
        self.close_cluster();
        self.valid = 0;
    }
}

/// One channel's share of a finished block.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct ChannelBlock {
    pub n_finite: u32,
    /// Outputs that differ from the previous finite output.
    pub n_changes: u32,
    /// Sum of squared second differences outside spikes, output unit², and their number.
    pub d2_sum: f64,
    pub d2_count: u32,
    pub spikes: u32,
    pub bursts: u32,
    pub clipped: u32,
}

impl ChannelBlock {
    /// White-noise variance of one output from the second differences, output unit².
    pub fn noise_var(&self) -> Option<f64> {
        (self.d2_count > 0).then(|| self.d2_sum / (6.0 * f64::from(self.d2_count)))
    }

    /// Degrees of freedom of [`noise_var`](Self::noise_var): neighbouring second differences
    /// are correlated (autocovariances 6, −4, 1), so their mean square varies as a χ² with
    /// `72/140` of their number.
    pub fn noise_dof(&self) -> f64 {
        72.0 / 140.0 * f64::from(self.d2_count)
    }
}

/// A finished block.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BlockSummary {
    /// Time of the block's last sample, ns.
    pub end_ns: i64,
    pub duration_s: f64,
    /// Samples in the block.
    pub n: u32,
    /// Samples finite and unclipped on all three channels, which the means cover.
    pub n3: u32,
    pub mean_output: [f64; 3],
    /// Sample covariance of the outputs, output unit².
    pub cov_output: [[f64; 3]; 3],
    /// Mean temperature of the block's batches; none if any batch had none.
    pub temperature_c: Option<f64>,
    pub channels: [ChannelBlock; 3],
}

/// The running sums of the block being filled.
#[derive(Debug, Clone, Default)]
pub struct BlockAccumulator {
    channels: [ChannelAcc; 3],
    n: u32,
    n3: u32,
    shift: [f64; 3],
    sum: [f64; 3],
    /// Upper triangle of Σ(v − shift)(v − shift)ᵀ: xx, yy, zz, xy, xz, yz.
    sum_sq: [f64; 6],
    temperature_sum: f64,
    temperature_missing: bool,
    /// Samples seen since the monitor started, for spike clusters.
    index: u64,
    full_scale: f64,
}

impl BlockAccumulator {
    pub fn new(full_scale: f64) -> BlockAccumulator {
        BlockAccumulator {
            full_scale,
            channels: Default::default(),
            ..Default::default()
        }
    }

    /// Samples in the block so far.
    #[inline]
    pub fn len(&self) -> u32 {
        self.n
    }

    #[inline]
    pub fn is_empty(&self) -> bool {
        self.n == 0
    }

    /// The thresholds of the next spike candidates, per channel, output unit.
    pub fn set_spike_thresholds(&mut self, thresholds: [f64; 3]) {
        for (c, t) in self.channels.iter_mut().zip(thresholds) {
            c.threshold = t;
        }
    }

    /// Notes that the next `count` samples come from a batch at `temperature_c`.
    #[inline]
    pub fn temperature(&mut self, temperature_c: Option<f64>, count: u32) {
        match temperature_c {
            Some(t) if t.is_finite() => self.temperature_sum += t * f64::from(count),
            _ => self.temperature_missing = true,
        }
    }

    #[inline(always)]
    pub fn push(&mut self, v: [f32; 3]) {
        let v = v.map(f64::from);
        let index = self.index;
        self.index += 1;
        self.n += 1;
        for (c, x) in self.channels.iter_mut().zip(v) {
            c.push(x, index, self.full_scale);
        }
        let usable = v.iter().all(|x| x.is_finite() && x.abs() < self.full_scale);
        if usable {
            if self.n3 == 0 {
                self.shift = v;
            }
            self.n3 += 1;
            let d = [
                v[0] - self.shift[0],
                v[1] - self.shift[1],
                v[2] - self.shift[2],
            ];
            self.sum[0] += d[0];
            self.sum[1] += d[1];
            self.sum[2] += d[2];
            self.sum_sq[0] += d[0] * d[0];
            self.sum_sq[1] += d[1] * d[1];
            self.sum_sq[2] += d[2] * d[2];
            self.sum_sq[3] += d[0] * d[1];
            self.sum_sq[4] += d[0] * d[2];
            self.sum_sq[5] += d[1] * d[2];
        }
    }

    /// Ends the block at `end_ns`, lasting `duration_s`, and starts the next.
    pub fn finish(&mut self, end_ns: i64, duration_s: f64) -> BlockSummary {
        for c in &mut self.channels {
            c.settle(self.index);
        }
        let n3 = f64::from(self.n3);
        let mean_d = self.sum.map(|s| s / n3.max(1.0));
        let mut cov = [[0.0; 3]; 3];
        if self.n3 >= 2 {
            let at = |i: usize, j: usize| match (i.min(j), i.max(j)) {
                (0, 0) => 0,
                (1, 1) => 1,
                (2, 2) => 2,
                (0, 1) => 3,
                (0, 2) => 4,
                _ => 5,
            };
            for (i, row) in cov.iter_mut().enumerate() {
                for (j, cell) in row.iter_mut().enumerate() {
                    *cell = (self.sum_sq[at(i, j)] - n3 * mean_d[i] * mean_d[j]) / (n3 - 1.0);
                }
            }
        }
        let summary = BlockSummary {
            end_ns,
            duration_s,
            n: self.n,
            n3: self.n3,
            mean_output: [0, 1, 2].map(|k| self.shift[k] + mean_d[k]),
            cov_output: cov,
            temperature_c: (!self.temperature_missing && self.n > 0)
                .then(|| self.temperature_sum / f64::from(self.n)),
            channels: [0, 1, 2].map(|k| self.channels[k].take()),
        };
        self.n = 0;
        self.n3 = 0;
        self.sum = [0.0; 3];
        self.sum_sq = [0.0; 6];
        self.temperature_sum = 0.0;
        self.temperature_missing = false;
        summary
    }

    /// Drops the partial block and the second-difference history: the next sample starts
    /// afresh (a gap, a restart, a new sample rate).
    pub fn discard(&mut self) {
        for c in &mut self.channels {
            c.break_run();
            c.take();
        }
        self.n = 0;
        self.n3 = 0;
        self.sum = [0.0; 3];
        self.sum_sq = [0.0; 6];
        self.temperature_sum = 0.0;
        self.temperature_missing = false;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn block(samples: &[[f32; 3]], threshold: f64) -> BlockSummary {
        let mut acc = BlockAccumulator::new(f64::INFINITY);
        acc.set_spike_thresholds([threshold; 3]);
        acc.temperature(Some(20.0), samples.len() as u32);
        for s in samples {
            acc.push(*s);
        }
        acc.finish(0, 1.0)
    }

    /// Means, covariance and second differences by hand on five samples.
    #[test]
    fn sums_by_hand() {
        let s = [
            [1.0, 0.0, 2.0],
            [2.0, 0.0, 2.0],
            [4.0, 1.0, 2.0],
            [3.0, 0.0, 2.0],
            [5.0, -1.0, 2.0],
        ];
        let b = block(&s, f64::INFINITY);
        assert_eq!(b.n, 5);
        assert_eq!(b.n3, 5);
        assert_eq!(b.mean_output, [3.0, 0.0, 2.0]);
        // x: deviations −2, −1, 1, 0, 2: Σ = 10, /4 = 2.5; y: 0, 0, 1, 0, −1: 0.5;
        // xy: 0 + 0 + 1 + 0 − 2 = −1, /4.
        assert!((b.cov_output[0][0] - 2.5).abs() < 1e-12);
        assert!((b.cov_output[1][1] - 0.5).abs() < 1e-12);
        assert!((b.cov_output[0][1] + 0.25).abs() < 1e-12);
        assert_eq!(b.cov_output[2][2], 0.0);
        // x second differences: 4 − 4 + 1 = 1, 3 − 8 + 2 = −3, 5 − 6 + 4 = 3: Σ² = 19.
        assert_eq!(b.channels[0].d2_count, 3);
        assert!((b.channels[0].d2_sum - 19.0).abs() < 1e-12);
        assert!((b.channels[0].noise_var().unwrap() - 19.0 / 18.0).abs() < 1e-12);
        assert_eq!(b.channels[0].n_changes, 4);
        assert_eq!(b.channels[2].n_changes, 0);
        assert_eq!(b.temperature_c, Some(20.0));
    }

    /// One outlier in a quiet channel is one spike and leaves the noise sum alone; a run of
    /// large second differences is a burst and goes into it; a NaN breaks the run.
    #[test]
    fn spikes_bursts_and_breaks() {
        let mut s = vec![[0.0f32; 3]; 100];
        for (i, x) in s.iter_mut().enumerate() {
            x[0] = if i % 2 == 0 { 0.01 } else { -0.01 };
        }
        s[50][0] = 5.0;
        for (i, x) in s.iter_mut().enumerate().take(90).skip(70) {
            x[1] = if i % 2 == 0 { 1.0 } else { -1.0 };
        }
        s[20][2] = f32::NAN;
        let b = block(&s, 1.0);
        assert_eq!(b.channels[0].spikes, 1);
        assert_eq!(b.channels[0].bursts, 0);
        // Only ±0.04 second differences count: 98 of them minus the three of the spike.
        assert_eq!(b.channels[0].d2_count, 95);
        assert!((b.channels[0].d2_sum - 95.0 * 0.0016).abs() < 1e-6);
        assert_eq!(b.channels[1].spikes, 0);
        assert_eq!(b.channels[1].bursts, 1);
        assert_eq!(b.channels[2].n_finite, 99);
        // The NaN costs the two differences that would span it and the one it would start.
        assert_eq!(b.channels[2].d2_count, 98 - 3);
        assert_eq!(b.n3, 99);
    }
}
