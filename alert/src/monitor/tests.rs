//! Scripted streams with a known truth through the monitor, no network.

use super::*;
use triax_protocol::{BatchHeader, CorrectionInfo, Mode};

const RATE_HZ: f64 = 100.0;
const BATCH: usize = 50;
/// Standard uncertainty of every clean sample; k·u = 0.04 m/s² at k = 2.
const U: f32 = 0.02;
const T0_NS: i64 = 1_800_000_000_000_000_000;

fn t0() -> OffsetDateTime {
    OffsetDateTime::from_unix_timestamp(1_800_000_000).unwrap()
}

fn at(s: f64) -> OffsetDateTime {
    t0() + time::Duration::seconds_f64(s)
}

fn hq() -> BuildingId {
    BuildingId::new("hq").unwrap()
}

fn acc() -> SensorId {
    SensorId::new("acc-01").unwrap()
}

fn config(extra: &str) -> Config {
    Config::from_toml(&format!(
        "window_s = 2.0\nstale_after_s = 30.0\nrepeat_interval_s = 0.0\nhighpass_hz = 1.0\n\
         {extra}\n\
         [buildings.hq.sensors.acc-01]\n"
    ))
    .unwrap()
}

fn config_with_limits(limits: &str) -> Config {
    Config::from_toml(&format!(
        "window_s = 2.0\nstale_after_s = 30.0\nrepeat_interval_s = 0.0\nhighpass_hz = 1.0\n\
         [buildings.hq.sensors.acc-01]\n{limits}\n"
    ))
    .unwrap()
}

/// A stream of batches: x is a 2 Hz sine of the given amplitude, z holds gravity.
struct Script {
    sequence: u64,
    sample_index: i64,
    /// The coverage factor the batches carry.
    k: f32,
}

impl Script {
    fn new() -> Script {
        Script {
            sequence: 0,
            sample_index: 0,
            k: 2.0,
        }
    }

    fn time_s(&self) -> f64 {
        self.sample_index as f64 / RATE_HZ
    }

    fn batch(
        &mut self,
        amplitude_mps2: f64,
        frequency_hz: f64,
        sample_flags: u16,
    ) -> CorrectedBatch {
        let start = self.sample_index;
        let samples = (0..BATCH as i64)
            .map(|i| {
                let t = (start + i) as f64 / RATE_HZ;
                let x = amplitude_mps2 * (2.0 * std::f64::consts::PI * frequency_hz * t).sin();
                let uncalibrated = sample_flags & flags::UNCALIBRATED != 0;
                CorrectedSample {
                    accel_mps2: [x as f32, 0.0, 9.81],
                    uncertainty_mps2: if uncalibrated { [f32::NAN; 3] } else { [U; 3] },
                    flags: sample_flags,
                }
            })
            .collect();
        self.sample_index += BATCH as i64;
        self.sequence += 1;
        CorrectedBatch {
            header: BatchHeader {
                sensor_id: acc(),
                sequence: self.sequence,
                timestamp_ns: T0_NS + (start as f64 * 1e9 / RATE_HZ) as i64,
                sample_rate_hz: RATE_HZ,
            },
            batch_flags: sample_flags,
            info: CorrectionInfo {
                calibration_version: if sample_flags & flags::UNCALIBRATED != 0 {
                    0
                } else {
                    3
                },
                mode: Mode::Dynamic,
                coverage_factor: self.k,
            },
            samples,
        }
    }

    /// Feeds `seconds` of signal; returns the alerts of the last batch, when the window holds
    /// only this regime.
    fn run(
        &mut self,
        m: &mut Monitor,
        seconds: f64,
        amplitude_mps2: f64,
        frequency_hz: f64,
        sample_flags: u16,
    ) -> Vec<Alert> {
        let mut last = Vec::new();
        let n = (seconds * RATE_HZ / BATCH as f64).ceil() as usize;
        for _ in 0..n {
            let b = self.batch(amplitude_mps2, frequency_hz, sample_flags);
            last = m.on_corrected(&hq(), &b, at(self.time_s()));
        }
        last
    }
}

fn levels(alerts: &[Alert], kind: AlertKind) -> Vec<AlertLevel> {
    alerts
        .iter()
        .filter(|a| a.kind == kind)
        .map(|a| a.level)
        .collect()
}

/// Seconds before the high pass of these tests (1 Hz) has settled: ln(1000)/(2π/√2).
const SETTLE_S: f64 = 1.5548;

