"""Fleet RUL (prognos_torch.fleet): batched equals per asset, shard-size and backend
invariance, the trend filter against exact Bayesian regression / Kalman recursions, tables in
and out, bad input, atomic output, the command line."""

from __future__ import annotations

import math
import os
import re

import numpy as np
import pytest
import torch

from prognos_torch.cli import main as cli_main
from prognos_torch.fleet import (
    DATE_COLUMNS,
    METHODS,
    MISFIT_P,
    OUTPUT_COLUMNS,
    RUL_COLUMNS,
    exponential_trend_rul,
    fleet_rul,
    ksigma_onset_batch,
    pad_batch,
    read_fleet_table,
    synthetic_fleet,
    write_table,
)


@pytest.fixture(scope="module")
def fleet():
    return synthetic_fleet(60, 200, seed=3, ragged=0.5, healthy_fraction=0.1)


@pytest.fixture(scope="module")
def whole(fleet):
    """The fleet in one shard (the default shard size), 300 samples: the reference that other
    shard sizes, worker processes and Ray are compared with (read only)."""
    return fleet_rul(read_fleet_table(fleet.table), fleet.threshold, samples=300)


def _assert_same(a, b, rtol=1e-12):
    assert a.columns["asset"] == b.columns["asset"]
    assert a.columns["flags"] == b.columns["flags"]
    for c in RUL_COLUMNS:
        np.testing.assert_allclose(
            np.array(a.columns[c]), np.array(b.columns[c]), rtol=rtol, atol=0, equal_nan=True
        )


def test_fleet_equals_the_per_asset_loop_and_does_not_depend_on_the_shard_size(fleet, whole):
    tab = read_fleet_table(fleet.table)
    assert whole.shard_size >= len(tab)  # one shard
    for size in (1, 7, 25):
        _assert_same(whole, fleet_rul(tab, fleet.threshold, samples=300, shard_size=size))
    # an explicit loop: each asset alone in its own table
    for j in (0, 5, 17, 42):
        a = fleet.assets[j]
        rows = fleet.table["asset"] == a
        alone = {k: v[rows] for k, v in fleet.table.items()}
        one = fleet_rul(alone, fleet.threshold, samples=300)
        for c in RUL_COLUMNS:
            x, y = one.columns[c][0], whole.row(a)[c]
            assert (math.isnan(x) and math.isnan(y)) or math.isclose(x, y, rel_tol=1e-12), c
        assert one.columns["flags"][0] == whole.row(a)["flags"]
    # the table order of the assets does not matter either
    perm = np.random.default_rng(0).permutation(len(fleet.table["asset"]))
    shuffled = {k: v[perm] for k, v in fleet.table.items()}
    with pytest.raises(ValueError, match="times must increase"):
        fleet_rul(shuffled, fleet.threshold)
    idx = np.concatenate([np.flatnonzero(fleet.table["asset"] == a) for a in fleet.assets[::-1]])
    reverse = {k: v[idx] for k, v in fleet.table.items()}  # assets in reverse order
    by_time = np.argsort(fleet.table["t"], kind="stable")
    interleaved = {k: v[by_time] for k, v in fleet.table.items()}  # assets interleaved
    for table, order in ((reverse, fleet.assets[::-1]), (interleaved, None)):
        res = fleet_rul(table, fleet.threshold, samples=300, shard_size=9)
        if order is not None:
            assert res.columns["asset"] == order
        for a in fleet.assets:
            r1, r2 = res.row(a), whole.row(a)
            assert r1["flags"] == r2["flags"]
            for c in RUL_COLUMNS:
                assert (math.isnan(r1[c]) and math.isnan(r2[c])) or r1[c] == r2[c]


def test_output_columns_and_flags(fleet):
    res = fleet_rul(fleet.table, fleet.threshold, samples=300, horizon=50.0)
    assert tuple(res.columns) == OUTPUT_COLUMNS + ("phi",)  # (phi="auto": the offset used)
    fixed = fleet_rul(fleet.table, fleet.threshold, samples=300, horizon=50.0, phi=0.0)
    assert tuple(fixed.columns) == OUTPUT_COLUMNS
    healthy = [a for a, on in zip(fleet.assets, fleet.onset) if not np.isfinite(on)]
    assert healthy and all("no_onset" in res.row(a)["flags"] for a in healthy)
    for a in healthy:
        assert math.isnan(res.row(a)["rul_median"])  # no number before onset
    ok = [i for i, v in enumerate(res.columns["rul_median"]) if not math.isnan(v)]
    assert len(ok) > 40
    for i in ok:
        q05, med, q95 = (res.columns[c][i] for c in ("rul_q05", "rul_median", "rul_q95"))
        assert q05 <= med <= q95
        p = res.columns["p_fail_within_horizon"][i]
        assert 0.0 <= p <= 1.0 and res.columns["censored_mass"][i] <= 1.0 - p + 1e-12
    # a larger horizon gives a larger failure probability
    far = fleet_rul(fleet.table, fleet.threshold, samples=300, horizon=5000.0)
    assert all(
        far.columns["p_fail_within_horizon"][i] >= res.columns["p_fail_within_horizon"][i]
        for i in ok
    )


def test_intervals_cover_the_known_failure_times(fleet):
    """90 % intervals on degradation simulated from the model: coverage 0.9 within 4 binomial
    standard deviations, and the median error small relative to the RUL."""
    sf = synthetic_fleet(400, 300, seed=11, healthy_fraction=0.0)
    res = fleet_rul(sf.table, sf.threshold, samples=1000)
    med = np.array(res.columns["rul_median"])
    lo, hi = np.array(res.columns["rul_q05"]), np.array(res.columns["rul_q95"])
    ok = np.isfinite(med)
    assert ok.mean() > 0.9
    truth = sf.true_rul[ok]
    cover = (lo[ok] <= truth) & (truth <= np.where(np.isnan(hi[ok]), np.inf, hi[ok]))
    sd = math.sqrt(0.9 * 0.1 / ok.sum())
    assert abs(cover.mean() - 0.9) <= 4 * sd, cover.mean()
    assert np.median(np.abs(med[ok] - truth) / truth) < 0.15


def _degrading_assets(batch, out):
    """``(b, onset index, rows, times, values)`` of each asset of ``batch`` with an onset in
    ``exponential_trend_rul(..., return_posterior=True)``'s output ``out``."""
    for b in range(len(batch)):
        i0 = int(out["onset_index"][b])
        if i0 >= 0:
            n = int(batch.lengths[b])
            yield b, i0, n, batch.times[b, :n].numpy(), batch.values[b, :n].numpy()


def test_trend_posterior_equals_exact_bayesian_regression_and_kalman(fleet):
    tab = read_fleet_table(fleet.table)
    batch = pad_batch(tab.assets, tab.times, tab.values, seed=0)
    for drift in ((0.0, 0.0), (0.02, 1e-3)):
        out = exponential_trend_rul(
            batch, fleet.threshold, phi=0.0, samples=10, drift_std=drift, return_posterior=True
        )
        checked = 0
        for b, i0, n, t, y in _degrading_assets(batch, out):
            z = np.log(y)
            base = np.isfinite(z[:n])  # the filter's inputs after onset
            tau, zz = t[i0:] - t[i0], z[i0:]
            sigma = float(out["log_noise_std"][b])
            # prior of the method: a ~ N(mean of z over the baseline, 1), beta ~ N(0, 1/dt^2)
            m = out["posterior_mean"][b].numpy()
            S = out["posterior_chol"][b].numpy()
            dt = np.median(np.diff(t))
            P0 = np.diag([1.0, 1.0 / dt**2])
            in_base = t <= t[0] + 0.3 * (t[n - 1] - t[0]) + 1e-12 * max(1.0, abs(t[n - 1]))
            m0 = np.array([z[in_base & base].mean(), 0.0])
            mk, Pk = m0, P0
            Qd = np.diag(np.square(drift))
            for tk, zk in zip(tau, zz):
                Pk = Pk + Qd
                if np.isnan(zk):
                    continue
                h = np.array([1.0, tk])
                s = h @ Pk @ h + sigma**2
                K = Pk @ h / s
                mk = mk + K * (zk - h @ mk)
                Pk = Pk - np.outer(K, K) * s
            np.testing.assert_allclose(m, mk, rtol=1e-9, atol=1e-12)
            np.testing.assert_allclose(S @ S.T, Pk, rtol=1e-7, atol=1e-14)
            if drift == (0.0, 0.0):  # the closed form of Bayesian linear regression
                H = np.stack([np.ones_like(tau), tau], 1)[~np.isnan(zz)]
                A = np.linalg.inv(P0) + H.T @ H / sigma**2
                mb = np.linalg.solve(A, np.linalg.inv(P0) @ m0 + H.T @ zz[~np.isnan(zz)] / sigma**2)
                np.testing.assert_allclose(m, mb, rtol=1e-8, atol=1e-12)
            checked += 1
        assert checked > 30


