"""Shared fixtures: the `ufops` binary of this checkout, a store with verifiers the trainer wrote
(a lowdim classifier in the policy's action space and a features/spectral-norm Q), and a running
`ufops serve` on it. Nothing is mocked: the binary trains, publishes and serves for real.

The binary is `$UFOPS_BIN`, else `$CARGO_TARGET_DIR/debug/ufops` (scripts/env.sh's target dir),
else `target/debug/ufops`; scripts/test.sh builds it first. A missing binary fails the tests.
"""
from __future__ import annotations

import contextlib
import importlib
import json
import os
import shutil
import subprocess
import time
import urllib.request
from pathlib import Path
from typing import Any, Dict, Iterator, List

import pytest

REPO = Path(__file__).resolve().parents[3]


def ufops_binary() -> Path:
    candidates = []
    if os.environ.get("UFOPS_BIN"):
        candidates.append(Path(os.environ["UFOPS_BIN"]))
    target = os.environ.get("CARGO_TARGET_DIR") or str(Path.home() / ".cache" / "ufops-target")
    candidates += [Path(target) / "debug" / "ufops", REPO / "target" / "debug" / "ufops"]
    for c in candidates:
        if c.is_file() and os.access(c, os.X_OK):
            return c
    pytest.fail(f"the ufops binary is needed (cargo build --bin ufops); looked at {[str(c) for c in candidates]}")


class Ufops:
    """Runs the binary against one data directory."""

    def __init__(self, data_dir: Path) -> None:
        self.bin = ufops_binary()
        self.data_dir = data_dir

    def run(self, *args: str) -> str:
        p = subprocess.run(
            [str(self.bin), "--data-dir", str(self.data_dir), *args], capture_output=True, text=True, timeout=600
        )
        if p.returncode != 0:
            raise AssertionError(f"ufops {' '.join(args)} failed ({p.returncode}):\n{p.stderr}")
        return p.stdout

    def json(self, *args: str) -> Any:
        return json.loads(self.run(*args))


FEATURES_CONFIG: Dict[str, Any] = {
    "epochs": 3,
    "batch_size": 256,
    "obs_noise_std": 0.02,
    "architecture": {
        "variant": "features",
        "activation": "gelu",
        "encoder_width": 16,
        "t_embed_dim": 16,
        "trunk_dims": [32, 16],
        "input_layernorm": True,
        "encoder_layernorm": True,
        "spectral_norm": True,
        "dropout": 0.1,
    },
}


@pytest.fixture(scope="session")
def trained(tmp_path_factory: pytest.TempPathFactory) -> Ufops:
    """A store with synthetic rollouts and two trained verifiers: `synth/ckpt-0/classifier@latest`
    (lowdim, actions in a non-trivial policy space) and `synth/ckpt-0/q@latest` (features)."""
    u = Ufops(tmp_path_factory.mktemp("store"))
    u.run("init")
    u.run("dev", "synth", "--episodes", "40", "--steps", "30", "--seed", "5")
    split = u.json("split", "create", "--policy", "synth", "--checkpoint", "ckpt-0", "--json")["id"]
    lowdim = u.data_dir / "lowdim.json"
    lowdim.write_text(json.dumps({"epochs": 3}))
    u.run("train", "--split", split, "--kind", "classifier", "--config", str(lowdim),
          "--action-scale", "0.5", "2.0", "--action-offset", "0.1", "0")
    features = u.data_dir / "features.json"
    features.write_text(json.dumps(FEATURES_CONFIG))
    u.run("train", "--split", split, "--kind", "q", "--config", str(features))
    return u


@pytest.fixture(scope="session")
def artifact_dirs(trained: Ufops, tmp_path_factory: pytest.TempPathFactory) -> Dict[str, Path]:
    out = {}
    base = tmp_path_factory.mktemp("artifacts")
    for kind in ("classifier", "q"):
        d = base / kind
        trained.run("artifacts", "download", f"synth/ckpt-0/{kind}@latest", str(d))
        out[kind] = d
    return out


class Server:
    def __init__(self, url: str, token: str, proc: "subprocess.Popen[str]") -> None:
        self.url, self.token, self.proc = url, token, proc


@pytest.fixture(scope="session")
def server(trained: Ufops) -> Iterator[Server]:
    """`ufops serve` on the trained store (loopback, a free port) and a labeler token."""
    with serving(trained, "labeler") as s:
        yield s


@contextlib.contextmanager
def serving(store: Ufops, role: str, name: str = "pytest") -> Iterator[Server]:
    """`ufops serve --no-worker` on `store` (loopback, a free port) with a token of `role`,
    stopped on exit."""
    token = store.json("token", "create", "--name", name, "--role", role, "--json")["token"]
    proc = subprocess.Popen(
        [str(store.bin), "--data-dir", str(store.data_dir), "serve", "--addr", "127.0.0.1:0", "--no-worker"],
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
    )
    try:
        assert proc.stdout is not None
        line = proc.stdout.readline()
        assert line.startswith("listening on "), f"ufops serve printed {line!r}"
        url = line.split()[-1]
        deadline = time.monotonic() + 30
        while True:
            try:
                urllib.request.urlopen(url + "/healthz", timeout=2).read()
                break
            except OSError:
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.1)
        yield Server(url, token, proc)
    finally:
        proc.terminate()
        proc.wait(timeout=10)


def rows(obs: Any, act: Any, t: Any) -> Dict[str, List[Dict[str, Any]]]:
    return {"rows": [{"obs": o.tolist(), "action": a.tolist(), "t": int(s)} for o, a, s in zip(obs, act, t)]}


@pytest.fixture()
def copy_dir(tmp_path: Path) -> Any:
    def copy(src: Path) -> Path:
        dst = tmp_path / src.name
        shutil.copytree(src, dst)
        return dst

    return copy


def require(module: str) -> Any:
    """The module, or a failure under UFOPS_REQUIRE_PYTHON=1 (scripts/test.sh sets it), else a skip."""
    try:
        return importlib.import_module(module)
    except ImportError:
        if os.environ.get("UFOPS_REQUIRE_PYTHON") == "1":
            pytest.fail(f"UFOPS_REQUIRE_PYTHON=1: {module} is required (pip install {module})")
        pytest.skip(f"{module} is not installed", allow_module_level=True)


def require_torch() -> Any:
    return require("torch")
