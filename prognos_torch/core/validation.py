"""Argument checks shared by the library: each error names the argument and the expected shape."""

from __future__ import annotations

import math

import torch
from torch import Tensor

__all__ = [
    "as_tensor",
    "all_finite",
    "check_finite",
    "check_chol",
    "check_shape",
    "chol_from_cov",
    "check_pos_int",
    "check_nonneg_int",
    "check_float_tensor",
    "check_window",
    "check_level",
    "check_channel",
    "check_controls",
    "check_index",
]


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
    if math.isfinite(float(x.sum())):
        return True
    return bool(torch.isfinite(x).all())


def check_finite(x: Tensor, name: str, shape: str | None = None) -> Tensor:
    """``ValueError`` if ``x`` holds NaN or inf; ``shape`` (e.g. ``'(T, ..., m)'``) is quoted."""
    if not all_finite(x):
        where = "" if shape is None else f"; shape {shape}"
        raise ValueError(f"{name} contains non-finite values (NaN or inf){where}")
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


# ------------------------------------------------------------------------------ integers
def check_pos_int(v, name: str) -> int:
    """A Python ``int >= 1`` (``bool`` rejected)."""
    if isinstance(v, bool) or not isinstance(v, int) or v < 1:
        raise ValueError(f"{name} must be a positive int, got {v!r}")
    return v


def check_nonneg_int(v, name: str) -> int:
    """A Python ``int >= 0`` (``bool`` rejected)."""
    if isinstance(v, bool) or not isinstance(v, int) or v < 0:
        raise ValueError(f"{name} must be a non-negative int, got {v!r}")
    return v


# ------------------------------------------------------------------------------ tensors
def check_float_tensor(x, name: str, shape: str) -> Tensor:
    """A floating-point tensor; ``shape`` spells the expected shape in the message."""
    if not isinstance(x, Tensor):
        raise TypeError(f"{name} must be a torch.Tensor of shape {shape}, got {type(x)}")
    if not x.is_floating_point():
        raise TypeError(f"{name} must be a floating tensor of shape {shape}, got {x.dtype}")
    return x


def check_window(window, m: int, name: str = "window") -> Tensor:
    """A finite embedding window ``(..., m)``, oldest value first (paper 002 Eq. 12-14)."""
    hint = f"(..., {m})"
    w = check_float_tensor(window, name, hint)
    if w.dim() < 1 or w.shape[-1] != m:
        raise ValueError(
            f"{name} must have shape (..., m) with m={m} (the embedding dimension, oldest value "
            f"first), got {tuple(w.shape)}"
        )
    return check_finite(w, name, hint)


# ------------------------------------------------------------------------------ choices
def check_level(level: float) -> float:
    """A probability ``level`` in ``(0, 1)`` (of a central band)."""
    if isinstance(level, bool) or not isinstance(level, (int, float)) or not 0.0 < level < 1.0:
        raise ValueError(f"level must be a number in (0, 1), got {level!r}")
    return float(level)


def check_channel(channel, obs_dim: int) -> int:
    """A measurement channel index in ``[0, obs_dim)``."""
    if isinstance(channel, bool) or not isinstance(channel, int) or not 0 <= channel < obs_dim:
        raise ValueError(f"channel must be an int in [0, {obs_dim}), got {channel!r}")
    return channel


def check_controls(model, us, horizon: int, name: str = "us") -> Tensor | None:
    """Controls ``(horizon, ..., p)`` for a model with ``control_dim = p > 0``; ``None`` for a
    model without controls (where passing ``us`` is an error)."""
    if model.control_dim == 0:
        if us is not None:
            raise ValueError(f"{name} was given but the model has control_dim=0")
        return None
    p = model.control_dim
    if not isinstance(us, Tensor) or us.dim() < 2 or us.shape[0] != horizon or us.shape[-1] != p:
        got = tuple(us.shape) if isinstance(us, Tensor) else type(us)
        raise ValueError(
            f"{name} must have shape ({horizon}, ..., {p}) (one row per step), got {got}"
        )
    return us


def check_index(index, n: int, name: str = "param_index") -> Tensor:
    """State components selected by an int, a slice, a sequence of ints or ``None`` (all of
    them) as an int64 index tensor ``(d,)`` in ``[0, n)``."""
    if index is None:
        return torch.arange(n)
    if isinstance(index, bool):
        raise TypeError(f"{name} must be an int, a slice, a sequence of ints or None")
    if isinstance(index, int):
        idx = [index]
    elif isinstance(index, slice):
        idx = list(range(n))[index]
    else:
        try:
            idx = [int(i) for i in index]
        except TypeError as exc:
            raise TypeError(f"{name} must be an int, a slice, a sequence of ints or None") from exc
    if not idx or any(not -n <= i < n for i in idx):
        raise ValueError(f"{name} {index!r} selects nothing or is out of range for n={n}")
    return torch.tensor([i % n for i in idx], dtype=torch.long)
