//! The one error type of the verifier core.
use thiserror::Error;

/// Every failure the core reports. Nothing a caller passes in (files, bytes, slices) makes it
/// panic: each problem maps to a variant here with a message naming it.
#[derive(Debug, Error)]
pub enum VerifierError {
    #[error("i/o error on {path}: {source}")]
    Io { path: String, source: std::io::Error },
    #[error("fetching {file} failed: {message}")]
    Fetch { file: String, message: String },
    #[error("manifest.json is invalid: {0}")]
    Manifest(String),
    #[error("sha256 mismatch for {file}: manifest says {expected}, file has {actual}")]
    HashMismatch { file: String, expected: String, actual: String },
    #[error("unsupported schema_version {0} (this client knows 1, one network, and 2, an ensemble)")]
    UnknownSchema(u64),
    #[error("unknown architecture.variant {0:?} (known: \"lowdim\", \"features\")")]
    UnknownVariant(String),
    #[error("unknown kind {0:?} (known: \"classifier\", \"q\")")]
    UnknownKind(String),
    #[error("unknown activation {0:?} (known: \"relu\", \"gelu\")")]
    UnknownActivation(String),
    #[error("config.json is invalid: {0}")]
    Config(String),
    #[error("model.safetensors is invalid: {0}")]
    Safetensors(String),
    #[error("tensor {name:?} is missing from model.safetensors")]
    MissingTensor { name: String },
    #[error("tensor {name:?} is not part of this architecture")]
    UnexpectedTensor { name: String },
    #[error("tensor {name:?} has shape {actual:?}, expected {expected:?}")]
    TensorShape { name: String, expected: Vec<usize>, actual: Vec<usize> },
    #[error("tensor {name:?} has dtype {dtype}, expected F32")]
    TensorDtype { name: String, dtype: String },
    #[error("bad input: {0}")]
    Input(String),
}

pub type Result<T, E = VerifierError> = std::result::Result<T, E>;

impl VerifierError {
    pub(crate) fn io(path: &std::path::Path, source: std::io::Error) -> Self {
        VerifierError::Io { path: path.display().to_string(), source }
    }
}