/// A window is judged only when it is whole and the baseline filter had settled before its
/// first sample: 1.55 s of settling, then a whole 2 s window. The first judgement comes with
/// the first batch that ends after 3.55 s.
#[test]
fn only_whole_settled_windows_are_judged() {
    let mut m = Monitor::new(config_with_limits("pga_mps2 = 0.5"), t0());
    let mut s = Script::new();
    let mut judged_at_s = None;
    for _ in 0..8 {
        let b = s.batch(0.9, 1.3, 0);
        let alerts = m.on_corrected(&hq(), &b, at(s.time_s()));
        let peak = levels(&alerts, AlertKind::PeakAcceleration);
        if s.time_s() < SETTLE_S + 2.0 {
            assert!(peak.is_empty(), "judged at {} s: {alerts:?}", s.time_s());
        } else if judged_at_s.is_none() && !peak.is_empty() {
            judged_at_s = Some(s.time_s());
            assert_eq!(peak, [AlertLevel::Exceeded]);
        }
    }
    assert_eq!(
        judged_at_s,
        Some(4.0),
        "judged as soon as the window is whole and settled"
    );
}

#[test]
fn peak_crossing_the_threshold_shows_the_three_regimes() {
    let mut m = Monitor::new(config_with_limits("pga_mps2 = 0.5"), t0());
    let mut s = Script::new();
    // Truth 0.40: the interval [0.36, 0.44] is below 0.5.
    let quiet = s.run(&mut m, SETTLE_S + 3.0, 0.40, 2.0, 0);
    assert!(quiet.is_empty(), "{quiet:?}");
    // Truth 0.49: [0.45, 0.53] straddles 0.5.
    let near = s.run(&mut m, 3.0, 0.49, 2.0, 0);
    assert_eq!(
        levels(&near, AlertKind::PeakAcceleration),
        [AlertLevel::Possible]
    );
    // Truth 0.60: [0.56, 0.64] is above 0.5.
    let over = s.run(&mut m, 3.0, 0.60, 2.0, 0);
    assert_eq!(
        levels(&over, AlertKind::PeakAcceleration),
        [AlertLevel::Exceeded]
    );
    let a = &over[0];
    // One sway, fitted exactly: the value is the amplitude, and u the stated u, all taken as
    // calibration error by default (noise_share = 0).
    // The motion above the baseline: the sine through the 1 Hz high pass, 0.970 of it at 2 Hz.
    let gain = crate::highpass::HighPass::new(1.0, RATE_HZ)
        .response()
        .at(std::f64::consts::TAU * 2.0 / RATE_HZ)
        .0;
    assert!((gain - 0.970).abs() < 1e-3, "{gain}");
    assert!((a.value - 0.60 * gain).abs() < 1e-5, "{a:?}");
    assert!(
        (a.standard_uncertainty - f64::from(U)).abs() < 1e-5,
        "{a:?}"
    );
    assert!(
        a.statement.contains("one sway at 2.000 Hz"),
        "{}",
        a.statement
    );
    assert_eq!(a.threshold, 0.5);
    assert_eq!(a.unit, UNIT_MPS2);
    assert_eq!(a.flagged_fraction, 0.0);
    assert!(
        a.statement.contains("value − k·u > threshold"),
        "{}",
        a.statement
    );
    // The decision survives the wire.
    let back: Alert = triax_protocol::from_json(&triax_protocol::to_json(a)).unwrap();
    assert_eq!(&back, a);
    // And back down again: nothing.
    assert!(s.run(&mut m, 3.0, 0.40, 2.0, 0).is_empty());
}

/// A stream whose batches carry k = 3 (few degrees of freedom behind its uncertainty) is
/// judged with it, not with the configured 2: a peak of 0.553 ± 0.02 (0.57 through the 1 Hz
/// high pass) against 0.5 is `exceeded` at k = 2 but only `possible` at k = 3.
#[test]
fn the_streams_coverage_factor_widens_the_guard_band() {
    let mut m = Monitor::new(config_with_limits("pga_mps2 = 0.5"), t0());
    let mut s = Script::new();
    let at_two = s.run(&mut m, SETTLE_S + 3.0, 0.57, 2.0, 0);
    assert_eq!(
        levels(&at_two, AlertKind::PeakAcceleration),
        [AlertLevel::Exceeded]
    );
    assert_eq!(at_two[0].coverage_factor, 2.0);
    s.k = 3.0;
    let at_three = s.run(&mut m, 3.0, 0.57, 2.0, 0);
    assert_eq!(
        levels(&at_three, AlertKind::PeakAcceleration),
        [AlertLevel::Possible]
    );
    assert_eq!(at_three[0].coverage_factor, 3.0);
}

