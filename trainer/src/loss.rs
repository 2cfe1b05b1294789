//! Losses: numerically stable BCE with logits, contrastive hinge on penultimate features, MSE.
//!
//! Each loss exists as a candle graph (used with autograd) and as a host-side function returning
//! the value and the gradient with respect to the model outputs (used by the fused fast path and
//! for validation); the two are tested against each other.

use anyhow::Result;
use candle_core::{Device, Tensor, D};
use serde::{Deserialize, Serialize};

/// Loss hyper-parameters.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct LossConfig {
    /// `lambda_c`, weight of the contrastive hinge (classifier only).
    pub contrastive_weight: f64,
    /// Hinge margin `epsilon`.
    pub contrastive_margin: f64,
    /// Added under the square root of the squared distance (avoids a NaN gradient at 0).
    pub contrastive_eps: f64,
}

impl Default for LossConfig {
    fn default() -> Self {
        LossConfig { contrastive_weight: 0.1, contrastive_margin: 1.0, contrastive_eps: 1e-9 }
    }
}

/// Stable BCE with logits per element: `max(x,0) - x*y + log(1 + exp(-|x|))`.
pub fn bce_with_logits_scalar(x: f32, y: f32) -> f32 {
    let x = x as f64;
    (x.max(0.0) - x * y as f64 + (-x.abs()).exp().ln_1p()) as f32
}

pub use verifier::sigmoid;

/// Mean stable BCE with logits (candle graph). `logits`, `y`: `[B]`.
pub fn bce_with_logits(logits: &Tensor, y: &Tensor) -> Result<Tensor> {
    let l = ((logits.relu()? - logits.mul(y)?)? + (logits.abs()?.neg()?.exp()? + 1.0)?.log()?)?;
    Ok(l.mean_all()?)
}

/// Mean squared error (candle graph).
pub fn mse(pred: &Tensor, target: &Tensor) -> Result<Tensor> {
    Ok(pred.sub(target)?.sqr()?.mean_all()?)
}

/// Contrastive pairs within a batch: each sample of a successful episode is paired with one of a
/// failed episode (cyclically, in batch order) and vice versa. Returns `(first, second)` index
/// lists (`|P| + |N|` pairs), empty when the batch has only one class.
pub fn contrastive_pairs(labels: &[f32]) -> (Vec<u32>, Vec<u32>) {
    let pos: Vec<u32> = (0..labels.len() as u32).filter(|&i| labels[i as usize] > 0.5).collect();
    let neg: Vec<u32> = (0..labels.len() as u32).filter(|&i| labels[i as usize] <= 0.5).collect();
    if pos.is_empty() || neg.is_empty() {
        return (vec![], vec![]);
    }
    let mut a = Vec::with_capacity(labels.len());
    let mut b = Vec::with_capacity(labels.len());
    for (k, &p) in pos.iter().enumerate() {
        a.push(p);
        b.push(neg[k % neg.len()]);
    }
    for (k, &n) in neg.iter().enumerate() {
        a.push(n);
        b.push(pos[k % pos.len()]);
    }
    (a, b)
}

/// Contrastive hinge (candle graph): mean over pairs of `max(0, margin - ||z_a - z_b||)^2` with
/// `||d|| = sqrt(sum d^2 + eps)`. `None` when there are no pairs.
pub fn contrastive_hinge(z: &Tensor, labels: &[f32], cfg: &LossConfig) -> Result<Option<Tensor>> {
    let (a, b) = contrastive_pairs(labels);
    if a.is_empty() {
        return Ok(None);
    }
    let dev = z.device();
    let ia = Tensor::from_slice(&a, a.len(), dev)?;
    let ib = Tensor::from_slice(&b, b.len(), dev)?;
    let d = (z.index_select(&ia, 0)? - z.index_select(&ib, 0)?)?;
    let dist = (d.sqr()?.sum(D::Minus1)? + cfg.contrastive_eps)?.sqrt()?;
    let h = dist.affine(-1.0, cfg.contrastive_margin)?.relu()?.sqr()?;
    Ok(Some(h.mean_all()?))
}

