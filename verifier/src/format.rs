//! The artifact format (trainer/ARTIFACT.md: schema_version 1, one network; 2, an ensemble of
//! members): the types of `config.json` and `manifest.json`, their validation, and the one list
//! of tensors (names, shapes, parameter order) an artifact needs. The trainer writes these types and every client reads them.
//!
//! One file past 700 lines: the artifact's types and their validation are the format's one
//! definition.

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};

use crate::error::{Result, VerifierError};
use crate::sha256_hex;

/// The schema of an artifact with one network.
pub const SCHEMA_VERSION: u32 = 1;
/// The schema of an ensemble's artifact (`config.json` has `ensemble`; the tensors of member `k`
/// are prefixed `members.{k}.`). A client that knows only 1 refuses it, as it must: it would
/// otherwise score with no member at all.
pub const ENSEMBLE_SCHEMA_VERSION: u32 = 2;
/// Most members an ensemble may have (each is a whole network in memory and per score).
pub const MAX_MEMBERS: usize = 64;
pub const CONFIG_FILE: &str = "config.json";
pub const MODEL_FILE: &str = "model.safetensors";
pub const MANIFEST_FILE: &str = "manifest.json";

/// What the verifier predicts.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Kind {
    /// Success classifier: score = sigmoid(y), guidance gradient = d log sigmoid(y) / d act.
    Classifier,
    /// Time-to-success value: score = y, guidance gradient = d y / d act.
    Q,
}

impl Kind {
    pub fn as_str(self) -> &'static str {
        match self {
            Kind::Classifier => "classifier",
            Kind::Q => "q",
        }
    }
}

/// Architecture variant.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Variant {
    /// Raw low-dimensional state (the paper's low-dim column): ReLU after both encoder linears.
    Lowdim,
    /// Frozen encoder features (the paper's image column): optional LayerNorms, activation
    /// between the encoder linears only.
    Features,
}

/// Encoder nonlinearity.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Activation {
    Relu,
    /// Exact (erf) GELU.
    Gelu,
}

/// An extra model input encoded by `Linear(dim, width) + ReLU`, concatenated after the step
/// embedding (`architecture.extra_inputs`).
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct ExtraInput {
    pub name: String,
    pub dim: usize,
    pub width: usize,
}

fn default_eps() -> f64 {
    1e-5
}

/// `config.json`'s `architecture` object. Unknown fields are refused: an architecture flag this
/// client does not know could change the forward pass.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Architecture {
    pub variant: Variant,
    pub activation: Activation,
    pub encoder_width: usize,
    /// Width of the sinusoidal step embedding; must be even (sin/cos pairs).
    pub t_embed_dim: usize,
    pub trunk_dims: Vec<usize>,
    /// Features: LayerNorm on the standardised observation.
    #[serde(default)]
    pub input_layernorm: bool,
    /// Features: LayerNorm after each encoder linear.
    #[serde(default)]
    pub encoder_layernorm: bool,
    /// Trained with spectral normalisation; weights are stored already divided by sigma, so this
    /// is informational for clients.
    #[serde(default)]
    pub spectral_norm: bool,
    /// Dropout before the head (identity at inference).
    #[serde(default)]
    pub dropout: f64,
    #[serde(default = "default_eps")]
    pub layernorm_eps: f64,
    #[serde(default)]
    pub extra_inputs: Vec<ExtraInput>,
}

impl Default for Architecture {
    fn default() -> Self {
        Self::lowdim()
    }
}

impl Architecture {
    /// The paper's low-dim (Square) column.
    pub fn lowdim() -> Self {
        Architecture {
            variant: Variant::Lowdim,
            activation: Activation::Relu,
            encoder_width: 64,
            t_embed_dim: 64,
            trunk_dims: vec![128, 64],
            input_layernorm: false,
            encoder_layernorm: false,
            spectral_norm: false,
            dropout: 0.5,
            layernorm_eps: 1e-5,
            extra_inputs: vec![],
        }
    }

