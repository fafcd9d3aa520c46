"""Fleet audit: table cells (booleans among numbers, missing times), FleetResult.row, the batched
onset rule against the per-series rule, the trend's settings, pad_batch, prognose_rul's
arguments, synthetic_fleet's settings and calibrate_fleet's checks before the replay."""

from __future__ import annotations

import math

import numpy as np
import pytest
import scipy.stats  # noqa: F401  (the trend's F test imports it lazily: here, at collection)
import torch

from prognos_torch.fleet import (
    RUL_COLUMNS,
    calibrate_fleet,
    exponential_trend_rul,
    fleet_rul,
    ksigma_onset_batch,
    pad_batch,
    prognose_rul,
    read_fleet_table,
    synthetic_fleet,
)
from prognos_torch.prognosis.onset import ksigma_onset


@pytest.fixture(scope="module")
def small():
    sf = synthetic_fleet(4, 120, seed=2, healthy_fraction=0.0)
    tab = read_fleet_table(sf.table)
    return sf, pad_batch(tab.assets, tab.times, tab.values, 0)


# --------------------------------------------------------------------------- tables
def test_booleans_among_numbers_are_refused_as_a_boolean_column_is():
    """An object column holding True among numbers (a pandas object column) was read as 1.0
    by NumPy's fast path, while a column of booleans is refused."""
    t = [0.0, 1.0, 2.0]
    for cell in (True, np.True_):
        vals = np.array([1.0, cell, 2.0], dtype=object)
        with pytest.raises(ValueError, match=r"asset 'a', row 2: value 'True' in column 'value' is "
                           "not a number"):  # fmt: skip
            read_fleet_table({"asset": ["a"] * 3, "t": t, "value": vals})
        tab = read_fleet_table({"asset": ["a"] * 3 + ["b"], "t": t + [0.0],
                                "value": np.array([1.0, cell, 2.0, 3.0], dtype=object)},
                               on_error="flag")  # fmt: skip
        assert list(tab.errors) == ["a"] and tab.values[1].tolist() == [3.0]
    times = np.array([0.0, True, 2.0], dtype=object)
    with pytest.raises(ValueError, match=r"row 2: time True is not a number, while .*row 1 holds"):
        read_fleet_table({"asset": ["a"] * 3, "t": times, "value": [1.0, 2.0, 3.0]})
    # numbers of mixed types stay numbers
    mixed = np.array([1, 2.5, "3", None], dtype=object)
    tab = read_fleet_table({"asset": ["a"] * 4, "t": [0, 1, 2, 3], "value": mixed})
    np.testing.assert_array_equal(tab.values[0], [1.0, 2.5, 3.0, np.nan])


def test_a_missing_time_in_a_column_of_numbers_names_its_own_row(tmp_path):
    """An empty, NaN or infinite time cell among numbers was reported at the first (valid)
    row, 'time '0' is neither a number nor an ISO 8601 date-time'; text cells printed as
    np.str_('x')."""
    for cell in ("", "nan", "inf", "NA"):
        p = tmp_path / "f.csv"
        p.write_text(f"asset,t,value\nA,0,1\nA,{cell},2\nA,2,3\n")
        with pytest.raises(ValueError) as err:
            read_fleet_table(p)
        assert (
            str(err.value) == f"{p}: asset 'A', row 2 (line 3): the time is missing or not finite"
        )
    with pytest.raises(ValueError, match=r"row 2: the time is missing or not finite"):
        read_fleet_table({"asset": ["a"] * 3, "t": np.array([0, None, 2], dtype=object),
                          "value": [1.0, 2.0, 3.0]})  # fmt: skip
    p.write_text("asset,t,value\nA,0,1\nA,1,2\nB,x,3\n")
    with pytest.raises(ValueError) as err:
        read_fleet_table(p)
    assert str(err.value) == (
        f"{p}: asset 'B', row 3 (line 4): time 'x' is not a number, while {p}: asset 'A', "
        "row 1 (line 2) holds the number '0': a time column holds numbers or ISO 8601 "
        "date-times, not both"
    )
    p.write_text("asset,t,value\nA,2024-01-01,1\nA,,2\n")  # date-times: as before
    with pytest.raises(ValueError, match=r"row 2 \(line 3\): the time is missing$"):
        read_fleet_table(p)


