//! Artifact writing, verified loading, content addressing and reference scoring.

use crate::common;

use trainer::artifact::{load_artifact, score_json, write_artifact, ScoreRow};
use trainer::data::build_samples;
use trainer::fast::{BatchSource, FastModel};
use trainer::{Kind, TrainConfig};

fn trained(kind: Kind) -> trainer::Trained {
    let eps = common::action_task(8, 15, 1);
    let val = common::action_task(4, 15, 2);
    let cfg = TrainConfig { kind, epochs: 2, batch_size: 64, ..Default::default() };
    trainer::train(&eps, &val, &common::action_spec(), &cfg).unwrap()
}

#[test]
fn write_load_score_roundtrip() {
    for kind in [Kind::Classifier, Kind::Q] {
        let t = trained(kind);
        let dir = tempfile::tempdir().unwrap();
        let lineage = serde_json::json!({"store_version": 3, "split_id": "s1"});
        let info = write_artifact(dir.path(), &t, lineage.clone()).unwrap();
        assert_eq!(info.id.len(), 16);
        let manifest = std::fs::read(dir.path().join("manifest.json")).unwrap();
        assert_eq!(info.id, trainer::artifact::sha256_hex(&manifest)[..16]);
        let a = load_artifact(dir.path()).unwrap();
        assert_eq!(a.id, info.id);
        assert_eq!(a.config.lineage, lineage);
        assert_eq!(a.params, t.params);
        assert_eq!(a.config.gamma.is_some(), kind == Kind::Q);
        let cfg: serde_json::Value =
            serde_json::from_slice(&std::fs::read(dir.path().join("config.json")).unwrap()).unwrap();
        for k in [
            "schema_version",
            "kind",
            "architecture",
            "input",
            "gamma",
            "hyperparameters",
            "metrics",
            "lineage",
        ] {
            assert!(cfg.get(k).is_some(), "config.json lacks {k}");
        }
        assert_eq!(cfg["input"]["obs_dim"], 8);
        assert_eq!(cfg["input"]["act_dim"], 8);
        // Writing the same model again gives the same id (deterministic bytes).
        let dir2 = tempfile::tempdir().unwrap();
        assert_eq!(write_artifact(dir2.path(), &t, lineage).unwrap().id, info.id);

        // Scores of raw rows equal the training-time forward on standardised rows.
        let eps = common::action_task(2, 15, 7);
        let s = build_samples(&eps, &t.input, 0.99).unwrap();
        let rows: Vec<ScoreRow> = (0..s.len())
            .map(|i| ScoreRow {
                obs: s.obs[i * s.obs_dim..(i + 1) * s.obs_dim].to_vec(),
                action: s.act[i * s.act_dim..(i + 1) * s.act_dim].to_vec(),
                t: s.t[i] as f64,
                extras: Default::default(),
            })
            .collect();
        let json = serde_json::json!({ "rows": rows }).to_string();
        let scores = score_json(dir.path(), &json).unwrap();
        let mut sn = s.clone();
        t.norm.apply(&mut sn.obs, &mut sn.act);
        let mut table = trainer::data::TimeEmbedTable::new(t.input.t_embed_dim);
        table.ensure(100);
        let mut f = FastModel::new(&t.spec, &t.params, s.len(), 1).unwrap();
        let idx: Vec<u32> = (0..s.len() as u32).collect();
        f.forward(
            &t.params,
            &BatchSource { obs: &sn.obs, act: &sn.act, t: &sn.t, temb: &table },
            &idx,
            None,
            None,
        );
        for (sc, y) in scores.iter().zip(f.y()) {
            let want = match kind {
                Kind::Classifier => trainer::loss::sigmoid(*y),
                Kind::Q => *y,
            };
            assert!((sc - want).abs() < 1e-5, "{sc} vs {want}");
        }
    }
}

