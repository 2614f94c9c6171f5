//! Provenance: telling what a building's gateway said from what any peer on the network says
//! (PROTOCOL.md §6).
//!
//! Zenoh lets any session that reaches the network put on any key and answer any query. So
//! every message a gateway puts or answers carries an Ed25519 signature by the gateway's own
//! key, over the key expression, a nonce the querier chose (empty for a put), the time it was
//! signed and the payload: a Zenoh attachment of [`ATTACHMENT_LEN`] bytes ([`sign_message`],
//! [`verify_message`]).
//!
//! Corrected batches are too many to sign one by one: at the building profile (10 000
//! batches/s) a signature each would cost the gateway about as much again as correcting them.
//! Instead the gateway puts, on `triax/<building>/seal`, a signed [`Seal`]: the [`Digest`]s of
//! the batches it has just published, at most one seal per interval. A consumer holds each batch
//! until a verified seal lists it ([`SealBook`]). A history answer is sealed the same way, its
//! seal bound to the query's nonce.
//!
//! What a signature proves: the message left the holder of that key unchanged. Which keys a
//! consumer trusts, and for which building, is the consumer's configuration ([`GatewayKeys`]),
//! never something read off the network.

use std::collections::{HashMap, VecDeque};

use ed25519_dalek::{Signature, Signer, SigningKey, Verifier, VerifyingKey};
use sha2::{Digest as _, Sha256};

use crate::keys::BuildingId;
use crate::signing::to_hex;

/// What every signed attachment starts with.
pub const ATTACHMENT_MAGIC: [u8; 4] = *b"TXS1";
/// `TXS1`, `signed_at_ns` (i64), the public key (32 bytes), the signature (64 bytes).
pub const ATTACHMENT_LEN: usize = 4 + 8 + 32 + 64;
/// Domain separation: a gateway's message signature can never be taken for a record's or an
/// alert's.
pub const MESSAGE_CONTEXT: &[u8] = b"triax gateway message v1\0";
/// Bytes of a batch digest kept (the first 16 of its SHA-256).
pub const DIGEST_LEN: usize = 16;
/// Message kind byte of a seal (batches are 1 and 2).
pub const SEAL_KIND: u8 = 3;
/// Most digests in one seal (a seal of this many is 1 MiB).
pub const MAX_SEAL_DIGESTS: usize = 65_536;
/// Longest nonce a querier may choose, in bytes.
pub const MAX_NONCE_LEN: usize = 64;

/// A batch's digest: the first [`DIGEST_LEN`] bytes of a SHA-256 over its key, its attachment
/// and its payload.
pub type Digest = [u8; DIGEST_LEN];

/// The public keys a consumer trusts, per building.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct GatewayKeys {
    by_building: HashMap<BuildingId, Vec<VerifyingKey>>,
}

impl GatewayKeys {
    pub fn new() -> GatewayKeys {
        GatewayKeys::default()
    }

    /// Trusts `key` for what is said of `building`.
    pub fn trust(&mut self, building: BuildingId, key: VerifyingKey) {
        let keys = self.by_building.entry(building).or_default();
        if !keys.contains(&key) {
            keys.push(key);
        }
    }

    /// The keys trusted for `building` (none: nothing of it verifies).
    pub fn keys(&self, building: &BuildingId) -> &[VerifyingKey] {
        self.by_building.get(building).map_or(&[], Vec::as_slice)
    }

    pub fn is_empty(&self) -> bool {
        self.by_building.is_empty()
    }

    pub fn buildings(&self) -> impl Iterator<Item = &BuildingId> {
        self.by_building.keys()
    }
}

/// Why a message was not taken as its building's gateway's.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum ProvenanceError {
    #[error("no signature is attached")]
    Unsigned,
    #[error("the attachment is not a signature: {0}")]
    Malformed(&'static str),
    #[error("key expression {0:?} names no building")]
    NoBuilding(String),
    #[error("signed by {public_key_hex}, a key not trusted for building {building}")]
    UnknownKey {
        public_key_hex: String,
        building: String,
    },
    #[error("the signature by {0} does not verify: the message was altered, or signed for another key, nonce or time")]
    BadSignature(String),
    #[error("signed at {signed_at_ns} ns, more than {window_s} s before the newest seen ({newest_ns} ns): a replay")]
    Stale {
        signed_at_ns: i64,
        newest_ns: i64,
        window_s: i64,
    },
}

