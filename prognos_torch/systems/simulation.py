"""The one simulation loop every system uses, its result record and its inputs.

Every simulator in :mod:`prognos_torch.systems` first builds the :class:`StateSpaceModel` a filter
would receive and then runs :func:`simulate_model` on it, so the simulated truth and the filter's
model are the same code (``x_k = f(x_{k-1}, u_k, k) + w_k``, ``y_k = h(x_k, u_k, k) + v_k``).
Noise comes from the per-run streams of :mod:`prognos_torch.systems.noise_streams`.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, fields
from fractions import Fraction
from types import MappingProxyType

import torch
from torch import Tensor

from ..core.model import StateSpaceModel
from ..core.validation import (
    broadcast_shape,
    check_flag,
    is_bool_or_complex,
    is_int,
    plain_number,
)
from .noise_streams import draw_run_noise

__all__ = [
    "SimulationResult",
    "simulate_model",
    "simulate_with_parameter",
    "accelerating_drift",
    "initial_state",
    "input_sequence",
    "resolve_generator",
]


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


# --------------------------------------------------------------------------- inputs
def _check_device(v: Tensor, name: str, device) -> None:
    """A tensor argument on the simulation's ``device`` (``None``: torch's default device);
    nothing is moved between devices (an array or list is created there)."""
    want = torch.empty(0, device=device).device  # ("cuda" -> "cuda:<current>")
    if v.device != want:
        raise ValueError(
            f"{name} is on {v.device} but the simulation runs on {want} (device={device!r}): "
            f"create {name} on {want}"
        )


def initial_state(x0, n: int, runs: int, dtype, device, name: str = "x0") -> Tensor:
    """``x0`` of shape ``(n,)`` (shared) or ``(runs, n)`` -> finite ``(runs, n)`` tensor on
    ``device`` (a tensor ``x0`` must be there already)."""
    if is_bool_or_complex(x0):  # (a cast read True as 1 or dropped the imaginary part)
        raise TypeError(f"{name} must hold real numbers, got {getattr(x0, 'dtype', x0)!r}")
    if isinstance(x0, Tensor):
        _check_device(x0, name, device)
    else:
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
    """``u`` of shape ``(T, p)`` (shared by all runs) or ``(T, runs, p)`` -> ``(T, runs, p)`` on
    ``device`` (a tensor ``u`` must be there already)."""
    if u is None:
        return None
    if is_bool_or_complex(u):  # (a cast read True as 1 or dropped the imaginary part)
        raise TypeError(f"u must hold real numbers, got {getattr(u, 'dtype', u)!r}")
    if isinstance(u, Tensor):
        _check_device(u, "u", device)
    else:
        try:
            u = torch.as_tensor(u, dtype=dtype, device=device)
        except (TypeError, ValueError, RuntimeError):
            raise TypeError(
                f"u must be a tensor or an array of numbers (T, {p}) or (T, runs, {p}), got "
                f"{type(u).__name__}"
            ) from None
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
    """``generator`` where ``noise`` (a bool: ``noise="no"`` is refused, not read as true), else
    ``None``."""
    if not check_flag(noise, "noise"):
        return None
    if not isinstance(generator, torch.Generator):
        # a missing generator is a ValueError, an object of another type a TypeError (an int
        # seed, a NumPy Generator)
        err = ValueError if generator is None else TypeError
        raise err(
            "generator must be a torch.Generator when noise=True (pass noise=False for a "
            f"noise-free run), got {type(generator).__name__}"
        )
    return generator


def _plain(v):
    """A parameter value with NumPy numbers as Python ones and lists as tuples (the same
    numbers; a frozen dataclass then holds what the Python values would give)."""
    if isinstance(v, (tuple, list)):
        return tuple(_plain(e) for e in v)
    return plain_number(v)


def check_state(x, n: int, names: str, name: str = "x") -> Tensor:
    """A floating-point state tensor ``(..., n)`` (``names`` spells its components, ``name``
    the argument), refused otherwise (a wider state was read by its first ``n`` components)."""
    if not isinstance(x, Tensor) or not x.is_floating_point():
        got = x.dtype if isinstance(x, Tensor) else type(x).__name__
        raise TypeError(f"{name} must be a floating-point tensor (..., {n}) {names}, got {got}")
    if x.dim() == 0 or x.shape[-1] != n:
        raise ValueError(f"{name} must have shape (..., {n}) {names}, got {tuple(x.shape)}")
    return x


def check_leading(
    v, name: str, x: Tensor, tail: int = 0, *, state: str = "x", numbers: bool = True
) -> None:
    """A tensor ``v`` ``(..., tail)`` (``tail = 0``: ``(...)``) whose leading shape broadcasts to
    the leading shape of the state ``x`` ``(..., n)`` without widening it: a wider one gave the
    rate or measurement another shape than ``x``. ``state`` names ``x`` in the messages; a
    number passes unless ``numbers=False`` (then a ``TypeError``)."""
    want = "(...)" if tail == 0 else f"(..., {tail})"
    if not isinstance(v, Tensor):
        if numbers:
            return
        raise TypeError(f"{name} must be a tensor of shape {want}, got {type(v).__name__}")
    if tail and (v.dim() == 0 or v.shape[-1] != tail):
        raise ValueError(f"{name} must have shape {want}, got {tuple(v.shape)}")
    lead = x.shape[:-1]
    vlead = v.shape if tail == 0 else v.shape[:-1]
    if vlead != lead:
        try:
            ok = broadcast_shape(vlead, lead) == lead
        except ValueError:
            ok = False
        if not ok:
            raise ValueError(
                f"{name} must have shape {want} with leading dimensions that broadcast to "
                f"{state}'s without widening them: {name} {tuple(v.shape)} must broadcast to "
                f"{state}'s leading shape {tuple(lead)}"
            )


def resolve_params(params, cls):
    """``params`` (a ``cls``) or ``cls()`` where ``None``; anything else is a ``TypeError``
    (a dict failed on a missing attribute, an empty one gave the defaults)."""
    if params is None:
        return cls()
    if not isinstance(params, cls):
        raise TypeError(f"params must be a {cls.__name__} or None, got {type(params).__name__}")
    return params


def plain_params(obj, *, scalars: bool = False) -> None:
    """Replace the fields of the frozen parameter dataclass ``obj`` by :func:`_plain` values;
    with ``scalars`` a sequence in a field is a ``TypeError`` (``(0.02,)`` failed later, in
    the integrator or the right-hand side)."""
    for f in fields(obj):
        v = getattr(obj, f.name)
        if scalars and isinstance(v, (tuple, list)):
            raise TypeError(f"{type(obj).__name__}.{f.name} must be a real number, got {v!r}")
        object.__setattr__(obj, f.name, _plain(v))


# --------------------------------------------------------------------------- the loop
def _times(L: Tensor, e: Tensor) -> Tensor:
    """``L @ e`` for each row of ``e`` (..., n), written elementwise: the result of a run does
    not depend on how many runs share the call (BLAS blocking does), and tiny matrices avoid
    slow BLAS paths."""
    return (L * e.unsqueeze(-2)).sum(-1)


def _add_noise(v: Tensor, chol: Tensor, e: Tensor, mean: Tensor | None) -> Tensor:
    """``v + chol e``, then ``+ mean`` when the noise has one (in this order)."""
    v = v + _times(chol, e)
    return v if mean is None else v + mean


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
            x = _add_noise(x, noise.chol_Q, e_w[k - 1], noise.q)
        xs.append(x)
        y = model.observe(x, uk, k)
        if e_v is not None:
            noise = model.noise(k)
            y = _add_noise(y, noise.chol_R, e_v[k - 1], noise.r)
        if y_offset is not None:
            y = y + y_offset[k - 1]
        ys.append(y)
    return torch.stack(xs), torch.stack(ys)


# --------------------------------------------------------------------------- parameter paths
def accelerating_drift(k: int, base: float, rate: float, k_fault: int) -> float:
    """Closed form of the drift recursion ``d_k = d_{k-1} + rate (k - k_fault)`` for ``k > k_fault``,
    ``d_k = base`` before (paper 000 Eq. 61, paper 003 Eq. 51):
    ``base + rate (k - k_fault)(k - k_fault + 1) / 2``.

    Evaluated in exact rational arithmetic on the decimal values and rounded once: the correctly
    rounded value of the recursion (no accumulated floating-point error).
    """
    if not is_int(k):  # (k = 52.5 gave the drift of a step between 52 and 53)
        raise TypeError(f"k must be an int (a step index), got {k!r}")
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
