//! ALOHA / ACT episodes: one HDF5 file per episode (`episode_<i>.hdf5`), as ALOHA's recorders
//! (`record_episodes.py`, `record_sim_episodes.py`) write them:
//!
//! * `/observations/qpos`, `/qvel`, `/effort` (real robots): `(T, 14)` numbers;
//! * `/observations/images/<camera>`: raw `(T, H, W, C)` uint8, or, recorded with compression,
//!   JPEG bytes zero-padded to a fixed length `(T, padded)` uint8 with `/compress_len`
//!   `(cameras, T)` giving each frame's real length and the root attribute `compress` true;
//! * `/action (T, 14)`; root attributes `sim` (bool), `compress`, and optionally `success`.
//!
//! Lossless: observations are float32 observation columns (with the exact values in an extra
//! column when the source's dtype is another), raw frames PNG image columns, JPEG frames image
//! columns holding the JPEG bytes as they are (never decoded); `compress_len`, non-zero padding
//! and every other per-step dataset are extra columns; small datasets, every group and every
//! attribute (with its type) go into the episode metadata's manifest (`aloha`), from which
//! `ufops export --format aloha` writes the same file back.
//!
//! Hostile files: every dataset's declared size is checked before it is read (as robomimic's),
//! cameras are read a window of frames at a time, and `compress_len` must describe frames that
//! exist (one column per step, each length inside its padded row).
//!
//! One file past 700 lines: one format's reader (the file walk, typed attributes, cameras raw and
//! JPEG, the manifest the export writes back from), whose parts share the file's error context.

use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};
use std::sync::Arc;

use arrow::array::{ArrayRef, BinaryArray, FixedSizeListArray, PrimitiveArray};
use arrow::datatypes::{
    ArrowPrimitiveType, Field, Float32Type, Float64Type, Int16Type, Int32Type, Int64Type, Int8Type,
    UInt16Type, UInt32Type, UInt64Type, UInt8Type,
};
use hdf5_pure::{AttrValue, DType, Dataset, File, Group};
use serde_json::{json, Map, Value};

use crate::error::{IngestError, Result};
use crate::h5rows::{raw_camera, read_rows_windowed};
use crate::h5src::{h5err, Src};
use crate::model::{EpisodeInput, ExtraColumn, Frames, ImageColumn, Label, VectorColumn};
use crate::options::ReadOptions;
use crate::robomimic::{dtype_name, group_attrs, info, is_numeric, open_h5};
use crate::sink::{EpisodeSink, SourceMeta};

/// Label source of a root attribute `success`.
pub const LABEL_SOURCE: &str = "aloha:success";

/// ALOHA's control period (50 Hz, `DT` in its constants): step times are `t * DT`.
pub const DT: f64 = 0.02;

/// Most objects (groups + datasets) one episode file may hold, and how deep groups may nest.
const MAX_OBJECTS: usize = 4096;
const MAX_DEPTH: usize = 16;

/// A non-per-step dataset up to this many elements is kept in the manifest (values as JSON).
const MAX_INLINE_ELEMENTS: u64 = 65_536;

/// An attribute's JSON larger than this is left out (with a note).
const MAX_ATTR_JSON: usize = 64 << 10;

/// `episode_<digits>.hdf5` (or `.h5`): its index.
pub fn episode_index(name: &str) -> Option<u64> {
    let stem = name.strip_suffix(".hdf5").or_else(|| name.strip_suffix(".h5"))?;
    let digits = stem.strip_prefix("episode_")?;
    (!digits.is_empty() && digits.len() <= 18 && digits.bytes().all(|b| b.is_ascii_digit()))
        .then(|| digits.parse().ok())
        .flatten()
}

/// The episode files of an ALOHA folder, sorted by their numeric index.
pub fn episode_files(dir: &Path) -> Result<Vec<(u64, PathBuf)>> {
    let rd = std::fs::read_dir(dir).map_err(|e| IngestError::io(dir, e))?;
    let mut out = Vec::new();
    for entry in rd {
        let entry = entry.map_err(|e| IngestError::io(dir, e))?;
        let name = entry.file_name().to_string_lossy().into_owned();
        if let Some(i) = episode_index(&name) {
            let ft = entry.file_type().map_err(|e| IngestError::io(entry.path(), e))?;
            if ft.is_symlink() {
                return Err(IngestError::invalid(
                    entry.path(),
                    "is a symbolic link: an ALOHA folder's episode files must be plain files inside it",
                ));
            }
            if ft.is_file() {
                out.push((i, entry.path()));
            }
        }
    }
    out.sort_by(|a, b| a.0.cmp(&b.0).then(a.1.cmp(&b.1)));
    Ok(out)
}

/// A folder holding at least one `episode_<i>.hdf5`.
pub fn looks_like_dir(dir: &Path) -> bool {
    episode_files(dir).is_ok_and(|f| !f.is_empty())
}

