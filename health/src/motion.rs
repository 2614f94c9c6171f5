//! What a building does to its sensors besides its sway: the motion the field checks must not
//! take for a change of the sensor.
//!
//! The checks were once tuned on a building that shook at two frequencies; an occupied
//! building is louder and richer than that, and every part of what follows is there because
//! some test would read it as the sensor's own doing:
//!
//! - **broadband ambient** (wind, traffic): white noise band-passed to `ambient_band_hz`
//!   (second-order Butterworth edges; no upper edge at or above 0.45 of the sample rate, so
//!   that the ambient is then white up to Nyquist, the hardest case for a noise estimate);
//! - **machinery**: tones in `machine_band_hz` (below 0.45 of the sample rate, as a sensor's
//!   anti-alias filter would leave them) with a second harmonic, each on a schedule of its own
//!   (one round the clock, the others by day), their frequency wandering slowly;
//! - **footfall**: walking episodes at 1.5–3 steps a second, mostly vertical, the step rate's
//!   first four harmonics;
//! - **transients**: door slams (a structural ring of 10–30 Hz decaying in a fraction of a
//!   second), vehicles (3–12 s bursts of 2–20 Hz), lift starts and stops (vertical pulses of
//!   about 2 s), each a Poisson process, by day more than by night;
//! - **slow drifts** of the level: a smooth day profile (night to day between 05:00 and 07:00,
//!   back between 21:00 and 23:00) times a log-normal wander with a half-hour memory.
//!
//! Every level is an RMS per axis in m/s² (peaks for transients), in the sensor's frame, with
//! "vertical" the sensor's `up`. Pure and seeded: the same configuration gives the same motion.

use std::f64::consts::PI;

use rand::rngs::SmallRng;
use rand::{Rng, SeedableRng};
use rand_distr::StandardNormal;

/// The field's motion beyond the building's modes. [`FieldMotion::none`] adds nothing;
/// [`FieldMotion::occupied`] is an ordinary office building; [`FieldMotion::busy`] a building
/// with a plant room and a road beside it.
#[derive(Debug, Clone, PartialEq)]
pub struct FieldMotion {
    pub ambient_band_hz: [f64; 2],
    /// RMS per axis of the broadband ambient by day and by night, m/s².
    pub ambient_day_mps2: f64,
    pub ambient_night_mps2: f64,
    /// Standard deviation of the log-level wander (0: none), and its correlation time, s.
    pub wander: f64,
    pub wander_tau_s: f64,
    /// Machines: how many, where their tones lie, and their RMS per axis range, m/s².
    pub machines: usize,
    pub machine_band_hz: [f64; 2],
    pub machine_mps2: [f64; 2],
    /// Walking episodes an hour by day and by night, and a step's peak range, m/s².
    pub walks_per_hour: [f64; 2],
    pub step_mps2: [f64; 2],
    /// Door slams, vehicles and lift runs an hour, by day and by night.
    pub doors_per_hour: [f64; 2],
    pub door_peak_mps2: [f64; 2],
    pub vehicles_per_hour: [f64; 2],
    pub vehicle_rms_mps2: [f64; 2],
    pub lifts_per_hour: [f64; 2],
    pub lift_peak_mps2: [f64; 2],
    /// Sways an hour (by day, by night): one to ten minutes of one sinusoid in `sway_hz` at an
    /// amplitude in `sway_mps2`, as an alerting test or a machine's resonance drives a sensor
    /// near the limits of its record's frequency domain.
    pub sways_per_hour: [f64; 2],
    pub sway_hz: [f64; 2],
    pub sway_mps2: [f64; 2],
}

impl FieldMotion {
    /// Nothing beyond the modes.
    pub fn none() -> FieldMotion {
        FieldMotion {
            ambient_band_hz: [0.5, 25.0],
            ambient_day_mps2: 0.0,
            ambient_night_mps2: 0.0,
            wander: 0.0,
            wander_tau_s: 1800.0,
            machines: 0,
            machine_band_hz: [10.0, 50.0],
            machine_mps2: [0.0, 0.0],
            walks_per_hour: [0.0, 0.0],
            step_mps2: [0.0, 0.0],
            doors_per_hour: [0.0, 0.0],
            door_peak_mps2: [0.0, 0.0],
            vehicles_per_hour: [0.0, 0.0],
            vehicle_rms_mps2: [0.0, 0.0],
            lifts_per_hour: [0.0, 0.0],
            lift_peak_mps2: [0.0, 0.0],
            sways_per_hour: [0.0, 0.0],
            sway_hz: [0.5, 10.0],
            sway_mps2: [0.0, 0.0],
        }
    }

