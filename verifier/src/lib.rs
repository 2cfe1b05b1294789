//! `verifier`: the ufops verifier core — the inference contract of a verifier artifact, once.
//!
//! It owns the artifact format (`config.json` and `manifest.json` types, [`format`](mod@format); the
//! contract is trainer/ARTIFACT.md), loading with every file checked against its sha256 (from a
//! directory, from bytes, or through any getter so the store and HTTP plug in: [`Artifact`]),
//! the artifact id, the weights and the one list of tensor names and shapes ([`Weights`],
//! [`Architecture::tensors`]), the step embedding, and the forward pass and its gradient w.r.t.
//! the action chunk for every variant ([`Verifier`]) — of one network or of an ensemble's
//! members, with the ensemble's rules for scores, best-of-N picks and guidance ([`ensemble`]) —
//! with AVX2/FMA kernels chosen at run time and a portable fallback ([`kernels`], which the trainer's fused training path shares). It
//! also builds the files the trainer writes ([`ArtifactFiles`]), and the verifier's inputs from
//! episodes ([`samples`]: what the trainer trains on and scorers query), from the store's steps
//! with feature `steps` (`steps::StepScorer`: how anything scores a stored episode; `stored`: the
//! scoring of a selection's stored episodes, read through the store's selection path, and the
//! error of the crates built on it, `monitor` and `replay`). The failure
//! monitor's record, running statistic and conformal threshold are here too ([`monitor`]), so the
//! offline evaluation, the robot and Python raise the same alarm at the same step, and so is the
//! action-sensitivity figure with its flag ([`quality`]), which the trainer records and the
//! steering helpers warn about, and the record of a steered step ([`telemetry`]: what
//! best-of-N saw and chose, kept with the episode for `ufops replay`).
//!
//! It has no heavy dependencies: `steer` (on the robot) and the Python package bind it. It does
//! not train (the `trainer` crate), sample policies or steer them (the `steer` crate).
//!
//! ```no_run
//! let v = verifier::Verifier::load_dir("artifact/")?;
//! let obs = vec![0.0; v.obs_dim()];
//! let candidates = vec![0.0; 10 * v.act_dim()];
//! let scores = v.score(&obs, &[7], &candidates, 10)?; // 10 scores
//! let grad = v.grad(&obs, &[7], &candidates[..v.act_dim()])?; // d log C / d chunk
//! # Ok::<(), verifier::VerifierError>(())
//! ```

pub mod artifact;
pub mod ensemble;
pub mod error;
pub mod format;
pub mod kernels;
mod math;
pub mod monitor;
mod net;
pub mod quality;
pub mod samples;
/// Verifier inputs from the store's steps batches and [`steps::StepScorer`] (feature `steps`).
#[cfg(feature = "steps")]
pub mod steps;
#[cfg(feature = "steps")]
pub mod stored;
pub mod telemetry;
/// Random artifacts for tests and benchmarks (feature `testing`).
#[cfg(any(test, feature = "testing"))]
pub mod testutil;
pub mod weights;

pub use artifact::{Artifact, ArtifactFiles};
pub use ensemble::{Picks, Verifier};
pub use error::{Result, VerifierError};
pub use format::{
    is_plain_name, member_prefix, short_hash, ActionSpace, Activation, Architecture, ArtifactConfig,
    EnsembleSpec, ExtraInput, ExtraInputSpec, InputConfig, InputLayout, Kind, LinearSpec, Manifest, ObsKey,
    TensorRole, TensorSpec, Variant, CONFIG_FILE, ENSEMBLE_SCHEMA_VERSION, MANIFEST_FILE, MAX_MEMBERS,
    MODEL_FILE, SCHEMA_VERSION,
};
pub use math::{sigmoid, time_embedding_into};
pub use monitor::{MonitorRecord, MonitorState, MonitorStep};
pub use quality::ActionSensitivity;
pub use samples::{build_samples, EpisodeSeries, ObsSeries, Samples};
#[cfg(feature = "steps")]
pub use steps::StepScorer;
pub use telemetry::SteeringStep;
pub use weights::{Tensor, Weights};

use sha2::{Digest, Sha256};

/// Lower-case hex sha256 of `bytes`.
pub fn sha256_hex(bytes: &[u8]) -> String {
    hex::encode(Sha256::digest(bytes))
}

/// The artifact id: the first 16 hex digits of sha256(manifest.json bytes).
pub fn artifact_id(manifest_bytes: &[u8]) -> String {
    sha256_hex(manifest_bytes)[..16].to_string()
}
