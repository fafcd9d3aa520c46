"""The "use it on your own data" workflow: CSV series, fitting, forecasts, RUL, safe model files.

References are independent: NumPy windows, scaling, ridge and LS-SVR KKT solves, first-passage
times computed by hand, datetime arithmetic from the standard library. The model-file format
and its refusals are tested in ``tests/test_model_file.py``.
"""

from __future__ import annotations

import json
import math
import subprocess
import sys
import textwrap
import warnings
from datetime import datetime

import numpy as np
import pytest
import torch

from prognos_torch.workflow import (
    ExtrapolationWarning,
    Series,
    ThresholdWarning,
    fit_series,
    forecast,
    load_model,
    load_series,
    plot_forecast,
    plot_rul,
    rul,
    save_model,
    select_embedding,
)


def _series_values(T=120, seed=0):
    rng = np.random.default_rng(seed)
    t = np.arange(T) * 0.5
    x = 1.0 + 0.01 * t + 0.3 * np.sin(2 * np.pi * t / 12) + 0.03 * rng.standard_normal(T)
    return t, x


def _write_csv(path, header, rows, sep=","):
    with open(path, "w", encoding="utf-8") as fh:
        fh.write(sep.join(header) + "\n")
        for r in rows:
            fh.write(sep.join(str(c) for c in r) + "\n")


def _np_windows(z, m):
    X = np.array([z[i : i + m] for i in range(len(z) - m)])
    return X, np.array(z[m:])


# --------------------------------------------------------------------------- load_series
def test_load_series_csv_values_time_and_where(tmp_path):
    t, x = _series_values(12)
    rows = []
    for i in range(12):
        for ch in (1, 2):
            stamp = datetime(2024, 1, 1, 0, 0).replace(hour=i)
            rows.append((stamp.isoformat(), ch, repr(float(x[i] * ch))))
    path = tmp_path / "d.csv"
    _write_csv(path, ("timestamp", "channel", "value"), rows, sep=";")
    s = load_series(path, "value", time_column="timestamp", where=["channel=2"])
    assert s.values.dtype == torch.float64
    np.testing.assert_array_equal(s.values.numpy(), x * 2)
    # days since the first row, from the standard library
    days = [
        (datetime(2024, 1, 1, i) - datetime(2024, 1, 1, 0)).total_seconds() / 86400
        for i in range(12)
    ]
    np.testing.assert_allclose(s.time.numpy(), days, rtol=0, atol=1e-12)
    assert s.time_unit == "days" and s.start == "2024-01-01T00:00:00"
    assert s.dt == pytest.approx(1 / 24)
    # numeric where value matches 2.0; until as an ISO date-time and as days
    s2 = load_series(path, "value", time_column="timestamp", where={"channel": "2.0"},
                     until="2024-01-01T05:00")  # fmt: skip
    assert len(s2) == 6
    s3 = load_series(path, "value", time_column="timestamp", where={"channel": 2}, until=5 / 24)
    assert torch.equal(s2.values, s3.values)
    assert len(load_series(path, "value", where=["channel=1"], last=4)) == 4
    # the same rows from pandas: a Series on a DatetimeIndex gives the CSV's series
    pd = pytest.importorskip("pandas")
    index = pd.DatetimeIndex([datetime(2024, 1, 1, i) for i in range(12)])
    p = load_series(pd.Series(x * 2, index=index, name="value"))
    assert torch.equal(p.values, s.values) and torch.equal(p.time, s.time)
    assert (p.name, p.time_unit, p.start) == ("value", "days", "2024-01-01T00:00:00")
    p2 = load_series(pd.Series(x * 2, index=index + pd.Timedelta(0)), until="2024-01-01T05:00")
    assert torch.equal(p2.values, s2.values)
    # a filtered pandas Series is taken by position, its index labels are no time
    sel = pd.Series(x * 2, index=np.arange(12) * 3 + 1)
    assert load_series(sel).time is None and torch.equal(load_series(sel).values, s.values)


