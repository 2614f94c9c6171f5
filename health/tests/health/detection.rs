//! Each fault found by the test meant for it, within its target, and nothing else raised.
//!
//! Sensor time is 100 Hz in batches of 10, as a node sends it. The gravity tests compress the
//! day (a ±10 °C cycle and night-time quiet in one hour) so that the default run stays short;
//! `monte_carlo` repeats them over real days.

use triax_health::sim::{Fault, FieldConfig, EPOCH_NS};
use triax_health::{HealthConfig, HealthReport, LocalGravity, Verdict};
use triax_protocol::batch::{BatchHeader, RawBatch, RawBatchView};
use triax_protocol::SensorId;

use crate::util::{not_ok, Run, HOUR_NS, SECOND_NS};

fn daytime() -> FieldConfig {
    FieldConfig {
        start_hour: 12.0,
        ..FieldConfig::default()
    }
}

/// A channel that freezes is `suspect` 10 s (`stuck_s`) after it froze, dated from the block
/// it froze in; nothing else is.
#[test]
fn a_stuck_channel_is_suspect_within_a_minute() {
    let config = HealthConfig::default();
    let mut run = Run::new(1, daytime(), &config);
    let fault_ns = EPOCH_NS + 120 * SECOND_NS + 350_000_000;
    run.inject(fault_ns, Fault::Stuck { channel: 1 });
    run.run(fault_ns);
    assert_eq!(run.monitor.report().verdict, Verdict::Ok);
    let found = run
        .run_until(fault_ns + 600 * SECOND_NS, |r| {
            r.stuck[1].verdict == Verdict::Suspect
        })
        .expect("found");
    let delay_s = (found - fault_ns) as f64 * 1e-9;
    assert!(delay_s <= 60.0, "found after {delay_s} s");
    let r = run.monitor.report();
    let since = r.stuck[1].since_ns.unwrap();
    // Dated from the first whole block it was frozen in.
    assert!(
        since >= fault_ns && since - fault_ns <= SECOND_NS,
        "since {since}"
    );
    assert_eq!(r.suspect_since_ns, Some(since));
    let others: Vec<_> = not_ok(&r)
        .into_iter()
        .filter(|t| !t.starts_with("stuck[1]"))
        .collect();
    assert!(others.is_empty(), "{others:?}");
    eprintln!("stuck channel: suspect after {delay_s:.1} s");
}

/// Noise doubled in the daytime's vibration (2 mg RMS per axis): `watch` on every channel
/// within ten minutes (two noise windows of 41 s once the fault fills one), dated from the
/// window the fault began in; `suspect` once that has held for `confirm_s` (ten minutes here,
/// a day by default); the gravity tests say nothing.
#[test]
fn doubled_noise_is_watch_within_ten_minutes_then_suspect() {
    let config = HealthConfig {
        confirm_s: 600.0,
        ..HealthConfig::default()
    };
    let mut run = Run::new(2, daytime(), &config);
    let fault_ns = EPOCH_NS + 300 * SECOND_NS + 500_000_000;
    run.inject(fault_ns, Fault::Noise { factor: 2.0 });
    run.run(fault_ns);
    let before = run.monitor.report();
    assert!(not_ok(&before).is_empty(), "{:?}", not_ok(&before));
    assert!(before.noise.iter().all(|t| t.judged));
    let watch = run
        .run_until(fault_ns + 600 * SECOND_NS, |r| {
            r.noise.iter().all(|t| t.verdict == Verdict::Watch)
        })
        .expect("watch");
    let watch_s = (watch - fault_ns) as f64 * 1e-9;
    // The window the fault began in is at most 41 s before it.
    let window_ns = 41 * SECOND_NS;
    for t in run.monitor.report().noise {
        let since = t.since_ns.unwrap();
        assert!(
            since >= fault_ns - window_ns && since <= fault_ns + window_ns,
            "{t:?}"
        );
        assert!((t.statistic / 2.0 - 1.0).abs() < 0.2, "{t:?}");
    }
    let found = run
        .run_until(fault_ns + 1800 * SECOND_NS, |r| {
            r.noise.iter().all(|t| t.verdict == Verdict::Suspect)
        })
        .expect("found");
    let delay_s = (found - fault_ns) as f64 * 1e-9;
    assert!(
        (600.0..=600.0 + 2.0 * 41.0 + 41.0).contains(&delay_s),
        "suspect after {delay_s} s"
    );
    let r = run.monitor.report();
    for t in r.noise {
        assert!(t.since_ns.unwrap() >= fault_ns - window_ns);
    }
    let others: Vec<_> = not_ok(&r)
        .into_iter()
        .filter(|t| !t.starts_with("noise"))
        .collect();
    assert!(others.is_empty(), "{others:?}");
    eprintln!("noise ×2: watch after {watch_s:.1} s, suspect after {delay_s:.1} s");
}

