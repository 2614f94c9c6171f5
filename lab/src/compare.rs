//! Back to the lab with the evidence: a sensor's new record against the one it replaces, and
//! against what the field saw while the old one was in force.
//!
//! **Parameters.** Per static-set parameter, old and new with their standard uncertainties
//! (the records' covariances), the change and its uncertainty: the two calibrations are
//! independent, so their variances add. Gains (the sensitivity's diagonal) as relative changes,
//! cross-axis terms and offsets as differences.
//!
//! **Against the field.** The gateway's relative gravity test (PROTOCOL.md §3.9) estimates how
//! much the magnitude of a quiet reading, corrected with the old record, has moved since that
//! record's first day in the field, along the direction `û` its report gives. If the new record
//! is the sensor's state now and the old one its state then, the lab predicts that change as
//!
//! ```text
//! d_lab = |S_old⁻¹·S_new·(g·û − q_new) + q_old| − g
//! ```
//!
//! (`a = S⁻¹·V + q`; a reading `V = S_new·(g·û − q_new)` corrected with the old record, minus
//! what the old record read then). Its uncertainty is propagated by Monte Carlo over both
//! records' covariances (4 000 draws, a fixed seed). The two estimates are independent, so
//! `z = (d_field − d_lab)/√(u_field² + u_lab²)` says whether the field and the lab saw the same
//! change: |z| ≤ 2 they agree at about 95 %.

use nalgebra::{Matrix3, SMatrix, SVector, Vector3};
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use rand_distr::StandardNormal;
use triax_protocol::messages::SensorHealthReport;
use triax_protocol::record::{CalibrationRecord, N_PARAMS};

/// Standard gravity, m/s²: the magnitude `d_lab` is taken at (its change hardly depends on it).
const G_MPS2: f64 = 9.80665;
const DRAWS: usize = 4000;

/// Why two records cannot be compared.
#[derive(Debug, thiserror::Error)]
pub enum CompareError {
    #[error("the records are of {old} and {new}: a comparison is of one sensor")]
    Sensors { old: String, new: String },
    #[error("the new record's version {new} is not after the old one's {old}")]
    Order { old: u64, new: u64 },
    #[error("record {sensor} version {version}: its static sensitivity does not invert")]
    Singular { sensor: String, version: u64 },
    #[error(
        "the health report is of {sensor} version {version}, not of the old record \
         ({old_sensor} version {old_version})"
    )]
    Report {
        sensor: String,
        version: u64,
        old_sensor: String,
        old_version: u64,
    },
}

/// One parameter, old and new.
#[derive(Debug, Clone, PartialEq)]
pub struct Row {
    /// `S[i][j]` or `q[i]`.
    pub name: String,
    pub old: (f64, f64),
    pub new: (f64, f64),
    /// The change (relative for gains) and its standard uncertainty.
    pub change: (f64, f64),
    pub relative: bool,
}

/// The field's relative gravity estimate against the lab's prediction of it.
#[derive(Debug, Clone, PartialEq)]
pub struct FieldCheck {
    pub direction: [f64; 3],
    /// m/s² and their standard uncertainties.
    pub field: (f64, f64),
    pub lab: (f64, f64),
    pub z: f64,
    /// Quiet stretches behind the field's estimate.
    pub observations: u64,
}

/// What the field report can say.
#[derive(Debug, Clone, PartialEq)]
pub enum Field {
    /// No report given.
    None,
    /// The report's relative gravity test was not judged, or gave no direction: why.
    Unjudged(String),
    Judged(FieldCheck),
}

#[derive(Debug, Clone, PartialEq)]
pub struct Comparison {
    pub sensor: String,
    pub old_version: u64,
    pub new_version: u64,
    pub rows: Vec<Row>,
    pub field: Field,
}

fn parameters(r: &CalibrationRecord) -> SVector<f64, N_PARAMS> {
    let s = &r.static_set;
    SVector::from_fn(|p, _| {
        if p < 9 {
            s.sensitivity[p / 3][p % 3]
        } else {
            s.offset[p - 9]
        }
    })
}

