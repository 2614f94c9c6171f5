//! The binary encoding of the high-rate streams: [`RawBatch`] and [`CorrectedBatch`].
//!
//! Both are little-endian, unpadded, and laid out byte by byte in PROTOCOL.md. Encode and
//! decode of each message sit side by side. Decoders never trust a length they have not checked
//! against the payload: a count that does not match, a truncated or oversized payload, an unknown
//! kind or format version is a [`DecodeError`], never a panic.
//!
//! The gateway's hot path uses the borrowed forms, [`RawBatchView`] to read samples straight from
//! the payload and [`CorrectedBatchWriter`] to append corrected samples to a reused buffer, so a
//! batch costs no allocation per sample.

use crate::keys::{IdError, SensorId, MAX_ID_LEN};

/// First two bytes of every binary payload.
pub const MAGIC: [u8; 2] = *b"TX";
/// The binary format version this build writes and reads.
pub const FORMAT_VERSION: u8 = 1;
/// Kind byte of a [`RawBatch`].
pub const KIND_RAW: u8 = 1;
/// Kind byte of a [`CorrectedBatch`].
pub const KIND_CORRECTED: u8 = 2;
/// Most samples one batch may carry (about 10 s at 1 kHz).
pub const MAX_SAMPLES: usize = 16_384;

/// Bytes of one raw sample: three `f32`.
pub const RAW_SAMPLE_BYTES: usize = 12;
/// Bytes of one corrected sample: six `f32` and a `u16`.
pub const CORRECTED_SAMPLE_BYTES: usize = 26;

/// Raw header flag: a temperature field follows the sample count.
const RAW_HAS_TEMPERATURE: u16 = 1;

/// Quality flags, per sample and per batch (the batch's flags are the union of its samples'
/// flags and the batch-level conditions). Bit values are part of the wire format.
pub mod flags {
    /// No calibration record for this sensor: values are raw outputs passed through, not m/s².
    pub const UNCALIBRATED: u16 = 1 << 0;
    /// The record in use is past its `valid_until`, or not yet at its `valid_from`.
    pub const CALIBRATION_EXPIRED: u16 = 1 << 1;
    /// |a| on some axis exceeds the record's calibrated amplitude.
    pub const OUTSIDE_AMPLITUDE: u16 = 1 << 2;
    /// The signal has content outside the record's calibrated frequency band.
    pub const OUTSIDE_FREQUENCY: u16 = 1 << 3;
    /// Sequence numbers skipped before this batch: samples were lost upstream.
    pub const SEQUENCE_GAP: u16 = 1 << 4;
    /// An output was NaN or infinite; the corrected value is NaN.
    pub const NON_FINITE_INPUT: u16 = 1 << 5;
    /// An output reached the sensor's full scale; the true value may be larger.
    pub const CLIPPED: u16 = 1 << 6;
    /// This batch repeats or precedes a sequence number already seen.
    pub const DUPLICATE: u16 = 1 << 7;
    /// The record corrects for temperature and the batch's temperature lies outside its
    /// calibrated range, or the batch carries none.
    pub const OUTSIDE_TEMPERATURE: u16 = 1 << 8;
    /// The sensor's calibration health checks found it `suspect` under the record in use: its
    /// values may be off by more than their uncertainty says, until a new record is in force.
    pub const CALIBRATION_SUSPECT: u16 = 1 << 9;
    /// The gateway fetched this batch from the node's buffer after a gap or an outage and
    /// publishes it after later ones: it fills a hole behind the live stream.
    pub const LATE: u16 = 1 << 10;
    /// Every defined bit. The gateway sets no other; a reader keeps a corrected batch that
    /// carries one (a flag defined after the reader was written) and treats it as any flag:
    /// the value is not clean (PROTOCOL.md §4).
    pub const ALL: u16 = (1 << 11) - 1;
    /// The flags that describe a batch, not its samples: set in the batch flags only.
    pub const BATCH_ONLY: u16 = SEQUENCE_GAP | DUPLICATE | LATE;

