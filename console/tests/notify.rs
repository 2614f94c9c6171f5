//! Notifications through real local receivers: an HTTP endpoint in the test (the webhook) and
//! Python's `aiosmtpd` (the mail relay, from the test's Python environment, `TRIAX_PYTHON`).
//!
//! - `notifications_reach_a_webhook_and_a_mail_relay`: a verified `exceeded` reaches the
//!   building's rota (webhook and e-mail), an unsigned one nothing; an unacknowledged alert is
//!   escalated, an acknowledged one not; a flood of 300 is one message and one digest; quiet
//!   hours hold a `stale` but not an `exceeded`; a sensor that becomes `calibration_suspect` or
//!   `silent` is told. The time from the put to the webhook's receipt is printed (BENCHMARKS.md).

mod site;

use std::io::{BufRead, BufReader};
use std::process::{Command, Stdio};
use std::time::Instant;

use serde_json::{json, Value};
use site::*;
use tokio::io::{AsyncReadExt, AsyncWriteExt};

/// A webhook receiver: every POST's path, JSON body and arrival.
async fn webhook() -> (
    u16,
    tokio::sync::mpsc::UnboundedReceiver<(String, Value, Instant)>,
) {
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let port = listener.local_addr().unwrap().port();
    let (tx, rx) = tokio::sync::mpsc::unbounded_channel();
    tokio::spawn(async move {
        loop {
            let (mut s, _) = listener.accept().await.unwrap();
            let tx = tx.clone();
            tokio::spawn(async move {
                let mut buf = Vec::new();
                let mut chunk = [0u8; 4096];
                let (head, body) = loop {
                    let n = s.read(&mut chunk).await.unwrap();
                    assert!(n > 0, "the console closed mid-request");
                    buf.extend_from_slice(&chunk[..n]);
                    if let Some(i) = buf.windows(4).position(|w| w == b"\r\n\r\n") {
                        let head = String::from_utf8_lossy(&buf[..i]).into_owned();
                        let len: usize = head
                            .lines()
                            .find_map(|l| l.strip_prefix("Content-Length: "))
                            .unwrap()
                            .parse()
                            .unwrap();
                        while buf.len() < i + 4 + len {
                            let n = s.read(&mut chunk).await.unwrap();
                            buf.extend_from_slice(&chunk[..n]);
                        }
                        break (head, buf[i + 4..i + 4 + len].to_vec());
                    }
                };
                let at = Instant::now();
                assert!(head.starts_with("POST /"), "{head}");
                assert!(head.contains("Content-Type: application/json"), "{head}");
                let path = head.split(' ').nth(1).unwrap().to_owned();
                s.write_all(b"HTTP/1.1 204 No Content\r\nConnection: close\r\n\r\n")
                    .await
                    .unwrap();
                let _ = tx.send((path, serde_json::from_slice(&body).unwrap(), at));
            });
        }
    });
    (port, rx)
}

const SMTP_SERVER: &str = r#"
import json, sys
from aiosmtpd.controller import Controller
class Handler:
    async def handle_DATA(self, server, session, envelope):
        print(json.dumps({"from": envelope.mail_from, "to": envelope.rcpt_tos,
                          "data": envelope.content.decode("utf-8", "replace")}), flush=True)
        return "250 OK"
c = Controller(Handler(), hostname="127.0.0.1", port=int(sys.argv[1]))
c.start()
print(json.dumps({"ready": True}), flush=True)
sys.stdin.read()
c.stop()
"#;

/// Waits for the next webhook message whose path is `path` and for which `keep` holds.
async fn next_on(
    rx: &mut tokio::sync::mpsc::UnboundedReceiver<(String, Value, Instant)>,
    seen: &mut Vec<(String, Value, Instant)>,
    path: &str,
    keep: impl Fn(&Value) -> bool,
) -> (Value, Instant) {
    if let Some(i) = seen.iter().position(|(p, v, _)| p == path && keep(v)) {
        let (_, v, t) = seen.remove(i);
        return (v, t);
    }
    loop {
        let (p, v, t) = tokio::time::timeout(TIMEOUT, rx.recv())
            .await
            .unwrap_or_else(|_| panic!("no message on {path}; others: {seen:?}"))
            .unwrap();
        if p == path && keep(&v) {
            return (v, t);
        }
        seen.push((p, v, t));
    }
}