def test_load_series_gaps_fill_and_errors(tmp_path):
    path = tmp_path / "g.csv"
    _write_csv(path, ("t", "x"), [(0, 1.0), (1, ""), (2, "nan"), (4, 7.0), (5, 8.0)])
    with pytest.raises(ValueError, match=r"2 missing value\(s\) at line\(s\) 3, 4; pass fill="):
        load_series(path, "x", time_column="t")
    lin = load_series(path, "x", time_column="t", fill="linear")
    np.testing.assert_allclose(lin.values.numpy(), np.interp([0, 1, 2, 4, 5], [0, 4, 5], [1, 7, 8]))
    drop = load_series(path, "x", time_column="t", fill="drop")
    np.testing.assert_array_equal(drop.values.numpy(), [1.0, 7.0, 8.0])
    np.testing.assert_array_equal(drop.time.numpy(), [0.0, 4.0, 5.0])

    _write_csv(path, ("t", "x"), [(0, ""), (1, 2.0), (2, 3.0)])
    with pytest.raises(ValueError, match="at the start .* cannot be interpolated; use fill='drop'"):
        load_series(path, "x", fill="linear")
    # only the runs at the ends are named (lines 3 and 8 would interpolate)
    _write_csv(path, ("t", "x"), [(0, ""), (1, "NA"), (2, ""), (3, 2.0), (4, 3.0), (5, ""),
                                  (6, 4.0), (7, "nan")])  # fmt: skip
    with pytest.raises(ValueError, match=r"missing value\(s\) at the start \(line\(s\) 2, 3, 4\) "
                       r"and the end \(line\(s\) 9\) that cannot be interpolated"):  # fmt: skip
        load_series(path, "x", fill="linear")
    _write_csv(path, ("t", "x", "ch"), [(0, 1.0, 1), (1, 2.0, 1)])
    with pytest.raises(ValueError, match="the value column 't' is also the time column"):
        load_series(path, "t", time_column="t")
    with pytest.raises(ValueError, match="the value column 'ch' is also a where column"):
        load_series(path, "ch", where={"ch": 1})
    _write_csv(path, ("t", "x"), [(0, ""), (1, "NA")])
    with pytest.raises(ValueError, match="'x' .*has no value: every one is missing"):
        load_series(path, "x", fill="linear")
    _write_csv(path, ("t", "x"), [(0, 1.0), (1, "abc"), (2, 3.0)])
    with pytest.raises(ValueError, match=r"line 3: column 'x' value 'abc' is not a number"):
        load_series(path, "x")
    with pytest.raises(ValueError, match=r"no column 'y'; columns: t, x"):
        load_series(path, "y")
    with pytest.raises(FileNotFoundError, match="data file not found"):
        load_series(tmp_path / "missing.csv", "x")
    _write_csv(path, ("t", "x"), [(0, 1.0), (2, 2.0), (1, 3.0)])
    with pytest.raises(ValueError, match=r"line 4: time column 't' must be strictly increasing"):
        load_series(path, "x", time_column="t")
    path.write_text('"t", "x"\n0, "1.5"\n1, 2.5\n')  # a space after the comma, then a quote
    np.testing.assert_array_equal(load_series(path, "x", time_column="t").values, [1.5, 2.5])
    path.write_bytes("t,x_\u00b5m\n0,1.5\n".encode("latin-1"))  # Windows' Latin-1 export
    with pytest.raises(ValueError, match=r"not a UTF-8 text CSV file \(the byte b'\\xb5' .*"
                       r"save it as UTF-8"):  # fmt: skip
        load_series(path)
    # day-first dates (a spreadsheet export) with time_format; a %z offset applied
    path.write_text("t,x\n31/12/2023 23:00,1\n01/01/2024 01:00,2\n01/01/2024 02:30,3\n")
    dmy = load_series(path, "x", time_column="t", time_format="%d/%m/%Y %H:%M")
    np.testing.assert_allclose(dmy.time.numpy(), [0.0, 2 / 24, 3.5 / 24], rtol=0, atol=1e-12)
    assert dmy.time_unit == "days" and dmy.start == "2023-12-31T23:00:00"
    path.write_text("t,x\n01/01/2024 01:00 +0100,1\n01/01/2024 02:00 +0000,2\n")
    z = load_series(path, "x", time_column="t", time_format="%d/%m/%Y %H:%M %z")
    assert z.start == "2024-01-01T00:00:00" and float(z.time[1]) == pytest.approx(2 / 24)
    with pytest.raises(ValueError, match=r"line 2: time column 't' value '01/01/2024 01:00 \+0100' "
                       r"does not match time_format '%d/%m/%Y %H:%M'"):  # fmt: skip
        load_series(path, "x", time_column="t", time_format="%d/%m/%Y %H:%M")
    with pytest.raises(
        ValueError, match=r"ISO 8601 date-time .* give time_format \(--time-format\)"
    ):
        load_series(path, "x", time_column="t")
    with pytest.raises(ValueError, match="time_format must be strptime codes"):
        load_series(path, "x", time_column="t", time_format="dd/mm/yyyy")
    with pytest.raises(ValueError, match="time_format applies to a time column"):
        load_series(path, "x", time_format="%d/%m/%Y")
    path.write_text("t;ch;x\n0,5;1;1,25\n1,5;2;9\n2,5;1;2,5\n3,5;1;\n")  # decimal commas
    eu = load_series(path, "x", time_column="t", where={"ch": "1,0"}, decimal=",", fill="drop")
    np.testing.assert_array_equal(eu.values.numpy(), [1.25, 2.5])
    np.testing.assert_array_equal(eu.time.numpy(), [0.5, 2.5])
    with pytest.raises(ValueError, match=r"line 2: time column 't' value '0,5' is not a number; "
                       r"a decimal comma\? pass decimal=','"):  # fmt: skip
        load_series(path, "x", time_column="t")
    path.write_text("t;x\n1;1,5\n2;1.500\n")  # a point with decimal=',': a thousands mark
    with pytest.raises(ValueError, match=r"line 3: column 'x' value '1.500' is not a number "
                       r"with decimal=','"):  # fmt: skip
        load_series(path, "x", decimal=",")
    with pytest.raises(ValueError, match="decimal must be '.' or ','"):
        load_series(path, "x", decimal=";")
    with pytest.raises(ValueError, match="where and decimal apply to CSV files"):
        load_series([1.0, 2.0], decimal=",")
    _write_csv(path, ("t", "x"), [(1700021180, 1.0), (1700024780, 2.0), (1700017580, 3.0)])
    with pytest.raises(ValueError, match=r"increasing \(1700017580 follows 1700024780\)"):
        load_series(path, "x", time_column="t")  # Unix seconds: %g printed 1.70002e+09 twice
    _write_csv(path, ("t", "ch", "x"), [(0, 1, 1.0), (0, 2, 1.1), (1, 1, 3.0), (1, 2, 3.1)])
    with pytest.raises(ValueError, match=r"\(0 follows 0\); a repeated time: .* --where COL="):
        load_series(path, "x", time_column="t")  # a long table: two channels in one file
    # date-times are shown as date-times (in UTC), not as the days since the first they became
    path.write_text("t,x\n2024-03-01T10:00:00+01:00,1\n2024-03-01T11:00:00Z,2\n"
                    "2024-03-01T09:00:00.25Z,3\n")  # fmt: skip
    with pytest.raises(ValueError, match=r"line 4: .* increasing \(2024-03-01T09:00:00.250 "
                       r"follows 2024-03-01T11:00:00\)"):  # fmt: skip
        load_series(path, "x", time_column="t")
    with pytest.raises(ValueError, match="fill must be None, 'linear' or 'drop'"):
        load_series(path, "x", fill="spline")
    with pytest.raises(ValueError, match=r"source must be 1-D"):
        load_series(np.zeros((3, 2)))


