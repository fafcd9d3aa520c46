"""Onset detectors and the trend backtest against exact, hand-written references.

prognosis/onset.py: the moving median (even windows, NaN), the k-sigma rule (both directions,
``after``, partial windows, NaN, unequal times), the CUSUM recursion and Page's estimate, the
documented false-alarm formulas, the Hampel identifier and the healthy window's statistics.
prognosis/backtest.py: the crossing pairs, the log-time CRPS and the scores of a model, each
re-implemented from its docstring on tiny cases.
"""

from __future__ import annotations

import math
from fractions import Fraction
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from _prognosis_helpers import lower_median

from prognos_torch.prognosis import (
    Baseline,
    backtest_scores,
    crossing_pairs,
    crps_log_time,
    cusum_arl0,
    cusum_onset,
    healthy_baseline,
    isolated_outliers,
    ksigma_false_alarm_rate,
    ksigma_onset,
    moving_median,
)
from prognos_torch.prognosis.backtest import LEVELS, ORIGINS

F64 = torch.float64


def _random_case(g, n_max=20, nan=0.2):
    """A short integer series (exact arithmetic, many ties) with missing values, and index or
    unequal times."""
    T = int(torch.randint(3, n_max, (1,), generator=g))
    x = torch.randint(-3, 6, (T,), generator=g).to(F64)
    x[torch.rand(T, generator=g, dtype=F64) < nan] = math.nan
    if bool(torch.rand(1, generator=g, dtype=F64) < 0.5):
        t = None
        tl = [float(i) for i in range(T)]
    else:
        t = torch.cumsum(torch.randint(1, 4, (T,), generator=g).to(F64) * 0.25, 0) + 3.0
        tl = t.tolist()
    return x, t, tl


# --------------------------------------------------------------------------- onset
def test_moving_median_even_windows_and_empty_windows_against_a_loop():
    g = torch.Generator().manual_seed(0)
    for w in (1, 2, 3, 4, 6):
        x = torch.randint(-2, 3, (15,), generator=g).to(F64)  # ties
        x[[2, 3, 4, 5, 6, 7, 11]] = math.nan  # a window of NaN only for w <= 6
        got = moving_median(x, w).tolist()
        for i in range(15):
            v = [a for a in x[max(0, i - w + 1) : i + 1].tolist() if not math.isnan(a)]
            ref = lower_median(v) if v else math.nan
            assert got[i] == ref or (math.isnan(ref) and math.isnan(got[i])), (w, i)


def _ksigma_reference(x, t, mu, sd, k, w, c, direction, after):
    """The documented rule on the series oriented to ``direction``: the trailing lower median of
    the last ``w`` observed values (none for the first ``w - 1``), the first of ``c``
    consecutive exceedances of ``k`` sigma among observed samples later than ``after``."""
    s = 1.0 if direction == "above" else -1.0
    obs = [i for i in range(len(x)) if not math.isnan(x[i])]
    xo = [s * x[i] for i in obs]
    ex = []
    for j in range(len(obs)):
        m = lower_median(xo[j - w + 1 : j + 1]) if j >= w - 1 else None
        ex.append(m is not None and (m - s * mu) / sd > k and (after is None or t[obs[j]] > after))
    for j in range(len(obs) - c + 1):
        if all(ex[j : j + c]):
            return obs[j], obs[j + c - 1]
    return None, None


def test_ksigma_below_with_an_even_window_needs_the_documented_majority():
    """An alarm needs ``j* = floor(w/2) + 1`` of the ``w`` values beyond the limit (the module's
    false-alarm rate): for ``direction="below"`` the lower median of the oriented series. The
    lower median of the data itself was used, so below a window of 4 alarmed with 2 of 4 values
    beyond the limit (an onset at index 3 here, where none is)."""
    x = torch.tensor([0.0, 0.0, 0.0, -9.0, -9.0, 0.0, 0.0, -9.0, -9.0, 0.0, 0.0], dtype=F64)
    base = Baseline(0.0, 1.0, 0.0, 3, 0.0)
    on = ksigma_onset(x, baseline=base, k=4.0, window=4, consecutive=1, direction="below")
    assert not on.detected
    assert ksigma_onset(-x, baseline=base, k=4.0, window=4, consecutive=1).detected is False
    # three of four beyond: detected, at the fourth value of the window (its lower median)
    x[5] = -9.0
    on = ksigma_onset(x, baseline=base, k=4.0, window=4, consecutive=1, direction="below")
    assert (on.index, on.alarm_index) == (5, 5)
    assert on.statistic[5].item() == 9.0  # oriented: degradation positive


