//! Training behaviour: sample construction, separation of a synthetic task, Q correlation,
//! reproducibility, cancellation, config files, and the candle backend on the features variant.

use crate::common;

use std::sync::atomic::AtomicBool;

use trainer::data::{build_samples, time_embedding};
use trainer::{EpisodeSeries, InputSpec, Kind, ObsKey, ObsSeries, TrainBackend, TrainConfig, Variant};

#[test]
fn samples_history_chunks_and_targets() {
    let ep = EpisodeSeries {
        id: "e".into(),
        success: true,
        obs: vec![
            ObsSeries { key: "b".into(), dim: 1, values: vec![10.0, 11.0, 12.0] },
            ObsSeries { key: "a".into(), dim: 2, values: vec![0.0, 0.5, 1.0, 1.5, 2.0, 2.5] },
        ],
        actions: vec![1.0, 2.0, 3.0],
        action_dim: 1,
        action_chunk: None,
        policy_steps: None,
    };
    let spec = InputSpec {
        obs_keys: vec![ObsKey::new("a", 2), ObsKey::new("b", 1)],
        obs_history: 2,
        chunk_len: 2,
        action_dim: 1,
        t_embed_dim: 4,
        extra_inputs: vec![],
    };
    let s = build_samples(std::slice::from_ref(&ep), &spec, 0.5).unwrap();
    assert_eq!(s.len(), 3);
    assert_eq!(s.obs_dim, 6);
    // t = 0: first observation repeated; keys in spec order (a then b).
    assert_eq!(&s.obs[0..6], &[0.0, 0.5, 10.0, 0.0, 0.5, 10.0]);
    assert_eq!(&s.obs[6..12], &[0.0, 0.5, 10.0, 1.0, 1.5, 11.0]);
    assert_eq!(&s.obs[12..18], &[1.0, 1.5, 11.0, 2.0, 2.5, 12.0]);
    // Chunks: next H executed actions, padded with the last.
    assert_eq!(s.act, vec![1.0, 2.0, 2.0, 3.0, 3.0, 3.0]);
    assert_eq!(s.t, vec![0, 1, 2]);
    assert_eq!(s.q_target, vec![0.25, 0.5, 1.0]);
    assert_eq!(s.label, vec![1.0; 3]);
    // Failure: zero targets; stored chunks are used when present.
    let mut f = ep.clone();
    f.success = false;
    f.action_chunk = Some((2, vec![9.0, 8.0, 7.0, 6.0, 5.0, 4.0]));
    let s = build_samples(&[f], &spec, 0.5).unwrap();
    assert_eq!(s.q_target, vec![0.0; 3]);
    assert_eq!(s.discount, vec![0.25, 0.5, 1.0]);
    assert_eq!(s.act, vec![9.0, 8.0, 7.0, 6.0, 5.0, 4.0]);
    // Step embedding (paper eq. 1).
    let e = time_embedding(3.0, 4);
    assert!((e[0] - 3f32.sin()).abs() < 1e-7);
    assert!((e[1] - 3f32.cos()).abs() < 1e-7);
    assert!((e[2] - (3.0f64 / 100.0).sin() as f32).abs() < 1e-7);
    assert!((e[3] - (3.0f64 / 100.0).cos() as f32).abs() < 1e-7);
}

fn small_cfg(kind: Kind) -> TrainConfig {
    TrainConfig { kind, epochs: 12, batch_size: 128, seed: 3, ..Default::default() }
}

#[test]
fn classifier_separates_action_dependent_success() {
    let eps = common::action_task(40, 30, 1);
    let val = common::action_task(12, 30, 2);
    let mut seen = Vec::new();
    let r = trainer::train_with(
        &eps,
        &val,
        &common::action_spec(),
        &small_cfg(Kind::Classifier),
        &mut |e| seen.push(e.clone()),
        None,
    )
    .unwrap();
    assert_eq!(seen.len(), 12);
    assert_eq!(r.metrics.backend, "fast");
    let auc = r.metrics.val_auc.unwrap();
    assert!(auc > 0.95, "val AUC {auc}");
    assert!(seen.last().unwrap().train_loss < seen[0].train_loss);
}

