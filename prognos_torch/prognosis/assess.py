"""Scoring forecast-fed fault prediction against the truth (paper 000 Sec. 5, steps 1-9).

The rolling n-step prediction of :func:`~prognos_torch.prognosis.rolling_fault_prediction`
produces, at every origin ``k``, the predicted fault parameter ``theta^_{k+n|k+n}``; these
helpers turn such records into the numbers a study reports:

* :func:`rolling_forecasts`: the measurement forecasts ``z^_{k+1..k+n}`` made at every origin
  (the forecaster's own accuracy, e.g. against persistence);
* :func:`aligned_forecasts`: the ``j``-step forecasts at their target times;
* :func:`persistence_forecasts`: the reference forecast ``z^_{k+j} = z_k`` in that layout;
* :func:`origin_fading_factors`: the strong-tracking fading factor of each prediction, aligned
  with the real-time record;
* :func:`first_alarm`: paper 000 step 8, the first origin whose prediction crosses a threshold;
* :func:`predict_threshold_crossings`: the predicted crossing time (hence the RUL) from a set
  of prediction times, each with the horizon stretched to ``H`` steps.

Time convention of :func:`~prognos_torch.filters.run`: ``ys[t]`` is the measurement at
``k = t + 1``; a true parameter path ``theta`` has row ``k`` for time ``k`` (row 0: ``x_0``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import torch
from torch import Tensor

from ..core.belief import GaussianBelief
from ..core.model import StateSpaceModel
from ..core.validation import check_pos_int
from ..filters import GaussianFilter
from ..filters import run as filter_run
from .fault import predict_fault_parameter
from .rul import rul_distribution

if TYPE_CHECKING:
    from .fault import RollingFaultPrediction

__all__ = [
    "rolling_forecasts",
    "persistence_forecasts",
    "aligned_forecasts",
    "origin_fading_factors",
    "first_alarm",
    "ThresholdCrossings",
    "predict_threshold_crossings",
]


def rolling_forecasts(forecaster, ys: Tensor, n: int, start: int) -> Tensor:
    """Forecasts ``z^_{k+1..k+n}`` made at ``k = start, ..., T`` over the record ``ys``.

    The forecaster (any object with ``copy``, ``initialized``, ``initialize``, ``forecast``,
    ``update``, e.g. :class:`~prognos_torch.prognosis.MeasurementForecaster`) is copied; a copy
    that is not initialised is trained on ``ys[:start]``; after the forecast at ``k < T`` it
    absorbs the real measurement ``ys[k]`` (``z_{k+1}``).

    Args:
        ys: ``(T, ..., m)`` measurements.
        n: horizon; start: first origin ``N0``, ``1 <= start <= T``.
    Returns:
        ``(T - start + 1, n, ..., m)``: row ``k - start`` holds the forecasts made at ``k``.
    """
    n, start = check_pos_int(n, "n"), check_pos_int(start, "start")
    if not isinstance(ys, Tensor) or ys.dim() < 2 or not start <= ys.shape[0]:
        raise ValueError(f"ys must have shape (T, ..., m) with T >= start={start}")
    T = ys.shape[0]
    f = forecaster.copy()
    if not f.initialized:
        f.initialize(ys[:start])
    out = []
    for k in range(start, T + 1):
        out.append(f.forecast(n))
        if k < T:
            f.update(ys[k])
    return torch.stack(out)


def aligned_forecasts(forecasts: Tensor, j: int) -> Tensor:
    """The ``j``-step forecasts of :func:`rolling_forecasts` at their target times.

    Args:
        forecasts: ``(K, n, ...)`` made at ``k = start..T`` (``T = start + K - 1``).
        j: ``1 <= j <= n``.
    Returns:
        ``(K - 1, ...)``: row ``t - start - 1`` holds the forecast of ``z_t`` made at ``t - j``,
        ``t = start + 1..T`` (NaN where ``t - j < start``).
    """
    K, n = forecasts.shape[:2]
    if not 1 <= j <= n:
        raise ValueError(f"j must be in 1..{n}, got {j}")
    out = forecasts.new_full((K - 1, *forecasts.shape[2:]), math.nan)
    out[j - 1 :] = forecasts[: K - j, j - 1]
    return out


def persistence_forecasts(ys: Tensor, n: int, start: int) -> Tensor:
    """The persistence forecast ``z^_{k+j} = z_k`` in the layout of :func:`rolling_forecasts`:
    ``(T - start + 1, n, ..., m)`` (a reference any forecaster should beat)."""
    n, start = check_pos_int(n, "n"), check_pos_int(start, "start")
    zk = ys[start - 1 :]  # z_k, k = start..T
    return zk[:, None].expand(zk.shape[0], n, *zk.shape[1:])


def origin_fading_factors(result: RollingFaultPrediction, step: int = -1) -> Tensor:
    """The fading factor ``lambda`` of forecast step ``step`` of the prediction made at each
    origin ``k``, aligned with the real-time record: ``(T, ...)``, row ``k - 1`` (NaN before
    the first origin), beside e.g. the real-time filter's ``Trajectory.fading_factors``."""
    T = result.filtered.shape[0]
    lam = result.fading_factors[:, step]  # (K, ...)
    out = lam.new_full((T, *lam.shape[1:]), math.nan)
    out[int(result.origin[0]) - 1 :] = lam
    return out


