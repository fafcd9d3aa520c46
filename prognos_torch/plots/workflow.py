"""Figures of :mod:`prognos_torch.workflow`: a forecast with its band, an RUL distribution with
its paths.

Each function draws on a fresh :class:`matplotlib.figure.Figure` (Agg canvas, no pyplot state),
renders the PNG in memory and writes it atomically (temporary file, then rename), so a failed
call never leaves a partial image behind.
"""

from __future__ import annotations

import os
from typing import TYPE_CHECKING

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from ..core.validation import is_int
from ._arrays import as_numpy, check_result, clip_for_drawing, time_axis, time_text, write_png
from .prognosis import plot_prognosis
from .rul import draw_paths

if TYPE_CHECKING:  # annotations only: the workflow imports this module, not the reverse
    from ..workflow.data import Series
    from ..workflow.predict import ForecastResult, RULResult

__all__ = ["plot_forecast", "plot_rul"]


def _check_history(history) -> None:
    """``history`` is ``None`` or a positive int: ``values[-0:]`` is the whole series and
    ``values[-n:]`` for ``n < 0`` drops the first ``|n|`` values."""
    if history is not None and (not is_int(history) or history < 1):
        raise ValueError(f"history must be None or a positive int, got {history!r}")


def _history_tail(series: Series, horizon: int, history: int | None) -> tuple:
    n = len(series) if history is None else min(len(series), history)
    if history is None:
        n = min(len(series), max(4 * horizon, 200))
    return as_numpy(series.t)[-n:], as_numpy(series.values)[-n:]


def plot_forecast(
    path: str | os.PathLike,
    result: ForecastResult,
    *,
    truth: Series | None = None,
    history: int | None = None,
    title: str | None = None,
) -> Figure:
    """History, forecast mean and band (and the held-out truth, if given).

    Args:
        path: figure file to write (.png, .pdf or .svg).
        result: :func:`~prognos_torch.workflow.forecast` output.
        truth: optional series with the actual values after the forecast origin (e.g. the full
            series when the forecast was made from its training part); drawn up to a quarter
            of the horizon past the forecast's end. Where its rows after the origin are not
            one step apart (a recording gap), they are also drawn at the steps they are
            compared with (:meth:`~prognos_torch.workflow.ForecastResult.observed`).
        history: number of past values shown (default ``max(4 H, 200)``).
    """
    check_result(result, "ForecastResult", "lower", "plot_forecast")
    _check_history(history)
    fig = Figure(figsize=(7.5, 4.0))
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    th, xh = _history_tail(result.history, result.horizon, history)
    tf = as_numpy(result.time)
    ax.plot(th, xh, color="0.25", lw=1.0, label="observed")
    if truth is not None:
        tt, xt = as_numpy(truth.t), as_numpy(truth.values)
        sel = (tt > th[-1]) & (tt <= tf[-1] + 0.25 * (tf[-1] - th[-1]))
        ax.plot(tt[sel], xt[sel], color="k", lw=1.0, ls=":", label="observed after origin")
        # the score pairs row k with step k; after a recording gap, show that pairing
        vals = result.observed(truth)[0]
        if vals.numel() and result.row_offset(truth) > 0.5 * result.history.dt:
            ax.plot(tf[: vals.numel()], as_numpy(vals), ls="none", marker=".", ms=3, color="k",
                    label="the same rows at their steps (after a gap)")  # fmt: skip
    pct = f"{100 * result.level:g} %"
    ax.fill_between(
        tf,
        as_numpy(result.lower),
        as_numpy(result.upper),
        color="C0",
        alpha=0.25,
        label=f"{pct} band",
    )
    ax.plot(
        tf, as_numpy(result.mean), color="C0", lw=1.5, label=f"forecast ({result.filter.upper()})"
    )
    ax.axvline(th[-1], color="0.6", lw=0.8, ls="--")
    time_axis(ax, result.history)
    ax.set_ylabel(result.history.name)
    ax.set_title(title or f"{result.horizon}-step forecast of {result.history.name}")
    ax.legend(loc="best", fontsize=8)
    return write_png(fig, path)


