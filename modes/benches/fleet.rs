//! `triax-modes` at fleet scale: B buildings, each the five-storey simulated building's six
//! sensors at 100 Hz, their corrected streams played S times faster than real time, to the
//! service in its own process (the `triax-modes` binary). B × S is the equivalent number of
//! buildings in real time: the service gathers B·6·100·S samples/s and identifies B·S windows
//! per 30 minutes of wall time, as it would for B·S buildings streaming live.
//!
//! ```text
//! cargo bench -p triax-modes --bench fleet -- [--buildings 10] [--speed 10] [--windows 2]
//!     [--batch 10]
//! ```
//!
//! Reports the service's CPU (cores; the identification thread apart) over the whole run and
//! over the full windows, its resident set, the windows published per building (identified or
//! refused, and why), and the delay from the last batch of a window (all buildings') to each
//! building's modes message, which shows the identification queue at a boundary: every
//! building's windows close at the same instants.
//!
//! This process plays the buildings' gateways: a Zenoh peer listening on a loopback port
//! (multicast scouting off) that the service connects to. The sensors' clock starts at the
//! moment the service starts and runs S times faster than the wall clock: a follower follows a
//! sensor it meets for the first time from its own start, and hands over a first batch stamped
//! no later than that without reading the history (client/src/follow.rs). No heartbeats are
//! published: a follower's first heartbeat from a gateway reads the history of every sensor it
//! does not name, and one that names a batch still in flight reads up to it; the batches alone
//! carry the load (a building's heartbeat is one small message a second). History queries, if
//! any (a batch lost on the way), are answered empty and counted.

use std::collections::{BTreeMap, HashMap};
use std::io::Write;
use std::process::{Child, Command, Stdio};
use std::sync::atomic::{AtomicU64, Ordering::Relaxed};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use triax_modal::sim::SimBuilding;
use triax_protocol::batch::CorrectedSample;
use triax_protocol::messages::BuildingModes;
use triax_protocol::{from_json, BuildingId, Key, SensorId};

// The benches' /proc readers.
use triax_test_support::proc as bench_proc;

/// The service's default window, s of the sensors' clocks.
const WINDOW_S: i64 = 1800;
const WINDOW_NS: i64 = WINDOW_S * 1_000_000_000;
const RATE_HZ: f64 = 100.0;
const SAMPLE_NS: i64 = 10_000_000;
const STANDARD_GRAVITY_MPS2: f64 = 9.806_65;
/// Wall time to wait for a window's modes after its last batch before giving up on them.
const MODES_TIMEOUT: Duration = Duration::from_secs(300);

struct Args {
    buildings: usize,
    speed: f64,
    windows: i64,
    batch: usize,
}