def _offset_fleet(n_assets, seed):
    """Assets that rise from a healthy level ``mu`` with additive noise: ``y = mu + noise +
    theta exp(beta (t - t_on))`` after onset (Gebraeel's model with ``phi = mu``), and the true
    RUL at the last row (crossing of 1.0 by the noise-free path)."""
    rng = np.random.default_rng(seed)
    cols, rul = {"asset": [], "t": [], "value": []}, []
    for j in range(n_assets):
        n = int(rng.integers(300, 500))
        t = np.arange(n, dtype=float)
        on, mu = rng.uniform(0.35, 0.7) * n, rng.uniform(0.05, 0.2)
        theta, beta = rng.uniform(0.005, 0.02), rng.uniform(2.0, 4.0) / (n - on)
        rise = np.where(t >= on, theta * np.exp(beta * (t - on)), 0.0)
        cols["asset"] += [f"b{j:03d}"] * n
        cols["t"] += list(t)
        cols["value"] += list(mu + rng.normal(0.0, 0.05 * mu, n) + rise)
        rul.append(on + math.log((1.0 - mu) / theta) / beta - (n - 1))
    return {k: np.asarray(v) for k, v in cols.items()}, np.asarray(rul)


def _data_scale_residuals(x, d, H, s0, m0, sd):
    return np.concatenate([(d - np.exp(H @ x)) / s0, (x - m0) / sd])


def test_baseline_phi_posterior_is_the_data_scale_map_with_its_laplace_covariance():
    """phi="baseline": y - mu_0 = exp(a + beta tau) + v, v ~ N(0, sigma_0^2), on every observed
    sample since onset, prior a ~ N(log of the first value at least sigma_0 above the level, 1),
    beta ~ N(0, 1 / median step^2). The posterior mean is the MAP that scipy's least_squares
    finds on the same residuals, its covariance the inverse Gauss-Newton Hessian there
    (Laplace), and the lack-of-fit p-value the F test of the data-scale residuals."""
    from scipy.optimize import least_squares
    from scipy.stats import f as f_dist

    table, _ = _offset_fleet(12, seed=3)
    tab = read_fleet_table(table)
    batch = pad_batch(tab.assets, tab.times, tab.values, seed=0)
    out = exponential_trend_rul(batch, 1.0, phi="baseline", samples=10, return_posterior=True)
    checked = 0
    for b, i0, n, t, y in _degrading_assets(batch, out):
        in_base = t <= t[0] + 0.3 * (t[n - 1] - t[0]) + 1e-12 * max(1.0, abs(t[n - 1]))
        mu, s0 = y[in_base].mean(), y[in_base].std(ddof=1)
        d, tau = y[i0:] - mu, t[i0:] - t[i0]
        m0 = np.array([np.log(d[d >= s0][0]), 0.0])
        sd = np.array([1.0, 1.0 / np.median(np.diff(t))])
        H = np.stack([np.ones_like(tau), tau], 1)

        start = out["posterior_mean"][b].numpy() + [0.05, 1e-3]
        fit = least_squares(
            _data_scale_residuals,
            start,
            args=(d, H, s0, m0, sd),
            xtol=1e-15,
            ftol=1e-15,
            gtol=1e-15,
        )
        J = fit.jac
        cov = np.linalg.inv(J.T @ J)
        S = out["posterior_chol"][b].numpy()
        post_sd = np.sqrt(np.diag(cov))
        # the mean to 1e-5 posterior std, the covariance to 1e-4 relative
        assert np.all(np.abs(out["posterior_mean"][b].numpy() - fit.x) < 1e-5 * post_sd)
        np.testing.assert_allclose(S @ S.T, cov, rtol=1e-4, atol=0)
        r = d - np.exp(H @ fit.x)
        F = (r * r).sum() / s0**2 / (d.size - 2)
        p = f_dist.sf(F, d.size - 2, int(in_base.sum()) - 1)
        assert float(out["misfit_p"][b]) == pytest.approx(p, rel=1e-4, abs=1e-300)
        checked += 1
    assert checked >= 8


def test_baseline_phi_with_a_vanishing_drift_is_the_fixed_parameter_answer():
    """With drift_std > 0 the linearisation points are the smoothed means (the iterated
    extended Kalman smoother), a path where the fixed parameters have one point: a drift of
    1e-9 gives the fixed-parameter posterior."""
    table, _ = _offset_fleet(12, seed=3)
    tab = read_fleet_table(table)
    batch = pad_batch(tab.assets, tab.times, tab.values, seed=0)
    kw = dict(phi="baseline", samples=10, return_posterior=True)
    fixed = exponential_trend_rul(batch, 1.0, **kw)
    drift = exponential_trend_rul(batch, 1.0, drift_std=(1e-9, 1e-12), **kw)
    S = fixed["posterior_chol"]
    sd = (S * S).sum(-1).sqrt()
    ok = torch.isfinite(sd).all(-1) & (fixed["onset_index"] >= 0)
    assert ok.sum() >= 8
    gap = (drift["posterior_mean"] - fixed["posterior_mean"]).abs()[ok]
    assert bool((gap < 1e-6 * sd[ok]).all())
    torch.testing.assert_close(drift["posterior_chol"][ok], S[ok], rtol=1e-6, atol=0)


def test_trend_misfit_flag_holds_its_rate_on_the_model_and_finds_the_wrong_phi():
    """On data from the model (the synthetic fleet: phi = 0, multiplicative noise) the
    lack-of-fit p-values are uniform: below 0.05 at about 5 % of the assets, and the flag
    (p < 1e-3) at about 0.1 %; with phi="baseline", which that data do not follow, it flags
    nearly every asset."""
    f = synthetic_fleet(400, 300, seed=1, healthy_fraction=0.0)
    tab = read_fleet_table(f.table)
    batch = pad_batch(tab.assets, tab.times, tab.values)
    right = exponential_trend_rul(batch, f.threshold, phi=0.0, samples=10, return_posterior=True)
    p = right["misfit_p"].numpy()
    p = p[np.isfinite(p)]
    assert p.size > 350
    assert 0.02 <= np.mean(p < 0.05) <= 0.08  # binomial sd 0.011 around 0.05
    assert np.sum(p < MISFIT_P) <= 3  # expected 0.4
    assert sum("trend_misfit" in fl for fl in right["flags"]) == np.sum(p < MISFIT_P)
    wrong = exponential_trend_rul(batch, f.threshold, samples=10, phi="baseline")
    assert np.mean(["trend_misfit" in fl for fl in wrong["flags"]]) > 0.9


def test_an_indicator_with_a_healthy_level_needs_phi_baseline():
    """Assets rising from a healthy level (Gebraeel's model with phi = that level): phi = 0
    reads the slow start of log(y) as the trend and predicts late; phi="baseline" recovers the
    RUL (median relative error 5 times smaller) and its 90 % intervals cover the truth at 0.82
    of 118 assets (seeds 5, 7-10: 0.82-0.89; a regression of log(y - mu_0) that left out the
    values within sigma_0 of the level, selected by their noise, covered 0.66-0.70)."""
    table, rul = _offset_fleet(120, seed=5)
    zero = fleet_rul(table, 1.0, samples=400, phi=0.0)
    base = fleet_rul(table, 1.0, samples=400, phi="baseline")
    med0, medb = np.array(zero.columns["rul_median"]), np.array(base.columns["rul_median"])
    ok = np.isfinite(med0) & np.isfinite(medb) & (rul > 0)
    assert ok.sum() > 100
    err0 = np.median(np.abs(med0[ok] / rul[ok] - 1.0))
    errb = np.median(np.abs(medb[ok] / rul[ok] - 1.0))
    assert np.median(med0[ok] / rul[ok]) > 1.3 and errb < err0 / 5
    q05, q95 = np.array(base.columns["rul_q05"])[ok], np.array(base.columns["rul_q95"])[ok]
    assert np.mean((q05 <= rul[ok]) & (rul[ok] <= q95)) >= 0.75  # binomial sd 0.033 at 0.85


