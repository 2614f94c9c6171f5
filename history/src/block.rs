//! A block: a run of one sensor's batches, as received, with what is needed to correct them
//! again: the calibration version in force, the gateway's sequence verdict, and at the start of
//! some blocks a checkpoint of the correction state (opaque here: the gateway's to write and to
//! read).
//!
//! ```text
//! block   = version:u8 (1)  id_len:u8 id  flags:u8  [ck_len:varint ck]  n:u32  record*n
//! record  = rflags:u8  arrival  sequence  timestamp  [rate:f64]  [version:varint]
//!           [temperature:f32]  n_samples:varint  samples:12·n (3×f32 LE, as received)
//! ```
//!
//! The first record of a block carries its arrival number, sequence number and timestamp in
//! full (and always its rate and calibration version); each later one carries deltas from what
//! the previous record predicts (the next arrival, the next sequence number, the end of the
//! previous batch), zigzag-encoded, so a steady stream costs five bytes of header per batch.
//! `rflags`: bits 0–2 the verdict, bit 3 a temperature, bit 4 a rate, bit 5 a version.

use triax_protocol::SensorId;

use crate::varint::{put_i64, put_u64, Reader, Truncated};

const BLOCK_VERSION: u8 = 1;
const HAS_CHECKPOINT: u8 = 1;
const R_TEMPERATURE: u8 = 1 << 3;
const R_RATE: u8 = 1 << 4;
const R_VERSION: u8 = 1 << 5;
const R_VERDICT: u8 = 0b111;

/// How the gateway's sequence tracking judged a batch: what correction needs to replay it
/// (a gap or a restart resets the frequency detector; a gap or a duplicate flags the batch).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Verdict {
    /// In order, or the first batch of the sensor.
    InOrder,
    Gap,
    Duplicate,
    Restart,
    /// Fetched from the node's buffer after later batches (a backfill), next in its run.
    Late,
    /// Fetched from the node's buffer, with numbers missing before it in its run.
    LateGap,
}

impl Verdict {
    fn code(self) -> u8 {
        match self {
            Verdict::InOrder => 0,
            Verdict::Gap => 1,
            Verdict::Duplicate => 2,
            Verdict::Restart => 3,
            Verdict::Late => 4,
            Verdict::LateGap => 5,
        }
    }

    fn from_code(c: u8) -> Option<Verdict> {
        Some(match c {
            0 => Verdict::InOrder,
            1 => Verdict::Gap,
            2 => Verdict::Duplicate,
            3 => Verdict::Restart,
            4 => Verdict::Late,
            5 => Verdict::LateGap,
            _ => return None,
        })
    }
}

/// One kept batch, as the gateway received and judged it.
#[derive(Debug, Clone, PartialEq)]
pub struct Kept<S> {
    /// Gateway-wide order of arrival, increasing across restarts.
    pub arrival: u64,
    pub sequence: u64,
    pub timestamp_ns: i64,
    pub sample_rate_hz: f64,
    pub temperature_c: Option<f32>,
    /// Version of the record in force; 0 when the sensor was uncalibrated.
    pub calibration_version: u64,
    pub verdict: Verdict,
    /// The samples as received: 3 × f32 little-endian per sample.
    pub samples: S,
}

impl<S> Kept<S> {
    /// The same batch with `samples` in place of its own.
    pub fn with_samples<T>(&self, samples: T) -> Kept<T> {
        Kept {
            arrival: self.arrival,
            sequence: self.sequence,
            timestamp_ns: self.timestamp_ns,
            sample_rate_hz: self.sample_rate_hz,
            temperature_c: self.temperature_c,
            calibration_version: self.calibration_version,
            verdict: self.verdict,
            samples,
        }
    }
}

impl<S: AsRef<[u8]>> Kept<S> {
    pub fn n_samples(&self) -> usize {
        self.samples.as_ref().len() / 12
    }

    /// The same batch, borrowing its samples.
    pub fn borrowed(&self) -> Kept<&[u8]> {
        self.with_samples(self.samples.as_ref())
    }
}

/// Where a batch ends: the start of the next one if none was lost. Shared by the encoder and
/// the decoder, so the prediction is bit for bit the same on both sides.
fn end_ns(timestamp_ns: i64, n: usize, sample_rate_hz: f64) -> i64 {
    timestamp_ns.wrapping_add((n as f64 * 1e9 / sample_rate_hz) as i64)
}

/// What the previous record of a block lets the next one leave out.
#[derive(Debug, Clone, Copy)]
struct Prev {
    arrival: u64,
    sequence: u64,
    end_ns: i64,
    rate_bits: u64,
    version: u64,
}

