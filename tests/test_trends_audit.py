"""Audit of prognosis/trends.py against exact references written here (no library code)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from prognos_torch.core import GaussianBelief
from prognos_torch.prognosis import (
    TrendNoise,
    fit_trends,
    local_trend_model,
    path_grid,
    simulate_first_passage,
    trend_measurement,
)

F64 = torch.float64


def _nz(level, slope, meas, wander=0.0, tau=1.0, batch=False):
    vals = (level, slope, meas, wander, tau)
    return TrendNoise(*(torch.tensor([v] if batch else v, dtype=F64) for v in vals))


def _kf_log_form(z, s, a, ql, qb, r, m0, P0):
    """The module docstring's model by hand: x = [L, beta] (beta a random-walk state),
    L_k = L_{k-1} + ds beta + w_L, z_k = L_k + v_k, v ~ N(0, r + a_k); NaN: missing."""
    m, P, prev = m0.copy(), P0.copy(), s[0]
    means, covs, ll = [], [], 0.0
    for zk, sk, ak in zip(z, s, a):
        d, prev = sk - prev, sk
        F = np.array([[1.0, d], [0.0, 1.0]])
        Q = np.array([[ql * d + qb * d**3 / 3, qb * d**2 / 2], [qb * d**2 / 2, qb * d]])
        m, P = F @ m, F @ P @ F.T + Q
        if not np.isnan(zk):
            S = P[0, 0] + r + ak
            K = P[:, 0] / S
            e = zk - m[0]
            ll += -0.5 * (math.log(2 * math.pi * S) + e * e / S)
            m, P = m + K * e, P - np.outer(K, P[0])
        means.append(m.copy())
        covs.append(P.copy())
    return np.array(means), np.array(covs), ll


@pytest.mark.parametrize("filt", ["ekf", "sckf"])
def test_exponential_fit_is_a_kalman_filter_on_log_excess_with_random_walk_slope(filt):
    """Irregular times, a gap, a value within sigma0 of phi (missing): with no wander (and no
    wander in the prior) the engine is the two-state Kalman filter on z = log(y - phi)."""
    g = torch.Generator().manual_seed(7)
    t = torch.sort(torch.rand(50, generator=g, dtype=F64) * 8).values
    y = 1.0 + 0.3 * torch.exp(0.4 * t + 0.05 * torch.randn(50, generator=g, dtype=F64))
    y[[5, 6]] = math.nan
    y[2] = 1.0 + 0.01  # below sigma0 = 0.02 above phi: no usable logarithm
    ql, qb, r = 2e-3, 3e-4, 1e-3
    prior = GaussianBelief(torch.tensor([-1.0, 0.2, 0.0], dtype=F64),
                           torch.diag(torch.tensor([2.0, 0.5, 1e-9], dtype=F64)))  # fmt: skip
    fit = fit_trends(t, y, phi=1.0, sigma0=0.02, shapes=("exponential",), filter=filt,
                     noise={"exponential": _nz(ql, qb, r, 0.0, 8.0)},
                     prior={"exponential": prior})["exponential"]  # fmt: skip
    yn = y.numpy()
    z = np.where(yn - 1.0 >= 0.02, np.log(np.where(yn - 1.0 > 0, yn - 1.0, 1.0)), np.nan)
    a = np.where(np.isnan(z), 0.0, 0.02**2 / (yn - 1.0) ** 2)
    assert np.isnan(z[[2, 5, 6]]).all()
    m, P, ll = _kf_log_form(z, t.numpy(), a, ql, qb, r, np.array([-1.0, 0.2]), np.diag([4.0, 0.25]))
    np.testing.assert_allclose(fit.means[:, :2].numpy(), m, rtol=0, atol=1e-10)
    np.testing.assert_allclose((fit.chols @ fit.chols.mT)[:, :2, :2].numpy(), P, atol=1e-10)
    assert float(fit.means[:, 2].abs().max()) < 1e-12
    assert fit.log_likelihood == pytest.approx(ll, abs=1e-9)


@pytest.mark.parametrize("shape", ["exponential", "power", "linear"])
def test_measurement_maps_transforms_and_jacobians(shape):
    t = torch.tensor([0.5, 1.0, 2.5, 4.0], dtype=F64)
    y = torch.tensor([2.0, 2.4, 3.5, 7.0], dtype=F64)
    phi, sigma0, t0 = 1.5, 0.1, 0.2
    z, s, a = trend_measurement(shape, t, y, phi=phi, sigma0=sigma0, t0=t0)
    tn, yn = t.numpy(), y.numpy()
    z_ref = yn if shape == "linear" else np.log(yn - phi)
    s_ref = {"exponential": tn, "power": np.log(tn - t0), "linear": tn}[shape]
    a_ref = np.full(4, sigma0**2) if shape == "linear" else sigma0**2 / (yn - phi) ** 2
    np.testing.assert_allclose(z.numpy(), z_ref, rtol=1e-15)
    np.testing.assert_allclose(s.numpy(), s_ref, rtol=1e-15)
    np.testing.assert_allclose(a.numpy(), a_ref, rtol=1e-14)
    # to_z / to_y / clock of a fit of the shape are the same maps and inverse to each other
    fit = fit_trends(t, y, phi=phi, sigma0=sigma0, shapes=(shape,), filter="ekf")[shape]
    for level in (1.7, 3.0, 12.5):
        zl = fit.to_z(level)
        assert zl == pytest.approx(level if shape == "linear" else math.log(level - phi), rel=1e-15)
        assert float(fit.to_y(torch.tensor(zl, dtype=F64))) == pytest.approx(level, rel=1e-14)
    if shape != "linear":
        assert fit.to_z(phi) == -math.inf and fit.to_z(phi - 1.0) == -math.inf
    clock_ref = np.log(tn - fit.t0) if shape == "power" else tn
    np.testing.assert_allclose(fit.clock(t).numpy(), clock_ref, rtol=1e-15)
    np.testing.assert_allclose(fit.s.numpy(), clock_ref, rtol=1e-15)
    # the model's analytic Jacobians against central finite differences
    model = local_trend_model(torch.eye(3, dtype=F64).expand(2, 3, 3), torch.ones(2, dtype=F64),
                              torch.ones(2, dtype=F64))  # fmt: skip
    x = torch.tensor([0.3, -0.7, 0.4], dtype=F64)
    u = torch.tensor([0.37, 0.81], dtype=F64)
    eps = 1e-6
    for fun, jac in ((model.f, model.jac_f), (model.h, model.jac_h)):
        fd = torch.stack(
            [(fun(x + eps * e, u, 1) - fun(x - eps * e, u, 1)) / (2 * eps)
             for e in torch.eye(3, dtype=F64)], -1)  # fmt: skip
        torch.testing.assert_close(jac(x, u, 1), fd, rtol=0, atol=1e-9)
    torch.testing.assert_close(model.f(x, u, 1), torch.tensor([0.3 - 0.37 * 0.7, -0.7, 0.81 * 0.4],
                                                              dtype=F64))  # fmt: skip


def test_noiseless_power_law_crossing_is_the_closed_form_time_on_the_grid():
    """y = phi + A (t - t0)^b: the crossing of X is t* = t0 + ((X - phi) / A)^(1 / b), reported
    as the first grid time at or past it (no interpolation inside a step)."""
    phi, A, b = 0.4, 0.05, 1.7
    t = torch.linspace(1.0, 6.0, 51, dtype=F64)
    t0 = 1.0 - 0.1  # the fit's origin: one median step before the first time
    y = phi + A * (t - t0) ** b
    zero = _nz(0.0, 0.0, 1e-14, 0.0, 1.0)
    fit = fit_trends(t, y, phi=phi, sigma0=1e-9, shapes=("power",), filter="ekf",
                     noise={"power": zero})["power"]  # fmt: skip
    assert fit.t0 == pytest.approx(t0, abs=1e-13)
    assert float(fit.means[-1, 1]) == pytest.approx(b, abs=1e-6)
    X = 3.0
    t_star = t0 + ((X - phi) / A) ** (1 / b)
    grid = path_grid(6.0, 40.0, 0.05, rel=0.01)
    pas = fit.first_passage(-1, X, grid, 50, torch.Generator().manual_seed(0))
    expect = float(grid[int(np.searchsorted(grid.numpy(), t_star))])
    assert torch.all(pas.times == expect)


def _snapped_mc(L0, beta, z_level, h):
    """Noiseless lines L0 + beta h from their origin: the first grid step at or past the
    crossing time (len(h): none within the horizon)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        tc = np.where(L0 >= z_level, 0.0, np.where(beta > 0, (z_level - L0) / beta, np.inf))
    return np.searchsorted(h, tc, side="left")


