//! Steering strategies: best-of-N (Algorithm 1), classifier guidance for DDPM (Algorithm 2) and
//! guidance for flow policies (flow analogue of Algorithm 2, applied from the second Euler step
//! on). All randomness comes from the caller's RNG; guided and unguided samplers draw exactly the
//! same random numbers in the same order, so lambda = 0 reproduces the unguided sample.
use crate::error::{Result, SteerError};
use crate::policy::{ActionAffine, NoisePredictor, VelocityField};
use crate::Scorer;
use rand::Rng;
use rand_distr::StandardNormal;

/// What guidance needs besides the policy: the scorer, its observation rows (`B * scorer.obs_dim`,
/// which may differ from the policy's conditioning), the episode step per row and the strength.
#[derive(Clone, Copy)]
pub struct Guidance<'a> {
    pub scorer: &'a dyn Scorer,
    pub obs: &'a [f32],
    pub t: &'a [u32],
    pub lambda: f32,
}

fn randn<R: Rng + ?Sized>(rng: &mut R, n: usize) -> Vec<f32> {
    (0..n).map(|_| rng.sample::<f32, _>(StandardNormal)).collect()
}

fn batch_of(obs: &[f32], od: usize) -> Result<usize> {
    if od == 0 || !obs.len().is_multiple_of(od) {
        return Err(SteerError::Input(format!("obs length {} is not a multiple of obs_dim {od}", obs.len())));
    }
    Ok(obs.len() / od)
}

fn check_guidance(g: &Guidance, b: usize, ad: usize) -> Result<()> {
    if g.scorer.act_dim() != ad {
        return Err(SteerError::Input(format!(
            "scorer act_dim {} != policy act_dim {ad}",
            g.scorer.act_dim()
        )));
    }
    if g.t.len() != b || g.obs.len() != b * g.scorer.obs_dim() {
        return Err(SteerError::Input(format!(
            "guidance needs {b} step indices and {b} * {} obs values, got {} and {}",
            g.scorer.obs_dim(),
            g.t.len(),
            g.obs.len()
        )));
    }
    Ok(())
}

/// `x0 += lambda * grad`, where `grad` is d log C / d x0 (classifier) or d Q / d x0. A scorer
/// in the policy's sample space takes x̂0 as it is (the paper's Algorithm 2); a scorer of raw
/// actions gets `raw(x0)` and its gradient is mapped back by the chain rule through the affine.
fn guide_x0(g: &Guidance, aff: &Option<ActionAffine>, x0: &mut [f32]) -> Result<()> {
    let grad = match aff {
        Some(a) if !g.scorer.takes_policy_space() => {
            let mut raw = x0.to_vec();
            a.apply(&mut raw)?;
            let mut gr = g.scorer.grad_batch(g.obs, g.t, &raw)?;
            let d = a.scale.len();
            for (i, v) in gr.iter_mut().enumerate() {
                *v *= a.scale[i % d];
            }
            gr
        }
        _ => g.scorer.grad_batch(g.obs, g.t, x0)?,
    };
    if grad.len() != x0.len() {
        return Err(SteerError::Model(format!(
            "scorer returned {} gradient values, expected {}",
            grad.len(),
            x0.len()
        )));
    }
    for (x, gr) in x0.iter_mut().zip(grad) {
        *x += g.lambda * gr;
    }
    Ok(())
}

fn clip(x: &mut [f32], c: Option<f32>) {
    if let Some(c) = c {
        for v in x {
            *v = v.clamp(-c, c);
        }
    }
}

/// Unguided DDPM sampling: one chunk per observation row (`B = obs.len() / obs_dim`). Returns
/// `B * act_dim` raw chunks.
pub fn ddpm_sample<P: NoisePredictor + ?Sized, R: Rng + ?Sized>(
    policy: &P,
    obs: &[f32],
    rng: &mut R,
) -> Result<Vec<f32>> {
    ddpm_impl(policy, obs, None, rng)
}

/// DDPM with verifier classifier guidance (Algorithm 2).
pub fn ddpm_sample_guided<P: NoisePredictor + ?Sized, R: Rng + ?Sized>(
    policy: &P,
    obs: &[f32],
    guidance: &Guidance,
    rng: &mut R,
) -> Result<Vec<f32>> {
    ddpm_impl(policy, obs, Some(guidance), rng)
}

