//! The self-contained HTML report: the paper's tables and plots like its Figures 5–7, for one
//! calibration. Inline CSS and SVG only; it opens offline and can be archived as it is.

use std::fmt::Write;

use nalgebra::{Matrix3, Vector3};
use time::OffsetDateTime;
use triax_calibration::fit::dynamic::prepare;
use triax_calibration::fit::ReferenceMethod;

use crate::commands::{low_dof_warning, parameter_sigmas, DynamicResult, StaticResult, Tables};
use crate::record::{coverage_factor, dynamic_dof, COVERAGE_PROBABILITY};
use crate::svg::{line_plot, Series};

/// Everything the report shows.
pub struct Report<'a> {
    pub sensor_id: &'a str,
    pub issued_at: OffsetDateTime,
    pub stat: Option<&'a StaticResult>,
    pub dynamic: &'a DynamicResult,
    pub tables: &'a Tables,
}

const AXES: [&str; 3] = ["x", "y", "z"];
const BLUE: &str = "#1f77b4";
const ORANGE: &str = "#ff7f0e";
const GREEN: &str = "#2ca02c";
const GREY: &str = "#555555";

fn esc(text: &str) -> String {
    text.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
}

fn matrix_table(caption: &str, m: &Matrix3<f64>, u: &Matrix3<f64>) -> String {
    let mut s = format!("<table><caption>{}</caption>", esc(caption));
    for i in 0..3 {
        s.push_str("<tr>");
        for j in 0..3 {
            let _ = write!(
                s,
                "<td>{:.6} <small>± {:.1e}</small></td>",
                m[(i, j)],
                u[(i, j)]
            );
        }
        s.push_str("</tr>");
    }
    s.push_str("</table>");
    s
}

fn vector_row(label: &str, v: &Vector3<f64>, precision: usize) -> String {
    format!(
        "<tr><th>{}</th><td>{:.p$}</td><td>{:.p$}</td><td>{:.p$}</td></tr>",
        esc(label),
        v.x,
        v.y,
        v.z,
        p = precision
    )
}

fn axis_header(first: &str) -> String {
    format!(
        "<tr><th>{}</th><th>x</th><th>y</th><th>z</th></tr>",
        esc(first)
    )
}

/// Renders the report.
pub fn render(r: &Report<'_>) -> String {
    let mut h = String::new();
    let _ = write!(
        h,
        "<!DOCTYPE html><html lang=\"en\"><head><meta charset=\"utf-8\">\
         <title>Calibration report {id}</title><style>\
         body{{font-family:sans-serif;max-width:960px;margin:2em auto;color:#222}}\
         table{{border-collapse:collapse;margin:0.8em 0}}\
         td,th{{border:1px solid #ccc;padding:3px 8px;text-align:right}}\
         caption{{text-align:left;font-weight:bold;padding:4px 0}}\
         h2{{border-bottom:1px solid #ccc}} small{{color:#666}}</style></head><body>\
         <h1>Calibration report: sensor {id}</h1><p>Issued {at}. Model a = S⁻¹·V + q; \
         uncertainties are standard uncertainties (k = 1) unless stated.</p>",
        id = esc(r.sensor_id),
        at = r
            .issued_at
            .format(&time::format_description::well_known::Rfc3339)
            .unwrap_or_default()
    );

    if let Some(stat) = r.stat {
        static_section(&mut h, stat);
    }
    dynamic_section(&mut h, r.dynamic);
    tables_section(&mut h, r.tables);
    plots_section(&mut h, r);
    h.push_str("</body></html>\n");
    h
}

