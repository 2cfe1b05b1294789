//! `trainer`: the ufops verifier trainer.
//!
//! This crate owns the verifier models (success classifier and time-to-success Q, `model.rs`,
//! written in candle as the single source of truth, plus a fused fast path for the low-dim
//! architecture in `fast.rs`), their losses (`loss.rs`), the training loop and recipe
//! (`train.rs`, `optim.rs`, `metrics.rs`), sample construction from episodes (`data.rs`, with no
//! dependency on the store), the artifact format: writing, verified loading and reference
//! scoring (`artifact.rs`, contract in `ARTIFACT.md`), and training jobs that read a split from
//! the store and publish the artifact back (`job.rs`).

pub mod artifact;
pub mod data;
pub mod fast;
pub mod job;
pub mod loss;
pub mod metrics;
pub mod model;
pub mod optim;
pub mod train;

pub use artifact::{load_artifact, score, score_json, write_artifact, Artifact, ArtifactConfig, ArtifactInfo, ScoreRow};
pub use job::{load_split, run_train_job, score_steps, SplitData, TrainJobSpec};
pub use data::{build_samples, Episode, ExtraInputSpec, InputSpec, ObsKey, ObsSeries, Samples};
pub use model::{Architecture, Kind, ModelSpec, Variant};
pub use train::{train, train_samples, train_with, Backend, Cancelled, EpochReport, Metrics, TrainConfig, Trained};
