//! Signing and verifying calibration pushes (Ed25519).
//!
//! The lab signs the exact JSON text of a record; a gateway trusts a record only if its
//! signature verifies under one of the lab public keys in its configuration. Signature checks do
//! not depend on the transport: they hold whether or not Zenoh runs over TLS.
//!
//! Keys are stored as 64 lowercase hex characters (the 32-byte secret seed or public key), one
//! per file, so they can be read, copied and diffed as text.

use ed25519_dalek::{Signature, Signer, SigningKey, Verifier, VerifyingKey};

use crate::event::{EventReport, SignedEvent};
use crate::json::{from_json, to_json, JsonError, JSON_FORMAT_VERSION};
use crate::messages::{Alert, RefusalReason, SignedAlert, SignedRecord, SIGNATURE_ALGORITHM};
use crate::record::CalibrationRecord;

pub use ed25519_dalek::{SigningKey as LabSigningKey, VerifyingKey as LabPublicKey};

/// Why a key text or a signed record was refused.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum SigningError {
    #[error("{what}: expected {expected} hex characters, found {found}")]
    HexLength {
        what: &'static str,
        expected: usize,
        found: usize,
    },
    #[error("{what}: {found:?} at position {position} is not a hex digit")]
    HexDigit {
        what: &'static str,
        found: char,
        position: usize,
    },
    #[error("public key is not a valid Ed25519 point")]
    BadPublicKey,
    #[error("algorithm {0:?} is not supported; only \"ed25519\" is")]
    UnsupportedAlgorithm(String),
    #[error("public key {0} is not among the trusted lab keys")]
    UnknownKey(String),
    #[error("signature does not verify under key {0}")]
    BadSignature(String),
    #[error("signed record: {0}")]
    Record(#[from] JsonError),
}

impl SigningError {
    /// The acknowledgement reason a gateway reports for this error.
    pub fn refusal_reason(&self) -> RefusalReason {
        match self {
            SigningError::UnknownKey(_) => RefusalReason::UnknownKey,
            SigningError::Record(_) => RefusalReason::Malformed,
            SigningError::UnsupportedAlgorithm(_) => RefusalReason::Malformed,
            SigningError::HexLength { .. }
            | SigningError::HexDigit { .. }
            | SigningError::BadPublicKey
            | SigningError::BadSignature(_) => RefusalReason::BadSignature,
        }
    }
}

/// Lowercase hex of `bytes`.
pub fn to_hex(bytes: &[u8]) -> String {
    const DIGITS: &[u8; 16] = b"0123456789abcdef";
    let mut s = String::with_capacity(bytes.len() * 2);
    for b in bytes {
        s.push(DIGITS[(b >> 4) as usize] as char);
        s.push(DIGITS[(b & 15) as usize] as char);
    }
    s
}

/// Parses exactly `N` bytes of hex (either case; surrounding whitespace ignored).
pub fn from_hex<const N: usize>(what: &'static str, text: &str) -> Result<[u8; N], SigningError> {
    let text = text.trim();
    if let Some((position, found)) = text.char_indices().find(|(_, c)| !c.is_ascii_hexdigit()) {
        return Err(SigningError::HexDigit {
            what,
            found,
            position,
        });
    }
    // Only ASCII hex digits remain, one byte each.
    if text.len() != 2 * N {
        return Err(SigningError::HexLength {
            what,
            expected: 2 * N,
            found: text.len(),
        });
    }
    let mut out = [0u8; N];
    for (i, byte) in out.iter_mut().enumerate() {
        // Both characters are ASCII hex digits, checked above.
        *byte = u8::from_str_radix(&text[2 * i..2 * i + 2], 16).expect("hex digits");
    }
    Ok(out)
}

/// Reads a secret key from its hex text.
pub fn signing_key_from_hex(text: &str) -> Result<SigningKey, SigningError> {
    Ok(SigningKey::from_bytes(&from_hex::<32>("secret key", text)?))
}

/// Reads a public key from its hex text.
pub fn public_key_from_hex(text: &str) -> Result<VerifyingKey, SigningError> {
    VerifyingKey::from_bytes(&from_hex::<32>("public key", text)?)
        .map_err(|_| SigningError::BadPublicKey)
}

