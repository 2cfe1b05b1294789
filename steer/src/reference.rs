//! Reference implementation of the ARTIFACT.md forward pass with candle: every variant (lowdim,
//! features, extra inputs). Gradients come from candle's autograd with the chunk as a `Var` and the
//! weights as constants. Slow-ish but a direct transcription of the contract; the fast path is
//! tested against it.
use crate::config::{Activation, Kind, Variant, VerifierConfig};
use crate::error::{Result, SteerError};
use crate::weights::{temb, Weights};
use crate::Scorer;
use candle_core::{DType, Device, Tensor, Var, D};

struct Linear {
    w_t: Tensor, // [in, out]
    b: Tensor,   // [out]
}

impl Linear {
    fn load(w: &Weights, p: &str, out: usize, inp: usize, dev: &Device) -> Result<Self> {
        let wt = w.get(&format!("{p}.weight"), &[out, inp])?;
        let bt = w.get(&format!("{p}.bias"), &[out])?;
        let w_t = Tensor::from_slice(&wt.data, (out, inp), dev)?.t()?.contiguous()?;
        let b = Tensor::from_slice(&bt.data, out, dev)?;
        Ok(Linear { w_t, b })
    }
    fn forward(&self, x: &Tensor) -> candle_core::Result<Tensor> {
        x.matmul(&self.w_t)?.broadcast_add(&self.b)
    }
}

struct Ln {
    w: Tensor,
    b: Tensor,
    eps: f64,
}

impl Ln {
    fn load(w: &Weights, p: &str, d: usize, eps: f64, dev: &Device) -> Result<Self> {
        let wt = w.get(&format!("{p}.weight"), &[d])?;
        let bt = w.get(&format!("{p}.bias"), &[d])?;
        Ok(Ln { w: Tensor::from_slice(&wt.data, d, dev)?, b: Tensor::from_slice(&bt.data, d, dev)?, eps })
    }
    fn forward(&self, x: &Tensor) -> candle_core::Result<Tensor> {
        let mu = x.mean_keepdim(D::Minus1)?;
        let xc = x.broadcast_sub(&mu)?;
        let var = xc.sqr()?.mean_keepdim(D::Minus1)?;
        let xhat = xc.broadcast_div(&(var + self.eps)?.sqrt()?)?;
        xhat.broadcast_mul(&self.w)?.broadcast_add(&self.b)
    }
}

struct Encoder {
    l0: Linear,
    l1: Linear,
    ln0: Option<Ln>,
    ln1: Option<Ln>,
}

/// The candle reference verifier.
pub struct CandleVerifier {
    cfg: VerifierConfig,
    dev: Device,
    obs_mean: Tensor,
    obs_std: Tensor,
    act_mean: Tensor,
    act_std: Tensor,
    obs_in_ln: Option<Ln>,
    obs_enc: Encoder,
    act_enc: Encoder,
    extras: Vec<Linear>,
    trunk: Vec<(Linear, Ln)>,
    head: Linear,
}

impl CandleVerifier {
    pub fn new(cfg: &VerifierConfig, w: &Weights) -> Result<Self> {
        cfg.validate()?;
        w.validate(cfg)?;
        let dev = Device::Cpu;
        let a = &cfg.architecture;
        let ew = a.encoder_width;
        let eps = a.layernorm_eps;
        let feats = cfg.variant() == Variant::Features;
        let enc = |p: &str, inp: usize| -> Result<Encoder> {
            let lnp = feats && a.encoder_layernorm;
            Ok(Encoder {
                l0: Linear::load(w, &format!("{p}.0"), ew, inp, &dev)?,
                l1: Linear::load(w, &format!("{p}.1"), ew, ew, &dev)?,
                ln0: if lnp { Some(Ln::load(w, &format!("{p}.0.ln"), ew, eps, &dev)?) } else { None },
                ln1: if lnp { Some(Ln::load(w, &format!("{p}.1.ln"), ew, eps, &dev)?) } else { None },
            })
        };
        let i = &cfg.input;
        let mut trunk = Vec::new();
        let mut prev = cfg.trunk_in();
        for (l, &d) in a.trunk_dims.iter().enumerate() {
            trunk.push((
                Linear::load(w, &format!("trunk.{l}"), d, prev, &dev)?,
                Ln::load(w, &format!("trunk.{l}.ln"), d, eps, &dev)?,
            ));
            prev = d;
        }
        Ok(CandleVerifier {
            obs_mean: Tensor::from_slice(&i.obs_mean, i.obs_dim, &dev)?,
            obs_std: Tensor::from_slice(&i.obs_std, i.obs_dim, &dev)?,
            act_mean: Tensor::from_slice(&i.act_mean, i.act_dim, &dev)?,
            act_std: Tensor::from_slice(&i.act_std, i.act_dim, &dev)?,
            obs_in_ln: if feats && a.input_layernorm {
                Some(Ln::load(w, "obs_in_ln", i.obs_dim, eps, &dev)?)
            } else {
                None
            },
            obs_enc: enc("obs_enc", i.obs_dim)?,
            act_enc: enc("act_enc", i.act_dim)?,
            extras: a
                .extra_inputs
                .iter()
                .map(|e| Linear::load(w, &format!("extra.{}", e.name), e.width, e.dim, &dev))
                .collect::<Result<_>>()?,
            trunk,
            head: Linear::load(w, "head", 1, prev, &dev)?,
            cfg: cfg.clone(),
            dev,
        })
    }

