"""Annotated heatmaps: a matrix of results (methods x settings) with a label in every cell.

Like the rest of :mod:`prognos_torch.plots`: a fresh Agg figure, a PNG written to ``path``,
the figure returned.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import matplotlib
import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from ._arrays import as_numpy, write_png
from .figures import PathLike

__all__ = ["HeatmapPanel", "draw_heatmap", "plot_heatmaps"]


@dataclass(frozen=True)
class HeatmapPanel:
    """One heatmap.

    Attributes:
        values: ``(r, c)`` colour values; NaN cells are grey (and show their label).
        rows, cols: the ``r`` row and ``c`` column names.
        labels: ``r`` lists of ``c`` cell texts (default: the values, 3 significant digits).
        title: axes title; cmap: colour map name; clim: ``(lo, hi)`` colour limits.
        colorbar: label of the colour bar (``None``: no colour bar).
    """

    values: object
    rows: Sequence[str]
    cols: Sequence[str]
    labels: Sequence[Sequence[str]] | None = None
    title: str = ""
    cmap: str = "viridis"
    clim: tuple[float, float] | None = None
    colorbar: str | None = None


def _checked(panel: HeatmapPanel) -> tuple[np.ndarray, list[list[str]]]:
    v = as_numpy(panel.values, "values")
    shape = (len(panel.rows), len(panel.cols))
    if v.shape != shape:
        raise ValueError(f"values must have shape {shape} (rows, cols), got {v.shape}")
    if panel.labels is None:
        labels = [["" if not np.isfinite(x) else f"{x:.3g}" for x in row] for row in v]
    else:
        labels = [list(map(str, row)) for row in panel.labels]
        if len(labels) != shape[0] or any(len(row) != shape[1] for row in labels):
            raise ValueError(f"labels must be {shape[0]} rows of {shape[1]} texts")
    return v, labels


def draw_heatmap(ax, panel: HeatmapPanel):
    """Draw ``panel`` on the axes ``ax``; returns the image (for a colour bar). Cell texts are
    white on dark colours."""
    values, labels = _checked(panel)
    cm = matplotlib.colormaps[panel.cmap].with_extremes(bad="0.85")
    im = ax.imshow(np.ma.masked_invalid(values), cmap=cm, aspect="auto")
    if panel.clim is not None:
        im.set_clim(*panel.clim)
    ax.set_xticks(range(len(panel.cols)), list(panel.cols), fontsize=8)
    ax.set_yticks(range(len(panel.rows)), list(panel.rows), fontsize=8)
    for i in range(len(panel.rows)):
        for j in range(len(panel.cols)):
            v = values[i, j]
            dark = False
            if np.isfinite(v):
                r, g, b, _ = cm(im.norm(v))
                dark = 0.299 * r + 0.587 * g + 0.114 * b < 0.5
            ax.text(
                j,
                i,
                labels[i][j],
                ha="center",
                va="center",
                fontsize=7,
                color="white" if dark else "black",
            )
    ax.set_title(panel.title, fontsize=9)
    return im


def plot_heatmaps(
    path: PathLike, panels: Sequence[HeatmapPanel], *, figsize: tuple[float, float] | None = None
) -> Figure:
    """One row of heatmaps, each with its colour bar when it names one."""
    if not panels:
        raise ValueError("panels must hold at least one HeatmapPanel")
    fig = Figure(figsize=figsize or (5.0 * len(panels), 4.0))
    FigureCanvasAgg(fig)
    for k, panel in enumerate(panels):
        ax = fig.add_subplot(1, len(panels), k + 1)
        im = draw_heatmap(ax, panel)
        if panel.colorbar is not None:
            fig.colorbar(im, ax=ax, label=panel.colorbar)
    return write_png(fig, path, make_folder=True)
