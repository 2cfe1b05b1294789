//! export: the way out of the store. A store version, a split or a filter of one (policy,
//! checkpoint, task, label, tag, verifier-score range of an artifact) becomes a **LeRobot v3.0 dataset** ([`lerobot`]), a
//! **robomimic HDF5 file** ([`robomimic`]) or an **ALOHA folder** of one HDF5 file per episode
//! ([`aloha`]), with the version's frozen labels and a record of where
//! it came from. This crate owns the selection of episodes ([`Selection`]), reading their steps
//! in order with bounded memory ([`for_each_episode`]), the provenance record, and writing to a
//! temporary name renamed at the end (a crash leaves no half dataset). It reads the store only
//! through its public read path (`Store::read_episodes`, and the media objects of video cameras,
//! which the HDF5 writers decode back into image arrays: `cameras`).

pub mod aloha;
mod cameras;
pub mod job;
pub mod lerobot;
pub mod robomimic;
pub mod score_job;

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use arrow::array::RecordBatch;
use serde::{Deserialize, Serialize};
use store::{EpisodeFilter, EpisodeLocation, EpisodeRecord, Label, Store, StoreError};

#[derive(Debug, thiserror::Error)]
pub enum ExportError {
    #[error(transparent)]
    Store(#[from] StoreError),
    #[error("{0}")]
    Invalid(String),
    #[error("{}: {source}", path.display())]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("writing {}: {message}", path.display())]
    Write { path: PathBuf, message: String },
}

impl ExportError {
    pub(crate) fn invalid(msg: impl Into<String>) -> Self {
        ExportError::Invalid(msg.into())
    }
    pub(crate) fn io(path: &Path, source: std::io::Error) -> Self {
        ExportError::Io { path: path.to_path_buf(), source }
    }
    pub(crate) fn write(path: &Path, e: impl std::fmt::Display) -> Self {
        ExportError::Write { path: path.to_path_buf(), message: e.to_string() }
    }
}

pub type Result<T, E = ExportError> = std::result::Result<T, E>;

/// Which episodes to export: a version (default: the head) or a split (pinned to its own
/// version), narrowed by the filters.
#[derive(Debug, Clone, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Selection {
    pub version: Option<i64>,
    pub split: Option<String>,
    pub policy: Option<String>,
    pub checkpoint: Option<String>,
    pub task: Option<String>,
    pub label: Option<Label>,
    pub tag: Option<String>,
    /// Keep only episodes whose verifier score lies in a range (Demo-SCORE-style curation); the
    /// scoring itself is done by [`filter_by_score`] with a scorer the caller supplies.
    pub score: Option<ScoreRange>,
    /// Layers (derived per-step data, e.g. an encoder's features) carried as observation
    /// columns `obs.<layer>` (LeRobot `observation.<layer>`, robomimic `obs/<layer>`); every
    /// selected episode must hold them (in the selection's version).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub layers: Vec<String>,
}

/// A range of episode scores of one verifier artifact: `min <= score <= max` (either bound open).
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ScoreRange {
    /// The artifact's id (resolved from an alias by the caller, so the record names one artifact).
    pub artifact: String,
    pub min: Option<f64>,
    pub max: Option<f64>,
}

impl ScoreRange {
    pub fn contains(&self, score: f64) -> bool {
        self.min.is_none_or(|m| score >= m) && self.max.is_none_or(|m| score <= m)
    }
}

pub use verifier::StepScorer;

/// An episode's score: the mean of its steps' scores, as Demo-SCORE aggregates a rollout
/// classifier over a demonstration. `None` for an episode without steps.
pub fn episode_score(step_scores: &[f32]) -> Option<f64> {
    (!step_scores.is_empty())
        .then(|| step_scores.iter().map(|&x| x as f64).sum::<f64>() / step_scores.len() as f64)
}

