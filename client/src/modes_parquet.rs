//! A building's modes record (`triax/<building>/modes` messages, PROTOCOL.md §3.10) as an
//! Apache Parquet file, one row per identified mode per window, for pandas, pyarrow, Polars or
//! DuckDB.
//!
//! Columns (an estimate's `value`, standard uncertainty `u` (k = 1), degrees of freedom `dof`
//! (null when infinite) and coverage factor `k` are four columns; `value ± k·u` claims
//! `coverage_probability`):
//!
//! | column | Parquet type | meaning |
//! |---|---|---|
//! | `building` | BYTE_ARRAY, UTF8 | |
//! | `window_start`, `window_end` | INT64, TIMESTAMP(NANOS, UTC) | the window's grid, end exclusive |
//! | `track` | INT64, optional | the track the mode joined; null when the window was not tracked |
//! | `direction` | BYTE_ARRAY, UTF8 | `x`, `y` or `z`: where most of the shape's energy is |
//! | `frequency_hz`, `frequency_u_hz`, `frequency_dof`, `frequency_k` | DOUBLE | natural frequency |
//! | `damping_ratio`, `damping_u`, `damping_dof`, `damping_k` | DOUBLE | fraction of critical |
//! | `coverage_probability` | DOUBLE | of every interval of the row but the residual's |
//! | `mac_previous` | DOUBLE, optional | MAC of the mode shape with the same track's shape in the previous window of the file (null for a track's first) |
//! | `order`, `stable_orders`, `replicates` | INT32 | model order, orders stable at, jackknife replicates |
//! | `temperature_c` | DOUBLE, optional | the window's mean temperature |
//! | `predicted_hz` | DOUBLE, optional | the track's environmental baseline; null while training |
//! | `residual_relative`, `residual_u`, `residual_k` | DOUBLE, optional | `(f − predicted)/predicted` and its guard band |
//! | `verdict`, `block_verdict` | BYTE_ARRAY, UTF8, optional | `training`, `normal`, `possible`, `shift` |
//! | `reference_component` | INT32 | index in the shape lists of the component that is exactly 1 |
//! | `reference_sensor` | BYTE_ARRAY, UTF8 | its sensor |
//! | `shape_sensor`, `shape_direction` | LIST of UTF8 | per component: sensor and building direction |
//! | `shape_real`, `shape_real_u`, `shape_real_k` | LIST of DOUBLE | the mode shape (in-phase parts) and its intervals |
//! | `shape_imag`, `shape_imag_u`, `shape_imag_k` | LIST of DOUBLE | the quadrature parts |
//! | `late` | BOOLEAN | some of the window's batches were read back from the history |
//!
//! Refused windows have no modes and give no row. The file's key-value metadata names the
//! format (`triax.format` = `triax-building-modes/1`) and the units (`triax.units`).

use std::collections::HashMap;
use std::io::Write;
use std::sync::Arc;

use ::parquet::basic::Compression;
use ::parquet::data_type::{BoolType, ByteArray, ByteArrayType, DoubleType, Int32Type, Int64Type};
use ::parquet::file::metadata::KeyValue;
use ::parquet::file::properties::WriterProperties;
use ::parquet::file::writer::SerializedFileWriter;
use ::parquet::schema::parser::parse_message_type;
use triax_protocol::messages::{
    BuildingModes, ModalDirection, ModalEstimate, ModalVerdict, ModeReport,
};

pub use crate::parquet::ParquetExportError;

/// The schema, in Parquet's message syntax (columns in the order [`ModesParquetWriter`]
/// writes them).
const SCHEMA: &str = "message triax_building_modes {
  required binary building (UTF8);
  required int64 window_start (TIMESTAMP(NANOS,true));
  required int64 window_end (TIMESTAMP(NANOS,true));
  optional int64 track;
  required binary direction (UTF8);
  required double frequency_hz;
  required double frequency_u_hz;
  optional double frequency_dof;
  required double frequency_k;
  required double damping_ratio;
  required double damping_u;
  optional double damping_dof;
  required double damping_k;
  required double coverage_probability;
  optional double mac_previous;
  required int32 order;
  required int32 stable_orders;
  required int32 replicates;
  optional double temperature_c;
  optional double predicted_hz;
  optional double residual_relative;
  optional double residual_u;
  optional double residual_k;
  optional binary verdict (UTF8);
  optional binary block_verdict (UTF8);
  required int32 reference_component;
  required binary reference_sensor (UTF8);
  required group shape_sensor (LIST) { repeated group list { required binary element (UTF8); } }
  required group shape_direction (LIST) { repeated group list { required binary element (UTF8); } }
  required group shape_real (LIST) { repeated group list { required double element; } }
  required group shape_real_u (LIST) { repeated group list { required double element; } }
  required group shape_real_k (LIST) { repeated group list { required double element; } }
  required group shape_imag (LIST) { repeated group list { required double element; } }
  required group shape_imag_u (LIST) { repeated group list { required double element; } }
  required group shape_imag_k (LIST) { repeated group list { required double element; } }
  required boolean late;
}";

