"""Learners as transition models, recursive multi-step prediction, and forecasted measurements.

Three pieces, each a functional core with (at most) a thin stateful shell:

1. **Learner as an m-order state-space model** (paper 002, Eq. 15-26):
   :func:`learner_transition_model` turns a trained one-step predictor ``f`` with embedding
   dimension ``m`` into a :class:`~prognos_torch.core.model.StateSpaceModel` on the window
   ``P_s = [x_{s-m+1}, ..., x_s]``::

       P_{s+1} = [x_{s-m+2}, ..., x_s, f(P_s)] + [0, ..., 0, w_s]      (Eq. 18-19)
       y_s     = x_s + v_s                                              (Eq. 16 with h = x)

   Its Jacobian is the companion matrix whose last row is ``df/dP_s`` (Eq. 21; Eq. 25 for the
   Gaussian-kernel LS-SVR), taken by ``torch.func`` through any learner.
2. **Recursive multi-step prediction** (paper 002, Eq. 11-14) with propagated uncertainty:
   :func:`recursive_predict` (deterministic), :func:`gaussian_paths` (the engine's
   :func:`~prognos_torch.filters.run.forecast`, sigma points or EKF) and :func:`particle_paths`
   (weighted sample paths ``(..., N, H)`` for :func:`~prognos_torch.prognosis.rul.fault_probability`
   and :func:`~prognos_torch.prognosis.rul.rul_distribution`); :func:`predict_paths` dispatches.
3. **Forecasted measurements for fault prediction** (paper 000, Sec. 5, steps 1-9):
   :class:`MeasurementForecaster` (one ROS-ELM per measurement channel, batched over Monte Carlo
   runs), :func:`predict_fault_parameter` (steps 3-8: filter the pseudo-measurements
   ``z_{k+1..k+n}`` from a copy of the current filter state) and
   :func:`rolling_fault_prediction` (step 9: walk ``k`` over the real measurements).
"""

from __future__ import annotations

import copy
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import torch
from torch import Tensor, nn
from torch.func import functional_call, jacrev, vmap

from ..core.belief import GaussianBelief
from ..core.model import StateSpaceModel
from ..datasets.windows import shift_append
from ..filters.gaussian import FilterState, GaussianFilter, sckf
from ..filters.run import forecast as _engine_forecast
from ..filters.run import run as _engine_run
from .rul import check_weights

__all__ = [
    "learner_transition_model",
    "recursive_predict",
    "gaussian_paths",
    "particle_paths",
    "predict_paths",
    "RecursivePaths",
    "GaussianPaths",
    "SamplePaths",
    "ROSELMState",
    "ros_elm_init",
    "ros_elm_update",
    "ros_elm_forecast",
    "MeasurementForecaster",
    "FaultPrediction",
    "predict_fault_parameter",
    "RollingFaultPrediction",
    "rolling_fault_prediction",
]

_JACOBIANS = ("autograd", "engine", "input_gradient")


# =============================================================================== checks
def _check_pos_int(v, name: str) -> int:
    if isinstance(v, bool) or not isinstance(v, int) or v < 1:
        raise ValueError(f"{name} must be a positive int, got {v!r}")
    return v


def _check_nonneg_int(v, name: str) -> int:
    if isinstance(v, bool) or not isinstance(v, int) or v < 0:
        raise ValueError(f"{name} must be a non-negative int, got {v!r}")
    return v


def _check_tensor(x, name: str, shape_hint: str) -> Tensor:
    if not isinstance(x, Tensor):
        raise TypeError(f"{name} must be a torch.Tensor of shape {shape_hint}, got {type(x)}")
    if not x.is_floating_point():
        raise TypeError(f"{name} must be a floating tensor of shape {shape_hint}, got {x.dtype}")
    return x


def _check_finite(x: Tensor, name: str, shape_hint: str) -> Tensor:
    if not bool(torch.isfinite(x).all()):
        raise ValueError(f"{name} contains non-finite values (NaN or inf); shape {shape_hint}")
    return x


def _check_window(window, m: int, name: str = "window") -> Tensor:
    hint = f"(..., {m})"
    w = _check_tensor(window, name, hint)
    if w.dim() < 1 or w.shape[-1] != m:
        raise ValueError(
            f"{name} must have shape (..., m) with m={m} (the embedding dimension, oldest value "
            f"first), got {tuple(w.shape)}"
        )
    return _check_finite(w, name, hint)


def _check_level(level: float) -> float:
    if isinstance(level, bool) or not isinstance(level, (int, float)) or not 0.0 < level < 1.0:
        raise ValueError(f"level must be a number in (0, 1), got {level!r}")
    return float(level)


