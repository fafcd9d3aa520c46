"""Recursive multi-step prediction with propagated uncertainty (paper 002, Eq. 11-14).

:func:`recursive_predict` (deterministic), :func:`settle` (where the noise-free recursion of a
model goes after many steps), :func:`gaussian_paths` (the engine's
:func:`~prognos_torch.filters.run.forecast`, sigma points or EKF) and :func:`particle_paths`
(weighted sample paths ``(..., N, H)`` for :func:`~prognos_torch.prognosis.rul.fault_probability`
and :func:`~prognos_torch.prognosis.rul.rul_distribution`); :func:`predict_paths` dispatches and
turns a learner into a model with
:func:`~prognos_torch.prognosis.learner_model.learner_transition_model` where a method needs one.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor, nn

from ..core.belief import GaussianBelief
from ..core.model import StateSpaceModel
from ..core.validation import (
    check_channel,
    check_controls,
    check_finite,
    check_flag,
    check_float_tensor,
    check_generator,
    check_level,
    check_nonneg_int,
    check_pos_int,
    check_real_tensor,
    check_weights,
    check_window,
    is_real,
)
from ..datasets.windows import shift_append
from ..filters.gaussian import FilterState, GaussianFilter
from ..filters.run import forecast as _engine_forecast
from ..filters.variants import sckf
from ..learners.introspect import learner_dims
from .learner_model import learner_transition_model

__all__ = [
    "RecursivePaths",
    "GaussianPaths",
    "SamplePaths",
    "recursive_predict",
    "settle",
    "gaussian_paths",
    "particle_paths",
    "predict_paths",
]


@dataclass(frozen=True)
class RecursivePaths:
    """Deterministic recursive prediction (paper 002, Eq. 11-14).

    Attributes:
        mean: ``(..., H)`` predicted values ``x^_{k+1}, ..., x^_{k+H}``.
    """

    mean: Tensor

    @property
    def horizon(self) -> int:
        return self.mean.shape[-1]


@dataclass(frozen=True)
class GaussianPaths:
    """Gaussian multi-step prediction from a filter belief (predict-only steps of the engine).

    Attributes:
        mean: ``(..., H)`` predictive mean of measurement channel ``channel`` at ``k+1..k+H``.
        std: ``(..., H)`` its predictive std (includes the measurement noise ``R``).
        lower, upper: ``(..., H)`` central ``level`` band ``mean -+ z std``.
        state_mean: ``(..., H, n)`` predicted state means ``x_{k+j|k}``.
        state_chol: ``(..., H, n, n)`` their square-root covariances.
        level: the band's probability.
    """

    mean: Tensor
    std: Tensor
    lower: Tensor
    upper: Tensor
    state_mean: Tensor
    state_chol: Tensor
    level: float

    @property
    def state_std(self) -> Tensor:
        """``(..., H, n)`` standard deviations of the predicted state elements."""
        return (self.state_chol * self.state_chol).sum(-1).sqrt()

    @property
    def horizon(self) -> int:
        return self.mean.shape[-1]


@dataclass(frozen=True)
class SamplePaths:
    """Weighted sample paths (particles propagated with process noise, weights frozen).

    Attributes:
        samples: ``(..., N, H)`` paths of the indicator (``h`` channel ``channel``); pass them
            with ``weights`` to :func:`~prognos_torch.prognosis.rul.fault_probability` and
            :func:`~prognos_torch.prognosis.rul.rul_distribution`.
        weights: ``(..., N)`` normalised weights (float64).
        mean: ``(..., H)`` weighted mean; std: ``(..., H)`` weighted std.
        lower, upper: ``(..., H)`` weighted quantiles ``(1 -+ level) / 2``
            (:func:`weighted_quantile`: NaN at a step where a path of positive weight is NaN).
        level: the band's probability.
    """

    samples: Tensor
    weights: Tensor
    mean: Tensor
    std: Tensor
    lower: Tensor
    upper: Tensor
    level: float

    @property
    def horizon(self) -> int:
        return self.samples.shape[-1]

    def quantile(self, q: float) -> Tensor:
        """Weighted lower quantile ``min{s : P(x <= s) >= q}`` per step, ``(..., H)``."""
        return weighted_quantile(self.samples, self.weights, q)


def weighted_quantile(samples: Tensor, weights: Tensor, q: float) -> Tensor:
    """The ``q`` quantile of ``samples`` ``(..., N, H)`` per column under ``weights`` ``(..., N)``
    summing to 1: the smallest sample whose cumulative weight reaches ``q`` (to 1e-12), and at
    most the largest sample of positive weight; ``(..., H)`` in the samples' dtype (integer
    samples as float64).

    NaN marks a missing value (a path that diverged): a column where a sample of positive
    weight is NaN has no quantile and gives NaN, whatever ``q`` (the value of that sample could
    lie anywhere); a NaN of weight zero is left out. ``inf`` and ``-inf`` are ordered as values.
    """
    if not is_real(q) or not 0.0 < q <= 1.0:  # (True was read as q = 1, text failed on '<')
        raise ValueError(f"q must be a number in (0, 1], got {q!r}")
    q = float(q)
    if isinstance(samples, Tensor) and not samples.is_floating_point():
        check_real_tensor(samples, "samples")  # (a bool or complex tensor is refused)
        samples = samples.to(torch.float64)
    x = check_float_tensor(samples, "samples", "(..., N, H)")
    if x.dim() < 2 or x.shape[-2] < 1:
        raise ValueError(f"samples must have shape (..., N, H) with N >= 1, got {tuple(x.shape)}")
    # (unnormalised weights gave the minimum, a weight (1,) was broadcast over the N samples)
    w = check_weights(weights, x.shape[:-2], x.shape[-2], x.device)
    nan = torch.isnan(x)
    missing = (nan & (w.unsqueeze(-1) > 0)).any(-2)  # (..., H): a positive weight on a NaN
    # (a NaN sorted as the largest sample: the upper quantiles ignored that its value is unknown)
    s, order = x.masked_fill(nan, math.inf).sort(dim=-2)  # (..., N, H)
    # The cumulative weights in float64 whatever the samples' dtype: a float32 cumsum of 1/N
    # falls short of q = k/N by more than the 1e-12 allowance and picks the next sample.
    ws = w.unsqueeze(-1).expand(x.shape).gather(-2, order)
    cdf = ws.cumsum(-2)
    idx = (cdf < q - 1e-12).sum(-2, keepdim=True)  # first index with cdf >= q
    pos = torch.arange(x.shape[-2], device=x.device).unsqueeze(-1)  # (N, 1)
    last = torch.where(ws > 0, pos, 0).amax(-2, keepdim=True)  # largest sample of weight > 0
    out = s.gather(-2, torch.minimum(idx, last)).squeeze(-2)
    return torch.where(missing, torch.full_like(out, math.nan), out)


def recursive_predict(
    learner_or_model: nn.Module | StateSpaceModel | Callable[[Tensor], Tensor],
    window: Tensor,
    horizon: int,
    *,
    n_out_index: int = 0,
    channel: int = 0,
    us: Tensor | None = None,
    k0: int = 0,
) -> Tensor:
    """Deterministic recursive multi-step prediction (paper 002, Eq. 11-14).

    With a learner ``f`` and ``P_{k-m+1} = window``::

        x^_{k+j} = f(P_{k-m+j}),   P_{k-m+j+1} = [x_{k-m+j+1}, ..., x^_{k+j}]    (Eq. 12-14)

    (the extracted Eq. 11-14 mix the sum limits ``l - m`` and ``k - m + 1``; they are the number
    of training pairs and do not affect the recursion). With a :class:`StateSpaceModel` the
    noise-free transition is iterated, ``x_{k+j} = f(x_{k+j-1}, u_{k+j}, k+j)``, and
    ``h(x_{k+j})[channel]`` is returned.

    Args:
        learner_or_model: a learner ``(..., m) -> (..., n_out)`` or a state-space model.
        window: ``(..., m)`` last ``m`` values, oldest first (or the state ``(..., n)``).
        horizon: number of steps ``H >= 1``.
        n_out_index: learner output used as the next value.
        channel: measurement channel reported for a model.
        us: ``(H, ..., p)`` controls for a model with ``control_dim > 0``.
        k0: time index of ``window``; step ``j`` uses ``k = k0 + j``.
    Returns:
        ``(..., H)`` predictions (differentiable; batch dims of ``window`` carried through).
    """
    horizon = check_pos_int(horizon, "horizon")
    k0 = check_nonneg_int(k0, "k0")  # (as forecast: a float k0 reached f and h as k)
    if isinstance(learner_or_model, StateSpaceModel):
        model = learner_or_model
        x = check_window(window, model.state_dim, "window")
        us = check_controls(model, us, horizon)
        check_channel(channel, model.obs_dim)
        out = []
        for j in range(horizon):
            u = None if us is None else us[j]
            x = model.transition(x, u, k0 + j + 1)
            out.append(model.observe(x, u, k0 + j + 1)[..., channel])
        return torch.stack(out, dim=-1)
    n_in, n_out = learner_dims(learner_or_model)
    if not callable(learner_or_model):
        raise TypeError(
            f"learner_or_model must be a learner or a StateSpaceModel, got {type(learner_or_model)}"
        )
    # as learner_transition_model (True added an axis, 0.0 or an index past n_out failed in
    # the indexing)
    n_out_index = check_nonneg_int(n_out_index, "n_out_index")
    if n_out is not None and n_out_index >= n_out:
        raise ValueError(f"n_out_index={n_out_index} is out of range for n_out={n_out}")
    m = n_in if n_in is not None else (window.shape[-1] if isinstance(window, Tensor) else 0)
    w = check_window(window, m, "window")
    out = []
    for _ in range(horizon):
        y = learner_or_model(w)
        if y.shape[-1] <= n_out_index:
            raise ValueError(
                f"n_out_index={n_out_index} is out of range for the learner's output of shape "
                f"{tuple(y.shape)}"
            )
        nxt = y[..., n_out_index]  # Eq. 12-14
        out.append(nxt)
        w = shift_append(w, nxt)  # P_{k-m+j+1}
    return torch.stack(out, dim=-1)


def settle(model: StateSpaceModel, states: Tensor, steps: int, *, k0: int = 0) -> Tensor:
    """Where the noise-free recursion of a model goes: the state after ``steps`` transitions.

    ``x_{k+1} = f(x_k, None, k + 1)`` for ``k = k0, ..., k0 + steps - 1`` from every state of
    ``states`` (paper 002 Eq. 12-14 iterated long enough to show its attractors: a fixed point,
    a cycle, or divergence), e.g. for an m-order learner model
    (:func:`~prognos_torch.prognosis.learner_transition_model`) from windows of a series.

    Args:
        model: a state-space model without controls (``control_dim == 0``).
        states: ``(..., n)`` finite start states (for a learner model: windows, oldest first).
        steps: number of transitions, ``>= 1``.
        k0: time index of ``states``.
    Returns:
        ``(..., n)`` the states after ``steps`` transitions (computed without autograd, under
        ``torch.inference_mode``).
    """
    if not isinstance(model, StateSpaceModel):
        raise TypeError(f"model must be a StateSpaceModel, got {type(model)}")
    if model.control_dim:
        raise ValueError(
            f"settle iterates a model without controls, got control_dim={model.control_dim}"
        )
    steps = check_pos_int(steps, "steps")
    k0 = check_nonneg_int(k0, "k0")
    x = check_window(states, model.state_dim, "states")
    with torch.inference_mode():
        for k in range(k0, k0 + steps):
            x = model.transition(x, None, k + 1)
    return x


def _z_of(level: float) -> float:
    return math.sqrt(2.0) * torch.special.erfinv(torch.tensor(level, dtype=torch.float64)).item()


def gaussian_paths(
    filt: GaussianFilter,
    model: StateSpaceModel,
    init: GaussianBelief | FilterState,
    horizon: int,
    *,
    us: Tensor | None = None,
    k0: int = 0,
    channel: int = 0,
    level: float = 0.95,
) -> GaussianPaths:
    """Gaussian propagation over ``H`` steps with the engine's predict-only
    :func:`~prognos_torch.filters.run.forecast` (sigma points, or Taylor for an EKF).

    For a linear model (e.g. a linear AR(m) learner as :func:`learner_transition_model`) every
    rule is exact: the mean is the AR recursion and the variance the closed-form AR prediction
    variance.

    Args:
        filt: the Gaussian filter whose moment rule propagates the belief.
        model: the state-space model.
        init: belief on ``x_{k0}`` ``(..., n)`` or a :class:`FilterState`.
        horizon: ``H >= 1``.
        us: ``(H, ..., p)`` controls for a model with ``control_dim > 0``.
        k0: time index of ``init``.
        channel: measurement channel reported in ``mean``/``std``.
        level: probability of the central band.
    Returns:
        :class:`GaussianPaths` with time on the last axis (``(..., H)``).
    """
    horizon = check_pos_int(horizon, "horizon")
    level = check_level(level)
    check_channel(channel, model.obs_dim)
    if not isinstance(init, (GaussianBelief, FilterState)):
        raise TypeError(f"init must be a GaussianBelief or a FilterState, got {type(init)}")
    belief = init.belief if isinstance(init, FilterState) else init
    if belief.dim != model.state_dim:
        raise ValueError(
            f"init.mean must have shape (..., {model.state_dim}) for this model, "
            f"got {tuple(belief.mean.shape)}"
        )
    check_finite(belief.mean, "init.mean", f"(..., {model.state_dim})")
    us = check_controls(model, us, horizon)
    fc = _engine_forecast(filt, model, init, horizon, us, k0=k0)
    mean = fc.y_means[..., channel].movedim(0, -1)
    yvar = (fc.y_chols[..., channel, :] ** 2).sum(-1)
    std = yvar.sqrt().movedim(0, -1)
    z = _z_of(level)
    return GaussianPaths(
        mean=mean,
        std=std,
        lower=mean - z * std,
        upper=mean + z * std,
        state_mean=fc.means.movedim(0, -2),
        state_chol=fc.chols.movedim(0, -3),
        level=level,
    )


def particle_paths(
    model: StateSpaceModel,
    particles: Tensor,
    horizon: int,
    *,
    generator: torch.Generator,
    weights: Tensor | None = None,
    us: Tensor | None = None,
    k0: int = 0,
    channel: int = 0,
    measurement_noise: bool = False,
    level: float = 0.95,
) -> SamplePaths:
    """Propagate weighted particles ``H`` steps with process noise (paper 002, step 2 of the
    prognosis flow): ``x^i_{k+j} = f(x^i_{k+j-1}, u, k+j) + q + S_Q e``, ``e ~ N(0, I)`` from
    ``generator``; the weights ``w^i_k`` stay frozen over the horizon.

    The path value is ``h(x^i_{k+j})[channel]`` (the condition indicator; add ``r + S_R v`` with
    ``measurement_noise=True``). The result's ``samples`` ``(..., N, H)`` and ``weights``
    ``(..., N)`` go straight into :func:`~prognos_torch.prognosis.rul.fault_probability` and
    :func:`~prognos_torch.prognosis.rul.rul_distribution`.

    Args:
        model: the state-space model (noise square roots ``(n, n)`` or with the batch dims
            ``(..., n, n)``).
        particles: ``(..., N, n)`` states at ``k0``.
        horizon: ``H >= 1``.
        generator: ``torch.Generator`` on the particles' device.
        weights: ``(..., N)`` normalised weights, ``None`` for ``1/N``.
        us: ``(H, ..., p)`` controls (broadcast over the particles).
        k0: time index of ``particles``.
        channel: measurement channel recorded.
        measurement_noise: add measurement noise to the recorded values.
        level: probability of the central band of weighted quantiles.
    Returns:
        :class:`SamplePaths`.
    """
    horizon = check_pos_int(horizon, "horizon")
    level = check_level(level)
    check_channel(channel, model.obs_dim)
    k0 = check_nonneg_int(k0, "k0")  # (a float k0 reached f, h and the noise as k)
    measurement_noise = check_flag(measurement_noise, "measurement_noise")  # ("no" was true)
    n = model.state_dim
    x = check_float_tensor(particles, "particles", f"(..., N, {n})")
    if x.dim() < 2 or x.shape[-1] != n:
        raise ValueError(f"particles must have shape (..., N, n) with n={n}, got {tuple(x.shape)}")
    check_finite(x, "particles", f"(..., N, {n})")
    check_generator(generator, x)
    batch, N = x.shape[:-2], x.shape[-2]
    w64 = check_weights(weights, batch, N, x.device)  # float64, kept for the weights returned
    w = w64.to(x.dtype)
    us = check_controls(model, us, horizon)
    out = []
    for j in range(horizon):
        k = k0 + j + 1
        u = None if us is None else us[j].unsqueeze(-2)
        # checked: (n,) / (n, n) or the particles' batch dims first (a batched S_Q once widened
        # unbatched particles into a batch of paths), finite
        noise = model.checked_noise(k, batch, x, owner="particles")
        x = model.transition(x, u, k)
        if noise.q is not None:
            x = x + _noise_vec(noise.q, x)
        e = torch.randn(x.shape, generator=generator, dtype=x.dtype, device=x.device)
        x = x + _apply_chol(noise.chol_Q, e, "model.chol_Q", n)
        y = model.observe(x, u, k)
        if measurement_noise:
            mdim = y.shape[-1]
            v = torch.randn(y.shape, generator=generator, dtype=y.dtype, device=y.device)
            y = y + _apply_chol(noise.chol_R, v, "model.chol_R", mdim)
            if noise.r is not None:
                y = y + _noise_vec(noise.r, y)
        out.append(y[..., channel])
    samples = torch.stack(out, dim=-1)  # (..., N, H)
    wu = w.unsqueeze(-1)
    # a path of weight zero does not count, even diverged (0 x NaN made the mean NaN); the
    # same sums wherever the paths are finite
    weighted = torch.where(wu > 0, samples, 0.0)
    mean = (wu * weighted).sum(-2)
    std = (wu * (weighted - mean.unsqueeze(-2)) ** 2).sum(-2).sqrt()
    lo, hi = (1.0 - level) / 2.0, (1.0 + level) / 2.0
    return SamplePaths(
        samples=samples,
        weights=w64,
        mean=mean,
        std=std,
        lower=weighted_quantile(samples, w64, lo),
        upper=weighted_quantile(samples, w64, hi),
        level=level,
    )


def _noise_vec(q: Tensor, x: Tensor) -> Tensor:
    q = q.to(dtype=x.dtype, device=x.device)
    return q if q.dim() == 1 else q.unsqueeze(-2)  # batch dims (..., n) -> (..., 1, n)


def _apply_chol(S: Tensor, e: Tensor, name: str, d: int) -> Tensor:
    """``S e`` per particle: ``S`` ``(d, d)`` or ``(..., d, d)`` (batch dims without N)."""
    S = torch.as_tensor(S, dtype=e.dtype, device=e.device)
    if S.dim() < 2 or tuple(S.shape[-2:]) != (d, d):
        raise ValueError(f"{name} must have shape (d, d) or (..., d, d) with d={d}")
    if S.dim() > 2:
        S = S.unsqueeze(-3)  # (..., 1, d, d): one factor per batch element, shared by particles
    return (S @ e.unsqueeze(-1)).squeeze(-1)


def predict_paths(
    model_or_learner: StateSpaceModel | nn.Module | Callable[[Tensor], Tensor],
    window: Tensor | GaussianBelief | FilterState,
    horizon: int,
    *,
    method: str = "auto",
    filt: GaussianFilter | None = None,
    chol_Q=None,
    chol_R=None,
    n_particles: int | None = None,
    weights: Tensor | None = None,
    generator: torch.Generator | None = None,
    n_out_index: int = 0,
    channel: int = 0,
    us: Tensor | None = None,
    k0: int = 0,
    level: float = 0.95,
    measurement_noise: bool = False,
) -> RecursivePaths | GaussianPaths | SamplePaths:
    """Recursive multi-step prediction (paper 002, Eq. 11-14), with or without uncertainty.

    ``method``:

    * ``"deterministic"``: :func:`recursive_predict` from ``window`` ``(..., m)``;
    * ``"gaussian"``: :func:`gaussian_paths` from ``window`` = a belief / filter state
      (``filt`` defaults to :func:`~prognos_torch.filters.sckf`);
    * ``"particle"``: :func:`particle_paths`; ``window`` is ``(..., N, n)`` particles (with
      ``weights``), or ``(..., n)`` replicated ``n_particles`` times, or a belief / filter state
      sampled ``n_particles`` times with ``generator``;
    * ``"auto"``: ``"gaussian"`` for a belief / filter state, ``"deterministic"`` for a tensor.

    A learner is turned into a model with :func:`learner_transition_model` (``m`` from the
    window, noise from ``chol_Q``/``chol_R``) when the method needs one.

    What the band describes differs by method: the Gaussian band is that of the predicted
    *measurement* (its std includes ``R``), the particle paths follow the noise-free
    measurement ``h(x)`` unless ``measurement_noise=True``. So with the defaults a fault
    probability read from a Gaussian band is that of a noisy reading crossing, from particle
    paths that of the indicator itself (lower where ``R`` matters); pass
    ``measurement_noise=True`` to the particle method for the Gaussian reading.

    Returns:
        :class:`RecursivePaths`, :class:`GaussianPaths` or :class:`SamplePaths`.
    """
    methods = ("auto", "deterministic", "gaussian", "particle")
    if method not in methods:
        raise ValueError(f"method must be one of {methods}, got {method!r}")
    horizon = check_pos_int(horizon, "horizon")
    is_belief = isinstance(window, (GaussianBelief, FilterState))
    if method == "auto":
        method = "gaussian" if is_belief else "deterministic"
    if method == "deterministic":
        if is_belief:
            raise TypeError("method='deterministic' needs a window tensor (..., m), not a belief")
        return RecursivePaths(
            recursive_predict(
                model_or_learner,
                window,
                horizon,
                n_out_index=n_out_index,
                channel=channel,
                us=us,
                k0=k0,
            )
        )

    if isinstance(model_or_learner, StateSpaceModel):
        model = model_or_learner
    else:
        if chol_Q is None or chol_R is None:
            raise ValueError(
                f"method={method!r} with a learner needs chol_Q and chol_R to build the "
                "m-order state-space model (learner_transition_model)"
            )
        if is_belief:
            m = (window.belief if isinstance(window, FilterState) else window).dim
        else:
            check_float_tensor(window, "window", "(..., m)")
            m = window.shape[-1]
        model = learner_transition_model(
            model_or_learner, m, chol_Q, chol_R, n_out_index=n_out_index
        )

    if method == "gaussian":
        if not is_belief:
            raise TypeError("method='gaussian' needs a GaussianBelief or FilterState as window")
        return gaussian_paths(
            filt or sckf(), model, window, horizon, us=us, k0=k0, channel=channel, level=level
        )

    # particle
    if generator is None:
        raise ValueError("method='particle' needs an explicit torch.Generator (generator=...)")
    n = model.state_dim
    if is_belief:
        belief = window.belief if isinstance(window, FilterState) else window
        N = check_pos_int(n_particles, "n_particles")
        if weights is not None:
            raise ValueError("weights are only accepted with particles (..., N, n) as window")
        e = torch.randn(
            (*belief.batch_shape, N, n),
            generator=generator,
            dtype=belief.mean.dtype,
            device=belief.mean.device,
        )
        particles = belief.mean.unsqueeze(-2) + (
            belief.chol.unsqueeze(-3) @ e.unsqueeze(-1)
        ).squeeze(-1)
    elif n_particles is not None:
        N = check_pos_int(n_particles, "n_particles")
        w0 = check_window(window, n, "window")
        if weights is not None:
            raise ValueError("weights are only accepted with particles (..., N, n) as window")
        particles = w0.unsqueeze(-2).expand(*w0.shape[:-1], N, n)
    else:
        particles = window
    return particle_paths(
        model,
        particles,
        horizon,
        generator=generator,
        weights=weights,
        us=us,
        k0=k0,
        channel=channel,
        measurement_noise=measurement_noise,
        level=level,
    )
