//! Golden byte vectors: any change to the binary or JSON formats shows up here.
//!
//! The vectors in `tests/golden/` are the examples PROTOCOL.md walks through. A failing test
//! means the format changed: bump the format version and document it, never just regenerate.

use triax_protocol::batch::{
    flags, BatchHeader, CorrectedBatch, CorrectedSample, CorrectionInfo, Mode, RawBatch,
};
use triax_protocol::SensorId;

fn hex_file(name: &str) -> Vec<u8> {
    let path = format!("{}/tests/golden/{name}", env!("CARGO_MANIFEST_DIR"));
    let text = std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("{path}: {e}"));
    let digits: String = text
        .lines()
        .map(|l| l.split('#').next().unwrap())
        .flat_map(|l| l.split_whitespace())
        .collect();
    (0..digits.len())
        .step_by(2)
        .map(|i| u8::from_str_radix(&digits[i..i + 2], 16).unwrap())
        .collect()
}

fn header() -> BatchHeader {
    BatchHeader {
        sensor_id: SensorId::new("acc-01").unwrap(),
        sequence: 7,
        timestamp_ns: 1_767_225_600_000_000_000, // 2026-01-01T00:00:00Z
        sample_rate_hz: 100.0,
    }
}

#[test]
fn raw_batch_golden() {
    let batch = RawBatch {
        header: header(),
        temperature_c: Some(21.5),
        samples: vec![[0.25, -0.5, 1.0], [0.0, 2.0, -1.5]],
    };
    let golden = hex_file("raw_batch_v1.hex");
    assert_eq!(batch.encode(), golden, "encoding changed");
    assert_eq!(RawBatch::decode(&golden).unwrap(), batch);
}

#[test]
fn corrected_batch_golden() {
    let batch = CorrectedBatch {
        header: header(),
        batch_flags: flags::SEQUENCE_GAP | flags::OUTSIDE_AMPLITUDE,
        info: CorrectionInfo {
            calibration_version: 3,
            mode: Mode::Dynamic,
            coverage_factor: 2.0,
        },
        samples: vec![
            CorrectedSample {
                accel_mps2: [0.5, -0.25, 9.75],
                uncertainty_mps2: [0.0625, 0.125, 0.25],
                flags: 0,
            },
            CorrectedSample {
                accel_mps2: [24.0, 0.0, 9.75],
                uncertainty_mps2: [0.5, 0.125, 0.25],
                flags: flags::OUTSIDE_AMPLITUDE,
            },
        ],
    };
    let golden = hex_file("corrected_batch_v1.hex");
    assert_eq!(batch.encode(), golden, "encoding changed");
    assert_eq!(CorrectedBatch::decode(&golden).unwrap(), batch);
}

#[test]
fn record_json_golden() {
    let path = format!("{}/tests/golden/record_v1.json", env!("CARGO_MANIFEST_DIR"));
    let text = std::fs::read(&path).unwrap();
    let record: triax_protocol::CalibrationRecord = triax_protocol::from_json(&text).unwrap();
    record.validate().unwrap();
    assert_eq!(record, triax_protocol::record::sample::record("acc-01", 3));
    assert_eq!(
        triax_protocol::to_json_pretty(&record),
        text,
        "JSON layout changed"
    );
}

/// A record that states degrees of freedom (PROTOCOL.md §3.1's worked example): the layout
/// of the optional fields, and what they say.
#[test]
fn record_with_degrees_of_freedom_golden() {
    let path = format!(
        "{}/tests/golden/record_v1_dof.json",
        env!("CARGO_MANIFEST_DIR")
    );
    let text = std::fs::read(&path).unwrap();
    let record: triax_protocol::CalibrationRecord = triax_protocol::from_json(&text).unwrap();
    record.validate().unwrap();
    assert_eq!(record.sensor.output_noise_dof, Some(200.0));
    for set in [&record.static_set, &record.dynamic] {
        assert_eq!(set.covariance_dof, Some(6.0));
        assert_eq!(set.uncertainty_dof, None);
        assert_eq!(set.coverage_probability, Some(0.95));
        assert_eq!(set.coverage_factor, 2.447);
    }
    assert_eq!(
        triax_protocol::to_json_pretty(&record),
        text,
        "JSON layout changed"
    );
    // The same record without the new fields is a valid version-1 record: absent means
    // infinitely many degrees of freedom.
    let mut v: serde_json::Value = serde_json::from_slice(&text).unwrap();
    v["sensor"]
        .as_object_mut()
        .unwrap()
        .remove("output_noise_dof");
    for set in ["static", "dynamic"] {
        let o = v[set].as_object_mut().unwrap();
        o.remove("covariance_dof");
        o.remove("coverage_probability");
    }
    let old: triax_protocol::CalibrationRecord =
        triax_protocol::from_json(&serde_json::to_vec(&v).unwrap()).unwrap();
    old.validate().unwrap();
    assert_eq!(old.static_set.covariance_dof, None);
}

/// The worked examples in PROTOCOL.md are the golden vectors, byte for byte.
#[test]
fn protocol_md_examples_match_golden_vectors() {
    let doc =
        std::fs::read_to_string(format!("{}/../PROTOCOL.md", env!("CARGO_MANIFEST_DIR"))).unwrap();
    let hex_blocks: Vec<Vec<u8>> = doc
        .split("```")
        .skip(1)
        .step_by(2)
        .filter(|block| {
            !block.trim().is_empty()
                && block
                    .split_whitespace()
                    .all(|w| w.len() == 2 && u8::from_str_radix(w, 16).is_ok())
        })
        .map(|block| {
            block
                .split_whitespace()
                .map(|w| u8::from_str_radix(w, 16).unwrap())
                .collect()
        })
        .collect();
    assert_eq!(hex_blocks.len(), 2, "PROTOCOL.md has two hex examples");
    assert_eq!(hex_blocks[0], hex_file("raw_batch_v1.hex"));
    assert_eq!(hex_blocks[1], hex_file("corrected_batch_v1.hex"));
}
