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

/// Per-step images of one camera, each stored losslessly as encoded bytes: PNG, or JPEG kept
/// exactly as the source recorded it (ALOHA's compressed cameras; never re-encoded). `shape` is
/// `[H, W, C]`.
///
/// The frames are [`Frames`]: either all in memory, or a [`FrameStream`] that the reader fills
/// while the consumer pulls it, so an episode's frames never sit in memory together (an ALOHA
/// episode is 0.5-2 GB of raw frames). The store's writer pulls a stream a page at a time
/// (`steps::PAGE_MAX_BYTES` of frames) and spills each page to a temporary file, so its memory
/// is bounded by a page per camera whatever the episode's length.
///
/// Consuming the frames elsewhere (a video encoder, a checker): take them with
/// [`ImageColumn::into_frames`] (or `std::mem::take(&mut column.frames)`) and iterate — every
/// [`Frames`] turns into an iterator of `Result<Vec<u8>, StoreError>`, one encoded frame per
/// step in order; the error names what could not be read (a stream reports a short or unreadable source
/// there, and yields nothing after it). [`Frames::collect_encoded`] gathers them (tests, small
/// episodes).
#[derive(Debug, PartialEq)]
pub struct ImageColumn {
    pub name: String,
    pub shape: [usize; 3],
    /// One encoded frame per step (PNG, or JPEG: see [`ImageColumn::encoding`]).
    pub frames: Frames,
}

impl ImageColumn {
    /// `jpeg` when every frame starts with a JPEG's start-of-image marker (in-memory frames), or
    /// when the stream says so; else `png` (recorded as the column's `ufops.encoding`).
    pub fn encoding(&self) -> &'static str {
        match &self.frames {
            Frames::Encoded(f) => {
                if !f.is_empty() && f.iter().all(|f| is_jpeg(f)) {
                    "jpeg"
                } else {
                    "png"
                }
            }
            Frames::Stream(s) => s.encoding,
        }
    }

    /// The frames, leaving an empty column behind.
    pub fn into_frames(self) -> Frames {
        self.frames
    }
}

/// Starts with a JPEG's start-of-image marker.
pub fn is_jpeg(frame: &[u8]) -> bool {
    frame.starts_with(&[0xFF, 0xD8, 0xFF])
}

/// One encoded frame, or why it could not be produced.
pub type FrameResult = Result<Vec<u8>, crate::StoreError>;

/// The encoded frames of one camera, in step order (see [`ImageColumn`]). Either way it turns
/// into an iterator of [`FrameResult`]s (`IntoIterator`).
pub enum Frames {
    /// Every frame in memory.
    Encoded(Vec<Vec<u8>>),
    /// Frames produced as they are pulled.
    Stream(FrameStream),
}

impl Default for Frames {
    fn default() -> Self {
        Frames::Encoded(Vec::new())
    }
}

impl From<Vec<Vec<u8>>> for Frames {
    fn from(v: Vec<Vec<u8>>) -> Self {
        Frames::Encoded(v)
    }
}

impl Frames {
    /// How many frames there are (a stream's declared count: pulling it checks that it holds
    /// exactly that many).
    pub fn len(&self) -> usize {
        match self {
            Frames::Encoded(f) => f.len(),
            Frames::Stream(s) => s.len,
        }
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The frames when they are all in memory.
    pub fn as_encoded(&self) -> Option<&[Vec<u8>]> {
        match self {
            Frames::Encoded(f) => Some(f),
            Frames::Stream(_) => None,
        }
    }

    /// Every frame in memory (pulls a stream to its end; its first error is returned).
    pub fn collect_encoded(self) -> Result<Vec<Vec<u8>>, crate::StoreError> {
        match self {
            Frames::Encoded(f) => Ok(f),
            Frames::Stream(s) => s.collect(),
        }
    }
}

/// Frames in step order: `for frame in column.frames { let png_or_jpeg = frame?; … }`.
impl IntoIterator for Frames {
    type Item = FrameResult;
    type IntoIter = Box<dyn Iterator<Item = FrameResult> + Send>;
    fn into_iter(self) -> Self::IntoIter {
        match self {
            Frames::Encoded(f) => Box::new(f.into_iter().map(Ok)),
            Frames::Stream(s) => Box::new(s),
        }
    }
}

impl std::fmt::Debug for Frames {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Frames::Encoded(v) => write!(f, "Frames::Encoded({} frames)", v.len()),
            Frames::Stream(s) => write!(f, "Frames::Stream({} {} frames)", s.len, s.encoding),
        }
    }
}