def test_result_row_takes_a_number_as_the_table_reads_it():
    """The table reads 7.0 as asset "7"; FleetResult.row(7.0) looked up '7.0' and failed."""
    t = np.arange(3.0)
    res = fleet_rul({"asset": np.array([7.0] * 3 + [8.5] * 3), "t": np.r_[t, t],
                     "value": np.ones(6)}, 20.0, samples=5)  # fmt: skip
    assert res.columns["asset"] == ["7", "8.5"]
    for key in (7.0, np.float64(7.0), 7, np.int64(7), "7"):
        assert res.row(key)["asset"] == "7"
    assert res.row(8.5)["asset"] == "8.5"
    with pytest.raises(ValueError, match=r"asset '9' is not in this result \(2 assets\)"):
        res.row(9.0)


# --------------------------------------------------------------------------- onset
def test_onset_batch_raises_no_alarm_on_partial_windows_as_the_per_series_rule():
    """After the healthy window, the per-series rule (prognose's, the fleet's reference)
    leaves the first window - 1 observed samples (a partial trailing window) out; the batch
    counted them: a short asset's onset at row 6 where the per-series rule says 7."""
    g = np.random.default_rng(0)
    assets, times, values = [], [], []
    for n in (10, 13, 16, 16):  # 3, 4, 5 healthy samples (the first 30 % of the span)
        t = np.arange(float(n))
        x = np.where(t <= 0.3 * (n - 1), 1.0, 5.0 + 0.1 * t) + 0.1 * g.standard_normal(n)
        if len(assets) == 3:
            x[1] = np.nan  # a gap in the healthy window
        assets.append(f"a{n}_{len(assets)}"), times.append(t), values.append(x)
    b = pad_batch(assets, times, values)
    detected = 0
    for w in (8, 10, 12):
        for c in (1, 2):
            got = ksigma_onset_batch(b.values, b.times, b.lengths, skip_window=True, window=w,
                                     consecutive=c)  # fmt: skip
            for j in range(len(b)):
                xs, ts = torch.from_numpy(values[j]), torch.from_numpy(times[j])
                first = ksigma_onset(xs, ts, window=w, consecutive=c)
                ref = ksigma_onset(xs, ts, window=w, consecutive=c, after=first.baseline.t_end)
                assert int(got.index[j]) == (ref.index if ref.detected else -1), (w, c, j)
                detected += ref.detected
    assert detected >= 12
    t, x = times[0], values[0]
    res = fleet_rul({"asset": ["a"] * 10, "t": t, "value": x}, 20.0, samples=10, window=8,
                    consecutive=2)  # fmt: skip
    ref = ksigma_onset(torch.from_numpy(x), torch.from_numpy(t), window=8, consecutive=2,
                       after=0.3 * 9)  # fmt: skip
    assert res.row("a")["onset_time"] == ref.time == 7.0


def test_onset_rule_settings_are_refused_by_name(small):
    """window=0 raised 'Trying to create tensor with negative dimension'; consecutive=0 put
    the onset at the first row; k=nan, baseline=0 or 2 gave every asset NaN silently; a
    misspelt direction was read as 'below' by ksigma_onset_batch."""
    _, b = small
    bad = [(dict(window=0), "window must be an int >= 1, got 0"),
           (dict(window=2.5), "window must be an int >= 1, got 2.5"),
           (dict(consecutive=0), "consecutive must be an int >= 1, got 0"),
           (dict(k=math.nan), "k must be a finite number > 0, got nan"),
           (dict(k=0.0), "k must be a finite number > 0, got 0.0"),
           (dict(baseline=0.0), r"baseline fraction must be a number in \(0, 1\], got 0.0"),
           (dict(baseline=2.0), r"baseline fraction must be a number in \(0, 1\], got 2.0"),
           (dict(direction="Above"), "direction must be 'above' or 'below', got 'Above'")]  # fmt: skip
    for kw, msg in bad:
        with pytest.raises(ValueError, match=msg):
            ksigma_onset_batch(b.values, b.times, b.lengths, **kw)
        with pytest.raises(ValueError, match=msg):
            exponential_trend_rul(b, 20.0, samples=5, **kw)
    # NumPy scalars are the Python numbers
    ref = exponential_trend_rul(b, 20.0, phi=0.0, samples=20, window=5, k=4.0, baseline=0.3)
    got = exponential_trend_rul(b, 20.0, phi=0.0, samples=20, window=np.int64(5),
                                k=np.float32(4.0), baseline=np.float64(0.3))  # fmt: skip
    for c in RUL_COLUMNS:
        np.testing.assert_array_equal(ref[c], got[c])


