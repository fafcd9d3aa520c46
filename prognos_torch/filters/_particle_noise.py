"""Model noise as the particle filters use it, checked once per run (private to
:mod:`prognos_torch.filters.particle`): the noise of a step with the particle dim inserted, the
constants of its Gaussian log densities, diagonal square roots applied by products, and the
engine's view of the model with the particles as a batch dimension."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import torch
from torch import Tensor

from ..core.linalg import tria
from ..core.model import Noise, StateSpaceModel

_LOG_2PI = math.log(2.0 * math.pi)


@dataclass(frozen=True)
class _PNoise:
    """Model noise of one step as the particle side uses it, checked once.

    ``q``/``r``: means with the particle dim inserted (or ``None``); ``chol_Q``/``chol_R``:
    the square roots; ``dQ``/``dR``: their diagonals ``(..., 1, d)`` when the square root is
    diagonal (then ``S eps = dQ * eps`` and ``S^{-1} e = e * (1 / dR)``, the same numbers as
    the triangular solve and the matrix product), else ``None``; ``kQ``/``kR``: the constants
    ``d log 2 pi + log det S S^T`` ``(..., 1)`` of the Gaussian log densities.
    """

    noise: Noise
    q: Tensor | None
    r: Tensor | None
    dQ: Tensor | None
    inv_dR: Tensor | None
    inv_dQ: Tensor | None
    kR: Tensor
    kQ: Tensor | None


def _diag_or_none(S: Tensor) -> Tensor | None:
    d = torch.diagonal(S, dim1=-2, dim2=-1)
    if S.shape[-1] == 1 or bool((S == torch.diag_embed(d)).all()):
        return d.unsqueeze(-2)
    return None


def _log_norm_const(S: Tensor) -> Tensor:
    """``d log 2 pi + log det S S^T`` ``(..., 1)`` for a lower square root ``S`` ``(..., d, d)``."""
    logdet = 2.0 * torch.log(torch.diagonal(S, dim1=-2, dim2=-1)).sum(-1)
    return S.shape[-1] * _LOG_2PI + logdet.unsqueeze(-1)


def _noise(
    model: StateSpaceModel, k: int, bs: torch.Size, like: Tensor, density_Q: bool = False
) -> _PNoise:
    """Model noise at step ``k``, converted and checked: each tensor ``tail`` or ``bs + tail``;
    ``chol_R`` (and with ``density_Q`` ``chol_Q``) must have a positive diagonal."""
    noise = model.checked_noise(k, bs, like, owner="particles")
    if not bool((torch.diagonal(noise.chol_R, dim1=-2, dim2=-1) > 0).all()):
        raise ValueError("model.chol_R must have a positive diagonal (R positive definite)")
    for name, S in (("chol_R", noise.chol_R), ("chol_Q", noise.chol_Q if density_Q else None)):
        if S is not None and bool(torch.triu(S, 1).ne(0).any()):  # (the Gaussian filters take
            raise ValueError(  # any square root; the weights solve with a triangular one)
                f"model.{name} must be lower triangular for a particle filter, whose weights "
                f"solve with it (got a square root with entries above the diagonal); pass "
                f"torch.linalg.cholesky({name[-1]}) or prognos_torch.core.linalg.tria({name})"
            )
    if density_Q and not bool((torch.diagonal(noise.chol_Q, dim1=-2, dim2=-1) > 0).all()):
        raise ValueError(
            "model.chol_Q must have a positive diagonal for a Gaussian-proposal particle "
            "filter (the transition density p(x_k | x_{k-1}) enters the weights)"
        )
    dQ, dR = _diag_or_none(noise.chol_Q), _diag_or_none(noise.chol_R)
    return _PNoise(
        noise,
        _pdim(noise.q, 1),
        _pdim(noise.r, 1),
        dQ,
        None if dR is None else 1.0 / dR,
        None if dQ is None or not density_Q else 1.0 / dQ,
        _log_norm_const(noise.chol_R),
        _log_norm_const(noise.chol_Q) if density_Q else None,
    )


def _constant_noise(model: StateSpaceModel) -> bool:
    return not any(callable(v) for v in (model.q, model.chol_Q, model.r, model.chol_R))


def _pdim(x: Tensor | None, tail: int) -> Tensor | None:
    """Insert the particle dim into a noise tensor that carries the batch dims."""
    if x is None or x.dim() == tail:
        return x
    return x.unsqueeze(-tail - 1)


def _sum_last(t: Tensor) -> Tensor:
    """``t.sum(-1)``; a last dimension of one is selected (the same numbers, one op less)."""
    return t[..., 0] if t.shape[-1] == 1 else t.sum(-1)


def _gauss_logpdf(e: Tensor, S: Tensor, k: Tensor | None = None, inv_d: Tensor | None = None):
    """``log N(e; 0, S S^T)`` for residuals ``e`` ``(..., N, d)`` and ``S`` ``(d, d)`` or
    ``(..., d, d)`` (shared by the particles). Returns ``(..., N)``. ``k``: the constant
    :func:`_log_norm_const` of ``S``; ``inv_d``: ``1 / diag(S)`` ``(..., 1, d)`` when ``S`` is
    diagonal."""
    if k is None:
        k = _log_norm_const(S)
    if inv_d is not None:
        z = e * inv_d
        if z.shape[-1] == 1:  # -k/2 - z^2/2 in one pass
            z = z[..., 0]
            return torch.addcmul(-0.5 * k, z, z, value=-0.5)
        return -0.5 * (k + (z * z).sum(-1))
    z = torch.linalg.solve_triangular(S, e.mT, upper=False)  # (..., d, N)
    return -0.5 * (k + (z * z).sum(-2))


def _observed_logpdf(e: Tensor, S: Tensor, observed: Tensor) -> Tensor:
    """``log N(e_o; 0, S_o S_o^T)`` over the observed components ``o`` of each run: the
    residuals ``e`` ``(..., N, d)``, ``S`` ``(d, d)`` or ``(..., d, d)``, ``observed``
    ``(..., d)`` bool. Returns ``(..., N)``.

    As the Gaussian filters' update (``_blocks._observed_part``): the rows of the missing
    components are zeroed in ``S`` and in ``e`` and unit columns ``diag(1 - o)`` appended, so
    ``S' S'^T = R_oo (+) I`` (block diagonal up to the order; ``S' = tria(...)``, Eq. 25 of
    paper 000). The unit block adds ``-1/2 log 2 pi`` per missing component, taken off again.
    """
    o = observed.to(e.dtype)
    SR = S * o.unsqueeze(-1)
    E = torch.diag_embed(1.0 - o)
    Sp = tria(torch.cat([SR.expand(*E.shape[:-2], *SR.shape[-2:]), E], dim=-1))
    n_miss = (1.0 - o).sum(-1, keepdim=True)  # (..., 1)
    return _gauss_logpdf(e * o.unsqueeze(-2), Sp) + 0.5 * _LOG_2PI * n_miss


def _particle_model(model: StateSpaceModel, bs_ndim: int, N: int) -> StateSpaceModel:
    """The model as the engine sees it with batch dims ``(..., N)``: noise tensors that carry the
    run batch dims get the particle dim inserted (the engine requires the full batch shape)."""
    if bs_ndim == 0:
        return model

    def lift(v, tail):
        if v is None:
            return None

        def at(k):
            t = v(k) if callable(v) else v
            if isinstance(t, Tensor) and t.dim() > tail:
                t = t.unsqueeze(-tail - 1)
                t = t.expand(*t.shape[: -tail - 1], N, *t.shape[-tail:])
            return t

        if callable(v):
            return at
        return at(0)

    return replace(
        model,
        q=lift(model.q, 1),
        chol_Q=lift(model.chol_Q, 2),
        r=lift(model.r, 1),
        chol_R=lift(model.chol_R, 2),
    )


@dataclass(frozen=True)
class _Setup:
    """What :meth:`ParticleFilter.run` checks and builds once for all its steps: the noise when
    the model's is constant (else ``None``: checked per step) and the engine's model view."""

    noise: _PNoise | None
    pmodel: StateSpaceModel | None
    engine_noise: Noise | None
    no_flag: Tensor  # (...) bool zeros
    yes_flag: Tensor  # (...) bool ones
    no_count: Tensor  # (...) int64 zeros
    unit: Tensor  # (...) ones
