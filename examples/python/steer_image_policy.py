#!/usr/bin/env python3
"""The second demo: a camera policy steered by a verifier that sees through the policy's own
encoder. The 2-D two-gap task (examples/python/nav_task.py) rendered as 64x64 RGB pictures
(examples/python/image_nav.py), end to end:

1. a PyTorch DDPM chunk policy that sees only the camera, through a small CNN trained end to end
   with it from random weights, is trained on expert demonstrations;
2. its noisy rollouts are recorded as a LeRobot v3.0 dataset (AV1 mp4 of
   `observation.images.top`, `action`, `next.success`/`next.reward`/`next.done`) and ingested as
   run `base` (`ufops ingest --run base`);
3. the policy encoder's features of every stored frame, decoded from the mp4, become the layer
   `features.nav-cnn` (`ufops.features.compute_layer`, producer = the encoder's weights);
4. `ufops split create` + `ufops train --obs-keys features.nav-cnn`: a success classifier on the
   encoder's features (never the agent's position) and the policy's action chunks;
5. the unchanged policy is steered with best-of-N (`ufops.torch.best_of_n`), the verifier's
   observation row built by `ufops.torch.CameraObservation` (the encoder runs once per control
   step for all N candidates); the steered rollouts are recorded and ingested as runs
   `c-bon10` / `c-bon30` for `ufops scoreboard`.

    python3 examples/python/steer_image_policy.py [--quick] [--episodes N] [--workdir DIR] [--ufops PATH]

Needs the `ufops` binary (`cargo build --bin ufops`; $UFOPS_BIN or $CARGO_TARGET_DIR/debug/ufops
like the tests, or --ufops), the `ufops` package (`pip install ./clients/python`), torch, av
(PyAV) and polars. Prints a results table and the time of each phase; writes report.json in
the work directory.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from collections import Counter
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Dict, Iterator, List, Optional

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
import ufops  # noqa: E402
import ufops.torch as ut  # noqa: E402
from ufops.features import FrameReader, compute_layer, encode_frames, producer_of  # noqa: E402

from image_nav import (  # noqa: E402
    ENCODER_NAME, Camera, Episode, ImagePolicy, clip_speed, newcombe, preprocess, rollout, wilson,
    write_lerobot_v30,
)
from nav_task import NavConfig, expert_demos  # noqa: E402

REPO = Path(__file__).resolve().parents[2]
POLICY, CHECKPOINT = "nav-img", "base"
LAYER, CAMERA = "features.nav-cnn", "observation.images.top"


def log(msg: str) -> None:
    print(msg, flush=True)


def find_ufops(explicit: Optional[str]) -> Path:
    target = os.environ.get("CARGO_TARGET_DIR") or str(Path.home() / ".cache" / "ufops-target")
    for c in [explicit, os.environ.get("UFOPS_BIN"), f"{target}/debug/ufops", str(REPO / "target/debug/ufops")]:
        if c and Path(c).is_file():
            return Path(c)
    sys.exit("the ufops binary is needed: cargo build --bin ufops (or pass --ufops PATH)")


class Phases:
    """Wall time of each phase, in order."""

    def __init__(self) -> None:
        self.seconds: Dict[str, float] = {}
        self.start = time.time()

    @contextmanager
    def __call__(self, name: str) -> Iterator[None]:
        t0 = time.time()
        try:
            yield
        finally:
            self.seconds[name] = self.seconds.get(name, 0.0) + time.time() - t0

    def total(self) -> float:
        return time.time() - self.start


class Cli:
    def __init__(self, bin_: Path, data_dir: Path) -> None:
        self.bin, self.data_dir = bin_, data_dir

    def __call__(self, *args: str) -> str:
        p = subprocess.run([str(self.bin), "--data-dir", str(self.data_dir), *args], capture_output=True, text=True)
        if p.returncode != 0:
            sys.exit(f"ufops {' '.join(args)} failed ({p.returncode}):\n{p.stderr.strip()}")
        return p.stdout

    def json(self, *args: str) -> Any:
        return json.loads(self(*args, "--json"))


def summary(name: str, eps: List[Episode], cfg: NavConfig) -> Dict[str, Any]:
    k, n = sum(e.success for e in eps), len(eps)
    lo, hi = wilson(k, n)
    gaps = Counter(e.gap(cfg) for e in eps)
    outcomes = Counter(e.outcome for e in eps)
    return {"method": name, "successes": k, "episodes": n, "rate": k / n, "wilson95": [lo, hi],
            "wide_gap": gaps.get("wide", 0), "narrow_gap": gaps.get("narrow", 0),
            "collisions": outcomes.get("wall", 0), "timeouts": outcomes.get("timeout", 0),
            "mean_length": float(np.mean([len(e.actions) for e in eps]))}


def codec_gap(store: ufops.Store, ids: List[str], policy: ImagePolicy, camera: Camera) -> Dict[str, Any]:
    """Cosine similarity between the layer's features (frames decoded from the stored AV1 mp4)
    and the encoder's features of the same states rendered raw, as the robot's camera sees them."""
    steps = store.steps(ids, layers=[LAYER])
    state_col = next(c for c in steps.columns if c.startswith("obs.") and c.endswith("state"))
    stored = np.asarray(steps[f"obs.{LAYER}"].to_list(), np.float32)
    pos = np.asarray(steps[state_col].to_list(), np.float32)
    raw_frames = camera.render(pos)
    raw = encode_frames(policy.encoder, raw_frames, preprocess=preprocess)
    cos = (stored * raw).sum(1) / (np.linalg.norm(stored, axis=1) * np.linalg.norm(raw, axis=1) + 1e-12)
    rel = np.linalg.norm(stored - raw, axis=1) / (np.linalg.norm(raw, axis=1) + 1e-12)
    first = steps["t"].to_numpy() == 0
    with FrameReader(store, CAMERA) as reader:
        decoded = np.stack([f for i in ids for f in reader.frames(store.steps([i]))])
    mse = ((decoded.astype(np.float64) - raw_frames) ** 2).mean()
    return {"episodes": len(ids), "frames": int(len(cos)), "cosine_mean": float(cos.mean()),
            "cosine_median": float(np.median(cos)), "cosine_p01": float(np.quantile(cos, 0.01)),
            "cosine_min": float(cos.min()), "cosine_mean_first_frames": float(cos[first].mean()),
            "cosine_mean_other_frames": float(cos[~first].mean()), "relative_l2_mean": float(rel.mean()),
            "pixel_mae": float(np.abs(decoded.astype(np.float64) - raw_frames).mean()),
            "psnr_db": float(10 * np.log10(255.0**2 / mse))}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--episodes", type=int, help="rollouts of the base policy (the verifier's data) and per "
                    "steered method (default 1000; --quick 200)")
    ap.add_argument("--bon", default="10,30", help="best-of-N sizes, comma-separated")
    ap.add_argument("--demos", type=int, help="expert demonstrations (default 100)")
    ap.add_argument("--policy-iters", type=int, help="policy training steps (default 600; --quick 300)")
    ap.add_argument("--config", help="a training recipe for `ufops train --config` (default: none, the "
                    "paper's image recipe for a features layer)")
    ap.add_argument("--quick", action="store_true", help="a small run (~3-4 minutes): fewer rollouts and steps")
    ap.add_argument("--threads", type=int, default=min(2, os.cpu_count() or 1), help="torch threads")
    ap.add_argument("--ufops")
    ap.add_argument("--workdir")
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args()
    episodes = a.episodes or (200 if a.quick else 1000)
    demos_n = a.demos or 100
    iters = a.policy_iters or (300 if a.quick else 600)
    sizes = [int(x) for x in a.bon.split(",") if x]
    torch.set_num_threads(max(1, a.threads))
    torch.manual_seed(a.seed)
    bin_ = find_ufops(a.ufops)
    work = Path(a.workdir) if a.workdir else Path(tempfile.mkdtemp(prefix="ufops-image-"))
    work.mkdir(parents=True, exist_ok=True)
    data_dir = work / "store"
    if data_dir.exists():
        sys.exit(f"{data_dir} exists: give a fresh --workdir")
    cli = Cli(bin_, data_dir)
    cfg = NavConfig()
    camera = Camera(cfg)
    phases = Phases()
    report: Dict[str, Any] = {"settings": {"episodes": episodes, "demos": demos_n, "policy_iters": iters,
                                           "bon": sizes, "quick": a.quick, "threads": a.threads, "seed": a.seed}}
    log(f"work directory {work}; {episodes} rollouts per method; torch threads {a.threads}")

    # 1. The camera policy, trained end to end from pixels.
    with phases("1 policy training"):
        demos = expert_demos(cfg, demos_n, a.seed)
        policy = ImagePolicy(cfg)
        policy.fit(demos, camera, iters, seed=a.seed, log=log)
        torch.save(policy.state_dict(), work / "policy.pt")
    n_params = sum(p.numel() for p in policy.parameters())
    n_enc = sum(p.numel() for p in policy.encoder.parameters())
    log(f"1. image DDPM policy ({n_params} parameters, encoder {n_enc}) trained on {len(demos)} demonstrations "
        f"({phases.seconds['1 policy training']:.0f} s)")

    # 2. Base rollouts -> LeRobot v3.0 -> the store (run `base`).
    with phases("2 base rollouts"):
        base_eps = rollout(policy, camera, episodes, seed=a.seed + 1)
    with phases("3 record + ingest"):
        ds = write_lerobot_v30(base_eps, work / "rollouts-base", camera)
        cli("init")
        ing = cli.json("ingest", str(work / "rollouts-base"), "--policy", POLICY, "--checkpoint", CHECKPOINT,
                       "--format", "lerobot", "--run", "base")
    base = summary("base (DDPM, camera)", base_eps, cfg)
    log(f"2. {episodes} base rollouts ({base['successes']} successes), {ds['frames']} frames, "
        f"{ds['video_bytes'] / 1e6:.1f} MB of AV1; ingested as run base: version {ing['version']}, "
        f"{ing['episodes']} episodes, {ing['steps']} steps ({phases.seconds['3 record + ingest']:.0f} s)")

    # 3. The policy encoder's features of every stored frame, decoded from the mp4.
    store = ufops.Store(str(data_dir))
    producer = producer_of(policy.encoder, encoder=ENCODER_NAME, policy=POLICY, checkpoint=CHECKPOINT)
    with phases("4 features layer"):
        rep = compute_layer(store, policy.encoder, name=LAYER, camera=CAMERA, producer=producer,
                            preprocess=preprocess, batch_size=256, commit_every=256, progress=False)
    log(f"3. layer {LAYER}: {rep.frames} frames of {rep.episodes_written} episodes in {rep.seconds:.1f} s "
        f"({rep.frames_per_second:.0f} frames/s), producer {rep.producer_hash[:12]}")
    sample_ids = store.episodes(policy=POLICY)["id"].to_list()[:50]
    gap = codec_gap(store, sample_ids, policy, camera)
    log(f"   codec gap over {gap['frames']} frames of {gap['episodes']} episodes: cosine(features of the decoded "
        f"frame, of the raw one) mean {gap['cosine_mean']:.4f}, median {gap['cosine_median']:.4f}, "
        f"1% quantile {gap['cosine_p01']:.3f}, min {gap['cosine_min']:.3f} (episodes' first frames: mean "
        f"{gap['cosine_mean_first_frames']:.3f}); relative L2 {gap['relative_l2_mean']:.3f}; pixels: MAE "
        f"{gap['pixel_mae']:.2f} / 255, PSNR {gap['psnr_db']:.1f} dB")

    # 4. Split and verifier training on the layer.
    h = policy.n_exec
    with phases("5 split + verifier training"):
        split = cli.json("split", "create", "--policy", POLICY, "--checkpoint", CHECKPOINT, "--seed", str(a.seed))
        train_args = ["train", "--split", split["id"], "--kind", "classifier", "--obs-keys", LAYER,
                      "--chunk-len", str(h), "--step-stride", str(h),
                      "--action-scale", str(cfg.max_speed), str(cfg.max_speed)]
        if a.config:
            train_args += ["--config", a.config]
        art = cli.json(*train_args)
    final = art.get("config", {}).get("metrics", {}).get("final", {})
    metrics = {k: final.get(k) for k in ("val_auc", "best_val_loss", "best_epoch", "epochs_run", "train_samples",
                                         "train_positive_fraction", "seconds", "backend")}
    metrics["val_accuracy"] = (final.get("val_calibration") or {}).get("accuracy")
    # How much of that AUC the action chunk earns (the trainer's observation-only twin).
    sensitivity = final.get("action_sensitivity") or {}
    metrics["action_auc"] = sensitivity.get("action_auc")
    metrics["obs_only_auc"] = sensitivity.get("obs_only_auc")
    metrics["steering_flagged"] = sensitivity.get("flagged")
    log(f"4. split {split['id']} ({split['train_episodes']} train / {split['val_episodes']} val episodes); "
        f"verifier {art['id']}: val AUC {metrics['val_auc']:.3f}, val accuracy {metrics['val_accuracy']:.3f}, "
        f"action AUC {sensitivity.get('action_auc') or float('nan'):.3f} "
        f"(obs-only twin {sensitivity.get('obs_only_auc') or float('nan'):.3f}"
        f"{', FLAGGED' if sensitivity.get('flagged') else ''}), "
        f"{metrics['train_samples']} samples, {metrics['seconds']:.1f} s")
    verifier = ufops.Verifier.from_store(store, f"{POLICY}/{CHECKPOINT}/classifier@latest")
    assert verifier.chunk_len == h and verifier.takes_policy_space, (verifier.chunk_len, verifier.takes_policy_space)

    def encode(frames: np.ndarray) -> np.ndarray:
        return encode_frames(policy.encoder, frames, preprocess=preprocess)

    # A verifier is bound to the encoder whose features it learned: another producer is refused.
    try:
        ut.CameraObservation(verifier, {LAYER: (encode, "0" * 64)})
        refused = False
    except ValueError:
        refused = True
    log(f"   CameraObservation with another encoder's producer hash: {'refused' if refused else 'NOT refused'}")

    # 5. Best-of-N on fresh rollouts of the unchanged policy.
    def best_of(n: int) -> Any:
        cams: Dict[int, ut.CameraObservation] = {}

        def choose(frames: np.ndarray, idx: np.ndarray, step: int, gen: torch.Generator) -> torch.Tensor:
            cond = policy.features(frames)  # the policy's own encoding of its frames
            rows = []
            for r, i in enumerate(idx):
                cam = cams.get(int(i))
                if cam is None:
                    cam = cams[int(i)] = ut.CameraObservation(verifier, {LAYER: (encode, rep.producer_hash)})
                # The verifier's history: the last obs_history frames (the policy keeps t_o of them).
                cam.reset()
                for f in frames[r, frames.shape[1] - cam.history:]:
                    row = cam.observe({LAYER: f})
                rows.append(row)
            cands = policy.sample(cond.repeat_interleave(n, 0), gen).view(len(idx), n, policy.horizon, 2)
            cands = clip_speed(cands[:, :, :h])  # what will be executed: the first n_exec steps
            best, _ = ut.best_of_n(verifier, lambda _n: cands, np.stack(rows), n, t=step)
            return best

        return choose

    seed = a.seed + 1000  # fresh starts and noise, the same for every steered method
    rows = [base]
    runs: Dict[int, List[Episode]] = {}
    for n in sizes:
        with phases(f"6 best-of-{n} rollouts"):
            runs[n] = rollout(policy, camera, episodes, seed, best_of(n))
        s = summary(f"C x BoN (N={n})", runs[n], cfg)
        lo, hi = newcombe(s["successes"], s["episodes"], base["successes"], base["episodes"])
        s["delta"], s["newcombe95"] = s["rate"] - base["rate"], [lo, hi]
        rows.append(s)
        log(f"5. best-of-{n}: {s['successes']}/{s['episodes']} ({phases.seconds[f'6 best-of-{n} rollouts']:.0f} s)")

    with phases("7 record + ingest steered"):
        for n, eps in runs.items():
            write_lerobot_v30(eps, work / f"rollouts-bon{n}", camera)
            cli("ingest", str(work / f"rollouts-bon{n}"), "--policy", POLICY, "--checkpoint", CHECKPOINT,
                "--format", "lerobot", "--run", f"c-bon{n}", "--steering", f"bon:{n}", "--run-artifact", art["id"])
        board = cli("scoreboard", "--policy", POLICY)

    # The report.
    log("")
    log("| method | verifier | success | 95% CI (Wilson) | Δ to base | 95% CI of Δ (Newcombe) | wide / narrow gap | collisions / timeouts |")
    log("|---|---|---|---|---|---|---|---|")
    for s in rows:
        lo, hi = s["wilson95"]
        if "delta" in s:
            d = f"{100 * s['delta']:+.1f} pp"
            nc = f"[{100 * s['newcombe95'][0]:+.1f}, {100 * s['newcombe95'][1]:+.1f}]"
            ver = f"classifier on {LAYER}"
        else:
            d = nc = ver = "-"
        log(f"| {s['method']} | {ver} | {s['successes']}/{s['episodes']} = {100 * s['rate']:.1f}% | "
            f"[{100 * lo:.1f}, {100 * hi:.1f}] | {d} | {nc} | {s['wide_gap']} / {s['narrow_gap']} | "
            f"{s['collisions']} / {s['timeouts']} |")
    log("")
    log(f"ufops scoreboard --policy {POLICY}:")
    log(board.rstrip())
    log("")
    total = phases.total()
    for name, sec in phases.seconds.items():
        log(f"  {name:<30} {sec:7.1f} s")
    log(f"  {'total':<30} {total:7.1f} s")
    best = max(rows[1:], key=lambda s: s["delta"]) if len(rows) > 1 else None
    if best is not None:
        ok = best["delta"] >= 0.15 and best["newcombe95"][0] > 0
        log(f"{best['method']} lifts the camera policy by {100 * best['delta']:+.1f} pp "
            f"(Newcombe 95% [{100 * best['newcombe95'][0]:+.1f}, {100 * best['newcombe95'][1]:+.1f}]); "
            f"goal >= +15 pp with the interval above 0: {'met' if ok else 'NOT met'}; total {total:.0f} s")
    report.update({
        "rows": rows, "codec_gap": gap, "layer": {"name": LAYER, "producer": producer.to_dict(),
                                                 "producer_hash": rep.producer_hash, "frames": rep.frames,
                                                 "seconds": rep.seconds},
        "split": split, "artifact": {"id": art["id"], "metrics": metrics}, "wrong_producer_refused": refused,
        "dataset": ds, "phases_seconds": phases.seconds, "total_seconds": total, "scoreboard": board,
        "store": str(data_dir),
    })
    (work / "report.json").write_text(json.dumps(report, indent=2, default=str))
    log(f"report: {work / 'report.json'}; store: {data_dir}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
