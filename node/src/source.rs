//! Where samples come from: the [`Source`] trait and its software sources, the simulated one
//! ([`SimSource`]) and the CSV one ([`CsvSource`]). The ADXL355 driver is in [`crate::adxl355`].
//!
//! A source stamps every sample with the node's clock (ns since the Unix epoch, UTC). The
//! batcher only keeps the first stamp of a batch, and cuts a batch where the stamps leave the
//! batch's time grid, so a source that loses samples (a FIFO overrun) or jumps (a clock step)
//! never makes a batch claim times its samples were not taken at.

use std::io::BufRead;
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use rand::rngs::StdRng;
use rand::SeedableRng;
use rand_distr::{Distribution, Normal};

/// One three-axis sample and when it was taken.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Sample {
    /// ns since the Unix epoch (UTC), by the node's clock.
    pub timestamp_ns: i64,
    /// Outputs in the source's unit (g for the simulated source and the ADXL355).
    pub v: [f32; 3],
}

/// Why a source could not deliver.
#[derive(Debug, thiserror::Error)]
pub enum SourceError {
    /// The source has nothing more, ever (the end of a CSV file): not a failure.
    #[error("end of input")]
    End,
    #[error("{path}, line {line}: {problem}")]
    Parse {
        path: String,
        line: u64,
        problem: String,
    },
    #[error("{what}: {source}")]
    Io {
        what: String,
        #[source]
        source: std::io::Error,
    },
    #[error(transparent)]
    Adxl355(#[from] crate::adxl355::Adxl355Error),
}

/// A sensor, as the node reads it.
pub trait Source: Send {
    /// The output data rate the samples are taken at.
    fn rate_hz(&self) -> f64;

    /// Appends the next block of samples to `out`, in time order, waiting until at least one is
    /// ready. The wait is short (at most about a tenth of a second for the sources here), so the
    /// caller can check for a stop between calls.
    fn read(&mut self, out: &mut Vec<Sample>) -> Result<(), SourceError>;

    /// The sensor's temperature, °C, if it measures one; asked once per batch.
    fn temperature_c(&mut self) -> Option<f32> {
        None
    }

    /// Standard uncertainty of a sample's stamp that comes from the source itself (when in its
    /// FIFO a sample was taken), ns; the clock's own uncertainty is added to it by the node.
    fn stamp_uncertainty_ns(&self) -> f64 {
        0.0
    }
}

/// The node's clock: ns since the Unix epoch.
pub fn now_ns() -> i64 {
    match SystemTime::now().duration_since(UNIX_EPOCH) {
        Ok(d) => i64::try_from(d.as_nanos()).unwrap_or(i64::MAX),
        // A clock set before 1970 is a broken clock; its stamps are as wrong as they come.
        Err(e) => -i64::try_from(e.duration().as_nanos()).unwrap_or(i64::MAX),
    }
}

/// A time grid anchored on the node's clock and paced by the monotonic clock: sample `k` is
/// stamped `start_ns + k·10⁹/rate_hz` and is not delivered before that moment.
#[derive(Debug, Clone)]
struct Pacer {
    start_ns: i64,
    start: Instant,
    period_s: f64,
}

impl Pacer {
    fn new(rate_hz: f64) -> Pacer {
        Pacer {
            start_ns: now_ns(),
            start: Instant::now(),
            period_s: 1.0 / rate_hz,
        }
    }

    fn stamp_ns(&self, k: u64) -> i64 {
        self.start_ns + (k as f64 * self.period_s * 1e9).round() as i64
    }

    /// Sleeps until sample `k` is due.
    fn wait_for(&self, k: u64) {
        let due = self.start + Duration::from_secs_f64(k as f64 * self.period_s);
        let now = Instant::now();
        if due > now {
            std::thread::sleep(due - now);
        }
    }

    /// How many samples are due now.
    fn due(&self) -> u64 {
        (self.start.elapsed().as_secs_f64() / self.period_s).floor() as u64 + 1
    }
}

/// How long a source's `read` waits for: samples arrive in blocks of about this, as they would
/// from a sensor's FIFO polled at this interval.
const BLOCK_S: f64 = 0.02;

/// A simulated accelerometer at rest on a swaying floor: gravity on z, a sway on x and y,
/// white noise on every axis, in g; seeded, so a run can be repeated.
#[derive(Debug, Clone)]
pub struct SimSource {
    rate_hz: f64,
    pacer: Pacer,
    next: u64,
    rng: StdRng,
    noise: Normal<f64>,
    /// Sway amplitude (g) and frequency.
    sway_g: f64,
    sway_hz: f64,
}

impl SimSource {
    /// White noise of the simulated outputs, g (about an ADXL355's at 100 Hz).
    pub const NOISE_G: f64 = 25e-6;
    /// Sway of the simulated floor: 2 mg at 1.2 Hz.
    pub const SWAY_G: f64 = 2e-3;
    pub const SWAY_HZ: f64 = 1.2;