def _mixed_fleet(n_each: int):
    """Half the assets rise from a healthy level (phi = that level), half grow from near zero
    with multiplicative noise (the synthetic fleet, phi = 0, scaled to threshold 1)."""
    t1, truth1 = _offset_fleet(n_each, seed=7)
    f = synthetic_fleet(n_each, 300, seed=3, healthy_fraction=0.0)
    table = {
        "asset": np.concatenate([t1["asset"], np.char.add("s", f.table["asset"].astype(str))]),
        "t": np.concatenate([t1["t"], f.table["t"]]),
        "value": np.concatenate([t1["value"], f.table["value"] / f.threshold]),
    }
    return table, np.concatenate([truth1, f.true_rul])


def test_phi_auto_takes_per_asset_the_offset_under_which_the_data_are_likelier():
    """phi="auto" on a fleet of both kinds: the baseline on the assets with a healthy level,
    0 on those that grow from near zero (each a model with two parameters: the likelier is
    also the AIC/BIC choice), every column that of the model chosen, and the intervals cover
    both kinds (0.86 / 0.89 on 150 + 150 assets, where phi = 0 covered 0.00 / 0.90 and the
    baseline 0.86 / 0.01)."""
    table, truth = _mixed_fleet(60)
    kinds = np.r_[np.zeros(60, bool), np.ones(60, bool)]  # True: phi = 0 is the true model
    auto = fleet_rul(table, 1.0, phi="auto", samples=400)
    zero = fleet_rul(table, 1.0, phi=0.0, samples=400)
    base = fleet_rul(table, 1.0, phi="baseline", samples=400)
    assert tuple(auto.columns) == OUTPUT_COLUMNS + ("phi",) and "phi" not in zero.columns
    chose_base = np.array(auto.columns["phi"]) != 0
    assert chose_base[~kinds].mean() >= 0.95 and chose_base[kinds].mean() <= 0.05
    np.testing.assert_array_equal(
        np.array(auto.columns["phi"])[chose_base], np.array(base.columns["phi"])[chose_base]
    )
    for c in (*RUL_COLUMNS, "flags"):
        want = [b if cb else z for b, z, cb in zip(base.columns[c], zero.columns[c], chose_base)]
        assert [str(v) for v in auto.columns[c]] == [str(v) for v in want], c
    q05, q95 = np.array(auto.columns["rul_q05"]), np.array(auto.columns["rul_q95"])
    hit = (q05 <= truth) & (truth <= np.where(np.isnan(q95), np.inf, q95))
    ok = np.isfinite(q05) & (truth > 0)
    assert hit[ok & ~kinds].mean() >= 0.75 and hit[ok & kinds].mean() >= 0.75


def test_phi_auto_on_a_falling_indicator_and_on_the_command_line(tmp_path, capsys):
    """A falling indicator with a positive threshold: phi = 0 cannot reach it (s (X - 0) < 0),
    so "auto" is the baseline on every asset; an asset about 0 without onset reads "no_onset"
    (phi = 0 alone: "no_baseline"); the command line's --phi auto writes the phi column."""
    table, _ = _offset_fleet(8, seed=3)
    fall = dict(table, value=2.0 - table["value"])  # from about 1.9 down towards 1.0
    auto = fleet_rul(fall, 1.0, direction="below", phi="auto", samples=50)
    base = fleet_rul(fall, 1.0, direction="below", phi="baseline", samples=50)
    for c in (*RUL_COLUMNS, "flags", "phi"):
        assert [str(v) for v in auto.columns[c]] == [str(v) for v in base.columns[c]], c
    with pytest.raises(ValueError, match="must lie below phi = 0"):
        fleet_rul(fall, 1.0, direction="below", samples=50, phi=0.0)
    # a healthy indicator about 0: phi = 0 has no baseline (no logarithm), auto says no onset
    y = np.random.default_rng(0).normal(0.0, 0.05, 200)
    centred = {"asset": ["c"] * 200, "t": np.arange(200.0), "value": y}
    assert fleet_rul(centred, 1.0, samples=50, phi=0.0).row("c")["flags"] == "no_baseline"
    row = fleet_rul(centred, 1.0, samples=50).row("c")
    assert row["flags"] == "no_onset" and row["phi"] == pytest.approx(y[:60].mean(), abs=1e-12)
    mixed, _ = _mixed_fleet(4)
    write_table(tmp_path / "m.csv", {k: list(v) for k, v in mixed.items()})
    argv = ["rul", str(tmp_path / "m.csv"), "--group-by", "asset", "--threshold", "1",
            "--phi", "auto", "--samples", "50", "--no-progress", "--out", str(tmp_path / "o.csv")]  # fmt: skip
    assert cli_main(argv) == 0
    phi = read_back(tmp_path / "o.csv")["phi"]
    assert len(phi) == 8 and all(p != 0 for p in phi[:4]) and all(p == 0 for p in phi[4:])
    assert "trend offset (--phi auto): the healthy level for 4, 0 for 4 of the 8 with a RUL" \
        in capsys.readouterr().out  # fmt: skip


def test_phi_auto_likelihoods_are_the_data_scale_densities():
    """The two log-likelihoods that phi="auto" compares, against SciPy's normal density: phi = 0,
    log(y) ~ N(a + beta tau, sigma^2) with the Jacobian 1 / y; the baseline, y - mu_0 ~
    N(exp(a + beta tau), sigma_0^2); over the samples since onset with y > 0."""
    from scipy.stats import norm

    from prognos_torch.fleet.trend import _data_log_likelihood

    table, _ = _mixed_fleet(6)
    tab = read_fleet_table(table)
    batch = pad_batch(tab.assets, tab.times, tab.values, seed=0)
    for phi, baseline_phi in ((0.0, False), ("baseline", True)):
        post = exponential_trend_rul(batch, 1.0, phi=phi, samples=10, return_posterior=True)
        if not baseline_phi:
            post["phi"] = np.zeros(len(post["flags"]))
        ll = _data_log_likelihood(batch, post, 1.0, baseline_phi).numpy()
        checked = 0
        for b, i0, n, t, y in _degrading_assets(batch, post):
            tau, yy = t[i0:n] - t[i0], y[i0:n]
            ok = np.isfinite(yy) & (yy > 0)
            a, beta = post["posterior_mean"][b].numpy()
            g = a + beta * tau[ok]
            if baseline_phi:
                want = norm.logpdf(yy[ok] - post["phi"][b], np.exp(g),
                                   float(post["baseline_std"][b])).sum()  # fmt: skip
            else:
                sd = float(post["log_noise_std"][b])
                want = (norm.logpdf(np.log(yy[ok]), g, sd) - np.log(yy[ok])).sum()
            assert ll[b] == pytest.approx(want, rel=1e-12)
            checked += 1
        assert checked >= 8


def test_noiseless_exponential_rul_is_the_closed_form_crossing():
    # y = theta exp(beta (t - t_on)) after t_on, a tiny noise keeps the baseline spread positive
    rng = np.random.default_rng(0)
    t = np.arange(300.0)
    theta, beta, t_on, X = 1.3, 0.01, 150.0, 20.0
    y = theta * np.exp(beta * np.maximum(0.0, t - t_on) + 1e-4 * rng.normal(size=t.size))
    res = fleet_rul({"asset": ["u"] * t.size, "t": t, "value": y}, X, samples=2000)
    truth = t_on + math.log(X / theta) / beta - t[-1]
    row = res.row("u")
    assert row["flags"] == ""
    assert abs(row["rul_median"] - truth) < 0.005 * truth
    assert row["rul_q05"] <= truth + 0.01 * truth and truth - 0.01 * truth <= row["rul_q95"]