impl ProvenanceError {
    /// A short name for counters and logs.
    pub fn reason(&self) -> &'static str {
        match self {
            ProvenanceError::Unsigned => "unsigned",
            ProvenanceError::Malformed(_) | ProvenanceError::NoBuilding(_) => "malformed",
            ProvenanceError::UnknownKey { .. } => "unknown_key",
            ProvenanceError::BadSignature(_) => "bad_signature",
            ProvenanceError::Stale { .. } => "stale",
        }
    }
}

/// What a verified signature says.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Signed {
    pub signed_at_ns: i64,
    pub public_key: VerifyingKey,
}

fn signing_message(key_expr: &str, nonce: &str, signed_at_ns: i64, payload: &[u8]) -> Vec<u8> {
    let mut m = Vec::with_capacity(MESSAGE_CONTEXT.len() + 12 + key_expr.len() + nonce.len());
    m.extend_from_slice(MESSAGE_CONTEXT);
    // Key expressions and nonces are short (a Zenoh key is far below 64 KiB): their lengths
    // prefix them so no two (key, nonce, payload) triples sign the same bytes.
    m.extend_from_slice(&(key_expr.len() as u32).to_le_bytes());
    m.extend_from_slice(key_expr.as_bytes());
    m.extend_from_slice(&(nonce.len() as u32).to_le_bytes());
    m.extend_from_slice(nonce.as_bytes());
    m.extend_from_slice(&signed_at_ns.to_le_bytes());
    m.extend_from_slice(payload);
    m
}

/// The attachment that signs `payload` put or answered on `key_expr` (for a reply, the query's
/// `nonce`; for a put, the empty string).
pub fn sign_message(
    key: &SigningKey,
    key_expr: &str,
    nonce: &str,
    signed_at_ns: i64,
    payload: &[u8],
) -> [u8; ATTACHMENT_LEN] {
    let signature = key.sign(&signing_message(key_expr, nonce, signed_at_ns, payload));
    let mut a = [0u8; ATTACHMENT_LEN];
    a[..4].copy_from_slice(&ATTACHMENT_MAGIC);
    a[4..12].copy_from_slice(&signed_at_ns.to_le_bytes());
    a[12..44].copy_from_slice(key.verifying_key().as_bytes());
    a[44..].copy_from_slice(&signature.to_bytes());
    a
}

/// Checks a query's `nonce` parameter: 1 to [`MAX_NONCE_LEN`] characters from an id's alphabet
/// (`A-Z a-z 0-9 _ -`), so that it cannot carry selector syntax.
pub fn check_nonce(value: &str) -> Result<(), String> {
    if value.is_empty() || value.len() > MAX_NONCE_LEN {
        return Err(format!(
            "nonce: {} characters, not 1..={MAX_NONCE_LEN}",
            value.len()
        ));
    }
    match value
        .chars()
        .find(|c| !(c.is_ascii_alphanumeric() || *c == '_' || *c == '-'))
    {
        Some(c) => Err(format!("nonce: {c:?} is not one of A-Z a-z 0-9 _ -")),
        None => Ok(()),
    }
}

/// A nonce for a query: 128 bits from the operating system's random source, as 32 hex
/// characters, so that no one can have an answer signed before the query is sent.
pub fn fresh_nonce() -> String {
    use rand::RngCore;
    let mut bytes = [0u8; 16];
    rand::rngs::OsRng.fill_bytes(&mut bytes);
    to_hex(&bytes)
}

/// The building chunk of a `triax/<building>/…` key expression.
pub fn building_of(key_expr: &str) -> Result<BuildingId, ProvenanceError> {
    key_expr
        .strip_prefix("triax/")
        .and_then(|rest| rest.split('/').next())
        .and_then(|b| BuildingId::new(b).ok())
        .ok_or_else(|| ProvenanceError::NoBuilding(key_expr.to_owned()))
}

/// Checks that `payload` on `key_expr` was signed, with `nonce`, by a key `trusted` holds for
/// the key's building.
pub fn verify_message(
    trusted: &GatewayKeys,
    key_expr: &str,
    nonce: &str,
    payload: &[u8],
    attachment: Option<&[u8]>,
) -> Result<Signed, ProvenanceError> {
    let building = building_of(key_expr)?;
    verify_with(
        trusted.keys(&building),
        key_expr,
        nonce,
        payload,
        attachment,
    )
}

