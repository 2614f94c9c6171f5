//! `triax-alert` at fleet scale: 100 buildings × 100 sensors at 100 Hz in 10-sample batches
//! (1 M samples/s, 100 000 batches/s) of corrected data, through a real `zenohd` router, to the
//! alerting service in its own process (the `triax-alert` binary). Reports the service's CPU
//! (cores, over the run and from the first event on, when every window is whole and judged)
//! and resident set, and the latency from the publish of a batch that crosses a limit to the
//! arrival of its `exceeded` alert, p50 and p99 over the injected events.
//!
//! ```text
//! cargo bench -p triax-alert --bench fleet -- [--buildings 100] [--sensors 100] [--seconds 30]
//!     [--sway-mps2 0.05] [--batch-samples 10]
//! ```
//!
//! `--sway-mps2` is every sensor's background sway (1.3 Hz, m/s² amplitude): 0.05 is a quiet
//! building whose windows the running bounds clear without estimating; near the 2 m/s² limit
//! (1.9, say) every window of every sensor is estimated in full. `--batch-samples` is the
//! samples in a batch (10 by default, 100 as in the gateway's standard profile): the service
//! judges a window once per batch, so its per-batch costs weigh ten times less at 100.
//!
//! Needs `zenohd` 1.10 on PATH (`scripts/test` installs it). The publisher plays the buildings'
//! gateways (it publishes corrected batches and each building's heartbeat), in this process.

use std::io::Write;
use std::process::{Child, Command, Stdio};
use std::sync::atomic::{AtomicU64, Ordering::Relaxed};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use rand::SeedableRng;
use rand_distr::Distribution;

use triax_protocol::batch::CorrectedSample;
use triax_protocol::messages::{AlertKind, AlertLevel, Heartbeat};
use triax_protocol::signing::{read_alert, TrustedKeys};
use triax_protocol::{to_json, BuildingId, Key, SensorId};

// The benches' /proc readers.
use triax_test_support::proc as bench_proc;

/// Seconds into the run of the first injected event.
const FIRST_EVENT_S: f64 = 13.0;

struct Args {
    buildings: usize,
    sensors: usize,
    seconds: f64,
    sway_mps2: f32,
    batch_samples: u64,
}

fn args() -> Args {
    let mut a = Args {
        buildings: 100,
        sensors: 100,
        seconds: 30.0,
        sway_mps2: 0.05,
        batch_samples: 10,
    };
    let mut it = std::env::args().skip(1);
    while let Some(flag) = it.next() {
        let mut value = || it.next().and_then(|v| v.parse::<f64>().ok());
        match flag.as_str() {
            "--buildings" => a.buildings = value().expect("a number") as usize,
            "--sensors" => a.sensors = value().expect("a number") as usize,
            "--seconds" => a.seconds = value().expect("a number"),
            "--sway-mps2" => a.sway_mps2 = value().expect("a number") as f32,
            "--batch-samples" => a.batch_samples = (value().expect("a number") as u64).max(1),
            // cargo bench passes `--bench`.
            _ => {}
        }
    }
    a
}

/// Killed when dropped.
struct Reaped(Child);

