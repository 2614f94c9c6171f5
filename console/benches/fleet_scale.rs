//! The fleet page at scale: `cargo bench -p triax-console --bench fleet_scale`.
//!
//! 100 buildings × 100 sensors behind a router: a real `zenohd` (on `PATH`, as the tests
//! use), the console's release binary connected to it as a client, and one process simulating
//! the buildings. Each simulated building answers `triax/<b>/status` with 100 calibrated
//! sensors (counters that grow), publishes a heartbeat every second naming its 100 sensors,
//! and a trickle of corrected batches (one sensor in ten puts a 50-sample batch every 5 s),
//! which the router carries and the console, watching no sensor, does not subscribe to. What
//! is not simulated: the gateways' correction, history and alerts.
//!
//! Figures, each over several runs (the machine is shared): the fleet page's load time in
//! headless Chromium (navigation start to every building drawn, by the page's own clock), the
//! console's CPU with no page and with the fleet page open (from `/proc/<pid>/stat`), its
//! resident memory, and the bytes a fleet event carries.

#[path = "../tests/site/mod.rs"]
#[allow(unused_imports)]
mod site;

use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use site::{free_port, now_ns, Browser};
use triax_protocol::batch::{BatchHeader, CorrectedBatch, CorrectedSample, CorrectionInfo, Mode};
use triax_protocol::messages::{
    GatewayStatus, HealthVerdict, Heartbeat, HeartbeatSensor, SensorStatus,
};
use triax_protocol::{to_json, BuildingId, SensorId, JSON_FORMAT_VERSION};

// The benches' /proc readers.
use triax_test_support::proc as bench_proc;

const BUILDINGS: usize = 100;
const SENSORS: usize = 100;

struct Killed(Child);