def test_onset_batch_equals_the_per_series_rule():
    onset = pytest.importorskip("prognos_torch.prognosis.onset")
    sf = synthetic_fleet(40, 150, seed=5, ragged=0.4)
    tab = read_fleet_table(sf.table)
    values = [v.copy() for v in tab.values]
    values[3][10:14] = np.nan  # gaps are skipped by both
    batch = pad_batch(tab.assets, tab.times, values)
    # (the falling mirror with an even window: the median of the oriented series, the lower
    # middle of four, as the per-series rule; the batch took the upper middle of the falling one)
    for direction, skip, w in (("above", False, 5), ("below", False, 5), ("above", True, 5),
                               ("below", False, 4)):  # fmt: skip
        sgn = -1.0 if w == 4 else 1.0
        got = ksigma_onset_batch(sgn * batch.values, batch.times, batch.lengths,
                                 direction=direction, skip_window=skip, window=w)  # fmt: skip
        if w == 4:
            assert int((got.index >= 0).sum()) >= 20  # the mirror degrades: onsets to compare
        for b in range(len(batch)):
            x, tb = torch.from_numpy(sgn * values[b]), torch.from_numpy(tab.times[b])
            ref = onset.ksigma_onset(x, tb, direction=direction, window=w)
            if skip:
                ref = onset.ksigma_onset(x, tb, direction=direction, after=ref.baseline.t_end)
            if ref.detected:
                assert int(got.index[b]) == ref.index
                assert float(got.time[b]) == ref.time
            else:
                assert int(got.index[b]) == -1
            assert math.isclose(float(got.base_mean[b]), ref.baseline.mean, rel_tol=1e-12)


def test_onset_batch_skips_a_run_in_in_the_healthy_window():
    g = np.random.default_rng(0)
    t = np.arange(400.0)
    x = 1.0 + 0.05 * g.standard_normal((2, 400))
    x[:, 300:] += 4.0  # a step at 300
    x[1, :6] += 3.0  # a run-in on the second asset (6 of the window's 120 samples)
    batch = pad_batch(["a", "b"], [t, t], [x[0], x[1]])
    plain = ksigma_onset_batch(batch.values, batch.times, batch.lengths)
    skip = ksigma_onset_batch(batch.values, batch.times, batch.lengths, skip_window=True)
    assert 300 <= int(plain.index[0]) == int(skip.index[0]) <= 304
    assert int(plain.index[1]) < 6  # the run-in counts as onset ...
    assert 300 <= int(skip.index[1]) <= 304  # ... unless the window is taken as healthy


# --------------------------------------------------------------------------- tables
def test_csv_mapping_dataframe_and_parquet_give_the_same_table(tmp_path, fleet):
    ref = fleet_rul(fleet.table, fleet.threshold, samples=200)
    cols = {"asset": list(fleet.table["asset"]), "t": list(fleet.table["t"]),
            "value": list(fleet.table["value"])}  # fmt: skip
    write_table(tmp_path / "f.csv", cols)
    _assert_same(ref, fleet_rul(tmp_path / "f.csv", fleet.threshold, samples=200), rtol=0)
    pd = pytest.importorskip("pandas")
    pytest.importorskip("pyarrow")
    df = pd.DataFrame(fleet.table)
    _assert_same(ref, fleet_rul(df, fleet.threshold, samples=200), rtol=0)
    write_table(tmp_path / "f.parquet", cols)
    _assert_same(ref, fleet_rul(tmp_path / "f.parquet", fleet.threshold, samples=200), rtol=0)
    # integer asset ids in a DataFrame are the same assets as their text in a CSV
    df2 = pd.DataFrame({"unit": [7] * 30 + [8] * 30, "t": list(range(30)) * 2, "v": 1.0})
    t2 = read_fleet_table(df2, group_by="unit", time_column="t", column="v")
    assert t2.assets == ["7", "8"]
    # results round-trip through both formats exactly
    for name in ("r.csv", "r.parquet"):
        ref.write(tmp_path / name)
        back = read_back(tmp_path / name)
        assert back["asset"] == ref.columns["asset"]
        for c in RUL_COLUMNS:
            np.testing.assert_array_equal(np.array(back[c], dtype=float), ref.columns[c])
    # a row count is written as an integer ("200", not "200.0"), a parquet int64 column
    rows = (tmp_path / "r.csv").read_text().splitlines()
    at = rows[0].split(",").index("n_rows")
    assert all(r.split(",")[at].isdigit() for r in rows[1:])
    assert all(type(v) is int for v in ref.columns["n_rows"])
    import pyarrow.parquet as pq

    assert pq.read_table(tmp_path / "r.parquet").schema.field("n_rows").type == "int64"


def test_a_csv_with_decimal_commas_gives_the_same_fleet_with_decimal_comma(tmp_path, fleet):
    """The fleet table written with ';' and decimal commas reads, with decimal=',', as the
    same table; without it the error says why; a point there is refused, not read."""
    cols = {"asset": list(fleet.table["asset"]), "t": list(fleet.table["t"]),
            "value": list(fleet.table["value"])}  # fmt: skip
    write_table(tmp_path / "f.csv", cols)
    rows = (tmp_path / "f.csv").read_text().splitlines()
    eu = tmp_path / "eu.csv"
    eu.write_text("".join(r.replace(",", ";").replace(".", ",") + "\n" for r in rows))
    ref, got = read_fleet_table(tmp_path / "f.csv"), read_fleet_table(eu, decimal=",")
    assert got.assets == ref.assets and not got.errors
    for x, y in zip(got.times + got.values, ref.times + ref.values):
        np.testing.assert_array_equal(x, y)
    with pytest.raises(ValueError, match=r"is not a number; a decimal comma\? pass decimal=','"):
        read_fleet_table(eu)
    lines = eu.read_text().splitlines()
    head, first = lines[0].split(";"), lines[1].split(";")
    first[head.index("value")] = "1.500"  # a point where the comma is the decimal mark
    (tmp_path / "dot.csv").write_text("\n".join([lines[0], ";".join(first), *lines[2:]]) + "\n")
    with pytest.raises(ValueError, match=r"row 1 \(line 2\): value '1.500' .* is not a number "
                       r"with decimal=','"):  # fmt: skip
        read_fleet_table(tmp_path / "dot.csv", decimal=",")
    flagged = read_fleet_table(tmp_path / "dot.csv", decimal=",", on_error="flag")
    assert list(flagged.errors) == [ref.assets[0]] and "1.500" in flagged.errors[ref.assets[0]]
    # day-first dates in a time_format: the same table as its ISO 8601 dates
    base = np.datetime64("2024-03-01T00:00")
    iso = {"asset": ["u"] * 3 + ["v"] * 3, "t": [str(base + np.timedelta64(h, "h")) for h in
           (0, 1, 2, 0, 2, 5)], "value": [1.0, 2.0, 3.0, 4.0, 5.0, 6.0]}  # fmt: skip
    dmy = dict(
        iso, t=[np.datetime64(t).astype(object).strftime("%d/%m/%Y %H:%M") for t in iso["t"]]
    )
    write_table(tmp_path / "iso.csv", iso)
    write_table(tmp_path / "dmy.csv", dmy)
    a, b = read_fleet_table(tmp_path / "iso.csv"), read_fleet_table(tmp_path / "dmy.csv",
                                                                  time_format="%d/%m/%Y %H:%M")  # fmt: skip
    assert a.epoch == b.epoch and all(np.array_equal(x, y) for x, y in zip(a.times, b.times))
    with pytest.raises(ValueError, match=r"--time-format"):
        read_fleet_table(tmp_path / "dmy.csv")
    # the command line: the same result file from either table
    outs = []
    for table, mark in ((tmp_path / "f.csv", []), (eu, ["--decimal", ","])):
        out = tmp_path / f"{table.stem}_rul.csv"
        argv = ["rul", str(table), "--group-by", "asset", "--threshold", "20", "--samples", "50"]
        assert cli_main([*argv, *mark, "--no-progress", "--out", str(out)]) == 0
        outs.append(out.read_bytes())
    assert outs[0] == outs[1]


def read_back(path):
    if path.suffix == ".csv":
        import csv

        with open(path, newline="") as fh:
            rows = list(csv.DictReader(fh))
        text = ("asset", "flags", "message", *DATE_COLUMNS)
        return {k: [r[k] if k in text else float(r[k] or "nan")
                    for r in rows] for k in rows[0]}  # fmt: skip
    import pyarrow.parquet as pq

    tab = pq.read_table(path).to_pydict()
    return {k: [math.nan if v is None else v for v in vals] for k, vals in tab.items()}


def _small_csv(tmp_path, body: str):
    p = tmp_path / "bad.csv"
    p.write_text("asset,t,value\n" + body)
    return p


