//! Helpers to build verifier artifacts with random weights (tests, benchmarks, examples).
//! Not a trainer: the weights are random.
use crate::config::VerifierConfig;
use crate::verifier::{artifact_id, sha256_hex};
use crate::weights::{required_tensors, Weights};
use rand::Rng;
use std::path::Path;

/// Shapes of a random artifact.
#[derive(Debug, Clone)]
pub struct RandomSpec {
    pub kind: &'static str,
    pub variant: &'static str,
    pub obs_keys: Vec<(String, usize)>,
    pub obs_history: usize,
    pub chunk_len: usize,
    pub action_dim: usize,
    pub encoder_width: usize,
    pub t_embed_dim: usize,
    pub trunk_dims: Vec<usize>,
    pub input_layernorm: bool,
    pub encoder_layernorm: bool,
    pub extra_inputs: Vec<(String, usize, usize)>,
}

impl RandomSpec {
    /// The paper's Square task dimensions: obs 46 (one step), chunk 16 x 10, encoders 64, t-emb 64,
    /// trunk 128 -> 64.
    pub fn square() -> Self {
        RandomSpec {
            kind: "classifier",
            variant: "lowdim",
            obs_keys: vec![("state".into(), 46)],
            obs_history: 1,
            chunk_len: 16,
            action_dim: 10,
            encoder_width: 64,
            t_embed_dim: 64,
            trunk_dims: vec![128, 64],
            input_layernorm: false,
            encoder_layernorm: false,
            extra_inputs: vec![],
        }
    }
    /// The 2-D navigation task: pos (2) x 2 steps, chunk 8 x 2.
    pub fn nav() -> Self {
        RandomSpec {
            obs_keys: vec![("pos".into(), 2)],
            obs_history: 2,
            chunk_len: 8,
            action_dim: 2,
            ..Self::square()
        }
    }

    pub fn config_json<R: Rng>(&self, rng: &mut R) -> serde_json::Value {
        let obs_dim = self.obs_history * self.obs_keys.iter().map(|k| k.1).sum::<usize>();
        let act_dim = self.chunk_len * self.action_dim;
        let mut v = |n: usize, lo: f32, hi: f32| (0..n).map(|_| rng.gen_range(lo..hi)).collect::<Vec<f32>>();
        serde_json::json!({
            "schema_version": 1,
            "kind": self.kind,
            "architecture": {
                "variant": self.variant,
                "activation": if self.variant == "features" { "gelu" } else { "relu" },
                "encoder_width": self.encoder_width,
                "t_embed_dim": self.t_embed_dim,
                "trunk_dims": self.trunk_dims,
                "input_layernorm": self.input_layernorm,
                "encoder_layernorm": self.encoder_layernorm,
                "spectral_norm": false,
                "dropout": 0.5,
                "layernorm_eps": 1e-5,
                "extra_inputs": self.extra_inputs.iter().map(|(n, d, w)| serde_json::json!({"name": n, "dim": d, "width": w})).collect::<Vec<_>>(),
            },
            "input": {
                "obs_keys": self.obs_keys.iter().map(|(k, d)| serde_json::json!({"key": k, "dim": d})).collect::<Vec<_>>(),
                "obs_history": self.obs_history,
                "chunk_len": self.chunk_len,
                "action_dim": self.action_dim,
                "obs_dim": obs_dim,
                "act_dim": act_dim,
                "obs_mean": v(obs_dim, -0.5, 0.5),
                "obs_std": v(obs_dim, 0.5, 2.0),
                "act_mean": v(act_dim, -0.5, 0.5),
                "act_std": v(act_dim, 0.5, 2.0),
            },
            "gamma": if self.kind == "q" { serde_json::json!(0.99) } else { serde_json::Value::Null },
            "hyperparameters": {}, "metrics": {}, "lineage": {"note": "random weights (steer::testutil)"}
        })
    }

    /// Random config + weights (PyTorch-like uniform(-1/sqrt(in), 1/sqrt(in)) init; LayerNorm
    /// gains near 1).
    pub fn build<R: Rng>(&self, rng: &mut R) -> (VerifierConfig, Weights) {
        let cfg: VerifierConfig = serde_json::from_value(self.config_json(rng)).expect("config");
        cfg.validate().expect("valid random config");
        let mut w = Weights::default();
        for (name, shape) in required_tensors(&cfg) {
            let n: usize = shape.iter().product();
            let data: Vec<f32> = if name.ends_with(".ln.weight") || name == "obs_in_ln.weight" {
                (0..n).map(|_| rng.gen_range(0.8..1.2)).collect()
            } else if name.ends_with(".ln.bias") || name == "obs_in_ln.bias" {
                (0..n).map(|_| rng.gen_range(-0.1..0.1)).collect()
            } else {
                let fan_in = if shape.len() == 2 { shape[1] } else { shape[0] };
                let bound = 1.0 / (fan_in as f32).sqrt();
                (0..n).map(|_| rng.gen_range(-bound..bound)).collect()
            };
            w.insert(&name, shape, data);
        }
        (cfg, w)
    }
}

/// Write an artifact directory (config.json, model.safetensors, manifest.json); returns its id.
pub fn write_artifact(dir: &Path, cfg: &VerifierConfig, w: &Weights) -> std::io::Result<String> {
    std::fs::create_dir_all(dir)?;
    let cfg_bytes = serde_json::to_vec_pretty(cfg).expect("config json");
    let st = w.to_safetensors();
    let manifest = serde_json::to_vec(&serde_json::json!({
        "schema_version": 1,
        "files": {"config.json": sha256_hex(&cfg_bytes), "model.safetensors": sha256_hex(&st)}
    }))
    .unwrap();
    std::fs::write(dir.join("config.json"), &cfg_bytes)?;
    std::fs::write(dir.join("model.safetensors"), &st)?;
    std::fs::write(dir.join("manifest.json"), &manifest)?;
    Ok(artifact_id(&manifest))
}
