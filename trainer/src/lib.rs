//! `trainer`: the ufops verifier trainer.
//!
//! This crate owns TRAINING: the verifier models as trainable candle graphs (success classifier
//! and time-to-success Q, `model.rs`, plus a fused fast path for the low-dim architecture in
//! `fast.rs`), their losses (`loss.rs`), the training loop and recipe (`train.rs`, `optim.rs`,
//! `metrics.rs`), the entry points that pick one network or an ensemble (`run.rs`), ensembles of members on bootstrap resamples (`ensemble.rs`), the
//! standardisation statistics over the core's samples (`data.rs`, no
//! dependency on the store), writing artifacts and scoring rows (`artifact.rs`), and training
//! jobs that read a split from the store and publish the artifact back (`job.rs`).
//!
//! The inference contract — artifact types, files and checks, tensor names, the step
//! embedding, the samples built from episodes (and from stored steps), the forward pass and its
//! gradient, the LayerNorm kernels — is the `verifier` core's (`trainer/ARTIFACT.md`); the
//! trainer writes and scores through it.

pub mod artifact;
pub mod data;
pub mod ensemble;
pub mod fast;
pub mod job;
pub mod loss;
pub mod metrics;
pub mod model;
pub mod optim;
pub mod run;
pub mod train;

pub use artifact::{
    grad_rows, load_artifact, parse_rows, score, score_json, score_rows, spread_rows, write_artifact,
    ArtifactConfig, ArtifactInfo, ScoreRow, TrainedArtifact,
};
pub use data::{build_samples, EpisodeSeries, ExtraInputSpec, InputSpec, ObsKey, ObsSeries, Samples};
pub use job::{load_split, run_train_job, SplitData, TrainJobSpec};
pub use model::{Architecture, Kind, ModelSpec, Variant};
pub use run::{train, train_samples, train_with};
pub use train::{Cancelled, EpochReport, Metrics, RecipeInput, TrainBackend, TrainConfig, Trained};
pub use verifier::{ActionSpace, Verifier};