    /// The paper's image (frozen-encoder features) Square column.
    pub fn features() -> Self {
        Architecture {
            variant: Variant::Features,
            activation: Activation::Gelu,
            encoder_width: 256,
            t_embed_dim: 128,
            trunk_dims: vec![512, 256],
            input_layernorm: true,
            encoder_layernorm: true,
            spectral_norm: true,
            dropout: 0.5,
            layernorm_eps: 1e-5,
            extra_inputs: vec![],
        }
    }

    /// Width of the trunk input: `2 * encoder_width + t_embed_dim + sum(extra widths)`.
    pub fn trunk_in(&self) -> usize {
        2 * self.encoder_width + self.t_embed_dim + self.extra_inputs.iter().map(|e| e.width).sum::<usize>()
    }

    /// Width of the penultimate layer `z` (the trunk's last), which the contrastive loss and
    /// dropout act on; 0 for an architecture without a trunk (which `validate` refuses).
    pub fn z_dim(&self) -> usize {
        self.trunk_dims.last().copied().unwrap_or(0)
    }

    /// Whether an activation follows encoder linear `i` (0 or 1): lowdim after both, features
    /// between them only.
    pub fn encoder_activation_after(&self, i: usize) -> bool {
        self.variant == Variant::Lowdim || i == 0
    }

    pub fn validate(&self) -> Result<()> {
        let bad = |m: String| Err(VerifierError::Config(m));
        if self.encoder_width == 0 || self.trunk_dims.is_empty() || self.trunk_dims.contains(&0) {
            return bad("encoder_width and trunk_dims must be non-empty and positive".into());
        }
        if self.t_embed_dim == 0 || !self.t_embed_dim.is_multiple_of(2) {
            return bad(format!(
                "t_embed_dim must be a positive even number (sin/cos pairs), got {}",
                self.t_embed_dim
            ));
        }
        if !(self.layernorm_eps > 0.0 && self.layernorm_eps.is_finite()) {
            return bad(format!("layernorm_eps must be a positive number, got {}", self.layernorm_eps));
        }
        if !(0.0..1.0).contains(&self.dropout) {
            return bad(format!("dropout must be in [0, 1), got {}", self.dropout));
        }
        if self.variant == Variant::Lowdim
            && (self.input_layernorm || self.encoder_layernorm || self.activation != Activation::Relu)
        {
            return bad("lowdim variant: ReLU encoders without LayerNorm (use variant \"features\")".into());
        }
        let mut names = std::collections::BTreeSet::new();
        for e in &self.extra_inputs {
            if !is_plain_name(&e.name) || e.name.contains('.') {
                return bad(format!(
                    "extra input name {:?} must be a plain name (letters, digits, - and _)",
                    e.name
                ));
            }
            if !names.insert(e.name.as_str()) {
                return bad(format!("extra input {:?} is listed twice", e.name));
            }
            if e.dim == 0 || e.width == 0 {
                return bad(format!("extra input {:?}: dim and width must be positive", e.name));
            }
        }
        Ok(())
    }

    /// The linear layers in parameter order: `obs_enc.0`, `obs_enc.1`, `act_enc.0`, `act_enc.1`,
    /// `extra.<name>`..., `trunk.0`..., `head`.
    pub fn linears(&self, obs_dim: usize, act_dim: usize) -> Vec<LinearSpec> {
        let w = self.encoder_width;
        let (enc_ln, sn) = (self.encoder_layernorm, self.spectral_norm);
        let lin = |name: String, input: usize, output: usize, layernorm: bool, spectral_norm: bool| {
            LinearSpec { name, input, output, layernorm, spectral_norm }
        };
        let mut v = vec![
            lin("obs_enc.0".into(), obs_dim, w, enc_ln, sn),
            lin("obs_enc.1".into(), w, w, enc_ln, sn),
            lin("act_enc.0".into(), act_dim, w, enc_ln, sn),
            lin("act_enc.1".into(), w, w, enc_ln, sn),
        ];
        for e in &self.extra_inputs {
            v.push(lin(format!("extra.{}", e.name), e.dim, e.width, false, false));
        }
        let mut prev = self.trunk_in();
        for (i, &d) in self.trunk_dims.iter().enumerate() {
            v.push(lin(format!("trunk.{i}"), prev, d, true, sn));
            prev = d;
        }
        v.push(lin("head".into(), prev, 1, false, false));
        v
    }

