//! miniSEED 2 records and an SDS tree: what seismology's tools (ObsPy, SeisComP) read natively.
//!
//! Each corrected batch becomes samples on nine channels per sensor (see [`channels`]): the
//! three axes in m/s² at location `00`, their standard uncertainties (k = 1) in m/s² at location
//! `U0`, and the per-sample quality flags (PROTOCOL.md §2.3, as integers) at location `Q0`.
//! Records are 512 bytes, big-endian, one channel each, with blockettes 1000 (encoding, word
//! order, length) and 1001 (microseconds); values are IEEE float32 (encoding 4), which keeps the
//! corrected stream's f32 values exactly, and the flags int32 (encoding 3).
//!
//! A record holds consecutive samples of one batch run: a new record starts when the next
//! sample is not where the last one's period says (a gap, a duplicate, a new run), when the
//! calibration version changes, or when the record is full. Its header says what miniSEED 2
//! can say of the flags in its samples: the data-quality byte sets bit 1 (digitizer clipping)
//! for `clipped`, bit 3 (glitches) for `non_finite_input`, bit 4 (missing or padded data) for
//! `sequence_gap`, bit 7 (time tag questionable) for `duplicate`; the quality indicator is `Q`
//! when any sample carries a flag, `D` otherwise. Everything else is in the `Q0` channel.
//!
//! Files follow SDS: `<root>/<year>/<net>/<sta>/<cha>.D/<net>.<sta>.<loc>.<cha>.D.<year>.<day>`,
//! split at UTC midnight; records are appended, so exporting consecutive time ranges into one
//! tree adds to the day files.

use std::collections::BTreeMap;
use std::io::Write;
use std::path::{Path, PathBuf};

use triax_protocol::batch::{flags, CorrectedBatch};
use triax_protocol::SensorId;

/// Bytes per record: 2⁹.
pub const RECORD_BYTES: usize = 512;
const RECORD_EXPONENT: u8 = 9;
/// Fixed header, blockette 1000 and blockette 1001, then the data from here.
const DATA_OFFSET: usize = 64;
/// Samples of four bytes per record.
pub const SAMPLES_PER_RECORD: usize = (RECORD_BYTES - DATA_OFFSET) / 4;

/// Why an export cannot be made.
#[derive(Debug, thiserror::Error)]
pub enum MseedError {
    #[error("sensor {sensor}: its station code {station:?} is also {other}'s; give each a station with --station SENSOR=CODE")]
    StationClash {
        sensor: String,
        other: String,
        station: String,
    },
    #[error("--station {0:?}: a station code is 1 to 5 letters or digits")]
    BadStation(String),
    #[error("sensor {sensor}: its id has no letter or digit to make a station code of; give it one with --station SENSOR=CODE")]
    NoStation { sensor: String },
    #[error("--network {0:?}: a network code is 1 or 2 letters or digits")]
    BadNetwork(String),
    #[error("sensor {sensor}: a sample rate of {rate_hz} Hz cannot be written as miniSEED 2's factor and multiplier")]
    SampleRate { sensor: String, rate_hz: f64 },
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        source: std::io::Error,
    },
}

/// One channel of a sensor: location, channel code and what it carries.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Channel {
    pub location: &'static str,
    /// Orientation code's axis: 0 = x, 1 = y, 2 = z.
    pub axis: usize,
    pub kind: ChannelKind,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ChannelKind {
    AccelerationMps2,
    UncertaintyMps2,
    Flags,
}

/// Location codes of the three kinds.
pub const DATA_LOCATION: &str = "00";
pub const UNCERTAINTY_LOCATION: &str = "U0";
pub const FLAGS_LOCATION: &str = "Q0";

/// The nine channels of a sensor, in the order the axes come: data, uncertainty, flags.
pub fn channels() -> [Channel; 9] {
    let kinds = [
        (DATA_LOCATION, ChannelKind::AccelerationMps2),
        (UNCERTAINTY_LOCATION, ChannelKind::UncertaintyMps2),
        (FLAGS_LOCATION, ChannelKind::Flags),
    ];
    std::array::from_fn(|i| Channel {
        location: kinds[i / 3].0,
        axis: i % 3,
        kind: kinds[i / 3].1,
    })
}

