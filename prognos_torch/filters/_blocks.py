"""The records and pure blocks of the Gaussian filter engine (:mod:`prognos_torch.filters.gaussian`).

Records a step carries or returns (:class:`Taylor`, :class:`FilterState`, :class:`StepInfo`,
:class:`Spread`) and the step's intermediate values (the propagated points, the prior, the
measurement moments), the sigma-point rule with its weight split done once (``_Sigma``,
``_sigma_points``), the innovation statistics (:func:`innovation_stats`) and the restriction
of the measurement moments to the observed components (``_observed_part``). Every function here
is pure: tensors in, tensors out, no host synchronisation and no module state beyond a cache
of the rules' unit points. The engine composes them into one step; the public names are
re-exported by :mod:`prognos_torch.filters.gaussian`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import cached_property

import torch
from torch import Tensor

from ..adapt.noise import NoiseEstimatorState
from ..adapt.strong_tracking import StrongTrackingState
from ..core.belief import GaussianBelief
from ..core.linalg import mm
from ..core.model import Noise
from ..quadrature import SigmaPoints

__all__ = [
    "Taylor",
    "FilterState",
    "StepInfo",
    "Spread",
    "innovation_stats",
]

_LOG_2PI = math.log(2.0 * math.pi)


@dataclass(frozen=True)
class Taylor:
    """First-order Taylor linearisation (EKF); Jacobians by ``torch.func.jacfwd`` or the model's."""


@dataclass(frozen=True)
class FilterState:
    """Everything a filter carries between steps (no hidden state on filter objects).

    Attributes:
        belief: posterior at the last step.
        fading: strong-tracking state (``V_k``) or ``None``.
        noise: noise-estimator state or ``None``.
    """

    belief: GaussianBelief
    fading: StrongTrackingState | None = None
    noise: NoiseEstimatorState | None = None


def innovation_stats(
    innovation: Tensor,
    chol_innovation: Tensor,
    missing: Tensor,
    n_observed: Tensor | None = None,
):
    """Normalised innovation squared and Gaussian log-likelihood of innovations.

    Works on any leading dims (one step, or a whole stacked trajectory). Missing steps get
    ``nis = NaN`` and a log-likelihood contribution of 0. ``n_observed`` ``(...)``: number of
    observed components of partially observed vectors (default: all ``m``); their innovation
    is 0 and their innovation factor a unit block at the missing components.
    """
    w = torch.linalg.solve_triangular(chol_innovation, innovation.unsqueeze(-1), upper=False)
    nis = w.squeeze(-1).pow(2).sum(-1)
    logdet = 2.0 * torch.log(torch.diagonal(chol_innovation, dim1=-2, dim2=-1)).sum(-1)
    m = innovation.shape[-1] if n_observed is None else n_observed.to(innovation.dtype)
    ll = -0.5 * (m * _LOG_2PI + logdet + nis)
    ll = torch.where(missing, torch.zeros_like(ll), ll)
    nis = torch.where(missing, torch.full_like(nis, float("nan")), nis)
    return nis, ll


@dataclass(frozen=True)
class StepInfo:
    """Diagnostics of one step (batch dims ``...``).

    Attributes:
        prior: the predicted belief ``N(x_{k|k-1}, S S^T)`` (after fading).
        innovation: ``(..., m)`` ``y_k - z_{k|k-1}`` (zeros where missing).
        chol_innovation: ``(..., m, m)`` square root of the innovation covariance.
        fading_factor: ``(...)`` ``lambda_k`` (1 without strong tracking).
        noise: the noise statistics used in this step.
        noise_fallback: ``(...)`` bool, true where a noise estimate had to be projected to PD.
        missing: ``(...)`` bool: no component observed (predict only).
        gain: ``(..., n, m)`` Kalman gain.
        observed: ``(..., m)`` bool, the observed components, or ``None`` when every component
            of every batch element was observed or missing as a whole.
        spread: the time update's deviation columns (:class:`Spread`; what a smoother needs).

    ``log_likelihood`` (``log N(y_k; z_{k|k-1}, S_zz S_zz^T)``, 0 where missing) and ``nis``
    (normalised innovation squared, NaN where missing) are computed on first access, so the
    hot loop does not pay for them when nobody reads them.
    """

    prior: GaussianBelief
    innovation: Tensor
    chol_innovation: Tensor
    fading_factor: Tensor
    noise: Noise
    noise_fallback: Tensor
    missing: Tensor
    gain: Tensor
    observed: Tensor | None = None
    spread: Spread | None = None

    @cached_property
    def _stats(self):
        n_obs = None if self.observed is None else self.observed.sum(-1)
        return innovation_stats(self.innovation, self.chol_innovation, self.missing, n_obs)

    @property
    def nis(self) -> Tensor:
        return self._stats[0]

    @property
    def log_likelihood(self) -> Tensor:
        return self._stats[1]