# --------------------------------------------------------------------------- fitting
def test_select_embedding_scores_match_numpy_windows():
    _, x = _series_values(100)
    z = torch.as_tensor((x - x.min()) / (x.max() - x.min()))
    opts = {"n_hidden": 10, "activation": "sigmoid", "lam": 1e-6}
    m, scores = select_embedding(z, "elm", opts, (2, 3, 4), seed=3)
    T, split = 100, 100 - math.ceil(0.2 * 100)
    from prognos_torch.learners import ELM

    for mm in (2, 3, 4):
        # same validation targets z[split:], training targets z[4:split] for every m
        Xt = np.array([z[i - mm : i].numpy() for i in range(4, split)])
        Xv = np.array([z[i - mm : i].numpy() for i in range(split, T)])
        net = ELM(mm, 10, 1, "sigmoid", torch.Generator().manual_seed(3))
        a, b = net.a.detach().numpy(), net.b.detach().numpy()
        H = 1 / (1 + np.exp(-(Xt @ a.T + b)))
        beta = np.linalg.solve(H.T @ H + 1e-6 * np.eye(10), H.T @ z[4:split].numpy())
        pred = (1 / (1 + np.exp(-(Xv @ a.T + b)))) @ beta
        ref = np.sqrt(np.mean((pred - z[split:].numpy()) ** 2))
        assert scores[mm] == pytest.approx(ref, rel=1e-6)
    assert m == min(scores, key=scores.get)


def test_fit_elm_closed_form_and_ekf_equal_numpy_ridge():
    """Ridge on NumPy windows of the min-max scaled training part; the EKF on the ELM output
    weights with Q = 0, P0 = 1, R = 1e-3 is recursive least squares = ridge with lam = R / P0."""
    _, x = _series_values(90)
    s = load_series(x)
    m, n_train = 3, 72
    xt = x[:n_train]
    z = (xt - xt.min()) / (xt.max() - xt.min())
    X, y = _np_windows(z, m)
    for optimizer, lam in (("closed-form", 1e-6), ("ekf", 1e-3)):
        model = fit_series(s, "elm", optimizer, m, holdout=18, seed=5)
        a, b = model.learner.a.detach().numpy(), model.learner.b.detach().numpy()
        H = 1 / (1 + np.exp(-(X @ a.T + b)))
        beta = np.linalg.solve(H.T @ H + lam * np.eye(H.shape[1]), H.T @ y)
        np.testing.assert_allclose(
            model.learner.beta.detach().numpy()[:, 0], beta, rtol=1e-6, atol=1e-8
        )
        assert model.config["scaler"]["data_min"] == xt.min()
        assert model.config["scaler"]["data_max"] == xt.max()
        res = np.sqrt(np.mean((H @ model.learner.beta.detach().numpy()[:, 0] - y) ** 2))
        assert model.config["residual_rmse"] == pytest.approx(res, rel=1e-9)


def test_fit_lssvr_closed_form_equals_numpy_kkt_and_holdout_metrics():
    _, x = _series_values(60)
    s = load_series(x)
    model = fit_series(s, "lssvr", None, 2, holdout=10)
    assert model.config["optimizer"] == "closed-form"
    xt = x[:50]
    z = (xt - xt.min()) / (xt.max() - xt.min())
    X, y = _np_windows(z, 2)
    sigma, C = 0.5, 100.0
    K = np.exp(-((X[:, None, :] - X[None, :, :]) ** 2).sum(-1) / (2 * sigma**2))
    n = len(y)
    A = np.block([[K + np.eye(n) / C, np.ones((n, 1))], [np.ones((1, n)), np.zeros((1, 1))]])
    sol = np.linalg.solve(A, np.concatenate([y, [0.0]]))
    np.testing.assert_allclose(model.learner.alpha.detach().numpy()[:, 0], sol[:n], atol=1e-8)
    # held-out metrics: one-step predictions from the true windows and persistence, by hand
    zz = (x - xt.min()) / (xt.max() - xt.min())
    Xtail = np.array([zz[i - 2 : i] for i in range(50, 60)])
    Kt = np.exp(-((Xtail[:, None, :] - X[None, :, :]) ** 2).sum(-1) / (2 * sigma**2))
    one = (Kt @ sol[:n] + sol[n]) * (xt.max() - xt.min()) + xt.min()
    mt = model.metrics
    assert mt["one_step_rmse"] == pytest.approx(np.sqrt(np.mean((one - x[50:]) ** 2)), rel=1e-8)
    assert mt["persistence_rmse"] == pytest.approx(np.sqrt(np.mean((x[49] - x[50:]) ** 2)))
    fc = forecast(model, s.head(50), 10)
    assert mt["rmse"] == pytest.approx(float((fc.mean - s.values[50:]).square().mean().sqrt()))
    inside = ((s.values[50:] >= fc.lower) & (s.values[50:] <= fc.upper)).double().mean()
    assert mt["coverage"] == pytest.approx(float(inside))


