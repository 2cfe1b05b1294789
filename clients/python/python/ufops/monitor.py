"""``ufops.Monitor``: a failure alarm with a stated false-alarm rate, on the robot.

A monitor record (``ufops monitor calibrate``) holds a threshold on a verifier artifact's per-step
scores, calibrated by split conformal prediction so that on a successful episode the alarm fires
with probability at most ``alpha``: on average over calibration draws, or — a record with a
``confidence`` (``--confidence``, 1 - delta) — for this calibration with that probability (the
training-conditional threshold). This class binds a record to the verifier it was calibrated
for (any other is refused) and steps the Rust core's running statistic — the code ``ufops monitor
evaluate`` runs offline, so both raise the alarm at the same step.
"""
from __future__ import annotations

import json
import os
from dataclasses import dataclass
from typing import Any, Mapping, Union

from ufops import _ufops
from ufops.verifier import ArrayLike, Verifier

RecordLike = Union[Mapping[str, Any], str, bytes, "os.PathLike[str]"]


@dataclass(frozen=True)
class MonitorStep:
    """One step of the monitor: the verifier's ``score`` of the chunk, the running ``statistic``
    (moving average of the risk ``1 - score``), whether it exceeds the threshold (``alarm``) and
    whether this is the episode's first alarm."""

    score: float
    statistic: float
    alarm: bool
    first_alarm: bool


def _record_json(record: RecordLike) -> str:
    if isinstance(record, Mapping):
        return json.dumps(dict(record))
    if isinstance(record, bytes):
        return record.decode()
    if isinstance(record, os.PathLike) or (isinstance(record, str) and not record.lstrip().startswith("{")):
        with open(record, encoding="utf-8") as f:
            return f.read()
    return record


class Monitor:
    """``Monitor(verifier, record)``: ``record`` is the monitor's record (a dict, its JSON, or a
    file ``ufops monitor show REF --out FILE`` wrote), or use :meth:`from_store`. Call
    :meth:`update` at every re-planning step and :meth:`reset` between episodes."""

    __slots__ = ("_native", "verifier")

    def __init__(self, verifier: Verifier, record: RecordLike) -> None:
        self.verifier = verifier
        self._native = _ufops.Monitor(verifier._native, _record_json(record))

    @classmethod
    def from_store(cls, store: Any, reference: str, verifier: Union[Verifier, None] = None) -> "Monitor":
        """The monitor ``reference`` (an id or ``POLICY/CHECKPOINT@ALIAS``) of a
        :class:`ufops.Store`, with the verifier it was calibrated for (loaded from the store unless
        given)."""
        entry = store.monitor(reference)
        v = verifier if verifier is not None else store.verifier(entry["artifact_id"])
        return cls(v, entry["record"])

    def update(self, obs: ArrayLike, chunk: ArrayLike, t: int) -> MonitorStep:
        """Scores ``chunk`` (``(act_dim,)`` or ``(chunk_len, action_dim)``) for the observation
        history ``obs`` (``(obs_dim,)``) at step ``t`` and steps the statistic."""
        return MonitorStep(*self._native.update(obs, chunk, int(t)))

    def update_score(self, score: float) -> MonitorStep:
        """Steps the statistic with a score already computed (best-of-N's score of the chunk it
        chose): no second forward pass."""
        return MonitorStep(*self._native.update_score(float(score)))

    def reset(self) -> None:
        """Starts a new episode."""
        self._native.reset()

    @property
    def alarmed(self) -> bool:
        """Whether the alarm has fired in this episode."""
        return self._native.alarmed

    @property
    def threshold(self) -> float:
        return self._native.threshold

    @property
    def alpha(self) -> float:
        """The false-alarm rate on successful episodes the calibration guarantees (at most)."""
        return self._native.alpha

    @property
    def confidence(self) -> Union[float, None]:
        """1 - delta of a training-conditional threshold: its false-alarm rate is at most ``alpha``
        with at least this probability over the calibration draw. ``None`` for a split-conformal
        threshold, whose guarantee holds on average over calibration draws."""
        c = self.record().get("confidence")
        return None if c is None else float(c)

    @property
    def method(self) -> str:
        """The calibration method the record names (``split_conformal_peak`` or
        ``split_conformal_peak_training_conditional``)."""
        return str(self.record()["method"])

    @property
    def artifact_id(self) -> str:
        return self._native.artifact_id

    def record(self) -> Mapping[str, Any]:
        return json.loads(self._native.record_json())  # type: ignore[no-any-return]

    def __repr__(self) -> str:
        c = self.confidence
        conf = "" if c is None else f", confidence={c}"
        return (
            f"Monitor(artifact={self.artifact_id}, alpha={self.alpha}{conf}, "
            f"threshold={self.threshold:.4f})"
        )