    /// An occupied office building: ambient 0.5–25 Hz at 5 mm/s² by day (1 mm/s² at night)
    /// wandering ±30 %, three machines of 0.5–3 mm/s² in 10–50 Hz, a dozen walks an hour with
    /// steps of 5–30 mm/s², and every hour by day six door slams of up to 0.2 m/s², four
    /// vehicles of 0.03–0.15 m/s² and four lift runs.
    pub fn occupied() -> FieldMotion {
        FieldMotion {
            ambient_band_hz: [0.5, 25.0],
            ambient_day_mps2: 0.005,
            ambient_night_mps2: 0.001,
            wander: 0.3,
            wander_tau_s: 1800.0,
            machines: 3,
            machine_band_hz: [10.0, 50.0],
            machine_mps2: [0.0005, 0.003],
            walks_per_hour: [12.0, 1.0],
            step_mps2: [0.005, 0.03],
            doors_per_hour: [6.0, 0.5],
            door_peak_mps2: [0.02, 0.2],
            vehicles_per_hour: [4.0, 1.0],
            vehicle_rms_mps2: [0.03, 0.15],
            lifts_per_hour: [4.0, 0.5],
            lift_peak_mps2: [0.01, 0.05],
            sways_per_hour: [0.0, 0.0],
            sway_hz: [0.5, 10.0],
            sway_mps2: [0.0, 0.0],
        }
    }

    /// The occupied building with a sway of 0.05–0.5 m/s² at 8–12 Hz (about a record's
    /// 10 Hz frequency limit) or 0.1–1 Hz, twice an hour, day and night.
    pub fn swaying() -> FieldMotion {
        FieldMotion {
            sways_per_hour: [2.0, 2.0],
            sway_hz: [8.0, 12.0],
            sway_mps2: [0.05, 0.5],
            ..FieldMotion::occupied()
        }
    }

    /// A plant room and a road: the ambient twice as loud and a fifth of it at night, six
    /// machines of up to 10 mm/s², and transients three times as often.
    pub fn busy() -> FieldMotion {
        let o = FieldMotion::occupied();
        FieldMotion {
            ambient_day_mps2: 0.01,
            ambient_night_mps2: 0.002,
            machines: 6,
            machine_mps2: [0.001, 0.01],
            walks_per_hour: [30.0, 3.0],
            doors_per_hour: [18.0, 2.0],
            vehicles_per_hour: [12.0, 3.0],
            lifts_per_hour: [12.0, 2.0],
            ..o
        }
    }
}

impl Default for FieldMotion {
    fn default() -> Self {
        FieldMotion::none()
    }
}

/// A second-order section, transposed direct form II.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Biquad {
    b: [f64; 3],
    a: [f64; 2],
    z: [f64; 2],
}

impl Biquad {
    /// Butterworth low pass (`high = false`) or high pass at `corner_hz`, by the bilinear
    /// transform with prewarping.
    fn butterworth(corner_hz: f64, sample_rate_hz: f64, high: bool) -> Biquad {
        let k = (PI * corner_hz / sample_rate_hz).tan();
        let q = std::f64::consts::FRAC_1_SQRT_2;
        let norm = 1.0 / (1.0 + k / q + k * k);
        let b = if high {
            [norm, -2.0 * norm, norm]
        } else {
            let b0 = k * k * norm;
            [b0, 2.0 * b0, b0]
        };
        Biquad {
            b,
            a: [2.0 * (k * k - 1.0) * norm, (1.0 - k / q + k * k) * norm],
            z: [0.0; 2],
        }
    }

    #[inline]
    fn step(&mut self, x: f64) -> f64 {
        let y = self.b[0] * x + self.z[0];
        self.z[0] = self.b[1] * x - self.a[0] * y + self.z[1];
        self.z[1] = self.b[2] * x - self.a[1] * y;
        y
    }
}

/// The ambient's band pass on one axis.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Band {
    high_pass: Biquad,
    low_pass: Option<Biquad>,
}

impl Band {
    fn new(band_hz: [f64; 2], sample_rate_hz: f64) -> Band {
        Band {
            high_pass: Biquad::butterworth(band_hz[0], sample_rate_hz, true),
            low_pass: (band_hz[1] < 0.45 * sample_rate_hz)
                .then(|| Biquad::butterworth(band_hz[1], sample_rate_hz, false)),
        }
    }

