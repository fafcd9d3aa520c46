"""Fleet trend, run and table: the batched answer of each asset against the same asset alone and
against the closed-form Bayesian regression on a ragged fleet with gaps, a falling indicator and
thresholds on either side; NumPy float32 offsets; infinite, boolean and complex cells; the
onset rule's rows; pandas' NA in tables; missing date-time cells and date-times past the
nanosecond range; a method's answer of the wrong length; fleet_rul's on_error and workers
checked where a table is given."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
import scipy.stats  # noqa: F401  (the trend's F test imports it lazily: here, at collection)
import torch

import prognos_torch.fleet.run as run_mod

try:  # (imported here, at collection, not in the test that needs it)
    import pandas as pd
except ImportError:  # the optional tables extra
    pd = None
from prognos_torch.fleet import (
    METHODS,
    RUL_COLUMNS,
    exponential_trend_rul,
    fleet_rul,
    ksigma_onset_batch,
    pad_batch,
    read_fleet_table,
)
from prognos_torch.prognosis.onset import healthy_baseline, ksigma_onset


def _series(n, onset, rate, *, level=1.0, sign=1.0, gaps=(), dt=1.0, t0=0.0, seed=0):
    """``level + noise`` that leaves the level as ``sign (exp(rate (k - onset)) - 1)`` from
    sample ``onset`` on; ``gaps`` missing."""
    g = np.random.default_rng(seed)
    k = np.arange(n)
    rise = np.where(k >= onset, np.exp(rate * (k - onset)) - 1.0, 0.0)
    x = level + 0.05 * g.standard_normal(n) + sign * rise
    x[list(gaps)] = np.nan
    return t0 + dt * k.astype(float), x


@pytest.fixture(scope="module")
def ragged():
    """Rising assets of different lengths, clocks and gaps (one with its last rows missing, one
    that never degrades) and falling ones around a level of 10."""
    specs = [
        ("r0", dict(n=30, onset=15, rate=0.12)),
        ("r1", dict(n=22, onset=11, rate=0.15, gaps=(3, 13, 21))),
        ("r2", dict(n=26, onset=12, rate=0.1, dt=0.5, t0=100.0, gaps=(23, 24, 25))),
        ("r3", dict(n=30, onset=40, rate=0.1)),
        ("f0", dict(n=36, onset=18, rate=0.08, sign=-1.0, level=10.0)),
        ("f1", dict(n=30, onset=14, rate=0.09, sign=-1.0, level=10.0, gaps=(5, 16, 29))),
    ]
    out = {}
    for j, (a, kw) in enumerate(specs):
        out[a] = _series(**kw, seed=j)
    return out


def _close(a, b):
    return (math.isnan(a) and math.isnan(b)) or math.isclose(a, b, rel_tol=1e-9, abs_tol=1e-12)


# --------------------------------------------------------------------------- per asset
def test_each_asset_of_a_ragged_fleet_is_its_answer_alone_and_the_exact_regression(ragged):
    """Padding, gaps, another asset's length or clock leak into no asset: its row is its row
    alone (phi auto, rising and falling, thresholds on either side of the healthy level), its
    onset the per-series rule's and its fixed-phi posterior the closed-form Bayesian regression
    on log(s (y - phi)) since onset."""
    assets = list(ragged)
    times, values = [ragged[a][0] for a in assets], [ragged[a][1] for a in assets]
    b = pad_batch(assets, times, values, seed=3)
    kw = dict(samples=20, min_rows=5, return_posterior=True)
    for direction, thr, phi in (("above", 8.0, "baseline"), ("below", 5.0, 20.0)):
        s = 1.0 if direction == "above" else -1.0
        full = exponential_trend_rul(b, thr, direction=direction, phi=phi, **kw)
        healthy_side = exact = 0
        for j, a in enumerate(assets):
            one = exponential_trend_rul(pad_batch([a], [times[j]], [values[j]], seed=3), thr,
                                        direction=direction, phi=phi, **kw)  # fmt: skip
            for c in RUL_COLUMNS:
                assert _close(float(full[c][j]), float(one[c][0])), (direction, a, c)
            assert full["flags"][j] == one["flags"][0]
            healthy_side += "threshold_on_healthy_side" in full["flags"][j]
            x, t = values[j], times[j]
            base = healthy_baseline(torch.from_numpy(s * x), torch.from_numpy(t))
            ref = ksigma_onset(torch.from_numpy(x), torch.from_numpy(t), direction=direction,
                               after=base.t_end)  # fmt: skip
            i0 = int(full["onset_index"][j])
            if "threshold_on_healthy_side" in full["flags"][j]:
                continue
            assert i0 == (ref.index if ref.detected else -1), (direction, a)
            if i0 < 0 or isinstance(phi, str):
                continue
            inb = ~np.isnan(x) & (t <= base.t_end)
            zb = np.log(s * (x[inb] - phi))
            sig = zb.std(ddof=1)
            P0 = np.diag([1.0, 1.0 / np.sort(np.diff(t))[(len(t) - 2) // 2] ** 2])
            ok = ~np.isnan(x[i0:])
            H = np.stack([np.ones(ok.sum()), t[i0:][ok] - t[i0]], 1)
            z = np.log(s * (x[i0:][ok] - phi))
            A = np.linalg.inv(P0) + H.T @ H / sig**2
            m = np.linalg.solve(A, np.linalg.inv(P0) @ [zb.mean(), 0.0] + H.T @ z / sig**2)
            L = full["posterior_chol"][j].numpy()
            np.testing.assert_allclose(full["posterior_mean"][j].numpy(), m, rtol=1e-9)
            np.testing.assert_allclose(L @ L.T, np.linalg.inv(A), rtol=1e-8, atol=1e-15)
            exact += 1
        # the other direction's assets (at 10 above, at 1 below): no RUL, a flag
        assert healthy_side == (2 if direction == "above" else 4)
        assert np.isfinite(full["rul_median"]).sum() == (3 if direction == "above" else 2)
        assert exact == (0 if isinstance(phi, str) else 2)


def test_a_numpy_float32_phi_is_the_number_it_holds(ragged):
    """phi=np.float32(-0.1) made s (X - phi) a float32 (NumPy's rule for a Python float with a
    float32), so the log threshold was rounded to 7 digits: RUL quantiles 6e-7 off those of
    phi=float(np.float32(-0.1)), the same number."""
    a = ["r0", "r1", "r2"]
    b = pad_batch(a, [ragged[k][0] for k in a], [ragged[k][1] for k in a])
    ref = exponential_trend_rul(b, 8.0, phi=float(np.float32(-0.1)), samples=40, min_rows=5)
    got = exponential_trend_rul(b, 8.0, phi=np.float32(-0.1), samples=40, min_rows=5)
    assert np.isfinite(ref["rul_median"]).all()
    for c in RUL_COLUMNS:
        np.testing.assert_allclose(got[c], ref[c], rtol=1e-13, atol=0)


# --------------------------------------------------------------------------- padded rows
def test_pad_batch_refuses_infinite_boolean_and_complex_cells_by_asset(ragged):
    """An infinite value went on to the engine, which refused the whole shard with 'ys contains
    inf (use NaN to mark a missing measurement)', naming no asset; booleans were read as 0/1 and
    complex numbers lost their imaginary part (a NumPy warning only)."""
    t, x = ragged["r0"]
    bad = x.copy()
    bad[20] = np.inf
    with pytest.raises(ValueError, match=r"^asset 'b': values must be numbers or NaN \(missing\), "
                       r"got inf at row 21$"):  # fmt: skip
        pad_batch(["a", "b"], [t, t], [x, bad])
    bad[20] = -np.inf
    with pytest.raises(ValueError, match=r"got -inf at row 21"):
        pad_batch(["b"], [t], [bad])
    with pytest.raises(ValueError, match=r"^asset 'a': values must be real numbers, got dtype "
                       r"bool"):  # fmt: skip
        pad_batch(["a"], [t[:3]], [np.array([True, False, True])])
    with pytest.raises(ValueError, match=r"^asset 'a': times must be real numbers, got dtype "
                       r"complex128"):  # fmt: skip
        pad_batch(["a"], [t[:2] + 1j], [x[:2]])
    # NaN (and None) stay missing
    b = pad_batch(["a"], [[0.0, 1.0, 2.0]], [[1.0, None, np.nan]])
    assert torch.isnan(b.values[0, 1:]).all()


def test_the_onset_rule_and_the_trend_check_the_rows_they_are_given(ragged):
    """ksigma_onset_batch took any tensors: a (1,) lengths was broadcast to every row, lengths
    past the columns were taken, infinite values were numbers (five after the healthy window of
    a healthy asset: an onset; the per-series rule refuses them), a 1-D values said 'not enough
    values to unpack'; a hand-made PaddedBatch with lengths past its columns failed with
    torch.gather's 'index 30 is out of bounds for dimension 1 with size 30'."""
    a = ["r0", "r1"]
    b = pad_batch(a, [ragged[k][0] for k in a], [ragged[k][1] for k in a])
    v, t, n = b.values, b.times, b.lengths
    bad = [((v, t, n[:1]), r"^lengths must be a \(2,\) int tensor, got \(1,\)"),
           ((v, t, n.to(torch.float64)), r"lengths must be a \(2,\) int tensor"),
           ((v, t, [30, 22]), r"lengths must be a \(2,\) int tensor, got list"),
           ((v, t, n + 1), r"^lengths must lie in \[0, 30\] \(the rows of values\), got \[31, 23\]"),
           ((v[0], t[0], n), r"^values must be a \(B, T\) float tensor, got \(30,\)"),
           ((v, t[:, :-1], n), r"^times must have the shape of values \(2, 30\), got \(2, 29\)"),
           ((v.masked_fill(torch.arange(30) == 20, math.inf), t, n),
            r"^values must be numbers or NaN \(missing\) within each row's length, got inf"),
           ((v, t.masked_fill(torch.arange(30) == 3, math.nan), n),
            r"^times must be finite and strictly increasing within each row's length"),
           ((v, t.flip(1), torch.tensor([30, 0])), r"^times must be finite and strictly")]  # fmt: skip
    for args, msg in bad:
        with pytest.raises(ValueError, match=msg):
            ksigma_onset_batch(*args)
    with pytest.raises(ValueError, match=r"^lengths must lie in \[0, 30\]"):
        exponential_trend_rul(replace(b, lengths=n + 1), 8.0, samples=5, min_rows=5)
    # padding past a row's length may hold anything: it is not read
    v2 = v.clone()
    v2[1, 22:] = math.inf
    t2 = t.clone()
    t2[1, 22:] = -1.0
    ref = ksigma_onset_batch(v, t, n, skip_window=True)
    got = ksigma_onset_batch(v2, t2, n, skip_window=True)
    assert torch.equal(ref.index, got.index) and torch.equal(ref.base_std, got.base_std)


