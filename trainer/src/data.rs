//! Training samples built from episodes: observation history, action chunk, step index, labels,
//! discounted Q targets, and train-set standardisation statistics.
//!
//! This module deliberately knows nothing about the store: the caller converts its rollouts into
//! [`Episode`]s and decides the train/validation division.

use anyhow::{bail, ensure, Context, Result};
use serde::{Deserialize, Serialize};

/// One observation modality of an episode, `values` is `steps * dim`, row-major.
#[derive(Clone, Debug, PartialEq)]
pub struct ObsSeries {
    pub key: String,
    pub dim: usize,
    pub values: Vec<f32>,
}

/// One rollout as the trainer needs it.
#[derive(Clone, Debug, PartialEq)]
pub struct Episode {
    pub id: String,
    pub success: bool,
    pub obs: Vec<ObsSeries>,
    /// Executed actions, `steps * action_dim`, row-major.
    pub actions: Vec<f32>,
    pub action_dim: usize,
    /// Optional stored action chunk per step: `(H, steps * H * action_dim)`.
    pub action_chunk: Option<(usize, Vec<f32>)>,
}

impl Episode {
    /// Number of steps (rows of `actions`).
    pub fn steps(&self) -> usize {
        self.actions.len().checked_div(self.action_dim).unwrap_or(0)
    }

    fn series(&self, key: &str) -> Result<&ObsSeries> {
        self.obs
            .iter()
            .find(|s| s.key == key)
            .with_context(|| format!("episode {}: no observation key {key:?}", self.id))
    }
}

/// How samples are built (observation keys, history, chunk shape, step-embedding width): the
/// core's input layout, which the artifact records as `config.json`'s `input`.
pub use verifier::InputLayout as InputSpec;
pub use verifier::{time_embedding_into, ExtraInputSpec, ObsKey};

/// Mean/std standardisation statistics (train set), std clamped to a floor.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Normalization {
    pub obs_mean: Vec<f32>,
    pub obs_std: Vec<f32>,
    pub act_mean: Vec<f32>,
    pub act_std: Vec<f32>,
}

/// Statistics fitted on a training set, with a warning per (near-)constant dimension.
#[derive(Clone, Debug, PartialEq)]
pub struct Fitted {
    pub norm: Normalization,
    /// One message per dimension whose std was below the floor (clamped to it): such a
    /// dimension would otherwise be multiplied by up to 1/std at inference.
    pub warnings: Vec<String>,
}

impl Normalization {
    /// Statistics of a sample set: population std, clamped to `std_floor`. With
    /// `standardize_actions` false (actions in the policy's space) the action statistics are
    /// the identity. Warnings name each clamped dimension by key, history step and component.
    pub fn fit(s: &Samples, input: &InputSpec, standardize_actions: bool, std_floor: f32) -> Fitted {
        let mut warnings = Vec::new();
        let (obs_mean, obs_std, low) = col_stats(&s.obs, s.obs_dim, std_floor);
        let per_step = input.step_obs_dim().max(1);
        for (k, sd) in low {
            let (h, mut off) = (k / per_step, k % per_step);
            let mut name = format!("obs[{k}]");
            for key in &input.obs_keys {
                if off < key.dim {
                    name = format!(
                        "obs[{k}] (key {:?}[{off}], history step {h} of {})",
                        key.key, input.obs_history
                    );
                    break;
                }
                off -= key.dim;
            }
            warnings.push(format!(
                "{name} is (near-)constant in the training set: std {sd:.3e} clamped to {std_floor:.1e}"
            ));
        }
        let (act_mean, act_std) = if standardize_actions {
            let (m, sd, low) = col_stats(&s.act, s.act_dim, std_floor);
            let a = input.action_dim.max(1);
            for (k, v) in low {
                warnings.push(format!(
                    "act[{k}] (chunk step {}, action component {}) is (near-)constant in the training set: std {v:.3e} clamped to {std_floor:.1e}",
                    k / a,
                    k % a
                ));
            }
            (m, sd)
        } else {
            (vec![0.0; s.act_dim], vec![1.0; s.act_dim])
        };
        Fitted { norm: Normalization { obs_mean, obs_std, act_mean, act_std }, warnings }
    }

    /// Identity statistics (mean 0, std 1).
    pub fn identity(obs_dim: usize, act_dim: usize) -> Self {
        Normalization {
            obs_mean: vec![0.0; obs_dim],
            obs_std: vec![1.0; obs_dim],
            act_mean: vec![0.0; act_dim],
            act_std: vec![1.0; act_dim],
        }
    }

    /// Standardise `obs`/`act` rows in place.
    pub fn apply(&self, obs: &mut [f32], act: &mut [f32]) {
        standardize(obs, &self.obs_mean, &self.obs_std);
        standardize(act, &self.act_mean, &self.act_std);
    }
}

