"""Strong tracking: the suboptimal fading factor ``lambda_k`` (paper 000, Sec. 3).

The fading factor inflates the propagated part of the predicted covariance,
``P_{k|k-1} = lambda_k F P F^T + Q`` (square-root form: ``S = Tria([sqrt(lambda_k) chi*, S_Q])``,
paper 000 Eq. 36), to keep the innovations orthogonal (Eq. 6) when the model is wrong.

Jacobian form (SFEKF, Eq. 7-12) and derivative-free form (Eq. 17-20, 27-35) share one formula:

    N_k = V_k - H Q H^T - beta R_k                                  (Eq. 8; beta: weakening factor)
    M_k = P_zz^(l) - R_k - H Q H^T   ( = H F P F^T H^T, Eq. 9/20)
    lambda_k = max(1, tr N_k / tr M_k)                              (Eq. 7)

where ``P_zz^(l)`` is the innovation covariance under the *unfaded* prior and ``H`` is the
measurement Jacobian (EKF) or its statistical linearisation ``H = P_xz^T (P^(l))^{-1}``
(Eq. 17). Note: the extracted Eq. 35 writes ``M_k = Z Z^T - V_k + N_k`` with ``Z Z^T`` lacking
``R``; Eq. 20, from which it is derived, uses ``P_zz`` *with* ``R``. We follow the derivation
(Eq. 20): otherwise ``M_k`` would be ``H F P F^T H^T - R`` and could be negative.

``V_k`` (Eq. 10) is the innovation covariance estimated with forgetting factor ``rho``:
``V_1 = e_1 e_1^T``, ``V_k = (rho V_{k-1} + e_k e_k^T) / (1 + rho)`` (the ``1 + rho``
denominator is garbled in the extracted Eq. 10-11; it is Zhou's standard form).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from ..core.linalg import cho_solve_right, mm
from ..core.validation import is_real

__all__ = ["StrongTracking", "StrongTrackingState", "fading_factor"]


@dataclass(frozen=True)
class StrongTracking:
    """Strong-tracking configuration.

    Attributes:
        rho: forgetting factor of ``V_k`` in ``(0, 1]`` (Eq. 10); 0.95 is customary.
        beta: weakening (softening) factor multiplying ``R`` in ``N_k``, any positive finite
            number; ``>= 1`` is customary: larger values make the fading factor less aggressive
            (smoother estimates), values below 1 more aggressive.
        max_factor: optional upper bound on ``lambda_k`` (``None``: unbounded, as in the paper).
    """

    rho: float = 0.95
    beta: float = 1.0
    max_factor: float | None = None

    def __post_init__(self):
        for name in ("rho", "beta", "max_factor"):
            v = getattr(self, name)
            if name == "max_factor" and v is None:
                continue
            if not is_real(v):
                raise TypeError(
                    f"{name} must be a real number (one value for every batch element), "
                    f"got {type(v).__name__}"
                )
            # a Python float: a NumPy float32 rho gave 1 + rho in float32 arithmetic (Eq. 10's
            # denominator), lambda_k 1e-7 relative off the same value given as a float
            object.__setattr__(self, name, float(v))
        if not 0.0 < self.rho <= 1.0:
            raise ValueError(f"rho must be in (0, 1], got {self.rho}")
        if not self.beta > 0 or self.beta == math.inf:  # (NaN fails every comparison)
            raise ValueError(
                f"beta (weakening factor) must be a positive finite number, got {self.beta}"
            )
        if self.max_factor is not None and not self.max_factor >= 1:
            raise ValueError(f"max_factor must be >= 1, got {self.max_factor}")

    def init(self, batch_shape: torch.Size, m: int, dtype, device) -> StrongTrackingState:
        V = torch.zeros(*batch_shape, m, m, dtype=dtype, device=device)
        started = torch.zeros(batch_shape, dtype=torch.bool, device=device)
        return StrongTrackingState(V=V, started=started)


@dataclass(frozen=True)
class StrongTrackingState:
    """``V``: ``(..., m, m)`` innovation covariance estimate; ``started``: ``(...)`` bool."""

    V: Tensor
    started: Tensor


def _sum_sq(A: Tensor) -> Tensor:
    """``sum(A * A)`` over the last two dims; of a 1 x 1 ``A`` the entry of ``A * A`` (a
    square is >= +0, so the one-element sum is that entry: the same numbers)."""
    A2 = A * A
    return A2[..., 0, 0] if A.shape[-2:] == (1, 1) else A2.sum((-2, -1))


def fading_factor(
    cfg: StrongTracking,
    state: StrongTrackingState,
    innovation: Tensor,
    missing: Tensor,
    H: Tensor,
    chol_Q: Tensor,
    chol_R: Tensor,
    chol_prior: Tensor,
    pzz_noR_trace: Tensor,
    pxz: Tensor | None = None,
    any_missing: bool = True,
) -> tuple[Tensor, StrongTrackingState]:
    """One fading-factor computation (paper 000 Eq. 7-10 with Eq. 18/20 or 35).

    Args:
        innovation: ``(..., m)`` innovation under the unfaded prior (Eq. 11).
        missing: ``(...)`` bool; where true, ``lambda = 1`` and ``V`` is kept.
        H: ``(..., m, n)`` Jacobian, or ``None`` to use ``H = P_xz^T P^{-1}`` (Eq. 17).
        chol_Q: ``(..., n, n)``; chol_R: ``(..., m, m)``; chol_prior: ``(..., n, n)`` unfaded prior.
        pzz_noR_trace: ``(...)`` trace of ``P_zz^(l) - R``.
        pxz: ``(..., n, m)`` cross covariance (needed when ``H`` is ``None``).
        any_missing: ``False`` when ``missing`` is known to be all false (the masking is then
            skipped; the same numbers).
    Returns:
        ``lambda_k`` ``(...)`` and the new state.
    """
    e = innovation.unsqueeze(-1)
    eeT = e * e.mT  # outer product e e^T
    V_new = torch.where(
        state.started[..., None, None], (cfg.rho * state.V + eeT) / (1.0 + cfg.rho), eeT
    )
    if H is None:
        H = cho_solve_right(pxz.mT, chol_prior)  # Eq. 17: H = P_xz^T P^{-1}, by two solves
    HSQ = mm(H, chol_Q)
    trHQH = _sum_sq(HSQ)
    trR = _sum_sq(chol_R)
    m = V_new.shape[-1]
    # (entries of V are >= +0: the one-element sum of a 1 x 1 V is its entry)
    trV = V_new[..., 0, 0] if m == 1 else torch.diagonal(V_new, dim1=-2, dim2=-1).sum(-1)
    trN = trV - trHQH
    trN = trN - (trR if cfg.beta == 1.0 else cfg.beta * trR)  # (1.0 * trR is trR)
    trM = pzz_noR_trace - trHQH
    # lambda = trN / trM where trM > 0 and the ratio exceeds 1, else 1: dividing by +inf where
    # trM <= 0 gives 0 or NaN there, neither > 1 (the same numbers as masking twice)
    lam0 = trN / torch.where(trM > 0, trM, math.inf)
    lam = torch.where(lam0 > 1.0, lam0, 1.0)
    if cfg.max_factor is not None:
        lam = lam.clamp(max=cfg.max_factor)
    if not any_missing:
        return lam, StrongTrackingState(V=V_new, started=torch.ones_like(state.started))
    lam = torch.where(missing, 1.0, lam)
    V = torch.where(missing[..., None, None], state.V, V_new)
    started = state.started | ~missing
    return lam, StrongTrackingState(V=V, started=started)
