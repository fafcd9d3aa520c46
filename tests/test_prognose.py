"""workflow.prognose: the one entry point from a degradation series to a RUL distribution."""

from __future__ import annotations

import functools
import math
import re

import numpy as np
import pytest
import torch

from prognos_torch.prognosis import healthy_baseline
from prognos_torch.workflow import RULResult, Series, load_series, prognose

F64 = torch.float64
PHI, A, B, ON = 1.0, 0.05, 0.02, 400  # y = PHI + A exp(B (t - ON)) after ON


def _series(n=550, noise_after=0.0, seed=0):
    """A healthy phase alternating exactly around PHI (mean PHI, std 0.05) and a noiseless (or
    noisy) exponential rise after ON."""
    t = torch.arange(n, dtype=F64)
    y = PHI + 0.05 * (-1.0) ** torch.arange(n, dtype=F64)
    s = (t - ON).clamp(min=0)
    rise = A * torch.exp(B * s)
    if noise_after:
        g = torch.Generator().manual_seed(seed)
        rise = rise * torch.exp(noise_after * torch.randn(n, generator=g, dtype=F64))
    y = torch.where(t >= ON, PHI + rise, y)
    return t, y


@functools.cache
def _noisy_auto():
    """``prognose``'s default answer (auto, EKF, seed 0) on the noisy rise, threshold 3: a
    reference that several tests compare with, computed once (read only)."""
    t, y = _series(noise_after=0.05)
    return prognose(y, 3.0, time=t)


def _crossing(threshold):
    return ON + math.log((threshold - PHI) / A) / B


def test_noiseless_exponential_rul_equals_the_closed_form():
    t, y = _series()
    thr = 3.0
    res = prognose(y, thr, time=t, method="exponential")
    assert isinstance(res, RULResult) and res.status == "ok" and res.model == "exponential"
    s = res.summary()
    true = _crossing(thr) - float(t[-1])
    assert s["median"] == pytest.approx(true, rel=0.02)
    assert s["q05"] <= s["median"] <= s["q95"]
    assert s["censored_mass"] == 0.0
    assert res.onset.detected and ON < res.onset.time < ON + 80
    assert set(s) >= {"median", "q05", "q95", "censored_mass", "bound", "status", "model"}
    # the horizon is a multiple of the observed life, not a short fixed cap
    assert s["bound"] >= 2.0 * float(t[-1] - t[0])


def test_failure_probability_reads_the_rul_distribution():
    """P(RUL <= h) from the per-path RULs of the paths alive at ``at`` agrees with the
    distribution's cdf (the binned route) to within one bin, is consistent with the summary's
    quantiles, and brackets the closed-form crossing of the noiseless exponential model."""
    t, y = _series()
    res = prognose(y, 3.0, time=t, method="exponential", at=float(t[-1]) + 3.5)
    s, true = res.summary(), _crossing(3.0) - (float(t[-1]) + 3.5)
    cdf = res.distribution.cdf
    for h in (0.0, 0.5 * true, 0.95 * true, true, 1.05 * true, 2.0 * true, res.bound):
        k = int(h / res.dt)  # bins wholly within h: a lower bound; one more: an upper bound
        lo = float(cdf[k - 1]) if k else 0.0
        hi = float(cdf[min(k, cdf.numel() - 1)])
        assert lo - 1e-12 <= res.failure_probability(h) <= hi + 1e-12
    assert (
        res.failure_probability(s["median"]) >= 0.5 > res.failure_probability(s["median"] - res.dt)
    )
    assert res.failure_probability(s["q05"]) >= 0.05
    assert res.failure_probability(0.7 * true) < 0.05 < 0.95 < res.failure_probability(1.3 * true)
    with pytest.raises(ValueError, match="within must be >= 0"):
        res.failure_probability(-1.0)
    with pytest.raises(ValueError, match="within must be a finite number"):
        res.failure_probability(float("nan"))
    # before onset nothing is estimated; beyond the horizon only a lower bound is known
    flat = prognose(y[:300], 3.0, time=t[:300])
    assert flat.status != "ok" and flat.failure_probability(5.0) is None
    cens = prognose(y, 1e6, time=t, method="linear")  # nearly every path censored
    assert cens.censored_mass > 0.5 and cens.failure_probability(cens.bound) < 0.5
    with pytest.raises(ValueError, match="beyond the horizon bound"):
        cens.failure_probability(2.0 * cens.bound)


def test_quantiles_are_the_exact_crossing_times_not_bin_edges():
    """``quantile`` (and the summary) reads the per-path RULs: the ``ceil(q N)``-th smallest,
    so that ``P(RUL <= Q(q)) >= q > P(RUL < Q(q))``. The binned distribution's quantile is the
    upper edge of a bin: with the evaluation time half a step after the last observation every
    crossing time lies half a bin below its edge, and the bin edge reads late by that half."""
    t, y = _series(noise_after=0.05)
    res = prognose(y, 3.0, time=t, method="exponential", at=float(t[-1]) + 3.5)
    x = res.rul_samples[~torch.isnan(res.rul_samples)].sort().values
    assert torch.isfinite(x).all() and res.censored_mass == 0.0
    qs = (0.05, 0.25, 0.5, 0.95)
    exact = res.quantile(qs)
    binned = res.distribution.quantile(qs)
    for q, v, b in zip(qs, exact.tolist(), binned.tolist()):
        assert v == float(x[math.ceil(q * x.numel()) - 1])
        assert res.failure_probability(v) >= q > res.failure_probability(v - 1e-9)
        assert b - v == pytest.approx(0.5 * res.dt, abs=1e-9)
    s = res.summary()
    assert (s["q05"], s["median"], s["q95"]) == tuple(exact[[0, 2, 3]].tolist())
    assert s["mean"] == pytest.approx(float(x.mean()), rel=1e-12)
    assert float(res.quantile(0.5)) == s["median"]
    # censored mass is the upper tail; nothing estimated before onset; q outside (0, 1]
    cens = prognose(y, 1e6, time=t, method="linear")
    assert cens.censored_mass > 0.5 and math.isnan(float(cens.quantile(0.9)))
    assert cens.summary()["q95"] is None and cens.summary()["mean"] is None
    flat = prognose(y[:300], 3.0, time=t[:300])
    assert flat.status != "ok" and bool(torch.isnan(flat.quantile([0.05, 0.5])).all())
    for bad in (0.0, 1.5, float("nan"), [[0.5]]):
        with pytest.raises(ValueError, match="q must"):
            res.quantile(bad)


