"""Forecasts whose inputs leave the training range: a warning and an honestly wider band.

A fitted learner has seen values inside the training range ``[data_min, data_max]`` of its
scaler only. Outside it the learner extrapolates, and its training residuals (which set the
filter's noise) say nothing about its error there: a forecast from far outside can look sure
of itself (a saturated ANFIS or ELM gives a band as narrow as the noise) with no data behind
it. So :func:`~prognos_torch.workflow.forecast` does three things:

* the *extrapolation distance* of step ``k``, ``d_k >= 0`` (data units), is how far the inputs
  of that step (the ``m`` values before it: the last observations, then the forecast means)
  lie outside the training range at most (:func:`extrapolation_distance`);
* the band is widened by ``d_k`` in quadrature, ``h_k' = sqrt(h_k^2 + (z d_k)^2)`` for each
  half-width ``h_k`` (``z``: the normal quantile of the band's level), and the std likewise,
  ``std_k' = sqrt(std_k^2 + d_k^2)`` (:func:`widen`). This says no more than that the
  learner's output there is unknown to the extent of the distance from the data; inside the
  range ``d_k = 0`` and the band is the filter's own. Sample paths (particle filters) are
  left as the model drew them;
* when ``max_k d_k`` exceeds :data:`WARN_FRACTION` of the training span, an
  :class:`ExtrapolationWarning` says so (``prognos forecast`` and ``prognos rul`` print it as
  one ``warning:`` line on stderr and exit 0).

:func:`~prognos_torch.workflow.rul` warns in the same way when the observations it starts from
lie outside the range; its sample paths are not widened.
"""

from __future__ import annotations

import math
import warnings

import torch
from torch import Tensor

from ..core.validation import check_level, check_pos_int, is_real

__all__ = [
    "ExtrapolationWarning",
    "WARN_FRACTION",
    "extrapolation_distance",
    "origin_distance",
    "widen",
    "warn",
    "diverged",
    "censor_diverged",
]

#: Fraction of the training span beyond which a forecast warns that it extrapolates.
WARN_FRACTION = 0.1


class ExtrapolationWarning(UserWarning):
    """A forecast or RUL starts from, or runs into, values outside the training range."""


def _check_range(lo: float, hi: float) -> tuple[float, float]:
    """The training range as floats: finite numbers with ``lo <= hi`` (a NaN bound gave
    ``d = 0`` everywhere, a swapped one a negative span)."""
    if not (is_real(lo) and is_real(hi) and math.isfinite(lo) and math.isfinite(hi) and lo <= hi):
        raise ValueError(
            f"lo, hi must be finite numbers with lo <= hi (the training range), got {lo!r}, {hi!r}"
        )
    return float(lo), float(hi)


def _check_history(history: Tensor, m: int) -> int:
    m = check_pos_int(m, "m")
    if not isinstance(history, Tensor) or history.dim() != 1:
        got = tuple(history.shape) if isinstance(history, Tensor) else type(history).__name__
        raise ValueError(f"history must be a tensor of shape (T,), got {got}")
    return m


def _outside(values: Tensor, lo: float, hi: float) -> Tensor:
    """Distance of each value from ``[lo, hi]``; 0 for a missing one (NaN), which the filter
    has estimated from its neighbours rather than taken as an input."""
    d = (lo - values).clamp_min(0.0) + (values - hi).clamp_min(0.0)
    return torch.where(torch.isnan(values), 0.0, d)


def extrapolation_distance(history: Tensor, mean: Tensor, m: int, lo: float, hi: float) -> Tensor:
    """``d_k`` for a forecast of ``H`` steps: ``(H,)``, data units.

    Args:
        history: ``(T,)`` observed values (at least ``m``); the last ``m`` feed the first step.
        mean: ``(H,)`` forecast means.
        m: embedding dimension (inputs per step).
        lo, hi: the training range.
    """
    m, (lo, hi) = _check_history(history, m), _check_range(lo, hi)
    if not isinstance(mean, Tensor) or mean.dim() != 1 or not mean.is_floating_point():
        got = tuple(mean.shape) if isinstance(mean, Tensor) else type(mean).__name__
        raise ValueError(f"mean must be a floating-point tensor of shape (H,), got {got}")
    if history.shape[0] < m:  # (fewer than H windows: a short d that widen broadcast)
        raise ValueError(f"history must hold at least m = {m} values, got {history.shape[0]}")
    seq = torch.cat([history[-m:].to(mean), mean])
    dist = _outside(seq, lo, hi)
    return dist.unfold(0, m, 1)[: mean.shape[0]].amax(-1)


def origin_distance(history: Tensor, m: int, lo: float, hi: float) -> float:
    """How far the last ``m`` observations lie outside the training range at most."""
    m, (lo, hi) = _check_history(history, m), _check_range(lo, hi)  # (m = 0 read all of it)
    if history.shape[0] == 0:
        raise ValueError("history must hold at least one value, got shape (0,)")
    return float(_outside(history[-m:], lo, hi).max())