/// Two in-memory frame lists compare by content; a stream equals nothing (comparing it would
/// consume it).
impl PartialEq for Frames {
    fn eq(&self, other: &Self) -> bool {
        match (self, other) {
            (Frames::Encoded(a), Frames::Encoded(b)) => a == b,
            _ => false,
        }
    }
}

/// A camera's frames produced on demand: `len` frames of one `encoding` (`png` or `jpeg`),
/// pulled in order. It checks what it yields: exactly `len` frames (fewer or more is an error
/// naming the camera), each of the declared encoding; after an error it yields nothing.
pub struct FrameStream {
    name: String,
    len: usize,
    encoding: &'static str,
    produced: usize,
    failed: bool,
    source: Box<dyn Iterator<Item = FrameResult> + Send>,
}

impl FrameStream {
    /// `len` frames of `encoding` (`png` or `jpeg`) of the camera `name` (for errors), from
    /// `source`.
    pub fn new(
        name: &str,
        len: usize,
        encoding: &'static str,
        source: impl Iterator<Item = FrameResult> + Send + 'static,
    ) -> Self {
        FrameStream {
            name: name.to_string(),
            len,
            encoding,
            produced: 0,
            failed: false,
            source: Box::new(source),
        }
    }

    /// The same stream produced ahead on a thread of its own (started on the first pull), at
    /// most `depth` frames ahead: the source's work (reading, PNG encoding) overlaps the
    /// consumer's (compressing, writing). Memory: `depth` frames and what the source holds.
    pub fn prefetched(mut self, depth: usize) -> Self {
        let source = std::mem::replace(&mut self.source, Box::new(std::iter::empty()));
        self.source = Box::new(Prefetch { source: Some(source), rx: None, depth: depth.max(1) });
        self
    }

    pub fn len(&self) -> usize {
        self.len
    }

    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    pub fn encoding(&self) -> &'static str {
        self.encoding
    }

    fn fail(&mut self, msg: String) -> Option<FrameResult> {
        self.failed = true;
        Some(Err(crate::StoreError::invalid(msg)))
    }
}

impl Iterator for FrameStream {
    type Item = FrameResult;
    fn next(&mut self) -> Option<FrameResult> {
        if self.failed {
            return None;
        }
        if self.produced == self.len {
            return match self.source.next() {
                None => None,
                Some(Err(e)) => {
                    self.failed = true;
                    Some(Err(e))
                }
                Some(Ok(_)) => {
                    let (name, len) = (self.name.clone(), self.len);
                    self.fail(format!("camera {name:?} yields more than its {len} frames"))
                }
            };
        }
        match self.source.next() {
            None => {
                let (name, len, got) = (self.name.clone(), self.len, self.produced);
                self.fail(format!("camera {name:?} ended after {got} of its {len} frames"))
            }
            Some(Err(e)) => {
                self.failed = true;
                Some(Err(e))
            }
            Some(Ok(f)) => {
                if self.encoding == "jpeg" && !is_jpeg(&f) {
                    let (name, t) = (self.name.clone(), self.produced);
                    return self.fail(format!("camera {name:?}: frame {t} is not a JPEG image"));
                }
                self.produced += 1;
                Some(Ok(f))
            }
        }
    }
}

