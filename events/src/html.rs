//! The event's page: one self-contained HTML file with inline SVG (no script, no external
//! resource), made from the report and the floors' time series, so that it reads offline, is
//! archived as is, and is drawn again when the report is revised.
//!
//! Every string from the configuration or the network reaches the page escaped.

use std::fmt::Write;

use serde::{Deserialize, Serialize};
use time::format_description::well_known::Rfc3339;
use time::OffsetDateTime;
use triax_protocol::event::{EventParameter, EventReport, EventTag, EventVerdict};
use triax_protocol::messages::ModalDirection;

/// One sensor's acceleration for the page: per pixel column its min and max, x and y of the
/// building frame, baseline removed, m/s².
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SeriesPlot {
    pub sensor_id: String,
    pub floor: i32,
    /// Seconds from the window's start of the first column, and of each column.
    pub start_s: f64,
    pub column_s: f64,
    pub x: Vec<[f64; 2]>,
    pub y: Vec<[f64; 2]>,
}

/// Columns of a time series plot.
pub const COLUMNS: usize = 600;

fn esc(s: &str) -> String {
    s.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
        .replace('"', "&quot;")
        .replace('\'', "&#39;")
}

fn utc(ns: i64) -> String {
    OffsetDateTime::from_unix_timestamp_nanos(i128::from(ns))
        .ok()
        .and_then(|t| t.format(&Rfc3339).ok())
        .unwrap_or_else(|| ns.to_string())
}

fn interval(p: &EventParameter, scale: f64, digits: usize) -> String {
    format!(
        "{:.*} ± {:.*} (k = {:.2})",
        digits,
        p.value * scale,
        digits,
        p.coverage_factor * p.standard_uncertainty * scale,
        p.coverage_factor
    )
}

fn colour(t: EventTag) -> &'static str {
    match t {
        EventTag::Green => "#2e7d32",
        EventTag::Yellow => "#f9a825",
        EventTag::Red => "#c62828",
    }
}

fn tag_name(t: EventTag) -> &'static str {
    match t {
        EventTag::Green => "green",
        EventTag::Yellow => "yellow",
        EventTag::Red => "red",
    }
}

fn verdict_name(v: Option<EventVerdict>) -> &'static str {
    match v {
        Some(EventVerdict::Below) => "below",
        Some(EventVerdict::Possible) => "possible",
        Some(EventVerdict::Exceeded) => "exceeded",
        None => "not judged",
    }
}

fn dir(d: ModalDirection) -> &'static str {
    match d {
        ModalDirection::X => "x",
        ModalDirection::Y => "y",
        ModalDirection::Z => "z",
    }
}

/// A plot area: pixel box and data ranges, linear or logarithmic in each axis.
struct Frame {
    x0: f64,
    y0: f64,
    w: f64,
    h: f64,
    xr: (f64, f64),
    yr: (f64, f64),
    xlog: bool,
    ylog: bool,
}

impl Frame {
    fn px(&self, x: f64) -> f64 {
        let (a, b) = if self.xlog {
            (self.xr.0.ln(), self.xr.1.ln())
        } else {
            self.xr
        };
        let v = if self.xlog { x.max(1e-300).ln() } else { x };
        self.x0 + (v - a) / (b - a).max(1e-300) * self.w
    }

    fn py(&self, y: f64) -> f64 {
        let (a, b) = if self.ylog {
            (self.yr.0.ln(), self.yr.1.ln())
        } else {
            self.yr
        };
        let v = if self.ylog { y.max(self.yr.0).ln() } else { y };
        self.y0 + self.h - (v - a) / (b - a).max(1e-300) * self.h
    }

