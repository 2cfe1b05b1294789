//! What `lerobot-eval` writes: a folder with `eval_info.json` (each episode's success, sum and
//! max reward; the seeds too, up to lerobot 0.3) and `videos/` (the first rendered episodes of
//! each task, one H.264 MP4 each, written by imageio from `env.render()`), ingested as the
//! evaluation of one checkpoint.
//!
//! * Layouts: both that `lerobot-eval` has written (`layout.rs`): lerobot ≥ 0.4's `per_task`
//!   (tasks named `<task_group>_<task_id>`, no seeds) and lerobot ≤ 0.3's `per_episode` (one
//!   task, seeds recorded).
//! * Seeds: episode i of a task ran with `--seed` + i (every task restarts at `--seed`). The 0.3
//!   layout records them; for 0.4 the user gives `--start-seed` (lerobot-eval's `--seed`, 1000 by
//!   default); without it the episodes have no seed and no pair key (a note says so), and
//!   `ufops compare` pairs them in arrival order.
//! * Pairing: `pair_key` is `seed:<seed>` (0.3) or `<task_group>_<task_id>/seed:<seed>` (0.4): the
//!   initial condition, so two evaluations run with the same `--seed` pair episode for episode,
//!   task by task. `seed` itself is in the metadata too (`--pair-key seed` across layouts).
//! * Steps: an episode with a video has one step per frame (lerobot-eval cuts the video at the
//!   done step: frame t is what the camera showed before action t), timed from the MP4
//!   (`mp4.rs`), each a reference into the stored MP4 (media column `render`). An episode past
//!   the rendered ones has no video: it is kept by its outcome alone, as one step at t = 0 with no
//!   frame (metadata `outcome_only`). No actions, observations or per-step rewards are recorded by
//!   lerobot-eval: actions are empty (dimension 0), rewards 0, the last step done.
//! * Labels: `success` → label, source `lerobot-eval:success`; `--success-file` overrides.
//!
//! Untrusted: `eval_info.json` is read whole up to 16 MB into compact types; a video path is
//! taken from its last `videos/` component on (lerobot writes the path it was given, often
//! relative to where it ran) and confined to the folder ([`crate::confine`]); MP4 headers are
//! read with bounded sizes.

mod layout;
mod mp4;

use std::collections::HashSet;
use std::path::{Component, Path, PathBuf};

use serde_json::{json, Map, Value};

use crate::error::{IngestError, Result};
use crate::model::{EpisodeInput, Label, MediaColumn, MediaFile, StepFlags, VectorColumn};
use crate::options::ReadOptions;
use crate::sink::{EpisodeSink, SourceMeta};
use layout::{Evaluation, Layout, Task};

/// The file `lerobot-eval` writes its results to.
pub const EVAL_INFO: &str = "eval_info.json";
/// Where a label read from `eval_info.json` comes from.
pub const LABEL_SOURCE: &str = "lerobot-eval:success";
/// The media column of an episode's rendered video.
pub const VIDEO_COLUMN: &str = "render";

/// A folder `lerobot-eval` wrote: `eval_info.json`, and no LeRobot dataset's `meta/info.json`.
pub fn looks_like_dir(path: &Path) -> bool {
    path.join(EVAL_INFO).is_file() && !path.join("meta/info.json").exists()
}

/// Refuses the options that have no meaning for a lerobot-eval folder.
fn check_options(opts: &ReadOptions) -> Result<()> {
    if opts.success_from_rewards.is_some() {
        return Err(IngestError::Usage(
            "--success-from rewards: lerobot-eval records no per-step rewards (only each episode's sum and max); \
             its eval_info.json gives each episode's success"
                .into(),
        ));
    }
    if let Some(k) = &opts.intervention_key {
        return Err(IngestError::Usage(format!(
            "--intervention-key {k:?}: lerobot-eval output records no takeover flags"
        )));
    }
    Ok(())
}

/// Where each episode's seed comes from.
enum Seeds {
    /// Recorded in the file (0.3 layout).
    File,
    /// `--start-seed` + the episode's index in its task (0.4 layout).
    Start(i64),
    Unknown,
}

