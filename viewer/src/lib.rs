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
//!
//! The code follows those steps: `selection` picks the episodes, `recording` logs each one
//! (trajectories, actions, state, scores, cameras) and the summary, `blueprint` lays them out.

mod blueprint;
mod recording;
mod selection;

use re_sdk::RecordingStreamBuilder;
use std::path::Path;
use store::{Store, StoreError};

pub use recording::episode_path;
pub use verifier::StepScorer;

/// The re_sdk version the recordings are written with (the PyPI `rerun-sdk` to read them).
pub const RERUN_SDK_VERSION: &str = "0.36.3";
/// Application id of the recordings.
pub const APPLICATION_ID: &str = "ufops";
/// Observation keys wider than this are not plotted as scalar series (images, features).
pub const MAX_STATE_DIMS: usize = 64;

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
    /// Episodes that logged their best-of-N steps (steering telemetry), drawn as the
    /// candidates' score spread and the chosen candidate's score at each of those steps.
    pub steered_episodes: usize,
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

pub(crate) fn rr<E: std::fmt::Display>(e: E) -> ViewError {
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
    let report = recording::record(&rec, store, opts, scores).await;
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
    let report = recording::record(&rec, store, opts, scores).await?;
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
