#!/usr/bin/env python3
"""The third demo: a LeRobot DiffusionPolicy on robosuite Lift, seen through an 84x84 camera, steered
by a verifier that reads the policy's own encoder features. End to end, with LeRobot's own code
wherever LeRobot has it:

1. a scripted expert (examples/python/lift_task.py) writes demonstrations with LeRobot's
   ``LeRobotDataset`` writer (v3.0; the camera as PNG frames, the state, the action);
2. a LeRobot ``DiffusionPolicy`` (random initialisation, a ResNet-18 encoder, a small U-Net: a
   config our 2-core CPU trains in well under an hour) is trained on that dataset, loaded
   with the policy's observation history and action horizon (``delta_timestamps``), and saved
   with ``save_pretrained`` (policy and its pre/post-processors) into a cache a re-run reuses;
3. its rollouts (the verifier's data) are recorded with ``LeRobotDataset`` (v3.0, the camera as
   video) and ingested (``ufops ingest --format lerobot --run rollouts``);
4. the layer of the policy's own encoder features, ``ufops.lerobot.encoder_of``, is computed
   over the stored video; a classifier is trained on it and the state (``ufops split create`` +
   ``ufops train``, the paper's features recipe, chunks of ``n_action_steps`` in the policy's
   normalised action space);
5. the unchanged policy, and the same policy wrapped in ``ufops.lerobot.SteeredPolicy``
   (best-of-N), are evaluated by LeRobot's own evaluation loop (``lerobot.scripts.lerobot_eval.
   eval_policy``, the function ``lerobot-eval`` runs) on the same seeds, in rounds; each round's
   ``eval_info.json`` and videos are ingested as runs ``base`` and ``c-bon<N>``
   (``ufops ingest --format lerobot-eval``), and ``ufops compare`` (sequential, paired by seed)
   decides after every round whether to stop; ``ufops scoreboard`` shows the runs;
6. the re-plan latency: policy sampling of N chunks, the encoder, verifier scoring and the total,
   against the unsteered policy's re-plan, on the same observations.

    MUJOCO_GL=osmesa python3 examples/python/steer_lerobot_robosuite.py [--quick] [--workdir DIR]

Needs the ``ufops`` binary (``cargo build --bin ufops``; $UFOPS_BIN or $CARGO_TARGET_DIR/debug/ufops
like the tests, or --ufops), the ``ufops`` package (``pip install ./clients/python``), lerobot,
mujoco==2.3.7 and robosuite==1.4.1 (PyPI) and an off-screen OpenGL (Debian's ``libosmesa6`` with
``MUJOCO_GL=osmesa``). Prints the results table and the wall time of each phase; writes
report.json and report.md in the work directory.
"""
from __future__ import annotations

import argparse
import hashlib
import json
import math
import multiprocessing as mp
import os
import shutil
import subprocess
import sys
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Dict, Iterator, List, Optional, Sequence, Tuple

os.environ.setdefault("MUJOCO_GL", "osmesa")
os.environ.setdefault("HF_HUB_OFFLINE", "1")

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))

REPO = Path(__file__).resolve().parents[2]
POLICY = "lift-dp"
CAMERA_KEY = "observation.images.agentview"
LAYER = f"features.{POLICY}.agentview"


def log(msg: str) -> None:
    print(msg, flush=True)


def find_ufops(explicit: Optional[str]) -> Path:
    target = os.environ.get("CARGO_TARGET_DIR") or str(Path.home() / ".cache" / "ufops-target")
    for c in [explicit, os.environ.get("UFOPS_BIN"), f"{target}/debug/ufops", str(REPO / "target/debug/ufops")]:
        if c and Path(c).is_file():
            return Path(c)
    sys.exit("the ufops binary is needed: cargo build --bin ufops (or pass --ufops PATH)")


class Cli:
    def __init__(self, bin_: Path, data_dir: Path) -> None:
        self.bin, self.data_dir = bin_, data_dir

    def run(self, *args: str, ok: Sequence[int] = (0,)) -> subprocess.CompletedProcess:  # type: ignore[type-arg]
        p = subprocess.run([str(self.bin), "--data-dir", str(self.data_dir), *args], capture_output=True, text=True)
        if p.returncode not in ok:
            sys.exit(f"ufops {' '.join(args)} failed ({p.returncode}):\n{p.stderr.strip()}")
        return p

    def __call__(self, *args: str) -> str:
        return str(self.run(*args).stdout)

    def json(self, *args: str) -> Any:
        return json.loads(self(*args, "--json"))


class Phases:
    """Wall time of each phase, in order."""

    def __init__(self) -> None:
        self.seconds: Dict[str, float] = {}
        self.start = time.time()

    def total(self) -> float:
        return time.time() - self.start

    @contextmanager
    def __call__(self, name: str) -> Iterator[None]:
        t0 = time.time()
        try:
            yield
        finally:
            self.seconds[name] = self.seconds.get(name, 0.0) + time.time() - t0


