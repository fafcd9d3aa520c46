"""Rauch-Tung-Striebel smoothers on the filter engine, in square-root form.

One backward pass serves every Gaussian filter configuration: the extended RTS smoother (EKS,
on :func:`~prognos_torch.filters.ekf`), the unscented and cubature RTS smoothers (URTSS /
square-root cubature smoother, on ``ukf``, ``srukf``, ``ckf``, ``sckf``) and the fixed-lag
smoother. The forward pass is :func:`~prognos_torch.filters.run` (missing and partially
observed measurements are handled there); each step's :class:`~prognos_torch.filters.Spread`
holds the paired deviation columns ``dx`` (points at ``k-1``) and ``df`` (their images under
``f``), from which (Sarkka, *Bayesian Filtering and Smoothing*, Alg. 8.2, 9.3, 10.3)

    C_k = dx df^T                               (cross-covariance of the prediction)
    G_{k-1} = C_k P_{k|k-1}^{-1}                (two triangular solves with S_{k|k-1})
    m_{k-1|T} = m_{k-1|k-1} + G_{k-1} (m_{k|T} - m_{k|k-1})
    P_{k-1|T} = P_{k-1|k-1} + G_{k-1} (P_{k|T} - P_{k|k-1}) G_{k-1}^T.

Square-root form: with ``P_{k|k-1} = lambda df df^T + S_Q S_Q^T`` (``lambda``: the filter's
fading factor, 1 without strong tracking), the identity
``P_{k-1|k-1} - G C^T = (dx - G df)(dx - G df)^T + G (S_Q S_Q^T + (lambda - 1) df df^T) G^T``
holds for any signed weights, so the conditional factor is

    S_c = Tria([dx - G df, G S_Q, sqrt(lambda - 1) G df])    (negative-weight columns downdated)
    S_{k-1|T} = Tria([S_c, G S_{k|T}])

(the square-root RTS smoother of Park and Kailath 1995; Sarkka's square-root URTSS). No
covariance is formed and nothing is inverted. ``filter.sqrt=False`` runs the same recursion on
full covariances (the textbook form, used to test that both agree). The lag-one smoothed
cross-covariance ``Cov(x_k, x_{k-1} | y_{1:T}) = P_{k|T} G_{k-1}^T`` (Shumway and Stoffer's
``P_{k,k-1|T}``) is returned for EM.

Strong tracking is smoothed as the model whose process noise the fading factor inflated
(``Q + (lambda - 1) df df^T``, uncorrelated with ``x_{k-1}``); noise estimators contribute the
``Q_k`` used at each step. The robust bound of paper 004 replaces the prior by a bound that is
not a predictive covariance and is refused.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from ..core.belief import GaussianBelief
from ..core.linalg import cho_solve_right, chol_downdate, safe_cholesky, symmetrize, tria
from ..core.model import StateSpaceModel
from ..core.validation import check_flag, is_int
from .gaussian import FilterState, GaussianFilter
from .run import Trajectory, run

__all__ = ["Smoothed", "smooth", "smooth_trajectory"]


@dataclass(frozen=True)
class Smoothed:
    """Smoother output over ``T`` steps, shaped like :class:`~prognos_torch.filters.Trajectory`.

    Row ``t`` refers to ``x_k`` with ``k = k0 + t + 1``; ``e`` is the last measurement each
    estimate conditions on (``T`` for the RTS smoother, ``min(k + lag, T)`` fixed-lag).

    Attributes:
        means: ``(T, ..., n)`` smoothed means ``x_{k|e}``.
        chols: ``(T, ..., n, n)`` their square roots.
        cross_covs: ``(T, ..., n, n)`` ``Cov(x_k, x_{k-1} | y_{1:e})`` (row 0 pairs ``x_{k0+1}``
            with the initial state).
        gains: ``(T, ..., n, n)`` smoother gains ``G_{k-1}`` (``x_{k-1}`` on ``x_k``).
        cond_chols: ``(T, ..., n, n)`` square roots ``S^c_{k-1}`` of
            ``Cov(x_{k-1} | x_k, y_{1:k-1}) = P_{k-1|k-1} - G_{k-1} C_k^T`` (square-root
            algebra only, else ``None``): ``x_{k-1} = b + G_{k-1} x_k + e``, ``e ~ N(0, S^c S^c^T)``.
        initial: smoothed belief on the initial state ``x_{k0}``.
        filtered: the forward :class:`Trajectory` (filtered moments, log-likelihood).
        lag: the fixed lag, or ``None`` for the RTS smoother.
    """

    means: Tensor
    chols: Tensor
    cross_covs: Tensor
    gains: Tensor
    cond_chols: Tensor | None
    initial: GaussianBelief
    filtered: Trajectory
    lag: int | None = None

    @property
    def covs(self) -> Tensor:
        return self.chols @ self.chols.mT

    @property
    def log_likelihood(self) -> Tensor:
        """The filter's log-likelihood ``log p(y_{1:T})`` ``(...)``."""
        return self.filtered.log_likelihood


