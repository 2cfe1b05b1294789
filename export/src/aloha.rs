//! ALOHA / ACT episodes: a folder with one `episode_<i>.hdf5` per episode, written front to back
//! by `h5stream` as ALOHA's recorders lay them out (`/observations/{qpos,qvel,effort}`,
//! `/observations/images/<camera>`, `/action`, `/compress_len`, root attributes `sim`,
//! `compress`, `success`).
//!
//! An episode ingested from ALOHA carries a manifest in its metadata (`aloha`: every group,
//! dataset — dtype, shape, where it is kept — and typed attribute), and is written back as it
//! was: observations and actions from their float32 columns (or the exact values kept beside them
//! when the source's dtype was another), raw cameras decoded from PNG (or from their H.264 video
//! when ingested with `--images video`: within a PSNR bound, see `cameras.rs`), compressed
//! cameras as their JPEG bytes padded to the source's row length (the source's non-zero padding
//! where ingest kept it), `compress_len` as it was, small datasets from the manifest. The
//! version's frozen label is the `success` attribute (in the source's type when it had one).
//! Boolean attributes are written as int8 0/1 (no enumerated attribute type is written; h5py
//! reads them as `np.int8`, which compares equal to the bool).
//!
//! Other episodes get ALOHA's layout from the store's columns: `obs.<key>` as
//! `/observations/<key>` (float32), `action`, PNG image columns and video cameras as raw
//! cameras, JPEG ones as compressed cameras with `compress_len`, `sim` false.
//!
//! Episodes are read and written one at a time (an ALOHA episode with raw cameras is 0.5-2 GB),
//! each file under the staged folder, renamed into place at the end. An episode's file is planned
//! from its steps and manifest (what each dataset is read from), then written a dataset at a
//! time, each group after its children: float columns straight from their buffers, PNG cameras
//! decoded a window of frames at a time (8 MiB), JPEG rows padded a window at a time (4 MiB),
//! video cameras fetched and decoded one at a time as their dataset is written (one camera's
//! frames in memory). Memory holds the episode's steps (PNG/JPEG bytes) and one window, not the
//! file.

use std::collections::{BTreeMap, HashMap};
use std::path::Path;

use arrow::array::{Array, ArrayRef, AsArray, RecordBatch};
use arrow::datatypes::{
    DataType, Float32Type, Float64Type, Int16Type, Int32Type, Int64Type, Int8Type, UInt16Type, UInt32Type,
    UInt64Type, UInt8Type,
};
use serde_json::Value;
use store::steps::{IMAGE_PREFIX, OBS_PREFIX};
use store::{EpisodeRecord, Store};

use crate::cameras::{png_frames, video_cameras, VideoDecoder};
use crate::{
    count_label, disk_size, EpisodeReader, ExportError, ExportReport, Progress, Result, Selected, Staged,
};
use h5stream::{Attr, Element, Group, StrKind, Writer};

fn bad(e: &EpisodeRecord, what: impl std::fmt::Display) -> ExportError {
    ExportError::invalid(format!("episode {}: {what}", e.id))
}

/// A dataset's values in its own number type.
#[derive(Debug, Clone)]
enum Values {
    F32(Vec<f32>),
    F64(Vec<f64>),
    I8(Vec<i8>),
    I16(Vec<i16>),
    I32(Vec<i32>),
    I64(Vec<i64>),
    U8(Vec<u8>),
    U16(Vec<u16>),
    U32(Vec<u32>),
    U64(Vec<u64>),
}

impl Values {
    fn len(&self) -> usize {
        match self {
            Values::F32(v) => v.len(),
            Values::F64(v) => v.len(),
            Values::I8(v) => v.len(),
            Values::I16(v) => v.len(),
            Values::I32(v) => v.len(),
            Values::I64(v) => v.len(),
            Values::U8(v) => v.len(),
            Values::U16(v) => v.len(),
            Values::U32(v) => v.len(),
            Values::U64(v) => v.len(),
        }
    }

    /// Values of a JSON list in the dtype named (the manifest's inline datasets).
    fn from_json(dtype: &str, v: &Value) -> Option<Values> {
        let a = v.as_array()?;
        macro_rules! ints {
            ($var:ident, $t:ty) => {
                Values::$var(
                    a.iter()
                        .map(|x| x.as_i64().and_then(|i| <$t>::try_from(i).ok()))
                        .collect::<Option<Vec<$t>>>()?,
                )
            };
        }
        Some(match dtype {
            "float32" => Values::F32(a.iter().map(|x| x.as_f64().map(|f| f as f32)).collect::<Option<_>>()?),
            "float64" => Values::F64(a.iter().map(Value::as_f64).collect::<Option<_>>()?),
            "int8" => ints!(I8, i8),
            "int16" => ints!(I16, i16),
            "int32" => ints!(I32, i32),
            "int64" => ints!(I64, i64),
            "uint8" => ints!(U8, u8),
            "uint16" => ints!(U16, u16),
            "uint32" => ints!(U32, u32),
            "uint64" => Values::U64(a.iter().map(Value::as_u64).collect::<Option<_>>()?),
            _ => return None,
        })
    }

