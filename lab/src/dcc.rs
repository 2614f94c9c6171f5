//! A calibration record as a Digital Calibration Certificate (PTB's DCC, XML, with D-SI
//! quantities): what a lab's document management and the DCC tools read.
//!
//! Layout (DCC 3 rings; D-SI 2 lists):
//!
//! - `administrativeData`: the software, the core data (certificate id as the unique
//!   identifier, performance dates from the sets' `calibrated_at`, the lab as performance
//!   location), the item (sensor id as the customer's identification, serial and model when the
//!   record has them), the laboratory, the responsible person (`approved_by`) and a customer
//!   placeholder (a record does not name one).
//! - `measurementResults`: one `measurementResult` per set (`static`, `dynamic`), each with its
//!   method, its reference standard as measuring equipment, the calibration temperature as an
//!   influence condition, and four results:
//!   - `sensitivity`: S row-major, nine values, with expanded uncertainties (k and p of the set);
//!   - `offset`: q, three values in m/s², likewise;
//!   - `parameters`: the twelve together with the 12×12 covariance in an ellipsoidal region
//!     (`si:covarianceMatrix`, columns of `si:covariance` with value and unit), the coverage
//!     factor and probability;
//!   - `statedUncertainty`: `uncertainty_mps2`, standard uncertainties (k = 1);
//!   - `domain`: the amplitude and frequency band the set covers;
//!
//!   and the degrees of freedom in the descriptions.
//!
//! Units are D-SI strings: m/s² is `\metre\second\tothe{-2}`; S is the output unit per m/s², so
//! `\volt\metre\tothe{-1}\second\tothe{2}` for volts and `\one\metre\tothe{-1}\second\tothe{2}`
//! for any other output unit (counts), which the result's description names.
//!
//! No package registry ships the official DCC and D-SI schemas, so the document is checked
//! against `lab/dcc/dcc-subset.xsd` and `lab/dcc/dsi-subset.xsd`, written from the published
//! element definitions for the elements used here (see those files).

use std::fmt::Write;

use time::format_description::well_known::Rfc3339;
use time::OffsetDateTime;
use triax_protocol::record::{CalibrationRecord, CalibrationSet, N_PARAMS};

/// DCC namespace and the schema version written.
pub const DCC_NAMESPACE: &str = "https://ptb.de/dcc";
pub const SI_NAMESPACE: &str = "https://ptb.de/si";
pub const DCC_SCHEMA_VERSION: &str = "3.2.1";

const MPS2: &str = "\\metre\\second\\tothe{-2}";

fn esc(s: &str) -> String {
    s.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
        .replace('"', "&quot;")
}

fn text(x: &mut String, element: &str, content: &str) {
    let _ = write!(
        x,
        "<dcc:{element}><dcc:content lang=\"en\">{}</dcc:content></dcc:{element}>",
        esc(content)
    );
}

fn date(t: OffsetDateTime) -> String {
    format!("{:04}-{:02}-{:02}", t.year(), u8::from(t.month()), t.day())
}

/// Decimal text that XML Schema's `xs:double` and D-SI's decimal lists accept (no `inf`).
fn num(v: f64) -> String {
    if v.is_finite() {
        format!("{v:e}")
    } else {
        "NaN".into()
    }
}

fn list(values: impl IntoIterator<Item = f64>) -> String {
    values.into_iter().map(num).collect::<Vec<_>>().join(" ")
}

/// The D-SI unit of S for the record's output unit.
fn sensitivity_unit(output_unit: &str) -> &'static str {
    match output_unit {
        "V" => "\\volt\\metre\\tothe{-1}\\second\\tothe{2}",
        _ => "\\one\\metre\\tothe{-1}\\second\\tothe{2}",
    }
}

/// The unit of the product of two D-SI units, for a covariance entry.
fn product_unit(a: &str, b: &str) -> String {
    format!("{a}{b}")
}

/// Options a record does not carry.
#[derive(Debug, Clone)]
pub struct DccOptions {
    /// ISO 3166-1 alpha-2 code of the lab's country; `ZZ` (user-assigned) when unknown.
    pub country: String,
    /// The writing software's release.
    pub software_release: String,
}

