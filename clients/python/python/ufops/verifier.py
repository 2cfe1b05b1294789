"""``ufops.Verifier``: a verifier artifact, loaded with every file checked against its sha256.

The forward pass and its input gradient run in the Rust verifier core (the one definition the
trainer and the Rust steering client use), with the GIL released; this class composes the native
``_ufops.Verifier`` and gives it types and documentation.
"""
from __future__ import annotations

import json
import os
import warnings
from typing import Any, Dict, List, Mapping, NamedTuple, Optional, Protocol, Tuple, Union

import numpy as np
import numpy.typing as npt

from ufops import _ufops


class Pick(NamedTuple):
    """Best-of-N's choice for B groups of candidates (:meth:`Verifier.pick`)."""

    #: The chosen candidate of each group, ``(B,)``.
    chosen: npt.NDArray[np.int64]
    #: Every candidate's score, shaped like :meth:`Verifier.score`'s result (an ensemble's: the
    #: members' mean).
    scores: npt.NDArray[np.float32]
    #: Every candidate's spread over the members (zeros for one network).
    spread: npt.NDArray[np.float32]
    #: Per group: an ensemble's members disagreed, so the first candidate (the policy's own
    #: sample) was kept, ``(B,)``.
    fell_back: npt.NDArray[np.bool_]
    #: Per group: the share of members that score the pessimistic pick above the first
    #: candidate, ``(B,)``.
    agreement: npt.NDArray[np.float32]


class _VerifierSource(Protocol):
    """What loads a verifier by reference: :class:`ufops.Store` (which imports this module, so
    this one names it only by what it does)."""

    def verifier(self, reference: str) -> "Verifier": ...

ArrayLike = Any  # numpy arrays (float32, C-contiguous: read in place), torch tensors, DLPack producers
StepLike = Union[int, Any]  # an int, or an integer array of shape (B,)


class SteeringWarning(UserWarning):
    """A verifier's training flagged it as unlikely to steer well: among held-out samples its
    observation-only twin scores alike, it barely ranks the action chunks (see
    :attr:`Verifier.action_sensitivity`). Shown once per artifact when it is loaded."""