/// Signs a record: its compact JSON becomes `record_json`, byte for byte what is signed.
pub fn sign(record: &CalibrationRecord, key: &SigningKey) -> SignedRecord {
    // to_json always yields UTF-8 (serde_json writes UTF-8 only).
    let record_json = String::from_utf8(to_json(record)).expect("JSON is UTF-8");
    let (public_key_hex, signature_hex) =
        signed_by(key, &SignedRecord::signing_message(&record_json));
    SignedRecord {
        format_version: JSON_FORMAT_VERSION,
        algorithm: SIGNATURE_ALGORITHM.into(),
        public_key_hex,
        record_json,
        signature_hex,
    }
}

/// Signs an alert: its compact JSON becomes `alert_json`, byte for byte what is signed.
pub fn sign_alert(alert: &Alert, key: &SigningKey) -> SignedAlert {
    // to_json always yields UTF-8 (serde_json writes UTF-8 only).
    let alert_json = String::from_utf8(to_json(alert)).expect("JSON is UTF-8");
    let (public_key_hex, signature_hex) =
        signed_by(key, &SignedAlert::signing_message(&alert_json));
    SignedAlert {
        format_version: JSON_FORMAT_VERSION,
        algorithm: SIGNATURE_ALGORITHM.into(),
        public_key_hex,
        alert_json,
        signature_hex,
    }
}

/// Signs an event report: its compact JSON becomes `event_json`, byte for byte what is signed.
pub fn sign_event(report: &EventReport, key: &SigningKey) -> SignedEvent {
    // to_json always yields UTF-8 (serde_json writes UTF-8 only).
    let event_json = String::from_utf8(to_json(report)).expect("JSON is UTF-8");
    let (public_key_hex, signature_hex) =
        signed_by(key, &SignedEvent::signing_message(&event_json));
    SignedEvent {
        format_version: JSON_FORMAT_VERSION,
        algorithm: SIGNATURE_ALGORITHM.into(),
        public_key_hex,
        event_json,
        signature_hex,
    }
}

/// Reads a signed event report, checked against `trusted` as [`read_alert`] checks an alert
/// (a bare report is `Unsigned`); the report whatever its trust, an error when the payload is
/// neither.
pub fn read_event(
    payload: &[u8],
    trusted: &TrustedKeys,
) -> Result<(EventReport, AlertTrust), JsonError> {
    let Ok(signed) = from_json::<SignedEvent>(payload) else {
        return Ok((from_json::<EventReport>(payload)?, AlertTrust::Unsigned));
    };
    let report: EventReport = from_json(signed.event_json.as_bytes())?;
    let key = match public_key_from_hex(&signed.public_key_hex) {
        Ok(k) if signed.algorithm == SIGNATURE_ALGORITHM => k,
        _ => {
            return Ok((
                report,
                AlertTrust::BadSignature {
                    public_key_hex: signed.public_key_hex.clone(),
                },
            ))
        }
    };
    let public_key_hex = to_hex(key.as_bytes());
    let holds = from_hex::<64>("signature", &signed.signature_hex)
        .map(|b| Signature::from_bytes(&b))
        .is_ok_and(|sig| {
            key.verify(&SignedEvent::signing_message(&signed.event_json), &sig)
                .is_ok()
        });
    let trust = match (holds, trusted.keys.contains(&key)) {
        (false, _) => AlertTrust::BadSignature { public_key_hex },
        (true, true) => AlertTrust::Verified { public_key_hex },
        (true, false) => AlertTrust::UnknownKey { public_key_hex },
    };
    Ok((report, trust))
}

/// The signer's public key and its signature of `message`, in hex.
fn signed_by(key: &SigningKey, message: &[u8]) -> (String, String) {
    (
        to_hex(key.verifying_key().as_bytes()),
        to_hex(&key.sign(message).to_bytes()),
    )
}

/// How far an alert read from the wire can be trusted.
#[derive(Debug, Clone, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "snake_case", tag = "status")]
pub enum AlertTrust {
    /// Signed by a trusted alerting service's key: a verdict.
    Verified { public_key_hex: String },
    /// Signed, and the signature holds, but by a key not configured as trusted.
    UnknownKey { public_key_hex: String },
    /// Signed, but the signature does not verify (altered, or made by another key).
    BadSignature { public_key_hex: String },
    /// A bare alert with no signature: anyone on the network can put one.
    Unsigned,
}

impl AlertTrust {
    pub fn is_verified(&self) -> bool {
        matches!(self, AlertTrust::Verified { .. })
    }