/// Checks that `payload` on `key_expr` was signed, with `nonce`, by one of `keys`: for a
/// service's messages (a modes window), whose key is the service's, not a building's.
pub fn verify_with(
    keys: &[VerifyingKey],
    key_expr: &str,
    nonce: &str,
    payload: &[u8],
    attachment: Option<&[u8]>,
) -> Result<Signed, ProvenanceError> {
    let a = attachment.ok_or(ProvenanceError::Unsigned)?;
    if a.len() != ATTACHMENT_LEN {
        return Err(ProvenanceError::Malformed("wrong length"));
    }
    if a[..4] != ATTACHMENT_MAGIC {
        return Err(ProvenanceError::Malformed("no TXS1 magic"));
    }
    // The slices have the lengths the ranges say (the length is checked above).
    let signed_at_ns = i64::from_le_bytes(a[4..12].try_into().expect("8 bytes"));
    let key_bytes: [u8; 32] = a[12..44].try_into().expect("32 bytes");
    let signature = Signature::from_bytes(&a[44..].try_into().expect("64 bytes"));
    let building = building_of(key_expr)?;
    let public_key_hex = to_hex(&key_bytes);
    let Some(key) = keys.iter().find(|k| k.as_bytes() == &key_bytes) else {
        return Err(ProvenanceError::UnknownKey {
            public_key_hex,
            building: building.to_string(),
        });
    };
    key.verify(
        &signing_message(key_expr, nonce, signed_at_ns, payload),
        &signature,
    )
    .map_err(|_| ProvenanceError::BadSignature(public_key_hex))?;
    Ok(Signed {
        signed_at_ns,
        public_key: *key,
    })
}

/// The digest of a batch put or answered on `key_expr` with `attachment` (empty for a live
/// batch; a history reply's cursor).
pub fn digest(key_expr: &str, attachment: &[u8], payload: &[u8]) -> Digest {
    let mut h = Sha256::new();
    h.update((key_expr.len() as u32).to_le_bytes());
    h.update(key_expr.as_bytes());
    h.update((attachment.len() as u32).to_le_bytes());
    h.update(attachment);
    h.update(payload);
    let full = h.finalize();
    let mut d = [0u8; DIGEST_LEN];
    d.copy_from_slice(&full[..DIGEST_LEN]);
    d
}

/// Why a payload is not a seal.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum SealError {
    #[error("seal is {len} bytes; its header needs 18")]
    Truncated { len: usize },
    #[error("seal does not start with \"TX\", kind 3, version 1")]
    NotASeal,
    #[error("seal counts {count} digests (at most {MAX_SEAL_DIGESTS}) but holds {len} bytes")]
    BadLength { count: u32, len: usize },
}

/// A gateway's signed list of what it published: the digests of its corrected batches, in the
/// order it put them.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Seal {
    /// +1 per seal from a gateway's start.
    pub sequence: u64,
    pub digests: Vec<Digest>,
}

const SEAL_HEADER_LEN: usize = 18;

impl Seal {
    /// `TX`, kind 3, version 1, flags 0 (u16), `sequence` (u64), count (u32), the digests.
    pub fn encode(&self) -> Vec<u8> {
        let mut out = Vec::with_capacity(SEAL_HEADER_LEN + DIGEST_LEN * self.digests.len());
        out.extend_from_slice(b"TX");
        out.extend_from_slice(&[SEAL_KIND, 1, 0, 0]);
        out.extend_from_slice(&self.sequence.to_le_bytes());
        out.extend_from_slice(&(self.digests.len() as u32).to_le_bytes());
        for d in &self.digests {
            out.extend_from_slice(d);
        }
        out
    }

    pub fn decode(bytes: &[u8]) -> Result<Seal, SealError> {
        if bytes.len() < SEAL_HEADER_LEN {
            return Err(SealError::Truncated { len: bytes.len() });
        }
        if !is_seal(bytes) || bytes[4..6] != [0, 0] {
            return Err(SealError::NotASeal);
        }
        // Lengths checked above.
        let sequence = u64::from_le_bytes(bytes[6..14].try_into().expect("8 bytes"));
        let count = u32::from_le_bytes(bytes[14..18].try_into().expect("4 bytes"));
        let body = &bytes[SEAL_HEADER_LEN..];
        if count as usize > MAX_SEAL_DIGESTS || body.len() != count as usize * DIGEST_LEN {
            return Err(SealError::BadLength {
                count,
                len: bytes.len(),
            });
        }
        let digests = body
            .chunks_exact(DIGEST_LEN)
            .map(|c| c.try_into().expect("DIGEST_LEN bytes"))
            .collect();
        Ok(Seal { sequence, digests })
    }
}

