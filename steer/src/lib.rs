//! `steer`: the UF-OPS steering client — what runs next to the policy on the robot.
//!
//! It owns the policy traits a user implements for their own model ([`NoisePredictor`] for
//! DDPM, [`VelocityField`] for flow matching) with the [`DdpmSchedule`], the [`Scorer`]
//! abstraction over verifiers, and the steering strategies of the paper: best-of-N
//! (Algorithm 1), classifier guidance for DDPM (Algorithm 2) and guidance for flow policies
//! (with an ensemble verifier: the pessimistic pick that may fall back to the policy's own
//! chunk, and the push scaled by the members' agreement, both the core's rules),
//! and the failure alarm that runs beside them ([`Monitor`]). Best-of-N can record what each
//! step saw and chose ([`best_of_n_recorded`], steering telemetry) for `ufops replay`.
//! With the `http` feature it also loads a verifier from a `ufops serve` API ([`http`]).
//!
//! Loading, checking and running a verifier (the forward pass and its gradient) is the
//! `verifier` core's, re-exported here as [`Verifier`]; training is the `trainer` crate's and
//! storage the `store` crate's.

pub mod error;
#[cfg(feature = "http")]
pub mod http;
pub mod monitor;
pub mod policy;
pub mod sample;
pub mod schedule;
pub mod telemetry;

pub use error::{Result, SteerError};
pub use monitor::Monitor;
pub use policy::{ActionAffine, NoisePredictor, VelocityField};
pub use sample::{
    best_of_n, best_of_n_raw, ddpm_sample, ddpm_sample_guided, flow_sample, flow_sample_guided, select_best,
    BestOfN, Guidance,
};
pub use schedule::DdpmSchedule;
pub use telemetry::best_of_n_recorded;
pub use verifier;
pub use verifier::SteeringStep;
pub use verifier::{Kind, Picks, Verifier};

/// Anything that scores action chunks and gives guidance gradients: implemented by
/// [`Verifier`]; tests and users may implement it for their own scorers.
///
/// Chunks are flattened `H x A` chunks in the space the scorer takes: the policy's normalised
/// sample space (the paper's choice, and the default) or, for older verifiers, raw actions
/// ([`Scorer::takes_policy_space`]). `obs` rows are the scorer's observation history
/// (`obs_dim` each).
pub trait Scorer {
    fn obs_dim(&self) -> usize;
    fn act_dim(&self) -> usize;
    /// True when chunks are in the policy's normalised sample space (guidance then takes the
    /// gradient w.r.t. x̂0 directly); false for a scorer of raw actions, whose gradient the
    /// samplers map back through the policy's [`ActionAffine`].
    fn takes_policy_space(&self) -> bool {
        true
    }
    /// Scores for `B = t.len()` groups of `n` candidates: `obs` is `B * obs_dim`, `candidates` is
    /// `B * n * act_dim` (group-major); returns `B * n` scores (classifier: sigmoid(logit), q: value).
    fn score_batch(&self, obs: &[f32], t: &[u32], candidates: &[f32], n: usize) -> Result<Vec<f32>>;
    /// Guidance gradients for `B = t.len()` rows: d log C / d chunk (classifier) or d Q / d chunk;
    /// returns `B * act_dim`.
    fn grad_batch(&self, obs: &[f32], t: &[u32], chunks: &[f32]) -> Result<Vec<f32>>;
    /// Best-of-N's choice in each of `B` groups of `n` candidates, with the scores it ranked by.
    /// The default is the argmax of [`Scorer::score_batch`]; a [`Verifier`] ensemble picks
    /// pessimistically and may fall back to each group's first candidate
    /// ([`Verifier::pick`]).
    fn pick_batch(&self, obs: &[f32], t: &[u32], candidates: &[f32], n: usize) -> Result<Picks> {
        let scores = self.score_batch(obs, t, candidates, n)?;
        let b = t.len();
        if n == 0 || scores.len() != b * n {
            return Err(SteerError::Input(format!(
                "{} scores for {b} groups of {n} candidates",
                scores.len()
            )));
        }
        Ok(Picks {
            index: scores.chunks(n).map(verifier::ensemble::argmax).collect(),
            spread: vec![0.0; scores.len()],
            scores,
            fell_back: vec![false; b],
            agreement: vec![1.0; b],
        })
    }

