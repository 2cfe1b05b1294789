//! Host-side optimiser pieces shared by both backends: AdamW (PyTorch semantics), global-norm
//! gradient clipping, and the linear learning-rate schedule.

use serde::{Deserialize, Serialize};

/// AdamW hyper-parameters.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct AdamWConfig {
    pub lr: f64,
    pub weight_decay: f64,
    pub beta1: f64,
    pub beta2: f64,
    pub eps: f64,
}

impl Default for AdamWConfig {
    fn default() -> Self {
        AdamWConfig { lr: 1e-3, weight_decay: 1e-2, beta1: 0.9, beta2: 0.999, eps: 1e-8 }
    }
}

/// AdamW state over a list of flat parameter tensors (decoupled weight decay on every tensor,
/// as `torch.optim.AdamW(model.parameters())`).
#[derive(Clone, Debug)]
pub struct AdamW {
    pub cfg: AdamWConfig,
    m: Vec<Vec<f32>>,
    v: Vec<Vec<f32>>,
    t: u64,
}

impl AdamW {
    pub fn new(cfg: AdamWConfig, sizes: impl IntoIterator<Item = usize>) -> Self {
        let (m, v): (Vec<_>, Vec<_>) = sizes.into_iter().map(|n| (vec![0.0; n], vec![0.0; n])).unzip();
        AdamW { cfg, m, v, t: 0 }
    }

    /// Steps taken so far.
    pub fn steps(&self) -> u64 {
        self.t
    }

    /// One update with learning rate `lr` (the schedule is applied by the caller).
    pub fn step(&mut self, params: &mut [Vec<f32>], grads: &[Vec<f32>], lr: f64) {
        self.t += 1;
        let c = &self.cfg;
        let bc1 = 1.0 - c.beta1.powi(self.t as i32);
        let bc2 = 1.0 - c.beta2.powi(self.t as i32);
        let step_size = (lr / bc1) as f32;
        let bc2_sqrt = bc2.sqrt() as f32;
        let decay = (1.0 - lr * c.weight_decay) as f32;
        let (b1, b2) = (c.beta1 as f32, c.beta2 as f32);
        let eps = c.eps as f32;
        for (((p, g), m), v) in params.iter_mut().zip(grads).zip(&mut self.m).zip(&mut self.v) {
            for (((p, g), m), v) in p.iter_mut().zip(g).zip(m.iter_mut()).zip(v.iter_mut()) {
                *p *= decay;
                *m = b1 * *m + (1.0 - b1) * g;
                *v = b2 * *v + (1.0 - b2) * g * g;
                let denom = v.sqrt() / bc2_sqrt + eps;
                *p -= step_size * *m / denom;
            }
        }
    }
}

/// Global L2 norm of all gradients.
pub fn global_norm(grads: &[Vec<f32>]) -> f64 {
    grads.iter().flat_map(|g| g.iter()).map(|x| (*x as f64) * (*x as f64)).sum::<f64>().sqrt()
}

/// Clip gradients to global norm `max_norm` in place (PyTorch `clip_grad_norm_`:
/// scale by `max_norm / (norm + 1e-6)` when that is < 1). Returns the norm before clipping.
pub fn clip_grad_norm(grads: &mut [Vec<f32>], max_norm: f64) -> f64 {
    let norm = global_norm(grads);
    let coef = max_norm / (norm + 1e-6);
    if coef < 1.0 {
        let c = coef as f32;
        grads.iter_mut().flat_map(|g| g.iter_mut()).for_each(|x| *x *= c);
    }
    norm
}

/// Linear LR factor from `start` to `end` over `total` steps (PyTorch `LinearLR` stepped once per
/// optimiser step): `start + (end - start) * min(step, total) / total`.
pub fn linear_factor(step: u64, total: u64, start: f64, end: f64) -> f64 {
    if total == 0 {
        return start;
    }
    start + (end - start) * (step.min(total) as f64 / total as f64)
}
