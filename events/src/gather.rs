//! An event's window of one sensor, from the batches the history gave back, on the sensor's own
//! time grid; and what its calibration record says of its errors.
//!
//! The grid starts at the first sample at or after the window's start, at that batch's rate; a
//! sample within `alignment_tolerance` of a period of a grid point is placed on it, any other is
//! left out (`misaligned`), never resampled; grid points no sample reached are `missing`. A
//! sample flagged `uncalibrated`, `non_finite_input` or `clipped` is unusable; other quality
//! flags (outside the calibrated band or amplitude, an expired or suspect record, outside the
//! calibrated temperatures) leave it used and the sensor `flagged`.

use nalgebra::Matrix3;
use triax_modal::SensorPlacement;
use triax_protocol::batch::{flags, CorrectedBatch, Mode};
use triax_protocol::record::{CalibrationRecord, CalibrationSet};
use triax_strongmotion::process::{SensorCalibration, SensorRecord};

use crate::building::{STREAM_ONLY, UNUSABLE};

/// A sensor's window, with how much of it could be used.
#[derive(Debug, Clone)]
pub struct Gathered {
    pub record: SensorRecord,
    pub calibration_versions: Vec<u64>,
    pub modes: Vec<Mode>,
    pub missing: u64,
    pub misaligned: u64,
    pub unusable: u64,
    /// The union of the caveat flags of the samples used.
    pub caveat_flags: u16,
}

