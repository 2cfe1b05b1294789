//! robomimic HDF5 files in robomimic's documented layout, written front to back by
//! `h5stream` (pure Rust, no system library; h5py and `hdf5-pure` read its files):
//!
//! * `data@total` (frames), `data@env_args` (JSON: the source's when it was robomimic), and
//!   `data@ufops` (JSON: where the export came from);
//! * `data/demo_<i>/obs/<key>` (float32 `T x dim`, float64 where the source's were; PNG image
//!   columns and H.264 video cameras decoded to uint8 `T x H x W x C`, see `cameras.rs`),
//!   `next_obs/<key>` (the next step's obs, or the source's own value where it
//!   differed: ingest keeps those rows), `actions` (float32), `rewards` (float64), `dones`
//!   (uint8), `states` and every other per-step array ingest kept (`extra.*` columns, in their
//!   source dtype and shape);
//! * `demo@num_samples`, the demo's attributes from the source (large ones such as `model_file`
//!   from their extra column), and `demo@success` (1 / 0; absent when unlabeled), the version's
//!   frozen label, which ingest reads back;
//! * `mask/train`, `mask/valid` from a split's parts, and `mask/<filter>` for the source's own
//!   filter keys (ingested as tags).
//!
//! Each demo's datasets are written as soon as its steps are read, under a temporary name
//! renamed at the end: memory holds one demo (its steps, decoded frames and `next_obs`) and
//! the names of the demos, never the file.

use std::collections::{BTreeMap, HashMap};
use std::path::Path;

use arrow::array::{Array, ArrayRef, AsArray, RecordBatch};
use arrow::datatypes::{DataType, Float32Type, Float64Type, UInt8Type};
use serde_json::Value;
use store::steps::{EXTRA_PREFIX, IMAGE_PREFIX, OBS_PREFIX};
use store::{EpisodeRecord, Store};

use crate::cameras::{png_frames, Frames, VideoDecoder};
use crate::{
    count_label, disk_size, EpisodeReader, ExportError, ExportReport, Progress, Result, Selected, Staged,
};
use h5stream::{Attr, Element, Group, Writer};

fn bad(e: &EpisodeRecord, what: impl std::fmt::Display) -> ExportError {
    ExportError::invalid(format!("episode {}: {what}", e.id))
}

/// The file being written and its final name (for errors).
struct Out<'a> {
    w: Writer,
    path: &'a Path,
}

impl Out<'_> {
    /// Writes a dataset and links it into `g` as `name`.
    fn dataset<T: Element>(&mut self, g: &mut Group, name: &str, shape: &[u64], values: &[T]) -> Result<()> {
        let at = self
            .w
            .dataset(shape, values)
            .map_err(|err| ExportError::write(self.path, format!("{name}: {err}")))?;
        g.link(name, at);
        Ok(())
    }
    /// Writes a finished group and links it into `parent` as `name`.
    fn group(&mut self, parent: &mut Group, name: &str, g: Group) -> Result<()> {
        let at = self.w.group(g).map_err(|err| ExportError::write(self.path, format!("{name}: {err}")))?;
        parent.link(name, at);
        Ok(())
    }
}

/// A float32 fixed-size-list column as (dim, values of its rows).
fn f32_rows(col: &ArrayRef) -> Option<(usize, Vec<f32>)> {
    let l = col.as_fixed_size_list_opt()?;
    let d = l.value_length() as usize;
    let v = l.values().as_primitive_opt::<Float32Type>()?;
    Some((d, v.values()[l.offset() * d..(l.offset() + l.len()) * d].to_vec()))
}

/// One observation of every step, as written to `obs/<key>` (and shifted into `next_obs`).
enum Obs {
    F32 { dim: usize, values: Vec<f32> },
    U8 { shape: [usize; 3], values: Vec<u8> },
}

impl From<Frames> for Obs {
    fn from(f: Frames) -> Obs {
        Obs::U8 { shape: f.shape, values: f.values }
    }
}

impl Obs {
    fn row_len(&self) -> usize {
        match self {
            Obs::F32 { dim, .. } => *dim,
            Obs::U8 { shape, .. } => shape.iter().product(),
        }
    }
}

