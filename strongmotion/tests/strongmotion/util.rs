//! Records for the tests.

use triax_strongmotion::process::{SensorCalibration, SensorRecord};

pub const IDENTITY: [[f64; 3]; 3] = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];

/// A record of `seconds` at `rate_hz` starting at `start_s`, its acceleration `f(t)` (sensor
/// axes, gravity on z added), all samples valid, with `calibration`.
pub fn record(
    rate_hz: f64,
    start_s: f64,
    seconds: f64,
    f: impl Fn(f64) -> [f64; 3],
    calibration: SensorCalibration,
) -> SensorRecord {
    let n = (seconds * rate_hz).round() as usize;
    let accel_mps2: Vec<[f64; 3]> = (0..n)
        .map(|i| {
            let t = start_s + i as f64 / rate_hz;
            let a = f(t);
            [a[0], a[1], a[2] + 9.81]
        })
        .collect();
    SensorRecord {
        sensor_id: "s1".into(),
        floor: 0,
        height_m: 0.0,
        mounting: IDENTITY,
        start_s,
        sample_rate_hz: rate_hz,
        valid: vec![true; n],
        flagged: false,
        accel_mps2,
        calibration,
    }
}

/// A sensitivity covariance with `variance` on entry `(i, j)` of S only.
pub fn covariance_on(i: usize, j: usize, variance: f64) -> [[f64; 9]; 9] {
    let mut c = [[0.0; 9]; 9];
    c[3 * i + j][3 * i + j] = variance;
    c
}
