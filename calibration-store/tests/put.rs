//! Validation and the version rules of `put`.

use triax_calibration::corrector::LoadError;
use triax_calibration_store::{PutOutcome, Rejection, Store};

use crate::util::{id, new_store, record};

#[test]
fn versions_only_go_up_and_retries_are_idempotent() {
    let (_dir, store) = new_store();
    assert_eq!(store.put(&record("s1", 1)).unwrap(), Ok(PutOutcome::Stored));
    assert_eq!(store.put(&record("s1", 3)).unwrap(), Ok(PutOutcome::Stored));

    // A retry of the current version, and of an older stored one, changes nothing.
    assert_eq!(
        store.put(&record("s1", 3)).unwrap(),
        Ok(PutOutcome::AlreadyStored)
    );
    assert_eq!(
        store.put(&record("s1", 1)).unwrap(),
        Ok(PutOutcome::AlreadyStored)
    );

    // An older version never stored: a replay or a rollback.
    let e = store.put(&record("s1", 2)).unwrap().unwrap_err();
    assert_eq!(
        e,
        Rejection::Stale {
            sensor_id: id("s1"),
            version: 2,
            current: 3
        }
    );
    assert!(
        e.to_string().contains("older than the current version 3"),
        "{e}"
    );

    // Same version, other content.
    let mut changed = record("s1", 3);
    changed.dynamic.offset[2] = 0.5;
    let e = store.put(&changed).unwrap().unwrap_err();
    assert_eq!(
        e,
        Rejection::Conflict {
            sensor_id: id("s1"),
            version: 3
        }
    );
    assert!(e.to_string().contains("different content"), "{e}");

    assert_eq!(store.current(&id("s1")).unwrap(), Some(record("s1", 3)));
    let versions: Vec<u64> = store
        .history(&id("s1"))
        .unwrap()
        .value
        .iter()
        .map(|r| r.version)
        .collect();
    assert_eq!(versions, [1, 3]);
}

#[test]
fn invalid_records_are_refused_with_the_reason_and_not_written() {
    let (_dir, store) = new_store();

    let mut non_finite = record("s1", 1);
    non_finite.dynamic.sensitivity[1][2] = f64::NAN;
    match store.put(&non_finite).unwrap() {
        Err(Rejection::Invalid(LoadError::Invalid(e))) => {
            assert_eq!(e.field, "dynamic.sensitivity[1][2]")
        }
        other => panic!("{other:?}"),
    }

    let mut singular = record("s1", 1);
    singular.static_set.sensitivity = [[0.1, 0.0, 0.0], [0.1, 0.0, 0.0], [0.0, 0.0, 0.1]];
    let e = store.put(&singular).unwrap().unwrap_err();
    assert!(
        matches!(
            e,
            Rejection::Invalid(LoadError::IllConditioned { set: "static", .. })
        ),
        "{e:?}"
    );
    assert!(e.to_string().contains("near-singular"), "{e}");

    let mut not_psd = record("s1", 1);
    let mut cov = [[0.0; 12]; 12];
    cov[0][0] = 1.0;
    cov[1][1] = 1.0;
    cov[0][1] = 2.0;
    cov[1][0] = 2.0;
    not_psd.dynamic.covariance = Some(Box::new(cov));
    let e = store.put(&not_psd).unwrap().unwrap_err();
    assert!(
        matches!(
            e,
            Rejection::Invalid(LoadError::CovarianceNotPositive { .. })
        ),
        "{e:?}"
    );

    assert_eq!(store.current(&id("s1")).unwrap(), None);
    assert!(store.list().unwrap().value.is_empty());
    assert!(store.check().unwrap().is_empty());
}

#[test]
fn records_survive_reopening() {
    let dir = tempfile::tempdir().unwrap();
    {
        let store = Store::open(dir.path()).unwrap();
        for v in 1..=3 {
            store.put(&record("s1", v)).unwrap().unwrap();
        }
        let outcomes = store
            .put_all(&[record("s2", 1), record("s2", 2), record("s2", 1)])
            .unwrap();
        assert_eq!(
            outcomes,
            [
                Ok(PutOutcome::Stored),
                Ok(PutOutcome::Stored),
                Ok(PutOutcome::AlreadyStored)
            ]
        );
    }
    let store = Store::open(dir.path()).unwrap();
    assert_eq!(store.current(&id("s1")).unwrap(), Some(record("s1", 3)));
    assert_eq!(store.get(&id("s1"), 2).unwrap(), Some(record("s1", 2)));
    assert_eq!(store.current(&id("s2")).unwrap(), Some(record("s2", 2)));
    assert!(store.check().unwrap().is_empty());
}
