"""``ufops.features``: layers of encoder features, so verifiers see what the policy sees.

A verifier that scores a vision policy's actions should read the policy's own view of the scene:
the embedding of its frozen vision encoder, not raw pixels. :func:`compute_layer` decodes a
camera's frames from the store (videos by range reads, or PNG columns), runs them in batches
through the encoder with the policy's preprocessing, and writes the features back as a *layer*:
a named per-step float32 column (``features.dp-resnet18``, 512-d) attached to the existing
episodes by ``(episode_id, t)`` and tagged with its :class:`Producer`. ``Store.steps(ids,
layers=[name])`` then returns it as the column ``obs.<name>``.

* :func:`compute_layer` — resumable and idempotent: episodes that already hold the layer from the
  same producer are skipped, and every ``commit_every`` finished episodes become one store
  version, so an interrupted run goes on where it stopped. Decoding runs in threads (more of them
  when the encoder waits for frames); the report says what each stage cost.
  :func:`ufops.features_ray.compute_layer_on_ray` computes the same rows on a Ray cluster.
* :func:`encode_frames` — the same preprocessing and encoder call on live frames, so the robot's
  features and the store's come out of one function.
* :class:`FrameReader` — a camera's frames of an episode as uint8 ``(H, W, C)`` arrays.
* :func:`producer_of` — who made a layer: encoder, policy, checkpoint and the sha256 of the
  encoder's weights.

torch, PyAV (``pip install av``) and Pillow (``pip install pillow``, for PNG columns) are imported
by the functions that need them, so ``import ufops`` works without them.
"""

# One module past 700 lines: it is the public namespace `ufops.features` (encoders, frame
# decoding, layer computation), which users import as one.
from __future__ import annotations

import contextlib
import hashlib
import importlib
import io
import os
import queue
import sys
import threading
import time
import warnings
from collections import OrderedDict
from dataclasses import asdict, dataclass, field
from typing import (
    TYPE_CHECKING,
    Any,
    Callable,
    ContextManager,
    Dict,
    Iterable,
    Iterator,
    List,
    Mapping,
    Optional,
    Protocol,
    Sequence,
    Tuple,
    Union,
)

import numpy as np
import numpy.typing as npt

from ufops.errors import IntegrityError, NotFoundError

if TYPE_CHECKING:
    import polars as pl
    from _typeshed import WriteableBuffer

Frames = npt.NDArray[np.uint8]  # (B, H, W, C) or one (H, W, C) frame
Features = npt.NDArray[np.float32]  # (B, D)
Preprocess = Callable[[Frames], Any]

# Range reads of a video ask for at least this much: one request per MB of video, not per the
# decoder's 32 KB buffer (each request to S3 costs tens of ms).
READ_AHEAD = 1 << 20
# Decode forward instead of seeking when the next wanted frame is at most this far ahead.
SEEK_AHEAD_SECONDS = 2.0
# Open videos kept between episodes (LeRobot v3 puts many episodes back to back in one video).
OPEN_VIDEOS = 4
# Batches of decoded frames waiting for the encoder: decoding runs ahead by at most this much.
QUEUED_BATCHES = 3


def _module(name: str, pip_name: str, why: str) -> Any:
    try:
        return importlib.import_module(name)
    except ImportError as e:
        raise ImportError(f"{why}: pip install {pip_name}") from e


class ObjectReader(Protocol):
    """What reading a store object takes (``ufops.Store`` has it)."""

    def object_size(self, path: str, /) -> int: ...

    def read_object_range(self, path: str, start: int, end: int, /) -> bytes: ...


class StepsReader(ObjectReader, Protocol):
    """What reading an episode's frames takes (``ufops.Store`` has it)."""

    def steps(self, ids: Sequence[str], /) -> "pl.DataFrame": ...


class LayerStore(StepsReader, Protocol):
    """What :func:`compute_layer` needs from a store (``ufops.Store`` has it)."""

    def episodes(self) -> "pl.DataFrame": ...

    def producer_hash(self, producer: Dict[str, Any], /) -> str: ...

    def layer_episodes(self, name: str, producer_hash: str, /) -> Sequence[str]: ...

    def write_layer(
        self, name: str, producer: Dict[str, Any], values: Dict[str, Features], /
    ) -> Mapping[str, Any]: ...


# --- producers ---------------------------------------------------------------------------------


@dataclass(frozen=True)
class Producer:
    """Who made a layer. Two runs with equal producers make the same layer (the store keeps one);
    a new checkpoint or changed weights make another. Name the preprocessing in ``encoder``
    (``"resnet18/224-imagenet"``): it is code, and only its name can be recorded."""

    encoder: str
    policy: str
    checkpoint: str
    content_hash: str

    def __post_init__(self) -> None:
        for k, v in asdict(self).items():
            if not isinstance(v, str) or not v:
                raise ValueError(f"Producer.{k} must be a non-empty string; got {v!r}")

    def to_dict(self) -> Dict[str, str]:
        return asdict(self)