/// The same episodes with the success signal moved from the actions into the observation: the
/// outcome is visible before any chunk is chosen.
fn observation_task(n_eps: usize, seed: u64) -> Vec<trainer::EpisodeSeries> {
    let mut eps = common::action_task(n_eps, 30, seed);
    for e in &mut eps {
        let sign = if e.success { 1.0 } else { -1.0 };
        for (i, a) in e.actions.iter_mut().enumerate() {
            if i % 2 == 0 {
                *a -= sign; // a[0] ~ N(0, 0.5) whatever the outcome
            }
        }
        for (i, p) in e.obs[0].values.iter_mut().enumerate() {
            if i % 3 == 0 {
                *p = sign + 0.5 * *p; // pos[0] ~ N(±1, 0.5)
            }
        }
    }
    eps
}

/// The observation-only twin tells the two apart: where the chunk decides the outcome, the
/// verifier ranks chunks well among samples the twin scores alike (not flagged); where the
/// observation does, its AUROC is as high but earned by the observation, and it is flagged.
#[test]
fn the_twin_tells_a_chunk_that_decides_from_an_observation_that_does() {
    let cfg = small_cfg(Kind::Classifier);
    let spec = common::action_spec();
    let r = trainer::train(&common::action_task(40, 30, 1), &common::action_task(12, 30, 2), &spec, &cfg)
        .unwrap();
    let s = r.metrics.action_sensitivity.clone().expect("trained with validation samples");
    assert!(
        r.metrics.val_auc.unwrap() > 0.95 && s.obs_only_auc.unwrap() < 0.75,
        "{:?} {s:?}",
        r.metrics.val_auc
    );
    assert!(s.action_auc.unwrap() > 0.9 && !s.flagged, "{s:?}");
    assert!((s.auc_gain.unwrap() - (r.metrics.val_auc.unwrap() - s.obs_only_auc.unwrap())).abs() < 1e-12);

    let o = trainer::train(&observation_task(40, 1), &observation_task(12, 2), &spec, &cfg).unwrap();
    let s = o.metrics.action_sensitivity.clone().unwrap();
    assert!(o.metrics.val_auc.unwrap() > 0.95 && s.obs_only_auc.unwrap() > 0.95, "{s:?}");
    assert!(s.auc_gain.unwrap().abs() < 0.03, "{s:?}");
    assert!(s.flagged && s.reason.as_deref().is_some_and(|r| r.contains("observation-only twin")), "{s:?}");

    // The twin is the recipe's to turn off, and needs validation samples.
    let off = TrainConfig { obs_only_twin: false, epochs: 2, ..cfg.clone() };
    assert!(trainer::train(&common::action_task(8, 30, 1), &common::action_task(4, 30, 2), &spec, &off)
        .unwrap()
        .metrics
        .action_sensitivity
        .is_none());
    let no_val = TrainConfig { epochs: 2, ..cfg };
    assert!(trainer::train(&common::action_task(8, 30, 1), &[], &spec, &no_val)
        .unwrap()
        .metrics
        .action_sensitivity
        .is_none());
}

#[test]
fn q_correlates_with_discounted_time_to_success() {
    let tr = common::q_task(40, 1);
    let va = common::q_task(12, 2);
    let mut cfg = small_cfg(Kind::Q);
    cfg.gamma = 0.9;
    cfg.epochs = 25;
    let r = trainer::train(&tr, &va, &common::q_spec(), &cfg).unwrap();
    let p = r.metrics.val_pearson.unwrap();
    assert!(p > 0.9, "val pearson {p}");
}

