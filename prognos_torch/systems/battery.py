"""Equivalent-circuit battery with an end-of-discharge event (Daigle & Sankararaman, 2013).

The model is the one NASA's progpy ships as ``BatteryCircuit`` (progpy 1.9.0), written here from
its documented equations and default parameters, so that the two can be compared step for
step. State ``x = [tb, qb, qcp, qcs]`` (progpy's order): battery temperature (K) and the charges
(C) in the capacitors ``Cb``, ``Ccp`` and ``Cs`` of the circuit. Control ``u = [i]``: the current
drawn (A). Outputs ``y = [t, v]``: temperature (K) and terminal voltage (V). With

    SOC  = (CMax - qMax + qb) / CMax
    Cb   = Cbp0 SOC^3 + Cbp1 SOC^2 + Cbp2 SOC + Cbp3          (SOC-dependent capacitance)
    Rcp  = Rcp0 + Rcp1 exp(Rcp2 (1 - SOC))                    (SOC-dependent resistance)
    Vb   = qb / Cb,   Vcp = qcp / Ccp,   Vcs = qcs / Cs
    v    = Vb - Vcp - Vcs
    ib   = i + v / Rp,   icp = ib - Vcp / Rcp,   ics = ib - Vcs / Rs

the dynamics are

    d tb / dt  = (ha (Ta - tb) + hcs Vcs^2 / Rs + hcp Vcp^2 / Rcp) / Jt
    d qb / dt  = -ib
    d qcp / dt = icp
    d qcs / dt = ics

discretised, as progpy's ``next_state`` does, by one explicit Euler step ``x + dt dx/dt``. The
end-of-discharge (EOD) event is ``v < VEOD``; progpy's event state is
``min(SOC, (v - VEOD) / VDropoff)``.

Conventions shared with progpy's simulator, so that trajectories and event times agree:

* the current of the step from ``t_{k-1}`` to ``t_k = t_{k-1} + dt`` is the load evaluated at the
  midpoint ``t_{k-1} + dt / 2`` (:func:`load_controls`);
* the event is checked after each step: the EOD time is the first ``t_k`` with ``v(x_k) < VEOD``.

progpy clips ``tb`` and ``qb`` at 0 in its simulator (``state_limits``). This model does not clip
(nothing in the library clips silently); both stay far above 0 before the end of discharge, so
trajectories up to the event are the same.

``Cb`` is evaluated by Horner's rule and the temperature rate in its reduced form above, which
are algebraically the forms progpy evaluates; the difference is rounding (relative ~1e-16).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable, Sequence
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
    check_positive_real,
    check_std,
    diag_chol,
    is_bool_or_complex,
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
    simulate_model,
)

__all__ = [
    "BatteryCircuitParams",
    "LOAD_TIMES",
    "LOAD_CURRENTS",
    "battery_circuit_rhs",
    "battery_circuit_step",
    "battery_circuit_output",
    "battery_voltage",
    "battery_event_state",
    "battery_eod_event",
    "battery_circuit_model",
    "piecewise_load",
    "load_controls",
    "simulate_battery",
]

#: Switching times (s) and currents (A) of progpy's documented battery example load: 2 A until
#: 600 s, 1 A until 900 s, 4 A until 1800 s, 2 A until 3000 s, 3 A after that.
LOAD_TIMES = (600.0, 900.0, 1800.0, 3000.0)
LOAD_CURRENTS = (2.0, 1.0, 4.0, 2.0, 3.0)

# progpy's UnscentedKalmanFilter defaults: Q = R = 1e-3 I.
_Q_STD = 1e-3**0.5
_R_STD = 1e-3**0.5


@dataclass(frozen=True)
class BatteryCircuitParams:
    """Parameters of the circuit model; defaults are progpy 1.9.0's ``BatteryCircuit`` defaults.

    Attributes:
        qMax: maximum charge (C). CMax: maximum capacity (C).
        VEOD: end-of-discharge voltage (V). VDropoff: voltage range of the event state (V).
        Rp: parasitic resistance (Ohm).
        Cbp0, Cbp1, Cbp2, Cbp3: coefficients of the capacitance ``Cb(SOC)`` (F).
        Rs, Cs: resistance (Ohm) and capacitance (F) of the surface R-C pair.
        Rcp0, Rcp1, Rcp2, Ccp: ``Rcp(SOC)`` coefficients (Ohm, Ohm, 1) and capacitance (F) of
            the concentration-polarisation R-C pair.
        Ta: ambient temperature (K). Jt: thermal capacity (J/K).
        ha, hcp, hcs: heat-transfer coefficients (ambient, Rcp pair, Rs pair).
        x0: full-charge initial state ``(tb, qb, qcp, qcs)``.
    """

    qMax: float = 7856.3254
    CMax: float = 7777.0
    VEOD: float = 3.0
    VDropoff: float = 0.1
    Rp: float = 1e4
    Cbp0: float = -230.0
    Cbp1: float = 1.2
    Cbp2: float = 2079.9
    Cbp3: float = 27.055726
    Rs: float = 0.0538926
    Cs: float = 234.387
    Rcp0: float = 0.0697776
    Rcp1: float = 1.50528e-17
    Rcp2: float = 37.223
    Ccp: float = 14.8223
    Ta: float = 292.1
    Jt: float = 800.0
    ha: float = 0.5
    hcp: float = 19.0
    hcs: float = 1.0
    x0: tuple[float, float, float, float] = (292.1, 7856.3254, 0.0, 0.0)

    def __post_init__(self):
        plain_params(self)  # a list x0 would leave the frozen (hashed) parameters mutable
        check_params_finite(self)
        check_positive(self, "qMax", "CMax", "VDropoff", "Rp", "Rs", "Cs", "Ccp", "Jt", "Ta")
        if not isinstance(self.x0, tuple) or len(self.x0) != 4:
            raise ValueError(f"BatteryCircuitParams.x0 must hold 4 numbers, got {self.x0!r}")


_STATE = "[tb, qb, qcp, qcs]"  # the state's components, named in messages


def _voltage_parts(x: Tensor, p: BatteryCircuitParams):
    """``tb, qb, Vcs, Vcp, v, SOC`` of the state ``x`` ``(..., 4)``; each ``(...)``."""
    tb, qb, qcp, qcs = check_state(x, 4, _STATE).unbind(-1)
    vcs = qcs * (1.0 / p.Cs)
    vcp = qcp * (1.0 / p.Ccp)
    soc = qb.mul(1.0 / p.CMax).add_((p.CMax - p.qMax) / p.CMax)
    cb = ((p.Cbp0 * soc + p.Cbp1) * soc + p.Cbp2) * soc + p.Cbp3
    v = (qb / cb).sub_(vcp).sub_(vcs)
    return tb, qb, vcs, vcp, v, soc


def _parts(x: Tensor, p: BatteryCircuitParams):
    """``tb, Vcs, Vcp, Rcp, v, SOC`` of the state ``x`` ``(..., 4)``; each ``(...)``."""
    tb, _, vcs, vcp, v, soc = _voltage_parts(x, p)
    rcp = torch.exp((1.0 - soc) * p.Rcp2).mul_(p.Rcp1).add_(p.Rcp0)
    return tb, vcs, vcp, rcp, v, soc


def _current(u: Tensor | None, x: Tensor) -> Tensor:
    """The current ``(...)`` of ``u`` ``(..., 1)``, whose leading shape broadcasts to ``x``'s."""
    if u is None:
        raise ValueError("the battery model needs the current u of shape (..., 1)")
    check_leading(u, "u", x, 1, numbers=False)  # (the current in A)
    return u.squeeze(-1)


