"""Running a Gaussian filter over a sequence (:func:`run`, on the loop
:func:`~prognos_torch.filters.sequence.scan`), and predict-only forecasting (:func:`forecast`)."""

from __future__ import annotations

import inspect
from dataclasses import dataclass

import torch
from torch import Tensor

from ..adapt.strong_tracking import StrongTracking, StrongTrackingState
from ..core.belief import GaussianBelief, check_belief
from ..core.model import StateSpaceModel
from ..core.validation import (
    check_finite,
    check_flag,
    check_nonneg_int,
    check_pos_int,
    check_sequence,
    has_missing,
)
from .gaussian import FilterState, GaussianFilter, StepInfo, innovation_stats
from .sequence import scan

__all__ = ["Trajectory", "Forecast", "run", "forecast"]


@dataclass(frozen=True)
class Trajectory:
    """Filter output over ``T`` steps (time leading, batch dims ``...`` after it).

    Attributes:
        means: ``(T, ..., n)`` posterior means.
        chols: ``(T, ..., n, n)`` posterior square roots.
        pred_means, pred_chols: the priors ``x_{k|k-1}`` (after fading).
        innovations: ``(T, ..., m)``.
        chol_innovations: ``(T, ..., m, m)``.
        log_likelihoods: ``(T, ...)`` per-step terms; ``log_likelihood`` their sum ``(...)``.
        nis: ``(T, ...)``; fading_factors: ``(T, ...)``.
        chol_Q, chol_R: ``(T, ..., n, n)``/``(T, ..., m, m)`` the noise estimator's square
            roots after each step (row ``t``: the estimate that includes step ``t``'s data,
            which step ``t + 1`` uses; the noise step ``t`` itself used is
            ``steps[t].noise``); only with a noise estimator, else ``None``; q, r likewise.
        noise_fallback: ``(T, ...)`` bool.
        final: the :class:`FilterState` after the last step (resume from it).
        steps: the :class:`StepInfo` of every step with ``run(..., keep_steps=True)``, else
            ``None`` (the smoothers read them).
    """

    means: Tensor
    chols: Tensor
    pred_means: Tensor
    pred_chols: Tensor
    innovations: Tensor
    chol_innovations: Tensor
    log_likelihoods: Tensor
    nis: Tensor
    fading_factors: Tensor
    noise_fallback: Tensor
    chol_Q: Tensor | None
    chol_R: Tensor | None
    q: Tensor | None
    r: Tensor | None
    final: FilterState
    steps: tuple[StepInfo, ...] | None = None

    @property
    def log_likelihood(self) -> Tensor:
        return self.log_likelihoods.sum(0)

    @property
    def covs(self) -> Tensor:
        return self.chols @ self.chols.mT


def check_filter(filt, name: str = "filter") -> GaussianFilter:
    """``filt`` if it is a :class:`GaussianFilter`, else a ``TypeError`` (a factory such as
    ``sckf`` passed without calling it is the usual slip)."""
    if isinstance(filt, GaussianFilter):
        return filt
    if inspect.isfunction(filt) or inspect.isclass(filt):
        what = "class" if inspect.isclass(filt) else "function"
        fname = getattr(filt, "__name__", "factory")
        raise TypeError(
            f"{name} must be a GaussianFilter, got the {what} {fname} itself: call it, e.g. "
            f"{fname}()"
        )
    raise TypeError(
        f"{name} must be a GaussianFilter (e.g. sckf() or make_filter('sckf')), got "
        f"{type(filt).__name__}"
    )


def _start(filt, model, init, k0) -> tuple[FilterState, int]:
    """The state at ``k0`` and ``k0`` as an ``int``."""
    check_filter(filt)
    # (a float k0 reached f, h and the noise as k; True was taken as k0 = 1, text failed in +)
    k0 = check_nonneg_int(k0, "k0")
    if isinstance(init, FilterState):
        mean = getattr(init.belief, "mean", None)
        if not isinstance(mean, Tensor) or mean.dim() < 1 or mean.shape[-1] != model.state_dim:
            got = tuple(mean.shape) if isinstance(mean, Tensor) else type(init.belief).__name__
            raise ValueError(
                f"init.belief.mean must have shape (..., {model.state_dim}) for this model, "
                f"got {got}"
            )
        return init, k0
    return filt.init(model, check_belief(init, model.state_dim, "init"), k0 + 1), k0


def _check_resumed(filt: GaussianFilter, state: FilterState) -> None:
    """A :class:`FilterState` to update from must carry the pieces ``filt`` adapts: strong
    tracking's ``V_k`` and a noise estimator's statistics (without them the step failed with an
    ``AttributeError``, or a noise-adaptive filter ran without adapting), and no noise
    statistics for a filter without an estimator (its step cannot update them)."""
    how = "resume from filter.init(model, belief) or from a run of this filter (Trajectory.final)"
    if isinstance(filt.fading, StrongTracking) and not isinstance(
        state.fading, StrongTrackingState
    ):
        raise ValueError(
            "init.fading must be the StrongTrackingState of this strong-tracking filter, got "
            f"{type(state.fading).__name__}: {how}"
        )
    if filt.noise is not None and state.noise is None:
        raise ValueError(
            "init.noise is None, but the filter estimates its noise "
            f"({type(filt.noise).__name__}): {how}"
        )
    if filt.noise is None and state.noise is not None:
        raise ValueError(
            "init.noise holds noise-estimator statistics, but the filter has no noise "
            f"estimator: {how}"
        )


