//! The ufops viewer: turns the rollouts of one policy checkpoint (or of one split) into a rerun
//! recording (`.rrd`, written with `re_sdk`, never spawning a viewer).
//!
//! It owns the recording's layout — entity paths, timelines (`step`, `time`), colours, the
//! blueprint — and nothing else: episodes and steps come from the `store` crate, verifier scores
//! from whoever implements [`StepScorer`] (a verifier artifact: `verifier::Verifier` implements it).
//! [`write_recording`] writes a file for `ufops view`; [`recording_bytes`] returns the same
//! recording in memory for the API's `GET /v1/views`.
//!
//! Layout (`L` = `success` | `failure` | `unknown`, `ID` = the episode id):
//!
//! | entity | content |
//! |---|---|
//! | `episodes/L/ID/trajectory` | static LineStrips2D/3D of the position dims, coloured by label |
//! | `episodes/L/ID/position` | Points2D/3D, one per step (the moving "head" of the trajectory) |
//! | `episodes/L/ID/action` | Scalars, one series per action dim |
//! | `episodes/L/ID/state/KEY` | Scalars, one series per dim of observation `KEY` (≤ 64 dims) |
//! | `episodes/L/ID/reward` | Scalars |
//! | `episodes/L/ID/score` | Scalars: the verifier's score per step (with a scorer) |
//! | `episodes/L/ID/camera/KEY` | VideoFrameReference per step into `media/KEY/FILE` (LeRobot videos) |
//! | `episodes/L/ID/image/KEY` | EncodedImage per step: the stored PNG or JPEG bytes (image columns) |
//! | `media/KEY/FILE` | static AssetVideo, one per referenced video object |
//! | `summary/score/{success,failure,gap}` | mean score per step of successes / failures, and their difference |
//! | `summary/info` | static markdown: counts, lengths, mean scores, where the verifier separates |
//!
//! All time-varying data is sent column-wise with `send_columns` (one chunk per entity and
//! episode), never row by row.

use arrow::array::{
    Array, BinaryArray, Float64Array, Int32Array, LargeBinaryArray, RecordBatch, StringArray,
};
use re_sdk::blueprint::{
    Blueprint, BlueprintActivation, ContainerLike, Grid, Horizontal, Spatial2DView, Spatial3DView,
    TimeSeriesView, Vertical,
};
use re_sdk::log::TimeColumn;
use re_sdk::{RecordingStream, RecordingStreamBuilder};
use re_sdk_types::archetypes::{
    AssetVideo, EncodedImage, LineStrips2D, LineStrips3D, Points2D, Points3D, Scalars, SeriesLines,
    TextDocument, VideoFrameReference,
};
use re_sdk_types::components::{Color, MediaType, VideoTimestamp};
use std::collections::{BTreeMap, BTreeSet, HashMap, HashSet};
use std::path::Path;
use store::{EpisodeFilter, EpisodeRecord, Label, Store, StoreError};
pub use verifier::StepScorer;

/// The re_sdk version the recordings are written with (the PyPI `rerun-sdk` to read them).
pub const RERUN_SDK_VERSION: &str = "0.36.3";
/// Application id of the recordings.
pub const APPLICATION_ID: &str = "ufops";
/// Observation keys wider than this are not plotted as scalar series (images, features).
pub const MAX_STATE_DIMS: usize = 64;

const GREEN: Color = Color(re_sdk_types::datatypes::Rgba32::from_rgb(40, 180, 70));
const RED: Color = Color(re_sdk_types::datatypes::Rgba32::from_rgb(220, 50, 47));
const GREY: Color = Color(re_sdk_types::datatypes::Rgba32::from_rgb(150, 150, 150));
const BLUE: Color = Color(re_sdk_types::datatypes::Rgba32::from_rgb(60, 110, 220));

/// What to put in a recording.
#[derive(Debug, Clone, Default)]
pub struct ViewOptions {
    pub policy: String,
    pub checkpoint: String,
    /// Show the episodes of this split (its version unless `version` is given) instead of
    /// all episodes of `policy`/`checkpoint`.
    pub split_id: Option<String>,
    /// Read the store as of this version (labels frozen in it); `None`: the head.
    pub version: Option<i64>,
    /// At most this many episodes, taken alternately from successes, failures and unknowns
    /// (in episode-id order within each) so that a limit keeps both sides visible.
    pub max_episodes: Option<usize>,
    /// Observation dims that form the trajectory: keys (`pos`, `robot0_eef_pos`) or keys with
    /// indices (`state[0,1]`), concatenated; 2 dims → 2-D, 3 dims → 3-D. Empty: the first
    /// observation key with 2 or 3 dims.
    pub position_keys: Vec<String>,
    /// Do not log image-column cameras (`image.<key>`: one EncodedImage per step, PNG or JPEG
    /// as stored); off by default, so every camera is in the recording.
    pub no_images: bool,
    /// Keep every n-th frame of image-column cameras (0 or 1: every frame).
    pub image_stride: usize,
    /// Do not embed referenced videos (AssetVideo + VideoFrameReference); on by default.
    pub no_videos: bool,
}

