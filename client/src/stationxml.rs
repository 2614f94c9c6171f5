//! FDSN StationXML 1.2 for the channels [`crate::mseed`] writes, from the calibration records.
//!
//! One station per sensor (its code from the SDS export), nine channels per stretch of the
//! exported data corrected with one calibration version ([`Run`]): an epoch describes exactly
//! the samples inside it, so it runs from the stretch's first sample to just before the next
//! stretch's first sample (one microsecond before, miniSEED's resolution), and the last one
//! to the record's `valid_until` when that is later than its last sample, else open. The
//! record's own `valid_from` does not cut the epochs: the gateway switches versions when it
//! receives a record, and the data follow the switch. The corrected data are already in m/s²,
//! so the response is unity, m/s² in and out, as one unity stage, which ObsPy's
//! `remove_response` and `remove_sensitivity` need; the uncertainty channels (location `U0`)
//! are in m/s² too, and the flag channels (`Q0`) carry bit fields. Each epoch's comments name the
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

use crate::mseed::{channel_code, channels, ChannelKind, Run};

/// Why a StationXML document cannot describe the data.
#[derive(Debug, thiserror::Error)]
pub enum StationXmlError {
    #[error("sensor {sensor}: its data were corrected with calibration version {version}, and no record given with --records is that version")]
    MissingRecord { sensor: SensorId, version: u64 },
}

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

/// The StationXML document for the exported stretches `runs` (sensor → stretches in time
/// order) of the sensors in `stations` (sensor → station code), sampled at `sample_rates_hz`
/// (sensor → rate; a sensor without one gets no `SampleRate`), with the calibration records
/// `records` (any versions, any order; each stretch's version must be among them).
pub fn stationxml(
    network: &str,
    building: &BuildingId,
    stations: &BTreeMap<SensorId, String>,
    sample_rates_hz: &BTreeMap<SensorId, f64>,
    runs: &BTreeMap<SensorId, Vec<Run>>,
    records: &[CalibrationRecord],
    created: OffsetDateTime,
) -> Result<String, StationXmlError> {
    let record = |sensor: &SensorId, version: u64| {
        records
            .iter()
            .find(|r| &r.sensor_id == sensor && r.version == version)
            .ok_or_else(|| StationXmlError::MissingRecord {
                sensor: sensor.clone(),
                version,
            })
    };
    let mut epochs: Vec<(&SensorId, Vec<Epoch>)> = Vec::new();
    for (sensor, list) in runs {
        if !stations.contains_key(sensor) || list.is_empty() {
            continue;
        }
        let mut e = Vec::with_capacity(list.len());
        for (i, run) in list.iter().enumerate() {
            let r = record(sensor, run.version)?;
            let end_ns = match list.get(i + 1) {
                // The next stretch's first sample, less a microsecond, so that no sample falls
                // in two epochs.
                Some(next) => Some(floor_us(next.first_ns) - 1000),
                None => r
                    .valid_until
                    .map(|t| t.unix_timestamp_nanos())
                    .filter(|&t| t > i128::from(run.last_ns))
                    .and_then(|t| i64::try_from(t).ok()),
            };
            e.push(Epoch {
                record: r,
                start_ns: floor_us(run.first_ns),
                end_ns,
            });
        }
        epochs.push((sensor, e));
    }
    let earliest = epochs.iter().map(|(_, e)| e[0].start_ns).min();
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
        earliest.map_or(String::new(), |t| format!(" startDate=\"{}\"", date_ns(t))),
        esc(building.as_str())
    );
    for (sensor, list) in &epochs {
        let station = &stations[*sensor];
        let _ = write!(
            x,
            "<Station code=\"{}\" startDate=\"{}\">\n\
             <Comment><Value>Triax sensor {} of building {}</Value></Comment>\n\
             <Comment><Value>Coordinates are not in a calibration record: latitude, longitude \
             and elevation are given as 0.</Value></Comment>\n\
             <Latitude>0</Latitude>\n<Longitude>0</Longitude>\n<Elevation>0</Elevation>\n\
             <Site><Name>{} {}</Name></Site>\n",
            esc(station),
            date_ns(list[0].start_ns),
            esc(sensor.as_str()),
            esc(building.as_str()),
            esc(building.as_str()),
            esc(sensor.as_str())
        );
        for e in list {
            for c in channels() {
                channel(&mut x, e, c, sample_rates_hz.get(*sensor).copied());
            }
        }
        x.push_str("</Station>\n");
    }
    x.push_str("</Network>\n</FDSNStationXML>\n");
    Ok(x)
}

