//! What the console checks of what the gateways say (PROTOCOL.md §6).
//!
//! Given its buildings' gateway keys (`--gateway-key`), the console shows nothing it cannot
//! verify as its gateway's: a heartbeat, a tilt sample or a status answer not signed by the
//! building's gateway key is counted by reason and dropped; a live batch is held until a seal of
//! that gateway lists it (one seal subscription per building watched, shared by its sensors'
//! feeds), and dropped as `unsealed` after [`SEAL_WAIT`]; history is read with a nonce and
//! only sealed replies are drawn or exported (`triax_client::history`). Without keys every
//! message is taken on trust, and the page says so.
//!
//! Alerts are not the gateways': they carry the alerting service's own signature and are
//! checked against `--trusted-alert-key` ([`crate::alertlog`]).

use std::collections::{BTreeMap, HashMap};
use std::sync::{Arc, Mutex, MutexGuard, Weak};
use std::time::Duration;

use serde::Serialize;
use triax_protocol::provenance::{
    fresh_nonce, verify_message, Digest, Freshness, GatewayKeys, ProvenanceError, Seal, SealBook,
};
use triax_protocol::{BuildingId, Key};

/// How long a live batch waits for the seal that lists it: the gateway seals within
/// milliseconds; the rest is slack for a loaded link.
pub const SEAL_WAIT: Duration = Duration::from_secs(2);
/// Live batches held at most per building while their seal is awaited (beyond, the oldest are
/// dropped as `unsealed`): at most about 13 MiB of the largest batches a second.
pub const MAX_HELD: usize = 65_536;

/// The console's checks, shared by the fleet, the live feeds and the history reads.
pub struct Provenance {
    keys: Option<Arc<GatewayKeys>>,
    fresh: Mutex<Freshness>,
    refused: Mutex<BTreeMap<&'static str, u64>>,
    seals: Mutex<HashMap<BuildingId, Weak<SealWatch>>>,
}

impl std::fmt::Debug for Provenance {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Provenance")
            .field("verifying", &self.keys.is_some())
            .field("refused", &*lock(&self.refused))
            .finish_non_exhaustive()
    }
}

/// What the fleet view says of the checks.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ProvenanceView {
    /// Whether the console holds gateway keys: `false` means everything shown is taken on
    /// trust.
    pub verifying: bool,
    /// Messages dropped, by reason: `unsigned`, `unknown_key`, `bad_signature`, `stale` (a
    /// signed put replayed), `malformed` (an attachment or seal that does not parse),
    /// `unsealed` (a live batch no verified seal listed within [`SEAL_WAIT`]).
    pub refused: BTreeMap<&'static str, u64>,
}

fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    // Counters and books are updated by single calls that cannot panic halfway.
    m.lock().unwrap_or_else(|p| p.into_inner())
}

fn now_ns() -> i64 {
    crate::live::wall_clock_ns()
}

impl Provenance {
    /// Every message taken on trust.
    pub fn on_trust() -> Provenance {
        Provenance::new(None)
    }

    /// `keys`: the gateways' public keys by building; None takes every message on trust.
    pub fn new(keys: Option<Arc<GatewayKeys>>) -> Provenance {
        Provenance {
            keys,
            fresh: Mutex::default(),
            refused: Mutex::default(),
            seals: Mutex::default(),
        }
    }

    pub fn keys(&self) -> Option<&Arc<GatewayKeys>> {
        self.keys.as_ref()
    }

    pub fn verifying(&self) -> bool {
        self.keys.is_some()
    }

    pub fn view(&self) -> ProvenanceView {
        ProvenanceView {
            verifying: self.verifying(),
            refused: lock(&self.refused).clone(),
        }
    }

    /// All messages dropped so far.
    pub fn refused_total(&self) -> u64 {
        lock(&self.refused).values().sum()
    }

    fn count(&self, reason: &'static str, n: u64) {
        if n > 0 {
            *lock(&self.refused).entry(reason).or_default() += n;
        }
    }

    fn refuse(&self, key_expr: &str, e: &ProvenanceError) -> bool {
        tracing::debug!(key = key_expr, cause = %e, "message not verified, dropped");
        self.count(e.reason(), 1);
        false
    }

    /// Whether a put on `key_expr` may be shown: signed by the building's gateway and not older
    /// than the newest on its key by more than the replay window. Always, on trust.
    pub fn put(&self, key_expr: &str, payload: &[u8], attachment: Option<&[u8]>) -> bool {
        let Some(keys) = &self.keys else { return true };
        let checked = verify_message(keys, key_expr, "", payload, attachment)
            .and_then(|s| lock(&self.fresh).check(key_expr, s.signed_at_ns));
        match checked {
            Ok(()) => true,
            Err(e) => self.refuse(key_expr, &e),
        }
    }

