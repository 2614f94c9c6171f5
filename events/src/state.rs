//! What the service keeps per building across restarts, in `<state_dir>/<building>/state.json`
//! (a new file renamed over the old): where each sensor's follower resumes, and the events
//! reported (their summaries; each report is in its event's directory).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};
use triax_client::follow::Position;
use triax_protocol::event::{EventReport, EventSummary};
use triax_protocol::{BuildingId, SensorId};

/// A resume point, as saved.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct SavedPosition {
    pub sequence: u64,
    pub timestamp_ns: i64,
}

/// One building's saved state.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BuildingState {
    pub resume: BTreeMap<SensorId, SavedPosition>,
    /// Reported events, oldest first.
    pub events: Vec<EventSummary>,
    /// Events whose report has the first modes window after them.
    #[serde(default)]
    pub modes_after: Vec<triax_protocol::EventId>,
}

impl BuildingState {
    pub fn positions(&self) -> BTreeMap<SensorId, Position> {
        self.resume
            .iter()
            .map(|(s, p)| {
                (
                    s.clone(),
                    Position {
                        sequence: p.sequence,
                        timestamp_ns: p.timestamp_ns,
                    },
                )
            })
            .collect()
    }
}

/// Why the state could not be read.
#[derive(Debug, thiserror::Error)]
#[error("state file {path}: {message}")]
pub struct StateError {
    pub path: String,
    pub message: String,
}

pub fn building_dir(root: &Path, building: &BuildingId) -> PathBuf {
    root.join(building.as_str())
}

pub fn event_dir(root: &Path, building: &BuildingId, event: &triax_protocol::EventId) -> PathBuf {
    building_dir(root, building)
        .join("events")
        .join(event.as_str())
}

fn state_path(root: &Path, building: &BuildingId) -> PathBuf {
    building_dir(root, building).join("state.json")
}

/// Reads a building's state; the default when there is none yet.
pub fn load(root: &Path, building: &BuildingId) -> Result<BuildingState, StateError> {
    let path = state_path(root, building);
    match std::fs::read(&path) {
        Ok(bytes) => serde_json::from_slice(&bytes).map_err(|e| StateError {
            path: path.display().to_string(),
            message: e.to_string(),
        }),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(BuildingState::default()),
        Err(e) => Err(StateError {
            path: path.display().to_string(),
            message: e.to_string(),
        }),
    }
}

/// Writes a building's state whole or not at all.
pub fn save(root: &Path, building: &BuildingId, state: &BuildingState) -> std::io::Result<()> {
    let body = serde_json::to_vec(state).map_err(std::io::Error::other)?;
    crate::files::write_whole(&state_path(root, building), &body)
}

/// The summary of a report, as the list of events gives it.
pub fn summary(r: &EventReport) -> EventSummary {
    let pfa = r
        .sensors
        .iter()
        .map(|s| s.pga_rotd100_mps2.value)
        .fold(None, |m: Option<f64>, v| Some(m.map_or(v, |m| m.max(v))));
    let drift = r
        .drifts
        .iter()
        .map(|d| d.drift_ratio.value)
        .fold(None, |m: Option<f64>, v| Some(m.map_or(v, |m| m.max(v))));
    EventSummary {
        event_id: r.event_id.clone(),
        revision: r.revision,
        start_ns: r.start_ns,
        end_ns: r.end_ns,
        tag: r.tag,
        drivers: r.drivers.clone(),
        peak_floor_acceleration_mps2: pfa,
        max_drift_ratio: drift,
        reported_at: r.reported_at,
    }
}
