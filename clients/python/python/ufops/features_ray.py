"""``ufops.features_ray``: a layer computed by a Ray Data pipeline (``pip install 'ufops[ray]'``).

The same layer as :func:`ufops.features.compute_layer` — the same batches (up to ``batch_size``
frames of one episode), the same preprocessing and encoder call, so the same rows, bit for bit,
on the same kind of machine — computed by a Ray cluster instead of one process:

* the driver (the process that calls :func:`compute_layer_on_ray`) lists the episodes from the
  store or ``ufops serve`` and skips those that hold the layer from the producer already;
* CPU tasks decode runs of consecutive episodes (range reads on the store's media, as
  :class:`ufops.features.FrameReader`) into batches of frames;
* actors holding the encoder (one GPU each with ``num_gpus=1``) encode the batches;
* the driver assembles each episode's rows and writes finished episodes through the store or
  the API, ``commit_every`` at a time, each group one store version.

Ray is the engine and ufops the contract. A task or actor that dies is retried by Ray (its
frames decoded or encoded again); a run that stops (an error, Ctrl-C, a lost driver) loses only
its uncommitted episodes, and a re-run computes only what is missing. Two runs for one producer
at once never write an episode twice: the store re-checks, inside the transaction of each
version, which episodes hold the layer from the producer, and writes only the others.

Stores cross to the workers by pickling: a ``ufops.Store`` is reopened there with the same
arguments (Postgres + S3 on a cluster; the S3 credentials come from each worker's environment,
``AWS_*``), a ``Client.layer_store()`` reconnects with its URL and token.
"""
from __future__ import annotations

import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Dict, Iterator, List, Optional, Sequence

import numpy as np

from ufops.errors import IntegrityError
from ufops.features import (
    FrameReader,
    LayerReport,
    LayerStore,
    Preprocess,
    Producer,
    _Assembler,
    _encode,
    _episode_batches,
    _is_module,
    _plan,
    _Progress,
    _Writer,
)

# Episodes one decoding task reads (consecutive in storage order: a shared video is decoded
# forward within a task, and a killed task loses this much decoding).
EPISODES_PER_TASK = 4
# Encoded batches (rows of the pipeline) handed to an encoder actor per call.
ROWS_PER_CALL = 2
# Heap reserved per decoding task (Ray's `memory`): a batch, a few open videos, PyAV's buffers.
# Also what keeps Ray from fusing decoding into the encoder actors (fused, the actors would
# decode too, and decoding would not scale apart from encoding).
DECODER_MEMORY = 256 << 20


def _peak_rss_mb() -> float:
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024
    except OSError:
        pass
    return float("nan")


def _decode_rows(batch: Dict[str, Any], *, store: Any, camera: str, batch_size: int) -> Iterator[Dict[str, Any]]:
    """A decoding task: each input row names a run of episodes (``\\n``-separated); each output
    row is one batch of one episode's frames, raw uint8 bytes with their shape."""
    pid = os.getpid()
    with FrameReader(store, camera) as reader:
        for run in batch["episodes"]:
            for ep in str(run).split("\n"):
                t0 = time.perf_counter()
                for b in _episode_batches(reader, store.steps([ep]), ep, batch_size):
                    n, h, w, c = b.frames.shape
                    yield {
                        "episode_id": np.array([ep], dtype=object),
                        "length": np.array([b.length], np.int64),
                        "start": np.array([b.start], np.int64),
                        "shape": np.array([[n, h, w, c]], np.int64),
                        "frames": np.array([b.frames.tobytes()], dtype=object),
                        "decode_seconds": np.array([time.perf_counter() - t0]),
                        "decode_pid": np.array([pid], np.int64),
                        "decode_rss_mb": np.array([_peak_rss_mb()]),
                    }
                    t0 = time.perf_counter()


