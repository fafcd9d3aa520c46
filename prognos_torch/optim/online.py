"""Sample-by-sample training around :func:`~prognos_torch.optim.fit`: blocks and online use.

* :func:`train_in_blocks`: one sample per step in time order, cut into blocks of ``block``
  steps; the same optimiser steps as one ``fit`` call, plus a training curve (mean loss per
  block).
* :func:`predict_then_update`: online one-step prediction on a stream (paper 003 Sec. V-B
  reading "online"): each sample is predicted first, then used for one optimiser step.

Both work with a :class:`~prognos_torch.optim.KalmanOptimizer` (one run or ``runs=R`` batched
runs) and with gradient optimisers (``torch.optim.Adam``, ...); the optimiser keeps its state
between the calls to ``fit``.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import NamedTuple

import torch
from torch import Tensor, nn

from ..core.validation import check_pos_int
from .fit import _check_data, _check_values, _fit, _observed_mse
from .kalman import KalmanOptimizer

__all__ = ["BlockCurve", "train_in_blocks", "predict_then_update"]


class BlockCurve(NamedTuple):
    """Training curve of :func:`train_in_blocks`.

    Attributes:
        steps: optimiser steps taken at the end of each block (cumulative, over all passes).
        losses: ``(n_blocks,)`` mean loss of the steps of each block, ``(n_blocks, R)`` for a
            :class:`KalmanOptimizer` with ``runs=R`` (Kalman: squared innovation before each
            update; gradient optimisers: the loss before each step).
        seconds: time spent in the optimiser steps (evaluation excluded).
    """

    steps: list[int]
    losses: Tensor
    seconds: float


def _rows(optimizer) -> int:
    """The sample dim: 1 for a Kalman optimiser with per-run data ``(R, N, ...)``, else 0."""
    return int(isinstance(optimizer, KalmanOptimizer) and optimizer.per_run_data)


def _step_through(module, optimizer, X: Tensor, Y: Tensor, missing: bool):
    """One :func:`fit` call, one sample per step, on a block of the stream. With missing
    targets anywhere in the stream a block may observe none (a run's, with per-run data): the
    Kalman steps are then the filter's predictions and a gradient optimiser takes no step, as
    in one ``fit`` call over the whole stream, whose default loss every block uses too."""
    return _fit(
        module,
        optimizer,
        (X, Y),
        epochs=1,
        batch_size=1,
        shuffle=False,
        generator=None,
        val=None,
        early_stopping=None,
        restore_best=False,
        drop_last=False,
        progress=False,
        metrics=("mse",),
        loss_fn=_observed_mse if missing else None,
        compile=False,
        observed=False,
    )


def train_in_blocks(
    module: nn.Module,
    optimizer: torch.optim.Optimizer,
    X: Tensor,
    Y: Tensor,
    block: int,
    passes: int = 1,
) -> BlockCurve:
    """Train with :func:`fit` (one sample per step, time order) in blocks of ``block`` steps.

    The optimiser keeps its state between the blocks, so this takes the same sequence of steps
    as ``fit(module, optimizer, (X, Y), epochs=passes, batch_size=1)`` (the Kalman parameters
    and gradient-trained weights agree exactly); it also records the mean loss of each block.
    The last block of a pass may be shorter than ``block``.

    Args:
        module: the learner (the optimiser was built on it).
        optimizer: a :class:`KalmanOptimizer` or a ``torch.optim.Optimizer``.
        X: ``(N, ...)`` inputs; Y: ``(N, ...)`` targets (``module(X).shape``); ``(R, N, ...)``
            for a :class:`KalmanOptimizer` with ``per_run_data``. NaN in ``Y`` marks a missing
            target, as for :func:`fit`; a block may observe none (its loss is NaN), the stream
            (every run's) needs one.
        block: optimiser steps per point of the curve.
        passes: sweeps over the samples.
    Returns:
        :class:`BlockCurve`.
    """
    d = _rows(optimizer)
    X, Y = _check_data((X, Y), "(X, Y)", optimizer.runs if d else None)
    missing = _check_values(X, Y, "(X, Y)", optimizer.runs if d else None)
    block, passes = check_pos_int(block, "block"), check_pos_int(passes, "passes")
    steps, losses, secs, done = [], [], 0.0, 0
    N = X.shape[d]
    for _ in range(passes):
        for a in range(0, N, block):
            n = min(block, N - a)
            h = _step_through(module, optimizer, X.narrow(d, a, n), Y.narrow(d, a, n), missing)
            done += h.steps
            steps.append(done)
            losses.append(h.loss[0])
            secs += h.train_time
    return BlockCurve(steps, torch.stack(losses), secs)


def predict_then_update(
    module: nn.Module,
    optimizer: torch.optim.Optimizer,
    X: Tensor,
    Y: Tensor,
    predict: Callable[[Tensor], Tensor] | None = None,
) -> tuple[Tensor, float]:
    """Online one-step prediction: predict each sample, then take one :func:`fit` step on it.

    Sample ``k`` is predicted by the parameters trained on the samples before it
    (``predict(X[k:k+1])`` without gradients), then the optimiser takes one step on
    ``(X[k:k+1], Y[k:k+1])``.

    Args:
        module, optimizer: as for :func:`fit`.
        X: ``(N, ...)`` inputs; Y: ``(N, ...)`` targets, in stream order (``(R, N, ...)`` for
            a :class:`KalmanOptimizer` with ``per_run_data``). NaN in ``Y`` marks a missing
            target, as for :func:`fit`: a sample with none observed is still predicted, then
            the Kalman step is the filter's prediction alone and a gradient optimiser takes
            none; the stream (every run's) needs one observed target.
        predict: ``(1, ...) -> (..., 1, *out)`` (default: ``optimizer.predict`` for a
            :class:`KalmanOptimizer`, whose ``runs=R`` give ``(R, 1, *out)``, else ``module``).
    Returns:
        ``(predictions, seconds)``: predictions ``(..., N, *out)`` (the runs, if any, lead) and
        the seconds spent predicting and stepping.
    """
    d = _rows(optimizer)
    X, Y = _check_data((X, Y), "(X, Y)", optimizer.runs if d else None)
    missing = _check_values(X, Y, "(X, Y)", optimizer.runs if d else None)
    if predict is None:
        predict = optimizer.predict if isinstance(optimizer, KalmanOptimizer) else module
    if not callable(predict):
        raise TypeError(f"predict must be callable (1, ...) -> (..., 1, *out), got {predict!r}")
    preds, secs, tail = [], 0.0, Y.dim() - d  # tail: the sample dim and the output dims
    for k in range(X.shape[d]):
        xk, yk = X.narrow(d, k, 1), Y.narrow(d, k, 1)
        t0 = time.perf_counter()
        with torch.no_grad():
            out = predict(xk)
        secs += time.perf_counter() - t0
        want = (1, *Y.shape[d + 1 :])  # one sample, then the output (as the targets)
        if not isinstance(out, Tensor) or tuple(out.shape[out.dim() - tail :]) != want:
            got = tuple(out.shape) if isinstance(out, Tensor) else type(out).__name__
            raise ValueError(
                f"predict must return (..., {', '.join(map(str, want))}) for one sample (the "
                f"targets' shape per sample {tuple(Y.shape[d + 1 :])} after a sample dim of 1), "
                f"got {got}"
            )
        preds.append(out.select(out.dim() - tail, 0))  # the run dims lead the sample dim
        h = _step_through(module, optimizer, xk, yk, missing)
        secs += h.train_time
    return torch.stack(preds, -tail), secs