# --------------------------------------------------------------------------- tables
def test_pandas_na_cells_are_missing_values_and_missing_times():
    """pandas' NA (a nullable 'string' column's or an object column's missing cell) printed
    '<NA>' and was refused as a value that 'is not a number'; in a time column of numbers it
    was 'time <NA> is not a number, while row 1 holds the number'."""
    if pd is None:
        pytest.skip("pandas (tables extra) is not installed")
    t = [0.0, 1.0, 2.0]
    for vals in (np.array([1.0, pd.NA, 2.0], dtype=object),
                 pd.array(["1", None, "2"], dtype="string")):  # fmt: skip
        tab = read_fleet_table(pd.DataFrame({"asset": ["a"] * 3, "t": t, "value": vals}))
        np.testing.assert_array_equal(tab.values[0], [1.0, np.nan, 2.0])
        assert not tab.errors
    times = np.array(["0", pd.NA, "2"], dtype=object)
    with pytest.raises(ValueError, match=r"^table: asset 'a', row 2: the time is missing or not "
                       r"finite$"):  # fmt: skip
        read_fleet_table({"asset": ["a"] * 3, "t": times, "value": [1.0, 2.0, 3.0]})


def test_a_missing_date_time_cell_is_the_time_missing(tmp_path):
    """None or NA among ISO 8601 date-times was 'time None is neither a number nor an ISO 8601
    date-time ... (Error parsing datetime string "None")'; an empty cell with a time_format
    'did not match' it; an empty ISO cell already said 'the time is missing'."""
    v = [1.0, 2.0, 3.0]
    for cell in (None, float("nan")):
        t = np.array(["2024-01-01", cell, "2024-01-03"], dtype=object)
        with pytest.raises(ValueError, match=r"^table: asset 'a', row 2: the time is missing$"):
            read_fleet_table({"asset": ["a"] * 3, "t": t, "value": v})
    for cell in (None, "", " NaT "):
        t = np.array(["01/01/2024", cell, "03/01/2024"], dtype=object)
        with pytest.raises(ValueError, match=r"^table: asset 'a', row 2: the time is missing$"):
            read_fleet_table({"asset": ["a"] * 3, "t": t, "value": v}, time_format="%d/%m/%Y")
    p = tmp_path / "f.csv"
    p.write_text("asset,t,value\nA,01/01/2024,1\nA,,2\n")
    with pytest.raises(ValueError, match=r"row 2 \(line 3\): the time is missing$"):
        read_fleet_table(p, time_format="%d/%m/%Y")
    # a text that is no date-time is still named as such
    t = np.array(["2024-01-01", "soon", "2024-01-03"], dtype=object)
    with pytest.raises(ValueError, match=r"row 2: time 'soon' is neither a number nor an ISO"):
        read_fleet_table({"asset": ["a"] * 3, "t": t, "value": v})


