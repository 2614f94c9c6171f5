//! Hand-computed checks.

use nalgebra::{Complex, Matrix3};
use triax_modal::model::{rotation_about_z, ModelError};
use triax_modal::sim::{
    seven_storey_model, ten_storey_model, ModeKind, PlanFrame, PlanMode, ShearFrame, SimBuilding,
    SimConfig, Structure,
};
use triax_modal::uncertainty::{chain_variances, jackknife_variance};
use triax_modal::window::{ChannelOptions, Channels};
use triax_modal::{
    BuildingModel, ChainUncertainty, ChannelId, Direction, SensorPlacement, SensorSeries, Window,
};

#[test]
fn two_storey_modes_are_the_closed_form() {
    // m₁ = m₂ = m, k₁ = k₂ = k: ω² = (k/m)·(3 ∓ √5)/2, shapes (1, (1 ± √5)/2).
    let m = 2.0e5;
    let k = 3.0e7;
    let frame = ShearFrame {
        floor_mass_kg: vec![m, m],
        storey_stiffness_x_n_per_m: vec![k, k],
        stiffness_ratio_y: 1.1,
        damping_ratio: vec![0.02, 0.03],
        frequency_change_per_c: 0.0,
        reference_temperature_c: 20.0,
        damage: Vec::new(),
    };
    let modes = frame.direction_modes(Direction::X, 20.0);
    let sqrt5 = 5.0f64.sqrt();
    for (mode, (sign, ratio)) in modes
        .iter()
        .zip([(-1.0, (1.0 + sqrt5) / 2.0), (1.0, (1.0 - sqrt5) / 2.0)])
    {
        let omega = (k / m * (3.0 + sign * sqrt5) / 2.0).sqrt();
        let f = omega / (2.0 * std::f64::consts::PI);
        assert!(
            (mode.frequency_hz - f).abs() < 1e-9 * f,
            "{} vs {f}",
            mode.frequency_hz
        );
        let shape_ratio = mode.floor_shape[1] / mode.floor_shape[0];
        assert!(
            (shape_ratio - ratio).abs() < 1e-9,
            "{shape_ratio} vs {ratio}"
        );
        // Mass-normalised: φᵀMφ = 1.
        let norm: f64 = mode.floor_shape.iter().map(|v| m * v * v).sum();
        assert!((norm - 1.0).abs() < 1e-9);
    }
    // y is 10 % stiffer: every frequency √1.1 higher.
    let y = frame.direction_modes(Direction::Y, 20.0);
    assert!((y[0].frequency_hz / modes[0].frequency_hz - 1.1f64.sqrt()).abs() < 1e-12);
}

#[test]
fn uniform_frame_matches_its_formula_and_temperature_moves_it_as_stated() {
    let mut frame = ShearFrame::uniform(6, 1.2, 1.0, 0.02);
    frame.frequency_change_per_c = -0.0015;
    let modes = frame.direction_modes(Direction::X, frame.reference_temperature_c);
    for (j, mode) in modes.iter().enumerate() {
        // ω_j = 2·√(k/m)·sin((2j−1)π / (2(2n+1))).
        let ratio = ((2 * j + 1) as f64 * std::f64::consts::PI / 26.0).sin()
            / (std::f64::consts::PI / 26.0).sin();
        assert!((mode.frequency_hz - 1.2 * ratio).abs() < 1e-9, "mode {j}");
    }
    let warm = frame.direction_modes(Direction::X, frame.reference_temperature_c + 10.0);
    assert!((warm[0].frequency_hz / modes[0].frequency_hz - 0.985).abs() < 1e-12);
}

