"""What the prognosis code may ask of any learner: its input/output sizes, dtype and device."""

from __future__ import annotations

import torch
from torch import nn

from ..core.validation import is_int

__all__ = ["learner_dims", "learner_dtype_device"]


def learner_dims(learner) -> tuple[int | None, int | None]:
    """Input/output sizes of a learner when it says them (ELM, LSSVR, ANFIS, nn.Linear)."""
    n_in = n_out = None
    for attr in ("n_in", "n_inputs", "in_features"):
        v = getattr(learner, attr, None)
        if is_int(v):
            n_in = int(v)
            break
    for attr in ("n_out", "out_features"):
        v = getattr(learner, attr, None)
        if is_int(v):
            n_out = int(v)
            break
    return n_in, n_out


def learner_dtype_device(learner) -> tuple[torch.dtype, torch.device]:
    """dtype and device of a learner's first parameter (or buffer); float64 on CPU otherwise."""
    if isinstance(learner, nn.Module):
        for t in list(learner.parameters()) + list(learner.buffers()):
            if t.is_floating_point():
                return t.dtype, t.device
    return torch.float64, torch.device("cpu")
