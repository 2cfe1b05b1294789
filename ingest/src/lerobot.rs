//! LeRobot datasets, codebase v2.1 and v3.0.
//!
//! * `meta/info.json` (`codebase_version` picks the layout, `fps`, `robot_type`, `features`).
//! * tasks: v2.1 `meta/tasks.jsonl`; v3.0 `meta/tasks.parquet`.
//! * episodes: v2.1 `meta/episodes.jsonl`; v3.0 `meta/episodes/chunk-*/file-*.parquet` with
//!   `dataset_from_index` / `dataset_to_index` and `videos/<key>/{chunk,file}_index,from_timestamp`.
//! * data Parquet (fixed-size or variable lists, or scalars) is streamed batch by batch, page by
//!   page: memory is bounded by an episode and a batch, not by the file.
//! * `video` features become [`MediaColumn`] references (each frame's time inside the shared
//!   mp4) plus one [`MediaFile`] per mp4 (content-addressed, emitted once); `image` features
//!   (PNG bytes in a `struct<bytes, path>` column) become [`ImageColumn`]s.
//! * success = any(`next.success`), label source `lerobot:next.success`; no such column → unknown.
//! * human takeovers: the bool feature `intervention` (LeRobot's DAgger recordings, `lerobot-rollout
//!   --strategy dagger`; another name with `--intervention-key`) becomes the episode's
//!   [`StepFlags::intervention`]; GR00T's `annotation.human.validity` (an index into the tasks,
//!   whose task is `valid` or `invalid`, or a bool) becomes [`StepFlags::validity`].

use std::collections::{BTreeMap, HashMap, HashSet};
use std::path::{Path, PathBuf};

use arrow::array::{Array, ArrayRef, AsArray, RecordBatch};
use arrow::datatypes::{DataType, Float32Type, Float64Type, Int64Type};
use parquet::arrow::arrow_reader::{
    ArrowReaderMetadata, ArrowReaderOptions, ParquetRecordBatchReaderBuilder,
};
use parquet::file::reader::ChunkReader;
use serde_json::{json, Map, Value};

use crate::error::{IngestError, Result};
use crate::model::{EpisodeInput, ImageColumn, Label, MediaColumn, MediaFile, StepFlags, VectorColumn};
use crate::options::ReadOptions;
use crate::sink::{EpisodeSink, SourceMeta};

const LABEL_SOURCE: &str = "lerobot:next.success";
/// GR00T's per-frame validity annotation (an index into the tasks: `valid` / `invalid`).
pub const VALIDITY_KEY: &str = "annotation.human.validity";

#[derive(Debug, Clone, PartialEq)]
pub struct Feature {
    pub key: String,
    pub dtype: String,
    pub shape: Vec<usize>,
    pub names: Value,
}

#[derive(Debug, Clone, PartialEq)]
pub struct Info {
    pub codebase_version: String,
    pub fps: f64,
    pub robot_type: Option<String>,
    pub features: Vec<Feature>,
    pub total_episodes: Option<u64>,
    pub chunks_size: u64,
    pub data_path: String,
    pub video_path: Option<String>,
    pub raw: Value,
}

impl Info {
    pub fn is_v3(&self) -> bool {
        self.codebase_version.starts_with("v3")
    }
    fn feature(&self, key: &str) -> Option<&Feature> {
        self.features.iter().find(|f| f.key == key)
    }
    fn video_keys(&self) -> Vec<&Feature> {
        self.features.iter().filter(|f| f.dtype == "video").collect()
    }
}

/// The keys of info.json's `features` object in the order the file lists them (empty when the
/// file does not parse; [`parse_info`] reports that).
fn feature_order(bytes: &[u8]) -> Vec<String> {
    struct Keys(Vec<String>);
    impl<'de> serde::Deserialize<'de> for Keys {
        fn deserialize<D: serde::Deserializer<'de>>(d: D) -> std::result::Result<Self, D::Error> {
            struct Visit;
            impl<'de> serde::de::Visitor<'de> for Visit {
                type Value = Keys;
                fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
                    f.write_str("a JSON object")
                }
                fn visit_map<A: serde::de::MapAccess<'de>>(
                    self,
                    mut map: A,
                ) -> std::result::Result<Keys, A::Error> {
                    let mut keys = Vec::new();
                    while let Some((k, _)) = map.next_entry::<String, serde::de::IgnoredAny>()? {
                        keys.push(k);
                    }
                    Ok(Keys(keys))
                }
            }
            d.deserialize_map(Visit)
        }
    }
    #[derive(serde::Deserialize)]
    struct Info {
        features: Keys,
    }
    serde_json::from_slice::<Info>(bytes).map(|i| i.features.0).unwrap_or_default()
}

/// Parses `meta/info.json`.
pub fn parse_info(path: &Path, bytes: &[u8]) -> Result<Info> {
    let raw: Value = serde_json::from_slice(bytes)
        .map_err(|e| IngestError::invalid(path, format!("not valid JSON: {e}")))?;
    let obj = raw.as_object().ok_or_else(|| IngestError::invalid(path, "expected a JSON object"))?;
    let codebase_version = obj
        .get("codebase_version")
        .and_then(|v| v.as_str())
        .ok_or_else(|| IngestError::invalid(path, "no `codebase_version`"))?
        .to_string();
    if !(codebase_version.starts_with("v2") || codebase_version.starts_with("v3")) {
        return Err(IngestError::invalid(
            path,
            format!("codebase_version {codebase_version:?} is not supported (expected v2.1 or v3.0)"),
        ));
    }
    let fps = obj
        .get("fps")
        .and_then(|v| v.as_f64())
        .filter(|f| f.is_finite() && *f > 0.0)
        .ok_or_else(|| IngestError::invalid(path, "no positive `fps`"))?;
    let feats = obj
        .get("features")
        .and_then(|v| v.as_object())
        .ok_or_else(|| IngestError::invalid(path, "no `features` object"))?;
    let mut features = Vec::new();
    for (key, f) in feats {
        let dtype = f
            .get("dtype")
            .and_then(|v| v.as_str())
            .ok_or_else(|| IngestError::invalid(path, format!("feature {key:?} has no dtype")))?
            .to_string();
        let shape = match f.get("shape") {
            Some(Value::Array(a)) => a
                .iter()
                .map(|d| d.as_u64().map(|x| x as usize))
                .collect::<Option<Vec<_>>>()
                .ok_or_else(|| IngestError::invalid(path, format!("feature {key:?} has a bad shape")))?,
            _ => vec![1],
        };
        features.push(Feature {
            key: key.clone(),
            dtype,
            shape,
            names: f.get("names").cloned().unwrap_or(Value::Null),
        });
    }
    // serde_json's map sorts keys; the file's order is the dataset's own (state before
    // environment state, say), which the store keeps and default verifier inputs follow.
    let order = feature_order(bytes);
    features.sort_by_key(|f| order.iter().position(|k| *k == f.key).unwrap_or(usize::MAX));
    let v3 = codebase_version.starts_with("v3");
    let data_path = obj.get("data_path").and_then(|v| v.as_str()).map(str::to_string).unwrap_or_else(|| {
        if v3 {
            "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet".into()
        } else {
            "data/chunk-{episode_chunk:03d}/episode_{episode_index:06d}.parquet".into()
        }
    });
    Ok(Info {
        codebase_version,
        fps,
        robot_type: obj.get("robot_type").and_then(|v| v.as_str()).map(str::to_string),
        features,
        total_episodes: obj.get("total_episodes").and_then(|v| v.as_u64()),
        chunks_size: obj.get("chunks_size").and_then(|v| v.as_u64()).filter(|&c| c > 0).unwrap_or(1000),
        data_path,
        video_path: obj.get("video_path").and_then(|v| v.as_str()).map(str::to_string),
        raw,
    })
}

