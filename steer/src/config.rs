//! `config.json` of a verifier artifact (schema_version 1, see trainer/ARTIFACT.md), parsed and validated.
use crate::error::{Result, SteerError};
use serde::{Deserialize, Serialize};

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Kind {
    /// success classifier: score = sigmoid(y), gradient = d log sigmoid(y) / d act
    Classifier,
    /// time-to-success value: score = y, gradient = d y / d act
    Q,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Variant {
    Lowdim,
    Features,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Activation {
    Relu,
    Gelu,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct ExtraInput {
    pub name: String,
    pub dim: usize,
    pub width: usize,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Architecture {
    pub variant: String,
    pub activation: String,
    pub encoder_width: usize,
    pub t_embed_dim: usize,
    pub trunk_dims: Vec<usize>,
    #[serde(default)]
    pub input_layernorm: bool,
    #[serde(default)]
    pub encoder_layernorm: bool,
    #[serde(default)]
    pub spectral_norm: bool,
    #[serde(default)]
    pub dropout: f64,
    #[serde(default = "default_eps")]
    pub layernorm_eps: f64,
    #[serde(default)]
    pub extra_inputs: Vec<ExtraInput>,
}

fn default_eps() -> f64 {
    1e-5
}

#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct ObsKey {
    pub key: String,
    pub dim: usize,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct InputSpec {
    pub obs_keys: Vec<ObsKey>,
    pub obs_history: usize,
    pub chunk_len: usize,
    pub action_dim: usize,
    pub obs_dim: usize,
    pub act_dim: usize,
    pub obs_mean: Vec<f32>,
    pub obs_std: Vec<f32>,
    pub act_mean: Vec<f32>,
    pub act_std: Vec<f32>,
}

/// The parsed `config.json`. Unknown extra fields are ignored; `hyperparameters`, `metrics`
/// and `lineage` are kept as raw JSON.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct VerifierConfig {
    pub schema_version: u64,
    pub kind: String,
    pub architecture: Architecture,
    pub input: InputSpec,
    #[serde(default)]
    pub gamma: Option<f64>,
    #[serde(default)]
    pub hyperparameters: serde_json::Value,
    #[serde(default)]
    pub metrics: serde_json::Value,
    #[serde(default)]
    pub lineage: serde_json::Value,
}

impl VerifierConfig {
    /// Parse and validate (schema version, kind, variant, activation, dimensions).
    pub fn from_json(bytes: &[u8]) -> Result<Self> {
        // Check schema_version first so an unknown future schema gets the right error even if
        // its fields no longer parse as schema 1.
        let raw: serde_json::Value = serde_json::from_slice(bytes)
            .map_err(|e| SteerError::Config(format!("not valid JSON: {e}")))?;
        match raw.get("schema_version").and_then(|v| v.as_u64()) {
            Some(1) => {}
            Some(v) => return Err(SteerError::UnknownSchema(v)),
            None => return Err(SteerError::Config("missing or non-integer schema_version".into())),
        }
        let cfg: VerifierConfig =
            serde_json::from_value(raw).map_err(|e| SteerError::Config(e.to_string()))?;
        cfg.validate()?;
        Ok(cfg)
    }

    pub fn kind(&self) -> Kind {
        match self.kind.as_str() {
            "q" => Kind::Q,
            _ => Kind::Classifier,
        }
    }
    pub fn variant(&self) -> Variant {
        match self.architecture.variant.as_str() {
            "features" => Variant::Features,
            _ => Variant::Lowdim,
        }
    }
    pub fn activation(&self) -> Activation {
        match self.architecture.activation.as_str() {
            "gelu" => Activation::Gelu,
            _ => Activation::Relu,
        }
    }
    pub fn obs_dim(&self) -> usize {
        self.input.obs_dim
    }
    pub fn act_dim(&self) -> usize {
        self.input.act_dim
    }
    /// Width of the trunk input: 2 * encoder_width + t_embed_dim + sum(extra widths).
    pub fn trunk_in(&self) -> usize {
        let a = &self.architecture;
        2 * a.encoder_width + a.t_embed_dim + a.extra_inputs.iter().map(|e| e.width).sum::<usize>()
    }

    pub fn validate(&self) -> Result<()> {
        if self.schema_version != 1 {
            return Err(SteerError::UnknownSchema(self.schema_version));
        }
        match self.kind.as_str() {
            "classifier" | "q" => {}
            k => return Err(SteerError::UnknownKind(k.to_string())),
        }
        let a = &self.architecture;
        match a.variant.as_str() {
            "lowdim" | "features" => {}
            v => return Err(SteerError::UnknownVariant(v.to_string())),
        }
        match a.activation.as_str() {
            "relu" | "gelu" => {}
            v => return Err(SteerError::UnknownActivation(v.to_string())),
        }
        let bad = |m: String| Err(SteerError::Config(m));
        if a.encoder_width == 0 || a.trunk_dims.is_empty() || a.trunk_dims.contains(&0) {
            return bad("encoder_width and trunk_dims must be non-empty and positive".into());
        }
        if a.t_embed_dim == 0 || a.t_embed_dim % 2 != 0 {
            return bad(format!("t_embed_dim must be a positive even number, got {}", a.t_embed_dim));
        }
        if !(a.layernorm_eps > 0.0) {
            return bad("layernorm_eps must be > 0".into());
        }
        let i = &self.input;
        let per_step: usize = i.obs_keys.iter().map(|k| k.dim).sum();
        if i.obs_dim == 0 || i.act_dim == 0 {
            return bad("obs_dim and act_dim must be positive".into());
        }
        if !i.obs_keys.is_empty() && i.obs_history * per_step != i.obs_dim {
            return bad(format!(
                "obs_dim {} != obs_history {} * sum(obs_keys dims) {}",
                i.obs_dim, i.obs_history, per_step
            ));
        }
        if i.chunk_len * i.action_dim != i.act_dim {
            return bad(format!(
                "act_dim {} != chunk_len {} * action_dim {}",
                i.act_dim, i.chunk_len, i.action_dim
            ));
        }
        for (name, v, n) in [
            ("obs_mean", &i.obs_mean, i.obs_dim),
            ("obs_std", &i.obs_std, i.obs_dim),
            ("act_mean", &i.act_mean, i.act_dim),
            ("act_std", &i.act_std, i.act_dim),
        ] {
            if v.len() != n {
                return bad(format!("{name} has length {}, expected {n}", v.len()));
            }
            if v.iter().any(|x| !x.is_finite()) {
                return bad(format!("{name} contains a non-finite value"));
            }
        }
        if i.obs_std.iter().chain(&i.act_std).any(|&s| s <= 0.0) {
            return bad("obs_std/act_std must be > 0".into());
        }
        Ok(())
    }
}