    /// A short name: `verified`, `unknown_key`, `bad_signature`, `unsigned`.
    pub fn name(&self) -> &'static str {
        match self {
            AlertTrust::Verified { .. } => "verified",
            AlertTrust::UnknownKey { .. } => "unknown_key",
            AlertTrust::BadSignature { .. } => "bad_signature",
            AlertTrust::Unsigned => "unsigned",
        }
    }
}

/// Reads an alert payload: a [`SignedAlert`] (PROTOCOL.md §3.6) checked against `trusted`, or a
/// bare [`Alert`] (then `Unsigned`). The alert is returned whatever its trust, for display; only
/// a `Verified` one may be acted on. An error when the payload is neither.
pub fn read_alert(payload: &[u8], trusted: &TrustedKeys) -> Result<(Alert, AlertTrust), JsonError> {
    let Ok(signed) = from_json::<SignedAlert>(payload) else {
        return Ok((from_json::<Alert>(payload)?, AlertTrust::Unsigned));
    };
    let alert: Alert = from_json(signed.alert_json.as_bytes())?;
    let key = match public_key_from_hex(&signed.public_key_hex) {
        Ok(k) if signed.algorithm == SIGNATURE_ALGORITHM => k,
        _ => {
            return Ok((
                alert,
                AlertTrust::BadSignature {
                    public_key_hex: signed.public_key_hex.clone(),
                },
            ))
        }
    };
    let public_key_hex = to_hex(key.as_bytes());
    let holds = from_hex::<64>("signature", &signed.signature_hex)
        .map(|b| Signature::from_bytes(&b))
        .is_ok_and(|sig| {
            key.verify(&SignedAlert::signing_message(&signed.alert_json), &sig)
                .is_ok()
        });
    let trust = match (holds, trusted.keys.contains(&key)) {
        (false, _) => AlertTrust::BadSignature { public_key_hex },
        (true, true) => AlertTrust::Verified { public_key_hex },
        (true, false) => AlertTrust::UnknownKey { public_key_hex },
    };
    Ok((alert, trust))
}

/// The lab keys a gateway trusts (and the alerting keys a console trusts).
#[derive(Debug, Clone, Default)]
pub struct TrustedKeys {
    keys: Vec<VerifyingKey>,
}

impl TrustedKeys {
    pub fn new(keys: Vec<VerifyingKey>) -> Self {
        TrustedKeys { keys }
    }

    /// Parses hex public keys, naming the index of a bad one.
    pub fn from_hex<S: AsRef<str>>(texts: &[S]) -> Result<Self, (usize, SigningError)> {
        let keys = texts
            .iter()
            .enumerate()
            .map(|(i, t)| public_key_from_hex(t.as_ref()).map_err(|e| (i, e)))
            .collect::<Result<_, _>>()?;
        Ok(TrustedKeys { keys })
    }

    /// The keys, in the order given.
    pub fn keys(&self) -> &[VerifyingKey] {
        &self.keys
    }

    pub fn is_empty(&self) -> bool {
        self.keys.is_empty()
    }

    pub fn len(&self) -> usize {
        self.keys.len()
    }

