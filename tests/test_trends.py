"""Degradation-trend models (prognosis/trends.py) and the online learner trend (learner_trend.py)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from _kalman_reference import kalman_filter_tv

from prognos_torch.core import GaussianBelief
from prognos_torch.filters import ekf, run
from prognos_torch.prognosis import (
    TrendNoise,
    fit_learner_trend,
    fit_learner_trends,
    fit_trends,
    local_trend_model,
    path_grid,
    simulate_first_passage,
    trend_transition,
)

F64 = torch.float64


def _noise(level=0.01, slope=0.002, meas=0.01, wander=0.02, tau=0.5):
    return TrendNoise(*(torch.tensor(v, dtype=F64) for v in (level, slope, meas, wander, tau)))


def _degradation(n=80, seed=0, gaps=True):
    g = torch.Generator().manual_seed(seed)
    t = torch.sort(torch.rand(n, generator=g, dtype=F64) * 10).values
    L = math.log(0.5) + 0.3 * t + 0.05 * torch.randn(n, generator=g, dtype=F64).cumsum(0)
    y = 1.0 + L.exp() * torch.exp(0.1 * torch.randn(n, generator=g, dtype=F64))
    if gaps:
        y[[10, 11, 40]] = math.nan
    return t, y


@pytest.mark.parametrize("filt", ["ekf", "sckf"])
@pytest.mark.parametrize("shape", ["exponential", "power", "linear"])
def test_filter_equals_exact_kalman_filter(shape, filt):
    """Each shape's log (or linear) form is linear-Gaussian: the engine equals a Kalman filter
    with the same per-step F_k, Q_k, R_k (irregular times, missing values) to 1e-10."""
    t, y = _degradation()
    nz = _noise()
    fit = fit_trends(t, y, phi=1.0, sigma0=0.05, shapes=(shape,), filter=filt, noise={shape: nz})
    fit = fit[shape]
    z, s, a = fit.z.numpy(), fit.s.numpy(), fit.a.numpy()
    ds = np.diff(s, prepend=s[0])
    rho, SQ = trend_transition(torch.tensor(ds), nz)
    Fs = np.stack([np.array([[1, d, 0], [0, 1, 0], [0, 0, r]]) for d, r in zip(ds, rho.numpy())])
    Qs = (SQ @ SQ.mT).numpy()
    Rs = (a + 0.01)[:, None, None]
    H = np.array([[1.0, 0.0, 1.0]])
    P0 = (fit.prior.chol @ fit.prior.chol.mT).numpy()
    m, P, ll = kalman_filter_tv(Fs, H, Qs, Rs, fit.prior.mean.numpy(), P0, z[:, None])
    np.testing.assert_allclose(fit.means.numpy(), m, rtol=0, atol=1e-10)
    np.testing.assert_allclose((fit.chols @ fit.chols.mT).numpy(), P, rtol=0, atol=1e-10)
    assert fit.log_likelihood == pytest.approx(ll, abs=1e-9)


def test_log_form_is_the_exponential_model():
    """z = log(y - phi) and the delta-method variance sigma^2 / (y - phi)^2; values within one
    sigma of phi are missing."""
    t = torch.arange(5, dtype=F64)
    y = torch.tensor([1.01, 1.5, 2.0, 3.0, 5.0], dtype=F64)
    fit = fit_trends(t, y, phi=1.0, sigma0=0.1, shapes=("exponential",), filter="ekf")
    fit = fit["exponential"]
    assert math.isnan(float(fit.z[0]))
    torch.testing.assert_close(fit.z[1:], (y[1:] - 1.0).log())
    torch.testing.assert_close(fit.a[1:], 0.01 / (y[1:] - 1.0) ** 2)
    assert fit.to_z(3.0) == pytest.approx(math.log(2.0))
    torch.testing.assert_close(
        fit.to_y(torch.tensor([0.0], dtype=F64)), torch.tensor([2.0], dtype=F64)
    )


def test_noiseless_exponential_rul_equals_closed_form_crossing():
    """y = phi + theta exp(beta t) without noise: every path crosses at the closed-form time
    t* = (log(c - phi) - log theta) / beta, to the grid resolution."""
    phi, theta, beta = 0.15, 0.02, 0.8
    t = torch.linspace(0.0, 3.0, 61, dtype=F64)
    y = phi + theta * torch.exp(beta * t)
    zero = _noise(level=0.0, slope=0.0, meas=1e-14, wander=0.0, tau=1.0)
    fit = fit_trends(t, y, phi=phi, sigma0=1e-9, shapes=("exponential",), filter="ekf",
                     noise={"exponential": zero})["exponential"]  # fmt: skip
    m = fit.means[-1]
    assert float(m[0]) == pytest.approx(math.log(theta) + beta * 3.0, abs=1e-6)
    assert float(m[1]) == pytest.approx(beta, abs=1e-6)
    c = 0.6
    t_star = (math.log(c - phi) - math.log(theta)) / beta
    grid = path_grid(3.0, 5.0, 1e-3, rel=1e-4)
    pas = fit.first_passage(-1, c, grid, 200, torch.Generator().manual_seed(0))
    res = float(torch.diff(grid).max())
    assert torch.all((pas.times - t_star).abs() <= res + 1e-9)


def test_rul_intervals_are_calibrated_on_data_from_the_model():
    """Degradation simulated from the model itself (prior, level Brownian motion, slope random
    walk, OU wander, white noise): the 90 % interval of the first passage of L + c, from the
    exact filter's posterior, covers the true crossing in 0.9 +- 3 binomial std of the runs."""
    B, n, dt = 300, 40, 0.05
    g = torch.Generator().manual_seed(3)
    nz = _noise(level=0.02, slope=0.05, meas=0.01, wander=0.02, tau=0.3)
    m0 = torch.tensor([0.0, 1.0, 0.0], dtype=F64)
    S0 = torch.diag(torch.tensor([0.1, 0.3, math.sqrt(0.02)], dtype=F64))
    x = m0 + torch.randn(B, 3, generator=g, dtype=F64) @ S0.mT
    rho, SQ = trend_transition(torch.tensor(dt, dtype=F64), nz)
    ys = []
    for _ in range(n):
        x = torch.stack([x[:, 0] + dt * x[:, 1], x[:, 1], rho * x[:, 2]], -1)
        x = x + torch.randn(B, 3, generator=g, dtype=F64) @ SQ.mT
        ys.append(x[:, 0] + x[:, 2] + 0.1 * torch.randn(B, generator=g, dtype=F64))
    ys = torch.stack(ys)[..., None]  # (n, B, 1)
    level = 3.0
    # the truth: continue the same process on a fine grid until L + c reaches the level
    true = torch.full((B,), math.inf, dtype=F64)
    h, k = 0.01, 0
    rho_h, SQ_h = trend_transition(torch.tensor(h, dtype=F64), nz)
    while bool(torch.isinf(true).any()) and k < 1500:  # horizon 15: beyond it, censored
        k += 1
        x = torch.stack([x[:, 0] + h * x[:, 1], x[:, 1], rho_h * x[:, 2]], -1)
        x = x + torch.randn(B, 3, generator=g, dtype=F64) @ SQ_h.mT
        hit = torch.isinf(true) & (x[:, 0] + x[:, 2] >= level)
        true = torch.where(hit, torch.full_like(true, k * h), true)
    assert float(torch.isfinite(true).to(F64).mean()) > 0.9
    # the exact filter, batched over the runs
    rho_b = rho.expand(n, B)
    model = local_trend_model(SQ.expand(n, B, 3, 3), rho_b, torch.full((n, B), 0.01, dtype=F64))
    us = torch.stack([torch.full((n, B), dt, dtype=F64), rho_b], -1)
    belief = GaussianBelief(m0.expand(B, 3).clone(), S0.expand(B, 3, 3).clone())
    post = run(ekf(), model, belief, ys, us).final.belief
    hp = 0.02  # prediction grid (the truth's crossing is within one step of it)
    grid = torch.arange(1, 751, dtype=F64) * hp
    noise_b = TrendNoise(*(v.expand(B) for v in nz._fields()))
    first, _ = simulate_first_passage(
        post.mean, post.chol, noise_b, torch.full((750,), hp, dtype=F64), level, 500, g
    )
    beyond = 1e6  # censored paths: a finite stand-in (torch.quantile turns inf into NaN)
    pred = torch.cat([grid, torch.tensor([beyond], dtype=F64)])[first]  # (B, N)
    lo, hi = pred.quantile(0.05, dim=1), pred.quantile(0.95, dim=1)
    true = torch.where(torch.isinf(true), torch.full_like(true, beyond), true)
    cover = float(((true >= lo) & (true <= hi)).to(F64).mean())
    tol = 3 * math.sqrt(0.9 * 0.1 / B) + 0.01  # binomial spread + grid and path Monte Carlo
    assert abs(cover - 0.9) <= tol, cover


