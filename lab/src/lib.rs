//! The calibration lab: bench files in, calibration records, corrected data and reports out.
//!
//! The mathematics lives in `triax_calibration::fit` (pure); this crate reads and checks the
//! input files ([`input`]), builds the record ([`record`]), renders the report ([`report`],
//! [`svg`]) and ties the steps together per command ([`commands`]). The `triax-lab` binary only
//! parses arguments, reads the clock and writes files.
//!
//! Recalibration: [`keypair`] (the lab's Ed25519 key files), [`registry`] (every record issued
//! and the buildings each sensor is assigned to), [`push`] (signed records to the buildings'
//! gateways over Zenoh, acknowledgements back), [`serve`] (the registry answering gateways'
//! catch-up queries), [`net`] (the Zenoh options they share), [`due`] (the sensors the
//! buildings' field health checks found suspect).
//!
//! Architecture invariant: nothing here writes a file except [`registry`], which owns the
//! registry directory; the other commands return what should be written, so a failing input
//! never leaves a partial output behind and tests need no disk for the outputs.

pub mod commands;
pub mod compare;
pub mod dcc;
pub mod due;
pub mod input;
pub mod keypair;
pub mod net;
pub mod push;
pub mod record;
pub mod registry;
pub mod report;
pub mod serve;
pub mod svg;

use std::path::PathBuf;

pub use input::InputError;

/// Why a lab command failed.
#[derive(Debug, thiserror::Error)]
pub enum LabError {
    #[error(transparent)]
    Input(#[from] InputError),
    /// A fit failed on the data of `file`.
    #[error("{file}: {source}")]
    Fit {
        file: PathBuf,
        #[source]
        source: triax_calibration::fit::FitError,
    },
    #[error("the calibration record cannot be loaded by the corrector: {0}")]
    Record(#[from] triax_calibration::corrector::LoadError),
    #[error("{file}: {problem}")]
    Json { file: PathBuf, problem: String },
    #[error("invalid argument: {0}")]
    Argument(String),
}