def state_dict_sha256(module: Any) -> str:
    """sha256 over a module's ``state_dict`` (parameters and buffers): each entry's name, dtype,
    shape and raw bytes, in name order. Equal weights give equal hashes, whatever the device."""
    import torch

    h = hashlib.sha256()
    state = module.state_dict()
    for name in sorted(state):
        v = state[name]
        if not isinstance(v, torch.Tensor):
            # `get_extra_state` values: recorded by their repr.
            h.update(f"{name}\0extra\0{v!r}\0".encode())
            continue
        t = v.detach()
        if t.layout != torch.strided:
            t = t.to_dense()
        t = t.cpu().contiguous()
        h.update(f"{name}\0{t.dtype}\0{list(t.shape)}\0{t.numel() * t.element_size()}\0".encode())
        if t.numel():
            # Bytes of any dtype (bfloat16 has no numpy twin), shared with the tensor, not copied.
            h.update(t.reshape(-1).view(torch.uint8).numpy())
    return h.hexdigest()


def producer_of(module: Any, *, encoder: str, policy: str, checkpoint: str) -> Producer:
    """The :class:`Producer` of a ``torch.nn.Module`` encoder, its ``content_hash`` the sha256
    of its weights (:func:`state_dict_sha256`)."""
    return Producer(encoder=encoder, policy=policy, checkpoint=checkpoint, content_hash=state_dict_sha256(module))


# --- reading store objects ---------------------------------------------------------------------


class ObjectFile(io.RawIOBase):
    """A store object as a seekable read-only file. Every miss is one range read of at least
    ``read_ahead`` bytes, so decoding an episode reads a few MB of a multi-GB video, never all
    of it. ``requests`` and ``bytes_fetched`` count what was read."""

    def __init__(self, store: ObjectReader, path: str, *, read_ahead: int = READ_AHEAD) -> None:
        super().__init__()
        self._store = store
        self.path = path
        self.size = int(store.object_size(path))
        self._read_ahead = max(1, int(read_ahead))
        self._pos = 0
        self._buf = b""
        self._buf_start = 0
        self.requests = 0
        self.bytes_fetched = 0

    def readable(self) -> bool:
        return True

    def seekable(self) -> bool:
        return True

    def tell(self) -> int:
        return self._pos

    def seek(self, offset: int, whence: int = io.SEEK_SET) -> int:
        if whence == io.SEEK_SET:
            pos = offset
        elif whence == io.SEEK_CUR:
            pos = self._pos + offset
        elif whence == io.SEEK_END:
            pos = self.size + offset
        else:
            raise ValueError(f"invalid whence {whence}")
        if pos < 0:
            raise ValueError(f"{self.path}: negative seek position {pos}")
        self._pos = pos
        return pos

    def readinto(self, buffer: "WriteableBuffer") -> int:
        if self.closed:
            raise ValueError(f"{self.path}: read from a closed file")
        view = memoryview(buffer).cast("B")
        want = min(len(view), self.size - self._pos)
        if want <= 0:
            return 0
        off = self._pos - self._buf_start
        if not 0 <= off < len(self._buf):
            end = min(self.size, self._pos + max(want, self._read_ahead))
            data = self._store.read_object_range(self.path, self._pos, end)
            if len(data) != end - self._pos:
                raise IntegrityError(
                    f"{self.path}: asked for bytes {self._pos}..{end} of {self.size}, got {len(data)}"
                )
            self.requests += 1
            self.bytes_fetched += len(data)
            self._buf, self._buf_start, off = bytes(data), self._pos, 0
        n = min(want, len(self._buf) - off)
        view[:n] = self._buf[off : off + n]
        self._pos += n
        return n


# --- decoding frames ---------------------------------------------------------------------------


