"""Resampling schemes for particle filters and the effective sample size.

Every resampler takes weights of shape ``(..., N)`` (log-weights by default, or non-negative
weights with ``log=False``; neither needs to be normalised), an explicit ``torch.Generator`` and
returns ancestor indices ``(..., N)`` (``int64``): offspring ``j`` of batch element ``b`` is a
copy of particle ``ancestors[b, j]``. All schemes are unbiased, ``E[#offspring of i] = N w_i``
(Douc, Cappe & Moulines, "Comparison of resampling schemes for particle filtering", 2005):

- :func:`multinomial`: ``N`` i.i.d. draws from the categorical distribution ``w``;
  ``Var[#offspring of i] = N w_i (1 - w_i)``.
- :func:`stratified`: one uniform in each stratum ``[j/N, (j+1)/N)``.
- :func:`systematic`: one uniform ``U`` shared by all strata, points ``(j + U)/N``; the number of
  offspring of ``i`` is ``floor(N w_i)`` or ``ceil(N w_i)``.
- :func:`residual`: ``floor(N w_i)`` deterministic copies, the remaining
  ``R = N - sum floor(N w_i)`` drawn multinomially from the residual weights
  ``(N w_i - floor(N w_i)) / R``.

All draws are inverse-CDF look-ups (``torch.searchsorted``; NumPy's on CPU from
``_NUMPY_SEARCH_MIN`` particles, one call per run) on the normalised cumulative weights, batched
over the leading dimensions: no Python loop over particles. Systematic resampling on the CPU
from ``_COUNT_MIN`` particles counts each particle's offspring instead (the same indices, in
O(N)).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import torch
from torch import Tensor

from ..core.validation import check_generator

__all__ = [
    "multinomial",
    "systematic",
    "stratified",
    "residual",
    "ess",
    "normalize_log_weights",
    "RESAMPLERS",
    "get_resampler",
]

Resampler = Callable[..., Tensor]


def _normalized(weights: Tensor, log: bool) -> Tensor:
    """Validated, normalised probabilities ``(..., N)`` (floating point)."""
    if not isinstance(weights, Tensor):
        raise TypeError("weights must be a torch.Tensor of shape (..., N)")
    if weights.dim() < 1 or weights.shape[-1] < 1:
        raise ValueError(
            f"weights must have shape (..., N) with N >= 1, got {tuple(weights.shape)}"
        )
    if not weights.is_floating_point():
        raise TypeError(f"weights must be a floating-point tensor, got {weights.dtype}")
    if weights.dtype in (torch.float16, torch.bfloat16):
        # half precision holds integers exactly only to 2048 (bfloat16: 256): the points
        # (j + U) / N and the offspring counts would be off; the draws are made in float32
        weights = weights.float()
    if log:
        _check_log_weights(weights)
        return torch.softmax(weights, dim=-1)
    if weights.numel() == 0:  # an empty batch (0, ..., N): nothing to check
        return weights.clone()
    s = weights.sum(-1, keepdim=True)
    low, total, s_min = torch.stack([weights.amin(), s.sum(), s.amin()]).tolist()
    # non-negative entries with a finite sum are finite (NaN makes the minimum NaN)
    if not (low >= 0 and math.isfinite(total)):
        if not bool(torch.isfinite(weights).all()) or bool((weights < 0).any()):
            raise ValueError("weights must be finite and non-negative (or pass log=True)")
        # finite weights whose sum overflows (1e308 + 1e308 = inf gave w = 0, a NaN cdf):
        # those runs are first divided by their largest weight (the others are kept as they are)
        big = ~torch.isfinite(s)
        if bool(big.any()):
            weights = torch.where(big, weights / weights.amax(-1, keepdim=True), weights)
            s = weights.sum(-1, keepdim=True)
    if s_min <= 0:
        raise ValueError("weights sum to zero for a batch element")
    return weights / s


def _check_log_weights(log_w: Tensor, name: str = "log-weights") -> None:
    """``ValueError`` for NaN or +inf log-weights ``(..., N)``, or a run whose log-weights are
    all -inf (no weight at all)."""
    # one host read in the usual case: the maxima propagate NaN and +inf, and a run whose
    # log-weights are all -inf has maximum -inf, so a finite sum of maxima means valid input
    if not math.isfinite(float(log_w.detach().amax(-1).sum())):
        if torch.isnan(log_w).any() or (log_w == float("inf")).any():
            raise ValueError(f"{name} must not contain NaN or +inf")
        mx = log_w.amax(-1, keepdim=True)
        if (mx == float("-inf")).any():
            raise ValueError(f"{name} are -inf for every particle of a batch element")


def _cdf(w: Tensor) -> Tensor:
    # dividing by the last element makes cdf[..., -1] == 1 exactly, so every u in [0, 1) finds an
    # index < N, and zero-weight particles (flat cdf steps) are never selected (right=True).
    c = torch.cumsum(w, dim=-1)
    cdf = c / c[..., -1:]
    return cdf if cdf.is_contiguous() else cdf.contiguous()


#: From this many particles a CPU look-up uses NumPy's ``searchsorted``, which exploits sorted
#: queries (systematic, stratified and residual draws are sorted). Best of 5, one thread, sorted
#: queries: torch / NumPy 33 / 43 us at 4,096, 185 / 91 us at 8,192, 2.6 / 1.4 ms at 10^5.
#: Both return the same indices.
_NUMPY_SEARCH_MIN = 8192


def _lookup(cdf: Tensor, u: Tensor) -> Tensor:
    """``min(#{i : cdf_i <= u_j}, N - 1)`` for each ``u_j`` (``cdf``: ``(..., N)``, ``u``:
    ``(..., M)``)."""
    N = cdf.shape[-1]
    M = u.shape[-1]
    if cdf.device.type == "cpu" and N >= _NUMPY_SEARCH_MIN and u.shape[:-1] == cdf.shape[:-1]:
        c2 = cdf.detach().reshape(-1, N).numpy()
        u2 = u.detach().contiguous().reshape(-1, M).numpy()
        out = np.empty(u2.shape, dtype=np.int64)
        for i in range(c2.shape[0]):  # one row per run; each row is a long look-up
            out[i] = np.searchsorted(c2[i], u2[i], side="right")
        idx = torch.from_numpy(out).reshape(u.shape)
    else:
        idx = torch.searchsorted(cdf, u if u.is_contiguous() else u.contiguous(), right=True)
    return idx.clamp_max(N - 1)


def _uniform(shape, generator, like: Tensor) -> Tensor:
    return torch.rand(shape, generator=generator, dtype=like.dtype, device=like.device)


def _multinomial(w: Tensor, generator: torch.Generator) -> Tensor:
    return _lookup(_cdf(w), _uniform(w.shape, generator, w))


_ARANGE: dict = {}


def _arange(N: int, dtype: torch.dtype, device) -> Tensor:
    """``arange(N)`` in ``dtype`` on ``device``, kept for reuse (never written to)."""
    key = (N, dtype, device)
    j = _ARANGE.get(key)
    if j is None:
        if len(_ARANGE) > 64:
            _ARANGE.clear()
        with torch.inference_mode(False):  # an ordinary tensor, whatever mode fills it
            j = _ARANGE[key] = torch.arange(N, dtype=dtype, device=device)
    return j


def _stratified(w: Tensor, generator: torch.Generator) -> Tensor:
    N = w.shape[-1]
    j = _arange(N, w.dtype, w.device)
    u = (j + _uniform(w.shape, generator, w)) / N
    return _lookup(_cdf(w), u.clamp_max(1.0 - torch.finfo(w.dtype).eps))


#: From this many particles a CPU systematic resampling counts offspring (O(N): a histogram
#: and a cumulative sum) instead of searching (O(N log N)). One thread, a peaked likelihood,
#: counts / search (with the points): 35 / 25 us at 1,000, 40 / 60 us at 2,000, 65 / 166 us
#: at 10^4, 0.71 / 2.9 ms at 10^5. The same indices. (Counting stratified draws needs a gather
#: of the points and a mask for the cdf's ends; it gained little over the search at 10^4 and
#: lost at 10^5, so stratified resampling searches.)
_COUNT_MIN = 2048


def _systematic(w: Tensor, generator: torch.Generator) -> Tensor:
    N = w.shape[-1]
    U = _uniform(w.shape[:-1] + (1,), generator, w)
    if w.device.type == "cpu" and N >= _COUNT_MIN:
        return _systematic_by_counts(_cdf(w), U)
    u = (_arange(N, w.dtype, w.device) + U) / N
    return _lookup(_cdf(w), u.clamp_max(1.0 - torch.finfo(w.dtype).eps))


def _near_integer(K: Tensor, x: Tensor) -> bool:
    """Whether some ``K - x`` (``K = ceil(x)``, so each in ``[0, 1)``) lies within rounding of 0
    or 1: O(N eps) for ``x = N cdf - U`` and for the points ``u_j``, with a margin."""
    if x.numel() == 0:  # an empty batch
        return False
    tol = 16.0 * x.shape[-1] * torch.finfo(x.dtype).eps
    lo, hi = torch.aminmax(K - x)
    return bool((lo < tol) | (hi > 1.0 - tol))


def _systematic_by_counts(cdf: Tensor, U: Tensor, *, traced: bool = False) -> Tensor:
    """The look-up's ancestors at the points ``u_j = min((j + U) / N, 1 - eps)``, counted.

    ``K_i = #{j : u_j < cdf_i} = ceil(N cdf_i - U)`` (clamped to ``[0, N]``): the offspring of
    particles ``0..i``. Where ``N cdf_i - U`` lies within rounding of an integer, ``K_i`` is
    corrected by comparing the points themselves, computed as the look-up computes them, so
    the indices are the look-up's. ``cdf`` ``(..., N)``, ``U`` ``(..., 1)``. ``traced``: the
    correction is applied everywhere instead of after a host read of whether it is needed
    (the same indices: away from an integer it changes nothing), for a compiled step.
    """
    N = cdf.shape[-1]
    x = cdf * N - U
    K = torch.ceil(x)
    near = traced or _near_integer(K, x)
    K = K.clamp_(0.0, float(N))
    if near:  # rare: the exact comparisons u_{K-1} >= cdf_i and u_K < cdf_i
        top = 1.0 - torch.finfo(cdf.dtype).eps
        K = K - ((K > 0) & (((K - 1.0 + U) / N).clamp_max(top) >= cdf)).to(K.dtype)
        K = K + ((K < N) & (((K + U) / N).clamp_max(top) < cdf)).to(K.dtype)
    return _ancestors_from_counts(K.to(torch.int64))


def _ancestors_from_counts(K: Tensor) -> Tensor:
    """``ancestor_j = #{i : K_i <= j}`` from the cumulative offspring counts ``K`` ``(..., N)``
    (non-decreasing, ``K_{N-1} <= N``; slots from ``K_{N-1}`` on get ``N``): a histogram of
    ``K`` and its cumulative sum."""
    N = K.shape[-1]
    bs = K.shape[:-1]
    B = K.numel() // N
    if bs:  # one histogram of N + 1 bins per run
        K = K + (_arange(B, torch.int64, K.device) * (N + 1)).reshape(*bs, 1)
    k = K.reshape(-1)
    hist = torch.zeros(B * (N + 1), dtype=torch.int64, device=k.device)
    hist.scatter_add_(0, k, k.new_ones(1).expand(k.numel()))
    return torch.cumsum(hist.reshape(*bs, N + 1)[..., :N], dim=-1)


def _sorted_uniforms(n: Tensor, m: int, generator: torch.Generator, like: Tensor) -> Tensor:
    """Row ``b`` of the ``(..., m)`` result starts with the order statistics of ``n_b <= m``
    independent ``U[0, 1)`` draws, by normalised exponential spacings (``S_k / S_{n_b + 1}``,
    ``S_k`` the sum of ``k`` standard exponentials: O(m), no sort). Sorted queries are what
    the inverse-CDF look-up is fastest on; entries past ``n_b`` are not draws (callers do not
    read them)."""
    e = torch.empty((*n.shape, m + 1), dtype=like.dtype, device=like.device).exponential_(
        generator=generator
    )
    S = torch.cumsum(e, dim=-1)
    # (a draw of 1, possible only through an exponential of 0, is clamped by the look-up)
    if n.dim() == 0:  # one run: n = m
        return S[:m] / S[m]
    return S[..., :m] / S.gather(-1, n.unsqueeze(-1))


def _residual(w: Tensor, generator: torch.Generator) -> Tensor:
    """``floor(N w_i)`` copies of ``i`` in slots ``j < D``, then ``R = N - D`` draws from the
    residual weights ``N w_i - floor(N w_i)`` (inverse CDF at ``R`` sorted uniforms)."""
    N = w.shape[-1]
    bs = w.shape[:-1]
    Nw = N * w
    # a whole N w_i that rounding left a few ulps below its integer (weights from log weights:
    # 1/8 as 0.12499999999999999) keeps its copy; a run whose raised floors would sum past N
    # (only with ~1/(8 eps) particles) keeps the plain floors
    det = torch.floor(Nw * (1.0 + 8.0 * torch.finfo(w.dtype).eps))
    det = torch.where(det.sum(-1, keepdim=True) > N, torch.floor(Nw), det)
    counts = det.to(torch.int64)
    R = N - counts.sum(-1)  # (...), residual draws per run (floors sum to at most N)
    # slot j < D of a run: the particle whose cumulative count first exceeds j; each run's
    # residual slots first hold the pad value N
    out = _ancestors_from_counts(torch.cumsum(counts, dim=-1))
    r_max = int(R.max()) if R.numel() else 0  # (an empty batch draws nothing)
    if r_max == 0:
        return out
    # a run with R_b > 0 draws has residual mass sum_i (N w_i - floor(N w_i)) = R_b >= 1 (up
    # to rounding); a run with none has no residual slot, whatever its look-up gives
    res = (Nw - det).clamp_min(0.0)
    u = _sorted_uniforms(R, r_max, generator, w)
    if not bs:  # one run: its R draws fill the last R slots, in order
        out[N - r_max :] = _lookup(_cdf(res), u)
        return out
    # the last r_max slots hold every run's residual slots: run b's k-th draw goes to slot
    # N - R_b + k, so the slot's query is its draw (k = j - (N - r_max) - (r_max - R_b))
    k = (_arange(r_max, torch.int64, w.device) - (r_max - R).unsqueeze(-1)).clamp_min(0)
    q = u.gather(-1, k)
    res_idx = _lookup(_cdf(res), q.contiguous())
    tail = out[..., N - r_max :]
    out[..., N - r_max :] = torch.where(tail == N, res_idx, tail)
    return out


_DRAWS = {
    "multinomial": _multinomial,
    "stratified": _stratified,
    "systematic": _systematic,
    "residual": _residual,
}


def _draw_ancestors(name: str, w: Tensor, generator: torch.Generator) -> Tensor:
    """The scheme ``name`` on probabilities ``w`` ``(..., N)`` that are already valid and
    normalised (a particle filter's own weights): the public functions minus their checks."""
    return _DRAWS[name.lower()](w, generator)


def multinomial(weights: Tensor, generator: torch.Generator, *, log: bool = True) -> Tensor:
    """Multinomial resampling: ``N`` i.i.d. ancestors from ``Cat(w)``; returns ``(..., N)``."""
    w = _normalized(weights, log)
    check_generator(generator, w, "weights")
    return _multinomial(w, generator)


def stratified(weights: Tensor, generator: torch.Generator, *, log: bool = True) -> Tensor:
    """Stratified resampling: ``u_j = (j + U_j) / N`` with independent ``U_j ~ U[0, 1)``."""
    w = _normalized(weights, log)
    check_generator(generator, w, "weights")
    return _stratified(w, generator)


def systematic(weights: Tensor, generator: torch.Generator, *, log: bool = True) -> Tensor:
    """Systematic resampling: ``u_j = (j + U) / N`` with one ``U ~ U[0, 1)`` per batch element."""
    w = _normalized(weights, log)
    check_generator(generator, w, "weights")
    return _systematic(w, generator)


def residual(weights: Tensor, generator: torch.Generator, *, log: bool = True) -> Tensor:
    """Residual resampling: ``floor(N w_i)`` copies of ``i``, the rest multinomial on residuals.

    Batched without a loop: offspring slot ``j < D = sum_i floor(N w_i)`` is filled by the
    particle whose cumulative deterministic count first exceeds ``j``; slots ``j >= D`` by
    inverse-CDF draws from the residual weights.
    """
    w = _normalized(weights, log)
    check_generator(generator, w, "weights")
    return _residual(w, generator)


def normalize_log_weights(log_w: Tensor) -> tuple[Tensor, Tensor]:
    """``(log_w - logsumexp(log_w), logsumexp(log_w))`` over the last dimension."""
    lse = torch.logsumexp(log_w, dim=-1, keepdim=True)
    return log_w - lse, lse.squeeze(-1)


def ess(log_w: Tensor) -> Tensor:
    """Effective sample size ``1 / sum_i w_i^2`` of (unnormalised) log-weights ``(..., N)``.

    Computed in log space, ``exp(2 logsumexp(l) - logsumexp(2 l))`` with ``l`` relative to each
    run's largest log-weight; returns ``(...)``. It lies in ``[1, N]``. NaN or +inf
    log-weights, or a run whose log-weights are all -inf, raise a ``ValueError``.
    """
    if not isinstance(log_w, Tensor) or log_w.dim() < 1 or log_w.shape[-1] < 1:
        got = tuple(log_w.shape) if isinstance(log_w, Tensor) else type(log_w).__name__
        raise ValueError(f"log_w must be a tensor of shape (..., N) with N >= 1, got {got}")
    _check_log_weights(log_w, "log_w")
    # shifted by the maximum: un-normalised float32 log-weights near -1e4 lost ~1e-3 of
    # 2 logsumexp(l) - logsumexp(2 l) to cancellation, and 2 l overflowed from |l| ~ max / 2
    l = log_w - log_w.detach().amax(-1, keepdim=True)
    return torch.exp(2.0 * torch.logsumexp(l, -1) - torch.logsumexp(2.0 * l, -1))


RESAMPLERS: dict[str, Resampler] = {
    "multinomial": multinomial,
    "stratified": stratified,
    "systematic": systematic,
    "residual": residual,
}


def get_resampler(resampler: str | Resampler) -> Resampler:
    """A resampler by name (``multinomial``, ``stratified``, ``systematic``, ``residual``) or a
    callable ``(log_w (..., N), generator) -> ancestors (..., N)`` passed through."""
    if callable(resampler):
        return resampler
    if not isinstance(resampler, str) or resampler.lower() not in RESAMPLERS:
        raise ValueError(
            f"resampler must be one of {sorted(RESAMPLERS)} or a callable, got {resampler!r}"
        )
    return RESAMPLERS[resampler.lower()]