def _learner_dims(learner) -> tuple[int | None, int | None]:
    """Input/output sizes of a learner when it says them (ELM, LSSVR, ANFIS, nn.Linear)."""
    n_in = n_out = None
    for attr in ("n_in", "n_inputs", "in_features"):
        v = getattr(learner, attr, None)
        if isinstance(v, int) and not isinstance(v, bool):
            n_in = v
            break
    for attr in ("n_out", "out_features"):
        v = getattr(learner, attr, None)
        if isinstance(v, int) and not isinstance(v, bool):
            n_out = v
            break
    return n_in, n_out


def _like(learner) -> tuple[torch.dtype, torch.device]:
    """dtype and device of a learner's first parameter (or buffer); float64 on CPU otherwise."""
    if isinstance(learner, nn.Module):
        for t in list(learner.parameters()) + list(learner.buffers()):
            if t.is_floating_point():
                return t.dtype, t.device
    return torch.float64, torch.device("cpu")


def _frozen_call(learner, detach: bool) -> Callable[[Tensor], Tensor]:
    """``x (..., m) -> learner(x) (..., n_out)`` as a pure function.

    With ``detach`` the learner's parameters enter as detached tensors through
    ``torch.func.functional_call``: the filter's beliefs carry no autograd graph to the learner
    (no memory growth over long runs), and the parameters are looked up at call time, so online
    updates of the learner (ROS-ELM ``partial_fit``, a re-``fit`` LS-SVR) are seen.
    """
    if not isinstance(learner, nn.Module):
        if not callable(learner):
            raise TypeError(f"learner must be a torch.nn.Module or a callable, got {type(learner)}")
        return learner
    if not detach:
        return learner

    def call(x: Tensor) -> Tensor:
        params = {k: v.detach() for k, v in learner.named_parameters()}
        return functional_call(learner, params, (x,))

    return call


def _as_chol(v, size: int, name: str, dtype, device, *, newest_only: bool):
    """A noise square root: a number/0-d tensor (std), a ``(..., size, size)`` tensor or a callable."""
    if callable(v) and not isinstance(v, Tensor):
        return v
    if isinstance(v, bool):
        raise TypeError(f"{name} must be a number, a tensor or a callable, got bool")
    if isinstance(v, (int, float)) or (isinstance(v, Tensor) and v.dim() == 0):
        std = float(v)
        if not math.isfinite(std) or std < 0:
            raise ValueError(f"{name} as a standard deviation must be finite and >= 0, got {std}")
        S = torch.zeros(size, size, dtype=dtype, device=device)
        if newest_only:
            S[-1, -1] = std
        else:
            S.diagonal().fill_(std)
        return S
    if not isinstance(v, Tensor):
        raise TypeError(f"{name} must be a number, a tensor (..., {size}, {size}) or a callable")
    if v.dim() < 2 or tuple(v.shape[-2:]) != (size, size):
        raise ValueError(
            f"{name} must be a number (std) or have shape (..., {size}, {size}), got "
            f"{tuple(v.shape)}"
        )
    return _check_finite(v, name, f"(..., {size}, {size})")