    pub fn config(&self) -> &VerifierConfig {
        &self.cfg
    }

    fn act_fn(&self, x: &Tensor) -> candle_core::Result<Tensor> {
        match self.cfg.activation() {
            Activation::Relu => x.relu(),
            Activation::Gelu => x.gelu_erf(),
        }
    }

    fn encode(&self, e: &Encoder, x: &Tensor) -> candle_core::Result<Tensor> {
        match self.cfg.variant() {
            // lowdim: act(enc.1(act(enc.0(x))))
            Variant::Lowdim => self.act_fn(&e.l1.forward(&self.act_fn(&e.l0.forward(x)?)?)?),
            // features: LN(enc.1(act(LN(enc.0(x)))))   (LN only when encoder_layernorm)
            Variant::Features => {
                let mut h = e.l0.forward(x)?;
                if let Some(ln) = &e.ln0 {
                    h = ln.forward(&h)?;
                }
                let mut h = e.l1.forward(&self.act_fn(&h)?)?;
                if let Some(ln) = &e.ln1 {
                    h = ln.forward(&h)?;
                }
                Ok(h)
            }
        }
    }

    /// Raw output y (logit for classifier, value for q) for M rows. `act` is the RAW chunk tensor
    /// [M, act_dim] (may be a Var).
    fn forward_y(&self, obs: &Tensor, extras: &[Tensor], act: &Tensor, t: &[u32]) -> candle_core::Result<Tensor> {
        let m = t.len();
        let mut o = obs.broadcast_sub(&self.obs_mean)?.broadcast_div(&self.obs_std)?;
        if let Some(ln) = &self.obs_in_ln {
            o = ln.forward(&o)?;
        }
        let a = act.broadcast_sub(&self.act_mean)?.broadcast_div(&self.act_std)?;
        let d = self.cfg.architecture.t_embed_dim;
        let mut e = vec![0f32; m * d];
        for (r, &tt) in t.iter().enumerate() {
            temb(tt, d, &mut e[r * d..(r + 1) * d]);
        }
        let e = Tensor::from_vec(e, (m, d), &self.dev)?;
        let ho = self.encode(&self.obs_enc, &o)?;
        let ha = self.encode(&self.act_enc, &a)?;
        let mut parts = vec![ho, ha, e];
        for (lin, x) in self.extras.iter().zip(extras) {
            parts.push(lin.forward(x)?.relu()?);
        }
        let mut h = Tensor::cat(&parts, 1)?;
        for (lin, ln) in &self.trunk {
            h = ln.forward(&lin.forward(&h)?)?.relu()?;
        }
        self.head.forward(&h)?.squeeze(1)
    }

    fn check(&self, obs: &[f32], extras: &[&[f32]], t: &[u32], chunks: &[f32], n: usize) -> Result<()> {
        check_batch(self.cfg.obs_dim(), self.cfg.act_dim(), obs, t, chunks, n)?;
        let ex = &self.cfg.architecture.extra_inputs;
        if extras.len() != ex.len() {
            return Err(SteerError::Input(format!(
                "the verifier needs {} extra input(s) ({:?}), got {}",
                ex.len(),
                ex.iter().map(|e| &e.name).collect::<Vec<_>>(),
                extras.len()
            )));
        }
        for (e, x) in ex.iter().zip(extras) {
            if x.len() != t.len() * e.dim {
                return Err(SteerError::Input(format!(
                    "extra input {:?}: length {} != batch {} * dim {}",
                    e.name,
                    x.len(),
                    t.len(),
                    e.dim
                )));
            }
        }
        Ok(())
    }