/// Widest zero padding a template may ask for (a u64 has 20 digits): `{episode_index:0999999999d}`
/// would otherwise allocate a GB-long path.
const MAX_TEMPLATE_WIDTH: usize = 32;

/// Fills a LeRobot path template such as `data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet`.
/// The result is untrusted: callers confine it to the dataset with [`crate::confine::Root::file`].
pub fn fill_template(t: &str, vars: &[(&str, &str, u64)]) -> std::result::Result<String, String> {
    let mut out = String::new();
    let mut rest = t;
    while let Some(i) = rest.find('{') {
        out.push_str(&rest[..i]);
        let Some(j) = rest[i..].find('}') else {
            out.push_str(&rest[i..]);
            return Ok(out);
        };
        let inner = &rest[i + 1..i + j];
        let (name, fmt) = inner.split_once(':').unwrap_or((inner, ""));
        let mut done = false;
        for (n, s, v) in vars {
            if *n == name {
                if !s.is_empty() {
                    out.push_str(s);
                } else {
                    let width: usize = fmt.trim_start_matches('0').trim_end_matches('d').parse().unwrap_or(0);
                    if width > MAX_TEMPLATE_WIDTH {
                        return Err(format!(
                            "{{{inner}}} asks for a width of {width} digits (at most {MAX_TEMPLATE_WIDTH})"
                        ));
                    }
                    out.push_str(&format!("{:0width$}", v, width = width));
                }
                done = true;
            }
        }
        if !done {
            out.push_str(&rest[i..=i + j]);
        }
        rest = &rest[i + j + 1..];
    }
    out.push_str(rest);
    Ok(out)
}

/// Largest metadata files read whole (`meta/info.json`, `meta/*.jsonl`): far above real ones
/// (a v2.1 `episodes.jsonl` of 100,000 episodes is ~20 MB), so that a huge one is refused instead
/// of being loaded.
const MAX_INFO_BYTES: u64 = 16 << 20;
const MAX_JSONL_BYTES: u64 = 512 << 20;

/// A metadata file read whole, refused when larger than `max` bytes.
fn read_bounded(path: &Path, max: u64) -> Result<Vec<u8>> {
    use std::io::Read;
    let f = std::fs::File::open(path).map_err(|e| IngestError::io(path, e))?;
    let len = f.metadata().map_err(|e| IngestError::io(path, e))?.len();
    if len > max {
        return Err(IngestError::invalid(
            path,
            format!("metadata file of {len} bytes (at most {max} are read): refused"),
        ));
    }
    let mut out = Vec::with_capacity(len as usize);
    f.take(max + 1).read_to_end(&mut out).map_err(|e| IngestError::io(path, e))?;
    if out.len() as u64 > max {
        return Err(IngestError::invalid(
            path,
            format!("metadata file grew past {max} bytes while read: refused"),
        ));
    }
    Ok(out)
}

#[derive(Debug, Clone, Default)]
struct VideoRef {
    chunk_index: u64,
    file_index: u64,
    from_timestamp: f64,
}

#[derive(Debug, Clone, Default)]
struct EpisodeMeta {
    episode_index: u64,
    tasks: Vec<String>,
    length: Option<u64>,
    data_chunk: u64,
    data_file: u64,
    from_index: Option<u64>,
    to_index: Option<u64>,
    videos: BTreeMap<String, VideoRef>,
}

fn read_jsonl(path: &Path) -> Result<Vec<Value>> {
    let text = String::from_utf8(read_bounded(path, MAX_JSONL_BYTES)?)
        .map_err(|e| IngestError::invalid(path, format!("not UTF-8 text: {e}")))?;
    let mut out = Vec::new();
    for (i, line) in text.lines().enumerate() {
        if line.trim().is_empty() {
            continue;
        }
        out.push(
            serde_json::from_str(line)
                .map_err(|e| IngestError::invalid(path, format!("line {}: not valid JSON: {e}", i + 1)))?,
        );
    }
    Ok(out)
}

fn open_parquet(path: &Path) -> Result<Vec<RecordBatch>> {
    let f = std::fs::File::open(path).map_err(|e| IngestError::io(path, e))?;
    parquet_batches(path, f)
}

/// Opens a Parquet reader after checking what the parquet crate asserts on (it panics on
/// negative column offsets/sizes in corrupt footers).
fn checked_builder<R: ChunkReader + 'static>(
    path: &Path,
    r: R,
) -> Result<ParquetRecordBatchReaderBuilder<R>> {
    guarded(path, || checked_builder_inner(path, r))
}

/// The parquet crate still panics on some corrupt pages (e.g. "Decoder for dict should have been
/// set", apache/arrow-rs#9434-style index errors): such a panic becomes an error naming the file.
pub(crate) fn guarded<T>(path: &Path, f: impl FnOnce() -> Result<T>) -> Result<T> {
    match std::panic::catch_unwind(std::panic::AssertUnwindSafe(f)) {
        Ok(r) => r,
        Err(p) => Err(IngestError::invalid(
            path,
            format!(
                "corrupt Parquet data: the parquet decoder failed ({})",
                crate::panic_message(p.as_ref())
            ),
        )),
    }
}

