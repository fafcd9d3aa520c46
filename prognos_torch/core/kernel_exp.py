"""``exp`` of log-kernel values with a floor: Gaussian kernels far from their centres.

A Gaussian kernel ``exp(-d^2 / (2 sigma^2))`` (the LS-SVR's RBF kernel, paper 002 Eq. 7/24;
the ELM's Gaussian activation) evaluated far from its centres has arguments of -10^3 to -10^5.
There ``exp`` underflows to a subnormal number or to 0, and torch's vectorised CPU ``exp`` takes
a slow path: on x86 it runs 5 to 15 times slower below about -708 than above. Inside a
particle filter whose paths wander away from the training windows, that slow path was most of
the run time.

:func:`floored_exp` evaluates ``exp(max(z, EXP_FLOOR))``: every kernel value below
``exp(EXP_FLOOR)`` ~ 1e-304 becomes 1e-304. A sum of ``M`` such terms with weights ``alpha``
moves by at most ``M max|alpha| 1e-304``, below one ulp of any result larger than about 1e-280;
the gradient of a floored value is 0 instead of a number below 1e-300.
"""

from __future__ import annotations

from torch import Tensor

__all__ = ["EXP_FLOOR", "floored_exp"]

#: the floor of the argument: ``exp(-700) = 9.86e-305``, a normal float64 (subnormals start
#: below ``exp(-708.4)``), and fast on the CPU.
EXP_FLOOR = -700.0


def floored_exp(z: Tensor, *, out_of_place: bool | None = None) -> Tensor:
    """``exp(max(z, EXP_FLOOR))`` elementwise, any shape, dtype and device.

    Args:
        z: the exponent (a log-kernel value), ``(...)``.
        out_of_place: ``False`` writes the result into ``z`` (for a fresh temporary, saving
            an allocation as large as ``z``); ``None`` (default) does so only when autograd
            is off; ``True`` never does.
    Returns:
        ``(...)``, ``z``'s shape; ``z`` itself when written in place.
    """
    if out_of_place is None:
        out_of_place = z.requires_grad
    if out_of_place:
        return z.clamp_min(EXP_FLOOR).exp()
    return z.clamp_min_(EXP_FLOOR).exp_()
