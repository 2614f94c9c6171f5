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
//! - `spectrogram_and_miniseed_over_http`: a spectrogram finds the sway's frequency in every
//!   column; the miniSEED export of a view is read by ObsPy with the CSV export's values.

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
    let operators = dir.path().join("operators");
    write_operators(
        &operators,
        &[
            ("alice", "operate"),
            ("bob", "operate"),
            ("viewer", "view"),
            ("root", "admin"),
        ],
    );
    let with_accounts = |o: &mut triax_console::ConsoleOptions| {
        o.operators_file = Some(operators.clone());
    };
    let console = Console::start_with(&site, Some(dir.path().to_owned()), with_accounts).await;
    // With accounts, nothing but the page and who one is before a login.
    let (status, body) = console.get("/api/alerts").await;
    assert_eq!(status, 401, "{body}");
    assert!(body.contains("logged-in operator"), "{body}");
    assert_eq!(console.get("/events").await.0, 401);
    assert_eq!(console.get("/app.js").await.0, 200);
    let me = console.json("/api/me").await;
    assert_eq!(me["operator"], Value::Null, "{me}");
    assert_eq!(me["login_required"], true, "{me}");
    let (status, body) = console
        .post(
            "/api/login",
            &json!({"name": "alice", "password": "not the password"}),
        )
        .await;
    assert_eq!(status, 401, "{body}");
    let (status, _) = console
        .post(
            "/api/login",
            &json!({"name": "mallory", "password": PASSWORD}),
        )
        .await;
    assert_eq!(status, 401, "an unknown operator");
    console.login("viewer").await;
    assert_eq!(console.json("/api/me").await["operator"]["role"], "view");
    let (_, page) = console.get("/").await;
    assert!(
        page.contains(r#"<meta name="triax-me" content="{&quot;accounts&quot;:true,"#)
            && page.contains("&quot;name&quot;:&quot;viewer&quot;"),
        "the page knows who it is for: {page}"
    );
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

    // A viewer sees, but does not acknowledge; an admin's health-latch clearing is not there yet.
    let (status, body) = console
        .post("/api/alerts/ack", &json!({"ids": [exceeded_id]}))
        .await;
    assert_eq!(status, 403, "{body}");
    assert!(
        body.contains("\"viewer\" has the role view") && body.contains("needs operate"),
        "{body}"
    );
    console.login("root").await;
    let (status, body) = console
        .post(
            "/api/health/clear",
            &json!({"building": "hq", "sensor": "acc-01"}),
        )
        .await;
    assert_eq!(status, 501, "{body}");
    assert!(body.contains("not available yet"), "{body}");
    console.login("alice").await;
    let (status, body) = console
        .post(
            "/api/health/clear",
            &json!({"building": "hq", "sensor": "acc-01"}),
        )
        .await;
    assert_eq!(status, 403, "an operator is no admin: {body}");
    // The free-text name is gone: who is the operator logged in.
    let (status, body) = console
        .post(
            "/api/alerts/ack",
            &json!({"ids": [exceeded_id], "by": "mallory"}),
        )
        .await;
    assert_eq!(status, 400, "{body}");
    assert!(body.contains("unknown field \"by\""), "{body}");

    // Acknowledge, with who and when.
    let (status, body) = console
        .post(
            "/api/alerts/ack",
            &json!({"ids": [exceeded_id], "note": "checked on site"}),
        )
        .await;
    assert_eq!(status, 200, "{body}");
    let answer: Value = serde_json::from_str(&body).unwrap();
    assert_eq!(answer["acknowledged"], json!([exceeded_id]));
    console.login("bob").await;
    let (_, again) = console
        .post("/api/alerts/ack", &json!({"ids": exceeded_id}))
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
        .post("/api/alerts/silence", &json!({"building": "hq", "sensor": "acc-02", "kind": "peak_acceleration", "duration_s": 3600, "reason": "works on floor 3"}))
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
        (json!({"note": "x"}), "\"ids\" is required"),
        (json!({"ids": [999_999]}), "\"ids\""),
        (json!({"ids": "all"}), "\"ids\""),
        (json!({"ids": [exceeded_id], "colour": 1}), "\"colour\""),
        (
            json!({"ids": [exceeded_id], "note": "x".repeat(1001)}),
            "\"note\"",
        ),
    ] {
        let (status, text) = console.post("/api/alerts/ack", &body).await;
        assert_eq!(status, 400, "{body}: {text}");
        assert!(text.contains(field), "{body}: {text}");
    }
    for (body, field) in [
        (json!({"building": "hq", "duration_s": 0}), "\"duration_s\""),
        (
            json!({"building": "hq", "duration_s": 1e9}),
            "\"duration_s\"",
        ),
        (
            json!({"building": "hq", "kind": "shake", "duration_s": 60}),
            "\"kind\"",
        ),
        (json!({"building": "h/q", "duration_s": 60}), "\"building\""),
    ] {
        let (status, text) = console.post("/api/alerts/silence", &body).await;
        assert_eq!(status, 400, "{body}: {text}");
        assert!(text.contains(field), "{body}: {text}");
    }
    let body = r#"{"ids":[1]}"#;
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
    let console = Console::start_with(&site, Some(dir.path().to_owned()), with_accounts).await;
    assert_eq!(
        console.get("/api/alerts").await.0,
        401,
        "sessions end with the console"
    );
    console.login("bob").await;
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
        .post("/api/alerts/lift", &json!({"id": silence_id}))
        .await;
    assert_eq!(status, 200, "{body}");
    let lifted = console.json("/api/silences").await;
    assert_eq!(lifted[0]["active"], false);
    assert_eq!(lifted[0]["lifted"]["by"], "bob", "{lifted}");
    // Logged out: the cookie is cleared and the session ends.
    let (status, _) = console.post("/api/logout", &json!({})).await;
    assert_eq!(status, 200);
    assert_eq!(console.get("/api/alerts").await.0, 401);
    console.login("bob").await;
    // New alerts continue the numbering.
    until_alerts_arrive(&site, &console).await;
    let newest = console.json("/api/alerts?limit=1").await;
    assert!(newest["alerts"][0]["id"].as_u64().unwrap() > *ids(&kept).iter().max().unwrap());
    console.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn alert_table_in_a_browser() {
    let site = Site::start(60).await;
    let dir = tempfile::tempdir().unwrap();
    let operators = dir.path().join("operators");
    write_operators(&operators, &[("alice", "operate")]);
    let console = Console::start_with(&site, None, |o| {
        o.operators_file = Some(operators.clone());
        o.time_zone = Some(triax_console::SiteTimeZone::get("Europe/Zurich").unwrap());
    })
    .await;
    console.login("alice").await;
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
    // Accounts exist: the page asks for a login before it shows anything.
    browser.go(&format!("{}#/alerts", console.url()));
    browser
        .wait(
            "the login form",
            "return location.hash === '#/login' && document.getElementById('login-name')",
        )
        .await;
    browser.js("document.getElementById('login-name').value = 'alice'; document.getElementById('login-password').value = 'wrong password'; document.getElementById('login-go').click(); return 1");
    browser
        .wait(
            "a refused login said so",
            "return document.getElementById('login-status').textContent.includes('(401)')",
        )
        .await;
    let errors = browser.errors();
    assert!(
        errors.len() == 1 && errors[0].contains("/api/login") && errors[0].contains("401"),
        "only the refused login: {errors:?}"
    );
    browser.js(&format!("document.getElementById('login-name').value = 'alice'; document.getElementById('login-password').value = '{PASSWORD}'; document.getElementById('login-go').click(); return 1"));
    browser
        .wait(
            "the alerts view after the login",
            "return location.hash === '#/alerts' && document.getElementById('who-name') && document.getElementById('who-name').textContent === 'alice (operate)'",
        )
        .await;
    assert_eq!(
        browser.js("return document.cookie"),
        "",
        "the session cookie is HttpOnly: no script reads it"
    );
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
    // At 1 400 px the table fits: no sideways scroll to reach Acknowledge.
    let fit = browser.js("const b = document.querySelector('#alert-rows button.ack').getBoundingClientRect(); return [window.innerWidth, document.documentElement.scrollWidth, Math.round(b.right)]");
    let (inner, scroll, right) = (
        fit[0].as_i64().unwrap(),
        fit[1].as_i64().unwrap(),
        fit[2].as_i64().unwrap(),
    );
    assert!(inner >= 1300, "{fit}");
    assert!(
        scroll <= inner && right <= inner,
        "the page scrolls sideways: {fit}"
    );
    // Times in the site's local time, labelled; UTC again after.
    let utc_at = browser
        .js("return document.querySelector('#alert-rows tr td').textContent")
        .as_str()
        .unwrap()
        .to_owned();
    assert!(utc_at.ends_with('Z'), "{utc_at}");
    browser.js("const s = document.getElementById('tz'); s.value = 'site'; s.dispatchEvent(new Event('change')); return 1");
    let local_at = browser
        .wait("the site's local time", "const t = document.querySelector('#alert-rows tr td'); return t && /(CET|CEST|GMT\\+[12])$/.test(t.textContent) && t.textContent")
        .await;
    let local_at = local_at.as_str().unwrap();
    let hours = |t: &str| t[11..13].parse::<i64>().unwrap();
    assert!(
        [1, 2].contains(&(hours(local_at) - hours(&utc_at)).rem_euclid(24)),
        "{utc_at} against {local_at}"
    );
    assert!(
        browser
            .js("return document.getElementById('tz-note').textContent")
            .as_str()
            .unwrap()
            .contains("Europe/Zurich"),
        "the footer says which zone"
    );
    browser.screenshot("alerts-log-local-time");
    browser.js("const s = document.getElementById('tz'); s.value = 'utc'; s.dispatchEvent(new Event('change')); return 1");
    browser
        .wait(
            "UTC again",
            "const t = document.querySelector('#alert-rows tr td'); return t && t.textContent.endsWith('Z')",
        )
        .await;
    // Acknowledge: recorded as the operator logged in.
    browser.js("document.querySelector('#alert-rows button.ack').click(); return 1");
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

/// The id of the newest alert of `sensor`, once the console has it.
async fn newest_alert(console: &Console, sensor: &str, since_ns: i64) -> u64 {
    let v = console
        .wait_json(
            "the alert",
            &format!("/api/alerts?sensor={sensor}&from_ns={since_ns}&limit=1"),
            |v| v["matched"].as_u64() > Some(0),
        )
        .await;
    v["alerts"][0]["id"].as_u64().unwrap()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn trend_spectrum_and_csv_over_http() {
    let site = Site::start(75 * 60).await;
    let console = Console::start(&site, None).await;
    let now = now_ns();
    let q = |path: &str, from: i64, to: i64| {
        format!("{path}?building=hq&sensor=acc-01&from_ns={from}&to_ns={to}")
    };
    // Spectrum of ten minutes: the sway at 2.5 Hz on x, a band around the estimate.
    let sp = console
        .json(&q(
            "/api/spectrum",
            now - 700_000_000_000,
            now - 100_000_000_000,
        ))
        .await;
    let s = &sp["spectrum"];
    let res = s["resolution_hz"].as_f64().unwrap();
    assert!(
        (s["axes"][0]["peak_hz"].as_f64().unwrap() - SWAY_HZ).abs() <= res,
        "{}",
        s["axes"][0]["peak_hz"]
    );
    assert_eq!(s["degrees_of_freedom"], 2 * s["segments"].as_u64().unwrap());
    assert!(s["segments"].as_u64().unwrap() >= 8);
    let k = (SWAY_HZ / res).round() as usize;
    let (lo, psd, hi) = (
        s["axes"][0]["lo"][k].as_f64().unwrap(),
        s["axes"][0]["psd"][k].as_f64().unwrap(),
        s["axes"][0]["hi"][k].as_f64().unwrap(),
    );
    assert!(lo < psd && psd < hi, "{lo} {psd} {hi}");
    let (status, body) = console
        .get(
            &(q(
                "/api/spectrum",
                now - 700_000_000_000,
                now - 100_000_000_000,
            ) + "&segment=1000"),
        )
        .await;
    assert_eq!(status, 400, "{body}");
    assert!(body.contains("\"segment\""), "{body}");
    let (status, body) = console
        .get(&q("/api/spectrum", now - 7_200_000_000_000, now))
        .await;
    assert_eq!(status, 400, "more than an hour: {body}");

    // Trend of the last 70 minutes: per-minute peak, RMS and dominant frequency; the second
    // time from the cache, without reading the history again.
    let from = now - 4_200_000_000_000;
    let t = console.json(&q("/api/trend", from, now)).await;
    assert_eq!(t["error"], Value::Null, "{}", t["error"]);
    let minutes = t["minutes"].as_array().unwrap();
    assert!(
        minutes.len() >= 68,
        "{} minutes from {} batches read; the first starts {:?} s after from_ns, the last {:?} s",
        minutes.len(),
        t["batches_read"],
        minutes
            .first()
            .and_then(|m| m["start_ns"].as_i64())
            .map(|t| (t - from) / 1_000_000_000),
        minutes
            .last()
            .and_then(|m| m["start_ns"].as_i64())
            .map(|t| (t - from) / 1_000_000_000)
    );
    let m = &minutes[10];
    assert_eq!(m["samples"], 6000);
    assert!(
        (m["peak_mps2"][0].as_f64().unwrap() - SWAY_MPS2).abs() < 0.005,
        "{m}"
    );
    assert!(
        (m["rms_mps2"][0].as_f64().unwrap() - SWAY_MPS2 / 2f64.sqrt()).abs() < 0.003,
        "{m}"
    );
    assert!(
        (m["dominant_hz"].as_f64().unwrap() - SWAY_HZ).abs() < 0.05,
        "{m}"
    );
    assert!(
        (m["mean_mps2"][2].as_f64().unwrap() - 9.81).abs() < 0.01,
        "{m}"
    );
    assert!(
        t["batches_read"].as_u64().unwrap() > 8_000,
        "{}",
        t["batches_read"]
    );
    let again = console
        .json(&q("/api/trend", from, now - 120_000_000_000))
        .await;
    assert_eq!(
        again["batches_read"], 0,
        "whole minutes come from the cache"
    );
    let (status, _) = console
        .get(&q("/api/trend", now - 8 * 86_400_000_000_000, now))
        .await;
    assert_eq!(status, 400, "more than seven days");

    // CSV: every sample of ten seconds, with its uncertainty, k, flags and version.
    let (from, to) = (now - 60_000_000_000, now - 50_000_000_000);
    let (status, csv) = console.get(&q("/api/export.csv", from, to)).await;
    assert_eq!(status, 200);
    let lines: Vec<&str> = csv.lines().collect();
    assert_eq!(
        lines[0],
        "time_utc,t_ns,sequence,ax_mps2,ay_mps2,az_mps2,ux_mps2,uy_mps2,uz_mps2,k,flags,calibration_version,mode"
    );
    assert_eq!(lines.len(), 1 + 1000, "ten seconds at 100 Hz");
    let first: Vec<&str> = lines[1].split(',').collect();
    assert!(first[1].parse::<i64>().unwrap() >= from);
    assert_eq!(&first[9..], ["2", first[10], "4", "dynamic"]);
    let (status, _) = console
        .get(&q("/api/export.csv", now - 7_200_000_000_000, now))
        .await;
    assert_eq!(status, 400, "more than an hour of samples");
    console.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn time_spectra_building_and_export_in_a_browser() {
    let site = Site::start(75 * 60).await;
    let console = Console::start(&site, None).await;
    until_alerts_arrive(&site, &console).await;
    let now = now_ns();
    let window = (now - 300_000_000_000, now - 290_000_000_000);
    site.alert("acc-02", "possible", "acc-02 too", window, true)
        .await;
    site.alert("acc-01", "exceeded", "judged ten seconds", window, true)
        .await;
    let id = newest_alert(&console, "acc-01", now).await;
    newest_alert(&console, "acc-02", now).await;
    let browser = Browser::start(false);
    let url = console.url();

    // The last 15 minutes, arriving from the alert: its window shaded, its threshold drawn.
    browser.go(&format!("{url}#/sensor/hq/acc-01?last=900&alert={id}"));
    browser
        .wait("the history of the last 15 min", "const p = document.getElementById('plot'); return p.dataset.source === 'history' && Number(p.dataset.buckets) > 100")
        .await;
    browser
        .wait("the alert's window and threshold", "const c = document.getElementById('canvas-x'); return c.dataset.shade && c.dataset.threshold")
        .await;
    assert_eq!(
        browser.js("return document.querySelector('button.last.active').dataset.last"),
        "900"
    );
    // Hover: value ± k·u, flags, calibration version.
    let readout = browser.js("const c = document.getElementById('canvas-x'); const r = c.getBoundingClientRect(); c.dispatchEvent(new MouseEvent('mousemove', { clientX: r.left + r.width / 2, clientY: r.top + 50, bubbles: true })); const b = document.getElementById('readout'); return b.hidden ? null : b.innerText");
    let readout = readout.as_str().expect("a readout").to_owned();
    assert!(
        readout.contains(" ± ") && readout.contains("m/s²"),
        "{readout}"
    );
    assert!(readout.contains("calibration v4, k = 2"), "{readout}");
    assert!(readout.contains("flags"), "{readout}");
    browser.screenshot("sensor-hover-and-alert");
    // Drag to zoom: a fifth of the plot becomes the view.
    let drag = |from: f64, to: f64, shift: bool| {
        format!("const c = document.getElementById('canvas-x'); const r = c.getBoundingClientRect(); const m = c._map; const x = (f) => r.left + m.left + f * m.pw; const ev = (t, f) => c.dispatchEvent(new MouseEvent(t, {{ clientX: x(f), clientY: r.top + 60, shiftKey: {shift}, bubbles: true }})); ev('mousedown', {from}); ev('mousemove', {to}); ev('mouseup', {to}); return location.hash")
    };
    let hash = browser.js(&drag(0.4, 0.6, false));
    let hash = hash.as_str().unwrap().to_owned();
    let span_of = |h: &str| {
        let p = |k: &str| -> i64 {
            h.split(['?', '&'])
                .find_map(|kv| kv.strip_prefix(k))
                .unwrap()
                .parse()
                .unwrap()
        };
        (p("from="), p("to="))
    };
    let (f1, t1) = span_of(&hash);
    assert!(((t1 - f1) as f64 / 1e9 - 180.0).abs() < 5.0, "{hash}");
    assert!(hash.contains(&format!("alert={id}")), "{hash}");
    browser
        .wait("the zoomed view", &format!("const c = document.getElementById('canvas-x'); return c._map && Math.abs(c._map.x0 - {}) < 1", f1 / 1_000_000))
        .await;
    // Shift-drag pans: dragging right to left moves the view later by the dragged time.
    let hash = browser.js(&drag(0.6, 0.4, true));
    let (f2, t2) = span_of(hash.as_str().unwrap());
    assert!(((f2 - f1) as f64 / 1e9 - 36.0).abs() < 2.0, "{f1} {f2}");
    assert_eq!(t2 - f2, t1 - f1);
    browser
        .wait("the panned view", &format!("const c = document.getElementById('canvas-x'); return c._map && Math.abs(c._map.x0 - {}) < 1", f2 / 1_000_000))
        .await;

    // Spectrum of the span shown.
    browser.js("document.getElementById('btn-spectrum').click(); return 1");
    let peaks = browser
        .wait("the spectrum", "const p = document.getElementById('spectrum-peaks'); return p && document.getElementById('canvas-psd').dataset.drawn && p.textContent")
        .await;
    let x_peak: f64 = peaks.as_str().unwrap()[2..]
        .split(' ')
        .next()
        .unwrap()
        .parse()
        .unwrap();
    assert!((x_peak - SWAY_HZ).abs() < 0.05, "{peaks}");
    let line = browser.js("return document.getElementById('spectrum-line').textContent");
    assert!(
        line.as_str().unwrap().contains("degrees of freedom"),
        "{line}"
    );
    browser.js("document.getElementById('spectrum').scrollIntoView(); return 1");
    browser.screenshot("sensor-spectrum");

    // Spectrogram of the same span: the sway's frequency is the strongest row.
    browser.js("document.getElementById('btn-spectrogram').click(); return 1");
    let peak = browser
        .wait("the spectrogram", "const c = document.getElementById('canvas-spectrogram'); return c.dataset.drawn && c.dataset.peakHz")
        .await;
    let res = browser.js("return document.getElementById('canvas-spectrogram') && JSON.stringify(document.getElementById('spectrogram-line').textContent)");
    let peak: f64 = peak.as_str().unwrap().parse().unwrap();
    let columns =
        browser.js("return Number(document.getElementById('canvas-spectrogram').dataset.drawn)");
    assert_eq!(columns, 60, "{res}");
    assert!((peak - SWAY_HZ).abs() < 0.4, "{peak} Hz; {res}");
    browser.js("document.getElementById('spectrogram').scrollIntoView(); return 1");
    browser.screenshot("sensor-spectrogram");
    browser.js("window.scrollTo(0, 0); return 1");

    // Export: the plot as PNG and SVG, the samples as CSV.
    browser.js("document.getElementById('btn-png').click(); return 1");
    browser
        .wait("a PNG", "const a = document.getElementById('export-link'); return a && a.dataset.type === 'image/png' && Number(a.dataset.bytes) > 5000 && a.getAttribute('download').endsWith('.png')")
        .await;
    browser.js("document.getElementById('btn-svg').click(); return 1");
    browser
        .wait("an SVG", "const a = document.getElementById('export-link'); return a && a.dataset.type === 'image/svg+xml' && Number(a.dataset.bytes) > 5000")
        .await;
    browser.js("document.getElementById('btn-csv').click(); return 1");
    let csv = browser
        .wait("a CSV link", "const a = document.getElementById('export-link'); return a && a.dataset.type === 'text/csv' && a.href")
        .await;
    assert!(
        csv.as_str()
            .unwrap()
            .contains("/api/export.csv?building=hq&sensor=acc-01&from_ns="),
        "{csv}"
    );
    browser.js("document.getElementById('btn-mseed').click(); return 1");
    let mseed = browser
        .wait("a miniSEED link", "const a = document.getElementById('export-link'); return a && a.dataset.type === 'application/vnd.fdsn.mseed' && a.href")
        .await;
    let mseed = mseed.as_str().unwrap().to_owned();
    assert!(
        mseed.contains("/api/export.mseed?building=hq&sensor=acc-01&from_ns="),
        "{mseed}"
    );
    let path = &mseed[mseed.find("/api/").unwrap()..];
    let (status, _) = console.get(path).await;
    assert_eq!(status, 200, "{path}");

    // The last 24 hours: a trend of per-minute aggregates (the site keeps 75 minutes).
    browser.js("document.querySelector('button.last[data-last=\"86400\"]').click(); return 1");
    browser
        .wait("the trend", "const p = document.getElementById('plot'); return p.dataset.source === 'trend' && Number(p.dataset.minutes) > 70 && !document.getElementById('freq-plot').hidden")
        .await;
    browser.screenshot("sensor-trend-24h");

    // The building view from the alert: every sensor on one time axis, the window shaded on
    // each and the threshold on the alert's sensor.
    browser.go(&format!("{url}#/alerts"));
    let href = browser
        .wait("the building link", &format!("const a = document.querySelector('#alert-rows tr[data-id=\"{id}\"] a.to-building'); return a && a.getAttribute('href')"))
        .await;
    browser.go(&format!("{url}{}", href.as_str().unwrap()));
    browser
        .wait("three sensors drawn", "const b = document.getElementById('building-plots'); return b && b.dataset.loaded === '3' && document.querySelectorAll('#building-plots canvas[data-drawn]').length === 3")
        .await;
    browser
        .wait("the alert on the building view", "return document.getElementById('bcanvas-acc-01').dataset.threshold && [...document.querySelectorAll('#building-plots canvas')].every((c) => c.dataset.shade)")
        .await;
    let aligned = browser.js("const m = [...document.querySelectorAll('#building-plots canvas')].map((c) => [c._map.x0, c._map.x1].join()); return new Set(m).size");
    assert_eq!(aligned, 1, "one time axis");
    assert_eq!(
        browser.js("return document.getElementById('bcanvas-acc-02').dataset.threshold || null"),
        Value::Null
    );
    browser.screenshot("building-view");
    browser.assert_no_errors("time, spectra, building and export");

    // Dark mode follows prefers-color-scheme.
    browser.cdp(
        "Emulation.setEmulatedMedia",
        json!({"features": [{"name": "prefers-color-scheme", "value": "dark"}]}),
    );
    browser.go(&format!("{url}#/sensor/hq/acc-01?last=900"));
    browser
        .wait("the dark plot", "const p = document.getElementById('plot'); return p && Number(p.dataset.buckets) > 100")
        .await;
    let bg = browser.js("return [getComputedStyle(document.body).backgroundColor, getComputedStyle(document.documentElement).getPropertyValue('--plot-bg').trim()]");
    assert_eq!(bg, json!(["rgb(17, 22, 28)", "#151b22"]), "{bg}");
    browser.screenshot("sensor-dark");
    browser.assert_no_errors("dark mode");
    drop(browser);
    console.stop().await;
}

fn python() -> String {
    std::env::var("TRIAX_PYTHON").unwrap_or_else(|_| {
        panic!(
            "TRIAX_PYTHON is not set: the miniSEED test reads the export with ObsPy; run the \
             tests with scripts/test, which makes a Python with it"
        )
    })
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn spectrogram_and_miniseed_over_http() {
    let site = Site::start(15 * 60).await;
    let console = Console::start(&site, None).await;
    let now = now_ns();
    let q = |path: &str, from: i64, to: i64| {
        format!("{path}?building=hq&sensor=acc-01&from_ns={from}&to_ns={to}")
    };

    // Spectrogram of ten minutes of x: the sway's 2.5 Hz is the loudest row of every column.
    let (from, to) = (now - 700_000_000_000, now - 100_000_000_000);
    let g = console
        .json(&(q("/api/spectrogram", from, to) + "&columns=100"))
        .await;
    assert_eq!(g["error"], Value::Null, "{}", g["error"]);
    let g = &g["spectrogram"];
    let res = g["resolution_hz"].as_f64().unwrap();
    let freqs: Vec<f64> = g["frequencies_hz"]
        .as_array()
        .unwrap()
        .iter()
        .map(|f| f.as_f64().unwrap())
        .collect();
    let columns = g["psd_db"].as_array().unwrap();
    assert_eq!(columns.len(), 100);
    assert_eq!(g["column_ns"], 6_000_000_000i64);
    assert_eq!(g["axis"], "x");
    assert_eq!(g["unit"], "dB re 1 (m/s²)²/Hz");
    for (i, c) in columns.iter().enumerate() {
        let db: Vec<f64> = c
            .as_array()
            .unwrap_or_else(|| panic!("column {i} is empty"))
            .iter()
            .map(|v| v.as_f64().unwrap())
            .collect();
        let loudest = (2..db.len())
            .max_by(|a, b| db[*a].total_cmp(&db[*b]))
            .unwrap();
        assert!(
            (freqs[loudest] - SWAY_HZ).abs() <= res,
            "column {i}: {} Hz",
            freqs[loudest]
        );
    }
    assert!((g["peak_hz"].as_f64().unwrap() - SWAY_HZ).abs() <= res);
    // z holds gravity and noise only: no tone there.
    let gz = console
        .json(&(q("/api/spectrogram", from, to) + "&axis=z"))
        .await;
    assert_eq!(gz["spectrogram"]["axis"], "z");
    for (bad, name) in [
        ("&axis=w", "\"axis\""),
        ("&segment=100", "\"segment\""),
        ("&segment=2048", "\"segment\""),
        ("&columns=5", "\"columns\""),
    ] {
        let (status, body) = console.get(&(q("/api/spectrogram", from, to) + bad)).await;
        assert_eq!(status, 400, "{bad}: {body}");
        assert!(body.contains(name), "{bad}: {body}");
    }
    let (status, _) = console
        .get(&q("/api/spectrogram", now - 7_200_000_000_000, now))
        .await;
    assert_eq!(status, 400, "more than an hour");

    // miniSEED of 20 s that starts and ends inside batches: ObsPy reads the nine channels, and
    // every value equals the CSV export's.
    let (from, to) = (now - 60_123_000_000, now - 40_077_000_000);
    let (status, csv) = console.get(&q("/api/export.csv", from, to)).await;
    assert_eq!(status, 200, "{csv}");
    let mseed = get_bytes(&console, &q("/api/export.mseed", from, to)).await;
    assert!(
        mseed
            .head
            .contains("Content-Type: application/vnd.fdsn.mseed"),
        "{}",
        mseed.head
    );
    assert!(
        mseed
            .head
            .contains(&format!("filename=\"hq_acc-01_{from}_{to}.mseed\"")),
        "{}",
        mseed.head
    );
    assert_eq!(mseed.body.len() % 512, 0);
    let dir = tempfile::tempdir().unwrap();
    let (mseed_path, csv_path) = (dir.path().join("view.mseed"), dir.path().join("view.csv"));
    std::fs::write(&mseed_path, &mseed.body).unwrap();
    std::fs::write(&csv_path, &csv).unwrap();
    let script = r#"
import csv, sys
import numpy as np
from obspy import read
st = read(sys.argv[1], format="MSEED")
st.merge(method=0)
rows = list(csv.DictReader(open(sys.argv[2])))
ids = sorted(tr.id for tr in st)
assert len(ids) == 9, ids
for axis, name in enumerate("xyz"):
    tr = st.select(location="00", channel="EN%d" % (axis + 1))
    assert len(tr) == 1, (name, tr)
    tr = tr[0]
    want = np.array([np.float32(r["a%s_mps2" % name]) for r in rows], dtype=np.float32)
    assert tr.stats.npts == len(rows), (tr.stats.npts, len(rows))
    assert np.array_equal(tr.data.astype(np.float32), want), name
    u = st.select(location="U0", channel="EN%d" % (axis + 1))[0]
    uwant = np.array([np.float32(r["u%s_mps2" % name]) for r in rows], dtype=np.float32)
    assert np.array_equal(u.data.astype(np.float32), uwant), "u" + name
    first_ns = tr.stats.starttime.ns
    assert first_ns == int(rows[0]["t_ns"]), (first_ns, rows[0]["t_ns"])
    assert tr.stats.sampling_rate == 100.0
print("ok", len(rows), st[0].stats.network, st[0].stats.station)
"#;
    let out = std::process::Command::new(python())
        .arg("-c")
        .arg(script)
        .arg(&mseed_path)
        .arg(&csv_path)
        .output()
        .expect("the Python interpreter runs");
    let said =
        String::from_utf8_lossy(&out.stdout).into_owned() + &String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "ObsPy: {said}");
    let rows = csv.lines().count() - 1;
    assert!(rows > 2000, "{rows}");
    assert!(said.starts_with(&format!("ok {rows} XX ACC01")), "{said}");
    let (status, body) = console
        .get(&(q("/api/export.mseed", from, to) + "&network=TOOLONG"))
        .await;
    assert_eq!(status, 400, "{body}");
    assert!(body.contains("\"network\""), "{body}");
    let (status, _) = console
        .get(&q("/api/export.mseed", now - 7_200_000_000_000, now))
        .await;
    assert_eq!(status, 400, "more than an hour");
    console.stop().await;
}

struct Raw {
    head: String,
    body: Vec<u8>,
}

/// GET `path` as bytes, with the response head.
async fn get_bytes(console: &Console, path: &str) -> Raw {
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let mut s = tokio::net::TcpStream::connect(console.addr).await.unwrap();
    s.write_all(
        format!(
            "GET {path} HTTP/1.1\r\nHost: {}\r\nConnection: close\r\n\r\n",
            console.addr
        )
        .as_bytes(),
    )
    .await
    .unwrap();
    let mut out = Vec::new();
    tokio::time::timeout(site::TIMEOUT, s.read_to_end(&mut out))
        .await
        .expect("the console answers")
        .unwrap();
    let split = out
        .windows(4)
        .position(|w| w == b"\r\n\r\n")
        .expect("a response head");
    Raw {
        head: String::from_utf8_lossy(&out[..split]).into_owned(),
        body: out[split + 4..].to_vec(),
    }
}

/// What one event stream carried from its first live frame on.
#[derive(Default)]
struct Carried {
    /// Bytes of every event after the first live frame.
    bytes: usize,
    live_frames: usize,
    fleet_events: usize,
    /// The stream time covered from the first frame's end to the last's, ns.
    first_end_ns: i64,
    last_end_ns: i64,
    bucket_ns: i64,
    /// Each bucket as last sent, by index.
    buckets: std::collections::BTreeMap<i64, Value>,
}

/// Reads `/events?<query>` until a live frame reaches `until_ns`.
async fn carried(addr: std::net::SocketAddr, query: String, until_ns: i64) -> Carried {
    use tokio::io::{AsyncBufReadExt, AsyncWriteExt, BufReader};
    let mut s = tokio::net::TcpStream::connect(addr).await.unwrap();
    s.write_all(format!("GET /events?{query} HTTP/1.1\r\nHost: {addr}\r\n\r\n").as_bytes())
        .await
        .unwrap();
    let mut lines = BufReader::new(s).lines();
    let mut out = Carried::default();
    let mut event = String::new();
    let mut started = false;
    loop {
        let line = tokio::time::timeout(TIMEOUT, lines.next_line())
            .await
            .expect("the stream goes on")
            .unwrap()
            .expect("the stream stays open");
        if let Some(e) = line.strip_prefix("event: ") {
            event = e.to_owned();
        }
        if started {
            out.bytes += line.len() + 1;
        }
        let Some(data) = line.strip_prefix("data: ") else {
            continue;
        };
        match event.as_str() {
            "fleet" | "fleet_delta" if started => out.fleet_events += 1,
            "live" => {
                let v: Value = serde_json::from_str(data).unwrap();
                let view = &v["view"];
                let end = view["end_ns"].as_i64().unwrap();
                out.bucket_ns = view["bucket_ns"].as_i64().unwrap();
                for b in view["buckets"].as_array().unwrap() {
                    out.buckets.insert(b[0].as_i64().unwrap(), b.clone());
                }
                if !started {
                    started = true;
                    out.first_end_ns = end;
                } else {
                    out.live_frames += 1;
                }
                out.last_end_ns = end;
                if end >= until_ns {
                    return out;
                }
            }
            _ => {}
        }
    }
}

/// A light stream (`lite=1`) carries the same buckets as the full one for a fraction of the
/// bytes: the sensor publishes live at 100 Hz and two streams of the same view read it.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_light_live_stream_carries_the_same_buckets_for_fewer_bytes() {
    let site = Site::start(60).await;
    let console = Console::start(&site, None).await;
    let period_ns = BATCH as i64 * 1_000_000_000 / RATE_HZ as i64;
    let first = ((now_ns() - site.t0_ns) / period_ns + 1) as u64;
    let batches = 30;
    let last_end_ns = site.t0_ns + (first + batches) as i64 * period_ns;
    // The sensor: each batch put once its last sample is past, as a node sends it.
    let publisher = site.session.clone();
    let t0 = site.t0_ns;
    let sensor = tokio::spawn(async move {
        for seq in first..first + batches {
            let b = batch(0, "acc-01", t0, seq);
            let due = b.header.timestamp_ns + period_ns - now_ns();
            if due > 0 {
                tokio::time::sleep(std::time::Duration::from_nanos(due as u64)).await;
            }
            publisher
                .put("triax/hq/corrected/acc-01", b.encode())
                .await
                .unwrap();
        }
    });
    let q = |lite: &str| format!("building=hq&sensor=acc-01&span_s=10&width=1300{lite}");
    let (full, light) = tokio::join!(
        carried(console.addr, q(""), last_end_ns),
        carried(console.addr, q("&lite=1"), last_end_ns)
    );
    sensor.await.unwrap();
    let rate = |c: &Carried| c.bytes as f64 / ((c.last_end_ns - c.first_end_ns) as f64 / 1e9);
    let (full_bps, light_bps) = (rate(&full), rate(&light));
    eprintln!(
        "10 s over 1300 columns at 100 Hz: full {:.0} B/s ({} frames, {} fleet events), light {:.0} B/s ({} frames, {} fleet events)",
        full_bps, full.live_frames, full.fleet_events, light_bps, light.live_frames, light.fleet_events
    );
    assert!(
        light_bps * 4.0 < full_bps,
        "light {light_bps:.0} B/s, full {full_bps:.0} B/s"
    );
    assert!(light.live_frames < full.live_frames);
    // The figures count the fleet's events too: a delta a second on the full stream, the
    // same deltas every 5 s on the light one.
    assert!(full.fleet_events >= 10, "{}", full.fleet_events);
    // Every bucket both have whole (after the first frames, up to the end) is the same.
    assert_eq!(full.bucket_ns, light.bucket_ns);
    let (lo, hi) = (
        full.first_end_ns.max(light.first_end_ns) / full.bucket_ns + 1,
        last_end_ns / full.bucket_ns,
    );
    let mut compared = 0;
    for i in lo..hi {
        assert_eq!(full.buckets.get(&i), light.buckets.get(&i), "bucket {i}");
        compared += 1;
    }
    assert!(compared > 500, "{compared}");
    // The page: the light stream chosen with its box, kept in the browser.
    let browser = Browser::start(false);
    browser.go(&format!("{}#/sensor/hq/acc-01", console.url()));
    browser
        .wait("the full stream", "const p = document.getElementById('plot'); return p && p.dataset.stream === 'full' && Number(p.dataset.frames) > 0")
        .await;
    browser.js("document.getElementById('lite').click(); return 1");
    browser
        .wait("the light stream", "const p = document.getElementById('plot'); return p && p.dataset.stream === 'light' && document.getElementById('lite').checked && Number(p.dataset.buckets) > 100")
        .await;
    browser.screenshot("sensor-light-stream");
    browser.go(&format!("{}#/sensor/hq/acc-02", console.url()));
    browser
        .wait(
            "the choice kept",
            "const p = document.getElementById('plot'); return p && p.dataset.stream === 'light'",
        )
        .await;
    browser.assert_no_errors("the light stream");
    drop(browser);
    let (status, body) = console
        .get("/events?building=hq&sensor=acc-01&lite=2")
        .await;
    assert_eq!(status, 400, "{body}");
    assert!(body.contains("\"lite\""), "{body}");
    console.stop().await;
}

/// The fleet event sends the fleet's brief once, then what changed: nothing but the clock and
/// the totals while the fleet is quiet, a sensor's new state when it changes. The page keeps
/// its table from them, and reads the counters of the buildings it shows on demand.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_fleet_event_sends_what_changed() {
    use tokio::io::{AsyncBufReadExt, AsyncWriteExt, BufReader};
    let site = Site::start(60).await;
    let console = Console::start(&site, None).await;
    console
        .wait_json("the site's status", "/api/fleet", |v| {
            v["buildings"][0]["sensors"].as_array().map(Vec::len) == Some(3)
        })
        .await;
    let one = console.json("/api/fleet?building=hq&sensor=acc-02").await;
    assert_eq!(one["sensors"].as_array().unwrap().len(), 1, "{one}");
    assert!(one["sensors"][0]["samples"].as_u64().unwrap() > 0, "{one}");
    assert_eq!(console.get("/api/fleet?building=nowhere").await.0, 404);
    assert_eq!(console.get("/api/fleet?sensor=acc-01").await.0, 400);

    // The stream: the whole brief first, then five quiet deltas, each a few hundred bytes.
    let addr = console.addr;
    let mut s = tokio::net::TcpStream::connect(addr).await.unwrap();
    s.write_all(format!("GET /events HTTP/1.1\r\nHost: {addr}\r\n\r\n").as_bytes())
        .await
        .unwrap();
    let mut lines = BufReader::new(s).lines();
    let mut event = String::new();
    let mut deltas: Vec<Value> = Vec::new();
    let mut first: Option<Value> = None;
    while deltas.len() < 5 {
        let line = tokio::time::timeout(TIMEOUT, lines.next_line())
            .await
            .expect("the stream goes on")
            .unwrap()
            .expect("the stream stays open");
        if let Some(e) = line.strip_prefix("event: ") {
            event = e.to_owned();
        } else if let Some(data) = line.strip_prefix("data: ") {
            let v: Value = serde_json::from_str(data).unwrap();
            match event.as_str() {
                "fleet" => first = Some(v),
                "fleet_delta" => {
                    assert!(
                        data.len() < 400,
                        "a quiet delta of {} bytes: {data}",
                        data.len()
                    );
                    deltas.push(v)
                }
                other => panic!("event {other:?}"),
            }
        }
    }
    let first = first.expect("the whole fleet first");
    assert_eq!(first["buildings"][0]["sensors"][0]["states"], json!(["ok"]));
    assert!(
        first["buildings"][0]["sensors"][0].get("samples").is_none(),
        "no counters in the event: {first}"
    );
    let seq = first["seq"].as_u64().unwrap();
    for (i, d) in deltas.iter().enumerate() {
        assert_eq!(d["seq"].as_u64().unwrap(), seq + 1 + i as u64, "{d}");
        assert!(d.get("sensors").is_none(), "a quiet fleet: {d}");
    }
    // A state changes: the next delta carries that sensor, and the new alert whole.
    site.alert("acc-02", "exceeded", "a verdict", (10, 20), true)
        .await;
    let changed = loop {
        let line = tokio::time::timeout(TIMEOUT, lines.next_line())
            .await
            .expect("the stream goes on")
            .unwrap()
            .expect("the stream stays open");
        let Some(data) = line.strip_prefix("data: ") else {
            continue;
        };
        let v: Value = serde_json::from_str(data).unwrap();
        if v.get("sensors").is_some() {
            break v;
        }
    };
    assert_eq!(changed["sensors"][0]["sensor_id"], "acc-02", "{changed}");
    assert_eq!(changed["sensors"][0]["states"], json!(["exceeded"]));
    assert_eq!(changed["alerts"][0]["statement"], "a verdict");
    assert_eq!(
        changed["sensors"][0]["latest_alert"],
        changed["alerts"][0]["id"]
    );

    // The page: states from the events, counters from /api/fleet?building=.
    let browser = Browser::start(false);
    browser.go(&console.url());
    browser
        .wait("the three rows with their counters", "const r = [...document.querySelectorAll('tr.sensor')]; return r.length === 3 && r.every((x) => x.querySelector('.flagged-share').textContent.endsWith('%')) && r.every((x) => Number(x.children[4].textContent) > 0)")
        .await;
    site.alert("acc-03", "exceeded", "another", (10, 20), true)
        .await;
    let row = browser
        .wait("acc-03's new state from a delta", "const r = document.querySelector('tr.sensor[data-sensor=\"acc-03\"]'); return r && r.dataset.states.includes('exceeded') && Number(document.getElementById('view').dataset.fleetDeltas) > 0 && r.children[10].textContent")
        .await;
    assert!(
        row.as_str().unwrap().contains("exceeded peak acceleration"),
        "{row}"
    );
    browser.screenshot("fleet-deltas");
    browser.assert_no_errors("the fleet view");
    drop(browser);
    console.stop().await;
}

/// Comparing: velocity and displacement by integration within a stated band, a filter per
/// plot, and every sensor's axes overlaid in one plot of the building view.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn comparing_in_a_browser() {
    let site = Site::start(15 * 60).await;
    let console = Console::start(&site, None).await;
    console
        .wait_json("the site's status", "/api/fleet", |v| {
            v["buildings"][0]["sensors"].as_array().map(Vec::len) == Some(3)
        })
        .await;
    let now = now_ns();
    let (from, to) = (now - 300_000_000_000, now - 180_000_000_000);
    let q = |extra: &str| {
        format!(
            "/api/processed?building=hq&sensor=acc-01&from_ns={from}&to_ns={to}&width=600{extra}"
        )
    };
    // Velocity of the 2.5 Hz sway of 0.05 m/s² in 0.5-20 Hz: a/ω through the filters.
    let v = console.json(&q("&quantity=velocity&band=0.5-20")).await;
    assert_eq!(v["error"], Value::Null, "{v}");
    let view = &v["view"];
    assert_eq!(view["unit"], "m/s");
    assert_eq!(view["band"], json!({"low_hz": 0.5, "high_hz": 20.0}));
    let peak = view["buckets"]
        .as_array()
        .unwrap()
        .iter()
        .map(|b| b[2].as_f64().unwrap().max(-b[1].as_f64().unwrap()))
        .fold(0.0f64, f64::max);
    let w = 2.0 * std::f64::consts::PI * SWAY_HZ;
    let want = SWAY_MPS2 / w;
    assert!((peak / want - 1.0).abs() < 0.03, "{peak} against {want}");
    assert_eq!(v["settle_s"], 6.0, "three periods of 0.5 Hz each side");
    for (extra, names) in [
        ("&quantity=velocity", "\"band\""),
        ("&quantity=jerk", "\"quantity\""),
        ("&band=20-5", "\"band\""),
    ] {
        let (status, body) = console.get(&q(extra)).await;
        assert_eq!(status, 400, "{extra}: {body}");
        assert!(body.contains(names), "{extra}: {body}");
    }

    let browser = Browser::start(false);
    let url = console.url();
    browser.go(&format!(
        "{url}#/sensor/hq/acc-01?from={from}&to={to}&q=displacement&band=0.5-20"
    ));
    browser
        .wait("the displacement view", "const p = document.getElementById('plot'); return p && p.dataset.source === 'processed' && document.getElementById('canvas-x').dataset.quantity === 'displacement'")
        .await;
    let title = browser.js("return document.getElementById('title-x').textContent");
    assert!(
        title
            .as_str()
            .unwrap()
            .contains("displacement x (m), band 0.5–20 Hz"),
        "{title}"
    );
    let readout = browser.js("const c = document.getElementById('canvas-x'); const r = c.getBoundingClientRect(); c.dispatchEvent(new MouseEvent('mousemove', { clientX: r.left + r.width / 2, clientY: r.top + 50, bubbles: true })); const b = document.getElementById('readout'); return b.hidden ? null : b.innerText");
    assert!(
        readout.as_str().unwrap().contains(" m\n") || readout.as_str().unwrap().contains(" m"),
        "{readout}"
    );
    browser.screenshot("sensor-displacement");
    // Zooming keeps the quantity and band.
    let hash = browser.js("const c = document.getElementById('canvas-x'); const r = c.getBoundingClientRect(); const m = c._map; const x = (f) => r.left + m.left + f * m.pw; const ev = (t, f) => c.dispatchEvent(new MouseEvent(t, { clientX: x(f), clientY: r.top + 60, bubbles: true })); ev('mousedown', 0.3); ev('mousemove', 0.6); ev('mouseup', 0.6); return location.hash");
    assert!(
        hash.as_str()
            .unwrap()
            .contains("q=displacement&band=0.5-20"),
        "{hash}"
    );

    // The building view: x and z of every sensor overlaid, and one plot filtered alone.
    browser.go(&format!(
        "{url}#/building/hq?from={from}&to={to}&overlay=xz"
    ));
    browser
        .wait("the overlay of six series", "const c = document.getElementById('bcanvas-overlay'); return c && c.dataset.series === '6' && document.getElementById('building-plots').dataset.loaded === '3'")
        .await;
    let legend = browser.js("return document.getElementById('overlay-legend').textContent");
    assert!(legend.as_str().unwrap().contains("acc-02 az"), "{legend}");
    browser.js("const i = document.querySelector('input.plot-band[data-sensor=\"acc-02\"]'); i.value = '5-20'; i.dispatchEvent(new Event('change')); return 1");
    let ranges = browser
        .wait("acc-02 filtered alone", "const c = document.getElementById('bcanvas-acc-02'); const d = document.getElementById('bcanvas-acc-01'); return c.dataset.band === '5-20' && d.dataset.band === undefined && [c._map.hi - c._map.lo, d._map.hi - d._map.lo]")
        .await;
    let (filtered, plain) = (ranges[0].as_f64().unwrap(), ranges[1].as_f64().unwrap());
    assert!(
        filtered < 0.4 * plain,
        "the sway is outside 5-20 Hz: {filtered} against {plain}"
    );
    browser.screenshot("building-overlay-and-filter");
    browser.assert_no_errors("comparing");
    drop(browser);
    console.stop().await;
}