def test_ksigma_against_a_brute_force_rule():
    g = torch.Generator().manual_seed(1)
    for trial in range(300):
        x, t, tl = _random_case(g)
        w = int(torch.randint(1, 6, (1,), generator=g))
        c = int(torch.randint(1, 4, (1,), generator=g))
        k = float(torch.randint(1, 4, (1,), generator=g))
        direction = ("above", "below")[trial % 2]
        after = None if trial % 3 else tl[int(torch.randint(0, len(tl), (1,), generator=g))]
        base = Baseline(0.5, 1.0, 0.5, 3, 0.0)
        on = ksigma_onset(
            x, t, baseline=base, k=k, window=w, consecutive=c, direction=direction, after=after
        )
        ref = _ksigma_reference(x.tolist(), tl, 0.5, 1.0, k, w, c, direction, after)
        assert (on.index, on.alarm_index) == ref, (x.tolist(), w, c, k, direction, after)
        if ref[0] is not None:
            assert (on.time, on.alarm_time) == (tl[ref[0]], tl[ref[1]])


def test_ksigma_exactly_at_the_limit_is_no_exceedance():
    base = Baseline(1.0, 0.5, 1.0, 3, 0.0)
    x = torch.full((12,), 3.0, dtype=F64)  # median exactly mu + 4 sigma
    assert not ksigma_onset(x, baseline=base).detected
    x[6:] = 3.0 + 1e-12
    on = ksigma_onset(x, baseline=base, consecutive=2)  # 3 of 5 above from index 8
    assert (on.index, on.alarm_index) == (8, 9)


def _cusum_reference(x, t, mu, sd, kappa, h, direction, after):
    """``S_i = max(0, S_{i-1} + z_i - kappa)`` from the first observed sample after ``after``;
    the alarm is the first ``S_i > h``, the change point the sample after the last zero of S."""
    s = 1.0 if direction == "above" else -1.0
    obs = [i for i in range(len(x)) if not math.isnan(x[i]) and (after is None or t[i] > after)]
    S, cand, stat = 0.0, (obs[0] if obs else None), {}
    for n, i in enumerate(obs):
        S = max(0.0, S + s * (x[i] - mu) / sd - kappa)
        stat[i] = S
        if S == 0.0 and n + 1 < len(obs):
            cand = obs[n + 1]
        if S > h:
            return cand, i, stat
    return None, None, stat


def test_cusum_against_the_recursion():
    """Integer data and half-integer drifts keep the Lindley form exact: ties of S with 0 and
    with h (``S = h`` is no alarm) are decided as by the recursion."""
    g = torch.Generator().manual_seed(2)
    for trial in range(300):
        x, t, tl = _random_case(g)
        kappa = 0.5 * float(torch.randint(0, 3, (1,), generator=g))
        h = float(torch.randint(1, 6, (1,), generator=g))
        direction = ("above", "below")[trial % 2]
        after = None if trial % 3 else tl[int(torch.randint(0, len(tl), (1,), generator=g))]
        base = Baseline(0.0, 1.0, 0.0, 3, 0.0)
        on = cusum_onset(x, t, baseline=base, drift=kappa, limit=h, direction=direction,
                         after=after)  # fmt: skip
        i, a, stat = _cusum_reference(x.tolist(), tl, 0.0, 1.0, kappa, h, direction, after)
        assert (on.index, on.alarm_index) == (i, a), (x.tolist(), kappa, h, direction, after)
        for j, v in stat.items():
            assert on.statistic[j].item() == v
    # a series that reaches h exactly: no alarm; one more unit: the alarm
    base = Baseline(0.0, 1.0, 0.0, 3, 0.0)
    x = torch.tensor([0.0, 0.0, 2.0, -1.0, 3.0, 2.0, 0.0], dtype=F64)  # S = 0, 0, 2, 1, 4, 6, 6
    assert not cusum_onset(x, baseline=base, drift=0.0, limit=6.0).detected
    on = cusum_onset(x, baseline=base, drift=0.0, limit=5.0)
    assert (on.index, on.alarm_index) == (2, 5)


