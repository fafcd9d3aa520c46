"""From predicted trajectories to fault probability and remaining-useful-life (RUL) distributions.

Paper 002 (Li et al., LS-SVR + strong tracking PF) turns the ``p``-step-ahead particle
predictions ``x^i_{k+j}`` (weights ``w^i_k`` frozen over the horizon) into

* the fault probability per future step (their unnumbered equation after step 2)::

      fault(j, k) = sum_i w^i_k I(x^i_{k+j} in Omega_0),   j = 1..p

  with ``Omega_0`` the failure region ``{x >= threshold}`` (or ``{x <= threshold}``);
* the RUL of each particle ``l^i`` (first step at which its path enters ``Omega_0``, times the
  step length) and the RUL expectation, Eq. 28::

      RUL = sum_i l^i w^i

Eq. 28 presumes that every particle crosses within the predicted horizon (the paper keeps
predicting "until the predicted values of all particles reach a predefined failure
threshold"). Here the horizon ``H`` is finite, so paths that never cross are *censored*: their
RUL is only known to exceed ``H * dt``. :func:`rul_distribution` keeps that mass apart and never
reports a number for it; the expectation is returned only when the censored mass is at most a
stated tolerance.

Shapes: ``samples`` is ``(..., N, H)`` (N sample paths / particles, H future steps), weights
``(..., N)``; leading batch dimensions (e.g. prediction times) are carried through.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from ..core.validation import (
    as_tensor,
    check_levels,
    check_positive_real,
    check_real_tensor,
    check_scalar,
    check_weights,
    is_int,
    is_real,
)

__all__ = [
    "RULDistribution",
    "fault_probability",
    "fault_probability_gaussian",
    "rul_distribution",
]

_DIRECTIONS = ("above", "below")


# --------------------------------------------------------------------------- validation helpers
def _check_direction(direction: str) -> str:
    if direction not in _DIRECTIONS:
        raise ValueError(f"direction must be 'above' or 'below', got {direction!r}")
    return direction


def _check_samples(samples) -> Tensor:
    samples = as_tensor(samples, "samples")
    # (a cast would drop the imaginary part with a warning only, or read True as 1)
    if samples.is_complex() or samples.dtype == torch.bool:
        raise TypeError(f"samples must be real, got dtype {samples.dtype}")
    if not samples.is_floating_point():
        samples = samples.to(torch.float64)
    if samples.dim() < 2:
        raise ValueError(
            f"samples must have shape (..., N, H) (N paths, H steps), got {tuple(samples.shape)}"
        )
    n_paths, horizon = samples.shape[-2], samples.shape[-1]
    if horizon < 1:
        raise ValueError(f"samples must have a horizon H >= 1 (last axis), got H = {horizon}")
    if n_paths < 1:
        raise ValueError(f"samples must hold N >= 1 paths (axis -2), got N = {n_paths}")
    if bool(torch.isnan(samples).any()):
        raise ValueError("samples contains NaN; shape (..., N, H)")
    return samples


def _crossed(samples: Tensor, threshold: float, direction: str) -> Tensor:
    # Failure region Omega_0 (paper 002): reaching the threshold counts as failure. Compared in
    # float64: a Python threshold against a float32 tensor is rounded to float32 first, so a
    # value below the threshold could count as reaching it (1e8 >= 1e8 + 1 in float32).
    samples = samples.to(torch.float64)
    return samples >= threshold if direction == "above" else samples <= threshold


# --------------------------------------------------------------------------- fault probability
def fault_probability(
    samples: Tensor,
    threshold: float,
    weights: Tensor | None = None,
    direction: str = "above",
) -> Tensor:
    """Weighted probability that the predicted state is in the failure region at each step.

    Paper 002, fault(j, k) = sum_i w^i_k I(x^i_{k+j} in Omega_0), j = 1..H, with
    ``Omega_0 = {x >= threshold}`` (``direction="above"``) or ``{x <= threshold}`` ("below").
    This is the per-step marginal probability, not the probability of having crossed *by* step j
    (that is ``rul_distribution(...).cdf``).

    Args:
        samples: ``(..., N, H)`` predicted sample paths / particles.
        threshold: finite scalar failure threshold.
        weights: ``(..., N)`` normalised non-negative weights; ``None`` means ``1/N``.
        direction: ``"above"`` or ``"below"``.

    Returns:
        ``(..., H)`` float64 probabilities on the device of ``samples``.
    """
    direction = _check_direction(direction)
    samples = _check_samples(samples)
    thr = check_scalar(threshold, "threshold")
    w = check_weights(weights, samples.shape[:-2], samples.shape[-2], samples.device)
    hit = _crossed(samples, thr, direction).to(torch.float64)
    return (w.unsqueeze(-1) * hit).sum(-2)


def fault_probability_gaussian(
    mean: Tensor,
    std: Tensor,
    threshold: float,
    direction: str = "above",
) -> Tensor:
    """Fault probability of a Gaussian prediction ``N(mean, std^2)`` at each step.

    ``P(x >= c) = 1 - Phi((c - m) / s) = erfc((c - m) / (s sqrt 2)) / 2`` ("above"),
    ``P(x <= c) = Phi((c - m) / s)`` ("below"): the Gaussian counterpart of paper 002's
    fault(j, k). ``std == 0`` is a point prediction: the indicator of the failure region.

    Args:
        mean: ``(..., H)`` predicted means.
        std: ``(..., H)`` predicted standard deviations (>= 0), same shape as ``mean``.
        threshold: finite scalar failure threshold.
        direction: ``"above"`` or ``"below"``.

    Returns:
        ``(..., H)`` float64 probabilities on the device of ``mean``.
    """
    direction = _check_direction(direction)
    thr = check_scalar(threshold, "threshold")
    mean = as_tensor(mean, "mean")
    std = as_tensor(std, "std", device=mean.device)
    check_real_tensor(mean, "mean")  # (True was read as 1, a complex mean lost its imaginary
    check_real_tensor(std, "std")  # part with a warning only)
    if mean.dim() < 1:
        raise ValueError(f"mean must have shape (..., H), got {tuple(mean.shape)}")
    if mean.shape[-1] < 1:
        raise ValueError("mean must have a horizon H >= 1 (last axis)")
    if tuple(std.shape) != tuple(mean.shape):
        raise ValueError(
            f"std must have the shape of mean {tuple(mean.shape)}, got {tuple(std.shape)}"
        )
    mean = mean.to(torch.float64)
    std = std.to(torch.float64)
    if not bool(torch.isfinite(mean).all()):
        raise ValueError("mean contains non-finite values; shape (..., H)")
    if not bool(torch.isfinite(std).all()) or bool((std < 0).any()):
        raise ValueError("std must be finite and >= 0; shape (..., H)")
    sign = 1.0 if direction == "above" else -1.0
    z = sign * (thr - mean) / (std * math.sqrt(2.0))
    p = 0.5 * torch.special.erfc(z)
    # std == 0: the prediction is a point; reaching the threshold counts as failure.
    point = _crossed(mean, thr, direction).to(torch.float64)
    return torch.where(std > 0, p, point)


# --------------------------------------------------------------------------- RUL distribution
@dataclass(frozen=True, eq=False)
class RULDistribution:
    """Discrete RUL distribution from first-passage times of sample paths (paper 002, Eq. 28).

    The RUL takes the values ``support = dt * (1, ..., H)``; mass that never crosses within the
    horizon is kept apart as ``censored_mass`` (RUL > ``H * dt``, value unknown).

    Attributes:
        first_passage: ``(..., N)`` int64, 1-based step at which each path first enters the
            failure region; ``-1`` marks a censored path (no crossing within ``H`` steps).
        weights: ``(..., N)`` float64 normalised path weights.
        pmf: ``(..., H)`` float64, ``pmf[..., j-1] = sum_i w^i I(first_passage_i = j)``;
            ``pmf.sum(-1) = 1 - censored_mass``.
        censored_mass: ``(...)`` float64 weight of the censored paths.
        expectation: ``(...)`` float64 Eq. 28 over the crossing paths,
            ``sum_j j dt pmf_j / sum_j pmf_j``; NaN wherever ``censored`` is True.
        dt: step length (time per prediction step).
        tol: censored-mass tolerance under which ``expectation`` is reported.
    """

    first_passage: Tensor
    weights: Tensor
    pmf: Tensor
    censored_mass: Tensor
    expectation: Tensor
    dt: float
    tol: float

    @property
    def horizon(self) -> int:
        """Number of predicted steps ``H``."""
        return self.pmf.shape[-1]

    @property
    def support(self) -> Tensor:
        """``(H,)`` RUL values ``dt * (1..H)`` of the pmf entries."""
        steps = torch.arange(1, self.horizon + 1, dtype=torch.float64, device=self.pmf.device)
        return steps * self.dt

    @property
    def censored(self) -> Tensor:
        """``(...)`` bool: censored mass exceeds ``tol``; the expectation is then withheld."""
        return self.censored_mass > self.tol

    @property
    def rul_lower_bound(self) -> float:
        """The censored mass has RUL > ``H * dt``; this is that bound."""
        return self.horizon * self.dt

    @property
    def restricted_mean(self) -> Tensor:
        """``(...)`` ``E[min(RUL, H dt)]``: Eq. 28 with the censored mass counted at the horizon,
        ``sum_j j dt pmf_j + censored_mass * H dt``. Equals ``expectation`` when nothing is
        censored and is a lower bound of the unconditional mean otherwise; always finite."""
        return (self.pmf * self.support).sum(-1) + self.censored_mass * self.rul_lower_bound

    @property
    def path_censored(self) -> Tensor:
        """``(..., N)`` bool: the path never crosses within the horizon."""
        return self.first_passage < 0

    @property
    def path_rul(self) -> Tensor:
        """``(..., N)`` float64 RUL ``l^i = dt * first_passage`` per path; NaN when censored."""
        rul = self.first_passage.to(torch.float64) * self.dt
        return torch.where(self.path_censored, torch.full_like(rul, math.nan), rul)

    @property
    def cdf(self) -> Tensor:
        """``(..., H)`` ``P(RUL <= j dt)``: probability of having crossed by step j."""
        return self.pmf.cumsum(-1)

    @property
    def mean(self) -> Tensor:
        """Alias of ``expectation`` (Eq. 28); NaN where censored."""
        return self.expectation

    @property
    def median(self) -> Tensor:
        """``quantile(0.5)``; NaN when more than half of the mass is censored."""
        return self.quantile(0.5)

    def binned(self, width: int) -> tuple[Tensor, Tensor]:
        """The pmf in bins of ``width`` steps, for display: ``(support (B,), pmf (..., B))``.

        ``B = max(1, H // width)`` bins of ``width`` consecutive steps (one bin of all ``H``
        steps when ``H < width``; the last ``H - B * width`` steps are dropped); ``support`` is
        the mean RUL of each bin's steps, ``pmf`` the mass of each bin.
        """
        if not is_int(width) or width < 1:
            raise ValueError(f"width must be a positive int (steps per bin), got {width!r}")
        width = int(width)
        n_bin = max(1, self.horizon // width)
        keep = n_bin * width
        pmf = self.pmf[..., :keep]
        return (
            self.support[:keep].reshape(n_bin, -1).mean(-1),
            pmf.reshape(*pmf.shape[:-1], n_bin, -1).sum(-1),
        )

    def quantile(self, q: float | Sequence[float] | Tensor) -> Tensor:
        """Lower quantile ``Q(q) = min{l in support : P(RUL <= l) >= q}``, q in (0, 1].

        The censored mass counts as the upper tail (RUL > ``H dt``), so ``Q(q)`` is well defined
        whenever ``q <= 1 - censored_mass``; otherwise the quantile lies beyond the horizon and
        NaN is returned. The comparison ``P(RUL <= l) >= q`` allows ``1e-12`` for the rounding of
        the cumulative sum (a cdf that sums to ``0.5 - 1e-16`` still gives the median). A scalar
        ``q`` gives shape ``(...)``, a 1-D ``q`` gives ``(..., Q)``.
        """
        qs = check_levels(q, device=self.pmf.device)
        scalar = qs.dim() == 0
        qs = qs.reshape(-1)
        h = self.horizon
        cdf = self.cdf.unsqueeze(-2)  # (..., 1, H)
        reached = cdf >= qs[:, None] - 1e-12  # (..., Q, H)
        steps = torch.arange(h, device=self.pmf.device)
        idx = torch.where(reached, steps, torch.full_like(steps, h)).amin(-1)  # (..., Q)
        val = (idx + 1).to(torch.float64) * self.dt
        val = torch.where(idx >= h, torch.full_like(val, math.nan), val)
        return val[..., 0] if scalar else val


def rul_distribution(
    samples: Tensor,
    threshold: float,
    weights: Tensor | None = None,
    dt: float = 1.0,
    direction: str = "above",
    tol: float = 0.0,
) -> RULDistribution:
    """RUL distribution from the first passage of each predicted path through the threshold.

    For path i, ``first_passage_i = min{j in 1..H : x^i_{k+j} in Omega_0}`` and its RUL is
    ``l^i = dt * first_passage_i`` (paper 002, Fig. 11 and Eq. 28); a path with no crossing
    within ``H`` steps is censored (RUL > ``H dt``). The pmf over steps ``1..H`` is weighted by
    ``weights`` and sums to ``1 - censored_mass``. The expectation (Eq. 28,
    ``sum_i l^i w^i`` renormalised over the crossing paths) is returned only where
    ``censored_mass <= tol``; elsewhere it is NaN and ``censored`` is True. With the default
    ``tol = 0`` the expectation exists only when every path with positive weight crosses, as in
    the paper. A positive ``tol`` accepts a conditional mean that ignores up to ``tol`` mass
    beyond the horizon (so it underestimates the unconditional mean).

    Args:
        samples: ``(..., N, H)`` predicted sample paths / particles.
        threshold: finite scalar failure threshold.
        weights: ``(..., N)`` normalised non-negative weights; ``None`` means ``1/N``.
        dt: positive step length (time units per step).
        direction: ``"above"`` (failure when ``x >= threshold``) or ``"below"``.
        tol: censored-mass tolerance in ``[0, 1)``.

    Returns:
        :class:`RULDistribution` with batch shape ``samples.shape[:-2]``.
    """
    direction = _check_direction(direction)
    samples = _check_samples(samples)
    thr = check_scalar(threshold, "threshold")
    check_positive_real(dt, "dt")
    dt = float(dt)
    if not is_real(tol) or not 0.0 <= tol < 1.0:
        raise ValueError(f"tol must be a number in [0, 1), got {tol!r}")
    n_paths, horizon = samples.shape[-2], samples.shape[-1]
    w = check_weights(weights, samples.shape[:-2], n_paths, samples.device)

    crossed = _crossed(samples, thr, direction)  # (..., N, H)
    steps = torch.arange(horizon, device=samples.device)
    # First crossing index (0-based); H marks "never crossed" (censored).
    idx = torch.where(crossed, steps, torch.full_like(steps, horizon)).amin(-1)  # (..., N)
    hit = idx < horizon
    first_passage = torch.where(hit, idx + 1, torch.full_like(idx, -1))

    mass = torch.zeros((*w.shape[:-1], horizon + 1), dtype=torch.float64, device=w.device)
    mass.scatter_add_(-1, idx, w)
    pmf = mass[..., :horizon]
    censored_mass = mass[..., horizon]

    # Eq. 28 over the crossing paths: sum_j (j dt) pmf_j / sum_j pmf_j.
    support = (steps + 1).to(torch.float64) * float(dt)
    crossing_mass = pmf.sum(-1)
    expectation = (pmf * support).sum(-1) / crossing_mass
    withheld = (censored_mass > tol) | (crossing_mass <= 0)
    expectation = torch.where(withheld, torch.full_like(expectation, math.nan), expectation)
    return RULDistribution(
        first_passage=first_passage,
        weights=w,
        pmf=pmf,
        censored_mass=censored_mass,
        expectation=expectation,
        dt=float(dt),
        tol=float(tol),
    )