    /// Every tensor of `model.safetensors`, in parameter order: `obs_in_ln` first (with
    /// `input_layernorm`), then each linear's weight `[out, in]`, bias, and its LayerNorm's
    /// weight and bias when it has one.
    pub fn tensors(&self, obs_dim: usize, act_dim: usize) -> Vec<TensorSpec> {
        let mut v = Vec::new();
        if self.input_layernorm {
            v.push(TensorSpec {
                name: "obs_in_ln.weight".into(),
                shape: vec![obs_dim],
                role: TensorRole::NormWeight,
            });
            v.push(TensorSpec {
                name: "obs_in_ln.bias".into(),
                shape: vec![obs_dim],
                role: TensorRole::NormBias,
            });
        }
        for l in self.linears(obs_dim, act_dim) {
            let fan_in = l.input;
            v.push(TensorSpec {
                name: format!("{}.weight", l.name),
                shape: vec![l.output, l.input],
                role: TensorRole::Weight { fan_in },
            });
            v.push(TensorSpec {
                name: format!("{}.bias", l.name),
                shape: vec![l.output],
                role: TensorRole::Bias { fan_in },
            });
            if l.layernorm {
                v.push(TensorSpec {
                    name: format!("{}.ln.weight", l.name),
                    shape: vec![l.output],
                    role: TensorRole::NormWeight,
                });
                v.push(TensorSpec {
                    name: format!("{}.ln.bias", l.name),
                    shape: vec![l.output],
                    role: TensorRole::NormBias,
                });
            }
        }
        v
    }
}

/// One linear layer of the architecture.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct LinearSpec {
    /// Name prefix (`trunk.0`): tensors `<name>.weight`, `<name>.bias`, `<name>.ln.*`.
    pub name: String,
    pub input: usize,
    pub output: usize,
    /// A LayerNorm follows (`<name>.ln`).
    pub layernorm: bool,
    /// Trained with spectral normalisation (obs/act encoders and trunk, never head or extras).
    pub spectral_norm: bool,
}

/// What a tensor is (how a trainer initialises it).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum TensorRole {
    Weight { fan_in: usize },
    Bias { fan_in: usize },
    NormWeight,
    NormBias,
}

/// A tensor of `model.safetensors`: name, shape (PyTorch layout) and role.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct TensorSpec {
    pub name: String,
    pub shape: Vec<usize>,
    pub role: TensorRole,
}

/// An observation key and its per-step width.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct ObsKey {
    pub key: String,
    pub dim: usize,
    /// For a key that is a store *layer* (derived features, e.g. a policy encoder's embedding of
    /// the camera frames): the sha256 of the producer that made the values the verifier was
    /// trained on. Features from any other producer (another encoder, other weights) mean
    /// something else, so scoring with them is refused ([`InputLayout::check_producers`]).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub producer: Option<String>,
}

impl ObsKey {
    /// A plain observation key (not a layer).
    pub fn new(key: impl Into<String>, dim: usize) -> Self {
        ObsKey { key: key.into(), dim, producer: None }
    }
}

/// Where an extra input comes from (`input.extra_inputs`): the per-step observation series
/// `key`, current step only, not standardised; the model side is [`ExtraInput`].
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct ExtraInputSpec {
    pub name: String,
    pub key: String,
    pub dim: usize,
    pub width: usize,
}

/// How one verifier input row is laid out: which observation keys, how much history, the chunk
/// shape and the step-embedding width (the trainer builds its samples from it).
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct InputLayout {
    /// Observation keys, concatenated in this order within one step.
    pub obs_keys: Vec<ObsKey>,
    /// `T_o`: the most recent observations, oldest first (the first repeated at episode start).
    pub obs_history: usize,
    /// `H`: action chunk length.
    pub chunk_len: usize,
    /// `A`: per-step action width.
    pub action_dim: usize,
    /// Repeats `architecture.t_embed_dim` (0 in artifacts written before it was recorded).
    #[serde(default)]
    pub t_embed_dim: usize,
    #[serde(default)]
    pub extra_inputs: Vec<ExtraInputSpec>,
}