impl ViewOptions {
    pub fn new(policy: impl Into<String>, checkpoint: impl Into<String>) -> Self {
        ViewOptions { policy: policy.into(), checkpoint: checkpoint.into(), ..Default::default() }
    }
}

/// What went into a recording.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct ViewReport {
    pub episodes: usize,
    pub success: usize,
    pub failure: usize,
    pub unknown: usize,
    /// Total rows (steps) over all episodes.
    pub steps: usize,
    /// The dims the trajectories were drawn from, e.g. `["pos[0]", "pos[1]"]`; empty: none.
    pub position_dims: Vec<String>,
    /// Episodes that had no usable position (drawn without trajectory).
    pub without_position: usize,
    pub videos: usize,
    pub video_frames: usize,
    pub images: usize,
    /// The cameras logged (image columns and videos), by key, sorted.
    pub cameras: Vec<String>,
    pub scored: bool,
    /// Mean score over all steps of successes / failures.
    pub mean_score_success: Option<f32>,
    pub mean_score_failure: Option<f32>,
    /// `(step, success mean − failure mean)` at the step where the gap is largest.
    pub max_separation: Option<(i64, f32)>,
    /// First step from which the gap stays ≥ half its maximum for the rest of the common steps.
    pub separates_from_step: Option<i64>,
    /// The entity paths with data (sorted).
    pub entities: Vec<String>,
}