def test_date_times_past_the_nanosecond_range_are_refused_not_wrapped():
    """A datetime64 column (a DataFrame's, a Parquet file's) with 3000-01-01 was cast to
    nanoseconds, where NumPy wraps around silently: 1830-11-23, so a fleet observed in 3000
    got its onset and failure dates in 1830, and 3000 after 2024 'came after' it (unsorted);
    the ISO text 3000-01-01 is refused as outside 1678-2262."""
    v = [1.0, 2.0, 3.0]
    t = np.array(["3000-01-01", "3000-01-02", "3000-01-03"], dtype="datetime64[D]")
    with pytest.raises(ValueError, match=r"^table: asset 'a', row 1: time 3000-01-01 lies outside "
                       r"1678-2262, the range of nanosecond times$"):  # fmt: skip
        read_fleet_table({"asset": ["a"] * 3, "t": t, "value": v})
    t = np.array(["2024-01-01T00:00", "NaT", "1600-01-01T00:00"], dtype="datetime64[m]")
    with pytest.raises(ValueError, match=r"row 3: time 1600-01-01T00:00 lies outside 1678-2262"):
        read_fleet_table({"asset": ["a"] * 3, "t": t, "value": v})
    # within the range: days since 1970-01-01 UTC, whatever the unit
    t = np.array(["2261-12-30", "2261-12-31"], dtype="datetime64[D]")
    tab = read_fleet_table({"asset": ["a"] * 2, "t": t, "value": v[:2]})
    day = (np.datetime64("2261-12-30", "D") - np.datetime64("1970-01-01", "D")).astype(float)
    np.testing.assert_array_equal(tab.times[0], [day, day + 1.0])


