"""Three-tank system DTS200 with a drifting outflow coefficient ``az2`` (paper 000 Sec. 6).

Model (paper 000 Eq. 57-58), state ``x = [h1, h2, h3]`` (m), input ``u = [Q1, Q2]`` (m^3/s)::

    A_s dh1/dt = Q1 - Q13
    A_s dh2/dt = Q2 + Q32 - Q20
    A_s dh3/dt = Q13 - Q32
    Q13 = az1 S_n sgn(h1 - h3) sqrt(2 g |h1 - h3|)
    Q32 = az3 S_n sgn(h3 - h2) sqrt(2 g |h3 - h2|)
    Q20 = az2 S_n sqrt(2 g h2)

discretised by explicit Euler with ``dt = 1`` s (Eq. 59):
``x_k = x_{k-1} + dt (A(az2_{k-1}) x_{k-1} + B u) + w_k``, ``w_k ~ N(0, 1e-4^2 I)``, and measured
as ``z_k = x_k + v_k``, ``v_k ~ N(0, 2e-4^2 I)`` (three levels, see below). Initial levels
``[1, 0.95, 0.9]`` m, 200 steps. The fault (Eq. 61)::

    az2_k = 0.6                              k <= 10
    az2_k = az2_{k-1} + 1e-4 (k - 10)        k > 10,  i.e.  0.6 + 1e-4 (k - 10)(k - 9) / 2

enters the step from ``k-1`` to ``k`` as ``az2_{k-1}`` (Eq. 62). The joint model augments
``az2`` as a random-walk state (Eq. 62-63).

Readings: Eq. 60 prints a two-component measurement ``[x1, x2]`` while the noise ``v_k`` has
three components and Eq. 63 measures ``[x1, x2, x3]``; the study forecasts ``z_1, z_2, z_3`` with
three ROS-ELMs, so all three levels are measured here. ``g`` is printed "9.81 m/s" (units: m/s^2).
To keep flows finite and differentiable for sigma points that stray below an empty tank,
``sqrt(2 g h2)`` is evaluated as ``sgn(h2) sqrt(2 g |h2|)`` (identical for ``h2 >= 0``), and the
derivative of ``sgn(d) sqrt(|d|)`` at ``d = 0`` (infinite) is replaced by 0.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from ..core.model import StateSpaceModel, joint_state_parameter_model
from ..core.validation import (
    check_count,
    check_dtype_arg,
    check_flag,
    check_params_finite,
    check_positive,
    check_positive_real,
    check_std,
    chol_from_std,
    diag_chol,
)
from .integrators import euler_step
from .simulation import (
    SimulationResult,
    accelerating_drift,
    check_leading,
    check_state,
    initial_state,
    input_sequence,
    plain_params,
    resolve_generator,
    resolve_params,
    simulate_with_parameter,
)

__all__ = [
    "ThreeTankParams",
    "three_tank_rhs",
    "three_tank_step",
    "az2_drift",
    "three_tank_equilibrium",
    "three_tank_model",
    "three_tank_joint_model",
    "simulate_three_tank",
]

_X0 = (1.0, 0.95, 0.9)
_W_STD = 1e-4
_V_STD = 2e-4


@dataclass(frozen=True)
class ThreeTankParams:
    """Paper 000 Sec. 6.1 (SI units) plus the fault profile of Eq. 61.

    Attributes:
        A_s: tank cross-section ``0.0154`` m^2.
        S_n: pipe cross-section ``5e-5`` m^2.
        Q1, Q2: pump flows ``4.5e-5`` m^3/s (the input ``u`` when none is given).
        g: ``9.81`` m/s^2.
        az1, az2, az3: outflow coefficients ``0.5, 0.6, 0.5`` (``az2`` is the nominal value),
            each ``>= 0``.
        dt: Euler / sampling step ``1`` s.
        k_fault: last step with the nominal ``az2`` (Eq. 61: 10).
        drift_rate: ``1e-4`` (Eq. 61).
    """

    A_s: float = 0.0154
    S_n: float = 5e-5
    Q1: float = 4.5e-5
    Q2: float = 4.5e-5
    g: float = 9.81
    az1: float = 0.5
    az2: float = 0.6
    az3: float = 0.5
    dt: float = 1.0
    k_fault: int = 10
    drift_rate: float = 1e-4

    def __post_init__(self):
        plain_params(self, scalars=True)  # NumPy values stored as Python numbers
        check_params_finite(self)
        check_positive(self, "A_s", "S_n", "g", "dt")
        for name in ("az1", "az2", "az3"):  # (0: a closed valve; < 0 reverses the square root)
            if getattr(self, name) < 0:
                raise ValueError(
                    f"ThreeTankParams.{name} must be >= 0, got {getattr(self, name)!r}"
                )
        check_count(self.k_fault, "ThreeTankParams.k_fault", 0)


def _signed_sqrt(d: Tensor) -> Tensor:
    """``sgn(d) sqrt(|d|)`` with derivative 0 (not inf/NaN) at ``d = 0``; vmap-friendly."""
    nz = d != 0
    safe = torch.where(nz, d.abs(), torch.ones_like(d))
    return torch.where(nz, torch.sign(d) * torch.sqrt(safe), torch.zeros_like(d))


def three_tank_rhs(x: Tensor, az2, u, params: ThreeTankParams) -> Tensor:
    """``dx/dt = A(az2) x + B u`` of paper 000 Eq. 57-58.

    Args:
        x: ``(..., 3)`` levels ``[h1, h2, h3]``.
        az2: number or tensor broadcastable to ``x[..., 0]``.
        u: ``(..., 2)`` pump flows ``[Q1, Q2]`` or ``None`` (the nominal ``params.Q1, Q2``).
    Returns:
        ``(..., 3)`` level rates (m/s).
    """
    p = params
    check_state(x, 3, "[h1, h2, h3]")
    check_leading(az2, "az2", x)
    if u is not None:
        if not isinstance(u, Tensor):
            raise TypeError(f"u must be a tensor (..., 2) [Q1, Q2] or None, got {type(u).__name__}")
        check_leading(u, "u", x, 2)  # (a third column was ignored)
    h1, h2, h3 = x[..., 0], x[..., 1], x[..., 2]
    c = p.S_n * (2.0 * p.g) ** 0.5
    Q13 = p.az1 * c * _signed_sqrt(h1 - h3)
    Q32 = p.az3 * c * _signed_sqrt(h3 - h2)
    Q20 = az2 * c * _signed_sqrt(h2)
    if u is None:
        q1, q2 = p.Q1, p.Q2
    else:
        q1, q2 = u[..., 0], u[..., 1]
    return torch.stack([q1 - Q13, q2 + Q32 - Q20, Q13 - Q32], dim=-1) / p.A_s


def three_tank_step(x: Tensor, az2, u, params: ThreeTankParams) -> Tensor:
    """One Euler step of Eq. 59 without noise: ``(..., 3) -> (..., 3)``."""
    return euler_step(lambda z: three_tank_rhs(z, az2, u, params), x, params.dt)


def az2_drift(k: int, params: ThreeTankParams | None = None) -> float:
    """``az2_k`` of paper 000 Eq. 61 in closed form (``k >= 0``).

    ``az2_k = az2`` for ``k <= k_fault``, else ``az2 + rate (k - k_fault)(k - k_fault + 1) / 2``,
    the sum of the recursion's increments ``rate * (j - k_fault)``, ``j = k_fault+1..k``.
    """
    p = resolve_params(params, ThreeTankParams)
    return accelerating_drift(k, p.az2, p.drift_rate, p.k_fault)


def three_tank_equilibrium(
    params: ThreeTankParams | None = None,
    az2: float | None = None,
    *,
    dtype=torch.float64,
    device=None,
) -> Tensor:
    """Closed-form equilibrium levels ``(3,)`` for the nominal pump flows.

    Flow balance: ``Q13 = Q32 = Q1`` and ``Q20 = Q1 + Q2``, so ``h2 = ((Q1+Q2)/(az2 S_n))^2/(2g)``,
    ``h3 = h2 + (Q1/(az3 S_n))^2/(2g)``, ``h1 = h3 + (Q1/(az1 S_n))^2/(2g)`` (needs ``Q1 >= 0``).
    """
    p = resolve_params(params, ThreeTankParams)
    a2 = p.az2 if az2 is None else az2
    check_positive_real(a2, "az2")  # (text, bool refused)
    a2 = float(a2)
    check_dtype_arg(dtype)  # (an integer dtype truncated the levels to 0)
    if p.Q1 < 0 or p.Q1 + p.Q2 < 0 or min(p.az1, p.az3) <= 0:
        raise ValueError(
            "three_tank_equilibrium needs Q1 >= 0, Q1 + Q2 >= 0, az2 > 0, az1 > 0 and az3 > 0 "
            "(tank 1 drains through tank 3; a closed valve leaves its levels undetermined)"
        )
    head = lambda q, a: (q / (a * p.S_n)) ** 2 / (2.0 * p.g)  # noqa: E731
    h2 = head(p.Q1 + p.Q2, a2)
    h3 = h2 + head(p.Q1, p.az3)
    h1 = h3 + head(p.Q1, p.az1)
    return torch.tensor([h1, h2, h3], dtype=dtype, device=device)


def _noise(process_noise_std, measurement_noise_std, dtype, device):
    sq = check_std(process_noise_std, 3, "process_noise_std")
    sr = check_std(measurement_noise_std, 3, "measurement_noise_std")
    return diag_chol(sq, dtype, device), diag_chol(sr, dtype, device)


def three_tank_model(
    params: ThreeTankParams | None = None,
    *,
    drift: bool = True,
    control: bool = False,
    process_noise_std=_W_STD,
    measurement_noise_std=_V_STD,
    dtype=torch.float64,
    device=None,
) -> StateSpaceModel:
    """DTS200 as a :class:`StateSpaceModel` with the known ``az2`` profile (the simulator's model).

    ``f(x, u, k)`` = Eq. 59 with ``az2_{k-1}`` from Eq. 61 (constant if ``drift=False``);
    ``h(x) = x`` (Eq. 63). With ``control=False`` (default, the paper's constant pumps) the model
    has ``control_dim = 0`` and uses ``params.Q1, Q2``; with ``control=True`` it takes
    ``u = [Q1, Q2]`` (m^3/s) each step (``control_dim = 2``, filters then require ``u``).
    """
    p = resolve_params(params, ThreeTankParams)
    drift, control = check_flag(drift, "drift"), check_flag(control, "control")
    check_dtype_arg(dtype)
    SQ, SR = _noise(process_noise_std, measurement_noise_std, dtype, device)

    def f(x, u, k):
        return three_tank_step(x, az2_drift(k - 1, p) if drift else p.az2, u, p)

    return StateSpaceModel(
        f=f,
        h=lambda x, u, k: x.clone(),
        state_dim=3,
        obs_dim=3,
        chol_Q=SQ,
        chol_R=SR,
        control_dim=2 if control else 0,
        batched=True,
    )


def three_tank_joint_model(
    params: ThreeTankParams | None = None,
    *,
    chol_D=1e-2,
    control: bool = False,
    process_noise_std=_W_STD,
    measurement_noise_std=_V_STD,
    dtype=torch.float64,
    device=None,
) -> StateSpaceModel:
    """Joint model of paper 000 Eq. 62-63: state ``[h1, h2, h3, az2]``, ``az2_k = az2_{k-1} + d``.

    ``control`` as in :func:`three_tank_model` (default: nominal pumps, ``control_dim = 0``).

    Args:
        chol_D: square root of the covariance of ``d_{k-1}`` (a std or a ``(1, 1)`` tensor). The
            paper gives none; the default ``1e-2`` per step is of the order of the Eq. 61
            increment in mid-horizon (``1e-4 * 90``).
        process_noise_std, measurement_noise_std: default the paper's ``1e-4`` and ``2e-4``.
    """
    p = resolve_params(params, ThreeTankParams)
    control = check_flag(control, "control")
    check_dtype_arg(dtype)
    SQ, SR = _noise(process_noise_std, measurement_noise_std, dtype, device)
    SD = chol_from_std(chol_D, 1, "chol_D", dtype, device)
    return joint_state_parameter_model(
        lambda x, th, u, k: three_tank_step(x, th[..., 0], u, p),
        lambda x, th, u, k: x.clone(),
        state_dim=3,
        param_dim=1,
        obs_dim=3,
        chol_Q=SQ,
        chol_D=SD,
        chol_R=SR,
        control_dim=2 if control else 0,
        batched=True,  # the step and the measurement take any leading dimensions
    )


def simulate_three_tank(
    n_steps: int = 200,
    runs: int = 1,
    *,
    params: ThreeTankParams | None = None,
    x0=_X0,
    u=None,
    drift: bool = True,
    noise: bool = True,
    process_noise_std=_W_STD,
    measurement_noise_std=_V_STD,
    generator: torch.Generator | None = None,
    dtype=torch.float64,
    device=None,
) -> SimulationResult:
    """Simulate DTS200 with the ``az2`` fault of paper 000 (Eq. 57-61), ``runs`` Monte Carlo runs.

    Args:
        n_steps: ``T`` (paper: 200 steps of 1 s).
        x0: ``(3,)`` or ``(runs, 3)`` initial levels (paper: ``[1, 0.95, 0.9]`` m).
        u: ``(T, 2)`` or ``(T, runs, 2)`` pump flows, or ``None`` for the constant nominal flows.
        drift: apply Eq. 61 (``False``: ``az2`` stays nominal).
        noise: ``False`` switches all noise off (no generator needed).
        generator: the source of all randomness (see :mod:`prognos_torch.systems.noise_streams`).
    Returns:
        :class:`SimulationResult`: ``x`` ``(T+1, runs, 3)``, ``y`` ``(T, runs, 3)``, ``theta``
        ``(T+1, runs, 1)`` = ``az2_k``, ``t`` in seconds.
    """
    p = resolve_params(params, ThreeTankParams)
    check_count(n_steps, "n_steps")
    check_count(runs, "runs")
    check_dtype_arg(dtype)
    drift, noise = check_flag(drift, "drift"), check_flag(noise, "noise")
    gen = resolve_generator(generator, noise)
    X0 = initial_state(x0, 3, runs, dtype, device)
    U = input_sequence(u, n_steps, runs, 2, dtype, device)
    model = three_tank_model(
        p,
        drift=drift,
        control=U is not None,
        process_noise_std=process_noise_std,
        measurement_noise_std=measurement_noise_std,
        dtype=dtype,
        device=device,
    )
    t, x, y, theta = simulate_with_parameter(
        model,
        X0,
        n_steps,
        runs,
        gen,
        lambda k: az2_drift(k, p) if drift else p.az2,
        p.dt,
        u=U,
        dtype=dtype,
        device=device,
    )
    return SimulationResult(
        t=t,
        x=x,
        y=y,
        theta=theta,
        u=U,
        meta={
            "system": "three_tank",
            "paper": "000",
            "equations": "Eq. 57-59 (Euler), Eq. 61 (az2 drift), Eq. 63 (measurements)",
            "dt": p.dt,
            "time_unit": "s",
            "state_names": ("h1", "h2", "h3"),
            "measurement_names": ("z1", "z2", "z3"),
            "param_names": ("az2",),
            "reading": "three measured levels (Eq. 63), not the two of Eq. 60",
            "process_noise_std": check_std(process_noise_std, 3, "process_noise_std"),
            "measurement_noise_std": check_std(measurement_noise_std, 3, "measurement_noise_std"),
            "noise": noise,
        },
    )