/// An HDF5 file with `/observations/qpos` and `/action` and no `/data` group (robomimic's).
pub fn looks_like_file(path: &Path) -> bool {
    let Ok(f) = open_h5(path) else { return false };
    let root = f.root();
    let groups = root.groups().unwrap_or_default();
    if groups.iter().any(|g| g == "data") || !groups.iter().any(|g| g == "observations") {
        return false;
    }
    let has_action = root.datasets().is_ok_and(|d| d.iter().any(|n| n == "action"));
    let has_qpos =
        f.group("observations").and_then(|g| g.datasets()).is_ok_and(|d| d.iter().any(|n| n == "qpos"));
    has_action && has_qpos
}

/// Reads an ALOHA folder (every `episode_<i>.hdf5`, by index) or one episode file.
pub fn read_path(path: &Path, opts: &ReadOptions, sink: &mut dyn EpisodeSink) -> Result<Vec<String>> {
    let (files, folder) = if path.is_dir() {
        let files = episode_files(path)?;
        if files.is_empty() {
            return Err(IngestError::invalid(path, "no episode_<i>.hdf5 files: not an ALOHA folder"));
        }
        (files.into_iter().map(|(_, p)| p).collect::<Vec<_>>(), path.to_path_buf())
    } else {
        (vec![path.to_path_buf()], path.parent().map(Path::to_path_buf).unwrap_or_default())
    };
    let names: Vec<String> =
        files.iter().map(|p| p.file_name().unwrap_or_default().to_string_lossy().into_owned()).collect();
    let task = opts
        .task
        .clone()
        .or_else(|| folder.canonicalize().ok()?.file_name().map(|n| n.to_string_lossy().into_owned()));
    sink.source(SourceMeta {
        format: "aloha".into(),
        metadata: json!({"episodes": files.len(), "files": names, "fps": 1.0 / DT}),
    })?;
    let mut left_out: BTreeMap<String, Vec<String>> = BTreeMap::new();
    for (index, file) in files.iter().enumerate() {
        let (ep, extras, notes) = read_episode(file, index as u32, task.clone(), opts)?;
        for n in notes {
            left_out.entry(n).or_default().push(ep.source_name.clone());
        }
        sink.episode_with_extras(ep, extras)?;
    }
    Ok(left_out
        .into_iter()
        .map(|(what, eps)| format!("left out {what} (in {} episode(s), e.g. {})", eps.len(), eps[0]))
        .collect())
}

/// Every group and dataset of the file, by path (`/observations/qpos`), walked with bounds.
struct Tree {
    groups: Vec<(String, Group)>,
    datasets: Vec<(String, Dataset)>,
}

fn walk(file: &File, src: &Src) -> Result<Tree> {
    let mut t = Tree { groups: Vec::new(), datasets: Vec::new() };
    let mut stack = vec![("/".to_string(), file.root(), 0usize)];
    while let Some((path, g, depth)) = stack.pop() {
        let mut names = g.datasets().map_err(h5err(src, format!("cannot list {path}")))?;
        names.sort();
        for n in names {
            let p = child(&path, &n);
            let ds = g.dataset(&n).map_err(h5err(src, format!("cannot open {p}")))?;
            t.datasets.push((p, ds));
        }
        let mut subs = g.groups().map_err(h5err(src, format!("cannot list {path}")))?;
        subs.sort();
        for n in subs.into_iter().rev() {
            let p = child(&path, &n);
            if depth + 1 > MAX_DEPTH {
                return Err(IngestError::invalid(src, format!("{p}: groups nest deeper than {MAX_DEPTH}")));
            }
            let sg = g.group(&n).map_err(h5err(src, format!("cannot open {p}")))?;
            stack.push((p, sg, depth + 1));
        }
        t.groups.push((path, g));
        if t.groups.len() + t.datasets.len() > MAX_OBJECTS {
            return Err(IngestError::invalid(src, format!("more than {MAX_OBJECTS} groups and datasets")));
        }
    }
    t.groups.sort_by(|a, b| a.0.cmp(&b.0));
    t.datasets.sort_by(|a, b| a.0.cmp(&b.0));
    Ok(t)
}

fn child(parent: &str, name: &str) -> String {
    if parent == "/" {
        format!("/{name}")
    } else {
        format!("{parent}/{name}")
    }
}