    /// Names of the set bits, for logs and reports.
    pub fn names(bits: u16) -> Vec<&'static str> {
        const NAMES: [&str; 11] = [
            "uncalibrated",
            "calibration_expired",
            "outside_amplitude",
            "outside_frequency",
            "sequence_gap",
            "non_finite_input",
            "clipped",
            "duplicate",
            "outside_temperature",
            "calibration_suspect",
            "late",
        ];
        (0..11)
            .filter(|i| bits & (1 << i) != 0)
            .map(|i| NAMES[i])
            .collect()
    }
}

/// Which calibration set produced a corrected batch.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Mode {
    /// No calibration applied (the sensor is uncalibrated).
    None = 0,
    /// The static set (quasi-static use, inclinometers).
    Static = 1,
    /// The dynamic set (vibration).
    Dynamic = 2,
    /// Static set on the low band, dynamic set on the rest.
    Split = 3,
}

impl Mode {
    fn from_byte(b: u8) -> Option<Mode> {
        Some(match b {
            0 => Mode::None,
            1 => Mode::Static,
            2 => Mode::Dynamic,
            3 => Mode::Split,
            _ => return None,
        })
    }
}

/// Why a binary payload was refused.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum DecodeError {
    #[error("payload is {len} bytes; the {field} needs {needed}")]
    Truncated {
        field: &'static str,
        needed: usize,
        len: usize,
    },
    #[error("payload does not start with the magic \"TX\" (found {found:02x?})")]
    BadMagic { found: [u8; 2] },
    #[error("message kind {found} where {expected} was expected")]
    WrongKind { expected: u8, found: u8 },
    #[error("format version {found} is not supported (this build reads {FORMAT_VERSION})")]
    UnsupportedVersion { found: u8 },
    #[error("sample count {n_samples} is outside 1..={MAX_SAMPLES}")]
    BadSampleCount { n_samples: u32 },
    #[error("{n_samples} samples need a {expected}-byte payload, this one has {len} bytes")]
    LengthMismatch {
        n_samples: u32,
        expected: usize,
        len: usize,
    },
    #[error("sensor id length {len} is outside 1..={MAX_ID_LEN}")]
    BadSensorIdLength { len: u8 },
    #[error("sensor id: {0}")]
    BadSensorId(#[from] IdError),
    #[error("sensor id is not UTF-8")]
    SensorIdNotUtf8,
    #[error("sample rate {0} Hz is not a positive finite number")]
    BadSampleRate(f64),
    #[error("unknown correction mode {0}")]
    BadMode(u8),
    #[error("reserved flag bits set in {0:#06x}")]
    ReservedFlags(u16),
    #[error("coverage factor {0} is not a positive finite number")]
    BadCoverageFactor(f32),
}

/// Header fields shared by raw and corrected batches.
#[derive(Debug, Clone, PartialEq)]
pub struct BatchHeader {
    pub sensor_id: SensorId,
    /// Increases by one per batch from a sensor node; a jump is a gap.
    pub sequence: u64,
    /// Time of the first sample, ns since the Unix epoch (UTC).
    pub timestamp_ns: i64,
    pub sample_rate_hz: f64,
}

/// Reads little-endian fields off the front of a payload, naming the field that ran short.
struct Reader<'a> {
    buf: &'a [u8],
    pos: usize,
}