#[test]
fn rms_and_dominant_frequency_regimes() {
    // RMS of a sine is amplitude/√2; u(RMS) = u·2√2/π ≈ 0.018, so k·u ≈ 0.036.
    let mut m = Monitor::new(
        config_with_limits("rms_mps2 = 0.3\nfrequency_below_hz = 1.8"),
        t0(),
    );
    let mut s = Script::new();
    let calm = s.run(&mut m, SETTLE_S + 3.0, 0.3, 2.5, 0);
    assert!(calm.is_empty(), "rms 0.21, 2.5 Hz: {calm:?}");
    let near = s.run(&mut m, 3.0, 0.43, 2.5, 0);
    assert_eq!(
        levels(&near, AlertKind::RmsAcceleration),
        [AlertLevel::Possible]
    );
    let over = s.run(&mut m, 3.0, 0.55, 2.5, 0);
    assert_eq!(
        levels(&over, AlertKind::RmsAcceleration),
        [AlertLevel::Exceeded]
    );
    // One sway, fitted: the frequency to the fit's precision.
    let softer = s.run(&mut m, 3.0, 0.2, 1.0, 0);
    assert_eq!(
        levels(&softer, AlertKind::DominantFrequency),
        [AlertLevel::Exceeded]
    );
    let f = softer
        .iter()
        .find(|a| a.kind == AlertKind::DominantFrequency)
        .unwrap();
    assert!((f.value - 1.0).abs() < 1e-6, "{f:?}");
    assert!(f.standard_uncertainty < 1e-6, "{f:?}");
    assert!(
        f.statement.contains("value + k·u < threshold"),
        "{}",
        f.statement
    );
    // A window that is not one sway (its amplitude steps down halfway) is judged from its
    // spectrum, to half a bin: 256 bins of 100 Hz give u = 0.39/√12 ≈ 0.11 Hz, and 1.85 Hz
    // against 1.8 Hz is within k·u: possible.
    s.run(&mut m, 3.0, 0.2, 1.85, 0);
    let borderline = s.run(&mut m, 1.0, 0.05, 1.85, 0);
    assert_eq!(
        levels(&borderline, AlertKind::DominantFrequency),
        [AlertLevel::Possible]
    );
    let f = borderline
        .iter()
        .find(|a| a.kind == AlertKind::DominantFrequency)
        .unwrap();
    assert!(
        (f.standard_uncertainty - 100.0 / 256.0 / 12f64.sqrt()).abs() < 1e-9,
        "{f:?}"
    );
    assert!(f.statement.contains("summed spectra"), "{}", f.statement);
}

#[test]
fn flagged_only_data_is_at_most_possible() {
    let mut m = Monitor::new(config_with_limits("pga_mps2 = 0.5\nrms_mps2 = 0.1"), t0());
    let mut s = Script::new();
    // Far above both limits, but every sample is clipped and outside the calibrated amplitude.
    let alerts = s.run(
        &mut m,
        SETTLE_S + 3.0,
        5.0,
        2.0,
        flags::CLIPPED | flags::OUTSIDE_AMPLITUDE,
    );
    assert_eq!(
        levels(&alerts, AlertKind::PeakAcceleration),
        [AlertLevel::Possible]
    );
    assert_eq!(
        levels(&alerts, AlertKind::RmsAcceleration),
        [AlertLevel::Possible]
    );
    for a in &alerts {
        assert_eq!(a.flagged_fraction, 1.0);
        assert!(
            a.statement.contains("never raise `exceeded`"),
            "{}",
            a.statement
        );
        assert!(a.statement.contains("clipped"), "{}", a.statement);
    }
    // Uncalibrated values are raw outputs, not m/s²: nothing is judged on them.
    let mut m = Monitor::new(config_with_limits("pga_mps2 = 0.5"), t0());
    let mut s = Script::new();
    let alerts = s.run(&mut m, 3.0, 5.0, 2.0, flags::UNCALIBRATED);
    assert!(alerts.is_empty(), "{alerts:?}");
}