/// A source run on its own thread, `depth` frames ahead (see [`FrameStream::prefetched`]). The
/// thread stops when the source ends or fails, or when this end is dropped.
struct Prefetch {
    source: Option<Box<dyn Iterator<Item = FrameResult> + Send>>,
    rx: Option<std::sync::mpsc::Receiver<FrameResult>>,
    depth: usize,
}

impl Iterator for Prefetch {
    type Item = FrameResult;
    fn next(&mut self) -> Option<FrameResult> {
        if let Some(source) = self.source.take() {
            let (tx, rx) = std::sync::mpsc::sync_channel(self.depth);
            let spawned = std::thread::Builder::new().name("ufops-frames".into()).spawn(move || {
                for f in source {
                    let stop = f.is_err();
                    // The consumer is gone: nothing left to do.
                    if tx.send(f).is_err() || stop {
                        break;
                    }
                }
            });
            if let Err(e) = spawned {
                return Some(Err(crate::StoreError::invalid(format!(
                    "cannot start a frame reader thread: {e}"
                ))));
            }
            self.rx = Some(rx);
        }
        self.rx.as_ref()?.recv().ok()
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

/// One episode as produced by an ingester. Not `Clone`: its cameras may be streams
/// ([`Frames::Stream`]), which only one consumer can pull.
#[derive(Debug, PartialEq)]
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
/// Passed beside the episode (`store::IngestWriter::push_episode_with_extras`).
#[derive(Debug, Clone)]
pub struct ExtraColumn {
    pub name: String,
    pub values: ExtraValues,
    pub metadata: std::collections::HashMap<String, String>,
}

impl PartialEq for ExtraColumn {
    fn eq(&self, other: &Self) -> bool {
        self.name == other.name && self.metadata == other.metadata && self.values == other.values
    }
}

/// An extra column's rows: in memory, or read a page of rows at a time as the store's writer
/// writes them ([`ExtraPages`]: a column as large as a camera, robomimic's `next_obs` images,
/// never sits in memory whole).
#[derive(Clone)]
pub enum ExtraValues {
    Array(arrow::array::ArrayRef),
    Pages(ExtraPages),
}

impl From<arrow::array::ArrayRef> for ExtraValues {
    fn from(a: arrow::array::ArrayRef) -> Self {
        ExtraValues::Array(a)
    }
}

impl From<ExtraPages> for ExtraValues {
    fn from(p: ExtraPages) -> Self {
        ExtraValues::Pages(p)
    }
}

impl ExtraValues {
    pub fn len(&self) -> usize {
        match self {
            ExtraValues::Array(a) => a.len(),
            ExtraValues::Pages(p) => p.len,
        }
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    pub fn data_type(&self) -> &arrow::datatypes::DataType {
        match self {
            ExtraValues::Array(a) => a.data_type(),
            ExtraValues::Pages(p) => &p.data_type,
        }
    }

    /// Heap bytes held now (a paged column holds none until it is read).
    pub fn memory_size(&self) -> usize {
        match self {
            ExtraValues::Array(a) => a.get_array_memory_size(),
            ExtraValues::Pages(_) => 0,
        }
    }

    /// Every row in memory (reads a paged column whole: tests, small columns).
    pub fn to_array(&self) -> Result<arrow::array::ArrayRef, crate::StoreError> {
        match self {
            ExtraValues::Array(a) => Ok(a.clone()),
            ExtraValues::Pages(p) => p.read(0, p.len),
        }
    }
}

impl std::fmt::Debug for ExtraValues {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            ExtraValues::Array(a) => write!(f, "ExtraValues::Array({} rows of {})", a.len(), a.data_type()),
            ExtraValues::Pages(p) => write!(f, "ExtraValues::Pages({} rows of {})", p.len, p.data_type),
        }
    }
}

/// In-memory columns compare by content; a paged one equals nothing (comparing would read it).
impl PartialEq for ExtraValues {
    fn eq(&self, other: &Self) -> bool {
        match (self, other) {
            (ExtraValues::Array(a), ExtraValues::Array(b)) => a.to_data() == b.to_data(),
            _ => false,
        }
    }
}

/// Rows read `(first, count)` at a time.
pub type ReadRows = dyn Fn(usize, usize) -> Result<arrow::array::ArrayRef, crate::StoreError> + Send + Sync;

/// An extra column of `len` rows of `data_type`, read on demand by `read(first, count)`. The
/// writer cuts it into pages where it would cut the whole column, which would occupy
/// `slice_bytes` (its `get_slice_memory_size`), so the stored file is the same either way.
#[derive(Clone)]
pub struct ExtraPages {
    pub(crate) data_type: arrow::datatypes::DataType,
    pub(crate) len: usize,
    pub(crate) slice_bytes: usize,
    read: std::sync::Arc<ReadRows>,
}

impl ExtraPages {
    pub fn new(
        data_type: arrow::datatypes::DataType,
        len: usize,
        slice_bytes: usize,
        read: impl Fn(usize, usize) -> Result<arrow::array::ArrayRef, crate::StoreError> + Send + Sync + 'static,
    ) -> Self {
        ExtraPages { data_type, len, slice_bytes, read: std::sync::Arc::new(read) }
    }

