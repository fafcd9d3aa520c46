"""n-step-ahead fault-parameter prediction from forecasted measurements (paper 000, Sec. 5).

:func:`predict_fault_parameter` (steps 3-8: filter the pseudo-measurements ``z_{k+1..k+n}``
from a copy of the current filter state) and :func:`rolling_fault_prediction` (step 9: walk
``k`` over the real measurements, with a
:class:`~prognos_torch.prognosis.forecaster.MeasurementForecaster` or any object with the same
``forecast``/``update`` methods).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from ..core.belief import GaussianBelief
from ..core.model import StateSpaceModel
from ..core.validation import (
    check_controls,
    check_finite,
    check_float_tensor,
    check_index,
    check_nonneg_int,
    check_pos_int,
    check_sequence,
    has_missing,
)
from ..filters.gaussian import FilterState, GaussianFilter
from ..filters.run import check_filter
from ..filters.run import run as _engine_run
from ..filters.sequence import scan

__all__ = [
    "FaultPrediction",
    "predict_fault_parameter",
    "RollingFaultPrediction",
    "rolling_fault_prediction",
]


def _check_model(model) -> None:
    if not isinstance(model, StateSpaceModel):
        raise TypeError(f"model must be a StateSpaceModel, got {type(model).__name__}")


@dataclass(frozen=True)
class FaultPrediction:
    """n-step-ahead prediction from pseudo-measurements (paper 000 Sec. 5 steps 3-8).

    Attributes:
        theta: ``(..., d)`` predicted parameter ``theta^_{k+n|k+n}`` (step 8).
        theta_std: ``(..., d)`` its standard deviation.
        means: ``(n, ..., n_x)`` the predicted state sequence ``x^e_{k+j|k+j}``, ``j = 1..n``.
        chols: ``(n, ..., n_x, n_x)`` their square roots.
        fading_factors: ``(n, ...)`` ``lambda_{k+j}`` (1 without strong tracking).
        pseudo_measurements: ``(n, ..., m)`` the forecasted ``z_{k+1..k+n}``.
        final: :class:`FilterState` at ``k + n`` (the real-time state is untouched).
        k: prediction origin; n: horizon.
    """

    theta: Tensor
    theta_std: Tensor
    means: Tensor
    chols: Tensor
    fading_factors: Tensor
    pseudo_measurements: Tensor
    final: FilterState
    k: int
    n: int


def predict_fault_parameter(
    filt: GaussianFilter,
    model: StateSpaceModel,
    state: FilterState,
    forecaster,
    n: int,
    k: int,
    *,
    us: Tensor | None = None,
    param_index=None,
) -> FaultPrediction:
    """n-step-ahead fault-parameter prediction (paper 000 Sec. 5, steps 3-8).

    Step 3: ``z_{k+1..k+n} = forecaster.forecast(n)``. Steps 4-7: filter them with ``filt``
    (e.g. STSCKF: time update Eq. 24-25, fading factor Eq. 27-36, measurement update Eq. 37-46)
    starting from ``state``, the real-time posterior at ``k``. The engine's states are
    immutable, so the n-step run works on a copy by construction: ``state`` is not changed.
    Step 8: ``theta^_{k+n|k+n}`` is read from the state at ``k + n``.

    Args:
        filt: the Gaussian filter (``stsckf()`` in the paper).
        model: joint state/parameter model (e.g. ``joint_state_parameter_model``).
        state: :class:`FilterState` at time ``k`` with batch shape ``(...)``.
        forecaster: any object with ``forecast(n) -> (n, ..., m)`` (a
            :class:`MeasurementForecaster`).
        n: horizon ``n >= 1``.
        k: current time index (the filter uses ``k + 1 .. k + n``).
        us: ``(n, ..., p)`` future controls for a model with ``control_dim > 0``.
        param_index: state components of ``theta`` (int, slice, ints; ``None``: whole state).
    Returns:
        :class:`FaultPrediction`.
    """
    _check_model(model)
    n = check_pos_int(n, "n")
    k = check_nonneg_int(k, "k")
    if not isinstance(state, FilterState):
        raise TypeError(
            f"state must be a FilterState (from filt.init / filt.step), got {type(state)}"
        )
    if not callable(getattr(forecaster, "forecast", None)):
        raise TypeError("forecaster must have a forecast(n) -> (n, ..., m) method")
    sel = check_index(param_index, model.state_dim)
    bs = tuple(state.belief.batch_shape)
    z = forecaster.forecast(n)
    want = (n, *bs, model.obs_dim)
    if not isinstance(z, Tensor) or tuple(z.shape) != want:
        got = tuple(z.shape) if isinstance(z, Tensor) else type(z)
        raise ValueError(f"forecaster.forecast(n) must return shape {want}, got {got}")
    check_finite(z, "forecaster.forecast(n)", f"{want}")
    us = check_controls(model, us, n)
    z = z.to(dtype=state.belief.mean.dtype, device=state.belief.mean.device)
    traj = _engine_run(filt, model, state, z, us, k0=k)
    final = traj.final
    sel = sel.to(final.belief.mean.device)
    var = (final.belief.chol**2).sum(-1)
    return FaultPrediction(
        theta=final.belief.mean.index_select(-1, sel),
        theta_std=var.index_select(-1, sel).sqrt(),
        means=traj.means,
        chols=traj.chols,
        fading_factors=traj.fading_factors,
        pseudo_measurements=z,
        final=final,
        k=k,
        n=n,
    )


@dataclass(frozen=True)
class RollingFaultPrediction:
    """Rolling n-step-ahead fault prediction over a measurement record (paper 000 Sec. 5 step 9).

    Attributes:
        origin: ``(K,)`` int64 times ``k = start, ..., T`` at which predictions were made.
        target: ``(K,)`` int64 times ``k + n`` they refer to.
        predicted: ``(K, ..., d)`` ``theta^_{k+n|k+n}`` for each origin.
        predicted_std: ``(K, ..., d)``.
        fading_factors: ``(K, n, ...)`` ``lambda`` of each n-step run.
        filtered: ``(T, ..., d)`` real-time estimates ``theta^_{k|k}``, row ``k - 1``.
        final: real-time :class:`FilterState` at ``T``.
        forecaster: the forecaster after the last measurement (a copy; the input is untouched).
        n: horizon.
    """

    origin: Tensor
    target: Tensor
    predicted: Tensor
    predicted_std: Tensor
    fading_factors: Tensor
    filtered: Tensor
    final: FilterState
    forecaster: object
    n: int

    def aligned(self) -> Tensor:
        """``(T + n, ..., d)``: row ``t - 1`` holds the prediction for time ``t`` (made at
        ``t - n``), NaN where no prediction refers to ``t``."""
        T = self.filtered.shape[0]
        out = self.predicted.new_full((T + self.n, *self.predicted.shape[1:]), math.nan)
        out[self.target - 1] = self.predicted
        return out


def rolling_fault_prediction(
    filt: GaussianFilter,
    model: StateSpaceModel,
    ys: Tensor,
    forecaster,
    n: int,
    start: int,
    *,
    init: GaussianBelief | FilterState,
    us: Tensor | None = None,
    param_index=None,
) -> RollingFaultPrediction:
    """Walk ``k = start, ..., T`` through the record (paper 000 Sec. 5, steps 1-9).

    Time convention of :func:`~prognos_torch.filters.run`: ``ys[t]`` is the measurement at
    ``k = t + 1``. Step 1: a forecaster that is not initialised is trained on
    ``ys[:start]`` (``z_1..z_{N0}``, ``N0 = start``); the real-time filter processes the same
    measurements. Then for each ``k``: predict ``n`` steps ahead from the real-time state
    (:func:`predict_fault_parameter`), and, for ``k < T``, filter the real measurement at
    ``k + 1`` and update the forecaster with it (step 9).

    Batched over Monte Carlo runs: ``ys`` ``(T, R, ..., m)`` with ``init`` of batch shape
    ``(R, ...)`` and a :class:`MeasurementForecaster` whose ROS-ELM state is batched the same
    way (one set of output weights per run, shared hidden layers): no loop over runs.

    Args:
        filt: Gaussian filter.
        model: joint state/parameter model.
        ys: ``(T, ..., m)`` real measurements; NaN: missing (the filter predicts without
            updating there, and the forecaster's window takes its prediction,
            :func:`~prognos_torch.learners.ros_elm_update`), except in the ``ys[:start]`` that
            train a forecaster not yet initialised.
        forecaster: :class:`MeasurementForecaster` (or any object with ``forecast(n)``,
            ``update(z)``, ``initialized`` and ``copy()``); it is copied, not modified.
        n: prediction horizon.
        start: ``N0``, ``1 <= start <= T``.
        init: belief on ``x_0`` with the batch shape of ``ys`` (or a :class:`FilterState`).
        us: ``(T + n, ..., p)`` controls (the last ``n`` rows are the planned future inputs).
        param_index: state components reported (``None``: whole state).
    Returns:
        :class:`RollingFaultPrediction`.
    """
    # (an uncalled factory, a wrong model or forecaster failed with an AttributeError, the
    # filter only after the forecaster's training)
    check_filter(filt, "filt")
    _check_model(model)
    lacking = [
        a for a in ("copy", "forecast", "update") if not callable(getattr(forecaster, a, None))
    ]
    if lacking or not hasattr(forecaster, "initialized"):
        raise TypeError(
            "forecaster must have initialized, copy(), initialize(z0), forecast(n) and update(z) "
            f"(a MeasurementForecaster), got {type(forecaster).__name__}"
        )
    n = check_pos_int(n, "n")
    ys = check_float_tensor(ys, "ys", "(T, ..., m)")
    if ys.dim() < 2 or ys.shape[-1] != model.obs_dim:
        raise ValueError(f"ys must have shape (T, ..., {model.obs_dim}), got {tuple(ys.shape)}")
    missing = has_missing(ys, "ys", "measurement")
    T = ys.shape[0]
    start = check_pos_int(start, "start")
    if start > T:
        raise ValueError(f"start must satisfy 1 <= start <= T={T}, got {start}")
    if missing and not forecaster.initialized and bool(torch.isnan(ys[:start]).any()):
        raise ValueError(
            f"ys[:start] (start={start}) trains the forecaster (paper 000 Sec. 5 step 1) and "
            "holds NaN: train it on complete measurements (forecaster.initialize(z0)), or "
            "start after the gap"
        )
    if not isinstance(init, (GaussianBelief, FilterState)):
        raise TypeError(f"init must be a GaussianBelief or a FilterState, got {type(init)}")
    if model.control_dim:  # (a wrong batch shape was named against T = start, NaN found late)
        p = model.control_dim
        check_sequence(us, "us", p, ys.shape[1:-1], steps=T + n, shared=True)
        check_finite(us, "us", f"(T + n, ..., {p})")
    elif us is not None:
        raise ValueError("us was given but the model has control_dim=0")
    sel = check_index(param_index, model.state_dim)

    # (the belief is checked before the forecaster's training)
    state = init if isinstance(init, FilterState) else filt.init(model, init, 1)
    fc = forecaster.copy()
    if not fc.initialized:
        fc.initialize(ys[:start])
    traj = _engine_run(filt, model, state, ys[:start], None if us is None else us[:start], k0=0)
    state = traj.final
    sel = sel.to(state.belief.mean.device)
    index = sel.tolist()

    def predict(s: FilterState, k: int) -> FaultPrediction:  # steps 3-8 from the state at k
        u_future = None if us is None else us[k : k + n]
        return predict_fault_parameter(filt, model, s, fc, n, k, us=u_future, param_index=index)

    def step(s: FilterState, y: Tensor, u: Tensor | None, k: int):  # step 9
        s, _ = filt.step(model, s, y, u, k=k)
        fc.update(y)
        return s, k

    def record(s: FilterState, k: int) -> dict[str, Tensor]:
        pred = predict(s, k)
        return {
            "filtered": s.belief.mean.index_select(-1, sel),
            "predicted": pred.theta,
            "predicted_std": pred.theta_std,
            "fading_factors": pred.fading_factors,
        }

    first = record(state, start)
    rows = {key: [v.unsqueeze(0)] for key, v in first.items()}
    rows["filtered"] = [traj.means.index_select(-1, sel)]
    if start < T:
        u_rest = None if us is None else us[start:T]
        state, more = scan(step, state, ys[start:], u_rest, record=record, k0=start)
        for key, v in more.items():
            rows[key].append(v)
    out = {key: torch.cat(parts) for key, parts in rows.items()}
    origin = torch.arange(start, T + 1, device=ys.device)
    return RollingFaultPrediction(
        origin=origin,
        target=origin + n,
        predicted=out["predicted"],
        predicted_std=out["predicted_std"],
        fading_factors=out["fading_factors"],
        filtered=out["filtered"],
        final=state,
        forecaster=fc,
        n=n,
    )