def test_trend_settings_are_refused_by_name(small):
    """prior_std=1.0 raised "'float' object is not subscriptable", a third prior_std entry
    was ignored, a negative drift_std was taken, drift_std of 3 entries failed in the
    engine; extrapolation_limit=nan switched the guard off; threshold='x' said "could not
    convert string to float"; phi=True was phi = 1; a NaN threshold with phi='auto' was
    reported as "got nan, 'baseline'"."""
    _, b = small
    bad = [(dict(prior_std=1.0), r"prior_std must be a pair of finite numbers > 0"),
           (dict(prior_std=(-1.0, None)), r"prior_std must be a pair .*got \(-1.0, None\)"),
           (dict(prior_std=(1.0, 0.0)), r"prior_std must be a pair"),
           (dict(prior_std=(1.0, None, 2.0)), r"prior_std must be a pair"),
           (dict(drift_std=(-0.01, 0.0)), r"drift_std must be a pair of finite numbers >= 0"),
           (dict(drift_std=0.0), r"drift_std must be a pair"),
           (dict(drift_std=(0.0, 0.0, 0.0)), r"drift_std must be a pair"),
           (dict(extrapolation_limit=math.nan), r"extrapolation_limit must be a number > 0"),
           (dict(extrapolation_limit=0.0), r"extrapolation_limit must be a number > 0"),
           (dict(phi=True), r"phi must be a finite number, 'baseline' or 'auto', got True"),
           (dict(phi=math.inf), r"phi must be a finite number, 'baseline' or 'auto', got inf")]  # fmt: skip
    for kw, msg in bad:
        with pytest.raises(ValueError, match=msg):
            exponential_trend_rul(b, 20.0, samples=5, **kw)
    for thr in ("x", math.nan, True):
        with pytest.raises(ValueError, match=r"^threshold must be a finite number, got"):
            exponential_trend_rul(b, thr, samples=5)
    # NumPy scalars and a drift of zeros are the Python numbers and the default
    ref = exponential_trend_rul(b, 20.0, phi=0.0, samples=20)
    got = exponential_trend_rul(b, np.float32(20.0), phi=np.float64(0.0), samples=20,
                                prior_std=(np.float64(1.0), None), drift_std=[0, 0],
                                extrapolation_limit=np.int64(10))  # fmt: skip
    for c in RUL_COLUMNS:
        np.testing.assert_array_equal(ref[c], got[c])
    assert ref["flags"] == got["flags"]


# --------------------------------------------------------------------------- pad_batch
def test_pad_batch_refuses_times_out_of_order_and_a_seed_that_is_not_an_int():
    """Unsorted or NaN times went to the trend (a window and a clock out of order); a 2-D
    value array raised NumPy's broadcast error; seed 1.5 was seed 1."""
    t, v = np.arange(5.0), np.ones(5)
    with pytest.raises(ValueError, match=r"asset 'b': times must be finite and strictly "
                       r"increasing, got \[0.0, 2.0, 1.0\]"):  # fmt: skip
        pad_batch(["a", "b"], [t, np.array([0.0, 2.0, 1.0])], [v, np.ones(3)])
    for bad_t in (np.array([0.0, np.nan, 2.0]), np.array([0.0, 1.0, 1.0])):
        with pytest.raises(ValueError, match="asset 'a': times must be finite and strictly"):
            pad_batch(["a"], [bad_t], [np.ones(3)])
    with pytest.raises(ValueError, match=r"asset 'a': times and values must be 1-D, got shapes "
                       r"\(5,\) and \(5, 1\)"):  # fmt: skip
        pad_batch(["a"], [t], [v[:, None]])
    with pytest.raises(TypeError, match="seed must be an int, got 1.5"):
        pad_batch(["a"], [t], [v], seed=1.5)
    assert pad_batch(["a"], [t], [v], seed=np.int64(3)).seeds == pad_batch(["a"], [t], [v], 3).seeds
    b = pad_batch(["a", "b"], [t, t[:2]], [v, np.array([np.nan, 1.0])])  # NaN values: missing
    assert b.lengths.tolist() == [5, 2] and torch.isnan(b.values[1, [0, 2, 3, 4]]).all()


# --------------------------------------------------------------------------- per asset
def test_prognose_rul_refuses_a_bad_threshold_and_horizon_as_arguments():
    """A NaN threshold called prognose on every asset and came back as each asset's
    prognose_error; horizon=-1 was taken (p_fail 1 for a reached threshold)."""
    t = np.arange(30.0)
    b = pad_batch(["a"], [t], [np.linspace(1.0, 30.0, 30)])
    with pytest.raises(ValueError, match="threshold must be a finite number, got nan"):
        prognose_rul(b, math.nan)
    with pytest.raises(ValueError, match="horizon must be a positive finite number or None, "
                       "got -1.0"):  # fmt: skip
        prognose_rul(b, 5.0, horizon=-1.0)
    out = prognose_rul(b, np.float64(20.0), horizon=np.float64(3.0))  # reached: RUL 0
    assert out["flags"] == ["threshold_reached"] and out["p_fail_within_horizon"][0] == 1.0


