"""``ufops.lerobot``: steer a LeRobot policy with a ufops verifier, inside LeRobot's own loops.

A LeRobot ``PreTrainedPolicy`` comes with its pre- and post-processor pipelines (normalisers,
device moves). Each function here takes the policy *and* its preprocessor, so the features, the
chunks and the actions are the ones the policy itself computes:

* :func:`encoder_of` — the policy's own image features: every camera through the policy's
  normaliser and its vision encoder in eval mode (centre crop), one row per frame. Its
  ``encoder(camera)`` / ``preprocess(camera)`` pair is what :func:`ufops.features.compute_layer`
  takes to write a layer over stored episodes; its ``producer(camera)`` names the policy
  checkpoint by a hash of its weights, config and normaliser statistics, so a verifier trained on
  the layer is refused by any other checkpoint.
* :func:`sample_chunks` — N action chunks from the policy's own sampler in one batched call, the
  observation encoded once: in the policy's normalised action space (what the verifier reads) and,
  with the postprocessor, in the robot's.
* :class:`SteeredPolicy` — a drop-in for the policy in a LeRobot control or evaluation loop
  (``lerobot-eval``'s ``eval_policy`` accepts it): ``select_action`` keeps the policy's action
  queue, re-plans when it runs dry, and then samples N chunks and executes the verifier's best
  (``mode="bon"``, the paper's Algorithm 1) or guides the sampler's x̂0 with the verifier's
  gradient (``mode="guidance"``, Algorithm 2); it logs steering telemetry like
  :func:`ufops.torch.best_of_n` and refuses a verifier trained on another producer's features.

What is specific to a policy class lives in one small adapter (:class:`DiffusionAdapter` for
LeRobot's ``DiffusionPolicy``): where the observation history is kept, how the conditioning is
computed once and where the image features sit in it, and how the sampler draws N chunks from it.
Another stochastic class plugs in by registering an adapter (:func:`register_adapter`) without
touching the rest. Deterministic classes (ACT) have nothing to choose among, and flow-matching
VLAs (pi0, SmolVLA) are not adapted yet: :func:`adapter_for` says so.

``lerobot`` and ``torch`` are imported by this module (``pip install lerobot``); ``import ufops``
does not import it.
"""

# The module holds the LeRobot surface in one place (encoder, sampler, steered policy and the
# DiffusionPolicy adapter), which users import as one: it is past 500 lines for that reason.
from __future__ import annotations

import hashlib
import json
import time
from dataclasses import dataclass
from typing import Any, Callable, Dict, List, Mapping, Optional, Sequence, Tuple

import numpy as np
import numpy.typing as npt
import torch
from lerobot.policies.pretrained import PreTrainedPolicy
from lerobot.policies.utils import populate_queues

from ufops.features import Producer, state_dict_sha256
from ufops.telemetry import SteeringLog
from ufops.verifier import Verifier

Tensor = Any  # torch.Tensor
Batch = Dict[str, Any]

OBS_STATE = "observation.state"
OBS_ENV_STATE = "observation.environment_state"
OBS_IMAGES = "observation.images"
ACTION = "action"
LAYER_PREFIX = "features."

# --- the policy's normaliser ------------------------------------------------------------------


def _normalizer(preprocessor: Any) -> Any:
    """The preprocessor's ``NormalizerProcessorStep`` (LeRobot's policy pipelines have one)."""
    from lerobot.processor import NormalizerProcessorStep

    steps = [s for s in getattr(preprocessor, "steps", []) if isinstance(s, NormalizerProcessorStep)]
    if len(steps) != 1:
        raise ValueError(
            f"the preprocessor must hold exactly one NormalizerProcessorStep (LeRobot's policy pipelines "
            f"do); found {len(steps)}: pass the preprocessor made with the policy (make_pre_post_processors)"
        )
    return steps[0]


def _stats_sha256(normalizer: Any) -> str:
    """sha256 of a normaliser's statistics and modes (they shape every feature and action)."""
    h = hashlib.sha256()
    h.update(json.dumps({str(k): str(v) for k, v in (normalizer.norm_map or {}).items()}, sort_keys=True).encode())
    for key in sorted(normalizer.stats or {}):
        for stat in sorted(normalizer.stats[key]):
            a = np.ascontiguousarray(np.asarray(normalizer.stats[key][stat], dtype=np.float64))
            h.update(f"{key}\0{stat}\0{list(a.shape)}\0".encode())
            h.update(a.tobytes())
    h.update(f"eps\0{normalizer.eps!r}".encode())
    return h.hexdigest()


