//! Whose history a directory is. The building (and the gateway) that created it are recorded in
//! its `OWNER` file before anything else is written, and checked at every open: batches carry
//! sensor ids but no building, so nothing else in the directory could tell one building's
//! history from another's, and a gateway pointed at a neighbour's history would serve it as its
//! own.
//!
//! ```text
//! OWNER   {"format":1,"building":"hq","gateway_name":"triax-gateway-hq"}
//! ```
//!
//! Written once, atomically (a temporary file, synced, renamed, the directory synced): a crash
//! leaves either no `OWNER` or a whole one.

use std::io::Write;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};
use triax_protocol::BuildingId;

use crate::HistoryError;

/// Name of the owner file in a history directory.
pub const OWNER_FILE: &str = "OWNER";

/// Layout of the owner file; a history whose file names another is refused, not guessed at.
const OWNER_FORMAT: u32 = 1;

/// Whom a history belongs to.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Owner {
    pub building: BuildingId,
    /// The gateway that created the history: reported, not checked (a gateway may be renamed
    /// and keep its building's history).
    pub gateway_name: String,
}

/// What opening made of a history's owner.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum OwnerCheck {
    /// No owner was asked for ([`crate::HistoryConfig::owner`] is none): nothing recorded or
    /// checked.
    Unchecked,
    /// A new history: the opening owner is recorded.
    Created,
    /// The recorded building is the opening one. `recorded_gateway_name` when the gateway that
    /// created it had another name.
    Confirmed {
        recorded_gateway_name: Option<String>,
    },
    /// A history made before owners were recorded: it held segments and no owner, and is now
    /// recorded as the opening building's. Its batches cannot be told apart from another
    /// building's, so the caller should say so.
    Adopted,
}

/// The owner file as stored.
#[derive(Debug, Serialize, Deserialize)]
struct OwnerFile {
    format: u32,
    building: BuildingId,
    gateway_name: String,
}

fn path_of(dir: &Path) -> PathBuf {
    dir.join(OWNER_FILE)
}

/// The owner recorded in the history in `dir`; none when no owner was ever recorded.
pub fn read_owner(dir: &Path) -> Result<Option<Owner>, HistoryError> {
    let path = path_of(dir);
    let bytes = match std::fs::read(&path) {
        Ok(b) => b,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
        Err(source) => {
            return Err(HistoryError::Io {
                action: "read the owner file",
                path,
                source,
            })
        }
    };
    let unreadable = |reason: String| HistoryError::OwnerUnreadable {
        path: path.clone(),
        reason,
    };
    let file: OwnerFile = serde_json::from_slice(&bytes).map_err(|e| unreadable(e.to_string()))?;
    if file.format != OWNER_FORMAT {
        return Err(unreadable(format!(
            "format {} (this version reads {OWNER_FORMAT})",
            file.format
        )));
    }
    Ok(Some(Owner {
        building: file.building,
        gateway_name: file.gateway_name,
    }))
}

/// Refuses the history in `dir` if it records another building than `owner`'s.
pub(crate) fn refuse_foreign(dir: &Path, owner: &Owner) -> Result<Option<Owner>, HistoryError> {
    let recorded = read_owner(dir)?;
    match &recorded {
        Some(r) if r.building != owner.building => Err(HistoryError::Foreign {
            path: dir.to_owned(),
            recorded: r.building.clone(),
            recorded_gateway_name: r.gateway_name.clone(),
            configured: owner.building.clone(),
        }),
        _ => Ok(recorded),
    }
}

/// Checks the history in `dir` against `owner`, and records `owner` when none is. To be called
/// with the directory's lock held, so that no other writer records another owner meanwhile.
/// `has_segments`: whether the directory already held data (an owner missing then means a
/// history from before owners were recorded).
pub(crate) fn claim(
    dir: &Path,
    owner: &Owner,
    has_segments: bool,
) -> Result<OwnerCheck, HistoryError> {
    if let Some(recorded) = refuse_foreign(dir, owner)? {
        return Ok(OwnerCheck::Confirmed {
            recorded_gateway_name: (recorded.gateway_name != owner.gateway_name)
                .then_some(recorded.gateway_name),
        });
    }
    write_owner(dir, owner)?;
    Ok(if has_segments {
        OwnerCheck::Adopted
    } else {
        OwnerCheck::Created
    })
}

