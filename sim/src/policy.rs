//! Base policies: a small candle MLP conditioned on the observation (previous and current
//! position), either a DDPM model ([`DiffusionPolicy`], implements `steer::NoisePredictor`,
//! squaredcos_cap_v2 schedule from steer; the network is trained to predict the clean chunk —
//! diffusers' prediction_type "sample", which learns this task far faster than eps-prediction —
//! and `predict_noise` converts that to eps) or a flow-matching velocity
//! ([`FlowPolicy`], implements `steer::VelocityField`). Action chunks of `horizon` velocities,
//! normalised by `max_speed` (so the sample space is ~[-1, 1], clipped like diffusers'
//! `clip_sample`). Training is seeded end to end (weights initialised from a ChaCha RNG).
use crate::demos::Demo;
use anyhow::{Context, Result};
use candle_core::{DType, Device, Tensor, Var};
use candle_nn::{AdamW, Optimizer, ParamsAdamW};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;
use serde::{Deserialize, Serialize};
use std::path::Path;
use steer::{ActionAffine, DdpmSchedule, Guidance, NoisePredictor, VelocityField};

#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct PolicyConfig {
    /// H, actions per chunk
    pub horizon: usize,
    /// actions executed before re-planning
    pub n_exec: usize,
    pub hidden: usize,
    /// hidden layers
    pub depth: usize,
    pub t_embed: usize,
    /// K (train and inference)
    pub diffusion_steps: usize,
    /// Euler steps of the flow twin
    pub flow_steps: usize,
    /// action normalisation: raw velocity = x * max_speed
    pub max_speed: f32,
}

impl Default for PolicyConfig {
    fn default() -> Self {
        PolicyConfig {
            horizon: 8,
            n_exec: 4,
            hidden: 128,
            depth: 3,
            t_embed: 32,
            diffusion_steps: 20,
            flow_steps: 10,
            max_speed: 0.04,
        }
    }
}

impl PolicyConfig {
    /// The policy's action normaliser, `raw velocity = x * max_speed`, per action dimension:
    /// the samplers apply it, and the trainer takes it to put stored velocities into the
    /// policy's space (`trainer::TrainConfig::action_space`).
    pub fn action_normalizer(&self) -> ActionAffine {
        ActionAffine { scale: vec![self.max_speed; 2], offset: vec![0.0; 2] }
    }
    /// Observation = previous and current position (oldest first).
    pub fn obs_dim(&self) -> usize {
        4
    }
    pub fn act_dim(&self) -> usize {
        self.horizon * 2
    }
}

#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct PolicyTrainConfig {
    pub steps: usize,
    pub batch: usize,
    pub lr: f64,
    pub seed: u64,
}

impl Default for PolicyTrainConfig {
    fn default() -> Self {
        PolicyTrainConfig { steps: 1500, batch: 256, lr: 3e-3, seed: 0 }
    }
}

/// The MLP eps/v network: [obs_n (4), x (H*2), temb] -> hidden (SiLU) x depth -> H*2.
struct Mlp {
    names: Vec<String>,
    vars: Vec<Var>,
}

impl Mlp {
    fn new(cfg: &PolicyConfig, rng: &mut ChaCha8Rng) -> Result<Self> {
        let mut dims = vec![cfg.obs_dim() + cfg.act_dim() + cfg.t_embed];
        dims.extend(std::iter::repeat_n(cfg.hidden, cfg.depth));
        dims.push(cfg.act_dim());
        let mut names = Vec::new();
        let mut vars = Vec::new();
        for l in 0..dims.len() - 1 {
            let (i, o) = (dims[l], dims[l + 1]);
            let bound = 1.0 / (i as f32).sqrt();
            let w: Vec<f32> = (0..i * o).map(|_| rng.gen_range(-bound..bound)).collect();
            let b: Vec<f32> = (0..o).map(|_| rng.gen_range(-bound..bound)).collect();
            names.push(format!("l{l}.w"));
            vars.push(Var::from_tensor(&Tensor::from_vec(w, (i, o), &Device::Cpu)?)?);
            names.push(format!("l{l}.b"));
            vars.push(Var::from_tensor(&Tensor::from_vec(b, o, &Device::Cpu)?)?);
        }
        Ok(Mlp { names, vars })
    }

    fn forward(&self, x: &Tensor) -> candle_core::Result<Tensor> {
        let nl = self.vars.len() / 2;
        let mut h = x.clone();
        for l in 0..nl {
            h = h.matmul(self.vars[2 * l].as_tensor())?.broadcast_add(self.vars[2 * l + 1].as_tensor())?;
            if l + 1 < nl {
                h = h.silu()?;
            }
        }
        Ok(h)
    }

