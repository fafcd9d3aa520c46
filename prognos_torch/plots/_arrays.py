"""Plot inputs as float64 NumPy arrays."""

from __future__ import annotations

import numpy as np
import torch


def as_numpy(x) -> np.ndarray:
    """``x`` as a float64 array: a tensor on any device is detached and copied to the CPU
    (``np.asarray`` refuses a CUDA tensor), anything else goes through ``np.asarray``."""
    if isinstance(x, torch.Tensor):
        x = x.detach().to("cpu", torch.float64).numpy()
    return np.asarray(x, dtype=np.float64)


def clip_for_drawing(paths: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """``paths`` limited to ``[lo - 10 pad, hi + 10 pad]`` (``pad = 0.15 (hi - lo)``, or 1 when
    ``hi == lo``) for drawing only: an exponential path can reach 1e300 or overflow to inf, and
    such coordinates ruin the axes' scale and make the Agg renderer allocate without bound. The
    result's data are not changed."""
    pad = 0.15 * (hi - lo) if hi > lo else 1.0
    return np.clip(paths, lo - 10.0 * pad, hi + 10.0 * pad)
