//! Triax sensor node: reads a three-axis MEMS accelerometer, publishes its outputs as raw
//! batches on `triax/<building>/raw/<sensor>` (PROTOCOL.md §2.1), and keeps every batch it
//! sent in a bounded on-disk ring that answers queries on `triax/<building>/buffer/<sensor>`
//! (PROTOCOL.md §5.4), so that a gateway fills what a network outage cost it.
//!
//! - [`source`]: the [`Source`] trait, a simulated sensor and a CSV reader;
//! - [`adxl355`]: the ADXL355 driver over a register [`adxl355::Bus`], with a register model
//!   of the part; [`spidev`]: the bus on Linux SPI;
//! - [`batcher`]: samples into batches, cut where the time stamps leave their grid;
//! - [`ring`]: the on-disk buffer and the node's durable sequence numbers;
//! - [`buffer`]: the query contract and the status message;
//! - [`node`]: the threads and the Zenoh side.

pub mod adxl355;
pub mod batcher;
pub mod buffer;
pub mod node;
pub mod ring;
pub mod source;
pub mod spidev;

pub use buffer::{BufferQuery, BufferStatus, MAX_BATCHES_PER_QUERY};
pub use node::{run, NodeConfig, NodeError, Summary};
pub use ring::{Ring, RingConfig, RingError, RingStats};
pub use source::{CsvSource, Sample, SimSource, Source, SourceError};
