//! Expert demonstrations: smooth curves from the start through the centre of one of the two gaps
//! (equal numbers) to the goal, as velocity actions.
use crate::env::{EnvConfig, NavEnv};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

#[derive(Debug, Clone)]
pub struct Demo {
    /// positions p_0..p_T (T + 1 of them)
    pub positions: Vec<[f32; 2]>,
    /// velocities a_0..a_{T-1}, p_{t+1} = p_t + a_t
    pub actions: Vec<[f32; 2]>,
    /// true for the wide gap
    pub wide: bool,
}

fn catmull_rom(p: &[[f32; 2]], samples_per_seg: usize) -> Vec<[f32; 2]> {
    let mut out = Vec::new();
    let n = p.len();
    for i in 0..n - 1 {
        let p0 = p[i.saturating_sub(1)];
        let p1 = p[i];
        let p2 = p[i + 1];
        let p3 = p[(i + 2).min(n - 1)];
        for s in 0..samples_per_seg {
            let t = s as f32 / samples_per_seg as f32;
            let (t2, t3) = (t * t, t * t * t);
            let mut q = [0f32; 2];
            for d in 0..2 {
                q[d] = 0.5
                    * (2.0 * p1[d]
                        + (-p0[d] + p2[d]) * t
                        + (2.0 * p0[d] - 5.0 * p1[d] + 4.0 * p2[d] - p3[d]) * t2
                        + (-p0[d] + 3.0 * p1[d] - 3.0 * p2[d] + p3[d]) * t3);
            }
            out.push(q);
        }
    }
    out.push(p[n - 1]);
    out
}

/// `n` demonstrations (alternating wide / narrow gap), seeded. Each is checked collision-free in
/// the noise-free environment; a rare colliding draw is redrawn.
pub fn expert_demos(cfg: &EnvConfig, n: usize, seed: u64) -> Vec<Demo> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut demos = Vec::with_capacity(n);
    while demos.len() < n {
        let wide = demos.len() % 2 == 0;
        let (gy, gh) = if wide { cfg.wide_gap } else { cfg.narrow_gap };
        let j = cfg.start_jitter;
        let start = [cfg.start[0] + rng.gen_range(-j..=j), cfg.start[1] + rng.gen_range(-j..=j)];
        let y = gy + rng.gen_range(-0.25..0.25) * gh;
        let pre = [cfg.wall_x - rng.gen_range(0.08..0.14), y + rng.gen_range(-0.2..0.2) * gh];
        let post = [cfg.wall_x + rng.gen_range(0.08..0.14), y + rng.gen_range(-0.2..0.2) * gh];
        let ang = rng.gen_range(0.0..std::f32::consts::TAU);
        let rr = rng.gen_range(0.0..0.5) * cfg.goal_radius;
        let goal = [cfg.goal[0] + rr * ang.cos(), cfg.goal[1] + rr * ang.sin()];
        let curve = catmull_rom(&[start, pre, [cfg.wall_x, y], post, goal], 200);
        // resample at a (slightly varying) constant speed
        let speed = cfg.max_speed * rng.gen_range(0.75..0.9);
        let mut positions = vec![start];
        let mut acc = 0.0f32;
        for w in curve.windows(2) {
            let seg = ((w[1][0] - w[0][0]).powi(2) + (w[1][1] - w[0][1]).powi(2)).sqrt();
            acc += seg;
            if acc >= speed {
                positions.push(w[1]);
                acc = 0.0;
            }
        }
        // stop once inside the goal
        let mut pos = Vec::new();
        for p in positions {
            pos.push(p);
            if cfg.in_goal(p) {
                break;
            }
        }
        if pos.last().is_none_or(|&p| !cfg.in_goal(p)) {
            pos.push(goal);
        }
        let actions: Vec<[f32; 2]> = pos.windows(2).map(|w| [w[1][0] - w[0][0], w[1][1] - w[0][1]]).collect();
        // replay in the noise-free env to check it
        let mut env = NavEnv::new(EnvConfig { start_jitter: 0.0, start, ..cfg.clone() }, 1, false, &mut rng);
        let mut ok = true;
        for a in &actions {
            if !env.running(0) {
                break;
            }
            env.step(0, *a, &mut rng);
        }
        ok &= env.status[0] == crate::env::Status::Success;
        if ok && actions.len() < cfg.max_steps {
            demos.push(Demo { positions: pos, actions, wide });
        }
    }
    demos
}