impl<'a> Reader<'a> {
    fn take(&mut self, n: usize, field: &'static str) -> Result<&'a [u8], DecodeError> {
        let end = self.pos.checked_add(n).filter(|&e| e <= self.buf.len());
        match end {
            Some(end) => {
                let s = &self.buf[self.pos..end];
                self.pos = end;
                Ok(s)
            }
            None => Err(DecodeError::Truncated {
                field,
                needed: self.pos.saturating_add(n),
                len: self.buf.len(),
            }),
        }
    }
    fn array<const N: usize>(&mut self, field: &'static str) -> Result<[u8; N], DecodeError> {
        let mut a = [0u8; N];
        a.copy_from_slice(self.take(N, field)?);
        Ok(a)
    }
    fn u8(&mut self, field: &'static str) -> Result<u8, DecodeError> {
        Ok(self.array::<1>(field)?[0])
    }
    fn u16(&mut self, field: &'static str) -> Result<u16, DecodeError> {
        Ok(u16::from_le_bytes(self.array(field)?))
    }
    fn u32(&mut self, field: &'static str) -> Result<u32, DecodeError> {
        Ok(u32::from_le_bytes(self.array(field)?))
    }
    fn u64(&mut self, field: &'static str) -> Result<u64, DecodeError> {
        Ok(u64::from_le_bytes(self.array(field)?))
    }
    fn i64(&mut self, field: &'static str) -> Result<i64, DecodeError> {
        Ok(i64::from_le_bytes(self.array(field)?))
    }
    fn f32(&mut self, field: &'static str) -> Result<f32, DecodeError> {
        Ok(f32::from_le_bytes(self.array(field)?))
    }
    fn f64(&mut self, field: &'static str) -> Result<f64, DecodeError> {
        Ok(f64::from_le_bytes(self.array(field)?))
    }
}

/// Reads the common prefix: magic, kind, version, flags, header. Returns the header, the header
/// flags, the sample count and the reader positioned after the count.
fn read_prefix(
    payload: &[u8],
    expected_kind: u8,
) -> Result<(BatchHeader, u16, usize, Reader<'_>), DecodeError> {
    let mut r = Reader {
        buf: payload,
        pos: 0,
    };
    let magic = r.array::<2>("magic")?;
    if magic != MAGIC {
        return Err(DecodeError::BadMagic { found: magic });
    }
    let kind = r.u8("kind")?;
    if kind != expected_kind {
        return Err(DecodeError::WrongKind {
            expected: expected_kind,
            found: kind,
        });
    }
    let version = r.u8("format version")?;
    if version != FORMAT_VERSION {
        return Err(DecodeError::UnsupportedVersion { found: version });
    }
    let header_flags = r.u16("flags")?;
    let id_len = r.u8("sensor id length")?;
    if id_len == 0 || id_len as usize > MAX_ID_LEN {
        return Err(DecodeError::BadSensorIdLength { len: id_len });
    }
    let id_bytes = r.take(id_len as usize, "sensor id")?;
    let id = std::str::from_utf8(id_bytes).map_err(|_| DecodeError::SensorIdNotUtf8)?;
    let sensor_id = SensorId::new(id)?;
    let sequence = r.u64("sequence")?;
    let timestamp_ns = r.i64("timestamp")?;
    let sample_rate_hz = r.f64("sample rate")?;
    if !(sample_rate_hz.is_finite() && sample_rate_hz > 0.0) {
        return Err(DecodeError::BadSampleRate(sample_rate_hz));
    }
    let n_samples = r.u32("sample count")?;
    if n_samples == 0 || n_samples as usize > MAX_SAMPLES {
        return Err(DecodeError::BadSampleCount { n_samples });
    }
    let header = BatchHeader {
        sensor_id,
        sequence,
        timestamp_ns,
        sample_rate_hz,
    };
    Ok((header, header_flags, n_samples as usize, r))
}

fn write_prefix(out: &mut Vec<u8>, kind: u8, header_flags: u16, h: &BatchHeader, n: usize) {
    out.extend_from_slice(&MAGIC);
    out.push(kind);
    out.push(FORMAT_VERSION);
    out.extend_from_slice(&header_flags.to_le_bytes());
    // Ids are validated to at most MAX_ID_LEN (64) bytes, so the length fits a u8.
    out.push(h.sensor_id.as_str().len() as u8);
    out.extend_from_slice(h.sensor_id.as_str().as_bytes());
    out.extend_from_slice(&h.sequence.to_le_bytes());
    out.extend_from_slice(&h.timestamp_ns.to_le_bytes());
    out.extend_from_slice(&h.sample_rate_hz.to_le_bytes());
    out.extend_from_slice(&(n as u32).to_le_bytes());
}

fn check_len(n_samples: usize, expected: usize, len: usize) -> Result<(), DecodeError> {
    if expected != len {
        return Err(DecodeError::LengthMismatch {
            n_samples: n_samples as u32,
            expected,
            len,
        });
    }
    Ok(())
}

/// Three consecutive f32 (a raw sample, a corrected acceleration or its uncertainty) from
/// `offset`.
#[inline(always)]
fn f32x3_at(bytes: &[u8], offset: usize) -> [f32; 3] {
    [
        f32_at(bytes, offset),
        f32_at(bytes, offset + 4),
        f32_at(bytes, offset + 8),
    ]
}

#[inline(always)]
fn f32_at(bytes: &[u8], offset: usize) -> f32 {
    f32::from_le_bytes([
        bytes[offset],
        bytes[offset + 1],
        bytes[offset + 2],
        bytes[offset + 3],
    ])
}

/// One batch of sensor outputs, as a sensor node publishes it.
#[derive(Debug, Clone, PartialEq)]
pub struct RawBatch {
    pub header: BatchHeader,
    /// Sensor temperature during the batch, if the node measures it.
    pub temperature_c: Option<f32>,
    /// Three-axis outputs in the sensor's output unit (the record's `output_unit`).
    pub samples: Vec<[f32; 3]>,
}

impl RawBatch {
    /// Appends the encoded batch to `out`.
    ///
    /// # Panics
    /// If `samples` is empty or longer than [`MAX_SAMPLES`]: a programming error of the caller,
    /// which owns the batch size.
    pub fn encode_into(&self, out: &mut Vec<u8>) {
        let n = self.samples.len();
        assert!(
            (1..=MAX_SAMPLES).contains(&n),
            "a raw batch holds 1..={MAX_SAMPLES} samples, not {n}"
        );
        let header_flags = if self.temperature_c.is_some() {
            RAW_HAS_TEMPERATURE
        } else {
            0
        };
        out.reserve(raw_len(
            self.header.sensor_id.as_str().len(),
            n,
            header_flags,
        ));
        write_prefix(out, KIND_RAW, header_flags, &self.header, n);
        if let Some(t) = self.temperature_c {
            out.extend_from_slice(&t.to_le_bytes());
        }
        for s in &self.samples {
            for v in s {
                out.extend_from_slice(&v.to_le_bytes());
            }
        }
    }

