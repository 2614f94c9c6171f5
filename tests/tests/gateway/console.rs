//! The operators' console against a running building, in a real browser.
//!
//! The building is the demo's: the six sensors of `triax_gateway::demo::fleet` (four
//! accelerometers, one of which loses batches and one of which sends truncated payloads, a
//! split-mode inclinometer with a tilt stream, and an uncalibrated node), their records in the
//! gateway's store (one of them made to expire in ten days), nodes publishing at 100 Hz in real time, and alerts published as
//! `triax-alert` does, one of them hostile. Headless Chromium (Debian's
//! `chromium` and `chromium-driver`, installed by `scripts/test`) is driven over the W3C
//! WebDriver protocol; screenshots go to `target/console-screenshots/`.
//!
//! - `console_in_a_browser`: the fleet view's states (a sensor whose samples are flagged says
//!   so, a building takes its worst state), an alert and its escaping, a live plot that moves,
//!   the tilt plot, a gap, the calibration record, the history around an alert and its steps
//!   (never past now), links that cannot be shown, a refusal told from an outage, and a
//!   gateway that goes away and comes back; no script error, no failed load on the way; and
//!   the details (units, k, ticks, times typed in ISO 8601 UTC, spans, sensor counts, an icon).
//! - `console_only_reads_and_refuses_what_it_must`: no put ever leaves the console; unknown
//!   paths, other methods, foreign Host headers, long heads, bad parameters and a non-loopback
//!   listener are refused.
//! - `one_sensor_status_carries_the_record_in_force`: what the console's calibration panel
//!   reads.
//! - `console_http_details` (issue 26): a page's first event carries the fleet; two Host
//!   headers, a 9 KiB query or header and a connection over the limit are answered with their
//!   status, and closed without a reset.

use std::io::{Read, Write};
use std::net::TcpStream as StdTcpStream;
use std::path::PathBuf;
use std::process::{Child, Command, Stdio};
use std::sync::Arc;
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use rand::rngs::StdRng;
use rand::SeedableRng;
use rand_distr::{Distribution, Normal};
use serde_json::{json, Value};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use triax_console::ConsoleOptions;
use triax_gateway::demo::{fleet, SimSensor};
use triax_net::{ZenohMode, ZenohSettings};
use triax_protocol::batch::{BatchHeader, RawBatch};
use triax_protocol::record::sample;
use triax_protocol::signing::{sign_alert, LabSigningKey, TrustedKeys};
use triax_protocol::{BuildingId, Key, SensorId};

use crate::util::*;

// ---- A minimal W3C WebDriver client ---------------------------------------------------------
//
// Four commands (new session, navigate, execute script, screenshot) over plain HTTP/1.1: a
// client crate would bring an HTTP stack and TLS into the build for them.

struct Browser {
    driver: Child,
    port: u16,
    session: String,
    /// The browser's process, killed if closing the session fails.
    browser_pid: Option<u64>,
    _profile: tempfile::TempDir,
}

fn http(port: u16, method: &str, path: &str, body: Option<&Value>) -> Value {
    let body = body.map(|b| b.to_string()).unwrap_or_default();
    let mut s = StdTcpStream::connect(("127.0.0.1", port)).expect("chromedriver answers");
    s.set_read_timeout(Some(Duration::from_secs(60))).unwrap();
    write!(
        s,
        "{method} {path} HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nContent-Type: application/json\r\nContent-Length: {}\r\nConnection: close\r\n\r\n{body}",
        body.len()
    )
    .unwrap();
    // Read the head, then exactly Content-Length bytes: chromedriver keeps the connection open.
    let mut raw = Vec::new();
    let mut byte = [0u8; 1];
    while !raw.ends_with(b"\r\n\r\n") {
        let n = s.read(&mut byte).expect("chromedriver response");
        assert!(n == 1, "chromedriver closed mid-response");
        raw.push(byte[0]);
    }
    let head = String::from_utf8_lossy(&raw).into_owned();
    let length: usize = head
        .lines()
        .find_map(|l| {
            let (k, v) = l.split_once(':')?;
            k.eq_ignore_ascii_case("content-length")
                .then(|| v.trim().parse().ok())?
        })
        .expect("chromedriver sends Content-Length");
    let mut body = vec![0u8; length];
    s.read_exact(&mut body).expect("chromedriver response body");
    let body = String::from_utf8_lossy(&body).into_owned();
    let v: Value = serde_json::from_str(&body).unwrap_or_else(|e| panic!("{e}: {body}"));
    assert!(
        head.starts_with("HTTP/1.1 200"),
        "WebDriver {method} {path}: {head}\n{v}"
    );
    v["value"].clone()
}

fn need(tool: &str) -> PathBuf {
    let found = std::env::var_os("PATH").and_then(|paths| {
        std::env::split_paths(&paths)
            .map(|d| d.join(tool))
            .find(|p| p.is_file())
    });
    found.unwrap_or_else(|| {
        panic!(
            "`{tool}` is not installed: the console's browser tests need Debian's chromium and \
             chromium-driver (scripts/test installs them: apt-get install -y chromium chromium-driver)"
        )
    })
}

impl Browser {
    fn start() -> Browser {
        let chromium = need("chromium");
        let driver_bin = need("chromedriver");
        let port = free_port();
        let driver = Command::new(driver_bin)
            .arg(format!("--port={port}"))
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .expect("chromedriver starts");
        let deadline = std::time::Instant::now() + TIMEOUT;
        while StdTcpStream::connect(("127.0.0.1", port)).is_err() {
            assert!(
                std::time::Instant::now() < deadline,
                "chromedriver did not listen"
            );
            std::thread::sleep(Duration::from_millis(50));
        }
        let profile = tempfile::tempdir().unwrap();
        let mut b = Browser {
            driver,
            port,
            session: String::new(),
            browser_pid: None,
            _profile: profile,
        };
        let caps = json!({"capabilities": {"alwaysMatch": {
            "browserName": "chrome",
            "goog:loggingPrefs": { "browser": "ALL" },
            "goog:chromeOptions": {
                "binary": chromium,
                "args": [
                    "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic",
                    "--no-first-run", "--disable-background-networking",
                    "--disable-component-update", "--disable-sync", "--disable-dev-shm-usage",
                    "--window-size=1400,1100",
                    format!("--user-data-dir={}", b._profile.path().display()),
                ]
            }
        }}});
        let v = http(port, "POST", "/session", Some(&caps));
        b.session = v["sessionId"].as_str().expect("a session id").to_owned();
        b.browser_pid = v["capabilities"]["goog:processID"].as_u64();
        b
    }

