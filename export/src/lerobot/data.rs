//! `data/chunk-XXX/file-YYY.parquet`: the [`Writer`] that turns each episode's steps into
//! LeRobot's per-frame rows, gathers their statistics and rolls data files over past 100 MB.

use std::collections::BTreeMap;
use std::fs::File;
use std::path::PathBuf;
use std::sync::Arc;

use arrow::array::{
    ArrayRef, AsArray, BinaryArray, BooleanArray, Float32Array, Float64Array, Int64Array, RecordBatch,
    StringArray, StructArray,
};
use arrow::datatypes::{DataType, Field, Fields, Float64Type, Schema, SchemaRef};
use parquet::arrow::ArrowWriter;
use parquet::basic::{Compression, ZstdLevel};
use parquet::file::properties::WriterProperties;
use store::steps::{IMAGE_PREFIX, INTERVENTION_COLUMN, MEDIA_PREFIX, OBS_PREFIX, VALIDITY_COLUMN};
use store::{EpisodeRecord, Label};

use super::stats::{f32_values, Stats};
use super::{
    feature_key, fill, layout_of, Layout, CHUNKS_SIZE, DATA_FILE_BYTES, DATA_PATH, NO_TASK, VALIDITY_KEY,
};
use crate::{ExportError, Result};

struct DataFile {
    path: PathBuf,
    writer: ArrowWriter<File>,
}

pub(super) struct Writer<'a> {
    root: PathBuf,
    schema: SchemaRef,
    pub(super) layout: Layout,
    pub(super) fps: f64,
    pub(super) labeled: bool,
    pub(super) tasks: &'a BTreeMap<String, i64>,
    /// Validity as GR00T's task indexes `(valid, invalid)`, else as a bool.
    pub(super) validity_tasks: Option<(i64, i64)>,
    file: Option<DataFile>,
    file_index: usize,
    pub(super) frames: i64,
    pub(super) stats: BTreeMap<String, Stats>,
    pub(super) episodes: Vec<EpisodeRow>,
    /// video key → store objects in order of first use (their index is the file index)
    pub(super) videos: BTreeMap<String, Vec<String>>,
}

/// One exported episode as `meta/episodes` lists it: where its rows and videos are, its label
/// and provenance (recorded by the [`Writer`] as it writes the episode's data).
pub(super) struct EpisodeRow {
    pub(super) index: i64,
    pub(super) task: String,
    pub(super) length: i64,
    pub(super) data_file: usize,
    pub(super) from: i64,
    /// per video key: (file index, from_timestamp, to_timestamp)
    pub(super) videos: Vec<(usize, f64, f64)>,
    pub(super) id: String,
    pub(super) label: Label,
    pub(super) source_name: String,
    pub(super) part: Option<String>,
    /// The episode's verifier score when the export was curated by one.
    pub(super) score: Option<f64>,
    /// From the label event that set the exported label: the failure cause and the time spans
    /// (JSON), when the labelers gave them.
    pub(super) failure_cause: Option<String>,
    pub(super) spans: Option<String>,
}

pub(super) fn data_props() -> WriterProperties {
    WriterProperties::builder()
        .set_compression(Compression::ZSTD(ZstdLevel::try_new(1).expect("valid level")))
        .set_max_row_group_row_count(Some(100_000))
        .build()
}

fn image_type() -> DataType {
    DataType::Struct(Fields::from(vec![
        Field::new("bytes", DataType::Binary, true),
        Field::new("path", DataType::Utf8, true),
    ]))
}

fn data_schema(steps: &Schema, l: &Layout, labeled: bool, validity_as_task: bool) -> Result<SchemaRef> {
    let mut fields = Vec::new();
    let field_of = |name: &str| -> Result<Field> {
        steps
            .field_with_name(name)
            .map(|f| f.as_ref().clone())
            .map_err(|_| ExportError::invalid(format!("steps have no column {name}")))
    };
    for (k, _) in &l.obs {
        fields.push(Field::new(
            feature_key(k),
            field_of(&format!("{OBS_PREFIX}{k}"))?.data_type().clone(),
            false,
        ));
    }
    fields.push(Field::new("action", field_of("action")?.data_type().clone(), false));
    for (k, _) in &l.images {
        fields.push(Field::new(feature_key(k), image_type(), false));
    }
    fields.push(Field::new("next.reward", DataType::Float32, false));
    fields.push(Field::new("next.done", DataType::Boolean, false));
    if labeled {
        fields.push(Field::new("next.success", DataType::Boolean, true));
    }
    if l.intervention {
        fields.push(Field::new(INTERVENTION_COLUMN, DataType::Boolean, false));
    }
    if l.validity {
        let dtype = if validity_as_task { DataType::Int64 } else { DataType::Boolean };
        fields.push(Field::new(VALIDITY_KEY, dtype, false));
    }
    fields.push(Field::new("timestamp", DataType::Float32, false));
    for k in ["frame_index", "episode_index", "index", "task_index"] {
        fields.push(Field::new(k, DataType::Int64, false));
    }
    Ok(Arc::new(Schema::new(fields)))
}