# --------------------------------------------------------------------------- fleet_rul
def _table():
    t = np.arange(12.0)
    return {"asset": ["a"] * 12 + ["b"] * 12 + ["c"] * 12, "t": np.r_[t, t, t],
            "value": np.r_[np.ones(12), 2 * np.ones(12), 3 * np.ones(12)]}  # fmt: skip


def test_a_method_answer_of_the_wrong_length_is_refused_by_column(monkeypatch):
    """A method that returned a (1,) column had it spread over every asset of the shard; a
    short flag list raised a bare IndexError."""

    def one_row(batch, threshold, **options):
        out = {c: np.zeros(1) for c in RUL_COLUMNS}
        out["flags"] = [""] * len(batch)
        return out

    monkeypatch.setitem(METHODS, "one_row", one_row)
    with pytest.raises(ValueError, match=r"^method 'one_row' returned 'n_rows' of shape \(1,\) "
                       r"for a shard of 3 assets; expected \(3,\)$"):  # fmt: skip
        fleet_rul(_table(), 5.0, method="one_row")

    def no_flags(batch, threshold, **options):
        return {c: np.zeros(len(batch)) for c in RUL_COLUMNS}

    monkeypatch.setitem(METHODS, "no_flags", no_flags)
    with pytest.raises(ValueError, match=r"^method 'no_flags' returned no 'flags' for a shard"):
        fleet_rul(_table(), 5.0, method="no_flags")

    def fine(batch, threshold, **options):  # a right answer still goes through
        out = {c: np.full(len(batch), 1.0) for c in RUL_COLUMNS}
        out["flags"] = ["x"] * len(batch)
        return out

    monkeypatch.setitem(METHODS, "fine", fine)
    res = fleet_rul(_table(), 5.0, method="fine", shard_size=2)
    assert res.columns["flags"] == ["x"] * 3 and res.columns["rul_median"] == [1.0] * 3


def test_fleet_rul_checks_on_error_and_counts_workers_where_a_table_is_given(monkeypatch):
    """on_error='Flag' was ignored where a FleetTable was given (read_fleet_table checks it
    only when it reads); workers=np.int64(2) made the result's shard_size a NumPy int."""
    tab = read_fleet_table(_table())
    with pytest.raises(ValueError, match=r"^on_error must be 'raise' or 'flag', got 'Flag'$"):
        fleet_rul(tab, 5.0, on_error="Flag", samples=5)

    def serial(fn, tasks, workers, sizes, caller, on_done=None):  # no processes spawned
        return [fn(*task) for task in tasks]

    monkeypatch.setattr(run_mod, "process_map", serial)
    res = fleet_rul(tab, 5.0, workers=np.int64(2), samples=5)
    assert type(res.shard_size) is int and res.shard_size == 2
