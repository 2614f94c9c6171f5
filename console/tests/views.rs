//! The console against a site of generated sensors, over HTTP and in headless Chromium
//! (issue 26, items 5 to 9). Screenshots go to `target/console-screenshots/`.
//!
//! - `alert_log_survives_a_restart`: the alert log is kept in `--state-dir`, read back and
//!   verified again after a restart; filtered by building, sensor, kind, level, state and time;
//!   acknowledgements and silences record who and when; writes are POST only, from the
//!   console's own origin, as JSON, within 16 KiB, and a bad field is named.
//! - `alert_table_in_a_browser`: rows are updated in place (a row, its open statement and a
//!   ticked box survive new alerts), statements are one line with details on demand, and an
//!   operator acknowledges from the page.

mod site;

use serde_json::{json, Value};
use site::*;

fn ids(v: &Value) -> Vec<u64> {
    v["alerts"]
        .as_array()
        .unwrap()
        .iter()
        .map(|a| a["id"].as_u64().unwrap())
        .collect()
}

/// Puts an alert on acc-03 until the console lists one: its subscription is then in place.
async fn until_alerts_arrive(site: &Site, console: &Console) {
    let since = now_ns();
    let deadline = tokio::time::Instant::now() + TIMEOUT;
    loop {
        site.alert("acc-03", "possible", "warm-up", (1, 2), true)
            .await;
        let v = console
            .json(&format!("/api/alerts?sensor=acc-03&from_ns={since}"))
            .await;
        if v["matched"].as_u64() > Some(0) {
            return;
        }
        assert!(
            tokio::time::Instant::now() < deadline,
            "no alert reached the console"
        );
        tokio::time::sleep(std::time::Duration::from_millis(100)).await;
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn alert_log_survives_a_restart() {
    let site = Site::start(60).await;
    let dir = tempfile::tempdir().unwrap();
    let console = Console::start(&site, Some(dir.path().to_owned())).await;
    until_alerts_arrive(&site, &console).await;
    site.alert(
        "acc-01",
        "exceeded",
        "first line\nsecond line",
        (10, 20),
        true,
    )
    .await;
    site.alert("acc-02", "possible", "possible", (10, 20), true)
        .await;
    site.alert("acc-01", "exceeded", "forged", (10, 20), false)
        .await;
    console
        .wait_json("acc-02's alert", "/api/alerts?sensor=acc-02", |v| {
            v["matched"] == 1
        })
        .await;
    let all = console
        .wait_json("acc-01's two alerts", "/api/alerts?sensor=acc-01", |v| {
            v["matched"] == 2
        })
        .await;
    assert!(
        all["file"].as_str().unwrap().ends_with("alerts.jsonl"),
        "{all}"
    );

    // Filters.
    let q = |p: &str| {
        let path = format!("/api/alerts?{p}");
        let c = &console;
        async move { c.json(&path).await }
    };
    let acc01 = q("building=hq&sensor=acc-01").await;
    assert_eq!(acc01["matched"], 2, "{acc01}");
    let exceeded = q("level=exceeded").await;
    assert_eq!(exceeded["matched"], 1, "only the verified one: {exceeded}");
    assert_eq!(
        exceeded["alerts"][0]["statement"],
        "first line\nsecond line"
    );
    let exceeded_id = exceeded["alerts"][0]["id"].as_u64().unwrap();
    let unverified = q("level=unverified").await;
    assert_eq!(unverified["matched"], 1, "{unverified}");
    assert_eq!(unverified["alerts"][0]["trust"], "unsigned");
    assert_eq!(q("kind=tilt_change").await["matched"], 0);
    assert_eq!(q("building=annex").await["matched"], 0);
    let future = now_ns() + 3_600_000_000_000;
    assert_eq!(q(&format!("from_ns={future}")).await["matched"], 0);
    assert!(
        q(&format!("to_ns={future}&limit=1")).await["alerts"]
            .as_array()
            .unwrap()
            .len()
            == 1
    );
    for (p, names) in [
        ("level=panic", "\"level\""),
        ("kind=shake", "\"kind\""),
        ("state=closed", "\"state\""),
        ("limit=0", "\"limit\""),
        ("from_ns=soon", "\"from_ns\""),
        ("colour=red", "\"colour\""),
    ] {
        let (status, body) = console.get(&format!("/api/alerts?{p}")).await;
        assert_eq!(status, 400, "{p}: {body}");
        assert!(body.contains(names), "{p}: {body}");
    }

    // Acknowledge, with who and when.
    let (status, body) = console
        .post(
            "/api/alerts/ack",
            &json!({"ids": [exceeded_id], "by": "alice", "note": "checked on site"}),
        )
        .await;
    assert_eq!(status, 200, "{body}");
    let answer: Value = serde_json::from_str(&body).unwrap();
    assert_eq!(answer["acknowledged"], json!([exceeded_id]));
    let (_, again) = console
        .post("/api/alerts/ack", &json!({"ids": exceeded_id, "by": "bob"}))
        .await;
    assert!(
        again.contains("\"already_acknowledged\":[") && again.contains(&exceeded_id.to_string()),
        "{again}"
    );
    let acked = q("state=acknowledged").await;
    assert_eq!(ids(&acked), [exceeded_id]);
    assert_eq!(
        acked["alerts"][0]["ack"]["by"], "alice",
        "the first acknowledgement stands"
    );
    assert_eq!(acked["alerts"][0]["ack"]["note"], "checked on site");
    assert!(acked["alerts"][0]["ack"]["at"]
        .as_str()
        .unwrap()
        .starts_with("20"));
    assert!(!ids(&q("state=open").await).contains(&exceeded_id));

    // Silence acc-02's peak alerts: a new one arrives silenced.
    let (status, body) = console
        .post("/api/alerts/silence", &json!({"building": "hq", "sensor": "acc-02", "kind": "peak_acceleration", "duration_s": 3600, "by": "bob", "reason": "works on floor 3"}))
        .await;
    assert_eq!(status, 200, "{body}");
    let silence: Value = serde_json::from_str(&body).unwrap();
    let silence_id = silence["id"].as_u64().unwrap();
    site.alert("acc-02", "exceeded", "during the works", (30, 40), true)
        .await;
    let silenced = console
        .wait_json("a silenced alert", "/api/alerts?state=silenced", |v| {
            v["matched"] == 1
        })
        .await;
    assert_eq!(silenced["alerts"][0]["silenced_by"], silence_id);
    assert_eq!(
        silenced["alerts"][0]["level"], "exceeded",
        "the verdict stands"
    );
    let silences = console.json("/api/silences").await;
    assert_eq!(silences[0]["by"], "bob");
    assert_eq!(silences[0]["active"], true);

    // Writes: POST only, on these routes only, from this origin, as JSON, bounded, and a bad
    // field named.
    let a = console.addr;
    let (status, _) = console.get("/api/alerts/ack").await;
    assert_eq!(status, 405);
    let (status, _) = console.post("/api/fleet", &json!({})).await;
    assert_eq!(status, 405);
    for (body, field) in [
        (json!({"ids": [exceeded_id]}), "\"by\""),
        (json!({"ids": [999_999], "by": "alice"}), "\"ids\""),
        (json!({"ids": "all", "by": "alice"}), "\"ids\""),
        (
            json!({"ids": [exceeded_id], "by": "alice", "colour": 1}),
            "\"colour\"",
        ),
        (
            json!({"ids": [exceeded_id], "by": "x".repeat(65)}),
            "\"by\"",
        ),
    ] {
        let (status, text) = console.post("/api/alerts/ack", &body).await;
        assert_eq!(status, 400, "{body}: {text}");
        assert!(text.contains(field), "{body}: {text}");
    }
    for (body, field) in [
        (
            json!({"building": "hq", "duration_s": 0, "by": "b"}),
            "\"duration_s\"",
        ),
        (
            json!({"building": "hq", "duration_s": 1e9, "by": "b"}),
            "\"duration_s\"",
        ),
        (
            json!({"building": "hq", "kind": "shake", "duration_s": 60, "by": "b"}),
            "\"kind\"",
        ),
        (
            json!({"building": "h/q", "duration_s": 60, "by": "b"}),
            "\"building\"",
        ),
    ] {
        let (status, text) = console.post("/api/alerts/silence", &body).await;
        assert_eq!(status, 400, "{body}: {text}");
        assert!(text.contains(field), "{body}: {text}");
    }
    let body = r#"{"ids":[1],"by":"eve"}"#;
    let foreign = format!(
        "POST /api/alerts/ack HTTP/1.1\r\nHost: {a}\r\nOrigin: http://evil.example\r\nContent-Type: application/json\r\nContent-Length: {}\r\n\r\n{body}",
        body.len()
    );
    assert_eq!(console.request(&foreign).await.0, 403);
    let form = format!(
        "POST /api/alerts/ack HTTP/1.1\r\nHost: {a}\r\nContent-Type: application/x-www-form-urlencoded\r\nContent-Length: {}\r\n\r\n{body}",
        body.len()
    );
    assert_eq!(console.request(&form).await.0, 415);
    let big = format!(
        "POST /api/alerts/ack HTTP/1.1\r\nHost: {a}\r\nContent-Type: application/json\r\nContent-Length: 20000\r\n\r\n"
    );
    assert_eq!(console.request(&big).await.0, 413);
    let broken = format!(
        "POST /api/alerts/ack HTTP/1.1\r\nHost: {a}\r\nContent-Type: application/json\r\nContent-Length: 5\r\n\r\n{{\"ids"
    );
    let (status, text) = console.request(&broken).await;
    assert_eq!(status, 400, "{text}");
    assert!(text.contains("not JSON"), "{text}");

    // A restart: the same alerts, ids, acknowledgement and silence, each alert verified again.
    let kept = console.json("/api/alerts").await;
    console.stop().await;
    // A torn last line, as a crash mid-write leaves, is skipped.
    use std::io::Write;
    std::fs::OpenOptions::new()
        .append(true)
        .open(dir.path().join("alerts.jsonl"))
        .unwrap()
        .write_all(b"{\"alert\":{\"id\":")
        .unwrap();
    let console = Console::start(&site, Some(dir.path().to_owned())).await;
    let after = console.json("/api/alerts").await;
    assert_eq!(ids(&after), ids(&kept));
    assert_eq!(after["kept"], kept["kept"]);
    let acked = console.json("/api/alerts?state=acknowledged").await;
    assert_eq!(acked["alerts"][0]["ack"]["by"], "alice");
    assert_eq!(
        console.json("/api/alerts?level=unverified").await["matched"],
        1
    );
    assert_eq!(
        console.json("/api/alerts?state=silenced").await["matched"],
        1
    );
    assert_eq!(console.json("/api/silences").await[0]["id"], silence_id);
    let (status, body) = console
        .post("/api/alerts/lift", &json!({"id": silence_id, "by": "bob"}))
        .await;
    assert_eq!(status, 200, "{body}");
    assert_eq!(console.json("/api/silences").await[0]["active"], false);
    // New alerts continue the numbering.
    until_alerts_arrive(&site, &console).await;
    let newest = console.json("/api/alerts?limit=1").await;
    assert!(newest["alerts"][0]["id"].as_u64().unwrap() > *ids(&kept).iter().max().unwrap());
    console.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn alert_table_in_a_browser() {
    let site = Site::start(60).await;
    let console = Console::start(&site, None).await;
    until_alerts_arrive(&site, &console).await;
    site.alert(
        "acc-01",
        "exceeded",
        "Exceeded at 95 %.\nThe interval lies above the threshold.",
        (10, 20),
        true,
    )
    .await;
    console
        .wait_json("acc-01's alert", "/api/alerts?sensor=acc-01", |v| {
            v["matched"] == 1
        })
        .await;
    let browser = Browser::start(false);
    browser.go(&format!("{}#/alerts", console.url()));
    let n: u64 = browser
        .wait("the alert rows", "return document.querySelectorAll('#alert-rows tr').length >= 2 && document.querySelectorAll('#alert-rows tr').length")
        .await
        .as_u64()
        .unwrap();
    // The statement is one line, its details on demand.
    let summary = browser.js("const r = document.querySelector('#alert-rows tr[data-sensor=\"acc-01\"]'); return [r.querySelector('summary').textContent, r.querySelector('details .full').textContent, r.querySelector('summary').getBoundingClientRect().height]");
    assert_eq!(summary[0], "Exceeded at 95 %.");
    assert_eq!(
        summary[1],
        "Exceeded at 95 %.\nThe interval lies above the threshold."
    );
    assert!(summary[2].as_f64().unwrap() < 30.0, "{summary}");
    // Open the statement, tick the row, mark its node; then let alerts arrive.
    browser.js("const r = document.querySelector('#alert-rows tr[data-sensor=\"acc-01\"]'); r.querySelector('details').open = true; r.querySelector('input.pick').checked = true; r.__kept = 'same node'; return 1");
    site.alert("acc-02", "possible", "a new one", (10, 20), true)
        .await;
    browser
        .wait(
            "a new row",
            &format!("return document.querySelectorAll('#alert-rows tr').length > {n}"),
        )
        .await;
    let kept = browser.js("const r = document.querySelector('#alert-rows tr[data-sensor=\"acc-01\"]'); return [r.__kept || null, r.querySelector('details').open, r.querySelector('input.pick').checked]");
    assert_eq!(
        kept,
        json!(["same node", true, true]),
        "the row was rebuilt under the cursor"
    );
    assert_eq!(
        browser.js("return document.querySelector('#alert-rows tr').dataset.sensor"),
        "acc-02",
        "newest first"
    );
    // Filters come from the URL and are applied by the server.
    browser.go(&format!(
        "{}#/alerts?sensor=acc-01&level=exceeded",
        console.url()
    ));
    browser
        .wait("the filtered table", "return document.querySelectorAll('#alert-rows tr').length === 1 && document.getElementById('f-level').value === 'exceeded'")
        .await;
    // Acknowledge without a name: refused on the page; with one: recorded.
    browser.js("document.querySelector('#alert-rows button.ack').click(); return 1");
    browser
        .wait(
            "the name asked for",
            "return document.getElementById('alerts-status').textContent.includes('operator')",
        )
        .await;
    browser.js("const i = document.getElementById('operator'); i.value = 'alice'; i.dispatchEvent(new Event('change')); document.querySelector('#alert-rows button.ack').click(); return 1");
    let handled = browser
        .wait("the acknowledgement", "const t = document.querySelector('#alert-rows td.handled').textContent; return t.includes('acknowledged') && t")
        .await;
    assert!(handled.as_str().unwrap().contains("by alice"), "{handled}");
    browser.screenshot("alerts-log");
    let acked = console.json("/api/alerts?state=acknowledged").await;
    assert_eq!(acked["alerts"][0]["ack"]["by"], "alice");
    browser.assert_no_errors("the alert table");
    drop(browser);
    console.stop().await;
}
