//! The key space: every Zenoh key Triax uses is built and parsed here, and nowhere else.
//!
//! ```text
//! triax/<building>/raw/<sensor>                  RawBatch (binary), sensor node → gateway
//! triax/<building>/corrected/<sensor>            CorrectedBatch (binary), gateway → consumers
//! triax/<building>/tilt/<sensor>                 TiltSample (JSON), gateway → consumers
//! triax/<building>/calibration/push/<sensor>     SignedRecord (JSON), lab → gateway (query)
//! triax/<building>/calibration/ack/<sensor>      PushAck (JSON), gateway → lab
//! triax/<building>/calibration/registry          lab registry queryable (catch-up)
//! triax/<building>/status                        GatewayStatus (JSON), gateway queryable
//! triax/<building>/alert/<sensor>                SignedAlert (JSON), alerting → operators
//! triax/<building>/history/<sensor>              history query → corrected batches (binary)
//! triax/<building>/heartbeat                     Heartbeat (JSON), gateway → consumers
//! triax/<building>/seal                          Seal (binary, signed), gateway → consumers
//! triax/<building>/alerting                      AlertingStatus (JSON), alerting queryable
//! triax/<building>/health/<sensor>               SensorHealthReport (JSON), gateway → lab, operators
//! triax/<building>/buffer/<sensor>               node's buffer query → raw batches (binary), gateway → node
//! triax/<building>/modes                         BuildingModes (JSON), modal service → operators
//! triax/<building>/event/<event>                 SignedEvent (JSON), event service → operators (put and queryable)
//! triax/<building>/events                        EventList (JSON), event service queryable
//! ```
//!
//! Building and sensor ids are 1 to 64 characters from `A–Z a–z 0–9 _ -`. That keeps every key
//! a valid Zenoh key expression with no wildcard (`*`, `**`), no verbatim chunk (`@`), no
//! selector syntax (`?`, `#`, `$`) and no empty chunk, so an id can never widen a subscription.

use std::fmt;
use std::str::FromStr;

use serde::{Deserialize, Serialize};

/// First chunk of every Triax key.
pub const ROOT: &str = "triax";

/// Longest building or sensor id, in bytes.
pub const MAX_ID_LEN: usize = 64;

/// Why an id was refused.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum IdError {
    #[error("{kind} id is empty")]
    Empty { kind: &'static str },
    #[error("{kind} id {id:?} is {len} bytes long; the limit is {MAX_ID_LEN}")]
    TooLong {
        kind: &'static str,
        id: String,
        len: usize,
    },
    #[error(
        "{kind} id {id:?} has {found:?} at byte {position}; allowed are A-Z, a-z, 0-9, '_' and '-'"
    )]
    BadCharacter {
        kind: &'static str,
        id: String,
        found: char,
        position: usize,
    },
}

/// Whether `id` is 1–64 characters from `A–Z a–z 0–9 _ -`: [`validate_id`] without the why,
/// bytewise, for the sample path.
fn is_valid_id(id: &str) -> bool {
    (1..=MAX_ID_LEN).contains(&id.len())
        && id
            .bytes()
            .all(|b| b.is_ascii_alphanumeric() || b == b'_' || b == b'-')
}

fn validate_id(kind: &'static str, id: &str) -> Result<(), IdError> {
    if is_valid_id(id) {
        return Ok(());
    }
    if id.is_empty() {
        return Err(IdError::Empty { kind });
    }
    if id.len() > MAX_ID_LEN {
        return Err(IdError::TooLong {
            kind,
            id: id.chars().take(MAX_ID_LEN).collect::<String>() + "…",
            len: id.len(),
        });
    }
    if let Some((position, found)) = id
        .char_indices()
        .find(|&(_, c)| !(c.is_ascii_alphanumeric() || c == '_' || c == '-'))
    {
        return Err(IdError::BadCharacter {
            kind,
            id: id.to_owned(),
            found,
            position,
        });
    }
    Ok(())
}

