//! What the store does with a store it cannot fully trust: newer schema, corrupt entries, a
//! second process.

use triax_calibration_store::{PutOutcome, Store, StoreError, SCHEMA_VERSION};

use crate::util::{id, raw_record_key, record, write_raw};

#[test]
fn a_store_from_a_newer_schema_is_refused_with_a_clear_message() {
    let dir = tempfile::tempdir().unwrap();
    drop(Store::open(dir.path()).unwrap());
    write_raw(
        dir.path(),
        "meta",
        b"schema_version",
        &(SCHEMA_VERSION + 1).to_be_bytes(),
    );
    let e = Store::open(dir.path()).unwrap_err();
    assert!(
        matches!(e, StoreError::NewerSchema { found, supported, .. }
            if found == SCHEMA_VERSION + 1 && supported == SCHEMA_VERSION),
        "{e:?}"
    );
    let message = e.to_string();
    assert!(message.contains("schema version 2"), "{message}");
    assert!(message.contains("newer Triax"), "{message}");
    assert!(
        message.contains(&dir.path().display().to_string()),
        "{message}"
    );
}

#[test]
fn records_without_a_schema_version_are_not_a_store() {
    let dir = tempfile::tempdir().unwrap();
    write_raw(dir.path(), "records", b"x", b"y");
    let e = Store::open(dir.path()).unwrap_err();
    assert!(matches!(e, StoreError::NotAStore { .. }), "{e:?}");

    let dir = tempfile::tempdir().unwrap();
    write_raw(dir.path(), "meta", b"schema_version", b"\x01");
    let e = Store::open(dir.path()).unwrap_err();
    assert!(e.to_string().contains("schema version is 1 bytes"), "{e}");
}

#[test]
fn corrupt_entries_are_reported_by_key_and_skipped() {
    let dir = tempfile::tempdir().unwrap();
    {
        let store = Store::open(dir.path()).unwrap();
        for (s, v) in [("s1", 1), ("s1", 2), ("s2", 1), ("s3", 1)] {
            store.put(&record(s, v)).unwrap().unwrap();
        }
    }
    // s1 v2: bytes that are not JSON. s2: an index value of the wrong length. s3 v1: the
    // record of another sensor under s3's key. A key that is not a record key at all.
    write_raw(
        dir.path(),
        "records",
        &raw_record_key("s1", 2),
        b"{\"format_ver",
    );
    write_raw(dir.path(), "current", b"s2", b"\x01\x02\x03");
    let other = triax_protocol::to_json(&record("s2", 1));
    write_raw(dir.path(), "records", &raw_record_key("s3", 1), &other);
    write_raw(dir.path(), "records", b"\xff\xfe", b"junk");

    let store = Store::open(dir.path()).unwrap();

    // The sensor whose index entry is damaged is still listed, from its records.
    let list = store.list().unwrap();
    let listed: Vec<(String, u64)> = list
        .value
        .iter()
        .map(|sv| (sv.sensor_id.to_string(), sv.version))
        .collect();
    assert_eq!(
        listed,
        [("s1".into(), 2), ("s2".into(), 1), ("s3".into(), 1)]
    );
    assert_eq!(list.skipped.len(), 1);
    assert_eq!(list.skipped[0].tree, "current");
    assert_eq!(list.skipped[0].key, "s2");
    assert_eq!(store.current(&id("s2")).unwrap(), Some(record("s2", 1)));

    // Asking for the corrupt current record itself is an error naming the key, not an older
    // version in its place.
    match store.current(&id("s1")) {
        Err(StoreError::Corrupt(entry)) => {
            assert_eq!((entry.tree, entry.key.as_str()), ("records", "s1 v2"));
            assert!(entry.to_string().contains("at key s1 v2"), "{entry}");
        }
        other => panic!("{other:?}"),
    }
    let history = store.history(&id("s1")).unwrap();
    assert_eq!(history.value, [record("s1", 1)]);
    assert_eq!(history.skipped.len(), 1);
    assert_eq!(history.skipped[0].key, "s1 v2");
    let at = store.at(&id("s1"), record("s1", 1).valid_from).unwrap();
    assert_eq!(at.value, Some(record("s1", 1)));
    assert_eq!(at.skipped.len(), 1);

    let current = store.current_records().unwrap();
    assert_eq!(current.value, [record("s2", 1)]);
    let keys: Vec<&str> = current.skipped.iter().map(|e| e.key.as_str()).collect();
    assert_eq!(keys, ["s2", "s1 v2", "s3 v1"]);
    assert!(current.skipped[2].problem.contains("sensor s2 version 1"));

    let problems = store.check().unwrap();
    let keys: Vec<&str> = problems.iter().map(|e| e.key.as_str()).collect();
    assert_eq!(
        keys,
        ["s1 v2", "s3 v1", "\\xff\\xfe", "s2"],
        "{problems:#?}"
    );

    // Putting the valid record again repairs the entry; a new version still goes on top.
    assert_eq!(
        store.put(&record("s1", 2)).unwrap(),
        Ok(PutOutcome::Repaired)
    );
    assert_eq!(store.current(&id("s1")).unwrap(), Some(record("s1", 2)));
    assert_eq!(store.put(&record("s2", 2)).unwrap(), Ok(PutOutcome::Stored));
    assert_eq!(store.put(&record("s1", 3)).unwrap(), Ok(PutOutcome::Stored));
}

#[test]
fn a_second_opener_is_told_the_store_is_in_use() {
    let dir = tempfile::tempdir().unwrap();
    let _first = Store::open(dir.path()).unwrap();
    let e = Store::open(dir.path()).unwrap_err();
    assert!(matches!(e, StoreError::Locked { .. }), "{e:?}");
    assert!(e.to_string().contains("in use by another process"), "{e}");
}

#[test]
fn load_current_gives_every_sensor_a_corrector_and_skips_the_corrupt_one() {
    let dir = tempfile::tempdir().unwrap();
    let sensors: Vec<String> = (0..600).map(|i| format!("s{i:04}")).collect();
    {
        let store = Store::open(dir.path()).unwrap();
        let records: Vec<_> = sensors.iter().map(|s| record(s, 1)).collect();
        assert!(store.put_all(&records).unwrap().iter().all(|o| o.is_ok()));
        store.put(&record("s0300", 2)).unwrap().unwrap();
    }
    write_raw(dir.path(), "records", &raw_record_key("s0450", 1), b"\x00");
    let store = Store::open(dir.path()).unwrap();

    // Enough sensors to take the multi-threaded path; order must survive it.
    let loaded = store.load_current().unwrap();
    let got: Vec<(String, u64)> = loaded
        .value
        .iter()
        .map(|l| (l.sensor_id.to_string(), l.version))
        .collect();
    let expected: Vec<(String, u64)> = sensors
        .iter()
        .filter(|s| *s != "s0450")
        .map(|s| (s.clone(), if s == "s0300" { 2 } else { 1 }))
        .collect();
    assert_eq!(got, expected);
    assert!(loaded.value.iter().all(|l| l.corrector.is_ok()));
    assert_eq!(loaded.skipped.len(), 1);
    assert_eq!(loaded.skipped[0].key, "s0450 v1");
    assert_eq!(store.current_records().unwrap().value.len(), 599);
}