# --------------------------------------------------------------------------- synthetic
def test_synthetic_fleet_refuses_settings_that_break_its_truth():
    """ragged=0.05 with 10 steps gave one-sample lives (failure time 0, beta inf); a negative
    threshold NaN values; healthy_fraction 2, negative noise, an onset past the life and a
    life fraction of 0 were taken; n_assets=4.5 raised NumPy's 'expected a sequence of
    integers'."""
    bad = [(dict(n_assets=4.5), "need ints n_assets >= 1 and n_steps >= 10, got 4.5, 20"),
           (dict(n_assets="4"), "need ints n_assets >= 1"),
           (dict(ragged=0.05, n_steps=10), r"ragged must be a number in \(0, 1\] with "
            r"ceil\(ragged \* n_steps\) >= 10 .*got 0.05 with n_steps=10"),
           (dict(ragged=0.0), r"ragged must be"), (dict(ragged=1.5), r"ragged must be"),
           (dict(threshold=-1.0), "threshold must be a finite number > 0, got -1.0"),
           (dict(healthy_fraction=2), r"healthy_fraction must be a number in \[0, 1\], got 2"),
           (dict(noise=(-1.0, -0.5)), r"noise must be a pair \(lo, hi\) with 0 <= lo <= hi"),
           (dict(noise=(0.2, 0.1)), r"noise must be a pair"),
           (dict(onset=(1.0, 1.0)), r"onset must be a pair \(lo, hi\) with 0 <= lo < 1"),
           (dict(onset=(0.5, 1.5)), r"onset must be a pair"), (dict(onset=0.5), r"onset must"),
           (dict(life_fraction=(0.0, 1.0)), r"life_fraction must be a pair \(lo, hi\) with 0 <")]  # fmt: skip
    for kw, msg in bad:
        kw = {"n_assets": 4, "n_steps": 20, **kw}
        with pytest.raises(ValueError, match=msg):
            synthetic_fleet(**kw)
    # accepted: NumPy counts, a fleet observed past failure, an onset up to the last sample
    a = synthetic_fleet(np.int64(4), np.int64(20), seed=1, life_fraction=(1.1, 1.3))
    b = synthetic_fleet(4, 20, seed=1, life_fraction=(1.1, 1.3))
    np.testing.assert_array_equal(a.table["value"], b.table["value"])
    assert (a.true_rul[np.isfinite(a.true_rul)] < 0).all()
    c = synthetic_fleet(6, 20, seed=1, onset=(0.5, 1.0), ragged=0.5, healthy_fraction=0.0)
    assert np.isfinite(c.failure).all() and np.isfinite(c.table["value"]).all()


# --------------------------------------------------------------------------- calibration
def test_calibrate_fleet_checks_coverage_bins_and_fractions_before_the_replay(monkeypatch):
    """A fraction of 1.5 replayed rows past the end of life, a repeated fraction counted
    its points twice, no fraction said "(first, '': )"; coverage and bins were refused
    only after the whole replay."""
    import prognos_torch.fleet.calibrate as cal_mod

    def no_replay(*a, **k):
        raise AssertionError("the replay ran before the arguments were checked")

    monkeypatch.setattr(cal_mod, "fleet_rul", no_replay)
    f = synthetic_fleet(2, 150, seed=4, life_fraction=(1.1, 1.3), healthy_fraction=0.0)
    frac = r"fractions must be distinct numbers in \(0, 1\) of \[onset, end of life\], got "
    bad = [(dict(fractions=(0.5, 1.5)), frac + r"\(0.5, 1.5\)"),
           (dict(fractions=(0.5, 0.5)), frac + r"\(0.5, 0.5\)"),
           (dict(fractions=()), frac + r"\(\)"), (dict(fractions=0.5), frac + "0.5"),
           (dict(coverage=1.5), r"coverage must lie in \(0, 1\), got 1.5"),
           (dict(bins=0), "bins must be an int >= 1, got 0"),
           (dict(bins="Auto"), "bins must be an int >= 1, got 'Auto'")]  # fmt: skip
    for kw, msg in bad:
        with pytest.raises(ValueError, match=msg):
            calibrate_fleet(f.table, 20.0, samples=10, **kw)
    with pytest.raises(AssertionError, match="the replay ran"):  # valid: goes on to replay
        calibrate_fleet(f.table, 20.0, samples=10, fractions=(np.float64(0.5),),
                        bins=np.int64(1), coverage=np.float32(0.9))  # fmt: skip