macro_rules! id_type {
    ($(#[$doc:meta])* $name:ident, $kind:literal) => {
        $(#[$doc])*
        #[derive(Debug, Clone, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
        #[serde(try_from = "String", into = "String")]
        pub struct $name(String);

        impl $name {
            /// Validates `id` (1–64 characters from `A–Z a–z 0–9 _ -`).
            pub fn new(id: impl Into<String>) -> Result<Self, IdError> {
                let id = id.into();
                validate_id($kind, &id)?;
                Ok(Self(id))
            }

            pub fn as_str(&self) -> &str {
                &self.0
            }
        }

        impl FromStr for $name {
            type Err = IdError;
            fn from_str(s: &str) -> Result<Self, IdError> {
                Self::new(s)
            }
        }

        impl TryFrom<String> for $name {
            type Error = IdError;
            fn try_from(s: String) -> Result<Self, IdError> {
                Self::new(s)
            }
        }

        impl From<$name> for String {
            fn from(id: $name) -> String {
                id.0
            }
        }

        impl fmt::Display for $name {
            fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
                f.write_str(&self.0)
            }
        }

        impl AsRef<str> for $name {
            fn as_ref(&self) -> &str {
                &self.0
            }
        }
    };
}

id_type!(
    /// A building: one gateway, one key space.
    BuildingId,
    "building"
);
id_type!(
    /// A three-axis sensor, unique within its building and across the lab's registry.
    SensorId,
    "sensor"
);
id_type!(
    /// An event of a building, unique within the building (the event service names it by its
    /// start, `20270115T080112Z`).
    EventId,
    "event"
);

/// A sensor's id held in place, with no allocation behind it: the key of a table looked up
/// every batch. A key that points to its text elsewhere (a [`SensorId`]) is, at a building's
/// pace, one more cold line to wait for before the lookup can even compare (BENCHMARKS.md,
/// "A fifth look"). Hashed and compared as the id's bytes, so that a table keyed by it is
/// looked up with the `&[u8]` of any id.
#[derive(Clone, Copy)]
pub struct InlineId {
    len: u8,
    bytes: [u8; MAX_ID_LEN],
}

impl InlineId {
    pub fn new(id: &SensorId) -> InlineId {
        InlineId::of_valid(id.as_str())
    }

    /// The id `text` is, when it is a valid id (1 to [`MAX_ID_LEN`] of `[A-Za-z0-9_-]`).
    pub fn parse(text: &str) -> Option<InlineId> {
        is_valid_id(text).then(|| InlineId::of_valid(text))
    }

    fn of_valid(id: &str) -> InlineId {
        let id = id.as_bytes();
        let mut bytes = [0; MAX_ID_LEN];
        // A valid id has 1 to MAX_ID_LEN bytes.
        bytes[..id.len()].copy_from_slice(id);
        InlineId {
            len: id.len() as u8,
            bytes,
        }
    }

    pub fn as_bytes(&self) -> &[u8] {
        &self.bytes[..usize::from(self.len)]
    }

    pub fn as_str(&self) -> &str {
        // Made from a valid id, whose characters are all ASCII: never the fallback.
        std::str::from_utf8(self.as_bytes()).unwrap_or_default()
    }

    /// The id it holds.
    pub fn to_sensor_id(&self) -> SensorId {
        // Made from a valid id, whose characters are all ASCII.
        SensorId(String::from_utf8_lossy(self.as_bytes()).into_owned())
    }
}

impl std::borrow::Borrow<[u8]> for InlineId {
    fn borrow(&self) -> &[u8] {
        self.as_bytes()
    }
}

// As the bytes' own: `Borrow<[u8]>` asks that a lookup by bytes hash alike.
impl std::hash::Hash for InlineId {
    fn hash<H: std::hash::Hasher>(&self, state: &mut H) {
        self.as_bytes().hash(state);
    }
}

impl PartialEq for InlineId {
    fn eq(&self, other: &InlineId) -> bool {
        self.as_bytes() == other.as_bytes()
    }
}

impl Eq for InlineId {}

impl fmt::Debug for InlineId {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "InlineId({:?})",
            String::from_utf8_lossy(self.as_bytes())
        )
    }
}

