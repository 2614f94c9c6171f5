//! A window of the building's corrected streams, and the channels identification works on.
//!
//! The caller (the modal service) puts every sensor's corrected samples on one time grid: sample
//! `m` of every sensor is at `start_timestamp_ns + m / sample_rate_hz`, in the sensor's own axes,
//! m/s². A sample the gateway flagged, or one missing from the stream (a gap), is marked invalid
//! in `valid` and its value is ignored. Nothing is interpolated: a gap stays a gap.
//!
//! From there ([`Channels::from_window`]):
//!
//! 1. each sensor's three axes are rotated into the building frame with its mounting; a
//!    building-frame sample is valid only when all three axes were, since the rotation mixes
//!    them;
//! 2. the horizontal directions asked for become channels, low-pass filtered and decimated
//!    (a Blackman-windowed sinc, linear phase, the same for every channel, so shapes and
//!    phases are untouched); a decimated sample is valid only if every input sample under
//!    the filter was, so a gap widens by the filter's length and nothing of it leaks in;
//! 3. each channel's mean over its valid samples is removed.
//!
//! A channel with less than `min_valid_fraction` of its samples valid after this refuses the
//! whole window ([`crate::ModalError::TooMuchMissing`]): the correlations would rest on too
//! little data for their uncertainty to mean what it says.

use nalgebra::Matrix3;
use serde::{Deserialize, Serialize};

use crate::error::ModalError;
use crate::model::{BuildingModel, Direction};

/// What the measurement chain of one sensor adds to a mode shape, from its calibration record
/// and its node's clock: standard uncertainties (k = 1).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ChainUncertainty {
    /// Relative standard uncertainty of each axis's gain after correction (0.003 for 0.3 %).
    pub gain_relative_u: [f64; 3],
    /// Standard uncertainty of each of the six cross-axis sensitivities after correction, as a
    /// fraction of the main axis (rad for a misalignment).
    pub cross_axis_u: f64,
    /// Degrees of freedom of those uncertainties (the record's; infinite when it states none).
    pub dof: f64,
    /// Standard uncertainty of the node's time stamps relative to the building's other nodes, s.
    pub timestamp_u_s: f64,
}

impl ChainUncertainty {
    /// A perfect chain: shapes carry only their statistical uncertainty.
    pub const NONE: ChainUncertainty = ChainUncertainty {
        gain_relative_u: [0.0; 3],
        cross_axis_u: 0.0,
        dof: f64::INFINITY,
        timestamp_u_s: 0.0,
    };
}

/// One sensor's corrected samples over the window, in its own axes.
#[derive(Debug, Clone, PartialEq)]
pub struct SensorSeries {
    pub sensor_id: String,
    /// Corrected acceleration, m/s², one per sample of the window's grid.
    pub acceleration_mps2: Vec<[f64; 3]>,
    /// Whether each sample is usable (not flagged, not missing). Same length as the samples.
    pub valid: Vec<bool>,
    /// The chain's uncertainty for this sensor, in force over the window.
    pub chain: ChainUncertainty,
}

/// A window of the building's streams on a common time grid.
#[derive(Debug, Clone, PartialEq)]
pub struct Window {
    pub start_timestamp_ns: i64,
    pub sample_rate_hz: f64,
    pub sensors: Vec<SensorSeries>,
}

impl Window {
    /// Samples per sensor (the first sensor's; [`Channels::from_window`] checks all agree).
    pub fn len(&self) -> usize {
        self.sensors
            .first()
            .map_or(0, |s| s.acceleration_mps2.len())
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Duration covered by the grid, s.
    pub fn duration_s(&self) -> f64 {
        self.len() as f64 / self.sample_rate_hz
    }
}

/// A channel: one sensor's motion along one direction of the building.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ChannelId {
    pub sensor_id: String,
    pub direction: Direction,
}