class _Video:
    """One open video, decoded forward from where the last request stopped; seeks only when the
    wanted frame is behind or more than SEEK_AHEAD_SECONDS ahead."""

    def __init__(self, file: ObjectFile, name: str) -> None:
        av = _module("av", "av", "decoding videos needs PyAV")
        self.name = name
        self.file = file
        self.container = av.open(file, mode="r")
        streams = self.container.streams.video
        if not streams:
            self.container.close()
            raise IntegrityError(f"{name}: no video stream")
        self.stream = streams[0]
        rate = self.stream.average_rate or self.stream.guessed_rate
        self.period: Optional[float] = 1.0 / float(rate) if rate else None
        self._frames: Optional[Iterator[Any]] = None
        self._cur: Optional[Tuple[float, Any]] = None
        self._next: Optional[Tuple[float, Any]] = None

    def close(self) -> None:
        self.container.close()
        self.file.close()

    def _decode(self) -> Optional[Tuple[float, Any]]:
        assert self._frames is not None
        for f in self._frames:
            if f.pts is None:
                continue
            return float(f.pts * f.time_base), f
        return None

    def _advance(self) -> None:
        self._cur = self._next
        self._next = self._decode() if self._next is not None else None

    def _restart(self, at: float) -> None:
        """Decodes from the keyframe at or before ``at`` seconds (from the start when ``at`` is 0)."""
        self.container.seek(max(0, int(at / self.stream.time_base)), stream=self.stream, backward=True)
        self._frames = iter(self.container.decode(self.stream))
        self._cur = self._decode()
        self._next = self._decode() if self._cur is not None else None

    def frames(self, timestamps: Sequence[float], tol: float) -> Iterator[Tuple[float, Optional[Any]]]:
        """For each wanted time, the frame whose pts time is nearest within ``tol`` (None when
        there is none). Times must not decrease."""
        for ts in timestamps:
            cur = self._cur
            if self._frames is None:
                at: Optional[float] = ts - tol if ts > SEEK_AHEAD_SECONDS else 0.0
            elif cur is None or ts < cur[0] - tol or ts > cur[0] + SEEK_AHEAD_SECONDS:
                at = max(0.0, ts - tol)
            else:
                at = None
            if at is not None:
                self._restart(at)
                if at > 0 and (self._cur is None or self._cur[0] > ts + tol):
                    # The seek landed after the frame (a sparse index): decode from the start.
                    self._restart(0.0)
            while self._cur is not None:
                if self._cur[0] < ts - tol:
                    self._advance()
                elif self._next is not None and abs(self._next[0] - ts) < abs(self._cur[0] - ts):
                    self._advance()
                else:
                    break
            cur = self._cur
            if cur is not None and abs(cur[0] - ts) <= tol:
                yield ts, cur[1]
            else:
                yield ts, None


def _png_frame(data: bytes) -> Frames:
    image_mod = _module("PIL.Image", "pillow", "decoding PNG frames needs Pillow")
    with image_mod.open(io.BytesIO(data)) as im:
        if im.mode == "P":
            im = im.convert("RGBA" if "transparency" in im.info else "RGB")
        elif im.mode == "1":
            im = im.convert("L")
        if im.mode not in ("L", "LA", "RGB", "RGBA"):
            raise TypeError(f"PNG frames must be 8-bit (L, LA, RGB, RGBA); got mode {im.mode}")
        a = np.asarray(im, dtype=np.uint8)
    return a[:, :, None] if a.ndim == 2 else a


def _camera_columns(columns: Sequence[str], camera: str) -> Tuple[str, str, str]:
    """("video", path column, timestamp column) or ("png", image column, "") of a camera; the
    LeRobot key (``observation.images.front``) names the store's camera ``images.front``."""
    names = [camera]
    if camera.startswith("observation."):
        names.append(camera[len("observation.") :])
    for c in names:
        if f"media.{c}.path" in columns and f"media.{c}.timestamp" in columns:
            return "video", f"media.{c}.path", f"media.{c}.timestamp"
        if f"image.{c}" in columns:
            return "png", f"image.{c}", ""
    cams = sorted(
        {c[len("media.") : -len(".path")] for c in columns if c.startswith("media.") and c.endswith(".path")}
        | {c[len("image.") :] for c in columns if c.startswith("image.")}
    )
    raise NotFoundError(f"no camera {camera!r} in the steps; cameras: {cams}")