fn checked_builder_inner<R: ChunkReader + 'static>(
    path: &Path,
    r: R,
) -> Result<ParquetRecordBatchReaderBuilder<R>> {
    let bad = |e: String| IngestError::invalid(path, format!("not a readable Parquet file: {e}"));
    // The parquet crate trusts the element counts in the footer when it allocates: check them first.
    crate::pqfooter::check(&r).map_err(bad)?;
    let meta = parquet::file::metadata::ParquetMetaDataReader::new()
        .parse_and_finish(&r)
        .map_err(|e| bad(e.to_string()))?;
    // ... and the page sizes the page headers declare (the decompression buffers' sizes); this
    // also checks that every column chunk lies inside the file.
    crate::pqfooter::check_pages(&r, &meta)
        .map_err(|e| IngestError::invalid(path, format!("corrupt Parquet data: {e}")))?;
    // The embedded Arrow schema (IPC flatbuffer in the footer) is skipped: the schema derived from
    // the Parquet types is enough here, and arrow-ipc panics on some corrupt ones (fuzzing).
    let opts = ArrowReaderOptions::new().with_skip_arrow_metadata(true);
    let meta =
        ArrowReaderMetadata::try_new(std::sync::Arc::new(meta), opts).map_err(|e| bad(e.to_string()))?;
    Ok(ParquetRecordBatchReaderBuilder::new_with_metadata(r, meta))
}

/// All record batches of a (small) Parquet file.
fn parquet_batches<R: ChunkReader + 'static>(path: &Path, r: R) -> Result<Vec<RecordBatch>> {
    let reader = checked_builder(path, r)?
        .build()
        .map_err(|e| IngestError::invalid(path, format!("not a readable Parquet file: {e}")))?;
    let mut reader = reader;
    let mut out = Vec::new();
    while let Some(b) = guarded(path, || Ok(reader.next()))? {
        out.push(b.map_err(|e| IngestError::invalid(path, format!("corrupt Parquet data: {e}")))?);
    }
    Ok(out)
}

fn col<'a>(b: &'a RecordBatch, name: &str) -> Option<&'a ArrayRef> {
    b.schema().index_of(name).ok().map(|i| b.column(i))
}

/// Values of an integer-like column as i64 (nulls → error).
fn ints(path: &Path, a: &ArrayRef, what: &str) -> Result<Vec<i64>> {
    let c = arrow::compute::cast(a, &DataType::Int64)
        .map_err(|e| IngestError::invalid(path, format!("column {what}: {e}")))?;
    let c = c.as_primitive::<Int64Type>();
    if c.null_count() > 0 {
        return Err(IngestError::invalid(path, format!("column {what} has null values")));
    }
    Ok(c.values().to_vec())
}

fn floats64(path: &Path, a: &ArrayRef, what: &str) -> Result<Vec<f64>> {
    let c = arrow::compute::cast(a, &DataType::Float64)
        .map_err(|e| IngestError::invalid(path, format!("column {what}: {e}")))?;
    let c = c.as_primitive::<Float64Type>();
    if c.null_count() > 0 {
        return Err(IngestError::invalid(path, format!("column {what} has null values")));
    }
    Ok(c.values().to_vec())
}

/// A boolean column keeping its nulls.
fn opt_bools(path: &Path, a: &ArrayRef, what: &str) -> Result<Vec<Option<bool>>> {
    let a = flatten_single(path, a, what)?;
    let c = arrow::compute::cast(&a, &DataType::Boolean)
        .map_err(|e| IngestError::invalid(path, format!("column {what}: {e}")))?;
    Ok(c.as_boolean().iter().collect())
}

fn bools(path: &Path, a: &ArrayRef, what: &str) -> Result<Vec<bool>> {
    let a = flatten_single(path, a, what)?;
    let c = arrow::compute::cast(&a, &DataType::Boolean)
        .map_err(|e| IngestError::invalid(path, format!("column {what}: {e}")))?;
    let c = c.as_boolean();
    Ok((0..c.len()).map(|i| c.is_valid(i) && c.value(i)).collect())
}

/// A column that may be a scalar or a one-element list: returns the scalar values.
fn flatten_single(path: &Path, a: &ArrayRef, what: &str) -> Result<ArrayRef> {
    match a.data_type() {
        DataType::FixedSizeList(_, 1) => Ok(a.as_fixed_size_list().values().clone()),
        DataType::List(_) | DataType::LargeList(_) | DataType::FixedSizeList(_, _) => {
            let (dim, vals) = list_f32(path, a, what)?;
            if dim.iter().any(|&d| d != 1) {
                return Err(IngestError::invalid(path, format!("column {what}: expected one value per row")));
            }
            Ok(std::sync::Arc::new(arrow::array::Float32Array::from(vals)))
        }
        _ => Ok(a.clone()),
    }
}

/// A numeric list (fixed or variable) or scalar column as (per-row lengths, flat f32 values).
fn list_f32(path: &Path, a: &ArrayRef, what: &str) -> Result<(Vec<usize>, Vec<f32>)> {
    let bad = |e: String| IngestError::invalid(path, format!("column {what}: {e}"));
    let to_f32 = |v: &ArrayRef| -> Result<Vec<f32>> {
        let c = arrow::compute::cast(v, &DataType::Float32).map_err(|e| bad(e.to_string()))?;
        Ok(c.as_primitive::<Float32Type>().values().to_vec())
    };
    if a.null_count() > 0 {
        return Err(bad("has null rows".into()));
    }
    match a.data_type() {
        DataType::FixedSizeList(_, n) => {
            let l = a.as_fixed_size_list();
            let n = *n as usize;
            let start = l.offset() * n;
            let vals = l.values().slice(start, l.len() * n);
            Ok((vec![n; l.len()], to_f32(&vals)?))
        }
        DataType::List(_) => {
            let l = a.as_list::<i32>();
            let offs = l.value_offsets();
            let (s, e) = (offs[0] as usize, offs[offs.len() - 1] as usize);
            let lens = offs.windows(2).map(|w| (w[1] - w[0]) as usize).collect();
            Ok((lens, to_f32(&l.values().slice(s, e - s))?))
        }
        DataType::LargeList(_) => {
            let l = a.as_list::<i64>();
            let offs = l.value_offsets();
            let (s, e) = (offs[0] as usize, offs[offs.len() - 1] as usize);
            let lens = offs.windows(2).map(|w| (w[1] - w[0]) as usize).collect();
            Ok((lens, to_f32(&l.values().slice(s, e - s))?))
        }
        _ => {
            let v = to_f32(a)?;
            Ok((vec![1; v.len()], v))
        }
    }
}

fn strings(a: &ArrayRef) -> Option<Vec<String>> {
    let c = arrow::compute::cast(a, &DataType::Utf8).ok()?;
    let c = c.as_string::<i32>();
    Some((0..c.len()).map(|i| if c.is_valid(i) { c.value(i).to_string() } else { String::new() }).collect())
}

fn list_strings(a: &ArrayRef) -> Option<Vec<Vec<String>>> {
    match a.data_type() {
        DataType::List(_) => {
            let l = a.as_list::<i32>();
            Some((0..l.len()).map(|i| strings(&l.value(i)).unwrap_or_default()).collect())
        }
        DataType::LargeList(_) => {
            let l = a.as_list::<i64>();
            Some((0..l.len()).map(|i| strings(&l.value(i)).unwrap_or_default()).collect())
        }
        _ => strings(a).map(|v| v.into_iter().map(|s| vec![s]).collect()),
    }
}

