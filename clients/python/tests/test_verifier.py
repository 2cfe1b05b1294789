"""ufops.Verifier against the Rust clients on artifacts the trainer wrote: scores and gradients
equal `ufops score --grad` (the binary, through the same core) and the independent numpy
reference to 1e-5; loading from a directory, the store and `ufops serve` give the same
verifier; bad artifacts, tokens, aliases and arrays raise exceptions naming the problem."""
from __future__ import annotations

import json
import subprocess
import sys
import threading
import warnings
from pathlib import Path
from typing import Any, Dict

import numpy as np
import pytest

import ufops
from ufops import _ufops
from conftest import REPO, Server, Ufops, require_torch, rows

KINDS = ("classifier", "q")


def close(got: Any, want: Any, tol: float = 1e-5) -> None:
    got, want = np.asarray(got, dtype=np.float64), np.asarray(want, dtype=np.float64)
    assert got.shape == want.shape
    err = np.abs(got - want) / np.maximum(1.0, np.abs(want))
    assert err.max() <= tol, f"max relative error {err.max()} at {np.unravel_index(err.argmax(), err.shape)}"


def inputs(v: ufops.Verifier, n: int, seed: int) -> Any:
    rng = np.random.default_rng(seed)
    obs = rng.normal(size=(n, v.obs_dim)).astype(np.float32)
    act = rng.normal(scale=0.7, size=(n, v.act_dim)).astype(np.float32)
    t = rng.integers(0, 30, size=n).astype(np.int64)
    return obs, act, t


@pytest.mark.parametrize("kind", KINDS)
def test_scores_and_grads_equal_the_rust_cli_and_the_numpy_reference(
    kind: str, trained: Ufops, artifact_dirs: Dict[str, Path], tmp_path: Path
) -> None:
    v = ufops.Verifier.load(artifact_dirs[kind])
    cfg = json.loads(v.config_json())
    if kind == "classifier":
        assert cfg["architecture"]["variant"] == "lowdim" and v.takes_policy_space
    else:
        a = cfg["architecture"]
        assert a["variant"] == "features" and a["spectral_norm"] and a["activation"] == "gelu"
    obs, act, t = inputs(v, 24, seed=1)
    scores = v.score(obs, act, t)
    grads = v.grad(obs, act, t)
    assert scores.shape == (24,) and grads.shape == (24, v.act_dim)
    assert scores.dtype == np.float32 and np.abs(grads).max() > 1e-4

    rows_file = tmp_path / "rows.json"
    rows_file.write_text(json.dumps(rows(obs, act, t)))
    cli = trained.json("score", "--artifact", f"synth/ckpt-0/{kind}@latest", "--input", str(rows_file), "--grad")
    assert cli["artifact"] == v.id
    close(scores, cli["scores"])
    close(grads, cli["grads"])

    # The independent float64 numpy reference (clients/python/reference).
    ref_path = REPO / "clients" / "python" / "reference" / "ufops_reference.py"
    out = subprocess.run([sys.executable, str(ref_path), str(artifact_dirs[kind]), str(rows_file)],
                         capture_output=True, text=True, check=True)
    ref = json.loads(out.stdout)
    close(scores, ref["scores"])
    close(grads, ref["grads"], tol=1e-4)

    # Batched groups of candidates equal the same rows scored one by one.
    groups = v.score(obs[:4], act[:20].reshape(4, 5, v.act_dim), t[:4])
    for b in range(4):
        close(groups[b], v.score(np.repeat(obs[b:b + 1], 5, 0), act[b * 5:(b + 1) * 5], np.full(5, t[b])))
    single = v.score(obs[0], act[:5], int(t[0]))
    close(single, groups[0])
    # A chunk may be given as (chunk_len, action_dim).
    chunked = act[:3].reshape(3, v.chunk_len, v.action_dim)
    close(v.grad(obs[:3], chunked, t[:3]).reshape(3, -1), grads[:3])


