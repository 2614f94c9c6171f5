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
//!
//! How many batches a gap counts as lost is bounded by the clock as well as by the numbering: no
//! more than fit, at the new batch's duration, between the end of the last accepted batch and the
//! start of the new one, plus one for jitter. A node that jumps its numbering by 10¹⁹ one batch
//! later (a bug, a reset counter, or a hostile sender) has lost at most one batch, and
//! `missing_batches` stays a count of batches that can really have been lost.

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
    /// What the history keeps of this verdict: what a replay needs.
    pub fn kept(self) -> triax_history::Verdict {
        match self {
            Verdict::InOrder | Verdict::First => triax_history::Verdict::InOrder,
            Verdict::Gap { .. } => triax_history::Verdict::Gap,
            Verdict::Duplicate => triax_history::Verdict::Duplicate,
            Verdict::Restart => triax_history::Verdict::Restart,
        }
    }
}

/// The highest accepted batch.
#[derive(Debug, Clone, Copy)]
struct Last {
    sequence: u64,
    timestamp_ns: i64,
    /// Where that batch ended: its start plus its duration.
    end_ns: i64,
}

#[derive(Debug, Clone, Default)]
pub struct SequenceTracker {
    last: Option<Last>,
}

impl SequenceTracker {
    /// The highest accepted batch: its number and first sample's time.
    pub fn last(&self) -> Option<(u64, i64)> {
        self.last.map(|l| (l.sequence, l.timestamp_ns))
    }

    /// Classifies batch `s` whose first sample is at `timestamp_ns` and which lasts
    /// `duration_ns` (its sample count over its rate).
    pub fn observe(&mut self, s: u64, timestamp_ns: i64, duration_ns: i64) -> Verdict {
        let this = Last {
            sequence: s,
            timestamp_ns,
            end_ns: timestamp_ns.saturating_add(duration_ns),
        };
        let Some(last) = self.last else {
            self.last = Some(this);
            return Verdict::First;
        };
        // At most as many batches as fit in the time between the two, plus one for jitter.
        let gap = |by_number: u64| {
            let between_ns = i128::from(timestamp_ns) - i128::from(last.end_ns);
            let by_clock = (between_ns.max(0) / i128::from(duration_ns.max(1))) + 1;
            Verdict::Gap {
                missing: by_number.min(u64::try_from(by_clock).unwrap_or(u64::MAX)),
            }
        };
        let accept = |tracker: &mut Self, verdict| {
            tracker.last = Some(this);
            verdict
        };
        if s == last.sequence.wrapping_add(1) {
            accept(self, Verdict::InOrder)
        } else if s > last.sequence {
            accept(self, gap(s - last.sequence - 1))
        } else if (s == 0 && last.sequence > 0) || last.sequence - s > RESTART_BACKWARDS {
            accept(self, Verdict::Restart)
        } else if timestamp_ns > last.timestamp_ns {
            // Not higher, yet later than the highest batch: a new run whose first batches
            // (0..s) were lost.
            let verdict = if s == 0 { Verdict::Restart } else { gap(s) };
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
        (t0_s + s as i64) * SECOND
    }

    const SECOND: i64 = 1_000_000_000;

    #[test]
    fn verdicts() {
        let mut t = SequenceTracker::default();
        let mut obs = |s: u64| t.observe(s, at(0, s), SECOND);
        assert_eq!(obs(0), Verdict::First);
        assert_eq!(obs(0), Verdict::Duplicate);
        assert_eq!(obs(5), Verdict::Gap { missing: 4 });
        assert_eq!(obs(6), Verdict::InOrder);
        assert_eq!(obs(9), Verdict::Gap { missing: 2 });
        assert_eq!(obs(9), Verdict::Duplicate);
        assert_eq!(obs(7), Verdict::Duplicate, "a late batch");
        assert_eq!(obs(10), Verdict::InOrder);
        let mut t = SequenceTracker::default();
        assert_eq!(t.observe(10, at(0, 10), SECOND), Verdict::First);
        assert_eq!(t.observe(0, at(100, 0), SECOND), Verdict::Restart);
        assert_eq!(t.observe(1, at(100, 1), SECOND), Verdict::InOrder);
        assert_eq!(
            t.observe(5000, at(100, 5000), SECOND),
            Verdict::Gap { missing: 4998 }
        );
        assert_eq!(
            t.observe(3, at(0, 3), SECOND),
            Verdict::Restart,
            "far behind"
        );
    }

    #[test]
    fn a_restart_whose_first_batches_were_lost_is_not_a_duplicate() {
        let mut t = SequenceTracker::default();
        for s in 0..=500 {
            t.observe(s, at(0, s), SECOND);
        }
        // The node restarts at t = 1000 s; its batches 0 and 1 are lost.
        assert_eq!(
            t.observe(2, at(1000, 2), SECOND),
            Verdict::Gap { missing: 2 }
        );
        assert_eq!(t.observe(3, at(1000, 3), SECOND), Verdict::InOrder);
        // A genuine duplicate of the new run is still one.
        assert_eq!(t.observe(3, at(1000, 3), SECOND), Verdict::Duplicate);
    }

    #[test]
    fn a_gap_counts_no_more_batches_than_the_clock_allows() {
        let mut t = SequenceTracker::default();
        assert_eq!(t.observe(5, at(0, 5), SECOND), Verdict::First);
        // Numbered 10^19 further on, one second later: at most one batch can be missing.
        assert_eq!(
            t.observe(u64::MAX - 3, at(0, 6), SECOND),
            Verdict::Gap { missing: 1 }
        );
        let mut t = SequenceTracker::default();
        t.observe(0, at(0, 0), SECOND);
        // Three batches really lost: numbering and clock agree.
        assert_eq!(t.observe(4, at(0, 4), SECOND), Verdict::Gap { missing: 3 });
        // A clock from the far past or future cannot overflow the bound.
        assert_eq!(
            t.observe(u64::MAX / 2, i64::MIN, i64::MAX),
            Verdict::Gap { missing: 1 }
        );
        assert_eq!(
            t.observe(u64::MAX / 2 + 10, i64::MAX, 0),
            Verdict::Gap { missing: 9 }
        );
    }
}
