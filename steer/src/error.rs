use thiserror::Error;

/// Every failure the steering client can report. Loading never panics on bad input: each problem
/// (bad hash, unknown schema, missing/ill-shaped tensor, truncated file, ...) maps to a variant here.
#[derive(Debug, Error)]
pub enum SteerError {
    #[error("i/o error on {path}: {source}")]
    Io { path: String, source: std::io::Error },
    #[error("fetching the artifact failed: {0}")]
    Http(String),
    #[error("manifest.json is invalid: {0}")]
    Manifest(String),
    #[error("sha256 mismatch for {file}: manifest says {expected}, file has {actual}")]
    HashMismatch { file: String, expected: String, actual: String },
    #[error("unsupported schema_version {0} (this client knows 1)")]
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
    #[error("tensor {name:?} has shape {actual:?}, expected {expected:?}")]
    TensorShape { name: String, expected: Vec<usize>, actual: Vec<usize> },
    #[error("tensor {name:?} has dtype {dtype}, expected F32")]
    TensorDtype { name: String, dtype: String },
    #[error("bad input: {0}")]
    Input(String),
    #[error("policy/model error: {0}")]
    Model(String),
    #[error("candle: {0}")]
    Candle(#[from] candle_core::Error),
}

pub type Result<T, E = SteerError> = std::result::Result<T, E>;