/// Whether `payload` is a seal rather than a batch (a history answer carries both).
pub fn is_seal(payload: &[u8]) -> bool {
    payload.len() >= 4 && payload[..2] == *b"TX" && payload[2] == SEAL_KIND && payload[3] == 1
}

/// Refuses what was signed long before the newest message seen on the same key: a put replayed
/// by a peer (a genuine heartbeat or seal of an hour ago) verifies, but is not news.
#[derive(Debug, Clone, Default)]
pub struct Freshness {
    newest_ns: HashMap<String, i64>,
}

/// How far behind the newest a signed put may be (puts of one gateway arrive in order; this is
/// slack for a gateway's clock stepped back).
pub const REPLAY_WINDOW_NS: i64 = 5_000_000_000;

impl Freshness {
    pub fn check(&mut self, key_expr: &str, signed_at_ns: i64) -> Result<(), ProvenanceError> {
        let newest = self
            .newest_ns
            .entry(key_expr.to_owned())
            .or_insert(i64::MIN);
        if signed_at_ns < newest.saturating_sub(REPLAY_WINDOW_NS) {
            return Err(ProvenanceError::Stale {
                signed_at_ns,
                newest_ns: *newest,
                window_s: REPLAY_WINDOW_NS / 1_000_000_000,
            });
        }
        *newest = (*newest).max(signed_at_ns);
        Ok(())
    }
}

/// Batches held until a seal lists them, and what seals listed before their batch came.
///
/// A gateway puts a seal after the batches it covers, on the same session, so a seal usually
/// finds its batches waiting; a consumer on another route may see the seal first, so listed
/// digests are remembered for as long as a batch is held. A batch no seal lists within
/// `hold_ns` is given back by [`SealBook::expire`] as unverified.
#[derive(Debug)]
pub struct SealBook<T> {
    hold_ns: i64,
    max_held: usize,
    waiting: HashMap<Digest, VecDeque<T>>,
    /// Arrival order of what waits (a digest per batch; a released one is skipped).
    waiting_order: VecDeque<(Digest, i64)>,
    listed: HashMap<Digest, u32>,
    listed_order: VecDeque<(Digest, i64)>,
}

impl<T> SealBook<T> {
    /// Holds at most `max_held` batches (beyond, the oldest are given up as unverified), each
    /// for at most `hold_ns`.
    pub fn new(hold_ns: i64, max_held: usize) -> SealBook<T> {
        SealBook {
            hold_ns,
            max_held: max_held.max(1),
            waiting: HashMap::new(),
            waiting_order: VecDeque::new(),
            listed: HashMap::new(),
            listed_order: VecDeque::new(),
        }
    }

    /// A batch arrived: given back at once when a seal already listed it, else held. What
    /// holding it pushed out is appended to `unverified`.
    pub fn offer(
        &mut self,
        digest: Digest,
        item: T,
        now_ns: i64,
        unverified: &mut Vec<T>,
    ) -> Option<T> {
        if let Some(n) = self.listed.get_mut(&digest) {
            *n -= 1;
            if *n == 0 {
                self.listed.remove(&digest);
            }
            return Some(item);
        }
        self.waiting.entry(digest).or_default().push_back(item);
        self.waiting_order.push_back((digest, now_ns));
        while self.waiting_order.len() > self.max_held {
            self.give_up_oldest(unverified);
        }
        None
    }

    /// A verified seal: what it lists that waits, in the seal's order, appended to `released`.
    pub fn seal(&mut self, digests: &[Digest], now_ns: i64, released: &mut Vec<T>) {
        for d in digests {
            match self.waiting.get_mut(d).and_then(VecDeque::pop_front) {
                Some(item) => {
                    if self.waiting.get(d).is_some_and(VecDeque::is_empty) {
                        self.waiting.remove(d);
                    }
                    released.push(item);
                }
                None => {
                    *self.listed.entry(*d).or_default() += 1;
                    self.listed_order.push_back((*d, now_ns));
                }
            }
        }
        while self.listed_order.len() > self.max_held {
            self.forget_oldest_listed();
        }
    }