def test_gaussian_posterior_crossing_times_match_numpy_monte_carlo_and_censor_at_horizon():
    """Parameters N(m, S S^T) on [L, beta], no process noise: each path is a line and crosses at
    (z - L0) / beta. The simulated first grid steps against an independent NumPy Monte Carlo:
    the CDF at every 10th step and the censored mass agree within 5 binomial std of the
    difference of two samples of 20000."""
    m = torch.tensor([[0.0, 0.5, 0.0]], dtype=F64)
    S = torch.tensor([[[0.3, 0.0, 0.0], [-0.05, 0.2, 0.0], [0.0, 0.0, 0.0]]], dtype=F64)
    grid = path_grid(0.0, 8.0, 0.05, rel=0.02)
    h = grid.numpy()
    ds = torch.diff(torch.cat([grid.new_zeros(1), grid]))
    N, z_level = 20000, 2.0
    first, _ = simulate_first_passage(m, S, _nz(0.0, 0.0, 0.0, batch=True), ds, z_level, N,
                                      torch.Generator().manual_seed(11))  # fmt: skip
    ours = first[0].numpy()
    rng = np.random.default_rng(12)
    x = m[0, :2].numpy() + rng.standard_normal((N, 2)) @ S[0, :2, :2].numpy().T
    ref = _snapped_mc(x[:, 0], x[:, 1], z_level, h)
    J = len(h)
    for k in list(range(0, J, 10)) + [J]:  # k = J: every path, 1 - CDF(J - 1) = censored
        p1, p2 = (ours < k).mean(), (ref < k).mean()
        p = (p1 + p2) / 2
        assert abs(p1 - p2) <= 5 * math.sqrt(max(p * (1 - p), 1e-4) * 2 / N) + 1e-12, (k, p1, p2)
    assert 0.05 < (ref == J).mean() < 0.5  # the horizon censors a good part of them
    # and, with the same draws, path by path exactly (the sampling is x0 = m + S e)
    e = torch.randn(1, N, 3, generator=torch.Generator().manual_seed(11), dtype=F64)
    x0 = (m[:, None] + e @ S.mT)[0].numpy()
    np.testing.assert_array_equal(ours, _snapped_mc(x0[:, 0], x0[:, 1], z_level, h))


