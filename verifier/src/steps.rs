//! Verifier inputs from stored steps (feature `steps`): a steps batch as the store reads it
//! (`obs.<key>`, `action`, `action_chunk` columns, layers joined as `obs.<layer>` with their
//! producer in the field metadata) → [`EpisodeSeries`] → the samples of [`build_samples`], and
//! [`StepScorer`], the one way anything (export curation, the review queue's score job, the
//! viewer, `ufops rank`) scores a stored episode's steps.

use arrow::array::RecordBatch;

use crate::samples::{build_samples, EpisodeSeries, ObsSeries, Samples};
use crate::{ArtifactConfig, Result, Verifier, VerifierError};

fn input_err(e: impl std::fmt::Display) -> VerifierError {
    VerifierError::Input(e.to_string())
}

/// The episode `id` of a steps batch, its observation series in the order of `keys`.
pub fn episode_from_steps(
    id: &str,
    success: bool,
    batch: &RecordBatch,
    keys: &[String],
) -> Result<EpisodeSeries> {
    let mut obs = Vec::with_capacity(keys.len());
    for k in keys {
        let (dim, values) = store::steps::vector_column(batch, &format!("{}{k}", store::steps::OBS_PREFIX))
            .map_err(|e| input_err(format!("episode {id}: {e}")))?;
        obs.push(ObsSeries { key: k.clone(), dim, values });
    }
    let (action_dim, actions) = store::steps::vector_column(batch, "action").map_err(input_err)?;
    let action_chunk = match batch.schema().field_with_name("action_chunk") {
        Ok(_) => {
            let (hd, values) = store::steps::vector_column(batch, "action_chunk").map_err(input_err)?;
            if action_dim == 0 || hd % action_dim != 0 {
                return Err(input_err(format!(
                    "episode {id}: action_chunk width {hd} is not a multiple of the action dim {action_dim}"
                )));
            }
            Some((hd / action_dim, values))
        }
        Err(_) => None,
    };
    Ok(EpisodeSeries {
        id: id.to_string(),
        success,
        obs,
        actions,
        action_dim,
        action_chunk,
        policy_steps: None,
    })
}

/// The verifier inputs of every step of a stored episode, built exactly as for training
/// (observation history; stored chunk, else the next H actions; step index) with the raw chunks
/// put into the space the artifact takes (`input.action_space`).
pub fn step_inputs(cfg: &ArtifactConfig, batch: &RecordBatch) -> Result<Samples> {
    let input = &cfg.input.layout;
    if !cfg.architecture.extra_inputs.is_empty() {
        return Err(input_err("building stored steps for a verifier with extra inputs is not supported"));
    }
    let keys: Vec<String> = input.obs_keys.iter().map(|k| k.key.clone()).collect();
    // Layer keys: the batch must hold them (a read joined with the layers) from the producer
    // the verifier was trained on.
    let schema = batch.schema();
    let mut provided = Vec::new();
    for (key, want) in input.required_producers() {
        let field = schema.field_with_name(&format!("{}{key}", store::steps::OBS_PREFIX)).map_err(|_| {
            input_err(format!(
                "this verifier reads layer {key} (features of producer {}): read the steps with that layer",
                crate::short_hash(want)
            ))
        })?;
        provided.push((key, field.metadata().get(store::PRODUCER_META_KEY).cloned().unwrap_or_default()));
    }
    input.check_producers(provided.iter().map(|(k, p)| (*k, p.as_str())))?;
    let mut ep = episode_from_steps("scored", false, batch, &keys)?;
    if ep.action_chunk.as_ref().is_some_and(|(h, _)| *h != input.chunk_len) {
        ep.action_chunk = None;
    }
    let mut s = build_samples(std::slice::from_ref(&ep), input, cfg.gamma.unwrap_or(0.99))?;
    cfg.input.action_space.raw_to_input(&mut s.act, input.action_dim);
    Ok(s)
}

/// Scores every step of a stored episode. [`Verifier`] implements it on [`step_inputs`]; tests
/// may bring their own.
pub trait StepScorer: Send + Sync {
    /// One score per row of `steps` (a steps batch as the store reads it).
    fn score_steps(&self, steps: &RecordBatch) -> Result<Vec<f32>>;
    /// The layers the scorer reads (observation keys that are layers): a caller joins them to
    /// the steps it passes.
    fn layers(&self) -> Vec<String> {
        Vec::new()
    }
}

impl StepScorer for Verifier {
    fn score_steps(&self, steps: &RecordBatch) -> Result<Vec<f32>> {
        let s = step_inputs(self.config(), steps)?;
        self.score(&s.obs, &s.t, &s.act, 1)
    }
    fn layers(&self) -> Vec<String> {
        self.config().input.layout.required_producers().iter().map(|(k, _)| k.to_string()).collect()
    }
}
