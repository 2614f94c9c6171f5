//! A calibration record as a Digital Calibration Certificate (PTB's DCC, XML, with D-SI
//! quantities): what a lab's document management and the DCC tools read.
//!
//! Layout (DCC 3.2.1 rings; D-SI 2.1.0 lists):
//!
//! - `administrativeData`: the software, the core data (certificate id as the unique
//!   identifier, performance dates from the sets' `calibrated_at`, the lab as performance
//!   location), the item (sensor id as the customer's identification, serial and model when the
//!   record has them), the laboratory (its contact e-mail when the lab gives one), the
//!   responsible person (`approved_by`) and a customer placeholder (a record does not name one).
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
//! Numbers are never rounded. Values, uncertainties and covariances are the shortest decimal
//! that reads back as the same `f64`, in exponent form (`-1.25e-3`), which D-SI's `decimalType`
//! and `uncertaintyValueType` allow. Coverage factors and probabilities are the same shortest
//! digits written without an exponent (`2.44691185114497`, `0.95`), because `kValueType` and
//! `probabilityValueType` forbid one; `kValueType` also starts at 1, so a set whose k is below 1
//! (which a record allows) has no certificate.
//!
//! Validity: the tests check every certificate against PTB's DCC 3.2.1 and D-SI 2.1.0 schemas
//! and against `lab/dcc/dcc-subset.xsd` with `lab/dcc/dsi-subset.xsd`, which admit only the
//! elements written here and, unlike the official `si:unitType`, only D-SI unit syntax.

use std::fmt::Write;

use time::format_description::well_known::Rfc3339;
use time::OffsetDateTime;
use triax_protocol::record::{CalibrationRecord, CalibrationSet, N_PARAMS};
use triax_protocol::RecordError;

/// DCC namespace and the schema version written.
pub const DCC_NAMESPACE: &str = "https://ptb.de/dcc";
pub const SI_NAMESPACE: &str = "https://ptb.de/si";
pub const DCC_SCHEMA_VERSION: &str = "3.2.1";

const MPS2: &str = "\\metre\\second\\tothe{-2}";