@pytest.mark.parametrize("tau", [5.0, 0.002])
def test_first_passage_paths_follow_the_exact_recursion(tau):
    """The simulated paths are the sequential recursion ``L += ds beta + w_L``, ``beta += w_b``,
    ``c = rho c + w_c`` with the same draws, across chunk boundaries: with a slow wander (the
    cumulative-product form) and with one that decays so fast that ``prod rho`` underflows
    (the decay-matrix form). There the cumulative-product form overflowed, and about half of the
    paths 'crossed' an unreachable level at one step."""
    N, chunk = 40, 16
    noise = TrendNoise(*(torch.tensor([v], dtype=F64) for v in (1e-4, 1e-6, 0.0, 0.04, tau)))
    m = torch.tensor([[0.0, 0.01, 0.0]], dtype=F64)
    S = torch.diag(torch.tensor([0.01, 0.001, 0.2], dtype=F64))[None]
    grid = path_grid(0.0, 300.0, 0.5, rel=0.02)
    ds = torch.diff(torch.cat([grid.new_zeros(1), grid]))
    J = ds.numel()
    first, levels = simulate_first_passage(
        m, S, noise, ds, 1e6, N, torch.Generator().manual_seed(3), keep=N, chunk=chunk
    )
    assert bool((first == J).all())  # 1e6 is never reached
    g = torch.Generator().manual_seed(3)  # the same draws, in the same order
    x = m[:, None, :] + torch.randn(1, N, 3, generator=g, dtype=F64) @ S.mT
    ref = []
    for j0 in range(0, J, chunk):
        d = ds[j0 : j0 + chunk]
        rho, SQ = trend_transition(d[None], TrendNoise(*(v[:, None] for v in noise._fields())))
        w = torch.randn(1, N, d.numel(), 3, generator=g, dtype=F64)
        w = (SQ[:, None] @ w.unsqueeze(-1)).squeeze(-1)
        for k in range(d.numel()):
            L = x[..., 0] + d[k] * x[..., 1] + w[:, :, k, 0]
            x = torch.stack(
                [L, x[..., 1] + w[:, :, k, 1], rho[0, k] * x[..., 2] + w[:, :, k, 2]], -1
            )
            ref.append(x[0, :, 0] + x[0, :, 2])
    torch.testing.assert_close(levels, torch.stack(ref, -1), rtol=1e-9, atol=1e-12)