/// An attribute as `{type, value}` JSON, so export writes the same type back; `None` for a type
/// this reader cannot carry.
fn attr_typed(v: &AttrValue, bool_enum: bool) -> Option<Value> {
    let (ty, val) = match v {
        AttrValue::F32(x) => ("f32", json!(x)),
        AttrValue::F64(x) => ("f64", json!(x)),
        AttrValue::I8(x) if bool_enum => ("bool", json!(*x != 0)),
        AttrValue::U8(x) if bool_enum => ("bool", json!(*x != 0)),
        AttrValue::I8(x) => ("i8", json!(x)),
        AttrValue::I16(x) => ("i16", json!(x)),
        AttrValue::I32(x) => ("i32", json!(x)),
        AttrValue::I64(x) => ("i64", json!(x)),
        AttrValue::U8(x) => ("u8", json!(x)),
        AttrValue::U16(x) => ("u16", json!(x)),
        AttrValue::U32(x) => ("u32", json!(x)),
        AttrValue::U64(x) => ("u64", json!(x)),
        AttrValue::F32Array(x) => ("f32[]", json!(x)),
        AttrValue::F64Array(x) => ("f64[]", json!(x)),
        AttrValue::I8Array(x) if bool_enum => {
            ("bool[]", json!(x.iter().map(|b| *b != 0).collect::<Vec<_>>()))
        }
        AttrValue::I8Array(x) => ("i8[]", json!(x)),
        AttrValue::I16Array(x) => ("i16[]", json!(x)),
        AttrValue::I32Array(x) => ("i32[]", json!(x)),
        AttrValue::I64Array(x) => ("i64[]", json!(x)),
        AttrValue::U8Array(x) => ("u8[]", json!(x)),
        AttrValue::U16Array(x) => ("u16[]", json!(x)),
        AttrValue::U32Array(x) => ("u32[]", json!(x)),
        AttrValue::U64Array(x) => ("u64[]", json!(x)),
        AttrValue::String(s) => ("str", json!(s)),
        AttrValue::AsciiString(s) => ("ascii", json!(s)),
        AttrValue::VarLenString(s) => ("vlen_str", json!(s)),
        AttrValue::VarLenAsciiString(s) => ("vlen_ascii", json!(s)),
        AttrValue::StringArray(s) => ("str[]", json!(s)),
        AttrValue::AsciiStringArray(s) => ("ascii[]", json!(s)),
        AttrValue::VarLenStringArray(s) => ("vlen_str[]", json!(s)),
        AttrValue::VarLenAsciiStringArray(s) => ("vlen_ascii[]", json!(s)),
        _ => return None,
    };
    Some(json!({"type": ty, "value": val}))
}

/// The attributes of a group or dataset as `{name: {type, value}}`; names of those left out go
/// to `notes`.
fn typed_attrs(
    attrs: &HashMap<String, AttrValue>,
    types: &HashMap<String, hdf5_pure::Datatype>,
    where_: &str,
    notes: &mut Vec<String>,
) -> Map<String, Value> {
    let mut out = Map::new();
    let mut names: Vec<&String> = types.keys().chain(attrs.keys()).collect();
    names.sort();
    names.dedup();
    for k in names {
        let bool_enum = matches!(types.get(k), Some(hdf5_pure::Datatype::Enumeration { members, .. }) if members.len() == 2);
        match attrs.get(k).and_then(|v| attr_typed(v, bool_enum)) {
            Some(v) if v.to_string().len() <= MAX_ATTR_JSON => {
                out.insert(k.clone(), v);
            }
            _ => notes.push(format!("attribute {where_}@{k} (a type or size the manifest cannot hold)")),
        }
    }
    out
}

/// A `(T, ...)` numeric dataset as a fixed-size-list column of its own number type, read whole
/// (bounded by `check_declared`, which `info` ran).
fn exact_column(ds: &Dataset, src: &Src, what: &str, dtype: &DType, dim: usize) -> Result<ArrayRef> {
    fn col<T: ArrowPrimitiveType>(dim: usize, v: Vec<T::Native>) -> std::result::Result<ArrayRef, String> {
        let item = Arc::new(Field::new("item", T::DATA_TYPE, false));
        let child = Arc::new(PrimitiveArray::<T>::from_iter_values(v));
        FixedSizeListArray::try_new(item, dim.max(1) as i32, child, None)
            .map(|a| Arc::new(a) as ArrayRef)
            .map_err(|e| e.to_string())
    }
    let e = |m: &str| h5err(src, format!("cannot read {what}{m}"));
    let r = match dtype {
        DType::F32 => col::<Float32Type>(dim, ds.read_f32().map_err(e(""))?),
        DType::F64 => col::<Float64Type>(dim, ds.read_f64().map_err(e(""))?),
        DType::I8 => col::<Int8Type>(dim, ds.read_i8().map_err(e(""))?),
        DType::I16 => col::<Int16Type>(dim, ds.read_i16().map_err(e(""))?),
        DType::I32 => col::<Int32Type>(dim, ds.read_i32().map_err(e(""))?),
        DType::I64 => col::<Int64Type>(dim, ds.read_i64().map_err(e(""))?),
        DType::U8 => col::<UInt8Type>(dim, ds.read_u8().map_err(e(""))?),
        DType::U16 => col::<UInt16Type>(dim, ds.read_u16().map_err(e(""))?),
        DType::U32 => col::<UInt32Type>(dim, ds.read_u32().map_err(e(""))?),
        DType::U64 => col::<UInt64Type>(dim, ds.read_u64().map_err(e(""))?),
        other => return Err(IngestError::invalid(src, format!("{what} has datatype {other}"))),
    };
    r.map_err(|m| IngestError::invalid(src, format!("{what}: {m}")))
}