fn write_owner(dir: &Path, owner: &Owner) -> Result<(), HistoryError> {
    let path = path_of(dir);
    let tmp = dir.join(format!("{OWNER_FILE}.tmp"));
    let io = |action, path: &Path| {
        let path = path.to_owned();
        move |source| HistoryError::Io {
            action,
            path,
            source,
        }
    };
    // A string and a validated id always serialise.
    let body = serde_json::to_vec(&OwnerFile {
        format: OWNER_FORMAT,
        building: owner.building.clone(),
        gateway_name: owner.gateway_name.clone(),
    })
    .expect("owner file serialises");
    let mut file = std::fs::File::create(&tmp).map_err(io("write the owner file", &tmp))?;
    file.write_all(&body)
        .and_then(|()| file.sync_all())
        .map_err(io("write the owner file", &tmp))?;
    std::fs::rename(&tmp, &path).map_err(io("write the owner file", &path))?;
    // The rename itself must survive a crash, before any batch is kept under this owner.
    std::fs::File::open(dir)
        .and_then(|d| d.sync_all())
        .map_err(io("sync the history directory", dir))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{History, HistoryConfig, Kept, Verdict};

    fn owner(building: &str) -> Owner {
        Owner {
            building: BuildingId::new(building).unwrap(),
            gateway_name: format!("triax-gateway-{building}"),
        }
    }

    fn open(dir: &Path, who: Option<Owner>) -> Result<crate::Opened, HistoryError> {
        let mut c = HistoryConfig::new(dir);
        c.owner = who;
        History::open(c)
    }

    /// Keeps one batch and makes it durable, so the directory holds data.
    fn keep_one(opened: crate::Opened) {
        let mut w = opened.writer;
        let samples = [0u8; 12];
        let kept = Kept {
            arrival: 0,
            sequence: 1,
            timestamp_ns: 1_800_000_000_000_000_000,
            sample_rate_hz: 100.0,
            temperature_c: None,
            calibration_version: 1,
            verdict: Verdict::InOrder,
            samples: &samples[..],
        };
        w.append(
            &triax_protocol::InlineId::new(&triax_protocol::SensorId::new("s1").unwrap()),
            kept,
            None,
        );
        w.flush().unwrap();
    }

    #[test]
    fn a_new_history_records_its_owner_and_reopens_as_its_own() {
        let dir = tempfile::tempdir().unwrap();
        let opened = open(dir.path(), Some(owner("xb"))).unwrap();
        assert_eq!(opened.owner, OwnerCheck::Created);
        keep_one(opened);
        assert_eq!(read_owner(dir.path()).unwrap(), Some(owner("xb")));

        let again = open(dir.path(), Some(owner("xb"))).unwrap();
        assert_eq!(
            again.owner,
            OwnerCheck::Confirmed {
                recorded_gateway_name: None
            }
        );
        drop(again);

        // A renamed gateway of the same building keeps its history, and hears the old name.
        let renamed = Owner {
            gateway_name: "gw-2".into(),
            ..owner("xb")
        };
        let opened = open(dir.path(), Some(renamed)).unwrap();
        assert_eq!(
            opened.owner,
            OwnerCheck::Confirmed {
                recorded_gateway_name: Some("triax-gateway-xb".into())
            }
        );
        drop(opened);
        assert_eq!(
            read_owner(dir.path()).unwrap(),
            Some(owner("xb")),
            "the creator stays recorded"
        );
    }

    #[test]
    fn another_building_is_refused_naming_the_path_and_both_buildings() {
        let dir = tempfile::tempdir().unwrap();
        keep_one(open(dir.path(), Some(owner("xb"))).unwrap());
        let segments_before = std::fs::read_dir(dir.path()).unwrap().count();

        let err = open(dir.path(), Some(owner("zz"))).unwrap_err();
        assert!(
            matches!(&err, HistoryError::Foreign { recorded, configured, .. }
                if recorded.as_str() == "xb" && configured.as_str() == "zz"),
            "{err:?}"
        );
        let text = err.to_string();
        for part in [
            dir.path().display().to_string(),
            "building xb".into(),
            "triax-gateway-xb".into(),
            "building zz".into(),
        ] {
            assert!(text.contains(&part), "{text:?} names {part:?}");
        }
        assert_eq!(
            std::fs::read_dir(dir.path()).unwrap().count(),
            segments_before,
            "a refused open writes nothing"
        );
        assert_eq!(read_owner(dir.path()).unwrap(), Some(owner("xb")));
    }

    #[test]
    fn another_building_is_refused_even_while_the_owner_holds_the_history() {
        let dir = tempfile::tempdir().unwrap();
        let held = open(dir.path(), Some(owner("xb"))).unwrap();
        let err = open(dir.path(), Some(owner("zz"))).unwrap_err();
        assert!(matches!(err, HistoryError::Foreign { .. }), "{err:?}");
        // The owner itself is only told that the history is in use.
        let err = open(dir.path(), Some(owner("xb"))).unwrap_err();
        assert!(matches!(err, HistoryError::Locked { .. }), "{err:?}");
        drop(held);
    }

    #[test]
    fn a_history_from_before_owners_is_adopted_by_the_first_building_to_open_it() {
        let dir = tempfile::tempdir().unwrap();
        // Opening with no owner is what a history made before owners were recorded looks like.
        keep_one(open(dir.path(), None).unwrap());
        assert_eq!(read_owner(dir.path()).unwrap(), None);

        let opened = open(dir.path(), Some(owner("xb"))).unwrap();
        assert_eq!(opened.owner, OwnerCheck::Adopted);
        assert_eq!(opened.history.sensors().len(), 1, "its batches are kept");
        drop(opened);
        assert_eq!(read_owner(dir.path()).unwrap(), Some(owner("xb")));
        let err = open(dir.path(), Some(owner("zz"))).unwrap_err();
        assert!(matches!(err, HistoryError::Foreign { .. }), "{err:?}");
    }

    #[test]
    fn opening_with_no_owner_neither_records_nor_checks() {
        let dir = tempfile::tempdir().unwrap();
        keep_one(open(dir.path(), Some(owner("xb"))).unwrap());
        let opened = open(dir.path(), None).unwrap();
        assert_eq!(opened.owner, OwnerCheck::Unchecked);
        drop(opened);
        assert_eq!(read_owner(dir.path()).unwrap(), Some(owner("xb")));
    }

    #[test]
    fn an_unreadable_owner_file_is_refused_not_replaced() {
        let dir = tempfile::tempdir().unwrap();
        let newer = br#"{"format":2,"building":"xb","gateway_name":"gw"}"#;
        std::fs::write(dir.path().join(OWNER_FILE), newer).unwrap();
        let err = open(dir.path(), Some(owner("xb"))).unwrap_err();
        assert!(
            matches!(&err, HistoryError::OwnerUnreadable { reason, .. } if reason.contains("format 2")),
            "{err:?}"
        );
        assert_eq!(std::fs::read(dir.path().join(OWNER_FILE)).unwrap(), newer);
    }
}