fn notices_of(v: &Value) -> Vec<(String, String, String)> {
    v["notices"]
        .as_array()
        .unwrap()
        .iter()
        .map(|n| {
            (
                n["building"].as_str().unwrap().to_owned(),
                n["sensor"].as_str().unwrap().to_owned(),
                n["event"].as_str().unwrap().to_owned(),
            )
        })
        .collect()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn notifications_reach_a_webhook_and_a_mail_relay() {
    let python = std::env::var("TRIAX_PYTHON").unwrap_or_else(|_| {
        panic!("TRIAX_PYTHON is not set: the mail relay is Python's aiosmtpd; run the tests with scripts/test")
    });
    let smtp_port = free_port();
    let mut relay = Command::new(python)
        .arg("-c")
        .arg(SMTP_SERVER)
        .arg(smtp_port.to_string())
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .spawn()
        .expect("the Python interpreter runs");
    let (mail_tx, mut mails) = tokio::sync::mpsc::unbounded_channel::<Value>();
    let out = relay.stdout.take().unwrap();
    std::thread::spawn(move || {
        for line in BufReader::new(out).lines() {
            let Ok(line) = line else { return };
            let _ = mail_tx.send(serde_json::from_str(&line).unwrap());
        }
    });
    let ready = tokio::time::timeout(TIMEOUT, mails.recv())
        .await
        .unwrap()
        .unwrap();
    assert_eq!(ready["ready"], true, "aiosmtpd: {ready}");
    let (hook_port, mut hooks) = webhook().await;

    // The quiet hours of the other buildings: the hour about now.
    let now_min = (now_ns() / 60_000_000_000).rem_euclid(1440);
    let hm = |m: i64| {
        format!(
            "{:02}:{:02}",
            m.rem_euclid(1440) / 60,
            m.rem_euclid(1440) % 60
        )
    };
    let settings = format!(
        r#"
[channels.hook]
webhook = "http://127.0.0.1:{hook_port}/hook"
[channels.boss]
webhook = "http://127.0.0.1:{hook_port}/boss"
[channels.flood]
webhook = "http://127.0.0.1:{hook_port}/flood"
[channels.annex]
webhook = "http://127.0.0.1:{hook_port}/annex"
[channels.mail]
smtp = "127.0.0.1:{smtp_port}"
from = "triax@site.example"
to = ["oncall@site.example"]

[[rota]]
building = "hq"
escalate_after_s = 4
escalate_to = ["boss"]
[[rota.shift]]
from = "00:00"
to = "24:00"
channels = ["hook", "mail"]

[[rota]]
building = "flood"
[[rota.shift]]
from = "00:00"
to = "24:00"
channels = ["flood"]

[[rota]]
building = "*"
quiet_hours = "{}-{}"
[[rota.shift]]
from = "00:00"
to = "24:00"
channels = ["annex"]

[digest]
window_s = 10
"#,
        hm(now_min - 60),
        hm(now_min + 60)
    );
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("notify.toml");
    std::fs::write(&path, &settings).unwrap();
    let config = triax_console::notify::Config::load(&path).unwrap();
    write_operators(&dir.path().join("operators"), &[("alice", "operate")]);
    let site = Site::start(60).await;
    let console = Console::start_with(&site, None, |o| {
        o.buildings = vec![];
        o.notify = Some(config);
        o.operators_file = Some(dir.path().join("operators"));
    })
    .await;
    console.login("alice").await;
    console
        .wait_json("hq's sensors", "/api/fleet", |v| {
            v["buildings"].as_array().is_some_and(|b| {
                b.iter()
                    .any(|b| b["sensors"].as_array().map(Vec::len) == Some(3))
            })
        })
        .await;
    let mut seen = Vec::new();

    // An unsigned `exceeded` tells nobody; a verified one its rota, within a moment.
    site.alert("acc-03", "exceeded", "forged", (10, 20), false)
        .await;
    let put = Instant::now();
    site.alert("acc-02", "exceeded", "acc-02 over", (10, 20), true)
        .await;
    let (first, at) = next_on(&mut hooks, &mut seen, "/hook", |_| true).await;
    let latency = at - put;
    assert_eq!(first["kind"], "notification", "{first}");
    assert_eq!(
        notices_of(&first),
        [("hq".into(), "acc-02".into(), "exceeded".into())],
        "the unsigned one is never told: {first}"
    );
    assert_eq!(first["notices"][0]["statement"], "acc-02 over");
    let mail = tokio::time::timeout(TIMEOUT, mails.recv())
        .await
        .unwrap()
        .unwrap();
    let data = mail["data"].as_str().unwrap();
    assert_eq!(mail["to"], json!(["oncall@site.example"]));
    assert!(
        data.contains("Subject: [triax] hq/acc-02 exceeded"),
        "{data}"
    );
    assert!(
        data.contains("acc-02 over") && data.contains("verified alert"),
        "{data}"
    );
    // Acknowledged at once: it will not be escalated.
    let id = first["notices"][0]["alert_id"].as_u64().unwrap();
    let (status, body) = console.post("/api/alerts/ack", &json!({"ids": [id]})).await;
    assert_eq!(status, 200, "{body}");

    // Not acknowledged: escalated to the boss after 4 s, and acc-02 (due earlier) never.
    site.alert("acc-01", "exceeded", "acc-01 over", (10, 20), true)
        .await;
    let (esc, _) = next_on(&mut hooks, &mut seen, "/boss", |_| true).await;
    assert_eq!(esc["kind"], "escalation", "{esc}");
    assert_eq!(
        notices_of(&esc),
        [("hq".into(), "acc-01".into(), "exceeded".into())]
    );

    // A flood: 300 verified alerts are one notification and one digest.
    let flood_start = Instant::now();
    for i in 0..300 {
        site.alert_in(
            "flood",
            "acc-09",
            "exceeded",
            &format!("flood {i}"),
            (10, 20),
            true,
        )
        .await;
    }
    let published = flood_start.elapsed();
    let mut messages = 0;
    let mut counted = 0;
    while counted < 300 {
        let (m, _) = next_on(&mut hooks, &mut seen, "/flood", |_| true).await;
        messages += 1;
        counted += m["count"].as_u64().unwrap();
        if m["kind"] == "digest" {
            assert_eq!(
                m["notices"].as_array().unwrap().len(),
                50,
                "listed, the rest counted"
            );
        }
    }
    assert_eq!(counted, 300);
    assert!(
        messages <= 2,
        "{messages} messages for a flood published in {published:?}"
    );

    // Quiet hours: a `stale` waits, an `exceeded` does not.
    site.alert_in("annex", "acc-x", "stale", "no data", (10, 20), true)
        .await;
    site.alert_in("annex", "acc-y", "exceeded", "annex over", (10, 20), true)
        .await;
    let (annex, _) = next_on(&mut hooks, &mut seen, "/annex", |_| true).await;
    assert_eq!(
        notices_of(&annex),
        [("annex".into(), "acc-y".into(), "exceeded".into())]
    );
    let status = console.json("/api/notifications").await;
    assert_eq!(status["held"], 1, "{status}");

    // Sensors that become suspect or silent.
    site.conditions
        .lock()
        .unwrap()
        .insert("acc-03".into(), "suspect");
    site.conditions
        .lock()
        .unwrap()
        .insert("acc-01".into(), "silent");
    let mut told = std::collections::BTreeSet::new();
    while told.len() < 2 {
        let (m, _) = next_on(&mut hooks, &mut seen, "/hook", |m| {
            notices_of(m)
                .iter()
                .any(|(_, _, e)| e == "calibration_suspect" || e == "silent")
        })
        .await;
        for (b, s, e) in notices_of(&m) {
            if e != "exceeded" {
                told.insert(format!("{b}/{s} {e}"));
            }
        }
    }
    assert_eq!(
        told.into_iter().collect::<Vec<_>>(),
        ["hq/acc-01 silent", "hq/acc-03 calibration_suspect"]
    );
    let status = console.json("/api/notifications").await;
    assert_eq!(status["failed"], 0, "{status}");
    // The alerts view says what left.
    let browser = Browser::start(false);
    browser.go(&format!("{}#/login", console.url()));
    browser
        .wait(
            "the login form",
            "return document.getElementById('login-name')",
        )
        .await;
    browser.js(&format!("document.getElementById('login-name').value = 'alice'; document.getElementById('login-password').value = '{PASSWORD}'; document.getElementById('login-go').click(); return 1"));
    browser
        .wait("logged in", "return document.getElementById('who-name')")
        .await;
    browser.go(&format!("{}#/alerts", console.url()));
    let line = browser
        .wait("the notifications line", "const n = document.getElementById('notify-status'); return n && Number(n.dataset.sent) > 0 && n.textContent")
        .await;
    assert!(
        line.as_str()
            .unwrap()
            .contains("Notifications on annex, boss, flood, hook, mail:")
            && line.as_str().unwrap().contains("0 failed"),
        "{line}"
    );
    browser.screenshot("alerts-notifications");
    browser.assert_no_errors("the notifications line");
    drop(browser);
    eprintln!(
        "verified alert put to webhook received: {:.1} ms; flood of 300 published in {published:?}, {messages} messages",
        latency.as_secs_f64() * 1e3
    );
    console.stop().await;
    // Its end of standard input ends the relay.
    drop(relay.stdin.take());
    let _ = relay.kill();
    let _ = relay.wait();
}
