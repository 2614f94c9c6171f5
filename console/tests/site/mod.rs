//! What the console's tests run it against: a site of one Zenoh peer that answers history
//! queries for a few sensors with generated batches and publishes signed alerts, the console
//! itself in the test's runtime, a plain HTTP client, and a W3C WebDriver client for headless
//! Chromium (Debian's `chromium` and `chromium-driver`).

#![allow(dead_code)]

use std::io::{Read, Write};
use std::net::TcpStream as StdTcpStream;
use std::path::PathBuf;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use serde_json::{json, Value};
use triax_console::ConsoleOptions;
use triax_net::{ZenohMode, ZenohSettings};
use triax_protocol::batch::{
    flags, BatchHeader, CorrectedBatch, CorrectedSample, CorrectionInfo, Mode,
};
use triax_protocol::messages::Alert;
use triax_protocol::signing::{sign_alert, LabSigningKey, TrustedKeys};
use triax_protocol::{from_json, to_json, BuildingId, SensorId};
use zenoh::Wait;

/// Longest wait for anything in these tests.
pub const TIMEOUT: Duration = Duration::from_secs(60);

pub fn now_ns() -> i64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .unwrap()
        .as_nanos() as i64
}

pub fn free_port() -> u16 {
    triax_net::free_loopback_port().expect("loopback is available")
}

/// The alerting service's key.
pub fn service_key() -> LabSigningKey {
    LabSigningKey::from_bytes(&[42; 32])
}

/// Sample rate of the generated sensors.
pub const RATE_HZ: f64 = 100.0;
/// Samples per generated batch.
pub const BATCH: usize = 50;
/// Amplitude of the generated sway on x, m/s², and its frequency.
pub const SWAY_MPS2: f64 = 0.05;
pub const SWAY_HZ: f64 = 2.5;
/// Standard uncertainty of every generated sample, m/s², and k.
pub const U_MPS2: f32 = 0.004;
pub const K: f32 = 2.0;

/// The generated value of axis `axis` at `t_ns` for sensor number `n`: a sway at
/// [`SWAY_HZ`] on x (phase shifted per sensor), a slower one on y, gravity on z, and a
/// deterministic noise.
pub fn value(n: usize, axis: usize, t_ns: i64) -> f32 {
    let t = t_ns as f64 / 1e9;
    let w = 2.0 * std::f64::consts::PI;
    let noise = ((t_ns / 10_000_000).wrapping_mul(2_654_435_761) % 1000) as f64 / 1000.0 - 0.5;
    (match axis {
        0 => SWAY_MPS2 * (w * SWAY_HZ * t + n as f64).sin() + 0.004 * noise,
        1 => 0.02 * (w * 0.7 * t).sin() + 0.004 * noise,
        _ => 9.81 + 0.004 * noise,
    }) as f32
}

/// Batch `seq` of sensor number `n`, whose stream starts at `t0_ns`. Every 7th batch carries
/// `outside_frequency` on its first ten samples.
pub fn batch(n: usize, sensor: &str, t0_ns: i64, seq: u64) -> CorrectedBatch {
    let start = t0_ns + seq as i64 * (BATCH as i64 * 1_000_000_000 / RATE_HZ as i64);
    let period = (1e9 / RATE_HZ) as i64;
    let flagged = seq % 7 == 3;
    let samples: Vec<CorrectedSample> = (0..BATCH)
        .map(|i| {
            let t = start + i as i64 * period;
            CorrectedSample {
                accel_mps2: [0, 1, 2].map(|a| value(n, a, t)),
                uncertainty_mps2: [U_MPS2; 3],
                flags: if flagged && i < 10 {
                    flags::OUTSIDE_FREQUENCY
                } else {
                    0
                },
            }
        })
        .collect();
    CorrectedBatch {
        header: BatchHeader {
            sensor_id: SensorId::new(sensor).unwrap(),
            sequence: seq,
            timestamp_ns: start,
            sample_rate_hz: RATE_HZ,
        },
        batch_flags: if flagged { flags::OUTSIDE_FREQUENCY } else { 0 },
        info: CorrectionInfo {
            calibration_version: 4,
            mode: Mode::Dynamic,
            coverage_factor: K,
        },
        samples,
    }
}