fn load_tasks(confine: &crate::confine::Root, info: &Info) -> Result<HashMap<i64, String>> {
    let root = confine.dir();
    let mut tasks = HashMap::new();
    if info.is_v3() {
        let p = root.join("meta/tasks.parquet");
        if !p.exists() {
            return Ok(tasks);
        }
        confine.check_inside(&p, "meta/tasks.parquet")?;
        for b in open_parquet(&p)? {
            let idx =
                col(&b, "task_index").ok_or_else(|| IngestError::invalid(&p, "no task_index column"))?;
            let idx = ints(&p, idx, "task_index")?;
            let names = ["task", "__index_level_0__"]
                .iter()
                .find_map(|n| col(&b, n).and_then(strings))
                .or_else(|| {
                    b.columns()
                        .iter()
                        .find(|c| matches!(c.data_type(), DataType::Utf8 | DataType::LargeUtf8))
                        .and_then(strings)
                })
                .ok_or_else(|| IngestError::invalid(&p, "no task text column"))?;
            for (i, t) in idx.into_iter().zip(names) {
                tasks.insert(i, t);
            }
        }
    } else {
        let p = root.join("meta/tasks.jsonl");
        if !p.exists() {
            return Ok(tasks);
        }
        confine.check_inside(&p, "meta/tasks.jsonl")?;
        for v in read_jsonl(&p)? {
            if let (Some(i), Some(t)) =
                (v.get("task_index").and_then(|x| x.as_i64()), v.get("task").and_then(|x| x.as_str()))
            {
                tasks.insert(i, t.to_string());
            }
        }
    }
    Ok(tasks)
}

fn load_episodes(confine: &crate::confine::Root, info: &Info) -> Result<Vec<EpisodeMeta>> {
    let root = confine.dir();
    let mut eps = Vec::new();
    if info.is_v3() {
        let dir = root.join("meta/episodes");
        confine.check_inside(&dir, "meta/episodes")?;
        let mut files: Vec<PathBuf> = crate::hashing::list_files(&dir)
            .map_err(|e| match e {
                IngestError::Io { .. } => IngestError::invalid(
                    &dir,
                    "missing: a v3.0 dataset needs meta/episodes/chunk-*/file-*.parquet",
                ),
                refused => refused,
            })?
            .into_iter()
            .filter(|(r, _)| r.ends_with(".parquet"))
            .map(|(_, p)| p)
            .collect();
        files.sort();
        if files.is_empty() {
            return Err(IngestError::invalid(&dir, "no episode Parquet files"));
        }
        let video_keys: Vec<String> = info.video_keys().iter().map(|f| f.key.clone()).collect();
        for p in files {
            for b in open_parquet(&p)? {
                let n = b.num_rows();
                let need = |name: &str| -> Result<Vec<i64>> {
                    let c =
                        col(&b, name).ok_or_else(|| IngestError::invalid(&p, format!("no {name} column")))?;
                    ints(&p, c, name)
                };
                let idx = need("episode_index")?;
                let opt_ints = |name: &str| -> Result<Option<Vec<i64>>> {
                    col(&b, name).map(|c| ints(&p, c, name)).transpose()
                };
                let length = opt_ints("length")?;
                let dchunk = opt_ints("data/chunk_index")?;
                let dfile = opt_ints("data/file_index")?;
                let from = opt_ints("dataset_from_index")?;
                let to = opt_ints("dataset_to_index")?;
                let tasks = col(&b, "tasks").and_then(list_strings);
                type VideoCols = (String, Vec<i64>, Vec<i64>, Vec<f64>);
                let mut vids: Vec<VideoCols> = Vec::new();
                for k in &video_keys {
                    let c = opt_ints(&format!("videos/{k}/chunk_index"))?;
                    let f = opt_ints(&format!("videos/{k}/file_index"))?;
                    let t = col(&b, &format!("videos/{k}/from_timestamp"))
                        .map(|c| floats64(&p, c, "from_timestamp"))
                        .transpose()?;
                    match (c, f, t) {
                        (Some(c), Some(f), Some(t)) => vids.push((k.clone(), c, f, t)),
                        _ => {
                            return Err(IngestError::invalid(
                                &p,
                                format!("no videos/{k}/{{chunk_index,file_index,from_timestamp}} columns for video feature {k}"),
                            ))
                        }
                    }
                }
                for r in 0..n {
                    let nonneg = |v: i64, what: &str| -> Result<u64> {
                        u64::try_from(v).map_err(|_| IngestError::invalid(&p, format!("negative {what} {v}")))
                    };
                    let mut videos = BTreeMap::new();
                    for (k, c, f, t) in &vids {
                        videos.insert(
                            k.clone(),
                            VideoRef {
                                chunk_index: nonneg(c[r], "chunk_index")?,
                                file_index: nonneg(f[r], "file_index")?,
                                from_timestamp: t[r],
                            },
                        );
                    }
                    eps.push(EpisodeMeta {
                        episode_index: nonneg(idx[r], "episode_index")?,
                        tasks: tasks.as_ref().map(|t| t[r].clone()).unwrap_or_default(),
                        length: length.as_ref().map(|l| nonneg(l[r], "length")).transpose()?,
                        data_chunk: dchunk
                            .as_ref()
                            .map(|l| nonneg(l[r], "data/chunk_index"))
                            .transpose()?
                            .unwrap_or(0),
                        data_file: dfile
                            .as_ref()
                            .map(|l| nonneg(l[r], "data/file_index"))
                            .transpose()?
                            .unwrap_or(0),
                        from_index: from.as_ref().map(|l| nonneg(l[r], "dataset_from_index")).transpose()?,
                        to_index: to.as_ref().map(|l| nonneg(l[r], "dataset_to_index")).transpose()?,
                        videos,
                    });
                }
            }
        }
    } else {
        let p = root.join("meta/episodes.jsonl");
        if !p.exists() {
            return Err(IngestError::invalid(&p, "missing: a v2.1 dataset needs meta/episodes.jsonl"));
        }
        confine.check_inside(&p, "meta/episodes.jsonl")?;
        for v in read_jsonl(&p)? {
            let idx = v
                .get("episode_index")
                .and_then(|x| x.as_u64())
                .ok_or_else(|| IngestError::invalid(&p, format!("entry without episode_index: {v}")))?;
            let tasks = v
                .get("tasks")
                .and_then(|t| t.as_array())
                .map(|a| a.iter().filter_map(|x| x.as_str().map(str::to_string)).collect())
                .unwrap_or_default();
            eps.push(EpisodeMeta {
                episode_index: idx,
                tasks,
                length: v.get("length").and_then(|x| x.as_u64()),
                data_chunk: idx / info.chunks_size,
                ..Default::default()
            });
        }
    }
    eps.sort_by_key(|e| e.episode_index);
    for w in eps.windows(2) {
        if w[0].episode_index == w[1].episode_index {
            return Err(IngestError::invalid(
                root,
                format!("episode {} is listed twice in the episode metadata", w[0].episode_index),
            ));
        }
    }
    if eps.is_empty() {
        return Err(IngestError::invalid(root, "the dataset lists no episodes"));
    }
    Ok(eps)
}

