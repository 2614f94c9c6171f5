//! Filtered and integrated views: a sensor's acceleration band-passed, or integrated once
//! (velocity) or twice (displacement), within a stated band, decimated per pixel column.
//!
//! Each run of contiguous samples ([`crate::spectrum::Collector`]) is processed alone, never
//! across a break. The filters are second-order Butterworth sections (bilinear transform) run
//! forward and then backward, so that they shift no phase: each band edge is a fourth-order
//! magnitude response, −6 dB at the edge (|H|² of the one section). Velocity is the trapezoidal
//! integral of the band-passed acceleration, high-passed again at the band's lower edge so that
//! the constant of integration and the drift of a residual offset go; displacement is the same
//! step applied to velocity. A run shorter than [`MIN_RUN_S`] is left out, and the first and
//! last [`SETTLE_PERIODS`] periods of the lower edge are read around the view and not shown,
//! so that what is drawn is past the filters' start-up.
//!
//! The ±k·u band is not carried: the uncertainty of an integrated value depends on the band and
//! the correlation of the samples' errors, which the records do not state.

use serde::Serialize;

use crate::spectrum::Collector;

/// Lowest band edge accepted, Hz.
pub const MIN_EDGE_HZ: f64 = 0.01;
/// Periods of the lower edge read before and after the view for the filters to settle.
pub const SETTLE_PERIODS: f64 = 3.0;
/// Most time read around the view for the filters, s.
pub const MAX_SETTLE_S: f64 = 300.0;
/// Shortest run processed, s.
pub const MIN_RUN_S: f64 = 1.0;

/// What is shown.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Quantity {
    Acceleration,
    Velocity,
    Displacement,
}

impl Quantity {
    pub fn parse(s: &str) -> Option<Quantity> {
        match s {
            "acceleration" => Some(Quantity::Acceleration),
            "velocity" => Some(Quantity::Velocity),
            "displacement" => Some(Quantity::Displacement),
            _ => None,
        }
    }

    pub fn unit(self) -> &'static str {
        match self {
            Quantity::Acceleration => "m/s²",
            Quantity::Velocity => "m/s",
            Quantity::Displacement => "m",
        }
    }
}

/// The band: a lower edge (high-pass) and an upper edge (low-pass), either may be absent
/// for acceleration; velocity and displacement need the lower one.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Band {
    pub low_hz: Option<f64>,
    pub high_hz: Option<f64>,
}

impl Band {
    /// `lo-hi`, `lo-` or `-hi` in Hz.
    pub fn parse(s: &str) -> Result<Band, String> {
        let (lo, hi) = s
            .split_once('-')
            .ok_or_else(|| format!("{s:?} is not LOW-HIGH in Hz (either may be left out)"))?;
        let edge = |t: &str| -> Result<Option<f64>, String> {
            if t.is_empty() {
                return Ok(None);
            }
            let f: f64 = t
                .parse()
                .map_err(|_| format!("{t:?} is not a frequency in Hz"))?;
            if !(f.is_finite() && f >= MIN_EDGE_HZ) {
                return Err(format!("{t} Hz is below {MIN_EDGE_HZ} Hz"));
            }
            Ok(Some(f))
        };
        let b = Band {
            low_hz: edge(lo)?,
            high_hz: edge(hi)?,
        };
        if let (Some(l), Some(h)) = (b.low_hz, b.high_hz) {
            if l >= h {
                return Err(format!(
                    "the lower edge {l} Hz is not below the upper {h} Hz"
                ));
            }
        }
        Ok(b)
    }

    /// Time read before and after the view for the filters to settle, ns.
    pub fn settle_ns(&self) -> i64 {
        self.low_hz
            .map_or(0.0, |f| (SETTLE_PERIODS / f).min(MAX_SETTLE_S))
            .mul_add(1e9, 0.0) as i64
    }
}

/// One second-order section, direct form II transposed.
#[derive(Debug, Clone, Copy)]
struct Biquad {
    b: [f64; 3],
    a: [f64; 2],
}

impl Biquad {
    /// Butterworth (Q = 1/√2) low-pass or high-pass at `f_hz` for sampling at `fs_hz`.
    fn butterworth(f_hz: f64, fs_hz: f64, high: bool) -> Biquad {
        let w0 = 2.0 * std::f64::consts::PI * f_hz / fs_hz;
        let (sin, cos) = w0.sin_cos();
        let alpha = sin / std::f64::consts::SQRT_2;
        let a0 = 1.0 + alpha;
        let b = if high {
            [(1.0 + cos) / 2.0, -(1.0 + cos), (1.0 + cos) / 2.0]
        } else {
            [(1.0 - cos) / 2.0, 1.0 - cos, (1.0 - cos) / 2.0]
        };
        Biquad {
            b: b.map(|x| x / a0),
            a: [-2.0 * cos / a0, (1.0 - alpha) / a0],
        }
    }

