//! Detecting an event in a building's corrected streams: a trigger per sensor, and several
//! sensors agreeing.
//!
//! **Per sensor** ([`SensorDetector`]): the characteristic function is the squared deviation of
//! the three axes from their slow mean (time constant `lta_s`: gravity and offsets), averaged
//! over the last `sta_s` (STA, a moving average, so that it falls back as soon as the motion
//! stops) and over `lta_s` (LTA, an exponential window). The sensor is *on* when
//! `STA/LTA ≥ trigger_ratio` (the LTA and the mean frozen while it is on, so the event does not
//! raise its own reference), or, with a `trigger_level_mps2`, when an axis's deviation is beyond
//! it by its guard band (`|a − m| − k·u > level`, `k·u` the sample's own expanded
//! uncertainty); *off* again when the ratio is below `detrigger_ratio` and no sample of the last
//! `sta_s` was beyond the level. Before the LTA has `lta_s` of data the sensor is *warming*.
//! A break in its stream (a gap longer than one and a half periods) leaves the LTA and the
//! mean as they were and makes the sensor *unknown* from the break until `sta_s` after its data
//! resume: what happened meanwhile is not known, so an event cannot end there.
//!
//! **False triggers from noise.** With stationary Gaussian noise the STA over `N = sta_s·rate`
//! samples of three axes is χ² with `3N` degrees of freedom over `3N`, and the LTA is steadier
//! still, so `P(STA/LTA ≥ r)` is the χ² tail: for `N = 100` and `r = 4`, below
//! 10⁻⁴⁰ per window. What triggers a sensor is motion: a door, a footstep, a truck. Hence
//! **coincidence** ([`Coincidence`]): an event opens when at least `min_sensors` sensors are on
//! at one instant; it starts at the earliest trigger among them, and ends at the last instant
//! any sensor was on or unknown, once `quiet_s` have passed with every sensor off. An event
//! longer than `max_event_s` is closed there (`truncated`) and, if the shaking goes on, the next
//! one opens at once.
//!
//! Time is the sensors' (`timestamp_ns`); the caller says up to when every sensor's data are in
//! ([`Coincidence::advance`]), so that sensors read at different paces (one catching up from a
//! history) are judged at the same instants.

use serde::Deserialize;

/// Detection settings.
#[derive(Debug, Clone, Copy, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct DetectorConfig {
    pub sta_s: f64,
    pub lta_s: f64,
    pub trigger_ratio: f64,
    pub detrigger_ratio: f64,
    /// A level (m/s²) an axis's deviation beyond its guard band triggers on too.
    pub trigger_level_mps2: Option<f64>,
    /// The STA's RMS must be at least this (m/s²) for the ratio to trigger: a very quiet
    /// building's ratio jumps for a footstep.
    pub min_rms_mps2: f64,
    pub min_sensors: usize,
    pub quiet_s: f64,
    pub max_event_s: f64,
}

impl Default for DetectorConfig {
    fn default() -> Self {
        DetectorConfig {
            sta_s: 1.0,
            lta_s: 30.0,
            trigger_ratio: 4.0,
            detrigger_ratio: 1.5,
            trigger_level_mps2: None,
            min_rms_mps2: 0.005,
            min_sensors: 2,
            quiet_s: 5.0,
            max_event_s: 300.0,
        }
    }
}

impl DetectorConfig {
    /// What is wrong with these settings, naming the field.
    pub fn check(&self) -> Result<(), String> {
        let positive = [
            ("sta_s", self.sta_s),
            ("lta_s", self.lta_s),
            ("quiet_s", self.quiet_s),
            ("max_event_s", self.max_event_s),
        ];
        for (name, v) in positive {
            if !(v.is_finite() && v > 0.0) {
                return Err(format!(
                    "{name} = {v}: must be a positive number of seconds"
                ));
            }
        }
        if self.lta_s <= self.sta_s {
            return Err(format!(
                "lta_s = {}: must be longer than sta_s = {}",
                self.lta_s, self.sta_s
            ));
        }
        if !(self.detrigger_ratio.is_finite() && self.detrigger_ratio >= 1.0) {
            return Err(format!(
                "detrigger_ratio = {}: must be ≥ 1",
                self.detrigger_ratio
            ));
        }
        if !(self.trigger_ratio.is_finite() && self.trigger_ratio > self.detrigger_ratio) {
            return Err(format!(
                "trigger_ratio = {}: must be above detrigger_ratio = {}",
                self.trigger_ratio, self.detrigger_ratio
            ));
        }
        if let Some(l) = self.trigger_level_mps2 {
            if !(l.is_finite() && l > 0.0) {
                return Err(format!("trigger_level_mps2 = {l}: must be > 0"));
            }
        }
        if !(self.min_rms_mps2.is_finite() && self.min_rms_mps2 >= 0.0) {
            return Err(format!("min_rms_mps2 = {}: must be ≥ 0", self.min_rms_mps2));
        }
        if self.min_sensors == 0 {
            return Err("min_sensors = 0: must be ≥ 1".into());
        }
        Ok(())
    }
}

