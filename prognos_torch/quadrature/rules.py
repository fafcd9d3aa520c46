"""Sigma-point rules: unit points ``xi_i`` and weights for ``E[g(x)]``, ``x ~ N(m, S S^T)``.

A rule places points ``X_i = m + S xi_i`` and approximates ``E[g] = sum_i wm_i g(X_i)`` and
``Cov[g] = sum_i wc_i (g(X_i) - E[g])(g(X_i) - E[g])^T``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
import torch
from torch import Tensor

from ..core.validation import check_setting, is_int

__all__ = ["SigmaPoints", "unscented", "julier", "cubature", "gauss_hermite"]


@dataclass(frozen=True)
class SigmaPoints:
    """A sigma-point rule; ``points(n)`` returns unit points ``(L, n)`` and weights ``(L,)``.

    Attributes:
        kind: ``"unscented"``, ``"cubature"`` or ``"gauss_hermite"``.
        alpha, beta, kappa: scaled unscented parameters (Van der Merwe); ``kappa=None`` means
            Julier's ``3 - n``.
        order: points per dimension of the Gauss-Hermite product rule.
    """

    kind: str
    alpha: float = 1.0
    beta: float = 0.0
    kappa: float | None = 0.0
    order: int = 3

    def __post_init__(self):
        if self.kind not in ("unscented", "cubature", "gauss_hermite"):
            raise ValueError(f"unknown sigma-point rule kind {self.kind!r}")
        for name in ("alpha", "beta") + (() if self.kappa is None else ("kappa",)):
            check_setting(getattr(self, name), name)
            # a Python float (a NumPy float32 kappa computed the weights in float32)
            object.__setattr__(self, name, float(getattr(self, name)))
        if self.kind == "unscented" and self.alpha == 0:
            raise ValueError("alpha must be nonzero (the points collapse onto the mean)")
        o = self.order
        if not is_int(o) or o < 2:
            # one point per dimension is the mean alone: zero spread, no update ever
            raise ValueError(f"order must be an int >= 2, got {o!r}")
        object.__setattr__(self, "order", int(o))

    def points(self, n: int, dtype=torch.float64, device=None) -> tuple[Tensor, Tensor, Tensor]:
        """Unit points ``xi`` ``(L, n)``, mean weights ``wm`` ``(L,)``, covariance weights ``wc``
        (new tensors each call: editing them leaves the rule unchanged)."""
        if not is_int(n) or n < 1:
            raise ValueError(f"n (the state dimension) must be an int >= 1, got {n!r}")
        xi, wm, wc = _points(self.kind, self.alpha, self.beta, self.kappa, self.order, int(n))
        # a copy: the cached arrays must not share memory with tensors handed out
        t = lambda a: torch.tensor(a, dtype=dtype, device=device)  # noqa: E731
        return t(xi), t(wm), t(wc)


@lru_cache(maxsize=256)
def _points(kind, alpha, beta, kappa, order, n):
    if kind == "unscented":
        k = (3.0 - n) if kappa is None else float(kappa)
        lam = alpha**2 * (n + k) - n  # scaled UT; alpha = 1 gives Julier's kappa (paper 003 Eq. 12)
        c = n + lam
        if c <= 0:
            raise ValueError(f"unscented rule needs alpha^2 (n + kappa) > 0, got n={n}, kappa={k}")
        xi = np.concatenate([np.zeros((1, n)), math.sqrt(c) * np.eye(n), -math.sqrt(c) * np.eye(n)])
        wm = np.full(2 * n + 1, 1.0 / (2.0 * c))
        wc = wm.copy()
        wm[0] = lam / c  # paper 003 Eq. 13: W_0 = kappa / (n + kappa), W_i = 1 / (2 (n + kappa))
        wc[0] = lam / c + 1.0 - alpha**2 + beta
        return xi, wm, wc
    if kind == "cubature":
        # third-degree spherical-radial rule (paper 000 Eq. 22): xi = +-sqrt(n) e_i, w = 1 / 2n
        xi = np.concatenate([math.sqrt(n) * np.eye(n), -math.sqrt(n) * np.eye(n)])
        w = np.full(2 * n, 1.0 / (2 * n))
        return xi, w, w.copy()
    if kind == "gauss_hermite":
        if order**n > 100_000:
            raise ValueError(f"Gauss-Hermite rule with order={order} in n={n} has too many points")
        x1, w1 = np.polynomial.hermite_e.hermegauss(order)  # probabilists' Hermite: N(0, 1)
        w1 = w1 / w1.sum()
        grids = np.meshgrid(*([x1] * n), indexing="ij")
        xi = np.stack([g.ravel() for g in grids], axis=-1)
        wg = np.meshgrid(*([w1] * n), indexing="ij")
        w = np.prod(np.stack([g.ravel() for g in wg], axis=-1), axis=-1)
        return xi, w, w.copy()
    raise ValueError(f"unknown sigma-point rule kind {kind!r}")


def unscented(alpha: float = 1.0, beta: float = 2.0, kappa: float | None = 0.0) -> SigmaPoints:
    """Scaled unscented rule (Van der Merwe): ``2n + 1`` points, ``lambda = alpha^2 (n + kappa) - n``."""
    # (checked by SigmaPoints: float() here gave its own message for text and read True as 1)
    return SigmaPoints("unscented", alpha=alpha, beta=beta, kappa=kappa)


def julier(kappa: float | None = 1.0) -> SigmaPoints:
    """Julier's unscented rule (paper 003 Eq. 12-13): ``W_0 = kappa / (n + kappa)``.

    ``kappa=None`` uses the classic ``3 - n``; paper 003 uses ``kappa = 1``.
    """
    return SigmaPoints("unscented", alpha=1.0, beta=0.0, kappa=kappa)


def cubature() -> SigmaPoints:
    """Third-degree cubature rule of the CKF / SCKF (paper 000 Eq. 21-22): ``2n`` equal-weight points."""
    return SigmaPoints("cubature")


def gauss_hermite(order: int = 3) -> SigmaPoints:
    """Gauss-Hermite product rule with ``order`` points per dimension (``order^n`` points)."""
    return SigmaPoints("gauss_hermite", order=order)
