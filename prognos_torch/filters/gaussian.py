"""One square-root predict/update engine for every Gaussian filter of the library.

EKF, UKF, SRUKF, CKF, SCKF, their strong-tracking versions (STEKF, STUKF, STSCKF), the
noise-adaptive ImSRUKF and the robust/adaptive RUKF/ARUKF are *configurations* of
:class:`GaussianFilter`: a moment rule (Taylor linearisation or a sigma-point rule), a covariance
algebra (square-root or full), and optional adaptation pieces (fading factor, noise estimator,
robust bound). There is one step function; nothing is copied per variant. The configurations by
name live in :mod:`prognos_torch.filters.variants`. The records and the pure blocks the step is
built from (the sigma-point rule, the measurement moments, the innovation statistics) live in
:mod:`prognos_torch.filters._blocks` and are re-exported here; the trace-aware helpers (no host
sync under ``torch.compile``, the deferred fallbacks) stay with the engine.

Step ``k`` (model convention of :mod:`prognos_torch.core.model`):

1. Propagate the posterior at ``k-1`` through ``f``: predicted mean ``x_pred`` and the
   "spread" factor ``A`` with ``A A^T = sum_i W_i (gamma_i - x_pred)(gamma_i - x_pred)^T``
   (EKF: ``A = F S``; random walk: ``A = S``).
2. Prior square root ``S_pred = Tria([sqrt(lambda_k) A, S_Q])`` (paper 000 Eq. 25/36; paper 003
   Eq. 16-18), with ``lambda_k = 1`` unless a fading factor is configured. Negative sigma-point
   weights enter as Cholesky downdates (paper 003 Eq. 17).
3. Measurement moments under the prior: predicted measurement, ``P_xz``, innovation factor
   ``S_zz = Tria([Z, S_R])`` (paper 000 Eq. 40; paper 003 Eq. 22-24).
4. Gain ``K = (P_xz / S_zz^T) / S_zz`` by triangular solves (paper 000 Eq. 44), mean update, and
   the posterior square root ``cholupdate(S_pred, K S_zz, -1)`` (paper 003 Eq. 28-29;
   closed-form rank-one downdates, O(n^2 m), on large factors, ``S chol(I - W W^T)`` on small
   ones). When the sigma points are redrawn from the prior (or for the EKF) this equals the
   Joseph form ``Tria([chi - K Z, K S_R])`` of paper 000 Eq. 46, which is used instead where the
   downdate would lose precision (a very informative measurement), under autograd (tensors
   that require grad: a failed downdate's NaN would leak into the gradient) and with the robust
   bound of paper 004.
5. A noise estimator updates its statistics (paper 003 Eq. 40-46) from the spread the prior
   used, ``sqrt(lambda_k) A``: with a fading factor, ``Q`` is not credited with the inflation.

Missing data: NaN marks a missing measurement component. A vector that is NaN throughout is
*missing*: the step only predicts (the posterior equals the prior, the log-likelihood
contribution is 0, ``nis`` is NaN). A partially observed vector updates with its observed
components only, exactly: the rows of the missing components are removed from the measurement
moments and the noise factor, and a unit block keeps the innovation factor square, so the gain
has zero columns there and ``nis`` and the log-likelihood are those of the observed components.
Strong tracking (fading factor 1) and the noise estimators (estimates held) skip any step that is
not fully observed; the robust bound of paper 004 treats a partially observed vector as missing
(the posterior of such a step is the prediction, not the lemma form's bound).
"""

from __future__ import annotations

from contextlib import contextmanager
from dataclasses import dataclass, replace

import torch
from torch import Tensor

from ..adapt.noise import MovingWindow, SageHusa, UpdateContext
from ..adapt.robust import RobustBound
from ..adapt.strong_tracking import StrongTracking, fading_factor
from ..core.belief import GaussianBelief, check_belief
from ..core.linalg import (
    cho_solve_right,
    chol_downdate,
    chol_downdate_ex,
    mm,
    safe_cholesky,
    symmetrize,
    tria,
)
from ..core.model import Noise, StateSpaceModel
from ..core.validation import check_control, check_flag, check_measurement, is_real
from ..quadrature import SigmaPoints
from ._blocks import (
    FilterState,
    Spread,
    StepInfo,
    Taylor,
    _Moments,
    _observed_part,
    _Prior,
    _Propagation,
    _sigma_points,
    innovation_stats,  # noqa: F401  (re-exported: filters.run)
)

__all__ = [
    "Taylor",
    "GaussianFilter",
    "FilterState",
    "StepInfo",
    "Spread",
]