/// A site: one Zenoh peer listening on loopback, answering history queries of building `hq`
/// for `SENSORS` from `t0_ns` to the time of the query.
pub struct Site {
    pub endpoint: String,
    pub session: zenoh::Session,
    pub t0_ns: i64,
    _history: zenoh::query::Queryable<()>,
    _status: zenoh::query::Queryable<()>,
    /// What the status says of a sensor besides `ok`: `"silent"` (its last batch a minute
    /// old) or `"suspect"` (the field health checks' verdict).
    pub conditions: Conditions,
}

pub type Conditions =
    std::sync::Arc<std::sync::Mutex<std::collections::HashMap<String, &'static str>>>;

pub const SENSORS: [&str; 3] = ["acc-01", "acc-02", "acc-03"];

fn param<'a>(params: &'a str, name: &str) -> Option<&'a str> {
    params
        .split([';', '&'])
        .find_map(|p| p.strip_prefix(name)?.strip_prefix('='))
}

impl Site {
    /// Starts the site; its history begins `history_s` seconds ago.
    pub async fn start(history_s: i64) -> Site {
        let port = free_port();
        let endpoint = format!("tcp/127.0.0.1:{port}");
        let config = ZenohSettings::loopback(ZenohMode::Peer, vec![endpoint.clone()], vec![])
            .to_config()
            .unwrap();
        let session = zenoh::open(config).await.unwrap();
        let period_ns = BATCH as i64 * 1_000_000_000 / RATE_HZ as i64;
        // Batches start on whole multiples of their length, as a node's would after a while.
        let t0_ns = (now_ns() - history_s * 1_000_000_000) / period_ns * period_ns;
        let history = session
            .declare_queryable("triax/hq/history/*")
            // Each query answered from a thread of its own, as a gateway answers from its replay
            // thread: a callback sending thousands of replies with block congestion control holds
            // the site's receive thread, and everything else its session hears, until the console
            // has taken them all.
            .callback(move |q| {
                std::thread::spawn(move || answer_history(q, t0_ns, period_ns));
            })
            .await
            .unwrap();
        // The gateway's status, as a gateway answers it: counters that grow with time.
        let started = time::OffsetDateTime::now_utc();
        let conditions: Conditions = Default::default();
        let cond = conditions.clone();
        let status = session
            .declare_queryable("triax/hq/status")
            .callback(move |q| {
                let rfc = |t: time::OffsetDateTime| {
                    t.format(&time::format_description::well_known::Rfc3339)
                        .unwrap()
                };
                let now = time::OffsetDateTime::now_utc();
                let batches = ((now_ns() - t0_ns) / period_ns) as u64;
                let sensors: Vec<Value> = SENSORS
                    .iter()
                    .map(|s| {
                        let c = cond.lock().unwrap().get(*s).copied();
                        let seen = if c == Some("silent") {
                            now - time::Duration::MINUTE
                        } else {
                            now
                        };
                        json!({
                            "sensor_id": s, "last_seen": rfc(seen), "batches": batches,
                            "health": if c == Some("suspect") { json!("suspect") } else { Value::Null },
                            "samples": batches * BATCH as u64, "gaps": 0, "missing_batches": 0,
                            "late_batches": 0, "duplicates": 0, "rejects": 0,
                            "flagged_samples": batches / 7 * 10, "keys_declared": true,
                            "calibration_version": 4, "mode": "dynamic",
                            "valid_from": rfc(now - time::Duration::DAY), "valid_until": null,
                        })
                    })
                    .collect();
                let body = json!({
                    "format_version": 1, "building": "hq", "gateway": "gw-hq",
                    "started_at": rfc(started), "reported_at": rfc(now), "malformed": 0,
                    "dropped": 0, "pushes_accepted": 0, "pushes_refused": 0,
                    "total_sensors": SENSORS.len(), "sensors": sensors,
                });
                let _ = q.reply("triax/hq/status", body.to_string()).wait();
            })
            .await
            .unwrap();
        Site {
            endpoint,
            session,
            t0_ns,
            _history: history,
            _status: status,
            conditions,
        }
    }