/// Logs the browser in as `name` through the page's form.
async fn browser_login(browser: &Browser, url: &str, name: &str) {
    browser.go(&format!("{url}#/login"));
    browser
        .wait(
            "the login form",
            "return document.getElementById('login-name')",
        )
        .await;
    browser.js(&format!("document.getElementById('login-name').value = '{name}'; document.getElementById('login-password').value = '{PASSWORD}'; document.getElementById('login-go').click(); return 1"));
    browser
        .wait("logged in", &format!("const w = document.getElementById('who-name'); return w && w.textContent.startsWith('{name} ')"))
        .await;
}

/// Marking: annotations of one's own, kept, shown on every plot of their building (a sensor's
/// only on its own), removed by their author or an admin, exported as CSV; and a day at a
/// glance: the helicorder of two hours from the per-second store, with gaps, flags and the
/// annotations, the second look read from the store.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn marking_and_a_day_at_a_glance() {
    let site = Site::start(2 * 3600).await;
    let dir = tempfile::tempdir().unwrap();
    let operators = dir.path().join("operators");
    write_operators(
        &operators,
        &[("alice", "operate"), ("bob", "operate"), ("root", "admin")],
    );
    let state = dir.path().join("state");
    let console = Console::start_with(&site, Some(state.clone()), |o| {
        o.operators_file = Some(operators.clone());
    })
    .await;
    console.login("alice").await;
    console
        .wait_json("the site's status", "/api/fleet", |v| {
            v["buildings"][0]["sensors"].as_array().map(Vec::len) == Some(3)
        })
        .await;
    let now = now_ns();
    let min = 60_000_000_000i64;
    let (status, crane) = console
        .post(
            "/api/annotations",
            &json!({"building": "hq", "from_ns": now - 30 * min, "to_ns": now - 20 * min, "text": "crane lift"}),
        )
        .await;
    assert_eq!(status, 200, "{crane}");
    let crane: Value = serde_json::from_str(&crane).unwrap();
    assert_eq!(
        (crane["by"].as_str(), crane["source"].as_str()),
        (Some("alice"), Some("operator"))
    );
    for (body, names) in [
        (
            json!({"building": "hq", "from_ns": now, "to_ns": now + min, "text": ""}),
            "\"text\"",
        ),
        (
            json!({"building": "hq", "from_ns": now, "to_ns": now - min, "text": "x"}),
            "\"to_ns\"",
        ),
        (
            json!({"building": "hq", "from_ns": "soon", "to_ns": now, "text": "x"}),
            "\"from_ns\"",
        ),
        (
            json!({"building": "hq", "from_ns": now, "to_ns": now, "text": "x", "by": "eve"}),
            "\"by\"",
        ),
    ] {
        let (status, text) = console.post("/api/annotations", &body).await;
        assert_eq!(status, 400, "{body}: {text}");
        assert!(text.contains(names), "{body}: {text}");
    }
    console.login("bob").await;
    let (status, moved) = console
        .post(
            "/api/annotations",
            &json!({"building": "hq", "sensor": "acc-02", "from_ns": now - 25 * min, "to_ns": now - 25 * min, "text": "=sensor moved \"2 m\""}),
        )
        .await;
    assert_eq!(status, 200, "{moved}");
    let (status, text) = console
        .post("/api/annotations/delete", &json!({"id": crane["id"]}))
        .await;
    assert_eq!(status, 400, "not bob's: {text}");
    assert!(text.contains("only its author or an admin"), "{text}");
    let (status, csv) = console.get("/api/annotations?building=hq&format=csv").await;
    assert_eq!(status, 200);
    let lines: Vec<&str> = csv.lines().collect();
    assert_eq!(
        lines[0],
        "id,building,sensor,from_utc,to_utc,from_ns,to_ns,text,by,at,source"
    );
    assert_eq!(lines.len(), 3, "{csv}");
    assert!(
        lines[2].contains(",acc-02,") && lines[2].contains("\"'=sensor moved \"\"2 m\"\"\""),
        "{csv}"
    );

    let browser = Browser::start(false);
    let url = console.url();
    browser_login(&browser, &url, "alice").await;
    // On every plot of the building: the building's note everywhere, acc-02's on acc-02 only.
    browser.go(&format!("{url}#/sensor/hq/acc-01?last=3600"));
    browser
        .wait("acc-01's plots with the crane lift", "const c = document.getElementById('canvas-x'); return c && document.getElementById('plot').dataset.source === 'history' && c.dataset.notes === '1' && document.querySelectorAll('#notes-list tr.note').length === 2")
        .await;
    browser.go(&format!("{url}#/building/hq?last=3600"));
    browser
        .wait("the building's plots with their notes", "const n = (s) => { const c = document.getElementById('bcanvas-' + s); return c && c.dataset.drawn && c.dataset.notes; }; return document.getElementById('building-plots').dataset.loaded === '3' && n('acc-01') === '1' && n('acc-02') === '2' && n('acc-03') === '1'")
        .await;
    // One of one's own, from the page: the span shown.
    browser.js("document.getElementById('note-text').value = 'floor 3 works'; document.getElementById('note-add').click(); return 1");
    browser
        .wait("the new note listed and drawn", "return document.querySelectorAll('#notes-list tr.note').length === 3 && document.getElementById('bcanvas-acc-01').dataset.notes === '2'")
        .await;
    browser.screenshot("building-annotations");
    let listed = console.json("/api/annotations?building=hq").await;
    assert_eq!(listed["matched"], 3, "{listed}");
    assert_eq!(listed["annotations"][2]["by"], "alice");

    // The helicorder of two hours: 8 rows of 15 min, one column a second.
    let t0 = std::time::Instant::now();
    browser.go(&format!("{url}#/helicorder/hq/acc-01?hours=2&row=900"));
    let drawn = browser
        .wait("the helicorder", "const c = document.getElementById('heli-canvas'); return c && c.dataset.drawn && [c.dataset.rows, c.dataset.gaps, c.dataset.flagged, c.dataset.notes, c.dataset.drawMs, c.dataset.fetchMs]")
        .await;
    let first_s = t0.elapsed().as_secs_f64();
    let n = |i: usize| drawn[i].as_str().unwrap().parse::<f64>().unwrap();
    assert!(
        [8.0, 9.0].contains(&n(0)),
        "2 h from a whole quarter: {drawn}"
    );
    assert!(
        n(1) >= 1.0,
        "the seconds before the history began and after now are gaps: {drawn}"
    );
    assert!(n(2) > 100.0, "every 7th batch is flagged: {drawn}");
    assert!(n(3) >= 2.0, "the crane lift and the works: {drawn}");
    browser.screenshot("helicorder");
    // Again: from the per-second store, reading only the last minute.
    let h = console
        .json(&format!(
            "/api/helicorder?building=hq&sensor=acc-01&from_ns={}&to_ns={}&row_s=900",
            now - 7_200_000_000_000,
            now
        ))
        .await;
    assert!(
        h["batches_read"].as_u64().unwrap() < 300,
        "{}",
        h["batches_read"]
    );
    let d = &h["helicorder"];
    assert_eq!(
        (d["rows"].as_u64(), d["columns"].as_u64()),
        (Some(8), Some(900))
    );
    // The sway of ±0.05 m/s² about the mean, in µm/s².
    let row = d["data"][4].as_array().unwrap();
    let top = row.iter().filter_map(Value::as_i64).max().unwrap();
    assert!((45_000..=56_000).contains(&top), "{top}");
    browser.assert_no_errors("annotations and helicorder");
    eprintln!(
        "helicorder of 2 h: first look {first_s:.1} s in all, {} ms the page's read, drawn in {} ms",
        n(5),
        n(4)
    );
    drop(browser);
    console.stop().await;
}

