"""The paper's 2-D two-gap navigation task in numpy — a port of the `sim` crate (sim/src/env.rs,
demos.rs), vectorised over episodes — and a small PyTorch DDPM chunk policy for it.

Unit box; start on the left, goal circle on the right, a wall at x = 0.5 with a wide gap (y 0.72)
and a narrow one (y 0.28). Actions are velocities clipped to 0.04; touching the wall fails, the
goal succeeds, 80 steps time out; test-time position noise 0.012 per axis per step.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Callable, List, Optional, Tuple

import numpy as np
import torch
import torch.nn as nn


@dataclass
class NavConfig:
    start: Tuple[float, float] = (0.1, 0.5)
    start_jitter: float = 0.03
    goal: Tuple[float, float] = (0.9, 0.5)
    goal_radius: float = 0.07
    wall_x: float = 0.5
    wall_half: float = 0.02
    wide_gap: Tuple[float, float] = (0.72, 0.09)
    narrow_gap: Tuple[float, float] = (0.28, 0.022)
    max_speed: float = 0.04
    pos_noise: float = 0.012
    max_steps: int = 80
    rects: np.ndarray = field(init=False)

    def __post_init__(self) -> None:
        x0, x1 = self.wall_x - self.wall_half, self.wall_x + self.wall_half
        gaps = sorted([(c - h, c + h) for c, h in (self.narrow_gap, self.wide_gap)])
        rects, y = [], 0.0
        for lo, hi in gaps:
            if lo > y:
                rects.append([x0, y, x1, lo])
            y = hi
        if y < 1.0:
            rects.append([x0, y, x1, 1.0])
        self.rects = np.array(rects, dtype=np.float64)

    def collides(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """Does segment a -> b (rows) touch the wall? Liang-Barsky against each rectangle."""
        hit = np.zeros(len(a), dtype=bool)
        d = b - a
        for r in self.rects:
            t0, t1 = np.zeros(len(a)), np.ones(len(a))
            inside = np.ones(len(a), dtype=bool)
            for ax in range(2):
                lo, hi = r[ax], r[ax + 2]
                flat = np.abs(d[:, ax]) < 1e-12
                inside &= ~(flat & ((a[:, ax] < lo) | (a[:, ax] > hi)))
                with np.errstate(divide="ignore", invalid="ignore"):
                    ta = (lo - a[:, ax]) / d[:, ax]
                    tb = (hi - a[:, ax]) / d[:, ax]
                lo_t, hi_t = np.minimum(ta, tb), np.maximum(ta, tb)
                t0 = np.where(flat, t0, np.maximum(t0, lo_t))
                t1 = np.where(flat, t1, np.minimum(t1, hi_t))
            hit |= inside & (t0 <= t1)
        return hit

    def in_goal(self, p: np.ndarray) -> np.ndarray:
        return ((p[:, 0] - self.goal[0]) ** 2 + (p[:, 1] - self.goal[1]) ** 2) <= self.goal_radius**2


def _catmull_rom(p: List[np.ndarray], per_seg: int) -> np.ndarray:
    out = []
    n = len(p)
    s = np.arange(per_seg) / per_seg
    for i in range(n - 1):
        p0, p1, p2, p3 = p[max(i - 1, 0)], p[i], p[i + 1], p[min(i + 2, n - 1)]
        t, t2, t3 = s[:, None], (s**2)[:, None], (s**3)[:, None]
        out.append(0.5 * (2 * p1 + (-p0 + p2) * t + (2 * p0 - 5 * p1 + 4 * p2 - p3) * t2 + (-p0 + 3 * p1 - 3 * p2 + p3) * t3))
    out.append(p[-1][None])
    return np.concatenate(out)


def expert_demos(cfg: NavConfig, n: int, seed: int) -> List[np.ndarray]:
    """`n` demonstrations (alternating wide / narrow gap): smooth curves through a gap's centre to
    the goal at a near-constant speed, each checked collision-free; returns positions (T+1, 2)."""
    rng = np.random.default_rng(seed)
    demos: List[np.ndarray] = []
    while len(demos) < n:
        gy, gh = cfg.wide_gap if len(demos) % 2 == 0 else cfg.narrow_gap
        j = cfg.start_jitter
        start = np.array(cfg.start) + rng.uniform(-j, j, 2)
        y = gy + rng.uniform(-0.25, 0.25) * gh
        pre = np.array([cfg.wall_x - rng.uniform(0.08, 0.14), y + rng.uniform(-0.2, 0.2) * gh])
        post = np.array([cfg.wall_x + rng.uniform(0.08, 0.14), y + rng.uniform(-0.2, 0.2) * gh])
        ang, rr = rng.uniform(0, 2 * math.pi), rng.uniform(0, 0.5) * cfg.goal_radius
        goal = np.array(cfg.goal) + rr * np.array([math.cos(ang), math.sin(ang)])
        curve = _catmull_rom([start, pre, np.array([cfg.wall_x, y]), post, goal], 200)
        speed = cfg.max_speed * rng.uniform(0.75, 0.9)
        pos, acc = [start], 0.0
        for a, b in zip(curve[:-1], curve[1:]):
            acc += float(np.hypot(*(b - a)))
            if acc >= speed:
                pos.append(b)
                acc = 0.0
                if cfg.in_goal(b[None])[0]:
                    break
        if not cfg.in_goal(pos[-1][None])[0]:
            pos.append(goal)
        p = np.array(pos)
        if len(p) - 1 < cfg.max_steps and not cfg.collides(p[:-1], p[1:]).any():
            demos.append(p)
    return demos


def obs_history(positions: List[np.ndarray], t_o: int = 2) -> np.ndarray:
    """The t_o most recent positions of each episode, oldest first (the first repeated)."""
    return np.stack([np.concatenate([h[max(len(h) - t_o + s, 0)] for s in range(t_o)]) for h in positions]).astype(np.float32)


# ---- a small DDPM chunk policy (epsilon prediction, diffusers' squaredcos_cap_v2 schedule) ----


class Scheduler:
    """A diffusers-style DDPM scheduler: ``alphas_cumprod``, ``timesteps``, ``step(eps, k, x)``."""

    def __init__(self, k: int, clip: float = 1.0) -> None:
        f = lambda t: math.cos((t + 0.008) / 1.008 * math.pi / 2) ** 2  # noqa: E731
        betas = torch.tensor([min(1 - f((i + 1) / k) / f(i / k), 0.999) for i in range(k)], dtype=torch.float64)
        self.betas = betas
        self.alphas_cumprod = torch.cumprod(1 - betas, 0)
        self.timesteps = list(range(k - 1, -1, -1))
        self.clip = clip

    @dataclass
    class Out:
        prev_sample: torch.Tensor

    def step(self, eps: torch.Tensor, k: int, x: torch.Tensor, generator: Optional[torch.Generator] = None) -> "Scheduler.Out":
        ab = float(self.alphas_cumprod[k])
        ab_prev = float(self.alphas_cumprod[k - 1]) if k > 0 else 1.0
        beta = 1 - ab / ab_prev
        x0 = ((x - math.sqrt(1 - ab) * eps) / math.sqrt(ab)).clamp(-self.clip, self.clip)
        c0 = math.sqrt(ab_prev) * beta / (1 - ab)
        ck = math.sqrt(1 - beta) * (1 - ab_prev) / (1 - ab)
        mean = c0 * x0 + ck * x
        if k == 0:
            return Scheduler.Out(mean)
        var = (1 - ab_prev) / (1 - ab) * beta
        z = torch.randn(x.shape, generator=generator)
        return Scheduler.Out(mean + math.sqrt(max(var, 1e-20)) * z)


def _temb(k: torch.Tensor, dim: int = 32) -> torch.Tensor:
    i = torch.arange(dim // 2, dtype=torch.float32)
    f = k[:, None].float() / (10000 ** (2 * i / dim))[None]
    return torch.cat([f.sin(), f.cos()], 1)


class ChunkPolicy(nn.Module):
    """A DDPM over chunks of `horizon` velocities in the normalised space x = a / max_speed (the
    `sim` crate's recipe: the network predicts the clean chunk, the sampler takes the eps it implies)."""

    def __init__(self, cfg: NavConfig, horizon: int = 16, n_exec: int = 8, steps: int = 20, hidden: int = 128) -> None:
        super().__init__()
        self.cfg, self.horizon, self.n_exec = cfg, horizon, n_exec
        self.sched = Scheduler(steps)
        d = 2 * horizon
        self.net = nn.Sequential(
            nn.Linear(4 + d + 32, hidden), nn.SiLU(), nn.Linear(hidden, hidden), nn.SiLU(),
            nn.Linear(hidden, hidden), nn.SiLU(), nn.Linear(hidden, hidden), nn.SiLU(), nn.Linear(hidden, d),
        )

    def _x0(self, x: torch.Tensor, k: torch.Tensor, obs: torch.Tensor) -> torch.Tensor:
        tval = k.float() * 1000.0 / len(self.sched.timesteps)
        return self.net(torch.cat([(obs - 0.5) * 2, x.flatten(1), _temb(tval)], 1)).view_as(x)

    def forward(self, x: torch.Tensor, k: torch.Tensor, obs: torch.Tensor) -> torch.Tensor:
        """The noise prediction eps(x_k, k | obs) a diffusers-style scheduler takes."""
        ab = self.sched.alphas_cumprod.float()[k][:, None, None]
        return (x - ab.sqrt() * self._x0(x, k, obs)) / (1 - ab).sqrt()

    def fit(self, demos: List[np.ndarray], iters: int, seed: int = 0, log: Callable[[str], None] = print) -> None:
        obs, chunks = [], []
        for p in demos:
            acts = np.diff(p, axis=0) / self.cfg.max_speed
            for t in range(len(acts)):
                obs.append(np.concatenate([p[max(t - 1, 0)], p[t]]))
                c = acts[t:t + self.horizon]
                c = np.concatenate([c, np.repeat(c[-1:], self.horizon - len(c), 0)]) if len(c) < self.horizon else c
                chunks.append(c)
        o = torch.tensor(np.array(obs), dtype=torch.float32)
        a = torch.tensor(np.array(chunks), dtype=torch.float32)
        g = torch.Generator().manual_seed(seed)
        opt = torch.optim.AdamW(self.parameters(), lr=3e-3, weight_decay=1e-4)
        sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, iters)
        ab = self.sched.alphas_cumprod.float()
        for it in range(iters):
            idx = torch.randint(0, len(o), (256,), generator=g)
            k = torch.randint(0, len(ab), (256,), generator=g)
            noise = torch.randn(a[idx].shape, generator=g)
            s = ab[k][:, None, None]
            xk = s.sqrt() * a[idx] + (1 - s).sqrt() * noise
            loss = ((self._x0(xk, k, o[idx]) - a[idx]) ** 2).mean()
            opt.zero_grad()
            loss.backward()
            opt.step()
            sched.step()
            if (it + 1) % max(iters // 4, 1) == 0:
                log(f"  policy iter {it + 1}/{iters}: loss {loss.item():.4f}")

    @torch.no_grad()
    def sample(self, obs: torch.Tensor, generator: torch.Generator,
               hook: Optional[Callable[[torch.Tensor, int, torch.Tensor], torch.Tensor]] = None) -> torch.Tensor:
        """Chunks (B, horizon, 2) in the normalised space; `hook(eps, k, x)` may guide each step."""
        x = torch.randn((len(obs), self.horizon, 2), generator=generator)
        for k in self.sched.timesteps:
            eps = self(x, torch.full((len(obs),), k), obs)
            if hook is not None:
                eps = hook(eps, k, x)
            x = self.sched.step(eps, k, x, generator).prev_sample
        return x


@dataclass
class Episode:
    positions: List[np.ndarray]
    actions: List[np.ndarray]
    success: bool = False


def rollout(policy: ChunkPolicy, n: int, seed: int,
            choose: Optional[Callable[[np.ndarray, int, torch.Generator], torch.Tensor]] = None) -> List[Episode]:
    """`n` noisy episodes in lockstep; `choose(obs, t, gen)` returns the (B, H, 2) chunks to run
    (default: the base policy's samples). Re-plans every `n_exec` steps."""
    cfg = policy.cfg
    rng = np.random.default_rng(seed)
    gen = torch.Generator().manual_seed(seed ^ 0x5EED)
    pos = np.array(cfg.start) + rng.uniform(-cfg.start_jitter, cfg.start_jitter, (n, 2))
    eps = [Episode([pos[i].copy()], []) for i in range(n)]
    alive = np.ones(n, dtype=bool)
    step = 0
    while alive.any() and step < cfg.max_steps:
        idx = np.flatnonzero(alive)
        obs = obs_history([eps[i].positions for i in idx])
        chunks = (choose(obs, step, gen) if choose else policy.sample(torch.from_numpy(obs), gen)).numpy()
        chunks = chunks.reshape(len(idx), policy.horizon, 2) * cfg.max_speed
        for j in range(policy.n_exec):
            live = alive[idx]
            if not live.any():
                break
            ii = idx[live]
            a = chunks[live, j].astype(np.float64)
            norm = np.linalg.norm(a, axis=1, keepdims=True)
            a = np.where(norm > cfg.max_speed, a * cfg.max_speed / np.maximum(norm, 1e-12), a)
            p = pos[ii]
            q = np.clip(p + a + cfg.pos_noise * rng.standard_normal((len(ii), 2)), 0, 1)
            hit, goal = cfg.collides(p, q), cfg.in_goal(q)
            for r, i in enumerate(ii):
                eps[i].actions.append(a[r].copy())
                eps[i].positions.append(q[r].copy())
            pos[ii] = q
            for r, i in enumerate(ii):
                if hit[r]:
                    alive[i] = False
                elif goal[r]:
                    alive[i] = False
                    eps[i].success = True
                elif len(eps[i].actions) >= cfg.max_steps:
                    alive[i] = False
        step += policy.n_exec
    return eps


def wilson(k: int, n: int, z: float = 1.96) -> Tuple[float, float]:
    if n == 0:
        return 0.0, 1.0
    p = k / n
    d = 1 + z * z / n
    c = (p + z * z / (2 * n)) / d
    h = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / d
    return c - h, c + h