fn static_section(h: &mut String, stat: &StaticResult) {
    let fit = &stat.fit;
    let (su, qu) = parameter_sigmas(&fit.calibration);
    let _ = write!(
        h,
        "<h2>Static calibration</h2><p>{} orientations from {}, {} residual degrees of \
         freedom. Covariance: ν = {:.0}, so k = {:.3} for {:.0} % intervals (Student's t).</p>",
        fit.residuals_mps2.len(),
        esc(&stat.path.display().to_string()),
        fit.dof,
        fit.covariance_dof,
        coverage_factor(fit.covariance_dof),
        COVERAGE_PROBABILITY * 100.0
    );
    h.push_str(&matrix_table(
        "S_S [output/(m/s²)] ± standard uncertainty",
        fit.calibration.sensitivity(),
        &su,
    ));
    let _ = write!(
        h,
        "<table><caption>Offset and residuals</caption>{}",
        axis_header("")
    );
    h.push_str(&vector_row("q_S [m/s²]", fit.calibration.offset_mps2(), 4));
    h.push_str(&vector_row("u(q_S) [m/s²]", &qu, 4));
    h.push_str(&vector_row(
        "residual RMS [m/s²]",
        &fit.residual_rms_mps2,
        4,
    ));
    h.push_str("</table>");
    let _ = write!(
        h,
        "<table><caption>Per orientation: reference and corrected − reference [m/s²]</caption>\
         <tr><th>#</th><th>a_x</th><th>a_y</th><th>a_z</th><th>Δx</th><th>Δy</th><th>Δz</th></tr>"
    );
    for (i, (obs, res)) in stat
        .observations
        .iter()
        .zip(&fit.residuals_mps2)
        .enumerate()
    {
        let a = obs.reference_mps2;
        let _ = write!(
            h,
            "<tr><td>{}</td><td>{:.3}</td><td>{:.3}</td><td>{:.3}</td><td>{:.4}</td><td>{:.4}</td><td>{:.4}</td></tr>",
            i + 1,
            a.x,
            a.y,
            a.z,
            res.x,
            res.y,
            res.z
        );
    }
    h.push_str("</table>");
    let _ = write!(
        h,
        "<p>±g check (section 3.1): largest deviation of the corrected output from the \
         reference {:.4} m/s² (orientation {}).",
        fit.max_deviation_mps2,
        fit.max_deviation_orientation + 1
    );
    if let Some(loo) = fit.leave_one_out_max_deviation_mps2 {
        let _ = write!(
            h,
            " With each orientation left out of its own fit: {loo:.4} m/s²."
        );
    }
    h.push_str("</p>");
    for w in fit.warnings.iter().cloned().chain(low_dof_warning(fit)) {
        let _ = write!(h, "<p><strong>Warning:</strong> {}</p>", esc(&w));
    }
}

fn dynamic_section(h: &mut String, d: &DynamicResult) {
    let fit = &d.fit;
    let b = &d.budget;
    let bench = d.bench();
    let (su, qu) = parameter_sigmas(&b.calibration);
    let dof = dynamic_dof(fit, b);
    let alphas: Vec<String> = d
        .loaded
        .recordings
        .iter()
        .map(|r| format!("{} ({}°)", r.path.display(), r.recording.alpha_deg))
        .collect();
    let _ = write!(
        h,
        "<h2>Dynamic calibration</h2><p>Reference: {}; n = {} points per cycle; {} points \
         from {} cycles of {} recordings: {}. r = {} m (u(r) = {} m), sine {} Hz, {} rad. \
         Covariance: ν = {:.0}, so k = {:.3} for {:.0} % intervals; uncertainty_mps2: ν = {}.</p>",
        fit.method,
        fit.points_per_cycle,
        fit.n_points,
        fit.cycles.iter().sum::<usize>(),
        fit.cycles.len(),
        esc(&alphas.join(", ")),
        bench.radius_m,
        bench.radius_uncertainty_m,
        bench.motion.frequency_hz,
        bench.motion.amplitude_rad,
        dof.covariance.unwrap_or(f64::INFINITY),
        coverage_factor(dof.covariance.unwrap_or(f64::INFINITY)),
        COVERAGE_PROBABILITY * 100.0,
        dof.uncertainty
            .map_or("∞".to_string(), |nu| format!("{nu:.0}"))
    );
    h.push_str(&matrix_table(
        "S_D [output/(m/s²)] ± standard uncertainty",
        b.calibration.sensitivity(),
        &su,
    ));
    let _ = write!(
        h,
        "<table><caption>Offset, residual and uncertainty budget (k = 1)</caption>{}",
        axis_header("")
    );
    h.push_str(&vector_row("q_D [m/s²]", b.calibration.offset_mps2(), 4));
    h.push_str(&vector_row("u(q_D) [m/s²]", &qu, 4));
    h.push_str(&vector_row(
        "RMS(corrected − reference) [m/s²]",
        &fit.residual_rms_mps2,
        4,
    ));
    h.push_str(&vector_row(
        "amplitude of the reference [m/s²]",
        &b.amplitude_mps2,
        3,
    ));
    h.push_str(&vector_row(
        &format!("repeatability, {} one-cycle sets [m/s²]", b.sets),
        &b.repeatability.mps2,
        4,
    ));
    h.push_str(&vector_row(
        "repeatability [% of amplitude]",
        &b.repeatability.percent,
        2,
    ));
    h.push_str(&vector_row(
        "reference variability over cycles [m/s²]",
        &b.reference_variability.mps2,
        4,
    ));
    h.push_str(&vector_row(
        "reference variability [% of amplitude]",
        &b.reference_variability.percent,
        2,
    ));
    h.push_str(&vector_row("radius u(r) [m/s²]", &b.radius_mps2, 4));
    h.push_str(&vector_row("lack of fit [m/s²]", &b.lack_of_fit_mps2, 4));
    h.push_str(&vector_row(
        "parameters, from the covariance [m/s²]",
        &b.parameter_mps2,
        4,
    ));
    h.push_str(&vector_row(
        "output noise [m/s²]",
        &fit.output_noise_mps2,
        4,
    ));
    h.push_str(&vector_row(
        "uncertainty_mps2 in the record [m/s²]",
        &b.combined_mps2,
        4,
    ));
    h.push_str("</table>");
    let _ = write!(
        h,
        "<p>The record's <code>uncertainty_mps2</code> holds the radius and lack-of-fit \
         contributions only; the corrector adds the parameter covariance (covariance scale \
         factor {:.2} from the repeatability check) and the output noise. Repeatability and \
         reference variability are shown for comparison with the paper; their effect on the \
         parameters is in the covariance. Applicability domain: |a| up to {:.2} m/s² per axis, \
         {} Hz.</p>",
        b.covariance_inflation,
        b.max_abs_mps2.max(),
        bench.motion.frequency_hz
    );
}

