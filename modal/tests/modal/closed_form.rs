//! Hand-computed checks.

use nalgebra::{Complex, Matrix3};
use triax_modal::model::{rotation_about_z, ModelError};
use triax_modal::sim::ShearFrame;
use triax_modal::uncertainty::{chain_variances, jackknife_variance};
use triax_modal::window::{ChannelOptions, Channels};
use triax_modal::{
    BuildingModel, ChainUncertainty, Direction, SensorPlacement, SensorSeries, Window,
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