#[test]
fn same_seed_same_weights_different_seed_different() {
    let eps = common::action_task(10, 20, 1);
    let val = common::action_task(4, 20, 2);
    for backend in [TrainBackend::Fast, TrainBackend::Candle] {
        let cfg = TrainConfig { epochs: 2, batch_size: 64, seed: 42, backend, ..Default::default() };
        let a = trainer::train(&eps, &val, &common::action_spec(), &cfg).unwrap();
        let b = trainer::train(&eps, &val, &common::action_spec(), &cfg).unwrap();
        assert_eq!(a.params, b.params, "{backend:?}: not reproducible");
        assert_eq!(
            a.history.iter().map(|h| h.train_loss).collect::<Vec<_>>(),
            b.history.iter().map(|h| h.train_loss).collect::<Vec<_>>()
        );
        let c = trainer::train(&eps, &val, &common::action_spec(), &TrainConfig { seed: 43, ..cfg }).unwrap();
        assert_ne!(a.params, c.params);
    }
}

#[test]
fn fast_and_candle_backends_train_alike() {
    // Same seed, same draws: the two backends follow the same trajectory up to float rounding.
    let eps = common::action_task(10, 20, 1);
    let val = common::action_task(4, 20, 2);
    let cfg = TrainConfig { epochs: 2, batch_size: 64, seed: 5, ..Default::default() };
    let a = trainer::train(
        &eps,
        &val,
        &common::action_spec(),
        &TrainConfig { backend: TrainBackend::Fast, ..cfg.clone() },
    )
    .unwrap();
    let b = trainer::train(
        &eps,
        &val,
        &common::action_spec(),
        &TrainConfig { backend: TrainBackend::Candle, ..cfg },
    )
    .unwrap();
    for (x, y) in a.history.iter().zip(&b.history) {
        assert!((x.train_loss - y.train_loss).abs() < 1e-3, "{} vs {}", x.train_loss, y.train_loss);
    }
    let max_diff = a
        .params
        .values
        .iter()
        .flatten()
        .zip(b.params.values.iter().flatten())
        .map(|(x, y)| (x - y).abs())
        .fold(0f32, f32::max);
    assert!(max_diff < 1e-3, "weights diverged by {max_diff}");
}

#[test]
fn cancel_flag_stops_training() {
    let eps = common::action_task(6, 20, 1);
    let flag = AtomicBool::new(true);
    let err = trainer::train_with(
        &eps,
        &[],
        &common::action_spec(),
        &small_cfg(Kind::Classifier),
        &mut |_| {},
        Some(&flag),
    )
    .unwrap_err();
    assert!(err.downcast_ref::<trainer::Cancelled>().is_some());
}

