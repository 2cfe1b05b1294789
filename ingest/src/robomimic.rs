//! robomimic HDF5 rollouts: `data/demo_N/{obs/<key>, next_obs/<key>, actions, rewards, dones,
//! states}`, attributes `data@total`, `data@env_args` (JSON), `demo@num_samples`,
//! `demo@model_file`, and `mask/<filter>` lists of demo names.
//!
//! Read with `hdf5-pure` (no system library) through positioned reads of the file, one demo at
//! a time: memory is bounded by a demo's low-dim datasets, not by the file; image observations
//! (and their `next_obs`) are read a window of rows at a time as the store pulls them (`h5rows`).
//!
//! Lossless: what the step model has no place for is kept as extra columns (`states`,
//! `next_obs/<key>` where it differs from the next step's `obs/<key>`, any other per-step
//! dataset, attribute values too large for the episode metadata), so an export gives the file
//! back; what still cannot be kept is reported as a note.
//!
//! One file past 700 lines: one format's reader (file checks, demo groups, observation and image
//! datasets, labels) whose parts are read in the file's order and share its error context.

use std::collections::{BTreeMap, HashMap};
use std::path::Path;

use hdf5_pure::{AttrValue, DType, Dataset, File, Group};
use serde_json::{json, Map, Value};
use sha2::Digest;

use crate::error::{IngestError, Result};
use crate::h5src::{h5err, BlockCached, Src, MAX_DATASET_BYTES, MAX_DECLARED_RATIO};
use crate::model::{EpisodeInput, ExtraColumn, ImageColumn, Label, VectorColumn};
use crate::options::ReadOptions;
use crate::sink::{EpisodeSink, SourceMeta};
use arrow::array::{ArrayRef, FixedSizeListArray, PrimitiveArray, StringArray};
use arrow::buffer::NullBuffer;
use arrow::datatypes::{ArrowPrimitiveType, Field, Float32Type, Float64Type, UInt8Type};
use std::sync::Arc;

/// Budget of the metadata cache of the streaming reader (object headers, B-tree and heap blocks
/// of the demo groups are read once each; a few MB keeps the ones still in use).
pub(crate) const METADATA_CACHE_BYTES: usize = 8 << 20;

/// Attribute values larger than this (e.g. the ~38 KB MuJoCo `model_file` per demo) are not
/// copied into episode metadata; their sha256 and length are kept instead.
const MAX_ATTR_CHARS: usize = 4096;

/// Refuses a dataset whose declared shape x element size (computed with checked arithmetic)
/// is more than the file can hold: a chunked dataset whose chunks were never written, or a
/// corrupt dataspace, would otherwise make a read allocate and fill that many bytes (a 12 kB file
/// declaring 10 GB). Called before every read of a dataset.
pub(crate) fn check_declared(ds: &Dataset, path: &Src, what: &str, shape: &[u64]) -> Result<u64> {
    let elem = ds.element_size().map_err(h5err(path, format!("cannot read the datatype of {what}")))?;
    let impossible = || {
        IngestError::invalid(
            path,
            format!("{what} declares shape {shape:?} of {elem}-byte elements: the size overflows 64 bits"),
        )
    };
    let elements = shape.iter().try_fold(1u64, |a, &d| a.checked_mul(d)).ok_or_else(impossible)?;
    let bytes = elements.checked_mul(elem).ok_or_else(impossible)?;
    let max = path.max_dataset_bytes();
    if bytes > max {
        let why = if max == MAX_DATASET_BYTES
            && path.file_len.saturating_mul(MAX_DECLARED_RATIO) >= MAX_DATASET_BYTES
        {
            format!("more than the {max} bytes one dataset may decode to")
        } else {
            format!("more than the {}-byte file can hold (at most {max} at a {MAX_DECLARED_RATIO}:1 compression ratio)", path.file_len)
        };
        return Err(IngestError::invalid(
            path,
            format!("{what} declares shape {shape:?} of {elem}-byte elements = {bytes} bytes, {why}: refused (unwritten chunks or a corrupt header)"),
        ));
    }
    Ok(bytes)
}

/// The file read with positioned reads (`pread`): no shared cursor, no lock, no whole-file copy.
pub(crate) struct PositionedFile {
    pub(crate) file: std::fs::File,
    pub(crate) len: u64,
}

impl hdf5_pure::Source for PositionedFile {
    fn len(&self) -> u64 {
        self.len
    }

