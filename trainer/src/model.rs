//! The verifier as a trainable candle graph. The architecture types, the tensor names and
//! shapes, and the inference forward pass are the `verifier` core's (re-exported here); this
//! module adds what training needs: parameters in a host-side [`ParamSet`] (the core's tensor
//! list, in its order), [`CandleModel`] over `Var`s with dropout, observation noise and
//! spectral normalisation, and the conversions to and from the core's [`Weights`]. The fused
//! fast path in `fast.rs` reads the same [`ParamSet`] and is tested against this model.

use std::collections::HashMap;
use std::sync::Mutex;

use anyhow::{ensure, Context, Result};
use candle_core::{Device, Tensor, Var, D};
use rand::Rng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};
use serde::{Deserialize, Serialize};
use verifier::{TensorRole, Weights};

pub use verifier::{Activation, Architecture, ExtraInput, Kind, LinearSpec, Variant};

/// Everything needed to build parameters and the forward pass.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ModelSpec {
    pub kind: Kind,
    pub arch: Architecture,
    pub obs_dim: usize,
    pub act_dim: usize,
}

/// Named host-side parameters, in a fixed order.
#[derive(Clone, Debug, PartialEq, Default)]
pub struct ParamSet {
    pub names: Vec<String>,
    pub shapes: Vec<Vec<usize>>,
    pub values: Vec<Vec<f32>>,
}

impl ParamSet {
    pub fn len(&self) -> usize {
        self.names.len()
    }
    pub fn is_empty(&self) -> bool {
        self.names.is_empty()
    }
    pub fn index(&self, name: &str) -> Option<usize> {
        self.names.iter().position(|n| n == name)
    }
    pub fn get(&self, name: &str) -> Option<&[f32]> {
        self.index(name).map(|i| self.values[i].as_slice())
    }
    pub fn numel(&self) -> usize {
        self.values.iter().map(|v| v.len()).sum()
    }
    fn push(&mut self, name: String, shape: Vec<usize>, values: Vec<f32>) {
        debug_assert_eq!(shape.iter().product::<usize>(), values.len());
        self.names.push(name);
        self.shapes.push(shape);
        self.values.push(values);
    }
    /// Zeros with the same layout (gradient / moment buffers).
    pub fn zeros_like(&self) -> Vec<Vec<f32>> {
        self.values.iter().map(|v| vec![0.0; v.len()]).collect()
    }
}

impl ModelSpec {
    /// The linear layers in parameter order (the core's list).
    pub fn layers(&self) -> Vec<LinearSpec> {
        self.arch.linears(self.obs_dim, self.act_dim)
    }

    /// Freshly initialised parameters in the core's tensor order (PyTorch defaults:
    /// `U(-1/sqrt(in), 1/sqrt(in))` for Linear weight and bias, LayerNorm weight 1 / bias 0),
    /// drawn from `rng`.
    pub fn init_params(&self, rng: &mut ChaCha8Rng) -> ParamSet {
        let mut p = ParamSet::default();
        for t in self.arch.tensors(self.obs_dim, self.act_dim) {
            let n: usize = t.shape.iter().product();
            let values = match t.role {
                TensorRole::Weight { fan_in } | TensorRole::Bias { fan_in } => {
                    let bound = 1.0 / (fan_in as f32).sqrt();
                    (0..n).map(|_| rng.gen_range(-bound..bound)).collect()
                }
                TensorRole::NormWeight => vec![1.0; n],
                TensorRole::NormBias => vec![0.0; n],
            };
            p.push(t.name, t.shape, values);
        }
        p
    }

    /// Check that `p` has exactly the tensors (names, shapes, order) this spec needs.
    pub fn check_params(&self, p: &ParamSet) -> Result<()> {
        let want = self.arch.tensors(self.obs_dim, self.act_dim);
        ensure!(want.len() == p.len(), "expected {} tensors, found {} ({:?})", want.len(), p.len(), p.names);
        for (i, t) in want.iter().enumerate() {
            ensure!(p.names[i] == t.name, "tensor {i} is {}, expected {}", p.names[i], t.name);
            ensure!(
                p.shapes[i] == t.shape,
                "tensor {}: shape {:?}, expected {:?}",
                t.name,
                p.shapes[i],
                t.shape
            );
        }
        Ok(())
    }
}

/// Persistent power-iteration vectors of one spectrally normalised layer.
#[derive(Clone, Debug)]
struct SnState {
    u: Vec<f32>,
    v: Vec<f32>,
}