#[derive(Debug, thiserror::Error)]
pub enum ViewError {
    #[error(transparent)]
    Store(#[from] StoreError),
    #[error("invalid view request: {0}")]
    Invalid(String),
    #[error("scoring episode {episode} failed: {message}")]
    Scorer { episode: String, message: String },
    #[error("rerun: {0}")]
    Rerun(String),
    #[error("writing {path}: {message}")]
    Io { path: String, message: String },
}

fn rr<E: std::fmt::Display>(e: E) -> ViewError {
    ViewError::Rerun(e.to_string())
}

/// Writes the recording to `out` (an `.rrd` file), no viewer involved.
pub async fn write_recording(
    store: &Store,
    opts: &ViewOptions,
    scores: Option<&dyn StepScorer>,
    out: &Path,
) -> Result<ViewReport, ViewError> {
    if let Some(parent) = out.parent().filter(|p| !p.as_os_str().is_empty()) {
        std::fs::create_dir_all(parent)
            .map_err(|e| ViewError::Io { path: parent.display().to_string(), message: e.to_string() })?;
    }
    // Fail early (and with our own message) if the file cannot be created.
    std::fs::File::create(out)
        .map_err(|e| ViewError::Io { path: out.display().to_string(), message: e.to_string() })?;
    let rec = builder(opts).save(out).map_err(rr)?;
    let report = record(&rec, store, opts, scores).await;
    rec.flush_blocking().map_err(rr)?;
    // Writes the footer and closes the file now rather than when the last handle drops.
    rec.finalize_deferred_sinks();
    drop(rec);
    report
}

/// The same recording as [`write_recording`], in memory (`.rrd` bytes, for `GET /v1/views`).
pub async fn recording_bytes(
    store: &Store,
    opts: &ViewOptions,
    scores: Option<&dyn StepScorer>,
) -> Result<(Vec<u8>, ViewReport), ViewError> {
    let (rec, storage) = builder(opts).memory().map_err(rr)?;
    let report = record(&rec, store, opts, scores).await?;
    let bytes = storage.drain_as_bytes().map_err(rr)?;
    Ok((bytes, report))
}

/// [`recording_bytes`] written to any writer.
pub async fn write_recording_to(
    store: &Store,
    opts: &ViewOptions,
    scores: Option<&dyn StepScorer>,
    w: &mut dyn std::io::Write,
) -> Result<ViewReport, ViewError> {
    let (bytes, report) = recording_bytes(store, opts, scores).await?;
    w.write_all(&bytes).map_err(|e| ViewError::Io { path: "<writer>".into(), message: e.to_string() })?;
    Ok(report)
}

fn builder(opts: &ViewOptions) -> RecordingStreamBuilder {
    let mut name = format!("{} / {}", opts.policy, opts.checkpoint);
    if let Some(s) = &opts.split_id {
        name.push_str(&format!(" / split {s}"));
    }
    if let Some(v) = opts.version {
        name.push_str(&format!(" @ v{v}"));
    }
    // `enabled(true)`: a `RERUN=off` in the environment must not silently produce an empty file.
    RecordingStreamBuilder::new(APPLICATION_ID).recording_name(name).enabled(true)
}

fn label_color(l: Label) -> Color {
    match l {
        Label::Success => GREEN,
        Label::Failure => RED,
        Label::Unknown => GREY,
    }
}

/// The episode path `episodes/L/ID` (the id is one path part, escaped if needed).
pub fn episode_path(label: Label, id: &str) -> String {
    let part = re_sdk::EntityPathPart::from(id);
    format!("episodes/{}/{}", label.as_str(), part.escaped_string())
}

/// Selects the episodes of the view, in recording order.
async fn select_episodes(store: &Store, opts: &ViewOptions) -> Result<Vec<EpisodeRecord>, ViewError> {
    let eps = match &opts.split_id {
        Some(split_id) => {
            let split = store.split(split_id).await?;
            let version = opts.version.unwrap_or(split.version);
            let ids: HashSet<String> =
                store.split_episodes(split_id).await?.into_iter().map(|e| e.episode_id).collect();
            let all = store.episodes(&EpisodeFilter { version: Some(version), ..Default::default() }).await?;
            all.into_iter().filter(|e| ids.contains(&e.id)).collect::<Vec<_>>()
        }
        None => {
            if opts.policy.is_empty() || opts.checkpoint.is_empty() {
                return Err(ViewError::Invalid("a policy and a checkpoint (or a split) are required".into()));
            }
            let f = EpisodeFilter {
                version: opts.version,
                policy: Some(opts.policy.clone()),
                checkpoint: Some(opts.checkpoint.clone()),
                ..Default::default()
            };
            store.episodes(&f).await?
        }
    };
    let Some(max) = opts.max_episodes else { return Ok(eps) };
    // Round-robin over labels so a limit keeps successes and failures side by side.
    let mut by_label: BTreeMap<u8, std::collections::VecDeque<EpisodeRecord>> = BTreeMap::new();
    for e in eps {
        let k = match e.label {
            Label::Success => 0,
            Label::Failure => 1,
            Label::Unknown => 2,
        };
        by_label.entry(k).or_default().push_back(e);
    }
    let mut out = Vec::new();
    while out.len() < max && by_label.values().any(|q| !q.is_empty()) {
        for q in by_label.values_mut() {
            if out.len() < max {
                if let Some(e) = q.pop_front() {
                    out.push(e);
                }
            }
        }
    }
    out.sort_by(|a, b| a.id.cmp(&b.id));
    Ok(out)
}

/// One position spec resolved against a steps schema: `(column, dim indices)`.
type PositionSpec = Vec<(String, Vec<usize>)>;

/// Parses `key` or `key[i,j]` position keys against the observation keys of a batch.
fn resolve_positions(keys: &[String], obs: &[(String, usize)]) -> Result<Option<PositionSpec>, String> {
    if keys.is_empty() {
        return Ok(obs
            .iter()
            .find(|(_, d)| *d == 2 || *d == 3)
            .map(|(k, d)| vec![(k.clone(), (0..*d).collect())]));
    }
    let mut spec = Vec::new();
    for raw in keys {
        let raw = raw.trim();
        let (key, idx) = match raw.split_once('[') {
            Some((k, rest)) => {
                let inner =
                    rest.strip_suffix(']').ok_or_else(|| format!("position key {raw:?}: missing ']'"))?;
                let idx = inner
                    .split(',')
                    .map(|s| {
                        s.trim()
                            .parse::<usize>()
                            .map_err(|_| format!("position key {raw:?}: bad index {s:?}"))
                    })
                    .collect::<Result<Vec<_>, _>>()?;
                (k.trim(), Some(idx))
            }
            None => (raw, None),
        };
        let key = key.strip_prefix(store::steps::OBS_PREFIX).unwrap_or(key);
        let Some((_, dim)) = obs.iter().find(|(k, _)| k == key) else {
            return Ok(None);
        };
        let idx = idx.unwrap_or_else(|| (0..*dim).collect());
        if let Some(bad) = idx.iter().find(|&&i| i >= *dim) {
            return Err(format!("position key {raw:?}: index {bad} out of range (dim {dim})"));
        }
        spec.push((key.to_string(), idx));
    }
    let total: usize = spec.iter().map(|(_, i)| i.len()).sum();
    if total != 2 && total != 3 {
        return Err(format!("position keys {keys:?} give {total} dims, expected 2 or 3"));
    }
    Ok(Some(spec))
}

fn spec_names(spec: &PositionSpec) -> Vec<String> {
    spec.iter().flat_map(|(k, idx)| idx.iter().map(move |i| format!("{k}[{i}]"))).collect()
}

/// Per-step score sums of one label.
#[derive(Default)]
struct ScoreAcc {
    sum: Vec<f64>,
    count: Vec<u32>,
    total: f64,
    n: u64,
}

impl ScoreAcc {
    fn add(&mut self, scores: &[f32]) {
        if self.sum.len() < scores.len() {
            self.sum.resize(scores.len(), 0.0);
            self.count.resize(scores.len(), 0);
        }
        for (i, s) in scores.iter().enumerate() {
            if s.is_finite() {
                self.sum[i] += *s as f64;
                self.count[i] += 1;
                self.total += *s as f64;
                self.n += 1;
            }
        }
    }
    fn means(&self) -> Vec<Option<f64>> {
        self.sum.iter().zip(&self.count).map(|(s, &c)| (c > 0).then(|| s / c as f64)).collect()
    }
    fn mean(&self) -> Option<f32> {
        (self.n > 0).then(|| (self.total / self.n as f64) as f32)
    }
}

struct EpisodeEntities {
    /// Position in the episode listing (episodes are logged as they arrive from the store).
    index: usize,
    base: String,
    label: Label,
    has_score: bool,
    /// `(camera key, entity path)` of each camera logged, in the steps' column order.
    cameras: Vec<(String, String)>,
}

fn indexes(t: &[i64], ts: &[f64]) -> [TimeColumn; 2] {
    [
        TimeColumn::new_sequence("step", t.iter().copied()),
        TimeColumn::new_duration_secs("time", ts.iter().copied()),
    ]
}

fn f64_col<'a>(batch: &'a RecordBatch, name: &str) -> Result<&'a Float64Array, ViewError> {
    batch
        .column_by_name(name)
        .and_then(|c| c.as_any().downcast_ref::<Float64Array>())
        .ok_or_else(|| ViewError::Invalid(format!("steps have no float64 column {name:?}")))
}

