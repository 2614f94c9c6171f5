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
//! split at UTC midnight.
//!
//! What goes in: only calibrated samples (a batch corrected with no record holds raw outputs,
//! not m/s², and is left out and counted), and each instant once (a batch whose samples fall
//! on instants already written, a duplicate, is left out and counted).
//!
//! How it goes in, so that an archive is never left half-written and an export run twice
//! leaves it as one run leaves it: records are first written to a staging directory inside the
//! root ([`SdsWriter::stage`]), and only once the whole export is there does
//! [`Staged::commit`] merge each day file into the archive. A merge replaces, per channel and
//! day, what the archive holds between the export's first and last sample of that file (an
//! older record that reaches into that span keeps only its samples outside it), keeps
//! everything else, sorts the records by time, and writes the file whole (a temporary file
//! beside it, synced, renamed over it). Records the merge does not recognise as this writer's
//! stop it with an error naming the file, before anything is replaced.
//!
//! Blockette 1001's timing quality is 0: the batches say nothing of their node's clock, so the
//! quality is unknown, which SEED has no other way to say.

use std::collections::BTreeMap;
use std::io::Write;
use std::path::{Path, PathBuf};

use triax_protocol::batch::{flags, CorrectedBatch, Mode};
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
    #[error("{path}: record {index} is not a record this writer makes ({why}); the file is left as it is")]
    Foreign {
        path: PathBuf,
        index: usize,
        why: &'static str,
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

/// A stretch of one sensor's exported samples corrected with one calibration version.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Run {
    pub version: u64,
    /// Time of the stretch's first sample, ns since the Unix epoch.
    pub first_ns: i64,
    /// Time of its last sample.
    pub last_ns: i64,
}

/// What an export left out, per sensor.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct LeftOut {
    /// Samples of batches corrected with no record: raw outputs, not m/s².
    pub uncalibrated_samples: u64,
    /// Batches whose instants were already written (duplicates).
    pub overlapping_batches: u64,
}

/// Where each channel's samples go, and the records staged so far.
pub struct SdsWriter {
    root: PathBuf,
    staging: Option<tempfile::TempDir>,
    network: String,
    stations: BTreeMap<SensorId, String>,
    overrides: BTreeMap<String, String>,
    pending: BTreeMap<(String, usize), Pending>,
    sequence: u32,
    /// Records staged per archive file, relative to the root.
    records: BTreeMap<PathBuf, usize>,
    /// Per sensor, the half-open spans `[start, end)` (ns, half a period either side of the
    /// samples) already written: a batch reaching into one is a duplicate.
    covered: BTreeMap<SensorId, BTreeMap<i64, i64>>,
    /// Per sensor, each written batch's `(first_ns, last_ns, version)`.
    spans: BTreeMap<SensorId, Vec<(i64, i64, u64)>>,
    left_out: BTreeMap<SensorId, LeftOut>,
    /// Samples written per channel.
    samples: u64,
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
            staging: None,
            network: network.to_ascii_uppercase(),
            stations: BTreeMap::new(),
            overrides: overrides
                .into_iter()
                .map(|(k, v)| (k, v.to_ascii_uppercase()))
                .collect(),
            pending: BTreeMap::new(),
            sequence: 0,
            records: BTreeMap::new(),
            covered: BTreeMap::new(),
            spans: BTreeMap::new(),
            left_out: BTreeMap::new(),
            samples: 0,
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

