//! A simulated labeling campaign on the demo's rollouts. The base diffusion
//! policy of `ufops demo` is trained (quick scale) and rolled out; a pool of rollouts is labeled
//! 50 at a time in verifier-uncertainty order (nearest 0.5 first, as the review queue serves) or
//! in random order, a classifier (the real trainer, the demo's recipe) is retrained after each
//! batch, and its AUROC on held-out rollouts is printed as a curve.
//!
//! `cargo bench -p demo --bench review_campaign` (quick: a few minutes on 2 cores);
//! `UFOPS_CAMPAIGN_POOL`, `UFOPS_CAMPAIGN_BUDGET`, `UFOPS_CAMPAIGN_SEED` for other runs.
#![allow(
    clippy::unwrap_used,
    clippy::too_many_lines,
    reason = "benchmarks: a failed unwrap is a failed run, and a measurement reads top to bottom"
)]

use anyhow::Result;
use demo::review_campaign::{run, table, AskOrder, Campaign, CurvePoint};
use sim::{rollout, ChunkChoice, DiffusionPolicy, EnvConfig, PolicyConfig};
use std::time::Instant;

fn env_usize(k: &str, d: usize) -> usize {
    std::env::var(k).ok().and_then(|v| v.parse().ok()).unwrap_or(d)
}

/// A sim rollout as the trainer reads it (the same columns `ufops demo` ingests).
fn trainer_episode(i: usize, e: &sim::Episode, horizon: usize) -> trainer::EpisodeSeries {
    let n = e.length;
    trainer::EpisodeSeries {
        id: format!("rollout_{i}"),
        success: e.success,
        obs: vec![trainer::ObsSeries {
            key: "pos".into(),
            dim: 2,
            values: e.positions[..n].iter().flatten().copied().collect(),
        }],
        actions: e.actions.iter().flatten().copied().collect(),
        action_dim: 2,
        action_chunk: Some((horizon, e.action_chunks.iter().flatten().copied().collect())),
        policy_steps: None,
    }
}

/// Each episode's score: the mean of its steps' scores (what the `score` job stores).
fn mean_scores(
    v: &trainer::Verifier,
    eps: &[trainer::EpisodeSeries],
    input: &trainer::InputSpec,
) -> Result<Vec<f64>> {
    eps.iter()
        .map(|e| {
            let mut s = trainer::build_samples(std::slice::from_ref(e), input, 0.99)?;
            v.config().input.action_space.raw_to_input(&mut s.act, input.action_dim);
            let x = v.score(&s.obs, &s.t, &s.act, 1)?;
            Ok(x.iter().map(|&y| y as f64).sum::<f64>() / x.len().max(1) as f64)
        })
        .collect()
}

fn main() -> Result<()> {
    let t0 = Instant::now();
    let seed = env_usize("UFOPS_CAMPAIGN_SEED", 0) as u64;
    let pool_n = env_usize("UFOPS_CAMPAIGN_POOL", 300);
    let budget = env_usize("UFOPS_CAMPAIGN_BUDGET", 220);
    let held_n = 200;
    let env = EnvConfig::default();
    let pc = PolicyConfig::default();
    let demos = sim::expert_demos(&env, 60, seed);
    let tc = sim::PolicyTrainConfig { steps: 800, seed, ..Default::default() };
    let base = DiffusionPolicy::train(&pc, &tc, &demos)?;
    let pool_eps = rollout(&base, &env, pool_n, ChunkChoice::None, seed + 100)?;
    let held_eps = rollout(&base, &env, held_n, ChunkChoice::None, seed + 300)?;
    let pool: Vec<trainer::EpisodeSeries> =
        pool_eps.iter().enumerate().map(|(i, e)| trainer_episode(i, e, pc.horizon)).collect();
    let held: Vec<trainer::EpisodeSeries> =
        held_eps.iter().enumerate().map(|(i, e)| trainer_episode(i, e, pc.horizon)).collect();
    let held_labels: Vec<f32> = held.iter().map(|e| e.success as u8 as f32).collect();
    println!(
        "review_campaign: base policy success {:.2} (pool {pool_n}), {:.2} (held-out {held_n}); rollouts ready in {:.0} s",
        pool.iter().filter(|e| e.success).count() as f64 / pool_n as f64,
        held_labels.iter().sum::<f32>() as f64 / held_n as f64,
        t0.elapsed().as_secs_f64()
    );
    let input = trainer::InputSpec {
        obs_keys: vec![trainer::ObsKey::new("pos", 2)],
        obs_history: 2,
        chunk_len: pc.horizon,
        action_dim: 2,
        t_embed_dim: 64,
        extra_inputs: vec![],
    };
    let norm = pc.action_normalizer();
    let cfg = trainer::TrainConfig {
        kind: trainer::Kind::Classifier,
        epochs: 40,
        seed,
        early_stopping_patience: Some(10),
        action_space: trainer::ActionSpace::policy(norm.scale.clone(), norm.offset.clone()),
        ..Default::default()
    };
    let stride = pc.n_exec as u32;
    let fit = |labeled: &[usize]| -> Result<(Vec<f64>, Option<f64>)> {
        // Every fifth labeled episode validates (checkpoint choice); the held-out set never trains.
        let (mut tr, mut va) = (Vec::new(), Vec::new());
        for (k, &i) in labeled.iter().enumerate() {
            if k % 5 == 4 {
                va.push(pool[i].clone())
            } else {
                tr.push(pool[i].clone())
            }
        }
        let keep = |t: u32| t.is_multiple_of(stride);
        let trs = trainer::build_samples(&tr, &input, cfg.gamma)?.filter_steps(keep);
        let vas = trainer::build_samples(&va, &input, cfg.gamma)?.filter_steps(keep);
        let trained =
            trainer::train_samples(trs, vas, &input, &cfg, &mut |_: &trainer::EpochReport| {}, None)?;
        let dir = tempfile::tempdir()?;
        trainer::write_artifact(dir.path(), &trained, serde_json::json!({"bench": "review_campaign"}))?;
        let v = trainer::Verifier::load_dir(dir.path())?;
        let scores = mean_scores(&v, &pool, &input)?;
        let held_scores: Vec<f32> = mean_scores(&v, &held, &input)?.iter().map(|&x| x as f32).collect();
        Ok((scores, trainer::metrics::roc_auc(&held_scores, &held_labels)))
    };
    let c = Campaign { pool: pool_n, start: 20, batch: 50, budget, seed };
    let unc = run(&c, AskOrder::Uncertain, fit)?;
    let rnd = run(&c, AskOrder::Random, fit)?;
    println!("{}", table(&unc, &rnd));
    let mean = |c: &[CurvePoint]| c.iter().filter_map(|p| p.auroc).sum::<f64>() / c.len() as f64;
    println!(
        "mean AUROC over the curve: uncertain-first {:.3}, random {:.3} ({:.0} s in all)",
        mean(&unc),
        mean(&rnd),
        t0.elapsed().as_secs_f64()
    );
    Ok(())
}