impl Drop for Killed {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

fn building(b: usize) -> String {
    format!("b{b:03}")
}

fn sensor(s: usize) -> String {
    format!("acc-{s:03}")
}

fn at(ns: i64) -> time::OffsetDateTime {
    time::OffsetDateTime::from_unix_timestamp_nanos(i128::from(ns)).expect("now is a valid time")
}

/// The status page of building `b` at `now`, built from the protocol's own types so that it
/// decodes as a gateway's does.
fn status(b: usize, started_ns: i64, now: i64) -> Vec<u8> {
    let up_s = ((now - started_ns) / 1_000_000_000).max(1) as u64;
    let sensors: Vec<SensorStatus> = (0..SENSORS)
        .map(|s| SensorStatus {
            sensor_id: SensorId::new(sensor(s)).expect("a valid id"),
            last_seen: Some(at(now - 200_000_000)),
            batches: up_s * 2,
            samples: up_s * 100,
            gaps: 0,
            missing_batches: 0,
            late_batches: 0,
            duplicates: 0,
            rejects: 0,
            flagged_samples: 0,
            keys_declared: true,
            calibration_version: Some(3),
            mode: Mode::Dynamic,
            valid_from: Some(at(now - 86_400_000_000_000)),
            valid_until: Some(at(now + 200 * 86_400_000_000_000)),
            health: Some(HealthVerdict::Ok),
            suspect_from_ns: None,
            calibration_record: None,
        })
        .collect();
    to_json(&GatewayStatus {
        format_version: JSON_FORMAT_VERSION,
        building: BuildingId::new(building(b)).expect("a valid id"),
        gateway: format!("gw-{b:03}"),
        started_at: at(started_ns),
        reported_at: at(now),
        malformed: 0,
        dropped: 0,
        pushes_accepted: 0,
        pushes_refused: 0,
        refused_keys: Default::default(),
        over_capacity: 0,
        admitted_sensors: 0,
        displaced_sensors: 0,
        expired_sensors: 0,
        history: None,
        backfill: None,
        total_sensors: SENSORS as u64,
        next_offset: None,
        sensors,
    })
}

fn heartbeat(b: usize, seq: u64, now: i64) -> Vec<u8> {
    to_json(&Heartbeat {
        format_version: JSON_FORMAT_VERSION,
        building: BuildingId::new(building(b)).expect("a valid id"),
        gateway: format!("gw-{b:03}"),
        sequence: seq,
        at: at(now),
        sensors: (0..SENSORS)
            .map(|s| {
                (
                    SensorId::new(sensor(s)).expect("a valid id"),
                    HeartbeatSensor {
                        late_sequence: None,
                        late_timestamp_ns: None,
                        last_sequence: seq * 2,
                        last_timestamp_ns: now - 200_000_000,
                    },
                )
            })
            .collect(),
    })
}

fn corrected(s: usize, seq: u64, now: i64) -> Vec<u8> {
    CorrectedBatch {
        header: BatchHeader {
            sensor_id: SensorId::new(sensor(s)).expect("a valid id"),
            sequence: seq,
            timestamp_ns: now - 500_000_000,
            sample_rate_hz: 100.0,
        },
        batch_flags: 0,
        info: CorrectionInfo {
            calibration_version: 3,
            mode: Mode::Dynamic,
            coverage_factor: 2.0,
        },
        samples: (0..50)
            .map(|i| CorrectedSample {
                accel_mps2: [0.01 * (i as f32 * 0.3).sin(), 0.0, 9.81],
                uncertainty_mps2: [0.004; 3],
                flags: 0,
            })
            .collect(),
    }
    .encode()
}

/// The simulated buildings, on one client session of the router.
async fn buildings(endpoint: String) -> (zenoh::Session, Vec<zenoh::query::Queryable<()>>) {
    let config =
        triax_net::ZenohSettings::loopback(triax_net::ZenohMode::Client, vec![], vec![endpoint])
            .to_config()
            .expect("a client configuration");
    let session = zenoh::open(config).await.expect("the router answers");
    let started = now_ns();
    let mut queryables = Vec::new();
    for b in 0..BUILDINGS {
        let q = session
            .declare_queryable(format!("triax/{}/status", building(b)))
            .callback(move |q| {
                use zenoh::Wait;
                // On the building's own key, as a gateway answers: the query's key may be a
                // wildcard (`triax/*/status`).
                let key = format!("triax/{}/status", building(b));
                let _ = q.reply(key, status(b, started, now_ns())).wait();
            })
            .await
            .expect("a queryable");
        queryables.push(q);
    }
    let s = session.clone();
    tokio::spawn(async move {
        let mut tick = tokio::time::interval(Duration::from_secs(1));
        for seq in 0u64.. {
            tick.tick().await;
            let now = now_ns();
            for b in 0..BUILDINGS {
                let _ = s
                    .put(
                        format!("triax/{}/heartbeat", building(b)),
                        heartbeat(b, seq, now),
                    )
                    .await;
                // One sensor in ten every 5 s: two of them each second.
                for k in 0..2 {
                    let sn = ((seq as usize * 2 + k) * 7 + b) % SENSORS;
                    let _ = s
                        .put(
                            format!("triax/{}/corrected/{}", building(b), sensor(sn)),
                            corrected(sn, seq, now),
                        )
                        .await;
                }
            }
        }
    });
    (session, queryables)
}

/// utime + stime of `pid`, in seconds.
fn cpu_s(pid: u32) -> f64 {
    bench_proc::cpu_seconds(pid).expect("the console runs")
}

fn rss_mib(pid: u32, field: &str) -> f64 {
    bench_proc::proc_status_kib(pid, field).map_or(f64::NAN, |kib| kib as f64 / 1024.0)
}

fn stats(mut v: Vec<f64>) -> String {
    v.sort_by(f64::total_cmp);
    format!(
        "median {:.3} (min {:.3}, max {:.3}, n = {})",
        v[v.len() / 2],
        v[0],
        v[v.len() - 1],
        v.len()
    )
}

async fn cpu_share(pid: u32, window: Duration) -> f64 {
    let (c0, t0) = (cpu_s(pid), Instant::now());
    tokio::time::sleep(window).await;
    (cpu_s(pid) - c0) / t0.elapsed().as_secs_f64()
}

#[tokio::main(flavor = "multi_thread", worker_threads = 2)]
async fn main() {
    if std::env::args().any(|a| a == "--list" || a == "--test") {
        // `cargo test --benches` asks for a list; this bench runs only when asked.
        return;
    }
    let port = free_port();
    let endpoint = format!("tcp/127.0.0.1:{port}");
    let router = Killed(
        Command::new("zenohd")
            .args(["--no-multicast-scouting", "--listen", &endpoint])
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .expect("zenohd 1.10.2 on PATH (cargo install zenohd --version 1.10.2 --locked)"),
    );
    while std::net::TcpStream::connect(("127.0.0.1", port)).is_err() {
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    // What the simulated buildings say must decode as the console decodes it.
    let now = now_ns();
    if let Err(e) = triax_protocol::from_json::<GatewayStatus>(&status(0, now, now)) {
        panic!("the simulated status does not decode: {e}");
    }
    if let Err(e) = triax_protocol::from_json::<Heartbeat>(&heartbeat(0, 1, now)) {
        panic!("the simulated heartbeat does not decode: {e}");
    }
    let (_site, _queryables) = buildings(endpoint.clone()).await;
    let http = free_port();
    let console = Killed(
        Command::new(env!("CARGO_BIN_EXE_triax-console"))
            .args([
                "--zenoh-mode",
                "client",
                "--connect",
                &endpoint,
                "--no-multicast-scouting",
                "--listen",
                &format!("127.0.0.1:{http}"),
                "--no-state",
                "--log",
                "warn",
            ])
            .stdout(Stdio::null())
            .stderr(Stdio::inherit())
            .spawn()
            .expect("the console starts"),
    );
    let pid = console.0.id();
    let url = format!("http://127.0.0.1:{http}/");
    // Every building and sensor known.
    let started = Instant::now();
    let mut seen = String::new();
    let fleet_bytes = loop {
        if let Ok(body) = fetch(http, "/api/fleet") {
            let v: serde_json::Value = serde_json::from_str(&body).unwrap_or_default();
            seen = format!(
                "{} buildings, malformed messages {}, first building {}",
                v["buildings"].as_array().map_or(0, Vec::len),
                v["malformed_messages"],
                v["buildings"][0]
                    .to_string()
                    .chars()
                    .take(400)
                    .collect::<String>()
            );
            let sensors: usize = v["buildings"]
                .as_array()
                .map(|bs| {
                    bs.iter()
                        .map(|b| b["sensors"].as_array().map_or(0, Vec::len))
                        .sum()
                })
                .unwrap_or(0);
            if sensors == BUILDINGS * SENSORS {
                break body.len();
            }
        }
        assert!(
            started.elapsed() < Duration::from_secs(120),
            "the console never listed every sensor: {seen}"
        );
        tokio::time::sleep(Duration::from_millis(200)).await;
    };
    println!(
        "fleet of {BUILDINGS} x {SENSORS} known after {:.1} s; a fleet snapshot is {} bytes of JSON",
        started.elapsed().as_secs_f64(),
        fleet_bytes
    );

    let mut idle = Vec::new();
    for _ in 0..3 {
        idle.push(cpu_share(pid, Duration::from_secs(10)).await);
    }
    println!("console CPU, no page open, cores: {}", stats(idle));
    println!(
        "console memory, no page open: RSS {:.1} MiB",
        rss_mib(pid, "VmRSS:")
    );

    let browser = Browser::start(false);
    let mut loads = Vec::new();
    for i in 0..6 {
        // A blank page between loads, so that each load starts from nothing.
        browser.go("about:blank");
        browser.go(&format!("{url}#/"));
        let ms = browser.js_async(&format!(
            "const done = arguments[0]; const t0 = performance.now(); \
             (function check() {{ const f = document.getElementById('fleet'); \
               if (f && f.dataset.buildings === '{BUILDINGS}' && document.body.textContent.includes('acc-{last:03}')) \
                 done(performance.now()); \
               else if (performance.now() - t0 > 30000) done(null); \
               else requestAnimationFrame(check); }})();",
            last = SENSORS - 1
        ));
        let ms = ms
            .as_f64()
            .expect("the fleet page drew every building within 30 s");
        if i > 0 {
            // The first load also fills the browser's caches: reported apart.
            loads.push(ms / 1000.0);
        } else {
            println!("fleet page, first load: {:.3} s", ms / 1000.0);
        }
    }
    println!(
        "fleet page load (navigation start to every building drawn), s: {}",
        stats(loads)
    );
    let mut busy = Vec::new();
    for _ in 0..3 {
        busy.push(cpu_share(pid, Duration::from_secs(10)).await);
    }
    println!("console CPU, the fleet page open, cores: {}", stats(busy));
    println!(
        "console memory, the fleet page open: RSS {:.1} MiB, peak {:.1} MiB",
        rss_mib(pid, "VmRSS:"),
        rss_mib(pid, "VmHWM:")
    );
    drop(browser);
    drop(console);
    drop(router);
}

/// GET `path` from the console: its body.
fn fetch(port: u16, path: &str) -> std::io::Result<String> {
    use std::io::{Read, Write};
    let mut s = std::net::TcpStream::connect(("127.0.0.1", port))?;
    write!(
        s,
        "GET {path} HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nConnection: close\r\n\r\n"
    )?;
    let mut out = String::new();
    s.read_to_string(&mut out)?;
    Ok(out
        .split_once("\r\n\r\n")
        .map(|(_, b)| b.to_owned())
        .unwrap_or_default())
}