    fn axes(&self, out: &mut String, xlabel: &str, ylabel: &str) {
        let _ = write!(
            out,
            "<rect x='{}' y='{}' width='{}' height='{}' fill='none' stroke='#888'/>\
             <text x='{}' y='{}' font-size='11' text-anchor='middle'>{}</text>\
             <text x='{}' y='{}' font-size='11' transform='rotate(-90 {} {})' text-anchor='middle'>{}</text>\
             <text x='{}' y='{}' font-size='10'>{}</text><text x='{}' y='{}' font-size='10' text-anchor='end'>{}</text>\
             <text x='{}' y='{}' font-size='10' text-anchor='end'>{}</text><text x='{}' y='{}' font-size='10' text-anchor='end'>{}</text>",
            self.x0, self.y0, self.w, self.h,
            self.x0 + self.w / 2.0, self.y0 + self.h + 28.0, esc(xlabel),
            self.x0 - 42.0, self.y0 + self.h / 2.0, self.x0 - 42.0, self.y0 + self.h / 2.0, esc(ylabel),
            self.x0, self.y0 + self.h + 14.0, fmt(self.xr.0), self.x0 + self.w, self.y0 + self.h + 14.0, fmt(self.xr.1),
            self.x0 - 4.0, self.y0 + self.h, fmt(self.yr.0), self.x0 - 4.0, self.y0 + 10.0, fmt(self.yr.1),
        );
    }
}

fn fmt(v: f64) -> String {
    if v == 0.0 {
        "0".into()
    } else if v.abs() >= 100.0 || v.abs() < 0.01 {
        format!("{v:.2e}")
    } else {
        format!("{v:.3}")
    }
}

const PALETTE: [&str; 8] = [
    "#1565c0", "#c62828", "#2e7d32", "#6a1b9a", "#ef6c00", "#00838f", "#4e342e", "#ad1457",
];

fn series_svg(series: &[SeriesPlot]) -> String {
    let row_h = 70.0;
    let (w, left) = (720.0, 60.0);
    let mut out = format!(
        "<svg xmlns='http://www.w3.org/2000/svg' width='{}' height='{}'>",
        w + left + 20.0,
        series.len() as f64 * (row_h + 26.0) + 30.0
    );
    for (r, s) in series.iter().enumerate() {
        let peak =
            s.x.iter()
                .chain(&s.y)
                .flat_map(|m| [m[0].abs(), m[1].abs()])
                .fold(1e-6f64, f64::max);
        let f = Frame {
            x0: left,
            y0: 10.0 + r as f64 * (row_h + 26.0),
            w,
            h: row_h,
            xr: (s.start_s, s.start_s + s.column_s * s.x.len().max(1) as f64),
            yr: (-peak, peak),
            xlog: false,
            ylog: false,
        };
        f.axes(&mut out, "", "m/s²");
        let _ = write!(
            out,
            "<text x='{}' y='{}' font-size='11'>{} (floor {}): x blue, y red</text>",
            left + 4.0,
            f.y0 + 12.0,
            esc(&s.sensor_id),
            s.floor
        );
        for (k, data) in [&s.x, &s.y].iter().enumerate() {
            let mut path = String::new();
            for (c, m) in data.iter().enumerate() {
                let x = f.px(s.start_s + (c as f64 + 0.5) * s.column_s);
                let _ = write!(path, "M{x:.1},{:.1}L{x:.1},{:.1}", f.py(m[0]), f.py(m[1]));
            }
            let _ = write!(
                out,
                "<path d='{path}' stroke='{}' stroke-width='1' fill='none' opacity='0.8'/>",
                PALETTE[k]
            );
        }
    }
    out.push_str("</svg>");
    out
}