def _mode(normalizer: Any, feature_type: str) -> str:
    for k, v in (normalizer.norm_map or {}).items():
        if str(getattr(k, "value", k)) == feature_type:
            return str(getattr(v, "value", v))
    return "IDENTITY"


def action_space(preprocessor: Any, key: str = ACTION) -> Tuple[List[float], List[float]]:
    """The policy's action normaliser as ``raw = x * scale + offset`` per action dimension: what
    ``ufops train --action-scale S… --action-offset O…`` takes, so the verifier reads chunks in the
    policy's normalised space (for MIN_MAX ``x = 2 (raw − min) / (max − min) − 1``; MEAN_STD
    ``x = (raw − mean) / (std + eps)``; IDENTITY: empty lists)."""
    norm = _normalizer(preprocessor)
    mode = _mode(norm, "ACTION")
    stats = (norm.stats or {}).get(key)
    if mode == "IDENTITY" or stats is None:
        return [], []
    if mode == "MIN_MAX":
        lo = np.asarray(stats["min"], np.float64)
        hi = np.asarray(stats["max"], np.float64)
        denom = np.where(hi - lo == 0, norm.eps, hi - lo)
        return (denom / 2).tolist(), (lo + denom / 2).tolist()
    if mode == "MEAN_STD":
        return (np.asarray(stats["std"], np.float64) + norm.eps).tolist(), np.asarray(stats["mean"], np.float64).tolist()
    raise ValueError(f"action normalisation {mode} has no affine form ufops can record")


def _normalize_observation(step: Any, observation: Dict[str, Tensor]) -> Dict[str, Tensor]:
    """``observation`` through a normaliser (or unnormaliser) step, as the pipeline runs it."""
    from lerobot.processor import TransitionKey

    return dict(step({TransitionKey.OBSERVATION: observation})[TransitionKey.OBSERVATION])


def _unnormalizer(normalizer: Any) -> Any:
    """The inverse of the preprocessor's normaliser, for observations (the postprocessor's
    unnormaliser covers only the action)."""
    from lerobot.processor import UnnormalizerProcessorStep

    return UnnormalizerProcessorStep(
        features=normalizer.features, norm_map=normalizer.norm_map, stats=normalizer.stats, eps=normalizer.eps
    )


# --- class-specific adapters -------------------------------------------------------------------


@dataclass
class Conditioning:
    """What a policy computed from its observation history at one re-plan."""

    history: Dict[str, Tensor]  # key -> (B, S, ...) normalised, as the policy stacked it
    image_features: Dict[str, Tensor]  # camera -> (B, S, D), the policy's own per-step features
    cond: Any  # the adapter's own conditioning (DiffusionPolicy: global_cond (B, S * per_step))


Guide = Callable[[Tensor, Any, Tensor], Tensor]  # (model output, scheduler step, x_k) -> model output


class PolicyAdapter:
    """The places where ufops touches a policy class. Subclass it for another stochastic class and
    :func:`register_adapter` it under the class's ``name``."""

    name = ""
    #: Whether :meth:`sample` can take a guidance hook on the sampler's x̂0.
    guidance = False

    def image_keys(self, policy: Any) -> List[str]:
        raise NotImplementedError

    def encode(self, policy: Any, camera: str, images: Tensor) -> Tensor:
        """The policy's own features of normalised images ``(B, C, H, W)`` of ``camera``: ``(B, D)``."""
        raise NotImplementedError

    def observe(self, policy: Any, batch: Batch) -> None:
        """Adds this step's preprocessed observation to the policy's history."""
        raise NotImplementedError

    def needs_plan(self, policy: Any) -> bool:
        raise NotImplementedError

    def condition(self, policy: Any) -> Conditioning:
        """Encodes the history once (the policy's own conditioning)."""
        raise NotImplementedError

    def sample(self, policy: Any, cond: Conditioning, n: int, guide: Optional[Guide] = None) -> Tensor:
        """``n`` chunks per row from the policy's sampler: ``(B, n, steps, action_dim)`` normalised,
        the steps the policy executes from this observation on."""
        raise NotImplementedError

    def enqueue(self, policy: Any, chunk: Tensor) -> None:
        """Queues ``chunk`` ``(B, steps, action_dim)`` for execution."""
        raise NotImplementedError

    def pop(self, policy: Any) -> Tensor:
        """The next queued action ``(B, action_dim)`` (normalised)."""
        raise NotImplementedError

    def alphas_cumprod(self, policy: Any) -> Tensor:
        raise NotImplementedError(f"{self.name}: no DDPM schedule")