#[test]
fn tampered_or_unknown_artifacts_are_refused() {
    let t = trained(Kind::Classifier);
    let dir = tempfile::tempdir().unwrap();
    write_artifact(dir.path(), &t, serde_json::Value::Null).unwrap();
    let p = dir.path().join("config.json");
    let orig = std::fs::read_to_string(&p).unwrap();
    std::fs::write(&p, orig.replace("\"lowdim\"", "\"fancy\"")).unwrap();
    let e = load_artifact(dir.path()).err().unwrap().to_string();
    assert!(e.contains("sha256 mismatch"), "{e}");
    // Unknown variant with a consistent manifest.
    let bytes = std::fs::read(&p).unwrap();
    let mpath = dir.path().join("manifest.json");
    let m = std::fs::read_to_string(&mpath).unwrap();
    let old = trainer::artifact::sha256_hex(orig.as_bytes());
    std::fs::write(&mpath, m.replace(&old, &trainer::artifact::sha256_hex(&bytes))).unwrap();
    let e = load_artifact(dir.path()).err().unwrap().to_string();
    assert!(e.contains("unknown architecture.variant"), "{e}");
    // Wrong row width.
    std::fs::write(&p, &orig).unwrap();
    std::fs::write(&mpath, &m).unwrap();
    assert!(score_json(dir.path(), r#"{"rows":[{"obs":[1.0],"action":[1.0],"t":0}]}"#).is_err());
}

/// The artifact stores spectrally normalised weights already divided by sigma; its scores
/// (through the verifier core) must equal the candle model WITH spectral norm active (weights
/// W, sigma = u^T W v applied in the graph), on weights whose sigma is far from 1 so that a
/// missing or wrong folding would show.
#[test]
fn features_artifact_scores_match_model_with_spectral_norm() {
    use rand::SeedableRng;
    use trainer::model::{CandleModel, TrainNoise};
    use trainer::Variant;
    let eps = common::action_task(6, 15, 1);
    let mut cfg = TrainConfig::preset(Kind::Classifier, Variant::Features);
    cfg.architecture.encoder_width = 8;
    cfg.architecture.trunk_dims = vec![16, 8];
    cfg.epochs = 1;
    cfg.batch_size = 32;
    let mut spec = common::action_spec();
    spec.t_embed_dim = 8;
    let mut t = trainer::train(&eps, &eps, &spec, &cfg).unwrap();
    assert!(t.spec.arch.spectral_norm);
    // A spectrally normalised model with large raw weights (sigma ~ 3).
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
    let mut raw = t.spec.init_params(&mut rng);
    for (n, v) in raw.names.iter().zip(raw.values.iter_mut()) {
        if n.ends_with(".weight") && !n.contains(".ln") && !n.starts_with("obs_in_ln") {
            v.iter_mut().for_each(|x| *x *= 3.0);
        }
    }
    let model = CandleModel::new(&t.spec, &raw, &mut rng).unwrap();
    model.power_iteration(20).unwrap();
    let sigma = model.sigma("trunk.0").unwrap();
    assert!((sigma - 1.0).abs() > 0.5, "sigma {sigma} too close to 1 for the test to mean anything");
    let rows: Vec<ScoreRow> = (0..6)
        .map(|i| ScoreRow {
            obs: (0..8).map(|k| ((i * 8 + k) as f32 * 0.61).sin()).collect(),
            action: (0..8).map(|k| ((i * 3 + k) as f32 * 0.37).cos()).collect(),
            t: (i * 5) as f64,
            extras: Default::default(),
        })
        .collect();
    // The candle graph with spectral norm on, on the artifact's standardisation.
    let norm = t.norm.clone();
    let eval = |m: &CandleModel| -> Vec<f32> {
        let n = rows.len();
        let mut obs: Vec<f32> = rows.iter().flat_map(|r| r.obs.clone()).collect();
        let mut act: Vec<f32> = rows.iter().flat_map(|r| r.action.clone()).collect();
        norm.apply(&mut obs, &mut act);
        let mut temb = vec![0f32; n * 8];
        for (k, r) in rows.iter().enumerate() {
            trainer::data::time_embedding_into(r.t, &mut temb[k * 8..(k + 1) * 8]);
        }
        let bt = m.batch_tensors(n, &obs, &act, &temb, &[]).unwrap();
        let (y, _) = m.forward(&bt, &TrainNoise::default()).unwrap();
        y.to_vec1::<f32>().unwrap().into_iter().map(trainer::loss::sigmoid).collect()
    };
    let with_sn = eval(&model);
    // Write the folded weights as the artifact and score through the core.
    t.params = model.inference_params().unwrap();
    let dir = tempfile::tempdir().unwrap();
    write_artifact(dir.path(), &t, serde_json::json!({})).unwrap();
    let cfg_json: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.path().join("config.json")).unwrap()).unwrap();
    assert_eq!(cfg_json["architecture"]["spectral_norm"], true);
    assert_eq!(cfg_json["architecture"]["activation"], "gelu");
    let a = load_artifact(dir.path()).unwrap();
    let scores = a.score(&rows).unwrap();
    for (k, (s, w)) in scores.iter().zip(&with_sn).enumerate() {
        assert!((s - w).abs() < 1e-5, "row {k}: artifact {s} vs candle with spectral norm {w}");
    }
    // Without the division by sigma the scores are different: the comparison above can fail.
    let mut no_sn = t.spec.clone();
    no_sn.arch.spectral_norm = false;
    let unfolded = CandleModel::new(&no_sn, &raw, &mut rng).unwrap();
    let wrong = eval(&unfolded);
    assert!(wrong.iter().zip(&with_sn).any(|(a, b)| (a - b).abs() > 1e-3), "folding sigma changed nothing");
}