    pub fn encode(&self) -> Vec<u8> {
        let mut out = Vec::new();
        self.encode_into(&mut out);
        out
    }

    pub fn decode(payload: &[u8]) -> Result<RawBatch, DecodeError> {
        let view = RawBatchView::parse(payload)?;
        Ok(RawBatch {
            header: view.header.clone(),
            temperature_c: view.temperature_c,
            samples: view.samples().collect(),
        })
    }
}

fn raw_len(id_len: usize, n: usize, header_flags: u16) -> usize {
    let temp = if header_flags & RAW_HAS_TEMPERATURE != 0 {
        4
    } else {
        0
    };
    prefix_len(id_len) + temp + n * RAW_SAMPLE_BYTES
}

/// Bytes before the first field that follows the sample count.
pub const fn prefix_len(id_len: usize) -> usize {
    2 + 1 + 1 + 2 + 1 + id_len + 8 + 8 + 8 + 4
}

/// Most bytes a valid raw batch has: the longest id, a temperature and [`MAX_SAMPLES`]
/// samples. A receiver may refuse a longer payload before reading or copying it.
pub const MAX_RAW_BATCH_BYTES: usize = prefix_len(MAX_ID_LEN) + 4 + MAX_SAMPLES * RAW_SAMPLE_BYTES;

/// A raw batch read in place: the header is parsed, the samples stay in the payload.
#[derive(Debug, Clone)]
pub struct RawBatchView<'a> {
    pub header: BatchHeader,
    pub temperature_c: Option<f32>,
    samples: &'a [u8],
}

