"""``ufops.Store``: a ufops store opened read-only, as polars DataFrames.

Episodes come from the catalog (what ``ufops episodes --json`` lists), steps from the Parquet
files through the store's read path (only the pages of the wanted rows are read), handed over as
Arrow IPC streams. polars is imported on first use (``pip install polars``).
"""
from __future__ import annotations

import functools
import io
import json
import os
from typing import TYPE_CHECKING, Any, Dict, List, Mapping, Optional, Sequence, Tuple, Union

from ufops import _ufops
from ufops.verifier import Verifier

if TYPE_CHECKING:
    import numpy as np
    import numpy.typing as npt
    import polars as pl

JsonObject = Dict[str, Any]


@functools.lru_cache(maxsize=8)
def _reopen(data_dir: Optional[str], database_url: Optional[str], object_store: Optional[str]) -> "Store":
    return Store(data_dir, database_url=database_url, object_store=object_store)


def _polars() -> None:
    try:
        import polars  # noqa: F401
    except ImportError as e:  # pragma: no cover - depends on the environment
        raise ImportError("ufops.Store returns polars DataFrames: pip install polars") from e


def episodes_frame(records: List[JsonObject]) -> "pl.DataFrame":
    """Episode records of the API (JSON) as a DataFrame of the same columns as
    :meth:`Store.episodes`: the store's one definition of them (``store::episodes_schema``),
    converted in Rust. ``metadata`` stays a JSON string."""
    _polars()
    import polars as pl

    return pl.read_ipc_stream(io.BytesIO(_ufops.episodes_ipc_from_json(json.dumps(records))))


