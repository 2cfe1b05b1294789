"""Steering telemetry: the best-of-N steps a robot took, written beside its evaluation's rollouts
so the store keeps them with the episodes and ``ufops replay`` can re-score them with another
verifier or fewer candidates, without running the robot.

Record with :func:`ufops.torch.best_of_n` (``log=``, ``episode=``), or add steps yourself with
:meth:`SteeringLog.add`; then :meth:`SteeringLog.write` the sidecar next to the rollouts
(:func:`sidecar_for`: ``rollouts.hdf5`` → ``rollouts.hdf5.steering.parquet``, a LeRobot dataset
folder → its ``steering.parquet``), and ``ufops ingest`` attaches each record to its episode.
Candidates are raw actions stored as half floats; a recorded best-of-N scores them on that grid
(:meth:`ufops.Verifier.telemetry_grid`) so a replay reproduces every choice.
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import List, Tuple, Union

import numpy as np
import numpy.typing as npt

from ufops import _ufops

_Record = Tuple[int, int, str, List[float], List[float], int, int]


def sidecar_for(source: Union[str, "os.PathLike[str]"]) -> Path:
    """Where ``ufops ingest SOURCE`` looks for its steering telemetry: ``SOURCE.steering.parquet``
    for a file, ``SOURCE/steering.parquet`` for a folder."""
    p = Path(source)
    return p / "steering.parquet" if p.is_dir() else p.with_name(p.name + ".steering.parquet")


class SteeringLog:
    """Best-of-N steps of one evaluation, in memory until :meth:`write`."""

    __slots__ = ("_records",)

    def __init__(self) -> None:
        self._records: List[_Record] = []

    def __len__(self) -> int:
        return len(self._records)

    def add(
        self,
        episode: int,
        t: int,
        artifact_id: str,
        raw_candidates: npt.ArrayLike,
        scores: npt.ArrayLike,
        chosen: int,
        latency_us: int = 0,
    ) -> None:
        """One step: ``episode`` is the source's episode index (robomimic ``demo_<i>``: i,
        LeRobot ``episode_index``), ``t`` the step whose chunk was chosen, ``raw_candidates`` the
        N chunks as raw actions (``(N, act_dim)`` or ``(N, chunk_len, action_dim)``), ``scores``
        their N scores, ``chosen`` the executed index."""
        s = np.asarray(scores, dtype=np.float32).reshape(-1)
        c = np.asarray(raw_candidates, dtype=np.float32)
        if s.size == 0 or c.shape[0] != s.size:
            raise ValueError(f"{c.shape[0] if c.ndim else 0} candidates for {s.size} scores")
        if not 0 <= chosen < s.size:
            raise ValueError(f"chosen index {chosen} of {s.size} candidates")
        self._records.append(
            (int(episode), int(t), str(artifact_id), c.reshape(-1).tolist(), s.tolist(), int(chosen), int(latency_us))
        )

    def write(self, path: Union[str, "os.PathLike[str]"]) -> Path:
        """Writes the sidecar Parquet file (atomically: a temporary file renamed into place)."""
        p = Path(path)
        _ufops.write_steering_log(p, self._records)
        return p
