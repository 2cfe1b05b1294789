//! Train the base DDPM (and flow) policy on expert demos and report its success rate under test
//! noise; writes a trajectory plot. `cargo run -p sim --example nav_base -- [episodes] [train_steps] [out_dir]`
#![allow(clippy::unwrap_used, reason = "examples stay short: a failed unwrap ends the example")]
use sim::plot::{plot_panels, Panel};
use sim::rollout::summary;
use sim::*;
use std::time::Instant;

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().collect();
    let n: usize = args.get(1).map(|s| s.parse().unwrap()).unwrap_or(500);
    let steps: usize = args.get(2).map(|s| s.parse().unwrap()).unwrap_or(PolicyTrainConfig::default().steps);
    let out = std::path::PathBuf::from(args.get(3).cloned().unwrap_or("/tmp/sim_out".into()));
    std::fs::create_dir_all(&out)?;
    let mut env = EnvConfig::default();
    let demos = expert_demos(&env, 100, 0);
    let mut pc = PolicyConfig::default();
    let ev = |k: &str| std::env::var(k).ok().map(|v| v.parse::<usize>().unwrap());
    if let Some(v) = ev("H") {
        pc.horizon = v;
    }
    if let Some(v) = ev("EXEC") {
        pc.n_exec = v;
    }
    if let Some(v) = ev("HIDDEN") {
        pc.hidden = v;
    }
    if let Some(v) = ev("DEPTH") {
        pc.depth = v;
    }
    println!("{pc:?}");
    let mut tc = PolicyTrainConfig { steps, ..Default::default() };
    if let Ok(v) = std::env::var("LR") {
        tc.lr = v.parse().unwrap();
    }
    if let Some(v) = ev("BATCH") {
        tc.batch = v;
    }
    if let Some(v) = ev("K") {
        pc.diffusion_steps = v;
    }
    if let Ok(v) = std::env::var("NOISE") {
        env.pos_noise = v.parse().unwrap();
    }
    if let Ok(v) = std::env::var("NARROW") {
        env.narrow_gap.1 = v.parse().unwrap();
    }
    let only_ddpm = std::env::var("ONLY_DDPM").is_ok();
    let t0 = Instant::now();
    let ddpm = DiffusionPolicy::train(&pc, &tc, &demos)?;
    println!("ddpm trained in {:.1}s, loss {:.4}", t0.elapsed().as_secs_f32(), ddpm.train_loss);
    ddpm.save(&out)?;
    let t0 = Instant::now();
    let base = rollout(&ddpm, &env, n, ChunkChoice::None, 1)?;
    println!("{}  ({:.1}s)", summary("ddpm base", &base), t0.elapsed().as_secs_f32());
    if only_ddpm {
        let noiseless =
            rollout(&ddpm, &EnvConfig { pos_noise: 0.0, ..env.clone() }, n, ChunkChoice::None, 1)?;
        println!("{}", summary("ddpm base, no noise", &noiseless));
        plot_panels(
            &out.join("base.png"),
            &env,
            &[Panel::from_demos("demos", &demos, 100), Panel::from_episodes("ddpm", &base, 100)],
            400,
        )?;
        return Ok(());
    }
    let t0 = Instant::now();
    let flow = FlowPolicy::train(&pc, &tc, &demos)?;
    println!("flow trained in {:.1}s, loss {:.4}", t0.elapsed().as_secs_f32(), flow.train_loss);
    flow.save(&out)?;
    let t0 = Instant::now();
    let fbase = rollout(&flow, &env, n, ChunkChoice::None, 1)?;
    println!("{}  ({:.1}s)", summary("flow base", &fbase), t0.elapsed().as_secs_f32());
    let noiseless = rollout(&ddpm, &EnvConfig { pos_noise: 0.0, ..env.clone() }, n, ChunkChoice::None, 1)?;
    println!("{}", summary("ddpm base, no noise", &noiseless));
    plot_panels(
        &out.join("base.png"),
        &env,
        &[
            Panel::from_demos("demos", &demos, 100),
            Panel::from_episodes("ddpm", &base, 100),
            Panel::from_episodes("flow", &fbase, 100),
        ],
        400,
    )?;
    Ok(())
}
