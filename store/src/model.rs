//! Plain data types shared by the store's writers and readers.

use serde::{Deserialize, Serialize};

/// An episode's success label.
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Label {
    Success,
    Failure,
    Unknown,
}

impl Label {
    pub fn as_str(self) -> &'static str {
        match self {
            Label::Success => "success",
            Label::Failure => "failure",
            Label::Unknown => "unknown",
        }
    }
    /// `Some(true)` for success, `Some(false)` for failure, `None` when unknown.
    pub fn as_bool(self) -> Option<bool> {
        match self {
            Label::Success => Some(true),
            Label::Failure => Some(false),
            Label::Unknown => None,
        }
    }
    pub fn from_bool(b: Option<bool>) -> Self {
        match b {
            Some(true) => Label::Success,
            Some(false) => Label::Failure,
            None => Label::Unknown,
        }
    }
}

impl std::str::FromStr for Label {
    type Err = crate::StoreError;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s.to_ascii_lowercase().as_str() {
            "success" | "true" | "s" => Ok(Label::Success),
            "failure" | "false" | "f" => Ok(Label::Failure),
            "unknown" | "null" | "u" => Ok(Label::Unknown),
            other => Err(crate::StoreError::invalid(format!(
                "unknown label {other:?}: expected success, failure or unknown"
            ))),
        }
    }
}

impl std::fmt::Display for Label {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.as_str())
    }
}

/// A per-step float vector column (`FixedSizeList<Float32>` of `dim` in Parquet), row-major.
#[derive(Debug, Clone, PartialEq)]
pub struct VectorColumn {
    pub name: String,
    pub dim: usize,
    /// `steps * dim` values.
    pub values: Vec<f32>,
}

/// Predicted action chunks, one `horizon x action_dim` chunk per step (flattened row-major).
#[derive(Debug, Clone, PartialEq)]
pub struct ChunkColumn {
    pub horizon: usize,
    pub action_dim: usize,
    pub values: Vec<f32>,
}

/// Per-step images, each stored losslessly as encoded bytes: PNG, or JPEG kept exactly as the
/// source recorded it (ALOHA's compressed cameras; never re-encoded). `shape` is `[H, W, C]`.
#[derive(Debug, Clone, PartialEq)]
pub struct ImageColumn {
    pub name: String,
    pub shape: [usize; 3],
    /// One encoded frame per step (PNG, or JPEG: see [`ImageColumn::encoding`]).
    pub png_frames: Vec<Vec<u8>>,
}

impl ImageColumn {
    /// `jpeg` when every frame starts with a JPEG's start-of-image marker, else `png` (recorded
    /// as the column's `ufops.encoding`).
    pub fn encoding(&self) -> &'static str {
        let jpeg =
            !self.png_frames.is_empty() && self.png_frames.iter().all(|f| f.starts_with(&[0xFF, 0xD8, 0xFF]));
        if jpeg {
            "jpeg"
        } else {
            "png"
        }
    }
}

/// Per-step references into a video stored in the object store (content-addressed by sha256).
#[derive(Debug, Clone, PartialEq)]
pub struct MediaColumn {
    pub name: String,
    /// The media object's sha256 (see [`MediaFile`]).
    pub sha256: String,
    /// Time of each step's frame inside the media file, in seconds.
    pub timestamps: Vec<f64>,
}

/// A media file (e.g. an mp4) to be copied into the store, content-addressed.
#[derive(Debug, Clone, PartialEq)]
pub struct MediaFile {
    pub sha256: String,
    pub local_path: std::path::PathBuf,
    /// e.g. `video/mp4`
    pub content_type: String,
    pub size_bytes: u64,
}