class DiffusionAdapter(PolicyAdapter):
    """LeRobot's ``DiffusionPolicy`` (Chi et al.): a DDPM/DDIM sampler conditioned on
    ``global_cond``, which stacks, for each of ``n_obs_steps`` steps, the normalised state, every
    camera's ``rgb_encoder`` features and the environment state. Its observation and action queues
    are the policy's ``_queues``; the chunk executed from a re-plan is the ``n_action_steps`` steps
    from the current observation on (``horizon`` steps are sampled)."""

    name = "diffusion"
    guidance = True

    def image_keys(self, policy: Any) -> List[str]:
        return list(policy.config.image_features)

    def _encoder(self, policy: Any, camera: str) -> Any:
        keys = self.image_keys(policy)
        if camera not in keys:
            raise KeyError(f"camera {camera!r} is not an input of the policy; its cameras: {keys}")
        enc = policy.diffusion.rgb_encoder
        return enc[keys.index(camera)] if policy.config.use_separate_rgb_encoder_per_camera else enc

    def encode(self, policy: Any, camera: str, images: Tensor) -> Tensor:
        return self._encoder(policy, camera)(images)

    def observe(self, policy: Any, batch: Batch) -> None:
        # As DiffusionPolicy.select_action does: cameras stacked into one key, then queued.
        if ACTION in batch:
            batch = {k: v for k, v in batch.items() if k != ACTION}
        if policy.config.image_features:
            batch = dict(batch)
            batch[OBS_IMAGES] = torch.stack([batch[k] for k in policy.config.image_features], dim=-4)
        policy._queues = populate_queues(policy._queues, batch)

    def needs_plan(self, policy: Any) -> bool:
        return len(policy._queues[ACTION]) == 0

    def condition(self, policy: Any) -> Conditioning:
        q = policy._queues
        history = {k: torch.stack(list(q[k]), dim=1) for k in (OBS_STATE, OBS_IMAGES, OBS_ENV_STATE) if k in q}
        model = policy.diffusion
        cond = model._prepare_global_conditioning(history)  # (B, S * per_step)
        b, s = history[OBS_STATE].shape[:2]
        per_step = cond.view(b, s, -1)
        state_dim = history[OBS_STATE].shape[-1]
        keys = self.image_keys(policy)
        feats: Dict[str, Tensor] = {}
        if keys:
            d = (per_step.shape[-1] - state_dim - (history[OBS_ENV_STATE].shape[-1] if OBS_ENV_STATE in history else 0)) // len(keys)
            for i, k in enumerate(keys):
                feats[k] = per_step[:, :, state_dim + i * d : state_dim + (i + 1) * d]
        return Conditioning(history=history, image_features=feats, cond=cond)

    def sample(self, policy: Any, cond: Conditioning, n: int, guide: Optional[Guide] = None) -> Tensor:
        model = policy.diffusion
        gc = cond.cond
        b = gc.shape[0]
        gc_n = gc.repeat_interleave(n, dim=0) if n > 1 else gc
        if guide is None:
            x = model.conditional_sample(b * n, global_cond=gc_n)
        else:
            x = self._guided_sample(model, b * n, gc_n, guide)
        start = policy.config.n_obs_steps - 1
        x = x[:, start : start + policy.config.n_action_steps]
        return x.reshape(b, n, *x.shape[1:])

    @staticmethod
    def _guided_sample(model: Any, batch: int, gc: Tensor, guide: Guide) -> Tensor:
        # DiffusionModel.conditional_sample with the model output passed through `guide`.
        p = next(model.parameters())
        x = torch.randn((batch, model.config.horizon, model.config.action_feature.shape[0]), dtype=p.dtype, device=p.device)
        sched = model.noise_scheduler
        sched.set_timesteps(model.num_inference_steps)
        for k in sched.timesteps:
            out = model.unet(x, torch.full(x.shape[:1], k, dtype=torch.long, device=x.device), global_cond=gc)
            out = guide(out, k, x)
            x = sched.step(out, k, x).prev_sample
        return x

    def enqueue(self, policy: Any, chunk: Tensor) -> None:
        policy._queues[ACTION].extend(chunk.transpose(0, 1))

    def pop(self, policy: Any) -> Tensor:
        return policy._queues[ACTION].popleft()

    def alphas_cumprod(self, policy: Any) -> Tensor:
        sched = policy.diffusion.noise_scheduler
        if policy.config.prediction_type != "epsilon":
            raise NotImplementedError("guidance needs an epsilon-predicting DiffusionPolicy (prediction_type='epsilon')")
        if type(sched).__name__ != "DDPMScheduler":
            raise NotImplementedError(f"guidance is written for the DDPM scheduler; the policy uses {type(sched).__name__}")
        return sched.alphas_cumprod