def test_censoring_at_the_horizon_and_crossing_on_a_grid_point():
    """A noiseless line is reported at the first grid time at or past its crossing; one that
    would reach the level past the last grid time is censored (inf)."""
    t = torch.arange(0.0, 10.0, dtype=F64)
    y = 2.0 + 0.5 * t
    fit = fit_trends(t, y, phi=0.0, sigma0=1e-9, shapes=("linear",), filter="ekf",
                     noise={"linear": _nz(0.0, 0.0, 1e-14)})["linear"]  # fmt: skip
    grid = torch.tensor([10.0, 12.0, 16.0], dtype=F64)  # line: 7, 8, 10
    gen = torch.Generator().manual_seed(0)
    assert torch.all(fit.first_passage(-1, 7.9, grid, 5, gen).times == 12.0)
    assert torch.all(fit.first_passage(-1, 8.1, grid, 5, gen).times == 16.0)
    assert torch.all(fit.first_passage(-1, 10.1, grid, 5, gen).times == math.inf)
    assert torch.all(fit.first_passage(-1, 6.0, grid, 5, gen).times == 10.0)  # at 6.5 already


def test_path_grid_is_linear_then_geometric_and_ends_at_the_horizon():
    g = path_grid(3.0, 1000.0, 1.0, rel=0.02).numpy() - 3.0
    np.testing.assert_allclose(g[:50], np.arange(1, 51), rtol=0, atol=1e-12)
    geo = 50.0 * 1.02 ** np.arange(1, 200)
    geo = geo[geo < 1000.0]
    np.testing.assert_allclose(g[50:-1], geo, rtol=1e-13)
    assert g[-1] == 1000.0 and len(g) == 50 + len(geo) + 1
    # a horizon inside the linear part: steps of dt, the horizon last
    np.testing.assert_allclose(path_grid(0.0, 3.5, 1.0).numpy(), [1.0, 2.0, 3.0, 3.5])


def test_path_grid_stays_strictly_increasing_after_a_large_origin():
    """The horizon's clamp left a step of one ulp of the horizon (5.1 vs 5.1000000000000005),
    which vanished once added to a large origin: the grid repeated a time and first_passage
    refused it ("strictly increasing")."""
    origin, horizon = 489545.17024207255, 5.1000000000000005
    grid = path_grid(origin, horizon, 0.1, rel=0.02)
    assert bool((grid.diff() > 0).all()) and float(grid[-1]) == origin + horizon
    t = origin + torch.arange(-9.0, 1.0, dtype=F64)
    fit = fit_trends(t, 1.0 + torch.arange(10, dtype=F64), phi=0.0, sigma0=0.1,
                     shapes=("linear",), noise={"linear": _nz(0.0, 0.0, 1e-6)})["linear"]  # fmt: skip
    times = fit.first_passage(-1, 13.0, grid, 4, torch.Generator().manual_seed(0)).times
    assert bool(((times - (origin + 3.0)).abs() <= 0.5).all())  # no refusal: crosses near +3


