"""Onset statistics, the known-threshold protocol, split-conformal intervals and the simulation
to an event against references written here: brute-force loops on tiny series (falling
indicators, NaN gaps, windows at the series ends, NumPy scalar settings), the binomial
false-alarm rate on a simulated stationary series, the CQR rank rule per bin, and the
protocol's text implemented directly."""

from __future__ import annotations

import math
import statistics

import numpy as np
import pytest
import torch
from _prognosis_helpers import lower_median

from prognos_torch.core import StateSpaceModel
from prognos_torch.prognosis import (
    Baseline,
    cusum_arl0,
    cusum_onset,
    healthy_baseline,
    ksigma_false_alarm_rate,
    ksigma_onset,
    simulate_to_event,
)
from prognos_torch.prognosis.conformal import (
    calibrate_intervals,
    interval_scores,
    leave_one_group_out,
)
from prognos_torch.prognosis.protocol import known_threshold_protocol, rul_scores

F64 = torch.float64


# --------------------------------------------------------------------------- onset
def _baseline_ref(x, t, fraction):
    """Mean and std (ddof 1) of the observed values with ``t <= t0 + fraction (t1 - t0)``."""
    obs = [i for i in range(len(x)) if not math.isnan(x[i])]
    t0, t1 = t[obs[0]], t[obs[-1]]
    xb = [x[i] for i in obs if t[i] <= t0 + fraction * (t1 - t0) + 1e-9]
    if len(xb) < 3:  # (the detector refuses a window of fewer)
        raise statistics.StatisticsError
    return statistics.fmean(xb), statistics.stdev(xb)


def test_ksigma_with_its_own_baseline_against_brute_force_with_numpy_settings():
    """The whole rule, baseline included, on short series with NaN gaps (also at both ends),
    falling and rising, unequal times, every setting a NumPy scalar."""
    g = np.random.default_rng(7)
    for trial in range(120):
        T = int(g.integers(8, 22))
        x = g.integers(-3, 4, T).astype(float)
        x[g.random(T) < 0.2] = math.nan
        x[0] = x[1] = 0.0 if trial % 4 else math.nan  # a gap at the start
        x[2:4] = (1.0, -1.0)  # spread in the healthy window
        if trial % 5 == 0:
            x[-1] = math.nan  # and at the end
        t = np.cumsum(g.integers(1, 4, T)) * 0.5 if trial % 2 else np.arange(T, dtype=float)
        direction = ("above", "below")[trial % 3 == 0]
        s = 1.0 if direction == "above" else -1.0
        x[-5:] += s * 9.0  # a step in the degradation direction near the end
        k, w, c = np.float32(1.5), np.int64(1 + trial % 4), np.int32(1 + trial % 3)
        frac = np.float64(0.3)
        try:
            mu, sd = _baseline_ref(list(x), list(t), 0.3)
        except statistics.StatisticsError:
            continue
        if not sd > 0:
            continue
        on = ksigma_onset(torch.from_numpy(x), torch.from_numpy(t), baseline=frac, k=k,
                          window=w, consecutive=c, direction=direction)  # fmt: skip
        assert on.baseline.mean == pytest.approx(mu, rel=1e-12, abs=1e-12)
        assert on.baseline.std == pytest.approx(sd, rel=1e-12)
        obs = [i for i in range(T) if not math.isnan(x[i])]
        xo = [s * x[i] for i in obs]
        ex = [j >= w - 1 and (lower_median(xo[j - w + 1 : j + 1]) - s * mu) / sd > float(k)
              for j in range(len(obs))]  # fmt: skip
        ref = next(((obs[j], obs[j + c - 1]) for j in range(len(obs) - c + 1)
                    if all(ex[j : j + c])), (None, None))  # fmt: skip
        assert (on.index, on.alarm_index) == ref, (trial, list(x), direction)