/// A stretch of one sensor's time: on (triggered) or unknown (a break in its data).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Interval {
    pub start_ns: i64,
    /// Exclusive; none while it lasts.
    pub end_ns: Option<i64>,
    pub unknown: bool,
}

#[derive(Debug, Clone, Copy, PartialEq)]
enum State {
    Warming,
    Off,
    On,
}

/// One sensor's trigger.
#[derive(Debug, Clone)]
pub struct SensorDetector {
    config: DetectorConfig,
    mean: [f64; 3],
    /// The last `sta_s` of the characteristic function, and their sum.
    window: std::collections::VecDeque<f64>,
    window_sum: f64,
    sta: f64,
    lta: f64,
    /// Samples averaged since the start (the LTA and mean are cumulative until warm).
    count: u64,
    warm_samples: u64,
    state: State,
    last_ns: Option<i64>,
    /// After a break: the STA restarts and the sensor is unknown until this.
    unknown_until_ns: Option<i64>,
    last_level_ns: Option<i64>,
    /// Past stretches, oldest first.
    pub intervals: Vec<Interval>,
}

impl SensorDetector {
    pub fn new(config: &DetectorConfig) -> SensorDetector {
        SensorDetector {
            config: *config,
            mean: [0.0; 3],
            window: std::collections::VecDeque::new(),
            window_sum: 0.0,
            sta: 0.0,
            lta: 0.0,
            count: 0,
            warm_samples: 0,
            state: State::Warming,
            last_ns: None,
            unknown_until_ns: None,
            last_level_ns: None,
            intervals: Vec::new(),
        }
    }

    /// The time of the last sample fed.
    pub fn last_ns(&self) -> Option<i64> {
        self.last_ns
    }

    /// Whether the sensor is on now.
    pub fn is_on(&self) -> bool {
        self.state == State::On
    }

    fn open(&mut self, start_ns: i64, unknown: bool) {
        self.intervals.push(Interval {
            start_ns,
            end_ns: None,
            unknown,
        });
    }

    fn close(&mut self, end_ns: i64, unknown: bool) {
        if let Some(last) = self
            .intervals
            .iter_mut()
            .rev()
            .find(|i| i.unknown == unknown && i.end_ns.is_none())
        {
            last.end_ns = Some(end_ns.max(last.start_ns));
        }
    }