    #[inline]
    fn step(&mut self, x: f64) -> f64 {
        let y = self.high_pass.step(x);
        match &mut self.low_pass {
            Some(lp) => lp.step(y),
            None => y,
        }
    }

    /// The output variance per unit white input variance: the impulse response's energy.
    fn gain_sq(band_hz: [f64; 2], sample_rate_hz: f64) -> f64 {
        let mut f = Band::new(band_hz, sample_rate_hz);
        let mut energy = 0.0;
        for i in 0..(200.0 * sample_rate_hz / band_hz[0]) as usize {
            let y = f.step(if i == 0 { 1.0 } else { 0.0 });
            energy += y * y;
        }
        energy
    }
}

#[derive(Debug, Clone, Copy, PartialEq)]
struct Machine {
    frequency_hz: f64,
    /// Amplitude per axis of the fundamental (the harmonic is 0.3 of it), m/s².
    amplitude: [f64; 3],
    phase: f64,
    always_on: bool,
    /// Relative frequency offset, wandering.
    drift: f64,
}

#[derive(Debug, Clone, Copy, PartialEq)]
enum Kind {
    /// A decaying ring: angular frequency per sample and decay per sample.
    Door { omega: f64, decay: f64 },
    /// A burst: eight tones under a Hann envelope.
    Vehicle { omegas: [f64; 8], phases: [f64; 8] },
    /// Steps: the step rate's first four harmonics under a Hann envelope.
    Walk { omega: f64, phases: [f64; 4] },
    /// A raised-cosine pulse up and, `gap` samples later, one down.
    Lift { width: u64, gap: u64 },
    /// One sinusoid, its first and last second ramped.
    Sway { omega: f64, ramp: u64 },
}

#[derive(Debug, Clone, Copy, PartialEq)]
struct Event {
    kind: Kind,
    start: u64,
    len: u64,
    /// Peak (or RMS for vehicles and walks) per axis, m/s².
    scale: [f64; 3],
}

impl Event {
    /// The event's motion at sample `index`, which lies in `start..start + len`.
    #[inline]
    fn at(&self, index: u64) -> [f64; 3] {
        let n = (index - self.start) as f64;
        let envelope = || 0.5 - 0.5 * (2.0 * PI * n / self.len as f64).cos();
        let v = match self.kind {
            Kind::Door { omega, decay } => (-decay * n).exp() * (omega * n).sin(),
            Kind::Vehicle { omegas, phases } => {
                let s: f64 = (0..8).map(|k| (omegas[k] * n + phases[k]).sin()).sum();
                envelope() * s / 2.0
            }
            Kind::Walk { omega, phases } => {
                const WEIGHTS: [f64; 4] = [1.0, 0.4, 0.2, 0.1];
                let s: f64 = (0..4)
                    .map(|h| WEIGHTS[h] * ((h + 1) as f64 * omega * n + phases[h]).sin())
                    .sum();
                envelope() * s
            }
            Kind::Lift { width, gap } => {
                let pulse = |m: f64| {
                    if (0.0..width as f64).contains(&m) {
                        0.5 - 0.5 * (2.0 * PI * m / width as f64).cos()
                    } else {
                        0.0
                    }
                };
                pulse(n) - pulse(n - gap as f64 - width as f64)
            }
            Kind::Sway { omega, ramp } => {
                let edge = n.min((self.len as f64 - n).max(0.0)) / ramp as f64;
                edge.min(1.0) * (omega * n).sin()
            }
        };
        self.scale.map(|s| s * v)
    }
}

/// Poisson arrivals of one kind of event: the next arrival, in samples.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Arrivals {
    per_hour: [f64; 2],
    next: f64,
}

/// The building's motion at one place, sample by sample: what [`FieldMotion`] describes,
/// beside the modes the caller adds.
#[derive(Debug, Clone)]
pub struct Motion {
    config: FieldMotion,
    rng: SmallRng,
    sample_rate_hz: f64,
    up: [f64; 3],
    band: [Band; 3],
    band_gain: f64,
    machines: Vec<Machine>,
    arrivals: [Arrivals; 5],
    events: Vec<Event>,
    log_level: f64,
    index: u64,
}

/// The day profile: 0 at night, 1 by day, raised-cosine ramps 05–07 and 21–23.
pub fn day_weight(hour: f64) -> f64 {
    let ramp = |x: f64| 0.5 - 0.5 * (PI * x.clamp(0.0, 1.0)).cos();
    if hour < 12.0 {
        ramp((hour - 5.0) / 2.0)
    } else {
        1.0 - ramp((hour - 21.0) / 2.0)
    }
}

