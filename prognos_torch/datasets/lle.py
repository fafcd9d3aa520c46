"""Locally linear embedding (Roweis & Saul, Science 290, 2000), as used by paper 002.

Paper 002 (Sec. "Experiments", Fig. 7) reduces the seven per-snapshot time-domain features of
IMS bearing 3 to a one-dimensional monitoring index with LLE and 12 nearest neighbours. The paper
gives no formulas for LLE; this module implements the standard algorithm of its reference 31:

1. for every point ``x_i`` find its ``K`` nearest neighbours (Euclidean, the point itself
   excluded);
2. reconstruction weights: minimise ``|x_i - sum_j w_ij x_j|^2`` subject to ``sum_j w_ij = 1``.
   With ``Z = [x_j - x_i]_j`` (K, D) and the local Gram matrix ``C = Z Z^T`` (K, K) the solution
   is ``w = C^{-1} 1 / (1^T C^{-1} 1)``. ``C`` is singular whenever ``K > D`` (paper 002: K = 12,
   D = 7), so it is regularised, ``C + reg * trace(C) * I`` (Roweis & Saul's note; the same
   rule as scikit-learn);
3. embedding: the ``d`` eigenvectors of ``M = (I - W)^T (I - W)`` with the smallest eigenvalues
   after the constant one (eigenvalue 0), scaled to the constraint ``(1/N) sum_i y_i y_i^T = I``
   of Roweis & Saul, i.e. ``y = sqrt(N) * v``.

Out-of-sample points (:meth:`LLEFit.transform`) are mapped with the same local rule: neighbours
and reconstruction weights of the new point among the *fitted* points, then ``y = sum_j w_j y_j``
(Saul & Roweis, JMLR 4, 2003, Sec. 6.1).

Implementation choice: steps 1-2 and the assembly of ``M`` are torch (batched ``linalg.solve``,
any device and floating dtype). The eigenproblem uses ``scipy.linalg.eigh`` with
``subset_by_index`` for CPU tensors (only the ``d + 1`` wanted eigenpairs, about 5x faster than a
full decomposition at N = 1263) and ``torch.linalg.eigh`` for tensors on other devices. ``M`` is
assembled densely, (N, N): fine for the few thousand points this library meets.

The sign of an eigenvector is arbitrary; every column is flipped so that its entry of largest
magnitude is positive, the first of them (in sample order) where several lie within a relative
1e-4 of the largest (an odd embedding, e.g. of evenly spaced points on a line, has two extremes
whose magnitudes differ by rounding only, and the eigensolvers round differently). Neighbours at
equal distances (duplicate points) are taken in index order. That makes results deterministic,
not meaningful: callers that need a
direction (a health indicator that grows with degradation) fix it themselves, see
:func:`prognos_torch.datasets.ims.health_indicator`.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from typing import Literal

import numpy as np
import scipy.linalg
import scipy.sparse
import scipy.sparse.csgraph
import torch
from torch import Tensor

from ..core.validation import check_real, is_int

__all__ = [
    "LLEFit",
    "knn",
    "reconstruction_weights",
    "lle_cost_matrix",
    "lle_fit",
    "locally_linear_embedding",
]


def _check_points(X, name: str) -> Tensor:
    if not isinstance(X, Tensor):
        try:
            X = torch.as_tensor(X, dtype=torch.float64)
        except (TypeError, ValueError, RuntimeError) as exc:
            raise TypeError(f"{name} must be a tensor of shape (n, D), got {type(X)}") from exc
    if X.dim() != 2:
        raise ValueError(f"{name} must have shape (n, D), got {tuple(X.shape)}")
    if not X.is_floating_point():
        raise TypeError(f"{name} must be a floating tensor of shape (n, D), got {X.dtype}")
    if not bool(torch.isfinite(X).all()):
        raise ValueError(f"{name} (shape (n, D)) contains non-finite values")
    return X


def _check_reg(reg) -> float:
    reg = check_real(reg, "reg")
    if not reg > 0:
        raise ValueError(f"reg must be a positive float, got {reg!r}")
    return reg


def _check_k(n_neighbors, n_available: int, what: str) -> int:
    if not is_int(n_neighbors) or n_neighbors < 1:
        raise ValueError(f"n_neighbors must be a positive int, got {n_neighbors!r}")
    if n_neighbors > n_available:
        raise ValueError(f"n_neighbors={n_neighbors} exceeds the {n_available} {what} available")
    return int(n_neighbors)


def _pow2_scaled(X: Tensor, size: Tensor) -> Tensor:
    """``X * 2^-e`` with ``size = f 2^e``, ``0.5 <= f < 1`` (``torch.frexp``; ``X`` itself for
    ``size`` 0): exact, up to the factor, wherever the result is a normal number.

    ``size`` broadcasts against ``X`` (one exponent for all, or one per leading index).
    """
    e = torch.frexp(size).exponent
    if e.dim() == 0 and int(e) == 0:
        return X
    return X * torch.pow(torch.tensor(2.0, dtype=X.dtype, device=X.device), (-e).to(X.dtype))


def knn(X_ref: Tensor, X_query: Tensor | None = None, n_neighbors: int = 12) -> Tensor:
    """Indices of the ``n_neighbors`` nearest reference points (Euclidean), nearest first.

    Args:
        X_ref: reference points, shape (n, D).
        X_query: query points, shape (m, D); ``None`` queries the reference points themselves
            and excludes each point from its own neighbourhood (LLE step 1).
        n_neighbors: K.

    Returns:
        LongTensor of shape (m, K) (or (n, K)) indexing rows of ``X_ref``.
    """
    X_ref = _check_points(X_ref, "X_ref")
    self_query = X_query is None
    Q = X_ref if self_query else _check_points(X_query, "X_query")
    if Q.shape[1] != X_ref.shape[1]:
        raise ValueError(
            f"X_query must have shape (m, {X_ref.shape[1]}) like X_ref, got {tuple(Q.shape)}"
        )
    k = _check_k(n_neighbors, X_ref.shape[0] - int(self_query), "other reference points")
    # the wider of the two dtypes (X_ref.to(Q.dtype) rounded float64 references to a float32
    # query's precision, and their order with it)
    common = torch.promote_types(X_ref.dtype, Q.dtype)
    X_ref, Q = X_ref.to(common), Q.to(common)
    # One power of two for both sets keeps every distance exact up to that factor, so the order
    # is the unscaled one, while squared distances of points near 1e-160 or 1e160 would
    # underflow or overflow.
    both = X_ref.abs().amax() if self_query else torch.maximum(X_ref.abs().amax(), Q.abs().amax())
    X_ref, Q = _pow2_scaled(X_ref, both), _pow2_scaled(Q, both)
    # Exact differences (no |a|^2 + |b|^2 - 2ab shortcut) so that neighbour order is reproducible.
    dist = torch.cdist(Q, X_ref, compute_mode="donot_use_mm_for_euclid_dist")
    if self_query:
        dist.fill_diagonal_(float("inf"))
    # a stable sort: equal distances (duplicate points) in index order, on every device
    return torch.sort(dist, dim=1, stable=True).indices[:, :k]


def reconstruction_weights(
    X_ref: Tensor, neighbors: Tensor, X_query: Tensor | None = None, reg: float = 1e-3
) -> Tensor:
    """LLE reconstruction weights (step 2): ``w = C^{-1} 1 / (1^T C^{-1} 1)`` per point.

    Args:
        X_ref: reference points, shape (n, D).
        neighbors: LongTensor (m, K) of row indices into ``X_ref`` (from :func:`knn`).
        X_query: points to reconstruct, shape (m, D); ``None`` means ``X_ref`` itself (m = n).
        reg: Tikhonov regulariser relative to the trace of each local Gram matrix
            (``C + reg * trace(C) * I``; ``reg * I`` when the trace is 0).

    Returns:
        weights of shape (m, K); every row sums to one.
    """
    X_ref = _check_points(X_ref, "X_ref")
    Q = X_ref if X_query is None else _check_points(X_query, "X_query")
    if Q.shape[1] != X_ref.shape[1]:  # (a (m, 1) query was broadcast against every coordinate)
        raise ValueError(
            f"X_query must have shape (m, {X_ref.shape[1]}) like X_ref, got {tuple(Q.shape)}"
        )
    if not isinstance(neighbors, Tensor) or neighbors.dim() != 2 or neighbors.shape[0] != len(Q):
        raise ValueError(f"neighbors must be a LongTensor of shape ({len(Q)}, K)")
    if neighbors.dtype not in (torch.int64, torch.int32):
        raise TypeError(f"neighbors must be a LongTensor of row indices, got {neighbors.dtype}")
    if neighbors.numel() and not 0 <= int(neighbors.min()) <= int(neighbors.max()) < len(X_ref):
        # (a negative index picked a point from the end)
        raise ValueError(
            f"neighbors must index rows 0..{len(X_ref) - 1} of X_ref, got values "
            f"{int(neighbors.min())}..{int(neighbors.max())}"
        )
    reg = _check_reg(reg)
    k = neighbors.shape[1]
    Z = X_ref[neighbors] - Q.unsqueeze(1)  # (m, K, D)
    # w does not depend on the scale of Z; a power of two per point scales C exactly and keeps
    # its entries normal numbers (they underflow for points near 1e-160, overflow near 1e160)
    Z = _pow2_scaled(Z, Z.abs().amax((1, 2))[:, None, None])
    C = Z @ Z.mT  # local Gram matrices (m, K, K)
    trace = torch.diagonal(C, dim1=-2, dim2=-1).sum(-1)
    ridge = torch.where(trace > 0, reg * trace, torch.full_like(trace, reg))
    eye = torch.eye(k, dtype=C.dtype, device=C.device)
    C = C + ridge[:, None, None] * eye
    ones = torch.ones(len(Q), k, 1, dtype=C.dtype, device=C.device)
    w = torch.linalg.solve(C, ones).squeeze(-1)
    return w / w.sum(-1, keepdim=True)


def lle_cost_matrix(neighbors: Tensor, weights: Tensor, n: int) -> Tensor:
    """``M = (I - W)^T (I - W)`` of shape (n, n) from sparse weights (LLE step 3).

    ``W[i, neighbors[i, j]] = weights[i, j]``. Assembled as ``I - W - W^T + W^T W`` with the
    ``W^T W`` term scatter-added from the (n, K, K) outer products ``w_i w_i^T`` (O(n K^2)).
    """
    m, k = neighbors.shape
    if m != n or weights.shape != neighbors.shape:
        raise ValueError(
            f"neighbors and weights must both have shape (n, K) = ({n}, K), "
            f"got {tuple(neighbors.shape)} and {tuple(weights.shape)}"
        )
    W = torch.zeros(m, n, dtype=weights.dtype, device=weights.device)
    W.scatter_add_(1, neighbors, weights)  # (scatter_ kept one of a repeated index's weights)
    M = torch.eye(n, dtype=weights.dtype, device=weights.device) - W - W.mT
    rows = neighbors.unsqueeze(2).expand(m, k, k)
    cols = neighbors.unsqueeze(1).expand(m, k, k)
    outer = weights.unsqueeze(2) * weights.unsqueeze(1)
    M.index_put_((rows.reshape(-1), cols.reshape(-1)), outer.reshape(-1), accumulate=True)
    return M


def _n_components_of_graph(neighbors: Tensor, n: int) -> int:
    nb = neighbors.detach().cpu().numpy()
    rows = np.repeat(np.arange(n), nb.shape[1])
    graph = scipy.sparse.coo_matrix((np.ones(rows.size), (rows, nb.ravel())), shape=(n, n))
    return int(scipy.sparse.csgraph.connected_components(graph, directed=False)[0])


def _bottom_eigh(M: Tensor, n_eig: int, solver: str) -> tuple[Tensor, Tensor]:
    if solver == "auto":
        solver = "scipy" if M.device.type == "cpu" else "torch"
    if solver == "scipy":
        evals, evecs = scipy.linalg.eigh(M.detach().cpu().numpy(), subset_by_index=[0, n_eig - 1])
        return (
            torch.as_tensor(evals, dtype=M.dtype, device=M.device),
            torch.as_tensor(evecs, dtype=M.dtype, device=M.device),
        )
    if solver == "torch":
        evals, evecs = torch.linalg.eigh(M)
        return evals[:n_eig], evecs[:, :n_eig]
    raise ValueError(f"eigen_solver must be 'auto', 'scipy' or 'torch', got {solver!r}")


#: entries within this fraction of a column's largest magnitude count as tied for its sign
SIGN_TIE_RTOL = 1e-4


def _sign_convention(Y: Tensor) -> Tensor:
    """``(1, d)`` signs that make the first entry of each column whose magnitude lies within
    :data:`SIGN_TIE_RTOL` of the column's largest positive. An odd embedding has two extremes
    of one magnitude: rounding, not the data, would pick one of them."""
    a = Y.abs()
    near = a >= a.amax(0, keepdim=True) * (1 - SIGN_TIE_RTOL)
    first = near.to(torch.uint8).argmax(0, keepdim=True)  # the first True of each column
    flip = torch.gather(Y, 0, first).sign()
    return torch.where(flip == 0, torch.ones_like(flip), flip)


@dataclass(frozen=True)
class LLEFit:
    """A fitted LLE: the reference points, their embedding and the fit's by-products.

    Attributes:
        points: fitted points, shape (n, D).
        embedding: Y, shape (n, d), with ``(1/n) Y^T Y = I`` and ``Y^T 1 = 0``.
        neighbors: LongTensor (n, K) of each point's neighbours.
        weights: reconstruction weights (n, K); rows sum to one.
        eigenvalues: the d + 1 smallest eigenvalues of M, shape (d + 1,) (the first is ~0).
        reg: the regulariser used.
    """

    points: Tensor
    embedding: Tensor
    neighbors: Tensor
    weights: Tensor
    eigenvalues: Tensor
    reg: float

    @property
    def n_neighbors(self) -> int:
        return int(self.neighbors.shape[1])

    def transform(self, X_new: Tensor) -> Tensor:
        """Map new points (m, D) to the embedding, (m, d): ``y = sum_j w_j y_j`` over the new
        point's K nearest fitted points, weights as in LLE step 2 (Saul & Roweis 2003, 6.1)."""
        X_new = _check_points(X_new, "X_new")
        if X_new.shape[1] != self.points.shape[1]:
            raise ValueError(
                f"X_new must have shape (m, {self.points.shape[1]}), got {tuple(X_new.shape)}"
            )
        X_new = X_new.to(dtype=self.points.dtype, device=self.points.device)
        nb = knn(self.points, X_new, self.n_neighbors)
        w = reconstruction_weights(self.points, nb, X_new, self.reg)
        return (w.unsqueeze(-1) * self.embedding[nb]).sum(1)


