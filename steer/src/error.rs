use thiserror::Error;

/// Every failure of the steering client: the verifier core's (loading, checks, bad inputs),
/// fetching over HTTP, the caller's inputs to a sampler, and the user's policy model.
#[derive(Debug, Error)]
pub enum SteerError {
    #[error(transparent)]
    Verifier(#[from] verifier::VerifierError),
    #[error("fetching the artifact failed: {0}")]
    Http(String),
    #[error("bad input: {0}")]
    Input(String),
    #[error("policy/model error: {0}")]
    Model(String),
}

pub type Result<T, E = SteerError> = std::result::Result<T, E>;