def wilson(k: int, n: int, z: float = 1.959963984540054) -> Tuple[float, float]:
    if n == 0:
        return 0.0, 1.0
    p = k / n
    d = 1 + z * z / n
    c = (p + z * z / (2 * n)) / d
    h = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / d
    return max(0.0, c - h), min(1.0, c + h)


def newcombe(k1: int, n1: int, k0: int, n0: int) -> Tuple[float, float]:
    """Newcombe's (method 10) 95% interval of p1 - p0."""
    l1, u1 = wilson(k1, n1)
    l0, u0 = wilson(k0, n0)
    p1, p0 = k1 / n1, k0 / n0
    d = p1 - p0
    return d - math.sqrt((p1 - l1) ** 2 + (u0 - p0) ** 2), d + math.sqrt((u1 - p1) ** 2 + (p0 - l0) ** 2)


# --- the policy --------------------------------------------------------------------------------


def policy_config(inp: Dict[str, Any], out: Dict[str, Any]) -> Any:
    """A DiffusionPolicy small enough to train on 2 CPU cores: ResNet-18 on a 76x76 crop (random
    init, GroupNorm), 32 keypoints (64-d features per frame), a U-Net of (64, 128, 256)."""
    from lerobot.policies.diffusion.configuration_diffusion import DiffusionConfig

    return DiffusionConfig(
        input_features=inp, output_features=out, n_obs_steps=2, horizon=16, n_action_steps=8,
        crop_shape=(76, 76), down_dims=(64, 128, 256), diffusion_step_embed_dim=64, spatial_softmax_num_keypoints=32,
        num_train_timesteps=100, device="cpu",
    )


INFERENCE_STEPS = int(os.environ.get("UFOPS_DP_INFERENCE_STEPS", "100"))


def load_policy(path: Path) -> Tuple[Any, Any, Any]:
    """The cached policy and its processors; the sampler runs ``--inference-steps`` DDPM steps."""
    from lerobot.policies.diffusion.modeling_diffusion import DiffusionPolicy
    from lerobot.policies.factory import make_pre_post_processors

    policy = DiffusionPolicy.from_pretrained(str(path)).eval()
    policy.diffusion.num_inference_steps = INFERENCE_STEPS
    pre, post = make_pre_post_processors(policy.config, pretrained_path=str(path))
    return policy, pre, post


# --- workers (each its own process: one torch thread, one robosuite env) -------------------------


def _worker_init() -> None:
    import torch

    torch.set_num_threads(1)


def record_worker(job: Dict[str, Any]) -> Dict[str, Any]:
    """Episodes of the scripted expert (``policy_dir`` None) or of the policy, seeds
    ``job['seeds']``, written as one LeRobot v3.0 dataset at ``job['root']``."""
    import torch
    from lerobot.datasets.lerobot_dataset import LeRobotDataset
    from lerobot.envs.utils import preprocess_observation

    from lift_task import ACTION_NAMES, CAMERA, FPS, SIZE, STATE_NAMES, Expert, LiftEnv

    _worker_init()
    video = bool(job["video"])
    features = {
        CAMERA_KEY: {"dtype": "video" if video else "image", "shape": (SIZE, SIZE, 3), "names": ["height", "width", "channels"]},
        "observation.state": {"dtype": "float32", "shape": (5,), "names": STATE_NAMES},
        "action": {"dtype": "float32", "shape": (4,), "names": ACTION_NAMES},
        "next.reward": {"dtype": "float32", "shape": (1,), "names": None},
        "next.success": {"dtype": "bool", "shape": (1,), "names": None},
        "next.done": {"dtype": "bool", "shape": (1,), "names": None},
    }
    ds = LeRobotDataset.create(job["repo_id"], FPS, features, root=job["root"], robot_type="panda", use_videos=video)
    env = LiftEnv()
    policy: Any = None
    pre: Any = None
    post: Any = None
    if job.get("policy_dir"):
        policy, pre, post = load_policy(Path(job["policy_dir"]))
    out: List[Dict[str, Any]] = []
    raw_frames: Dict[int, List[np.ndarray]] = {}  # the first few episodes' camera, as rendered (the codec gap)
    t0 = time.time()
    for seed in job["seeds"]:
        obs, _ = env.reset(seed=int(seed))
        torch.manual_seed(int(seed))
        expert = Expert(np.random.default_rng(int(seed) + 7_000_000)) if policy is None else None
        if policy is not None:
            policy.reset()
        success = False
        for t in range(env.cfg.max_steps):
            if expert is not None:
                action = expert(env)
            else:
                o = preprocess_observation(obs)
                with torch.inference_mode():
                    action = post(policy.select_action(pre(o)))[0].numpy().astype(np.float32)
            frame = {CAMERA_KEY: obs["pixels"][CAMERA], "observation.state": obs["agent_pos"], "action": action, "task": env.task}
            if video and len(out) < int(job.get("keep_raw", 0)):
                raw_frames.setdefault(int(seed), []).append(obs["pixels"][CAMERA].copy())
            obs, reward, term, trunc, info = env.step(action)
            success = bool(info["is_success"])
            frame.update({"next.reward": np.array([reward], np.float32), "next.success": np.array([success]),
                          "next.done": np.array([term or trunc])})
            ds.add_frame(frame)
            if term or trunc:
                break
        ds.save_episode()
        out.append({"seed": int(seed), "success": success, "steps": t + 1})
    ds.finalize()
    env.close()
    if raw_frames:
        np.savez_compressed(Path(job["root"]).parent / f"{Path(job['root']).name}-raw-frames.npz",
                            **{str(k): np.stack(v) for k, v in raw_frames.items()})
    return {"root": str(job["root"]), "episodes": out, "seconds": time.time() - t0}


