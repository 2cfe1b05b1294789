#!/usr/bin/env python3
"""The paper's loop from Python, end to end, on the 2-D two-gap task (examples/python/nav_task.py,
a port of the `sim` crate):

1. a small PyTorch DDPM chunk policy is trained on expert demonstrations;
2. it is rolled out (with test-time noise) and the rollouts are written as a LeRobot v2.1
   dataset (`next.success` labels) and ingested with `ufops ingest`;
3. `ufops serve` + `ufops worker` run: a split and a classifier training job go through the API's
   job queue, and the verifier is pulled by alias with `ufops.Verifier.from_server`;
4. fresh rollouts of the unchanged policy, unsteered, with best-of-N (Algorithm 1, through
   `ufops.torch.best_of_n`) and with classifier guidance (Algorithm 2 on x̂0, through
   `ufops.torch.ddpm_guidance` in the sampler loop), with Wilson 95% intervals;
5. the fresh unsteered rollouts are ingested too, and `ufops monitor calibrate` turns the
   verifier into a failure alarm at a stated false-alarm rate (α = 0.1), calibrated on half of the
   successes the verifier did not train on and measured on the other half and on the failures.

    python3 examples/python/steer_torch_policy.py [--episodes 500] [--quick] [--ufops PATH] [--workdir DIR]

Needs the `ufops` binary (`cargo build --bin ufops`; found in $CARGO_TARGET_DIR/debug like the
tests do, or --ufops), the `ufops` package (`pip install ./clients/python`) and torch.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
import urllib.request
from pathlib import Path
from typing import Any, Dict, List, Optional

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
import ufops  # noqa: E402
import ufops.torch as ut  # noqa: E402
from nav_task import ChunkPolicy, Episode, NavConfig, expert_demos, rollout, wilson  # noqa: E402

REPO = Path(__file__).resolve().parents[2]
POLICY, CHECKPOINT = "py-dp", "base"


def log(msg: str) -> None:
    print(msg, flush=True)


def find_ufops(explicit: Optional[str]) -> Path:
    target = os.environ.get("CARGO_TARGET_DIR") or str(Path.home() / ".cache" / "ufops-target")
    for c in [explicit, os.environ.get("UFOPS_BIN"), f"{target}/debug/ufops", str(REPO / "target/debug/ufops")]:
        if c and Path(c).is_file():
            return Path(c)
    sys.exit("the ufops binary is needed: cargo build --bin ufops (or pass --ufops PATH)")


def write_lerobot(eps: List[Episode], root: Path, fps: int = 10) -> None:
    """The rollouts as a LeRobot v2.1 dataset: observation.pos, action, next.success/reward/done."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    (root / "meta").mkdir(parents=True)
    data = root / "data" / "chunk-000"
    data.mkdir(parents=True)
    vec = pa.list_(pa.float32(), 2)
    index = 0
    with open(root / "meta" / "episodes.jsonl", "w") as f:
        for i, e in enumerate(eps):
            n = len(e.actions)
            done = np.zeros(n, bool)
            done[-1] = True
            success = done & e.success
            table = pa.table({
                "observation.pos": pa.array([p.astype(np.float32).tolist() for p in e.positions[:n]], vec),
                "action": pa.array([a.astype(np.float32).tolist() for a in e.actions], vec),
                "timestamp": pa.array(np.arange(n, dtype=np.float32) / fps),
                "frame_index": pa.array(np.arange(n, dtype=np.int64)),
                "episode_index": pa.array(np.full(n, i, dtype=np.int64)),
                "index": pa.array(np.arange(index, index + n, dtype=np.int64)),
                "task_index": pa.array(np.zeros(n, dtype=np.int64)),
                "next.reward": pa.array(success.astype(np.float32)),
                "next.done": pa.array(done),
                "next.success": pa.array(success),
            })
            pq.write_table(table, data / f"episode_{i:06d}.parquet")
            index += n
            f.write(json.dumps({"episode_index": i, "tasks": ["two-gap navigation"], "length": n}) + "\n")
    (root / "meta" / "tasks.jsonl").write_text(json.dumps({"task_index": 0, "task": "two-gap navigation"}) + "\n")
    feat = lambda dtype, shape, names=None: {"dtype": dtype, "shape": shape, "names": names}  # noqa: E731
    info = {
        "codebase_version": "v2.1", "robot_type": "point_2d", "total_episodes": len(eps), "total_frames": index,
        "total_tasks": 1, "total_videos": 0, "total_chunks": 1, "chunks_size": 1000, "fps": fps,
        "splits": {"train": f"0:{len(eps)}"},
        "data_path": "data/chunk-{episode_chunk:03d}/episode_{episode_index:06d}.parquet", "video_path": None,
        "features": {
            "observation.pos": feat("float32", [2], ["x", "y"]), "action": feat("float32", [2], ["vx", "vy"]),
            "timestamp": feat("float32", [1]), "frame_index": feat("int64", [1]), "episode_index": feat("int64", [1]),
            "index": feat("int64", [1]), "task_index": feat("int64", [1]), "next.reward": feat("float32", [1]),
            "next.done": feat("bool", [1]), "next.success": feat("bool", [1]),
        },
    }
    (root / "meta" / "info.json").write_text(json.dumps(info, indent=2))


