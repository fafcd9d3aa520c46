"""Audit of the RUL distribution from predicted paths (prognosis.rul, prognosis.paths).

References are written here: closed-form first-passage probabilities of a +-1 random walk
(exact enumeration of all paths), a NumPy Monte Carlo of a Gaussian random walk with drift,
deterministic linear / exponential crossing times, weighted lower quantiles by sort-and-cumsum,
hand-computed summary fields, batched calls against per-series loops, and float32 inputs.
"""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
import torch

from prognos_torch.core import StateSpaceModel
from prognos_torch.prognosis import (
    SamplePaths,
    fault_probability,
    particle_paths,
    rul_distribution,
)

F64 = torch.float64
F32 = torch.float32


def _shift_model(step: float, sigma: float, dtype) -> StateSpaceModel:
    """x_{k+1} = x_k + step + sigma e (scalar state, observed directly)."""
    return StateSpaceModel(
        f=lambda x, u, k: x + step,
        h=lambda x, u, k: x,
        state_dim=1,
        obs_dim=1,
        chol_Q=torch.eye(1, dtype=dtype) * sigma,
        chol_R=torch.eye(1, dtype=dtype),
    )


def _np_lower_quantile(values: np.ndarray, weights: np.ndarray, q: float) -> float:
    """min{v : sum_{v_i <= v} w_i >= q} by sort and cumsum (inf entries = censored)."""
    order = np.argsort(values, kind="stable")
    cw = np.cumsum(weights[order])
    i = int(np.searchsorted(cw, q - 1e-12))  # first index with cw >= q
    return float(values[order][min(i, len(values) - 1)])


# ------------------------------------------------------------------------- defects (fixed)
def test_float32_samples_are_compared_with_the_threshold_in_float64():
    # float32(1e8 + 1) == 1e8: the old comparison in float32 counted 1e8 as reaching 1e8 + 1.
    x = torch.full((2, 3), 1e8, dtype=F32)
    d = rul_distribution(x, 1e8 + 1)
    assert d.first_passage.tolist() == [-1, -1]
    assert d.censored_mass.item() == 1.0
    assert fault_probability(x, 1e8 + 1).tolist() == [0.0, 0.0, 0.0]
    # A value just below the threshold is "below" and not "above" (float32 had it both ways).
    v = torch.tensor([[0.1]], dtype=F32)
    thr = float(v.double()) + 1e-10
    assert rul_distribution(v, thr).first_passage.tolist() == [-1]
    assert rul_distribution(v, thr, direction="below").first_passage.tolist() == [1]
    assert fault_probability(v, thr).item() == 0.0
    # Same answer as the float64 copy of the samples.
    g = torch.Generator().manual_seed(0)
    s = (1e6 + torch.randint(-3, 4, (4, 50, 6), generator=g)).to(F32)
    for direction in ("above", "below"):
        a = rul_distribution(s, 1e6 + 0.5, direction=direction)
        b = rul_distribution(s.double(), 1e6 + 0.5, direction=direction)
        assert torch.equal(a.first_passage, b.first_passage) and torch.equal(a.pmf, b.pmf)


def test_particle_paths_of_float32_particles_keep_the_float64_weights():
    # Half of the paths start at 0, half at -1, and rise by 1 per step (no noise): threshold 1 is
    # reached at step 1 by half the mass, so the median RUL is 1 step. The old particle_paths
    # returned the weights rounded to float32 (1/100 -> 0.0099999998), the cdf at step 1 was
    # 0.49999999 and the median became 2 steps.
    N = 100
    start = -(torch.arange(N) % 2).to(F32).unsqueeze(-1)
    sp = particle_paths(_shift_model(1.0, 0.0, F32), start, 4, generator=torch.Generator())
    assert sp.samples.dtype == F32 and sp.weights.dtype == F64
    assert torch.equal(sp.weights, torch.full((N,), 1.0 / N, dtype=F64))
    d = rul_distribution(sp.samples, 1.0, sp.weights)
    torch.testing.assert_close(d.pmf[:2], torch.tensor([0.5, 0.5], dtype=F64))
    assert d.median.item() == 1.0 == rul_distribution(sp.samples, 1.0).median.item()
    # Given float64 weights are handed back as they were.
    w = torch.rand(N, generator=torch.Generator().manual_seed(1), dtype=F64)
    w = w / w.sum()
    sp_w = particle_paths(_shift_model(1.0, 0.0, F32), start, 2, generator=torch.Generator(),
                          weights=w)  # fmt: skip
    assert torch.equal(sp_w.weights, w)


