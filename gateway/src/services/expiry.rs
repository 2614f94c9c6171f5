//! Forgets the uncalibrated sensors that fell silent, so that what a flood of made-up ids
//! admitted ages out (`state::sensors`, "Admission").

use std::sync::Arc;

use super::{Context, Task};
use crate::clock::now_ns;
use crate::shutdown::Shutdown;
use crate::state::SensorTable;

/// Starts `expire_unknown_sensors`.
pub fn start(ctx: &Context) -> Task {
    tokio::spawn(expire_unknown_sensors(
        ctx.table.clone(),
        ctx.shutdown.clone(),
    ))
}

/// Forgets uncalibrated sensors silent for `unknown_sensor_expiry_s`, checking ten times per
/// expiry period (at least every 10 s and at most every 100 ms).
async fn expire_unknown_sensors(table: Arc<SensorTable>, mut shutdown: Shutdown) {
    let period = (table.unknown_sensor_expiry() / 10).clamp(
        std::time::Duration::from_millis(100),
        std::time::Duration::from_secs(10),
    );
    let mut tick = tokio::time::interval(period);
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    loop {
        tokio::select! {
            _ = tick.tick() => {}
            _ = shutdown.recv() => return,
        }
        let n = table.expire_idle(now_ns());
        if n > 0 {
            tracing::info!(forgotten = n, "silent uncalibrated sensors forgotten");
        }
    }
}