/// Builds one block in memory, framed: room for the frame's header (length and CRC, filled in
/// by [`finish`](Self::finish)) comes first, so the finished frame is written as it is, with no
/// copy.
#[derive(Debug)]
pub struct BlockBuilder {
    buf: Vec<u8>,
    /// Where the record count goes (a fixed four bytes, filled in by `finish`).
    n_at: usize,
    n: u32,
    prev: Option<Prev>,
    pub summary: BlockSummary,
}

/// Bytes of a frame's header, before its block: the block's length and CRC-32.
pub const FRAME_HEADER: usize = 8;

/// What the index keeps of a block.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct BlockSummary {
    pub checkpoint: bool,
    pub n_records: u32,
    pub min_ts: i64,
    pub max_ts: i64,
    pub min_seq: u64,
    pub max_seq: u64,
    pub first_arrival: u64,
    pub last_arrival: u64,
}

impl BlockBuilder {
    /// Starts a block for `sensor`, with `checkpoint` (the correction state before its first
    /// batch) if given.
    pub fn new(sensor: &SensorId, checkpoint: Option<&[u8]>) -> BlockBuilder {
        BlockBuilder::in_buffer(Vec::new(), sensor, checkpoint)
    }

    /// As [`new`](Self::new), in a buffer whose memory is reused (its contents are dropped).
    pub fn in_buffer(
        mut buf: Vec<u8>,
        sensor: &SensorId,
        checkpoint: Option<&[u8]>,
    ) -> BlockBuilder {
        let id = sensor.as_str().as_bytes();
        buf.clear();
        // A second of a 100 Hz sensor's batches (1.2–1.4 KB with the headers) fits without
        // growing: a block that doubles to 2 KiB leaves its 1 KiB behind in the heap, and a
        // thousand sensors' worth of those cost the gateway a megabyte and a half (measured).
        buf.reserve(1536 + checkpoint.map_or(0, <[u8]>::len));
        buf.extend_from_slice(&[0; FRAME_HEADER]);
        buf.push(BLOCK_VERSION);
        // Ids are at most 64 bytes.
        buf.push(id.len() as u8);
        buf.extend_from_slice(id);
        match checkpoint {
            Some(ck) => {
                buf.push(HAS_CHECKPOINT);
                put_u64(&mut buf, ck.len() as u64);
                buf.extend_from_slice(ck);
            }
            None => buf.push(0),
        }
        let n_at = buf.len();
        buf.extend_from_slice(&[0; 4]);
        BlockBuilder {
            buf,
            n_at,
            n: 0,
            prev: None,
            summary: BlockSummary {
                checkpoint: checkpoint.is_some(),
                n_records: 0,
                min_ts: i64::MAX,
                max_ts: i64::MIN,
                min_seq: u64::MAX,
                max_seq: 0,
                first_arrival: 0,
                last_arrival: 0,
            },
        }
    }

    pub fn is_empty(&self) -> bool {
        self.n == 0
    }

    /// Bytes so far, frame header included.
    pub fn len(&self) -> usize {
        self.buf.len()
    }

    /// Appends one batch. `samples` must hold whole samples (a multiple of 12 bytes).
    pub fn push(&mut self, k: &Kept<&[u8]>) {
        debug_assert_eq!(k.samples.len() % 12, 0);
        let n = k.samples.len() / 12;
        let rate_bits = k.sample_rate_hz.to_bits();
        let mut rflags = k.verdict.code();
        if k.temperature_c.is_some() {
            rflags |= R_TEMPERATURE;
        }
        let records = &mut self.buf;
        match self.prev {
            None => {
                rflags |= R_RATE | R_VERSION;
                records.push(rflags);
                put_u64(records, k.arrival);
                put_u64(records, k.sequence);
                put_i64(records, k.timestamp_ns);
            }
            Some(p) => {
                if p.rate_bits != rate_bits {
                    rflags |= R_RATE;
                }
                if p.version != k.calibration_version {
                    rflags |= R_VERSION;
                }
                records.push(rflags);
                put_u64(records, k.arrival.wrapping_sub(p.arrival.wrapping_add(1)));
                put_i64(
                    records,
                    k.sequence.wrapping_sub(p.sequence.wrapping_add(1)) as i64,
                );
                put_i64(records, k.timestamp_ns.wrapping_sub(p.end_ns));
            }
        }
        if rflags & R_RATE != 0 {
            records.extend_from_slice(&k.sample_rate_hz.to_le_bytes());
        }
        if rflags & R_VERSION != 0 {
            put_u64(records, k.calibration_version);
        }
        if let Some(t) = k.temperature_c {
            records.extend_from_slice(&t.to_le_bytes());
        }
        put_u64(records, n as u64);
        records.extend_from_slice(k.samples);
        self.prev = Some(Prev {
            arrival: k.arrival,
            sequence: k.sequence,
            end_ns: end_ns(k.timestamp_ns, n, k.sample_rate_hz),
            rate_bits,
            version: k.calibration_version,
        });
        let s = &mut self.summary;
        if self.n == 0 {
            s.first_arrival = k.arrival;
        }
        s.last_arrival = k.arrival;
        s.min_ts = s.min_ts.min(k.timestamp_ns);
        s.max_ts = s.max_ts.max(k.timestamp_ns);
        s.min_seq = s.min_seq.min(k.sequence);
        s.max_seq = s.max_seq.max(k.sequence);
        self.n = self.n.saturating_add(1);
        s.n_records = self.n;
    }

