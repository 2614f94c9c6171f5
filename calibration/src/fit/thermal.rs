//! First-order temperature coefficients from static runs at two or more temperatures.
//!
//! A run is the rows within 0.5 °C of its coolest row. Every run must visit the same arm
//! positions (the same reference vectors): the arm's angle error belongs to a position, so it
//! is common to all runs and cancels when a position is compared with itself across
//! temperatures, where fitting each run on its own would leave it in every run's offset.
//!
//! Model, per output channel k: `V(T) = (1 + c_g·ΔT)·S·(a − q − c_q·ΔT)`, so to first order
//! `V_pk(T) = m_pk + ΔT·(c_g,k·m_pk − d_k)` with `m_pk` the position's output at the reference
//! temperature and `d = S·c_q`. Subtracting each position's mean over the runs (`ȳ_p`, which
//! also stands in for `m_pk` in the small product term) leaves a linear least-squares problem
//! in `(c_g,k, d_k)` with regressors `(ΔT_g − ΔT̄)·ȳ_p` and `−(ΔT_g − ΔT̄)`, and
//! `P·(G − 1) − 2` residual degrees of freedom for P positions and G runs. Its covariance is the
//! residual variance times `(XᵀX)⁻¹`; the channels' noises are independent, and
//! `c_q = S⁻¹·d` maps them to the offsets with the reference run's S.
//!
//! The static set the record carries is the reference run's own fit: the run with the most
//! rows, the nearest to the mean temperature among equals; its temperature is the model's
//! reference. The model is first order, and the residuals would show a curvature with three or
//! more runs as a larger residual variance, hence a larger uncertainty, not as a bias that goes
//! unstated.

use nalgebra::{Matrix2, Matrix3, Vector2, Vector3};
use triax_protocol::record::TemperatureModel;

use super::static_fit::{fit_static_with, ArmAngleUncertainty, StaticFit, StaticObservation};
use super::FitError;

/// Rows within this many °C of a run's coolest row belong to that run.
pub const RUN_TOLERANCE_C: f64 = 0.5;

/// One run of the static bench at one temperature.
#[derive(Debug, Clone)]
pub struct TemperatureRun {
    /// Mean temperature of the run's rows, °C.
    pub temperature_c: f64,
    /// Indices of the run's rows in the input.
    pub rows: Vec<usize>,
}

/// Runs, the reference run's static fit and the temperature model fitted across them.
#[derive(Debug, Clone)]
pub struct ThermalFit {
    /// In order of temperature.
    pub runs: Vec<TemperatureRun>,
    /// The run whose fit is the record's static set.
    pub reference: usize,
    pub reference_fit: StaticFit,
    /// `None` with a single run: nothing to regress.
    pub model: Option<TemperatureModel>,
}

/// Splits the rows into runs by temperature, fits the reference run, and the coefficients
/// across all of them.
pub fn fit_thermal(
    observations: &[StaticObservation],
    temperatures_c: &[f64],
    arm: Option<ArmAngleUncertainty>,
) -> Result<ThermalFit, FitError> {
    debug_assert_eq!(observations.len(), temperatures_c.len());
    if let Some(index) = temperatures_c.iter().position(|t| !t.is_finite()) {
        return Err(FitError::NonFinite {
            what: "temperature of orientation",
            index,
        });
    }
    let mut order: Vec<usize> = (0..temperatures_c.len()).collect();
    order.sort_by(|&a, &b| temperatures_c[a].total_cmp(&temperatures_c[b]));
    let mut groups: Vec<Vec<usize>> = Vec::new();
    for i in order {
        match groups.last_mut() {
            Some(g) if temperatures_c[i] - temperatures_c[g[0]] <= RUN_TOLERANCE_C => g.push(i),
            _ => groups.push(vec![i]),
        }
    }
    let runs: Vec<TemperatureRun> = groups
        .into_iter()
        .map(|mut rows| {
            rows.sort_unstable();
            let temperature_c =
                rows.iter().map(|&i| temperatures_c[i]).sum::<f64>() / rows.len() as f64;
            TemperatureRun {
                temperature_c,
                rows,
            }
        })
        .collect();
    let mean_c = runs.iter().map(|r| r.temperature_c).sum::<f64>() / runs.len().max(1) as f64;
    let reference = (0..runs.len())
        .max_by(|&a, &b| {
            let key = |r: &TemperatureRun| (r.rows.len(), -(r.temperature_c - mean_c).abs());
            let (ka, kb) = (key(&runs[a]), key(&runs[b]));
            ka.0.cmp(&kb.0).then(ka.1.total_cmp(&kb.1))
        })
        .unwrap_or(0);
    let obs: Vec<_> = runs
        .get(reference)
        .map(|r| r.rows.iter().map(|&i| observations[i]).collect())
        .unwrap_or_default();
    let reference_fit = fit_static_with(&obs, arm)?;
    let model = if runs.len() >= 2 {
        Some(model(observations, &runs, reference, &reference_fit)?)
    } else {
        None
    };
    Ok(ThermalFit {
        runs,
        reference,
        reference_fit,
        model,
    })
}

