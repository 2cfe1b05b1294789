"""ufops.features_ray on a real local Ray cluster — a head and two worker nodes started with the
`ray` CLI, as on a fleet's machines — against `ufops serve` on Postgres + S3 (SeaweedFS): the
layer of the repository's LeRobot v3.0 video fixture equals compute_layer's row for row, bit for
bit; an encoder worker process killed mid-run and a re-run leave each episode written once
(counted in the versions); a run stopped with Ctrl-C (SIGINT) and resumed, on the Ray path and
on compute_layer's, leaves the store as one run would; two runs at once write each episode once."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any, Callable, Dict, Iterator, List, Optional, Tuple

import numpy as np
import pytest

from conftest import REPO, Server, Ufops, require, serving

torch = require("torch")
require("av")
pl = require("polars")
ray = require("ray")
require("ray.data")

import ufops  # noqa: E402
from ufops import features, features_ray  # noqa: E402

import ray_encoders  # noqa: E402

FIXTURE = REPO / "fixtures" / "lerobot" / "v30_eval_video"
CAMERA = "observation.images.front"
LAYER = "features.tiny-cnn"
FRAMES = 519
ENCODER = ray_encoders.tiny_cnn()
PRODUCER = features.producer_of(ENCODER, encoder="tiny-cnn/unit", policy="p", checkpoint="c")
# Ray pickles the test's encoders by value: the workers cannot import this directory.
ray.cloudpickle.register_pickle_by_value(ray_encoders)


# --- the cluster -------------------------------------------------------------------------------


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class Cluster:
    """`ray start --head` and `ray start --address` worker nodes, each a process group of ours."""

    def __init__(self, root: Path) -> None:
        self.root = root
        self.port = _free_port()
        self.address = f"127.0.0.1:{self.port}"
        self.nodes: List["subprocess.Popen[bytes]"] = []
        self.ray_bin = str(Path(sys.executable).parent / "ray")
        # A loopback cluster of one test: no token (Ray reads a driver's token when it is
        # imported, before this fixture could set one; the README's clusters use tokens).
        self.env = {**os.environ, "RAY_AUTH_MODE": "disabled", "RAY_USAGE_STATS_ENABLED": "0"}

    def _start(self, args: List[str], log: str) -> None:
        with open(self.root / log, "wb") as out:
            self.nodes.append(subprocess.Popen(
                [self.ray_bin, "start", "--block", "--disable-usage-stats", "--object-store-memory", str(150 << 20),
                 *args],
                stdin=subprocess.DEVNULL, stdout=out, stderr=subprocess.STDOUT, env=self.env, start_new_session=True,
            ))

    @staticmethod
    def _ports() -> List[str]:
        """Nodes on one machine: each its own agent and metrics ports (Ray's defaults are fixed)."""
        return [a for flag in ("--dashboard-agent-listen-port", "--dashboard-agent-grpc-port",
                               "--runtime-env-agent-port", "--metrics-export-port")
                for a in (flag, str(_free_port()))]

    def start_head(self) -> None:
        self._start(["--head", "--node-ip-address", "127.0.0.1", "--port", str(self.port), "--num-cpus", "0",
                     "--include-dashboard", "false", "--temp-dir", str(self.root / "ray"), *self._ports()],
                    "head.log")

    def add_worker(self, k: int, cpus: int) -> None:
        self._start([f"--address={self.address}", "--node-ip-address", "127.0.0.1", "--num-cpus", str(cpus),
                     *self._ports()], f"worker{k}.log")

    def processes(self) -> Dict[int, str]:
        """pid → command line of every process of the cluster (all ours)."""
        return descendants({p.pid for p in self.nodes})

    def stop(self) -> None:
        """SIGTERM to each node, then SIGKILL to whatever of them is left after a few seconds."""
        left = descendants({p.pid for p in self.nodes})
        for p in self.nodes:
            if p.poll() is None:
                os.killpg(p.pid, signal.SIGTERM)
        deadline = time.monotonic() + 5
        for p in self.nodes:
            try:
                p.wait(timeout=max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                pass
        for pid in left:
            try:
                os.kill(pid, signal.SIGKILL)
            except OSError:
                pass
        for p in self.nodes:
            p.wait(timeout=10)


def descendants(roots: "set[int]") -> "dict[int, str]":
    """pid → command line of the processes under `roots` (their process groups and children:
    Ray's worker processes are the raylets' children in sessions of their own)."""
    table: Dict[int, Tuple[int, int, str]] = {}
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            stat = (d / "stat").read_text()
            fields = stat[stat.rindex(")") + 2 :].split()
            cmd = (d / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
            table[int(d.name)] = (int(fields[1]), int(fields[2]), cmd)
        except (OSError, ValueError):
            continue
    mine = {pid for pid, (ppid, pgid, _) in table.items() if pgid in roots or pid in roots}
    grew = True
    while grew:
        more = {pid for pid, (ppid, _, _) in table.items() if ppid in mine and pid not in mine}
        mine |= more
        grew = bool(more)
    return {pid: table[pid][2] for pid in mine}


def _connect_and_wait(c: Cluster, nodes: int) -> None:
    deadline = time.monotonic() + 120
    last: Optional[Exception] = None
    while True:
        time.sleep(1)
        try:
            if not ray.is_initialized():
                ray.init(address=c.address, logging_level="ERROR", log_to_driver=False)
            if sum(n["Alive"] for n in ray.nodes()) == nodes:
                return
        except Exception as e:  # the head is not up yet
            last = e
            if ray.is_initialized():
                ray.shutdown()
        if time.monotonic() > deadline or c.nodes[-1].poll() is not None:
            logs = "\n".join(f.read_text(errors="replace")[-2000:] for f in c.root.glob("*.log"))
            pytest.fail(f"Ray node {nodes - 1} did not join in 120 s ({last!r}):\n{logs}")


@pytest.fixture(scope="module")
def cluster() -> Iterator[Cluster]:
    """A head (no CPUs: the driver's) and two worker nodes of one CPU each on this machine,
    started one after the other (two raylets starting at once on one machine can take one node
    index); this process is the driver."""
    with tempfile.TemporaryDirectory(prefix="ufops-ray-", dir="/tmp") as root:
        c = Cluster(Path(root))
        try:
            c.start_head()
            _connect_and_wait(c, 1)
            for k in range(2):
                c.add_worker(k, cpus=1)
                _connect_and_wait(c, k + 2)
            assert ray.cluster_resources().get("CPU") == 2
            yield c
        finally:
            if ray.is_initialized():
                ray.shutdown()
            c.stop()


# --- helpers -----------------------------------------------------------------------------------


def ingest(u: Ufops) -> None:
    u.run("ingest", str(FIXTURE), "--policy", "p", "--checkpoint", "c")


@pytest.fixture(scope="module")
def reference(tmp_path_factory: pytest.TempPathFactory) -> Dict[int, np.ndarray]:
    """compute_layer's rows (a local store of the same fixture), by LeRobot episode_index."""
    u = Ufops(tmp_path_factory.mktemp("reference"))
    u.run("init")
    ingest(u)
    s = ufops.Store(u.data_dir)
    with ray_encoders.torch_threads(1):
        features.compute_layer(s, ENCODER, name=LAYER, camera=CAMERA, producer=PRODUCER, batch_size=16,
                               progress=False)
    return {index: rows for index, rows in by_index(s.episodes(), lambda i: s.steps(i, layers=[LAYER])).items()}


def by_index(episodes: Any, steps_of: Callable[[str], Any]) -> Dict[int, np.ndarray]:
    out = {}
    for i, meta in zip(episodes["id"], episodes["metadata"]):
        meta = json.loads(meta) if isinstance(meta, str) else meta
        rows = steps_of(i).sort("t")
        out[int(meta["episode_index"])] = np.asarray(rows[f"obs.{LAYER}"].to_list(), dtype=np.float32)
    return out


def api_rows(client: ufops.Client) -> Dict[int, np.ndarray]:
    return by_index(client.episodes_frame(), lambda i: client.steps(i, layers=[LAYER]))


def layer_versions(u: Ufops) -> List[int]:
    """Episodes written by each layer version of the store, from the version log."""
    out = []
    for v in u.json("versions", "--json"):
        if v["kind"] == "layer" and LAYER in v["message"]:
            out.append(int(v["message"].rsplit(" on ", 1)[1].split()[0]))
    return out


def assert_as_if_run_once(u: Ufops, client: ufops.Client, reference: Dict[int, np.ndarray]) -> None:
    """Each episode written once in all the versions, holding the layer, equal to compute_layer's."""
    assert sum(layer_versions(u)) == 8, f"episodes written per version: {layer_versions(u)}"
    assert [(x["name"], x["dim"], x["episodes"]) for x in client.layers()] == [(LAYER, 12, 8)]
    got = api_rows(client)
    assert sorted(got) == sorted(reference)
    for e, rows in got.items():
        np.testing.assert_array_equal(rows, reference[e], err_msg=f"episode {e}")


def when_committed(client: ufops.Client, episodes: int, then: Callable[[], None]) -> threading.Thread:
    """A thread that calls `then` once `episodes` episodes hold the layer."""
    phash = client.layer_store().producer_hash(PRODUCER.to_dict())

    def watch() -> None:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:
            if len(client.layer_episodes(LAYER, phash)) >= episodes:
                then()
                return
            time.sleep(0.05)

    t = threading.Thread(target=watch, daemon=True)
    t.start()
    return t


def run_on_ray(api: Any, encoder: Any, **kw: Any) -> features_ray.RayLayerReport:
    args: Dict[str, Any] = dict(name=LAYER, camera=CAMERA, producer=PRODUCER, batch_size=16, commit_every=2,
                                encoders=1, decoders=1, episodes_per_task=2, torch_threads=1, progress=False)
    args.update(kw)
    return features_ray.compute_layer_on_ray(api, encoder, **args)


@pytest.fixture()
def served(scale_out: Ufops) -> Iterator[Server]:
    ingest(scale_out)
    with serving(scale_out, "trainer") as s:
        yield s


# --- the tests ---------------------------------------------------------------------------------


def test_ray_layer_equals_compute_layer_and_a_killed_worker_writes_nothing_twice(
    cluster: Cluster, scale_out: Ufops, served: Server, reference: Dict[int, np.ndarray]
) -> None:
    client = ufops.Client(served.url, served.token)
    api = client.layer_store()
    killed: List[int] = []

    def kill_encoder() -> None:
        for pid, cmd in cluster.processes().items():
            if "_EncoderActor" in cmd:
                os.kill(pid, signal.SIGKILL)
                killed.append(pid)

    watcher = when_committed(client, 2, kill_encoder)
    first: Optional[features_ray.RayLayerReport] = None
    try:
        first = run_on_ray(api, ray_encoders.Slow(ENCODER, 0.1))
    except Exception as e:  # Ray gave up on the killed worker's tasks: the re-run finishes
        print(f"\nthe first run stopped: {type(e).__name__}: {str(e)[:300]}")
    watcher.join(timeout=5)
    assert killed, "an encoder worker process was killed mid-run"
    held = set(client.layer_episodes(LAYER, api.producer_hash(PRODUCER.to_dict())))
    if first is not None:
        # Ray restarted the actor and retried its batches: the run went on to the end.
        print(f"\nthe first run went on past the kill: {first.episodes_written} written, {first.frames} frames, "
              + ", ".join(f"{k} {s.frames_per_second:.0f} x{s.workers}" for k, s in first.stages.items()))
        assert first.episodes_written == 8 and len(held) == 8
        assert first.frames >= FRAMES, "the killed actor's batches were encoded again"
        assert first.bound_by in first.stages and first.stages["write"].frames == FRAMES
        assert len([w for w in first.workers.values() if w["stage"] == "encode"]) >= 2, "a new actor took over"
        assert all(w["peak_rss_mb"] > 0 for w in first.workers.values())

    lengths = {e["id"]: int(e["length"]) for e in client.episodes()}
    with pytest.raises(ValueError, match="no 1.0 CPU of the cluster's 2 to decode on"):
        run_on_ray(api, ENCODER, encoders=2)
    again = run_on_ray(api, ENCODER)
    assert (again.episodes_written, again.episodes_skipped) == (8 - len(held), len(held))
    assert again.frames == sum(n for i, n in lengths.items() if i not in held), "only what was missing"
    assert_as_if_run_once(scale_out, client, reference)
    third = run_on_ray(api, ENCODER)
    assert (third.episodes_written, third.episodes_skipped, third.frames, third.versions) == (0, 8, 0, [])


def sigint_when_committed(client: ufops.Client, episodes: int) -> threading.Thread:
    """Ctrl-C (SIGINT to this process) once `episodes` episodes hold the layer."""
    return when_committed(client, episodes, lambda: os.kill(os.getpid(), signal.SIGINT))


def test_ctrl_c_on_ray_then_resume_leaves_the_store_as_one_run(
    cluster: Cluster, scale_out: Ufops, served: Server, reference: Dict[int, np.ndarray]
) -> None:
    client = ufops.Client(served.url, served.token)
    api = client.layer_store()
    watcher = sigint_when_committed(client, 2)
    with pytest.raises(KeyboardInterrupt):
        run_on_ray(api, ray_encoders.Slow(ENCODER, 0.1))
        time.sleep(30)  # the SIGINT lands in the run (a run that ended first fails the test)
    watcher.join(timeout=5)
    held = client.layer_episodes(LAYER, api.producer_hash(PRODUCER.to_dict()))
    assert 2 <= len(held) < 8, "stopped mid-run, its finished episodes committed"
    r = run_on_ray(api, ENCODER)
    assert (r.episodes_written, r.episodes_skipped) == (8 - len(held), len(held))
    assert_as_if_run_once(scale_out, client, reference)


def test_two_runs_at_once_write_each_episode_once(
    cluster: Cluster, scale_out: Ufops, served: Server, reference: Dict[int, np.ndarray]
) -> None:
    """A Ray run and a compute_layer run of one producer started together against one server:
    both compute every episode, the store writes each once (its version transactions decide)."""
    client = ufops.Client(served.url, served.token)
    reports: Dict[str, Any] = {}

    def local() -> None:
        with ray_encoders.torch_threads(1):
            reports["local"] = features.compute_layer(
                ufops.Client(served.url, served.token).layer_store(), ray_encoders.Slow(ENCODER, 0.05), name=LAYER,
                camera=CAMERA,
                producer=PRODUCER, batch_size=16, commit_every=1, progress=False)

    t = threading.Thread(target=local)
    t.start()
    reports["ray"] = run_on_ray(client.layer_store(), ray_encoders.Slow(ENCODER, 0.05), commit_every=1)
    t.join(timeout=300)
    written = reports["ray"].episodes_written + reports["local"].episodes_written
    assert written == 8, {k: (r.episodes_written, r.episodes_skipped) for k, r in reports.items()}
    assert_as_if_run_once(scale_out, client, reference)