@dataclass(frozen=True)
class _Propagation:
    mean: Tensor  # (..., n) predicted mean including q
    f_mean: Tensor  # (..., n) sum W f(xi), without q
    pos: Tensor  # (..., n, Lp) spread factor (positive weights)
    neg: Tensor | None  # (..., n, Ln) negative-weight part
    points: Tensor | None  # (..., L, n) propagated sigma points incl. q (for redraw=False)
    dev: Tensor | None = None  # (..., L, n) sigma-point deviations before f, or S (Taylor)
    sigma: _Sigma | None = None  # the rule's points (None: dev is the factor S itself)


@dataclass(frozen=True)
class Spread:
    """Deviation columns of a time update, paired column by column (batch dims ``...``).

    ``dx`` are the weighted deviations of the points at ``k-1`` from the posterior mean,
    ``df`` those of their images under ``f`` from the predicted mean (before fading), with
    ``sqrt|W_i|`` folded in and negative-weight columns apart:
    ``P_{k-1|k-1} = dx_pos dx_pos^T - dx_neg dx_neg^T``, the cross-covariance
    ``C_k = Cov(x_{k-1}, x_k | y_{1:k-1}) = dx_pos df_pos^T - dx_neg df_neg^T`` and
    ``P_{k|k-1} = lambda_k (df_pos df_pos^T - df_neg df_neg^T) + Q_k``. EKF: ``dx = S``,
    ``df = F S``; random walk: ``dx = df = S``. The smoothers read them.

    Attributes:
        df_pos: ``(..., n, Lp)``; df_neg: ``(..., n, Ln)`` or ``None`` (no negative weight).
        dx_pos, dx_neg: the same for ``dx`` (computed on first access, off the hot loop).
    """

    df_pos: Tensor
    df_neg: Tensor | None
    dev: Tensor = field(repr=False)  # (..., L, n) point deviations, or the factor S
    sigma: _Sigma | None = field(default=None, repr=False)

    @cached_property
    def _dx(self) -> tuple[Tensor, Tensor | None]:
        return (self.dev, None) if self.sigma is None else self.sigma.columns(self.dev)

    @property
    def dx_pos(self) -> Tensor:
        return self._dx[0]

    @property
    def dx_neg(self) -> Tensor | None:
        return self._dx[1]


@dataclass(frozen=True)
class _Prior:
    mean: Tensor
    chol: Tensor
    cov: Tensor | None  # kept by the full-covariance algebra


@dataclass(frozen=True)
class _Moments:
    z: Tensor  # (..., m) predicted measurement including r
    dx_pos: Tensor  # (..., n, Lp)
    dz_pos: Tensor  # (..., m, Lp)
    dx_neg: Tensor | None
    dz_neg: Tensor | None
    joseph: bool  # dx factors reproduce the prior covariance exactly
    H: Tensor | None  # Jacobian (Taylor rule)

    def pxz(self) -> Tensor:
        P = mm(self.dx_pos, self.dz_pos.mT)
        if self.dx_neg is not None:
            P = P - self.dx_neg @ self.dz_neg.mT
        return P

    def pzz(self) -> Tensor:
        P = self.dz_pos @ self.dz_pos.mT
        if self.dz_neg is not None:
            P = P - self.dz_neg @ self.dz_neg.mT
        return P

    def pzz_trace(self) -> Tensor:
        t = (self.dz_pos * self.dz_pos).sum((-2, -1))
        if self.dz_neg is not None:
            t = t - (self.dz_neg * self.dz_neg).sum((-2, -1))
        return t


