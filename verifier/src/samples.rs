//! Verifier inputs built from episodes, the one definition the trainer trains on and every
//! scorer of stored steps queries with: per step, the observation history (oldest first, the
//! first observation repeated at the episode start), the action chunk (the stored one, else the
//! next `H` executed actions, the last repeated), the step index, the label and the discounted
//! Q target `γ^(T−t)·r`.
//!
//! It knows nothing about the store: callers turn their rollouts into [`EpisodeSeries`]
//! (`steps::episode_from_steps` does it for stored steps, behind the `steps` feature).

use crate::{InputLayout, Result, VerifierError};

/// `Err(VerifierError::Input)` with the message unless `cond` holds.
macro_rules! ensure_input {
    ($cond:expr, $($fmt:tt)+) => {
        if !$cond {
            return Err(VerifierError::Input(format!($($fmt)+)));
        }
    };
}

/// One observation modality of an episode, `values` is `steps * dim`, row-major.
#[derive(Clone, Debug, PartialEq)]
pub struct ObsSeries {
    pub key: String,
    pub dim: usize,
    pub values: Vec<f32>,
}

/// One rollout as the trainer needs it.
#[derive(Clone, Debug, PartialEq)]
pub struct EpisodeSeries {
    pub id: String,
    pub success: bool,
    pub obs: Vec<ObsSeries>,
    /// Executed actions, `steps * action_dim`, row-major.
    pub actions: Vec<f32>,
    pub action_dim: usize,
    /// Optional stored action chunk per step: `(H, steps * H * action_dim)`.
    pub action_chunk: Option<(usize, Vec<f32>)>,
    /// Build samples only for the steps before this one: the first step a human took over, after
    /// which the rollout is no longer the policy's own behaviour. `None`: every step.
    pub policy_steps: Option<usize>,
}

impl EpisodeSeries {
    /// Number of steps (rows of `actions`).
    pub fn steps(&self) -> usize {
        self.actions.len().checked_div(self.action_dim).unwrap_or(0)
    }

    fn series(&self, key: &str) -> Result<&ObsSeries> {
        self.obs
            .iter()
            .find(|s| s.key == key)
            .ok_or_else(|| VerifierError::Input(format!("episode {}: no observation key {key:?}", self.id)))
    }
}

/// Flat, row-major sample arrays.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Samples {
    pub obs_dim: usize,
    pub act_dim: usize,
    /// `n * obs_dim`
    pub obs: Vec<f32>,
    /// `n * act_dim`
    pub act: Vec<f32>,
    /// EpisodeSeries step index `t` of each sample.
    pub t: Vec<u32>,
    /// Extra inputs, one `n * dim` array per [`crate::ExtraInputSpec`].
    pub extras: Vec<Vec<f32>>,
    /// EpisodeSeries success (1.0 / 0.0).
    pub label: Vec<f32>,
    /// `gamma^(T - t) * r_T`, `T = steps - 1`.
    pub q_target: Vec<f32>,
    /// `gamma^(T - t)` (regardless of success).
    pub discount: Vec<f32>,
    /// Index of the sample's episode in the list it was built from.
    pub episode: Vec<u32>,
}

impl Samples {
    pub fn len(&self) -> usize {
        self.t.len()
    }
    pub fn is_empty(&self) -> bool {
        self.t.is_empty()
    }
    /// The samples whose step index passes `keep` (e.g. the steps where a chunking policy
    /// re-planned, which are the (obs, chunk, t) a verifier is queried on at run time).
    pub fn filter_steps(&self, keep: impl Fn(u32) -> bool) -> Samples {
        let mut out = Samples { obs_dim: self.obs_dim, act_dim: self.act_dim, ..Default::default() };
        out.extras = vec![Vec::new(); self.extras.len()];
        for i in 0..self.len() {
            if !keep(self.t[i]) {
                continue;
            }
            out.obs.extend_from_slice(&self.obs[i * self.obs_dim..(i + 1) * self.obs_dim]);
            out.act.extend_from_slice(&self.act[i * self.act_dim..(i + 1) * self.act_dim]);
            for (dst, src) in out.extras.iter_mut().zip(&self.extras) {
                let d = src.len() / self.len();
                dst.extend_from_slice(&src[i * d..(i + 1) * d]);
            }
            out.t.push(self.t[i]);
            out.label.push(self.label[i]);
            out.q_target.push(self.q_target[i]);
            out.discount.push(self.discount[i]);
            out.episode.push(self.episode[i]);
        }
        out
    }