def test_time_order_messages_show_the_times_as_written(tmp_path):
    """A time out of order is reported as the table holds it: an ISO 8601 cell as its text (not
    the day count it was read as), a number with 10 significant digits (Unix seconds no longer
    1.70002e+09 alike), all of them where 10 would print two times alike."""
    p = _small_csv(
        tmp_path,
        "a,2024-03-01T10:00:00Z,1\na,2024-03-01T10:00:00Z,2\n"
        "b,2024-03-01T10:00:00Z,1\nb,2024-02-29T10:00:00Z,1\n",
    )
    err = read_fleet_table(p, on_error="flag").errors
    assert "duplicate timestamp '2024-03-01T10:00:00Z' (also at row 1)" in err["a"]
    assert "time '2024-02-29T10:00:00Z' comes after '2024-03-01T10:00:00Z' (row 3)" in err["b"]
    unix = [1700021180.0, 1700017580.0, 0.1 + 0.2, 0.3]
    table = {"asset": np.array(["u", "u", "v", "v"]), "t": np.array(unix), "value": np.ones(4)}
    err = read_fleet_table(table, on_error="flag").errors
    assert "time 1700017580 comes after 1700021180 (row 1)" in err["u"]
    assert "time 0.3 comes after 0.30000000000000004 (row 3)" in err["v"]


def test_bad_input_messages_name_the_asset_and_row(tmp_path):
    good = "".join(f"A,{k},{1 + 0.01 * k}\n" for k in range(12))
    p = tmp_path / "nocol.csv"
    p.write_text("unit,t,value\nA,0,1\n")
    with pytest.raises(ValueError, match=r"no asset \(--group-by\) column 'asset'; columns found"):
        fleet_rul(p, 2.0)
    p = _small_csv(tmp_path, good + "B,0,1.0\nB,1,abc\n")
    with pytest.raises(ValueError, match=r"asset 'B', row 14 \(line 15\): value 'abc'"):
        fleet_rul(p, 2.0)
    p = _small_csv(tmp_path, good + "B,0,1.0\nB,0,1.1\n")
    with pytest.raises(ValueError, match=r"asset 'B', row 14 .*duplicate timestamp '0'"):
        fleet_rul(p, 2.0)
    p = _small_csv(tmp_path, good + "B,5,1.0\nB,3,1.1\n")
    with pytest.raises(ValueError, match=r"asset 'B', row 14 .*time '3' comes after '5'"):
        fleet_rul(p, 2.0)
    p = _small_csv(tmp_path, good + "B,x,1.0\n")
    with pytest.raises(
        ValueError, match=r"asset 'B', row 13 .*is not a number, while .* holds the number"
    ):
        fleet_rul(p, 2.0)
    with pytest.raises(ValueError, match="threshold 0.5 must lie above phi = 1"):
        fleet_rul(_small_csv(tmp_path, good), 0.5, phi=1.0)
    # with on_error="flag" the bad asset is set aside, the others go on
    p = _small_csv(tmp_path, good + "B,0,1.0\nB,1,abc\n" + good.replace("A,", "C,"))
    res = fleet_rul(p, 2.0, on_error="flag")
    assert res.row("B")["flags"] == "bad_input" and "row 14" in res.row("B")["message"]
    assert res.row("A")["message"] == "" and res.row("C")["flags"] != "bad_input"
    # too few rows: reported per asset, not fatal
    res = fleet_rul(_small_csv(tmp_path, good + "D,0,1.0\nD,1,1.0\n"), 2.0)
    assert res.row("D")["flags"] == "too_few_rows" and math.isnan(res.row("D")["rul_median"])
    assert res.row("A")["flags"] != "too_few_rows"
    # blank lines are skipped; the message gives the data row and the file line
    p = _small_csv(tmp_path, good + "\nB,0,1.0\nB,1,abc\n")
    with pytest.raises(ValueError, match=r"asset 'B', row 14 \(line 16\): value 'abc'"):
        fleet_rul(p, 2.0)
    # ISO 8601 date-times: days since the Unix epoch, whatever else the table holds (results
    # of tables read apart merge; they used to count from each table's earliest time)
    p = _small_csv(tmp_path, "".join(f"A,2026-01-{k + 1:02d}T12:00:00,{1 + 0.01 * k}\n"
                                     for k in range(12)))  # fmt: skip
    tab = read_fleet_table(p)
    assert tab.time_unit == "days" and tab.epoch == "1970-01-01T00:00:00"
    np.testing.assert_array_equal(tab.times[0], 20454.5 + np.arange(12.0))
    early = _small_csv(tmp_path, "".join(f"{a},2025-0{k // 5 + 1}-{k % 5 + 1:02d}T12:00:00,1\n"
                                         for a in "AB" for k in range(12)))  # fmt: skip
    np.testing.assert_array_equal(read_fleet_table(early).times[0][:3], tab.times[0][:3] - 365)
    # missing values are NaN (skipped), not errors
    res = fleet_rul(_small_csv(tmp_path, good + "".join(f"E,{k},\n" for k in range(12))), 2.0)
    assert res.row("E")["n_rows"] == 12.0


def test_threshold_already_reached_gives_rul_zero():
    t = np.arange(100.0)
    y = np.exp(0.05 * np.maximum(0, t - 40) + 0.01 * np.random.default_rng(1).normal(size=100))
    res = fleet_rul({"asset": ["a"] * 100, "t": t, "value": y}, 5.0)
    row = res.row("a")
    assert "threshold_reached" in row["flags"]
    assert row["rul_median"] == 0.0 and row["p_fail_within_horizon"] == 1.0


# --------------------------------------------------------------------------- atomic output, CLI
def test_interrupted_run_leaves_no_output_file(tmp_path, fleet, monkeypatch):
    write_table(tmp_path / "f.csv", {k: list(v) for k, v in fleet.table.items()})
    calls = {"n": 0}
    real = METHODS["exponential"]

    def flaky(batch, threshold, **kw):
        calls["n"] += 1
        if calls["n"] == 2:
            raise KeyboardInterrupt
        return real(batch, threshold, **kw)

    monkeypatch.setitem(METHODS, "exponential", flaky)
    out = tmp_path / "res.parquet"
    args = ["rul", str(tmp_path / "f.csv"), "--group-by", "asset", "--threshold", "20",
            "--shard-size", "10", "--no-progress", "--out"]  # fmt: skip
    assert cli_main(args + [str(out)]) == 130
    assert calls["n"] == 2 and not out.exists()
    assert os.listdir(tmp_path) == ["f.csv"]  # no temporary file left behind either
    # an interruption while the file is being written leaves nothing either
    monkeypatch.setitem(METHODS, "exponential", real)
    import prognos_torch.io as pio

    def broken_replace(src, dst):
        raise KeyboardInterrupt

    monkeypatch.setattr(pio.os, "replace", broken_replace)
    assert cli_main(args + [str(tmp_path / "res.csv")]) == 130
    assert os.listdir(tmp_path) == ["f.csv"]


def test_cli_writes_csv_and_parquet(tmp_path, fleet, capsys):
    write_table(tmp_path / "f.csv", {k: list(v) for k, v in fleet.table.items()})
    for name in ("out.csv", "out.parquet"):
        if name.endswith("parquet"):
            pytest.importorskip("pyarrow")
        code = cli_main(
            [
                "rul",
                str(tmp_path / "f.csv"),
                "--group-by",
                "asset",
                "--column",
                "value",
                "--time-column",
                "t",
                "--threshold",
                "20",
                "--samples",
                "200",
                "--out",
                str(tmp_path / name),
                "--no-progress",
            ]  # fmt: skip
        )
        assert code == 0
        back = read_back(tmp_path / name)
        assert tuple(back) == OUTPUT_COLUMNS + ("phi",) and len(back["asset"]) == len(fleet.assets)
    out = capsys.readouterr().out
    assert "60 assets" in out and "no_onset" in out
    assert cli_main(["rul", str(tmp_path / "f.csv"), "--group-by", "unit", "--threshold", "2",
                     "--out", str(tmp_path / "x.csv")]) == 2  # fmt: skip
    assert "no asset (--group-by) column 'unit'" in capsys.readouterr().err
    assert not (tmp_path / "x.csv").exists()


