"""Degradation onset: k-sigma moving-median rule and one-sided CUSUM (prognosis/onset.py)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from prognos_torch.prognosis import (
    Baseline,
    cusum_arl0,
    cusum_onset,
    detect_onset,
    healthy_baseline,
    isolated_outliers,
    ksigma_false_alarm_rate,
    ksigma_onset,
    moving_median,
)

F64 = torch.float64


def _gen(seed):
    return torch.Generator().manual_seed(seed)


def test_moving_median_matches_numpy_with_missing_values():
    g = _gen(0)
    x = torch.randn(60, generator=g, dtype=F64)
    x[[3, 17, 18, 40]] = math.nan
    got = moving_median(x, 5).numpy()
    xs = x.numpy()
    for i in range(60):
        w = xs[max(0, i - 4) : i + 1]
        w = np.sort(w[~np.isnan(w)])
        ref = w[(len(w) - 1) // 2]  # lower median for even counts
        assert got[i] == ref


def test_documented_rates():
    indep, dep = ksigma_false_alarm_rate(4.0, 5)
    p = 0.5 * math.erfc(4 / math.sqrt(2))
    assert indep == pytest.approx(10 * p**3, rel=1e-3)
    assert dep == pytest.approx(5 * p / 3, rel=1e-12)
    # Siegmund (kappa = 0.5, h = 5): the textbook ARL_0 of about 930
    assert cusum_arl0(0.5, 5.0) == pytest.approx(930, rel=0.01)
    assert cusum_arl0(0.5, 12.0) == pytest.approx(1.04e6, rel=0.01)


@pytest.mark.parametrize("seed", range(5))
def test_ksigma_finds_a_step_within_the_window(seed):
    g = _gen(seed)
    tau = 700
    x = torch.randn(1000, generator=g, dtype=F64)
    x[tau:] += 6.0  # a 6-sigma step
    on = ksigma_onset(x)
    # the moving median (w = 5) exceeds 4 sigma once 3 post-change samples are in its window
    assert on.detected and tau <= on.index <= tau + 4
    assert on.alarm_index == on.index + 4
    assert on.time == float(on.index)


@pytest.mark.parametrize("seed", range(5))
def test_ksigma_finds_a_ramp_within_the_stated_tolerance(seed):
    g = _gen(seed)
    tau, slope = 600, 0.05  # sigma per sample
    t = torch.arange(1000, dtype=F64) * 0.5  # time in half units, to check the time axis
    x = 2.0 + 0.1 * torch.randn(1000, generator=g, dtype=F64)
    x[tau:] += 0.1 * slope * torch.arange(400, dtype=F64)
    on = ksigma_onset(x, t)
    # the level reaches mu + 4 sigma at tau + 4 / slope = tau + 80; noise moves the median
    # crossing by a few samples either way (tolerance +- 25 samples)
    assert on.detected and abs(on.index - (tau + 80)) <= 25
    assert on.time == pytest.approx(0.5 * on.index)
    b = on.baseline
    assert b.mean == pytest.approx(2.0, abs=0.02) and b.std == pytest.approx(0.1, rel=0.15)


def test_ksigma_direction_below_and_missing_values():
    g = _gen(1)
    x = torch.randn(800, generator=g, dtype=F64)
    x[500:] -= 8.0
    on = ksigma_onset(x, direction="below")
    assert on.detected and 500 <= on.index <= 504
    assert not ksigma_onset(x, direction="above").detected
    # NaN samples are skipped: same onset as the series without them, indices mapped back
    xm = x.clone()
    xm[[100, 501, 502]] = math.nan
    on_m = ksigma_onset(xm, direction="below")
    keep = ~torch.isnan(xm)
    on_d = ksigma_onset(x[keep], torch.nonzero(keep).flatten().to(F64), direction="below")
    assert on_m.index == int(on_d.time)
    assert math.isnan(float(on_m.statistic[501]))


@pytest.mark.parametrize("seed", range(5))
def test_cusum_change_point_estimate(seed):
    g = _gen(seed)
    tau = 2400
    x = torch.randn(3000, generator=g, dtype=F64)
    x[tau:] += 2.0
    on = cusum_onset(x)  # baseline: 900 samples (the CUSUM is sensitive to a biased mean)
    # a 2-sigma shift: S grows by 1.5 per sample, alarm about 8 samples after tau; Page's
    # estimate of the change point lies within a few samples of tau
    assert on.detected and tau < on.alarm_index <= tau + 20
    assert abs(on.index - tau) <= 5
    assert float(on.statistic[on.alarm_index]) > on.limit


def test_no_false_alarm_over_stationary_samples_ksigma():
    # 100 stationary Gaussian series of 10,000 samples, baseline estimated from the first 30 %:
    # documented probability of a false alarm per series < 3.2e-9 -> none expected
    g = _gen(7)
    for _ in range(100):
        x = 0.3 + 0.02 * torch.randn(10_000, generator=g, dtype=F64)
        assert not ksigma_onset(x).detected


def test_ksigma_dependence_free_bound_holds_for_ar1():
    # AR(1), rho = 0.95, marginally N(0, 1): samples are strongly dependent; the per-sample
    # frequency of a moving median above 4 sigma stays below the dependence-free bound w p / j*
    # (5.3e-5); the independent-sample bound (3.2e-13) does not apply here
    g = _gen(3)
    rho, T, R = 0.95, 20_000, 50
    e = torch.randn(R, T, generator=g, dtype=F64) * math.sqrt(1 - rho**2)
    x = torch.empty(R, T, dtype=F64)
    x[:, 0] = torch.randn(R, generator=g, dtype=F64)
    for i in range(1, T):
        x[:, i] = rho * x[:, i - 1] + e[:, i]
    base = Baseline(0.0, 1.0, 0.0, 1000, 0.0)
    exceed = 0
    for r in range(R):
        on = ksigma_onset(x[r], baseline=base, consecutive=1)
        exceed += int((on.statistic > 4.0).sum())
    _, bound = ksigma_false_alarm_rate(4.0, 5)
    freq = exceed / (R * T)
    assert freq <= bound  # measured about 1e-5 in this set-up


def test_cusum_false_alarm_rate_matches_siegmund():
    g = _gen(11)
    base = Baseline(0.0, 1.0, 0.0, 1000, 0.0)
    # documented defaults (h = 12): P(alarm within 10,000 samples) = 1 - exp(-1e4 / ARL_0)
    R = 400
    alarms = sum(
        cusum_onset(torch.randn(10_000, generator=g, dtype=F64), baseline=base).detected
        for _ in range(R)
    )
    p = 1.0 - math.exp(-1e4 / cusum_arl0(0.5, 12.0))
    assert alarms <= R * p + 4 * math.sqrt(R * p * (1 - p))  # expected 3.8
    # the approximation itself, where alarms are frequent enough to measure (h = 4: ARL_0 = 336)
    runs = []
    for _ in range(300):
        on = cusum_onset(torch.randn(4000, generator=g, dtype=F64), baseline=base, limit=4.0)
        runs.append(on.alarm_index + 1 if on.detected else 4000)
    arl = float(np.mean(runs))
    assert arl == pytest.approx(cusum_arl0(0.5, 4.0), rel=0.15)


def test_onset_after_the_healthy_window_skips_a_run_in():
    g = _gen(4)
    x = 0.1 * torch.randn(1000, generator=g, dtype=F64)
    x += 3.0 * torch.exp(-torch.arange(1000, dtype=F64) / 5.0)  # run-in in the first ~20 samples
    x[700:] += 1.0  # a 10-sigma step
    b = healthy_baseline(x[100:], torch.arange(100, 1000, dtype=F64))  # a clean window
    b = Baseline(b.mean, b.std, b.median, b.n, 299.0, b.noise)  # taken as [0, 299]
    assert ksigma_onset(x, baseline=b).index < 20  # the run-in counts as onset ...
    on = ksigma_onset(x, baseline=b, after=b.t_end)  # ... unless the window is taken as healthy
    assert on.detected and 700 <= on.index <= 704
    assert not ksigma_onset(x[:600], baseline=b, after=b.t_end).detected
    cu = cusum_onset(x, baseline=b, after=b.t_end)
    assert cu.detected and 690 <= cu.index <= 705
    assert ksigma_onset(x, baseline=b, after=None).index == ksigma_onset(x, baseline=b).index
    with pytest.raises(ValueError, match="after"):
        ksigma_onset(x, after="end")


def test_quantised_data_with_a_constant_window():
    """A sensor reporting whole units (or tenths): the constant healthy window's spread is the
    rounding noise q / sqrt(12), so a sustained level two steps up is an onset and one step up
    is not (4 sigma = 1.15 q). A constant window with off-grid values later (a stuck sensor that
    recovers) or a constant series is still an error."""
    t = torch.arange(400, dtype=F64)
    level = torch.where(
        t < 250, torch.full_like(t, 20.0), 20.0 + 0.25 * torch.exp((t - 250) / 40.0)
    )
    x = level.round()
    for scale in (1.0, 0.1):
        b = healthy_baseline(scale * x[:330], fraction=0.3)
        assert b.resolution == pytest.approx(scale, rel=1e-12)
        assert b.std == b.noise == pytest.approx(scale / math.sqrt(12.0), rel=1e-12)
        assert (b.mean, b.median) == (pytest.approx(20.0 * scale), pytest.approx(20.0 * scale))
        on = ksigma_onset(scale * x[:330], baseline=b)
        # the trailing median of 5 steps up 2 samples after the data (3 of 5 at 22)
        first_two_up = int(torch.nonzero(x >= 22.0)[0])
        assert on.detected and on.index == first_two_up + 2
    one_up = torch.where(t < 250, 20.0, 21.0)
    assert not ksigma_onset(one_up, baseline=healthy_baseline(one_up, fraction=0.3)).detected
    stuck = torch.where(t < 250, 20.0, 20.0 + 0.013 * (t - 250) ** 1.5)
    with pytest.raises(ValueError, match="not quantised on a common step"):
        healthy_baseline(stuck, fraction=0.3)
    # whole units rising by 2 and 3: the step is their common step 1, not the smallest gap 2
    # (which left 45 off the grid and refused the series as a stuck sensor)
    rise = torch.cat([torch.full((100,), 40.0, dtype=F64),
                      (40.0 + 2.5 * torch.arange(1, 21, dtype=F64)).round()])  # fmt: skip
    assert healthy_baseline(rise, fraction=0.3).resolution == 1.0
    assert healthy_baseline(0.1 * rise, fraction=0.3).resolution == pytest.approx(0.1)


def test_baseline_window_does_not_depend_on_the_clock_origin():
    """The window's rounding allowance is relative to the span (and a few ulp of the clock), so
    epoch-like origins give the same window; it used to grow with |t| (1e-12 |t_end|: 100
    samples more at an origin of 1e14)."""
    x = 1.0 + 0.05 * torch.randn(550, generator=torch.Generator().manual_seed(0), dtype=F64)
    t = torch.arange(550, dtype=F64)
    ref = healthy_baseline(x, t, fraction=0.3)
    for t0 in (1.7e9, 1.7e12, 1e14):
        b = healthy_baseline(x, t + t0, fraction=0.3)
        assert (b.n, b.mean, b.std) == (ref.n, ref.mean, ref.std)


def test_bad_input():
    x = torch.randn(100, dtype=F64)
    with pytest.raises(ValueError, match="shape"):
        ksigma_onset(x.reshape(10, 10))
    with pytest.raises(ValueError, match="strictly increasing"):
        ksigma_onset(x, torch.zeros(100, dtype=F64))
    with pytest.raises(ValueError, match="the series is constant"):
        healthy_baseline(torch.ones(100, dtype=F64))
    with pytest.raises(ValueError, match="direction"):
        cusum_onset(x, direction="up")
    with pytest.raises(ValueError, match="onset method"):
        detect_onset(x, method="pelt")
    with pytest.raises(ValueError, match="inf"):
        ksigma_onset(torch.tensor([1.0, math.inf, 2.0, 3.0]))
    with pytest.raises(ValueError, match="at least 3"):
        healthy_baseline(torch.tensor([1.0, 2.0]))


def test_isolated_outliers_are_spikes_not_steps_or_ramps():
    x = torch.cat([torch.zeros(20, dtype=F64), torch.ones(20, dtype=F64)])  # a level shift
    x = x + 0.01 * torch.arange(40, dtype=F64)  # on a ramp
    assert not bool(isolated_outliers(x, 0.01, 5.0).any())
    x[7] += 1.0  # a spike of 100 noise std, and a two-sample burst
    x[30] -= 1.0
    x[31] -= 1.0
    got = isolated_outliers(x, 0.01, 20.0)
    assert torch.nonzero(got).flatten().tolist() == [7, 30, 31]
    # by hand at index 7: the median of x[5..9]
    nb = x[5:10].median()
    assert bool(isolated_outliers(x, float(x[7] - nb) / 20.01, 20.0)[7])
    assert not bool(isolated_outliers(x, float(x[7] - nb) / 19.99, 20.0)[7])
    # NaN: never an outlier, skipped as a neighbour; the ends use the neighbours they have
    x[8] = math.nan
    x[0] += 1.0
    got = isolated_outliers(x, 0.01, 20.0)
    assert bool(got[7]) and bool(got[0]) and not bool(got[8])
    with pytest.raises(ValueError, match="scale"):
        isolated_outliers(x, 0.0, 20.0)
    with pytest.raises(ValueError, match="limit"):
        isolated_outliers(x, 0.01, -1.0)
    with pytest.raises(ValueError, match=r"shape \(T,\)"):
        isolated_outliers(x.reshape(4, 10), 0.01, 20.0)


def test_no_gaussian_value_is_an_isolated_outlier_at_the_documented_limit():
    """10^5 Gaussian samples: the deviation from the window median has std 0.94 noise std
    (module docstring), so none lies beyond 8 (a rate below 1e-15 per sample) or 20."""
    x = torch.randn(100_000, generator=_gen(3), dtype=F64)
    assert int(isolated_outliers(x, 1.0, 8.0).sum()) == 0
    assert int(isolated_outliers(x, 1.0, 4.0).sum()) > 0  # the rule does look


def test_glitch_limit_leaves_a_glitch_out_of_the_healthy_statistics():
    g = _gen(4)
    t = torch.arange(300, dtype=F64)
    x = 1.0 + 0.05 * torch.randn(300, generator=g, dtype=F64)
    clean = healthy_baseline(x, t, glitch_limit=20.0)
    assert clean == healthy_baseline(x, t)  # nothing to leave out: the same statistics
    assert clean.glitches == ()
    x[40] = 3.0  # 40 noise std
    plain = healthy_baseline(x, t)
    base = healthy_baseline(x, t, glitch_limit=20.0)
    window = torch.cat([x[:40], x[41:90]])  # the first 30 % of [0, 299] without the glitch
    assert base.glitches == (40.0,) and base.n == 89 and plain.n == 90
    assert base.mean == float(window.mean()) and base.std == float(window.std())
    assert base.median == float(window.median())
    assert base.noise == plain.noise and plain.std > 3 * base.std
    with pytest.raises(ValueError, match="glitch_limit"):
        healthy_baseline(x, t, glitch_limit=0.0)


def test_ksigma_raises_no_alarm_on_the_partial_windows_at_the_start():
    # with consecutive = 1 the first sample's "median" is the sample itself: it exceeded k = 2
    # in 2.3 % of stationary series, 200 times the documented rate
    g = torch.Generator().manual_seed(0)
    base = Baseline(0.0, 1.0, 0.0, 1000, -1.0)  # (mean, std, median, n, t_end)
    hits = 0
    for _ in range(2000):
        x = torch.randn(50, generator=g, dtype=F64)
        on = ksigma_onset(x, baseline=base, k=2.0, window=5, consecutive=1)
        hits += int(on.detected and on.index < 4)
    assert hits == 0
    # a series that starts above the limit alarms once its first window is full
    x = torch.full((20,), 10.0, dtype=F64)
    assert ksigma_onset(x, baseline=base, k=2.0, window=5, consecutive=1).index == 4
