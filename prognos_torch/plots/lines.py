"""Line panels: several labelled series per axes, one axes per panel (predictions, errors).

Like the rest of :mod:`prognos_torch.plots`: a fresh Agg figure, a PNG written to ``path``,
the figure returned; values may be tensors (any device) or array-likes.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from ..core.validation import check_pos_int
from ._arrays import write_png
from .figures import PathLike, _np, _same_len

__all__ = [
    "LinePanel",
    "plot_line_panels",
    "plot_line_row",
    "plot_prediction_errors",
    "break_at_gaps",
]


@dataclass(frozen=True)
class LinePanel:
    """One axes of :func:`plot_line_panels`.

    Attributes:
        lines: ``label -> (T,)`` series, drawn in order with colours ``C0, C1, ...``.
        title, ylabel: axes title and y label.
        logy: logarithmic y axis.
        truth: optional ``(T,)`` reference drawn in black under the series.
        truth_label: its legend label.
        hline: optional constant (e.g. a failure threshold) drawn as a dotted red line.
        hline_label: its legend label (default ``"threshold <value>"``).
        style: matplotlib line style of the series (``"-"``, ``"--"``, ``".-"``).
        legend: legend location (``None``: no legend).
        x: this panel's own ``(T',)`` x values (default: the figure's common ``x``), e.g. a
            zoom on a part of the series.
        gap: break the lines where consecutive x values are more than ``gap`` apart (a record
            with pauses); ``None``: connect every point.
        vline: optional x position (e.g. an end of life) drawn as a dotted grey line.
        vline_label: its legend label.
    """

    lines: Mapping[str, object]
    title: str = ""
    ylabel: str = ""
    logy: bool = False
    truth: object | None = None
    truth_label: str = "truth"
    hline: float | None = None
    hline_label: str | None = None
    style: str = "-"
    legend: str | None = "best"
    x: object | None = None
    gap: float | None = None
    vline: float | None = None
    vline_label: str | None = None


def break_at_gaps(x, *ys, gap: float) -> list[np.ndarray]:
    """``[x, *ys]`` with a NaN inserted wherever ``x`` jumps by more than ``gap``, so that a
    plotted line breaks there instead of bridging the pause. ``x`` and each ``y``: ``(T,)``."""
    xs = _np(x, "x")
    cut = np.nonzero(np.diff(xs) > gap)[0] + 1
    out = [np.insert(xs, cut, np.nan)]
    for i, y in enumerate(ys):
        y = _np(y, f"ys[{i}]")
        _same_len(xs, y, "x", f"ys[{i}]")
        out.append(np.insert(y, cut, np.nan))
    return out


def plot_line_panels(
    path: PathLike,
    x,
    panels: Sequence[LinePanel],
    *,
    ncols: int = 1,
    sharey: bool = False,
    xlabel: str = "time",
    title: str | None = None,
    alternate: bool = False,
    lw: float = 1.1,
    figsize: tuple[float, float] | None = None,
) -> Figure:
    """Panels of labelled lines over a common ``x`` ``(T,)``.

    Args:
        panels: the :class:`LinePanel` of each axes, row by row.
        ncols: axes per row; sharey: one y scale for all axes.
        xlabel: x label of every axes; title: figure title (suptitle).
        alternate: draw every second series wide and pale under the others, so that series
            that coincide stay visible.
        lw: line width of the series.
    """
    xs = _np(x, "x")
    if not panels:
        raise ValueError("panels must hold at least one LinePanel")
    check_pos_int(ncols, "ncols")
    ncols = min(int(ncols), len(panels))
    nrows = -(-len(panels) // ncols)
    if figsize is None:
        figsize = (7.0 if ncols == 1 else 5.5 * ncols, 3.0 * nrows + (0.6 if title else 0.0))
    fig = Figure(figsize=figsize)
    FigureCanvasAgg(fig)
    axes = fig.subplots(nrows, ncols, squeeze=False, sharey=sharey).ravel()
    for ax in axes[len(panels) :]:
        ax.set_visible(False)
    for ax, panel in zip(axes, panels):
        if not isinstance(panel, LinePanel):
            raise TypeError(f"panels must be LinePanel objects, got {type(panel)}")
        px = xs if panel.x is None else _np(panel.x, "panel.x")

        def xy(y, name, px=px, gap=panel.gap):
            y = _np(y, name)
            _same_len(px, y, "x", name)
            return (px, y) if gap is None else tuple(break_at_gaps(px, y, gap=gap))

        if panel.truth is not None:
            ax.plot(*xy(panel.truth, "truth"), "k-", lw=1.6, label=panel.truth_label)
        if panel.hline is not None:
            label = panel.hline_label or f"threshold {panel.hline:g}"
            ax.axhline(panel.hline, color="C3", lw=0.9, ls=":", label=label)
        if panel.vline is not None:
            ax.axvline(panel.vline, color="0.4", lw=0.9, ls=":", label=panel.vline_label)
        for i, (label, y) in enumerate(panel.lines.items()):
            w, a = (3.5, 0.45) if alternate and i % 2 else (lw, 1.0)
            ax.plot(
                *xy(y, f"lines[{label!r}]"),
                panel.style,
                color=f"C{i}",
                lw=w,
                alpha=a,
                ms=3.5,
                label=label,
            )
        if panel.logy:
            ax.set_yscale("log")
        ax.set_xlabel(xlabel)
        if panel.ylabel:
            ax.set_ylabel(panel.ylabel)
        if panel.title:
            ax.set_title(panel.title, fontsize=10)
        if panel.legend:
            ax.legend(loc=panel.legend, fontsize=8)
    if title:
        fig.suptitle(title, fontsize=10)
    return write_png(fig, path, make_folder=True)


def plot_line_row(
    path: PathLike,
    x,
    panels: Mapping[str, Mapping[str, object]],
    *,
    ylabel: str = "",
    xlabel: str = "time",
    title: str | None = None,
    logy: bool = False,
    style: str = "-",
    figsize: tuple[float, float] | None = None,
) -> Figure:
    """One row of axes on one y scale, one per panel ``title -> {label: (T,) series}``.

    A shorthand of :func:`plot_line_panels` for side-by-side readings of the same methods (the
    same labels, hence colours, in every panel): ``ylabel`` on the first axes only; ``figsize``
    ``(7.5, 4.2)`` for one panel and ``(5.5 n, 4.2)`` for ``n`` by default.

    Args:
        x: ``(T,)`` common x values; logy: logarithmic y axis; style: line style of the series.
    """
    n = len(panels)
    return plot_line_panels(
        path,
        x,
        [
            LinePanel(lines, title=t, ylabel=ylabel if i == 0 else "", logy=logy, style=style)
            for i, (t, lines) in enumerate(panels.items())
        ],
        ncols=max(n, 1),
        sharey=True,
        xlabel=xlabel,
        title=title,
        figsize=figsize or (7.5 if n == 1 else 5.5 * n, 4.2),
    )


def plot_prediction_errors(
    path: PathLike,
    t,
    truth,
    predictions: Mapping[str, object],
    *,
    title: str,
    ylabel: str,
    xlabel: str = "time",
    truth_label: str = "truth",
    threshold: float | None = None,
    error_ylabel: str = "absolute error",
    alternate: bool = False,
) -> Figure:
    """(a) predictions of several methods against the truth, (b) their absolute errors (log).

    Args:
        t, truth: ``(T,)``; predictions: ``label -> (T,)``.
        threshold: optional failure threshold drawn in (a).
        alternate: see :func:`plot_line_panels`.
    """
    tt, tr = _np(t, "t"), _np(truth, "truth")
    _same_len(tt, tr, "t", "truth")
    errors = {}
    for k, v in predictions.items():  # lengths first: NumPy would broadcast a length-1 series
        v = _np(v, f"predictions[{k!r}]")
        _same_len(tt, v, "t", f"predictions[{k!r}]")
        errors[k] = np.abs(v - tr)
    panels = [
        LinePanel(
            predictions,
            title=f"(a) {title}",
            ylabel=ylabel,
            truth=tr,
            truth_label=truth_label,
            hline=threshold,
            style="--",
            legend="upper left",
        ),
        LinePanel(
            errors,
            title="(b) prediction error",
            ylabel=error_ylabel,
            logy=True,
            legend="lower right",
        ),
    ]
    return plot_line_panels(path, t, panels, xlabel=xlabel, alternate=alternate, figsize=(7.0, 6.0))
