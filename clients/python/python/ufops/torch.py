"""Steering helpers for PyTorch samplers, running the verifier core through :class:`ufops.Verifier`.

* :func:`best_of_n` — the paper's Algorithm 1: sample N candidate chunks, keep the best scored
  (and, with ``log=``, record the step for ``ufops replay``: :mod:`ufops.telemetry`); with an
  ensemble verifier, the pessimistic pick that falls back to the policy's own chunk when the
  members disagree.
* :func:`ddpm_guidance` — Algorithm 2 for a diffusers-style loop: a hook that turns the policy's
  noise prediction into the one whose x̂0 is ``x̂0 + λ ∇ log C(o, x̂0)`` (classifier) or
  ``x̂0 + λ ∇ Q`` (q), so ``scheduler.step`` then takes its posterior mean at the guided x̂0.
* With an ensemble verifier the guidance gradient is the members' mean scaled by their agreement
  (zero where they disagree): the verifier core's rule, so nothing changes here.
* :func:`flow_guidance` — the same for a flow-matching sampler: ``x̂0 = a_t − t·v``, guided, and
  the velocity that reaches it, ``v' = v − λ ∇ / t`` (not applied at t = 1, where x̂0 is noise).

The verifier reads chunks in the policy's normalised sample space (the artifact's
``takes_policy_space``), as the trainer writes them by default. Tensors stay where they are:
gradients come back on the input's device and dtype. torch is imported by these functions only.
"""
from __future__ import annotations

import time
from typing import Any, Callable, List, Optional, Tuple

import numpy as np
import numpy.typing as npt

from ufops.telemetry import SteeringLog
from ufops.verifier import Pick, Verifier

Tensor = Any  # torch.Tensor (kept loose so the package imports without torch)


def _steps(t: Any) -> Any:
    if isinstance(t, (int, np.integer)):
        return int(t)
    return np.ascontiguousarray(np.asarray(t.detach().cpu() if hasattr(t, "detach") else t, dtype=np.int64))


def _policy_space(verifier: Verifier) -> None:
    if not verifier.takes_policy_space:
        raise ValueError(
            f"verifier {verifier.id} scores raw actions, not the policy's sample space: "
            "guide with a verifier trained in the policy space (the trainer's default)"
        )