/// One episode as produced by an ingester.
#[derive(Debug, Clone, PartialEq)]
pub struct EpisodeInput {
    /// Name of the episode inside its source (`demo_3`, `episode_000002`, `episode 1`).
    pub source_name: String,
    /// Index of the episode inside its source (0-based, in the source's natural order).
    pub source_index: u32,
    pub task: Option<String>,
    pub label: Label,
    /// Where the label came from, e.g. `sidecar:lift.success.json`, `rewards>=1`, `lerobot:next.success`.
    pub label_source: String,
    pub tags: Vec<String>,
    /// Free-form per-episode metadata (JSON object).
    pub metadata: serde_json::Value,
    /// Step times in seconds since the episode start (len = steps).
    pub timestamps: Vec<f64>,
    pub observations: Vec<VectorColumn>,
    /// The executed action; `dim` 0 (no values) when the source recorded none for this episode
    /// (e.g. an MCAP episode without action messages): the steps then have no `action` column.
    pub action: VectorColumn,
    pub reward: Vec<f32>,
    pub done: Vec<bool>,
    pub action_chunk: Option<ChunkColumn>,
    pub images: Vec<ImageColumn>,
    pub media: Vec<MediaColumn>,
    /// Per-step flags of human involvement (takeovers, validity) when the source recorded them.
    pub flags: StepFlags,
}

/// Per-step flags a recording may carry beside its data, kept as the steps columns
/// `intervention` and `validity` (each only when the source has it).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct StepFlags {
    /// `true` where a human controlled the robot instead of the policy: LeRobot's DAgger
    /// recordings (`lerobot-rollout --strategy dagger`) mark each such frame `intervention`.
    pub intervention: Option<Vec<bool>>,
    /// `false` where a person marked the step invalid (GR00T's `annotation.human.validity`).
    pub validity: Option<Vec<bool>>,
}

impl StepFlags {
    /// The first step a human controlled, if any: the steps before it are the policy's own.
    pub fn first_intervention(&self) -> Option<usize> {
        self.intervention.as_ref()?.iter().position(|&b| b)
    }

    /// How many steps a human controlled (`None`: the source records no takeovers).
    pub fn intervention_steps(&self) -> Option<usize> {
        Some(self.intervention.as_ref()?.iter().filter(|&&b| b).count())
    }
}

impl EpisodeInput {
    pub fn len(&self) -> usize {
        self.timestamps.len()
    }
    pub fn is_empty(&self) -> bool {
        self.timestamps.is_empty()
    }
}

/// A per-step array of the source that the step model has no place for (robomimic `states`,
/// `next_obs/<key>`, large demo attributes), kept so an export can give the source back. Stored
/// as the steps column `extra.<name>`; `values` has one row per step (null rows allowed), any
/// Arrow type; `metadata` becomes the field's metadata (e.g. `ufops.dtype`, `ufops.shape`).
/// Passed beside the episode ([`crate::IngestWriter::push_episode_with_extras`]).
#[derive(Debug, Clone)]
pub struct ExtraColumn {
    pub name: String,
    pub values: arrow::array::ArrayRef,
    pub metadata: std::collections::HashMap<String, String>,
}

impl PartialEq for ExtraColumn {
    fn eq(&self, other: &Self) -> bool {
        self.name == other.name
            && self.metadata == other.metadata
            && self.values.to_data() == other.values.to_data()
    }
}

/// What was ingested: a file or folder, identified by the sha256 of its content.
#[derive(Debug, Clone, PartialEq)]
pub struct SourceInput {
    /// The path as the user gave it (for provenance only).
    pub path: String,
    pub sha256: String,
    /// `robomimic`, `lerobot`, `mcap`, `sim`, ...
    pub format: String,
    pub size_bytes: u64,
    /// Format-specific metadata (robomimic `env_args`, LeRobot `info.json` bits, ...).
    pub metadata: serde_json::Value,
}

/// The rule for every name the store keeps (policy, checkpoint, task, run, alias, layer, actor…):
/// 1-200 printable characters without surrounding spaces.
pub(crate) fn check_name(what: &str, s: &str) -> Result<(), crate::StoreError> {
    if s.is_empty() || s.chars().count() > 200 || s.chars().any(|c| c.is_control()) || s.trim() != s {
        return Err(crate::StoreError::invalid(format!(
            "invalid {what} name {s:?}: 1-200 printable characters without surrounding spaces"
        )));
    }
    Ok(())
}
