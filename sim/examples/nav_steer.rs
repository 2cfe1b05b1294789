//! Quick end-to-end check of the steering plumbing on the navigation task, with a HAND-MADE scorer
//! (no training: it prefers chunks that head for the wide gap). Not a verifier trainer.
//! `cargo run -p sim --example nav_steer -- [episodes]`
#![allow(clippy::unwrap_used, reason = "examples stay short: a failed unwrap ends the example")]
use sim::rollout::summary;
use sim::*;
use steer::{Result as SResult, Scorer};

/// log C = -((y_end - wide_y)^2) / (2 s^2) where y_end = current y + sum of chunk dy.
struct WideGapScorer {
    wide_y: f32,
    s: f32,
}
impl Scorer for WideGapScorer {
    fn obs_dim(&self) -> usize {
        4
    }
    fn act_dim(&self) -> usize {
        16
    }
    /// It reasons in raw velocities (it sums the chunk's dy).
    fn takes_policy_space(&self) -> bool {
        false
    }
    fn score_batch(&self, obs: &[f32], t: &[u32], c: &[f32], n: usize) -> SResult<Vec<f32>> {
        Ok((0..t.len() * n)
            .map(|i| {
                let y = obs[(i / n) * 4 + 3] + (0..8).map(|h| c[i * 16 + 2 * h + 1]).sum::<f32>();
                (-(y - self.wide_y).powi(2) / (2.0 * self.s * self.s)).exp()
            })
            .collect())
    }
    fn grad_batch(&self, obs: &[f32], t: &[u32], c: &[f32]) -> SResult<Vec<f32>> {
        let mut g = vec![0f32; c.len()];
        for r in 0..t.len() {
            let y = obs[r * 4 + 3] + (0..8).map(|h| c[r * 16 + 2 * h + 1]).sum::<f32>();
            for h in 0..8 {
                g[r * 16 + 2 * h + 1] = -(y - self.wide_y) / (self.s * self.s);
            }
        }
        Ok(g)
    }
}

fn main() -> anyhow::Result<()> {
    let n: usize = std::env::args().nth(1).map(|s| s.parse().unwrap()).unwrap_or(500);
    let env = EnvConfig::default();
    let demos = expert_demos(&env, 100, 0);
    let pc = PolicyConfig::default();
    let tc = PolicyTrainConfig::default();
    let ddpm = DiffusionPolicy::train(&pc, &tc, &demos)?;
    let flow = FlowPolicy::train(&pc, &tc, &demos)?;
    let sc = WideGapScorer { wide_y: env.wide_gap.0, s: 0.1 };
    let t = std::time::Instant::now();
    for (name, p) in [("ddpm", &ddpm as &dyn ChunkPolicy), ("flow", &flow as &dyn ChunkPolicy)] {
        let base = rollout(p, &env, n, ChunkChoice::None, 7)?;
        println!("{}", summary(&format!("{name} base"), &base));
        let bon = rollout(p, &env, n, ChunkChoice::BestOfN { scorer: &sc, n: 30 }, 7)?;
        println!("{}", summary(&format!("{name} best-of-30 (hand scorer)"), &bon));
        for lambda in [0.02, 0.1] {
            let g = rollout(p, &env, n, ChunkChoice::Guided { scorer: &sc, lambda }, 7)?;
            println!("{}", summary(&format!("{name} guided lambda={lambda} (hand scorer)"), &g));
        }
        let (k1, n1, _) = success_rate(&bon);
        let (k0, n0, _) = success_rate(&base);
        let (lo, hi) = stats::newcombe_diff(k1, n1, k0, n0);
        println!(
            "  BoN - base: {:+.1} pp, 95% CI [{:+.1}, {:+.1}]",
            100.0 * (k1 as f64 / n1 as f64 - k0 as f64 / n0 as f64),
            100.0 * lo,
            100.0 * hi
        );
        if name == "ddpm" {
            sim::plot::plot_panels(
                std::path::Path::new("/tmp/sim_out/steer.png"),
                &env,
                &[
                    sim::plot::Panel::from_episodes("base", &base, 100),
                    sim::plot::Panel::from_episodes("bon", &bon, 100),
                ],
                400,
            )?;
        }
    }
    println!("rollouts took {:.1}s", t.elapsed().as_secs_f32());
    Ok(())
}