def test_fit_series_shows_progress_only_when_asked(capsys):
    """progress=True: bars over the embedding candidates and the training on stderr; the
    default (and None off a terminal, the command line's choice) writes nothing there, and the
    model is the same either way."""
    t, x = _series_values(90)
    s = load_series(x, time=t)
    quiet = fit_series(s, "anfis", "ekf", holdout=10, seed=4)
    assert capsys.readouterr().err == ""
    shown = fit_series(s, "anfis", "ekf", holdout=10, seed=4, progress=True)
    err = capsys.readouterr().err
    assert "embedding m" in err and "fit:" in err
    fit_series(s, "anfis", "ekf", holdout=10, seed=4, progress=None)  # stderr is no terminal
    assert capsys.readouterr().err == ""
    for a, b in zip(quiet.learner.parameters(), shown.learner.parameters()):
        assert torch.equal(a, b)


def test_fit_bad_input():
    s = load_series(np.linspace(0, 1, 5))
    with pytest.raises(ValueError, match=r"has 5 values; embedding m=5 needs at least m \+ 1 = 6"):
        fit_series(s, "elm", None, 5)
    with pytest.raises(ValueError, match="unknown learner 'svm'; choose one of elm, lssvr, anfis"):
        fit_series(s, "svm")
    with pytest.raises(ValueError, match="unknown optimizer 'sgd'; choose one of closed-form"):
        fit_series(s, "elm", "sgd")
    with pytest.raises(ValueError, match="constant over its"):
        fit_series(load_series(np.ones(30)), "elm", None, 2)
    # 160 training values and m = 159: one window, fitted exactly (it was accepted)
    ramp = load_series(np.sin(np.arange(200) / 7.0))
    with pytest.raises(ValueError, match=r"160 training values: embedding m=159 leaves 1 "
                       r"training window\(s\), fewer than the m \+ 1 = 160 .* give m <= 79"):  # fmt: skip
        fit_series(ramp, "elm", None, 159)
    assert fit_series(ramp, "elm", None, 79).m == 79  # 81 windows for 80 coefficients
    with pytest.raises(ValueError, match=r"unknown elm learner option\(s\) \['n_hiden'\]"):
        fit_series(load_series(np.arange(30.0)), "elm", None, 2, learner_options={"n_hiden": 3})


def test_series_converts_numbers_and_refuses_other_shapes_and_fit_refuses_missing_values():
    x = np.linspace(0.0, 1.0, 30)
    for v in (x, list(x), torch.tensor(x, dtype=torch.float32)):
        s = Series(v)
        assert s.values.dtype == torch.float64 and s.values.shape == (30,)
    torch.testing.assert_close(Series(torch.tensor(x, dtype=torch.float32)).values,
                               torch.tensor(x, dtype=torch.float32).double())  # fmt: skip
    with pytest.raises(ValueError, match=r"Series values must have shape \(T,\), got \(30, 1\)"):
        Series(torch.tensor(x)[:, None])
    with pytest.raises(TypeError, match="Series values must be numbers, got booleans"):
        Series(torch.ones(3, dtype=torch.bool))
    with pytest.raises(ValueError, match=r"Series time must have the values' shape \(30,\)"):
        Series(x, torch.arange(29.0))
    xn = x.copy()
    xn[[12, 20]] = np.nan
    with pytest.raises(ValueError, match="has 2 missing or non-finite value.s., the first at row 12"):
        fit_series(Series(xn), "elm", None, 2)


