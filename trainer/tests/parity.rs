//! The verifier core (through the trainer's scorer) against the independent numpy reference
//! (`clients/python/reference/ufops_reference.py`): scores and guidance gradients, on artifacts
//! the trainer wrote for every variant. Without python3 + numpy + safetensors the test is skipped
//! with a message, and FAILS when `UFOPS_REQUIRE_PYTHON=1` (as `scripts/test.sh` sets).

use crate::common;

use std::path::PathBuf;
use std::process::Command;

use trainer::artifact::{grad_rows, score_json, write_artifact, ScoreRow};
use trainer::data::build_samples;
use trainer::{ActionSpace, ExtraInputSpec, Kind, TrainConfig, Variant};

/// The numpy reference needs python3 with numpy and safetensors (the tests' one rule for a
/// missing tool: skipped with a notice, a failure under UFOPS_REQUIRE_PYTHON).
fn python_ready() -> bool {
    store::test_support::require_python(&["numpy", "safetensors"])
}

#[test]
fn numpy_reference_reproduces_the_core_scores_and_gradients() {
    if !python_ready() {
        return;
    }
    let script =
        PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../clients/python/reference/ufops_reference.py");
    let eps = common::action_task(8, 15, 1);
    let val = common::action_task(4, 15, 2);
    let small = |c: &mut TrainConfig| {
        c.epochs = 2;
        c.batch_size = 64;
    };
    let mut cases = vec![];
    // Lowdim classifier in the policy's space with a non-trivial normaliser.
    let mut c = TrainConfig {
        kind: Kind::Classifier,
        action_space: ActionSpace::policy(vec![0.5, 2.0], vec![0.1, -0.3]),
        ..Default::default()
    };
    small(&mut c);
    cases.push((c, common::action_spec()));
    // Lowdim Q on standardised raw chunks (the older recipe).
    let mut c = TrainConfig { kind: Kind::Q, action_space: ActionSpace::Standardized, ..Default::default() };
    small(&mut c);
    cases.push((c, common::action_spec()));
    // Features (GELU, every LayerNorm, spectral norm folded, observation noise) with an extra input.
    for kind in [Kind::Classifier, Kind::Q] {
        let mut f = TrainConfig::preset(kind, Variant::Features);
        f.architecture.encoder_width = 16;
        f.architecture.trunk_dims = vec![32, 16];
        small(&mut f);
        let mut fspec = common::action_spec();
        fspec.t_embed_dim = 8;
        fspec.extra_inputs =
            vec![ExtraInputSpec { name: "lang".into(), key: "vel".into(), dim: 1, width: 4 }];
        cases.push((f, fspec));
    }

    for (cfg, spec) in cases {
        let what = format!("{:?}/{:?}", cfg.kind, cfg.architecture.variant);
        let t = trainer::train(&eps, &val, &spec, &cfg).unwrap();
        let dir = tempfile::tempdir().unwrap();
        let info = write_artifact(dir.path(), &t, serde_json::json!({"test": "parity"})).unwrap();
        let s = build_samples(&common::action_task(3, 15, 11), &spec, 0.99).unwrap();
        let rows: Vec<ScoreRow> = (0..s.len())
            .map(|i| ScoreRow {
                obs: s.obs[i * s.obs_dim..(i + 1) * s.obs_dim].to_vec(),
                action: s.act[i * s.act_dim..(i + 1) * s.act_dim].to_vec(),
                t: s.t[i] as f64,
                extras: spec
                    .extra_inputs
                    .iter()
                    .zip(&s.extras)
                    .map(|(e, v)| (e.name.clone(), v[i * e.dim..(i + 1) * e.dim].to_vec()))
                    .collect(),
            })
            .collect();
        let input = serde_json::json!({ "rows": rows }).to_string();
        let scores = score_json(dir.path(), &input).unwrap();
        let v = verifier::Verifier::load_dir(dir.path()).unwrap();
        let grads = grad_rows(&v, &rows).unwrap();
        let rows_path = dir.path().join("rows.json");
        std::fs::write(&rows_path, &input).unwrap();
        let out = Command::new("python3").arg(&script).arg(dir.path()).arg(&rows_path).output().unwrap();
        assert!(
            out.status.success(),
            "{what}: numpy reference failed:\n{}",
            String::from_utf8_lossy(&out.stderr)
        );
        let py: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
        assert_eq!(py["artifact_id"], info.id.as_str(), "{what}: artifact id");
        let (mut worst_s, mut worst_g) = (0f64, 0f64);
        for (k, (s, p)) in scores.iter().zip(py["scores"].as_array().unwrap()).enumerate() {
            let e = (*s as f64 - p.as_f64().unwrap()).abs();
            assert!(e <= 1e-5, "{what} row {k}: core score {s} vs numpy {p}");
            worst_s = worst_s.max(e);
        }
        for (k, (g, p)) in grads.iter().zip(py["grads"].as_array().unwrap()).enumerate() {
            for (j, (a, b)) in g.iter().zip(p.as_array().unwrap()).enumerate() {
                let b = b.as_f64().unwrap();
                let e = (*a as f64 - b).abs();
                assert!(e <= 1e-5 * b.abs().max(1.0), "{what} row {k} d/da[{j}]: core {a} vs numpy {b}");
                worst_g = worst_g.max(e);
            }
        }
        assert!(grads.iter().flatten().any(|g| g.abs() > 1e-4), "{what}: gradient is trivially zero");
        eprintln!(
            "{what}: {} rows, max |core - numpy|: scores {worst_s:.2e}, gradients {worst_g:.2e}",
            rows.len()
        );
    }
}