def eval_worker(job: Dict[str, Any]) -> Dict[str, Any]:
    """One arm of one round through LeRobot's own evaluation loop: ``eval_policy_all``, what
    ``lerobot-eval`` runs, with the policy or the policy in a :class:`ufops.lerobot.SteeredPolicy`,
    on seeds ``start_seed .. start_seed + episodes - 1``. Writes what ``lerobot-eval`` writes
    (``eval_info.json``, the episode videos under ``videos/lift_0/``) and the steering telemetry
    beside them."""
    import gymnasium as gym
    import torch
    from lerobot.processor import PolicyProcessorPipeline
    from lerobot.scripts.lerobot_eval import eval_policy_all

    import ufops
    from lift_task import LiftEnv

    _worker_init()
    out_dir = Path(job["out"])
    policy, pre, post = load_policy(Path(job["policy_dir"]))
    steered = None
    log_ = None
    if job["n"] > 0:
        from ufops.lerobot import SteeredPolicy

        verifier = ufops.Verifier.from_store(job["store"], job["verifier"])
        log_ = ufops.SteeringLog()
        steered = SteeredPolicy(policy, verifier, pre, n=job["n"], policy_name=POLICY, checkpoint=job["checkpoint"],
                                log=log_)
    env = gym.vector.SyncVectorEnv([LiftEnv], autoreset_mode=gym.vector.AutoresetMode.SAME_STEP)
    identity = PolicyProcessorPipeline(steps=[])
    torch.manual_seed(job["start_seed"])
    t0 = time.time()
    with torch.no_grad():
        info = eval_policy_all(
            envs={"lift": {0: env}}, policy=steered if steered is not None else policy, env_preprocessor=identity,
            env_postprocessor=identity, preprocessor=pre, postprocessor=post, n_episodes=job["episodes"],
            max_episodes_rendered=job["episodes"], videos_dir=out_dir / "videos", start_seed=job["start_seed"],
        )
    seconds = time.time() - t0
    env.close()
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "eval_info.json").write_text(json.dumps(info, indent=2))
    if log_ is not None and len(log_):
        log_.write(ufops.sidecar_for(out_dir))
    successes = [bool(x) for x in info["per_task"][0]["metrics"]["successes"]]
    timings = [vars(t) for t in steered.timings] if steered is not None else []
    return {"out": str(out_dir), "seconds": seconds, "successes": successes,
            "seeds": [job["start_seed"] + i for i in range(len(successes))], "timings": timings}


def finished_job(job: Dict[str, Any]) -> Optional[Dict[str, Any]]:
    """What :func:`eval_worker` returned for ``job``, read back from its output folder when an
    earlier run finished it (``eval_info.json`` for these seeds, and the telemetry of a steered
    arm); None when it has to run."""
    out = Path(job["out"])
    try:
        info = json.loads((out / "eval_info.json").read_text())
        successes = [bool(x) for x in info["per_task"][0]["metrics"]["successes"]]
    except (OSError, ValueError, KeyError, IndexError):
        return None
    if len(successes) != job["episodes"] or (job["n"] > 0 and not (out / "steering.parquet").is_file()):
        return None
    return {"out": str(out), "seconds": float("nan"), "successes": successes,
            "seeds": [job["start_seed"] + i for i in range(len(successes))], "timings": []}


def latency_worker(job: Dict[str, Any]) -> Dict[str, Any]:
    """Re-plan wall times on the same recorded observations, interleaved: the unsteered policy's
    own re-plan (``predict_action_chunk``) and the steered one (encoder, sampler of N, scoring)."""
    import torch
    from lerobot.envs.utils import preprocess_observation

    import ufops
    from lift_task import LiftEnv
    from ufops.lerobot import SteeredPolicy

    torch.set_num_threads(int(job["threads"]))
    policy, pre, _ = load_policy(Path(job["policy_dir"]))
    verifier = ufops.Verifier.from_store(job["store"], job["verifier"])
    steered = SteeredPolicy(policy, verifier, pre, n=job["n"], policy_name=POLICY, checkpoint=job["checkpoint"])
    env = LiftEnv()
    plain: List[float] = []
    rng = np.random.default_rng(0)
    for rep in range(job["replans"]):
        obs, _ = env.reset(seed=900_000 + rep)
        for _ in range(int(rng.integers(0, 30))):
            obs, *_ = env.step(rng.uniform(-0.3, 0.3, 4).astype(np.float32))
        batch = pre(preprocess_observation(obs))
        with torch.inference_mode():
            policy.reset()
            t0 = time.perf_counter()
            policy.select_action(batch)  # an empty queue: one conditioning, one draw
            plain.append(time.perf_counter() - t0)
            steered.reset()
            steered.select_action(batch)
    env.close()
    return {"plain": plain, "steered": [vars(t) for t in steered.timings]}