def test_auto_pools_exponential_and_learner_and_reports_the_scores():
    t, y = _series(noise_after=0.05)
    res = _noisy_auto()
    sel = res.selection
    assert sel["pairs"] > 0 and set(sel["scores"]) == {"exponential", "power", "linear", "elm"}
    assert res.model == sel["chosen"] == "exponential+elm" and sel["pool"] == ("exponential", "elm")
    assert res.summary()["median"] is not None
    # half the paths come from each model: the pooled samples are those of the two models
    exp = prognose(y, 3.0, time=t, method="exponential", n_paths=4000)
    elm = prognose(y, 3.0, time=t, method="elm", n_paths=4000)
    q = lambda r: torch.nanquantile(r.rul_samples.clamp(max=1e9), 0.5).item()  # noqa: E731
    lo, hi = sorted((q(exp), q(elm)))
    assert lo - 5 <= res.summary()["median"] <= hi + 5


def test_several_seeds_pool_the_models_each_seed_fits():
    """``seed=(0, 1, 2)``: each seed's models, noise choice and ELMs included, are exactly those
    of a call with that seed alone (the same backtest scores), they are pooled with equal
    weights (the pooled median lies within the seeds' range), and one seed in a tuple is that
    seed; with several filters every filter is run under every seed."""
    t, y = _series(noise_after=0.05)
    one = {s: prognose(y, 3.0, time=t, seed=s) for s in (1, 2)} | {0: _noisy_auto()}
    pool = prognose(y, 3.0, time=t, seed=(0, 1, 2))
    runs = ("EKF, seed 0", "EKF, seed 1", "EKF, seed 2")
    assert pool.model == " + ".join(f"exponential+elm ({r})" for r in runs)
    assert pool.filter == "EKF" and tuple(pool.selection["by_run"]) == runs
    for s, r in zip((0, 1, 2), runs):
        assert pool.selection["by_run"][r]["scores"] == one[s].selection["scores"]
    assert one[0].selection["scores"] != one[1].selection["scores"]  # the seeds differ
    assert pool.rul_samples.numel() == 2000 and pool.onset.time == one[0].onset.time
    med = sorted(r.summary()["median"] for r in one.values())
    assert med[0] - 2 <= pool.summary()["median"] <= med[-1] + 2
    assert torch.equal(prognose(y, 3.0, time=t, seed=[1]).rul_samples, one[1].rul_samples)
    both = prognose(y, 3.0, time=t, seed=(0, 1), filter="ekf+stekf", method="exponential")
    assert set(both.selection["by_run"]) == {"EKF, seed 0", "EKF, seed 1", "STEKF, seed 0",
                                             "STEKF, seed 1"}  # fmt: skip
    assert both.filter == "EKF+STEKF"
    for bad, err, msg in (((), ValueError, "non-empty"), ((1, 1), ValueError, "twice"),
                          ((1, "a"), TypeError, "seed must be an int"),
                          ((1, 2.0), TypeError, "seed must be an int")):  # fmt: skip
        with pytest.raises(err, match=msg):
            prognose(y, 3.0, time=t, seed=bad)


def test_several_filters_pool_the_models_fitted_under_each():
    """``filter="ekf+stekf"``: each filter's models, noise choice included, are exactly those of
    a call with that filter alone (the same backtest scores), and their RUL distributions are
    pooled with equal weights (the pooled median lies between the two). The series jumps
    during its rise, so that strong tracking fires."""
    t, y = _series(noise_after=0.05)
    y = torch.where(t >= 470, PHI + 1.8 * (y - PHI), y)
    one = {f: prognose(y, 3.0, time=t, filter=f) for f in ("ekf", "stekf")}
    both = prognose(y, 3.0, time=t, filter="ekf+stekf")
    assert both.model == "exponential+elm (EKF) + exponential+elm (STEKF)"
    assert both.filter == "EKF+STEKF" and one["ekf"].filter == "EKF"
    by = both.selection["by_filter"]
    assert by["EKF"]["scores"] == one["ekf"].selection["scores"]
    assert by["STEKF"]["scores"] == one["stekf"].selection["scores"]
    assert by["EKF"]["scores"] != by["STEKF"]["scores"]  # strong tracking moved the fits
    # the learner trend alone: each run is named by the filter of the fit it learns from
    elm = prognose(y, 3.0, time=t, method="elm", filter="ekf+stekf")
    assert elm.model == "elm (EKF) + elm (STEKF)" and set(elm.selection["by_filter"]) == {
        "EKF", "STEKF"}  # fmt: skip
    assert elm.filter == "EKF+STEKF"
    med = sorted(r.summary()["median"] for r in one.values())
    assert med[0] - 2 <= both.summary()["median"] <= med[1] + 2
    # the tuple form is the same call; one filter in a tuple is that filter
    tup = prognose(y, 3.0, time=t, filter=("ekf", "stekf"))
    assert torch.equal(tup.rul_samples, both.rul_samples)
    assert torch.equal(prognose(y, 3.0, time=t, filter=("ekf",)).rul_samples,
                       one["ekf"].rul_samples)  # fmt: skip
    for bad, msg in (("ekf+ekf", "twice"), ("stpf", "Gaussian filters"), ((), "filter must"),
                     (3, "filter must"), (("ekf", 3), "names or GaussianFilters")):  # fmt: skip
        with pytest.raises(ValueError, match=msg):
            prognose(y, 3.0, time=t, filter=bad)