/// FDSN channel code at `sample_rate_hz`: band code from the rate (a short-period band for an
/// accelerometer, whose corner is not long-period), `N` for accelerometer, and `1`, `2`, `3`
/// for the sensor's own x, y, z (orthogonal, not geographic: the orientation is the mounting's).
pub fn channel_code(sample_rate_hz: f64, axis: usize) -> String {
    let band = match sample_rate_hz {
        r if r >= 1000.0 => 'G',
        r if r >= 250.0 => 'D',
        r if r >= 80.0 => 'E',
        r if r >= 10.0 => 'S',
        r if r > 1.0 => 'M',
        r if r > 0.1 => 'L',
        _ => 'V',
    };
    format!("{band}N{}", axis + 1)
}

/// The default station code of a sensor: its letters and digits, upper case, at most five.
pub fn default_station(sensor: &SensorId) -> String {
    sensor
        .as_str()
        .chars()
        .filter(char::is_ascii_alphanumeric)
        .map(|c| c.to_ascii_uppercase())
        .take(5)
        .collect()
}

fn valid_code(code: &str, max: usize) -> bool {
    !code.is_empty() && code.len() <= max && code.chars().all(|c| c.is_ascii_alphanumeric())
}

/// miniSEED 2's sample rate factor and multiplier for a rate, exactly.
fn rate_factor(rate_hz: f64) -> Option<(i16, i16)> {
    if rate_hz >= 1.0 && rate_hz.fract() == 0.0 && rate_hz <= 32767.0 {
        return Some((rate_hz as i16, 1));
    }
    let period = 1.0 / rate_hz;
    if period.fract() == 0.0 && period <= 32767.0 {
        return Some((-(period as i16), 1));
    }
    (1..=10_000i32).find_map(|k| {
        let f = rate_hz * f64::from(k);
        (f.fract().abs() < 1e-9 && f <= 32767.0).then(|| (f.round() as i16, -(k as i16)))
    })
}

/// Samples waiting to become a record.
#[derive(Debug, Default)]
struct Pending {
    start_ns: i64,
    period_ns: f64,
    version: u64,
    factor: (i16, i16),
    values: Vec<[u8; 4]>,
    /// Each sample's flags, for its record's header.
    flags: Vec<u16>,
}

/// Where each channel's samples go, and the records written so far.
pub struct SdsWriter {
    root: PathBuf,
    network: String,
    stations: BTreeMap<SensorId, String>,
    overrides: BTreeMap<String, String>,
    pending: BTreeMap<(String, usize), Pending>,
    sequence: u32,
    /// Records written per file; `finish` hands them over.
    records: BTreeMap<PathBuf, usize>,
}

impl SdsWriter {
    /// A writer into `root`, with `network` and per-sensor station overrides.
    pub fn new(
        root: &Path,
        network: &str,
        overrides: BTreeMap<String, String>,
    ) -> Result<SdsWriter, MseedError> {
        if !valid_code(network, 2) {
            return Err(MseedError::BadNetwork(network.to_string()));
        }
        if let Some(bad) = overrides.values().find(|s| !valid_code(s, 5)) {
            return Err(MseedError::BadStation(bad.clone()));
        }
        Ok(SdsWriter {
            root: root.to_path_buf(),
            network: network.to_ascii_uppercase(),
            stations: BTreeMap::new(),
            overrides: overrides
                .into_iter()
                .map(|(k, v)| (k, v.to_ascii_uppercase()))
                .collect(),
            pending: BTreeMap::new(),
            sequence: 0,
            records: BTreeMap::new(),
        })
    }

    /// The station code of `sensor`, refusing one that another sensor already has.
    pub fn station(&mut self, sensor: &SensorId) -> Result<String, MseedError> {
        if let Some(s) = self.stations.get(sensor) {
            return Ok(s.clone());
        }
        let code = self
            .overrides
            .get(sensor.as_str())
            .cloned()
            .unwrap_or_else(|| default_station(sensor));
        if !valid_code(&code, 5) {
            return Err(MseedError::NoStation {
                sensor: sensor.to_string(),
            });
        }
        if let Some((other, _)) = self.stations.iter().find(|(_, s)| **s == code) {
            return Err(MseedError::StationClash {
                sensor: sensor.to_string(),
                other: other.to_string(),
                station: code,
            });
        }
        self.stations.insert(sensor.clone(), code.clone());
        Ok(code)
    }