impl<'a> RawBatchView<'a> {
    pub fn parse(payload: &'a [u8]) -> Result<Self, DecodeError> {
        let (header, header_flags, n, mut r) = read_prefix(payload, KIND_RAW)?;
        if header_flags & !RAW_HAS_TEMPERATURE != 0 {
            return Err(DecodeError::ReservedFlags(header_flags));
        }
        let expected = raw_len(header.sensor_id.as_str().len(), n, header_flags);
        check_len(n, expected, payload.len())?;
        let temperature_c = if header_flags & RAW_HAS_TEMPERATURE != 0 {
            Some(r.f32("temperature")?)
        } else {
            None
        };
        let samples = r.take(n * RAW_SAMPLE_BYTES, "samples")?;
        Ok(RawBatchView {
            header,
            temperature_c,
            samples,
        })
    }

    pub fn len(&self) -> usize {
        self.samples.len() / RAW_SAMPLE_BYTES
    }

    pub fn is_empty(&self) -> bool {
        self.samples.is_empty()
    }

    /// The samples as they are in the payload: 12 bytes (3 × f32 little-endian) each.
    pub fn sample_bytes(&self) -> &'a [u8] {
        self.samples
    }

    /// The view of a batch kept in parts (a header and its samples as [`Self::sample_bytes`]
    /// gave them), without encoding it: the same checks as [`Self::parse`] on what the parts
    /// can get wrong.
    pub fn from_parts(
        header: BatchHeader,
        temperature_c: Option<f32>,
        samples: &'a [u8],
    ) -> Result<Self, DecodeError> {
        let n = samples.len() / RAW_SAMPLE_BYTES;
        if !(1..=MAX_SAMPLES).contains(&n) {
            return Err(DecodeError::BadSampleCount {
                n_samples: n.min(u32::MAX as usize) as u32,
            });
        }
        check_len(n, n * RAW_SAMPLE_BYTES, samples.len())?;
        if !(header.sample_rate_hz.is_finite() && header.sample_rate_hz > 0.0) {
            return Err(DecodeError::BadSampleRate(header.sample_rate_hz));
        }
        Ok(RawBatchView {
            header,
            temperature_c,
            samples,
        })
    }

    /// Sample `i` (`i < len()`).
    #[inline]
    pub fn sample(&self, i: usize) -> [f32; 3] {
        let o = i * RAW_SAMPLE_BYTES;
        f32x3_at(&self.samples[o..o + RAW_SAMPLE_BYTES], 0)
    }

    /// The samples in order.
    pub fn samples(&self) -> impl ExactSizeIterator<Item = [f32; 3]> + '_ {
        self.samples
            .chunks_exact(RAW_SAMPLE_BYTES)
            .map(|record| f32x3_at(record, 0))
    }

    /// Replaces the contents of `out` with the samples widened to f64.
    ///
    /// For the gateway's sample path: one call per batch with the loop compiled here, where
    /// whole-record chunks leave no bounds to check, instead of a call across crates per sample.
    /// Not written over [`Self::samples`]: that version measured 40 % slower on the whole batch
    /// path (its mapping function was not inlined into the loop).
    pub fn samples_f64_into(&self, out: &mut Vec<[f64; 3]>) {
        out.clear();
        out.extend(
            self.samples
                .chunks_exact(RAW_SAMPLE_BYTES)
                .map(|record| f32x3_at(record, 0).map(f64::from)),
        );
    }
}

/// Fields of a corrected batch that follow the sample count.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CorrectionInfo {
    /// Version of the calibration record used; 0 when uncalibrated.
    pub calibration_version: u64,
    pub mode: Mode,
    /// The k by which to multiply a standard uncertainty for an expanded one (≈95 % at k = 2).
    pub coverage_factor: f32,
}

/// One corrected sample.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CorrectedSample {
    /// Specific force in m/s² (raw outputs passed through when uncalibrated).
    pub accel_mps2: [f32; 3],
    /// Standard uncertainty (k = 1) per axis, m/s²; NaN when uncalibrated.
    pub uncertainty_mps2: [f32; 3],
    /// [`flags`] bits of this sample.
    pub flags: u16,
}