def _rates(x: Tensor, u: Tensor, p: BatteryCircuitParams) -> Tensor:
    i = _current(u, check_state(x, 4, _STATE))
    tb, vcs, vcp, rcp, v, _ = _parts(x, p)
    ib = torch.add(i, v, alpha=1.0 / p.Rp)  # i + v / Rp
    g = vcp / rcp  # Vcp / Rcp
    # (ha (Ta - tb) + hcs Vcs^2 / Rs + hcp Vcp^2 / Rcp) / Jt
    dtb = (tb * (-p.ha / p.Jt)).add_(p.ha * p.Ta / p.Jt)
    dtb = dtb.addcmul_(vcs, vcs, value=p.hcs / (p.Rs * p.Jt)).addcmul_(g, vcp, value=p.hcp / p.Jt)
    return torch.stack([dtb, -ib, ib - g, torch.add(ib, vcs, alpha=-1.0 / p.Rs)], dim=-1)


def battery_circuit_rhs(x: Tensor, u: Tensor, params: BatteryCircuitParams | None = None) -> Tensor:
    """``dx/dt`` of the circuit model (module docstring).

    Args:
        x: ``(..., 4)`` states ``[tb, qb, qcp, qcs]``.
        u: ``(..., 1)`` currents (A), broadcastable to ``x[..., :1]``.
    Returns:
        ``(..., 4)`` rates ``[dtb, dqb, dqcp, dqcs] / dt``.
    """
    return _rates(x, u, params or BatteryCircuitParams())