/// Scores every step of each episode (in order) with `scorer`, reading steps with bounded
/// memory, and hands `f` the episode's index, record and step scores (all finite).
pub async fn score_each_episode(
    store: &Store,
    episodes: &[EpisodeRecord],
    scorer: &dyn StepScorer,
    mut f: impl FnMut(usize, &EpisodeRecord, Vec<f32>) -> Result<()>,
) -> Result<()> {
    for_each_episode_with_layers(store, episodes, &scorer.layers(), None, |i, e, steps| {
        let s = scorer
            .score_steps(&steps)
            .map_err(|m| ExportError::invalid(format!("scoring episode {}: {m}", e.id)))?;
        if s.iter().any(|x| !x.is_finite()) {
            return Err(ExportError::invalid(format!(
                "scoring episode {}: the verifier returned a non-finite score",
                e.id
            )));
        }
        f(i, e, s)
    })
    .await
}

/// Scores each episode (in order) with `scorer`: its [`episode_score`].
pub async fn score_episodes(
    store: &Store,
    episodes: &[EpisodeRecord],
    scorer: &dyn StepScorer,
    progress: Progress<'_>,
) -> Result<Vec<Option<f64>>> {
    let mut scores = vec![None; episodes.len()];
    let total = episodes.len();
    score_each_episode(store, episodes, scorer, |i, _, s| {
        scores[i] = episode_score(&s);
        if let Some(p) = progress {
            p(i + 1, total);
        }
        Ok(())
    })
    .await?;
    Ok(scores)
}

/// Narrows a resolved selection to the episodes whose score lies in `sel.selection.score`
/// (a no-op without one) and records each kept episode's score.
pub async fn filter_by_score(
    store: &Store,
    sel: &mut Selected,
    scorer: &dyn StepScorer,
    progress: Progress<'_>,
) -> Result<()> {
    let Some(range) = sel.selection.score.clone() else { return Ok(()) };
    let scores = score_episodes(store, &sel.episodes, scorer, progress).await?;
    sel.scored = Some(sel.episodes.len());
    let mut kept = Vec::new();
    for (e, s) in std::mem::take(&mut sel.episodes).into_iter().zip(scores) {
        if let Some(s) = s.filter(|s| range.contains(*s)) {
            sel.scores.insert(e.id.clone(), s);
            kept.push(e);
        }
    }
    sel.episodes = kept;
    Ok(())
}

/// The episodes a [`Selection`] resolved to, in the store's order (by version added, source,
/// index in the source), with their labels frozen in `version`.
#[derive(Debug, Clone)]
pub struct Selected {
    pub version: i64,
    /// The labels files of `version`: a full one, then the deltas after it (store/README.md,
    /// "Label files").
    pub labels_files: Vec<String>,
    pub episodes: Vec<EpisodeRecord>,
    /// For a split: each episode's part (`train` or `val`).
    pub parts: HashMap<String, String>,
    pub selection: Selection,
    /// With a score range: each kept episode's verifier score ([`filter_by_score`]).
    pub scores: HashMap<String, f64>,
    /// With a score range: how many episodes were scored before the range was applied.
    pub scored: Option<usize>,
    /// The data of the label event behind each exported label (failure cause, time spans,
    /// votes), for the episodes whose labelers gave any.
    pub label_data: HashMap<String, serde_json::Value>,
}

/// The failure cause in a label event's data.
pub(crate) fn failure_cause(data: Option<&serde_json::Value>) -> Option<String> {
    data?.get("failure_cause")?.as_str().map(str::to_string)
}

/// The time spans in a label event's data, as JSON (`[{start_step, end_step, actor?}]`).
pub(crate) fn label_spans(data: Option<&serde_json::Value>) -> Option<String> {
    data?.get("spans").filter(|s| s.as_array().is_some_and(|a| !a.is_empty())).map(|s| s.to_string())
}

