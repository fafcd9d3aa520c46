"""Shared set-up of the prognosis tests: seeded series, trained learners, the drift problem."""

from __future__ import annotations

import copy
import math

import torch

from prognos_torch.core.belief import GaussianBelief
from prognos_torch.core.model import StateSpaceModel
from prognos_torch.datasets.windows import embed
from prognos_torch.learners import ANFIS, ELM, LSSVR

F64 = torch.float64


def _gen(seed: int) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def _series(T: int = 120, seed: int = 0) -> torch.Tensor:
    t = torch.arange(T, dtype=F64)
    return (
        torch.sin(0.15 * t)
        + 0.3 * torch.cos(0.05 * t)
        + 0.02 * torch.randn(T, generator=_gen(seed), dtype=F64)
    )


def _learner(kind: str, m: int = 4):
    X, y = embed(_series(), m)
    if kind == "elm":
        return ELM(m, 15, generator=_gen(1)).fit_ridge(X, y, 1e-6), X
    if kind == "lssvr":
        return LSSVR("rbf", sigma=0.8, C=50.0).fit(X, y), X
    if kind == "anfis":
        return ANFIS(m, 2).init_premises(X).init_consequents_lstsq(X, y, 1e-6), X
    raise AssertionError(kind)


class _Oracle:
    """A forecaster that returns the true future measurements (for exact wiring checks)."""

    def __init__(self, future: torch.Tensor):
        self.future = future
        self.pos = None

    @property
    def initialized(self):
        return self.pos is not None

    def copy(self):
        return copy.copy(self)

    def initialize(self, z0):
        self.pos = z0.shape[0]
        return self

    def update(self, z):
        torch.testing.assert_close(z, self.future[self.pos])
        self.pos += 1
        return self

    def forecast(self, n):
        return self.future[self.pos : self.pos + n]


def _drift_problem(T=110, R=3, onset=30, seed=0, extra=10):
    """theta: constant, then a quadratic ramp (as paper 000 Eq. 61); y = [theta, exp(theta/2)]."""
    th = torch.ones(T + extra, dtype=F64)
    for k in range(onset, T + extra):
        th[k] = th[k - 1] + 0.0004 * (k - onset)
    clean = torch.stack([th, torch.exp(0.5 * th)], -1)
    ys_all = clean.unsqueeze(1) + 0.01 * torch.randn(
        T + extra, R, 2, generator=_gen(seed), dtype=F64
    )
    model = StateSpaceModel(
        None,  # random walk theta_k = theta_{k-1} + d_k (the assistant model of paper 000)
        lambda x, u, k: torch.stack([x[0], torch.exp(0.5 * x[0])]),
        1,
        2,
        chol_Q=1e-3 * torch.eye(1, dtype=F64),
        chol_R=0.01 * torch.eye(2, dtype=F64),
    )
    init = GaussianBelief(
        torch.ones(R, 1, dtype=F64), 0.1 * torch.eye(1, dtype=F64).expand(R, 1, 1)
    )
    return th, ys_all, model, init


def degradation_history(seed: int, n: int = 60, onset: int = 30):
    """A run-to-failure history ``(t, y)``: noise about 1 (std 0.01), then a power-law rise
    ``0.05 (t - onset)^1.5`` from ``onset`` on."""
    g = torch.Generator().manual_seed(seed)
    t = torch.arange(n, dtype=F64)
    y = 1.0 + 0.01 * torch.randn(n, generator=g, dtype=F64)
    y[onset:] += 0.05 * (t[onset:] - onset) ** 1.5
    return t, y


def lower_median(v):
    """The lower of the two middle values for an even count (the library's moving median)."""
    v = sorted(v)
    return v[(len(v) - 1) // 2]


def brute_weighted_quantile(x, w, q: float) -> float:
    """One column of samples ``x`` (NumPy) under weights ``w``: NaN if a sample of positive
    weight is NaN; else the smallest value ``v`` with ``sum(w[x <= v]) >= q`` (to 1e-12) among
    the samples of positive weight, or their largest when no value reaches ``q``."""
    import numpy as np

    if np.any(np.isnan(x) & (w > 0)):
        return math.nan
    vals = sorted(v for v, wi in zip(x, w) if not np.isnan(v) and wi > 0)
    for v in vals:
        if w[(x <= v) & ~np.isnan(x)].sum() >= q - 1e-12:
            return v
    return vals[-1]
