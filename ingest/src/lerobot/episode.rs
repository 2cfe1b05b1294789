//! One episode's rows ([`EpBuf`]) checked against its metadata and turned into an
//! [`EpisodeInput`]: observations, images, videos, label, task, flags and metadata.

use std::collections::{HashMap, HashSet};
use std::path::{Path, PathBuf};

use serde_json::{json, Map, Value};

use super::data::{EpBuf, Plan, Validity};
use super::info::Info;
use super::meta::EpisodeMeta;
use super::VALIDITY_KEY;
use crate::error::{IngestError, Result};
use crate::model::{EpisodeInput, Frames, ImageColumn, Label, MediaFile, StepFlags, VectorColumn};
use crate::options::ReadOptions;
use crate::sink::EpisodeSink;

const LABEL_SOURCE: &str = "lerobot:next.success";

pub(super) struct Ctx<'a> {
    pub(super) root: &'a Path,
    pub(super) confine: &'a crate::confine::Root,
    pub(super) info_path: &'a Path,
    pub(super) info: &'a Info,
    pub(super) plan: &'a Plan,
    pub(super) tasks: &'a HashMap<i64, String>,
    pub(super) metas: HashMap<u64, (usize, EpisodeMeta)>,
    pub(super) opts: &'a ReadOptions,
    pub(super) emitted_media: HashMap<PathBuf, MediaFile>,
    pub(super) seen: HashSet<u64>,
}

impl Ctx<'_> {
    pub(super) fn finish(&mut self, path: &Path, b: EpBuf, sink: &mut dyn EpisodeSink) -> Result<()> {
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
        check_rows(path, e, &meta, &b)?;
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
        for ((_, short), (shape, frames)) in self.plan.images.iter().zip(b.images) {
            let shape = shape.ok_or_else(|| {
                IngestError::invalid(path, format!("episode {e}: image {short} is not a valid PNG"))
            })?;
            images.push(ImageColumn { name: short.clone(), shape, frames: Frames::Stream(frames) });
        }
        let (media, video_md) = self.video_columns(e, &meta, &b.timestamps, sink)?;
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

/// The episode's row count, and its `index` column when there is one, against what its
/// metadata declares (`length`, `dataset_from_index..dataset_to_index`).
fn check_rows(path: &Path, e: u64, meta: &EpisodeMeta, b: &EpBuf) -> Result<()> {
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
    Ok(())
}
