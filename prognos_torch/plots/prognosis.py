"""Figures of :func:`~prognos_torch.workflow.prognose` results and of RUL trajectories.

* :func:`plot_prognosis`: the data since a little before onset, sample paths with their 5-95 %
  band and median until the threshold, the threshold, the onset, and the RUL pmf beneath with the
  censored mass stated;
* :func:`plot_prognosis_grid`: those panels for several series and prediction times;
* :func:`plot_rul_trajectory`: predicted RUL (median and 90 % interval) against the true RUL
  line and the alpha cone ``[(1 - alpha) r*, (1 + alpha) r*]`` (Saxena et al. 2010), one panel
  per series.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from ..core.validation import check_count, check_nonneg, check_pos_int
from ._arrays import as_numpy, check_result, clip_for_drawing, time_axis, time_text, write_png

if TYPE_CHECKING:  # annotations only: the workflow imports the plots, not the reverse
    from ..workflow.predict import RULResult

__all__ = ["plot_prognosis", "plot_prognosis_grid", "plot_rul_trajectory"]


def _check_len(x: np.ndarray, times: np.ndarray, name: str) -> None:
    """``x`` must be ``(P,)`` like the panel's times (matplotlib broadcast a length 1)."""
    if x.shape != times.shape:
        raise ValueError(f"{name} must have shape {times.shape} like the times, got {x.shape}")


def _reach(summary: dict, bound: float, shown: float) -> float:
    """How far past the last observation the figure looks: to the RUL's 95 % quantile (the
    horizon when more than 5 % is censored), but no further than 3 x the median or the width of
    the history drawn, whichever is longer. A heavy right tail would otherwise squeeze the data,
    the median crossing and what followed into the left edge; the pmf panel and its censored
    mass state the tail. Without an RUL (no degradation yet) the bound is no forecast: the
    figure looks a quarter of the history drawn ahead, or to the bound when it is nearer."""
    if summary["status"] != "ok":
        return max(min(bound, 0.25 * shown), 0.05 * shown)
    reach = summary["q95"] if summary["q95"] is not None else bound
    if summary["median"] is not None:
        reach = min(reach, max(3.0 * summary["median"], shown))
    return max(reach, 0.05 * shown)


def _bars(sup: np.ndarray, pmf: np.ndarray, dt: float, upto: float):
    """Histogram of the RUL pmf for drawing: bars of a whole number of RUL bins (1.5 bins a bar
    would alternate 1 and 2: a comb), at least ``upto / 200`` wide, widened (doubling, up to
    ``upto / 20``) while more than a tenth of the bars inside the mass are empty, as where the
    paths' time grid is coarser than the RUL bins far ahead."""
    k = max(1, math.ceil(upto / 200.0 / dt))
    while True:
        width = k * dt
        edges = np.arange(0.5 * dt, upto + width, width)
        hist, _ = np.histogram(sup, bins=edges, weights=pmf)
        full = np.flatnonzero(hist > 0)
        inside = hist[full[0] : full[-1] + 1] if full.size else hist
        if full.size == 0 or np.mean(inside == 0) <= 0.1 or width * 2 > upto / 20.0:
            return edges, hist
        k *= 2


