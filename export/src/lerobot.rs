//! LeRobot v3.0 datasets (`codebase_version: v3.0`, as lerobot 0.6 writes them):
//!
//! * `data/chunk-XXX/file-YYY.parquet`: one row per frame — `observation.<key>` (float32 lists),
//!   `observation.<camera>` for PNG image columns (`struct<bytes, path>`), `action`,
//!   `next.reward`, `next.done`, `next.success` (true on the last frame of a successful episode,
//!   null through an unlabeled one; absent when no episode is labeled), `timestamp` (float32),
//!   `frame_index`, `episode_index`, `index`, `task_index`; files roll over past 100 MB;
//! * `videos/<key>/chunk-XXX/file-YYY.mp4`: the store's video objects copied byte for byte (never
//!   re-encoded), one file per object; each episode's frames are located in it by
//!   `from_timestamp`/`to_timestamp` in the episode metadata, as v3.0 expects;
//! * `meta/info.json` (features, fps, paths, and `ufops`: where the export came from),
//!   `meta/stats.json`, `meta/tasks.parquet`, `meta/episodes/chunk-000/file-000.parquet`
//!   (with `ufops/episode_id`, `ufops/label`, `ufops/source_name`, `ufops/split_part`).
//!
//! Human takeovers (the steps column `intervention`) are written as the bool feature
//! `intervention`, as LeRobot's DAgger recordings have it; validity (`validity`) as GR00T's
//! `annotation.human.validity`, an index into the tasks `valid` / `invalid` when the source was
//! such a dataset (its tasks then hold them), else a bool.
//!
//! Extra columns (`extra.*`: robomimic `states`, `next_obs`) have no LeRobot feature: they are
//! listed in the report's warnings.

use std::collections::{BTreeMap, HashMap};
use std::fs::File;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use arrow::array::{
    Array, ArrayRef, AsArray, BinaryArray, BooleanArray, Float32Array, Int64Array, ListBuilder, RecordBatch,
    StringArray, StringBuilder, StructArray,
};
use arrow::datatypes::{DataType, Field, Fields, Float32Type, Float64Type, Schema, SchemaRef};
use parquet::arrow::ArrowWriter;
use parquet::basic::{Compression, ZstdLevel};
use parquet::file::properties::WriterProperties;
use serde_json::{json, Map, Value};
use store::steps::{
    EXTRA_PREFIX, IMAGE_PREFIX, INTERVENTION_COLUMN, MEDIA_PREFIX, OBS_PREFIX, VALIDITY_COLUMN,
};
use store::{EpisodeRecord, Label, Store};

use crate::{
    count_label, disk_size, for_each_episode_with_layers, ExportError, ExportReport, Progress, Result,
    Selected, Staged,
};

pub const CODEBASE_VERSION: &str = "v3.0";
const CHUNKS_SIZE: usize = 1000;
const DATA_FILE_BYTES: usize = 100 << 20;
const DATA_PATH: &str = "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet";
const VIDEO_PATH: &str = "videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4";
/// The task of episodes that have none (LeRobot needs one per frame).
pub const NO_TASK: &str = "(no task)";
/// Video objects are copied in pieces of this size.
const COPY_BYTES: u64 = 8 << 20;
/// GR00T's per-frame validity feature (what ingest reads it from).
const VALIDITY_KEY: &str = "annotation.human.validity";
/// The tasks GR00T's validity indexes name.
const VALID_TASKS: [&str; 2] = ["valid", "invalid"];

/// The step columns of the first episode, which every other must share (a LeRobot dataset has
/// one feature set).
#[derive(Debug, Clone, PartialEq)]
struct Layout {
    /// (store key, dimension)
    obs: Vec<(String, usize)>,
    action: usize,
    /// (store key, [H, W, C])
    images: Vec<(String, Vec<usize>)>,
    videos: Vec<String>,
    extras: Vec<String>,
    /// The per-step flags (steps columns `intervention`, `validity`).
    intervention: bool,
    validity: bool,
}