fn tables_section(h: &mut String, t: &Tables) {
    h.push_str("<h2>Tables</h2>");
    let _ = write!(
        h,
        "<table><caption>Table 1: RMS of (corrected by the dynamic matrix − reference) vs n \
         [m/s²]</caption>{}",
        axis_header("n")
    );
    for row in &t.points {
        h.push_str(&vector_row(
            &row.points_per_cycle.to_string(),
            &row.rms_mps2,
            4,
        ));
    }
    h.push_str("</table>");
    let _ = write!(
        h,
        "<table><caption>Tables 2 and 3: RMS of (corrected − reference) on the dynamic data, \
         absolute [m/s²] and relative to the amplitude</caption>{}",
        axis_header("set")
    );
    h.push_str(&vector_row("dynamic, absolute", &t.dynamic_set.rms_mps2, 4));
    h.push_str(&vector_row("dynamic, relative", &t.dynamic_set.relative, 3));
    if let Some(s) = &t.static_set {
        h.push_str(&vector_row("static, absolute", &s.rms_mps2, 4));
        h.push_str(&vector_row("static, relative", &s.relative, 3));
    }
    h.push_str("</table>");
    let refs = &t.references;
    let _ = write!(
        h,
        "<table><caption>Reference methods: RMS of each method's own fit [m/s²]</caption>{}",
        axis_header("method")
    );
    for (m, v) in refs.methods.iter().zip(&refs.fit_rms_mps2) {
        h.push_str(&vector_row(m.name(), v, 4));
    }
    h.push_str("</table>");
    h.push_str(
        "<table><caption>Reference methods against each other: RMS of the difference of the \
         reference specific forces, x / y / z [m/s²]</caption><tr><th></th>",
    );
    for m in &refs.methods {
        let _ = write!(h, "<th>{}</th>", m.name());
    }
    h.push_str("</tr>");
    for (i, m) in refs.methods.iter().enumerate() {
        let _ = write!(h, "<tr><th>{}</th>", m.name());
        for (j, v) in refs.pairwise_rms_mps2[i].iter().enumerate() {
            if i == j {
                h.push_str("<td>—</td>");
            } else {
                let _ = write!(h, "<td>{:.3} / {:.3} / {:.3}</td>", v.x, v.y, v.z);
            }
        }
        h.push_str("</tr>");
    }
    h.push_str("</table>");
}