# --- the experiment ----------------------------------------------------------------------------


def run_jobs(fn: Any, jobs: List[Dict[str, Any]], workers: int) -> List[Dict[str, Any]]:
    if workers <= 1 or len(jobs) == 1:
        return [fn(j) for j in jobs]
    ctx = mp.get_context("spawn")
    with ctx.Pool(min(workers, len(jobs)), maxtasksperchild=1) as pool:
        return list(pool.map(fn, jobs, chunksize=1))


def split_seeds(seeds: Sequence[int], parts: int) -> List[List[int]]:
    k = max(1, min(parts, len(seeds)))
    return [list(seeds[i::k]) for i in range(k)]


def train_policy(roots: List[Path], steps: int, batch_size: int, seed: int, threads: int, out: Path) -> Dict[str, Any]:
    """The DiffusionPolicy trained on the demonstration datasets (LeRobotDataset with the
    policy's delta_timestamps; the samples are decoded once and kept as uint8)."""
    import torch
    from lerobot.configs.types import FeatureType
    from lerobot.datasets.compute_stats import aggregate_stats
    from lerobot.datasets.lerobot_dataset import LeRobotDataset
    from lerobot.datasets.utils import dataset_to_policy_features
    from lerobot.policies.diffusion.modeling_diffusion import DiffusionPolicy
    from lerobot.policies.factory import make_pre_post_processors

    torch.set_num_threads(threads)
    torch.manual_seed(seed)
    metas = [LeRobotDataset(f"ufops/lift-demos-{i}", root=r).meta for i, r in enumerate(roots)]
    feats = dataset_to_policy_features(metas[0].features)
    out_f = {k: f for k, f in feats.items() if f.type is FeatureType.ACTION}
    inp = {k: f for k, f in feats.items() if f.type in (FeatureType.VISUAL, FeatureType.STATE)}
    cfg = policy_config(inp, out_f)
    stats = aggregate_stats([m.stats for m in metas])
    policy = DiffusionPolicy(cfg)
    pre, post = make_pre_post_processors(cfg, dataset_stats=stats)
    fps = metas[0].fps
    dt = {k: [i / fps for i in cfg.observation_delta_indices] for k in inp}
    dt["action"] = [i / fps for i in cfg.action_delta_indices]
    images, states, actions, pads = [], [], [], []
    t0 = time.time()
    for i, r in enumerate(roots):
        ds = LeRobotDataset(f"ufops/lift-demos-{i}", root=r, delta_timestamps=dt)
        for j in range(len(ds)):
            item = ds[j]
            images.append((item[CAMERA_KEY] * 255).round().to(torch.uint8))
            states.append(item["observation.state"])
            actions.append(item["action"])
            pads.append(item["action_is_pad"])
    img, st, act, pad = torch.stack(images), torch.stack(states), torch.stack(actions), torch.stack(pads)
    load_s = time.time() - t0
    opt = torch.optim.AdamW(policy.get_optim_params(), lr=cfg.optimizer_lr, betas=cfg.optimizer_betas,
                            eps=cfg.optimizer_eps, weight_decay=cfg.optimizer_weight_decay)
    warm = min(200, steps // 10)
    sched = torch.optim.lr_scheduler.LambdaLR(
        opt, lambda s: (s + 1) / warm if s < warm else 0.5 * (1 + math.cos(math.pi * (s - warm) / max(1, steps - warm))))
    gen = torch.Generator().manual_seed(seed)
    policy.train()
    losses: List[float] = []
    t0 = time.time()
    for step in range(steps):
        idx = torch.randint(0, len(img), (batch_size,), generator=gen)
        batch = pre({CAMERA_KEY: img[idx].float() / 255.0, "observation.state": st[idx], "action": act[idx],
                     "action_is_pad": pad[idx]})
        loss, _ = policy.forward(batch)
        opt.zero_grad()
        loss.backward()
        torch.nn.utils.clip_grad_norm_(policy.parameters(), 10.0)
        opt.step()
        sched.step()
        losses.append(float(loss))
        if step % 50 == 0 or step == steps - 1:
            log(f"   step {step}/{steps} loss {np.mean(losses[-50:]):.4f} ({time.time() - t0:.0f} s)")
    train_s = time.time() - t0
    policy.eval()
    out.mkdir(parents=True, exist_ok=True)
    policy.save_pretrained(str(out))
    pre.save_pretrained(str(out))
    post.save_pretrained(str(out))
    params = sum(p.numel() for p in policy.parameters())
    info = {"steps": steps, "batch_size": batch_size, "samples": len(img), "load_seconds": load_s,
            "train_seconds": train_s, "seconds_per_step": train_s / max(1, steps), "final_loss": float(np.mean(losses[-50:])),
            "parameters": params, "encoder_parameters": sum(p.numel() for p in policy.diffusion.rgb_encoder.parameters()),
            "threads": threads}
    (out / "training.json").write_text(json.dumps(info, indent=2))
    return info


def codec_gap(store: Any, enc: Any, parts: List[Tuple[Path, int]]) -> Dict[str, Any]:
    """Cosine similarity between the layer's rows (frames decoded from the stored AV1 video) and
    the policy's features of the same frames as rendered (what SteeredPolicy sees live), over the
    first episodes of each recorded part (``parts``: its dataset root and ingest version)."""
    eps = store.episodes(policy=POLICY)
    cos: List[float] = []
    rel: List[float] = []  # |stored - live| / |live|: cosine alone hides a shift of keypoint coordinates
    for root, version in parts:
        path = root.parent / f"{root.name}-raw-frames.npz"
        if not path.is_file():
            continue
        raw = np.load(path)
        for i, key in enumerate(raw.files):  # in recording order: episode_index i
            ids = eps.filter((eps["version_added"] == version) & (eps["source_index"] == i))["id"].to_list()
            if len(ids) != 1:
                raise RuntimeError(f"episode {i} of {root}: {len(ids)} episodes in version {version}")
            stored = np.asarray(store.steps(ids, layers=[LAYER])[f"obs.{LAYER}"].to_list(), np.float32)
            live = enc(CAMERA_KEY, raw[key])
            if len(stored) != len(live):
                raise RuntimeError(f"episode {ids[0]}: {len(stored)} stored steps, {len(live)} rendered frames")
            cos += list((stored * live).sum(1) / (np.linalg.norm(stored, axis=1) * np.linalg.norm(live, axis=1) + 1e-12))
            rel += list(np.linalg.norm(stored - live, axis=1) / (np.linalg.norm(live, axis=1) + 1e-12))
    c, r = np.asarray(cos, np.float64), np.asarray(rel, np.float64)
    if not len(c):
        return {"frames": 0, "cosine_mean": float("nan"), "cosine_p01": float("nan"), "cosine_min": float("nan"),
                "rel_l2_mean": float("nan"), "rel_l2_p99": float("nan"), "rel_l2_max": float("nan")}
    return {"frames": int(len(c)), "cosine_mean": float(c.mean()), "cosine_median": float(np.median(c)),
            "cosine_p01": float(np.quantile(c, 0.01)), "cosine_min": float(c.min()),
            "rel_l2_mean": float(r.mean()), "rel_l2_p99": float(np.quantile(r, 0.99)), "rel_l2_max": float(r.max())}


def pct(xs: Sequence[float], q: float) -> float:
    return float(np.percentile(np.asarray(xs, np.float64), q)) if len(xs) else float("nan")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="fewer rollouts and pairs, the same (cached) policy")
    ap.add_argument("--demos", type=int, default=100, help="expert demonstrations")
    ap.add_argument("--policy-steps", type=int, default=1200, help="policy training steps")
    ap.add_argument("--batch-size", type=int, default=32, help="policy training batch size")
    ap.add_argument("--inference-steps", type=int, default=20,
                    help="the policy's DDPM denoising steps at rollout time (trained with 100)")
    ap.add_argument("--rollouts", type=int, help="rollouts of the policy for the verifier (default 300; --quick 60)")
    ap.add_argument("--n", type=int, default=8, help="best-of-N candidates")
    ap.add_argument("--round", type=int, help="pairs per arm and round of the comparison (default 40; --quick 20)")
    ap.add_argument("--max-pairs", type=int, help="at most this many pairs per arm (default 120; --quick 40)")
    ap.add_argument("--latency-replans", type=int, default=40, help="re-plans timed per variant")
    ap.add_argument("--workers", type=int, default=min(2, os.cpu_count() or 1), help="processes")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--workdir", help="default: target/steer-lerobot-robosuite/<full|quick> in the repository")
    ap.add_argument("--cache", help="where trained policies are kept (default: target/steer-lerobot-robosuite/policies)")
    ap.add_argument("--ufops")
    ap.add_argument("--policy-only", action="store_true", help="stop after the policy is trained (and cached)")
    ap.add_argument("--resume", action="store_true", help="keep the work directory's store, rollouts and verifier "
                    "(state.json) and the arms' finished jobs; run what is missing")
    a = ap.parse_args()
    # Worker processes read it from the environment (they are spawned).
    os.environ["UFOPS_DP_INFERENCE_STEPS"] = str(a.inference_steps)
    global INFERENCE_STEPS
    INFERENCE_STEPS = a.inference_steps
    demos, steps = a.demos, a.policy_steps
    rollouts = a.rollouts or (60 if a.quick else 300)
    round_pairs = a.round or (20 if a.quick else 40)
    max_pairs = a.max_pairs or (40 if a.quick else 120)
    base_dir = REPO / "target" / "steer-lerobot-robosuite"
    work = Path(a.workdir) if a.workdir else base_dir / ("quick" if a.quick else "full")
    cache = Path(a.cache) if a.cache else base_dir / "policies"
    bin_ = find_ufops(a.ufops)
    data_dir = work / "store"
    cli = Cli(bin_, data_dir)
    if not (a.resume and (work / "state.json").is_file()):
        if work.exists():
            shutil.rmtree(work)
        work.mkdir(parents=True)
    else:  # the store as it was before the arms; the arms' finished jobs are kept (finished_job)
        shutil.rmtree(data_dir)
        shutil.copytree(work / "store-prepared", data_dir)
    phases = Phases()
    settings = {"demos": demos, "policy_steps": steps, "batch_size": a.batch_size, "seed": a.seed,
                "policy": "diffusion-resnet18-76-unet64", "lift": "max_steps=120"}
    key = hashlib.sha256(json.dumps(settings, sort_keys=True).encode()).hexdigest()[:12]
    policy_dir = cache / key
    checkpoint = f"steps-{steps}-{key[:6]}"
    report: Dict[str, Any] = {"settings": {**settings, "rollouts": rollouts, "n": a.n, "round": round_pairs,
                                           "max_pairs": max_pairs, "workers": a.workers, "quick": a.quick},
                              "command": " ".join([Path(sys.executable).name, *sys.argv]), "checkpoint": checkpoint}
    log(f"work directory {work}; policy cache {policy_dir}; {a.workers} worker processes")

    # 1-2. Demonstrations and the policy (cached).
    if (policy_dir / "training.json").is_file():
        training = json.loads((policy_dir / "training.json").read_text())
        training["cached"] = True
        log(f"1-2. policy from the cache ({training['steps']} steps, trained in {training['train_seconds']:.0f} s)")
    else:
        demo_dir = cache / f"{key}-demos"
        shutil.rmtree(demo_dir, ignore_errors=True)
        with phases("1 expert demonstrations"):
            jobs: List[Dict[str, Any]] = [{"repo_id": f"ufops/lift-demos-{i}", "root": str(demo_dir / f"part{i}"), "seeds": s, "video": False}
                    for i, s in enumerate(split_seeds(range(1_000_000 + a.seed * 10_000, 1_000_000 + a.seed * 10_000 + demos), a.workers))]
            recs = run_jobs(record_worker, jobs, a.workers)
        eps = [e for r in recs for e in r["episodes"]]
        log(f"1. {len(eps)} expert demonstrations ({sum(e['success'] for e in eps)} successful, "
            f"{np.mean([e['steps'] for e in eps]):.0f} steps on average) in {phases.seconds['1 expert demonstrations']:.0f} s")
        with phases("2 policy training"):
            training = train_policy([Path(r["root"]) for r in recs], steps, a.batch_size, a.seed,
                                    max(1, a.workers), policy_dir)
        training["cached"] = False
        log(f"2. DiffusionPolicy ({training['parameters']} parameters, encoder {training['encoder_parameters']}) trained "
            f"{steps} steps of {a.batch_size} in {training['train_seconds']:.0f} s ({training['seconds_per_step']:.2f} s/step)")
    report["policy_training"] = training
    if a.policy_only:
        (work / "report.json").write_text(json.dumps(report, indent=2, default=str))
        return 0

    # 3-5 are kept in state.json: --resume goes on from the arms with the same store and verifier.
    state_path = work / "state.json"
    if a.resume and state_path.is_file():
        state = json.loads(state_path.read_text())
        report.update(state["report"])
        art = state["art"]
        log(f"3-5. resumed: {report['rollouts']['episodes']} rollouts, verifier {art['id']}")
    else:
        # 3. The policy's rollouts, recorded with LeRobot's writer, into the store.
        with phases("3 policy rollouts"):
            jobs = [{"repo_id": f"ufops/lift-rollouts-{i}", "root": str(work / f"rollouts-{i}"), "seeds": s, "video": True,
                     "policy_dir": str(policy_dir), "keep_raw": 4} for i, s in enumerate(split_seeds(range(rollouts), a.workers))]
            recs = run_jobs(record_worker, jobs, a.workers)
        parts: List[Tuple[Path, int]] = []
        with phases("4 ingest"):
            cli("init")  # the store, once there is something to put in it
            for r in recs:
                ing = cli.json("ingest", r["root"], "--policy", POLICY, "--checkpoint", checkpoint, "--format", "lerobot",
                               "--run", "rollouts")
                parts.append((Path(r["root"]), int(ing["version"])))
        eps = [e for r in recs for e in r["episodes"]]
        k = sum(e["success"] for e in eps)
        log(f"3. {len(eps)} rollouts of the policy: {k} successful ({100 * k / len(eps):.1f}%), "
            f"{phases.seconds['3 policy rollouts']:.0f} s; ingested as run `rollouts`")
        report["rollouts"] = {"episodes": len(eps), "successes": k, "seconds": phases.seconds["3 policy rollouts"]}

        # 4. The layer of the policy's own encoder features, and the verifier.
        import torch

        import ufops
        from ufops.lerobot import action_space, encoder_of

        torch.set_num_threads(max(1, a.workers))
        policy, pre, _ = load_policy(policy_dir)
        store = ufops.Store(str(data_dir))
        with phases("5 features layer"):
            enc = encoder_of(policy, pre, policy_name=POLICY, checkpoint=checkpoint)
            rep = enc.compute_layers(store, batch_size=128, commit_every=64, progress=False)[LAYER]
        log(f"4. layer {LAYER}: {rep.frames} frames in {rep.seconds:.0f} s ({rep.frames_per_second:.0f} frames/s)")
        report["layer"] = {"frames": rep.frames, "seconds": rep.seconds, "producer_hash": rep.producer_hash}
        report["codec_gap"] = codec_gap(store, enc, parts)
        g = report["codec_gap"]
        log(f"   codec gap over {g['frames']} frames: cosine(features of the stored AV1 frame, of the rendered one) "
            f"mean {g['cosine_mean']:.4f}, 1% quantile {g['cosine_p01']:.4f}, min {g['cosine_min']:.4f}; relative L2 "
            f"distance mean {g['rel_l2_mean']:.4f}, 99% quantile {g['rel_l2_p99']:.4f}, max {g['rel_l2_max']:.4f}")
        with phases("6 verifier"):
            split = cli.json("split", "create", "--policy", POLICY, "--checkpoint", checkpoint, "--seed", str(a.seed))
            scale, offset = action_space(pre)
            art = cli.json("train", "--split", split["id"], "--kind", "classifier", "--obs-keys", f"{LAYER},state",
                           "--chunk-len", str(policy.config.n_action_steps), "--action-scale", *map(str, scale),
                           "--action-offset", *map(str, offset))
        final = art.get("config", {}).get("metrics", {}).get("final", {})
        sens = final.get("action_sensitivity") or {}
        verifier_info = {"id": art["id"], "val_auc": final.get("val_auc"), "action_auc": sens.get("action_auc"),
                         "obs_only_auc": sens.get("obs_only_auc"), "flagged": sens.get("flagged"),
                         "train_samples": final.get("train_samples"), "seconds": final.get("seconds"),
                         "split": {k2: split.get(k2) for k2 in ("id", "train_episodes", "val_episodes")}}
        report["verifier"] = verifier_info
        log(f"5. verifier {art['id']}: held-out AUROC {verifier_info['val_auc']}, action AUROC {verifier_info['action_auc']} "
            f"(observation-only twin {verifier_info['obs_only_auc']}), {phases.seconds['6 verifier']:.0f} s")
        del policy
        state_path.write_text(json.dumps({"report": {k: report[k] for k in (
            "rollouts", "layer", "codec_gap", "verifier")}, "art": {"id": art["id"]}}, indent=2, default=str))
        shutil.rmtree(work / "store-prepared", ignore_errors=True)
        shutil.copytree(data_dir, work / "store-prepared")

    # 5. The arms, round by round, through LeRobot's evaluation loop; compare decides.
    arm_b = f"c-bon{a.n}"
    ref = f"{POLICY}/{checkpoint}/classifier@latest"
    results: Dict[str, Dict[str, List[Any]]] = {"base": {"successes": [], "seeds": [], "timings": []},
                                                arm_b: {"successes": [], "seeds": [], "timings": []}}
    decision: Dict[str, Any] = {}
    start = 100_000 + a.seed * 10_000
    pairs = 0
    rounds = 0
    with phases("7 steering arms"):
        while pairs < max_pairs:
            m = min(round_pairs, max_pairs - pairs)
            # Each arm's seeds of the round in consecutive blocks (eval_policy seeds episode i with
            # start_seed + i), one job per block; the pool takes the jobs as workers free up.
            size = math.ceil(m / max(1, a.workers))
            jobs = [{"out": str(work / "arms" / f"{arm}-r{rounds}-p{i}"), "policy_dir": str(policy_dir), "n": n,
                     "store": str(data_dir), "verifier": ref, "checkpoint": checkpoint, "arm": arm,
                     "start_seed": start + pairs + i * size, "episodes": min(size, m - i * size)}
                    for arm, n in ((arm_b, a.n), ("base", 0)) for i in range(max(1, a.workers)) if m - i * size > 0]
            done = {i: r for i, r in ((i, finished_job(j)) for i, j in enumerate(jobs)) if r is not None}
            todo = [j for i, j in enumerate(jobs) if i not in done]
            ran = iter(run_jobs(eval_worker, todo, a.workers) if todo else [])
            res = [done[i] if i in done else next(ran) for i in range(len(jobs))]
            if done:
                log(f"   round {rounds + 1}: {len(done)} of {len(jobs)} jobs kept from an earlier run")
            for j, r in zip(jobs, res):
                results[j["arm"]]["successes"] += r["successes"]
                results[j["arm"]]["seeds"] += r["seeds"]
                results[j["arm"]]["timings"] += r["timings"]
                out = cli("ingest", r["out"], "--policy", POLICY, "--checkpoint", checkpoint, "--format", "lerobot-eval",
                          "--start-seed", str(j["start_seed"]), "--run", j["arm"],
                          *(["--steering", f"bon:{a.n}", "--run-artifact", art["id"]] if j["n"] else []))
                log(f"   {j['arm']}: {out.strip()}")
            pairs += m
            rounds += 1
            p = cli.run("compare", "--policy", POLICY, "--a", f"{checkpoint}/base", "--b", f"{checkpoint}/{arm_b}",
                        "--pair-key", "pair_key", "--format", "json", ok=(0, 1, 2))
            if not p.stdout.strip():
                sys.exit(f"ufops compare printed nothing (exit {p.returncode}):\n{p.stderr.strip()}")
            decision = json.loads(p.stdout)
            decision["exit_code"] = p.returncode
            kb, kc = sum(results["base"]["successes"]), sum(results[arm_b]["successes"])
            pooled = decision.get("pooled", {})
            log(f"6. round {rounds}: {pairs} pairs, base {kb}/{pairs}, {arm_b} {kc}/{pairs}; compare: "
                f"{pooled.get('decision')} over {pooled.get('pairs')} pairs (exit {p.returncode}), "
                f"confidence sequence {pooled.get('confidence_sequence')} ({phases.total():.0f} s so far)")
            if p.returncode in (0, 1) and decision_final(decision):
                break
    board = cli("scoreboard", "--policy", POLICY)
    report["compare"] = decision
    report["scoreboard"] = board

    # 6. Latency of a re-plan.
    with phases("8 latency"):
        lat = latency_worker({"policy_dir": str(policy_dir), "store": str(data_dir), "verifier": ref, "n": a.n,
                              "checkpoint": checkpoint, "replans": a.latency_replans, "threads": 1})
    st = lat["steered"]
    latency = {
        "threads": 1,
        "replans": a.latency_replans,
        "unsteered_total_ms": [1e3 * pct(lat["plain"], 50), 1e3 * pct(lat["plain"], 99)],
        "encode_ms": [1e3 * pct([t["encode"] for t in st], q) for q in (50, 99)],
        "sample_ms": [1e3 * pct([t["sample"] for t in st], q) for q in (50, 99)],
        "score_ms": [1e3 * pct([t["score"] for t in st], q) for q in (50, 99)],
        "total_ms": [1e3 * pct([t["total"] for t in st], q) for q in (50, 99)],
    }
    report["latency"] = latency

    # The report.
    rows = []
    kb, nb = sum(results["base"]["successes"]), len(results["base"]["successes"])
    for arm in ("base", arm_b):
        k2, n2 = sum(results[arm]["successes"]), len(results[arm]["successes"])
        lo, hi = wilson(k2, n2)
        row: Dict[str, Any] = {"arm": arm, "successes": k2, "episodes": n2, "rate": k2 / max(1, n2), "wilson95": [lo, hi]}
        if arm != "base":
            d0, d1 = newcombe(k2, n2, kb, nb)
            row.update({"delta": k2 / max(1, n2) - kb / max(1, nb), "newcombe95": [d0, d1]})
        rows.append(row)
    report["rows"] = rows
    report["phases_seconds"] = phases.seconds
    report["total_seconds"] = time.time() - phases.start
    md = render(report, arm_b)
    (work / "report.json").write_text(json.dumps(report, indent=2, default=str))
    (work / "report.md").write_text(md)
    log("")
    log(md)
    log(f"report: {work / 'report.md'}; store: {data_dir}")
    return 0


