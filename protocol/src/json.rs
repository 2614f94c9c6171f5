//! The JSON encoding used for records, acknowledgements, status, tilt and alerts.
//!
//! Every JSON message is an object with a `format_version` field. The decoder reads that field
//! first, so a message from a newer format is refused as such rather than as a confusing field
//! error, and refuses payloads above [`MAX_JSON_BYTES`] before parsing them.

use serde::de::DeserializeOwned;
use serde::{Deserialize, Serialize};

/// The JSON format version this build writes and reads.
pub const JSON_FORMAT_VERSION: u32 = 1;

/// Largest JSON payload accepted. A record with full covariances is about 10 KiB; a status
/// report for 10 000 sensors about 4 MiB, so status has its own, larger limit.
pub const MAX_JSON_BYTES: usize = 1 << 20;

/// A message with a JSON encoding.
pub trait JsonMessage: Serialize + DeserializeOwned {
    /// Name used in error messages ("calibration record", "push acknowledgement", …).
    const WHAT: &'static str;
    /// Largest payload accepted for this message.
    const MAX_BYTES: usize = MAX_JSON_BYTES;
    /// The message's `format_version` field.
    fn format_version(&self) -> u32;
}

/// Why a JSON payload was refused.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum JsonError {
    #[error("{what} payload is {len} bytes; the limit is {max}")]
    TooLarge {
        what: &'static str,
        len: usize,
        max: usize,
    },
    #[error("{what}: line {line}, column {column}: {message}")]
    Malformed {
        what: &'static str,
        line: usize,
        column: usize,
        message: String,
    },
    #[error("{what} has format_version {found}; this build reads {JSON_FORMAT_VERSION}")]
    UnsupportedVersion { what: &'static str, found: u64 },
}

fn malformed(what: &'static str, e: serde_json::Error) -> JsonError {
    JsonError::Malformed {
        what,
        line: e.line(),
        column: e.column(),
        message: e.to_string(),
    }
}

/// Compact JSON, as sent on the wire.
pub fn to_json<T: JsonMessage>(message: &T) -> Vec<u8> {
    // Our messages are plain structs with string keys: serialization cannot fail.
    serde_json::to_vec(message).expect("JSON messages always serialize")
}

/// Indented JSON, for files people read (records, exports).
pub fn to_json_pretty<T: JsonMessage>(message: &T) -> Vec<u8> {
    // As in to_json: plain structs with string keys always serialize.
    let mut out = serde_json::to_vec_pretty(message).expect("JSON messages always serialize");
    out.push(b'\n');
    out
}

/// Decodes a message, checking size and format version.
///
/// The common case parses once. Only when the full parse fails, or yields another format
/// version, is the `format_version` field read on its own, so that a message from a newer format
/// is reported as such rather than as a confusing field error.
pub fn from_json<T: JsonMessage>(bytes: &[u8]) -> Result<T, JsonError> {
    if bytes.len() > T::MAX_BYTES {
        return Err(JsonError::TooLarge {
            what: T::WHAT,
            len: bytes.len(),
            max: T::MAX_BYTES,
        });
    }
    match serde_json::from_slice::<T>(bytes) {
        Ok(m) if m.format_version() == JSON_FORMAT_VERSION => Ok(m),
        Ok(m) => Err(JsonError::UnsupportedVersion {
            what: T::WHAT,
            found: u64::from(m.format_version()),
        }),
        Err(e) => Err(version_error::<T>(bytes).unwrap_or_else(|| malformed(T::WHAT, e))),
    }
}

/// The error to report instead of a parse error, when the `format_version` field explains it.
fn version_error<T: JsonMessage>(bytes: &[u8]) -> Option<JsonError> {
    #[derive(Deserialize)]
    struct Probe {
        format_version: Option<serde_json::Value>,
    }
    let probe: Probe = serde_json::from_slice(bytes).ok()?;
    let message = match probe.format_version {
        None => "missing field `format_version`".to_owned(),
        Some(v) => match v.as_u64() {
            Some(found) if found == u64::from(JSON_FORMAT_VERSION) => return None,
            Some(found) => {
                return Some(JsonError::UnsupportedVersion {
                    what: T::WHAT,
                    found,
                })
            }
            None => format!("format_version {v} is not a non-negative integer"),
        },
    };
    Some(JsonError::Malformed {
        what: T::WHAT,
        line: 1,
        column: 1,
        message,
    })
}