fn layout_of(schema: &Schema) -> Result<Layout> {
    let mut l = Layout {
        obs: vec![],
        action: 0,
        images: vec![],
        videos: vec![],
        extras: vec![],
        intervention: false,
        validity: false,
    };
    for f in schema.fields() {
        let n = f.name();
        if let Some(k) = n.strip_prefix(OBS_PREFIX) {
            if let DataType::FixedSizeList(_, d) = f.data_type() {
                l.obs.push((k.to_string(), *d as usize));
            }
        } else if n == "action" {
            if let DataType::FixedSizeList(_, d) = f.data_type() {
                l.action = *d as usize;
            }
        } else if let Some(k) = n.strip_prefix(IMAGE_PREFIX) {
            let shape = f
                .metadata()
                .get("ufops.shape")
                .and_then(|s| serde_json::from_str::<Vec<usize>>(s).ok())
                .unwrap_or_default();
            l.images.push((k.to_string(), shape));
        } else if let Some(k) = n.strip_prefix(MEDIA_PREFIX).and_then(|k| k.strip_suffix(".path")) {
            l.videos.push(k.to_string());
        } else if let Some(k) = n.strip_prefix(EXTRA_PREFIX) {
            l.extras.push(k.to_string());
        } else if n == INTERVENTION_COLUMN {
            l.intervention = true;
        } else if n == VALIDITY_COLUMN {
            l.validity = true;
        }
    }
    Ok(l)
}

/// LeRobot's key for a store observation, image or video key (`state` → `observation.state`).
fn feature_key(k: &str) -> String {
    format!("observation.{k}")
}

/// Running min / max / mean / std per dimension (meta/stats.json).
#[derive(Default)]
struct Stats {
    min: Vec<f64>,
    max: Vec<f64>,
    sum: Vec<f64>,
    sumsq: Vec<f64>,
    count: u64,
}

impl Stats {
    fn add(&mut self, dim: usize, values: impl Iterator<Item = f64>) {
        if self.min.is_empty() {
            self.min = vec![f64::INFINITY; dim];
            self.max = vec![f64::NEG_INFINITY; dim];
            self.sum = vec![0.0; dim];
            self.sumsq = vec![0.0; dim];
        }
        for (k, v) in values.into_iter().enumerate() {
            let d = k % dim;
            self.min[d] = self.min[d].min(v);
            self.max[d] = self.max[d].max(v);
            self.sum[d] += v;
            self.sumsq[d] += v * v;
            if d + 1 == dim {
                self.count += 1;
            }
        }
    }
    fn json(&self) -> Value {
        let n = self.count.max(1) as f64;
        let mean: Vec<f64> = self.sum.iter().map(|s| s / n).collect();
        let std: Vec<f64> =
            self.sumsq.iter().zip(&mean).map(|(q, m)| (q / n - m * m).max(0.0).sqrt()).collect();
        json!({"min": self.min, "max": self.max, "mean": mean, "std": std, "count": [self.count]})
    }
}

fn f32_values(col: &ArrayRef) -> Vec<f64> {
    match col.data_type() {
        DataType::FixedSizeList(_, _) => {
            let l = col.as_fixed_size_list();
            let d = l.value_length() as usize;
            let v = l.values().as_primitive::<Float32Type>();
            v.values()[l.offset() * d..(l.offset() + l.len()) * d].iter().map(|&x| x as f64).collect()
        }
        DataType::Float32 => col.as_primitive::<Float32Type>().values().iter().map(|&x| x as f64).collect(),
        DataType::Float64 => col.as_primitive::<Float64Type>().values().to_vec(),
        DataType::Int64 => {
            col.as_primitive::<arrow::datatypes::Int64Type>().values().iter().map(|&x| x as f64).collect()
        }
        DataType::Boolean => {
            col.as_boolean().iter().map(|b| if b == Some(true) { 1.0 } else { 0.0 }).collect()
        }
        _ => Vec::new(),
    }
}

struct DataFile {
    path: PathBuf,
    writer: ArrowWriter<File>,
}