    fn cmd(&self, method: &str, what: &str, body: Option<Value>) -> Value {
        tokio::task::block_in_place(|| {
            http(
                self.port,
                method,
                &format!("/session/{}/{what}", self.session),
                body.as_ref(),
            )
        })
    }

    fn go(&self, url: &str) {
        self.cmd("POST", "url", Some(json!({ "url": url })));
    }

    fn js(&self, script: &str) -> Value {
        self.cmd(
            "POST",
            "execute/sync",
            Some(json!({ "script": script, "args": [] })),
        )
    }

    /// Polls `script` until it returns something truthy; fails naming `what` after `limit`.
    async fn wait(&self, what: &str, limit: Duration, script: &str) -> Value {
        let deadline = tokio::time::Instant::now() + limit;
        loop {
            let v = self.js(script);
            let truthy =
                !matches!(v, Value::Null | Value::Bool(false)) && v != json!(0) && v != json!("");
            if truthy {
                return v;
            }
            if tokio::time::Instant::now() > deadline {
                let page = self.js("return document.body.innerText.slice(0, 3000)");
                panic!(
                    "timed out waiting for {what}; the page shows:\n{}\nand logged {:#?}",
                    page.as_str().unwrap_or(""),
                    self.errors()
                );
            }
            tokio::time::sleep(Duration::from_millis(200)).await;
        }
    }

    /// Errors the page logged since the last call: uncaught exceptions and failed loads.
    fn errors(&self) -> Vec<String> {
        let v = self.cmd("POST", "se/log", Some(json!({ "type": "browser" })));
        v.as_array()
            .expect("a browser log")
            .iter()
            .filter(|e| e["level"] == "SEVERE")
            .map(|e| e["message"].as_str().unwrap_or_default().to_owned())
            .collect()
    }

    fn assert_no_errors(&self, when: &str) {
        let errors = self.errors();
        assert!(errors.is_empty(), "{when}: the page logged {errors:#?}");
    }

    fn screenshot(&self, name: &str) {
        let b64 = self.cmd("GET", "screenshot", None);
        let png = base64_decode(b64.as_str().expect("base64 screenshot"));
        let dir = screenshot_dir();
        std::fs::create_dir_all(&dir).unwrap();
        std::fs::write(dir.join(format!("{name}.png")), png).unwrap();
    }
}

impl Drop for Browser {
    fn drop(&mut self) {
        let closed = !self.session.is_empty()
            && std::panic::catch_unwind(|| {
                http(
                    self.port,
                    "DELETE",
                    &format!("/session/{}", self.session),
                    None,
                )
            })
            .is_ok();
        if let (false, Some(pid)) = (closed, self.browser_pid) {
            let _ = Command::new("kill").arg(pid.to_string()).status();
        }
        let _ = self.driver.kill();
        let _ = self.driver.wait();
    }
}

fn screenshot_dir() -> PathBuf {
    // CARGO_TARGET_TMPDIR is <target>/tmp.
    PathBuf::from(env!("CARGO_TARGET_TMPDIR"))
        .parent()
        .expect("target/tmp has a parent")
        .join("console-screenshots")
}

fn base64_decode(s: &str) -> Vec<u8> {
    let val = |c: u8| match c {
        b'A'..=b'Z' => c - b'A',
        b'a'..=b'z' => c - b'a' + 26,
        b'0'..=b'9' => c - b'0' + 52,
        b'+' => 62,
        b'/' => 63,
        _ => panic!("not base64: {c}"),
    };
    let bytes: Vec<u8> = s
        .bytes()
        .filter(|c| !b"=\r\n".contains(c))
        .map(val)
        .collect();
    let mut out = Vec::with_capacity(bytes.len() * 3 / 4);
    for chunk in bytes.chunks(4) {
        let mut acc = 0u32;
        for (i, v) in chunk.iter().enumerate() {
            acc |= u32::from(*v) << (18 - 6 * i);
        }
        out.extend_from_slice(&acc.to_be_bytes()[1..chunk.len()]);
    }
    out
}

// ---- The demo building ----------------------------------------------------------------------

fn now_ns() -> i64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .unwrap()
        .as_nanos() as i64
}

/// One of the demo's sensor nodes: outputs `V = S_static·(gravity part − q) + S_dynamic·sway`
/// plus noise, 50 samples every 0.5 s, losing or truncating batches as the demo's nodes do.
async fn node(session: zenoh::Session, sim: SimSensor, t0_ns: i64, stop: Arc<tokio::sync::Notify>) {
    let key = Key::Raw(BuildingId::new("demo").unwrap(), sim.id.clone()).to_string();
    let publisher = session.declare_publisher(key).await.unwrap();
    let noise = Normal::new(0.0, 0.002).unwrap();
    let mut rng = StdRng::seed_from_u64(sim.q_mps2[0].to_bits());
    let mut tick = tokio::time::interval(Duration::from_millis(500));
    for sequence in 0u64.. {
        tokio::select! {
            _ = stop.notified() => return,
            _ = tick.tick() => {}
        }
        let t_first = sequence as f64 * 0.5;
        let samples = (0..50)
            .map(|i| {
                let t = t_first + i as f64 / 100.0;
                let sway = sim
                    .sway
                    .map(|(f, a, phi)| a * (2.0 * std::f64::consts::PI * f * t + phi).sin());
                let truth = sim.truth_at(t);
                let d = [0, 1, 2].map(|k| truth[k] - sway[k] - sim.q_mps2[k]);
                [0, 1, 2].map(|r| {
                    let v: f64 = (0..3)
                        .map(|c| sim.s_static[r][c] * d[c] + sim.s_dynamic[r][c] * sway[c])
                        .sum();
                    (v + noise.sample(&mut rng)) as f32
                })
            })
            .collect();
        let batch = RawBatch {
            header: BatchHeader {
                sensor_id: sim.id.clone(),
                sequence,
                timestamp_ns: t0_ns + (t_first * 1e9) as i64,
                sample_rate_hz: 100.0,
            },
            temperature_c: Some(21.0),
            samples,
        };
        let n = sequence + 1;
        if sim.lose_every > 0 && n % sim.lose_every == 0 {
            continue;
        }
        let mut payload = batch.encode();
        if sim.malformed_every > 0 && n % sim.malformed_every == 0 {
            payload.truncate(payload.len() / 2);
        }
        let _ = publisher.put(payload).await;
    }
}

struct Demo {
    _dir: tempfile::TempDir,
    config: triax_gateway::Config,
    gateway: Option<Running>,
    stop_nodes: Arc<tokio::sync::Notify>,
    nodes: Vec<tokio::task::JoinHandle<()>>,
    node_session: zenoh::Session,
}