def test_prior_of_the_wrong_size_is_refused_by_name():
    t = torch.linspace(0.0, 5.0, 20, dtype=F64)
    y = 1.0 + 0.1 * torch.exp(0.5 * t)
    two = GaussianBelief(torch.zeros(2, dtype=F64), torch.eye(2, dtype=F64))
    with pytest.raises(ValueError, match=r"prior of 'exponential' must be on \[L, beta, c\]"):
        fit_trends(t, y, phi=1.0, sigma0=0.01, shapes=("exponential",),
                   prior={"exponential": two})  # fmt: skip


def test_learner_trend_paths_refuse_a_bad_grid_count_or_generator():
    """LearnerTrendFit.first_passage took a grid that steps back (sqrt of a negative step: a
    path quietly counted as diverged), any n_paths, and generator=None (the global stream);
    TrendFit.first_passage refused each."""
    from prognos_torch.prognosis import fit_learner_trend

    g = torch.Generator().manual_seed(0)
    t = torch.sort(torch.rand(60, generator=g, dtype=torch.float64) * 10).values
    y = 1.0 + 0.5 * torch.exp(0.3 * t + 0.05 * torch.randn(60, generator=g, dtype=torch.float64))
    level = fit_trends(t, y, phi=1.0, sigma0=0.05, shapes=("exponential",), filter="ekf")
    fit = fit_learner_trend(level["exponential"])
    grid = torch.tensor([10.5, 11.0, 12.0], dtype=torch.float64)
    ok = fit.first_passage(-1, 30.0, grid, 8, torch.Generator().manual_seed(1))
    assert ok.times.shape == (8,)
    back = torch.tensor([10.5, 11.0, 10.8], dtype=torch.float64)
    with pytest.raises(ValueError, match="strictly increasing"):
        fit.first_passage(-1, 30.0, back, 8, torch.Generator().manual_seed(1))
    with pytest.raises(ValueError, match="n_paths must be an int >= 1"):
        fit.first_passage(-1, 30.0, grid, 0, torch.Generator().manual_seed(1))
    with pytest.raises(TypeError, match="generator must be a torch.Generator"):
        fit.first_passage(-1, 30.0, grid, 8, None)


def test_trend_paths_refuse_an_index_past_the_data_a_bad_keep_or_grid():
    """TrendFit.first_passage and belief took index n + 5 as torch's IndexError and a bool as a
    new dimension; keep=2.5 failed on slice indices and keep=-1 kept nothing; a list grid
    raised AttributeError. The learner trend and the pool refuse the same way."""
    from prognos_torch.prognosis import TrendPool

    g = torch.Generator().manual_seed(0)
    t = torch.linspace(0.0, 10.0, 40, dtype=F64)
    y = 1.0 + 0.5 * torch.exp(0.3 * t + 0.05 * torch.randn(40, generator=g, dtype=F64))
    fit = fit_trends(t, y, phi=1.0, sigma0=0.05, shapes=("exponential",))["exponential"]
    grid = torch.tensor([10.5, 11.0, 12.0], dtype=F64)
    gen = torch.Generator().manual_seed(1)
    for bad in (40, 45, -41):
        with pytest.raises(ValueError, match=r"index must be an observation index in \[-40, 40\)"):
            fit.first_passage(bad, 30.0, grid, 8, gen)
        with pytest.raises(ValueError, match="observation index"):
            fit.belief(bad)
    for bad in (True, 2.0):
        with pytest.raises(TypeError, match="index must be an int"):
            fit.first_passage(bad, 30.0, grid, 8, gen)
    for bad in (2.5, True, -1):
        with pytest.raises(ValueError, match="keep must be a non-negative int"):
            fit.first_passage(-1, 30.0, grid, 8, gen, keep=bad)
        with pytest.raises(ValueError, match="keep must be a non-negative int"):
            TrendPool((fit, fit)).first_passage(-1, 30.0, grid, 8, gen, keep=bad)
    with pytest.raises(TypeError, match=r"grid must be a torch.Tensor of shape \(J,\)"):
        fit.first_passage(-1, 30.0, [10.5, 11.0], 8, gen)
    # a valid index in either spelling is the same observation (the same draws)
    a = fit.first_passage(39, 3.0, grid, 8, torch.Generator().manual_seed(2), keep=2)
    b = fit.first_passage(np.int64(-1), 3.0, grid, 8, torch.Generator().manual_seed(2), keep=2)
    assert torch.equal(a.times, b.times) and torch.equal(a.paths, b.paths)
    assert torch.equal(fit.belief(-1).mean, fit.means[39])
