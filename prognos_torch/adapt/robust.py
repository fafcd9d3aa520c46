"""Robust update of paper 004 (Theorem 1): bound ``gamma`` on the measurement uncertainty.

The measurement is ``y_k = C x_k + Delta E_k + v_k`` with ``Delta E_k = M F_k N``,
``F_k^T F_k <= I`` (Eq. 14). With ``nu = N^T N`` and ``lambda = (1 - nu / gamma^2)^{-1}``
(Eq. 34), the gain minimising the covariance bound is (Eq. 35, equivalently Eq. 29)

    K = P C^T (C P C^T + (gamma^2 - nu) M M^T + (1 - nu / gamma^2) R)^{-1}

and the bound itself is (Eq. 28)

    P_k = lambda (I - K C) P (I - K C)^T + gamma^2 K M M^T K^T + K R K^T.

Eq. 29's ``N_M`` is garbled in the extracted text ("NM = gamma2 NNT - NTN MMT"); substituting
Eq. 34 into Eq. 35 gives ``N_M = (gamma^2 - N^T N) M M^T``, which is what we use. For a
nonlinear ``h`` the terms ``C P C^T`` and ``(I - K C) P (I - K C)^T`` are the sigma-point
(statistically linearised) ones, as in the paper's RUKF steps 1-3. ``N`` is a scalar, as in the
paper's simulation (``N = 1``); ``M`` is ``(m,)`` or ``(m, j)``.

Two readings (``form``):

- ``"scalar"`` (default) — Eq. 28-29 as printed: the scalar ``lambda`` multiplies the whole propagated
  covariance at every update. With the paper's ``gamma = 1.05``, ``N = 1`` that is a factor
  ``10.76`` per step, and the filter diverges on the paper's own train model
  (``docs/RESULTS.md``, arukf-hst).
- ``"lemma"`` — Lemma 1 applied with ``U = P_{k|k-1}`` and ``chi_3 = N``, which is what
  the proof of Theorem 1 needs when the uncertainty acts on the prediction error
  (``Delta E_k = M F_k N psi~_{k|k-1}``): the prior is replaced by the bound
  ``P~ = (P^{-1} - gamma^{-2} N^T N)^{-1}`` (requires ``gamma^2 I - N P N^T > 0``, Eq. 25/42),
  and then ``K = P~ C^T (C P~ C^T + gamma^2 M M^T + R)^{-1}``,
  ``P_k = (I - K C) P~ (I - K C)^T + gamma^2 K M M^T K^T + K R K^T``. This is the classical
  robust Kalman bound; it reduces to the UKF for ``M = 0, N = 0``. ``N`` is then a scalar
  (``N I``) or an ``(l, n)`` matrix.

The scale of the scalar form (``bound``). The proof of Theorem 1 (Eq. 31-33) bounds the
cross terms of ``a = (I - K C) psi~_{k|k-1}`` and ``b = K M F_k N`` by the scalar inequality
``(a + b)(a + b)^T <= (1 + eps) a a^T + (1 + 1/eps) b b^T`` (any ``eps > 0``; this is what
Lemma 1, Eq. 26, gives for a scalar ``chi_3``), with ``b b^T <= nu K M M^T K^T``. With
``alpha = 1 / gamma^2`` and ``t = nu alpha in (0, 1)`` Eq. 27 is ``t < 1``, Eq. 34 is
``lambda = 1 + eps = 1 / (1 - t)`` and Eq. 28's ``gamma^2`` is ``nu (1 + 1/eps) = nu / t``:
the printed ``gamma`` *is* a choice of ``eps``, and every ``t in (0, 1)`` gives a valid bound
``Sigma_k <= P_k(t)`` with its own minimising gain (Eq. 35),

    P_k(t) = (1 - t)^{-1} (I - K C) P (I - K C)^T + (nu / t) K M M^T K^T + K R K^T,
    K(t)   = P C^T (C P C^T + nu (1 - t) / t M M^T + (1 - t) R)^{-1}.

``bound="printed"`` keeps ``t = nu / gamma^2`` (Eq. 28-29 as printed); ``bound="optimised"``
chooses ``t`` at each step, per batch element, to minimise ``trace P_k(t)``, the tightest bound
the printed theorem allows. With the optimal gain ``P_k(t) = (1 - t)^{-1} (P - P_xz S(t)^{-1}
P_xz^T)``, ``S(t) = P_zz + nu (1 - t) / t M M^T + (1 - t) R``, so each trial costs one ``(m, m)``
Cholesky and triangular solves (the ``M M^T`` term by Woodbury, well conditioned as
``t -> 0``); the search is a grid in ``logit t = log eps`` followed by zoomed grids
around the best point (fixed sizes, batched, no host synchronisation). With ``N = 0`` there is
no uncertainty and the optimised bound is the UKF.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from ..core.linalg import tria
from ..core.validation import as_tensor, is_int, is_real

__all__ = ["RobustBound"]


@dataclass(frozen=True)
class RobustBound:
    """Robust-update configuration (paper 004 Theorem 1).

    Attributes:
        gamma: robust bound, a positive number; must satisfy ``gamma^2 > N^2`` (Eq. 27).
            Paper 004 uses 1.05.
        M: ``(m,)`` or ``(m, j)`` uncertainty direction.
        N: scalar uncertainty gain (``form="lemma"``: or an ``(l, n)`` tensor).
        form: ``"scalar"`` (Eq. 28-29) or ``"lemma"`` (module docstring).
        bound: ``"printed"`` (``t = N^2 / gamma^2``) or ``"optimised"`` (``t`` chosen per step
            to minimise ``trace P_k``; ``form="scalar"`` only, ``gamma`` then unused).
        search: grid sizes of the ``"optimised"`` search: the first over ``logit t`` in
            ``span``, each further one over the two neighbouring cells of the best point.
        span: ``(lo, hi)`` range of ``logit t`` of the first grid.
    """

    gamma: float
    M: Tensor
    N: float | Tensor = 1.0
    form: str = "scalar"
    bound: str = "printed"
    search: tuple[int, ...] = (33, 9, 9, 9, 9)
    span: tuple[float, float] = (-30.0, 14.0)

    def __post_init__(self):
        if self.form not in ("lemma", "scalar"):
            raise ValueError(f"form must be 'scalar' or 'lemma', got {self.form!r}")
        if self.bound not in ("printed", "optimised"):
            raise ValueError(f"bound must be 'printed' or 'optimised', got {self.bound!r}")
        # gamma and a scalar N as Python floats: a NumPy float32 squared in float32 arithmetic
        # (gamma**2, 1 - nu / gamma^2) moved the coefficients by 1e-7 relative
        if not is_real(self.gamma):
            raise TypeError(f"gamma must be a real number, got {type(self.gamma).__name__}")
        object.__setattr__(self, "gamma", float(self.gamma))
        if isinstance(self.N, Tensor):
            if self.N.dim() != 2:
                raise ValueError(
                    "N must be a real number or an (l, n) tensor (form='lemma'), got a tensor "
                    f"of shape {tuple(self.N.shape)}"
                )
        elif is_real(self.N):
            object.__setattr__(self, "N", float(self.N))
        else:
            raise TypeError(
                f"N must be a real number or an (l, n) tensor, got {type(self.N).__name__}"
            )
        M = as_tensor(self.M, "M")  # (TypeError naming M for None, text, ...)
        if M.dim() not in (1, 2):
            raise ValueError(f"M must have shape (m,) or (m, j), got {tuple(M.shape)}")
        # non-finite settings: NaN estimates (scalar form) or a misleading "gamma too small"
        # (lemma form) at the first step otherwise
        if self.bound == "printed" and not math.isfinite(self.gamma):
            raise ValueError(f"gamma must be a finite number, got {self.gamma}")
        N = self.N if isinstance(self.N, Tensor) else torch.as_tensor(self.N)
        if not bool(torch.isfinite(N).all()):
            raise ValueError(f"N must be finite, got {self.N}")
        if not bool(torch.isfinite(M).all()):
            raise ValueError(f"M must be finite, got {self.M}")
        if self.bound == "optimised":
            if self.form != "scalar":
                raise ValueError("bound='optimised' needs form='scalar' (Eq. 28-29)")
            if isinstance(self.N, Tensor):
                raise ValueError("bound='optimised' takes a scalar N")
            search = self.search
            if (
                not isinstance(search, (tuple, list))
                or len(search) < 1
                or not all(is_int(g) and g >= 3 for g in search)
            ):
                raise ValueError(f"search must be a tuple of int grid sizes >= 3, got {search!r}")
            object.__setattr__(self, "search", tuple(int(g) for g in search))
            span = self.span
            if (
                not isinstance(span, (tuple, list))
                or len(span) != 2
                or not all(is_real(v) and math.isfinite(v) for v in span)
                or not span[0] < span[1]
            ):
                raise ValueError(
                    f"span must be (lo, hi), two finite numbers with lo < hi, got {span!r}"
                )
            object.__setattr__(self, "span", (float(span[0]), float(span[1])))
            return
        if not self.gamma > 0:  # Theorem 1: a positive constant gamma
            raise ValueError(f"gamma must be positive, got {self.gamma}")
        if self.form == "lemma":
            return
        if isinstance(self.N, Tensor):
            raise ValueError("form='scalar' takes a scalar N (paper 004's simulation: N = 1)")
        if not self.gamma**2 > self.N**2:
            raise ValueError(
                f"gamma must satisfy gamma^2 > N^2 (paper 004 Eq. 27), got gamma={self.gamma}, "
                f"N={self.N}"
            )

    def coefficients(self, t: Tensor | None = None) -> tuple:
        """``(c_M, c_R, c_P, c_K)``: the innovation factor is ``Tria([Z, c_M M, c_R S_R])`` and
        the posterior factor ``Tria([c_P (chi - K Z), c_K K M, K S_R])`` (Eq. 28-29).

        For the scalar form ``c_M = sqrt(nu (1 - t) / t)``, ``c_R = sqrt(1 - t)``,
        ``c_P = (1 - t)^{-1/2}``, ``c_K = sqrt(nu / t)``; ``t = nu / gamma^2`` (printed: floats
        ``sqrt(gamma^2 - nu)``, ``sqrt(1 - nu / gamma^2)``, ``sqrt(lambda)``, ``gamma``) or a
        ``(...)`` tensor from :meth:`choose_t` (optimised: tensors ``(..., 1, 1)``)."""
        if self.form == "lemma":
            return self.gamma, 1.0, 1.0, self.gamma
        nu = self.nu
        if t is None:
            if self.bound == "optimised":
                raise ValueError("the optimised bound needs t from choose_t()")
            g2 = self.gamma**2
            return math.sqrt(g2 - nu), math.sqrt(1.0 - nu / g2), math.sqrt(self.lam), self.gamma
        t = t[..., None, None]
        one = 1.0 - t
        if nu == 0:
            z = torch.zeros_like(t)
            return z, torch.ones_like(t), torch.ones_like(t), z
        return (nu * one / t).sqrt(), one.sqrt(), one.rsqrt(), (nu / t).sqrt()

    def bound_trace(self, t: Tensor, trace_P: Tensor, Pxz: Tensor, Pzz: Tensor, RR: Tensor):
        """``trace P_k(t)`` of the scalar bound with the gain of Eq. 35 (module docstring).

        Args:
            t: ``(..., G)`` trial values in ``(0, 1)``.
            trace_P: ``(...)`` trace of the prior (``P_{k|k-1}``, or the bound ``P~``).
            Pxz: ``(..., n, m)`` cross covariance; Pzz: ``(..., m, m)`` (``C P C^T``);
            RR: ``(..., m, m)`` measurement-noise covariance.
        Returns:
            ``(..., G)``; ``inf`` where ``S(t)`` is not positive definite.
        """
        m = Pzz.shape[-1]
        M = self.M_matrix(m, Pzz.dtype, Pzz.device)
        tt = t[..., None, None]
        A = Pzz[..., None, :, :] + (1.0 - tt) * RR[..., None, :, :]
        L, info = torch.linalg.cholesky_ex(A)
        X = torch.linalg.solve_triangular(L, Pxz.mT[..., None, :, :], upper=False)
        g = X.square().sum((-2, -1))  # trace P_xz A^{-1} P_xz^T
        if self.nu > 0:  # Woodbury for the c M M^T term, c = nu (1 - t) / t (large as t -> 0)
            Y = torch.linalg.solve_triangular(L, M.expand(*L.shape[:-1], M.shape[-1]), upper=False)
            eye = torch.eye(M.shape[-1], dtype=M.dtype, device=M.device)
            G = Y.mT @ Y + (tt / (self.nu * (1.0 - tt))) * eye
            LG, info_g = torch.linalg.cholesky_ex(G)
            Z = torch.linalg.solve_triangular(LG, Y.mT @ X, upper=False)
            g = g - Z.square().sum((-2, -1))
            info = info + info_g
        f = (trace_P[..., None] - g) / (1.0 - t)
        return torch.where(info == 0, f, torch.full_like(f, math.inf))

    def choose_t(self, trace_P: Tensor, Pxz: Tensor, Pzz: Tensor, RR: Tensor) -> Tensor:
        """The ``t = N^2 / gamma^2`` of each batch element minimising :meth:`bound_trace`
        (``bound="optimised"``): a grid of ``search[0]`` points over ``logit t`` in ``span``,
        then, per further entry of ``search``, a grid over the two cells next to the best point,
        and one parabolic step through the best point and its neighbours. Returns ``(...)``."""
        lo, hi = self.span
        dt, dev = Pzz.dtype, Pzz.device
        bs = Pzz.shape[:-2]
        u = torch.linspace(lo, hi, self.search[0], dtype=dt, device=dev).expand(*bs, -1)
        h = (hi - lo) / (self.search[0] - 1)
        best = None
        for i, G in enumerate(self.search):
            if i > 0:
                s = torch.linspace(-h, h, G, dtype=dt, device=dev)
                u = best[..., None] + s
                h = 2 * h / (G - 1)
            f = self.bound_trace(torch.sigmoid(u), trace_P, Pxz, Pzz, RR)
            j = f.argmin(-1, keepdim=True)
            best, f_best = u.gather(-1, j).squeeze(-1), f.gather(-1, j).squeeze(-1)
        # one parabolic step through the best point and its two neighbours (spacing h)
        three = best[..., None] + torch.tensor([-h, 0.0, h], dtype=dt, device=dev)
        f0, f1, f2 = self.bound_trace(torch.sigmoid(three), trace_P, Pxz, Pzz, RR).unbind(-1)
        curv = f0 - 2 * f1 + f2
        ok = torch.isfinite(curv) & (curv > 0)
        step = torch.where(ok, 0.5 * h * (f0 - f2) / torch.where(ok, curv, 1.0), 0.0)
        cand = best + step.clamp(-h, h)
        f_cand = self.bound_trace(torch.sigmoid(cand)[..., None], trace_P, Pxz, Pzz, RR)[..., 0]
        return torch.sigmoid(torch.where(f_cand < f_best, cand, best))

    def inflate(self, S: Tensor) -> Tensor:
        """Square root of ``P~ = (P^{-1} - gamma^{-2} N^T N)^{-1}`` for ``P = S S^T`` (``"lemma"``;
        identity for ``"scalar"``). Written as ``P~ = S (I - gamma^{-2} B^T B)^{-1} S^T`` with
        ``B = N S``: one small Cholesky and one triangular solve, no inverse of ``P``."""
        if self.form != "lemma":
            return S
        N = self.N
        n = S.shape[-1]
        if isinstance(N, Tensor):
            if N.shape[-1] != n:
                raise ValueError(
                    f"RobustBound.N must have shape (l, n) with n={n} (the state dimension), "
                    f"got {tuple(N.shape)}"
                )
            B = N.to(dtype=S.dtype, device=S.device) @ S
        elif N == 0:
            return S
        else:
            B = N * S
        A = torch.eye(n, dtype=S.dtype, device=S.device) - (B.mT @ B) / self.gamma**2
        L, info = torch.linalg.cholesky_ex(A)
        if bool((info > 0).any()):
            raise ValueError(
                f"robust bound gamma={self.gamma} is too small for the current covariance: "
                "gamma^2 I - N P N^T must be positive definite (paper 004 Eq. 25/42)"
            )
        X = torch.linalg.solve_triangular(L, S.mT, upper=False)  # L^{-1} S^T
        return tria(X.mT)

    @property
    def nu(self) -> float:
        return float(self.N) ** 2

    @property
    def lam(self) -> float:
        """``lambda = (1 - N^T N / gamma^2)^{-1}`` (Eq. 34)."""
        return 1.0 / (1.0 - self.nu / self.gamma**2)

    def M_matrix(self, m: int, dtype, device) -> Tensor:
        M = torch.as_tensor(self.M, dtype=dtype, device=device)
        if M.dim() == 1:
            M = M.unsqueeze(-1)
        if M.shape[0] != m:
            raise ValueError(
                f"RobustBound.M must have shape (m,) or (m, j) with m={m}, got {tuple(M.shape)}"
            )
        return M