fn covariance(r: &CalibrationRecord) -> SMatrix<f64, N_PARAMS, N_PARAMS> {
    match &r.static_set.covariance {
        Some(c) => SMatrix::from_fn(|i, j| 0.5 * (c[i][j] + c[j][i])),
        None => SMatrix::zeros(),
    }
}

/// A square root of a covariance for drawing from it: its eigenvectors by the roots of its
/// eigenvalues (negative ones, round-off, taken as 0).
fn root(c: &SMatrix<f64, N_PARAMS, N_PARAMS>) -> SMatrix<f64, N_PARAMS, N_PARAMS> {
    let e = c.symmetric_eigen();
    let d = SMatrix::<f64, N_PARAMS, N_PARAMS>::from_diagonal(
        &e.eigenvalues.map(|l| l.max(0.0).sqrt()),
    );
    e.eigenvectors * d
}

fn sensitivity(p: &SVector<f64, N_PARAMS>) -> Matrix3<f64> {
    Matrix3::from_fn(|i, j| p[3 * i + j])
}

fn offset(p: &SVector<f64, N_PARAMS>) -> Vector3<f64> {
    Vector3::new(p[9], p[10], p[11])
}

/// `d_lab` for parameter vectors `old` and `new` along `u`; none when a sensitivity is singular.
fn predicted(
    old: &SVector<f64, N_PARAMS>,
    new: &SVector<f64, N_PARAMS>,
    u: &Vector3<f64>,
) -> Option<f64> {
    let s_old_inv = sensitivity(old).try_inverse()?;
    let v = sensitivity(new) * (u * G_MPS2 - offset(new));
    Some((s_old_inv * v + offset(old)).norm() - G_MPS2)
}

/// Compares `new` with `old`, and with what `field` (a health report of `old`) saw.
pub fn compare(
    old: &CalibrationRecord,
    new: &CalibrationRecord,
    field: Option<&SensorHealthReport>,
) -> Result<Comparison, CompareError> {
    if old.sensor_id != new.sensor_id {
        return Err(CompareError::Sensors {
            old: old.sensor_id.to_string(),
            new: new.sensor_id.to_string(),
        });
    }
    if new.version <= old.version {
        return Err(CompareError::Order {
            old: old.version,
            new: new.version,
        });
    }
    let (po, pn) = (parameters(old), parameters(new));
    let (co, cn) = (covariance(old), covariance(new));
    let mut rows = Vec::with_capacity(N_PARAMS);
    for p in 0..N_PARAMS {
        let (uo, un) = (co[(p, p)].max(0.0).sqrt(), cn[(p, p)].max(0.0).sqrt());
        let gain = p < 9 && p / 3 == p % 3;
        let change = if gain {
            let rel = pn[p] / po[p] - 1.0;
            let u = (pn[p] / po[p]) * ((uo / po[p]).powi(2) + (un / pn[p]).powi(2)).sqrt();
            (rel, u)
        } else {
            (pn[p] - po[p], uo.hypot(un))
        };
        rows.push(Row {
            name: if p < 9 {
                format!("S[{}][{}]", p / 3, p % 3)
            } else {
                format!("q[{}]", p - 9)
            },
            old: (po[p], uo),
            new: (pn[p], un),
            change,
            relative: gain,
        });
    }
    let field = match field {
        None => Field::None,
        Some(r) => {
            if r.sensor_id != old.sensor_id || r.calibration_version != old.version {
                return Err(CompareError::Report {
                    sensor: r.sensor_id.to_string(),
                    version: r.calibration_version,
                    old_sensor: old.sensor_id.to_string(),
                    old_version: old.version,
                });
            }
            field_check(old, new, r, &po, &pn, &co, &cn)?
        }
    };
    Ok(Comparison {
        sensor: old.sensor_id.to_string(),
        old_version: old.version,
        new_version: new.version,
        rows,
        field,
    })
}