/// One column's values and, for optional and list columns, its levels.
#[derive(Default)]
struct Column<T> {
    values: Vec<T>,
    definition: Vec<i16>,
    repetition: Vec<i16>,
}

impl<T> Column<T> {
    fn required(&mut self, v: T) {
        self.values.push(v);
    }

    fn optional(&mut self, v: Option<T>) {
        self.definition.push(i16::from(v.is_some()));
        self.values.extend(v);
    }

    /// A list of required elements: an empty list is one level pair with no value.
    fn list(&mut self, items: impl IntoIterator<Item = T>) {
        let before = self.values.len();
        for (i, v) in items.into_iter().enumerate() {
            self.values.push(v);
            self.definition.push(1);
            self.repetition.push(i16::from(i > 0));
        }
        if self.values.len() == before {
            self.definition.push(0);
            self.repetition.push(0);
        }
    }

    fn levels(&self) -> (Option<&[i16]>, Option<&[i16]>) {
        let d = (!self.definition.is_empty()).then_some(&self.definition[..]);
        let r = (!self.repetition.is_empty()).then_some(&self.repetition[..]);
        (d, r)
    }
}

#[derive(Default)]
struct Rows {
    text: Vec<Column<ByteArray>>,
    int64: Vec<Column<i64>>,
    int32: Vec<Column<i32>>,
    double: Vec<Column<f64>>,
    boolean: Vec<Column<bool>>,
    /// Per schema column: which vector and index it is in.
    layout: Vec<(Kind, usize)>,
    count: u64,
}

#[derive(Clone, Copy)]
enum Kind {
    Text,
    Int64,
    Int32,
    Double,
    Boolean,
}

/// Writes a building's modes to a Parquet file, row by row, whole at [`finish`](Self::finish).
/// A record holds at most twice the service's `record_max_windows` windows, a few hundred
/// thousand rows: they are kept in memory and written as one row group.
pub struct ModesParquetWriter<W: Write + Send> {
    file: SerializedFileWriter<W>,
    rows: Rows,
    /// Per track, the previous window's mode shape (for `mac_previous`).
    previous: HashMap<u64, Vec<f64>>,
}

fn direction_name(d: ModalDirection) -> &'static str {
    match d {
        ModalDirection::X => "x",
        ModalDirection::Y => "y",
        ModalDirection::Z => "z",
    }
}

fn verdict_name(v: ModalVerdict) -> &'static str {
    match v {
        ModalVerdict::Training => "training",
        ModalVerdict::Normal => "normal",
        ModalVerdict::Possible => "possible",
        ModalVerdict::Shift => "shift",
    }
}

fn finite(v: f64) -> Option<f64> {
    v.is_finite().then_some(v)
}

/// MAC of two real shapes: `(aᵀb)² / (aᵀa · bᵀb)`.
fn mac(a: &[f64], b: &[f64]) -> Option<f64> {
    if a.len() != b.len() {
        return None;
    }
    let ab: f64 = a.iter().zip(b).map(|(x, y)| x * y).sum();
    let aa: f64 = a.iter().map(|x| x * x).sum();
    let bb: f64 = b.iter().map(|x| x * x).sum();
    (aa > 0.0 && bb > 0.0).then(|| ab * ab / (aa * bb))
}

impl<W: Write + Send> ModesParquetWriter<W> {
    pub fn new(out: W) -> Result<ModesParquetWriter<W>, ParquetExportError> {
        let schema = Arc::new(parse_message_type(SCHEMA)?);
        let props = WriterProperties::builder()
            .set_compression(Compression::UNCOMPRESSED)
            .set_key_value_metadata(Some(vec![
                KeyValue::new(
                    "triax.format".to_owned(),
                    "triax-building-modes/1".to_owned(),
                ),
                KeyValue::new(
                    "triax.units".to_owned(),
                    "window_start, window_end: ns since the Unix epoch (UTC); frequency_*: Hz; \
                     damping_*, residual_*, shape_*: dimensionless (shapes relative to the \
                     reference component); *_u: standard uncertainty (k = 1), the interval is \
                     value ± k·u; temperature_c: °C (PROTOCOL.md §3.10)"
                        .to_owned(),
                ),
            ]))
            .build();
        let file = SerializedFileWriter::new(out, schema.clone(), Arc::new(props))?;
        let mut rows = Rows::default();
        // The layout follows the schema's leaves: one column vector per leaf, by type.
        for field in schema.get_fields() {
            let leaf = if field.is_group() {
                // LIST → repeated group list → element.
                field.get_fields()[0].get_fields()[0].clone()
            } else {
                field.clone()
            };
            let kind = match leaf.get_physical_type() {
                ::parquet::basic::Type::BYTE_ARRAY => Kind::Text,
                ::parquet::basic::Type::INT64 => Kind::Int64,
                ::parquet::basic::Type::INT32 => Kind::Int32,
                ::parquet::basic::Type::BOOLEAN => Kind::Boolean,
                _ => Kind::Double,
            };
            let index = match kind {
                Kind::Text => push_index(&mut rows.text),
                Kind::Int64 => push_index(&mut rows.int64),
                Kind::Int32 => push_index(&mut rows.int32),
                Kind::Double => push_index(&mut rows.double),
                Kind::Boolean => push_index(&mut rows.boolean),
            };
            rows.layout.push((kind, index));
        }
        Ok(ModesParquetWriter {
            file,
            rows,
            previous: HashMap::new(),
        })
    }