/// Which data columns become what.
struct Plan {
    observations: Vec<(String, String)>, // (parquet column, store name)
    images: Vec<(String, String)>,
    has_reward: bool,
    has_done: bool,
    has_success: bool,
    /// The per-frame takeover flag's column, when the dataset has one.
    intervention: Option<String>,
    has_validity: bool,
}

fn plan(info: &Info, opts: &ReadOptions) -> Result<Plan> {
    let (key, named) = opts.intervention_key();
    let intervention = match info.feature(key) {
        Some(_) => Some(key.to_string()),
        None if named => {
            return Err(IngestError::Usage(format!(
                "--intervention-key {key:?}: the dataset has no such feature (its features: {})",
                info.features.iter().map(|f| f.key.as_str()).collect::<Vec<_>>().join(", ")
            )))
        }
        None => None,
    };
    let mut observations = Vec::new();
    let mut images = Vec::new();
    for f in &info.features {
        let short = f.key.strip_prefix("observation.").unwrap_or(&f.key).to_string();
        match f.dtype.as_str() {
            "video" => {}
            "image" => images.push((f.key.clone(), short)),
            "string" | "str" => {}
            _ if intervention.as_deref() == Some(f.key.as_str()) => {}
            _ if f.key.starts_with("observation.") => observations.push((f.key.clone(), short)),
            _ => {}
        }
    }
    Ok(Plan {
        observations,
        images,
        has_reward: info.feature("next.reward").is_some(),
        has_done: info.feature("next.done").is_some(),
        has_success: info.feature("next.success").is_some(),
        intervention,
        has_validity: info.feature(VALIDITY_KEY).is_some(),
    })
}

/// Accumulates the rows of one episode.
#[derive(Default)]
struct EpBuf {
    episode_index: u64,
    rows: usize,
    timestamps: Vec<f64>,
    frame_index: Vec<i64>,
    global_index: Vec<i64>,
    task_index: Vec<i64>,
    obs: Vec<(usize, Vec<f32>)>,
    action: (usize, Vec<f32>),
    reward: Vec<f32>,
    done: Vec<bool>,
    /// `next.success` per row; null rows (an unlabeled episode in a ufops export) are `None`.
    success: Vec<Option<bool>>,
    images: Vec<Vec<Vec<u8>>>,
    intervention: Vec<bool>,
    /// GR00T validity per row: a bool, or a task index (resolved when the episode ends).
    validity: Vec<Validity>,
}

/// One row's `annotation.human.validity`.
#[derive(Clone, Copy)]
enum Validity {
    Flag(bool),
    TaskIndex(i64),
}

/// Streams one data file's batches into per-episode buffers, calling `emit` when an episode's
/// rows end (rows of an episode are contiguous).
struct DataReader<'a> {
    plan: &'a Plan,
    cur: Option<EpBuf>,
}

impl<'a> DataReader<'a> {
    fn push_batch(
        &mut self,
        path: &Path,
        b: &RecordBatch,
        emit: &mut dyn FnMut(EpBuf) -> Result<()>,
    ) -> Result<()> {
        let n = b.num_rows();
        if n == 0 {
            return Ok(());
        }
        let need = |name: &str| {
            col(b, name).ok_or_else(|| IngestError::invalid(path, format!("no `{name}` column")))
        };
        let ep = ints(path, need("episode_index")?, "episode_index")?;
        let ts = floats64(path, &flatten_single(path, need("timestamp")?, "timestamp")?, "timestamp")?;
        let fi = col(b, "frame_index")
            .map(|c| flatten_single(path, c, "frame_index").and_then(|c| ints(path, &c, "frame_index")))
            .transpose()?;
        let gi = col(b, "index")
            .map(|c| flatten_single(path, c, "index").and_then(|c| ints(path, &c, "index")))
            .transpose()?;
        let ti = col(b, "task_index")
            .map(|c| flatten_single(path, c, "task_index").and_then(|c| ints(path, &c, "task_index")))
            .transpose()?;
        let (alens, avals) = list_f32(path, need("action")?, "action")?;
        let mut obs = Vec::new();
        for (c, _) in &self.plan.observations {
            obs.push(list_f32(path, need(c)?, c)?);
        }
        let reward = if self.plan.has_reward {
            Some(list_f32(path, need("next.reward")?, "next.reward")?)
        } else {
            None
        };
        let done =
            if self.plan.has_done { Some(bools(path, need("next.done")?, "next.done")?) } else { None };
        let success = if self.plan.has_success {
            Some(opt_bools(path, need("next.success")?, "next.success")?)
        } else {
            None
        };
        let mut imgs = Vec::new();
        for (c, _) in &self.plan.images {
            imgs.push(image_bytes(path, need(c)?, c)?);
        }
        let intervention = match &self.plan.intervention {
            Some(c) => Some(bools(path, need(c)?, c)?),
            None => None,
        };
        let validity = if self.plan.has_validity {
            let c = flatten_single(path, need(VALIDITY_KEY)?, VALIDITY_KEY)?;
            Some(match c.data_type() {
                DataType::Boolean => bools(path, &c, VALIDITY_KEY)?.into_iter().map(Validity::Flag).collect(),
                _ => ints(path, &c, VALIDITY_KEY)?.into_iter().map(Validity::TaskIndex).collect::<Vec<_>>(),
            })
        } else {
            None
        };
        if let Some(r) = &reward {
            if r.0.iter().any(|&l| l != 1) {
                return Err(IngestError::invalid(path, "column next.reward: expected one value per row"));
            }
        }
        // offsets into flat arrays
        let offsets = |lens: &[usize]| -> Vec<usize> {
            let mut o = Vec::with_capacity(lens.len() + 1);
            let mut s = 0;
            o.push(0);
            for l in lens {
                s += l;
                o.push(s);
            }
            o
        };
        let aoff = offsets(&alens);
        let ooffs: Vec<Vec<usize>> = obs.iter().map(|(l, _)| offsets(l)).collect();
        for r in 0..n {
            let e = u64::try_from(ep[r])
                .map_err(|_| IngestError::invalid(path, format!("negative episode_index {}", ep[r])))?;
            if self.cur.as_ref().map(|c| c.episode_index) != Some(e) {
                if let Some(prev) = self.cur.take() {
                    emit(prev)?;
                }
                let mut nb = EpBuf { episode_index: e, ..Default::default() };
                nb.obs = vec![(0, Vec::new()); obs.len()];
                nb.images = vec![Vec::new(); imgs.len()];
                nb.action.0 = alens[r];
                for (k, (l, _)) in obs.iter().enumerate() {
                    nb.obs[k].0 = l[r];
                }
                self.cur = Some(nb);
            }
            let cur = self.cur.as_mut().expect("set above");
            cur.rows += 1;
            cur.timestamps.push(ts[r]);
            if let Some(fi) = &fi {
                cur.frame_index.push(fi[r]);
            }
            if let Some(gi) = &gi {
                cur.global_index.push(gi[r]);
            }
            if let Some(ti) = &ti {
                cur.task_index.push(ti[r]);
            }
            if alens[r] != cur.action.0 {
                return Err(IngestError::invalid(
                    path,
                    format!("episode {e}: action length changes from {} to {}", cur.action.0, alens[r]),
                ));
            }
            cur.action.1.extend_from_slice(&avals[aoff[r]..aoff[r + 1]]);
            for (k, (lens, vals)) in obs.iter().enumerate() {
                if lens[r] != cur.obs[k].0 {
                    return Err(IngestError::invalid(
                        path,
                        format!(
                            "episode {e}: {} length changes from {} to {}",
                            self.plan.observations[k].0, cur.obs[k].0, lens[r]
                        ),
                    ));
                }
                cur.obs[k].1.extend_from_slice(&vals[ooffs[k][r]..ooffs[k][r + 1]]);
            }
            if let Some((_, v)) = &reward {
                cur.reward.push(v[r]);
            }
            if let Some(d) = &done {
                cur.done.push(d[r]);
            }
            if let Some(s) = &success {
                cur.success.push(s[r]);
            }
            for (k, im) in imgs.iter_mut().enumerate() {
                cur.images[k].push(std::mem::take(&mut im[r]));
            }
            if let Some(i) = &intervention {
                cur.intervention.push(i[r]);
            }
            if let Some(v) = &validity {
                cur.validity.push(v[r]);
            }
        }
        Ok(())
    }
}

