//! Prometheus metrics over HTTP: a small responder on a tokio listener that answers
//! `GET /metrics` with the text exposition format, and 404 to anything else.
//!
//! Hand-rolled because the endpoint is one read-only page: an HTTP framework would be most of
//! the gateway's dependencies for it. Requests are read up to a size and time limit, answered,
//! and the connection closed.

use std::fmt::Write as _;
use std::net::SocketAddr;
use std::sync::atomic::Ordering::Relaxed;
use std::sync::Arc;
use std::time::Duration;

use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpListener, TcpStream};

use triax_protocol::keys::RawKeyRefusal;
use triax_protocol::messages::{HealthVerdict, HistoryStatus};

use super::{Context, Task};
use crate::error::GatewayError;
use crate::sample_path::SamplePath;
use crate::sample_path::Sink;
use crate::shutdown::Shutdown;
use crate::state::{BackfillCounters, GatewayCounters, SensorCounters, SensorEntry, SensorTable};

/// Longest request head read.
const MAX_REQUEST_BYTES: usize = 8 * 1024;
/// Time a client gets to send its request.
const REQUEST_TIMEOUT: Duration = Duration::from_secs(5);

/// What the page reports.
#[derive(Clone)]
pub struct MetricsSource {
    pub table: Arc<SensorTable>,
    pub counters: Arc<GatewayCounters>,
    pub history: Option<Arc<Sink>>,
    pub backfill: Option<Arc<BackfillCounters>>,
    pub queued: Arc<dyn Fn() -> usize + Send + Sync>,
}

/// Writes one metric family: its help, its type and one line per labelled value (`labels` is
/// the text between the braces, empty for none).
fn family(
    out: &mut String,
    name: &str,
    kind: &str,
    help: &str,
    values: impl IntoIterator<Item = (String, u64)>,
) {
    // Writing to a String cannot fail.
    let _ = writeln!(out, "# HELP {name} {help}\n# TYPE {name} {kind}");
    for (labels, v) in values {
        let _ = match labels.is_empty() {
            true => writeln!(out, "{name} {v}"),
            false => writeln!(out, "{name}{{{labels}}} {v}"),
        };
    }
}

/// One unlabelled value.
fn single(v: u64) -> [(String, u64); 1] {
    [(String::new(), v)]
}

/// Renders the metrics page.
pub fn render(src: &MetricsSource) -> String {
    let mut out = String::with_capacity(4096);
    render_flow(&mut out, src);
    render_intake(&mut out, src);
    if let Some(h) = &src.history {
        render_history(&mut out, &h.status());
    }
    if let Some(b) = &src.backfill {
        render_backfill(&mut out, &b.status());
    }
    render_sensors(&mut out, &src.table.snapshot());
    out
}

/// Batches through the gateway, and its resources.
fn render_flow(out: &mut String, src: &MetricsSource) {
    let c = &src.counters;
    let counters: [(&str, &str, u64); 6] = [
        (
            "triax_gateway_received_batches_total",
            "Raw payloads taken from Zenoh, before any check.",
            c.received_batches.load(Relaxed),
        ),
        (
            "triax_gateway_malformed_payloads_total",
            "Payloads that did not decode.",
            c.malformed.load(Relaxed),
        ),
        (
            "triax_gateway_dropped_batches_total",
            "Raw batches dropped from a full queue (drop-oldest).",
            c.dropped.load(Relaxed),
        ),
        (
            "triax_gateway_published_batches_total",
            "Corrected batches published.",
            c.published_batches.load(Relaxed),
        ),
        (
            "triax_gateway_publish_errors_total",
            "Corrected batches Zenoh refused to publish.",
            c.publish_errors.load(Relaxed),
        ),
        (
            "triax_gateway_tilt_samples_total",
            "Tilt samples published.",
            c.tilt_samples.load(Relaxed),
        ),
    ];
    for (name, help, v) in counters {
        family(out, name, "counter", help, single(v));
    }
    let gauges: [(&str, &str, u64); 3] = [
        (
            "triax_gateway_queued_batches",
            "Raw batches waiting for a worker.",
            (src.queued)() as u64,
        ),
        (
            "triax_gateway_sensors_online",
            "Sensors whose stream is being corrected (seen since start).",
            c.sensors_online.load(Relaxed),
        ),
        (
            "triax_gateway_declared_keys",
            "Keys declared to Zenoh (raw and output); further sensors' keys are used undeclared.",
            c.declared_keys.load(Relaxed) as u64,
        ),
    ];
    for (name, help, v) in gauges {
        family(out, name, "gauge", help, single(v));
    }
    if let Some(bytes) = super::memory::resident_bytes() {
        family(
            out,
            "process_resident_memory_bytes",
            "gauge",
            "Resident memory of the gateway process.",
            single(bytes),
        );
    }
}