    /// The framed block: its frame header (length, CRC-32 of the block) and the record count
    /// go where `new` left room for them.
    pub fn finish(mut self) -> (Vec<u8>, BlockSummary) {
        self.buf[self.n_at..self.n_at + 4].copy_from_slice(&self.n.to_le_bytes());
        let block = &self.buf[FRAME_HEADER..];
        // Blocks are bounded far below 4 GiB by the writer.
        let len = (block.len() as u32).to_le_bytes();
        let crc = crc32fast::hash(block).to_le_bytes();
        self.buf[..4].copy_from_slice(&len);
        self.buf[4..FRAME_HEADER].copy_from_slice(&crc);
        (self.buf, self.summary)
    }
}

/// Why a block could not be read.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum BlockError {
    #[error("block version {0} is not 1")]
    Version(u8),
    #[error("block names an invalid sensor id")]
    SensorId,
    #[error("unknown verdict code {0}")]
    Verdict(u8),
    #[error("record flags {0:#04x} have reserved bits set")]
    Flags(u8),
    #[error(transparent)]
    Truncated(#[from] Truncated),
    #[error("{0} bytes after the last record")]
    Trailing(usize),
}

/// A decoded block: its sensor, its checkpoint and its batches, borrowing the block's bytes.
#[derive(Debug, Clone, PartialEq)]
pub struct Block<'a> {
    pub sensor: SensorId,
    pub checkpoint: Option<&'a [u8]>,
    pub kept: Vec<Kept<&'a [u8]>>,
}

