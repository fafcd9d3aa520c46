"""Per-run random streams of the system simulators.

The caller's ``generator`` is asked for one 62-bit seed per Monte Carlo run (``torch.randint``,
drawn in run order); run ``r`` then draws all of its noise from a private generator seeded with
seed ``r``, in a fixed order (process noise ``(T, n)``, measurement noise ``(T, m)``, then any
system-specific draws). Hence a batch of ``R`` runs equals ``R`` successive single-run calls with
the same generator, and run ``r`` does not depend on ``R``.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor

__all__ = ["draw_run_noise"]


def draw_run_noise(
    generator: torch.Generator,
    runs: int,
    n_steps: int,
    draws: Sequence[tuple[str, tuple[int, ...]]],
    *,
    dtype=torch.float64,
    device=None,
) -> list[Tensor]:
    """Standard random draws for ``runs`` Monte Carlo runs (see the module docstring).

    Args:
        generator: the caller's generator; one seed per run is drawn from it.
        draws: ``[(kind, shape), ...]`` with ``kind`` ``"normal"`` (N(0, 1)) or ``"uniform"``
            (U[0, 1)); each run draws ``(n_steps, *shape)`` for each entry, in this order.
    Returns:
        One tensor ``(n_steps, runs, *shape)`` per entry of ``draws``.
    """
    seeds = torch.randint(0, 2**62, (runs,), generator=generator, device=generator.device)
    out: list[list[Tensor]] = [[] for _ in draws]
    for seed in seeds.tolist():
        g = torch.Generator(device=device if device is not None else "cpu").manual_seed(seed)
        for j, (kind, shape) in enumerate(draws):
            size = (n_steps, *shape)
            if kind == "normal":
                out[j].append(torch.randn(size, generator=g, dtype=dtype, device=device))
            elif kind == "uniform":
                out[j].append(torch.rand(size, generator=g, dtype=dtype, device=device))
            else:
                raise ValueError(f"draw kind must be 'normal' or 'uniform', got {kind!r}")
    return [torch.stack(parts, dim=1) for parts in out]