    fn save(&self, path: &Path) -> Result<()> {
        let map: std::collections::HashMap<String, Tensor> =
            self.names.iter().cloned().zip(self.vars.iter().map(|v| v.as_tensor().clone())).collect();
        candle_core::safetensors::save(&map, path)?;
        Ok(())
    }

    fn load(&mut self, path: &Path) -> Result<()> {
        let map = candle_core::safetensors::load(path, &Device::Cpu)?;
        for (n, v) in self.names.iter().zip(&self.vars) {
            let t = map.get(n).with_context(|| format!("missing {n} in {}", path.display()))?;
            v.set(t)?;
        }
        Ok(())
    }
}

/// The diffusion step fed to the sinusoidal embedding, spread over [0, 1000) like diffusers'
/// 1000-step timesteps (raw k in 0..20 would leave most embedding frequencies constant).
fn ddpm_tval(k: usize, big_k: usize) -> f32 {
    k as f32 * 1000.0 / big_k as f32
}

fn temb_into(x: f32, d: usize, out: &mut Vec<f32>) {
    for j in 0..d / 2 {
        let f = (x as f64) / 10000f64.powf(2.0 * j as f64 / d as f64);
        out.push(f.sin() as f32);
        out.push(f.cos() as f32);
    }
}

/// Network input rows: [normalised obs, x, temb(tval)] for B rows.
fn build_input(cfg: &PolicyConfig, obs: &[f32], x: &[f32], tvals: &[f32]) -> Result<Tensor> {
    let (od, ad, te) = (cfg.obs_dim(), cfg.act_dim(), cfg.t_embed);
    let b = tvals.len();
    let w = od + ad + te;
    let mut v = Vec::with_capacity(b * w);
    for r in 0..b {
        v.extend(obs[r * od..(r + 1) * od].iter().map(|p| (p - 0.5) * 2.0));
        v.extend_from_slice(&x[r * ad..(r + 1) * ad]);
        temb_into(tvals[r], te, &mut v);
    }
    Ok(Tensor::from_vec(v, (b, w), &Device::Cpu)?)
}

/// Training pairs from demos: obs = (p_{t-1}, p_t) (p_{-1} = p_0), chunk = a_t..a_{t+H-1} padded
/// with the last action, normalised by max_speed.
pub fn training_pairs(cfg: &PolicyConfig, demos: &[Demo]) -> (Vec<f32>, Vec<f32>) {
    let mut obs = Vec::new();
    let mut act = Vec::new();
    for d in demos {
        let t_len = d.actions.len();
        for t in 0..t_len {
            let prev = d.positions[t.saturating_sub(1)];
            let cur = d.positions[t];
            obs.extend_from_slice(&[prev[0], prev[1], cur[0], cur[1]]);
            for h in 0..cfg.horizon {
                let a = d.actions[(t + h).min(t_len - 1)];
                act.push(a[0] / cfg.max_speed);
                act.push(a[1] / cfg.max_speed);
            }
        }
    }
    (obs, act)
}

enum Objective {
    Ddpm(DdpmSchedule),
    Flow,
}

fn train_mlp(
    cfg: &PolicyConfig,
    tc: &PolicyTrainConfig,
    demos: &[Demo],
    obj: &Objective,
) -> Result<(Mlp, f32)> {
    let mut rng = ChaCha8Rng::seed_from_u64(tc.seed);
    let mlp = Mlp::new(cfg, &mut rng)?;
    let (obs, act) = training_pairs(cfg, demos);
    let (od, ad) = (cfg.obs_dim(), cfg.act_dim());
    let n = obs.len() / od;
    anyhow::ensure!(n > 0, "no training pairs");
    let mut opt =
        AdamW::new(mlp.vars.clone(), ParamsAdamW { lr: tc.lr, weight_decay: 1e-4, ..Default::default() })?;
    let mut last = f32::NAN;
    let mut ema = None::<f32>;
    for step in 0..tc.steps {
        // cosine learning-rate decay
        let lr = tc.lr * 0.5 * (1.0 + (std::f64::consts::PI * step as f64 / tc.steps as f64).cos());
        opt.set_learning_rate(lr.max(tc.lr * 0.02));
        let b = tc.batch;
        let mut bo = Vec::with_capacity(b * od);
        let mut xt = Vec::with_capacity(b * ad);
        let mut target = Vec::with_capacity(b * ad);
        let mut tv = Vec::with_capacity(b);
        for _ in 0..b {
            let i = rng.gen_range(0..n);
            bo.extend_from_slice(&obs[i * od..(i + 1) * od]);
            let x0 = &act[i * ad..(i + 1) * ad];
            let eps: Vec<f32> = (0..ad).map(|_| rng.sample::<f32, _>(StandardNormal)).collect();
            match obj {
                Objective::Ddpm(s) => {
                    let k = rng.gen_range(0..s.num_steps());
                    let ab = s.alpha_bar(k + 1);
                    let (sa, s1) = (ab.sqrt() as f32, (1.0 - ab).sqrt() as f32);
                    xt.extend(x0.iter().zip(&eps).map(|(x, e)| sa * x + s1 * e));
                    // the network predicts the clean chunk (diffusers' prediction_type "sample");
                    // `predict_noise` converts it to eps for the sampler
                    target.extend_from_slice(x0);
                    tv.push(ddpm_tval(k, s.num_steps()));
                }
                Objective::Flow => {
                    let t: f32 = rng.gen_range(0.0..1.0);
                    xt.extend(x0.iter().zip(&eps).map(|(x, e)| (1.0 - t) * x + t * e));
                    // x0-parameterised like the DDPM twin: v = (a_t - x0_hat) / t at sampling
                    target.extend_from_slice(x0);
                    tv.push(t * 1000.0);
                }
            }
        }
        let inp = build_input(cfg, &bo, &xt, &tv)?;
        let tgt = Tensor::from_vec(target, (b, ad), &Device::Cpu)?;
        let loss = (mlp.forward(&inp)? - tgt)?.sqr()?.mean_all()?;
        opt.backward_step(&loss)?;
        if step % 50 == 0 || step + 1 == tc.steps {
            last = loss.to_dtype(DType::F32)?.to_scalar::<f32>()?;
            ema = Some(ema.map_or(last, |e| 0.8 * e + 0.2 * last));
        }
    }
    Ok((mlp, ema.unwrap_or(last)))
}