fn dims(t: usize, row: &[usize]) -> Vec<u64> {
    std::iter::once(t as u64).chain(row.iter().map(|&d| d as u64)).collect()
}

/// `next_obs/<key>`: row t is obs row t+1, or the source's own row where ingest kept one
/// (`extra.next_obs/<key>` not null), the last row its own kept value or a repeat of the last obs.
fn next_obs(obs: &Obs, kept: Option<&ArrayRef>, t: usize) -> Obs {
    let row = obs.row_len();
    let pick = |k: usize| -> Option<usize> { kept.filter(|c| c.is_valid(k)).map(|_| k) };
    match obs {
        Obs::F32 { dim, values } => {
            let src = kept.and_then(f32_rows).map(|(_, v)| v);
            let mut out = Vec::with_capacity(values.len());
            for k in 0..t {
                match (pick(k), &src) {
                    (Some(k), Some(s)) if s.len() == t * row => {
                        out.extend_from_slice(&s[k * row..(k + 1) * row])
                    }
                    _ => {
                        let n = (k + 1).min(t - 1);
                        out.extend_from_slice(&values[n * row..(n + 1) * row]);
                    }
                }
            }
            Obs::F32 { dim: *dim, values: out }
        }
        Obs::U8 { shape, values } => {
            let src: Option<Vec<u8>> = kept.and_then(|c| {
                let l = c.as_fixed_size_list_opt()?;
                let v = l.values().as_primitive_opt::<UInt8Type>()?;
                Some(v.values()[l.offset() * row..(l.offset() + l.len()) * row].to_vec())
            });
            let mut out = Vec::with_capacity(values.len());
            for k in 0..t {
                match (pick(k), &src) {
                    (Some(k), Some(s)) if s.len() == t * row => {
                        out.extend_from_slice(&s[k * row..(k + 1) * row])
                    }
                    _ => {
                        let n = (k + 1).min(t - 1);
                        out.extend_from_slice(&values[n * row..(n + 1) * row]);
                    }
                }
            }
            Obs::U8 { shape: *shape, values: out }
        }
    }
}

/// Writes an observation; float ones as float64 when the source's were (`wide`: the widened
/// float32 values), else float32.
fn put_obs(out: &mut Out, g: &mut Group, key: &str, o: &Obs, t: usize, wide: bool) -> Result<()> {
    match o {
        Obs::F32 { dim, values } if wide => {
            let v: Vec<f64> = values.iter().map(|&x| x as f64).collect();
            out.dataset(g, key, &dims(t, &[*dim]), &v)
        }
        Obs::F32 { dim, values } => out.dataset(g, key, &dims(t, &[*dim]), values),
        Obs::U8 { shape, values } => out.dataset(g, key, &dims(t, shape), values),
    }
}

/// An extra column back as a dataset in its source dtype and shape.
fn put_extra(
    out: &mut Out,
    g: &mut Group,
    e: &EpisodeRecord,
    name: &str,
    col: &ArrayRef,
    meta: &HashMap<String, String>,
    t: usize,
) -> Result<()> {
    let l = col
        .as_fixed_size_list_opt()
        .ok_or_else(|| bad(e, format!("extra column {name} is not a list column")))?;
    let d = l.value_length() as usize;
    let shape: Vec<usize> =
        meta.get("ufops.shape").and_then(|s| serde_json::from_str(s).ok()).unwrap_or_else(|| vec![d]);
    let shape = dims(t, &shape);
    let (a, b) = (l.offset() * d, (l.offset() + l.len()) * d);
    let dtype = meta.get("ufops.dtype").map(String::as_str).unwrap_or("");
    match l.value_type() {
        DataType::UInt8 => {
            out.dataset(g, name, &shape, &l.values().as_primitive::<UInt8Type>().values()[a..b])
        }
        DataType::Float32 => {
            out.dataset(g, name, &shape, &l.values().as_primitive::<Float32Type>().values()[a..b])
        }
        DataType::Float64 => {
            let v = &l.values().as_primitive::<Float64Type>().values()[a..b];
            // Integers were kept as float64 (exact): write them back as integers.
            if dtype.starts_with("int") || dtype.starts_with("uint") || dtype == "bool" {
                let ints: Vec<i64> = v.iter().map(|&x| x as i64).collect();
                out.dataset(g, name, &shape, &ints)
            } else {
                out.dataset(g, name, &shape, v)
            }
        }
        other => Err(bad(e, format!("extra column {name} holds {other}, not numbers"))),
    }
}

