"""Model selection for time series: blocked (contiguous) cross-validation folds.

Shuffled k-fold cross-validation leaks the future into the training folds of a time series
(neighbouring windows share samples). Blocked folds keep the time order: fold ``f`` of ``k``
holds the samples ``i`` with ``floor(i k / n) = f``, a contiguous block, and the model is
trained on all other samples. Any learner fits: :func:`blocked_cv_rmse` takes a ``fit``
function that returns a predictor.

A one-step criterion selects a model for one-step use. A model that is *iterated* (recursive
multi-step prediction, paper 002 Eq. 12-14, the basis of an RUL) has to be selected as an
iterated model: :func:`blocked_multistep_cv` trains on the same blocked folds, starts the
recursion from every window of the held block and scores the whole predicted path against the
series (RMSE over the horizon) and, given a failure threshold, the predicted time to cross it.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass

import torch
from torch import Tensor

from ..core.validation import check_pos_int, is_real

__all__ = [
    "blocked_folds",
    "blocked_cv_rmse",
    "MultiStepCV",
    "blocked_multistep_cv",
    "best_setting",
]


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
        X: ``(N, ...)`` inputs in time order; Y: ``(N, ...)`` targets, both finite (a
            missing value is refused, naming its row).
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
    for name, T in (("X", X), ("Y", Y)):
        bad = ~torch.isfinite(T).reshape(T.shape[0], -1).all(1)
        if bool(bad.any()):
            raise ValueError(
                f"{name} has a missing or non-finite value at row {int(bad.nonzero()[0, 0])}: "
                "every row is trained on or scored (fill or cut the gap first)"
            )
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


@dataclass(frozen=True)
class MultiStepCV:
    """Out-of-fold scores of :func:`blocked_multistep_cv` (blocked folds, no shuffling).

    Attributes:
        one_step: one-step RMSE over all windows, the value :func:`blocked_cv_rmse` gives on
            the same windows and folds.
        multi_step: RMSE of the recursive prediction over steps ``1..H`` from every scored
            origin (each step compared with the series where the series still has a value).
        crossing: RMSE, in steps, of the time to cross ``threshold``; NaN without a threshold
            or when no origin qualifies.
        origins: number of origins scored for ``multi_step``.
        crossing_origins: number of origins scored for ``crossing`` (those whose window ends
            on the safe side of the threshold).
    """

    one_step: float
    multi_step: float
    crossing: float
    origins: int
    crossing_origins: int


def _first_passage(paths: Tensor, valid: Tensor, threshold: float, above: bool) -> Tensor:
    """First step ``j`` (1-based) with ``paths[:, j-1]`` across the threshold, else ``L + 1``,
    ``L`` = the number of valid steps of the row (the series' end caps the horizon)."""
    hit = (paths >= threshold) if above else (paths <= threshold)
    hit = hit & valid
    steps = torch.arange(1, paths.shape[1] + 1, device=paths.device).expand_as(paths)
    cap = valid.sum(1) + 1
    first = torch.where(hit, steps, cap[:, None].expand_as(steps)).min(1).values
    return torch.minimum(first, cap)


def blocked_multistep_cv(
    fit: Callable[[Tensor, Tensor], Callable[[Tensor], Tensor]],
    series: Tensor,
    m: int,
    horizon: int,
    folds: int = 5,
    *,
    threshold: float | None = None,
    direction: str = "above",
    stride: int = 1,
) -> MultiStepCV:
    """Blocked cross-validation of a model used recursively (paper 002, Eq. 12-14).

    The windows ``P_i = [z_i, ..., z_{i+m-1}]`` with targets ``z_{i+m}`` (``i = 0..n-m-1``)
    are split into blocked folds (:func:`blocked_folds`). For fold ``f`` the model is trained on
    the other folds' windows, ``predict = fit(X_train, y_train)``, and

    * one step: ``predict(P_i) - z_{i+m}`` for every held window (as :func:`blocked_cv_rmse`);
    * multi step: from every ``stride``-th held window (the origin, last value ``z_o``,
      ``o = i + m - 1``) the recursion ``x^_{o+j} = predict([.., x^_{o+j-1}])``, ``j = 1..H``,
      is compared with ``z_{o+j}`` wherever ``o + j < n``;
    * crossing (with ``threshold``): for the origins whose last value ``z_o`` is on the safe
      side, the first step ``J`` at which the recursion crosses and the first step ``J*`` at
      which the series crosses, both capped at ``L + 1`` with ``L = min(H, n - 1 - o)`` the
      steps the series still covers; the score is ``sqrt(mean (J - J*)^2)`` in steps.

    A model that is fine for one step can be poor when iterated (a recursion may settle on an
    attractor away from the data); the last two scores see that, the first does not. The
    targets of an origin's path lie after its block, in samples that the other folds may train
    on (as in any blocked cross-validation of a time series); the held windows themselves are
    never trained on.

    Args:
        fit: trains a model on ``(X_train (N_t, m), y_train (N_t,))`` and returns its
            predictor ``(B, m) -> (B,)``.
        series: ``(n,)`` the training series in time order.
        m: embedding dimension (window length) ``>= 1``.
        horizon: recursion length ``H >= 1`` (steps).
        folds: number of blocked folds, ``2 <= folds <= n - m``.
        threshold: failure threshold for the crossing score (``None``: no crossing score).
        direction: ``"above"`` (failure when ``z >= threshold``) or ``"below"``.
        stride: score every ``stride``-th held window as an origin (``>= 1``).
    Returns:
        :class:`MultiStepCV`.
    """
    if not callable(fit):
        raise TypeError(f"fit must be callable (X_train, y_train) -> predictor, got {fit!r}")
    if not isinstance(series, Tensor):
        raise TypeError(f"series must be a tensor (n,), got {type(series)}")
    if series.dim() != 1 or not series.is_floating_point():
        raise ValueError(f"series must be a floating-point tensor (n,), got {tuple(series.shape)}")
    m, horizon = check_pos_int(m, "m"), check_pos_int(horizon, "horizon")
    stride = check_pos_int(stride, "stride")
    if direction not in ("above", "below"):
        raise ValueError(f"direction must be 'above' or 'below', got {direction!r}")
    if threshold is not None and (not is_real(threshold) or not math.isfinite(threshold)):
        raise ValueError(f"threshold must be a finite number or None, got {threshold!r}")
    if not bool(torch.isfinite(series).all()):
        i = int((~torch.isfinite(series)).nonzero()[0, 0])
        raise ValueError(
            f"series has a missing or non-finite value at index {i}: the folds' windows need "
            "every value (fill or cut the gap first)"
        )
    n = series.shape[0]
    if n - m < 2:
        raise ValueError(f"series must have at least m + 2 = {m + 2} samples (n,), got n={n}")
    folds = check_pos_int(folds, "folds")
    if not 2 <= folds <= n - m:
        raise ValueError(
            f"folds must satisfy 2 <= folds <= n - m = {n - m} (the windows of m = {m} values "
            f"with a target in a series of n = {n} samples), got {folds}"
        )
    X = series.unfold(0, m, 1)[: n - m]  # (n - m, m): P_i = z[i : i + m]
    y = series[m:]
    index = blocked_folds(X.shape[0], folds, device=series.device)
    steps = torch.arange(1, horizon + 1, device=series.device)
    above = direction == "above"
    sq1 = sqh = sqc = 0.0
    n_h = n_o = n_c = 0
    for f in range(folds):
        hold = index == f
        predict = fit(X[~hold], y[~hold])
        held = torch.nonzero(hold).flatten()
        with torch.no_grad():
            one = predict(X[held])
            if one.shape != y[held].shape:
                raise ValueError(
                    f"the predictor returned shape {tuple(one.shape)} for a batch of windows "
                    f"{tuple(X[held].shape)}; expected {tuple(y[held].shape)}"
                )
            sq1 += float(((one - y[held]) ** 2).sum())
            org = held[::stride]
            w, out = X[org], []
            for _ in range(horizon):
                nxt = predict(w)
                out.append(nxt)
                w = torch.cat([w[:, 1:], nxt[:, None]], dim=1)
            paths = torch.stack(out, dim=1)  # (O, H)
        last = org + m - 1  # index of each origin's newest value
        at = last[:, None] + steps  # (O, H) indices of the targets
        valid = at < n
        truth = series[at.clamp(max=n - 1)]
        err = torch.where(valid, paths - truth, torch.zeros_like(paths))
        sqh += float((err**2).sum())
        n_h += int(valid.sum())
        n_o += org.shape[0]
        if threshold is not None:
            z_o = series[last]
            safe = (z_o < threshold) if above else (z_o > threshold)
            safe = safe & valid[:, 0]
            if bool(safe.any()):
                j_hat = _first_passage(paths[safe], valid[safe], float(threshold), above)
                j_true = _first_passage(truth[safe], valid[safe], float(threshold), above)
                sqc += float(((j_hat - j_true).to(torch.float64) ** 2).sum())
                n_c += int(safe.sum())
    return MultiStepCV(
        one_step=math.sqrt(sq1 / y.numel()),
        multi_step=math.sqrt(sqh / max(n_h, 1)),
        crossing=math.sqrt(sqc / n_c) if n_c else math.nan,
        origins=n_o,
        crossing_origins=n_c,
    )


def best_setting(scores: Mapping, criterion: str = "one_step"):
    """The key of ``scores`` (``{setting: MultiStepCV}``, e.g. from
    :func:`~prognos_torch.learners.lssvr_grid_cv`) with the lowest finite ``criterion``
    (``"one_step"``, ``"multi_step"`` or ``"crossing"``); a tie goes to the first in the
    mapping's order. A NaN score (no origin qualified) never wins: ``min`` over the keys kept a
    NaN first cell, since nothing compares below NaN. Raises ``ValueError`` when no setting
    has a finite score."""
    if criterion not in ("one_step", "multi_step", "crossing"):
        raise ValueError(
            f"criterion must be 'one_step', 'multi_step' or 'crossing', got {criterion!r}"
        )
    if not isinstance(scores, Mapping) or not scores:
        raise ValueError("scores must be a non-empty mapping {setting: MultiStepCV}")
    best, best_v = None, math.inf
    for key, sc in scores.items():
        v = float(getattr(sc, criterion))
        if math.isfinite(v) and (best is None or v < best_v):
            best, best_v = key, v
    if best is None:
        raise ValueError(
            f"no setting has a finite {criterion} score ({len(scores)} settings; for "
            "'crossing': no origin's window ended on the safe side of the threshold)"
        )
    return best