/// Something that samples raw action chunks for a batch of observations, optionally guided.
pub trait ChunkPolicy {
    fn config(&self) -> &PolicyConfig;
    /// The map from the policy's normalised sample space to raw actions (`raw = x * max_speed`);
    /// the verifier is trained and queried in that space (see [`PolicyConfig::action_normalizer`]).
    fn sample_space(&self) -> ActionAffine {
        self.config().action_normalizer()
    }
    /// One raw chunk (`horizon * 2` velocities) per observation row (`obs` is `B * 4`).
    fn sample_chunks(
        &self,
        obs: &[f32],
        guidance: Option<&Guidance>,
        rng: &mut ChaCha8Rng,
    ) -> steer::Result<Vec<f32>>;
    fn name(&self) -> &'static str;
}

/// DDPM base policy.
pub struct DiffusionPolicy {
    pub cfg: PolicyConfig,
    sched: DdpmSchedule,
    mlp: Mlp,
    /// final training loss (smoothed)
    pub train_loss: f32,
}

impl DiffusionPolicy {
    pub fn train(cfg: &PolicyConfig, tc: &PolicyTrainConfig, demos: &[Demo]) -> Result<Self> {
        let sched = DdpmSchedule::squaredcos_cap_v2(cfg.diffusion_steps)?;
        let (mlp, train_loss) = train_mlp(cfg, tc, demos, &Objective::Ddpm(sched.clone()))?;
        Ok(DiffusionPolicy { cfg: cfg.clone(), sched, mlp, train_loss })
    }
    /// Writes `<dir>/ddpm.safetensors` and `<dir>/ddpm.json`.
    pub fn save(&self, dir: &Path) -> Result<()> {
        std::fs::create_dir_all(dir)?;
        std::fs::write(dir.join("ddpm.json"), serde_json::to_vec_pretty(&self.cfg)?)?;
        self.mlp.save(&dir.join("ddpm.safetensors"))
    }
    pub fn load(dir: &Path) -> Result<Self> {
        let cfg: PolicyConfig = serde_json::from_slice(&std::fs::read(dir.join("ddpm.json"))?)?;
        let mut mlp = Mlp::new(&cfg, &mut ChaCha8Rng::seed_from_u64(0))?;
        mlp.load(&dir.join("ddpm.safetensors"))?;
        let sched = DdpmSchedule::squaredcos_cap_v2(cfg.diffusion_steps)?;
        Ok(DiffusionPolicy { sched, cfg, mlp, train_loss: f32::NAN })
    }
}

fn to_steer<E: std::fmt::Display>(e: E) -> steer::SteerError {
    steer::SteerError::Model(e.to_string())
}

fn run_mlp(mlp: &Mlp, cfg: &PolicyConfig, obs: &[f32], x: &[f32], tval: f32) -> steer::Result<Vec<f32>> {
    let b = obs.len() / cfg.obs_dim();
    let inp = build_input(cfg, obs, x, &vec![tval; b]).map_err(to_steer)?;
    let out = mlp.forward(&inp).map_err(to_steer)?;
    out.flatten_all().and_then(|o| o.to_vec1::<f32>()).map_err(to_steer)
}