/// Writes one demo's datasets from an episode's steps and its video cameras' frames, and
/// returns its group (attributes set) for the caller to complete and write.
fn demo_group(
    out: &mut Out,
    e: &EpisodeRecord,
    steps: &RecordBatch,
    videos: BTreeMap<String, Frames>,
    robomimic_source: bool,
) -> Result<Group> {
    let mut g = Group::default();
    put_observations(out, &mut g, e, steps, videos)?;
    put_step_datasets(out, &mut g, e, steps)?;
    let mut attrs = put_extras(out, &mut g, e, steps)?;
    // The source's demo attributes (robomimic sources keep them as episode metadata).
    if robomimic_source {
        add_source_attrs(&mut attrs, e);
    }
    if let Some(s) = e.label.as_bool() {
        attrs.insert("success".into(), Attr::I64(s as i64));
    }
    for (k, v) in attrs {
        g.attr(&k, v);
    }
    Ok(g)
}

/// `obs/<key>` and `next_obs/<key>` of every observation, image column (decoded from PNG) and
/// video camera (`videos`: decoded by the caller), float64 where the source's were.
fn put_observations(
    out: &mut Out,
    g: &mut Group,
    e: &EpisodeRecord,
    steps: &RecordBatch,
    videos: BTreeMap<String, Frames>,
) -> Result<()> {
    let t = steps.num_rows();
    let schema = steps.schema();
    let mut obs: Vec<(String, Obs)> = Vec::new();
    for f in schema.fields() {
        let col = steps.column_by_name(f.name()).expect("field of the batch");
        if let Some(k) = f.name().strip_prefix(OBS_PREFIX) {
            let (dim, values) =
                f32_rows(col).ok_or_else(|| bad(e, format!("{} is not a float32 list column", f.name())))?;
            obs.push((k.to_string(), Obs::F32 { dim, values }));
        } else if let Some(k) = f.name().strip_prefix(IMAGE_PREFIX) {
            obs.push((k.to_string(), png_frames(e, f.name(), col)?.into()));
        }
    }
    obs.extend(videos.into_iter().map(|(k, f)| (k, f.into())));
    let mut obs_g = Group::default();
    let mut next_g = Group::default();
    for (key, o) in obs {
        // The source's dtype is recorded on the kept `next_obs` column (robomimic writes obs and
        // next_obs alike).
        let kept_name = format!("{EXTRA_PREFIX}next_obs/{key}");
        let kept = steps.column_by_name(&kept_name);
        let wide = schema
            .field_with_name(&kept_name)
            .is_ok_and(|f| f.metadata().get("ufops.dtype").is_some_and(|d| d == "float64"));
        put_obs(out, &mut obs_g, &key, &o, t, wide)?;
        put_obs(out, &mut next_g, &key, &next_obs(&o, kept, t), t, wide)?;
    }
    out.group(g, "obs", obs_g)?;
    out.group(g, "next_obs", next_g)
}