impl Demo {
    async fn start() -> Demo {
        let dir = tempfile::tempdir().unwrap();
        let store = dir.path().join("store");
        let sims = fleet(4, 2015);
        let mut records: Vec<_> = sims.iter().filter_map(|s| s.record.clone()).collect();
        // One record runs out in ten days: the fleet view must warn.
        for r in records
            .iter_mut()
            .filter(|r| r.sensor_id.as_str() == "acc-03")
        {
            r.valid_until = Some(time::OffsetDateTime::now_utc() + time::Duration::days(10));
        }
        seed_store(&store, &records);
        let mut config = config("demo", &store);
        for s in &sims {
            config.sensors.insert(s.id.clone(), s.settings.clone());
        }
        let gateway = start(config.clone()).await;
        let node_session = client(&gateway.endpoint).await;
        let stop_nodes = Arc::new(tokio::sync::Notify::new());
        let t0 = now_ns();
        let nodes = sims
            .into_iter()
            .map(|s| tokio::spawn(node(node_session.clone(), s, t0, stop_nodes.clone())))
            .collect();
        Demo {
            _dir: dir,
            config,
            gateway: Some(gateway),
            stop_nodes,
            nodes,
            node_session,
        }
    }

    fn endpoint(&self) -> String {
        self.config.zenoh.listen[0].clone()
    }

    async fn stop_gateway(&mut self) {
        if let Some(g) = self.gateway.take() {
            g.stop().await;
        }
    }

    async fn start_gateway(&mut self) {
        self.gateway = Some(start(self.config.clone()).await);
    }

    async fn stop(mut self) {
        self.stop_nodes.notify_waiters();
        for n in self.nodes.drain(..) {
            n.abort();
        }
        let _ = self.node_session.close().await;
        self.stop_gateway().await;
    }
}

struct Console {
    url: String,
    stop: Option<tokio::sync::oneshot::Sender<()>>,
    task: tokio::task::JoinHandle<Result<(), triax_console::ConsoleError>>,
    session: zenoh::Session,
}

impl Console {
    /// A console connected to every endpoint of `connect` (peers do not relay between other
    /// peers: whatever publishes alerts must be reachable from it directly, or via a router),
    /// trusting the alerting key `alert_key`.
    async fn start(connect: &[String], alert_key: &LabSigningKey) -> Console {
        let config = ZenohSettings::loopback(ZenohMode::Peer, vec![], connect.to_vec())
            .to_config()
            .unwrap();
        let session = zenoh::open(config).await.unwrap();
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
        let url = triax_console::url(listener.local_addr().unwrap());
        let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
        let options = ConsoleOptions {
            status_interval: Duration::from_secs(1),
            trusted_alert_keys: TrustedKeys::new(vec![alert_key.verifying_key()]),
            ..ConsoleOptions::default()
        };
        let task = tokio::spawn(triax_console::serve(
            session.clone(),
            listener,
            options,
            async {
                let _ = stopped.await;
            },
        ));
        Console {
            url,
            stop: Some(stop),
            task,
            session,
        }
    }

    async fn stop(mut self) {
        if let Some(s) = self.stop.take() {
            let _ = s.send(());
        }
        tokio::time::timeout(TIMEOUT, &mut self.task)
            .await
            .expect("console stops in time")
            .unwrap()
            .expect("console stops cleanly");
        let _ = self.session.close().await;
    }
}

