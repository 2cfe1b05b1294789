"""Independent numpy reference of a ufops verifier artifact (trainer/ARTIFACT.md: schema_version 1,
one network; 2, an ensemble).

Written from the contract alone, in float64, so the Rust verifier core can be checked against it:
scores and guidance gradients (d log C / d action for the classifier, d Q / d action for q), and
for an ensemble the members' mean and spread, best-of-N's pick with its fall-back and the
agreement-scaled gradient ("Ensembles"). Depends on numpy and safetensors only.

    v = load_artifact("path/to/artifact_dir")   # checks every sha256, schema, kind, variant, tensors
    v.score(obs, act, t)                         # obs [N, obs_dim] raw, act [N, act_dim] in the
    v.grad(obs, act, t)                          # artifact's action space (input.action_space), t [N]

Command line (what the Rust tests call):

    python3 ufops_reference.py ARTIFACT_DIR ROWS_JSON
    ROWS_JSON: {"rows": [{"obs": [...], "action": [...], "t": 3, "extras": {"name": [...]}}, ...]}
    prints {"artifact_id": ..., "members": K, "scores": [...], "spread": [...], "grads": [[...], ...]}
"""
import hashlib
import json
import math
import os
import sys

import numpy as np
from safetensors.numpy import load_file

SCHEMA_VERSION = 1
ENSEMBLE_SCHEMA_VERSION = 2


class ArtifactError(Exception):
    pass


def _sha256(path):
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def time_embedding(t, d):
    """sin(t / 10000^(j/d)) for even j, cos(t / 10000^((j-1)/d)) for odd j; f64, rounded to f32."""
    t = np.asarray(t, dtype=np.float64).reshape(-1, 1)
    j = np.arange(d)
    arg = t / np.power(10000.0, (j - j % 2) / float(d))[None, :]
    return np.where(j % 2 == 0, np.sin(arg), np.cos(arg)).astype(np.float32).astype(np.float64)


_erf = np.vectorize(math.erf, otypes=[np.float64])


def _act(name, x):
    if name == "relu":
        return np.maximum(x, 0.0)
    return 0.5 * x * (1.0 + _erf(x / math.sqrt(2.0)))


def _act_grad(name, x):
    if name == "relu":
        return (x > 0).astype(np.float64)
    return 0.5 * (1.0 + _erf(x / math.sqrt(2.0))) + x * np.exp(-0.5 * x * x) / math.sqrt(2.0 * math.pi)


def _f64(x, cols):
    return np.asarray(x, dtype=np.float32).astype(np.float64).reshape(-1, cols)