fn ddpm_impl<P: NoisePredictor + ?Sized, R: Rng + ?Sized>(
    policy: &P,
    obs: &[f32],
    guidance: Option<&Guidance>,
    rng: &mut R,
) -> Result<Vec<f32>> {
    let b = batch_of(obs, policy.obs_dim())?;
    let ad = policy.act_dim();
    if let Some(g) = guidance {
        check_guidance(g, b, ad)?;
    }
    let sched = policy.schedule();
    let aff = policy.action_affine();
    if let Some(a) = &aff {
        a.check(ad)?;
    }
    let clip_c = policy.clip_sample();
    let n = b * ad;
    let mut x = randn(rng, n); // a_K ~ N(0, I)
    for k in (1..=sched.num_steps()).rev() {
        let z = if k > 1 { randn(rng, n) } else { vec![0.0; n] };
        let eps = policy.predict_noise(obs, &x, k - 1)?;
        if eps.len() != n {
            return Err(SteerError::Model(format!(
                "noise predictor returned {} values, expected {n}",
                eps.len()
            )));
        }
        let ab = sched.alpha_bar(k);
        let (sa, s1a) = (ab.sqrt() as f32, (1.0 - ab).sqrt() as f32);
        // Tweedie: x0_hat = (a_k - sqrt(1 - ab_k) eps) / sqrt(ab_k)
        let mut x0: Vec<f32> = x.iter().zip(&eps).map(|(a, e)| (a - s1a * e) / sa).collect();
        // diffusers' clip_sample acts on the model's x̂0; Algorithm 2 then adds the gradient
        // step and uses the perturbed x̂0 as it is (no second clip).
        clip(&mut x0, clip_c);
        if let Some(g) = guidance {
            guide_x0(g, &aff, &mut x0)?;
        }
        // Standard DDPM posterior mean
        //   mu_k = sqrt(ab_{k-1}) beta_k / (1 - ab_k) * x0_hat + sqrt(alpha_k) (1 - ab_{k-1}) / (1 - ab_k) * a_k.
        // NOTE: Algorithm 2's line in the paper writes the two coefficients the other way round
        // (sqrt(ab_{k-1}) beta_k / (1 - ab_k) on a_k); that is a typo, we implement the standard one.
        let (c0, ck, var) = sched.posterior(k);
        let (c0, ck) = (c0 as f32, ck as f32);
        let sigma = var.max(1e-20).sqrt() as f32;
        for i in 0..n {
            x[i] = c0 * x0[i] + ck * x[i] + sigma * z[i];
        }
    }
    if let Some(a) = &aff {
        a.apply(&mut x)?;
    }
    Ok(x)
}

/// Unguided flow sampling: Euler from t = 1 (noise) to t = 0 (data).
pub fn flow_sample<P: VelocityField + ?Sized, R: Rng + ?Sized>(
    policy: &P,
    obs: &[f32],
    rng: &mut R,
) -> Result<Vec<f32>> {
    flow_impl(policy, obs, None, rng)
}

/// Flow sampling with verifier guidance: at every Euler step after the first,
/// x0_hat = a_t - t v, x0_hat' = x0_hat + lambda grad, v' = (a_t - x0_hat') / t, a <- a - dt v'.
pub fn flow_sample_guided<P: VelocityField + ?Sized, R: Rng + ?Sized>(
    policy: &P,
    obs: &[f32],
    guidance: &Guidance,
    rng: &mut R,
) -> Result<Vec<f32>> {
    flow_impl(policy, obs, Some(guidance), rng)
}

fn flow_impl<P: VelocityField + ?Sized, R: Rng + ?Sized>(
    policy: &P,
    obs: &[f32],
    guidance: Option<&Guidance>,
    rng: &mut R,
) -> Result<Vec<f32>> {
    let b = batch_of(obs, policy.obs_dim())?;
    let ad = policy.act_dim();
    if let Some(g) = guidance {
        check_guidance(g, b, ad)?;
    }
    let aff = policy.action_affine();
    if let Some(a) = &aff {
        a.check(ad)?;
    }
    let n = b * ad;
    let steps = policy.num_steps().max(1);
    let dt = 1.0 / steps as f32;
    let mut x = randn(rng, n); // a_1 ~ N(0, I)
    for i in 0..steps {
        let t = 1.0 - i as f32 * dt;
        let mut v = policy.velocity(obs, &x, t)?;
        if v.len() != n {
            return Err(SteerError::Model(format!(
                "velocity field returned {} values, expected {n}",
                v.len()
            )));
        }
        if let (Some(g), true) = (guidance, i >= 1) {
            let x0: Vec<f32> = x.iter().zip(&v).map(|(a, v)| a - t * v).collect();
            let mut x0p = x0.clone();
            guide_x0(g, &aff, &mut x0p)?;
            // v' = (a_t - x0') / t = v - (x0' - x0) / t; written this way so that lambda = 0
            // reproduces the unguided step bit for bit.
            for j in 0..n {
                v[j] -= (x0p[j] - x0[j]) / t;
            }
        }
        for j in 0..n {
            x[j] -= dt * v[j];
        }
    }
    clip(&mut x, policy.clip_sample());
    if let Some(a) = &aff {
        a.apply(&mut x)?;
    }
    Ok(x)
}