#[allow(clippy::too_many_arguments)]
fn field_check(
    old: &CalibrationRecord,
    new: &CalibrationRecord,
    r: &SensorHealthReport,
    po: &SVector<f64, N_PARAMS>,
    pn: &SVector<f64, N_PARAMS>,
    co: &SMatrix<f64, N_PARAMS, N_PARAMS>,
    cn: &SMatrix<f64, N_PARAMS, N_PARAMS>,
) -> Result<Field, CompareError> {
    let Some(test) = r.tests.iter().find(|t| t.test == "gravity_relative") else {
        return Ok(Field::Unjudged(
            "the report has no gravity_relative test".into(),
        ));
    };
    let (true, Some(d), Some(u)) = (test.judged, test.statistic, test.uncertainty) else {
        return Ok(Field::Unjudged(format!(
            "gravity_relative not judged: {}",
            test.reason.as_deref().unwrap_or("no reason given")
        )));
    };
    let Some(direction) = r.gravity_direction else {
        return Ok(Field::Unjudged(
            "the report gives no gravity_direction (a gateway that predates it)".into(),
        ));
    };
    let dir = Vector3::from(direction);
    let norm = dir.norm();
    if !(norm.is_finite() && norm > 0.0) {
        return Ok(Field::Unjudged(format!(
            "gravity_direction {direction:?} is not a direction"
        )));
    }
    let dir = dir / norm;
    let singular = |rec: &CalibrationRecord| CompareError::Singular {
        sensor: rec.sensor_id.to_string(),
        version: rec.version,
    };
    let lab = predicted(po, pn, &dir).ok_or_else(|| singular(old))?;
    let (ro, rn) = (root(co), root(cn));
    let mut rng = StdRng::seed_from_u64(0x1AB5);
    let mut sum = 0.0;
    let mut sum_sq = 0.0;
    let mut n = 0usize;
    for _ in 0..DRAWS {
        let zo = SVector::<f64, N_PARAMS>::from_fn(|_, _| rng.sample(StandardNormal));
        let zn = SVector::<f64, N_PARAMS>::from_fn(|_, _| rng.sample(StandardNormal));
        if let Some(x) = predicted(&(po + ro * zo), &(pn + rn * zn), &dir) {
            sum += x;
            sum_sq += x * x;
            n += 1;
        }
    }
    if n < DRAWS / 2 {
        return Err(singular(new));
    }
    let mean = sum / n as f64;
    let lab_u = ((sum_sq / n as f64 - mean * mean).max(0.0) * n as f64 / (n as f64 - 1.0)).sqrt();
    let z = (d - lab) / u.hypot(lab_u);
    Ok(Field::Judged(FieldCheck {
        direction: dir.into(),
        field: (d, u),
        lab: (lab, lab_u),
        z,
        observations: test.observations,
    }))
}

/// Decimals that show `u` to two significant digits.
fn decimals(u: f64) -> usize {
    if !(u.is_finite() && u > 0.0) {
        return 6;
    }
    (1.0 - u.log10().floor()).clamp(0.0, 12.0) as usize
}

fn pm(value: f64, u: f64, scale: f64) -> String {
    let d = decimals(u * scale);
    format!("{:.d$} ± {:.d$}", value * scale, u * scale)
}