    /// Checks algorithm, key and signature, then parses the record. Nothing of the record is
    /// read before its signature verified.
    pub fn verify(&self, signed: &SignedRecord) -> Result<CalibrationRecord, SigningError> {
        if signed.algorithm != SIGNATURE_ALGORITHM {
            return Err(SigningError::UnsupportedAlgorithm(signed.algorithm.clone()));
        }
        let key = public_key_from_hex(&signed.public_key_hex)?;
        if !self.keys.contains(&key) {
            return Err(SigningError::UnknownKey(to_hex(key.as_bytes())));
        }
        let signature = Signature::from_bytes(&from_hex::<64>("signature", &signed.signature_hex)?);
        key.verify(
            &SignedRecord::signing_message(&signed.record_json),
            &signature,
        )
        .map_err(|_| SigningError::BadSignature(to_hex(key.as_bytes())))?;
        Ok(signed.record()?)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::record::sample;
    use rand::rngs::StdRng;
    use rand::SeedableRng;

    fn key(seed: u64) -> SigningKey {
        SigningKey::generate(&mut StdRng::seed_from_u64(seed))
    }

    #[test]
    fn sign_then_verify() {
        let lab = key(1);
        let record = sample::record("acc-1", 2);
        let signed = sign(&record, &lab);
        let trusted = TrustedKeys::new(vec![key(9).verifying_key(), lab.verifying_key()]);
        assert_eq!(trusted.verify(&signed).unwrap(), record);
        let again = TrustedKeys::from_hex(&[to_hex(lab.verifying_key().as_bytes())]).unwrap();
        assert_eq!(again.verify(&signed).unwrap(), record);
    }

    #[test]
    fn forged_and_foreign_records_are_refused() {
        let lab = key(1);
        let trusted = TrustedKeys::new(vec![lab.verifying_key()]);
        let signed = sign(&sample::record("acc-1", 2), &lab);

        // Tampered content: one digit of the version.
        let mut tampered = signed.clone();
        tampered.record_json = tampered
            .record_json
            .replace("\"version\":2", "\"version\":3");
        assert_ne!(tampered.record_json, signed.record_json);
        let e = trusted.verify(&tampered).unwrap_err();
        assert!(matches!(e, SigningError::BadSignature(_)), "{e}");
        assert_eq!(e.refusal_reason(), RefusalReason::BadSignature);

        // Signed by a key the gateway does not trust.
        let foreign = sign(&sample::record("acc-1", 2), &key(2));
        let e = trusted.verify(&foreign).unwrap_err();
        assert_eq!(e.refusal_reason(), RefusalReason::UnknownKey);

        // A trusted key named, but the signature made by another key.
        let mut swapped = foreign.clone();
        swapped.public_key_hex = signed.public_key_hex.clone();
        assert!(matches!(
            trusted.verify(&swapped),
            Err(SigningError::BadSignature(_))
        ));

        let mut short = signed.clone();
        short.signature_hex.pop();
        assert!(matches!(
            trusted.verify(&short),
            Err(SigningError::HexLength { .. })
        ));

        let mut alg = signed;
        alg.algorithm = "rsa".into();
        assert_eq!(
            trusted.verify(&alg).unwrap_err().refusal_reason(),
            RefusalReason::Malformed
        );
    }

    fn alert() -> Alert {
        crate::messages::sample::alert("hq", "acc-04")
    }

    /// A signed alert verifies under its key; a forged, altered, foreign or bare one is read
    /// but never `Verified`.
    #[test]
    fn alerts_are_verified_or_said_not_to_be() {
        let service = key(4);
        let trusted = TrustedKeys::new(vec![service.verifying_key()]);
        let signed = sign_alert(&alert(), &service);
        let payload = to_json(&signed);
        let (read, trust) = read_alert(&payload, &trusted).unwrap();
        assert_eq!(read, alert());
        assert_eq!(
            trust,
            AlertTrust::Verified {
                public_key_hex: to_hex(service.verifying_key().as_bytes())
            }
        );

        let (_, trust) = read_alert(&payload, &TrustedKeys::default()).unwrap();
        assert_eq!(trust.name(), "unknown_key");

        let mut altered = signed.clone();
        altered.alert_json = altered.alert_json.replace("\"value\":2.5", "\"value\":0.5");
        assert_ne!(altered.alert_json, signed.alert_json);
        let (read, trust) = read_alert(&to_json(&altered), &trusted).unwrap();
        assert_eq!(read.value, 0.5);
        assert_eq!(trust.name(), "bad_signature");

        let mut borrowed = sign_alert(&alert(), &key(5));
        borrowed.public_key_hex = signed.public_key_hex.clone();
        let (_, trust) = read_alert(&to_json(&borrowed), &trusted).unwrap();
        assert_eq!(trust.name(), "bad_signature");

        let (_, trust) = read_alert(&to_json(&alert()), &trusted).unwrap();
        assert_eq!(trust, AlertTrust::Unsigned);
        assert!(read_alert(b"forged", &trusted).is_err());
    }

    #[test]
    fn hex_round_trip_and_errors() {
        let bytes: [u8; 4] = [0x00, 0x7f, 0xa0, 0xff];
        assert_eq!(to_hex(&bytes), "007fa0ff");
        assert_eq!(from_hex::<4>("x", " 007FA0ff\n").unwrap(), bytes);
        assert!(matches!(
            from_hex::<4>("x", "007fa0fg"),
            Err(SigningError::HexDigit {
                found: 'g',
                position: 7,
                ..
            })
        ));
        assert!(matches!(
            from_hex::<4>("x", "é0"),
            Err(SigningError::HexDigit { found: 'é', .. })
        ));
        assert!(matches!(
            from_hex::<4>("x", "00"),
            Err(SigningError::HexLength { .. })
        ));
        let k = key(3);
        let text = to_hex(&k.to_bytes());
        assert_eq!(
            signing_key_from_hex(&text).unwrap().to_bytes(),
            k.to_bytes()
        );
    }
}