impl<'a> Block<'a> {
    pub fn decode(bytes: &'a [u8]) -> Result<Block<'a>, BlockError> {
        let mut r = Reader::new(bytes);
        let version = r.u8()?;
        if version != BLOCK_VERSION {
            return Err(BlockError::Version(version));
        }
        let id_len = usize::from(r.u8()?);
        let id = std::str::from_utf8(r.bytes(id_len)?).map_err(|_| BlockError::SensorId)?;
        let sensor = SensorId::new(id).map_err(|_| BlockError::SensorId)?;
        let flags = r.u8()?;
        if flags & !HAS_CHECKPOINT != 0 {
            return Err(BlockError::Flags(flags));
        }
        let checkpoint = if flags & HAS_CHECKPOINT != 0 {
            let len = r.u64()?;
            Some(r.bytes(usize::try_from(len).map_err(|_| Truncated { at: r.position() })?)?)
        } else {
            None
        };
        let n = u32::from_le_bytes(r.array()?);
        // Every record takes at least six bytes: a count past that is damage, not a size.
        let mut kept = Vec::with_capacity((n as usize).min(bytes.len() / 6));
        let mut prev: Option<Prev> = None;
        for _ in 0..n {
            let rflags = r.u8()?;
            if rflags & 0b1100_0000 != 0 {
                return Err(BlockError::Flags(rflags));
            }
            let verdict =
                Verdict::from_code(rflags & R_VERDICT).ok_or(BlockError::Verdict(rflags & 7))?;
            let (arrival, sequence, timestamp_ns) = match prev {
                None => (r.u64()?, r.u64()?, r.i64()?),
                Some(p) => (
                    p.arrival.wrapping_add(1).wrapping_add(r.u64()?),
                    p.sequence.wrapping_add(1).wrapping_add(r.i64()? as u64),
                    p.end_ns.wrapping_add(r.i64()?),
                ),
            };
            let rate_bits = match (rflags & R_RATE != 0, prev) {
                (true, _) => u64::from_le_bytes(r.array()?),
                (false, Some(p)) => p.rate_bits,
                (false, None) => return Err(BlockError::Flags(rflags)),
            };
            let version = match (rflags & R_VERSION != 0, prev) {
                (true, _) => r.u64()?,
                (false, Some(p)) => p.version,
                (false, None) => return Err(BlockError::Flags(rflags)),
            };
            let temperature_c = (rflags & R_TEMPERATURE != 0)
                .then(|| r.array().map(f32::from_le_bytes))
                .transpose()?;
            let n_samples = r.u64()?;
            let len = usize::try_from(n_samples)
                .ok()
                .and_then(|n| n.checked_mul(12))
                .ok_or(Truncated { at: r.position() })?;
            let samples = r.bytes(len)?;
            let sample_rate_hz = f64::from_bits(rate_bits);
            prev = Some(Prev {
                arrival,
                sequence,
                end_ns: end_ns(timestamp_ns, n_samples as usize, sample_rate_hz),
                rate_bits,
                version,
            });
            kept.push(Kept {
                arrival,
                sequence,
                timestamp_ns,
                sample_rate_hz,
                temperature_c,
                calibration_version: version,
                verdict,
                samples,
            });
        }
        if !r.is_empty() {
            return Err(BlockError::Trailing(bytes.len() - r.position()));
        }
        Ok(Block {
            sensor,
            checkpoint,
            kept,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn samples(n: usize, seed: u32) -> Vec<u8> {
        (0..n * 3)
            .flat_map(|i| (seed as f32 + i as f32 * 0.25).to_le_bytes())
            .collect()
    }

    #[test]
    fn a_steady_stream_costs_five_bytes_of_header_per_batch() {
        let id = SensorId::new("acc-01").unwrap();
        let mut b = BlockBuilder::new(&id, Some(b"state"));
        let s = samples(10, 1);
        for i in 0..100u64 {
            b.push(&Kept {
                arrival: 1000 + 2 * i,
                sequence: 7 + i,
                timestamp_ns: 1_800_000_000_000_000_000 + i as i64 * 100_000_000,
                sample_rate_hz: 100.0,
                temperature_c: None,
                calibration_version: 3,
                verdict: Verdict::InOrder,
                samples: &s,
            });
        }
        let (frame, summary) = b.finish();
        // Header of the first record: flags, arrival (2), sequence, timestamp (9), rate (8),
        // version, count; then five bytes a batch.
        let per_batch = (frame.len() - 100 * 120) as f64 / 100.0;
        assert!(per_batch < 5.6, "{per_batch} bytes of header per batch");
        let block = Block::decode(&frame[FRAME_HEADER..]).unwrap();
        assert_eq!(block.checkpoint, Some(&b"state"[..]));
        assert_eq!(block.kept.len(), 100);
        assert_eq!(block.kept[99].arrival, 1198);
        assert_eq!(block.kept[99].sequence, 106);
        assert_eq!(summary.min_seq, 7);
        assert_eq!(summary.max_seq, 106);
        assert_eq!(summary.last_arrival, 1198);
    }

    prop_compose! {
        fn kept()(arrival in any::<u64>(), sequence in any::<u64>(), timestamp_ns in any::<i64>(),
                  rate in prop_oneof![Just(100.0f64), Just(1e-300), Just(f64::MAX), 0.1f64..1e6],
                  temperature in proptest::option::of(any::<f32>()),
                  version in any::<u64>(), verdict in 0u8..4, n in 0usize..20, seed in any::<u32>())
            -> Kept<Vec<u8>> {
            Kept { arrival, sequence, timestamp_ns, sample_rate_hz: rate,
                   temperature_c: temperature, calibration_version: version,
                   verdict: Verdict::from_code(verdict).unwrap(), samples: samples(n, seed) }
        }
    }

    proptest! {
        #[test]
        fn any_batches_round_trip_bit_for_bit(all in proptest::collection::vec(kept(), 1..20),
                                              ck in proptest::option::of(proptest::collection::vec(any::<u8>(), 0..50))) {
            let id = SensorId::new("s").unwrap();
            let mut b = BlockBuilder::new(&id, ck.as_deref());
            for k in &all {
                b.push(&k.borrowed());
            }
            let (frame, _) = b.finish();
            let block = Block::decode(&frame[FRAME_HEADER..]).unwrap();
            prop_assert_eq!(block.checkpoint, ck.as_deref());
            prop_assert_eq!(block.kept.len(), all.len());
            for (got, want) in block.kept.iter().zip(&all) {
                prop_assert_eq!(got.arrival, want.arrival);
                prop_assert_eq!(got.sequence, want.sequence);
                prop_assert_eq!(got.timestamp_ns, want.timestamp_ns);
                prop_assert_eq!(got.sample_rate_hz.to_bits(), want.sample_rate_hz.to_bits());
                prop_assert_eq!(got.temperature_c.map(f32::to_bits), want.temperature_c.map(f32::to_bits));
                prop_assert_eq!(got.calibration_version, want.calibration_version);
                prop_assert_eq!(got.verdict, want.verdict);
                prop_assert_eq!(got.samples, &want.samples[..]);
            }
        }

        #[test]
        fn damaged_blocks_never_panic(bytes in proptest::collection::vec(any::<u8>(), 0..300)) {
            let _ = Block::decode(&bytes);
        }
    }
}