    /// The stations assigned so far.
    pub fn stations(&self) -> &BTreeMap<SensorId, String> {
        &self.stations
    }

    /// Adds a batch's samples to its sensor's nine channels.
    pub fn push(&mut self, batch: &CorrectedBatch) -> Result<(), MseedError> {
        let h = &batch.header;
        let station = self.station(&h.sensor_id)?;
        let factor = rate_factor(h.sample_rate_hz).ok_or_else(|| MseedError::SampleRate {
            sensor: h.sensor_id.to_string(),
            rate_hz: h.sample_rate_hz,
        })?;
        let period_ns = 1e9 / h.sample_rate_hz;
        let version = batch.info.calibration_version;
        for (c, channel) in channels().iter().enumerate() {
            let key = (station.clone(), c);
            let continues = self.pending.get(&key).is_some_and(|p| {
                let expected = p.start_ns as f64 + p.values.len() as f64 * p.period_ns;
                p.version == version
                    && p.factor == factor
                    && (h.timestamp_ns as f64 - expected).abs() < 0.5 * period_ns
            });
            if !continues {
                self.flush(&key, h.sample_rate_hz, true)?;
            }
            for (i, s) in batch.samples.iter().enumerate() {
                let p = self.pending.entry(key.clone()).or_default();
                if p.values.is_empty() {
                    p.start_ns = h
                        .timestamp_ns
                        .saturating_add((i as f64 * period_ns).round() as i64);
                    p.period_ns = period_ns;
                    p.version = version;
                    p.factor = factor;
                }
                // A batch-only flag (a gap before it, a duplicate) marks its first sample.
                let batch_only = batch.batch_flags & (flags::SEQUENCE_GAP | flags::DUPLICATE);
                let sample_flags = s.flags | if i == 0 { batch_only } else { 0 };
                p.flags.push(sample_flags);
                p.values.push(match channel.kind {
                    ChannelKind::AccelerationMps2 => s.accel_mps2[channel.axis].to_be_bytes(),
                    ChannelKind::UncertaintyMps2 => s.uncertainty_mps2[channel.axis].to_be_bytes(),
                    ChannelKind::Flags => i32::from(sample_flags).to_be_bytes(),
                });
                self.flush(&key, h.sample_rate_hz, false)?;
            }
        }
        Ok(())
    }

    /// Writes every partial record.
    pub fn finish(mut self) -> Result<BTreeMap<PathBuf, usize>, MseedError> {
        let keys: Vec<_> = self.pending.keys().cloned().collect();
        for key in keys {
            let rate = self
                .pending
                .get(&key)
                .map(|p| 1e9 / p.period_ns)
                .unwrap_or(1.0);
            self.flush(&key, rate, true)?;
        }
        Ok(self.records)
    }

    /// Writes `key`'s pending samples as records, never across UTC midnight (SDS files are per
    /// day): every one of them when `all`, otherwise only full records and those a midnight
    /// closes.
    fn flush(&mut self, key: &(String, usize), rate_hz: f64, all: bool) -> Result<(), MseedError> {
        const DAY_NS: i64 = 86_400_000_000_000;
        loop {
            let Some(p) = self.pending.get_mut(key) else {
                return Ok(());
            };
            // In i128: a timestamp near the end of i64's range has no midnight after it there.
            let next_midnight =
                (i128::from(p.start_ns).div_euclid(DAY_NS.into()) + 1) * i128::from(DAY_NS);
            let fit = ((next_midnight - i128::from(p.start_ns)) as f64 / p.period_ns)
                .ceil()
                .max(1.0) as usize;
            let closed = p.values.len() >= SAMPLES_PER_RECORD.min(fit);
            if p.values.is_empty() || !(all || closed) {
                return Ok(());
            }
            let take = p.values.len().min(fit).min(SAMPLES_PER_RECORD);
            let values: Vec<[u8; 4]> = p.values.drain(..take).collect();
            let flag_bits = p.flags.drain(..take).fold(0, |a, f| a | f);
            let start_ns = p.start_ns;
            let factor = p.factor;
            p.start_ns = p
                .start_ns
                .saturating_add((take as f64 * p.period_ns).round() as i64);
            let channel = channels()[key.1];
            self.sequence = self.sequence % 999_999 + 1;
            let record = record(
                self.sequence,
                &self.network,
                &key.0,
                channel.location,
                &channel_code(rate_hz, channel.axis),
                start_ns,
                factor,
                channel.kind == ChannelKind::Flags,
                flag_bits,
                &values,
            );
            let path = self.path(&key.0, channel, rate_hz, start_ns);
            append(&path, &record)?;
            *self.records.entry(path).or_default() += 1;
        }
    }