def test_noise_chosen_by_maximum_likelihood_and_band_floor():
    t, y = _degradation(gaps=False)
    fits = fit_trends(t, y, phi=1.0, sigma0=0.05, filter="ekf")
    for fit in fits.values():
        assert fit.choice == int(torch.argmax(fit.grid_log_likelihood))
        assert float(fit.grid.level.min()) > 0  # the predictive band never collapses
        other = fit.select((fit.choice + 1) % fit.grid.level.numel())
        assert other.log_likelihood <= fit.log_likelihood


def _fixed_learner(n, seed=0, drift=1.0):
    """An exponential degradation observed n times over the same span; level noise off."""
    g = torch.Generator().manual_seed(seed)
    t = torch.linspace(0.0, 4.0, n, dtype=F64)
    y = 0.2 + 0.05 * torch.exp(0.6 * t) * torch.exp(0.05 * torch.randn(n, generator=g, dtype=F64))
    nz = _noise(level=0.0, slope=0.0, meas=0.0025, wander=0.0, tau=1.0)
    fit = fit_trends(t, y, phi=0.2, sigma0=1e-6, shapes=("exponential",), filter="ekf",
                     noise={"exponential": nz})["exponential"]  # fmt: skip
    return fit_learner_trend(fit, seed=seed, max_steps=10_000, drift=drift)