/// A small dataset's values as JSON numbers (exact for every integer type).
fn inline_values(ds: &Dataset, src: &Src, what: &str, dtype: &DType) -> Result<Value> {
    let e = || h5err(src, format!("cannot read {what}"));
    Ok(match dtype {
        DType::F32 => json!(ds.read_f32().map_err(e())?),
        DType::F64 => json!(ds.read_f64().map_err(e())?),
        DType::I8 => json!(ds.read_i8().map_err(e())?),
        DType::I16 => json!(ds.read_i16().map_err(e())?),
        DType::I32 => json!(ds.read_i32().map_err(e())?),
        DType::I64 => json!(ds.read_i64().map_err(e())?),
        DType::U8 => json!(ds.read_u8().map_err(e())?),
        DType::U16 => json!(ds.read_u16().map_err(e())?),
        DType::U32 => json!(ds.read_u32().map_err(e())?),
        DType::U64 => json!(ds.read_u64().map_err(e())?),
        _ => Value::Null,
    })
}

fn extra(
    name: &str,
    values: ArrayRef,
    dtype: &DType,
    row_shape: &[u64],
    more: &[(&str, String)],
) -> ExtraColumn {
    let mut metadata = HashMap::from([
        ("ufops.dtype".to_string(), dtype_name(dtype)),
        ("ufops.shape".to_string(), json!(row_shape).to_string()),
    ]);
    for (k, v) in more {
        metadata.insert(k.to_string(), v.clone());
    }
    ExtraColumn { name: name.to_string(), values: values.into(), metadata }
}

/// `[H, W, C]` from a JPEG's frame header (SOFn), without decoding it; `None` when the bytes are
/// not a JPEG (no SOI, or no frame header before the scan).
pub fn jpeg_shape(b: &[u8]) -> Option<[usize; 3]> {
    if b.len() < 4 || b[0] != 0xFF || b[1] != 0xD8 {
        return None;
    }
    let mut i = 2;
    while i + 4 <= b.len() {
        if b[i] != 0xFF {
            return None;
        }
        let m = b[i + 1];
        if m == 0xFF {
            i += 1; // fill byte
            continue;
        }
        if m == 0x01 || (0xD0..=0xD7).contains(&m) {
            i += 2;
            continue;
        }
        let len = u16::from_be_bytes([b[i + 2], b[i + 3]]) as usize;
        if len < 2 || i + 2 + len > b.len() {
            return None;
        }
        let is_sof = matches!(m, 0xC0..=0xC3 | 0xC5..=0xC7 | 0xC9..=0xCB | 0xCD..=0xCF);
        if is_sof {
            if len < 8 {
                return None;
            }
            let h = u16::from_be_bytes([b[i + 5], b[i + 6]]) as usize;
            let w = u16::from_be_bytes([b[i + 7], b[i + 8]]) as usize;
            let c = b[i + 9] as usize;
            return (h > 0 && w > 0 && (1..=4).contains(&c)).then_some([h, w, c]);
        }
        if m == 0xDA {
            return None;
        }
        i += 2 + len;
    }
    None
}

/// Whether `row[..len]` ends a JPEG (EOI) and the rest is zero padding.
fn fits(row: &[u8], len: usize) -> bool {
    len >= 4 && len <= row.len() && row[len - 2..len] == [0xFF, 0xD9] && row[len..].iter().all(|&b| b == 0)
}

/// `/compress_len` `(cameras, T)`, checked: whole non-negative numbers, one column per step.
struct CompressLen {
    /// `lens[row][t]`
    lens: Vec<Vec<u64>>,
    column: ExtraColumn,
    dtype: DType,
    shape: Vec<u64>,
}

fn read_compress_len(ds: &Dataset, src: &Src, steps: usize, cameras: usize) -> Result<CompressLen> {
    let what = "/compress_len";
    let inf = info(ds, src, what)?;
    if !is_numeric(&inf.dtype) || inf.shape.len() != 2 {
        return Err(IngestError::invalid(
            src,
            format!("{what} has shape {:?} of {} (expected (cameras, T) numbers)", inf.shape, inf.dtype),
        ));
    }
    let (rows, cols) = (inf.shape[0] as usize, inf.shape[1] as usize);
    if cols != steps {
        return Err(IngestError::invalid(
            src,
            format!(
                "{what} declares {cols} frames per camera but /observations/qpos has {steps} steps: refused (frames that are not there)"
            ),
        ));
    }
    if rows != cameras {
        return Err(IngestError::invalid(
            src,
            format!("{what} has {rows} rows for {cameras} compressed camera(s) in /observations/images"),
        ));
    }
    let v = ds.read_f64().map_err(h5err(src, format!("cannot read {what}")))?;
    if v.len() != rows * cols {
        return Err(IngestError::invalid(
            src,
            format!("{what}: read {} values for shape {:?}", v.len(), inf.shape),
        ));
    }
    let mut lens = vec![Vec::with_capacity(cols); rows];
    for (k, x) in v.iter().enumerate() {
        if !(x.is_finite() && *x >= 0.0 && x.fract() == 0.0 && *x < 9.0e15) {
            return Err(IngestError::invalid(
                src,
                format!("{what}[{}, {}] = {x} is not a frame length", k / cols, k % cols),
            ));
        }
        lens[k / cols].push(*x as u64);
    }
    // One row per step: row t holds every camera's length at t (the dataset transposed).
    let dim = rows;
    let column = {
        let full = exact_column(ds, src, what, &inf.dtype, cols * rows)?;
        transpose_rows(&full, rows, cols).map_err(|m| IngestError::invalid(src, format!("{what}: {m}")))?
    };
    let col =
        extra("compress_len", column, &inf.dtype, &[dim as u64], &[("ufops.transposed", "true".to_string())]);
    Ok(CompressLen { lens, column: col, dtype: inf.dtype, shape: inf.shape })
}

