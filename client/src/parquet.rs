//! Corrected batches as an Apache Parquet file, one row per sample, for pandas, pyarrow, Polars
//! or DuckDB.
//!
//! Columns (all required):
//!
//! | column | Parquet type | meaning |
//! |---|---|---|
//! | `time` | INT64, TIMESTAMP(NANOS, UTC) | the sample's time: batch timestamp + i / rate |
//! | `sensor_id` | BYTE_ARRAY, UTF8 | |
//! | `sequence` | INT64 | the batch's sequence number |
//! | `ax_mps2`, `ay_mps2`, `az_mps2` | FLOAT | corrected acceleration, m/s² (raw outputs when uncalibrated) |
//! | `ux_mps2`, `uy_mps2`, `uz_mps2` | FLOAT | standard uncertainty (k = 1), m/s² (NaN when uncalibrated) |
//! | `coverage_factor` | FLOAT | k of the batch |
//! | `flags` | INT32 (UINT_16) | the sample's own flags (PROTOCOL.md §2.3); the batch-only flags `sequence_gap` and `duplicate` on the batch's first sample only |
//! | `calibration_version` | INT64 | 0 when uncalibrated |
//! | `mode` | BYTE_ARRAY, UTF8 | `none`, `static`, `dynamic`, `split` |
//!
//! The file's key-value metadata says the units (`triax.units`), the flag bits
//! (`triax.flags`) and the format (`triax.format` = `triax-corrected-samples/1`).
//!
//! Written with the `parquet` crate's column writers, without Arrow: Arrow would double the
//! build for nothing this file needs.

use std::io::Write;
use std::sync::Arc;

use ::parquet::basic::{Compression, Encoding};
use ::parquet::data_type::{ByteArray, ByteArrayType, FloatType, Int32Type, Int64Type};
use ::parquet::errors::ParquetError;
use ::parquet::file::metadata::KeyValue;
use ::parquet::file::properties::WriterProperties;
use ::parquet::file::writer::SerializedFileWriter;
use ::parquet::schema::parser::parse_message_type;
use ::parquet::schema::types::ColumnPath;
use triax_protocol::batch::{CorrectedBatch, Mode};

/// The schema, in Parquet's message syntax.
const SCHEMA: &str = "message triax_corrected_samples {
  required int64 time (TIMESTAMP(NANOS,true));
  required binary sensor_id (UTF8);
  required int64 sequence;
  required float ax_mps2;
  required float ay_mps2;
  required float az_mps2;
  required float ux_mps2;
  required float uy_mps2;
  required float uz_mps2;
  required float coverage_factor;
  required int32 flags (INTEGER(16,false));
  required int64 calibration_version;
  required binary mode (UTF8);
}";

/// Rows buffered before a row group is written: 1 M samples, about 40 MiB of columns.
const ROW_GROUP_ROWS: usize = 1 << 20;

/// Why a Parquet file could not be written.
#[derive(Debug, thiserror::Error)]
#[error("parquet: {0}")]
pub struct ParquetExportError(#[from] ParquetError);

/// The columns of the rows not yet written.
#[derive(Default)]
struct Columns {
    time: Vec<i64>,
    sensor: Vec<ByteArray>,
    sequence: Vec<i64>,
    a: [Vec<f32>; 3],
    u: [Vec<f32>; 3],
    k: Vec<f32>,
    flags: Vec<i32>,
    version: Vec<i64>,
    mode: Vec<ByteArray>,
}

/// Writes corrected batches to a Parquet file as they come.
pub struct ParquetWriter<W: Write + Send> {
    file: SerializedFileWriter<W>,
    rows: Columns,
    written: u64,
}

fn mode_name(m: Mode) -> &'static str {
    match m {
        Mode::None => "none",
        Mode::Static => "static",
        Mode::Dynamic => "dynamic",
        Mode::Split => "split",
    }
}