/// A concrete Triax key.
#[derive(Debug, Clone, PartialEq, Eq, Hash)]
pub enum Key {
    Raw(BuildingId, SensorId),
    Corrected(BuildingId, SensorId),
    Tilt(BuildingId, SensorId),
    CalibrationPush(BuildingId, SensorId),
    CalibrationAck(BuildingId, SensorId),
    CalibrationRegistry(BuildingId),
    Status(BuildingId),
    Alert(BuildingId, SensorId),
    History(BuildingId, SensorId),
    Heartbeat(BuildingId),
    /// What an alerting service last judged of the building's sensors (its queryable).
    Alerting(BuildingId),
    /// A sensor's calibration health (published, and the gateway's queryable).
    Health(BuildingId, SensorId),
    /// A sensor node's buffer of the raw batches it sent (its queryable, for backfill).
    Buffer(BuildingId, SensorId),
    /// The building's modes identified over each window (the modal service's publications).
    Modes(BuildingId),
    /// The gateway's signed seals over the corrected batches it published (PROTOCOL.md §6).
    Seal(BuildingId),
    /// One event's signed report (the event service's publications, and its queryable).
    Event(BuildingId, EventId),
    /// The building's list of events (the event service's queryable).
    Events(BuildingId),
}

/// Why a key string is not a Triax key.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum KeyError {
    #[error("key {key:?} does not start with \"{ROOT}/\"")]
    WrongRoot { key: String },
    #[error("key {key:?} has an unknown shape after the building id")]
    UnknownShape { key: String },
    #[error("key {key:?}: {source}")]
    BadId {
        key: String,
        #[source]
        source: IdError,
    },
}

impl Key {
    pub fn building(&self) -> &BuildingId {
        match self {
            Key::Raw(b, _)
            | Key::Corrected(b, _)
            | Key::Tilt(b, _)
            | Key::CalibrationPush(b, _)
            | Key::CalibrationAck(b, _)
            | Key::CalibrationRegistry(b)
            | Key::Status(b)
            | Key::Alert(b, _)
            | Key::History(b, _)
            | Key::Heartbeat(b)
            | Key::Seal(b)
            | Key::Alerting(b)
            | Key::Health(b, _)
            | Key::Buffer(b, _)
            | Key::Modes(b)
            | Key::Event(b, _)
            | Key::Events(b) => b,
        }
    }

    pub fn sensor(&self) -> Option<&SensorId> {
        match self {
            Key::Raw(_, s)
            | Key::Corrected(_, s)
            | Key::Tilt(_, s)
            | Key::CalibrationPush(_, s)
            | Key::CalibrationAck(_, s)
            | Key::Alert(_, s)
            | Key::History(_, s)
            | Key::Health(_, s)
            | Key::Buffer(_, s) => Some(s),
            Key::CalibrationRegistry(_)
            | Key::Status(_)
            | Key::Heartbeat(_)
            | Key::Seal(_)
            | Key::Alerting(_)
            | Key::Modes(_)
            | Key::Event(_, _)
            | Key::Events(_) => None,
        }
    }

    /// Parses a concrete key (no wildcards).
    pub fn parse(key: &str) -> Result<Key, KeyError> {
        let chunks: Vec<&str> = key.split('/').collect();
        if chunks.first() != Some(&ROOT) || chunks.len() < 3 {
            return Err(KeyError::WrongRoot { key: key.into() });
        }
        let bad_id = |source| KeyError::BadId {
            key: key.into(),
            source,
        };
        let b = BuildingId::new(chunks[1]).map_err(bad_id)?;
        let sensor = |s: &str| SensorId::new(s).map_err(bad_id);
        Ok(match chunks[2..] {
            ["raw", s] => Key::Raw(b, sensor(s)?),
            ["corrected", s] => Key::Corrected(b, sensor(s)?),
            ["tilt", s] => Key::Tilt(b, sensor(s)?),
            ["calibration", "push", s] => Key::CalibrationPush(b, sensor(s)?),
            ["calibration", "ack", s] => Key::CalibrationAck(b, sensor(s)?),
            ["calibration", "registry"] => Key::CalibrationRegistry(b),
            ["status"] => Key::Status(b),
            ["alert", s] => Key::Alert(b, sensor(s)?),
            ["history", s] => Key::History(b, sensor(s)?),
            ["heartbeat"] => Key::Heartbeat(b),
            ["seal"] => Key::Seal(b),
            ["alerting"] => Key::Alerting(b),
            ["health", s] => Key::Health(b, sensor(s)?),
            ["buffer", s] => Key::Buffer(b, sensor(s)?),
            ["modes"] => Key::Modes(b),
            ["event", e] => Key::Event(b, EventId::new(e).map_err(bad_id)?),
            ["events"] => Key::Events(b),
            _ => return Err(KeyError::UnknownShape { key: key.into() }),
        })
    }
}

