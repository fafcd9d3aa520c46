"""Square-root linear algebra: ``tria`` via QR, Cholesky rank-one up/downdates, safe Cholesky.

All functions act on the last two dimensions, batched over the leading ones; the leading
dimensions of the arguments of one call broadcast against each other (a factor ``(n, n)``
shared by a batch of ``(B, n, k)`` columns), and a vector argument is one with a dimension
fewer than the factor.
Nothing here forms an explicit inverse; triangular factors are applied with solves.
Shapes, dtypes and batch dimensions are checked (a ``ValueError`` or ``TypeError`` naming the
argument); values are not (that would synchronise the device): NaN propagates.
"""

from __future__ import annotations

import torch
from torch import Tensor

from .validation import check_count, check_nonneg

__all__ = [
    "tria",
    "chol_update",
    "chol_downdate",
    "chol_downdate_ex",
    "safe_cholesky",
    "cho_solve_right",
    "symmetrize",
]


def _check_square(S, name: str) -> None:
    """``S`` a floating tensor ``(..., n, n)``; anything else named (shapes only: no sync)."""
    if not isinstance(S, Tensor):
        raise TypeError(
            f"{name} must be a torch.Tensor of shape (..., n, n), got {type(S).__name__}"
        )
    shape = S.shape
    if len(shape) < 2 or shape[-1] != shape[-2]:
        raise ValueError(f"{name} must have shape (..., n, n), got {tuple(shape)}")
    if not S.is_floating_point():
        raise TypeError(f"{name} must be a floating-point tensor, got {S.dtype}")


def _check_like(S: Tensor, X, name: str, dim: int) -> None:
    """``X`` a tensor of ``S``'s dtype with ``X.shape[dim] == n`` (``S`` ``(..., n, n)``) and
    batch dimensions that broadcast against ``S``'s: ``V`` ``(..., n, k)`` (``dim=-2``) or ``B``
    ``(..., m, n)`` (``dim=-1``)."""
    if not isinstance(X, Tensor):
        _raise_shape(S, X, name, dim)
    xs, ss = X.shape, S.shape
    if len(xs) < 2 or xs[dim] != ss[-1]:
        _raise_shape(S, X, name, dim)
    if X.dtype != S.dtype:
        raise TypeError(f"S and {name} must have one dtype, got {S.dtype} and {X.dtype}")
    if xs[:-2] != ss[:-2]:
        try:
            torch.broadcast_shapes(xs[:-2], ss[:-2])
        except RuntimeError:
            raise ValueError(
                f"the batch dimensions of S {tuple(ss[:-2])} and {name} {tuple(xs[:-2])} "
                "do not broadcast"
            ) from None


def _raise_shape(S: Tensor, X, name: str, dim: int) -> None:
    """The error of :func:`_check_like` for an ``X`` of the wrong type or shape."""
    n = S.shape[-1]
    want = (
        f"(..., {n}) (one dimension fewer than S) or (..., {n}, k)"
        if dim == -2
        else f"(..., n, {n})"
    )
    if not isinstance(X, Tensor):
        raise TypeError(f"{name} must be a torch.Tensor of shape {want}, got {type(X).__name__}")
    raise ValueError(
        f"{name} must have shape {want} for S of shape {tuple(S.shape)}, got {tuple(X.shape)}"
    )


def _columns(S: Tensor, V, name: str = "V") -> Tensor:
    """``V`` as ``(..., n, k)``, checked against the factor ``S`` ``(..., n, n)``: a vector
    ``(..., n)`` (one dimension fewer than ``S``) becomes one column."""
    _check_square(S, "S")
    if isinstance(V, Tensor) and V.dim() == S.dim() - 1:
        if V.shape[-1] != S.shape[-1]:
            _raise_shape(S, V, name, -2)
        V = V.unsqueeze(-1)
    _check_like(S, V, name, -2)
    return V