/// Why a record or the options cannot make a valid certificate.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum DccError {
    #[error(transparent)]
    Record(#[from] RecordError),
    #[error("country {0:?} is not two capital letters (ISO 3166-1 alpha-2)")]
    Country(String),
    #[error("e-mail {0:?} is not an address: one word with an @ between a name and a domain")]
    EMail(String),
    /// A text DCC 3.2.1 requires (`dcc:notEmptyStringType`) is empty or blank.
    #[error("{what} is empty, and a DCC requires it")]
    Empty { what: &'static str },
    #[error(
        "{set} set: coverage factor {k} is below 1, which a DCC cannot state (D-SI's kValueType \
         starts at 1)"
    )]
    CoverageFactorBelowOne { set: &'static str, k: f64 },
    /// A number the record's own validation leaves unchecked is NaN or infinite, which
    /// D-SI's `decimalType` does not admit.
    #[error("{what} is {value}, not a finite number")]
    NotFinite { what: &'static str, value: f64 },
    /// XML Schema's `xs:date` has no year 0 nor negative years in the form written here.
    #[error("{what} {date} is before the year 1")]
    Date {
        what: &'static str,
        date: OffsetDateTime,
    },
}

/// Options a record does not carry.
#[derive(Debug, Clone)]
pub struct DccOptions {
    /// ISO 3166-1 alpha-2 code of the lab's country; `ZZ` (user-assigned) when unknown.
    pub country: String,
    /// The lab's contact address. None leaves `dcc:eMail` out, which DCC 3.2.1 allows; an
    /// empty element it does not.
    pub email: Option<String>,
    /// The writing software's release.
    pub software_release: String,
}

impl DccOptions {
    /// Checks what the schema constrains, so that a bad option is named before any record is
    /// read.
    pub fn check(&self) -> Result<(), DccError> {
        let c = &self.country;
        if !(c.len() == 2 && c.chars().all(|c| c.is_ascii_uppercase())) {
            return Err(DccError::Country(c.clone()));
        }
        if let Some(e) = &self.email {
            let well_formed = e
                .split_once('@')
                .is_some_and(|(name, domain)| !name.is_empty() && !domain.is_empty())
                && !e.chars().any(char::is_whitespace);
            if !well_formed {
                return Err(DccError::EMail(e.clone()));
            }
        }
        if nonblank(&self.software_release).is_none() {
            return Err(DccError::Empty {
                what: "the software release",
            });
        }
        Ok(())
    }
}

/// Text for XML character data and attribute values. Characters XML 1.0 cannot hold at all
/// (C0 controls other than tab and line breaks, U+FFFE, U+FFFF) become U+FFFD, since a JSON
/// record may carry them in a name and the document must still parse.
fn esc(s: &str) -> String {
    let mut out = String::with_capacity(s.len());
    for c in s.chars() {
        match c {
            '&' => out.push_str("&amp;"),
            '<' => out.push_str("&lt;"),
            '>' => out.push_str("&gt;"),
            '"' => out.push_str("&quot;"),
            '\t' | '\n' | '\r' => out.push(c),
            '\u{0}'..='\u{1f}' | '\u{fffe}' | '\u{ffff}' => out.push('\u{fffd}'),
            _ => out.push(c),
        }
    }
    out
}

/// `s` without surrounding blanks, or none when nothing is left: DCC's `notEmptyStringType`
/// admits neither an empty value nor leading or trailing white space.
fn nonblank(s: &str) -> Option<&str> {
    Some(s.trim()).filter(|t| !t.is_empty())
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

/// A value for D-SI's `decimalType` or `uncertaintyValueType`: the shortest digits that read
/// back as `v`. Callers pass finite numbers only (the record is validated first).
fn num(v: f64) -> String {
    format!("{v:e}")
}

/// A coverage factor or probability: D-SI's `kValueType` and `probabilityValueType` forbid
/// exponents, and `Display` writes the same shortest round-trip digits without one.
fn plain(v: f64) -> String {
    format!("{v}")
}

fn list(values: impl IntoIterator<Item = f64>, format: fn(f64) -> String) -> String {
    values.into_iter().map(format).collect::<Vec<_>>().join(" ")
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

/// The DCC document for `record`, valid against DCC 3.2.1 with D-SI 2.1.0; refused when the
/// record fails [`CalibrationRecord::validate`] or states something the schema cannot hold.
pub fn dcc_xml(record: &CalibrationRecord, options: &DccOptions) -> Result<String, DccError> {
    options.check()?;
    record.validate()?;
    let r = record;
    for (name, set) in [("static", &r.static_set), ("dynamic", &r.dynamic)] {
        if set.coverage_factor < 1.0 {
            return Err(DccError::CoverageFactorBelowOne {
                set: name,
                k: set.coverage_factor,
            });
        }
    }
    if let Some(t) = r.certificate.temperature_c.filter(|t| !t.is_finite()) {
        return Err(DccError::NotFinite {
            what: "the certificate's temperature",
            value: t,
        });
    }
    let certificate_id = nonblank(&r.certificate.id).ok_or(DccError::Empty {
        what: "the certificate id",
    })?;
    let dates = [r.static_set.calibrated_at, r.dynamic.calibrated_at];
    let (begin, end) = (
        dates.iter().min().copied().unwrap_or(r.issued_at),
        dates.iter().max().copied().unwrap_or(r.issued_at),
    );
    if begin.year() < 1 {
        return Err(DccError::Date {
            what: "the first calibration date",
            date: begin,
        });
    }
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
        esc(options.software_release.trim())
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
        esc(certificate_id),
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
    if let Some(m) = r.sensor.model.as_deref().and_then(nonblank) {
        let _ = write!(x, "<dcc:model>{}</dcc:model>", esc(m));
    }
    let _ = write!(
        x,
        "<dcc:identifications><dcc:identification><dcc:issuer>customer</dcc:issuer>\
         <dcc:value>{}</dcc:value></dcc:identification>",
        esc(r.sensor_id.as_str())
    );
    if let Some(s) = r.sensor.serial.as_deref().and_then(nonblank) {
        let _ = write!(
            x,
            "<dcc:identification><dcc:issuer>manufacturer</dcc:issuer>\
             <dcc:value>{}</dcc:value></dcc:identification>",
            esc(s)
        );
    }
    x.push_str("</dcc:identifications></dcc:item></dcc:items>\n");
    x.push_str("<dcc:calibrationLaboratory>");
    if let Some(a) = r.lab.accreditation.as_deref().and_then(nonblank) {
        let _ = write!(
            x,
            "<dcc:calibrationLaboratoryCode>{}</dcc:calibrationLaboratoryCode>",
            esc(a)
        );
    }
    x.push_str("<dcc:contact>");
    contact_fields(&mut x, &r.lab.name, options.email.as_deref());
    x.push_str("</dcc:contact></dcc:calibrationLaboratory>\n");
    x.push_str("<dcc:respPersons><dcc:respPerson><dcc:person>");
    text(
        &mut x,
        "name",
        r.lab
            .approved_by
            .as_deref()
            .unwrap_or("not stated in the calibration record"),
    );
    x.push_str("</dcc:person><dcc:mainSigner>true</dcc:mainSigner></dcc:respPerson></dcc:respPersons>\n<dcc:customer>");
    contact_fields(&mut x, "not stated in the calibration record", None);
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
    Ok(x)
}

fn contact_fields(x: &mut String, name: &str, email: Option<&str>) {
    text(x, "name", name);
    if let Some(e) = email {
        let _ = write!(x, "<dcc:eMail>{}</dcc:eMail>", esc(e));
    }
    x.push_str("<dcc:location><dcc:further><dcc:content lang=\"en\">not stated in the calibration record</dcc:content></dcc:further></dcc:location>");
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
    // A variance of -0.0 passes validation; its square root would be written "-0e0", which
    // uncertaintyValueType refuses.
    let sd = |i: usize| cov.map_or(0.0, |c| if c[i][i] > 0.0 { c[i][i].sqrt() } else { 0.0 });
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
            list(values, num),
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
            "</si:covarianceMatrix><si:coverageFactor>{}</si:coverageFactor>\
             <si:coverageProbability>{}</si:coverageProbability>\
             <si:distribution>normal</si:distribution>\
             </si:ellipsoidalRegionXMLList></si:realListXMLList></dcc:quantity></dcc:data>\
             </dcc:result>",
            plain(k),
            plain(p)
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
        list(set.uncertainty_mps2, num)
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
        list(
            [d.amplitude_max_mps2, d.frequency_min_hz, d.frequency_max_hz],
            num
        )
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
        list(values.iter().copied(), num),
        units.join(" "),
        list(expanded.iter().copied(), num),
        list(std::iter::repeat_n(k, n), plain),
        list(std::iter::repeat_n(p, n), plain),
    );
}

#[cfg(test)]
mod tests {
    use super::*;
    use triax_protocol::record::sample;

    fn options() -> DccOptions {
        DccOptions {
            country: "ZZ".into(),
            email: None,
            software_release: "0.1.0".into(),
        }
    }

    #[test]
    fn carries_the_records_numbers_and_escapes_its_text() {
        let mut r = sample::record("acc-01", 3);
        r.lab.name = "Lab <A> & Co\u{1}".into();
        let mut cov = [[0.0; 12]; 12];
        for (i, row) in cov.iter_mut().enumerate() {
            row[i] = 1e-6 * (i + 1) as f64;
        }
        r.static_set.covariance = Some(Box::new(cov));
        r.static_set.covariance_dof = Some(6.0);
        r.static_set.coverage_factor = 2.44691185114497;
        let x = dcc_xml(&r, &options()).unwrap();
        assert!(x.contains("Lab &lt;A&gt; &amp; Co\u{fffd}"));
        assert!(x.contains("<dcc:uniqueIdentifier>SAMPLE-acc-01-3</dcc:uniqueIdentifier>"));
        assert_eq!(
            x.matches("<si:covariance>").count(),
            144,
            "one 12×12 matrix"
        );
        assert!(x.contains("(6 degrees of freedom)"));
        // q_x's expanded uncertainty: k times √1e-5.
        assert!(x.contains(&num(2.44691185114497 * 1e-5f64.sqrt())), "{x}");
        assert!(x.contains("<si:coverageFactor>2.44691185114497</si:coverageFactor>"));
        assert!(x.contains("<si:coverageProbability>0.95</si:coverageProbability>"));
        assert_eq!(x.matches("<dcc:measurementResult>").count(), 2);
        assert!(!x.contains("eMail"), "no address, no element");
    }

    /// Display and LowerExp both give the shortest digits that parse back to the same bits.
    #[test]
    fn numbers_read_back_exactly_and_k_and_p_have_no_exponent() {
        for v in [
            2.44691185114497,
            0.95,
            1.0,
            9.999999999999998,
            0.1 + 0.2,
            1e-300,
        ] {
            assert_eq!(plain(v).parse::<f64>().unwrap().to_bits(), v.to_bits());
            assert!(!plain(v).contains('e'), "{}", plain(v));
            assert_eq!(num(v).parse::<f64>().unwrap().to_bits(), v.to_bits());
        }
    }

    #[test]
    fn an_address_is_written_and_bad_options_are_refused() {
        let r = sample::record("acc-01", 3);
        let x = dcc_xml(
            &r,
            &DccOptions {
                email: Some("calibration@lab.example".into()),
                ..options()
            },
        )
        .unwrap();
        assert_eq!(
            x.matches("<dcc:eMail>calibration@lab.example</dcc:eMail>")
                .count(),
            1,
            "the lab's, not the customer's"
        );
        for email in ["", " a@b.c", "lab", "@b.c", "a@", "a b@c.d"] {
            let o = DccOptions {
                email: Some(email.into()),
                ..options()
            };
            assert_eq!(dcc_xml(&r, &o), Err(DccError::EMail(email.into())));
        }
        let o = DccOptions {
            country: "de".into(),
            ..options()
        };
        assert_eq!(dcc_xml(&r, &o), Err(DccError::Country("de".into())));
        let o = DccOptions {
            software_release: " ".into(),
            ..options()
        };
        assert!(matches!(dcc_xml(&r, &o), Err(DccError::Empty { .. })));
    }

    #[test]
    fn what_the_schema_cannot_hold_is_refused_or_left_out() {
        let mut r = sample::record("acc-01", 3);
        r.dynamic.coverage_factor = 0.5;
        assert_eq!(
            dcc_xml(&r, &options()),
            Err(DccError::CoverageFactorBelowOne {
                set: "dynamic",
                k: 0.5
            })
        );
        let mut r = sample::record("acc-01", 3);
        r.certificate.id = " \t".into();
        assert!(matches!(
            dcc_xml(&r, &options()),
            Err(DccError::Empty { .. })
        ));
        let mut r = sample::record("acc-01", 3);
        r.certificate.temperature_c = Some(f64::NAN);
        assert!(matches!(
            dcc_xml(&r, &options()),
            Err(DccError::NotFinite { .. })
        ));
        let mut r = sample::record("acc-01", 3);
        r.static_set.offset[0] = f64::INFINITY;
        assert!(matches!(dcc_xml(&r, &options()), Err(DccError::Record(_))));
        let mut r = sample::record("acc-01", 3);
        r.sensor.model = Some("  ".into());
        r.sensor.serial = Some(" SN 12 ".into());
        let mut cov = [[0.0; 12]; 12];
        cov[9][9] = -0.0;
        r.static_set.covariance = Some(Box::new(cov));
        let x = dcc_xml(&r, &options()).unwrap();
        assert!(!x.contains("<dcc:model>"));
        assert!(x.contains("<dcc:value>SN 12</dcc:value>"));
        assert!(!x.contains("-0e0 "), "a negative zero uncertainty");
    }
}