# =============================================================================== 1. learner -> model
def learner_transition_model(
    learner: nn.Module | Callable[[Tensor], Tensor],
    m: int,
    chol_Q,
    chol_R,
    *,
    n_out_index: int = 0,
    jacobian: str = "autograd",
    detach: bool = True,
    shift_std: float = 0.0,
) -> StateSpaceModel:
    """A trained one-step predictor as an m-order state-space model (paper 002, Eq. 15-26).

    State ``P_s = [x_{s-m+1}, ..., x_s]`` (``(m,)``, oldest first, as
    :func:`~prognos_torch.datasets.windows.embed` builds the training inputs)::

        P_{s+1} = [x_{s-m+2}, ..., x_s, f(P_s)] + w_s,   w_s ~ N(0, Q)          (Eq. 18-19)
        y_s     = x_s + v_s,                              v_s ~ N(0, R)          (Eq. 16, y = x)

    **Process noise structure.** Eq. 19 puts the noise on the new element only, so
    ``Q = q^2 e_m e_m^T`` and its lower square root is ``diag(0, ..., 0, q)``: singular, which
    the square-root filters handle exactly (``Tria([A, S_Q])`` needs no positive definite
    ``S_Q``). Pass ``chol_Q`` as the number ``q`` to get that factor, and ``shift_std`` ``s > 0``
    for ``diag(s, ..., s, q)``: the particle filters with Gaussian proposals (EKPF, UPF, STPF)
    weight by the transition density, which needs a nonsingular ``Q``. Or pass an ``(m, m)`` (or
    ``(..., m, m)`` with the belief's batch dims) lower factor, or a callable ``k -> tensor``, to
    use any other structure (e.g. a small jitter on the shifted elements). ``chol_R`` is the
    measurement std (a number) or a ``(1, 1)``/``(..., 1, 1)`` factor or a callable.

    **Jacobian** (EKF / strong-tracking EKF, Eq. 17 and 20-26). The state is the whole window,
    so ``dF/dP`` is the companion matrix: rows ``e_2, ..., e_m`` (the shift) and the last row
    ``df/dP_s`` (Eq. 21; for the Gaussian-kernel LS-SVR its closed form is Eq. 25). Paper 002
    Eq. 23/26 keep only the ``(m, m)`` entry ``df/dx_s`` (a scalar-state view of the same
    model; their ``Tr[(df/dP_s)^T dP_s/dx_s]`` is exactly that entry). ``jacobian`` selects how
    it is computed:

    * ``"autograd"`` (default): ``torch.func.jacrev`` of the learner's scalar output through the
      learner (any learner), assembled into the companion matrix;
    * ``"engine"``: no ``jac_f``; the engine's ``vmap(jacfwd(f))`` of the whole transition;
    * ``"input_gradient"``: ``learner.input_gradient(P)`` (``(B, n_out, m)``, e.g.
      :meth:`~prognos_torch.learners.LSSVR.input_gradient`, the route of Eq. 20-26).

    ``f`` and ``h`` accept any leading dimensions (``batched=True``) and are pure tensor code,
    so they also run under ``vmap`` (over particles, sigma points or runs).

    Args:
        learner: trained predictor ``(..., m) -> (..., n_out)`` (ELM, LSSVR, ANFIS, any
            ``nn.Module`` or pure callable).
        m: embedding dimension (model order), the state dimension.
        chol_Q: std ``q`` of ``w_s`` (number) or a square-root factor / callable, see above.
        chol_R: std of ``v_s`` (number) or a ``(..., 1, 1)`` factor / callable.
        n_out_index: which learner output is the next value ``x_{s+1}``.
        jacobian: ``"autograd"``, ``"engine"`` or ``"input_gradient"``.
        detach: evaluate the learner with detached parameters (default; see the module notes).
        shift_std: std of the noise on the shifted (older) window elements when ``chol_Q`` is
            a number (default 0: Eq. 19 exactly).
    Returns:
        A :class:`StateSpaceModel` with ``state_dim = m``, ``obs_dim = 1``, ``batched=True``.
    """
    m = _check_pos_int(m, "m")
    n_in, n_out = _learner_dims(learner)
    if n_in is not None and n_in != m:
        raise ValueError(f"m={m} does not match the learner's input dimension {n_in}")
    if isinstance(n_out_index, bool) or not isinstance(n_out_index, int) or n_out_index < 0:
        raise ValueError(f"n_out_index must be a non-negative int, got {n_out_index!r}")
    if n_out is not None and n_out_index >= n_out:
        raise ValueError(f"n_out_index={n_out_index} is out of range for n_out={n_out}")
    if jacobian not in _JACOBIANS:
        raise ValueError(f"jacobian must be one of {_JACOBIANS}, got {jacobian!r}")
    if jacobian == "input_gradient" and not callable(getattr(learner, "input_gradient", None)):
        raise TypeError("jacobian='input_gradient' needs a learner with input_gradient(x)")
    dtype, device = _like(learner)
    shift_std = float(shift_std)
    if not math.isfinite(shift_std) or shift_std < 0:
        raise ValueError(f"shift_std must be finite and >= 0, got {shift_std}")
    if shift_std > 0 and (callable(chol_Q) or (isinstance(chol_Q, Tensor) and chol_Q.dim() > 0)):
        raise ValueError("shift_std applies when chol_Q is a number (the std q of Eq. 19)")
    SQ = _as_chol(chol_Q, m, "chol_Q", dtype, device, newest_only=True)
    if shift_std > 0:
        SQ.diagonal()[:-1] = shift_std
    SR = _as_chol(chol_R, 1, "chol_R", dtype, device, newest_only=False)
    call = _frozen_call(learner, detach)
    idx = n_out_index

    def f(x: Tensor, u, k: int) -> Tensor:  # Eq. 18-19 (noise-free part)
        nxt = call(x)[..., idx : idx + 1]
        return torch.cat([x[..., 1:], nxt], dim=-1)

    def h(x: Tensor, u, k: int) -> Tensor:  # y_s = x_s
        return x[..., -1:]

    def jac_h(x: Tensor, u, k: int) -> Tensor:
        e = torch.zeros(m, dtype=x.dtype, device=x.device)
        e[-1] = 1.0
        return e.expand(*x.shape[:-1], 1, m)

    def companion(x: Tensor, grad: Tensor) -> Tensor:
        shift = torch.eye(m, dtype=x.dtype, device=x.device)[1:]  # rows e_2 .. e_m
        return torch.cat([shift.expand(*grad.shape[:-1], m - 1, m), grad.unsqueeze(-2)], dim=-2)

    def jac_autograd(x: Tensor, u, k: int) -> Tensor:  # Eq. 21, any learner
        lead = x.shape[:-1]
        xf = x.reshape(-1, m)
        g = vmap(jacrev(lambda xi: call(xi)[..., idx]))(xf)  # (B, m)
        return companion(x, g.reshape(*lead, m))

    def jac_input_gradient(x: Tensor, u, k: int) -> Tensor:  # Eq. 20-26 via the learner
        lead = x.shape[:-1]
        g = learner.input_gradient(x.reshape(-1, m))[:, idx, :]  # (B, m)
        if detach:
            g = g.detach()
        return companion(x, g.reshape(*lead, m))

    jac_f = {"autograd": jac_autograd, "engine": None, "input_gradient": jac_input_gradient}
    return StateSpaceModel(
        f=f,
        h=h,
        state_dim=m,
        obs_dim=1,
        chol_Q=SQ,
        chol_R=SR,
        batched=True,
        jac_f=jac_f[jacobian],
        jac_h=jac_h,
    )