def plot_prognosis(
    path: str | os.PathLike | None,
    result: RULResult,
    *,
    truth=None,
    n_paths: int = 30,
    title: str | None = None,
    ax=None,
) -> Figure:
    """Paths with the threshold (top) and the RUL pmf (bottom) of a ``prognose`` result.

    Args:
        path: figure file to write (.png, .pdf or .svg), or ``None``.
        result: a :class:`RULResult` from :func:`~prognos_torch.workflow.prognose`.
        truth: optional ``(t, y)`` tensors of what followed (drawn in grey).
        n_paths: sample paths drawn.
        title: figure title.
        ax: draw only the top panel into this matplotlib axis (no file is written).
    """
    check_result(result, "RULResult from prognose", "distribution", "plot_prognosis", "(or None) ")
    check_count(n_paths, "n_paths", 0, error=ValueError)
    if truth is not None:
        if not isinstance(truth, (tuple, list)) or len(truth) != 2:
            raise ValueError("truth must be a pair (t, y) of (T,) values")
        tt, yt = as_numpy(truth[0], "truth t"), as_numpy(truth[1], "truth y")
        if tt.ndim != 1 or yt.shape != tt.shape:
            raise ValueError(
                f"truth must be a pair (t, y) of (T,) values, got shapes {tt.shape}, {yt.shape}"
            )
    own = ax is None
    fig = None
    if own:
        fig = Figure(figsize=(7.5, 6.0))
        FigureCanvasAgg(fig)
        ax, bx = fig.add_subplot(2, 1, 1), fig.add_subplot(2, 1, 2)
    h = result.history
    th, yh = as_numpy(h.t), as_numpy(h.values)
    t0 = th[0]
    on = result.onset
    if on is not None and on.detected:
        span = result.t_last - on.time
        t0 = max(th[0], on.time - 0.5 * max(span, 1e-12))
        ax.axvline(on.time, color="C2", lw=0.8, ls=":", label="onset")
    keep = th >= t0
    ax.plot(th[keep], yh[keep], ".", ms=2, color="0.2", label="observed")
    s = result.summary()
    reach = _reach(s, result.bound, result.t_last - t0)
    t_end = result.t_last + reach
    if truth is not None:
        sel = (tt > result.t_last) & (tt <= t_end)
        ax.plot(tt[sel], yt[sel], ".", ms=2, color="0.65", label="what followed")
    ylo, yhi = float(np.min(yh[keep])), float(np.max(yh[keep]))
    lo_t, hi_t = min(ylo, result.threshold), max(yhi, result.threshold)
    pad = 0.15 * (hi_t - lo_t) if hi_t > lo_t else 1.0
    if result.status == "ok":
        tf = result.t_last + result.dt * np.arange(1, result.horizon + 1)
        m = tf <= t_end
        P = clip_for_drawing(as_numpy(result.paths)[:, m], lo_t, hi_t)
        if P.shape[1]:
            lo, med, hi = np.quantile(P, [0.05, 0.5, 0.95], axis=0)
            ax.fill_between(tf[m], lo, hi, color="C1", alpha=0.2, label="paths 5-95 %")
            for p in P[:n_paths]:
                ax.plot(tf[m], p, color="C1", lw=0.3, alpha=0.6)
            ax.plot(tf[m], med, color="C1", lw=1.3, label="median path")
    ax.axhline(result.threshold, color="C3", lw=1.0, ls="--", label="threshold")
    ax.set_xlim(t0, t_end)
    ax.set_ylim(lo_t - pad, hi_t + pad)
    time_axis(ax, h)
    ax.set_ylabel(h.name)
    ax.legend(loc="best", fontsize=7)
    unit = result.time_unit
    if result.status != "ok":
        told = f"{result.status}, RUL > {s['bound']:.3g} {unit}"
    elif s["median"] is None:
        told = f"median RUL > {result.bound:.3g} {unit} ({result.model})"
    else:
        told = f"median RUL {s['median']:.3g} {unit} ({result.model})"
    ax.set_title(title or f"at {time_text(h, result.t_last)}: {told}", fontsize=9)
    if not own:
        return ax.figure
    d = result.distribution
    if result.status == "ok":
        sup, pmf = as_numpy(d.support), as_numpy(d.pmf)
        upto = 1.5 * reach
        m = sup <= upto
        edges, hist = _bars(sup[m], pmf[m], result.dt, upto)
        width = edges[1] - edges[0]
        bx.bar(edges[:-1], hist, width=width, align="edge", color="C0", alpha=0.7)
        for q, name in ((s["q05"], "q05"), (s["median"], "median"), (s["q95"], "q95")):
            if q is not None and q <= upto:
                bx.axvline(q, color="k", lw=0.8, ls="-" if name == "median" else ":")
        bx.set_xlim(0.0, upto)
        # a quantile beyond the horizon (censored paths) is known only to exceed the bound
        q = [(f"> {result.bound:.3g}" if s[k] is None else f"{s[k]:.3g}")
             for k in ("median", "q05", "q95")]  # fmt: skip
        bx.text(0.98, 0.9, f"median {q[0]}, 90 % [{q[1]}, {q[2]}]\n"
                f"P(RUL > {result.bound:.3g} {unit}) = {result.censored_mass:.2f}",
                transform=bx.transAxes, ha="right", va="top", fontsize=8)  # fmt: skip
    else:
        bx.text(0.5, 0.5, f"{result.status}: RUL > {s['bound']:.3g} {unit}",
                transform=bx.transAxes, ha="center")  # fmt: skip
    bx.set_xlabel(f"RUL ({unit})")
    bx.set_ylabel("probability")
    return write_png(fig, path)


def plot_prognosis_grid(
    path: str | os.PathLike | None,
    rows: Sequence[tuple[str, Sequence[RULResult], tuple]],
    *,
    dpi: int = 60,
) -> Figure:
    """One row of :func:`plot_prognosis` top panels per series, one panel per prediction time.

    Args:
        path: figure file (.png, .pdf or .svg), or ``None``.
        rows: ``(name, results, truth)`` per series: its ``prognose`` results in time order and
            the whole series ``(t, y)`` drawn as what followed each prediction.
        dpi: resolution (the grid is large).
    """
    if not rows or not all(len(r[1]) for r in rows):
        raise ValueError("rows must be a non-empty sequence of (name, results, truth) with results")
    n, k = len(rows), max(len(r[1]) for r in rows)
    fig = Figure(figsize=(3.6 * k, 2.8 * n))
    FigureCanvasAgg(fig)
    for i, (name, results, truth) in enumerate(rows):
        for j, res in enumerate(results):
            ax = fig.add_subplot(n, k, i * k + j + 1)
            at = time_text(res.history, res.t_last)
            plot_prognosis(None, res, truth=truth, ax=ax, title=f"{name}, {at}")
            ax.legend().set_visible(i == 0 and j == 0)
    return write_png(fig, path, dpi=dpi)