/// The comparison as the terminal shows it.
pub fn render_text(c: &Comparison) -> String {
    let mut out = format!(
        "{} version {} against version {} (static set; gains as relative changes in %)\n",
        c.sensor, c.new_version, c.old_version
    );
    out.push_str(&format!(
        "{:<8} {:>26} {:>26} {:>26} {:>6}\n",
        "PARAM", "OLD", "NEW", "CHANGE", "z"
    ));
    for r in &c.rows {
        let scale = if r.relative { 100.0 } else { 1.0 };
        let z = if r.change.1 > 0.0 {
            format!("{:.1}", r.change.0 / r.change.1)
        } else {
            "-".into()
        };
        out.push_str(&format!(
            "{:<8} {:>26} {:>26} {:>26} {:>6}\n",
            r.name,
            pm(r.old.0, r.old.1, 1.0),
            pm(r.new.0, r.new.1, 1.0),
            pm(r.change.0, r.change.1, scale),
            z
        ));
    }
    match &c.field {
        Field::None => {}
        Field::Unjudged(why) => out.push_str(&format!("field: {why}\n")),
        Field::Judged(f) => out.push_str(&format!(
            "field: the quiet reading along ({:.3}, {:.3}, {:.3}) moved {} m/s^2 over {} quiet \
             minutes; the lab's records predict {} m/s^2: z = {:.2} ({})\n",
            f.direction[0],
            f.direction[1],
            f.direction[2],
            pm(f.field.0, f.field.1, 1.0),
            f.observations,
            pm(f.lab.0, f.lab.1, 1.0),
            f.z,
            if f.z.abs() <= 2.0 {
                "they agree"
            } else {
                "they disagree: the field saw another change than the lab measured"
            }
        )),
    }
    out
}

fn esc(text: &str) -> String {
    text.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
}

