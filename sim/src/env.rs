//! The 2-D navigation environment, vectorised over many episodes (struct of arrays).
//!
//! Unit box `[0,1]^2`. Start around `start` on the left, goal circle on the right, a vertical wall
//! at `wall_x` (thickness 2 * `wall_half`) with a wide gap and a narrow gap. The action is a
//! velocity (displacement per step), clipped to `max_speed` in norm. Touching the wall (the swept
//! segment of a step intersects it) is a failure, entering the goal circle a success, and running
//! out of steps a failure. At test time Gaussian position noise (`pos_noise` per axis per step)
//! emulates actuator noise.
use rand::Rng;
use rand_distr::StandardNormal;
use serde::{Deserialize, Serialize};

#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct EnvConfig {
    pub start: [f32; 2],
    /// uniform jitter of the start position (+- per axis)
    pub start_jitter: f32,
    pub goal: [f32; 2],
    pub goal_radius: f32,
    pub wall_x: f32,
    pub wall_half: f32,
    /// (centre y, half height) of the wide gap
    pub wide_gap: (f32, f32),
    /// (centre y, half height) of the narrow gap
    pub narrow_gap: (f32, f32),
    pub max_speed: f32,
    /// std of the per-step Gaussian position noise at test time
    pub pos_noise: f32,
    pub max_steps: usize,
}

impl Default for EnvConfig {
    fn default() -> Self {
        EnvConfig {
            start: [0.1, 0.5],
            start_jitter: 0.03,
            goal: [0.9, 0.5],
            goal_radius: 0.07,
            wall_x: 0.5,
            wall_half: 0.02,
            wide_gap: (0.72, 0.09),
            narrow_gap: (0.28, 0.022),
            max_speed: 0.04,
            pos_noise: 0.012,
            max_steps: 80,
        }
    }
}

/// Why an episode ended.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum Status {
    Running,
    Success,
    Collision,
    Timeout,
}

impl EnvConfig {
    /// The wall as axis-aligned rectangles (x0, y0, x1, y1).
    pub fn wall_rects(&self) -> Vec<[f32; 4]> {
        let (x0, x1) = (self.wall_x - self.wall_half, self.wall_x + self.wall_half);
        let mut gaps = [
            (self.narrow_gap.0 - self.narrow_gap.1, self.narrow_gap.0 + self.narrow_gap.1),
            (self.wide_gap.0 - self.wide_gap.1, self.wide_gap.0 + self.wide_gap.1),
        ];
        gaps.sort_by(|a, b| a.0.total_cmp(&b.0));
        let mut rects = Vec::new();
        let mut y = 0.0f32;
        for (lo, hi) in gaps {
            if lo > y {
                rects.push([x0, y, x1, lo]);
            }
            y = hi;
        }
        if y < 1.0 {
            rects.push([x0, y, x1, 1.0]);
        }
        rects
    }

    /// Does the segment a -> b touch the wall?
    pub fn collides(&self, a: [f32; 2], b: [f32; 2]) -> bool {
        self.wall_rects().iter().any(|r| segment_hits_rect(a, b, r))
    }

    pub fn in_goal(&self, p: [f32; 2]) -> bool {
        let dx = p[0] - self.goal[0];
        let dy = p[1] - self.goal[1];
        dx * dx + dy * dy <= self.goal_radius * self.goal_radius
    }