/// Two isolated spikes of 50 mV (50 σ) a minute on one channel, 120 times the allowed rate:
/// `watch` within minutes, `suspect` once that has held for `confirm_s` (ten minutes here);
/// the channel's noise estimate stays clean.
#[test]
fn spikes_are_found_within_minutes_and_kept_out_of_the_noise() {
    let config = HealthConfig {
        confirm_s: 600.0,
        ..HealthConfig::default()
    };
    let mut run = Run::new(3, daytime(), &config);
    let fault_ns = EPOCH_NS + 120 * SECOND_NS;
    run.inject(
        fault_ns,
        Fault::Spikes {
            channel: 0,
            per_hour: 120.0,
            height_v: 0.05,
        },
    );
    let watch = run
        .run_until(fault_ns + 1800 * SECOND_NS, |r| {
            r.spikes[0].verdict >= Verdict::Watch
        })
        .expect("watch");
    let watch_s = (watch - fault_ns) as f64 * 1e-9;
    let found = run
        .run_until(fault_ns + 3600 * SECOND_NS, |r| {
            r.spikes[0].verdict == Verdict::Suspect
        })
        .expect("found");
    let delay_s = (found - fault_ns) as f64 * 1e-9;
    let r = run.monitor.report();
    assert!(watch_s <= 900.0, "watch after {watch_s} s");
    assert!(
        (600.0..=1800.0).contains(&delay_s),
        "found after {delay_s} s"
    );
    assert_eq!(r.noise[0].verdict, Verdict::Ok, "{:?}", r.noise[0]);
    // The rate is an hour's average, still climbing towards 120/h.
    assert!(
        r.spikes[0].statistic > 2.0 * r.spikes[0].uncertainty,
        "{:?}",
        r.spikes[0]
    );
    let others: Vec<_> = not_ok(&r)
        .into_iter()
        .filter(|t| !t.starts_with("spikes[0]"))
        .collect();
    assert!(others.is_empty(), "{others:?}");
    eprintln!(
        "spikes 120/h: watch after {watch_s:.0} s, suspect after {delay_s:.0} s, rate {:.0} ± {:.0} /h",
        r.spikes[0].statistic, r.spikes[0].uncertainty
    );
}

/// One-hour days: ±10 °C and a third of each in night-time quiet.
fn compressed() -> (FieldConfig, HealthConfig) {
    let field = FieldConfig {
        day_s: 3600.0,
        ..FieldConfig::default()
    };
    let g = LocalGravity::normal(47.37, 420.0).unwrap();
    let config = HealthConfig {
        local_gravity: Some(LocalGravity::known(field.gravity_mps2, g.uncertainty_mps2).unwrap()),
        baseline_s: 3600.0,
        baseline_stretches: 30,
        ..HealthConfig::default()
    };
    (field, config)
}

/// The channel nearest gravity of the record's sensor.
fn gravity_channel(field: &FieldConfig) -> usize {
    (0..3)
        .max_by(|&a, &b| field.up[a].abs().total_cmp(&field.up[b].abs()))
        .unwrap()
}

/// Runs a compressed-day sensor to its baseline and beyond, healthy, then injects `fault` in
/// the daytime (the worst moment: the next quiet stretch is most of a day away) and returns the
/// report when the relative test is `suspect`, and the delay in compressed days.
fn relative_detection(seed: u64, fault: Fault) -> (HealthReport, f64) {
    let (field, config) = compressed();
    let mut run = Run::new(seed, field, &config);
    // 2.3 days: baseline done after the second night, the third night seen, now 07:12.
    let fault_ns = EPOCH_NS + (2.3 * HOUR_NS as f64) as i64;
    run.inject(fault_ns, fault);
    run.run(fault_ns);
    let before = run.monitor.report();
    assert!(run.monitor.has_gravity_baseline());
    assert!(
        not_ok(&before).is_empty(),
        "healthy before the fault: {:?}",
        not_ok(&before)
    );
    assert!(before.gravity_absolute.judged && before.gravity_relative.judged);
    let found = run
        .run_until(fault_ns + 2 * HOUR_NS, |r| {
            r.gravity_relative.verdict == Verdict::Suspect
        })
        .unwrap_or_else(|| panic!("not found: {:?}", run.monitor.report()));
    let r = run.monitor.report();
    (r, (found - fault_ns) as f64 / HOUR_NS as f64)
}

/// A 0.1 % gain change on the output channel nearest gravity moves the quiet magnitude by
/// about 9.8 mm/s² (1 mg): far below the static set's own uncertainty along gravity (about
/// 13 mm/s² here), so the absolute test cannot see it, and the relative test, where the
/// calibration's error cancels, finds it at the first quiet stretch after the change.
#[test]
fn a_tenth_of_a_percent_gain_drift_is_found_within_a_day() {
    let (field, _) = compressed();
    let channel = gravity_channel(&field);
    let (r, delay_days) = relative_detection(
        4,
        Fault::GainStep {
            channel,
            relative: 0.001,
        },
    );
    assert!(delay_days <= 1.0, "found after {delay_days} days");
    let change = r.gravity_relative.statistic;
    assert!(
        (change - 0.001 * 9.80665).abs() < 3.0 * r.gravity_relative.uncertainty + 5e-4,
        "{:?}",
        r.gravity_relative
    );
    assert_ne!(r.gravity_absolute.verdict, Verdict::Suspect);
    let others: Vec<_> = not_ok(&r)
        .into_iter()
        .filter(|t| !t.starts_with("gravity"))
        .collect();
    assert!(others.is_empty(), "{others:?}");
    eprintln!(
        "gain +0.1 %: relative suspect after {delay_days:.2} days, change {:.2e} ± {:.1e} m/s²",
        change, r.gravity_relative.uncertainty
    );
}