/// The stream plus the entity paths written so far.
struct Out<'a> {
    rec: &'a RecordingStream,
    entities: HashSet<String>,
    /// Video object (store key) → its AssetVideo entity: each video is embedded once, however
    /// many episodes share it (LeRobot v3.0 keeps a camera's episodes in one mp4).
    videos: HashMap<String, String>,
}

/// One episode's step indexes: `t` and its `timestamp` (seconds since the episode start).
#[derive(Clone, Copy)]
struct StepIndex<'a> {
    t: &'a [i64],
    ts: &'a [f64],
}

impl StepIndex<'_> {
    /// The `step` and `time` columns of the rows `rows`.
    fn of(&self, rows: impl Iterator<Item = usize> + Clone) -> [TimeColumn; 2] {
        indexes(
            &rows.clone().map(|i| self.t[i]).collect::<Vec<_>>(),
            &rows.map(|i| self.ts[i]).collect::<Vec<_>>(),
        )
    }
}

/// An image column's frames as byte slices (Binary or LargeBinary), `None` where null.
fn binary_frames(col: &dyn Array) -> Option<Vec<Option<&[u8]>>> {
    if let Some(a) = col.as_any().downcast_ref::<BinaryArray>() {
        return Some((0..a.len()).map(|i| a.is_valid(i).then(|| a.value(i))).collect());
    }
    let a = col.as_any().downcast_ref::<LargeBinaryArray>()?;
    Some((0..a.len()).map(|i| a.is_valid(i).then(|| a.value(i))).collect())
}

impl Out<'_> {
    fn send(
        &mut self,
        path: String,
        idx: &[TimeColumn],
        cols: Vec<re_sdk::SerializedComponentColumn>,
    ) -> Result<(), ViewError> {
        self.rec.send_columns(path.as_str(), idx.iter().cloned(), cols).map_err(rr)?;
        self.entities.insert(path);
        Ok(())
    }

    /// An image-column camera: one EncodedImage per kept step (every `stride`-th, non-null),
    /// the stored bytes as they are with their media type. Returns the frames logged.
    fn image_camera(
        &mut self,
        batch: &RecordBatch,
        key: &str,
        media: MediaType,
        stride: usize,
        path: &str,
        at: StepIndex<'_>,
    ) -> Result<usize, ViewError> {
        let Some(frames) = batch
            .column_by_name(&format!("{}{key}", store::steps::IMAGE_PREFIX))
            .and_then(|c| binary_frames(c))
        else {
            return Err(ViewError::Invalid(format!("image column {key:?} is not binary")));
        };
        let rows: Vec<usize> =
            (0..frames.len()).step_by(stride.max(1)).filter(|&i| frames[i].is_some()).collect();
        if rows.is_empty() {
            return Ok(0);
        }
        let arch = EncodedImage::update_fields()
            .with_many_blob(rows.iter().map(|&i| frames[i].unwrap_or_default().to_vec()))
            .with_many_media_type(vec![media; rows.len()]);
        let cols = arch.columns_of_unit_batches().map_err(rr)?.collect::<Vec<_>>();
        self.send(path.to_string(), &at.of(rows.iter().copied()), cols)?;
        Ok(rows.len())
    }

    /// A video camera (`media.<key>.path` / `.timestamp`): each video object it references is
    /// logged once, static, as an AssetVideo at `media/<key>/<file>`; every step becomes a
    /// VideoFrameReference to it at the step's frame time inside the video (in a v3.0 file
    /// shared by many episodes, the episode's own span of it). Returns (videos embedded now,
    /// frame references).
    async fn video_camera(
        &mut self,
        store: &Store,
        batch: &RecordBatch,
        key: &str,
        path: &str,
        at: StepIndex<'_>,
    ) -> Result<(usize, usize), ViewError> {
        let n = batch.num_rows();
        let paths = batch
            .column_by_name(&format!("{}{key}.path", store::steps::MEDIA_PREFIX))
            .and_then(|c| c.as_any().downcast_ref::<StringArray>())
            .ok_or_else(|| ViewError::Invalid(format!("media column {key:?} is not utf8")))?;
        let times = f64_col(batch, &format!("{}{key}.timestamp", store::steps::MEDIA_PREFIX))?;
        let part = re_sdk::EntityPathPart::from(key).escaped_string();
        let (mut videos, mut frames) = (0, 0);
        // Consecutive runs of the same video object (usually one per episode).
        let mut row = 0;
        while row < n {
            if !paths.is_valid(row) {
                row += 1;
                continue;
            }
            let obj = paths.value(row).to_string();
            let end = (row..n).find(|&i| !paths.is_valid(i) || paths.value(i) != obj).unwrap_or(n);
            let video_path = match self.videos.get(&obj) {
                Some(p) => p.clone(),
                None => {
                    let data = store.get_object(&obj).await?;
                    let file = obj.rsplit('/').next().unwrap_or(&obj);
                    let file = re_sdk::EntityPathPart::from(file).escaped_string();
                    let vpath = format!("media/{part}/{file}");
                    let media =
                        MediaType::guess_from_path(&obj).or_else(|| MediaType::guess_from_data(&data));
                    self.rec
                        .log_static(vpath.as_str(), &AssetVideo::from_file_contents(data.to_vec(), media))
                        .map_err(rr)?;
                    self.entities.insert(vpath.clone());
                    self.videos.insert(obj.clone(), vpath.clone());
                    videos += 1;
                    vpath
                }
            };
            let k = end - row;
            let arch = VideoFrameReference::update_fields()
                .with_many_timestamp((row..end).map(|i| VideoTimestamp::from_secs(times.value(i))))
                .with_many_video_reference(vec![video_path; k]);
            let cols = arch.columns_of_unit_batches().map_err(rr)?.collect::<Vec<_>>();
            self.send(path.to_string(), &at.of(row..end), cols)?;
            frames += k;
            row = end;
        }
        Ok((videos, frames))
    }

    /// A scalar series entity of `dim` series (named `names`), `values` row-major over the steps.
    fn series(
        &mut self,
        idx: &[TimeColumn],
        color: Color,
        path: String,
        names: Vec<String>,
        dim: usize,
        values: Vec<f32>,
    ) -> Result<(), ViewError> {
        self.rec
            .log_static(path.as_str(), &SeriesLines::new().with_colors(vec![color; dim]).with_names(names))
            .map_err(rr)?;
        let n = values.len() / dim.max(1);
        let values: Vec<f64> = values.into_iter().map(f64::from).collect();
        let cols = Scalars::new(values).columns(std::iter::repeat_n(dim, n)).map_err(rr)?.collect();
        self.send(path, idx, cols)
    }
}

