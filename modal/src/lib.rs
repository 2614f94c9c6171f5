//! The building's own health: its modes (frequencies, damping ratios and shapes), identified
//! from ambient vibration with an uncertainty that states its coverage, and tracked.
//!
//! To be completed.

pub mod error;
pub mod identify;
pub mod model;
pub mod sim;
pub mod ssi;
pub mod stabilisation;
pub mod track;
pub mod uncertainty;
pub mod window;

pub use error::ModalError;
pub use identify::{identify, Identification, Mode, ShapeComponent, SsiConfig};
pub use model::{BuildingModel, Direction, ModelError, SensorPlacement};
pub use uncertainty::Estimate;
pub use window::{ChainUncertainty, ChannelId, ChannelOptions, SensorSeries, Window};
