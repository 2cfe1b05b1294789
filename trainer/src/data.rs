//! What training adds to the verifier core's samples (`verifier::samples`: observation history,
//! action chunk, step index, labels, discounted Q targets): the train-set standardisation
//! statistics and a cache of step embeddings.
//!
//! This module deliberately knows nothing about the store: the caller converts its rollouts into
//! [`EpisodeSeries`]s and decides the train/validation division.

use serde::{Deserialize, Serialize};

/// How samples are built (observation keys, history, chunk shape, step-embedding width): the
/// core's input layout, which the artifact records as `config.json`'s `input`.
pub use verifier::InputLayout as InputSpec;
pub use verifier::{
    build_samples, time_embedding_into, EpisodeSeries, ExtraInputSpec, ObsKey, ObsSeries, Samples,
};

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