/// A one-row list column of `rows x cols` values, transposed into `cols` rows of `rows` values.
fn transpose_rows(full: &ArrayRef, rows: usize, cols: usize) -> std::result::Result<ArrayRef, String> {
    use arrow::array::{Array, AsArray};
    let l = full.as_fixed_size_list();
    let values = l.values();
    let idx: Vec<u32> = (0..cols).flat_map(|t| (0..rows).map(move |r| (r * cols + t) as u32)).collect();
    let taken = arrow::compute::take(values.as_ref(), &arrow::array::UInt32Array::from(idx), None)
        .map_err(|e| e.to_string())?;
    let item = Arc::new(Field::new("item", taken.data_type().clone(), false));
    FixedSizeListArray::try_new(item, rows as i32, taken, None)
        .map(|a| Arc::new(a) as ArrayRef)
        .map_err(|e| e.to_string())
}

/// A compressed camera: each row's first `lens[t]` bytes (a JPEG, kept as it is), and the rest
/// of the row where it is not all zeros (an extra column, null where it is).
fn jpeg_camera(
    ds: &Dataset,
    src: &Src,
    what: &str,
    name: &str,
    padded: u64,
    lens: &[u64],
    row: usize,
) -> Result<(ImageColumn, Option<ExtraColumn>)> {
    let t = lens.len();
    let mut frames = Vec::with_capacity(t);
    let mut tails: Vec<Option<Vec<u8>>> = Vec::with_capacity(t);
    let mut shape = None;
    read_rows_windowed(ds, src, what, t as u64, padded, |start, _, bytes| {
        for (k, r) in bytes.chunks_exact(padded as usize).enumerate() {
            let ti = start as usize + k;
            let len = lens[ti] as usize;
            let jpeg = &r[..len];
            let s = jpeg_shape(jpeg).ok_or_else(|| {
                IngestError::invalid(
                    src,
                    format!(
                        "{what}: frame {ti} (compress_len[{row}, {ti}] = {len} bytes) is not a JPEG image"
                    ),
                )
            })?;
            shape.get_or_insert(s);
            frames.push(jpeg.to_vec());
            let tail = &r[len..];
            tails.push(tail.iter().any(|&b| b != 0).then(|| tail.to_vec()));
        }
        Ok(())
    })?;
    let shape = shape.unwrap_or([0, 0, 0]);
    let pad = tails.iter().any(Option::is_some).then(|| {
        let arr: ArrayRef = Arc::new(BinaryArray::from_iter(tails.iter().map(|t| t.as_deref())));
        ExtraColumn {
            name: format!("pad/{name}"),
            values: arr.into(),
            metadata: HashMap::from([(
                "ufops.null_means".to_string(),
                format!("the rest of the row of {what} after the JPEG is zeros"),
            )]),
        }
    });
    Ok((ImageColumn { name: name.to_string(), shape, frames: Frames::Encoded(frames) }, pad))
}

/// Assigns each compressed camera (sorted by name) its `/compress_len` row: the row whose first
/// length ends the camera's first JPEG with only zeros after it, preferring the camera's own
/// position (ALOHA's loaders pair them in listing order; its recorders write rows in their
/// configuration's order, which may differ).
fn assign_rows(first_rows: &[Vec<u8>], cl: &CompressLen) -> Vec<usize> {
    let k = first_rows.len();
    let mut taken = vec![false; k];
    let mut out = vec![usize::MAX; k];
    for (cam, row) in first_rows.iter().enumerate() {
        let order = std::iter::once(cam).chain((0..k).filter(|&r| r != cam));
        for r in order {
            if !taken[r] && fits(row, cl.lens[r][0] as usize) {
                taken[r] = true;
                out[cam] = r;
                break;
            }
        }
    }
    for cam in 0..k {
        if out[cam] == usize::MAX {
            let r = if !taken[cam] { cam } else { (0..k).find(|&r| !taken[r]).unwrap_or(cam) };
            taken[r] = true;
            out[cam] = r;
        }
    }
    out
}