/// Reads a `lerobot-eval` output folder; returns notes for the user.
pub fn read_dir(root: &Path, opts: &ReadOptions, sink: &mut dyn EpisodeSink) -> Result<Vec<String>> {
    check_options(opts)?;
    let confine = crate::confine::Root::new(root)?;
    let info_path = root.join(EVAL_INFO);
    if !info_path.is_file() {
        return Err(IngestError::invalid(&info_path, "missing: not a lerobot-eval output folder"));
    }
    confine.check_inside(&info_path, EVAL_INFO)?;
    let bytes = crate::lerobot::read_bounded(&info_path, layout::MAX_EVAL_INFO_BYTES)?;
    let eval = layout::parse(&info_path, &bytes)?;
    let mut notes = Vec::new();
    let seeds = seeds(&info_path, &eval, opts.start_seed)?;
    if matches!(seeds, Seeds::Unknown) && eval.layout == Layout::PerTask {
        notes.push(format!(
            "{}: lerobot-eval (>= 0.4) does not record seeds; the episodes have no seed or pair_key, so \
             `ufops compare` pairs them in arrival order. Pass --start-seed S (lerobot-eval's --seed, 1000 \
             unless it was set) to pair evaluations by seed",
            info_path.display()
        ));
    }
    sink.source(SourceMeta { format: "lerobot-eval".into(), metadata: source_metadata(&eval, &seeds) })?;
    let several = eval.tasks.len() > 1;
    let mut index = 0u32;
    let mut emitted = HashSet::new();
    for task in &eval.tasks {
        let videos = task_videos(&confine, &info_path, task, &mut notes)?;
        for (i, ep) in task.episodes.iter().enumerate() {
            let seed = match seeds {
                Seeds::File => ep.seed,
                Seeds::Start(s) => s.checked_add(i as i64),
                Seeds::Unknown => None,
            };
            let name = match (several, task.name()) {
                (true, Some(t)) => format!("{t}/episode_{i}"),
                _ => format!("episode_{i}"),
            };
            let video = videos.get(i).map(|v| emit_video(&confine, v, &mut emitted, sink)).transpose()?;
            let e = Ctx { task, several, seed, opts, index, name, episode_index: i, video };
            sink.episode(e.episode(ep))?;
            index =
                index.checked_add(1).ok_or_else(|| IngestError::invalid(&info_path, "too many episodes"))?;
        }
    }
    Ok(notes)
}

fn seeds(info_path: &Path, eval: &Evaluation, start: Option<i64>) -> Result<Seeds> {
    match eval.layout {
        Layout::PerTask => Ok(start.map_or(Seeds::Unknown, Seeds::Start)),
        Layout::PerEpisode => {
            let first = eval.tasks.first().and_then(|t| t.episodes.first()).and_then(|e| e.seed);
            match (start, first) {
                (Some(s), Some(f)) if s != f => Err(IngestError::Usage(format!(
                    "--start-seed {s}: {} records the seeds, starting at {f}",
                    info_path.display()
                ))),
                (Some(s), None) => Err(IngestError::Usage(format!(
                    "--start-seed {s}: {} records no seed (the evaluation was not seeded)",
                    info_path.display()
                ))),
                _ => Ok(Seeds::File),
            }
        }
    }
}

fn source_metadata(eval: &Evaluation, seeds: &Seeds) -> Value {
    let mut m = Map::new();
    m.insert("layout".into(), json!(eval.layout.as_str()));
    let tasks: Vec<Value> = eval
        .tasks
        .iter()
        .map(|t| {
            json!({"task_group": t.group, "task_id": t.id, "episodes": t.episodes.len(),
                   "videos": t.videos.len().min(t.episodes.len())})
        })
        .collect();
    m.insert("tasks".into(), Value::Array(tasks));
    let (source, start) = match seeds {
        Seeds::File => ("eval_info.json", Value::Null),
        Seeds::Start(s) => ("--start-seed", json!(s)),
        Seeds::Unknown => ("unknown", Value::Null),
    };
    m.insert("seeds".into(), json!(source));
    m.insert("start_seed".into(), start);
    m.extend(eval.aggregates.clone());
    Value::Object(m)
}

/// A task's listed videos as files inside the folder, one per rendered episode in order; videos
/// past the task's episodes (lerobot-eval renders whole batches) are left out with a note.
fn task_videos(
    confine: &crate::confine::Root,
    info_path: &Path,
    task: &Task,
    notes: &mut Vec<String>,
) -> Result<Vec<PathBuf>> {
    let n = task.episodes.len();
    if task.videos.len() > n {
        notes.push(format!(
            "{}: {} videos listed past the {n} episodes{} (the last batch's extra environments): left out",
            info_path.display(),
            task.videos.len() - n,
            task.name().map(|t| format!(" of task {t}")).unwrap_or_default()
        ));
    }
    task.videos
        .iter()
        .take(n)
        .enumerate()
        .map(|(i, listed)| {
            let field = format!("the video of episode {i} ({listed:?})");
            let rel = video_rel(listed).ok_or_else(|| {
                IngestError::invalid(
                    info_path,
                    format!("{field} is not inside a `videos/` folder of the evaluation: refused (an evaluation may only name files inside its folder)"),
                )
            })?;
            let abs = confine.file(info_path, &field, &rel)?;
            if !abs.is_file() {
                return Err(IngestError::invalid(&abs, format!("missing: {field}, listed in {EVAL_INFO}")));
            }
            Ok(abs)
        })
        .collect()
}

/// The part of a listed video path from its last `videos` component on (lerobot writes
/// `<output_dir>/videos/…`, with the output dir as it was given, often relative to where it ran).
fn video_rel(listed: &str) -> Option<String> {
    let comps: Vec<Component> = Path::new(listed).components().collect();
    let at = comps.iter().rposition(|c| c.as_os_str() == "videos")?;
    let rel: PathBuf = comps[at..].iter().collect();
    Some(rel.to_string_lossy().into_owned())
}