impl Selected {
    /// Where the export came from, recorded in its metadata.
    pub fn provenance(&self, format: &str) -> serde_json::Value {
        serde_json::json!({
            "exported_by": format!("ufops {}", env!("CARGO_PKG_VERSION")),
            "exported_at": chrono::Utc::now().to_rfc3339_opts(chrono::SecondsFormat::Secs, true),
            "format": format,
            "store_version": self.version,
            "label_files": self.labels_files,
            "selection": self.selection,
            "episodes": self.episodes.len(),
            "episodes_scored": self.scored,
        })
    }
}

/// Resolves a selection against the store. Labels are always those frozen in a version (the
/// head's when none is given), never unsnapshotted edits.
pub async fn select(store: &Store, sel: &Selection) -> Result<Selected> {
    let mut parts = HashMap::new();
    let (version, members) = match &sel.split {
        Some(id) => {
            let split = store.split(id).await?;
            if sel.version.is_some_and(|v| v != split.version) {
                return Err(ExportError::invalid(format!(
                    "split {id} is pinned to version {}, not {}",
                    split.version,
                    sel.version.unwrap_or_default()
                )));
            }
            for m in store.split_episodes(id).await? {
                parts.insert(m.episode_id, m.part);
            }
            (split.version, true)
        }
        None => match sel.version {
            Some(v) => (v, false),
            None => (store.head_version().await?, false),
        },
    };
    let info = store.version(version).await?;
    let filter = EpisodeFilter {
        version: Some(version),
        policy: sel.policy.clone(),
        checkpoint: sel.checkpoint.clone(),
        task: sel.task.clone(),
        label: sel.label,
        tag: sel.tag.clone(),
        ..Default::default()
    };
    let mut episodes = store.episodes(&filter).await?;
    if members {
        episodes.retain(|e| parts.contains_key(&e.id));
    }
    episodes.sort_by(|a, b| {
        (a.version_added, &a.source_sha256, a.source_index).cmp(&(
            b.version_added,
            &b.source_sha256,
            b.source_index,
        ))
    });
    if let Some(r) = &sel.score {
        if r.min.is_some_and(|m| !m.is_finite())
            || r.max.is_some_and(|m| !m.is_finite())
            || r.min.zip(r.max).is_some_and(|(a, b)| a > b)
        {
            return Err(ExportError::invalid(format!(
                "score range [{:?}, {:?}]: bounds must be finite with min <= max",
                r.min, r.max
            )));
        }
    }
    let keys: Vec<(String, i64)> = episodes.iter().map(|e| (e.id.clone(), e.label_revision)).collect();
    let label_data = store.label_event_data(&keys).await?;
    Ok(Selected {
        label_data,
        version,
        labels_files: store.labels_files(info.version).await?,
        episodes,
        parts,
        selection: sel.clone(),
        scores: HashMap::new(),
        scored: None,
    })
}

/// Episodes read per request to the store: a group's steps are held at once, so memory is
/// bounded by the group, not by the export.
const GROUP_ROWS: i64 = 32_768;
const GROUP_EPISODES: usize = 256;

/// Calls `f` with each episode's steps, in the order of `episodes`, reading them in groups
/// through `Store::read_episodes` (each group's row groups read once).
pub async fn for_each_episode(
    store: &Store,
    episodes: &[EpisodeRecord],
    f: impl FnMut(usize, &EpisodeRecord, RecordBatch) -> Result<()>,
) -> Result<()> {
    for_each_episode_with_layers(store, episodes, &[], None, f).await
}

/// [`for_each_episode`] with `layers` joined to the steps (as `obs.<layer>`), as of `version`.
pub async fn for_each_episode_with_layers(
    store: &Store,
    episodes: &[EpisodeRecord],
    layers: &[String],
    version: Option<i64>,
    mut f: impl FnMut(usize, &EpisodeRecord, RecordBatch) -> Result<()>,
) -> Result<()> {
    let mut reader = EpisodeReader::new(store, episodes, layers, version);
    while let Some((i, e, steps)) = reader.next().await? {
        f(i, e, steps)?;
    }
    Ok(())
}

