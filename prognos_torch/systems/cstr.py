"""Continuous stirred tank reactor with a drifting feed concentration (paper 003 Sec. V-B).

Model (paper 003 Eq. 50, parameters Table II), state ``x = [C_A, T]`` (mol/L, K), time in min::

    dC_A/dt = -k0 exp(-E/(R T)) C_A + Q_F (C_AF - C_A) / V
    dT/dt   =  k0 exp(-E/(R T)) (-dH) C_A / (rho C_p) + Q_F (T_F - T) / V
               + U A_c (T_c - T) / (rho C_p V)

integrated by classical RK4 with ``dt = 0.02`` min, one RK4 step per sample. The feed
concentration drifts from ``k = 50`` (Eq. 51)::

    C_AF,k = 1                               k <= 50
    C_AF,k = C_AF,k-1 + 1e-5 (k - 50)        k > 50,  i.e.  1 + 1e-5 (k - 50)(k - 49) / 2

Step convention (as paper 000 Eq. 62 for the three-tank system): ``x_k = RK4(x_{k-1};
C_AF,k-1) + w_k``, ``y_k = [C_A, T]_k + v_k``, ``k = 1..T``.

Reading chosen where paper 003 contradicts itself: the text says "the total number of simulation
steps is 200" and "the first 100 C_A data is treated as training data while the rest 100 one is
used as testing data", but also "all the 1000 data is normalized" (a sentence repeated from the
Lorenz experiment). We take **200 steps** (``T = 200``, 4 min, measurements ``y_1..y_200``;
first 100 for training, last 100 for testing). The paper states no noise level; the default
measurement noise std ``(1e-4 mol/L, 0.1 K)`` is our choice (about 1 % of the range that C_A and T
sweep over the drift), and the default process noise is zero (Eq. 50 is deterministic).
With ``C_AF = 1`` the steady state is ``C_A = 0.037241 mol/L``, ``T = 402.3518 K`` (Table II
lists 0.037 and 402.35), which is the default initial state.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor
from torch.func import jacfwd

from ..core.model import StateSpaceModel, joint_state_parameter_model
from ..core.validation import (
    check_count,
    check_dtype_arg,
    check_flag,
    check_params_finite,
    check_positive,
    check_positive_real,
    check_real,
    check_std,
    chol_from_std,
    diag_chol,
)
from .integrators import rk4_step
from .simulation import (
    SimulationResult,
    accelerating_drift,
    check_leading,
    check_state,
    initial_state,
    plain_params,
    resolve_generator,
    resolve_params,
    simulate_with_parameter,
)

__all__ = [
    "CSTRParams",
    "cstr_rhs",
    "cstr_step",
    "cstr_feed_drift",
    "cstr_steady_state",
    "cstr_model",
    "cstr_joint_model",
    "simulate_cstr",
]

_MEAS_STD = (1e-4, 0.1)
_PROC_STD = (0.0, 0.0)


@dataclass(frozen=True)
class CSTRParams:
    """Paper 003 Table II (units: mol, L, K, J, min) and the integration step.

    Attributes:
        k0: pre-exponential factor ``7.2e10`` 1/min.
        E_R: activation energy over gas constant ``E/R = 8750`` K.
        Q_F: feed flow ``100`` L/min.
        V: reactor volume ``99.96`` L (as printed in Table II).
        dH: reaction enthalpy ``-5e4`` J/mol.
        rho_Cp: ``rho C_p = 239`` J/(L K).
        T_F: feed temperature ``320`` K.
        T_c: coolant temperature ``345.44`` K.
        UA_c: heat-transfer coefficient times area ``5e4`` J/(min K).
        C_AF: nominal feed concentration ``1.0`` mol/L (before the drift of Eq. 51).
        dt: integration and sampling step ``0.02`` min (Sec. V-B).
        k_fault: last step with the nominal feed (Eq. 51: 50).
        drift_rate: drift coefficient of Eq. 51 (``1e-5`` mol/L per step squared).
    """

    k0: float = 7.2e10
    E_R: float = 8750.0
    Q_F: float = 100.0
    V: float = 99.96
    dH: float = -5.0e4
    rho_Cp: float = 239.0
    T_F: float = 320.0
    T_c: float = 345.44
    UA_c: float = 5.0e4
    C_AF: float = 1.0
    dt: float = 0.02
    k_fault: int = 50
    drift_rate: float = 1e-5

    def __post_init__(self):
        plain_params(self, scalars=True)  # NumPy values stored as Python numbers
        check_params_finite(self)
        check_positive(self, "k0", "E_R", "Q_F", "V", "rho_Cp", "T_F", "T_c", "dt")
        check_count(self.k_fault, "CSTRParams.k_fault", 0)


def cstr_rhs(x: Tensor, C_AF, params: CSTRParams) -> Tensor:
    """Right-hand side of paper 003 Eq. 50.

    Args:
        x: ``(..., 2)`` state ``[C_A, T]``.
        C_AF: feed concentration, a number or a tensor broadcastable to ``x[..., 0]``.
    Returns:
        ``(..., 2)`` time derivative (per minute).
    """
    p = params
    check_leading(C_AF, "C_AF", check_state(x, 2, "[C_A, T]"))
    C_A, T = x[..., 0], x[..., 1]
    r = p.k0 * torch.exp(-p.E_R / T) * C_A  # reaction rate k0 e^{-E/(RT)} C_A
    dC_A = -r + p.Q_F * (C_AF - C_A) / p.V
    dT = (
        r * (-p.dH) / p.rho_Cp + p.Q_F * (p.T_F - T) / p.V + p.UA_c * (p.T_c - T) / (p.rho_Cp * p.V)
    )
    return torch.stack([dC_A, dT], dim=-1)


def cstr_step(x: Tensor, C_AF, params: CSTRParams) -> Tensor:
    """One RK4 step of length ``params.dt`` with ``C_AF`` held constant: ``(..., 2) -> (..., 2)``."""
    return rk4_step(lambda z: cstr_rhs(z, C_AF, params), x, params.dt)


def cstr_feed_drift(k: int, params: CSTRParams | None = None) -> float:
    """``C_AF,k`` of paper 003 Eq. 51 in closed form (``k >= 0``).

    ``C_AF,k = C_AF`` for ``k <= k_fault``, else ``C_AF + rate (k - k_fault)(k - k_fault + 1)/2``,
    the sum of the recursion's increments ``rate * (j - k_fault)``, ``j = k_fault+1..k``.
    """
    p = resolve_params(params, CSTRParams)
    return accelerating_drift(k, p.C_AF, p.drift_rate, p.k_fault)


def cstr_steady_state(
    params: CSTRParams | None = None,
    C_AF: float | None = None,
    *,
    x_init=(0.037, 402.35),
    dtype=torch.float64,
    device=None,
    tol: float = 1e-11,
    max_iter: int = 50,
) -> Tensor:
    """Steady state of Eq. 50 (``dx/dt = 0``) by Newton's method: ``(2,)`` tensor ``[C_A, T]``.

    With Table II and ``C_AF = 1`` it returns ``[0.0372410, 402.3518]`` (Table II: 0.037, 402.35).
    ``x_init`` picks the branch (the reactor can have several steady states).
    """
    p = resolve_params(params, CSTRParams)
    caf = p.C_AF if C_AF is None else check_real(C_AF, "C_AF")  # (text, bool refused)
    check_dtype_arg(dtype)  # (an integer dtype truncated the state to [0, 402])
    check_positive_real(tol, "tol")  # (tol <= 0 or NaN never converged: "did not converge")
    max_iter = check_count(max_iter, "max_iter")  # (2.5: "'float' object cannot be ...")
    # Newton in float64 whatever dtype is asked (the parameters are float64 and a float32
    # iteration could not reach tol), the answer returned in dtype
    x = torch.as_tensor(x_init, dtype=torch.float64, device=device).clone()
    if tuple(x.shape) != (2,):
        raise ValueError(f"x_init must have shape (2,), got {tuple(x.shape)}")
    scale = torch.tensor([1.0, 100.0], dtype=torch.float64, device=device)
    F = lambda z: cstr_rhs(z, caf, p)  # noqa: E731
    for _ in range(max_iter):
        step = torch.linalg.solve(jacfwd(F)(x), F(x))
        x = x - step
        if bool((step.abs() <= tol * scale).all()):
            return x.to(dtype)
    raise RuntimeError(f"cstr_steady_state did not converge in {max_iter} Newton steps")


def _model_noise(process_noise_std, measurement_noise_std, dtype, device):
    sq = check_std(process_noise_std, 2, "process_noise_std")
    sr = check_std(measurement_noise_std, 2, "measurement_noise_std")
    return diag_chol(sq, dtype, device), diag_chol(sr, dtype, device)


def _observe(x: Tensor) -> Tensor:
    return x.clone()  # y = [C_A, T] (both measured, Sec. V-B)


def cstr_model(
    params: CSTRParams | None = None,
    *,
    drift: bool = True,
    process_noise_std=_PROC_STD,
    measurement_noise_std=_MEAS_STD,
    dtype=torch.float64,
    device=None,
) -> StateSpaceModel:
    """The CSTR as a :class:`StateSpaceModel` with the known feed profile (the simulator's model).

    ``f(x, u, k) = RK4(x; C_AF,k-1)`` with ``C_AF`` from Eq. 51 (or constant when
    ``drift=False``), ``h(x) = x``. ``u`` is ignored (no control input). Noise stds are per
    component ``[C_A, T]``; ``chol_Q``/``chol_R`` are the diagonal ``(2, 2)`` factors.
    """
    p = resolve_params(params, CSTRParams)
    drift = check_flag(drift, "drift")
    check_dtype_arg(dtype)
    SQ, SR = _model_noise(process_noise_std, measurement_noise_std, dtype, device)

    def f(x, u, k):
        return cstr_step(x, cstr_feed_drift(k - 1, p) if drift else p.C_AF, p)

    return StateSpaceModel(
        f=f,
        h=lambda x, u, k: _observe(x),
        state_dim=2,
        obs_dim=2,
        chol_Q=SQ,
        chol_R=SR,
        batched=True,
    )


def cstr_joint_model(
    params: CSTRParams | None = None,
    *,
    chol_D=1e-3,
    process_noise_std=(1e-6, 1e-3),
    measurement_noise_std=_MEAS_STD,
    dtype=torch.float64,
    device=None,
) -> StateSpaceModel:
    """Joint state/parameter model with ``C_AF`` as a random-walk state (paper 000 Eq. 3-4).

    Augmented state ``[C_A, T, C_AF]``: ``x_k = RK4(x_{k-1}; C_AF,k-1) + w``,
    ``C_AF,k = C_AF,k-1 + d``, ``y_k = [C_A, T]_k + v``.

    Args:
        chol_D: square root of the random-walk covariance of ``C_AF``: a std or a ``(1, 1)``
            tensor. The paper gives none; the default ``1e-3`` mol/L per step is of the order of
            the Eq. 51 increment in mid-horizon (``1e-5 * 75``).
        process_noise_std: the filter's state-noise stds for ``[C_A, T]`` (a modelling choice;
            nonzero so that the filter's ``Q`` is positive definite).
    """
    p = resolve_params(params, CSTRParams)
    check_dtype_arg(dtype)
    SQ, SR = _model_noise(process_noise_std, measurement_noise_std, dtype, device)
    SD = chol_from_std(chol_D, 1, "chol_D", dtype, device)
    return joint_state_parameter_model(
        lambda x, th, u, k: cstr_step(x, th[..., 0], p),
        lambda x, th, u, k: _observe(x),
        state_dim=2,
        param_dim=1,
        obs_dim=2,
        chol_Q=SQ,
        chol_D=SD,
        chol_R=SR,
        batched=True,  # the step and the measurement take any leading dimensions
    )


def simulate_cstr(
    n_steps: int = 200,
    runs: int = 1,
    *,
    params: CSTRParams | None = None,
    x0=None,
    drift: bool = True,
    noise: bool = True,
    process_noise_std=_PROC_STD,
    measurement_noise_std=_MEAS_STD,
    generator: torch.Generator | None = None,
    dtype=torch.float64,
    device=None,
) -> SimulationResult:
    """Simulate the CSTR of paper 003 (Eq. 50-51, Table II), ``runs`` Monte Carlo runs.

    Args:
        n_steps: ``T`` (default 200 steps of 0.02 min, see the module docstring).
        runs: number of Monte Carlo runs (``>= 1``).
        x0: ``(2,)`` or ``(runs, 2)`` initial ``[C_A, T]``; default the steady state at the
            nominal ``C_AF`` (:func:`cstr_steady_state`).
        drift: apply the feed drift of Eq. 51 (``False``: constant ``C_AF``).
        noise: ``False`` switches all noise off (no generator needed).
        generator: the source of all randomness (see :mod:`prognos_torch.systems.noise_streams`).
    Returns:
        :class:`SimulationResult` with ``x`` ``(T+1, runs, 2)``, ``y`` ``(T, runs, 2)``,
        ``theta`` ``(T+1, runs, 1)`` = ``C_AF,k``, ``t`` in minutes.
    """
    p = resolve_params(params, CSTRParams)
    check_count(n_steps, "n_steps")
    check_count(runs, "runs")
    check_dtype_arg(dtype)
    drift, noise = check_flag(drift, "drift"), check_flag(noise, "noise")
    g = resolve_generator(generator, noise)
    if x0 is None:
        x0 = cstr_steady_state(p, dtype=dtype, device=device)
    X0 = initial_state(x0, 2, runs, dtype, device)
    model = cstr_model(
        p,
        drift=drift,
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
        g,
        lambda k: cstr_feed_drift(k, p) if drift else p.C_AF,
        p.dt,
        dtype=dtype,
        device=device,
    )
    return SimulationResult(
        t=t,
        x=x,
        y=y,
        theta=theta,
        u=None,
        meta={
            "system": "cstr",
            "paper": "003",
            "equations": "Eq. 50 (RK4), Eq. 51 (C_AF drift), Table II",
            "dt": p.dt,
            "time_unit": "min",
            "state_names": ("C_A", "T"),
            "measurement_names": ("C_A", "T"),
            "param_names": ("C_AF",),
            "reading": "200 steps of 0.02 min; first 100 measurements train, last 100 test",
            "process_noise_std": check_std(process_noise_std, 2, "process_noise_std"),
            "measurement_noise_std": check_std(measurement_noise_std, 2, "measurement_noise_std"),
            "noise": noise,
        },
    )