impl InputLayout {
    /// The observation keys that are layers, with the producer each requires.
    pub fn required_producers(&self) -> Vec<(&str, &str)> {
        self.obs_keys.iter().filter_map(|k| k.producer.as_deref().map(|p| (k.key.as_str(), p))).collect()
    }

    /// Refuses features from the wrong producer: `provided` names, per observation key, the
    /// producer (sha256) of the values about to be scored. Every layer key of this verifier must
    /// be provided with its own producer; a key the verifier takes as a plain observation may
    /// not claim one.
    pub fn check_producers<'a>(
        &self,
        provided: impl IntoIterator<Item = (&'a str, &'a str)>,
    ) -> crate::Result<()> {
        let provided: Vec<(&str, &str)> = provided.into_iter().collect();
        for k in &self.obs_keys {
            let given = provided.iter().find(|(key, _)| *key == k.key).map(|(_, p)| *p);
            match (&k.producer, given) {
                (Some(want), Some(got)) if want != got => {
                    return Err(crate::VerifierError::Input(format!(
                        "observation {:?} comes from producer {}, but this verifier was trained on features of producer {} \
                         (another encoder or other weights: its scores would mean nothing)",
                        k.key,
                        short_hash(got),
                        short_hash(want)
                    )))
                }
                (Some(want), None) => {
                    return Err(crate::VerifierError::Input(format!(
                        "observation {:?} is a feature layer of producer {}: say which producer made the features \
                         you score (this verifier refuses features of any other)",
                        k.key,
                        short_hash(want)
                    )))
                }
                _ => {}
            }
        }
        Ok(())
    }

    /// Width of one observation step (sum of key dims).
    pub fn step_obs_dim(&self) -> usize {
        self.obs_keys.iter().map(|k| k.dim).sum()
    }
    /// `T_o * sum(dim)`.
    pub fn obs_dim(&self) -> usize {
        self.obs_history * self.step_obs_dim()
    }
    /// `H * A`.
    pub fn act_dim(&self) -> usize {
        self.chunk_len * self.action_dim
    }
}

/// In which space the action chunk is fed to the verifier (`input.action_space`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "space", rename_all = "lowercase")]
pub enum ActionSpace {
    /// The paper's choice: the chunk in the policy's normalised sample space,
    /// `x = (raw - offset) / scale` per action dimension (`scale`, `offset`: length
    /// `action_dim`, or empty for the identity), so guidance gradients are taken w.r.t. the
    /// policy's x̂0 directly. `act_mean`/`act_std` are then 0 and 1.
    Policy {
        #[serde(default)]
        scale: Vec<f32>,
        #[serde(default)]
        offset: Vec<f32>,
    },
    /// Before the field existed: the raw chunk, standardised with the train-set
    /// `act_mean`/`act_std`. An artifact without `action_space` is read as this.
    Standardized,
}

impl Default for ActionSpace {
    /// The policy's space with an identity normaliser.
    fn default() -> Self {
        ActionSpace::Policy { scale: vec![], offset: vec![] }
    }
}

impl ActionSpace {
    fn legacy() -> Self {
        ActionSpace::Standardized
    }

    /// The policy's space with the normaliser `raw = x * scale + offset`.
    pub fn policy(scale: Vec<f32>, offset: Vec<f32>) -> Self {
        ActionSpace::Policy { scale, offset }
    }

    pub fn is_policy(&self) -> bool {
        matches!(self, ActionSpace::Policy { .. })
    }