def test_auto_flags_model_doubt_on_linear_wear():
    t = torch.arange(800, dtype=F64)
    g = torch.Generator().manual_seed(1)
    y = 1.0 + 0.02 * torch.randn(800, generator=g, dtype=F64)
    y = y + torch.where(t >= 400, 0.004 * (t - 400), torch.zeros_like(t))
    res = prognose(y, 4.0, time=t)
    assert res.model == "exponential+elm"
    assert any(f.startswith("model doubt: the linear shape") for f in res.flags)
    lin = prognose(y, 4.0, time=t, method="linear")
    true = 400 + 3.0 / 0.004 - 799  # the noise-free wear reaches 4.0 at t = 1150
    assert lin.summary()["median"] == pytest.approx(true, rel=0.1)


def test_one_standard_error_rule_and_crps():
    from prognos_torch.prognosis import crps_log_time, one_standard_error_choice

    t = lambda *v: torch.tensor(v, dtype=F64)  # noqa: E731
    # clearly better on every pair: chosen; better on average but noisy: the default stays
    assert one_standard_error_choice({"exponential": t(1, 1, 1), "power": t(0.5, 0.4, 0.6)},
                                     "exponential") == "power"  # fmt: skip
    assert one_standard_error_choice({"exponential": t(1, 1, 1), "power": t(0.1, 1.5, 1.2)},
                                     "exponential") == "exponential"  # fmt: skip
    # k standard errors: d = (-0.5, -0.6, -0.4), mean -0.5, se 0.0577: beaten by 8.7 se
    sc = {"exponential": t(1, 1, 1), "power": t(0.5, 0.4, 0.6)}
    assert one_standard_error_choice(sc, "exponential", k=8.0) == "power"
    assert one_standard_error_choice(sc, "exponential", k=9.0) == "exponential"
    # CRPS of a point mass at the truth is 0; of a sample spread 0 it is |log ratio|
    assert float(crps_log_time(t(2.0, 2.0, 2.0), 2.0, 100.0)) == pytest.approx(0.0, abs=1e-15)
    assert float(crps_log_time(t(4.0), 2.0, 100.0)) == pytest.approx(math.log(2.0))
    # a closed form: samples uniform on two points a < b, CRPS = mean|X-x| - (b-a)/4
    got = float(crps_log_time(t(1.0, math.e), 1.0, 100.0))
    assert got == pytest.approx(0.5 - 0.25)


def test_backtest_pairs_and_scores_against_closed_forms():
    from prognos_torch.prognosis import backtest_scores, crossing_pairs
    from prognos_torch.prognosis.trends import Passage

    # a noise-free ramp y = t on t = 0..100: the trailing 5-point median is t - 2 from t = 4 on,
    # so m_0 = 0 and the top is 98; level 49 (f = 0.5) is first reached at t = 51 and 78.4
    # (f = 0.8) at t = 81; the origins are the last samples at 40 % and 70 % of the way
    t = torch.arange(101, dtype=F64)
    pairs = crossing_pairs(t, t.clone(), 0.5)
    want = [(49.0, 20, 51.0), (49.0, 35, 51.0), (78.4, 32, 81.0), (78.4, 56, 81.0)]
    assert len(pairs) == 4
    for (c, i, tc), (c_, i_, tc_) in zip(pairs, want):
        assert c == pytest.approx(c_, abs=1e-12) and (i, tc) == (i_, tc_)
    assert crossing_pairs(t, torch.zeros(101, dtype=F64), 0.5) == []  # no rise: no pairs

    class Exact:  # predicts every crossing at ratio x the true duration, for every path
        def __init__(self, ratio):
            self.ratio = ratio

        def first_passage(self, i, level, grid, n, gen, keep=0):
            tc = next(tc for c, j, tc in pairs if c == level and j == i)
            return Passage(torch.full((n,), float(t[i]) + self.ratio * (tc - float(t[i])), dtype=F64),
                           None, torch.zeros(n, dtype=torch.bool))  # fmt: skip

    assert torch.allclose(backtest_scores(Exact(1.0), pairs, t, None), torch.zeros(4, dtype=F64))
    # CRPS of a point mass on the log scale: |log ratio|; censored beyond 10 x counts as 10 x
    assert torch.allclose(backtest_scores(Exact(2.0), pairs, t, None),
                          torch.full((4,), math.log(2.0), dtype=F64))  # fmt: skip
    assert torch.allclose(backtest_scores(Exact(math.inf), pairs, t, None),
                          torch.full((4,), math.log(10.0), dtype=F64))  # fmt: skip


def test_direction_below_mirrors_above():
    t, y = _series(noise_after=0.05)
    up = prognose(y, 3.0, time=t, method="linear", seed=3)
    down = prognose(-y, -3.0, time=t, method="linear", seed=3)
    assert down.direction == "below" and up.direction == "above"
    assert down.summary()["median"] == up.summary()["median"]
    torch.testing.assert_close(down.paths, -up.paths)


@pytest.mark.parametrize("method", ["exponential", "power", "linear", "elm"])
def test_rul_does_not_depend_on_units(method):
    """A change of units of the data (scale and offset: g to m/s^2, a sensor bias) or of the
    clock (days to minutes, another origin) maps the RUL exactly: every model, the learner
    trend's prior included, sees only unit-free quantities."""
    t, y = _series(noise_after=0.05, n=520)
    ref = prognose(y, 3.0, time=t, method=method, at=525.0).summary()

    def same(s, tscale=1.0, ref=ref):
        for k in ("median", "q05", "q95"):
            a, b = ref[k], s[k]
            assert (a is None) == (b is None), k
            if a is not None:
                assert b / tscale == pytest.approx(a, rel=1e-8), k
        assert s["censored_mass"] == pytest.approx(ref["censored_mass"], abs=1e-12)

    values = ((1e-3, 0.0), (9.81, 0.0), (1e3, 0.0), (1.0, 7.0), (-2.5, 3.0), (1e-9, 0.0),
              (1.0, 1e6))  # fmt: skip
    # days to minutes, another origin, 10-minute samples in hours (a step that is no binary
    # fraction), Unix seconds; each change of the data's units goes with one of the clock's
    clocks = ((1.0, 0.0), (1440.0, 0.0), (1.0, 1e4), (1.0 / 6.0, 0.0), (600.0, 1.7e9))
    for i, (c, d) in enumerate(values):
        ts, t0 = clocks[i % len(clocks)]
        got = prognose(c * y + d, c * 3.0 + d, time=ts * t + t0, method=method, at=ts * 525.0 + t0)
        same(got.summary(), ts)
    # at the last observation the crossings fall on bin edges, where rounding used to decide
    ref0 = prognose(y, 3.0, time=t, method=method).summary()
    for j, (ts, t0) in enumerate(clocks[1:]):
        c, d = values[(2 * j + 1) % len(values)]
        same(prognose(c * y + d, c * 3.0 + d, time=ts * t + t0, method=method).summary(), ts, ref0)