/// Logs everything; shared by the file and the in-memory writers.
async fn record(
    rec: &RecordingStream,
    store: &Store,
    opts: &ViewOptions,
    scorer: Option<&dyn StepScorer>,
) -> Result<ViewReport, ViewError> {
    let episodes = select_episodes(store, opts).await?;
    let mut report = ViewReport { scored: scorer.is_some(), ..Default::default() };
    let mut out = Out { rec, entities: HashSet::new(), videos: HashMap::new() };
    let mut logged: Vec<EpisodeEntities> = Vec::new();
    let mut acc: HashMap<Label, ScoreAcc> = HashMap::new();
    let mut lengths: HashMap<Label, Vec<usize>> = HashMap::new();
    let mut pos_dims: Option<usize> = None;
    let stride = opts.image_stride.max(1);

    // The episodes' steps are read in one pass grouped by steps file (each row group once) and
    // logged as they arrive, one episode (its frames included) in memory at a time; the
    // blueprint orders them back by the listing.
    let locations =
        episodes.iter().map(store::EpisodeLocation::try_from).collect::<Result<Vec<_>, StoreError>>()?;
    let mut steps = store.read_episodes(locations);
    let mut seen = vec![false; episodes.len()];
    let mut cameras_seen: BTreeSet<String> = BTreeSet::new();
    while let Some(item) = steps.next().await {
        let item = item.map_err(StoreError::from)?;
        let i = item.index;
        let (Some(ep), batch) = (episodes.get(i), item.steps) else {
            return Err(
                StoreError::Corrupt(format!("the read returned episode #{i} of {}", episodes.len())).into()
            );
        };
        seen[i] = true;
        let n = batch.num_rows();
        if n == 0 {
            continue;
        }
        let label = ep.label;
        let color = label_color(label);
        let base = episode_path(label, &ep.id);
        let t: Vec<i64> =
            match batch.column_by_name("t").and_then(|c| c.as_any().downcast_ref::<Int32Array>()) {
                Some(a) => a.values().iter().map(|&v| v as i64).collect(),
                None => (0..n as i64).collect(),
            };
        let ts: Vec<f64> = f64_col(&batch, "timestamp")?.values().to_vec();
        let idx = indexes(&t, &ts);
        let obs = store::steps::observation_keys(batch.schema().as_ref());
        report.episodes += 1;
        report.steps += n;
        match label {
            Label::Success => report.success += 1,
            Label::Failure => report.failure += 1,
            Label::Unknown => report.unknown += 1,
        }
        lengths.entry(label).or_default().push(n);
        // Trajectory: a static strip (the whole path) and a point per step (where it is now).
        let spec = resolve_positions(&opts.position_keys, &obs).map_err(ViewError::Invalid)?;
        match spec {
            Some(spec) => {
                let mut cols: Vec<(usize, Vec<f32>)> = Vec::new();
                for (key, _) in &spec {
                    cols.push(store::steps::vector_column(
                        &batch,
                        &format!("{}{key}", store::steps::OBS_PREFIX),
                    )?);
                }
                let pts: Vec<Vec<f32>> = (0..n)
                    .map(|row| {
                        spec.iter()
                            .zip(&cols)
                            .flat_map(|((_, idx), (dim, vals))| idx.iter().map(move |&i| vals[row * dim + i]))
                            .collect()
                    })
                    .collect();
                let d = pts[0].len();
                if report.position_dims.is_empty() {
                    report.position_dims = spec_names(&spec);
                }
                if *pos_dims.get_or_insert(d) != d {
                    return Err(ViewError::Invalid(format!(
                        "episode {} has a {d}-D position, earlier episodes {}-D",
                        ep.id,
                        pos_dims.unwrap_or(0)
                    )));
                }
                let strip_path = format!("{base}/trajectory");
                let point_path = format!("{base}/position");
                let lbl = format!("{} {}", ep.id, label);
                if d == 2 {
                    let p2: Vec<[f32; 2]> = pts.iter().map(|p| [p[0], p[1]]).collect();
                    rec.log_static(
                        strip_path.as_str(),
                        &LineStrips2D::new([p2.clone()]).with_colors([color]).with_labels([lbl]),
                    )
                    .map_err(rr)?;
                    let arch = Points2D::new(p2).with_colors(vec![color; n]).with_radii(vec![0.02f32; n]);
                    out.send(point_path, &idx, arch.columns_of_unit_batches().map_err(rr)?.collect())?;
                } else {
                    let p3: Vec<[f32; 3]> = pts.iter().map(|p| [p[0], p[1], p[2]]).collect();
                    rec.log_static(
                        strip_path.as_str(),
                        &LineStrips3D::new([p3.clone()]).with_colors([color]).with_labels([lbl]),
                    )
                    .map_err(rr)?;
                    let arch = Points3D::new(p3).with_colors(vec![color; n]).with_radii(vec![0.01f32; n]);
                    out.send(point_path, &idx, arch.columns_of_unit_batches().map_err(rr)?.collect())?;
                }
                out.entities.insert(strip_path);
            }
            None => report.without_position += 1,
        }

        // Action and state dims as scalar series, coloured by label.
        if let Ok((dim, values)) = store::steps::vector_column(&batch, "action") {
            let names = (0..dim).map(|i| format!("action[{i}]")).collect();
            out.series(&idx, color, format!("{base}/action"), names, dim, values)?;
        }
        for (key, dim) in &obs {
            if *dim > MAX_STATE_DIMS {
                continue;
            }
            let (dim, values) =
                store::steps::vector_column(&batch, &format!("{}{key}", store::steps::OBS_PREFIX))?;
            let names = (0..dim).map(|i| format!("{key}[{i}]")).collect();
            let part = re_sdk::EntityPathPart::from(key.as_str()).escaped_string();
            out.series(&idx, color, format!("{base}/state/{part}"), names, dim, values)?;
        }
        if let Some(r) = batch
            .column_by_name("reward")
            .and_then(|c| c.as_any().downcast_ref::<arrow::array::Float32Array>())
        {
            let vals: Vec<f32> = (0..n).map(|i| if r.is_valid(i) { r.value(i) } else { f32::NAN }).collect();
            out.series(&idx, color, format!("{base}/reward"), vec!["reward".into()], 1, vals)?;
        }

        // The verifier's score along the episode.
        let mut has_score = false;
        if let Some(sc) = scorer {
            let scores = sc
                .score_steps(&batch)
                .map_err(|e| ViewError::Scorer { episode: ep.id.clone(), message: e.to_string() })?;
            if scores.len() != n {
                return Err(ViewError::Scorer {
                    episode: ep.id.clone(),
                    message: format!("{} scores for {n} steps", scores.len()),
                });
            }
            acc.entry(label).or_default().add(&scores);
            out.series(&idx, color, format!("{base}/score"), vec!["score".into()], 1, scores)?;
            has_score = true;
        }

        // Cameras, in the steps' column order: a video (LeRobot mp4) as one static AssetVideo
        // per object plus a VideoFrameReference per step; an image column as one EncodedImage
        // per step, the stored bytes (PNG, or JPEG as recorded) with their media type.
        let mut cameras: Vec<(String, String)> = Vec::new();
        for cam in store::cameras_of(batch.schema().as_ref()) {
            let part = re_sdk::EntityPathPart::from(cam.name.as_str()).escaped_string();
            let at = StepIndex { t: &t, ts: &ts };
            let logged_frames = match cam.kind {
                store::CameraKind::Video if !opts.no_videos => {
                    let cam_path = format!("{base}/camera/{part}");
                    let (videos, frames) = out.video_camera(store, &batch, &cam.name, &cam_path, at).await?;
                    report.videos += videos;
                    report.video_frames += frames;
                    (frames > 0).then_some(cam_path)
                }
                store::CameraKind::Image if !opts.no_images => {
                    let img_path = format!("{base}/image/{part}");
                    let media = match cam.encoding.as_deref() {
                        Some("jpeg") => MediaType::jpeg(),
                        _ => MediaType::png(),
                    };
                    let frames = out.image_camera(&batch, &cam.name, media, stride, &img_path, at)?;
                    report.images += frames;
                    (frames > 0).then_some(img_path)
                }
                _ => None,
            };
            if let Some(path) = logged_frames {
                cameras_seen.insert(cam.name.clone());
                cameras.push((cam.name.clone(), path));
            }
        }
        tracing::debug!(episode = %ep.id, steps = n, label = %label, "recorded episode");
        logged.push(EpisodeEntities { index: i, base, label, has_score, cameras });
    }

    if let Some(i) = seen.iter().position(|s| !s) {
        return Err(StoreError::Corrupt(format!("episode {} was not read", episodes[i].id)).into());
    }
    logged.sort_by_key(|e| e.index);
    report.cameras = cameras_seen.into_iter().collect();

    if !opts.position_keys.is_empty() && report.episodes > 0 && report.without_position == report.episodes {
        return Err(ViewError::Invalid(format!(
            "no episode has the position keys {:?} among its observation keys",
            opts.position_keys
        )));
    }

    // Summary: mean score of successes vs failures per step, and their gap.
    if scorer.is_some() {
        let empty = ScoreAcc::default();
        let s = acc.get(&Label::Success).unwrap_or(&empty);
        let f = acc.get(&Label::Failure).unwrap_or(&empty);
        report.mean_score_success = s.mean();
        report.mean_score_failure = f.mean();
        for (name, a, color) in [("success", s, GREEN), ("failure", f, RED)] {
            let means = a.means();
            let steps: Vec<i64> = (0..means.len() as i64).filter(|&i| means[i as usize].is_some()).collect();
            if steps.is_empty() {
                continue;
            }
            let vals: Vec<f64> = means.iter().flatten().copied().collect();
            let path = format!("summary/score/{name}");
            rec.log_static(
                path.as_str(),
                &SeriesLines::new()
                    .with_colors([color])
                    .with_names([format!("mean score ({name})")])
                    .with_widths([3.0f32]),
            )
            .map_err(rr)?;
            let cols = Scalars::new(vals).columns_of_unit_batches().map_err(rr)?.collect::<Vec<_>>();
            out.send(path, &[TimeColumn::new_sequence("step", steps)], cols)?;
        }
        let (sm, fm) = (s.means(), f.means());
        let gap: Vec<(i64, f64)> = sm
            .iter()
            .zip(&fm)
            .enumerate()
            .filter_map(|(i, (a, b))| Some((i as i64, (*a)? - (*b)?)))
            .collect();
        if !gap.is_empty() {
            let path = "summary/score/gap";
            rec.log_static(
                path,
                &SeriesLines::new()
                    .with_colors([BLUE])
                    .with_names(["success − failure"])
                    .with_widths([2.0f32]),
            )
            .map_err(rr)?;
            let cols = Scalars::new(gap.iter().map(|g| g.1))
                .columns_of_unit_batches()
                .map_err(rr)?
                .collect::<Vec<_>>();
            out.send(path.to_string(), &[TimeColumn::new_sequence("step", gap.iter().map(|g| g.0))], cols)?;
            let (best_step, best) =
                gap.iter().copied().fold((0, f64::NEG_INFINITY), |acc, g| if g.1 > acc.1 { g } else { acc });
            report.max_separation = Some((best_step, best as f32));
            if best > 0.0 {
                // The earliest step after which the gap never drops below half its maximum.
                let mut from = None;
                for (i, g) in gap.iter().rev() {
                    if *g >= best / 2.0 {
                        from = Some(*i);
                    } else {
                        break;
                    }
                }
                report.separates_from_step = from;
            }
        }
    }
    rec.log_static(
        "summary/info",
        &TextDocument::new(summary_markdown(opts, &report, &lengths)).with_media_type(MediaType::markdown()),
    )
    .map_err(rr)?;
    out.entities.insert("summary/info".into());

    let bp = blueprint(&logged, pos_dims, scorer.is_some());
    bp.send(rec, BlueprintActivation { make_active: true, make_default: true }).map_err(rr)?;

    let mut ents: Vec<String> = out.entities.into_iter().collect();
    ents.sort();
    report.entities = ents;
    Ok(report)
}