@dataclass(frozen=True)
class _Sigma:
    """A rule's unit points for one dimension, with the weight split done once."""

    xi: Tensor  # (L, n)
    wm: Tensor  # (L,)
    pos: Tensor | None  # indices with wc > 0 (None: all of them)
    neg: Tensor | None  # indices with wc < 0 (None if there are none)
    sw_pos: Tensor  # sqrt(wc[pos]), (Lp, 1)
    sw_neg: Tensor | None  # sqrt(-wc[neg]), (Ln, 1)
    # xi = [0 (if centre); c I; -c I] (UKF, cubature): the deviations are +-c S^T, no product
    centre: bool = False
    scale: float | None = None

    def deviations(self, S: Tensor) -> Tensor:
        """``xi S^T`` ``(..., L, n)``: the points' deviations from the mean for the factor ``S``
        ``(..., n, n)`` (for the symmetric rules the columns of ``S`` times ``+-c``, exactly
        the entries the product gives)."""
        if self.scale is None:
            return self.xi @ S.mT
        C = S.mT * self.scale
        parts = [C, -C]
        if self.centre:
            parts.insert(0, C.new_zeros(*C.shape[:-2], 1, C.shape[-1]))
        return torch.cat(parts, dim=-2)

    def columns(self, D: Tensor) -> tuple[Tensor, Tensor | None]:
        """``D``: ``(..., L, d)`` deviations -> ``(..., d, Lp)``, ``(..., d, Ln)`` columns ``sqrt|w| D_i``."""
        Dp = D if self.pos is None else D[..., self.pos, :]
        pos = (Dp * self.sw_pos).mT
        if self.neg is None:
            return pos, None
        return pos, (D[..., self.neg, :] * self.sw_neg).mT


_SIGMA_CACHE: dict = {}


def _sigma_points(rule: SigmaPoints, n: int, like: Tensor) -> _Sigma:
    key = (rule, n, like.dtype, like.device)
    sig = _SIGMA_CACHE.get(key)
    if sig is None:
        with torch.inference_mode(False), torch.no_grad():  # ordinary tensors in the cache
            sig = _make_sigma(rule, n, like)
        if len(_SIGMA_CACHE) > 256:
            _SIGMA_CACHE.clear()
        _SIGMA_CACHE[key] = sig
    return sig


def _make_sigma(rule: SigmaPoints, n: int, like: Tensor) -> _Sigma:
    """The cached form of ``rule``'s points and weights for dimension ``n``."""
    xi, wm, wc = rule.points(n, dtype=like.dtype, device=like.device)
    pos = (wc > 0).nonzero().squeeze(-1)
    neg = (wc < 0).nonzero().squeeze(-1)
    has_neg = neg.numel() > 0
    centre, scale = _symmetric_rule(xi)
    return _Sigma(
        xi,
        wm,
        None if pos.numel() == wc.numel() else pos,
        neg if has_neg else None,
        wc[pos].sqrt().unsqueeze(-1),
        (-wc[neg]).sqrt().unsqueeze(-1) if has_neg else None,
        centre,
        scale,
    )


def _symmetric_rule(xi: Tensor) -> tuple[bool, float | None]:
    """``(centre, c)`` when the unit points are exactly ``[0; c I; -c I]`` (``centre``) or
    ``[c I; -c I]``, else ``(False, None)``."""
    L, n = xi.shape
    centre = L == 2 * n + 1
    if L not in (2 * n, 2 * n + 1) or n == 0:
        return False, None
    body = xi[1:] if centre else xi
    c = float(body[0, 0])
    eye = torch.eye(n, dtype=xi.dtype, device=xi.device)
    want = torch.cat([c * eye, -c * eye])
    if c > 0 and torch.equal(body, want) and (not centre or not bool(xi[0].any())):
        return centre, c
    return False, None


def _observed_part(mom: _Moments, chol_R: Tensor, observed: Tensor) -> tuple[_Moments, Tensor]:
    """Measurement moments and noise factor restricted to the observed components.

    The rows of missing components are zeroed in the deviations ``Z`` and in ``S_R``, and unit
    columns ``E = diag(1 - o)`` are appended to ``S_R``. Then ``P_zz' = P_oo (+) I`` (block
    diagonal up to the component order) and ``P_xz'`` has zero columns at the missing
    components, so the gain is ``P_xo P_oo^{-1}`` on the observed ones and 0 elsewhere: the
    exact update with the observed sub-vector, on the full-size arrays.
    """
    o = observed.to(mom.z.dtype)
    row = o.unsqueeze(-1)  # (..., m, 1)
    SR = chol_R * row
    E = torch.diag_embed(1.0 - o)
    SR = torch.cat([SR.expand(*E.shape[:-2], *SR.shape[-2:]), E], dim=-1)  # (..., m, 2m)
    masked = _Moments(
        mom.z,
        mom.dx_pos,
        mom.dz_pos * row,
        mom.dx_neg,
        None if mom.dz_neg is None else mom.dz_neg * row,
        mom.joseph,
        None if mom.H is None else mom.H * row,
    )
    return masked, SR