def test_forecast_and_rul_read_nan_as_missing():
    """NaN is a missing value: the filter predicts over it, a missing value in the window the
    filter would start from moves the start to the last complete window before it, and a
    missing last value neither sets the RUL's direction nor hides the extrapolation flag."""
    g = torch.Generator().manual_seed(0)
    t = torch.arange(150, dtype=torch.float64)
    x = 0.5 + 0.01 * t + 0.02 * torch.randn(150, generator=g, dtype=torch.float64)
    model = fit_series(Series(x), "elm", None, 3)  # the last 20 % lie above the training range
    xn = x.clone()
    xn[47] = math.nan  # in the window rows 47-49 that 100 filtered steps start from
    got = forecast(model, Series(xn), 5)
    ref = forecast(model, Series(xn), 5, filter_steps=103)  # rows 44-46 start it
    for k in ("mean", "lower", "upper"):
        assert torch.equal(getattr(got, k), getattr(ref, k))
    gone = xn.clone()
    gone[:149] = math.nan
    with pytest.raises(ValueError, match="has no 3 consecutive observed values"):
        forecast(model, Series(gone), 5)
    xl = x.clone()
    xl[-1] = math.nan
    with pytest.warns(ExtrapolationWarning):
        fc = forecast(model, Series(xl), 5)
    assert bool(torch.isfinite(fc.lower).all() and torch.isfinite(fc.upper).all())
    assert bool(torch.isfinite(fc.extrapolation).all())
    with pytest.warns(ExtrapolationWarning):
        clean = rul(model, Series(x), 2.5, filter="sckf", n_particles=200)
    with pytest.warns(ExtrapolationWarning):
        r = rul(model, Series(xl), 2.5, filter="sckf", n_particles=200)
    # the missing last value read as a number made the direction "below": every path at
    # step 1, a certain RUL of one step, and no flag
    assert r.direction == clean.direction == "above"
    assert r.flags and r.flags[0].startswith("the series the RUL starts from lies outside")
    assert r.censored_mass == clean.censored_mass == 1.0
    with pytest.raises(ValueError, match="already reaches the threshold"):
        rul(model, Series(xl), float(x[-2]) - 0.01, direction="above")
    # the threshold is any real scalar, as for prognose
    for thr in (np.float32(2.5), torch.tensor(2.5)):
        with pytest.warns(ExtrapolationWarning):
            assert rul(model, Series(x), thr, filter="sckf", n_particles=200).threshold == 2.5
    with pytest.raises(ValueError, match="threshold must be a finite number"):
        rul(model, Series(x), math.inf)


def test_rul_warns_when_the_auto_direction_goes_against_the_series():
    """A rising series with a threshold below its whole history: direction "auto" read
    "below" from the last value and gave a confident RUL without a word."""
    t = np.arange(400.0)
    y = 1 + 0.05 * np.random.default_rng(0).standard_normal(400)
    y[200:] += np.exp((t[200:] - 200) / 190) - 1
    model = fit_series(Series(y), "elm", None, 3)
    kw = dict(filter="sckf", n_particles=50)
    with pytest.warns(ThresholdWarning, match=r"the threshold 0.5 lies below every observed "
                      r"value while the series rose \(median of its first tenth 0.99"):  # fmt: skip
        r = rul(model, Series(y), 0.5, **kw)
    assert r.direction == "below" and r.flags[-1].startswith("the threshold 0.5 lies below")
    mirrored = fit_series(Series(-y), "elm", None, 3)
    with pytest.warns(ThresholdWarning, match="lies above every observed value while the "
                      "series fell"):  # fmt: skip
        rul(mirrored, Series(-y), -0.5, **kw)
    with warnings.catch_warnings():  # meant, or on the side the series moves to: no warning
        warnings.simplefilter("error", ThresholdWarning)
        warnings.simplefilter("ignore", ExtrapolationWarning)
        assert not any("every observed" in f for f in rul(model, Series(y), 0.5,
                                                           direction="below", **kw).flags)
        assert not any("every observed" in f for f in rul(mirrored, Series(-y), -3.0,
                                                           **kw).flags)  # fmt: skip


# --------------------------------------------------------------------------- scaling, forecast, RUL
def test_forecast_and_rul_are_affine_equivariant():
    """Min-max scaling makes the fitted problem identical for a x + c (a > 0): forecasts map by
    the same affine map, and the RUL for the mapped threshold is the same distribution."""
    t, x = _series_values(80)
    a, c = 3.0, -2.0
    s1, s2 = load_series(x, time=t), load_series(a * x + c, time=t)
    m1 = fit_series(s1, "elm", None, 3, holdout=0)
    m2 = fit_series(s2, "elm", None, 3, holdout=0)
    f1, f2 = forecast(m1, s1, 12), forecast(m2, s2, 12)
    for k in ("mean", "lower", "upper"):
        torch.testing.assert_close(getattr(f2, k), a * getattr(f1, k) + c, rtol=1e-7, atol=1e-7)
    torch.testing.assert_close(f1.time, t[-1] + 0.5 * torch.arange(1, 13, dtype=torch.float64))
    r1 = rul(m1, s1, 1.5, horizon=40, filter="pf", n_particles=64, filter_steps=10)
    r2 = rul(m2, s2, a * 1.5 + c, horizon=40, filter="pf", n_particles=64, filter_steps=10)
    torch.testing.assert_close(r2.distribution.pmf, r1.distribution.pmf)


def test_rul_first_passage_by_hand_and_censoring():
    t, x = _series_values(80)
    s = load_series(x, time=t)
    model = fit_series(s, "elm", None, 3, holdout=0)
    thr = float(x[-1]) + 0.2
    r = rul(model, s, thr, horizon=30, filter="sckf", n_particles=50, seed=1)
    assert r.direction == "above"
    paths, w = r.paths.numpy(), r.weights.numpy()
    pmf = np.zeros(30)
    for p, wi in zip(paths, w):
        hit = np.flatnonzero(p >= thr)
        if hit.size:
            pmf[hit[0]] += wi
    np.testing.assert_allclose(r.distribution.pmf.numpy(), pmf, atol=1e-12)
    assert r.crossing_probability == pytest.approx(pmf.sum())
    np.testing.assert_allclose(r.distribution.support.numpy(), 0.5 * np.arange(1, 31))
    far = rul(model, s, 1e6, horizon=20, filter="sckf", n_particles=20)
    assert far.fully_censored and all(
        far.summary()[k] is None for k in ("mean", "median", "q05", "q95")
    )
    low = rul(model, s, -1e6, horizon=5, filter="sckf", n_particles=10)
    assert low.direction == "below" and low.fully_censored
    with pytest.raises(ValueError, match="already reaches the threshold"):
        rul(model, s, float(x[-1]) + 1, direction="below")
    with pytest.raises(ValueError, match="unknown filter 'kf'"):
        rul(model, s, thr, filter="kf")


