//! Prometheus metrics over HTTP: a small responder on a tokio listener that answers
//! `GET /metrics` with the text exposition format, and 404 to anything else.
//!
//! Hand-rolled because the endpoint is one read-only page: an HTTP framework would be most of
//! the gateway's dependencies for it. Requests are read up to a size and time limit, answered,
//! and the connection closed.

use std::fmt::Write as _;
use std::sync::atomic::Ordering::Relaxed;
use std::sync::Arc;
use std::time::Duration;

use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpListener, TcpStream};

use crate::sensors::{GatewayCounters, SensorTable};
use crate::shutdown::Shutdown;

/// Longest request head read.
const MAX_REQUEST_BYTES: usize = 8 * 1024;
/// Time a client gets to send its request.
const REQUEST_TIMEOUT: Duration = Duration::from_secs(5);

/// What the page reports.
#[derive(Clone)]
pub struct MetricsSource {
    pub table: Arc<SensorTable>,
    pub counters: Arc<GatewayCounters>,
    pub queued: Arc<dyn Fn() -> usize + Send + Sync>,
}

/// Renders the metrics page.
pub fn render(src: &MetricsSource) -> String {
    let mut out = String::with_capacity(4096);
    let c = &src.counters;
    let gauge = |out: &mut String, name: &str, kind: &str, help: &str, v: u64| {
        // Writing to a String cannot fail.
        let _ = writeln!(
            out,
            "# HELP {name} {help}\n# TYPE {name} {kind}\n{name} {v}"
        );
    };
    gauge(
        &mut out,
        "triax_gateway_received_batches_total",
        "counter",
        "Raw payloads taken from Zenoh, before any check.",
        c.received_batches.load(Relaxed),
    );
    gauge(
        &mut out,
        "triax_gateway_malformed_payloads_total",
        "counter",
        "Payloads that did not decode.",
        c.malformed.load(Relaxed),
    );
    gauge(
        &mut out,
        "triax_gateway_dropped_batches_total",
        "counter",
        "Raw batches dropped from a full queue (drop-oldest).",
        c.dropped.load(Relaxed),
    );
    gauge(
        &mut out,
        "triax_gateway_published_batches_total",
        "counter",
        "Corrected batches published.",
        c.published_batches.load(Relaxed),
    );
    gauge(
        &mut out,
        "triax_gateway_publish_errors_total",
        "counter",
        "Corrected batches Zenoh refused to publish.",
        c.publish_errors.load(Relaxed),
    );
    gauge(
        &mut out,
        "triax_gateway_over_capacity_batches_total",
        "counter",
        "Raw batches skipped because they came from a new sensor past max_sensors.",
        c.over_capacity.load(Relaxed),
    );
    gauge(
        &mut out,
        "triax_gateway_tilt_samples_total",
        "counter",
        "Tilt samples published.",
        c.tilt_samples.load(Relaxed),
    );
    gauge(
        &mut out,
        "triax_gateway_queued_batches",
        "gauge",
        "Raw batches waiting for a worker.",
        (src.queued)() as u64,
    );
    gauge(
        &mut out,
        "triax_gateway_sensors_online",
        "gauge",
        "Sensors whose stream is being corrected (seen since start).",
        c.sensors_online.load(Relaxed),
    );
    gauge(
        &mut out,
        "triax_gateway_declared_keys",
        "gauge",
        "Keys declared to Zenoh (raw and output); further sensors' keys are used undeclared.",
        c.declared_keys.load(Relaxed) as u64,
    );
    if let Some(bytes) = crate::memory::resident_bytes() {
        gauge(
            &mut out,
            "process_resident_memory_bytes",
            "gauge",
            "Resident memory of the gateway process.",
            bytes,
        );
    }
    let sensors = src.table.snapshot();
    gauge(
        &mut out,
        "triax_gateway_sensors",
        "gauge",
        "Sensors known.",
        sensors.len() as u64,
    );
    gauge(
        &mut out,
        "triax_gateway_uncalibrated_sensors",
        "gauge",
        "Sensors with no calibration in force.",
        sensors
            .iter()
            .filter(|s| s.calibration_version().is_none())
            .count() as u64,
    );
    type Field = fn(&crate::sensors::SensorCounters) -> u64;
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
            "Sequence numbers lost in gaps.",
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
    for (suffix, help, get) in per_sensor {
        let _ = writeln!(
            out,
            "# HELP triax_sensor_{suffix} {help}\n# TYPE triax_sensor_{suffix} counter"
        );
        for s in &sensors {
            let _ = writeln!(
                out,
                "triax_sensor_{suffix}{{sensor=\"{}\"}} {}",
                s.id,
                get(&s.counters)
            );
        }
    }
    let _ = writeln!(out, "# HELP triax_sensor_calibration_version Version in force (0: uncalibrated).\n# TYPE triax_sensor_calibration_version gauge");
    for s in &sensors {
        let _ = writeln!(
            out,
            "triax_sensor_calibration_version{{sensor=\"{}\"}} {}",
            s.id,
            s.calibration_version().unwrap_or(0)
        );
    }
    out
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
