//! `triax-modes` through a real gateway: a simulated five-storey building's six sensors stream
//! raw batches (their outputs through the records' sensitivity and offset) faster than real
//! time, stamped by the simulation's clock; the service gathers the corrected streams into a
//! 30-minute window, identifies it and publishes the modes on `triax/<building>/modes`; stopped
//! over the next window, it reads that back from the history when started again, says it is
//! late, and its tracks go on. The setup here is shared with `modes_mc`.

use std::collections::BTreeMap;
use std::path::Path;

use triax_modal::sim::{SimBuilding, SimConfig};
use triax_modal::{BuildingModel, ChainUncertainty, Direction, SsiConfig, TrackerConfig};
use triax_modes::{BuildingConfig, Config as ModesConfig};
use triax_net::{ZenohMode, ZenohSettings};
use triax_protocol::batch::{BatchHeader, RawBatch};
use triax_protocol::messages::{BuildingModes, ModalDirection};
use triax_protocol::record::{sample, CalibrationRecord};
use triax_protocol::{from_json, BuildingId, CalibrationSet, SensorId};

use crate::util::*;

/// Midnight UTC, a window boundary: the simulation's first sample.
pub(crate) const EPOCH_NS: i64 = 1_800_921_600_000_000_000;
const STANDARD_GRAVITY_MPS2: f64 = 9.806_65;
/// Samples per raw batch: 5 s at 100 Hz.
pub(crate) const BATCH: usize = 500;