    fn read_at(&self, offset: u64, buf: &mut [u8]) -> std::result::Result<(), hdf5_pure::FormatError> {
        use std::os::unix::fs::FileExt;
        let past_end = offset.checked_add(buf.len() as u64).is_none_or(|end| end > self.len);
        if past_end {
            return Err(hdf5_pure::FormatError::UnexpectedEof {
                expected: offset.saturating_add(buf.len() as u64).try_into().unwrap_or(usize::MAX),
                available: self.len.try_into().unwrap_or(usize::MAX),
            });
        }
        self.file.read_exact_at(buf, offset).map_err(|e| hdf5_pure::FormatError::Source(e.to_string()))
    }
}

/// Reads a robomimic file from disk, demo by demo: the file is never loaded whole (memory is
/// bounded by one demo's datasets, whatever the file's size).
pub fn read_file(path: &Path, opts: &ReadOptions, sink: &mut dyn EpisodeSink) -> Result<()> {
    read_file_notes(path, opts, sink).map(|_| ())
}

/// [`read_file`], returning notes on what could not be kept (for the user, as warnings).
pub fn read_file_notes(path: &Path, opts: &ReadOptions, sink: &mut dyn EpisodeSink) -> Result<Vec<String>> {
    read_h5(&open_h5(path)?, path, opts, sink)
}

/// Opens a source's HDF5 file (robomimic or ALOHA): its signature checked, its metadata cached
/// and its small reads served from cached blocks of the file.
pub(crate) fn open_h5(path: &Path) -> Result<File> {
    check_signature_file(path)?;
    let f = std::fs::File::open(path).map_err(|e| IngestError::io(path, e))?;
    let len = f.metadata().map_err(|e| IngestError::io(path, e))?.len();
    let props = hdf5_pure::FileAccessProperties::new()
        .with_metadata_cache(hdf5_pure::MetadataCacheConfig::new(METADATA_CACHE_BYTES));
    File::from_source_with_options(BlockCached::new(PositionedFile { file: f, len }), props)
        .map_err(|e| IngestError::invalid(path, format!("not a readable HDF5 file: {e}")))
}

/// Reads a robomimic file held in memory (`name` is used in error messages).
pub fn read_bytes(name: &Path, bytes: Vec<u8>, opts: &ReadOptions, sink: &mut dyn EpisodeSink) -> Result<()> {
    if !hdf5_pure::is_hdf5_bytes(&bytes) {
        return Err(IngestError::invalid(name, "not an HDF5 file (no HDF5 signature)"));
    }
    let file = File::from_bytes(bytes)
        .map_err(|e| IngestError::invalid(name, format!("not a readable HDF5 file: {e}")))?;
    read_h5(&file, name, opts, sink).map(|_| ())
}

pub(crate) fn check_signature_file(path: &Path) -> Result<()> {
    match hdf5_pure::is_hdf5(path) {
        Ok(true) => Ok(()),
        Ok(false) => Err(IngestError::invalid(path, "not an HDF5 file (no HDF5 signature)")),
        Err(e) => Err(IngestError::io(path, e)),
    }
}

/// Converts an attribute value to JSON.
pub(crate) fn attr_json(v: &AttrValue) -> Value {
    if let Some(s) = v.as_str() {
        return Value::String(s.to_string());
    }
    if let Some(ss) = v.as_strings() {
        return json!(ss);
    }
    match v {
        AttrValue::F32(x) => json!(x),
        AttrValue::F64(x) => json!(x),
        AttrValue::F32Array(x) => json!(x),
        AttrValue::F64Array(x) => json!(x),
        AttrValue::I8Array(x) => json!(x),
        AttrValue::I16Array(x) => json!(x),
        AttrValue::I32Array(x) => json!(x),
        AttrValue::I64Array(x) => json!(x),
        AttrValue::U8Array(x) => json!(x),
        AttrValue::U16Array(x) => json!(x),
        AttrValue::U32Array(x) => json!(x),
        AttrValue::U64Array(x) => json!(x),
        _ => {
            if let Some(i) = v.as_i64() {
                json!(i)
            } else if let Some(u) = v.as_u64() {
                json!(u)
            } else if let Some(f) = v.as_f64() {
                json!(f)
            } else {
                Value::String(format!("{v:?}"))
            }
        }
    }
}

