"""The compiled sequence pass of the Kalman optimiser: ``KalmanOptimizer.steps(...,
compile=True)``.

``T`` optimiser steps (paper 003 Eq. 45-46, one engine step each) run as ONE
``torch.compile(fullgraph=True)`` call, the loop a traced :func:`~prognos_torch.filters.scan`
over the same engine step (:meth:`GaussianFilter.step`) that an eager step calls. The functions
take the optimiser (a :class:`~prognos_torch.optim.kalman.KalmanOptimizer`) and read its
configuration and state; :meth:`KalmanOptimizer.steps` delegates here.

The EKF with a scalar measurement runs the engine configured with ``posterior="potter"``:
Potter's posterior square root ``S - beta K (H S)`` (one outer product) instead of the
triangular downdate; its factor is not triangular, which the next step's Cholesky prior does
not need, and the factor the pass ends with is re-triangularised once (``tria``), so that the
state is the lower-triangular factor eager steps keep (the same to rounding).
"""

from __future__ import annotations

import math
from dataclasses import replace
from itertools import chain

import torch
from torch import Tensor
from torch.optim import Optimizer
from torch.optim.optimizer import _global_optimizer_post_hooks, _global_optimizer_pre_hooks

from ..core.belief import GaussianBelief
from ..core.linalg import tria
from ..core.model import Noise, diagonal_noise
from ..core.validation import all_finite, check_finite
from ..filters import sequence as _sequence
from ..filters.gaussian import FilterState, Taylor, _sigma_points, deferred_fallbacks
from ._buffers import tracking_batch_norms
from ._kalman_common import _state_key
from ._step_model import _random_walk_model, measurement_noise

__all__ = ["compiled_steps", "check_compilable", "sequence_step", "potter_posterior"]


def compiled_steps(opt: Optimizer, inputs: Tensor, targets: Tensor) -> Tensor:
    """``opt.steps(inputs, targets, compile=True)`` after its argument checks: inputs ``(T, *x)``,
    targets ``(T, *out)``; returns the ``(T,)`` (or ``(T, R)``) losses. Sets
    ``opt.compile_time``; a pass that needed a fallback (non-finite result) is discarded and
    the steps rerun eagerly (``opt._steps_eager_from``)."""
    T = inputs.shape[0]
    if T == 0:  # (before check_compilable, whose EKF test reads inputs[0]: an IndexError)
        raise ValueError("steps needs at least one step (T >= 1)")
    check_compilable(opt, inputs)
    args = (opt, inputs, targets)
    for hook in chain(_global_optimizer_pre_hooks.values(), opt._optimizer_step_pre_hooks.values()):
        if hook(opt, args, {}) is not None:
            raise RuntimeError("a step pre-hook may not replace the arguments of steps()")
    checked = opt._finite_checked
    with torch.inference_mode():
        # the rows share their shape: row 0 stands for all in the type, shape, dtype and
        # device checks of a step; the values are checked all at once
        _, _, out_shape, _ = opt._check_batch(inputs[0], targets[0], True)
        if not checked:
            check_finite(inputs, "inputs")
            if not all_finite(targets):
                if bool(torch.isnan(targets).any()):
                    raise ValueError(
                        "targets contains NaN (missing targets): the compiled pass needs "
                        "complete targets; compile=False steps update with the observed ones"
                    )
                check_finite(targets, "targets")
        step, record = sequence_step(opt, inputs.shape[1:], out_shape)
        # the caches the traced step reads (the learner's constants, the sigma points) are
        # filled here, outside the trace
        s = opt.state[_state_key(0)]
        opt._cfg[0].bridge.measurement(s["mean"].reshape(-1, s["mean"].shape[-1]), inputs[0])
        if not isinstance(opt._cfg[0].filter.rule, Taylor):
            _sigma_points(opt._cfg[0].filter.rule, opt._cfg[0].bridge.numel, s["mean"])
        ys = targets.reshape(T, -1)
        if ys.dtype != torch.float64:
            ys = ys.to(torch.float64)
        key = _state_key(0)
        s = opt.state[key]
        with deferred_fallbacks():
            (mean, chol), rows = _sequence._compiled_scan(
                step, (s["mean"], s["chol"]), ys, inputs, record, cpp_wrapper=_cpp_safe(opt)
            )
        opt.compile_time = _sequence.last_compile_seconds
        if not bool(torch.isfinite(chol).all() & torch.isfinite(mean).all()):
            # a step needed a fallback (or the pass diverged): the eager steps decide
            return opt._steps_eager_from(s, inputs, targets)
    if potter_posterior(opt, out_shape):
        chol = tria(chol).contiguous()  # the triangular factor of S S^T (Potter's is not)
    with torch.inference_mode(False):
        mean, chol = mean.clone(), chol.clone()  # ordinary tensors, as eager steps keep
    opt.state[key] = {
        "mean": mean,
        "chol": chol,
        "fading": None,
        "noise": None,
        "step": s["step"] + T,
    }
    if opt.runs is None:
        opt._cfg[0].bridge.assign(mean)
    for hook in chain(
        opt._optimizer_step_post_hooks.values(), _global_optimizer_post_hooks.values()
    ):
        hook(opt, args, {})
    return rows["loss"]


