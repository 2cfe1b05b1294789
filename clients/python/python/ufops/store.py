"""``ufops.Store``: a ufops store opened read-only, as polars DataFrames.

Episodes come from the catalog (what ``ufops episodes --json`` lists), steps from the Parquet
files through the store's read path (only the pages of the wanted rows are read), handed over as
Arrow IPC streams. polars is imported on first use (``pip install polars``).
"""
from __future__ import annotations

import io
import json
from typing import TYPE_CHECKING, Any, Dict, List, Mapping, Optional, Sequence, Union

from ufops import _ufops

if TYPE_CHECKING:
    import polars as pl

JsonObject = Dict[str, Any]

# The episode record's columns and their polars types (store::EpisodeRecord).
_EPISODE_COLUMNS = [
    ("id", "Utf8"),
    ("policy", "Utf8"),
    ("checkpoint", "Utf8"),
    ("task", "Utf8"),
    ("label", "Utf8"),
    ("label_source", "Utf8"),
    ("label_revision", "Int64"),
    ("label_actor", "Utf8"),
    ("label_updated_at", "Utf8"),
    ("length", "Int64"),
    ("source_sha256", "Utf8"),
    ("source_name", "Utf8"),
    ("source_index", "Int64"),
    ("tags", "List[Utf8]"),
    ("metadata", "Utf8"),
    ("data_file", "Utf8"),
    ("row_group", "Int64"),
    ("row_offset", "Int64"),
    ("row_count", "Int64"),
    ("version_added", "Int64"),
    ("created_at", "Utf8"),
]


def _polars() -> None:
    try:
        import polars  # noqa: F401
    except ImportError as e:  # pragma: no cover - depends on the environment
        raise ImportError("ufops.Store returns polars DataFrames: pip install polars") from e


def episodes_frame(records: List[JsonObject]) -> "pl.DataFrame":
    """Episode records (store or API) as a DataFrame; ``metadata`` stays a JSON string."""
    _polars()
    import polars as pl

    types: Dict[str, "pl.DataType | type[pl.DataType]"] = {"Utf8": pl.Utf8, "Int64": pl.Int64, "List[Utf8]": pl.List(pl.Utf8)}
    schema = {name: types[t] for name, t in _EPISODE_COLUMNS}
    rows = [
        {name: (json.dumps(r.get(name)) if name == "metadata" else r.get(name)) for name in schema} for r in records
    ]
    return pl.DataFrame(rows, schema=schema, orient="row") if rows else pl.DataFrame(schema=schema)


class Store(_ufops.Store):
    """A ufops store opened read-only: ``Store("ufops-data")`` for a local data directory, or
    ``Store(database_url="postgres://…", object_store="s3://bucket/prefix")``."""

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
        """Episodes with their labels, now or as of ``version`` (labels frozen in it), in id order."""
        records = json.loads(self.episodes_json(version, policy, checkpoint, task, label, tag, after, limit))
        return episodes_frame(records)

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
        streams = self.steps_ipc(wanted, version, list(layers) if layers else None)
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
        rows = [{**r, "producer": json.dumps(r["producer"], sort_keys=True)} for r in json.loads(self.layers_json())]
        return pl.DataFrame(rows, schema=schema, orient="row") if rows else pl.DataFrame(schema=schema)

    def episode_layers(self, episode_id: str, version: Optional[int] = None) -> List[JsonObject]:
        """The layers an episode holds (layer, producer_hash, dim, version_added), now or at ``version``."""
        return json.loads(self.episode_layers_json(episode_id, version))  # type: ignore[no-any-return]

    def producer_hash(self, producer: Mapping[str, Any]) -> str:  # type: ignore[override]
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
        out = self.write_layer_arrays(name, json.dumps(dict(producer)), ids, arrays, actor)
        return json.loads(out)  # type: ignore[no-any-return]

    def versions(self) -> "pl.DataFrame":
        """The store's versions."""
        _polars()
        import polars as pl

        return pl.DataFrame(json.loads(self.versions_json()))

    def splits(self) -> List[JsonObject]:
        """The splits (records: id, policy, checkpoint, mode, version, sizes...)."""
        return json.loads(self.splits_json())  # type: ignore[no-any-return]

    def split_episodes(self, split_id: str) -> "pl.DataFrame":
        """A split's members: episode_id, part (train / val), label."""
        _polars()
        import polars as pl

        rows = json.loads(self.split_episodes_json(split_id))
        schema = {"episode_id": pl.Utf8, "part": pl.Utf8, "label": pl.Utf8}
        return pl.DataFrame([{k: r.get(k) for k in schema} for r in rows], schema=schema, orient="row")

    def artifacts(
        self, policy: Optional[str] = None, checkpoint: Optional[str] = None, kind: Optional[str] = None
    ) -> List[JsonObject]:
        """Verifier artifacts (records with files, config and aliases)."""
        return json.loads(self.artifacts_json(policy, checkpoint, kind))  # type: ignore[no-any-return]

    def verifier(self, reference: str) -> _ufops.Verifier:
        """The verifier ``reference`` (id or ``POLICY/CHECKPOINT/KIND@ALIAS``), checked."""
        return super().verifier(reference)