/// The helicorder of 24 h at 100 Hz: read once into the per-second store, then drawn from it.
/// Run by hand, in release (BENCHMARKS.md):
/// `cargo test --release -p triax-console --test views -- --ignored helicorder_of_a_day --nocapture`
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
#[ignore]
async fn helicorder_of_a_day() {
    let site = Site::start(24 * 3600).await;
    let console = Console::start(&site, None).await;
    console
        .wait_json("the site's status", "/api/fleet", |v| {
            v["buildings"][0]["sensors"].as_array().map(Vec::len) == Some(3)
        })
        .await;
    let browser = Browser::start(false);
    let url = console.url();
    let mut looks = Vec::new();
    for look in 0..4 {
        let t0 = std::time::Instant::now();
        browser.go(&format!(
            "{url}#/helicorder/hq/acc-01?hours=24&row=900&look={look}"
        ));
        let d = browser
            .wait("the helicorder of a day", "const c = document.getElementById('heli-canvas'); return c && c.dataset.drawn && [c.dataset.rows, c.dataset.drawMs, c.dataset.fetchMs]")
            .await;
        looks.push((t0.elapsed().as_secs_f64(), d));
    }
    for (i, (s, d)) in looks.iter().enumerate() {
        eprintln!("look {i}: {s:.2} s in all; rows, draw ms, read ms: {d}");
    }
    browser.screenshot("helicorder-day");
    drop(browser);
    console.stop().await;
}