/// The steps of episodes in order, read in groups as [`for_each_episode_with_layers`] reads them,
/// handed out one episode at a time: for writers that await between episodes (a video camera's
/// object is fetched from the store once its episode's steps name it).
pub(crate) struct EpisodeReader<'a> {
    store: &'a Store,
    episodes: &'a [EpisodeRecord],
    layers: &'a [String],
    version: Option<i64>,
    /// The first episode of the next group.
    next_group: usize,
    /// The steps of the group read last, not handed out yet.
    ready: std::vec::IntoIter<(usize, RecordBatch)>,
}

impl<'a> EpisodeReader<'a> {
    pub fn new(
        store: &'a Store,
        episodes: &'a [EpisodeRecord],
        layers: &'a [String],
        version: Option<i64>,
    ) -> Self {
        EpisodeReader { store, episodes, layers, version, next_group: 0, ready: Vec::new().into_iter() }
    }

    /// The next episode's index, record and steps; `None` after the last.
    pub async fn next(&mut self) -> Result<Option<(usize, &'a EpisodeRecord, RecordBatch)>> {
        if let Some((i, steps)) = self.ready.next() {
            return Ok(Some((i, &self.episodes[i], steps)));
        }
        if self.next_group >= self.episodes.len() {
            return Ok(None);
        }
        self.ready = self.read_group().await?.into_iter();
        Ok(self.ready.next().map(|(i, steps)| (i, &self.episodes[i], steps)))
    }

    /// Reads the next group: at most [`GROUP_ROWS`] rows (or one episode) and [`GROUP_EPISODES`].
    async fn read_group(&mut self) -> Result<Vec<(usize, RecordBatch)>> {
        let (episodes, start) = (self.episodes, self.next_group);
        let mut end = start;
        let mut rows = 0;
        while end < episodes.len()
            && (end == start || rows + episodes[end].row_count <= GROUP_ROWS)
            && end - start < GROUP_EPISODES
        {
            rows += episodes[end].row_count;
            end += 1;
        }
        self.next_group = end;
        let locations =
            episodes[start..end].iter().map(EpisodeLocation::try_from).collect::<Result<Vec<_>, _>>()?;
        let mut slots: Vec<Option<RecordBatch>> = vec![None; end - start];
        let mut stream = if self.layers.is_empty() {
            self.store.read_episodes(locations)
        } else {
            let ids: Vec<String> = episodes[start..end].iter().map(|e| e.id.clone()).collect();
            let at = self.store.locate_layers(&ids, self.layers, self.version).await?;
            self.store.read_episodes_with_layers(locations, self.layers.to_vec(), at)
        };
        while let Some(item) = stream.next().await {
            let item = item.map_err(StoreError::from)?;
            slots[item.index] = Some(item.steps);
        }
        slots
            .into_iter()
            .enumerate()
            .map(|(k, steps)| {
                let e = &episodes[start + k];
                let steps = steps.ok_or_else(|| {
                    ExportError::invalid(format!("episode {}: the store returned no steps", e.id))
                })?;
                Ok((start + k, steps))
            })
            .collect()
    }
}

/// A destination written under a temporary name next to it and renamed into place by
/// [`Staged::commit`]; dropped uncommitted, the temporary is removed.
pub(crate) struct Staged {
    pub tmp: PathBuf,
    pub dest: PathBuf,
    committed: bool,
}

impl Staged {
    /// The staged output of a writer exporting `sel` to `dest` (a folder when `dir`): refused
    /// when the selection holds no episodes, before anything is created.
    pub fn for_selection(sel: &Selected, dest: &Path, dir: bool) -> Result<Self> {
        if sel.episodes.is_empty() {
            return Err(ExportError::invalid("the selection holds no episodes: nothing to export"));
        }
        Staged::new(dest, dir)
    }

