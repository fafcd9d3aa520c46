"""workflow.prognose as a reliability engineer calls it: its options checked with their names,
a hand-built Series checked as an array is, the horizon before onset, the flags of pooled
seeds, and the result read against brute force over its own paths."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from prognos_torch.workflow import Series, prognose
from prognos_torch.workflow import prognosing as module

F64 = torch.float64


@pytest.fixture
def no_backtest(monkeypatch):
    """No level crossed since onset: each shape's noise by maximum likelihood (quick; the
    bookkeeping read here does not depend on how the noise was chosen)."""
    monkeypatch.setattr(module, "crossing_pairs", lambda *args, **kwargs: [])


def _degrading(n=120, on=60, seed=0):
    """Healthy noise around 1 (std 0.05), then an exponential rise from ``on``."""
    g = torch.Generator().manual_seed(seed)
    t = torch.arange(n, dtype=F64)
    y = 1.0 + 0.05 * torch.randn(n, generator=g, dtype=F64)
    return t, torch.where(t >= on, y + 0.1 * torch.exp(0.04 * (t - on)), y)


def _healthy(n=30):
    g = torch.Generator().manual_seed(0)
    return 1.0 + 0.05 * torch.randn(n, generator=g, dtype=F64)


# ----------------------------------------------------------------------------- fixes
def test_a_time_format_that_is_no_strptime_text_is_named():
    """time_format=5 failed inside strptime ("strptime() argument 2 must be str, not int",
    a TypeError that named no argument); now the message of load_series."""
    stamps = np.datetime64("2024-03-01T00:00:00") + np.arange(30).astype("timedelta64[h]")
    texts = [str(s) for s in stamps]
    for bad in (5, b"%Y-%m-%dT%H:%M:%S", "Y-m-d"):
        with pytest.raises(ValueError, match=r"time_format must be strptime codes .* got"):
            prognose(_healthy(), 2.0, time=texts, time_format=bad)


def test_a_hand_built_series_of_huge_or_tiny_values_is_refused_as_the_array_is():
    """A Series of values near 1e200 read as a healthy band [-inf, inf] ("threshold 3e+200
    lies inside the healthy band"): its magnitude is now checked as an array's is."""
    t, y = _degrading()
    for scale in (1e200, 1e-160):
        with pytest.raises(ValueError) as arr:
            prognose(y * scale, 3.0 * scale, time=t)
        with pytest.raises(ValueError) as ser:
            prognose(Series(y * scale, t), 3.0 * scale)
        assert str(ser.value) == str(arr.value) and "'series'" in str(ser.value)


def test_horizon_factor_sets_the_horizon_before_onset():
    """Before onset the horizon was 2 x the observed life whatever horizon_factor said; a
    threshold no path reaches has its bound at the horizon, ``horizon_factor x`` the life (29
    steps of 1 here)."""
    h = _healthy()
    for factor, bins in ((5.0, 145), (np.float32(0.5), 15)):  # (default 2: 58)
        res = prognose(h, 50.0, horizon_factor=factor)
        assert res.status == "no degradation detected yet"
        assert res.horizon == bins and res.dt == 1.0
        assert res.summary()["bound"] == bins and res.censored_mass == pytest.approx(1.0, abs=1e-12)


def test_n_paths_sets_the_paths_before_onset():
    """Before onset 2000 paths were drawn whatever n_paths said (and n_particles read 2000):
    with 50 the bound's distribution is one of 50 equally weighted paths."""
    res = prognose(_healthy(), 1.5, n_paths=50)
    assert res.status == "no degradation detected yet" and res.n_particles == 50
    pmf = torch.cat([res.distribution.pmf, res.distribution.censored_mass.reshape(1)])
    k = pmf * 50  # whole numbers of paths
    assert torch.allclose(k, k.round(), atol=1e-9) and 0 < float(k[:-1].sum()) < 50


def test_pooled_seeds_of_the_linear_trend_are_not_flagged_back_at_the_healthy_level(no_backtest):
    """The "back at the healthy level" flag concerns the log shapes (no measurement there):
    with seed=(0, 1) the linear trend's model name became "linear (ekf, seed 0) + ...", which
    is not "linear", and the flag was raised for it."""
    g = torch.Generator().manual_seed(0)
    y = 0.33 + 0.02 * torch.randn(120, generator=g, dtype=F64)
    y[70:100] += 0.5  # a transient, then back to health: the last 5 at the healthy mean
    y[-5:] = y[:36].mean()

    def back(method):
        res = prognose(y, 1.1, method=method, seed=(0, 1), n_paths=20)
        assert res.status == "ok" and res.model.count("seed") == 2
        return any(f.startswith("back at the healthy level") for f in res.flags)

    assert back("exponential") and not back("linear")


# ----------------------------------------------------------------------------- consistency
def test_summary_reads_the_paths_brute_force_on_irregular_times_with_gaps(no_backtest):
    """Irregular times and NaN gaps: the onset indexes the series as given; the censored mass
    is the share of the still running paths that never cross within ``bound``; the quantiles
    are the ceil(q N)-th smallest crossing times; the inputs are untouched; the same seed gives
    the same answer."""
    t, y = _degrading()
    g = torch.Generator().manual_seed(1)
    t = torch.cumsum(0.1 + 2.0 * torch.rand(120, generator=g, dtype=F64), 0)
    y[30:40] = math.nan
    y[100] = math.nan
    y0, t0 = y.clone(), t.clone()
    for thr, at in ((3.0, None), (8.0, float(t[-1]) + 7.5)):  # (8: partly censored)
        res = prognose(y, thr, time=t, method="linear", n_paths=200, at=at)
        assert torch.equal(y.isnan(), y0.isnan()) and torch.equal(y.nan_to_num(), y0.nan_to_num())
        assert torch.equal(t, t0)
        ons = res.onset
        assert ons.time == float(t[ons.index]) and ons.alarm_time == float(t[ons.alarm_index])
        assert not math.isnan(float(y[ons.index]))
        x = res.rul_samples[~res.rul_samples.isnan()]
        out = ~torch.isfinite(x) | (x > res.bound)
        s = res.summary()
        assert s["censored_mass"] == pytest.approx(float(out.to(F64).mean()), abs=1e-12)
        srt = torch.where(out, math.inf, x).sort().values
        for key, q in (("q05", 0.05), ("median", 0.5), ("q95", 0.95)):
            v = float(srt[math.ceil(q * srt.numel()) - 1])
            assert s[key] == (v if math.isfinite(v) else None)
    assert 0.0 < s["censored_mass"] < 1.0
    again = prognose(y, thr, time=t, method="linear", n_paths=200, at=at)
    assert torch.equal(again.rul_samples.nan_to_num(-1.0), res.rul_samples.nan_to_num(-1.0))


def test_float32_numpy_scalars_and_lists_give_the_float64_answer(no_backtest):
    """float32 values are their float64 upcast (the same paths); NumPy scalars for the
    threshold, seed and counts, and a list of times, are the numbers they hold."""
    t, y = _degrading()
    ref = prognose(y.float().double(), 3.0, time=t, method="linear", n_paths=100, seed=2)
    for got in (
        prognose(y.float(), 3.0, time=t.float(), method="linear", n_paths=100, seed=2),
        prognose(
            y.float().numpy(),
            np.float32(3.0),
            time=t.tolist(),
            method="linear",
            n_paths=np.int64(100),
            seed=[np.int32(2)],
        ),
    ):
        assert torch.equal(got.rul_samples.nan_to_num(-1.0), ref.rul_samples.nan_to_num(-1.0))
    f64 = prognose(y, 3.0, time=t, method="linear", n_paths=100, seed=2).summary()
    assert f64["median"] == pytest.approx(ref.summary()["median"], abs=2.0 * ref.dt)
