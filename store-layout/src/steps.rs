//! The Parquet layout of episode steps (see store/README.md): one row per step, one
//! `FixedSizeList<Float32>` column per observation key, the episode's metadata repeated on each
//! row so the files stand on their own. Episodes follow each other in row groups of up to 1 Mi
//! rows / 64 MB; the catalog records each one's `(row_group, row_offset, row_count)`.
//!
//! One file past 700 lines: the steps layout's one definition (schema, the writer that builds files
//! in it, the label rows) is read as one; the page spilling lives in spill.rs.

use crate::spill::{SpillColumn, SpilledChunk};
use crate::{EpisodeInput, ExtraColumn, ExtraPages, ExtraValues, Frames, Label, StoreError};
use arrow::array::{
    Array, ArrayRef, BinaryArray, BooleanArray, FixedSizeListArray, Float32Array, Float64Array, Int32Array,
    RecordBatch, StringArray,
};
use arrow::datatypes::{DataType, Field, Schema, SchemaRef};
use bytes::Bytes;
use parquet::arrow::arrow_reader::{
    ArrowReaderOptions, ParquetRecordBatchReaderBuilder, RowSelection, RowSelector,
};
use parquet::arrow::arrow_writer::{
    compute_leaves, ArrowColumnChunk, ArrowColumnWriter, ArrowRowGroupWriterFactory,
};
use parquet::arrow::{add_encoded_arrow_schema_to_metadata, ArrowSchemaConverter, ArrowWriter};
use parquet::basic::{Compression, ConvertedType, Type as PhysicalType, ZstdLevel};
use parquet::file::metadata::PageIndexPolicy;
use parquet::file::properties::{EnabledStatistics, WriterProperties, WriterPropertiesPtr};
use parquet::file::writer::SerializedFileWriter;
use parquet::schema::types::SchemaDescriptor;
use std::collections::HashMap;
use std::sync::Arc;

pub const SCHEMA_VERSION: &str = "1";
pub const OBS_PREFIX: &str = "obs.";
pub const IMAGE_PREFIX: &str = "image.";
pub const MEDIA_PREFIX: &str = "media.";
/// Per-step arrays of the source beyond the step model ([`crate::ExtraColumn`]).
pub const EXTRA_PREFIX: &str = "extra.";
/// `true` on the steps a human controlled ([`crate::StepFlags::intervention`]).
pub const INTERVENTION_COLUMN: &str = "intervention";
/// `false` on the steps a person marked invalid ([`crate::StepFlags::validity`]).
pub const VALIDITY_COLUMN: &str = "validity";
/// Steering telemetry of a steered episode: on the row of each step whose chunk best-of-N chose,
/// what it saw and chose (candidates, scores, chosen index, artifact, latency; the record is
/// `verifier::telemetry::SteeringStep`, its encoding `verifier::steps::steering_array`); null on
/// the other rows. Type: [`steering_data_type`].
pub const STEERING_COLUMN: &str = "steering";

/// The type of the [`STEERING_COLUMN`]: a struct of the artifact id, the chosen index, the
/// scoring latency in microseconds, the N scores (float32) and the N candidate chunks, raw
/// actions flattened (`N * H * A`, float16).
pub fn steering_data_type() -> DataType {
    let list = |item: DataType| DataType::List(Arc::new(Field::new("item", item, false)));
    DataType::Struct(arrow::datatypes::Fields::from(vec![
        Field::new("artifact_id", DataType::Utf8, false),
        Field::new("chosen", DataType::UInt32, false),
        Field::new("latency_us", DataType::UInt32, false),
        Field::new("scores", list(DataType::Float32), false),
        Field::new("candidates", list(DataType::Float16), false),
    ]))
}

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
    schema_with_extras(ep, &[], false)
}