impl fmt::Display for Key {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Key::Raw(b, s) => write!(f, "{ROOT}/{b}/raw/{s}"),
            Key::Corrected(b, s) => write!(f, "{ROOT}/{b}/corrected/{s}"),
            Key::Tilt(b, s) => write!(f, "{ROOT}/{b}/tilt/{s}"),
            Key::CalibrationPush(b, s) => write!(f, "{ROOT}/{b}/calibration/push/{s}"),
            Key::CalibrationAck(b, s) => write!(f, "{ROOT}/{b}/calibration/ack/{s}"),
            Key::CalibrationRegistry(b) => write!(f, "{ROOT}/{b}/calibration/registry"),
            Key::Status(b) => write!(f, "{ROOT}/{b}/status"),
            Key::Alert(b, s) => write!(f, "{ROOT}/{b}/alert/{s}"),
            Key::History(b, s) => write!(f, "{ROOT}/{b}/history/{s}"),
            Key::Heartbeat(b) => write!(f, "{ROOT}/{b}/heartbeat"),
            Key::Seal(b) => write!(f, "{ROOT}/{b}/seal"),
            Key::Alerting(b) => write!(f, "{ROOT}/{b}/alerting"),
            Key::Health(b, s) => write!(f, "{ROOT}/{b}/health/{s}"),
            Key::Buffer(b, s) => write!(f, "{ROOT}/{b}/buffer/{s}"),
            Key::Modes(b) => write!(f, "{ROOT}/{b}/modes"),
            Key::Event(b, e) => write!(f, "{ROOT}/{b}/event/{e}"),
            Key::Events(b) => write!(f, "{ROOT}/{b}/events"),
        }
    }
}

/// Which stream family a wildcard subscription covers.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Stream {
    Raw,
    Corrected,
    Tilt,
    CalibrationPush,
    CalibrationAck,
    Alert,
    History,
    Health,
    Buffer,
}

impl Stream {
    fn path(self) -> &'static str {
        match self {
            Stream::Raw => "raw",
            Stream::Corrected => "corrected",
            Stream::Tilt => "tilt",
            Stream::CalibrationPush => "calibration/push",
            Stream::CalibrationAck => "calibration/ack",
            Stream::Alert => "alert",
            Stream::History => "history",
            Stream::Health => "health",
            Stream::Buffer => "buffer",
        }
    }
}

/// Key expression for every sensor of one stream family in one building,
/// e.g. `triax/b1/raw/*`.
pub fn all_sensors(building: &BuildingId, stream: Stream) -> String {
    format!("{ROOT}/{building}/{}/*", stream.path())
}

/// The sensor chunk of a key received on a per-sensor subscription ([`all_sensors`],
/// [`all_buildings`]): its last chunk, unvalidated, for routing on the hot path without
/// allocating. Zenoh delivers only keys that match the subscription, so the last chunk is the
/// sensor's; the payload's own sensor id is checked against it afterwards.
pub fn sensor_chunk(key: &str) -> &str {
    key.rsplit_once('/').map_or(key, |(_, sensor)| sensor)
}

