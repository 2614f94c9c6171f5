//! Every key the protocol builds is a canonical Zenoh key expression, and the wildcard
//! subscriptions cover exactly the keys they are meant to.

use proptest::prelude::*;
use triax_protocol::keys::{all_buildings, all_registries, all_sensors, Stream};
use triax_protocol::{BuildingId, Key, SensorId};
use zenoh::key_expr::keyexpr;

fn all_keys(b: &BuildingId, s: &SensorId) -> Vec<Key> {
    vec![
        Key::Raw(b.clone(), s.clone()),
        Key::Corrected(b.clone(), s.clone()),
        Key::Tilt(b.clone(), s.clone()),
        Key::CalibrationPush(b.clone(), s.clone()),
        Key::CalibrationAck(b.clone(), s.clone()),
        Key::CalibrationRegistry(b.clone()),
        Key::Status(b.clone()),
        Key::Alert(b.clone(), s.clone()),
        Key::Modes(b.clone()),
    ]
}

fn ke(s: &str) -> &keyexpr {
    keyexpr::new(s).unwrap_or_else(|e| panic!("{s:?} is not a canonical key expression: {e}"))
}

proptest! {
    #[test]
    fn built_keys_are_canonical_zenoh_key_expressions(
        b in "[A-Za-z0-9_-]{1,64}",
        s in "[A-Za-z0-9_-]{1,64}",
    ) {
        let b = BuildingId::new(b).unwrap();
        let s = SensorId::new(s).unwrap();
        for key in all_keys(&b, &s) {
            let text = key.to_string();
            let k = ke(&text);
            prop_assert!(!k.is_wild(), "{} is wild", text);
            prop_assert_eq!(Key::parse(k.as_str()).unwrap(), key);
        }
        let raw = Key::Raw(b.clone(), s.clone()).to_string();
        prop_assert!(ke(&all_sensors(&b, Stream::Raw)).includes(ke(&raw)));
        prop_assert!(ke(&all_buildings(Stream::Raw)).includes(ke(&raw)));
        prop_assert!(!ke(&all_sensors(&b, Stream::Corrected)).intersects(ke(&raw)));
        let push = Key::CalibrationPush(b.clone(), s.clone()).to_string();
        prop_assert!(ke(&all_sensors(&b, Stream::CalibrationPush)).includes(ke(&push)));
        let registry = Key::CalibrationRegistry(b.clone()).to_string();
        prop_assert!(ke(&all_registries()).includes(ke(&registry)));
    }
}

#[test]
fn one_building_never_sees_another() {
    let a = BuildingId::new("tower-a").unwrap();
    let b = BuildingId::new("tower-b").unwrap();
    let s = SensorId::new("s1").unwrap();
    for stream in [
        Stream::Raw,
        Stream::Corrected,
        Stream::Tilt,
        Stream::CalibrationPush,
        Stream::CalibrationAck,
        Stream::Alert,
    ] {
        let sub = all_sensors(&a, stream);
        for key in all_keys(&b, &s) {
            assert!(
                !ke(&sub).intersects(ke(&key.to_string())),
                "{sub} reaches {key}"
            );
        }
    }
}
