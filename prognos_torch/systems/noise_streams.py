"""Per-run random streams of the system simulators.

The caller's ``generator`` is asked for one 62-bit seed per Monte Carlo run (``torch.randint``,
drawn in run order); run ``r`` then draws all of its noise from a private generator seeded with
seed ``r``, in a fixed order (process noise ``(T, n)``, measurement noise ``(T, m)``, then any
system-specific draws). Hence a batch of ``R`` runs equals ``R`` successive single-run calls with
the same generator, and run ``r`` does not depend on ``R``.

The draws are made in float64 on the device of the caller's generator, then cast to the
requested dtype and moved to the requested device (as :mod:`prognos_torch.core.random` draws): a
float32 simulation receives the float64 simulation's noise rounded (``torch.randn`` draws other
numbers in float32 than in float64), and a CPU generator gives the same noise whatever device
the simulation runs on.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor

from ..core.validation import check_count, check_dtype_arg, is_int

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

    Every argument is checked before the first draw: a refused call leaves ``generator`` as it
    was.
    """
    if not isinstance(generator, torch.Generator):
        raise TypeError(f"generator must be a torch.Generator, got {type(generator).__name__}")
    runs = check_count(runs, "runs")
    n_steps = check_count(n_steps, "n_steps", minimum=0)
    check_dtype_arg(dtype)
    specs: list[tuple[str, tuple[int, ...]]] = []
    for entry in draws:
        if not isinstance(entry, (tuple, list)) or len(entry) != 2:
            raise ValueError(f"each entry of draws must be a pair (kind, shape), got {entry!r}")
        kind, shape = entry
        if kind not in ("normal", "uniform"):
            raise ValueError(f"draw kind must be 'normal' or 'uniform', got {kind!r}")
        if not isinstance(shape, (tuple, list)) or not all(is_int(d) and d >= 0 for d in shape):
            raise ValueError(
                f"the shape of a draw must be a tuple of ints >= 0, got {shape!r} for {kind!r}"
            )
        specs.append((kind, tuple(int(d) for d in shape)))
    target = torch.get_default_device() if device is None else torch.device(device)
    where = generator.device
    f64 = torch.float64
    seeds = torch.randint(0, 2**62, (runs,), generator=generator, device=where)
    out: list[list[Tensor]] = [[] for _ in specs]
    for seed in seeds.tolist():
        g = torch.Generator(device=where).manual_seed(seed)
        for j, (kind, shape) in enumerate(specs):
            draw = torch.randn if kind == "normal" else torch.rand
            out[j].append(draw((n_steps, *shape), generator=g, dtype=f64, device=where))
    result = []
    for (kind, _), parts in zip(specs, out):
        z = torch.stack(parts, dim=1).to(dtype=dtype, device=target)
        if kind == "uniform" and dtype != f64:  # rounding may reach 1: keep U[0, 1)
            z = z.clamp_(max=torch.nextafter(z.new_ones(()), z.new_zeros(())))
        result.append(z)
    return result