/// Publishes a simulated stretch as raw batches of every sensor, interleaved, from sequence
/// `first_sequence` and sample `first_sample` of the simulation's clock, each sensor's outputs
/// made with its own `sets[i]` (its true sensitivity and offset); returns how many batches
/// each sensor sent.
pub(crate) async fn stream(
    sim: &triax_modal::Window,
    publishers: &[zenoh::pubsub::Publisher<'static>],
    sets: &[CalibrationSet],
    first_sequence: u64,
    first_sample: usize,
) -> u64 {
    assert_eq!(sets.len(), sim.sensors.len(), "one set per sensor");
    let batches = sim.len().div_ceil(BATCH);
    for b in 0..batches {
        for ((series, publisher), set) in sim.sensors.iter().zip(publishers).zip(sets) {
            let from = b * BATCH;
            let to = (from + BATCH).min(series.acceleration_mps2.len());
            let samples = series.acceleration_mps2[from..to]
                .iter()
                // The sensors' axes turn about the vertical only: gravity is on their z, where
                // the gateway's health checks expect it.
                .map(|a| {
                    let a = [a[0], a[1], a[2] + STANDARD_GRAVITY_MPS2];
                    outputs(&set.sensitivity, &set.offset, a).map(|v| v as f32)
                })
                .collect();
            let raw = RawBatch {
                header: BatchHeader {
                    sensor_id: SensorId::new(series.sensor_id.clone()).unwrap(),
                    sequence: first_sequence + b as u64,
                    timestamp_ns: EPOCH_NS + ((first_sample + from) as i64) * 10_000_000,
                    sample_rate_hz: 100.0,
                },
                temperature_c: None,
                samples,
            };
            publisher.put(raw.encode()).await.unwrap();
        }
    }
    batches as u64
}

/// A sensor's record: the sample record, its static and dynamic sets alike (whichever the
/// gateway applies), with a band up to Nyquist, so that the sensors' white noise is in band.
pub(crate) fn record_for(sensor_id: &str) -> CalibrationRecord {
    let mut r = sample::record(sensor_id, 1);
    r.dynamic.domain.frequency_max_hz = 50.0;
    r.static_set = r.dynamic.clone();
    r
}

/// A gateway of `building` on `store`. The field health checks judge the records against the
/// data; the sample record's sensor is not this simulation's (its stated noise, its gravity),
/// and a record turned suspect flags every sample after: the checks are not what these tests
/// are about.
pub(crate) fn gateway_config(building: &str, store: &Path) -> triax_gateway::Config {
    let mut c = config(building, store);
    c.health = None;
    c
}

/// The service's settings for a building of `model`: 30-minute windows, the default
/// identification and tracker, no temperature source, shapes with the measurement chain's
/// uncertainty `chain`.
pub(crate) fn building_config(model: &BuildingModel, chain: ChainUncertainty) -> BuildingConfig {
    BuildingConfig {
        model: model.clone(),
        window_s: 1800.0,
        alignment_tolerance: 0.1,
        close_after_s: 60.0,
        chain: Some(chain),
        ssi: SsiConfig::default(),
        tracker: TrackerConfig::default(),
        alert_modes_per_direction: 3,
        temperature_key: None,
        record_max_windows: 100,
    }
}

/// The service following `building` through the gateway at `endpoint`, its state in
/// `dir/modes`, its signing key at `dir/modes.key`.
pub(crate) fn service_config(
    endpoint: &str,
    building: &str,
    settings: BuildingConfig,
    dir: &Path,
) -> ModesConfig {
    let mut buildings = BTreeMap::new();
    buildings.insert(BuildingId::new(building).unwrap(), settings);
    ModesConfig {
        zenoh: ZenohSettings::loopback(ZenohMode::Peer, vec![], vec![endpoint.to_owned()]),
        buildings,
        state_dir: Some(dir.join("modes")),
        signing_key_file: Some(dir.join("modes.key")),
        gateway_keys: None,
    }
}

/// Returns once the service has subscribed to `building`'s corrected streams: it follows live
/// batches from the moment it starts.
pub(crate) async fn wait_service_listens(node: &zenoh::Session, building: &str) {
    let probe = format!("triax/{building}/corrected/probe");
    wait_until_async("the modes service subscribed", || async {
        node.declare_publisher(probe.clone())
            .await
            .unwrap()
            .matching_status()
            .await
            .unwrap()
            .matching()
    })
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_service_identifies_the_first_three_modes_of_each_direction_through_a_gateway() {
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("store");
    let building = SimBuilding::five_storey(11);
    let records: Vec<_> = building
        .model
        .sensors
        .iter()
        .map(|s| record_for(&s.sensor_id))
        .collect();
    seed_store(&store, &records);
    let gw = start(gateway_config("hm1", &store)).await;
    let node = client(&gw.endpoint).await;
    let published = node.declare_subscriber("triax/hm1/modes").await.unwrap();

    let state_dir = dir.path().join("modes");
    let modes_config = || {
        service_config(
            &gw.endpoint,
            "hm1",
            building_config(&building.model, SimConfig::default().chain),
            dir.path(),
        )
    };
    let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
    let service = tokio::spawn(triax_modes::run(modes_config(), async {
        let _ = stopped.await;
    }));

    // A window and a second more, so that every sensor passes the window's last point.
    let t = building.frame.reference_temperature_c;
    let sim = building.simulate(t, 1801.0, EPOCH_NS, 3);
    let mut publishers = Vec::new();
    for s in &building.model.sensors {
        publishers.push(blocking_publisher(&node, key_raw("hm1", &s.sensor_id)).await);
    }
    wait_service_listens(&node, "hm1").await;
    let sets: Vec<_> = records.iter().map(|r| r.dynamic.clone()).collect();
    let first_batches = stream(&sim, &publishers, &sets, 0, 0).await;
    let sample = tokio::time::timeout(TIMEOUT, published.recv_async())
        .await
        .expect("the window's modes are published")
        .unwrap();
    let modes: BuildingModes = from_json(&sample.payload().to_bytes()).unwrap();
    assert!(
        modes.refused.is_none(),
        "{:?}: {:?}",
        modes.refused,
        modes.sensors
    );
    assert_eq!(modes.window_start_ns, EPOCH_NS);
    assert_eq!(modes.sensors.len(), 6);
    for c in &modes.sensors {
        assert_eq!(c.samples, 180_000, "{c:?}");
        assert_eq!(c.flagged + c.missing + c.misaligned, 0, "{c:?}");
        assert_eq!(c.calibration_versions, vec![1]);
    }
    // The same window identified directly, off the wire: the gateway's correction gives back
    // the simulated accelerations to f32 precision, so the service's frequencies are those.
    let direct = triax_modal::identify(&building.model, &sim, &SsiConfig::default()).unwrap();
    for direction in [Direction::X, Direction::Y] {
        let d = if direction == Direction::X {
            ModalDirection::X
        } else {
            ModalDirection::Y
        };
        for truth in building.frame.direction_modes(direction, t).iter().take(3) {
            let nearest = |fs: &mut dyn Iterator<Item = (f64, f64)>| {
                fs.min_by(|a, b| {
                    (a.0 - truth.frequency_hz)
                        .abs()
                        .total_cmp(&(b.0 - truth.frequency_hz).abs())
                })
            };
            let (f, band) = nearest(&mut modes.modes.iter().filter(|m| m.direction == d).map(
                |m| {
                    (
                        m.frequency_hz.value,
                        m.frequency_hz.coverage_factor * m.frequency_hz.standard_uncertainty,
                    )
                },
            ))
            .unwrap_or_else(|| panic!("{direction:?} mode {} not published", truth.number));
            let error = (f - truth.frequency_hz).abs();
            assert!(
                error <= 0.005 * truth.frequency_hz && error <= band,
                "{direction:?} {}: {f} ± {band} Hz against {}",
                truth.number,
                truth.frequency_hz
            );
            let (g, _) = nearest(
                &mut direct
                    .modes
                    .iter()
                    .filter(|m| m.direction == direction)
                    .map(|m| (m.frequency_hz.value, 0.0)),
            )
            .unwrap();
            assert!(
                (f - g).abs() <= 1e-4 * g,
                "through the gateway {f}, direct {g}"
            );
        }
    }
    // Kept: one line in the record, and where to resume.
    let record = triax_modes::record::read(&state_dir.join("hm1")).unwrap();
    assert_eq!(record.len(), 1);
    assert_eq!(record[0].window_start_ns, EPOCH_NS);
    assert!(state_dir.join("hm1").join("state.json").exists());
    stop.send(()).unwrap();
    service.await.unwrap().unwrap();

    // Stopped, the service misses the next window whole and two minutes more; started again,
    // it reads them back from the history from where it left off, one sensor's stretch after
    // another's (the first runs minutes past the window's end before the others arrive: the
    // window waits for them), identifies it late, and its tracks go on.
    let next = building.simulate(t, 1920.0, EPOCH_NS + 1_801_000_000_000, 4);
    let last = first_batches + stream(&next, &publishers, &sets, first_batches, 180_100).await - 1;
    for s in &building.model.sensors {
        wait_history_holds(&node, "hm1", &s.sensor_id, last).await;
    }
    let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
    let service = tokio::spawn(triax_modes::run(modes_config(), async {
        let _ = stopped.await;
    }));
    let sample = tokio::time::timeout(TIMEOUT, published.recv_async())
        .await
        .expect("the missed window's modes are published")
        .unwrap();
    let again: BuildingModes = from_json(&sample.payload().to_bytes()).unwrap();
    assert_eq!(again.window_start_ns, EPOCH_NS + 1_800_000_000_000);
    assert!(again.late, "read back from the history");
    assert!(
        again.refused.is_none(),
        "{:?}: {:?}",
        again.refused,
        again.sensors
    );
    for c in &again.sensors {
        assert_eq!(c.flagged + c.missing + c.misaligned, 0, "{c:?}");
    }
    let fundamental = |m: &BuildingModes| {
        m.modes
            .iter()
            .find(|x| x.direction == ModalDirection::X)
            .and_then(|x| x.track)
    };
    assert_eq!(
        fundamental(&again),
        fundamental(&modes),
        "the x fundamental's track goes on"
    );
    assert_eq!(
        triax_modes::record::read(&state_dir.join("hm1"))
            .unwrap()
            .len(),
        2
    );
    stop.send(()).unwrap();
    service.await.unwrap().unwrap();
    node.close().await.unwrap();
    gw.stop().await;
}