def first_alarm(
    result: RollingFaultPrediction,
    threshold: float,
    *,
    component: int = 0,
    direction: str = "above",
) -> Tensor:
    """Paper 000 step 8: the first origin ``k`` whose prediction ``theta^_{k+n|k+n}`` reaches
    ``threshold``; the crossing is then predicted at ``k + n``.

    Returns:
        ``(...)`` float64 predicted crossing times ``k + n`` (NaN: no alarm).
    """
    path = result.predicted[..., component].movedim(0, -1).unsqueeze(-2)  # (..., 1, K)
    fp = rul_distribution(path, threshold, direction=direction).first_passage[..., 0]
    k = (int(result.origin[0]) - 1 + fp + result.n).to(torch.float64)
    return torch.where(fp > 0, k, math.nan)


@dataclass(frozen=True)
class ThresholdCrossings:
    """Predicted threshold-crossing times from several prediction times.

    Attributes:
        times: ``(P,)`` int64 prediction times ``k_p``.
        crossing: ``(P, ...)`` float64 predicted crossing times (NaN: no crossing within the
            horizon, censored); the predicted RUL at ``k_p`` is ``crossing - k_p``.
        diverged: number of predicted paths that became non-finite within the horizon.
    """

    times: Tensor
    crossing: Tensor
    diverged: int

    def rul(self) -> Tensor:
        """``(P, ...)`` predicted RUL ``crossing - k_p`` (NaN where censored)."""
        return self.crossing - self.times.reshape(-1, *([1] * (self.crossing.dim() - 1)))


def predict_threshold_crossings(
    filt: GaussianFilter,
    model: StateSpaceModel,
    init: GaussianBelief,
    ys: Tensor,
    forecaster,
    times: Sequence[int],
    horizon: int,
    threshold: float,
    *,
    param_index: int,
    direction: str = "above",
) -> ThresholdCrossings:
    """RUL from prediction times ``k_p`` (paper 000 steps 3-8 with the horizon ``H``).

    The real-time filter runs over ``ys`` up to each ``k_p``; from its state the filter runs
    over ``H`` forecast measurements (:func:`~prognos_torch.prognosis.predict_fault_parameter`,
    the forecaster copied and initialised on ``ys[:k_p]``) and the first passage of the
    predicted parameter path through ``threshold``
    (:func:`~prognos_torch.prognosis.rul_distribution`) is the predicted crossing ``k_p + j``.

    A predicted path that becomes non-finite (e.g. an explicit integrator driven unstable by a
    runaway forecast) counts from then on as not crossing: its first passage before the
    divergence is kept, otherwise it is censored; :attr:`ThresholdCrossings.diverged` counts
    such paths.

    Args:
        filt, model: the Gaussian filter and the joint state/parameter model.
        init: belief on ``x_0`` with the batch shape of ``ys``.
        ys: ``(T, ..., m)`` real measurements.
        forecaster: see :func:`rolling_forecasts`.
        times: increasing prediction times ``1 <= k_p <= T``.
        horizon: ``H``; threshold: the failure threshold of the parameter.
        param_index: the state component of the fault parameter.
        direction: ``"above"`` or ``"below"`` (see :func:`rul_distribution`).
    """
    horizon = check_pos_int(horizon, "horizon")
    times = [int(k) for k in times]
    if not times or any(b <= a for a, b in zip(times, times[1:])) or times[0] < 1:
        raise ValueError(f"times must be increasing prediction times >= 1, got {times}")
    if times[-1] > ys.shape[0]:
        raise ValueError(f"times must not exceed T={ys.shape[0]}, got {times[-1]}")
    state = filt.init(model, init, 1)
    k_prev, crossing, diverged = 0, [], 0
    for kp in times:
        state = filter_run(filt, model, state, ys[k_prev:kp], k0=k_prev).final
        k_prev = kp
        fc = forecaster.copy().initialize(ys[:kp])
        pred = predict_fault_parameter(filt, model, state, fc, horizon, kp, param_index=param_index)
        path = pred.means[..., param_index]  # (H, ...): theta^_{kp+j|kp+j}
        nonfinite = ~torch.isfinite(pred.means).all(-1)  # (H, ...)
        bad = nonfinite.to(torch.int8).cummax(0).values.bool()  # from the first one on
        diverged += int(bad.any(0).sum())
        path = torch.where(bad, -math.inf if direction == "above" else math.inf, path)
        fp = rul_distribution(path.movedim(0, -1).unsqueeze(-2), threshold, direction=direction)
        fp = fp.first_passage[..., 0]  # (...)
        cross = torch.where(fp > 0, kp + fp, -1).to(torch.float64)
        crossing.append(torch.where(fp > 0, cross, math.nan))
    return ThresholdCrossings(
        torch.tensor(times, device=ys.device), torch.stack(crossing), diverged
    )
