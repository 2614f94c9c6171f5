//! What an event leaves on disk beside its report, in `<state_dir>/<building>/events/<id>/`:
//!
//! | file | what |
//! |---|---|
//! | `report.json` | the signed report, as published (PROTOCOL.md §3.11) |
//! | `report.html` | the page ([`crate::html`]) |
//! | `parameters.csv`, `parameters.parquet` | every parameter of the report, one row each ([`rows`]) |
//! | `sds/` | the window's corrected data as miniSEED 2, an SDS archive (`triax_client::mseed`) |
//! | `stationxml.xml` | its StationXML, from the calibration records in force (`triax_client::stationxml`) |
//! | `plot.json` | the floors' acceleration as the page draws it, for a revised page |
//!
//! Each file is written whole or not at all (a temporary file renamed over its target).

use std::io::Write;
use std::path::Path;
use std::sync::Arc;

use parquet::basic::Compression;
use parquet::data_type::{ByteArray, ByteArrayType, DoubleType, Int32Type, Int64Type};
use parquet::file::properties::WriterProperties;
use parquet::file::writer::SerializedFileWriter;
use parquet::schema::parser::parse_message_type;
use triax_protocol::event::{EventParameter, EventReport};
use triax_protocol::messages::ModalDirection;

/// The files, by name, in the order the report lists them.
pub const REPORT_JSON: &str = "report.json";
pub const REPORT_HTML: &str = "report.html";
pub const PARAMETERS_CSV: &str = "parameters.csv";
pub const PARAMETERS_PARQUET: &str = "parameters.parquet";
pub const SDS_DIR: &str = "sds";
pub const STATIONXML: &str = "stationxml.xml";
pub const PLOT_JSON: &str = "plot.json";

/// Writes `bytes` to `path` whole or not at all.
pub fn write_whole(path: &Path, bytes: &[u8]) -> std::io::Result<()> {
    let dir = path.parent().unwrap_or(Path::new("."));
    std::fs::create_dir_all(dir)?;
    let mut tmp = tempfile::NamedTempFile::new_in(dir)?;
    tmp.write_all(bytes)?;
    tmp.as_file().sync_all()?;
    tmp.persist(path).map_err(|e| e.error)?;
    Ok(())
}

/// One parameter of a report.
#[derive(Debug, Clone, PartialEq)]
pub struct Row {
    /// The sensor, or the storey (`storey 0-3`) for a drift, or `building` for a frequency.
    pub item: String,
    pub floor: Option<i32>,
    pub parameter: &'static str,
    pub direction: String,
    pub period_s: Option<f64>,
    pub unit: &'static str,
    pub value: EventParameter,
}

fn dir(d: ModalDirection) -> &'static str {
    match d {
        ModalDirection::X => "x",
        ModalDirection::Y => "y",
        ModalDirection::Z => "z",
    }
}

/// Every parameter of `r`, one row each.
pub fn rows(r: &EventReport) -> Vec<Row> {
    let mut out = Vec::new();
    for s in &r.sensors {
        let id = s.sensor_id.to_string();
        let mut push = |parameter, direction: &str, period_s, unit, value: &EventParameter| {
            out.push(Row {
                item: id.clone(),
                floor: Some(s.floor),
                parameter,
                direction: direction.to_owned(),
                period_s,
                unit,
                value: *value,
            })
        };
        for a in &s.axes {
            let d = dir(a.direction);
            push("pga", d, None, "m/s^2", &a.pga_mps2);
            push("pgv", d, None, "m/s", &a.pgv_mps);
            push("pgd", d, None, "m", &a.pgd_m);
            push("arias", d, None, "m/s", &a.arias_mps);
            push("cav", d, None, "m/s", &a.cav_mps);
            if let Some(v) = &a.d5_95_s {
                push("d5_95", d, None, "s", v);
            }
        }
        push(
            "pga_rotd50",
            "horizontal",
            None,
            "m/s^2",
            &s.pga_rotd50_mps2,
        );
        push(
            "pga_rotd100",
            "horizontal",
            None,
            "m/s^2",
            &s.pga_rotd100_mps2,
        );
        for o in &s.spectrum {
            for (d, v) in [
                ("x", &o.x),
                ("y", &o.y),
                ("z", &o.z),
                ("rotd50", &o.rotd50),
                ("rotd100", &o.rotd100),
            ] {
                push("psa", d, Some(o.period_s), "m/s^2", v);
            }
        }
        for v in &s.vibration {
            push(
                "din4150_velocity",
                dir(v.direction),
                None,
                "mm/s",
                &v.peak_velocity_mmps,
            );
            if let Some(f) = &v.dominant_frequency_hz {
                push("din4150_frequency", dir(v.direction), None, "Hz", f);
            }
        }
        if let Some(t) = &s.tilt {
            push("residual_tilt_roll", "", None, "deg", &t.roll_change_deg);
            push("residual_tilt_pitch", "", None, "deg", &t.pitch_change_deg);
        }
    }
    for d in &r.drifts {
        out.push(Row {
            item: format!("storey {}-{}", d.lower_floor, d.upper_floor),
            floor: Some(d.upper_floor),
            parameter: "drift_ratio",
            direction: dir(d.direction).to_owned(),
            period_s: None,
            unit: "1",
            value: d.drift_ratio,
        });
    }
    out
}

