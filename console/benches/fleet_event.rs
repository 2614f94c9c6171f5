//! The fleet event's bytes on a quiet fleet: `cargo bench -p triax-console --bench fleet_event`.
//!
//! 100 buildings × 100 calibrated sensors fed into the console's own `Fleet` as its Zenoh side
//! feeds it: a heartbeat per building every second and a status answer per building every 2 s
//! whose counters grow (every sensor sends 100 samples a second), no alert, no state change.
//! Once a second the console's own brief and delta are taken, as its event stream does, for
//! 30 s of real time. Printed: the bytes a page receives per second as `fleet_delta` events,
//! the first `fleet` event (the whole brief), the old whole snapshot the event used to repeat
//! every second, and the CPU time of one tick. No Zenoh: what is measured is what the console
//! serialises.

use std::time::{Duration, Instant};

use serde_json::json;
use triax_console::fleet::{Fleet, FleetOptions};
use triax_protocol::messages::GatewayStatus;
use triax_protocol::signing::TrustedKeys;

const BUILDINGS: usize = 100;
const SENSORS: usize = 100;
const SECONDS: u64 = 30;

fn rfc(t: time::OffsetDateTime) -> String {
    t.format(&time::format_description::well_known::Rfc3339)
        .expect("formats")
}

fn status(b: usize, started: time::OffsetDateTime, samples: u64) -> GatewayStatus {
    let now = time::OffsetDateTime::now_utc();
    let sensors: Vec<_> = (0..SENSORS)
        .map(|s| {
            json!({
                "sensor_id": format!("acc-{s:03}"), "last_seen": rfc(now), "batches": samples / 50,
                "samples": samples, "gaps": 0, "missing_batches": 0, "late_batches": 0,
                "duplicates": 0, "rejects": 0, "flagged_samples": 0, "keys_declared": true,
                "calibration_version": 3, "mode": "dynamic",
                "valid_from": rfc(now - time::Duration::DAY), "valid_until": null,
            })
        })
        .collect();
    serde_json::from_value(json!({
        "format_version": 1, "building": format!("b{b:03}"), "gateway": format!("gw-{b:03}"),
        "started_at": rfc(started), "reported_at": rfc(now), "malformed": 0, "dropped": 0,
        "pushes_accepted": 0, "pushes_refused": 0, "total_sensors": SENSORS,
        "sensors": sensors,
    }))
    .expect("a gateway's status")
}

fn heartbeat(b: usize, seq: u64) -> Vec<u8> {
    serde_json::to_vec(&json!({
        "format_version": 1, "building": format!("b{b:03}"), "gateway": format!("gw-{b:03}"),
        "sequence": seq, "at": rfc(time::OffsetDateTime::now_utc()),
        "sensors": (0..SENSORS)
            .map(|s| (format!("acc-{s:03}"), json!({"last_sequence": seq, "last_timestamp_ns": 0})))
            .collect::<serde_json::Map<_, _>>(),
    }))
    .expect("serialises")
}

fn main() {
    let fleet = Fleet::new(FleetOptions {
        buildings: vec![],
        status_interval: Duration::from_secs(2),
        expiry_warning: Duration::from_secs(30 * 86_400),
        trusted_alert_keys: TrustedKeys::default(),
        provenance: std::sync::Arc::new(triax_console::provenance::Provenance::on_trust()),
    });
    let started = time::OffsetDateTime::now_utc();
    for b in 0..BUILDINGS {
        fleet.status(status(b, started, 0));
        fleet.heartbeat(&format!("triax/b{b:03}/heartbeat"), &heartbeat(b, 0), None);
    }
    let snapshot_bytes = serde_json::to_vec(&fleet.snapshot())
        .expect("serialises")
        .len();
    let mut before = fleet.brief();
    let brief_bytes = serde_json::to_vec(&before).expect("serialises").len();
    let t0 = Instant::now();
    let mut delta_bytes = Vec::new();
    let mut tick_cpu = Vec::new();
    let mut quiet = 0;
    for second in 1..=SECONDS {
        let due = t0 + Duration::from_secs(second);
        std::thread::sleep(due.saturating_duration_since(Instant::now()));
        for b in 0..BUILDINGS {
            fleet.heartbeat(
                &format!("triax/b{b:03}/heartbeat"),
                &heartbeat(b, second),
                None,
            );
            if second % 2 == 0 {
                fleet.status(status(b, started, second * 100));
            }
        }
        let t = Instant::now();
        let brief = fleet.brief();
        let delta = brief.delta(&before, second);
        let text = serde_json::to_string(&delta).expect("serialises");
        tick_cpu.push(t.elapsed().as_secs_f64() * 1e3);
        quiet += usize::from(delta.is_quiet());
        // As the stream frames it: `event: fleet_delta\ndata: …\n\n`.
        delta_bytes.push(text.len() + "event: fleet_delta\ndata: \n\n".len());
        before = brief;
    }
    let total: usize = delta_bytes.iter().sum();
    tick_cpu.sort_by(f64::total_cmp);
    println!(
        "{BUILDINGS} buildings x {SENSORS} sensors, quiet, {SECONDS} s of real time:\n\
         fleet_delta events: {:.0} B/s (largest one {} B; {quiet} of {SECONDS} quiet)\n\
         first fleet event (the whole brief): {brief_bytes} B\n\
         the whole snapshot once repeated every second: {snapshot_bytes} B\n\
         one tick (brief, delta, JSON): median {:.1} ms ({:.1}-{:.1})",
        total as f64 / SECONDS as f64,
        delta_bytes.iter().max().unwrap_or(&0),
        tick_cpu[tick_cpu.len() / 2],
        tick_cpu[0],
        tick_cpu[tick_cpu.len() - 1],
    );
}