/// Why a key expression delivered on a building's raw subscription is not one of its sensors'
/// raw keys. Zenoh delivers a put to every subscription its key expression intersects, so a put
/// on `triax/*/raw/x` or `**/x` reaches the raw subscription of every building: only a concrete
/// key of the building's own is data of one of its sensors.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum RawKeyRefusal {
    /// A chunk holds a wildcard (`*`, `**`, `$*`): the put addresses many keys, no one sensor.
    Wildcard,
    /// A concrete key of another building (reached here through a wildcard subscription).
    OtherBuilding,
    /// Not `triax/<building>/raw/<sensor>` with a valid sensor id.
    Malformed,
}

impl RawKeyRefusal {
    /// Every reason, in the order status and metrics list them.
    pub const ALL: [RawKeyRefusal; 3] = [
        RawKeyRefusal::Wildcard,
        RawKeyRefusal::OtherBuilding,
        RawKeyRefusal::Malformed,
    ];

    /// Name used in status, metrics and logs.
    pub fn as_str(self) -> &'static str {
        match self {
            RawKeyRefusal::Wildcard => "wildcard",
            RawKeyRefusal::OtherBuilding => "other_building",
            RawKeyRefusal::Malformed => "malformed",
        }
    }
}

/// The sensor of `key` when it is exactly `triax/<building>/raw/<sensor>` with a valid sensor
/// id; why not otherwise. For the sample path: no allocation; a raw key of the building is
/// recognised by its prefix and one pass over the id, and only a refusal asks why.
pub fn raw_sensor_of<'k>(key: &'k str, building: &BuildingId) -> Result<&'k str, RawKeyRefusal> {
    // Neither a building id nor a sensor id holds `/`, `*` or `$`: what this accepts is what
    // the chunk by chunk reading below accepts, and nothing else.
    let sensor = key
        .strip_prefix(ROOT)
        .and_then(|k| k.strip_prefix('/'))
        .and_then(|k| k.strip_prefix(building.as_str()))
        .and_then(|k| k.strip_prefix("/raw/"));
    match sensor {
        Some(sensor) if is_valid_id(sensor) => Ok(sensor),
        _ => raw_key_refusal(key, building),
    }
}

/// [`raw_sensor_of`] chunk by chunk, which tells why a key is refused.
fn raw_key_refusal<'k>(key: &'k str, building: &BuildingId) -> Result<&'k str, RawKeyRefusal> {
    if key.contains(['*', '$']) {
        return Err(RawKeyRefusal::Wildcard);
    }
    let mut chunks = key.split('/');
    let (Some(ROOT), Some(b), Some("raw"), Some(sensor), None) = (
        chunks.next(),
        chunks.next(),
        chunks.next(),
        chunks.next(),
        chunks.next(),
    ) else {
        return Err(RawKeyRefusal::Malformed);
    };
    if b != building.as_str() {
        return Err(match validate_id("building", b) {
            Ok(()) => RawKeyRefusal::OtherBuilding,
            Err(_) => RawKeyRefusal::Malformed,
        });
    }
    validate_id("sensor", sensor).map_err(|_| RawKeyRefusal::Malformed)?;
    Ok(sensor)
}

/// Key expression for every sensor of one stream family in every building,
/// e.g. `triax/*/corrected/*`.
pub fn all_buildings(stream: Stream) -> String {
    format!("{ROOT}/*/{}/*", stream.path())
}

/// Key expression for the registry of every building, served by the lab.
pub fn all_registries() -> String {
    format!("{ROOT}/*/calibration/registry")
}

/// Key expression for the status queryable of every building (what a console asks to find
/// the gateways).
pub fn all_statuses() -> String {
    format!("{ROOT}/*/status")
}

/// Key expression for the heartbeat of every building.
pub fn all_heartbeats() -> String {
    format!("{ROOT}/*/heartbeat")
}

/// Key expression for every event report of every building, or of one.
pub fn all_events(building: Option<&BuildingId>) -> String {
    match building {
        Some(b) => format!("{ROOT}/{b}/event/*"),
        None => format!("{ROOT}/*/event/*"),
    }
}

