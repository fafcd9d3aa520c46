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
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

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
    N: float = 1.0

    def __post_init__(self):
        if not self.gamma**2 > self.N**2:
            raise ValueError(
                f"gamma must satisfy gamma^2 > N^2 (paper 004 Eq. 27), got gamma={self.gamma}, "
                f"N={self.N}"
            )

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
