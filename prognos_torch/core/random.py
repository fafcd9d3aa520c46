"""Draws from an explicit ``torch.Generator``, onto the device that uses them."""

from __future__ import annotations

import torch
from torch import Tensor


def standard_normal(
    shape: tuple[int, ...],
    generator: torch.Generator | None,
    dtype: torch.dtype,
    device: torch.device | str,
) -> Tensor:
    """Standard normal draws of ``shape`` on ``device``.

    They are drawn on the generator's own device and then moved, so a CPU generator gives the
    same draws whatever device the computation runs on, and a CUDA generator draws on its GPU
    (``torch.randn`` refuses a generator of another device). ``generator=None`` draws from the
    global stream of ``device``.
    """
    where = device if generator is None else generator.device
    return torch.randn(shape, generator=generator, dtype=dtype, device=where).to(device)
