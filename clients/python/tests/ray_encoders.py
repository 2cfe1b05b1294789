"""Encoders of the Ray tests, in a module of their own: Ray pickles them by value to its workers
(which cannot import the tests' directory), so they reference nothing from the tests."""
from __future__ import annotations

import contextlib
import time
from typing import Any, Iterator

import torch


def tiny_cnn(seed: int = 0) -> Any:
    """A stand-in for a policy's vision encoder: random, seeded, 12-d (test_features.py's)."""
    torch.manual_seed(seed)
    return torch.nn.Sequential(
        torch.nn.Conv2d(3, 8, 3, stride=2),
        torch.nn.BatchNorm2d(8),
        torch.nn.ReLU(),
        torch.nn.Conv2d(8, 16, 3, stride=2),
        torch.nn.ReLU(),
        torch.nn.AdaptiveAvgPool2d(1),
        torch.nn.Flatten(),
        torch.nn.Linear(16, 12),
    ).eval()


class Slow(torch.nn.Module):  # type: ignore[misc]
    """`inner`, `seconds` slower a batch: a run long enough to be stopped in the middle."""

    def __init__(self, inner: Any, seconds: float) -> None:
        super().__init__()
        self.inner = inner
        self.seconds = seconds

    def forward(self, x: Any) -> Any:
        time.sleep(self.seconds)
        return self.inner(x)


@contextlib.contextmanager
def torch_threads(n: int) -> Iterator[None]:
    """torch's intra-op threads set to `n` (as in the Ray actors), restored after."""
    before = torch.get_num_threads()
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(before)