/// Reads the attributes of a group and fails when one cannot be represented (hdf5-pure skips
/// those silently in `attrs()`) and `required` names it.
pub(crate) fn group_attrs(
    g: &Group,
    path: &Path,
    where_: &str,
    required: &[&str],
) -> Result<HashMap<String, AttrValue>> {
    let attrs = g.attrs().map_err(h5err(path, format!("cannot read the attributes of {where_}")))?;
    if !required.is_empty() {
        let types =
            g.attr_datatypes().map_err(h5err(path, format!("cannot read the attributes of {where_}")))?;
        for r in required {
            if types.contains_key(*r) && !attrs.contains_key(*r) {
                return Err(IngestError::invalid(
                    path,
                    format!("attribute {where_}@{r} has a datatype that cannot be read"),
                ));
            }
        }
    }
    Ok(attrs)
}

fn demo_index(name: &str) -> Option<u64> {
    name.rsplit('_').next().and_then(|s| s.parse().ok())
}

pub(crate) struct DatasetInfo {
    pub(crate) shape: Vec<u64>,
    pub(crate) dtype: DType,
}

pub(crate) fn info(ds: &Dataset, path: &Src, what: &str) -> Result<DatasetInfo> {
    let shape = ds.shape().map_err(h5err(path, format!("cannot read the shape of {what}")))?;
    let dtype = ds.dtype().map_err(h5err(path, format!("cannot read the datatype of {what}")))?;
    check_declared(ds, path, what, &shape)?;
    Ok(DatasetInfo { shape, dtype })
}

pub(crate) fn is_numeric(d: &DType) -> bool {
    matches!(
        d,
        DType::F32
            | DType::F64
            | DType::I8
            | DType::I16
            | DType::I32
            | DType::I64
            | DType::U8
            | DType::U16
            | DType::U32
            | DType::U64
    )
}

/// Rows x columns of a (T, ...) numeric dataset, read as f32.
pub(crate) fn read_matrix(
    ds: &Dataset,
    path: &Src,
    what: &str,
    steps: Option<usize>,
) -> Result<(usize, usize, Vec<f32>)> {
    let inf = info(ds, path, what)?;
    if !is_numeric(&inf.dtype) {
        return Err(IngestError::invalid(
            path,
            format!("{what} has datatype {} (expected a number type)", inf.dtype),
        ));
    }
    if inf.shape.is_empty() {
        return Err(IngestError::invalid(path, format!("{what} is a scalar (expected one row per step)")));
    }
    let rows = inf.shape[0] as usize;
    let dim: u64 = inf.shape[1..].iter().try_fold(1u64, |a, &b| a.checked_mul(b)).ok_or_else(|| {
        IngestError::invalid(path, format!("{what} has an impossible shape {:?}", inf.shape))
    })?;
    if let Some(t) = steps {
        if rows != t {
            return Err(IngestError::invalid(
                path,
                format!("{what} has {rows} rows but the demo has {t} steps"),
            ));
        }
    }
    let values = ds.read_f32().map_err(h5err(path, format!("cannot read {what}")))?;
    if values.len() as u64 != rows as u64 * dim {
        return Err(IngestError::invalid(
            path,
            format!("{what}: read {} values, shape {:?} says {}", values.len(), inf.shape, rows as u64 * dim),
        ));
    }
    Ok((rows, dim as usize, values))
}

fn read_env_args(data: &Group, path: &Path) -> Result<(Value, Map<String, Value>)> {
    let attrs = group_attrs(data, path, "data", &["env_args", "total"])?;
    let mut extra = Map::new();
    let env_args = match attrs.get("env_args") {
        Some(v) => match v.as_str() {
            Some(s) => serde_json::from_str::<Value>(s)
                .map_err(|e| IngestError::invalid(path, format!("data@env_args is not valid JSON: {e}")))?,
            None => {
                return Err(IngestError::invalid(path, "data@env_args is not a string"));
            }
        },
        None => Value::Null,
    };
    for (k, v) in attrs.iter() {
        if k != "env_args" {
            extra.insert(k.clone(), attr_json(v));
        }
    }
    Ok((env_args, extra))
}

/// Reads `mask/<filter>` lists (demo names as strings) into demo → tags.
fn read_masks(file: &File, path: &Src) -> Result<HashMap<String, Vec<String>>> {
    let mut tags: HashMap<String, Vec<String>> = HashMap::new();
    let Ok(mask) = file.group("mask") else { return Ok(tags) };
    let names = mask.datasets().map_err(h5err(path, "cannot list mask/"))?;
    for filter in names {
        let ds = mask.dataset(&filter).map_err(h5err(path, format!("cannot open mask/{filter}")))?;
        info(&ds, path, &format!("mask/{filter}"))?;
        let demos =
            ds.read_string().map_err(h5err(path, format!("mask/{filter} is not a list of demo names")))?;
        for d in demos {
            let d = d.trim_end_matches('\0').trim().to_string();
            tags.entry(d).or_default().push(filter.clone());
        }
    }
    Ok(tags)
}

