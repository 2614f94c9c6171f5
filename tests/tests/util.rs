//! Helpers shared by the gateway tests: loopback ports, a gateway started and stopped at will,
//! Zenoh client sessions, simulated raw batches.
#![allow(dead_code)] // Each test binary that includes this module uses a different subset.

use std::collections::BTreeMap;
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use tokio::sync::oneshot;
use tokio::task::JoinHandle;
use triax_calibration_store::Store;
use triax_gateway::{Config, Gateway};
use triax_net::{ZenohMode, ZenohSettings};
use triax_protocol::batch::{BatchHeader, CorrectedBatch, RawBatch};
use triax_protocol::record::CalibrationRecord;
use triax_protocol::{BuildingId, Key, SensorId};

/// Longest any step of a test waits for an event: generous, so that only a real failure
/// reaches it, however loaded the machine (a step that should take milliseconds may take
/// seconds while two test binaries and a build share two cores).
pub const TIMEOUT: Duration = Duration::from_secs(60);

/// Key of a sensor's raw stream.
pub fn key_raw(b: &str, s: &str) -> String {
    Key::Raw(BuildingId::new(b).unwrap(), SensorId::new(s).unwrap()).to_string()
}

/// Key of a sensor's corrected stream.
pub fn key_corrected(b: &str, s: &str) -> String {
    Key::Corrected(BuildingId::new(b).unwrap(), SensorId::new(s).unwrap()).to_string()
}

/// A node's publisher that blocks rather than drops when the link is full, so that a burst
/// reaches the gateway whole, once the gateway's subscription matches it.
pub async fn blocking_publisher(
    session: &zenoh::Session,
    key: String,
) -> zenoh::pubsub::Publisher<'static> {
    let publisher = session
        .declare_publisher(key)
        .congestion_control(zenoh::qos::CongestionControl::Block)
        .await
        .unwrap();
    wait_matching(&publisher).await;
    publisher
}

/// The gateway's status of building `b` (the first page).
pub async fn status(session: &zenoh::Session, b: &str) -> triax_protocol::messages::GatewayStatus {
    try_status(session, b)
        .await
        .expect("the gateway answers its status")
}

/// The gateway's status of building `b`, or none when no gateway answered: one that has just
/// started may not be reachable from `session` yet, and a test waiting for an event polls on.
pub async fn try_status(
    session: &zenoh::Session,
    b: &str,
) -> Option<triax_protocol::messages::GatewayStatus> {
    let replies = session
        .get(Key::Status(BuildingId::new(b).unwrap()).to_string())
        .timeout(TIMEOUT)
        .await
        .expect("status query sent");
    let reply = tokio::time::timeout(TIMEOUT, replies.recv_async())
        .await
        .expect("status answered in time")
        .ok()?;
    let sample = reply.result().expect("status reply is not an error");
    Some(triax_protocol::from_json(&sample.payload().to_bytes()).expect("status decodes"))
}

/// A loopback TCP port nobody listens on right now (see [`triax_net::free_loopback_port`]).
pub fn free_port() -> u16 {
    triax_net::free_loopback_port().expect("loopback is available")
}

/// Returns as soon as `cond` holds, checked every millisecond; fails the test, naming `what`,
/// after [`TIMEOUT`].
pub async fn wait_until(what: &str, cond: impl Fn() -> bool) {
    let deadline = tokio::time::Instant::now() + TIMEOUT;
    while !cond() {
        assert!(
            tokio::time::Instant::now() < deadline,
            "timed out waiting for {what}"
        );
        tokio::time::sleep(Duration::from_millis(1)).await;
    }
}

