//! FDSN StationXML 1.2 for the channels [`crate::mseed`] writes, from the calibration records.
//!
//! One station per sensor (its code from the SDS export), nine channels per calibration
//! version: an epoch per version from `valid_from` to the record's `valid_until` or the next
//! version's `valid_from`, whichever is first. The corrected data are already in m/s², so the
//! response is unity, m/s² in and out; the uncertainty channels (location `U0`) are in m/s²
//! too, and the flag channels (`Q0`) carry bit fields. Each epoch's comments name the
//! certificate, the lab, the version and the set, and say what StationXML cannot: the
//! cross-axis terms of S (FDSN StationXML issue #111), the per-sample uncertainty and the
//! degrees of freedom, for which the record itself is the reference.
//!
//! Coordinates are not part of a calibration record: stations and channels carry latitude,
//! longitude and elevation 0 with a comment saying so, since the schema requires them.

use std::collections::BTreeMap;
use std::fmt::Write;

use time::format_description::well_known::Rfc3339;
use time::OffsetDateTime;
use triax_protocol::record::CalibrationRecord;
use triax_protocol::{BuildingId, SensorId};

use crate::mseed::{channel_code, channels, ChannelKind};

/// XML text with `&`, `<`, `>` and quotes escaped.
fn esc(s: &str) -> String {
    s.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
        .replace('"', "&quot;")
        .replace('\'', "&apos;")
}

fn date(t: OffsetDateTime) -> String {
    // A calibration record's times are RFC 3339 already; formatting one cannot fail.
    t.format(&Rfc3339).unwrap_or_default()
}

/// The StationXML document for `records` (any versions, any order) of the sensors in
/// `stations` (sensor → station code), sampled at `sample_rates_hz` (sensor → rate; a sensor
/// without one gets no `SampleRate`). Records of sensors not in `stations` are left out.
pub fn stationxml(
    network: &str,
    building: &BuildingId,
    stations: &BTreeMap<SensorId, String>,
    sample_rates_hz: &BTreeMap<SensorId, f64>,
    records: &[CalibrationRecord],
    created: OffsetDateTime,
) -> String {
    let mut by_sensor: BTreeMap<&SensorId, Vec<&CalibrationRecord>> = BTreeMap::new();
    for r in records {
        if stations.contains_key(&r.sensor_id) {
            by_sensor.entry(&r.sensor_id).or_default().push(r);
        }
    }
    for list in by_sensor.values_mut() {
        list.sort_by_key(|r| r.version);
        list.dedup_by_key(|r| r.version);
    }
    let earliest = by_sensor
        .values()
        .flat_map(|l| l.iter().map(|r| r.valid_from))
        .min();
    let mut x = String::new();
    let _ = write!(
        x,
        "<?xml version=\"1.0\" encoding=\"UTF-8\"?>\n\
         <FDSNStationXML xmlns=\"http://www.fdsn.org/xml/station/1\" schemaVersion=\"1.2\">\n\
         <Source>Triax</Source>\n<Sender>Triax</Sender>\n<Module>triax-export</Module>\n\
         <Created>{}</Created>\n<Network code=\"{}\"{}>\n\
         <Description>Triax building {}: corrected accelerations in m/s²</Description>\n",
        date(created),
        esc(network),
        earliest.map_or(String::new(), |t| format!(" startDate=\"{}\"", date(t))),
        esc(building.as_str())
    );
    for (sensor, list) in &by_sensor {
        let station = &stations[*sensor];
        let first = list[0];
        let _ = write!(
            x,
            "<Station code=\"{}\" startDate=\"{}\">\n\
             <Comment><Value>Triax sensor {} of building {}</Value></Comment>\n\
             <Comment><Value>Coordinates are not in a calibration record: latitude, longitude \
             and elevation are given as 0.</Value></Comment>\n\
             <Latitude>0</Latitude>\n<Longitude>0</Longitude>\n<Elevation>0</Elevation>\n\
             <Site><Name>{} {}</Name></Site>\n",
            esc(station),
            date(first.valid_from),
            esc(sensor.as_str()),
            esc(building.as_str()),
            esc(building.as_str()),
            esc(sensor.as_str())
        );
        for (i, r) in list.iter().enumerate() {
            let end = match (r.valid_until, list.get(i + 1).map(|n| n.valid_from)) {
                (Some(a), Some(b)) => Some(a.min(b)),
                (a, b) => a.or(b),
            };
            for c in channels() {
                channel(&mut x, r, c, end, sample_rates_hz.get(*sensor).copied());
            }
        }
        x.push_str("</Station>\n");
    }
    x.push_str("</Network>\n</FDSNStationXML>\n");
    x
}

