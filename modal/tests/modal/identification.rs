//! SSI-COV on simulated windows of the five-storey building against the frame's exact modes.

use triax_modal::sim::{punch_gaps, SimBuilding};
use triax_modal::{identify, ChannelId, Direction, ModalError, SsiConfig};

use crate::util::{find, summary};

/// A configuration light enough for unoptimised test builds: four references (the roof's and
/// the third floor's two directions) and orders up to 36.
pub(crate) fn light_config() -> SsiConfig {
    let reference = |sensor: &str, direction| ChannelId {
        sensor_id: sensor.into(),
        direction,
    };
    SsiConfig {
        references: vec![
            reference("s5", Direction::X),
            reference("s5", Direction::Y),
            reference("s3", Direction::X),
            reference("s3", Direction::Y),
        ],
        max_order: Some(36),
        ..SsiConfig::default()
    }
}

#[test]
fn first_three_modes_of_each_direction_are_recovered() {
    let building = SimBuilding::five_storey(11);
    let temperature_c = building.frame.reference_temperature_c;
    let window = building.simulate(temperature_c, 1800.0, 0, 3);
    let identification = identify(&building.model, &window, &light_config()).unwrap();
    println!("{}", summary(&building, &identification, temperature_c));
    for direction in [Direction::X, Direction::Y] {
        for truth in building
            .frame
            .direction_modes(direction, temperature_c)
            .iter()
            .take(3)
        {
            let (mode, mac) = find(&building, &identification, truth)
                .unwrap_or_else(|| panic!("{direction:?} mode {} not found", truth.number));
            let error = (mode.frequency_hz.value - truth.frequency_hz).abs() / truth.frequency_hz;
            assert!(
                error <= 0.005,
                "{direction:?} {}: frequency error {error}",
                truth.number
            );
            // The shape's error is what its stated uncertainty says: 1 − MAC is about the sum of
            // the components' variances over the shape's squared norm.
            let expected = crate::util::expected_mac_loss(mode);
            assert!(mac >= 0.95, "{direction:?} {}: MAC {mac}", truth.number);
            assert!(
                1.0 - mac <= 5.0 * expected,
                "{direction:?} {}: MAC {mac}, 1 − MAC expected {expected}",
                truth.number
            );
            assert_eq!(mode.direction, direction);
            assert!(mode.frequency_hz.standard_uncertainty > 0.0);
            assert!(
                (mode.frequency_hz.coverage_factor - 2.201).abs() < 1e-3,
                "t(11, 95 %)"
            );
            let damping_error = (mode.damping_ratio.value - truth.damping_ratio).abs();
            assert!(
                damping_error < 0.006,
                "{direction:?} {}: damping {}",
                truth.number,
                mode.damping_ratio.value
            );
        }
    }
}

#[test]
fn gaps_are_left_out_and_too_many_refuse_the_window() {
    let building = SimBuilding::five_storey(12);
    let temperature_c = building.frame.reference_temperature_c;
    let mut window = building.simulate(temperature_c, 1200.0, 0, 4);
    // 5 % of every sensor's samples flagged, in 2-second runs, their values wild.
    punch_gaps(&mut window, 0.05, 200, 9);
    let identification = identify(&building.model, &window, &light_config()).unwrap();
    assert!(identification
        .valid_fraction
        .iter()
        .all(|&v| v < 0.97 && v > 0.8));
    for direction in [Direction::X, Direction::Y] {
        let truth = &building.frame.direction_modes(direction, temperature_c)[0];
        let (mode, mac) = find(&building, &identification, truth).expect("fundamental found");
        let error = (mode.frequency_hz.value - truth.frequency_hz).abs() / truth.frequency_hz;
        assert!(error <= 0.005, "{direction:?}: frequency error {error}");
        assert!(mac >= 0.95, "{direction:?}: MAC {mac}");
    }
    punch_gaps(&mut window, 0.3, 200, 10);
    match identify(&building.model, &window, &light_config()) {
        Err(ModalError::TooMuchMissing {
            valid_fraction,
            required,
            ..
        }) => {
            assert!(valid_fraction < required)
        }
        other => panic!("expected a refusal, got {:?}", other.map(|i| i.modes.len())),
    }
}