fn control_freq(env_args: &Value) -> Option<f64> {
    let f =
        env_args.pointer("/env_kwargs/control_freq").or_else(|| env_args.get("control_freq"))?.as_f64()?;
    (f.is_finite() && f > 0.0).then_some(f)
}

fn read_h5(file: &File, path: &Path, opts: &ReadOptions, sink: &mut dyn EpisodeSink) -> Result<Vec<String>> {
    let path = &Src::new(path, file.file_size());
    let data = file.group("data").map_err(h5err(path, "no `data` group: not a robomimic file"))?;
    let (env_args, data_attrs) = read_env_args(&data, path)?;
    let freq = control_freq(&env_args);
    let masks = read_masks(file, path)?;

    // One walk of data/ yields every demo group's handle: looking each one up by name instead
    // scans data/'s symbol table again per demo (quadratic in the number of demos).
    let mut demos: Vec<(String, Group)> =
        data.iter_groups().map_err(h5err(path, "cannot list data/"))?.collect();
    demos.sort_by(|(a, _), (b, _)| match (demo_index(a), demo_index(b)) {
        (Some(x), Some(y)) => x.cmp(&y).then(a.cmp(b)),
        (Some(_), None) => std::cmp::Ordering::Less,
        (None, Some(_)) => std::cmp::Ordering::Greater,
        (None, None) => a.cmp(b),
    });
    if demos.is_empty() {
        return Err(IngestError::invalid(path, "data/ holds no demo groups"));
    }
    let mut meta = Map::new();
    meta.insert("env_args".into(), env_args.clone());
    for (k, v) in data_attrs {
        meta.insert(k, v);
    }
    meta.insert("num_demos".into(), json!(demos.len()));
    if !masks.is_empty() {
        let mut filters: Vec<&String> = masks.values().flatten().collect();
        filters.sort();
        filters.dedup();
        meta.insert("mask_filters".into(), json!(filters));
    }
    if let Some(f) = freq {
        meta.insert("control_freq".into(), json!(f));
    }
    sink.source(SourceMeta { format: "robomimic".into(), metadata: Value::Object(meta) })?;

    let env_name = env_args.get("env_name").and_then(|v| v.as_str()).map(str::to_string);
    let mut left_out: BTreeMap<String, Vec<String>> = BTreeMap::new();
    for (index, (name, g)) in demos.iter().enumerate() {
        let (ep, extras, skipped) =
            read_demo(g, path, name, index as u32, freq, &masks, env_name.as_deref(), opts)?;
        for s in skipped {
            left_out.entry(s).or_default().push(name.clone());
        }
        sink.episode_with_extras(ep, extras)?;
    }
    Ok(left_out
        .into_iter()
        .map(|(what, demos)| format!("left out {what} (in {} demo(s), e.g. {})", demos.len(), demos[0]))
        .collect())
}

/// A `(T, ...)` array as a fixed-size-list column (`dim` values per row); rows where `valid` is
/// false are null.
pub(crate) fn fsl_column<T: ArrowPrimitiveType>(
    dim: usize,
    values: Vec<T::Native>,
    valid: Option<Vec<bool>>,
) -> Result<ArrayRef, String> {
    let item = Arc::new(Field::new("item", T::DATA_TYPE, false));
    let child = Arc::new(PrimitiveArray::<T>::from_iter_values(values));
    let nulls = valid.map(NullBuffer::from);
    FixedSizeListArray::try_new(item, dim as i32, child, nulls)
        .map(|a| Arc::new(a) as ArrayRef)
        .map_err(|e| e.to_string())
}

pub(crate) fn dtype_name(d: &DType) -> String {
    match d {
        DType::F32 => "float32".into(),
        DType::F64 => "float64".into(),
        DType::I8 => "int8".into(),
        DType::I16 => "int16".into(),
        DType::I32 => "int32".into(),
        DType::I64 => "int64".into(),
        DType::U8 => "uint8".into(),
        DType::U16 => "uint16".into(),
        DType::U32 => "uint32".into(),
        DType::U64 => "uint64".into(),
        DType::Enum(_) => "bool".into(),
        other => other.to_string(),
    }
}

