"""examples/python/steer_torch_policy.py --quick: the paper's loop from Python end to end (a
PyTorch DDPM policy, its rollouts ingested, a classifier trained through the API's job queue by
`ufops worker`, best-of-N and guidance through ufops.Verifier), on 200 rollouts per method."""
from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

from conftest import REPO, require, ufops_binary


def test_the_example_runs_the_loop_and_best_of_n_helps(tmp_path: Path) -> None:
    require("torch")
    require("pyarrow")
    script = REPO / "examples" / "python" / "steer_torch_policy.py"
    env = dict(os.environ, OMP_NUM_THREADS="1")
    p = subprocess.run(
        [sys.executable, str(script), "--quick", "--episodes", "200", "--ufops", str(ufops_binary()),
         "--workdir", str(tmp_path)],
        capture_output=True, text=True, timeout=900, env=env,
    )
    assert p.returncode == 0, p.stdout + p.stderr
    out = p.stdout
    rates = {m.group(1).strip(): int(m.group(2)) for m in re.finditer(r"^\s+(.+?)\s+(\d+)/200 = ", out, re.M)}
    assert set(rates) == {"base (DDPM)", "best-of-10 (Algorithm 1)", "guidance λ=3 (Algorithm 2)"}, out
    assert "95% CI [" in out and "pulled from the API" in out and "job succeeded" in out
    assert rates["best-of-10 (Algorithm 1)"] > rates["base (DDPM)"], out
    # The failure alarm, calibrated on the fresh base rollouts the verifier did not train on.
    m = re.search(r"^5\. monitor \w+ at alpha 0\.1 .* false alarms on held-out successes (\d+)/(\d+) = ", out, re.M)
    assert m and int(m.group(2)) > 0, out


def test_the_camera_example_steers_through_the_policy_encoder(tmp_path: Path) -> None:
    """examples/python/steer_image_policy.py --quick: a camera DDPM policy, its rollouts as a
    LeRobot v3.0 dataset with mp4 video, the encoder's features of the decoded frames as a layer, a
    classifier on them, and best-of-N through CameraObservation: on 200 rollouts per method the
    steered policy succeeds more often than the base one, with Newcombe's interval above 0."""
    import json

    require("torch")
    require("av")
    script = REPO / "examples" / "python" / "steer_image_policy.py"
    env = dict(os.environ, OMP_NUM_THREADS="1")
    p = subprocess.run(
        [sys.executable, str(script), "--quick", "--ufops", str(ufops_binary()), "--workdir", str(tmp_path)],
        capture_output=True, text=True, timeout=900, env=env,
    )
    assert p.returncode == 0, p.stdout + p.stderr
    report = json.loads((tmp_path / "report.json").read_text())
    base, *steered = report["rows"]
    assert steered and base["episodes"] >= 200, report["rows"]
    best = max(steered, key=lambda s: s["delta"])
    assert best["delta"] > 0 and best["newcombe95"][0] > 0, report["rows"]
    assert report["wrong_producer_refused"], "a verifier of another encoder must be refused"
    assert report["layer"]["frames"] > 0 and report["codec_gap"]["cosine_mean"] > 0.9, report["codec_gap"]
    assert "c-bon" in report["scoreboard"], report["scoreboard"]