class FrameReader:
    """A camera's frames, episode by episode, as uint8 ``(H, W, C)`` arrays: from its video
    (``media.<camera>.path`` / ``.timestamp``, decoded with range reads; up to OPEN_VIDEOS stay
    open so back-to-back episodes decode forward) or from its PNG column (``image.<camera>``)."""

    def __init__(self, store: StepsReader, camera: str, *, read_ahead: int = READ_AHEAD) -> None:
        self.store = store
        self.camera = camera
        self.read_ahead = read_ahead
        self._videos: "OrderedDict[str, _Video]" = OrderedDict()
        self._closed_requests = 0
        self._closed_bytes = 0

    @property
    def requests(self) -> int:
        """Range reads of videos so far."""
        return self._closed_requests + sum(v.file.requests for v in self._videos.values())

    @property
    def bytes_fetched(self) -> int:
        """Bytes of videos read so far."""
        return self._closed_bytes + sum(v.file.bytes_fetched for v in self._videos.values())

    def _close_video(self, v: "_Video") -> None:
        self._closed_requests += v.file.requests
        self._closed_bytes += v.file.bytes_fetched
        v.close()

    def __enter__(self) -> "FrameReader":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        while self._videos:
            self._close_video(self._videos.popitem(last=False)[1])

    def _video(self, path: str) -> _Video:
        v = self._videos.pop(path, None)
        if v is None:
            v = _Video(ObjectFile(self.store, path, read_ahead=self.read_ahead), path)
            while len(self._videos) >= OPEN_VIDEOS:
                self._close_video(self._videos.popitem(last=False)[1])
        self._videos[path] = v
        return v

    def episode(self, episode_id: str) -> Iterator[Frames]:
        """The frames of one episode, in step order (``store.steps`` of it read first)."""
        return self.frames(self.store.steps([episode_id]))

    def frames(self, steps: "pl.DataFrame") -> Iterator[Frames]:
        """The frames of one episode's steps (a ``Store.steps`` frame), one per row in row order."""
        if steps.height == 0:
            return
        episode = str(steps["episode_id"][0]) if "episode_id" in steps.columns else "?"
        kind, col, ts_col = _camera_columns(steps.columns, self.camera)
        if kind == "png":
            for data in steps[col]:
                if data is None:
                    raise IntegrityError(f"episode {episode}: camera {self.camera}: a step has no image")
                yield _png_frame(data)
            return
        paths = steps[col].to_list()
        times = steps[ts_col].to_list()
        start = 0
        while start < len(paths):
            # A run of steps in one video (an episode is normally one run).
            stop = start + 1
            while stop < len(paths) and paths[stop] == paths[start]:
                stop += 1
            yield from self._video_run(episode, paths[start], times[start:stop])
            start = stop

    def _video_run(self, episode: str, path: str, times: List[float]) -> Iterator[Frames]:
        if any(b < a for a, b in zip(times, times[1:])):
            raise IntegrityError(f"episode {episode}: camera {self.camera}: frame times decrease in {path}")
        video = self._video(path)
        if video.period is not None:
            tol = video.period / 2
        else:
            gaps = [b - a for a, b in zip(times, times[1:]) if b > a]
            tol = min(gaps) / 2 if gaps else 1e-3
        for ts, frame in video.frames(times, tol):
            if frame is None:
                raise IntegrityError(
                    f"episode {episode}: camera {self.camera}: no frame at {ts:.6f} s in {path} "
                    f"(within {tol:.6f} s)"
                )
            yield frame.to_ndarray(format="rgb24")


# --- encoding ----------------------------------------------------------------------------------


def to_tensor(frames: Frames) -> Any:
    """The default preprocessing: uint8 ``(B, H, W, C)`` frames as a float32 ``(B, C, H, W)``
    torch tensor in [0, 1] (torchvision's ``ToTensor``). Policies that normalise or resize pass
    their own."""
    import torch

    x = torch.from_numpy(np.ascontiguousarray(frames)).permute(0, 3, 1, 2)
    return x.to(torch.float32).div_(255.0).contiguous()


def _is_module(encoder: Any) -> bool:
    torch = sys.modules.get("torch")
    return torch is not None and isinstance(encoder, torch.nn.Module)


def _no_grad() -> ContextManager[Any]:
    torch = sys.modules.get("torch")
    return torch.inference_mode() if torch is not None else contextlib.nullcontext()


def _as_frames(frames: Union[Frames, Sequence[Frames]]) -> Frames:
    a = frames if isinstance(frames, np.ndarray) else np.stack([np.asarray(f) for f in frames])
    if a.dtype != np.uint8:
        raise TypeError(f"frames must be uint8; got {a.dtype}")
    if a.ndim != 4:
        raise ValueError(f"frames must be (B, H, W, C) or one (H, W, C) frame; got shape {a.shape}")
    return a


def _encode(encoder: Callable[[Any], Any], frames: Frames, preprocess: Optional[Preprocess], device: str) -> Features:
    x = (preprocess or to_tensor)(frames)
    torch = sys.modules.get("torch")
    if torch is not None and isinstance(x, torch.Tensor):
        x = x.to(device)
    with _no_grad():
        out = encoder(x)
    if torch is not None and isinstance(out, torch.Tensor):
        out = out.detach().to("cpu", torch.float32).numpy()
    try:
        a = np.asarray(out, dtype=np.float32)
    except (TypeError, ValueError) as e:
        raise TypeError(f"the encoder must return a (B, D) array or tensor; got {type(out).__name__}") from e
    if a.ndim != 2 or a.shape[0] != len(frames):
        raise ValueError(
            f"the encoder returned shape {a.shape} for {len(frames)} frames: it must return (B, D) "
            "(pool or flatten feature maps)"
        )
    return np.ascontiguousarray(a)