    /// Publishes an alert on `sensor` as `triax-alert` does, signed by [`service_key`]
    /// (or unsigned), judging the window `[start, end]`.
    pub async fn alert(
        &self,
        sensor: &str,
        level: &str,
        statement: &str,
        window: (i64, i64),
        signed: bool,
    ) {
        self.alert_in("hq", sensor, level, statement, window, signed)
            .await
    }

    /// [`Site::alert`] in another building.
    pub async fn alert_in(
        &self,
        building: &str,
        sensor: &str,
        level: &str,
        statement: &str,
        window: (i64, i64),
        signed: bool,
    ) {
        let a: Alert = from_json(
            &serde_json::to_vec(&json!({
                "format_version": 1, "building": building, "sensor_id": sensor,
                "kind": "peak_acceleration", "level": level, "value": 0.052,
                "standard_uncertainty": 0.002, "coverage_factor": 2.0, "threshold": 0.045,
                "unit": "m/s^2", "window_s": (window.1 - window.0) as f64 / 1e9,
                "flagged_fraction": 0.0, "statement": statement,
                "at": time::OffsetDateTime::now_utc()
                    .format(&time::format_description::well_known::Rfc3339)
                    .unwrap(),
                "window_start_ns": window.0, "window_end_ns": window.1,
            }))
            .unwrap(),
        )
        .unwrap();
        let payload = if signed {
            to_json(&sign_alert(&a, &service_key()))
        } else {
            to_json(&a)
        };
        self.session
            .put(format!("triax/{building}/alert/{sensor}"), payload)
            .congestion_control(zenoh::qos::CongestionControl::Block)
            .await
            .unwrap();
    }
}

/// A console serving in the background.
pub struct Console {
    pub addr: std::net::SocketAddr,
    stop: Option<tokio::sync::oneshot::Sender<()>>,
    task: Option<tokio::task::JoinHandle<()>>,
    /// The session cookie its requests send (`name=value`), once logged in.
    cookie: std::sync::Mutex<Option<String>>,
}

/// The password of every operator the tests make.
pub const PASSWORD: &str = "correct horse battery";

/// Writes an operators file with `accounts` (name, role), each with [`PASSWORD`]; an account
/// whose role ends in `!` has no password (named by a proxy only).
pub fn write_operators(path: &std::path::Path, accounts: &[(&str, &str)]) {
    use triax_console::operators::{hash_password, write_accounts, Account, Role};
    let accounts: Vec<Account> = accounts
        .iter()
        .map(|(name, role)| Account {
            name: (*name).into(),
            role: Role::parse(role.trim_end_matches('!')).unwrap(),
            hash: (!role.ends_with('!')).then(|| hash_password(PASSWORD).unwrap()),
        })
        .collect();
    write_accounts(path, &accounts).unwrap();
}

impl Console {
    pub async fn start(site: &Site, state_dir: Option<PathBuf>) -> Console {
        Console::start_with(site, state_dir, |_| {}).await
    }