def test_plots_written(tmp_path):
    t, x = _series_values(60)
    s = load_series(x, time=t)
    model = fit_series(s, "elm", None, 2, holdout=0)
    fc = forecast(model, s, 8, filter="pf", n_particles=30, filter_steps=5)
    assert fc.samples.shape == (30, 8)
    plot_forecast(tmp_path / "f.png", fc, truth=s)
    plot_rul(tmp_path / "r.png", rul(model, s, 2.0, horizon=20, filter="pf", n_particles=30))
    for name in ("f.png", "r.png"):
        assert (tmp_path / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["f.png", "r.png"]  # no temp files


def test_rul_plots_keep_their_axes_near_the_data_when_paths_overflow(tmp_path):
    # an exponential path far beyond the threshold can reach 1e300 or inf: the figures draw
    # it clipped near the data and the threshold, so the axes stay readable
    from dataclasses import replace

    from prognos_torch.plots import plot_prognosis
    from prognos_torch.workflow import prognose

    t, x = _series_values(60)
    s = load_series(x, time=t)
    model = fit_series(s, "elm", None, 2, holdout=0)
    r = rul(model, s, 2.0, horizon=20, filter="pf", n_particles=30)
    tt = torch.linspace(0.0, 10.0, 80, dtype=torch.float64)
    y = 1.0 + 0.01 * torch.sin(7 * tt) + torch.where(tt > 5, torch.exp(tt - 5) - 1, 0 * tt)
    p = prognose(y, 150.0, time=tt)
    for res, draw in ((r, plot_rul), (p, plot_prognosis)):
        wild = res.paths.clone()
        wild[0], wild[-1] = math.inf, -1e300
        fig = draw(tmp_path / "w.png", replace(res, paths=wild))
        y_seen = np.append(res.history.values.numpy(), res.threshold)
        lo, hi = y_seen.min(), y_seen.max()
        ylo, yhi = fig.axes[0].get_ylim()
        assert lo - 12 * (hi - lo) < ylo <= lo and hi <= yhi < hi + 12 * (hi - lo)


def test_prognosis_figure_looks_as_far_as_the_bulk_of_the_rul_not_its_tail(tmp_path):
    # IMS test 1 bearing 3 a day before failure: median RUL 0.17 d, 95 % quantile 16.5 d.
    # Drawn to the 95 % quantile, the data and the median crossing would sit in the left 1 %
    from prognos_torch.datasets import load_ims_features
    from prognos_torch.plots import plot_prognosis
    from prognos_torch.workflow import prognose

    f = load_ims_features(1)
    keep = f.days <= 34.06
    r = prognose(f.feature("rms")[keep, 4], 0.446, time=f.days[keep])
    s = r.summary()
    assert r.time_unit == "time"  # numbers given as time= are not "steps"
    assert s["q95"] > 30 * s["median"]
    fig = plot_prognosis(tmp_path / "p.png", r)
    top, pmf = fig.axes
    t0, t1 = top.get_xlim()
    shown = r.t_last - t0
    assert r.t_last + s["median"] < t1 <= r.t_last + max(3 * s["median"], shown) + 1e-9
    assert top.get_xlabel() == "time"
    assert s["median"] < pmf.get_xlim()[1] < s["q95"]
    assert top.get_title().endswith(f"median RUL {s['median']:.3g} time (exponential+elm)")
    heights = np.array([b.get_height() for b in pmf.patches])
    full = np.flatnonzero(heights > 0)
    assert np.mean(heights[full[0] : full[-1] + 1] == 0) <= 0.1  # no comb of empty bars
    # before onset the bound is no forecast: the data keep the panel, the title says so
    g = torch.Generator().manual_seed(0)
    healthy = prognose(1.0 + 0.05 * torch.randn(2000, generator=g, dtype=torch.float64), 2.0)
    assert healthy.status == "no degradation detected yet"
    top = plot_prognosis(tmp_path / "h.png", healthy).axes[0]
    shown = healthy.t_last - float(healthy.history.t[0])
    assert top.get_xlim()[1] <= healthy.t_last + 0.25 * shown + 1e-9
    assert (
        "no degradation detected yet, RUL > " in top.get_title() and "None" not in top.get_title()
    )
    # workflow.plot_rul draws a prognose result as plot_prognosis does (before and after
    # onset); the arguments swapped, or history on such a result, are refused
    from prognos_torch.workflow import plot_rul

    for res in (r, healthy):
        plot_prognosis(tmp_path / "a.png", res, n_paths=20)  # plot_rul's n_paths
        plot_rul(tmp_path / "b.png", res)
        assert (tmp_path / "a.png").read_bytes() == (tmp_path / "b.png").read_bytes()
    with pytest.raises(TypeError, match=r"got PosixPath; the call is plot_rul\(path, result\)"):
        plot_rul(r, tmp_path / "x.png")
    with pytest.raises(ValueError, match="history applies to rul"):
        plot_rul(tmp_path / "x.png", r, history=50)
    assert not (tmp_path / "x.png").exists()


# --------------------------------------------------------------------------- model files
def test_model_file_round_trip_in_a_fresh_process(tmp_path):
    t, x = _series_values(90)
    s = load_series(x, time=t)
    model = fit_series(s, "anfis", "ekf", 2, holdout=10, seed=4)
    path = tmp_path / "model.pt"
    save_model(model, path)
    again = load_model(path)
    assert again.config == model.config
    for k, v in model.learner.state_dict().items():
        assert torch.equal(again.learner.state_dict()[k], v) and v.dtype == torch.float64
    fc = forecast(model, s, 15)
    r = rul(model, s, 1.8, horizon=40, filter="ekpf", n_particles=40, filter_steps=10, seed=2)
    np.save(tmp_path / "x.npy", x)
    np.save(tmp_path / "t.npy", t)
    script = textwrap.dedent(
        f"""
        import json, numpy as np, torch
        torch.set_num_threads(1)
        from prognos_torch.workflow import forecast, load_model, load_series, rul
        d = {str(tmp_path)!r}
        s = load_series(np.load(d + "/x.npy"), time=np.load(d + "/t.npy"))
        model = load_model(d + "/model.pt")
        fc = forecast(model, s, 15)
        r = rul(model, s, 1.8, horizon=40, filter="ekpf", n_particles=40, filter_steps=10, seed=2)
        print(json.dumps({{"mean": fc.mean.tolist(), "lower": fc.lower.tolist(),
                          "upper": fc.upper.tolist(), "pmf": r.distribution.pmf.tolist()}}))
        """
    )
    out = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, check=True, timeout=120
    )
    got = json.loads(out.stdout.strip().splitlines()[-1])
    for k in ("mean", "lower", "upper"):
        assert torch.equal(torch.tensor(got[k], dtype=torch.float64), getattr(fc, k))
    assert torch.equal(torch.tensor(got["pmf"], dtype=torch.float64), r.distribution.pmf)


