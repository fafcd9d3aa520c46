"""Figures: one home for every plot of the library, the studies and the workflow.

Every function draws on a fresh :class:`matplotlib.figure.Figure` (Agg canvas, no pyplot state,
no window), writes a PNG to ``path`` atomically (never half-written) and returns the figure.
Inputs may be tensors (any device) or array-likes.

* :mod:`.figures`: predictions, fading factors, fault probabilities, RUL distributions,
  alpha-lambda charts, training curves;
* :mod:`.panels`: a grid of small panels, estimated multivariate series against the truth;
* :mod:`.lines`: panels of labelled lines (:func:`plot_line_panels`; one row on one y scale:
  :func:`plot_line_row`), predictions with their errors (:func:`plot_prediction_errors`);
* :mod:`.heatmap`: annotated heatmaps of a results matrix (:func:`plot_heatmaps`);
* :mod:`.rul`: predicted RUL over prediction time with the alpha cone (:func:`plot_rul_band`),
  predicted paths against a threshold (:func:`plot_paths`);
* :mod:`.workflow`: a forecast with its band and an RUL distribution with its paths (the
  figures of :mod:`prognos_torch.workflow`);
* :mod:`.prognosis`: a :func:`~prognos_torch.workflow.prognose` result (paths with the
  threshold, RUL pmf), a grid of them, and RUL trajectories against the alpha cone.
"""

from ._arrays import time_axis, time_label
from .figures import (
    plot_alpha_lambda,
    plot_fading_factor,
    plot_fault_probability,
    plot_fault_probability_box,
    plot_prediction,
    plot_rul_pdf,
    plot_training_curves,
)
from .heatmap import HeatmapPanel, draw_heatmap, plot_heatmaps
from .lines import (
    LinePanel,
    break_at_gaps,
    plot_line_panels,
    plot_line_row,
    plot_prediction_errors,
)
from .panels import plot_panels
from .prognosis import plot_prognosis, plot_prognosis_grid, plot_rul_trajectory
from .rul import draw_paths, plot_paths, plot_rul_band, weighted_quantiles
from .workflow import plot_forecast, plot_rul

__all__ = [
    "plot_prediction",
    "plot_fading_factor",
    "plot_rul_pdf",
    "plot_alpha_lambda",
    "plot_fault_probability",
    "plot_fault_probability_box",
    "plot_training_curves",
    "plot_panels",
    "LinePanel",
    "plot_line_panels",
    "plot_line_row",
    "break_at_gaps",
    "plot_prediction_errors",
    "HeatmapPanel",
    "draw_heatmap",
    "plot_heatmaps",
    "plot_rul_band",
    "draw_paths",
    "plot_paths",
    "weighted_quantiles",
    "plot_forecast",
    "plot_rul",
    "time_label",
    "time_axis",
    "plot_prognosis",
    "plot_prognosis_grid",
    "plot_rul_trajectory",
]
