"""One-step integrators of ``dx/dt = rhs(x)`` used by the system simulators."""

from __future__ import annotations

from collections.abc import Callable

from torch import Tensor

__all__ = ["rk4_step", "euler_step"]


def rk4_step(rhs: Callable[[Tensor], Tensor], x: Tensor, dt: float) -> Tensor:
    """One classical 4th-order Runge-Kutta step of ``dx/dt = rhs(x)`` (paper 003 ref. [24]).

    Pure and vmap-friendly; ``x`` may carry leading batch dimensions if ``rhs`` broadcasts.
    """
    k1 = rhs(x)
    k2 = rhs(x + (0.5 * dt) * k1)
    k3 = rhs(x + (0.5 * dt) * k2)
    k4 = rhs(x + dt * k3)
    return x + (dt / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)


def euler_step(rhs: Callable[[Tensor], Tensor], x: Tensor, dt: float) -> Tensor:
    """One explicit Euler step ``x + dt * rhs(x)`` (paper 000 Eq. 59, paper 004 Eq. 13)."""
    return x + dt * rhs(x)