    pub fn validate(&self, action_dim: usize) -> Result<()> {
        if let ActionSpace::Policy { scale, offset } = self {
            for (name, v) in [("scale", scale), ("offset", offset)] {
                if !v.is_empty() && v.len() != action_dim {
                    return Err(VerifierError::Config(format!(
                        "action_space.{name} has length {}, expected action_dim {action_dim} (or empty for the identity)",
                        v.len()
                    )));
                }
                if v.iter().any(|x| !x.is_finite()) {
                    return Err(VerifierError::Config(format!(
                        "action_space.{name} contains a non-finite value"
                    )));
                }
            }
            if scale.contains(&0.0) {
                return Err(VerifierError::Config("action_space.scale contains 0".into()));
            }
        }
        Ok(())
    }

    /// Raw action chunks (flattened `H x A` rows) to the chunks the verifier takes, in place.
    pub fn raw_to_input(&self, chunks: &mut [f32], action_dim: usize) {
        if let ActionSpace::Policy { scale, offset } = self {
            for (i, v) in chunks.iter_mut().enumerate() {
                let d = i % action_dim.max(1);
                let o = offset.get(d).copied().unwrap_or(0.0);
                let s = scale.get(d).copied().unwrap_or(1.0);
                *v = (*v - o) / s;
            }
        }
    }

    /// The inverse of [`Self::raw_to_input`].
    pub fn input_to_raw(&self, chunks: &mut [f32], action_dim: usize) {
        if let ActionSpace::Policy { scale, offset } = self {
            for (i, v) in chunks.iter_mut().enumerate() {
                let d = i % action_dim.max(1);
                let o = offset.get(d).copied().unwrap_or(0.0);
                let s = scale.get(d).copied().unwrap_or(1.0);
                *v = *v * s + o;
            }
        }
    }
}

/// `config.json`'s `ensemble` (schema_version 2): `members` networks of one architecture,
/// trained on one split with different seeds and bootstrap resamples of its episodes, sharing
/// the input statistics; and the rules steering applies with them (trainer/ARTIFACT.md,
/// "Ensembles"; their one implementation is [`crate::ensemble`]).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EnsembleSpec {
    /// K, at least 2.
    pub members: usize,
    /// κ: best-of-N ranks candidates by `mean − κ · spread` of the members' scores.
    pub pessimism: f64,
    /// Best-of-N keeps the policy's own first candidate unless at least this share of the
    /// members score the pick above it.
    pub min_agreement: f64,
    /// Guidance: below this mean resultant length `R` of the members' gradients the push is
    /// zero; above it the push is the mean gradient scaled by `(R − r0) / (1 − r0)`.
    pub min_gradient_agreement: f64,
}

impl EnsembleSpec {
    /// The defaults the trainer records: κ = 1, a pick needs 80% of the members (4 of 5), the
    /// push needs members' gradients with `R` above 0.5.
    pub fn new(members: usize) -> Self {
        EnsembleSpec { members, pessimism: 1.0, min_agreement: 0.8, min_gradient_agreement: 0.5 }
    }

    /// Members in `2..=MAX_MEMBERS`, κ ≥ 0, the agreements in [0, 1).
    pub fn validate(&self) -> Result<()> {
        let bad = |m: String| Err(VerifierError::Config(m));
        if !(2..=MAX_MEMBERS).contains(&self.members) {
            return bad(format!("ensemble.members must be in 2..={MAX_MEMBERS}, got {}", self.members));
        }
        if !(self.pessimism.is_finite() && self.pessimism >= 0.0) {
            return bad(format!("ensemble.pessimism must be finite and >= 0, got {}", self.pessimism));
        }
        for (name, v) in
            [("min_agreement", self.min_agreement), ("min_gradient_agreement", self.min_gradient_agreement)]
        {
            if !(0.0..1.0).contains(&v) {
                return bad(format!("ensemble.{name} must be in [0, 1), got {v}"));
            }
        }
        Ok(())
    }
}

/// The prefix of member `k`'s tensor names in an ensemble's `model.safetensors`.
pub fn member_prefix(k: usize) -> String {
    format!("members.{k}.")
}