@pytest.mark.parametrize("kind", KINDS)
def test_store_and_server_load_the_same_verifier(
    kind: str, trained: Ufops, artifact_dirs: Dict[str, Path], server: Server
) -> None:
    ref = f"synth/ckpt-0/{kind}@latest"
    local = ufops.Verifier.load(artifact_dirs[kind])
    from_store = ufops.Verifier.from_store(str(trained.data_dir), ref)
    store = ufops.Store(trained.data_dir)
    also_store = ufops.Verifier.from_store(store, ref)
    remote = ufops.Verifier.from_server(server.url, ref, server.token)
    by_id = ufops.Verifier.from_server(server.url, str(local.id), server.token)
    assert local.id == from_store.id == also_store.id == remote.id == by_id.id
    obs, act, t = inputs(local, 8, seed=2)
    want = local.score(obs, act, t)
    for v in (from_store, also_store, remote, by_id):
        np.testing.assert_array_equal(v.score(obs, act, t), want)
        np.testing.assert_array_equal(v.grad(obs, act, t), local.grad(obs, act, t))


def test_torch_tensors_are_accepted(artifact_dirs: Dict[str, Path]) -> None:
    torch = require_torch()
    v = ufops.Verifier.load(artifact_dirs["classifier"])
    obs, act, t = inputs(v, 6, seed=3)
    want_s, want_g = v.score(obs, act, t), v.grad(obs, act, t)
    x = torch.from_numpy(act).requires_grad_(True)
    np.testing.assert_array_equal(v.score(torch.from_numpy(obs), x, torch.from_numpy(t)), want_s)
    np.testing.assert_array_equal(v.grad(torch.from_numpy(obs), x, torch.from_numpy(t)), want_g)
    # Strided views are copied, not misread.
    wide = np.zeros((6, 2 * v.act_dim), np.float32)
    wide[:, ::2] = act
    np.testing.assert_array_equal(v.score(obs, wide[:, ::2], t), want_s)


def test_the_gil_is_released_while_scoring(artifact_dirs: Dict[str, Path]) -> None:
    v = ufops.Verifier.load(artifact_dirs["q"])
    obs, act, t = inputs(v, 2048, seed=4)
    want = v.score(obs, act, t)
    results: list[Any] = []
    threads = [threading.Thread(target=lambda: results.append(v.score(obs, act, t))) for _ in range(4)]
    for th in threads:
        th.start()
    for th in threads:
        th.join()
    assert len(results) == 4
    for r in results:
        np.testing.assert_array_equal(r, want)


def test_a_tampered_artifact_is_refused(artifact_dirs: Dict[str, Path], copy_dir: Any) -> None:
    d = copy_dir(artifact_dirs["classifier"])
    model = d / "model.safetensors"
    data = bytearray(model.read_bytes())
    data[-1] ^= 0x01
    model.write_bytes(bytes(data))
    with pytest.raises(ufops.IntegrityError, match="sha256 mismatch for model.safetensors"):
        ufops.Verifier.load(d)
    with pytest.raises(ufops.NotFoundError, match="manifest.json"):
        ufops.Verifier.load(d / "nowhere")
    (d / "config.json").write_text("{")
    with pytest.raises(ufops.ArtifactError):
        ufops.Verifier.load(d)


def test_wrong_token_and_unknown_alias_are_exceptions(server: Server, trained: Ufops) -> None:
    with pytest.raises(ufops.AuthError, match="401"):
        ufops.Verifier.from_server(server.url, "synth/ckpt-0/classifier@latest", "not-a-token")
    with pytest.raises(ufops.NotFoundError, match="404"):
        ufops.Verifier.from_server(server.url, "synth/ckpt-0/classifier@nope", server.token)
    with pytest.raises(ValueError, match="POLICY/CHECKPOINT/KIND@ALIAS"):
        ufops.Verifier.from_server(server.url, "../etc/passwd", server.token)
    with pytest.raises(ufops.FetchError, match="127.0.0.1:9"):
        ufops.Verifier.from_server("http://127.0.0.1:9", "synth/ckpt-0/classifier@latest", "t", timeout=2)
    with pytest.raises(ufops.NotFoundError):
        ufops.Verifier.from_store(str(trained.data_dir), "synth/ckpt-0/classifier@nope")