impl<'a> Writer<'a> {
    /// The writer of a dataset whose feature set is the first episode's (`e`, `steps`); its fps
    /// is the sources' (`fps`) or, when they give none, estimated from the episode's step times.
    pub(super) fn for_first_episode(
        root: PathBuf,
        e: &EpisodeRecord,
        steps: &RecordBatch,
        fps: Option<f64>,
        labeled: bool,
        tasks: &'a BTreeMap<String, i64>,
        validity_tasks: Option<(i64, i64)>,
    ) -> Result<Self> {
        let layout = layout_of(&steps.schema())?;
        if layout.action == 0 {
            return Err(no_actions(e));
        }
        let fps = match fps {
            Some(f) => f,
            None => estimate_fps(steps),
        };
        let schema = data_schema(&steps.schema(), &layout, labeled, validity_tasks.is_some())?;
        Ok(Writer {
            root,
            schema,
            layout,
            fps,
            labeled,
            tasks,
            validity_tasks,
            file: None,
            file_index: 0,
            frames: 0,
            stats: BTreeMap::new(),
            episodes: Vec::new(),
            videos: BTreeMap::new(),
        })
    }

    fn column<'b>(&self, steps: &'b RecordBatch, name: &str, e: &EpisodeRecord) -> Result<&'b ArrayRef> {
        steps
            .column_by_name(name)
            .ok_or_else(|| ExportError::invalid(format!("episode {}: no column {name}", e.id)))
    }

    /// Appends one episode: its frames to the open data file (the next one when none is open,
    /// closed past `DATA_FILE_BYTES`), its values to the statistics, its row to `meta/episodes`.
    pub(super) fn add(
        &mut self,
        index: usize,
        e: &EpisodeRecord,
        steps: RecordBatch,
        part: Option<&String>,
        score: Option<f64>,
        label_data: Option<&serde_json::Value>,
    ) -> Result<()> {
        self.check_layout(e, &steps)?;
        let n = steps.num_rows();
        let mut cols = self.feature_columns(e, &steps)?;
        self.outcome_columns(e, &steps, &mut cols)?;
        self.flag_columns(e, &steps, &mut cols)?;
        let ts = self.column(&steps, "timestamp", e)?.as_primitive::<Float64Type>().clone();
        let task = e.task.clone().unwrap_or_else(|| NO_TASK.to_string());
        self.time_and_index_columns(index, &task, &ts, &mut cols);
        let videos = self.video_spans(e, &steps, &ts)?;
        self.write_batch(e, cols)?;
        self.episodes.push(EpisodeRow {
            index: index as i64,
            task,
            length: n as i64,
            data_file: self.file_index,
            from: self.frames,
            videos,
            id: e.id.clone(),
            label: e.label,
            source_name: e.source_name.clone(),
            part: part.cloned(),
            score,
            failure_cause: crate::failure_cause(label_data),
            spans: crate::label_spans(label_data),
        });
        self.frames += n as i64;
        let df = self.file.as_ref().expect("written above");
        if df.writer.bytes_written() + df.writer.in_progress_size() > DATA_FILE_BYTES {
            self.close_file()?;
        }
        Ok(())
    }

    /// Fails unless the episode has actions and the step columns of the first one exported.
    fn check_layout(&self, e: &EpisodeRecord, steps: &RecordBatch) -> Result<()> {
        let l = layout_of(&steps.schema())?;
        if l.action == 0 {
            return Err(no_actions(e));
        }
        if l != self.layout {
            return Err(ExportError::invalid(format!(
                "episode {} has other step columns than the first one exported ({:?} vs {:?}): a LeRobot dataset has one feature set; export them separately",
                e.id, l, self.layout
            )));
        }
        Ok(())
    }

    /// The `observation.*` vectors, `action` and images (LeRobot's `struct<bytes, path>`, no
    /// path), with the statistics of the vectors.
    fn feature_columns(&mut self, e: &EpisodeRecord, steps: &RecordBatch) -> Result<Vec<ArrayRef>> {
        let n = steps.num_rows();
        let mut cols: Vec<ArrayRef> = Vec::new();
        for (k, _) in &self.layout.obs {
            let c = self.column(steps, &format!("{OBS_PREFIX}{k}"), e)?.clone();
            self.stats
                .entry(feature_key(k))
                .or_default()
                .add(c.as_fixed_size_list().value_length() as usize, f32_values(&c).into_iter());
            cols.push(c);
        }
        let action = self.column(steps, "action", e)?.clone();
        self.stats
            .entry("action".into())
            .or_default()
            .add(self.layout.action, f32_values(&action).into_iter());
        cols.push(action);
        for (k, _) in &self.layout.images {
            let bin = self.column(steps, &format!("{IMAGE_PREFIX}{k}"), e)?.clone();
            let bin: ArrayRef = Arc::new(bin.as_binary::<i32>().clone() as BinaryArray);
            let paths: ArrayRef = Arc::new(StringArray::new_null(n));
            let DataType::Struct(fields) = image_type() else { unreachable!("struct type") };
            cols.push(Arc::new(
                StructArray::try_new(fields, vec![bin, paths], None)
                    .map_err(|e| ExportError::invalid(e.to_string()))?,
            ));
        }
        Ok(cols)
    }

    /// `next.reward`, `next.done` and, when any episode is labeled, `next.success` (true on the
    /// last frame of a success, null through an unlabeled episode), with their statistics.
    fn outcome_columns(
        &mut self,
        e: &EpisodeRecord,
        steps: &RecordBatch,
        cols: &mut Vec<ArrayRef>,
    ) -> Result<()> {
        let n = steps.num_rows();
        let reward = self.column(steps, "reward", e)?.clone();
        let done = self.column(steps, "done", e)?.clone();
        self.stats.entry("next.reward".into()).or_default().add(1, f32_values(&reward).into_iter());
        self.stats.entry("next.done".into()).or_default().add(1, f32_values(&done).into_iter());
        cols.push(reward);
        cols.push(done);
        if self.labeled {
            let s: BooleanArray = match e.label {
                Label::Unknown => BooleanArray::new_null(n),
                l => (0..n).map(|t| Some(l == Label::Success && t + 1 == n)).collect(),
            };
            let s: ArrayRef = Arc::new(s);
            self.stats.entry("next.success".into()).or_default().add(1, f32_values(&s).into_iter());
            cols.push(s);
        }
        Ok(())
    }

    /// The per-step flags the layout has: `intervention`, and validity as GR00T's task index or
    /// a bool, with their statistics.
    fn flag_columns(
        &mut self,
        e: &EpisodeRecord,
        steps: &RecordBatch,
        cols: &mut Vec<ArrayRef>,
    ) -> Result<()> {
        if self.layout.intervention {
            let c = self.column(steps, INTERVENTION_COLUMN, e)?.clone();
            self.stats.entry(INTERVENTION_COLUMN.into()).or_default().add(1, f32_values(&c).into_iter());
            cols.push(c);
        }
        if self.layout.validity {
            let c = self.column(steps, VALIDITY_COLUMN, e)?.clone();
            let c: ArrayRef = match self.validity_tasks {
                Some((valid, invalid)) => {
                    Arc::new(Int64Array::from_iter_values(c.as_boolean().iter().map(|b| {
                        if b == Some(true) {
                            valid
                        } else {
                            invalid
                        }
                    })))
                }
                None => c,
            };
            self.stats.entry(VALIDITY_KEY.into()).or_default().add(1, f32_values(&c).into_iter());
            cols.push(c);
        }
        Ok(())
    }

    /// `timestamp` (float32), `frame_index`, `episode_index`, `index` (counted across the
    /// dataset) and `task_index`, with their statistics.
    fn time_and_index_columns(
        &mut self,
        index: usize,
        task: &str,
        ts: &Float64Array,
        cols: &mut Vec<ArrayRef>,
    ) {
        let n = ts.len();
        let ts32: ArrayRef = Arc::new(Float32Array::from_iter_values(ts.values().iter().map(|&t| t as f32)));
        self.stats.entry("timestamp".into()).or_default().add(1, f32_values(&ts32).into_iter());
        cols.push(ts32);
        let task_index = self.tasks[task];
        let ints: [(&str, Vec<i64>); 4] = [
            ("frame_index", (0..n as i64).collect()),
            ("episode_index", vec![index as i64; n]),
            ("index", (self.frames..self.frames + n as i64).collect()),
            ("task_index", vec![task_index; n]),
        ];
        for (name, v) in ints {
            self.stats.entry(name.into()).or_default().add(1, v.iter().map(|&x| x as f64));
            cols.push(Arc::new(Int64Array::from(v)));
        }
    }

    /// Per video key: the file of the episode's store object (one per object, numbered in order
    /// of first use) and the episode's span in it, from its first frame's time.
    fn video_spans(
        &mut self,
        e: &EpisodeRecord,
        steps: &RecordBatch,
        ts: &Float64Array,
    ) -> Result<Vec<(usize, f64, f64)>> {
        let n = steps.num_rows();
        let mut videos = Vec::new();
        for k in &self.layout.videos {
            let path = self
                .column(steps, &format!("{MEDIA_PREFIX}{k}.path"), e)?
                .as_string::<i32>()
                .value(0)
                .to_string();
            let mts = self
                .column(steps, &format!("{MEDIA_PREFIX}{k}.timestamp"), e)?
                .as_primitive::<Float64Type>()
                .value(0);
            let from = mts - ts.value(0);
            let objs = self.videos.entry(k.clone()).or_default();
            let file = match objs.iter().position(|p| *p == path) {
                Some(i) => i,
                None => {
                    objs.push(path);
                    objs.len() - 1
                }
            };
            videos.push((file, from, from + n as f64 / self.fps));
        }
        Ok(videos)
    }

    /// Writes the episode's columns to the open data file, opening the next one when none is.
    fn write_batch(&mut self, e: &EpisodeRecord, cols: Vec<ArrayRef>) -> Result<()> {
        let batch = RecordBatch::try_new(self.schema.clone(), cols)
            .map_err(|err| ExportError::invalid(format!("episode {}: {err}", e.id)))?;
        if self.file.is_none() {
            let rel = fill(DATA_PATH, None, self.file_index / CHUNKS_SIZE, self.file_index % CHUNKS_SIZE);
            let path = self.root.join(rel);
            std::fs::create_dir_all(path.parent().expect("has a parent"))
                .map_err(|err| ExportError::io(&path, err))?;
            let f = File::create(&path).map_err(|err| ExportError::io(&path, err))?;
            let writer = ArrowWriter::try_new(f, self.schema.clone(), Some(data_props()))
                .map_err(|err| ExportError::write(&path, err))?;
            self.file = Some(DataFile { path, writer });
        }
        let df = self.file.as_mut().expect("opened above");
        df.writer.write(&batch).map_err(|err| ExportError::write(&df.path, err))?;
        Ok(())
    }

    pub(super) fn close_file(&mut self) -> Result<()> {
        if let Some(df) = self.file.take() {
            df.writer.close().map_err(|err| ExportError::write(&df.path, err))?;
            self.file_index += 1;
        }
        Ok(())
    }
}

fn no_actions(e: &EpisodeRecord) -> ExportError {
    ExportError::invalid(format!(
        "episode {} has no actions: a LeRobot dataset needs an action per frame (select episodes with actions)",
        e.id
    ))
}

/// Frames per second from an episode's step times (median interval), 10 when they say nothing.
fn estimate_fps(steps: &RecordBatch) -> f64 {
    let Some(ts) = steps.column_by_name("timestamp") else { return 10.0 };
    let ts = ts.as_primitive::<Float64Type>();
    let mut dts: Vec<f64> = ts.values().windows(2).map(|w| w[1] - w[0]).filter(|d| *d > 0.0).collect();
    if dts.is_empty() {
        return 10.0;
    }
    dts.sort_by(f64::total_cmp);
    let f = 1.0 / dts[dts.len() / 2];
    if f.is_finite() {
        (f * 1000.0).round() / 1000.0
    } else {
        10.0
    }
}
