"""A trained one-step predictor as an m-order state-space model (paper 002, Eq. 15-26).

:func:`learner_transition_model` turns a learner ``f`` with embedding dimension ``m`` into a
:class:`~prognos_torch.core.model.StateSpaceModel` on the window
``P_s = [x_{s-m+1}, ..., x_s]``::

    P_{s+1} = [x_{s-m+2}, ..., x_s, f(P_s)] + [0, ..., 0, w_s]      (Eq. 18-19)
    y_s     = x_s + v_s                                              (Eq. 16 with h = x)

Its Jacobian is the companion matrix whose last row is ``df/dP_s`` (Eq. 21; Eq. 25 for the
Gaussian-kernel LS-SVR), taken by ``torch.func`` through any learner. A filter on this model
starts from :func:`window_belief`, the measured window before its first measurement.

By default the learner is evaluated with detached parameters through
``torch.func.functional_call``: the filter's beliefs carry no autograd graph to the learner (no
memory growth over long runs), and the parameters are looked up at call time, so online updates
of the learner (ROS-ELM ``partial_fit``, a re-``fit`` LS-SVR) are seen.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch
from torch import Tensor, nn
from torch.func import functional_call, jacrev, vmap

from ..core.belief import GaussianBelief
from ..core.model import StateSpaceModel
from ..core.validation import check_finite, check_nonneg_int, check_pos_int, is_int, is_real
from ..learners.introspect import learner_dims, learner_dtype_device

__all__ = ["learner_transition_model", "window_belief"]

_JACOBIANS = ("autograd", "engine", "input_gradient")


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
    if is_real(v) or (isinstance(v, Tensor) and v.dim() == 0):
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
    return check_finite(v, name, f"(..., {size}, {size})")


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
    m = check_pos_int(m, "m")
    n_in, n_out = learner_dims(learner)
    if n_in is not None and n_in != m:
        raise ValueError(f"m={m} does not match the learner's input dimension {n_in}")
    check_nonneg_int(n_out_index, "n_out_index")
    if n_out is not None and n_out_index >= n_out:
        raise ValueError(f"n_out_index={n_out_index} is out of range for n_out={n_out}")
    if jacobian not in _JACOBIANS:
        raise ValueError(f"jacobian must be one of {_JACOBIANS}, got {jacobian!r}")
    if jacobian == "input_gradient" and not callable(getattr(learner, "input_gradient", None)):
        raise TypeError("jacobian='input_gradient' needs a learner with input_gradient(x)")
    dtype, device = learner_dtype_device(learner)
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


def window_belief(
    series: Tensor, end: int, m: int, std: float | Tensor, runs: int | None = None
) -> GaussianBelief:
    """The belief over the m-order state ``P_s`` (Eq. 15-19) from a measured window.

    Mean ``series[end - m : end]`` (the ``m`` values before index ``end``, oldest first),
    square-root covariance ``std I`` (e.g. the measurement noise: the window is measured), the
    start of a filter whose first measurement is ``series[end]``.

    Args:
        series: ``(T,)`` the measured series.
        end: index after the window, ``m <= end <= T``.
        m: the embedding dimension, ``>= 1``.
        std: standard deviation of every window element, ``>= 0`` (a number or a 0-d tensor).
        runs: ``None``, or ``R`` to repeat the belief over ``R`` runs.
    Returns:
        :class:`~prognos_torch.core.belief.GaussianBelief` with mean ``(m,)`` and square-root
        covariance ``(m, m)`` (``(R, m)``, ``(R, m, m)`` with ``runs``), copies.
    """
    m = check_pos_int(m, "m")
    if not isinstance(series, Tensor) or series.dim() != 1:
        raise ValueError(
            f"series must be a tensor of shape (T,), got {getattr(series, 'shape', series)}"
        )
    if not is_int(end) or not m <= end <= series.shape[0]:
        raise ValueError(
            f"end must be an int with m={m} <= end <= T={series.shape[0]}, got {end!r}"
        )
    end = int(end)
    if runs is not None:
        runs = check_pos_int(runs, "runs")
    w = series[end - m : end]
    chol = std * torch.eye(m, dtype=w.dtype, device=w.device)
    if not bool(torch.isfinite(chol).all()) or bool((chol.diagonal() < 0).any()):
        raise ValueError(f"std must be finite and >= 0, got {std!r}")
    if runs is None:
        return GaussianBelief(w.clone(), chol)
    return GaussianBelief(w.expand(runs, m).clone(), chol.expand(runs, m, m).clone())
