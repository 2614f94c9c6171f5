//! The services around the sample path, each started by a `start` of its own from the
//! composition in `lib.rs`:
//!
//! - `backfill`: what a gap or the gateway's downtime cost, fetched from the nodes' buffers;
//! - `health`: the health queryable (the feed itself runs on the sample path);
//! - `replay`: the history queryable;
//! - `push`, `catchup`: signed calibration updates, pushed by the lab or caught up from its
//!   registry;
//! - `status`, `metrics`, `heartbeat`: what the gateway says of itself;
//! - `expiry`, `memory`: housekeeping (forgetting silent unknown sensors, keeping the resident
//!   set near what is used).
//!
//! Architecture invariant: a service uses the sample path's face (`crate::sample_path`'s
//! re-exports), the state and the settings, never the reverse; nothing below this module
//! imports it. A service the sample path feeds owns its end of the way in: the backfill makes
//! the queue a shard reports its holes into, and hands the shards its sending end.

pub mod backfill;
pub mod catchup;
pub mod expiry;
pub mod health;
pub mod heartbeat;
pub mod memory;
pub mod metrics;
pub mod push;
pub mod replay;
pub mod status;

use std::sync::Arc;

use time::OffsetDateTime;
use triax_calibration_store::Store;

use crate::config::Config;
use crate::shutdown::Shutdown;
use crate::state::{GatewayCounters, SensorTable, Signer};

/// What every service may be started with.
pub struct Context {
    pub config: Arc<Config>,
    pub session: zenoh::Session,
    pub table: Arc<SensorTable>,
    pub counters: Arc<GatewayCounters>,
    pub store: Arc<Store>,
    /// Signs every put and reply (PROTOCOL.md §6).
    pub signer: Arc<Signer>,
    pub started_at: OffsetDateTime,
    pub shutdown: Shutdown,
}

/// A running service, awaited at the gateway's stop.
pub type Task = tokio::task::JoinHandle<()>;