    fn path(&self, station: &str, channel: Channel, rate_hz: f64, start_ns: i64) -> PathBuf {
        let t = time::OffsetDateTime::from_unix_timestamp_nanos(i128::from(start_ns))
            .unwrap_or(time::OffsetDateTime::UNIX_EPOCH);
        let cha = channel_code(rate_hz, channel.axis);
        self.root
            .join(t.year().to_string())
            .join(&self.network)
            .join(station)
            .join(format!("{cha}.D"))
            .join(format!(
                "{}.{station}.{}.{cha}.D.{}.{:03}",
                self.network,
                channel.location,
                t.year(),
                t.ordinal()
            ))
    }
}

fn append(path: &Path, bytes: &[u8]) -> Result<(), MseedError> {
    let io = |source| MseedError::Io {
        path: path.to_path_buf(),
        source,
    };
    if let Some(dir) = path.parent() {
        std::fs::create_dir_all(dir).map_err(io)?;
    }
    let mut f = std::fs::OpenOptions::new()
        .create(true)
        .append(true)
        .open(path)
        .map_err(io)?;
    f.write_all(bytes).map_err(io)
}

fn padded(out: &mut Vec<u8>, text: &str, width: usize) {
    let mut b: Vec<u8> = text.bytes().take(width).collect();
    b.resize(width, b' ');
    out.extend_from_slice(&b);
}

/// One 512-byte record (SEED 2.4, chapter 8): fixed header, blockettes 1000 and 1001, data.
#[allow(clippy::too_many_arguments)]
fn record(
    sequence: u32,
    network: &str,
    station: &str,
    location: &str,
    channel: &str,
    start_ns: i64,
    (factor, multiplier): (i16, i16),
    integers: bool,
    sample_flags: u16,
    values: &[[u8; 4]],
) -> Vec<u8> {
    let mut r = Vec::with_capacity(RECORD_BYTES);
    r.extend_from_slice(format!("{sequence:06}").as_bytes());
    r.push(if sample_flags != 0 { b'Q' } else { b'D' });
    r.push(b' ');
    padded(&mut r, station, 5);
    padded(&mut r, location, 2);
    padded(&mut r, channel, 3);
    padded(&mut r, network, 2);
    // BTIME to the nearest 100 µs; blockette 1001 carries the microseconds from there, −50 to
    // +49 as the format asks (what lies below a microsecond is dropped).
    let start_ns = i128::from(start_ns);
    let rounded_ns = (start_ns + 50_000).div_euclid(100_000) * 100_000;
    let offset_us = (start_ns - rounded_ns).div_euclid(1000) as i8;
    let t = time::OffsetDateTime::from_unix_timestamp_nanos(rounded_ns)
        .unwrap_or(time::OffsetDateTime::UNIX_EPOCH);
    r.extend_from_slice(&(t.year() as u16).to_be_bytes());
    r.extend_from_slice(&t.ordinal().to_be_bytes());
    r.extend_from_slice(&[t.hour(), t.minute(), t.second(), 0]);
    r.extend_from_slice(&((t.microsecond() / 100) as u16).to_be_bytes());
    r.extend_from_slice(&(values.len() as u16).to_be_bytes());
    r.extend_from_slice(&factor.to_be_bytes());
    r.extend_from_slice(&multiplier.to_be_bytes());
    let mut quality = 0u8;
    if sample_flags & flags::CLIPPED != 0 {
        quality |= 1 << 1;
    }
    if sample_flags & flags::NON_FINITE_INPUT != 0 {
        quality |= 1 << 3;
    }
    if sample_flags & flags::SEQUENCE_GAP != 0 {
        quality |= 1 << 4;
    }
    if sample_flags & flags::DUPLICATE != 0 {
        quality |= 1 << 7;
    }
    // Activity flags, I/O flags, data quality flags, number of blockettes.
    r.extend_from_slice(&[0, 0, quality, 2]);
    r.extend_from_slice(&0i32.to_be_bytes());
    r.extend_from_slice(&(DATA_OFFSET as u16).to_be_bytes());
    r.extend_from_slice(&48u16.to_be_bytes());
    // Blockette 1000: encoding (3 int32, 4 float32), big-endian, 2⁹ bytes.
    r.extend_from_slice(&1000u16.to_be_bytes());
    r.extend_from_slice(&56u16.to_be_bytes());
    r.extend_from_slice(&[if integers { 3 } else { 4 }, 1, RECORD_EXPONENT, 0]);
    // Blockette 1001: timing quality unknown (0), microseconds beyond BTIME, frame count 0.
    r.extend_from_slice(&1001u16.to_be_bytes());
    r.extend_from_slice(&0u16.to_be_bytes());
    r.extend_from_slice(&[0, offset_us as u8, 0, 0]);
    debug_assert_eq!(r.len(), DATA_OFFSET);
    for v in values {
        r.extend_from_slice(v);
    }
    r.resize(RECORD_BYTES, 0);
    r
}