fn args() -> Args {
    let mut a = Args {
        buildings: 10,
        speed: 10.0,
        windows: 2,
        batch: 10,
    };
    let mut it = std::env::args().skip(1);
    while let Some(flag) = it.next() {
        let mut value = || it.next().and_then(|v| v.parse::<f64>().ok());
        match flag.as_str() {
            "--buildings" => a.buildings = value().expect("a number") as usize,
            "--speed" => a.speed = value().expect("a number"),
            "--windows" => a.windows = value().expect("a number") as i64,
            "--batch" => a.batch = value().expect("a number") as usize,
            // cargo bench passes `--bench`.
            _ => {}
        }
    }
    assert!(a.buildings >= 1 && a.speed > 0.0 && a.windows >= 1);
    // A batch must not straddle a window's boundary: its duration divides the window.
    assert!(
        a.batch >= 1 && (WINDOW_NS % (a.batch as i64 * SAMPLE_NS)) == 0,
        "--batch must divide the window"
    );
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

/// The CPU seconds of the service's identification thread (named `triax-identify`).
fn identify_cpu_seconds(pid: u32) -> f64 {
    bench_proc::named_threads_cpu_seconds(pid, "triax-identify").unwrap_or(0.0)
}

/// A `/proc/<pid>/status` figure in MiB (`VmRSS`, `VmHWM`: the peak).
fn status_mib(pid: u32, field: &str) -> f64 {
    bench_proc::proc_status_kib(pid, field).map_or(0.0, |kib| kib as f64 / 1024.0)
}

fn load_average() -> String {
    std::fs::read_to_string("/proc/loadavg")
        .map(|l| l.split_whitespace().take(3).collect::<Vec<_>>().join(" "))
        .unwrap_or_default()
}

fn now_ns() -> i64 {
    let d = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .expect("after 1970");
    i64::try_from(d.as_nanos()).expect("before 2262")
}

/// The service's configuration: every building the simulated one, default window and
/// identification, the simulation's chain uncertainty, its state in `dir`.
fn service_toml(sim: &SimBuilding, buildings: &[BuildingId], dir: &std::path::Path) -> String {
    let chain = sim.config.chain;
    let mut toml = format!(
        "state_dir = {:?}\nsigning_key_file = {:?}\n",
        dir.join("state").display().to_string(),
        dir.join("modes.key").display().to_string()
    );
    for b in buildings {
        toml.push_str(&format!(
            "\n[buildings.{b}]\n[buildings.{b}.chain]\ngain_relative_u = {:?}\n\
             cross_axis_u = {:?}\ndof = {:?}\ntimestamp_u_s = {:?}\n",
            chain.gain_relative_u, chain.cross_axis_u, chain.dof, chain.timestamp_u_s
        ));
        for s in &sim.model.sensors {
            toml.push_str(&format!(
                "[[buildings.{b}.sensors]]\nsensor_id = {:?}\nfloor = {}\nheight_m = {:?}\n\
                 position_m = {:?}\nmounting = {:?}\n",
                s.sensor_id, s.floor, s.height_m, s.position_m, s.mounting
            ));
        }
    }
    toml
}

/// A modes message as it arrived.
struct Arrival {
    at: Instant,
    building: BuildingId,
    index: i64,
    refused: Option<String>,
    modes: usize,
}

/// What the modes subscription saw, and the service's CPU at the moment a window's last
/// building was published.
#[derive(Default)]
struct Seen {
    arrivals: Vec<Arrival>,
    per_window: HashMap<i64, usize>,
    /// Per window, when its last building's modes arrived: (wall, service CPU s, of it the
    /// identification thread's).
    complete: HashMap<i64, (Instant, f64, f64)>,
}

fn quantile(sorted: &[f64], p: f64) -> f64 {
    if sorted.is_empty() {
        return f64::NAN;
    }
    sorted[((sorted.len() - 1) as f64 * p).round() as usize]
}

#[tokio::main(flavor = "multi_thread", worker_threads = 2)]
async fn main() {
    let a = args();
    let load_start = load_average();
    let equivalent = a.buildings as f64 * a.speed;

    // The motion is simulated once, one window, and replayed for every building and window:
    // the cost does not depend on the data being fresh. The samples are what a gateway
    // publishes corrected: the simulated acceleration in the sensor's axes, gravity on its z.
    let sim = SimBuilding::five_storey(7);
    let window = sim.simulate(sim.frame.reference_temperature_c, WINDOW_S as f64, 0, 3);
    let motion: Vec<Vec<CorrectedSample>> = window
        .sensors
        .iter()
        .map(|s| {
            s.acceleration_mps2
                .iter()
                .map(|a| CorrectedSample {
                    accel_mps2: [
                        a[0] as f32,
                        a[1] as f32,
                        (a[2] + STANDARD_GRAVITY_MPS2) as f32,
                    ],
                    uncertainty_mps2: [0.003; 3],
                    flags: 0,
                })
                .collect()
        })
        .collect();
    assert_eq!(motion[0].len() as i64 * SAMPLE_NS, WINDOW_NS);

    let port = triax_net::free_loopback_port().expect("a port");
    let endpoint = format!("tcp/127.0.0.1:{port}");
    let mut zc = zenoh::Config::default();
    for (k, v) in [
        ("mode", "\"peer\"".to_owned()),
        ("listen/endpoints", format!("[\"{endpoint}\"]")),
        ("scouting/multicast/enabled", "false".to_owned()),
    ] {
        zc.insert_json5(k, &v).expect("valid setting");
    }
    let session = zenoh::open(zc).await.expect("session");

    let buildings: Vec<BuildingId> = (0..a.buildings)
        .map(|b| BuildingId::new(format!("b{b:03}")).expect("id"))
        .collect();
    let sensors: Vec<SensorId> = sim
        .model
        .sensors
        .iter()
        .map(|s| SensorId::new(s.sensor_id.clone()).expect("id"))
        .collect();
    // Blocking, not dropping as a gateway's do: a batch lost here would be a gap in the
    // window (the history this bench plays is empty), and the offered rate is reported as
    // achieved.
    let mut publishers = Vec::new();
    for b in &buildings {
        for s in &sensors {
            publishers.push(
                session
                    .declare_publisher(Key::Corrected(b.clone(), s.clone()).to_string())
                    .congestion_control(zenoh::qos::CongestionControl::Block)
                    .await
                    .expect("publisher"),
            );
        }
    }
    let history_queries = Arc::new(AtomicU64::new(0));
    let hq = history_queries.clone();
    // Answered empty: dropping the query ends it with no reply.
    let _history = session
        .declare_queryable("triax/*/history/*")
        .callback(move |_query| {
            hq.fetch_add(1, Relaxed);
        })
        .await
        .expect("queryable");

    let dir = tempfile::tempdir().expect("tempdir");
    let config = dir.path().join("modes.toml");
    std::fs::File::create(&config)
        .and_then(|mut f| f.write_all(service_toml(&sim, &buildings, dir.path()).as_bytes()))
        .expect("config");

    // The sensors' clock starts now, before the service's followers do: each follows a sensor
    // it meets for the first time from its own start, and a first batch stamped earlier is
    // handed over as it comes, with no history read. On a batch boundary, so that no batch
    // straddles a window's.
    let batch_ns = a.batch as i64 * SAMPLE_NS;
    let t0_ns = now_ns().div_euclid(batch_ns) * batch_ns;
    let spawned = Instant::now();
    let log = dir.path().join("triax-modes.log");
    let service = Reaped(
        Command::new(env!("CARGO_BIN_EXE_triax-modes"))
            .arg("--config")
            .arg(&config)
            .args(["--connect", &endpoint, "--no-multicast-scouting"])
            .env("RUST_LOG", "info")
            .stdout(Stdio::null())
            .stderr(std::fs::File::create(&log).expect("log file"))
            .spawn()
            .expect("triax-modes"),
    );
    let pid = service.0.id();

    let seen: Arc<Mutex<Seen>> = Arc::default();
    let (seen_sub, n_buildings) = (seen.clone(), a.buildings);
    let _modes = session
        .declare_subscriber("triax/*/modes")
        .callback(move |s| {
            let at = Instant::now();
            let Ok(m) = from_json::<BuildingModes>(&s.payload().to_bytes()) else {
                eprintln!("a modes message that does not decode");
                return;
            };
            let index = m.window_start_ns.div_euclid(WINDOW_NS);
            let mut seen = seen_sub.lock().expect("lock");
            let n = seen.per_window.entry(index).or_default();
            *n += 1;
            if *n == n_buildings {
                // Read here, as the window's last building is published: the CPU over the
                // full windows runs from one such moment to another.
                seen.complete
                    .insert(index, (at, cpu_seconds(pid), identify_cpu_seconds(pid)));
            }
            seen.arrivals.push(Arrival {
                at,
                building: m.building,
                index,
                refused: m.refused,
                modes: m.modes.len(),
            });
        })
        .await
        .expect("subscriber");

    // The service subscribes to every building's corrected streams with one wildcard, then
    // starts a follower per building: batches published before then would reach no follower.
    let ready = Instant::now();
    while !publishers[0]
        .matching_status()
        .await
        .expect("matching status")
        .matching()
    {
        assert!(
            ready.elapsed() < Duration::from_secs(60),
            "triax-modes did not subscribe within 60 s (log: {})",
            std::fs::read_to_string(&log).unwrap_or_default()
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    tokio::time::sleep(Duration::from_secs(1)).await;

    let first = t0_ns.div_euclid(WINDOW_NS);
    let last = first + a.windows;
    // Sensor time t0 + k·batch is due at wall time k·batch / S after the start.
    let wall_per_batch = Duration::from_secs_f64(batch_ns as f64 / 1e9 / a.speed);
    let started = Instant::now();
    let (cpu_started, identify_started) = (cpu_seconds(pid), identify_cpu_seconds(pid));
    let bench_cpu_started = cpu_seconds(std::process::id());
    let mut last_batch_at: BTreeMap<i64, Instant> = BTreeMap::new();
    let mut k: i64 = 0;
    let mut batches = 0u64;
    // How far the sensors' clock fell behind its schedule at worst (this process was late).
    let mut worst_lag = Duration::ZERO;
    let timed_out = loop {
        let due = started + wall_per_batch.mul_f64(k as f64);
        let now = Instant::now();
        if now < due {
            tokio::time::sleep_until(due.into()).await;
        } else {
            worst_lag = worst_lag.max(now - due);
        }
        let ts = t0_ns + k * batch_ns;
        // The sample of the simulated window at the same place in this window.
        let from = (ts.rem_euclid(WINDOW_NS) / SAMPLE_NS) as usize;
        for (i, p) in publishers.iter().enumerate() {
            let s = i % sensors.len();
            let batch = triax_protocol::batch::sample::dynamic(
                sensors[s].clone(),
                k as u64,
                ts,
                RATE_HZ,
                motion[s][from..from + a.batch].to_vec(),
            );
            p.put(batch.encode()).await.expect("put");
        }
        batches += publishers.len() as u64;
        k += 1;
        let next_ts = t0_ns + k * batch_ns;
        if next_ts % WINDOW_NS == 0 {
            // The round just published ended a window, for every building.
            last_batch_at.insert(next_ts / WINDOW_NS - 1, Instant::now());
        }
        // Until the last full window's modes are all out; the load goes on meanwhile.
        if let Some(&end) = last_batch_at.get(&last) {
            if seen.lock().expect("lock").complete.contains_key(&last) {
                break false;
            }
            if end.elapsed() > MODES_TIMEOUT {
                break true;
            }
        }
    };
    let elapsed = started.elapsed().as_secs_f64();
    let cpu_end = cpu_seconds(pid);
    let identify_end = identify_cpu_seconds(pid);
    let bench_cpu = (cpu_seconds(std::process::id()) - bench_cpu_started) / elapsed;
    let (rss, peak) = (status_mib(pid, "VmRSS:"), status_mib(pid, "VmHWM:"));
    let whole = spawned.elapsed().as_secs_f64();
    drop(service);
    let load_end = load_average();
    let seen = seen.lock().expect("lock");

    let samples_per_s = batches as f64 * a.batch as f64 / elapsed;
    let full = match (seen.complete.get(&first), seen.complete.get(&last)) {
        (Some(a0), Some(a1)) => {
            let span = (a1.0 - a0.0).as_secs_f64();
            Some((span, (a1.1 - a0.1) / span, (a1.2 - a0.2) / span))
        }
        _ => None,
    };
    println!();
    println!(
        "triax-modes fleet: {} buildings × speed {} = {} buildings in real time; {} full windows \
         after the first; {}-sample batches",
        a.buildings, a.speed, equivalent, a.windows, a.batch
    );
    println!();
    println!("| figure | value |");
    println!("|---|---|");
    println!(
        "| corrected samples/s offered (achieved; {} in real time) | {:.0} ({:.0} batches/s) |",
        equivalent as u64 * 6 * 100,
        samples_per_s,
        batches as f64 / elapsed
    );
    println!(
        "| identification load | {} windows per 30 min of wall time |",
        equivalent
    );
    println!(
        "| triax-modes CPU, whole run ({:.0} s from its start) | {:.3} cores, of which identification {:.3} |",
        whole,
        cpu_end / whole,
        identify_end / whole
    );
    match full {
        Some((span, cores, identify)) => println!(
            "| triax-modes CPU over the full windows ({:.0} s: from the partial window's modes \
             to the last full window's) | {:.3} cores, of which identification {:.3} |",
            span, cores, identify
        ),
        None => println!("| triax-modes CPU over the full windows | not measured: modes missing |"),
    }
    println!(
        "| triax-modes CPU while publishing ({:.0} s) | {:.3} cores, of which identification {:.3} |",
        elapsed,
        (cpu_end - cpu_started) / elapsed,
        (identify_end - identify_started) / elapsed
    );
    println!("| triax-modes RSS at the end / peak | {rss:.0} MiB / {peak:.0} MiB |");
    println!("| this bench (the gateways) CPU | {bench_cpu:.2} cores |");
    println!(
        "| history queries (answered empty) | {} |",
        history_queries.load(Relaxed)
    );
    println!(
        "| the sensors' clock behind its schedule, at worst | {:.0} ms of wall time |",
        worst_lag.as_secs_f64() * 1e3
    );
    println!("| load average at start / end | {load_start} / {load_end} |");
    println!();
    println!("| window | start (sensor clock) | identified | refused | modes per building, median | delay from its last batch to the modes, p50 / max |");
    println!("|---|---|---|---|---|---|");
    let mut refusals: BTreeMap<String, usize> = BTreeMap::new();
    let mut full_delays: Vec<f64> = Vec::new();
    let mut per_building: BTreeMap<&BuildingId, (usize, usize)> = BTreeMap::new();
    for index in first..=last {
        let here: Vec<&Arrival> = seen.arrivals.iter().filter(|r| r.index == index).collect();
        let refused = here.iter().filter(|r| r.refused.is_some()).count();
        for r in &here {
            let e = per_building.entry(&r.building).or_default();
            if let Some(why) = &r.refused {
                *refusals.entry(why.clone()).or_default() += 1;
                e.1 += 1;
            } else {
                e.0 += 1;
            }
        }
        let mut modes: Vec<f64> = here.iter().map(|r| r.modes as f64).collect();
        modes.sort_by(f64::total_cmp);
        let mut delays: Vec<f64> = match last_batch_at.get(&index) {
            Some(end) => here
                .iter()
                .map(|r| r.at.saturating_duration_since(*end).as_secs_f64())
                .collect(),
            None => Vec::new(),
        };
        delays.sort_by(f64::total_cmp);
        if index > first {
            full_delays.extend(&delays);
        }
        let start = time::OffsetDateTime::from_unix_timestamp(index * WINDOW_S)
            .map(|t| format!("{} {:02}:{:02}", t.date(), t.hour(), t.minute()))
            .unwrap_or_default();
        let kind = if index == first { " (partial)" } else { "" };
        println!(
            "| {}{kind} | {start} | {} of {} | {refused} | {} | {:.2} s / {:.2} s |",
            index - first,
            here.len() - refused,
            a.buildings,
            quantile(&modes, 0.5),
            quantile(&delays, 0.5),
            quantile(&delays, 1.0),
        );
    }
    full_delays.sort_by(f64::total_cmp);
    println!(
        "\nfull windows: delay from a window's last batch to a building's modes p50 {:.2} s, \
         max {:.2} s ({} messages)",
        quantile(&full_delays, 0.5),
        quantile(&full_delays, 1.0),
        full_delays.len()
    );
    let counts: BTreeMap<(usize, usize), usize> =
        per_building.values().fold(BTreeMap::new(), |mut m, &c| {
            *m.entry(c).or_default() += 1;
            m
        });
    for ((identified, refused), n) in counts {
        println!("{n} buildings: {identified} windows identified, {refused} refused");
    }
    for (why, n) in &refusals {
        println!("refused {n}×: {why}");
    }
    if timed_out || full.is_none() {
        eprintln!(
            "the last window's modes did not all arrive within {} s; the service's log ends:",
            MODES_TIMEOUT.as_secs()
        );
        let text = std::fs::read_to_string(&log).unwrap_or_default();
        let tail: Vec<&str> = text.lines().rev().take(20).collect();
        for line in tail.into_iter().rev() {
            eprintln!("  {line}");
        }
    }
}
