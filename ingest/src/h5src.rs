//! An HDF5 file being read as untrusted input: its path (every error names it) and the most
//! decoded bytes one of its datasets may declare, whatever its header says. robomimic and ALOHA
//! files, and the windowed reads of their cameras (`h5rows`), share it.

use std::path::Path;

use crate::error::IngestError;

/// Decoded size of one dataset that is believed whatever the file's size (small datasets
/// holding only the fill value cost nothing to allow).
const DECLARED_BYTES_FLOOR: u64 = 1 << 20;

/// Largest believable ratio of a dataset's decoded size to the file's size: deflate, the
/// strongest filter robomimic files use, cannot exceed 1032:1.
pub const MAX_DECLARED_RATIO: u64 = 1100;

/// Largest decoded size of one dataset, whatever the file's size: a demo is decoded whole, so
/// this bounds memory (a 2,000-step demo of 480x640 RGB frames is 1.8 GB).
pub const MAX_DATASET_BYTES: u64 = 2 << 30;

/// The file being read: its path (errors name it) and how many decoded bytes one of its
/// datasets may declare. Derefs to the path.
pub(crate) struct Src<'a> {
    pub(crate) path: &'a Path,
    pub(crate) file_len: u64,
}

impl Src<'_> {
    pub(crate) fn new(path: &Path, file_len: u64) -> Src<'_> {
        Src { path, file_len }
    }

    /// What one dataset may declare: the file's size times [`MAX_DECLARED_RATIO`] (at least
    /// [`DECLARED_BYTES_FLOOR`]), never more than [`MAX_DATASET_BYTES`].
    pub(crate) fn max_dataset_bytes(&self) -> u64 {
        self.file_len.saturating_mul(MAX_DECLARED_RATIO).clamp(DECLARED_BYTES_FLOOR, MAX_DATASET_BYTES)
    }
}

impl std::ops::Deref for Src<'_> {
    type Target = Path;
    fn deref(&self) -> &Path {
        self.path
    }
}

impl AsRef<Path> for Src<'_> {
    fn as_ref(&self) -> &Path {
        self.path
    }
}

pub(crate) fn h5err(
    path: &Path,
    what: impl std::fmt::Display,
) -> impl FnOnce(hdf5_pure::Error) -> IngestError {
    let what = what.to_string();
    let path = path.to_path_buf();
    move |e| IngestError::invalid(path, format!("{what}: {e}"))
}