def widen(
    mean: Tensor, lower: Tensor, upper: Tensor, std: Tensor, dist: Tensor, level: float
) -> tuple[Tensor, Tensor, Tensor]:
    """``(lower, upper, std)`` widened by ``dist`` in quadrature (module notes)."""
    level = check_level(level)  # (level >= 1 gave a NaN band)
    for name, v in (("lower", lower), ("upper", upper), ("std", std), ("dist", dist)):
        if not isinstance(v, Tensor) or v.shape != mean.shape:
            got = tuple(v.shape) if isinstance(v, Tensor) else type(v).__name__
            raise ValueError(f"{name} must have the shape of mean {tuple(mean.shape)}, got {got}")
    z = math.sqrt(2.0) * float(torch.special.erfinv(torch.tensor(level, dtype=torch.float64)))
    # sqrt(h^2 + (z d)^2) as hypot: h^2 overflowed in float32 for h > 1.8e19 (an infinite band)
    lower = mean - torch.hypot(mean - lower, z * dist)
    upper = mean + torch.hypot(upper - mean, z * dist)
    return lower, upper, torch.hypot(std, dist)


def warn(what: str, dist: float, lo: float, hi: float) -> str | None:
    """Issue an :class:`ExtrapolationWarning` when ``dist`` exceeds :data:`WARN_FRACTION` of
    the span, and return its sentence (a result's flag); ``None``: no warning."""
    lo, hi = _check_range(lo, hi)
    if not is_real(dist) or math.isnan(dist) or dist < 0:
        raise ValueError(f"dist must be a number >= 0 (data units), got {dist!r}")
    span = hi - lo
    if not dist > WARN_FRACTION * span:
        return None
    # (a constant training range, span 0, raised ZeroDivisionError here)
    share = f"{100 * (dist / span):.0f} % of its span" if span > 0 else "its span is 0"
    if math.isinf(dist):  # ("inf % of its span": the values overflowed)
        share = "the values overflow"
    elif "inf" in share:  # (100 x a ratio near the largest float)
        share = f"{dist / span:.3g} times its span"
    text = (
        f"{what} lies outside the model's training range [{lo:.4g}, {hi:.4g}] by up to "
        f"{dist:.4g} ({share}): the learner extrapolates there"
        + (", so the band is widened by that distance" if what.startswith("the forecast") else "")
        + " (prognos_torch.workflow.extrapolation)"
    )
    warnings.warn(text, ExtrapolationWarning, stacklevel=3)
    return text


def censor_diverged(paths: Tensor, direction: str) -> tuple[Tensor, str | None]:
    """Paths ``(..., N, H)`` whose values become non-finite (the learner's output, iterated,
    overflowed: ``inf``, then ``inf - inf = NaN``) count as not crossing from their first
    non-finite step on, as the library's other first passages do
    (:func:`~prognos_torch.prognosis.assess.threshold_crossings`): a crossing before it is
    kept, otherwise the path is censored. Returns the paths to take the first passage of
    (``-inf``, or ``+inf`` for ``direction="below"``, from that step on) and, where some path
    diverged, the sentence of an :class:`ExtrapolationWarning` (issued here)."""
    bad = ~torch.isfinite(paths)
    if not bool(bad.any()):
        return paths, None
    bad = bad.to(torch.int8).cummax(-1).values.bool()  # from the first one on
    share = float(bad[..., -1].to(torch.float64).mean())
    text = (
        f"diverging paths: {100 * share:.1f} % of the predicted paths became non-finite within "
        "the horizon (the learner's output, iterated, grows without bound); each counts as not "
        "crossing from then on, its crossing before that kept (prognos_torch.workflow."
        "extrapolation)"
    )
    warnings.warn(text, ExtrapolationWarning, stacklevel=3)
    return torch.where(bad, -math.inf if direction == "above" else math.inf, paths), text


def diverged(mean: Tensor) -> str | None:
    """Issue an :class:`ExtrapolationWarning` when the forecast means ``(H,)`` are not all
    finite (the learner's output, iterated, overflowed), naming the first such step, and
    return its sentence; ``None`` when every mean is finite."""
    bad = ~torch.isfinite(mean)
    if not bool(bad.any()):
        return None
    k = int(bad.nonzero()[0, 0]) + 1
    text = (
        f"the forecast diverges: its mean is not finite from step {k} of {mean.shape[0]} on "
        "(the learner's output, iterated, grows without bound), so the steps from there are no "
        "forecast; forecast fewer steps (prognos_torch.workflow.extrapolation)"
    )
    warnings.warn(text, ExtrapolationWarning, stacklevel=3)
    return text
