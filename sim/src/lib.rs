//! `sim`: the paper's pedagogical 2-D navigation task (Sec. "Pedagogical Navigation Task").
//!
//! It owns: the vectorised environment ([`env`](mod@env): start on the left, goal circle on the right, a
//! vertical wall with a wide and a narrow gap, velocity control, test-time position noise), the
//! expert demonstrations ([`demos`]: smooth curves through both gaps in equal numbers), the base
//! policies ([`policy`]: a small candle MLP DDPM noise predictor implementing
//! `steer::NoisePredictor`, and a flow-matching twin implementing `steer::VelocityField`), rollouts
//! returning per-episode trajectories, unsteered or steered with any `steer::Scorer` ([`rollout`](mod@rollout)),
//! the statistics used in the report ([`stats`]: Wilson and Newcombe intervals, re-exported from
//! `evalstats`) and a PNG trajectory plot ([`plot`]). It does not train verifiers (the `trainer` crate does).

pub mod demos;
pub mod env;
pub mod plot;
pub mod policy;
pub mod rollout;
/// The interval arithmetic, from the one crate that owns it.
pub use evalstats as stats;

pub use demos::{expert_demos, Demo};
pub use env::{EnvConfig, NavEnv};
pub use policy::{ChunkPolicy, DiffusionPolicy, FlowPolicy, PolicyConfig, PolicyTrainConfig};
pub use rollout::{rollout, success_rate, ChunkChoice, Episode, Outcome};
