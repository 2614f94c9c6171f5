//! The console's modes view: a building's windows from `triax/<building>/modes` (PROTOCOL.md
//! §3.10) over HTTP (`/api/modes`) and in headless Chromium (`#/modes/<building>`): the
//! frequency trend of each track with its band, the latest window's modes and shapes.
//! Screenshots go to `target/console-screenshots/`.

mod site;

use serde_json::Value;
use site::*;
use time::OffsetDateTime;
use triax_protocol::messages::{
    BuildingModes, ModalDirection, ModalEstimate, ModalVerdict, ModeReport, ModeShapeComponent,
};
use triax_protocol::provenance::sign_message;
use triax_protocol::{to_json, BuildingId, SensorId};
use zenoh::qos::CongestionControl;

const WINDOW_NS: i64 = 1_800_000_000_000;

fn estimate(value: f64, u: f64) -> ModalEstimate {
    ModalEstimate {
        value,
        standard_uncertainty: u,
        dof: 11.0,
        coverage_factor: 2.201,
        coverage_probability: 0.95,
    }
}

/// A mode of track `track` at `frequency_hz`, its shape on two sensors in x and y.
fn mode(
    track: u64,
    direction: ModalDirection,
    frequency_hz: f64,
    verdict: ModalVerdict,
) -> ModeReport {
    let along = |d: ModalDirection, own: f64| if d == direction { own } else { 0.05 };
    let component = |sensor: &str, d: ModalDirection, v: f64| ModeShapeComponent {
        sensor_id: SensorId::new(sensor).unwrap(),
        direction: d,
        real: estimate(v, 0.02),
        imag: estimate(0.0, 0.01),
        calibration_suspect: false,
    };
    ModeReport {
        track: Some(track),
        direction,
        frequency_hz: estimate(frequency_hz, 0.0015),
        damping_ratio: estimate(0.02, 0.002),
        shape: vec![
            component("acc-01", ModalDirection::X, along(ModalDirection::X, 0.6)),
            component("acc-01", ModalDirection::Y, along(ModalDirection::Y, 0.6)),
            component("acc-02", ModalDirection::X, along(ModalDirection::X, 1.0)),
            component("acc-02", ModalDirection::Y, along(ModalDirection::Y, 1.0)),
        ],
        reference_component: if direction == ModalDirection::X { 2 } else { 3 },
        pooled_shape: None,
        order: 24,
        stable_orders: 12,
        replicates: 12,
        predicted_hz: Some(frequency_hz + 0.0005),
        residual_relative: Some(estimate(-0.0005, 0.001)),
        verdict: Some(verdict),
        block_mean_relative: None,
        block_verdict: None,
        normal_coverage_factor: None,
        cusum: None,
    }
}