    /// Feeds one sample at `t_ns` (increasing), its corrected acceleration, standard
    /// uncertainty and coverage factor; an invalid sample only moves time.
    pub fn feed(&mut self, t_ns: i64, a: [f64; 3], u: [f64; 3], k: f64, valid: bool, dt_s: f64) {
        let c = self.config;
        if let Some(last) = self.last_ns {
            if t_ns <= last {
                return;
            }
            if (t_ns - last) as f64 > 1.5 * dt_s * 1e9 {
                // A break: what happened in it is unknown until the STA has refilled.
                let until = t_ns + (c.sta_s * 1e9) as i64;
                if self.state == State::On {
                    self.close(last, false);
                    self.state = State::Off;
                }
                if self.unknown_until_ns.is_none() {
                    self.open(last, true);
                }
                self.unknown_until_ns = Some(until);
                self.window.clear();
                self.window_sum = 0.0;
            }
        }
        self.last_ns = Some(t_ns);
        if let Some(until) = self.unknown_until_ns {
            if t_ns >= until {
                self.close(t_ns, true);
                self.unknown_until_ns = None;
            }
        }
        if !valid || a.iter().any(|v| !v.is_finite()) {
            return;
        }
        self.count += 1;
        let warm = (c.lta_s / dt_s).ceil() as u64;
        // Cumulative until warm: the reference converges from the first sample.
        let alpha_l = if self.count < warm {
            1.0 / self.count as f64
        } else {
            dt_s / c.lta_s
        };
        let on = self.state == State::On;
        if !on {
            for (m, x) in self.mean.iter_mut().zip(a) {
                *m += alpha_l * (x - *m);
            }
        }
        let d: [f64; 3] = std::array::from_fn(|i| a[i] - self.mean[i]);
        let cf = d.iter().map(|v| v * v).sum::<f64>();
        let n_sta = ((c.sta_s / dt_s).round() as usize).max(1);
        self.window.push_back(cf);
        self.window_sum += cf;
        while self.window.len() > n_sta {
            self.window_sum -= self.window.pop_front().unwrap_or(0.0);
        }
        // The running sum drifts by rounding over hours: summed afresh once a window.
        if self.count % n_sta as u64 == 0 {
            self.window_sum = self.window.iter().sum();
        }
        self.sta = self.window_sum / self.window.len() as f64;
        if !on {
            self.lta += alpha_l * (cf - self.lta);
        }
        if let Some(level) = c.trigger_level_mps2 {
            if (0..3).any(|i| d[i].abs() - k * u[i] > level) {
                self.last_level_ns = Some(t_ns);
            }
        }
        if self.state == State::Warming {
            self.warm_samples += 1;
            if self.warm_samples >= warm {
                self.state = State::Off;
            } else {
                return;
            }
        }
        if self.unknown_until_ns.is_some() || self.window.len() < n_sta {
            return;
        }
        let ratio = if self.lta > 0.0 {
            self.sta / self.lta
        } else {
            0.0
        };
        let level_recent = self
            .last_level_ns
            .is_some_and(|l| (t_ns - l) as f64 <= c.sta_s * 1e9);
        let level_now = self.last_level_ns == Some(t_ns);
        match self.state {
            State::Off => {
                let ratio_on = ratio >= c.trigger_ratio && self.sta.sqrt() >= c.min_rms_mps2;
                if ratio_on || level_now {
                    self.state = State::On;
                    self.open(t_ns, false);
                }
            }
            State::On => {
                if ratio < c.detrigger_ratio && !level_recent {
                    self.state = State::Off;
                    self.close(t_ns, false);
                }
            }
            State::Warming => {}
        }
    }

    /// Whether the sensor was on (or, with `unknown`, unknown) at `t_ns`.
    fn covering(&self, t_ns: i64, unknown: bool) -> Option<&Interval> {
        self.intervals.iter().rev().find(|i| {
            i.unknown == unknown && i.start_ns <= t_ns && i.end_ns.is_none_or(|e| t_ns < e)
        })
    }

    /// Forgets stretches that ended before `t_ns`.
    fn prune(&mut self, t_ns: i64) {
        self.intervals
            .retain(|i| i.end_ns.is_none_or(|e| e >= t_ns));
    }
}

/// An event found: when it started and ended (ns, by the sensors' clocks), and who triggered.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct DetectedEvent {
    /// The earliest trigger among the sensors that opened it.
    pub start_ns: i64,
    /// The instant the coincidence was reached.
    pub coincidence_ns: i64,
    /// The last instant a sensor was on or unknown.
    pub end_ns: i64,
    /// Sensors (by index) on at any point of the event.
    pub sensors: Vec<usize>,
    /// Closed at `max_event_s`, the shaking going on.
    pub truncated: bool,
}

#[derive(Debug, Clone)]
enum Phase {
    Idle,
    Open {
        start_ns: i64,
        coincidence_ns: i64,
        last_active_ns: i64,
        sensors: Vec<bool>,
    },
}

/// The building's detector: every sensor's trigger and their coincidence.
#[derive(Debug, Clone)]
pub struct Coincidence {
    config: DetectorConfig,
    pub sensors: Vec<SensorDetector>,
    phase: Phase,
    evaluated_ns: Option<i64>,
    /// Whether a sensor was on or unknown at the last instant judged.
    active_before: bool,
}

impl Coincidence {
    pub fn new(config: &DetectorConfig, sensors: usize) -> Coincidence {
        Coincidence {
            config: *config,
            sensors: (0..sensors).map(|_| SensorDetector::new(config)).collect(),
            phase: Phase::Idle,
            evaluated_ns: None,
            active_before: false,
        }
    }

