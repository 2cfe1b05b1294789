"""``ufops.Store``: a ufops store opened read-only, as polars DataFrames.

Episodes come from the catalog (what ``ufops episodes --json`` lists), steps from the Parquet
files through the store's read path (only the pages of the wanted rows are read), handed over as
Arrow IPC streams. polars is imported on first use (``pip install polars``).
"""
from __future__ import annotations

import io
import json
from typing import TYPE_CHECKING, Any, Dict, List, Optional, Sequence, Union

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

    def steps(self, ids: Union[Sequence[str], str], version: Optional[int] = None) -> "pl.DataFrame":
        """The steps of one or many episodes (in the order of ``ids``), one row per step, with the
        columns of the Parquet files (``episode_id``, ``t``, ``obs.*``, ``action``, ...)."""
        _polars()
        import polars as pl

        wanted = [ids] if isinstance(ids, str) else list(ids)
        frames = [pl.read_ipc_stream(io.BytesIO(s)) for s in self.steps_ipc(wanted, version)]
        if not frames:
            return pl.DataFrame()
        return frames[0] if len(frames) == 1 else pl.concat(frames, how="diagonal_relaxed")

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