class Api:
    def __init__(self, url: str, token: str) -> None:
        self.url, self.token = url, token

    def call(self, method: str, path: str, body: Optional[Dict[str, Any]] = None) -> Any:
        req = urllib.request.Request(self.url + path, method=method,
                                     data=None if body is None else json.dumps(body).encode())
        req.add_header("Authorization", f"Bearer {self.token}")
        req.add_header("Content-Type", "application/json")
        with urllib.request.urlopen(req, timeout=60) as r:
            return json.loads(r.read())


def train_verifier_through_the_api(bin_: Path, data_dir: Path, epochs: int, max_speed: float,
                                   chunk_len: int) -> ufops.Verifier:
    run = lambda *a: subprocess.run([str(bin_), "--data-dir", str(data_dir), *a], check=True,  # noqa: E731
                                    capture_output=True, text=True).stdout
    token = json.loads(run("token", "create", "--name", "example", "--role", "trainer", "--json"))["token"]
    serve = subprocess.Popen([str(bin_), "--data-dir", str(data_dir), "serve", "--addr", "127.0.0.1:0", "--no-worker"],
                             stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    worker = subprocess.Popen([str(bin_), "--data-dir", str(data_dir), "worker", "--id", "example-worker"],
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        assert serve.stdout is not None
        url = serve.stdout.readline().split()[-1]
        api = Api(url, token)
        for _ in range(100):
            try:
                urllib.request.urlopen(url + "/healthz", timeout=2)
                break
            except OSError:
                time.sleep(0.1)
        split = api.call("POST", "/v1/splits", {"policy": POLICY, "checkpoint": CHECKPOINT, "seed": 0})
        log(f"split {split['id']}: {split['train_episodes']} train / {split['val_episodes']} val episodes")
        config = {"epochs": epochs, "action_space": {"space": "policy", "scale": [max_speed] * 2, "offset": [0.0, 0.0]}}
        job = api.call("POST", "/v1/jobs", {"split_id": split["id"], "kind": "classifier", "chunk_len": chunk_len,
                                        "config": config})
        log(f"job {job['id']} queued; `ufops worker` trains it")
        t0 = time.time()
        while job["state"] in ("queued", "running"):
            time.sleep(0.5)
            job = api.call("GET", f"/v1/jobs/{job['id']}")
        if job["state"] != "succeeded":
            sys.exit(f"training job {job['state']}: {job.get('error')}")
        log(f"job {job['state']} in {time.time() - t0:.0f} s")
        return ufops.Verifier.from_server(url, f"{POLICY}/{CHECKPOINT}/classifier@latest", token)
    finally:
        for p in (worker, serve):
            p.terminate()
            p.wait(timeout=10)


def report(name: str, eps: List[Episode], base: Optional[float] = None) -> float:
    k, n = sum(e.success for e in eps), len(eps)
    lo, hi = wilson(k, n)
    delta = "" if base is None else f"   {100 * (k / n - base):+5.1f} pp vs base"
    log(f"  {name:<28} {k:>4}/{n} = {100 * k / n:5.1f}%   95% CI [{100 * lo:5.1f}, {100 * hi:5.1f}]{delta}")
    return k / n


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--episodes", type=int, default=500, help="rollouts per evaluated method (and for training)")
    ap.add_argument("--bon", type=int, default=10)
    ap.add_argument("--lam", type=float, default=3.0)
    ap.add_argument("--quick", action="store_true", help="a small run (the pytest's): fewer demos, steps, epochs")
    ap.add_argument("--ufops")
    ap.add_argument("--workdir")
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args()
    torch.set_num_threads(1)
    torch.manual_seed(a.seed)
    bin_ = find_ufops(a.ufops)
    work = Path(a.workdir) if a.workdir else Path(tempfile.mkdtemp(prefix="ufops-example-"))
    data_dir = work / "store"
    cfg = NavConfig()

    t0 = time.time()
    demos = expert_demos(cfg, 60 if a.quick else 100, a.seed)
    policy = ChunkPolicy(cfg)
    policy.fit(demos, 800 if a.quick else 1500, seed=a.seed, log=log)
    log(f"1. DDPM policy trained on {len(demos)} expert demonstrations ({time.time() - t0:.0f} s)")

    train_eps = rollout(policy, a.episodes, seed=a.seed + 1)
    write_lerobot(train_eps, work / "rollouts")
    subprocess.run([str(bin_), "--data-dir", str(data_dir), "init"], check=True, capture_output=True)
    out = subprocess.run([str(bin_), "--data-dir", str(data_dir), "ingest", str(work / "rollouts"), "--policy", POLICY,
                          "--checkpoint", CHECKPOINT, "--format", "lerobot"], check=True, capture_output=True, text=True)
    log(f"2. {len(train_eps)} rollouts ({sum(e.success for e in train_eps)} successes) ingested: "
        f"{out.stdout.strip().splitlines()[-1] if out.stdout.strip() else 'ok'}")

    v = train_verifier_through_the_api(bin_, data_dir, 40 if a.quick else 200, cfg.max_speed, policy.horizon)
    log(f"3. verifier {v.id} ({v.kind}, obs {v.obs_dim}, chunk {v.chunk_len} x {v.action_dim}) pulled from the API")
    assert v.chunk_len == policy.horizon and v.takes_policy_space

    seed = a.seed + 1000  # fresh starts and noise, the same for every method
    log(f"4. {a.episodes} fresh rollouts per method:")
    fresh = rollout(policy, a.episodes, seed)
    base = report("base (DDPM)", fresh)

    def bon(obs: np.ndarray, t: int, gen: torch.Generator) -> torch.Tensor:
        o = torch.from_numpy(obs)
        cands = policy.sample(o.repeat_interleave(a.bon, 0), gen).view(len(obs), a.bon, -1)
        best, _ = ut.best_of_n(v, lambda n: cands, obs, a.bon, t=t)
        return best

    bon_rate = report(f"best-of-{a.bon} (Algorithm 1)", rollout(policy, a.episodes, seed, bon), base)

    def guided(obs: np.ndarray, t: int, gen: torch.Generator) -> torch.Tensor:
        hook = ut.ddpm_guidance(v, obs, policy.sched.alphas_cumprod, lam=a.lam, t=t)
        return policy.sample(torch.from_numpy(obs), gen, hook=hook)

    report(f"guidance λ={a.lam:g} (Algorithm 2)", rollout(policy, a.episodes, seed, guided), base)
    # 5. A failure alarm: the fresh base rollouts join the store, the monitor is calibrated on the
    # successes the verifier did not train on (half of them; the other half measure it).
    write_lerobot(fresh, work / "fresh")
    subprocess.run([str(bin_), "--data-dir", str(data_dir), "ingest", str(work / "fresh"), "--policy", POLICY,
                    "--checkpoint", CHECKPOINT, "--format", "lerobot", "--run", "fresh-base"],
                   check=True, capture_output=True, text=True)
    m = json.loads(subprocess.run(
        [str(bin_), "--data-dir", str(data_dir), "monitor", "calibrate", "--artifact",
         f"{POLICY}/{CHECKPOINT}/classifier@latest", "--alpha", "0.1", "--json"],
        check=True, capture_output=True, text=True).stdout)
    e = m["evaluation"]
    fa_lo, fa_hi = e["false_alarm_interval"]
    log(f"5. monitor {m['id']} at alpha 0.1 (threshold {m['threshold']:.3f}): false alarms on held-out successes "
        f"{e['false_alarms']}/{e['successes']} = {100 * e['false_alarm_rate']:.1f}% [{100 * fa_lo:.1f}, {100 * fa_hi:.1f}], "
        f"failures caught {e['detected']}/{e['failures']}, median lead {e['lead_steps_median']} steps")
    lift = 100 * (bon_rate - base)
    log(f"best-of-{a.bon} lifts success by {lift:+.1f} pp (goal: >= +15 pp); total {time.time() - t0:.0f} s; "
        f"store in {data_dir}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
