"""ufops.torch: best-of-N keeps the best-scored candidate, and the DDPM / flow guidance hooks move
x̂0 by exactly λ·∇ (the verifier core's gradient), as steer's samplers do."""
from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

import ufops
import ufops.torch as ut
from ufops import _ufops

from conftest import require_torch


@pytest.fixture(scope="module")
def nav(tmp_path_factory: pytest.TempPathFactory) -> ufops.Verifier:
    d = tmp_path_factory.mktemp("nav")
    _ufops.write_random_artifact(d, "nav", 3)
    return ufops.Verifier.load(d)


def test_best_of_n_keeps_the_best(nav: ufops.Verifier) -> None:
    torch = require_torch()
    g = torch.Generator().manual_seed(0)
    obs = torch.randn(nav.obs_dim, generator=g)
    cands = torch.randn(12, nav.chunk_len, nav.action_dim, generator=g)
    best, scores = ut.best_of_n(nav, lambda n: cands[:n], obs, 12, t=3)
    want = nav.score(obs.numpy(), cands.numpy(), 3)
    np.testing.assert_array_equal(scores.numpy(), want)
    assert torch.equal(best, cands[int(want.argmax())])
    # Batched rows: one best per row.
    obs_b = torch.randn(3, nav.obs_dim, generator=g)
    cands_b = torch.randn(3, 5, nav.act_dim, generator=g)
    best_b, scores_b = ut.best_of_n(nav, lambda n: cands_b, obs_b, 5, t=torch.tensor([0, 1, 2]))
    idx = scores_b.argmax(dim=1)
    assert scores_b.shape == (3, 5)
    for b in range(3):
        assert torch.equal(best_b[b], cands_b[b, idx[b]])
    with pytest.raises(ValueError, match="n must be at least 1"):
        ut.best_of_n(nav, lambda n: cands, obs, 0)


def test_ddpm_hook_moves_x0_by_lambda_grad(nav: ufops.Verifier) -> None:
    torch = require_torch()
    g = torch.Generator().manual_seed(1)
    ab = torch.linspace(0.99, 0.05, 20)
    obs = torch.randn(4, nav.obs_dim, generator=g)
    x = torch.randn(4, nav.chunk_len, nav.action_dim, generator=g)
    eps = torch.randn(4, nav.chunk_len, nav.action_dim, generator=g)
    k, lam = 7, 2.5
    hook = ut.ddpm_guidance(nav, obs, ab, lam=lam, t=5)
    eps2 = hook(eps, k, x)
    a = ab[k].double()
    x0 = (x.double() - (1 - a).sqrt() * eps.double()) / a.sqrt()
    x0_guided = (x.double() - (1 - a).sqrt() * eps2.double()) / a.sqrt()
    grad = torch.from_numpy(nav.grad(obs.numpy(), x0.float().numpy(), 5)).double()
    torch.testing.assert_close(x0_guided - x0, lam * grad, atol=1e-4, rtol=1e-4)
    assert torch.equal(ut.ddpm_guidance(nav, obs, ab, lam=0.0)(eps, k, x), eps)


def test_flow_hook_moves_x0_by_lambda_grad(nav: ufops.Verifier) -> None:
    torch = require_torch()
    g = torch.Generator().manual_seed(2)
    obs = torch.randn(2, nav.obs_dim, generator=g)
    x = torch.randn(2, nav.act_dim, generator=g)
    v = torch.randn(2, nav.act_dim, generator=g)
    hook = ut.flow_guidance(nav, obs, lam=0.7)
    s = 0.4
    v2 = hook(v, s, x)
    grad = torch.from_numpy(nav.grad(obs.numpy(), (x - s * v).numpy(), 0))
    torch.testing.assert_close((x - s * v2) - (x - s * v), 0.7 * grad, atol=1e-5, rtol=1e-4)
    assert torch.equal(hook(v, 1.0, x), v), "no guidance at t = 1 (x̂0 is noise there)"


def test_helpers_take_numpy_too(nav: ufops.Verifier) -> Any:
    torch = require_torch()
    obs = np.zeros(nav.obs_dim, np.float32)
    chunk = torch.zeros(nav.act_dim)
    g = ut.guidance_gradient(nav, obs, chunk, 0)
    assert isinstance(g, torch.Tensor) and g.shape == chunk.shape and g.dtype == chunk.dtype
