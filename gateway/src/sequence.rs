//! Per-sensor sequence tracking: gaps, duplicates and node restarts.
//!
//! A node numbers its batches 0, 1, 2, … The rule, per batch with sequence `s` after the
//! highest accepted `last`:
//! - `s = last + 1`: in order;
//! - `s > last + 1`: a gap of `s − last − 1` lost batches (`sequence_gap`);
//! - `s ≤ last`: a duplicate or late batch (`duplicate`), published flagged, `last` unchanged;
//! - except when the node restarted and counts again from there, which shows as `s = 0` after a
//!   later batch, as `s` more than [`RESTART_BACKWARDS`] below `last`, or as a batch that starts
//!   after the highest accepted batch began although its number is not higher (the restart's
//!   first batches were lost, so the number alone would pass for a duplicate and flag a whole
//!   stretch of fresh signal). A restart at `s = 0` carries no flag; one at `s > 0` is a gap of
//!   `s` batches.

use triax_protocol::batch::flags;

/// A jump back by more than this many batches is a node restart, not a late batch.
pub const RESTART_BACKWARDS: u64 = 1024;

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Verdict {
    InOrder,
    First,
    Gap { missing: u64 },
    Duplicate,
    Restart,
}

impl Verdict {
    /// Batch-level flags for this verdict.
    pub fn flags(self) -> u16 {
        match self {
            Verdict::Gap { .. } => flags::SEQUENCE_GAP,
            Verdict::Duplicate => flags::DUPLICATE,
            _ => 0,
        }
    }
}

#[derive(Debug, Clone, Default)]
pub struct SequenceTracker {
    /// Highest accepted sequence number and the timestamp of that batch's first sample.
    last: Option<(u64, i64)>,
}

impl SequenceTracker {
    /// Classifies batch `s` whose first sample is at `timestamp_ns`.
    pub fn observe(&mut self, s: u64, timestamp_ns: i64) -> Verdict {
        let Some((last, last_ns)) = self.last else {
            self.last = Some((s, timestamp_ns));
            return Verdict::First;
        };
        let accept = |tracker: &mut Self, verdict| {
            tracker.last = Some((s, timestamp_ns));
            verdict
        };
        if s == last.wrapping_add(1) {
            accept(self, Verdict::InOrder)
        } else if s > last {
            accept(
                self,
                Verdict::Gap {
                    missing: s - last - 1,
                },
            )
        } else if (s == 0 && last > 0) || last - s > RESTART_BACKWARDS {
            accept(self, Verdict::Restart)
        } else if timestamp_ns > last_ns {
            // Not higher, yet later than the highest batch: a new run whose first batches
            // (0..s) were lost.
            let verdict = if s == 0 {
                Verdict::Restart
            } else {
                Verdict::Gap { missing: s }
            };
            accept(self, verdict)
        } else {
            Verdict::Duplicate
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Batch `s` of a node that sends one batch a second, starting at `t0_s`.
    fn at(t0_s: i64, s: u64) -> i64 {
        (t0_s + s as i64) * 1_000_000_000
    }

    #[test]
    fn verdicts() {
        let mut t = SequenceTracker::default();
        let mut obs = |s: u64| t.observe(s, at(0, s));
        assert_eq!(obs(0), Verdict::First);
        assert_eq!(obs(0), Verdict::Duplicate);
        assert_eq!(obs(5), Verdict::Gap { missing: 4 });
        assert_eq!(obs(6), Verdict::InOrder);
        assert_eq!(obs(9), Verdict::Gap { missing: 2 });
        assert_eq!(obs(9), Verdict::Duplicate);
        assert_eq!(obs(7), Verdict::Duplicate, "a late batch");
        assert_eq!(obs(10), Verdict::InOrder);
        let mut t = SequenceTracker::default();
        assert_eq!(t.observe(10, at(0, 10)), Verdict::First);
        assert_eq!(t.observe(0, at(100, 0)), Verdict::Restart);
        assert_eq!(t.observe(1, at(100, 1)), Verdict::InOrder);
        assert_eq!(
            t.observe(5000, at(100, 5000)),
            Verdict::Gap { missing: 4998 }
        );
        assert_eq!(t.observe(3, at(0, 3)), Verdict::Restart, "far behind");
    }

    #[test]
    fn a_restart_whose_first_batches_were_lost_is_not_a_duplicate() {
        let mut t = SequenceTracker::default();
        for s in 0..=500 {
            t.observe(s, at(0, s));
        }
        // The node restarts at t = 1000 s; its batches 0 and 1 are lost.
        assert_eq!(t.observe(2, at(1000, 2)), Verdict::Gap { missing: 2 });
        assert_eq!(t.observe(3, at(1000, 3)), Verdict::InOrder);
        // A genuine duplicate of the new run is still one.
        assert_eq!(t.observe(3, at(1000, 3)), Verdict::Duplicate);
    }
}
