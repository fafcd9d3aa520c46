"""Synthetic run-to-failure indicators from degradation processes outside the trend models.

:func:`~prognos_torch.workflow.prognose` fits local-trend models to ``log(y - phi)``
(:mod:`prognos_torch.prognosis.trends`). Judging it only on data drawn from those models would
flatter it; these generators draw from *other* degradation processes, so that rules chosen on
them (e.g. ``method="auto"``) are chosen on data the models do not contain, and real bearings
stay a held-out check. Four families, each a healthy level ``y_0`` until a random onset
``t_on`` and a degradation ``D(s)``, ``s = max(0, t - t_on)``, that rises from 0 at ``s = 0``
to ``F - y_0`` at the end of the record ``s = S`` (``F``: the final level; ``"two_phase"``
before its wander)::

    y(t) = y_0 + D(s) + e(t)

``"shocks"``  monotone compound-Poisson damage (shock models, Esary et al. 1973; the
              jump-process counterpart of the gamma process of van Noortwijk 2009): jumps of
              exponential size at the event times of a Poisson process of intensity
              ``lambda(s) ~ s^(b-1)`` (``b in [1, 2.5]``: a rate that grows), scaled so that
              ``D(S) = F - y_0``.
``"paris"``   crack growth by the Paris-Erdogan law ``da/ds = C (dK)^m``, ``dK ~ sqrt(a)``,
              ``m in [2.5, 4]``: ``a(s) = (a_0^e - k s)^(1/e)``, ``e = 1 - m/2 < 0`` (finite-time
              blow-up, faster than any exponential), ``D ~ a - a_0``; multiplicative noise.
``"two_phase"`` a two-stage exponential (Wang et al. 2012's two-phase degradation): rate
              ``b_1`` until a change at ``s_c``, a jump by the factor ``J in [1.5, 3]``, then a
              faster rate ``b_2``, times ``exp(c(t))`` with ``c`` a stationary AR(1) wander.
``"hump"``    an exponential with a transient bump ``1 + A exp(-((s - s_h)/w)^2)``, the rise and
              fall that defects show when their edges wear smooth (the "healing" of bearing
              indicators).

The measurement noise ``e`` is Gaussian or Student-t (3 or 5 degrees of freedom, scaled to the
same standard deviation ``sigma = y_0 x U(noise)``), i.i.d. Times are regular steps ``dt``
(default 10 minutes in days, as the IMS snapshots) with up to 3 recording gaps of 20-200 steps.
Every draw comes from the given :class:`torch.Generator`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from ..core.validation import check_flag, check_positive_real, check_seed, is_int, is_real

__all__ = ["RUN_TO_FAILURE_FAMILIES", "RunToFailure", "simulate_run_to_failure",
           "run_to_failure_set"]  # fmt: skip

RUN_TO_FAILURE_FAMILIES = ("shocks", "paris", "two_phase", "hump")


@dataclass(frozen=True)
class RunToFailure:
    """One synthetic run-to-failure record.

    Attributes:
        t: ``(T,)`` strictly increasing times (days); y: ``(T,)`` indicator values.
        family: one of :data:`RUN_TO_FAILURE_FAMILIES`.
        onset: the true degradation onset ``t_on``.
        degradation: ``(T,)`` the noise-free ``y_0 + D(s)`` (the indicator without ``e``).
        params: the drawn parameters (floats).
    """

    t: Tensor
    y: Tensor
    family: str
    onset: float
    degradation: Tensor
    params: dict


def _uniform(g: torch.Generator, lo: float, hi: float) -> float:
    return float(torch.empty((), dtype=torch.float64).uniform_(lo, hi, generator=g))


def _range(v, name: str, lo: float, hi: float | None = None) -> tuple[float, float]:
    if not (isinstance(v, tuple) and len(v) == 2) or not all(is_real(x) for x in v):
        raise TypeError(f"{name} must be a tuple (low, high) of numbers, got {v!r}")
    a, b = float(v[0]), float(v[1])
    if not (lo <= a <= b < math.inf) or (hi is not None and b > hi):  # (inf: no draw)
        bound = f"[{lo:g}, {hi:g}]" if hi is not None else f">= {lo:g}"
        raise ValueError(f"{name} must satisfy low <= high within {bound} (finite), got {v!r}")
    return a, b


def _times(n: int, dt: float, gaps: bool, g: torch.Generator) -> Tensor:
    steps = torch.full((n,), dt, dtype=torch.float64)
    if gaps:
        for _ in range(int(torch.randint(0, 4, (1,), generator=g))):
            i = int(torch.randint(1, n, (1,), generator=g))
            steps[i] = dt * _uniform(g, 20.0, 200.0)
    return torch.cumsum(steps, 0)


def _noise(n: int, sd: float, df: int | None, g: torch.Generator) -> Tensor:
    z = torch.randn(n, generator=g, dtype=torch.float64)
    if df is None:
        return sd * z
    chi2 = torch.randn(n, df, generator=g, dtype=torch.float64).pow(2).sum(-1)
    return sd * z / (chi2 / df).sqrt() * math.sqrt((df - 2) / df)  # unit-variance Student t


def _ar1(n: int, rho: float, sd: float, g: torch.Generator) -> Tensor:
    """Stationary AR(1) ``c_i = rho c_{i-1} + w_i`` with marginal std ``sd``."""
    w = torch.randn(n, generator=g, dtype=torch.float64) * sd * math.sqrt(1.0 - rho * rho)
    c = torch.empty(n, dtype=torch.float64)
    c[0] = sd * float(torch.randn((), generator=g, dtype=torch.float64))
    for i in range(1, n):
        c[i] = rho * c[i - 1] + w[i]
    return c


def _shocks(s: Tensor, S: float, rise: float, g: torch.Generator) -> tuple[Tensor, dict]:
    b = _uniform(g, 1.0, 2.5)
    n_jumps = _uniform(g, 30.0, 300.0)  # expected number of shocks over the degradation
    count = int(torch.poisson(torch.tensor(n_jumps, dtype=torch.float64), generator=g))
    count = max(count, 1)
    # event times: Lambda(s) ~ (s / S)^b, so s = S u^(1/b) for u ~ U(0, 1)
    u = torch.rand(count, generator=g, dtype=torch.float64)
    times = S * u.pow(1.0 / b)
    sizes = torch.empty(count, dtype=torch.float64).exponential_(1.0, generator=g)
    D = (sizes[None, :] * (times[None, :] <= s[:, None])).sum(-1)
    D = D * (rise / float(sizes.sum()))
    return D, {"b": b, "shocks": float(count)}


def _paris(s: Tensor, S: float, rise: float, g: torch.Generator) -> tuple[Tensor, dict]:
    m = _uniform(g, 2.5, 4.0)
    e = 1.0 - m / 2.0
    aF = _uniform(g, 5.0, 30.0)  # final crack size over the initial one
    k = (1.0 - aF**e) / S
    a = (1.0 - k * s).pow(1.0 / e)
    return rise * (a - 1.0) / (aF - 1.0), {"m": m, "a_final": aF}


def _two_phase(s: Tensor, S: float, rise: float, g: torch.Generator) -> tuple[Tensor, dict]:
    frac, J = _uniform(g, 0.3, 0.7), _uniform(g, 1.5, 3.0)
    sc = frac * S
    R = math.log(20.0)  # D rises from rise / 20 at onset (log scale) ...
    b1 = _uniform(g, 0.2, 0.6) * R / S
    b2 = max((R - b1 * sc - math.log(J)) / (S - sc), b1)
    L = torch.where(s < sc, b1 * s, b1 * sc + math.log(J) + b2 * (s - sc))
    L = L - float(L[-1])  # ... to rise at the end of the record
    c = _ar1(s.shape[0], 0.98, _uniform(g, 0.05, 0.2), g)
    D = torch.where(s > 0, rise * torch.exp(L + c), torch.zeros_like(s))
    return D, {"change": frac, "jump": J, "b1": b1, "b2": b2}


def _hump(s: Tensor, S: float, rise: float, g: torch.Generator) -> tuple[Tensor, dict]:
    b = math.log(20.0) / S
    sh, w, A = _uniform(g, 0.2, 0.6) * S, _uniform(g, 0.03, 0.1) * S, _uniform(g, 1.0, 3.0)
    shape = torch.exp(b * (s - S)) * (1.0 + A * torch.exp(-(((s - sh) / w) ** 2)))
    D = torch.where(s > 0, rise * shape / float(shape[-1]), torch.zeros_like(s))
    return D, {"b": b, "hump_at": sh / S, "hump_width": w / S, "hump_height": A}


_FAMILY = {"shocks": _shocks, "paris": _paris, "two_phase": _two_phase, "hump": _hump}


def simulate_run_to_failure(
    family: str,
    generator: torch.Generator,
    *,
    dt: float = 1.0 / 144.0,
    life: tuple[float, float] = (3.0, 30.0),
    onset: tuple[float, float] = (0.5, 0.9),
    rise: tuple[float, float] = (2.0, 9.0),
    noise: tuple[float, float] = (0.02, 0.08),
    gaps: bool = True,
) -> RunToFailure:
    """Draw one record of ``family`` (module docstring).

    Args:
        family: one of :data:`RUN_TO_FAILURE_FAMILIES`.
        generator: the only source of randomness.
        dt: sampling step (days).
        life: range of the record length (days); onset: range of the onset as a fraction of it.
        rise: range of the final rise ``(F - y_0) / y_0``.
        noise: range of the noise standard deviation as a fraction of ``y_0``.
        gaps: insert up to 3 recording gaps.

    Returns:
        :class:`RunToFailure` with ``t``, ``y`` ``(T,)``.
    """
    if not isinstance(family, str) or family not in _FAMILY:  # (a list was unhashable)
        raise ValueError(f"family must be one of {', '.join(_FAMILY)}, got {family!r}")
    if not isinstance(generator, torch.Generator):
        raise TypeError(f"generator must be a torch.Generator, got {type(generator).__name__}")
    if generator.device.type != "cpu":  # (every draw is a CPU float64 tensor)
        raise ValueError(f"generator must be a CPU torch.Generator, got one on {generator.device}")
    check_positive_real(dt, "dt")
    dt = float(dt)  # (an np.float32 dt divided the life in float32: another sample count)
    gaps = check_flag(gaps, "gaps")
    life_r = _range(life, "life", 0.0)
    onset_r = _range(onset, "onset", 0.0, 0.99)
    rise_r = _range(rise, "rise", 0.0)
    noise_r = _range(noise, "noise", 0.0)
    g = generator
    n = int(_uniform(g, *life_r) / dt)
    if n < 50:
        raise ValueError(f"life / dt gives {n} samples; at least 50 are needed")
    t = _times(n, dt, gaps, g)
    t_on = _uniform(g, *onset_r) * float(t[-1])
    s = (t - t_on).clamp(min=0.0)
    S = float(t[-1]) - t_on
    y0 = _uniform(g, 0.05, 0.2)
    rise_abs = y0 * _uniform(g, *rise_r)
    D, params = _FAMILY[family](s, S, rise_abs, g)
    sd = y0 * _uniform(g, *noise_r)
    df = (None, 3, 5)[int(torch.randint(0, 3, (1,), generator=g))]
    clean = y0 + D
    if family == "paris":  # multiplicative measurement noise on the crack signal
        e = _noise(n, sd, df, g) * (clean / y0)
    else:
        e = _noise(n, sd, df, g)
    params.update({"y0": y0, "rise": rise_abs / y0, "noise_sd": sd, "t_dof": df or math.inf})
    return RunToFailure(t, clean + e, family, t_on, clean, params)


def run_to_failure_set(
    per_family: int = 8, *, seed: int = 0, families: tuple[str, ...] = RUN_TO_FAILURE_FAMILIES
) -> dict[str, RunToFailure]:
    """``per_family`` records of each family from one generator seeded with ``seed``, named
    ``"<family> <i>"`` (drawn from the stream family by family in the order given: all records
    of the first family, then those of the next)."""
    if not is_int(per_family) or per_family < 1:
        raise ValueError(f"per_family must be an int >= 1, got {per_family!r}")
    fams = () if isinstance(families, str) else tuple(families)  # (str: read letter by letter)
    if isinstance(families, str) or any(f not in RUN_TO_FAILURE_FAMILIES for f in fams):
        raise ValueError(
            f"families must be a sequence of names from {RUN_TO_FAILURE_FAMILIES}, got {families!r}"
        )
    g = torch.Generator().manual_seed(check_seed(seed))  # (a float seed was truncated)
    return {
        f"{fam} {i}": simulate_run_to_failure(fam, g) for fam in fams for i in range(per_family)
    }