/// PNG bytes per row from an `image` column (`struct<bytes: binary, path: string>` or binary).
fn image_bytes(path: &Path, a: &ArrayRef, what: &str) -> Result<Vec<Vec<u8>>> {
    let bin: ArrayRef = match a.data_type() {
        DataType::Struct(_) => {
            let s = a.as_struct();
            s.column_by_name("bytes").cloned().ok_or_else(|| {
                IngestError::invalid(path, format!("image column {what} has no `bytes` field"))
            })?
        }
        _ => a.clone(),
    };
    let bin = arrow::compute::cast(&bin, &DataType::LargeBinary)
        .map_err(|e| IngestError::invalid(path, format!("image column {what}: {e}")))?;
    let bin = bin.as_binary::<i64>();
    let mut out = Vec::with_capacity(bin.len());
    for i in 0..bin.len() {
        if !bin.is_valid(i) {
            return Err(IngestError::invalid(path, format!("image column {what}: row {i} has no image bytes (images stored only by path are not supported)")));
        }
        let v = bin.value(i);
        if !v.starts_with(b"\x89PNG\r\n\x1a\n") {
            return Err(IngestError::invalid(
                path,
                format!("image column {what}: row {i} is not a PNG image"),
            ));
        }
        out.push(v.to_vec());
    }
    Ok(out)
}

/// (height, width, channels) from a PNG's IHDR.
fn png_shape(png: &[u8]) -> Option<[usize; 3]> {
    if png.len() < 33 || &png[12..16] != b"IHDR" {
        return None;
    }
    let w = u32::from_be_bytes(png[16..20].try_into().ok()?) as usize;
    let h = u32::from_be_bytes(png[20..24].try_into().ok()?) as usize;
    let c = match png[25] {
        0 => 1,
        2 => 3,
        3 => 3,
        4 => 2,
        6 => 4,
        _ => return None,
    };
    Some([h, w, c])
}

struct Ctx<'a> {
    root: &'a Path,
    confine: &'a crate::confine::Root,
    info_path: &'a Path,
    info: &'a Info,
    plan: &'a Plan,
    tasks: &'a HashMap<i64, String>,
    metas: HashMap<u64, (usize, EpisodeMeta)>,
    opts: &'a ReadOptions,
    emitted_media: HashMap<PathBuf, MediaFile>,
    seen: HashSet<u64>,
}