#: Smallest ``det(P_post) / det(P_pred)`` for which the posterior is taken from the Cholesky
#: downdate (``chol_downdate_ex``: rank-one steps on large factors, ``S chol(I - W W^T)`` on
#: small ones), as a power of the dtype's epsilon (float64: 1.3e-6, float32: 2.5e-3); below it
#: the Joseph-form QR (the downdate's rounding error grows like ``eps / ratio``).
_DOWNDATE_MIN_RATIO_EXP = 0.375


def _downdate_min_ratio(dtype: torch.dtype) -> float:
    return torch.finfo(dtype).eps ** _DOWNDATE_MIN_RATIO_EXP


def _no_sync() -> bool:
    """Whether the step avoids host synchronisations: while ``torch.compile`` traces it (a
    sync would break the graph). Fallbacks are then computed everywhere and selected with
    ``torch.where``; eager steps test a flag once and compute a fallback only where needed.
    Both select the same values."""
    return torch.compiler.is_compiling()


#: While true, a step traced by ``torch.compile`` does not compute its fallbacks (the QR of a
#: failed Cholesky prior, the Joseph form of an imprecise downdate): it writes NaN into the
#: factor there instead, which every later step carries on. The caller (a compiled sequence
#: of steps, :meth:`KalmanOptimizer.steps`) tests the final state once and reruns the sequence
#: eagerly when it is not finite, so that the result is the eager one in every case.
_DEFER_FALLBACKS = False


@contextmanager
def deferred_fallbacks():
    """Inside, traced steps defer their fallbacks (see ``_DEFER_FALLBACKS``)."""
    global _DEFER_FALLBACKS
    old, _DEFER_FALLBACKS = _DEFER_FALLBACKS, True
    try:
        yield
    finally:
        _DEFER_FALLBACKS = old


def _deferred() -> bool:
    return _DEFER_FALLBACKS and torch.compiler.is_compiling()


def _check_measurement_traced(y, obs_dim: int, belief: GaussianBelief) -> tuple[Tensor, bool]:
    """:func:`check_measurement` for a step traced by ``torch.compile``: the same type, shape
    and device checks (static), and finiteness by ``torch._assert_async`` (no host sync; a
    ``RuntimeError``). A traced step takes fully observed measurements only: NaN (missing)
    is rejected there, and eager steps handle it."""
    if isinstance(y, Tensor) and tuple(y.shape) == tuple(belief.batch_shape) + (obs_dim,):
        if y.device == belief.mean.device:
            torch._assert_async(
                torch.isfinite(y).all(),
                "y must be finite in a compiled step (NaN-marked missing data: run eager)",
            )
            return y.to(belief.mean.dtype), False
    return check_measurement(y, obs_dim, belief.batch_shape, belief.mean)  # raises


_GRAM_CACHE: dict = {}


def _gram(S: Tensor) -> Tensor:
    """``S S^T``, remembered for the last few noise factors: a model's ``S_Q`` is usually
    the same tensor at every step (keyed by identity and version counter, so an in-place
    change is seen; inference tensors, which have no version counter, traced steps and
    factors that need a gradient are not cached: a cached product's graph would be spent by
    the first backward pass)."""
    if _no_sync() or S.is_inference() or S.requires_grad:
        return S @ S.transpose(-2, -1)
    key = (id(S), S._version)
    hit = _GRAM_CACHE.get(key)
    if hit is not None and hit[0] is S:
        return hit[1]
    with torch.inference_mode(False), torch.no_grad():  # an ordinary tensor in the cache
        G = S @ S.mT
    if len(_GRAM_CACHE) > 16:
        _GRAM_CACHE.clear()
    _GRAM_CACHE[key] = (S, G)
    return G


def _chol_prior(pos: Tensor, chol_Q: Tensor, diag_Q: Tensor | None = None) -> Tensor:
    """``chol(pos pos^T + S_Q S_Q^T)`` ``(..., n, n)``, with ``Tria([pos, S_Q])`` (paper 000
    Eq. 25) where the Cholesky fails. ``chol_Q``: ``(n, n)`` or batched like ``pos``;
    ``diag_Q``: ``Q``'s diagonal when ``Q`` is diagonal (:class:`Noise`), added to the
    diagonal of the product (batched or traced steps; a single eager step keeps the one
    ``addmm`` with the remembered ``Q``, fewer operations)."""
    if diag_Q is not None and (pos.dim() > 2 or _no_sync()):
        P = torch.matmul(pos, pos.mT)
        P.diagonal(dim1=-2, dim2=-1).add_(diag_Q)
    elif pos.dim() == 2:
        P = torch.addmm(_gram(chol_Q), pos, pos.mT)
    else:
        P = torch.matmul(pos, pos.mT).add_(_gram(chol_Q))
    L, info = torch.linalg.cholesky_ex(P)
    if not _no_sync() and not bool(info.any()):
        return L
    bad = info > 0
    if _deferred():
        return torch.where(bad[..., None, None], float("nan"), L)
    SQ = _bcast(chol_Q, pos.shape[:-2], chol_Q.shape[-2:])
    S = tria(torch.cat([pos, SQ], dim=-1))
    return torch.where(bad[..., None, None], S, L)


