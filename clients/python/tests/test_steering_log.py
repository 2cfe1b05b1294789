"""Steering telemetry from Python: ``ufops.torch.best_of_n(log=…, episode=…)`` records each step
on the stored episodes' own verifier inputs (a trained classifier in a non-trivial policy space);
the sidecar ``SteeringLog.write`` produces is what the ingest's sidecar reader keeps with the
episodes (``ufops dev synth --steering-log``: the same synthetic episodes again, as a steered
run), and ``ufops replay`` with the logging artifact and N reproduces every logged choice and
score, and with fewer candidates changes exactly the choices computed here from the log."""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Dict, List

import numpy as np
import pytest

import ufops
import ufops.torch
from conftest import Ufops, require_torch

torch = require_torch()

N = 8
SYNTH = ("--episodes", "12", "--steps", "30", "--seed", "7")


@pytest.fixture(scope="module")
def synth(tmp_path_factory: pytest.TempPathFactory) -> Ufops:
    u = Ufops(tmp_path_factory.mktemp("steering"))
    u.run("init")
    u.run("dev", "synth", *SYNTH)
    split = u.json("split", "create", "--policy", "synth", "--checkpoint", "ckpt-0", "--json")["id"]
    cfg = u.data_dir / "recipe.json"
    cfg.write_text(json.dumps({"epochs": 2}))
    u.run("train", "--split", split, "--kind", "classifier", "--chunk-len", "4", "--config", str(cfg),
          "--action-scale", "0.5", "2.0", "--action-offset", "0.1", "0")
    return u


def test_recorded_steps_round_trip_through_ingest_and_replay(synth: Ufops, tmp_path: Path) -> None:
    store = ufops.Store(synth.data_dir)
    v = store.verifier("synth/ckpt-0/classifier@latest")
    assert v.id is not None
    log = ufops.SteeringLog()
    gen = torch.Generator().manual_seed(3)
    logged: List[Dict[str, Any]] = []
    for row in store.episodes(policy="synth").iter_rows(named=True):
        obs, t, _ = store.step_inputs(row["id"], v)
        for k in range(0, len(t), 5):
            chunk, scores = ufops.torch.best_of_n(
                v, lambda n: torch.randn(n, v.act_dim, generator=gen), obs[k], N, t=int(t[k]), log=log,
                episode=row["source_index"],
            )
            # The executed chunk is on the stored grid: putting it there again changes nothing.
            again, _ = v.telemetry_grid(chunk.numpy()[None])
            assert np.array_equal(again[0], chunk.numpy())
            logged.append({"scores": scores.numpy(), "chosen": int(scores.argmax())})
    assert len(log) == len(logged) == 12 * 6
    sidecar = log.write(tmp_path / "synth.steering.parquet")
    assert ufops.sidecar_for(tmp_path / "synth") == tmp_path / "synth.steering.parquet"

    # The same episodes again as a steered run, with the log attached by the ingest's reader.
    synth.run("dev", "synth", *SYNTH, "--checkpoint", "ckpt-steered", "--run", "bon8", "--steering", "bon:8",
              "--run-artifact", v.id, "--steering-log", str(sidecar))
    same = synth.json("replay", "--run", "bon8", "--json")
    assert same["artifact_id"] == v.id and same["steps"] == len(logged)
    assert same["changed"] == 0 and same["max_score_difference"] == 0.0, same
    assert same["logged_n"] == [N] and same["episodes_without_telemetry"] == 0

    k = 3
    expect = sum(int(np.argmax(r["scores"][:k])) != r["chosen"] for r in logged)
    assert 0 < expect < len(logged)
    fewer = synth.json("replay", "--run", "bon8", "--n", str(k), "--json")
    assert fewer["changed"] == expect, fewer


def test_a_log_refuses_inconsistent_steps(tmp_path: Path) -> None:
    log = ufops.SteeringLog()
    with pytest.raises(ValueError, match="chosen index 3 of 3"):
        log.add(0, 0, "a", np.zeros((3, 4)), [0.1, 0.2, 0.3], 3)
    with pytest.raises(ValueError, match="2 candidates for 3 scores"):
        log.add(0, 0, "a", np.zeros((2, 4)), [0.1, 0.2, 0.3], 0)
    with pytest.raises(ValueError, match="needs the episode"):
        v = ufops.Verifier.load(_random_artifact(tmp_path))
        ufops.torch.best_of_n(v, lambda n: torch.zeros(n, v.act_dim), np.zeros(v.obs_dim, np.float32), 2, log=log)
    assert len(log) == 0


def _random_artifact(tmp_path: Path) -> Path:
    from ufops import _ufops

    d = tmp_path / "artifact"
    _ufops.write_random_artifact(d, "nav", 1)
    return d