/// Inputs of one batch as tensors (already standardised).
pub struct BatchTensors {
    /// `[B, obs_dim]`
    pub obs: Tensor,
    /// `[B, act_dim]`
    pub act: Tensor,
    /// `[B, t_embed_dim]`
    pub temb: Tensor,
    /// One `[B, dim]` per extra input.
    pub extras: Vec<Tensor>,
}

/// Training-time randomness for one forward pass (drawn by the caller from its seeded RNG).
#[derive(Default)]
pub struct TrainNoise {
    /// `[B, trunk_dims.last]` dropout mask, already scaled (0 or 1/(1-p)).
    pub drop_mask: Option<Tensor>,
    /// `[B, obs_dim]` Gaussian noise added to the (layer-normed) observation.
    pub obs_noise: Option<Tensor>,
}

/// The verifier as a candle graph over `Var`s.
pub struct CandleModel {
    pub spec: ModelSpec,
    names: Vec<String>,
    vars: Vec<Var>,
    index: HashMap<String, usize>,
    sn: Mutex<HashMap<String, SnState>>,
    device: Device,
}

impl CandleModel {
    /// Wrap `params` (copied) in `Var`s. Spectral-norm vectors are initialised from `rng`
    /// (unit-normalised Gaussian, as PyTorch) when the architecture uses spectral norm.
    pub fn new(spec: &ModelSpec, params: &ParamSet, rng: &mut ChaCha8Rng) -> Result<Self> {
        spec.check_params(params)?;
        let device = Device::Cpu;
        let mut vars = Vec::with_capacity(params.len());
        let mut index = HashMap::new();
        for (i, ((n, s), v)) in params.names.iter().zip(&params.shapes).zip(&params.values).enumerate() {
            vars.push(Var::from_tensor(&Tensor::from_slice(v, s.as_slice(), &device)?)?);
            index.insert(n.clone(), i);
        }
        let mut sn = HashMap::new();
        if spec.arch.spectral_norm {
            for l in spec.layers().into_iter().filter(|l| l.spectral_norm) {
                let u = unit_normal(rng, l.output);
                let v = unit_normal(rng, l.input);
                sn.insert(l.name, SnState { u, v });
            }
        }
        Ok(CandleModel {
            spec: spec.clone(),
            names: params.names.clone(),
            vars,
            index,
            sn: Mutex::new(sn),
            device,
        })
    }

    pub fn device(&self) -> &Device {
        &self.device
    }
    pub fn vars(&self) -> &[Var] {
        &self.vars
    }
    pub fn names(&self) -> &[String] {
        &self.names
    }
    pub fn var(&self, name: &str) -> Result<&Var> {
        let i = *self.index.get(name).with_context(|| format!("no parameter {name}"))?;
        Ok(&self.vars[i])
    }

    /// Overwrite the `Var`s from host values (same layout as at construction).
    pub fn set_params(&self, params: &ParamSet) -> Result<()> {
        for (var, (v, s)) in self.vars.iter().zip(params.values.iter().zip(&params.shapes)) {
            var.set(&Tensor::from_slice(v, s.as_slice(), &self.device)?)?;
        }
        Ok(())
    }

    /// Current raw parameter values.
    pub fn params(&self) -> Result<ParamSet> {
        let mut p = ParamSet::default();
        for (n, var) in self.names.iter().zip(&self.vars) {
            let t = var.as_tensor();
            p.push(n.clone(), t.dims().to_vec(), t.flatten_all()?.to_vec1::<f32>()?);
        }
        Ok(p)
    }

    /// Parameters for inference/export: spectrally normalised weights replaced by `W / sigma`
    /// (sigma from the current power-iteration vectors), so clients need no power iteration.
    pub fn inference_params(&self) -> Result<ParamSet> {
        let mut p = self.params()?;
        if self.spec.arch.spectral_norm {
            let sn = self.sn.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
            for (name, st) in sn.iter() {
                let i = p.index(&format!("{name}.weight")).context("sn weight")?;
                let sigma = sigma_uv(&p.values[i], &st.u, &st.v);
                p.values[i].iter_mut().for_each(|x| *x /= sigma);
            }
        }
        Ok(p)
    }

    /// One power-iteration update of every spectrally normalised layer (call once per training
    /// step, before the forward pass, as PyTorch's `spectral_norm` does in train mode).
    pub fn power_iteration(&self, iters: usize) -> Result<()> {
        if !self.spec.arch.spectral_norm {
            return Ok(());
        }
        let mut sn = self.sn.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
        for (name, st) in sn.iter_mut() {
            let w = self.var(&format!("{name}.weight"))?.as_tensor().flatten_all()?.to_vec1::<f32>()?;
            power_iterate(&w, st.u.len(), st.v.len(), &mut st.u, &mut st.v, iters);
        }
        Ok(())
    }

