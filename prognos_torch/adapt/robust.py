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
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from ..core.linalg import tria

__all__ = ["RobustBound"]


@dataclass(frozen=True)
class RobustBound:
    """Robust-update configuration (paper 004 Theorem 1).

    Attributes:
        gamma: robust bound; must satisfy ``gamma^2 > N^2`` (Eq. 27). Paper 004 uses 1.05.
        M: ``(m,)`` or ``(m, j)`` uncertainty direction.
        N: scalar uncertainty gain.
    """

    gamma: float
    M: Tensor
    N: float | Tensor = 1.0
    form: str = "scalar"

    def __post_init__(self):
        if self.form not in ("lemma", "scalar"):
            raise ValueError(f"form must be 'scalar' or 'lemma', got {self.form!r}")
        if self.form == "lemma":
            if not self.gamma > 0:
                raise ValueError(f"gamma must be positive, got {self.gamma}")
            return
        if isinstance(self.N, Tensor):
            raise ValueError("form='scalar' takes a scalar N (paper 004's simulation: N = 1)")
        if not self.gamma**2 > self.N**2:
            raise ValueError(
                f"gamma must satisfy gamma^2 > N^2 (paper 004 Eq. 27), got gamma={self.gamma}, "
                f"N={self.N}"
            )

    def coefficients(self) -> tuple[float, float, float]:
        """``(c_M, c_R, c_P)``: the innovation factor is ``Tria([Z, c_M M, c_R S_R])`` and the
        posterior factor ``Tria([c_P (chi - K Z), gamma K M, K S_R])``."""
        if self.form == "lemma":
            return self.gamma, 1.0, 1.0
        g2, nu = self.gamma**2, self.nu
        return math.sqrt(g2 - nu), math.sqrt(1.0 - nu / g2), math.sqrt(self.lam)

    def inflate(self, S: Tensor) -> Tensor:
        """Square root of ``P~ = (P^{-1} - gamma^{-2} N^T N)^{-1}`` for ``P = S S^T`` (``"lemma"``;
        identity for ``"scalar"``). Written as ``P~ = S (I - gamma^{-2} B^T B)^{-1} S^T`` with
        ``B = N S``: one small Cholesky and one triangular solve, no inverse of ``P``."""
        if self.form != "lemma":
            return S
        N = self.N
        if isinstance(N, Tensor):
            B = N.to(dtype=S.dtype, device=S.device) @ S
        else:
            B = float(N) * S
        if isinstance(N, (int, float)) and N == 0:
            return S
        n = S.shape[-1]
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