def _mv(A: Tensor, x: Tensor) -> Tensor:
    return (A @ x.unsqueeze(-1)).squeeze(-1)


def _stack_opt(xs: list) -> Tensor | None:
    return None if xs[0] is None else torch.stack(xs)


def _check_lag(lag) -> int | None:
    """``lag`` as an ``int`` (any integral number, e.g. ``numpy.int64``), or ``None``."""
    if lag is not None and (not is_int(lag) or lag < 0):
        raise ValueError(f"lag must be None or a non-negative int, got {lag!r}")
    return None if lag is None else int(lag)


def smooth(
    filt: GaussianFilter,
    model: StateSpaceModel,
    init: GaussianBelief | FilterState,
    ys: Tensor,
    us: Tensor | None = None,
    *,
    k0: int = 0,
    lag: int | None = None,
) -> Smoothed:
    """Smooth the measurements ``ys`` ``(T, ..., m)`` (NaN: missing) with ``filt``'s model of the
    time update (Taylor: EKS; sigma points: unscented/cubature RTS smoother).

    Arguments as in :func:`~prognos_torch.filters.run`. ``lag=None`` gives the RTS smoother
    ``x_{k|T}``; ``lag=L >= 0`` the fixed-lag smoother ``x_{k|min(k+L, T)}`` (``L = 0``: the
    filter; ``L >= T``: RTS), computed from one forward run in ``L`` vectorised backward steps.
    Square-root algebra when ``filt.sqrt`` (see the module docstring), else full covariances.
    Differentiable (autograd flows through the forward and backward passes).
    """
    if not isinstance(filt, GaussianFilter):
        raise TypeError(
            f"filt must be a GaussianFilter (e.g. filters.ekf(), filters.sckf()), got {type(filt)}"
        )
    if filt.robust is not None:
        raise ValueError(
            "the robust bound replaces the prior by a bound, not a predictive covariance: "
            "smooth with the filter without robust="
        )
    lag = _check_lag(lag)
    tr = run(filt, model, init, ys, us, k0=k0, keep_steps=True)
    b0 = init.belief if isinstance(init, FilterState) else init
    return smooth_trajectory(tr, b0, sqrt=filt.sqrt, lag=lag)