    /// The values of a fixed-size-list column (all rows), in its item type.
    fn from_list(col: &ArrayRef) -> Option<(usize, Values)> {
        let l = col.as_fixed_size_list_opt()?;
        let d = l.value_length() as usize;
        let (a, b) = (l.offset() * d, (l.offset() + l.len()) * d);
        let v = l.values();
        macro_rules! take {
            ($var:ident, $t:ty) => {
                Values::$var(v.as_primitive_opt::<$t>()?.values()[a..b].to_vec())
            };
        }
        Some((
            d,
            match l.value_type() {
                DataType::Float32 => take!(F32, Float32Type),
                DataType::Float64 => take!(F64, Float64Type),
                DataType::Int8 => take!(I8, Int8Type),
                DataType::Int16 => take!(I16, Int16Type),
                DataType::Int32 => take!(I32, Int32Type),
                DataType::Int64 => take!(I64, Int64Type),
                DataType::UInt8 => take!(U8, UInt8Type),
                DataType::UInt16 => take!(U16, UInt16Type),
                DataType::UInt32 => take!(U32, UInt32Type),
                DataType::UInt64 => take!(U64, UInt64Type),
                _ => return None,
            },
        ))
    }

    /// `t` rows of `d` values transposed into `d` rows of `t` values.
    fn transposed(&self, t: usize, d: usize) -> Values {
        fn tr<T: Copy>(v: &[T], t: usize, d: usize) -> Vec<T> {
            (0..d).flat_map(|r| (0..t).map(move |k| v[k * d + r])).collect()
        }
        match self {
            Values::F32(v) => Values::F32(tr(v, t, d)),
            Values::F64(v) => Values::F64(tr(v, t, d)),
            Values::I8(v) => Values::I8(tr(v, t, d)),
            Values::I16(v) => Values::I16(tr(v, t, d)),
            Values::I32(v) => Values::I32(tr(v, t, d)),
            Values::I64(v) => Values::I64(tr(v, t, d)),
            Values::U8(v) => Values::U8(tr(v, t, d)),
            Values::U16(v) => Values::U16(tr(v, t, d)),
            Values::U32(v) => Values::U32(tr(v, t, d)),
            Values::U64(v) => Values::U64(tr(v, t, d)),
        }
    }
}

/// Frames decoded from PNG at a time: as many as fit this many bytes (at least one).
const PNG_WINDOW_BYTES: usize = 8 << 20;
/// JPEG rows padded at a time: as many as fit this many bytes (at least one).
const JPEG_WINDOW_BYTES: usize = 4 << 20;

/// Where a dataset's values come from: read (decoded, padded) while the dataset is written.
enum Source {
    /// Values already in memory: the manifest's inline ones, `compress_len`, `intervention`.
    Values(Values),
    /// A fixed-size-list column, every row.
    List(ArrayRef),
    /// A PNG image column, decoded a window of frames at a time.
    Png(String),
    /// A JPEG image column as rows of `width` bytes: each frame, then its kept padding (the
    /// `pad` column) or zeros.
    Jpeg { column: String, pad: Option<String>, width: usize },
    /// A video camera (`media.<camera>`), decoded when its dataset is written; left out when it
    /// is not H.264 (the decoder warns).
    Video(String),
}

/// A dataset to write: where its values come from, its shape (`None`: the frames' own, known
/// once decoded) and attributes.
struct Spec {
    source: Source,
    shape: Option<Vec<u64>>,
    attrs: Vec<(String, Attr)>,
}

/// The file to write: groups by path, each with its datasets (not read yet) and attributes.
#[derive(Default)]
struct Node {
    datasets: Vec<(String, Spec)>,
    groups: BTreeMap<String, Node>,
    attrs: Vec<(String, Attr)>,
}

/// Sets `name` in `attrs`, replacing a value of the same name.
fn set_attr(attrs: &mut Vec<(String, Attr)>, name: &str, value: Attr) {
    match attrs.iter_mut().find(|(n, _)| n == name) {
        Some(slot) => slot.1 = value,
        None => attrs.push((name.to_string(), value)),
    }
}

impl Node {
    fn group(&mut self, path: &str) -> &mut Node {
        let mut n = self;
        for part in path.split('/').filter(|p| !p.is_empty()) {
            n = n.groups.entry(part.to_string()).or_default();
        }
        n
    }

    fn dataset(&mut self, path: &str, source: Source, shape: Option<Vec<u64>>) {
        let (parent, name) = path.rsplit_once('/').unwrap_or(("", path));
        self.group(parent).datasets.push((name.to_string(), Spec { source, shape, attrs: Vec::new() }));
    }

    /// Attributes of the object at `path` (a group, or a dataset already added).
    fn set_attrs(&mut self, path: &str, attrs: Vec<(String, Attr)>) {
        let (parent, name) = path.rsplit_once('/').unwrap_or(("", path));
        let g = self.group(parent);
        if let Some(d) = g.datasets.iter_mut().find(|d| d.0 == name) {
            for (k, a) in attrs {
                set_attr(&mut d.1.attrs, &k, a);
            }
        } else {
            let g = self.group(path);
            for (k, a) in attrs {
                set_attr(&mut g.attrs, &k, a);
            }
        }
    }