def test_learner_keeps_learning_and_its_covariance_drives_the_rul_interval():
    """The ELM of time trained online by the Kalman optimiser (one step per observation, here
    without the random walk: recursive least squares): its parameter covariance shrinks as
    observations accrue, and the RUL interval, whose width here comes only from sampling theta
    from that covariance, narrows with it."""
    stds, widths = [], []
    for n in (30, 120, 480):
        lt = _fixed_learner(n, drift=0.0)
        assert bool((torch.diff(lt.trace) <= 1e-9 * lt.trace[0]).all())  # P never grows
        stds.append(float(lt.predictive_std(torch.tensor([4.0, 5.0], dtype=F64)).max()))
        grid = path_grid(4.0, 20.0, 0.01, rel=0.005)
        pas = lt.first_passage(-1, 2.0, grid, 1000, torch.Generator().manual_seed(1))
        times = torch.where(torch.isinf(pas.times), torch.full_like(pas.times, 1e6), pas.times)
        q = times.quantile(torch.tensor([0.05, 0.95], dtype=F64))  # censored: beyond any
        widths.append(float(q[1] - q[0]))
    assert stds[0] > stds[1] > stds[2]
    assert widths[0] > widths[1] > widths[2]
    # the belief the paths sample is the optimiser's own
    lt = _fixed_learner(120)
    b = lt.parameter_belief(-1)
    torch.testing.assert_close(b.chol @ b.chol.mT, lt.optimizer.parameter_covariance())
    # with the random walk (default) the parameters keep moving: P stops shrinking at a floor
    assert float(lt.trace[-1]) < float(lt.trace[0])


def test_learner_snapshots_follow_the_data_order():
    """The belief recorded at index 29 is the one after the first 30 observations: it differs
    from the final one and has the larger predictive spread at the last time."""
    lt = _fixed_learner(60, drift=0.0)
    fit = lt.level_fit
    lt2 = fit_learner_trend(fit, snapshots=(29,), max_steps=10_000, drift=0.0)
    torch.testing.assert_close(lt2.parameter_belief(-1).mean, lt.parameter_belief(-1).mean)
    t_end = fit.t[-1:]
    assert float(lt2.predictive_std(t_end, 29)) > float(lt2.predictive_std(t_end, -1))
    assert 29 in lt2.snapshots and int(lt2.seen[-1]) == 60


def test_learner_ensemble_members_are_the_single_learners_of_their_seeds():
    """fit_learner_trends: member j is fit_learner_trend with features of seed
    ``seed * members + j``; the ensemble's paths are the members' paths, an equal share each,
    drawn in member order from one generator; one member is the single learner itself."""
    fit = _fixed_learner(60).level_fit
    kw = dict(max_steps=10_000, snapshots=(29,))
    grid = path_grid(4.0, 20.0, 0.01, rel=0.005)
    ens = fit_learner_trends(fit, members=3, seed=2, **kw)
    singles = [fit_learner_trend(fit, seed=6 + j, **kw) for j in range(3)]
    for m, one in zip(ens.members, singles):
        torch.testing.assert_close(m.parameter_belief(29).mean, one.parameter_belief(29).mean,
                                   rtol=0, atol=0)  # fmt: skip
    got = ens.first_passage(29, 2.0, grid, 100, torch.Generator().manual_seed(5))
    g = torch.Generator().manual_seed(5)
    ref = torch.cat([one.first_passage(29, 2.0, grid, n, g).times
                     for one, n in zip(singles, (34, 33, 33))])  # fmt: skip
    torch.testing.assert_close(got.times, ref, rtol=0, atol=0)
    solo = fit_learner_trends(fit, members=1, seed=4, **kw).first_passage(
        -1, 2.0, grid, 50, torch.Generator().manual_seed(1)
    )
    ref1 = fit_learner_trend(fit, seed=4, **kw).first_passage(
        -1, 2.0, grid, 50, torch.Generator().manual_seed(1)
    )
    torch.testing.assert_close(solo.times, ref1.times, rtol=0, atol=0)
    with pytest.raises(ValueError, match="members must be an int >= 1"):
        fit_learner_trends(fit, members=0)


def test_bad_input():
    t, y = _degradation(gaps=False)
    with pytest.raises(ValueError, match="shape"):
        fit_trends(t, y[:-1], phi=1.0, sigma0=0.1)
    with pytest.raises(ValueError, match="sigma0"):
        fit_trends(t, y, phi=1.0, sigma0=0.0)
    with pytest.raises(ValueError, match="usable"):
        fit_trends(t, torch.full_like(y, 0.5), phi=1.0, sigma0=0.1, shapes=("exponential",))
    with pytest.raises(ValueError, match="shape must be"):
        fit_trends(t, y, phi=1.0, sigma0=0.1, shapes=("cubic",))
    fit = fit_trends(t, y, phi=1.0, sigma0=0.1, filter="ekf")["linear"]
    with pytest.raises(ValueError, match="after the origin"):
        fit.first_passage(-1, 10.0, t[:5], 10, torch.Generator())