fn extra(
    name: String,
    values: impl Into<store::ExtraValues>,
    dtype: &DType,
    row_shape: &[u64],
    extra_meta: &[(&str, String)],
) -> ExtraColumn {
    let mut metadata = HashMap::from([
        ("ufops.dtype".to_string(), dtype_name(dtype)),
        ("ufops.shape".to_string(), json!(row_shape).to_string()),
    ]);
    for (k, v) in extra_meta {
        metadata.insert(k.to_string(), v.clone());
    }
    ExtraColumn { name, values: values.into(), metadata }
}

/// A per-step dataset (`T` rows) as an extra column: u8 kept as u8, floats of 32 bits as f32,
/// every other number type as f64 (exact for integers up to 2^53).
fn read_extra(
    ds: &Dataset,
    path: &Src,
    what: &str,
    name: String,
    steps: usize,
) -> Result<Option<ExtraColumn>> {
    let inf = info(ds, path, what)?;
    if inf.shape.first().copied() != Some(steps as u64)
        || !(is_numeric(&inf.dtype) || matches!(inf.dtype, DType::Enum(_)))
    {
        return Ok(None);
    }
    let dim = inf.shape[1..].iter().product::<u64>() as usize;
    let bad = |e: String| IngestError::invalid(path, format!("{what}: {e}"));
    let values = match inf.dtype {
        DType::U8 => fsl_column::<UInt8Type>(
            dim,
            ds.read_u8().map_err(h5err(path, format!("cannot read {what}")))?,
            None,
        ),
        DType::F32 => fsl_column::<Float32Type>(
            dim,
            ds.read_f32().map_err(h5err(path, format!("cannot read {what}")))?,
            None,
        ),
        _ => fsl_column::<Float64Type>(
            dim,
            ds.read_f64().map_err(h5err(path, format!("cannot read {what}")))?,
            None,
        ),
    }
    .map_err(bad)?;
    Ok(Some(extra(name, values, &inf.dtype, &inf.shape[1..], &[])))
}

/// `next_obs/<key>` keeping only the rows that differ from `obs/<key>` of the next step (robomimic
/// writes `next_obs[t] == obs[t + 1]` but for the last step; rendered images may differ).
fn read_next_obs(
    ds: &Dataset,
    path: &Src,
    what: &str,
    key: &str,
    obs: Option<&ObsValues>,
    steps: usize,
) -> Result<Option<ExtraColumn>> {
    let inf = info(ds, path, what)?;
    if inf.shape.first().copied() != Some(steps as u64) {
        return Ok(None);
    }
    let dim = inf.shape[1..].iter().product::<u64>() as usize;
    let bad = |e: String| IngestError::invalid(path, format!("{what}: {e}"));
    let keep = |same: &dyn Fn(usize) -> bool| -> Vec<bool> {
        (0..steps).map(|t| t + 1 == steps || !same(t)).collect()
    };
    let meta = [("ufops.null_means", format!("obs/{key} of the next step"))];
    let values = if inf.dtype == DType::U8 {
        let valid = match obs {
            Some(ObsValues::U8(o, owhat, row_bytes)) if *row_bytes == dim as u64 => {
                crate::h5rows::rows_differ_from_shift((ds, what), (o, owhat), path, dim as u64, steps as u64)?
            }
            _ => vec![true; steps],
        };
        if inf.shape.len() == 4 {
            // An image (as large as a camera): the store reads it a page of rows at a time.
            let pages = crate::h5rows::u8_rows_paged(ds, path, what, dim, valid);
            return Ok(Some(extra(format!("next_obs/{key}"), pages, &inf.dtype, &inf.shape[1..], &meta)));
        }
        let v = ds.read_u8().map_err(h5err(path, format!("cannot read {what}")))?;
        fsl_column::<UInt8Type>(dim, v, Some(valid))
    } else if is_numeric(&inf.dtype) {
        let v = ds.read_f32().map_err(h5err(path, format!("cannot read {what}")))?;
        let valid = match obs {
            Some(ObsValues::F32(o)) if o.len() == v.len() => keep(&|t| {
                v[t * dim..(t + 1) * dim]
                    .iter()
                    .zip(&o[(t + 1) * dim..(t + 2) * dim])
                    .all(|(a, b)| a.to_bits() == b.to_bits())
            }),
            _ => vec![true; steps],
        };
        fsl_column::<Float32Type>(dim, v, Some(valid))
    } else {
        return Ok(None);
    }
    .map_err(bad)?;
    Ok(Some(extra(format!("next_obs/{key}"), values, &inf.dtype, &inf.shape[1..], &meta)))
}