    /// Adds a batch's samples to its sensor's nine channels, unless it is uncalibrated or
    /// its instants are already written (then it is counted in [`left_out`](Self::left_out)).
    pub fn push(&mut self, batch: &CorrectedBatch) -> Result<(), MseedError> {
        let h = &batch.header;
        if batch.samples.is_empty() {
            return Ok(());
        }
        if batch.info.mode == Mode::None || batch.batch_flags & flags::UNCALIBRATED != 0 {
            self.left_out
                .entry(h.sensor_id.clone())
                .or_default()
                .uncalibrated_samples += batch.samples.len() as u64;
            return Ok(());
        }
        let station = self.station(&h.sensor_id)?;
        let factor = rate_factor(h.sample_rate_hz).ok_or_else(|| MseedError::SampleRate {
            sensor: h.sensor_id.to_string(),
            rate_hz: h.sample_rate_hz,
        })?;
        let period_ns = 1e9 / h.sample_rate_hz;
        let last_ns = h
            .timestamp_ns
            .saturating_add(((batch.samples.len() - 1) as f64 * period_ns).round() as i64);
        let half_ns = (period_ns / 2.0) as i64;
        let (span_start, span_end) = (
            h.timestamp_ns.saturating_sub(half_ns),
            last_ns.saturating_add(half_ns),
        );
        let covered = self.covered.entry(h.sensor_id.clone()).or_default();
        // The spans are disjoint: only the last one starting before this batch ends can reach it.
        if covered
            .range(..span_end)
            .next_back()
            .is_some_and(|(_, &end)| end > span_start)
        {
            self.left_out
                .entry(h.sensor_id.clone())
                .or_default()
                .overlapping_batches += 1;
            return Ok(());
        }
        covered.insert(span_start, span_end);
        self.samples += batch.samples.len() as u64;
        let version = batch.info.calibration_version;
        self.spans
            .entry(h.sensor_id.clone())
            .or_default()
            .push((h.timestamp_ns, last_ns, version));
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
                let sample_flags = batch.sample_flags(i);
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

    /// What was left out so far, per sensor.
    pub fn left_out(&self) -> &BTreeMap<SensorId, LeftOut> {
        &self.left_out
    }

    /// Writes every partial record to the staging directory; the archive is not touched yet.
    pub fn stage(mut self) -> Result<Staged, MseedError> {
        let keys: Vec<_> = self.pending.keys().cloned().collect();
        for key in keys {
            let rate = self
                .pending
                .get(&key)
                .map(|p| 1e9 / p.period_ns)
                .unwrap_or(1.0);
            self.flush(&key, rate, true)?;
        }
        let mut runs: BTreeMap<SensorId, Vec<Run>> = BTreeMap::new();
        for (sensor, mut spans) in std::mem::take(&mut self.spans) {
            spans.sort_unstable();
            let list = runs.entry(sensor).or_default();
            for (first_ns, last_ns, version) in spans {
                match list.last_mut() {
                    Some(r) if r.version == version => r.last_ns = r.last_ns.max(last_ns),
                    _ => list.push(Run {
                        version,
                        first_ns,
                        last_ns,
                    }),
                }
            }
        }
        Ok(Staged {
            root: self.root,
            staging: self.staging,
            records: self.records,
            stations: self.stations,
            runs,
            left_out: self.left_out,
            samples: self.samples,
        })
    }

    /// The staging directory, made inside the root on the first record.
    fn staging_dir(&mut self) -> Result<PathBuf, MseedError> {
        if let Some(d) = &self.staging {
            return Ok(d.path().to_path_buf());
        }
        let io = |source| MseedError::Io {
            path: self.root.clone(),
            source,
        };
        std::fs::create_dir_all(&self.root).map_err(io)?;
        let dir = tempfile::Builder::new()
            .prefix(".triax-export-")
            .tempdir_in(&self.root)
            .map_err(io)?;
        let path = dir.path().to_path_buf();
        self.staging = Some(dir);
        Ok(path)
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
            append(&self.staging_dir()?.join(&path), &record)?;
            *self.records.entry(path).or_default() += 1;
        }
    }

