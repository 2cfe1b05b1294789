"""The 2-D two-gap task (nav_task.py) seen through a camera: a 64x64 RGB top-down picture of the
current state only (wall with its two gaps, goal, the agent as a dot), a PyTorch DDPM chunk
policy that sees nothing but those pictures through a small CNN trained end to end with it, its
vectorised noisy rollouts, and a LeRobot v3.0 writer (one AV1 mp4 for all episodes) for them.

The agent's position is never given to the policy (it has only the camera) nor to the verifier
(it reads the policy encoder's features); `observation.state` is recorded in the dataset for
plots and checks only.
"""
from __future__ import annotations

import json
import math
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Dict, List, Optional, Sequence, Tuple

import numpy as np
import torch
import torch.nn as nn

from nav_task import NavConfig, Scheduler, _temb

SIZE = 64
# The picture's colours (RGB). Everything the policy needs is also in the luma (the dot is much
# brighter than anything else), so the video's 4:2:0 chroma subsampling loses nothing essential.
BACKGROUND = (24, 26, 38)
WALL = (150, 150, 160)
GOAL = (40, 150, 70)
AGENT = (255, 236, 140)
AGENT_RADIUS_PX = 1.6
# The policy's preprocessing, named in the layer's producer (code is recorded by name only).
ENCODER_NAME = "nav-cnn/64px-rgb-sym"


class Camera:
    """Renders positions (B, 2) in the unit box as uint8 frames (B, 64, 64, 3); y points up."""

    def __init__(self, cfg: NavConfig, size: int = SIZE) -> None:
        self.cfg, self.size = cfg, size
        ss = 4  # the static scene is supersampled 4x4 (anti-aliased edges)
        n = size * ss
        c = (np.arange(n) + 0.5) / n
        x, y = np.meshgrid(c, 1.0 - c)
        img = np.empty((n, n, 3), np.float32)
        img[:] = BACKGROUND
        img[(x - cfg.goal[0]) ** 2 + (y - cfg.goal[1]) ** 2 <= cfg.goal_radius**2] = GOAL
        for x0, y0, x1, y1 in cfg.rects:
            img[(x >= x0) & (x <= x1) & (y >= y0) & (y <= y1)] = WALL
        self.background = img.reshape(size, ss, size, ss, 3).mean((1, 3)).astype(np.float32)
        self.centres = (np.arange(size, dtype=np.float32) + 0.5)

    def render(self, pos: np.ndarray) -> np.ndarray:
        pos = np.asarray(pos, dtype=np.float32).reshape(-1, 2)
        px = pos[:, 0] * self.size
        py = (1.0 - pos[:, 1]) * self.size
        dx2 = (self.centres[None, :] - px[:, None]) ** 2
        dy2 = (self.centres[None, :] - py[:, None]) ** 2
        d = np.sqrt(dy2[:, :, None] + dx2[:, None, :])  # (B, H, W)
        cover = np.clip(AGENT_RADIUS_PX + 0.5 - d, 0.0, 1.0)[..., None]
        out = self.background[None] * (1.0 - cover) + np.asarray(AGENT, np.float32) * cover
        return (out + 0.5).astype(np.uint8)


def preprocess(frames: Any) -> torch.Tensor:
    """The policy's preprocessing: uint8 (B, H, W, 3) frames -> float32 (B, 3, H, W) in [-1, 1]."""
    x = torch.as_tensor(np.ascontiguousarray(frames)).permute(0, 3, 1, 2).to(torch.float32)
    return x.mul_(2.0 / 255.0).sub_(1.0).contiguous()


class SpatialSoftmax(nn.Module):
    """Per channel, the softmax-weighted mean (x, y) over the feature map (Levine et al. 2016;
    Diffusion Policy's image encoders pool this way): (B, C, H, W) -> (B, 2C)."""

    def __init__(self, h: int, w: int) -> None:
        super().__init__()
        ys, xs = torch.meshgrid(torch.linspace(-1, 1, h), torch.linspace(-1, 1, w), indexing="ij")
        self.register_buffer("grid", torch.stack([xs.reshape(-1), ys.reshape(-1)], 1), persistent=False)

    def forward(self, f: torch.Tensor) -> torch.Tensor:
        b, c, h, w = f.shape
        att = torch.softmax(f.reshape(b, c, h * w), -1)
        return (att @ self.grid).reshape(b, 2 * c)