/// One batch of corrected samples, as the gateway publishes it.
#[derive(Debug, Clone, PartialEq)]
pub struct CorrectedBatch {
    pub header: BatchHeader,
    /// Union of the samples' flags and the batch-level conditions.
    pub batch_flags: u16,
    pub info: CorrectionInfo,
    pub samples: Vec<CorrectedSample>,
}

/// Length of a corrected batch with an id of `id_len` bytes and `n` samples.
pub fn corrected_len(id_len: usize, n: usize) -> usize {
    prefix_len(id_len) + 8 + 1 + 1 + 4 + n * CORRECTED_SAMPLE_BYTES
}

impl CorrectedBatch {
    /// Sample `i`'s flags as a row of a table or a sample of a channel should carry them: its
    /// own, plus the batch-only flags on the batch's first sample, where what they describe
    /// (a gap before the batch, a repeated batch) begins. The batch flags ORed into every row
    /// would mark good samples bad.
    pub fn sample_flags(&self, i: usize) -> u16 {
        let own = self.samples.get(i).map_or(0, |s| s.flags);
        if i == 0 {
            own | (self.batch_flags & flags::BATCH_ONLY)
        } else {
            own
        }
    }

    pub fn encode(&self) -> Vec<u8> {
        let mut out = Vec::new();
        let mut w =
            CorrectedBatchWriter::begin(&mut out, &self.header, self.info, self.samples.len());
        for s in &self.samples {
            w.push(s);
        }
        w.finish(self.batch_flags);
        out
    }

    pub fn decode(payload: &[u8]) -> Result<CorrectedBatch, DecodeError> {
        // Flags not defined yet are kept, not refused: a new flag must break no reader.
        let (header, batch_flags, n, mut r) = read_prefix(payload, KIND_CORRECTED)?;
        check_len(
            n,
            corrected_len(header.sensor_id.as_str().len(), n),
            payload.len(),
        )?;
        let calibration_version = r.u64("calibration version")?;
        let mode_byte = r.u8("mode")?;
        let mode = Mode::from_byte(mode_byte).ok_or(DecodeError::BadMode(mode_byte))?;
        let _reserved = r.u8("reserved")?;
        let coverage_factor = r.f32("coverage factor")?;
        if !(coverage_factor.is_finite() && coverage_factor > 0.0) {
            return Err(DecodeError::BadCoverageFactor(coverage_factor));
        }
        let records = r.take(n * CORRECTED_SAMPLE_BYTES, "samples")?;
        let mut samples = Vec::with_capacity(n);
        for rec in records.chunks_exact(CORRECTED_SAMPLE_BYTES) {
            let flags = u16::from_le_bytes([rec[24], rec[25]]);
            samples.push(CorrectedSample {
                accel_mps2: f32x3_at(rec, 0),
                uncertainty_mps2: f32x3_at(rec, 12),
                flags,
            });
        }
        Ok(CorrectedBatch {
            header,
            batch_flags,
            info: CorrectionInfo {
                calibration_version,
                mode,
                coverage_factor,
            },
            samples,
        })
    }
}

/// Writes a corrected batch into a caller-owned buffer, one sample at a time, so the gateway can
/// reuse one buffer per sensor and allocate nothing per sample.
pub struct CorrectedBatchWriter<'a> {
    out: &'a mut Vec<u8>,
    start: usize,
    n_expected: usize,
    n_written: usize,
}

impl<'a> CorrectedBatchWriter<'a> {
    /// Appends the header of a batch of `n_samples` to `out`.
    ///
    /// # Panics
    /// If `n_samples` is 0 or above [`MAX_SAMPLES`] (callers take `n_samples` from a decoded
    /// raw batch, which is already within bounds).
    pub fn begin(
        out: &'a mut Vec<u8>,
        header: &BatchHeader,
        info: CorrectionInfo,
        n_samples: usize,
    ) -> Self {
        assert!(
            (1..=MAX_SAMPLES).contains(&n_samples),
            "a corrected batch holds 1..={MAX_SAMPLES} samples, not {n_samples}"
        );
        let start = out.len();
        out.reserve(corrected_len(header.sensor_id.as_str().len(), n_samples));
        write_prefix(out, KIND_CORRECTED, 0, header, n_samples);
        out.extend_from_slice(&info.calibration_version.to_le_bytes());
        out.push(info.mode as u8);
        out.push(0);
        out.extend_from_slice(&info.coverage_factor.to_le_bytes());
        CorrectedBatchWriter {
            out,
            start,
            n_expected: n_samples,
            n_written: 0,
        }
    }

