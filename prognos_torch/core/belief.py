"""Gaussian beliefs in square-root form, with leading batch dimensions."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from .validation import check_chol, check_finite

__all__ = ["GaussianBelief", "check_belief"]


@dataclass(frozen=True)
class GaussianBelief:
    """A batch of Gaussian beliefs ``N(mean, chol chol^T)``.

    Attributes:
        mean: ``(..., n)``.
        chol: ``(..., n, n)`` lower-triangular square root of the covariance.

    Construction checks the types and that ``mean`` and ``chol`` agree on ``n`` (``TypeError``,
    ``ValueError``); :meth:`validate` checks the rest (batch shapes, finiteness, diagonal).
    """

    mean: Tensor
    chol: Tensor

    def __post_init__(self) -> None:
        mean, chol = self.mean, self.chol
        if not isinstance(mean, Tensor) or not isinstance(chol, Tensor):
            raise TypeError(
                "GaussianBelief(mean, chol) needs torch.Tensor mean (..., n) and chol "
                f"(..., n, n), got {type(mean).__name__} and {type(chol).__name__}"
            )
        if mean.dim() < 1:
            raise ValueError(
                f"GaussianBelief: mean must have shape (..., n), got {tuple(mean.shape)}"
            )
        n = mean.shape[-1]
        if chol.dim() < 2 or chol.shape[-2:] != (n, n):
            if chol.dim() >= 2 and chol.shape[-1] == chol.shape[-2]:
                raise ValueError(
                    f"GaussianBelief: mean {tuple(mean.shape)} and chol {tuple(chol.shape)} "
                    f"disagree on n ({n} vs {chol.shape[-1]}); mean must be (..., n) and chol "
                    "(..., n, n)"
                )
            raise ValueError(
                f"GaussianBelief: chol must be square (..., n, n) with n = {n} (the length of "
                f"mean), got {tuple(chol.shape)}"
            )

    @classmethod
    def from_cov(cls, mean: Tensor, cov: Tensor) -> GaussianBelief:
        """Build from a full covariance ``(..., n, n)`` (Cholesky-factorised once)."""
        mean = torch.as_tensor(mean)
        cov = torch.as_tensor(cov, dtype=mean.dtype, device=mean.device)
        if not cov.is_floating_point():
            raise TypeError(f"mean must be a floating tensor, got {mean.dtype}")
        if mean.dim() < 1 or cov.dim() < 2 or cov.shape[-2:] != (mean.shape[-1],) * 2:
            raise ValueError(
                f"GaussianBelief.from_cov: mean must be (..., n) and cov (..., n, n), got "
                f"{tuple(mean.shape)} and {tuple(cov.shape)}"
            )
        check_finite(cov, "cov")
        # symmetric to rounding (a product A A^T), never symmetrised away; the scale of each
        # matrix of the batch is its own
        tol = 1e3 * torch.finfo(cov.dtype).eps * cov.abs().amax(dim=(-2, -1), keepdim=True)
        if not bool(((cov - cov.mT).abs() <= tol).all()):
            raise ValueError("cov must be symmetric positive definite, shape (..., n, n)")
        L, info = torch.linalg.cholesky_ex(0.5 * (cov + cov.mT))
        if bool((info > 0).any()):
            raise ValueError("cov must be symmetric positive definite, shape (..., n, n)")
        return cls(mean, L)

    @property
    def cov(self) -> Tensor:
        """Full covariance ``chol chol^T``, ``(..., n, n)``."""
        return self.chol @ self.chol.mT

    @property
    def dim(self) -> int:
        return self.mean.shape[-1]

    @property
    def batch_shape(self) -> torch.Size:
        return self.mean.shape[:-1]

    def to(self, *args, **kwargs) -> GaussianBelief:
        return GaussianBelief(self.mean.to(*args, **kwargs), self.chol.to(*args, **kwargs))

    def expand(self, *batch_shape: int) -> GaussianBelief:
        """Repeat the belief over new leading batch dimensions (e.g. Monte Carlo runs)."""
        n = self.dim
        try:
            mean = self.mean.expand(*batch_shape, n)
            chol = self.chol.expand(*batch_shape, n, n)
        except RuntimeError as exc:
            raise ValueError(
                f"GaussianBelief.expand: batch_shape {tuple(batch_shape)} must be the new batch "
                f"shape: new leading dimensions, then the belief's own {tuple(self.batch_shape)} "
                "(each kept, or expanded from 1)"
            ) from exc
        return GaussianBelief(mean.clone(), chol.clone())

    def __getitem__(self, idx) -> GaussianBelief:
        if not isinstance(idx, tuple):
            idx = (idx,)
        return GaussianBelief(self.mean[idx + (slice(None),)], self.chol[idx + (slice(None),) * 2])

    def validate(self, name: str = "belief") -> GaussianBelief:
        """Check shapes, finiteness and a positive diagonal; raise ``ValueError`` naming ``name``."""
        if not isinstance(self.mean, Tensor) or not isinstance(self.chol, Tensor):
            raise TypeError(f"{name}: mean and chol must be torch.Tensor")
        if self.mean.dim() < 1:
            raise ValueError(f"{name}.mean must have shape (..., n), got {tuple(self.mean.shape)}")
        n = self.mean.shape[-1]
        if self.chol.shape != self.mean.shape + (n,):
            raise ValueError(
                f"{name}.chol must have shape {tuple(self.mean.shape) + (n,)} "
                f"(the batch shape of {name}.mean, then n x n), got {tuple(self.chol.shape)}"
            )
        if not self.mean.is_floating_point() or self.chol.dtype != self.mean.dtype:
            raise TypeError(
                f"{name}.mean and {name}.chol must have one floating dtype, got "
                f"{self.mean.dtype} and {self.chol.dtype}"
            )
        if self.mean.dtype in (torch.float16, torch.bfloat16):
            raise TypeError(
                f"{name} has dtype {self.mean.dtype}: the filters need float32 or float64 (half "
                "precision has no QR or Cholesky, and its 3 digits lose the weights and "
                "events); convert it with .to(torch.float32)"
            )
        if self.chol.device != self.mean.device:
            raise ValueError(
                f"{name}.mean is on {self.mean.device}, {name}.chol on {self.chol.device}"
            )
        check_finite(self.mean, f"{name}.mean")
        check_chol(self.chol, f"{name}.chol", n)
        return self


def check_belief(belief, state_dim: int, name: str = "belief"):
    """A valid :class:`GaussianBelief` (finite mean, lower triangular
    factor with a positive diagonal) on a state of dimension ``state_dim``; anything else is a
    ``TypeError`` that says how to build one (a ``(mean, chol)`` pair is the usual slip)."""
    if not isinstance(belief, GaussianBelief):
        if isinstance(belief, (tuple, list)) and len(belief) == 2:
            raise TypeError(
                f"{name} must be a GaussianBelief, got a {type(belief).__name__} of two items; "
                "wrap it: GaussianBelief(mean, chol) (or GaussianBelief.from_cov(mean, cov))"
            )
        raise TypeError(
            f"{name} must be a GaussianBelief(mean (..., n), chol (..., n, n)), got "
            f"{type(belief).__name__}"
        )
    belief.validate(name)
    if belief.dim != state_dim:
        raise ValueError(
            f"{name}.mean must have shape (..., {state_dim}) for this model, "
            f"got {tuple(belief.mean.shape)}"
        )
    return belief
