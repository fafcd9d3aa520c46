"""Evaluation protocols the studies share: scores of predictions against the truth.

* :func:`fault_prediction_errors`: per-run errors of a rolling n-step fault prediction
  (:func:`~prognos_torch.prognosis.rolling_fault_prediction`, paper 000 Sec. 5);
* :func:`rolling_forecast_rmse`: the RMSE per horizon and channel of measurement forecasts
  (:func:`~prognos_torch.prognosis.rolling_forecasts`) against the true signal;
* :func:`crossing_scores`: per-run errors of predicted threshold-crossing times
  (:func:`~prognos_torch.prognosis.predict_threshold_crossings`), and :func:`crossing_table`:
  the median predicted RUL and the censored fraction per prediction time;
* :func:`run_errors`: per-run MAE, RMSE and MSE of predictions against one target series, and
  :func:`lowest_counts`: in how many runs each method has the lowest score.

They sit in :mod:`prognos_torch.studies` (above :mod:`~prognos_torch.prognosis` and
:mod:`~prognos_torch.metrics`) because they combine both.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING

import torch
from torch import Tensor

from ..metrics import mae, rmse
from .tables import markdown_table

if TYPE_CHECKING:
    from ..prognosis import RollingFaultPrediction, ThresholdCrossings

__all__ = [
    "fault_prediction_errors",
    "rolling_forecast_rmse",
    "crossing_scores",
    "crossing_table",
    "run_errors",
    "lowest_counts",
]


def fault_prediction_errors(
    result: RollingFaultPrediction, theta: Tensor, *, component: int = 0
) -> dict[str, Tensor]:
    """Per-run errors of a rolling n-step fault prediction.

    Time convention of :func:`~prognos_torch.filters.run`: ``ys[t]`` is the measurement at
    ``k = t + 1``; the true parameter path has row ``k`` at time ``k`` (row 0: ``x_0``).

    Args:
        result: :func:`~prognos_torch.prognosis.rolling_fault_prediction` output over ``T``
            measurements with origins ``k = N0..T``.
        theta: ``(T + n + 1, ..., d)`` true parameter, row ``k`` at time ``k``.
        component: which reported component of the prediction to score.
    Returns:
        ``{"MAE", "RMSE"}``: of ``theta^_{k+n|k+n}`` against ``theta_{k+n}``, ``k = N0..T``;
        ``"filt_RMSE"``: of the real-time ``theta^_{k|k}`` against ``theta_k``, ``k = N0..T``;
        each ``(...)``, one value per run.
    """
    N0, T, n = int(result.origin[0]), int(result.origin[-1]), result.n
    if theta.shape[0] < T + n + 1:
        raise ValueError(f"theta must have T + n + 1 = {T + n + 1} rows, got {theta.shape[0]}")
    pred = result.predicted[..., component]  # (K, ...)
    truth = theta[N0 + n : T + n + 1, ..., component]
    filt = result.filtered[N0 - 1 :, ..., component]  # theta^_{k|k}, k = N0..T
    ftruth = theta[N0 : T + 1, ..., component]
    return {
        "MAE": mae(pred, truth, dim=0),
        "RMSE": rmse(pred, truth, dim=0),
        "filt_RMSE": rmse(filt, ftruth, dim=0),
    }


def rolling_forecast_rmse(forecasts: Tensor, truth: Tensor, start: int) -> Tensor:
    """RMSE per horizon and channel of rolling measurement forecasts, over origins and runs.

    Args:
        forecasts: ``(K, n, R, C)`` forecasts of ``z_{k+j}`` made at ``k = start..start+K-1``
            (:func:`~prognos_torch.prognosis.rolling_forecasts`).
        truth: ``(T + n + 1, R, C)`` the true signal, row ``k`` at time ``k``.
    Returns:
        ``(n, C)``.
    """
    K, n = forecasts.shape[:2]
    T = start + K - 1
    if truth.shape[0] < T + n + 1:
        raise ValueError(f"truth must have T + n + 1 = {T + n + 1} rows, got {truth.shape[0]}")
    target = torch.stack([truth[start + j : T + j + 1] for j in range(1, n + 1)], 1)
    return rmse(forecasts, target, dim=(0, 2))


def crossing_scores(
    crossings: ThresholdCrossings, true_crossing: float, at: Sequence[int] = ()
) -> dict[str, Tensor]:
    """Per-run errors of predicted threshold-crossing times (= RUL errors at ``k_p``).

    Returns ``(R,)`` float64 tensors: ``"RUL_err@<k_p>"`` (predicted minus true crossing, NaN
    where censored) for each ``k_p`` in ``at``; ``"cross_MAE"``: the mean absolute error over
    the prediction times with a predicted crossing (NaN if none); ``"censored"``: the fraction
    of prediction times without one.
    """
    err = crossings.crossing - true_crossing  # (P, R)
    times = crossings.times.tolist()
    out = {}
    for kp in at:
        if kp not in times:
            raise ValueError(f"{kp} is not one of the prediction times {times}")
        out[f"RUL_err@{kp}"] = err[times.index(kp)]
    mae_, cens = [], []
    for r in range(err.shape[1]):
        e = err[:, r]
        ok = torch.isfinite(e)
        mae_.append(e[ok].abs().mean().item() if bool(ok.any()) else math.nan)
        cens.append((~ok).double().mean().item())
    out["cross_MAE"] = torch.tensor(mae_, dtype=torch.float64)
    out["censored"] = torch.tensor(cens, dtype=torch.float64)
    return out


def crossing_table(crossings: Mapping[str, ThresholdCrossings], true_crossing: int) -> str:
    """Markdown table: per prediction time ``k_p`` the true RUL and, per method, the median
    predicted RUL over the runs that predict a crossing (``—`` if none; ``torch.median``: the
    lower of the two middle values for an even count) and the fraction of runs that do not
    (censored)."""
    first = next(iter(crossings.values()))
    rows = []
    for j, kp in enumerate(first.times.tolist()):
        cells = [str(kp), str(true_crossing - kp)]
        for cr in crossings.values():
            c = cr.crossing[j]
            ok = torch.isfinite(c)
            med = (c[ok] - kp).median().item() if bool(ok.any()) else math.nan
            cells += ["—" if math.isnan(med) else f"{med:.0f}", f"{(~ok).double().mean():.2f}"]
        rows.append(cells)
    head = [c for n in crossings for c in (f"{n} pred. RUL (median)", f"{n} censored")]
    return markdown_table(["k_p", "true RUL", *head], rows)


def run_errors(pred: Tensor, target: Tensor) -> dict[str, Tensor]:
    """Per-run MAE, RMSE (paper 003 Eq. 48-49) and MSE (``RMSE**2``) of ``pred`` ``(..., N)``
    against ``target`` ``(N,)`` (broadcast over the leading run dims); each ``(...)``."""
    if target.dim() != 1 or pred.dim() < 1 or pred.shape[-1] != target.shape[0]:
        raise ValueError(  # a (1,) target was broadcast over every sample
            f"target must be (N,) with N = pred.shape[-1], got target {tuple(target.shape)} "
            f"and pred {tuple(pred.shape)}"
        )
    t = target.expand_as(pred)
    r = rmse(pred, t, dim=-1)
    return {"MAE": mae(pred, t, dim=-1), "RMSE": r, "MSE": r.square()}


def lowest_counts(scores: Mapping[str, Tensor]) -> dict[str, int]:
    """In how many runs each method has the lowest score: ``scores`` maps each method to its
    ``(R,)`` per-run values (lower is better); a tie goes to the method named first. A NaN score
    (a diverged run) is never the lowest; a run where every score is NaN counts for no method."""
    shapes = {k: tuple(v.shape) for k, v in scores.items()}
    if not scores or len(set(shapes.values())) != 1 or len(next(iter(shapes.values()))) != 1:
        raise ValueError(f"scores must map methods to (R,) tensors of one length, got {shapes}")
    m = torch.stack(list(scores.values()))  # (M, R)
    nan = torch.isnan(m)
    best = torch.where(nan, math.inf, m).argmin(0)  # (argmin took a NaN for the lowest)
    counts = torch.bincount(best[~nan.all(0)], minlength=len(scores)).tolist()
    return dict(zip(scores, counts))
