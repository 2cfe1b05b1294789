//! `steer`: the UF-OPS steering client — what runs next to the policy on the robot.
//!
//! It owns: loading a verifier artifact (trainer/ARTIFACT.md, schema_version 1: manifest sha256
//! checks, config validation, safetensors weights) into a [`Verifier`] that scores candidate action
//! chunks and gives guidance gradients w.r.t. the raw chunk (a candle reference implementation for
//! every variant, plus a hand-written AVX2/FMA fast path for `lowdim`); the policy traits a user
//! implements for their own model ([`NoisePredictor`] for DDPM, [`VelocityField`] for flow
//! matching) with the [`DdpmSchedule`]; and the steering strategies of the paper: best-of-N
//! (Algorithm 1), classifier guidance for DDPM (Algorithm 2) and guidance for flow policies.
//! With the `http` feature it also loads an artifact from a `ufops serve` API ([`http::ApiSource`]).
//! It does not own training (the `trainer` crate) or storage (the `store` crate).

pub mod config;
pub mod error;
pub mod fast;
#[cfg(feature = "http")]
pub mod http;
pub mod policy;
pub mod reference;
pub mod sample;
pub mod schedule;
pub mod testutil;
pub mod verifier;
pub mod weights;

pub use config::{Kind, Variant, VerifierConfig};
pub use error::{Result, SteerError};
pub use policy::{ActionAffine, NoisePredictor, VelocityField};
pub use sample::{
    best_of_n, ddpm_sample, ddpm_sample_guided, flow_sample, flow_sample_guided, select_best, Guidance,
};
pub use schedule::DdpmSchedule;
pub use verifier::Verifier;

/// Anything that scores action chunks and gives guidance gradients: implemented by [`Verifier`]
/// (and its two back-ends); tests and users may implement it for their own scorers.
///
/// All chunks are RAW (un-normalised) flattened `H x A` chunks; `obs` rows are the verifier's
/// observation history (`obs_dim` each).
pub trait Scorer {
    fn obs_dim(&self) -> usize;
    fn act_dim(&self) -> usize;
    /// Scores for `B = t.len()` groups of `n` candidates: `obs` is `B * obs_dim`, `candidates` is
    /// `B * n * act_dim` (group-major); returns `B * n` scores (classifier: sigmoid(logit), q: value).
    fn score_batch(&self, obs: &[f32], t: &[u32], candidates: &[f32], n: usize) -> Result<Vec<f32>>;
    /// Guidance gradients for `B = t.len()` rows: d log C / d chunk (classifier) or d Q / d chunk,
    /// w.r.t. the raw chunk; returns `B * act_dim`.
    fn grad_batch(&self, obs: &[f32], t: &[u32], chunks: &[f32]) -> Result<Vec<f32>>;

    /// Scores of N candidate chunks (`N * act_dim`) for one observation history.
    fn score(&self, obs_history: &[f32], candidates: &[f32], t: u32) -> Result<Vec<f32>> {
        let ad = self.act_dim();
        if ad == 0 || candidates.len() % ad != 0 {
            return Err(SteerError::Input(format!(
                "candidates length {} is not a multiple of act_dim {ad}",
                candidates.len()
            )));
        }
        self.score_batch(obs_history, &[t], candidates, candidates.len() / ad)
    }
    /// Guidance gradient for one chunk.
    fn grad(&self, obs_history: &[f32], chunk: &[f32], t: u32) -> Result<Vec<f32>> {
        self.grad_batch(obs_history, &[t], chunk)
    }
}

impl<S: Scorer + ?Sized> Scorer for &S {
    fn obs_dim(&self) -> usize {
        (**self).obs_dim()
    }
    fn act_dim(&self) -> usize {
        (**self).act_dim()
    }
    fn score_batch(&self, obs: &[f32], t: &[u32], candidates: &[f32], n: usize) -> Result<Vec<f32>> {
        (**self).score_batch(obs, t, candidates, n)
    }
    fn grad_batch(&self, obs: &[f32], t: &[u32], chunks: &[f32]) -> Result<Vec<f32>> {
        (**self).grad_batch(obs, t, chunks)
    }
}