/// The DCC document for `record`.
pub fn dcc_xml(record: &CalibrationRecord, options: &DccOptions) -> String {
    let r = record;
    let mut x = String::new();
    let _ = write!(
        x,
        "<?xml version=\"1.0\" encoding=\"UTF-8\"?>\n\
         <dcc:digitalCalibrationCertificate xmlns:dcc=\"{DCC_NAMESPACE}\" \
         xmlns:si=\"{SI_NAMESPACE}\" schemaVersion=\"{DCC_SCHEMA_VERSION}\">\n\
         <dcc:administrativeData>\n<dcc:dccSoftware><dcc:software>"
    );
    text(&mut x, "name", "triax-lab");
    let _ = writeln!(
        x,
        "<dcc:release>{}</dcc:release></dcc:software></dcc:dccSoftware>",
        esc(&options.software_release)
    );
    let dates = [r.static_set.calibrated_at, r.dynamic.calibrated_at];
    let (begin, end) = (
        dates.iter().min().copied().unwrap_or(r.issued_at),
        dates.iter().max().copied().unwrap_or(r.issued_at),
    );
    let _ = writeln!(
        x,
        "<dcc:coreData><dcc:countryCodeISO3166_1>{}</dcc:countryCodeISO3166_1>\
         <dcc:usedLangCodeISO639_1>en</dcc:usedLangCodeISO639_1>\
         <dcc:mandatoryLangCodeISO639_1>en</dcc:mandatoryLangCodeISO639_1>\
         <dcc:uniqueIdentifier>{}</dcc:uniqueIdentifier>\
         <dcc:beginPerformanceDate>{}</dcc:beginPerformanceDate>\
         <dcc:endPerformanceDate>{}</dcc:endPerformanceDate>\
         <dcc:performanceLocation>laboratory</dcc:performanceLocation></dcc:coreData>",
        esc(&options.country),
        esc(&r.certificate.id),
        date(begin),
        date(end)
    );
    x.push_str("<dcc:items><dcc:item>");
    text(
        &mut x,
        "name",
        &format!("three-axis MEMS accelerometer {}", r.sensor_id),
    );
    x.push_str("<dcc:manufacturer>");
    text(&mut x, "name", "not stated in the calibration record");
    x.push_str("</dcc:manufacturer>");
    if let Some(m) = &r.sensor.model {
        let _ = write!(x, "<dcc:model>{}</dcc:model>", esc(m));
    }
    let _ = write!(
        x,
        "<dcc:identifications><dcc:identification><dcc:issuer>customer</dcc:issuer>\
         <dcc:value>{}</dcc:value></dcc:identification>",
        esc(r.sensor_id.as_str())
    );
    if let Some(s) = &r.sensor.serial {
        let _ = write!(
            x,
            "<dcc:identification><dcc:issuer>manufacturer</dcc:issuer>\
             <dcc:value>{}</dcc:value></dcc:identification>",
            esc(s)
        );
    }
    x.push_str("</dcc:identifications></dcc:item></dcc:items>\n");
    x.push_str("<dcc:calibrationLaboratory>");
    if let Some(a) = &r.lab.accreditation {
        let _ = write!(
            x,
            "<dcc:calibrationLaboratoryCode>{}</dcc:calibrationLaboratoryCode>",
            esc(a)
        );
    }
    contact(&mut x, &r.lab.name);
    x.push_str("</dcc:calibrationLaboratory>\n<dcc:respPersons><dcc:respPerson><dcc:person>");
    text(
        &mut x,
        "name",
        r.lab
            .approved_by
            .as_deref()
            .unwrap_or("not stated in the calibration record"),
    );
    x.push_str("</dcc:person><dcc:mainSigner>true</dcc:mainSigner></dcc:respPerson></dcc:respPersons>\n<dcc:customer>");
    contact_fields(&mut x, "not stated in the calibration record");
    x.push_str("</dcc:customer>\n</dcc:administrativeData>\n<dcc:measurementResults>\n");
    for (name, set) in [("static", &r.static_set), ("dynamic", &r.dynamic)] {
        measurement_result(&mut x, r, name, set);
    }
    let _ = write!(
        x,
        "</dcc:measurementResults>\n<dcc:comment><dcc:content lang=\"en\">Issued from Triax \
         calibration record version {} of sensor {} (issued {}, valid from {}{}). The record \
         (JSON, PROTOCOL.md §3.1) is the reference for what this certificate cannot carry: \
         the output noise, a temperature model, and how a gateway combines the parts.\
         </dcc:content></dcc:comment>\n</dcc:digitalCalibrationCertificate>\n",
        r.version,
        esc(r.sensor_id.as_str()),
        r.issued_at.format(&Rfc3339).unwrap_or_default(),
        r.valid_from.format(&Rfc3339).unwrap_or_default(),
        r.valid_until
            .map(|t| format!(", valid until {}", t.format(&Rfc3339).unwrap_or_default()))
            .unwrap_or_default()
    );
    x
}

fn contact(x: &mut String, name: &str) {
    x.push_str("<dcc:contact>");
    contact_fields(x, name);
    x.push_str("</dcc:contact>");
}