_ADAPTERS: Dict[str, PolicyAdapter] = {"diffusion": DiffusionAdapter()}
_NOT_ADAPTED = {
    "act": "ACT predicts its chunk deterministically (a zero latent at inference): best-of-N would score N copies",
    "pi0": "pi0's flow sampler is not adapted yet (its conditioning is a VLM prefix; the velocity hook is ufops.torch.flow_guidance)",
    "pi05": "pi0.5's flow sampler is not adapted yet",
    "smolvla": "SmolVLA's flow sampler is not adapted yet",
}


def register_adapter(adapter: PolicyAdapter) -> None:
    """Makes ``adapter`` the one for policies whose ``name`` is ``adapter.name``."""
    if not adapter.name:
        raise ValueError("an adapter needs the policy class's name")
    _ADAPTERS[adapter.name] = adapter


def adapter_for(policy: Any) -> PolicyAdapter:
    """The adapter of ``policy``'s class (by its LeRobot ``name``), or an error saying why there is none."""
    name = str(getattr(policy, "name", "") or type(policy).__name__)
    if name in _ADAPTERS:
        return _ADAPTERS[name]
    why = _NOT_ADAPTED.get(name, "no adapter is registered for it (ufops.lerobot.register_adapter)")
    raise NotImplementedError(f"LeRobot policy {name!r} cannot be steered: {why}; adapted: {sorted(_ADAPTERS)}")


# --- the policy's own image features ------------------------------------------------------------


def _short(camera: str) -> str:
    return camera[len(OBS_IMAGES) + 1 :] if camera.startswith(OBS_IMAGES + ".") else camera


class PolicyEncoder:
    """The policy's image features, per camera: see :func:`encoder_of`."""

    def __init__(self, policy: Any, preprocessor: Any, *, policy_name: str, checkpoint: str) -> None:
        self.policy = policy
        self.adapter = adapter_for(policy)
        self.normalizer = _normalizer(preprocessor)
        self.policy_name = policy_name
        self.checkpoint = checkpoint
        self.cameras = self.adapter.image_keys(policy)
        if not self.cameras:
            raise ValueError("the policy has no camera inputs (image_features is empty)")
        config_json = json.dumps(_config_dict(policy.config), sort_keys=True, default=str)
        h = hashlib.sha256()
        for part in (state_dict_sha256(policy), hashlib.sha256(config_json.encode()).hexdigest(), _stats_sha256(self.normalizer)):
            h.update(part.encode())
        self.content_hash = h.hexdigest()

    def __repr__(self) -> str:
        return f"PolicyEncoder({self.adapter.name}, cameras={self.cameras}, content_hash={self.content_hash[:12]})"

    def layer_name(self, camera: str) -> str:
        """The layer this camera's features are written as: ``features.<policy_name>.<camera>``."""
        return f"{LAYER_PREFIX}{self.policy_name}.{_short(camera)}"

    def producer(self, camera: str) -> Producer:
        """Who makes the layer: the policy class and camera, the policy name and checkpoint, and a
        sha256 of the policy's weights, config and normaliser statistics."""
        if camera not in self.cameras:
            raise KeyError(f"camera {camera!r} is not an input of the policy; its cameras: {self.cameras}")
        return Producer(
            encoder=f"lerobot/{self.adapter.name}/{camera}",
            policy=self.policy_name,
            checkpoint=self.checkpoint,
            content_hash=self.content_hash,
        )

    def producer_hash(self, camera: str) -> str:
        """The store's hash of :meth:`producer` (what a verifier trained on the layer records)."""
        from ufops import _ufops

        return str(_ufops.Store.producer_hash(json.dumps(self.producer(camera).to_dict())))

    def normalize(self, camera: str, images: Tensor) -> Tensor:
        """Images ``(B, C, H, W)`` in [0, 1] through the policy's normaliser (its VISUAL mode and stats)."""
        return _normalize_observation(self.normalizer, {camera: images})[camera]

    def preprocess(self, camera: str) -> Callable[[npt.NDArray[np.uint8]], Tensor]:
        """uint8 frames ``(B, H, W, C)`` → the camera's normalised ``(B, C, H, W)`` float32 tensor, as
        LeRobot's ``preprocess_observation`` and the preprocessor make it."""

        def prep(frames: npt.NDArray[np.uint8]) -> Tensor:
            x = torch.from_numpy(np.ascontiguousarray(frames)).permute(0, 3, 1, 2).to(torch.float32) / 255.0
            return self.normalize(camera, x.contiguous())

        return prep

    def encoder(self, camera: str) -> Callable[[Tensor], Tensor]:
        """Normalised images of ``camera`` → the policy's features ``(B, D)`` (eval mode, no grad)."""
        policy, adapter = self.policy, self.adapter

        def enc(x: Tensor) -> Tensor:
            training = policy.training
            policy.eval()
            try:
                with torch.inference_mode():
                    return adapter.encode(policy, camera, x.to(next(policy.parameters()).device))
            finally:
                if training:
                    policy.train()

        return enc

    def __call__(self, camera: str, frames: npt.NDArray[np.uint8]) -> npt.NDArray[np.float32]:
        """Features of uint8 frames ``(B, H, W, C)`` of ``camera``: ``(B, D)`` float32."""
        out = self.encoder(camera)(self.preprocess(camera)(frames))
        return np.ascontiguousarray(out.detach().to("cpu", torch.float32).numpy())

    def compute_layers(self, store: Any, **kwargs: Any) -> Dict[str, Any]:
        """:func:`ufops.features.compute_layer` for every camera (keyword arguments are passed on);
        returns each layer's report by its name."""
        from ufops.features import compute_layer

        reports = {}
        for cam in self.cameras:
            name = self.layer_name(cam)
            reports[name] = compute_layer(
                store, self.encoder(cam), name=name, camera=cam, producer=self.producer(cam),
                preprocess=self.preprocess(cam), **kwargs,
            )
        return reports


