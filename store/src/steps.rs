//! The Parquet layout of episode steps (see store/README.md): one row per step, one
//! `FixedSizeList<Float32>` column per observation key, the episode's metadata repeated on each
//! row so the files stand on their own, one row group per episode.

use crate::{EpisodeInput, Label, StoreError};
use arrow::array::{
    Array, ArrayRef, BinaryBuilder, BooleanArray, FixedSizeListArray, Float32Array, Float64Array,
    Int32Array, RecordBatch, StringArray,
};
use arrow::datatypes::{DataType, Field, Schema, SchemaRef};
use bytes::Bytes;
use parquet::arrow::arrow_reader::ParquetRecordBatchReaderBuilder;
use parquet::arrow::ArrowWriter;
use parquet::basic::{Compression, ZstdLevel};
use parquet::file::properties::WriterProperties;
use std::collections::HashMap;
use std::sync::Arc;

pub const SCHEMA_VERSION: &str = "1";
pub const OBS_PREFIX: &str = "obs.";
pub const IMAGE_PREFIX: &str = "image.";
pub const MEDIA_PREFIX: &str = "media.";

/// The episode-level values repeated on every row.
pub struct EpisodeMeta<'a> {
    pub episode_id: &'a str,
    pub policy: &'a str,
    pub checkpoint: &'a str,
}

fn f32_item() -> Arc<Field> {
    Arc::new(Field::new("item", DataType::Float32, false))
}

fn fsl_field(name: &str, dim: usize, meta: HashMap<String, String>) -> Field {
    Field::new(name, DataType::FixedSizeList(f32_item(), dim as i32), false).with_metadata(meta)
}

/// The Arrow schema an episode is written with.
pub fn schema_for(ep: &EpisodeInput) -> SchemaRef {
    let mut fields = vec![
        Field::new("episode_id", DataType::Utf8, false),
        Field::new("t", DataType::Int32, false),
        Field::new("timestamp", DataType::Float64, false),
    ];
    for o in &ep.observations {
        let meta = HashMap::from([("ufops.observation_key".to_string(), o.name.clone())]);
        fields.push(fsl_field(&format!("{OBS_PREFIX}{}", o.name), o.dim, meta));
    }
    fields.push(fsl_field("action", ep.action.dim, HashMap::new()));
    fields.push(Field::new("reward", DataType::Float32, false));
    fields.push(Field::new("done", DataType::Boolean, false));
    if let Some(c) = &ep.action_chunk {
        let meta = HashMap::from([(
            "ufops.shape".to_string(),
            format!("[{}, {}]", c.horizon, c.action_dim),
        )]);
        fields.push(fsl_field("action_chunk", c.horizon * c.action_dim, meta));
    }
    for im in &ep.images {
        let meta = HashMap::from([
            ("ufops.shape".to_string(), format!("[{}, {}, {}]", im.shape[0], im.shape[1], im.shape[2])),
            ("ufops.encoding".to_string(), "png".to_string()),
        ]);
        fields.push(
            Field::new(format!("{IMAGE_PREFIX}{}", im.name), DataType::Binary, false).with_metadata(meta),
        );
    }
    for m in &ep.media {
        fields.push(Field::new(format!("{MEDIA_PREFIX}{}.path", m.name), DataType::Utf8, false));
        fields.push(Field::new(format!("{MEDIA_PREFIX}{}.timestamp", m.name), DataType::Float64, false));
    }
    fields.push(Field::new("policy", DataType::Utf8, false));
    fields.push(Field::new("checkpoint", DataType::Utf8, false));
    fields.push(Field::new("task", DataType::Utf8, true));
    fields.push(Field::new("success", DataType::Boolean, true));
    fields.push(Field::new("label_source", DataType::Utf8, false));
    let meta = HashMap::from([("ufops.schema_version".to_string(), SCHEMA_VERSION.to_string())]);
    Arc::new(Schema::new(fields).with_metadata(meta))
}

/// Checks that every column of an episode has one value per step.
pub fn validate(ep: &EpisodeInput) -> Result<(), StoreError> {
    let n = ep.len();
    let bad = |what: String| {
        Err(StoreError::invalid(format!("episode {:?}: {what}", ep.source_name)))
    };
    if n == 0 {
        return bad("has no steps".into());
    }
    if n > i32::MAX as usize {
        return bad(format!("has too many steps ({n})"));
    }
    let mut names = std::collections::HashSet::new();
    for v in ep.observations.iter().chain(std::iter::once(&ep.action)) {
        if v.dim == 0 {
            return bad(format!("column {:?} has dimension 0", v.name));
        }
        if v.values.len() != n * v.dim {
            return bad(format!(
                "column {:?} has {} values, expected {} steps x {}",
                v.name,
                v.values.len(),
                n,
                v.dim
            ));
        }
    }
    for o in &ep.observations {
        if !names.insert(o.name.clone()) {
            return bad(format!("observation key {:?} appears twice", o.name));
        }
    }
    if ep.reward.len() != n || ep.done.len() != n {
        return bad(format!(
            "reward/done have {}/{} values for {n} steps",
            ep.reward.len(),
            ep.done.len()
        ));
    }
    if let Some(c) = &ep.action_chunk {
        if c.horizon == 0 || c.action_dim == 0 || c.values.len() != n * c.horizon * c.action_dim {
            return bad(format!(
                "action_chunk has {} values, expected {n} x {} x {}",
                c.values.len(),
                c.horizon,
                c.action_dim
            ));
        }
    }
    for im in &ep.images {
        if im.png_frames.len() != n {
            return bad(format!("image {:?} has {} frames for {n} steps", im.name, im.png_frames.len()));
        }
    }
    for m in &ep.media {
        if m.timestamps.len() != n {
            return bad(format!("media {:?} has {} timestamps for {n} steps", m.name, m.timestamps.len()));
        }
    }
    Ok(())
}

