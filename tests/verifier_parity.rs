//! One verifier core, every client. A lowdim classifier (actions in the policy's space, with a
//! non-trivial normaliser) and a features/spectral-norm Q verifier are trained through the
//! binary and published in a store; on the steps of a stored episode, the robot (steer's
//! `Scorer`), `ufops score` (the binary, from the store, with policy-space and with raw
//! actions), the viewer's scorer and the independent numpy reference give the same scores
//! (1e-5); the gradients agree with each other, with finite differences, and with the trainer's
//! candle graph and its autograd. The numpy part FAILS without python3 + numpy + safetensors
//! when `UFOPS_REQUIRE_PYTHON=1` (scripts/test.sh sets it), and is skipped with a message
//! otherwise.

use crate::common;
use common::*;

use std::path::Path;
use std::process::Command;

use steer::Scorer;
use verifier::StepScorer;

/// The numpy reference's python3 with numpy and safetensors, by the tests' one rule for a missing
/// tool (a notice and the Rust parts only; a failure under UFOPS_REQUIRE_PYTHON).
fn numpy_available() -> bool {
    store::test_support::require_python(&["numpy", "safetensors"])
}

fn floats(v: &serde_json::Value) -> Vec<f32> {
    v.as_array()
        .unwrap_or_else(|| panic!("not an array: {v}"))
        .iter()
        .map(|x| x.as_f64().unwrap() as f32)
        .collect()
}

fn nested(v: &serde_json::Value) -> Vec<f32> {
    v.as_array().unwrap().iter().flat_map(floats).collect()
}

/// `got` equals `want` to `tol` (relative to max(1, |want|)).
fn same(what: &str, got: &[f32], want: &[f32], tol: f32) {
    assert_eq!(got.len(), want.len(), "{what}: lengths");
    for (i, (g, w)) in got.iter().zip(want).enumerate() {
        assert!((g - w).abs() <= tol * w.abs().max(1.0), "{what}[{i}]: {g} vs {w}");
    }
}

fn rows_json(path: &Path, obs: &[f32], act: &[f32], t: &[u32]) {
    let (n, od, ad) = (t.len(), obs.len() / t.len(), act.len() / t.len());
    let rows: Vec<serde_json::Value> = (0..n)
        .map(|i| serde_json::json!({"obs": &obs[i * od..(i + 1) * od], "action": &act[i * ad..(i + 1) * ad], "t": t[i]}))
        .collect();
    std::fs::write(path, serde_json::json!({ "rows": rows }).to_string()).unwrap();
}

