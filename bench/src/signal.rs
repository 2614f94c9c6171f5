//! A healthy node's raw batches for the benches (`triax-gateway-bench`'s building profile and
//! `triax-fleet-bench`): a sway that goes on across batches and white noise at the bench
//! record's stated `output_noise` (1 mV), so that the gateway's field health checks see the
//! healthy sensor they would see in a building. (A batch repeated verbatim looks like spikes at
//! every boundary and turns every sensor suspect at once: a one-off, not the steady state.)

use rand::Rng;
use triax_protocol::batch::{BatchHeader, RawBatch};
use triax_protocol::SensorId;

/// Batch `sequence` of `samples` outputs at `sample_rate_hz`, its first sample stamped
/// `timestamp_ns`.
pub fn healthy_batch(
    sensor: &SensorId,
    sequence: u64,
    timestamp_ns: i64,
    samples: usize,
    sample_rate_hz: f64,
    rng: &mut rand::rngs::StdRng,
) -> Vec<u8> {
    let outputs = (0..samples)
        .map(|i| {
            let t = (sequence as usize * samples + i) as f64 / sample_rate_hz;
            let mut noise = || 0.001 * rng.sample::<f64, _>(rand_distr::StandardNormal);
            [
                (0.03 * (2.0 * std::f64::consts::PI * 1.3 * t).sin() + noise()) as f32,
                (0.02 * (2.0 * std::f64::consts::PI * 1.9 * t).cos() + noise()) as f32,
                (0.98 + noise()) as f32,
            ]
        })
        .collect();
    RawBatch {
        header: BatchHeader {
            sensor_id: sensor.clone(),
            sequence,
            timestamp_ns,
            sample_rate_hz,
        },
        temperature_c: None,
        samples: outputs,
    }
    .encode()
}
