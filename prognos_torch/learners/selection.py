"""Model selection for time series: blocked (contiguous) cross-validation folds.

Shuffled k-fold cross-validation leaks the future into the training folds of a time series
(neighbouring windows share samples). Blocked folds keep the time order: fold ``f`` of ``k``
holds the samples ``i`` with ``floor(i k / n) = f``, a contiguous block, and the model is
trained on all other samples. Any learner fits: :func:`blocked_cv_rmse` takes a ``fit``
function that returns a predictor.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch
from torch import Tensor

from ..core.validation import check_pos_int

__all__ = ["blocked_folds", "blocked_cv_rmse"]


def blocked_folds(n: int, folds: int, device=None) -> Tensor:
    """Fold index ``floor(i * folds / n)`` of each sample ``i = 0..n-1``: ``(n,)`` int64.

    The folds are contiguous blocks in sample order whose sizes differ by at most one.
    """
    n, folds = check_pos_int(n, "n"), check_pos_int(folds, "folds")
    if not 2 <= folds <= n:
        raise ValueError(f"folds must satisfy 2 <= folds <= n={n}, got {folds}")
    return torch.arange(n, device=device) * folds // n


def blocked_cv_rmse(
    fit: Callable[[Tensor, Tensor], Callable[[Tensor], Tensor]],
    X: Tensor,
    Y: Tensor,
    folds: int = 5,
) -> float:
    """Out-of-fold RMSE with blocked folds (:func:`blocked_folds`, no shuffling).

    For each fold ``f``: ``predict = fit(X[~hold], Y[~hold])``, then the squared errors
    ``(predict(X[hold]) - Y[hold])^2`` (evaluated without gradients) are summed over the held
    samples; the result is ``sqrt(sum over all folds / Y.numel())``, each sample predicted once
    by a model that did not see it.

    Args:
        fit: trains a model on ``(X_train, Y_train)`` and returns its predictor, a callable
            ``(n_hold, ...) -> `` the shape of ``Y[hold]``.
        X: ``(N, ...)`` inputs in time order; Y: ``(N, ...)`` targets.
        folds: number of folds ``k``, ``2 <= k <= N``.
    Returns:
        The out-of-fold RMSE (a Python float).
    """
    if not isinstance(X, Tensor) or not isinstance(Y, Tensor):
        raise TypeError(f"X and Y must be tensors (N, ...), got {type(X)} and {type(Y)}")
    if X.dim() < 1 or Y.dim() < 1 or X.shape[0] != Y.shape[0]:
        raise ValueError(
            f"X and Y must have the same number of rows (N, ...), got {tuple(X.shape)} and "
            f"{tuple(Y.shape)}"
        )
    if not callable(fit):
        raise TypeError(f"fit must be callable (X_train, Y_train) -> predictor, got {fit!r}")
    index = blocked_folds(X.shape[0], folds, device=X.device)
    sq = 0.0
    for f in range(folds):
        hold = index == f
        predict = fit(X[~hold], Y[~hold])
        with torch.no_grad():
            pred = predict(X[hold])
        if pred.shape != Y[hold].shape:
            raise ValueError(
                f"the predictor returned shape {tuple(pred.shape)} for held targets of shape "
                f"{tuple(Y[hold].shape)}"
            )
        sq += float(((pred - Y[hold]) ** 2).sum())
    return math.sqrt(sq / Y.numel())
