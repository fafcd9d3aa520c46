"""Lorenz system and the Lorenz(x) series of paper 003 Sec. V-A.

Paper 003 Eq. 47, state ``[x, y, z]``::

    dx/dt = -a (x - y),   dy/dt = b x - y - x z,   dz/dt = x y - c z,   a = 10, b = 28, c = 8/3

(the classical sigma, rho, beta). The paper does not state the integrator, step, initial
condition or transient; our documented choices: classical RK4 with ``dt = 0.01``, one sample
per step (sampling interval 0.01), initial condition ``[1, 1, 1]``, the first 1000 steps
(10 time units) discarded as transient. :func:`lorenz_series` returns the raw x component
(1000 points by default; the paper trains on the first 500 and tests on the last 500); the
scaling to ``[0, 1]`` is a separate step (:func:`prognos_torch.datasets.minmax_normalize`).

As a state-space model: ``x_k = RK4(x_{k-1}) + w_k``, ``y_k = x-component + v_k``.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from ..core.model import StateSpaceModel
from ..core.validation import (
    check_count,
    check_dtype_arg,
    check_flag,
    check_params_finite,
    check_positive,
    check_std,
    diag_chol,
)
from .integrators import rk4_step
from .noise_streams import draw_run_noise
from .simulation import (
    SimulationResult,
    check_state,
    initial_state,
    plain_params,
    resolve_generator,
    resolve_params,
    simulate_model,
)

__all__ = [
    "LorenzParams",
    "lorenz_rhs",
    "lorenz_step",
    "lorenz_model",
    "simulate_lorenz",
    "lorenz_series",
]

LORENZ_X0 = (1.0, 1.0, 1.0)
LORENZ_TRANSIENT = 1000


@dataclass(frozen=True)
class LorenzParams:
    """Paper 003 Eq. 47 coefficients and the integration step.

    Attributes:
        a: ``10`` (sigma). b: ``28`` (rho). c: ``8/3`` (beta).
        dt: RK4 step and sampling interval (our choice, ``0.01``).
        substeps: RK4 steps per sample (``1``: sample every integration step).
    """

    a: float = 10.0
    b: float = 28.0
    c: float = 8.0 / 3.0
    dt: float = 0.01
    substeps: int = 1

    def __post_init__(self):
        plain_params(self, scalars=True)  # NumPy values stored as Python numbers
        check_params_finite(self)
        check_positive(self, "dt")
        check_count(self.substeps, "LorenzParams.substeps")


def lorenz_rhs(x: Tensor, params: LorenzParams) -> Tensor:
    """Paper 003 Eq. 47: ``(..., 3) -> (..., 3)``."""
    p = params
    check_state(x, 3, "[x, y, z]")
    X, Y, Z = x[..., 0], x[..., 1], x[..., 2]
    return torch.stack([-p.a * (X - Y), p.b * X - Y - X * Z, X * Y - p.c * Z], dim=-1)


def lorenz_step(x: Tensor, params: LorenzParams) -> Tensor:
    """One sample: ``params.substeps`` RK4 steps of ``dt / substeps``: ``(..., 3) -> (..., 3)``."""
    h = params.dt / params.substeps
    for _ in range(params.substeps):
        x = rk4_step(lambda z: lorenz_rhs(z, params), x, h)
    return x


def lorenz_model(
    params: LorenzParams | None = None,
    *,
    process_noise_std=0.0,
    measurement_noise_std=0.0,
    dtype=torch.float64,
    device=None,
) -> StateSpaceModel:
    """Lorenz as a :class:`StateSpaceModel`: ``f = lorenz_step``, ``h(x) = x[..., :1]``.

    Noise stds: ``process_noise_std`` per state component (number or 3 numbers),
    ``measurement_noise_std`` for the x component. Defaults zero (the paper's series is
    noise-free); a filter on this model should pass positive values.
    """
    p = resolve_params(params, LorenzParams)
    check_dtype_arg(dtype)  # (an integer dtype truncated chol_Q = 0.5 I to 0)
    SQ = diag_chol(check_std(process_noise_std, 3, "process_noise_std"), dtype, device)
    SR = diag_chol(check_std(measurement_noise_std, 1, "measurement_noise_std"), dtype, device)
    return StateSpaceModel(
        f=lambda x, u, k: lorenz_step(x, p),
        h=lambda x, u, k: x[..., :1].clone(),
        state_dim=3,
        obs_dim=1,
        chol_Q=SQ,
        chol_R=SR,
        batched=True,
    )


def simulate_lorenz(
    n_steps: int,
    runs: int = 1,
    *,
    params: LorenzParams | None = None,
    x0=LORENZ_X0,
    n_transient: int = 0,
    noise: bool = True,
    process_noise_std=0.0,
    measurement_noise_std=0.0,
    generator: torch.Generator | None = None,
    dtype=torch.float64,
    device=None,
) -> SimulationResult:
    """Simulate ``runs`` Lorenz trajectories.

    Args:
        n_steps: ``T`` samples after the transient.
        x0: ``(3,)`` or ``(runs, 3)`` state at time 0 (before the transient).
        n_transient: noise-free steps run first and discarded; ``x[0]`` of the result is the
            state after them, and ``t`` restarts at 0 there.
        noise: ``False`` switches all noise off (no generator needed).
    Returns:
        :class:`SimulationResult`: ``x`` ``(T+1, runs, 3)``, ``y`` ``(T, runs, 1)`` (x component),
        ``theta`` ``(T+1, runs, 0)``.
    """
    p = resolve_params(params, LorenzParams)
    check_count(n_steps, "n_steps")
    check_count(runs, "runs")
    n_transient = check_count(n_transient, "n_transient", 0)
    check_dtype_arg(dtype)
    noise = check_flag(noise, "noise")
    gen = resolve_generator(generator, noise)
    X0 = initial_state(x0, 3, runs, dtype, device)
    model = lorenz_model(
        p,
        process_noise_std=process_noise_std,
        measurement_noise_std=measurement_noise_std,
        dtype=dtype,
        device=device,
    )
    for k in range(1, n_transient + 1):
        X0 = model.transition(X0, None, k)
    e_w = e_v = None
    if gen is not None:
        e_w, e_v = draw_run_noise(
            gen, runs, n_steps, [("normal", (3,)), ("normal", (1,))], dtype=dtype, device=device
        )
    x, y = simulate_model(model, X0, n_steps, e_w=e_w, e_v=e_v)
    return SimulationResult(
        t=torch.arange(n_steps + 1, dtype=dtype, device=device) * p.dt,
        x=x,
        y=y,
        theta=x.new_zeros(n_steps + 1, runs, 0),
        u=None,
        meta={
            "system": "lorenz",
            "paper": "003",
            "equations": "Eq. 47 (RK4)",
            "dt": p.dt,
            "substeps": p.substeps,
            "n_transient": n_transient,
            "time_unit": "1",
            "state_names": ("x", "y", "z"),
            "measurement_names": ("x",),
            "param_names": (),
            "noise": noise,
        },
    )


def lorenz_series(
    n_points: int = 1000,
    *,
    params: LorenzParams | None = None,
    x0=LORENZ_X0,
    n_transient: int = LORENZ_TRANSIENT,
    dtype=torch.float64,
    device=None,
) -> Tensor:
    """The raw Lorenz(x) series of paper 003 Sec. V-A: ``(n_points,)``, not normalised.

    Samples ``x(t_j)``, ``t_j = (n_transient + j) dt`` for ``j = 0..n_points-1``, of the noise-free
    RK4 solution from ``x0`` (defaults: ``dt = 0.01``, ``x0 = [1, 1, 1]``, 1000 transient steps).
    Paper 003 uses 1000 points, the first 500 for training, and scales all 1000 to ``[0, 1]``
    with :func:`prognos_torch.datasets.minmax_normalize` before forecasting.
    """
    check_count(n_points, "n_points")
    sim = simulate_lorenz(
        n_points,  # one extra step so that n_points = 1 works; x[0] is the first sample
        1,
        params=params,
        x0=x0,
        n_transient=n_transient,
        noise=False,
        dtype=dtype,
        device=device,
    )
    return sim.x[:n_points, 0, 0].clone()