/// `config.json`'s `input` object: the layout plus the standardisation statistics.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct InputConfig {
    #[serde(flatten)]
    pub layout: InputLayout,
    /// `T_o * sum(obs_keys dims)`.
    pub obs_dim: usize,
    /// `H * A`.
    pub act_dim: usize,
    pub obs_mean: Vec<f32>,
    pub obs_std: Vec<f32>,
    pub act_mean: Vec<f32>,
    pub act_std: Vec<f32>,
    /// What the action input is (absent in older artifacts: [`ActionSpace::Standardized`]).
    #[serde(default = "ActionSpace::legacy")]
    pub action_space: ActionSpace,
}

/// `config.json`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ArtifactConfig {
    pub schema_version: u32,
    pub kind: Kind,
    pub architecture: Architecture,
    pub input: InputConfig,
    /// Q only (null for the classifier).
    #[serde(default)]
    pub gamma: Option<f64>,
    /// The full training recipe, as the trainer wrote it.
    #[serde(default)]
    pub hyperparameters: serde_json::Value,
    #[serde(default)]
    pub metrics: serde_json::Value,
    /// Store version, label snapshot, split, episode counts, code version...
    #[serde(default)]
    pub lineage: serde_json::Value,
    /// An ensemble's members and steering rules (schema_version 2 only).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub ensemble: Option<EnsembleSpec>,
}

impl ArtifactConfig {
    /// Parse and validate `config.json` bytes. The schema version, kind, variant and activation
    /// are checked first so an unknown one gets its own error even when the rest no longer
    /// parses as schema 1.
    pub fn from_json(bytes: &[u8]) -> Result<Self> {
        let raw: serde_json::Value = serde_json::from_slice(bytes)
            .map_err(|e| VerifierError::Config(format!("not valid JSON: {e}")))?;
        match raw.get("schema_version").and_then(|v| v.as_u64()) {
            Some(1 | 2) => {}
            Some(v) => return Err(VerifierError::UnknownSchema(v)),
            None => return Err(VerifierError::Config("missing or non-integer schema_version".into())),
        }
        if let Some(k) = raw.get("kind").and_then(|v| v.as_str()) {
            if !matches!(k, "classifier" | "q") {
                return Err(VerifierError::UnknownKind(k.into()));
            }
        }
        if let Some(v) = raw.pointer("/architecture/variant").and_then(|v| v.as_str()) {
            if !matches!(v, "lowdim" | "features") {
                return Err(VerifierError::UnknownVariant(v.into()));
            }
        }
        if let Some(a) = raw.pointer("/architecture/activation").and_then(|v| v.as_str()) {
            if !matches!(a, "relu" | "gelu") {
                return Err(VerifierError::UnknownActivation(a.into()));
            }
        }
        let cfg: ArtifactConfig =
            serde_json::from_value(raw).map_err(|e| VerifierError::Config(e.to_string()))?;
        cfg.validate()?;
        Ok(cfg)
    }

    /// The bytes the trainer writes: pretty-printed JSON with a trailing newline.
    pub fn to_json(&self) -> Result<Vec<u8>> {
        let mut b = serde_json::to_vec_pretty(self).map_err(|e| VerifierError::Config(e.to_string()))?;
        b.push(b'\n');
        Ok(b)
    }

    pub fn obs_dim(&self) -> usize {
        self.input.obs_dim
    }
    pub fn act_dim(&self) -> usize {
        self.input.act_dim
    }

    /// Every tensor this configuration needs, in parameter order: one network's, or each
    /// member's under its prefix ([`member_prefix`]).
    pub fn tensors(&self) -> Vec<TensorSpec> {
        let one = self.member_tensors();
        match &self.ensemble {
            None => one,
            Some(e) => (0..e.members)
                .flat_map(|k| {
                    let p = member_prefix(k);
                    one.iter().map(move |t| TensorSpec { name: format!("{p}{}", t.name), ..t.clone() })
                })
                .collect(),
        }
    }

    /// The tensors of one network (of each member of an ensemble, unprefixed).
    pub fn member_tensors(&self) -> Vec<TensorSpec> {
        self.architecture.tensors(self.input.obs_dim, self.input.act_dim)
    }