def test_load_series_date_times_zones_fractions_and_duplicate_columns(tmp_path):
    """A zone designator is applied (the same instants as in UTC), the start keeps its fraction
    of a second (until= used to count from the start truncated to the second), date-times
    outside 1678-2262 are refused (nanoseconds wrap there), and a column named twice is an
    error instead of a silent choice."""
    from prognos_torch.workflow.times import datetime_ns

    assert datetime_ns("2024-01-01T01:30:00+01:30") == datetime_ns("2024-01-01T00:00:00Z")
    assert datetime_ns("2024-01-01 00:00:00-0500") == datetime_ns("2024-01-01T05:00:00")
    for bad in ("9999-12-31", "1500-01-01T00:00", "17", "noon"):
        with pytest.raises(ValueError):
            datetime_ns(bad)
    p = tmp_path / "frac.csv"
    p.write_text(
        "t,v\n" + "".join(f"2024-01-01T00:00:{0.9 + 0.1 * k:06.3f},{k}\n" for k in range(30))
    )
    s = load_series(p, column="v", time_column="t", until="2024-01-01T00:00:01.000")
    assert s.start == "2024-01-01T00:00:00.900" and len(s) == 2
    z = tmp_path / "zone.csv"
    z.write_text(
        "t,v\n"
        + "".join(f"2024-01-01T0{1 + k // 60}:{k % 60:02d}:00+01:00,{k}\n" for k in range(30))
    )
    u = tmp_path / "utc.csv"
    u.write_text("t,v\n" + "".join(f"2024-01-01T00:{k % 60:02d}:00,{k}\n" for k in range(30)))
    a, b = load_series(z, column="v", time_column="t"), load_series(u, column="v", time_column="t")
    assert torch.equal(a.t, b.t) and a.start == b.start == "2024-01-01T00:00:00"
    for bad in ("nan", "inf", "-inf"):
        with pytest.raises(ValueError, match="until must be finite"):
            load_series(u, column="v", time_column="t", until=bad)
    d = tmp_path / "dup.csv"
    d.write_text("t,v,v\n" + "".join(f"{k},{k},{2 * k}\n" for k in range(30)))
    with pytest.raises(ValueError, match="'v' appears more than once"):
        load_series(d, column="v", time_column="t")