/// Returns as soon as the asynchronous `cond` holds, checked every 50 ms; fails the test,
/// naming `what`, after [`TIMEOUT`].
pub async fn wait_until_async<F, Fut>(what: &str, cond: F)
where
    F: Fn() -> Fut,
    Fut: std::future::Future<Output = bool>,
{
    let deadline = tokio::time::Instant::now() + TIMEOUT;
    while !cond().await {
        assert!(
            tokio::time::Instant::now() < deadline,
            "timed out waiting for {what}"
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

/// Returns once something accepts connections on `port` of 127.0.0.1: a listener there is up.
pub async fn wait_for_listener(port: u16) {
    let deadline = tokio::time::Instant::now() + TIMEOUT;
    while tokio::net::TcpStream::connect(("127.0.0.1", port))
        .await
        .is_err()
    {
        assert!(
            tokio::time::Instant::now() < deadline,
            "nothing listened on 127.0.0.1:{port} in time"
        );
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
}

/// A `zenohd` router on a loopback port, killed when dropped.
pub struct Router {
    pub endpoint: String,
    child: Child,
}

impl Router {
    pub async fn start() -> Router {
        Router::start_on(free_port()).await
    }

    /// Kills the router, waits `down`, and starts it again on the same endpoint: a site link
    /// that goes away and comes back.
    pub async fn restart_after(&mut self, down: Duration) {
        let _ = self.child.kill();
        let _ = self.child.wait();
        tokio::time::sleep(down).await;
        let port = self
            .endpoint
            .rsplit(':')
            .next()
            .and_then(|p| p.parse().ok())
            .expect("the endpoint names a port");
        // The old router, already reaped, is dropped here.
        *self = Router::start_on(port).await;
    }

    async fn start_on(port: u16) -> Router {
        let endpoint = format!("tcp/127.0.0.1:{port}");
        let child = Command::new("zenohd")
            .args(["--no-multicast-scouting", "--listen", &endpoint])
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .unwrap_or_else(|e| {
                panic!(
                    "cannot start `zenohd` ({e}): these tests need the Zenoh router on PATH; \
                     install it with `cargo install zenohd --version 1.10.2 --locked`"
                )
            });
        wait_for_listener(port).await;
        Router { endpoint, child }
    }

    /// Settings of a client of this router, on loopback.
    pub fn client_settings(&self) -> ZenohSettings {
        ZenohSettings::loopback(ZenohMode::Client, vec![], vec![self.endpoint.clone()])
    }
}

impl Drop for Router {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// Writes records into the store at `path` (the store must not be open elsewhere).
pub fn seed_store(path: &Path, records: &[CalibrationRecord]) {
    let store = Store::open(path).expect("store opens");
    for r in records {
        store
            .put(r)
            .expect("store works")
            .expect("record is accepted");
    }
}

/// A gateway running in the background.
pub struct Running {
    pub endpoint: String,
    pub metrics: Option<std::net::SocketAddr>,
    stop: Option<oneshot::Sender<()>>,
    task: JoinHandle<Result<(), triax_gateway::GatewayError>>,
}

impl Running {
    /// Stops the gateway and waits until it has released the store.
    pub async fn stop(mut self) {
        if let Some(s) = self.stop.take() {
            let _ = s.send(());
        }
        tokio::time::timeout(TIMEOUT, &mut self.task)
            .await
            .expect("gateway stops in time")
            .expect("gateway task does not panic")
            .expect("gateway stops cleanly");
    }
}

/// A test configuration: building `building`, store at `store`, listening on a fresh port.
pub fn config(building: &str, store: &Path) -> Config {
    let endpoint = format!("tcp/127.0.0.1:{}", free_port());
    Config::for_tests(building, store, vec![endpoint])
}

/// Starts a gateway; `endpoint` is where it listens, or, for a client of a router, the router.
pub async fn start(config: Config) -> Running {
    let endpoint = config
        .zenoh
        .listen
        .first()
        .or(config.zenoh.connect.first())
        .expect("a test gateway listens or connects")
        .clone();
    let gateway = Gateway::start(config).await.expect("gateway starts");
    let metrics = gateway.metrics_addr();
    let (tx, rx) = oneshot::channel::<()>();
    let task = tokio::spawn(gateway.run_until(async move {
        let _ = rx.await;
    }));
    Running {
        endpoint,
        metrics,
        stop: Some(tx),
        task,
    }
}

/// A peer session connected to `endpoint`, with no scouting and no listener.
pub async fn client(endpoint: &str) -> zenoh::Session {
    client_of(&[endpoint]).await
}

/// A peer session connected to every one of `endpoints`, with no scouting and no listener.
pub async fn client_of(endpoints: &[&str]) -> zenoh::Session {
    let list = endpoints
        .iter()
        .map(|e| format!("\"{e}\""))
        .collect::<Vec<_>>()
        .join(",");
    peer(&[
        ("connect/endpoints", format!("[{list}]")),
        ("listen/endpoints", "[]".to_owned()),
    ])
    .await
}

/// A peer session listening on `endpoint`, with no scouting: one that outlives the gateways
/// that connect to it.
pub async fn listening_peer(endpoint: &str) -> zenoh::Session {
    peer(&[("listen/endpoints", format!("[\"{endpoint}\"]"))]).await
}

/// A peer session with multicast scouting off and `settings` (JSON5 values by key).
async fn peer(settings: &[(&str, String)]) -> zenoh::Session {
    let mut c = zenoh::Config::default();
    c.insert_json5("mode", "\"peer\"")
        .expect("valid zenoh setting");
    c.insert_json5("scouting/multicast/enabled", "false")
        .expect("valid zenoh setting");
    for (k, v) in settings {
        c.insert_json5(k, v).expect("valid zenoh setting");
    }
    zenoh::open(c).await.expect("peer session opens")
}

/// Runs a gateway with `config` in this process (a test binary started as a child by its
/// test, so that it can be killed) until its standard input closes, as the binary does on
/// SIGTERM; logs at info on standard error, which the parent keeps.
pub fn run_gateway_until_stdin_closes(config: Config) {
    triax_gateway::init_logging("info").expect("logging starts once");
    triax_test_support::child::run_until_stdin_closes(|stdin_closed| {
        triax_gateway::run(config, stdin_closed)
    })
    .expect("the child gateway runs");
}

/// Waits until `publisher` has a matching subscriber (the gateway's).
pub async fn wait_matching(publisher: &zenoh::pubsub::Publisher<'_>) {
    let deadline = tokio::time::Instant::now() + TIMEOUT;
    while !publisher
        .matching_status()
        .await
        .expect("matching status")
        .matching()
    {
        assert!(
            tokio::time::Instant::now() < deadline,
            "no subscriber matched in time"
        );
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
}

/// Receives `n` corrected batches from a subscriber's channel.
pub async fn collect(
    sub: &zenoh::pubsub::Subscriber<zenoh::handlers::FifoChannelHandler<zenoh::sample::Sample>>,
    n: usize,
) -> Vec<CorrectedBatch> {
    let mut out = Vec::with_capacity(n);
    while out.len() < n {
        let s = tokio::time::timeout(TIMEOUT, sub.recv_async())
            .await
            .unwrap_or_else(|_| panic!("only {} of {n} corrected batches arrived", out.len()))
            .expect("subscriber open");
        out.push(CorrectedBatch::decode(&s.payload().to_bytes()).expect("corrected batch decodes"));
    }
    out
}

/// A raw batch at 100 Hz starting at `sequence × n / 100` seconds after a fixed epoch.
pub fn raw(sensor: &str, sequence: u64, samples: Vec<[f32; 3]>) -> Vec<u8> {
    let n = samples.len() as i64;
    RawBatch {
        header: BatchHeader {
            sensor_id: SensorId::new(sensor).expect("test ids are valid"),
            sequence,
            timestamp_ns: 1_800_000_000_000_000_000 + sequence as i64 * n * 10_000_000,
            sample_rate_hz: 100.0,
        },
        temperature_c: None,
        samples,
    }
    .encode()
}

/// Outputs of a sensor with sensitivity `s` and offset `q` under acceleration `a`:
/// `V = S·(a − q)`.
pub fn outputs(s: &[[f64; 3]; 3], q: &[f64; 3], a: [f64; 3]) -> [f64; 3] {
    let d = [a[0] - q[0], a[1] - q[1], a[2] - q[2]];
    [0, 1, 2].map(|i| s[i][0] * d[0] + s[i][1] * d[1] + s[i][2] * d[2])
}

/// Returns once the gateway's history for `building` answers with `sequence` for `sensor`:
/// everything put up to it has then been corrected and kept.
pub async fn wait_history_holds(
    session: &zenoh::Session,
    building: &str,
    sensor: &str,
    sequence: u64,
) {
    let mut request = triax_client::HistoryRequest::sensor(
        &BuildingId::new(building).unwrap(),
        &SensorId::new(sensor).unwrap(),
    );
    request.from_seq = Some(sequence);
    request.to_seq = Some(sequence);
    wait_until_async(
        &format!("{building}/{sensor} #{sequence} in the history"),
        || async {
            triax_client::history::fetch(session, &request, TIMEOUT, &mut |_| {})
                .await
                .is_ok_and(|n| n > 0)
        },
    )
    .await;
}

/// A sensor node's buffer (PROTOCOL.md §5.4) as a test plays it: every batch it made, by sensor
/// and number, answered on its buffer key. Not publishing a kept batch is a link cut, exactly.
/// A buffer's batches, by sensor and number.
type Held = BTreeMap<(String, u64), Vec<u8>>;

#[derive(Default, Clone)]
pub struct Buffer {
    held: Arc<Mutex<Held>>,
    /// While true, answers wait (a node slow to answer, or the test ordering events).
    paused: Arc<(Mutex<bool>, std::sync::Condvar)>,
    /// Replies still to be lost (a busy link): each answer skips its middle batch while any are.
    lose: Arc<std::sync::atomic::AtomicUsize>,
}

impl Buffer {
    /// Answers wait from now until [`Buffer::answer`].
    pub fn pause(&self) {
        *self.paused.0.lock().unwrap() = true;
    }

    /// The next `n` answers of two batches or more each lose their middle batch.
    pub fn lose_replies(&self, n: usize) {
        self.lose.store(n, std::sync::atomic::Ordering::Relaxed);
    }

    pub fn answer(&self) {
        *self.paused.0.lock().unwrap() = false;
        self.paused.1.notify_all();
    }

    pub fn keep(&self, sensor: &str, seq: u64, payload: &[u8]) {
        self.held
            .lock()
            .unwrap()
            .insert((sensor.to_owned(), seq), payload.to_vec());
    }

    /// Answers §5.4 batch queries for `building` (no status, no error cases: the gateway asks
    /// well-formed ranges).
    pub async fn serve(
        &self,
        session: &zenoh::Session,
        building: &str,
    ) -> zenoh::query::Queryable<()> {
        let (held, paused, lose) = (self.held.clone(), self.paused.clone(), self.lose.clone());
        session
            .declare_queryable(format!("triax/{building}/buffer/*"))
            .callback(move |q| {
                let sensor = q.key_expr().as_str().rsplit('/').next().unwrap().to_owned();
                let p = q.parameters();
                let from: u64 = p.get("from_seq").unwrap().parse().unwrap();
                let to: u64 = p.get("to_seq").unwrap().parse().unwrap();
                let mut batches: Vec<Vec<u8>> = held
                    .lock()
                    .unwrap()
                    .range((sensor.clone(), from)..=(sensor.clone(), to))
                    .map(|(_, b)| b.clone())
                    .collect();
                let lost = batches.len() >= 2
                    && lose
                        .fetch_update(
                            std::sync::atomic::Ordering::Relaxed,
                            std::sync::atomic::Ordering::Relaxed,
                            |n| n.checked_sub(1),
                        )
                        .is_ok();
                if lost {
                    batches.remove(batches.len() / 2);
                }
                let key = q.key_expr().clone();
                // Replies in order, from a thread of its own: Zenoh's callback must not block.
                let paused = paused.clone();
                std::thread::spawn(move || {
                    use zenoh::Wait;
                    let (lock, answer) = &*paused;
                    let mut p = lock.lock().unwrap();
                    while *p {
                        p = answer.wait(p).unwrap();
                    }
                    drop(p);
                    for b in batches {
                        q.reply(key.clone(), b).wait().unwrap();
                    }
                });
            })
            .await
            .unwrap()
    }
}