/// Key expression for the event list of every building, or of one.
pub fn all_event_lists(building: Option<&BuildingId>) -> String {
    match building {
        Some(b) => format!("{ROOT}/{b}/events"),
        None => format!("{ROOT}/*/events"),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_inline_id_is_found_by_its_bytes_only() {
        let ids = ["acc-1", "acc-10", "a", &"x".repeat(MAX_ID_LEN)].map(s);
        let map: std::collections::HashMap<InlineId, usize> = ids
            .iter()
            .enumerate()
            .map(|(i, id)| (InlineId::new(id), i))
            .collect();
        for (i, id) in ids.iter().enumerate() {
            assert_eq!(map.get(id.as_str().as_bytes()), Some(&i), "{id}");
            assert_eq!(&InlineId::new(id).to_sensor_id(), id);
        }
        for id in &ids {
            let parsed = InlineId::parse(id.as_str()).expect("a valid id parses");
            assert_eq!(parsed.as_str(), id.as_str());
            assert_eq!(parsed, InlineId::new(id));
        }
        let longest = "x".repeat(MAX_ID_LEN);
        assert_eq!(
            InlineId::parse(&longest).map(|i| i.as_str().len()),
            Some(MAX_ID_LEN)
        );
        for invalid in [
            "",
            "acc/1",
            "acc-*",
            "acc 1",
            "é",
            &"x".repeat(MAX_ID_LEN + 1),
        ] {
            assert!(InlineId::parse(invalid).is_none(), "{invalid:?}");
        }
        for absent in ["acc-", "acc-100", "acc-1\0", ""] {
            assert_eq!(map.get(absent.as_bytes()), None, "{absent:?}");
        }
    }

    fn b(s: &str) -> BuildingId {
        BuildingId::new(s).unwrap()
    }
    fn s(x: &str) -> SensorId {
        SensorId::new(x).unwrap()
    }

    #[test]
    fn every_key_round_trips() {
        let keys = [
            Key::Raw(b("hq"), s("acc-01")),
            Key::Corrected(b("hq"), s("acc-01")),
            Key::Tilt(b("hq"), s("acc-01")),
            Key::CalibrationPush(b("hq"), s("acc-01")),
            Key::CalibrationAck(b("hq"), s("acc-01")),
            Key::CalibrationRegistry(b("hq")),
            Key::Status(b("hq")),
            Key::Alert(b("hq"), s("acc-01")),
            Key::History(b("hq"), s("acc-01")),
            Key::Heartbeat(b("hq")),
            Key::Seal(b("hq")),
            Key::Alerting(b("hq")),
            Key::Health(b("hq"), s("acc-01")),
            Key::Buffer(b("hq"), s("acc-01")),
            Key::Modes(b("hq")),
            Key::Event(b("hq"), EventId::new("20270115T080112Z").unwrap()),
            Key::Events(b("hq")),
        ];
        for k in keys {
            let text = k.to_string();
            assert_eq!(Key::parse(&text).unwrap(), k, "{text}");
        }
        assert_eq!(
            Key::Raw(b("B_2"), s("x")).to_string(),
            "triax/B_2/raw/x",
            "documented layout"
        );
    }

    #[test]
    fn ids_are_validated() {
        assert!(matches!(
            SensorId::new(""),
            Err(IdError::Empty { kind: "sensor" })
        ));
        assert!(matches!(
            BuildingId::new("a".repeat(65)),
            Err(IdError::TooLong { len: 65, .. })
        ));
        assert!(BuildingId::new("a".repeat(64)).is_ok());
        for bad in ["a/b", "a*", "**", "a b", "x?y", "$z", "@q", "é"] {
            let err = SensorId::new(bad).unwrap_err();
            assert!(matches!(err, IdError::BadCharacter { .. }), "{bad}: {err}");
        }
        let msg = SensorId::new("ab/c").unwrap_err().to_string();
        assert!(msg.contains("'/'") && msg.contains("byte 2"), "{msg}");
    }

    #[test]
    fn foreign_keys_are_refused() {
        for bad in [
            "",
            "triax",
            "triax/hq",
            "other/hq/raw/s",
            "triax/hq/raw",
            "triax/hq/raw/s/extra",
            "triax/hq/unknown/s",
            "triax/hq/calibration/other/s",
        ] {
            assert!(Key::parse(bad).is_err(), "{bad:?} parsed");
        }
        assert!(matches!(
            Key::parse("triax/h q/raw/s"),
            Err(KeyError::BadId { .. })
        ));
    }

    #[test]
    fn sensor_chunk_is_the_last_chunk() {
        let k = Key::Raw(b("hq"), s("acc-9")).to_string();
        assert_eq!(sensor_chunk(&k), "acc-9");
        assert_eq!(sensor_chunk("acc-9"), "acc-9");
    }

    #[test]
    fn only_concrete_raw_keys_of_the_building_name_a_sensor() {
        let hq = b("hq");
        assert_eq!(raw_sensor_of("triax/hq/raw/acc-01", &hq), Ok("acc-01"));
        for wild in [
            "triax/*/raw/acc-01",
            "**/raw/acc-01",
            "triax/**/acc-01",
            "**/acc-01",
            "triax/hq/raw/*",
            "triax/hq/*/acc-01",
            "triax/hq/raw/acc-$*",
            "triax/hq/raw/**",
        ] {
            assert_eq!(
                raw_sensor_of(wild, &hq),
                Err(RawKeyRefusal::Wildcard),
                "{wild}"
            );
        }
        assert_eq!(
            raw_sensor_of("triax/other/raw/acc-01", &hq),
            Err(RawKeyRefusal::OtherBuilding)
        );
        for bad in [
            "triax/hq/raw",
            "triax/hq/raw/a/b",
            "triax/hq/corrected/acc-01",
            "other/hq/raw/acc-01",
            "triax/hq/raw/@x",
            "triax/h@q/raw/x",
            "triax/hq/raw/",
        ] {
            assert_eq!(
                raw_sensor_of(bad, &hq),
                Err(RawKeyRefusal::Malformed),
                "{bad}"
            );
        }
    }

    /// The prefix path answers as the chunk by chunk one does, for keys put together from
    /// every kind of piece a hostile or broken node might send.
    #[test]
    fn the_quick_reading_of_a_raw_key_agrees_with_the_full_one() {
        let hq = b("hq");
        let long = "x".repeat(MAX_ID_LEN);
        let too_long = "x".repeat(MAX_ID_LEN + 1);
        let roots = ["triax", "triaxx", "triax/", "", "Triax", "**", "*"];
        let buildings = ["hq", "hq2", "h", "other", "", "*", "$*", "hq/", "h@q"];
        let streams = ["raw", "raw/", "raws", "corrected", "", "*", "**"];
        let sensors = [
            "acc-01", "a", &long, &too_long, "", "*", "**", "acc-$*", "acc/01", "acc-01/", "@x",
            "acc é", "a_b-C9", "acc\0",
        ];
        let mut accepted = 0;
        for r in roots {
            for bd in buildings {
                for st in streams {
                    for sn in sensors {
                        let key = format!("{r}/{bd}/{st}/{sn}");
                        let quick = raw_sensor_of(&key, &hq);
                        assert_eq!(quick, raw_key_refusal(&key, &hq), "{key:?}");
                        accepted += usize::from(quick.is_ok());
                    }
                }
            }
        }
        // "acc-01", "a", the longest id and "a_b-C9" under triax/hq/raw/.
        assert_eq!(accepted, 4);
    }

    #[test]
    fn wildcards() {
        assert_eq!(all_sensors(&b("hq"), Stream::Raw), "triax/hq/raw/*");
        assert_eq!(all_buildings(Stream::Corrected), "triax/*/corrected/*");
        assert_eq!(
            all_sensors(&b("hq"), Stream::CalibrationPush),
            "triax/hq/calibration/push/*"
        );
        assert_eq!(all_registries(), "triax/*/calibration/registry");
        assert_eq!(all_statuses(), "triax/*/status");
        assert_eq!(all_heartbeats(), "triax/*/heartbeat");
        assert_eq!(all_events(Some(&b("hq"))), "triax/hq/event/*");
        assert_eq!(all_event_lists(None), "triax/*/events");
    }
}