class Verifier:
    def __init__(self, config, tensors, artifact_id):
        self.config = config
        self.id = artifact_id
        self.kind = config["kind"]
        self.arch = config["architecture"]
        inp = config["input"]
        self.obs_dim, self.act_dim = inp["obs_dim"], inp["act_dim"]
        self.action_space = inp.get("action_space", {"space": "standardized"})
        stat = lambda k: np.asarray(inp[k], dtype=np.float32).astype(np.float64)
        self.obs_mean, self.obs_std = stat("obs_mean"), stat("obs_std")
        self.act_mean, self.act_std = stat("act_mean"), stat("act_std")
        self.eps = float(self.arch.get("layernorm_eps", 1e-5))
        self.w = {k: v.astype(np.float64) for k, v in tensors.items()}
        self._check_tensors()

    def _expected_tensors(self):
        a = self.arch
        ew = a["encoder_width"]
        extras = a.get("extra_inputs", [])
        enc_ln = a.get("encoder_layernorm", False)
        want = {}
        if a.get("input_layernorm", False):
            want["obs_in_ln.weight"] = want["obs_in_ln.bias"] = (self.obs_dim,)
        lin = [("obs_enc.0", self.obs_dim, ew, enc_ln), ("obs_enc.1", ew, ew, enc_ln),
               ("act_enc.0", self.act_dim, ew, enc_ln), ("act_enc.1", ew, ew, enc_ln)]
        lin += [("extra." + e["name"], e["dim"], e["width"], False) for e in extras]
        prev = 2 * ew + a["t_embed_dim"] + sum(e["width"] for e in extras)
        for i, d in enumerate(a["trunk_dims"]):
            lin.append((f"trunk.{i}", prev, d, True))
            prev = d
        lin.append(("head", prev, 1, False))
        for name, i, o, ln in lin:
            want[name + ".weight"], want[name + ".bias"] = (o, i), (o,)
            if ln:
                want[name + ".ln.weight"] = want[name + ".ln.bias"] = (o,)
        return want

    def _check_tensors(self):
        want = self._expected_tensors()
        for k, s in want.items():
            if k not in self.w or tuple(self.w[k].shape) != s:
                found = None if k not in self.w else tuple(self.w[k].shape)
                raise ArtifactError(f"tensor {k}: expected shape {s}, found {found}")
        extra = sorted(set(self.w) - set(want))
        if extra:
            raise ArtifactError(f"tensors not in this architecture: {extra}")

    # -- pieces -------------------------------------------------------------------------------
    def _lin(self, x, name):
        return x @ self.w[name + ".weight"].T + self.w[name + ".bias"]

    def _ln(self, x, name):
        mean = x.mean(axis=-1, keepdims=True)
        rstd = 1.0 / np.sqrt(((x - mean) ** 2).mean(axis=-1, keepdims=True) + self.eps)
        xhat = (x - mean) * rstd
        return xhat * self.w[name + ".weight"] + self.w[name + ".bias"], (xhat, rstd)

    def _ln_back(self, dy, cache, name):
        xhat, rstd = cache
        dxh = dy * self.w[name + ".weight"]
        return rstd * (dxh - dxh.mean(-1, keepdims=True) - xhat * (dxh * xhat).mean(-1, keepdims=True))

    def _encoder(self, x, prefix):
        """Returns the output and, per layer, (pre-activation, LayerNorm cache)."""
        a = self.arch
        caches = []
        for i in range(2):
            name = f"{prefix}.{i}"
            h = self._lin(x, name)
            cache = None
            if a.get("encoder_layernorm", False):
                h, cache = self._ln(h, name + ".ln")
            caches.append((h, cache))
            # lowdim: activation after both linears; features: between them only
            x = _act(a["activation"], h) if (a["variant"] == "lowdim" or i == 0) else h
        return x, caches

    def _forward(self, obs, act, t, extras):
        a = self.arch
        o = (_f64(obs, self.obs_dim) - self.obs_mean) / self.obs_std
        x_act = (_f64(act, self.act_dim) - self.act_mean) / self.act_std
        if a.get("input_layernorm", False):
            o, _ = self._ln(o, "obs_in_ln")
        ho, _ = self._encoder(o, "obs_enc")
        ha, act_caches = self._encoder(x_act, "act_enc")
        parts = [ho, ha, time_embedding(t, a["t_embed_dim"])]
        for e in a.get("extra_inputs", []):
            parts.append(np.maximum(self._lin(_f64((extras or {})[e["name"]], e["dim"]), "extra." + e["name"]), 0.0))
        h = np.concatenate(parts, axis=1)
        trunk = []
        for i in range(len(a["trunk_dims"])):
            s, cache = self._ln(self._lin(h, f"trunk.{i}"), f"trunk.{i}.ln")
            trunk.append((s, cache))
            h = np.maximum(s, 0.0)
        return self._lin(h, "head")[:, 0], act_caches, trunk

    # -- API ----------------------------------------------------------------------------------
    members = 1

    def spread(self, obs, act, t, extras=None):
        return np.zeros(np.asarray(t).reshape(-1).shape[0])

    def pick(self, obs_row, cands, t, extras=None):
        """Best-of-N over candidates cands [N, act_dim] at one observation: (index, fell_back)."""
        n = cands.shape[0]
        s = self.score(np.repeat(_f64(obs_row, self.obs_dim), n, axis=0), cands, np.full(n, t), extras)
        return int(_argmax(s)), False

    def score(self, obs, act, t, extras=None):
        """Classifier: sigmoid(logit); q: the value. Shape [N]."""
        y, _, _ = self._forward(obs, act, t, extras)
        return 1.0 / (1.0 + np.exp(-y)) if self.kind == "classifier" else y

    def grad(self, obs, act, t, extras=None):
        """d log sigmoid(y) / d act (classifier) or d y / d act (q), by hand-written backprop."""
        a = self.arch
        y, act_caches, trunk = self._forward(obs, act, t, extras)
        gy = 1.0 / (1.0 + np.exp(y)) if self.kind == "classifier" else np.ones_like(y)
        d = gy[:, None] * self.w["head.weight"][0][None, :]
        for i in reversed(range(len(trunk))):
            s, cache = trunk[i]
            du = self._ln_back(d * (s > 0), cache, f"trunk.{i}.ln")
            d = du @ self.w[f"trunk.{i}.weight"]
        ew = a["encoder_width"]
        g = d[:, ew:2 * ew]
        for i in reversed(range(2)):
            pre, cache = act_caches[i]
            if a["variant"] == "lowdim" or i == 0:
                g = g * _act_grad(a["activation"], pre)
            if cache is not None:
                g = self._ln_back(g, cache, f"act_enc.{i}.ln")
            g = g @ self.w[f"act_enc.{i}.weight"]
        return g / self.act_std


def _argmax(x):
    """First index of the largest value; NaN counts as -inf."""
    x = np.where(np.isnan(x), -np.inf, x)
    return int(np.argmax(x))


