//! ALOHA / ACT episodes: a folder with one `episode_<i>.hdf5` per episode, written with
//! `hdf5-pure` as ALOHA's recorders lay them out (`/observations/{qpos,qvel,effort}`,
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
//! Boolean attributes are written as int8 0/1 (`hdf5-pure` writes no enumerated attribute type; h5py reads them as
//! `np.int8`, which compares equal to the bool).
//!
//! Other episodes get ALOHA's layout from the store's columns: `obs.<key>` as
//! `/observations/<key>` (float32), `action`, PNG image columns and video cameras as raw
//! cameras, JPEG ones as compressed cameras with `compress_len`, `sim` false.
//!
//! Episodes are read and written one at a time (an ALOHA episode with raw cameras is 0.5-2 GB),
//! each file under the staged folder, renamed into place at the end; an episode's video cameras
//! are fetched and decoded one after the other into that episode's file.

use std::collections::{BTreeMap, HashMap};
use std::path::Path;

use arrow::array::{Array, ArrayRef, AsArray, RecordBatch};
use arrow::datatypes::{
    DataType, Float32Type, Float64Type, Int16Type, Int32Type, Int64Type, Int8Type, UInt16Type, UInt32Type,
    UInt64Type, UInt8Type,
};
use hdf5_pure::{AttrValue, DatasetBuilder, FileBuilder, GroupBuilder};
use serde_json::Value;
use store::steps::{IMAGE_PREFIX, OBS_PREFIX};
use store::{EpisodeRecord, Store};