@functools.lru_cache(maxsize=64)
def _step_constants(p: BatteryCircuitParams, dt: float, dtype: torch.dtype, device) -> tuple:
    """0-dim tensors of the step's additive constants (fused ``add``/``addcmul`` take them)."""

    def c(v: float) -> Tensor:
        return torch.tensor(v, dtype=dtype, device=device)

    return (
        c((p.CMax - p.qMax) / p.CMax),  # SOC offset
        c(p.Cbp1),
        c(p.Cbp2),
        c(p.Cbp3),
        c(p.Rcp0),
        c(dt * p.ha * p.Ta / p.Jt),  # ambient term of the temperature update
    )


@functools.lru_cache(maxsize=64)
def _stepper(p: BatteryCircuitParams, dt: float) -> Callable[..., Tensor]:
    """The Euler step of ``p`` and ``dt`` with every scalar factor computed once.

    Returns ``step(x (..., 4), u (..., 1), out=None) -> (..., 4)``; with ``out`` (a ``(..., 4)``
    tensor of ``x``'s dtype, any strides) the next state is written there and ``out`` returned.
    """
    a_soc, cbp0, rcp2, rcp1 = 1.0 / p.CMax, p.Cbp0, p.Rcp2, p.Rcp1
    i_ccp, m_cs, i_rp = 1.0 / p.Ccp, -1.0 / p.Cs, 1.0 / p.Rp
    a_tb = 1.0 - dt * p.ha / p.Jt
    c_cs = dt * p.hcs / (p.Rs * p.Jt * p.Cs * p.Cs)
    c_cp = dt * p.hcp / p.Jt
    d_cs = 1.0 - dt / (p.Cs * p.Rs)
    consts: dict = {}
    none4 = (None, None, None, None)

    def step(x: Tensor, u: Tensor, out: Tensor | None = None) -> Tensor:
        i = _current(u, x)
        key = (x.dtype, x.device)
        k = consts.get(key)
        if k is None:
            k = consts[key] = _step_constants(p, dt, x.dtype, x.device)
        soc0, cb1, cb2, cb3, rcp0, amb = k
        tb, qb, qcp, qcs = x.unbind(-1)
        soc = torch.add(soc0, qb, alpha=a_soc)
        cb = torch.addcmul(cb3, torch.addcmul(cb2, torch.add(cb1, soc, alpha=cbp0), soc), soc)
        rcp = torch.add(rcp0, torch.rsub(soc, rcp2, alpha=rcp2).exp_(), alpha=rcp1)
        vcp = qcp * i_ccp
        g = vcp / rcp  # Vcp / Rcp
        v = torch.add((qb / cb).sub_(vcp), qcs, alpha=m_cs)  # Vb - Vcp - Vcs
        ib = torch.add(i, v, alpha=i_rp)
        o = none4 if out is None else out.unbind(-1)
        # tb + dt (ha (Ta - tb) + hcs Vcs^2 / Rs + hcp Vcp^2 / Rcp) / Jt
        tb1 = torch.add(amb, tb, alpha=a_tb, out=o[0])
        tb1 = tb1.addcmul_(qcs, qcs, value=c_cs).addcmul_(g, vcp, value=c_cp)
        qb1 = torch.add(qb, ib, alpha=-dt, out=o[1])
        qcp1 = torch.add(qcp, ib, alpha=dt, out=o[2]).sub_(g, alpha=dt)
        qcs1 = torch.mul(qcs, d_cs, out=o[3]).add_(ib, alpha=dt)
        if out is not None:
            return out
        # stacked component-major and returned as a (..., 4) view: the next step's components
        # are then contiguous rows (no interleaving copy)
        return torch.stack([tb1, qb1, qcp1, qcs1], dim=0).movedim(0, -1)

    return step