def test_weighted_quantile_band_of_float32_samples_matches_float64():
    # Constant paths 0..N-1 with uniform weights: the lower quantile q is sample ceil(qN) - 1.
    # The old float32 cumsum of 1/N fell short of q = k/N and returned the next sample.
    N, H = 200, 2
    vals = torch.arange(N, dtype=F32).unsqueeze(-1).expand(N, H).contiguous()
    w = torch.full((N,), 1.0 / N, dtype=F64)
    z = torch.zeros(H, dtype=F32)
    paths = SamplePaths(vals, w, z, z, z, z, 0.9)
    for q in (0.025, 0.05, 0.5, 0.95, 0.975):
        want = math.ceil(q * N - 1e-9) - 1
        assert paths.quantile(q).tolist() == [float(want)] * H
        torch.testing.assert_close(paths.quantile(q).double(), SamplePaths(
            vals.double(), w, z, z, z, z, 0.9).quantile(q))  # fmt: skip
    # particle_paths' own band (level 0.95: q = 0.025 and 0.975) on float32 particles.
    sp = particle_paths(_shift_model(0.0, 0.0, F32), vals[:, :1], 3, generator=torch.Generator())
    assert sp.lower.tolist() == [4.0] * 3 and sp.upper.tolist() == [194.0] * 3


# ------------------------------------------------------------------------- correct behaviour
def test_pm1_random_walk_enumeration_matches_closed_form_first_passage():
    # All 2^H paths of a +-1 walk (up with prob p) weighted by their probabilities. First passage
    # to level c at step n: (c / n) C(n, (n + c) / 2) p^((n+c)/2) (1-p)^((n-c)/2).
    H, p, c = 10, 0.6, 3
    steps = np.array(list(itertools.product([1, -1], repeat=H)), dtype=float)
    x = steps.cumsum(1)
    w = np.prod(np.where(steps > 0, p, 1 - p), axis=1)
    ref = np.zeros(H)
    for n in range(c, H + 1):
        if (n + c) % 2 == 0:
            k = (n + c) // 2
            ref[n - 1] = c / n * math.comb(n, k) * p**k * (1 - p) ** (n - k)
    d = rul_distribution(torch.from_numpy(x), float(c), torch.from_numpy(w), dt=0.5)
    np.testing.assert_allclose(d.pmf.numpy(), ref, atol=1e-15)
    assert d.censored_mass.item() == pytest.approx(1 - ref.sum(), abs=1e-14)
    # by symmetry: the mirrored walk crossing -c from above ("below")
    d_b = rul_distribution(torch.from_numpy(-x), float(-c), torch.from_numpy(w), direction="below")
    torch.testing.assert_close(d_b.pmf, d.pmf, rtol=0, atol=0)
    # median from the cdf by hand (lower quantile)
    cdf = np.cumsum(ref)
    j = int(np.argmax(cdf >= 0.5 - 1e-12)) if cdf[-1] >= 0.5 else None
    assert (j is None and math.isnan(d.median.item())) or d.median.item() == 0.5 * (j + 1)
    assert d.rul_lower_bound == 0.5 * H


def test_gaussian_random_walk_particle_paths_against_numpy_monte_carlo():
    # x_j = x_{j-1} + mu + sigma e; discrete first passage of 3.0 at steps 1..H. Both estimates of
    # P(T <= j) are Monte Carlo; they must agree within 5 standard errors of the difference.
    mu, sigma, H, thr = 0.2, 0.5, 20, 2.0
    N, M = 8000, 100_000
    sp = particle_paths(_shift_model(mu, sigma, F64), torch.zeros(N, 1, dtype=F64), H,
                        generator=torch.Generator().manual_seed(3))  # fmt: skip
    d = rul_distribution(sp.samples, thr, sp.weights)
    rng = np.random.default_rng(4)
    X = (mu + sigma * rng.standard_normal((M, H))).cumsum(1)
    hit = X >= thr
    fp = np.where(hit.any(1), hit.argmax(1) + 1, H + 1)
    ref = (fp[:, None] <= np.arange(1, H + 1)).mean(0)
    se = np.sqrt(ref * (1 - ref) * (1 / N + 1 / M)) + 1e-12
    assert np.all(np.abs(d.cdf.numpy() - ref) <= 5 * se)
    assert abs(d.censored_mass.item() - np.mean(fp > H)) <= 5 * se[-1]
    # per-step fault probability = the marginal P(x_j >= thr)
    p_step = (X >= thr).mean(0)
    fp_mc = fault_probability(sp.samples, thr, sp.weights).numpy()
    assert np.all(np.abs(fp_mc - p_step) <= 5 * np.sqrt(p_step * (1 - p_step) / N) + 1e-12)


