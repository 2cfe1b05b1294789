//! Ensembles: K members on bootstrap resamples of the training episodes, one artifact whose
//! score is the members' mean (each member checked as a network of its own), figures of the
//! held-out samples, reruns identical, and one network's recipe and artifact unchanged.

use crate::common;

use trainer::artifact::{load_artifact, write_artifact};
use trainer::{Kind, TrainConfig};
use verifier::{member_prefix, Verifier, Weights, SCHEMA_VERSION};

fn cfg(kind: Kind, ensemble: usize) -> TrainConfig {
    TrainConfig { kind, epochs: 3, batch_size: 64, ensemble, ..Default::default() }
}

#[test]
fn an_ensemble_is_one_artifact_whose_score_is_its_members_mean() {
    let eps = common::action_task(12, 15, 1);
    let val = common::action_task(6, 15, 2);
    for kind in [Kind::Classifier, Kind::Q] {
        let t = trainer::train(&eps, &val, &common::action_spec(), &cfg(kind, 3)).unwrap();
        assert_eq!(t.members.len(), 3);
        let e = t.ensemble.clone().unwrap();
        assert_eq!((e.members, e.seeds.clone(), e.train_episodes), (3, vec![0, 1, 2], 12));
        assert!(e.distinct_episodes.iter().all(|&d| (1..=12).contains(&d)), "{:?}", e.distinct_episodes);
        assert!(e.distinct_episodes.iter().any(|&d| d < 12), "a bootstrap resample repeats episodes");
        assert_eq!(e.member_val_auc.len(), 3);
        assert!(e.val_auc.is_some() && t.metrics.val_auc == e.val_auc);
        assert_ne!(t.members[0].values, t.members[1].values, "members differ");

        let dir = tempfile::tempdir().unwrap();
        let info = write_artifact(dir.path(), &t, serde_json::json!({"test": "ensemble"})).unwrap();
        assert_eq!(info.manifest.schema_version, 2);
        let a = load_artifact(dir.path()).unwrap();
        assert_eq!(a.verifier.members(), 3);
        assert_eq!(a.params, t.members[0], "the trainer's view of an ensemble is its first member");
        assert!(a.config.metrics["ensemble"]["member_val_auc"].is_array());

        // Each member as a network of its own; the ensemble scores their mean.
        let raw = verifier::Artifact::load_dir(dir.path()).unwrap();
        let members: Vec<Verifier> = (0..3)
            .map(|k| {
                let mut one = raw.config.clone();
                one.schema_version = SCHEMA_VERSION;
                one.ensemble = None;
                let mut w = Weights::default();
                for (name, x) in raw.weights.iter() {
                    if let Some(rest) = name.strip_prefix(&member_prefix(k)) {
                        w.insert(rest, x.shape.clone(), x.data.clone()).unwrap();
                    }
                }
                Verifier::new(one, &w).unwrap()
            })
            .collect();
        let v = &a.verifier;
        let obs: Vec<f32> = (0..4 * v.obs_dim()).map(|i| (i as f32 * 0.37).sin()).collect();
        let act: Vec<f32> = (0..4 * 6 * v.act_dim()).map(|i| (i as f32 * 0.11).cos()).collect();
        let t4 = [0u32, 3, 7, 11];
        let got = v.score(&obs, &t4, &act, 6).unwrap();
        let per: Vec<Vec<f32>> = members.iter().map(|m| m.score(&obs, &t4, &act, 6).unwrap()).collect();
        for (i, g) in got.iter().enumerate() {
            let want = per.iter().map(|p| p[i]).sum::<f32>() / 3.0;
            assert!((g - want).abs() <= 1e-6 * want.abs().max(1.0), "{kind:?} score {i}: {g} vs {want}");
        }
    }
}

#[test]
fn ensembles_rerun_identically_and_one_network_is_written_as_before() {
    let eps = common::action_task(10, 15, 3);
    let val = common::action_task(4, 15, 4);
    let spec = common::action_spec();
    // (The artifact records wall times, so the weights are what must repeat.)
    let runs: Vec<trainer::Trained> =
        (0..2).map(|_| trainer::train(&eps, &val, &spec, &cfg(Kind::Classifier, 2)).unwrap()).collect();
    assert_eq!(runs[0].members, runs[1].members, "seeds and resamples are fixed by the recipe");
    let e = (runs[0].ensemble.as_ref().unwrap(), runs[1].ensemble.as_ref().unwrap());
    assert_eq!((&e.0.distinct_episodes, e.0.val_auc), (&e.1.distinct_episodes, e.1.val_auc));
    // One network: no `ensemble` key in its recipe, schema 1, so earlier artifacts' ids stand.
    let t = trainer::train(&eps, &val, &spec, &cfg(Kind::Classifier, 1)).unwrap();
    assert!(t.members.is_empty() && t.ensemble.is_none());
    let dir = tempfile::tempdir().unwrap();
    let info = write_artifact(dir.path(), &t, serde_json::Value::Null).unwrap();
    let config: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.path().join("config.json")).unwrap()).unwrap();
    assert_eq!((info.manifest.schema_version, config["schema_version"].as_u64()), (1, Some(1)));
    assert!(config["hyperparameters"].get("ensemble").is_none() && config.get("ensemble").is_none());
    // A recipe asking for too many members is refused before training.
    let e = trainer::train(&eps, &val, &spec, &cfg(Kind::Classifier, 65)).unwrap_err().to_string();
    assert!(e.contains("ensemble must be in 1..=64"), "{e}");
}