    /// Expand per-group rows (B of them) to B*n rows.
    fn expand(&self, x: &[f32], dim: usize, n: usize) -> Vec<f32> {
        let mut v = Vec::with_capacity(x.len() * n);
        for row in x.chunks(dim) {
            for _ in 0..n {
                v.extend_from_slice(row);
            }
        }
        v
    }

    /// Scores for B groups of n candidates (see [`Scorer::score_batch`]), with extra inputs
    /// (one `[B * dim]` slice per `extra_inputs` entry, in config order).
    pub fn score_batch_ext(&self, obs: &[f32], extras: &[&[f32]], t: &[u32], cands: &[f32], n: usize) -> Result<Vec<f32>> {
        self.check(obs, extras, t, cands, n)?;
        let b = t.len();
        let m = b * n;
        let od = self.cfg.obs_dim();
        let o = Tensor::from_vec(self.expand(obs, od, n), (m, od), &self.dev)?;
        let ex: Vec<Tensor> = extras
            .iter()
            .zip(&self.cfg.architecture.extra_inputs)
            .map(|(x, e)| Tensor::from_vec(self.expand(x, e.dim, n), (m, e.dim), &self.dev))
            .collect::<candle_core::Result<_>>()?;
        let a = Tensor::from_slice(cands, (m, self.cfg.act_dim()), &self.dev)?;
        let tt: Vec<u32> = t.iter().flat_map(|&x| std::iter::repeat(x).take(n)).collect();
        let y = self.forward_y(&o, &ex, &a, &tt)?.to_dtype(DType::F32)?.to_vec1::<f32>()?;
        Ok(match self.cfg.kind() {
            Kind::Classifier => y.into_iter().map(sigmoid).collect(),
            Kind::Q => y,
        })
    }

    /// Gradients of log sigmoid(y) (classifier) or y (q) w.r.t. the raw chunks, one per row.
    pub fn grad_batch_ext(&self, obs: &[f32], extras: &[&[f32]], t: &[u32], chunks: &[f32]) -> Result<Vec<f32>> {
        self.check(obs, extras, t, chunks, 1)?;
        let m = t.len();
        let o = Tensor::from_slice(obs, (m, self.cfg.obs_dim()), &self.dev)?;
        let ex: Vec<Tensor> = extras
            .iter()
            .zip(&self.cfg.architecture.extra_inputs)
            .map(|(x, e)| Tensor::from_slice(x, (m, e.dim), &self.dev))
            .collect::<candle_core::Result<_>>()?;
        let var = Var::from_tensor(&Tensor::from_slice(chunks, (m, self.cfg.act_dim()), &self.dev)?)?;
        let y = self.forward_y(&o, &ex, var.as_tensor(), t)?;
        let obj = match self.cfg.kind() {
            // log sigmoid(y) = -relu(-y) - log(1 + exp(-|y|))   (stable)
            Kind::Classifier => {
                let sp = y.abs()?.neg()?.exp()?.affine(1.0, 1.0)?.log()?;
                (y.neg()?.relu()?.neg()? - sp)?
            }
            Kind::Q => y,
        };
        let grads = obj.sum_all()?.backward()?;
        let g = grads
            .get(var.as_tensor())
            .ok_or_else(|| SteerError::Model("no gradient for the action chunk".into()))?;
        Ok(g.flatten_all()?.to_vec1::<f32>()?)
    }
}

pub(crate) fn sigmoid(y: f32) -> f32 {
    if y >= 0.0 {
        1.0 / (1.0 + (-y).exp())
    } else {
        let e = y.exp();
        e / (1.0 + e)
    }
}

pub(crate) fn check_batch(od: usize, ad: usize, obs: &[f32], t: &[u32], chunks: &[f32], n: usize) -> Result<()> {
    let b = t.len();
    if obs.len() != b * od {
        return Err(SteerError::Input(format!("obs length {} != batch {b} * obs_dim {od}", obs.len())));
    }
    if chunks.len() != b * n * ad {
        return Err(SteerError::Input(format!(
            "candidates length {} != batch {b} * n {n} * act_dim {ad}",
            chunks.len()
        )));
    }
    Ok(())
}

impl Scorer for CandleVerifier {
    fn obs_dim(&self) -> usize {
        self.cfg.obs_dim()
    }
    fn act_dim(&self) -> usize {
        self.cfg.act_dim()
    }
    fn score_batch(&self, obs: &[f32], t: &[u32], candidates: &[f32], n: usize) -> Result<Vec<f32>> {
        self.score_batch_ext(obs, &[], t, candidates, n)
    }
    fn grad_batch(&self, obs: &[f32], t: &[u32], chunks: &[f32]) -> Result<Vec<f32>> {
        self.grad_batch_ext(obs, &[], t, chunks)
    }
}
