//! Ensembles (`TrainConfig.ensemble = K`, `ufops train --ensemble K`): K members trained on one
//! split, member `k` with seed `seed + k` on a bootstrap resample of the training episodes (drawn
//! with replacement, as many as there are), all with the full training set's statistics, so
//! they share one `input` and differ only in their weights. The artifact is one (schema 2,
//! trainer/ARTIFACT.md "Ensembles"); the scores, picks and gradients are the verifier core's
//! (`verifier::ensemble`), which also scores the held-out samples for the figures here.

use std::collections::BTreeMap;
use std::sync::atomic::AtomicBool;
use std::time::Instant;

use anyhow::{ensure, Result};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use crate::data::{InputSpec, Normalization, Samples};
use crate::metrics::{pearson, roc_auc, EnsembleMetrics};
use crate::model::Kind;
use crate::train::{train_one, EpochReport, TrainConfig, Trained};

/// The rows of `s` listed in `rows` (repeats kept), as samples of their own.
fn gather(s: &Samples, rows: &[u32]) -> Samples {
    let (od, ad) = (s.obs_dim, s.act_dim);
    let pick = |v: &[f32], d: usize| -> Vec<f32> {
        let mut out = Vec::with_capacity(rows.len() * d);
        for &r in rows {
            out.extend_from_slice(&v[r as usize * d..(r as usize + 1) * d]);
        }
        out
    };
    let one = |v: &[f32]| rows.iter().map(|&r| v[r as usize]).collect::<Vec<f32>>();
    let n = s.len().max(1);
    Samples {
        obs_dim: od,
        act_dim: ad,
        obs: pick(&s.obs, od),
        act: pick(&s.act, ad),
        t: rows.iter().map(|&r| s.t[r as usize]).collect(),
        extras: s.extras.iter().map(|x| pick(x, x.len() / n)).collect(),
        label: one(&s.label),
        q_target: one(&s.q_target),
        discount: one(&s.discount),
        episode: rows.iter().map(|&r| s.episode[r as usize]).collect(),
    }
}

/// Trains the K members ([`TrainConfig::ensemble`]) and returns them as one [`Trained`]:
/// member 0's run (its epochs, timings and, when the recipe asks, its observation-only twin's
/// action-sensitivity figure) with every member's weights in `members`, the ensemble's held-out
/// AUROC (or Pearson) in `metrics`, and the rest in `ensemble`.
pub(crate) fn train_ensemble(
    tr: Samples,
    va: Samples,
    input: &InputSpec,
    cfg: &TrainConfig,
    observer: &mut dyn FnMut(&EpochReport),
    cancel: Option<&AtomicBool>,
) -> Result<Trained> {
    let start = Instant::now();
    let k = cfg.ensemble;
    ensure!(k >= 2, "an ensemble needs at least 2 members, got {k}");
    ensure!(!tr.is_empty(), "no training samples");
    cfg.validate()?;
    cfg.action_space.validate(input.action_dim)?;
    // The full training set's statistics, in the verifier's input space (as `prepare` fits them).
    let fitted = {
        let mut probe = tr.clone();
        cfg.action_space.raw_to_input(&mut probe.act, input.action_dim);
        Normalization::fit(&probe, input, !cfg.action_space.is_policy(), cfg.std_floor as f32)
    };
    for w in &fitted.warnings {
        tracing::warn!("{w}");
    }
    let mut by_episode: BTreeMap<u32, Vec<u32>> = BTreeMap::new();
    for (row, &e) in tr.episode.iter().enumerate() {
        by_episode.entry(e).or_default().push(row as u32);
    }
    let episodes: Vec<u32> = by_episode.keys().copied().collect();
    let mut members: Vec<Trained> = Vec::with_capacity(k);
    let (mut seeds, mut distinct) = (Vec::with_capacity(k), Vec::with_capacity(k));
    for m in 0..k {
        let seed = cfg.seed.wrapping_add(m as u64);
        let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 0xb007_57a9_0e45_e3b1);
        let draw: Vec<u32> =
            (0..episodes.len()).map(|_| episodes[rng.gen_range(0..episodes.len())]).collect();
        let mut seen = draw.clone();
        seen.sort_unstable();
        seen.dedup();
        let rows: Vec<u32> = draw.iter().flat_map(|e| by_episode[e].iter().copied()).collect();
        let member_cfg =
            TrainConfig { seed, ensemble: 1, obs_only_twin: cfg.obs_only_twin && m == 0, ..cfg.clone() };
        tracing::info!(
            "ensemble member {}/{k}: seed {seed}, {} of {} training episodes drawn ({} distinct)",
            m + 1,
            draw.len(),
            episodes.len(),
            seen.len()
        );
        members.push(train_one(
            gather(&tr, &rows),
            va.clone(),
            input,
            &member_cfg,
            Some(&fitted.norm),
            observer,
            cancel,
        )?);
        seeds.push(seed);
        distinct.push(seen.len());
    }
    let mut it = members.into_iter();
    let mut trained = it.next().expect("k >= 2 members were trained");
    let rest: Vec<Trained> = it.collect();
    trained.members =
        std::iter::once(trained.params.clone()).chain(rest.iter().map(|t| t.params.clone())).collect();
    trained.config = cfg.clone();
    trained.metrics.warnings = fitted.warnings;
    let seconds = start.elapsed().as_secs_f64();
    trained.metrics.seconds = seconds;
    let mut metrics = EnsembleMetrics {
        members: k,
        seeds,
        train_episodes: episodes.len(),
        distinct_episodes: distinct,
        val_auc: None,
        member_val_auc: Vec::new(),
        val_pearson: None,
        val_mean_spread: None,
        seconds,
    };
    if !va.is_empty() {
        held_out(&trained, &va, input, &mut metrics)?;
        trained.metrics.val_auc = metrics.val_auc;
        trained.metrics.val_pearson = metrics.val_pearson;
    }
    trained.ensemble = Some(metrics);
    Ok(trained)
}

/// Scores the held-out samples with the ensemble through the core and fills the figures.
fn held_out(trained: &Trained, va: &Samples, input: &InputSpec, m: &mut EnsembleMetrics) -> Result<()> {
    let v = crate::artifact::verifier_of(trained)?;
    let mut act = va.act.clone();
    trained.action_space.raw_to_input(&mut act, input.action_dim);
    let extras: Vec<&[f32]> = va.extras.iter().map(Vec::as_slice).collect();
    let b = va.len();
    let (mut mean, mut spread) = (vec![0f32; b], vec![0f32; b]);
    v.score_spread_into(&va.obs, &extras, &va.t, &act, 1, &mut mean, &mut spread)?;
    let mut all = vec![0f32; v.members() * b];
    v.score_members_into(&va.obs, &extras, &va.t, &act, 1, &mut all)?;
    m.val_auc = roc_auc(&mean, &va.label);
    m.member_val_auc = all.chunks(b.max(1)).map(|s| roc_auc(s, &va.label)).collect();
    if v.kind() == Kind::Q {
        m.val_pearson = pearson(&mean, &va.q_target);
    }
    m.val_mean_spread = Some(spread.iter().map(|&s| s as f64).sum::<f64>() / b.max(1) as f64);
    Ok(())
}
