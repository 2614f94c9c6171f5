//! The store's key space: every sled key and index value is built and parsed here, and nowhere
//! else.
//!
//! ```text
//! tree "records":  <sensor id bytes> 0x00 <version: u64 big-endian>  →  record, compact JSON
//! tree "current":  <sensor id bytes>                                 →  version: u64 big-endian
//! tree "meta":     "schema_version"                                  →  u32 big-endian
//! tree "suspect":  <sensor id bytes> 0x00 <version: u64 big-endian>  →  flagged_from_ns: i64 big-endian
//! ```
//!
//! The suspect tree came after schema version 1 without a bump: a build that does not know it
//! ignores it, and a store without it has no suspect records.
//!
//! Sensor ids are 1 to 64 bytes from `A–Z a–z 0–9 _ -`, so they never contain `0x00`. Because
//! `0x00` sorts below every id byte and versions are big-endian, sled's byte order is the order
//! people expect: by sensor id, then by version ascending. A sensor's history is one contiguous
//! range, and the prefix `<id> 0x00` of one sensor is never a prefix of another's keys.

use std::fmt::Write as _;

use triax_protocol::SensorId;

/// Name of the tree holding every record of every sensor.
pub(crate) const RECORDS_TREE: &str = "records";
/// Name of the index tree: sensor id to its current version.
pub(crate) const CURRENT_TREE: &str = "current";
/// Name of the tree of records the field health checks found suspect.
pub(crate) const SUSPECT_TREE: &str = "suspect";
/// Name of the tree holding store-wide facts such as the schema version.
pub(crate) const META_TREE: &str = "meta";
/// Key of the schema version in the meta tree.
pub(crate) const SCHEMA_VERSION_KEY: &[u8] = b"schema_version";

const SEPARATOR: u8 = 0x00;
const VERSION_BYTES: usize = 8;

/// Prefix shared by every record key of one sensor.
pub(crate) fn sensor_prefix(sensor_id: &SensorId) -> Vec<u8> {
    let mut key = Vec::with_capacity(sensor_id.as_str().len() + 1 + VERSION_BYTES);
    key.extend_from_slice(sensor_id.as_str().as_bytes());
    key.push(SEPARATOR);
    key
}

/// Key of one version of one sensor's record.
pub(crate) fn record_key(sensor_id: &SensorId, version: u64) -> Vec<u8> {
    let mut key = sensor_prefix(sensor_id);
    key.extend_from_slice(&version.to_be_bytes());
    key
}

/// Splits a record key into sensor id and version.
pub(crate) fn parse_record_key(key: &[u8]) -> Result<(SensorId, u64), String> {
    let Some(split) = key.len().checked_sub(1 + VERSION_BYTES) else {
        return Err(format!(
            "key is {} bytes, too short for a record key",
            key.len()
        ));
    };
    if key[split] != SEPARATOR {
        return Err("no separator before the version".into());
    }
    let sensor_id = parse_sensor_id(&key[..split])?;
    let mut version = [0; VERSION_BYTES];
    version.copy_from_slice(&key[split + 1..]);
    Ok((sensor_id, u64::from_be_bytes(version)))
}

/// Key of a sensor in the current-version index.
pub(crate) fn current_key(sensor_id: &SensorId) -> Vec<u8> {
    sensor_id.as_str().as_bytes().to_vec()
}

/// Parses a key of the current-version index.
pub(crate) fn parse_current_key(key: &[u8]) -> Result<SensorId, String> {
    parse_sensor_id(key)
}

fn parse_sensor_id(bytes: &[u8]) -> Result<SensorId, String> {
    let text = std::str::from_utf8(bytes).map_err(|e| format!("sensor id is not UTF-8: {e}"))?;
    SensorId::new(text).map_err(|e| e.to_string())
}

/// Value of the current-version index.
pub(crate) fn encode_version(version: u64) -> [u8; VERSION_BYTES] {
    version.to_be_bytes()
}

/// Parses a value of the current-version index.
pub(crate) fn decode_version(value: &[u8]) -> Result<u64, String> {
    let bytes: [u8; VERSION_BYTES] = value
        .try_into()
        .map_err(|_| format!("version is {} bytes, not {VERSION_BYTES}", value.len()))?;
    Ok(u64::from_be_bytes(bytes))
}

pub(crate) fn encode_schema_version(version: u32) -> [u8; 4] {
    version.to_be_bytes()
}

pub(crate) fn decode_schema_version(value: &[u8]) -> Result<u32, String> {
    let bytes: [u8; 4] = value
        .try_into()
        .map_err(|_| format!("schema version is {} bytes, not 4", value.len()))?;
    Ok(u32::from_be_bytes(bytes))
}

/// Printable ASCII as is, every other byte as `\xNN`.
pub(crate) fn escape(bytes: &[u8]) -> String {
    let mut out = String::with_capacity(bytes.len());
    for &b in bytes {
        if b.is_ascii_graphic() {
            out.push(char::from(b));
        } else {
            // Writing to a String cannot fail.
            let _ = write!(out, "\\x{b:02x}");
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn id(s: &str) -> SensorId {
        SensorId::new(s).unwrap()
    }

    #[test]
    fn record_keys_round_trip() {
        for (s, v) in [("a", 1), ("s-1_Z", u64::MAX), ("x", 0x0102_0304_0506_0708)] {
            let key = record_key(&id(s), v);
            assert_eq!(parse_record_key(&key).unwrap(), (id(s), v));
        }
    }

    #[test]
    fn byte_order_is_sensor_then_version() {
        let mut keys = [
            record_key(&id("s1a"), 1),
            record_key(&id("s1"), 256),
            record_key(&id("s1"), 2),
            record_key(&id("s2"), 1),
            record_key(&id("s1"), 1),
        ];
        keys.sort();
        let parsed: Vec<_> = keys.iter().map(|k| parse_record_key(k).unwrap()).collect();
        assert_eq!(
            parsed,
            vec![
                (id("s1"), 1),
                (id("s1"), 2),
                (id("s1"), 256),
                (id("s1a"), 1),
                (id("s2"), 1)
            ]
        );
        assert!(!record_key(&id("s1a"), 1).starts_with(&sensor_prefix(&id("s1"))));
    }

    #[test]
    fn malformed_keys_are_described() {
        assert!(parse_record_key(b"short").is_err());
        assert!(parse_record_key(b"s1\x01\0\0\0\0\0\0\0\x01").is_err());
        assert!(parse_record_key(b"bad id\0\0\0\0\0\0\0\0\x01").is_err());
        assert_eq!(escape(b"a\xff"), "a\\xff");
        assert!(decode_version(b"abc").is_err());
        assert_eq!(decode_version(&encode_version(7)).unwrap(), 7);
    }
}