fn window(building: &str, index: i64, t0_ns: i64, refused: bool) -> BuildingModes {
    let start = t0_ns + index * WINDOW_NS;
    // The last identified window drops track 0 by 2 %: a shift.
    let (f0, v0) = if index == 5 {
        (0.98, ModalVerdict::Shift)
    } else {
        (1.0 + 0.001 * index as f64, ModalVerdict::Normal)
    };
    BuildingModes {
        format_version: triax_protocol::JSON_FORMAT_VERSION,
        building: BuildingId::new(building).unwrap(),
        window_start_ns: start,
        window_end_ns: start + WINDOW_NS,
        sample_rate_hz: 100.0,
        identification_rate_hz: if refused { 0.0 } else { 25.0 },
        sensors: Vec::new(),
        temperature_c: Some(12.0 + index as f64),
        regressors: vec![12.0 + index as f64],
        tracked: !refused,
        modes: if refused {
            Vec::new()
        } else {
            vec![
                mode(0, ModalDirection::X, f0, v0),
                mode(1, ModalDirection::Y, 1.015, ModalVerdict::Normal),
            ]
        },
        unquantified: Vec::new(),
        refused: refused
            .then(|| "sensor acc-02, direction x: only 41.0 % of the window is usable".into()),
        warnings: Vec::new(),
        late: false,
        identified_at: OffsetDateTime::UNIX_EPOCH,
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn modes_trend_and_shapes_over_http_and_in_a_browser() {
    let site = Site::start(60).await;
    let console = Console::start(&site, None).await;
    let t0_ns = (now_ns() - 8 * WINDOW_NS) / WINDOW_NS * WINDOW_NS;
    let put = |m: BuildingModes| {
        let session = site.session.clone();
        async move {
            // As the modes service publishes: signed with its alerting key, and a full link
            // waits rather than drops.
            let payload = to_json(&m);
            let signed = sign_message(&service_key(), "triax/hq/modes", "", now_ns(), &payload);
            session
                .put("triax/hq/modes", payload)
                .attachment(signed.to_vec())
                .congestion_control(CongestionControl::Block)
                .await
                .unwrap()
        }
    };
    // The first window until the console has it: its subscription is then in place. The same
    // window again replaces itself.
    let deadline = tokio::time::Instant::now() + TIMEOUT;
    loop {
        put(window("hq", 0, t0_ns, false)).await;
        if console.json("/api/modes?building=hq").await["windows"] == 1 {
            break;
        }
        assert!(
            tokio::time::Instant::now() < deadline,
            "no modes reached the console"
        );
        tokio::time::sleep(std::time::Duration::from_millis(100)).await;
    }
    // Out of order, a refused window last, and one whose key names another building.
    for i in [2, 1, 3, 4, 5] {
        put(window("hq", i, t0_ns, false)).await;
    }
    put(window("hq", 6, t0_ns, true)).await;
    put(window("b2", 7, t0_ns, false)).await;
    // And one a peer put, unsigned: dropped as unverified.
    site.session
        .put("triax/hq/modes", to_json(&window("hq", 8, t0_ns, false)))
        .congestion_control(CongestionControl::Block)
        .await
        .unwrap();
    let v = console
        .wait_json(
            "seven windows and the malformed one",
            "/api/modes?building=hq",
            |v| v["windows"] == 7 && v["malformed"] == 1 && v["unverified"] == 1,
        )
        .await;
    let tracks = v["tracks"].as_array().unwrap();
    assert_eq!(tracks.len(), 2, "{v}");
    assert_eq!(tracks[0]["direction"], "x");
    let points = tracks[0]["points"].as_array().unwrap();
    assert_eq!(points.len(), 6, "one per identified window");
    let starts: Vec<i64> = points
        .iter()
        .map(|p| p["start_ns"].as_i64().unwrap())
        .collect();
    assert!(
        starts.windows(2).all(|w| w[0] < w[1]),
        "in time order: {starts:?}"
    );
    assert_eq!(points[1]["frequency_hz"], 1.001);
    assert!((points[1]["expanded_hz"].as_f64().unwrap() - 2.201 * 0.0015).abs() < 1e-15);
    assert_eq!(points[5]["verdict"], "shift");
    assert_eq!(
        v["latest"]["start_ns"],
        t0_ns + 5 * WINDOW_NS,
        "the latest identified window"
    );
    assert_eq!(
        v["latest"]["modes"][0]["shape"].as_array().unwrap().len(),
        4
    );
    assert_eq!(v["latest"]["modes"][0]["shape"][2]["real"], 1.0);
    assert_eq!(v["refused_since_latest"], 1);
    assert!(v["last_refusal"]["reason"]
        .as_str()
        .unwrap()
        .contains("acc-02"));
    let (status, body) = console.get("/api/modes").await;
    assert_eq!(status, 400, "{body}");
    assert_eq!(
        console.json("/api/modes?building=elsewhere").await["windows"],
        0
    );

    let browser = Browser::start(false);
    browser.go(&format!("{}#/modes/hq", console.url()));
    browser
        .wait(
            "two trends and two shapes drawn",
            "return document.querySelectorAll('canvas.mode-trend[data-drawn]').length === 2 && document.querySelectorAll('canvas.mode-shape[data-drawn]').length === 2",
        )
        .await;
    let drawn: Value = browser.js("return [...document.querySelectorAll('canvas.mode-trend')].map((c) => [c.dataset.points, c.dataset.shifts]).concat([...document.querySelectorAll('canvas.mode-shape')].map((c) => [c.dataset.components, null]))");
    assert_eq!(
        drawn,
        serde_json::json!([["6", "1"], ["6", "0"], ["4", null], ["4", null]]),
        "six windows per track, the shift marked, four components per shape"
    );
    let table = browser.js(
        "return [...document.querySelectorAll('#modes-table tbody tr')].map((r) => r.textContent)",
    );
    assert!(table[0].as_str().unwrap().contains("0.9800"), "{table}");
    assert!(table[0].as_str().unwrap().contains("shift"), "{table}");
    let status = browser.js("return document.getElementById('modes-status').textContent");
    assert!(
        status.as_str().unwrap().contains("7 windows heard"),
        "{status}"
    );
    assert!(status.as_str().unwrap().contains("1 refused"), "{status}");
    browser.screenshot("modes");
    // A building with none says so.
    browser.go(&format!("{}#/modes/elsewhere", console.url()));
    browser
        .wait(
            "the empty view",
            "return document.getElementById('modes-status').dataset.windows === '0'",
        )
        .await;
    browser.assert_no_errors("the modes view");
    drop(browser);
    console.stop().await;
}