fn csv_field(s: &str) -> String {
    if s.contains([',', '"', '\n']) {
        format!("\"{}\"", s.replace('"', "\"\""))
    } else {
        s.to_owned()
    }
}

fn opt(v: Option<f64>) -> String {
    v.filter(|x| x.is_finite())
        .map_or(String::new(), |x| format!("{x}"))
}

/// The rows as CSV, with a header; empty fields for absent values (ν infinite, no time).
pub fn csv(r: &EventReport, rows: &[Row]) -> String {
    let mut out = String::from(
        "building,event_id,item,floor,parameter,direction,period_s,unit,value,standard_uncertainty,dof,coverage_factor,coverage_probability,at_ns,angle_deg\n",
    );
    for row in rows {
        let v = &row.value;
        out += &format!(
            "{},{},{},{},{},{},{},{},{},{},{},{},{},{},{}\n",
            r.building,
            r.event_id,
            csv_field(&row.item),
            row.floor.map_or(String::new(), |f| f.to_string()),
            row.parameter,
            csv_field(&row.direction),
            opt(row.period_s),
            row.unit,
            v.value,
            v.standard_uncertainty,
            opt(Some(v.dof)),
            v.coverage_factor,
            v.coverage_probability,
            v.at_ns.map_or(String::new(), |t| t.to_string()),
            opt(v.angle_deg),
        );
    }
    out
}

const SCHEMA: &str = "message triax_event_parameters {
  required binary building (UTF8);
  required binary event_id (UTF8);
  required binary item (UTF8);
  optional int32 floor;
  required binary parameter (UTF8);
  required binary direction (UTF8);
  optional double period_s;
  required binary unit (UTF8);
  required double value;
  required double standard_uncertainty;
  optional double dof;
  required double coverage_factor;
  required double coverage_probability;
  optional int64 at (TIMESTAMP(NANOS,true));
  optional double angle_deg;
}";

fn texts(v: impl Iterator<Item = String>) -> Vec<ByteArray> {
    v.map(|s| ByteArray::from(s.into_bytes())).collect()
}

fn optional<T: Copy>(v: impl Iterator<Item = Option<T>>) -> (Vec<T>, Vec<i16>) {
    let mut values = Vec::new();
    let mut def = Vec::new();
    for x in v {
        def.push(i16::from(x.is_some()));
        values.extend(x);
    }
    (values, def)
}