impl Ctx<'_> {
    fn media_for(
        &mut self,
        key: &str,
        v: Option<&VideoRef>,
        episode_index: u64,
        sink: &mut dyn EpisodeSink,
    ) -> Result<(MediaFile, f64)> {
        let tpl = self.info.video_path.clone().unwrap_or_else(|| {
            if self.info.is_v3() {
                "videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4".into()
            } else {
                "videos/chunk-{episode_chunk:03d}/{video_key}/episode_{episode_index:06d}.mp4".into()
            }
        });
        let (chunk, file, from) = match v {
            Some(v) => (v.chunk_index, v.file_index, v.from_timestamp),
            None => (episode_index / self.info.chunks_size, 0, 0.0),
        };
        let field = format!("`video_path` template {tpl:?} (feature {key:?}, episode {episode_index})");
        let rel = fill_template(
            &tpl,
            &[
                ("video_key", key, 0),
                ("chunk_index", "", chunk),
                ("file_index", "", file),
                ("episode_chunk", "", episode_index / self.info.chunks_size),
                ("episode_index", "", episode_index),
            ],
        )
        .map_err(|m| IngestError::invalid(self.info_path, format!("{field}: {m}")))?;
        let abs = self.confine.join(self.info_path, &field, &rel)?;
        if let Some(m) = self.emitted_media.get(&abs) {
            return Ok((m.clone(), from));
        }
        self.confine.check_inside(&abs, &field)?;
        if !abs.is_file() {
            return Err(IngestError::invalid(
                &abs,
                format!("missing video file for feature {key}, episode {episode_index}"),
            ));
        }
        let (sha, size) = crate::hashing::hash_file(&abs)?;
        let ct = if rel.ends_with(".mp4") { "video/mp4" } else { "application/octet-stream" };
        let m = MediaFile { sha256: sha, local_path: abs.clone(), content_type: ct.into(), size_bytes: size };
        sink.media(m.clone())?;
        self.emitted_media.insert(abs, m.clone());
        Ok((m, from))
    }

    fn finish(&mut self, path: &Path, b: EpBuf, sink: &mut dyn EpisodeSink) -> Result<()> {
        let e = b.episode_index;
        let Some((pos, meta)) = self.metas.get(&e).cloned() else {
            return Err(IngestError::invalid(
                path,
                format!("data rows for episode {e}, which the episode metadata does not list"),
            ));
        };
        if !self.seen.insert(e) {
            return Err(IngestError::invalid(path, format!("rows of episode {e} are not contiguous")));
        }
        if let Some(l) = meta.length {
            if l as usize != b.rows {
                return Err(IngestError::invalid(
                    path,
                    format!("episode {e} has {} rows but its metadata says length {l}", b.rows),
                ));
            }
        }
        if let (Some(f), Some(t)) = (meta.from_index, meta.to_index) {
            if t.saturating_sub(f) as usize != b.rows {
                return Err(IngestError::invalid(
                    path,
                    format!(
                        "episode {e} has {} rows but dataset_from_index..dataset_to_index is {f}..{t}",
                        b.rows
                    ),
                ));
            }
            if let (Some(first), Some(last)) = (b.global_index.first(), b.global_index.last()) {
                if u64::try_from(*first).ok() != Some(f)
                    || u64::try_from(*last).ok().and_then(|l| l.checked_add(1)) != Some(t)
                {
                    return Err(IngestError::invalid(path, format!("episode {e}: index column {first}..={last} does not match dataset_from_index..dataset_to_index {f}..{t}")));
                }
            }
        }
        let steps = b.rows;
        let t0 = b.timestamps.first().copied().unwrap_or(0.0);
        let timestamps: Vec<f64> = b.timestamps.iter().map(|t| t - t0).collect();
        let observations = self
            .plan
            .observations
            .iter()
            .zip(b.obs)
            .map(|((_, short), (dim, values))| VectorColumn { name: short.clone(), dim, values })
            .collect();
        let mut images = Vec::new();
        for ((_, short), frames) in self.plan.images.iter().zip(b.images) {
            let shape = frames.first().and_then(|f| png_shape(f)).ok_or_else(|| {
                IngestError::invalid(path, format!("episode {e}: image {short} is not a valid PNG"))
            })?;
            images.push(ImageColumn { name: short.clone(), shape, frames: frames.into() });
        }
        let mut media = Vec::new();
        let mut video_md = Map::new();
        let vkeys: Vec<String> = self.info.video_keys().iter().map(|f| f.key.clone()).collect();
        for key in vkeys {
            let (m, from) = self.media_for(&key, meta.videos.get(&key), e, sink)?;
            let short = key.strip_prefix("observation.").unwrap_or(&key).to_string();
            video_md.insert(key.clone(), json!({"sha256": m.sha256, "from_timestamp": from, "file": m.local_path.strip_prefix(self.root).unwrap_or(&m.local_path).to_string_lossy()}));
            media.push(MediaColumn {
                name: short,
                sha256: m.sha256.clone(),
                timestamps: b.timestamps.iter().map(|t| from + t).collect(),
            });
        }
        let reward = if self.plan.has_reward { b.reward } else { vec![0.0; steps] };
        let done = if self.plan.has_done {
            b.done
        } else {
            let mut d = vec![false; steps];
            if let Some(x) = d.last_mut() {
                *x = true;
            }
            d
        };
        let name = format!("episode_{e:06}");
        let (label, label_source) = match self.opts.user_label(&name, e as u32, &reward) {
            Some(l) => l,
            // An episode whose `next.success` is null throughout is unlabeled.
            None if self.plan.has_success && b.success.iter().any(|s| s.is_some()) => {
                (Label::from_bool(Some(b.success.contains(&Some(true)))), LABEL_SOURCE.to_string())
            }
            None => (Label::Unknown, String::new()),
        };
        let task = self
            .opts
            .task
            .clone()
            .or_else(|| meta.tasks.first().cloned())
            .or_else(|| b.task_index.first().and_then(|i| self.tasks.get(i).cloned()));
        let mut md = Map::new();
        md.insert("episode_index".into(), json!(e));
        md.insert("length".into(), json!(steps));
        if meta.tasks.len() > 1 {
            md.insert("tasks".into(), json!(meta.tasks));
        }
        if let (Some(f), Some(t)) = (meta.from_index, meta.to_index) {
            md.insert("dataset_from_index".into(), json!(f));
            md.insert("dataset_to_index".into(), json!(t));
        }
        if !video_md.is_empty() {
            md.insert("videos".into(), Value::Object(video_md));
        }
        md.insert("data_file".into(), json!(path.strip_prefix(self.root).unwrap_or(path).to_string_lossy()));
        let validity = match self.plan.has_validity.then(|| self.validity(&b.validity)) {
            Some(Err(why)) => {
                md.insert("validity_not_kept".into(), json!(why));
                None
            }
            Some(Ok(v)) => Some(v),
            None => None,
        };
        let flags =
            StepFlags { intervention: self.plan.intervention.is_some().then_some(b.intervention), validity };
        sink.episode(EpisodeInput {
            source_name: name,
            source_index: pos as u32,
            task,
            label,
            label_source,
            tags: Vec::new(),
            metadata: Value::Object(md),
            timestamps,
            observations,
            action: VectorColumn { name: "action".into(), dim: b.action.0, values: b.action.1 },
            reward,
            done,
            action_chunk: None,
            images,
            media,
            flags,
        })
    }

    /// GR00T's validity of each row: a task index names the task `valid` or `invalid` (any
    /// case). An index naming another task, or none, is not read as a flag (that would guess
    /// what the recorder meant): the episode keeps no validity, and its metadata says why.
    fn validity(&self, rows: &[Validity]) -> std::result::Result<Vec<bool>, String> {
        rows.iter()
            .map(|v| match *v {
                Validity::Flag(b) => Ok(b),
                Validity::TaskIndex(i) => match self.tasks.get(&i).map(|t| t.to_ascii_lowercase()) {
                    Some(t) if t == "valid" => Ok(true),
                    Some(t) if t == "invalid" => Ok(false),
                    other => Err(format!(
                        "{VALIDITY_KEY} {i} names {}, not the task \"valid\" or \"invalid\"",
                        other.map_or("no task".to_string(), |t| format!("the task {t:?}"))
                    )),
                },
            })
            .collect()
    }
}

