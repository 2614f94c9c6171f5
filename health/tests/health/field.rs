//! Healthy sensors in the motion of occupied buildings (`triax_health::motion`): what the
//! checks say of them, and how fast they still find what they are meant to.

use triax_health::sim::{FieldConfig, FieldMotion, EPOCH_NS};
use triax_health::{HealthConfig, LocalGravity, Verdict};

use crate::util::{not_ok, Run, HOUR_NS};

/// Scratch: a few sensors for a day in an occupied building, verdicts printed.
#[test]
#[ignore]
fn scratch_occupied_day() {
    let fs: f64 = std::env::var("FS")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(100.0);
    let busy = std::env::var("BUSY").is_ok();
    for seed in 0..4u64 {
        let field = FieldConfig {
            sample_rate_hz: fs,
            motion: if busy {
                FieldMotion::busy()
            } else {
                FieldMotion::occupied()
            },
            vibration_day_mps2: 0.005,
            vibration_night_mps2: 0.001,
            ..FieldConfig::default()
        };
        let config = HealthConfig {
            local_gravity: Some(LocalGravity::normal(47.37, 420.0).unwrap()),
            ..HealthConfig::default()
        };
        let mut run = Run::new(100 + seed, field, &config);
        for hour in 1..=24 {
            run.run(EPOCH_NS + hour * HOUR_NS);
            let r = run.monitor.report();
            if r.verdict != Verdict::Ok {
                eprintln!("seed {seed} hour {hour}: {:?}", not_ok(&r));
                if r.verdict == Verdict::Suspect {
                    break;
                }
            }
        }
        let r = run.monitor.report();
        eprintln!(
            "seed {seed}: {} quiet stretches, noise {:?}",
            r.quiet_stretches,
            r.noise.map(|t| t.statistic)
        );
    }
}