/// The Arrow schema of an episode and its extra columns (after the media columns), with the
/// [`STEERING_COLUMN`] after them when `steered`.
pub fn schema_with_extras(ep: &EpisodeInput, extras: &[ExtraColumn], steered: bool) -> SchemaRef {
    let mut fields = vec![
        Field::new("episode_id", DataType::Utf8, false),
        Field::new("t", DataType::Int32, false),
        Field::new("timestamp", DataType::Float64, false),
    ];
    for o in &ep.observations {
        let meta = HashMap::from([("ufops.observation_key".to_string(), o.name.clone())]);
        fields.push(fsl_field(&format!("{OBS_PREFIX}{}", o.name), o.dim, meta));
    }
    if ep.action.dim > 0 {
        fields.push(fsl_field("action", ep.action.dim, HashMap::new()));
    }
    fields.push(Field::new("reward", DataType::Float32, false));
    fields.push(Field::new("done", DataType::Boolean, false));
    for (name, flag) in flag_columns(&ep.flags) {
        if flag.is_some() {
            fields.push(Field::new(name, DataType::Boolean, false));
        }
    }
    if let Some(c) = &ep.action_chunk {
        let meta = HashMap::from([("ufops.shape".to_string(), format!("[{}, {}]", c.horizon, c.action_dim))]);
        fields.push(fsl_field("action_chunk", c.horizon * c.action_dim, meta));
    }
    for im in &ep.images {
        let meta = HashMap::from([
            ("ufops.shape".to_string(), format!("[{}, {}, {}]", im.shape[0], im.shape[1], im.shape[2])),
            ("ufops.encoding".to_string(), im.encoding().to_string()),
        ]);
        fields.push(
            Field::new(format!("{IMAGE_PREFIX}{}", im.name), DataType::Binary, false).with_metadata(meta),
        );
    }
    for m in &ep.media {
        fields.push(Field::new(format!("{MEDIA_PREFIX}{}.path", m.name), DataType::Utf8, false));
        fields.push(Field::new(format!("{MEDIA_PREFIX}{}.timestamp", m.name), DataType::Float64, false));
    }
    for x in extras {
        fields.push(
            Field::new(format!("{EXTRA_PREFIX}{}", x.name), x.values.data_type().clone(), true)
                .with_metadata(x.metadata.clone()),
        );
    }
    if steered {
        fields.push(Field::new(STEERING_COLUMN, steering_data_type(), true));
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
    let bad = |what: String| Err(StoreError::invalid(format!("episode {:?}: {what}", ep.source_name)));
    if n == 0 {
        return bad("has no steps".into());
    }
    if n > i32::MAX as usize {
        return bad(format!("has too many steps ({n})"));
    }
    let mut names = std::collections::HashSet::new();
    // An action of dimension 0 with no values: the source recorded no actions.
    let no_action = ep.action.dim == 0 && ep.action.values.is_empty();
    for v in ep.observations.iter().chain(std::iter::once(&ep.action).filter(|_| !no_action)) {
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
        return bad(format!("reward/done have {}/{} values for {n} steps", ep.reward.len(), ep.done.len()));
    }
    for (name, flag) in flag_columns(&ep.flags) {
        if let Some(f) = flag.filter(|f| f.len() != n) {
            return bad(format!("{name} has {} values for {n} steps", f.len()));
        }
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
        if im.frames.len() != n {
            return bad(format!("image {:?} has {} frames for {n} steps", im.name, im.frames.len()));
        }
    }
    for m in &ep.media {
        if m.timestamps.len() != n {
            return bad(format!("media {:?} has {} timestamps for {n} steps", m.name, m.timestamps.len()));
        }
    }
    Ok(())
}

/// [`validate`], and the extra columns: one row per step, unique names; the steering column, when
/// there is one: one row per step, of [`steering_data_type`].
pub fn validate_with_extras(
    ep: &EpisodeInput,
    extras: &[ExtraColumn],
    steering: Option<&ArrayRef>,
) -> Result<(), StoreError> {
    validate(ep)?;
    if let Some(s) = steering {
        if s.len() != ep.len() || s.data_type() != &steering_data_type() {
            return Err(StoreError::invalid(format!(
                "episode {:?}: the steering column has {} rows of {} for {} steps of {}",
                ep.source_name,
                s.len(),
                s.data_type(),
                ep.len(),
                steering_data_type()
            )));
        }
    }
    let mut names = std::collections::HashSet::new();
    for x in extras {
        if x.name.is_empty() || !names.insert(x.name.as_str()) {
            return Err(StoreError::invalid(format!(
                "episode {:?}: extra column {:?} is empty-named or appears twice",
                ep.source_name, x.name
            )));
        }
        if x.values.len() != ep.len() {
            return Err(StoreError::invalid(format!(
                "episode {:?}: extra column {:?} has {} rows for {} steps",
                ep.source_name,
                x.name,
                x.values.len(),
                ep.len()
            )));
        }
    }
    Ok(())
}

/// The per-step flag columns in schema order, with the episode's values when it has them.
fn flag_columns(flags: &crate::StepFlags) -> [(&'static str, Option<&Vec<bool>>); 2] {
    [(INTERVENTION_COLUMN, flags.intervention.as_ref()), (VALIDITY_COLUMN, flags.validity.as_ref())]
}

/// The per-step flags of a steps batch as the store reads it (a column it lacks: `None`).
pub fn step_flags(batch: &RecordBatch) -> Result<crate::StepFlags, StoreError> {
    let flag = |name: &str| -> Result<Option<Vec<bool>>, StoreError> {
        let Some(c) = batch.column_by_name(name) else { return Ok(None) };
        let b = c.as_any().downcast_ref::<BooleanArray>().ok_or_else(|| {
            StoreError::invalid(format!("steps column {name} is {}, not boolean", c.data_type()))
        })?;
        Ok(Some((0..b.len()).map(|i| b.is_valid(i) && b.value(i)).collect()))
    };
    Ok(crate::StepFlags { intervention: flag(INTERVENTION_COLUMN)?, validity: flag(VALIDITY_COLUMN)? })
}

fn fsl(dim: usize, values: Vec<f32>) -> Result<ArrayRef, StoreError> {
    // `Float32Array::from(Vec)` takes the vector's buffer over: no copy.
    let child: ArrayRef = Arc::new(Float32Array::from(values));
    Ok(Arc::new(FixedSizeListArray::try_new(f32_item(), dim as i32, child, None)?))
}

/// Builds the record batch of one episode (call [`validate`] first); its cameras' frames are
/// pulled into memory.
pub fn episode_batch(
    ep: EpisodeInput,
    meta: &EpisodeMeta<'_>,
    media_paths: &HashMap<String, String>,
) -> Result<RecordBatch, StoreError> {
    let n = ep.len();
    let schema = schema_for(&ep);
    let mut cols: Vec<ArrayRef> = vec![Arc::new(StringArray::from(vec![meta.episode_id; n]))];
    for c in episode_columns(ep, meta.policy, meta.checkpoint, media_paths)? {
        cols.push(match c {
            StepColumn::Values(a) => a,
            StepColumn::Frames(f) => {
                let frames = f.collect_encoded()?;
                Arc::new(BinaryArray::from_iter_values(frames.iter()))
            }
            StepColumn::Pages(p) => ExtraValues::Pages(p).to_array()?,
        });
    }
    Ok(RecordBatch::try_new(schema, cols)?)
}

/// One column of an episode as [`StepsFileWriter::write_episode`] takes it: values in memory, a
/// camera's frames, which the writer pulls a page at a time (a stream's frames are never all in
/// memory), or an extra column read a page of rows at a time.
pub enum StepColumn {
    Values(ArrayRef),
    Frames(Frames),
    Pages(ExtraPages),
}

impl StepColumn {
    fn rows(&self) -> usize {
        match self {
            StepColumn::Values(a) => a.len(),
            StepColumn::Frames(f) => f.len(),
            StepColumn::Pages(p) => p.len,
        }
    }
}

/// The columns of one episode after `episode_id` (which [`StepsFileWriter`] adds itself, as the
/// id may only be known once the source's hash is), in [`schema_for`] order. Consumes the episode
/// so its vectors become Arrow buffers without a copy and its cameras' frames are handed on
/// unread. Call [`validate`] first.
pub fn episode_columns(
    ep: EpisodeInput,
    policy: &str,
    checkpoint: &str,
    media_paths: &HashMap<String, String>,
) -> Result<Vec<StepColumn>, StoreError> {
    episode_columns_with_extras(ep, Vec::new(), None, policy, checkpoint, media_paths)
}

/// [`episode_columns`] with the episode's extra columns and steering column, in
/// [`schema_with_extras`] order. Call [`validate_with_extras`] first.
pub fn episode_columns_with_extras(
    ep: EpisodeInput,
    extras: Vec<ExtraColumn>,
    steering: Option<ArrayRef>,
    policy: &str,
    checkpoint: &str,
    media_paths: &HashMap<String, String>,
) -> Result<Vec<StepColumn>, StoreError> {
    let n = ep.len();
    let label = ep.label.as_bool();
    let mut cols: Vec<ArrayRef> = Vec::with_capacity(12 + ep.observations.len());
    cols.push(Arc::new(Int32Array::from_iter_values(0..n as i32)));
    cols.push(Arc::new(Float64Array::from(ep.timestamps)));
    for o in ep.observations {
        cols.push(fsl(o.dim, o.values)?);
    }
    if ep.action.dim > 0 {
        cols.push(fsl(ep.action.dim, ep.action.values)?);
    }
    cols.push(Arc::new(Float32Array::from(ep.reward)));
    cols.push(Arc::new(BooleanArray::from(ep.done)));
    for flag in [ep.flags.intervention, ep.flags.validity].into_iter().flatten() {
        cols.push(Arc::new(BooleanArray::from(flag)));
    }
    if let Some(c) = ep.action_chunk {
        cols.push(fsl(c.horizon * c.action_dim, c.values)?);
    }
    let mut frames = Vec::with_capacity(ep.images.len());
    for im in ep.images {
        frames.push(im.frames);
    }
    // The image columns' position among the others (schema order).
    let image_at = cols.len();
    for m in ep.media {
        let path = media_paths.get(&m.sha256).ok_or_else(|| {
            StoreError::invalid(format!(
                "episode {:?} references media {} that was not added to the ingest",
                ep.source_name, m.sha256
            ))
        })?;
        cols.push(Arc::new(StringArray::from(vec![path.as_str(); n])));
        cols.push(Arc::new(Float64Array::from(m.timestamps)));
    }
    let mut out: Vec<StepColumn> = Vec::with_capacity(cols.len() + frames.len() + extras.len() + 5);
    let mut cols = cols.into_iter();
    out.extend(cols.by_ref().take(image_at).map(StepColumn::Values));
    out.extend(frames.into_iter().map(StepColumn::Frames));
    out.extend(cols.map(StepColumn::Values));
    out.extend(extras.into_iter().map(|x| match x.values {
        ExtraValues::Array(a) => StepColumn::Values(a),
        ExtraValues::Pages(p) => StepColumn::Pages(p),
    }));
    out.extend(steering.map(StepColumn::Values));
    let tail: [ArrayRef; 5] = [
        Arc::new(StringArray::from(vec![policy; n])),
        Arc::new(StringArray::from(vec![checkpoint; n])),
        Arc::new(StringArray::from(vec![ep.task.as_deref(); n])),
        Arc::new(BooleanArray::from(vec![label; n])),
        Arc::new(StringArray::from(vec![ep.label_source.as_str(); n])),
    ];
    out.extend(tail.into_iter().map(StepColumn::Values));
    Ok(out)
}

/// zstd level of every file the store writes (level 1, like pyarrow's default).
const ZSTD_LEVEL: i32 = 1;

/// Writer settings for a steps file of this schema: zstd(1); dictionary encoding only where it
/// pays (the repeated strings), never for float data, whose values hardly repeat (the dictionary
/// is built, found too large and thrown away at a real cost); chunk statistics for the small
/// scalar columns (`t`, `episode_id`, …) and none for float vectors and images; no page-level
/// statistics. Pages are cut by [`StepsFileWriter`] between episodes (one page per `write` call:
/// a row-count limit of 1 closes the page after each call, and a call is never split into
/// mini-batches), so the offset index points at each episode's own pages and reading one episode
/// fetches its bytes and no one else's (store/README.md, "Read path").
pub fn steps_writer_properties(parquet: &SchemaDescriptor) -> WriterProperties {
    let mut b = WriterProperties::builder()
        .set_compression(Compression::ZSTD(ZstdLevel::try_new(ZSTD_LEVEL).expect("valid zstd level")))
        // Row groups are cut by StepsFileWriter itself, between episodes.
        .set_max_row_group_row_count(None)
        .set_data_page_row_count_limit(1)
        .set_write_batch_size(1 << 30)
        .set_statistics_enabled(EnabledStatistics::Chunk);
    for c in parquet.columns() {
        let float = matches!(c.physical_type(), PhysicalType::FLOAT | PhysicalType::DOUBLE);
        let vector = c.max_rep_level() > 0;
        let binary = c.physical_type() == PhysicalType::BYTE_ARRAY
            && c.converted_type() != ConvertedType::UTF8
            && c.logical_type_ref().is_none();
        if float || binary {
            b = b.set_column_dictionary_enabled(c.path().clone(), false);
        }
        if vector || binary {
            b = b.set_column_statistics_enabled(c.path().clone(), EnabledStatistics::None);
        }
    }
    b.build()
}

pub fn writer_properties() -> WriterProperties {
    WriterProperties::builder()
        .set_compression(Compression::ZSTD(ZstdLevel::try_new(ZSTD_LEVEL).expect("valid zstd level")))
        .set_max_row_group_row_count(Some(1 << 20))
        .build()
}

/// A page holds one episode's values of one column, or this many uncompressed bytes of them when
/// the episode is larger (long episodes, images): small enough to decode one at a time, large
/// enough that page headers and index entries stay a small fraction of the file.
pub const PAGE_MAX_BYTES: usize = 1 << 20;

/// Where the pages of one episode's column start and end: `(first row, rows)` of each, at most
/// [`PAGE_MAX_BYTES`] of values apiece (at least one row).
fn page_cuts(col: &dyn Array) -> Vec<(usize, usize)> {
    let n = col.len();
    let mut cuts = Vec::new();
    if let Some(bin) = col.as_any().downcast_ref::<BinaryArray>() {
        let offsets = bin.value_offsets();
        let mut start = 0;
        for end in 1..=n {
            if (offsets[end] - offsets[start]) as usize >= PAGE_MAX_BYTES || end == n {
                cuts.push((start, end - start));
                start = end;
            }
        }
        return cuts;
    }
    fixed_cuts(n, col.to_data().get_slice_memory_size().unwrap_or(n * 8))
}

/// [`page_cuts`] of a fixed-width column of `n` rows occupying `bytes`: as many rows a page as
/// [`PAGE_MAX_BYTES`] holds (at least one).
fn fixed_cuts(n: usize, bytes: usize) -> Vec<(usize, usize)> {
    let rows = (PAGE_MAX_BYTES / (bytes / n.max(1)).max(1)).max(1);
    let mut cuts = Vec::new();
    let mut start = 0;
    while start < n {
        let len = rows.min(n - start);
        cuts.push((start, len));
        start += len;
    }
    cuts
}

/// A row group is closed (between episodes) once it holds this many rows…
pub const ROW_GROUP_MAX_ROWS: usize = 1 << 20;
/// …or this many estimated encoded bytes.
pub const ROW_GROUP_MAX_BYTES: usize = 64 << 20;

/// Where an episode's rows are in its steps file.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct RowRange {
    pub row_group: usize,
    /// First row of the episode inside its row group.
    pub offset: usize,
    pub count: usize,
}

/// The row group being filled: one column writer per leaf column, the episode id column
/// (leaf 0) written last, once the episodes' ids are known. Image leaves are written by their
/// [`SpillColumn`] (pages to a temporary file), their in-memory writer left unused.
struct OpenRowGroup {
    writers: Vec<ArrowColumnWriter>,
    /// Per leaf: the spilled writer of an image column.
    spills: Vec<Option<SpillColumn>>,
    /// `(source index, rows)` of each episode, in order.
    episodes: Vec<(u32, usize)>,
    rows: usize,
}

impl OpenRowGroup {
    fn estimated_bytes(&self) -> usize {
        self.writers.iter().map(|w| w.get_estimated_total_bytes()).sum::<usize>()
            + self.spills.iter().flatten().map(SpillColumn::bytes_written).sum::<usize>()
    }
}

/// An encoded column chunk: in memory, or spilled to a temporary file (image columns).
enum Chunk {
    Memory(ArrowColumnChunk),
    Spilled(SpilledChunk),
}

/// A row group whose data columns are encoded and whose id column waits for the id prefix.
struct ClosedRowGroup {
    id_writer: ArrowColumnWriter,
    chunks: Vec<Chunk>,
    episodes: Vec<(u32, usize)>,
}

/// Bytes a steps file is written in (its encoded pages are buffered up to this much).
const WRITE_BUFFER_BYTES: usize = 1 << 20;

/// A Parquet steps file being filled in a temporary file (or a store's staging file). Several episodes share a row group
/// (cut between episodes at [`ROW_GROUP_MAX_ROWS`] / [`ROW_GROUP_MAX_BYTES`]);
/// [`Self::write_episode`] says where each one landed. The `episode_id` column
/// (`<prefix>-<index:05>`) is written when a row group closes; until the prefix (from the
/// source's sha256) is known, closed row groups wait, encoded (in memory, image columns in
/// their temporary files), and are appended to the file by [`Self::set_id_prefix`]. What stays
/// in memory is the open row group's non-image columns and a page per camera: never an
/// episode's frames.
pub struct StepsFileWriter {
    file: SerializedFileWriter<std::io::BufWriter<std::fs::File>>,
    factory: ArrowRowGroupWriterFactory,
    props: WriterPropertiesPtr,
    parquet: SchemaDescriptor,
    /// Per leaf: whether it is an image column's (written by a [`SpillColumn`]).
    image_leaf: Vec<bool>,
    pub schema: SchemaRef,
    open: Option<OpenRowGroup>,
    waiting: Vec<ClosedRowGroup>,
    waiting_bytes: usize,
    id_prefix: Option<String>,
    max_row_group_bytes: usize,
    pub rows: usize,
    pub row_groups: usize,
}

impl StepsFileWriter {
    pub fn new(schema: SchemaRef) -> Result<Self, StoreError> {
        let tmp = tempfile::tempfile()
            .map_err(|e| StoreError::invalid(format!("cannot create a temporary steps file: {e}")))?;
        Self::in_file(schema, tmp)
    }

    /// Like [`Self::new`], building the file in `file` (empty, opened for reading and writing):
    /// a local store stages it where the object will live, so storing it is a rename.
    pub fn in_file(schema: SchemaRef, file: std::fs::File) -> Result<Self, StoreError> {
        let parquet = ArrowSchemaConverter::new().convert(&schema)?;
        let mut props = steps_writer_properties(&parquet);
        add_encoded_arrow_schema_to_metadata(&schema, &mut props);
        let props = Arc::new(props);
        // Parquet buffers only 8 KiB: a file of small pages would be ~one write per page.
        let out = std::io::BufWriter::with_capacity(WRITE_BUFFER_BYTES, file);
        let file = SerializedFileWriter::new(out, parquet.root_schema_ptr(), props.clone())?;
        let factory = ArrowRowGroupWriterFactory::new(&file, schema.clone());
        let image_leaf = (0..parquet.num_columns())
            .map(|leaf| {
                let f = schema.field(parquet.get_column_root_idx(leaf));
                f.name().starts_with(IMAGE_PREFIX) && f.data_type() == &DataType::Binary
            })
            .collect();
        Ok(StepsFileWriter {
            file,
            factory,
            props,
            parquet,
            image_leaf,
            schema,
            open: None,
            waiting: Vec::new(),
            waiting_bytes: 0,
            id_prefix: None,
            max_row_group_bytes: ROW_GROUP_MAX_BYTES,
            rows: 0,
            row_groups: 0,
        })
    }

    /// Closes row groups past this many estimated encoded bytes instead of
    /// [`ROW_GROUP_MAX_BYTES`]: the open row group is what a writer holds in memory.
    pub fn with_max_row_group_bytes(mut self, bytes: usize) -> Self {
        self.max_row_group_bytes = bytes.max(1);
        self
    }

    /// The id prefix (`<source sha256[:12]>`) when known up front.
    pub fn with_id_prefix(mut self, prefix: &str) -> Self {
        self.id_prefix = Some(prefix.to_string());
        self
    }

    /// Sets the id prefix and writes the row groups that were waiting for it.
    pub fn set_id_prefix(&mut self, prefix: &str) -> Result<(), StoreError> {
        self.id_prefix = Some(prefix.to_string());
        for rg in std::mem::take(&mut self.waiting) {
            self.append_row_group(rg)?;
        }
        self.waiting_bytes = 0;
        Ok(())
    }

    /// Moves the file being built into `file` (empty, opened for reading and writing) if nothing
    /// has reached the current one yet, which holds until the id prefix is known (row groups wait
    /// in memory until then): a writer started before the source's hash was known is moved from
    /// its temporary file to a staging file in the store. Returns whether it moved.
    pub fn move_to(&mut self, file: std::fs::File) -> Result<bool, StoreError> {
        let current = self.file.inner_mut().get_mut();
        let written = current
            .metadata()
            .map_err(|e| StoreError::invalid(format!("cannot inspect a temporary steps file: {e}")))?
            .len();
        if written > 0 {
            return Ok(false);
        }
        *current = file;
        Ok(true)
    }

    /// Appends one episode: `columns` are its columns after `episode_id` (see
    /// [`episode_columns`]), `index` its source index. Returns where its rows are. A camera's
    /// frames are pulled a page (up to [`PAGE_MAX_BYTES`]) at a time and written to its
    /// temporary file; a frame source that fails, or holds more or fewer frames than the
    /// episode's steps, fails the episode (the file is then unusable: drop the writer).
    pub fn write_episode(&mut self, index: u32, columns: Vec<StepColumn>) -> Result<RowRange, StoreError> {
        let fields = self.schema.fields().clone();
        if columns.len() + 1 != fields.len() {
            return Err(StoreError::invalid(format!(
                "episode has {} columns, the steps file has {}",
                columns.len() + 1,
                fields.len()
            )));
        }
        let n = columns.first().map(StepColumn::rows).unwrap_or(0);
        if self.open.is_none() {
            let writers = self.factory.create_column_writers(self.row_groups)?;
            let mut spills = Vec::with_capacity(writers.len());
            for (leaf, image) in self.image_leaf.iter().enumerate() {
                spills.push(match image {
                    true => Some(SpillColumn::new(self.parquet.column(leaf), self.props.clone())?),
                    false => None,
                });
            }
            self.open = Some(OpenRowGroup { writers, spills, episodes: Vec::new(), rows: 0 });
            self.row_groups += 1;
        }
        let rg = self.open.as_mut().expect("row group just opened");
        // Leaf 0 is episode_id (written at close); every other field is one leaf here, but map
        // fields to leaves in order anyway. Each `write` is one page (see steps_writer_properties).
        let mut leaf = 1;
        for (field, col) in fields.iter().skip(1).zip(columns) {
            let (rows_of, data_type) = match &col {
                StepColumn::Values(a) => (a.len(), a.data_type()),
                StepColumn::Pages(p) => (p.len, &p.data_type),
                StepColumn::Frames(_) => (n, field.data_type()),
            };
            if rows_of != n || data_type != field.data_type() {
                return Err(StoreError::invalid(format!(
                    "column {:?}: {rows_of} rows of {data_type}, expected {n} of {}",
                    field.name(),
                    field.data_type()
                )));
            }
            // A paged column is cut where the whole column would be, so the file is the same.
            let (cuts, page): (_, Box<crate::ReadRows>) = match col {
                StepColumn::Values(a) => (page_cuts(a.as_ref()), Box::new(move |f, r| Ok(a.slice(f, r)))),
                StepColumn::Pages(p) => {
                    (fixed_cuts(p.len, p.slice_bytes), Box::new(move |f, r| p.read(f, r)))
                }
                StepColumn::Frames(frames) => {
                    let spill = rg.spills.get_mut(leaf).and_then(Option::as_mut).ok_or_else(|| {
                        StoreError::invalid(format!("column {:?} is not an image column", field.name()))
                    })?;
                    write_frames(spill, field.name(), frames, n)?;
                    leaf += 1;
                    continue;
                }
            };
            let mut leaves = 0;
            for (first, rows) in cuts {
                let page = page(first, rows)?;
                for (k, l) in compute_leaves(field, &page)?.into_iter().enumerate() {
                    let w = rg
                        .writers
                        .get_mut(leaf + k)
                        .ok_or_else(|| StoreError::invalid("schema leaf mismatch"))?;
                    w.write(&l)?;
                    leaves = leaves.max(k + 1);
                }
            }
            leaf += leaves;
        }
        let range = RowRange { row_group: self.row_groups - 1, offset: rg.rows, count: n };
        rg.episodes.push((index, n));
        rg.rows += n;
        self.rows += n;
        let full = rg.rows >= ROW_GROUP_MAX_ROWS || rg.estimated_bytes() >= self.max_row_group_bytes;
        if full {
            self.close_row_group()?;
        }
        Ok(range)
    }

    fn close_row_group(&mut self) -> Result<(), StoreError> {
        let Some(rg) = self.open.take() else { return Ok(()) };
        let mut writers = rg.writers.into_iter().zip(rg.spills);
        let (id_writer, _) =
            writers.next().ok_or_else(|| StoreError::invalid("steps schema has no columns"))?;
        let chunks = writers
            .map(|(w, spill)| match spill {
                Some(s) => s.close().map(Chunk::Spilled),
                None => Ok(Chunk::Memory(w.close()?)),
            })
            .collect::<Result<Vec<_>, StoreError>>()?;
        let closed = ClosedRowGroup { id_writer, chunks, episodes: rg.episodes };
        if self.id_prefix.is_some() && self.waiting.is_empty() {
            self.append_row_group(closed)
        } else {
            self.waiting_bytes += closed
                .chunks
                .iter()
                .map(|c| match c {
                    Chunk::Memory(c) => c.close().bytes_written as usize,
                    Chunk::Spilled(c) => c.bytes(),
                })
                .sum::<usize>();
            self.waiting.push(closed);
            Ok(())
        }
    }

    fn append_row_group(&mut self, rg: ClosedRowGroup) -> Result<(), StoreError> {
        let prefix =
            self.id_prefix.as_deref().ok_or_else(|| StoreError::invalid("episode ids are not known yet"))?;
        let mut id_writer = rg.id_writer;
        let field = self.schema.field(0);
        for (index, n) in &rg.episodes {
            let id = episode_id(prefix, *index);
            let col: ArrayRef = Arc::new(StringArray::from(vec![id.as_str(); *n]));
            for l in compute_leaves(field, &col)? {
                id_writer.write(&l)?;
            }
        }
        let mut w = self.file.next_row_group()?;
        id_writer.close()?.append_to_row_group(&mut w)?;
        for c in rg.chunks {
            match c {
                Chunk::Memory(c) => c.append_to_row_group(&mut w)?,
                Chunk::Spilled(c) => c.append_to_row_group(&mut w)?,
            }
        }
        w.close()?;
        Ok(())
    }

    /// Encoded bytes so far (written, waiting, and an estimate for the open row group).
    pub fn bytes_written(&self) -> usize {
        self.file.bytes_written()
            + self.waiting_bytes
            + self.open.as_ref().map_or(0, OpenRowGroup::estimated_bytes)
    }

    /// Closes the file (the id prefix must be known) and returns it (the temporary or staging
    /// file it was built in, read from its start) and its size.
    pub fn finish(mut self) -> Result<(std::fs::File, u64), StoreError> {
        use std::io::{Seek, SeekFrom};
        self.close_row_group()?;
        if !self.waiting.is_empty() {
            return Err(StoreError::invalid("steps file finished before its episode ids were known"));
        }
        let mut f = self.file.into_inner()?.into_inner().map_err(|e| {
            StoreError::invalid(format!("cannot write a temporary steps file: {}", e.error()))
        })?;
        let size = f
            .seek(SeekFrom::End(0))
            .and_then(|n| f.seek(SeekFrom::Start(0)).map(|_| n))
            .map_err(|e| StoreError::invalid(format!("cannot read back a temporary steps file: {e}")))?;
        Ok((f, size))
    }
}

/// Pulls a camera's `n` frames and writes them as pages of up to [`PAGE_MAX_BYTES`] (at least
/// one frame each): memory is a page, whatever the episode's length.
fn write_frames(spill: &mut SpillColumn, column: &str, frames: Frames, n: usize) -> Result<(), StoreError> {
    let mut page: Vec<Vec<u8>> = Vec::new();
    let mut page_bytes = 0usize;
    let mut got = 0usize;
    for f in frames {
        let f = f.map_err(|e| StoreError::invalid(format!("column {column:?}: {e}")))?;
        got += 1;
        if got > n {
            return Err(StoreError::invalid(format!("column {column:?} has more than {n} frames")));
        }
        page_bytes += f.len();
        page.push(f);
        if page_bytes >= PAGE_MAX_BYTES {
            spill.write_page(std::mem::take(&mut page))?;
            page_bytes = 0;
        }
    }
    if got != n {
        return Err(StoreError::invalid(format!("column {column:?} has {got} frames for {n} steps")));
    }
    if !page.is_empty() {
        spill.write_page(page)?;
    }
    Ok(())
}

/// An episode's id: `<source sha256[:12]>-<index:05>`.
pub fn episode_id(prefix: &str, index: u32) -> String {
    format!("{prefix}-{index:05}")
}

/// Reads one row group (one episode, in stores written before row ranges) of a steps file.
pub fn read_row_group(data: Bytes, row_group: usize) -> Result<RecordBatch, StoreError> {
    read_rows(data, row_group, None)
}

/// Reads `range = (offset, count)` rows of a row group (all of it for `None`), skipping the pages
/// before and after them (the offset index says where pages start).
pub fn read_rows(
    data: Bytes,
    row_group: usize,
    range: Option<(usize, usize)>,
) -> Result<RecordBatch, StoreError> {
    let opts = ArrowReaderOptions::new().with_page_index_policy(PageIndexPolicy::Optional);
    let builder = ParquetRecordBatchReaderBuilder::try_new_with_options(data, opts)?;
    let n_groups = builder.metadata().num_row_groups();
    if row_group >= n_groups {
        return Err(StoreError::Corrupt(format!(
            "steps file has {n_groups} row groups, episode points at {row_group}"
        )));
    }
    let rg_rows = builder.metadata().row_group(row_group).num_rows().max(0) as usize;
    let schema = builder.schema().clone();
    let mut builder = builder.with_row_groups(vec![row_group]).with_batch_size(1 << 20);
    let expect = match range {
        None => rg_rows,
        Some((offset, count)) => {
            if offset.checked_add(count).is_none_or(|end| end > rg_rows) {
                return Err(StoreError::Corrupt(format!(
                    "row group {row_group} has {rg_rows} rows, episode points at rows {offset}..{}",
                    offset.saturating_add(count)
                )));
            }
            let mut sel = Vec::with_capacity(3);
            if offset > 0 {
                sel.push(RowSelector::skip(offset));
            }
            sel.push(RowSelector::select(count));
            if offset + count < rg_rows {
                sel.push(RowSelector::skip(rg_rows - offset - count));
            }
            builder = builder.with_row_selection(RowSelection::from(sel));
            count
        }
    };
    let reader = builder.build()?;
    let batches: Vec<RecordBatch> = reader.collect::<Result<_, _>>()?;
    let batch = arrow::compute::concat_batches(&schema, &batches)?;
    if batch.num_rows() != expect {
        return Err(StoreError::Corrupt(format!("read {} rows, expected {expect}", batch.num_rows())));
    }
    Ok(batch)
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

/// A row of a version's labels file. A `full` file has one row per visible episode; a `delta`
/// file (store/README.md, "Label files") one per episode the version added, relabeled or removed.
#[derive(Debug, Clone, PartialEq)]
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
    /// The episode's first row inside its row group, and its number of rows.
    pub row_offset: i64,
    pub row_count: i64,
    /// In a delta file: the episode left the store in this version (its row holds its last label).
    pub removed: bool,
}

/// What a labels file holds: every visible episode, or the rows one version changed.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LabelsKind {
    Full,
    Delta,
}