fn summary_markdown(opts: &ViewOptions, r: &ViewReport, lengths: &HashMap<Label, Vec<usize>>) -> String {
    let mut s = format!("# {} / {}\n\n", opts.policy, opts.checkpoint);
    if let Some(split) = &opts.split_id {
        s.push_str(&format!("split `{split}`\n\n"));
    }
    s.push_str("| label | episodes | mean length |\n|---|---|---|\n");
    for (l, n) in [(Label::Success, r.success), (Label::Failure, r.failure), (Label::Unknown, r.unknown)] {
        let lens = lengths.get(&l).map(Vec::as_slice).unwrap_or(&[]);
        let mean = if lens.is_empty() { 0.0 } else { lens.iter().sum::<usize>() as f64 / lens.len() as f64 };
        s.push_str(&format!("| {l} | {n} | {mean:.1} |\n"));
    }
    if !r.position_dims.is_empty() {
        s.push_str(&format!("\ntrajectory: {}\n", r.position_dims.join(", ")));
    }
    if r.scored {
        let f = |x: Option<f32>| x.map(|v| format!("{v:.3}")).unwrap_or_else(|| "–".into());
        s.push_str(&format!(
            "\nverifier score: mean {} on successes, {} on failures\n",
            f(r.mean_score_success),
            f(r.mean_score_failure)
        ));
        if let Some((step, gap)) = r.max_separation {
            s.push_str(&format!("\nlargest gap {gap:.3} at step {step}"));
            if let Some(from) = r.separates_from_step {
                s.push_str(&format!("; gap ≥ half of it from step {from} on"));
            }
            s.push('\n');
        }
    }
    s
}

