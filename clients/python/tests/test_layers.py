"""Layers through the Python package: ``Store.write_layer`` writes an encoder's per-step features
as a new version (idempotent per producer), ``Store.steps(..., layers=[...])`` reads them joined
(and not in the version before), the CLI trains a verifier on them, and ``ufops.Verifier``
refuses features of another producer."""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Dict

import numpy as np
import pytest

import ufops
from conftest import FEATURES_CONFIG, Ufops, require

pl = require("polars")

LAYER = "features.proj"
PRODUCER: Dict[str, Any] = {"encoder": "proj", "policy": "synth", "checkpoint": "ckpt-0", "content_hash": "v1"}


def project(obs: np.ndarray) -> np.ndarray:
    """A stand-in for a policy's encoder: a fixed nonlinear projection of each step's observation."""
    w = np.cos(np.arange(obs.shape[1] * 6, dtype=np.float32).reshape(obs.shape[1], 6))
    return np.tanh(obs @ w).astype(np.float32)


@pytest.fixture(scope="module")
def layered(tmp_path_factory: pytest.TempPathFactory) -> Ufops:
    u = Ufops(tmp_path_factory.mktemp("layers"))
    u.run("init")
    u.run("dev", "synth", "--episodes", "40", "--steps", "30", "--seed", "5")
    return u


def obs_of(steps: Any) -> np.ndarray:
    key = next(c for c in steps.columns if c.startswith("obs."))
    return np.asarray(steps[key].to_list(), dtype=np.float32)


def test_write_read_train_and_refuse(layered: Ufops, tmp_path: Path) -> None:
    s = ufops.Store(layered.data_dir)
    before = s.head_version()
    ids = s.episodes()["id"].to_list()
    values = {i: project(obs_of(s.steps(i))) for i in ids}

    # Half, then all: the second call writes only the rest (a resumed computation).
    first = s.write_layer(LAYER, PRODUCER, {i: values[i] for i in ids[:20]})
    assert (first["episodes_written"], first["episodes_skipped"]) == (20, 0)
    assert first["producer_hash"] == s.producer_hash(dict(reversed(list(PRODUCER.items()))))
    rest = s.write_layer(LAYER, PRODUCER, values)
    assert (rest["episodes_written"], rest["episodes_skipped"]) == (20, 20)
    again = s.write_layer(LAYER, PRODUCER, values)
    assert again["version"] is None and again["episodes_written"] == 0
    assert s.head_version() == rest["version"]
    assert sorted(s.layer_episodes(LAYER, first["producer_hash"])) == sorted(ids)
    layers = s.layers()
    assert layers.height == 1 and layers["episodes"][0] == 40 and layers["dim"][0] == 6

    # Joined reads equal what was written; the version before has no layer.
    steps = s.steps(ids[:3], layers=[LAYER])
    got = np.asarray(steps[f"obs.{LAYER}"].to_list(), dtype=np.float32)
    np.testing.assert_array_equal(got, np.concatenate([values[i] for i in ids[:3]]))
    with pytest.raises(ufops.NotFoundError, match="layer not found"):
        s.steps(ids[0], before, layers=[LAYER])
    assert s.episode_layers(ids[0], before) == []
    assert [layer["layer"] for layer in s.episode_layers(ids[0])] == [LAYER]

    # Bad input is refused and writes nothing.
    head = s.head_version()
    with pytest.raises(ValueError, match="steps"):
        s.write_layer(LAYER, {"content_hash": "other"}, {ids[0]: values[ids[0]][:5]})
    with pytest.raises(ValueError, match="shape"):
        s.write_layer(LAYER, PRODUCER, {ids[0]: values[ids[0]].ravel()})
    assert s.head_version() == head

    # A verifier trained on the layer records its producer and refuses any other.
    split = layered.json("split", "create", "--policy", "synth", "--checkpoint", "ckpt-0", "--json")["id"]
    config = tmp_path / "features.json"
    config.write_text(json.dumps(FEATURES_CONFIG))
    art = layered.json(
        "train", "--split", split, "--kind", "classifier", "--chunk-len", "16", "--config", str(config), "--obs-keys", LAYER,
        "--json"
    )
    v = ufops.Verifier.from_store(s, art["id"])
    assert v.required_producers == {LAYER: first["producer_hash"]}
    v.check_producers({LAYER: first["producer_hash"]})
    with pytest.raises(ValueError, match="trained on features of producer"):
        v.check_producers({LAYER: "0" * 64})
    with pytest.raises(ValueError, match="say which producer"):
        v.check_producers({})
    lineage = json.loads(v.config_json())
    assert any(k.get("producer") == first["producer_hash"] for k in lineage["input"]["obs_keys"])


def test_camera_observation_encodes_once_and_refuses_another_encoder(layered: Ufops, tmp_path: Path) -> None:
    """ufops.torch.CameraObservation: the encoder runs once per control step, the row stacks the
    verifier's history as the trainer did, and a verifier of another producer is refused."""
    import ufops.torch as ut

    s = ufops.Store(layered.data_dir)
    ids = s.episodes()["id"].to_list()
    if not s.layers().height:
        s.write_layer(LAYER, PRODUCER, {i: project(obs_of(s.steps(i))) for i in ids})
    split = layered.json("split", "create", "--policy", "synth", "--checkpoint", "ckpt-0", "--seed", "3", "--json")["id"]
    config = tmp_path / "features.json"
    config.write_text(json.dumps({**FEATURES_CONFIG, "obs_history": 2}))
    art = layered.json(
        "train", "--split", split, "--kind", "classifier", "--chunk-len", "16", "--config", str(config), "--obs-keys", LAYER,
        "--json"
    )
    v = ufops.Verifier.from_store(s, art["id"])
    right = s.producer_hash(PRODUCER)
    calls: list[int] = []

    def encode(frames: np.ndarray) -> np.ndarray:
        calls.append(len(frames))
        return project(frames.reshape(len(frames), -1).astype(np.float32))

    with pytest.raises(ValueError, match="trained on features of producer"):
        ut.CameraObservation(v, {LAYER: (encode, "f" * 64)})
    cam = ut.CameraObservation(v, {LAYER: (encode, right)})
    steps = s.steps(ids[0])
    obs = obs_of(steps)
    frames = obs.reshape(len(obs), 1, 1, -1)  # a one-pixel "camera" whose pixel is the state
    rows = [cam.observe({LAYER: frames[t]}) for t in range(3)]
    assert calls == [1, 1, 1], "one encoder call per control step"
    feats = project(obs[:3])
    np.testing.assert_allclose(rows[0], np.concatenate([feats[0], feats[0]]), rtol=1e-6)
    np.testing.assert_allclose(rows[2], np.concatenate([feats[1], feats[2]]), rtol=1e-6)
    assert rows[0].shape == (v.obs_dim,)
    # The same rows the trainer built from the stored layer score the same.
    chunks = np.zeros((5, v.act_dim), dtype=np.float32)
    scores = v.score(rows[2], chunks, 2)
    assert scores.shape == (5,) and np.all(np.isfinite(scores))
    cam.reset()
    np.testing.assert_allclose(cam.observe({LAYER: frames[2]}), np.concatenate([feats[2], feats[2]]), rtol=1e-6)