def test_deterministic_linear_and_exponential_crossing_times():
    dt, H = 0.25, 80
    t = dt * torch.arange(1, H + 1, dtype=F64)
    # linear x = 0.3 + 0.4 t reaches 5: t = 11.75 -> step 47 exactly (>= counts)
    d = rul_distribution((0.3 + 0.4 * t).unsqueeze(0), 0.3 + 0.4 * 11.75, dt=dt)
    assert d.first_passage.tolist() == [47] and d.expectation.item() == pytest.approx(11.75)
    # exponential decay exp(-0.2 t) below 0.1: t = ln 10 / 0.2 = 11.51 -> step ceil(46.05) = 47
    d = rul_distribution(torch.exp(-0.2 * t).unsqueeze(0), 0.1, dt=dt, direction="below")
    assert d.first_passage.tolist() == [math.ceil(math.log(10) / 0.2 / dt)]
    # a path already beyond the threshold at the first predicted step: RUL = one step
    d = rul_distribution(torch.tensor([[5.0, 4.0, 6.0]], dtype=F64), 2.0, dt=3.0)
    assert d.first_passage.tolist() == [1] and d.median.item() == 3.0
    assert d.expectation.item() == 3.0
    # a path that crosses and comes back counts its first entry only
    d = rul_distribution(torch.tensor([[0.0, 2.5, 0.0, 3.0]], dtype=F64), 2.0)
    assert d.first_passage.tolist() == [2]


def test_weighted_quantiles_and_summary_fields_against_numpy():
    g = torch.Generator().manual_seed(5)
    B, N, H, dt = 3, 9, 6, 0.7
    for _ in range(30):
        s = torch.randn(B, N, H, generator=g, dtype=F64).cumsum(-1)
        w = torch.rand(B, N, generator=g, dtype=F64)
        w[:, 0] = 0.0
        w = w / w.sum(-1, keepdim=True)
        d = rul_distribution(s, 1.0, w, dt=dt, tol=0.2)
        qs = [0.05, 0.25, 0.5, 0.95, 1.0]
        got = d.quantile(qs)
        for b in range(B):
            fp = d.first_passage[b].numpy().astype(float)
            fp[fp < 0] = np.inf
            wb = w[b].numpy()
            for i, q in enumerate(qs):
                ref = _np_lower_quantile(fp, wb, q) * dt
                ref = ref if np.isfinite(ref) else math.nan
                assert got[b, i].item() == pytest.approx(ref, nan_ok=True, abs=1e-12)
            cens = wb[~np.isfinite(fp)].sum()
            assert d.censored_mass[b].item() == pytest.approx(cens, abs=1e-15)
            crossing = np.isfinite(fp)
            mean = (wb[crossing] * fp[crossing] * dt).sum() / wb[crossing].sum()
            if cens > 0.2:
                assert math.isnan(d.expectation[b].item()) and bool(d.censored[b])
            else:
                assert d.expectation[b].item() == pytest.approx(mean, rel=1e-12)
            rmean = (wb * np.where(crossing, fp, H) * dt).sum()
            assert d.restricted_mean[b].item() == pytest.approx(rmean, rel=1e-12)
            # batched call = per-series call
            db = rul_distribution(s[b], 1.0, w[b], dt=dt, tol=0.2)
            assert torch.equal(db.first_passage, d.first_passage[b])
            torch.testing.assert_close(db.pmf, d.pmf[b], rtol=0, atol=1e-15)  # (a sum order: ulps)
            torch.testing.assert_close(db.quantile(qs), got[b], equal_nan=True)


def test_paths_with_nan_are_refused_naming_samples():
    x = torch.tensor([[0.0, math.nan, 3.0], [0.0, 1.0, 2.0]], dtype=F64)
    with pytest.raises(ValueError, match=r"samples contains NaN; shape \(\.\.\., N, H\)"):
        rul_distribution(x, 1.5)
    with pytest.raises(ValueError, match="samples"):
        fault_probability(x, 1.5)