class _EncoderActor:
    """An encoder actor: the encoder built once (given, or made by ``encoder_factory`` on the
    actor: weights loaded where they run), each row's frames one :func:`_encode` call."""

    def __init__(
        self,
        encoder: Any,
        encoder_factory: Optional[Callable[[], Any]],
        preprocess: Optional[Preprocess],
        device: str,
        torch_threads: Optional[int],
    ) -> None:
        if torch_threads is not None:
            import torch

            torch.set_num_threads(torch_threads)
        self.encoder = encoder_factory() if encoder_factory is not None else encoder
        if _is_module(self.encoder):
            self.encoder.to(device)
            self.encoder.eval()
        self.preprocess = preprocess
        self.device = device
        self.pid = os.getpid()

    def __call__(self, batch: Dict[str, Any]) -> Dict[str, Any]:
        feats: List[bytes] = []
        dims: List[int] = []
        seconds: List[float] = []
        for shape, raw in zip(batch["shape"], batch["frames"]):
            # A copy: the preprocessing may write (torch.from_numpy wants a writable array).
            frames = np.frombuffer(raw, np.uint8).reshape(tuple(int(x) for x in shape)).copy()
            t0 = time.perf_counter()
            out = _encode(self.encoder, frames, self.preprocess, self.device)
            seconds.append(time.perf_counter() - t0)
            feats.append(out.tobytes())
            dims.append(out.shape[1])
        k = len(feats)
        return {
            "episode_id": batch["episode_id"],
            "length": batch["length"],
            "start": batch["start"],
            "rows": np.array([int(s[0]) for s in batch["shape"]], np.int64),
            "dim": np.array(dims, np.int64),
            "features": np.array(feats, dtype=object),
            "decode_seconds": batch["decode_seconds"],
            "decode_pid": batch["decode_pid"],
            "decode_rss_mb": batch["decode_rss_mb"],
            "encode_seconds": np.array(seconds),
            "encode_pid": np.full(k, self.pid, np.int64),
            "encode_rss_mb": np.full(k, _peak_rss_mb()),
        }


@dataclass
class RayLayerReport(LayerReport):
    """:class:`ufops.features.LayerReport` of a Ray run, with each worker process seen: its pid
    → ``{"stage": "decode" | "encode", "peak_rss_mb": …}`` (VmHWM as the process last reported
    it), and the driver's own peak RSS."""

    workers: Dict[int, Dict[str, Any]] = field(default_factory=dict)
    driver_peak_rss_mb: float = 0.0