def encode_frames(
    encoder: Callable[[Any], Any],
    frames: Union[Frames, Sequence[Frames]],
    *,
    preprocess: Optional[Preprocess] = None,
    device: str = "cpu",
) -> Features:
    """Features of frames exactly as :func:`compute_layer` computes them: uint8 ``(B, H, W, C)``
    frames (or a list of ``(H, W, C)`` ones) give float32 ``(B, D)``; one ``(H, W, C)`` frame
    gives ``(D,)``. ``preprocess`` (default :func:`to_tensor`) makes the encoder's input, which
    goes to ``device`` when it is a tensor; a ``torch.nn.Module`` runs in eval mode (restored
    after) under ``torch.inference_mode``."""
    single = isinstance(frames, np.ndarray) and frames.ndim == 3
    batch = _as_frames(np.asarray(frames)[None] if single else frames)
    training = _is_module(encoder) and bool(getattr(encoder, "training"))
    if training:
        getattr(encoder, "eval")()
    try:
        out = _encode(encoder, batch, preprocess, device)
    finally:
        if training:
            getattr(encoder, "train")()
    return out[0] if single else out


# --- computing a layer -------------------------------------------------------------------------


@dataclass
class StageStats:
    """One stage of a layer's computation (``decode``, ``encode``, ``write``): the frames it
    handled, the seconds its workers were busy (summed over workers; waiting for the next stage
    is not busy) and how many workers it had. ``frames_per_second`` is one worker's rate while
    busy; ``capacity`` (rate x workers) is what the stage can give the whole computation."""

    frames: int = 0
    seconds: float = 0.0
    workers: int = 1

    @property
    def frames_per_second(self) -> float:
        return self.frames / self.seconds if self.seconds > 0 else 0.0

    @property
    def capacity(self) -> float:
        return self.frames_per_second * self.workers

    def to_dict(self) -> Dict[str, float]:
        return {**asdict(self), "frames_per_second": self.frames_per_second, "capacity": self.capacity}


STAGES = ("decode", "encode", "write")


@dataclass
class LayerReport:
    """What :func:`compute_layer` (or :func:`ufops.features_ray.compute_layer_on_ray`) did.
    ``stages`` says what each stage cost (:class:`StageStats`) and ``bound_by`` names the one of
    least capacity: the stage to give more workers (decoders, encoders) to go faster."""

    episodes_written: int
    episodes_skipped: int
    frames: int
    seconds: float
    frames_per_second: float
    versions: List[int] = field(default_factory=list)
    producer_hash: str = ""
    stages: Dict[str, StageStats] = field(default_factory=lambda: {s: StageStats() for s in STAGES})

    @property
    def bound_by(self) -> str:
        """The stage of least capacity among those that handled frames ("" before any did)."""
        busy = {k: s.capacity for k, s in self.stages.items() if s.frames and s.seconds > 0}
        return min(busy, key=lambda k: busy[k]) if busy else ""


@dataclass
class _Batch:
    """Rows ``start .. start + len(frames)`` of an episode of ``length`` steps."""

    frames: Frames
    episode_id: str
    length: int
    start: int


_DONE = object()


def _episode_batches(reader: FrameReader, steps: "pl.DataFrame", episode_id: str, batch_size: int) -> Iterator[_Batch]:
    """An episode's frames in batches of ``batch_size`` from its first step (the last one
    shorter; a change of frame shape cuts one too). A batch never holds two episodes' frames,
    so what the encoder sees — and, on one machine, the bits of every row — depends on the
    episode and ``batch_size`` only: not on which other episodes a run computes, how many
    decoders run, or where (one process or a Ray cluster)."""
    length = steps.height
    if length == 0:
        raise NotFoundError(f"episode {episode_id} has no steps")
    if steps["t"].to_list() != list(range(length)):
        raise IntegrityError(f"episode {episode_id}: its steps are not t = 0..{length - 1} in order")
    buf: Optional[Frames] = None
    n = start = 0
    for t, frame in enumerate(reader.frames(steps)):
        if buf is None or frame.shape != buf.shape[1:]:
            if n and buf is not None:
                yield _Batch(buf[:n], episode_id, length, start)
            buf, n, start = np.empty((min(batch_size, length - t), *frame.shape), np.uint8), 0, t
        buf[n] = frame
        n += 1
        if n == len(buf):
            yield _Batch(buf, episode_id, length, start)
            buf, n = None, 0
    if n and buf is not None:
        yield _Batch(buf[:n], episode_id, length, start)