/// One epoch: a stretch of data and the record that corrected it.
struct Epoch<'a> {
    record: &'a CalibrationRecord,
    start_ns: i64,
    end_ns: Option<i64>,
}

fn floor_us(t_ns: i64) -> i64 {
    t_ns.div_euclid(1000) * 1000
}

/// An instant to the microsecond, RFC 3339 in UTC.
fn date_ns(t_ns: i64) -> String {
    date(
        OffsetDateTime::from_unix_timestamp_nanos(i128::from(floor_us(t_ns)))
            .unwrap_or(OffsetDateTime::UNIX_EPOCH),
    )
}

fn channel(x: &mut String, e: &Epoch, c: crate::mseed::Channel, rate_hz: Option<f64>) {
    let r = e.record;
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
         </InstrumentSensitivity>\n\
         <Stage number=\"1\"><PolesZeros>\
         <InputUnits><Name>{unit}</Name></InputUnits><OutputUnits><Name>{unit}</Name></OutputUnits>\
         <PzTransferFunctionType>LAPLACE (RADIANS/SECOND)</PzTransferFunctionType>\
         <NormalizationFactor>1</NormalizationFactor><NormalizationFrequency>1</NormalizationFrequency>\
         </PolesZeros><StageGain><Value>1</Value><Frequency>1</Frequency></StageGain></Stage>\n\
         </Response>\n</Channel>\n",
        c.location,
        date_ns(e.start_ns),
        e.end_ns.map_or(String::new(), |t| format!(" endDate=\"{}\"", date_ns(t))),
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

    /// Epochs cut where the data changed version, not at the records' `valid_from`; the
    /// last one open; a version without a record refused by name.
    #[test]
    fn epochs_follow_the_data() {
        let mut v1 = sample::record("acc-01", 1);
        v1.lab.name = "Lab <A> & Co".into();
        let mut v2 = sample::record("acc-01", 2);
        v2.valid_from = v1.valid_from + time::Duration::days(30);
        let other = sample::record("acc-02", 1);
        let sensor = v1.sensor_id.clone();
        let stations = BTreeMap::from([(sensor.clone(), "ACC01".to_string())]);
        let rates = BTreeMap::from([(sensor.clone(), 100.0)]);
        // 2026-11-25T12:00:00Z, v1 for 10 s, then v2 (pushed 20 s after its valid_from).
        let t0 = 1_795_608_000_000_000_000i64;
        let switch = t0 + 10_000_000_000 + 123_456;
        let runs = BTreeMap::from([(
            sensor.clone(),
            vec![
                Run {
                    version: 1,
                    first_ns: t0,
                    last_ns: switch - 10_000_000,
                },
                Run {
                    version: 2,
                    first_ns: switch,
                    last_ns: switch + 5_000_000_000,
                },
            ],
        )]);
        let records = [v2.clone(), v1.clone(), other];
        let hq = BuildingId::new("hq").unwrap();
        let x = stationxml("XX", &hq, &stations, &rates, &runs, &records, v1.issued_at).unwrap();
        assert_eq!(
            x.matches("<Channel ").count(),
            18,
            "nine channels per stretch"
        );
        assert_eq!(x.matches("<Station ").count(), 1, "acc-02 has no station");
        assert!(x.contains("startDate=\"2026-11-25T12:00:00Z\""), "{x}");
        assert!(x.contains("endDate=\"2026-11-25T12:00:10.000122Z\""), "{x}");
        assert!(
            x.contains("startDate=\"2026-11-25T12:00:10.000123Z\""),
            "{x}"
        );
        assert_eq!(x.matches("endDate=").count(), 9, "the last epoch is open");
        assert!(x.contains("Lab &lt;A&gt; &amp; Co"));
        assert!(x.contains("locationCode=\"U0\""));
        assert!(x.contains("<SampleRate>100</SampleRate>"));
        assert!(x.contains("issue #111"));
        assert_eq!(x.matches("<Stage number=\"1\">").count(), 18);
        let e = stationxml("XX", &hq, &stations, &rates, &runs, &[v1], v2.issued_at).unwrap_err();
        assert!(e.to_string().contains("version 2"), "{e}");
        assert!(e.to_string().contains("acc-01"), "{e}");
    }
}