const HOSTILE: &str =
    "<img src=x onerror=\"window.__pwned=1\"><script>window.__pwned=2</script>&amp; \"quoted\"";

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn console_in_a_browser() {
    let browser = tokio::task::block_in_place(Browser::start);
    let mut demo = Demo::start().await;
    // Where alerts come from: a peer the console connects to, as it would to an alerting
    // service's endpoint or a site router.
    let alerts_endpoint = format!("tcp/127.0.0.1:{}", free_port());
    let alerts = zenoh::open(
        ZenohSettings::loopback(ZenohMode::Peer, vec![alerts_endpoint.clone()], vec![])
            .to_config()
            .unwrap(),
    )
    .await
    .unwrap();
    // The alerting service's key, which the console is given; and a forger's.
    let service_key = LabSigningKey::from_bytes(&[11; 32]);
    let forger_key = LabSigningKey::from_bytes(&[12; 32]);
    let signed = |v: &Value, key: &LabSigningKey| {
        let alert: triax_protocol::messages::Alert = serde_json::from_value(v.clone()).unwrap();
        String::from_utf8(triax_protocol::to_json(&sign_alert(&alert, key))).unwrap()
    };
    let console = Console::start(&[demo.endpoint(), alerts_endpoint], &service_key).await;

    // Alerts as `triax-alert` publishes them (PROTOCOL.md §3.6): a genuine `exceeded` on acc-04,
    // and a hostile one on acc-03 whose free text tries to inject markup and script.
    let now = || {
        time::OffsetDateTime::now_utc()
            .format(&time::format_description::well_known::Rfc3339)
            .unwrap()
    };
    let exceeded = json!({
        "format_version": 1, "building": "demo", "sensor_id": "acc-04",
        "kind": "peak_acceleration", "level": "exceeded", "value": 0.31,
        "standard_uncertainty": 0.004, "coverage_factor": 2.0, "threshold": 0.2,
        "unit": "m/s^2", "window_s": 4.0, "flagged_fraction": 0.0,
        "statement": "peak 0.31 ± 0.008 m/s² (k = 2) is above the limit 0.2 m/s²", "at": now(),
    });
    let hostile = json!({
        "format_version": 1, "building": "demo", "sensor_id": "acc-03",
        "kind": "peak_acceleration", "level": "possible", "value": 0.98,
        "standard_uncertainty": 0.02, "coverage_factor": 2.0, "threshold": 1.0,
        "unit": "<b>m/s²</b>", "window_s": 4.0, "flagged_fraction": 0.0,
        "statement": HOSTILE, "at": now(),
    });
    let hostile_key = Key::Alert(
        BuildingId::new("demo").unwrap(),
        SensorId::new("acc-03").unwrap(),
    );

    // Fleet view: the six sensors and their states.
    browser.go(&console.url);
    let states = browser
        .wait(
            "the fleet view to list six sensors with gaps and flags seen",
            TIMEOUT,
            "const rows = [...document.querySelectorAll('tr.sensor')];
             if (rows.length !== 6) return null;
             const m = Object.fromEntries(rows.map(r => [r.dataset.sensor, r.dataset.states]));
             return m['acc-01'].includes('gaps') && m['acc-02'].includes('rejects')
                && m['acc-02'].includes('gaps') && m['acc-03'].includes('flagged') ? m : null;",
        )
        .await;
    let state = |s: &str| {
        states[s]
            .as_str()
            .unwrap()
            .split(' ')
            .map(String::from)
            .collect::<Vec<_>>()
    };
    assert_eq!(state("acc-new"), ["uncalibrated"], "{states}");
    assert_eq!(state("acc-01"), ["gaps"], "{states}");
    // A truncated payload is lost, so the batch after it follows a gap.
    assert_eq!(state("acc-02"), ["gaps", "rejects"], "{states}");
    // acc-03 uses its static set, calibrated to 1 Hz, on a 1–5 Hz sway: every batch is flagged
    // `outside_frequency`, and the fleet says so (issue 26).
    assert_eq!(state("acc-03"), ["flagged", "expiring"], "{states}");
    let shares = browser.js(
        "return Object.fromEntries([...document.querySelectorAll('tr.sensor')].map(r =>
           [r.dataset.sensor, r.querySelector('.flagged-share').textContent]));",
    );
    let share = |s: &str| -> f64 {
        let text = shares[s].as_str().unwrap();
        text.trim_end_matches(" %")
            .parse()
            .unwrap_or_else(|_| panic!("{shares}"))
    };
    assert!(share("acc-03") > 20.0, "{shares}");
    assert!(share("acc-04") < 20.0, "{shares}");
    assert!(share("acc-01") < 20.0, "a batch in 15 lost: {shares}");
    let warning = browser.js(
        "return document.querySelector('tr.sensor[data-sensor=\"acc-03\"]').children[9].textContent",
    );
    assert!(warning.as_str().unwrap().contains("in 10.0 d"), "{warning}");
    assert_eq!(state("incl-01"), ["ok"], "{states}");
    let building = browser.js(
        "const b = document.querySelector('section.building[data-building=demo]');
         return [b.dataset.state, b.querySelector('h2').textContent, b.dataset.worst,
                 b.querySelector('.sensor-count').textContent];",
    );
    assert_eq!(building[0], "up", "{building}");
    assert_eq!(
        building[2], "uncalibrated",
        "the worst of its sensors: {building}"
    );
    assert!(
        building[1].as_str().unwrap().contains("uncalibrated"),
        "{building}"
    );
    assert_eq!(building[3], "6 sensors", "{building}");
    // The first event carries the fleet (not null), and the icon is there: nothing failed.
    browser.assert_no_errors("the fleet view");
    let icon = browser.js(
        "const l = document.querySelector('link[rel=icon]'); return l && l.getAttribute('href');",
    );
    assert_eq!(icon, "/favicon.svg");
    browser.screenshot("fleet");

    // An alert from the alerting service shows on the fleet view; the hostile one is text.
    tokio::time::sleep(Duration::from_secs(2)).await;
    let acc04 = Key::Alert(
        BuildingId::new("demo").unwrap(),
        SensorId::new("acc-04").unwrap(),
    );
    // First a forgery: `exceeded` on acc-01, signed by a key the console does not trust.
    let mut forged = exceeded.clone();
    forged["sensor_id"] = json!("acc-01");
    alerts
        .put("triax/demo/alert/acc-01", signed(&forged, &forger_key))
        .await
        .unwrap();
    browser
        .wait(
            "acc-01's forged alert shown as unverified",
            TIMEOUT,
            "const r = document.querySelector('tr.sensor[data-sensor=\"acc-01\"]');
             return r && r.dataset.states.includes('unverified');",
        )
        .await;
    let acc01 = browser.js(
        "const r = document.querySelector('tr.sensor[data-sensor=\"acc-01\"]');
         return [r.dataset.states, r.children[10].textContent];",
    );
    assert!(
        !acc01[0].as_str().unwrap().contains("exceeded"),
        "a forged alert is never a verdict: {acc01}"
    );
    assert!(
        acc01[1]
            .as_str()
            .unwrap()
            .contains("unverified (claims exceeded)"),
        "{acc01}"
    );
    alerts
        .put(acc04.to_string(), signed(&exceeded, &service_key))
        .await
        .unwrap();
    browser
        .wait(
            "acc-04's alert on the fleet view",
            TIMEOUT,
            "const r = document.querySelector('tr.sensor[data-sensor=\"acc-04\"]');
             return r && r.dataset.states.includes('exceeded');",
        )
        .await;
    let worst = browser
        .js("return document.querySelector('section.building[data-building=demo]').dataset.worst");
    assert_eq!(worst, "exceeded", "the building takes its worst state");
    alerts
        .put(hostile_key.to_string(), hostile.to_string())
        .await
        .unwrap();
    // A sensor the gateway does not list, heard of in an alert: listed and counted.
    let stranger = json!({
        "format_version": 1, "building": "demo", "sensor_id": "acc-99",
        "kind": "peak_acceleration", "level": "possible", "value": 0.19,
        "standard_uncertainty": 0.01, "coverage_factor": 2.0, "threshold": 0.2,
        "unit": "m/s^2", "window_s": 4.0, "flagged_fraction": 0.0,
        "statement": "peak near the limit", "at": now(),
    });
    alerts
        .put("triax/demo/alert/acc-99", signed(&stranger, &service_key))
        .await
        .unwrap();
    let count = browser
        .wait(
            "the sensor known from an alert only",
            TIMEOUT,
            "const rows = document.querySelectorAll('tr.sensor');
             return rows.length === 7 ? document.querySelector('section.building[data-building=demo] .sensor-count').textContent : null;",
        )
        .await;
    assert_eq!(count, "7 sensors (1 known only from an alert)");
    browser.go(&format!("{}#/alerts", console.url));
    let shown = browser
        .wait(
            "the hostile alert in the alerts view",
            TIMEOUT,
            "const r = document.querySelector('tr.alert[data-sensor=\"acc-03\"]');
             return r && [r.querySelector('.statement').textContent, r.textContent,
                          document.querySelectorAll('#alerts img, #alerts script, #alerts b').length,
                          window.__pwned === undefined];",
        )
        .await;
    assert_eq!(
        shown[0], HOSTILE,
        "the statement is shown as text, verbatim"
    );
    assert!(
        shown[1].as_str().unwrap().contains("<b>m/s²</b>"),
        "{shown}"
    );
    assert_eq!(shown[2], 0, "no element injected");
    assert_eq!(shown[3], true, "no script ran");
    // The hostile alert is unsigned: shown as such, never with a verdict.
    let hostile_row = browser.js(
        "const r = document.querySelector('tr.alert[data-sensor=\"acc-03\"]');
         return [r.dataset.level, r.dataset.trust];",
    );
    assert_eq!(hostile_row, json!(["unverified", "unsigned"]));
    let verdicts = browser.js(
        "return [...document.querySelectorAll('tr.alert[data-sensor=\"acc-04\"]')].map(r => r.dataset.level + ' ' + r.children[4].textContent + ' vs ' + r.children[5].textContent)",
    );
    assert!(
        verdicts
            .as_array()
            .unwrap()
            .iter()
            .any(|v| v.as_str().unwrap().starts_with("exceeded ")),
        "{verdicts}"
    );
    for v in verdicts.as_array().unwrap() {
        let v = v.as_str().unwrap();
        assert!(
            v.contains("m/s²") && !v.contains("m/s^2"),
            "one way to write units: {v}"
        );
    }
    browser.screenshot("alerts");

    // The alert links to the sensor view at its time: the history around it.
    browser.js(
        "document.querySelector('tr.alert[data-level=exceeded][data-sensor=\"acc-04\"] a').click()",
    );
    let history = browser
        .wait(
            "the history around acc-04's alert",
            TIMEOUT,
            "const p = document.getElementById('plot');
             const line = document.getElementById('status-line').textContent;
             return p && p.dataset.source === 'history' && Number(p.dataset.buckets) > 50
                && line.startsWith('history:') ? [location.hash, line, Number(p.dataset.buckets)] : null;",
        )
        .await;
    assert!(history[0].as_str().unwrap().contains("?at="), "{history}");
    browser.screenshot("history-at-alert");
    // ▶ from a recent time goes as far as now, not into the future, and then stops.
    let stepped = browser.js(
        "const before = location.hash; document.getElementById('btn-fwd').click(); return before;",
    );
    let forward = browser
        .wait(
            "the history one step forward",
            TIMEOUT,
            &format!(
                "const p = document.getElementById('plot');
                 const line = document.getElementById('status-line').textContent;
                 return location.hash !== {stepped} && p && p.dataset.source === 'history'
                    && line.startsWith('history:')
                    ? [Number(new URLSearchParams(location.hash.split('?')[1]).get('at')) / 1e6,
                       Date.now(), Number(p.dataset.buckets),
                       document.getElementById('btn-fwd').disabled] : null;"
            ),
        )
        .await;
    let (at_ms, now_ms) = (forward[0].as_f64().unwrap(), forward[1].as_f64().unwrap());
    assert!(
        at_ms + 0.25 * 30_000.0 <= now_ms + 1.0,
        "the window ends by now: {forward}"
    );
    assert!(
        forward[2].as_u64().unwrap() > 50,
        "not an empty plot: {forward}"
    );
    assert_eq!(forward[3], true, "▶ stops at now: {forward}");
    browser.assert_no_errors("stepping the history");

    // A live plot that opens with the recent past (read from the history) and moves.
    let opened_ns = SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .unwrap()
        .as_nanos() as f64;
    browser.go(&format!("{}#/sensor/demo/acc-04", console.url));
    let filled = browser
        .wait(
            "the live window filled from the history",
            TIMEOUT,
            // 30 s over the plot's width: more than 12 s of buckets.
            "const p = document.getElementById('plot');
             if (!p || !p.dataset.endNs) return null;
             const c = document.getElementById('canvas-x').clientWidth;
             return Number(p.dataset.buckets) > 0.4 * c
                 ? [Number(p.dataset.endNs), Number(p.dataset.buckets), c] : null;",
        )
        .await;
    // A bucket holds 30 s / width of the stream, so the oldest data shown is at least this old:
    // from before the page opened, whenever the wait ended.
    let (end_ns, buckets, width) = (
        filled[0].as_f64().unwrap(),
        filled[1].as_f64().unwrap(),
        filled[2].as_f64().unwrap(),
    );
    let oldest_ns = end_ns - buckets * 30e9 / width;
    assert!(
        oldest_ns < opened_ns - 5e9,
        "the window starts {:.1} s after the page opened: not from the history",
        (oldest_ns - opened_ns) * 1e-9
    );
    let first = browser
        .wait(
            "live frames for acc-04",
            TIMEOUT,
            "const p = document.getElementById('plot');
             return p && Number(p.dataset.frames) >= 2 ? [Number(p.dataset.frames), Number(p.dataset.endNs), Number(p.dataset.buckets)] : null;",
        )
        .await;
    let moved = browser
        .wait(
            "the live plot to move",
            TIMEOUT,
            &format!(
                "const p = document.getElementById('plot');
                 return Number(p.dataset.frames) >= {} + 3 && Number(p.dataset.endNs) > {} ? Number(p.dataset.endNs) : null;",
                first[0], first[1]
            ),
        )
        .await;
    assert!(moved.as_f64().unwrap() > first[1].as_f64().unwrap());
    let inked = browser.js(
        "const c = document.getElementById('canvas-x'); const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;
         let n = 0; for (let i = 0; i < d.length; i += 4) if (d[i+3] > 0 && d[i+2] > 150 && d[i] < 80) n++; return n;",
    );
    assert!(
        inked.as_u64().unwrap() > 200,
        "the x axis is drawn in blue: {inked} pixels"
    );
    // Tick labels: one precision per axis, none under the title.
    let ticks = browser.js(
        "return ['x', 'y', 'z'].map(a => { const c = document.getElementById('canvas-' + a);
           return [c.dataset.yTicks, Number(c.dataset.yTickTop), Number(c.dataset.plotTop)]; });",
    );
    for axis in ticks.as_array().unwrap() {
        let labels: Vec<&str> = axis[0].as_str().unwrap().split(' ').collect();
        assert!(labels.len() >= 2, "{ticks}");
        let decimals = |l: &str| l.split_once('.').map_or(0, |(_, d)| d.len());
        assert!(
            labels.iter().all(|l| decimals(l) == decimals(labels[0])),
            "{ticks}"
        );
        assert!(
            axis[1].as_f64().unwrap() >= axis[2].as_f64().unwrap(),
            "{ticks}"
        );
    }
    let record = browser
        .wait(
            "the calibration record",
            TIMEOUT,
            "const r = document.getElementById('record'); return r && r.querySelector('dl') ? r.textContent : null;",
        )
        .await;
    let expected = sample::record("acc-04", 1);
    for part in [
        expected.certificate.id.as_str(),
        expected.lab.name.as_str(),
        "until superseded",
    ] {
        assert!(
            record.as_str().unwrap().contains(part),
            "{part} in {record}"
        );
    }
    let own_alerts = browser.js(
        "return [...document.querySelectorAll('#sensor-alerts tr.alert')].map(r => r.dataset.level)",
    );
    assert!(
        own_alerts
            .as_array()
            .unwrap()
            .iter()
            .any(|l| l == "exceeded"),
        "the sensor view lists its alerts: {own_alerts}"
    );
    browser.screenshot("sensor-live");

    // The inclinometer's tilt, and a gap drawn as a gap.
    browser.go(&format!("{}#/sensor/demo/incl-01", console.url));
    browser
        .wait(
            "tilt points for incl-01",
            TIMEOUT,
            "const p = document.getElementById('plot'); const t = document.getElementById('tilt-plot');
             return p && Number(p.dataset.tiltPoints) >= 2 && !t.hidden;",
        )
        .await;
    let k = browser
        .wait(
            "incl-01's coverage factor",
            TIMEOUT,
            "const h = document.getElementById('sensor-header').textContent;
             const l = document.getElementById('legend').textContent;
             return h.includes('k = ') && l.includes('k = ') ? [h, l] : null;",
        )
        .await;
    for text in k.as_array().unwrap() {
        let text = text.as_str().unwrap();
        let k = text.split("k = ").nth(1).unwrap();
        let k: String = k
            .chars()
            .take_while(|c| c.is_ascii_digit() || *c == '.')
            .collect();
        assert!(
            k.replace('.', "").trim_start_matches('0').len() <= 3,
            "k to three digits: {text}"
        );
    }
    browser.screenshot("sensor-tilt");
    browser.go(&format!("{}#/sensor/demo/acc-01", console.url));
    browser
        .wait(
            "a gap in acc-01's live plot",
            TIMEOUT,
            "const p = document.getElementById('plot'); return p && Number(p.dataset.gaps) >= 1;",
        )
        .await;
    browser.screenshot("sensor-gap");
    // The sensor view says what the fleet says: acc-03's samples are flagged.
    browser.go(&format!("{}#/sensor/demo/acc-03", console.url));
    let flagged = browser
        .wait(
            "acc-03's flagged state and share in its view",
            TIMEOUT,
            "const h = document.getElementById('sensor-header');
             const f = document.getElementById('flagged-share');
             return h && h.querySelector('.badge.flagged') && f ? f.textContent : null;",
        )
        .await;
    let flagged = flagged.as_str().unwrap();
    let percent: f64 = flagged.trim_end_matches(" % flagged").parse().unwrap();
    assert!(percent > 20.0, "{flagged}");
    browser.screenshot("sensor-flagged");
    browser.assert_no_errors("the sensor views");

    // Links that cannot be shown say why, rather than throw and leave the previous view up.
    browser.go(&console.url);
    browser
        .wait(
            "the fleet view",
            TIMEOUT,
            "return document.querySelectorAll('tr.sensor').length > 0",
        )
        .await;
    let now_ns = now_ns();
    for (link, says) in [
        ("at=abc&span=30".to_owned(), "at=abc is not a time"),
        (
            format!("at={}&span=30", now_ns + 3_600_000_000_000),
            "is in the future",
        ),
        (
            format!("at={}&span=0", now_ns - 60_000_000_000),
            "span=0 is not",
        ),
    ] {
        let error = browser
            .wait(
                &format!("the sensor view to refuse {link}"),
                TIMEOUT,
                &format!(
                    "if (!location.hash.endsWith({link:?})) location.hash = '#/sensor/demo/acc-04?' + {link:?};
                     const e = document.querySelector('#sensor #status-line[data-error]');
                     return e && e.textContent.includes({says:?}) && e.textContent;"
                ),
            )
            .await;
        assert!(
            error
                .as_str()
                .unwrap()
                .starts_with("This link cannot be shown"),
            "{link}: {error}"
        );
    }
    browser.screenshot("sensor-bad-link");
    // A span that is not one of the list's is shown as itself.
    let seven_at = now_ns - 60_000_000_000;
    browser.go(&format!(
        "{}#/sensor/demo/acc-04?at={seven_at}&span=7",
        console.url
    ));
    let span = browser
        .wait(
            "a 7 s history view",
            TIMEOUT,
            "const s = document.getElementById('span');
             const line = document.getElementById('status-line').textContent;
             return s && line.startsWith('history:') ? s.options[s.selectedIndex].textContent : null;",
        )
        .await;
    assert_eq!(span, "7 s");
    // The time is typed in ISO 8601 UTC, as the page writes it, and checked.
    let input = browser.js("const i = document.getElementById('at'); return [i.type, i.value];");
    assert_eq!(input[0], "text", "{input}");
    let value = input[1].as_str().unwrap();
    assert!(
        value.len() == 19 && value.as_bytes()[4] == b'-' && value.as_bytes()[10] == b' ',
        "YYYY-MM-DD HH:MM:SS: {input}"
    );
    let refused = browser.js(
        "const i = document.getElementById('at'); i.value = '01/15/2027 8:00 AM';
         document.getElementById('btn-go').click();
         return [i.getAttribute('aria-invalid'), document.getElementById('status-line').textContent];",
    );
    assert_eq!(refused[0], "true", "{refused}");
    assert!(
        refused[1].as_str().unwrap().contains("is not a time like"),
        "{refused}"
    );
    let earlier =
        time::OffsetDateTime::from_unix_timestamp_nanos(i128::from(now_ns) - 120_000_000_000)
            .unwrap();
    let typed = format!(
        "{:04}-{:02}-{:02} {:02}:{:02}:{:02}",
        earlier.year(),
        u8::from(earlier.month()),
        earlier.day(),
        earlier.hour(),
        earlier.minute(),
        earlier.second()
    );
    browser.js(&format!(
        "const i = document.getElementById('at'); i.value = {typed:?}; document.getElementById('btn-go').click();"
    ));
    let at = browser
        .wait(
            "the typed time in the link",
            TIMEOUT,
            &format!(
                "const a = new URLSearchParams(location.hash.split('?')[1] || '').get('at');
                 return a && a !== '{seven_at}' && document.getElementById('at').value;"
            ),
        )
        .await;
    assert_eq!(at, typed.as_str());
    browser.assert_no_errors("links and typed times");

    // A refusal is told from an outage: a bad sensor id is the console's 400, not a lost line.
    browser.go(&format!("{}#/sensor/demo/acc.04", console.url));
    let refusal = browser
        .wait(
            "the refusal of a bad sensor id",
            TIMEOUT,
            "const c = document.getElementById('conn');
             return c.dataset.state === 'refused' ? c.textContent : null;",
        )
        .await;
    let refusal = refusal.as_str().unwrap();
    assert!(
        refusal.contains("400") && refusal.contains("\"sensor\""),
        "{refusal}"
    );
    browser.screenshot("sensor-refused");
    let errors: Vec<String> = browser
        .errors()
        .into_iter()
        .filter(|e| !e.contains("status of 400"))
        .collect();
    assert!(errors.is_empty(), "{errors:#?}");

    // The gateway goes away and comes back; the page stays connected and follows.
    browser.go(&console.url);
    demo.stop_gateway().await;
    browser
        .wait(
            "the gateway shown down",
            TIMEOUT,
            "const b = document.querySelector('section.building[data-building=demo]');
             return b && b.dataset.state === 'down' && document.getElementById('conn').dataset.state === 'open';",
        )
        .await;
    browser.screenshot("gateway-down");
    demo.start_gateway().await;
    browser
        .wait(
            "the gateway shown up again",
            TIMEOUT,
            "const b = document.querySelector('section.building[data-building=demo]');
             return b && b.dataset.state === 'up' && document.querySelectorAll('tr.sensor').length === 7;",
        )
        .await;
    browser.go(&format!("{}#/sensor/demo/acc-04", console.url));
    browser
        .wait(
            "live frames again after the gateway came back",
            TIMEOUT,
            "const p = document.getElementById('plot'); return p && Number(p.dataset.frames) >= 3;",
        )
        .await;
    browser.screenshot("gateway-back");

    drop(browser);
    alerts.close().await.unwrap();
    console.stop().await;
    demo.stop().await;
}

