"""ufops.lerobot with a real LeRobot ``DiffusionPolicy`` (lerobot from PyPI, random weights, a
small config) on the repository's LeRobot v3.0 video fixture, ingested with the CLI:

* the layer ``encoder_of`` computes over the stored episodes (frames decoded from the store's AV1
  video by range reads) equals, row for row, the image features the policy's own
  ``_prepare_global_conditioning`` computes for the same frames as LeRobotDataset loads them
  (its pyav backend, ``n_obs_steps`` frames per sample, the history padded at an episode's start);
* ``SteeredPolicy`` with N = 1 returns exactly the unsteered policy's actions for the same seed;
  with N > 1 it executes the verifier's argmax among chunks the policy's sampler produced, checked
  against the same draw redone here and scored separately from independently built rows; the
  action queue is refilled (and the sampler run) only at re-plans; a verifier trained on another
  checkpoint's features is refused;
* ``sample_chunks`` encodes once whatever N, and its two action spaces are the postprocessor apart;
* guidance with λ = 0 is the policy's own sampler, and λ > 0 moves the chunk;
* ``SteeredPolicy`` runs in the policy's place in lerobot-eval's ``eval_policy`` (two environments
  a batch), re-planning every ``n_action_steps`` and numbering its telemetry as lerobot numbers
  the episodes.
"""
from __future__ import annotations

import json
import os
import shutil
from pathlib import Path
from typing import Any, Dict, List, Tuple

import numpy as np
import pytest

from conftest import REPO, Ufops, require

torch = require("torch")
require("av")
pl = require("polars")
require("lerobot")

os.environ.setdefault("HF_HUB_OFFLINE", "1")

import gymnasium as gym  # noqa: E402
from lerobot.configs.types import FeatureType  # noqa: E402
from lerobot.datasets.lerobot_dataset import LeRobotDataset  # noqa: E402
from lerobot.datasets.utils import dataset_to_policy_features  # noqa: E402
from lerobot.policies.diffusion.configuration_diffusion import DiffusionConfig  # noqa: E402
from lerobot.policies.diffusion.modeling_diffusion import DiffusionPolicy  # noqa: E402
from lerobot.policies.factory import make_pre_post_processors  # noqa: E402

import ufops  # noqa: E402
from ufops import lerobot as ul  # noqa: E402

FIXTURE = REPO / "fixtures" / "lerobot" / "v30_eval_video"
CAMERA = "observation.images.front"
POLICY, CHECKPOINT = "toy-dp", "random-0"
LAYER = f"features.{POLICY}.front"


def make_policy(root: Path, seed: int) -> Tuple[Any, Any, Any]:
    """A small DiffusionPolicy (ResNet-18 encoder, random weights) for the fixture's features,
    with the pre/post-processors made from the dataset's statistics."""
    meta = LeRobotDataset("ufops/fixture", root=root, video_backend="pyav").meta
    feats = dataset_to_policy_features(meta.features)
    out = {k: f for k, f in feats.items() if f.type is FeatureType.ACTION}
    inp = {k: f for k, f in feats.items() if k not in out and f.type in (FeatureType.VISUAL, FeatureType.STATE)}
    cfg = DiffusionConfig(
        input_features=inp, output_features=out, n_obs_steps=2, horizon=16, n_action_steps=8, crop_shape=(56, 56),
        down_dims=(16, 32, 64), diffusion_step_embed_dim=16, spatial_softmax_num_keypoints=8,
        num_inference_steps=10, device="cpu",
    )
    torch.manual_seed(seed)
    policy = DiffusionPolicy(cfg).eval()
    pre, post = make_pre_post_processors(cfg, dataset_stats=meta.stats)
    return policy, pre, post