impl LabelsKind {
    pub fn as_str(self) -> &'static str {
        match self {
            LabelsKind::Full => "full",
            LabelsKind::Delta => "delta",
        }
    }
}

/// Metadata key naming a labels file's [`LabelsKind`].
pub const LABELS_KIND_KEY: &str = "ufops.labels";

pub fn labels_file(version_hint: i64, kind: LabelsKind, rows: &[LabelRow]) -> Result<Vec<u8>, StoreError> {
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
            Field::new("row_offset", DataType::Int64, false),
            Field::new("row_count", DataType::Int64, false),
            Field::new("removed", DataType::Boolean, false),
        ])
        .with_metadata(HashMap::from([
            ("ufops.schema_version".to_string(), SCHEMA_VERSION.to_string()),
            ("ufops.version".to_string(), version_hint.to_string()),
            (LABELS_KIND_KEY.to_string(), kind.as_str().to_string()),
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
        Arc::new(Int64Array::from_iter_values(rows.iter().map(|r| r.row_offset))),
        Arc::new(Int64Array::from_iter_values(rows.iter().map(|r| r.row_count))),
        Arc::new(BooleanArray::from(rows.iter().map(|r| r.removed).collect::<Vec<_>>())),
    ];
    let batch = RecordBatch::try_new(schema.clone(), cols)?;
    let mut w = ArrowWriter::try_new(Vec::new(), schema, Some(writer_properties()))?;
    w.write(&batch)?;
    Ok(w.into_inner()?)
}

/// Reads a labels file back: its kind (files written before deltas carry none: full) and rows.
pub fn read_labels_file(data: Bytes) -> Result<(LabelsKind, Vec<LabelRow>), StoreError> {
    use arrow::array::{Array, AsArray};
    use arrow::datatypes::Int64Type;
    let bad = |what: &str| StoreError::invalid(format!("labels file: {what}"));
    let builder = ParquetRecordBatchReaderBuilder::try_new(data)?;
    // The Arrow schema's metadata (stored in the file's `ARROW:schema`).
    let kind = match builder.schema().metadata().get(LABELS_KIND_KEY).cloned() {
        Some(k) if k == "delta" => LabelsKind::Delta,
        Some(k) if k != "full" => return Err(bad(&format!("unknown kind {k:?}"))),
        _ => LabelsKind::Full,
    };
    let mut out = Vec::new();
    for batch in builder.build()? {
        let b = batch?;
        let col = |name: &str| b.column_by_name(name).ok_or_else(|| bad(&format!("no column {name}")));
        let strs = |name: &str| -> Result<_, StoreError> {
            col(name)?.as_string_opt::<i32>().cloned().ok_or_else(|| bad(&format!("{name} is not text")))
        };
        let ints = |name: &str| -> Result<_, StoreError> {
            col(name)?
                .as_primitive_opt::<Int64Type>()
                .cloned()
                .ok_or_else(|| bad(&format!("{name} is not int64")))
        };
        let (id, policy, checkpoint, task, label, source, data_file) = (
            strs("episode_id")?,
            strs("policy")?,
            strs("checkpoint")?,
            strs("task")?,
            strs("label")?,
            strs("label_source")?,
            strs("data_file")?,
        );
        let (length, revision, row_group, row_offset, row_count) = (
            ints("length")?,
            ints("label_revision")?,
            ints("row_group")?,
            ints("row_offset")?,
            ints("row_count")?,
        );
        let removed = match b.column_by_name("removed") {
            Some(c) => Some(c.as_boolean_opt().cloned().ok_or_else(|| bad("removed is not boolean"))?),
            None => None,
        };
        for i in 0..b.num_rows() {
            out.push(LabelRow {
                episode_id: id.value(i).to_string(),
                policy: policy.value(i).to_string(),
                checkpoint: checkpoint.value(i).to_string(),
                task: task.is_valid(i).then(|| task.value(i).to_string()),
                length: length.value(i),
                label: label.value(i).parse()?,
                label_source: source.value(i).to_string(),
                revision: revision.value(i),
                data_file: data_file.value(i).to_string(),
                row_group: row_group.value(i),
                row_offset: row_offset.value(i),
                row_count: row_count.value(i),
                removed: removed.as_ref().is_some_and(|r| r.value(i)),
            });
        }
    }
    Ok((kind, out))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn batch(first: i32, n: i32) -> RecordBatch {
        let a: ArrayRef = Arc::new(Int32Array::from_iter_values(first..first + n));
        RecordBatch::try_from_iter([("t", a)]).unwrap()
    }

    fn ints(b: &RecordBatch) -> Vec<i32> {
        b.column(0).as_any().downcast_ref::<Int32Array>().unwrap().values().to_vec()
    }

    /// Files of stores before row ranges (one row group per episode) read whole; row ranges read
    /// exactly their rows, across page boundaries; a range past the row group is an error.
    #[test]
    fn row_groups_and_row_ranges() {
        let b0 = batch(0, 5);
        let mut w = ArrowWriter::try_new(Vec::new(), b0.schema(), Some(writer_properties())).unwrap();
        w.write(&b0).unwrap();
        w.flush().unwrap();
        w.write(&batch(100, 3)).unwrap();
        w.flush().unwrap();
        let old = Bytes::from(w.into_inner().unwrap());
        assert_eq!(ints(&read_row_group(old.clone(), 1).unwrap()), vec![100, 101, 102]);
        assert!(read_row_group(old, 2).is_err());

        let props =
            WriterProperties::builder().set_data_page_row_count_limit(64).set_write_batch_size(64).build();
        let big = batch(0, 10_000);
        let mut w = ArrowWriter::try_new(Vec::new(), big.schema(), Some(props)).unwrap();
        w.write(&big).unwrap();
        let data = Bytes::from(w.into_inner().unwrap());
        for (off, n) in [(0, 1), (0, 10_000), (63, 2), (5_000, 777), (9_999, 1)] {
            let got = ints(&read_rows(data.clone(), 0, Some((off, n))).unwrap());
            assert_eq!(got, (off as i32..(off + n) as i32).collect::<Vec<_>>(), "{off}+{n}");
        }
        assert!(read_rows(data.clone(), 0, Some((9_999, 2))).is_err());
        assert!(read_rows(data, 0, Some((usize::MAX, 2))).is_err());
    }
}
