#!/usr/bin/env python3
"""Throughput of ``ufops.features.compute_layer`` on a two-camera LeRobot v3.0 dataset, one torch
thread, with the encoder alone measured in the same run:

1. writes a LeRobot v3.0 dataset (pyarrow + PyAV, examples/python/image_nav.py's layout) with two
   96x96 cameras ``observation.images.front`` / ``.wrist`` (AV1: libsvtav1 yuv420p g=2 crf=30,
   lerobot's defaults; ``--codec h264`` for libx264), ``--frames`` frames per camera (default
   10,000: 50 episodes x 200 steps), and ingests it (``ufops init`` + ``ufops ingest DIR --policy
   bench --checkpoint c``) into a fresh data dir under ``--out``;
2. measures, each phase in a fresh child process (its peak RSS = VmHWM):
   (a) decode + encode + write: ``compute_layer`` of each camera (a fresh layer name per camera
       and repetition), frames/s over both cameras;
   (b) encode alone: ``encode_frames`` of the same encoder over the same frames, decoded into
       memory first (untimed), in batches of the same size;
   (r) the same layers by ``ufops.features_ray.compute_layer_on_ray`` on a local Ray cluster
       started for the phase (``ray start --head`` without CPUs, which runs the driver, and W
       worker nodes of ``--ray-cpus`` CPUs joining it; W from ``--ray-workers``, default 1 and
       2): W encoder actors of one torch thread and up to W decoding tasks; the peak RSS of the
       driver, of each Ray worker process (encoder actor, decoder) and of Ray's own processes;
   the phases alternate ``--reps`` times (default 3); medians are reported, and (a)/(b)
   (goal >= 0.7: decoding overlapped with encoding) and the peak RSS of (a) (goal <= 1 GB),
   and for (a) and (r) the stage that bounded the run (the report's ``bound_by``);
3. prints a table and writes ``--out``/features_throughput.json.

The encoder: ``--encoder cnn`` (default; 4 stride-2 3x3 conv + ReLU layers 3->32->64->128->256,
global average pool: 256-d) or ``resnet18`` (torchvision, random init, 512-d). Weights are random
(seed 0): the throughput does not depend on them.

    python3 clients/python/bench/features_throughput.py [--frames 10000] [--out DIR] [--ufops PATH]
"""
from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import platform
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, Dict, List, Tuple

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("MKL_NUM_THREADS", "1")
os.environ.setdefault("SVT_LOG", "1")  # SVT-AV1: errors only

import numpy as np  # noqa: E402
from numpy.typing import NDArray  # noqa: E402

CAMERAS = ("observation.images.front", "observation.images.wrist")
POLICY, CHECKPOINT = "bench", "c"
SIZE, FPS, STEPS = 96, 10, 200
DIM = 6


# --- the dataset -------------------------------------------------------------------------------


def _frames(ep: int, n: int, wrist: bool) -> NDArray[Any]:
    """An episode's frames: a coloured square moving over a gradient (the wrist camera zoomed
    and tinted), so the video is not noise and not constant."""
    rng = np.random.default_rng(ep * 2 + wrist)
    yy, xx = np.mgrid[0:SIZE, 0:SIZE].astype(np.float32) / SIZE
    bg = np.stack([xx, yy, 0.5 * (xx + yy)], -1) * (120 if wrist else 200)
    out = np.empty((n, SIZE, SIZE, 3), np.uint8)
    p0, v = rng.uniform(10, 70, 2), rng.uniform(-0.4, 0.4, 2)
    side = 30 if wrist else 14
    colour = rng.integers(60, 256, 3)
    for t in range(n):
        f = bg.copy()
        x, y = (p0 + v * t) % (SIZE - side)
        f[int(y) : int(y) + side, int(x) : int(x) + side] = colour
        out[t] = f.astype(np.uint8)
    return out


def _stats(x: NDArray[Any]) -> Dict[str, Any]:
    x = np.asarray(x, np.float64).reshape(len(x), -1)
    return {"min": x.min(0), "max": x.max(0), "mean": x.mean(0), "std": x.std(0), "count": np.array([len(x)])}


