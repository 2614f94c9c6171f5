//! SSI-COV on simulated windows against the frame's exact modes.

use std::time::Instant;

use triax_modal::sim::SimBuilding;
use triax_modal::{identify, SsiConfig};

use crate::util::find;

#[test]
#[ignore]
fn explore() {
    let building = SimBuilding::five_storey(1);
    let minutes: f64 = std::env::var("MINUTES")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(30.0);
    let t = Instant::now();
    let window = building.simulate(20.0, 60.0 * minutes, 0, 7);
    println!("simulated in {:?}", t.elapsed());
    let rms: f64 = (window.sensors[4]
        .acceleration_mps2
        .iter()
        .map(|a| a[0] * a[0] + a[1] * a[1])
        .sum::<f64>()
        / window.len() as f64)
        .sqrt();
    println!("roof rms {rms} m/s²");
    let t = Instant::now();
    let id = identify(&building.model, &window, &SsiConfig::default()).unwrap();
    println!("identified in {:?}, i = {}", t.elapsed(), id.block_rows);
    for m in &id.modes {
        println!(
            "f {:.4} ± {:.4}  ζ {:.4} ± {:.4} dir {:?} order {} stable {}",
            m.frequency_hz.value,
            m.frequency_hz.standard_uncertainty,
            m.damping_ratio.value,
            m.damping_ratio.standard_uncertainty,
            m.direction,
            m.order,
            m.stable_orders
        );
    }
    println!("unquantified {:?}", id.unquantified);
    for truth in building.frame.modes(20.0) {
        let found = find(&building, &id, &truth);
        println!(
            "truth {:?} {} f {:.4} ζ {:.3} -> {:?}",
            truth.direction,
            truth.number,
            truth.frequency_hz,
            truth.damping_ratio,
            found.map(|(m, mac)| (m.frequency_hz.value, m.damping_ratio.value, mac))
        );
    }
}