    /// The nonce to send with a status query; None on trust (older gateways then answer as
    /// before).
    pub fn nonce(&self) -> Option<String> {
        self.keys.as_ref().map(|_| fresh_nonce())
    }

    /// Whether a reply on `key_expr` to a query sent with `nonce` may be shown.
    pub fn reply(
        &self,
        key_expr: &str,
        nonce: Option<&str>,
        payload: &[u8],
        attachment: Option<&[u8]>,
    ) -> bool {
        let Some(keys) = &self.keys else { return true };
        match verify_message(keys, key_expr, nonce.unwrap_or(""), payload, attachment) {
            Ok(_) => true,
            Err(e) => self.refuse(key_expr, &e),
        }
    }

    /// The seals of `building`, shared by the feeds that watch its sensors; None on trust.
    pub async fn seal_watch(
        self: &Arc<Self>,
        session: &zenoh::Session,
        building: &BuildingId,
    ) -> zenoh::Result<Option<Arc<SealWatch>>> {
        if self.keys.is_none() {
            return Ok(None);
        }
        if let Some(w) = lock(&self.seals).get(building).and_then(Weak::upgrade) {
            return Ok(Some(w));
        }
        let book = Arc::new(Mutex::new(SealBook::<Release>::new(
            SEAL_WAIT.as_nanos() as i64,
            MAX_HELD,
        )));
        let (b, me) = (book.clone(), self.clone());
        let subscriber = session
            .declare_subscriber(Key::Seal(building.clone()).to_string())
            .callback(move |sample| {
                let key = sample.key_expr().as_str();
                let payload = sample.payload().to_bytes();
                let attachment = sample.attachment().map(|a| a.to_bytes());
                if !me.put(key, &payload, attachment.as_deref()) {
                    return;
                }
                let seal = match Seal::decode(&payload) {
                    Ok(s) => s,
                    Err(e) => {
                        tracing::debug!(key, cause = %e, "seal does not decode");
                        return me.count("malformed", 1);
                    }
                };
                let (mut released, mut expired) = (Vec::new(), Vec::new());
                {
                    let mut book = lock(&b);
                    book.expire(now_ns(), &mut expired);
                    book.seal(&seal.digests, now_ns(), &mut released);
                }
                me.count("unsealed", expired.len() as u64);
                for release in released {
                    release();
                }
            })
            .await?;
        // Batches no seal lists are dropped on time even when nothing more arrives.
        let (weak, me) = (Arc::downgrade(&book), self.clone());
        tokio::spawn(async move {
            let mut tick = tokio::time::interval(SEAL_WAIT / 4);
            tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
            loop {
                tick.tick().await;
                let Some(book) = weak.upgrade() else { return };
                let mut expired = Vec::new();
                lock(&book).expire(now_ns(), &mut expired);
                me.count("unsealed", expired.len() as u64);
            }
        });
        let watch = Arc::new(SealWatch {
            provenance: self.clone(),
            book,
            _seals: subscriber,
        });
        let mut seals = lock(&self.seals);
        // Another feed of the building may have made one meanwhile: keep one.
        if let Some(w) = seals.get(building).and_then(Weak::upgrade) {
            return Ok(Some(w));
        }
        seals.retain(|_, w| w.strong_count() > 0);
        seals.insert(building.clone(), Arc::downgrade(&watch));
        Ok(Some(watch))
    }
}

/// What a held batch does once a seal lists it.
pub type Release = Box<dyn FnOnce() + Send>;

/// One building's seals, and the live batches of its watched sensors waiting for them.
pub struct SealWatch {
    provenance: Arc<Provenance>,
    book: Arc<Mutex<SealBook<Release>>>,
    _seals: zenoh::pubsub::Subscriber<()>,
}

impl SealWatch {
    /// A live batch of digest `d` (`triax_protocol::provenance::digest` of its key and
    /// payload): `release` runs once a verified seal lists it (at once if one already did),
    /// never if none does within [`SEAL_WAIT`].
    pub fn offer(&self, d: Digest, release: Release) {
        let mut dropped = Vec::new();
        let now = now_ns();
        let ready = {
            let mut book = lock(&self.book);
            book.expire(now, &mut dropped);
            book.offer(d, release, now, &mut dropped)
        };
        self.provenance.count("unsealed", dropped.len() as u64);
        if let Some(release) = ready {
            release();
        }
    }

    /// Batches waiting for their seal.
    pub fn held(&self) -> usize {
        lock(&self.book).held()
    }
}