/// A rendered episode's video: its media file, path in the folder and frames' times.
struct Video {
    file: MediaFile,
    rel: String,
    info: mp4::VideoInfo,
}

/// A rendered episode's video (emitted once per content: `emitted` holds the sha256s so far).
fn emit_video(
    confine: &crate::confine::Root,
    abs: &Path,
    emitted: &mut HashSet<String>,
    sink: &mut dyn EpisodeSink,
) -> Result<Video> {
    let info = mp4::probe(abs)?;
    let (sha256, size_bytes) = crate::hashing::hash_file(abs)?;
    let file =
        MediaFile { sha256, local_path: abs.to_path_buf(), content_type: "video/mp4".into(), size_bytes };
    if emitted.insert(file.sha256.clone()) {
        sink.media(file.clone())?;
    }
    let rel = abs.strip_prefix(confine.dir()).unwrap_or(abs).to_string_lossy().into_owned();
    Ok(Video { file, rel, info })
}

/// One episode's place and what was found for it.
struct Ctx<'a> {
    task: &'a Task,
    several: bool,
    seed: Option<i64>,
    opts: &'a ReadOptions,
    index: u32,
    name: String,
    episode_index: usize,
    video: Option<Video>,
}

impl Ctx<'_> {
    fn episode(self, ep: &layout::Episode) -> EpisodeInput {
        let (timestamps, media, video_md) = match &self.video {
            Some(v) => (
                v.info.times.clone(),
                vec![MediaColumn {
                    name: VIDEO_COLUMN.into(),
                    sha256: v.file.sha256.clone(),
                    timestamps: v.info.times.clone(),
                }],
                json!({"file": v.rel, "sha256": v.file.sha256, "frames": v.info.times.len(),
                       "fps": v.info.fps, "codec": v.info.codec}),
            ),
            None => (vec![0.0], Vec::new(), Value::Null),
        };
        let steps = timestamps.len();
        let reward = vec![0.0f32; steps];
        let mut done = vec![false; steps];
        done[steps - 1] = true;
        let (label, label_source) = match self.opts.user_label(&self.name, self.index, &reward) {
            Some(l) => l,
            None => match ep.success {
                Some(b) => (Label::from_bool(Some(b)), LABEL_SOURCE.to_string()),
                None => (Label::Unknown, String::new()),
            },
        };
        let task_name = self.task.name();
        let pair_key = self.seed.map(|s| match &task_name {
            Some(t) => format!("{t}/seed:{s}"),
            None => format!("seed:{s}"),
        });
        let mut md = Map::new();
        md.insert("episode_index".into(), json!(self.episode_index));
        md.insert("seed".into(), json!(self.seed));
        md.insert("pair_key".into(), json!(pair_key));
        md.insert("success".into(), json!(ep.success));
        md.insert("sum_reward".into(), json!(ep.sum_reward));
        md.insert("max_reward".into(), json!(ep.max_reward));
        if self.task.group.is_some() {
            md.insert("task_group".into(), json!(self.task.group));
            md.insert("task_id".into(), json!(self.task.id));
        }
        md.insert("video".into(), video_md);
        if self.video.is_none() {
            md.insert("outcome_only".into(), json!(true));
        }
        let task = self.opts.task.clone().or(task_name.filter(|_| self.several));
        EpisodeInput {
            source_name: self.name,
            source_index: self.index,
            task,
            label,
            label_source,
            tags: Vec::new(),
            metadata: Value::Object(md),
            timestamps,
            observations: Vec::new(),
            action: VectorColumn { name: "action".into(), dim: 0, values: Vec::new() },
            reward,
            done,
            action_chunk: None,
            images: Vec::new(),
            media,
            flags: StepFlags::default(),
        }
    }
}

/// Fuzzing entry: `eval_info.json` bytes parsed in either layout, and MP4 bytes probed for
/// their frame times. Feature `testing` (the fuzz targets and the tests).
#[cfg(any(test, feature = "testing"))]
pub fn fuzz_entry(eval_info: &[u8], mp4_bytes: &[u8]) -> (Result<usize>, Result<usize>) {
    let episodes = layout::parse(Path::new("fuzz/eval_info.json"), eval_info)
        .map(|e| e.tasks.iter().map(|t| t.episodes.len()).sum());
    let mut cursor = std::io::Cursor::new(mp4_bytes);
    let frames = mp4::probe_from(Path::new("fuzz/eval_episode_0.mp4"), &mut cursor, mp4_bytes.len() as u64)
        .map(|v| v.times.len());
    (episodes, frames)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn video_paths_are_read_from_their_videos_folder_on() {
        let rel = |s: &str| video_rel(s);
        assert_eq!(
            rel("outputs/eval/x/videos/pusht_0/eval_episode_0.mp4").unwrap(),
            "videos/pusht_0/eval_episode_0.mp4"
        );
        assert_eq!(rel("/abs/videos/run/videos/eval_episode_3.mp4").unwrap(), "videos/eval_episode_3.mp4");
        assert_eq!(rel("videos/../../secret").unwrap(), "videos/../../secret");
        assert_eq!(rel("/etc/passwd"), None);
    }
}
