"""Expectation-maximisation for linear-Gaussian state-space models, in square-root form.

Model (batch dims ``...`` first; every series has its own parameters):

    x_k = A x_{k-1} + w_k,  w_k ~ N(0, Q);   y_k = C x_k + v_k,  v_k ~ N(0, R);
    x_0 ~ N(mu_0, S_0 S_0^T).

E-step: the square-root RTS smoother (:func:`~prognos_torch.filters.smooth` with the EKF, exact
here) gives ``x_{t|T}``, ``S_{t|T}``, the gains ``G_{t-1}`` and the conditional factors
``S^c_{t-1}`` (``Cov(x_{t-1} | x_t, y_{1:t-1})``); the lag-one covariance is
``P_{t,t-1|T} = P_{t|T} G_{t-1}^T``. M-step (Shumway and Stoffer 1982; Ghahramani and Hinton
1996), each covariance as a square root of a sum of outer products:

    A = S_10 S_00^{-1},  S_00 = sum_t E[x_{t-1} x_{t-1}^T] = Tria([S_{t-1|T}, x_{t-1|T}]_t)^2,
                         S_10 = sum_t E[x_t x_{t-1}^T]
    S_Q = Tria([(I - A G_{t-1}) S_{t|T}, A S^c_{t-1}, x_{t|T} - A x_{t-1|T}]_t) / sqrt(T)
    C = S_yx S_xx^{-1} over the observed steps, S_R = Tria([y_t - C x_{t|T}, C S_{t|T}]_t) / sqrt(N)
    mu_0 = x_{0|T},  S_0 = S_{0|T}

(``x_t - A x_{t-1} = (I - A G_{t-1}) x_t - A e`` with ``e`` the conditional residual, which
gives the ``S_Q`` columns.) The solves with ``S_00`` and ``S_xx`` use their square roots; no
inverse is formed. The log-likelihood of each iterate is the filter's; EM never decreases it.

Missing data: rows that are NaN throughout are skipped in the ``C`` and ``R`` sums. A
partially observed row would need the conditional moments of its missing components and is
refused when ``C`` or ``R`` is learned.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass

import torch
from torch import Tensor

from ..core.belief import GaussianBelief
from ..core.linalg import cho_solve_right, tria
from ..core.model import StateSpaceModel
from ..core.validation import check_real_tensor, is_int, is_real
from ..filters.smooth import smooth
from ..filters.variants import ekf

__all__ = ["EMFit", "em_linear_gaussian", "linear_model"]

_LEARNABLE = ("A", "C", "Q", "R", "init")


def linear_model(A: Tensor, C: Tensor, chol_Q: Tensor, chol_R: Tensor) -> StateSpaceModel:
    """``x_k = A x_{k-1} + w``, ``y_k = C x_k + v`` (analytic Jacobians, no ``vmap``).

    ``A`` ``(n, n)`` or ``(*batch, n, n)`` and ``C`` ``(m, n)`` or ``(*batch, m, n)``: one
    matrix for every series, or one per series with *all* the belief's batch dims ``batch``
    (dims of size 1 broadcast), as :class:`EMFit` returns them. Sigma points and particles
    come after the series' dims (``(*batch, L, n)``), and per-series matrices are applied to
    the points of their own series (right-aligned broadcasting would pair them with the
    points).

    Raises:
        TypeError: ``A`` or ``C`` is not a tensor.
        ValueError: ``A`` is not square or ``C`` has another ``n``; at a filter call, the
            states' leading dims do not match the matrices' batch dims (per-series matrices
            with fewer dims than the belief's, or a belief dim of size 1 against several).
    """
    for M, name in ((A, "A"), (C, "C")):
        if not isinstance(M, Tensor):
            raise TypeError(f"{name} must be a torch.Tensor, got {type(M).__name__}")
    n = A.shape[-1] if A.dim() >= 2 else -1
    if A.dim() < 2 or A.shape[-2] != n or C.dim() < 2 or C.shape[-1] != n:
        raise ValueError(
            f"A must have shape (..., n, n) and C (..., m, n) with the same n, got A "
            f"{tuple(A.shape)} and C {tuple(C.shape)}"
        )
    m = C.shape[-2]

    def aligned(M: Tensor, x: Tensor, name: str) -> Tensor:
        batch = M.shape[:-2]
        extra = x.dim() - 1 - len(batch)  # the point dims after the series' dims
        if not batch:
            return M
        # (a matrix dim of size 1 broadcasts over the states'; a states' dim of size 1 does
        # not take the matrices' size: one series would become several)
        if extra < 0 or any(a != b and a != 1 for a, b in zip(batch, x.shape)):
            raise ValueError(
                f"{name} has batch dims {tuple(batch)}, the states {tuple(x.shape[:-1])}: "
                f"per-series matrices carry all the belief's batch dims, first"
            )
        return M.reshape(*batch, *([1] * extra), *M.shape[-2:])

    def mv(M, x, name):
        return (aligned(M, x, name) @ x.unsqueeze(-1)).squeeze(-1)

    return StateSpaceModel(
        f=lambda x, u, k: mv(A, x, "A"),
        h=lambda x, u, k: mv(C, x, "C"),
        state_dim=n,
        obs_dim=m,
        chol_Q=chol_Q,
        chol_R=chol_R,
        batched=True,
        jac_f=lambda x, u, k: aligned(A, x, "A").expand(*x.shape[:-1], n, n),
        jac_h=lambda x, u, k: aligned(C, x, "C").expand(*x.shape[:-1], m, n),
    )


@dataclass(frozen=True)
class EMFit:
    """Result of :func:`em_linear_gaussian` (every tensor with the series' batch dims).

    Attributes:
        A: ``(..., n, n)``; C: ``(..., m, n)``; chol_Q: ``(..., n, n)``; chol_R: ``(..., m, m)``.
        init: the initial belief ``N(mu_0, S_0 S_0^T)``.
        trace: ``(iterations + 1, ...)`` log-likelihood of the starting point and of each
            iterate (fewer rows when ``tol`` stopped early).
        iterations: EM iterations taken.
    """

    A: Tensor
    C: Tensor
    chol_Q: Tensor
    chol_R: Tensor
    init: GaussianBelief
    trace: Tensor
    iterations: int

    @property
    def model(self) -> StateSpaceModel:
        return linear_model(self.A, self.C, self.chol_Q, self.chol_R)

    @property
    def log_likelihood(self) -> Tensor:
        return self.trace[-1]


def _cols(x: Tensor) -> Tensor:
    """``(T, ..., r, c)`` -> ``(..., r, T c)``: the time steps' columns side by side."""
    x = x.movedim(0, -2)  # (..., r, T, c)
    return x.reshape(*x.shape[:-2], x.shape[-2] * x.shape[-1])


def _check(x, name: str, shape: tuple, batch: tuple) -> Tensor:
    want = f"{shape} or {batch + shape}"
    if not isinstance(x, Tensor):
        raise TypeError(f"{name} must be a torch.Tensor of shape {want}, got {type(x).__name__}")
    check_real_tensor(x, name)  # (the cast to the belief's dtype read bool and complex)
    if tuple(x.shape) not in (shape, batch + shape):
        raise ValueError(f"{name} must have shape {want}, got {tuple(x.shape)}")
    return x


def em_linear_gaussian(
    A: Tensor,
    C: Tensor,
    chol_Q: Tensor,
    chol_R: Tensor,
    init: GaussianBelief,
    ys: Tensor,
    *,
    iterations: int = 50,
    learn: Iterable[str] = _LEARNABLE,
    tol: float | None = None,
) -> EMFit:
    """EM estimates of ``A``, ``C``, ``Q``, ``R`` and the initial belief (module docstring).

    Args:
        A, C, chol_Q, chol_R: starting values ``(n, n)``, ``(m, n)``, ``(n, n)``, ``(m, m)``, or
            with the batch dims of ``init`` first (one model per series).
        init: starting initial belief on ``x_0``, batch dims ``...``.
        ys: ``(T, ..., m)`` measurements (rows NaN throughout: missing).
        iterations: number of EM iterations.
        learn: which of ``"A"``, ``"C"``, ``"Q"``, ``"R"``, ``"init"`` to update (others fixed).
        tol: stop when no series' log-likelihood rises by more than ``tol * (1 + |ll|)``.
    Returns:
        :class:`EMFit` with the parameters broadcast to the batch dims (new tensors, never
        views of the arguments).
    """
    if isinstance(learn, str) or not isinstance(learn, Iterable):  # ("init": not 4 letters)
        raise TypeError(f"learn must be a collection of names from {_LEARNABLE}, got {learn!r}")
    learn = tuple(learn)
    bad = [x for x in learn if x not in _LEARNABLE]
    if bad:
        raise ValueError(f"learn may contain {_LEARNABLE}, got {bad}")
    if tol is not None and (not is_real(tol) or not tol >= 0):
        raise ValueError(f"tol must be a number >= 0 or None, got {tol!r}")
    if not isinstance(init, GaussianBelief):
        raise TypeError("init must be a GaussianBelief on x_0")
    init.validate("init")
    n = init.dim
    bs = tuple(init.batch_shape)
    _check(A, "A", (n, n), bs)
    if not isinstance(C, Tensor):
        raise TypeError(f"C must be a torch.Tensor of shape (m, {n}), got {type(C).__name__}")
    if C.dim() < 2 or C.shape[-1] != n:
        raise ValueError(
            f"C must be a tensor of shape (m, {n}) or (..., m, {n}), got "
            f"{tuple(getattr(C, 'shape', ()))}"
        )
    m = C.shape[-2]
    _check(C, "C", (m, n), bs)
    _check(chol_Q, "chol_Q", (n, n), bs)
    _check(chol_R, "chol_R", (m, m), bs)
    for x, name in ((A, "A"), (C, "C")):  # (chol_Q and chol_R: the model's own check)
        if not bool(torch.isfinite(x).all()):
            raise ValueError(f"{name} contains non-finite values (NaN or inf)")
    if not isinstance(ys, Tensor):
        raise TypeError(f"ys must be a torch.Tensor, got {type(ys).__name__}")
    if tuple(ys.shape[1:]) != bs + (m,) or ys.shape[0] < 1:
        want = ", ".join(map(str, bs + (m,)))
        raise ValueError(f"ys must have shape (T, {want}), got {tuple(getattr(ys, 'shape', ()))}")
    if not is_int(iterations) or iterations < 0:
        raise ValueError(f"iterations must be a non-negative int, got {iterations!r}")
    dt = init.mean.dtype
    nan = torch.isnan(ys)
    observed = ~nan.all(-1)  # (T, ...)
    if ("C" in learn or "R" in learn) and bool((nan.any(-1) & observed).any()):
        raise ValueError(
            "ys has partially observed rows; EM of C and R supports rows that are observed "
            "or NaN throughout (or fix C and R with learn=...)"
        )
    T = ys.shape[0]
    n_obs = observed.sum(0).to(dt)  # (...)
    if ("C" in learn or "R" in learn) and bool((n_obs == 0).any()):
        raise ValueError("a series has no observed row: C and R cannot be estimated")
    A = A.to(dt).expand(*bs, n, n)
    C = C.to(dt).expand(*bs, m, n)
    SQ = chol_Q.to(dt).expand(*bs, n, n)
    SR = chol_R.to(dt).expand(*bs, m, m)
    b0 = init
    obs_f = observed.to(dt)[..., None, None]  # (T, ..., 1, 1)
    y0 = torch.where(nan, torch.zeros_like(ys), ys).to(dt)

    filt = ekf()
    trace = []
    it = 0
    for it in range(iterations + 1):
        sm = smooth(filt, linear_model(A, C, SQ, SR), b0, ys)
        trace.append(sm.log_likelihood)
        if tol is not None and len(trace) >= 2:
            rise = trace[-1] - trace[-2]
            if bool((rise <= tol * (1.0 + trace[-1].abs())).all()):
                break
        if it == iterations:
            break
        ms = torch.cat([sm.initial.mean.unsqueeze(0), sm.means])  # (T + 1, ..., n)
        Ss = torch.cat([sm.initial.chol.unsqueeze(0), sm.chols])
        x1, x0 = ms[1:, ..., None], ms[:-1, ..., None]  # (T, ..., n, 1)
        if "A" in learn:
            S10 = (sm.cross_covs + x1 @ x0.mT).sum(0)
            R00 = tria(_cols(torch.cat([Ss[:-1], x0], dim=-1)))  # S_00 = R00 R00^T
            A_new = cho_solve_right(S10, R00)
        else:
            A_new = A
        if "Q" in learn:
            eye = torch.eye(n, dtype=dt, device=ys.device)
            cols = [
                (eye - A_new @ sm.gains) @ Ss[1:],
                A_new @ sm.cond_chols,
                x1 - A_new @ x0,
            ]
            SQ = tria(_cols(torch.cat(cols, dim=-1))) / math.sqrt(T)
        if "C" in learn:
            Syx = (obs_f * (y0[..., None] @ x1.mT)).sum(0)
            Rxx = tria(_cols(obs_f * torch.cat([Ss[1:], x1], dim=-1)))
            C_new = cho_solve_right(Syx, Rxx)
        else:
            C_new = C
        if "R" in learn:
            cols = [y0[..., None] - C_new @ x1, C_new @ Ss[1:]]
            SR = tria(_cols(obs_f * torch.cat(cols, dim=-1))) / n_obs.sqrt()[..., None, None]
        if "init" in learn:
            b0 = GaussianBelief(sm.initial.mean, sm.initial.chol)
        A, C = A_new, C_new
    # copies: a parameter that was not learned (or iterations=0) is otherwise the caller's
    # tensor or a view of it, which an in-place edit of the result would change
    b0 = GaussianBelief(b0.mean.clone(), b0.chol.clone())
    return EMFit(A.clone(), C.clone(), SQ.clone(), SR.clone(), b0, torch.stack(trace), it)
