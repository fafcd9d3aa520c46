"""Square-root linear algebra: ``tria`` via QR, Cholesky rank-one up/downdates, safe Cholesky.

All functions act on the last two dimensions and broadcast over leading batch dimensions.
Nothing here forms an explicit inverse; triangular factors are applied with solves.
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = [
    "tria",
    "chol_update",
    "chol_downdate",
    "safe_cholesky",
    "cho_solve_right",
    "symmetrize",
]


def tria(A: Tensor) -> Tensor:
    """Lower-triangular square root of ``A A^T`` (paper 000 Eq. 25: ``S = Tria(C)``).

    ``A`` has shape ``(..., n, L)`` (any ``L``; zero columns are added when ``L < n``). With
    ``A^T = Q R`` (reduced QR),
    ``A A^T = R^T R`` and ``S = R^T`` is lower triangular. The sign of each column is fixed so
    that ``diag(S) >= 0``, which makes the factor unique and equal to ``cholesky(A A^T)``.

    Args:
        A: ``(..., n, L)``.
    Returns:
        ``(..., n, n)`` lower triangular with non-negative diagonal.
    """
    n, L = A.shape[-2], A.shape[-1]
    if L < n:  # pad with zero columns so that R is square
        A = torch.cat([A, A.new_zeros(*A.shape[:-1], n - L)], dim=-1)
    R = torch.linalg.qr(A.mT, mode="r").R  # (..., n, n) upper
    S = R.mT
    d = torch.diagonal(S, dim1=-2, dim2=-1)
    return S * torch.where(d < 0, -1.0, 1.0).unsqueeze(-2)


def chol_update(S: Tensor, V: Tensor) -> Tensor:
    """Cholesky update: ``S' S'^T = S S^T + V V^T`` for ``V`` of shape ``(..., n)`` or ``(..., n, k)``.

    A rank-k update is done with one QR (``tria([S, V])``), which is both faster and more
    stable than k sequential rank-one updates.
    """
    if V.dim() == S.dim() - 1:
        V = V.unsqueeze(-1)
    return tria(torch.cat([S, V], dim=-1))


def chol_downdate(S: Tensor, V: Tensor) -> Tensor:
    """Cholesky downdate: ``S' S'^T = S S^T - V V^T`` (``V``: ``(..., n)`` or ``(..., n, k)``).

    Written as ``S S^T - V V^T = S (I - W W^T) S^T`` with ``W = S^{-1} V`` (a triangular solve), so
    ``S' = S chol(I - W W^T)``: one small, well-conditioned Cholesky instead of k sequential
    rank-one downdates, and the same result (Van der Merwe's ``cholupdate(S, u, '-')``).
    Raises ``torch.linalg.LinAlgError`` when the result would not be positive definite.
    """
    if V.dim() == S.dim() - 1:
        V = V.unsqueeze(-1)
    W = torch.linalg.solve_triangular(S, V, upper=False)
    eye = torch.eye(S.shape[-1], dtype=S.dtype, device=S.device)
    L, info = torch.linalg.cholesky_ex(eye - W @ W.mT)
    if bool((info > 0).any()):
        raise torch.linalg.LinAlgError(
            "Cholesky downdate failed: the downdated matrix is not positive definite"
        )
    return S @ L


def symmetrize(P: Tensor) -> Tensor:
    """``(P + P^T) / 2``."""
    return 0.5 * (P + P.mT)


def safe_cholesky(P: Tensor, *, jitter: float = 0.0, max_tries: int = 6) -> Tensor:
    """Lower Cholesky factor of a symmetric matrix, with optional escalating diagonal jitter.

    With ``jitter == 0`` a failure raises ``torch.linalg.LinAlgError``. With ``jitter > 0``
    the jitter (relative to the mean diagonal) is multiplied by 10 up to ``max_tries`` times.
    """
    P = symmetrize(P)
    L, info = torch.linalg.cholesky_ex(P)
    if not bool((info > 0).any()):
        return L
    if jitter <= 0:
        raise torch.linalg.LinAlgError("matrix is not positive definite")
    scale = torch.diagonal(P, dim1=-2, dim2=-1).abs().mean(-1, keepdim=True).clamp_min(1e-300)
    eye = torch.eye(P.shape[-1], dtype=P.dtype, device=P.device)
    eps = jitter
    for _ in range(max_tries):
        L, info = torch.linalg.cholesky_ex(P + (eps * scale).unsqueeze(-1) * eye)
        if not bool((info > 0).any()):
            return L
        eps *= 10.0
    raise torch.linalg.LinAlgError("matrix is not positive definite, even with jitter")


def cho_solve_right(B: Tensor, S: Tensor) -> Tensor:
    """``B (S S^T)^{-1}`` for lower ``S`` by two triangular solves (paper 000 Eq. 44: ``(B/S^T)/S``).

    ``B``: ``(..., n, m)``, ``S``: ``(..., m, m)`` lower. Returns ``(..., n, m)``.
    """
    # X S S^T = B  <=>  S S^T X^T = B^T
    Y = torch.linalg.solve_triangular(S, B.mT, upper=False)
    return torch.linalg.solve_triangular(S.mT, Y, upper=True).mT