    /// Rows `first..first + count`, checked to be that many of the declared type.
    pub fn read(&self, first: usize, count: usize) -> Result<arrow::array::ArrayRef, crate::StoreError> {
        let a = (self.read)(first, count)?;
        if a.len() != count || a.data_type() != &self.data_type {
            return Err(crate::StoreError::invalid(format!(
                "extra column rows {first}..{}: read {} rows of {}, expected {count} of {}",
                first + count,
                a.len(),
                a.data_type(),
                self.data_type
            )));
        }
        Ok(a)
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
pub fn check_name(what: &str, s: &str) -> Result<(), crate::StoreError> {
    if s.is_empty() || s.chars().count() > 200 || s.chars().any(|c| c.is_control()) || s.trim() != s {
        return Err(crate::StoreError::invalid(format!(
            "invalid {what} name {s:?}: 1-200 printable characters without surrounding spaces"
        )));
    }
    Ok(())
}

/// Policy and checkpoint names: [`check_name`]'s rule, and no '/', since artifact references
/// (`POLICY/CHECKPOINT/KIND@ALIAS`), comparison arms (`CHECKPOINT/RUN`) and URL paths join them
/// with it. The store refuses them at ingest, the API in every request that names one.
pub fn check_ref_name(what: &str, s: &str) -> Result<(), crate::StoreError> {
    check_name(what, s)?;
    if s.contains('/') {
        return Err(crate::StoreError::invalid(format!(
            "invalid {what} name {s:?}: 1-200 printable characters without surrounding spaces, no '/'"
        )));
    }
    Ok(())
}

/// How an ingest stores image cameras (`ufops ingest --images`, the API's `images`).
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum ImageStorage {
    /// One PNG per step in the steps file: lossless (the default).
    #[default]
    Png,
    /// One H.264 MP4 per episode and camera: lossy, a fraction of the bytes, played by the page.
    Video,
}

impl ImageStorage {
    pub fn as_str(self) -> &'static str {
        match self {
            ImageStorage::Png => "png",
            ImageStorage::Video => "video",
        }
    }
}

impl std::fmt::Display for ImageStorage {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.as_str())
    }
}

impl std::str::FromStr for ImageStorage {
    type Err = crate::StoreError;
    fn from_str(s: &str) -> Result<Self, crate::StoreError> {
        match s.to_ascii_lowercase().as_str() {
            "png" => Ok(ImageStorage::Png),
            "video" | "mp4" | "h264" => Ok(ImageStorage::Video),
            other => {
                Err(crate::StoreError::invalid(format!("unknown --images {other:?}: expected png or video")))
            }
        }
    }
}
