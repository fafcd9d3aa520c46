"""The particle state and the pure blocks of the particle step, shared by the eager step
(:meth:`prognos_torch.filters.particle.ParticleFilter.step`) and the compiled pass
(:mod:`prognos_torch.filters._particle_compiled`): the log-normaliser of the weights and the
weighted estimates. No host reads, so that both trace. :class:`ParticleState` is re-exported
by :mod:`prognos_torch.filters.particle`."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from ._blocks import FilterState


@dataclass(frozen=True)
class ParticleState:
    """A weighted particle set (batch dims ``...`` leading).

    Attributes:
        particles: ``(..., N, n)``.
        log_weights: ``(..., N)``, normalised (``logsumexp`` over ``N`` is 0; ``step``,
            ``predict`` and ``run`` refuse a state whose are not, never renormalise it).
        proposal: per-particle Gaussian filter state with batch dims ``(..., N)`` (Gaussian-proposal
            PFs; its ``belief.mean`` equals ``particles``), or ``None`` (bootstrap).
    """

    particles: Tensor
    log_weights: Tensor
    proposal: FilterState | None = None

    @property
    def num_particles(self) -> int:
        return self.log_weights.shape[-1]

    @property
    def batch_shape(self) -> torch.Size:
        return self.log_weights.shape[:-1]

    @property
    def weights(self) -> Tensor:
        return self.log_weights.exp()


def _weighted_moments_1d(W: Tensor, x: Tensor) -> tuple[Tensor, Tensor]:
    """Weighted mean ``(..., 1)`` and variance ``(..., 1, 1)`` of one state ``x`` ``(..., N)``
    under normalised weights ``W`` ``(..., N)`` (paper 002 STPF step 5)."""
    if W.dim() == 1:
        m = torch.dot(W, x)
        d = x - m
        # (weight first: a zero-weight particle far out gives 0, not 0 * inf)
        v = torch.dot(W * d, d)
    else:
        m = (W * x).sum(-1)
        d = x - m.unsqueeze(-1)
        v = (W * d * d).sum(-1)  # (left to right: weight first)
    return m.unsqueeze(-1), v[..., None, None]


def _log_normaliser(lw_un: Tensor) -> Tensor:
    """``log sum_i exp(lw_un_i)`` over the last dim, ``(...)``: ``log p(y_k | y_{1:k-1})`` from
    ``lw_un = log W_{k-1}^i + log p(y_k | x_k^i)`` (paper 002 STPF step 4). ``torch.logsumexp``'s
    arithmetic without its guard for infinite maxima (those give NaN here)."""
    mx = lw_un.amax(-1, keepdim=True)
    return mx.squeeze(-1) + (lw_un - mx).exp_().sum(-1).log_()


def _estimates(W: Tensor, x: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Weighted mean ``(..., n)``, covariance ``(..., n, n)`` and effective sample size ``(...)``
    of finite particles ``x`` ``(..., N, n)`` under normalised weights ``W`` ``(..., N)``
    (paper 002 STPF steps 5-6)."""
    if x.shape[-1] == 1:
        # one state: weighted sums (a matrix product over N is several times slower)
        mean, cov = _weighted_moments_1d(W, x[..., 0])
    else:
        if W.dim() == 1:  # (one run: a vector-matrix product)
            mean = W @ x
            d = x - mean
        else:
            mean = (W.unsqueeze(-2) @ x).squeeze(-2)
            d = x - mean.unsqueeze(-2)
        cov = (d * W.unsqueeze(-1)).mT @ d
        cov = 0.5 * (cov + cov.mT)
    # effective sample size (sum W)^2 / sum W^2 of the normalised weights (sum W = 1 up to
    # rounding): two sums instead of the two log-sum-exps of ess()
    sw = W.sum(-1)
    n_eff = sw * sw / (torch.dot(W, W) if W.dim() == 1 else (W * W).sum(-1))
    return mean, cov, n_eff


def _resample_some(do: Tensor, anc: Tensor, lw: Tensor) -> tuple[Tensor, Tensor]:
    """Ancestors and log-weights when only the runs ``do`` ``(...)`` resample (paper 002 STPF
    step 6): theirs are ``anc`` ``(..., N)`` and ``-log N``; the other runs keep their own
    particles and log-weights ``lw`` ``(..., N)``."""
    N = lw.shape[-1]
    keep = torch.arange(N, device=anc.device).expand(lw.shape)
    anc = torch.where(do[..., None], anc, keep)
    return anc, torch.where(do[..., None], torch.full_like(lw, -math.log(N)), lw)


#: a resampling threshold above this fraction of ``N`` can meet uniform weights, whose effective
#: sample size is ``N`` only up to rounding (below ``N`` for about half the particle counts in
#: float64): :func:`_resample_flags` keeps those, as the threshold 1 promises
_UNIFORM_CHECK = 1.0 - 1e-3


def _resample_flags(n_eff: Tensor, lw: Tensor, fraction: float) -> Tensor:
    """``(...)`` bool: resample the runs with ``N_eff < fraction * N`` (paper 002 STPF step 6)
    whose normalised log-weights ``lw`` ``(..., N)`` are not all equal."""
    do = n_eff < fraction * lw.shape[-1]
    if fraction > _UNIFORM_CHECK:
        lo, hi = torch.aminmax(lw, dim=-1)
        do = do & (hi > lo)
    return do
