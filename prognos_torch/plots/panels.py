"""Grid of small panels: several estimated multivariate series against the truth over time.

Paper 004 Fig. 2-5 style (state, fault, process-noise and measurement-noise estimates, one panel
per component). Like :mod:`prognos_torch.plots.figures`, it draws on a fresh Agg figure (no pyplot
state), saves a PNG and returns the figure. Inputs may be tensors (any device) or array-likes.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping, Sequence

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from ..core.validation import check_pos_int
from ._arrays import as_numpy, write_png

__all__ = ["plot_panels"]

PathLike = str | os.PathLike


def _arr(x, name: str) -> np.ndarray:
    a = as_numpy(x, name)
    if a.ndim == 1:
        a = a[:, None]
    if a.ndim != 2:
        raise ValueError(f"{name} must have shape (T,) or (T, P), got {a.shape}")
    return a


def plot_panels(
    path: PathLike,
    t,
    series: Mapping[str, object],
    *,
    truth=None,
    names: Sequence[str] | None = None,
    ncols: int = 3,
    clip: float | None = None,
    title: str | None = None,
    xlabel: str = "time",
    ylabel: str | None = None,
    panel_size: tuple[float, float] = (3.4, 2.2),
) -> Figure:
    """One panel per component: the truth (black) and each labelled series.

    Args:
        path: figure file to write (.png, .pdf or .svg; parent folders are created).
        t: ``(T,)`` times.
        series: non-empty mapping ``label -> (T, P)`` (or ``(T,)`` for ``P = 1``) estimates,
            drawn in order (later series on top, the truth last).
        truth: ``(T, P)`` reference values or ``None``.
        names: ``P`` panel titles (default ``"1" .. "P"``).
        ncols: panels per row.
        clip: with ``truth``, limit each panel's y axis to the truth's range widened by
            ``clip`` times its span on either side (span floor: ``1e-3 max(1, max |truth|)``), so
            that a diverging estimate does not hide the others; ``None`` lets matplotlib scale.
        title: figure title; ylabel: y label of the first column.
    Returns:
        The saved :class:`~matplotlib.figure.Figure`.
    """
    tt = as_numpy(t, "t")
    if tt.ndim != 1:
        raise ValueError(f"t must have shape (T,), got {tt.shape}")
    if not isinstance(series, Mapping) or not series:
        raise ValueError("series must be a non-empty mapping label -> (T, P) values")
    data = {str(k): _arr(v, f"series[{k!r}]") for k, v in series.items()}
    first = next(iter(data.values())).shape
    P = first[1]
    if P == 0:
        raise ValueError(f"series must have at least one component (T, P >= 1), got {first}")
    for k, v in data.items():
        if v.shape != (tt.shape[0], P):
            raise ValueError(f"series[{k!r}] must have shape ({tt.shape[0]}, {P}), got {v.shape}")
    tr = None
    if truth is not None:
        tr = _arr(truth, "truth")
        if tr.shape != (tt.shape[0], P):
            raise ValueError(f"truth must have shape ({tt.shape[0]}, {P}), got {tr.shape}")
    if names is None:
        names = [str(i + 1) for i in range(P)]
    if len(names) != P:
        raise ValueError(f"names must list {P} panel titles, got {len(names)}")
    check_pos_int(ncols, "ncols")
    if clip is not None and (tr is None or not clip > 0):
        raise ValueError("clip needs truth and a value > 0")
    ncols = min(ncols, P)
    nrows = math.ceil(P / ncols)
    fig = Figure(figsize=(panel_size[0] * ncols, panel_size[1] * nrows + 0.8), layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(nrows, ncols, squeeze=False)
    for j in range(nrows * ncols):
        ax = axes[j // ncols][j % ncols]
        if j >= P:
            ax.set_visible(False)
            continue
        for i, (label, v) in enumerate(data.items()):
            ax.plot(tt, v[:, j], color=f"C{i}", lw=0.7, alpha=0.85, label=label)
        if tr is not None:
            ax.plot(tt, tr[:, j], "k-", lw=1.3, label="truth")
            if clip is not None:
                finite = tr[np.isfinite(tr[:, j]), j]
                if finite.size:  # (a truth missing throughout: matplotlib scales)
                    lo, hi = float(finite.min()), float(finite.max())
                    span = max(hi - lo, 1e-3 * max(1.0, float(np.abs(finite).max())))
                    ax.set_ylim(lo - clip * span, hi + clip * span)
        ax.set_title(names[j], fontsize=9)
        ax.tick_params(labelsize=7)
        if j // ncols == nrows - 1 or j + ncols >= P:
            ax.set_xlabel(xlabel, fontsize=8)
        if j % ncols == 0 and ylabel:
            ax.set_ylabel(ylabel, fontsize=8)
    handles, labels = axes[0][0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="outside lower center", ncol=min(len(labels), 6), fontsize=8)
    if title:
        fig.suptitle(title, fontsize=10)
    return write_png(fig, path, make_folder=True, tight=False)