def battery_circuit_step(
    x: Tensor,
    u: Tensor,
    dt: float,
    params: BatteryCircuitParams | None = None,
    *,
    out: Tensor | None = None,
) -> Tensor:
    """One Euler step ``x + dt * dx/dt`` (progpy's ``next_state``): ``(..., 4) -> (..., 4)``.

    The same equations as :func:`battery_circuit_rhs`, arranged for few tensor operations
    (the Monte-Carlo EOD prediction calls it once per step on all samples): scalar factors are
    folded into fused ``add``/``addcmul`` calls, ``tb`` and ``qcs`` enter their own updates as
    ``tb (1 - dt ha / Jt)`` and ``qcs (1 - dt / (Cs Rs))``. Equal to
    ``x + dt * battery_circuit_rhs(x, u)`` up to rounding. Without ``out`` the result is a
    ``(..., 4)`` view of component-major memory (not contiguous). With ``out`` (a ``(..., 4)``
    tensor of ``x``'s shape and dtype, any strides, not overlapping ``x``) the next state is
    written into it and ``out`` is returned (the same numbers; no stacking copy). ``out`` is for
    plain tensors (not under ``torch.func`` transforms). ``dt`` is a finite positive number.
    """
    check_state(x, 4, _STATE)
    check_positive_real(dt, "dt")
    if out is not None and (
        not isinstance(out, Tensor)
        or (out.shape, out.dtype, out.device) != (x.shape, x.dtype, x.device)
    ):
        got = (tuple(out.shape), out.dtype, out.device) if isinstance(out, Tensor) else type(out)
        raise ValueError(
            f"out must be a tensor of x's shape, dtype and device "
            f"{(tuple(x.shape), x.dtype, x.device)}, got {got}"
        )
    return _stepper(params or BatteryCircuitParams(), float(dt))(x, u, out)


def battery_voltage(x: Tensor, params: BatteryCircuitParams | None = None) -> Tensor:
    """Terminal voltage ``v = Vb - Vcp - Vcs`` (V) of ``x`` ``(..., 4)``: shape ``(...)``."""
    return _voltage_parts(x, params or BatteryCircuitParams())[4]


def battery_circuit_output(x: Tensor, params: BatteryCircuitParams | None = None) -> Tensor:
    """Outputs ``[t, v]`` (K, V) of ``x`` ``(..., 4)``: shape ``(..., 2)`` (progpy's ``output``)."""
    v = battery_voltage(x, params)  # (checks x)
    return torch.stack([x[..., 0], v], dim=-1)


def battery_event_state(x: Tensor, params: BatteryCircuitParams | None = None) -> Tensor:
    """progpy's EOD event state ``min(SOC, (v - VEOD) / VDropoff)``: ``(..., 4) -> (...)``."""
    p = params or BatteryCircuitParams()
    *_, v, soc = _voltage_parts(x, p)
    return torch.minimum(soc, (v - p.VEOD) / p.VDropoff)


def battery_eod_event(
    params: BatteryCircuitParams | None = None,
) -> Callable[[Tensor], Tensor]:
    """The end-of-discharge event ``v(x) < VEOD`` as ``event(x (..., 4)) -> bool (...)``.

    This is the ``event`` argument of :func:`prognos_torch.prognosis.simulate_to_event`.
    """
    p = params or BatteryCircuitParams()

    a_soc, cbp0, i_ccp, m_cs = 1.0 / p.CMax, p.Cbp0, -1.0 / p.Ccp, -1.0 / p.Cs
    consts: dict = {}

    def event(x: Tensor) -> Tensor:
        # v = Vb - Vcp - Vcs in fused operations (the step's arrangement, 9 tensor operations;
        # it is evaluated on every state of every step)
        key = (check_state(x, 4, _STATE).dtype, x.device)
        k = consts.get(key)
        if k is None:
            k = consts[key] = _step_constants(p, 1.0, x.dtype, x.device)
        soc0, cb1, cb2, cb3 = k[:4]
        _, qb, qcp, qcs = x.unbind(-1)
        soc = torch.add(soc0, qb, alpha=a_soc)
        cb = torch.addcmul(cb3, torch.addcmul(cb2, torch.add(cb1, soc, alpha=cbp0), soc), soc)
        v = torch.div(qb, cb).add_(qcp, alpha=i_ccp).add_(qcs, alpha=m_cs)
        return v < p.VEOD

    return event