def plot_rul(
    path: str | os.PathLike,
    result: RULResult,
    *,
    history: int | None = None,
    n_paths: int = 20,
    title: str | None = None,
) -> Figure:
    """Top: history, predicted paths (5-95 % band, median, a few paths) and the threshold;
    paths far beyond the data and the threshold (an exponential path can overflow to inf) are
    drawn clipped near them. Bottom: the RUL pmf (paper 002, Fig. 11-12), with the censored
    mass stated.

    A result of :func:`~prognos_torch.workflow.prognose` (it carries an onset) is drawn by
    :func:`~prognos_torch.plots.plot_prognosis` instead: the data from a little before onset,
    the paths until the threshold and the pmf on the scale of its RUL (``history`` does not
    apply there).

    Args:
        path: figure file to write (.png, .pdf or .svg).
        result: :func:`~prognos_torch.workflow.rul` or :func:`~prognos_torch.workflow.prognose`
            output.
        history: number of past values shown (``rul`` results; default ``max(4 H, 200)``).
        n_paths: sample paths drawn.
        title: figure title.
    """
    check_result(result, "RULResult", "distribution", "plot_rul")
    _check_history(history)
    if result.onset is not None:  # a prognose result
        if history is not None:
            raise ValueError(
                "history applies to rul() results; a prognose result is drawn from a little "
                "before its onset (plot_prognosis)"
            )
        return plot_prognosis(path, result, n_paths=n_paths, title=title)
    fig = Figure(figsize=(7.5, 6.0))
    FigureCanvasAgg(fig)
    ax, bx = fig.add_subplot(2, 1, 1), fig.add_subplot(2, 1, 2)
    th, xh = _history_tail(result.history, result.horizon, history)
    tf = result.t_last + result.dt * np.arange(1, result.horizon + 1)
    ax.plot(th, xh, color="0.25", lw=1.0, label="observed")
    seen = np.append(xh[np.isfinite(xh)], result.threshold)  # (NaN: missing values)
    lo, hi = float(seen.min()), float(seen.max())
    paths = clip_for_drawing(as_numpy(result.paths), lo, hi)
    draw_paths(ax, tf, paths, result.weights, threshold=result.threshold, n_show=n_paths)
    time_axis(ax, result.history)
    ax.set_ylabel(result.history.name)
    ax.legend(loc="best", fontsize=8)
    ax.set_title(
        title or f"RUL at {time_text(result.history, result.t_last)} ({result.filter.upper()})"
    )

    d = result.distribution
    support, pmf = as_numpy(d.support), as_numpy(d.pmf)
    bx.bar(support, pmf, width=result.dt, color="C0", alpha=0.7, label="RUL pmf")
    s = result.summary()
    if s["median"] is not None:
        bx.axvline(s["median"], color="k", lw=1.0, label=f"median {s['median']:.4g}")
    if s["mean"] is not None:
        bx.axvline(s["mean"], color="C3", lw=1.0, ls="--", label=f"mean {s['mean']:.4g}")
    if result.fully_censored:
        bx.text(
            0.5,
            0.5,
            f"no path reaches {result.threshold:g} within {result.bound:g} {result.time_unit}",
            transform=bx.transAxes,
            ha="center",
        )
    elif result.censored_mass > 0:
        bx.text(
            0.98,
            0.9,
            f"P(RUL > {result.bound:g}) = {result.censored_mass:.2f}",
            transform=bx.transAxes,
            ha="right",
            fontsize=8,
        )
    bx.set_xlim(0, result.bound + result.dt)
    bx.set_xlabel(f"RUL ({result.time_unit})")
    bx.set_ylabel("probability")
    if s["median"] is not None or s["mean"] is not None:
        bx.legend(loc="upper left", fontsize=8)
    return write_png(fig, path)