/// The full training objective as a candle graph: classifier `BCE + lambda_c * hinge`, Q `MSE`.
pub fn objective(
    kind: crate::model::Kind,
    y: &Tensor,
    z: &Tensor,
    target: &[f32],
    cfg: &LossConfig,
) -> Result<Tensor> {
    let t = Tensor::from_slice(target, target.len(), &Device::Cpu)?;
    Ok(match kind {
        crate::model::Kind::Q => mse(y, &t)?,
        crate::model::Kind::Classifier => {
            let mut l = bce_with_logits(y, &t)?;
            if cfg.contrastive_weight != 0.0 {
                if let Some(h) = contrastive_hinge(z, target, cfg)? {
                    l = (l + (h * cfg.contrastive_weight)?)?;
                }
            }
            l
        }
    })
}

/// Host-side objective: value, and (when `dy`/`dz` are given) the gradients with respect to the
/// head output `y [B]` and the penultimate features `z [B, dz]` (row-major). Gradients are
/// overwritten (dz zeroed first). Accumulates in f64.
pub fn objective_host(
    kind: crate::model::Kind,
    y: &[f32],
    z: &[f32],
    zdim: usize,
    target: &[f32],
    cfg: &LossConfig,
    grads: Option<(&mut [f32], &mut [f32])>,
) -> f64 {
    let n = y.len();
    let inv_n = 1.0 / n.max(1) as f64;
    let mut loss = 0f64;
    let (mut dy, mut dz) = match grads {
        Some((a, b)) => (Some(a), Some(b)),
        None => (None, None),
    };
    if let Some(dz) = dz.as_deref_mut() {
        dz.iter_mut().for_each(|v| *v = 0.0);
    }
    match kind {
        crate::model::Kind::Q => {
            for i in 0..n {
                let d = y[i] as f64 - target[i] as f64;
                loss += d * d;
                if let Some(dy) = dy.as_deref_mut() {
                    dy[i] = (2.0 * d * inv_n) as f32;
                }
            }
            loss * inv_n
        }
        crate::model::Kind::Classifier => {
            for i in 0..n {
                loss += bce_with_logits_scalar(y[i], target[i]) as f64;
                if let Some(dy) = dy.as_deref_mut() {
                    dy[i] = ((sigmoid(y[i]) as f64 - target[i] as f64) * inv_n) as f32;
                }
            }
            loss *= inv_n;
            if cfg.contrastive_weight != 0.0 {
                let (a, b) = contrastive_pairs(target);
                if !a.is_empty() {
                    let np = a.len() as f64;
                    let mut h = 0f64;
                    let mut diff = vec![0f64; zdim];
                    for (&i, &j) in a.iter().zip(&b) {
                        let (i, j) = (i as usize, j as usize);
                        let mut s = 0f64;
                        for k in 0..zdim {
                            let d = z[i * zdim + k] as f64 - z[j * zdim + k] as f64;
                            diff[k] = d;
                            s += d * d;
                        }
                        let dist = (s + cfg.contrastive_eps).sqrt();
                        let m = (cfg.contrastive_margin - dist).max(0.0);
                        h += m * m;
                        if let Some(dz) = dz.as_deref_mut() {
                            if m > 0.0 {
                                // d/d z_i of w * m^2 / np = -2 w m / np * diff / dist
                                let c = -2.0 * cfg.contrastive_weight * m / np / dist;
                                for k in 0..zdim {
                                    let g = (c * diff[k]) as f32;
                                    dz[i * zdim + k] += g;
                                    dz[j * zdim + k] -= g;
                                }
                            }
                        }
                    }
                    loss += cfg.contrastive_weight * h / np;
                }
            }
            loss
        }
    }
}