impl Motion {
    /// The motion at a sensor whose vertical is `up` (its frame), sampled at `sample_rate_hz`.
    pub fn new(config: FieldMotion, seed: u64, sample_rate_hz: f64, up: [f64; 3]) -> Motion {
        let mut rng = SmallRng::seed_from_u64(seed ^ 0x000F_1E1D_0001);
        let norm = up.iter().map(|x| x * x).sum::<f64>().sqrt().max(1e-12);
        let up = up.map(|x| x / norm);
        let nyquist_cap = 0.45 * sample_rate_hz;
        let mut machines = Vec::new();
        for m in 0..config.machines {
            let [lo, hi] = config.machine_band_hz;
            let hi = hi.min(nyquist_cap);
            if hi <= lo {
                break;
            }
            let frequency_hz = rng.gen_range(lo..hi);
            let rms = rng.gen_range(
                config.machine_mps2[0]..=config.machine_mps2[1].max(config.machine_mps2[0]),
            );
            let direction = random_unit(&mut rng);
            machines.push(Machine {
                frequency_hz,
                amplitude: direction.map(|d| d * rms * 2f64.sqrt() * 3f64.sqrt()),
                phase: rng.gen_range(0.0..2.0 * PI),
                always_on: m == 0,
                drift: 0.0,
            });
        }
        let first = |rng: &mut SmallRng, per_hour: [f64; 2]| Arrivals {
            per_hour,
            next: exponential(rng) * 3600.0 * sample_rate_hz / per_hour[1].max(1e-9),
        };
        let arrivals = [
            first(&mut rng, config.doors_per_hour),
            first(&mut rng, config.vehicles_per_hour),
            first(&mut rng, config.walks_per_hour),
            first(&mut rng, config.lifts_per_hour),
            first(&mut rng, config.sways_per_hour),
        ];
        let band = [0; 3].map(|_| Band::new(config.ambient_band_hz, sample_rate_hz));
        Motion {
            band_gain: Band::gain_sq(config.ambient_band_hz, sample_rate_hz).sqrt(),
            band,
            machines,
            arrivals,
            events: Vec::new(),
            log_level: 0.0,
            index: 0,
            rng,
            sample_rate_hz,
            up,
            config,
        }
    }

    /// Adds the next `out.len()` samples of motion to `out`, m/s², at hour `hour` of the day
    /// (a batch is short against the day's profile).
    pub fn add(&mut self, hour: f64, out: &mut [[f64; 3]]) {
        let fs = self.sample_rate_hz;
        let n = out.len();
        let w = day_weight(hour);
        // The level's wander moves once a batch: its memory is half an hour.
        if self.config.wander > 0.0 {
            let dt = n as f64 / fs;
            let a = (-dt / self.config.wander_tau_s).exp();
            let e: f64 = self.rng.sample(StandardNormal);
            self.log_level = a * self.log_level + self.config.wander * (1.0 - a * a).sqrt() * e;
        }
        let level = (self.log_level - 0.5 * self.config.wander.powi(2)).exp();
        let c = &self.config;
        let ambient =
            level * (c.ambient_night_mps2 + w * (c.ambient_day_mps2 - c.ambient_night_mps2));
        if ambient > 0.0 {
            let scale = ambient / self.band_gain;
            for sample in out.iter_mut() {
                for (k, x) in sample.iter_mut().enumerate() {
                    let e: f64 = self.rng.sample(StandardNormal);
                    *x += self.band[k].step(scale * e);
                }
            }
        }
        self.add_machines(hour, out);
        self.schedule(w, n as u64);
        let end = self.index + n as u64;
        for event in &self.events {
            let from = event.start.max(self.index);
            let to = (event.start + event.len).min(end);
            for i in from..to {
                let v = event.at(i);
                let s = &mut out[(i - self.index) as usize];
                for k in 0..3 {
                    s[k] += v[k];
                }
            }
        }
        self.events.retain(|e| e.start + e.len > end);
        self.index = end;
    }