/// An observation's values as stored (to compare `next_obs` with): low-dim values in memory, an
/// image's dataset (its name and bytes a row), read a window at a time.
enum ObsValues {
    F32(Vec<f32>),
    U8(Dataset, String, u64),
}

/// A demo's rewards (zeros when it has none) and dones (the last step when it has none).
fn read_rewards_and_dones(
    g: &Group,
    path: &Src,
    name: &str,
    members: &[String],
    steps: usize,
) -> Result<(Vec<f32>, Vec<bool>)> {
    let reward: Vec<f32> = if members.iter().any(|m| m == "rewards") {
        let ds = g.dataset("rewards").map_err(h5err(path, format!("cannot open data/{name}/rewards")))?;
        let (_, d, v) = read_matrix(&ds, path, &format!("data/{name}/rewards"), Some(steps))?;
        if d != 1 {
            return Err(IngestError::invalid(path, format!("data/{name}/rewards is not one value per step")));
        }
        v
    } else {
        vec![0.0; steps]
    };
    let done: Vec<bool> = if members.iter().any(|m| m == "dones") {
        read_dones(g, path, name, steps)?
    } else {
        let mut d = vec![false; steps];
        if let Some(l) = d.last_mut() {
            *l = true;
        }
        d
    };
    Ok((reward, done))
}

/// What a demo's `obs` and `next_obs` groups become.
struct Observations {
    observations: Vec<VectorColumn>,
    images: Vec<ImageColumn>,
    /// `next_obs` keys, kept exactly as extra columns (or as a shift of `obs` where they are one).
    extras: Vec<ExtraColumn>,
    skipped: Vec<String>,
}

fn read_observations(g: &Group, path: &Src, name: &str, steps: usize) -> Result<Observations> {
    let mut observations = Vec::new();
    let mut images = Vec::new();
    let mut extras = Vec::new();
    let mut skipped = Vec::new();
    // Each image observation's dataset, to compare `next_obs` with window by window.
    let mut image_obs: HashMap<String, (Dataset, String, u64)> = HashMap::new();
    if let Ok(obs) = g.group("obs") {
        let mut keys = obs.datasets().map_err(h5err(path, format!("cannot list data/{name}/obs")))?;
        keys.sort();
        for key in keys {
            let what = format!("data/{name}/obs/{key}");
            let ds = obs.dataset(&key).map_err(h5err(path, format!("cannot open {what}")))?;
            let inf = info(&ds, path, &what)?;
            if inf.dtype == DType::U8 && inf.shape.len() == 4 {
                images.push(read_images(&ds, path, &what, &key, &inf.shape, steps)?);
                let row_bytes = inf.shape[1..].iter().product();
                image_obs.insert(key, (ds, what, row_bytes));
            } else {
                let (_, dim, values) = read_matrix(&ds, path, &what, Some(steps))?;
                observations.push(VectorColumn { name: key, dim, values });
            }
        }
    }
    if let Ok(next) = g.group("next_obs") {
        let mut keys = next.datasets().map_err(h5err(path, format!("cannot list data/{name}/next_obs")))?;
        keys.sort();
        for key in keys {
            let what = format!("data/{name}/next_obs/{key}");
            let ds = next.dataset(&key).map_err(h5err(path, format!("cannot open {what}")))?;
            let o = match image_obs.remove(&key) {
                Some((ds, what, row_bytes)) => Some(ObsValues::U8(ds, what, row_bytes)),
                None => observations.iter().find(|o| o.name == key).map(|o| ObsValues::F32(o.values.clone())),
            };
            match read_next_obs(&ds, path, &what, &key, o.as_ref(), steps)? {
                Some(x) => extras.push(x),
                None => skipped.push(format!("next_obs/{key} (not one row per step)")),
            }
        }
    }
    Ok(Observations { observations, images, extras, skipped })
}

