"""Noise-statistics estimators that run inside the Gaussian filter engine.

Both estimators see the same per-step quantities (:class:`UpdateContext`) and return the noise
statistics the filter should use at the next step. All estimates are kept as full matrices
``(..., n, n)`` per batch element plus their Cholesky factors.

Positive definiteness. Unbiased estimators subtract a covariance term and can leave the cone of
positive-definite matrices (a known weakness of Sage-Husa). We never let the filter see such a
matrix: when an updated estimate is not positive definite, it is symmetrised and its eigenvalues
are raised to a floor ``max(floor_rel * trace(initial) / dim, 1e-10 * max |eig|)`` — relative
to the *initial* statistic, so repeated projections cannot ratchet the floor down —
(documented projection), and the step
is flagged in ``StepInfo.noise_fallback``. ``diagonal=True`` estimates only the variances (paper
004 Eq. 67-68 uses diagonal ``Q`` and ``R``), each floored the same way.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from functools import cached_property

import torch
from torch import Tensor

from ..core.model import Noise
from ..core.validation import check_setting, is_int

__all__ = ["SageHusa", "MovingWindow", "NoiseEstimatorState", "UpdateContext"]


@dataclass(frozen=True)
class UpdateContext:
    """Quantities of one filter step used by the noise estimators (batch dims ``...``).

    Covariances are handed over as square-root factors; the full matrices (and their diagonals,
    which is all a ``diagonal=True`` estimator needs) are formed on first access.

    Attributes:
        x_post: ``(..., n)`` posterior mean.
        f_mean: ``(..., n)`` ``sum_i W_i f(xi_{i,k-1})`` without ``q`` (paper 003 Eq. 37).
        spread_pos, spread_neg: ``(..., n, L)`` factors with
            ``spread = sum_i W_i (gamma_i - x_pred)(gamma_i - x_pred)^T = A_+ A_+^T - A_- A_-^T``
            (Eq. 36); ``spread_neg`` may be ``None``.
        gain: ``(..., n, m)``.
        innovation: ``(..., m)`` ``e_k = y_k - z_pred`` (Eq. 35).
        chol_post: ``(..., n, n)`` posterior square root (``P_k = S S^T``).
        y: ``(..., m)`` measurement.
        h_mean: ``(..., m)`` ``sum_i W_i h(xi_{i,k|k-1})`` without ``r`` (Eq. 39).
        dz_pos, dz_neg: ``(..., m, L)`` factors of ``sum_i W_i (eta_i - z)(eta_i - z)^T`` (Eq. 38).
        missing: ``(...)`` bool.
        chol_innovation: ``(..., m, m)`` square root of the innovation covariance
            ``P_zz = sum W (eta - z)(eta - z)^T + R`` used by the gain (the post-fit form of
            :class:`SageHusa` needs it), or ``None``.
        any_missing: ``bool(missing.any())`` when the caller knows it (saves a device sync),
            else ``None``.
    """

    x_post: Tensor
    f_mean: Tensor
    spread_pos: Tensor
    spread_neg: Tensor | None
    gain: Tensor
    innovation: Tensor
    chol_post: Tensor
    y: Tensor
    h_mean: Tensor
    dz_pos: Tensor
    dz_neg: Tensor | None
    missing: Tensor
    any_missing: bool | None = None
    chol_innovation: Tensor | None = None

    @property
    def has_missing(self) -> bool:
        return bool(self.missing.any()) if self.any_missing is None else self.any_missing

    @staticmethod
    def _gram(pos: Tensor, neg: Tensor | None) -> Tensor:
        G = pos @ pos.mT
        return G if neg is None else G - neg @ neg.mT

    @staticmethod
    def _gram_diag(pos: Tensor, neg: Tensor | None) -> Tensor:
        d = pos.pow(2).sum(-1)
        return d if neg is None else d - neg.pow(2).sum(-1)

    @cached_property
    def spread(self) -> Tensor:
        return self._gram(self.spread_pos, self.spread_neg)

    @cached_property
    def cov_post(self) -> Tensor:
        return self.chol_post @ self.chol_post.mT

    @cached_property
    def pzz_noR(self) -> Tensor:
        return self._gram(self.dz_pos, self.dz_neg)

    def diag(self, name: str) -> Tensor:
        """Diagonal of ``spread``, ``cov_post`` or ``pzz_noR`` without forming the matrix."""
        if name == "spread":
            return self._gram_diag(self.spread_pos, self.spread_neg)
        if name == "cov_post":
            return self.chol_post.pow(2).sum(-1)
        if name == "pzz_noR":
            return self._gram_diag(self.dz_pos, self.dz_neg)
        raise ValueError(f"unknown quantity {name!r}")


@dataclass(frozen=True)
class NoiseEstimatorState:
    """Current estimates (full matrices and factors) and bookkeeping; batch dims leading."""

    q: Tensor
    Q: Tensor
    chol_Q: Tensor
    r: Tensor
    R: Tensor
    chol_R: Tensor
    count: Tensor
    fallback: Tensor
    floor_Q: Tensor
    floor_R: Tensor
    buf_Q: Tensor | None = None
    buf_R: Tensor | None = None
    buf_valid: Tensor | None = None

    def noise(self) -> Noise:
        return Noise(self.q, self.chol_Q, self.r, self.chol_R)


def _expand(x: Tensor | None, batch_shape, tail, like: Tensor) -> Tensor:
    if x is None:
        return like.new_zeros(*batch_shape, *tail)
    x = x.to(dtype=like.dtype, device=like.device)
    return x.expand(*batch_shape, *tail).clone()


def _project_pd(C: Tensor, floor: Tensor, diagonal: bool) -> tuple[Tensor, Tensor, Tensor]:
    """Return ``(C_pd, chol, fallback)``; see the module docstring."""
    C = 0.5 * (C + C.mT)
    if diagonal:
        d = torch.diagonal(C, dim1=-2, dim2=-1)
        fb = (d < floor[..., None]).any(-1)
        d = torch.maximum(d, floor[..., None])
        C = torch.diag_embed(d)
        return C, torch.diag_embed(d.sqrt()), fb
    L, info = torch.linalg.cholesky_ex(C)
    fb = info > 0
    if bool(fb.any()):
        w, V = torch.linalg.eigh(C)
        # the floor is also kept above round-off relative to the largest eigenvalue: 1e-10 in
        # float64, 64 eps in float32 (1e-10 lies below its rounding: the Cholesky failed)
        rel = max(1e-10, 64.0 * torch.finfo(C.dtype).eps)
        fl = torch.maximum(floor, rel * w.abs().amax(-1))
        w = torch.maximum(w, fl[..., None])
        Cp = (V * w.unsqueeze(-2)) @ V.mT
        Cp = 0.5 * (Cp + Cp.mT)
        C = torch.where(fb[..., None, None], Cp, C)
        L2, info2 = torch.linalg.cholesky_ex(C)
        if bool((info2 > 0).any()):  # pragma: no cover - floor makes this PD
            raise torch.linalg.LinAlgError("noise estimate projection failed")
        L = L2
    return C, L, fb


def _check_floor(floor_rel) -> None:
    check_setting(floor_rel, "floor_rel")
    if floor_rel < 0:
        raise ValueError(f"floor_rel must be >= 0, got {floor_rel}")


def _outer(v: Tensor) -> Tensor:
    return v.unsqueeze(-1) * v.unsqueeze(-2)


@dataclass(frozen=True)
class SageHusa:
    """Sage-Husa noise-statistics estimator adapted to SRUKF (paper 003 Eq. 40-43; ImSRUKF).

    With ``d_k = 1 / k`` (the paper) or, with ``forgetting=b`` in ``(0, 1)``, the fading-memory
    weight ``d_k = (1 - b) / (1 - b^k)``:

        q_k = (1 - d_k) q_{k-1} + d_k (x_k - sum W f(xi_{k-1}))                         (Eq. 40)
        Q_k = (1 - d_k) Q_{k-1} + d_k (K e e^T K^T + P_k - sum W (g - x)(g - x)^T)      (Eq. 41)
        r_k = (1 - d_k) r_{k-1} + d_k (y_k - sum W h(xi_{k|k-1}))                       (Eq. 42)
        R_k = (1 - d_k) R_{k-1} + d_k (e e^T - sum W (eta - z)(eta - z)^T)             (Eq. 43)

    Prior weight. The counter ``k`` starts at ``k0``: the first step uses ``d = 1 / k0`` (with
    forgetting ``(1 - b) / (1 - b^k0)``), so the prior ``Q_0``, ``R_0`` count as ``k0 - 1``
    earlier steps. With ``k0 = 1`` (the paper) ``d_1 = 1`` and the prior is discarded at the
    first step: ``Q_1``, ``R_1`` are one step's rank-one terms.

    Post-fit form of the ``R`` estimate (``r_form="post-fit"``). Eq. 43 subtracts the predicted
    spread ``H P_{k|k-1} H^T`` from ``e e^T``; while ``P`` is being learned the difference is
    mostly negative, and ``R`` sits on the floor of the projection. Paper 003's own
    maximum-a-posteriori estimator (appendix, Eq. 55) takes the residual at the smoothed state
    ``x_{k|N}``; the recursion replaces it by the prediction (Eq. 59). Taking the filtered
    state instead gives the post-fit residual ``rho = y - h(x_k)`` with
    ``E[rho rho^T] = R - H P_k H^T``, so (Akhlaghi et al., 2017)

        R_k = (1 - d_k) R_{k-1} + d_k (rho rho^T + H P_k H^T),

    positive semi-definite by construction. Under statistical linearisation (``H P_{k|k-1} H^T
    = sum W (eta - z)(eta - z)^T``, exact for a linear ``h``) ``rho = R P_zz^-1 e`` and
    ``H P_k H^T = R - R P_zz^-1 R``, both from the innovation factor the gain used (two
    triangular solves; no further evaluation of ``h``).

    Attributes:
        estimate: which statistics to adapt, a subset of ``("q", "Q", "r", "R")``.
        forgetting: ``None`` for ``1/k`` averaging, else ``b`` in ``(0, 1)``.
        diagonal: estimate only variances.
        floor_rel: eigenvalue floor of the positive-definite projection (module docstring).
        frozen: adaptation off: the filter uses the model's noise at every step (exactly
            SRUKF, per-step noise included). The statistics not in ``estimate`` are the model's
            at every step too.
        k0: the counter's start, ``>= 1`` (prior weight, above).
        r_form: ``"innovation"`` (Eq. 43 as printed) or ``"post-fit"`` (above).
    """

    estimate: tuple[str, ...] = ("q", "Q", "r", "R")
    forgetting: float | None = None
    diagonal: bool = False
    floor_rel: float = 1e-6
    frozen: bool = False
    k0: float = 1.0
    r_form: str = "innovation"

    def __post_init__(self):
        bad = set(self.estimate) - {"q", "Q", "r", "R"}
        if bad:
            raise ValueError(f"estimate must be a subset of ('q', 'Q', 'r', 'R'), got {bad}")
        check_setting(self.forgetting, "forgetting", optional=True)
        _check_floor(self.floor_rel)
        if self.forgetting is not None and not 0.0 < self.forgetting < 1.0:
            raise ValueError(f"forgetting must be in (0, 1) or None, got {self.forgetting}")
        if (
            isinstance(self.k0, bool)
            or not isinstance(self.k0, (int, float))
            or not (self.k0 >= 1.0 and self.k0 < float("inf"))
        ):
            raise ValueError(f"k0 must be a finite number >= 1, got {self.k0!r}")
        if self.r_form not in ("innovation", "post-fit"):
            raise ValueError(f"r_form must be 'innovation' or 'post-fit', got {self.r_form!r}")

    def init(self, noise: Noise, batch_shape, n: int, m: int, like: Tensor) -> NoiseEstimatorState:
        cQ = _expand(noise.chol_Q, batch_shape, (n, n), like)
        cR = _expand(noise.chol_R, batch_shape, (m, m), like)
        Q, R = cQ @ cQ.mT, cR @ cR.mT
        floor = lambda C: (  # noqa: E731
            self.floor_rel * torch.diagonal(C, dim1=-2, dim2=-1).sum(-1) / C.shape[-1]
        ).clamp_min(1e-300)
        return NoiseEstimatorState(
            q=_expand(noise.q, batch_shape, (n,), like),
            Q=Q,
            chol_Q=cQ,
            r=_expand(noise.r, batch_shape, (m,), like),
            R=R,
            chol_R=cR,
            count=torch.full(
                batch_shape, float(self.k0) - 1.0, dtype=like.dtype, device=like.device
            ),
            fallback=torch.zeros(batch_shape, dtype=torch.bool, device=like.device),
            floor_Q=floor(Q),
            floor_R=floor(R),
        )

    def _weight(self, count: Tensor) -> Tensor:
        if self.forgetting is None:
            return 1.0 / count
        b = self.forgetting
        return (1.0 - b) / (1.0 - b**count)

    def update(self, s: NoiseEstimatorState, c: UpdateContext) -> NoiseEstimatorState:
        if self.frozen:
            return s
        keep = c.missing
        held = c.has_missing  # some batch elements skip this step (missing measurement)

        def hold(old: Tensor, new: Tensor, extra: int) -> Tensor:
            if not held:
                return new
            return torch.where(keep.reshape(keep.shape + (1,) * extra), old, new)

        def merge(fb: Tensor | None, f: Tensor) -> Tensor:  # fallback flags of updated runs
            f = f & ~keep if held else f
            return f if fb is None else fb | f

        count = hold(s.count, s.count + 1, 0)
        d = self._weight(count.clamp_min(1.0) if held else count)
        d1 = d[..., None]
        q, Q, cQ, r, R, cR = s.q, s.Q, s.chol_Q, s.r, s.R, s.chol_R
        fb = None
        if "q" in self.estimate:  # Eq. 40
            q = hold(q, torch.lerp(q, c.x_post - c.f_mean, d1), 1)
        if "Q" in self.estimate:  # Eq. 41
            Ke = (c.gain @ c.innovation.unsqueeze(-1)).squeeze(-1)
            if self.diagonal:  # only the variances: no n x n products
                term = Ke * Ke + c.diag("cov_post") - c.diag("spread")
                Q, cQ, f1 = self._diagonal_step(Q, cQ, term, d1, s.floor_Q, hold)
            else:
                new = torch.lerp(Q, _outer(Ke) + c.cov_post - c.spread, d1[..., None])
                new, cnew, f1 = _project_pd(new, s.floor_Q, False)
                Q, cQ = hold(Q, new, 2), hold(cQ, cnew, 2)
            fb = merge(fb, f1)
        if "r" in self.estimate:  # Eq. 42
            r = hold(r, torch.lerp(r, c.y - c.h_mean, d1), 1)
        if "R" in self.estimate:  # Eq. 43
            e = c.innovation
            if self.r_form == "post-fit":
                rho, W = self._post_fit(s.R, c)
                if self.diagonal:
                    term = rho * rho + torch.diagonal(s.R, dim1=-2, dim2=-1) - W.pow(2).sum(-2)
                else:
                    term = _outer(rho) + s.R - W.mT @ W
            elif self.diagonal:
                term = e * e - c.diag("pzz_noR")
            else:
                term = _outer(e) - c.pzz_noR
            if self.diagonal:
                R, cR, f2 = self._diagonal_step(R, cR, term, d1, s.floor_R, hold)
            else:
                new = torch.lerp(R, term, d1[..., None])
                new, cnew, f2 = _project_pd(new, s.floor_R, False)
                R, cR = hold(R, new, 2), hold(cR, cnew, 2)
            fb = merge(fb, f2)
        if fb is None:
            fb = torch.zeros_like(s.fallback)
        # positional construction: dataclasses.replace costs more than the update's arithmetic
        return NoiseEstimatorState(
            q, Q, cQ, r, R, cR, count, fb, s.floor_Q, s.floor_R, s.buf_Q, s.buf_R, s.buf_valid
        )

    @staticmethod
    def _post_fit(R: Tensor, c: UpdateContext) -> tuple[Tensor, Tensor]:
        """``(rho, W)``: post-fit residual ``R P_zz^-1 e`` and ``W = S_zz^-1 R`` (``W^T W =
        R P_zz^-1 R``), from the innovation factor ``S_zz`` (class docstring)."""
        Szz = c.chol_innovation
        if Szz is None:
            raise ValueError("SageHusa(r_form='post-fit') needs UpdateContext.chol_innovation")
        a = torch.cholesky_solve(c.innovation.unsqueeze(-1), Szz)
        rho = (R @ a).squeeze(-1)
        W = torch.linalg.solve_triangular(Szz, R, upper=False)
        return rho, W

    @staticmethod
    def _diagonal_step(C, chol_C, term, d1, floor, hold):
        """``diag(C) <- (1 - d) diag(C) + d term``, floored (module docstring); vectors only."""
        v = torch.lerp(torch.diagonal(C, dim1=-2, dim2=-1), term, d1)
        fl = floor[..., None]
        fb = (v < fl).any(-1)
        v = torch.maximum(v, fl)
        return hold(C, torch.diag_embed(v), 2), hold(chol_C, torch.diag_embed(v.sqrt()), 2), fb


@dataclass(frozen=True)
class MovingWindow:
    """Moving-window unbiased estimator of ``Q`` and ``R`` (paper 004 Theorem 2, Eq. 47-48; ARUKF).

        Q_{k-1} = 1/N sum_{j=1..N} [P_{k-j} + K e e^T K^T - sum W (xi - x)(xi - x)^T]_{k-j}   (Eq. 47)
        R_k     = 1/N sum_{j=1..N} [e e^T - (1 - N^T N / mu) C P_{k|k-1} C^T - mu M M^T]_{k-j} (Eq. 48)

    For a nonlinear ``h``, ``C P_{k|k-1} C^T`` is the sigma-point ``sum W (eta - z)(eta - z)^T``.
    ``mu`` is not defined in the extracted text; we take ``mu = gamma^2`` of the robust bound,
    the value that makes Eq. 48 the innovation-matching counterpart of Eq. 29. Without a robust
    bound (``M = 0``) Eq. 48 is plain innovation matching. Until ``warmup`` valid steps are in
    the window, the model's noise statistics are used.

    Attributes:
        window: ``N``, the window length.
        M: ``(m,)``/``(m, j)`` uncertainty direction, or ``None``.
        N: scalar uncertainty gain.
        mu: the Lemma-1 scalar of Eq. 48 (``None``: 1, only used when ``M`` is given).
        warmup: valid steps needed before the estimates are used (default: ``window``).
    """

    window: int = 50
    M: Tensor | None = None
    N: float = 0.0
    mu: float | None = None
    warmup: int | None = None
    estimate: tuple[str, ...] = ("Q", "R")
    diagonal: bool = False
    floor_rel: float = 1e-6
    frozen: bool = False

    def __post_init__(self):
        if not is_int(self.window) or self.window < 1:
            raise ValueError(f"window must be a positive int, got {self.window!r}")
        w = self.warmup
        if w is not None and (
            not is_int(w) or not 1 <= w <= self.window
        ):
            # 0 would average an empty window (a zero estimate, floored) after missing steps;
            # above the window length the estimates would never be used
            raise ValueError(f"warmup must be an int in [1, window={self.window}], got {w!r}")
        object.__setattr__(self, "window", int(self.window))
        if w is not None:
            object.__setattr__(self, "warmup", int(w))
        bad = set(self.estimate) - {"Q", "R"}
        if bad:
            raise ValueError(f"estimate must be a subset of ('Q', 'R'), got {bad}")
        check_setting(self.N, "N")
        check_setting(self.mu, "mu", optional=True)
        if self.mu is not None and not self.mu > 0:
            raise ValueError(f"mu must be positive (Eq. 48 divides by it), got {self.mu}")
        _check_floor(self.floor_rel)

    def init(self, noise: Noise, batch_shape, n: int, m: int, like: Tensor) -> NoiseEstimatorState:
        base = SageHusa(floor_rel=self.floor_rel).init(noise, batch_shape, n, m, like)
        W = self.window
        # diagonal estimates keep only the diagonals of the window's terms
        tq, tr = ((n,), (m,)) if self.diagonal else ((n, n), (m, m))
        return replace(
            base,
            buf_Q=like.new_zeros(W, *batch_shape, *tq),
            buf_R=like.new_zeros(W, *batch_shape, *tr),
            buf_valid=torch.zeros(W, *batch_shape, dtype=torch.bool, device=like.device),
        )

    def update(self, s: NoiseEstimatorState, c: UpdateContext) -> NoiseEstimatorState:
        if self.frozen:
            return s
        m = c.innovation.shape[-1]
        e, dg = c.innovation, self.diagonal
        Ke = (c.gain @ e.unsqueeze(-1)).squeeze(-1)
        if dg:  # Eq. 47-48 on the diagonals only: no n x n products
            termQ = c.diag("cov_post") + Ke * Ke - c.diag("spread")
            termR, pzz = e * e, c.diag("pzz_noR")
        else:
            termQ = c.cov_post + _outer(Ke) - c.spread
            termR, pzz = _outer(e), c.pzz_noR
        if self.M is not None:
            mu = 1.0 if self.mu is None else self.mu
            M = torch.as_tensor(self.M, dtype=c.y.dtype, device=c.y.device)
            M = M.unsqueeze(-1) if M.dim() == 1 else M
            if M.shape[0] != m:
                raise ValueError(f"MovingWindow.M must have shape (m,) or (m, j), m={m}")
            MM = (M * M).sum(-1) if dg else M @ M.mT
            termR = termR - (1.0 - self.N**2 / mu) * pzz - mu * MM
        else:
            termR = termR - pzz
        valid = ~c.missing
        buf_Q = torch.cat([s.buf_Q[1:], termQ.unsqueeze(0)])
        buf_R = torch.cat([s.buf_R[1:], termR.unsqueeze(0)])
        buf_valid = torch.cat([s.buf_valid[1:], valid.unsqueeze(0)])
        nv = buf_valid.sum(0).to(c.y.dtype)
        ready = nv >= (self.window if self.warmup is None else self.warmup)
        Q, cQ, R, cR = s.Q, s.chol_Q, s.R, s.chol_R
        fb = torch.zeros_like(s.fallback)
        # window mean over the valid steps: one contraction over the window axis
        wv = buf_valid.to(c.y.dtype) / nv.clamp_min(1.0)  # (W, ...)
        tail = 1 if dg else 2

        def window_mean(buf: Tensor) -> Tensor:
            return (wv.reshape(wv.shape + (1,) * tail) * buf).sum(0)

        def project(mean: Tensor, floor: Tensor):
            if dg:
                return _project_pd(torch.diag_embed(mean), floor, True)
            return _project_pd(mean, floor, False)

        if "Q" in self.estimate:
            new, cnew, f1 = project(window_mean(buf_Q), s.floor_Q)
            Q = torch.where(ready[..., None, None], new, Q)
            cQ = torch.where(ready[..., None, None], cnew, cQ)
            fb = fb | (f1 & ready)
        if "R" in self.estimate:
            new, cnew, f2 = project(window_mean(buf_R), s.floor_R)
            R = torch.where(ready[..., None, None], new, R)
            cR = torch.where(ready[..., None, None], cnew, cR)
            fb = fb | (f2 & ready)
        count = s.count + valid.to(s.count.dtype)
        return replace(
            s,
            Q=Q,
            chol_Q=cQ,
            R=R,
            chol_R=cR,
            count=count,
            fallback=fb,
            buf_Q=buf_Q,
            buf_R=buf_R,
            buf_valid=buf_valid,
        )