    fn add_machines(&mut self, hour: f64, out: &mut [[f64; 3]]) {
        let fs = self.sample_rate_hz;
        let by_day = (7.0..19.0).contains(&hour);
        let cap = 0.45 * fs;
        for m in &mut self.machines {
            // A machine's speed wanders by a few tenths of a percent over minutes.
            let e: f64 = self.rng.sample(StandardNormal);
            m.drift = (0.999 * m.drift + 1e-4 * e).clamp(-0.005, 0.005);
            let omega = 2.0 * PI * m.frequency_hz * (1.0 + m.drift) / fs;
            let on = m.always_on || by_day;
            let harmonic = 2.0 * m.frequency_hz < cap;
            for sample in out.iter_mut() {
                m.phase = (m.phase + omega) % (2.0 * PI);
                if on {
                    let v = m.phase.sin()
                        + if harmonic {
                            0.3 * (2.0 * m.phase).sin()
                        } else {
                            0.0
                        };
                    for (x, a) in sample.iter_mut().zip(m.amplitude) {
                        *x += a * v;
                    }
                }
            }
        }
    }

    /// Starts the events that arrive before the batch's end.
    fn schedule(&mut self, w: f64, n: u64) {
        let fs = self.sample_rate_hz;
        let end = (self.index + n) as f64;
        for kind in 0..self.arrivals.len() {
            loop {
                let a = self.arrivals[kind];
                if a.next >= end {
                    break;
                }
                let start = a.next.max(self.index as f64) as u64;
                let rate = a.per_hour[1] + w * (a.per_hour[0] - a.per_hour[1]);
                // Thinning: arrivals are drawn at the larger rate and kept at the hour's.
                let max_rate = a.per_hour[0].max(a.per_hour[1]);
                let keep = max_rate > 0.0 && self.rng.gen::<f64>() * max_rate < rate;
                self.arrivals[kind].next +=
                    exponential(&mut self.rng) * 3600.0 * fs / max_rate.max(1e-9);
                if keep {
                    let event = self.event(kind, start);
                    self.events.push(event);
                }
            }
        }
    }

    fn event(&mut self, kind: usize, start: u64) -> Event {
        let fs = self.sample_rate_hz;
        let cap = 0.45 * fs;
        let c = self.config.clone();
        let rng = &mut self.rng;
        let uniform = |rng: &mut SmallRng, r: [f64; 2]| {
            if r[1] > r[0] {
                rng.gen_range(r[0]..r[1])
            } else {
                r[0]
            }
        };
        let vertical = |rng: &mut SmallRng, peak: f64, up: [f64; 3]| {
            let side = random_unit(rng);
            [0, 1, 2].map(|k| peak * (up[k] + 0.3 * side[k]))
        };
        match kind {
            0 => {
                let f = uniform(rng, [10.0, 30.0f64.min(cap)]);
                let zeta = 0.03;
                let omega = 2.0 * PI * f / fs;
                let decay = zeta * omega;
                let peak = uniform(rng, c.door_peak_mps2);
                let d = random_unit(rng);
                Event {
                    kind: Kind::Door { omega, decay },
                    start,
                    len: ((1000f64).ln() / decay).ceil() as u64,
                    scale: d.map(|x| x * peak),
                }
            }
            1 => {
                let omegas = [0; 8].map(|_| 2.0 * PI * uniform(rng, [2.0, 20.0f64.min(cap)]) / fs);
                let phases = [0; 8].map(|_| rng.gen_range(0.0..2.0 * PI));
                let rms = uniform(rng, c.vehicle_rms_mps2);
                let d = random_unit(rng);
                Event {
                    kind: Kind::Vehicle { omegas, phases },
                    start,
                    len: (uniform(rng, [3.0, 12.0]) * fs) as u64,
                    scale: d.map(|x| x * rms),
                }
            }
            2 => {
                let omega = 2.0 * PI * uniform(rng, [1.5, 3.0]) / fs;
                let phases = [0; 4].map(|_| rng.gen_range(0.0..2.0 * PI));
                let peak = uniform(rng, c.step_mps2);
                Event {
                    kind: Kind::Walk { omega, phases },
                    start,
                    len: (uniform(rng, [10.0, 60.0]) * fs) as u64,
                    scale: vertical(rng, peak, self.up),
                }
            }
            4 => {
                // Below the cap, or its lower band when the whole band is above it.
                let band = if c.sway_hz[0] < cap {
                    [c.sway_hz[0], c.sway_hz[1].min(cap)]
                } else {
                    [0.1, 1.0]
                };
                let omega = 2.0 * PI * uniform(rng, band) / fs;
                let amplitude = uniform(rng, c.sway_mps2);
                let d = random_unit(rng);
                Event {
                    kind: Kind::Sway {
                        omega,
                        ramp: fs as u64,
                    },
                    start,
                    len: (uniform(rng, [60.0, 600.0]) * fs) as u64,
                    scale: d.map(|x| x * amplitude),
                }
            }
            _ => {
                let width = (2.0 * fs) as u64;
                let gap = (uniform(rng, [5.0, 20.0]) * fs) as u64;
                let peak = uniform(rng, c.lift_peak_mps2);
                Event {
                    kind: Kind::Lift { width, gap },
                    start,
                    len: 2 * width + gap,
                    scale: vertical(rng, peak, self.up),
                }
            }
        }
    }
}