fn parent_of(path: &str) -> &str {
    match path.rfind('/') {
        Some(0) => "/",
        Some(i) => &path[..i],
        None => "/",
    }
}

fn base_name(path: &str) -> &str {
    path.rsplit('/').next().unwrap_or(path)
}

/// The attributes of every group and dataset, typed (by path), and the root's as read.
fn all_attributes(
    tree: &Tree,
    src: &Src,
    notes: &mut Vec<String>,
) -> Result<(Map<String, Value>, HashMap<String, AttrValue>)> {
    let mut attrs = Map::new();
    let mut root_attrs = HashMap::new();
    for (p, g) in &tree.groups {
        let a = group_attrs(g, src, p, &[])?;
        let types = g.attr_datatypes().map_err(h5err(src, format!("cannot read the attributes of {p}")))?;
        let typed = typed_attrs(&a, &types, p, notes);
        if p == "/" {
            root_attrs = a;
        }
        if !typed.is_empty() {
            attrs.insert(p.clone(), Value::Object(typed));
        }
    }
    for (p, ds) in &tree.datasets {
        let a = ds.attrs().map_err(h5err(src, format!("cannot read the attributes of {p}")))?;
        let types = ds.attr_datatypes().map_err(h5err(src, format!("cannot read the attributes of {p}")))?;
        let typed = typed_attrs(&a, &types, p, notes);
        if !typed.is_empty() {
            attrs.insert(p.clone(), Value::Object(typed));
        }
    }
    Ok((attrs, root_attrs))
}

/// A file's JPEG-compressed cameras: `(T, padded)` uint8 datasets under /observations/images
/// when the file says it is compressed (`@compress`, or a `/compress_len`), with each frame's
/// real length and each camera's row of `/compress_len`.
struct CompressedCameras {
    /// The file is compressed.
    on: bool,
    /// Each camera's dataset path and padded row width.
    cams: Vec<(String, u64)>,
    cl: Option<CompressLen>,
    /// Each camera's row of `/compress_len` (in `cams` order).
    rows: Vec<usize>,
}

fn compressed_cameras(
    tree: &Tree,
    src: &Src,
    compress_attr: bool,
    steps: usize,
) -> Result<CompressedCameras> {
    let find = |p: &str| tree.datasets.iter().find(|(q, _)| q == p).map(|(_, d)| d);
    let compress_ds = find("/compress_len");
    let compressed = compress_attr || compress_ds.is_some();
    let mut jpeg_cams: Vec<(String, u64)> = Vec::new();
    if compressed {
        for (p, ds) in &tree.datasets {
            if parent_of(p) == "/observations/images" {
                let inf = info(ds, src, p)?;
                if inf.dtype == DType::U8 && inf.shape.len() == 2 {
                    jpeg_cams.push((p.clone(), inf.shape[1]));
                }
            }
        }
    }
    let cl = match (compress_ds, jpeg_cams.is_empty()) {
        (Some(ds), _) => Some(read_compress_len(ds, src, steps, jpeg_cams.len())?),
        (None, false) => {
            return Err(IngestError::invalid(
                src,
                "@compress is true but there is no /compress_len: the frames' lengths are unknown",
            ));
        }
        (None, true) => None,
    };
    let rows = match &cl {
        Some(cl) if !jpeg_cams.is_empty() => {
            let mut first = Vec::new();
            for (p, _) in &jpeg_cams {
                let ds = find(p).expect("listed");
                first.push(ds.read_u8_rows(0, 1).map_err(h5err(src, format!("cannot read {p}")))?);
            }
            assign_rows(&first, cl)
        }
        _ => Vec::new(),
    };

    Ok(CompressedCameras { on: compressed, cams: jpeg_cams, cl, rows })
}

/// What an episode file's datasets become: observation and action columns, cameras, exact
/// columns (`extra.*`), and the manifest entry of each dataset (how to write it back).
#[derive(Default)]
struct Columns {
    observations: Vec<VectorColumn>,
    images: Vec<ImageColumn>,
    extras: Vec<ExtraColumn>,
    manifest: Vec<Value>,
    action: Option<VectorColumn>,
}

