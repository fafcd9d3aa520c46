"""Figures for predictions, fading factors, fault probabilities, RUL distributions and training.

Every function draws on a fresh :class:`matplotlib.figure.Figure` (no pyplot state, no window;
the PNG is rendered by the Agg canvas), saves it to ``path`` (parent folders are created) and
returns the figure. Inputs may be tensors (any device) or array-likes; several series are given
as a mapping ``label -> values``.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping, Sequence

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from ..core.validation import check_nonneg
from ..metrics import alpha_bounds, lambda_index, lambda_time
from ._arrays import as_numpy, write_png

__all__ = [
    "plot_prediction",
    "plot_fading_factor",
    "plot_rul_pdf",
    "plot_alpha_lambda",
    "plot_fault_probability",
    "plot_fault_probability_box",
    "plot_training_curves",
]

PathLike = str | os.PathLike


def _np(x, name: str, ndim: int | None = 1) -> np.ndarray:
    arr = as_numpy(x, name)
    if ndim is not None and arr.ndim != ndim:
        raise ValueError(f"{name} must be {ndim}-D, got shape {arr.shape}")
    return arr


def _same_len(a: np.ndarray, b: np.ndarray, a_name: str, b_name: str) -> None:
    if a.shape[0] != b.shape[0]:
        raise ValueError(
            f"{b_name} must have length {a.shape[0]} (like {a_name}), got shape {b.shape}"
        )


def _series(x, name: str, default_label: str) -> list[tuple[str, str, np.ndarray]]:
    """``(label, name, values)`` of each series: ``name[label]`` names an entry of a mapping."""
    if isinstance(x, Mapping):
        if not x:
            raise ValueError(f"{name} is empty")
        return [(str(k), f"{name}[{k!r}]", _np(v, f"{name}[{k!r}]")) for k, v in x.items()]
    return [(default_label, name, _np(x, name))]


def _new(figsize=(7.0, 4.0)) -> tuple[Figure, object]:
    fig = Figure(figsize=figsize)
    FigureCanvasAgg(fig)
    return fig, fig.add_subplot(1, 1, 1)


def plot_prediction(
    path: PathLike,
    t,
    truth,
    mean,
    std=None,
    *,
    lower=None,
    upper=None,
    n_std: float = 2.0,
    title: str | None = None,
    ylabel: str = "state",
) -> Figure:
    """Prediction vs truth with an uncertainty band.

    Args:
        t: ``(T,)`` times; truth, mean: ``(T,)``.
        std: ``(T,)`` predicted standard deviation; band ``mean +- n_std * std``.
        lower, upper: ``(T,)`` explicit band (e.g. particle quantiles), instead of ``std``.
    """
    t = _np(t, "t")
    truth, mean = _np(truth, "truth"), _np(mean, "mean")
    _same_len(t, truth, "t", "truth")
    _same_len(t, mean, "t", "mean")
    if std is not None and (lower is not None or upper is not None):
        raise ValueError("give std or (lower, upper), not both")
    if std is not None:
        check_nonneg(n_std, "n_std", numbers_only=True)
        std = _np(std, "std")
        _same_len(t, std, "t", "std")
        if np.any(std < 0):  # (NaN: missing, no band there)
            raise ValueError(f"std must be >= 0 (NaN: missing), got {np.nanmin(std):g}")
        lower, upper = mean - n_std * std, mean + n_std * std
        band_label = f"mean +- {n_std:g} std"
    elif lower is not None or upper is not None:
        if lower is None or upper is None:
            raise ValueError("give both lower and upper")
        lower, upper = _np(lower, "lower"), _np(upper, "upper")
        _same_len(t, lower, "t", "lower")
        _same_len(t, upper, "t", "upper")
        band_label = "band"
    fig, ax = _new()
    if lower is not None:
        ax.fill_between(t, lower, upper, color="C0", alpha=0.25, label=band_label)
    ax.plot(t, truth, "k-", lw=1.2, label="truth")
    ax.plot(t, mean, "C0--", lw=1.2, label="prediction")
    ax.set_xlabel("time")
    ax.set_ylabel(ylabel)
    ax.set_title(title or "Prediction")
    ax.legend(loc="best")
    return write_png(fig, path, make_folder=True)


def plot_fading_factor(path: PathLike, t, lam, *, title: str | None = None) -> Figure:
    """Strong-tracking fading factor ``lambda_k`` over time (one line per series).

    Args:
        t: ``(T,)`` times; lam: ``(T,)`` or a mapping ``label -> (T,)``.
    """
    t = _np(t, "t")
    fig, ax = _new()
    for label, name, y in _series(lam, "lam", "lambda_k"):
        _same_len(t, y, "t", name)
        ax.plot(t, y, lw=1.2, label=label)
    ax.axhline(1.0, color="0.5", lw=0.8, ls=":")
    ax.set_xlabel("time")
    ax.set_ylabel(r"$\lambda_k$")
    ax.set_title(title or "Fading factor")
    ax.legend(loc="best")
    return write_png(fig, path, make_folder=True)


def plot_rul_pdf(
    path: PathLike,
    prediction_times,
    support,
    pmf,
    *,
    true_rul=None,
    censored_mass=None,
    title: str | None = None,
) -> Figure:
    """RUL pmf per prediction time as a ridge plot (paper 002, Fig. 12).

    Args:
        prediction_times: ``(n,)``; support: ``(K,)`` RUL values; pmf: ``(n, K)`` (e.g.
            ``RULDistribution.support`` and ``.pmf`` for a batch over prediction times).
        true_rul: optional ``(n,)`` true RUL, marked on each ridge.
        censored_mass: optional ``(n,)`` mass beyond the horizon, written next to each ridge.
    """
    times = _np(prediction_times, "prediction_times")
    support = _np(support, "support")
    pmf = _np(pmf, "pmf", ndim=2)
    if pmf.shape != (times.shape[0], support.shape[0]):
        raise ValueError(
            f"pmf must have shape ({times.shape[0]}, {support.shape[0]}) (n, K), got {pmf.shape}"
        )
    if true_rul is not None:
        true_rul = _np(true_rul, "true_rul")
        _same_len(times, true_rul, "prediction_times", "true_rul")
    if censored_mass is not None:
        censored_mass = _np(censored_mass, "censored_mass")
        _same_len(times, censored_mass, "prediction_times", "censored_mass")
    peak = float(np.max(pmf)) if pmf.size else 0.0
    scale = 0.9 / peak if peak > 0 else 1.0
    fig, ax = _new((7.0, 1.0 + 0.8 * max(len(times), 3)))
    for i in range(len(times)):
        base = float(i)
        ax.fill_between(support, base, base + scale * pmf[i], step="mid", alpha=0.6, color="C0")
        ax.plot(support, base + scale * pmf[i], drawstyle="steps-mid", color="C0", lw=0.8)
        if true_rul is not None:
            ax.plot([true_rul[i]] * 2, [base, base + 0.95], "r-", lw=1.2)
        if censored_mass is not None and censored_mass[i] > 0:
            x = support[-1] if support.size else 0.0  # (no support: an empty pmf)
            ax.text(x, base + 0.5, f" censored {censored_mass[i]:.2f}", fontsize=7)
    ax.set_yticks(np.arange(len(times)))
    ax.set_yticklabels([f"{v:g}" for v in times])
    ax.set_xlabel("RUL")
    ax.set_ylabel("prediction time")
    ax.set_title(title or "RUL distribution")
    return write_png(fig, path, make_folder=True)


def plot_alpha_lambda(
    path: PathLike,
    times,
    true_rul,
    pred_rul,
    *,
    alpha: float | tuple[float, float],
    lower=None,
    upper=None,
    lam: float | None = None,
    t_eol: float | None = None,
    title: str | None = None,
) -> Figure:
    """Alpha-lambda chart (Saxena et al. 2010): true RUL, alpha cone, predictions.

    Args:
        times, true_rul, pred_rul: ``(n,)`` prediction times, true and predicted RUL.
        alpha: cone ``[(1 - alpha^-) r*, (1 + alpha^+) r*]`` (number or pair).
        lower, upper: optional ``(n,)`` interval of each prediction (error bars).
        lam: optional lambda; marks ``t_lambda`` and the prediction evaluated there.
        t_eol: end of life (default ``times[-1] + true_rul[-1]``).
    """
    t = _np(times, "times")
    r_true, r_pred = _np(true_rul, "true_rul"), _np(pred_rul, "pred_rul")
    _same_len(t, r_true, "times", "true_rul")
    _same_len(t, r_pred, "times", "pred_rul")
    if t.size == 0:
        raise ValueError("times must hold at least one prediction time, got shape (0,)")
    t_eol = float(t[-1] + r_true[-1]) if t_eol is None else float(t_eol)
    grid = np.linspace(float(t[0]), t_eol, 200)
    r_grid = t_eol - grid
    lo, hi = (b.numpy() for b in alpha_bounds(r_grid, alpha))
    fig, ax = _new()
    ax.fill_between(grid, lo, hi, color="0.85", label="alpha bounds")
    ax.plot(grid, r_grid, "k-", lw=1.2, label="true RUL")
    if lower is not None or upper is not None:
        if lower is None or upper is None:
            raise ValueError("give both lower and upper")
        lower, upper = _np(lower, "lower"), _np(upper, "upper")
        _same_len(t, lower, "times", "lower")
        _same_len(t, upper, "times", "upper")
        yerr = np.vstack([np.clip(r_pred - lower, 0, None), np.clip(upper - r_pred, 0, None)])
        ax.errorbar(t, r_pred, yerr=yerr, fmt="o", color="C0", capsize=3, label="prediction")
    else:
        ax.plot(t, r_pred, "o", color="C0", label="prediction")
    if lam is not None:
        t_lam = lambda_time(float(t[0]), t_eol, lam)
        ax.axvline(t_lam, color="C3", ls="--", lw=1.0, label=rf"$t_\lambda$, $\lambda$={lam:g}")
        i = lambda_index(t, lam, t_eol=t_eol)
        ax.plot(t[i], r_pred[i], "s", mfc="none", mec="C3", ms=10)
    ax.set_xlabel("time")
    ax.set_ylabel("RUL")
    ax.set_title(title or r"$\alpha$-$\lambda$ accuracy")
    ax.legend(loc="best")
    return write_png(fig, path, make_folder=True)


def plot_fault_probability(
    path: PathLike,
    t,
    prob,
    *,
    decision: float = 0.5,
    title: str | None = None,
) -> Figure:
    """Fault probability per prediction step (paper 002, Fig. 10(a)-(c)).

    Args:
        t: ``(T,)`` times or steps; prob: ``(T,)`` or a mapping ``label -> (T,)``.
        decision: probability above which a fault is declared (0.5 in paper 002).
    """
    t = _np(t, "t")
    fig, ax = _new()
    for label, name, p in _series(prob, "prob", "fault probability"):
        _same_len(t, p, "t", name)
        ax.plot(t, p, ".-", lw=0.8, ms=3, label=label)
    ax.axhline(decision, color="C3", ls="--", lw=1.0, label=f"decision {decision:g}")
    ax.set_ylim(-0.02, 1.02)
    ax.set_xlabel("time")
    ax.set_ylabel("fault probability")
    ax.set_title(title or "Fault probability")
    ax.legend(loc="best")
    return write_png(fig, path, make_folder=True)


def plot_fault_probability_box(
    path: PathLike,
    t,
    prob,
    *,
    period: float = 1.0,
    decision: float = 0.5,
    title: str | None = None,
) -> Figure:
    """Box plot of the fault probability per period, e.g. per day (paper 002, Fig. 10(d)-(f)).

    Values are grouped by ``floor(t / period)``; one box per non-empty group.

    Args:
        t: ``(T,)`` times; prob: ``(T,)`` fault probabilities; period: group length (> 0).
    """
    t, p = _np(t, "t"), _np(prob, "prob")
    _same_len(t, p, "t", "prob")
    if not (math.isfinite(period) and period > 0):
        raise ValueError(f"period must be a finite positive number, got {period}")
    keep = np.isfinite(t) & ~np.isnan(p)  # NaN: missing (a NaN time cast to int64 made a group)
    t, p = t[keep], p[keep]
    if t.size == 0:
        raise ValueError("t and prob must hold at least one pair of a finite time and a value")
    groups = np.floor(t / period).astype(np.int64)
    keys = np.unique(groups)
    data = [p[groups == k] for k in keys]
    fig, ax = _new()
    ax.boxplot(data, positions=np.arange(1, len(keys) + 1))
    ax.set_xticks(np.arange(1, len(keys) + 1))
    ax.set_xticklabels([f"{k * period:g}" for k in keys])
    ax.axhline(decision, color="C3", ls="--", lw=1.0)
    ax.set_ylim(-0.02, 1.02)
    ax.set_xlabel(f"period start (period = {period:g})")
    ax.set_ylabel("fault probability")
    ax.set_title(title or "Fault probability per period")
    return write_png(fig, path, make_folder=True)


def plot_training_curves(
    path: PathLike,
    curves: Mapping[str, Sequence[float]],
    *,
    logy: bool = True,
    title: str | None = None,
    xlabel: str = "epoch",
    x_step: float = 1.0,
) -> Figure:
    """Loss curves for several optimisers, one line per ``label -> (E,)`` entry.

    Point ``e`` (1-based) is drawn at ``e * x_step`` on an axis labelled ``xlabel`` (per epoch by
    default; e.g. ``xlabel="step", x_step=50`` for a loss recorded every 50 steps).
    """
    fig, ax = _new()
    for label, _, y in _series(curves, "curves", "loss"):
        ax.plot(x_step * np.arange(1, len(y) + 1), y, lw=1.2, label=label)
    if logy:
        ax.set_yscale("log")
    ax.set_xlabel(xlabel)
    ax.set_ylabel("loss")
    ax.set_title(title or "Training curves")
    ax.legend(loc="best")
    return write_png(fig, path, make_folder=True)