_CONSTANTS: dict = {}


def _constant(shape, dtype: torch.dtype, device: torch.device, value) -> Tensor:
    """A tensor of ``shape`` filled with ``value``, made once per shape, dtype and device:
    the step's flags without a missing measurement (all false) and ``lambda_k = 1`` without
    fading. The diagnostics of :class:`StepInfo` share it; they are read, not written."""
    if _no_sync():
        return torch.full(tuple(shape), value, dtype=dtype, device=device)
    key = (tuple(shape), dtype, device, value)
    t = _CONSTANTS.get(key)
    if t is None:
        with torch.inference_mode(False), torch.no_grad():
            t = torch.full(tuple(shape), value, dtype=dtype, device=device)
        if len(_CONSTANTS) > 64:
            _CONSTANTS.clear()
        _CONSTANTS[key] = t
    return t


def _check_state(state, method: str) -> None:
    if not isinstance(state, FilterState):
        raise TypeError(
            f"state must be a FilterState, got {type(state).__name__}; start from "
            f"state = filter.init(model, belief) (filter.{method})"
        )


def _bcast(x: Tensor, batch_shape: torch.Size, tail: tuple[int, ...]) -> Tensor:
    return x.expand(*batch_shape, *tail)


@dataclass(frozen=True)
class GaussianFilter:
    """A Gaussian filter configuration; see the module docstring.

    Attributes:
        rule: :class:`Taylor` (EKF) or a :class:`~prognos_torch.quadrature.SigmaPoints` rule.
        sqrt: square-root algebra (QR/Cholesky updates) if true, else full covariances.
        redraw: redraw sigma points from the prior before the measurement update (SRUKF of
            paper 003 and SCKF of paper 000 do, and so does filterpy's UKF: its ``predict()``
            ends by drawing new sigma points from the predicted ``(x, P)``); ``False`` reuses
            the propagated points ``f(chi)``, so ``Q`` does not enter ``P_xz`` and ``P_zz``.
        fading: ``None``, a constant fading factor ``>= 1``, or :class:`StrongTracking`.
        noise: ``None``, :class:`SageHusa` or :class:`MovingWindow`.
        robust: ``None`` or :class:`RobustBound` (paper 004 Theorem 1).
        prior: how the square-root algebra forms the prior factor when no sigma-point weight is
            negative: ``"qr"`` (``Tria([sqrt(lambda) A, S_Q])``, paper 000 Eq. 25) or
            ``"cholesky"`` (``chol(lambda A A^T + S_Q S_Q^T)``: one product and one Cholesky
            instead of a QR of ``(n, L + n)``, 1.3-1.4 times faster at n = 44; the QR is the
            fallback wherever the Cholesky fails). The optimiser face (random walk, where
            ``A = S``) uses ``"cholesky"``; both give the same factor up to rounding.
        posterior: the posterior square root of the square-root algebra where the measurement
            is a scalar and ``P_xz = S Z^T`` (the Taylor rule: ``Z = H S``): ``"downdate"``
            (the lower-triangular Cholesky downdate of paper 003 Eq. 28-29) or ``"potter"``
            (Potter's square root ``S - beta K Z`` with ``beta = 1 / (1 + s_R / s_zz)``,
            ``s_R^2`` the measurement noise: one O(n^2) outer product, NOT triangular; the
            same covariance ``P - K s_zz^2 K^T``). A non-triangular posterior is only right
            where the next step does not need a triangular one: the Taylor rule (any square
            root gives the same moments), whose next prior (``"cholesky"``, or the QR) is
            triangular again; the compiled optimiser pass uses it and re-triangularises the
            final factor (one QR). Vector measurements keep the downdate.
        name: label for tables.
    """

    rule: Taylor | SigmaPoints
    sqrt: bool = True
    redraw: bool = True
    fading: StrongTracking | float | None = None
    noise: SageHusa | MovingWindow | None = None
    robust: RobustBound | None = None
    prior: str = "qr"
    posterior: str = "downdate"
    name: str = ""

    def __post_init__(self):
        if not isinstance(self.rule, (Taylor, SigmaPoints)):
            raise TypeError(f"rule must be Taylor() or a SigmaPoints rule, got {type(self.rule)}")
        # (read by their truth value otherwise: sqrt="no" ran the square-root algebra)
        object.__setattr__(self, "sqrt", check_flag(self.sqrt, "sqrt"))
        object.__setattr__(self, "redraw", check_flag(self.redraw, "redraw"))
        if self.noise is not None and not isinstance(self.noise, (SageHusa, MovingWindow)):
            raise TypeError(
                "noise must be None, SageHusa or MovingWindow, got " + type(self.noise).__name__
            )
        if self.robust is not None and not isinstance(self.robust, RobustBound):
            raise TypeError(
                f"robust must be None or a RobustBound, got {type(self.robust).__name__}"
            )
        if is_real(self.fading):  # a constant factor (a NumPy scalar becomes a float)
            object.__setattr__(self, "fading", float(self.fading))
            if not 1.0 <= self.fading < float("inf"):
                raise ValueError(
                    f"a constant fading factor must be a finite number >= 1, got {self.fading}"
                )
        elif self.fading is not None and not isinstance(self.fading, StrongTracking):
            raise TypeError("fading must be None, a float >= 1 or StrongTracking")
        if self.robust is not None and not self.redraw:
            raise ValueError("the robust update needs redraw=True (Joseph-form posterior)")
        if self.fading is not None and not self.redraw and isinstance(self.rule, SigmaPoints):
            # the propagated points carry neither lambda nor Q: the gain would ignore the
            # fading factor, and strong tracking's H (Eq. 17) and M_k would be misread
            raise ValueError(
                "a fading factor needs redraw=True with a sigma-point rule (paper 000 Eq. 36-37: "
                "the points are drawn from the faded prior)"
            )
        if self.prior not in ("qr", "cholesky"):
            raise ValueError(f"prior must be 'qr' or 'cholesky', got {self.prior!r}")
        if self.posterior not in ("downdate", "potter"):
            raise ValueError(f"posterior must be 'downdate' or 'potter', got {self.posterior!r}")
        if self.posterior == "potter" and not (isinstance(self.rule, Taylor) and self.sqrt):
            raise ValueError(
                "posterior='potter' needs the Taylor rule and sqrt=True (its factor is not "
                "triangular: sigma points drawn from it would differ)"
            )

    # ------------------------------------------------------------------ state
    def init(self, model: StateSpaceModel, belief: GaussianBelief, k: int = 0) -> FilterState:
        """Initial :class:`FilterState` for ``belief`` (validated; ``k``: step of the noise used)."""
        check_belief(belief, model.state_dim)
        bs, like = belief.batch_shape, belief.mean
        fstate = None
        if isinstance(self.fading, StrongTracking):
            fstate = self.fading.init(bs, model.obs_dim, like.dtype, like.device)
        nstate = None
        if self.noise is not None:
            noise = model.checked_noise(k, belief.batch_shape, belief.mean)
            nstate = self.noise.init(noise, bs, model.state_dim, model.obs_dim, like)
        return FilterState(belief, fstate, nstate)

    # ------------------------------------------------------------------ noise
    def _noise(self, model, state: FilterState, k: int) -> Noise:
        """The noise of step ``k``: the estimator's statistics where it estimates them, the
        model's (per step, where callable) for the others and when it is frozen."""
        if state.noise is None:
            return model.checked_noise(k, state.belief.batch_shape, state.belief.mean)
        est = state.noise.noise()
        raw = {"q": model.q, "Q": model.chol_Q, "r": model.r, "R": model.chol_R}
        if not any(map(callable, raw.values())):  # constant noise: the estimator's holds it
            return est
        held = {"q", "Q", "r", "R"} - (set() if self.noise.frozen else set(self.noise.estimate))
        if not any(callable(raw[name]) for name in held):
            return est
        mod = model.checked_noise(k, state.belief.batch_shape, state.belief.mean)
        return Noise(
            mod.q if "q" in held else est.q,
            mod.chol_Q if "Q" in held else est.chol_Q,
            mod.r if "r" in held else est.r,
            mod.chol_R if "R" in held else est.chol_R,
            mod.diag_Q if "Q" in held else None,
        )

    # ------------------------------------------------------------------ stages
    def _propagate(self, model, belief: GaussianBelief, u, k: int, q) -> _Propagation:
        m, S = belief.mean, belief.chol
        if model.f is None:  # random walk: exact for every rule
            mean = m if q is None else m + q
            return _Propagation(mean, m, S, None, None, S)
        if isinstance(self.rule, Taylor):
            fx = model.transition(m, u, k)
            F = model.transition_jacobian(m, u, k)
            mean = fx if q is None else fx + q
            return _Propagation(mean, fx, mm(F, S), None, None, S)
        sig = _sigma_points(self.rule, model.state_dim, m)
        D = sig.deviations(S)
        X = m.unsqueeze(-2) + D  # (..., L, n), paper 000 Eq. 21
        uu = None if u is None else u.unsqueeze(-2)
        Y = model.transition(X, uu, k)  # Eq. 23 / paper 003 Eq. 14
        f_mean = sig.wm @ Y  # Eq. 24
        mean = f_mean if q is None else f_mean + q
        pos, neg = sig.columns(Y - f_mean.unsqueeze(-2))  # Eq. 26
        pts = Y if q is None else Y + q.unsqueeze(-2)
        return _Propagation(mean, f_mean, pos, neg, pts, D, sig)

    def _prior(
        self,
        prop: _Propagation,
        chol_Q: Tensor,
        lam: Tensor | None,
        update: bool = False,
        diag_Q: Tensor | None = None,
    ) -> _Prior:
        """Prior factor ``Tria([sqrt(lambda) A, S_Q])``; before an update with a robust bound of
        the ``"lemma"`` form, the bound ``P~`` of :class:`RobustBound` replaces it. ``diag_Q``:
        ``Q``'s diagonal when it is diagonal (:attr:`Noise.diag_Q`; the Cholesky prior)."""
        bs = prop.mean.shape[:-1]
        n = prop.mean.shape[-1]
        pos, neg = prop.pos, prop.neg
        if lam is not None:
            sl = lam.sqrt()[..., None, None]
            pos = sl * pos
            neg = None if neg is None else sl * neg
        if self.sqrt and self.prior == "cholesky" and neg is None:
            S = _chol_prior(pos, chol_Q, diag_Q)
            if update and self.robust is not None:
                S = self.robust.inflate(S)
            return _Prior(prop.mean, S, None)
        SQ = _bcast(chol_Q, bs, (n, n))
        if self.sqrt:
            S = tria(torch.cat([pos, SQ], dim=-1))  # paper 000 Eq. 25/36; paper 003 Eq. 16
            if neg is not None:
                S = chol_downdate(S, neg)  # paper 003 Eq. 17 (negative W_0)
            if update and self.robust is not None:
                S = self.robust.inflate(S)
            return _Prior(prop.mean, S, None)
        P = pos @ pos.mT + SQ @ SQ.mT
        if neg is not None:
            P = P - neg @ neg.mT
        P = symmetrize(P)
        if update and self.robust is not None and self.robust.form == "lemma":
            S = self.robust.inflate(safe_cholesky(P))
            return _Prior(prop.mean, S, S @ S.mT)
        return _Prior(prop.mean, safe_cholesky(P), P)

    def _moments(self, model, prior: _Prior, prop: _Propagation, u, k: int, r) -> _Moments:
        x, S = prior.mean, prior.chol
        if isinstance(self.rule, Taylor):
            hx = model.observe(x, u, k)
            H = model.observation_jacobian(x, u, k)
            z = hx if r is None else hx + r
            return _Moments(z, S, mm(H, S), None, None, True, H)
        sig = _sigma_points(self.rule, model.state_dim, x)
        if self.redraw or prop.points is None:
            D = sig.deviations(S)  # X - x exactly
            X = x.unsqueeze(-2) + D  # paper 000 Eq. 37
            joseph = True
        else:
            X = prop.points  # reuse the propagated points: Q is not in P_xz, P_zz
            D = X - x.unsqueeze(-2)
            joseph = False
        uu = None if u is None else u.unsqueeze(-2)
        eta = model.observe(X, uu, k)  # Eq. 38
        h_mean = sig.wm @ eta
        z = h_mean if r is None else h_mean + r  # Eq. 39
        dz_pos, dz_neg = sig.columns(eta - h_mean.unsqueeze(-2))  # Eq. 41
        dx_pos, dx_neg = sig.columns(D)  # Eq. 43
        return _Moments(z, dx_pos, dz_pos, dx_neg, dz_neg, joseph, None)

    def _robust_coef(self, mom: _Moments, chol_R: Tensor) -> tuple | None:
        """Coefficients of the robust bound (:meth:`RobustBound.coefficients`); with
        ``bound="optimised"`` the scale ``t`` minimising ``trace P_k`` of this step."""
        rob = self.robust
        if rob is None:
            return None
        if rob.bound != "optimised":
            return rob.coefficients()
        tr = (mom.dx_pos * mom.dx_pos).sum((-2, -1))  # trace of the prior (redraw=True)
        if mom.dx_neg is not None:
            tr = tr - (mom.dx_neg * mom.dx_neg).sum((-2, -1))
        RR = chol_R @ chol_R.mT
        RR = RR.expand(*mom.z.shape[:-1], *RR.shape[-2:])
        return rob.coefficients(rob.choose_t(tr, mom.pxz(), mom.pzz(), RR))

    def _innovation_chol(self, mom: _Moments, chol_R: Tensor, coef: tuple | None = None) -> Tensor:
        bs = mom.z.shape[:-1]
        mdim = mom.z.shape[-1]
        SR = _bcast(chol_R, bs, (mdim, chol_R.shape[-1]))  # (m, m), or (m, 2m) when masked
        if self.robust is not None:
            cM, cR = (coef or self._robust_coef(mom, chol_R))[:2]
            M = self.robust.M_matrix(mdim, SR.dtype, SR.device)
            cols = [mom.dz_pos, cM * _bcast(M, bs, M.shape), cR * SR]
        else:
            cols = [mom.dz_pos, SR]
        if self.sqrt:
            Szz = tria(torch.cat(cols, dim=-1))  # paper 000 Eq. 40; paper 003 Eq. 22
            if mom.dz_neg is not None:
                Szz = chol_downdate(Szz, mom.dz_neg)  # paper 003 Eq. 23
            return Szz
        P = sum(c @ c.mT for c in cols)
        if mom.dz_neg is not None:
            P = P - mom.dz_neg @ mom.dz_neg.mT
        return safe_cholesky(P)

    def _posterior_chol(
        self, prior: _Prior, mom: _Moments, K: Tensor, Szz: Tensor, chol_R, coef=None
    ) -> Tensor:
        rob = self.robust
        # under autograd the Joseph QR throughout: a failed downdate's NaN would reach the
        # gradient through the masked branch of torch.where
        grad = torch.is_grad_enabled() and (prior.chol.requires_grad or K.requires_grad)
        if self.sqrt and mom.joseph and rob is None and not grad:
            # The sigma points (or F S) reproduce the prior, so Eq. 46's Joseph form equals
            # P_pred - K S_zz S_zz^T K^T: the cholupdate of paper 003 Eq. 28-29 (m rank-one
            # steps on large factors, the dense S chol(I - W W^T) on small ones) instead of a
            # QR of (n, L + m). Where the downdate loses precision (determinant ratio below
            # _downdate_min_ratio: a very informative measurement) the Joseph QR is used.
            W = None
            cross = mom.dx_pos is prior.chol and mom.dx_neg is None
            if cross and self.posterior == "potter" and Szz.shape[-1] == 1:
                # P - v v^T = S (I - w w^T) S^T with w = Z^T / s_zz and v = S w = K s_zz;
                # I - w w^T = (I - beta w w^T)^2 with beta = 1 / (1 + sqrt(1 - |w|^2)), and
                # 1 - |w|^2 = s_R^2 / s_zz^2 (the determinant ratio): S - beta K Z
                ratio = chol_R.square().sum((-2, -1)) / Szz[..., 0, 0].square()
                beta = 1.0 / (1.0 + ratio.sqrt())
                S = prior.chol - (beta[..., None, None] * K) * mom.dz_pos
            else:
                if cross:
                    # P_xz = S Z^T (EKF: Z = H S), so W = S^{-1} K S_zz = Z^T S_zz^{-T}: no
                    # n x n triangular solve
                    if Szz.shape[-1] == 1:
                        W = mom.dz_pos.mT / Szz
                    else:
                        W = torch.linalg.solve_triangular(Szz, mom.dz_pos, upper=False).mT
                S, ratio = chol_downdate_ex(prior.chol, mm(K, Szz), W)
            ok = ratio > _downdate_min_ratio(ratio.dtype)
            if not _no_sync() and bool(ok.all()):
                return S
            if _deferred():
                return torch.where(ok[..., None, None], S, float("nan"))
        else:
            ok = None
        bs = prior.mean.shape[:-1]
        mdim = mom.z.shape[-1]
        SR = _bcast(chol_R, bs, (mdim, chol_R.shape[-1]))
        c, cK = (1.0, None) if rob is None else (coef or rob.coefficients())[2:]
        if not self.sqrt:
            if rob is None:
                U = K @ Szz
                P = prior.cov - U @ U.mT
            else:
                A = mom.dx_pos - K @ mom.dz_pos
                P = c * c * (A @ A.mT) + (K @ SR) @ (K @ SR).mT
                M = rob.M_matrix(mdim, SR.dtype, SR.device)
                P = P + (cK * cK) * (K @ M) @ (K @ M).mT
                if mom.dx_neg is not None:
                    B = mom.dx_neg - K @ mom.dz_neg
                    P = P - c * c * (B @ B.mT)
            return safe_cholesky(symmetrize(P))
        if not mom.joseph:
            return chol_downdate(prior.chol, K @ Szz)  # paper 003 Eq. 28-29
        cols = [c * (mom.dx_pos - K @ mom.dz_pos), K @ SR]  # paper 000 Eq. 46
        if rob is not None:  # paper 004 Eq. 28 in square-root form
            M = rob.M_matrix(mdim, SR.dtype, SR.device)
            cols.append(cK * (K @ M))
        SJ = tria(torch.cat(cols, dim=-1))
        if mom.dx_neg is not None:
            SJ = chol_downdate(SJ, c * (mom.dx_neg - K @ mom.dz_neg))
        return SJ if ok is None else torch.where(ok[..., None, None], S, SJ)

    # ------------------------------------------------------------------ public steps
    def predict(
        self, model, state: FilterState, u: Tensor | None = None, k: int = 1
    ) -> FilterState:
        """Time update only (multi-step-ahead prediction; noise estimates held). Strong
        tracking predicts with ``lambda = 1``; a constant fading factor inflates ``A A^T`` as in
        a step (paper 000 Eq. 36)."""
        _check_state(state, "predict")
        u = check_control(u, model.control_dim, state.belief.batch_shape, state.belief.mean)
        noise = self._noise(model, state, k)
        prop = self._propagate(model, state.belief, u, k, noise.q)
        lam = None
        if isinstance(self.fading, (int, float)):
            lam = torch.full(
                state.belief.batch_shape,
                float(self.fading),
                dtype=prop.mean.dtype,
                device=prop.mean.device,
            )
        prior = self._prior(prop, noise.chol_Q, lam, False, noise.diag_Q)
        return replace(state, belief=GaussianBelief(prior.mean, prior.chol))

    def predict_measurement(
        self, model, belief: GaussianBelief, u: Tensor | None = None, k: int = 1
    ) -> GaussianBelief:
        """Predictive distribution of ``y_k`` given a belief on ``x_k``: ``N(z, S_zz S_zz^T)``."""
        if not isinstance(belief, GaussianBelief):  # (was an AttributeError on batch_shape)
            what = type(belief).__name__
            hint = ": pass state.belief" if isinstance(belief, FilterState) else ""
            raise TypeError(f"belief must be a GaussianBelief, got {what}{hint}")
        u = check_control(u, model.control_dim, belief.batch_shape, belief.mean)
        noise = model.checked_noise(k, belief.batch_shape, belief.mean)
        prior = _Prior(belief.mean, belief.chol, belief.cov if not self.sqrt else None)
        dummy = _Propagation(belief.mean, belief.mean, belief.chol, None, None)
        mom = self._moments(model, prior, dummy, u, k, noise.r)
        return GaussianBelief(mom.z, self._innovation_chol(mom, noise.chol_R))

    def step(
        self,
        model: StateSpaceModel,
        state: FilterState,
        y: Tensor,
        u: Tensor | None = None,
        k: int = 1,
    ) -> tuple[FilterState, StepInfo]:
        """One predict/update step with measurement ``y`` ``(..., m)`` (NaN: missing).

        Args:
            model: the state-space model.
            state: :class:`FilterState` at ``k - 1`` (from :meth:`init` or a previous step).
            y: ``(..., m)`` with the belief's batch shape.
            u: control ``(..., p)`` or ``(p,)`` (shared by all batch elements), or ``None``.
            k: step index passed to ``f``, ``h`` and per-step noise.
        Returns:
            The new state and a :class:`StepInfo`.
        """
        _check_state(state, "step")
        belief = state.belief
        if _no_sync():
            y, any_missing = _check_measurement_traced(y, model.obs_dim, belief)
        else:
            y, any_missing = check_measurement(y, model.obs_dim, belief.batch_shape, belief.mean)
        u = check_control(u, model.control_dim, belief.batch_shape, belief.mean)
        return self._update(model, state, y, u, k, any_missing)

    def _update(
        self,
        model: StateSpaceModel,
        state: FilterState,
        y: Tensor,
        u: Tensor | None,
        k: int,
        any_missing: bool,
        noise: Noise | None = None,
    ) -> tuple[FilterState, StepInfo]:
        """:meth:`step` on checked arguments: ``y`` ``(..., m)`` in the belief's dtype and
        device, NaN only where missing (``any_missing`` says whether any entry is NaN), ``u``
        as :func:`check_control` returns it; ``noise``: the model's checked noise at ``k``, or
        ``None`` to take it here. A caller that has validated its data already (the optimiser
        face: finite targets, checked once per :func:`~prognos_torch.optim.fit` call; the
        particle filters' per-particle proposal) enters here, so that a step pays for no
        check twice."""
        belief = state.belief
        if noise is None or state.noise is not None:
            noise = self._noise(model, state, k)
        observed = nan = None
        if any_missing:
            nan = torch.isnan(y)
            incomplete = nan.any(-1)  # strong tracking and noise estimators skip these
            missing = nan.all(-1) if self.robust is None else incomplete
            if self.robust is None and bool((incomplete & ~missing).any()):
                observed = ~nan  # some vector is partially observed: update with its part
        else:
            missing = _constant(belief.batch_shape, torch.bool, y.device, False)
            incomplete = missing
        prop = self._propagate(model, belief, u, k, noise.q)

        fstate = state.fading
        lam = None
        if isinstance(self.fading, StrongTracking):
            prior_l = self._prior(prop, noise.chol_Q, None, True, noise.diag_Q)
            mom_l = self._moments(model, prior_l, prop, u, k, noise.r)
            eps_l = y - mom_l.z
            if any_missing:
                eps_l = torch.where(incomplete[..., None], torch.zeros_like(y), eps_l)
            lam, fstate = fading_factor(
                self.fading,
                state.fading,
                eps_l,
                incomplete,
                mom_l.H,
                _bcast(noise.chol_Q, belief.batch_shape, noise.chol_Q.shape[-2:]),
                _bcast(noise.chol_R, belief.batch_shape, noise.chol_R.shape[-2:]),
                prior_l.chol,
                mom_l.pzz_trace(),
                mom_l.pxz() if mom_l.H is None else None,
                any_missing=any_missing,
            )
            # (traced: always, no host read; lambda = 1 scales by sqrt(1) = 1, the same factor)
            if torch.compiler.is_compiling() or bool((lam > 1).any()):
                prior = self._prior(prop, noise.chol_Q, lam, True, noise.diag_Q)  # paper 000 Eq. 36
                if mom_l.H is not None:  # Taylor: same mean, same h and Jacobian, new factor
                    mom = _Moments(
                        mom_l.z, prior.chol, mm(mom_l.H, prior.chol), None, None, True, mom_l.H
                    )
                else:
                    mom = self._moments(model, prior, prop, u, k, noise.r)
            else:
                prior, mom = prior_l, mom_l
        else:
            if self.fading is not None:
                lam = torch.full(
                    belief.batch_shape, float(self.fading), dtype=y.dtype, device=y.device
                )
            prior = self._prior(prop, noise.chol_Q, lam, True, noise.diag_Q)
            mom = self._moments(model, prior, prop, u, k, noise.r)

        chol_R = noise.chol_R
        if observed is not None:
            mom, chol_R = _observed_part(mom, chol_R, observed)
        coef = self._robust_coef(mom, chol_R)
        Szz = self._innovation_chol(mom, chol_R, coef)
        K = cho_solve_right(mom.pxz(), Szz)  # paper 000 Eq. 44
        eps = y - mom.z
        if any_missing:
            eps = torch.where(nan, torch.zeros_like(y), eps)
        if eps.shape[-1] == 1:  # scalar measurement: the product K eps is one multiplication
            mean = torch.addcmul(prior.mean, K[..., 0], eps)  # Eq. 45
        else:
            mean = prior.mean + mm(K, eps.unsqueeze(-1)).squeeze(-1)  # Eq. 45
        chol = self._posterior_chol(prior, mom, K, Szz, chol_R, coef)
        if any_missing:
            keep = prior
            if self.robust is not None and self.robust.form == "lemma" and bool(missing.any()):
                # the lemma form's prior is the bound P~ (paper 004 Theorem 1); a step without
                # a measurement has no uncertainty term to bound: its posterior is the prediction
                keep = self._prior(prop, noise.chol_Q, lam, False, noise.diag_Q)
            mean = torch.where(missing[..., None], keep.mean, mean)
            chol = torch.where(missing[..., None, None], keep.chol, chol)

        nstate = state.noise
        if nstate is None:
            fallback = _constant(belief.batch_shape, torch.bool, y.device, False)
        else:
            h_mean = mom.z if noise.r is None else mom.z - noise.r
            spread_pos, spread_neg = prop.pos, prop.neg
            if lam is not None:  # Eq. 41 subtracts the spread the prior used: lambda F P F^T
                sl = lam.sqrt()[..., None, None]
                spread_pos = sl * spread_pos
                spread_neg = None if spread_neg is None else sl * spread_neg
            ctx = UpdateContext(
                x_post=mean,
                f_mean=prop.f_mean,
                spread_pos=spread_pos,
                spread_neg=spread_neg,
                gain=K,
                innovation=eps,
                chol_post=chol,
                y=torch.where(nan, mom.z, y) if any_missing else y,
                h_mean=h_mean,
                dz_pos=mom.dz_pos,
                dz_neg=mom.dz_neg,
                missing=incomplete,
                any_missing=any_missing,
                chol_innovation=Szz,
            )
            nstate = self.noise.update(nstate, ctx)
            fallback = nstate.fallback
        if lam is None:
            lam = _constant(belief.batch_shape, y.dtype, y.device, 1.0)
        info = StepInfo(
            prior=GaussianBelief(prior.mean, prior.chol),
            innovation=eps,
            chol_innovation=Szz,
            fading_factor=lam,
            noise=noise,
            noise_fallback=fallback,
            missing=missing,
            gain=K,
            observed=observed,
            # (the robust bound is no predictive covariance: nothing for a smoother)
            spread=None
            if self.robust is not None
            else Spread(prop.pos, prop.neg, prop.dev, prop.sigma),  # fmt: skip
        )
        return FilterState(GaussianBelief(mean, chol), fstate, nstate), info
