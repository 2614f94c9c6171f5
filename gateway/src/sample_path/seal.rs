//! Seals over the corrected batches (PROTOCOL.md §6): the digests of what the outbox and the
//! late path published, signed and put on `triax/<b>/seal` by a thread of their own.
//!
//! Why a thread: a signature costs about 20 µs, more than half of a batch's correction. On the
//! receive thread it would be paid per burst; here it is paid at most once per
//! `seal_interval`, however many batches the seal lists, and the receive thread pays only a
//! digest (a SHA-256 of the batch, under a microsecond) and a push under a short lock.
//!
//! Invariants: a digest is pushed after its batch's put returned, so a seal never leaves
//! before a batch it lists on this session's links; every digest pushed before the stop is in
//! a seal put at the stop; a seal lists at most [`MAX_SEAL_DIGESTS`].

use std::sync::atomic::Ordering::Relaxed;
use std::sync::{Arc, Condvar, Mutex};
use std::time::{Duration, Instant};

use triax_protocol::provenance::{Digest, Seal, MAX_SEAL_DIGESTS};
use triax_protocol::{BuildingId, Key};
use zenoh::qos::CongestionControl;
use zenoh::Wait;

use crate::state::{GatewayCounters, Signer};
use crate::sync::lock;

/// Where the publishers leave the digests of what they put.
pub struct SealQueue {
    waiting: Mutex<Waiting>,
    wake: Condvar,
}

#[derive(Default)]
struct Waiting {
    digests: Vec<Digest>,
    closed: bool,
}

impl SealQueue {
    /// Adds the digests of batches just put.
    pub fn push(&self, digests: impl IntoIterator<Item = Digest>) {
        let mut w = lock(&self.waiting);
        let was_empty = w.digests.is_empty();
        w.digests.extend(digests);
        if was_empty && !w.digests.is_empty() {
            self.wake.notify_one();
        }
    }

    /// Seals what waits, then ends the thread.
    pub fn close(&self) {
        lock(&self.waiting).closed = true;
        self.wake.notify_one();
    }

    /// Waits for digests; None once closed and empty.
    fn take(&self) -> Option<Vec<Digest>> {
        let mut w = lock(&self.waiting);
        loop {
            if !w.digests.is_empty() {
                return Some(std::mem::take(&mut w.digests));
            }
            if w.closed {
                return None;
            }
            w = self.wake.wait(w).unwrap_or_else(|p| p.into_inner());
        }
    }
}

/// The running sealer: its queue, and the thread to join at the stop.
pub struct Sealer {
    pub queue: Arc<SealQueue>,
    thread: Option<std::thread::JoinHandle<()>>,
}

impl Sealer {
    pub fn start(
        session: zenoh::Session,
        building: &BuildingId,
        signer: Arc<Signer>,
        interval: Duration,
        counters: Arc<GatewayCounters>,
    ) -> std::io::Result<Sealer> {
        let queue = Arc::new(SealQueue {
            waiting: Mutex::default(),
            wake: Condvar::new(),
        });
        let q = queue.clone();
        let key = Key::Seal(building.clone()).to_string();
        let thread = std::thread::Builder::new()
            .name("triax-sealer".into())
            .spawn(move || run(&q, &session, &key, &signer, interval, &counters))?;
        Ok(Sealer {
            queue,
            thread: Some(thread),
        })
    }

    /// Seals what was published and stops the thread.
    pub fn finish(&mut self) {
        self.queue.close();
        if let Some(t) = self.thread.take() {
            if t.join().is_err() {
                tracing::error!("the sealer thread ended abnormally");
            }
        }
    }
}

fn run(
    queue: &SealQueue,
    session: &zenoh::Session,
    key: &str,
    signer: &Signer,
    interval: Duration,
    counters: &GatewayCounters,
) {
    let mut sequence = 0u64;
    while let Some(digests) = queue.take() {
        let started = Instant::now();
        for chunk in digests.chunks(MAX_SEAL_DIGESTS) {
            let payload = Seal {
                sequence,
                digests: chunk.to_vec(),
            }
            .encode();
            sequence += 1;
            let Some(attachment) = signer.attachment(key, "", &payload) else {
                return;
            };
            // Dropped for a consumer that cannot keep up, as the batches are: it reads them
            // back from the history, sealed there.
            let put = session
                .put(key, payload)
                .attachment(attachment)
                .congestion_control(CongestionControl::Drop)
                .wait();
            match put {
                Ok(()) => {
                    counters.seals.fetch_add(1, Relaxed);
                }
                Err(e) => {
                    counters.publish_errors.fetch_add(1, Relaxed);
                    tracing::warn!(cause = %e, "seal not published");
                }
            }
        }
        // At most one seal an interval: under load a seal lists what came meanwhile.
        if let Some(rest) = interval.checked_sub(started.elapsed()) {
            std::thread::sleep(rest);
        }
    }
}