#[cfg(test)]
mod tests {
    use super::*;
    use triax_protocol::batch::{BatchHeader, CorrectedSample, CorrectionInfo, Mode};

    fn batch(sequence: u64, timestamp_ns: i64, n: usize, flag: u16) -> CorrectedBatch {
        CorrectedBatch {
            header: BatchHeader {
                sensor_id: SensorId::new("acc-01").unwrap(),
                sequence,
                timestamp_ns,
                sample_rate_hz: 100.0,
            },
            batch_flags: flag,
            info: CorrectionInfo {
                calibration_version: 3,
                mode: Mode::Dynamic,
                coverage_factor: 2.0,
            },
            samples: (0..n)
                .map(|i| CorrectedSample {
                    accel_mps2: [i as f32 * 0.5, -1.25, 9.75],
                    uncertainty_mps2: [0.01, 0.02, 0.03],
                    flags: if i == 3 { flags::CLIPPED } else { 0 },
                })
                .collect(),
        }
    }

    /// The header fields read back by hand: codes, start time to the microsecond, rate,
    /// blockettes, the clipped bit, and the values as big-endian f32.
    #[test]
    fn a_record_reads_back_by_hand() {
        let dir = tempfile::tempdir().unwrap();
        let mut w = SdsWriter::new(dir.path(), "XX", BTreeMap::new()).unwrap();
        // 2026-11-25T12:34:56.123456789Z.
        let t0 = 1_795_610_096_123_456_789i64;
        w.push(&batch(1, t0, 50, 0)).unwrap();
        let files = w.finish().unwrap();
        assert_eq!(files.len(), 9, "{files:?}");
        let path = dir
            .path()
            .join("2026/XX/ACC01/EN1.D/XX.ACC01.00.EN1.D.2026.329");
        let r = std::fs::read(&path).unwrap();
        assert_eq!(r.len(), 512);
        assert_eq!(&r[0..8], b"000001Q ");
        assert_eq!(&r[8..20], b"ACC0100EN1XX");
        assert_eq!(u16::from_be_bytes([r[20], r[21]]), 2026);
        assert_eq!(u16::from_be_bytes([r[22], r[23]]), 329);
        assert_eq!(&r[24..27], &[12, 34, 56]);
        // .123456789 s: BTIME .1235, then −44 µs (what is below a microsecond dropped).
        assert_eq!(u16::from_be_bytes([r[28], r[29]]), 1235);
        assert_eq!(u16::from_be_bytes([r[30], r[31]]), 50);
        assert_eq!(i16::from_be_bytes([r[32], r[33]]), 100);
        assert_eq!(r[38], 1 << 1, "clipped");
        assert_eq!(u16::from_be_bytes([r[48], r[49]]), 1000);
        assert_eq!(r[52..55], [4, 1, 9]);
        assert_eq!(u16::from_be_bytes([r[56], r[57]]), 1001);
        assert_eq!(r[61] as i8, -44, "microseconds from the BTIME");
        let v = |i: usize| f32::from_be_bytes(r[64 + 4 * i..68 + 4 * i].try_into().unwrap());
        assert_eq!(v(0), 0.0);
        assert_eq!(v(7), 3.5);
        let flags_path = dir
            .path()
            .join("2026/XX/ACC01/EN1.D/XX.ACC01.Q0.EN1.D.2026.329");
        let q = std::fs::read(flags_path).unwrap();
        assert_eq!(q[52], 3, "int32");
        assert_eq!(
            i32::from_be_bytes(q[64 + 12..68 + 12].try_into().unwrap()),
            64
        );
    }

