//! Verifiers with random weights for tests, benchmarks and examples (not a trainer).

use crate::format::{
    ActionSpace, Activation, Architecture, ArtifactConfig, ExtraInput, InputConfig, InputLayout, Kind,
    ObsKey, TensorRole, Variant, SCHEMA_VERSION,
};
use crate::weights::Weights;

/// The shapes of a random verifier.
#[derive(Debug, Clone)]
pub struct RandomSpec {
    pub kind: Kind,
    pub variant: Variant,
    pub obs_keys: Vec<(String, usize)>,
    pub obs_history: usize,
    pub chunk_len: usize,
    pub action_dim: usize,
    pub encoder_width: usize,
    pub t_embed_dim: usize,
    pub trunk_dims: Vec<usize>,
    pub input_layernorm: bool,
    pub encoder_layernorm: bool,
    /// `(name, dim, width)`
    pub extra_inputs: Vec<(String, usize, usize)>,
    /// Raw chunks standardised with random statistics (older artifacts) instead of the policy's
    /// space.
    pub standardized: bool,
}

impl RandomSpec {
    /// The paper's Square task dimensions: obs 46 (one step), chunk 16 x 10, encoders 64,
    /// step embedding 64, trunk 128 -> 64.
    pub fn square() -> Self {
        RandomSpec {
            kind: Kind::Classifier,
            variant: Variant::Lowdim,
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
            standardized: false,
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

    /// The features variant (GELU, every LayerNorm) at the nav dimensions.
    pub fn nav_features() -> Self {
        RandomSpec {
            variant: Variant::Features,
            input_layernorm: true,
            encoder_layernorm: true,
            ..Self::nav()
        }
    }

    /// A random configuration and weights (PyTorch-like `U(-1/sqrt(in), 1/sqrt(in))` linears,
    /// LayerNorm gains near 1), all drawn from `seed`.
    pub fn build(&self, seed: u64) -> (ArtifactConfig, Weights) {
        let mut rng = SplitMix(seed ^ 0x9e37_79b9_7f4a_7c15);
        let obs_dim = self.obs_history * self.obs_keys.iter().map(|k| k.1).sum::<usize>();
        let act_dim = self.chunk_len * self.action_dim;
        let arch = Architecture {
            variant: self.variant,
            activation: if self.variant == Variant::Features { Activation::Gelu } else { Activation::Relu },
            encoder_width: self.encoder_width,
            t_embed_dim: self.t_embed_dim,
            trunk_dims: self.trunk_dims.clone(),
            input_layernorm: self.input_layernorm,
            encoder_layernorm: self.encoder_layernorm,
            spectral_norm: false,
            dropout: 0.5,
            layernorm_eps: 1e-5,
            extra_inputs: self
                .extra_inputs
                .iter()
                .map(|(n, d, w)| ExtraInput { name: n.clone(), dim: *d, width: *w })
                .collect(),
        };
        let mut v = |n: usize, lo: f32, hi: f32| (0..n).map(|_| rng.uniform(lo, hi)).collect::<Vec<f32>>();
        let obs_mean = v(obs_dim, -0.5, 0.5);
        let obs_std = v(obs_dim, 0.5, 2.0);
        let (act_mean, act_std, action_space) = if self.standardized {
            (v(act_dim, -0.5, 0.5), v(act_dim, 0.5, 2.0), ActionSpace::Standardized)
        } else {
            (vec![0.0; act_dim], vec![1.0; act_dim], ActionSpace::default())
        };
        let config = ArtifactConfig {
            schema_version: SCHEMA_VERSION,
            kind: self.kind,
            input: InputConfig {
                layout: InputLayout {
                    obs_keys: self.obs_keys.iter().map(|(k, d)| ObsKey::new(k.clone(), *d)).collect(),
                    obs_history: self.obs_history,
                    chunk_len: self.chunk_len,
                    action_dim: self.action_dim,
                    t_embed_dim: self.t_embed_dim,
                    extra_inputs: vec![],
                },
                obs_dim,
                act_dim,
                obs_mean,
                obs_std,
                act_mean,
                act_std,
                action_space,
            },
            gamma: (self.kind == Kind::Q).then_some(0.99),
            hyperparameters: serde_json::json!({}),
            metrics: serde_json::json!({}),
            lineage: serde_json::json!({"note": "random weights (verifier::testutil)"}),
            ensemble: None,
            architecture: arch,
        };
        let w = random_weights(&config, &mut rng);
        (config, w)
    }

    /// An ensemble's configuration and weights: `members` random networks of this spec (each
    /// drawn from the same seeded stream in member order), sharing [`Self::build`]'s statistics.
    pub fn build_ensemble(&self, seed: u64, members: usize) -> (ArtifactConfig, Weights) {
        let (mut config, _) = self.build(seed);
        config.schema_version = crate::ENSEMBLE_SCHEMA_VERSION;
        config.ensemble = Some(crate::EnsembleSpec::new(members));
        let mut rng = SplitMix(seed ^ 0x5eed_0e45_e3b1_e000);
        let w = random_weights(&config, &mut rng);
        (config, w)
    }
}

/// Every tensor `config` needs, drawn as [`RandomSpec::build`] describes.
fn random_weights(config: &ArtifactConfig, rng: &mut SplitMix) -> Weights {
    {
        let mut w = Weights::default();
        for t in config.tensors() {
            let n: usize = t.shape.iter().product();
            let data: Vec<f32> = match t.role {
                TensorRole::NormWeight => (0..n).map(|_| rng.uniform(0.8, 1.2)).collect(),
                TensorRole::NormBias => (0..n).map(|_| rng.uniform(-0.1, 0.1)).collect(),
                TensorRole::Weight { fan_in } | TensorRole::Bias { fan_in } => {
                    let bound = 1.0 / (fan_in as f32).sqrt();
                    (0..n).map(|_| rng.uniform(-bound, bound)).collect()
                }
            };
            w.insert(&t.name, t.shape, data).expect("shape and data agree");
        }
        w
    }
}

/// splitmix64: enough randomness for test weights, no dependency.
struct SplitMix(u64);

impl SplitMix {
    fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^ (z >> 31)
    }
    fn uniform(&mut self, lo: f32, hi: f32) -> f32 {
        let u = (self.next() >> 40) as f32 / (1u64 << 24) as f32;
        lo + (hi - lo) * u
    }
}