    /// Adds one window's modes (none for a refused window). Windows should come in time order,
    /// which `mac_previous` assumes.
    pub fn push(&mut self, window: &BuildingModes) {
        for mode in &window.modes {
            self.push_mode(window, mode);
        }
    }

    fn push_mode(&mut self, w: &BuildingModes, m: &ModeReport) {
        let shape: Vec<f64> = m.shape.iter().map(|c| c.real.value).collect();
        let mac_previous = m
            .track
            .and_then(|t| self.previous.insert(t, shape.clone()))
            .and_then(|before| mac(&before, &shape));
        let text = |s: &str| ByteArray::from(s);
        let r = &mut self.rows;
        let (t, i64c, i32c, d, b) = (
            &mut r.text,
            &mut r.int64,
            &mut r.int32,
            &mut r.double,
            &mut r.boolean,
        );
        let estimate = |d: &mut Vec<Column<f64>>, at: usize, e: &ModalEstimate| {
            d[at].required(e.value);
            d[at + 1].required(e.standard_uncertainty);
            d[at + 2].optional(finite(e.dof));
            d[at + 3].required(e.coverage_factor);
        };
        t[0].required(text(w.building.as_str()));
        i64c[0].required(w.window_start_ns);
        i64c[1].required(w.window_end_ns);
        i64c[2].optional(m.track.map(|v| v as i64));
        t[1].required(text(direction_name(m.direction)));
        estimate(d, 0, &m.frequency_hz);
        estimate(d, 4, &m.damping_ratio);
        d[8].required(m.frequency_hz.coverage_probability);
        d[9].optional(mac_previous);
        i32c[0].required(m.order as i32);
        i32c[1].required(m.stable_orders as i32);
        i32c[2].required(m.replicates as i32);
        d[10].optional(w.temperature_c);
        d[11].optional(m.predicted_hz);
        d[12].optional(m.residual_relative.map(|e| e.value));
        d[13].optional(m.residual_relative.map(|e| e.standard_uncertainty));
        d[14].optional(m.residual_relative.map(|e| e.coverage_factor));
        t[2].optional(m.verdict.map(|v| text(verdict_name(v))));
        t[3].optional(m.block_verdict.map(|v| text(verdict_name(v))));
        i32c[3].required(m.reference_component as i32);
        t[4].required(text(
            m.shape
                .get(m.reference_component)
                .map_or("", |c| c.sensor_id.as_str()),
        ));
        t[5].list(m.shape.iter().map(|c| text(c.sensor_id.as_str())));
        t[6].list(m.shape.iter().map(|c| text(direction_name(c.direction))));
        d[15].list(m.shape.iter().map(|c| c.real.value));
        d[16].list(m.shape.iter().map(|c| c.real.standard_uncertainty));
        d[17].list(m.shape.iter().map(|c| c.real.coverage_factor));
        d[18].list(m.shape.iter().map(|c| c.imag.value));
        d[19].list(m.shape.iter().map(|c| c.imag.standard_uncertainty));
        d[20].list(m.shape.iter().map(|c| c.imag.coverage_factor));
        b[0].required(w.late);
        r.count += 1;
    }

    /// Writes the rows and the footer; returns the rows written.
    pub fn finish(mut self) -> Result<u64, ParquetExportError> {
        let r = std::mem::take(&mut self.rows);
        if r.count > 0 {
            let mut group = self.file.next_row_group()?;
            let mut column = 0;
            while let Some(mut c) = group.next_column()? {
                let (kind, at) = r.layout[column];
                match kind {
                    Kind::Text => {
                        let (d, rep) = r.text[at].levels();
                        c.typed::<ByteArrayType>()
                            .write_batch(&r.text[at].values, d, rep)?
                    }
                    Kind::Int64 => {
                        let (d, rep) = r.int64[at].levels();
                        c.typed::<Int64Type>()
                            .write_batch(&r.int64[at].values, d, rep)?
                    }
                    Kind::Int32 => {
                        let (d, rep) = r.int32[at].levels();
                        c.typed::<Int32Type>()
                            .write_batch(&r.int32[at].values, d, rep)?
                    }
                    Kind::Double => {
                        let (d, rep) = r.double[at].levels();
                        c.typed::<DoubleType>()
                            .write_batch(&r.double[at].values, d, rep)?
                    }
                    Kind::Boolean => {
                        let (d, rep) = r.boolean[at].levels();
                        c.typed::<BoolType>()
                            .write_batch(&r.boolean[at].values, d, rep)?
                    }
                };
                c.close()?;
                column += 1;
            }
            group.close()?;
        }
        self.file.close()?;
        Ok(r.count)
    }
}

fn push_index<T: Default>(v: &mut Vec<Column<T>>) -> usize {
    v.push(Column::default());
    v.len() - 1
}