/// Reads a LeRobot dataset folder.
///
/// Every path the dataset's metadata names is confined to `root` ([`crate::confine`]).
pub fn read_dir(root: &Path, opts: &ReadOptions, sink: &mut dyn EpisodeSink) -> Result<()> {
    let confine = crate::confine::Root::new(root)?;
    let info_path = root.join("meta/info.json");
    if !info_path.exists() {
        return Err(IngestError::invalid(&info_path, "missing: not a LeRobot dataset (no meta/info.json)"));
    }
    confine.check_inside(&info_path, "meta/info.json")?;
    let bytes = read_bounded(&info_path, MAX_INFO_BYTES)?;
    let info = parse_info(&info_path, &bytes)?;
    if info.feature("action").is_none() {
        return Err(IngestError::invalid(&info_path, "no `action` feature"));
    }
    let tasks = load_tasks(&confine, &info)?;
    let episodes = load_episodes(&confine, &info)?;
    if let Some(t) = info.total_episodes {
        if t as usize != episodes.len() {
            return Err(IngestError::invalid(
                &info_path,
                format!("total_episodes is {t} but the episode metadata lists {}", episodes.len()),
            ));
        }
    }
    let plan = plan(&info, opts)?;

    let mut meta = Map::new();
    meta.insert("codebase_version".into(), json!(info.codebase_version));
    meta.insert("fps".into(), json!(info.fps));
    meta.insert("robot_type".into(), json!(info.robot_type));
    let mut feats = Map::new();
    for f in &info.features {
        feats.insert(f.key.clone(), json!({"dtype": f.dtype, "shape": f.shape, "names": f.names}));
    }
    meta.insert("features".into(), Value::Object(feats));
    let mut tlist: Vec<(&i64, &String)> = tasks.iter().collect();
    tlist.sort();
    meta.insert("tasks".into(), json!(tlist.iter().map(|(_, t)| t).collect::<Vec<_>>()));
    meta.insert("total_episodes".into(), json!(episodes.len()));
    if let Some(t) = info.raw.get("total_frames") {
        meta.insert("total_frames".into(), t.clone());
    }
    sink.source(SourceMeta { format: "lerobot".into(), metadata: Value::Object(meta) })?;

    // Data files in episode order.
    let mut files: Vec<(PathBuf, Vec<u64>)> = Vec::new();
    for ep in &episodes {
        let field = format!("`data_path` template {:?} (episode {})", info.data_path, ep.episode_index);
        let rel = fill_template(
            &info.data_path,
            &[
                ("chunk_index", "", ep.data_chunk),
                ("file_index", "", ep.data_file),
                ("episode_chunk", "", ep.data_chunk),
                ("episode_index", "", ep.episode_index),
            ],
        )
        .map_err(|m| IngestError::invalid(&info_path, format!("{field}: {m}")))?;
        let abs = confine.join(&info_path, &field, &rel)?;
        match files.last_mut() {
            Some((p, v)) if *p == abs => v.push(ep.episode_index),
            _ => {
                confine.check_inside(&abs, &field)?;
                files.push((abs, vec![ep.episode_index]))
            }
        }
    }
    let mut ctx = Ctx {
        root,
        confine: &confine,
        info_path: &info_path,
        info: &info,
        plan: &plan,
        tasks: &tasks,
        metas: episodes.iter().enumerate().map(|(i, e)| (e.episode_index, (i, e.clone()))).collect(),
        opts,
        emitted_media: HashMap::new(),
        seen: HashSet::new(),
    };
    let mut done_files = HashSet::new();
    for (file, _) in &files {
        if !done_files.insert(file.clone()) {
            continue;
        }
        if !file.is_file() {
            return Err(IngestError::invalid(file, "missing data file"));
        }
        let f = std::fs::File::open(file).map_err(|e| IngestError::io(file, e))?;
        stream_data(file, f, &plan, &mut |b| ctx.finish(file, b, sink))?;
    }
    for ep in &episodes {
        if !ctx.seen.contains(&ep.episode_index) {
            return Err(IngestError::invalid(root, format!("episode {} has no data rows", ep.episode_index)));
        }
    }
    Ok(())
}

fn stream_data<R: ChunkReader + 'static>(
    path: &Path,
    r: R,
    plan: &Plan,
    emit: &mut dyn FnMut(EpBuf) -> Result<()>,
) -> Result<()> {
    // Rows are decoded a batch at a time, page by page from the file (the sync reader reads
    // pages, not whole row groups); PNG image columns make a row KBs, so their batches are small.
    let batch_rows = if plan.images.is_empty() { 4096 } else { 64 };
    let reader = checked_builder(path, r)?
        .with_batch_size(batch_rows)
        .build()
        .map_err(|e| IngestError::invalid(path, format!("not a readable Parquet file: {e}")))?;
    let mut dr = DataReader { plan, cur: None };
    let mut reader = reader;
    while let Some(b) = guarded(path, || Ok(reader.next()))? {
        let b = b.map_err(|e| IngestError::invalid(path, format!("corrupt Parquet data: {e}")))?;
        dr.push_batch(path, &b, emit)?;
    }
    if let Some(last) = dr.cur.take() {
        emit(last)?;
    }
    Ok(())
}

/// Fuzzing entry: parse `info.json` bytes, then stream `parquet` bytes as a data file of that
/// dataset (episodes are only counted). Feature `testing` (the fuzz targets and the tests).
#[cfg(any(test, feature = "testing"))]
pub fn fuzz_entry(info_json: &[u8], parquet: &[u8]) -> Result<usize> {
    let p = Path::new("fuzz/meta/info.json");
    let info = match parse_info(p, info_json) {
        Ok(i) => i,
        Err(_) => parse_info(p, DEFAULT_INFO.as_bytes())?,
    };
    let plan = plan(&info, &ReadOptions::default())?;
    let mut n = 0usize;
    let data = bytes::Bytes::copy_from_slice(parquet);
    stream_data(Path::new("fuzz/data.parquet"), data, &plan, &mut |b| {
        n += b.rows;
        for im in b.images.iter().flatten() {
            let _ = png_shape(im);
        }
        Ok(())
    })?;
    Ok(n)
}

#[cfg(any(test, feature = "testing"))]
const DEFAULT_INFO: &str = r#"{"codebase_version":"v3.0","fps":10,"features":{
 "observation.state":{"dtype":"float32","shape":[6]},"action":{"dtype":"float32","shape":[6]},
 "next.reward":{"dtype":"float32","shape":[1]},"next.success":{"dtype":"bool","shape":[1]},
 "next.done":{"dtype":"bool","shape":[1]},"timestamp":{"dtype":"float32","shape":[1]}}}"#;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn observations_keep_the_order_info_json_lists_them_in() {
        let info = br#"{"codebase_version":"v3.0","fps":10,"features":{
            "observation.state":{"dtype":"float32","shape":[7]},
            "observation.environment_state":{"dtype":"float32","shape":[3]},
            "action":{"dtype":"float32","shape":[7]},
            "observation.arm_effort":{"dtype":"float32","shape":[7]}}}"#;
        let info = parse_info(Path::new("meta/info.json"), info).unwrap();
        let plan = plan(&info, &ReadOptions::default()).unwrap();
        let names: Vec<&str> = plan.observations.iter().map(|(_, n)| n.as_str()).collect();
        assert_eq!(names, ["state", "environment_state", "arm_effort"]);
    }
}