use crate::cameras::{png_frames, Frames, VideoDecoder};
use crate::{
    count_label, disk_size, EpisodeReader, ExportError, ExportReport, Progress, Result, Selected, Staged,
};

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

    fn put(&self, d: &mut DatasetBuilder, shape: &[u64]) {
        match self {
            Values::F32(v) => d.with_f32_data(v),
            Values::F64(v) => d.with_f64_data(v),
            Values::I8(v) => d.with_i8_data(v),
            Values::I16(v) => d.with_i16_data(v),
            Values::I32(v) => d.with_i32_data(v),
            Values::I64(v) => d.with_i64_data(v),
            Values::U8(v) => d.with_u8_data(v),
            Values::U16(v) => d.with_u16_data(v),
            Values::U32(v) => d.with_u32_data(v),
            Values::U64(v) => d.with_u64_data(v),
        }
        .with_shape(shape);
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

/// A dataset to write: name, values, shape, attributes.
type DatasetSpec = (String, Values, Vec<u64>, Vec<(String, AttrValue)>);

/// The file being assembled: groups by path, each with its datasets and attributes.
#[derive(Default)]
struct Node {
    datasets: Vec<DatasetSpec>,
    groups: BTreeMap<String, Node>,
    attrs: Vec<(String, AttrValue)>,
}

impl Node {
    fn group(&mut self, path: &str) -> &mut Node {
        let mut n = self;
        for part in path.split('/').filter(|p| !p.is_empty()) {
            n = n.groups.entry(part.to_string()).or_default();
        }
        n
    }

    fn dataset(&mut self, path: &str, v: Values, shape: Vec<u64>) {
        let (parent, name) = path.rsplit_once('/').unwrap_or(("", path));
        self.group(parent).datasets.push((name.to_string(), v, shape, Vec::new()));
    }

    /// Attributes of the object at `path` (a group, or a dataset already added).
    fn set_attrs(&mut self, path: &str, attrs: Vec<(String, AttrValue)>) {
        let (parent, name) = path.rsplit_once('/').unwrap_or(("", path));
        let g = self.group(parent);
        if let Some(d) = g.datasets.iter_mut().find(|d| d.0 == name) {
            d.3.extend(attrs);
        } else {
            self.group(path).attrs.extend(attrs);
        }
    }

    fn emit_group(self, g: &mut GroupBuilder) {
        for (name, v, shape, attrs) in self.datasets {
            let d = g.create_dataset(&name);
            v.put(d, &shape);
            for (k, a) in attrs {
                d.set_attr(&k, a);
            }
        }
        for (name, child) in self.groups {
            let mut cg = g.create_group(&name);
            child.emit_group(&mut cg);
            g.add_group(cg.finish());
        }
        for (k, a) in self.attrs {
            g.set_attr(&k, a);
        }
    }

    fn emit_file(self, fb: &mut FileBuilder) {
        for (name, v, shape, attrs) in self.datasets {
            let d = fb.create_dataset(&name);
            v.put(d, &shape);
            for (k, a) in attrs {
                d.set_attr(&k, a);
            }
        }
        for (name, child) in self.groups {
            let mut g = fb.create_group(&name);
            child.emit_group(&mut g);
            fb.add_group(g.finish());
        }
        for (k, a) in self.attrs {
            fb.set_attr(&k, a);
        }
    }
}

/// A manifest attribute (`{type, value}`) back as the value ingest read.
fn attr_value(t: &Value) -> Option<AttrValue> {
    let ty = t.get("type")?.as_str()?;
    let v = t.get("value")?;
    let strs =
        || -> Option<Vec<String>> { v.as_array()?.iter().map(|s| s.as_str().map(str::to_string)).collect() };
    macro_rules! arr {
        ($var:ident, $f:expr) => {
            AttrValue::$var(v.as_array()?.iter().map($f).collect::<Option<Vec<_>>>()?)
        };
    }
    Some(match ty {
        "bool" => AttrValue::I8(v.as_bool()? as i8),
        "bool[]" => arr!(I8Array, |x: &Value| x.as_bool().map(|b| b as i8)),
        "f32" => AttrValue::F32(v.as_f64()? as f32),
        "f64" => AttrValue::F64(v.as_f64()?),
        "i8" => AttrValue::I8(i8::try_from(v.as_i64()?).ok()?),
        "i16" => AttrValue::I16(i16::try_from(v.as_i64()?).ok()?),
        "i32" => AttrValue::I32(i32::try_from(v.as_i64()?).ok()?),
        "i64" => AttrValue::I64(v.as_i64()?),
        "u8" => AttrValue::U8(u8::try_from(v.as_u64()?).ok()?),
        "u16" => AttrValue::U16(u16::try_from(v.as_u64()?).ok()?),
        "u32" => AttrValue::U32(u32::try_from(v.as_u64()?).ok()?),
        "u64" => AttrValue::U64(v.as_u64()?),
        "f32[]" => arr!(F32Array, |x: &Value| x.as_f64().map(|f| f as f32)),
        "f64[]" => arr!(F64Array, Value::as_f64),
        "i8[]" => arr!(I8Array, |x: &Value| x.as_i64().and_then(|i| i8::try_from(i).ok())),
        "i16[]" => arr!(I16Array, |x: &Value| x.as_i64().and_then(|i| i16::try_from(i).ok())),
        "i32[]" => arr!(I32Array, |x: &Value| x.as_i64().and_then(|i| i32::try_from(i).ok())),
        "i64[]" => arr!(I64Array, Value::as_i64),
        "u8[]" => arr!(U8Array, |x: &Value| x.as_u64().and_then(|i| u8::try_from(i).ok())),
        "u16[]" => arr!(U16Array, |x: &Value| x.as_u64().and_then(|i| u16::try_from(i).ok())),
        "u32[]" => arr!(U32Array, |x: &Value| x.as_u64().and_then(|i| u32::try_from(i).ok())),
        "u64[]" => arr!(U64Array, Value::as_u64),
        "str" => AttrValue::String(v.as_str()?.to_string()),
        "ascii" => AttrValue::AsciiString(v.as_str()?.to_string()),
        "vlen_str" => AttrValue::VarLenString(v.as_str()?.to_string()),
        "vlen_ascii" => AttrValue::VarLenAsciiString(v.as_str()?.to_string()),
        "str[]" => AttrValue::StringArray(strs()?),
        "ascii[]" => AttrValue::AsciiStringArray(strs()?),
        "vlen_str[]" => AttrValue::VarLenStringArray(strs()?),
        "vlen_ascii[]" => AttrValue::VarLenAsciiStringArray(strs()?),
        _ => return None,
    })
}

/// A JPEG image column as `(T, padded)` rows: each frame, then its kept padding or zeros.
fn padded_rows(
    e: &EpisodeRecord,
    name: &str,
    col: &ArrayRef,
    pad: Option<&ArrayRef>,
    padded: Option<usize>,
) -> Result<(Vec<u8>, Vec<u64>, Vec<usize>)> {
    let bin = col.as_binary_opt::<i32>().ok_or_else(|| bad(e, format!("{name} is not a binary column")))?;
    let pad = pad.and_then(|p| p.as_binary_opt::<i32>());
    let lens: Vec<usize> = (0..bin.len()).map(|r| bin.value(r).len()).collect();
    let width = padded.unwrap_or_else(|| lens.iter().copied().max().unwrap_or(0));
    let mut out = vec![0u8; width * bin.len()];
    for r in 0..bin.len() {
        let f = bin.value(r);
        let tail = pad.filter(|p| p.is_valid(r)).map(|p| p.value(r)).unwrap_or(&[]);
        if f.len() + tail.len() > width {
            return Err(bad(
                e,
                format!("{name} row {r}: {} bytes do not fit rows of {width}", f.len() + tail.len()),
            ));
        }
        let row = &mut out[r * width..(r + 1) * width];
        row[..f.len()].copy_from_slice(f);
        row[f.len()..f.len() + tail.len()].copy_from_slice(tail);
    }
    Ok((out, vec![bin.len() as u64, width as u64], lens))
}

/// Builds one episode file from its steps, its video cameras' frames (decoded by the caller)
/// and the manifest of an ALOHA source.
fn episode_file(
    e: &EpisodeRecord,
    steps: &RecordBatch,
    videos: BTreeMap<String, Frames>,
    manifest: Option<&Value>,
) -> Result<(Node, Vec<String>)> {
    match manifest {
        Some(m) => episode_from_manifest(e, steps, videos, m),
        None => Ok((episode_from_columns(e, steps, videos)?, Vec::new())),
    }
}

/// The steps' column `name`, or an error saying the episode has none.
fn need<'a>(e: &EpisodeRecord, steps: &'a RecordBatch, name: &str) -> Result<&'a ArrayRef> {
    steps.column_by_name(name).ok_or_else(|| bad(e, format!("has no column {name}")))
}

