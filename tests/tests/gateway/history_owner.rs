//! A history serves only the building it was created for (issue 25, item 10: a gateway for `zz`
//! whose store sat in the same folder as `xb`'s served all of `xb`'s batches as its own).
//!
//! - `buildings_whose_stores_share_a_folder_keep_separate_histories`: two gateways with default
//!   history paths and stores in one folder each keep and serve their own batches only, one
//!   after the other and both at once; a gateway pointed at the other building's history
//!   explicitly is refused at start, naming the path and both buildings.

use std::path::Path;

use triax_client::{history::fetch, HistoryRequest};
use triax_gateway::config::FileConfig;
use triax_gateway::{Config, Gateway};
use triax_protocol::{BuildingId, SensorId};

use crate::util::*;

/// A test gateway for `building` whose history is where the defaults put it (the tests'
/// configuration otherwise names it after the store).
fn with_default_history(building: &str, store: &Path) -> Config {
    let mut cfg = config(building, store);
    let defaults = FileConfig {
        building: Some(building.into()),
        store_path: Some(store.to_owned()),
        ..FileConfig::default()
    }
    .into_config()
    .expect("defaults are valid");
    cfg.history = defaults.history;
    cfg
}

/// Batches `0..n` of `sensor` of `building`, through a node that does not drop them.
async fn stream(session: &zenoh::Session, building: &str, sensor: &str, n: u64) {
    let publisher = blocking_publisher(session, key_raw(building, sensor)).await;
    for seq in 0..n {
        publisher
            .put(raw(sensor, seq, vec![[0.01, -0.02, 0.98]; 10]))
            .await
            .expect("put");
    }
    wait_until_async(
        &format!("{building}/{sensor}: {n} batches kept"),
        || async {
            count(session, building, sensor)
                .await
                .is_ok_and(|k| k as u64 == n)
        },
    )
    .await;
}

async fn count(
    session: &zenoh::Session,
    building: &str,
    sensor: &str,
) -> Result<usize, triax_client::ClientError> {
    let request = HistoryRequest::sensor(
        &BuildingId::new(building).unwrap(),
        &SensorId::new(sensor).unwrap(),
    );
    fetch(session, &request, TIMEOUT, &mut |_| {}).await
}

/// Batches of `sensor` the history of `building` answers with.
async fn kept(session: &zenoh::Session, building: &str, sensor: &str) -> usize {
    count(session, building, sensor)
        .await
        .expect("history query answered")
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn buildings_whose_stores_share_a_folder_keep_separate_histories() {
    let dir = tempfile::tempdir().unwrap();
    let (store_xb, store_zz) = (dir.path().join("xb-store"), dir.path().join("zz-store"));
    let cfg_xb = with_default_history("xb", &store_xb);
    let cfg_zz = with_default_history("zz", &store_zz);
    let path_of = |c: &Config| c.history.as_ref().expect("history on").path.clone();
    let (history_xb, history_zz) = (path_of(&cfg_xb), path_of(&cfg_zz));
    assert_ne!(history_xb, history_zz, "the default paths differ");

    // `xb` keeps a stream and stops; then `zz` starts beside it, as in the issue.
    let xb = start(cfg_xb.clone()).await;
    let session = client(&xb.endpoint).await;
    stream(&session, "xb", "s1", 20).await;
    session.close().await.unwrap();
    xb.stop().await;

    let zz = start(cfg_zz.clone()).await;
    let session_zz = client(&zz.endpoint).await;
    stream(&session_zz, "zz", "s2", 5).await;
    assert_eq!(kept(&session_zz, "zz", "s2").await, 5, "zz serves its own");
    assert_eq!(
        kept(&session_zz, "zz", "s1").await,
        0,
        "zz serves none of xb's batches"
    );

    // Both at once: a shared history would refuse the second gateway as in use.
    let xb = start(cfg_xb.clone()).await;
    let session_xb = client(&xb.endpoint).await;
    assert_eq!(
        kept(&session_xb, "xb", "s1").await,
        20,
        "xb still has its own"
    );
    assert_eq!(kept(&session_xb, "xb", "s2").await, 0);
    for (path, building) in [(&history_xb, "xb"), (&history_zz, "zz")] {
        let owner = triax_history::read_owner(path)
            .expect("owner file reads")
            .expect("an owner is recorded");
        assert_eq!(owner.building.as_str(), building, "{}", path.display());
        assert_eq!(owner.gateway_name, format!("triax-gateway-{building}"));
    }
    session_zz.close().await.unwrap();
    zz.stop().await;

    // `zz` pointed at `xb`'s history explicitly, while `xb` runs on it: refused at start with
    // whose history it is, not merely that it is in use.
    let mut foreign = config("zz", &store_zz);
    foreign.history.as_mut().expect("history on").path = history_xb.clone();
    let Err(err) = Gateway::start(foreign).await else {
        panic!("a gateway for zz started on xb's history");
    };
    let message = err.to_string();
    for part in [
        history_xb.display().to_string(),
        "building xb".into(),
        "building zz".into(),
    ] {
        assert!(message.contains(&part), "{message:?} names {part:?}");
    }
    assert_eq!(
        kept(&session_xb, "xb", "s1").await,
        20,
        "the refused start touched nothing"
    );
    session_xb.close().await.unwrap();
    xb.stop().await;

    // Stopped, the same: the check does not rest on the lock.
    let mut foreign = config("zz", &store_zz);
    foreign.history.as_mut().expect("history on").path = history_xb.clone();
    let Err(err) = Gateway::start(foreign).await else {
        panic!("a gateway for zz started on xb's history");
    };
    assert!(
        matches!(
            err,
            triax_gateway::GatewayError::History(triax_history::HistoryError::Foreign { .. })
        ),
        "{err}"
    );
}
