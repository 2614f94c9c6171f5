//! Samples into batches: `batch_samples` at a time, stamped with their first sample's time.
//!
//! A raw batch states only its first sample's time and the rate; every other sample is placed
//! on that grid (PROTOCOL.md §2.1). So a batch is cut early where a sample is off its grid by
//! more than half a period (samples lost in the sensor, a clock step): each batch then tells
//! the truth about its samples' times, and the next one starts at the next sample's own stamp.

use crate::source::Sample;

/// Samples gathered for one batch.
#[derive(Debug, Clone, PartialEq)]
pub struct Pending {
    pub timestamp_ns: i64,
    pub samples: Vec<[f32; 3]>,
}

#[derive(Debug)]
pub struct Batcher {
    batch_samples: usize,
    period_ns: f64,
    current: Option<Pending>,
    /// Batches cut early because a sample was off the grid.
    pub breaks: u64,
}

impl Batcher {
    pub fn new(batch_samples: usize, rate_hz: f64) -> Batcher {
        Batcher {
            batch_samples,
            period_ns: 1e9 / rate_hz,
            current: None,
            breaks: 0,
        }
    }

    /// Adds a sample; returns the batch it completed or cut, if any.
    pub fn push(&mut self, s: Sample, done: &mut Vec<Pending>) {
        if let Some(cur) = &self.current {
            let expected = cur.timestamp_ns as f64 + cur.samples.len() as f64 * self.period_ns;
            if (s.timestamp_ns as f64 - expected).abs() > 0.5 * self.period_ns {
                self.breaks += 1;
                done.extend(self.current.take());
            }
        }
        let cur = self.current.get_or_insert_with(|| Pending {
            timestamp_ns: s.timestamp_ns,
            samples: Vec::with_capacity(self.batch_samples),
        });
        cur.samples.push(s.v);
        if cur.samples.len() >= self.batch_samples {
            done.extend(self.current.take());
        }
    }

    /// The samples gathered so far, as a shorter batch (at a stop).
    pub fn flush(&mut self) -> Option<Pending> {
        self.current.take()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn s(t_ns: i64, x: f32) -> Sample {
        Sample {
            timestamp_ns: t_ns,
            v: [x, 0.0, 1.0],
        }
    }

    #[test]
    fn batches_of_n_stamped_with_their_first_sample() {
        let mut b = Batcher::new(3, 100.0);
        let mut done = Vec::new();
        for i in 0..7 {
            b.push(s(1_000 + i * 10_000_000, i as f32), &mut done);
        }
        assert_eq!(done.len(), 2);
        assert_eq!(done[0].timestamp_ns, 1_000);
        assert_eq!(done[1].timestamp_ns, 1_000 + 30_000_000);
        assert_eq!(done[1].samples[2][0], 5.0);
        let rest = b.flush().unwrap();
        assert_eq!(rest.samples.len(), 1);
        assert_eq!(rest.timestamp_ns, 1_000 + 60_000_000);
        assert!(b.flush().is_none());
    }

    #[test]
    fn a_sample_off_the_grid_cuts_the_batch() {
        let mut b = Batcher::new(10, 100.0);
        let mut done = Vec::new();
        // Jitter within half a period stays in the batch.
        b.push(s(0, 0.0), &mut done);
        b.push(s(14_000_000, 1.0), &mut done);
        assert!(done.is_empty());
        // Two samples lost: the next is 30 ms after the last.
        b.push(s(40_000_000, 2.0), &mut done);
        assert_eq!(done.len(), 1);
        assert_eq!(done[0].samples.len(), 2);
        assert_eq!(b.breaks, 1);
        assert_eq!(b.flush().unwrap().timestamp_ns, 40_000_000);
    }
}