def battery_circuit_model(
    dt: float = 1.0,
    *,
    params: BatteryCircuitParams | None = None,
    process_noise_std=_Q_STD,
    measurement_noise_std=_R_STD,
    dtype=torch.float64,
    device=None,
) -> StateSpaceModel:
    """The circuit model as a :class:`StateSpaceModel` (states in progpy's order, current as control).

    ``f(x, u, k) = x + dt * dx/dt`` (:func:`battery_circuit_step`, ``u = [i]``,
    ``control_dim = 1``), ``h(x, u, k) = [tb, v]`` (:func:`battery_circuit_output`). The model is
    written for arbitrary leading dimensions (``batched=True``); ``model.transition`` and
    ``model.observe`` evaluate it on ``(..., 4)``, and ``model.transition_into`` writes the step
    into a given tensor (``f_into``: :func:`battery_circuit_step` with ``out``).

    Args:
        dt: step length (s), positive.
        params: :class:`BatteryCircuitParams` (progpy's defaults).
        process_noise_std: per-step std of ``w_k`` (one number or 4), i.e. ``chol_Q = diag``. The
            default ``sqrt(1e-3)`` gives progpy's ``UnscentedKalmanFilter`` default ``Q = 1e-3 I``.
            (progpy's simulator adds ``dt * N(0, process_noise)`` per step: for ``dt != 1`` pass
            ``dt * process_noise`` here.)
        measurement_noise_std: std of ``v_k`` (one number or 2); default ``sqrt(1e-3)``, progpy's
            UKF default ``R = 1e-3 I``.
    """
    p = params or BatteryCircuitParams()
    check_positive_real(dt, "dt")
    dt = float(dt)
    check_dtype_arg(dtype)
    SQ = diag_chol(check_std(process_noise_std, 4, "process_noise_std"), dtype, device)
    SR = diag_chol(check_std(measurement_noise_std, 2, "measurement_noise_std"), dtype, device)

    step = _stepper(p, dt)

    def f(x, u, k):
        return step(x, u)

    def f_into(x, u, k, out):
        return step(x, u, out)

    def h(x, u, k):
        return battery_circuit_output(x, p)

    return StateSpaceModel(
        f=f,
        h=h,
        state_dim=4,
        obs_dim=2,
        chol_Q=SQ,
        chol_R=SR,
        control_dim=1,
        batched=True,
        f_into=f_into,
    )


def piecewise_load(
    times: Sequence[float] = LOAD_TIMES, values: Sequence[float] = LOAD_CURRENTS
) -> Callable[[Tensor], Tensor]:
    """A piecewise-constant load ``t -> value``: ``values[j]`` for ``times[j-1] <= t < times[j]``.

    ``values`` has one more entry than ``times`` (the last holds after the last switch), as
    progpy's ``Piecewise`` loading. The default is progpy's battery example load
    (:data:`LOAD_TIMES`, :data:`LOAD_CURRENTS`). The returned function maps a tensor of times
    ``(...)`` to ``(...)``.
    """
    ts, vs = _numbers(times, "times"), _numbers(values, "values")
    if len(vs) != len(ts) + 1:
        raise ValueError(
            f"values must have one more entry than times, got {len(vs)} values for {len(ts)} times"
        )
    if any(not math.isfinite(t) for t in ts) or any(b <= a for a, b in zip(ts, ts[1:])):
        raise ValueError(f"times must be finite and strictly increasing, got {tuple(ts)}")
    if any(not math.isfinite(v) for v in vs):
        raise ValueError(f"values must be finite, got {tuple(vs)}")

    def load(t: Tensor) -> Tensor:
        t = torch.as_tensor(t, dtype=torch.float64)
        edges = torch.tensor(ts, dtype=t.dtype, device=t.device)
        table = torch.tensor(vs, dtype=t.dtype, device=t.device)
        value = table[torch.bucketize(t, edges, right=True)]
        return value.masked_fill_(t.isnan(), math.nan)  # a missing time has a missing load

    return load


def _numbers(seq, name: str) -> list[float]:
    """``seq`` (a sequence, array or tensor of real numbers; not text or bools) as floats."""
    if isinstance(seq, Tensor):
        seq = seq.tolist() if seq.dim() == 1 and not is_bool_or_complex(seq) else [seq]
    if isinstance(seq, (str, bytes)) or not hasattr(seq, "__iter__"):
        raise TypeError(f"{name} must be a sequence of numbers, got {seq!r}")
    vals = list(seq)
    if not all(is_real(v) for v in vals):
        raise TypeError(f"{name} must be a sequence of real numbers, got {seq!r}")
    return [float(v) for v in vals]