impl Drop for Reaped {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

fn cpu_seconds(pid: u32) -> f64 {
    bench_proc::cpu_seconds(pid).unwrap_or(0.0)
}

fn rss_mib(pid: u32) -> f64 {
    bench_proc::proc_status_kib(pid, "VmRSS:").map_or(0.0, |kib| kib as f64 / 1024.0)
}

fn batch(
    sensor: &SensorId,
    seq: u64,
    n: u64,
    t0_ns: i64,
    amplitude: f32,
    rng: &mut rand::rngs::StdRng,
) -> Vec<u8> {
    let noise = rand_distr::Normal::new(0.0, 0.01).expect("finite deviation");
    triax_protocol::batch::sample::dynamic(
        sensor.clone(),
        seq,
        t0_ns + (seq * n) as i64 * 10_000_000,
        100.0,
        (0..n)
            .map(|i| {
                // The phase in f64 from the sample's index: an f32 time loses the phase's
                // precision within minutes, and the sway would not be one sinusoid.
                let t = (seq * n + i) as f64 / 100.0;
                let x = f64::from(amplitude) * (std::f64::consts::TAU * 1.3 * t).sin();
                // White noise at the stated u, as a sensor has: without it the samples are a
                // sinusoid to their rounding, which no fit judges as noise.
                let mut e = || noise.sample(rng) as f32;
                CorrectedSample {
                    accel_mps2: [x as f32 + e(), e(), 9.81 + e()],
                    uncertainty_mps2: [0.01; 3],
                    flags: 0,
                }
            })
            .collect(),
    )
    .encode()
}

async fn client(endpoint: &str) -> zenoh::Session {
    let mut c = zenoh::Config::default();
    for (k, v) in [
        ("mode", "\"client\"".to_owned()),
        ("connect/endpoints", format!("[\"{endpoint}\"]")),
        ("scouting/multicast/enabled", "false".to_owned()),
    ] {
        c.insert_json5(k, &v).expect("valid setting");
    }
    zenoh::open(c).await.expect("session")
}

#[tokio::main(flavor = "multi_thread", worker_threads = 2)]
async fn main() {
    let a = args();
    let sway_mps2 = a.sway_mps2;
    let port = triax_net::free_loopback_port().expect("a port");
    let endpoint = format!("tcp/127.0.0.1:{port}");
    let _router = Reaped(
        Command::new("zenohd")
            .args(["--no-multicast-scouting", "--listen", &endpoint])
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .expect("zenohd on PATH (cargo install zenohd --version 1.10.2 --locked)"),
    );
    for _ in 0..100 {
        if std::net::TcpStream::connect(("127.0.0.1", port)).is_ok() {
            break;
        }
        std::thread::sleep(Duration::from_millis(50));
    }
    let dir = tempfile::tempdir().expect("tempdir");
    let config = dir.path().join("alert.toml");
    let mut toml = String::from(
        "window_s = 10.0\nstale_after_s = 30.0\nrepeat_interval_s = 0.0\nstate_path = \"\"\n\
         highpass_hz = 1.0\n\
         [defaults]\npga_mps2 = 2.0\n",
    );
    let buildings: Vec<BuildingId> = (0..a.buildings)
        .map(|b| BuildingId::new(format!("b{b:03}")).expect("id"))
        .collect();
    for b in &buildings {
        toml.push_str(&format!("[buildings.{b}]\n"));
    }
    std::fs::File::create(&config)
        .and_then(|mut f| f.write_all(toml.as_bytes()))
        .expect("config");
    let service = Reaped(
        Command::new(env!("CARGO_BIN_EXE_triax-alert"))
            .arg("--config")
            .arg(&config)
            .args([
                "--zenoh-mode",
                "client",
                "--connect",
                &endpoint,
                "--no-multicast-scouting",
            ])
            .env("RUST_LOG", "warn")
            .stdout(Stdio::null())
            .stderr(std::fs::File::create(dir.path().join("triax-alert.log")).expect("log file"))
            .spawn()
            .expect("triax-alert"),
    );
    let pid = service.0.id();
    let session = client(&endpoint).await;
    let sensors: Vec<SensorId> = (0..a.sensors)
        .map(|s| SensorId::new(format!("s{s:03}")).expect("id"))
        .collect();
    let mut publishers = Vec::new();
    for b in &buildings {
        for s in &sensors {
            publishers.push((
                s.clone(),
                session
                    .declare_publisher(Key::Corrected(b.clone(), s.clone()).to_string())
                    .await
                    .expect("publisher"),
            ));
        }
    }
    // Alerts, and when each injected event was published, by (building, sensor).
    let injected: Arc<Mutex<std::collections::HashMap<String, Instant>>> = Arc::default();
    let latencies: Arc<Mutex<Vec<f64>>> = Arc::default();
    let alerts = Arc::new(AtomicU64::new(0));
    let (inj, lat, n) = (injected.clone(), latencies.clone(), alerts.clone());
    let _sub = session
        .declare_subscriber("triax/*/alert/*")
        .callback(move |s| {
            // The bench trusts no key: it times alerts, whoever signed them.
            let Ok((alert, _)) = read_alert(&s.payload().to_bytes(), &TrustedKeys::default())
            else {
                return;
            };
            n.fetch_add(1, Relaxed);
            if alert.kind == AlertKind::PeakAcceleration && alert.level == AlertLevel::Exceeded {
                let key = format!("{}/{}", alert.building, alert.sensor_id);
                if let Some(at) = inj.lock().expect("lock").remove(&key) {
                    lat.lock()
                        .expect("lock")
                        .push(at.elapsed().as_secs_f64() * 1e3);
                }
            }
        })
        .await
        .expect("subscriber");
    tokio::time::sleep(Duration::from_secs(2)).await;
    let t0_ns = 1_800_000_000_000_000_000i64;
    let rate = (a.buildings * a.sensors) as f64 * 100.0 / a.batch_samples as f64;
    let total = publishers.len();
    let mut seq = vec![0u64; total];
    let (cpu0, start) = (cpu_seconds(pid), Instant::now());
    // The service's CPU from the first event on as well: by then every window is whole and
    // judged, and the first judgements' searches are behind (the first 11.55 s only fill the
    // windows, so a run's whole mean mixes in a warm-up).
    let mut steady: Option<(f64, Instant)> = None;
    let mut sent = 0u64;
    let mut next = 0usize;
    // Windows are judged once the baseline has settled (1.55 s at 1 Hz) and a window has
    // filled (10 s): events start after that.
    let mut next_event = FIRST_EVENT_S;
    let mut next_beat = 0.0;
    let mut event_sensor = 7usize;
    let mut rng = rand::rngs::StdRng::seed_from_u64(1);
    while start.elapsed().as_secs_f64() < a.seconds {
        let now_s = start.elapsed().as_secs_f64();
        if steady.is_none() && now_s >= FIRST_EVENT_S {
            steady = Some((cpu_seconds(pid), Instant::now()));
        }
        if now_s >= next_beat {
            for b in &buildings {
                let beat = Heartbeat {
                    format_version: 1,
                    building: b.clone(),
                    gateway: format!("gw-{b}"),
                    sequence: (next_beat as u64),
                    at: time::OffsetDateTime::now_utc(),
                    sensors: Default::default(),
                };
                let _ = session
                    .put(Key::Heartbeat(b.clone()).to_string(), to_json(&beat))
                    .await;
            }
            next_beat += 1.0;
        }
        let due = (now_s * rate) as u64;
        while sent < due {
            let i = next % total;
            let strong = now_s >= next_event && i == event_sensor;
            let amplitude = if strong { 8.0 } else { sway_mps2 };
            let (s, p) = &publishers[i];
            if strong {
                let b = &buildings[i / a.sensors];
                injected
                    .lock()
                    .expect("lock")
                    .insert(format!("{b}/{s}"), Instant::now());
                next_event += 1.0;
                event_sensor = (event_sensor * 7919 + 13) % total;
            }
            let _ = p
                .put(batch(
                    s,
                    seq[i],
                    a.batch_samples,
                    t0_ns,
                    amplitude,
                    &mut rng,
                ))
                .await;
            seq[i] += 1;
            next += 1;
            sent += 1;
        }
        tokio::time::sleep(Duration::from_millis(1)).await;
    }
    let elapsed = start.elapsed().as_secs_f64();
    let cpu1 = cpu_seconds(pid);
    let cores = (cpu1 - cpu0) / elapsed;
    let steady_cores = steady.map_or(f64::NAN, |(c, at)| (cpu1 - c) / at.elapsed().as_secs_f64());
    tokio::time::sleep(Duration::from_secs(2)).await;
    let rss = rss_mib(pid);
    let mut l = latencies.lock().expect("lock").clone();
    l.sort_by(|x, y| x.total_cmp(y));
    let pct = |p: f64| {
        l.get(((l.len().max(1) - 1) as f64 * p) as usize)
            .copied()
            .unwrap_or(f64::NAN)
    };
    println!(
        "| {} buildings × {} sensors, {}-sample batches | {:.0} batches/s offered ({:.2} M samples/s) | triax-alert {:.2} cores ({:.2} from {FIRST_EVENT_S} s on), RSS {:.1} MiB | alert latency p50 {:.0} ms, p99 {:.0} ms ({} of {} events) | {} alerts |",
        a.buildings,
        a.sensors,
        a.batch_samples,
        sent as f64 / elapsed,
        sent as f64 * a.batch_samples as f64 / elapsed / 1e6,
        cores,
        steady_cores,
        rss,
        pct(0.5),
        pct(0.99),
        l.len(),
        (a.seconds - FIRST_EVENT_S).max(0.0) as u64,
        alerts.load(Relaxed)
    );
    if l.is_empty() {
        let log = std::fs::read_to_string(dir.path().join("triax-alert.log")).unwrap_or_default();
        let tail: Vec<&str> = log.lines().rev().take(20).collect();
        eprintln!("no injected event was alerted; the service's log ends:");
        for line in tail.into_iter().rev() {
            eprintln!("  {line}");
        }
    }
    drop(service);
}