struct Writer<'a> {
    root: PathBuf,
    schema: SchemaRef,
    layout: Layout,
    fps: f64,
    labeled: bool,
    tasks: &'a BTreeMap<String, i64>,
    /// Validity as GR00T's task indexes `(valid, invalid)`, else as a bool.
    validity_tasks: Option<(i64, i64)>,
    file: Option<DataFile>,
    file_index: usize,
    frames: i64,
    stats: BTreeMap<String, Stats>,
    episodes: Vec<EpisodeRow>,
    /// video key → store objects in order of first use (their index is the file index)
    videos: BTreeMap<String, Vec<String>>,
}

struct EpisodeRow {
    index: i64,
    task: String,
    length: i64,
    data_file: usize,
    from: i64,
    /// per video key: (file index, from_timestamp, to_timestamp)
    videos: Vec<(usize, f64, f64)>,
    id: String,
    label: Label,
    source_name: String,
    part: Option<String>,
    /// The episode's verifier score when the export was curated by one.
    score: Option<f64>,
    /// From the label event that set the exported label: the failure cause and the time spans
    /// (JSON), when the labelers gave them.
    failure_cause: Option<String>,
    spans: Option<String>,
}

fn data_props() -> WriterProperties {
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

impl Writer<'_> {
    fn column<'b>(&self, steps: &'b RecordBatch, name: &str, e: &EpisodeRecord) -> Result<&'b ArrayRef> {
        steps
            .column_by_name(name)
            .ok_or_else(|| ExportError::invalid(format!("episode {}: no column {name}", e.id)))
    }

    fn add(
        &mut self,
        index: usize,
        e: &EpisodeRecord,
        steps: RecordBatch,
        part: Option<&String>,
        score: Option<f64>,
        label_data: Option<&serde_json::Value>,
    ) -> Result<()> {
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
        let n = steps.num_rows();
        let mut cols: Vec<ArrayRef> = Vec::new();
        for (k, _) in &self.layout.obs {
            let c = self.column(&steps, &format!("{OBS_PREFIX}{k}"), e)?.clone();
            self.stats
                .entry(feature_key(k))
                .or_default()
                .add(c.as_fixed_size_list().value_length() as usize, f32_values(&c).into_iter());
            cols.push(c);
        }
        let action = self.column(&steps, "action", e)?.clone();
        self.stats
            .entry("action".into())
            .or_default()
            .add(self.layout.action, f32_values(&action).into_iter());
        cols.push(action);
        for (k, _) in &self.layout.images {
            let bin = self.column(&steps, &format!("{IMAGE_PREFIX}{k}"), e)?.clone();
            let bin: ArrayRef = Arc::new(bin.as_binary::<i32>().clone() as BinaryArray);
            let paths: ArrayRef = Arc::new(StringArray::new_null(n));
            let DataType::Struct(fields) = image_type() else { unreachable!("struct type") };
            cols.push(Arc::new(
                StructArray::try_new(fields, vec![bin, paths], None)
                    .map_err(|e| ExportError::invalid(e.to_string()))?,
            ));
        }
        let reward = self.column(&steps, "reward", e)?.clone();
        let done = self.column(&steps, "done", e)?.clone();
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
        if self.layout.intervention {
            let c = self.column(&steps, INTERVENTION_COLUMN, e)?.clone();
            self.stats.entry(INTERVENTION_COLUMN.into()).or_default().add(1, f32_values(&c).into_iter());
            cols.push(c);
        }
        if self.layout.validity {
            let c = self.column(&steps, VALIDITY_COLUMN, e)?.clone();
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
        let ts = self.column(&steps, "timestamp", e)?.as_primitive::<Float64Type>().clone();
        let ts32: ArrayRef = Arc::new(Float32Array::from_iter_values(ts.values().iter().map(|&t| t as f32)));
        self.stats.entry("timestamp".into()).or_default().add(1, f32_values(&ts32).into_iter());
        cols.push(ts32);
        let task = e.task.clone().unwrap_or_else(|| NO_TASK.to_string());
        let task_index = self.tasks[&task];
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
        // Video files: one per store object; the episode's frames from its first frame's time.
        let mut videos = Vec::new();
        for k in &self.layout.videos {
            let path = self
                .column(&steps, &format!("{MEDIA_PREFIX}{k}.path"), e)?
                .as_string::<i32>()
                .value(0)
                .to_string();
            let mts = self
                .column(&steps, &format!("{MEDIA_PREFIX}{k}.timestamp"), e)?
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
        if df.writer.bytes_written() + df.writer.in_progress_size() > DATA_FILE_BYTES {
            self.close_file()?;
        }
        Ok(())
    }

    fn close_file(&mut self) -> Result<()> {
        if let Some(df) = self.file.take() {
            df.writer.close().map_err(|err| ExportError::write(&df.path, err))?;
            self.file_index += 1;
        }
        Ok(())
    }
}

/// Fills LeRobot's path templates.
fn fill(template: &str, video_key: Option<&str>, chunk: usize, file: usize) -> String {
    template
        .replace("{video_key}", video_key.unwrap_or(""))
        .replace("{chunk_index:03d}", &format!("{chunk:03}"))
        .replace("{file_index:03d}", &format!("{file:03}"))
}

fn write_parquet(path: &Path, batch: &RecordBatch) -> Result<()> {
    std::fs::create_dir_all(path.parent().expect("has a parent")).map_err(|e| ExportError::io(path, e))?;
    let f = File::create(path).map_err(|e| ExportError::io(path, e))?;
    let mut w = ArrowWriter::try_new(f, batch.schema(), Some(data_props()))
        .map_err(|e| ExportError::write(path, e))?;
    w.write(batch).map_err(|e| ExportError::write(path, e))?;
    w.close().map_err(|e| ExportError::write(path, e))?;
    Ok(())
}

fn write_json(path: &Path, v: &Value) -> Result<()> {
    let text = serde_json::to_string_pretty(v).map_err(|e| ExportError::write(path, e))?;
    std::fs::write(path, text).map_err(|e| ExportError::io(path, e))
}

/// `meta/tasks.parquet`: `task_index`, `task`, with the pandas index metadata lerobot reads the
/// task text by (`pd.read_parquet(...)` gives a frame indexed by task).
fn tasks_batch(tasks: &BTreeMap<String, i64>) -> Result<RecordBatch> {
    let mut by_index: Vec<(&i64, &String)> = tasks.iter().map(|(t, i)| (i, t)).collect();
    by_index.sort();
    let pandas = json!({
        "index_columns": ["task"],
        "column_indexes": [{"name": null, "field_name": null, "pandas_type": "unicode", "numpy_type": "object", "metadata": {"encoding": "UTF-8"}}],
        "columns": [
            {"name": "task_index", "field_name": "task_index", "pandas_type": "int64", "numpy_type": "int64", "metadata": null},
            {"name": "task", "field_name": "task", "pandas_type": "unicode", "numpy_type": "object", "metadata": null}
        ],
        "attributes": {}, "creator": {"library": "ufops", "version": env!("CARGO_PKG_VERSION")}, "pandas_version": "2.3.3"
    });
    let schema = Schema::new(vec![
        Field::new("task_index", DataType::Int64, false),
        Field::new("task", DataType::Utf8, false),
    ])
    .with_metadata(HashMap::from([("pandas".to_string(), pandas.to_string())]));
    RecordBatch::try_new(
        Arc::new(schema),
        vec![
            Arc::new(Int64Array::from_iter_values(by_index.iter().map(|(i, _)| **i))),
            Arc::new(StringArray::from_iter_values(by_index.iter().map(|(_, t)| t.as_str()))),
        ],
    )
    .map_err(|e| ExportError::invalid(e.to_string()))
}

fn episodes_batch(rows: &[EpisodeRow], video_keys: &[String]) -> Result<RecordBatch> {
    let mut fields = vec![
        Field::new("episode_index", DataType::Int64, false),
        Field::new("tasks", DataType::List(Arc::new(Field::new("item", DataType::Utf8, true))), false),
        Field::new("length", DataType::Int64, false),
        Field::new("data/chunk_index", DataType::Int64, false),
        Field::new("data/file_index", DataType::Int64, false),
        Field::new("dataset_from_index", DataType::Int64, false),
        Field::new("dataset_to_index", DataType::Int64, false),
    ];
    let ints = |f: &dyn Fn(&EpisodeRow) -> i64| -> ArrayRef {
        Arc::new(Int64Array::from_iter_values(rows.iter().map(f)))
    };
    let mut tasks = ListBuilder::new(StringBuilder::new());
    for r in rows {
        tasks.values().append_value(&r.task);
        tasks.append(true);
    }
    let mut cols: Vec<ArrayRef> = vec![
        ints(&|r| r.index),
        Arc::new(tasks.finish()),
        ints(&|r| r.length),
        ints(&|r| (r.data_file / CHUNKS_SIZE) as i64),
        ints(&|r| (r.data_file % CHUNKS_SIZE) as i64),
        ints(&|r| r.from),
        ints(&|r| r.from + r.length),
    ];
    for (v, k) in video_keys.iter().enumerate() {
        let fk = feature_key(k);
        fields.push(Field::new(format!("videos/{fk}/chunk_index"), DataType::Int64, false));
        fields.push(Field::new(format!("videos/{fk}/file_index"), DataType::Int64, false));
        fields.push(Field::new(format!("videos/{fk}/from_timestamp"), DataType::Float64, false));
        fields.push(Field::new(format!("videos/{fk}/to_timestamp"), DataType::Float64, false));
        cols.push(ints(&|r| (r.videos[v].0 / CHUNKS_SIZE) as i64));
        cols.push(ints(&|r| (r.videos[v].0 % CHUNKS_SIZE) as i64));
        cols.push(Arc::new(arrow::array::Float64Array::from_iter_values(rows.iter().map(|r| r.videos[v].1))));
        cols.push(Arc::new(arrow::array::Float64Array::from_iter_values(rows.iter().map(|r| r.videos[v].2))));
    }
    fields.push(Field::new("meta/episodes/chunk_index", DataType::Int64, false));
    fields.push(Field::new("meta/episodes/file_index", DataType::Int64, false));
    cols.push(ints(&|_| 0));
    cols.push(ints(&|_| 0));
    fields.push(Field::new("ufops/episode_id", DataType::Utf8, false));
    fields.push(Field::new("ufops/label", DataType::Utf8, false));
    fields.push(Field::new("ufops/source_name", DataType::Utf8, false));
    fields.push(Field::new("ufops/split_part", DataType::Utf8, true));
    cols.push(Arc::new(StringArray::from_iter_values(rows.iter().map(|r| r.id.as_str()))));
    cols.push(Arc::new(StringArray::from_iter_values(rows.iter().map(|r| r.label.as_str()))));
    cols.push(Arc::new(StringArray::from_iter_values(rows.iter().map(|r| r.source_name.as_str()))));
    cols.push(Arc::new(StringArray::from_iter(rows.iter().map(|r| r.part.as_deref()))));
    if rows.iter().any(|r| r.score.is_some()) {
        fields.push(Field::new("ufops/verifier_score", DataType::Float64, true));
        cols.push(Arc::new(arrow::array::Float64Array::from_iter(rows.iter().map(|r| r.score))));
    }
    if rows.iter().any(|r| r.failure_cause.is_some() || r.spans.is_some()) {
        fields.push(Field::new("ufops/failure_cause", DataType::Utf8, true));
        fields.push(Field::new("ufops/label_spans", DataType::Utf8, true));
        cols.push(Arc::new(StringArray::from_iter(rows.iter().map(|r| r.failure_cause.as_deref()))));
        cols.push(Arc::new(StringArray::from_iter(rows.iter().map(|r| r.spans.as_deref()))));
    }
    RecordBatch::try_new(Arc::new(Schema::new(fields)), cols).map_err(|e| ExportError::invalid(e.to_string()))
}

/// Copies a store object to a local file in pieces (memory: one piece).
async fn copy_object(store: &Store, object: &str, dest: &Path) -> Result<u64> {
    use std::io::Write;
    let size = store.object_size(object).await?;
    std::fs::create_dir_all(dest.parent().expect("has a parent")).map_err(|e| ExportError::io(dest, e))?;
    let mut f = File::create(dest).map_err(|e| ExportError::io(dest, e))?;
    let mut at = 0;
    while at < size {
        let end = (at + COPY_BYTES).min(size);
        let bytes = store.get_object_range(object, at..end).await?;
        f.write_all(&bytes).map_err(|e| ExportError::io(dest, e))?;
        at = end;
    }
    f.sync_all().map_err(|e| ExportError::io(dest, e))?;
    Ok(size)
}

/// The feature entry of `key` in the sources' LeRobot metadata (dtype, shape, names, info).
fn source_feature(sources: &[Value], key: &str) -> Option<Value> {
    sources.iter().find_map(|m| m.get("features").and_then(|f| f.get(key)).cloned())
}

/// Writes the selected episodes as a LeRobot v3.0 dataset at `out` (a new folder).
pub async fn export(
    store: &Store,
    sel: &Selected,
    out: &Path,
    progress: Progress<'_>,
) -> Result<ExportReport> {
    if sel.episodes.is_empty() {
        return Err(ExportError::invalid("the selection holds no episodes: nothing to export"));
    }
    let staged = Staged::new(out, true)?;
    // The sources' metadata: fps, robot type, feature names of LeRobot sources.
    let mut sources: Vec<Value> = Vec::new();
    let mut seen = std::collections::HashSet::new();
    for e in &sel.episodes {
        if seen.insert(e.source_sha256.clone()) {
            sources.push(store.source(&e.source_sha256).await?.metadata);
        }
    }
    let fps = sources
        .iter()
        .find_map(|m| m.get("fps").or_else(|| m.get("control_freq")).and_then(|v| v.as_f64()))
        .filter(|f| f.is_finite() && *f > 0.0);
    let robot_type =
        sources.iter().find_map(|m| m.get("robot_type").and_then(|v| v.as_str()).map(str::to_string));
    let mut tasks: BTreeMap<String, i64> = BTreeMap::new();
    for e in &sel.episodes {
        let t = e.task.clone().unwrap_or_else(|| NO_TASK.to_string());
        let next = tasks.len() as i64;
        tasks.entry(t).or_insert(next);
    }
    // A GR00T-style source's validity indexes its tasks `valid` / `invalid`: keep them so.
    let validity_tasks = match source_feature(&sources, VALIDITY_KEY) {
        Some(f) if f.get("dtype") != Some(&json!("bool")) => {
            let mut at = VALID_TASKS.iter().map(|t| {
                let next = tasks.len() as i64;
                *tasks.entry(t.to_string()).or_insert(next)
            });
            Some((at.next().expect("two tasks"), at.next().expect("two tasks")))
        }
        _ => None,
    };
    let labeled = sel.episodes.iter().any(|e| e.label != Label::Unknown);
    let mut report = ExportReport {
        path: out.to_path_buf(),
        format: "lerobot".into(),
        version: sel.version,
        episodes: 0,
        frames: 0,
        labels: Default::default(),
        media_files: 0,
        bytes: 0,
        warnings: Vec::new(),
    };

    let total = sel.episodes.len();
    let mut writer: Option<Writer> = None;
    let root = staged.tmp.clone();
    for_each_episode_with_layers(
        store,
        &sel.episodes,
        &sel.selection.layers,
        Some(sel.version),
        |i, e, steps| {
            if writer.is_none() {
                let layout = layout_of(&steps.schema())?;
                if layout.action == 0 {
                    return Err(no_actions(e));
                }
                let fps = match fps {
                    Some(f) => f,
                    None => estimate_fps(&steps),
                };
                let schema = data_schema(&steps.schema(), &layout, labeled, validity_tasks.is_some())?;
                writer = Some(Writer {
                    root: root.clone(),
                    schema,
                    layout,
                    fps,
                    labeled,
                    tasks: &tasks,
                    validity_tasks,
                    file: None,
                    file_index: 0,
                    frames: 0,
                    stats: BTreeMap::new(),
                    episodes: Vec::new(),
                    videos: BTreeMap::new(),
                });
            }
            let w = writer.as_mut().expect("set above");
            w.add(
                i,
                e,
                steps,
                sel.parts.get(&e.id),
                sel.scores.get(&e.id).copied(),
                sel.label_data.get(&e.id),
            )?;
            count_label(&mut report.labels, e.label);
            if let Some(p) = progress {
                p(i + 1, total);
            }
            Ok(())
        },
    )
    .await?;
    let mut w = writer.expect("at least one episode");
    w.close_file()?;

    // Videos: the store's objects, byte for byte.
    for (k, objs) in &w.videos {
        for (i, obj) in objs.iter().enumerate() {
            let rel = fill(VIDEO_PATH, Some(&feature_key(k)), i / CHUNKS_SIZE, i % CHUNKS_SIZE);
            copy_object(store, obj, &root.join(rel)).await?;
            report.media_files += 1;
        }
    }

    // meta/
    let meta = root.join("meta");
    write_parquet(&meta.join("tasks.parquet"), &tasks_batch(&tasks)?)?;
    write_parquet(
        &meta.join("episodes/chunk-000/file-000.parquet"),
        &episodes_batch(&w.episodes, &w.layout.videos)?,
    )?;
    let mut stats = Map::new();
    for (k, s) in &w.stats {
        stats.insert(k.clone(), s.json());
    }
    write_json(&meta.join("stats.json"), &Value::Object(stats))?;

    let mut features = Map::new();
    let vector = |key: &str, dim: usize| -> Value {
        let names = source_feature(&sources, key)
            .filter(|f| f.get("shape") == Some(&json!([dim])))
            .and_then(|f| f.get("names").cloned())
            .unwrap_or(Value::Null);
        json!({"dtype": "float32", "shape": [dim], "names": names})
    };
    for (k, d) in &w.layout.obs {
        features.insert(feature_key(k), vector(&feature_key(k), *d));
    }
    features.insert("action".into(), vector("action", w.layout.action));
    for (k, shape) in &w.layout.images {
        features.insert(
            feature_key(k),
            json!({"dtype": "image", "shape": shape, "names": ["height", "width", "channel"]}),
        );
    }
    for k in &w.layout.videos {
        let fk = feature_key(k);
        let f = source_feature(&sources, &fk).filter(|f| f.get("dtype") == Some(&json!("video")));
        let f = f.ok_or_else(|| {
            ExportError::invalid(format!(
                "video {fk}: its source does not say the video's shape (not a LeRobot source)"
            ))
        })?;
        features.insert(fk, f);
    }
    features.insert("next.reward".into(), json!({"dtype": "float32", "shape": [1], "names": null}));
    features.insert("next.done".into(), json!({"dtype": "bool", "shape": [1], "names": null}));
    if labeled {
        features.insert("next.success".into(), json!({"dtype": "bool", "shape": [1], "names": null}));
    }
    if w.layout.intervention {
        features.insert(INTERVENTION_COLUMN.into(), json!({"dtype": "bool", "shape": [1], "names": null}));
    }
    if w.layout.validity {
        let dtype = if w.validity_tasks.is_some() { "int64" } else { "bool" };
        features.insert(VALIDITY_KEY.into(), json!({"dtype": dtype, "shape": [1], "names": null}));
    }
    features.insert("timestamp".into(), json!({"dtype": "float32", "shape": [1], "names": null}));
    for k in ["frame_index", "episode_index", "index", "task_index"] {
        features.insert(k.into(), json!({"dtype": "int64", "shape": [1], "names": null}));
    }
    let n = w.episodes.len();
    let info = json!({
        "codebase_version": CODEBASE_VERSION,
        "robot_type": robot_type,
        "total_episodes": n,
        "total_frames": w.frames,
        "total_tasks": tasks.len(),
        "chunks_size": CHUNKS_SIZE,
        "data_files_size_in_mb": DATA_FILE_BYTES >> 20,
        "video_files_size_in_mb": 200,
        "fps": w.fps,
        "splits": {"train": format!("0:{n}")},
        "data_path": DATA_PATH,
        "video_path": if w.layout.videos.is_empty() { Value::Null } else { json!(VIDEO_PATH) },
        "features": features,
        "ufops": sel.provenance("lerobot"),
    });
    write_json(&meta.join("info.json"), &info)?;
    if !w.layout.extras.is_empty() {
        report.warnings.push(format!(
            "left out {} column(s) LeRobot has no feature for: {}",
            w.layout.extras.len(),
            w.layout.extras.join(", ")
        ));
    }
    report.episodes = n;
    report.frames = w.frames as u64;
    report.bytes = disk_size(&root);
    staged.commit()?;
    Ok(report)
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