#[test]
fn early_stopping_and_no_validation_set() {
    // Two of twelve training episodes carry the wrong label: the model first learns the rule
    // (validation loss falls), then memorises the flipped ones (it rises again), so there is a
    // real best epoch, reached through epochs that did not improve.
    let mut eps = common::action_task(12, 20, 1);
    for e in eps.iter_mut().take(2) {
        e.success = !e.success;
    }
    let val = common::action_task(8, 20, 9);
    let spec = common::action_spec();
    let mut cfg = TrainConfig { epochs: 30, batch_size: 32, seed: 5, ..Default::default() };
    cfg.optimizer.lr = 3e-3;
    // The reference: every epoch, no early stopping (the same trajectory: patience draws nothing).
    let full = trainer::train(&eps, &val, &spec, &cfg).unwrap();
    assert!(!full.metrics.early_stopped && full.metrics.epochs_run == 30);
    let losses: Vec<f64> = full.history.iter().map(|h| h.val_loss.unwrap()).collect();
    // (best epoch, last epoch) of a run with patience p: it stops p epochs after the best so far.
    let expected_stop = |p: usize| {
        let (mut best_loss, mut best) = (f64::INFINITY, 0);
        for (i, &l) in losses.iter().enumerate() {
            if l < best_loss {
                (best_loss, best) = (l, i + 1);
            }
            if i + 1 - best >= p {
                return (best, i + 1);
            }
        }
        (best, losses.len())
    };
    let mut runs = Vec::new();
    for p in [2, 3] {
        let r = trainer::train(
            &eps,
            &val,
            &spec,
            &TrainConfig { early_stopping_patience: Some(p), ..cfg.clone() },
        )
        .unwrap();
        let (best, last) = expected_stop(p);
        assert!(r.metrics.early_stopped && last < cfg.epochs, "patience {p}: ran every epoch");
        assert_eq!(
            (r.metrics.best_epoch, r.metrics.epochs_run),
            (best, last),
            "patience {p}, val losses {losses:?}"
        );
        assert_eq!(last - best, p, "patience {p}: stops exactly {p} epochs after the best");
        let seen: Vec<f64> = r.history.iter().map(|h| h.val_loss.unwrap()).collect();
        assert_eq!(seen.as_slice(), &losses[..last], "patience {p}: another trajectory");
        assert_eq!(r.metrics.best_val_loss, Some(losses[best - 1]));
        assert!(r.history[best - 1].best && r.history[best..].iter().all(|h| !h.best));
        runs.push(r);
    }
    // Not the trivial case: patience 3 rode out a worse stretch that stopped patience 2, and found
    // a better epoch after it.
    assert!(runs[1].metrics.best_epoch > runs[0].metrics.epochs_run, "{losses:?}");
    // The best epoch's weights are kept, not the last ones: the patience-3 run (stopped at its
    // best + 3) and the full run (30 epochs) share only their best epoch.
    assert_eq!(full.metrics.best_epoch, runs[1].metrics.best_epoch, "{losses:?}");
    assert!(
        runs[1].params == full.params,
        "patience 3 did not keep epoch {}'s weights",
        full.metrics.best_epoch
    );
    assert!(runs[0].params != full.params, "patience 2 kept weights it never reached");

    // No validation set: the best epoch is chosen by the training loss.
    let r = trainer::train(&eps, &[], &spec, &TrainConfig { epochs: 4, ..cfg }).unwrap();
    assert!(r.metrics.val_auc.is_none() && r.history.iter().all(|h| h.val_loss.is_none()));
    let min_train = r.history.iter().map(|h| h.train_loss).fold(f64::INFINITY, f64::min);
    assert_eq!(r.metrics.best_val_loss, Some(min_train));
    assert_eq!(r.history[r.metrics.best_epoch - 1].train_loss, min_train);
}