def plot_rul_trajectory(
    path: str | os.PathLike | None,
    panels: Sequence[dict],
    *,
    alpha: float = 0.3,
    ncols: int = 2,
    time_unit: str | None = None,
) -> Figure:
    """Predicted RUL against the truth and the alpha cone, one panel per series.

    Args:
        path: figure file (.png, .pdf or .svg), or ``None``.
        panels: dicts with ``title``, ``times`` ``(P,)``, ``true`` ``(P,)`` (NaN: missing),
            ``t_eol``, and
            ``methods``: ``{name: {"pred": (P,), "lo": (P,) | None, "hi": (P,) | None}}``
            (``inf``/NaN: no finite prediction, drawn at the top edge).
        alpha: cone half-width.
        ncols: panels per row.
        time_unit: the unit of the times and RULs, for the axis labels (e.g. ``"days"``).
    """
    check_nonneg(alpha, "alpha", numbers_only=True)  # (fill_between would flip a < 0)
    check_pos_int(ncols, "ncols")
    n = len(panels)
    unit = f" ({time_unit})" if time_unit else ""
    nrows = max(1, math.ceil(n / ncols))
    fig = Figure(figsize=(5.0 * ncols, 3.6 * nrows))
    FigureCanvasAgg(fig)
    for k, pan in enumerate(panels):
        ax = fig.add_subplot(nrows, ncols, k + 1)
        tt = as_numpy(pan["times"], f"panels[{k}]['times']")
        tr = as_numpy(pan["true"], f"panels[{k}]['true']")
        t_eol = float(pan["t_eol"])
        if tt.ndim != 1 or tt.size == 0 or not np.all(np.isfinite(tt)):
            raise ValueError(f"panels[{k}]['times'] must be finite (P,) times with P >= 1, "
                             f"got shape {tt.shape}")  # fmt: skip
        _check_len(tr, tt, f"panels[{k}]['true']")
        if not np.isfinite(tr).any():
            raise ValueError(f"panels[{k}]['true'] holds no finite true RUL")
        grid = np.linspace(tt.min() - 0.05 * (t_eol - tt.min()), t_eol, 50)
        r = t_eol - grid
        ax.fill_between(grid, (1 - alpha) * r, (1 + alpha) * r, color="0.85",
                        label=f"alpha = {alpha:g} cone")  # fmt: skip
        ax.plot(grid, r, color="k", lw=1.0, label="true RUL")
        top = 2.2 * float(tr[np.isfinite(tr)].max())  # (NaN: a missing true RUL)
        for j, (name, m) in enumerate(pan["methods"].items()):
            where = f"panels[{k}]['methods'][{name!r}]"
            p = as_numpy(m["pred"], f"{where}['pred']")
            _check_len(p, tt, f"{where}['pred']")
            if (m.get("lo") is None) != (m.get("hi") is None):
                raise ValueError(f"{where}: give both 'lo' and 'hi' or neither")
            shown = np.where(np.isfinite(p), np.minimum(p, top), top)
            dx = (j - 0.5 * (len(pan["methods"]) - 1)) * 0.01 * (t_eol - tt.min())
            ax.plot(tt + dx, shown, "o-" if j == 0 else "s--", ms=4, lw=0.8, color=f"C{j}",
                    label=name)  # fmt: skip
            if m.get("lo") is not None:
                lo, hi = (as_numpy(m[b], f"{where}[{b!r}]") for b in ("lo", "hi"))
                _check_len(lo, tt, f"{where}['lo']")
                _check_len(hi, tt, f"{where}['hi']")
                lo = np.minimum(np.nan_to_num(lo, nan=top, posinf=top), top)
                hi = np.minimum(np.nan_to_num(hi, nan=top, posinf=top), top)
                ax.vlines(tt + dx, lo, hi, color=f"C{j}", lw=2.0, alpha=0.35)
        ax.set_ylim(0, top * 1.02)
        ax.set_title(pan["title"], fontsize=9)
        ax.set_xlabel(f"prediction time{unit}")
        ax.set_ylabel(f"RUL{unit}")
        if k == 0:
            ax.legend(fontsize=6, loc="upper right")
    return write_png(fig, path)
