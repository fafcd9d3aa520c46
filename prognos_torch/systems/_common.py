"""Pieces shared by the system simulators: integrators, the result record, argument checks,
per-run noise streams and the one simulation loop that every system uses.

Every simulator in :mod:`prognos_torch.systems` first builds the :class:`StateSpaceModel` a filter
would receive and then runs :func:`simulate_model` on it, so the simulated truth and the filter's
model are the same code (``x_k = f(x_{k-1}, u_k, k) + w_k``, ``y_k = h(x_k, u_k, k) + v_k``).

Random streams (used by every simulator): the caller's ``generator`` is asked for one 62-bit seed
per Monte Carlo run (``torch.randint``, drawn in run order); run ``r`` then draws all of its noise
from a private generator seeded with seed ``r``, in a fixed order (process noise ``(T, n)``,
measurement noise ``(T, m)``, then any system-specific draws). Hence a batch of ``R`` runs equals
``R`` successive single-run calls with the same generator, and run ``r`` does not depend on ``R``.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, fields
from fractions import Fraction
from types import MappingProxyType
from typing import NamedTuple

import torch
from torch import Tensor

from ..core.model import StateSpaceModel

__all__ = [
    "SimulationResult",
    "NormalizedSeries",
    "rk4_step",
    "euler_step",
    "simulate_model",
    "draw_run_noise",
    "minmax_normalize",
    "minmax_denormalize",
]


# --------------------------------------------------------------------------- integrators
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


# --------------------------------------------------------------------------- result record
@dataclass(frozen=True, eq=False)
class SimulationResult:
    """A batch of simulated runs, time leading.

    Attributes:
        t: ``(T + 1,)`` sample times ``t_k = k * dt`` for ``k = 0..T`` (in the system's time unit).
        x: ``(T + 1, runs, n)`` true states ``x_0 .. x_T`` (row 0 is the initial state).
        y: ``(T, runs, m)`` measurements ``y_1 .. y_T`` (row ``k - 1`` holds ``y_k``).
        theta: ``(T + 1, runs, d)`` true parameter / fault values ``theta_0 .. theta_T``, aligned
            with ``x`` so that ``torch.cat([x, theta], -1)`` is the true augmented state of the
            system's joint model (``d = 0`` for systems without one).
        u: ``(T, runs, p)`` inputs ``u_1 .. u_T`` passed to the model, or ``None``.
        meta: read-only mapping: system name, paper and equation numbers, step size, names of the
            state / measurement / parameter components, the readings chosen where the paper is
            ambiguous, and system-specific extras.
    """

    t: Tensor
    x: Tensor
    y: Tensor
    theta: Tensor
    u: Tensor | None
    meta: Mapping[str, object]

    def __post_init__(self):
        object.__setattr__(self, "meta", MappingProxyType(dict(self.meta)))

    @property
    def n_steps(self) -> int:
        """``T``."""
        return self.y.shape[0]

    @property
    def runs(self) -> int:
        return self.x.shape[1]


# --------------------------------------------------------------------------- checks
def check_params_finite(obj) -> None:
    """``ValueError`` naming the first field of a parameter dataclass that is not finite."""
    for f in fields(obj):
        v = getattr(obj, f.name)
        vals = v if isinstance(v, (tuple, list)) else (v,)
        flat = []
        for e in vals:
            flat.extend(e if isinstance(e, (tuple, list)) else (e,))
        for e in flat:
            if isinstance(e, bool) or not isinstance(e, (int, float)):
                raise TypeError(f"{type(obj).__name__}.{f.name} must be a real number, got {e!r}")
            if not math.isfinite(e):
                raise ValueError(f"{type(obj).__name__}.{f.name} must be finite, got {v!r}")


def check_positive(obj, *names: str) -> None:
    for name in names:
        v = getattr(obj, name)
        vals = v if isinstance(v, (tuple, list)) else (v,)
        if any(e <= 0 for e in vals):
            raise ValueError(f"{type(obj).__name__}.{name} must be > 0, got {v!r}")


def check_count(value, name: str, minimum: int = 1) -> int:
    """A Python ``int`` ``>= minimum`` (``bool`` rejected)."""
    if isinstance(value, bool) or not isinstance(value, int):
        raise TypeError(f"{name} must be an int >= {minimum}, got {value!r}")
    if value < minimum:
        raise ValueError(f"{name} must be an int >= {minimum}, got {value}")
    return value


def check_std(value, n: int, name: str) -> tuple[float, ...]:
    """A standard deviation given as one number or ``n`` numbers, finite and ``>= 0``."""
    if isinstance(value, Tensor):
        value = value.detach().cpu().reshape(-1).tolist()
    vals = (value,) * n if isinstance(value, (int, float)) else tuple(value)
    if len(vals) != n:
        raise ValueError(f"{name} must be a number or a sequence of {n} numbers, got {value!r}")
    for v in vals:
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise TypeError(f"{name} must contain real numbers, got {value!r}")
        if not math.isfinite(v) or v < 0:
            raise ValueError(f"{name} must be finite and >= 0, got {value!r}")
    return tuple(float(v) for v in vals)


def diag_chol(std: Sequence[float], dtype, device) -> Tensor:
    return torch.diag(torch.tensor(list(std), dtype=dtype, device=device))


def as_chol(value, d: int, name: str, dtype, device) -> Tensor:
    """A ``(d, d)`` square-root factor from a number (``std * I``), ``d`` stds or a matrix."""
    if isinstance(value, Tensor) and value.dim() == 2:
        S = value.to(dtype=dtype, device=device)
        if tuple(S.shape) != (d, d):
            raise ValueError(f"{name} must have shape ({d}, {d}), got {tuple(S.shape)}")
        if not bool(torch.isfinite(S).all()):
            raise ValueError(f"{name} contains non-finite values")
        if not bool(torch.equal(S, torch.tril(S))):
            raise ValueError(f"{name} must be lower triangular, shape ({d}, {d})")
        return S
    return diag_chol(check_std(value, d, name), dtype, device)


def initial_state(x0, n: int, runs: int, dtype, device, name: str = "x0") -> Tensor:
    """``x0`` of shape ``(n,)`` (shared) or ``(runs, n)`` -> finite ``(runs, n)`` tensor."""
    if not isinstance(x0, Tensor):
        try:
            x0 = torch.as_tensor(x0, dtype=dtype, device=device)
        except (TypeError, ValueError, RuntimeError) as exc:
            raise TypeError(f"{name} must be a tensor of shape ({n},) or ({runs}, {n})") from exc
    x0 = x0.to(dtype=dtype, device=device)
    if tuple(x0.shape) == (n,):
        x0 = x0.expand(runs, n)
    elif tuple(x0.shape) != (runs, n):
        raise ValueError(
            f"{name} must have shape ({n},) or (runs, {n}) = ({runs}, {n}), got {tuple(x0.shape)}"
        )
    if not bool(torch.isfinite(x0).all()):
        raise ValueError(f"{name} contains non-finite values")
    return x0.clone()


def input_sequence(u, n_steps: int, runs: int, p: int, dtype, device) -> Tensor | None:
    """``u`` of shape ``(T, p)`` (shared by all runs) or ``(T, runs, p)`` -> ``(T, runs, p)``."""
    if u is None:
        return None
    if not isinstance(u, Tensor):
        u = torch.as_tensor(u, dtype=dtype, device=device)
    u = u.to(dtype=dtype, device=device)
    if tuple(u.shape) == (n_steps, p):
        u = u.unsqueeze(1).expand(n_steps, runs, p)
    elif tuple(u.shape) != (n_steps, runs, p):
        raise ValueError(
            f"u must have shape (T, {p}) or (T, runs, {p}) = ({n_steps}, {runs}, {p}), "
            f"got {tuple(u.shape)}"
        )
    if not bool(torch.isfinite(u).all()):
        raise ValueError("u contains non-finite values")
    return u


def resolve_generator(generator, noise: bool) -> torch.Generator | None:
    if not noise:
        return None
    if not isinstance(generator, torch.Generator):
        raise ValueError(
            "generator must be a torch.Generator when noise=True (pass noise=False for a "
            f"noise-free run), got {generator!r}"
        )
    return generator


# --------------------------------------------------------------------------- noise streams
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
    """
    seeds = torch.randint(0, 2**62, (runs,), generator=generator, device=generator.device)
    out: list[list[Tensor]] = [[] for _ in draws]
    for seed in seeds.tolist():
        g = torch.Generator(device=device if device is not None else "cpu").manual_seed(seed)
        for j, (kind, shape) in enumerate(draws):
            size = (n_steps, *shape)
            if kind == "normal":
                out[j].append(torch.randn(size, generator=g, dtype=dtype, device=device))
            elif kind == "uniform":
                out[j].append(torch.rand(size, generator=g, dtype=dtype, device=device))
            else:
                raise ValueError(f"draw kind must be 'normal' or 'uniform', got {kind!r}")
    return [torch.stack(parts, dim=1) for parts in out]


# --------------------------------------------------------------------------- the loop
def _at(v, k: int):
    return v(k) if callable(v) else v


def _times(L: Tensor, e: Tensor) -> Tensor:
    """``L @ e`` for each row of ``e`` (..., n), written elementwise: the result of a run does
    not depend on how many runs share the call (BLAS blocking does), and tiny matrices avoid
    slow BLAS paths."""
    return (L * e.unsqueeze(-2)).sum(-1)


def simulate_model(
    model: StateSpaceModel,
    x0: Tensor,
    n_steps: int,
    *,
    e_w: Tensor | None = None,
    e_v: Tensor | None = None,
    u: Tensor | None = None,
    y_offset: Tensor | None = None,
) -> tuple[Tensor, Tensor]:
    """Run ``x_k = f(x_{k-1}, u_k, k) + w_k``, ``y_k = h(x_k, u_k, k) + v_k`` for ``k = 1..T``.

    ``w_k = q_k + chol_Q(k) e_w[k-1]`` and ``v_k = r_k + chol_R(k) e_v[k-1]`` (noise off where
    ``e_w`` / ``e_v`` is ``None``), so that ``w_k ~ N(q_k, Q_k)`` exactly as the model states.

    Args:
        model: the system's :class:`StateSpaceModel`.
        x0: ``(runs, n)`` initial states.
        e_w: ``(T, runs, n)`` standard normal draws or ``None``.
        e_v: ``(T, runs, m)`` standard normal draws or ``None``.
        u: ``(T, runs, p)`` inputs (row ``k - 1`` is ``u_k``) or ``None``.
        y_offset: ``(T, runs, m)`` extra additive measurement terms (e.g. paper 004's
            ``Delta E_k``) or ``None``.
    Returns:
        ``x`` ``(T + 1, runs, n)`` and ``y`` ``(T, runs, m)``.
    """
    xs = [x0]
    ys = []
    x = x0
    for k in range(1, n_steps + 1):
        uk = None if u is None else u[k - 1]
        x = model.transition(x, uk, k)
        if e_w is not None:
            noise = model.noise(k)
            x = x + _times(noise.chol_Q, e_w[k - 1])
            if noise.q is not None:
                x = x + noise.q
        xs.append(x)
        y = model.observe(x, uk, k)
        if e_v is not None:
            noise = model.noise(k)
            y = y + _times(noise.chol_R, e_v[k - 1])
            if noise.r is not None:
                y = y + noise.r
        if y_offset is not None:
            y = y + y_offset[k - 1]
        ys.append(y)
    return torch.stack(xs), torch.stack(ys)


# --------------------------------------------------------------------------- normalisation
class NormalizedSeries(NamedTuple):
    """``values = (series - lo) / (hi - lo)``; ``lo``/``hi`` are kept to undo the scaling."""

    values: Tensor
    lo: Tensor
    hi: Tensor


def minmax_normalize(series: Tensor, lo=None, hi=None) -> NormalizedSeries:
    """Affine min-max scaling to ``[0, 1]`` (paper 003 Sec. V: "normalized into 0 to 1").

    By default ``lo``/``hi`` are the minimum and maximum over the whole ``series`` (paper 003
    scales all 1000 Lorenz / all CSTR points at once, test part included). Pass ``lo``/``hi``
    (e.g. from the training part only) to avoid that look-ahead; values outside ``[lo, hi]`` then
    map outside ``[0, 1]`` and are not clipped.

    Args:
        series: ``(N, ...)``; the extremes are taken over dim 0 (per column).
    """
    if not isinstance(series, Tensor) or series.dim() < 1 or series.shape[0] < 1:
        raise ValueError("series must be a tensor of shape (N, ...) with N >= 1")
    if not bool(torch.isfinite(series).all()):
        raise ValueError("series contains non-finite values")
    lo = series.amin(0) if lo is None else torch.as_tensor(lo, dtype=series.dtype).to(series)
    hi = series.amax(0) if hi is None else torch.as_tensor(hi, dtype=series.dtype).to(series)
    if not bool((hi > lo).all()):
        raise ValueError("minmax_normalize needs hi > lo (a constant series cannot be scaled)")
    return NormalizedSeries((series - lo) / (hi - lo), lo, hi)


def minmax_denormalize(values: Tensor, lo: Tensor, hi: Tensor) -> Tensor:
    """Inverse of :func:`minmax_normalize`: ``values * (hi - lo) + lo``."""
    return values * (hi - lo) + lo


def accelerating_drift(k: int, base: float, rate: float, k_fault: int) -> float:
    """Closed form of the drift recursion ``d_k = d_{k-1} + rate (k - k_fault)`` for ``k > k_fault``,
    ``d_k = base`` before (paper 000 Eq. 61, paper 003 Eq. 51):
    ``base + rate (k - k_fault)(k - k_fault + 1) / 2``.

    Evaluated in exact rational arithmetic on the decimal values and rounded once: the correctly
    rounded value of the recursion (no accumulated floating-point error).
    """
    j = k - k_fault
    if j <= 0:
        return float(base)
    return float(Fraction(repr(float(base))) + Fraction(repr(float(rate))) * (j * (j + 1) // 2))


def simulate_with_parameter(
    model,
    X0: Tensor,
    n_steps: int,
    runs: int,
    generator: torch.Generator | None,
    theta_at: Callable[[int], float],
    dt: float,
    *,
    u: Tensor | None = None,
    dtype=torch.float64,
    device=None,
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Per-run noise draws, the shared simulation loop and the true scalar parameter path.

    Returns ``t`` ``(T + 1,)``, ``x`` ``(T + 1, runs, n)``, ``y`` ``(T, runs, m)`` and
    ``theta`` ``(T + 1, runs, 1)`` with ``theta[k] = theta_at(k)`` (no noise when ``generator`` is
    ``None``).
    """
    e_w = e_v = None
    if generator is not None:
        shapes = [("normal", (model.state_dim,)), ("normal", (model.obs_dim,))]
        e_w, e_v = draw_run_noise(generator, runs, n_steps, shapes, dtype=dtype, device=device)
    x, y = simulate_model(model, X0, n_steps, e_w=e_w, e_v=e_v, u=u)
    vals = [theta_at(k) for k in range(n_steps + 1)]
    theta = torch.tensor(vals, dtype=dtype, device=device)[:, None, None].expand(-1, runs, 1)
    t = torch.arange(n_steps + 1, dtype=dtype, device=device) * dt
    return t, x, y, theta.clone()