/// Index of the largest score (first one on ties; NaN counts as -inf).
pub fn select_best(scores: &[f32]) -> usize {
    verifier::ensemble::argmax(scores)
}

/// Result of best-of-N for B groups.
#[derive(Debug, Clone)]
pub struct BestOfN {
    /// chosen candidate index per group
    pub index: Vec<usize>,
    /// all `B * n` scores (an ensemble's: the members' mean)
    pub scores: Vec<f32>,
    /// the chosen chunks, `B * act_dim`
    pub chunks: Vec<f32>,
    /// per group: an ensemble's members disagreed, so the group's first candidate (the policy's
    /// own sample) was kept ([`verifier::ensemble::pick_group`]); always false for one network
    pub fell_back: Vec<bool>,
}

impl BestOfN {
    /// The share of groups that fell back to their first candidate.
    pub fn fallback_rate(&self) -> f64 {
        self.fell_back.iter().filter(|&&f| f).count() as f64 / self.fell_back.len().max(1) as f64
    }
}

/// Best-of-N (Algorithm 1): score `n` candidates per group (`candidates` is `B * n * act_dim`,
/// group-major, in the space the scorer takes) and keep the argmax of each group.
pub fn best_of_n(
    scorer: &dyn Scorer,
    obs: &[f32],
    t: &[u32],
    candidates: &[f32],
    n: usize,
) -> Result<BestOfN> {
    check_n(n)?;
    crate::warn_if_flagged(scorer);
    let picks = scorer.pick_batch(obs, t, candidates, n)?;
    pick(scorer.act_dim(), picks, t.len(), candidates, n)
}

/// Best-of-N on raw candidates as the samplers return them (e.g. from [`ddpm_sample`] with each
/// observation repeated `n` times): a scorer in the policy's space scores them mapped back
/// through the policy's `affine`; the chosen chunks are returned raw.
pub fn best_of_n_raw(
    scorer: &dyn Scorer,
    affine: Option<&ActionAffine>,
    obs: &[f32],
    t: &[u32],
    raw_candidates: &[f32],
    n: usize,
) -> Result<BestOfN> {
    check_n(n)?;
    crate::warn_if_flagged(scorer);
    let picks = match affine {
        Some(a) if scorer.takes_policy_space() => {
            let mut x = raw_candidates.to_vec();
            a.invert(&mut x)?;
            scorer.pick_batch(obs, t, &x, n)?
        }
        _ => scorer.pick_batch(obs, t, raw_candidates, n)?,
    };
    pick(scorer.act_dim(), picks, t.len(), raw_candidates, n)
}

fn check_n(n: usize) -> Result<()> {
    if n == 0 {
        return Err(SteerError::Input("best-of-N needs at least one candidate per group (n = 0)".into()));
    }
    Ok(())
}

/// `n >= 1` is checked by the callers, before scoring.
fn pick(ad: usize, picks: crate::Picks, b: usize, candidates: &[f32], n: usize) -> Result<BestOfN> {
    let crate::Picks { index, scores, fell_back, .. } = picks;
    if scores.len() != b * n || index.len() != b || fell_back.len() != b || candidates.len() != b * n * ad {
        return Err(SteerError::Input(format!(
            "{} scores and {} candidate values for {b} groups of {n} chunks of {ad}",
            scores.len(),
            candidates.len()
        )));
    }
    let mut chunks = Vec::with_capacity(b * ad);
    for (g, &i) in index.iter().enumerate() {
        if i >= n {
            return Err(SteerError::Model(format!("the scorer picked candidate {i} of {n}")));
        }
        chunks.extend_from_slice(&candidates[(g * n + i) * ad..(g * n + i + 1) * ad]);
    }
    Ok(BestOfN { index, scores, chunks, fell_back })
}
