//! The gateway's state: the sensor table (each sensor's corrector snapshot, settings and
//! counters), the gateway's and the backfill's counters, what the health checks keep beside the
//! workers, the calibration store as the gateway holds it, and the key it signs with.
//!
//! Architecture invariant: the state knows nothing of Zenoh, of the sample path or of the
//! services; it imports only the settings and the foundations (`clock`, `sync`, `error`).

mod counters;
mod health;
mod sensors;
pub mod signer;
pub mod store;

pub use counters::{BackfillCounters, GatewayCounters};
pub use health::{GroupSlot, GroupTests, Groups, HealthSeed};
pub use sensors::{
    AdmissionCounters, SensorCounters, SensorEntry, SensorTable, ESTABLISHED_BATCHES, NO_HEALTH,
};
pub use signer::Signer;