    /// [`Console::start`] with options changed by `change`.
    pub async fn start_with(
        site: &Site,
        state_dir: Option<PathBuf>,
        change: impl FnOnce(&mut ConsoleOptions),
    ) -> Console {
        let config = ZenohSettings::loopback(ZenohMode::Peer, vec![], vec![site.endpoint.clone()])
            .to_config()
            .unwrap();
        let session = zenoh::open(config).await.unwrap();
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
        let addr = listener.local_addr().unwrap();
        let options = ConsoleOptions {
            buildings: vec![BuildingId::new("hq").unwrap()],
            trusted_alert_keys: TrustedKeys::new(vec![service_key().verifying_key()]),
            state_dir,
            // Tests run side by side, unoptimised, on small machines: a history page may take
            // longer than an operator would wait.
            history_timeout: TIMEOUT,
            ..ConsoleOptions::default()
        };
        let mut options = options;
        change(&mut options);
        let (tx, rx) = tokio::sync::oneshot::channel::<()>();
        let task = tokio::spawn(async move {
            triax_console::serve(session.clone(), listener, options, rx)
                .await
                .unwrap();
            let _ = session.close().await;
        });
        Console {
            addr,
            stop: Some(tx),
            task: Some(task),
            cookie: std::sync::Mutex::new(None),
        }
    }

    /// Logs in as `name` with [`PASSWORD`]: later requests send the session's cookie.
    pub async fn login(&self, name: &str) {
        let body = json!({"name": name, "password": PASSWORD}).to_string();
        let raw = self
            .request_raw(&format!(
                "POST /api/login HTTP/1.1\r\nHost: {a}\r\nOrigin: http://{a}\r\nContent-Type: application/json\r\nContent-Length: {}\r\nConnection: close\r\n\r\n{body}",
                body.len(),
                a = self.addr
            ))
            .await;
        assert!(raw.starts_with("HTTP/1.1 200"), "login as {name}: {raw}");
        let cookie = raw
            .lines()
            .find_map(|l| l.strip_prefix("Set-Cookie: "))
            .and_then(|c| c.split(';').next())
            .unwrap_or_else(|| panic!("no session cookie: {raw}"))
            .to_owned();
        *self.cookie.lock().unwrap() = Some(cookie);
    }

    /// Forgets the session cookie (the session stays open on the console).
    pub fn forget_login(&self) {
        *self.cookie.lock().unwrap() = None;
    }

    fn cookie_header(&self) -> String {
        match &*self.cookie.lock().unwrap() {
            Some(c) => format!("Cookie: {c}\r\n"),
            None => String::new(),
        }
    }

    pub fn url(&self) -> String {
        format!("http://{}/", self.addr)
    }

    /// Stops the console and waits until it has ended.
    pub async fn stop(mut self) {
        if let Some(s) = self.stop.take() {
            let _ = s.send(());
        }
        if let Some(t) = self.task.take() {
            t.await.unwrap();
        }
    }

    /// GET `path`: the status and the body.
    pub async fn get(&self, path: &str) -> (u16, String) {
        self.request(&format!(
            "GET {path} HTTP/1.1\r\nHost: {}\r\n{}Connection: close\r\n\r\n",
            self.addr,
            self.cookie_header()
        ))
        .await
    }

    /// GET `path`, which must answer 200, as JSON.
    pub async fn json(&self, path: &str) -> Value {
        let (status, body) = self.get(path).await;
        assert_eq!(status, 200, "GET {path}: {body}");
        serde_json::from_str(&body).unwrap_or_else(|e| panic!("GET {path}: {e}: {body}"))
    }

    /// POST `body` as JSON to `path` from the console's own origin.
    pub async fn post(&self, path: &str, body: &Value) -> (u16, String) {
        let body = body.to_string();
        self.request(&format!(
            "POST {path} HTTP/1.1\r\nHost: {a}\r\nOrigin: http://{a}\r\nContent-Type: application/json\r\nContent-Length: {}\r\n{}Connection: close\r\n\r\n{body}",
            body.len(),
            self.cookie_header(),
            a = self.addr
        ))
        .await
    }