    /// Networks in the artifact: 1, or the ensemble's members.
    pub fn members(&self) -> usize {
        self.ensemble.as_ref().map_or(1, |e| e.members)
    }

    /// Schema version, architecture, dimensions, statistics and action space are consistent.
    pub fn validate(&self) -> Result<()> {
        match (self.schema_version, &self.ensemble) {
            (SCHEMA_VERSION, None) => {}
            (ENSEMBLE_SCHEMA_VERSION, Some(e)) => e.validate()?,
            (ENSEMBLE_SCHEMA_VERSION, None) => {
                return Err(VerifierError::Config(
                    "schema_version 2 is an ensemble's, but config.json has no `ensemble`".into(),
                ))
            }
            (SCHEMA_VERSION, Some(_)) => {
                return Err(VerifierError::Config("`ensemble` needs schema_version 2, not 1".into()))
            }
            (v, _) => return Err(VerifierError::UnknownSchema(v as u64)),
        }
        let a = &self.architecture;
        a.validate()?;
        let bad = |m: String| Err(VerifierError::Config(m));
        let i = &self.input;
        let l = &i.layout;
        if i.obs_dim == 0 || i.act_dim == 0 {
            return bad("obs_dim and act_dim must be positive".into());
        }
        let per_step = l.obs_keys.iter().try_fold(0usize, |s, k| s.checked_add(k.dim));
        let obs = per_step.and_then(|p| p.checked_mul(l.obs_history));
        if !l.obs_keys.is_empty() && obs != Some(i.obs_dim) {
            return bad(format!(
                "obs_dim {} != obs_history {} * sum(obs_keys dims) {}",
                i.obs_dim,
                l.obs_history,
                per_step.map_or("(overflow)".into(), |p| p.to_string())
            ));
        }
        if l.chunk_len.checked_mul(l.action_dim) != Some(i.act_dim) {
            return bad(format!(
                "act_dim {} != chunk_len {} * action_dim {}",
                i.act_dim, l.chunk_len, l.action_dim
            ));
        }
        if l.t_embed_dim != 0 && l.t_embed_dim != a.t_embed_dim {
            return bad(format!(
                "input.t_embed_dim {} != architecture.t_embed_dim {}",
                l.t_embed_dim, a.t_embed_dim
            ));
        }
        if !l.extra_inputs.is_empty() {
            let same = l.extra_inputs.len() == a.extra_inputs.len()
                && l.extra_inputs
                    .iter()
                    .zip(&a.extra_inputs)
                    .all(|(s, m)| s.name == m.name && s.dim == m.dim && s.width == m.width);
            if !same {
                return bad(
                    "input.extra_inputs does not match architecture.extra_inputs (name, dim, width, order)"
                        .into(),
                );
            }
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
        if let Some(k) = i.obs_std.iter().chain(&i.act_std).position(|&s| s <= 0.0) {
            return bad(format!("obs_std/act_std must be > 0 (entry {k} is not)"));
        }
        i.action_space.validate(l.action_dim)?;
        if let Some(g) = self.gamma {
            if !g.is_finite() {
                return bad("gamma is not finite".into());
            }
        }
        Ok(())
    }
}

/// `manifest.json`: the sha256 of every file of the artifact.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Manifest {
    pub schema_version: u32,
    pub files: BTreeMap<String, String>,
}

impl Manifest {
    /// The manifest of `config.json` and `model.safetensors` bytes, at the configuration's
    /// schema version.
    pub fn of(schema_version: u32, config_json: &[u8], model: &[u8]) -> Self {
        Manifest {
            schema_version,
            files: BTreeMap::from([
                (CONFIG_FILE.to_string(), sha256_hex(config_json)),
                (MODEL_FILE.to_string(), sha256_hex(model)),
            ]),
        }
    }

