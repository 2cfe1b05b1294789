"""Ensemble verifiers (trainer/ARTIFACT.md, "Ensembles"): a trained ensemble scores the same in
the Rust core (`ufops score`), Python and the independent numpy reference — scores, spreads,
agreement-scaled gradients and best-of-N's picks with their fall-backs — and a client that cannot
read it whole refuses it."""
from __future__ import annotations

import importlib.util
import json
import subprocess
import sys
from pathlib import Path
from typing import Any, List

import numpy as np
import pytest

import ufops
from ufops import _ufops
from conftest import REPO, Ufops, require_torch, rows

REFERENCE = REPO / "clients" / "python" / "reference" / "ufops_reference.py"


def reference() -> Any:
    spec = importlib.util.spec_from_file_location("ufops_reference", REFERENCE)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def close(got: Any, want: Any, tol: float = 1e-5) -> None:
    got, want = np.asarray(got, dtype=np.float64), np.asarray(want, dtype=np.float64)
    assert got.shape == want.shape
    err = np.abs(got - want) / np.maximum(1.0, np.abs(want))
    assert err.max() <= tol, f"max relative error {err.max()}"


@pytest.fixture(scope="module")
def ensembles(tmp_path_factory: pytest.TempPathFactory) -> Ufops:
    """A store of its own (the session's store keeps exactly its two verifiers) with the same
    synthetic rollouts and `ufops train --ensemble 3` on their split."""
    u = Ufops(tmp_path_factory.mktemp("ensemble-store"))
    u.run("init")
    u.run("dev", "synth", "--episodes", "40", "--steps", "30", "--seed", "5")
    split = u.json("split", "create", "--policy", "synth", "--checkpoint", "ckpt-0", "--json")["id"]
    recipe = u.data_dir / "ensemble.json"
    recipe.write_text(json.dumps({"epochs": 3}))
    u.run("train", "--split", split, "--kind", "classifier", "--chunk-len", "16", "--config", str(recipe),
          "--ensemble", "3", "--action-scale", "0.5", "2.0", "--action-offset", "0.1", "0")
    return u


@pytest.fixture(scope="module")
def ensemble_dir(ensembles: Ufops, tmp_path_factory: pytest.TempPathFactory) -> Path:
    d = tmp_path_factory.mktemp("ensemble") / "artifact"
    ensembles.run("artifacts", "download", "synth/ckpt-0/classifier@latest", str(d))
    return d


def test_a_trained_ensemble_scores_alike_in_rust_python_and_numpy(
    ensembles: Ufops, ensemble_dir: Path, tmp_path: Path
) -> None:
    v = ufops.Verifier.load(ensemble_dir)
    cfg = v.config()
    assert v.members == 3 and cfg["schema_version"] == 2
    assert v.ensemble == {"members": 3, "pessimism": 1.0, "min_agreement": 0.8, "min_gradient_agreement": 0.5}
    e = cfg["metrics"]["ensemble"]
    assert e["members"] == 3 and e["seeds"] == [0, 1, 2] and len(e["member_val_auc"]) == 3
    assert all(0 < d <= e["train_episodes"] for d in e["distinct_episodes"])
    rng = np.random.default_rng(7)
    obs = rng.normal(size=(24, v.obs_dim)).astype(np.float32)
    act = rng.normal(scale=0.7, size=(24, v.act_dim)).astype(np.float32)
    t = rng.integers(0, 30, size=24).astype(np.int64)
    scores, grads = v.score(obs, act, t), v.grad(obs, act, t)
    members = v.score_members(obs, act, t)
    assert members.shape == (3, 24)
    close(scores, members.mean(axis=0), tol=1e-6)
    assert members.std(axis=0).max() > 0, "members trained on different resamples disagree somewhere"

    rows_file = tmp_path / "rows.json"
    rows_file.write_text(json.dumps(rows(obs, act, t)))
    cli = ensembles.json("score", "--artifact", str(ensemble_dir), "--input", str(rows_file), "--grad")
    assert cli["artifact"] == v.id and cli["members"] == 3
    close(scores, cli["scores"])
    close(grads, cli["grads"])
    close(members.std(axis=0), cli["spread"])

    out = subprocess.run([sys.executable, str(REFERENCE), str(ensemble_dir), str(rows_file)],
                         capture_output=True, text=True, check=True)
    ref = json.loads(out.stdout)
    assert ref["members"] == 3 and ref["artifact_id"] == v.id
    close(scores, ref["scores"])
    close(members.std(axis=0), ref["spread"], tol=1e-5)
    close(grads, ref["grads"], tol=1e-4)

    # Best-of-N's pick with its fall-back, group by group, against the reference's rule.
    r = reference().load_artifact(str(ensemble_dir))
    cands = rng.normal(scale=0.7, size=(40, 30, v.act_dim)).astype(np.float32)
    group_obs = rng.normal(size=(40, v.obs_dim)).astype(np.float32)
    steps = np.arange(40, dtype=np.int64)
    p = v.pick(group_obs, cands, steps)
    assert p.chosen.shape == (40,) and p.scores.shape == (40, 30) and p.fell_back.dtype == np.bool_
    for g in range(40):
        assert (int(p.chosen[g]), bool(p.fell_back[g])) == r.pick(group_obs[g], cands[g], int(steps[g])), g
    print(f"trained 3-member ensemble: {int(p.fell_back.sum())} of 40 random groups fell back")


