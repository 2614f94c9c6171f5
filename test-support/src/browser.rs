//! A minimal W3C WebDriver client for Debian's headless Chromium through `chromedriver`.
//!
//! Six commands (new session, navigate, execute script, log, screenshot, DevTools) over plain
//! HTTP/1.1: a client crate would bring an HTTP stack and TLS into the build for them. Every
//! call blocks in place on a multi-threaded Tokio runtime (`block_in_place`).

use std::io::{Read, Write};
use std::net::TcpStream as StdTcpStream;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::Duration;

use serde_json::{json, Value};

use crate::{free_port, TIMEOUT};

/// Headless Chromium under `chromedriver`, with a profile of its own; closed (and killed if
/// need be) when dropped.
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
        self.wait_within(what, TIMEOUT, script).await
    }

    /// As [`Browser::wait`], failing after `limit`.
    pub async fn wait_within(&self, what: &str, limit: Duration, script: &str) -> Value {
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
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
    }

    /// Errors the page logged since the last call: uncaught exceptions and failed loads.
    pub fn errors(&self) -> Vec<String> {
        let v = self.cmd("POST", "se/log", Some(json!({ "type": "browser" })));
        v.as_array()
            .expect("a browser log")
            .iter()
            .filter(|e| e["level"] == "SEVERE")
            .map(|e| e["message"].as_str().unwrap_or_default().to_owned())
            .collect()
    }

    /// Fails, naming `when`, if the page logged an error since the last look.
    pub fn assert_no_errors(&self, when: &str) {
        let errors = self.errors();
        assert!(errors.is_empty(), "{when}: the page logged {errors:#?}");
    }

    /// Saves what the page shows as `<dir>/<name>.png`.
    pub fn screenshot(&self, dir: &Path, name: &str) {
        let b64 = self.cmd("GET", "screenshot", None);
        let png = base64_decode(b64.as_str().expect("base64 screenshot"));
        std::fs::create_dir_all(dir).unwrap();
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