def test_cusum_arl0_for_a_small_drift():
    """Siegmund's ``(exp(2 kappa b) - 2 kappa b - 1) / (2 kappa^2)`` tends to ``b^2`` as the
    drift goes to 0; its direct form cancelled: 0 (and a ZeroDivisionError in cusum_onset's
    rate) for kappa = 1e-9, h = 3, and 2 % off at 1e-8."""
    b = 3.0 + 1.166
    assert cusum_arl0(0.0, 3.0) == pytest.approx(b * b, rel=1e-15)
    for kappa in (1e-12, 1e-9, 1e-8, 1e-6, 1e-3, 0.05):
        a = 2 * kappa * b
        series = b * b * sum(2 * a**n / math.factorial(n + 2) for n in range(12))
        assert cusum_arl0(kappa, 3.0) == pytest.approx(series, rel=1e-14)
    # on either side of the switch to the direct form, and the default unchanged
    for kappa in (0.49 / (2 * b), 0.51 / (2 * b), 0.3):
        a = 2 * kappa * b
        ref = b * b * sum(2 * a**n / math.factorial(n + 2) for n in range(40))
        assert cusum_arl0(kappa, 3.0) == pytest.approx(ref, rel=1e-14)
    on = cusum_onset(torch.tensor([0.0, 1.0] * 5 + [5.0], dtype=F64), drift=1e-9, limit=3.0)
    assert on.false_alarm_rate == pytest.approx(1.0 / (b * b), rel=1e-8)  # (1 + a / 3) b^2


def test_ksigma_false_alarm_rate_even_window_closed_form():
    p = 0.5 * math.erfc(2.0 / math.sqrt(2.0))
    indep, dep = ksigma_false_alarm_rate(2.0, 4)  # j* = 3
    assert indep == pytest.approx(4 * p**3 * (1 - p) + p**4, rel=1e-14)
    assert dep == pytest.approx(4 * p / 3, rel=1e-14)
    indep, dep = ksigma_false_alarm_rate(0.5, 1)  # a median of one value: p itself
    assert indep == pytest.approx(0.5 * math.erfc(0.5 / math.sqrt(2.0)), rel=1e-14)
    assert dep == indep


def test_isolated_outliers_against_the_hampel_definition():
    g = torch.Generator().manual_seed(3)
    for _ in range(200):
        T = int(torch.randint(1, 12, (1,), generator=g))
        x = torch.randint(-4, 5, (T,), generator=g).to(F64)
        x[torch.rand(T, generator=g, dtype=F64) < 0.2] = math.nan
        scale, limit = 0.5 + float(torch.rand(1, generator=g, dtype=F64)), 1.0 + int(T % 3)
        got = isolated_outliers(x, scale, limit).tolist()
        xl = x.tolist()
        for i in range(T):
            v = [a for a in xl[max(0, i - 2) : i + 3] if not math.isnan(a)]
            ref = not math.isnan(xl[i]) and abs(xl[i] - lower_median(v)) > limit * scale
            assert got[i] == ref, (xl, i)