/// The comparison as a section of the HTML report.
pub fn render_html(c: &Comparison) -> String {
    let mut s = format!(
        "<h2>Against version {} and the field</h2><table><tr><th>parameter</th><th>old</th>\
         <th>new</th><th>change</th><th>z</th></tr>",
        c.old_version
    );
    for r in &c.rows {
        let scale = if r.relative { 100.0 } else { 1.0 };
        let unit = if r.relative { " %" } else { "" };
        let z = if r.change.1 > 0.0 {
            format!("{:.1}", r.change.0 / r.change.1)
        } else {
            "–".into()
        };
        s.push_str(&format!(
            "<tr><td>{}</td><td>{}</td><td>{}</td><td>{}{unit}</td><td>{z}</td></tr>",
            esc(&r.name),
            pm(r.old.0, r.old.1, 1.0),
            pm(r.new.0, r.new.1, 1.0),
            pm(r.change.0, r.change.1, scale),
        ));
    }
    s.push_str("</table>");
    match &c.field {
        Field::None => s.push_str("<p>No field health report was given.</p>"),
        Field::Unjudged(why) => s.push_str(&format!("<p>Field: {}.</p>", esc(why))),
        Field::Judged(f) => s.push_str(&format!(
            "<p>Field: the quiet reading's magnitude through version {} moved {} m/s² over {} \
             quiet minutes (relative gravity test); the two records predict {} m/s² for that \
             attitude: z = {:.2}.</p>",
            c.old_version,
            pm(f.field.0, f.field.1, 1.0),
            f.observations,
            pm(f.lab.0, f.lab.1, 1.0),
            f.z
        )),
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;
    use triax_protocol::messages::{HealthTest, HealthVerdict, StreamQuality};
    use triax_protocol::record::sample;

    fn record(version: u64, gain_z: f64, offset_z: f64) -> CalibrationRecord {
        let mut r = sample::record("cmp", version);
        r.static_set.sensitivity = [[0.1, 0.0, 0.0], [0.0, 0.1, 0.0], [0.0, 0.0, gain_z]];
        r.static_set.offset = [0.0, 0.0, offset_z];
        let mut cov = [[0.0; N_PARAMS]; N_PARAMS];
        cov[8][8] = 1e-10;
        cov[11][11] = 1e-8;
        r.static_set.covariance = Some(Box::new(cov));
        r
    }

    fn report(statistic: f64, u: f64) -> SensorHealthReport {
        SensorHealthReport {
            format_version: 1,
            building: triax_protocol::BuildingId::new("hq").unwrap(),
            sensor_id: triax_protocol::SensorId::new("cmp").unwrap(),
            calibration_version: 1,
            verdict: HealthVerdict::Suspect,
            suspect_since_ns: None,
            flagged_from_ns: None,
            reported_at: time::OffsetDateTime::UNIX_EPOCH,
            data_until_ns: None,
            blocks: 0,
            quiet_stretches: 100,
            discontinuities: 0,
            calibration_checked: Some(true),
            gravity_direction: Some([0.0, 0.0, 1.0]),
            tests: vec![HealthTest {
                test: "gravity_relative".into(),
                channel: None,
                peer: None,
                verdict: HealthVerdict::Suspect,
                judged: true,
                statistic: Some(statistic),
                uncertainty: Some(u),
                unit: "m/s^2".into(),
                since_ns: None,
                evidence_nats: 30.0,
                observations: 100,
                reason: None,
                masked: None,
                loud: None,
            }],
            quality: StreamQuality {
                samples: 0,
                availability: 1.0,
                gaps: 0,
                latency_min_ms: None,
                latency_max_ms: None,
            },
        }
    }

    /// Gravity along z, the z gain 0.1 % higher in the new record: a reading through the old
    /// one is 0.1 % high, 9.807 mm/s² along gravity, by hand; the field saw 9.6 ± 0.5 mm/s²:
    /// they agree. An offset of the new record 10 mm/s² higher lowers the reading by as much.
    #[test]
    fn the_lab_predicts_what_the_field_saw() {
        let old = record(1, 0.1, 0.0);
        let new = record(2, 0.1001, 0.0);
        let c = compare(&old, &new, Some(&report(0.0096, 0.0005))).unwrap();
        let gain = &c.rows[8];
        assert_eq!(gain.name, "S[2][2]");
        assert!((gain.change.0 - 0.001).abs() < 1e-12, "{gain:?}");
        let Field::Judged(f) = &c.field else {
            panic!("{:?}", c.field)
        };
        assert!((f.lab.0 - 0.001 * G_MPS2).abs() < 1e-9, "{f:?}");
        // u(S₂₂) = 10⁻⁵ on 0.1: 10⁻⁴ relative in each, √2·10⁻⁴·g and both offsets' 10⁻⁴ m/s².
        let expect = ((2.0f64.sqrt() * 1e-4 * G_MPS2).powi(2) + 2e-8).sqrt();
        assert!(
            (f.lab.1 / expect - 1.0).abs() < 0.05,
            "{f:?} against {expect}"
        );
        assert!(f.z.abs() < 2.0, "{f:?}");
        let text = render_text(&c);
        assert!(text.contains("they agree"), "{text}");
        let shifted = record(2, 0.1, 0.01);
        let c = compare(&old, &shifted, Some(&report(0.0096, 0.0005))).unwrap();
        let Field::Judged(f) = &c.field else { panic!() };
        assert!((f.lab.0 + 0.01).abs() < 1e-9, "{f:?}");
        assert!(f.z > 2.0 && render_text(&c).contains("disagree"));
    }

    #[test]
    fn refusals_name_what_is_wrong() {
        let old = record(2, 0.1, 0.0);
        let new = record(1, 0.1, 0.0);
        assert!(compare(&old, &new, None)
            .unwrap_err()
            .to_string()
            .contains("not after"));
        let mut other = record(3, 0.1, 0.0);
        other.sensor_id = triax_protocol::SensorId::new("other").unwrap();
        assert!(compare(&old, &other, None)
            .unwrap_err()
            .to_string()
            .contains("one sensor"));
        let e = compare(
            &record(1, 0.1, 0.0),
            &record(2, 0.1, 0.0),
            Some(&{
                let mut r = report(0.0, 1.0);
                r.calibration_version = 7;
                r
            }),
        )
        .unwrap_err();
        assert!(e.to_string().contains("version 7"), "{e}");
        let mut unjudged = report(0.0, 1.0);
        unjudged.tests[0].judged = false;
        unjudged.tests[0].reason = Some("baseline".into());
        let c = compare(&record(1, 0.1, 0.0), &record(2, 0.1, 0.0), Some(&unjudged)).unwrap();
        assert_eq!(
            c.field,
            Field::Unjudged("gravity_relative not judged: baseline".into())
        );
    }
}
