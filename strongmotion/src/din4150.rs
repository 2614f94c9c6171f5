//! DIN 4150-3 (2016-12), vibration of structures: peak component velocity against the
//! guideline curves, with the dominant frequency.
//!
//! Guideline values `v_i` (mm/s) for the three building classes (line 1: commercial and
//! industrial buildings; line 2: dwellings and buildings of similar design; line 3: structures
//! particularly sensitive to vibration):
//!
//! | | foundation 1–10 Hz | 10–50 Hz | 50–100 Hz | top floor, horizontal | top floor, long-term |
//! |---|---|---|---|---|---|
//! | line 1 | 20 | 20 → 40 | 40 → 50 | 40 | 10 |
//! | line 2 | 5 | 5 → 15 | 15 → 20 | 15 | 5 |
//! | line 3 | 3 | 3 → 8 | 8 → 10 | 8 | 2.5 |
//!
//! Between the table's corners the foundation's value is taken linear in frequency; below 1 Hz
//! the 1–10 Hz value, above 100 Hz the 100 Hz value (the standard: "at least"). The short-term
//! values apply to vibration that does not occur often enough to fatigue the structure or excite
//! resonance (blasting, demolition, a single event); long-term ones to the rest (traffic,
//! vibratory compaction, machines), judged at the top floor in the horizontal directions.
//!
//! The dominant frequency is that of the half cycle holding the peak: the reciprocal of twice
//! the time between the velocity's zero crossings around it (linear between samples), the
//! standard's zero-crossing method.

use serde::{Deserialize, Serialize};

/// The standard's building classes, by line of its table.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum BuildingClass {
    #[serde(rename = "1")]
    Line1,
    #[serde(rename = "2")]
    Line2,
    #[serde(rename = "3")]
    Line3,
}

impl BuildingClass {
    fn row(self) -> usize {
        match self {
            BuildingClass::Line1 => 0,
            BuildingClass::Line2 => 1,
            BuildingClass::Line3 => 2,
        }
    }

    /// The class's number, 1 to 3.
    pub fn number(self) -> u8 {
        self.row() as u8 + 1
    }
}

/// Foundation corners per class: (frequency Hz, value mm/s).
const FOUNDATION: [[(f64, f64); 4]; 3] = [
    [(1.0, 20.0), (10.0, 20.0), (50.0, 40.0), (100.0, 50.0)],
    [(1.0, 5.0), (10.0, 5.0), (50.0, 15.0), (100.0, 20.0)],
    [(1.0, 3.0), (10.0, 3.0), (50.0, 8.0), (100.0, 10.0)],
];
const TOP_FLOOR_SHORT_MMPS: [f64; 3] = [40.0, 15.0, 8.0];
const TOP_FLOOR_LONG_MMPS: [f64; 3] = [10.0, 5.0, 2.5];

/// The foundation's guideline value at `f_hz` (mm/s) and its slope (mm/s per Hz).
pub fn foundation_mmps(class: BuildingClass, f_hz: f64) -> (f64, f64) {
    let c = &FOUNDATION[class.row()];
    if f_hz <= c[0].0 {
        return (c[0].1, 0.0);
    }
    for w in c.windows(2) {
        let ((f0, v0), (f1, v1)) = (w[0], w[1]);
        if f_hz <= f1 {
            let slope = (v1 - v0) / (f1 - f0);
            return (v0 + slope * (f_hz - f0), slope);
        }
    }
    (c[3].1, 0.0)
}

/// The top floor's horizontal guideline value, short-term, mm/s.
pub fn top_floor_short_mmps(class: BuildingClass) -> f64 {
    TOP_FLOOR_SHORT_MMPS[class.row()]
}

/// The top floor's horizontal guideline value, long-term, mm/s.
pub fn top_floor_long_mmps(class: BuildingClass) -> f64 {
    TOP_FLOOR_LONG_MMPS[class.row()]
}

/// The dominant frequency at sample `peak` of velocity `v` (interval `dt`), and its standard
/// uncertainty from the velocity's noise `sd_v` at the two crossings; none without a crossing
/// on each side.
pub fn dominant_frequency(v: &[f64], peak: usize, dt: f64, sd_v: f64) -> Option<(f64, f64)> {
    let sign = v.get(peak)?.signum();
    // The crossing before: the last sample pair (i − 1, i) at or before the peak changing sign.
    let mut before = None;
    for i in (1..=peak).rev() {
        if v[i - 1].signum() != sign {
            before = Some(i - 1);
            break;
        }
    }
    let mut after = None;
    for i in peak..v.len() - 1 {
        if v[i + 1].signum() != sign {
            after = Some(i);
            break;
        }
    }
    let (b, a) = (before?, after?);
    let cross = |i: usize| {
        let (x0, x1) = (v[i], v[i + 1]);
        let frac = x0 / (x0 - x1);
        let slope = (x1 - x0).abs() / dt;
        ((i as f64 + frac) * dt, slope)
    };
    let ((t0, s0), (t1, s1)) = (cross(b), cross(a));
    let half = t1 - t0;
    if half <= 0.0 {
        return None;
    }
    let f = 1.0 / (2.0 * half);
    // A crossing moves by the noise over the slope there; f = 1/(2·half).
    let u_half = ((sd_v / s0).powi(2) + (sd_v / s1).powi(2)).sqrt();
    Some((f, f * u_half / half))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_curves_at_their_corners_and_between() {
        assert_eq!(foundation_mmps(BuildingClass::Line1, 5.0), (20.0, 0.0));
        assert_eq!(foundation_mmps(BuildingClass::Line2, 0.5), (5.0, 0.0));
        assert_eq!(foundation_mmps(BuildingClass::Line2, 10.0).0, 5.0);
        // 30 Hz is halfway from 10 to 50: 5 + (15 − 5)/2.
        let (v, s) = foundation_mmps(BuildingClass::Line2, 30.0);
        assert!((v - 10.0).abs() < 1e-12 && (s - 0.25).abs() < 1e-12);
        assert!((foundation_mmps(BuildingClass::Line3, 75.0).0 - 9.0).abs() < 1e-12);
        assert_eq!(foundation_mmps(BuildingClass::Line1, 200.0), (50.0, 0.0));
        assert_eq!(top_floor_short_mmps(BuildingClass::Line3), 8.0);
        assert_eq!(top_floor_long_mmps(BuildingClass::Line1), 10.0);
        assert_eq!(BuildingClass::Line2.number(), 2);
    }

    #[test]
    fn the_dominant_frequency_of_a_sine() {
        let dt = 0.001;
        let f = 12.5;
        let v: Vec<f64> = (0..1000)
            .map(|i| (2.0 * std::f64::consts::PI * f * (i as f64 * dt + 0.0003)).sin())
            .collect();
        let peak = (400..600)
            .max_by(|&a, &b| v[a].abs().total_cmp(&v[b].abs()))
            .unwrap();
        let (got, u) = dominant_frequency(&v, peak, dt, 0.0).unwrap();
        assert!((got - f).abs() < 0.01, "{got}");
        assert_eq!(u, 0.0);
        let (_, u) = dominant_frequency(&v, peak, dt, 0.01).unwrap();
        // Each crossing moves by 0.01/(2π·12.5) s; f by f·√2·that/(1/25 s).
        let want = f * 2f64.sqrt() * 0.01 / (2.0 * std::f64::consts::PI * f) * 2.0 * f;
        assert!((u - want).abs() < 0.02 * want, "{u} vs {want}");
    }
}