def write_dataset(root: Path, frames_per_camera: int, codec: str) -> Dict[str, Any]:
    """A LeRobot v3.0 dataset: ``frames_per_camera`` frames per camera in episodes of STEPS (the
    last one shorter), each camera one mp4 with the episodes back to back, each starting on a
    keyframe (as lerobot's files)."""
    import av
    import pyarrow as pa  # type: ignore[import-untyped]
    import pyarrow.parquet as pq  # type: ignore[import-untyped]

    if root.exists():
        shutil.rmtree(root)
    (root / "meta" / "episodes" / "chunk-000").mkdir(parents=True)
    (root / "data" / "chunk-000").mkdir(parents=True)
    full, rest = divmod(frames_per_camera, STEPS)
    lengths = [STEPS] * full + ([rest] if rest else [])
    if codec == "av1":
        enc, opts, codec_name = "libsvtav1", {"g": "2", "crf": "30", "preset": "12"}, "av1"
    else:
        enc, opts, codec_name = "libx264", {"g": "2", "crf": "30", "preset": "ultrafast"}, "h264"
    outs: Dict[str, Any] = {}
    for cam in CAMERAS:
        vdir = root / "videos" / cam / "chunk-000"
        vdir.mkdir(parents=True)
        c = av.open(str(vdir / "file-000.mp4"), "w")
        s: Any = c.add_stream(enc, rate=FPS, options=opts)
        s.width = s.height = SIZE
        s.pix_fmt = "yuv420p"
        s.thread_count = 1
        outs[cam] = (c, s)
    rng = np.random.default_rng(0)
    cols: Dict[str, List[NDArray[Any]]] = {}
    ep_rows: List[Dict[str, Any]] = []
    index = 0
    for i, n in enumerate(lengths):
        for cam, (c, s) in outs.items():
            for t, f in enumerate(_frames(i, n, cam.endswith("wrist"))):
                vf = av.VideoFrame.from_ndarray(f, format="rgb24")
                if t == 0:
                    vf.pict_type = av.video.frame.PictureType.I
                for pkt in s.encode(vf):
                    c.mux(pkt)
        state = np.cumsum(rng.normal(0, 0.01, (n, DIM)), 0).astype(np.float32)
        done = np.zeros(n, bool)
        done[-1] = True
        success = done & bool(i % 2)
        per = {
            "observation.state": state, "action": (state + rng.normal(0, 0.01, (n, DIM))).astype(np.float32),
            "next.reward": success.astype(np.float32), "next.success": success, "next.done": done,
            "timestamp": (np.arange(n) / FPS).astype(np.float32), "frame_index": np.arange(n, dtype=np.int64),
            "episode_index": np.full(n, i, np.int64), "index": np.arange(index, index + n, dtype=np.int64),
            "task_index": np.zeros(n, np.int64),
        }
        for k, v in per.items():
            cols.setdefault(k, []).append(v)
        row: Dict[str, Any] = {
            "episode_index": i, "tasks": ["bench"], "length": n, "data/chunk_index": 0, "data/file_index": 0,
            "dataset_from_index": index, "dataset_to_index": index + n,
        }
        for cam in CAMERAS:
            row.update({f"videos/{cam}/chunk_index": 0, f"videos/{cam}/file_index": 0,
                        f"videos/{cam}/from_timestamp": index / FPS, f"videos/{cam}/to_timestamp": (index + n) / FPS})
        for k in ("observation.state", "action"):
            for sk, sv in _stats(per[k]).items():
                row[f"stats/{k}/{sk}"] = sv.tolist()
        row["meta/episodes/chunk_index"] = 0
        row["meta/episodes/file_index"] = 0
        ep_rows.append(row)
        index += n
    video_bytes = 0
    for cam, (c, s) in outs.items():
        for pkt in s.encode():
            c.mux(pkt)
        c.close()
        video_bytes += (root / "videos" / cam / "chunk-000" / "file-000.mp4").stat().st_size

    def cat(k: str) -> NDArray[Any]:
        return np.concatenate(cols[k])

    vec = {"feature": {"dtype": "float32", "_type": "Value"}, "length": DIM, "_type": "List"}
    hf = {"info": {"features": {
        "observation.state": vec, "action": vec,
        "next.reward": {"dtype": "float32", "_type": "Value"}, "next.success": {"dtype": "bool", "_type": "Value"},
        "next.done": {"dtype": "bool", "_type": "Value"}, "timestamp": {"dtype": "float32", "_type": "Value"},
        **{k: {"dtype": "int64", "_type": "Value"} for k in ("frame_index", "episode_index", "index", "task_index")},
    }}}
    table = pa.table({
        "observation.state": pa.FixedSizeListArray.from_arrays(pa.array(cat("observation.state").reshape(-1)), DIM),
        "action": pa.FixedSizeListArray.from_arrays(pa.array(cat("action").reshape(-1)), DIM),
        **{k: pa.array(cat(k)) for k in ("next.reward", "next.success", "next.done", "timestamp", "frame_index",
                                         "episode_index", "index", "task_index")},
    }).replace_schema_metadata({"huggingface": json.dumps(hf)})
    pq.write_table(table, root / "data" / "chunk-000" / "file-000.parquet", compression="snappy")
    pq.write_table(pa.Table.from_pylist(ep_rows), root / "meta" / "episodes" / "chunk-000" / "file-000.parquet")
    pq.write_table(pa.table({"task_index": pa.array([0], pa.int64()), "task": pa.array(["bench"])}),
                   root / "meta" / "tasks.parquet")
    stats = {k: {sk: sv.tolist() for sk, sv in _stats(cat(k)).items()} for k in ("observation.state", "action")}
    (root / "meta" / "stats.json").write_text(json.dumps(stats, indent=4))
    vinfo = {"video.height": SIZE, "video.width": SIZE, "video.codec": codec_name, "video.pix_fmt": "yuv420p",
             "video.fps": FPS, "video.channels": 3, "has_audio": False, "video.g": 2, "video.crf": 30,
             "video.preset": 12, "video.fast_decode": 0, "video.video_backend": "pyav", "video.extra_options": {},
             "is_depth_map": False}
    names6 = [f"j{k}" for k in range(DIM)]
    features: Dict[str, Any] = {
        "observation.state": {"dtype": "float32", "shape": [DIM], "names": names6},
        "action": {"dtype": "float32", "shape": [DIM], "names": names6},
        **{cam: {"dtype": "video", "shape": [SIZE, SIZE, 3], "names": ["height", "width", "channel"], "info": vinfo}
           for cam in CAMERAS},
        "next.reward": {"dtype": "float32", "shape": [1], "names": None},
        "next.success": {"dtype": "bool", "shape": [1], "names": None},
        "next.done": {"dtype": "bool", "shape": [1], "names": None},
        "timestamp": {"dtype": "float32", "shape": [1], "names": None},
        **{k: {"dtype": "int64", "shape": [1], "names": None}
           for k in ("frame_index", "episode_index", "index", "task_index")},
    }
    info = {
        "codebase_version": "v3.0", "fps": FPS, "features": features, "total_episodes": len(lengths),
        "total_frames": index, "total_tasks": 1, "chunks_size": 1000, "data_files_size_in_mb": 100,
        "video_files_size_in_mb": 200, "data_path": "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet",
        "video_path": "videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4",
        "robot_type": "bench", "splits": {"train": f"0:{len(lengths)}"},
    }
    (root / "meta" / "info.json").write_text(json.dumps(info, indent=4))
    return {"episodes": len(lengths), "frames_per_camera": index, "video_bytes": video_bytes, "codec": codec_name}


