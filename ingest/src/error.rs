//! The ingest error type. Every variant that concerns the input names the file and what is wrong.

use std::path::{Path, PathBuf};

#[derive(Debug, thiserror::Error)]
pub enum IngestError {
    /// The input is broken, has the wrong layout, or holds values we cannot represent.
    #[error("{}: {msg}", path.display())]
    Invalid { path: PathBuf, msg: String },
    /// A recording was cut off (e.g. an MCAP without summary/footer). `recoverable` says what
    /// `--recover` would ingest.
    #[error("{}: {msg}", path.display())]
    Truncated { path: PathBuf, msg: String, recoverable: usize },
    #[error("{}: {source}", path.display())]
    Io { path: PathBuf, source: std::io::Error },
    /// Bad command-line options (mapping file, success file, format name, ...).
    #[error("{0}")]
    Usage(String),
    /// The store refused the write (the store is left as it was).
    #[error("store: {0}")]
    Store(String),
    /// A camera's frames failed while they were pulled from their stream (`store::FrameStream`);
    /// the message names the file and the dataset.
    #[error("{0}")]
    Frames(String),
    /// The run was cancelled (the consumer went away); nothing was committed.
    #[error("ingest cancelled")]
    Cancelled,
}

impl IngestError {
    pub fn invalid(path: impl AsRef<Path>, msg: impl Into<String>) -> Self {
        IngestError::Invalid { path: path.as_ref().to_path_buf(), msg: msg.into() }
    }
    pub fn io(path: impl AsRef<Path>, source: std::io::Error) -> Self {
        IngestError::Io { path: path.as_ref().to_path_buf(), source }
    }
    /// The file the error is about, when it is about one.
    pub fn path(&self) -> Option<&Path> {
        match self {
            IngestError::Invalid { path, .. }
            | IngestError::Truncated { path, .. }
            | IngestError::Io { path, .. } => Some(path),
            _ => None,
        }
    }
}

pub type Result<T, E = IngestError> = std::result::Result<T, E>;