/// A demo's attributes as catalog metadata (sorted; a text too long for the catalog is kept as
/// its hash and length, its value goes to a column: [`long_attribute_columns`]).
fn demo_metadata(attrs: &HashMap<String, AttrValue>) -> Map<String, Value> {
    let mut md = Map::new();
    let mut attr_names: Vec<_> = attrs.keys().cloned().collect();
    attr_names.sort();
    for k in attr_names {
        let v = &attrs[&k];
        let jv = attr_json(v);
        match jv {
            Value::String(s) if s.len() > MAX_ATTR_CHARS => {
                md.insert(
                    k,
                    json!({"sha256": hex::encode(sha2::Sha256::digest(s.as_bytes())), "chars": s.chars().count()}),
                );
            }
            other => {
                md.insert(k, other);
            }
        }
    }
    md
}

/// Attribute values too large for the catalog (the MuJoCo `model_file`): the text on the first
/// row of an extra column (later rows null, so it costs its compressed size once).
fn long_attribute_columns(
    md: &Map<String, Value>,
    attrs: &HashMap<String, AttrValue>,
    steps: usize,
) -> Vec<ExtraColumn> {
    let mut extras = Vec::new();
    for (k, v) in md {
        if let (Some(obj), Some(text)) = (v.as_object(), attrs.get(k).and_then(|a| a.as_str())) {
            if obj.contains_key("sha256") && obj.contains_key("chars") {
                let col: ArrayRef =
                    Arc::new(StringArray::from_iter((0..steps).map(|t| (t == 0).then_some(text))));
                let meta = HashMap::from([("ufops.attribute".to_string(), k.clone())]);
                extras.push(ExtraColumn { name: format!("attr/{k}"), values: col.into(), metadata: meta });
            }
        }
    }
    extras
}

#[allow(clippy::too_many_arguments)]
fn read_demo(
    g: &Group,
    path: &Src,
    name: &str,
    index: u32,
    freq: Option<f64>,
    masks: &HashMap<String, Vec<String>>,
    env_name: Option<&str>,
    opts: &ReadOptions,
) -> Result<(EpisodeInput, Vec<ExtraColumn>, Vec<String>)> {
    let attrs = group_attrs(g, path, &format!("data/{name}"), &["num_samples"])?;
    let members = g.datasets().map_err(h5err(path, format!("cannot list data/{name}")))?;
    if !members.iter().any(|m| m == "actions") {
        return Err(IngestError::invalid(path, format!("data/{name} has no `actions` dataset")));
    }
    let actions_ds = g.dataset("actions").map_err(h5err(path, format!("cannot open data/{name}/actions")))?;
    let (steps, adim, actions) = read_matrix(&actions_ds, path, &format!("data/{name}/actions"), None)?;
    if let Some(n) = attrs.get("num_samples").and_then(|v| v.as_i64()) {
        if n != steps as i64 {
            return Err(IngestError::invalid(
                path,
                format!("data/{name}@num_samples is {n} but actions has {steps} rows"),
            ));
        }
    }

    let (reward, done) = read_rewards_and_dones(g, path, name, &members, steps)?;

    let Observations { observations, images, mut extras, mut skipped } =
        read_observations(g, path, name, steps)?;

    let timestamps: Vec<f64> = match freq {
        Some(f) => (0..steps).map(|t| t as f64 / f).collect(),
        None => (0..steps).map(|t| t as f64).collect(),
    };

    // A label given by the user wins; else a `success` demo attribute (ufops' robomimic export
    // writes the frozen label there); else unknown (robomimic itself never writes success).
    let (label, label_source) = opts.user_label(name, index, &reward).unwrap_or_else(|| {
        match attrs.get("success").and_then(|v| v.as_i64()) {
            Some(s) => (Label::from_bool(Some(s != 0)), "robomimic:demo@success".to_string()),
            None => (Label::Unknown, String::new()),
        }
    });

    let mut md = demo_metadata(&attrs);
    // The per-step human-takeover flag: a demo's `intervention` dataset (ufops' export writes it
    // there), or the one `--intervention-key` names.
    let (ikey, named) = opts.intervention_key();
    let intervention = if members.iter().any(|m| m == ikey) {
        let what = format!("data/{name}/{ikey}");
        let ds = g.dataset(ikey).map_err(h5err(path, format!("cannot open {what}")))?;
        Some(read_flags(&ds, path, &what, steps)?)
    } else if named {
        return Err(IngestError::Usage(format!(
            "--intervention-key {ikey:?}: data/{name} has no such dataset (it has {})",
            members.join(", ")
        )));
    } else {
        None
    };
    // `states` and any other per-step dataset become extra columns.
    let mut others: BTreeMap<String, Value> = BTreeMap::new();
    for m in &members {
        if !matches!(m.as_str(), "actions" | "rewards" | "dones") && m != ikey {
            let what = format!("data/{name}/{m}");
            let ds = g.dataset(m).map_err(h5err(path, format!("cannot open {what}")))?;
            match read_extra(&ds, path, &what, m.clone(), steps)? {
                Some(x) => extras.push(x),
                None => {
                    skipped.push(format!("data/<demo>/{m} (not a number array with one row per step)"));
                    if let Ok(s) = ds.shape() {
                        others.insert(m.clone(), json!(s));
                    }
                }
            }
        }
    }
    if !others.is_empty() {
        md.insert("not_ingested".into(), json!(others));
    }
    extras.extend(long_attribute_columns(&md, &attrs, steps));

    let task = opts.task.clone().or_else(|| env_name.map(str::to_string));
    let tags = masks.get(name).cloned().unwrap_or_default();
    let ep = EpisodeInput {
        source_name: name.to_string(),
        source_index: index,
        task,
        label,
        label_source,
        tags,
        metadata: Value::Object(md),
        timestamps,
        observations,
        action: VectorColumn { name: "action".into(), dim: adim, values: actions },
        reward,
        done,
        action_chunk: None,
        images,
        media: Vec::new(),
        flags: crate::model::StepFlags { intervention, validity: None },
    };
    Ok((ep, extras, skipped))
}