/// Each run's rows by arm position, in the order of the reference run's rows.
fn positions(
    observations: &[StaticObservation],
    runs: &[TemperatureRun],
    reference: usize,
) -> Result<Vec<Vec<Vector3<f64>>>, FitError> {
    let same = |a: &Vector3<f64>, b: &Vector3<f64>| (a - b).norm() <= 1e-9 * a.norm().max(1.0);
    let reference_rows = &runs[reference].rows;
    let mut out = Vec::with_capacity(reference_rows.len());
    for &i in reference_rows {
        let a = observations[i].reference_mps2;
        let mut outputs = Vec::with_capacity(runs.len());
        for run in runs {
            let found: Vec<_> = run
                .rows
                .iter()
                .filter(|&&j| same(&observations[j].reference_mps2, &a))
                .collect();
            match found.as_slice() {
                [j] => outputs.push(observations[**j].output),
                [] => {
                    return Err(FitError::Temperature(format!(
                        "the run at {:.1} °C lacks the orientation with reference \
                         ({:.4}, {:.4}, {:.4}) m/s² of the run at {:.1} °C: every run must \
                         visit the same orientations",
                        run.temperature_c, a.x, a.y, a.z, runs[reference].temperature_c
                    )))
                }
                _ => {
                    return Err(FitError::Temperature(format!(
                        "the run at {:.1} °C visits the orientation with reference \
                         ({:.4}, {:.4}, {:.4}) m/s² {} times; once per run",
                        run.temperature_c,
                        a.x,
                        a.y,
                        a.z,
                        found.len()
                    )))
                }
            }
        }
        out.push(outputs);
    }
    Ok(out)
}