    /// Number of successful / failed samples.
    pub fn class_counts(&self) -> (usize, usize) {
        let pos = self.label.iter().filter(|&&l| l > 0.5).count();
        (pos, self.len() - pos)
    }
}

/// Build one sample per step of every episode (raw, un-normalised values), up to an episode's
/// `policy_steps`: the steps before a human took over, whose chunks (of executed actions) stop at
/// the takeover too; the Q target's `T` stays the episode's end.
pub fn build_samples(episodes: &[EpisodeSeries], spec: &InputLayout, gamma: f64) -> Result<Samples> {
    ensure_input!(spec.obs_history >= 1, "obs_history must be >= 1");
    ensure_input!(spec.chunk_len >= 1, "chunk_len must be >= 1");
    let obs_dim = spec.obs_dim();
    let act_dim = spec.act_dim();
    let total: usize = episodes.iter().map(|e| e.steps()).sum();
    let mut s = Samples {
        obs_dim,
        act_dim,
        obs: Vec::with_capacity(total * obs_dim),
        act: Vec::with_capacity(total * act_dim),
        extras: vec![Vec::new(); spec.extra_inputs.len()],
        ..Default::default()
    };
    let (h, a_dim) = (spec.chunk_len, spec.action_dim);
    for (ei, ep) in episodes.iter().enumerate() {
        ensure_input!(
            ep.action_dim == a_dim,
            "episode {}: action_dim {} != input spec action_dim {}",
            ep.id,
            ep.action_dim,
            a_dim
        );
        let steps = ep.steps();
        if steps == 0 {
            continue;
        }
        ensure_input!(ep.actions.len() == steps * a_dim, "episode {}: ragged actions", ep.id);
        let series: Vec<&ObsSeries> =
            spec.obs_keys.iter().map(|k| ep.series(&k.key)).collect::<Result<_>>()?;
        for (k, sr) in spec.obs_keys.iter().zip(&series) {
            if sr.dim != k.dim || sr.values.len() != steps * k.dim {
                return Err(VerifierError::Input(format!(
                    "episode {}: obs {:?} has dim {} and {} values, expected dim {} x {} steps",
                    ep.id,
                    k.key,
                    sr.dim,
                    sr.values.len(),
                    k.dim,
                    steps
                )));
            }
        }
        let extras: Vec<&ObsSeries> = spec
            .extra_inputs
            .iter()
            .map(|x| {
                let sr = ep.series(&x.key)?;
                ensure_input!(
                    sr.dim == x.dim && sr.values.len() == steps * x.dim,
                    "episode {}: extra input {:?} has wrong shape",
                    ep.id,
                    x.key
                );
                Ok(sr)
            })
            .collect::<Result<_>>()?;
        if let Some((ch, v)) = &ep.action_chunk {
            ensure_input!(*ch == h, "episode {}: stored chunk length {ch} != chunk_len {h}", ep.id);
            ensure_input!(v.len() == steps * h * a_dim, "episode {}: ragged action_chunk", ep.id);
        }
        let big_t = (steps - 1) as i32;
        let r = if ep.success { 1.0 } else { 0.0 };
        let end = ep.policy_steps.map_or(steps, |p| p.min(steps));
        for t in 0..end {
            // Observation history, oldest first, first observation repeated at episode start.
            for k in 0..spec.obs_history {
                let src = (t as isize - (spec.obs_history - 1 - k) as isize).max(0) as usize;
                for sr in &series {
                    s.obs.extend_from_slice(&sr.values[src * sr.dim..(src + 1) * sr.dim]);
                }
            }
            // Action chunk.
            match &ep.action_chunk {
                Some((_, v)) => s.act.extend_from_slice(&v[t * act_dim..(t + 1) * act_dim]),
                None => {
                    for j in 0..h {
                        let src = (t + j).min(end - 1);
                        s.act.extend_from_slice(&ep.actions[src * a_dim..(src + 1) * a_dim]);
                    }
                }
            }
            for (dst, sr) in s.extras.iter_mut().zip(&extras) {
                dst.extend_from_slice(&sr.values[t * sr.dim..(t + 1) * sr.dim]);
            }
            let disc = gamma.powi(big_t - t as i32);
            s.t.push(t as u32);
            s.label.push(r);
            s.discount.push(disc as f32);
            s.q_target.push((disc * r as f64) as f32);
            s.episode.push(ei as u32);
        }
    }
    Ok(s)
}