def test_every_path_keeps_its_bin_when_the_clock_changes():
    """Crossings on the grid's linear part lie on bin edges ``t_last + k dt``; with the clock in
    hours and 10-minute samples (``dt = 1/6``, no binary fraction) or in Unix seconds, rounding
    used to push most of them one bin later (1163 of 2000 paths). Now each path keeps its bin."""
    t = torch.arange(550, dtype=F64)
    g = torch.Generator().manual_seed(0)
    y = 1.0 + 0.05 * torch.randn(550, generator=g, dtype=F64)
    rise = 0.05 * torch.exp(0.02 * (t - 400).clamp(min=0))
    rise = rise * torch.exp(0.05 * torch.randn(550, generator=g, dtype=F64))
    y = torch.where(t >= 400, 1.0 + rise + 0.05 * torch.randn(550, generator=g, dtype=F64), y)
    ref = prognose(y, 3.0, time=t, method="exponential")
    assert ref.summary()["median"] < 50  # on the linear part of the grid
    for ts, t0 in ((1.0 / 6.0, 0.0), (600.0, 1.7e9), (0.1, 0.0)):
        got = prognose(y, 3.0, time=ts * t + t0, method="exponential")
        assert torch.equal(got.distribution.first_passage, ref.distribution.first_passage)


def test_backtest_origins_on_sample_times_do_not_depend_on_the_clock_origin():
    """Regular sampling puts a backtest origin (a fraction of the way to a crossed level)
    exactly on a sample time; in seconds from 0 and in days since 1970 the same sample must
    be taken, whatever the last bit of the clock's rounding."""
    t, y = _series(noise_after=0.1, seed=1)
    ref = prognose(y[:490], 3.0, time=t[:490] * 10.0, method="exponential").summary()
    got = prognose(y[:490], 3.0, time=t[:490] * 10.0 / 86400 + 19700.0, method="exponential")
    got = got.summary()
    assert got["median"] * 86400 == pytest.approx(ref["median"], rel=1e-6)
    assert got["censored_mass"] == pytest.approx(ref["censored_mass"], abs=1e-12)


def test_lower_bound_before_onset_does_not_depend_on_units():
    """The no-degradation bound (a linear trend of the healthy data) in any units of the data
    and the clock; its positive floors used to be absolute (1 step for values near 1e-9)."""
    g = torch.Generator().manual_seed(0)
    y = 1.0 + 0.05 * torch.randn(3000, generator=g, dtype=F64)
    t = torch.arange(3000, dtype=F64)
    ref = prognose(y, 2.0, time=t).summary()["bound"]
    assert ref > 1000
    for c, d in ((1e-9, 0.0), (1e3, 0.0), (1.0, 1e6), (-1.0, 0.0)):
        assert prognose(c * y + d, c * 2.0 + d, time=t).summary()["bound"] == pytest.approx(ref)
    for ts, t0 in ((1.0 / 6.0, 0.0), (600.0, 1.7e9)):
        b = prognose(y, 2.0, time=ts * t + t0).summary()["bound"]
        assert b / ts == pytest.approx(ref)


def test_rul_after_a_long_gap_keeps_the_bin_resolution():
    """With ``at`` far after the last observation the path grid starts again at ``at``: the
    RULs near 0 lie on the bins ``k dt`` (the grid's geometric steps from the last observation
    used to leave nothing below about 2 % of the gap)."""
    t, y = _series(noise_after=0.05, n=520)
    res = prognose(y, 3.0, time=t, method="linear", at=float(t[-1]) + 200.0)
    r = res.rul_samples[torch.isfinite(res.rul_samples)]
    near = r[r < 50 * res.dt]
    assert near.numel() > 0 and float(near.min()) <= 5 * res.dt
    k = near / res.dt
    assert torch.allclose(k, k.round(), atol=1e-9)


def test_missing_values_are_skipped():
    t, y = _series(noise_after=0.05)
    ym = y.clone()
    gone = torch.tensor([50, 120, 450, 451, 500])
    ym[gone] = math.nan
    keep = ~torch.isnan(ym)
    a = prognose(ym, 3.0, time=t, method="exponential", seed=1)
    b = prognose(y[keep], 3.0, time=t[keep], method="exponential", seed=1)
    assert a.summary()["median"] == b.summary()["median"]
    # the onset's indices and statistic refer to the series as given (NaN where missing)
    oa, ob = a.onset, b.onset
    assert oa.time == ob.time and float(t[oa.index]) == oa.time
    assert float(t[oa.alarm_index]) == oa.alarm_time
    assert oa.statistic.shape == ym.shape and bool(torch.isnan(oa.statistic[gone]).all())
    torch.testing.assert_close(oa.statistic[keep], ob.statistic)


def test_evaluation_time_after_the_last_observation():
    t, y = _series()
    res0 = prognose(y, 3.0, time=t, method="exponential")
    res = prognose(y, 3.0, time=t, method="exponential", at=float(t[-1]) + 10.0)
    assert res.t_last == float(t[-1]) + 10.0
    assert res.summary()["median"] == pytest.approx(res0.summary()["median"] - 10.0, abs=1.5)
    # paths that crossed before `at` are dropped, and counted in a flag
    late = prognose(y, 3.0, time=t, method="exponential", at=float(t[-1]) + res0.summary()["q05"])
    flag = [f for f in late.flags if "crossed before the evaluation time" in f]
    dead = int(flag[0].split(" of ")[0])
    assert flag[0].startswith(f"{dead} of 2000 paths (") and 0 < dead < 2000
    assert int(late.rul_samples.isnan().sum()) == dead


