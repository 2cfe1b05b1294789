//! The trainer's entry points: episodes or prepared samples in, a trained verifier out — one
//! network (`train.rs`) or, when the recipe asks for K > 1 members, an ensemble (`ensemble.rs`).

use std::sync::atomic::AtomicBool;

use anyhow::{Context, Result};

use crate::data::{build_samples, EpisodeSeries, InputSpec, Samples};
use crate::ensemble::train_ensemble;
use crate::train::{train_one, EpochReport, TrainConfig, Trained};

/// Train from episodes (train / validation division by the caller).
pub fn train(
    train: &[EpisodeSeries],
    val: &[EpisodeSeries],
    input: &InputSpec,
    cfg: &TrainConfig,
) -> Result<Trained> {
    train_with(train, val, input, cfg, &mut |_| {}, None)
}

/// [`train`] with a per-epoch observer and a cancel flag (checked every step; on cancel the
/// function returns an error that downcasts to [`crate::Cancelled`]).
pub fn train_with(
    train: &[EpisodeSeries],
    val: &[EpisodeSeries],
    input: &InputSpec,
    cfg: &TrainConfig,
    observer: &mut dyn FnMut(&EpochReport),
    cancel: Option<&AtomicBool>,
) -> Result<Trained> {
    let tr = build_samples(train, input, cfg.gamma).context("building train samples")?;
    let va = build_samples(val, input, cfg.gamma).context("building validation samples")?;
    train_samples(tr, va, input, cfg, observer, cancel)
}

/// Train on prepared (raw, un-normalised) samples. The step embedding width comes from `input`
/// and must be even (sin/cos pairs), as every client requires. With validation samples and
/// `cfg.obs_only_twin`, an observation-only twin is trained after the verifier and the
/// action-sensitivity figure recorded in the metrics.
///
/// The seeded stream is drawn in one fixed order (initialisation, each epoch's permutation,
/// dropout masks, observation noise), which is what makes both backends and every rerun train the
/// same model; `fit` reads top to bottom in that order.
pub fn train_samples(
    tr: Samples,
    va: Samples,
    input: &InputSpec,
    cfg: &TrainConfig,
    observer: &mut dyn FnMut(&EpochReport),
    cancel: Option<&AtomicBool>,
) -> Result<Trained> {
    if cfg.ensemble > 1 {
        return train_ensemble(tr, va, input, cfg, observer, cancel);
    }
    train_one(tr, va, input, cfg, None, observer, cancel)
}