/// What the gateway refused to take on, and how it admits and forgets sensors.
fn render_intake(out: &mut String, src: &MetricsSource) {
    let c = &src.counters;
    family(
        out,
        "triax_gateway_refused_keys_total",
        "counter",
        "Raw payloads on a key that is not a concrete raw key of this building, by reason.",
        RawKeyRefusal::ALL.map(|r| (format!("reason=\"{}\"", r.as_str()), c.refused_keys(r))),
    );
    let a = &src.table.admission;
    let counters: [(&str, &str, u64); 4] = [
        (
            "triax_gateway_over_capacity_batches_total",
            "Raw batches skipped: a new sensor while max_sensors are calibrated or established.",
            c.over_capacity.load(Relaxed),
        ),
        (
            "triax_gateway_admitted_sensors_total",
            "New uncalibrated sensor ids admitted (on probation).",
            a.admitted.load(Relaxed),
        ),
        (
            "triax_gateway_displaced_sensors_total",
            "Sensors on probation forgotten to admit a new id while the table was full.",
            a.displaced.load(Relaxed),
        ),
        (
            "triax_gateway_expired_sensors_total",
            "Uncalibrated sensors forgotten after unknown_sensor_expiry_s of silence.",
            a.expired.load(Relaxed),
        ),
    ];
    for (name, help, v) in counters {
        family(out, name, "counter", help, single(v));
    }
}

/// Gaps filled from the nodes' buffers.
fn render_backfill(out: &mut String, b: &triax_protocol::messages::BackfillStatus) {
    let counters: [(&str, &str, u64); 6] = [
        (
            "triax_backfill_queries_total",
            "Queries sent to nodes' buffers.",
            b.queries,
        ),
        (
            "triax_backfill_wanted_batches_total",
            "Batches gaps and the gateway's downtime asked for.",
            b.wanted_batches,
        ),
        (
            "triax_backfill_late_batches_total",
            "Batches fetched, corrected and published flagged late.",
            b.late_batches,
        ),
        (
            "triax_backfill_rejected_replies_total",
            "Buffer replies that were not a batch of the hole asked for.",
            b.rejected_replies,
        ),
        (
            "triax_backfill_failed_queries_total",
            "Buffer queries that ended in an error or timed out.",
            b.failed_queries,
        ),
        (
            "triax_backfill_refused_requests_total",
            "Gaps not asked for: the backfill queue was full.",
            b.refused_requests,
        ),
    ];
    for (name, help, v) in counters {
        family(out, name, "counter", help, single(v));
    }
}

/// The history: what it holds, and what it kept, dropped and deleted.
fn render_history(out: &mut String, h: &HistoryStatus) {
    let gauges: [(&str, &str, u64); 5] = [
        (
            "triax_history_bytes",
            "History on disk, logs and indexes.",
            h.bytes,
        ),
        (
            "triax_history_max_bytes",
            "Size cap of the history.",
            h.max_bytes,
        ),
        (
            "triax_history_segments",
            "History segments on disk.",
            h.segments,
        ),
        (
            "triax_history_queued_batches",
            "Batches waiting for the history writer.",
            h.queued_batches,
        ),
        (
            "triax_history_oldest_seconds",
            "First-sample time of the oldest batch kept, s since the Unix epoch (0: empty).",
            h.oldest_ns
                .map_or(0, |ns| (ns.max(0) / 1_000_000_000) as u64),
        ),
    ];
    for (name, help, v) in gauges {
        family(out, name, "gauge", help, single(v));
    }
    let counters: [(&str, &str, u64); 6] = [
        (
            "triax_history_written_batches_total",
            "Batches kept.",
            h.written_batches,
        ),
        (
            "triax_history_dropped_batches_total",
            "Batches not kept: the writer's queue was full.",
            h.dropped_batches,
        ),
        (
            "triax_history_deleted_segments_total",
            "Segments removed by retention.",
            h.deleted_segments,
        ),
        (
            "triax_history_deleted_bytes_total",
            "Bytes removed by retention.",
            h.deleted_bytes,
        ),
        (
            "triax_history_damaged_blocks_total",
            "Blocks that failed their check when read.",
            h.damaged_blocks,
        ),
        (
            "triax_history_write_errors_total",
            "History flushes that failed.",
            h.write_errors,
        ),
    ];
    for (name, help, v) in counters {
        family(out, name, "counter", help, single(v));
    }
}