def test_no_degradation_gives_a_lower_bound_only():
    g = torch.Generator().manual_seed(0)
    y = 1.0 + 0.05 * torch.randn(3000, generator=g, dtype=F64)
    res = prognose(y, 2.0)
    s = res.summary()
    assert res.status == "no degradation detected yet"
    assert s["median"] is None and s["q05"] is None and s["q95"] is None and s["mean"] is None
    assert s["bound"] > 0 and res.lower_bound == s["bound"]
    assert not res.onset.detected
    assert any("no degradation detected yet" in f for f in res.flags)


def test_a_run_in_transient_is_no_onset():
    """A decaying run-in at the start (common on bearings) lies in the healthy window, which is
    taken as healthy: before the real onset the answer is "no degradation detected yet", after
    it the onset is the real one (a little later than with a clean start: the run-in widens
    the band)."""
    t, y = _series(noise_after=0.05)
    y = y + 1.0 * torch.exp(-t / 5.0)
    early = prognose(y[:350], 3.0, time=t[:350])
    assert early.status == "no degradation detected yet" and not early.onset.detected
    late = prognose(y, 3.0, time=t, method="exponential")
    assert late.status == "ok" and ON <= late.onset.time < ON + 150


def test_extrapolation_is_flagged():
    t, y = _series(noise_after=0.05)
    res = prognose(y, 1e4, time=t, method="linear")
    assert any(f.startswith("extrapolation") for f in res.flags)


def test_a_threshold_far_beyond_the_data_in_data_units_is_flagged():
    # IMS test 2 bearing 1 at 6.18 d (highest rms 0.17): in the log space of the shapes a
    # threshold of 100 is only about twice the rise seen away, so only the data-unit rule sees
    # it; the protocol's threshold (0.478) is not flagged
    from prognos_torch.datasets import load_ims_features

    f = load_ims_features(2)
    keep = f.days <= 6.181
    t, y = f.days[keep], f.feature("rms")[keep, 0]
    far = prognose(y, 100.0, time=t)
    assert [g for g in far.flags if g.startswith("extrapolation")] == [
        next(g for g in far.flags if "data units" in g)
    ]
    near = prognose(y, 0.4779, time=t)
    assert not any(g.startswith("extrapolation") for g in near.flags)


def test_a_series_back_at_its_healthy_level_is_flagged():
    # a transient after which the indicator returns to health: the log trends have no
    # measurement in the healthy values, so their RUL extrapolates the transient
    g = torch.Generator().manual_seed(0)
    y = 0.33 + 0.02 * torch.randn(800, generator=g, dtype=F64)
    y[500:530] += 0.5
    back = prognose(y, 1.1)
    assert back.status == "ok" and any(
        f.startswith("back at the healthy level") for f in back.flags
    )
    t, y = _series(noise_after=0.05)
    assert not any(f.startswith("back at") for f in prognose(y, 3.0, time=t).flags)


def test_onset_pending_is_flagged_before_onset():
    # 3 medians beyond the onset limit are fewer than the 5 in a row that declare onset
    g = torch.Generator().manual_seed(0)
    y = 1.0 + 0.05 * torch.randn(600, generator=g, dtype=F64)
    y[-5:] += 1.0  # the last 3 medians of 5 values are above mean + 4 std
    res = prognose(y, 3.0)
    assert res.status == "no degradation detected yet"
    pending = [f for f in res.flags if f.startswith("onset pending")]
    assert len(pending) == 1 and "the last 3 median(s)" in pending[0]
    assert not any(f.startswith("onset pending") for f in prognose(y[:-5], 3.0).flags)


def test_series_input():
    t, y = _series()
    s = Series(y, t, name="hi", time_name="t", time_unit="t")
    res = prognose(s, 3.0, method="exponential")
    assert res.time_unit == "t" and res.history.name == "hi"
    with pytest.raises(ValueError, match="time is taken from the Series"):
        prognose(s, 3.0, time=t)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"threshold": 1.25}, "already reached"),
        ({"threshold": 1.05}, "inside the healthy band"),
        ({"threshold": 0.5, "direction": "above"}, "wrong side"),
        ({"threshold": 0.5}, "left the band above it.*wrong side"),  # rising, threshold below
        ({"threshold": 3.0, "method": "cubic"}, "method must be"),
        ({"threshold": 3.0, "at": 10.0}, "before the last observation"),
        ({"threshold": math.nan}, "finite number"),
        ({"threshold": 3.0, "direction": "up"}, "direction"),
        ({"threshold": 3.0, "learner_hidden": 0}, "learner_hidden must be an int >= 1"),
        ({"threshold": 3.0, "learner_members": 0}, "learner_members must be an int >= 1"),
    ],
)
def test_bad_input(kwargs, match):
    t, y = _series()
    if kwargs.get("threshold") == 1.25:  # the last 5 values are beyond it
        y = torch.cat([y[:420], torch.full((5,), 1.3, dtype=F64)])
        t = torch.arange(y.shape[0], dtype=F64)
    with pytest.raises(ValueError, match=match):
        prognose(y, time=t, **kwargs)


def test_messages_tell_unix_times_and_offset_levels_apart():
    """On a clock of Unix seconds and with values offset by 64,000 (a sensor bias), errors and
    flags print times and levels with the digits that tell them apart (``%g`` printed both
    times below as 1.7e+09 and the band as [6.45e+04, 6.45e+04])."""
    t, y = _series()
    t, y = 600.0 * t + 1.7e9, y + 64_000.0
    late = r"at = 1700000600 is before the last observation 1700329400"
    with pytest.raises(ValueError, match=late):
        prognose(y, 64_003.0, time=t, at=1.7e9 + 600.0)
    with pytest.raises(ValueError) as err:
        prognose(y, 64_001.05, time=t)
    thr, lo, hi = (float(v) for v in re.findall(r"[-\d.]+(?=[],\s])", str(err.value))[:3])
    assert "inside the healthy band" in str(err.value) and lo < thr < hi
    assert (lo, hi) == pytest.approx((64_000.8, 64_001.2), abs=1e-3)
    # a series that settles below its healthy band, away from the threshold above it
    g = torch.arange(400, dtype=F64)
    z = PHI + 0.05 * (-1.0) ** g
    z = torch.where(g >= 200, z - 0.3 * ((g - 200) / 50).clamp(max=1.0), z) + 64_000.0
    res = prognose(z, 64_000.0 + PHI + 0.5, time=600.0 * g + 1.7e9)
    (flag,) = [f for f in res.flags if "left its healthy band below it" in f]
    assert re.search(r"below it at 17001\d{5}, away", flag)


