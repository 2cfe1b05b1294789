//! Rust reference scorer vs the numpy client (`clients/python/test_parity.py`).
//! Skips (with a message) only when python3 with numpy and safetensors is not available.

mod common;

use std::path::PathBuf;
use std::process::Command;

use trainer::artifact::{score_json, write_artifact, ScoreRow};
use trainer::data::build_samples;
use trainer::{ExtraInputSpec, Kind, TrainConfig, Variant};

fn python_ok() -> bool {
    Command::new("python3")
        .args(["-c", "import numpy, safetensors"])
        .output()
        .map(|o| o.status.success())
        .unwrap_or(false)
}

#[test]
fn python_client_reproduces_rust_scores() {
    if !python_ok() {
        eprintln!("SKIPPED python parity: python3 with numpy and safetensors is not importable (pip install numpy safetensors)");
        return;
    }
    let script = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../clients/python/test_parity.py");
    let eps = common::action_task(8, 15, 1);
    let val = common::action_task(4, 15, 2);
    let mut cases = vec![];
    for kind in [Kind::Classifier, Kind::Q] {
        cases.push((TrainConfig { kind, epochs: 2, batch_size: 64, ..Default::default() }, common::action_spec()));
    }
    // Features variant (GELU, LayerNorms, spectral norm folded) with an extra input.
    let mut f = TrainConfig::preset(Kind::Classifier, Variant::Features);
    f.architecture.encoder_width = 16;
    f.architecture.trunk_dims = vec![32, 16];
    f.epochs = 2;
    f.batch_size = 64;
    let mut fspec = common::action_spec();
    fspec.t_embed_dim = 8;
    fspec.extra_inputs = vec![ExtraInputSpec { name: "lang".into(), key: "vel".into(), dim: 1, width: 4 }];
    cases.push((f, fspec));

    for (cfg, spec) in cases {
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
        let scores_path = dir.path().join("rust_scores.json");
        std::fs::write(
            &scores_path,
            serde_json::json!({ "rows": rows, "scores": scores, "artifact_id": info.id }).to_string(),
        )
        .unwrap();
        let out = Command::new("python3").arg(&script).arg(dir.path()).arg(&scores_path).output().unwrap();
        let text = format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
        eprintln!("{text}");
        assert!(out.status.success(), "python parity failed:\n{text}");
    }
}