    pub fn new(rate_hz: f64, seed: u64) -> SimSource {
        SimSource {
            rate_hz,
            pacer: Pacer::new(rate_hz),
            next: 0,
            rng: StdRng::seed_from_u64(seed),
            // A positive finite standard deviation is always accepted.
            noise: Normal::new(0.0, Self::NOISE_G).expect("a valid standard deviation"),
            sway_g: Self::SWAY_G,
            sway_hz: Self::SWAY_HZ,
        }
    }

    /// The noiseless outputs at `t_s` seconds after the start.
    pub fn truth_at(&self, t_s: f64) -> [f64; 3] {
        let w = 2.0 * std::f64::consts::PI * self.sway_hz * t_s;
        [self.sway_g * w.sin(), 0.5 * self.sway_g * w.cos(), 1.0]
    }

    fn sample(&mut self, k: u64) -> Sample {
        let t_s = k as f64 / self.rate_hz;
        let truth = self.truth_at(t_s);
        let v = truth.map(|x| (x + self.noise.sample(&mut self.rng)) as f32);
        Sample {
            timestamp_ns: self.pacer.stamp_ns(k),
            v,
        }
    }
}

impl Source for SimSource {
    fn rate_hz(&self) -> f64 {
        self.rate_hz
    }

    fn read(&mut self, out: &mut Vec<Sample>) -> Result<(), SourceError> {
        let block = ((self.rate_hz * BLOCK_S).ceil() as u64).max(1);
        self.pacer.wait_for(self.next + block - 1);
        // A late wake-up delivers everything due, as a FIFO would hold it.
        let due = self.pacer.due().max(self.next + block);
        while self.next < due {
            let s = self.sample(self.next);
            out.push(s);
            self.next += 1;
        }
        Ok(())
    }

    fn temperature_c(&mut self) -> Option<f32> {
        Some(21.0)
    }
}

/// Samples from CSV text (a file, or standard input with `-`).
///
/// Each line is `vx,vy,vz` (outputs at the stated rate, stamped on a grid from the moment the
/// source opened and paced to it, so a file plays at the sensor's speed) or `t_ns,vx,vy,vz`
/// (stamps as given, ns since the Unix epoch, delivered as fast as they are read). The first
/// data line decides which; every line must then have as many fields. Blank lines, lines
/// starting with `#` and a first line that does not parse as numbers (a header) are skipped.
pub struct CsvSource {
    path: String,
    reader: Box<dyn BufRead + Send>,
    rate_hz: f64,
    pacer: Pacer,
    next: u64,
    line_no: u64,
    /// Fields per line, once the first data line is read.
    fields: Option<usize>,
    line: String,
}

impl CsvSource {
    /// Opens `path`, or standard input for `-`.
    pub fn open(path: &str, rate_hz: f64) -> Result<CsvSource, SourceError> {
        let reader: Box<dyn BufRead + Send> = if path == "-" {
            Box::new(std::io::BufReader::new(std::io::stdin()))
        } else {
            let f = std::fs::File::open(path).map_err(|source| SourceError::Io {
                what: format!("cannot open {path}"),
                source,
            })?;
            Box::new(std::io::BufReader::new(f))
        };
        Ok(Self::from_reader(path, reader, rate_hz))
    }

    pub fn from_reader(name: &str, reader: Box<dyn BufRead + Send>, rate_hz: f64) -> CsvSource {
        CsvSource {
            path: name.to_owned(),
            reader,
            rate_hz,
            pacer: Pacer::new(rate_hz),
            next: 0,
            line_no: 0,
            fields: None,
            line: String::new(),
        }
    }

