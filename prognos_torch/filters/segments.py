"""Long sequences in bounded memory: :func:`~prognos_torch.filters.run` over time segments.

A :class:`~prognos_torch.filters.Trajectory` keeps every posterior, prior and innovation factor;
for many runs over many steps that is most of the memory. :func:`run_in_segments` filters the
sequence in consecutive segments, resuming each from the previous segment's final
:class:`~prognos_torch.filters.FilterState` (so the result equals one ``run``), and keeps only
the posterior means and the diagonals of the noise covariances the filter used at each step:
the nominal ``Q_k``, ``R_k`` of the model, or the noise estimator's current estimate (the
estimate after step ``k`` is the one step ``k + 1`` uses).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from ..core.belief import GaussianBelief
from ..core.model import StateSpaceModel
from ..core.validation import check_pos_int, check_sequence
from .gaussian import FilterState, GaussianFilter
from .run import _start, run

__all__ = ["SegmentedTrajectory", "run_in_segments"]


@dataclass(frozen=True)
class SegmentedTrajectory:
    """Output of :func:`run_in_segments` over ``T`` steps (time leading).

    Attributes:
        means: ``(T, ..., n)`` posterior means.
        var_Q: ``(T, ..., n)`` diagonal of the process-noise covariance used at each step.
        var_R: ``(T, ..., m)`` diagonal of the measurement-noise covariance used at each step.
        final: the :class:`FilterState` after the last step.
    """

    means: Tensor
    var_Q: Tensor
    var_R: Tensor
    final: FilterState


def _diag(L: Tensor) -> Tensor:
    return L.square().sum(-1)  # diag(L L^T)


def run_in_segments(
    filt: GaussianFilter,
    model: StateSpaceModel,
    init: GaussianBelief | FilterState,
    ys: Tensor,
    us: Tensor | None = None,
    *,
    segment: int,
    k0: int = 0,
) -> SegmentedTrajectory:
    """Filter ``ys`` ``(T, ..., m)`` with :func:`~prognos_torch.filters.run`, ``segment`` steps
    at a time; same time convention (step ``t`` uses ``k = k0 + t + 1``, ``us[t]``, ``ys[t]``).

    Args:
        filt: the Gaussian filter.
        model: the state-space model.
        init: belief on ``x_{k0}`` or a :class:`FilterState` to resume.
        ys: ``(T, ..., m)`` measurements (NaN: missing).
        us: ``(T, ..., p)`` or ``(T, p)`` controls, if the model has inputs.
        segment: steps per call of ``run`` (bounds the memory of one call).
        k0: time index of ``init``.
    Returns:
        :class:`SegmentedTrajectory`.
    """
    segment = check_pos_int(segment, "segment")
    # run's checks of filt, init and k0 (k0 = True was taken as 1; an uncalled factory or a
    # wrong belief failed in filt.init, unnamed)
    state, k0 = _start(filt, model, init, k0)
    bs = state.belief.batch_shape
    check_sequence(ys, "ys", model.obs_dim, bs, nonempty=True)
    T = ys.shape[0]
    if model.control_dim:  # whole (a segment's slice hid extra rows, and named its own T)
        check_sequence(us, "us", model.control_dim, bs, steps=T, shared=True)
    means, var_Q, var_R = [], [], []
    if state.noise is not None:  # the estimate held before the first step
        var_Q.append(_diag(state.noise.chol_Q).expand(1, *bs, -1))
        var_R.append(_diag(state.noise.chol_R).expand(1, *bs, -1))
    for a in range(0, T, segment):
        b = min(a + segment, T)
        tr = run(filt, model, state, ys[a:b], None if us is None else us[a:b], k0=k0 + a)
        means.append(tr.means)
        if tr.chol_Q is not None:
            var_Q.append(_diag(tr.chol_Q))
            var_R.append(_diag(tr.chol_R))
        state = tr.final
    ks = range(k0 + 1, k0 + T + 1)

    def nominal(name: str, dim: int) -> Tensor:  # the model's at each step
        return torch.stack([_diag(getattr(model.noise(k), name)).expand(*bs, dim) for k in ks])

    # a noise estimator: step k uses the estimate after step k - 1, except for a statistic it
    # holds (frozen, or not in its estimate) that the model gives per step: the filter takes
    # the model's Q_k, R_k there (GaussianFilter._noise), not the value held from the start
    held = set()
    if var_Q:
        est = filt.noise
        held = {"Q", "R"} if est.frozen else {"Q", "R"} - set(est.estimate)
        held = {name for name in held if callable(getattr(model, "chol_" + name))}
    n, m = model.state_dim, model.obs_dim
    vq = torch.cat(var_Q)[:T] if var_Q and "Q" not in held else nominal("chol_Q", n)
    vr = torch.cat(var_R)[:T] if var_R and "R" not in held else nominal("chol_R", m)
    like = state.belief.mean  # (the filter ran in the belief's dtype; the model's noise is cast)
    return SegmentedTrajectory(torch.cat(means), vq.to(like), vr.to(like), state)
