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