def test_healthy_baseline_window_statistics_with_unequal_times_and_a_glitch():
    g = torch.Generator().manual_seed(4)
    t = torch.cumsum(0.5 + torch.rand(40, generator=g, dtype=F64), 0)
    x = torch.randn(40, generator=g, dtype=F64)
    x[3] += 100.0  # a glitch
    x[[0, 7]] = math.nan  # a missing first sample: the span starts at t[1]
    b = healthy_baseline(x, t, fraction=0.3, glitch_limit=20.0)
    tn, xn = t.numpy(), x.numpy()
    inside = ~np.isnan(xn) & (tn <= tn[1] + 0.3 * (tn[-1] - tn[1]))
    xb = xn[inside]
    d = np.diff(xb)
    noise = 1.4826 * np.median(np.abs(d - np.median(d))) / math.sqrt(2.0)
    kept = xn[inside & (np.arange(40) != 3)]  # all but the glitch
    assert b.glitches == (t[3].item(),) and b.n == kept.size == inside.sum() - 1
    assert b.mean == pytest.approx(kept.mean(), rel=1e-13)
    assert b.std == pytest.approx(kept.std(ddof=1), rel=1e-13)
    assert b.median == np.sort(kept)[(kept.size - 1) // 2]
    assert b.noise == pytest.approx(noise, rel=1e-13)
    assert b.t_end == tn[inside][-1]
    # index time: the first 30 % of the index span, ends included (3 of 10, 4 of 11)
    assert healthy_baseline(torch.arange(10, dtype=F64) ** 2).n == 3
    assert healthy_baseline(torch.arange(11, dtype=F64) ** 2).n == 4


def test_a_constant_window_of_tenths_is_quantised_data():
    """A constant window of 0.1 has a computed mean of 0.1 - 1.4e-17, so its std came out
    1.5e-17 rather than 0: a 'spread' of round-off, a band of 6e-17, and the first moving
    median of 0.2 an onset (index 9, alarm 13 here). A constant window has no spread: the
    tenths are quantised data, std 0.1 / sqrt(12) (as the window of 2.0 in tests/test_onset.py,
    whose std is exactly 0)."""
    x = torch.tensor(
        [0.1] * 6 + [0.2, 0.1, 0.2, 0.3, 0.2, 0.3, 0.4, 0.5, 0.6] + [0.7] * 5, dtype=F64
    )
    b = healthy_baseline(x)
    assert b.resolution == pytest.approx(0.1, rel=1e-12)
    assert b.std == b.noise == pytest.approx(0.1 / math.sqrt(12.0), rel=1e-12)
    on = ksigma_onset(x)
    # limit 0.1 + 4 * 0.0289 = 0.215: the median first above it at index 12 (the median 0.3 of
    # 0.2, 0.3, 0.2, 0.3, 0.4), five such in a row from there
    assert (on.index, on.alarm_index) == (12, 16)


# --------------------------------------------------------------------------- backtest
def _pairs_reference(t, y, sigma0):
    """The docstring in exact rational arithmetic: levels ``m_0 + f (max m - m_0)``, the first
    moving median at or above each, origins the last sample at or before ``t_0 + g (t_c - t_0)``
    with at least 5 values up to it and the crossing after it."""
    n = len(y)
    m = [lower_median(y[max(0, i - 4) : i + 1]) for i in range(n)]
    out = []
    if max(m) - m[0] > sigma0:
        for f in LEVELS:
            c = m[0] + Fraction(str(f)) * (max(m) - m[0])
            k = min(j for j in range(n) if m[j] >= c)
            for g in ORIGINS:
                o = t[0] + Fraction(str(g)) * (t[k] - t[0])
                i = max(j for j in range(n) if t[j] <= o)
                if 4 <= i < k:
                    out.append((c, i, t[k]))
    return out


def test_crossing_pairs_against_the_documented_procedure():
    g = torch.Generator().manual_seed(5)
    for trial in range(300):
        n = int(torch.randint(5, 20, (1,), generator=g))
        y = torch.randint(0, 8, (n,), generator=g).to(F64)
        if trial % 2:
            y = 0.5 * y.cumsum(0)
        if trial % 3 == 0:
            t = torch.arange(n, dtype=F64)
        else:  # unequal steps, origins often exactly on a sample time
            t = 7.0 + 0.25 * torch.randint(1, 5, (n,), generator=g).to(F64).cumsum(0)
        s0 = float(torch.randint(0, 4, (1,), generator=g))
        got = crossing_pairs(t, y, s0)
        ref = _pairs_reference(
            [Fraction(v) for v in t.tolist()], [Fraction(v) for v in y.tolist()], Fraction(s0)
        )
        assert [(i, tc) for _, i, tc in got] == [(i, float(tc)) for _, i, tc in ref]
        assert [c for c, _, _ in got] == pytest.approx([float(c) for c, _, _ in ref], rel=1e-15)
    # a rise of exactly sigma0 gives no pairs; a tiny bit more does
    y = torch.tensor([0.0, 0, 0, 0, 0, 1, 2, 3, 4, 4, 4, 4], dtype=F64)
    assert crossing_pairs(torch.arange(12, dtype=F64), y, 4.0) == []
    ref = [(2.0, 5, 8.0), (3.2, 4, 10.0), (3.2, 7, 10.0)]  # origins 5.6; 4.0 and 7.0 on samples
    assert crossing_pairs(torch.arange(12, dtype=F64), y, 4.0 - 1e-9) == ref
    t = 1e6 + 0.1 * torch.arange(12, dtype=F64)  # another clock: the same origins
    assert [p[:2] for p in crossing_pairs(t, y, 4.0 - 1e-9)] == [p[:2] for p in ref]


def test_crps_log_time_against_the_pairwise_sum():
    g = torch.Generator().manual_seed(6)
    for _ in range(50):
        N = int(torch.randint(1, 9, (1,), generator=g))
        x = 5.0 * torch.rand(N, generator=g, dtype=F64)
        x[torch.rand(N, generator=g, dtype=F64) < 0.3] = math.inf  # censored: at the cap
        true, cap = 0.1 + float(torch.rand(1, generator=g, dtype=F64)), 4.0
        X = [math.log(min(v, cap)) for v in x.tolist()]
        ref = sum(abs(a - math.log(true)) for a in X) / N
        ref -= sum(abs(a - b) for a in X for b in X) / (2 * N * N)
        assert crps_log_time(x, true, cap).item() == pytest.approx(ref, rel=1e-13, abs=1e-15)


class _FakeFit:
    """First passages that are fixed fractions of the grid, recording what was asked."""

    def __init__(self):
        self.calls = []

    def _times(self, grid, n):
        j = torch.arange(n) * (grid.numel() - 1) // max(n - 1, 1)
        times = grid[j].clone()
        times[-1] = math.inf  # one censored path
        return times

    def first_passage(self, i, c, grid, n, gen):
        self.calls.append((i, c, grid))
        return SimpleNamespace(times=self._times(grid, n))

    def grid_first_passage(self, i, c, grid, n, gen):
        self.calls.append((i, c, grid))
        return torch.stack([self._times(grid, n), self._times(grid, n) * 1.5])


def test_backtest_scores_against_the_documented_procedure():
    t = torch.tensor([0.0, 0.5, 1.5, 2.0, 3.0, 3.5, 5.0, 6.0, 7.5, 8.0], dtype=F64)
    pairs = [(2.0, 4, 7.5), (3.0, 5, 8.0)]
    fit = _FakeFit()
    got = backtest_scores(fit, pairs, t, torch.Generator(), n_paths=7)
    every = backtest_scores(fit, pairs, t, torch.Generator(), n_paths=7, every_noise=True)
    assert got.shape == (2,) and every.shape == (2, 2)
    for p, (c, i, t_c) in enumerate(pairs):
        true = t_c - t[i].item()
        # the grid: steps of true / 20 up to true, then 5 % geometric steps, up to 10 true
        h = [true / 20 * j for j in range(1, 21)]
        while h[-1] < 10 * true:
            h.append(min(h[-1] * 1.05, 10 * true))
        i_got, c_got, grid = fit.calls[p]
        assert (i_got, c_got) == (i, c)
        np.testing.assert_allclose(grid.numpy(), t[i].item() + np.array(h), rtol=1e-12)
        for row, factor in ((got, 1.0), (every[0], 1.0), (every[1], 1.5)):
            times = fit._times(grid, 7) * factor
            d = [min(v - t[i].item(), 10 * true) for v in times.tolist()]
            X = [math.log(v) for v in d]
            ref = sum(abs(a - math.log(true)) for a in X) / 7
            ref -= sum(abs(a - b) for a in X for b in X) / (2 * 49)
            assert row[p].item() == pytest.approx(ref, rel=1e-12)