/// ALOHA's layout from the store's columns (an episode whose source was not ALOHA).
fn episode_from_columns(
    e: &EpisodeRecord,
    steps: &RecordBatch,
    videos: BTreeMap<String, Frames>,
) -> Result<Node> {
    let t = steps.num_rows();
    let mut root = Node::default();
    let schema = steps.schema();
    let mut jpeg: Vec<(String, ArrayRef)> = Vec::new();
    for f in schema.fields() {
        let c = need(e, steps, f.name())?;
        if let Some(k) = f.name().strip_prefix(OBS_PREFIX) {
            let (d, v) =
                Values::from_list(c).ok_or_else(|| bad(e, format!("{} is not a list column", f.name())))?;
            root.dataset(&format!("/observations/{k}"), v, vec![t as u64, d as u64]);
        } else if f.name() == store::steps::INTERVENTION_COLUMN {
            // Human takeovers, where ingest reads them back (`/intervention`, 0/1).
            let flags = c.as_boolean_opt().ok_or_else(|| bad(e, "intervention is not a boolean column"))?;
            let flags: Vec<u8> = flags.iter().map(|b| (b == Some(true)) as u8).collect();
            root.dataset("/intervention", Values::U8(flags), vec![t as u64]);
        } else if let Some(k) = f.name().strip_prefix(IMAGE_PREFIX) {
            if f.metadata().get("ufops.encoding").is_some_and(|x| x == "jpeg") {
                jpeg.push((k.to_string(), c.clone()));
            } else {
                let (v, dims) = png_frames(e, f.name(), c)?.into_dataset();
                root.dataset(&format!("/observations/images/{k}"), Values::U8(v), dims);
            }
        }
    }
    for (k, frames) in videos {
        let (v, dims) = frames.into_dataset();
        root.dataset(&format!("/observations/images/{k}"), Values::U8(v), dims);
    }
    let (d, v) = Values::from_list(need(e, steps, "action")?)
        .ok_or_else(|| bad(e, "has no actions: ALOHA needs one per step"))?;
    root.dataset("/action", v, vec![t as u64, d as u64]);
    root.group("/observations/images");
    let mut attrs = vec![("sim".to_string(), AttrValue::I8(0))];
    if !jpeg.is_empty() {
        jpeg.sort_by(|a, b| a.0.cmp(&b.0));
        let mut lens = Vec::new();
        for (k, c) in &jpeg {
            let (rows, shape, l) = padded_rows(e, k, c, None, None)?;
            root.dataset(&format!("/observations/images/{k}"), Values::U8(rows), shape);
            lens.extend(l.into_iter().map(|x| x as f32));
        }
        root.dataset("/compress_len", Values::F32(lens), vec![jpeg.len() as u64, t as u64]);
        attrs.push(("compress".to_string(), AttrValue::I8(1)));
    }
    root.set_attrs("/", attrs);
    Ok(root)
}