# =============================================================================== 2. prediction
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
        lower, upper: ``(..., H)`` weighted quantiles ``(1 -+ level) / 2``.
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
        return _weighted_quantile(self.samples, self.weights, q)


def _weighted_quantile(samples: Tensor, weights: Tensor, q: float) -> Tensor:
    if not 0.0 < q <= 1.0:
        raise ValueError(f"q must lie in (0, 1], got {q}")
    s, order = samples.sort(dim=-2)  # (..., N, H)
    w = weights.to(samples.dtype).unsqueeze(-1).expand_as(samples).gather(-2, order)
    cdf = w.cumsum(-2)
    n = samples.shape[-2]
    idx = (cdf < q - 1e-12).sum(-2, keepdim=True).clamp(max=n - 1)  # first index with cdf >= q
    return s.gather(-2, idx).squeeze(-2)


def _check_us(model: StateSpaceModel, us, horizon: int, name: str = "us") -> Tensor | None:
    if model.control_dim == 0:
        if us is not None:
            raise ValueError(f"{name} was given but the model has control_dim=0")
        return None
    p = model.control_dim
    if not isinstance(us, Tensor) or us.dim() < 2 or us.shape[0] != horizon or us.shape[-1] != p:
        got = tuple(us.shape) if isinstance(us, Tensor) else type(us)
        raise ValueError(
            f"{name} must have shape ({horizon}, ..., {p}) (one row per step), got {got}"
        )
    return us


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
    horizon = _check_pos_int(horizon, "horizon")
    if isinstance(learner_or_model, StateSpaceModel):
        model = learner_or_model
        x = _check_window(window, model.state_dim, "window")
        us = _check_us(model, us, horizon)
        _check_channel(channel, model.obs_dim)
        out = []
        for j in range(horizon):
            u = None if us is None else us[j]
            x = model.transition(x, u, k0 + j + 1)
            out.append(model.observe(x, u, k0 + j + 1)[..., channel])
        return torch.stack(out, dim=-1)
    n_in, _ = _learner_dims(learner_or_model)
    if not callable(learner_or_model):
        raise TypeError(
            f"learner_or_model must be a learner or a StateSpaceModel, got {type(learner_or_model)}"
        )
    m = n_in if n_in is not None else (window.shape[-1] if isinstance(window, Tensor) else 0)
    w = _check_window(window, m, "window")
    out = []
    for _ in range(horizon):
        nxt = learner_or_model(w)[..., n_out_index]  # Eq. 12-14
        out.append(nxt)
        w = shift_append(w, nxt)  # P_{k-m+j+1}
    return torch.stack(out, dim=-1)