def _record(state: FilterState, info: StepInfo) -> dict[str, Tensor | None]:
    """What :func:`run` keeps of each step (the noise in use only with a noise estimator)."""
    nz = state.noise
    return {
        "means": state.belief.mean,
        "chols": state.belief.chol,
        "pred_means": info.prior.mean,
        "pred_chols": info.prior.chol,
        "innovations": info.innovation,
        "chol_innovations": info.chol_innovation,
        "missing": info.missing,
        "fading_factors": info.fading_factor,
        "noise_fallback": info.noise_fallback,
        "chol_Q": None if nz is None else nz.chol_Q,
        "chol_R": None if nz is None else nz.chol_R,
        "q": None if nz is None else nz.q,
        "r": None if nz is None else nz.r,
    }


def run(
    filt: GaussianFilter,
    model: StateSpaceModel,
    init: GaussianBelief | FilterState,
    ys: Tensor,
    us: Tensor | None = None,
    *,
    k0: int = 0,
    keep_steps: bool = False,
    inference: bool = False,
) -> Trajectory:
    """Filter the measurements ``ys`` ``(T, ..., m)`` (NaN: missing; a row that is NaN
    throughout only predicts, a partially NaN row updates with its observed components).

    Step ``t`` (0-based) uses ``k = k0 + t + 1``, the control ``us[t]`` (``(T, ..., p)`` or
    ``(T, p)`` shared by the batch) and measurement ``ys[t]``. ``init`` is the belief on
    ``x_{k0}`` (or a :class:`FilterState` to resume). ``keep_steps=True`` keeps every
    step's :class:`StepInfo` in ``Trajectory.steps``. ``inference=True`` runs the steps after
    the first under ``torch.inference_mode()`` (not with ``keep_steps``; the conditions of
    :meth:`~prognos_torch.filters.ParticleFilter.run`).
    """
    # (text was read by its truth value: keep_steps="no" kept the steps)
    keep_steps = check_flag(keep_steps, "keep_steps")
    inference = check_flag(inference, "inference")
    state, k0 = _start(filt, model, init, k0)
    if isinstance(init, FilterState):
        _check_resumed(filt, state)
    bs = state.belief.batch_shape
    check_sequence(ys, "ys", model.obs_dim, bs)
    T = ys.shape[0]
    if T == 0:
        raise ValueError("ys must hold at least one step, shape (T, ..., m) with T >= 1")
    has_missing(ys, "ys", "measurement")  # inf named here, not as the step's y
    if model.control_dim:
        check_sequence(us, "us", model.control_dim, bs, steps=T, shared=True)
        check_finite(us, "us", "(T, ..., p)")
    elif us is not None:
        raise ValueError("us was given but the model has control_dim=0")

    infos: list[StepInfo] = []

    def step(s: FilterState, y: Tensor, u: Tensor | None, k: int):
        s, info = filt.step(model, s, y, u, k=k)
        if keep_steps:
            infos.append(info)
        return s, info

    # (with keep_steps the steps' StepInfo are handed out: they stay ordinary tensors)
    fast = inference and not keep_steps
    state, stacked = scan(step, state, ys, us, record=_record, k0=k0, inference=fast)
    # one vectorised pass over the whole trajectory instead of one per step
    stacked["nis"], stacked["log_likelihoods"] = innovation_stats(
        stacked["innovations"],
        stacked["chol_innovations"],
        stacked.pop("missing"),
        (~torch.isnan(ys)).sum(-1),  # partially observed vectors count their observed part
    )
    return Trajectory(**stacked, final=state, steps=tuple(infos) if keep_steps else None)


@dataclass(frozen=True)
class Forecast:
    """Predict-only output over ``H`` steps: state and measurement predictive moments.

    Attributes:
        means, chols: ``(H, ..., n)``, ``(H, ..., n, n)`` state predictions ``x_{k+j|k}``.
        y_means, y_chols: ``(H, ..., m)``, ``(H, ..., m, m)`` measurement predictions.
    """

    means: Tensor
    chols: Tensor
    y_means: Tensor
    y_chols: Tensor


def forecast(
    filt: GaussianFilter,
    model: StateSpaceModel,
    init: GaussianBelief | FilterState,
    steps: int,
    us: Tensor | None = None,
    *,
    k0: int = 0,
) -> Forecast:
    """Multi-step-ahead prediction without measurements (``k = k0 + 1 .. k0 + steps``)."""
    steps = check_pos_int(steps, "steps")
    state, k0 = _start(filt, model, init, k0)
    if model.control_dim:
        bs = state.belief.batch_shape
        check_sequence(us, "us", model.control_dim, bs, steps=steps, shared=True)
        check_finite(us, "us", "(H, ..., p)")
    elif us is not None:
        raise ValueError("us was given but the model has control_dim=0")
    means, chols, ym, yc = [], [], [], []
    for j in range(steps):
        u = None if us is None else us[j]
        state = filt.predict(model, state, u, k=k0 + j + 1)
        yb = filt.predict_measurement(model, state.belief, u, k=k0 + j + 1)
        means.append(state.belief.mean)
        chols.append(state.belief.chol)
        ym.append(yb.mean)
        yc.append(yb.chol)
    return Forecast(torch.stack(means), torch.stack(chols), torch.stack(ym), torch.stack(yc))