/// A sensor whose record the field health checks found suspect still raises `exceeded` for
/// motion far beyond its limit, with its samples' uncertainty widened by 5 % of their value,
/// and only `possible` where the widened interval reaches the limit. Its statement says so.
#[test]
fn calibration_suspect_samples_widen_the_interval_and_still_exceed() {
    let mut m = Monitor::new(config_with_limits("pga_mps2 = 0.5"), t0());
    let mut s = Script::new();
    let alerts = s.run(&mut m, SETTLE_S + 3.0, 1.0, 2.0, flags::CALIBRATION_SUSPECT);
    assert_eq!(
        levels(&alerts, AlertKind::PeakAcceleration),
        [AlertLevel::Exceeded]
    );
    let a = &alerts[0];
    assert_eq!(a.flagged_fraction, 0.0);
    // u = √(0.02² + (0.05·0.970)²) = 0.0525.
    assert!(
        (a.standard_uncertainty - 0.02f64.hypot(0.05 * a.value)).abs() < 1e-6,
        "{a:?}"
    );
    assert!(
        a.statement.contains("widened by 5.0 % of its value"),
        "{}",
        a.statement
    );
    // 0.58 (0.563 through the high pass) against 0.5: clean samples with u = 0.02 say
    // exceeded; widened by 5 % of the value (u = √(0.02² + 0.028²) = 0.035, k = 2: ±0.07)
    // the interval reaches the limit: possible.
    let mut m = Monitor::new(config_with_limits("pga_mps2 = 0.5"), t0());
    let mut s = Script::new();
    let clean = s.run(&mut m, SETTLE_S + 3.0, 0.58, 2.0, 0);
    assert_eq!(
        levels(&clean, AlertKind::PeakAcceleration),
        [AlertLevel::Exceeded]
    );
    let mut m = Monitor::new(config_with_limits("pga_mps2 = 0.5"), t0());
    let mut s = Script::new();
    let suspect = s.run(
        &mut m,
        SETTLE_S + 3.0,
        0.58,
        2.0,
        flags::CALIBRATION_SUSPECT,
    );
    assert_eq!(
        levels(&suspect, AlertKind::PeakAcceleration),
        [AlertLevel::Possible]
    );
}

#[test]
fn a_few_flagged_samples_do_not_stop_a_clean_decision() {
    let mut m = Monitor::new(config_with_limits("pga_mps2 = 0.5"), t0());
    let mut s = Script::new();
    s.run(&mut m, SETTLE_S + 1.5, 0.8, 2.0, 0);
    let alerts = s.run(&mut m, 0.5, 0.8, 2.0, flags::OUTSIDE_FREQUENCY);
    assert_eq!(
        levels(&alerts, AlertKind::PeakAcceleration),
        [AlertLevel::Exceeded]
    );
    let a = &alerts[0];
    assert!((a.flagged_fraction - 0.25).abs() < 1e-9, "{a:?}");
    assert!(
        a.statement.contains("unflagged samples only"),
        "{}",
        a.statement
    );
    assert!(a.statement.contains("outside_frequency"), "{}", a.statement);
}

#[test]
fn stale_sensors_raise_their_own_alert() {
    let mut c = config("");
    c.settings.repeat_interval_s = 60.0;
    let mut m = Monitor::new(c, t0());
    // Expected from the start: silent for 31 s is stale even though it never spoke.
    assert!(m.check_stale(at(29.0)).is_empty());
    let stale = m.check_stale(at(31.0));
    assert_eq!(stale.len(), 1, "{stale:?}");
    let a = &stale[0];
    assert_eq!((a.kind, a.level), (AlertKind::Stale, AlertLevel::Stale));
    assert_eq!(a.sensor_id, acc());
    assert!((a.value - 31.0).abs() < 1e-9 && a.threshold == 30.0 && a.unit == UNIT_S);
    // Rate-limited while the silence lasts.
    assert!(m.check_stale(at(50.0)).is_empty());
    // Data clears it; the next silence alerts at once.
    let mut s = Script::new();
    let b = s.batch(0.1, 2.0, 0);
    m.on_corrected(&hq(), &b, at(55.0));
    assert!(m.check_stale(at(80.0)).is_empty());
    let again = m.check_stale(at(86.0));
    assert_eq!(levels(&again, AlertKind::Stale), [AlertLevel::Stale]);
    assert!(again[0].statement.contains("no corrected or tilt data"));
    // A sensor of an unwatched building is not tracked at all.
    assert!(m
        .on_corrected(&BuildingId::new("annex").unwrap(), &b, at(87.0))
        .is_empty());
}