/// `actions` (float32), `rewards` (float64), `dones` (uint8) and, when the steps have them,
/// human takeovers as `intervention` (uint8).
fn put_step_datasets(out: &mut Out, g: &mut Group, e: &EpisodeRecord, steps: &RecordBatch) -> Result<()> {
    let t = steps.num_rows();
    let actions = steps
        .column_by_name("action")
        .ok_or_else(|| bad(e, "has no actions: robomimic needs one per step"))?;
    let (adim, avals) = f32_rows(actions).ok_or_else(|| bad(e, "action is not a float32 list column"))?;
    out.dataset(g, "actions", &dims(t, &[adim]), &avals)?;
    let reward = steps
        .column_by_name("reward")
        .and_then(|c| c.as_primitive_opt::<Float32Type>().cloned())
        .ok_or_else(|| bad(e, "no reward column"))?;
    let rewards: Vec<f64> = reward.values().iter().map(|&r| r as f64).collect();
    out.dataset(g, "rewards", &[t as u64], &rewards)?;
    let done = steps
        .column_by_name("done")
        .and_then(|c| c.as_boolean_opt().cloned())
        .ok_or_else(|| bad(e, "no done column"))?;
    let dones: Vec<u8> = done.iter().map(|d| (d == Some(true)) as u8).collect();
    out.dataset(g, "dones", &[t as u64], &dones)?;
    // Human takeovers, where ingest reads them back (a demo's `intervention` dataset).
    if let Some(c) = steps.column_by_name(store::steps::INTERVENTION_COLUMN) {
        let flags = c.as_boolean_opt().ok_or_else(|| bad(e, "intervention is not a boolean column"))?;
        let flags: Vec<u8> = flags.iter().map(|d| (d == Some(true)) as u8).collect();
        out.dataset(g, store::steps::INTERVENTION_COLUMN, &[t as u64], &flags)?;
    }
    Ok(())
}

/// The extra columns ingest kept: per-step arrays back as datasets, `attr/*` as the demo's
/// attributes (returned with `num_samples`, for the caller to complete and set).
fn put_extras(
    out: &mut Out,
    g: &mut Group,
    e: &EpisodeRecord,
    steps: &RecordBatch,
) -> Result<BTreeMap<String, Attr>> {
    let t = steps.num_rows();
    let schema = steps.schema();
    let mut attrs: BTreeMap<String, Attr> = BTreeMap::new();
    attrs.insert("num_samples".into(), Attr::I64(t as i64));
    for f in schema.fields() {
        let Some(name) = f.name().strip_prefix(EXTRA_PREFIX) else { continue };
        let col = steps.column_by_name(f.name()).expect("field of the batch");
        if name.starts_with("next_obs/") {
            continue;
        }
        if let Some(attr) = name.strip_prefix("attr/") {
            if let Some(s) = col.as_string_opt::<i32>().filter(|s| s.is_valid(0)) {
                attrs.insert(attr.to_string(), Attr::Str(s.value(0).to_string()));
            }
            continue;
        }
        put_extra(out, g, e, name, col, f.metadata(), t)?;
    }
    Ok(attrs)
}

/// The episode metadata of a robomimic source (its demo's attributes: strings and numbers) that
/// `attrs` does not hold yet.
fn add_source_attrs(attrs: &mut BTreeMap<String, Attr>, e: &EpisodeRecord) {
    if let Some(md) = e.metadata.as_object() {
        for (k, v) in md {
            if k == "not_ingested" || k == "success" || attrs.contains_key(k) {
                continue;
            }
            match v {
                Value::String(s) => {
                    attrs.insert(k.clone(), Attr::Str(s.clone()));
                }
                Value::Number(n) if n.is_i64() => {
                    attrs.insert(k.clone(), Attr::I64(n.as_i64().unwrap_or_default()));
                }
                Value::Number(n) => {
                    attrs.insert(k.clone(), Attr::F64(n.as_f64().unwrap_or_default()));
                }
                _ => {}
            }
        }
    }
}

/// Each selected source's format and metadata, by its sha256.
async fn source_formats(store: &Store, sel: &Selected) -> Result<HashMap<String, (String, Value)>> {
    Ok(sel.sources(store).await?.into_iter().map(|s| (s.sha256, (s.format, s.metadata))).collect())
}

/// `data@env_args`: a robomimic source's own, else one naming the episodes' task.
fn env_args(sources: &HashMap<String, (String, Value)>, sel: &Selected) -> Value {
    sources
        .values()
        .find_map(|(f, m)| (f == "robomimic").then(|| m.get("env_args").cloned()).flatten())
        .filter(|v| !v.is_null())
        .unwrap_or_else(|| {
            let task = sel.episodes.iter().find_map(|e| e.task.clone()).unwrap_or_default();
            serde_json::json!({"env_name": task, "env_kwargs": {}})
        })
}