/// The channels identification runs on: building-frame, decimated, mean removed.
#[derive(Debug, Clone)]
pub struct Channels {
    pub ids: Vec<ChannelId>,
    /// Index of each channel's sensor in the model.
    pub sensor_index: Vec<usize>,
    /// Channel-major samples; an invalid sample holds 0 so that products with it vanish.
    pub data: Vec<Vec<f64>>,
    /// Channel-major validity as 0.0 or 1.0, for counting valid pairs by dot products.
    pub mask: Vec<Vec<f64>>,
    /// Whether every sample of the channel is valid (counts are then known without summing).
    pub complete: Vec<bool>,
    pub sample_rate_hz: f64,
    pub decimation: usize,
    pub start_timestamp_ns: i64,
    /// Rotation of each model sensor (sensor axes into the building frame).
    pub rotations: Vec<Matrix3<f64>>,
    /// Chain uncertainty of each model sensor.
    pub chains: Vec<ChainUncertainty>,
    /// Share of valid samples per channel after decimation.
    pub valid_fraction: Vec<f64>,
}

/// Options of the channel preparation.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ChannelOptions {
    /// Directions that become channels.
    pub directions: Vec<Direction>,
    /// Highest frequency of interest, Hz: the decimation keeps it clear of aliasing.
    pub max_frequency_hz: f64,
    /// Refuse a window in which any channel has fewer valid samples than this share.
    pub min_valid_fraction: f64,
}

impl Default for ChannelOptions {
    fn default() -> Self {
        ChannelOptions {
            directions: vec![Direction::X, Direction::Y],
            max_frequency_hz: 8.0,
            min_valid_fraction: 0.8,
        }
    }
}

/// Blackman's transition width, in units of the sampling rate over the number of taps.
const BLACKMAN_TRANSITION: f64 = 5.5;

/// Decimation factor and low-pass taps for a rate and a highest frequency of interest: the
/// output rate is at least three times `max_frequency_hz`, so that the band from `max` to
/// `rate_out − max` (what would fold back into the band of interest) is the filter's
/// transition and stop band.
pub fn decimation_filter(sample_rate_hz: f64, max_frequency_hz: f64) -> (usize, Vec<f64>) {
    let factor = ((sample_rate_hz / (3.0 * max_frequency_hz)).floor() as usize).max(1);
    if factor == 1 {
        return (1, vec![1.0]);
    }
    let rate_out = sample_rate_hz / factor as f64;
    let transition_hz = (rate_out - 2.0 * max_frequency_hz).max(0.1 * rate_out);
    let mut taps = (BLACKMAN_TRANSITION * sample_rate_hz / transition_hz).ceil() as usize;
    taps |= 1;
    let cutoff = 0.5 * rate_out / sample_rate_hz;
    let centre = (taps / 2) as f64;
    let mut h: Vec<f64> = (0..taps)
        .map(|n| {
            let x = n as f64 - centre;
            let sinc = if x == 0.0 {
                2.0 * cutoff
            } else {
                (2.0 * std::f64::consts::PI * cutoff * x).sin() / (std::f64::consts::PI * x)
            };
            let w = 2.0 * std::f64::consts::PI * n as f64 / (taps - 1) as f64;
            sinc * (0.42 - 0.5 * w.cos() + 0.08 * (2.0 * w).cos())
        })
        .collect();
    let sum: f64 = h.iter().sum();
    h.iter_mut().for_each(|v| *v /= sum);
    (factor, h)
}