    fn dc_gain(&self) -> f64 {
        (self.b[0] + self.b[1] + self.b[2]) / (1.0 + self.a[0] + self.a[1])
    }

    /// Filters `x` in place, starting in the steady state of its first value.
    fn run(&self, x: &mut [f64]) {
        let Some(&x0) = x.first() else { return };
        let g = self.dc_gain();
        let (mut z1, mut z2) = ((g - self.b[0]) * x0, (self.b[2] - self.a[1] * g) * x0);
        for v in x.iter_mut() {
            let y = self.b[0] * *v + z1;
            z1 = self.b[1] * *v - self.a[0] * y + z2;
            z2 = self.b[2] * *v - self.a[1] * y;
            *v = y;
        }
    }

    /// Forward, then backward: no phase shift.
    fn zero_phase(&self, x: &mut [f64]) {
        self.run(x);
        x.reverse();
        self.run(x);
        x.reverse();
    }
}

fn high_pass(x: &mut [f64], f: Option<f64>, fs: f64) {
    if let Some(f) = f.filter(|f| *f < fs / 2.0) {
        let mean = x.iter().sum::<f64>() / x.len().max(1) as f64;
        x.iter_mut().for_each(|v| *v -= mean);
        Biquad::butterworth(f, fs, true).zero_phase(x);
    }
}

fn low_pass(x: &mut [f64], f: Option<f64>, fs: f64) {
    if let Some(f) = f.filter(|f| *f < fs / 2.0) {
        Biquad::butterworth(f, fs, false).zero_phase(x);
    }
}

fn integrate(x: &mut [f64], fs: f64) {
    let dt = 1.0 / fs;
    let mut acc = 0.0;
    let mut prev = x.first().copied().unwrap_or(0.0);
    for v in x.iter_mut() {
        acc += 0.5 * (prev + *v) * dt;
        prev = *v;
        *v = acc;
    }
}

/// The processed signal of one run, per axis.
pub fn process(values: &[Vec<f32>; 3], fs: f64, q: Quantity, band: Band) -> [Vec<f64>; 3] {
    values.clone().map(|axis| {
        let mut x: Vec<f64> = axis.iter().map(|v| f64::from(*v)).collect();
        high_pass(&mut x, band.low_hz, fs);
        low_pass(&mut x, band.high_hz, fs);
        let times = match q {
            Quantity::Acceleration => 0,
            Quantity::Velocity => 1,
            Quantity::Displacement => 2,
        };
        for _ in 0..times {
            integrate(&mut x, fs);
            high_pass(&mut x, band.low_hz, fs);
        }
        x
    })
}

/// A processed view, decimated: per bucket and axis the min and max.
#[derive(Debug, Clone, Serialize)]
pub struct ProcessedView {
    pub quantity: Quantity,
    pub unit: &'static str,
    pub band: Band,
    pub filter: &'static str,
    pub from_ns: i64,
    pub to_ns: i64,
    pub bucket_ns: i64,
    /// `[index, min_x, max_x, min_y, max_y, min_z, max_z]`, index = floor(t / bucket_ns).
    pub buckets: Vec<[f64; 7]>,
    /// The runs shown, `[start_ns, end_ns]`: breaks between them are not drawn across.
    pub runs: Vec<[i64; 2]>,
    pub samples_used: usize,
    /// Runs left out for being shorter than [`MIN_RUN_S`].
    pub runs_too_short: usize,
}

pub const FILTER: &str = "Butterworth 2nd-order sections run forward and backward (zero phase, -6 dB at each edge); integration trapezoidal, high-passed again at the lower edge";

