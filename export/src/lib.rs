//! export: the way out of the store. A store version, a split or a filter of one (policy,
//! checkpoint, task, label, tag, verifier-score range of an artifact) becomes a **LeRobot v3.0 dataset** ([`lerobot`]), a
//! **robomimic HDF5 file** ([`robomimic`]) or an **ALOHA folder** of one HDF5 file per episode
//! ([`aloha`]), with the version's frozen labels and a record of where
//! it came from. This crate owns the writers, the export and score jobs ([`job`], [`score_job`])
//! and writing to a temporary name renamed at the end (a crash leaves no half dataset). Which
//! episodes, read in order with bounded memory, is the store's selection path
//! (`store::Selection`, `store::select`, `store::EpisodeReader`, with the provenance record
//! `store::Selected::provenance`); scoring them for a score range is the verifier core's
//! (`verifier::stored`). It reads the store only through its public read path (that selection
//! path, and the media objects of video cameras, which the HDF5 writers decode back into image
//! arrays: `cameras`).

pub mod aloha;
mod cameras;
pub mod job;
pub mod lerobot;
pub mod robomimic;
pub mod score_job;

use std::path::{Path, PathBuf};

use arrow::array::RecordBatch;
use serde::Serialize;
use store::{EpisodeRecord, Label, Store, StoreError};
// The writers' names for the store's selection path (`crate::Selected`, ...).
use store::{EpisodeReader, Progress, Selected};
use verifier::stored::StoredEpisodesError;

#[derive(Debug, thiserror::Error)]
pub enum ExportError {
    #[error(transparent)]
    Store(#[from] StoreError),
    /// Scoring the selection for a score range ([`verifier::stored`]).
    #[error(transparent)]
    Scoring(#[from] StoredEpisodesError),
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

/// The failure cause in a label event's data.
pub(crate) fn failure_cause(data: Option<&serde_json::Value>) -> Option<String> {
    data?.get("failure_cause")?.as_str().map(str::to_string)
}

/// The time spans in a label event's data, as JSON (`[{start_step, end_step, actor?}]`).
pub(crate) fn label_spans(data: Option<&serde_json::Value>) -> Option<String> {
    data?.get("spans").filter(|s| s.as_array().is_some_and(|a| !a.is_empty())).map(|s| s.to_string())
}

/// [`store::for_each_episode_with_layers`] with callbacks that fail with [`ExportError`].
pub(crate) async fn for_each_episode_with_layers(
    store: &Store,
    episodes: &[EpisodeRecord],
    layers: &[String],
    version: Option<i64>,
    f: impl FnMut(usize, &EpisodeRecord, RecordBatch) -> Result<()>,
) -> Result<()> {
    store::for_each_episode_with_layers(store, episodes, layers, version, f).await
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