fn channel(
    x: &mut String,
    r: &CalibrationRecord,
    c: crate::mseed::Channel,
    end: Option<OffsetDateTime>,
    rate_hz: Option<f64>,
) {
    let code = channel_code(rate_hz.unwrap_or(100.0), c.axis);
    let (what, unit, unit_text) = match c.kind {
        ChannelKind::AccelerationMps2 => (
            "corrected acceleration",
            "M/S**2",
            "acceleration, m/s² (already corrected: unity response)",
        ),
        ChannelKind::UncertaintyMps2 => (
            "standard uncertainty (k = 1) of the corrected acceleration at location 00",
            "M/S**2",
            "acceleration, m/s²",
        ),
        ChannelKind::Flags => (
            "quality flags of each sample, bits of PROTOCOL.md §2.3",
            "FLAGS",
            "bit field, no unit",
        ),
    };
    let axis = ["x", "y", "z"][c.axis];
    let _ = write!(
        x,
        "<Channel code=\"{code}\" locationCode=\"{}\" startDate=\"{}\"{}>\n\
         <Comment><Value>{what}, sensor axis {axis}; calibration version {}, certificate {}, \
         lab {}, issued {}</Value></Comment>\n\
         <Comment><Value>The record's sensitivity matrix has cross-axis terms StationXML cannot \
         express (FDSN StationXML issue #111), nor the per-sample uncertainty, the degrees of \
         freedom or a temperature model: the calibration record (sensor {}, version {}) is the \
         reference.</Value></Comment>\n\
         <Latitude>0</Latitude>\n<Longitude>0</Longitude>\n<Elevation>0</Elevation>\n\
         <Depth>0</Depth>\n{}\
         <Sensor><Type>three-axis MEMS accelerometer, Triax-corrected</Type>{}{}</Sensor>\n\
         <Response><InstrumentSensitivity><Value>1</Value><Frequency>1</Frequency>\
         <InputUnits><Name>{unit}</Name><Description>{unit_text}</Description></InputUnits>\
         <OutputUnits><Name>{unit}</Name><Description>{unit_text}</Description></OutputUnits>\
         </InstrumentSensitivity></Response>\n</Channel>\n",
        c.location,
        date(r.valid_from),
        end.map_or(String::new(), |t| format!(" endDate=\"{}\"", date(t))),
        r.version,
        esc(&r.certificate.id),
        esc(&r.lab.name),
        date(r.issued_at),
        esc(r.sensor_id.as_str()),
        r.version,
        rate_hz.map_or(String::new(), |f| format!("<SampleRate>{f}</SampleRate>\n")),
        r.sensor
            .model
            .as_deref()
            .map_or(String::new(), |m| format!("<Model>{}</Model>", esc(m))),
        r.sensor
            .serial
            .as_deref()
            .map_or(String::new(), |m| format!(
                "<SerialNumber>{}</SerialNumber>",
                esc(m)
            )),
    );
}

#[cfg(test)]
mod tests {
    use super::*;
    use triax_protocol::record::sample;

    #[test]
    fn epochs_follow_the_versions() {
        let mut v1 = sample::record("acc-01", 1);
        v1.lab.name = "Lab <A> & Co".into();
        let mut v2 = sample::record("acc-01", 2);
        v2.valid_from = v1.valid_from + time::Duration::days(30);
        let other = sample::record("acc-02", 1);
        let stations = BTreeMap::from([(v1.sensor_id.clone(), "ACC01".to_string())]);
        let rates = BTreeMap::from([(v1.sensor_id.clone(), 100.0)]);
        let x = stationxml(
            "XX",
            &BuildingId::new("hq").unwrap(),
            &stations,
            &rates,
            &[v2.clone(), v1.clone(), other],
            v1.issued_at,
        );
        assert_eq!(
            x.matches("<Channel ").count(),
            18,
            "nine channels per version"
        );
        assert_eq!(x.matches("<Station ").count(), 1, "acc-02 has no station");
        assert!(x.contains("endDate=\"2026-01-31T00:00:00Z\""), "{x}");
        assert!(x.contains("Lab &lt;A&gt; &amp; Co"));
        assert!(x.contains("locationCode=\"U0\""));
        assert!(x.contains("<SampleRate>100</SampleRate>"));
        assert!(x.contains("issue #111"));
    }
}