def test_figures_of_a_dated_series_put_dates_on_the_time_axis(tmp_path):
    # a planner reads dates: the axis keeps days since the first date-time as data, its ticks
    # fall on round dates and say which, the title gives the prediction's date-time
    from prognos_torch.plots import plot_prognosis
    from prognos_torch.workflow import prognose
    from prognos_torch.workflow.times import date_after

    g = torch.Generator().manual_seed(3)
    n = 240  # hourly for ten days, wear from day 5
    days = torch.arange(n, dtype=torch.float64) / 24
    y = 1.0 + 0.02 * torch.randn(n, generator=g, dtype=torch.float64)
    y = y + torch.where(days > 5, torch.exp(0.8 * (days - 5)) - 1, torch.zeros(()))
    stamps = np.datetime64("2004-02-12T10:32:39") + (days.numpy() * 3600 * 24).astype(
        "timedelta64[s]"
    )
    r = prognose(y, 60.0, time=stamps)
    assert r.status == "ok" and r.history.start == "2004-02-12T10:32:39"
    fig = plot_prognosis(tmp_path / "p.png", r)
    top, pmf = fig.axes
    fig.canvas.draw()
    assert top.get_xlabel() == "date (UTC)"
    assert top.get_title().startswith(f"at {r.history.date(r.t_last)} UTC: median RUL")
    ticks = top.get_xticks()
    labels = [t.get_text() for t in top.get_xticklabels()]
    t0, t1 = top.get_xlim()
    inside = [(v, s) for v, s in zip(ticks, labels) if t0 <= v <= t1]
    assert len(inside) >= 3
    for v, text in inside:
        when = date_after(r.history.start, float(v), "s")
        assert when.endswith("T00:00:00") or when.endswith(":00:00")  # a round date-time
        if when.endswith("T00:00:00"):  # a day's tick names its day (or month)
            assert text in (when[8:10], "Feb", "Mar"), (when, text)
    assert top.xaxis.get_offset_text().get_text().startswith("2004-")
    s = r.summary()  # the pmf's legend: a quantile beyond the horizon reads "> bound"
    q = [f"> {r.bound:.3g}" if s[k] is None else f"{s[k]:.3g}" for k in ("q05", "q95")]
    assert f"90 % [{q[0]}, {q[1]}]" in pmf.texts[0].get_text()
    # the JSON-safe record: the summary's numbers and the dates of its quantiles
    import json

    rec = json.loads(json.dumps(r.to_dict(), allow_nan=False))
    assert rec["status"] == "ok" and rec["date"] == date_after(r.history.start, r.t_last, "s")
    assert rec["filter"] == r.filter.lower() == "ekf"  # as filter= names it (it read "EKF")
    for k in ("mean", "median", "q05", "q95", "censored_mass", "bound"):
        assert rec["rul"][k] == s[k], k
    for k, q in (("q05", 0.05), ("median", 0.5), ("q95", 0.95)):
        v = float(r.quantile(q))
        want = None if math.isnan(v) else date_after(r.history.start, r.t_last + v, "s")
        assert rec["failure_date"][k] == want, k
    assert rec["failure_date"]["bound"] == date_after(r.history.start, r.t_last + r.bound, "s")
    on = rec["onset"]
    assert on["detected"] and on["time"] == r.onset.time and on["method"] == "ksigma"
    assert on["date"] == date_after(r.history.start, r.onset.time, "s")
    assert on["baseline"]["n"] == r.onset.baseline.n and rec["flags"] == list(r.flags)
    # numeric time keeps its numbers and its name
    plain = prognose(y, 60.0, time=days)
    top = plot_prognosis(tmp_path / "q.png", plain).axes[0]
    top.figure.canvas.draw()
    assert top.get_xlabel() == "time" and top.get_title().startswith(f"at t = {plain.t_last:g}:")
    assert float(top.get_xticklabels()[1].get_text().replace("−", "-")) == top.get_xticks()[1]


def test_dates_far_beyond_2262_are_given_and_beyond_292000_years_are_none():
    # nanosecond date-times end in 2262: a RUL or horizon of a few centuries raised an
    # OverflowError in every dated report; the date is held in microseconds now
    from prognos_torch.fleet.run import _dates
    from prognos_torch.workflow.times import date_after

    start = "2004-02-12T10:32:39"
    assert date_after(start, 1e5, "s") == "2277-11-27T10:32:39"  # NumPy's days, below
    assert np.datetime64(start) + np.timedelta64(100_000, "D") == np.datetime64(
        "2277-11-27T10:32:39"
    )
    assert date_after(start, 1e6, "s") == str(
        np.datetime64(start, "s") + np.timedelta64(10**6, "D")
    )
    assert date_after(start, 1e9, "s") is None and date_after(start, -1e9, "s") is None
    s = load_series(
        np.arange(3.0), time=np.datetime64(start) + np.arange(3).astype("timedelta64[D]")
    )
    assert s.date(1e6) == date_after(start, 1e6, "s") and s.date(1e9) is None
    assert _dates(start, [1.0, math.nan, 1e9]) == ["2004-02-13T10:32:39", "", ""]


def test_refit_trains_the_written_model_on_every_value_and_keeps_the_scores():
    """refit=True: the held-out scores of the model of the training part, and the model of
    every value (the same m, options and seed), which a plain holdout=0 fit equals."""
    t, x = _series_values(120)
    s = load_series(x, time=t)
    scored = fit_series(s, "elm", None, None)
    full = fit_series(s, "elm", None, None, refit=True)
    ref = fit_series(s, "elm", None, scored.m, holdout=0)
    assert full.m == scored.m and full.metrics == scored.metrics and full.config["refit"]
    assert full.config["series"]["n_train"] == 120 and full.config["m_selection"] is not None
    for a, b in zip(full.learner.parameters(), ref.learner.parameters()):
        assert torch.equal(a, b)
    assert float(full.scaler.data_max) == float(ref.scaler.data_max) == float(x.max())
    with pytest.raises(TypeError, match="refit must be a bool"):
        fit_series(s, "elm", None, 3, refit="yes")