impl Columns {
    /// The dataset `p` of an episode of `steps` steps.
    fn add(
        &mut self,
        p: &str,
        ds: &Dataset,
        src: &Src,
        steps: usize,
        jpeg: &CompressedCameras,
        notes: &mut Vec<String>,
    ) -> Result<()> {
        let inf = info(ds, src, p)?;
        let mut entry = json!({"path": p, "dtype": dtype_name(&inf.dtype), "shape": inf.shape});
        let per_step = inf.shape.first().copied() == Some(steps as u64);
        let parent = parent_of(p);
        let key = base_name(p);
        if p == "/compress_len" {
            let cl = jpeg.cl.as_ref().expect("read above");
            entry["column"] = json!("extra.compress_len");
            entry["transposed"] = json!(true);
            debug_assert_eq!(cl.shape, inf.shape);
            let _ = &cl.dtype;
        } else if let Some(k) = jpeg.cams.iter().position(|(q, _)| q == p) {
            if !per_step {
                return Err(IngestError::invalid(
                src,
                format!("{p} has {} frames but /observations/qpos has {steps} steps: refused (frames that are not there)", inf.shape[0]),
            ));
            }
            let cl = jpeg.cl.as_ref().expect("compressed cameras have compress_len");
            let r = jpeg.rows[k];
            let padded = jpeg.cams[k].1;
            if let Some((t, len)) = cl.lens[r].iter().enumerate().find(|(_, &l)| l > padded) {
                return Err(IngestError::invalid(
                    src,
                    format!(
                        "/compress_len[{r}, {t}] = {len} points past the {padded}-byte rows of {p}: refused"
                    ),
                ));
            }
            let (im, pad) = jpeg_camera(ds, src, p, key, padded, &cl.lens[r], r)?;
            entry["column"] = json!(format!("image.{key}"));
            entry["encoding"] = json!("jpeg");
            entry["compress_len_row"] = json!(r);
            if let Some(pad) = pad {
                entry["pad_column"] = json!(format!("extra.{}", pad.name));
                self.extras.push(pad);
            }
            self.images.push(im);
        } else if parent == "/observations/images" && inf.dtype == DType::U8 && inf.shape.len() == 4 {
            if !per_step {
                return Err(IngestError::invalid(
                src,
                format!("{p} has {} frames but /observations/qpos has {steps} steps: refused (frames that are not there)", inf.shape[0]),
            ));
            }
            self.images.push(raw_camera(ds, src, p, key, &inf.shape)?);
            entry["column"] = json!(format!("image.{key}"));
            entry["encoding"] = json!("png");
        } else if (p == "/action" || parent == "/observations")
            && is_numeric(&inf.dtype)
            && !inf.shape.is_empty()
        {
            if !per_step {
                return Err(IngestError::invalid(
                    src,
                    format!("{p} has {} rows but /observations/qpos has {steps} steps", inf.shape[0]),
                ));
            }
            let dim = inf.shape[1..].iter().product::<u64>() as usize;
            let values = ds.read_f32().map_err(h5err(src, format!("cannot read {p}")))?;
            if values.len() != steps * dim || dim == 0 {
                return Err(IngestError::invalid(
                    src,
                    format!("{p}: read {} values for shape {:?}", values.len(), inf.shape),
                ));
            }
            if p == "/action" {
                self.action = Some(VectorColumn { name: "action".into(), dim, values });
                entry["column"] = json!("action");
            } else {
                self.observations.push(VectorColumn { name: key.to_string(), dim, values });
                entry["column"] = json!(format!("obs.{key}"));
            }
            if inf.dtype != DType::F32 {
                let xname = p.trim_start_matches('/').to_string();
                let col = exact_column(ds, src, p, &inf.dtype, dim)?;
                self.extras.push(extra(&xname, col, &inf.dtype, &inf.shape[1..], &[]));
                entry["exact_column"] = json!(format!("extra.{xname}"));
            }
        } else if is_numeric(&inf.dtype) && per_step && !inf.shape.is_empty() {
            let dim = inf.shape[1..].iter().product::<u64>() as usize;
            let xname = p.trim_start_matches('/').to_string();
            let col = exact_column(ds, src, p, &inf.dtype, dim)?;
            self.extras.push(extra(&xname, col, &inf.dtype, &inf.shape[1..], &[]));
            entry["column"] = json!(format!("extra.{xname}"));
        } else if is_numeric(&inf.dtype) && inf.shape.iter().product::<u64>() <= MAX_INLINE_ELEMENTS {
            entry["values"] = inline_values(ds, src, p, &inf.dtype)?;
        } else {
            notes.push(format!("{p} ({} {:?}: not one row per step)", inf.dtype, inf.shape));
            entry["not_ingested"] = json!(true);
        }
        self.manifest.push(entry);
        Ok(())
    }
}