fn fsl(dim: usize, values: &[f32]) -> Result<ArrayRef, StoreError> {
    let child: ArrayRef = Arc::new(Float32Array::from(values.to_vec()));
    Ok(Arc::new(FixedSizeListArray::try_new(f32_item(), dim as i32, child, None)?))
}

/// Builds the record batch of one episode (call [`validate`] first).
pub fn episode_batch(
    ep: &EpisodeInput,
    meta: &EpisodeMeta<'_>,
    media_paths: &HashMap<String, String>,
) -> Result<RecordBatch, StoreError> {
    let n = ep.len();
    let schema = schema_for(ep);
    let mut cols: Vec<ArrayRef> = vec![
        Arc::new(StringArray::from(vec![meta.episode_id; n])),
        Arc::new(Int32Array::from_iter_values(0..n as i32)),
        Arc::new(Float64Array::from(ep.timestamps.clone())),
    ];
    for o in &ep.observations {
        cols.push(fsl(o.dim, &o.values)?);
    }
    cols.push(fsl(ep.action.dim, &ep.action.values)?);
    cols.push(Arc::new(Float32Array::from(ep.reward.clone())));
    cols.push(Arc::new(BooleanArray::from(ep.done.clone())));
    if let Some(c) = &ep.action_chunk {
        cols.push(fsl(c.horizon * c.action_dim, &c.values)?);
    }
    for im in &ep.images {
        let total: usize = im.png_frames.iter().map(|f| f.len()).sum();
        let mut b = BinaryBuilder::with_capacity(n, total);
        for f in &im.png_frames {
            b.append_value(f);
        }
        cols.push(Arc::new(b.finish()));
    }
    for m in &ep.media {
        let path = media_paths.get(&m.sha256).ok_or_else(|| {
            StoreError::invalid(format!(
                "episode {:?} references media {} that was not added to the ingest",
                ep.source_name, m.sha256
            ))
        })?;
        cols.push(Arc::new(StringArray::from(vec![path.as_str(); n])));
        cols.push(Arc::new(Float64Array::from(m.timestamps.clone())));
    }
    cols.push(Arc::new(StringArray::from(vec![meta.policy; n])));
    cols.push(Arc::new(StringArray::from(vec![meta.checkpoint; n])));
    cols.push(Arc::new(StringArray::from(vec![ep.task.as_deref(); n])));
    cols.push(Arc::new(BooleanArray::from(vec![ep.label.as_bool(); n])));
    cols.push(Arc::new(StringArray::from(vec![ep.label_source.as_str(); n])));
    Ok(RecordBatch::try_new(schema, cols)?)
}

pub fn writer_properties() -> WriterProperties {
    WriterProperties::builder()
        .set_compression(Compression::ZSTD(ZstdLevel::try_new(1).expect("valid zstd level")))
        .set_max_row_group_row_count(Some(1 << 20))
        .build()
}

/// A Parquet file being filled in memory, one row group per episode.
pub struct StepsFileWriter {
    writer: ArrowWriter<Vec<u8>>,
    pub schema: SchemaRef,
    pub rows: usize,
    pub row_groups: usize,
}

impl StepsFileWriter {
    pub fn new(schema: SchemaRef) -> Result<Self, StoreError> {
        let writer = ArrowWriter::try_new(Vec::with_capacity(1 << 20), schema.clone(), Some(writer_properties()))?;
        Ok(StepsFileWriter { writer, schema, rows: 0, row_groups: 0 })
    }

    /// Appends one episode as its own row group; returns the row-group index.
    pub fn write_episode(&mut self, batch: &RecordBatch) -> Result<usize, StoreError> {
        self.writer.write(batch)?;
        self.writer.flush()?;
        self.rows += batch.num_rows();
        self.row_groups += 1;
        Ok(self.row_groups - 1)
    }

    pub fn bytes_written(&self) -> usize {
        self.writer.bytes_written() + self.writer.in_progress_size()
    }

    pub fn finish(self) -> Result<Vec<u8>, StoreError> {
        Ok(self.writer.into_inner()?)
    }
}