fn model(
    observations: &[StaticObservation],
    runs: &[TemperatureRun],
    reference: usize,
    reference_fit: &StaticFit,
) -> Result<TemperatureModel, FitError> {
    let by_position = positions(observations, runs, reference)?;
    let reference_c = runs[reference].temperature_c;
    let dt: Vec<f64> = runs.iter().map(|r| r.temperature_c - reference_c).collect();
    let dt_mean = dt.iter().sum::<f64>() / dt.len() as f64;
    let n_obs = by_position.len() * runs.len();
    let dof = n_obs as f64 - by_position.len() as f64 - 2.0;
    if dof < 1.0 {
        return Err(FitError::Temperature(format!(
            "{} orientations in {} runs leave no degree of freedom for the temperature \
             coefficients; measure more orientations or another run",
            by_position.len(),
            runs.len()
        )));
    }
    let mut gain = [0.0; 3];
    let mut d = Vector3::zeros();
    let mut var_d = [0.0; 3];
    let mut cov_gd = [0.0; 3];
    let mut var_g = [0.0; 3];
    for k in 0..3 {
        let mut xtx = Matrix2::zeros();
        let mut xtz = Vector2::zeros();
        let rows: Vec<(Vector2<f64>, f64)> = by_position
            .iter()
            .flat_map(|outputs| {
                let mean = outputs.iter().map(|v| v[k]).sum::<f64>() / outputs.len() as f64;
                outputs.iter().zip(&dt).map(move |(v, t)| {
                    let c = t - dt_mean;
                    (Vector2::new(c * mean, -c), v[k] - mean)
                })
            })
            .collect();
        for (x, z) in &rows {
            xtx += x * x.transpose();
            xtz += x * *z;
        }
        let inv = xtx.try_inverse().ok_or_else(|| {
            FitError::Temperature(
                "the runs do not separate gain from offset drift: the outputs do not differ \
                 between orientations"
                    .into(),
            )
        })?;
        let beta = inv * xtz;
        let rss: f64 = rows.iter().map(|(x, z)| (z - x.dot(&beta)).powi(2)).sum();
        let cov = inv * (rss / dof);
        gain[k] = beta[0];
        d[k] = beta[1];
        var_g[k] = cov[(0, 0)];
        var_d[k] = cov[(1, 1)];
        cov_gd[k] = cov[(0, 1)];
    }
    let s_inv: &Matrix3<f64> = reference_fit.calibration.sensitivity_inv();
    let offset = s_inv * d;
    let mut covariance = [[0.0; 6]; 6];
    for m in 0..3 {
        for n in 0..3 {
            // Cov(c_q) = S⁻¹·diag(var_d)·S⁻ᵀ.
            covariance[m][n] = (0..3)
                .map(|k| s_inv[(m, k)] * var_d[k] * s_inv[(n, k)])
                .sum();
        }
        for k in 0..3 {
            // Cov(c_q,m, c_g,k) = (S⁻¹)_mk·Cov(d_k, c_g,k): channel k's own pair.
            let c = s_inv[(m, k)] * cov_gd[k];
            covariance[m][3 + k] = c;
            covariance[3 + k][m] = c;
        }
    }
    for k in 0..3 {
        covariance[3 + k][3 + k] = var_g[k];
    }
    Ok(TemperatureModel {
        reference_c,
        range_c: [runs[0].temperature_c, runs[runs.len() - 1].temperature_c],
        offset_mps2_per_c: [offset[0], offset[1], offset[2]],
        gain_per_c: Some(gain),
        covariance,
        covariance_dof: Some(dof),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sim::{simulate, SensorTruth, SimConfig};

    /// Three runs of a drifting sensor: the coefficients come back within 3u of the truth,
    /// and the run at 21 °C (the middle, among equals) is the reference.
    #[test]
    fn coefficients_come_back_within_their_uncertainty() {
        let config = SimConfig {
            sensor: SensorTruth::drifting(),
            static_temperatures_c: vec![6.0, 21.0, 36.0],
            static_orientations: 12,
            ..SimConfig::default()
        };
        let sim = simulate(&config);
        let temps = sim.static_temperatures_c.clone().unwrap();
        let fit = fit_thermal(&sim.static_observations, &temps, None).unwrap();
        assert_eq!(fit.runs.len(), 3);
        assert_eq!(fit.reference, 1);
        let m = fit.model.unwrap();
        assert_eq!(m.reference_c, 21.0);
        assert_eq!(m.range_c, [6.0, 36.0]);
        // 12 positions in 3 runs: 36 − 12 − 2.
        assert_eq!(m.covariance_dof, Some(22.0));
        let truth = &config.sensor;
        let gain = m.gain_per_c.unwrap();
        for (k, g) in gain.iter().enumerate() {
            let u_q = m.covariance[k][k].sqrt();
            let u_g = m.covariance[3 + k][3 + k].sqrt();
            let (eq, eg) = (
                m.offset_mps2_per_c[k] - truth.offset_drift_mps2_per_c[k],
                g - truth.gain_drift_per_c[k],
            );
            assert!(eq.abs() < 3.0 * u_q, "c_q[{k}] off by {eq} with u {u_q}");
            assert!(eg.abs() < 3.0 * u_g, "c_g[{k}] off by {eg} with u {u_g}");
            // A drift of a few mm/s² per °C is resolved: u well below it.
            assert!(u_q < 0.2e-3, "u(c_q[{k}]) = {u_q}");
        }
    }

    #[test]
    fn a_run_missing_an_orientation_is_named_by_its_temperature() {
        let config = SimConfig {
            static_temperatures_c: vec![10.0, 30.0],
            ..SimConfig::default()
        };
        let sim = simulate(&config);
        let mut temps = sim.static_temperatures_c.clone().unwrap();
        // Three rows of the first run moved to 40 °C: a run of three.
        for t in temps.iter_mut().take(3) {
            *t = 40.0;
        }
        let e = fit_thermal(&sim.static_observations, &temps, None).unwrap_err();
        assert!(
            e.to_string()
                .contains("the run at 10.0 °C lacks the orientation"),
            "{e}"
        );
    }
}
