//! Export and import.

use std::fs;

use triax_calibration_store::{export_file_name, FileOutcome, PutOutcome, Rejection};

use crate::util::{id, new_store, record};

#[test]
fn export_then_import_restores_every_version() {
    let (_dir, source) = new_store();
    for (s, n) in [("s1", 3), ("s2", 1)] {
        for v in 1..=n {
            source.put(&record(s, v)).unwrap().unwrap();
        }
    }
    let out = tempfile::tempdir().unwrap();
    let export = source.export(out.path()).unwrap();
    assert!(export.skipped.is_empty());
    let mut names: Vec<String> = fs::read_dir(out.path())
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    names.sort();
    assert_eq!(
        names,
        ["s1.v1.json", "s1.v2.json", "s1.v3.json", "s2.v1.json"]
    );
    assert_eq!(export_file_name(&record("s1", 2)), "s1.v2.json");

    let (_dir, restored) = new_store();
    let report = restored.import(out.path()).unwrap();
    assert!(report.all_accepted());
    assert!(report
        .files
        .iter()
        .all(|f| f.outcome == FileOutcome::Put(PutOutcome::Stored)));
    assert_eq!(
        restored.all_records().unwrap().value,
        source.all_records().unwrap().value
    );

    // Importing the same directory again is idempotent.
    let again = restored.import(out.path()).unwrap();
    assert!(again
        .files
        .iter()
        .all(|f| f.outcome == FileOutcome::Put(PutOutcome::AlreadyStored)));
}

#[test]
fn import_applies_the_put_rules_and_reports_each_file() {
    let dir = tempfile::tempdir().unwrap();
    let write = |name: &str, bytes: &[u8]| fs::write(dir.path().join(name), bytes).unwrap();
    // Names out of version order: the import sorts by content, not by name.
    write("b.json", &triax_protocol::to_json_pretty(&record("s1", 1)));
    write("a.json", &triax_protocol::to_json_pretty(&record("s1", 2)));
    let mut bad = record("s2", 1);
    bad.static_set.coverage_factor = -1.0;
    write("bad-values.json", &triax_protocol::to_json(&bad));
    write("truncated.json", b"{\"format_version\": 1, \"sensor_id\": ");
    let mut newer = serde_json::to_value(record("s3", 1)).unwrap();
    newer["format_version"] = 9.into();
    write("newer.json", &serde_json::to_vec(&newer).unwrap());
    write("notes.txt", b"not a record, ignored");

    let (_store_dir, store) = new_store();
    let mut conflicting = record("s1", 2);
    conflicting.certificate.id = "OTHER".into();
    store.put(&record("s4", 5)).unwrap().unwrap();
    write("stale.json", &triax_protocol::to_json(&record("s4", 4)));
    write("conflict.json", &triax_protocol::to_json(&conflicting));

    let report = store.import(dir.path()).unwrap();
    assert!(!report.all_accepted());
    let by_name = |name: &str| {
        &report
            .files
            .iter()
            .find(|f| f.path.file_name().unwrap() == name)
            .unwrap_or_else(|| panic!("{name} not reported"))
            .outcome
    };
    assert_eq!(report.files.len(), 7, "notes.txt is not a record file");
    assert_eq!(by_name("b.json"), &FileOutcome::Put(PutOutcome::Stored));
    assert_eq!(by_name("a.json"), &FileOutcome::Put(PutOutcome::Stored));
    assert!(matches!(
        by_name("bad-values.json"),
        FileOutcome::Rejected(Rejection::Invalid(_))
    ));
    assert!(
        matches!(by_name("truncated.json"), FileOutcome::Unreadable(m) if m.contains("line")),
        "{:?}",
        by_name("truncated.json")
    );
    assert!(
        matches!(by_name("newer.json"), FileOutcome::Unreadable(m) if m.contains("format_version 9")),
        "{:?}",
        by_name("newer.json")
    );
    assert!(matches!(
        by_name("stale.json"),
        FileOutcome::Rejected(Rejection::Stale { current: 5, .. })
    ));
    // Both a.json and conflict.json hold s1 v2; ties keep file-name order, so a.json is the
    // one stored and conflict.json differs from it.
    assert_eq!(
        by_name("conflict.json"),
        &FileOutcome::Rejected(Rejection::Conflict {
            sensor_id: id("s1"),
            version: 2
        })
    );
    assert_eq!(store.current(&id("s1")).unwrap(), Some(record("s1", 2)));
}