fn exponential(rng: &mut SmallRng) -> f64 {
    -(1.0 - rng.gen::<f64>()).ln()
}

fn random_unit(rng: &mut SmallRng) -> [f64; 3] {
    loop {
        let v: [f64; 3] = [0, 1, 2].map(|_| rng.sample(StandardNormal));
        let n = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
        if n > 1e-3 {
            return v.map(|x| x / n);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn rms(config: FieldMotion, fs: f64, hour: f64, seconds: f64) -> [f64; 3] {
        let mut m = Motion::new(config, 7, fs, [0.0, 0.0, 1.0]);
        let n = (seconds * fs) as usize;
        let mut sum = [0.0; 3];
        let mut buf = vec![[0.0; 3]; 10];
        for _ in 0..n / 10 {
            buf.iter_mut().for_each(|s| *s = [0.0; 3]);
            m.add(hour, &mut buf);
            for s in &buf {
                for k in 0..3 {
                    sum[k] += s[k] * s[k];
                }
            }
        }
        sum.map(|s| (s / n as f64).sqrt())
    }

    /// The ambient alone, without wander: its RMS per axis is the stated level, by day and by
    /// night, at 100 and 50 Hz (where it is white to Nyquist).
    #[test]
    fn the_ambient_has_its_stated_level() {
        let config = FieldMotion {
            ambient_day_mps2: 0.004,
            ambient_night_mps2: 0.001,
            ..FieldMotion::none()
        };
        for fs in [100.0, 50.0] {
            for (hour, want) in [(12.0, 0.004), (2.0, 0.001)] {
                let r = rms(config.clone(), fs, hour, 2000.0);
                for x in r {
                    assert!((x / want - 1.0).abs() < 0.03, "{fs} Hz at {hour} h: {r:?}");
                }
            }
        }
    }

    /// A Butterworth high pass has half its power at the corner, and none at DC.
    #[test]
    fn butterworth_corners() {
        let fs = 100.0;
        let response = |f: f64, high: bool| {
            let mut b = Biquad::butterworth(5.0, fs, high);
            let n = 20_000;
            let mut p = 0.0;
            for i in 0..n {
                let y = b.step((2.0 * PI * f * i as f64 / fs).sin());
                if i > n / 2 {
                    p += y * y;
                }
            }
            p / (n / 2) as f64 * 2.0
        };
        assert!((response(5.0, true) - 0.5).abs() < 0.01);
        assert!((response(5.0, false) - 0.5).abs() < 0.01);
        assert!(response(0.5, true) < 1e-3);
        assert!(response(45.0, false) < 1e-3);
    }

    /// Transients arrive at their rates: a night of the busy building holds about the stated
    /// number of vehicles (3 an hour), counted by their starts.
    #[test]
    fn events_arrive_at_their_rates() {
        let mut m = Motion::new(FieldMotion::busy(), 3, 50.0, [0.0, 0.0, 1.0]);
        let mut buf = vec![[0.0; 3]; 50];
        let mut starts = std::collections::HashSet::new();
        let hours = 40.0;
        for _ in 0..(hours * 3600.0) as usize {
            m.add(2.0, &mut buf);
            for e in &m.events {
                if matches!(e.kind, Kind::Vehicle { .. }) {
                    starts.insert(e.start);
                }
            }
        }
        let expect = 3.0 * hours;
        let got = starts.len() as f64;
        assert!((got - expect).abs() < 4.0 * expect.sqrt(), "{got} vehicles");
    }

    #[test]
    fn the_day_profile_is_smooth_and_bounded() {
        assert_eq!(day_weight(3.0), 0.0);
        assert_eq!(day_weight(12.0), 1.0);
        assert!((day_weight(6.0) - 0.5).abs() < 1e-12);
        assert!((day_weight(22.0) - 0.5).abs() < 1e-12);
        assert_eq!(day_weight(23.5), 0.0);
    }
}