def _cpp_safe(opt: Optimizer) -> bool:
    """Whether the compiled pass may use inductor's C++ wrapper: not when the learner holds a
    fixed tensor (outside its trained parameters) whose last two dimensions are 1 x 1 (an ELM
    with one input and one hidden node). Its ``.mT`` is evaluated outside the loop and enters
    it as an input that is a view with its base's own layout; in torch 2.13 the C++ wrapper
    passes such an input as a temporary handle that the first iteration frees, and the process
    aborts. A tensor built inside ``forward``, or transposed by a method call
    (``transpose(0, 1)``), stays inside the loop and does not trigger it. The Python wrapper
    runs these learners, slower."""
    fixed = chain(opt.module.buffers(), (p for p in opt.module.parameters() if not p.requires_grad))
    return not any(t.dim() >= 2 and t.shape[-2:] == (1, 1) for t in fixed)


def check_compilable(opt: Optimizer, inputs: Tensor) -> None:
    """Raise a ``ValueError`` naming what ``steps(compile=True)`` needs that ``opt`` lacks."""
    cfg = opt._cfg[0] if len(opt._cfg) == 1 else None
    why = None
    if cfg is None:
        why = "one parameter group"
    elif opt.per_run_data:
        why = "per_run_data=False"
    elif (
        cfg.filter.noise is not None
        or cfg.filter.fading is not None
        or cfg.filter.robust is not None
    ):
        why = "a filter without strong tracking, fading, noise estimator or robust bound"
    elif tracking_batch_norms(opt.module):
        why = "no BatchNorm layer in training mode"
    elif isinstance(cfg.filter.rule, Taylor) and not (
        opt.param_groups[0]["jacobian"] == "auto"
        and opt._closed_form_applies(cfg.bridge, inputs[0], opt._chunk)
    ):
        why = "the learner's closed-form Jacobian for the EKF"
    elif opt._chunk is not None:
        why = "chunk_size=None"
    if why is not None:
        raise ValueError(f"steps(compile=True) needs {why}; use compile=False")


def potter_posterior(opt: Optimizer, out_shape) -> bool:
    """Whether the compiled pass takes Potter's posterior square root
    (``GaussianFilter(posterior="potter")``): the EKF with a scalar measurement."""
    return isinstance(opt._cfg[0].filter.rule, Taylor) and math.prod(out_shape) == 1


def sequence_step(opt: Optimizer, x_shape, out_shape):
    """The step and record functions of the compiled sequence (one per mini-batch shape and
    ``R / lr``, kept so that later passes reuse the compiled code)."""
    cfg = opt._cfg[0]
    chol_R = measurement_noise(opt, 0, out_shape)
    key = ("sequence", tuple(x_shape), tuple(out_shape))
    hit = cfg.models.get(key)
    if hit is not None and hit[0] is chol_R:
        return hit[1], hit[2]
    b, filt, M, runs = cfg.bridge, cfg.filter, math.prod(out_shape), opt.runs
    chol_Q = cfg.chol_Q
    taylor = isinstance(filt.rule, Taylor)
    # the noise of every step, checked and its diagonal test done here, outside the trace
    # (a traced step would form S_Q S_Q^T at every step)
    noise = Noise(None, chol_Q, None, chol_R, diagonal_noise(chol_Q))
    if potter_posterior(opt, out_shape):
        # a scalar EKF measurement: Potter's O(n^2) posterior square root (not triangular;
        # the next step's Cholesky prior is, and compiled_steps re-triangularises the last)
        filt = replace(filt, posterior="potter")

    def step(carry, y, x, k):
        mean, chol = carry
        if taylor:  # h and its closed-form Jacobian from one pass, as in step_model
            last: list = [None, None]

            def h(th, u, k):
                out, J = b.measurement_and_jacobian(th, x)
                last[0], last[1] = th, J
                return out

            def jac_h(th, u, k):
                if last[0] is th:
                    return last[1]
                return b.jacobian(th, x)
        else:

            def h(th, u, k):
                return b.measurement(th, x)

            jac_h = None
        model = _random_walk_model(b, h, jac_h, M, chol_Q, chol_R)
        yy = y if runs is None else y.expand(runs, M)
        state = FilterState(GaussianBelief(mean, chol))
        new, info = filt._update(model, state, yy, None, k, False, noise)
        return (new.belief.mean, new.belief.chol), info

    def record(state, info):
        return {"loss": info.innovation.square().mean(-1)}

    cfg.models[key] = (chol_R, step, record)
    return step, record