def test_ksigma_false_alarm_rate_on_a_stationary_series():
    """With the baseline known, an alarm (``c = 1``) at a full window is exactly ``median >
    k``: ``P(Bin(w, Q(k)) >= floor(w/2) + 1)`` for independent samples. Windows that do not
    overlap are independent Bernoulli draws; 4,000 of them against the documented rate, within
    4.5 binomial standard deviations (two-sided probability 7e-6), rising and falling, odd and
    even windows."""
    gen = torch.Generator().manual_seed(123)
    base = Baseline(0.0, 1.0, 0.0, 1000, -1.0)
    k = 1.0
    for w in (5, 4):
        x = torch.randn(4000 * w, generator=gen, dtype=F64)
        rate = ksigma_false_alarm_rate(k, w)[0]
        p = 0.5 * math.erfc(k / math.sqrt(2.0))
        exact = sum(math.comb(w, j) * p**j * (1 - p) ** (w - j) for j in range(w // 2 + 1, w + 1))
        assert rate == pytest.approx(exact, rel=1e-14)
        for sign, direction in ((1.0, "above"), (-1.0, "below")):
            on = ksigma_onset(sign * x, baseline=base, k=k, window=w, consecutive=1,
                              direction=direction)  # fmt: skip
            z = on.statistic[w - 1 :: w]  # the last sample of each disjoint window
            n = z.numel()
            alarms = int((z > k).sum())
            assert abs(alarms - n * rate) <= 4.5 * math.sqrt(n * rate * (1 - rate))
            # the first alarm is the first such exceedance over every full window
            first = int(torch.nonzero(on.statistic[w - 1 :] > k).flatten()[0]) + w - 1
            assert on.index == first


def test_cusum_arl0_past_the_range_of_exp_is_infinite():
    """``exp(2 kappa b)`` overflows past 2 kappa b = 709.78: ``cusum_onset(drift=1,
    limit=400)`` raised ``OverflowError: math range error``; the ARL is beyond 1e300 samples, a
    per-sample rate of 0. Below the overflow Siegmund's form is unchanged."""
    x = torch.tensor([0.0, 1.0] * 10 + [500.0] * 3, dtype=F64)
    on = cusum_onset(x, drift=1.0, limit=400.0)
    assert on.false_alarm_rate == 0.0 and on.detected
    assert cusum_arl0(1.0, 400.0) == math.inf
    b = 350.0 + 1.166  # a = 702.3: finite
    assert cusum_arl0(1.0, 350.0) == pytest.approx((math.exp(2 * b) - 2 * b - 1) / 2, rel=1e-13)


@pytest.mark.parametrize(
    "call, match",
    [
        (lambda: ksigma_false_alarm_rate(4.0, 0), "window must be an int >= 1"),
        (lambda: ksigma_false_alarm_rate(4.0, 2.5), "window must be an int >= 1"),
        (lambda: ksigma_false_alarm_rate(-1.0, 5), "k must be > 0"),
        (lambda: cusum_arl0(-0.5, 12.0), "drift must be >= 0"),
        (lambda: cusum_arl0(math.nan, 12.0), "drift must be a finite number"),
        (lambda: cusum_arl0(0.5, 0.0), "limit must be > 0"),
    ],
)
def test_false_alarm_formulas_refuse_bad_settings(call, match):
    # (were (0, 0.0) for a window of 0, TypeError "'float' object cannot be interpreted as an
    # integer", an ARL of -587 for a negative drift, NaN for a NaN one)
    with pytest.raises(ValueError, match=match):
        call()


def test_false_alarm_formulas_take_numpy_scalars_as_python_numbers():
    got = ksigma_false_alarm_rate(np.float32(4.0), np.int64(5))
    assert got == ksigma_false_alarm_rate(4.0, 5)
    assert all(type(v) is float for v in got)  # (the bound was a numpy.float64)
    assert cusum_arl0(np.float32(0.5), np.int64(12)) == cusum_arl0(0.5, 12.0)


@pytest.mark.parametrize(
    "base, match",
    [
        (Baseline(0.0, 0.0, 0.0, 3, 0.0), r"baseline.std must be > 0, got 0.0"),
        (Baseline(0.0, -1.0, 0.0, 3, 0.0), r"baseline.std must be > 0, got -1.0"),
        (Baseline(0.0, math.nan, 0.0, 3, 0.0), r"baseline.std must be a finite number, got nan"),
        (Baseline(math.nan, 1.0, 0.0, 3, 0.0), r"baseline.mean must be a finite number"),
    ],
)
def test_a_given_baseline_without_a_spread_or_a_mean_is_refused(base, match):
    # a std of 0 made the first value above the mean an onset (index 11 here, on noise), a
    # negative std turned the direction round (an onset on a falling series, "above"), NaN
    # never alarmed
    x = torch.linspace(-1.0, 1.0, 30, dtype=F64)
    for detector in (ksigma_onset, cusum_onset):
        with pytest.raises(ValueError, match=match):
            detector(x, baseline=base)


@pytest.mark.parametrize(
    "values",
    [
        torch.tensor([True, False] * 10),
        [True, False] * 10,
        np.ones(20) * (1 + 1j),
        torch.ones(20, dtype=torch.complex64),
    ],
)
def test_bool_and_complex_values_are_refused(values):
    # (read as 0/1, or cast with only a warning that the imaginary part was discarded)
    base = Baseline(0.0, 0.1, 0.0, 3, 0.0)
    for call in (lambda: ksigma_onset(values, baseline=base),
                 lambda: cusum_onset(values, baseline=base),
                 lambda: healthy_baseline(values)):  # fmt: skip
        with pytest.raises(TypeError, match="values must hold real numbers"):
            call()


# --------------------------------------------------------------------------- protocol
def _protocol_ref(t, y, fractions):
    """The module docstring's protocol, written out: trailing 5-point lower medians, threshold
    0.9 x their highest, EoL the first reaching it, baseline the first 30 % of [t0, t_EoL],
    onset the first of 5 consecutive full-window medians above mean + 4 std (up to EoL)."""
    n = len(y)
    m = [lower_median(y[max(0, i - 4) : i + 1]) for i in range(n)]
    thr = 0.9 * max(m)
    ie = next(i for i in range(n) if m[i] >= thr)
    end = t[0] + 0.3 * (t[ie] - t[0])
    xb = [y[i] for i in range(ie + 1) if t[i] <= end + 1e-9]
    mu, sd = statistics.fmean(xb), statistics.stdev(xb)
    ex = [i >= 4 and m[i] > mu + 4 * sd for i in range(ie + 1)]
    on = next((i for i in range(ie - 3) if all(ex[i : i + 5])), None)
    times = None if on is None else [t[on] + f * (t[ie] - t[on]) for f in fractions]
    return thr, ie, mu, sd, on, times


def test_known_threshold_protocol_against_a_direct_implementation():
    g = np.random.default_rng(3)
    fractions = (0.2, 0.4, 0.6, 0.8, 0.9)
    for trial in range(40):
        n = int(g.integers(30, 60))
        t = np.cumsum(g.uniform(0.5, 1.5, n)) if trial % 2 else np.arange(n, dtype=float)
        knee = int(g.integers(n // 3, 2 * n // 3))
        y = 1.0 + 0.1 * g.standard_normal(n)
        y[knee:] += 0.05 * np.arange(n - knee) ** 2  # a rise after the knee
        if trial % 3 == 0:
            y[-3:] -= 0.5 * y[-3:].max()  # a drop after the peak (EoL before the end)
        thr, ie, mu, sd, on, times = _protocol_ref(list(t), list(y), fractions)
        pc = known_threshold_protocol(torch.from_numpy(t), torch.from_numpy(y))
        assert pc.threshold == pytest.approx(thr, rel=1e-15) and pc.i_eol == ie
        assert pc.t_eol == t[ie]
        assert pc.baseline.mean == pytest.approx(mu, rel=1e-12)
        assert pc.baseline.std == pytest.approx(sd, rel=1e-12)
        assert pc.i_onset == on, trial
        if on is not None:
            np.testing.assert_allclose(pc.times.numpy(), times, rtol=1e-14)
            np.testing.assert_allclose(pc.true_rul.numpy(), t[ie] - np.array(times), rtol=1e-12)
            assert pc.valid == (ie - on >= 10)


def test_protocol_refuses_fractions_outside_the_life_and_bad_times():
    # fractions (1.5,) gave a prediction time past end of life and a true RUL of -8; a NaN or
    # a decreasing time after end of life was kept in the case unseen
    t = torch.arange(40, dtype=F64)
    y = torch.cat(
        [0.1 * torch.sin(torch.arange(20, dtype=F64)), torch.linspace(1, 20, 20, dtype=F64)]
    )
    assert known_threshold_protocol(t, y).valid
    for fr in ((1.5,), (0.0, 0.5), (0.5, 0.5), ()):
        with pytest.raises(ValueError, match=r"fractions must be distinct numbers in \(0, 1\)"):
            known_threshold_protocol(t, y, fractions=fr)
    assert known_threshold_protocol(t, y, fractions=np.array([0.5])).times.tolist() == [30.0]
    for bad in (math.nan, 0.0):
        tb = t.clone()
        tb[-1] = bad
        with pytest.raises(ValueError, match="t must be finite and strictly increasing"):
            known_threshold_protocol(tb, y)


def _v(values):
    return torch.tensor(values, dtype=F64)


def test_rul_scores_against_their_definitions_and_unequal_shapes_refused():
    times, r = [1.0, 2.0, 3.0, 4.0], [4.0, 3.0, 2.0, 1.0]
    p = [4.5, math.nan, 2.9, 1.0]
    lo, hi = [3.0, 1.0, 2.5, math.nan], [5.0, math.inf, 3.5, 2.0]
    sc = rul_scores(_v(times), _v(r), _v(p), t_onset=0.0,
                    t_eol=5.0, lower=_v(lo), upper=_v(hi))  # fmt: skip
    pp = [math.inf if math.isnan(v) else v for v in p]
    err = [abs(a - b) for a, b in zip(pp, r)]
    assert sc["abs_error"].tolist() == err
    assert sc["ra"].tolist() == [1 - e / b for e, b in zip(err, r)]
    for a in (0.2, 0.3):
        inside = [(1 - a) * b <= v <= (1 + a) * b for v, b in zip(pp, r)]
        assert sc[f"in_cone_{a:g}"].tolist() == inside
        assert sc[f"alpha_lambda_{a:g}"] == sum(inside) / 4
    covered = [not math.isnan(a) and a <= b <= c for a, b, c in zip(lo, r, hi)]
    assert sc["covered"].tolist() == covered and sc["coverage"] == sum(covered) / 4
    # a (1,) prediction failed with a mask IndexError; (1,) bounds were broadcast
    with pytest.raises(ValueError, match=r"must have the same shape \(P,\).*pred_rul \(1,\)"):
        rul_scores(_v(times), _v(r), _v([2.0]), t_onset=0.0,
                   t_eol=5.0)  # fmt: skip
    with pytest.raises(ValueError, match=r"lower \(1,\)"):
        rul_scores(_v(times), _v(r), _v(p), t_onset=0.0,
                   t_eol=5.0, lower=_v([0.0]), upper=_v(hi))  # fmt: skip


# --------------------------------------------------------------------------- conformal
def _margin(scores, c):
    s = sorted(v for v in scores if not math.isnan(v))
    k = math.ceil((len(s) + 1) * c - 1e-9)
    return math.inf if k > len(s) else s[k - 1]


def test_binned_margins_and_coverage_against_brute_force_with_ties():
    g = np.random.default_rng(5)
    for trial in range(30):
        n, B, c = int(g.integers(20, 60)), int(g.integers(2, 4)), (0.5, 0.8, 0.9)[trial % 3]
        lo = np.round(g.uniform(1.0, 5.0, n), 1)
        hi = lo * np.round(g.uniform(1.0, 3.0, n), 1)
        tr = np.round(g.uniform(0.5, 12.0, n), 1)
        med = np.round(g.uniform(1.0, 6.0, n))  # ties among the medians
        med[g.random(n) < 0.15] = math.inf  # censored
        cal = calibrate_intervals(torch.from_numpy(lo), torch.from_numpy(hi),
                                  torch.from_numpy(tr), c, median=torch.from_numpy(med), bins=B)  # fmt: skip
        s = [
            max(math.log(a) - math.log(y), math.log(y) - math.log(b)) for a, b, y in zip(lo, hi, tr)
        ]
        z = [math.log(m) for m in med]
        edges = list(cal.edges) + [math.inf]
        assert cal.margin == _margin(s, c)
        assert len(cal.margins) == (len(edges) if cal.edges else 0)
        # each bin's margin is the rank rule on its own scores; its points covered as ranked
        for j, e in enumerate(edges if cal.edges else []):
            below = -math.inf if j == 0 else edges[j - 1]
            mine = [i for i in range(n) if below < z[i] <= e]
            assert mine, (trial, cal.edges)
            assert cal.margins[j] == _margin([s[i] for i in mine], c)
            q = cal.margins[j]
            a, b = cal.interval(lo[mine], hi[mine], med[mine])
            for i, ai, bi in zip(mine, a.tolist(), b.tolist()):
                assert ai == pytest.approx(lo[i] * math.exp(-q), rel=1e-14)
                assert bi == pytest.approx(hi[i] * math.exp(q), rel=1e-14)
                if abs(s[i] - q) > 1e-12:  # (a score at the margin is on the boundary)
                    assert (ai <= tr[i] <= bi) == (s[i] <= q)
            k = math.ceil((len(mine) + 1) * c - 1e-9)
            if k <= len(mine):
                assert sum(s[i] <= q for i in mine) >= k


def test_censored_medians_make_the_top_bin():
    """With as many censored as finite medians and two bins, the cut between them is halfway
    between a finite log median and +inf: the boundary was dropped and all points shared one
    margin. The documented top bin of censored medians now has its own."""
    n = 20
    lo, hi = torch.full((n,), 1.0, dtype=F64), torch.full((n,), 2.0, dtype=F64)
    tr = torch.linspace(0.5, 3.0, n, dtype=F64)
    med = torch.cat([torch.linspace(1.0, 2.0, 10, dtype=F64), torch.full((10,), math.inf)])
    cal = calibrate_intervals(lo, hi, tr, 0.5, median=med, bins=2)
    s = interval_scores(lo, hi, tr).tolist()
    assert cal.edges == (math.log(2.0),)
    assert cal.margins == (_margin(s[:10], 0.5), _margin(s[10:], 0.5))
    q = cal.margin_for(torch.tensor([1.5, 2.0, 2.5, math.inf, math.nan], dtype=F64))
    assert q.tolist() == [cal.margins[0]] * 2 + [cal.margins[1]] * 3


def test_groups_given_as_a_tensor_are_counted_by_value():
    # the entries of a tensor are 0-d tensors, each its own set member: 20 points of 5 assets
    # counted as 20 assets, and the few-assets warning was silent
    n = 20
    lo, hi = torch.full((n,), 1.0, dtype=F64), torch.full((n,), 2.0, dtype=F64)
    tr = torch.linspace(0.5, 3.0, n, dtype=F64)
    labels = [i % 5 for i in range(n)]
    for groups in (torch.tensor(labels), np.array(labels), labels):
        cal = calibrate_intervals(lo, hi, tr, 0.9, groups=groups)
        assert cal.assets == 5 and cal.warning() is not None
        a, b, q = leave_one_group_out(lo, hi, tr, groups, 0.5)
        for i in range(n):  # the margin of the other assets' scores
            other = [
                float(v)
                for j, v in enumerate(interval_scores(lo, hi, tr))
                if labels[j] != labels[i]
            ]
            assert q[i].item() == _margin(other, 0.5)
            assert a[i].item() == pytest.approx(math.exp(-q[i].item()), rel=1e-14)
            assert b[i].item() == pytest.approx(2.0 * math.exp(q[i].item()), rel=1e-14)
    with pytest.raises(ValueError, match="groups must be 20 labels"):
        calibrate_intervals(lo, hi, tr, 0.9, groups=torch.zeros(20, 1))


def test_interval_refuses_two_dimensional_ends():
    # (a (4, 5) interval came back flattened to (20,))
    cal = calibrate_intervals(torch.ones(9, dtype=F64), torch.full((9,), 2.0, dtype=F64),
                              torch.linspace(0.5, 3.0, 9, dtype=F64), 0.5)  # fmt: skip
    with pytest.raises(
        ValueError, match=r"lower must have shape \(n,\) or be a scalar, got \(4, 5\)"
    ):
        cal.interval(torch.ones(4, 5), torch.ones(4, 5))
    a, b = cal.interval(1.0, 2.0)
    assert a.dim() == b.dim() == 0


@pytest.mark.parametrize(
    "args, err, match",
    [
        (([True], [True], [True]), TypeError, "lower must hold real numbers"),
        (([1.0], [2.0], [1 + 1j]), TypeError, "truth must hold real numbers"),
        ((np.array([1.0]), np.array([2.0]), np.array([True])), TypeError, "truth must hold real"),
        ((["a"], [2.0], [1.0]), TypeError, "lower must be a tensor or array-like of numbers"),
    ],
)
def test_scores_refuse_bool_complex_and_text(args, err, match):
    # (True was a RUL of 1; text failed with "too many dimensions 'str'")
    with pytest.raises(err, match=match):
        interval_scores(*args)


# --------------------------------------------------------------------------- events
def _walk():
    return StateSpaceModel(f=lambda x, u, k: x + 0.25, h=lambda x, u, k: x, state_dim=1,
                           obs_dim=1, chol_Q=torch.eye(1, dtype=F64), chol_R=torch.eye(1, dtype=F64),
                           batched=True)  # fmt: skip


def test_simulate_to_event_settings_numpy_counts_and_refusals():
    x0 = torch.tensor([[0.0], [0.5], [-9.0]], dtype=F64)
    ev = lambda x: x[..., 0] >= 1.0  # noqa: E731
    got = simulate_to_event(_walk(), x0, ev, max_steps=np.int64(10), chunk=np.int64(3),
                            t0=np.float32(1.0), dt=np.float64(0.5), k0=np.int64(2))  # fmt: skip
    # j = ceil((1 - x0) / 0.25): 4, 2, censored
    assert type(got.steps_run) is int and got.steps_run == 10  # (was numpy.int64)
    assert got.time_of_event[:2].tolist() == [1.0 + 0.5 * 4, 1.0 + 0.5 * 2]
    assert math.isnan(got.time_of_event[2].item())
    # (k0 = 1.5 reached the transition as k; process_noise="no" was read as True)
    for kw, match in (({"k0": 1.5}, "k0 must be a non-negative int"),
                      ({"k0": True}, "k0 must be a non-negative int"),
                      ({"k0": -1}, "k0 must be a non-negative int")):  # fmt: skip
        with pytest.raises(ValueError, match=match):
            simulate_to_event(_walk(), x0, ev, max_steps=10, **kw)
    with pytest.raises(TypeError, match="process_noise must be a bool"):
        simulate_to_event(_walk(), x0, ev, max_steps=10, process_noise="no",
                          generator=torch.Generator())  # fmt: skip