class Ensemble:
    """K member networks; the rules of trainer/ARTIFACT.md, "Ensembles"."""

    def __init__(self, config, tensors, artifact_id):
        spec = config.get("ensemble")
        if not isinstance(spec, dict):
            raise ArtifactError("schema_version 2 without an ensemble object")
        known = {"members", "pessimism", "min_agreement", "min_gradient_agreement"}
        if set(spec) != known:
            raise ArtifactError(f"ensemble has fields {sorted(spec)}, expected {sorted(known)}")
        k = spec["members"]
        if not (isinstance(k, int) and 2 <= k <= 64):
            raise ArtifactError(f"ensemble.members {k!r} is not in 2..=64")
        self.config, self.id, self.spec, self.members = config, artifact_id, spec, k
        self.kind = config["kind"]
        self.arch = config["architecture"]
        prefixes = [f"members.{i}." for i in range(k)]
        stray = [n for n in tensors if not any(n.startswith(p) for p in prefixes)]
        if stray:
            raise ArtifactError(f"tensors outside the members: {sorted(stray)}")
        self.nets = [Verifier(config, {n[len(p):]: v for n, v in tensors.items() if n.startswith(p)}, artifact_id)
                     for p in prefixes]
        self.obs_dim, self.act_dim = self.nets[0].obs_dim, self.nets[0].act_dim

    def member_scores(self, obs, act, t, extras=None):
        """[K, N]"""
        return np.stack([m.score(obs, act, t, extras) for m in self.nets])

    def score(self, obs, act, t, extras=None):
        return self.member_scores(obs, act, t, extras).mean(axis=0)

    def spread(self, obs, act, t, extras=None):
        return self.member_scores(obs, act, t, extras).std(axis=0)

    def pick(self, obs_row, cands, t, extras=None):
        n = cands.shape[0]
        s = self.member_scores(np.repeat(_f64(obs_row, self.obs_dim), n, axis=0), cands, np.full(n, t), extras)
        best = _argmax(s.mean(axis=0) - self.spec["pessimism"] * s.std(axis=0))
        if best == 0:
            return 0, False
        agreement = float((s[:, best] > s[:, 0]).mean())
        if agreement < self.spec["min_agreement"]:
            return 0, True
        return best, False

    def grad(self, obs, act, t, extras=None):
        g = np.stack([m.grad(obs, act, t, extras) for m in self.nets])  # [K, N, act_dim]
        mean = g.mean(axis=0)
        mean_norm = np.linalg.norm(g, axis=2).mean(axis=0)
        r = np.where(mean_norm > 0, np.linalg.norm(mean, axis=1) / np.where(mean_norm > 0, mean_norm, 1.0), 0.0)
        r0 = self.spec["min_gradient_agreement"]
        scale = np.clip((np.minimum(r, 1.0) - r0) / (1.0 - r0), 0.0, 1.0)
        return mean * scale[:, None]


def load_artifact(directory):
    """Load an artifact directory, checking every file against manifest.json first."""
    with open(os.path.join(directory, "manifest.json"), "rb") as f:
        manifest_bytes = f.read()
    manifest = json.loads(manifest_bytes)
    if manifest.get("schema_version") not in (SCHEMA_VERSION, ENSEMBLE_SCHEMA_VERSION):
        raise ArtifactError(f"unknown schema_version {manifest.get('schema_version')}")
    files = manifest.get("files", {})
    for name in ("config.json", "model.safetensors"):
        if name not in files:
            raise ArtifactError(f"manifest lists no {name}")
    for name, want in files.items():
        if os.path.basename(name) != name or name in (".", ".."):
            raise ArtifactError(f"file name {name!r} is not a plain file name")
        got = _sha256(os.path.join(directory, name))
        if got != want:
            raise ArtifactError(f"sha256 mismatch for {name}: manifest {want}, file {got}")
    with open(os.path.join(directory, "config.json")) as f:
        config = json.load(f)
    if config.get("schema_version") != manifest["schema_version"]:
        raise ArtifactError(f"config schema_version {config.get('schema_version')} is not the manifest's")
    if (config["schema_version"] == ENSEMBLE_SCHEMA_VERSION) != ("ensemble" in config):
        raise ArtifactError("an ensemble block goes with schema_version 2, and only with it")
    arch = config.get("architecture", {})
    for field, known in (("variant", ("lowdim", "features")), ("activation", ("relu", "gelu"))):
        if arch.get(field) not in known:
            raise ArtifactError(f"unknown architecture.{field} {arch.get(field)!r}")
    if config.get("kind") not in ("classifier", "q"):
        raise ArtifactError(f"unknown kind {config.get('kind')!r}")
    if arch["t_embed_dim"] % 2:
        raise ArtifactError("t_embed_dim must be even")
    tensors = load_file(os.path.join(directory, "model.safetensors"))
    artifact_id = hashlib.sha256(manifest_bytes).hexdigest()[:16]
    if config["schema_version"] == ENSEMBLE_SCHEMA_VERSION:
        return Ensemble(config, tensors, artifact_id)
    return Verifier(config, tensors, artifact_id)


def main(argv):
    if len(argv) != 3:
        print(__doc__, file=sys.stderr)
        return 2
    v = load_artifact(argv[1])
    with open(argv[2]) as f:
        rows = json.load(f)["rows"]
    obs = np.array([r["obs"] for r in rows])
    act = np.array([r["action"] for r in rows])
    t = np.array([r["t"] for r in rows])
    extras = {e["name"]: np.array([r["extras"][e["name"]] for r in rows]) for e in v.arch.get("extra_inputs", [])}
    out = {"artifact_id": v.id, "members": v.members, "scores": v.score(obs, act, t, extras).tolist(),
           "spread": v.spread(obs, act, t, extras).tolist(), "grads": v.grad(obs, act, t, extras).tolist()}
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
