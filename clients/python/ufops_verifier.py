"""Reference numpy implementation of a ufops verifier artifact (schema_version 1, see
trainer/ARTIFACT.md). Depends on numpy and safetensors only.

    v = load_artifact("path/to/artifact_dir")   # checks sha256s, schema version and variant
    scores = v.score(obs, act, t)                # raw (un-normalised) inputs, shapes [N, obs_dim], [N, act_dim], [N]

The forward pass is rebuilt from config.json alone; computation is in float64.
"""
import hashlib
import json
import math
import os

import numpy as np
from safetensors.numpy import load_file

SCHEMA_VERSION = 1
KNOWN_VARIANTS = ("lowdim", "features")


class ArtifactError(Exception):
    pass


def _sha256(path):
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def time_embedding(t, d):
    """Sinusoidal step embedding: sin(t/10000^(j/d)) for even j, cos(t/10000^((j-1)/d)) for odd j.
    Computed in float64 and rounded to float32 (as the Rust trainer does)."""
    t = np.asarray(t, dtype=np.float64).reshape(-1, 1)
    j = np.arange(d)
    expo = (j - (j % 2)) / float(d)
    arg = t / np.power(10000.0, expo)[None, :]
    e = np.where(j[None, :] % 2 == 0, np.sin(arg), np.cos(arg))
    return e.astype(np.float32).astype(np.float64)


_erf = np.vectorize(math.erf, otypes=[np.float64])


def gelu(x):
    return 0.5 * x * (1.0 + _erf(x / math.sqrt(2.0)))


def relu(x):
    return np.maximum(x, 0.0)


class Verifier:
    def __init__(self, directory, config, tensors, artifact_id):
        self.directory = directory
        self.config = config
        self.id = artifact_id
        self.w = {k: v.astype(np.float64) for k, v in tensors.items()}
        arch = config["architecture"]
        inp = config["input"]
        self.kind = config["kind"]
        self.arch = arch
        self.obs_dim = inp["obs_dim"]
        self.act_dim = inp["act_dim"]
        self.obs_mean = np.asarray(inp["obs_mean"], dtype=np.float32).astype(np.float64)
        self.obs_std = np.asarray(inp["obs_std"], dtype=np.float32).astype(np.float64)
        self.act_mean = np.asarray(inp["act_mean"], dtype=np.float32).astype(np.float64)
        self.act_std = np.asarray(inp["act_std"], dtype=np.float32).astype(np.float64)
        self.eps = float(arch["layernorm_eps"])
        self._check_shapes()

    def _check_shapes(self):
        a, w = self.arch, self.w
        ew = a["encoder_width"]
        trunk_in = 2 * ew + a["t_embed_dim"] + sum(e["width"] for e in a.get("extra_inputs", []))
        want = {
            "obs_enc.0.weight": (ew, self.obs_dim), "obs_enc.1.weight": (ew, ew),
            "act_enc.0.weight": (ew, self.act_dim), "act_enc.1.weight": (ew, ew),
            "trunk.0.weight": (a["trunk_dims"][0], trunk_in),
            "head.weight": (1, a["trunk_dims"][-1]),
        }
        for k, s in want.items():
            if k not in w or tuple(w[k].shape) != s:
                raise ArtifactError(f"tensor {k}: expected shape {s}, found {None if k not in w else w[k].shape}")

    def _lin(self, x, name):
        return x @ self.w[name + ".weight"].T + self.w[name + ".bias"]

    def _ln(self, x, name):
        mean = x.mean(axis=-1, keepdims=True)
        var = ((x - mean) ** 2).mean(axis=-1, keepdims=True)
        return (x - mean) / np.sqrt(var + self.eps) * self.w[name + ".weight"] + self.w[name + ".bias"]

    def _encoder(self, x, prefix):
        if self.arch["variant"] == "lowdim":
            return relu(self._lin(relu(self._lin(x, prefix + ".0")), prefix + ".1"))
        act = gelu if self.arch["activation"] == "gelu" else relu
        h = self._lin(x, prefix + ".0")
        if self.arch["encoder_layernorm"]:
            h = self._ln(h, prefix + ".0.ln")
        h = self._lin(act(h), prefix + ".1")
        if self.arch["encoder_layernorm"]:
            h = self._ln(h, prefix + ".1.ln")
        return h

    def head_output(self, obs, act, t, extras=None):
        """Logit (classifier) or value (q) for raw inputs obs [N, obs_dim], act [N, act_dim], t [N]."""
        obs = np.asarray(obs, dtype=np.float32).astype(np.float64).reshape(-1, self.obs_dim)
        act = np.asarray(act, dtype=np.float32).astype(np.float64).reshape(-1, self.act_dim)
        o = (obs - self.obs_mean) / self.obs_std
        a = (act - self.act_mean) / self.act_std
        if self.arch["input_layernorm"]:
            o = self._ln(o, "obs_in_ln")
        parts = [self._encoder(o, "obs_enc"), self._encoder(a, "act_enc"),
                 time_embedding(t, self.arch["t_embed_dim"])]
        for e in self.arch.get("extra_inputs", []):
            x = np.asarray((extras or {})[e["name"]], dtype=np.float32).astype(np.float64).reshape(-1, e["dim"])
            parts.append(relu(self._lin(x, "extra." + e["name"])))
        h = np.concatenate(parts, axis=1)
        for i in range(len(self.arch["trunk_dims"])):
            h = relu(self._ln(self._lin(h, f"trunk.{i}"), f"trunk.{i}.ln"))
        return self._lin(h, "head")[:, 0]

    def score(self, obs, act, t, extras=None):
        y = self.head_output(obs, act, t, extras)
        if self.kind == "classifier":
            return 1.0 / (1.0 + np.exp(-y))
        return y


def load_artifact(directory):
    """Load and verify an artifact directory (manifest sha256s, schema version, variant)."""
    mpath = os.path.join(directory, "manifest.json")
    with open(mpath, "rb") as f:
        manifest_bytes = f.read()
    manifest = json.loads(manifest_bytes)
    if manifest.get("schema_version") != SCHEMA_VERSION:
        raise ArtifactError(f"unknown schema_version {manifest.get('schema_version')}")
    for name in ("config.json", "model.safetensors"):
        want = manifest.get("files", {}).get(name)
        if want is None:
            raise ArtifactError(f"manifest lists no {name}")
        got = _sha256(os.path.join(directory, name))
        if got != want:
            raise ArtifactError(f"sha256 mismatch for {name}: manifest {want}, file {got}")
    with open(os.path.join(directory, "config.json")) as f:
        config = json.load(f)
    if config.get("schema_version") != SCHEMA_VERSION:
        raise ArtifactError(f"unknown config schema_version {config.get('schema_version')}")
    variant = config.get("architecture", {}).get("variant")
    if variant not in KNOWN_VARIANTS:
        raise ArtifactError(f"unknown architecture variant {variant!r}")
    if config.get("kind") not in ("classifier", "q"):
        raise ArtifactError(f"unknown kind {config.get('kind')!r}")
    tensors = load_file(os.path.join(directory, "model.safetensors"))
    artifact_id = hashlib.sha256(manifest_bytes).hexdigest()[:16]
    return Verifier(directory, config, tensors, artifact_id)