    /// The file in the order it is written: each group's datasets and groups before the group.
    fn into_ops(self, name: String, ops: &mut Vec<Op>) {
        ops.push(Op::Open(name.clone()));
        for (dataset, spec) in self.datasets {
            ops.push(Op::Dataset(dataset, spec));
        }
        for (child, node) in self.groups {
            node.into_ops(child, ops);
        }
        ops.push(Op::Close(name, self.attrs));
    }
}

/// One step of writing the file: open a group, write a dataset into the open group, close the
/// open group (its attributes) and link it into its parent.
enum Op {
    Open(String),
    Dataset(String, Spec),
    Close(String, Vec<(String, Attr)>),
}

/// A manifest attribute (`{type, value}`) back as the value ingest read.
fn attr_value(t: &Value) -> Option<Attr> {
    let ty = t.get("type")?.as_str()?;
    let v = t.get("value")?;
    let strs =
        || -> Option<Vec<String>> { v.as_array()?.iter().map(|s| s.as_str().map(str::to_string)).collect() };
    macro_rules! arr {
        ($f:expr) => {
            Attr::numbers(&v.as_array()?.iter().map($f).collect::<Option<Vec<_>>>()?)
        };
    }
    Some(match ty {
        "bool" => Attr::number(v.as_bool()? as i8),
        "bool[]" => arr!(|x: &Value| x.as_bool().map(|b| b as i8)),
        "f32" => Attr::number(v.as_f64()? as f32),
        "f64" => Attr::number(v.as_f64()?),
        "i8" => Attr::number(i8::try_from(v.as_i64()?).ok()?),
        "i16" => Attr::number(i16::try_from(v.as_i64()?).ok()?),
        "i32" => Attr::number(i32::try_from(v.as_i64()?).ok()?),
        "i64" => Attr::number(v.as_i64()?),
        "u8" => Attr::number(u8::try_from(v.as_u64()?).ok()?),
        "u16" => Attr::number(u16::try_from(v.as_u64()?).ok()?),
        "u32" => Attr::number(u32::try_from(v.as_u64()?).ok()?),
        "u64" => Attr::number(v.as_u64()?),
        "f32[]" => arr!(|x: &Value| x.as_f64().map(|f| f as f32)),
        "f64[]" => arr!(Value::as_f64),
        "i8[]" => arr!(|x: &Value| x.as_i64().and_then(|i| i8::try_from(i).ok())),
        "i16[]" => arr!(|x: &Value| x.as_i64().and_then(|i| i16::try_from(i).ok())),
        "i32[]" => arr!(|x: &Value| x.as_i64().and_then(|i| i32::try_from(i).ok())),
        "i64[]" => arr!(Value::as_i64),
        "u8[]" => arr!(|x: &Value| x.as_u64().and_then(|i| u8::try_from(i).ok())),
        "u16[]" => arr!(|x: &Value| x.as_u64().and_then(|i| u16::try_from(i).ok())),
        "u32[]" => arr!(|x: &Value| x.as_u64().and_then(|i| u32::try_from(i).ok())),
        "u64[]" => arr!(Value::as_u64),
        "str" => Attr::string(v.as_str()?, StrKind::FixedUtf8),
        "ascii" => Attr::string(v.as_str()?, StrKind::FixedAscii),
        "vlen_str" => Attr::string(v.as_str()?, StrKind::VarUtf8),
        "vlen_ascii" => Attr::string(v.as_str()?, StrKind::VarAscii),
        "str[]" => Attr::strings(strs()?, StrKind::FixedUtf8),
        "ascii[]" => Attr::strings(strs()?, StrKind::FixedAscii),
        "vlen_str[]" => Attr::strings(strs()?, StrKind::VarUtf8),
        "vlen_ascii[]" => Attr::strings(strs()?, StrKind::VarAscii),
        _ => return None,
    })
}

/// The byte lengths of a JPEG image column's frames.
fn jpeg_lens(e: &EpisodeRecord, name: &str, col: &ArrayRef) -> Result<Vec<usize>> {
    let bin = col.as_binary_opt::<i32>().ok_or_else(|| bad(e, format!("{name} is not a binary column")))?;
    Ok((0..bin.len()).map(|r| bin.value(r).len()).collect())
}

/// The item count of a fixed-size-list column of numbers (what [`Values::from_list`] takes).
fn list_dim(col: &ArrayRef) -> Option<usize> {
    let l = col.as_fixed_size_list_opt()?;
    let numbers = matches!(
        l.value_type(),
        DataType::Float32
            | DataType::Float64
            | DataType::Int8
            | DataType::Int16
            | DataType::Int32
            | DataType::Int64
            | DataType::UInt8
            | DataType::UInt16
            | DataType::UInt32
            | DataType::UInt64
    );
    numbers.then_some(l.value_length() as usize)
}

