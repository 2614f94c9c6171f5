//! The Triax wire protocol: the shared language of sensor nodes, gateways, the lab and consumers.
//!
//! - [`keys`]: the Zenoh key space, built and parsed in this one module.
//! - [`batch`]: the compact binary encoding of the high-rate streams ([`batch::RawBatch`],
//!   [`batch::CorrectedBatch`]).
//! - [`record`]: the calibration record ([`record::CalibrationRecord`]), in JSON.
//! - [`messages`]: signed pushes, acknowledgements, gateway status, tilt and alerts, in JSON.
//! - [`event`]: the event service's signed reports and its list of events, in JSON.
//! - [`provenance`]: the gateway's signatures on what it says, and the seals over its batches.
//! - [`json`]: the versioned JSON codec every JSON message goes through.
//!
//! PROTOCOL.md at the repository root documents every key and payload byte by byte.
//!
//! Architecture invariant: this crate knows nothing of the network, the disk, async runtimes or
//! linear algebra (no zenoh, tokio, sled, nalgebra), so a client in any setting can use it and
//! every decoder can be tested on bytes alone. Decoders return typed errors and never panic.

pub mod batch;
pub mod event;
pub mod json;
pub mod keys;
pub mod messages;
pub mod provenance;
pub mod record;
pub mod signing;

pub use batch::{
    flags, BatchHeader, CorrectedBatch, CorrectedBatchWriter, CorrectedSample, CorrectionInfo,
    DecodeError, Mode, RawBatch, RawBatchView,
};
pub use json::{from_json, to_json, to_json_pretty, JsonError, JsonMessage, JSON_FORMAT_VERSION};
pub use keys::{BuildingId, EventId, IdError, InlineId, Key, KeyError, SensorId};
pub use record::{CalibrationRecord, CalibrationSet, Domain, RecordError, SetKind};
