//! DDPM noise schedule, indexed as in the paper: k = 1..=K, with alpha_bar(0) = 1.
//! (diffusers' 0-based timestep index is k - 1; that index is what a [`crate::NoisePredictor`]
//! receives.) The constructors refuse an empty schedule or betas outside (0, 1), so every
//! schedule that exists has K >= 1 valid steps.

use crate::error::{Result, SteerError};

#[derive(Debug, Clone)]
pub struct DdpmSchedule {
    betas: Vec<f64>,
    alphas_cumprod: Vec<f64>,
}

impl DdpmSchedule {
    /// diffusers' `squaredcos_cap_v2` (`betas_for_alpha_bar`, cosine, max_beta = 0.999):
    /// alpha_bar(s) = cos^2((s + 0.008) / 1.008 * pi / 2),
    /// beta_i = min(1 - alpha_bar((i+1)/K) / alpha_bar(i/K), 0.999) for i = 0..K-1.
    pub fn squaredcos_cap_v2(k: usize) -> Result<Self> {
        let ab = |s: f64| ((s + 0.008) / 1.008 * std::f64::consts::FRAC_PI_2).cos().powi(2);
        let betas = (0..k)
            .map(|i| {
                let t1 = i as f64 / k as f64;
                let t2 = (i + 1) as f64 / k as f64;
                (1.0 - ab(t2) / ab(t1)).min(0.999)
            })
            .collect();
        Self::from_betas(betas)
    }

    /// diffusers' `linear` schedule.
    pub fn linear(k: usize, beta_start: f64, beta_end: f64) -> Result<Self> {
        let betas =
            (0..k).map(|i| beta_start + (beta_end - beta_start) * i as f64 / (k.max(2) - 1) as f64).collect();
        Self::from_betas(betas)
    }

    pub fn from_betas(betas: Vec<f64>) -> Result<Self> {
        if betas.is_empty() {
            return Err(SteerError::Input("a DDPM schedule needs at least one step".into()));
        }
        if let Some((i, b)) = betas.iter().enumerate().find(|(_, b)| !(**b > 0.0 && **b < 1.0)) {
            return Err(SteerError::Input(format!("beta {b} at step {} is not in (0, 1)", i + 1)));
        }
        let mut acc = 1.0;
        let alphas_cumprod = betas
            .iter()
            .map(|b| {
                acc *= 1.0 - b;
                acc
            })
            .collect();
        Ok(DdpmSchedule { betas, alphas_cumprod })
    }

    /// K, the number of diffusion steps.
    pub fn num_steps(&self) -> usize {
        self.betas.len()
    }
    /// beta_k, k in 1..=K.
    pub fn beta(&self, k: usize) -> f64 {
        self.betas[k - 1]
    }
    /// alpha_k = 1 - beta_k.
    pub fn alpha(&self, k: usize) -> f64 {
        1.0 - self.betas[k - 1]
    }
    /// alpha_bar_k = prod_{s<=k} alpha_s, with alpha_bar_0 = 1.
    pub fn alpha_bar(&self, k: usize) -> f64 {
        if k == 0 {
            1.0
        } else {
            self.alphas_cumprod[k - 1]
        }
    }
    /// Standard DDPM posterior q(a_{k-1} | a_k, x0) mean coefficients (on x0, on a_k) and variance
    /// beta_tilde_k = (1 - alpha_bar_{k-1}) / (1 - alpha_bar_k) * beta_k.
    pub fn posterior(&self, k: usize) -> (f64, f64, f64) {
        let ab = self.alpha_bar(k);
        let abp = self.alpha_bar(k - 1);
        let b = self.beta(k);
        let c_x0 = abp.sqrt() * b / (1.0 - ab);
        let c_xk = (1.0 - b).sqrt() * (1.0 - abp) / (1.0 - ab);
        let var = (1.0 - abp) / (1.0 - ab) * b;
        (c_x0, c_xk, var)
    }
}