impl Channels {
    /// Rotates, decimates and centres a window's streams (see the module's documentation).
    pub fn from_window(
        model: &BuildingModel,
        window: &Window,
        options: &ChannelOptions,
    ) -> Result<Channels, ModalError> {
        if !(window.sample_rate_hz.is_finite() && window.sample_rate_hz > 0.0) {
            return Err(ModalError::InvalidRate(window.sample_rate_hz));
        }
        if !(options.max_frequency_hz > 0.0
            && options.max_frequency_hz < 0.5 * window.sample_rate_hz)
        {
            return Err(ModalError::InvalidOption {
                field: "max_frequency_hz",
                reason: format!(
                    "{} Hz is not below the Nyquist frequency of {} Hz",
                    options.max_frequency_hz,
                    0.5 * window.sample_rate_hz
                ),
            });
        }
        let n = window.len();
        let mut rotations = vec![Matrix3::identity(); model.sensors.len()];
        let mut chains = vec![ChainUncertainty::NONE; model.sensors.len()];
        let mut present = vec![false; model.sensors.len()];
        let (factor, taps) = decimation_filter(window.sample_rate_hz, options.max_frequency_hz);
        let mut ids = Vec::new();
        let mut sensor_index = Vec::new();
        let mut data = Vec::new();
        let mut mask = Vec::new();
        let mut complete = Vec::new();
        let mut valid_fraction = Vec::new();
        for series in &window.sensors {
            let index =
                model
                    .sensor_index(&series.sensor_id)
                    .ok_or_else(|| ModalError::UnknownSensor {
                        sensor_id: series.sensor_id.clone(),
                    })?;
            if present[index] {
                return Err(ModalError::DuplicateSeries {
                    sensor_id: series.sensor_id.clone(),
                });
            }
            present[index] = true;
            if series.acceleration_mps2.len() != n || series.valid.len() != n {
                return Err(ModalError::LengthMismatch {
                    sensor_id: series.sensor_id.clone(),
                    samples: series.acceleration_mps2.len(),
                    valid: series.valid.len(),
                    expected: n,
                });
            }
            let r = model.sensors[index].rotation();
            rotations[index] = r;
            chains[index] = series.chain;
            for &direction in &options.directions {
                let row = r.row(direction.index());
                let mut raw = vec![0.0; n];
                let mut ok = vec![false; n];
                for (m, (a, &v)) in series
                    .acceleration_mps2
                    .iter()
                    .zip(&series.valid)
                    .enumerate()
                {
                    let value = row[0] * a[0] + row[1] * a[1] + row[2] * a[2];
                    if v && value.is_finite() {
                        raw[m] = value;
                        ok[m] = true;
                    }
                }
                let (values, valid) = decimate(&raw, &ok, factor, &taps);
                let count = valid.iter().filter(|&&v| v).count();
                let fraction = if valid.is_empty() {
                    0.0
                } else {
                    count as f64 / valid.len() as f64
                };
                if fraction < options.min_valid_fraction || count == 0 {
                    return Err(ModalError::TooMuchMissing {
                        sensor_id: series.sensor_id.clone(),
                        direction,
                        valid_fraction: fraction,
                        required: options.min_valid_fraction,
                    });
                }
                let mean = values
                    .iter()
                    .zip(&valid)
                    .filter(|(_, &v)| v)
                    .map(|(x, _)| x)
                    .sum::<f64>()
                    / count as f64;
                let centred: Vec<f64> = values
                    .iter()
                    .zip(&valid)
                    .map(|(x, &v)| if v { x - mean } else { 0.0 })
                    .collect();
                ids.push(ChannelId {
                    sensor_id: series.sensor_id.clone(),
                    direction,
                });
                sensor_index.push(index);
                data.push(centred);
                complete.push(count == valid.len());
                mask.push(valid.iter().map(|&v| f64::from(u8::from(v))).collect());
                valid_fraction.push(fraction);
            }
        }
        if ids.len() < 2 {
            return Err(ModalError::TooFewChannels(ids.len()));
        }
        Ok(Channels {
            ids,
            sensor_index,
            data,
            mask,
            complete,
            sample_rate_hz: window.sample_rate_hz / factor as f64,
            decimation: factor,
            start_timestamp_ns: window.start_timestamp_ns,
            rotations,
            chains,
            valid_fraction,
        })
    }

    /// Samples per channel.
    pub fn len(&self) -> usize {
        self.data.first().map_or(0, Vec::len)
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

/// Low-pass filters and keeps every `factor`-th sample; an output is valid only if every
/// input under the filter was.
fn decimate(raw: &[f64], ok: &[bool], factor: usize, taps: &[f64]) -> (Vec<f64>, Vec<bool>) {
    let len = taps.len();
    if raw.len() < len {
        return (Vec::new(), Vec::new());
    }
    // Prefix count of invalid samples: an output's support is checked in O(1).
    let mut bad = Vec::with_capacity(raw.len() + 1);
    bad.push(0usize);
    for &v in ok {
        let last = bad[bad.len() - 1];
        bad.push(last + usize::from(!v));
    }
    let outputs = (raw.len() - len) / factor + 1;
    let mut values = Vec::with_capacity(outputs);
    let mut valid = Vec::with_capacity(outputs);
    for m in 0..outputs {
        let start = m * factor;
        let good = bad[start + len] == bad[start];
        valid.push(good);
        values.push(if good {
            raw[start..start + len]
                .iter()
                .zip(taps)
                .map(|(x, h)| x * h)
                .sum()
        } else {
            0.0
        });
    }
    (values, valid)
}