/// Per-sensor counters, and the sensor population.
fn render_sensors(out: &mut String, sensors: &[Arc<SensorEntry>]) {
    family(
        out,
        "triax_gateway_sensors",
        "gauge",
        "Sensors known.",
        single(sensors.len() as u64),
    );
    family(
        out,
        "triax_gateway_uncalibrated_sensors",
        "gauge",
        "Sensors with no calibration in force.",
        single(
            sensors
                .iter()
                .filter(|s| s.calibration_version().is_none())
                .count() as u64,
        ),
    );
    type Field = fn(&SensorCounters) -> u64;
    let per_sensor: [(&str, &str, Field); 9] = [
        ("batches_total", "Raw batches received.", |c| {
            c.batches.load(Relaxed)
        }),
        ("samples_total", "Samples corrected and published.", |c| {
            c.samples.load(Relaxed)
        }),
        (
            "gaps_total",
            "Batches that followed a jump in sequence numbers.",
            |c| c.gaps.load(Relaxed),
        ),
        (
            "missing_batches_total",
            "Batches lost in gaps (as many as both the numbering and the clock allow).",
            |c| c.missing_batches.load(Relaxed),
        ),
        (
            "duplicate_batches_total",
            "Batches repeating or preceding a sequence number seen.",
            |c| c.duplicates.load(Relaxed),
        ),
        (
            "node_restarts_total",
            "Sequence restarts of the sensor node.",
            |c| c.restarts.load(Relaxed),
        ),
        (
            "rejected_payloads_total",
            "Malformed payloads on the sensor's key.",
            |c| c.rejects.load(Relaxed),
        ),
        (
            "flagged_samples_total",
            "Samples published with a quality flag.",
            |c| c.flagged_samples.load(Relaxed),
        ),
        (
            "uncalibrated_samples_total",
            "Samples published uncalibrated.",
            |c| c.uncalibrated_samples.load(Relaxed),
        ),
    ];
    let labels = |s: &SensorEntry| format!("sensor=\"{}\"", s.id);
    for (suffix, help, get) in per_sensor {
        family(
            out,
            &format!("triax_sensor_{suffix}"),
            "counter",
            help,
            sensors.iter().map(|s| (labels(s), get(&s.counters))),
        );
    }
    family(
        out,
        "triax_sensor_calibration_version",
        "gauge",
        "Version in force (0: uncalibrated).",
        sensors
            .iter()
            .map(|s| (labels(s), s.calibration_version().unwrap_or(0))),
    );
    render_health(out, sensors);
}

/// The calibration health verdicts: per sensor, and how many sensors have each.
fn render_health(out: &mut String, sensors: &[Arc<SensorEntry>]) {
    let judged: Vec<_> = sensors
        .iter()
        .filter_map(|s| s.health_verdict().map(|v| (s, v)))
        .collect();
    family(
        out,
        "triax_sensor_health",
        "gauge",
        "Calibration health verdict of the latest report: 0 ok, 1 watch, 2 suspect.",
        judged
            .iter()
            .map(|(s, v)| (format!("sensor=\"{}\"", s.id), *v as u64)),
    );
    family(
        out,
        "triax_gateway_health_sensors",
        "gauge",
        "Sensors by the verdict of their latest calibration health report.",
        [
            HealthVerdict::Ok,
            HealthVerdict::Watch,
            HealthVerdict::Suspect,
        ]
        .map(|verdict| {
            (
                format!("verdict=\"{}\"", verdict.as_str()),
                judged.iter().filter(|(_, v)| *v == verdict).count() as u64,
            )
        }),
    );
}

