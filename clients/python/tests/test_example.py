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
