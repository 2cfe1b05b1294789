#![allow(dead_code)]
//! Synthetic episodes for tests.

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;
use trainer::{EpisodeSeries, InputSpec, ObsKey, ObsSeries};

pub fn normal(rng: &mut ChaCha8Rng) -> f32 {
    rng.sample(StandardNormal)
}

/// Episodes whose success is determined by the actions: successful episodes act with
/// `a[0] ~ N(+1, 0.5)`, failed ones with `a[0] ~ N(-1, 0.5)`; observations are noise.
pub fn action_task(n_eps: usize, steps: usize, seed: u64) -> Vec<EpisodeSeries> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    (0..n_eps)
        .map(|e| {
            let success = e % 2 == 0;
            let s = if success { 1.0 } else { -1.0 };
            let pos: Vec<f32> = (0..steps * 3).map(|_| normal(&mut rng)).collect();
            let vel: Vec<f32> = (0..steps).map(|_| normal(&mut rng)).collect();
            let mut actions = Vec::with_capacity(steps * 2);
            for _ in 0..steps {
                actions.push(s + 0.5 * normal(&mut rng));
                actions.push(normal(&mut rng));
            }
            EpisodeSeries {
                id: format!("ep{e}"),
                success,
                obs: vec![
                    ObsSeries { key: "pos".into(), dim: 3, values: pos },
                    ObsSeries { key: "vel".into(), dim: 1, values: vel },
                ],
                actions,
                action_dim: 2,
                action_chunk: None,
                policy_steps: None,
            }
        })
        .collect()
}

pub fn action_spec() -> InputSpec {
    InputSpec {
        obs_keys: vec![ObsKey::new("pos", 3), ObsKey::new("vel", 1)],
        obs_history: 2,
        chunk_len: 4,
        action_dim: 2,
        t_embed_dim: 16,
        extra_inputs: vec![],
    }
}

/// Successful episodes of varying length whose observation carries the remaining steps
/// (`(T - t) / 20` plus noise), so `gamma^(T-t)` is predictable.
pub fn q_task(n_eps: usize, seed: u64) -> Vec<EpisodeSeries> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    (0..n_eps)
        .map(|e| {
            let steps = rng.gen_range(20..50);
            let success = e % 4 != 3;
            let mut obs = Vec::new();
            for t in 0..steps {
                let remaining = (steps - 1 - t) as f32;
                obs.push(remaining / 20.0 + 0.02 * normal(&mut rng));
                obs.push(normal(&mut rng));
            }
            let actions: Vec<f32> =
                (0..steps).map(|_| if success { 1.0 } else { -1.0 } + 0.3 * normal(&mut rng)).collect();
            EpisodeSeries {
                id: format!("q{e}"),
                success,
                obs: vec![ObsSeries { key: "s".into(), dim: 2, values: obs }],
                actions,
                action_dim: 1,
                action_chunk: None,
                policy_steps: None,
            }
        })
        .collect()
}

pub fn q_spec() -> InputSpec {
    InputSpec {
        obs_keys: vec![ObsKey::new("s", 2)],
        obs_history: 1,
        chunk_len: 2,
        action_dim: 1,
        t_embed_dim: 8,
        extra_inputs: vec![],
    }
}