/// Plans one episode file from its steps and the manifest of an ALOHA source.
fn episode_file(
    e: &EpisodeRecord,
    steps: &RecordBatch,
    manifest: Option<&Value>,
) -> Result<(Node, Vec<String>)> {
    match manifest {
        Some(m) => episode_from_manifest(e, steps, m),
        None => Ok((episode_from_columns(e, steps)?, Vec::new())),
    }
}

/// The steps' column `name`, or an error saying the episode has none.
fn need<'a>(e: &EpisodeRecord, steps: &'a RecordBatch, name: &str) -> Result<&'a ArrayRef> {
    steps.column_by_name(name).ok_or_else(|| bad(e, format!("has no column {name}")))
}

/// ALOHA's layout from the store's columns (an episode whose source was not ALOHA).
fn episode_from_columns(e: &EpisodeRecord, steps: &RecordBatch) -> Result<Node> {
    let t = steps.num_rows();
    let mut root = Node::default();
    let schema = steps.schema();
    let mut jpeg: Vec<(String, String)> = Vec::new();
    for f in schema.fields() {
        let c = need(e, steps, f.name())?;
        if let Some(k) = f.name().strip_prefix(OBS_PREFIX) {
            let d = list_dim(c).ok_or_else(|| bad(e, format!("{} is not a list column", f.name())))?;
            root.dataset(
                &format!("/observations/{k}"),
                Source::List(c.clone()),
                Some(vec![t as u64, d as u64]),
            );
        } else if f.name() == store::steps::INTERVENTION_COLUMN {
            // Human takeovers, where ingest reads them back (`/intervention`, 0/1).
            let flags = c.as_boolean_opt().ok_or_else(|| bad(e, "intervention is not a boolean column"))?;
            let flags: Vec<u8> = flags.iter().map(|b| (b == Some(true)) as u8).collect();
            root.dataset("/intervention", Source::Values(Values::U8(flags)), Some(vec![t as u64]));
        } else if let Some(k) = f.name().strip_prefix(IMAGE_PREFIX) {
            if f.metadata().get("ufops.encoding").is_some_and(|x| x == "jpeg") {
                jpeg.push((k.to_string(), f.name().clone()));
            } else {
                root.dataset(&format!("/observations/images/{k}"), Source::Png(f.name().clone()), None);
            }
        }
    }
    for k in video_cameras(steps) {
        root.dataset(&format!("/observations/images/{k}"), Source::Video(k.clone()), None);
    }
    let action = need(e, steps, "action")?;
    let d = list_dim(action).ok_or_else(|| bad(e, "has no actions: ALOHA needs one per step"))?;
    root.dataset("/action", Source::List(action.clone()), Some(vec![t as u64, d as u64]));
    root.group("/observations/images");
    let mut attrs = vec![("sim".to_string(), Attr::number(0i8))];
    if !jpeg.is_empty() {
        jpeg.sort_by(|a, b| a.0.cmp(&b.0));
        let mut lens = Vec::new();
        for (k, column) in &jpeg {
            let l = jpeg_lens(e, k, need(e, steps, column)?)?;
            let width = l.iter().copied().max().unwrap_or(0);
            let source = Source::Jpeg { column: column.clone(), pad: None, width };
            root.dataset(&format!("/observations/images/{k}"), source, Some(vec![t as u64, width as u64]));
            lens.extend(l.into_iter().map(|x| x as f32));
        }
        let shape = vec![jpeg.len() as u64, t as u64];
        root.dataset("/compress_len", Source::Values(Values::F32(lens)), Some(shape));
        attrs.push(("compress".to_string(), Attr::number(1i8)));
    }
    root.set_attrs("/", attrs);
    Ok(root)
}

/// The ALOHA source's file as its manifest describes it: groups, datasets and attributes, with
/// warnings for what could not be written back.
fn episode_from_manifest(e: &EpisodeRecord, steps: &RecordBatch, m: &Value) -> Result<(Node, Vec<String>)> {
    let mut root = Node::default();
    let mut warnings = Vec::new();
    for g in m.get("groups").and_then(Value::as_array).into_iter().flatten() {
        if let Some(p) = g.as_str() {
            root.group(p);
        }
    }
    for d in m.get("datasets").and_then(Value::as_array).into_iter().flatten() {
        if let Some((path, source, shape)) = manifest_dataset(e, steps, d, &mut warnings)? {
            root.dataset(path, source, Some(shape));
        }
    }
    for (p, a) in m.get("attrs").and_then(Value::as_object).into_iter().flatten() {
        let mut list = Vec::new();
        for (k, v) in a.as_object().into_iter().flatten() {
            match attr_value(v) {
                Some(x) => list.push((k.clone(), x)),
                None => {
                    warnings.push(format!("attribute {p}@{k} of {} could not be written back", e.source_name))
                }
            }
        }
        root.set_attrs(p, list);
    }
    Ok((root, warnings))
}