fn standardize(x: &mut [f32], mean: &[f32], std: &[f32]) {
    let d = mean.len();
    if d == 0 {
        return;
    }
    for row in x.chunks_exact_mut(d) {
        for ((v, m), s) in row.iter_mut().zip(mean).zip(std) {
            *v = (*v - m) / s;
        }
    }
}

/// Column means and population stds, each std clamped to `floor`; also the (column, std) of
/// every clamped column.
fn col_stats(x: &[f32], d: usize, floor: f32) -> (Vec<f32>, Vec<f32>, Vec<(usize, f32)>) {
    let n = x.len().checked_div(d).unwrap_or(0);
    let mut mean = vec![0f64; d];
    for row in x.chunks_exact(d.max(1)).take(n) {
        for (m, v) in mean.iter_mut().zip(row) {
            *m += *v as f64;
        }
    }
    let nn = n.max(1) as f64;
    mean.iter_mut().for_each(|m| *m /= nn);
    let mut var = vec![0f64; d];
    for row in x.chunks_exact(d.max(1)).take(n) {
        for ((s, v), m) in var.iter_mut().zip(row).zip(&mean) {
            let c = *v as f64 - m;
            *s += c * c;
        }
    }
    let mut low = Vec::new();
    let std = var
        .iter()
        .enumerate()
        .map(|(k, s)| {
            let sd = (s / nn).sqrt() as f32;
            if sd < floor {
                low.push((k, sd));
            }
            sd.max(floor)
        })
        .collect();
    (mean.iter().map(|m| *m as f32).collect(), std, low)
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
    /// Episode step index `t` of each sample.
    pub t: Vec<u32>,
    /// Extra inputs, one `n * dim` array per [`ExtraInputSpec`].
    pub extras: Vec<Vec<f32>>,
    /// Episode success (1.0 / 0.0).
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

/// Build one sample per step of every episode (raw, un-normalised values).
pub fn build_samples(episodes: &[Episode], spec: &InputSpec, gamma: f64) -> Result<Samples> {
    ensure!(spec.obs_history >= 1, "obs_history must be >= 1");
    ensure!(spec.chunk_len >= 1, "chunk_len must be >= 1");
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
        ensure!(
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
        ensure!(ep.actions.len() == steps * a_dim, "episode {}: ragged actions", ep.id);
        let series: Vec<&ObsSeries> =
            spec.obs_keys.iter().map(|k| ep.series(&k.key)).collect::<Result<_>>()?;
        for (k, sr) in spec.obs_keys.iter().zip(&series) {
            if sr.dim != k.dim || sr.values.len() != steps * k.dim {
                bail!(
                    "episode {}: obs {:?} has dim {} and {} values, expected dim {} x {} steps",
                    ep.id,
                    k.key,
                    sr.dim,
                    sr.values.len(),
                    k.dim,
                    steps
                );
            }
        }
        let extras: Vec<&ObsSeries> = spec
            .extra_inputs
            .iter()
            .map(|x| {
                let sr = ep.series(&x.key)?;
                ensure!(
                    sr.dim == x.dim && sr.values.len() == steps * x.dim,
                    "episode {}: extra input {:?} has wrong shape",
                    ep.id,
                    x.key
                );
                Ok(sr)
            })
            .collect::<Result<_>>()?;
        if let Some((ch, v)) = &ep.action_chunk {
            ensure!(*ch == h, "episode {}: stored chunk length {ch} != chunk_len {h}", ep.id);
            ensure!(v.len() == steps * h * a_dim, "episode {}: ragged action_chunk", ep.id);
        }
        let big_t = (steps - 1) as i32;
        let r = if ep.success { 1.0 } else { 0.0 };
        for t in 0..steps {
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
                        let src = (t + j).min(steps - 1);
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

/// Embedding of one step index.
pub fn time_embedding(t: f64, d: usize) -> Vec<f32> {
    let mut v = vec![0.0; d];
    verifier::time_embedding_into(t, &mut v);
    v
}

/// Cache of step embeddings for integer steps `0..len` (grown on demand).
#[derive(Clone, Debug, Default)]
pub struct TimeEmbedTable {
    d: usize,
    table: Vec<f32>,
}

impl TimeEmbedTable {
    pub fn new(d: usize) -> Self {
        TimeEmbedTable { d, table: Vec::new() }
    }
    /// Make sure steps `0..=max_t` are cached.
    pub fn ensure(&mut self, max_t: u32) {
        let have = self.table.len().checked_div(self.d).unwrap_or(usize::MAX);
        let need = max_t as usize + 1;
        if have >= need {
            return;
        }
        self.table.resize(need * self.d, 0.0);
        for t in have..need {
            verifier::time_embedding_into(t as f64, &mut self.table[t * self.d..(t + 1) * self.d]);
        }
    }
    /// Embedding of step `t` (must have been `ensure`d).
    pub fn get(&self, t: u32) -> &[f32] {
        let t = t as usize;
        &self.table[t * self.d..(t + 1) * self.d]
    }
}
