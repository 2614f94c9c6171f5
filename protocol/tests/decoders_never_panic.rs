//! Property tests: no decoder panics, whatever the bytes.
//!
//! Arbitrary bytes rarely get past the magic, so the strongest cases start from a valid payload
//! and corrupt it: flipped bytes, truncation, extension, a forged sample count.

use proptest::prelude::*;
use triax_protocol::batch::{
    BatchHeader, CorrectedBatch, CorrectedSample, CorrectionInfo, Mode, RawBatch, RawBatchView,
};
use triax_protocol::messages::{Alert, GatewayStatus, PushAck, SignedRecord, TiltSample};
use triax_protocol::{from_json, CalibrationRecord, Key, SensorId};

fn header(n: u64) -> BatchHeader {
    BatchHeader {
        sensor_id: SensorId::new("node-1").unwrap(),
        sequence: n,
        timestamp_ns: 1_000_000_000 * n as i64,
        sample_rate_hz: 100.0,
    }
}

fn valid_raw(n: usize) -> Vec<u8> {
    RawBatch {
        header: header(n as u64),
        temperature_c: n.is_multiple_of(2).then_some(20.0),
        samples: (0..n).map(|i| [i as f32, 1.0, -1.0]).collect(),
    }
    .encode()
}

fn valid_corrected(n: usize) -> Vec<u8> {
    CorrectedBatch {
        header: header(n as u64),
        batch_flags: 0,
        info: CorrectionInfo {
            calibration_version: 3,
            mode: Mode::Dynamic,
            coverage_factor: 2.0,
        },
        samples: vec![
            CorrectedSample {
                accel_mps2: [0.0, 0.0, 9.8],
                uncertainty_mps2: [0.01; 3],
                flags: 0,
            };
            n
        ],
    }
    .encode()
}

fn decode_all(bytes: &[u8]) {
    let _ = RawBatch::decode(bytes);
    let _ = RawBatchView::parse(bytes);
    let _ = CorrectedBatch::decode(bytes);
    let _ = from_json::<CalibrationRecord>(bytes);
    let _ = from_json::<SignedRecord>(bytes);
    let _ = from_json::<PushAck>(bytes);
    let _ = from_json::<GatewayStatus>(bytes);
    let _ = from_json::<TiltSample>(bytes);
    let _ = from_json::<Alert>(bytes);
    if let Ok(s) = std::str::from_utf8(bytes) {
        let _ = Key::parse(s);
    }
}

fn corrupt(mut bytes: Vec<u8>, edits: &[(usize, u8)], cut: Option<usize>, extra: &[u8]) -> Vec<u8> {
    for &(at, value) in edits {
        if !bytes.is_empty() {
            let i = at % bytes.len();
            bytes[i] = value;
        }
    }
    if let Some(c) = cut {
        bytes.truncate(c % (bytes.len() + 1));
    }
    bytes.extend_from_slice(extra);
    bytes
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(2000))]

    #[test]
    fn arbitrary_bytes(bytes in proptest::collection::vec(any::<u8>(), 0..512)) {
        decode_all(&bytes);
    }

    #[test]
    fn arbitrary_bytes_with_magic(kind in 0u8..4, version in 0u8..3,
                                  rest in proptest::collection::vec(any::<u8>(), 0..512)) {
        let mut bytes = vec![b'T', b'X', kind, version];
        bytes.extend(rest);
        decode_all(&bytes);
    }

    #[test]
    fn corrupted_valid_payloads(n in 1usize..40,
                                edits in proptest::collection::vec((any::<usize>(), any::<u8>()), 0..6),
                                cut in proptest::option::of(any::<usize>()),
                                extra in proptest::collection::vec(any::<u8>(), 0..8)) {
        for valid in [valid_raw(n), valid_corrected(n)] {
            let bytes = corrupt(valid, &edits, cut, &extra);
            decode_all(&bytes);
        }
    }

    #[test]
    fn corrupted_json(edits in proptest::collection::vec((any::<usize>(), any::<u8>()), 1..6),
                      cut in proptest::option::of(any::<usize>())) {
        let json = triax_protocol::to_json(&triax_protocol::record::sample::record("s", 1));
        decode_all(&corrupt(json, &edits, cut, &[]));
    }

    #[test]
    fn valid_batches_round_trip(n in 1usize..200, seq in any::<u64>(), t in any::<i64>(),
                                rate in 0.001f64..1e6) {
        let raw = RawBatch {
            header: BatchHeader { sensor_id: SensorId::new("x").unwrap(), sequence: seq,
                                  timestamp_ns: t, sample_rate_hz: rate },
            temperature_c: None,
            samples: (0..n).map(|i| [i as f32, -(i as f32), 0.5]).collect(),
        };
        prop_assert_eq!(RawBatch::decode(&raw.encode()).unwrap(), raw);
    }
}