/// One dataset of the manifest as (path, source, shape): its inline values, or its column's
/// checked against the source's shape; `None` (and a warning) when it was not ingested.
fn manifest_dataset<'m>(
    e: &EpisodeRecord,
    steps: &RecordBatch,
    d: &'m Value,
    warnings: &mut Vec<String>,
) -> Result<Option<(&'m str, Source, Vec<u64>)>> {
    let path =
        d.get("path").and_then(Value::as_str).ok_or_else(|| bad(e, "manifest: a dataset without a path"))?;
    let dtype = d.get("dtype").and_then(Value::as_str).unwrap_or("");
    let shape: Vec<u64> = d
        .get("shape")
        .and_then(Value::as_array)
        .map(|s| s.iter().filter_map(Value::as_u64).collect())
        .unwrap_or_default();
    if d.get("not_ingested").is_some() {
        warnings.push(format!("{path} was not ingested: left out of {}", e.source_name));
        return Ok(None);
    }
    if let Some(v) = d.get("values") {
        let v = Values::from_json(dtype, v)
            .ok_or_else(|| bad(e, format!("manifest: {path} has values that are not {dtype}")))?;
        check_len(e, path, v.len() as u64, &shape)?;
        return Ok(Some((path, Source::Values(v), shape)));
    }
    // A video camera's frame count is checked once it is decoded.
    let source = match video_camera(steps, d) {
        Some(k) => Source::Video(k.to_string()),
        None => column_source(e, steps, d, path, &shape)?,
    };
    Ok(Some((path, source, shape)))
}

/// `n` values for the source's `shape`, or an error.
fn check_len(e: &EpisodeRecord, path: &str, n: u64, shape: &[u64]) -> Result<()> {
    let expected: u64 = shape.iter().product();
    if n != expected {
        return Err(bad(e, format!("{path}: {n} values for the source's shape {shape:?}")));
    }
    Ok(())
}

/// The camera a manifest dataset names (`image.<camera>`) when the steps hold it as a video
/// (`--images video`: a `media.<camera>` column instead of the image column).
fn video_camera<'m>(steps: &RecordBatch, d: &'m Value) -> Option<&'m str> {
    let column = d.get("column").and_then(Value::as_str)?;
    let k = column.strip_prefix(IMAGE_PREFIX)?;
    (steps.column_by_name(column).is_none()
        && steps.column_by_name(&format!("{}{k}.path", store::steps::MEDIA_PREFIX)).is_some())
    .then_some(k)
}

/// Where a manifest dataset's values come from in the steps: a camera's frames (JPEG rows
/// padded as the source's were, or raw frames), else a list column (the exact one when kept),
/// transposed back where the source's was.
fn column_source(
    e: &EpisodeRecord,
    steps: &RecordBatch,
    d: &Value,
    path: &str,
    shape: &[u64],
) -> Result<Source> {
    let t = steps.num_rows();
    let column = d.get("column").and_then(Value::as_str).unwrap_or("");
    let exact = d.get("exact_column").and_then(Value::as_str);
    if let Some(k) = column.strip_prefix(IMAGE_PREFIX) {
        let c = need(e, steps, column)?;
        if d.get("encoding").and_then(Value::as_str) == Some("jpeg") {
            let pad =
                d.get("pad_column").and_then(Value::as_str).filter(|p| steps.column_by_name(p).is_some());
            let lens = jpeg_lens(e, k, c)?;
            let width = match shape.get(1) {
                Some(&w) => w as usize,
                None => lens.iter().copied().max().unwrap_or(0),
            };
            let s = vec![lens.len() as u64, width as u64];
            if s != shape {
                return Err(bad(e, format!("{path}: rows of shape {s:?}, the source's were {shape:?}")));
            }
            return Ok(Source::Jpeg { column: column.to_string(), pad: pad.map(str::to_string), width });
        }
        // The frames' shape is checked against the source's as they are decoded.
        return Ok(Source::Png(column.to_string()));
    }
    let name = exact.unwrap_or(column);
    let c = need(e, steps, name)?;
    let dim = list_dim(c).ok_or_else(|| bad(e, format!("{name} is not a list column")))?;
    check_len(e, path, (c.len() * dim) as u64, shape)?;
    if d.get("transposed").and_then(Value::as_bool) == Some(true) {
        let (_, v) = Values::from_list(c).ok_or_else(|| bad(e, format!("{name} is not a list column")))?;
        Ok(Source::Values(v.transposed(t, dim)))
    } else {
        Ok(Source::List(c.clone()))
    }
}

/// The label as the root attribute `success`, in the source's type when it had one.
fn success_attr(root: &mut Node, label: Option<bool>, manifest: Option<&Value>) {
    let Some(ok) = label else { return };
    let ty =
        manifest.and_then(|m| m.pointer("/attrs/~1/success/type")).and_then(Value::as_str).unwrap_or("bool");
    let v = attr_value(&serde_json::json!({"type": ty, "value": if ty == "bool" { Value::Bool(ok) } else { Value::from(ok as u8) }}))
        .or_else(|| attr_value(&serde_json::json!({"type": ty, "value": ok as u8 as f64})))
        .unwrap_or(Attr::number(ok as i8));
    root.attrs.retain(|(k, _)| k != "success");
    root.attrs.push(("success".into(), v));
}