class Verifier:
    """A verifier artifact: ``Verifier.load(dir)``, ``Verifier.from_store(store, ref)`` or
    ``Verifier.from_server(url, ref, token)``; then :meth:`score` candidate chunks or take the
    :meth:`grad` of the score with respect to them (guidance)."""

    __slots__ = ("_native",)

    def __init__(self, native: _ufops.Verifier) -> None:
        """Wraps a loaded native verifier; use the ``load`` / ``from_*`` constructors."""
        if not isinstance(native, _ufops.Verifier):
            raise TypeError("use Verifier.load, Verifier.from_store or Verifier.from_server")
        self._native = native
        warning = native.steering_warning
        if warning is not None:
            warnings.warn(warning, SteeringWarning, stacklevel=3)

    @classmethod
    def load(cls, path: Union[str, "os.PathLike[str]"]) -> "Verifier":
        """Loads an artifact directory (``manifest.json``, ``config.json``, ``model.safetensors``),
        every file checked against the sha256 the manifest records."""
        return cls(_ufops.Verifier.load(path))

    @classmethod
    def from_server(cls, url: str, reference: str, token: str, timeout: float = 60.0) -> "Verifier":
        """Fetches ``reference`` (``POLICY/CHECKPOINT/KIND@ALIAS`` or an artifact id) from a
        ``ufops serve`` API with a bearer token; the manifest must hash to the resolved id."""
        return cls(_ufops.Verifier.from_server(url, reference, token, timeout))

    @classmethod
    def from_store(cls, store: Union[_VerifierSource, str, "os.PathLike[str]"], reference: str) -> "Verifier":
        """Loads ``reference`` (an artifact id or ``POLICY/CHECKPOINT/KIND@ALIAS``) from a
        :class:`ufops.Store` or a data directory (opened read-only for the purpose). Every file is
        checked against the manifest, and the manifest against the id the catalog records."""
        if isinstance(store, (str, os.PathLike)):
            return cls(_ufops.Store(store).verifier(reference))
        return store.verifier(reference)

    def __repr__(self) -> str:
        return repr(self._native)

    @property
    def id(self) -> Optional[str]:
        """The artifact id (first 16 hex digits of sha256(manifest.json))."""
        return self._native.id

    @property
    def kind(self) -> str:
        """``classifier`` (scores are probabilities of success) or ``q`` (time-to-success values)."""
        return self._native.kind

    @property
    def obs_dim(self) -> int:
        """Length of one observation row: obs_history x the observation keys' widths."""
        return self._native.obs_dim

    @property
    def act_dim(self) -> int:
        """Length of one flattened action chunk: chunk_len x action_dim."""
        return self._native.act_dim

    @property
    def chunk_len(self) -> int:
        return self._native.chunk_len

    @property
    def action_dim(self) -> int:
        return self._native.action_dim

    @property
    def takes_policy_space(self) -> bool:
        """Whether candidates are read in the policy's normalised sample space (guidance needs it)."""
        return self._native.takes_policy_space

    @property
    def backend(self) -> str:
        """The kernels in use (``avx2+fma`` or ``portable``)."""
        return self._native.backend

    @property
    def members(self) -> int:
        """Networks behind the scores: 1, or an ensemble's members (trainer/ARTIFACT.md,
        "Ensembles")."""
        return self._native.members

    @property
    def ensemble(self) -> Optional[Dict[str, Any]]:
        """An ensemble's members and steering rules (``pessimism`` κ, ``min_agreement``,
        ``min_gradient_agreement``); ``None`` for one network."""
        found = self.config().get("ensemble")
        return dict(found) if isinstance(found, dict) else None

    @property
    def extra_inputs(self) -> List[Tuple[str, int]]:
        """Inputs beside (obs, chunk, t), by name and width."""
        return list(self._native.extra_inputs)

    @property
    def required_producers(self) -> Dict[str, str]:
        """Layer key → the producer hash whose features this verifier was trained on."""
        return dict(self._native.required_producers)

    def check_producers(self, provided: Mapping[str, str]) -> None:
        """Raises unless ``provided`` (layer key → producer hash) gives every layer this verifier
        reads from the producer it was trained on."""
        self._native.check_producers(dict(provided))

    @property
    def action_sensitivity(self) -> Optional[Dict[str, Any]]:
        """How much the action chunk matters to this verifier's held-out scores, as its training
        measured with an observation-only twin (``obs_only_auc``, ``auc_gain``, ``action_auc``,
        ``flagged``, ``reason``...); ``None`` for artifacts trained without the twin."""
        found = self.config().get("metrics", {}).get("final", {}).get("action_sensitivity")
        return dict(found) if isinstance(found, dict) else None

    @property
    def steering_warning(self) -> Optional[str]:
        """Why steering with this verifier may not help, when its training flagged it."""
        return self._native.steering_warning

    def config(self) -> Dict[str, Any]:
        """The artifact's config.json."""
        return json.loads(self._native.config_json())  # type: ignore[no-any-return]

    def config_json(self) -> str:
        return self._native.config_json()

    def score(
        self, obs: ArrayLike, act: ArrayLike, t: StepLike, extras: Optional[Mapping[str, ArrayLike]] = None
    ) -> npt.NDArray[np.float32]:
        """Scores of action chunks: ``obs`` ``(obs_dim,)`` with ``act`` ``(N, act_dim)`` → ``(N,)``;
        ``obs`` ``(B, obs_dim)`` with ``act`` ``(B, N, act_dim)`` → ``(B, N)`` or ``(B, act_dim)`` →
        ``(B,)``. A chunk may also be ``(chunk_len, action_dim)``. ``t`` is the step (an int, or
        ``(B,)`` ints)."""
        return self._native.score(obs, act, t, extras)

    def score_members(
        self, obs: ArrayLike, act: ArrayLike, t: StepLike, extras: Optional[Mapping[str, ArrayLike]] = None
    ) -> npt.NDArray[np.float32]:
        """Every member's scores, ``(members, *score's shape)``; :meth:`score` is their mean."""
        return self._native.score_members(obs, act, t, extras)

    def pick(
        self, obs: ArrayLike, act: ArrayLike, t: StepLike, extras: Optional[Mapping[str, ArrayLike]] = None
    ) -> Pick:
        """Best-of-N's choice among groups of candidates — ``obs`` ``(obs_dim,)`` with ``act``
        ``(N, chunk)``, or ``(B, obs_dim)`` with ``(B, N, chunk)`` — by the verifier core's rule:
        the argmax of the score for one network; for an ensemble the argmax of ``mean − κ ·
        spread``, kept only when at least ``min_agreement`` of the members score it above the
        group's first candidate (the policy's own sample), else that first candidate."""
        index, scores, spread, fell_back, agreement = self._native.pick(obs, act, t, extras)
        return Pick(
            np.asarray(index, dtype=np.int64),
            scores,
            spread,
            np.asarray(fell_back, dtype=np.bool_),
            np.asarray(agreement, dtype=np.float32),
        )

    def telemetry_grid(self, act: ArrayLike) -> Tuple[npt.NDArray[np.float32], npt.NDArray[np.float32]]:
        """Chunks in the space this verifier takes, put on the grid steering telemetry stores:
        ``(scored, raw)`` — the raw actions (the artifact's action normaliser undone) rounded to
        half floats, and those back in this verifier's space. A recorded best-of-N scores and
        executes ``scored`` and logs ``raw``, so a replay scores exactly what the robot did."""
        return self._native.telemetry_grid(act)

    def grad(
        self, obs: ArrayLike, act: ArrayLike, t: StepLike, extras: Optional[Mapping[str, ArrayLike]] = None
    ) -> npt.NDArray[np.float32]:
        """Guidance gradients with respect to the chunk as passed: d log C / d act (classifier) or
        d Q / d act (q), in the chunk's shape (batched like :meth:`score`). An ensemble's is the
        members' mean gradient scaled by how much they agree (zero where they do not)."""
        return self._native.grad(obs, act, t, extras)