def test_trend_pool_splits_the_paths_evenly():
    from prognos_torch.prognosis.trends import Passage, TrendPool

    class Fake:
        def __init__(self, value):
            self.value = value

        def first_passage(self, index, level, grid, n, gen, *, keep=0):
            return Passage(torch.full((n,), self.value, dtype=F64),
                           torch.full((keep, grid.numel()), self.value, dtype=F64),
                           torch.zeros(n, dtype=torch.bool))  # fmt: skip

    grid = torch.arange(1.0, 4.0, dtype=F64)
    p = TrendPool((Fake(1.0), Fake(2.0))).first_passage(-1, 0.0, grid, 2001, None, keep=101)
    assert p.times.shape == (2001,) and p.diverged.shape == (2001,)
    assert int((p.times == 1.0).sum()) == 1001 and int((p.times == 2.0).sum()) == 1000
    assert p.paths.shape == (101, 3) and float(p.paths[:51].max()) == 1.0
    assert float(p.paths[51:].min()) == 2.0
    one = TrendPool((Fake(3.0),)).first_passage(-1, 0.0, grid, 10, None, keep=100)
    assert one.paths.shape == (100, 3) and one.times.shape == (10,)
    # nested: an ensemble inside a pool gets its half, split again (prognose's auto pool)
    inner = TrendPool(tuple(Fake(v) for v in (3.0, 4.0, 5.0, 6.0)))
    nest = TrendPool((Fake(1.0), inner)).first_passage(-1, 0.0, grid, 2000, None, keep=100)
    counts = [int((nest.times == v).sum()) for v in (1.0, 3.0, 4.0, 5.0, 6.0)]
    assert counts == [1000, 250, 250, 250, 250] and nest.paths.shape == (100, 3)
    with pytest.raises(ValueError, match="members must be a non-empty tuple"):
        TrendPool(())


def test_sampling_arguments_are_checked_by_name():
    from prognos_torch.prognosis import TrendPool

    t = torch.arange(60, dtype=F64)
    rng = np.random.default_rng(5)
    y = torch.tensor(1.0 + 0.2 * np.exp(0.05 * np.arange(60)) + 0.05 * rng.standard_normal(60))
    fits = fit_trends(t, y, phi=1.0, sigma0=0.05)
    grid = path_grid(59.0, 200.0, 1.0)
    g = torch.Generator().manual_seed(0)
    for shape in ("exponential", "linear"):  # a NaN level: every path "crossed" / none did
        with pytest.raises(ValueError, match="level must be a finite number, got nan"):
            fits[shape].first_passage(-1, math.nan, grid, 20, g)
    with pytest.raises(ValueError, match="n_paths must be an int >= the 3 members"):
        TrendPool(tuple(fits.values())).first_passage(-1, 20.0, grid, 2, g)  # (ZeroDivisionError)
    with pytest.raises(ValueError, match="n_paths must be an int >= 1, got 0"):
        fits["linear"].first_passage(-1, 20.0, grid, 0, g)
    for bad in ([61.0, 70.0, 65.0, 80.0], [61.0, math.nan, 80.0]):  # (taken silently)
        with pytest.raises(ValueError, match="finite, strictly increasing times"):
            fits["linear"].first_passage(-1, 5.0, torch.tensor(bad, dtype=F64), 5, g)
    # no hidden draw from torch's global stream
    with pytest.raises(TypeError, match="generator must be a torch.Generator, got NoneType"):
        fits["linear"].first_passage(-1, 20.0, grid, 5, None)
    for args, match in [((0.0, 1e3, 1.0, 0.0), "rel must be a positive"),
                        ((0.0, 1e3, 1.0, math.nan), "rel must be a positive"),
                        ((0.0, math.inf, 1.0), "positive finite numbers"),
                        ((math.nan, 10.0, 1.0), "t_origin must be a finite time")]:  # fmt: skip
        with pytest.raises(ValueError, match=match):
            path_grid(*args)
