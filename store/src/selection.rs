//! Selecting episodes and reading their steps in order: the path every consumer that works
//! episode by episode shares (the exports, the verifier core's scoring of stored steps, the
//! failure monitors' calibration, the replay of steering telemetry). A [`Selection`] (a version
//! or a split, narrowed by filters) resolves to [`Selected`] episodes with the labels frozen in
//! that version; [`for_each_episode`] and [`EpisodeReader`] read their steps in groups, so
//! memory is bounded by a group, not by the selection. It uses only the store's public read
//! path (`Store::episodes`, `Store::read_episodes`, `Store::locate_layers`).

use std::collections::{HashMap, HashSet};

use arrow::array::RecordBatch;
use serde::{Deserialize, Serialize};

use crate::{EpisodeFilter, EpisodeLocation, EpisodeRecord, Label, SourceRecord, Store, StoreError};

/// Which episodes: a version (default: the head) or a split (pinned to its own version),
/// narrowed by the filters.
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
    /// scoring itself is the verifier core's (`verifier::stored::filter_by_score`), with a scorer
    /// the caller supplies.
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
    /// With a score range: each kept episode's verifier score (`verifier::stored::filter_by_score`).
    pub scores: HashMap<String, f64>,
    /// With a score range: how many episodes were scored before the range was applied.
    pub scored: Option<usize>,
    /// The data of the label event behind each selected label (failure cause, time spans,
    /// votes), for the episodes whose labelers gave any.
    pub label_data: HashMap<String, serde_json::Value>,
}

impl Selected {
    /// Where a dataset written from this selection came from, recorded in its metadata.
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

    /// The sources of the selected episodes, each read once, in order of first use (keyed by
    /// sha256): their formats and metadata shape what a writer gives back.
    pub async fn sources(&self, store: &Store) -> Result<Vec<SourceRecord>, StoreError> {
        let mut seen = HashSet::new();
        let mut sources = Vec::new();
        for e in &self.episodes {
            if seen.insert(e.source_sha256.as_str()) {
                sources.push(store.source(&e.source_sha256).await?);
            }
        }
        Ok(sources)
    }
}

/// Resolves a selection against the store. Labels are always those frozen in a version (the
/// head's when none is given), never unsnapshotted edits.
pub async fn select(store: &Store, sel: &Selection) -> Result<Selected, StoreError> {
    let mut parts = HashMap::new();
    let (version, members) = match &sel.split {
        Some(id) => {
            let split = store.split(id).await?;
            if sel.version.is_some_and(|v| v != split.version) {
                return Err(StoreError::invalid(format!(
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
            return Err(StoreError::invalid(format!(
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

/// Optional progress callback: `(episodes done, episodes total)`.
pub type Progress<'a> = Option<&'a (dyn Fn(usize, usize) + Send + Sync)>;

/// Episodes read per request to the store: a group's steps are held at once, so memory is
/// bounded by the group, not by the selection.
const GROUP_ROWS: i64 = 32_768;
const GROUP_EPISODES: usize = 256;

/// Calls `f` with each episode's steps, in the order of `episodes`, reading them in groups
/// through `Store::read_episodes` (each group's row groups read once). `f` fails with the
/// caller's own error, into which the store's converts.
pub async fn for_each_episode<E: From<StoreError>>(
    store: &Store,
    episodes: &[EpisodeRecord],
    f: impl FnMut(usize, &EpisodeRecord, RecordBatch) -> Result<(), E>,
) -> Result<(), E> {
    for_each_episode_with_layers(store, episodes, &[], None, f).await
}

/// [`for_each_episode`] with `layers` joined to the steps (as `obs.<layer>`), as of `version`.
pub async fn for_each_episode_with_layers<E: From<StoreError>>(
    store: &Store,
    episodes: &[EpisodeRecord],
    layers: &[String],
    version: Option<i64>,
    mut f: impl FnMut(usize, &EpisodeRecord, RecordBatch) -> Result<(), E>,
) -> Result<(), E> {
    let mut reader = EpisodeReader::new(store, episodes, layers, version);
    while let Some((i, e, steps)) = reader.next().await? {
        f(i, e, steps)?;
    }
    Ok(())
}

/// The steps of episodes in order, read in groups as [`for_each_episode_with_layers`] reads them,
/// handed out one episode at a time: for consumers that await between episodes (an export's
/// video camera object is fetched from the store once its episode's steps name it).
pub struct EpisodeReader<'a> {
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
    pub async fn next(&mut self) -> Result<Option<(usize, &'a EpisodeRecord, RecordBatch)>, StoreError> {
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
    async fn read_group(&mut self) -> Result<Vec<(usize, RecordBatch)>, StoreError> {
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
                    StoreError::invalid(format!("episode {}: the store returned no steps", e.id))
                })?;
                Ok((start + k, steps))
            })
            .collect()
    }
}