    /// Parse: known schema version, lists `config.json` and `model.safetensors`, plain names only.
    pub fn parse(bytes: &[u8]) -> Result<Self> {
        let raw: serde_json::Value = serde_json::from_slice(bytes)
            .map_err(|e| VerifierError::Manifest(format!("not valid JSON: {e}")))?;
        match raw.get("schema_version").and_then(|v| v.as_u64()) {
            Some(1 | 2) => {}
            Some(v) => return Err(VerifierError::UnknownSchema(v)),
            None => return Err(VerifierError::Manifest("missing or non-integer schema_version".into())),
        }
        let m: Manifest = serde_json::from_value(raw).map_err(|e| VerifierError::Manifest(e.to_string()))?;
        for f in [CONFIG_FILE, MODEL_FILE] {
            if !m.files.contains_key(f) {
                return Err(VerifierError::Manifest(format!("files does not list {f}")));
            }
        }
        if let Some(name) = m.files.keys().find(|n| !is_plain_name(n) || n.as_str() == MANIFEST_FILE) {
            return Err(VerifierError::Manifest(format!("file name {name:?} is not a plain file name")));
        }
        Ok(m)
    }

    /// Check `bytes` against the manifest's sha256 for `file`.
    pub fn check(&self, file: &str, bytes: &[u8]) -> Result<()> {
        let expected = self
            .files
            .get(file)
            .ok_or_else(|| VerifierError::Manifest(format!("files does not list {file}")))?;
        let actual = sha256_hex(bytes);
        if !actual.eq_ignore_ascii_case(expected.trim()) {
            return Err(VerifierError::HashMismatch {
                file: file.into(),
                expected: expected.clone(),
                actual,
            });
        }
        Ok(())
    }

    /// The bytes the trainer writes: pretty-printed JSON with a trailing newline.
    pub fn to_json(&self) -> Vec<u8> {
        let mut b = serde_json::to_vec_pretty(self).expect("a manifest always serialises");
        b.push(b'\n');
        b
    }
}

/// A file or extra-input name that is safe to join to a directory or a URL: ASCII letters,
/// digits, `-`, `_`, `.`, `@`, at most 200 bytes, not `.` or `..`.
pub fn is_plain_name(s: &str) -> bool {
    !s.is_empty()
        && s.len() <= 200
        && s != "."
        && s != ".."
        && s.bytes().all(|b| b.is_ascii_alphanumeric() || b"-_.@".contains(&b))
}

/// The first 12 characters of a hash for messages (the whole string when shorter or when byte 12
/// is not a character boundary: a producer string from an artifact file is untrusted).
pub fn short_hash(hash: &str) -> &str {
    hash.get(..12).unwrap_or(hash)
}

#[cfg(test)]
mod producer_tests {
    use super::*;

    fn layout() -> InputLayout {
        InputLayout {
            obs_keys: vec![
                ObsKey { key: "features.cnn".into(), dim: 4, producer: Some("a".repeat(64)) },
                ObsKey::new("state", 2),
            ],
            obs_history: 1,
            chunk_len: 2,
            action_dim: 2,
            t_embed_dim: 8,
            extra_inputs: vec![],
        }
    }

    #[test]
    fn features_of_another_producer_are_refused() {
        let l = layout();
        let right = "a".repeat(64);
        let wrong = "b".repeat(64);
        assert_eq!(l.required_producers(), vec![("features.cnn", right.as_str())]);
        assert!(l.check_producers([("features.cnn", right.as_str())]).is_ok());
        let err = l.check_producers([("features.cnn", wrong.as_str())]).unwrap_err().to_string();
        assert!(
            err.contains("bbbbbbbbbbbb") && err.contains("aaaaaaaaaaaa") && err.contains("features.cnn"),
            "{err}"
        );
        let err = l.check_producers([]).unwrap_err().to_string();
        assert!(err.contains("say which producer"), "{err}");
        // A plain key may be given any producer (it is not a layer), and old artifacts' JSON
        // (no producer field) reads as plain keys and is written back unchanged.
        let plain: ObsKey = serde_json::from_str(r#"{"key":"state","dim":2}"#).unwrap();
        assert_eq!(plain, ObsKey::new("state", 2));
        assert_eq!(serde_json::to_string(&plain).unwrap(), r#"{"key":"state","dim":2}"#);
    }
}
