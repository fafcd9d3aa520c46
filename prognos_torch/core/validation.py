"""Argument checks shared by the library: each error names the argument and the expected shape."""

from __future__ import annotations

import math

import torch
from torch import Tensor

__all__ = ["as_tensor", "all_finite", "check_finite", "check_chol", "check_shape", "chol_from_cov"]


def as_tensor(x, name: str, *, dtype=None, device=None) -> Tensor:
    """Convert array-likes to a tensor; reject anything else with a ``TypeError`` naming ``name``."""
    if isinstance(x, Tensor):
        return x.to(dtype=dtype or x.dtype, device=device or x.device)
    try:
        return torch.as_tensor(x, dtype=dtype or torch.float64, device=device)
    except (TypeError, ValueError, RuntimeError) as exc:
        raise TypeError(f"{name} must be a tensor or array-like of numbers, got {type(x)}") from exc


def all_finite(x: Tensor) -> bool:
    """``bool(torch.isfinite(x).all())``, usually with one reduction instead of five operations.

    A sum is finite only if every entry is (inf and NaN propagate); a non-finite sum of finite
    entries (overflow) falls back to the exact elementwise test.
    """
    if x.numel() == 0:
        return True
    if not x.is_floating_point():
        return True
    if math.isfinite(float(x.detach().sum())):  # no graph node, no warning under autograd
        return True
    return bool(torch.isfinite(x).all())


def check_finite(x: Tensor, name: str) -> Tensor:
    if not all_finite(x):
        raise ValueError(f"{name} contains non-finite values (NaN or inf)")
    return x


def check_shape(x: Tensor, name: str, tail: tuple[int, ...], what: str) -> Tensor:
    """Check that ``x.shape`` ends with ``tail``; ``what`` spells the expected shape, e.g. '(..., n)'."""
    if x.dim() < len(tail) or tuple(x.shape[x.dim() - len(tail) :]) != tuple(tail):
        raise ValueError(f"{name} must have shape {what} with {tail}, got {tuple(x.shape)}")
    return x


def check_chol(S: Tensor, name: str, n: int) -> Tensor:
    """A square-root factor: shape ``(..., n, n)``, finite, lower triangular, positive diagonal."""
    check_shape(S, name, (n, n), "(..., n, n)")
    check_finite(S, name)
    if not bool(torch.equal(S, torch.tril(S))):
        raise ValueError(f"{name} must be lower triangular (a Cholesky factor), shape (..., n, n)")
    if not bool((torch.diagonal(S, dim1=-2, dim2=-1) > 0).all()):
        raise ValueError(
            f"{name} must have a positive diagonal (the covariance must be positive definite)"
        )
    return S


def chol_from_cov(C: Tensor, name: str, n: int) -> Tensor:
    """Cholesky factor of a covariance ``(..., n, n)``; ``ValueError`` if not symmetric PD."""
    check_shape(C, name, (n, n), "(..., n, n)")
    check_finite(C, name)
    if not bool(torch.allclose(C, C.mT, rtol=1e-10, atol=1e-12 * float(C.abs().max()) + 1e-300)):
        raise ValueError(f"{name} must be symmetric, shape (..., n, n)")
    L, info = torch.linalg.cholesky_ex(C)
    if bool((info > 0).any()):
        raise ValueError(f"{name} must be positive definite, shape (..., n, n)")
    return L
