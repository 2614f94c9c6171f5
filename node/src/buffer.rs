//! The buffer's query contract (PROTOCOL.md §5.4): `triax/<building>/buffer/<sensor>` with
//! `from_seq=<u64>;to_seq=<u64>` (inclusive, both required, at most [`MAX_BATCHES_PER_QUERY`]
//! batches) answers one reply per batch held in the range, its payload the raw batch exactly
//! as published, in sequence order; `status` answers a [`BufferStatus`] (JSON).

use serde::{Deserialize, Serialize};

/// Most batches one query may span (sequence numbers `from_seq..=to_seq`).
pub const MAX_BATCHES_PER_QUERY: u64 = 100_000;

/// What a buffer query asks.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum BufferQuery {
    /// The batches held whose sequence number is in `from..=to`.
    Range { from: u64, to: u64 },
    /// The buffer's status.
    Status,
}

const KNOWN: &str = "known: from_seq, to_seq, status";

impl BufferQuery {
    /// Reads the selector's parameters; the error names the parameter and what is wrong.
    pub fn parse<'a>(
        parameters: impl IntoIterator<Item = (&'a str, &'a str)>,
    ) -> Result<BufferQuery, String> {
        let mut from = None;
        let mut to = None;
        let mut status = false;
        for (name, value) in parameters {
            let slot = match name {
                "from_seq" => &mut from,
                "to_seq" => &mut to,
                "status" => {
                    if !value.is_empty() {
                        return Err(format!(
                            "buffer query: status: takes no value, got {value:?}"
                        ));
                    }
                    status = true;
                    continue;
                }
                other => {
                    return Err(format!(
                        "buffer query: unknown parameter {other:?} ({KNOWN})"
                    ))
                }
            };
            if slot.is_some() {
                return Err(format!("buffer query: {name}: given twice"));
            }
            *slot = Some(value.parse::<u64>().map_err(|_| {
                format!("buffer query: {name}: {value:?} is not a whole number ≥ 0")
            })?);
        }
        if status {
            if from.is_some() || to.is_some() {
                return Err(
                    "buffer query: status: asked with from_seq or to_seq; ask one or the other"
                        .into(),
                );
            }
            return Ok(BufferQuery::Status);
        }
        let missing = |name: &str| {
            format!(
                "buffer query: {name}: missing (ask from_seq=<first>;to_seq=<last>, both \
                 inclusive, or status)"
            )
        };
        let from = from.ok_or_else(|| missing("from_seq"))?;
        let to = to.ok_or_else(|| missing("to_seq"))?;
        if to < from {
            return Err(format!(
                "buffer query: to_seq: {to} is below from_seq {from}"
            ));
        }
        let span = to - from;
        if span >= MAX_BATCHES_PER_QUERY {
            return Err(format!(
                "buffer query: to_seq: from_seq={from};to_seq={to} spans {} batches, more than \
                 {MAX_BATCHES_PER_QUERY} per query",
                u128::from(span) + 1
            ));
        }
        Ok(BufferQuery::Range { from, to })
    }
}

/// The reply to `triax/<building>/buffer/<sensor>?status` (PROTOCOL.md §5.4).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct BufferStatus {
    pub format_version: u32,
    pub building: String,
    pub sensor: String,
    /// Oldest and newest batch held, by sequence number and first-sample time; `null` when the
    /// buffer is empty.
    pub oldest_sequence: Option<u64>,
    pub newest_sequence: Option<u64>,
    pub oldest_timestamp_ns: Option<i64>,
    pub newest_timestamp_ns: Option<i64>,
    /// Batches held (fewer than `newest − oldest + 1` where numbers were skipped).
    pub batches: u64,
    /// Bytes of the buffer's files on disk.
    pub bytes: u64,
    /// Seconds from the oldest batch's first sample to the newest's.
    pub span_s: f64,
    /// Batches the buffer keeps at least (`--buffer-hours` at the rate and batch size).
    pub capacity_batches: u64,
    /// The number the next batch will carry.
    pub next_sequence: u64,
    pub sample_rate_hz: f64,
    pub batch_samples: usize,
    /// Standard uncertainty of the node's clock against UTC, as configured.
    pub clock_uncertainty_ns: f64,
    /// Standard uncertainty a sample's stamp gets from the source itself.
    pub source_stamp_uncertainty_ns: f64,
    /// Standard uncertainty of a batch's `timestamp_ns`: the two above, root sum of squares.
    pub timestamp_uncertainty_ns: f64,
    /// Counters since the node started.
    pub published_batches: u64,
    /// Batches not handed to Zenoh because its queue was full (kept in the buffer).
    pub publish_skipped_batches: u64,
    /// Batches the buffer failed to write (published all the same).
    pub buffer_write_errors: u64,
    /// Batches lost before they were numbered (the buffer's writer fell behind the sensor).
    pub dropped_batches: u64,
    /// Batches cut short because a sample left the time grid (samples lost, a clock step).
    pub time_breaks: u64,
}

#[cfg(test)]
mod tests {
    use super::*;

    fn parse(s: &str) -> Result<BufferQuery, String> {
        BufferQuery::parse(zenoh::query::Parameters::from(s).iter())
    }

    #[test]
    fn ranges_and_status_parse() {
        assert_eq!(
            parse("from_seq=3;to_seq=7"),
            Ok(BufferQuery::Range { from: 3, to: 7 })
        );
        assert_eq!(
            parse("to_seq=3;from_seq=3"),
            Ok(BufferQuery::Range { from: 3, to: 3 })
        );
        assert_eq!(
            parse("from_seq=0;to_seq=99999"),
            Ok(BufferQuery::Range {
                from: 0,
                to: 99_999
            })
        );
        assert_eq!(parse("status"), Ok(BufferQuery::Status));
    }

    #[test]
    fn every_bad_parameter_is_named() {
        let cases = [
            ("", "from_seq: missing"),
            ("from_seq=1", "to_seq: missing"),
            ("to_seq=1", "from_seq: missing"),
            (
                "from_seq=x;to_seq=1",
                "from_seq: \"x\" is not a whole number",
            ),
            (
                "from_seq=1;to_seq=-2",
                "to_seq: \"-2\" is not a whole number",
            ),
            ("from_seq=5;to_seq=4", "to_seq: 4 is below from_seq 5"),
            ("from_seq=0;to_seq=100000", "spans 100001 batches"),
            (
                "from_seq=0;to_seq=18446744073709551615",
                "spans 18446744073709551616 batches",
            ),
            ("from_seq=1;from_seq=2;to_seq=3", "from_seq: given twice"),
            ("from_seq=1;to_seq=2;limit=3", "unknown parameter \"limit\""),
            ("status;from_seq=1", "status: asked with from_seq"),
            ("status=yes", "status: takes no value"),
        ];
        for (q, want) in cases {
            let e = parse(q).unwrap_err();
            assert!(e.starts_with("buffer query: "), "{q}: {e}");
            assert!(e.contains(want), "{q}: {e} lacks {want}");
        }
    }
}