fn plots_section(h: &mut String, r: &Report<'_>) {
    let d = r.dynamic;
    let fit = &d.fit;
    let bench = d.bench();
    // The recording with the largest x–y excitation shows all effects; any one will do.
    let index = d.loaded.recordings.len().min(2) - 1;
    let loaded = &d.loaded.recordings[index];
    let rec = &loaded.recording;
    let prep = &fit.prepared[index];
    let period = bench.motion.period_s();
    let cycles = &prep.cycles;
    let start = cycles[cycles.len() / 2 - if cycles.len() >= 3 { 1 } else { 0 }].start;
    let end =
        (start + (2.0 * period / (rec.t_s[1] - rec.t_s[0])).round() as usize).min(prep.valid().end);
    let t0 = rec.t_s[start];

    let _ = write!(
        h,
        "<h2>Figures</h2><p>Recording {} (α = {}°), two cycles.</p>",
        esc(&loaded.path.display().to_string()),
        rec.alpha_deg
    );

    // Like Figure 5: the paper's two references and the one used.
    let mut refs = Vec::new();
    for (method, colour) in [
        (ReferenceMethod::FiniteDifference, GREY),
        (ReferenceMethod::MotionLaw, ORANGE),
        (fit.method, BLUE),
    ] {
        if refs.iter().any(|(m, _, _)| *m == method) {
            continue;
        }
        if let Ok(p) = prepare(bench, method, rec) {
            refs.push((method, colour, p));
        }
    }
    for (axis, name) in AXES.iter().enumerate() {
        let series: Vec<Series> = refs
            .iter()
            .map(|(m, colour, p)| Series {
                label: m.name(),
                colour,
                points: (start.max(p.valid().start)..end.min(p.valid().end))
                    .map(|i| (rec.t_s[i] - t0, p.reference_mps2[i][axis]))
                    .collect(),
                faint: *m == ReferenceMethod::FiniteDifference,
            })
            .collect();
        h.push_str(&line_plot(
            &format!("Reference a_{} by method (like Figure 5)", name),
            "t [s]",
            "m/s²",
            &series,
        ));
    }

    // Like Figure 6: reference vs corrected by the static and by the dynamic matrix.
    for (axis, name) in AXES.iter().enumerate() {
        let mut series = vec![Series {
            label: "reference",
            colour: GREY,
            points: (start..end)
                .map(|i| (rec.t_s[i] - t0, prep.reference_mps2[i][axis]))
                .collect(),
            faint: false,
        }];
        if let Some(stat) = r.stat {
            series.push(Series {
                label: "static matrix",
                colour: ORANGE,
                points: (start..end)
                    .map(|i| {
                        (
                            rec.t_s[i] - t0,
                            stat.fit.calibration.correct(&rec.output[i])[axis],
                        )
                    })
                    .collect(),
                faint: false,
            });
        }
        series.push(Series {
            label: "dynamic matrix",
            colour: BLUE,
            points: (start..end)
                .map(|i| {
                    (
                        rec.t_s[i] - t0,
                        d.budget.calibration.correct(&rec.output[i])[axis],
                    )
                })
                .collect(),
            faint: false,
        });
        h.push_str(&line_plot(
            &format!("a_{}: reference and corrected output (like Figure 6)", name),
            "t [s]",
            "m/s²",
            &series,
        ));
    }

    // Like Figure 7: every cycle of the reference, overlaid.
    for (axis, name) in AXES.iter().enumerate() {
        let series: Vec<Series> = cycles
            .iter()
            .map(|c| Series {
                label: "",
                colour: GREEN,
                points: c
                    .clone()
                    .map(|i| (rec.t_s[i] - rec.t_s[c.start], prep.reference_mps2[i][axis]))
                    .collect(),
                faint: true,
            })
            .collect();
        h.push_str(&line_plot(
            &format!(
                "a_{}: {} cycles of the reference overlaid (like Figure 7)",
                name,
                cycles.len()
            ),
            "time in cycle [s]",
            "m/s²",
            &series,
        ));
    }
}