@pytest.fixture(scope="module")
def dataset_root(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("lerobot") / "v30_eval_video"
    shutil.copytree(FIXTURE, root)
    return root


@pytest.fixture(scope="module")
def setup(dataset_root: Path, tmp_path_factory: pytest.TempPathFactory) -> Dict[str, Any]:
    """The fixture ingested, the policy's layer written with encoder_of, and a classifier trained
    on it (layer + state, chunks of n_action_steps in the policy's normalised space)."""
    torch.set_num_threads(1)
    u = Ufops(tmp_path_factory.mktemp("store"))
    u.run("init")
    u.run("ingest", str(FIXTURE), "--policy", POLICY, "--checkpoint", CHECKPOINT, "--format", "lerobot")
    policy, pre, post = make_policy(dataset_root, seed=0)
    enc = ul.encoder_of(policy, pre, policy_name=POLICY, checkpoint=CHECKPOINT)
    store = ufops.Store(str(u.data_dir))
    reports = enc.compute_layers(store, batch_size=64, commit_every=4, progress=False)
    assert list(reports) == [LAYER]
    assert reports[LAYER].frames == 519 and reports[LAYER].episodes_written == 8
    split = u.json("split", "create", "--policy", POLICY, "--checkpoint", CHECKPOINT, "--val-fraction", "0.25",
                   "--seed", "1", "--json")["id"]
    scale, offset = ul.action_space(pre)
    recipe = u.data_dir / "recipe.json"
    recipe.write_text(json.dumps({"epochs": 2, "batch_size": 128}))
    u.run("train", "--split", split, "--kind", "classifier", "--obs-keys", f"{LAYER},state", "--chunk-len", "8",
          "--config", str(recipe), "--action-scale", *map(str, scale), "--action-offset", *map(str, offset))
    verifier = ufops.Verifier.from_store(store, f"{POLICY}/{CHECKPOINT}/classifier@latest")
    return {"u": u, "store": store, "policy": policy, "pre": pre, "post": post, "enc": enc, "verifier": verifier}


def dataset_batches(root: Path, policy: Any, batch_size: int = 64) -> Any:
    """LeRobotDataset samples with the policy's observation history (n_obs_steps frames)."""
    fps = LeRobotDataset("ufops/fixture", root=root, video_backend="pyav").meta.fps
    dt = {k: [i / fps for i in policy.config.observation_delta_indices] for k in (CAMERA, "observation.state")}
    ds = LeRobotDataset("ufops/fixture", root=root, delta_timestamps=dt, video_backend="pyav")
    return torch.utils.data.DataLoader(ds, batch_size=batch_size, shuffle=False)


def test_layer_rows_equal_the_policys_own_conditioning(setup: Dict[str, Any], dataset_root: Path) -> None:
    policy, pre, store = setup["policy"], setup["pre"], setup["store"]
    eps = store.episodes()
    by_index = dict(zip(eps["source_index"].to_list(), eps["id"].to_list()))
    steps = store.steps(list(by_index.values()), layers=[LAYER])
    layer = {(r["episode_id"], r["t"]): np.asarray(r[f"obs.{LAYER}"], np.float32)
             for r in steps.select("episode_id", "t", f"obs.{LAYER}").iter_rows(named=True)}
    assert len(layer) == 519
    checked = 0
    for batch in dataset_batches(dataset_root, policy):
        b = pre(dict(batch))
        b["observation.images"] = torch.stack([b[CAMERA]], dim=-4)
        with torch.inference_mode():
            cond = policy.diffusion._prepare_global_conditioning(b)  # (B, 2 * (6 + 16))
        per_step = cond.view(cond.shape[0], 2, -1)[:, :, 6:].numpy()  # image features of t-1 and t
        for i in range(cond.shape[0]):
            ep = by_index[int(batch["episode_index"][i])]
            t = int(batch["frame_index"][i])
            for s, when in enumerate((max(t - 1, 0), t)):
                np.testing.assert_allclose(layer[(ep, when)], per_step[i, s], rtol=1e-4, atol=1e-5,
                                           err_msg=f"episode {ep} step {t} history {s}")
            checked += 1
    assert checked == 519
    # The producer names the checkpoint: other weights, another hash.
    other, pre2, _ = make_policy(dataset_root, seed=1)
    assert ul.encoder_of(other, pre2, policy_name=POLICY, checkpoint=CHECKPOINT).content_hash != setup["enc"].content_hash


def observations(root: Path, episode: int, steps: int) -> List[Dict[str, Any]]:
    """An episode's frames as a LeRobot evaluation feeds them (batch of 1, images in [0, 1])."""
    ds = LeRobotDataset("ufops/fixture", root=root, video_backend="pyav")
    idx = [i for i in range(len(ds)) if int(ds.hf_dataset[i]["episode_index"]) == episode][:steps]
    out = []
    for i in idx:
        item = ds[i]
        out.append({CAMERA: item[CAMERA][None], "observation.state": item["observation.state"][None]})
    return out


def run(policy: Any, pre: Any, obs: List[Dict[str, Any]], seed: int) -> Any:
    torch.manual_seed(seed)
    policy.reset()
    with torch.inference_mode():
        return torch.stack([policy.select_action(pre(dict(o))) for o in obs])


def test_one_candidate_is_exactly_the_policy(setup: Dict[str, Any], dataset_root: Path) -> None:
    policy, pre, verifier = setup["policy"], setup["pre"], setup["verifier"]
    obs = observations(dataset_root, 0, 20)
    plain = run(policy, pre, obs, seed=7)
    steered = ul.SteeredPolicy(policy, verifier, pre, n=1, policy_name=POLICY, checkpoint=CHECKPOINT)
    same = run(steered, pre, obs, seed=7)
    assert torch.equal(plain, same)
    # Guidance at λ = 0 is the policy's own sampler too.
    zero = ul.SteeredPolicy(policy, verifier, pre, n=1, mode="guidance", lam=0.0, policy_name=POLICY, checkpoint=CHECKPOINT)
    assert torch.equal(plain, run(zero, pre, obs, seed=7))
    pushed = ul.SteeredPolicy(policy, verifier, pre, n=1, mode="guidance", lam=5.0, policy_name=POLICY, checkpoint=CHECKPOINT)
    assert not torch.equal(plain, run(pushed, pre, obs, seed=7))


def independent_rows(setup: Dict[str, Any], obs: List[Dict[str, Any]], t: int) -> np.ndarray:
    """The verifier's row at step t built here: the layer's encoder on the frames (uint8, as the
    store holds them) and the raw states, the last two steps, oldest first."""
    enc = setup["enc"]
    keys = [k["key"] for k in setup["verifier"].config()["input"]["obs_keys"]]
    assert keys == [LAYER, "state"], keys
    parts = []
    for s in (max(t - 1, 0), t):
        frame = np.rint(obs[s][CAMERA][0].permute(1, 2, 0).numpy() * 255).astype(np.uint8)[None]
        parts += [enc(CAMERA, frame)[0], obs[s]["observation.state"][0].numpy()]
    return np.concatenate(parts).astype(np.float32)


def test_best_of_n_executes_the_verifiers_argmax_and_replans_only_when_the_queue_is_empty(
    setup: Dict[str, Any], dataset_root: Path
) -> None:
    policy, pre, verifier = setup["policy"], setup["pre"], setup["verifier"]
    obs = observations(dataset_root, 1, 20)
    n, h = 6, policy.config.n_action_steps
    steered = ul.SteeredPolicy(policy, verifier, pre, n=n, policy_name=POLICY, checkpoint=CHECKPOINT)
    calls = []
    original = policy.diffusion.conditional_sample

    def counting(batch_size: int, **kw: Any) -> Any:
        calls.append(batch_size)
        return original(batch_size, **kw)

    policy.diffusion.conditional_sample = counting
    try:
        torch.manual_seed(3)
        steered.reset()
        executed, plans = [], []
        with torch.inference_mode():
            for t, o in enumerate(obs):
                rng = torch.get_rng_state()
                executed.append(steered.select_action(pre(dict(o)))[0])
                if t % h == 0:
                    plans.append((t, rng, steered.last_plan))
    finally:
        del policy.diffusion.conditional_sample
    # The sampler ran once per re-plan (t = 0, 8, 16), with the batch of N candidates.
    assert calls == [n, n, n] and [p[0] for p in plans] == [0, 8, 16]
    assert len(steered.timings) == 3
    for t, rng, plan in plans:
        assert plan is not None and plan.t == t
        # The same draw, redone here from the policy's own conditioning and sampler.
        torch.set_rng_state(rng)
        hist = {
            "observation.state": torch.cat([pre(dict(obs[s]))["observation.state"] for s in (max(t - 1, 0), t)])[None],
            "observation.images": torch.stack([pre(dict(obs[s]))[CAMERA] for s in (max(t - 1, 0), t)], dim=1)[:, :, None],
        }
        with torch.inference_mode():
            gc = policy.diffusion._prepare_global_conditioning(hist)
            cands = policy.diffusion.conditional_sample(n, global_cond=gc.repeat_interleave(n, 0))[:, 1 : 1 + h]
        assert torch.equal(cands, plan.candidates[0])
        row = independent_rows(setup, obs, t)
        np.testing.assert_allclose(plan.rows[0], row, rtol=1e-4, atol=1e-5)
        scores = verifier.score(row, cands.reshape(n, -1).numpy(), t)
        np.testing.assert_allclose(plan.scores[0], scores, rtol=1e-4, atol=1e-6)
        best = int(np.argmax(scores))
        assert int(plan.chosen[0]) == best
        got = torch.stack(executed[t : t + h])
        assert torch.equal(got, cands[best][: len(got)])


def test_a_verifier_of_another_checkpoint_is_refused(setup: Dict[str, Any], dataset_root: Path) -> None:
    other, pre, _ = make_policy(dataset_root, seed=2)
    with pytest.raises(ValueError, match="producer"):
        ul.SteeredPolicy(other, setup["verifier"], pre, n=4, policy_name=POLICY, checkpoint=CHECKPOINT)
    with pytest.raises(ValueError, match="policy_name"):
        ul.SteeredPolicy(setup["policy"], setup["verifier"], setup["pre"], n=4)


def test_sample_chunks_encodes_once_and_returns_both_action_spaces(setup: Dict[str, Any], dataset_root: Path) -> None:
    policy, pre, post = setup["policy"], setup["pre"], setup["post"]
    obs = observations(dataset_root, 2, 2)
    encoder_calls = []
    hook = policy.diffusion.rgb_encoder.register_forward_hook(lambda m, i, o: encoder_calls.append(i[0].shape[0]))
    try:
        policy.reset()
        chunks = ul.sample_chunks(policy, pre(dict(obs[0])), 16, postprocessor=post)
    finally:
        hook.remove()
    assert encoder_calls == [2]  # one call: the two history frames, not 16 x 2
    assert tuple(chunks.normalized.shape) == (1, 16, 8, 6)
    assert torch.allclose(post(chunks.normalized), chunks.actions)
    scale, offset = ul.action_space(pre)
    raw = chunks.normalized * torch.tensor(scale, dtype=torch.float32) + torch.tensor(offset, dtype=torch.float32)
    assert torch.allclose(raw, chunks.actions, atol=1e-5)
    assert float(chunks.normalized.std(dim=1).mean()) > 0.01  # the sampler's draws differ


class ToyEnv(gym.Env):  # type: ignore[misc]
    """A gymnasium environment with the fixture's observation and action spaces (a 64x64 camera,
    6 joint values, 6-d actions), for LeRobot's evaluation loop: each episode lasts 20 steps and
    succeeds for even seeds."""

    metadata = {"render_fps": 10}

    def __init__(self) -> None:
        self.observation_space = gym.spaces.Dict({
            "pixels": gym.spaces.Dict({"front": gym.spaces.Box(0, 255, (64, 64, 3), np.uint8)}),
            "agent_pos": gym.spaces.Box(-np.inf, np.inf, (6,), np.float32),
        })
        self.action_space = gym.spaces.Box(-np.inf, np.inf, (6,), np.float32)
        self._max_episode_steps = 30
        self.task = self.task_description = "reach"
        self.rng = np.random.default_rng(0)
        self.t = 0
        self.seed_ = 0

    def _obs(self) -> Dict[str, Any]:
        self.frame = self.rng.integers(0, 255, (64, 64, 3), dtype=np.uint8)
        return {"pixels": {"front": self.frame}, "agent_pos": self.rng.normal(size=6).astype(np.float32)}

    def reset(self, *, seed: Any = None, options: Any = None) -> Tuple[Dict[str, Any], Dict[str, Any]]:
        self.seed_ = int(seed) if seed is not None else self.seed_ + 1
        self.rng = np.random.default_rng(self.seed_)
        self.t = 0
        return self._obs(), {"is_success": False}

    def step(self, action: Any) -> Tuple[Dict[str, Any], float, bool, bool, Dict[str, Any]]:
        assert np.asarray(action).shape == (6,)
        self.t += 1
        done = self.t >= 20
        success = done and self.seed_ % 2 == 0
        return self._obs(), float(success), done, False, {"is_success": success}

    def render(self) -> Any:
        return self.frame

    def close(self) -> None:
        pass


def test_steered_policy_runs_in_lerobots_evaluation_loop(setup: Dict[str, Any], tmp_path: Path) -> None:
    """SteeredPolicy in the place of the policy in lerobot-eval's eval_policy, two environments a
    batch: re-plans every n_action_steps, telemetry numbered by lerobot's episode index."""
    from lerobot.processor import PolicyProcessorPipeline
    from lerobot.scripts.lerobot_eval import eval_policy

    policy, pre, post = setup["policy"], setup["pre"], setup["post"]
    log = ufops.SteeringLog()
    steered = ul.SteeredPolicy(policy, setup["verifier"], pre, n=3, policy_name=POLICY, checkpoint=CHECKPOINT, log=log)
    env = gym.vector.SyncVectorEnv([ToyEnv, ToyEnv], autoreset_mode=gym.vector.AutoresetMode.SAME_STEP)
    identity = PolicyProcessorPipeline(steps=[])
    torch.manual_seed(0)
    with torch.no_grad():
        info = eval_policy(env=env, policy=steered, env_preprocessor=identity, env_postprocessor=identity,
                           preprocessor=pre, postprocessor=post, n_episodes=4, start_seed=100)
    assert [e["seed"] for e in info["per_episode"]] == [100, 101, 102, 103]
    assert [e["success"] for e in info["per_episode"]] == [True, False, True, False]
    # 2 batches x 2 rows x re-plans at t = 0, 8, 16 (20 steps each).
    assert len(steered.timings) == 2 * 3 and len(log) == 4 * 3
    path = log.write(tmp_path / "steering.parquet")
    table = pl.read_parquet(path)
    episode_col = next(c for c in table.columns if c.startswith("episode"))
    steps = sorted(zip(table[episode_col].to_list(), table["t"].to_list()))
    assert steps == [(e, t) for e in range(4) for t in (0, 8, 16)]