/// Reads one row group (one episode) of a steps file.
pub fn read_row_group(data: Bytes, row_group: usize) -> Result<RecordBatch, StoreError> {
    let builder = ParquetRecordBatchReaderBuilder::try_new(data)?;
    let n_groups = builder.metadata().num_row_groups();
    if row_group >= n_groups {
        return Err(StoreError::Corrupt(format!(
            "steps file has {n_groups} row groups, episode points at {row_group}"
        )));
    }
    let schema = builder.schema().clone();
    let reader = builder.with_row_groups(vec![row_group]).with_batch_size(1 << 20).build()?;
    let batches: Vec<RecordBatch> = reader.collect::<Result<_, _>>()?;
    Ok(arrow::compute::concat_batches(&schema, &batches)?)
}

/// A float vector column of a steps batch as `(dim, row-major values)`.
pub fn vector_column(batch: &RecordBatch, name: &str) -> Result<(usize, Vec<f32>), StoreError> {
    let col = batch
        .column_by_name(name)
        .ok_or_else(|| StoreError::invalid(format!("steps have no column {name:?}")))?;
    let list = col
        .as_any()
        .downcast_ref::<FixedSizeListArray>()
        .ok_or_else(|| StoreError::invalid(format!("column {name:?} is not a fixed-size list")))?;
    let dim = list.value_length() as usize;
    let values = list
        .values()
        .as_any()
        .downcast_ref::<Float32Array>()
        .ok_or_else(|| StoreError::invalid(format!("column {name:?} is not float32")))?;
    let start = list.offset() * dim;
    Ok((dim, values.values()[start..start + list.len() * dim].to_vec()))
}

/// The observation keys present in a steps schema, in column order.
pub fn observation_keys(schema: &Schema) -> Vec<(String, usize)> {
    schema
        .fields()
        .iter()
        .filter_map(|f| {
            let key = f.name().strip_prefix(OBS_PREFIX)?;
            match f.data_type() {
                DataType::FixedSizeList(_, d) => Some((key.to_string(), *d as usize)),
                _ => None,
            }
        })
        .collect()
}

/// Snapshot file of a version's labels: one row per visible episode.
pub struct LabelRow {
    pub episode_id: String,
    pub policy: String,
    pub checkpoint: String,
    pub task: Option<String>,
    pub length: i64,
    pub label: Label,
    pub label_source: String,
    pub revision: i64,
    pub data_file: String,
    pub row_group: i64,
}

pub fn labels_file(version_hint: i64, rows: &[LabelRow]) -> Result<Vec<u8>, StoreError> {
    use arrow::array::Int64Array;
    let schema = Arc::new(
        Schema::new(vec![
            Field::new("episode_id", DataType::Utf8, false),
            Field::new("policy", DataType::Utf8, false),
            Field::new("checkpoint", DataType::Utf8, false),
            Field::new("task", DataType::Utf8, true),
            Field::new("length", DataType::Int64, false),
            Field::new("label", DataType::Utf8, false),
            Field::new("success", DataType::Boolean, true),
            Field::new("label_source", DataType::Utf8, false),
            Field::new("label_revision", DataType::Int64, false),
            Field::new("data_file", DataType::Utf8, false),
            Field::new("row_group", DataType::Int64, false),
        ])
        .with_metadata(HashMap::from([
            ("ufops.schema_version".to_string(), SCHEMA_VERSION.to_string()),
            ("ufops.version".to_string(), version_hint.to_string()),
        ])),
    );
    let cols: Vec<ArrayRef> = vec![
        Arc::new(StringArray::from_iter_values(rows.iter().map(|r| r.episode_id.as_str()))),
        Arc::new(StringArray::from_iter_values(rows.iter().map(|r| r.policy.as_str()))),
        Arc::new(StringArray::from_iter_values(rows.iter().map(|r| r.checkpoint.as_str()))),
        Arc::new(StringArray::from_iter(rows.iter().map(|r| r.task.as_deref()))),
        Arc::new(Int64Array::from_iter_values(rows.iter().map(|r| r.length))),
        Arc::new(StringArray::from_iter_values(rows.iter().map(|r| r.label.as_str()))),
        Arc::new(BooleanArray::from(rows.iter().map(|r| r.label.as_bool()).collect::<Vec<_>>())),
        Arc::new(StringArray::from_iter_values(rows.iter().map(|r| r.label_source.as_str()))),
        Arc::new(Int64Array::from_iter_values(rows.iter().map(|r| r.revision))),
        Arc::new(StringArray::from_iter_values(rows.iter().map(|r| r.data_file.as_str()))),
        Arc::new(Int64Array::from_iter_values(rows.iter().map(|r| r.row_group))),
    ];
    let batch = RecordBatch::try_new(schema.clone(), cols)?;
    let mut w = ArrowWriter::try_new(Vec::new(), schema, Some(writer_properties()))?;
    w.write(&batch)?;
    Ok(w.into_inner()?)
}
