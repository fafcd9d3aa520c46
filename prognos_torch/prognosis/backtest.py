"""Trend models judged by multi-step crossing-time skill on a series' own past (backtest).

A trend model that is iterated far ahead is used for one thing: the time at which the indicator
reaches a level. One-step error is the wrong criterion for it (issue 12). The backtest asks each
model the question it will be asked, on levels the series has already reached:

1. :func:`crossing_pairs`: for the levels ``m_0 + f (max m - m_0)``, ``f in`` :data:`LEVELS`,
   that the 5-point moving median ``m`` has crossed since onset, the origins at the fractions
   :data:`ORIGINS` of the way from onset to the crossing.
2. :func:`backtest_scores`: each model predicts the crossing from the posterior at each origin
   (causal: the filter had seen only the data up to it) by sampled first passages, scored by
   :func:`crps_log_time`, the CRPS of the predicted log time to the crossing (Gneiting & Raftery
   2007; a proper score: it rewards calibrated as well as sharp predictions). With
   ``every_noise=True`` a :class:`~prognos_torch.prognosis.trends.TrendFit` is scored at every
   point of its noise grid at once, which is how ``prognose`` chooses each shape's noise.
3. :func:`one_standard_error_choice`: with a handful of pairs, a model replaces the canonical
   one only when its mean score is better by more than its own noise.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from .onset import moving_median, window_end
from .trends import path_grid

__all__ = [
    "LEVELS",
    "ORIGINS",
    "crossing_pairs",
    "crps_log_time",
    "backtest_scores",
    "one_standard_error_choice",
]

#: Fractions of the rise of the moving median since onset whose crossings are predicted.
LEVELS = (0.5, 0.8)
#: Prediction origins as fractions of the way from onset to each crossing.
ORIGINS = (0.4, 0.7)


def crossing_pairs(
    t: Tensor,
    y: Tensor,
    sigma0: float,
    *,
    levels: tuple[float, ...] = LEVELS,
    origins: tuple[float, ...] = ORIGINS,
) -> list[tuple[float, int, float]]:
    """``(level, origin index, crossing time)`` of the levels already crossed since onset.

    Args:
        t, y: ``(n,)`` times and oriented values since onset (degradation raises ``y``).
        sigma0: the values' noise std; a rise of the moving median below it gives no pairs.
        levels: fractions ``f`` of the rise, the level being ``m_0 + f (max m - m_0)``.
        origins: fractions of ``[t_0, crossing time]`` at which the prediction is made; an
            origin needs at least 5 values before it and the crossing after it.

    Returns:
        A list of ``(level, i, t_c)``: the origin is ``t[i]``, the crossing of the 5-point
        moving median is at ``t_c``.
    """
    m = moving_median(y, 5)
    m0, top = float(m[0]), float(m.max())
    pairs = []
    if top - m0 > sigma0:
        for f in levels:
            c = m0 + f * (top - m0)
            k = int(torch.nonzero(m >= c).flatten()[0])
            t_c = float(t[k])
            for g in origins:
                # (an origin on a sample time takes that sample in any clock: the rounding
                # allowance of window_end)
                o = window_end(t[0], t[k], g)
                i = int(torch.searchsorted(t, o, right=True)) - 1
                if 4 <= i < k and t_c > float(t[i]):
                    pairs.append((c, i, t_c))
    return pairs


def crps_log_time(times: Tensor, true: float, cap: float) -> Tensor:
    """CRPS of sampled crossing durations on the log scale, ``(..., N)`` -> ``(...)``.

    ``CRPS = E|X - x| - E|X - X'| / 2`` with ``X = log(min(T, cap))``, ``x = log(true)``
    (Gneiting & Raftery 2007; the sample form uses the sorted samples). ``inf`` durations
    (censored) enter as ``cap``.
    """
    X = times.clamp(min=1e-300, max=cap).log()
    x = math.log(true)
    n = X.shape[-1]
    Xs = torch.sort(X, -1).values
    i = torch.arange(1, n + 1, dtype=X.dtype, device=X.device)
    spread = ((2.0 * i - n - 1.0) * Xs).sum(-1)
    return (X - x).abs().mean(-1) - spread / (n * n)


def backtest_scores(
    fit,
    pairs: list[tuple[float, int, float]],
    t: Tensor,
    generator: torch.Generator,
    *,
    n_paths: int = 64,
    every_noise: bool = False,
) -> Tensor:
    """Log-time CRPS of a model's predicted crossings, one per pair.

    Each pair ``(c, i, t_c)`` is predicted from the posterior at ``t[i]`` with ``n_paths``
    sampled first passages of ``c`` on a grid of ``true / 20`` steps (geometric beyond) up to
    ``10 x`` the true duration ``true = t_c - t[i]``; censored paths count at that cap.

    Args:
        fit: a :class:`~prognos_torch.prognosis.trends.TrendFit` or a
            :class:`~prognos_torch.prognosis.learner_trend.LearnerTrendFit` (anything with
            ``first_passage``; with ``every_noise`` also ``grid_first_passage``).
        pairs: from :func:`crossing_pairs` on the same times ``t`` ``(n,)``.
        generator: draws the paths.
        every_noise: score every noise grid point of a trend fit at once.

    Returns:
        ``(P,)`` scores, or ``(G, P)`` with ``every_noise`` (lower is better).
    """
    cols = []
    for c, i, t_c in pairs:
        t_i = float(t[i])
        true = t_c - t_i
        grid = path_grid(t_i, 10.0 * true, true / 20.0, rel=0.05)
        if every_noise:
            times = fit.grid_first_passage(i, c, grid, n_paths, generator)
        else:
            times = fit.first_passage(i, c, grid, n_paths, generator).times
        cols.append(crps_log_time(times - t_i, true, 10.0 * true))
    return torch.stack(cols, -1)


def one_standard_error_choice(per_pair: dict[str, Tensor], default: str, k: float = 1.0) -> str:
    """The model whose mean backtest score beats ``default``'s by more than ``k`` standard
    errors of the paired differences, the best of those; otherwise ``default`` (the
    one-standard-error rule of Breiman et al. 1984 for ``k = 1``: with a handful of backtest
    pairs, prefer the canonical model unless the evidence against it exceeds its own noise)."""
    if default not in per_pair:
        return min(per_pair, key=lambda name: float(per_pair[name].mean()))
    ref = per_pair[default]
    best, best_mean = default, float(ref.mean())
    for name, sc in per_pair.items():
        d = sc - ref
        se = float(d.std(correction=1)) / math.sqrt(d.numel()) if d.numel() > 1 else math.inf
        if float(d.mean()) < -k * se and float(sc.mean()) < best_mean:
            best, best_mean = name, float(sc.mean())
    return best
