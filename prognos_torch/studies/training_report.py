"""Figures of an optimiser comparison on one-step prediction (:mod:`.training` results), in the
style of paper 003's Fig. 3-5 and 7-8: test predictions against the truth, the absolute error
and the test MAE of each run, per reading (frozen after training, online), and the training
curves. The drawing is :mod:`prognos_torch.plots`; this module lays the results out.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from .. import plots
from .evaluate import run_errors
from .training import TrainTest

__all__ = ["training_figures"]


def training_figures(
    out_dir: Path,
    results: Mapping[str, TrainTest],
    k_test: np.ndarray,
    truth: Tensor,
    *,
    name: str,
    block: int,
    files: Sequence[str],
    readings: Mapping[str, str],
) -> list[str]:
    """Four figures of one data set; returns ``files``.

    Args:
        results: ``{optimiser: TrainTest}`` with ``R`` runs each, trained over the same blocks.
        k_test: ``(N,)`` sample index of each test target; truth: ``(N,)`` the targets.
        name: the data set's name (titles); block: optimiser steps per curve point.
        files: the four file names: predictions, absolute error, MAE per run, training curves.
        readings: ``{label: TrainTest field}`` of the test predictions to draw (``"pred"``,
            ``"online_pred"``); a reading that some result lacks is left out.
    """
    names, first = list(results), next(iter(results.values()))
    get = {r: {n: getattr(results[n], key) for n in names} for r, key in readings.items()
           if all(getattr(o, key) is not None for o in results.values())}  # fmt: skip
    plots.plot_panels(
        out_dir / files[0],
        k_test,
        {f"{r}, run 0": torch.stack([p[0] for p in g.values()], -1) for r, g in get.items()},
        truth=truth[:, None].expand(-1, len(names)),
        names=names,
        ncols=2,
        clip=0.3 if len(get) > 1 else None,
        xlabel="sample k",
        panel_size=(4.6, 2.4),
        title=f"{name}: one-step-ahead test predictions vs truth (scaled to [0, 1])",
    )
    err = {r: {n: (p[0] - truth).abs() for n, p in g.items()} for r, g in get.items()}
    plots.plot_line_row(out_dir / files[1], k_test, err, xlabel="sample k", logy=True,
                        ylabel="absolute error",
                        title=f"{name}: absolute one-step prediction error (run 0)")  # fmt: skip
    mae = {r: {n: run_errors(p, truth)["MAE"] for n, p in g.items()} for r, g in get.items()}
    plots.plot_line_row(out_dir / files[2], np.arange(first.pred.shape[0]), mae, logy=True,
                        ylabel="test MAE", xlabel="Monte Carlo run (ANFIS initialisation)",
                        style="o-", title=f"{name}: test MAE of each run")  # fmt: skip
    curves = {f"squared error before each step, mean over blocks of {block} steps and over "
              "runs": {n: results[n].curve.mean(-1) for n in names}}  # fmt: skip
    plots.plot_line_row(out_dir / files[3], first.curve_steps, curves, logy=True,
                        xlabel="optimiser steps (training samples seen)", ylabel="training loss",
                        title=f"{name}: training curves (one pass, one sample per step)",
                        style="o-")  # fmt: skip
    return list(files)