    #[inline]
    pub fn push(&mut self, s: &CorrectedSample) {
        let mut rec = [0u8; CORRECTED_SAMPLE_BYTES];
        for (i, v) in s.accel_mps2.iter().chain(&s.uncertainty_mps2).enumerate() {
            rec[i * 4..i * 4 + 4].copy_from_slice(&v.to_le_bytes());
        }
        rec[24..26].copy_from_slice(&s.flags.to_le_bytes());
        self.out.extend_from_slice(&rec);
        self.n_written += 1;
    }

    /// Writes the batch flags into the header.
    ///
    /// # Panics
    /// If fewer or more samples were pushed than announced in [`begin`](Self::begin).
    pub fn finish(self, batch_flags: u16) {
        assert_eq!(
            self.n_written, self.n_expected,
            "corrected batch announced {} samples",
            self.n_expected
        );
        // The flags sit at bytes 4..6 of the message, after magic, kind and version.
        self.out[self.start + 4..self.start + 6].copy_from_slice(&batch_flags.to_le_bytes());
    }
}

/// Small, valid batches for tests, simulations and benches across the workspace.
pub mod sample {
    use super::*;

    /// A batch as the gateway publishes a clean one corrected in `dynamic` mode with record
    /// version 1 and k = 2: no batch flag.
    pub fn dynamic(
        sensor_id: SensorId,
        sequence: u64,
        timestamp_ns: i64,
        sample_rate_hz: f64,
        samples: Vec<CorrectedSample>,
    ) -> CorrectedBatch {
        CorrectedBatch {
            header: BatchHeader {
                sensor_id,
                sequence,
                timestamp_ns,
                sample_rate_hz,
            },
            batch_flags: 0,
            info: CorrectionInfo {
                calibration_version: 1,
                mode: Mode::Dynamic,
                coverage_factor: 2.0,
            },
            samples,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn header() -> BatchHeader {
        BatchHeader {
            sensor_id: SensorId::new("acc-7").unwrap(),
            sequence: 42,
            timestamp_ns: 1_700_000_000_123_456_789,
            sample_rate_hz: 100.0,
        }
    }

    #[test]
    fn raw_round_trip_with_and_without_temperature() {
        for temperature_c in [None, Some(21.5f32)] {
            let b = RawBatch {
                header: header(),
                temperature_c,
                samples: vec![[1.0, -2.0, 3.5], [f32::NAN, 0.0, 1e-3]],
            };
            let bytes = b.encode();
            assert_eq!(
                bytes.len(),
                prefix_len(5) + 24 + temperature_c.map_or(0, |_| 4)
            );
            let back = RawBatch::decode(&bytes).unwrap();
            assert_eq!(back.header, b.header);
            assert_eq!(back.temperature_c, temperature_c);
            assert_eq!(back.samples[0], b.samples[0]);
            assert!(back.samples[1][0].is_nan(), "NaN survives to be flagged");
        }
    }

    #[test]
    fn corrected_round_trip() {
        let b = CorrectedBatch {
            header: header(),
            batch_flags: flags::SEQUENCE_GAP | flags::CLIPPED,
            info: CorrectionInfo {
                calibration_version: 9,
                mode: Mode::Split,
                coverage_factor: 2.0,
            },
            samples: vec![
                CorrectedSample {
                    accel_mps2: [0.1, 0.2, 9.8],
                    uncertainty_mps2: [0.01, 0.02, 0.03],
                    flags: 0,
                },
                CorrectedSample {
                    accel_mps2: [0.0, 0.0, 20.0],
                    uncertainty_mps2: [0.01, 0.02, 0.03],
                    flags: flags::CLIPPED,
                },
            ],
        };
        let bytes = b.encode();
        assert_eq!(bytes.len(), corrected_len(5, 2));
        assert_eq!(CorrectedBatch::decode(&bytes).unwrap(), b);
    }

    #[test]
    fn flags_defined_later_are_kept_by_a_reader() {
        let later = 1 << 11;
        let b = CorrectedBatch {
            header: header(),
            batch_flags: later | flags::LATE,
            info: CorrectionInfo {
                calibration_version: 1,
                mode: Mode::Dynamic,
                coverage_factor: 2.0,
            },
            samples: vec![CorrectedSample {
                accel_mps2: [0.1, 0.2, 9.8],
                uncertainty_mps2: [0.01, 0.02, 0.03],
                flags: 1 << 15,
            }],
        };
        assert_eq!(CorrectedBatch::decode(&b.encode()).unwrap(), b);
        assert_eq!(flags::names(later | flags::LATE), vec!["late"]);
    }

    #[test]
    fn the_largest_raw_batch_is_max_raw_batch_bytes_long() {
        let b = RawBatch {
            header: BatchHeader {
                sensor_id: SensorId::new("x".repeat(MAX_ID_LEN)).unwrap(),
                ..header()
            },
            temperature_c: Some(20.0),
            samples: vec![[1.0, 2.0, 3.0]; MAX_SAMPLES],
        };
        let bytes = b.encode();
        assert_eq!(bytes.len(), MAX_RAW_BATCH_BYTES);
        assert!(RawBatch::decode(&bytes).is_ok());
    }

    #[test]
    fn every_truncation_is_an_error() {
        let b = RawBatch {
            header: header(),
            temperature_c: Some(3.0),
            samples: vec![[1.0, 2.0, 3.0]; 3],
        };
        let bytes = b.encode();
        for cut in 0..bytes.len() {
            let e = RawBatch::decode(&bytes[..cut]).unwrap_err();
            assert!(
                matches!(
                    e,
                    DecodeError::Truncated { .. } | DecodeError::LengthMismatch { .. }
                ),
                "cut at {cut}: {e}"
            );
        }
        let mut long = bytes.clone();
        long.push(0);
        assert!(matches!(
            RawBatch::decode(&long),
            Err(DecodeError::LengthMismatch { .. })
        ));
    }

    #[test]
    fn refuses_unknown_version_kind_and_bad_counts() {
        let bytes = RawBatch {
            header: header(),
            temperature_c: None,
            samples: vec![[0.0; 3]],
        }
        .encode();
        let mut v2 = bytes.clone();
        v2[3] = 2;
        assert_eq!(
            RawBatch::decode(&v2),
            Err(DecodeError::UnsupportedVersion { found: 2 })
        );
        assert!(matches!(
            CorrectedBatch::decode(&bytes),
            Err(DecodeError::WrongKind {
                expected: 2,
                found: 1
            })
        ));
        // Sample count is the u32 right before the samples.
        let count_at = prefix_len(5) - 4;
        let mut zero = bytes.clone();
        zero[count_at..count_at + 4].copy_from_slice(&0u32.to_le_bytes());
        assert_eq!(
            RawBatch::decode(&zero),
            Err(DecodeError::BadSampleCount { n_samples: 0 })
        );
        let mut huge = bytes.clone();
        huge[count_at..count_at + 4].copy_from_slice(&u32::MAX.to_le_bytes());
        assert!(matches!(
            RawBatch::decode(&huge),
            Err(DecodeError::BadSampleCount { .. })
        ));
        let mut two = bytes;
        two[count_at..count_at + 4].copy_from_slice(&2u32.to_le_bytes());
        assert!(matches!(
            RawBatch::decode(&two),
            Err(DecodeError::LengthMismatch { n_samples: 2, .. })
        ));
    }

    #[test]
    fn flag_names() {
        assert_eq!(
            flags::names(flags::UNCALIBRATED | flags::DUPLICATE),
            ["uncalibrated", "duplicate"]
        );
    }
}