/// The window `[start_ns, end_ns)` of one sensor from its `batches` (any order); none when no
/// sample falls in it. Times are relative to `start_ns`.
pub fn gather(
    placement: &SensorPlacement,
    batches: &[CorrectedBatch],
    start_ns: i64,
    end_ns: i64,
    tolerance: f64,
) -> Option<Gathered> {
    let mut sorted: Vec<&CorrectedBatch> = batches.iter().collect();
    sorted.sort_by_key(|b| b.header.timestamp_ns);
    // The grid: the first sample in the window fixes its rate and phase.
    let (t0, rate) = sorted.iter().find_map(|b| {
        let period = 1e9 / b.header.sample_rate_hz;
        (0..b.samples.len())
            .map(|i| b.header.timestamp_ns + (i as f64 * period) as i64)
            .find(|&t| t >= start_ns && t < end_ns)
            .map(|t| (t, b.header.sample_rate_hz))
    })?;
    let period = 1e9 / rate;
    let n = (((end_ns - t0) as f64 / period).ceil() as usize).max(1);
    let mut accel = vec![[0.0; 3]; n];
    let mut valid = vec![false; n];
    let mut placed = vec![false; n];
    let (mut misaligned, mut unusable, mut caveat_flags) = (0u64, 0u64, 0u16);
    let mut versions = Vec::new();
    let mut modes = Vec::new();
    for b in sorted {
        let h = &b.header;
        let same_rate = (h.sample_rate_hz - rate).abs() <= 1e-9 * rate;
        let bp = 1e9 / h.sample_rate_hz;
        let mut used = false;
        for (i, s) in b.samples.iter().enumerate() {
            let t = h.timestamp_ns as f64 + i as f64 * bp;
            if t < start_ns as f64 || t >= end_ns as f64 {
                continue;
            }
            let x = (t - t0 as f64) / period;
            let k = x.round();
            if !same_rate || (x - k).abs() > tolerance || k < 0.0 || k as usize >= n {
                misaligned += 1;
                continue;
            }
            let k = k as usize;
            if placed[k] {
                continue;
            }
            placed[k] = true;
            let f = b.sample_flags(i) & !STREAM_ONLY;
            let a = s.accel_mps2.map(f64::from);
            if f & UNUSABLE != 0 || a.iter().any(|v| !v.is_finite()) {
                unusable += 1;
                continue;
            }
            caveat_flags |= f;
            accel[k] = a;
            valid[k] = true;
            used = true;
        }
        if used {
            if !versions.contains(&b.info.calibration_version) {
                versions.push(b.info.calibration_version);
            }
            if !modes.contains(&b.info.mode) {
                modes.push(b.info.mode);
            }
        }
    }
    let missing = placed.iter().filter(|p| !**p).count() as u64;
    Some(Gathered {
        record: SensorRecord {
            sensor_id: placement.sensor_id.clone(),
            floor: placement.floor as i32,
            height_m: placement.height_m,
            mounting: placement.mounting,
            start_s: (t0 - start_ns) as f64 * 1e-9,
            sample_rate_hz: rate,
            accel_mps2: accel,
            valid,
            flagged: caveat_flags != 0,
            // Replaced by the record's once it is read.
            calibration: SensorCalibration::noise_only(
                [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
                0.0,
            ),
        },
        calibration_versions: versions,
        modes,
        missing,
        misaligned,
        unusable,
        caveat_flags,
    })
}

/// The set the gateway corrected vibration with in `mode`: the static set in static mode, the
/// dynamic set otherwise (split mode corrects the band above its crossover with it).
fn set_of(record: &CalibrationRecord, mode: Mode) -> &CalibrationSet {
    match mode {
        Mode::Static => &record.static_set,
        _ => &record.dynamic,
    }
}

/// What a record says of its corrected samples' errors (PROTOCOL.md §3.1): the set's
/// sensitivity and the covariance of its nine entries, and the white error of one sample,
/// `S⁻¹·diag(output_noise²)·S⁻ᵀ + diag(uncertainty_mps2²)`, with their degrees of freedom.
pub fn calibration_of(record: &CalibrationRecord, mode: Mode) -> SensorCalibration {
    let set = set_of(record, mode);
    let s = set.sensitivity;
    let sm = Matrix3::from_fn(|i, j| s[i][j]);
    let si = sm.try_inverse().unwrap_or_else(Matrix3::identity);
    let noise = record.sensor.output_noise.unwrap_or([0.0; 3]);
    let n = si
        * Matrix3::from_diagonal(&nalgebra::Vector3::from(noise.map(|v| v * v)))
        * si.transpose();
    let stated = set.uncertainty_mps2;
    let noise_covariance = std::array::from_fn(|i| {
        std::array::from_fn(|j| n[(i, j)] + if i == j { stated[i] * stated[i] } else { 0.0 })
    });
    let sensitivity_covariance = set
        .covariance
        .as_ref()
        .map(|c| std::array::from_fn(|i| std::array::from_fn(|j| c[i][j])));
    let dof = |v: Option<f64>| v.unwrap_or(f64::INFINITY);
    SensorCalibration {
        sensitivity: s,
        sensitivity_covariance,
        covariance_dof: dof(set.covariance_dof),
        noise_covariance,
        noise_dof: dof(record.sensor.output_noise_dof).min(dof(set.uncertainty_dof)),
    }
}

/// With no record to read: the samples' own mean stated variance taken as white noise, and no
/// calibration part (said in the report's caveats).
pub fn calibration_from_samples(batches: &[CorrectedBatch]) -> SensorCalibration {
    let mut sum = [0.0; 3];
    let mut n = 0usize;
    for b in batches {
        for s in &b.samples {
            if s.flags & flags::UNCALIBRATED == 0
                && s.uncertainty_mps2.iter().all(|u| u.is_finite())
            {
                for (total, u) in sum.iter_mut().zip(s.uncertainty_mps2) {
                    *total += f64::from(u).powi(2);
                }
                n += 1;
            }
        }
    }
    let v = sum.map(|x| x / n.max(1) as f64);
    SensorCalibration {
        sensitivity: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
        sensitivity_covariance: None,
        covariance_dof: f64::INFINITY,
        noise_covariance: [[v[0], 0.0, 0.0], [0.0, v[1], 0.0], [0.0, 0.0, v[2]]],
        noise_dof: f64::INFINITY,
    }
}