    /// Batches held longer than `hold_ns`, oldest first: no seal listed them.
    pub fn expire(&mut self, now_ns: i64, unverified: &mut Vec<T>) {
        while self
            .waiting_order
            .front()
            .is_some_and(|(_, at)| now_ns - at > self.hold_ns)
        {
            self.give_up_oldest(unverified);
        }
        while self
            .listed_order
            .front()
            .is_some_and(|(_, at)| now_ns - at > self.hold_ns)
        {
            self.forget_oldest_listed();
        }
    }

    /// How many batches wait for a seal.
    pub fn held(&self) -> usize {
        self.waiting.values().map(VecDeque::len).sum()
    }

    /// When the oldest waiting batch arrived.
    pub fn oldest_held_ns(&self) -> Option<i64> {
        // Entries of released batches stay in the order queue until they reach its front.
        self.waiting_order
            .iter()
            .find(|(d, _)| self.waiting.contains_key(d))
            .map(|(_, at)| *at)
    }

    fn give_up_oldest(&mut self, unverified: &mut Vec<T>) {
        let Some((d, _)) = self.waiting_order.pop_front() else {
            return;
        };
        // The order queue holds an entry per offered batch; one whose batch a seal released
        // finds nothing (or a later batch of the same digest, which is then older than due).
        if let Some(q) = self.waiting.get_mut(&d) {
            if let Some(item) = q.pop_front() {
                unverified.push(item);
            }
            if q.is_empty() {
                self.waiting.remove(&d);
            }
        }
    }