/// The ALOHA source's file as its manifest describes it: groups, datasets and attributes, with
/// warnings for what could not be written back.
fn episode_from_manifest(
    e: &EpisodeRecord,
    steps: &RecordBatch,
    mut videos: BTreeMap<String, Frames>,
    m: &Value,
) -> Result<(Node, Vec<String>)> {
    let mut root = Node::default();
    let mut warnings = Vec::new();
    for g in m.get("groups").and_then(Value::as_array).into_iter().flatten() {
        if let Some(p) = g.as_str() {
            root.group(p);
        }
    }
    for d in m.get("datasets").and_then(Value::as_array).into_iter().flatten() {
        if let Some((path, values, shape)) = manifest_dataset(e, steps, &mut videos, d, &mut warnings)? {
            root.dataset(path, values, shape);
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

/// One dataset of the manifest as (path, values, shape): its inline values, or its column's
/// checked against the source's shape; `None` (and a warning) when it was not ingested, `None`
/// for a camera stored as a video that was not decoded (the caller warns about those).
fn manifest_dataset<'m>(
    e: &EpisodeRecord,
    steps: &RecordBatch,
    videos: &mut BTreeMap<String, Frames>,
    d: &'m Value,
    warnings: &mut Vec<String>,
) -> Result<Option<(&'m str, Values, Vec<u64>)>> {
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
        return Ok(Some((path, v, shape)));
    }
    let values = match video_camera(steps, d) {
        Some(k) => match videos.remove(k) {
            Some(frames) => Values::U8(frames.values),
            None => return Ok(None),
        },
        None => column_values(e, steps, d, path, &shape)?,
    };
    let expected: u64 = shape.iter().product();
    if values.len() as u64 != expected {
        return Err(bad(e, format!("{path}: {} values for the source's shape {shape:?}", values.len())));
    }
    Ok(Some((path, values, shape)))
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

/// A manifest dataset's values from the steps: a camera's frames (JPEG rows padded as the
/// source's were, or raw frames), else a list column (the exact one when kept), transposed
/// back where the source's was.
fn column_values(
    e: &EpisodeRecord,
    steps: &RecordBatch,
    d: &Value,
    path: &str,
    shape: &[u64],
) -> Result<Values> {
    let t = steps.num_rows();
    let col = |name: &str| steps.column_by_name(name);
    let column = d.get("column").and_then(Value::as_str).unwrap_or("");
    let exact = d.get("exact_column").and_then(Value::as_str);
    let values = if let Some(k) = column.strip_prefix(IMAGE_PREFIX) {
        let c = need(e, steps, column)?;
        if d.get("encoding").and_then(Value::as_str) == Some("jpeg") {
            let pad = d.get("pad_column").and_then(Value::as_str).and_then(col);
            let width = shape.get(1).map(|&w| w as usize);
            let (rows, s, _) = padded_rows(e, k, c, pad, width)?;
            if s != shape {
                return Err(bad(e, format!("{path}: rows of shape {s:?}, the source's were {shape:?}")));
            }
            Values::U8(rows)
        } else {
            let (v, s) = png_frames(e, column, c)?.into_dataset();
            if s != shape {
                return Err(bad(e, format!("{path}: frames of shape {s:?}, the source's were {shape:?}")));
            }
            Values::U8(v)
        }
    } else {
        let name = exact.unwrap_or(column);
        let c = need(e, steps, name)?;
        let (dim, v) = Values::from_list(c).ok_or_else(|| bad(e, format!("{name} is not a list column")))?;
        if d.get("transposed").and_then(Value::as_bool) == Some(true) {
            v.transposed(t, dim)
        } else {
            v
        }
    };
    Ok(values)
}

/// The label as the root attribute `success`, in the source's type when it had one.
fn success_attr(root: &mut Node, label: Option<bool>, manifest: Option<&Value>) {
    let Some(ok) = label else { return };
    let ty =
        manifest.and_then(|m| m.pointer("/attrs/~1/success/type")).and_then(Value::as_str).unwrap_or("bool");
    let v = attr_value(&serde_json::json!({"type": ty, "value": if ty == "bool" { Value::Bool(ok) } else { Value::from(ok as u8) }}))
        .or_else(|| attr_value(&serde_json::json!({"type": ty, "value": ok as u8 as f64})))
        .unwrap_or(AttrValue::I8(ok as i8));
    root.attrs.retain(|(k, _)| k != "success");
    root.attrs.push(("success".into(), v));
}

/// Writes one episode's file at `path`, with the selection's label and curation attributes;
/// returns what could not be written back.
fn write_episode(
    sel: &Selected,
    e: &EpisodeRecord,
    steps: &RecordBatch,
    videos: BTreeMap<String, Frames>,
    manifest: Option<&Value>,
    path: &Path,
) -> Result<Vec<String>> {
    let (mut root, warnings) = episode_file(e, steps, videos, manifest)?;
    success_attr(&mut root, e.label.as_bool(), manifest);
    if let Some(score) = sel.scores.get(&e.id) {
        root.attrs.push(("verifier_score".into(), AttrValue::F64(*score)));
    }
    if let Some(c) = crate::failure_cause(sel.label_data.get(&e.id)) {
        root.attrs.push(("failure_cause".into(), AttrValue::VarLenString(c)));
    }
    if let Some(spans) = crate::label_spans(sel.label_data.get(&e.id)) {
        root.attrs.push(("label_spans".into(), AttrValue::VarLenString(spans)));
    }
    let mut fb = FileBuilder::new();
    root.emit_file(&mut fb);
    fb.write(path).map_err(|err| ExportError::write(path, err))?;
    Ok(warnings)
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
            let videos = decoder.episode(store, e, &steps).await?;
            let manifest = if is_aloha(e) { e.metadata.get("aloha") } else { None };
            let path = staged.tmp.join(format!("{name}.hdf5"));
            for w in write_episode(sel, e, &steps, videos, manifest, &path)? {
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
        assert_eq!(attr_value(&j), Some(AttrValue::I8(1)));
        let j = serde_json::json!({"type": "vlen_str", "value": "x"});
        assert_eq!(attr_value(&j), Some(AttrValue::VarLenString("x".into())));
        let j = serde_json::json!({"type": "u64[]", "value": [1, 2]});
        assert_eq!(attr_value(&j), Some(AttrValue::U64Array(vec![1, 2])));
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