# --------------------------------------------------------------------------- Ray
def test_ray_backend_equals_local(fleet, whole):
    ray = pytest.importorskip("ray")
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:
        remote = fleet_rul(fleet.table, fleet.threshold, samples=300, shard_size=16, backend="ray")
    finally:
        ray.shutdown()
    _assert_same(whole, remote)  # (shards of 16 on Ray, one shard here)


def test_workers_run_the_shards_side_by_side_and_give_the_same_table(fleet, whole):
    """workers=2: the shards in two spawned processes (cut to one shard per worker at least):
    the table of the sequential run, to the 1e-12 of another shard size for the batched trend
    and bit for bit for the per-asset prognose; bad counts and Ray are refused by name."""
    tab = read_fleet_table(fleet.table)
    par = fleet_rul(tab, fleet.threshold, samples=300, workers=2)
    assert par.shard_size == 30  # 60 assets, 2 workers: two shards instead of one
    _assert_same(whole, par)
    sf = synthetic_fleet(3, 200, seed=2, healthy_fraction=0.0)
    kw = dict(method="prognose", n_paths=100)
    a = fleet_rul(sf.table, sf.threshold, shard_size=1, **kw)
    _assert_same(a, fleet_rul(sf.table, sf.threshold, workers=2, **kw), rtol=0)
    with pytest.raises(ValueError, match="workers must be >= 1"):
        fleet_rul(tab, fleet.threshold, workers=0)
    with pytest.raises(TypeError, match="workers must be an int"):
        fleet_rul(tab, fleet.threshold, workers=2.0)
    with pytest.raises(ValueError, match="workers=2 applies to backend='local'"):
        fleet_rul(tab, fleet.threshold, workers=2, backend="ray")


def test_prognose_method_equals_prognose_per_asset_whatever_the_shards():
    from prognos_torch.fleet import asset_seed
    from prognos_torch.workflow import prognose

    sf = synthetic_fleet(4, 200, seed=2, healthy_fraction=0.0)
    a = fleet_rul(sf.table, sf.threshold, method="prognose", n_paths=200, shard_size=1)
    b = fleet_rul(sf.table, sf.threshold, method="prognose", n_paths=200, shard_size=4)
    _assert_same(a, b, rtol=0)
    assert a.columns["message"] == b.columns["message"]
    asset = sf.assets[1]
    rows = sf.table["asset"] == asset
    r = prognose(
        torch.from_numpy(sf.table["value"][rows]),
        sf.threshold,
        time=torch.from_numpy(sf.table["t"][rows]),
        seed=asset_seed(0, asset),
        direction="above",
        n_paths=200,
    )
    s = r.summary()
    for key, col in (("median", "rul_median"), ("q05", "rul_q05"), ("q95", "rul_q95")):
        want = math.nan if s[key] is None else s[key]
        got = a.row(asset)[col]
        assert (math.isnan(want) and math.isnan(got)) or got == want
    assert a.row(asset)["censored_mass"] == r.censored_mass


def test_threshold_on_the_healthy_side_is_flagged_not_rul_zero():
    """A falling indicator (capacity near 1, threshold 0.8) with the default direction "above":
    the healthy assets used to get RUL 0 and `threshold_reached`; now a flag and no RUL."""
    t = np.arange(150.0)
    rng = np.random.default_rng(0)
    table = {"asset": ["c0"] * 150 + ["c1"] * 150, "t": np.concatenate([t, t]),
             "value": np.concatenate([1.0 - 0.0001 * t, 0.97 - 0.0001 * t]) + 0.002 * rng.normal(size=300)}  # fmt: skip
    res = fleet_rul(table, 0.8)
    for a in ("c0", "c1"):
        row = res.row(a)
        assert (
            "threshold_on_healthy_side" in row["flags"] and "threshold_reached" not in row["flags"]
        )
        assert math.isnan(row["rul_median"]) and math.isnan(row["p_fail_within_horizon"])


def test_prognose_method_counts_the_rul_from_the_last_row_and_checks_the_horizon():
    """An asset whose last values are missing: the RUL counts from its last row (t_last), as the
    exponential method's does (prognose evaluates at=t_last); horizons are checked alike."""
    from prognos_torch.fleet import asset_seed
    from prognos_torch.workflow import prognose

    sf = synthetic_fleet(2, 200, seed=2, healthy_fraction=0.0)
    a = sf.assets[0]
    rows = sf.table["asset"] == a
    t, y = sf.table["t"][rows].copy(), sf.table["value"][rows].copy()
    y[-15:] = np.nan
    res = fleet_rul({"asset": [a] * len(t), "t": t, "value": y}, sf.threshold,
                    method="prognose", n_paths=200, horizon=30.0)  # fmt: skip
    r = prognose(torch.from_numpy(y), sf.threshold, time=torch.from_numpy(t), n_paths=200,
                 seed=asset_seed(0, a), direction="above", at=float(t[-1]))  # fmt: skip
    row = res.row(a)
    assert row["t_last"] == float(t[-1]) and r.t_last == float(t[-1])
    assert row["rul_median"] == r.summary()["median"]
    alive = r.rul_samples[~torch.isnan(r.rul_samples)]
    assert row["p_fail_within_horizon"] == pytest.approx(float((alive <= 30.0).double().mean()))
    for method in ("exponential", "prognose"):
        for bad in (math.inf, math.nan, -5.0, "30", True):
            with pytest.raises(ValueError, match="horizon"):
                fleet_rul(sf.table, sf.threshold, method=method, horizon=bad)
    ok = fleet_rul(sf.table, sf.threshold, horizon=np.int64(30), samples=100)
    _assert_same(ok, fleet_rul(sf.table, sf.threshold, horizon=30.0, samples=100))
    # beyond prognose's own horizon with censored paths: unknown (NaN and a flag), not the
    # fraction of paths that crossed read as a probability
    far = 2.0 * r.bound
    res = fleet_rul({"asset": [a] * len(t), "t": t, "value": y}, 10.0 * sf.threshold,
                    method="prognose", n_paths=200, horizon=far)  # fmt: skip
    row = res.row(a)
    assert row["censored_mass"] > 0.1 and math.isnan(row["p_fail_within_horizon"])
    assert "horizon_beyond_prognosis" in row["flags"].split(";")


def test_asset_ids_duplicate_columns_and_date_times(tmp_path):
    """A whole-number float id is the integer (7.0 is asset "7"); a missing id is an error, not
    an asset "nan"; a column named twice is an error; date-times outside 1678-2262 (where
    nanoseconds wrap) or numbers mixed into a date-time column are errors; a time zone is
    applied (the same table in UTC gives the same RULs, and t_last)."""
    t = np.arange(60.0)
    y = 1.0 + 0.02 * np.random.default_rng(0).normal(size=60)
    y[40:] += 0.05 * np.exp(0.15 * (t[40:] - 40))
    ints = fleet_rul({"asset": [7] * 60, "t": t, "value": y}, 3.0, samples=50)
    floats = fleet_rul({"asset": [7.0] * 60, "t": t, "value": y}, 3.0, samples=50)
    assert floats.columns["asset"] == ["7"] and ints.columns["asset"] == ["7"]
    _assert_same(ints, floats, rtol=0)
    ids = np.array(["a"] * 60, dtype=object)
    ids[5] = float("nan")
    with pytest.raises(ValueError, match="empty asset id"):
        read_fleet_table({"asset": ids, "t": t, "value": y})
    p = tmp_path / "dup.csv"
    p.write_text("asset,t,value,value\n" + "".join(f"a,{k},1.0,2.0\n" for k in range(20)))
    with pytest.raises(ValueError, match="'value' appears more than once"):
        read_fleet_table(p)
    stamps = [f"2024-01-01T{k // 60:02d}:{k % 60:02d}:00" for k in range(60)]
    naive = fleet_rul({"asset": ["a"] * 60, "t": np.array(stamps), "value": y}, 3.0, samples=50)
    zoned = [f"2024-01-01T{(k // 60) + 1:02d}:{k % 60:02d}:00+01:00" for k in range(60)]
    tz = fleet_rul({"asset": ["a"] * 60, "t": np.array(zoned), "value": y}, 3.0, samples=50)
    _assert_same(naive, tz, rtol=0)
    # date-times: the dates a planner reads, in UTC to the second, beside the day counts
    assert tuple(naive.columns) == OUTPUT_COLUMNS + ("phi",) + DATE_COLUMNS
    assert tuple(ints.columns) == OUTPUT_COLUMNS + ("phi",)  # numeric time: none
    assert all(naive.columns[c] == tz.columns[c] for c in DATE_COLUMNS)
    row = naive.row("a")
    assert row["t_last_date"] == "2024-01-01T00:59:00" and math.isfinite(row["rul_q95"])

    def date_of(days):  # NumPy's own arithmetic from the last stamp
        return str(np.datetime64(stamps[-1]) + np.timedelta64(round(days * 86400), "s"))

    for q in ("q05", "median", "q95"):
        assert row[f"failure_date_{q}"] == date_of(row[f"rul_{q}"])
    assert row["onset_date"] == date_of(row["onset_time"] - row["t_last"])
    naive.write(tmp_path / "dated.csv")
    back = read_back(tmp_path / "dated.csv")
    assert back["failure_date_median"] == [row["failure_date_median"]]
    with pytest.raises(ValueError, match="ISO 8601 date-time in 1678-2262"):
        read_fleet_table(
            {"asset": ["a"] * 60, "t": np.array(["9999-12-31"] + stamps[1:]), "value": y}
        )
    with pytest.raises(ValueError, match="numbers or ISO 8601 date-times, not both"):
        read_fleet_table({"asset": ["a"] * 60, "t": np.array(["0"] + stamps[1:]), "value": y})


