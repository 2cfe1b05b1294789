//! Reading `model.safetensors` and checking every tensor the config requires (names/shapes from
//! trainer/ARTIFACT.md).
use crate::config::{Variant, VerifierConfig};
use crate::error::{Result, SteerError};
use std::collections::HashMap;

/// One F32 tensor, row-major, PyTorch layout (`Linear.weight` is `[out, in]`).
#[derive(Debug, Clone)]
pub struct Tensor {
    pub shape: Vec<usize>,
    pub data: Vec<f32>,
}

#[derive(Debug, Clone, Default)]
pub struct Weights {
    pub tensors: HashMap<String, Tensor>,
}

impl Weights {
    /// Parse safetensors bytes (all tensors must be F32, little-endian).
    pub fn from_safetensors(bytes: &[u8]) -> Result<Self> {
        let st = safetensors::SafeTensors::deserialize(bytes)
            .map_err(|e| SteerError::Safetensors(e.to_string()))?;
        let mut tensors = HashMap::new();
        for (name, view) in st.tensors() {
            if view.dtype() != safetensors::Dtype::F32 {
                return Err(SteerError::TensorDtype { name, dtype: format!("{:?}", view.dtype()) });
            }
            let raw = view.data();
            let n: usize = view.shape().iter().product();
            if raw.len() != 4 * n {
                return Err(SteerError::Safetensors(format!("tensor {name:?}: data length mismatch")));
            }
            let data: Vec<f32> =
                raw.chunks_exact(4).map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect();
            if data.iter().any(|x| !x.is_finite()) {
                return Err(SteerError::Safetensors(format!("tensor {name:?} contains non-finite values")));
            }
            tensors.insert(name, Tensor { shape: view.shape().to_vec(), data });
        }
        Ok(Weights { tensors })
    }

    /// Serialize (used by tests/benches and by anything that builds artifacts in Rust).
    pub fn to_safetensors(&self) -> Vec<u8> {
        let mut names: Vec<&String> = self.tensors.keys().collect();
        names.sort();
        let bytes: Vec<(String, Vec<usize>, Vec<u8>)> = names
            .iter()
            .map(|n| {
                let t = &self.tensors[*n];
                (n.to_string(), t.shape.clone(), t.data.iter().flat_map(|x| x.to_le_bytes()).collect())
            })
            .collect();
        let views: Vec<(String, safetensors::tensor::TensorView<'_>)> = bytes
            .iter()
            .map(|(n, s, b)| {
                (n.clone(), safetensors::tensor::TensorView::new(safetensors::Dtype::F32, s.clone(), b).unwrap())
            })
            .collect();
        safetensors::tensor::serialize(views, None).expect("serialize safetensors")
    }

    pub fn insert(&mut self, name: &str, shape: Vec<usize>, data: Vec<f32>) {
        assert_eq!(shape.iter().product::<usize>(), data.len());
        self.tensors.insert(name.to_string(), Tensor { shape, data });
    }

    /// Get a tensor, checking it exists and has exactly `shape`.
    pub fn get(&self, name: &str, shape: &[usize]) -> Result<&Tensor> {
        let t = self.tensors.get(name).ok_or_else(|| SteerError::MissingTensor { name: name.into() })?;
        if t.shape != shape {
            return Err(SteerError::TensorShape {
                name: name.into(),
                expected: shape.to_vec(),
                actual: t.shape.clone(),
            });
        }
        Ok(t)
    }

    /// Check every tensor the config requires is present with the right shape.
    pub fn validate(&self, cfg: &VerifierConfig) -> Result<()> {
        for (name, shape) in required_tensors(cfg) {
            self.get(&name, &shape)?;
        }
        Ok(())
    }
}

/// (name, shape) of every tensor the forward pass needs, per ARTIFACT.md.
pub fn required_tensors(cfg: &VerifierConfig) -> Vec<(String, Vec<usize>)> {
    let a = &cfg.architecture;
    let w = a.encoder_width;
    let mut v: Vec<(String, Vec<usize>)> = Vec::new();
    let lin = |v: &mut Vec<(String, Vec<usize>)>, p: &str, o: usize, i: usize| {
        v.push((format!("{p}.weight"), vec![o, i]));
        v.push((format!("{p}.bias"), vec![o]));
    };
    lin(&mut v, "obs_enc.0", w, cfg.input.obs_dim);
    lin(&mut v, "obs_enc.1", w, w);
    lin(&mut v, "act_enc.0", w, cfg.input.act_dim);
    lin(&mut v, "act_enc.1", w, w);
    for e in &a.extra_inputs {
        lin(&mut v, &format!("extra.{}", e.name), e.width, e.dim);
    }
    let mut prev = cfg.trunk_in();
    for (l, &d) in a.trunk_dims.iter().enumerate() {
        lin(&mut v, &format!("trunk.{l}"), d, prev);
        v.push((format!("trunk.{l}.ln.weight"), vec![d]));
        v.push((format!("trunk.{l}.ln.bias"), vec![d]));
        prev = d;
    }
    lin(&mut v, "head", 1, prev);
    if cfg.variant() == Variant::Features {
        if a.input_layernorm {
            v.push(("obs_in_ln.weight".into(), vec![cfg.input.obs_dim]));
            v.push(("obs_in_ln.bias".into(), vec![cfg.input.obs_dim]));
        }
        if a.encoder_layernorm {
            for p in ["obs_enc.0", "obs_enc.1", "act_enc.0", "act_enc.1"] {
                v.push((format!("{p}.ln.weight"), vec![w]));
                v.push((format!("{p}.ln.bias"), vec![w]));
            }
        }
    }
    v
}

/// Sinusoidal episode-step embedding (ARTIFACT.md): even j -> sin(t / 10000^(j/d)), odd j ->
/// cos(t / 10000^((j-1)/d)). Computed in f64, rounded to f32.
pub fn temb(t: u32, d: usize, out: &mut [f32]) {
    for j in 0..d {
        let e = (j - (j % 2)) as f64 / d as f64;
        let x = t as f64 / 10000f64.powf(e);
        out[j] = if j % 2 == 0 { x.sin() } else { x.cos() } as f32;
    }
}
