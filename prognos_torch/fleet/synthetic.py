"""A synthetic fleet with known failure times: exponential degradation after a random onset.

Asset ``j`` is sampled at ``t = 0, 1, ..., n_j - 1`` (``n_j = n_steps``, or uniform in
``[ragged * n_steps, n_steps]`` with ``ragged < 1``) with

    y_t = theta_j exp(beta_j max(0, t - t_on,j) + eps_t),   eps_t ~ N(0, sigma_j^2) i.i.d.,

``theta_j ~ LogNormal(0, 0.25^2)``, ``sigma_j ~ U(noise)``, the onset
``t_on,j ~ U(onset) * t_end,j`` (``t_end,j = n_j - 1``; the first 30 % of each life stay
healthy, as the onset protocol assumes) and the observation ending at the fraction
``lambda_j ~ U(life_fraction)`` of the degradation interval, so that the failure time (the
noise-free path ``theta exp(beta (t - t_on))`` reaches ``threshold``) is

    t_fail,j = t_on,j + (t_end,j - t_on,j) / lambda_j,
    beta_j = log(threshold / theta_j) / (t_fail,j - t_on,j).

A ``healthy_fraction`` of the assets never degrades (``beta = 0``, onset and failure at
``inf``). All randomness comes from ``numpy.random.default_rng(seed)``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..core.validation import is_int, is_real

__all__ = ["SyntheticFleet", "synthetic_fleet"]


@dataclass(frozen=True, eq=False)
class SyntheticFleet:
    """Long table and truth of :func:`synthetic_fleet`.

    Attributes:
        table: ``{"asset": str array, "t": float64, "value": float64}`` (one row per sample).
        assets: the asset ids ``"a00000"`` ... in table order.
        onset, failure, t_end: ``(A,)`` true onset, failure and last observation times
            (``inf`` onset/failure for healthy assets).
        true_rul: ``failure - t_end`` (``inf`` for healthy assets).
        threshold: the failure threshold.
    """

    table: dict[str, np.ndarray]
    assets: list[str]
    onset: np.ndarray
    failure: np.ndarray
    t_end: np.ndarray
    true_rul: np.ndarray
    threshold: float


def synthetic_fleet(
    n_assets: int = 1000,
    n_steps: int = 500,
    *,
    threshold: float = 20.0,
    seed: int = 0,
    ragged: float = 0.6,
    healthy_fraction: float = 0.05,
    noise: tuple[float, float] = (0.05, 0.15),
    onset: tuple[float, float] = (0.35, 0.75),
    life_fraction: tuple[float, float] = (0.3, 0.9),
) -> SyntheticFleet:
    """Simulate the fleet of the module docstring.

    ``ValueError`` naming the argument unless: ``ragged`` in (0, 1] with every life at least
    10 samples (``ceil(ragged n_steps) >= 10``), ``healthy_fraction`` in [0, 1], the pairs
    ``noise`` ``0 <= lo <= hi``, ``onset`` ``0 <= lo < 1``, ``lo <= hi <= 1`` (fractions of
    each life) and ``life_fraction`` ``0 < lo <= hi`` (above 1: observed past failure), and
    ``threshold`` finite and > 0.
    """
    if not is_int(n_assets) or not is_int(n_steps) or n_assets < 1 or n_steps < 10:
        raise ValueError(
            f"need ints n_assets >= 1 and n_steps >= 10, got {n_assets!r}, {n_steps!r}"
        )
    n_assets, n_steps = int(n_assets), int(n_steps)
    if not is_real(ragged) or not 0.0 < ragged <= 1.0 or math.ceil(ragged * n_steps) < 10:
        raise ValueError(
            "ragged must be a number in (0, 1] with ceil(ragged * n_steps) >= 10 (the shortest "
            f"life in samples), got {ragged!r} with n_steps={n_steps}"
        )
    if not is_real(threshold) or not 0.0 < threshold < math.inf:
        raise ValueError(f"threshold must be a finite number > 0, got {threshold!r}")
    if not is_real(healthy_fraction) or not 0.0 <= healthy_fraction <= 1.0:
        raise ValueError(f"healthy_fraction must be a number in [0, 1], got {healthy_fraction!r}")
    for name, pair, span in (
        ("noise", noise, "0 <= lo <= hi, finite"),
        ("onset", onset, "0 <= lo < 1, lo <= hi <= 1"),  # (an onset at the end: beta inf)
        ("life_fraction", life_fraction, "0 < lo <= hi, finite"),  # (above 1: past failure)
    ):
        lo, hi = tuple(pair) if np.ndim(pair) == 1 and len(pair) == 2 else (None, None)
        ok = is_real(lo) and is_real(hi) and lo <= hi < math.inf
        if name == "noise":
            ok = ok and lo >= 0.0
        elif name == "onset":
            ok = ok and 0.0 <= lo < 1.0 and hi <= 1.0
        else:
            ok = ok and lo > 0.0
        if not ok:
            raise ValueError(f"{name} must be a pair (lo, hi) with {span}, got {pair!r}")
    rng = np.random.default_rng(seed)
    lo = int(np.ceil(ragged * n_steps)) if ragged < 1 else n_steps
    n = rng.integers(lo, n_steps + 1, size=n_assets) if lo < n_steps else np.full(n_assets, n_steps)
    t_end = (n - 1).astype(np.float64)
    theta = np.exp(rng.normal(0.0, 0.25, n_assets))
    sigma = rng.uniform(*noise, n_assets)
    t_on = rng.uniform(*onset, n_assets) * t_end
    lam = rng.uniform(*life_fraction, n_assets)
    t_fail = t_on + (t_end - t_on) / lam
    beta = np.log(threshold / theta) / (t_fail - t_on)
    healthy = rng.uniform(size=n_assets) < healthy_fraction
    beta[healthy] = 0.0
    t_on[healthy] = np.inf
    t_fail[healthy] = np.inf
    assets = [f"a{j:05d}" for j in range(n_assets)]
    total = int(n.sum())
    asset_col = np.repeat(np.array(assets, dtype=object), n)
    starts = np.repeat(np.cumsum(n) - n, n)
    t = (np.arange(total) - starts).astype(np.float64)
    ramp = np.maximum(0.0, t - np.repeat(np.where(healthy, np.inf, t_on), n))
    ramp = np.where(np.isfinite(ramp), ramp, 0.0)
    value = np.repeat(theta, n) * np.exp(
        np.repeat(beta, n) * ramp + rng.normal(size=total) * np.repeat(sigma, n)
    )
    return SyntheticFleet(
        table={"asset": asset_col, "t": t, "value": value},
        assets=assets,
        onset=t_on,
        failure=t_fail,
        t_end=t_end,
        true_rul=t_fail - t_end,
        threshold=float(threshold),
    )
