//! Traits a user implements for their own policy model.
use crate::error::{Result, SteerError};
use crate::schedule::DdpmSchedule;

/// Per-dimension affine map from the policy's sample space to raw actions:
/// `raw = x * scale + offset` (e.g. a [-1, 1] normaliser); `scale` and `offset` have one entry
/// per action dimension and repeat over the chunk. A verifier trained in the policy's space (the
/// paper's choice) sees `x` itself; one trained on raw actions sees `raw`, and its gradient is
/// mapped back by the chain rule (`d/dx = scale * d/draw`). The trainer takes the same normaliser
/// (`TrainConfig::action_space`) so it can put stored raw actions into the policy's space.
#[derive(Debug, Clone)]
pub struct ActionAffine {
    pub scale: Vec<f32>,
    pub offset: Vec<f32>,
}

impl ActionAffine {
    /// Checks the map against chunks of `act_dim` values: one finite, non-zero scale and one
    /// finite offset per action dimension, and a chunk made of whole actions.
    pub fn check(&self, act_dim: usize) -> Result<()> {
        let d = self.scale.len();
        if d == 0 || self.offset.len() != d {
            return Err(SteerError::Input(format!(
                "action affine has {} scales and {} offsets: needs one of each per action dimension",
                d,
                self.offset.len()
            )));
        }
        if !act_dim.is_multiple_of(d) {
            return Err(SteerError::Input(format!(
                "chunk of {act_dim} values is not whole actions of {d} dimensions"
            )));
        }
        if self.scale.iter().any(|s| !s.is_finite() || *s == 0.0)
            || self.offset.iter().any(|o| !o.is_finite())
        {
            return Err(SteerError::Input(
                "action affine scales must be finite and non-zero, offsets finite".into(),
            ));
        }
        Ok(())
    }
    /// Sample space to raw actions, in place.
    pub fn apply(&self, x: &mut [f32]) -> Result<()> {
        self.check(x.len())?;
        let d = self.scale.len();
        for (i, v) in x.iter_mut().enumerate() {
            *v = *v * self.scale[i % d] + self.offset[i % d];
        }
        Ok(())
    }
    /// Raw actions to the sample space, in place (the inverse of [`Self::apply`]).
    pub fn invert(&self, raw: &mut [f32]) -> Result<()> {
        self.check(raw.len())?;
        let d = self.scale.len();
        for (i, v) in raw.iter_mut().enumerate() {
            *v = (*v - self.offset[i % d]) / self.scale[i % d];
        }
        Ok(())
    }
}

/// A DDPM noise predictor eps_theta(s, a_k, k), batched.
pub trait NoisePredictor {
    /// Length of one observation row the model is conditioned on.
    fn obs_dim(&self) -> usize;
    /// Length of one flattened action chunk (H * A).
    fn act_dim(&self) -> usize;
    fn schedule(&self) -> &DdpmSchedule;
    /// eps for B rows: `obs` is `B * obs_dim`, `a_k` is `B * act_dim`; `timestep` is diffusers'
    /// 0-based index, i.e. the paper's k - 1 (in 0..K).
    fn predict_noise(&self, obs: &[f32], a_k: &[f32], timestep: usize) -> Result<Vec<f32>>;
    /// diffusers' `clip_sample`: clamp the x0 estimate to [-c, c] at every step.
    fn clip_sample(&self) -> Option<f32> {
        None
    }
    /// Map from sample space to raw actions (identity when `None`).
    fn action_affine(&self) -> Option<ActionAffine> {
        None
    }
}

/// A flow-matching velocity field v(s, a_t, t), batched, with the paper's convention
/// a_t = (1 - t) a_0 + t a_1: t = 1 is noise, t = 0 is data, x0_hat = a_t - t v.
pub trait VelocityField {
    fn obs_dim(&self) -> usize;
    fn act_dim(&self) -> usize;
    /// v for B rows at time `t` in (0, 1].
    fn velocity(&self, obs: &[f32], a_t: &[f32], t: f32) -> Result<Vec<f32>>;
    /// Number of Euler steps from t = 1 to t = 0.
    fn num_steps(&self) -> usize {
        10
    }
    /// Clamp the final sample to [-c, c].
    fn clip_sample(&self) -> Option<f32> {
        None
    }
    fn action_affine(&self) -> Option<ActionAffine> {
        None
    }
}