class Store:
    """A ufops store opened read-only: ``Store("ufops-data")`` for a local data directory, or
    ``Store(database_url="postgres://…", object_store="s3://bucket/prefix")``.

    Composes the native ``_ufops.Store`` (the store's Rust read path): records cross as JSON,
    episodes and steps as Arrow IPC, and this class turns them into polars DataFrames."""

    __slots__ = ("_native", "_opened_with")

    def __init__(
        self,
        data_dir: Union[str, "os.PathLike[str]", None] = None,
        *,
        database_url: Optional[str] = None,
        object_store: Optional[str] = None,
    ) -> None:
        """Opens an existing store (nothing is created: a missing one raises NotFoundError)."""
        self._native = _ufops.Store(data_dir, database_url=database_url, object_store=object_store)
        self._opened_with = (None if data_dir is None else os.fspath(data_dir), database_url, object_store)

    def __reduce__(self) -> Tuple[Any, Tuple[Optional[str], Optional[str], Optional[str]]]:
        """Pickled as what opened it, so a worker process (Ray's, multiprocessing's) opens the same
        store; each process opens it once (`_reopen`). S3 credentials are not pickled: they come
        from the environment (``AWS_*``) where it is opened."""
        return (_reopen, self._opened_with)

    def __repr__(self) -> str:
        return repr(self._native)

    def head_version(self) -> int:
        """The latest committed version."""
        return self._native.head_version()

    def episodes(
        self,
        version: Optional[int] = None,
        *,
        policy: Optional[str] = None,
        checkpoint: Optional[str] = None,
        task: Optional[str] = None,
        label: Optional[str] = None,
        tag: Optional[str] = None,
        after: Optional[str] = None,
        limit: Optional[int] = None,
    ) -> "pl.DataFrame":
        """Episodes with their labels, now or as of ``version`` (labels frozen in it), in id order;
        the columns of ``store::episodes_schema`` (``metadata`` as a JSON string)."""
        _polars()
        import polars as pl

        stream = self._native.episodes_ipc(version, policy, checkpoint, task, label, tag, after, limit)
        return pl.read_ipc_stream(io.BytesIO(stream))

    def steps(
        self,
        ids: Union[Sequence[str], str],
        version: Optional[int] = None,
        *,
        layers: Optional[Sequence[str]] = None,
    ) -> "pl.DataFrame":
        """The steps of one or many episodes (in the order of ``ids``), one row per step, with the
        columns of the Parquet files (``episode_id``, ``t``, ``obs.*``, ``action``, ...).

        ``layers`` joins those layers' values (e.g. an encoder's features) as ``obs.<layer>``
        columns; an episode without one of them (now, or in ``version``) is an error."""
        _polars()
        import polars as pl

        wanted = [ids] if isinstance(ids, str) else list(ids)
        streams = self._native.steps_ipc(wanted, version, list(layers) if layers else None)
        frames = [pl.read_ipc_stream(io.BytesIO(s)) for s in streams]
        if not frames:
            return pl.DataFrame()
        return frames[0] if len(frames) == 1 else pl.concat(frames, how="diagonal_relaxed")

    def layers(self) -> "pl.DataFrame":
        """The layers: one row per (name, producer) with its dim and the episodes holding it now."""
        _polars()
        import polars as pl

        schema = {
            "name": pl.Utf8,
            "producer_hash": pl.Utf8,
            "producer": pl.Utf8,
            "dim": pl.Int64,
            "episodes": pl.Int64,
            "version": pl.Int64,
        }
        rows = [{**r, "producer": json.dumps(r["producer"], sort_keys=True)} for r in json.loads(self._native.layers_json())]
        return pl.DataFrame(rows, schema=schema, orient="row") if rows else pl.DataFrame(schema=schema)

    def episode_layers(self, episode_id: str, version: Optional[int] = None) -> List[JsonObject]:
        """The layers an episode holds (layer, producer_hash, dim, version_added), now or at ``version``."""
        return json.loads(self._native.episode_layers_json(episode_id, version))  # type: ignore[no-any-return]

    def layer_episodes(self, name: str, producer_hash: str) -> List[str]:
        """The episodes holding layer ``name`` from the producer ``producer_hash`` now."""
        return self._native.layer_episodes(name, producer_hash)

    def producer_hash(self, producer: Mapping[str, Any]) -> str:
        """The sha256 the store gives a producer (its canonical JSON: key order does not matter)."""
        return _ufops.Store.producer_hash(json.dumps(dict(producer)))

    def write_layer(
        self, name: str, producer: Mapping[str, Any], values: Mapping[str, Any], *, actor: str = "python"
    ) -> JsonObject:
        """Writes one group of episodes' values of layer ``name`` as one new store version.

        ``values`` maps an episode id to a float32 array of shape ``(steps, dim)``, one row per
        stored step. Episodes that hold this layer from this ``producer`` already are skipped, so
        writing in groups resumes after an interruption. Returns ``{"version", "producer_hash",
        "episodes_written", "episodes_skipped"}`` (``version`` is None when nothing was written)."""
        import numpy as np

        ids = list(values)
        arrays = [np.ascontiguousarray(np.asarray(values[i], dtype=np.float32)) for i in ids]
        for i, a in zip(ids, arrays):
            if a.ndim != 2:
                raise ValueError(f"layer {name}: episode {i} values have shape {a.shape}, expected (steps, dim)")
        out = self._native.write_layer_arrays(name, json.dumps(dict(producer)), ids, arrays, actor)
        return json.loads(out)  # type: ignore[no-any-return]

    def versions(self) -> "pl.DataFrame":
        """The store's versions."""
        _polars()
        import polars as pl

        return pl.DataFrame(json.loads(self._native.versions_json()))

    def splits(self) -> List[JsonObject]:
        """The splits (records: id, policy, checkpoint, mode, version, sizes...)."""
        return json.loads(self._native.splits_json())  # type: ignore[no-any-return]

    def split_episodes(self, split_id: str) -> "pl.DataFrame":
        """A split's members: episode_id, part (train / val), label."""
        _polars()
        import polars as pl

        rows = json.loads(self._native.split_episodes_json(split_id))
        schema = {"episode_id": pl.Utf8, "part": pl.Utf8, "label": pl.Utf8}
        return pl.DataFrame([{k: r.get(k) for k in schema} for r in rows], schema=schema, orient="row")

    def artifacts(
        self, policy: Optional[str] = None, checkpoint: Optional[str] = None, kind: Optional[str] = None
    ) -> List[JsonObject]:
        """Verifier artifacts (records with files, config and aliases)."""
        return json.loads(self._native.artifacts_json(policy, checkpoint, kind))  # type: ignore[no-any-return]

    def monitors(
        self, policy: Optional[str] = None, checkpoint: Optional[str] = None, artifact: Optional[str] = None
    ) -> List[JsonObject]:
        """Failure monitors (records with their held-out evaluation and aliases)."""
        return json.loads(self._native.monitors_json(policy, checkpoint, artifact))  # type: ignore[no-any-return]

    def monitor(self, reference: str) -> JsonObject:
        """The monitor ``reference`` (id or ``POLICY/CHECKPOINT@ALIAS``): ``record`` (what
        :class:`ufops.Monitor` loads), ``evaluation``, ``aliases``..."""
        return json.loads(self._native.monitor_json(reference))  # type: ignore[no-any-return]

    def step_inputs(
        self, episode_id: str, verifier: Verifier, version: Optional[int] = None
    ) -> "Tuple[npt.NDArray[np.float32], npt.NDArray[np.uint32], npt.NDArray[np.float32]]":
        """A stored episode's verifier inputs, step by step, built by the Rust core as training and
        ``ufops monitor evaluate`` build them: ``(obs (T, obs_dim), t (T,), act (T, act_dim))``."""
        return self._native.step_inputs(episode_id, verifier._native, version)

    def verifier(self, reference: str) -> Verifier:
        """The verifier ``reference`` (id or ``POLICY/CHECKPOINT/KIND@ALIAS``), checked."""
        return Verifier(self._native.verifier(reference))

    def object_size(self, path: str) -> int:
        """Size in bytes of a stored object (e.g. a video an episode's frames are in)."""
        return self._native.object_size(path)

    def read_object_range(self, path: str, start: int, end: int) -> bytes:
        """Bytes ``[start, end)`` of a stored object (one range read)."""
        return self._native.read_object_range(path, start, end)