/// `values` as a whole dataset of `shape` with `attrs`.
fn write_whole<T: Element>(
    w: &mut Writer,
    shape: &[u64],
    values: &[T],
    attrs: &[(String, Attr)],
) -> std::io::Result<u64> {
    let mut d = w.stream::<T>(shape)?;
    d.write(values)?;
    for (k, a) in attrs {
        d.attr(k, a.clone());
    }
    d.finish()
}

/// The episode file being written, its final name (for errors), and what its video cameras are
/// decoded with.
struct Out<'a> {
    w: Writer,
    path: &'a Path,
    store: &'a Store,
    decoder: &'a mut VideoDecoder,
}

impl Out<'_> {
    fn err(&self, name: &str, err: std::io::Error) -> ExportError {
        ExportError::write(self.path, format!("{name}: {err}"))
    }

    /// Writes `values` as a whole dataset of `shape` with `attrs`.
    fn put<T: Element>(
        &mut self,
        name: &str,
        shape: &[u64],
        values: &[T],
        attrs: &[(String, Attr)],
    ) -> Result<u64> {
        write_whole(&mut self.w, shape, values, attrs).map_err(|err| self.err(name, err))
    }

    fn put_values(&mut self, name: &str, shape: &[u64], v: &Values, attrs: &[(String, Attr)]) -> Result<u64> {
        match v {
            Values::F32(v) => self.put(name, shape, v, attrs),
            Values::F64(v) => self.put(name, shape, v, attrs),
            Values::I8(v) => self.put(name, shape, v, attrs),
            Values::I16(v) => self.put(name, shape, v, attrs),
            Values::I32(v) => self.put(name, shape, v, attrs),
            Values::I64(v) => self.put(name, shape, v, attrs),
            Values::U8(v) => self.put(name, shape, v, attrs),
            Values::U16(v) => self.put(name, shape, v, attrs),
            Values::U32(v) => self.put(name, shape, v, attrs),
            Values::U64(v) => self.put(name, shape, v, attrs),
        }
    }

    /// A fixed-size-list column's rows, straight from its buffer.
    fn put_list(
        &mut self,
        e: &EpisodeRecord,
        name: &str,
        shape: &[u64],
        col: &ArrayRef,
        attrs: &[(String, Attr)],
    ) -> Result<u64> {
        let l = col.as_fixed_size_list_opt().ok_or_else(|| bad(e, format!("{name} is not a list column")))?;
        let d = l.value_length() as usize;
        let (a, b) = (l.offset() * d, (l.offset() + l.len()) * d);
        let v = l.values();
        macro_rules! put {
            ($t:ty) => {
                self.put(name, shape, &v.as_primitive::<$t>().values()[a..b], attrs)
            };
        }
        match l.value_type() {
            DataType::Float32 => put!(Float32Type),
            DataType::Float64 => put!(Float64Type),
            DataType::Int8 => put!(Int8Type),
            DataType::Int16 => put!(Int16Type),
            DataType::Int32 => put!(Int32Type),
            DataType::Int64 => put!(Int64Type),
            DataType::UInt8 => put!(UInt8Type),
            DataType::UInt16 => put!(UInt16Type),
            DataType::UInt32 => put!(UInt32Type),
            DataType::UInt64 => put!(UInt64Type),
            _ => Err(bad(e, format!("{name} is not a list column"))),
        }
    }

    /// A PNG image column's frames, decoded a window at a time; checked against `want` (the
    /// source's shape) when given, else of their own shape.
    fn put_png(
        &mut self,
        e: &EpisodeRecord,
        name: &str,
        column: &str,
        col: &ArrayRef,
        want: Option<&[u64]>,
        attrs: &[(String, Attr)],
    ) -> Result<u64> {
        let t = col.len();
        // The first frame gives the frame shape (and the window); none: `T x 0 x 0 x 0`.
        let first = png_frames(e, column, &col.slice(0, t.min(1)))?;
        let frame = first.shape;
        let dims: Vec<u64> = std::iter::once(t as u64).chain(frame.iter().map(|&x| x as u64)).collect();
        let dims = if t == 0 { vec![0; 4] } else { dims };
        if let Some(want) = want.filter(|w| *w != dims) {
            return Err(bad(e, format!("{name}: frames of shape {dims:?}, the source's were {want:?}")));
        }
        let window = (PNG_WINDOW_BYTES / frame.iter().product::<usize>().max(1)).max(1);
        let path = self.path;
        let werr = |err: std::io::Error| ExportError::write(path, format!("{name}: {err}"));
        let mut d = self.w.stream::<u8>(&dims).map_err(werr)?;
        d.write(&first.values).map_err(werr)?;
        drop(first);
        let mut r = t.min(1);
        while r < t {
            let n = window.min(t - r);
            let f = png_frames(e, column, &col.slice(r, n))
                .map_err(|err| ExportError::invalid(format!("{err} (rows counted from row {r})")))?;
            if f.shape != frame {
                return Err(bad(e, format!("{column}: frames of different sizes")));
            }
            d.write(&f.values).map_err(werr)?;
            r += n;
        }
        for (k, a) in attrs {
            d.attr(k, a.clone());
        }
        d.finish().map_err(werr)
    }

    /// A JPEG image column as `(T, width)` rows, a window of rows at a time: each frame, then
    /// its kept padding (`pad`) or zeros.
    fn put_jpeg(
        &mut self,
        e: &EpisodeRecord,
        name: &str,
        col: &ArrayRef,
        pad: Option<&ArrayRef>,
        width: usize,
        attrs: &[(String, Attr)],
    ) -> Result<u64> {
        let bin =
            col.as_binary_opt::<i32>().ok_or_else(|| bad(e, format!("{name} is not a binary column")))?;
        let pad = pad.and_then(|p| p.as_binary_opt::<i32>());
        let t = bin.len();
        let path = self.path;
        let werr = |err: std::io::Error| ExportError::write(path, format!("{name}: {err}"));
        let mut d = self.w.stream::<u8>(&[t as u64, width as u64]).map_err(werr)?;
        let window = (JPEG_WINDOW_BYTES / width.max(1)).clamp(1, t.max(1));
        let mut rows = vec![0u8; window * width];
        let mut r = 0;
        while r < t {
            let n = window.min(t - r);
            let buf = &mut rows[..n * width];
            buf.fill(0);
            for k in 0..n {
                let row = &mut buf[k * width..(k + 1) * width];
                let f = bin.value(r + k);
                let tail = pad.filter(|p| p.is_valid(r + k)).map(|p| p.value(r + k)).unwrap_or(&[]);
                if f.len() + tail.len() > width {
                    return Err(bad(
                        e,
                        format!(
                            "{name} row {}: {} bytes do not fit rows of {width}",
                            r + k,
                            f.len() + tail.len()
                        ),
                    ));
                }
                row[..f.len()].copy_from_slice(f);
                row[f.len()..f.len() + tail.len()].copy_from_slice(tail);
            }
            d.write(buf).map_err(werr)?;
            r += n;
        }
        for (k, a) in attrs {
            d.attr(k, a.clone());
        }
        d.finish().map_err(werr)
    }

    /// Writes one planned dataset; `None` when it is left out (a video that is not H.264).
    async fn dataset(
        &mut self,
        e: &EpisodeRecord,
        steps: &RecordBatch,
        name: &str,
        spec: Spec,
    ) -> Result<Option<u64>> {
        let Spec { source, shape, attrs } = spec;
        let at = match source {
            Source::Values(v) => {
                let shape = shape.unwrap_or_else(|| vec![v.len() as u64]);
                self.put_values(name, &shape, &v, &attrs)?
            }
            Source::List(col) => {
                let shape = shape.ok_or_else(|| bad(e, format!("{name}: no shape")))?;
                self.put_list(e, name, &shape, &col, &attrs)?
            }
            Source::Png(column) => {
                let col = need(e, steps, &column)?.clone();
                self.put_png(e, name, &column, &col, shape.as_deref(), &attrs)?
            }
            Source::Jpeg { column, pad, width } => {
                let col = need(e, steps, &column)?.clone();
                let pad = pad.and_then(|p| steps.column_by_name(&p).cloned());
                let key = column.strip_prefix(IMAGE_PREFIX).unwrap_or(&column);
                self.put_jpeg(e, key, &col, pad.as_ref(), width, &attrs)?
            }
            Source::Video(cam) => {
                // This camera's columns alone: its video is decoded now, the others' later.
                let schema = steps.schema();
                let prefix = format!("{}{cam}.", store::steps::MEDIA_PREFIX);
                let cols: Vec<usize> = (0..schema.fields().len())
                    .filter(|&i| schema.field(i).name().starts_with(&prefix))
                    .collect();
                let one = steps.project(&cols).map_err(|err| bad(e, format!("{cam}: {err}")))?;
                let Some(frames) = self.decoder.episode(self.store, e, &one).await?.remove(&cam) else {
                    return Ok(None);
                };
                let (values, dims) = frames.into_dataset();
                let shape = match shape {
                    Some(s) => {
                        check_len(e, name, values.len() as u64, &s)?;
                        s
                    }
                    None => dims,
                };
                self.put(name, &shape, &values, &attrs)?
            }
        };
        Ok(Some(at))
    }
}

