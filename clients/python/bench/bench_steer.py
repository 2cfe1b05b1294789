#!/usr/bin/env python3
"""Steering latency from Python at the paper's Square dimensions (obs 46, chunk 16 x 10, lowdim:
encoders 64, t-embedding 64, trunk 128 -> 64), one thread, random weights, with the PyTorch eager
peer (bench/reference/torch_verifier_epoch.py's model) measured in the same run:

* BoN(10) score: ``Verifier.score`` of 10 candidates for one observation + argmax;
* CG gradient: ``Verifier.grad`` of one chunk (d log C / d chunk);
* ensemble cost: best-of-30 with an ensemble of K = 5 (``Verifier.pick``: the members' scores,
  the pessimistic pick, the fall-back) against the same with one verifier, in the same run.

Times include the Python call overhead (array checks, GIL release, the result array). Goals:
BoN(10) p50 <= 20 us, CG gradient p50 <= 15 us, ensemble BoN(30) p50 <= 3x the one verifier's.

    python3 clients/python/bench/bench_steer.py [--iters 20000] [--no-torch] [--members 5]

It needs the package built with its ``testing`` feature (``write_random_artifact``):
``MATURIN_PEP517_ARGS="--features testing" pip install ./clients/python``.
"""
from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path
from typing import Callable, Tuple

import numpy as np

os.environ.setdefault("OMP_NUM_THREADS", "1")
import ufops  # noqa: E402
from ufops import _ufops  # noqa: E402

REPO = Path(__file__).resolve().parents[3]


def measure(iters: int, f: Callable[[], object]) -> Tuple[float, float]:
    for _ in range(iters // 10 + 50):
        f()
    ts = np.empty(iters)
    clock = time.perf_counter_ns
    for i in range(iters):
        t0 = clock()
        f()
        ts[i] = clock() - t0
    ts.sort()
    return ts[iters // 2] / 1e3, ts[iters * 99 // 100] / 1e3


def torch_peer(iters: int) -> Tuple[Tuple[float, float], Tuple[float, float]]:
    import torch

    sys.path.insert(0, str(REPO / "bench" / "reference"))
    from torch_verifier_epoch import Clf

    torch.set_num_threads(1)
    torch.manual_seed(0)
    m = Clf().eval()
    o, a, t = torch.randn(10, 46), torch.randn(10, 160), torch.full((10,), 7)

    def bon() -> object:
        with torch.no_grad():
            return m(o, a, t)[0].argmax()

    def cg() -> object:
        x = a[:1].clone().requires_grad_(True)
        logit, _ = m(o[:1], x, t[:1])
        torch.nn.functional.logsigmoid(logit).sum().backward()
        return x.grad

    return measure(iters, bon), measure(iters, cg)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--iters", type=int, default=20000)
    p.add_argument("--no-torch", action="store_true")
    p.add_argument("--members", type=int, default=5)
    args = p.parse_args()

    with tempfile.TemporaryDirectory() as d:
        _ufops.write_random_artifact(d, "square", 0)
        v = ufops.Verifier.load(d)
    with tempfile.TemporaryDirectory() as d:
        _ufops.write_random_artifact(d, "square", 0, None, args.members)
        ens = ufops.Verifier.load(d)
    rng = np.random.default_rng(0)
    obs = rng.uniform(-1, 1, 46).astype(np.float32)
    cands = rng.uniform(-1, 1, (10, 160)).astype(np.float32)
    chunk = cands[0].copy()

    bon = measure(args.iters, lambda: int(v.score(obs, cands, 7).argmax()))
    cg = measure(args.iters, lambda: v.grad(obs, chunk, 7))
    print(f"ufops Python bench, Square dims (obs 46, chunk 160, enc 64, t-emb 64, trunk 128/64), 1 thread, {v.backend}")
    row = lambda name, r: print(f"  {name:<34} p50 {r[0]:>8.1f} us   p99 {r[1]:>8.1f} us")  # noqa: E731
    row("ufops BoN(10) score + argmax", bon)
    row("ufops CG gradient", cg)
    cands30 = rng.uniform(-1, 1, (30, 160)).astype(np.float32)
    one30 = measure(args.iters, lambda: v.pick(obs, cands30, 7))
    ens30 = measure(args.iters, lambda: ens.pick(obs, cands30, 7))
    ens_cg = measure(args.iters, lambda: ens.grad(obs, chunk, 7))
    row("one verifier BoN(30) pick", one30)
    row(f"ensemble of {args.members} BoN(30) pick", ens30)
    row(f"ensemble of {args.members} CG gradient", ens_cg)
    print(f"  ensemble / one verifier at p50: BoN(30) {ens30[0] / one30[0]:.2f}x, CG gradient {ens_cg[0] / cg[0]:.2f}x "
          f"(goal BoN(30) <= 3x: {'met' if ens30[0] <= 3 * one30[0] else 'MISSED'})")
    if not args.no_torch:
        tb, tc = torch_peer(max(2000, args.iters // 10))
        row("PyTorch eager BoN(10) score", tb)
        row("PyTorch eager CG gradient", tc)
        print(f"  speed-up at p50: BoN(10) {tb[0] / bon[0]:.1f}x, CG gradient {tc[0] / cg[0]:.1f}x")
    print(f"  goals: BoN(10) p50 <= 20 us: {'met' if bon[0] <= 20 else 'MISSED'}; "
          f"CG gradient p50 <= 15 us: {'met' if cg[0] <= 15 else 'MISSED'}")


if __name__ == "__main__":
    main()