def best_of_n(
    verifier: Verifier,
    sample_fn: Callable[[int], Tensor],
    obs: Any,
    n: int,
    t: Any = 0,
    log: Optional[SteeringLog] = None,
    episode: Any = None,
    picks: Optional[List[Pick]] = None,
) -> Tuple[Tensor, Tensor]:
    """Algorithm 1. ``sample_fn(n)`` returns ``n`` candidate chunks for the observation row
    ``obs`` (shape ``(obs_dim,)``): ``(n, act_dim)`` or ``(n, chunk_len, action_dim)``; with a
    batch of rows ``obs`` ``(B, obs_dim)`` it returns ``(B, n, ...)``. Returns the best chunk
    (per row) and all scores ``(n,)`` / ``(B, n)``, as tensors like the candidates.

    With a :class:`~ufops.telemetry.SteeringLog` ``log`` the step is recorded for ``episode``
    (the source's episode index; a sequence of them with a batch): the candidates are first put
    on the half-float grid the log stores them on (:meth:`ufops.Verifier.telemetry_grid`), so the
    chunk returned is the one a replay scores."""
    import torch

    if n < 1:
        raise ValueError(f"n must be at least 1; got {n}")
    cands = sample_fn(n)
    raw: Optional[npt.NDArray[np.float32]] = None
    if log is not None:
        if episode is None:
            raise ValueError("recording a step needs the episode it belongs to (episode=)")
        if verifier.id is None:
            raise ValueError("recording a step needs a verifier loaded from an artifact (it has no id)")
        scored, raw = verifier.telemetry_grid(cands.detach().cpu().numpy())
        cands = torch.from_numpy(scored).to(device=cands.device, dtype=cands.dtype)
    started = time.perf_counter()
    picked = verifier.pick(obs, cands, _steps(t))
    latency_us = int((time.perf_counter() - started) * 1e6)
    if picks is not None:
        picks.append(picked)
    scores = picked.scores
    s = torch.from_numpy(np.ascontiguousarray(scores)).to(cands.device)
    best = torch.from_numpy(picked.chosen).to(cands.device)
    if s.dim() == 1:
        best = best[0]
    if log is not None and raw is not None:
        assert verifier.id is not None
        rows = int(s.shape[0]) if s.dim() == 2 else 1
        episodes = np.atleast_1d(np.asarray(episode)).reshape(-1)
        steps = np.broadcast_to(np.asarray(_steps(t)), (rows,)).reshape(-1)
        if len(episodes) != rows:
            raise ValueError(f"{len(episodes)} episodes for {rows} rows of candidates")
        score_rows = np.asarray(scores).reshape(rows, n)
        raw_rows = raw.reshape(rows, n, -1)
        chosen = best.reshape(-1).tolist()
        for r in range(rows):
            log.add(int(episodes[r]), int(steps[r]), verifier.id, raw_rows[r], score_rows[r], int(chosen[r]),
                    latency_us // rows)
    if s.dim() == 1:
        return cands[best], s
    return cands[torch.arange(cands.shape[0], device=cands.device), best], s


def guidance_gradient(verifier: Verifier, obs: Any, x0: Tensor, t: Any) -> Tensor:
    """∇ log C (classifier) or ∇ Q (q) w.r.t. the chunk ``x0``, a tensor like ``x0``."""
    import torch

    g = verifier.grad(obs, x0, _steps(t))
    return torch.from_numpy(np.ascontiguousarray(g)).to(device=x0.device, dtype=x0.dtype)


def ddpm_guidance(
    verifier: Verifier,
    obs: Any,
    alphas_cumprod: Any,
    lam: float,
    t: Any = 0,
) -> Callable[[Tensor, Any, Tensor], Tensor]:
    """A hook for an epsilon-predicting DDPM loop (diffusers' ``scheduler.step`` or your own)::

        hook = ddpm_guidance(verifier, obs, scheduler.alphas_cumprod, lam=3.0)
        for k in scheduler.timesteps:
            eps = policy(x, k, cond)
            eps = hook(eps, k, x)                 # Algorithm 2 on x̂0
            x = scheduler.step(eps, k, x).prev_sample

    ``alphas_cumprod[k]`` is ᾱ at the 0-based step ``k``; ``obs`` are the verifier's rows for
    ``x``'s batch and ``t`` their episode steps."""
    _policy_space(verifier)
    import torch

    ab = torch.as_tensor(alphas_cumprod, dtype=torch.float64)

    def hook(eps: Tensor, k: Any, x: Tensor) -> Tensor:
        if lam == 0.0:
            return eps
        a = float(ab[int(k)])
        sa, s1a = a**0.5, (1.0 - a) ** 0.5
        x0 = (x - s1a * eps) / sa
        g = guidance_gradient(verifier, obs, x0, t)
        # The eps whose x̂0 is x0 + lam * g.
        return eps - (sa / s1a) * lam * g

    return hook


def flow_guidance(
    verifier: Verifier,
    obs: Any,
    lam: float,
    t: Any = 0,
) -> Callable[[Tensor, float, Tensor], Tensor]:
    """A hook for a flow-matching Euler loop from flow time 1 (noise) to 0 (data)::

        hook = flow_guidance(verifier, obs, lam=1.0)
        for i in range(steps):
            s = 1 - i / steps
            v = hook(policy(x, s, cond), s, x)
            x = x - v / steps
    """
    _policy_space(verifier)

    def hook(v: Tensor, s: float, x: Tensor) -> Tensor:
        s = float(s)
        if lam == 0.0 or s >= 1.0 - 1e-6 or s <= 0.0:
            return v
        x0 = x - s * v
        g = guidance_gradient(verifier, obs, x0, t)
        return v - (lam / s) * g

    return hook


def as_tensor(a: np.ndarray[Any, Any], like: Optional[Tensor] = None) -> Tensor:
    """A numpy result as a tensor (sharing memory on the CPU), on ``like``'s device if given."""
    import torch

    out = torch.from_numpy(np.ascontiguousarray(a))
    return out if like is None else out.to(like.device)


class CameraObservation:
    """The verifier's observation row for a policy that sees through cameras (the paper's
    "frozen embedding of the base policy's vision encoder").

    Built once per rollout from the verifier and, per layer key of the verifier, the encoder
    that makes those features and its producer hash (what :func:`ufops.features.producer_of`
    computes and the store recorded when the layer was written)::

        cam = CameraObservation(verifier, {"features.front": (encode_front, producer_hash)})
        cam.reset()
        for step in range(T):
            row = cam.observe({"features.front": frame}, {"state": qpos})   # encoder runs once
            best, scores = best_of_n(verifier, sample_fn, row, n=30, t=step)  # N chunks, one call

    A verifier trained on another encoder's features is refused here, before the first score
    (``ValueError``). ``encode`` maps a batch of frames ``(B, H, W, C)`` uint8 to features
    ``(B, dim)``; plain observation keys (joint state) are passed as they are. The row stacks
    the last ``obs_history`` steps, oldest first, the first step repeated at the start of a
    rollout — as the trainer built its samples.
    """

    def __init__(self, verifier: Verifier, encoders: Any) -> None:
        import json

        self.verifier = verifier
        layout = json.loads(verifier.config_json())["input"]
        self.keys: list[tuple[str, int]] = [(k["key"], int(k["dim"])) for k in layout["obs_keys"]]
        self.history = int(layout["obs_history"])
        self.encoders = dict(encoders)
        verifier.check_producers({k: p for k, (_, p) in self.encoders.items()})
        self._steps: list[np.ndarray[Any, Any]] = []

    def reset(self) -> None:
        """Starts a new rollout (forgets the history)."""
        self._steps = []

    def step_features(self, frames: Any, state: Any = None) -> np.ndarray[Any, Any]:
        """One step's observation (the verifier's keys concatenated), running each encoder once."""
        parts = []
        state = state or {}
        for key, dim in self.keys:
            if key in self.encoders:
                encode = self.encoders[key][0]
                frame = np.asarray(frames[key])
                batch = frame[None] if frame.ndim == 3 else frame
                value = encode(batch)
                value = value.detach().cpu().numpy() if hasattr(value, "detach") else np.asarray(value)
                value = value.reshape(-1)
            elif key in state:
                value = np.asarray(state[key], dtype=np.float32).reshape(-1)
            else:
                raise ValueError(f"observation key {key!r}: give its frame (an encoder key) or its state value")
            if value.shape[0] != dim:
                raise ValueError(f"observation key {key!r}: {value.shape[0]} values, the verifier takes {dim}")
            parts.append(value.astype(np.float32))
        return np.concatenate(parts)

    def observe(self, frames: Any, state: Any = None) -> np.ndarray[Any, Any]:
        """Adds this step and returns the verifier's observation row ``(obs_dim,)``."""
        step = self.step_features(frames, state)
        if not self._steps:
            self._steps = [step] * self.history
        else:
            self._steps = (self._steps + [step])[-self.history :]
        return np.ascontiguousarray(np.concatenate(self._steps))