/// A per-step flag dataset (one number per step, non-zero = set), e.g. human takeovers.
pub(crate) fn read_flags(ds: &Dataset, path: &Src, what: &str, steps: usize) -> Result<Vec<bool>> {
    let (_, dim, values) = read_matrix(ds, path, what, Some(steps))?;
    if dim != 1 {
        return Err(IngestError::invalid(
            path,
            format!("{what} has {dim} values per step (expected one flag)"),
        ));
    }
    Ok(values.iter().map(|&v| v != 0.0).collect())
}

fn read_dones(g: &Group, path: &Src, name: &str, steps: usize) -> Result<Vec<bool>> {
    let what = format!("data/{name}/dones");
    let ds = g.dataset("dones").map_err(h5err(path, format!("cannot open {what}")))?;
    let inf = info(&ds, path, &what)?;
    let rows = inf.shape.first().copied().unwrap_or(0) as usize;
    if rows != steps || inf.shape.iter().skip(1).any(|&d| d != 1) {
        return Err(IngestError::invalid(
            path,
            format!("{what} has shape {:?} but the demo has {steps} steps", inf.shape),
        ));
    }
    let vals: Vec<bool> = match &inf.dtype {
        DType::F32 | DType::F64 => ds
            .read_f64()
            .map_err(h5err(path, format!("cannot read {what}")))?
            .into_iter()
            .map(|x| x != 0.0)
            .collect(),
        DType::Enum(_) => {
            // bool stored as an HDF5 enum {FALSE=0, TRUE=1} over an integer base.
            match ds.read_i64() {
                Ok(v) => v.into_iter().map(|x| x != 0).collect(),
                Err(_) => {
                    let raw = ds.read_raw().map_err(h5err(path, format!("cannot read {what}")))?;
                    if raw.is_empty() || raw.len() % steps.max(1) != 0 {
                        return Err(IngestError::invalid(path, format!("{what}: unexpected enum storage")));
                    }
                    let w = raw.len() / steps.max(1);
                    raw.chunks(w).map(|c| c.iter().any(|&b| b != 0)).collect()
                }
            }
        }
        d if is_numeric(d) => ds
            .read_i64()
            .map_err(h5err(path, format!("cannot read {what}")))?
            .into_iter()
            .map(|x| x != 0)
            .collect(),
        other => {
            return Err(IngestError::invalid(
                path,
                format!("{what} has datatype {other} (expected bool or integer)"),
            ));
        }
    };
    if vals.len() != steps {
        return Err(IngestError::invalid(
            path,
            format!("{what}: read {} values for {steps} steps", vals.len()),
        ));
    }
    Ok(vals)
}

fn read_images(
    ds: &Dataset,
    path: &Src,
    what: &str,
    key: &str,
    shape: &[u64],
    steps: usize,
) -> Result<ImageColumn> {
    let t = shape[0] as usize;
    if t != steps {
        return Err(IngestError::invalid(
            path,
            format!("{what} has {t} frames but the demo has {steps} steps"),
        ));
    }
    // Streamed: read and PNG-encoded a window of frames at a time as the store pulls them.
    crate::h5rows::raw_camera(ds, path, what, key, shape)
}