def smooth_trajectory(
    tr: Trajectory,
    init: GaussianBelief | FilterState,
    *,
    sqrt: bool = True,
    lag: int | None = None,
) -> Smoothed:
    """The backward pass of :func:`smooth` on a forward run ``run(..., keep_steps=True)``
    started from ``init`` (the belief on ``x_{k0}``, or the :class:`FilterState` the run
    resumed from); ``sqrt``: square-root or full algebra.

    Raises:
        ValueError: ``tr`` is not such a run, or a robust filter's (paper 004's bound is no
            predictive covariance), or ``init`` is not shaped and typed as its states.
    """
    if not isinstance(tr, Trajectory) or tr.steps is None:
        raise ValueError("tr must be a Trajectory from run(..., keep_steps=True)")
    if any(s.spread is None for s in tr.steps):
        raise ValueError(
            "tr is a robust filter's run: the robust bound replaces the prior by a bound, not a "
            "predictive covariance; smooth with the filter without robust="
        )
    if isinstance(init, FilterState):
        init = init.belief
    if not isinstance(init, GaussianBelief):
        raise TypeError(
            f"init must be the GaussianBelief (or FilterState) the run started from, got "
            f"{type(init).__name__}"
        )
    want = tuple(tr.means.shape[1:])
    if tuple(init.mean.shape) != want or tuple(init.chol.shape) != tuple(tr.chols.shape[1:]):
        raise ValueError(
            f"init must have mean {want} and chol {tuple(tr.chols.shape[1:])} (the run's "
            f"states), got {tuple(init.mean.shape)} and {tuple(init.chol.shape)}"
        )
    if init.mean.dtype != tr.means.dtype or init.chol.dtype != tr.chols.dtype:
        raise ValueError(f"init must have the run's dtype {tr.means.dtype}, got {init.mean.dtype}")
    sqrt = check_flag(sqrt, "sqrt")  # (a NumPy bool as GaussianFilter(sqrt=) takes it)
    lag = _check_lag(lag)
    b0 = init
    steps = tr.steps
    T, n = tr.means.shape[0], tr.means.shape[-1]
    bs = tr.means.shape[1:-1]

    fm = torch.cat([b0.mean.unsqueeze(0), tr.means])  # x_{t|t}, t = 0..T
    fS = torch.cat([b0.chol.unsqueeze(0), tr.chols])
    dx_pos = torch.stack([s.spread.dx_pos for s in steps])  # (T, ..., n, Lp)
    df_pos = torch.stack([s.spread.df_pos for s in steps])
    dx_neg = _stack_opt([s.spread.dx_neg for s in steps])
    df_neg = _stack_opt([s.spread.df_neg for s in steps])
    SQ = torch.stack([s.noise.chol_Q.expand(*bs, n, n) for s in steps])

    C = dx_pos @ df_pos.mT  # Cov(x_{t}, x_{t+1} | y_{1:t})
    if dx_neg is not None:
        C = C - dx_neg @ df_neg.mT
    G = cho_solve_right(C, tr.pred_chols)  # (T, ..., n, n)
    bad = ~torch.isfinite(G).flatten(1).all(-1)
    if bool(bad.any()):
        fin = [torch.isfinite(x).flatten(1).all(-1) for x in (fm[1:], fS[1:], C)]
        nonfinite = ~(fin[0] & fin[1] & fin[2])
        if bool(nonfinite.any()):  # (no singular covariance: the run itself holds NaN or inf)
            t = int(nonfinite.nonzero()[0, 0])
            raise ValueError(
                f"the filter's run is non-finite (NaN or inf) from step {t + 1} on: check the "
                "model's f and h and the parameters they use (a NaN there), and the belief"
            )
        t = int(bad.nonzero()[0, 0])
        raise ValueError(
            f"the predicted covariance P_{{k|k-1}} of step {t + 1} is singular (its factor "
            "has a zero on the diagonal: no process noise on a direction the transition "
            "keeps, e.g. chol_Q = 0 with a singular A), so the smoother gain C P^-1 does not "
            "exist; give every state some process noise (chol_Q with a positive diagonal)"
        )
    b = fm[:-1] - _mv(G, tr.pred_means)
    lam1 = None
    if bool((tr.fading_factors != 1.0).any()):
        lam1 = (tr.fading_factors - 1.0).clamp_min(0.0).sqrt()[..., None, None]
    if sqrt:
        cols = [dx_pos - G @ df_pos, G @ SQ]
        neg = [] if dx_neg is None else [dx_neg - G @ df_neg]
        if lam1 is not None:
            cols.append(lam1 * (G @ df_pos))
            if df_neg is not None:
                neg.append(lam1 * (G @ df_neg))
        Sc = tria(torch.cat(cols, dim=-1))
        if neg:
            Sc = chol_downdate(Sc, torch.cat(neg, dim=-1))
        fX = fS
    else:  # textbook form: P_{t|t} - G C^T
        Sc = symmetrize(fS[:-1] @ fS[:-1].mT - G @ C.mT)
        fX = fS @ fS.mT

    def back(j: Tensor | int, m: Tensor, X: Tensor) -> tuple[Tensor, Tensor]:
        Gj = G[j]
        m = b[j] + _mv(Gj, m)
        if sqrt:
            return m, tria(torch.cat([Sc[j], Gj @ X], dim=-1))
        return m, symmetrize(Sc[j] + Gj @ X @ Gj.mT)

    if lag is None or lag >= T:
        ms, Xs = [fm[T]], [fX[T]]
        for t in range(T - 1, -1, -1):
            m, X = back(t, ms[-1], Xs[-1])
            ms.append(m)
            Xs.append(X)
        m_s, X_s = torch.stack(ms[::-1]), torch.stack(Xs[::-1])
    else:
        # target t = 0..T ends at e(t) = min(t + lag, T); after s backward steps the targets
        # t <= T - s are still moving (index e(t) - s), the others have arrived
        idx = torch.arange(T + 1, device=fm.device)
        e = (idx + lag).clamp(max=T)
        m_s, X_s = fm[e], fX[e]
        for s in range(1, lag + 1):
            a = T - s + 1
            m, X = back(e[:a] - s, m_s[:a], X_s[:a])
            m_s = torch.cat([m, m_s[a:]])
            X_s = torch.cat([X, X_s[a:]])
    chols = X_s if sqrt else safe_cholesky(X_s)
    P1 = chols[1:] @ chols[1:].mT
    cross = P1 @ G.mT  # Cov(x_{t+1}, x_t | y_{1:e}) = P_{t+1|e} G_t^T
    return Smoothed(
        means=m_s[1:],
        chols=chols[1:],
        cross_covs=cross,
        gains=G,
        cond_chols=Sc if sqrt else None,
        initial=GaussianBelief(m_s[0], chols[0]),
        filtered=tr,
        lag=lag,
    )