def test_cli_refuses_options_it_would_ignore(tmp_path, fleet, capsys):
    write_table(tmp_path / "f.csv", {k: list(v) for k, v in fleet.table.items()})
    base = ["rul", str(tmp_path / "f.csv"), "--group-by", "asset", "--threshold", "20",
            "--out", str(tmp_path / "o.csv"), "--no-progress"]  # fmt: skip
    for extra, text in ((["--method", "prognose", "--phi", "15"], "--phi applies to"),
                        (["--min-rows", "-3"], "--min-rows must be at least 1"),
                        (["--workers", "0"], "--workers must be at least 1")):  # fmt: skip
        assert cli_main([*base, *extra]) == 2
        err = capsys.readouterr().err
        assert err.startswith("error: ") and text in err
        assert not (tmp_path / "o.csv").exists()


def test_glitch_in_baseline_flag_matches_prognose_per_asset():
    """The fleet's batched glitch screen against ``prognose``'s flag and
    ``healthy_baseline(glitch_limit=20)`` asset by asset: a clean asset, one glitch of 40 noise
    std in a window of 120 (widening 3.7), one of 24 in a window of 900 (1.3: not flagged), a
    pair in a window with missing values, ragged lengths."""
    from prognos_torch.prognosis.onset import healthy_baseline
    from prognos_torch.workflow import prognose

    g = np.random.default_rng(5)
    lengths = (400, 400, 3000, 350)
    t = [np.arange(n, dtype=float) for n in lengths]
    v = [1.0 + 0.05 * g.standard_normal(n) for n in lengths]
    v[1][40] += 2.0
    v[2][100] += 1.2
    v[3][[30, 31]] += 3.0
    v[3][[10, 50]] = np.nan
    batch = pad_batch(["clean", "glitch", "long", "pair"], t, v)
    on = ksigma_onset_batch(batch.values, batch.times, batch.lengths, skip_window=True)
    out = exponential_trend_rul(batch, 3.0, samples=50)
    for b, name in enumerate(batch.assets):
        x, tb = torch.from_numpy(v[b]), torch.from_numpy(t[b])
        plain, screened = healthy_baseline(x, tb), healthy_baseline(x, tb, glitch_limit=20.0)
        ref = plain.std / screened.std if screened.glitches else 1.0
        assert float(on.glitch_widening[b]) == pytest.approx(ref, rel=1e-12)
        flagged = "glitch_in_baseline" in out["flags"][b].split(";")
        per_series = any(f.startswith("glitches in") for f in prognose(x, 3.0, time=tb).flags)
        assert flagged == per_series == (name in ("glitch", "pair")), name


def test_asset_ids_of_an_object_column_are_read_per_cell_and_by_type():
    # each distinct id is converted once: a cache keyed by value alone would read True as 1
    from prognos_torch.fleet.table import _asset_text

    col = np.array([True, 1, "1", 1.0, 2.5, None, float("nan"), " b ", True, 1], dtype=object)
    got = _asset_text(col)
    assert got.tolist() == ["True", "1", "1", "1", "2.5", "", "", "b", "True", "1"]
    assert got.dtype == object


def test_an_option_the_method_does_not_take_is_refused_before_the_table_is_read(tmp_path):
    """A misspelt option was refused by the method itself, after the whole table had been
    read, naming an internal function; now fleet_rul names it first (the file below does
    not exist, so reading it would fail otherwise)."""
    missing = tmp_path / "no_such_fleet.csv"
    with pytest.raises(TypeError, match=r"fleet_rul got 'sample', not an option of method "
                       r"'exponential'; its options: .*\bsamples\b"):  # fmt: skip
        fleet_rul(missing, 20.0, sample=10)
    with pytest.raises(TypeError, match=r"got 'n_path', not an option of method 'prognose'; "
                       r"its options: .*\bn_paths\b"):  # fmt: skip
        fleet_rul(missing, 20.0, method="prognose", n_path=10)
    # what fleet_rul sets itself is not an option of prognose's
    with pytest.raises(TypeError, match="got 'at', not an option"):
        fleet_rul(missing, 20.0, method="prognose", at=3.0)
    with pytest.raises(FileNotFoundError):
        fleet_rul(missing, 20.0, method="prognose", n_paths=10, learner_members=2)


def test_one_column_in_two_roles_is_refused():
    """--column t --time-column t read the clock as the indicator without a word."""
    tab = {"asset": ["a"] * 20, "t": list(range(20)), "value": list(range(20))}
    for kw, msg in (
        (dict(column="t"), "time (--time-column) and value (--column)"),
        (dict(time_column="asset"), "asset (--group-by) and time (--time-column)"),
    ):
        with pytest.raises(ValueError, match=rf"the {re.escape(msg)} columns must differ"):
            read_fleet_table(tab, **kw)


def test_one_row_assets_get_their_flag_whatever_the_shards():
    """A shard holding only one-row assets raised an IndexError (the healthy window's noise
    and the median step of an empty difference), so the table depended on --shard-size."""
    tab = {"asset": ["a", "b", "b", "c"], "t": [0.0, 0.0, 1.0, 0.0], "value": [1.0, 1.0, 2.0, 1.0]}
    for shard_size in (1, 2, 1024):
        for phi in ("auto", 0.0, "baseline"):
            res = fleet_rul(tab, 20.0, shard_size=shard_size, phi=phi)
            assert res.columns["flags"] == ["too_few_rows"] * 3
    assert fleet_rul(tab, 20.0, shard_size=1, min_rows=1).columns["flags"][0] == "no_baseline"


def test_a_trend_past_the_threshold_the_data_have_not_reached_gives_no_rul():
    """A decaying indicator (direction below) that the baseline offset's trend overshoots: its
    fitted value at the last row lay below the threshold the data were three times above, and
    the asset came out failed for certain (RUL 0, no flag but the misfit). Missing last rows
    are said, as their crossing is a RUL of 0 counted from the last row."""
    t = np.arange(200.0)
    rng = np.random.default_rng(0)
    decay = np.exp(-0.02 * np.maximum(0, t - 100) + rng.normal(0, 0.01, 200))
    res = fleet_rul({"asset": ["F"] * 200, "t": t, "value": decay}, 0.05, direction="below")
    assert "fit_past_threshold" in res.columns["flags"][0].split(";")
    assert math.isnan(res.columns["rul_median"][0]) and decay[-1] > 2 * 0.05
    rise = np.exp(0.05 * np.maximum(0, t - 100) + rng.normal(0, 0.01, 200))
    rise[150:] = np.nan  # the last observed value 11.6 < 20; the trend crosses near t = 160
    res = fleet_rul({"asset": ["G"] * 200, "t": t, "value": rise}, 20.0)
    assert res.columns["flags"] == ["last_rows_missing"] and res.columns["rul_median"] == [0.0]
    whole = fleet_rul({"asset": ["G"] * 150, "t": t[:150], "value": rise[:150]}, 20.0)
    assert whole.columns["flags"] == [""] and whole.columns["rul_median"][0] > 0


