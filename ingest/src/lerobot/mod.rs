//! LeRobot datasets, codebase v2.1 and v3.0.
//!
//! * `meta/info.json` (`codebase_version` picks the layout, `fps`, `robot_type`, `features`).
//! * tasks: v2.1 `meta/tasks.jsonl`; v3.0 `meta/tasks.parquet`.
//! * episodes: v2.1 `meta/episodes.jsonl`; v3.0 `meta/episodes/chunk-*/file-*.parquet` with
//!   `dataset_from_index` / `dataset_to_index` and `videos/<key>/{chunk,file}_index,from_timestamp`.
//! * data Parquet (fixed-size or variable lists, or scalars) is streamed batch by batch, page by
//!   page: memory is bounded by an episode's low-dim columns and a batch, not by the file; image
//!   frames are read again as the store's writer pulls them (`data.rs`), never an episode's whole.
//! * `video` features become [`MediaColumn`] references (each frame's time inside the shared
//!   mp4) plus one [`MediaFile`] per mp4 (content-addressed, emitted once); `image` features
//!   (PNG bytes in a `struct<bytes, path>` column) become [`ImageColumn`]s.
//! * success = any(`next.success`), label source `lerobot:next.success`; no such column → unknown.
//! * human takeovers: the bool feature `intervention` (LeRobot's DAgger recordings, `lerobot-rollout
//!   --strategy dagger`; another name with `--intervention-key`) becomes the episode's
//!   [`StepFlags::intervention`]; GR00T's `annotation.human.validity` (an index into the tasks,
//!   whose task is `valid` or `invalid`, or a bool) becomes [`StepFlags::validity`].
//!
//! [`MediaColumn`]: crate::model::MediaColumn
//! [`MediaFile`]: crate::model::MediaFile
//! [`ImageColumn`]: crate::model::ImageColumn
//! [`StepFlags::intervention`]: crate::model::StepFlags::intervention
//! [`StepFlags::validity`]: crate::model::StepFlags::validity

pub(crate) mod columns;
mod data;
mod episode;
mod info;
mod media;
mod meta;

use std::collections::{HashMap, HashSet};
use std::path::{Path, PathBuf};

use serde_json::{json, Map, Value};

use crate::error::{IngestError, Result};
use crate::options::ReadOptions;
use crate::sink::{EpisodeSink, SourceMeta};
use data::{plan, stream_data};
use episode::Ctx;
pub(crate) use info::read_bounded;
use info::MAX_INFO_BYTES;
pub use info::{fill_template, parse_info, Feature, Info};
use meta::{load_episodes, load_tasks};

/// GR00T's per-frame validity annotation (an index into the tasks: `valid` / `invalid`).
pub const VALIDITY_KEY: &str = "annotation.human.validity";

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
        let open = || std::fs::File::open(file).map_err(|e| IngestError::io(file, e));
        stream_data(file, &open, &plan, &mut |b| ctx.finish(file, b, sink))?;
    }
    for ep in &episodes {
        if !ctx.seen.contains(&ep.episode_index) {
            return Err(IngestError::invalid(root, format!("episode {} has no data rows", ep.episode_index)));
        }
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
    stream_data(Path::new("fuzz/data.parquet"), &|| Ok(data.clone()), &plan, &mut |b| {
        n += b.rows;
        for (_, frames) in b.images {
            // Every frame pulled (as the store's writer would), each checked to be a PNG.
            for f in frames {
                f.map_err(|e| IngestError::Frames(e.to_string()))?;
            }
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