/// Processes what `c` gathered (over the view and the settling time around it) and keeps
/// `[from_ns, to_ns)` in buckets of `bucket_ns`.
pub fn view(
    c: &Collector,
    q: Quantity,
    band: Band,
    from_ns: i64,
    to_ns: i64,
    bucket_ns: i64,
) -> ProcessedView {
    let mut buckets: std::collections::BTreeMap<i64, [f64; 7]> = Default::default();
    let mut runs = Vec::new();
    let mut used = 0;
    let mut short = 0;
    for (fs, start_ns, values) in c.runs() {
        let n = values[0].len();
        if (n as f64) < MIN_RUN_S * fs {
            short += 1;
            continue;
        }
        let out = process(values, fs, q, band);
        let period_ns = 1e9 / fs;
        let (mut first, mut last) = (None, None);
        #[allow(clippy::needless_range_loop)] // i indexes the time and three axes at once
        for i in 0..n {
            let t = (start_ns + i as f64 * period_ns) as i64;
            if t < from_ns || t >= to_ns {
                continue;
            }
            first.get_or_insert(t);
            last = Some(t + period_ns as i64);
            used += 1;
            let idx = t.div_euclid(bucket_ns);
            let b = buckets.entry(idx).or_insert_with(|| {
                let mut b = [f64::INFINITY; 7];
                b[0] = idx as f64;
                for k in 0..3 {
                    b[2 + 2 * k] = f64::NEG_INFINITY;
                }
                b
            });
            for k in 0..3 {
                b[1 + 2 * k] = b[1 + 2 * k].min(out[k][i]);
                b[2 + 2 * k] = b[2 + 2 * k].max(out[k][i]);
            }
        }
        if let (Some(a), Some(b)) = (first, last) {
            runs.push([a, b]);
        }
    }
    ProcessedView {
        quantity: q,
        unit: q.unit(),
        band,
        filter: FILTER,
        from_ns,
        to_ns,
        bucket_ns,
        buckets: buckets.into_values().collect(),
        runs,
        samples_used: used,
        runs_too_short: short,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::f64::consts::PI;

    fn sine(a: f64, f: f64, fs: f64, n: usize, offset: f64) -> Vec<f32> {
        (0..n)
            .map(|i| (offset + a * (2.0 * PI * f * i as f64 / fs).sin()) as f32)
            .collect()
    }

    fn peak_middle(x: &[f64]) -> f64 {
        let n = x.len();
        x[n / 4..3 * n / 4]
            .iter()
            .fold(0.0f64, |m, v| m.max(v.abs()))
    }

    #[test]
    fn a_sway_integrates_to_its_velocity_and_displacement() {
        // 0.05 m/s² at 2.5 Hz over gravity: velocity a/ω, displacement a/ω².
        let (a, f, fs) = (0.05, 2.5, 100.0);
        let v = [
            sine(a, f, fs, 6000, 0.0),
            sine(0.0, f, fs, 6000, 0.0),
            sine(0.0, f, fs, 6000, 9.81),
        ];
        let band = Band::parse("0.2-20").unwrap();
        let w = 2.0 * PI * f;
        // Each zero-phase edge passes |H|², for a 2nd-order Butterworth 1/(1 + (fc/f)^4) at the
        // lower edge, 1/(1 + (f/fc)^4) at the upper; velocity passes the lower edge twice,
        // displacement three times.
        // With the bilinear transform, frequencies map through tan(πf/fs).
        let t = |x: f64| (PI * x / fs).tan();
        let hp = 1.0 / (1.0 + (t(0.2) / t(f)).powi(4));
        let lp = 1.0 / (1.0 + (t(f) / t(20.0)).powi(4));
        // The trapezoid integrates a sinusoid with the gain (ωT/2)/tan(ωT/2) of 1/ω.
        let half = w / fs / 2.0;
        let trap = half / half.tan();
        let out = process(&v, fs, Quantity::Velocity, band);
        let want = a / w * trap * hp * hp * lp;
        assert!(
            (peak_middle(&out[0]) / want - 1.0).abs() < 1e-3,
            "{} vs {want}",
            peak_middle(&out[0])
        );
        assert!(
            peak_middle(&out[2]) < 1e-9,
            "gravity is no velocity: {}",
            peak_middle(&out[2])
        );
        let out = process(&v, fs, Quantity::Displacement, band);
        let want = a / (w * w) * trap * trap * hp * hp * hp * lp;
        assert!(
            (peak_middle(&out[0]) / want - 1.0).abs() < 1e-3,
            "{} vs {want}",
            peak_middle(&out[0])
        );
        // A band-pass that leaves the sway out: 5-20 Hz.
        let out = process(&v, fs, Quantity::Acceleration, Band::parse("5-20").unwrap());
        let pass = 1.0 / (1.0 + (t(5.0) / t(f)).powi(4)) / (1.0 + (t(f) / t(20.0)).powi(4));
        assert!(
            (peak_middle(&out[0]) / (a * pass) - 1.0).abs() < 2e-3,
            "{}",
            peak_middle(&out[0])
        );
    }

    #[test]
    fn bands_are_checked() {
        assert_eq!(Band::parse("0.1-").unwrap().high_hz, None);
        assert_eq!(Band::parse("-10").unwrap().low_hz, None);
        for bad in ["1", "x-2", "2-1", "0.001-1", "nan-1"] {
            assert!(Band::parse(bad).is_err(), "{bad}");
        }
        assert_eq!(Band::parse("1-").unwrap().settle_ns(), 3_000_000_000);
    }
}
