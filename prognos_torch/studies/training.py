"""Timed training of a learner by an optimiser over input/target pairs, read two ways.

A study that compares optimisers on one-step prediction (paper 003: an ANFIS trained by the
EKF, SRUKF, ImSRUKF and Adam) needs, per optimiser and data set:

* :func:`train_and_test`: ``passes`` sweeps of :func:`~prognos_torch.optim.train_in_blocks`
  (one sample per step, in time order, a training curve in blocks), then the test inputs
  predicted with the parameters frozen (the batch reading) and, optionally, each test sample
  predicted first and then used for one more step
  (:func:`~prognos_torch.optim.predict_then_update`, the online reading); seconds of each part;
* :func:`kalman_runs`, :func:`runs_in_turn`: ``R`` Monte Carlo runs (initialisations) as one
  :class:`~prognos_torch.optim.KalmanOptimizer` with ``runs=R``, or one after the other with
  any optimiser; seconds per run. :func:`untrained_runs`: the initial modules as a reading;
* :func:`outcome_rows`: the ``results.csv`` rows of a reading (the errors of
  :func:`~prognos_torch.studies.run_errors` and the seconds).

The learner has one output: targets are ``(N, 1)`` and predictions drop that dim, ``(R, N)``.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Callable, Sequence
from typing import NamedTuple

import torch
from torch import Tensor, nn

from ..optim import (
    KalmanOptimizer,
    kalman_runs_optimizer,
    predict_then_update,
    train_in_blocks,
)
from .evaluate import run_errors
from .rows import run_rows
from .runner import timed

__all__ = [
    "TrainTest",
    "train_and_test",
    "kalman_runs",
    "runs_in_turn",
    "untrained_runs",
    "outcome_rows",
]

Pairs = tuple[Tensor, Tensor]  # (X (N, n_in), Y (N, 1))


class TrainTest(NamedTuple):
    """One optimiser's runs on one data set (``R`` runs lead every prediction).

    Attributes:
        pred: ``(R, N)`` test predictions with the trained parameters frozen.
        pred_train: ``(R, N_train)`` training-set predictions right after training.
        train_time: seconds of the training steps (per run for :func:`kalman_runs` and
            :func:`runs_in_turn`).
        test_time: seconds of the frozen test predictions (likewise).
        curve: ``(n_blocks, R)`` mean loss of the optimiser steps of each block
            (:class:`~prognos_torch.optim.BlockCurve`); ``None`` when untrained.
        curve_steps: optimiser steps taken at the end of each block.
        online_pred: ``(R, N)`` predict-then-update predictions of the test segment, or
            ``None`` without the online reading.
        online_time: seconds of the online pass, NaN without one.
    """

    pred: Tensor
    pred_train: Tensor
    train_time: float
    test_time: float
    curve: Tensor | None = None
    curve_steps: list[int] | None = None
    online_pred: Tensor | None = None
    online_time: float = math.nan

    def per_run(self, runs: int) -> TrainTest:
        """The seconds divided by ``runs`` (``R`` runs trained as one batch)."""
        t = (self.train_time / runs, self.test_time / runs)
        return self._replace(train_time=t[0], test_time=t[1], online_time=self.online_time / runs)


def _predict(predict: Callable[[Tensor], Tensor], X: Tensor) -> tuple[Tensor, float]:
    """``predict(X)`` without gradients, its single output dropped: ``((..., N), seconds)``."""
    with torch.no_grad():
        out, secs = timed(predict, X)
    return out[..., 0], secs


def train_and_test(
    module: nn.Module,
    optimizer: torch.optim.Optimizer,
    train: Pairs,
    test: Pairs,
    *,
    block: int,
    passes: int = 1,
    online: bool = False,
    predict: Callable[[Tensor], Tensor] | None = None,
) -> TrainTest:
    """Train on ``train`` in blocks, predict ``test`` frozen, optionally go on online.

    Args:
        module: the learner the optimiser was built on (one output).
        optimizer: a :class:`~prognos_torch.optim.KalmanOptimizer` (``runs=R`` batched runs
            lead the predictions) or a ``torch.optim.Optimizer``.
        train, test: ``(X (N, n_in), Y (N, 1))``.
        block: optimiser steps per point of the training curve; passes: sweeps over ``train``.
        online: also predict each test sample, then take one step on it (the parameters move:
            call last).
        predict: ``(N, n_in) -> (..., N, 1)``, used for every prediction (default:
            ``optimizer.predict`` for a Kalman optimiser, else ``module``).
    Returns:
        :class:`TrainTest` with the seconds of this one call (not per run).
    """
    if predict is None:
        predict = optimizer.predict if isinstance(optimizer, KalmanOptimizer) else module
    (X, Y), (Xt, Yt) = train, test
    steps, curve, t_train = train_in_blocks(module, optimizer, X, Y, block, passes)
    pred, t_test = _predict(predict, Xt)
    out = TrainTest(pred, _predict(predict, X)[0], t_train, t_test, curve, steps)
    if not online:
        return out
    p, t_online = predict_then_update(module, optimizer, Xt, Yt, predict)
    return out._replace(online_pred=p[..., 0], online_time=t_online)


def _stack_runs(parts: Sequence[TrainTest]) -> TrainTest:
    """Single runs as one :class:`TrainTest`: predictions stacked on a leading run dim, curves
    on a trailing one, seconds averaged."""

    def stack(key: str, dim: int = 0) -> Tensor | None:
        vals = [getattr(p, key) for p in parts]
        return None if vals[0] is None else torch.stack(vals, dim)

    def secs(key: str) -> float:
        return sum(getattr(p, key) for p in parts) / len(parts)

    return TrainTest(
        stack("pred"),
        stack("pred_train"),
        secs("train_time"),
        secs("test_time"),
        stack("curve", -1),
        parts[0].curve_steps,
        stack("online_pred"),
        secs("online_time"),
    )


def kalman_runs(
    inits: Sequence[nn.Module],
    train: Pairs,
    test: Pairs,
    *,
    block: int,
    passes: int = 1,
    online: bool = False,
    **kalman_options,
) -> TrainTest:
    """``R`` runs, one per initialisation, trained as one batch: a
    :class:`~prognos_torch.optim.KalmanOptimizer` with ``runs=R`` on a copy of ``inits[0]``
    starting from the parameters of every module (they must share every tensor outside the
    Kalman state). Arguments as for :func:`train_and_test`; ``kalman_options`` go to the
    optimiser (``filter``, ``P0``, ``Q``, ``R``, ...). Seconds per run (batch time / ``R``)."""
    module = copy.deepcopy(inits[0])
    opt = kalman_runs_optimizer(module, inits, **kalman_options)
    out = train_and_test(module, opt, train, test, block=block, passes=passes, online=online)
    return out.per_run(len(inits))


def runs_in_turn(
    inits: Sequence[nn.Module],
    make_optimizer: Callable[[nn.Module], torch.optim.Optimizer],
    train: Pairs,
    test: Pairs,
    *,
    block: int,
    passes: int = 1,
    online: bool = False,
) -> TrainTest:
    """``R`` runs one after the other: a copy of each initialisation trained by its own
    ``make_optimizer(module)`` (e.g. ``lambda m: torch.optim.Adam(m.parameters(), lr)``) and
    predicting through the module (a single-run Kalman optimiser keeps its posterior mean
    there). Arguments as for :func:`train_and_test`; seconds per run (mean over the runs)."""
    parts = []
    for init in inits:
        module = copy.deepcopy(init)
        opt = make_optimizer(module)
        kw = dict(block=block, passes=passes, online=online, predict=module)
        parts.append(train_and_test(module, opt, train, test, **kw))
    return _stack_runs(parts)


def untrained_runs(modules: Sequence[nn.Module], X_train: Tensor, X_test: Tensor) -> TrainTest:
    """The modules as they are: their predictions of ``X_train`` ``(N_train, n_in)`` and
    ``X_test`` ``(N, n_in)``, no training time, the prediction seconds per run."""
    parts = []
    for m in modules:
        pred, secs = _predict(m, X_test)
        parts.append(TrainTest(pred, _predict(m, X_train)[0], 0.0, secs))
    return _stack_runs(parts)


def outcome_rows(
    method: str, out: TrainTest, y_train: Tensor, y_test: Tensor, *, online: bool = False
) -> list[dict]:
    """The ``results.csv`` rows of one reading, one per run.

    Args:
        method: the row label.
        out: the runs; online: score ``out.online_pred`` and the online seconds instead of the
            frozen predictions.
        y_train: ``(N_train,)``, y_test: ``(N,)`` targets.
    Returns:
        Per run ``MAE``, ``RMSE``, ``MSE`` on the test segment (:func:`run_errors`),
        ``train_MAE`` of ``out.pred_train``, and ``train_time_s``, ``test_time_s`` and their
        sum ``time_s``, rounded to the microsecond.
    """
    if online and out.online_pred is None:
        raise ValueError(
            f"online=True needs the online reading, but {method!r} was run without it "
            "(train_and_test(..., online=True))"
        )
    pred, test_time = (out.online_pred, out.online_time) if online else (out.pred, out.test_time)
    err = run_errors(pred, y_test)
    err["train_MAE"] = run_errors(out.pred_train, y_train)["MAE"]
    err["train_time_s"], err["test_time_s"] = round(out.train_time, 6), round(test_time, 6)
    return run_rows(method, err | {"time_s": round(out.train_time + test_time, 6)})