def compute_layer_on_ray(
    store: LayerStore,
    encoder: Any = None,
    *,
    name: str,
    camera: str,
    producer: Producer,
    episodes: Optional[Sequence[str]] = None,
    batch_size: int = 64,
    commit_every: int = 16,
    preprocess: Optional[Preprocess] = None,
    encoder_factory: Optional[Callable[[], Any]] = None,
    encoders: int = 1,
    num_gpus: float = 0.0,
    encoder_cpus: float = 1.0,
    decoders: Optional[int] = None,
    decoder_cpus: float = 1.0,
    decoder_memory: int = DECODER_MEMORY,
    episodes_per_task: int = EPISODES_PER_TASK,
    device: Optional[str] = None,
    torch_threads: Optional[int] = None,
    progress: bool = True,
) -> RayLayerReport:
    """Computes the layer ``name`` as :func:`ufops.features.compute_layer` does (same arguments,
    same rows, same resumable groups), on the Ray cluster this process is connected to
    (``ray.init(address=…)`` first; otherwise Ray starts a local one).

    ``store`` is a ``ufops.Store`` (on a cluster: Postgres + S3) or ``Client(url,
    token).layer_store()``; the workers reopen it. ``encoder`` is pickled to ``encoders``
    actors, or ``encoder_factory`` (a picklable zero-argument callable) builds it on each actor.
    Each actor takes ``num_gpus`` GPUs (``device`` defaults to ``"cuda"`` when that is positive)
    and ``encoder_cpus`` CPUs, and sets ``torch_threads`` when given. Up to ``decoders`` tasks
    (default: as many as the cluster's CPUs allow) of ``decoder_cpus`` CPUs and
    ``decoder_memory`` bytes each decode ``episodes_per_task`` consecutive episodes apiece.

    A worker killed mid-run is retried by Ray; a stopped run (an error, Ctrl-C) commits its
    finished episodes first and loses only what was in flight; a re-run computes what is
    missing; two runs at once write each episode once (the store checks inside each version's
    transaction). The report has each stage's frames and busy seconds, the stage that bounded
    the run, and each worker process's peak RSS."""
    ray = _ray()
    if encoder is None and encoder_factory is None:
        raise ValueError("pass an encoder or an encoder_factory")
    if encoder is not None and encoder_factory is not None:
        raise ValueError("pass an encoder or an encoder_factory, not both")
    if encoders < 1 or episodes_per_task < 1 or (decoders is not None and decoders < 1):
        raise ValueError(f"encoders, decoders and episodes_per_task must be at least 1; got {encoders}, {decoders}, {episodes_per_task}")
    if ray.is_initialized() and num_gpus <= 0:
        cpus = float(ray.cluster_resources().get("CPU", 0.0))
        if encoders * encoder_cpus + decoder_cpus > cpus:
            raise ValueError(
                f"{encoders} encoder actor(s) of {encoder_cpus} CPU leave no {decoder_cpus} CPU of the cluster's "
                f"{cpus:g} to decode on: fewer encoders, or encoder_cpus / decoder_cpus below 1"
            )
    started = time.monotonic()
    producer_dict, todo, base = _plan(store, name, producer, episodes, batch_size, commit_every)
    report = RayLayerReport(**{k: getattr(base, k) for k in base.__dataclass_fields__})
    dev = device or ("cuda" if num_gpus > 0 else "cpu")
    bar = _Progress(name, report.episodes_skipped + len(todo), progress)
    assembler = _Assembler()
    writer = _Writer(store, name, producer_dict, report.producer_hash, commit_every, report)
    decode, encode = report.stages["decode"], report.stages["encode"]
    if not todo:
        return _finish(report, started, bar)

    runs = ["\n".join(todo[i : i + episodes_per_task]) for i in range(0, len(todo), episodes_per_task)]
    data = ray.data
    ds = data.from_items([{"episodes": r} for r in runs], override_num_blocks=len(runs))
    ds = ds.map_batches(
        _decode_rows,
        batch_size=None,
        batch_format="numpy",
        fn_kwargs={"store": store, "camera": camera, "batch_size": batch_size},
        compute=data.TaskPoolStrategy(size=decoders),
        num_cpus=decoder_cpus,
        memory=decoder_memory,
    )
    ds = ds.map_batches(
        _EncoderActor,
        batch_size=ROWS_PER_CALL,
        batch_format="numpy",
        fn_constructor_kwargs={
            "encoder": encoder,
            "encoder_factory": encoder_factory,
            "preprocess": preprocess,
            "device": dev,
            "torch_threads": torch_threads,
        },
        compute=data.ActorPoolStrategy(size=encoders),
        num_cpus=encoder_cpus,
        num_gpus=num_gpus,
    )
    ctx = data.DataContext.get_current()
    saved = ctx.enable_progress_bars
    if not progress:
        ctx.enable_progress_bars = False
    decoders_seen: Dict[int, float] = {}
    encoders_seen: Dict[int, float] = {}
    it = iter(ds.iter_batches(batch_size=None, batch_format="numpy", prefetch_batches=2))
    try:
        bar.update(report.episodes_skipped, 0)
        for batch in it:
            for k in range(len(batch["episode_id"])):
                ep = str(batch["episode_id"][k])
                n, dim = int(batch["rows"][k]), int(batch["dim"][k])
                rows = np.frombuffer(batch["features"][k], np.float32).reshape(n, dim)
                decode.frames += n
                decode.seconds += float(batch["decode_seconds"][k])
                encode.frames += n
                encode.seconds += float(batch["encode_seconds"][k])
                decoders_seen[int(batch["decode_pid"][k])] = float(batch["decode_rss_mb"][k])
                encoders_seen[int(batch["encode_pid"][k])] = float(batch["encode_rss_mb"][k])
                report.frames += n
                done = assembler.add(ep, int(batch["length"][k]), int(batch["start"][k]), rows)
                if done is not None:
                    writer.add(ep, done)
            decode.workers, encode.workers = max(1, len(decoders_seen)), max(1, len(encoders_seen))
            bar.update(report.episodes_skipped + report.episodes_written + len(writer.finished), report.frames,
                       stages=report.stages)
        writer.commit()
        if len(assembler):
            raise IntegrityError(f"layer {name}: {len(assembler)} episode(s) did not get all their rows from the pipeline")
    except BaseException:
        writer.salvage()
        raise
    finally:
        close = getattr(it, "close", None)
        if close is not None:
            close()
        ctx.enable_progress_bars = saved
        report.workers = {
            **{pid: {"stage": "decode", "peak_rss_mb": rss} for pid, rss in decoders_seen.items()},
            **{pid: {"stage": "encode", "peak_rss_mb": rss} for pid, rss in encoders_seen.items()},
        }
    return _finish(report, started, bar)


def _finish(report: RayLayerReport, started: float, bar: _Progress) -> RayLayerReport:
    report.seconds = time.monotonic() - started
    report.frames_per_second = report.frames / report.seconds if report.seconds > 0 else 0.0
    report.driver_peak_rss_mb = _peak_rss_mb()
    bar.update(report.episodes_skipped + report.episodes_written, report.frames, final=True, stages=report.stages)
    return report


def _ray() -> Any:
    try:
        import ray
        import ray.data  # noqa: F401
    except ImportError as e:
        raise ImportError("computing a layer on Ray needs Ray Data: pip install 'ufops[ray]'") from e
    return ray
