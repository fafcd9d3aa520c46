"""The state-space model of one Kalman-optimiser step (paper 003 Eq. 45-46).

``theta_k = theta_{k-1} + w_k`` (Eq. 45, ``f=None``: the random walk the engine propagates
exactly) and ``t_k = g(theta_k, u_k) + v_k`` (Eq. 46, ``h`` closing over the mini-batch
inputs), with the mini-batch's measurement noise ``R / lr`` (block-diagonal, one ``R`` per
sample). The functions take the optimiser (a :class:`~prognos_torch.optim.kalman.KalmanOptimizer`)
and keep its per-shape models in its group configuration; the eager step
(``KalmanOptimizer.step``) and the compiled pass (:mod:`prognos_torch.optim.compiled`) build
their models here.
"""

from __future__ import annotations

import math
from dataclasses import replace

import torch
from torch import Tensor
from torch.func import vmap
from torch.optim import Optimizer

from ..core.model import StateSpaceModel
from ..filters.gaussian import Taylor
from ._kalman_common import _check_lr
from .params import ParameterBridge


def _random_walk_model(b: ParameterBridge, h, jac_h, M: int, chol_Q, chol_R) -> StateSpaceModel:
    """Eq. 45-46 with the measurement ``h`` (and its Jacobian ``jac_h``) of ``M`` entries."""
    return StateSpaceModel(
        f=None,  # Eq. 45: theta_k = theta_{k-1} + w_k (exact in the engine)
        h=h,  # Eq. 46: t_k = g(theta_k, u_k) + v_k
        state_dim=b.numel,
        obs_dim=M,
        chol_Q=chol_Q,
        chol_R=chol_R,
        batched=True,
        jac_h=jac_h,
    )


def measurement_noise(opt: Optimizer, i: int, out_shape: torch.Size) -> Tensor:
    """Square root of group ``i``'s measurement noise ``R / lr`` of a mini-batch."""
    cfg = opt._cfg[i]
    lr = _check_lr(opt.param_groups[i]["lr"], cfg.filter, f"param_groups[{i}]['lr']")
    M = math.prod(out_shape)
    hit = cfg.chol_R.get(M)
    if hit is not None and hit[0] == lr:
        return hit[1]
    dev = cfg.bridge.device
    if cfg.R_scalar:
        S = cfg.chol_R1[0, 0] * torch.eye(M, dtype=torch.float64, device=dev)
    else:
        n_out = cfg.chol_R1.shape[0]
        if len(out_shape) == 0 or out_shape[-1] != n_out:
            raise ValueError(
                f"R is ({n_out}, {n_out}) per output vector, but the model output has shape "
                f"{tuple(out_shape)} (its last dimension must be {n_out})"
            )
        eye = torch.eye(M // n_out, dtype=torch.float64, device=dev)
        S = torch.kron(eye, cfg.chol_R1.contiguous())  # block diagonal: one R per sample
    if lr != 1.0:
        S = S / math.sqrt(lr)
    cfg.chol_R[M] = (lr, S)
    return S


def step_model(opt: Optimizer, i: int, x: Tensor, out_shape: torch.Size) -> StateSpaceModel:
    """Paper 003 Eq. 45-46 for group ``i`` and this mini-batch: random walk,
    ``h(theta) = g(theta, x)`` (the other groups at their values in the module).

    The model is built once per mini-batch shape (and rebuilt with a new ``R / lr`` when
    ``lr`` changes); its ``h`` reads the current inputs from ``opt._inputs``.
    """
    cfg = opt._cfg[i]
    b, chunk = cfg.bridge, opt.param_groups[i]["chunk_size"]
    key = (tuple(x.shape), tuple(out_shape))
    opt._inputs[0] = x
    chol_R = measurement_noise(opt, i, out_shape)
    model = cfg.models.get(key)
    if model is not None:
        if model.chol_R is not chol_R:
            model = cfg.models[key] = replace(model, chol_R=chol_R)
        return model
    M = math.prod(out_shape)
    mode = opt.param_groups[i]["jacobian"]
    if mode == "auto" and not opt._closed_form_applies(b, x, chunk):
        mode = "fwd" if b.numel <= M else "autograd"
    inputs = opt._inputs
    if opt.per_run_data:  # run r evaluates g(theta_r, x_r): vmap over the runs
        if mode == "autograd":  # reverse mode through autograd does not vmap
            mode = "rev"
        model = _per_run_model(opt, b, M, chol_R, mode, chunk)
    elif isinstance(cfg.filter.rule, Taylor) and mode in ("auto", "autograd"):
        # the EKF asks for h and then for its Jacobian at the same point: one pass (the
        # learner's closed form, or forward + reverse) gives both, the Jacobian is handed
        # over by identity of the evaluation point
        last: list = [None, None]

        def h(th, u, k):
            out, J = b.measurement_and_jacobian(th, inputs[0], chunk_size=chunk, mode=mode)
            last[0], last[1] = th, J
            return out

        def jac_h(th, u, k):
            if last[0] is th:
                J, last[0], last[1] = last[1], None, None
                return J
            return b.jacobian(th, inputs[0], mode=mode, chunk_size=chunk)

        model = _random_walk_model(b, h, jac_h, M, cfg.chol_Q, chol_R)
    else:

        def h(th, u, k):
            return b.measurement(th, inputs[0], chunk_size=chunk)

        def jac_h(th, u, k):
            return b.jacobian(th, inputs[0], mode=mode, chunk_size=chunk)

        model = _random_walk_model(b, h, jac_h, M, cfg.chol_Q, chol_R)
    cfg.models[key] = model
    return model


def _per_run_model(opt: Optimizer, b, M: int, chol_R, mode: str, chunk) -> StateSpaceModel:
    """Eq. 45-46 with per-run data: ``theta`` ``(R, ..., n)``, inputs ``(R, *x)``."""
    inputs = opt._inputs

    def h(th, u, k):
        return vmap(lambda t, xr: b.measurement(t, xr, chunk_size=chunk))(th, inputs[0])

    def jac_h(th, u, k):
        return vmap(lambda t, xr: b.jacobian(t, xr, mode=mode, chunk_size=chunk))(th, inputs[0])

    return _random_walk_model(b, h, jac_h, M, opt._cfg[0].chol_Q, chol_R)