    /// Whether an event is open, and since when.
    pub fn open_since_ns(&self) -> Option<i64> {
        match &self.phase {
            Phase::Open { start_ns, .. } => Some(*start_ns),
            Phase::Idle => None,
        }
    }

    /// Up to when the coincidence has been judged.
    pub fn evaluated_ns(&self) -> Option<i64> {
        self.evaluated_ns
    }

    /// Judges every instant up to `watermark_ns` (every sensor still reporting has been fed up
    /// to it) and returns the events that closed.
    pub fn advance(&mut self, watermark_ns: i64) -> Vec<DetectedEvent> {
        let from = self.evaluated_ns.unwrap_or(i64::MIN);
        if watermark_ns <= from {
            return Vec::new();
        }
        // The statuses change only at the stretches' ends: judge there, in order.
        let mut instants: Vec<i64> = self
            .sensors
            .iter()
            .flat_map(|s| s.intervals.iter())
            .flat_map(|i| [Some(i.start_ns), i.end_ns])
            .flatten()
            .filter(|&t| t > from && t <= watermark_ns)
            .collect();
        instants.push(watermark_ns);
        instants.sort_unstable();
        instants.dedup();
        let mut closed = Vec::new();
        let quiet = (self.config.quiet_s * 1e9) as i64;
        let longest = (self.config.max_event_s * 1e9) as i64;
        for t in instants {
            // Nothing changed since the last instant judged: if nothing was active then, the
            // event ended `quiet` after its last activity, before `t`.
            if let Phase::Open {
                start_ns,
                coincidence_ns,
                last_active_ns,
                sensors,
            } = &self.phase
            {
                if !self.active_before && t - *last_active_ns >= quiet {
                    closed.push(DetectedEvent {
                        start_ns: *start_ns,
                        coincidence_ns: *coincidence_ns,
                        end_ns: *last_active_ns,
                        sensors: (0..sensors.len()).filter(|&s| sensors[s]).collect(),
                        truncated: false,
                    });
                    self.phase = Phase::Idle;
                }
            }
            let on: Vec<usize> = (0..self.sensors.len())
                .filter(|&s| self.sensors[s].covering(t, false).is_some())
                .collect();
            let unknown =
                (0..self.sensors.len()).any(|s| self.sensors[s].covering(t, true).is_some());
            let active = !on.is_empty() || unknown;
            match &mut self.phase {
                Phase::Idle => {
                    if on.len() >= self.config.min_sensors {
                        let start_ns = on
                            .iter()
                            .filter_map(|&s| self.sensors[s].covering(t, false))
                            .map(|i| i.start_ns)
                            .min()
                            .unwrap_or(t);
                        let mut sensors = vec![false; self.sensors.len()];
                        on.iter().for_each(|&s| sensors[s] = true);
                        self.phase = Phase::Open {
                            start_ns,
                            coincidence_ns: t,
                            last_active_ns: t,
                            sensors,
                        };
                    }
                }
                Phase::Open {
                    start_ns,
                    coincidence_ns,
                    last_active_ns,
                    sensors,
                } => {
                    on.iter().for_each(|&s| sensors[s] = true);
                    // A stretch that ended at or before now was active up to its end.
                    for s in &self.sensors {
                        for i in &s.intervals {
                            if let Some(e) = i.end_ns {
                                if e <= t && e > *last_active_ns {
                                    *last_active_ns = e;
                                }
                            }
                        }
                    }
                    if active {
                        *last_active_ns = t;
                    }
                    if t - *start_ns >= longest {
                        closed.push(DetectedEvent {
                            start_ns: *start_ns,
                            coincidence_ns: *coincidence_ns,
                            end_ns: t,
                            sensors: (0..sensors.len()).filter(|&s| sensors[s]).collect(),
                            truncated: true,
                        });
                        self.phase = Phase::Idle;
                        if on.len() >= self.config.min_sensors {
                            let mut sensors = vec![false; self.sensors.len()];
                            on.iter().for_each(|&s| sensors[s] = true);
                            self.phase = Phase::Open {
                                start_ns: t,
                                coincidence_ns: t,
                                last_active_ns: t,
                                sensors,
                            };
                        }
                    }
                }
            }
            self.active_before = active;
        }
        self.evaluated_ns = Some(watermark_ns);
        let keep_from = match &self.phase {
            Phase::Open { start_ns, .. } => *start_ns,
            Phase::Idle => watermark_ns,
        };
        for s in &mut self.sensors {
            s.prune(keep_from - quiet);
        }
        closed
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::Rng;

    const DT: f64 = 0.01;

    /// Three sensors, 100 Hz: noise of 1 mg, and from `shake_from` to `shake_to` seconds a 2 Hz
    /// sway of `amplitude` on the sensors in `shaking`; a break from `gap.0` to `gap.1` s.
    fn run(
        shake: (f64, f64),
        amplitude: f64,
        shaking: &[usize],
        gap: Option<(f64, f64)>,
        seconds: f64,
    ) -> Vec<DetectedEvent> {
        let config = DetectorConfig::default();
        let mut c = Coincidence::new(&config, 3);
        let mut rng = Rng::new(5);
        let mut events = Vec::new();
        let n = (seconds / DT) as usize;
        for i in 0..n {
            let t = i as f64 * DT;
            if gap.is_some_and(|(a, b)| t >= a && t < b) {
                continue;
            }
            let t_ns = (t * 1e9) as i64;
            for s in 0..3 {
                let sway = if shaking.contains(&s) && t >= shake.0 && t < shake.1 {
                    amplitude * (2.0 * std::f64::consts::PI * 2.0 * t).sin()
                } else {
                    0.0
                };
                let a = [
                    0.01 * rng.normal() + sway,
                    0.01 * rng.normal(),
                    9.81 + 0.01 * rng.normal(),
                ];
                c.sensors[s].feed(t_ns, a, [0.01; 3], 2.0, true, DT);
            }
            if i % 10 == 0 {
                events.extend(c.advance(t_ns));
            }
        }
        events
    }

    #[test]
    fn an_event_seen_by_two_sensors_opens_and_closes() {
        let events = run((60.0, 80.0), 0.5, &[0, 1], None, 120.0);
        assert_eq!(events.len(), 1, "{events:?}");
        let e = &events[0];
        let (start, end) = (e.start_ns as f64 * 1e-9, e.end_ns as f64 * 1e-9);
        assert!((60.0..60.5).contains(&start), "starts {start}");
        assert!((80.0..82.0).contains(&end), "ends {end}");
        assert_eq!(e.sensors, vec![0, 1]);
        assert!(!e.truncated);
    }

    #[test]
    fn one_sensor_alone_is_not_an_event_and_noise_never_is() {
        assert!(run((60.0, 80.0), 0.5, &[2], None, 120.0).is_empty());
        assert!(run((0.0, 0.0), 0.0, &[], None, 200.0).is_empty());
    }

    #[test]
    fn a_break_during_the_shaking_keeps_one_event() {
        // Every stream stops for 20 s in the middle of the shaking (a gateway restarting).
        let events = run((60.0, 100.0), 0.5, &[0, 1, 2], Some((70.0, 90.0)), 150.0);
        assert_eq!(events.len(), 1, "{events:?}");
        let end = events[0].end_ns as f64 * 1e-9;
        assert!((100.0..102.0).contains(&end), "ends {end}");
        // A break after the shaking ended within it: one event, ending when the data resume
        // and show no motion (what happened in the break is unknown).
        let events = run((60.0, 75.0), 0.5, &[0, 1, 2], Some((70.0, 90.0)), 150.0);
        assert_eq!(events.len(), 1, "{events:?}");
        let end = events[0].end_ns as f64 * 1e-9;
        assert!((90.0..92.0).contains(&end), "ends {end}");
    }

    #[test]
    fn a_long_shaking_is_cut_at_the_longest_event() {
        let events = run((40.0, 400.0), 0.5, &[0, 1], None, 420.0);
        assert!(events.len() >= 2, "{events:?}");
        assert!(events[0].truncated);
        assert!(((events[0].end_ns - events[0].start_ns) as f64 * 1e-9 - 300.0).abs() < 1.0);
        assert_eq!(events[1].start_ns, events[0].end_ns);
    }

    #[test]
    fn bad_settings_are_named() {
        let c = DetectorConfig {
            lta_s: 0.5,
            ..DetectorConfig::default()
        };
        assert!(c.check().unwrap_err().contains("lta_s"));
        let c = DetectorConfig {
            trigger_ratio: 1.2,
            ..DetectorConfig::default()
        };
        assert!(c.check().unwrap_err().contains("trigger_ratio"));
        assert!(DetectorConfig::default().check().is_ok());
    }
}