def load_controls(
    steps: int = 10_000,
    *,
    load: Callable[[Tensor], Tensor] | None = None,
    dt: float = 1.0,
    t0: float = 0.0,
    dtype=torch.float64,
    device=None,
) -> Tensor:
    """Controls ``(steps, 1)`` for steps ``k = 1..steps`` from ``t0``: ``u_k = load(t0 + (k - 1/2) dt)``.

    The midpoint rule is progpy's: the load of the step from ``t_{k-1}`` to ``t_k`` is read at
    ``t_{k-1} + dt / 2``. ``load`` defaults to :func:`piecewise_load` (progpy's example load);
    it must map the ``(steps,)`` times to ``(steps,)`` (or ``(steps, 1)``) currents.
    """
    steps = check_count(steps, "steps")
    check_positive_real(dt, "dt")
    if not is_real(t0) or not math.isfinite(t0):
        raise ValueError(f"t0 must be a finite number, got {t0!r}")
    check_dtype_arg(dtype)
    load = load or piecewise_load()
    k = torch.arange(1, steps + 1, dtype=torch.float64)
    t_mid = (k - 0.5) * float(dt) + float(t0)
    i = load(t_mid)
    if not isinstance(i, Tensor) or tuple(i.shape) not in ((steps,), (steps, 1)):
        got = tuple(i.shape) if isinstance(i, Tensor) else type(i).__name__
        raise ValueError(f"load must map the ({steps},) times to ({steps},) currents, got {got}")
    return i.to(dtype=dtype, device=device).reshape(steps, 1)


def simulate_battery(
    n_steps: int,
    runs: int = 1,
    *,
    params: BatteryCircuitParams | None = None,
    x0=None,
    u=None,
    dt: float = 1.0,
    noise: bool = True,
    process_noise_std=0.0,
    measurement_noise_std=_R_STD,
    generator: torch.Generator | None = None,
    dtype=torch.float64,
    device=None,
) -> SimulationResult:
    """Simulate ``runs`` discharges of the circuit model for ``n_steps`` steps of ``dt``.

    Args:
        x0: ``(4,)`` or ``(runs, 4)`` initial state; default the full charge ``params.x0``.
        u: ``(T, 1)`` or ``(T, runs, 1)`` currents; default :func:`load_controls` of progpy's
            example load.
        process_noise_std: per-step process-noise std (default 0: progpy's model default).
        measurement_noise_std: std of the ``[t, v]`` measurements (default ``sqrt(1e-3)``).
        noise: ``False`` switches all noise off (no generator needed).
    Returns:
        :class:`SimulationResult` with ``x`` ``(T+1, runs, 4)``, ``y`` ``(T, runs, 2)``,
        ``u`` ``(T, runs, 1)``, ``t = k dt``. The run is not stopped at the EOD event.
    """
    p = params or BatteryCircuitParams()
    check_count(n_steps, "n_steps")
    check_count(runs, "runs")
    check_dtype_arg(dtype)
    gen = resolve_generator(generator, check_flag(noise, "noise"))
    X0 = initial_state(p.x0 if x0 is None else x0, 4, runs, dtype, device)
    if u is None:
        u = load_controls(steps=n_steps, dt=dt, dtype=dtype, device=device)
    U = input_sequence(u, n_steps, runs, 1, dtype, device)  # (as every simulator: finite)
    model = battery_circuit_model(
        dt,
        params=p,
        process_noise_std=process_noise_std,
        measurement_noise_std=measurement_noise_std,
        dtype=dtype,
        device=device,
    )
    e_w = e_v = None
    if gen is not None:
        e_w, e_v = draw_run_noise(
            gen, runs, n_steps, [("normal", (4,)), ("normal", (2,))], dtype=dtype, device=device
        )
    x, y = simulate_model(model, X0, n_steps, e_w=e_w, e_v=e_v, u=U)
    return SimulationResult(
        t=torch.arange(n_steps + 1, dtype=dtype, device=device) * float(dt),
        x=x,
        y=y,
        theta=x.new_zeros(n_steps + 1, runs, 0),
        u=U,
        meta={
            "system": "battery_circuit",
            "paper": "Daigle & Sankararaman 2013 (progpy BatteryCircuit)",
            "equations": "equivalent circuit, explicit Euler",
            "dt": float(dt),
            "time_unit": "s",
            "state_names": ("tb", "qb", "qcp", "qcs"),
            "measurement_names": ("t", "v"),
            "param_names": (),
            "process_noise_std": check_std(process_noise_std, 4, "process_noise_std"),
            "measurement_noise_std": check_std(measurement_noise_std, 2, "measurement_noise_std"),
            "noise": noise,
        },
    )