def decision_final(decision: Dict[str, Any]) -> bool:
    d = decision.get("pooled", decision)
    return str(d.get("decision", "")) in ("better", "worse", "not_worse", "no_practical_difference")


def render(r: Dict[str, Any], arm_b: str) -> str:
    lines = ["| arm | success | 95% CI (Wilson) | Δ to base | 95% CI of Δ (Newcombe) |", "|---|---|---|---|---|"]
    for row in r["rows"]:
        lo, hi = row["wilson95"]
        d = f"{100 * row['delta']:+.1f} pp" if "delta" in row else "-"
        nc = f"[{100 * row['newcombe95'][0]:+.1f}, {100 * row['newcombe95'][1]:+.1f}]" if "delta" in row else "-"
        lines.append(f"| {row['arm']} | {row['successes']}/{row['episodes']} = {100 * row['rate']:.1f}% | "
                     f"[{100 * lo:.1f}, {100 * hi:.1f}] | {d} | {nc} |")
    v = r["verifier"]
    lines += ["", f"verifier {v['id']}: held-out AUROC {v['val_auc']}, action AUROC {v['action_auc']}, "
              f"observation-only twin {v['obs_only_auc']}", "",
              "compare (pooled): " + json.dumps({k: r["compare"].get("pooled", {}).get(k) for k in (
                  "decision", "decided_at_pairs", "pairs", "rate_a", "rate_b", "confidence_sequence", "pair_table")})
              + f", pairing {r['compare'].get('pairing')}, exit {r['compare'].get('exit_code')}",
              "", "latency per re-plan (ms, p50 / p99): " + json.dumps(r["latency"]), "",
              "phases: " + ", ".join(f"{k} {v2:.0f} s" for k, v2 in r["phases_seconds"].items()) + f"; total {r['total_seconds']:.0f} s",
              "", "policy training: " + json.dumps(r["policy_training"])]
    return "\n".join(lines)


if __name__ == "__main__":
    sys.exit(main())
