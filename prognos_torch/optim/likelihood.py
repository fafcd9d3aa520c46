"""Maximum-likelihood fitting of model parameters through the square-root filter.

The filter's prediction-error decomposition ``log p(y_{1:T}) = sum_k log N(y_k; z_{k|k-1},
S_zz S_zz^T)`` (:attr:`~prognos_torch.filters.Trajectory.log_likelihood`) is differentiable in
the model: autograd runs through every stage of :meth:`GaussianFilter.step` (QR, Cholesky
downdates, triangular solves, sigma points, Jacobians by ``torch.func``). :func:`fit_likelihood`
maximises it with any ``torch.optim`` optimiser over parameters that a user function maps to a
:class:`~prognos_torch.core.StateSpaceModel` (noise factors, parameters of ``f`` and ``h``, the
initial belief). Square-root factors are parameterised by their log-Cholesky form
(:func:`from_log_cholesky`: strictly lower part free, diagonal ``exp``), so every iterate is a
valid factor and the optimisation is unconstrained.

Batches of series: ``ys`` ``(T, ..., m)`` with the belief's batch dims. The objective is the
sum over the batch, so parameters with the batch dims (one set per series) are fitted
independently in one pass, and parameters without them are shared by all series.
"""

from __future__ import annotations

import copy
from collections.abc import Callable, Mapping
from dataclasses import dataclass

import torch
from torch import Tensor

from ..core.belief import GaussianBelief
from ..core.model import NonFiniteNoiseError, StateSpaceModel
from ..core.validation import is_int, is_real
from ..filters.gaussian import GaussianFilter
from ..filters.run import run

__all__ = ["LikelihoodFit", "fit_likelihood", "from_log_cholesky", "log_cholesky"]


def from_log_cholesky(raw: Tensor) -> Tensor:
    """Lower-triangular factor with positive diagonal from an unconstrained ``(..., n, n)``:
    the strictly lower part of ``raw`` plus ``diag(exp(diag(raw)))`` (the upper part is unused).
    """
    if not isinstance(raw, Tensor) or raw.dim() < 2 or raw.shape[-1] != raw.shape[-2]:
        raise ValueError(
            f"raw must be a tensor of shape (..., n, n), got {getattr(raw, 'shape', raw)}"
        )
    return torch.tril(raw, -1) + torch.diag_embed(torch.diagonal(raw, dim1=-2, dim2=-1).exp())


def log_cholesky(chol: Tensor) -> Tensor:
    """Inverse of :func:`from_log_cholesky` for a lower factor with positive diagonal."""
    if not isinstance(chol, Tensor) or chol.dim() < 2 or chol.shape[-1] != chol.shape[-2]:
        raise ValueError(
            f"chol must be a tensor of shape (..., n, n), got {getattr(chol, 'shape', chol)}"
        )
    if bool((torch.triu(chol, 1) != 0).any()):  # (its upper part would be dropped silently)
        raise ValueError(
            "chol must be lower-triangular (a Cholesky factor); for another square root S of "
            "a covariance use torch.linalg.cholesky(S @ S.mT)"
        )
    d = torch.diagonal(chol, dim1=-2, dim2=-1)
    if not bool((d > 0).all()):
        raise ValueError("chol must have a positive diagonal (a Cholesky factor)")
    return torch.tril(chol, -1) + torch.diag_embed(d.log())


@dataclass(frozen=True)
class LikelihoodFit:
    """Result of :func:`fit_likelihood`.

    Attributes:
        params: the fitted parameters (detached copies, same names and shapes as given).
        model: ``build_model(params)`` at the fitted parameters (built from detached tensors).
        belief: the initial belief used (from ``belief(params)`` when it is a function).
        trace: ``(steps + 1, ...)`` log-likelihood of each series at the start and after each
            optimiser step (fewer rows when ``tol`` stopped the fit early).
        steps: optimiser steps taken.
    """

    params: dict[str, Tensor]
    model: StateSpaceModel
    belief: GaussianBelief
    trace: Tensor
    steps: int

    @property
    def log_likelihood(self) -> Tensor:
        """Log-likelihood per series at the fitted parameters, ``(...)``."""
        return self.trace[-1]