def _config_dict(config: Any) -> Dict[str, Any]:
    import dataclasses

    if dataclasses.is_dataclass(config):
        return {f.name: getattr(config, f.name) for f in dataclasses.fields(config) if f.name not in ("device", "push_to_hub", "repo_id", "pretrained_path")}
    return dict(vars(config))


def encoder_of(policy: Any, preprocessor: Any, *, policy_name: str, checkpoint: str) -> PolicyEncoder:
    """The policy's own image features, exactly as it computes them, for every camera::

        enc = ufops.lerobot.encoder_of(policy, preprocessor, policy_name="lift-dp", checkpoint="step-3000")
        enc.compute_layers(store)                                # features.lift-dp.<camera> layers
        # or one camera: features.compute_layer(store, enc.encoder(cam), preprocess=enc.preprocess(cam),
        #                name=enc.layer_name(cam), camera=cam, producer=enc.producer(cam))
        feats = enc(cam, frames)                                 # live frames (B, H, W, C) -> (B, D)

    A frame goes through the policy's normaliser (its VISUAL statistics) and the camera's vision
    encoder in eval mode (the centre crop), as ``_prepare_global_conditioning`` runs it for each
    observation step; a verifier reading ``obs_history = n_obs_steps`` steps of the layer sees
    what the policy's conditioning holds."""
    return PolicyEncoder(policy, preprocessor, policy_name=policy_name, checkpoint=checkpoint)


# --- N chunks from the policy's sampler ----------------------------------------------------------


@dataclass
class Chunks:
    """N chunks per observation row from one conditioning."""

    normalized: Tensor  # (B, N, steps, action_dim): the policy's sample space (what a verifier reads)
    actions: Optional[Tensor]  # the same in the robot's action space (with a postprocessor), else None
    conditioning: Conditioning


def sample_chunks(
    policy: Any, batch: Batch, n: int, *, postprocessor: Any = None, guide: Optional[Guide] = None
) -> Chunks:
    """``n`` action chunks for the policy's observation history after ``batch`` (a preprocessed
    observation, as ``select_action`` takes it; it is added to the policy's history as
    ``select_action`` would), from one conditioning (the encoder runs once) and one batched call
    of the policy's sampler; only the denoiser sees the ``B·n`` batch."""
    if n < 1:
        raise ValueError(f"n must be at least 1; got {n}")
    adapter = adapter_for(policy)
    adapter.observe(policy, batch)
    with torch.inference_mode():
        cond = adapter.condition(policy)
        x = adapter.sample(policy, cond, n, guide)
    actions = postprocessor(x) if postprocessor is not None else None
    return Chunks(normalized=x, actions=actions, conditioning=cond)