    /// Largest-singular-value estimate `u^T W v` of a spectrally normalised layer.
    pub fn sigma(&self, layer: &str) -> Result<f32> {
        let sn = self.sn.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
        let st = sn.get(layer).with_context(|| format!("{layer} has no spectral norm"))?;
        let w = self.var(&format!("{layer}.weight"))?.as_tensor().flatten_all()?.to_vec1::<f32>()?;
        Ok(sigma_uv(&w, &st.u, &st.v))
    }

    fn weight(&self, layer: &str) -> Result<Tensor> {
        let w = self.var(&format!("{layer}.weight"))?.as_tensor().clone();
        let sn = self.sn.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
        if let Some(st) = sn.get(layer) {
            // sigma = u^T W v with u, v constants: the gradient flows through sigma into W.
            let u = Tensor::from_slice(&st.u, (1, st.u.len()), &self.device)?;
            let v = Tensor::from_slice(&st.v, (st.v.len(), 1), &self.device)?;
            let sigma = u.matmul(&w)?.matmul(&v)?; // [1, 1]
            return Ok(w.broadcast_div(&sigma)?);
        }
        Ok(w)
    }

    fn linear(&self, x: &Tensor, layer: &str) -> Result<Tensor> {
        let w = self.weight(layer)?;
        let b = self.var(&format!("{layer}.bias"))?.as_tensor();
        Ok(x.matmul(&w.t()?)?.broadcast_add(b)?)
    }

    fn ln(&self, x: &Tensor, prefix: &str) -> Result<Tensor> {
        let w = self.var(&format!("{prefix}.weight"))?.as_tensor();
        let b = self.var(&format!("{prefix}.bias"))?.as_tensor();
        layer_norm(x, w, b, self.spec.arch.layernorm_eps)
    }

    fn act(&self, x: &Tensor) -> Result<Tensor> {
        Ok(match self.spec.arch.activation {
            Activation::Relu => x.relu()?,
            Activation::Gelu => x.gelu_erf()?,
        })
    }

    fn encoder(&self, x: &Tensor, prefix: &str) -> Result<Tensor> {
        let a = &self.spec.arch;
        let mut h = x.clone();
        for i in 0..2 {
            let name = format!("{prefix}.{i}");
            h = self.linear(&h, &name)?;
            if a.encoder_layernorm {
                h = self.ln(&h, &format!("{name}.ln"))?;
            }
            // lowdim: relu after both linears; features: GELU between them only (ARTIFACT.md).
            if a.variant == Variant::Lowdim || i == 0 {
                h = self.act(&h)?;
            }
        }
        Ok(h)
    }

    /// Forward pass. Returns `(y [B], z [B, trunk_dims.last])` where `y` is the head output
    /// (logit or value) and `z` the penultimate features (contrastive embedding, pre-dropout).
    pub fn forward(&self, b: &BatchTensors, noise: &TrainNoise) -> Result<(Tensor, Tensor)> {
        let a = &self.spec.arch;
        let mut o = b.obs.clone();
        if a.input_layernorm {
            o = self.ln(&o, "obs_in_ln")?;
        }
        if let Some(n) = &noise.obs_noise {
            o = (o + n)?;
        }
        let ho = self.encoder(&o, "obs_enc")?;
        let ha = self.encoder(&b.act, "act_enc")?;
        let mut parts = vec![ho, ha, b.temb.clone()];
        ensure!(b.extras.len() == a.extra_inputs.len(), "wrong number of extra inputs");
        for (e, x) in a.extra_inputs.iter().zip(&b.extras) {
            parts.push(self.linear(x, &format!("extra.{}", e.name))?.relu()?);
        }
        let mut h = Tensor::cat(&parts, 1)?;
        for i in 0..a.trunk_dims.len() {
            let name = format!("trunk.{i}");
            h = self.linear(&h, &name)?;
            h = self.ln(&h, &format!("{name}.ln"))?.relu()?;
        }
        let z = h;
        let zd = match &noise.drop_mask {
            Some(m) => z.mul(m)?,
            None => z.clone(),
        };
        let y = self.linear(&zd, "head")?.squeeze(1)?;
        Ok((y, z))
    }