def test_prognose_method_reports_a_reached_threshold_as_the_exponential_method_does():
    """An asset whose last value is beyond the threshold came back from method="prognose" as
    prognose_error with no RUL (prognose refuses it); the exponential method said
    threshold_reached with RUL 0. Both say the latter now."""
    t = np.arange(120.0)
    y = np.exp(0.05 * np.maximum(0, t - 60) + np.random.default_rng(2).normal(0, 0.01, 120))
    tab = {"asset": ["X"] * 120, "t": t, "value": y}  # ends at 20, threshold 10
    for method, kw in (("prognose", {"n_paths": 100}), ("exponential", {})):
        res = fleet_rul(tab, 10.0, method=method, **kw)
        assert res.columns["flags"] == ["threshold_reached"], method
        assert res.columns["rul_median"] == [0.0] and res.columns["p_fail_within_horizon"] == [1.0]


def test_prognose_method_flags_a_threshold_on_the_healthy_side_not_rul_zero():
    """A falling capacity (healthy near 1, threshold 0.8) with the default direction "above"
    came back from method="prognose" as threshold_reached with RUL 0 for every healthy asset;
    it gets the exponential method's threshold_on_healthy_side and no RUL now. An asset whose
    rising indicator did reach the threshold is still RUL 0 (neither calls prognose)."""
    t = np.arange(30.0)
    wobble = 0.01 * np.sin(t)
    tab = {"asset": ["cap"] * 30 + ["rms"] * 30, "t": np.concatenate([t, t]),
           "value": np.concatenate([1.0 - 0.001 * t + wobble, 0.5 + 0.02 * t + wobble])}  # fmt: skip
    # reference: the healthy window's mean (first 30 % of the time span) against 0.8
    first = t <= 0.3 * t[-1]
    assert (1.0 - 0.001 * t + wobble)[first].mean() > 0.8 > (0.5 + 0.02 * t + wobble)[first].mean()
    for method in ("prognose", "exponential"):
        res = fleet_rul(tab, 0.8, method=method)
        # the one flag: the exponential method also said no_onset, which the first one explains
        assert res.row("cap")["flags"] == "threshold_on_healthy_side", method
        assert math.isnan(res.row("cap")["rul_median"]), method
        assert res.row("rms")["flags"] == "threshold_reached" and res.row("rms")["rul_median"] == 0


def test_direction_and_min_rows_are_refused_by_name_before_the_table_is_read(tmp_path):
    """A mistyped direction reached method="prognose" per asset and came back as a
    prognose_error row for every asset; min_rows=0 or -1 sent assets without a value to the
    fit, and 2.5 was taken as is. All are argument errors, raised before the table is read."""
    missing = tmp_path / "not_there.csv"
    with pytest.raises(ValueError, match=r"direction must be 'above', 'below' or 'auto' .*'Below'"):
        fleet_rul(missing, 0.8, method="prognose", direction="Below")
    with pytest.raises(ValueError, match=r"direction must be 'above' or 'below' .*got 'auto'"):
        fleet_rul(missing, 0.8, direction="auto")
    for bad, err in ((0, ValueError), (-1, ValueError), (2.5, TypeError), (True, TypeError)):
        with pytest.raises(err, match=r"min_rows must be"):
            fleet_rul(missing, 0.8, min_rows=bad)
    batch = pad_batch(["a"], [np.arange(3.0)], [np.ones(3)])
    for method in METHODS.values():
        with pytest.raises(ValueError, match=r"min_rows must be >= 1 \(observed rows\), got 0"):
            method(batch, 2.0, min_rows=0)
    with pytest.raises(ValueError, match=r"direction must be .*got 'up'"):
        METHODS["prognose"](batch, 2.0, direction="up")


def test_a_column_with_one_cell_for_the_whole_table_is_refused_not_spread():
    """A single asset id for a one-asset table ({"asset": "A", ...}) raised "len() of unsized
    object"; columns of two lengths said only "must be 1-D"."""
    t = np.arange(5.0)
    with pytest.raises(ValueError, match=r"table: column 'asset' must be 1-D \(one cell per row\), got shape \(\)"):  # fmt: skip
        read_fleet_table({"asset": "A", "t": t, "value": t})
    with pytest.raises(ValueError, match=r"column 'value' has 4 rows, column 'asset' has 5"):
        read_fleet_table({"asset": ["A"] * 5, "t": t, "value": t[:4]})
    # (and a result asked for an asset it does not hold said only "'B' is not in list")
    res = fleet_rul({"asset": [7] * 5, "t": t, "value": t}, 20.0)
    assert res.row(7) == res.row("7")
    with pytest.raises(ValueError, match=r"asset 'B' is not in this result \(1 assets\)"):
        res.row("B")


def test_baseline_phi_with_a_drift_does_not_depend_on_the_shard():
    """With drift_std the baseline trend's iterated smoother ran every asset of a shard until
    the LAST one had converged, so an asset's RUL moved (~1e-7) with its shard mates; each
    asset now stops where it converges alone."""
    g = torch.Generator().manual_seed(1)
    t = torch.arange(40.0, dtype=torch.float64)

    def rise(rate, noise, start):
        ramp = torch.where(t > start, torch.exp(rate * (t - start)) - 1, 0.0)
        return (1.0 + ramp + noise * torch.randn(40, generator=g, dtype=torch.float64)).numpy()

    ys = [rise(0.1, 0.02, 20), rise(0.05, 0.3, 12)]  # 5 and 3 iterations alone
    kw = dict(phi="baseline", drift_std=(1e-2, 1e-3), samples=20)
    whole = exponential_trend_rul(pad_batch(["a", "b"], [t.numpy()] * 2, ys), 60.0, **kw)
    for i, a in enumerate("ab"):
        alone = exponential_trend_rul(pad_batch([a], [t.numpy()], [ys[i]]), 60.0, **kw)
        assert alone["flags"][0] == whole["flags"][i]
        for c in ("rul_median", "rul_q05", "rul_q95"):
            np.testing.assert_allclose(alone[c][0], whole[c][i], rtol=1e-12, atol=0)


def test_a_healthy_window_of_one_repeated_value_has_no_baseline_whatever_its_rounding():
    """A constant healthy window of 0.1s has a round-off std of 1.5e-17 (1s: exactly 0), which
    made a band of 1e-16 around it and the first rise an onset; both now get no_baseline."""
    t = np.arange(60.0)
    for level in (0.1, 1.0):
        y = np.full(60, level)
        y[40:] = level + 0.01 * np.exp((t[40:] - 40) / 5)
        assert fleet_rul({"asset": ["a"] * 60, "t": t, "value": y}, 5.0).row("a")["flags"] == \
            "no_baseline", level  # fmt: skip


@pytest.mark.parametrize("direction", ["above", "below"])
def test_prognose_method_reads_a_median_past_the_threshold_as_reached(direction):
    """An asset whose last value dipped back below the threshold while the median of its last
    5 values is past it: ``prognose``'s own rule says the threshold is reached (it refuses the
    series, RUL 0), so the row is ``threshold_reached`` with RUL 0, as for a last value past
    it (it was ``prognose_error``); a last value past it alone is reached as before."""
    from prognos_torch.workflow import prognose

    g = np.random.default_rng(0)
    t = np.arange(160.0)
    y = 1.0 + 0.02 * g.standard_normal(160)
    y[150:] = [1.5, 2.0, 2.6, 3.1, 3.2, 3.3, 3.1, 3.4, 3.2, 2.9]  # median of the last 5: 3.2
    sign = 1.0 if direction == "above" else -1.0
    table = {"asset": ["m"] * 160, "t": t, "value": sign * y}
    with pytest.raises(ValueError, match="already reached: the median of the last 5"):
        prognose(torch.from_numpy(sign * y), sign * 3.0, time=torch.from_numpy(t),
                 direction=direction)  # fmt: skip
    row = fleet_rul(table, sign * 3.0, method="prognose", direction=direction,
                    n_paths=100).row("m")  # fmt: skip
    assert row["flags"] == "threshold_reached" and row["message"] == ""
    assert (row["rul_median"], row["p_fail_within_horizon"]) == (0.0, 1.0)
    spike = dict(table, value=sign * np.concatenate([y[:159], [3.5]]))
    spike["value"][150:159] = sign * 1.5  # only the last value past it
    assert fleet_rul(spike, sign * 3.0, method="prognose", direction=direction,
                     n_paths=100).row("m")["flags"] == "threshold_reached"  # fmt: skip