# --- the steered policy ---------------------------------------------------------------------------


@dataclass
class Plan:
    """What one re-plan chose among (kept as :attr:`SteeredPolicy.last_plan`)."""

    t: int  # the episode step of the observation planned from
    candidates: Tensor  # (B, N, steps, action_dim), normalised (on the telemetry grid when logging)
    scores: Optional[npt.NDArray[np.float32]]  # (B, N); None when N = 1 without a log (nothing scored)
    chosen: npt.NDArray[np.int64]  # (B,) index of the executed candidate
    rows: npt.NDArray[np.float32]  # (B, obs_dim) the verifier's observation rows
    # (B,) an ensemble's members disagreed, so the policy's own first candidate was kept
    fell_back: Optional[npt.NDArray[np.bool_]] = None


@dataclass
class ReplanTiming:
    """Wall time of one re-plan, in seconds."""

    encode: float  # the conditioning (the encoder runs once)
    sample: float  # the sampler's N chunks
    score: float  # building the verifier's rows and scoring (or the gradients, with guidance)
    total: float


class SteeredPolicy(PreTrainedPolicy):  # type: ignore[misc]
    """A LeRobot policy steered by a ufops verifier, a drop-in wherever the policy was used::

        steered = SteeredPolicy(policy, verifier, preprocessor, n=8)                 # best-of-8
        steered = SteeredPolicy(policy, verifier, preprocessor, mode="guidance", lam=1.0)
        action = steered.select_action(preprocessor(observation))                   # as before
        action = postprocessor(action)

    ``select_action`` keeps the policy's queue: actions are popped from it, and only when it is
    empty is the next chunk chosen, scored once per re-plan: the observation history is encoded
    once, the sampler draws ``n`` chunks (``n = 1``: exactly the policy's own draw), the verifier
    scores the executed steps of each in the policy's normalised space, and the best is queued.
    With ``mode="guidance"`` the sampler's x̂0 is nudged by ``lam · ∇ log C`` (classifier) or
    ``lam · ∇ Q`` at every denoising step (the policy's scheduler then clips it as it always
    does), over the executed steps.

    The verifier's observation row is built from what the policy computed: for a layer key, the
    policy's own features of its camera at each of the last ``obs_history`` steps (taken from the
    conditioning, not recomputed); for another key (``state``, ``observation.state``), the
    policy's history of that observation with its normaliser undone (the raw values the store
    keeps). ``layers`` maps a verifier's layer key to a camera (default: the key
    ``features.<policy_name>.<camera>`` that :func:`encoder_of` names). The verifier must have
    been trained on this policy's features: its recorded producers are checked against
    :func:`encoder_of`'s, and another checkpoint's are refused (``ValueError``).

    ``log`` records each re-plan's candidates for ``ufops replay`` (:mod:`ufops.telemetry`); the
    episode of row ``b`` is ``episode_base + b``, where ``episode_base`` counts the rows of every
    earlier :meth:`reset` (LeRobot's ``eval_policy`` numbers episodes the same way), or the
    ``episodes`` given to :meth:`reset`. ``timings`` keeps each re-plan's :class:`ReplanTiming`.
    """

    config_class = object
    name = "ufops-steered"

    def __init__(
        self,
        policy: Any,
        verifier: Verifier,
        preprocessor: Any,
        *,
        n: int = 8,
        mode: str = "bon",
        lam: float = 0.0,
        policy_name: Optional[str] = None,
        checkpoint: Optional[str] = None,
        layers: Optional[Mapping[str, str]] = None,
        log: Optional[SteeringLog] = None,
        keep_timings: bool = True,
    ) -> None:
        super().__init__(policy.config)
        if mode not in ("bon", "guidance"):
            raise ValueError(f"mode must be 'bon' or 'guidance'; got {mode!r}")
        if n < 1:
            raise ValueError(f"n must be at least 1; got {n}")
        self.policy = policy
        self.verifier = verifier
        self.adapter = adapter_for(policy)
        self.n = int(n)
        self.mode = mode
        self.lam = float(lam)
        self.log = log
        self.keep_timings = keep_timings
        self.timings: List[ReplanTiming] = []
        self.last_plan: Optional[Plan] = None
        self.normalizer = _normalizer(preprocessor)
        self.unnormalizer = _unnormalizer(self.normalizer)
        if mode == "guidance":
            if not self.adapter.guidance:
                raise NotImplementedError(f"{self.adapter.name}: its sampler takes no guidance hook")
            if not verifier.takes_policy_space:
                raise ValueError(f"verifier {verifier.id} reads raw actions: guidance needs one trained in the policy's space")
            self._alphas = torch.as_tensor(self.adapter.alphas_cumprod(policy), dtype=torch.float64)
        cfg = verifier.config()["input"]
        self.obs_keys: List[Tuple[str, int]] = [(k["key"], int(k["dim"])) for k in cfg["obs_keys"]]
        self.obs_history = int(cfg["obs_history"])
        n_obs = int(getattr(policy.config, "n_obs_steps", 1))
        if self.obs_history > n_obs:
            raise ValueError(
                f"the verifier reads {self.obs_history} observation steps; the policy keeps {n_obs} (n_obs_steps)"
            )
        steps = int(getattr(policy.config, "n_action_steps", verifier.chunk_len))
        if verifier.chunk_len != steps:
            raise ValueError(
                f"the verifier scores chunks of {verifier.chunk_len} steps; the policy executes {steps} per re-plan "
                "(n_action_steps): train it with --chunk-len equal to n_action_steps"
            )
        # Which camera each layer key reads, and the producer check.
        self.encoder = PolicyEncoder(
            policy, preprocessor, policy_name=policy_name or "policy", checkpoint=checkpoint or "unknown"
        )
        required = verifier.required_producers
        self.layers: Dict[str, str] = dict(layers or {})
        if not layers and policy_name is not None:
            self.layers = {self.encoder.layer_name(c): c for c in self.encoder.cameras}
        unmapped = [k for k, _ in self.obs_keys if k in required and k not in self.layers]
        if unmapped:
            raise ValueError(
                f"the verifier reads layers {unmapped}: give the policy_name/checkpoint they were computed with "
                f"(layer features.<policy_name>.<camera>) or layers={{layer: camera}}"
            )
        provided = {k: self.encoder.producer_hash(c) for k, c in self.layers.items() if k in required}
        verifier.check_producers(provided)
        for key, _ in self.obs_keys:
            if key not in self.layers and self._obs_source(key) is None:
                raise ValueError(f"the verifier reads {key!r}, which is neither a layer nor an observation the policy keeps")
        self._episode_base = 0
        self._rows = 0
        self._episodes: Optional[List[int]] = None
        self._t = 0

    def _obs_source(self, key: str) -> Optional[str]:
        """The policy's history key of a low-dimensional verifier key (``state`` → ``observation.state``)."""
        for name in (OBS_STATE, OBS_ENV_STATE):
            if key in (name, name[len("observation.") :]):
                return name
        return None

    # PreTrainedPolicy's interface.
    def get_optim_params(self) -> Any:
        return self.policy.get_optim_params()

    def forward(self, batch: Batch) -> Any:
        raise TypeError("a SteeredPolicy is for inference; train the policy itself")

    def reset(self, episodes: Optional[Sequence[int]] = None) -> None:
        """Starts new episodes (LeRobot calls it at every environment reset). ``episodes``: the
        source's episode index of each row, for the telemetry (default: counted on)."""
        self.policy.reset()
        self._episode_base += self._rows
        self._rows = 0
        self._episodes = [int(e) for e in episodes] if episodes is not None else None
        self._t = 0

    def predict_action_chunk(self, batch: Batch, **kwargs: Any) -> Tensor:
        """The chosen chunk ``(B, steps, action_dim)`` for the history after ``batch``."""
        self.adapter.observe(self.policy, batch)
        return self._plan(batch)

    def select_action(self, batch: Batch, **kwargs: Any) -> Tensor:
        with torch.no_grad():
            return self._select_action(batch)

    def _select_action(self, batch: Batch) -> Tensor:
        b = next(iter(v for v in batch.values() if isinstance(v, torch.Tensor))).shape[0]
        self._rows = max(self._rows, b)
        self.adapter.observe(self.policy, batch)
        if self.adapter.needs_plan(self.policy):
            self.adapter.enqueue(self.policy, self._plan(batch))
        self._t += 1
        return self.adapter.pop(self.policy)

    # Steering.
    def _verifier_rows(self, cond: Conditioning) -> npt.NDArray[np.float32]:
        h = self.obs_history
        parts = []
        for key, dim in self.obs_keys:
            if key in self.layers:
                v = cond.image_features[self.layers[key]][:, -h:]
            else:
                name = self._obs_source(key)
                assert name is not None
                v = _normalize_observation(self.unnormalizer, {name: cond.history[name][:, -h:]})[name]
            if v.shape[-1] != dim:
                raise ValueError(f"observation key {key!r}: the policy gives {v.shape[-1]} values, the verifier takes {dim}")
            parts.append(v.to(torch.float32))
        # (B, h, sum dims) -> rows of h steps, oldest first, each step its keys in order.
        return np.ascontiguousarray(torch.cat(parts, dim=-1).reshape(parts[0].shape[0], -1).cpu().numpy())

    def _guide(self, rows: npt.NDArray[np.float32]) -> Guide:
        """Algorithm 2's hook on the executed steps of x̂0: ε' whose x̂0 is x̂0 + λ ∇."""
        from ufops.torch import guidance_gradient

        start = self.policy.config.n_obs_steps - 1
        stop = start + self.policy.config.n_action_steps
        n, t = self.n, self._t
        obs = np.repeat(rows, n, axis=0) if n > 1 else rows
        steps = np.full(obs.shape[0], t, np.int64)

        def guide(eps: Tensor, k: Any, x: Tensor) -> Tensor:
            if self.lam == 0.0:
                return eps
            a = float(self._alphas[int(k)])
            sa, s1a = a**0.5, (1.0 - a) ** 0.5
            x0 = (x - s1a * eps) / sa
            g = torch.zeros_like(x0)
            part = x0[:, start:stop].reshape(x0.shape[0], -1).contiguous()
            g[:, start:stop] = guidance_gradient(self.verifier, obs, part, steps).reshape(x0.shape[0], stop - start, -1)
            return eps - (sa / s1a) * self.lam * g

        return guide

    def _plan(self, batch: Batch) -> Tensor:
        t0 = time.perf_counter()
        cond = self.adapter.condition(self.policy)
        rows = self._verifier_rows(cond)
        t1 = time.perf_counter()
        # The verifier's gradient comes from the verifier core, not from autograd.
        guide = self._guide(rows) if self.mode == "guidance" else None
        cands = self.adapter.sample(self.policy, cond, self.n, guide)  # (B, n, steps, A)
        t2 = time.perf_counter()
        b = cands.shape[0]
        scores: Optional[npt.NDArray[np.float32]] = None
        pick = np.zeros(b, np.int64)
        fell_back: Optional[npt.NDArray[np.bool_]] = None
        if self.n == 1 and self.log is None:
            chosen = cands[:, 0]
        else:
            flat = cands.reshape(b, self.n, -1)
            raw: Optional[npt.NDArray[np.float32]] = None
            if self.log is not None:
                if self.verifier.id is None:
                    raise ValueError("recording telemetry needs a verifier loaded from an artifact")
                scored, raw = self.verifier.telemetry_grid(flat.detach().cpu().numpy())
                flat = torch.from_numpy(scored).to(device=cands.device, dtype=cands.dtype)
            s0 = time.perf_counter()
            # The verifier core's choice: the argmax, or an ensemble's pessimistic pick that keeps
            # the policy's own first candidate when the members disagree.
            picked = self.verifier.pick(rows, flat.detach().cpu().numpy(), np.full(b, self._t, np.int64))
            scores = np.asarray(picked.scores).reshape(b, self.n)
            score_s = time.perf_counter() - s0
            pick = picked.chosen
            fell_back = picked.fell_back
            chosen = flat[torch.arange(b), torch.as_tensor(pick)].reshape(b, *cands.shape[2:])
            cands = flat.reshape(cands.shape)
            if self.log is not None and raw is not None:
                raw_rows = raw.reshape(b, self.n, -1)
                for r in range(b):
                    ep = self._episodes[r] if self._episodes is not None else self._episode_base + r
                    self.log.add(ep, self._t, str(self.verifier.id), raw_rows[r], scores[r], int(pick[r]),
                                 int(score_s * 1e6) // b)
        t3 = time.perf_counter()
        self.last_plan = Plan(
            t=self._t, candidates=cands, scores=scores, chosen=pick.astype(np.int64), rows=rows, fell_back=fell_back
        )
        if self.keep_timings:
            self.timings.append(ReplanTiming(encode=t1 - t0, sample=t2 - t1, score=t3 - t2, total=t3 - t0))
        return chosen
