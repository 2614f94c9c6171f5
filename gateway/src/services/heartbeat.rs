//! The heartbeat: every second, on `triax/<building>/heartbeat`, the gateway says it is alive and,
//! per sensor active in the last [`ACTIVE_WITHIN_NS`], the last batch it published (PROTOCOL.md
//! §5.3). A consumer that lost a sensor's last batch before the sensor fell silent learns of it
//! here, since no later batch will show the gap.

use std::collections::BTreeMap;
use std::sync::atomic::Ordering::Relaxed;
use std::sync::Arc;
use std::time::Duration;

use time::OffsetDateTime;
use triax_protocol::messages::{Heartbeat, HeartbeatSensor};
use triax_protocol::{to_json, BuildingId, Key, JSON_FORMAT_VERSION};
use zenoh::qos::CongestionControl;

use super::{Context, Task};
use crate::clock::now_ns;
use crate::shutdown::Shutdown;
use crate::state::{SensorTable, Signer};

pub const INTERVAL: Duration = Duration::from_secs(1);
/// Sensors that published within this are listed.
pub const ACTIVE_WITHIN_NS: i64 = 10_000_000_000;

/// The heartbeat at `now_ns`, number `sequence`.
pub fn heartbeat(
    building: &BuildingId,
    gateway: &str,
    table: &SensorTable,
    sequence: u64,
    now_ns: i64,
) -> Heartbeat {
    let mut sensors = BTreeMap::new();
    for e in table.snapshot() {
        let c = &e.counters;
        let recent = |at: i64| at != 0 && now_ns.saturating_sub(at) <= ACTIVE_WITHIN_NS;
        if recent(c.last_published_ns.load(Relaxed)) {
            let late = recent(c.late_published_ns.load(Relaxed));
            sensors.insert(
                e.id.clone(),
                HeartbeatSensor {
                    last_sequence: c.last_published_sequence.load(Relaxed),
                    last_timestamp_ns: c.last_published_timestamp_ns.load(Relaxed),
                    late_sequence: late.then(|| c.late_sequence.load(Relaxed)),
                    late_timestamp_ns: late.then(|| c.late_timestamp_ns.load(Relaxed)),
                },
            );
        }
    }
    Heartbeat {
        format_version: JSON_FORMAT_VERSION,
        building: building.clone(),
        gateway: gateway.to_owned(),
        sequence,
        at: OffsetDateTime::from_unix_timestamp_nanos(i128::from(now_ns))
            .unwrap_or(OffsetDateTime::UNIX_EPOCH),
        sensors,
    }
}

/// Puts a heartbeat every [`INTERVAL`] until shutdown.
pub async fn run(
    session: zenoh::Session,
    building: BuildingId,
    gateway: String,
    table: Arc<SensorTable>,
    signer: Arc<Signer>,
    mut shutdown: Shutdown,
) {
    let key = Key::Heartbeat(building.clone()).to_string();
    let mut tick = tokio::time::interval(INTERVAL);
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    let mut sequence = 0u64;
    loop {
        tokio::select! {
            _ = tick.tick() => {}
            _ = shutdown.recv() => return,
        }
        let body = to_json(&heartbeat(&building, &gateway, &table, sequence, now_ns()));
        sequence += 1;
        let put = session
            .put(&key, &body[..])
            .attachment(signer.attachment(&key, "", &body));
        let put = put.congestion_control(CongestionControl::Drop).await;
        if let Err(e) = put {
            tracing::warn!(cause = %e, "heartbeat not published");
        }
    }
}

/// Starts the heartbeat.
pub fn start(ctx: &Context) -> Task {
    tokio::spawn(run(
        ctx.session.clone(),
        ctx.config.building.clone(),
        ctx.config.gateway_name.clone(),
        ctx.table.clone(),
        ctx.signer.clone(),
        ctx.shutdown.clone(),
    ))
}