class _EpisodeDealer:
    """The episodes to decode, dealt to decoding threads a run of ``take`` consecutive ones at a
    time (in storage order: a shared video is decoded forward within a run)."""

    def __init__(self, episodes: Sequence[str], take: int) -> None:
        self._episodes = list(episodes)
        self._next = 0
        self.take_size = max(1, take)
        self._lock = threading.Lock()

    def remaining(self) -> int:
        with self._lock:
            return len(self._episodes) - self._next

    def take(self) -> List[str]:
        with self._lock:
            run = self._episodes[self._next : self._next + self.take_size]
            self._next += len(run)
            return run


def _decode_batches(
    store: StepsReader,
    camera: str,
    dealer: _EpisodeDealer,
    batch_size: int,
    out: "queue.Queue[Any]",
    stop: threading.Event,
    stats: StageStats,
    lock: threading.Lock,
) -> None:
    """A decoding thread: batches of the episodes it is dealt into ``out``, then _DONE; an
    exception goes into ``out`` instead. Its busy time (not the time blocked on a full queue)
    is added to ``stats``."""

    def put(item: Any) -> bool:
        # Up to QUEUED_BATCHES queued per running thread (the queue holds room for the most).
        while not stop.is_set():
            if out.qsize() < QUEUED_BATCHES * max(1, stats.workers) or not isinstance(item, _Batch):
                try:
                    out.put(item, timeout=0.1)
                    return True
                except queue.Full:
                    pass
            else:
                time.sleep(0.002)
        return False

    busy_since = time.perf_counter()

    def account(frames: int) -> None:
        nonlocal busy_since
        now = time.perf_counter()
        with lock:
            stats.frames += frames
            stats.seconds += now - busy_since

    try:
        with FrameReader(store, camera) as reader:
            while not stop.is_set():
                run = dealer.take()
                if not run:
                    break
                for ep in run:
                    for batch in _episode_batches(reader, store.steps([ep]), ep, batch_size):
                        account(len(batch.frames))
                        if not put(batch):
                            return
                        busy_since = time.perf_counter()
                    if stop.is_set():
                        return
        put(_DONE)
    except BaseException as e:  # handed to the encoding thread, which raises it
        put(e)


class _Progress:
    """The progress line on stderr: episodes and frames done, the overall rate and each stage's
    (one worker's, while busy)."""

    def __init__(self, name: str, total: int, enabled: bool) -> None:
        self.name, self.total, self.enabled = name, total, enabled
        self.tty = enabled and sys.stderr.isatty()
        self.start = time.monotonic()
        self.last = 0.0

    def update(self, episodes: int, frames: int, final: bool = False, stages: Optional[Mapping[str, StageStats]] = None) -> None:
        if not self.enabled:
            return
        now = time.monotonic()
        if not final and now - self.last < (0.5 if self.tty else 10.0):
            return
        self.last = now
        rate = frames / max(now - self.start, 1e-9)
        line = f"{self.name}: {episodes}/{self.total} episodes, {frames} frames, {rate:.0f} frames/s"
        busy = [
            f"{k} {s.frames_per_second:.0f}" + (f" x{s.workers}" if s.workers > 1 else "")
            for k, s in (stages or {}).items()
            if s.frames
        ]
        if busy:
            line += " (" + ", ".join(busy) + " frames/s)"
        sys.stderr.write(("\r" + line + ("\n" if final else "")) if self.tty else line + "\n")
        sys.stderr.flush()


class _Assembler:
    """Encoded batches into whole episodes: an episode's array is handed back once every one of
    its rows has arrived. A row given twice (a retried task) is written over with the same
    values, never counted twice."""

    def __init__(self) -> None:
        self.dim: Optional[int] = None
        self._filling: Dict[str, Tuple[Features, npt.NDArray[np.bool_]]] = {}

    def __len__(self) -> int:
        return len(self._filling)

    def add(self, episode_id: str, length: int, start: int, rows: Features) -> Optional[Features]:
        if self.dim is None:
            self.dim = rows.shape[1]
        elif rows.shape[1] != self.dim:
            raise ValueError(f"the encoder returned {rows.shape[1]} features, earlier {self.dim}")
        if not np.isfinite(rows).all():
            raise ValueError(f"episode {episode_id}: the encoder returned non-finite features")
        if start < 0 or start + len(rows) > length:
            raise IntegrityError(f"episode {episode_id}: rows {start}..{start + len(rows)} of {length}")
        entry = self._filling.get(episode_id)
        if entry is None:
            entry = self._filling[episode_id] = (np.empty((length, self.dim), np.float32), np.zeros(length, bool))
        arr, seen = entry
        arr[start : start + len(rows)] = rows
        seen[start : start + len(rows)] = True
        if seen.all():
            del self._filling[episode_id]
            return arr
        return None