impl<W: Write + Send> ParquetWriter<W> {
    pub fn new(out: W) -> Result<ParquetWriter<W>, ParquetExportError> {
        let schema = Arc::new(parse_message_type(SCHEMA)?);
        let props = WriterProperties::builder()
            .set_compression(Compression::UNCOMPRESSED)
            // A dictionary pays where values repeat (ids, sequence numbers, versions, flags, k,
            // uncertainties, which change slowly); for times and accelerations it only costs:
            // interning them was a fifth of the export's CPU. Times step evenly within a batch:
            // delta encoding stores them in a bit or two each.
            .set_column_dictionary_enabled(ColumnPath::from("time"), false)
            .set_column_encoding(ColumnPath::from("time"), Encoding::DELTA_BINARY_PACKED)
            .set_column_dictionary_enabled(ColumnPath::from("ax_mps2"), false)
            .set_column_dictionary_enabled(ColumnPath::from("ay_mps2"), false)
            .set_column_dictionary_enabled(ColumnPath::from("az_mps2"), false)
            .set_key_value_metadata(Some(vec![
                KeyValue::new(
                    "triax.format".to_owned(),
                    "triax-corrected-samples/1".to_owned(),
                ),
                KeyValue::new(
                    "triax.units".to_owned(),
                    "time: ns since the Unix epoch (UTC); a*_mps2, u*_mps2: m/s² (u: standard \
                     uncertainty, k = 1; the expanded uncertainty is coverage_factor·u)"
                        .to_owned(),
                ),
                KeyValue::new(
                    "triax.flags".to_owned(),
                    "bit 0 uncalibrated, 1 calibration_expired, 2 outside_amplitude, 3 \
                     outside_frequency, 4 sequence_gap, 5 non_finite_input, 6 clipped, 7 \
                     duplicate, 8 outside_temperature, 9 calibration_suspect, 10 late (PROTOCOL.md §2.3)"
                        .to_owned(),
                ),
            ]))
            .build();
        Ok(ParquetWriter {
            file: SerializedFileWriter::new(out, schema, Arc::new(props))?,
            rows: Columns::default(),
            written: 0,
        })
    }

    /// Adds a batch's samples; writes a row group when enough are buffered.
    pub fn push(&mut self, b: &CorrectedBatch) -> Result<(), ParquetExportError> {
        let h = &b.header;
        let period_ns = 1e9 / h.sample_rate_hz;
        let sensor = ByteArray::from(h.sensor_id.as_str());
        let mode = ByteArray::from(mode_name(b.info.mode));
        let r = &mut self.rows;
        for (i, s) in b.samples.iter().enumerate() {
            r.time
                .push(h.timestamp_ns.saturating_add((i as f64 * period_ns) as i64));
            r.sensor.push(sensor.clone());
            r.sequence.push(h.sequence as i64);
            for j in 0..3 {
                r.a[j].push(s.accel_mps2[j]);
                r.u[j].push(s.uncertainty_mps2[j]);
            }
            r.k.push(b.info.coverage_factor);
            r.flags.push(i32::from(b.sample_flags(i)));
            r.version.push(b.info.calibration_version as i64);
            r.mode.push(mode.clone());
        }
        if self.rows.time.len() >= ROW_GROUP_ROWS {
            self.flush()?;
        }
        Ok(())
    }

    fn flush(&mut self) -> Result<(), ParquetExportError> {
        let r = std::mem::take(&mut self.rows);
        if r.time.is_empty() {
            return Ok(());
        }
        let mut group = self.file.next_row_group()?;
        let mut column = 0;
        while let Some(mut c) = group.next_column()? {
            match column {
                0 => c.typed::<Int64Type>().write_batch(&r.time, None, None)?,
                1 => c
                    .typed::<ByteArrayType>()
                    .write_batch(&r.sensor, None, None)?,
                2 => c
                    .typed::<Int64Type>()
                    .write_batch(&r.sequence, None, None)?,
                3..=5 => c
                    .typed::<FloatType>()
                    .write_batch(&r.a[column - 3], None, None)?,
                6..=8 => c
                    .typed::<FloatType>()
                    .write_batch(&r.u[column - 6], None, None)?,
                9 => c.typed::<FloatType>().write_batch(&r.k, None, None)?,
                10 => c.typed::<Int32Type>().write_batch(&r.flags, None, None)?,
                11 => c.typed::<Int64Type>().write_batch(&r.version, None, None)?,
                _ => c
                    .typed::<ByteArrayType>()
                    .write_batch(&r.mode, None, None)?,
            };
            c.close()?;
            column += 1;
        }
        group.close()?;
        self.written += r.time.len() as u64;
        Ok(())
    }

    /// Writes what is buffered and the footer; returns the rows written.
    pub fn finish(mut self) -> Result<u64, ParquetExportError> {
        self.flush()?;
        self.file.close()?;
        Ok(self.written)
    }
}
