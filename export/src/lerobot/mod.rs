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

mod data;
mod meta;
mod stats;
mod videos;

use std::collections::BTreeMap;
use std::path::Path;

use arrow::datatypes::{DataType, Schema};
use serde_json::{json, Value};
use store::steps::{
    EXTRA_PREFIX, IMAGE_PREFIX, INTERVENTION_COLUMN, MEDIA_PREFIX, OBS_PREFIX, VALIDITY_COLUMN,
};
use store::{Label, Store};

use crate::{
    count_label, disk_size, for_each_episode_with_layers, ExportReport, Progress, Result, Selected, Staged,
};
use data::Writer;

pub const CODEBASE_VERSION: &str = "v3.0";
const CHUNKS_SIZE: usize = 1000;
const DATA_FILE_BYTES: usize = 100 << 20;
const DATA_PATH: &str = "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet";
const VIDEO_PATH: &str = "videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4";
/// The task of episodes that have none (LeRobot needs one per frame).
pub const NO_TASK: &str = "(no task)";
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

/// Fills LeRobot's path templates.
fn fill(template: &str, video_key: Option<&str>, chunk: usize, file: usize) -> String {
    template
        .replace("{video_key}", video_key.unwrap_or(""))
        .replace("{chunk_index:03d}", &format!("{chunk:03}"))
        .replace("{file_index:03d}", &format!("{file:03}"))
}

/// The feature entry of `key` in the sources' LeRobot metadata (dtype, shape, names, info).
fn source_feature(sources: &[Value], key: &str) -> Option<Value> {
    sources.iter().find_map(|m| m.get("features").and_then(|f| f.get(key)).cloned())
}

/// The metadata of the selected episodes' sources, each once, in order of first use.
async fn source_metadata(store: &Store, sel: &Selected) -> Result<Vec<Value>> {
    Ok(sel.sources(store).await?.into_iter().map(|s| s.metadata).collect())
}

/// Task text → `task_index`, numbered in order of first use ([`NO_TASK`] for episodes without).
fn task_indexes(sel: &Selected) -> BTreeMap<String, i64> {
    let mut tasks: BTreeMap<String, i64> = BTreeMap::new();
    for e in &sel.episodes {
        let t = e.task.clone().unwrap_or_else(|| NO_TASK.to_string());
        let next = tasks.len() as i64;
        tasks.entry(t).or_insert(next);
    }
    tasks
}

/// The task indexes `(valid, invalid)` (added to `tasks` when missing) when a source is GR00T-style
/// (its validity feature is not a bool), else `None`: validity is then written as a bool.
fn validity_task_indexes(sources: &[Value], tasks: &mut BTreeMap<String, i64>) -> Option<(i64, i64)> {
    match source_feature(sources, VALIDITY_KEY) {
        Some(f) if f.get("dtype") != Some(&json!("bool")) => {
            let mut at = VALID_TASKS.iter().map(|t| {
                let next = tasks.len() as i64;
                *tasks.entry(t.to_string()).or_insert(next)
            });
            Some((at.next().expect("two tasks"), at.next().expect("two tasks")))
        }
        _ => None,
    }
}

/// Writes the selected episodes as a LeRobot v3.0 dataset at `out` (a new folder).
pub async fn export(
    store: &Store,
    sel: &Selected,
    out: &Path,
    progress: Progress<'_>,
) -> Result<ExportReport> {
    let staged = Staged::for_selection(sel, out, true)?;
    // The sources' metadata: fps, robot type, feature names of LeRobot sources.
    let sources = source_metadata(store, sel).await?;
    let fps = sources
        .iter()
        .find_map(|m| m.get("fps").or_else(|| m.get("control_freq")).and_then(|v| v.as_f64()))
        .filter(|f| f.is_finite() && *f > 0.0);
    let robot_type =
        sources.iter().find_map(|m| m.get("robot_type").and_then(|v| v.as_str()).map(str::to_string));
    let mut tasks = task_indexes(sel);
    // A GR00T-style source's validity indexes its tasks `valid` / `invalid`: keep them so.
    let validity_tasks = validity_task_indexes(&sources, &mut tasks);
    let labeled = sel.episodes.iter().any(|e| e.label != Label::Unknown);
    let mut report = ExportReport::empty(out, "lerobot", sel.version);

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
                writer = Some(Writer::for_first_episode(
                    root.clone(),
                    e,
                    &steps,
                    fps,
                    labeled,
                    &tasks,
                    validity_tasks,
                )?);
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
    videos::copy_videos(store, &w.videos, &root, &mut report).await?;
    meta::write_meta(&root, &w, &sources, robot_type, sel)?;
    if !w.layout.extras.is_empty() {
        report.warnings.push(format!(
            "left out {} column(s) LeRobot has no feature for: {}",
            w.layout.extras.len(),
            w.layout.extras.join(", ")
        ));
    }
    report.episodes = w.episodes.len();
    report.frames = w.frames as u64;
    report.bytes = disk_size(&root);
    staged.commit()?;
    Ok(report)
}
