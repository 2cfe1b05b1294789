"""ufops for Python: steer PyTorch policies with ufops verifiers, and read the ufops store.

* :class:`Verifier` — a verifier artifact loaded from a directory, a store or ``ufops serve``
  (every file checked against its sha256); ``score`` and ``grad`` run the Rust verifier core on
  numpy arrays or torch tensors, with the GIL released.
* :class:`Monitor` — a failure alarm calibrated for a verifier artifact (false-alarm rate at most
  its ``alpha`` on successful episodes), stepped on the robot like ``ufops monitor evaluate`` steps it.
* :class:`Store` — a store opened read-only: episodes, steps, splits and artifacts as polars
  DataFrames (``pip install polars``).
* :class:`Client` — the ``ufops serve`` API: episodes, labels (with optimistic concurrency).
* :mod:`ufops.torch` — best-of-N and guidance hooks for PyTorch samplers.
* :class:`SteeringLog` — best-of-N steps recorded on the robot, written as the sidecar
  ``ufops ingest`` keeps with the episodes (``ufops replay`` re-scores them).
* :mod:`ufops.lerobot` — LeRobot policies: their own encoder features as layers, N chunks from
  their sampler, and ``SteeredPolicy`` in LeRobot's loops (``import ufops.lerobot``; needs lerobot).
"""
from __future__ import annotations

from ufops._ufops import __version__
from ufops.client import Client
from ufops.errors import (
    ArtifactError,
    AuthError,
    ConflictError,
    FetchError,
    IntegrityError,
    NotFoundError,
    StoreError,
    UfopsError,
)
from ufops.monitor import Monitor, MonitorStep
from ufops.store import Store
from ufops.telemetry import SteeringLog, sidecar_for
from ufops.verifier import Pick, SteeringWarning, Verifier

__all__ = [
    "Verifier",
    "Pick",
    "SteeringWarning",
    "Monitor",
    "MonitorStep",
    "Store",
    "SteeringLog",
    "sidecar_for",
    "Client",
    "UfopsError",
    "ArtifactError",
    "IntegrityError",
    "FetchError",
    "AuthError",
    "NotFoundError",
    "StoreError",
    "ConflictError",
    "__version__",
]