fn spectra_svg(r: &EventReport) -> String {
    let mut points: Vec<(f64, f64)> = Vec::new();
    for s in &r.sensors {
        for o in &s.spectrum {
            points.push((
                o.period_s,
                o.rotd50.value + o.rotd50.coverage_factor * o.rotd50.standard_uncertainty,
            ));
        }
    }
    let limits: Vec<(f64, f64, &str)> = r
        .limits
        .iter()
        .filter(|l| l.quantity == "psa_rotd50")
        .filter_map(|l| {
            let period = l
                .item
                .as_deref()?
                .rsplit(" at ")
                .next()?
                .trim_end_matches(" s")
                .parse()
                .ok()?;
            Some((period, l.threshold, l.name.as_str()))
        })
        .collect();
    let (tmin, tmax) = points
        .iter()
        .fold((f64::MAX, f64::MIN), |(a, b), p| (a.min(p.0), b.max(p.0)));
    let ymax = points
        .iter()
        .map(|p| p.1)
        .chain(limits.iter().map(|l| l.1))
        .fold(1e-4f64, f64::max)
        * 1.3;
    if points.is_empty() {
        return String::new();
    }
    let f = Frame {
        x0: 60.0,
        y0: 10.0,
        w: 520.0,
        h: 300.0,
        xr: (tmin, tmax),
        yr: (ymax * 1e-3, ymax),
        xlog: true,
        ylog: true,
    };
    let mut out = "<svg xmlns='http://www.w3.org/2000/svg' width='760' height='360'>".to_string();
    f.axes(&mut out, "period (s)", "PSA RotD50 (m/s²), 5 % damped");
    for (i, s) in r.sensors.iter().enumerate() {
        let c = PALETTE[i % PALETTE.len()];
        let mut path = String::new();
        for (j, o) in s.spectrum.iter().enumerate() {
            let _ = write!(
                path,
                "{}{:.1},{:.1}",
                if j == 0 { "M" } else { "L" },
                f.px(o.period_s),
                f.py(o.rotd50.value)
            );
            let band = o.rotd50.coverage_factor * o.rotd50.standard_uncertainty;
            let _ = write!(
                out,
                "<line x1='{x:.1}' x2='{x:.1}' y1='{:.1}' y2='{:.1}' stroke='{c}'/>",
                f.py((o.rotd50.value - band).max(ymax * 1e-3)),
                f.py(o.rotd50.value + band),
                x = f.px(o.period_s)
            );
            if !o.usable {
                let _ = write!(
                    out,
                    "<circle cx='{:.1}' cy='{:.1}' r='3' fill='none' stroke='{c}'/>",
                    f.px(o.period_s),
                    f.py(o.rotd50.value)
                );
            }
        }
        let _ = write!(out, "<path d='{path}' stroke='{c}' fill='none'/>");
        let _ = write!(
            out,
            "<text x='600' y='{}' font-size='11' fill='{c}'>{}</text>",
            20 + 14 * i,
            esc(s.sensor_id.as_str())
        );
    }
    for (period, threshold, name) in limits {
        let _ = write!(
            out,
            "<rect x='{:.1}' y='{:.1}' width='8' height='8' fill='#000'/><text x='{:.1}' y='{:.1}' font-size='10'>{}</text>",
            f.px(period) - 4.0,
            f.py(threshold) - 4.0,
            f.px(period) + 6.0,
            f.py(threshold) - 6.0,
            esc(name)
        );
    }
    out.push_str("</svg>");
    out
}

fn drift_svg(r: &EventReport) -> String {
    if r.drifts.is_empty() {
        return String::new();
    }
    let heights: Vec<f64> = r.sensors.iter().map(|s| s.height_m).collect();
    let top = heights.iter().cloned().fold(1.0f64, f64::max);
    let limit_values: Vec<(f64, &str)> = r
        .limits
        .iter()
        .filter(|l| l.quantity == "drift_ratio")
        .map(|l| (l.threshold, l.name.as_str()))
        .collect();
    let xmax = r
        .drifts
        .iter()
        .map(|d| {
            d.drift_ratio.value
                + d.drift_ratio.coverage_factor * d.drift_ratio.standard_uncertainty
                + d.bias_bound
        })
        .chain(limit_values.iter().map(|l| l.0))
        .fold(1e-6f64, f64::max)
        * 1.15;
    let f = Frame {
        x0: 60.0,
        y0: 10.0,
        w: 480.0,
        h: 300.0,
        xr: (0.0, 100.0 * xmax),
        yr: (0.0, top),
        xlog: false,
        ylog: false,
    };
    let mut out = "<svg xmlns='http://www.w3.org/2000/svg' width='700' height='360'>".to_string();
    f.axes(
        &mut out,
        "inter-storey drift ratio (%), x blue, y red; the bar ± k·u and the bias bound",
        "height (m)",
    );
    // The storey's height range, heights of the floors' sensors.
    let floor_height = |floor: i32| {
        let h: Vec<f64> = r
            .sensors
            .iter()
            .filter(|s| s.floor == floor)
            .map(|s| s.height_m)
            .collect();
        h.iter().sum::<f64>() / h.len().max(1) as f64
    };
    for d in &r.drifts {
        let c = if d.direction == ModalDirection::X {
            PALETTE[0]
        } else {
            PALETTE[1]
        };
        let (y0, y1) = (
            f.py(floor_height(d.lower_floor)),
            f.py(floor_height(d.upper_floor)),
        );
        let v = 100.0 * d.drift_ratio.value;
        let reach = 100.0
            * (d.drift_ratio.coverage_factor * d.drift_ratio.standard_uncertainty + d.bias_bound);
        let ym = 0.5 * (y0 + y1)
            + if d.direction == ModalDirection::X {
                -3.0
            } else {
                3.0
            };
        let _ = write!(
            out,
            "<line x1='{:.1}' x2='{:.1}' y1='{y0:.1}' y2='{y1:.1}' stroke='{c}' stroke-width='3'/>\
             <line x1='{:.1}' x2='{:.1}' y1='{ym:.1}' y2='{ym:.1}' stroke='{c}'/>",
            f.px(v),
            f.px(v),
            f.px((v - reach).max(0.0)),
            f.px(v + reach)
        );
    }
    for (t, name) in limit_values {
        let x = f.px(100.0 * t);
        let _ = write!(
            out,
            "<line x1='{x:.1}' x2='{x:.1}' y1='10' y2='310' stroke='#000' stroke-dasharray='4 3'/>\
             <text x='{:.1}' y='24' font-size='10'>{}</text>",
            x + 3.0,
            esc(name)
        );
    }
    out.push_str("</svg>");
    out
}

