//! Steering your own DDPM chunk policy with a ufops verifier, the two ways of the paper:
//! best-of-N (Algorithm 1) and classifier guidance on the Tweedie estimate x̂0 (Algorithm 2).
//!
//! ```sh
//! ufops artifacts download my-policy/ckpt-40k/classifier@latest ./verifier
//! cargo run -p steer --example steer_own_policy -- ./verifier
//! ```
//!
//! The policy here is a stand-in whose samples spread around zero; put your
//! network's forward pass in `predict_noise`. Everything else is what a robot loop does at each
//! re-planning step.
#![allow(clippy::unwrap_used, reason = "examples stay short: a failed unwrap ends the example")]

use rand::SeedableRng;
use steer::{
    best_of_n_raw, ddpm_sample, ddpm_sample_guided, ActionAffine, DdpmSchedule, Guidance, NoisePredictor,
    Scorer, Verifier,
};

/// Your policy: conditioned on `obs_dim` numbers, it samples flattened `H x A` action chunks in
/// its normalised space; `affine` maps them to raw actions (the normaliser it was trained with).
struct MyPolicy {
    schedule: DdpmSchedule,
    obs_dim: usize,
    act_dim: usize,
    affine: ActionAffine,
}

impl NoisePredictor for MyPolicy {
    fn obs_dim(&self) -> usize {
        self.obs_dim
    }
    fn act_dim(&self) -> usize {
        self.act_dim
    }
    fn schedule(&self) -> &DdpmSchedule {
        &self.schedule
    }
    /// eps for a batch of rows (`obs` is `B * obs_dim`, `a_k` is `B * act_dim`). `timestep` is
    /// diffusers' 0-based index: the noise level is `alpha_bar(timestep + 1)`.
    fn predict_noise(&self, _obs: &[f32], a_k: &[f32], timestep: usize) -> steer::Result<Vec<f32>> {
        let ab = self.schedule.alpha_bar(timestep + 1);
        // The eps whose x̂0 is half the noisy chunk (samples spread around zero): a real policy
        // runs its network here.
        let (sa, s1a) = (ab.sqrt() as f32, (1.0 - ab).sqrt().max(1e-6) as f32);
        Ok(a_k.iter().map(|a| a * (1.0 - 0.5 * sa) / s1a).collect())
    }
    fn clip_sample(&self) -> Option<f32> {
        Some(1.0)
    }
    fn action_affine(&self) -> Option<ActionAffine> {
        Some(self.affine.clone())
    }
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let Some(dir) = std::env::args().nth(1) else {
        eprintln!("usage: steer_own_policy ARTIFACT_DIR   (ufops artifacts download ID ARTIFACT_DIR)");
        std::process::exit(2);
    };
    // Loading checks every file's sha256 and the tensors against the config; a verifier trained
    // on encoder features also says which producer's features it needs (`check_producers`).
    let verifier = Verifier::load_dir(&dir)?;
    let (obs_dim, act_dim) = (verifier.obs_dim(), verifier.act_dim());
    println!("verifier {:?}: obs {obs_dim}, chunk {act_dim} values", verifier.kind());

    let policy = MyPolicy {
        schedule: DdpmSchedule::squaredcos_cap_v2(100)?,
        obs_dim,
        act_dim,
        // One scale and offset per action dimension; identity here.
        affine: ActionAffine { scale: vec![1.0], offset: vec![0.0] },
    };
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(0);

    // The robot's current observation: for the verifier, its observation history (T_o stacked
    // rows of the keys it was trained on, `obs_dim` in all); the policy here takes the same.
    let obs = vec![0.1_f32; obs_dim];
    let t = 0_u32; // the step in the episode (the verifier embeds it)

    // Best-of-N: N candidates from the unchanged policy (the observation repeated N times, one
    // batched call), scored by the verifier, the best one executed.
    let n = 16;
    let repeated: Vec<f32> = obs.iter().copied().cycle().take(n * obs_dim).collect();
    let candidates = ddpm_sample(&policy, &repeated, &mut rng)?;
    let affine = policy.action_affine();
    let best = best_of_n_raw(&verifier, affine.as_ref(), &obs, &[t], &candidates, n)?;
    println!(
        "best-of-{n}: candidate {} scored {:.3} (worst {:.3})",
        best.index[0],
        best.scores[best.index[0]],
        best.scores.iter().copied().fold(f32::INFINITY, f32::min)
    );

    // Guidance: one sample, each denoising step nudged along the verifier's gradient on x̂0.
    let guidance = Guidance { scorer: &verifier, obs: &obs, t: &[t], lambda: 1.0 };
    let guided = ddpm_sample_guided(&policy, &obs, &guidance, &mut rng)?;
    println!("guided chunk scored {:.3}", Scorer::score(&verifier, &obs, &guided, t)?[0]);
    Ok(())
}