    /// The next data line's sample, or `None` at the end.
    fn next_sample(&mut self) -> Result<Option<Sample>, SourceError> {
        loop {
            self.line.clear();
            let n = self
                .reader
                .read_line(&mut self.line)
                .map_err(|source| SourceError::Io {
                    what: format!("cannot read {}", self.path),
                    source,
                })?;
            if n == 0 {
                return Ok(None);
            }
            self.line_no += 1;
            let text = self.line.trim();
            if text.is_empty() || text.starts_with('#') {
                continue;
            }
            let parts: Vec<&str> = text.split(',').map(str::trim).collect();
            let problem = |problem: String| SourceError::Parse {
                path: self.path.clone(),
                line: self.line_no,
                problem,
            };
            let expected = match self.fields {
                Some(f) => f,
                None => match parts.len() {
                    3 | 4 => parts.len(),
                    n => {
                        return Err(problem(format!(
                            "{n} fields: expected vx,vy,vz or t_ns,vx,vy,vz"
                        )))
                    }
                },
            };
            if parts.len() != expected {
                return Err(problem(format!(
                    "{} fields where the first data line had {expected}",
                    parts.len()
                )));
            }
            let vs = &parts[expected - 3..];
            let mut v = [0f32; 3];
            let mut bad = None;
            for (i, (slot, text)) in v.iter_mut().zip(vs).enumerate() {
                match text.parse::<f32>() {
                    Ok(x) => *slot = x,
                    Err(_) => {
                        bad = Some((["vx", "vy", "vz"][i], *text));
                        break;
                    }
                }
            }
            let t_ns = if expected == 4 {
                match parts[0].parse::<i64>() {
                    Ok(t) => Some(t),
                    Err(_) => {
                        bad = bad.or(Some(("t_ns", parts[0])));
                        None
                    }
                }
            } else {
                None
            };
            if let Some((field, text)) = bad {
                if self.fields.is_none() {
                    // The first line of words is a header.
                    continue;
                }
                return Err(problem(format!("{field}: {text:?} is not a number")));
            }
            self.fields = Some(expected);
            let timestamp_ns = match t_ns {
                Some(t) => t,
                None => {
                    self.pacer.wait_for(self.next);
                    self.pacer.stamp_ns(self.next)
                }
            };
            self.next += 1;
            return Ok(Some(Sample { timestamp_ns, v }));
        }
    }
}

impl Source for CsvSource {
    fn rate_hz(&self) -> f64 {
        self.rate_hz
    }

    fn read(&mut self, out: &mut Vec<Sample>) -> Result<(), SourceError> {
        let block = ((self.rate_hz * BLOCK_S).ceil() as usize).max(1);
        for i in 0..block {
            match self.next_sample()? {
                Some(s) => out.push(s),
                None if i == 0 => return Err(SourceError::End),
                None => break,
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn csv(text: &str, rate_hz: f64) -> CsvSource {
        CsvSource::from_reader(
            "test.csv",
            Box::new(std::io::Cursor::new(text.as_bytes().to_vec())),
            rate_hz,
        )
    }

    fn read_all(s: &mut dyn Source) -> Result<Vec<Sample>, SourceError> {
        let mut out = Vec::new();
        loop {
            match s.read(&mut out) {
                Ok(()) => {}
                Err(SourceError::End) => return Ok(out),
                Err(e) => return Err(e),
            }
        }
    }

    #[test]
    fn csv_with_stamps_keeps_them_and_skips_a_header() {
        let mut s = csv("t_ns,vx,vy,vz\n10,1,2,3\n# note\n\n20,4,5,6.5\n", 100.0);
        let got = read_all(&mut s).unwrap();
        assert_eq!(
            got,
            vec![
                Sample {
                    timestamp_ns: 10,
                    v: [1.0, 2.0, 3.0]
                },
                Sample {
                    timestamp_ns: 20,
                    v: [4.0, 5.0, 6.5]
                },
            ]
        );
    }

    #[test]
    fn csv_without_stamps_is_on_the_rate_grid() {
        let mut s = csv("0,0,1\n0,0,1\n0,0,1\n", 1000.0);
        let got = read_all(&mut s).unwrap();
        assert_eq!(got.len(), 3);
        assert_eq!(got[1].timestamp_ns - got[0].timestamp_ns, 1_000_000);
        assert_eq!(got[2].timestamp_ns - got[0].timestamp_ns, 2_000_000);
    }

    #[test]
    fn csv_errors_name_line_and_field() {
        let e = read_all(&mut csv("1,2,3\n1,x,3\n", 1000.0)).unwrap_err();
        assert_eq!(e.to_string(), "test.csv, line 2: vy: \"x\" is not a number");
        let e = read_all(&mut csv("1,2,3\n1,2,3,4\n", 1000.0)).unwrap_err();
        assert_eq!(
            e.to_string(),
            "test.csv, line 2: 4 fields where the first data line had 3"
        );
        let e = read_all(&mut csv("1,2\n", 1000.0)).unwrap_err();
        assert!(e.to_string().contains("line 1: 2 fields"), "{e}");
    }

    #[test]
    fn sim_is_seeded_and_on_its_grid() {
        let mut a = SimSource::new(1000.0, 7);
        let mut b = SimSource::new(1000.0, 7);
        let (mut va, mut vb) = (Vec::new(), Vec::new());
        a.read(&mut va).unwrap();
        b.read(&mut vb).unwrap();
        let n = va.len().min(vb.len());
        assert!(n >= 20, "a block is about 20 ms: {n}");
        for i in 0..n {
            assert_eq!(va[i].v, vb[i].v);
        }
        for w in va.windows(2) {
            assert_eq!(w[1].timestamp_ns - w[0].timestamp_ns, 1_000_000);
        }
        // Gravity on z, in g.
        assert!((va[0].v[2] - 1.0).abs() < 1e-3);
    }
}