#[test]
fn a_tall_building_is_identified_with_every_setting_at_its_default() {
    // The ten-storey building's 13 modes below 8 Hz, its fundamentals far weaker in
    // acceleration than its higher modes: a diagram to order 40 finds the upper ones only.
    let building = SimBuilding::ten_storey(7);
    let window = building.simulate(20.0, 1800.0, 0, 8);
    let identification = identify(&building.model, &window, &SsiConfig::default()).unwrap();
    assert!(
        identification.warnings.is_empty(),
        "{:?}",
        identification.warnings
    );
    // 25 modes below the decimated Nyquist frequency (12.5 Hz), two singular values each.
    assert!(
        (46..=54).contains(&identification.signal_rank),
        "signal rank {}",
        identification.signal_rank
    );
    assert!(identification.max_order >= 2 * identification.signal_rank);
    let truths: Vec<_> = building
        .plan_modes(20.0)
        .into_iter()
        .filter(|m| m.frequency_hz < 8.0)
        .collect();
    assert_eq!(truths.len(), 13);
    for truth in &truths {
        let (mode, mac) = crate::buildings::find_plan(&building, &identification, truth)
            .unwrap_or_else(|| panic!("{:?}{} not found", truth.kind, truth.number));
        let error = (mode.frequency_hz.value - truth.frequency_hz).abs() / truth.frequency_hz;
        assert!(error < 0.005, "{:?}{}: {error}", truth.kind, truth.number);
        assert!(mac > 0.98, "{:?}{}: MAC {mac}", truth.kind, truth.number);
    }
    // At order 40 the fundamentals are missing, and the window says its diagram had not
    // settled: they appear only in its upper orders, or not at all.
    let forty = SsiConfig {
        max_order: Some(40),
        ..SsiConfig::default()
    };
    let short = identify(&building.model, &window, &forty).unwrap();
    assert!(crate::buildings::find_plan(&building, &short, &truths[0]).is_none());
    assert!(
        matches!(
            short.warnings.as_slice(),
            [triax_modal::IdentificationWarning::NotStabilised { max_order: 40, .. }]
        ),
        "{:?}",
        short.warnings
    );
}

#[test]
fn a_misdeclared_mounting_and_a_late_node_are_named() {
    // The ten-storey building: s07 (floor 6, with s06) turned 10° in plan beyond its declared
    // mounting, s05 tilted 10° (its declared vertical is not the building's), and s03's node
    // one sample late; every other clock exact.
    let mut building = SimBuilding::ten_storey(3);
    let turn = |axis: nalgebra::Vector3<f64>| {
        nalgebra::Rotation3::from_axis_angle(
            &nalgebra::Unit::new_normalize(axis),
            10f64.to_radians(),
        )
        .into_inner()
    };
    building.true_mounting[6] = turn(nalgebra::Vector3::z()) * building.true_mounting[6];
    building.true_mounting[4] = turn(nalgebra::Vector3::x()) * building.true_mounting[4];
    for e in &mut building.errors {
        e.time_offset_s = 0.0;
    }
    building.errors[2].time_offset_s = -1.0 / building.config.sample_rate_hz;
    let window = building.simulate(20.0, 1800.0, 0, 9);
    let id = identify(&building.model, &window, &SsiConfig::default()).unwrap();
    let named: Vec<(&str, &str)> = id
        .checks
        .iter()
        .flat_map(|c| {
            c.findings
                .iter()
                .map(move |f| (c.sensor_id.as_str(), f.as_str()))
        })
        .collect();
    let check = |id_: &str| id.checks.iter().find(|c| c.sensor_id == id_).unwrap();
    let s07 = check("s07").plan_rotation_deg.unwrap();
    assert!(
        s07.covers(10.0) || (s07.value - 10.0).abs() < 0.5,
        "{s07:?}"
    );
    let s05 = check("s05").tilt_deg.unwrap();
    assert!((s05.value - 10.0).abs() < 0.5, "{s05:?}");
    let s03 = check("s03").time_offset_s.unwrap();
    assert!((s03.value + 0.02).abs() < 0.002, "{s03:?}");
    for (sensor, what) in [("s07", "in plan"), ("s05", "tilted"), ("s03", "clock")] {
        assert!(
            named.iter().any(|(s, f)| *s == sensor && f.contains(what)),
            "{sensor} not named for {what}: {named:?}"
        );
    }
    assert_eq!(named.len(), 3, "nothing else named: {named:?}");
    // The healthy sensors' checks are there, and say nothing.
    let s12 = check("s12");
    assert!(s12.plan_rotation_deg.unwrap().value.abs() < 1.0);
    assert!(s12.tilt_deg.unwrap().value < 1.0);
}