#[test]
fn every_client_gives_the_same_scores_and_gradients() {
    let dir = tempfile::tempdir().unwrap();
    let t = Target::sqlite(dir.path());
    t.ok(&["init"]);
    t.ok(&["dev", "synth", "--episodes", "40", "--steps", "30", "--seed", "5"]);
    let split = t.json(&["split", "create", "--policy", "synth", "--checkpoint", "ckpt-0", "--json"]);
    let split = split["id"].as_str().unwrap().to_string();
    let lowdim = dir.path().join("lowdim.json");
    std::fs::write(&lowdim, r#"{"epochs": 3}"#).unwrap();
    t.ok(&[
        "train",
        "--split",
        &split,
        "--kind",
        "classifier",
        "--chunk-len",
        "16",
        "--config",
        lowdim.to_str().unwrap(),
        "--action-scale",
        "0.5",
        "2.0",
        "--action-offset",
        "0.1",
        "0",
    ]);
    let mut f = trainer::TrainConfig::preset(trainer::Kind::Q, trainer::Variant::Features);
    f.architecture.encoder_width = 16;
    f.architecture.t_embed_dim = 16;
    f.architecture.trunk_dims = vec![32, 16];
    f.epochs = 3;
    f.batch_size = 256;
    let features = dir.path().join("features.json");
    std::fs::write(&features, serde_json::to_string(&f).unwrap()).unwrap();
    t.ok(&[
        "train",
        "--split",
        &split,
        "--kind",
        "q",
        "--chunk-len",
        "16",
        "--config",
        features.to_str().unwrap(),
    ]);

    // A verifier that sees through a layer: every episode gets a per-step "encoder feature"
    // (a fixed nonlinear projection of its observation, standing in for a policy's image
    // encoder) written as layer `features.proj` by producer `proj-v1`, and a classifier is
    // trained on it plus nothing else, with the features recipe.
    let rt = tokio::runtime::Builder::new_current_thread().enable_all().build().unwrap();
    let producer = serde_json::json!({"encoder": "proj", "policy": "synth", "checkpoint": "ckpt-0", "content_hash": "v1"});
    let layer = "features.proj";
    rt.block_on(async {
        let store = store::Store::open(&store::StoreConfig::local(dir.path())).await.unwrap();
        let eps = store
            .episodes(&store::EpisodeFilter { policy: Some("synth".into()), ..Default::default() })
            .await
            .unwrap();
        let mut values = Vec::new();
        for e in &eps {
            let b = store.read_steps(&e.id, None).await.unwrap();
            let keys = store::steps::observation_keys(b.schema().as_ref());
            let (dim, obs) = store::steps::vector_column(&b, &format!("obs.{}", keys[0].0)).unwrap();
            let feats: Vec<f32> = obs
                .chunks(dim)
                .flat_map(|o| {
                    (0..6).map(move |j| {
                        (o.iter()
                            .enumerate()
                            .map(|(i, x)| x * ((i * 7 + j * 3) % 5) as f32 * 0.3)
                            .sum::<f32>()
                            + j as f32 * 0.1)
                            .tanh()
                    })
                })
                .collect();
            values.push(store::LayerValues { episode_id: e.id.clone(), dim: 6, values: feats });
        }
        let w = store.write_layer(layer, &producer, values, "test").await.unwrap();
        assert_eq!(w.episodes_written, eps.len());
    });
    let mut fc = trainer::TrainConfig::preset(trainer::Kind::Classifier, trainer::Variant::Features);
    fc.architecture.encoder_width = 16;
    fc.architecture.t_embed_dim = 16;
    fc.architecture.trunk_dims = vec![32, 16];
    fc.epochs = 3;
    fc.batch_size = 256;
    let features_c = dir.path().join("features-classifier.json");
    std::fs::write(&features_c, serde_json::to_string(&fc).unwrap()).unwrap();
    let layer_split =
        t.json(&["split", "create", "--policy", "synth", "--checkpoint", "ckpt-0", "--seed", "1", "--json"]);
    let layer_split = layer_split["id"].as_str().unwrap().to_string();
    let trained = t.json(&[
        "train",
        "--split",
        &layer_split,
        "--kind",
        "classifier",
        "--chunk-len",
        "16",
        "--config",
        features_c.to_str().unwrap(),
        "--obs-keys",
        layer,
        "--json",
    ]);
    let layer_artifact =
        trained["id"].as_str().unwrap_or_else(|| panic!("no artifact id in {trained}")).to_string();
    let producer_hash = store::producer_hash(&producer).unwrap();

    // The steps of a stored episode: what the viewer scores (with the layer joined for the
    // verifier that reads it).
    let (plain_batch, layer_batch) = rt.block_on(async {
        let store = store::Store::open(&store::StoreConfig::local(dir.path())).await.unwrap();
        let filter =
            store::EpisodeFilter { policy: Some("synth".into()), limit: Some(1), ..Default::default() };
        let ep = store.episodes(&filter).await.unwrap().remove(0);
        (
            store.read_steps(&ep.id, None).await.unwrap(),
            store.read_steps_with_layers(&ep.id, None, &[layer.to_string()]).await.unwrap(),
        )
    });
    let numpy = numpy_available();
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("clients/python/reference/ufops_reference.py");

    let cases =
        [(layer_artifact.as_str(), "layer", &layer_batch), ("synth/ckpt-0/q@latest", "q", &plain_batch)];
    // The lowdim classifier was published first; the layer classifier is now classifier@latest.
    let lowdim_id = t.json(&["artifacts", "--policy", "synth", "--checkpoint", "ckpt-0", "--json"]);
    let lowdim_id = lowdim_id
        .as_array()
        .unwrap()
        .iter()
        .find(|a| a["kind"] == "classifier" && a["id"] != layer_artifact.as_str())
        .map(|a| a["id"].as_str().unwrap().to_string())
        .expect("the lowdim classifier");
    for (reference, name, batch) in
        [(lowdim_id.as_str(), "classifier", &plain_batch)].into_iter().chain(cases)
    {
        let local = dir.path().join(name);
        t.ok(&["artifacts", "download", reference, local.to_str().unwrap()]);
        let robot = steer::Verifier::load_dir(&local).unwrap();
        let cfg = robot.config();
        match name {
            "layer" => {
                assert_eq!(cfg.architecture.variant, verifier::Variant::Features);
                assert_eq!(cfg.input.layout.required_producers(), vec![(layer, producer_hash.as_str())]);
                // The robot refuses features of another encoder, and so does scoring stored
                // steps whose layer came from another producer.
                assert!(robot.check_producers([(layer, producer_hash.as_str())]).is_ok());
                let err = robot.check_producers([(layer, "0".repeat(64).as_str())]).unwrap_err().to_string();
                assert!(err.contains("trained on features of producer"), "{err}");
                let schema = batch.schema();
                let mut fields: Vec<arrow::datatypes::Field> =
                    schema.fields().iter().map(|f| f.as_ref().clone()).collect();
                for f in fields.iter_mut().filter(|f| f.name() == &format!("obs.{layer}")) {
                    let mut m = f.metadata().clone();
                    m.insert(store::PRODUCER_META_KEY.into(), "f".repeat(64));
                    *f = f.clone().with_metadata(m);
                }
                let forged = arrow::array::RecordBatch::try_new(
                    std::sync::Arc::new(arrow::datatypes::Schema::new(fields)),
                    batch.columns().to_vec(),
                )
                .unwrap();
                let err = verifier::steps::step_inputs(cfg, &forged).unwrap_err().to_string();
                assert!(err.contains("ffffffffffff"), "{err}");
                let err = verifier::steps::step_inputs(cfg, &plain_batch).unwrap_err().to_string();
                assert!(err.contains("read the steps with that layer"), "{err}");
            }
            "classifier" => {
                assert_eq!(cfg.architecture.variant, verifier::Variant::Lowdim);
                assert_eq!(
                    cfg.input.action_space,
                    verifier::ActionSpace::policy(vec![0.5, 2.0], vec![0.1, 0.0])
                );
            }
            _ => {
                let a = &cfg.architecture;
                assert!(
                    a.variant == verifier::Variant::Features
                        && a.spectral_norm
                        && a.input_layernorm
                        && a.encoder_layernorm
                );
                assert_eq!(a.activation, verifier::Activation::Gelu);
            }
        }
        let s = verifier::steps::step_inputs(cfg, batch).unwrap();
        let (n, ad) = (s.len(), s.act_dim);
        assert!(n >= 10, "{name}: {n} steps");

        // The robot: steer's Scorer.
        let scores = robot.score_batch(&s.obs, &s.t, &s.act, 1).unwrap();
        let grads = robot.grad_batch(&s.obs, &s.t, &s.act).unwrap();
        assert!(grads.iter().any(|g| g.abs() > 1e-4), "{name}: the gradient is trivially zero");

        // The stored-steps scorer (the viewer's, export curation's, the review queue's), on the
        // stored steps themselves.
        let viewer_scores = verifier::Verifier::load_dir(&local).unwrap().score_steps(batch).unwrap();
        same(&format!("{name}: viewer scores"), &viewer_scores, &scores, 1e-5);

        // `ufops score` from the store, with policy-space rows and with raw rows.
        let rows = dir.path().join(format!("{name}-rows.json"));
        rows_json(&rows, &s.obs, &s.act, &s.t);
        let cli = t.json(&["score", "--artifact", reference, "--input", rows.to_str().unwrap(), "--grad"]);
        same(&format!("{name}: ufops score"), &floats(&cli["scores"]), &scores, 1e-5);
        same(&format!("{name}: ufops score --grad"), &nested(&cli["grads"]), &grads, 1e-5);
        let mut raw = s.act.clone();
        cfg.input.action_space.input_to_raw(&mut raw, cfg.input.layout.action_dim);
        let raw_rows = dir.path().join(format!("{name}-raw-rows.json"));
        rows_json(&raw_rows, &s.obs, &raw, &s.t);
        let cli_raw = t.json(&[
            "score",
            "--artifact",
            reference,
            "--input",
            raw_rows.to_str().unwrap(),
            "--raw-actions",
        ]);
        same(&format!("{name}: ufops score --raw-actions"), &floats(&cli_raw["scores"]), &scores, 1e-5);

        // The trainer's candle graph and its autograd.
        let art = trainer::load_artifact(&local).unwrap();
        let score_rows = trainer::parse_rows(&std::fs::read_to_string(&rows).unwrap()).unwrap();
        let (cs, cg) = art.candle_scores_and_grads(&score_rows).unwrap();
        same(&format!("{name}: candle scores"), &cs, &scores, 1e-5);
        same(&format!("{name}: candle autograd"), &cg.concat(), &grads, 1e-5);

        // Finite differences of the robot's own scores (log C for the classifier), a few rows.
        for r in [0, n / 2, n - 1] {
            let obj = |c: &[f32]| -> f64 {
                let v = robot
                    .score_batch(&s.obs[r * s.obs_dim..(r + 1) * s.obs_dim], &s.t[r..r + 1], c, 1)
                    .unwrap()[0] as f64;
                if name == "q" {
                    v
                } else {
                    v.ln()
                }
            };
            let chunk = &s.act[r * ad..(r + 1) * ad];
            for j in 0..ad {
                // Central differences at a few step sizes: a step may straddle a ReLU kink (the
                // difference is then off at that step only) and the scores are f32, so one step
                // size that agrees is enough; a wrong gradient agrees at none.
                let g = grads[r * ad + j] as f64;
                let fds: Vec<f64> = [1e-3f32, 3e-3, 1e-2]
                    .iter()
                    .map(|&h| {
                        let (mut p, mut m) = (chunk.to_vec(), chunk.to_vec());
                        p[j] += h;
                        m[j] -= h;
                        (obj(&p) - obj(&m)) / (2.0 * h as f64)
                    })
                    .collect();
                assert!(
                    fds.iter().any(|fd| (fd - g).abs() < 2e-3 + 2e-2 * fd.abs()),
                    "{name} row {r} d/da[{j}]: finite differences {fds:?} vs {g}"
                );
            }
        }

        // The independent numpy reference (float64, hand-written backprop).
        if numpy {
            let out = Command::new("python3").arg(&script).arg(&local).arg(&rows).output().unwrap();
            assert!(
                out.status.success(),
                "{name}: numpy reference failed: {}",
                String::from_utf8_lossy(&out.stderr)
            );
            let py: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
            assert_eq!(py["artifact_id"].as_str(), robot.id());
            same(&format!("{name}: numpy scores"), &floats(&py["scores"]), &scores, 1e-5);
            same(&format!("{name}: numpy gradients"), &nested(&py["grads"]), &grads, 1e-5);
        }
    }
}