    /// A day file's path relative to the root.
    fn path(&self, station: &str, channel: Channel, rate_hz: f64, start_ns: i64) -> PathBuf {
        let t = time::OffsetDateTime::from_unix_timestamp_nanos(i128::from(start_ns))
            .unwrap_or(time::OffsetDateTime::UNIX_EPOCH);
        let cha = channel_code(rate_hz, channel.axis);
        PathBuf::from(t.year().to_string())
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

/// An export written to the staging directory, not yet in the archive.
pub struct Staged {
    root: PathBuf,
    staging: Option<tempfile::TempDir>,
    records: BTreeMap<PathBuf, usize>,
    stations: BTreeMap<SensorId, String>,
    runs: BTreeMap<SensorId, Vec<Run>>,
    left_out: BTreeMap<SensorId, LeftOut>,
    samples: u64,
}

impl Staged {
    /// Samples written per channel.
    pub fn samples(&self) -> u64 {
        self.samples
    }

    /// Per sensor, its stretches of one calibration version, in time order.
    pub fn runs(&self) -> &BTreeMap<SensorId, Vec<Run>> {
        &self.runs
    }

    /// The station code of each sensor written.
    pub fn stations(&self) -> &BTreeMap<SensorId, String> {
        &self.stations
    }

    /// What was left out, per sensor.
    pub fn left_out(&self) -> &BTreeMap<SensorId, LeftOut> {
        &self.left_out
    }

    /// Records staged per day file (paths relative to the root).
    pub fn records(&self) -> &BTreeMap<PathBuf, usize> {
        &self.records
    }

    /// Merges every staged day file into the archive (see the module's documentation) and
    /// removes the staging directory. Returns the records written per archive file.
    pub fn commit(self) -> Result<BTreeMap<PathBuf, usize>, MseedError> {
        let Some(staging) = &self.staging else {
            return Ok(BTreeMap::new());
        };
        let mut written = BTreeMap::new();
        for relative in self.records.keys() {
            let target = self.root.join(relative);
            let fresh = read_records(&staging.path().join(relative))?;
            let old = if target.exists() {
                read_records(&target)?
            } else {
                Vec::new()
            };
            let merged = merge(old, fresh);
            replace(&target, &merged)?;
            written.insert(target, merged.len());
        }
        Ok(written)
    }
}

/// A record read back from a day file, with what a merge needs of its header.
#[derive(Debug, Clone)]
struct Parsed {
    bytes: Vec<u8>,
    start_ns: i64,
    period_ns: f64,
    samples: usize,
}

impl Parsed {
    fn last_ns(&self) -> i64 {
        self.sample_ns(self.samples.max(1) - 1)
    }

    fn sample_ns(&self, i: usize) -> i64 {
        self.start_ns
            .saturating_add((i as f64 * self.period_ns).round() as i64)
    }

    /// The same record with only samples `range`, its header otherwise kept (quality bits
    /// included: they may then say more than the samples left, never less).
    fn part(&self, range: std::ops::Range<usize>) -> Parsed {
        let start_ns = self.sample_ns(range.start);
        let mut bytes = self.bytes.clone();
        let t = btime(start_ns);
        bytes[20..30].copy_from_slice(&t.0);
        bytes[61] = t.1 as u8;
        bytes[30..32].copy_from_slice(&(range.len() as u16).to_be_bytes());
        let data = self.bytes[DATA_OFFSET + 4 * range.start..DATA_OFFSET + 4 * range.end].to_vec();
        bytes[DATA_OFFSET..].fill(0);
        bytes[DATA_OFFSET..DATA_OFFSET + data.len()].copy_from_slice(&data);
        Parsed {
            bytes,
            start_ns,
            period_ns: self.period_ns,
            samples: range.len(),
        }
    }
}

/// Reads every record of a day file this writer made, refusing anything else by name.
fn read_records(path: &Path) -> Result<Vec<Parsed>, MseedError> {
    let bytes = std::fs::read(path).map_err(|source| MseedError::Io {
        path: path.to_path_buf(),
        source,
    })?;
    if bytes.len() % RECORD_BYTES != 0 {
        return Err(MseedError::Foreign {
            path: path.to_path_buf(),
            index: bytes.len() / RECORD_BYTES,
            why: "the file is not a whole number of 512-byte records",
        });
    }
    bytes
        .chunks_exact(RECORD_BYTES)
        .enumerate()
        .map(|(index, r)| {
            parse(r).map_err(|why| MseedError::Foreign {
                path: path.to_path_buf(),
                index,
                why,
            })
        })
        .collect()
}

fn parse(r: &[u8]) -> Result<Parsed, &'static str> {
    let u16_at = |i: usize| u16::from_be_bytes([r[i], r[i + 1]]);
    let i16_at = |i: usize| i16::from_be_bytes([r[i], r[i + 1]]);
    if u16_at(44) as usize != DATA_OFFSET
        || u16_at(48) != 1000
        || u16_at(56) != 1001
        || r[54] != RECORD_EXPONENT
        || !matches!(r[52], 3 | 4)
        || r[53] != 1
    {
        return Err("not a 512-byte big-endian record with blockettes 1000 and 1001 at 48 and 56");
    }
    let samples = u16_at(30) as usize;
    if samples == 0 || samples > SAMPLES_PER_RECORD {
        return Err("sample count outside 1..=112");
    }
    let (factor, multiplier) = (f64::from(i16_at(32)), f64::from(i16_at(34)));
    let rate_hz = match (factor > 0.0, multiplier > 0.0) {
        (true, true) => factor * multiplier,
        (true, false) => -factor / multiplier,
        (false, true) => -multiplier / factor,
        (false, false) => 1.0 / (factor * multiplier),
    };
    if !(rate_hz.is_finite() && rate_hz > 0.0) {
        return Err("no sample rate");
    }
    let date = time::Date::from_ordinal_date(i32::from(u16_at(20)), u16_at(22))
        .map_err(|_| "start day out of range")?;
    let start_s = i128::from(date.midnight().assume_utc().unix_timestamp())
        + i128::from(r[24]) * 3600
        + i128::from(r[25]) * 60
        + i128::from(r[26]);
    // In i128, then saturated: a record the writer made at the end of i64's range rounds past it.
    let start_ns =
        start_s * 1_000_000_000 + i128::from(u16_at(28)) * 100_000 + i128::from(r[61] as i8) * 1000;
    let start_ns = start_ns.clamp(i128::from(i64::MIN), i128::from(i64::MAX)) as i64;
    Ok(Parsed {
        bytes: r.to_vec(),
        start_ns,
        period_ns: 1e9 / rate_hz,
        samples,
    })
}

/// An archive file's records with a fresh export's: the old ones keep only their samples
/// outside the export's span, then all in time order (old before new at the same instant).
fn merge(old: Vec<Parsed>, fresh: Vec<Parsed>) -> Vec<Parsed> {
    let Some(from_ns) = fresh.iter().map(|r| r.start_ns).min() else {
        return old;
    };
    let to_ns = fresh.iter().map(Parsed::last_ns).max().unwrap_or(from_ns);
    let mut out = Vec::with_capacity(old.len() + fresh.len());
    for r in old {
        let half = (r.period_ns / 2.0) as i64;
        let outside = |i: usize| {
            let t = r.sample_ns(i);
            t < from_ns.saturating_sub(half) || t > to_ns.saturating_add(half)
        };
        let before = (0..r.samples).take_while(|&i| outside(i)).count();
        let after = (0..r.samples).rev().take_while(|&i| outside(i)).count();
        if before == r.samples {
            out.push(r);
            continue;
        }
        if before > 0 {
            out.push(r.part(0..before));
        }
        if after > 0 {
            out.push(r.part(r.samples - after..r.samples));
        }
    }
    out.extend(fresh);
    out.sort_by_key(|r| r.start_ns);
    out
}

/// Writes `records` as the whole of `path` ([`crate::whole`]).
fn replace(path: &Path, records: &[Parsed]) -> Result<(), MseedError> {
    crate::whole::write(path, records.iter().map(|r| r.bytes.as_slice())).map_err(|source| {
        MseedError::Io {
            path: path.to_path_buf(),
            source,
        }
    })
}

/// BTIME (10 bytes) for an instant to the nearest 100 µs, and the microseconds from there
/// (−50 to +49, for blockette 1001; what lies below a microsecond is dropped).
fn btime(start_ns: i64) -> ([u8; 10], i8) {
    let start_ns = i128::from(start_ns);
    let rounded_ns = (start_ns + 50_000).div_euclid(100_000) * 100_000;
    let offset_us = (start_ns - rounded_ns).div_euclid(1000) as i8;
    let t = time::OffsetDateTime::from_unix_timestamp_nanos(rounded_ns)
        .unwrap_or(time::OffsetDateTime::UNIX_EPOCH);
    let mut b = [0u8; 10];
    b[0..2].copy_from_slice(&(t.year() as u16).to_be_bytes());
    b[2..4].copy_from_slice(&t.ordinal().to_be_bytes());
    b[4..8].copy_from_slice(&[t.hour(), t.minute(), t.second(), 0]);
    b[8..10].copy_from_slice(&((t.microsecond() / 100) as u16).to_be_bytes());
    (b, offset_us)
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
    let (start, offset_us) = btime(start_ns);
    r.extend_from_slice(&start);
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
    // Blockette 1001: timing quality 0 (unknown: the module's documentation says why),
    // microseconds beyond BTIME, frame count 0.
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
        let files = w.stage().unwrap().commit().unwrap();
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
        let files = w.stage().unwrap().commit().unwrap();
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

    /// Every file under `root` with its bytes, staging left-overs included.
    fn tree(root: &Path) -> BTreeMap<PathBuf, Vec<u8>> {
        let mut out = BTreeMap::new();
        let mut dirs = vec![root.to_path_buf()];
        while let Some(d) = dirs.pop() {
            for e in std::fs::read_dir(&d).unwrap() {
                let p = e.unwrap().path();
                if p.is_dir() {
                    dirs.push(p);
                } else {
                    out.insert(p.clone(), std::fs::read(&p).unwrap());
                }
            }
        }
        out
    }

    fn export(root: &Path, batches: &[CorrectedBatch]) -> Staged {
        let mut w = SdsWriter::new(root, "XX", BTreeMap::new()).unwrap();
        for b in batches {
            w.push(b).unwrap();
        }
        w.stage().unwrap()
    }

    /// Exporting the same range twice leaves the archive byte for byte as once; a second
    /// export that overlaps the first replaces the overlap and keeps the rest; a duplicate
    /// batch and an uncalibrated one are left out and counted.
    #[test]
    fn exports_merge_into_the_archive_once() {
        let dir = tempfile::tempdir().unwrap();
        let root = dir.path().join("sds");
        let t0 = 1_795_610_096_000_000_000i64;
        let second = 1_000_000_000;
        let batches: Vec<_> = (0..6)
            .map(|i| batch(i, t0 + i as i64 * second / 2, 50, 0))
            .collect();
        export(&root, &batches).commit().unwrap();
        let once = tree(&root);
        assert_eq!(once.len(), 9, "no staging left behind: {:?}", once.keys());
        export(&root, &batches).commit().unwrap();
        assert_eq!(
            tree(&root),
            once,
            "a second export of the same range changes nothing"
        );

        // The same stretch again, with a duplicate of batch 2 and an uncalibrated batch.
        let mut with_extras = batches.clone();
        with_extras.insert(3, batch(2, t0 + second, 50, flags::DUPLICATE));
        let mut raw = batch(9, t0 + 10 * second, 50, flags::UNCALIBRATED);
        raw.info.mode = Mode::None;
        with_extras.push(raw);
        let staged = export(&root, &with_extras);
        let left = &staged.left_out()[&SensorId::new("acc-01").unwrap()];
        assert_eq!(left.overlapping_batches, 1);
        assert_eq!(left.uncalibrated_samples, 50);
        assert_eq!(staged.samples(), 300);
        staged.commit().unwrap();
        assert_eq!(tree(&root), once);

        // A later export from the middle on: the first half kept, the rest replaced, each
        // instant once.
        let later: Vec<_> = (3..10)
            .map(|i| batch(i, t0 + i as i64 * second / 2, 50, 0))
            .collect();
        export(&root, &later).commit().unwrap();
        let path = root.join("2026/XX/ACC01/EN1.D/XX.ACC01.00.EN1.D.2026.329");
        let records = read_records(&path).unwrap();
        let mut times: Vec<i64> = records
            .iter()
            .flat_map(|r| (0..r.samples).map(|i| r.sample_ns(i)))
            .collect();
        assert_eq!(times.len(), 500, "10 batches of 50 samples");
        times.dedup();
        assert_eq!(times.len(), 500, "no instant twice");
        assert!(
            times.windows(2).all(|w| w[1] - w[0] == 10_000_000),
            "in order, no gap"
        );
        assert!((times[0] - t0).abs() < 1000);
        // Each value is the one of its instant: sample i of a batch holds i·0.5 on x.
        for r in &records {
            for i in 0..r.samples {
                let v = f32::from_be_bytes(
                    r.bytes[DATA_OFFSET + 4 * i..DATA_OFFSET + 4 * i + 4]
                        .try_into()
                        .unwrap(),
                );
                let n = ((r.sample_ns(i) - t0 + 500) / 10_000_000) % 50;
                assert_eq!(v, n as f32 * 0.5);
            }
        }
    }

    /// A station code two sensors share is found while staging: the export stops before the
    /// archive holds a byte of it.
    #[test]
    fn a_clash_leaves_the_archive_untouched() {
        let dir = tempfile::tempdir().unwrap();
        let root = dir.path().join("sds");
        let t0 = 1_795_610_096_000_000_000i64;
        let mut w = SdsWriter::new(&root, "XX", BTreeMap::new()).unwrap();
        // Enough for whole records of the first sensor to be staged already.
        for i in 0..10 {
            let mut b = batch(i, t0 + i as i64 * 500_000_000, 50, 0);
            b.header.sensor_id = SensorId::new("incl-01").unwrap();
            w.push(&b).unwrap();
        }
        let mut b = batch(0, t0, 50, 0);
        b.header.sensor_id = SensorId::new("incl-02").unwrap();
        let e = w.push(&b).unwrap_err();
        assert!(e.to_string().contains("INCL0"), "{e}");
        drop(w);
        assert!(tree(&root).is_empty(), "{:?}", tree(&root).keys());
    }

    /// A day file another program wrote is refused by name, and left as it is.
    #[test]
    fn a_foreign_day_file_is_refused_and_kept() {
        let dir = tempfile::tempdir().unwrap();
        let root = dir.path().join("sds");
        let t0 = 1_795_610_096_000_000_000i64;
        let path = root.join("2026/XX/ACC01/EN1.D/XX.ACC01.00.EN1.D.2026.329");
        std::fs::create_dir_all(path.parent().unwrap()).unwrap();
        std::fs::write(&path, vec![7u8; 512]).unwrap();
        let e = export(&root, &[batch(1, t0, 50, 0)]).commit().unwrap_err();
        assert!(e.to_string().contains("XX.ACC01.00.EN1.D.2026.329"), "{e}");
        assert!(e.to_string().contains("record 0"), "{e}");
        assert_eq!(std::fs::read(&path).unwrap(), vec![7u8; 512]);
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
        w.stage().unwrap().commit().unwrap();
        assert!(SdsWriter::new(dir.path(), "X-", BTreeMap::new()).is_err());
        let bad = BTreeMap::from([("a".to_string(), "TOOLONG".to_string())]);
        assert!(SdsWriter::new(dir.path(), "XX", bad).is_err());
        assert_eq!(rate_factor(100.0), Some((100, 1)));
        assert_eq!(rate_factor(0.5), Some((-2, 1)));
        assert_eq!(rate_factor(12.5), Some((25, -2)));
        assert_eq!(channel_code(100.0, 2), "EN3");
    }
}