/// Sends raw bytes to the console and returns its status code and body.
async fn raw_http(addr: std::net::SocketAddr, request: &[u8]) -> (u16, String) {
    let mut s = tokio::net::TcpStream::connect(addr).await.unwrap();
    s.write_all(request).await.unwrap();
    let mut out = Vec::new();
    let _ = tokio::time::timeout(TIMEOUT, s.read_to_end(&mut out)).await;
    let text = String::from_utf8_lossy(&out).into_owned();
    let code = text
        .get(9..12)
        .and_then(|c| c.parse().ok())
        .unwrap_or_else(|| panic!("no status line: {text:?}"));
    (code, text)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn console_only_reads_and_refuses_what_it_must() {
    let endpoint = format!("tcp/127.0.0.1:{}", free_port());
    // A spy listening where the console connects: it sees every put the console makes.
    let spy_config = ZenohSettings::loopback(ZenohMode::Peer, vec![endpoint.clone()], vec![])
        .to_config()
        .unwrap();
    let spy = zenoh::open(spy_config).await.unwrap();
    let seen = Arc::new(std::sync::atomic::AtomicU64::new(0));
    let s2 = seen.clone();
    let _sub = spy
        .declare_subscriber("**")
        .callback(move |_| {
            s2.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        })
        .await
        .unwrap();
    let session = client(&endpoint).await;
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = listener.local_addr().unwrap();
    let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
    let task = tokio::spawn(triax_console::serve(
        session.clone(),
        listener,
        ConsoleOptions {
            status_interval: Duration::from_millis(200),
            max_streams: 1,
            ..ConsoleOptions::default()
        },
        async {
            let _ = stopped.await;
        },
    ));
    let get = |path: &str| {
        format!(
            "GET {path} HTTP/1.1\r\nHost: 127.0.0.1:{}\r\n\r\n",
            addr.port()
        )
    };

    let (code, body) = raw_http(addr, get("/").as_bytes()).await;
    assert_eq!(code, 200);
    assert!(body.contains("Content-Security-Policy: default-src 'none'; script-src 'self'"));
    let (code, body) = raw_http(addr, get("/api/fleet").as_bytes()).await;
    assert_eq!(code, 200, "{body}");
    let (code, body) = raw_http(addr, get("/favicon.svg").as_bytes()).await;
    assert_eq!(code, 200, "{body}");
    assert!(body.contains("Content-Type: image/svg+xml"), "{body}");
    for (request, expected, says) in [
        (get("/etc/passwd"), 404, "no such page"),
        (
            get("/api/sensor?building=hq"),
            400,
            "\"sensor\" is required",
        ),
        (
            get("/api/sensor?building=hq&sensor=a/b"),
            400,
            "parameter \"sensor\"",
        ),
        (get("/api/fleet?x=1"), 400, "unknown parameter \"x\""),
        (get("/events?span_s=99999"), 400, "\"span_s\""),
        (
            get("/api/history?building=hq&sensor=s&from_ns=0&to_ns=99999999999999"),
            400,
            "at most 3600 s",
        ),
        (
            get("/api/history?building=hq&sensor=s&from_ns=0&to_ns=10&calibration=old"),
            400,
            "\"calibration\"",
        ),
        (
            "POST /api/fleet HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Length: 2\r\n\r\n{}".into(),
            405,
            "only reads",
        ),
        (
            "GET / HTTP/1.1\r\nHost: evil.example:80\r\n\r\n".into(),
            403,
            "loopback name",
        ),
        ("GET / HTTP/1.1\r\n\r\n".into(), 403, "loopback name"),
        (
            format!("GET /{} HTTP/1.1\r\n\r\n", "a".repeat(10_000)),
            431,
            "longer than",
        ),
    ] {
        let (code, body) = raw_http(addr, request.as_bytes()).await;
        assert_eq!(code, expected, "{request:.60}: {body}");
        assert!(body.contains(says), "{request:.60}: {body}");
    }
    // A live stream on a sensor (subscribes, never puts); a second one is over the limit.
    let mut sse = tokio::net::TcpStream::connect(addr).await.unwrap();
    sse.write_all(get("/events?building=hq&sensor=acc-01").as_bytes())
        .await
        .unwrap();
    let mut head = [0u8; 64];
    let n = tokio::time::timeout(TIMEOUT, sse.read(&mut head))
        .await
        .unwrap()
        .unwrap();
    assert!(String::from_utf8_lossy(&head[..n]).starts_with("HTTP/1.1 200"));
    let (code, body) = raw_http(addr, get("/events").as_bytes()).await;
    assert_eq!(
        (code, body.contains("too many live streams")),
        (503, true),
        "{body}"
    );
    tokio::time::sleep(Duration::from_secs(1)).await;
    drop(sse);
    let (code, body) = raw_http(
        addr,
        get("/api/history?building=hq&sensor=acc-01&from_ns=1800000000000000000&to_ns=1800000001000000000").as_bytes(),
    )
    .await;
    assert_eq!(code, 200, "{body}");
    assert!(body.contains("\"error\""), "no gateway answers: {body}");
    stop.send(()).unwrap();
    task.await.unwrap().unwrap();
    assert_eq!(
        seen.load(std::sync::atomic::Ordering::Relaxed),
        0,
        "the console put something"
    );

    // Not on a non-loopback address unless told to.
    let wide = tokio::net::TcpListener::bind("0.0.0.0:0").await.unwrap();
    let e = triax_console::serve(session.clone(), wide, ConsoleOptions::default(), async {})
        .await
        .unwrap_err();
    assert!(
        matches!(e, triax_console::ConsoleError::NotLoopback { .. }),
        "{e}"
    );
    assert!(e.to_string().contains("no authentication"), "{e}");
    session.close().await.unwrap();
    spy.close().await.unwrap();
}

/// Sends `request` and reads the answer to its end: its status, its text, and whether the
/// connection ended with a close rather than a reset (which may cost a client the answer).
async fn exchange(addr: std::net::SocketAddr, request: &[u8]) -> (u16, String, bool) {
    let mut s = tokio::net::TcpStream::connect(addr).await.unwrap();
    s.write_all(request).await.unwrap();
    let mut out = Vec::new();
    let ended = tokio::time::timeout(TIMEOUT, s.read_to_end(&mut out))
        .await
        .expect("the console closes the connection");
    let text = String::from_utf8_lossy(&out).into_owned();
    let code = text
        .get(9..12)
        .and_then(|c| c.parse().ok())
        .unwrap_or_else(|| panic!("no status line: {text:?} ({ended:?})"));
    (code, text, ended.is_ok())
}

/// A console on a Zenoh session of its own (nothing to watch: these are HTTP matters).
async fn lone_console(
    options: ConsoleOptions,
) -> (
    std::net::SocketAddr,
    tokio::sync::oneshot::Sender<()>,
    tokio::task::JoinHandle<Result<(), triax_console::ConsoleError>>,
    zenoh::Session,
) {
    let session = zenoh::open(
        ZenohSettings::loopback(ZenohMode::Peer, vec![], vec![])
            .to_config()
            .unwrap(),
    )
    .await
    .unwrap();
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = listener.local_addr().unwrap();
    let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
    let task = tokio::spawn(triax_console::serve(
        session.clone(),
        listener,
        options,
        async {
            let _ = stopped.await;
        },
    ));
    (addr, stop, task, session)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn console_http_details() {
    let (addr, stop, task, session) = lone_console(ConsoleOptions::default()).await;
    let host = format!("Host: 127.0.0.1:{}", addr.port());

    // A page's first event is the fleet, even from a console no page has opened yet.
    let mut sse = tokio::net::TcpStream::connect(addr).await.unwrap();
    sse.write_all(format!("GET /events HTTP/1.1\r\n{host}\r\n\r\n").as_bytes())
        .await
        .unwrap();
    let mut got = Vec::new();
    let first = loop {
        let mut chunk = [0u8; 4096];
        let n = tokio::time::timeout(TIMEOUT, sse.read(&mut chunk))
            .await
            .expect("the first event in time")
            .unwrap();
        assert!(n > 0, "the stream ended: {}", String::from_utf8_lossy(&got));
        got.extend_from_slice(&chunk[..n]);
        let text = String::from_utf8_lossy(&got);
        if let Some(rest) = text.split("event: fleet\ndata: ").nth(1) {
            if let Some((data, _)) = rest.split_once('\n') {
                break data.to_owned();
            }
        }
    };
    let fleet: Value = serde_json::from_str(&first).unwrap();
    assert!(fleet["buildings"].is_array(), "{first}");
    drop(sse);

    // Two Host headers, the foreign one first: refused, not the last one believed.
    let (code, body, _) = exchange(
        addr,
        format!("GET / HTTP/1.1\r\nHost: evil.example\r\n{host}\r\n\r\n").as_bytes(),
    )
    .await;
    assert_eq!(code, 400, "{body}");
    assert!(body.contains("more than one Host header"), "{body}");

    // A 9 KiB query or header: 431, and the answer is not lost to a reset.
    for request in [
        format!(
            "GET /?q={} HTTP/1.1\r\n{host}\r\n\r\n",
            "a".repeat(9 * 1024)
        ),
        format!(
            "GET / HTTP/1.1\r\n{host}\r\nX-Long: {}\r\n\r\n",
            "a".repeat(9 * 1024)
        ),
    ] {
        let (code, body, clean) = exchange(addr, request.as_bytes()).await;
        assert_eq!(code, 431, "{request:.40}: {body}");
        assert!(body.contains("longer than 8192 bytes"), "{body}");
        assert!(clean, "{request:.40}: the connection was reset");
    }
    stop.send(()).unwrap();
    task.await.unwrap().unwrap();
    session.close().await.unwrap();

    // The connection over the limit is answered 503 (and closed cleanly), not dropped silently.
    let (addr, stop, task, session) = lone_console(ConsoleOptions {
        max_connections: 2,
        ..ConsoleOptions::default()
    })
    .await;
    // Two connections that say nothing hold the two places; the console accepts in order.
    let idle = [
        tokio::net::TcpStream::connect(addr).await.unwrap(),
        tokio::net::TcpStream::connect(addr).await.unwrap(),
    ];
    let (code, body, clean) = exchange(
        addr,
        format!(
            "GET /api/fleet HTTP/1.1\r\nHost: 127.0.0.1:{}\r\n\r\n",
            addr.port()
        )
        .as_bytes(),
    )
    .await;
    assert_eq!(code, 503, "{body}");
    assert!(body.contains("too many connections at once (2)"), "{body}");
    assert!(clean, "the 503 was reset");
    drop(idle);
    stop.send(()).unwrap();
    task.await.unwrap().unwrap();
    session.close().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn one_sensor_status_carries_the_record_in_force() {
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("store");
    let mut r = sample::record("rec-1", 2);
    r.valid_until = Some(r.valid_from + time::Duration::days(400));
    r.lab.name = "Lab <with> \"free\" text".into();
    seed_store(&store, &[r.clone(), sample::record("rec-2", 1)]);
    let gw = start(config("rec", &store)).await;
    let session = client(&gw.endpoint).await;
    let ask = |selector: String| {
        let session = session.clone();
        async move {
            let replies = session.get(selector).timeout(TIMEOUT).await.unwrap();
            let reply = replies.recv_async().await.unwrap();
            let sample = reply.result().expect("status answered");
            triax_protocol::from_json::<triax_protocol::messages::GatewayStatus>(
                &sample.payload().to_bytes(),
            )
            .unwrap()
        }
    };
    let one = ask("triax/rec/status?sensor=rec-1".into()).await;
    let s = &one.sensors[0];
    assert_eq!(s.calibration_version, Some(2));
    assert_eq!(s.valid_from, Some(r.valid_from));
    assert_eq!(s.valid_until, r.valid_until);
    assert_eq!(
        s.calibration_record.as_deref(),
        Some(&r),
        "the record in force, whole"
    );
    let all = ask("triax/rec/status".into()).await;
    assert_eq!(all.sensors.len(), 2);
    assert!(
        all.sensors
            .iter()
            .all(|s| s.calibration_record.is_none() && s.valid_from.is_some()),
        "pages carry validity, not records"
    );
    assert_eq!(all.sensors[1].valid_until, None, "until superseded");
    session.close().await.unwrap();
    gw.stop().await;
}