fn modes_svg(r: &EventReport) -> String {
    let m = &r.modes;
    if m.before.is_empty() && m.after.is_empty() {
        return String::new();
    }
    let all: Vec<_> = m.before.iter().chain(&m.after).collect();
    let lo = all
        .iter()
        .map(|x| x.frequency_hz.value - 3.0 * x.frequency_hz.standard_uncertainty)
        .fold(f64::MAX, f64::min);
    let hi = all
        .iter()
        .map(|x| x.frequency_hz.value + 3.0 * x.frequency_hz.standard_uncertainty)
        .fold(f64::MIN, f64::max);
    let pad = (hi - lo).max(1e-3) * 0.2;
    let f = Frame {
        x0: 60.0,
        y0: 10.0,
        w: 300.0,
        h: 220.0,
        xr: (0.0, 3.0),
        yr: (lo - pad, hi + pad),
        xlog: false,
        ylog: false,
    };
    let mut out = "<svg xmlns='http://www.w3.org/2000/svg' width='520' height='280'>".to_string();
    f.axes(
        &mut out,
        "before · after",
        "fundamental (Hz), x blue, y red",
    );
    for (side, list) in [(1.0, &m.before), (2.0, &m.after)] {
        for e in list.iter() {
            let c = if e.direction == ModalDirection::X {
                PALETTE[0]
            } else {
                PALETTE[1]
            };
            let band = e.frequency_hz.coverage_factor * e.frequency_hz.standard_uncertainty;
            let x = f.px(side
                + if e.direction == ModalDirection::X {
                    -0.1
                } else {
                    0.1
                });
            let _ = write!(
                out,
                "<circle cx='{x:.1}' cy='{:.1}' r='4' fill='{c}'/><line x1='{x:.1}' x2='{x:.1}' y1='{:.1}' y2='{:.1}' stroke='{c}'/>",
                f.py(e.frequency_hz.value),
                f.py(e.frequency_hz.value - band),
                f.py(e.frequency_hz.value + band)
            );
        }
    }
    out.push_str("</svg>");
    out
}

