//! Reads: current, in force at a time, history, list, newer-than.

use std::collections::BTreeMap;

use time::{Duration, OffsetDateTime};
use triax_calibration_store::{PutOutcome, SensorVersion};

use crate::util::{id, new_store, record};

#[test]
fn record_in_force_is_the_newest_whose_window_contains_the_time() {
    let (_dir, store) = new_store();
    let t0 = record("s1", 1).valid_from;
    let day = Duration::days(1);

    // v1 open-ended from t0; v2 a bounded window [t0+10d, t0+20d); v3 open-ended from t0+30d.
    store.put(&record("s1", 1)).unwrap().unwrap();
    let mut v2 = record("s1", 2);
    v2.valid_from = t0 + 10 * day;
    v2.valid_until = Some(t0 + 20 * day);
    store.put(&v2).unwrap().unwrap();
    let mut v3 = record("s1", 3);
    v3.valid_from = t0 + 30 * day;
    store.put(&v3).unwrap().unwrap();

    let at = |t: OffsetDateTime| {
        let scan = store.at(&id("s1"), t).unwrap();
        assert!(scan.skipped.is_empty());
        scan.value.map(|r| r.version)
    };
    assert_eq!(at(t0 - Duration::seconds(1)), None);
    assert_eq!(at(t0), Some(1));
    assert_eq!(at(t0 + 10 * day), Some(2));
    assert_eq!(at(t0 + 20 * day - Duration::seconds(1)), Some(2));
    // v2's window is closed at its end; v1's is still open.
    assert_eq!(at(t0 + 20 * day), Some(1));
    assert_eq!(at(t0 + 30 * day), Some(3));
    assert_eq!(at(t0 + 1000 * day), Some(3));
    assert_eq!(store.at(&id("other"), t0).unwrap().value, None);
    // The current record is the highest version, even before its window opens.
    assert_eq!(store.current(&id("s1")).unwrap().unwrap().version, 3);
}

#[test]
fn history_and_list_are_ordered_by_sensor_then_version() {
    let (_dir, store) = new_store();
    // 255 → 256 crosses a byte boundary: little-endian keys would sort 256 first.
    let puts = [
        ("s1", 255),
        ("s10", 1),
        ("a", 7),
        ("s1", 256),
        ("s1a", 2),
        ("s1", 1),
    ];
    for (s, v) in puts {
        let outcome = store.put(&record(s, v)).unwrap();
        // ("s1", 1) comes after 256 and is refused; put it first in another store below.
        if (s, v) == ("s1", 1) {
            assert!(outcome.is_err());
        } else {
            assert_eq!(outcome, Ok(PutOutcome::Stored));
        }
    }
    let history: Vec<u64> = store
        .history(&id("s1"))
        .unwrap()
        .value
        .iter()
        .map(|r| r.version)
        .collect();
    assert_eq!(history, [255, 256]);

    let list = store.list().unwrap();
    assert!(list.skipped.is_empty());
    let sv = |s: &str, version| SensorVersion {
        sensor_id: id(s),
        version,
    };
    assert_eq!(
        list.value,
        [sv("a", 7), sv("s1", 256), sv("s10", 1), sv("s1a", 2)]
    );
    let current: Vec<(String, u64)> = store
        .current_records()
        .unwrap()
        .value
        .iter()
        .map(|r| (r.sensor_id.to_string(), r.version))
        .collect();
    assert_eq!(
        current,
        [
            ("a".into(), 7),
            ("s1".into(), 256),
            ("s10".into(), 1),
            ("s1a".into(), 2)
        ]
    );
    let all: Vec<(String, u64)> = store
        .all_records()
        .unwrap()
        .value
        .iter()
        .map(|r| (r.sensor_id.to_string(), r.version))
        .collect();
    assert_eq!(all.len(), 5);
    assert_eq!(all[1], ("s1".into(), 255));
}

#[test]
fn newer_than_gives_a_catching_up_peer_what_it_lacks() {
    let (_dir, lab) = new_store();
    for (s, n) in [("s1", 3), ("s2", 2), ("s3", 1)] {
        for v in 1..=n {
            lab.put(&record(s, v)).unwrap().unwrap();
        }
    }
    let known = BTreeMap::from([(id("s1"), 1), (id("s2"), 2), (id("s9"), 4)]);
    let newer = lab.newer_than(&known).unwrap();
    assert!(newer.skipped.is_empty());
    let got: Vec<(String, u64)> = newer
        .value
        .iter()
        .map(|r| (r.sensor_id.to_string(), r.version))
        .collect();
    assert_eq!(
        got,
        [("s1".into(), 2), ("s1".into(), 3), ("s3".into(), 1)],
        "s2 is up to date, s9 is unknown to the lab, s3 is unknown to the peer"
    );
    assert_eq!(lab.newer_than(&BTreeMap::new()).unwrap().value.len(), 6);
    assert!(lab
        .newer_than(&BTreeMap::from([(id("s1"), u64::MAX)]))
        .unwrap()
        .value
        .iter()
        .all(|r| r.sensor_id != id("s1")));

    // A peer that puts the answer in order ends up with the lab's current versions.
    let (_dir, gateway) = new_store();
    gateway.put(&record("s1", 1)).unwrap().unwrap();
    gateway.put(&record("s2", 1)).unwrap().unwrap();
    gateway.put(&record("s2", 2)).unwrap().unwrap();
    let outcomes = gateway.put_all(&newer.value).unwrap();
    assert!(outcomes.iter().all(|o| *o == Ok(PutOutcome::Stored)));
    assert_eq!(gateway.list().unwrap().value, lab.list().unwrap().value);
}

/// A suspect mark is per record, the first mark stands, and it survives reopening the store.
#[test]
fn suspect_marks_are_per_record_first_wins_and_durable() {
    let (dir, store) = new_store();
    store.put(&record("s1", 1)).unwrap().unwrap();
    store.put(&record("s1", 2)).unwrap().unwrap();
    assert_eq!(store.suspect_from(&id("s1"), 1).unwrap(), None);
    assert_eq!(store.mark_suspect(&id("s1"), 1, 5_000).unwrap(), 5_000);
    // A later mark of the same record keeps the first time.
    assert_eq!(store.mark_suspect(&id("s1"), 1, 9_000).unwrap(), 5_000);
    assert_eq!(store.mark_suspect(&id("s2"), 7, -3).unwrap(), -3);
    assert_eq!(store.suspect_from(&id("s1"), 1).unwrap(), Some(5_000));
    assert_eq!(
        store.suspect_from(&id("s1"), 2).unwrap(),
        None,
        "another version"
    );
    drop(store);
    let store = triax_calibration_store::Store::open(dir.path()).unwrap();
    let scan = store.suspects().unwrap();
    assert!(scan.skipped.is_empty());
    let marks: Vec<_> = scan
        .value
        .iter()
        .map(|m| (m.sensor_id.clone(), m.version, m.flagged_from_ns))
        .collect();
    assert_eq!(
        marks,
        vec![(id("s1"), 1, 5_000), (id("s2"), 7, -3)],
        "sorted by sensor, then version"
    );
}
