//! The calibration store as the gateway holds it: claimed for the gateway's life, read whole
//! into the sensor table at start, then used only for pushes, catch-ups and suspect marks
//! (from blocking tasks).

use std::path::Path;
use std::sync::Arc;

use triax_calibration::corrector::Corrector;
use triax_calibration_store::{Store, StoreError};

use super::sensors::SensorTable;
use crate::config::Config;
use crate::error::GatewayError;

/// Opens the store, loads every current record into the table, and returns the store opened
/// afresh with how many records loaded.
///
/// Why afresh: sled keeps every leaf it has read in its page cache, and its `cache_capacity`
/// does not bound that below a few hundred leaves (the cache is split in 256 shards, each
/// keeping at least one page). A handle that has read every record at start keeps about
/// 2 000 of them, 11 MiB for ten thousand sensors, for nothing: the gateway reads the store
/// again only for a push or a catch-up. A new handle starts with an empty cache, and sled's
/// directory lock, released in the background when the first handle closes, is waited for by
/// [`Store::open`].
async fn open_and_load(
    path: &Path,
    table: &Arc<SensorTable>,
) -> Result<(Store, usize), StoreError> {
    let task_failed = |e: tokio::task::JoinError| StoreError::Io {
        action: "load records",
        source: std::io::Error::other(e.to_string()),
    };
    let open_path = path.to_path_buf();
    let t = table.clone();
    // Each record is loaded into its corrector and health monitor, then dropped: the gateway
    // never holds every record at once.
    let (scan, suspects) = tokio::task::spawn_blocking(move || {
        let store = Store::open(&open_path)?;
        let scan = store.map_current(|record| {
            let corrector = Corrector::from_record(&record);
            let health = corrector
                .as_ref()
                .map(|c| t.health_seed(&record, c))
                .unwrap_or_default();
            (record.sensor_id, record.version, corrector, health)
        })?;
        Ok::<_, StoreError>((scan, store.suspects()?))
    })
    .await
    .map_err(task_failed)??;
    for skipped in scan.skipped.iter().chain(&suspects.skipped) {
        tracing::error!(entry = %skipped, "unreadable store entry: sensor stays uncalibrated");
    }
    let mut loaded = 0;
    for (sensor_id, version, corrector, health) in scan.value {
        match corrector {
            Ok(c) => {
                table.install(c, health);
                loaded += 1;
            }
            // The store validates on put; this is a record from an older, laxer build.
            Err(e) => tracing::error!(sensor = %sensor_id, version, cause = %e,
                "stored record does not load: sensor stays uncalibrated"),
        }
    }
    // The newest suspect mark of each sensor: older records no longer correct anything live.
    for m in suspects.value {
        if let Some(e) = table.get(&m.sensor_id) {
            e.set_suspect(m.version, m.flagged_from_ns);
        }
    }
    let open_path = path.to_path_buf();
    let store = tokio::task::spawn_blocking(move || Store::open(&open_path))
        .await
        .map_err(task_failed)??;
    Ok((store, loaded))
}

/// Holds the gateway's claim on its store for its life: a second gateway on the same store (and
/// history) is refused at start, and none can slip in while the store is closed and opened again
/// at start-up (see [`open_and_load`]).
fn claim_store(store_path: &Path) -> Result<std::fs::File, GatewayError> {
    let path = store_path.with_extension("lock");
    let io = |source| GatewayError::Store {
        path: path.clone(),
        source: StoreError::Io {
            action: "lock the store",
            source,
        },
    };
    if let Some(parent) = path.parent().filter(|p| !p.as_os_str().is_empty()) {
        std::fs::create_dir_all(parent).map_err(io)?;
    }
    let file = std::fs::File::options()
        .create(true)
        .truncate(false)
        .write(true)
        .open(&path)
        .map_err(io)?;
    match triax_lockfile::try_lock_exclusive(&file) {
        Ok(true) => Ok(file),
        Ok(false) => Err(io(std::io::Error::other(
            "another gateway holds this store",
        ))),
        Err(e) => Err(io(e)),
    }
}

/// The store, claimed and loaded.
pub struct Opened {
    pub store: Arc<Store>,
    /// Records that loaded into the table.
    pub loaded: usize,
    /// The lock on the store (`claim_store`), to hold for the gateway's life.
    pub claim: std::fs::File,
}

/// Claims the store, loads every current record into `table` and opens it afresh.
pub async fn open(config: &Config, table: &Arc<SensorTable>) -> Result<Opened, GatewayError> {
    let path = &config.store_path;
    let claim = claim_store(path)?;
    let (store, loaded) =
        open_and_load(path, table)
            .await
            .map_err(|source| GatewayError::Store {
                path: path.clone(),
                source,
            })?;
    tracing::info!(building = %config.building, calibrations = loaded, store = %path.display(), "calibrations loaded");
    Ok(Opened {
        store: Arc::new(store),
        loaded,
        claim,
    })
}