#[test]
fn the_model_is_read_from_toml_and_every_mistake_named() {
    let text = r#"
        building_id = "b1"
        [[sensors]]
        sensor_id = "roof"
        floor = 5
        height_m = 17.5
        position_m = [3.0, 4.0]
        mounting = [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]
    "#;
    let model: BuildingModel = toml::from_str(text).unwrap();
    model.validate().unwrap();
    let json = r#"{"building_id":"b1","sensors":[{"sensor_id":"a","floor":1,"height_m":3.0,
        "mounting":[[1,0,0],[0,1,0],[0,0,1]]}]}"#;
    let from_json: BuildingModel = serde_json::from_str(json).unwrap();
    from_json.validate().unwrap();

    let sensor = |id: &str, mounting| SensorPlacement {
        sensor_id: id.to_string(),
        floor: 1,
        height_m: 3.0,
        position_m: [0.0, 0.0],
        mounting,
    };
    let mirror = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, -1.0]];
    match BuildingModel::new("b", vec![sensor("a", mirror)]) {
        Err(ModelError::NotRotation { sensor_id, .. }) => assert_eq!(sensor_id, "a"),
        other => panic!("{other:?}"),
    }
    let sheared = [[1.0, 0.1, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
    let err = BuildingModel::new("b", vec![sensor("s", sheared)]).unwrap_err();
    assert!(err.to_string().contains("sensor s: mounting"), "{err}");
    let twice = vec![
        sensor("a", rotation_about_z(0.1)),
        sensor("a", rotation_about_z(0.2)),
    ];
    assert!(matches!(
        BuildingModel::new("b", twice),
        Err(ModelError::DuplicateSensor { .. })
    ));
    let mut high = sensor("h", rotation_about_z(0.0));
    high.height_m = f64::NAN;
    assert_eq!(
        BuildingModel::new("b", vec![high]).unwrap_err(),
        ModelError::NotFinite {
            sensor_id: "h".into(),
            field: "height_m"
        }
    );
}

/// Two sensors, the second turned by 90°: its x channel is its −y axis... (see below).
fn two_sensor_channels(chain: ChainUncertainty) -> Channels {
    let sensors = vec![
        SensorPlacement {
            sensor_id: "a".into(),
            floor: 1,
            height_m: 3.0,
            position_m: [0.0, 0.0],
            mounting: rotation_about_z(0.0),
        },
        SensorPlacement {
            sensor_id: "b".into(),
            floor: 2,
            height_m: 6.0,
            position_m: [0.0, 0.0],
            mounting: rotation_about_z(std::f64::consts::FRAC_PI_2),
        },
    ];
    let model = BuildingModel::new("b", sensors).unwrap();
    let n = 4000;
    let series = |id: &str| SensorSeries {
        sensor_id: id.into(),
        acceleration_mps2: (0..n)
            .map(|i| [(i as f64 * 0.3).sin(), (i as f64 * 0.7).cos(), 0.0])
            .collect(),
        valid: vec![true; n],
        chain,
    };
    let window = Window {
        start_timestamp_ns: 0,
        sample_rate_hz: 100.0,
        sensors: vec![series("a"), series("b")],
    };
    let options = ChannelOptions {
        directions: vec![Direction::X],
        ..ChannelOptions::default()
    };
    Channels::from_window(&model, &window, &options).unwrap()
}

#[test]
fn chain_terms_are_the_first_order_formulas() {
    // Shape (1, 2) on the x channels of a (reference) and b. A gain error on b's axis that
    // carries building x moves component b by 2·u_g; one on a's moves every ratio to a:
    // b/a by 2·u_g as well. In quadrature: var_b = 2·(2·u_g)².
    let u_g = 0.004;
    let chain = ChainUncertainty {
        gain_relative_u: [u_g; 3],
        cross_axis_u: 0.0,
        dof: 30.0,
        timestamp_u_s: 0.0,
    };
    let channels = two_sensor_channels(chain);
    let shape = [Complex::new(1.0, 0.0), Complex::new(2.0, 0.0)];
    let v = chain_variances(&channels, &shape, 0, 1.0);
    assert_eq!(v[0].0, 0.0, "the reference component is 1 by definition");
    let expected = 2.0 * (2.0 * u_g).powi(2);
    assert!(
        (v[1].0 / expected - 1.0).abs() < 0.02,
        "{} vs {expected}",
        v[1].0
    );
    assert!(
        v[1].1 < 1e-3 * expected,
        "a gain error does not turn the phase"
    );
    assert_eq!(v[1].2, 30.0);

    // A time-stamp error of σ_t on each node turns b/a by 2π·f·σ_t·√2 in quadrature.
    let sigma_t = 0.002;
    let f = 3.0;
    let chain = ChainUncertainty {
        gain_relative_u: [0.0; 3],
        cross_axis_u: 0.0,
        dof: f64::INFINITY,
        timestamp_u_s: sigma_t,
    };
    let channels = two_sensor_channels(chain);
    let v = chain_variances(&channels, &shape, 0, f);
    let phase = 2.0 * std::f64::consts::PI * f * sigma_t;
    let expected_im = 2.0 * (2.0 * phase).powi(2);
    assert!(
        (v[1].1 / expected_im - 1.0).abs() < 0.01,
        "{} vs {expected_im}",
        v[1].1
    );

    // Cross-axis: b is turned by 90°, so building x is its −y axis; the x axis's cross term
    // from y moves nothing in x, y's from x and z (zero motion) nothing; the z axis's from y
    // moves the vertical, which is no channel. Only the y axis's own gain moves x: zero here.
    let chain = ChainUncertainty {
        gain_relative_u: [0.0; 3],
        cross_axis_u: 0.01,
        dof: 10.0,
        timestamp_u_s: 0.0,
    };
    let channels = two_sensor_channels(chain);
    let v = chain_variances(&channels, &shape, 0, f);
    assert!(v[1].0 < 1e-12, "{}", v[1].0);
    let r: Matrix3<f64> = channels.rotations[1];
    assert!((r[(0, 1)] + 1.0).abs() < 1e-12);
}

#[test]
fn jackknife_variance_of_a_mean_is_the_variance_of_the_mean() {
    // For the mean, the delete-one replicates are (n·x̄ − x_j)/(n−1); their jackknife variance
    // is s²/n exactly.
    let x: Vec<f64> = (0..12).map(|i| ((i * 7919) % 13) as f64 * 0.37).collect();
    let n = x.len() as f64;
    let mean = x.iter().sum::<f64>() / n;
    let s2 = x.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / (n - 1.0);
    let replicates: Vec<f64> = x.iter().map(|v| (n * mean - v) / (n - 1.0)).collect();
    assert!((jackknife_variance(&replicates) / (s2 / n) - 1.0).abs() < 1e-12);
}

#[test]
fn one_eccentric_storey_couples_sway_and_torsion_as_its_quadratic_says() {
    // Centre of stiffness e_x off the centre of mass: x stays alone; y and θ solve
    // det([k_y − ω²m, k_y·e_x; k_y·e_x, k_θ + k_y·e_x² − ω²J]) = 0, a quadratic in ω².
    let (m, j) = (4.0e5, 4.0e5 * 150.0);
    let (kx, ky, kt, ex) = (2.0e7, 3.0e7, 3.0e9, 2.0);
    let frame = PlanFrame {
        floor_mass_kg: vec![m],
        floor_inertia_kg_m2: vec![j],
        centre_of_mass_m: [10.0, 5.0],
        storey_stiffness_x_n_per_m: vec![kx],
        storey_stiffness_y_n_per_m: vec![ky],
        storey_stiffness_torsion_n_m_per_rad: vec![kt],
        eccentricity_m: [ex, 0.0],
        damping_ratio: vec![0.02],
        frequency_change_per_c: 0.0,
        reference_temperature_c: 20.0,
        damage: Vec::new(),
        torque_arm_m: 12.0,
    };
    let modes = frame.plan_modes(20.0);
    let two_pi = 2.0 * std::f64::consts::PI;
    let x = modes.iter().find(|m| m.kind == ModeKind::X).unwrap();
    assert!((x.frequency_hz - (kx / m).sqrt() / two_pi).abs() < 1e-9);
    assert_eq!((x.floor_motion[0][1], x.floor_motion[0][2]), (0.0, 0.0));
    let (a, b, c) = (
        m * j,
        -(m * (kt + ky * ex * ex) + j * ky),
        ky * (kt + ky * ex * ex) - (ky * ex).powi(2),
    );
    let disc = (b * b - 4.0 * a * c).sqrt();
    let mut expected = [(-b - disc) / (2.0 * a), (-b + disc) / (2.0 * a)];
    expected.sort_by(f64::total_cmp);
    let mut coupled: Vec<&PlanMode> = modes.iter().filter(|m| m.kind != ModeKind::X).collect();
    coupled.sort_by(|p, q| p.frequency_hz.total_cmp(&q.frequency_hz));
    for (mode, w2) in coupled.iter().zip(expected) {
        let f = w2.sqrt() / two_pi;
        assert!(
            (mode.frequency_hz - f).abs() < 1e-9 * f,
            "{} vs {f}",
            mode.frequency_hz
        );
        let [_, y, theta] = mode.floor_motion[0];
        // (k_y − ω²m)·y + k_y·e_x·θ = 0, and mass-normalised.
        assert!(((ky - w2 * m) * y + ky * ex * theta).abs() < 1e-6 * ky * y.abs().max(1e-9));
        assert!((m * y * y + j * theta * theta - 1.0).abs() < 1e-9);
    }
    // A sensor 4 m along y from the centre of mass sees x − θ·4 in x.
    let model = BuildingModel::new(
        "one",
        vec![SensorPlacement {
            sensor_id: "a".into(),
            floor: 1,
            height_m: 3.0,
            position_m: [14.0, 9.0],
            mounting: rotation_about_z(0.0),
        }],
    )
    .unwrap();
    let building = SimBuilding::new(frame, model, SimConfig::default(), 1);
    let channels = [Direction::X, Direction::Y].map(|direction| ChannelId {
        sensor_id: "a".into(),
        direction,
    });
    let shape = building.plan_shape(coupled[0], &channels);
    let [x0, y0, t0] = coupled[0].floor_motion[0];
    assert!((shape[0] - (x0 - 4.0 * t0)).abs() < 1e-15);
    assert!((shape[1] - (y0 + 4.0 * t0)).abs() < 1e-15);
}

#[test]
fn the_tuned_buildings_have_their_stated_modes() {
    let (ten, model) = ten_storey_model();
    assert_eq!(model.sensors.len(), 12);
    let modes = ten.plan_modes(20.0);
    let first = |kind| modes.iter().find(|m| m.kind == kind).unwrap().frequency_hz;
    for (kind, f) in [
        (ModeKind::X, 0.85),
        (ModeKind::Y, 0.90),
        (ModeKind::Torsion, 1.25),
    ] {
        assert!((first(kind) - f).abs() < 1e-8, "{kind:?}: {}", first(kind));
    }
    assert_eq!(modes.iter().filter(|m| m.frequency_hz < 8.0).count(), 13);
    // Eccentric: the torsional fundamental sways too, and the sway modes turn.
    let t1 = modes.iter().find(|m| m.kind == ModeKind::Torsion).unwrap();
    assert!(t1.floor_motion[9][0].abs() > 1e-6 && t1.floor_motion[9][1].abs() > 1e-6);
    let (seven, _) = seven_storey_model();
    assert_eq!(
        seven
            .plan_modes(20.0)
            .iter()
            .filter(|m| m.frequency_hz < 8.0)
            .count(),
        9
    );
    // No eccentricity: the sway modes are the shear frame's.
    let mut square = PlanFrame::tuned(5, 5.0e5, [20.0, 20.0], [1.0, 1.03, 1.6], [0.0, 0.0], 0.02);
    square.frequency_change_per_c = -0.0015;
    let shear = ShearFrame::uniform(5, 1.0, 1.0, 0.02);
    let xs: Vec<f64> = square
        .plan_modes(20.0)
        .iter()
        .filter(|m| m.kind == ModeKind::X)
        .map(|m| m.frequency_hz)
        .collect();
    for (a, b) in xs.iter().zip(shear.direction_modes(Direction::X, 20.0)) {
        assert!(
            (a - b.frequency_hz).abs() < 1e-9,
            "{a} vs {}",
            b.frequency_hz
        );
    }
    let warm = square.plan_modes(30.0);
    assert!((warm[0].frequency_hz / 1.0 - 0.985).abs() < 1e-9);
}

#[test]
fn a_late_node_a_misdeclared_mounting_and_gravity_are_rendered_as_stated() {
    // Two sensors at one point of the roof, perfect and noiseless; the second's stamps are one
    // period late, so its sample m is the first's sample m − 1; the third is turned 30° more
    // than declared.
    let (frame, mut model) = ten_storey_model();
    model.sensors.truncate(3);
    for s in &mut model.sensors {
        s.floor = 10;
        s.position_m = [3.0, 3.0];
    }
    let config = SimConfig {
        sample_rate_hz: 50.0,
        noise_std_mps2: 0.0,
        chain: ChainUncertainty::NONE,
        gravity_mps2: triax_modal::sim::STANDARD_GRAVITY_MPS2,
        ..SimConfig::default()
    };
    let mut building = SimBuilding::new(frame, model, config, 1);
    for e in &mut building.errors {
        e.time_offset_s = 0.0;
    }
    building.errors[1].time_offset_s = -1.0 / 50.0;
    let declared = building.model.sensors[2].rotation();
    building.true_mounting[0] = Matrix3::identity();
    building.model.sensors[0].mounting = rotation_about_z(0.0);
    building.model.sensors[1].mounting = rotation_about_z(0.0);
    building.true_mounting[1] = Matrix3::identity();
    let turn = Matrix3::from_row_slice(&rotation_about_z(30f64.to_radians()).concat());
    building.true_mounting[2] = turn * declared;
    let window = building.simulate(20.0, 20.0, 0, 4);
    let (a, late, turned) = (
        &window.sensors[0].acceleration_mps2,
        &window.sensors[1].acceleration_mps2,
        &window.sensors[2].acceleration_mps2,
    );
    for m in 1..a.len() {
        for axis in 0..3 {
            assert!((late[m][axis] - a[m - 1][axis]).abs() < 1e-12, "sample {m}");
        }
        // Gravity along every sensor's z (they turn about the vertical only).
        assert!((a[m][2] - 9.80665).abs() < 1e-12);
        // The turned sensor reads the first's building-frame motion through its true mounting.
        let building_frame = nalgebra::Vector3::new(a[m][0], a[m][1], a[m][2]);
        let expected = building.true_mounting[2].transpose() * building_frame;
        for axis in 0..3 {
            assert!((turned[m][axis] - expected[axis]).abs() < 1e-12);
        }
    }
}