fn contact_fields(x: &mut String, name: &str) {
    text(x, "name", name);
    x.push_str("<dcc:eMail></dcc:eMail><dcc:location><dcc:further><dcc:content lang=\"en\">not stated in the calibration record</dcc:content></dcc:further></dcc:location>");
}

fn measurement_result(x: &mut String, r: &CalibrationRecord, name: &str, set: &CalibrationSet) {
    let k = set.coverage_factor;
    let p = set.coverage_probability.unwrap_or(0.95);
    let s_unit = sensitivity_unit(&r.sensor.output_unit);
    x.push_str("<dcc:measurementResult>");
    text(x, "name", &format!("{name} set"));
    x.push_str("<dcc:usedMethods><dcc:usedMethod>");
    text(x, "name", &set.method);
    x.push_str(
        "</dcc:usedMethod></dcc:usedMethods><dcc:measuringEquipments><dcc:measuringEquipment>",
    );
    text(x, "name", &set.reference);
    x.push_str("</dcc:measuringEquipment></dcc:measuringEquipments>");
    if let Some(t) = r.certificate.temperature_c {
        x.push_str("<dcc:influenceConditions><dcc:influenceCondition>");
        text(x, "name", "ambient temperature");
        let _ = write!(
            x,
            "<dcc:data><dcc:quantity><si:real><si:value>{}</si:value>\
             <si:unit>\\degreeCelsius</si:unit></si:real></dcc:quantity></dcc:data>\
             </dcc:influenceCondition></dcc:influenceConditions>",
            num(t)
        );
    }
    x.push_str("<dcc:results>");
    let s: Vec<f64> = set.sensitivity.iter().flatten().copied().collect();
    let cov = set.covariance.as_deref();
    let sd = |i: usize| cov.map_or(0.0, |c| c[i][i].max(0.0).sqrt());
    let labels_s = [
        "Sxx", "Sxy", "Sxz", "Syx", "Syy", "Syz", "Szx", "Szy", "Szz",
    ];
    let s_text = if s_unit.starts_with("\\one") {
        format!(
            "S of a = S⁻¹·V + q, row-major, in {} per m/s² (the output unit)",
            r.sensor.output_unit
        )
    } else {
        "S of a = S⁻¹·V + q, row-major, in V per m/s²".to_string()
    };
    expanded_list(
        x,
        "sensitivity",
        &s_text,
        &labels_s,
        &s,
        &[s_unit; 9],
        &(0..9).map(|i| k * sd(i)).collect::<Vec<_>>(),
        k,
        p,
    );
    expanded_list(
        x,
        "offset",
        "q of a = S⁻¹·V + q, m/s²",
        &["qx", "qy", "qz"],
        &set.offset,
        &[MPS2; 3],
        &(9..12).map(|i| k * sd(i)).collect::<Vec<_>>(),
        k,
        p,
    );
    if let Some(c) = cov {
        let units: Vec<&str> = (0..N_PARAMS)
            .map(|i| if i < 9 { s_unit } else { MPS2 })
            .collect();
        x.push_str("<dcc:result>");
        text(x, "name", "parameters");
        let _ = write!(
            x,
            "<dcc:description><dcc:content lang=\"en\">S row-major then q, with their \
             covariance{}</dcc:content></dcc:description>",
            set.covariance_dof
                .map(|nu| format!(" ({nu} degrees of freedom)"))
                .unwrap_or_default()
        );
        let labels: Vec<&str> = labels_s.iter().copied().chain(["qx", "qy", "qz"]).collect();
        let values: Vec<f64> = s.iter().copied().chain(set.offset).collect();
        let _ = write!(
            x,
            "<dcc:data><dcc:quantity><si:realListXMLList>\
             <si:labelXMLList>{}</si:labelXMLList><si:valueXMLList>{}</si:valueXMLList>\
             <si:unitXMLList>{}</si:unitXMLList><si:ellipsoidalRegionXMLList>\
             <si:covarianceMatrix>",
            labels.join(" "),
            list(values),
            units.join(" ")
        );
        for j in 0..N_PARAMS {
            x.push_str("<si:column>");
            for (i, row) in c.iter().enumerate() {
                let _ = write!(
                    x,
                    "<si:covariance><si:value>{}</si:value><si:unit>{}</si:unit></si:covariance>",
                    num(row[j]),
                    product_unit(units[i], units[j])
                );
            }
            x.push_str("</si:column>");
        }
        let _ = write!(
            x,
            "</si:covarianceMatrix><si:coverageFactorXMLList>{}</si:coverageFactorXMLList>\
             <si:coverageProbabilityXMLList>{}</si:coverageProbabilityXMLList>\
             <si:distributionXMLList>normal</si:distributionXMLList>\
             </si:ellipsoidalRegionXMLList></si:realListXMLList></dcc:quantity></dcc:data>\
             </dcc:result>",
            num(k),
            num(p)
        );
    }
    x.push_str("<dcc:result>");
    text(x, "name", "statedUncertainty");
    let _ = write!(
        x,
        "<dcc:description><dcc:content lang=\"en\">standard uncertainty (k = 1) of a corrected \
         value from what the covariance does not cover{}</dcc:content></dcc:description>\
         <dcc:data><dcc:quantity><si:realListXMLList><si:labelXMLList>ux uy uz</si:labelXMLList>\
         <si:valueXMLList>{}</si:valueXMLList><si:unitXMLList>{MPS2} {MPS2} {MPS2}\
         </si:unitXMLList></si:realListXMLList></dcc:quantity></dcc:data></dcc:result>",
        set.uncertainty_dof
            .map(|nu| format!(" ({nu} degrees of freedom)"))
            .unwrap_or_default(),
        list(set.uncertainty_mps2)
    );
    x.push_str("<dcc:result>");
    text(x, "name", "domain");
    let d = &set.domain;
    let _ = write!(
        x,
        "<dcc:description><dcc:content lang=\"en\">where the set was shown to hold: largest \
         |a| per axis, and the band of the varying content ({} points)</dcc:content>\
         </dcc:description><dcc:data><dcc:quantity><si:realListXMLList>\
         <si:labelXMLList>amplitudeMax frequencyMin frequencyMax</si:labelXMLList>\
         <si:valueXMLList>{}</si:valueXMLList><si:unitXMLList>{MPS2} \\hertz \\hertz\
         </si:unitXMLList></si:realListXMLList></dcc:quantity></dcc:data></dcc:result>",
        set.n_points,
        list([d.amplitude_max_mps2, d.frequency_min_hz, d.frequency_max_hz])
    );
    x.push_str("</dcc:results></dcc:measurementResult>\n");
}