def _adam(params: list[Tensor]) -> torch.optim.Optimizer:
    return torch.optim.Adam(params, lr=0.05)


def fit_likelihood(
    build_model: Callable[[dict[str, Tensor]], StateSpaceModel],
    params: Mapping[str, Tensor],
    filt: GaussianFilter,
    belief: GaussianBelief | Callable[[dict[str, Tensor]], GaussianBelief],
    ys: Tensor,
    us: Tensor | None = None,
    *,
    optimizer: torch.optim.Optimizer | Callable[[list[Tensor]], torch.optim.Optimizer] = _adam,
    steps: int = 100,
    k0: int = 0,
    tol: float | None = None,
) -> LikelihoodFit:
    """Maximise the filter's log-likelihood of ``ys`` over ``params``.

    Args:
        build_model: ``params -> StateSpaceModel``; use :func:`from_log_cholesky` for the noise
            factors (or any other differentiable map to valid values).
        params: ``{name: tensor}`` initial unconstrained values (float tensors).
        filt: the filter whose likelihood is maximised (any :class:`GaussianFilter`).
        belief: initial belief on ``x_{k0}``, or ``params -> GaussianBelief`` to learn it.
        ys: ``(T, ..., m)`` measurements (NaN: missing), the belief's batch dims after ``T``.
        us: controls as in :func:`~prognos_torch.filters.run`.
        optimizer: an optimiser instance over the tensors of ``params`` (they are updated in
            place), or a factory ``list[Tensor] -> Optimizer`` (e.g. ``torch.optim.LBFGS`` or
            ``lambda p: torch.optim.Adam(p, lr=0.05)``, the default) applied to copies.
            ``step(closure)`` is called, so closure-based optimisers such as LBFGS work.
        steps: number of optimiser steps.
        k0: index of the initial state (as in ``run``).
        tol: stop when the total log-likelihood changes by less than ``tol * (1 + |ll|)``
            between steps (``None``: always take ``steps`` steps).
    Returns:
        :class:`LikelihoodFit`. The minimised loss is ``-sum(log_likelihood) / T``.
    Raises:
        FloatingPointError: the log-likelihood became non-finite (lower the learning rate), or
            is at the starting parameters. With an optimiser instance, its tensors and its
            state are put back to the last iterate with a finite log-likelihood (also when
            another exception ends the fit); the exception's ``trace`` holds the
            log-likelihoods up to there (``(k, ...)``, or ``None``).
        ValueError: an optimiser instance does not hold every tensor of ``params``, or one
            of them does not require grad.
    """
    if not callable(build_model):
        raise TypeError("build_model must be a callable params -> StateSpaceModel")
    if not isinstance(params, Mapping) or not params:
        raise TypeError("params must be a non-empty mapping {name: tensor}")
    for name, p in params.items():
        if not isinstance(p, Tensor) or not p.is_floating_point():
            raise TypeError(f"params[{name!r}] must be a floating-point torch.Tensor")
    if not isinstance(filt, GaussianFilter):
        raise TypeError(f"filt must be a GaussianFilter (e.g. filters.sckf()), got {type(filt)}")
    if not isinstance(ys, Tensor) or ys.dim() < 2 or ys.shape[0] < 1:
        raise ValueError("ys must be a tensor of shape (T, ..., m) with T >= 1")
    if not is_int(steps) or steps < 0:
        raise ValueError(f"steps must be a non-negative int, got {steps!r}")
    if tol is not None and (not is_real(tol) or not tol >= 0):
        raise ValueError(f"tol must be a number >= 0 or None, got {tol!r}")

    if isinstance(optimizer, torch.optim.Optimizer):
        opt = optimizer
        leaves = dict(params)
        owned = {id(p) for g in opt.param_groups for p in g["params"]}
        missing = [n for n, p in leaves.items() if id(p) not in owned]
        if missing:
            raise ValueError(f"the optimizer does not hold params {missing}")
        # (the loss had no graph: torch's "element 0 of tensors does not require grad")
        frozen = [n for n, p in leaves.items() if not p.requires_grad]
        if frozen:
            raise ValueError(
                f"params {frozen} do not require grad, so the optimizer cannot fit them: pass "
                "leaf tensors with requires_grad=True (or an optimizer factory)"
            )
    elif callable(optimizer):
        leaves = {n: p.detach().clone().requires_grad_(True) for n, p in params.items()}
        opt = optimizer(list(leaves.values()))
        if not isinstance(opt, torch.optim.Optimizer):
            raise TypeError("optimizer(params) must return a torch.optim.Optimizer")
    else:
        raise TypeError("optimizer must be a torch.optim.Optimizer or a factory of one")

    T = ys.shape[0]

    def get_belief(p):
        b = belief(p) if callable(belief) else belief
        if not isinstance(b, GaussianBelief):
            raise TypeError("belief must be a GaussianBelief or params -> GaussianBelief")
        return b

    def where() -> str:
        if not trace:
            return "is non-finite at the starting parameters (check them and the model they build)"
        return (f"became non-finite after {len(trace)} steps (lower the learning rate or "
                "start closer)")  # fmt: skip

    def get_model(p) -> StateSpaceModel:
        model = build_model(p)
        if not isinstance(model, StateSpaceModel):
            raise TypeError(
                f"build_model must return a StateSpaceModel, got {type(model).__name__}"
            )
        return model

    def loglik(p) -> Tensor:
        try:
            return run(filt, get_model(p), get_belief(p), ys, us, k0=k0).log_likelihood
        except NonFiniteNoiseError as exc:  # parameters whose model noise overflowed
            raise FloatingPointError(f"the log-likelihood {where()}: {exc}") from None

    trace: list[Tensor] = []
    state: dict = {}

    def closure():
        opt.zero_grad()
        ll = loglik(leaves)
        if not bool(torch.isfinite(ll).all()):
            raise FloatingPointError(f"the log-likelihood {where()}")
        if "ll" not in state:  # the first evaluation of a step is at its starting point
            state["ll"] = ll.detach()
        loss = -ll.sum() / T
        loss.backward()
        return loss

    # an optimiser instance is the caller's: its state (Adam's moments, LBFGS's history) goes
    # back with its tensors, or it would hold the steps that led to the failure
    keep_opt = isinstance(optimizer, torch.optim.Optimizer)

    def restore(params_at, opt_at) -> None:
        if params_at is not None:
            with torch.no_grad():
                for n, p in leaves.items():
                    p.copy_(params_at[n])
        if opt_at is not None:
            opt.load_state_dict(opt_at)

    taken, prev, prev_opt = 0, None, None
    for _ in range(steps):
        state.clear()
        start = {n: p.detach().clone() for n, p in leaves.items()}
        start_opt = copy.deepcopy(opt.state_dict()) if keep_opt else None
        try:
            opt.step(closure)
        except Exception as exc:
            # the caller's tensors (an optimiser instance) go back to the last finite iterate
            # (the start of this step, or of the one before when its start failed), also when
            # the model failed otherwise (e.g. a Cholesky in build_model) part-way through
            if "ll" in state:
                restore(start, start_opt)
            elif prev is not None:
                restore(prev, prev_opt)
            if isinstance(exc, FloatingPointError):
                done = trace + ([state["ll"]] if "ll" in state else [])
                exc.trace = torch.stack(done) if done else None
            raise
        prev, prev_opt = start, start_opt
        trace.append(state["ll"])
        taken += 1
        if tol is not None and len(trace) >= 2:
            a, b = trace[-2].sum(), trace[-1].sum()
            if bool((a - b).abs() <= tol * (1.0 + b.abs())):
                break
    with torch.no_grad():
        final = {n: p.detach().clone() for n, p in leaves.items()}
        try:
            ll = loglik(final)
            if not bool(torch.isfinite(ll).all()):
                raise FloatingPointError(f"the log-likelihood {where()}")
        except Exception as exc:
            # the last step diverged: as inside the loop, the caller's tensors go back to the
            # start of that step (the last finite iterate, trace[-1])
            if prev is not None:
                restore(prev, prev_opt)
            if isinstance(exc, FloatingPointError):
                exc.trace = torch.stack(trace) if trace else None
            raise
        trace.append(ll)
        model = get_model(final)
        b0 = get_belief(final)
    return LikelihoodFit(final, model, b0, torch.stack(trace), taken)