def _check_channel(channel, obs_dim: int) -> int:
    if isinstance(channel, bool) or not isinstance(channel, int) or not 0 <= channel < obs_dim:
        raise ValueError(f"channel must be an int in [0, {obs_dim}), got {channel!r}")
    return channel


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
    horizon = _check_pos_int(horizon, "horizon")
    level = _check_level(level)
    _check_channel(channel, model.obs_dim)
    if not isinstance(init, (GaussianBelief, FilterState)):
        raise TypeError(f"init must be a GaussianBelief or a FilterState, got {type(init)}")
    belief = init.belief if isinstance(init, FilterState) else init
    if belief.dim != model.state_dim:
        raise ValueError(
            f"init.mean must have shape (..., {model.state_dim}) for this model, "
            f"got {tuple(belief.mean.shape)}"
        )
    _check_finite(belief.mean, "init.mean", f"(..., {model.state_dim})")
    us = _check_us(model, us, horizon)
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
    horizon = _check_pos_int(horizon, "horizon")
    level = _check_level(level)
    _check_channel(channel, model.obs_dim)
    n = model.state_dim
    x = _check_tensor(particles, "particles", f"(..., N, {n})")
    if x.dim() < 2 or x.shape[-1] != n:
        raise ValueError(f"particles must have shape (..., N, n) with n={n}, got {tuple(x.shape)}")
    _check_finite(x, "particles", f"(..., N, {n})")
    if not isinstance(generator, torch.Generator):
        raise TypeError(f"generator must be a torch.Generator, got {type(generator)}")
    batch, N = x.shape[:-2], x.shape[-2]
    w = check_weights(weights, batch, N, x.device).to(x.dtype)
    us = _check_us(model, us, horizon)
    out = []
    for j in range(horizon):
        k = k0 + j + 1
        u = None if us is None else us[j].unsqueeze(-2)
        noise = model.noise(k)
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
    mean = (wu * samples).sum(-2)
    std = (wu * (samples - mean.unsqueeze(-2)) ** 2).sum(-2).sqrt()
    lo, hi = (1.0 - level) / 2.0, (1.0 + level) / 2.0
    return SamplePaths(
        samples=samples,
        weights=w.to(torch.float64),
        mean=mean,
        std=std,
        lower=_weighted_quantile(samples, w, lo),
        upper=_weighted_quantile(samples, w, hi),
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

    Returns:
        :class:`RecursivePaths`, :class:`GaussianPaths` or :class:`SamplePaths`.
    """
    methods = ("auto", "deterministic", "gaussian", "particle")
    if method not in methods:
        raise ValueError(f"method must be one of {methods}, got {method!r}")
    horizon = _check_pos_int(horizon, "horizon")
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
            _check_tensor(window, "window", "(..., m)")
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
        N = _check_pos_int(n_particles, "n_particles")
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
        N = _check_pos_int(n_particles, "n_particles")
        w0 = _check_window(window, n, "window")
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


# =============================================================================== 3. ROS-ELM forecaster
@dataclass(frozen=True)
class ROSELMState:
    """Online state of one ROS-ELM per measurement channel, batched over runs (paper 000 Eq. 54-56).

    Attributes:
        window: ``(..., C, p)`` the last ``p`` measurements of each channel, oldest first.
        beta: per channel ``(..., L_c)`` output weights (float64); empty for static learners.
        K: per channel ``(..., L_c, L_c)`` ``(H^T H + lambda I)^{-1}`` (float64, Eq. 55).
        n_seen: number of (window, target) pairs absorbed.
    """

    window: Tensor
    beta: tuple[Tensor, ...]
    K: tuple[Tensor, ...]
    n_seen: int

    @property
    def batch_shape(self) -> torch.Size:
        return self.window.shape[:-2]


def _hidden(elm, x: Tensor) -> Tensor:
    """ELM hidden outputs (paper 000 Eq. 48) in float64, ``(..., p) -> (..., L)``."""
    dt = elm.a.dtype
    return elm.hidden(x.to(dt)).to(torch.float64)


def _pairs(series: Tensor, p: int) -> tuple[Tensor, Tensor]:
    """``series`` ``(..., T)`` -> inputs ``(..., T - p, p)`` and targets ``(..., T - p)``
    (:func:`~prognos_torch.datasets.windows.embed` with batch dims leading)."""
    win = series.unfold(-1, p, 1)  # (..., T - p + 1, p)
    return win[..., :-1, :], series[..., p:]


def ros_elm_init(elms: Sequence[nn.Module], z0: Tensor, p: int, lam: float) -> ROSELMState:
    """ROS-ELM Step I for every channel and run (paper 000 Sec. 5 step 1 and Eq. 54).

    Channel ``c`` of ``z0`` is embedded into ``N0 - p`` pairs ``([z_{t-p+1}, ..., z_t], z_{t+1})``
    and ``K_0 = (H_0^T H_0 + lambda I)^{-1}``, ``beta_0 = K_0 H_0^T T_0`` are solved per run
    (Cholesky, float64). The ELMs supply the random hidden layer only (``a``, ``b``, ``g``); they
    are shared by the runs and not modified.

    Args:
        elms: one :class:`~prognos_torch.learners.ELM` (``n_in = p``, ``n_out = 1``) per channel.
        z0: ``(N0, ..., C)`` initial measurements, time first.
        p: embedding dimension.
        lam: ridge parameter ``lambda >= 0`` (Eq. 52).
    Returns:
        The :class:`ROSELMState` after ``z0``.
    """
    z0 = _check_tensor(z0, "z0", "(N0, ..., C)")
    C = len(elms)
    if z0.dim() < 2 or z0.shape[-1] != C:
        raise ValueError(
            f"z0 must have shape (N0, ..., C) with C={C} channels, got {tuple(z0.shape)}"
        )
    if z0.shape[0] < p + 1:
        raise ValueError(
            f"z0 must hold N0 >= p + 1 = {p + 1} samples to form a training pair, got N0={z0.shape[0]}"
        )
    _check_finite(z0, "z0", "(N0, ..., C)")
    if not (isinstance(lam, (int, float)) and not isinstance(lam, bool) and 0 <= lam < math.inf):
        raise ValueError(f"lam must be a finite number >= 0, got {lam!r}")
    z64 = z0.to(torch.float64).movedim(0, -1)  # (..., C, N0)
    betas, Ks = [], []
    for c, elm in enumerate(elms):
        X, T = _pairs(z64[..., c, :], p)  # (..., N', p), (..., N')
        H = _hidden(elm, X)  # (..., N', L)
        L = H.shape[-1]
        G = H.mT @ H + lam * torch.eye(L, dtype=H.dtype, device=H.device)
        chol, info = torch.linalg.cholesky_ex(G)
        if bool((info > 0).any()):
            raise ValueError(
                f"channel {c}: H^T H + lam I (Eq. 54) is singular; use lam > 0 or N0 - p >= L"
            )
        eye = torch.eye(L, dtype=H.dtype, device=H.device).expand_as(G)
        K = torch.cholesky_solve(eye, chol)
        K = 0.5 * (K + K.mT)
        beta = torch.cholesky_solve((H.mT @ T.unsqueeze(-1)), chol).squeeze(-1)  # Eq. 54
        betas.append(beta)
        Ks.append(K)
    window = z64[..., -p:]  # (..., C, p)
    return ROSELMState(window, tuple(betas), tuple(Ks), int(z0.shape[0] - p))


def ros_elm_update(elms: Sequence[nn.Module], state: ROSELMState, z: Tensor) -> ROSELMState:
    """ROS-ELM Step II with the newest measurement ``z`` (paper 000 Eq. 55-56, Sec. 5 step 9).

    Per channel and run, with ``h = g(a P + b)`` of the current window ``P`` and target ``z_c``::

        K_k    = K_{k-1} - K_{k-1} h^T h K_{k-1} / (1 + h K_{k-1} h^T)      (Eq. 55)
        beta_k = beta_{k-1} + K_k h^T (z_c - h beta_{k-1})                   (Eq. 56)

    then the window shifts in ``z`` (Eq. 12-14 on real data).

    Args:
        z: ``(..., C)`` with the state's batch shape.
    """
    want = tuple(state.window.shape[:-1])
    z = _check_tensor(z, "z", f"{want}")
    if tuple(z.shape) != want:
        raise ValueError(f"z must have shape {want} (batch shape + (C,)), got {tuple(z.shape)}")
    _check_finite(z, "z", f"{want}")
    z = z.to(state.window.dtype)
    betas, Ks = [], []
    for c, elm in enumerate(elms):
        beta, K = state.beta[c], state.K[c]
        if beta.numel() == 0:  # static learner: nothing to learn
            betas.append(beta)
            Ks.append(K)
            continue
        h = _hidden(elm, state.window[..., c, :])  # (..., L)
        Kh = (K @ h.unsqueeze(-1)).squeeze(-1)  # (..., L)
        s = 1.0 + (h * Kh).sum(-1, keepdim=True)
        K_new = K - Kh.unsqueeze(-1) * Kh.unsqueeze(-2) / s.unsqueeze(-1)  # Eq. 55
        K_new = 0.5 * (K_new + K_new.mT)
        err = z[..., c] - (h * beta).sum(-1)
        beta_new = beta + (K_new @ h.unsqueeze(-1)).squeeze(-1) * err.unsqueeze(-1)  # Eq. 56
        betas.append(beta_new)
        Ks.append(K_new)
    window = shift_append(state.window, z)
    return ROSELMState(window, tuple(betas), tuple(Ks), state.n_seen + 1)


def ros_elm_forecast(
    elms: Sequence[nn.Module | Callable[[Tensor], Tensor]], state: ROSELMState, n: int
) -> Tensor:
    """Measurements ``z_{k+1..k+n}`` by successive one-step predictions (paper 000 Sec. 5 step 3).

    ROS-ELM channel ``c``: ``z^_{c,k+j} = h(P) beta_c`` (Eq. 47); a static learner uses its own
    ``forward``. The window of each channel absorbs its forecasts (paper 002 Eq. 12-14).

    Returns:
        ``(n, ..., C)`` float64.
    """
    n = _check_pos_int(n, "n")
    w = state.window
    out = []
    for _ in range(n):
        cols = []
        for c, learner in enumerate(elms):
            beta = state.beta[c]
            if beta.numel():
                cols.append((_hidden(learner, w[..., c, :]) * beta).sum(-1))
            else:
                wc = w[..., c, :]
                dt, _dev = _like(learner)
                cols.append(learner(wc.to(dt))[..., 0].to(w.dtype))
        zhat = torch.stack(cols, dim=-1)  # (..., C)
        out.append(zhat)
        w = shift_append(w, zhat)
    return torch.stack(out, dim=0)


class MeasurementForecaster:
    """Forecast future measurements with one learner per channel (paper 000 Sec. 5).

    A thin stateful shell over :func:`ros_elm_init` (step 1), :func:`ros_elm_forecast` (step 3)
    and :func:`ros_elm_update` (step 9). The online state (window, ``beta``, ``K``) lives in an
    immutable :class:`ROSELMState` with leading batch dims (Monte Carlo runs, assets): one set
    of output weights per run, while the random hidden layers of the ELMs are shared by the
    runs. The learner modules themselves are never modified.

    Learners: :class:`~prognos_torch.learners.ELM` with ``online=True`` (ROS-ELM, default for
    ELMs), or any trained learner ``(..., p) -> (..., 1)`` with ``online=False`` (static model:
    :meth:`update` only shifts the window).

    Args:
        learners: one learner per measurement channel (input dimension ``p``).
        p: embedding dimension.
        lam: ridge parameter ``lambda`` of the ROS-ELM initialisation (Eq. 52-54).
        online: learn online (ELMs only); ``None``: true if every learner is an ELM.
    """

    def __init__(
        self,
        learners: Sequence[nn.Module | Callable[[Tensor], Tensor]],
        p: int,
        *,
        lam: float = 1e-8,
        online: bool | None = None,
    ) -> None:
        from ..learners import ELM

        self.p = _check_pos_int(p, "p")
        learners = tuple(learners)
        if not learners:
            raise ValueError("learners must hold one learner per measurement channel (C >= 1)")
        all_elm = all(isinstance(lr, ELM) for lr in learners)
        self.online = all_elm if online is None else bool(online)
        if self.online and not all_elm:
            raise TypeError("online=True (ROS-ELM) needs ELM learners for every channel")
        for c, lr in enumerate(learners):
            if not callable(lr):
                raise TypeError(f"learners[{c}] must be callable, got {type(lr)}")
            n_in, n_out = _learner_dims(lr)
            if n_in is not None and n_in != p:
                raise ValueError(f"learners[{c}] has input dimension {n_in}, expected p={p}")
            if self.online and n_out != 1:
                raise ValueError(f"learners[{c}] must have n_out=1 for ROS-ELM, got {n_out}")
        if not (
            isinstance(lam, (int, float)) and not isinstance(lam, bool) and 0 <= lam < math.inf
        ):
            raise ValueError(f"lam must be a finite number >= 0, got {lam!r}")
        self.learners = learners
        self.lam = float(lam)
        self.state: ROSELMState | None = None

    @classmethod
    def ros_elm(
        cls,
        n_channels: int,
        p: int = 3,
        n_hidden: int = 50,
        lam: float = 1e-8,
        *,
        activation: str = "sigmoid",
        generator: torch.Generator | None = None,
        dtype: torch.dtype = torch.float64,
    ) -> MeasurementForecaster:
        """``n_channels`` ROS-ELMs with the paper's set-up (paper 000 Sec. 6: ``p = 3``,
        ``L = 50``, ``lambda = 1e-8``, sigmoid, ``a ~ U[-1, 1]``, ``b ~ U[0, 1]``); the hidden
        layers are drawn from ``generator`` (``None``: seeded with 0)."""
        from ..learners import ELM

        n_channels = _check_pos_int(n_channels, "n_channels")
        if generator is None:
            generator = torch.Generator().manual_seed(0)
        elms = [
            ELM(p, n_hidden, 1, activation=activation, generator=generator, dtype=dtype)
            for _ in range(n_channels)
        ]
        return cls(elms, p, lam=lam, online=True)

    @property
    def n_channels(self) -> int:
        return len(self.learners)

    @property
    def initialized(self) -> bool:
        return self.state is not None

    def copy(self) -> MeasurementForecaster:
        """A copy sharing the (unmodified) learners; the immutable state is shared until updated."""
        return copy.copy(self)

    def initialize(self, z0: Tensor) -> MeasurementForecaster:
        """Step 1: train on the first ``N0`` measurements ``z0`` ``(N0, ..., C)``."""
        if self.online:
            self.state = ros_elm_init(self.learners, z0, self.p, self.lam)
            return self
        z0 = _check_tensor(z0, "z0", "(N0, ..., C)")
        C = self.n_channels
        if z0.dim() < 2 or z0.shape[-1] != C or z0.shape[0] < self.p:
            raise ValueError(
                f"z0 must have shape (N0, ..., C) with C={C} and N0 >= p={self.p}, "
                f"got {tuple(z0.shape)}"
            )
        _check_finite(z0, "z0", "(N0, ..., C)")
        win = z0[-self.p :].to(torch.float64).movedim(0, -1)
        empty = win.new_zeros(0)
        self.state = ROSELMState(win, (empty,) * C, (empty,) * C, 0)
        return self

    def _require(self) -> ROSELMState:
        if self.state is None:
            raise RuntimeError("call initialize(z0) first (paper 000 Sec. 5 step 1)")
        return self.state

    def forecast(self, n: int) -> Tensor:
        """Step 3: ``z_{k+1..k+n}`` ``(n, ..., C)`` by successive one-step predictions."""
        return ros_elm_forecast(self.learners, self._require(), n)

    def update(self, z: Tensor) -> MeasurementForecaster:
        """Step 9: absorb the new real measurement ``z`` ``(..., C)`` (ROS-ELM Eq. 55-56)."""
        self.state = ros_elm_update(self.learners, self._require(), z)
        return self


# =============================================================================== fault prediction
def _param_select(index, n: int) -> Tensor:
    if index is None:
        return torch.arange(n)
    if isinstance(index, bool):
        raise TypeError("param_index must be an int, a slice, a sequence of ints or None")
    if isinstance(index, int):
        idx = [index]
    elif isinstance(index, slice):
        idx = list(range(n))[index]
    else:
        try:
            idx = [int(i) for i in index]
        except TypeError as exc:
            raise TypeError(
                "param_index must be an int, a slice, a sequence of ints or None"
            ) from exc
    if not idx or any(not -n <= i < n for i in idx):
        raise ValueError(f"param_index {index!r} selects nothing or is out of range for n={n}")
    return torch.tensor([i % n for i in idx], dtype=torch.long)


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
    n = _check_pos_int(n, "n")
    k = _check_nonneg_int(k, "k")
    if not isinstance(state, FilterState):
        raise TypeError(
            f"state must be a FilterState (from filt.init / filt.step), got {type(state)}"
        )
    if not callable(getattr(forecaster, "forecast", None)):
        raise TypeError("forecaster must have a forecast(n) -> (n, ..., m) method")
    sel = _param_select(param_index, model.state_dim)
    bs = tuple(state.belief.batch_shape)
    z = forecaster.forecast(n)
    want = (n, *bs, model.obs_dim)
    if not isinstance(z, Tensor) or tuple(z.shape) != want:
        got = tuple(z.shape) if isinstance(z, Tensor) else type(z)
        raise ValueError(f"forecaster.forecast(n) must return shape {want}, got {got}")
    _check_finite(z, "forecaster.forecast(n)", f"{want}")
    us = _check_us(model, us, n)
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
        ys: ``(T, ..., m)`` real measurements (finite).
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
    n = _check_pos_int(n, "n")
    ys = _check_tensor(ys, "ys", "(T, ..., m)")
    if ys.dim() < 2 or ys.shape[-1] != model.obs_dim:
        raise ValueError(f"ys must have shape (T, ..., {model.obs_dim}), got {tuple(ys.shape)}")
    _check_finite(ys, "ys", "(T, ..., m)")
    T = ys.shape[0]
    start = _check_pos_int(start, "start")
    if start > T:
        raise ValueError(f"start must satisfy 1 <= start <= T={T}, got {start}")
    if not isinstance(init, (GaussianBelief, FilterState)):
        raise TypeError(f"init must be a GaussianBelief or a FilterState, got {type(init)}")
    if model.control_dim:
        us = _check_us(model, us, T + n)
    elif us is not None:
        raise ValueError("us was given but the model has control_dim=0")
    sel = _param_select(param_index, model.state_dim)

    fc = forecaster.copy()
    if not fc.initialized:
        fc.initialize(ys[:start])
    state = init if isinstance(init, FilterState) else filt.init(model, init, 1)
    traj = _engine_run(filt, model, state, ys[:start], None if us is None else us[:start], k0=0)
    state = traj.final
    sel = sel.to(state.belief.mean.device)
    filtered = [m_.index_select(-1, sel) for m_ in traj.means.unbind(0)]

    preds, stds, lams = [], [], []
    for k in range(start, T + 1):
        pred = predict_fault_parameter(
            filt,
            model,
            state,
            fc,
            n,
            k,
            us=None if us is None else us[k : k + n],
            param_index=sel.tolist(),
        )
        preds.append(pred.theta)
        stds.append(pred.theta_std)
        lams.append(pred.fading_factors)
        if k < T:
            u = None if us is None else us[k]
            state, _ = filt.step(model, state, ys[k], u, k=k + 1)
            fc.update(ys[k])
            filtered.append(state.belief.mean.index_select(-1, sel))
    origin = torch.arange(start, T + 1, device=ys.device)
    return RollingFaultPrediction(
        origin=origin,
        target=origin + n,
        predicted=torch.stack(preds),
        predicted_std=torch.stack(stds),
        fading_factors=torch.stack(lams),
        filtered=torch.stack(filtered),
        final=state,
        forecaster=fc,
        n=n,
    )