class _Writer:
    """Finished episodes into the store, ``commit_every`` at a time, each group one
    ``write_layer`` call (one version); counts into ``report``."""

    def __init__(self, store: LayerStore, name: str, producer: Dict[str, Any], phash: str, commit_every: int, report: LayerReport) -> None:
        self.store, self.name, self.producer, self.phash = store, name, producer, phash
        self.commit_every = commit_every
        self.report = report
        self.finished: Dict[str, Features] = {}
        self.failed = False

    def add(self, episode_id: str, values: Features) -> None:
        self.finished[episode_id] = values
        if len(self.finished) >= self.commit_every:
            self.commit()

    def commit(self) -> None:
        if not self.finished:
            return
        started = time.perf_counter()
        try:
            res = self.store.write_layer(self.name, self.producer, dict(self.finished))
        except BaseException:
            self.failed = True
            raise
        if res.get("producer_hash", self.phash) != self.phash:
            self.failed = True
            raise IntegrityError(f"layer {self.name}: the store wrote producer {res['producer_hash']}, not {self.phash}")
        stage = self.report.stages["write"]
        stage.frames += sum(len(v) for v in self.finished.values())
        stage.seconds += time.perf_counter() - started
        self.report.episodes_written += int(res["episodes_written"])
        self.report.episodes_skipped += int(res["episodes_skipped"])
        if res.get("version") is not None:
            self.report.versions.append(int(res["version"]))
        self.finished.clear()

    def salvage(self) -> None:
        """After an error or Ctrl-C: commits the finished episodes, so the next run resumes after
        them (unless writing was what failed); a second error is only warned about."""
        if self.finished and not self.failed:
            try:
                self.commit()
            except Exception as e:  # the first error is the one to raise
                warnings.warn(f"layer {self.name}: could not write the {len(self.finished)} finished episodes: {e}")


def _storage_order(store: LayerStore, ids: Optional[Sequence[str]]) -> List[str]:
    """The episodes to compute (all visible ones when ``ids`` is None) in storage order: steps
    files read front to back, and a shared video decoded forward rather than by seeks."""
    eps = store.episodes()
    cols = ["data_file", "row_group", "row_offset"]
    order: List[str] = (
        eps.sort([c for c in cols if c in eps.columns], nulls_last=True)["id"].to_list()
        if all(c in eps.columns for c in cols)
        else eps["id"].to_list()
    )
    if ids is None:
        return order
    wanted = list(dict.fromkeys(ids))
    known = set(order)
    missing = [i for i in wanted if i not in known]
    if missing:
        raise NotFoundError(f"episode not found: {missing[0]}" + (f" (and {len(missing) - 1} more)" if len(missing) > 1 else ""))
    chosen = set(wanted)
    return [i for i in order if i in chosen]


def _plan(store: LayerStore, name: str, producer: Producer, episodes: Optional[Sequence[str]], batch_size: int,
          commit_every: int) -> Tuple[Dict[str, Any], List[str], LayerReport]:
    """The producer as a dict, the episodes still to compute (storage order), and the report
    started with those skipped."""
    if batch_size < 1 or commit_every < 1:
        raise ValueError(f"batch_size and commit_every must be at least 1; got {batch_size}, {commit_every}")
    producer_dict: Dict[str, Any] = producer.to_dict()
    phash = store.producer_hash(producer_dict)
    order = _storage_order(store, episodes)
    done = set(store.layer_episodes(name, phash))
    todo = [e for e in order if e not in done]
    return producer_dict, todo, LayerReport(0, len(order) - len(todo), 0, 0.0, 0.0, [], phash)


# The most decoding threads compute_layer starts by itself; it adds one when the encoder waited
# for frames more than STARVED of its own busy time over at least RAMP_BATCHES batches.
AUTO_DECODE_THREADS = 4
STARVED = 0.5
RAMP_BATCHES = 4
# Episodes dealt to a decoding thread at a time.
EPISODES_PER_TAKE = 2