def tria(A: Tensor) -> Tensor:
    """Lower-triangular square root of ``A A^T`` (paper 000 Eq. 25: ``S = Tria(C)``).

    ``A`` has shape ``(..., n, L)`` (any ``L``; zero columns are added when ``L < n``). With
    ``A^T = Q R`` (QR by Householder reflections, LAPACK ``geqrf``; ``Q`` is never formed),
    ``A A^T = R^T R`` and ``S = R^T`` is lower triangular. The sign of each column is fixed so
    that ``diag(S) >= 0``, which makes the factor unique and equal to ``cholesky(A A^T)``.
    A single row (``n = 1``, e.g. a scalar innovation) is its Euclidean norm. Under autograd
    (``A.requires_grad``) the reduced ``torch.linalg.qr`` is used instead, which has a
    derivative where ``A`` has full row rank.

    Args:
        A: ``(..., n, L)``.
    Returns:
        ``(..., n, n)`` lower triangular with non-negative diagonal.
    """
    if not isinstance(A, Tensor):
        raise TypeError(f"A must be a torch.Tensor of shape (..., n, L), got {type(A).__name__}")
    if A.dim() < 2:
        raise ValueError(f"A must have shape (..., n, L), got {tuple(A.shape)}")
    if not A.is_floating_point():
        raise TypeError(f"A must be a floating-point tensor, got {A.dtype}")
    n, L = A.shape[-2], A.shape[-1]
    if n == 1:  # QR of one column: R = +-||a||
        return torch.linalg.vector_norm(A, dim=-1, keepdim=True)
    if L < n:  # pad with zero columns so that R is square
        A = torch.cat([A, A.new_zeros(*A.shape[:-1], n - L)], dim=-1)
    if A.requires_grad and torch.is_grad_enabled():
        if L < n:
            # the padded A has rank L < n and its QR no derivative (NaN); the first L columns
            # of S are those of the QR of the L x n matrix A^T, which has one where A has full
            # column rank, and the others are zero. The values are the padded QR's.
            Rw = torch.linalg.qr(A[..., :L].mT, mode="reduced")[1]  # (..., L, n)
            dw = torch.diagonal(Rw, dim1=-2, dim2=-1)
            Sw = (Rw * torch.ones_like(dw).copysign(dw).unsqueeze(-1)).mT
            Sw = torch.cat([Sw, Sw.new_zeros(*Sw.shape[:-1], n - L)], dim=-1)
            with torch.no_grad():
                S0 = tria(A)
            return S0 + (Sw - Sw.detach())
        # geqrf has no derivative; the reduced QR has one (it needs a full-rank A)
        R = torch.linalg.qr(A.mT, mode="reduced")[1]
    elif torch.compiler.is_compiling():
        # geqrf cannot be traced (no fake-tensor rule); the R-only QR is the same
        # Householder factorisation
        R = torch.linalg.qr(A.mT, mode="r")[1]
    else:
        # geqrf leaves R in the upper triangle of its first output; A^T of a row-major A is
        # the column-major layout LAPACK wants, and unlike linalg.qr nothing else is computed
        R = torch.geqrf(A.mT)[0][..., :n, :].triu()
    d = torch.diagonal(R, dim1=-2, dim2=-1)
    # row j of R times sign(R_jj) (copysign keeps rows with R_jj = 0 unchanged up to sign)
    return (R * torch.ones_like(d).copysign(d).unsqueeze(-1)).mT


def mm(A: Tensor, B: Tensor) -> Tensor:
    """``A @ B``; with an inner dimension of 1 the outer product ``A * B``, the same numbers
    without a batched matrix product (1 x 1 factors batched over particles or runs)."""
    if A.shape[-1] == 1 and B.dim() > 1 and B.shape[-2] == 1:
        return A * B
    return A @ B