/// Writes one episode's file at `path` (a dataset at a time, its groups after their children),
/// with the selection's label and curation attributes; returns what could not be written back.
async fn write_episode(
    store: &Store,
    decoder: &mut VideoDecoder,
    sel: &Selected,
    e: &EpisodeRecord,
    steps: &RecordBatch,
    manifest: Option<&Value>,
    path: &Path,
) -> Result<Vec<String>> {
    let (mut root, warnings) = episode_file(e, steps, manifest)?;
    success_attr(&mut root, e.label.as_bool(), manifest);
    if let Some(score) = sel.scores.get(&e.id) {
        set_attr(&mut root.attrs, "verifier_score", Attr::F64(*score));
    }
    if let Some(c) = crate::failure_cause(sel.label_data.get(&e.id)) {
        set_attr(&mut root.attrs, "failure_cause", Attr::Str(c));
    }
    if let Some(spans) = crate::label_spans(sel.label_data.get(&e.id)) {
        set_attr(&mut root.attrs, "label_spans", Attr::Str(spans));
    }
    let mut ops = Vec::new();
    root.into_ops(String::new(), &mut ops);
    let w = Writer::create(path).map_err(|err| ExportError::write(path, err))?;
    let mut out = Out { w, path, store, decoder };
    // The groups open (the root first), each with its name.
    let mut open: Vec<(Group, String)> = Vec::new();
    for op in ops {
        match op {
            Op::Open(name) => open.push((Group::default(), name)),
            Op::Dataset(name, spec) => {
                let mut full: String = open.iter().skip(1).map(|g| format!("/{}", g.1)).collect();
                full.push('/');
                full.push_str(&name);
                if let Some(at) = out.dataset(e, steps, &full, spec).await? {
                    open.last_mut().expect("an open group").0.link(&name, at);
                }
            }
            Op::Close(name, attrs) => {
                let (mut g, _) = open.pop().expect("an open group");
                for (k, a) in attrs {
                    g.attr(&k, a);
                }
                match open.last_mut() {
                    Some(parent) => {
                        let at = out.w.group(g).map_err(|err| out.err(&name, err))?;
                        parent.0.link(&name, at);
                    }
                    None => {
                        let Out { w, .. } = out;
                        w.finish(g).map_err(|err| ExportError::write(path, err))?;
                        return Ok(warnings);
                    }
                }
            }
        }
    }
    unreachable!("the root group closes last")
}