def compute_layer(
    store: LayerStore,
    encoder: Callable[[Any], Any],
    *,
    name: str,
    camera: str,
    producer: Producer,
    episodes: Optional[Sequence[str]] = None,
    batch_size: int = 64,
    commit_every: int = 16,
    preprocess: Optional[Preprocess] = None,
    device: str = "cpu",
    progress: bool = True,
    decode_threads: Optional[int] = None,
) -> LayerReport:
    """Computes the layer ``name`` — ``encoder`` applied to ``camera``'s frames — for
    ``episodes`` (default: every visible episode) and writes it into ``store``.

    ``encoder`` is the policy's frozen vision encoder: a ``torch.nn.Module`` (moved to ``device``,
    run in eval mode under ``torch.inference_mode``; its mode is restored after) or any callable
    mapping a preprocessed batch to ``(B, D)`` features. ``preprocess`` maps uint8
    ``(B, H, W, C)`` frames to the encoder's input (default :func:`to_tensor`); use the policy's
    own. ``camera`` is the store's camera (``images.front``) or the LeRobot key
    (``observation.images.front``). A batch is up to ``batch_size`` frames of one episode.

    Episodes already holding the layer from ``producer`` are skipped; every ``commit_every``
    finished episodes are one ``store.write_layer`` call (one store version), so a run that is
    stopped (an error, Ctrl-C: the finished episodes are committed first) resumes where it
    stopped.

    Decoding runs in threads ahead of the encoder, up to QUEUED_BATCHES batches ahead per
    thread. ``decode_threads=None`` starts one and adds another (up to AUTO_DECODE_THREADS and
    the CPUs) whenever the encoder waits for frames longer than half its own busy time — an
    encoder on a GPU outpaces one decoder; an int fixes the number. Memory holds the queued
    batches, each thread's open videos and one commit group of features, never a whole video.
    The returned report says what each stage cost and which bounded the run."""
    started = time.monotonic()
    producer_dict, todo, report = _plan(store, name, producer, episodes, batch_size, commit_every)
    if decode_threads is not None and decode_threads < 1:
        raise ValueError(f"decode_threads must be at least 1; got {decode_threads}")
    max_threads = decode_threads or max(1, min(AUTO_DECODE_THREADS, os.cpu_count() or 1))
    bar = _Progress(name, report.episodes_skipped + len(todo), progress)

    module = _is_module(encoder)
    training = module and bool(getattr(encoder, "training"))
    if module:
        getattr(encoder, "to")(device)
        getattr(encoder, "eval")()

    assembler = _Assembler()
    writer = _Writer(store, name, producer_dict, report.producer_hash, commit_every, report)
    decode, encode = report.stages["decode"], report.stages["encode"]
    decode.workers = 0
    stats_lock = threading.Lock()
    stop = threading.Event()
    batches: "queue.Queue[Any]" = queue.Queue(maxsize=QUEUED_BATCHES * max_threads)
    dealer = _EpisodeDealer(todo, EPISODES_PER_TAKE if max_threads > 1 else len(todo))
    threads: List[threading.Thread] = []

    def start_thread() -> None:
        t = threading.Thread(
            target=_decode_batches,
            args=(store, camera, dealer, batch_size, batches, stop, decode, stats_lock),
            name=f"ufops-decode-{name}-{len(threads)}",
            daemon=True,
        )
        threads.append(t)
        with stats_lock:
            decode.workers = len(threads)
        t.start()

    # A fixed number starts at once (no more than there are runs to deal); auto starts one.
    first = min(decode_threads or 1, -(-len(todo) // dealer.take_size))
    for _ in range(first):
        start_thread()
    running = len(threads)
    waited = busy = 0.0
    since_ramp = 0
    try:
        bar.update(report.episodes_skipped, 0)
        while running:
            t0 = time.perf_counter()
            item = batches.get()
            t1 = time.perf_counter()
            if item is _DONE:
                running -= 1
                continue
            if isinstance(item, BaseException):
                raise item
            feats = _encode(encoder, item.frames, preprocess, device)
            t2 = time.perf_counter()
            encode.frames += len(item.frames)
            encode.seconds += t2 - t1
            report.frames += len(item.frames)
            done = assembler.add(item.episode_id, item.length, item.start, feats)
            if done is not None:
                writer.add(item.episode_id, done)
            # More decoders when this thread waits for frames more than it encodes them.
            waited, busy, since_ramp = waited + (t1 - t0), busy + (t2 - t1), since_ramp + 1
            if since_ramp >= RAMP_BATCHES and decode_threads is None:
                if waited > STARVED * busy and len(threads) < max_threads and dealer.remaining() > 0:
                    start_thread()
                    running += 1
                waited = busy = 0.0
                since_ramp = 0
            with stats_lock:
                bar.update(report.episodes_skipped + report.episodes_written + len(writer.finished), report.frames,
                           stages=report.stages)
        writer.commit()
    except BaseException:
        # Keep the finished work: the next run resumes after it.
        writer.salvage()
        raise
    finally:
        stop.set()
        for t in threads:
            t.join(timeout=60)
        if training:
            getattr(encoder, "train")()
    report.seconds = time.monotonic() - started
    report.frames_per_second = report.frames / report.seconds if report.seconds > 0 else 0.0
    bar.update(report.episodes_skipped + report.episodes_written, report.frames, final=True, stages=report.stages)
    return report