    /// Scores of N candidate chunks (`N * act_dim`) for one observation history.
    fn score(&self, obs_history: &[f32], candidates: &[f32], t: u32) -> Result<Vec<f32>> {
        let ad = self.act_dim();
        if ad == 0 || !candidates.len().is_multiple_of(ad) {
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
    /// Why steering with this scorer may not help, when its training flagged it (a verifier
    /// artifact's action-sensitivity figure, [`verifier::ActionSensitivity`]); the best-of-N
    /// helpers log it once per process ([`warn_if_flagged`]).
    fn steering_warning(&self) -> Option<String> {
        None
    }
    /// The id of the artifact behind this scorer, which steering telemetry records
    /// ([`telemetry`]); `None` for a scorer that is not an artifact.
    fn artifact_id(&self) -> Option<String> {
        None
    }
}

impl Scorer for Verifier {
    fn obs_dim(&self) -> usize {
        Verifier::obs_dim(self)
    }
    fn act_dim(&self) -> usize {
        Verifier::act_dim(self)
    }
    fn takes_policy_space(&self) -> bool {
        Verifier::takes_policy_space(self)
    }
    fn score_batch(&self, obs: &[f32], t: &[u32], candidates: &[f32], n: usize) -> Result<Vec<f32>> {
        Ok(Verifier::score(self, obs, t, candidates, n)?)
    }
    fn grad_batch(&self, obs: &[f32], t: &[u32], chunks: &[f32]) -> Result<Vec<f32>> {
        Ok(Verifier::grad(self, obs, t, chunks)?)
    }
    fn pick_batch(&self, obs: &[f32], t: &[u32], candidates: &[f32], n: usize) -> Result<Picks> {
        Ok(Verifier::pick(self, obs, &[], t, candidates, n)?)
    }
    fn steering_warning(&self) -> Option<String> {
        Verifier::steering_warning(self)
    }
    fn artifact_id(&self) -> Option<String> {
        Verifier::id(self).map(str::to_string)
    }
}

impl<S: Scorer + ?Sized> Scorer for &S {
    fn obs_dim(&self) -> usize {
        (**self).obs_dim()
    }
    fn act_dim(&self) -> usize {
        (**self).act_dim()
    }
    fn takes_policy_space(&self) -> bool {
        (**self).takes_policy_space()
    }
    fn score_batch(&self, obs: &[f32], t: &[u32], candidates: &[f32], n: usize) -> Result<Vec<f32>> {
        (**self).score_batch(obs, t, candidates, n)
    }
    fn grad_batch(&self, obs: &[f32], t: &[u32], chunks: &[f32]) -> Result<Vec<f32>> {
        (**self).grad_batch(obs, t, chunks)
    }
    fn pick_batch(&self, obs: &[f32], t: &[u32], candidates: &[f32], n: usize) -> Result<Picks> {
        (**self).pick_batch(obs, t, candidates, n)
    }
    fn steering_warning(&self) -> Option<String> {
        (**self).steering_warning()
    }
    fn artifact_id(&self) -> Option<String> {
        (**self).artifact_id()
    }
}

/// Logs a flagged scorer's [`Scorer::steering_warning`] (tracing, level `warn`) the first time
/// this process steers with it; returns whether it warned now. The best-of-N helpers call it, so
/// a verifier whose training said it is unlikely to steer well is named once, not per step.
pub fn warn_if_flagged(scorer: &dyn Scorer) -> bool {
    use std::sync::{Mutex, OnceLock};
    static WARNED: OnceLock<Mutex<std::collections::HashSet<String>>> = OnceLock::new();
    let Some(message) = scorer.steering_warning() else { return false };
    let first =
        WARNED.get_or_init(Default::default).lock().map(|mut w| w.insert(message.clone())).unwrap_or(false);
    if first {
        tracing::warn!("{message}");
    }
    first
}