/// Writes the selected episodes as an ALOHA folder at `out` (a new folder).
pub async fn export(
    store: &Store,
    sel: &Selected,
    out: &Path,
    progress: Progress<'_>,
) -> Result<ExportReport> {
    let staged = Staged::for_selection(sel, out, true)?;
    let formats: HashMap<String, String> =
        sel.sources(store).await?.into_iter().map(|s| (s.sha256, s.format)).collect();
    let is_aloha = |e: &EpisodeRecord| formats.get(&e.source_sha256).is_some_and(|f| f == "aloha");
    // The source's own file names when they are ALOHA's and unique, else episode_<i>.
    let mut names: Vec<String> = sel.episodes.iter().map(|e| e.source_name.clone()).collect();
    let unique = names.iter().collect::<std::collections::HashSet<_>>().len() == names.len();
    let own = unique && sel.episodes.iter().all(|e| is_aloha(e) && ingest_name_ok(&e.source_name));
    if !own {
        names = (0..sel.episodes.len()).map(|i| format!("episode_{i}")).collect();
    }
    let mut report = ExportReport::empty(out, "aloha", sel.version);
    let total = sel.episodes.len();
    let mut decoder = VideoDecoder::default();
    for (i, name) in names.iter().enumerate() {
        // One episode read at a time: a file with raw cameras is 0.5-2 GB.
        let mut reader =
            EpisodeReader::new(store, &sel.episodes[i..=i], &sel.selection.layers, Some(sel.version));
        while let Some((_, e, steps)) = reader.next().await? {
            let manifest = if is_aloha(e) { e.metadata.get("aloha") } else { None };
            let path = staged.tmp.join(format!("{name}.hdf5"));
            for w in write_episode(store, &mut decoder, sel, e, &steps, manifest, &path).await? {
                if !report.warnings.contains(&w) {
                    report.warnings.push(w);
                }
            }
            report.frames += steps.num_rows() as u64;
            count_label(&mut report.labels, e.label);
        }
        if let Some(p) = progress {
            p(i + 1, total);
        }
    }
    report.warnings.extend(decoder.warnings("ALOHA"));
    report.episodes = total;
    report.bytes = disk_size(&staged.tmp);
    staged.commit()?;
    Ok(report)
}

/// `episode_<digits>`.
fn ingest_name_ok(name: &str) -> bool {
    name.strip_prefix("episode_").is_some_and(|d| !d.is_empty() && d.bytes().all(|b| b.is_ascii_digit()))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn attributes_come_back_in_their_type() {
        let j = serde_json::json!({"type": "bool", "value": true});
        assert_eq!(attr_value(&j), Some(Attr::number(1i8)));
        let j = serde_json::json!({"type": "vlen_str", "value": "x"});
        assert_eq!(attr_value(&j), Some(Attr::string("x", StrKind::VarUtf8)));
        let j = serde_json::json!({"type": "u64[]", "value": [1, 2]});
        assert_eq!(attr_value(&j), Some(Attr::numbers(&[1u64, 2])));
        assert_eq!(attr_value(&serde_json::json!({"type": "i8", "value": 300})), None);
    }

    #[test]
    fn transposes_back() {
        // 3 steps of 2 cameras -> 2 rows of 3 steps
        let v = Values::F32(vec![1.0, 10.0, 2.0, 20.0, 3.0, 30.0]);
        let Values::F32(t) = v.transposed(3, 2) else { panic!() };
        assert_eq!(t, vec![1.0, 2.0, 3.0, 10.0, 20.0, 30.0]);
        assert!(ingest_name_ok("episode_3") && !ingest_name_ok("episode_") && !ingest_name_ok("demo_1"));
    }
}