def test_best_of_n_and_the_lerobot_picks_use_the_ensemble_rule(ensemble_dir: Path) -> None:
    torch = require_torch()
    from ufops.torch import best_of_n

    v = ufops.Verifier.load(ensemble_dir)
    rng = np.random.default_rng(3)
    obs = rng.normal(size=(8, v.obs_dim)).astype(np.float32)
    cands = torch.from_numpy(rng.normal(scale=0.7, size=(8, 30, v.act_dim)).astype(np.float32))
    picks: List[ufops.Pick] = []
    best, scores = best_of_n(v, lambda n: cands, obs, 30, t=np.arange(8), picks=picks)
    want = v.pick(obs, cands.numpy(), np.arange(8))
    np.testing.assert_array_equal(scores.numpy(), want.scores)
    np.testing.assert_array_equal(best.numpy(), cands.numpy()[np.arange(8), want.chosen])
    assert len(picks) == 1 and (picks[0].fell_back == want.fell_back).all()
    # Where the members disagree the policy's own first candidate is what runs.
    for g in np.flatnonzero(want.fell_back):
        np.testing.assert_array_equal(best.numpy()[g], cands.numpy()[g, 0])


def test_random_ensembles_of_every_shape_match_the_reference(tmp_path: Path) -> None:
    ref = reference()
    for dims, seed in (("nav", 1), ("nav_features", 2), ("square", 3)):
        d = tmp_path / dims
        _ufops.write_random_artifact(str(d), dims, seed, None, 4)
        v = ufops.Verifier.load(d)
        r = ref.load_artifact(str(d))
        assert v.members == r.members == 4
        rng = np.random.default_rng(seed)
        obs = rng.normal(size=(10, v.obs_dim)).astype(np.float32)
        act = rng.normal(size=(10, v.act_dim)).astype(np.float32)
        t = rng.integers(0, 50, size=10)
        close(v.score(obs, act, t), r.score(obs, act, t))
        close(v.grad(obs, act, t), r.grad(obs, act, t), tol=1e-4)
        cands = rng.normal(size=(12, v.act_dim)).astype(np.float32)
        p = v.pick(obs[0], cands, int(t[0]))
        assert (int(p.chosen[0]), bool(p.fell_back[0])) == r.pick(obs[0], cands, int(t[0]))


def test_a_client_that_cannot_read_an_ensemble_whole_refuses_it(ensemble_dir: Path, copy_dir: Any) -> None:
    # A member's tensors missing (the manifest rewritten to match): refused, not scored with the rest.
    d = copy_dir(ensemble_dir)
    cfg = json.loads((d / "config.json").read_text())
    cfg["ensemble"]["members"] = 4
    (d / "config.json").write_text(json.dumps(cfg))
    import hashlib

    m = json.loads((d / "manifest.json").read_text())
    m["files"]["config.json"] = hashlib.sha256((d / "config.json").read_bytes()).hexdigest()
    (d / "manifest.json").write_text(json.dumps(m))
    with pytest.raises(ufops.ArtifactError, match="members.3"):
        ufops.Verifier.load(d)
    ref = reference()
    with pytest.raises(ref.ArtifactError, match="obs_enc"):
        ref.load_artifact(str(d))
    # A schema this client does not know.
    m["schema_version"] = 3
    (d / "manifest.json").write_text(json.dumps(m))
    with pytest.raises(ufops.ArtifactError, match="schema_version 3"):
        ufops.Verifier.load(d)