# --- the phases (each in a child process) ------------------------------------------------------


def make_encoder(kind: str) -> Any:
    import torch

    torch.manual_seed(0)
    if kind == "resnet18":
        import torchvision  # type: ignore[import-untyped]

        m = torchvision.models.resnet18(weights=None)
        m.fc = torch.nn.Identity()
        return m.eval()
    layers: List[Any] = []
    ch = [3, 32, 64, 128, 256]
    for a, b in zip(ch, ch[1:]):
        layers += [torch.nn.Conv2d(a, b, 3, stride=2, padding=1), torch.nn.ReLU(inplace=True)]
    layers += [torch.nn.AdaptiveAvgPool2d(1), torch.nn.Flatten()]
    return torch.nn.Sequential(*layers).eval()


def _vm_hwm_mb() -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def _phase(kind: str, data_dir: str, encoder_kind: str, batch_size: int, decoder_threads: Any, rep: int,
           extra: Dict[str, Any], out: "mp.Queue[Any]") -> None:
    try:
        import torch

        torch.set_num_threads(1)
        import ufops
        from ufops.features import FrameReader, compute_layer, encode_frames, producer_of

        if decoder_threads is not None:
            # ufops opens videos with PyAV's default thread_count (0: the decoder's own choice).
            import ufops.features as uf

            init = uf._Video.__init__

            def patched(self: Any, *a: Any, **k: Any) -> None:
                init(self, *a, **k)
                self.stream.thread_count = decoder_threads

            uf._Video.__init__ = patched  # type: ignore[method-assign]
        store = ufops.Store(data_dir)
        enc = make_encoder(encoder_kind)
        producer = producer_of(enc, encoder=f"{encoder_kind}/96-totensor", policy=POLICY, checkpoint=CHECKPOINT)
        res: Dict[str, Any] = {"phase": kind, "rep": rep, "per_camera": {}}
        frames = seconds = 0.0
        if kind == "compute_layer":
            res["rss_before_mb"] = _vm_hwm_mb()
            for cam in CAMERAS:
                name = f"features.bench-{cam.rsplit('.', 1)[-1]}-r{rep}"
                t0 = time.perf_counter()
                rep_ = compute_layer(store, enc, name=name, camera=cam, producer=producer, batch_size=batch_size,
                                     progress=False, decode_threads=extra.get("decode_threads"))
                dt = time.perf_counter() - t0
                res["per_camera"][cam] = {"layer": name, "frames": rep_.frames, "seconds": dt,
                                          "frames_per_second": rep_.frames / dt, "versions": len(rep_.versions),
                                          "stages": {k: v.to_dict() for k, v in rep_.stages.items()},
                                          "bound_by": rep_.bound_by}
                frames += rep_.frames
                seconds += dt
        elif kind.startswith("ray"):
            import ray

            from ufops.features_ray import compute_layer_on_ray

            ray.init(address=extra["ray_address"], logging_level="ERROR", log_to_driver=False)
            res["rss_before_mb"] = _vm_hwm_mb()
            workers: Dict[int, Any] = {}
            for cam in CAMERAS:
                name = f"features.bench-{cam.rsplit('.', 1)[-1]}-{kind}-r{rep}"
                t0 = time.perf_counter()
                rep_ = compute_layer_on_ray(store, enc, name=name, camera=cam, producer=producer,
                                            batch_size=batch_size, encoders=extra["ray_workers"],
                                            decoders=extra["ray_workers"], torch_threads=1, progress=False)
                dt = time.perf_counter() - t0
                res["per_camera"][cam] = {"layer": name, "frames": rep_.frames, "seconds": dt,
                                          "frames_per_second": rep_.frames / dt, "versions": len(rep_.versions),
                                          "stages": {k: v.to_dict() for k, v in rep_.stages.items()},
                                          "bound_by": rep_.bound_by}
                for pid, w in rep_.workers.items():
                    workers[pid] = {**w, "peak_rss_mb": max(w["peak_rss_mb"], workers.get(pid, w)["peak_rss_mb"])}
                frames += rep_.frames
                seconds += dt
            res["ray_worker_processes"] = {str(k): v for k, v in workers.items()}
            ray.shutdown()
        else:
            eps = store.episodes()
            ids, n_frames = eps["id"].to_list(), int(eps["length"].sum())
            decode_frames = decode_seconds = 0.0
            for cam in CAMERAS:
                # Decoded first (timed apart: decoding alone), in batches of batch_size as compute_layer's.
                t0 = time.perf_counter()
                with FrameReader(store, cam) as reader:
                    it = (f for e in ids for f in reader.episode(e))
                    flat = np.empty((n_frames, SIZE, SIZE, 3), np.uint8)
                    k = -1
                    for k, f in enumerate(it):
                        flat[k] = f
                    if k + 1 != n_frames:
                        raise RuntimeError(f"{cam}: decoded {k + 1} frames, the store has {n_frames} steps")
                decode_seconds += time.perf_counter() - t0
                decode_frames += len(flat)
                batches = [flat[i : i + batch_size] for i in range(0, len(flat), batch_size)]
                res["rss_before_mb"] = _vm_hwm_mb()
                with torch.inference_mode():
                    t0 = time.perf_counter()
                    for b in batches:
                        encode_frames(enc, b)
                    dt = time.perf_counter() - t0
                res["per_camera"][cam] = {"frames": len(flat), "seconds": dt, "frames_per_second": len(flat) / dt}
                frames += len(flat)
                seconds += dt
                del flat, batches
            res["decode_frames_per_second"] = decode_frames / decode_seconds
        res.update(frames=int(frames), seconds=seconds, frames_per_second=frames / seconds, peak_rss_mb=_vm_hwm_mb())
        out.put(res)
    except BaseException as e:  # reported by the parent
        out.put({"phase": kind, "error": f"{type(e).__name__}: {e}"})
        raise


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