def lle_fit(
    X: Tensor,
    n_components: int = 1,
    n_neighbors: int = 12,
    reg: float = 1e-3,
    eigen_solver: Literal["auto", "scipy", "torch"] = "auto",
) -> LLEFit:
    """Fit locally linear embedding (Roweis & Saul 2000; paper 002 uses K = 12, d = 1).

    Args:
        X: points, shape (n, D), floating; the result follows its dtype and device.
        n_components: d, the embedding dimension (1 <= d <= n - 2).
        n_neighbors: K (1 <= K <= n - 1).
        reg: regulariser of the local Gram matrices, relative to their trace.
        eigen_solver: ``"scipy"`` (``scipy.linalg.eigh`` on the d + 1 bottom eigenpairs),
            ``"torch"`` (``torch.linalg.eigh``), or ``"auto"`` (scipy on CPU, torch elsewhere).

    Returns:
        :class:`LLEFit`. Emits a ``RuntimeWarning`` when the neighbourhood graph is disconnected:
        the bottom eigenvectors then describe the components, not a manifold coordinate.
    """
    X = _check_points(X, "X")
    n = X.shape[0]
    if not is_int(n_components) or n_components < 1:
        raise ValueError(f"n_components must be a positive int, got {n_components!r}")
    if n_components > n - 2:
        raise ValueError(f"n_components={n_components} needs at least {n_components + 2} points")
    nb = knn(X, None, n_neighbors)
    w = reconstruction_weights(X, nb, None, reg)
    M = lle_cost_matrix(nb, w, n)
    n_graph = _n_components_of_graph(nb, n)
    if n_graph > 1:
        warnings.warn(
            f"LLE neighbourhood graph (n_neighbors={n_neighbors}) has {n_graph} connected "
            "components; the embedding separates components instead of following a manifold. "
            "Increase n_neighbors.",
            RuntimeWarning,
            stacklevel=2,
        )
    evals, evecs = _bottom_eigh(M, n_components + 1, eigen_solver)
    # Skip the constant eigenvector (eigenvalue 0); scale to (1/n) Y^T Y = I.
    Y = evecs[:, 1:] * math.sqrt(n)
    Y = Y * _sign_convention(Y)
    return LLEFit(points=X, embedding=Y, neighbors=nb, weights=w, eigenvalues=evals, reg=reg)


def locally_linear_embedding(
    X: Tensor, n_components: int = 1, n_neighbors: int = 12, reg: float = 1e-3
) -> Tensor:
    """Embedding Y of shape (n, d) of points X (n, D); see :func:`lle_fit`."""
    return lle_fit(X, n_components, n_neighbors, reg).embedding