/// Binds the metrics endpoint when one is configured and serves it until shutdown; returns the
/// bound address.
pub async fn start(
    ctx: &Context,
    path: &SamplePath,
    backfill: Option<Arc<BackfillCounters>>,
) -> Result<Option<(SocketAddr, Task)>, GatewayError> {
    let Some(addr) = ctx.config.metrics_listen else {
        return Ok(None);
    };
    let src = MetricsSource {
        table: ctx.table.clone(),
        counters: ctx.counters.clone(),
        history: path.history().cloned(),
        backfill,
        queued: path.queued(),
    };
    bind_and_serve(addr, src, ctx.shutdown.clone())
        .await
        .map(Some)
}

async fn bind_and_serve(
    addr: SocketAddr,
    src: MetricsSource,
    shutdown: Shutdown,
) -> Result<(SocketAddr, Task), GatewayError> {
    let listener = tokio::net::TcpListener::bind(addr)
        .await
        .map_err(|source| GatewayError::Metrics { addr, source })?;
    let bound = listener
        .local_addr()
        .map_err(|source| GatewayError::Metrics { addr, source })?;
    tracing::info!(addr = %bound, "metrics at http://{bound}/metrics");
    Ok((bound, tokio::spawn(serve(listener, src, shutdown))))
}

/// Serves the page until shutdown.
pub async fn serve(listener: TcpListener, src: MetricsSource, mut shutdown: Shutdown) {
    loop {
        let accepted = tokio::select! {
            a = listener.accept() => a,
            _ = shutdown.recv() => return,
        };
        match accepted {
            Ok((stream, _)) => {
                let src = src.clone();
                tokio::spawn(async move {
                    if let Err(e) = answer(stream, &src).await {
                        tracing::debug!(cause = %e, "metrics request failed");
                    }
                });
            }
            Err(e) => {
                tracing::warn!(cause = %e, "metrics accept failed");
                // Out of file descriptors and the like: back off instead of spinning.
                tokio::time::sleep(Duration::from_millis(100)).await;
            }
        }
    }
}

async fn answer(mut stream: TcpStream, src: &MetricsSource) -> std::io::Result<()> {
    let mut buf = Vec::with_capacity(512);
    let read = async {
        let mut chunk = [0u8; 1024];
        while !buf.windows(4).any(|w| w == b"\r\n\r\n") && buf.len() < MAX_REQUEST_BYTES {
            let n = stream.read(&mut chunk).await?;
            if n == 0 {
                break;
            }
            buf.extend_from_slice(&chunk[..n]);
        }
        Ok::<_, std::io::Error>(())
    };
    tokio::time::timeout(REQUEST_TIMEOUT, read)
        .await
        .map_err(|_| std::io::Error::new(std::io::ErrorKind::TimedOut, "request head"))??;
    let line = buf.split(|&b| b == b'\r').next().unwrap_or_default();
    let mut parts = line.split(|&b| b == b' ');
    let (method, path) = (parts.next(), parts.next());
    let (status, ctype, body) = match (method, path) {
        (Some(b"GET"), Some(b"/metrics")) => (
            "200 OK",
            "text/plain; version=0.0.4; charset=utf-8",
            render(src),
        ),
        (Some(b"GET"), _) => ("404 Not Found", "text/plain", "try /metrics\n".to_owned()),
        _ => (
            "405 Method Not Allowed",
            "text/plain",
            "GET only\n".to_owned(),
        ),
    };
    let head = format!(
        "HTTP/1.1 {status}\r\nContent-Type: {ctype}\r\nContent-Length: {}\r\nConnection: close\r\n\r\n",
        body.len()
    );
    stream.write_all(head.as_bytes()).await?;
    stream.write_all(body.as_bytes()).await?;
    stream.shutdown().await
}
