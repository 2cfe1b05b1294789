"""Reads a ufops robomimic export with h5py, following robomimic's documented layout
(https://robomimic.github.io/docs/datasets/overview.html), and compares it with the source file
it was ingested from: states bit for bit (float64), obs / next_obs / actions / rewards as the
store keeps them (float32), dones, demo attributes (model_file), env_args, and the masks of the
split given on the command line.

usage: check_robomimic_export.py EXPORT.hdf5 SOURCE.hdf5 EXPECTED.json
EXPECTED.json: {"labels": {"demo_0": true|false|null}, "masks": {"train": [...], "valid": [...]}}
"""
import json
import sys

import h5py
import numpy as np

exp_path, src_path, expected_path = sys.argv[1:4]
expected = json.load(open(expected_path))
ex = h5py.File(exp_path, "r")
src = h5py.File(src_path, "r")

data = ex["data"]
env_args = json.loads(data.attrs["env_args"])
assert env_args == json.loads(src["data"].attrs["env_args"]), "env_args"
provenance = json.loads(data.attrs["ufops"])
assert provenance["format"] == "robomimic" and provenance["store_version"] >= 1, provenance
demos = sorted(data.keys(), key=lambda d: int(d.split("_")[1]))
assert demos == sorted(src["data"].keys(), key=lambda d: int(d.split("_")[1])), demos
total = 0
for d in demos:
    e, s = data[d], src["data"][d]
    n = e["actions"].shape[0]
    total += n
    assert int(e.attrs["num_samples"]) == n == s["actions"].shape[0], d
    # states: float64, as the simulator wrote them.
    assert e["states"].dtype == np.float64 and np.array_equal(e["states"][()], s["states"][()]), d
    assert np.array_equal(e["actions"][()], s["actions"][()].astype(np.float32)), d
    assert np.array_equal(e["rewards"][()], s["rewards"][()].astype(np.float32).astype(np.float64)), d
    assert np.array_equal(e["dones"][()].astype(bool), s["dones"][()].astype(bool)), d
    assert sorted(e["obs"].keys()) == sorted(s["obs"].keys()), d
    assert sorted(e["next_obs"].keys()) == sorted(s["next_obs"].keys()), d
    for group in ("obs", "next_obs"):
        for k in s[group]:
            a, b = e[group][k][()], s[group][k][()]
            want = b if b.dtype == np.uint8 else b.astype(np.float32).astype(b.dtype)
            assert a.dtype == b.dtype and a.shape == want.shape and np.array_equal(a, want), (d, group, k)
    assert e.attrs["model_file"] == s.attrs["model_file"], d
    label = expected["labels"][d]
    if label is None:
        assert "success" not in e.attrs, d
    else:
        assert bool(e.attrs["success"]) == label, d
assert int(data.attrs["total"]) == total
masks = {k: sorted(v.decode() if isinstance(v, bytes) else v for v in ex["mask"][k][()]) for k in ex.get("mask", {})}
assert masks == {k: sorted(v) for k, v in expected["masks"].items()}, (masks, expected["masks"])
print(f"h5py: {len(demos)} demos, {total} steps, masks {sorted(masks)}: states, obs, next_obs, actions, rewards, dones, model_file as in the source")