    fn forget_oldest_listed(&mut self) {
        if let Some((d, _)) = self.listed_order.pop_front() {
            if let Some(n) = self.listed.get_mut(&d) {
                *n -= 1;
                if *n == 0 {
                    self.listed.remove(&d);
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn key(seed: u8) -> SigningKey {
        SigningKey::from_bytes(&[seed; 32])
    }

    fn trusted(seed: u8) -> GatewayKeys {
        let mut k = GatewayKeys::new();
        k.trust(BuildingId::new("hq").unwrap(), key(seed).verifying_key());
        k
    }

    const KEY: &str = "triax/hq/status";

    #[test]
    fn a_signed_message_verifies_and_names_its_time() {
        let a = sign_message(&key(1), KEY, "n-1", 42, b"{}");
        let s = verify_message(&trusted(1), KEY, "n-1", b"{}", Some(&a)).unwrap();
        assert_eq!(s.signed_at_ns, 42);
        assert_eq!(s.public_key, key(1).verifying_key());
    }

    #[test]
    fn every_change_to_what_was_signed_is_refused() {
        let a = sign_message(&key(1), KEY, "n-1", 42, b"{}");
        let t = trusted(1);
        let bad = |e: Result<Signed, ProvenanceError>| e.unwrap_err().reason();
        assert_eq!(
            bad(verify_message(&t, KEY, "n-1", b"{ }", Some(&a))),
            "bad_signature"
        );
        assert_eq!(
            bad(verify_message(&t, KEY, "n-2", b"{}", Some(&a))),
            "bad_signature"
        );
        assert_eq!(
            bad(verify_message(
                &t,
                "triax/hq/heartbeat",
                "n-1",
                b"{}",
                Some(&a)
            )),
            "bad_signature"
        );
        let mut later = a;
        later[4] ^= 1;
        assert_eq!(
            bad(verify_message(&t, KEY, "n-1", b"{}", Some(&later))),
            "bad_signature"
        );
        // Moved to another building: that building trusts no key here.
        assert_eq!(
            bad(verify_message(
                &t,
                "triax/b2/status",
                "n-1",
                b"{}",
                Some(&a)
            )),
            "unknown_key"
        );
        assert_eq!(
            bad(verify_message(&trusted(2), KEY, "n-1", b"{}", Some(&a))),
            "unknown_key"
        );
        assert_eq!(bad(verify_message(&t, KEY, "n-1", b"{}", None)), "unsigned");
        assert_eq!(
            bad(verify_message(&t, KEY, "n-1", b"{}", Some(&a[..107]))),
            "malformed"
        );
        assert_eq!(
            bad(verify_message(&t, KEY, "n-1", b"{}", Some(b"acc-01:17"))),
            "malformed"
        );
        // A peer's own key, its signature good, is still not the gateway's.
        let forged = sign_message(&key(9), KEY, "n-1", 42, b"{}");
        assert_eq!(
            bad(verify_message(&t, KEY, "n-1", b"{}", Some(&forged))),
            "unknown_key"
        );
    }

    #[test]
    fn digests_bind_key_attachment_and_payload() {
        let d = digest("triax/hq/corrected/a", b"", b"xy");
        assert_ne!(d, digest("triax/hq/corrected/b", b"", b"xy"));
        assert_ne!(d, digest("triax/hq/corrected/a", b"x", b"y"));
        assert_ne!(d, digest("triax/hq/corrected/a", b"", b"xz"));
        // The definition written out, as a client in another language would.
        let mut m = Vec::new();
        m.extend_from_slice(&20u32.to_le_bytes());
        m.extend_from_slice(b"triax/hq/corrected/a");
        m.extend_from_slice(&0u32.to_le_bytes());
        m.extend_from_slice(b"xy");
        assert_eq!(d[..], Sha256::digest(&m)[..16]);
    }

    #[test]
    fn seals_round_trip_and_refuse_wrong_lengths() {
        let s = Seal {
            sequence: 7,
            digests: vec![[1; 16], [2; 16]],
        };
        let bytes = s.encode();
        assert_eq!(bytes.len(), 18 + 32);
        assert!(is_seal(&bytes));
        assert_eq!(Seal::decode(&bytes).unwrap(), s);
        assert!(matches!(
            Seal::decode(&bytes[..bytes.len() - 1]),
            Err(SealError::BadLength { count: 2, .. })
        ));
        assert!(matches!(
            Seal::decode(&bytes[..10]),
            Err(SealError::Truncated { len: 10 })
        ));
        let mut batch = bytes.clone();
        batch[2] = 2;
        assert!(!is_seal(&batch));
        assert_eq!(Seal::decode(&batch), Err(SealError::NotASeal));
    }

    #[test]
    fn a_book_releases_in_seal_order_either_way_round_and_gives_up_the_unlisted() {
        let mut book = SealBook::new(1_000, 100);
        let mut out = Vec::new();
        assert_eq!(book.offer([1; 16], "a", 0, &mut out), None);
        assert_eq!(book.offer([2; 16], "b", 0, &mut out), None);
        assert_eq!(book.offer([9; 16], "forged", 0, &mut out), None);
        book.seal(&[[2; 16], [1; 16], [3; 16]], 10, &mut out);
        assert_eq!(out, ["b", "a"]);
        // The seal came before its third batch.
        out.clear();
        assert_eq!(book.offer([3; 16], "c", 20, &mut out), Some("c"));
        // A second copy of a sealed batch is not sealed by the first seal.
        assert_eq!(book.offer([3; 16], "c again", 20, &mut out), None);
        assert_eq!(book.held(), 2);
        book.expire(1_001, &mut out);
        assert_eq!(out, ["forged"]);
        out.clear();
        book.expire(2_000, &mut out);
        assert_eq!(out, ["c again"]);
        assert_eq!(book.held(), 0);
    }

    #[test]
    fn a_flood_cannot_make_a_book_hold_more_than_its_room() {
        let mut book = SealBook::new(i64::MAX, 3);
        let mut out = Vec::new();
        for i in 0..10u8 {
            book.offer([i; 16], i, 0, &mut out);
        }
        assert_eq!(out, (0..7).collect::<Vec<u8>>());
        assert_eq!(book.held(), 3);
    }

    #[test]
    fn freshness_refuses_a_put_replayed_long_after() {
        let mut f = Freshness::default();
        f.check(KEY, 100 * REPLAY_WINDOW_NS).unwrap();
        // Reordered a little: still news.
        f.check(KEY, 100 * REPLAY_WINDOW_NS - 1).unwrap();
        let e = f.check(KEY, 98 * REPLAY_WINDOW_NS).unwrap_err();
        assert_eq!(e.reason(), "stale");
        // Another key has its own newest.
        f.check("triax/hq/heartbeat", 1).unwrap();
    }
}
