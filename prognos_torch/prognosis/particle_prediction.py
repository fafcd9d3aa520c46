"""Rolling prediction with a particle filter: predict ahead before each measurement is seen.

Paper 002 (Fig. 8-10): at every step the filter's weighted particles at ``k - 1`` are
propagated ``H`` steps with process noise (:func:`~prognos_torch.prognosis.particle_paths`,
weights frozen) to give the predictive mean of the indicator and the fault probability
``fault(j, k-1) = sum_i w^i I(x^i_{k-1+j} in Omega_0)``; then the filter assimilates ``y_k``.
The loop is the library's one sequence loop (:func:`~prognos_torch.filters.scan`) over the
particle filter's step wrapped with the prediction; the prediction draws from the same
generator as the filter, between the filter's steps.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass

import torch
from torch import Tensor

from ..core.belief import GaussianBelief, check_belief
from ..core.model import StateSpaceModel
from ..core.validation import (
    check_channel,
    check_finite,
    check_generator,
    check_nonneg_int,
    check_pos_int,
    check_scalar,
    check_sequence,
    has_missing,
    is_int,
)
from ..filters import ParticleFilter, ParticleState, scan
from .paths import particle_paths
from .rul import fault_probability

__all__ = ["RollingParticlePrediction", "rolling_particle_prediction"]


@dataclass(frozen=True)
class RollingParticlePrediction:
    """Output of :func:`rolling_particle_prediction` over ``T`` steps (time leading).

    Attributes:
        mean: ``(T, ..., H)`` weighted predictive mean of ``h(x)[channel]`` at
            ``k, ..., k + H - 1``, made from the state at ``k - 1`` before ``y_k`` is seen.
        std: ``(T, ..., H)`` weighted predictive std.
        fault_probability: ``(T, ..., H)`` ``fault(j, k - 1)``, ``j = 1..H`` (``None`` without
            a threshold).
        filtered: ``(T, ..., n)`` the filter's weighted posterior mean after each update.
        ess: ``(T, ...)`` effective sample size before resampling.
        fading_factors: ``(T, ...)`` weighted mean fading factor (1 without strong tracking).
        prior_fallback: ``(T, ...)`` particles drawn from the prior (invalid proposals).
        collapsed: ``(T, ...)`` bool, weight collapse.
        states: ``{k: ParticleState}`` the filter state after step ``k`` for each requested
            ``k`` (after resampling; ``k0`` is the initial state).
        final: the state after the last step.
    """

    mean: Tensor
    std: Tensor
    fault_probability: Tensor | None
    filtered: Tensor
    ess: Tensor
    fading_factors: Tensor
    prior_fallback: Tensor
    collapsed: Tensor
    states: dict[int, ParticleState]
    final: ParticleState


def _finite_particles(st: ParticleState) -> Tensor:
    """The particles, those that left the reals (which the filter keeps with weight zero)
    replaced by the run's heaviest particle: their paths then carry weight zero too, and
    :func:`particle_paths` draws the same numbers for every particle. A non-finite particle
    with positive weight is left for :func:`particle_paths` to refuse."""
    x = st.particles
    if bool(torch.isfinite(x).all()):
        return x
    ok = torch.isfinite(x).all(-1) | (st.log_weights > -math.inf)
    best = st.log_weights.argmax(-1, keepdim=True)  # (..., 1)
    heaviest = torch.gather(x, -2, best.unsqueeze(-1).expand(*best.shape, x.shape[-1]))
    return torch.where(ok.unsqueeze(-1), x, heaviest)


def rolling_particle_prediction(
    pf: ParticleFilter,
    model: StateSpaceModel,
    init: GaussianBelief | ParticleState,
    ys: Tensor,
    horizon: int = 1,
    *,
    generator: torch.Generator,
    threshold: float | None = None,
    direction: str = "above",
    us: Tensor | None = None,
    k0: int = 0,
    channel: int = 0,
    keep: Iterable[int] = (),
) -> RollingParticlePrediction:
    """Filter ``ys`` with ``pf`` and predict ``horizon`` steps ahead before every update.

    Time convention of :meth:`ParticleFilter.run`: ``ys[t]`` is the measurement at
    ``k = k0 + t + 1``; ``init`` is the belief on ``x_{k0}`` (or a state to resume). Before step
    ``k`` the particles at ``k - 1`` are propagated by :func:`particle_paths` (``k0 = k - 1``)
    and summarised; with ``threshold`` the per-step fault probability of those paths is kept.

    Args:
        pf: the particle filter.
        model: the state-space model.
        init: belief on ``x_{k0}`` (batch dims = runs) or a :class:`ParticleState`.
        ys: ``(T, ..., m)`` measurements (NaN: missing).
        horizon: prediction steps ``H >= 1``.
        generator: ``torch.Generator`` on the particles' device (filter and predictions).
        threshold, direction: failure region of :func:`fault_probability` (optional).
        us: ``(T + H - 1, ..., p)`` controls for models with inputs (the filter uses the first
            ``T`` rows, the prediction from ``k - 1`` the rows ``t .. t + H - 1``).
        k0: time index of ``init``.
        channel: measurement channel predicted.
        keep: step indices ``k`` in ``k0 .. k0 + T`` whose filter states are returned.
    Returns:
        :class:`RollingParticlePrediction`.
    """
    if not isinstance(pf, ParticleFilter):  # (a factory passed uncalled: AttributeError on init)
        raise TypeError(
            f"pf must be a ParticleFilter (e.g. sir(), stpf()), got {type(pf).__name__}"
        )
    if not isinstance(model, StateSpaceModel):
        raise TypeError(f"model must be a StateSpaceModel, got {type(model).__name__}")
    horizon = check_pos_int(horizon, "horizon")
    k0 = check_nonneg_int(k0, "k0")  # (as run: a float k0 reached f, h and the noise as k)
    if direction not in ("above", "below"):  # (checked with or without a threshold)
        raise ValueError(f"direction must be 'above' or 'below', got {direction!r}")
    # every argument is checked before the first draw: an error leaves the generator as it was
    # (threshold and channel were read after the first filter step)
    if threshold is not None:
        check_scalar(threshold, "threshold")
    check_channel(channel, model.obs_dim)
    if isinstance(init, ParticleState):
        pf._check_state(model, init)
        like, bs = init.particles, init.batch_shape
    else:
        like = check_belief(init, model.state_dim, "init").mean
        bs = init.batch_shape
    check_generator(generator, like)
    check_sequence(ys, "ys", model.obs_dim, bs, nonempty=True)
    has_missing(ys, "ys", "measurement")  # inf named here, not as a step's y
    T = ys.shape[0]
    if isinstance(keep, (str, bytes)) or not isinstance(keep, Iterable):
        raise TypeError(f"keep must be an iterable of int step indices, got {keep!r}")
    keep = list(keep)
    if any(not is_int(k) for k in keep):  # (before sorting: text among ints failed in sorted)
        raise TypeError(f"keep must hold int step indices, got {keep!r}")
    keep = sorted({int(k) for k in keep})
    if keep and not (k0 <= keep[0] and keep[-1] <= k0 + T):
        raise ValueError(f"keep must lie in [k0, k0 + T] = [{k0}, {k0 + T}], got {keep}")
    if model.control_dim:
        check_sequence(us, "us", model.control_dim, bs, steps=T + horizon - 1, shared=True)
        # (the last H - 1 rows reach only the predictions: NaN there gave NaN means silently)
        check_finite(us, "us", f"(T + H - 1, ..., {model.control_dim})")
    elif us is not None:
        raise ValueError("us was given but the model has control_dim=0")
    state = (
        init if isinstance(init, ParticleState) else pf.init(model, init, generator=generator, k=k0)
    )
    states, wanted = {}, set(keep)

    def step(st: ParticleState, y: Tensor, u, k: int):
        t = k - k0 - 1
        paths = particle_paths(
            model,
            _finite_particles(st),
            horizon,
            generator=generator,
            weights=st.weights,
            us=None if us is None else us[t : t + horizon],
            k0=k - 1,
            channel=channel,
        )
        if k - 1 in wanted:
            states[k - 1] = st
        st, info = pf.step(model, st, y, u, k, generator=generator)
        return st, (paths, info)

    def record(st: ParticleState, out) -> dict[str, Tensor | None]:
        paths, info = out
        fault = None
        if threshold is not None:
            fault = fault_probability(paths.samples, threshold, paths.weights, direction)
        return {
            "mean": paths.mean,
            "std": paths.std,
            "fault_probability": fault,
            "filtered": info.mean,
            "ess": info.ess,
            "fading_factors": info.fading_factor,
            "prior_fallback": info.prior_fallback,
            "collapsed": info.collapsed,
        }

    final, stacked = scan(step, state, ys, None if us is None else us[:T], record=record, k0=k0)
    if k0 + T in wanted:
        states[k0 + T] = final
    return RollingParticlePrediction(**stacked, states=states, final=final)