def _rank_one(S: Tensor, v: Tensor, sign: float, w: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """``S'`` with ``S' S'^T = S S^T + sign v v^T`` in O(n^2), and ``s_n`` (see below).

    With ``w = S^{-1} v`` (one triangular solve), ``S S^T + sign v v^T = S (I + sign w w^T) S^T``
    and ``I + sign w w^T = L D L^T`` in closed form (Gill, Golub, Murray and Saunders 1974,
    method C1): with ``s_j = 1 + sign sum_{i <= j} w_i^2``, ``s_0 = 1``,
    ``D_j = s_j / s_{j-1}`` and ``L_ij = sign w_i w_j / s_j`` for ``i > j``. Hence column ``j`` of
    ``S' = S L D^{1/2}`` is

        S'_j = sqrt(s_j / s_{j-1}) S_j + sign w_j / sqrt(s_j s_{j-1}) sum_{i > j} w_i S_i,

    which needs one reverse cumulative sum over the columns: no loop over ``j``. ``S'`` is lower
    triangular with a positive diagonal, i.e. the Cholesky factor. A downdate is valid while
    ``s_n > 0``; ``s_n`` (the ratio of the determinants after and before) is returned so the
    caller can judge the loss of precision, which grows like ``eps / s_n``. ``w``: ``S^{-1} v``
    when the caller has it (then ``v`` is not read).
    """
    if w is None:
        w = torch.linalg.solve_triangular(S, v.unsqueeze(-1), upper=False).squeeze(-1)
    w2 = w * w
    c = torch.cumsum(w2, dim=-1)
    if sign < 0:
        s = 1.0 - c  # s_j, (..., n)
        s_prev = s + w2  # s_{j-1}
    else:
        s = 1.0 + c
        s_prev = s - w2
    Sw = S * w.unsqueeze(-2)
    T = Sw.flip(-1).cumsum(-1).flip(-1).sub_(Sw)  # T_j = sum_{i > j} w_i S_i
    a = (s / s_prev).sqrt_()  # sqrt(s_j / s_{j-1})
    b = w * a / s  # w_j / sqrt(s_j s_{j-1})
    # negative s (a failed downdate) gives NaN here; the caller sees it in the ratio s_n
    S2 = torch.addcmul(S * a.unsqueeze(-2), T, b.unsqueeze(-2), value=sign)
    return S2, s[..., -1]


#: When to use sequential rank-one steps instead of one dense factorisation. Per rank, a
#: rank-one step costs O(n^2) but about 15 small operations; the dense form
#: ``S chol(I -+ W W^T)`` costs O(n^3) in 3 operations. Measured on CPU (best of 3, one
#: thread; microseconds for a rank-1 downdate): n = 44, batch 1: 31 vs 21; n = 44, batch 256:
#: 2,200 vs 4,400; n = 200, batch 1: 140 vs 530 (rank 4: 500 vs 520); n = 4: equal or dense.
_RANK_ONE_MIN_NUMEL = 8192
_RANK_ONE_MIN_N_PER_RANK = 50


def _use_rank_one(S: Tensor, k: int) -> bool:
    n = S.shape[-1]
    if k == 0:
        return False  # nothing to add or remove: the dense form gives S and a ratio of 1
    if k == 1 and n >= 8 and torch.compiler.is_compiling():
        return True  # compiled, the closed form's small operations fuse: O(n^2) wins
    return S.numel() >= _RANK_ONE_MIN_NUMEL and (k == 1 or _RANK_ONE_MIN_N_PER_RANK * k <= n)


def _dense(S: Tensor, V: Tensor, sign: float, W: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """``S chol(I + sign W W^T)`` with ``W = S^{-1} V`` (given, or by a triangular solve), and
    the determinant ratio (``-1`` where the Cholesky factorisation fails)."""
    if S.shape[-1] == 1:
        # a 1 x 1 factor (e.g. each particle's Gaussian of a 1-D state) in closed form,
        # s' = s sqrt(1 + sign sum_j (v_j / s)^2): no batched LAPACK calls on 1 x 1 matrices
        W = V / S
        W2 = W * W
        W2 = W2 if W2.shape[-1] == 1 else W2.sum(-1, keepdim=True)
        a = 1.0 - W2 if sign < 0 else 1.0 + W2  # (1 + (-1) x is 1 - x)
        L = a.sqrt()  # NaN where a < 0 (a failed downdate, ratio -1 below)
        ratio = torch.where(a[..., 0, 0] > 0, (L * L)[..., 0, 0], -1.0)
        return S * L, ratio
    if W is None:
        W = torch.linalg.solve_triangular(S, V, upper=False)
    eye = _eye(S.shape[-1], S.dtype, S.device)
    if W.dim() == 2:
        A = torch.addmm(eye, W, W.mT, alpha=sign)
    else:
        A = torch.matmul(W, W.mT).mul_(sign).add_(eye)
    L, info = torch.linalg.cholesky_ex(A)
    d = torch.diagonal(L, dim1=-2, dim2=-1)
    ratio = d.square().prod(-1)
    if V.shape[-1] > 1:
        # det(I - W W^T) is a product of k eigenvalues in (0, 1]: for many strongly downdating
        # columns it underflows to 0 although every factor is positive (a valid downdate)
        ratio = ratio.clamp_min(torch.finfo(ratio.dtype).tiny)
    return S @ L, ratio.masked_fill(info > 0, -1.0)


_EYE_CACHE: dict = {}


def _eye(n: int, dtype: torch.dtype, device: torch.device) -> Tensor:
    """``I_n``, made once per size, dtype and device (read only: never modified in place)."""
    if torch.compiler.is_compiling():
        return torch.eye(n, dtype=dtype, device=device)
    key = (n, dtype, device)
    E = _EYE_CACHE.get(key)
    if E is None:
        with torch.inference_mode(False), torch.no_grad():
            E = torch.eye(n, dtype=dtype, device=device)
        if len(_EYE_CACHE) > 64:
            _EYE_CACHE.clear()
        _EYE_CACHE[key] = E
    return E


def chol_update(S: Tensor, V: Tensor) -> Tensor:
    """Cholesky update: ``S' S'^T = S S^T + V V^T`` for ``V`` of shape ``(..., n)`` or ``(..., n, k)``.

    By closed-form rank-one updates (O(n^2) each, Gill et al. 1974) for large factors and small
    ranks (``_use_rank_one``), otherwise by one QR (``tria([S, V])``). The closed form needs
    ``S^{-1} v``; where ``S`` is singular (a zero on its diagonal, e.g. a ``tria`` of fewer
    columns than rows) or so near it that the result overflows, that batch element is made by
    the QR instead.
    """
    V = _columns(S, V)
    if not _use_rank_one(S, V.shape[-1]):
        return tria(torch.cat(_broadcast_batch(S, V), dim=-1))
    S2 = _rank_one_updates(S, V)
    if torch.compiler.is_compiling():
        return S2
    bad = ~torch.isfinite(S2).flatten(-2).all(-1)
    if not bool(bad.any()):
        return S2
    # again with those elements replaced by I and 0 (so that no inf or NaN reaches autograd),
    # then the QR there
    keep = bad[..., None, None]
    eye = _eye(S.shape[-1], S.dtype, S.device)
    S2 = _rank_one_updates(torch.where(keep, eye, S), torch.where(keep, 0.0, V))
    return torch.where(keep, tria(torch.cat(_broadcast_batch(S, V), dim=-1)), S2)


def _rank_one_updates(S: Tensor, V: Tensor) -> Tensor:
    for j in range(V.shape[-1]):
        S, _ = _rank_one(S, V[..., j], 1.0)
    return S


def _broadcast_batch(*Xs: Tensor) -> list[Tensor]:
    """``Xs`` expanded to their common leading dimensions (the last two kept)."""
    batch = torch.broadcast_shapes(*(X.shape[:-2] for X in Xs))
    return [X if X.shape[:-2] == batch else X.expand(*batch, *X.shape[-2:]) for X in Xs]


def chol_downdate_ex(S: Tensor, V: Tensor, W: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """Cholesky downdate ``S' S'^T = S S^T - V V^T`` without raising; also returns ``ratio``.

    ``ratio`` ``(...)`` is ``det(S' S'^T) / det(S S^T)`` (in ``(0, 1]`` for a valid downdate,
    floored at the dtype's smallest normal number where the product of several columns'
    ratios underflows; ``<= 0`` or NaN where the result would not be positive definite; ``S'``
    is then NaN or garbage there, so test ``ratio > 0``, which is false for NaN). Large
    factors, small ranks: ``k`` closed-form rank-one downdates (Gill et al. 1974, O(n^2)
    each); otherwise ``S chol(I - W W^T)`` with ``W = S^{-1} V`` (one triangular solve, one
    small Cholesky).

    ``W`` ``(..., n, k)`` (like ``V``): ``S^{-1} V`` when the caller knows it without a solve
    (a Kalman update whose cross-covariance is ``S Z^T``: ``W = Z^T S_zz^{-T}``); the
    triangular solves are then skipped. Sequential rank-one steps need ``S^{-1} V`` against
    the factor of each step, so there only the first column's ``W`` is used.
    """
    V = _columns(S, V)
    if W is not None:
        W = _columns(S, W, "W")
        if W.shape[-1] != V.shape[-1]:
            raise ValueError(
                f"W (S^-1 V) must have V's {V.shape[-1]} column(s), got shape {tuple(W.shape)}"
            )
    k = V.shape[-1]
    if not _use_rank_one(S, k):
        return _dense(S, V, -1.0, W)
    S, ratio = _rank_one(S, V[..., 0], -1.0, None if W is None else W[..., 0])
    if k == 1:
        return S, ratio
    r_min = ratio
    for j in range(1, k):
        S, r = _rank_one(S, V[..., j], -1.0)
        ratio = ratio * r
        r_min = torch.minimum(r_min, r)  # (NaN propagates)
    # the product of k positive s_n can underflow to 0: kept positive where every step was
    # valid (as in _dense)
    ratio = torch.where(r_min > 0, ratio.clamp_min(torch.finfo(ratio.dtype).tiny), ratio)
    return S, ratio


def chol_downdate(S: Tensor, V: Tensor) -> Tensor:
    """Cholesky downdate: ``S' S'^T = S S^T - V V^T`` (``V``: ``(..., n)`` or ``(..., n, k)``).

    Van der Merwe's ``cholupdate(S, u, '-')``, vectorised (:func:`chol_downdate_ex`).
    Raises ``torch.linalg.LinAlgError`` when the result would not be positive definite.
    """
    S2, ratio = chol_downdate_ex(S, V)
    if not bool((ratio > 0).all()):
        if bool(S.isnan().any()) or bool(V.isnan().any()):
            raise torch.linalg.LinAlgError("Cholesky downdate failed: S or V contains NaN")
        raise torch.linalg.LinAlgError(
            "Cholesky downdate failed: the downdated matrix is not positive definite"
        )
    return S2


def symmetrize(P: Tensor) -> Tensor:
    """``(P + P^T) / 2`` of ``P`` ``(..., n, n)``."""
    _check_square(P, "P")  # (P + P^T of a (1, n) P would broadcast to (n, n))
    return 0.5 * (P + P.mT)


def safe_cholesky(P: Tensor, *, jitter: float = 0.0, max_tries: int = 6) -> Tensor:
    """Lower Cholesky factor of a symmetric matrix, with optional escalating diagonal jitter.

    With ``jitter == 0`` a failure raises ``torch.linalg.LinAlgError``. With ``jitter > 0``
    the jitter (relative to the mean diagonal) is multiplied by 10 up to ``max_tries`` times,
    for the batch elements that fail only: the others get their exact factor.
    """
    jitter = check_nonneg(jitter, "jitter", numbers_only=True)
    max_tries = check_count(max_tries, "max_tries", 0)
    P = symmetrize(P)
    L, info = torch.linalg.cholesky_ex(P)
    bad = info > 0
    if not bool(bad.any()):
        return L
    if not bool(torch.isfinite(P).all()):
        raise torch.linalg.LinAlgError("P contains non-finite values (NaN or inf)")
    if jitter <= 0:
        raise torch.linalg.LinAlgError("matrix is not positive definite")
    # a zero diagonal: the scale's floor makes the first jitter at least the smallest normal
    # number (1e-300 alone is 0 in float32, and a subnormal jitter fails the factorisation)
    floor = max(1e-300, torch.finfo(P.dtype).tiny / jitter)
    scale = torch.diagonal(P, dim1=-2, dim2=-1).abs().mean(-1, keepdim=True).clamp_min(floor)
    eye = torch.eye(P.shape[-1], dtype=P.dtype, device=P.device)
    eps = jitter
    for _ in range(max_tries):
        # only the batch elements that still fail get the jitter: the others keep their exact
        # factor (or the one of the smallest jitter that worked for them)
        Lj, info = torch.linalg.cholesky_ex(P + (eps * scale).unsqueeze(-1) * eye)
        L = torch.where(bad[..., None, None], Lj, L)
        bad = bad & (info > 0)
        if not bool(bad.any()):
            return L
        eps *= 10.0
    raise torch.linalg.LinAlgError("matrix is not positive definite, even with jitter")


def cho_solve_right(B: Tensor, S: Tensor) -> Tensor:
    """``B (S S^T)^{-1}`` for lower ``S`` by two triangular solves (paper 000 Eq. 44: ``(B/S^T)/S``).

    ``B``: ``(..., n, m)``, ``S``: ``(..., m, m)`` lower. Returns ``(..., n, m)``.
    """
    _check_square(S, "S")
    _check_like(S, B, "B", -1)
    if S.shape[-1] == 1:  # scalar innovation: B / s^2
        return B / (S * S)
    # X S S^T = B  <=>  S S^T X^T = B^T
    Y = torch.linalg.solve_triangular(S, B.mT, upper=False)
    return torch.linalg.solve_triangular(S.mT, Y, upper=True).mT
