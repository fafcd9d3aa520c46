"""One-step integrators of ``dx/dt = rhs(x)`` used by the system simulators."""

from __future__ import annotations

from collections.abc import Callable

from torch import Tensor

from ..core.validation import check_positive_real

__all__ = ["rk4_step", "euler_step"]


def _check_step(x, dt) -> None:
    """``x`` a floating-point tensor and ``dt`` a finite positive real (NumPy scalars too)."""
    if not isinstance(x, Tensor) or not x.is_floating_point():
        got = x.dtype if isinstance(x, Tensor) else type(x).__name__
        raise TypeError(f"x must be a floating-point tensor (..., n), got {got}")
    check_positive_real(dt, "dt")


def _rate(rhs: Callable[[Tensor], Tensor], x: Tensor) -> Tensor:
    """``rhs(x)``, refused unless it has ``x``'s shape (a broadcast rate would silently give the
    step another shape than ``x``)."""
    k = rhs(x)
    if not isinstance(k, Tensor) or k.shape != x.shape:
        got = tuple(k.shape) if isinstance(k, Tensor) else type(k).__name__
        raise ValueError(f"rhs(x) must have x's shape {tuple(x.shape)}, got {got}")
    return k


def rk4_step(rhs: Callable[[Tensor], Tensor], x: Tensor, dt: float) -> Tensor:
    """One classical 4th-order Runge-Kutta step of ``dx/dt = rhs(x)`` (paper 003 ref. [24]).

    Pure and vmap-friendly; ``x`` may carry leading batch dimensions if ``rhs`` broadcasts.
    ``rhs(x)`` must have ``x``'s shape; ``dt`` is a finite positive number.
    """
    _check_step(x, dt)
    k1 = _rate(rhs, x)
    k2 = rhs(x + (0.5 * dt) * k1)
    k3 = rhs(x + (0.5 * dt) * k2)
    k4 = rhs(x + dt * k3)
    return x + (dt / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)


def euler_step(rhs: Callable[[Tensor], Tensor], x: Tensor, dt: float) -> Tensor:
    """One explicit Euler step ``x + dt * rhs(x)`` (paper 000 Eq. 59, paper 004 Eq. 13).

    ``rhs(x)`` must have ``x``'s shape; ``dt`` is a finite positive number.
    """
    _check_step(x, dt)
    return x + dt * _rate(rhs, x)