#[test]
fn config_from_json_and_toml_files() {
    let dir = tempfile::tempdir().unwrap();
    let j = dir.path().join("c.json");
    std::fs::write(&j, r#"{"kind": "q", "epochs": 7, "contrastive_weight": 0.2, "optimizer": {"lr": 0.01, "weight_decay": 0.0, "beta1": 0.9, "beta2": 0.99, "eps": 1e-8}}"#).unwrap();
    let c = TrainConfig::from_file(&j).unwrap();
    assert_eq!((c.kind, c.epochs, c.batch_size), (Kind::Q, 7, 1024));
    assert_eq!(c.contrastive_weight, 0.2);
    assert_eq!(c.optimizer.lr, 0.01);
    let t = dir.path().join("c.toml");
    std::fs::write(&t, "epochs = 3\nseed = 9\nearly_stopping_patience = 5\n[architecture]\nvariant = \"lowdim\"\nactivation = \"relu\"\nencoder_width = 32\nt_embed_dim = 16\ntrunk_dims = [64, 32]\ninput_layernorm = false\nencoder_layernorm = false\nspectral_norm = false\ndropout = 0.5\nlayernorm_eps = 1e-5\n").unwrap();
    let c = TrainConfig::from_file(&t).unwrap();
    assert_eq!(
        (c.epochs, c.seed, c.early_stopping_patience, c.architecture.encoder_width),
        (3, 9, Some(5), 32)
    );
    std::fs::write(&j, r#"{"epoch": 3}"#).unwrap();
    assert!(TrainConfig::from_file(&j).is_err(), "unknown fields are rejected");
    // Round trip of the defaults.
    let d = TrainConfig::default();
    assert_eq!(serde_json::from_str::<TrainConfig>(&serde_json::to_string(&d).unwrap()).unwrap(), d);
}

#[test]
fn features_variant_trains_with_candle_backend() {
    let eps = common::action_task(8, 20, 1);
    let val = common::action_task(4, 20, 2);
    let mut cfg = TrainConfig::preset(Kind::Q, Variant::Features);
    cfg.architecture.encoder_width = 16;
    cfg.architecture.trunk_dims = vec![32, 16];
    cfg.epochs = 2;
    cfg.batch_size = 64;
    let mut spec = common::action_spec();
    spec.t_embed_dim = 8;
    let r = trainer::train(&eps, &val, &spec, &cfg).unwrap();
    assert_eq!(r.metrics.backend, "candle");
    assert!(r.metrics.best_val_loss.unwrap().is_finite());
    let i = r.params.index("trunk.0.weight").unwrap();
    let s = trainer::model::spectral_norm_estimate(&r.params.values[i], 32, r.params.shapes[i][1], 300, 1);
    // One power iteration per step: sigma estimate is close to, and never above, the true norm.
    assert!(s > 0.9 && s < 1.5, "sigma of the stored weight {s}");
}

#[test]
fn fast_path_honours_observation_noise() {
    // obs_noise_std on the lowdim model: the fused path adds the same noise as the candle graph
    // (same draws), so both backends train alike — and differently from training without noise.
    let eps = common::action_task(10, 20, 1);
    let val = common::action_task(4, 20, 2);
    let cfg = TrainConfig { epochs: 2, batch_size: 64, seed: 5, obs_noise_std: 0.3, ..Default::default() };
    let fast = trainer::train(
        &eps,
        &val,
        &common::action_spec(),
        &TrainConfig { backend: TrainBackend::Fast, ..cfg.clone() },
    )
    .unwrap();
    let candle = trainer::train(
        &eps,
        &val,
        &common::action_spec(),
        &TrainConfig { backend: TrainBackend::Candle, ..cfg.clone() },
    )
    .unwrap();
    assert_eq!(fast.metrics.backend, "fast");
    let diff = |a: &trainer::Trained, b: &trainer::Trained| {
        a.params
            .values
            .iter()
            .flatten()
            .zip(b.params.values.iter().flatten())
            .map(|(x, y)| (x - y).abs())
            .fold(0f32, f32::max)
    };
    assert!(diff(&fast, &candle) < 1e-3, "fast and candle diverge with noise: {}", diff(&fast, &candle));
    let quiet =
        trainer::train(&eps, &val, &common::action_spec(), &TrainConfig { obs_noise_std: 0.0, ..cfg })
            .unwrap();
    assert!(diff(&fast, &quiet) > 1e-3, "the noise changed nothing: it was ignored");
}

#[test]
fn odd_step_embedding_is_refused_at_train_time() {
    let eps = common::action_task(4, 10, 1);
    let mut spec = common::action_spec();
    spec.t_embed_dim = 7;
    let e = trainer::train(&eps, &[], &spec, &TrainConfig { epochs: 1, ..Default::default() }).unwrap_err();
    assert!(format!("{e:#}").contains("even"), "{e:#}");
}

#[test]
fn constant_dimensions_are_clamped_to_the_floor_and_named() {
    let mut eps = common::action_task(6, 20, 1);
    for e in &mut eps {
        // "vel" constant up to float noise.
        let vel = e.obs.iter_mut().find(|o| o.key == "vel").unwrap();
        vel.values.iter_mut().enumerate().for_each(|(i, v)| *v = 0.25 + 1e-7 * (i % 2) as f32);
    }
    let cfg = TrainConfig { epochs: 1, batch_size: 64, ..Default::default() };
    let t = trainer::train(&eps, &[], &common::action_spec(), &cfg).unwrap();
    // obs = 2 steps of [pos (3), vel (1)]: dims 3 and 7 are the constant ones.
    let floor = cfg.std_floor as f32;
    for k in 0..8 {
        if k == 3 || k == 7 {
            assert_eq!(t.norm.obs_std[k], floor, "dim {k}");
        } else {
            assert!(t.norm.obs_std[k] > 0.5, "dim {k}: {}", t.norm.obs_std[k]);
        }
    }
    let w = &t.metrics.warnings;
    assert_eq!(w.len(), 2, "{w:?}");
    assert!(
        w[0].contains("obs[3]") && w[0].contains("\"vel\"") && w[0].contains("history step 0"),
        "{}",
        w[0]
    );
    assert!(w[1].contains("obs[7]") && w[1].contains("history step 1"), "{}", w[1]);
    // A bad floor is a config error.
    assert!(
        trainer::train(&eps, &[], &common::action_spec(), &TrainConfig { std_floor: 0.0, ..cfg }).is_err()
    );
}

#[test]
fn actions_are_fed_in_the_policy_space_by_default() {
    // raw = x * scale + offset. Training on raw actions with the normaliser is training on the
    // policy-space actions with no normaliser: nothing re-standardises them.
    let (scale, offset) = (vec![2.0f32, 0.5], vec![1.0f32, -0.25]);
    let raw = common::action_task(8, 20, 1);
    let mut policy = raw.clone();
    for e in &mut policy {
        for (i, a) in e.actions.iter_mut().enumerate() {
            *a = (*a - offset[i % 2]) / scale[i % 2];
        }
    }
    let cfg = TrainConfig { epochs: 2, batch_size: 64, seed: 2, ..Default::default() };
    assert_eq!(cfg.action_space, trainer::ActionSpace::default());
    let with_norm = TrainConfig {
        action_space: trainer::ActionSpace::policy(scale.clone(), offset.clone()),
        ..cfg.clone()
    };
    let a = trainer::train(&raw, &[], &common::action_spec(), &with_norm).unwrap();
    let b = trainer::train(&policy, &[], &common::action_spec(), &cfg).unwrap();
    assert!(a.norm.act_mean.iter().all(|m| *m == 0.0) && a.norm.act_std.iter().all(|s| *s == 1.0));
    let d = a
        .params
        .values
        .iter()
        .flatten()
        .zip(b.params.values.iter().flatten())
        .map(|(x, y)| (x - y).abs())
        .fold(0f32, f32::max);
    assert!(d < 1e-5, "policy-space training differs by {d}");
    // The artifact records the normaliser; the older recipe records train-set statistics.
    let dir = tempfile::tempdir().unwrap();
    trainer::write_artifact(dir.path(), &a, serde_json::Value::Null).unwrap();
    let c: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.path().join("config.json")).unwrap()).unwrap();
    assert_eq!(
        c["input"]["action_space"],
        serde_json::json!({"space": "policy", "scale": [2.0, 0.5], "offset": [1.0, -0.25]})
    );
    let s = trainer::train(
        &raw,
        &[],
        &common::action_spec(),
        &TrainConfig { action_space: trainer::ActionSpace::Standardized, ..cfg },
    )
    .unwrap();
    assert!(s.norm.act_mean[0] > 0.5 || s.norm.act_mean[0] < -0.5 || s.norm.act_std[0] != 1.0);
    let dir = tempfile::tempdir().unwrap();
    trainer::write_artifact(dir.path(), &s, serde_json::Value::Null).unwrap();
    let c: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.path().join("config.json")).unwrap()).unwrap();
    assert_eq!(c["input"]["action_space"], serde_json::json!({"space": "standardized"}));
}