/// A 10 mg offset step on the axis nearest gravity: the corrected reading drops by 98 mm/s²
/// along gravity.
#[test]
fn a_ten_mg_offset_step_is_found_within_a_day() {
    let (field, _) = compressed();
    let axis = gravity_channel(&field);
    let (r, delay_days) = relative_detection(
        5,
        Fault::OffsetStep {
            axis,
            mps2: 0.01 * 9.80665,
        },
    );
    assert!(delay_days <= 1.0, "found after {delay_days} days");
    let change = r.gravity_relative.statistic;
    assert!((change + 0.0981).abs() < 0.003, "{:?}", r.gravity_relative);
    assert!(r.gravity_relative.since_ns.is_some());
    eprintln!(
        "offset 10 mg: relative suspect after {delay_days:.2} days, change {change:.4} ± {:.1e} m/s²",
        r.gravity_relative.uncertainty
    );
}

/// A record whose offset along gravity is wrong by three expanded uncertainties of the
/// absolute comparison (3·k·u, k at 95 %): `suspect` once the test has its ten quiet minutes.
#[test]
fn an_absolute_error_of_three_k_u_is_found_within_an_hour() {
    let (field, config) = compressed();
    let mut probe = Run::new(6, field.clone(), &config);
    probe.run(EPOCH_NS + 12 * 60 * SECOND_NS);
    let honest = probe.monitor.report().gravity_absolute;
    assert!(honest.judged && honest.verdict == Verdict::Ok, "{honest:?}");
    // k at 95 % for the comparison's ν (≈ 56, the static fit's): below 2.01.
    let k = 2.01;
    let error = 3.0 * k * honest.uncertainty;
    let mut record = probe.record.clone();
    let axis = gravity_channel(&field);
    let sign = field.up[axis].signum();
    record.static_set.offset[axis] += sign * error;
    let mut run = Run::with_record(record, 6, field, &config);
    let found = run
        .run_until(EPOCH_NS + HOUR_NS, |r| {
            r.gravity_absolute.verdict == Verdict::Suspect
        })
        .expect("found within the hour");
    let r = run.monitor.report();
    assert!(
        (r.gravity_absolute.statistic - honest.statistic - error).abs() < 1e-3,
        "{:?} vs {honest:?}",
        r.gravity_absolute
    );
    eprintln!(
        "absolute error {error:.4} m/s² (3·k·u): suspect after {:.0} s, D = {:.4} ± {:.4}",
        (found - EPOCH_NS) as f64 * 1e-9,
        r.gravity_absolute.statistic,
        r.gravity_absolute.uncertainty
    );
}

fn encode(samples: &[[f32; 3]]) -> Vec<u8> {
    samples
        .iter()
        .flat_map(|s| s.iter().flat_map(|x| x.to_le_bytes()))
        .collect()
}

/// The bytes of a raw batch, its protocol view and the numbers give the same monitor; a batch
/// lost in between breaks the stream once and no block spans the hole.
#[test]
fn bytes_views_and_numbers_agree_and_gaps_break_blocks() {
    let config = HealthConfig::default();
    let run = Run::new(8, FieldConfig::default(), &config);
    let mut field = run.field.clone();
    let mut by_numbers = run.monitor.clone();
    let mut by_bytes = run.monitor.clone();
    let mut by_view = run.monitor.clone();
    let mut buf = Vec::new();
    let mut payload = Vec::new();
    for i in 0..3000 {
        let b = field.next_batch(&mut buf);
        if i == 1234 {
            continue;
        }
        by_numbers.feed_samples(b.timestamp_ns, b.sample_rate_hz, b.temperature_c, &buf);
        by_bytes.feed(
            b.timestamp_ns,
            b.sample_rate_hz,
            b.temperature_c,
            &encode(&buf),
        );
        let raw = RawBatch {
            header: BatchHeader {
                sensor_id: SensorId::new("sim").unwrap(),
                sequence: i,
                timestamp_ns: b.timestamp_ns,
                sample_rate_hz: b.sample_rate_hz,
            },
            temperature_c: b.temperature_c,
            samples: buf.clone(),
        };
        payload.clear();
        raw.encode_into(&mut payload);
        by_view.feed_view(&RawBatchView::parse(&payload).unwrap());
    }
    let a = format!("{:?}", by_numbers.report());
    assert_eq!(a, format!("{:?}", by_bytes.report()));
    assert_eq!(a, format!("{:?}", by_view.report()));
    let r = by_numbers.report();
    assert_eq!(r.discontinuities, 1);
    // 300 s in 1 s blocks, but the hole at 123.4 s costs the block it fell in: 123 before,
    // and 176 from 123.5 s to 299.5 s.
    assert_eq!(r.blocks, 299, "{r:?}");
}