    /// Consecutive batches share records; a gap starts a new one; a full record is 112
    /// samples; a day boundary splits files.
    #[test]
    fn records_follow_the_stream() {
        let dir = tempfile::tempdir().unwrap();
        let mut w = SdsWriter::new(dir.path(), "XX", BTreeMap::new()).unwrap();
        let day_ns = 86_400_000_000_000i64;
        let t0 = 20_000 * day_ns - 1_000_000_000; // one second before midnight
        w.push(&batch(1, t0, 50, 0)).unwrap();
        w.push(&batch(2, t0 + 500_000_000, 50, 0)).unwrap();
        w.push(&batch(3, t0 + 1_000_000_000, 50, 0)).unwrap();
        // A batch lost: the next follows a gap.
        w.push(&batch(5, t0 + 2_000_000_000, 150, flags::SEQUENCE_GAP))
            .unwrap();
        let files = w.finish().unwrap();
        let count = |day: i64| -> usize {
            let t = time::OffsetDateTime::from_unix_timestamp(day * 86_400).unwrap();
            files
                .iter()
                .filter(|(p, _)| {
                    p.to_string_lossy().contains(".00.EN1.")
                        && p.to_string_lossy().ends_with(&format!(
                            ".{}.{:03}",
                            t.year(),
                            t.ordinal()
                        ))
                })
                .map(|(_, n)| *n)
                .sum()
        };
        // Before midnight: the first second's 100 samples in one record.
        assert_eq!(count(19_999), 1);
        // After: 50 samples, then after the gap 150 = 112 + 38.
        assert_eq!(count(20_000), 3);
    }

    #[test]
    fn clashing_and_bad_codes_are_refused_by_name() {
        let dir = tempfile::tempdir().unwrap();
        let mut w = SdsWriter::new(dir.path(), "XX", BTreeMap::new()).unwrap();
        w.station(&SensorId::new("incl-01").unwrap()).unwrap();
        let e = w.station(&SensorId::new("incl-02").unwrap()).unwrap_err();
        assert!(e.to_string().contains("INCL0"), "{e}");
        assert!(e.to_string().contains("--station"), "{e}");
        let e = w.station(&SensorId::new("---").unwrap()).unwrap_err();
        assert!(e.to_string().contains("sensor ---"), "{e}");
        // A timestamp at the end of i64's range is written, not a panic.
        let mut b = batch(1, i64::MAX - 1_000, 3, 0);
        b.header.sensor_id = SensorId::new("end-1").unwrap();
        w.push(&b).unwrap();
        w.finish().unwrap();
        assert!(SdsWriter::new(dir.path(), "X-", BTreeMap::new()).is_err());
        let bad = BTreeMap::from([("a".to_string(), "TOOLONG".to_string())]);
        assert!(SdsWriter::new(dir.path(), "XX", bad).is_err());
        assert_eq!(rate_factor(100.0), Some((100, 1)));
        assert_eq!(rate_factor(0.5), Some((-2, 1)));
        assert_eq!(rate_factor(12.5), Some((25, -2)));
        assert_eq!(channel_code(100.0, 2), "EN3");
    }
}