def test_failure_date_is_the_last_time_plus_the_rul_quantile():
    """On date-times, failure_date(q) is the date-time of t_last + quantile(q) (UTC, to the
    second), computed here by NumPy from the first stamp; None on numeric time, for a quantile
    beyond the horizon and before onset."""
    t, y = _series(n=520, noise_after=0.05)
    stamps = np.datetime64("2024-03-01T00:00:00") + (t.numpy() * 600).astype("timedelta64[s]")
    res = prognose(y, 3.0, time=stamps, method="exponential")
    assert res.status == "ok"
    for q in (0.05, 0.5, 0.95):
        days = res.t_last + float(res.quantile(q))
        want = stamps[0] + np.timedelta64(round(days * 86400), "s")
        assert res.failure_date(q) == str(want)
    assert prognose(y, 3.0, time=t, method="exponential").failure_date(0.5) is None
    far = prognose(y, 30.0, time=stamps, method="linear")  # every path beyond the horizon
    assert far.status == "ok" and far.censored_mass > 0.05 and far.failure_date(0.95) is None
    early = prognose(y[:420], 3.0, time=stamps[:420], method="exponential")
    assert early.status != "ok" and early.failure_date(0.5) is None


def test_time_texts_in_a_time_format_are_the_same_date_times():
    """Times as text in another layout (day first; digits only) read with time_format give the
    RUL of the same times as ISO 8601 texts, through prognose and load_series; a cell that
    does not match, numbers with a time_format, and a time_format without time are named."""
    t, y = _series(n=520, noise_after=0.05)
    stamps = np.datetime64("2024-03-01T00:00:00") + (t.numpy() * 600).astype("timedelta64[s]")
    ref = prognose(y, 3.0, time=[str(s) for s in stamps], method="exponential").summary()
    moments = [s.astype("datetime64[s]").astype(object) for s in stamps]
    for fmt in ("%d/%m/%Y %H:%M:%S", "%Y%m%d%H%M%S"):
        texts = [m.strftime(fmt) for m in moments]
        got = prognose(y, 3.0, time=texts, time_format=fmt, method="exponential").summary()
        assert got["median"] == ref["median"] and got["q05"] == ref["q05"]
        series = load_series(y.numpy(), time=texts, time_format=fmt)
        assert series.start == "2024-03-01T00:00:00" and series.time_unit == "days"
    texts[7] = "7 March"
    with pytest.raises(ValueError, match=r"time\[7\] = '7 March' does not match time_format"):
        prognose(y, 3.0, time=texts, time_format="%Y%m%d%H%M%S")
    with pytest.raises(ValueError, match="time_format applies to date-times written as text"):
        prognose(y, 3.0, time=t, time_format="%Y")
    with pytest.raises(ValueError, match="time_format applies to time= given as text"):
        prognose(y, 3.0, time_format="%Y")
    with pytest.raises(ValueError, match="time_format applies to a time column or time="):
        load_series(y.numpy(), time_format="%Y")


def test_iso_texts_as_time_are_date_times():
    """Times as ISO 8601 texts (a CSV read without date parsing) give the RUL of the same
    times as datetime64, zone designators applied; a text that is no date-time is named."""
    t, y = _series(n=520, noise_after=0.05)
    stamps = np.datetime64("2024-03-01T00:00:00") + (t.numpy() * 600).astype("timedelta64[s]")
    ref = prognose(y, 3.0, time=stamps, method="exponential").summary()
    texts = [str(s) for s in stamps]
    zoned = [str(s - np.timedelta64(1, "h")) + "-01:00" for s in stamps]  # the same instants
    for times in (texts, np.array(texts), zoned):
        got = prognose(y, 3.0, time=times, method="exponential")
        assert got.time_unit == "days" and got.summary()["median"] == ref["median"]
    texts[7] = "yesterday"
    with pytest.raises(ValueError, match=r"time\[7\] = 'yesterday' is not an ISO 8601 date-time"):
        prognose(y, 3.0, time=texts)
    texts[7] = None  # a missing cell of a text column (None, NaN) is a missing date-time
    with pytest.raises(ValueError, match=r"time has missing date-times \(NaT\) at index 7"):
        prognose(y, 3.0, time=texts)


@pytest.mark.parametrize("bad", [None, 3.0, "0.5"])
def test_a_series_or_time_that_is_no_array_is_a_type_error(bad):
    with pytest.raises(
        TypeError, match=f"series must be a 1-D array of numbers .* got {type(bad).__name__}"
    ):
        prognose(bad, 1.0)
    if bad is None:
        return  # (time=None: the position)
    with pytest.raises(
        TypeError, match=f"time must be a 1-D array of numbers .* got {type(bad).__name__}"
    ):
        prognose(torch.ones(20, dtype=F64), 2.0, time=bad)


def test_an_excursion_away_from_the_threshold_is_refused_only_when_it_is_as_far():
    """A healthy level that settles 0.3 below its mean (a bearing's rms after run-in; its 5-value
    median, of alternating +-0.05, 0.35 below): with the threshold 0.5 above the mean that is a
    drift (no degradation yet, flagged); with the threshold 0.3 above it the series went further
    the other way (a wrong side, refused)."""
    t = torch.arange(400, dtype=F64)
    y = PHI + 0.05 * (-1.0) ** torch.arange(400, dtype=F64)
    y = torch.where(t >= 200, y - 0.3 * ((t - 200) / 50).clamp(max=1.0), y)
    res = prognose(y, PHI + 0.5, time=t)
    assert res.status == "no degradation detected yet" and res.lower_bound > 0
    (flag,) = [f for f in res.flags if "left its healthy band below it" in f]
    assert "moved 0.35 from the healthy mean, the threshold lies 0.5 on the other side" in flag
    with pytest.raises(ValueError, match=r"moved 0.35 .* lies 0.3 on the other side.*wrong side"):
        prognose(y, PHI + 0.3, time=t)
    assert not any("healthy band below" in f for f in prognose(y[:200], PHI + 0.5).flags)


