#!/usr/bin/env python3
"""Parity check between the numpy reference client and the Rust trainer's reference scorer.

    python3 test_parity.py ARTIFACT_DIR SCORES_JSON [--tol 1e-4]

SCORES_JSON: {"rows": [{"obs": [...], "action": [...], "t": 3, "extras": {...}}, ...],
              "scores": [...], "artifact_id": "..."} as written by the Rust test
(`trainer/tests/parity.rs`, scores from `trainer::score_json`). Exits non-zero on mismatch."""
import argparse
import json
import os
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from ufops_verifier import load_artifact  # noqa: E402


def main():
    p = argparse.ArgumentParser()
    p.add_argument("artifact_dir")
    p.add_argument("scores_file")
    p.add_argument("--tol", type=float, default=1e-4)
    a = p.parse_args()
    v = load_artifact(a.artifact_dir)
    with open(a.scores_file) as f:
        ref = json.load(f)
    if "artifact_id" in ref and ref["artifact_id"] != v.id:
        print(f"artifact id mismatch: python {v.id}, rust {ref['artifact_id']}")
        return 1
    rows = ref["rows"]
    obs = np.array([r["obs"] for r in rows])
    act = np.array([r["action"] for r in rows])
    t = np.array([r["t"] for r in rows])
    extras = {}
    for e in v.arch.get("extra_inputs", []):
        extras[e["name"]] = np.array([r["extras"][e["name"]] for r in rows])
    got = v.score(obs, act, t, extras)
    want = np.asarray(ref["scores"], dtype=np.float64)
    err = np.abs(got - want)
    worst = float(err.max()) if len(err) else 0.0
    print(f"{v.config['kind']}/{v.arch['variant']} artifact {v.id}: {len(rows)} rows, max |python - rust| = {worst:.3g}")
    if not np.all(err <= a.tol):
        bad = int(np.argmax(err))
        print(f"MISMATCH at row {bad}: python {got[bad]!r}, rust {want[bad]!r}")
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