    pub fn new(dest: &Path, dir: bool) -> Result<Self> {
        if dest.exists() {
            return Err(ExportError::invalid(format!(
                "{} already exists: choose a new output path",
                dest.display()
            )));
        }
        let name = dest
            .file_name()
            .ok_or_else(|| ExportError::invalid(format!("{}: not a file or folder name", dest.display())))?;
        let parent = dest.parent().filter(|p| !p.as_os_str().is_empty()).unwrap_or(Path::new("."));
        if !parent.is_dir() {
            return Err(ExportError::invalid(format!("{}: the folder does not exist", parent.display())));
        }
        let tmp = parent.join(format!(".{}.tmp-{}", name.to_string_lossy(), uuid::Uuid::new_v4().simple()));
        if dir {
            std::fs::create_dir(&tmp).map_err(|e| ExportError::io(&tmp, e))?;
        }
        Ok(Staged { tmp, dest: dest.to_path_buf(), committed: false })
    }

    pub fn commit(mut self) -> Result<()> {
        if self.dest.exists() {
            return Err(ExportError::invalid(format!(
                "{} appeared while exporting: not replaced",
                self.dest.display()
            )));
        }
        std::fs::rename(&self.tmp, &self.dest).map_err(|e| ExportError::io(&self.dest, e))?;
        self.committed = true;
        Ok(())
    }
}

impl Drop for Staged {
    fn drop(&mut self) {
        if !self.committed {
            let _ = if self.tmp.is_dir() {
                std::fs::remove_dir_all(&self.tmp)
            } else {
                std::fs::remove_file(&self.tmp)
            };
        }
    }
}

/// What an export wrote.
#[derive(Debug, Clone, Serialize)]
pub struct ExportReport {
    pub path: PathBuf,
    pub format: String,
    pub version: i64,
    pub episodes: usize,
    pub frames: u64,
    pub labels: store::LabelCounts,
    /// Video files copied (LeRobot).
    pub media_files: usize,
    pub bytes: u64,
    /// What could not be exported as it is (e.g. columns the format has no place for).
    pub warnings: Vec<String>,
}

impl Selected {
    /// The sources of the selected episodes, each read once, in order of first use (keyed by
    /// sha256): their formats and metadata shape what a writer gives back.
    pub(crate) async fn sources(&self, store: &Store) -> Result<Vec<store::SourceRecord>> {
        let mut seen = std::collections::HashSet::new();
        let mut sources = Vec::new();
        for e in &self.episodes {
            if seen.insert(e.source_sha256.as_str()) {
                sources.push(store.source(&e.source_sha256).await?);
            }
        }
        Ok(sources)
    }
}

impl ExportReport {
    /// Nothing written yet: an export of `version` as `format` to `path`.
    pub(crate) fn empty(path: &Path, format: &str, version: i64) -> ExportReport {
        ExportReport {
            path: path.to_path_buf(),
            format: format.to_string(),
            version,
            episodes: 0,
            frames: 0,
            labels: Default::default(),
            media_files: 0,
            bytes: 0,
            warnings: Vec::new(),
        }
    }
}

pub(crate) fn count_label(c: &mut store::LabelCounts, l: Label) {
    c.total += 1;
    match l {
        Label::Success => c.success += 1,
        Label::Failure => c.failure += 1,
        Label::Unknown => c.unknown += 1,
    }
}

/// Size of a file or of every file under a folder.
pub(crate) fn disk_size(p: &Path) -> u64 {
    match std::fs::metadata(p) {
        Ok(m) if m.is_dir() => {
            std::fs::read_dir(p).map(|rd| rd.flatten().map(|e| disk_size(&e.path())).sum()).unwrap_or(0)
        }
        Ok(m) => m.len(),
        Err(_) => 0,
    }
}

/// Optional progress callback: `(episodes done, episodes total)`.
pub type Progress<'a> = Option<&'a (dyn Fn(usize, usize) + Send + Sync)>;