/// The page of `report`, with the floors' `series`.
pub fn page(report: &EventReport, series: &[SeriesPlot]) -> String {
    let r = report;
    let mut out = String::new();
    let _ = write!(
        out,
        "<!DOCTYPE html><html lang='en'><head><meta charset='utf-8'>\
         <meta http-equiv='Content-Security-Policy' content=\"default-src 'none'; style-src 'unsafe-inline'; img-src data:\">\
         <title>{b} event {id}</title><style>body{{font-family:sans-serif;margin:1.5em;max-width:1100px}}\
         table{{border-collapse:collapse;font-size:12px;margin:0.5em 0}}td,th{{border:1px solid #ccc;padding:2px 6px;text-align:right}}\
         th{{background:#f3f3f3}}td.l,th.l{{text-align:left}}.tag{{display:inline-block;padding:4px 12px;color:#fff;font-weight:bold;border-radius:4px}}</style></head><body>",
        b = esc(r.building.as_str()),
        id = esc(r.event_id.as_str())
    );
    let _ = write!(
        out,
        "<h1>{} — event {}</h1><p><span class='tag' style='background:{}'>{}</span> {}</p>\
         <p>From {} to {} (sensors' clocks; window {} to {}), revision {} ({}), reported {}.{}</p>",
        esc(r.building.as_str()),
        esc(r.event_id.as_str()),
        colour(r.tag),
        tag_name(r.tag),
        if r.drivers.is_empty() {
            "every limit below".to_string()
        } else {
            format!("driven by {}", esc(&r.drivers.join(", ")))
        },
        utc(r.start_ns),
        utc(r.end_ns),
        utc(r.window_start_ns),
        utc(r.window_end_ns),
        r.revision,
        esc(&r.revision_reason),
        r.reported_at.format(&Rfc3339).unwrap_or_default(),
        if r.truncated {
            " The event was cut at the longest event length; the shaking went on."
        } else {
            ""
        }
    );
    out.push_str("<h2>Decisions</h2><table><tr><th class='l'>limit</th><th class='l'>quantity</th><th>threshold</th><th class='l'>verdict</th><th class='l'>deciding item</th><th>value ± k·u</th><th>bias bound</th><th>decision k</th><th>items</th><th>false exceeded ≤</th></tr>");
    for l in &r.limits {
        let _ = write!(
            out,
            "<tr><td class='l'>{}</td><td class='l'>{}</td><td>{} {}</td><td class='l' style='color:{}'>{}</td><td class='l'>{}</td><td>{}</td><td>{}</td><td>{}</td><td>{}</td><td>{:.1} %</td></tr>",
            esc(&l.name),
            esc(&l.quantity),
            fmt(l.threshold),
            esc(&l.unit),
            colour(l.tag),
            verdict_name(l.verdict),
            esc(l.item.as_deref().unwrap_or("")),
            l.value.as_ref().map_or(String::new(), |v| interval(v, 1.0, 4)),
            fmt(l.bias_bound),
            l.decision_factor.map_or(String::new(), |k| format!("{k:.2}")),
            l.items,
            100.0 * l.false_exceeded_probability
        );
    }
    out.push_str("</table><p>Decision rule: <em>exceeded</em> when value − k·u − bias bound &gt; threshold, <em>possible</em> when the interval reaches the threshold, <em>below</em> otherwise; k is Student's one-sided quantile at the estimate's degrees of freedom for the limit's false-exceeded probability, shared by its items (Šidák). Flagged data decide <em>possible</em> at most.</p>");
    if !r.caveats.is_empty() {
        out.push_str("<h2>Caveats</h2><ul>");
        for c in &r.caveats {
            let _ = write!(out, "<li>{}</li>", esc(c));
        }
        out.push_str("</ul>");
    }
    out.push_str("<h2>Acceleration per floor</h2>");
    out.push_str(&series_svg(series));
    out.push_str("<h2>Response spectra</h2>");
    out.push_str(&spectra_svg(r));
    out.push_str("<p>RotD50 of each sensor with its k·u bars; open circles: periods outside what the band supports; squares: configured limits.</p>");
    out.push_str("<h2>Drift profile</h2>");
    out.push_str(&drift_svg(r));
    out.push_str("<table><tr><th>storey</th><th class='l'>direction</th><th>drift ratio (%) ± k·u</th><th>bias bound (%)</th><th>fundamental (Hz)</th></tr>");
    for d in &r.drifts {
        let _ =
            write!(
            out,
            "<tr><td>{}–{}</td><td class='l'>{}</td><td>{}</td><td>{}</td><td>{:.3}{}</td></tr>",
            d.lower_floor,
            d.upper_floor,
            dir(d.direction),
            interval(&d.drift_ratio, 100.0, 4),
            fmt(100.0 * d.bias_bound),
            d.fundamental_hz,
            if d.fundamental_from_event { " (from the event)" } else { "" }
        );
    }
    out.push_str("</table><h2>Modal frequency before and after</h2>");
    let modes = modes_svg(r);
    if modes.is_empty() {
        out.push_str("<p>No modes window of the building was received.</p>");
    } else {
        out.push_str(&modes);
        for d in &r.modes.drops {
            let _ = write!(
                out,
                "<p>Drop of the {} fundamental: {:.2} ± {:.2} % (k = {:.2}).</p>",
                dir(d.direction),
                d.drop_percent.value,
                d.drop_percent.coverage_factor * d.drop_percent.standard_uncertainty,
                d.drop_percent.coverage_factor
            );
        }
        if r.modes.after.is_empty() {
            out.push_str("<p>The first window after the event has not arrived yet: a revision follows when it does.</p>");
        }
    }
    out.push_str("<h2>Parameters per sensor</h2><table><tr><th class='l'>sensor</th><th>floor</th><th class='l'>dir.</th><th>PGA (m/s²)</th><th>PGV (m/s)</th><th>PGD (m)</th><th>Arias (m/s)</th><th>CAV (m/s)</th><th>D5–95 (s)</th><th>DIN 4150-3 v (mm/s) at f (Hz)</th></tr>");
    for s in &r.sensors {
        for (a, v) in s.axes.iter().zip(&s.vibration) {
            let _ = write!(
                out,
                "<tr><td class='l'>{}</td><td>{}</td><td class='l'>{}</td><td>{}</td><td>{}</td><td>{}</td><td>{}</td><td>{}</td><td>{}</td><td>{}{}</td></tr>",
                esc(s.sensor_id.as_str()),
                s.floor,
                dir(a.direction),
                interval(&a.pga_mps2, 1.0, 4),
                interval(&a.pgv_mps, 1.0, 5),
                interval(&a.pgd_m, 1.0, 5),
                interval(&a.arias_mps, 1.0, 5),
                interval(&a.cav_mps, 1.0, 4),
                a.d5_95_s.as_ref().map_or(String::new(), |d| interval(d, 1.0, 2)),
                interval(&v.peak_velocity_mmps, 1.0, 3),
                v.dominant_frequency_hz.as_ref().map_or(String::new(), |f| format!(" at {:.2}", f.value))
            );
        }
        let _ = write!(
            out,
            "<tr><td class='l'>{}</td><td>{}</td><td class='l'>RotD</td><td colspan='8' class='l'>PGA RotD50 {}, RotD100 {} m/s²{}; {} of {} samples unusable</td></tr>",
            esc(s.sensor_id.as_str()),
            s.floor,
            interval(&s.pga_rotd50_mps2, 1.0, 4),
            interval(&s.pga_rotd100_mps2, 1.0, 4),
            s.tilt.as_ref().map_or(String::new(), |t| format!(
                "; residual tilt roll {} °, pitch {} °",
                interval(&t.roll_change_deg, 1.0, 4),
                interval(&t.pitch_change_deg, 1.0, 4)
            )),
            s.invalid_samples,
            s.samples
        );
    }
    let p = &r.processing;
    let _ = write!(
        out,
        "</table><h2>Processing</h2><p>Baseline: the pre-event mean. Acausal Butterworth band-pass {} Hz to {} Hz, order {} each way, run forward and backward (zero phase), padded with {:.0} s of zeros; velocity and displacement by the trapezoidal rule; oscillators {} % damped, exact for input linear between samples. Intervals claim {} % coverage; the calibration's part is the records' covariance of the sensitivities, the noise's their output noise. Sensors' clocks {} s apart (standard uncertainty). DIN 4150-3 velocity in {} Hz to {} Hz. Files: {}.</p></body></html>",
        p.band_low_hz,
        p.band_high_hz,
        p.band_order,
        1.5 * f64::from(p.band_order) / p.band_low_hz,
        100.0 * p.damping,
        100.0 * p.coverage_probability,
        p.clock_uncertainty_s,
        p.din_low_hz,
        p.din_high_hz,
        esc(&r.files.join(", "))
    );
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_page_is_self_contained_and_escapes_what_it_is_given() {
        let mut r = triax_protocol::event::sample::report("hq", "20270115T080112Z");
        r.limits[0].name = "<script>alert(1)</script>".into();
        r.caveats.push("a & b < c".into());
        let series = vec![SeriesPlot {
            sensor_id: "roof".into(),
            floor: 5,
            start_s: 0.0,
            column_s: 0.1,
            x: vec![[-1.0, 1.0]; 10],
            y: vec![[-0.5, 0.5]; 10],
        }];
        let html = page(&r, &series);
        assert!(html.starts_with("<!DOCTYPE html>"));
        assert!(!html.contains("<script>"), "escaped");
        assert!(html.contains("&lt;script&gt;") && html.contains("a &amp; b &lt; c"));
        assert!(html.matches("<svg").count() >= 2);
        assert!(!html.contains("src='http") && !html.contains("href='http"));
        assert!(html.contains("yellow"));
    }
}
