"""ufops.Monitor against `ufops monitor evaluate`: a monitor calibrated by the CLI on a trained
verifier, stepped in Python on every stored step's verifier inputs, raises the same alarms with the
same statistics as the offline evaluation's trace; a verifier it was not calibrated for is refused."""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Dict, List, Tuple

import numpy as np
import pytest

import ufops
from conftest import Ufops


@pytest.fixture(scope="module")
def calibrated(tmp_path_factory: pytest.TempPathFactory) -> Tuple[Ufops, Dict[str, Any], Path]:
    u = Ufops(tmp_path_factory.mktemp("monitor"))
    u.run("init")
    u.run("dev", "synth", "--episodes", "120", "--steps", "20", "--seed", "9", "--success-rate", "0.6")
    split = u.json("split", "create", "--policy", "synth", "--checkpoint", "ckpt-0", "--val-fraction", "0.6",
                   "--json")["id"]
    cfg = u.data_dir / "recipe.json"
    cfg.write_text(json.dumps({"epochs": 2}))
    u.run("train", "--split", split, "--kind", "classifier", "--chunk-len", "4", "--config", str(cfg))
    u.run("train", "--split", split, "--kind", "q", "--chunk-len", "4", "--config", str(cfg))
    entry = u.json("monitor", "calibrate", "--artifact", "synth/ckpt-0/classifier@latest", "--alpha", "0.2",
                   "--smoothing", "0.6", "--seed", "3", "--json")
    trace = u.data_dir / "trace.jsonl"
    u.run("monitor", "evaluate", "synth/ckpt-0@latest", "--trace", str(trace))
    return u, entry, trace


def test_python_monitor_agrees_with_the_offline_evaluation_step_for_step(
    calibrated: Tuple[Ufops, Dict[str, Any], Path]
) -> None:
    u, entry, trace = calibrated
    store = ufops.Store(u.data_dir)
    assert store.monitor("synth/ckpt-0@latest")["id"] == entry["id"]
    assert [m["id"] for m in store.monitors(policy="synth")] == [entry["id"]]
    monitor = ufops.Monitor.from_store(store, entry["id"])
    assert monitor.artifact_id == entry["artifact_id"] and monitor.alpha == 0.2
    verifier = monitor.verifier

    by_episode: Dict[str, List[Dict[str, Any]]] = {}
    for line in trace.read_text().splitlines():
        row = json.loads(line)
        by_episode.setdefault(row["episode_id"], []).append(row)
    evaluation = entry["evaluation"]
    assert len(by_episode) == evaluation["successes"] + evaluation["failures"]

    steps = alarms = 0
    for episode_id, rows in by_episode.items():
        obs, t, act = store.step_inputs(episode_id, verifier)
        assert obs.shape == (len(rows), verifier.obs_dim) and act.shape == (len(rows), verifier.act_dim)
        monitor.reset()
        for k, row in enumerate(rows):
            s = monitor.update(obs[k], act[k], int(t[k]))
            assert s.score == pytest.approx(row["score"], abs=1e-5), (episode_id, k)
            assert s.statistic == pytest.approx(row["statistic"], abs=1e-5), (episode_id, k)
            assert s.alarm == row["alarm"], (episode_id, k)
            steps += 1
            alarms += s.alarm
    assert steps == sum(len(r) for r in by_episode.values()) and steps > 500
    # Both outcomes occur, so the comparison tested the alarm, not a constant.
    assert 0 < alarms < steps

    # update_score steps the same statistic without a forward pass.
    monitor.reset()
    again = ufops.Monitor(verifier, monitor.record())
    for k in range(3):
        a = monitor.update(obs[k], act[k], int(t[k]))
        b = again.update_score(a.score)
        assert (a.statistic, a.alarm) == (b.statistic, b.alarm)


def test_a_monitor_refuses_a_verifier_it_was_not_calibrated_for(
    calibrated: Tuple[Ufops, Dict[str, Any], Path]
) -> None:
    u, entry, _ = calibrated
    store = ufops.Store(u.data_dir)
    q = store.verifier("synth/ckpt-0/q@latest")
    with pytest.raises(ValueError, match=f"calibrated for verifier artifact {entry['artifact_id']}"):
        ufops.Monitor(q, entry["record"])
    record_file = u.data_dir / "monitor.json"
    u.run("monitor", "show", entry["id"], "--out", str(record_file))
    m = ufops.Monitor(store.verifier(entry["artifact_id"]), record_file)
    assert m.threshold == entry["threshold"]
    with pytest.raises(ValueError, match="one chunk"):
        m.update(np.zeros(m.verifier.obs_dim, np.float32), np.zeros(3, np.float32), 0)
