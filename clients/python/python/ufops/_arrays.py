"""Conversion of array-likes for the native module (its slow path: numpy arrays go straight in).

torch tensors are detached and shared with numpy on the CPU (``Tensor.numpy()`` copies nothing);
tensors on another device are copied to the CPU; other DLPack producers go through
``numpy.from_dlpack``; lists and scalars become ``dtype``.
"""
from __future__ import annotations

from typing import Any

import numpy as np


def as_numpy(x: Any, dtype: str) -> np.ndarray[Any, Any]:
    if isinstance(x, np.ndarray):
        return x
    if type(x).__module__.startswith("torch"):
        t = x.detach()
        if t.device.type != "cpu":
            t = t.cpu()
        return t.numpy()  # type: ignore[no-any-return]
    if hasattr(x, "__dlpack__"):
        return np.from_dlpack(x)
    return np.asarray(x, dtype=dtype)
