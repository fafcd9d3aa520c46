"""RUL over prediction time (with the alpha cone) and predicted paths against a threshold.

Like the rest of :mod:`prognos_torch.plots`: a fresh Agg figure, a PNG written to ``path``,
the figure returned; values may be tensors (any device) or array-likes.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Mapping, Sequence

import numpy as np
import torch

from ..core.validation import check_count, is_real
from ..metrics import alpha_bounds
from ..prognosis.paths import weighted_quantile
from ._arrays import as_numpy, write_png
from .figures import PathLike, _new, _np, _same_len

__all__ = ["plot_rul_band", "draw_paths", "plot_paths", "weighted_quantiles"]


def plot_rul_band(
    path: PathLike,
    times,
    true_rul,
    predictions: Mapping[str, object],
    *,
    alpha: float | tuple[float, float] | None = None,
    band: tuple[float, float] = (10.0, 90.0),
    title: str | None = None,
    xlabel: str = "prediction time",
    ylabel: str = "RUL",
):
    """Predicted RUL against prediction time: the median and a percentile band over runs.

    Args:
        times: ``(n,)`` prediction times; true_rul: ``(n,)``.
        predictions: ``label -> (n, R)`` predicted RUL of ``R`` runs (NaN: censored, left out
            of the median and band; a time where every run is censored shows no point).
        alpha: optional alpha cone ``[(1 - alpha^-) r*, (1 + alpha^+) r*]`` around the true
            RUL (Saxena et al. 2010), a number or a pair.
        band: the percentiles of the band.
    """
    t = _np(times, "times")
    r_true = _np(true_rul, "true_rul")
    _same_len(t, r_true, "times", "true_rul")
    if (
        not isinstance(band, (tuple, list))
        or len(band) != 2
        or not all(is_real(q) and 0 <= q <= 100 for q in band)
        or band[0] > band[1]
    ):
        raise ValueError(f"band must be a pair of percentiles 0 <= lo <= hi <= 100, got {band!r}")
    fig, ax = _new((7.0, 4.2))
    if alpha is not None:
        lo, hi = (b.numpy() for b in alpha_bounds(r_true, alpha))
        ax.fill_between(t, lo, hi, color="0.88", label="alpha cone")
    ax.plot(t, r_true, "k-", lw=1.4, label="true RUL")
    for i, (label, pred) in enumerate(predictions.items()):
        p = _np(pred, f"predictions[{label!r}]", ndim=2)
        if p.shape[0] != t.shape[0]:
            raise ValueError(
                f"predictions[{label!r}] must have shape ({t.shape[0]}, R), got {p.shape}"
            )
        with warnings.catch_warnings():  # all-NaN rows (every run censored) stay NaN
            warnings.simplefilter("ignore", RuntimeWarning)
            med = np.nanmedian(p, axis=1)
            lo, hi = (np.nanpercentile(p, q, axis=1) for q in band)
        ax.fill_between(t, lo, hi, color=f"C{i}", alpha=0.2)
        ax.plot(
            t, med, f"C{i}o-", ms=3, lw=1.2, label=f"{label} (median, {band[0]:g}-{band[1]:g} %)"
        )
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(title or "Predicted RUL")
    ax.legend(loc="best", fontsize=8)
    return write_png(fig, path, make_folder=True)


def weighted_quantiles(samples, weights, qs: Sequence[float]) -> np.ndarray:
    """Per column of ``samples`` ``(N, H)`` the weighted quantiles ``qs``: ``(len(qs), H)``
    (the smallest sample whose cumulative weight reaches ``q`` of the total; ``weights``
    ``(N,)``, ``>= 0``, need not sum to 1)."""
    samples, w = as_numpy(samples, "samples"), as_numpy(weights, "weights")
    if samples.ndim != 2 or samples.shape[0] == 0:
        raise ValueError(f"samples must have shape (N, H) with N >= 1, got {samples.shape}")
    if w.shape != (samples.shape[0],):
        raise ValueError(f"weights must have shape ({samples.shape[0]},), got {w.shape}")
    total = float(w.sum())
    if not (np.all(w >= 0) and math.isfinite(total) and total > 0):
        raise ValueError("weights must be finite, >= 0 and not all 0")
    # the library's rule on normalised weights (unnormalised ones gave the minimum)
    s, wn = torch.from_numpy(samples), torch.from_numpy(w / total)
    return np.stack([weighted_quantile(s, wn, q).numpy() for q in qs])


def draw_paths(
    ax,
    t,
    paths,
    weights=None,
    *,
    threshold: float | None = None,
    n_show: int = 20,
    color: str = "C1",
) -> None:
    """Draw predicted paths on ``ax``: the weighted 5-95 % band, the median, the ``n_show``
    heaviest paths and the threshold.

    Args:
        t: ``(H,)`` times of the path steps; paths: ``(N, H)``; weights: ``(N,)``, ``>= 0``,
            need not sum to 1 (default equal).
    """
    tf, p = _np(t, "t"), _np(paths, "paths", ndim=2)
    if p.shape[1] != tf.shape[0] or p.shape[0] == 0:
        raise ValueError(f"paths must have shape (N, {tf.shape[0]}) with N >= 1, got {p.shape}")
    check_count(n_show, "n_show", 0, error=ValueError)
    w = np.full(p.shape[0], 1.0 / p.shape[0]) if weights is None else _np(weights, "weights")
    if w.shape != (p.shape[0],):
        raise ValueError(f"weights must have shape ({p.shape[0]},), got {w.shape}")
    lo, med, hi = weighted_quantiles(p, w, (0.05, 0.5, 0.95))
    ax.fill_between(tf, lo, hi, color=color, alpha=0.25, label="paths 5-95 %")
    for i in np.argsort(-w, kind="stable")[:n_show]:
        ax.plot(tf, p[i], color=color, lw=0.4, alpha=0.5)
    ax.plot(tf, med, color=color, lw=1.5, label="median path")
    if threshold is not None:
        ax.axhline(threshold, color="C3", lw=1.0, ls="--", label="threshold")


def plot_paths(
    path: PathLike,
    t,
    paths,
    weights=None,
    *,
    threshold: float | None = None,
    history: tuple[object, object] | None = None,
    n_show: int = 20,
    title: str | None = None,
    xlabel: str = "time",
    ylabel: str = "value",
):
    """Predicted paths (:func:`draw_paths`) after an optional observed ``history = (t, x)``."""
    fig, ax = _new((7.5, 4.0))
    if history is not None:
        th, xh = _np(history[0], "history t"), _np(history[1], "history x")
        _same_len(th, xh, "history t", "history x")
        ax.plot(th, xh, color="0.25", lw=1.0, label="observed")
    draw_paths(ax, t, paths, weights, threshold=threshold, n_show=n_show)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(title or "Predicted paths")
    ax.legend(loc="best", fontsize=8)
    return write_png(fig, path, make_folder=True)