    /// Which gap a trajectory went through (by the y where it crossed x = wall_x), if any.
    pub fn gap_of(&self, positions: &[[f32; 2]]) -> Option<Gap> {
        for w in positions.windows(2) {
            let (a, b) = (w[0], w[1]);
            if (a[0] - self.wall_x) * (b[0] - self.wall_x) <= 0.0 && a[0] != b[0] {
                let s = (self.wall_x - a[0]) / (b[0] - a[0]);
                let y = a[1] + s * (b[1] - a[1]);
                let dn = (y - self.narrow_gap.0).abs();
                let dw = (y - self.wide_gap.0).abs();
                return Some(if dn < dw { Gap::Narrow } else { Gap::Wide });
            }
        }
        None
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum Gap {
    Wide,
    Narrow,
}

/// Liang-Barsky segment / rectangle intersection (closed rectangle).
pub fn segment_hits_rect(a: [f32; 2], b: [f32; 2], r: &[f32; 4]) -> bool {
    let d = [b[0] - a[0], b[1] - a[1]];
    let (mut t0, mut t1) = (0.0f32, 1.0f32);
    for ax in 0..2 {
        let (lo, hi) = (r[ax], r[ax + 2]);
        if d[ax].abs() < 1e-12 {
            if a[ax] < lo || a[ax] > hi {
                return false;
            }
        } else {
            let mut ta = (lo - a[ax]) / d[ax];
            let mut tb = (hi - a[ax]) / d[ax];
            if ta > tb {
                std::mem::swap(&mut ta, &mut tb);
            }
            t0 = t0.max(ta);
            t1 = t1.min(tb);
            if t0 > t1 {
                return false;
            }
        }
    }
    true
}

/// Many episodes of the environment stepped in lockstep (struct of arrays).
pub struct NavEnv {
    pub cfg: EnvConfig,
    pub x: Vec<f32>,
    pub y: Vec<f32>,
    pub status: Vec<Status>,
    pub steps: Vec<usize>,
    /// apply test-time position noise
    pub noisy: bool,
}

impl NavEnv {
    pub fn new<R: Rng + ?Sized>(cfg: EnvConfig, n: usize, noisy: bool, rng: &mut R) -> Self {
        let j = cfg.start_jitter;
        let mut x = Vec::with_capacity(n);
        let mut y = Vec::with_capacity(n);
        for _ in 0..n {
            x.push(cfg.start[0] + if j > 0.0 { rng.gen_range(-j..j) } else { 0.0 });
            y.push(cfg.start[1] + if j > 0.0 { rng.gen_range(-j..j) } else { 0.0 });
        }
        NavEnv { cfg, x, y, status: vec![Status::Running; n], steps: vec![0; n], noisy }
    }

    pub fn len(&self) -> usize {
        self.x.len()
    }
    pub fn is_empty(&self) -> bool {
        self.x.is_empty()
    }
    pub fn pos(&self, i: usize) -> [f32; 2] {
        [self.x[i], self.y[i]]
    }
    pub fn running(&self, i: usize) -> bool {
        self.status[i] == Status::Running
    }

    /// Clip a velocity to `max_speed` in norm.
    pub fn clip_action(&self, a: [f32; 2]) -> [f32; 2] {
        let n = (a[0] * a[0] + a[1] * a[1]).sqrt();
        let m = self.cfg.max_speed;
        if n > m {
            [a[0] * m / n, a[1] * m / n]
        } else {
            a
        }
    }

    /// Step episode `i` with velocity `a` (clipped). Returns the executed (clipped) action.
    pub fn step<R: Rng + ?Sized>(&mut self, i: usize, a: [f32; 2], rng: &mut R) -> [f32; 2] {
        debug_assert!(self.running(i));
        let a = self.clip_action(a);
        let p = self.pos(i);
        let (mut nx, mut ny) = (p[0] + a[0], p[1] + a[1]);
        if self.noisy && self.cfg.pos_noise > 0.0 {
            nx += self.cfg.pos_noise * rng.sample::<f32, _>(StandardNormal);
            ny += self.cfg.pos_noise * rng.sample::<f32, _>(StandardNormal);
        }
        let q = [nx.clamp(0.0, 1.0), ny.clamp(0.0, 1.0)];
        self.steps[i] += 1;
        if self.cfg.collides(p, q) {
            self.status[i] = Status::Collision;
        } else if self.cfg.in_goal(q) {
            self.status[i] = Status::Success;
        } else if self.steps[i] >= self.cfg.max_steps {
            self.status[i] = Status::Timeout;
        }
        self.x[i] = q[0];
        self.y[i] = q[1];
        a
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;

    #[test]
    fn wall_and_gaps() {
        let c = EnvConfig::default();
        // straight through the middle of each gap: free
        assert!(!c.collides([0.45, c.wide_gap.0], [0.55, c.wide_gap.0]));
        assert!(!c.collides([0.45, c.narrow_gap.0], [0.55, c.narrow_gap.0]));
        // between the gaps, below, above: wall
        assert!(c.collides([0.45, 0.5], [0.55, 0.5]));
        assert!(c.collides([0.45, 0.05], [0.55, 0.05]));
        assert!(c.collides([0.45, 0.95], [0.55, 0.95]));
        // grazing the narrow gap's edge
        let e = c.narrow_gap.0 + c.narrow_gap.1 + 0.002;
        assert!(c.collides([0.45, e], [0.55, e]));
        // diagonal through the wall corner
        assert!(c.collides([0.47, c.narrow_gap.0], [0.53, c.narrow_gap.0 + 0.2]));
        // far away
        assert!(!c.collides([0.1, 0.5], [0.2, 0.5]));
        assert_eq!(c.wall_rects().len(), 3);
    }

    #[test]
    fn stepping_and_termination() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(0);
        let c = EnvConfig { start_jitter: 0.0, ..EnvConfig::default() };
        let mut env = NavEnv::new(c.clone(), 2, false, &mut rng);
        // speed is clipped
        let a = env.step(0, [1.0, 0.0], &mut rng);
        assert!((a[0] - c.max_speed).abs() < 1e-6 && env.running(0));
        // env 0 walks straight into the wall
        while env.running(0) {
            env.step(0, [1.0, 0.0], &mut rng);
        }
        assert_eq!(env.status[0], Status::Collision);
        assert!(env.x[0] <= c.wall_x + c.wall_half);
        // env 1 stands still: timeout
        while env.running(1) {
            env.step(1, [0.0, 0.0], &mut rng);
        }
        assert_eq!(env.status[1], Status::Timeout);
        assert_eq!(env.steps[1], c.max_steps);
        assert!(c.in_goal(c.goal));
    }
}
