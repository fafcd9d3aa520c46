"""Five-car high-speed train (HST) with actuator, coupler and sensor faults (paper 004).

Longitudinal multi-particle model (paper 004 Eq. 1-4): car ``i`` with mass ``m_i``, speed ``v_i``
and traction/braking force ``u_i``; coupler ``i`` (between cars ``i`` and ``i+1``) with extension
``x_i`` and force ``k x_i + d dx_i/dt`` (Eq. 1); running resistance ``m_i (eps_0 + eps_v v_i)``
on every car (Eq. 2) and aerodynamic drag ``eps_a (sum m) v_1^2`` on the leading car (Eq. 3).
In deviations from cruising at ``v_r`` (``x_i^e = 0``, ``v_i^e = v_r``, traction ``u_i^e`` of
Eq. 5-6), with ``psi = [x_1..x_4, v_1..v_5]`` (9 states, ``hat`` dropped)::

    dx_i/dt = v_i - v_{i+1}                                                   i = 1..4
    m_1 dv_1/dt = u_1 - k x_1 - d (v_1 - v_2) - eps_v m_1 v_1
                  - eps_a M (2 v_r v_1 + v_1^2)                               (M = sum m_i)
    m_i dv_i/dt = u_i + k (x_{i-1} - x_i) + d (v_{i-1} - 2 v_i + v_{i+1}) - eps_v m_i v_i
    m_5 dv_5/dt = u_5 + k x_4 + d (v_4 - v_5) - eps_v m_5 v_5

i.e. ``dpsi/dt = A psi + E_xi p(psi) + B u + F_a f^a`` (Eq. 7-8) with
``p(psi) = -eps_a (M / m_1) v_1^2``. Because the resistance is polynomial, this deviation form is
exact (not only a first-order Taylor model) for constant ``v_r``; for the time-varying cruise
profile (Eq. 66) it is exact when the nominal traction also supplies the inertial force
``m_i dv_r/dt``. Discretised by Euler with ``sigma = 0.01`` s (Eq. 13)::

    psi_k = psi_{k-1} + sigma (A(v_r(t_{k-1})) psi_{k-1} + E_xi p(psi_{k-1}) + B u_k
            + F_a f^a(t_{k-1})) + w_k,      w_k ~ N(0, Q_{k-1})                 (Eq. 13, 67)
    y_k   = psi_k + F_s f^s_k + Delta E_k + v_k,   v_k ~ N(0, R_k),  C = I_9     (Eq. 13, 68)

with ``t_k = k sigma``, ``Delta E_k = M F_k N`` (Eq. 14; ``M = 0.01 * 1_9``, ``N = 1``, ``F_k``
drawn uniformly from ``[-1, 1]``, which satisfies ``F_k^T F_k <= 1``; the paper does not say how
``F_k`` is generated). Faults (Eq. 61-65): ``f^a = [f_a^c, f_a^d]`` enters the speeds of car 3
(gain 0.85) and car 5 (gain 1.2); ``f^s`` offsets the speed sensor of car 1.

Derived or chosen where the extracted paper is garbled or silent (see ``docs/systems.md``):

* Eq. 4 (and Eq. 7) print the middle-car damping as ``-d (dx_{i-1} - dx_i)``; the coupler
  law Eq. 1 and the car-1/car-5 equations give ``+d (dx_{i-1} - dx_i)``, and so do the positive
  off-diagonals ``d / m_i`` of ``A_22``. With the printed sign the chain would be unstable. The
  diagonal of ``A_22`` for the middle cars is then ``-eps_v - 2 d / m_i`` (printed ``- d / m_i``),
  and ``a_1`` in ``U_1`` is ``eps_v``.
* ``B = [0; I_n]`` is printed, but the speed equations are divided by ``m_i`` (see ``A_21``), so
  with ``u`` in newtons ``B = [0; diag(1/m_i)]``. The fault signals are accelerations (m/s^2)
  added through ``F_a`` (Eq. 13: ``sigma F_a``).
* Eq. 61-62 print ``F_a`` (two columns) and ``F_s`` with 12 rows, the augmented dimension
  ``9 + 2 + 1``; rows 10-12 are zero and rows 1-9 are the distribution matrices used here
  (``F_a``: 0.85 at ``v_3``, 1.2 at ``v_5``; ``F_s``: 1 at ``v_1``).
* Eq. 10 defines the coupler fault through the state (``f_a^d = x_p``); the simulation section
  prescribes the explicit signal of Eq. 64, which is what is simulated.
* Eq. 65's ``x_4(t) x_5(t)`` is read as the state components ``psi_4 psi_5`` (coupler 4
  extension times car-1 speed deviation, 1-based).
* "sawtooth(t), a 0.16 Hz sawtooth" is MATLAB's ``sawtooth(2 pi 0.16 t)``, i.e.
  ``2 frac(0.16 t) - 1``, rising from -1 to 1.
* Eq. 66 jumps from 220 km/h to 20 km/h at ``t = 316`` s (``230 - 0.625 * 16 = 220``); we keep the
  ramp of 0.625 km/h per s until it reaches 20 km/h (``t = 636`` s). Only ``t >= 316`` s differs.
* Eq. 67 gives ``Q_k``; the library's ``w_k`` is the paper's ``w_{k-1}``, so step ``k`` uses
  ``Q_{k-1}``. Taken literally the noise is large (unit variance per 0.01 s step);
  ``q_scale``/``r_scale`` multiply ``Q``/``R`` (``q_scale = sigma**2`` reads Eq. 67 as the
  intensity of the continuous-time noise ``w(t)`` of Eq. 8 under Euler).

Parameter values: paper 004's Table 1 was lost in extraction, so the values below are **not the
paper's**. Car mass ``m_i = 8e4`` kg, coupler stiffness ``k = 8e4`` N/m and the Davis
coefficients ``eps_0 = 0.01176`` N/kg, ``eps_v = 7.7616e-4`` N s/(m kg),
``eps_a = 1.6e-5`` N s^2/(m^2 kg) are the values used for high-speed-train cascade (multi-point)
models by Yang & Sun (2001, Int. J. Control 74(9)), Song, Song, Tang & Ning (2011, IEEE T-ITS
12(4)) and Faieghi, Jalali & Mashhadi (2014, ISA Trans. 53(2)). Those works model couplers as pure
springs, so the damping ``d = 1e4`` N s/m is our choice (damping ratio about 0.09 for the
two-car coupler mode ``sqrt(2 k / m)``).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from ..core.model import StateSpaceModel, joint_state_parameter_model
from ..core.validation import (
    check_count,
    check_dtype_arg,
    check_flag,
    check_float_tensor,
    check_nonneg,
    check_params_finite,
    check_positive_real,
    chol_from_std,
    is_real,
)
from .noise_streams import draw_run_noise
from .simulation import (
    SimulationResult,
    check_leading,
    check_state,
    initial_state,
    input_sequence,
    plain_params,
    resolve_generator,
    resolve_params,
    simulate_model,
)

__all__ = [
    "HST_FAULT_NAMES",
    "hst_state_names",
    "HSTParams",
    "hst_rhs",
    "hst_step",
    "hst_measure",
    "hst_cruise_speed",
    "hst_actuator_fault",
    "hst_coupler_fault",
    "hst_sensor_fault",
    "hst_process_variance",
    "hst_measurement_variance",
    "hst_noise_variances",
    "hst_estimation_errors",
    "hst_model",
    "hst_fault_model",
    "hst_nominal_fault_model",
    "simulate_hst",
    "simulate_hst_runs",
]

#: Names of the faults ``[f_a^c, f_a^d, f_s]`` (Eq. 61-65), the fault model's last states.
HST_FAULT_NAMES = ("f_a^c", "f_a^d", "f_s")


def hst_state_names(n_cars: int = 5) -> tuple[str, ...]:
    """Names of the state ``psi``: the ``n - 1`` coupler displacements ``x1..`` and the ``n``
    car speeds ``v1..`` (Eq. 1-8)."""
    return tuple(f"x{i}" for i in range(1, n_cars)) + tuple(f"v{i}" for i in range(1, n_cars + 1))


_FA = (
    (0.0, 0.0),
    (0.0, 0.0),
    (0.0, 0.0),
    (0.0, 0.0),
    (0.0, 0.0),
    (0.0, 0.0),
    (0.85, 0.0),  # psi_7 = v_3: traction fault of car 3 (Eq. 61, column 1)
    (0.0, 0.0),
    (0.0, 1.2),  # psi_9 = v_5: coupler fault between cars 4 and 5 (Eq. 61, column 2)
)
_FS = (0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0)  # psi_5 = v_1: speed sensor of car 1 (Eq. 62)


@dataclass(frozen=True)
class HSTParams:
    """Train parameters (literature values, not paper 004's lost Table 1; see module docstring).

    Attributes:
        m: car masses (kg), ``n_cars`` entries (default five cars of ``8e4`` kg).
        k: coupler stiffness (N/m). d: coupler damping (N s/m).
        eps_0, eps_v, eps_a: Davis coefficients per unit mass (N/kg, N s/(m kg), N s^2/(m^2 kg)).
        sigma: sampling interval (s), paper 004 Sec. 4: 0.01.
        F_a: ``(2 n - 1, 2)`` actuator/coupler fault distribution (Eq. 61, rows 1-9).
        F_s: ``(2 n - 1,)`` sensor fault distribution (Eq. 62, rows 1-9).
        M: ``(2 n - 1,)`` measurement-uncertainty direction (Sec. 4: 0.01 each). N: scalar 1.
        gamma: robust bound of Theorem 1 used in paper 004's simulation (1.05); for filters.
    """

    m: tuple[float, ...] = (8.0e4,) * 5
    k: float = 8.0e4
    d: float = 1.0e4
    eps_0: float = 0.01176
    eps_v: float = 0.00077616
    eps_a: float = 1.6e-5
    sigma: float = 0.01
    F_a: tuple[tuple[float, float], ...] = _FA
    F_s: tuple[float, ...] = _FS
    M: tuple[float, ...] = (0.01,) * 9
    N: float = 1.0
    gamma: float = 1.05

    def __post_init__(self):
        plain_params(self)  # list fields would leave the frozen parameters mutable
        check_params_finite(self)
        for name in ("m", "F_a", "F_s", "M"):
            if not isinstance(getattr(self, name), tuple):
                raise ValueError(
                    f"HSTParams.{name} must be a sequence, got {getattr(self, name)!r}"
                )
        n = len(self.m)
        if n < 2:
            raise ValueError(f"HSTParams.m must list at least 2 car masses, got {self.m!r}")
        if any(mi <= 0 for mi in self.m):
            raise ValueError(f"HSTParams.m must be > 0, got {self.m!r}")
        for name in ("k", "d", "eps_0", "eps_v", "eps_a"):
            if getattr(self, name) < 0:
                raise ValueError(f"HSTParams.{name} must be >= 0, got {getattr(self, name)!r}")
        if self.sigma <= 0:
            raise ValueError(f"HSTParams.sigma must be > 0, got {self.sigma!r}")
        s = 2 * n - 1
        if len(self.F_a) != s or any(not isinstance(r, tuple) or len(r) != 2 for r in self.F_a):
            raise ValueError(f"HSTParams.F_a must have shape ({s}, 2) for {n} cars")
        for name in ("F_s", "M"):
            if len(getattr(self, name)) != s:
                raise ValueError(f"HSTParams.{name} must have shape ({s},) for {n} cars")

    @property
    def n_cars(self) -> int:
        return len(self.m)

    @property
    def state_dim(self) -> int:
        """``2 n - 1`` (coupler extensions and car speeds)."""
        return 2 * len(self.m) - 1


# --------------------------------------------------------------------------- dynamics
def hst_rhs(psi: Tensor, u, f_a, v_r: float, params: HSTParams) -> Tensor:
    """``dpsi/dt`` of paper 004 Eq. 8 (derived form, see module docstring).

    Args:
        psi: ``(..., 2n-1)`` deviations ``[x_1..x_{n-1}, v_1..v_n]``.
        u: ``(..., n)`` deviation forces ``u_i - u_i^e`` (N) or ``None`` (zero).
        f_a: actuator/coupler faults ``[f_a^c, f_a^d]``: two numbers or a ``(..., 2)`` tensor.
        v_r: cruising speed (m/s) of the linearisation.
    Returns:
        ``(..., 2n-1)``.
    """
    p = params
    n = p.n_cars
    check_state(psi, p.state_dim, "[x_c, v]", "psi")
    if u is not None:
        check_leading(u, "u", psi, n, state="psi", numbers=False)
    if isinstance(f_a, Tensor):
        check_leading(f_a, "f_a", psi, 2, state="psi")
        fa = f_a.to(psi.dtype)
    elif isinstance(f_a, (tuple, list)) and len(f_a) == 2 and all(is_real(e) for e in f_a):
        fa = psi.new_tensor(f_a)
    else:
        raise ValueError(f"f_a must be two numbers or a tensor (..., 2), got {f_a!r}")
    xc, v = psi[..., : n - 1], psi[..., n - 1 :]
    dx = v[..., :-1] - v[..., 1:]  # Eq. 4 line 1 (noise mu_i excluded)
    F = p.k * xc + p.d * dx  # coupler forces, Eq. 1
    z = torch.zeros_like(F[..., :1])
    force = torch.cat([z, F], -1) - torch.cat([F, z], -1)  # pulled by the coupler ahead, held back
    if u is not None:
        force = force + u
    acc = force / psi.new_tensor(p.m) - p.eps_v * v  # rolling resistance deviation, Eq. 2
    v1 = v[..., :1]
    drag = p.eps_a * (sum(p.m) / p.m[0]) * (2.0 * v_r * v1 + v1 * v1)  # Eq. 3 about v_r (exact)
    acc = acc - torch.cat([drag, torch.zeros_like(v[..., 1:])], -1)
    return torch.cat([dx, acc], -1) + fa @ psi.new_tensor(p.F_a).mT  # + F_a f^a


def hst_step(psi: Tensor, u, f_a, v_r: float, params: HSTParams) -> Tensor:
    """Euler step of Eq. 13 without noise: ``psi + sigma * hst_rhs(...)``."""
    return psi + params.sigma * hst_rhs(psi, u, f_a, v_r, params)


def hst_measure(psi: Tensor, f_s, params: HSTParams) -> Tensor:
    """``C psi + F_s f^s`` with ``C = I`` (Eq. 11, 13); ``f_s`` a number or ``(...)`` tensor
    (broadcasting to ``psi``'s leading shape)."""
    check_state(psi, params.state_dim, "[x_c, v]", "psi")
    Fs = psi.new_tensor(params.F_s)
    if isinstance(f_s, Tensor):
        check_leading(f_s, "f_s", psi, state="psi")
        fs = f_s.unsqueeze(-1)
    elif is_real(f_s):
        fs = f_s
    else:
        raise TypeError(f"f_s must be a number or a tensor (...), got {f_s!r}")
    return psi + fs * Fs


# --------------------------------------------------------------------------- profiles
def hst_cruise_speed(t: float) -> float:
    """Cruising speed ``v_r(t)`` of Eq. 66 in m/s (continuous reading, see module docstring)."""
    if t < 50.0:
        kmh = 200.0
    elif t < 100.0:
        kmh = 200.0 + 0.6 * (t - 50.0)
    elif t < 300.0:
        kmh = 230.0
    else:
        kmh = max(230.0 - 0.625 * (t - 300.0), 20.0)
    return kmh / 3.6


def _sawtooth(t: float, freq: float = 0.16) -> float:
    """MATLAB ``sawtooth(2 pi freq t)``: ``2 frac(freq t) - 1``."""
    ft = freq * t
    return 2.0 * (ft - math.floor(ft)) - 1.0


def hst_actuator_fault(t: float) -> float:
    """``f_a^c(t)`` of Eq. 63 (traction loss of car 3), m/s^2."""
    if 5.0 < t <= 15.0:
        return -0.04 * (-1.0 + 0.2 * _sawtooth(t))
    return 0.0


def hst_coupler_fault(t: float) -> float:
    """``f_a^d(t)`` of Eq. 64 (stiffness change of coupler 4), m/s^2."""
    if 4.0 < t <= 15.0:
        return 0.06 * (1.0 + math.exp(-t + 7.5))
    return 0.0


def hst_sensor_fault(psi: Tensor, t: float) -> Tensor:
    """``f_s(t)`` of Eq. 65 (drift of the car-1 speed sensor): ``(..., 9) -> (...)``.

    ``1e-3 (-1 + sin(0.1 psi_4 psi_5))`` (1-based components) for ``2.5 < t <= 15``, else 0.
    Eq. 65 is written for the five-car train (``psi_4 psi_5`` = coupler 4 times car-1 speed);
    a state of another width is refused (it read other components, or failed on an index).
    """
    check_state(psi, 9, "[x_1..x_4, v_1..v_5] (Eq. 65 is written for five cars)", "psi")
    if 2.5 < t <= 15.0:
        return 1e-3 * (-1.0 + torch.sin(0.1 * psi[..., 3] * psi[..., 4]))
    return torch.zeros_like(psi[..., 0])


def hst_process_variance(k: int) -> float:
    """Diagonal of ``Q_k`` of Eq. 67: ``1 + 0.5 sin(0.0003 k)``."""
    return 1.0 + 0.5 * math.sin(0.0003 * k)


def hst_measurement_variance(k: int) -> float:
    """Diagonal of ``R_k`` of Eq. 68: ``1.1 + 0.08 cos(0.0002 k)``."""
    return 1.1 + 0.08 * math.cos(0.0002 * k)


def hst_noise_variances(n_steps: int, *, dtype=torch.float64, device=None) -> tuple[Tensor, Tensor]:
    """Diagonals of ``Q`` and ``R`` (Eq. 67-68, before ``q_scale``/``r_scale``) at the library
    steps ``k = 1..T``: step ``k`` uses ``Q_{k-1}`` and ``R_k`` (module docstring).

    Returns:
        ``(q, r)``, each ``(T,)``.
    """
    check_count(n_steps, "n_steps")
    check_dtype_arg(dtype)
    q = [hst_process_variance(k - 1) for k in range(1, n_steps + 1)]
    r = [hst_measurement_variance(k) for k in range(1, n_steps + 1)]
    return torch.tensor(q, dtype=dtype, device=device), torch.tensor(r, dtype=dtype, device=device)


def _rmse_t(est: Tensor, ref: Tensor) -> Tensor:
    return (est - ref).square().mean(dim=0).sqrt()  # over time; NaN where an estimate diverged


def hst_estimation_errors(
    means: Tensor,
    var_Q: Tensor,
    var_R: Tensor,
    truth: Tensor,
    *,
    q_scale: float = 1.0,
    skip: int = 0,
) -> dict[str, Tensor]:
    """Per-run RMSEs over time of a fault-estimation run (paper 004 Tables 2-5).

    Args:
        means: ``(T, ..., 2n-1+3)`` estimates of :func:`hst_fault_model`'s state at steps 1..T.
        var_Q: ``(T, ..., >= 2n-1)`` process-noise variances used per step (the first ``2n-1``
            are compared, divided by ``q_scale``: in the units of Eq. 67).
        var_R: ``(T, ..., 2n-1)`` measurement-noise variances used per step.
        truth: ``(T', ..., 2n-1+3)`` with ``T' > T``: ``cat([x, theta], -1)`` of
            :func:`simulate_hst` from ``k = 0`` (row ``k`` is step ``k``).
        q_scale: the ``q_scale`` of the model (Eq. 67 reading).
        skip: the ``*_late`` entries use only the steps ``k > skip`` (e.g. after a noise
            estimator's window has filled).
    Returns:
        ``state`` ``(..., 2n-1)``, ``fault`` ``(..., 3)``, ``Q``, ``R``, ``Q_late``, ``R_late``
        ``(..., 2n-1)``: RMSE over the steps of each component (truth of ``Q``, ``R``:
        :func:`hst_noise_variances`).
    """
    for name, v, want in (
        ("means", means, "(T, ..., 2n+2)"),
        ("var_Q", var_Q, "(T, ..., >= 2n-1)"),
        ("var_R", var_R, "(T, ..., 2n-1)"),
        ("truth", truth, "(T + 1, ..., 2n+2)"),
    ):
        check_float_tensor(v, name, want)
        if v.dim() < 2:
            raise ValueError(f"{name} must have shape {want}, got {tuple(v.shape)}")
    T = means.shape[0]
    s = var_R.shape[-1]
    check_positive_real(q_scale, "q_scale")
    check_count(skip, "skip", minimum=0)
    if skip >= T:
        raise ValueError(
            f"skip must be < T = {T} (the late scores need a step k > skip), got {skip}"
        )
    if truth.shape[0] <= T or means.shape[-1] != s + 3 or truth.shape[1:] != means.shape[1:]:
        raise ValueError(
            f"means (T, ..., {s + 3}) and truth (T + 1, ..., {s + 3}) do not match: "
            f"{tuple(means.shape)}, {tuple(truth.shape)}"
        )
    if var_Q.shape[0] != T or var_R.shape[0] != T or var_Q.shape[-1] < s:
        raise ValueError(
            f"var_Q (T, ..., >= {s}) and var_R (T, ..., {s}) must have T = {T} rows, got "
            f"{tuple(var_Q.shape)}, {tuple(var_R.shape)}"
        )
    lead = means.shape[1:-1]  # (a wider or shorter batch was broadcast against the truth's)
    if var_Q.shape[1:-1] != lead or var_R.shape[1:-1] != lead:
        raise ValueError(
            f"var_Q and var_R must have the batch shape {tuple(lead)} of means (T, ..., {s + 3}), "
            f"got {tuple(var_Q.shape)}, {tuple(var_R.shape)}"
        )
    ref = truth[1 : T + 1]
    qt, rt = hst_noise_variances(T, dtype=means.dtype, device=means.device)
    shape = (T,) + (1,) * (var_R.dim() - 1)
    Q, R = var_Q[..., :s] / q_scale, var_R  # Q in the units of Eq. 67
    Qt, Rt = qt.reshape(shape).expand_as(Q), rt.reshape(shape).expand_as(R)
    return {
        "state": _rmse_t(means[..., :s], ref[..., :s]),
        "fault": _rmse_t(means[..., s:], ref[..., s:]),
        "Q": _rmse_t(Q, Qt),
        "R": _rmse_t(R, Rt),
        "Q_late": _rmse_t(Q[skip:], Qt[skip:]),
        "R_late": _rmse_t(R[skip:], Rt[skip:]),
    }


def _check_five_cars(params: HSTParams, faults: bool) -> None:
    """The faults of Eq. 63-65 need the five-car train (Eq. 65 reads ``psi_4 psi_5``)."""
    if faults and params.n_cars != 5:
        raise ValueError(
            f"faults=True applies Eq. 63-65 of the five-car train (Eq. 65 reads psi_4 psi_5), "
            f"got HSTParams with {params.n_cars} cars: pass faults=False"
        )


def _noise_chols(params: HSTParams, q_scale, r_scale, dtype, device):
    check_dtype_arg(dtype)
    qs = check_nonneg(q_scale, "q_scale", numbers_only=True)
    rs = check_nonneg(r_scale, "r_scale", numbers_only=True)
    eye = torch.eye(params.state_dim, dtype=dtype, device=device)

    def chol_Q(k: int) -> Tensor:  # library step k uses the paper's Q_{k-1} (w_{k-1} in Eq. 13)
        return math.sqrt(qs * hst_process_variance(k - 1)) * eye

    def chol_R(k: int) -> Tensor:
        return math.sqrt(rs * hst_measurement_variance(k)) * eye

    return chol_Q, chol_R


# --------------------------------------------------------------------------- models
def hst_model(
    params: HSTParams | None = None,
    *,
    faults: bool = True,
    control: bool = False,
    q_scale: float = 1.0,
    r_scale: float = 1.0,
    dtype=torch.float64,
    device=None,
) -> StateSpaceModel:
    """The train with known fault signals as a :class:`StateSpaceModel` (the simulator's model).

    ``f(psi, u, k)`` = Eq. 13 with ``v_r(t_{k-1})`` and ``f^a(t_{k-1})``; ``h(psi, u, k) =
    psi + F_s f_s(psi, t_k)``; ``t_k = k sigma``; ``chol_Q(k) = sqrt(q_scale Q_{k-1})``,
    ``chol_R(k) = sqrt(r_scale R_k)`` (Eq. 67-68). ``faults=False`` gives the healthy train.
    ``control=True`` makes ``u`` (``(..., n)`` deviation forces, N) an input each step
    (``control_dim = n``); by default ``control_dim = 0`` and ``u = 0``. The measurement uncertainty
    ``Delta E_k`` is not part of ``h``; a robust filter uses ``params.M``, ``params.N``.
    """
    p = resolve_params(params, HSTParams)
    chol_Q, chol_R = _noise_chols(p, q_scale, r_scale, dtype, device)
    faults, control = check_flag(faults, "faults"), check_flag(control, "control")
    _check_five_cars(p, faults)

    def f(psi, u, k):
        t = (k - 1) * p.sigma
        fa = (hst_actuator_fault(t), hst_coupler_fault(t)) if faults else (0.0, 0.0)
        return hst_step(psi, u, fa, hst_cruise_speed(t), p)

    def h(psi, u, k):
        fs = hst_sensor_fault(psi, k * p.sigma) if faults else 0.0
        return hst_measure(psi, fs, p)

    return StateSpaceModel(
        f=f,
        h=h,
        state_dim=p.state_dim,
        obs_dim=p.state_dim,
        chol_Q=chol_Q,
        chol_R=chol_R,
        control_dim=p.n_cars if control else 0,
        batched=True,
    )


def hst_fault_model(
    params: HSTParams | None = None,
    *,
    chol_D=(1e-2, 1e-2, 1e-4),
    control: bool = False,
    q_scale: float = 1.0,
    r_scale: float = 1.0,
    dtype=torch.float64,
    device=None,
) -> StateSpaceModel:
    """Augmented model of paper 004 Eq. 12-13 for fault estimation.

    State ``[psi (2n-1), f_a^c, f_a^d, f_s]``; the faults follow ``f_k = f_{k-1} + d`` (Eq. 12);
    ``psi_k = psi_{k-1} + sigma (A psi + E_xi p + B u + F_a f^a_{k-1}) + w``,
    ``y_k = psi_k + F_s f_s,k + v`` (``C_bar = [C 0 F_s]``).

    Args:
        chol_D: square root of the fault random-walk covariance (``Q_1`` in the paper's
            ``diag(Q, Q_1)``, value not given): 3 stds, one std, or a ``(3, 3)`` tensor.
        control: take the deviation forces ``u`` as an input (``control_dim = n``); default
            ``u = 0`` and ``control_dim = 0``.
        q_scale, r_scale: multiply ``Q_k``/``R_k`` of Eq. 67-68.
    """
    p = resolve_params(params, HSTParams)
    chol_Q, chol_R = _noise_chols(p, q_scale, r_scale, dtype, device)
    control = check_flag(control, "control")
    SD = chol_from_std(chol_D, 3, "chol_D", dtype, device)

    def f(psi, th, u, k):
        return hst_step(psi, u, th[..., :2], hst_cruise_speed((k - 1) * p.sigma), p)

    def h(psi, th, u, k):
        return hst_measure(psi, th[..., 2], p)

    return joint_state_parameter_model(
        f,
        h,
        state_dim=p.state_dim,
        param_dim=3,
        obs_dim=p.state_dim,
        chol_Q=chol_Q,
        chol_D=SD,
        chol_R=chol_R,
        control_dim=p.n_cars if control else 0,
        batched=True,  # hst_step and hst_measure take any leading dimensions
    )


def hst_nominal_fault_model(
    params: HSTParams | None = None,
    *,
    q_level: float = 1.0,
    r_level: float = 1.1,
    chol_D=(1e-2, 1e-2, 1e-4),
    q_scale: float = 1.0,
    dtype=torch.float64,
    device=None,
) -> StateSpaceModel:
    """:func:`hst_fault_model` with fixed nominal noise instead of the true ``Q_k``, ``R_k``.

    The statistics a filter assumes when it does not know Eq. 67-68: the constant parts
    ``Q = q_scale q_level I`` (Eq. 67: 1) and ``R = r_level I`` (Eq. 68: 1.1), with the fault
    random walk ``chol_D`` (Eq. 12) as in :func:`hst_fault_model`.

    Returns:
        The augmented model, state ``2n-1+3``; ``chol_Q`` ``(2n+2, 2n+2)`` =
        ``blockdiag(sqrt(q_scale q_level) I, chol_D)``, ``chol_R`` ``(2n-1, 2n-1)`` =
        ``sqrt(r_level) I``, both constant.
    """
    p = resolve_params(params, HSTParams)
    check_nonneg(q_level, "q_level", numbers_only=True)
    check_nonneg(r_level, "r_level", numbers_only=True)
    model = hst_fault_model(p, chol_D=chol_D, q_scale=q_scale, dtype=dtype, device=device)
    eye = torch.eye(p.state_dim, dtype=dtype, device=device)
    SD = chol_from_std(chol_D, 3, "chol_D", dtype, device)
    cQ = torch.block_diag(math.sqrt(q_scale * q_level) * eye, SD)
    return dataclasses.replace(model, chol_Q=cQ, chol_R=math.sqrt(r_level) * eye)


# --------------------------------------------------------------------------- simulator
def simulate_hst(
    n_steps: int = 2000,
    runs: int = 1,
    *,
    params: HSTParams | None = None,
    x0=None,
    u=None,
    faults: bool = True,
    measurement_uncertainty: bool = True,
    noise: bool = True,
    q_scale: float = 1.0,
    r_scale: float = 1.0,
    generator: torch.Generator | None = None,
    dtype=torch.float64,
    device=None,
) -> SimulationResult:
    """Simulate the faulty five-car train of paper 004 Sec. 4, ``runs`` Monte Carlo runs.

    Args:
        n_steps: ``T`` steps of ``sigma = 0.01`` s (default 2000, i.e. 20 s; the faults act
            during ``t <= 15`` s).
        x0: ``(9,)`` or ``(runs, 9)`` initial deviations (default zero: cruising at equilibrium).
        u: ``(T, 5)`` or ``(T, runs, 5)`` deviation forces (N), or ``None`` (zero).
        faults: apply Eq. 63-65 (``False``: healthy train).
        measurement_uncertainty: add ``Delta E_k = M F_k N`` (Eq. 14).
        noise: ``False`` switches process and measurement noise and ``Delta E_k`` off.
        q_scale, r_scale: multiply ``Q_k``/``R_k`` of Eq. 67-68.
        generator: the source of all randomness (per run: ``w`` ``(T, 9)``, ``v`` ``(T, 9)``,
            then ``T`` uniforms for ``F_k = 2 U - 1``).
    Returns:
        :class:`SimulationResult`: ``x`` ``(T+1, runs, 9)``, ``y`` ``(T, runs, 9)``, ``theta``
        ``(T+1, runs, 3)`` = ``[f_a^c(t_k), f_a^d(t_k), f_s(psi_k, t_k)]`` (so that
        ``cat([x, theta], -1)`` is the state of :func:`hst_fault_model`), ``t`` in seconds;
        ``meta["delta_E"]`` ``(T, runs, 9)`` (or ``None``) and ``meta["v_r"]`` ``(T+1,)`` m/s.
    """
    p = resolve_params(params, HSTParams)
    check_count(n_steps, "n_steps")
    check_count(runs, "runs")
    check_dtype_arg(dtype)
    faults = check_flag(faults, "faults")
    _check_five_cars(p, faults)
    measurement_uncertainty = check_flag(measurement_uncertainty, "measurement_uncertainty")
    gen = resolve_generator(generator, check_flag(noise, "noise"))
    s = p.state_dim
    X0 = initial_state(
        torch.zeros(s, dtype=dtype, device=device) if x0 is None else x0, s, runs, dtype, device
    )
    U = input_sequence(u, n_steps, runs, p.n_cars, dtype, device)
    model = hst_model(
        p, faults=faults, q_scale=q_scale, r_scale=r_scale, dtype=dtype, device=device
    )
    e_w = e_v = dE = None
    if gen is not None:
        e_w, e_v, unif = draw_run_noise(
            gen,
            runs,
            n_steps,
            [("normal", (s,)), ("normal", (s,)), ("uniform", ())],
            dtype=dtype,
            device=device,
        )
        if measurement_uncertainty:
            Fk = 2.0 * unif - 1.0  # |F_k| <= 1 (Eq. 14)
            dE = Fk.unsqueeze(-1) * torch.tensor(p.M, dtype=dtype, device=device) * p.N
    x, y = simulate_model(model, X0, n_steps, e_w=e_w, e_v=e_v, u=U, y_offset=dE)
    ts = [k * p.sigma for k in range(n_steps + 1)]
    if faults:
        fa = torch.tensor(
            [(hst_actuator_fault(t), hst_coupler_fault(t)) for t in ts], dtype=dtype, device=device
        )
        fs = torch.stack([hst_sensor_fault(x[k], t) for k, t in enumerate(ts)])
    else:
        fa = torch.zeros(n_steps + 1, 2, dtype=dtype, device=device)
        fs = torch.zeros(n_steps + 1, runs, dtype=dtype, device=device)
    theta = torch.cat([fa.unsqueeze(1).expand(-1, runs, 2), fs.unsqueeze(-1)], -1)
    return SimulationResult(
        t=torch.arange(n_steps + 1, dtype=dtype, device=device) * p.sigma,
        x=x,
        y=y,
        theta=theta,
        u=U,
        meta={
            "system": "high_speed_train",
            "paper": "004",
            "equations": "Eq. 1-8, 13 (Euler), 14, 61-68",
            "dt": p.sigma,
            "time_unit": "s",
            "state_names": hst_state_names(p.n_cars),
            "param_names": HST_FAULT_NAMES,
            "v_r": torch.tensor([hst_cruise_speed(t) for t in ts], dtype=dtype, device=device),
            "delta_E": dE,
            "M": p.M,
            "N": p.N,
            "gamma": p.gamma,
            "q_scale": q_scale,
            "r_scale": r_scale,
            "noise": noise,
            "parameters_source": "literature values, not paper 004's (its Table 1 was lost)",
        },
    )


def simulate_hst_runs(
    n_steps: int,
    generators: Sequence[torch.Generator],
    *,
    params: HSTParams | None = None,
    q_scale: float = 1.0,
    r_scale: float = 1.0,
    dtype=torch.float64,
    device=None,
) -> tuple[Tensor, Tensor, Tensor]:
    """:func:`simulate_hst` once per generator, run ``i`` from ``generators[i]`` alone (so that a
    run does not depend on how many runs are drawn), stacked along the run dimension.

    Returns:
        ``(truth, y, t)``: ``truth`` ``(T+1, B, 2n-1+3)`` = ``cat([x, theta], -1)``, the state of
        :func:`hst_fault_model` at steps ``0..T``; ``y`` ``(T, B, 2n-1)``; ``t`` ``(T+1,)``
        seconds; ``B = len(generators)``.
    """
    if isinstance(generators, torch.Generator):
        raise TypeError(
            "generators must be a sequence of torch.Generator, one per run, got one Generator: "
            "pass [generator], or simulate_hst(n_steps, runs, generator=generator)"
        )
    if not generators:
        raise ValueError("generators must list at least one torch.Generator")
    sims = [
        simulate_hst(
            n_steps,
            1,
            params=params,
            q_scale=q_scale,
            r_scale=r_scale,
            generator=g,
            dtype=dtype,
            device=device,
        )
        for g in generators
    ]
    x, theta = torch.cat([s.x for s in sims], 1), torch.cat([s.theta for s in sims], 1)
    return torch.cat([x, theta], -1), torch.cat([s.y for s in sims], 1), sims[-1].t