def free_port() -> int:
    import socket

    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


class LocalRay:
    """A Ray cluster on this machine as on a fleet's: ``ray start --head`` (no CPUs: it runs the
    driver) and ``workers`` nodes joining it (``ray start --address``), each of ``cpus`` CPUs;
    every node a process group of ours, stopped by its id."""

    def __init__(self, workers: int, cpus: int, root: Path) -> None:
        port = free_port()
        self.temp = tempfile.mkdtemp(prefix="ufops-ray-", dir="/tmp")  # short: Ray's socket paths
        self.address = f"127.0.0.1:{port}"
        self.workers = workers
        self.root = root
        root.mkdir(parents=True, exist_ok=True)
        ray_bin = str(Path(sys.executable).parent / "ray")
        # Token authentication, as a cluster should run: every node and the driver (the phase's
        # child, which inherits this process's environment) hold the same token; one for the
        # whole run (Ray reads it once per process).
        os.environ.setdefault("RAY_AUTH_TOKEN", os.urandom(16).hex())
        os.environ["RAY_AUTH_MODE"] = "token"
        env = {**os.environ, "RAY_USAGE_STATS_ENABLED": "0"}
        common = ["--block", "--disable-usage-stats", "--object-store-memory", str(500 << 20),
                  "--node-ip-address", "127.0.0.1"]
        nodes = [["--head", "--port", str(port), "--num-cpus", "0", "--include-dashboard", "false",
                  "--temp-dir", self.temp]]
        nodes += [[f"--address={self.address}", "--num-cpus", str(cpus)] for _ in range(workers)]
        # Nodes on one machine: each its own agent and metrics ports (Ray's defaults are fixed).
        nodes = [[*n, *(a for flag in ("--dashboard-agent-listen-port", "--dashboard-agent-grpc-port",
                                       "--runtime-env-agent-port", "--metrics-export-port")
                        for a in (flag, str(free_port())))] for n in nodes]
        self.procs: List["subprocess.Popen[bytes]"] = []
        self._nodes = [[ray_bin, "start", *common, *args] for args in nodes]
        self._env = env

    def wait(self) -> None:
        """Starts the nodes one after the other (two raylets starting at once on one machine
        can take one node index) and waits for each to join."""
        import ray

        for k, cmd in enumerate(self._nodes):
            with open(self.root / f"node{k}.log", "wb") as log:
                self.procs.append(subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=log,
                                                   stderr=subprocess.STDOUT, env=self._env, start_new_session=True))
            deadline = time.monotonic() + 120
            while True:
                time.sleep(1)
                if self.procs[-1].poll() is not None:
                    raise RuntimeError(f"Ray node {k} exited (logs in {self.root})")
                try:
                    if not ray.is_initialized():
                        ray.init(address=self.address, logging_level="ERROR", log_to_driver=False)
                    if sum(n["Alive"] for n in ray.nodes()) == k + 1:
                        break
                except Exception:
                    if ray.is_initialized():
                        ray.shutdown()
                if time.monotonic() > deadline or self.procs[-1].poll() is not None:
                    raise RuntimeError(f"Ray node {k} did not join in 120 s (logs in {self.root})")
        ray.shutdown()

    def peak_rss_mb(self) -> Dict[str, float]:
        """Peak RSS (VmHWM) of the cluster's own processes (gcs_server, raylet, ...) by kind,
        the largest of each kind; Ray's worker processes are reported by the run itself."""
        out: Dict[str, float] = {}
        for pid in descendants({p.pid for p in self.procs}):
            try:
                status = Path(f"/proc/{pid}/status").read_text()
            except OSError:
                continue
            name = next(line.split()[1] for line in status.splitlines() if line.startswith("Name:"))
            hwm = [int(line.split()[1]) / 1024 for line in status.splitlines() if line.startswith("VmHWM:")]
            if hwm and not name.startswith("ray::"):
                out[name] = max(out.get(name, 0.0), hwm[0])
        return out

    def stop(self) -> None:
        """SIGTERM to each node, then SIGKILL to whatever of them is left after a few seconds."""
        left = descendants({p.pid for p in self.procs})
        for p in self.procs:
            if p.poll() is None:
                os.killpg(p.pid, signal.SIGTERM)
        deadline = time.monotonic() + 5
        for p in self.procs:
            try:
                p.wait(timeout=max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                pass
        for pid in left:
            try:
                os.kill(pid, signal.SIGKILL)
            except OSError:
                pass
        for p in self.procs:
            p.wait(timeout=10)
        shutil.rmtree(self.temp, ignore_errors=True)


def run_phase(ctx: Any, *args: Any) -> Dict[str, Any]:
    q = ctx.Queue()
    p = ctx.Process(target=_phase, args=(*args, q))
    p.start()
    res: Dict[str, Any] = q.get()
    p.join()
    if "error" in res:
        raise RuntimeError(f"phase {res['phase']}: {res['error']}")
    return res


# --- main --------------------------------------------------------------------------------------


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--frames", type=int, default=10_000, help="frames per camera (default 10000)")
    p.add_argument("--out", type=Path, default=None, help="work dir and JSON report (default: a temp dir)")
    p.add_argument("--reps", type=int, default=3)
    p.add_argument("--batch-size", type=int, default=64, help="compute_layer's default")
    p.add_argument("--encoder", choices=["cnn", "resnet18"], default="cnn")
    p.add_argument("--codec", choices=["av1", "h264"], default="av1")
    p.add_argument("--decoder-threads", type=int, default=None,
                   help="set PyAV's thread_count of the videos ufops opens (default: leave ufops's, i.e. auto)")
    p.add_argument("--decode-threads", type=int, default=None,
                   help="compute_layer's decoding threads (default: its own choice, more when the encoder waits)")
    p.add_argument("--ray-workers", default="1,2",
                   help="Ray runs: worker nodes of a local cluster, one encoder actor and one decoding task "
                        "each (comma-separated; '' for none; needs ufops[ray])")
    p.add_argument("--ray-cpus", type=int, default=2, help="CPUs each Ray worker node offers (default 2)")
    target = os.environ.get("CARGO_TARGET_DIR") or str(Path.home() / ".cache" / "ufops-target")
    p.add_argument("--ufops", default=f"{target}/debug/ufops")
    a = p.parse_args()

    started = time.perf_counter()
    tmp = None
    if a.out is None:
        tmp = tempfile.TemporaryDirectory(prefix="ufops-features-bench-")
        a.out = Path(tmp.name)
    a.out = a.out.resolve()  # Ray wants an absolute temp dir
    a.out.mkdir(parents=True, exist_ok=True)
    dataset, data_dir = a.out / "lerobot-v30", a.out / "ufops-data"
    t0 = time.perf_counter()
    ds = write_dataset(dataset, a.frames, a.codec)
    t_write = time.perf_counter() - t0
    print(f"dataset: {ds['episodes']} episodes x 2 cameras, {ds['frames_per_camera']} frames per camera, "
          f"{SIZE}x{SIZE} {ds['codec']}, {ds['video_bytes'] / 1e6:.1f} MB of video, written in {t_write:.1f} s")
    if data_dir.exists():
        shutil.rmtree(data_dir)
    cli = [a.ufops, "--data-dir", str(data_dir)]
    t0 = time.perf_counter()
    subprocess.run([*cli, "init"], check=True, capture_output=True)
    ing = subprocess.run([*cli, "ingest", str(dataset), "--policy", POLICY, "--checkpoint", CHECKPOINT, "--json"],
                         check=True, capture_output=True, text=True)
    t_ingest = time.perf_counter() - t0
    ing_j = json.loads(ing.stdout)
    print(f"ingested in {t_ingest:.1f} s: version {ing_j.get('version')}, {ing_j.get('episodes')} episodes, "
          f"{ing_j.get('steps')} steps")

    ctx = mp.get_context("spawn")
    runs: List[Dict[str, Any]] = []
    ray_workers = [int(w) for w in a.ray_workers.split(",") if w.strip()]
    kinds = ["compute_layer", "encode_only", *[f"ray{w}" for w in ray_workers]]
    for rep in range(a.reps):
        for kind in kinds:
            extra: Dict[str, Any] = {"decode_threads": a.decode_threads}
            cluster = None
            if kind.startswith("ray"):
                w = int(kind[3:])
                cluster = LocalRay(w, a.ray_cpus, a.out / f"ray-{kind}-r{rep}")
                cluster.wait()
                extra.update(ray_address=cluster.address, ray_workers=w)
            try:
                r = run_phase(ctx, kind, str(data_dir), a.encoder, a.batch_size, a.decoder_threads, rep, extra)
                if cluster is not None:
                    r["ray_system_peak_rss_mb"] = cluster.peak_rss_mb()
            finally:
                if cluster is not None:
                    cluster.stop()
            runs.append(r)
            bound = {c: v.get("bound_by", "") for c, v in r["per_camera"].items()}
            print(f"  rep {rep} {kind:13s} {r['frames']} frames in {r['seconds']:.1f} s: "
                  f"{r['frames_per_second']:.0f} frames/s, peak RSS {r['peak_rss_mb']:.0f} MB"
                  + (f", bound by {sorted(set(bound.values()))}" if any(bound.values()) else ""), flush=True)

    def med(kind: str, key: str) -> float:
        return float(statistics.median(r[key] for r in runs if r["phase"] == kind))

    fps_a, fps_b = med("compute_layer", "frames_per_second"), med("encode_only", "frames_per_second")
    fps_dec = med("encode_only", "decode_frames_per_second")
    rss_base = med("compute_layer", "rss_before_mb")
    rss_a = max(r["peak_rss_mb"] for r in runs if r["phase"] == "compute_layer")
    rss_b = max(r["peak_rss_mb"] for r in runs if r["phase"] == "encode_only")
    ratio = fps_a / fps_b
    wall = time.perf_counter() - started
    print()
    print(f"encoder {a.encoder}, batch {a.batch_size}, 1 torch thread, {2 * ds['frames_per_camera']} frames a phase, "
          f"medians of {a.reps}")
    print(f"{'phase':38s} {'frames/s':>9s} {'peak RSS MB':>12s}  (RSS: max of the reps)")
    print(f"{'(a) compute_layer: decode+encode+write':38s} {fps_a:9.0f} {rss_a:12.0f}")
    print(f"{'(b) encode alone (pre-decoded)':38s} {fps_b:9.0f} {rss_b:12.0f}")
    print(f"{'(-) decode alone (FrameReader)':38s} {fps_dec:9.0f} {'':>12s}")
    print(f"{'(-) child after imports + encoder':38s} {'':>9s} {rss_base:12.0f}")
    ray_summary: Dict[str, Any] = {}
    for w in ray_workers:
        kind = f"ray{w}"
        these = [r for r in runs if r["phase"] == kind]
        procs = [p for r in these for p in r["ray_worker_processes"].values()]
        system: Dict[str, float] = {}
        for r in these:
            for k, v in r["ray_system_peak_rss_mb"].items():
                system[k] = max(system.get(k, 0.0), v)
        row = {
            "frames_per_second": med(kind, "frames_per_second"),
            "ratio_to_compute_layer": med(kind, "frames_per_second") / fps_a,
            "driver_peak_rss_mb": max(r["peak_rss_mb"] for r in these),
            "encode_actor_peak_rss_mb": max((p["peak_rss_mb"] for p in procs if p["stage"] == "encode"), default=0.0),
            "decode_worker_peak_rss_mb": max((p["peak_rss_mb"] for p in procs if p["stage"] == "decode"),
                                             default=0.0),
            "system_peak_rss_mb": system,
            "bound_by": sorted({c["bound_by"] for r in these for c in r["per_camera"].values()}),
        }
        ray_summary[kind] = row
        print(f"{f'(r) Ray, {w} worker node(s) x {a.ray_cpus} CPUs':38s} {row['frames_per_second']:9.0f} "
              f"{row['driver_peak_rss_mb']:12.0f}  driver; encoder actor {row['encode_actor_peak_rss_mb']:.0f}, "
              f"decoder {row['decode_worker_peak_rss_mb']:.0f}, "
              + ", ".join(f"{k} {v:.0f}" for k, v in sorted(system.items())) + f" MB; bound by {row['bound_by']}")
    bound_a = sorted({c["bound_by"] for r in runs if r["phase"] == "compute_layer" for c in r["per_camera"].values()})
    print(f"(a) bound by {bound_a}; "
          + "; ".join(f"{k}/(a) = {v['ratio_to_compute_layer']:.2f}" for k, v in ray_summary.items()))
    print(f"(a)/(b) = {ratio:.2f} (goal >= 0.7); peak RSS of (a) = {rss_a:.0f} MB (goal <= 1024); wall {wall:.0f} s")
    report = {
        "command": " ".join([Path(sys.argv[0]).name, *sys.argv[1:]]),
        "machine": {"cpus": os.cpu_count(), "platform": platform.platform(), "python": platform.python_version()},
        "dataset": {**ds, "size": SIZE, "steps_per_episode": STEPS, "write_seconds": t_write,
                    "ingest_seconds": t_ingest},
        "encoder": a.encoder, "batch_size": a.batch_size, "torch_threads": 1, "reps": a.reps,
        "decoder_threads": a.decoder_threads,
        "median_frames_per_second": {"compute_layer": fps_a, "encode_only": fps_b, "decode_only": fps_dec},
        "compute_layer_bound_by": bound_a, "ray": ray_summary, "decode_threads": a.decode_threads,
        "ratio": ratio,
        "peak_rss_mb": {"compute_layer": rss_a, "encode_only": rss_b, "after_imports_and_encoder": rss_base},
        "goals": {"ratio_ge_0.7": ratio >= 0.7, "compute_layer_rss_le_1gb": rss_a <= 1024},
        "wall_seconds": wall, "runs": runs,
    }
    path = a.out / "features_throughput.json"
    path.write_text(json.dumps(report, indent=2))
    print(f"report: {path}" + (" (temp dir, removed)" if tmp else ""))
    if tmp is not None:
        print(json.dumps({k: report[k] for k in ("median_frames_per_second", "ratio", "peak_rss_mb")}))
        tmp.cleanup()


if __name__ == "__main__":
    main()