impl NoisePredictor for DiffusionPolicy {
    fn obs_dim(&self) -> usize {
        self.cfg.obs_dim()
    }
    fn act_dim(&self) -> usize {
        self.cfg.act_dim()
    }
    fn schedule(&self) -> &DdpmSchedule {
        &self.sched
    }
    fn predict_noise(&self, obs: &[f32], a_k: &[f32], timestep: usize) -> steer::Result<Vec<f32>> {
        let x0 = run_mlp(&self.mlp, &self.cfg, obs, a_k, ddpm_tval(timestep, self.sched.num_steps()))?;
        // eps = (a_k - sqrt(ab) x0) / sqrt(1 - ab)
        let ab = self.sched.alpha_bar(timestep + 1);
        let (sa, s1) = (ab.sqrt() as f32, (1.0 - ab).sqrt() as f32);
        Ok(a_k.iter().zip(&x0).map(|(a, x)| (a - sa * x) / s1).collect())
    }
    fn clip_sample(&self) -> Option<f32> {
        Some(1.0)
    }
    fn action_affine(&self) -> Option<ActionAffine> {
        Some(self.cfg.action_normalizer())
    }
}

impl ChunkPolicy for DiffusionPolicy {
    fn config(&self) -> &PolicyConfig {
        &self.cfg
    }
    fn sample_chunks(
        &self,
        obs: &[f32],
        guidance: Option<&Guidance>,
        rng: &mut ChaCha8Rng,
    ) -> steer::Result<Vec<f32>> {
        match guidance {
            None => steer::ddpm_sample(self, obs, rng),
            Some(g) => steer::ddpm_sample_guided(self, obs, g, rng),
        }
    }
    fn name(&self) -> &'static str {
        "ddpm"
    }
}

/// Flow-matching twin (a_t = (1 - t) a_0 + t a_1, t = 1 noise). The network predicts the clean
/// chunk and the velocity is derived from it (v = (a_t - x0_hat) / t), the x0-parameterisation of
/// the same flow.
pub struct FlowPolicy {
    pub cfg: PolicyConfig,
    mlp: Mlp,
    pub train_loss: f32,
}

impl FlowPolicy {
    pub fn train(cfg: &PolicyConfig, tc: &PolicyTrainConfig, demos: &[Demo]) -> Result<Self> {
        let (mlp, train_loss) = train_mlp(cfg, tc, demos, &Objective::Flow)?;
        Ok(FlowPolicy { cfg: cfg.clone(), mlp, train_loss })
    }
    /// Writes `<dir>/flow.safetensors` and `<dir>/flow.json`.
    pub fn save(&self, dir: &Path) -> Result<()> {
        std::fs::create_dir_all(dir)?;
        std::fs::write(dir.join("flow.json"), serde_json::to_vec_pretty(&self.cfg)?)?;
        self.mlp.save(&dir.join("flow.safetensors"))
    }
    pub fn load(dir: &Path) -> Result<Self> {
        let cfg: PolicyConfig = serde_json::from_slice(&std::fs::read(dir.join("flow.json"))?)?;
        let mut mlp = Mlp::new(&cfg, &mut ChaCha8Rng::seed_from_u64(0))?;
        mlp.load(&dir.join("flow.safetensors"))?;
        Ok(FlowPolicy { cfg, mlp, train_loss: f32::NAN })
    }
}

impl VelocityField for FlowPolicy {
    fn obs_dim(&self) -> usize {
        self.cfg.obs_dim()
    }
    fn act_dim(&self) -> usize {
        self.cfg.act_dim()
    }
    fn velocity(&self, obs: &[f32], a_t: &[f32], t: f32) -> steer::Result<Vec<f32>> {
        let x0 = run_mlp(&self.mlp, &self.cfg, obs, a_t, t * 1000.0)?;
        // the network predicts the clean chunk; v = (a_t - x0_hat) / t (t >= 1 / num_steps here)
        let t = t.max(1e-3);
        Ok(a_t.iter().zip(&x0).map(|(a, x)| (a - x) / t).collect())
    }
    fn num_steps(&self) -> usize {
        self.cfg.flow_steps
    }
    fn clip_sample(&self) -> Option<f32> {
        Some(1.0)
    }
    fn action_affine(&self) -> Option<ActionAffine> {
        Some(self.cfg.action_normalizer())
    }
}

impl ChunkPolicy for FlowPolicy {
    fn config(&self) -> &PolicyConfig {
        &self.cfg
    }
    fn sample_chunks(
        &self,
        obs: &[f32],
        guidance: Option<&Guidance>,
        rng: &mut ChaCha8Rng,
    ) -> steer::Result<Vec<f32>> {
        match guidance {
            None => steer::flow_sample(self, obs, rng),
            Some(g) => steer::flow_sample_guided(self, obs, g, rng),
        }
    }
    fn name(&self) -> &'static str {
        "flow"
    }
}