/// Reads one episode file.
pub fn read_episode(
    path: &Path,
    index: u32,
    task: Option<String>,
    opts: &ReadOptions,
) -> Result<(EpisodeInput, Vec<ExtraColumn>, Vec<String>)> {
    let file = open_h5(path)?;
    let src = &Src::new(path, file.file_size());
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default()
        .trim_end_matches(".hdf5")
        .trim_end_matches(".h5")
        .to_string();
    let tree = walk(&file, src)?;
    let mut notes = Vec::new();
    let (attrs, root_attrs) = all_attributes(&tree, src, &mut notes)?;
    let flag = |k: &str| root_attrs.get(k).and_then(|v| v.as_i64().or_else(|| v.as_f64().map(|f| f as i64)));

    let find = |p: &str| tree.datasets.iter().find(|(q, _)| q == p).map(|(_, d)| d);
    let qpos = find("/observations/qpos").ok_or_else(|| {
        IngestError::invalid(src, "no /observations/qpos dataset: not an ALOHA episode file")
    })?;
    let steps = info(qpos, src, "/observations/qpos")?.shape.first().copied().unwrap_or(0) as usize;
    if steps == 0 {
        return Err(IngestError::invalid(src, "/observations/qpos has no rows"));
    }
    let action_ds = find("/action")
        .ok_or_else(|| IngestError::invalid(src, "no /action dataset: not an ALOHA episode file"))?;

    let compressed = flag("compress").is_some_and(|c| c != 0);
    let jpeg = compressed_cameras(&tree, src, compressed, steps)?;
    let mut cols = Columns::default();
    for (p, ds) in &tree.datasets {
        cols.add(p, ds, src, steps, &jpeg, &mut notes)?;
    }
    let Columns { mut observations, images, mut extras, manifest, action } = cols;
    // The per-step human-takeover flag: the dataset `/intervention` (what ufops' export of a
    // takeover-flagged episode writes) or the one `--intervention-key` names. It is kept as it
    // is above too (an exact column), so the round trip stays exact.
    let (ikey, named) = opts.intervention_key();
    let ipath = format!("/{}", ikey.trim_start_matches('/'));
    let intervention = match find(&ipath) {
        Some(ds) => Some(crate::robomimic::read_flags(ds, src, &ipath, steps)?),
        None if named => {
            return Err(IngestError::Usage(format!(
                "--intervention-key {ikey:?}: {} has no dataset {ipath}",
                path.display()
            )))
        }
        None => None,
    };
    let action = action.expect("/action was found above");
    if action.values.len() != steps * action.dim {
        return Err(IngestError::invalid(src, "/action does not have one row per step"));
    }
    let _ = action_ds;
    if let Some(cl) = jpeg.cl {
        extras.push(cl.column);
    }
    // ALOHA's order: qpos, qvel, effort, then the others by name.
    let rank = |n: &str| ["qpos", "qvel", "effort"].iter().position(|k| *k == n).unwrap_or(3);
    observations.sort_by(|a, b| (rank(&a.name), &a.name).cmp(&(rank(&b.name), &b.name)));

    let reward = vec![0.0f32; steps];
    let mut done = vec![false; steps];
    done[steps - 1] = true;
    let (label, label_source) =
        opts.user_label(&name, index, &reward).unwrap_or_else(|| match flag("success") {
            Some(s) => (Label::from_bool(Some(s != 0)), LABEL_SOURCE.to_string()),
            None => (Label::Unknown, String::new()),
        });
    let groups: Vec<&String> = tree.groups.iter().map(|(p, _)| p).collect();
    let metadata = json!({
        "file": path.file_name().map(|n| n.to_string_lossy().into_owned()),
        "sim": flag("sim").map(|s| s != 0),
        "compress": jpeg.on,
        "aloha": {"groups": groups, "datasets": manifest, "attrs": attrs},
    });
    let ep = EpisodeInput {
        source_name: name,
        source_index: index,
        task,
        label,
        label_source,
        tags: Vec::new(),
        metadata,
        timestamps: (0..steps).map(|t| t as f64 * DT).collect(),
        observations,
        action,
        reward,
        done,
        action_chunk: None,
        images,
        media: Vec::new(),
        flags: crate::model::StepFlags { intervention, validity: None },
    };
    Ok((ep, extras, notes))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn episode_names() {
        assert_eq!(episode_index("episode_0.hdf5"), Some(0));
        assert_eq!(episode_index("episode_12.h5"), Some(12));
        assert_eq!(episode_index("episode_.hdf5"), None);
        assert_eq!(episode_index("episode_1x.hdf5"), None);
        assert_eq!(episode_index("demo_1.hdf5"), None);
    }

    #[test]
    fn jpeg_headers() {
        // SOI, APP0 (len 4), SOF0 (len 11: 8-bit, 480 x 640, 3 components), SOS
        let mut b = vec![0xFF, 0xD8, 0xFF, 0xE0, 0, 4, 0, 0, 0xFF, 0xC0, 0, 11, 8, 1, 0xE0, 2, 0x80, 3];
        b.extend([0, 0, 0, 0, 0, 0, 0, 0, 0xFF, 0xDA, 0, 2]);
        assert_eq!(jpeg_shape(&b), Some([480, 640, 3]));
        assert_eq!(jpeg_shape(&b[..10]), None);
        assert_eq!(jpeg_shape(b"\x89PNG\r\n\x1a\n"), None);
        assert!(fits(&[0xFF, 0xD8, 0xFF, 0xD9, 0, 0], 4));
        assert!(!fits(&[0xFF, 0xD8, 0xFF, 0xD9, 0, 1], 4));
        assert!(!fits(&[0xFF, 0xD8, 0xFF, 0xD9], 5));
    }
}