/// A list result with expanded uncertainties per value.
#[allow(clippy::too_many_arguments)]
fn expanded_list(
    x: &mut String,
    name: &str,
    description: &str,
    labels: &[&str],
    values: &[f64],
    units: &[&str],
    expanded: &[f64],
    k: f64,
    p: f64,
) {
    x.push_str("<dcc:result>");
    text(x, "name", name);
    let n = values.len();
    let _ = write!(
        x,
        "<dcc:description><dcc:content lang=\"en\">{}</dcc:content></dcc:description>\
         <dcc:data><dcc:quantity><si:realListXMLList><si:labelXMLList>{}</si:labelXMLList>\
         <si:valueXMLList>{}</si:valueXMLList><si:unitXMLList>{}</si:unitXMLList>\
         <si:expandedUncXMLList><si:uncertaintyXMLList>{}</si:uncertaintyXMLList>\
         <si:coverageFactorXMLList>{}</si:coverageFactorXMLList>\
         <si:coverageProbabilityXMLList>{}</si:coverageProbabilityXMLList>\
         <si:distributionXMLList>normal</si:distributionXMLList></si:expandedUncXMLList>\
         </si:realListXMLList></dcc:quantity></dcc:data></dcc:result>",
        esc(description),
        labels.join(" "),
        list(values.iter().copied()),
        units.join(" "),
        list(expanded.iter().copied()),
        list(std::iter::repeat_n(k, n)),
        list(std::iter::repeat_n(p, n)),
    );
}

#[cfg(test)]
mod tests {
    use super::*;
    use triax_protocol::record::sample;

    #[test]
    fn carries_the_records_numbers_and_escapes_its_text() {
        let mut r = sample::record("acc-01", 3);
        r.lab.name = "Lab <A> & Co".into();
        let mut cov = [[0.0; 12]; 12];
        for (i, row) in cov.iter_mut().enumerate() {
            row[i] = 1e-6 * (i + 1) as f64;
        }
        r.static_set.covariance = Some(Box::new(cov));
        r.static_set.covariance_dof = Some(6.0);
        let x = dcc_xml(
            &r,
            &DccOptions {
                country: "ZZ".into(),
                software_release: "0.1.0".into(),
            },
        );
        assert!(x.contains("Lab &lt;A&gt; &amp; Co"));
        assert!(x.contains("<dcc:uniqueIdentifier>SAMPLE-acc-01-3</dcc:uniqueIdentifier>"));
        assert_eq!(
            x.matches("<si:covariance>").count(),
            144,
            "one 12×12 matrix"
        );
        assert!(x.contains("(6 degrees of freedom)"));
        // q_x's expanded uncertainty: k = 2 times √1e-5.
        assert!(x.contains(&num(2.0 * 1e-5f64.sqrt())), "{x}");
        assert_eq!(x.matches("<dcc:measurementResult>").count(), 2);
    }
}
