//! Per-sensor sequence tracking: gaps, duplicates and node restarts.
//!
//! A node numbers its batches 0, 1, 2, … The rule, per batch with sequence `s` after the
//! highest accepted `last`:
//! - `s = last + 1`: in order;
//! - `s > last + 1`: a gap of `s − last − 1` lost batches (`sequence_gap`);
//! - `s ≤ last`: a duplicate or late batch (`duplicate`), published flagged, `last` unchanged;
//! - except `s = 0` after a later batch, or `s` more than [`RESTART_BACKWARDS`] below `last`: the node restarted and
//!   counts again from there; tracking restarts with no flag.

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
    last: Option<u64>,
}

impl SequenceTracker {
    pub fn observe(&mut self, s: u64) -> Verdict {
        let Some(last) = self.last else {
            self.last = Some(s);
            return Verdict::First;
        };
        if s == last.wrapping_add(1) {
            self.last = Some(s);
            Verdict::InOrder
        } else if s > last {
            self.last = Some(s);
            Verdict::Gap {
                missing: s - last - 1,
            }
        } else if (s == 0 && last > 0) || last - s > RESTART_BACKWARDS {
            self.last = Some(s);
            Verdict::Restart
        } else {
            Verdict::Duplicate
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn verdicts() {
        let mut t = SequenceTracker::default();
        assert_eq!(t.observe(0), Verdict::First);
        assert_eq!(t.observe(0), Verdict::Duplicate);
        assert_eq!(t.observe(5), Verdict::Gap { missing: 4 });
        assert_eq!(t.observe(6), Verdict::InOrder);
        assert_eq!(t.observe(9), Verdict::Gap { missing: 2 });
        assert_eq!(t.observe(9), Verdict::Duplicate);
        assert_eq!(t.observe(7), Verdict::Duplicate);
        assert_eq!(t.observe(10), Verdict::InOrder);
        assert_eq!(t.observe(0), Verdict::Restart);
        assert_eq!(t.observe(1), Verdict::InOrder);
        assert_eq!(t.observe(5000), Verdict::Gap { missing: 4998 });
        assert_eq!(t.observe(3), Verdict::Restart);
    }
}