/// The rows as one Parquet row group (the columns of the CSV; `at` a UTC timestamp).
pub fn parquet(r: &EventReport, rows: &[Row]) -> Result<Vec<u8>, parquet::errors::ParquetError> {
    let schema = Arc::new(parse_message_type(SCHEMA)?);
    let props = Arc::new(
        WriterProperties::builder()
            .set_compression(Compression::UNCOMPRESSED)
            .build(),
    );
    let mut buffer = Vec::new();
    {
        let mut file = SerializedFileWriter::new(&mut buffer, schema, props)?;
        let mut group = file.next_row_group()?;
        let n = rows.len();
        let mut column = 0;
        while let Some(mut c) = group.next_column()? {
            match column {
                0 => c.typed::<ByteArrayType>().write_batch(
                    &texts((0..n).map(|_| r.building.to_string())),
                    None,
                    None,
                )?,
                1 => c.typed::<ByteArrayType>().write_batch(
                    &texts((0..n).map(|_| r.event_id.to_string())),
                    None,
                    None,
                )?,
                2 => c.typed::<ByteArrayType>().write_batch(
                    &texts(rows.iter().map(|x| x.item.clone())),
                    None,
                    None,
                )?,
                3 => {
                    let (v, d) = optional(rows.iter().map(|x| x.floor));
                    c.typed::<Int32Type>().write_batch(&v, Some(&d), None)?
                }
                4 => c.typed::<ByteArrayType>().write_batch(
                    &texts(rows.iter().map(|x| x.parameter.to_owned())),
                    None,
                    None,
                )?,
                5 => c.typed::<ByteArrayType>().write_batch(
                    &texts(rows.iter().map(|x| x.direction.clone())),
                    None,
                    None,
                )?,
                6 => {
                    let (v, d) = optional(rows.iter().map(|x| x.period_s));
                    c.typed::<DoubleType>().write_batch(&v, Some(&d), None)?
                }
                7 => c.typed::<ByteArrayType>().write_batch(
                    &texts(rows.iter().map(|x| x.unit.to_owned())),
                    None,
                    None,
                )?,
                8 => c.typed::<DoubleType>().write_batch(
                    &rows.iter().map(|x| x.value.value).collect::<Vec<_>>(),
                    None,
                    None,
                )?,
                9 => c.typed::<DoubleType>().write_batch(
                    &rows
                        .iter()
                        .map(|x| x.value.standard_uncertainty)
                        .collect::<Vec<_>>(),
                    None,
                    None,
                )?,
                10 => {
                    let (v, d) = optional(
                        rows.iter()
                            .map(|x| Some(x.value.dof).filter(|f| f.is_finite())),
                    );
                    c.typed::<DoubleType>().write_batch(&v, Some(&d), None)?
                }
                11 => c.typed::<DoubleType>().write_batch(
                    &rows
                        .iter()
                        .map(|x| x.value.coverage_factor)
                        .collect::<Vec<_>>(),
                    None,
                    None,
                )?,
                12 => c.typed::<DoubleType>().write_batch(
                    &rows
                        .iter()
                        .map(|x| x.value.coverage_probability)
                        .collect::<Vec<_>>(),
                    None,
                    None,
                )?,
                13 => {
                    let (v, d) = optional(rows.iter().map(|x| x.value.at_ns));
                    c.typed::<Int64Type>().write_batch(&v, Some(&d), None)?
                }
                _ => {
                    let (v, d) = optional(rows.iter().map(|x| x.value.angle_deg));
                    c.typed::<DoubleType>().write_batch(&v, Some(&d), None)?
                }
            };
            c.close()?;
            column += 1;
        }
        group.close()?;
        file.close()?;
    }
    Ok(buffer)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rows_csv_and_parquet_of_a_report() {
        let r = triax_protocol::event::sample::report("hq", "20270115T080112Z");
        let rows = rows(&r);
        // Three directions of six parameters, two RotD, one period of five ordinates.
        assert_eq!(rows.len(), 3 * 6 + 2 + 5);
        let text = csv(&r, &rows);
        assert_eq!(text.lines().count(), rows.len() + 1);
        let line = text.lines().find(|l| l.contains(",pga,x,")).unwrap();
        assert!(
            line.starts_with("hq,20270115T080112Z,roof,5,pga,x,,m/s^2,1.2,0.01,,1.96,0.95,"),
            "{line}"
        );
        let bytes = parquet(&r, &rows).unwrap();
        assert_eq!(&bytes[..4], b"PAR1");
        assert_eq!(&bytes[bytes.len() - 4..], b"PAR1");
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("x").join("f.csv");
        write_whole(&p, text.as_bytes()).unwrap();
        assert_eq!(std::fs::read_to_string(&p).unwrap(), text);
    }
}