    /// Sends `raw` as the whole request: the whole answer, head and body.
    pub async fn request_raw(&self, raw: &str) -> String {
        use tokio::io::{AsyncReadExt, AsyncWriteExt};
        let mut s = tokio::net::TcpStream::connect(self.addr).await.unwrap();
        s.write_all(raw.as_bytes()).await.unwrap();
        let mut out = Vec::new();
        tokio::time::timeout(TIMEOUT, s.read_to_end(&mut out))
            .await
            .expect("the console answers")
            .unwrap();
        String::from_utf8_lossy(&out).into_owned()
    }

    /// Sends `raw` as the whole request: the status and the body of the answer.
    pub async fn request(&self, raw: &str) -> (u16, String) {
        let text = self.request_raw(raw).await;
        let status = text
            .get(9..12)
            .and_then(|s| s.parse().ok())
            .unwrap_or_else(|| panic!("no status line: {text:?}"));
        let body = text
            .split_once("\r\n\r\n")
            .map(|(_, b)| b.to_owned())
            .unwrap_or_default();
        (status, body)
    }

    /// Polls `path` until `cond` holds on its JSON; fails naming `what` after [`TIMEOUT`].
    pub async fn wait_json(&self, what: &str, path: &str, cond: impl Fn(&Value) -> bool) -> Value {
        let deadline = tokio::time::Instant::now() + TIMEOUT;
        loop {
            let v = self.json(path).await;
            if cond(&v) {
                return v;
            }
            assert!(
                tokio::time::Instant::now() < deadline,
                "timed out waiting for {what}; {path} answers {v}"
            );
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
    }
}

impl Drop for Console {
    fn drop(&mut self) {
        if let Some(s) = self.stop.take() {
            let _ = s.send(());
        }
    }
}

// ---- A minimal W3C WebDriver client ---------------------------------------------------------
//
// Five commands (new session, navigate, execute script, log, screenshot) over plain HTTP/1.1:
// a client crate would bring an HTTP stack and TLS into the build for them.

pub struct Browser {
    driver: Child,
    port: u16,
    session: String,
    browser_pid: Option<u64>,
    _profile: tempfile::TempDir,
}

fn webdriver(port: u16, method: &str, path: &str, body: Option<&Value>) -> Value {
    let body = body.map(|b| b.to_string()).unwrap_or_default();
    let mut s = StdTcpStream::connect(("127.0.0.1", port)).expect("chromedriver answers");
    s.set_read_timeout(Some(TIMEOUT)).unwrap();
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
    /// Starts headless Chromium; `dark` asks for `prefers-color-scheme: dark`.
    pub fn start(dark: bool) -> Browser {
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
        let mut args = vec![
            "--headless".to_owned(),
            "--no-sandbox".into(),
            "--disable-gpu".into(),
            "--disable-quic".into(),
            "--no-first-run".into(),
            "--disable-background-networking".into(),
            "--disable-component-update".into(),
            "--disable-sync".into(),
            "--disable-dev-shm-usage".into(),
            "--window-size=1400,1100".into(),
            format!("--user-data-dir={}", b._profile.path().display()),
        ];
        if dark {
            args.push("--force-dark-mode".into());
            args.push("--blink-settings=preferredColorScheme=0".into());
        }
        let caps = json!({"capabilities": {"alwaysMatch": {
            "browserName": "chrome",
            "goog:loggingPrefs": { "browser": "ALL" },
            "goog:chromeOptions": { "binary": chromium, "args": args }
        }}});
        let v = webdriver(port, "POST", "/session", Some(&caps));
        b.session = v["sessionId"].as_str().expect("a session id").to_owned();
        b.browser_pid = v["capabilities"]["goog:processID"].as_u64();
        b
    }

    fn cmd(&self, method: &str, what: &str, body: Option<Value>) -> Value {
        tokio::task::block_in_place(|| {
            webdriver(
                self.port,
                method,
                &format!("/session/{}/{what}", self.session),
                body.as_ref(),
            )
        })
    }

    pub fn go(&self, url: &str) {
        self.cmd("POST", "url", Some(json!({ "url": url })));
    }

    pub fn js(&self, script: &str) -> Value {
        self.cmd(
            "POST",
            "execute/sync",
            Some(json!({ "script": script, "args": [] })),
        )
    }

    /// Runs `script` as an async script: it ends by calling `arguments[0](value)`.
    pub fn js_async(&self, script: &str) -> Value {
        self.cmd(
            "POST",
            "execute/async",
            Some(json!({ "script": script, "args": [] })),
        )
    }

    /// A Chrome DevTools command through chromedriver.
    pub fn cdp(&self, cmd: &str, params: Value) -> Value {
        self.cmd(
            "POST",
            "goog/cdp/execute",
            Some(json!({ "cmd": cmd, "params": params })),
        )
    }

    /// Polls `script` until it returns something truthy; fails naming `what` after [`TIMEOUT`].
    pub async fn wait(&self, what: &str, script: &str) -> Value {
        let deadline = tokio::time::Instant::now() + TIMEOUT;
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
                    "timed out waiting for {what}; the page shows:\n{}",
                    page.as_str().unwrap_or("")
                );
            }
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
    }

    /// Errors the page logged since the last call: uncaught exceptions and failed loads.
    pub fn assert_no_errors(&self, when: &str) {
        let errors = self.errors();
        assert!(errors.is_empty(), "{when}: the page logged {errors:#?}");
    }

    /// The errors the page logged since the last look.
    pub fn errors(&self) -> Vec<String> {
        let v = self.cmd("POST", "se/log", Some(json!({ "type": "browser" })));
        v.as_array()
            .expect("a browser log")
            .iter()
            .filter(|e| e["level"] == "SEVERE")
            .map(|e| e["message"].as_str().unwrap_or_default().to_owned())
            .collect()
    }

    pub fn screenshot(&self, name: &str) {
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
                webdriver(
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

pub fn screenshot_dir() -> PathBuf {
    // CARGO_TARGET_TMPDIR is <target>/tmp.
    PathBuf::from(env!("CARGO_TARGET_TMPDIR"))
        .parent()
        .expect("target/tmp has a parent")
        .join("console-screenshots")
}

pub fn base64_decode(s: &str) -> Vec<u8> {
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

/// Answers one history query of the site, as PROTOCOL.md §5.1 says a gateway does. A reply that
/// cannot be sent ends the answer, said on standard error, so that a short answer is seen.
fn answer_history(q: zenoh::query::Query, t0_ns: i64, period_ns: i64) {
    let key = q.key_expr().as_str().to_owned();
    let sensor = key.rsplit('/').next().unwrap_or_default().to_owned();
    let Some(n) = SENSORS.iter().position(|s| *s == sensor) else {
        return;
    };
    let params = q.parameters().as_str().to_owned();
    let num = |name| param(&params, name).and_then(|v| v.parse::<i64>().ok());
    let now = now_ns();
    let from = num("from_ns").unwrap_or(t0_ns).max(t0_ns);
    let to = num("to_ns").unwrap_or(now).min(now);
    let limit = num("limit").unwrap_or(10_000);
    let after = num("after");
    let mut seq = ((from - t0_ns) / period_ns).max(0) as u64;
    if let Some(a) = after {
        seq = seq.max(a as u64 + 1);
    }
    let mut sent = 0;
    while sent < limit {
        let b = batch(n, &sensor, t0_ns, seq);
        // A batch is kept once its last sample is past.
        if b.header.timestamp_ns >= to || b.header.timestamp_ns + period_ns > now {
            break;
        }
        if let Err(e) = q
            .reply(key.as_str(), b.encode())
            .attachment(seq.to_string())
            .wait()
        {
            eprintln!("site: history reply {seq} of {sensor} not sent: {e}");
            break;
        }
        seq += 1;
        sent += 1;
    }
}