/// The sources' own filter keys (they came in as tags: they go back as masks).
fn mask_filters(sources: &HashMap<String, (String, Value)>) -> std::collections::HashSet<String> {
    sources
        .values()
        .filter_map(|(_, m)| m.get("mask_filters").and_then(|v| v.as_array()).cloned())
        .flatten()
        .filter_map(|v| v.as_str().map(str::to_string))
        .collect()
}

/// The demo attributes of the selection's curation: verifier score, failure cause, label spans.
fn set_curation_attrs(g: &mut Group, sel: &Selected, e: &EpisodeRecord) {
    if let Some(score) = sel.scores.get(&e.id) {
        g.attr("verifier_score", Attr::F64(*score));
    }
    if let Some(c) = crate::failure_cause(sel.label_data.get(&e.id)) {
        g.attr("failure_cause", Attr::Str(c));
    }
    if let Some(spans) = crate::label_spans(sel.label_data.get(&e.id)) {
        g.attr("label_spans", Attr::Str(spans));
    }
}

/// The `mask` group: per mask, the names of its demos (none when there are no masks).
fn add_masks(out: &mut Out, root: &mut Group, masks: &BTreeMap<String, Vec<String>>) -> Result<()> {
    if !masks.is_empty() {
        let mut mask = Group::default();
        for (k, demos) in masks {
            let names: Vec<&str> = demos.iter().map(String::as_str).collect();
            let at = out
                .w
                .ascii_strings(&names)
                .map_err(|err| ExportError::write(out.path, format!("mask/{k}: {err}")))?;
            mask.link(k, at);
        }
        out.group(root, "mask", mask)?;
    }
    Ok(())
}

/// Writes the selected episodes as one robomimic HDF5 file at `out` (a new file).
pub async fn export(
    store: &Store,
    sel: &Selected,
    out: &Path,
    progress: Progress<'_>,
) -> Result<ExportReport> {
    let staged = Staged::for_selection(sel, out, false)?;
    let sources = source_formats(store, sel).await?;
    let env_args = env_args(&sources, sel);
    // The source's filter keys came in as tags: they go back as masks.
    let filters = mask_filters(&sources);
    let mut masks: BTreeMap<String, Vec<String>> = BTreeMap::new();
    let mut report = ExportReport::empty(out, "robomimic", sel.version);
    let w = Writer::create(&staged.tmp).map_err(|err| ExportError::io(&staged.tmp, err))?;
    let mut file = Out { w, path: out };
    let mut data = Group::default();
    let total = sel.episodes.len();
    let mut decoder = VideoDecoder::default();
    let mut reader = EpisodeReader::new(store, &sel.episodes, &sel.selection.layers, Some(sel.version));
    while let Some((i, e, steps)) = reader.next().await? {
        let name = format!("demo_{i}");
        let robomimic_source = sources.get(&e.source_sha256).is_some_and(|(f, _)| f == "robomimic");
        let videos = decoder.episode(store, e, &steps).await?;
        let mut g = demo_group(&mut file, e, &steps, videos, robomimic_source)?;
        set_curation_attrs(&mut g, sel, e);
        file.group(&mut data, &name, g)?;
        for tag in &e.tags {
            if filters.contains(tag) {
                masks.entry(tag.clone()).or_default().push(name.clone());
            }
        }
        if let Some(part) = sel.parts.get(&e.id) {
            let key = if part == "val" { "valid" } else { part.as_str() };
            masks.entry(key.to_string()).or_default().push(name.clone());
        }
        report.frames += steps.num_rows() as u64;
        count_label(&mut report.labels, e.label);
        if let Some(p) = progress {
            p(i + 1, total);
        }
    }
    data.attr("total", Attr::I64(report.frames as i64));
    data.attr("env_args", Attr::Str(env_args.to_string()));
    data.attr("ufops", Attr::Str(sel.provenance("robomimic").to_string()));
    let mut root = Group::default();
    file.group(&mut root, "data", data)?;
    add_masks(&mut file, &mut root, &masks)?;
    report.warnings.extend(decoder.warnings("robomimic"));
    file.w.finish(root).map_err(|err| ExportError::write(out, err))?;
    report.episodes = total;
    report.bytes = disk_size(&staged.tmp);
    staged.commit()?;
    Ok(report)
}
