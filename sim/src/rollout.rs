//! Vectorised rollouts of a base policy, unsteered or steered with any `steer::Scorer`
//! (best-of-N, DDPM classifier guidance, flow guidance), returning per-episode trajectories.
use crate::env::{EnvConfig, Gap, NavEnv, Status};
use crate::policy::ChunkPolicy;
use anyhow::Result;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};
use steer::{best_of_n_raw, best_of_n_recorded, Guidance, Scorer};

/// How chunks are chosen at each re-planning step.
#[derive(Clone, Copy)]
pub enum ChunkChoice<'a> {
    /// the base policy
    None,
    /// sample `n` chunks, execute the verifier's argmax (Algorithm 1)
    BestOfN { scorer: &'a dyn Scorer, n: usize },
    /// best-of-N that records each step's candidates, scores and choice in
    /// [`Episode::steering`] (`steer::best_of_n_recorded`: candidates on the f16 grid)
    RecordedBestOfN { scorer: &'a dyn Scorer, n: usize },
    /// verifier guidance inside the sampler (Algorithm 2 for DDPM, its flow analogue for flow)
    Guided { scorer: &'a dyn Scorer, lambda: f32 },
}

impl ChunkChoice<'_> {
    pub fn label(&self) -> String {
        match self {
            ChunkChoice::None => "base".into(),
            ChunkChoice::BestOfN { n, .. } | ChunkChoice::RecordedBestOfN { n, .. } => format!("best-of-{n}"),
            ChunkChoice::Guided { lambda, .. } => format!("guided(lambda={lambda})"),
        }
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum Outcome {
    Success,
    Collision,
    Timeout,
}

/// One episode. Step `t` (0..length) observed `positions[t]` (obs key `pos`, dim 2), executed
/// `actions[t]` (dim 2, the clipped velocity), which was entry `chunk_offset[t]` of the raw chunk
/// `action_chunks[t]` (`horizon * 2`, row-major H x 2) sampled at the last re-planning step
/// (`chunk_offset[t] == 0` marks re-planning steps: the (obs, chunk, t) the verifier is queried on).
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Episode {
    /// length + 1 positions (the last is the final position)
    pub positions: Vec<[f32; 2]>,
    pub actions: Vec<[f32; 2]>,
    pub action_chunks: Vec<Vec<f32>>,
    pub chunk_offset: Vec<usize>,
    pub length: usize,
    pub success: bool,
    pub outcome: Outcome,
    /// which gap the trajectory crossed the wall line at (None if it never did)
    pub gap: Option<Gap>,
    /// steering telemetry, one record per re-planning step ([`ChunkChoice::RecordedBestOfN`]
    /// only; empty otherwise)
    #[serde(skip)]
    pub steering: Vec<steer::SteeringStep>,
    /// Best-of-N re-planning steps, and those at which an ensemble verifier's members disagreed
    /// so the policy's own first candidate was kept ([`steer::BestOfN::fell_back`]).
    #[serde(default)]
    pub best_of_n_steps: u32,
    #[serde(default)]
    pub fell_back: u32,
}

/// (successes, episodes, rate)
pub fn success_rate(eps: &[Episode]) -> (u64, u64, f64) {
    let k = eps.iter().filter(|e| e.success).count() as u64;
    let n = eps.len() as u64;
    (k, n, if n > 0 { k as f64 / n as f64 } else { 0.0 })
}

/// Verifier observation for env history `hist` (positions so far): the `t_o` most recent positions,
/// oldest first, the first one repeated at the start of an episode.
pub fn obs_history(hist: &[[f32; 2]], t_o: usize, out: &mut Vec<f32>) {
    let n = hist.len();
    for s in 0..t_o {
        let idx = (n as isize - t_o as isize + s as isize).max(0) as usize;
        out.extend_from_slice(&hist[idx]);
    }
}

/// Roll out `n_episodes` episodes in lockstep with test-time noise. `seed` fixes the start
/// positions and the environment noise (one RNG) and the policy's sampling (another), so base and
/// steered runs with the same seed face the same starts and noise sequence.
#[allow(
    clippy::too_many_lines,
    reason = "one rollout's loop: policy, steering, environment and record, step by step"
)]
pub fn rollout(
    policy: &dyn ChunkPolicy,
    env_cfg: &EnvConfig,
    n_episodes: usize,
    steering: ChunkChoice,
    seed: u64,
) -> Result<Vec<Episode>> {
    let pc = policy.config().clone();
    let mut env_rng = ChaCha8Rng::seed_from_u64(seed);
    let mut pol_rng = ChaCha8Rng::seed_from_u64(seed ^ 0x5eed0f901c7);
    let mut env = NavEnv::new(env_cfg.clone(), n_episodes, true, &mut env_rng);
    let mut eps: Vec<Episode> = (0..n_episodes)
        .map(|i| Episode {
            positions: vec![env.pos(i)],
            actions: vec![],
            action_chunks: vec![],
            chunk_offset: vec![],
            length: 0,
            success: false,
            outcome: Outcome::Timeout,
            gap: None,
            steering: Vec::new(),
            best_of_n_steps: 0,
            fell_back: 0,
        })
        .collect();
    let ad = pc.act_dim();
    if let ChunkChoice::BestOfN { scorer, .. }
    | ChunkChoice::RecordedBestOfN { scorer, .. }
    | ChunkChoice::Guided { scorer, .. } = steering
    {
        anyhow::ensure!(scorer.act_dim() == ad, "scorer act_dim {} != policy chunk {}", scorer.act_dim(), ad);
        anyhow::ensure!(scorer.obs_dim() % 2 == 0, "scorer obs_dim {} is not T_o * 2", scorer.obs_dim());
    }
    let mut step = 0usize;
    loop {
        let alive: Vec<usize> = (0..n_episodes).filter(|&i| env.running(i)).collect();
        if alive.is_empty() {
            break;
        }
        let mut obs = Vec::with_capacity(alive.len() * 4);
        for &i in &alive {
            obs_history(&eps[i].positions, 2, &mut obs);
        }
        let verifier_obs = |scorer: &dyn Scorer| {
            let t_o = scorer.obs_dim() / 2;
            let mut v = Vec::with_capacity(alive.len() * scorer.obs_dim());
            for &i in &alive {
                obs_history(&eps[i].positions, t_o, &mut v);
            }
            v
        };
        let ts = vec![step as u32; alive.len()];
        let chunks = match steering {
            ChunkChoice::None => policy.sample_chunks(&obs, None, &mut pol_rng)?,
            ChunkChoice::BestOfN { scorer, n } | ChunkChoice::RecordedBestOfN { scorer, n } => {
                let mut rep = Vec::with_capacity(obs.len() * n);
                for row in obs.chunks(4) {
                    for _ in 0..n {
                        rep.extend_from_slice(row);
                    }
                }
                let cands = policy.sample_chunks(&rep, None, &mut pol_rng)?;
                let space = policy.sample_space();
                let vo = verifier_obs(scorer);
                let best = if let ChunkChoice::RecordedBestOfN { .. } = steering {
                    let (best, log) = best_of_n_recorded(scorer, Some(&space), &vo, &ts, &cands, n)?;
                    for (&i, record) in alive.iter().zip(log) {
                        eps[i].steering.push(record);
                    }
                    best
                } else {
                    best_of_n_raw(scorer, Some(&space), &vo, &ts, &cands, n)?
                };
                for (&i, &f) in alive.iter().zip(&best.fell_back) {
                    eps[i].best_of_n_steps += 1;
                    eps[i].fell_back += f as u32;
                }
                best.chunks
            }
            ChunkChoice::Guided { scorer, lambda } => {
                let vo = verifier_obs(scorer);
                let g = Guidance { scorer, obs: &vo, t: &ts, lambda };
                policy.sample_chunks(&obs, Some(&g), &mut pol_rng)?
            }
        };
        for j in 0..pc.n_exec.min(pc.horizon) {
            for (r, &i) in alive.iter().enumerate() {
                if !env.running(i) {
                    continue;
                }
                let chunk = &chunks[r * ad..(r + 1) * ad];
                let a = env.step(i, [chunk[2 * j], chunk[2 * j + 1]], &mut env_rng);
                let e = &mut eps[i];
                e.actions.push(a);
                e.action_chunks.push(chunk.to_vec());
                e.chunk_offset.push(j);
                e.positions.push(env.pos(i));
            }
        }
        step += pc.n_exec.min(pc.horizon);
    }
    for (i, e) in eps.iter_mut().enumerate() {
        e.length = e.actions.len();
        e.outcome = match env.status[i] {
            Status::Success => Outcome::Success,
            Status::Collision => Outcome::Collision,
            _ => Outcome::Timeout,
        };
        e.success = e.outcome == Outcome::Success;
        e.gap = env_cfg.gap_of(&e.positions);
    }
    Ok(eps)
}

/// Summary line: success rate with Wilson 95% interval and failure/gap breakdown.
pub fn summary(label: &str, eps: &[Episode]) -> String {
    let (k, n, r) = success_rate(eps);
    let (lo, hi) = crate::stats::wilson(k, n);
    let count = |f: &dyn Fn(&Episode) -> bool| eps.iter().filter(|e| f(e)).count();
    format!(
        "{label}: {k}/{n} = {:.1}% [{:.1}, {:.1}]; wide gap {} (ok {}), narrow gap {} (ok {}); collisions {}, timeouts {}",
        100.0 * r,
        100.0 * lo,
        100.0 * hi,
        count(&|e| e.gap == Some(Gap::Wide)),
        count(&|e| e.gap == Some(Gap::Wide) && e.success),
        count(&|e| e.gap == Some(Gap::Narrow)),
        count(&|e| e.gap == Some(Gap::Narrow) && e.success),
        count(&|e| e.outcome == Outcome::Collision),
        count(&|e| e.outcome == Outcome::Timeout),
    )
}