    /// Build batch tensors from flat host arrays (`n` rows).
    pub fn batch_tensors(
        &self,
        n: usize,
        obs: &[f32],
        act: &[f32],
        temb: &[f32],
        extras: &[&[f32]],
    ) -> Result<BatchTensors> {
        let d = &self.device;
        let a = &self.spec.arch;
        Ok(BatchTensors {
            obs: Tensor::from_slice(obs, (n, self.spec.obs_dim), d)?,
            act: Tensor::from_slice(act, (n, self.spec.act_dim), d)?,
            temb: Tensor::from_slice(temb, (n, a.t_embed_dim), d)?,
            extras: extras
                .iter()
                .zip(&a.extra_inputs)
                .map(|(x, e)| Tensor::from_slice(x, (n, e.dim), d))
                .collect::<candle_core::Result<_>>()?,
        })
    }
}

/// LayerNorm written from primitive ops (biased variance over the last dim), so gradients reach
/// the input, weight and bias (candle_nn's fused LayerNorm drops them on contiguous inputs).
pub fn layer_norm(x: &Tensor, w: &Tensor, b: &Tensor, eps: f64) -> Result<Tensor> {
    let mean = x.mean_keepdim(D::Minus1)?;
    let xc = x.broadcast_sub(&mean)?;
    let var = xc.sqr()?.mean_keepdim(D::Minus1)?;
    let xhat = xc.broadcast_div(&(var + eps)?.sqrt()?)?;
    Ok(xhat.broadcast_mul(w)?.broadcast_add(b)?)
}

fn unit_normal(rng: &mut ChaCha8Rng, n: usize) -> Vec<f32> {
    let mut v: Vec<f32> = (0..n).map(|_| StandardNormal.sample(rng)).collect();
    normalize(&mut v);
    v
}

fn normalize(v: &mut [f32]) {
    let n = v.iter().map(|x| (*x as f64) * (*x as f64)).sum::<f64>().sqrt().max(1e-12);
    v.iter_mut().for_each(|x| *x = (*x as f64 / n) as f32);
}

/// `u^T W v` for row-major `W [u.len(), v.len()]`.
pub fn sigma_uv(w: &[f32], u: &[f32], v: &[f32]) -> f32 {
    let n = v.len();
    let mut s = 0f64;
    for (i, ui) in u.iter().enumerate() {
        let row = &w[i * n..(i + 1) * n];
        let dot: f64 = row.iter().zip(v).map(|(a, b)| *a as f64 * *b as f64).sum();
        s += *ui as f64 * dot;
    }
    s as f32
}

/// Power iteration on row-major `W [m, n]` (PyTorch order: `v = norm(W^T u)`, `u = norm(W v)`).
pub fn power_iterate(w: &[f32], m: usize, n: usize, u: &mut [f32], v: &mut [f32], iters: usize) {
    for _ in 0..iters {
        let mut nv = vec![0f64; n];
        for i in 0..m {
            let ui = u[i] as f64;
            for (acc, wij) in nv.iter_mut().zip(&w[i * n..(i + 1) * n]) {
                *acc += *wij as f64 * ui;
            }
        }
        for (dst, s) in v.iter_mut().zip(&nv) {
            *dst = *s as f32;
        }
        normalize(v);
        for i in 0..m {
            u[i] = w[i * n..(i + 1) * n].iter().zip(v.iter()).map(|(a, b)| *a as f64 * *b as f64).sum::<f64>()
                as f32;
        }
        normalize(u);
    }
}

/// Spectral norm estimate of row-major `W [m, n]` by `iters` power iterations from a seeded start.
pub fn spectral_norm_estimate(w: &[f32], m: usize, n: usize, iters: usize, seed: u64) -> f32 {
    let mut rng: ChaCha8Rng = rand::SeedableRng::seed_from_u64(seed);
    let mut u = unit_normal(&mut rng, m);
    let mut v = unit_normal(&mut rng, n);
    power_iterate(w, m, n, &mut u, &mut v, iters);
    sigma_uv(w, &u, &v)
}

impl ParamSet {
    /// The core's weights (for writing an artifact).
    pub fn to_weights(&self) -> Result<Weights> {
        let mut w = Weights::default();
        for ((n, s), v) in self.names.iter().zip(&self.shapes).zip(&self.values) {
            w.insert(n, s.clone(), v.clone())?;
        }
        Ok(w)
    }

    /// Parameters in `spec`'s order from the core's weights (already checked against the
    /// artifact's configuration).
    pub fn from_weights(spec: &ModelSpec, w: &Weights) -> Result<Self> {
        let mut p = ParamSet::default();
        for t in spec.arch.tensors(spec.obs_dim, spec.act_dim) {
            let x = w.tensor(&t.name, &t.shape)?;
            p.push(t.name, t.shape, x.data.clone());
        }
        ensure!(p.len() == w.len(), "the weights hold {} tensors, the architecture {}", w.len(), p.len());
        Ok(p)
    }
}
