#!/usr/bin/env python3
"""Checks ufops.Store on a store of any size against the CLI and the Parquet files themselves:
``Store.episodes()`` equals ``ufops episodes --json``, and ``Store.steps(all ids)`` equals the
steps files read directly with polars (in the order of the ids). Prints the read times.

    ufops --data-dir /tmp/big init && ufops --data-dir /tmp/big dev synth --episodes 5000 --steps 30
    python3 clients/python/bench/check_store.py /tmp/big [--ufops PATH]
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import time
from pathlib import Path

import polars as pl
from polars.testing import assert_frame_equal

import ufops
from ufops.store import episodes_frame


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("data_dir")
    target = os.environ.get("CARGO_TARGET_DIR") or str(Path.home() / ".cache" / "ufops-target")
    p.add_argument("--ufops", default=f"{target}/debug/ufops")
    a = p.parse_args()
    s = ufops.Store(a.data_dir)
    t0 = time.perf_counter()
    eps = s.episodes()
    t_eps = time.perf_counter() - t0
    cli = json.loads(subprocess.run([a.ufops, "--data-dir", a.data_dir, "episodes", "--json"],
                                    capture_output=True, text=True, check=True).stdout)
    assert_frame_equal(eps, episodes_frame(cli))
    print(f"Store.episodes(): {eps.height} episodes in {1e3 * t_eps:.0f} ms, equal to `ufops episodes --json`")
    ids = eps["id"].to_list()
    t0 = time.perf_counter()
    steps = s.steps(ids)
    t_steps = time.perf_counter() - t0
    files = eps["data_file"].unique().to_list()
    direct = pl.concat([pl.read_parquet(Path(a.data_dir) / "objects" / f) for f in files])
    order = pl.DataFrame({"episode_id": ids, "_order": range(len(ids))})
    direct = direct.join(order, on="episode_id").sort(["_order", "t"]).drop("_order")
    assert_frame_equal(steps, direct)
    print(f"Store.steps(all): {steps.height} rows x {steps.width} columns in {1e3 * t_steps:.0f} ms, "
          f"equal to polars.read_parquet of the {len(files)} steps files")


if __name__ == "__main__":
    main()