def test_wrong_shapes_and_dtypes_name_the_expected_shape(artifact_dirs: Dict[str, Path]) -> None:
    v = ufops.Verifier.load(artifact_dirs["classifier"])
    od, ad = v.obs_dim, v.act_dim
    obs, act, t = inputs(v, 4, seed=5)
    with pytest.raises(TypeError, match=rf"obs must be a float32 array of shape \({od},\) or \(B, {od}\); got dtype float64"):
        v.score(obs.astype(np.float64), act, t)
    with pytest.raises(TypeError, match="act must be a float32 array"):
        v.grad(obs, act.astype(np.float16), t)
    with pytest.raises(ValueError, match=rf"obs must have shape \({od},\) or \(B, {od}\); got \(4, {od + 1}\)"):
        v.score(np.zeros((4, od + 1), np.float32), act, t)
    with pytest.raises(ValueError, match=rf"act must have shape .*\(4, N, {ad}\).*got \(4, {ad - 1}\)"):
        v.score(obs, act[:, :-1], t)
    with pytest.raises(ValueError, match=rf"act must have shape .*got \(3, {ad}\)"):
        v.grad(obs, act[:3], t)
    with pytest.raises(ValueError, match=r"t must be an int or an integer array of shape \(4,\); got shape \(3,\)"):
        v.score(obs, act, t[:3])
    with pytest.raises(TypeError, match="t must be an int or an integer array"):
        v.score(obs, act, t.astype(np.float32))
    with pytest.raises(ValueError, match="non-negative"):
        v.score(obs, act, -1)
    with pytest.raises(ValueError, match="no extra input"):
        v.score(obs, act, t, extras={"bogus": obs})
    # The interpreter is alive and the verifier still works.
    assert v.score(obs, act, t).shape == (4,)


def test_python_lists_and_empty_batches(artifact_dirs: Dict[str, Path]) -> None:
    v = ufops.Verifier.load(artifact_dirs["classifier"])
    obs, act, t = inputs(v, 2, seed=6)
    close(v.score(obs.tolist(), act.tolist(), t.tolist()), v.score(obs, act, t))
    assert v.score(np.zeros((0, v.obs_dim), np.float32), np.zeros((0, v.act_dim), np.float32), 0).shape == (0,)


def _figure(action_auc: float) -> Dict[str, Any]:
    """An action-sensitivity figure as the trainer records it (`flagged` by its rule: < 0.5)."""
    flagged = action_auc < 0.5
    return {"obs_only_auc": 0.9, "auc_gain": 0.004, "action_auc": action_auc, "strata": 10,
            "unsure_fraction": 0.2, "unsure_auc": None, "unsure_obs_only_auc": None, "flagged": flagged,
            "reason": "ranks action chunks at 0.41 AUROC among held-out samples its observation-only twin "
                      "scores alike" if flagged else None, "twin_seconds": 1.0}


def test_a_flagged_verifier_warns_when_loaded_and_an_unflagged_one_does_not(tmp_path: Path) -> None:
    for action_auc, warns in ((0.41, True), (0.55, False)):
        d = tmp_path / str(action_auc)
        metrics = {"final": {"val_auc": 0.93, "action_sensitivity": _figure(action_auc)}}
        art = _ufops.write_random_artifact(d, "nav", 3, json.dumps(metrics))
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            v = ufops.Verifier.load(d)
        steering = [w for w in caught if issubclass(w.category, ufops.SteeringWarning)]
        assert len(steering) == int(warns), [str(w.message) for w in caught]
        assert v.action_sensitivity == metrics["final"]["action_sensitivity"]
        if warns:
            assert v.steering_warning is not None and str(steering[0].message) == v.steering_warning
            assert v.steering_warning.startswith(f"verifier {art}: ranks action chunks at 0.41 AUROC")
        else:
            assert v.steering_warning is None


def test_trained_verifiers_record_the_figure_and_warn_exactly_when_flagged(
    artifact_dirs: Dict[str, Path],
) -> None:
    for kind, d in artifact_dirs.items():
        figure = json.loads((d / "config.json").read_text())["metrics"]["final"]["action_sensitivity"]
        assert 0.0 <= figure["obs_only_auc"] <= 1.0, (kind, figure)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            v = ufops.Verifier.load(d)
        steering = [w for w in caught if issubclass(w.category, ufops.SteeringWarning)]
        assert len(steering) == int(figure["flagged"]), (kind, figure)
        # The same figure (config.json is read back through the core: floats to the last digit or so).
        got = v.action_sensitivity
        assert got is not None and got.keys() == figure.keys()
        for k, want in figure.items():
            if isinstance(want, float):
                assert got[k] == pytest.approx(want, rel=1e-12), k
            else:
                assert got[k] == want, k
