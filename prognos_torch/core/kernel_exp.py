"""``exp`` of log-kernel values with a floor: Gaussian kernels far from their centres.

A Gaussian kernel ``exp(-d^2 / (2 sigma^2))`` (the LS-SVR's RBF kernel, paper 002 Eq. 7/24;
the ELM's Gaussian activation) evaluated far from its centres, on a path that has left the
training range, has arguments of -10^3 to -10^5. There ``exp`` underflows to a subnormal number
or to 0, and torch's vectorised CPU ``exp`` takes a slow path: on x86 it runs 5 to 15 times
slower below about -708 in float64 (below about -87 in float32) than above
(``benchmarks/bench_kernel_exp.py``: an LS-SVR evaluated 100 sigma beyond its training range
runs 4.5-4.8x faster floored).

:func:`floored_exp` evaluates ``exp(max(z, floor))`` with the floor of ``z``'s dtype in
:data:`EXP_FLOORS`, the log of a normal number just above the smallest: every kernel value
below ``exp(floor)`` (9.9e-305 in float64, 1.6e-38 in float32) becomes ``exp(floor)``. A sum
of ``M`` such terms with weights ``alpha`` moves by at most ``M max|alpha| exp(floor)``, below
one ulp of any result larger than about 1e-280 (float64) or 1e-30 (float32); the gradient of a
floored value is 0 instead of a number below ``exp(floor)``. Dtypes without a floor (float16,
whose smallest normal number is 6e-5) get plain ``exp``.
"""

from __future__ import annotations

import torch
from torch import Tensor

from .validation import check_flag

__all__ = ["EXP_FLOORS", "floored_exp"]

#: the floor of the argument by dtype: ``exp(-700) = 9.86e-305`` (float64 subnormals start
#: below ``exp(-708.4)``), ``exp(-87) = 1.65e-38`` (float32 and bfloat16: below
#: ``exp(-87.3)``); both fast on the CPU.
EXP_FLOORS: dict[torch.dtype, float] = {
    torch.float64: -700.0,
    torch.float32: -87.0,
    torch.bfloat16: -87.0,
}


def floored_exp(z: Tensor, *, out_of_place: bool | None = None) -> Tensor:
    """``exp(max(z, EXP_FLOORS[z.dtype]))`` elementwise, any shape and device (plain ``exp``
    for a dtype without a floor).

    Args:
        z: the exponent (a log-kernel value), ``(...)``.
        out_of_place: ``False`` writes the result into ``z`` (for a fresh temporary, saving
            an allocation as large as ``z``); ``None`` (default) does so only when ``z`` does
            not require grad and is floating (``exp`` of an integer tensor is a new float
            tensor); ``True`` never does.
    Returns:
        ``(...)``, ``z``'s shape; ``z`` itself when written in place.
    """
    if not isinstance(z, Tensor):
        raise TypeError(f"z must be a torch.Tensor, got {type(z).__name__}")
    inexact = z.is_floating_point() or z.is_complex()
    if out_of_place is None:
        out_of_place = z.requires_grad or not inexact
    else:
        out_of_place = check_flag(out_of_place, "out_of_place")
        if not out_of_place and not inexact:
            raise TypeError(f"out_of_place=False needs a floating z to write into, got {z.dtype}")
    floor = EXP_FLOORS.get(z.dtype)
    if out_of_place:
        return z.exp() if floor is None else z.clamp_min(floor).exp()
    # clamp_min_ (not clamp_): it has a vmap batching rule
    return z.exp_() if floor is None else z.clamp_min_(floor).exp_()