#[test]
fn repeated_alerts_are_rate_limited_but_escalations_pass() {
    let mut c = config_with_limits("pga_mps2 = 0.5");
    c.settings.repeat_interval_s = 60.0;
    let mut m = Monitor::new(c, t0());
    let mut s = Script::new();
    s.run(&mut m, SETTLE_S, 0.49, 2.0, 0);
    let mut got = Vec::new();
    for _ in 0..6 {
        let b = s.batch(0.49, 2.0, 0);
        got.extend(m.on_corrected(&hq(), &b, at(s.time_s())));
    }
    assert_eq!(
        levels(&got, AlertKind::PeakAcceleration),
        [AlertLevel::Possible]
    );
    got.clear();
    for _ in 0..6 {
        let b = s.batch(0.7, 2.0, 0);
        got.extend(m.on_corrected(&hq(), &b, at(s.time_s())));
    }
    assert_eq!(
        levels(&got, AlertKind::PeakAcceleration),
        [AlertLevel::Exceeded],
        "escalation passes once"
    );
    // After the interval the same alert passes again and counts what was held back.
    let b = s.batch(0.7, 2.0, 0);
    let later = m.on_corrected(&hq(), &b, at(200.0));
    assert_eq!(
        levels(&later, AlertKind::PeakAcceleration),
        [AlertLevel::Exceeded]
    );
    assert!(
        later[0].statement.contains("suppressed"),
        "{}",
        later[0].statement
    );
}

#[test]
fn duplicates_stay_out_of_the_window() {
    let mut m = Monitor::new(config_with_limits("pga_mps2 = 0.5"), t0());
    let mut s = Script::new();
    s.run(&mut m, 3.0, 0.2, 2.0, 0);
    let mut loud = s.batch(3.0, 2.0, 0);
    loud.batch_flags |= flags::DUPLICATE;
    assert!(m.on_corrected(&hq(), &loud, at(10.0)).is_empty());
}

fn tilt(t_s: f64, roll_deg: f64, version: u64, tilt_flags: u16) -> TiltSample {
    TiltSample {
        format_version: 1,
        sensor_id: acc(),
        timestamp_ns: T0_NS + (t_s * 1e9) as i64,
        roll_deg,
        pitch_deg: 0.0,
        roll_uncertainty_deg: 0.005,
        pitch_uncertainty_deg: 0.005,
        coverage_factor: 2.0,
        calibration_version: version,
        flags: tilt_flags,
    }
}

#[test]
fn tilt_change_is_judged_against_a_baseline() {
    // Baseline u 0.005 and window u 0.005: u(Δ) ≈ 0.0071, k·u ≈ 0.014 deg.
    let mut m = Monitor::new(config_with_limits("tilt_change_deg = 0.05"), t0());
    let mut t = 0.0;
    let mut feed = |m: &mut Monitor, roll: f64, version: u64, f: u16, n: usize| {
        let mut last = Vec::new();
        for _ in 0..n {
            t += 1.0;
            last = m.on_tilt(&hq(), &tilt(t, roll, version, f), at(t));
        }
        last
    };
    assert!(feed(&mut m, 0.0, 3, 0, 10).is_empty(), "baseline");
    assert!(feed(&mut m, 0.03, 3, 0, 3).is_empty());
    let near = feed(&mut m, 0.045, 3, 0, 3);
    assert_eq!(levels(&near, AlertKind::TiltChange), [AlertLevel::Possible]);
    let over = feed(&mut m, 0.08, 3, 0, 3);
    assert_eq!(levels(&over, AlertKind::TiltChange), [AlertLevel::Exceeded]);
    assert_eq!(over[0].unit, UNIT_DEG);
    // Flagged tilt samples alone stay at `possible`.
    let flagged = feed(&mut m, 0.5, 3, flags::CALIBRATION_EXPIRED, 3);
    assert_eq!(
        levels(&flagged, AlertKind::TiltChange),
        [AlertLevel::Possible]
    );
    // A new calibration restarts the baseline rather than reading its offset change as tilt.
    assert!(feed(&mut m, 0.5, 4, 0, 10).is_empty());
    assert!(feed(&mut m, 0.5, 4, 0, 3).is_empty());
}

/// The windows are most of the service's memory (ten thousand sensors' worth): a sample is 48
/// bytes, not the 56 a nested `CorrectedSample` with its padding would make.
#[test]
fn a_window_sample_is_48_bytes() {
    assert_eq!(std::mem::size_of::<TimedSample>(), 48);
}