def test_a_threshold_reached_before_and_fallen_back_from_is_flagged():
    t, y = _series(noise_after=0.05)
    y = y[:480].clone()
    y[440:446] = 3.5  # the median of 5 crosses 3.0, then the series falls back
    res = prognose(y, 3.0, time=t[:480], method="exponential")
    assert res.status == "ok"
    assert any("already reached the threshold at 442" in f for f in res.flags), res.flags
    clean = prognose(_series(noise_after=0.05)[1][:480], 3.0, time=t[:480], method="exponential")
    assert not any("already reached" in f for f in clean.flags)


def test_block_means_end_at_the_newest_value():
    """Above max_points values since onset the filter sees block means; the newest block is
    always a full one (a short newest block entered with a full block's noise, so the RUL
    followed the parity of the number of values), the oldest takes the remainder."""
    from prognos_torch.workflow.prognosing import _blocks

    g = torch.Generator().manual_seed(0)
    for n in (501, 502, 1003):
        t = torch.arange(n, dtype=F64)
        y = torch.randn(n, generator=g, dtype=F64)
        tb, yb, s0, size = _blocks(t, y, 0.3, 500)
        assert size == math.ceil(n / 500) and s0 == pytest.approx(0.3 / math.sqrt(size))
        torch.testing.assert_close(yb[-1], y[-size:].mean(), rtol=0, atol=1e-15)
        torch.testing.assert_close(tb[1:], t[n % size + size :].reshape(-1, size).mean(1))
        torch.testing.assert_close(yb[0], y[: size + n % size].mean(), rtol=0, atol=1e-15)


def test_pandas_and_datetime_input_give_the_array_result():
    """A pandas Series is taken by position (a filtered index is no time), a read-only pandas
    array raises no warning, date-times (NumPy, pandas, zone-aware, or a Series on a
    DatetimeIndex) are days since the first and durations (timedelta64, a pandas timedelta
    Series or TimedeltaIndex) are days, not nanoseconds: the RUL of the same data in days."""
    import warnings

    pd = pytest.importorskip("pandas")
    t, y = _series(noise_after=0.05)
    n = 480
    ref = prognose(y[:n], 3.0, time=t[:n] / 144.0, method="exponential").summary()  # 10-min steps
    rows = pd.Series(y[:n].numpy(), index=np.arange(n) * 2 + 7, name="rms")  # filtered rows
    since = pd.to_timedelta(t[:n].numpy() * 10, unit="min")
    stamps = pd.Timestamp("2004-02-12 10:32:39") + since
    cases = {
        "datetime64": (rows.to_numpy(), {"time": stamps.to_numpy()}),
        "pandas series": (rows, {"time": pd.Series(stamps)}),
        "zone-aware": (rows, {"time": stamps.tz_localize("Europe/Berlin")}),
        "DatetimeIndex": (pd.Series(rows.to_numpy(), index=stamps, name="rms"), {}),
        "timedelta64": (rows, {"time": since.to_numpy()}),
        "timedelta series": (rows, {"time": pd.Series(since)}),
        "TimedeltaIndex": (pd.Series(rows.to_numpy(), index=since, name="rms"), {}),
    }
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        for label, (values, kw) in cases.items():
            res = prognose(values, 3.0, method="exponential", **kw)
            got = res.summary()
            assert res.time_unit == "days", label
            assert got["median"] == pytest.approx(ref["median"], rel=1e-9), label
            assert got["censored_mass"] == pytest.approx(ref["censored_mass"], abs=1e-12), label
        by_position = prognose(rows, 3.0, method="exponential").summary()
    plain = prognose(y[:n], 3.0, method="exponential").summary()
    assert by_position["median"] == plain["median"]
    bad = stamps.to_numpy().copy()
    bad[3] = np.datetime64("NaT")
    with pytest.raises(ValueError, match="NaT"):
        prognose(rows, 3.0, time=bad)
    with pytest.raises(TypeError, match="series must be numbers, got date-times"):
        prognose(pd.Series(stamps), 3.0)
    with pytest.raises(TypeError, match="or durations"):
        prognose(pd.Series(since), 3.0)
    # at as a date-time on a date-time series: the same as the number of days
    on_index = pd.Series(rows.to_numpy(), index=stamps, name="rms")
    later = stamps[-1] + pd.Timedelta(hours=6)
    in_days = float(t[n - 1]) / 144.0 + 0.25
    ref_at = prognose(y[:n], 3.0, time=t[:n] / 144.0, method="exponential", at=in_days)
    for at in (later, later.isoformat(), later.to_datetime64()):
        got = prognose(on_index, 3.0, method="exponential", at=at)
        assert got.t_last == pytest.approx(in_days, abs=1e-9)
        assert got.summary()["median"] == pytest.approx(ref_at.summary()["median"], rel=1e-9)
    with pytest.raises(ValueError, match="at=.* is a date-time but the series' time does not"):
        prognose(y[:n], 3.0, at=later)


def test_explicit_direction_predicts_on_its_side_of_a_series_degrading_the_other_way():
    t, y = _series()
    res = prognose(y, 0.5, time=t, direction="below")
    assert res.status == "no degradation detected yet" and res.direction == "below"