class ImageEncoder(nn.Module):
    """A small CNN: (B, 3, 64, 64) preprocessed frames -> (B, dim) features. Three convolutions,
    spatial-softmax keypoints, a linear layer. Trained from scratch with the policy."""

    def __init__(self, dim: int = 64, channels: int = 32) -> None:
        super().__init__()
        self.dim = dim
        self.conv = nn.Sequential(
            nn.Conv2d(3, 16, 5, stride=2, padding=2), nn.ReLU(),
            nn.Conv2d(16, channels, 3, stride=2, padding=1), nn.ReLU(),
            nn.Conv2d(channels, channels, 3, padding=1),
        )
        self.pool = SpatialSoftmax(SIZE // 4, SIZE // 4)
        self.out = nn.Linear(2 * channels, dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.out(self.pool(self.conv(x)))


class ImagePolicy(nn.Module):
    """A DDPM over chunks of `horizon` velocities in x = a / max_speed (nav_task.ChunkPolicy's
    recipe: the network predicts the clean chunk, the sampler takes the eps it implies),
    conditioned on the encoder's features of the last `t_o` camera frames."""

    def __init__(self, cfg: NavConfig, horizon: int = 16, n_exec: int = 8, steps: int = 20, hidden: int = 256,
                 feat_dim: int = 64, t_o: int = 2) -> None:
        super().__init__()
        self.cfg, self.horizon, self.n_exec, self.t_o = cfg, horizon, n_exec, t_o
        self.sched = Scheduler(steps)
        self.encoder = ImageEncoder(feat_dim)
        d = 2 * horizon
        self.norm = nn.LayerNorm(t_o * feat_dim)
        self.net = nn.Sequential(
            nn.Linear(t_o * feat_dim + d + 32, hidden), nn.SiLU(), nn.Linear(hidden, hidden), nn.SiLU(),
            nn.Linear(hidden, hidden), nn.SiLU(), nn.Linear(hidden, d),
        )

    @torch.no_grad()
    def features(self, frames: np.ndarray) -> torch.Tensor:
        """uint8 frames (B, t_o, H, W, 3), oldest first -> the denoiser's condition (B, t_o * dim)."""
        b = frames.shape[0]
        f = self.encoder(preprocess(frames.reshape(-1, *frames.shape[2:])))
        return f.reshape(b, -1)

    def _x0(self, x: torch.Tensor, k: torch.Tensor, cond: torch.Tensor) -> torch.Tensor:
        tval = k.float() * 1000.0 / len(self.sched.timesteps)
        return self.net(torch.cat([self.norm(cond), x.flatten(1), _temb(tval)], 1)).view_as(x)

    def forward(self, x: torch.Tensor, k: torch.Tensor, cond: torch.Tensor) -> torch.Tensor:
        """The noise prediction eps(x_k, k | features) a diffusers-style scheduler takes."""
        ab = self.sched.alphas_cumprod.float()[k][:, None, None]
        return (x - ab.sqrt() * self._x0(x, k, cond)) / (1 - ab).sqrt()

    def fit(self, demos: List[np.ndarray], camera: Camera, iters: int, seed: int = 0, batch: int = 32,
            noise_draws: int = 16, lr: float = 2e-3, first_weight: float = 10.0,
            log: Callable[[str], None] = print) -> None:
        """End to end from pixels: each step encodes `batch` observations (t_o frames each) and
        denoises `noise_draws` noisy copies of each one's chunk, so the CNN's cost is shared.

        The first step of each demonstration is drawn `first_weight` times as often as the others.
        There the two frames are equal and the gap is a coin flip, but it is one sample in ~25;
        unweighted, the CNN policy generalises from the later steps ("above the middle: go up")
        and picks its gap from the start's jitter (a pixel or two) nearly deterministically: at
        most starts all of its samples take one gap, and best-of-N has nothing to choose from.
        The low-dim policy of nav_task mixes more at every start without this."""
        frames, obs_idx, chunks, first = [], [], [], []
        base = 0
        for p in demos:
            frames.append(camera.render(p))
            acts = np.diff(p, axis=0) / self.cfg.max_speed
            for t in range(len(acts)):
                obs_idx.append([base + max(t - self.t_o + 1 + s, 0) for s in range(self.t_o)])
                first.append(t == 0)
                c = acts[t:t + self.horizon]
                c = np.concatenate([c, np.repeat(c[-1:], self.horizon - len(c), 0)]) if len(c) < self.horizon else c
                chunks.append(c)
            base += len(p)
        all_frames = np.concatenate(frames)
        o = torch.tensor(np.array(obs_idx))
        weight = torch.tensor(np.array(first), dtype=torch.float64) * (first_weight - 1) + 1
        a = torch.tensor(np.array(chunks), dtype=torch.float32)
        g = torch.Generator().manual_seed(seed)
        opt = torch.optim.AdamW(self.parameters(), lr=lr, weight_decay=1e-4)
        sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=lr, total_steps=iters, pct_start=0.05)
        ab = self.sched.alphas_cumprod.float()
        self.train()
        for it in range(iters):
            idx = torch.multinomial(weight, batch, replacement=True, generator=g)
            img = preprocess(all_frames[o[idx].reshape(-1).numpy()])
            cond = self.encoder(img).reshape(batch, -1).repeat_interleave(noise_draws, 0)
            target = a[idx].repeat_interleave(noise_draws, 0)
            k = torch.randint(0, len(ab), (len(target),), generator=g)
            noise = torch.randn(target.shape, generator=g)
            s = ab[k][:, None, None]
            xk = s.sqrt() * target + (1 - s).sqrt() * noise
            loss = ((self._x0(xk, k, cond) - target) ** 2).mean()
            opt.zero_grad()
            loss.backward()
            opt.step()
            sched.step()
            if (it + 1) % max(iters // 4, 1) == 0:
                log(f"  policy iter {it + 1}/{iters}: loss {loss.item():.4f}")
        self.eval()

    @torch.no_grad()
    def sample(self, cond: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
        """Chunks (B, horizon, 2) in the normalised space for conditions (B, t_o * dim)."""
        x = torch.randn((len(cond), self.horizon, 2), generator=generator)
        for k in self.sched.timesteps:
            eps = self(x, torch.full((len(cond),), k), cond)
            x = self.sched.step(eps, k, x, generator).prev_sample
        return x


@dataclass
class Episode:
    positions: List[np.ndarray]
    actions: List[np.ndarray]
    success: bool = False
    outcome: str = "timeout"  # goal | wall | timeout

    def gap(self, cfg: NavConfig) -> Optional[str]:
        """Which gap the episode went through (or died in): wide / narrow / None."""
        p = np.array(self.positions)
        past = np.flatnonzero(p[:, 0] >= cfg.wall_x - cfg.wall_half)
        if len(past) == 0:
            return None
        y = p[past[0], 1]
        return "wide" if abs(y - cfg.wide_gap[0]) < abs(y - cfg.narrow_gap[0]) else "narrow"


# choose(frames (B, t_o, H, W, 3), alive episode indices, step, generator) -> (B, horizon, 2)
Chooser = Callable[[np.ndarray, np.ndarray, int, torch.Generator], torch.Tensor]


def rollout(policy: ImagePolicy, camera: Camera, n: int, seed: int, choose: Optional[Chooser] = None) -> List[Episode]:
    """`n` noisy episodes in lockstep (nav_task.rollout's dynamics and noise), the policy seeing
    only rendered frames; re-plans every `n_exec` steps with `choose` (default: one base sample)."""
    cfg = policy.cfg
    rng = np.random.default_rng(seed)
    gen = torch.Generator().manual_seed(seed ^ 0x5EED)
    pos = np.array(cfg.start) + rng.uniform(-cfg.start_jitter, cfg.start_jitter, (n, 2))
    eps = [Episode([pos[i].copy()], []) for i in range(n)]
    alive = np.ones(n, dtype=bool)
    step = 0
    while alive.any() and step < cfg.max_steps:
        idx = np.flatnonzero(alive)
        hist = np.stack([[eps[i].positions[max(len(eps[i].positions) - policy.t_o + s, 0)] for s in range(policy.t_o)]
                         for i in idx])  # (B, t_o, 2), oldest first, the first repeated
        frames = camera.render(hist.reshape(-1, 2)).reshape(len(idx), policy.t_o, camera.size, camera.size, 3)
        plan = policy.sample(policy.features(frames), gen) if choose is None else choose(frames, idx, step, gen)
        chunks = plan.numpy().astype(np.float64).reshape(len(idx), -1, 2) * cfg.max_speed
        for j in range(min(policy.n_exec, chunks.shape[1])):
            live = alive[idx]
            if not live.any():
                break
            ii = idx[live]
            a = chunks[live, j]
            norm = np.linalg.norm(a, axis=1, keepdims=True)
            a = np.where(norm > cfg.max_speed, a * cfg.max_speed / np.maximum(norm, 1e-12), a)
            p = pos[ii]
            q = np.clip(p + a + cfg.pos_noise * rng.standard_normal((len(ii), 2)), 0, 1)
            hit, goal = cfg.collides(p, q), cfg.in_goal(q)
            pos[ii] = q
            for r, i in enumerate(ii):
                e = eps[i]
                e.actions.append(a[r].copy())
                e.positions.append(q[r].copy())
                if hit[r]:
                    alive[i], e.outcome = False, "wall"
                elif goal[r]:
                    alive[i], e.success, e.outcome = False, True, "goal"
                elif len(e.actions) >= cfg.max_steps:
                    alive[i] = False
        step += policy.n_exec
    return eps


def clip_speed(chunks: torch.Tensor) -> torch.Tensor:
    """Chunks (..., 2) in x = a / max_speed with each step's norm clipped to 1: what the
    environment executes (and what the dataset records as the action)."""
    norm = chunks.norm(dim=-1, keepdim=True)
    return torch.where(norm > 1.0, chunks / norm.clamp_min(1e-12), chunks)


# ---- a LeRobot v3.0 dataset (the layout lerobot 0.4+/0.6 writes), one mp4 for all episodes ----

_QUANTILES = {"q01": 0.01, "q10": 0.10, "q50": 0.50, "q90": 0.90, "q99": 0.99}


def _stats(x: np.ndarray) -> Dict[str, Any]:
    """lerobot's per-feature stats of rows x (N, D): min/max/mean/std/count and quantiles."""
    x = x.astype(np.float64).reshape(len(x), -1)
    out: Dict[str, Any] = {"min": x.min(0), "max": x.max(0), "mean": x.mean(0), "std": x.std(0),
                           "count": np.array([len(x)])}
    qs = np.quantile(x, list(_QUANTILES.values()), axis=0)
    for k, q in zip(_QUANTILES, qs):
        out[k] = q
    return out


def _image_stats(frames: np.ndarray) -> Dict[str, Any]:
    """Per-channel stats of uint8 frames (N, H, W, 3) in [0, 1], shaped (3, 1, 1) as lerobot's."""
    x = frames[:, ::4, ::4].reshape(-1, 3).astype(np.float64) / 255.0  # every 4th pixel (as lerobot samples)
    s = _stats(x)
    return {k: (v if k == "count" else v.reshape(3, 1, 1)) for k, v in {**s, "count": np.array([len(frames)])}.items()}


def _aggregate(stats: List[Dict[str, Any]]) -> Dict[str, Any]:
    n = np.array([s["count"][0] for s in stats], np.float64)
    w = n / n.sum()
    mean = sum(wi * s["mean"] for wi, s in zip(w, stats))
    var = sum(wi * (s["std"] ** 2 + (s["mean"] - mean) ** 2) for wi, s in zip(w, stats))
    out = {"min": np.min([s["min"] for s in stats], 0), "max": np.max([s["max"] for s in stats], 0),
           "mean": mean, "std": np.sqrt(var), "count": np.array([int(n.sum())])}
    for k in _QUANTILES:
        out[k] = sum(wi * s[k] for wi, s in zip(w, stats))
    return out


def write_lerobot_v30(eps: Sequence[Episode], root: Path, camera: Camera, *, fps: int = 10,
                      task: str = "Reach the green goal through a gap in the wall.",
                      video_key: str = "observation.images.top", crf: int = 30, gop: int = 2,
                      key_at_start: bool = True) -> Dict[str, Any]:
    """The rollouts as a LeRobot v3.0 dataset in lerobot's layout (data/chunk-000/file-000.parquet,
    videos/<key>/chunk-000/file-000.mp4 with the episodes back to back, meta/info.json,
    meta/stats.json, meta/tasks.parquet, meta/episodes/chunk-000/file-000.parquet with per-episode
    stats), AV1 (libsvtav1, yuv420p, g=2, crf=30: lerobot's defaults). Each episode starts on a
    keyframe, as in lerobot's files (it encodes episode by episode and concatenates): a first
    frame predicted from the previous episode's last one decodes worse (the encoder's features of
    it: cosine ~0.8 to the raw frame's, against ~0.998 from a keyframe). Written directly with
    pyarrow + PyAV because lerobot's writer encodes each episode separately and re-muxes the
    growing file (~0.3 s an episode here, and quadratic). Frame t holds the picture before step t,
    the action taken and what the step returned (`next.*` as lerobot-eval)."""
    import av
    import pyarrow as pa
    import pyarrow.parquet as pq

    if root.exists():
        shutil.rmtree(root)
    (root / "meta" / "episodes" / "chunk-000").mkdir(parents=True)
    (root / "data" / "chunk-000").mkdir(parents=True)
    vdir = root / "videos" / video_key / "chunk-000"
    vdir.mkdir(parents=True)

    container = av.open(str(vdir / "file-000.mp4"), "w")
    stream = container.add_stream("libsvtav1", rate=fps, options={"g": str(gop), "crf": str(crf), "preset": "12"})
    stream.width = stream.height = camera.size
    stream.pix_fmt = "yuv420p"
    stream.thread_count = 1

    vec = pa.list_(pa.float32(), 2)
    cols: Dict[str, List[Any]] = {k: [] for k in ["observation.state", "action", "next.reward", "next.success", "next.done",
                                                  "timestamp", "frame_index", "episode_index", "index", "task_index"]}
    ep_rows: List[Dict[str, Any]] = []
    all_stats: Dict[str, List[Dict[str, Any]]] = {}
    index = 0
    for i, e in enumerate(eps):
        n = len(e.actions)
        pos = np.array(e.positions[:n], np.float32)
        act = np.array(e.actions, np.float32)
        frames = camera.render(pos)
        for t, f in enumerate(frames):
            vf = av.VideoFrame.from_ndarray(f, format="rgb24")
            if t == 0 and key_at_start:
                vf.pict_type = av.video.frame.PictureType.I
            for pkt in stream.encode(vf):
                container.mux(pkt)
        done = np.zeros(n, bool)
        done[-1] = True
        success = done & e.success
        ts = (np.arange(n) / fps).astype(np.float32)
        per = {
            "observation.state": pos, "action": act, "next.reward": success.astype(np.float32),
            "next.success": success, "next.done": done, "timestamp": ts,
            "frame_index": np.arange(n, dtype=np.int64), "episode_index": np.full(n, i, np.int64),
            "index": np.arange(index, index + n, dtype=np.int64), "task_index": np.zeros(n, np.int64),
        }
        for k, v in per.items():
            cols[k].append(v)
        stats = {k: _stats(np.asarray(v, np.float64).reshape(n, -1)) for k, v in per.items()}
        stats[video_key] = _image_stats(frames)
        for k, s in stats.items():
            all_stats.setdefault(k, []).append(s)
        from_ts = index / fps
        row: Dict[str, Any] = {
            "episode_index": i, "tasks": [task], "length": n, "data/chunk_index": 0, "data/file_index": 0,
            "dataset_from_index": index, "dataset_to_index": index + n,
            f"videos/{video_key}/chunk_index": 0, f"videos/{video_key}/file_index": 0,
            f"videos/{video_key}/from_timestamp": from_ts, f"videos/{video_key}/to_timestamp": (index + n) / fps,
        }
        for k in list(per)[:2] + [video_key] + list(per)[2:]:
            for sk, sv in stats[k].items():
                row[f"stats/{k}/{sk}"] = np.asarray(sv).tolist()
        row["meta/episodes/chunk_index"] = 0
        row["meta/episodes/file_index"] = 0
        ep_rows.append(row)
        index += n
    for pkt in stream.encode():
        container.mux(pkt)
    container.close()

    def cat(k: str) -> np.ndarray:
        return np.concatenate(cols[k])

    features: Dict[str, Any] = {
        "observation.state": {"dtype": "float32", "shape": [2], "names": ["x", "y"]},
        "action": {"dtype": "float32", "shape": [2], "names": ["vx", "vy"]},
        video_key: {
            "dtype": "video", "shape": [camera.size, camera.size, 3], "names": ["height", "width", "channel"],
            "info": {"video.height": camera.size, "video.width": camera.size, "video.codec": "av1",
                     "video.pix_fmt": "yuv420p", "video.fps": fps, "video.channels": 3, "has_audio": False,
                     "video.g": gop, "video.crf": crf, "video.preset": 12, "video.fast_decode": 0,
                     "video.video_backend": "pyav", "video.extra_options": {}, "is_depth_map": False},
        },
        "next.reward": {"dtype": "float32", "shape": [1], "names": None},
        "next.success": {"dtype": "bool", "shape": [1], "names": None},
        "next.done": {"dtype": "bool", "shape": [1], "names": None},
        "timestamp": {"dtype": "float32", "shape": [1], "names": None},
        "frame_index": {"dtype": "int64", "shape": [1], "names": None},
        "episode_index": {"dtype": "int64", "shape": [1], "names": None},
        "index": {"dtype": "int64", "shape": [1], "names": None},
        "task_index": {"dtype": "int64", "shape": [1], "names": None},
    }
    # The data parquet, with the `huggingface` schema metadata lerobot's `datasets` writer adds.
    hf = {"info": {"features": {
        **{k: {"feature": {"dtype": "float32", "_type": "Value"}, "length": 2, "_type": "List"}
           for k in ("observation.state", "action")},
        "next.reward": {"dtype": "float32", "_type": "Value"}, "next.success": {"dtype": "bool", "_type": "Value"},
        "next.done": {"dtype": "bool", "_type": "Value"}, "timestamp": {"dtype": "float32", "_type": "Value"},
        **{k: {"dtype": "int64", "_type": "Value"} for k in ("frame_index", "episode_index", "index", "task_index")},
    }}}
    table = pa.table({
        "observation.state": pa.FixedSizeListArray.from_arrays(pa.array(cat("observation.state").reshape(-1)), 2),
        "action": pa.FixedSizeListArray.from_arrays(pa.array(cat("action").reshape(-1)), 2),
        "next.reward": pa.array(cat("next.reward")), "next.success": pa.array(cat("next.success")),
        "next.done": pa.array(cat("next.done")), "timestamp": pa.array(cat("timestamp")),
        "frame_index": pa.array(cat("frame_index")), "episode_index": pa.array(cat("episode_index")),
        "index": pa.array(cat("index")), "task_index": pa.array(cat("task_index")),
    })
    table = table.replace_schema_metadata({"huggingface": json.dumps(hf)})
    pq.write_table(table, root / "data" / "chunk-000" / "file-000.parquet", compression="snappy")
    pq.write_table(pa.Table.from_pylist(ep_rows), root / "meta" / "episodes" / "chunk-000" / "file-000.parquet")
    pq.write_table(pa.table({"task_index": pa.array([0], pa.int64()), "task": pa.array([task])}),
                   root / "meta" / "tasks.parquet")
    stats = {k: {sk: np.asarray(sv).tolist() for sk, sv in _aggregate(v).items()} for k, v in all_stats.items()}
    (root / "meta" / "stats.json").write_text(json.dumps(stats, indent=4))
    info = {
        "codebase_version": "v3.0", "fps": fps, "features": features, "total_episodes": len(eps),
        "total_frames": index, "total_tasks": 1, "chunks_size": 1000, "data_files_size_in_mb": 100,
        "video_files_size_in_mb": 200, "data_path": "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet",
        "video_path": "videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4",
        "robot_type": "point_2d_camera", "splits": {"train": f"0:{len(eps)}"},
    }
    (root / "meta" / "info.json").write_text(json.dumps(info, indent=4))
    return {"episodes": len(eps), "frames": index, "video_bytes": (vdir / "file-000.mp4").stat().st_size}


def wilson(k: int, n: int, z: float = 1.959963984540054) -> Tuple[float, float]:
    """Wilson score interval (evalstats::wilson_p)."""
    if n == 0:
        return 0.0, 1.0
    p = k / n
    d = 1 + z * z / n
    c = (p + z * z / (2 * n)) / d
    h = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / d
    return (0.0 if k == 0 else max(c - h, 0.0)), (1.0 if k == n else min(c + h, 1.0))


def newcombe(k1: int, n1: int, k2: int, n2: int, z: float = 1.959963984540054) -> Tuple[float, float]:
    """Newcombe's hybrid score interval (1998, method 10) of p1 - p2 for two independent
    proportions, as evalstats::newcombe_p computes it."""
    l1, u1 = wilson(k1, n1, z)
    l2, u2 = wilson(k2, n2, z)
    p1 = k1 / n1 if n1 else 0.0
    p2 = k2 / n2 if n2 else 0.0
    d = p1 - p2
    lo = d - math.sqrt((p1 - l1) ** 2 + (u2 - p2) ** 2)
    hi = d + math.sqrt((u1 - p1) ** 2 + (p2 - l2) ** 2)
    return max(lo, -1.0), min(hi, 1.0)