/// Trajectories (2-D or 3-D) left; score, action and state plots right; cameras below them.
fn blueprint(eps: &[EpisodeEntities], pos_dims: Option<usize>, scored: bool) -> Blueprint {
    let mut spatial_excl: Vec<String> = vec!["+ /episodes/**".into()];
    for e in eps.iter().filter(|e| !e.cameras.is_empty()) {
        spatial_excl.push(format!("- /{}/camera/**", e.base));
        spatial_excl.push(format!("- /{}/image/**", e.base));
    }
    let trajectories: ContainerLike = match pos_dims {
        Some(3) => Spatial3DView::new("trajectories").with_origin("/").with_contents(spatial_excl).into(),
        _ => Spatial2DView::new("trajectories").with_origin("/").with_contents(spatial_excl).into(),
    };
    let per_ep = |suffix: &str, only: &dyn Fn(&EpisodeEntities) -> bool| -> Vec<String> {
        eps.iter().filter(|e| only(e)).map(|e| format!("+ /{}/{suffix}", e.base)).collect()
    };
    let mut plots: Vec<ContainerLike> = Vec::new();
    if scored {
        let mut c = vec!["+ /summary/score/**".to_string()];
        c.extend(per_ep("score", &|e| e.has_score));
        plots.push(TimeSeriesView::new("verifier score").with_origin("/").with_contents(c).into());
    }
    plots.push(
        TimeSeriesView::new("actions").with_origin("/").with_contents(per_ep("action", &|_| true)).into(),
    );
    let mut state = per_ep("state/**", &|_| true);
    state.extend(per_ep("reward", &|_| true));
    plots.push(TimeSeriesView::new("state & reward").with_origin("/").with_contents(state).into());
    // Camera views: a success and a failure first, then whatever comes; one row per episode
    // with each of its cameras side by side (at most 8 views, at most 4 episodes).
    let per_row = eps.iter().map(|e| e.cameras.len()).max().unwrap_or(0);
    let max_eps = 8usize.checked_div(per_row).map_or(0, |k| k.clamp(1, 4));
    let shown =
        eps.iter().filter(|e| !e.cameras.is_empty()).fold(Vec::<&EpisodeEntities>::new(), |mut v, e| {
            if v.len() < max_eps && (v.iter().all(|x| x.label != e.label) || v.len() >= 2) {
                v.push(e);
            }
            v
        });
    let mut cams: Vec<ContainerLike> = Vec::new();
    for e in shown {
        let name = e.base.trim_start_matches("episodes/").to_string();
        for (key, path) in &e.cameras {
            cams.push(
                Spatial2DView::new(format!("{name} · {key}"))
                    .with_origin(format!("/{path}"))
                    .with_contents([format!("+ /{path}")])
                    .into(),
            );
        }
    }
    let right: ContainerLike = Vertical::new(plots).into();
    let root: ContainerLike = if cams.is_empty() {
        Horizontal::new([trajectories, right]).into()
    } else {
        let grid = Grid::new(cams).with_grid_columns(per_row as u32);
        let left: ContainerLike = Vertical::new([trajectories, grid.into()]).into();
        Horizontal::new([left, right]).into()
    };
    Blueprint::new(root).with_auto_views(false)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn position_keys_resolve() {
        let obs = vec![("agent".to_string(), 5), ("pos".to_string(), 2), ("eef".to_string(), 3)];
        assert_eq!(resolve_positions(&[], &obs).unwrap(), Some(vec![("pos".into(), vec![0, 1])]));
        assert_eq!(
            resolve_positions(&["eef".into()], &obs).unwrap(),
            Some(vec![("eef".into(), vec![0, 1, 2])])
        );
        assert_eq!(
            resolve_positions(&["obs.agent[3, 4]".into()], &obs).unwrap(),
            Some(vec![("agent".into(), vec![3, 4])])
        );
        assert!(resolve_positions(&["agent".into()], &obs).is_err(), "5 dims");
        assert!(resolve_positions(&["agent[9,1]".into()], &obs).is_err());
        assert_eq!(resolve_positions(&["missing".into()], &obs).unwrap(), None);
    }

    #[test]
    fn episode_paths_escape_ids() {
        assert_eq!(episode_path(Label::Success, "abc123-4"), "episodes/success/abc123-4");
        assert!(!episode_path(Label::Failure, "a/b").ends_with("a/b"));
    }
}