def test_threshold_and_at_as_tensor_or_numpy_scalars():
    """A 0-dim tensor or a NumPy scalar is the number it holds (the same RUL to the last bit);
    a bool, a 1-element vector or a string is refused with the argument's name."""

    t, y = _series(noise_after=0.05)
    ref = prognose(y[:480], 3.0, time=t[:480], method="exponential", at=480.0)
    for thr, at in (
        (torch.tensor(3.0, dtype=F64), torch.tensor(480)),
        (np.float32(3.0), np.int64(480)),
    ):
        got = prognose(y[:480], thr, time=t[:480], method="exponential", at=at)
        assert torch.allclose(got.rul_samples, ref.rul_samples, equal_nan=True, rtol=0, atol=0)
    for bad in (True, torch.tensor(True), torch.tensor([3.0]), "3.0", 3 + 0j):
        with pytest.raises(ValueError, match="threshold must be a finite number"):
            prognose(y[:480], bad, time=t[:480])


def test_quantised_series_with_a_constant_healthy_window():
    """Whole-unit readings: prognose runs on the rounding noise of the data's step (flagged),
    exactly as with that baseline given explicitly; the previous code refused the series."""
    t = torch.arange(400, dtype=F64)
    x = torch.where(t < 250, 20.0, 20.0 + 0.25 * torch.exp((t - 250) / 40.0)).round()
    res = prognose(x[:360], 60.0, method="exponential")
    assert res.status == "ok" and res.onset.detected
    assert any("quantisation noise of the data's step 1" in f for f in res.flags)
    b = healthy_baseline(x[:360], fraction=0.3)
    ref = prognose(x[:360], 60.0, method="exponential", baseline=b)
    assert torch.allclose(res.rul_samples, ref.rul_samples, equal_nan=True, rtol=0, atol=0)
    before = prognose(x[:300], 60.0)  # one step up only: no degradation, the flag kept
    assert before.status == "no degradation detected yet"
    assert any("quantisation" in f for f in before.flags)


def test_too_short_and_bad_arrays():
    with pytest.raises(ValueError, match="at least"):
        prognose(torch.ones(5, dtype=F64), 2.0)
    with pytest.raises(ValueError, match="at least"):
        prognose(torch.tensor([1.0] * 3 + [math.nan] * 20, dtype=F64), 2.0)
    with pytest.raises(ValueError, match="strictly increasing"):
        prognose(torch.randn(50, dtype=F64), 9.0, time=torch.zeros(50, dtype=F64))
    with pytest.raises(ValueError, match="shape"):
        prognose(torch.randn(5, 5, dtype=F64), 9.0)
    with pytest.raises(ValueError, match="inf"):
        prognose(torch.tensor([1.0] * 20 + [math.inf], dtype=F64), 9.0)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_series_gives_the_cpu_result():
    """A series on the GPU is computed on the CPU: the same RUL samples as the CPU series."""
    t, y = _series(noise_after=0.05)
    ref = prognose(y[:480], 3.0, time=t[:480])
    got = prognose(y[:480].cuda(), 3.0, time=t[:480].cuda())
    assert got.rul_samples.device.type == "cpu"
    assert torch.allclose(got.rul_samples, ref.rul_samples, equal_nan=True, rtol=0, atol=0)
    s = Series(y[:480].cuda(), t[:480].cuda())
    assert torch.equal(prognose(s, 3.0).rul_samples.isnan(), ref.rul_samples.isnan())


def test_learner_hidden_and_members_set_the_learner_ensemble(monkeypatch):
    # the learner trend is an ensemble of 4 ELMs of 10 hidden nodes unless asked otherwise
    from prognos_torch.workflow import prognosing as module

    seen = []
    real = module.fit_learner_trends

    def spy(*args, **kwargs):
        seen.append((kwargs["n_hidden"], kwargs["members"], kwargs["seed"]))
        return real(*args, **kwargs)

    monkeypatch.setattr(module, "fit_learner_trends", spy)
    t, y = _series(noise_after=0.05)
    prognose(y[:480], 3.0, time=t[:480], method="elm")
    res = prognose(y[:480], 3.0, time=t[:480], method="elm", learner_hidden=40,
                   learner_members=2, seed=3)  # fmt: skip
    assert seen == [(10, 4, 0), (40, 2, 3)]
    assert res.model == "elm" and res.rul_samples.shape == (2000,)


def test_a_glitch_in_the_healthy_window_is_flagged_and_glitch_limit_leaves_it_out():
    """One sample at 40 noise std in the healthy window inflates its std 3.5 times and hides
    the onset; glitch_limit leaves it out and gives the clean series' onset and RUL."""
    g = torch.Generator().manual_seed(0)
    t = torch.arange(480, dtype=F64)
    y = 1.0 + 0.05 * torch.randn(480, generator=g, dtype=F64)
    y[300:] += 0.02 * torch.exp((t[300:] - 300) / 60)
    clean = prognose(y, 3.0, time=t)
    assert clean.status == "ok" and not any("glitch" in f for f in clean.flags)
    y[40] = 3.0
    hidden = prognose(y, 3.0, time=t)
    assert hidden.status == "no degradation detected yet"
    (flag,) = [f for f in hidden.flags if f.startswith("glitches in the healthy window")]
    assert "1 isolated value" in flag and "t = 40" in flag and "glitch_limit=20" in flag
    left_out = prognose(y, 3.0, time=t, glitch_limit=20.0)
    assert left_out.status == "ok" and left_out.onset.index == clean.onset.index
    assert left_out.onset.baseline.glitches == (40.0,)
    assert any(f.startswith("glitches left out") for f in left_out.flags)
    assert left_out.summary()["median"] == pytest.approx(clean.summary()["median"], rel=0.02)
    # in a window of 900 values a glitch of 24 noise std widens the band 1.3 times, below
    # GLITCH_WIDENING: not flagged; one of 60 widens it 2.2 times
    flat = 1.0 + 0.05 * torch.randn(3000, generator=g, dtype=F64)
    flat[100] += 1.2
    assert not any("glitch" in f for f in prognose(flat, 3.0).flags)
    flat[100] += 1.8
    assert any(f.startswith("glitches in") for f in prognose(flat, 3.0).flags)
    with pytest.raises(ValueError, match="glitch_limit applies"):
        prognose(y, 3.0, time=t, baseline=healthy_baseline(y, t), glitch_limit=20.0)
    with pytest.raises(ValueError, match="glitch_limit must be"):
        prognose(y, 3.0, time=t, glitch_limit=-1.0)
