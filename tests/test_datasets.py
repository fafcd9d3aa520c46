"""Tests of prognos_torch.datasets: IMS reader and table, LLE, health indicator, windows."""

from __future__ import annotations

import io
import math
import os
import warnings
from datetime import datetime, timedelta

import numpy as np
import pytest
import scipy.linalg
import scipy.stats
import torch

from prognos_torch.datasets import (
    FEATURE_NAMES,
    HI_FEATURES,
    PAPER_FEATURES,
    IMSFormatError,
    MinMaxScaler,
    bearing_channels,
    chronological_split,
    default_data_dir,
    embed,
    health_indicator,
    knn,
    lle_cost_matrix,
    lle_fit,
    load_ims_features,
    one_step_pairs,
    read_raw_features,
    reconstruction_weights,
    shift_append,
)
from prognos_torch.datasets import ims as ims_module

DATA = default_data_dir()
START = datetime(2003, 10, 22, 12, 6, 24)


# --------------------------------------------------------------------------- helpers


def _name(t: datetime) -> str:
    return t.strftime("%Y.%m.%d.%H.%M.%S")


def _write_snapshots(folder, n_files, n_rows, n_channels, seed=0, step_min=10, sep="\t"):
    """Synthetic IMS-like snapshots (values quantised to 0.001 g, DC offset, impulsive noise)."""
    rng = np.random.default_rng(seed)
    data = {}
    for i in range(n_files):
        x = -0.09 + 0.08 * rng.standard_normal((n_rows, n_channels))
        x += 0.3 * rng.standard_normal((n_rows, n_channels)) * (rng.random((n_rows, 1)) < 0.02)
        x = np.round(x, 3)
        name = _name(START + timedelta(minutes=step_min * i))
        text = "\n".join(sep.join(f"{v:.3f}" for v in row) for row in x) + "\n"
        (folder / name).write_text(text)
        data[name] = x
    return data


def _reference_features(x: np.ndarray) -> np.ndarray:
    """Independent NumPy/SciPy reference, (C, 9) in FEATURE_NAMES order."""
    n = x.shape[0]
    std = np.std(x, axis=0, ddof=1)
    rms = np.sqrt(np.mean(x**2, axis=0))
    peak = np.max(np.abs(x), axis=0)
    return np.stack(
        [
            np.mean(x, axis=0),
            np.median(x, axis=0),
            std,
            scipy.stats.skew(x, axis=0),
            rms,
            std / np.sqrt(n),
            scipy.stats.kurtosis(x, axis=0, fisher=False),
            peak,
            peak / rms,
        ],
        axis=1,
    )


def _reference_lle(X: np.ndarray, k: int, reg: float, n_eig: int = 3):
    """Loop-by-loop NumPy LLE (Roweis & Saul): weights (n, n), M and the n_eig bottom eigenpairs
    from a dense LAPACK eigensolver."""
    n = X.shape[0]
    W = np.zeros((n, n))
    for i in range(n):
        d = np.sqrt(((X - X[i]) ** 2).sum(1))
        d[i] = np.inf
        nb = np.argsort(d, kind="stable")[:k]
        Z = X[nb] - X[i]
        C = Z @ Z.T
        C += np.eye(k) * reg * np.trace(C)
        w = np.linalg.solve(C, np.ones(k))
        W[i, nb] = w / w.sum()
    IW = np.eye(n) - W
    M = IW.T @ IW
    evals, evecs = scipy.linalg.eigh(M, subset_by_index=[0, n_eig - 1], driver="evx")
    return W, M, evals, evecs


# --------------------------------------------------------------------------- raw reader


@pytest.mark.parametrize("test, n_channels", [(1, 8), (2, 4)])
def test_raw_features_match_numpy_scipy_reference(tmp_path, test, n_channels):
    data = _write_snapshots(tmp_path, n_files=3, n_rows=300, n_channels=n_channels)
    feats = read_raw_features(tmp_path, test=test, cache=False)
    names = sorted(data)
    assert feats.values.shape == (3, n_channels, len(FEATURE_NAMES))
    assert feats.values.dtype == torch.float64
    assert feats.channels == tuple(range(1, n_channels + 1))
    assert feats.feature_names == FEATURE_NAMES
    assert feats.skipped == ()
    for t, name in enumerate(names):
        ref = _reference_features(data[name])
        np.testing.assert_allclose(feats.values[t].numpy(), ref, rtol=1e-12, atol=1e-15)
    # 10 minutes between snapshots, days since the first one.
    np.testing.assert_allclose(feats.days.numpy(), np.arange(3) * 10 / 1440, rtol=0, atol=1e-15)
    assert feats.days.dtype == torch.float64
    assert str(feats.timestamps[0]) == "2003-10-22T12:06:24"


def test_raw_reader_subset_order_and_space_separator(tmp_path):
    data = _write_snapshots(tmp_path, n_files=4, n_rows=64, n_channels=8, sep="  ")
    names = sorted(data)
    feats = read_raw_features(tmp_path, files=[names[3], names[1]], cache=False)
    assert len(feats) == 2  # sorted by time, not by the order given
    np.testing.assert_allclose(
        feats.values[0].numpy(), _reference_features(data[names[1]]), rtol=1e-12
    )
    np.testing.assert_allclose(float(feats.days[1]), 20 / 1440, rtol=1e-15)


def test_raw_reader_cache_is_identical_and_skips_parsing(tmp_path, monkeypatch):
    raw = tmp_path / "raw"
    raw.mkdir()
    data = _write_snapshots(raw, n_files=3, n_rows=128, n_channels=8, seed=3)
    first = read_raw_features(raw)
    cache_file = raw / ".prognos_ims_test1_features_cache.npz"
    assert cache_file.is_file()

    def no_parsing(*args, **kwargs):
        raise AssertionError("cached snapshot was parsed again")

    monkeypatch.setattr(ims_module, "read_snapshot", no_parsing)
    second = read_raw_features(raw)  # the cache file itself is not reported as skipped
    assert torch.equal(first.values, second.values)
    assert np.array_equal(first.timestamps, second.timestamps)
    assert second.skipped == ()
    monkeypatch.undo()

    # A changed file (new size and mtime) is read again; the others come from the cache.
    name = sorted(data)[1]
    x = data[name][:100] * 2
    (raw / name).write_text("\n".join("\t".join(f"{v:.3f}" for v in r) for r in x) + "\n")
    os.utime(raw / name, ns=(10**18, 10**18))
    third = read_raw_features(raw)
    np.testing.assert_allclose(third.values[1].numpy(), _reference_features(x), rtol=1e-12)
    assert torch.equal(third.values[0], first.values[0])

    # An explicit cache path; cache=False writes nothing.
    other = tmp_path / "elsewhere.npz"
    read_raw_features(raw, cache=other)
    assert other.is_file()
    fresh = tmp_path / "fresh"
    fresh.mkdir()
    _write_snapshots(fresh, n_files=1, n_rows=16, n_channels=8)
    read_raw_features(fresh, cache=False)
    assert sorted(p.name for p in fresh.iterdir()) == [_name(START)]


def test_raw_features_csv_round_trip_in_shipped_format(tmp_path):
    raw = tmp_path / "raw"
    raw.mkdir()
    data = _write_snapshots(raw, n_files=2, n_rows=200, n_channels=4)
    feats = read_raw_features(raw, test=2, cache=False)
    out = tmp_path / "test2_features.csv"
    feats.to_csv(out)
    lines = out.read_text().splitlines()
    shipped_header = (DATA / "test1_features.csv").read_text().splitlines()[0]
    assert lines[0] == shipped_header
    assert len(lines) == 1 + 2 * 4
    assert lines[1].startswith("2003-10-22T12:06:24,1,")
    back = load_ims_features(test=2, path=tmp_path)
    ref = np.stack([_reference_features(data[n]) for n in sorted(data)])
    np.testing.assert_allclose(back.values.numpy(), ref, rtol=1e-8)


def test_raw_reader_wrong_column_count_names_file_and_line(tmp_path):
    _write_snapshots(tmp_path, n_files=2, n_rows=20, n_channels=8)
    bad = tmp_path / _name(START + timedelta(minutes=30))
    rows = ["\t".join(["0.1"] * 8)] * 4 + ["\t".join(["0.1"] * 7)] + ["\t".join(["0.1"] * 8)]
    bad.write_text("\n".join(rows) + "\n")
    with pytest.raises(IMSFormatError, match=rf"{bad.name}, line 5: 7 columns, expected 8"):
        read_raw_features(tmp_path, cache=False)
    # A whole file with the test-2 layout read as test 1.
    four = tmp_path / "four"
    four.mkdir()
    _write_snapshots(four, n_files=1, n_rows=10, n_channels=4)
    with pytest.raises(IMSFormatError, match="line 1: 4 columns, expected 8"):
        read_raw_features(four, test=1, cache=False)


def test_raw_reader_non_numeric_line_and_skip_mode(tmp_path):
    data = _write_snapshots(tmp_path, n_files=2, n_rows=20, n_channels=4)
    bad = tmp_path / _name(START + timedelta(minutes=5))
    rows = ["\t".join(["0.1"] * 4)] * 2 + ["0.1\tabc\t0.2\t0.3"] + ["\t".join(["0.2"] * 4)]
    bad.write_text("\n".join(rows) + "\n")
    (tmp_path / "README.txt").write_text("not a snapshot")
    with pytest.raises(IMSFormatError, match=r"line 3: non-numeric value 'abc' in column 2"):
        read_raw_features(tmp_path, test=2, cache=False)
    with pytest.warns(UserWarning, match=r"skipped 1 unreadable snapshot"):
        feats = read_raw_features(tmp_path, test=2, cache=False, on_error="skip")
    assert len(feats) == 2
    assert [str(t) for t in feats.timestamps] == [
        str(np.datetime64(datetime.strptime(n, "%Y.%m.%d.%H.%M.%S"), "s")) for n in sorted(data)
    ]
    reasons = {os.path.basename(s.path): s.reason for s in feats.skipped}
    assert "line 3" in reasons[bad.name]
    assert "not a snapshot" in reasons["README.txt"]


def test_raw_reader_non_finite_and_row_count(tmp_path):
    bad = tmp_path / _name(START)
    bad.write_text("0.1\t0.2\t0.3\t0.4\n0.1\tnan\t0.3\t0.4\n")
    with pytest.raises(IMSFormatError, match=r"line 2: non-finite value 'nan' in column 2"):
        read_raw_features(tmp_path, test=3, cache=False)
    bad.write_text("0.1\t0.2\t0.3\t0.4\n0.5\t0.2\t0.3\t0.4\n")
    with pytest.raises(IMSFormatError, match="2 sample rows, expected 20480"):
        read_raw_features(tmp_path, test=3, cache=False, expected_samples=20480)
    bad.write_text("")
    with pytest.raises(IMSFormatError, match="no samples"):
        read_raw_features(tmp_path, test=3, cache=False)


def test_raw_reader_bad_arguments(tmp_path):
    with pytest.raises(FileNotFoundError, match="directory not found"):
        read_raw_features(tmp_path / "nope")
    with pytest.raises(FileNotFoundError, match="no snapshot files"):
        read_raw_features(tmp_path, cache=False)
    _write_snapshots(tmp_path, n_files=1, n_rows=8, n_channels=8)
    with pytest.raises(FileNotFoundError, match="2003.10.22.12.16.24"):
        read_raw_features(tmp_path, files=["2003.10.22.12.16.24"], cache=False)
    (tmp_path / "notes").write_text("x")
    with pytest.raises(ValueError, match="not a snapshot name"):
        read_raw_features(tmp_path, files=["notes"], cache=False)
    with pytest.raises(ValueError, match="test must be one of"):
        read_raw_features(tmp_path, test=4)
    with pytest.raises(ValueError, match="on_error"):
        read_raw_features(tmp_path, on_error="ignore")


# --------------------------------------------------------------------------- shipped table


@pytest.fixture(scope="module")
def test1():
    return load_ims_features(1)


def test_shipped_table_shape_time_and_conventions(test1):
    assert test1.values.shape == (2156, 8, 9)
    assert test1.values.dtype == torch.float64 and test1.days.dtype == torch.float64
    assert str(test1.timestamps[0]) == "2003-10-22T12:06:24"
    assert str(test1.timestamps[-1]) == "2003-11-25T23:39:56"
    expected_span = (datetime(2003, 11, 25, 23, 39, 56) - START).total_seconds() / 86400
    assert float(test1.days[0]) == 0.0
    assert math.isclose(float(test1.days[-1]), expected_span, rel_tol=1e-15)
    assert 34.4 < expected_span < 34.6
    assert bool((torch.diff(test1.days) > 0).all())
    # Median empty in the shipped table; everything else present.
    assert bool(torch.isnan(test1.feature("median")).all())
    others = [n for n in FEATURE_NAMES if n != "median"]
    assert bool(torch.isfinite(test1.select(others).values).all())
    # Table-internal identities of the README conventions (9 significant digits).
    torch.testing.assert_close(
        test1.feature("std_error"), test1.feature("std") / math.sqrt(20480), rtol=2e-8, atol=0
    )
    torch.testing.assert_close(
        test1.feature("crest_factor"),
        test1.feature("peak") / test1.feature("rms"),
        rtol=2e-8,
        atol=0,
    )
    # README: test 1 ends on its highest bearing-3 rms, 0.594 g on channel 5.
    rms5 = test1.feature("rms")[:, 4]
    assert int(rms5.argmax()) == 2155 and abs(float(rms5[-1]) - 0.594) < 5e-4
    # README: the last 12 days hold 1,263 snapshots.
    assert len(test1.last_days(12.0)) == 1263


def test_shipped_table_bearing_and_feature_selection(test1):
    b3 = test1.bearing(3)
    assert b3.channels == (5, 6) and b3.values.shape == (2156, 2, 9)
    torch.testing.assert_close(b3.values, test1.values[:, 4:6], rtol=0, atol=0, equal_nan=True)
    sub = b3.select(["rms", "kurtosis"])
    assert sub.feature_names == ("rms", "kurtosis")
    assert torch.equal(sub.values[:, :, 0], test1.values[:, 4:6, 4])
    torch.testing.assert_close(test1.channel(6), test1.values[:, 5], rtol=0, atol=0, equal_nan=True)
    assert bearing_channels(1, 4) == (7, 8) and bearing_channels(2, 4) == (4,)
    with pytest.raises(ValueError, match="bearing must be 1, 2, 3 or 4"):
        test1.bearing(5)
    with pytest.raises(ValueError, match="unknown feature 'energy'"):
        test1.select(["energy"])
    with pytest.raises(ValueError, match="channel must be one of"):
        b3.channel(1)
    with pytest.raises(ValueError, match="test must be one of"):
        load_ims_features(4)
    with pytest.raises(FileNotFoundError, match="not found"):
        load_ims_features(2, path=DATA / "nowhere")
    with pytest.raises(FileNotFoundError):
        load_ims_features(1, path=DATA / "missing.csv")


def test_ims_table_snapshots_are_in_time_order_however_their_date_times_are_written(tmp_path):
    """Snapshots were ordered by their text: '2004-02-12 12:02:39' (a space) sorted before
    every '...T...' stamp, giving negative days; an empty stamp became a NaT snapshot; one
    instant written two ways passed the duplicate check."""
    lines = (DATA / "test2_features.csv").read_text().splitlines()
    head, rows = lines[0], lines[1:41]  # 10 snapshots x 4 channels
    last = rows[36].split(",")[0]
    spaced = [r.replace(last, last.replace("T", " ")) for r in rows]
    path = tmp_path / "t.csv"
    path.write_text("\n".join([head, *spaced]) + "\n")
    got = load_ims_features(2, path=path)
    ref_path = tmp_path / "ref.csv"
    ref_path.write_text("\n".join([head, *rows]) + "\n")
    ref = load_ims_features(2, path=ref_path)
    assert np.array_equal(got.timestamps, ref.timestamps) and bool((np.diff(got.days) > 0).all())
    torch.testing.assert_close(got.values, ref.values, rtol=0, atol=0, equal_nan=True)
    twice = [*rows, rows[0].replace("T", " ")]
    path.write_text("\n".join([head, *twice]) + "\n")
    with pytest.raises(ValueError, match=r"line 42: duplicate row 2004-02-12T10:32:39 channel 1 "
                       r"\(written '2004-02-12 10:32:39' here\)"):  # fmt: skip
        load_ims_features(2, path=path)
    for bad in ("", "NaT", "12/02/2004"):
        path.write_text("\n".join([head, *rows, bad + rows[0][len(rows[0].split(",")[0]):]])
                        + "\n")  # fmt: skip
        with pytest.raises(ValueError, match=f"line 42: timestamp {bad!r} is not an ISO 8601"):
            load_ims_features(2, path=path)


def test_shipped_tests_2_and_3():
    for test, n in ((2, 984), (3, 6324)):
        f = load_ims_features(test)
        assert f.values.shape == (n, 4, len(f.feature_names)) and f.channels == (1, 2, 3, 4)
        assert bool(torch.isfinite(f.feature("rms")).all())


def test_first50_from_raw_agrees_with_shipped_table(test1):
    raw50 = load_ims_features(1, path=DATA / "test1_first50_from_raw.csv")
    assert raw50.values.shape == (50, 8, 9)
    assert np.array_equal(raw50.timestamps, test1.timestamps[:50])
    keep = [n for n in FEATURE_NAMES if n != "median"]
    # Identical to 9 significant digits, hence identical after parsing.
    assert torch.equal(raw50.select(keep).values, test1.select(keep).values[:50])
    median, mean = raw50.feature("median"), raw50.feature("mean")
    assert bool(torch.isfinite(median).all())
    assert float((median - mean).abs().max()) < 0.01  # a near-copy of the mean (README)


def test_load_rejects_malformed_tables(tmp_path):
    good = (DATA / "test1_first50_from_raw.csv").read_text().splitlines()
    path = tmp_path / "t.csv"
    path.write_text("\n".join(good[:1] + good[2:9]) + "\n")  # first snapshot lacks channel 1
    with pytest.raises(ValueError, match="no row for 2003-10-22T12:06:24 channel 1"):
        load_ims_features(1, path=path)
    path.write_text("\n".join(good[:10] + good[2:3]) + "\n")
    with pytest.raises(ValueError, match="duplicate row"):
        load_ims_features(1, path=path)
    path.write_text("\n".join(good[:9]).replace("0.72,", "oops,") + "\n")
    with pytest.raises(ValueError, match="line 2"):
        load_ims_features(1, path=path)
    path.write_text("a,b\n")
    with pytest.raises(ValueError, match="header"):
        load_ims_features(1, path=path)


# --------------------------------------------------------------------------- LLE


def _curve(t: np.ndarray) -> np.ndarray:
    """A 1-D curve in 3-D (a helix segment with a drift): arc length grows with t."""
    return np.stack([np.cos(t), np.sin(t), 0.5 * t], axis=1)


def test_lle_weights_cost_matrix_and_embedding_match_numpy_reference():
    rng = np.random.default_rng(1)
    t = np.sort(rng.uniform(0, 3 * np.pi, 120))
    X = _curve(t) + 1e-3 * rng.standard_normal((120, 3))
    k, reg = 8, 1e-3
    W_ref, M_ref, evals_ref, evecs_ref = _reference_lle(X, k, reg)
    Xt = torch.as_tensor(X)
    fit = lle_fit(Xt, n_components=2, n_neighbors=k, reg=reg)
    # Reconstruction weights sum to one and equal the reference.
    torch.testing.assert_close(fit.weights.sum(1), torch.ones(120, dtype=torch.float64))
    W = torch.zeros(120, 120, dtype=torch.float64).scatter_(1, fit.neighbors, fit.weights)
    np.testing.assert_allclose(W.numpy(), W_ref, rtol=1e-9, atol=1e-12)
    M = lle_cost_matrix(fit.neighbors, fit.weights, 120)
    np.testing.assert_allclose(M.numpy(), M_ref, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(fit.eigenvalues.numpy(), evals_ref[:3], rtol=1e-6, atol=1e-12)
    # Embedding = sqrt(n) * bottom eigenvectors after the constant one (up to sign).
    for j in range(2):
        ref = evecs_ref[:, j + 1] * math.sqrt(120)
        got = fit.embedding[:, j].numpy()
        sign = np.sign(got @ ref)
        np.testing.assert_allclose(sign * got, ref, rtol=1e-6, atol=1e-6)
    Y = fit.embedding
    torch.testing.assert_close(Y.T @ Y / 120, torch.eye(2, dtype=torch.float64))
    # Orthogonal to the constant null vector (up to the eigensolver's accuracy at a 1e-9 gap).
    assert float(Y.mean(0).abs().max()) < 1e-5
    # Deterministic sign: the largest-magnitude entry of each column is positive.
    assert bool((Y.gather(0, Y.abs().argmax(0, keepdim=True)) > 0).all())


def test_lle_recovers_curve_parameter_monotonically_and_maps_new_points():
    rng = np.random.default_rng(2)
    t = rng.uniform(0, 3 * np.pi, 200)
    fit = lle_fit(torch.as_tensor(_curve(t)), n_components=1, n_neighbors=10)
    y = fit.embedding[:, 0].numpy()
    order = np.argsort(t)
    steps = np.diff(y[order])
    assert (steps > 0).all() or (steps < 0).all()  # strictly monotone in the curve parameter
    # Out-of-sample: held-out points inside the range map monotonically as well ...
    t_new = np.linspace(0.5, 3 * np.pi - 0.5, 50)
    y_new = fit.transform(torch.as_tensor(_curve(t_new)))[:, 0].numpy()
    d = np.diff(y_new) * np.sign(steps[0])
    assert (d > 0).all()
    # ... and equal the independent rule: neighbours, weights, weighted embedding.
    Xr = _curve(t)
    for i in (0, 17, 49):
        x = _curve(t_new[i : i + 1])[0]
        nb = np.argsort(np.sqrt(((Xr - x) ** 2).sum(1)), kind="stable")[:10]
        Z = Xr[nb] - x
        C = Z @ Z.T + np.eye(10) * 1e-3 * np.trace(Z @ Z.T)
        w = np.linalg.solve(C, np.ones(10))
        w /= w.sum()
        assert math.isclose(y_new[i], w @ y[nb], rel_tol=1e-9, abs_tol=1e-12)


def test_lle_solvers_agree_and_bad_inputs():
    rng = np.random.default_rng(4)
    X = torch.as_tensor(_curve(np.sort(rng.uniform(0, 6, 60))))
    a = lle_fit(X, n_neighbors=6, eigen_solver="scipy").embedding
    b = lle_fit(X, n_neighbors=6, eigen_solver="torch").embedding
    torch.testing.assert_close(a, b, rtol=1e-6, atol=1e-6)
    nb = knn(X, None, 6)
    assert not bool((nb == torch.arange(60)[:, None]).any())  # a point is not its own neighbour
    w = reconstruction_weights(X, nb)
    torch.testing.assert_close(w.sum(1), torch.ones(60, dtype=torch.float64))
    with pytest.raises(ValueError, match="n_neighbors=60 exceeds"):
        lle_fit(X, n_neighbors=60)
    with pytest.raises(ValueError, match=r"shape \(n, D\)"):
        lle_fit(X[:, 0])
    with pytest.raises(ValueError, match="non-finite"):
        lle_fit(torch.full((10, 2), float("nan")))
    with pytest.raises(ValueError, match="eigen_solver"):
        lle_fit(X, n_neighbors=6, eigen_solver="arpack")
    with pytest.raises(ValueError, match=r"X_new must have shape \(m, 3\)"):
        lle_fit(X, n_neighbors=6).transform(X[:, :2])


def test_lle_warns_on_disconnected_neighbourhood_graph():
    rng = np.random.default_rng(5)
    X = np.concatenate([rng.normal(0, 0.1, (30, 2)), rng.normal(100, 0.1, (30, 2))])
    with pytest.warns(RuntimeWarning, match="2 connected components"):
        lle_fit(torch.as_tensor(X), n_neighbors=5)


def test_lle_follows_float32_dtype():
    rng = np.random.default_rng(6)
    X = torch.as_tensor(_curve(np.sort(rng.uniform(0, 6, 40))), dtype=torch.float32)
    fit = lle_fit(X, n_neighbors=6)
    assert fit.embedding.dtype == torch.float32 and fit.weights.dtype == torch.float32


@pytest.mark.parametrize("scale", [2.0**-560, 2.0**530])
def test_lle_does_not_depend_on_the_scale_of_the_points(scale):
    # LLE is scale invariant, and a power of two scales every product exactly: neighbours,
    # weights and embedding must equal the unscaled fit's bit for bit. At 2^-560 (1e-169) the
    # squared distances and the local Gram matrices underflow to 0, at 2^530 (1e160) they
    # overflow.
    rng = np.random.default_rng(8)
    X = torch.as_tensor(_curve(np.sort(rng.uniform(0, 6, 40))))
    ref = lle_fit(X, n_neighbors=6)
    got = lle_fit(X * scale, n_neighbors=6)
    assert torch.equal(got.neighbors, ref.neighbors)
    assert torch.equal(got.weights, ref.weights)
    assert torch.equal(got.embedding, ref.embedding)
    assert torch.equal(got.transform(X[:5] * scale), ref.transform(X[:5]))


def test_lle_with_duplicate_samples_breaks_distance_ties_by_index():
    # every point twice: a point's twin lies at distance 0 (singular local Gram matrices, the
    # regulariser must carry them) and every other neighbour comes as two tied copies; the
    # neighbours, weights and M are those of the loop reference with a stable sort (lowest
    # index first among equal distances)
    rng = np.random.default_rng(9)
    P = _curve(np.sort(rng.uniform(0, 6, 15)))
    X = np.concatenate([P, P])
    d = np.sqrt(((X[:, None] - X[None]) ** 2).sum(-1))
    np.fill_diagonal(d, np.inf)
    nb_ref = np.argsort(d, axis=1, kind="stable")[:, :5]
    nb = knn(torch.as_tensor(X), None, 5)
    assert nb.tolist() == nb_ref.tolist()
    W_ref, M_ref, _, _ = _reference_lle(X, 5, 1e-3)
    w = reconstruction_weights(torch.as_tensor(X), nb)
    W = torch.zeros(30, 30, dtype=torch.float64).scatter_(1, nb, w)
    np.testing.assert_allclose(W.numpy(), W_ref, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(lle_cost_matrix(nb, w, 30).numpy(), M_ref, rtol=1e-9, atol=1e-9)


def test_lle_sign_does_not_depend_on_rounding_between_tied_extremes():
    # evenly spaced points on a line: the embedding is odd about the middle, its two ends equal
    # in magnitude up to rounding, which decided the sign (the scipy and torch solvers
    # disagreed); the first of the (nearly) tied largest entries is made positive
    for n in (21, 31):
        t = np.linspace(0.0, 1.0, n)
        X = np.stack([t, 2 * t, -t], 1)
        got = lle_fit(torch.as_tensor(X), n_neighbors=4).embedding[:, 0].numpy()
        _, _, _, evecs = _reference_lle(X, 4, 1e-3)  # another LAPACK driver (evx)
        ref = evecs[:, 1] * math.sqrt(n)
        assert abs(abs(ref[0]) - abs(ref[-1])) < 1e-6 * abs(ref[0])  # tied extremes
        np.testing.assert_allclose(got, np.sign(ref[0]) * ref, rtol=1e-6, atol=1e-6)
        assert got[0] > 0


def test_lle_reg_must_be_a_finite_positive_number():
    rng = np.random.default_rng(10)
    X = torch.as_tensor(_curve(np.sort(rng.uniform(0, 6, 20))))
    nb = knn(X, None, 4)
    with pytest.raises(ValueError, match="reg must be a finite number, got inf"):
        reconstruction_weights(X, nb, reg=float("inf"))  # it gave NaN weights
    with pytest.raises(ValueError, match="reg must be a finite number, got True"):
        lle_fit(X, n_neighbors=4, reg=True)  # it was taken as 1
    with pytest.raises(ValueError, match="reg must be a positive float, got 0"):
        reconstruction_weights(X, nb, reg=0)
    a = reconstruction_weights(X, nb, reg=np.float32(0.25))  # it was refused
    assert torch.equal(a, reconstruction_weights(X, nb, reg=0.25))


# --------------------------------------------------------------------------- health indicator


@pytest.fixture(scope="module")
def hi(test1):
    return health_indicator(test1)


def test_health_indicator_window_shapes_and_trend(test1, hi):
    window = test1.last_days(12.0)
    assert hi.train.shape == hi.test.shape == hi.days.shape == (1263,)
    assert torch.equal(hi.days, window.days)
    assert hi.train_channel == 5 and hi.test_channel == 6
    assert hi.feature_names == HI_FEATURES and "median" not in hi.feature_names
    # The 12-day window opens inside the 3.8-day recording gap that ends on 2003-11-14T11:02.
    assert str(hi.timestamps[0]).startswith("2003-11-14T11:0")
    assert 11.5 < float(hi.elapsed[-1]) <= 12.0
    # Oriented to grow with degradation: positive correlation with rms on both channels.
    rms = window.feature("rms").numpy()
    assert np.corrcoef(hi.train.numpy(), rms[:, 4])[0, 1] > 0.5
    assert np.corrcoef(hi.test.numpy(), rms[:, 5])[0, 1] > 0.5
    # Measured Spearman correlations with time: 0.65 (channel 5) and 0.75 (channel 6).
    rho_train = scipy.stats.spearmanr(hi.days.numpy(), hi.train.numpy())[0]
    rho_test = scipy.stats.spearmanr(hi.days.numpy(), hi.test.numpy())[0]
    assert rho_train > 0.6 and rho_test > 0.6
    # The index at the end of life is far above its early level.
    assert float(hi.train[-10:].mean()) > float(hi.train[:200].mean()) + 2 * float(
        hi.train[:200].std()
    )


def test_health_indicator_equals_numpy_reference_pipeline(test1, hi):
    window = test1.last_days(12.0)
    cols = [FEATURE_NAMES.index(n) for n in HI_FEATURES]
    X = window.values[:, 4][:, cols].numpy()
    Z = (X - X.mean(0)) / X.std(0, ddof=1)
    _, _, evals, evecs = _reference_lle(Z, 12, 1e-3)
    ref = evecs[:, 1] * math.sqrt(len(Z))
    ref *= np.sign(np.corrcoef(ref, X[:, HI_FEATURES.index("rms")])[0, 1])
    np.testing.assert_allclose(hi.train.numpy(), ref, rtol=1e-5, atol=1e-5)
    assert evals[1] > 1e3 * abs(evals[0])  # the one-dimensional coordinate is well separated


def test_health_indicator_separate_mode_and_bad_inputs(test1):
    sep = health_indicator(test1, mode="separate")
    rho = scipy.stats.spearmanr(sep.days.numpy(), sep.test.numpy())[0]
    assert rho > 0.45  # measured 0.52
    with pytest.raises(ValueError, match=r"feature\(s\) \['median'\] have missing values"):
        health_indicator(test1, feature_names=PAPER_FEATURES)
    with pytest.raises(ValueError, match="must differ"):
        health_indicator(test1, train_channel=5, test_channel=5)
    with pytest.raises(ValueError, match="bearing must be"):
        health_indicator(test1, bearing=0)
    with pytest.raises(ValueError, match="mode must be"):
        health_indicator(test1, mode="joint")


# --------------------------------------------------------------------------- windows


def test_embed_matches_eq9_eq10_hand_example():
    x = torch.tensor([1.0, 2.0, 4.0, 8.0, 16.0, 32.0], dtype=torch.float64)
    P, target = embed(x, 3)
    expected = torch.tensor([[1.0, 2, 4], [2, 4, 8], [4, 8, 16]], dtype=torch.float64)
    assert torch.equal(P, expected)
    assert torch.equal(target, torch.tensor([8.0, 16.0, 32.0], dtype=torch.float64))
    P[0, 0] = -1.0  # a fresh tensor, not a view of the series
    assert float(x[0]) == 1.0


def test_embed_vector_series_and_shift_append_recursion():
    g = torch.Generator().manual_seed(0)
    x = torch.randn(20, 3, generator=g, dtype=torch.float64)
    P, target = embed(x, 4)
    assert P.shape == (16, 4, 3) and target.shape == (16, 3)
    for i in range(16):
        assert torch.equal(P[i], x[i : i + 4]) and torch.equal(target[i], x[i + 4])
    # Eq. 12-14: dropping the oldest and appending the next value gives the next window.
    for i in range(15):
        assert torch.equal(shift_append(P[i], target[i], time_dim=-2), P[i + 1])
    s = torch.randn(30, generator=g, dtype=torch.float64)
    Ps, ts = embed(s, 5)
    batch = shift_append(Ps[:-1], ts[:-1])  # batch dims leading, one window per row
    assert torch.equal(batch, Ps[1:])
    assert torch.equal(
        shift_append(torch.tensor([1.0, 2.0, 3.0]), torch.tensor(9.0)), torch.tensor([2.0, 3, 9])
    )


def test_windows_bad_inputs():
    x = torch.arange(5, dtype=torch.float64)
    with pytest.raises(ValueError, match="m=5"):
        embed(x, 5)
    with pytest.raises(ValueError, match="m=9"):
        embed(x, 9)
    with pytest.raises(ValueError, match="embedding dimension m"):
        embed(x, 0)
    with pytest.raises(ValueError, match=r"shape \(T,\) or \(T, d\)"):
        embed(x.reshape(1, 1, 5), 2)
    with pytest.raises(ValueError, match=r"new_value must have shape \(2,\)"):
        shift_append(torch.zeros(2, 4), torch.zeros(4))
    with pytest.raises(ValueError, match="time_dim"):
        shift_append(torch.zeros(4), torch.zeros(()), time_dim=1)


def test_minmax_scaler_formula_inverse_state_and_guards():
    x = torch.tensor([[1.0, -2.0], [3.0, 6.0], [2.0, 0.0]], dtype=torch.float64)
    sc = MinMaxScaler((-1.0, 1.0)).fit(x)
    y = sc.transform(x)
    expected = torch.tensor([[-1.0, -1.0], [1.0, 1.0], [0.0, -0.5]], dtype=torch.float64)
    torch.testing.assert_close(y, expected, rtol=0, atol=1e-15)
    torch.testing.assert_close(sc.inverse_transform(y), x, rtol=0, atol=1e-15)
    # Out of range values are not clipped.
    out = sc.transform(torch.tensor([5.0, -6.0], dtype=torch.float64))  # -1 + (5 - 1) * 2 / 2
    assert out.tolist() == [3.0, -2.0]
    # float32 in, float32 out.
    assert sc.transform(x.float()).dtype == torch.float32
    # State round trip through torch.save(weights_only) without pickling objects.
    buf = io.BytesIO()
    torch.save(sc.state_dict(), buf)
    buf.seek(0)
    other = MinMaxScaler()
    other.load_state_dict(torch.load(buf, weights_only=True))
    assert other.feature_range == (-1.0, 1.0)
    assert torch.equal(other.transform(x), y)
    # A 1-D series has one range.
    s = MinMaxScaler().fit(torch.tensor([2.0, 4.0, 3.0]))
    assert torch.equal(s.transform(torch.tensor([[3.0, 4.0]])), torch.tensor([[0.5, 1.0]]))
    with pytest.raises(ValueError, match=r"column\(s\) \[1\] are constant"):
        MinMaxScaler().fit(torch.tensor([[1.0, 2.0], [3.0, 2.0]]))
    with pytest.raises(ValueError, match="series is constant"):
        MinMaxScaler().fit(torch.ones(4))
    with pytest.raises(RuntimeError, match="not fitted"):
        MinMaxScaler().transform(x)
    with pytest.raises(ValueError, match=r"shape \(\.\.\., 2\)"):
        sc.transform(torch.zeros(3, 3))
    with pytest.raises(ValueError, match="lo < hi"):
        MinMaxScaler((1.0, 0.0))
    with pytest.raises(ValueError, match="missing keys"):
        other.load_state_dict({"data_min": torch.zeros(2)})


def test_chronological_split():
    x = torch.arange(10)
    a, b = chronological_split(x, 0.75)
    assert torch.equal(a, torch.arange(7)) and torch.equal(b, torch.arange(7, 10))
    a, b = chronological_split(np.arange(10), n_train=3)
    assert a.tolist() == [0, 1, 2] and len(b) == 7
    with pytest.raises(ValueError, match="exactly one"):
        chronological_split(x, 0.5, n_train=3)
    with pytest.raises(ValueError, match="n_train=10"):
        chronological_split(x, n_train=10)
    with pytest.raises(ValueError, match="train_fraction"):
        chronological_split(x, 1.5)
    with pytest.raises(ValueError, match="n_train=0"):
        chronological_split(x, 0.05)


def test_one_step_pairs_split_at_the_targets_hand_example():
    # T = 8, m = 3, the first 5 samples hold the training targets x_4, x_5 (1-based)
    x = torch.tensor([1.0, 2, 4, 8, 16, 32, 64, 128], dtype=torch.float64)
    p = one_step_pairs(x, 3, 5)
    assert torch.equal(p.X_train, torch.tensor([[1.0, 2, 4], [2, 4, 8]], dtype=torch.float64))
    assert p.Y_train.tolist() == [[8.0], [16.0]]
    assert p.X_test.tolist() == [[4.0, 8, 16], [8.0, 16, 32], [16.0, 32, 64]]
    assert p.Y_test.tolist() == [[32.0], [64.0], [128.0]]
    assert p.k_test.tolist() == [6, 7, 8]  # 1-based indices of the test targets
    assert torch.equal(x[p.k_test - 1], p.Y_test[:, 0])
    for bad in (3, 8, 2.5):
        with pytest.raises(ValueError, match="n_train"):
            one_step_pairs(x, 3, bad)
    with pytest.raises(ValueError, match=r"shape \(T,\)"):
        one_step_pairs(x.reshape(4, 2), 2, 3)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_lle_and_windows_on_cuda():
    rng = np.random.default_rng(7)
    X = torch.as_tensor(_curve(np.sort(rng.uniform(0, 6, 80))))
    cpu = lle_fit(X, n_neighbors=8)
    gpu = lle_fit(X.cuda(), n_neighbors=8)
    assert gpu.embedding.device.type == "cuda"
    torch.testing.assert_close(gpu.embedding.cpu(), cpu.embedding, rtol=1e-6, atol=1e-6)
    torch.testing.assert_close(gpu.transform(X.cuda()[:5]).cpu(), cpu.transform(X[:5]))
    P, t = embed(X.cuda()[:, 0], 3)
    assert P.device.type == "cuda"
    assert torch.equal(shift_append(P[:-1], t[:-1]), P[1:])
    sc = MinMaxScaler().fit(X)
    assert sc.transform(X.cuda()).device.type == "cuda"


def test_no_warnings_from_a_clean_read(tmp_path):
    _write_snapshots(tmp_path, n_files=2, n_rows=16, n_channels=8)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        read_raw_features(tmp_path)
        read_raw_features(tmp_path)


def test_raw_reader_cache_does_not_bypass_expected_samples(tmp_path):
    """A short snapshot read once (cache filled) was accepted later with expected_samples:
    the cache hit skipped the row count."""
    _write_snapshots(tmp_path, n_files=2, n_rows=30, n_channels=4)
    short = tmp_path / _name(START + timedelta(minutes=20))
    short.write_text("0.1\t0.2\t0.3\t0.4\n0.5\t0.1\t0.2\t0.3\n0.2\t0.4\t0.1\t0.0\n")
    assert len(read_raw_features(tmp_path, test=2)) == 3  # fills the cache
    with pytest.raises(IMSFormatError, match="3 sample rows, expected 30"):
        read_raw_features(tmp_path, test=2, expected_samples=30)
    with pytest.warns(UserWarning, match="skipped 1 unreadable"):
        kept = read_raw_features(tmp_path, test=2, expected_samples=30, on_error="skip")
    assert len(kept) == 2


def test_raw_reader_refuses_one_snapshot_listed_twice(tmp_path):
    """files naming one snapshot twice (or two copies of one time from two folders) gave a
    duplicate snapshot at the same instant: days [0, 0, ...]."""
    data = _write_snapshots(tmp_path, n_files=2, n_rows=20, n_channels=4)
    first = sorted(data)[0]
    with pytest.raises(ValueError, match=rf"files: two files for the snapshot time {first}"):
        read_raw_features(tmp_path, test=2, files=[first, sorted(data)[1], first], cache=False)
    other = tmp_path / "copy"
    other.mkdir()
    (other / first).write_text((tmp_path / first).read_text())
    with pytest.raises(ValueError, match="two files for the snapshot time"):
        read_raw_features(tmp_path, test=2, files=[first, other / first], cache=False)


def test_ims_table_without_rows_or_with_infinite_cells_is_refused(tmp_path):
    """A table holding its header alone gave an empty IMSFeatures (start NaT) that failed later
    (last_days: IndexError); an 'inf' cell became an infinite feature."""
    lines = (DATA / "test2_features.csv").read_text().splitlines()
    path = tmp_path / "t.csv"
    path.write_text(lines[0] + "\n")
    with pytest.raises(ValueError, match=r"t\.csv: the table holds no rows"):
        load_ims_features(2, path=path)
    cells = lines[1].split(",")
    cells[4] = "inf"
    path.write_text("\n".join([lines[0], ",".join(cells), *lines[2:5]]) + "\n")
    with pytest.raises(ValueError, match=r"line 2: non-finite value 'inf' in column 'std'"):
        load_ims_features(2, path=path)


def test_minmax_normalize_of_integer_series_with_given_extremes():
    """lo/hi were cast to the series' integer dtype (0.5 -> 0, 9.5 -> 9): silently other
    numbers; without them an integer series came back in float32. A NaN lo was reported as a
    constant series."""
    from prognos_torch.datasets import minmax_denormalize, minmax_normalize

    x = torch.arange(11)
    ns = minmax_normalize(x, lo=0.5, hi=9.5)
    assert ns.values.dtype == torch.float64
    assert torch.equal(ns.values, (x.double() - 0.5) / 9.0)
    torch.testing.assert_close(minmax_denormalize(ns.values, ns.lo, ns.hi), x.double())
    assert torch.equal(minmax_normalize(x).values, x.double() / 10.0)
    with pytest.raises(ValueError, match="lo must be finite"):
        minmax_normalize(torch.arange(5.0), lo=float("nan"))
    with pytest.raises(ValueError, match=r"hi must broadcast to one row of series \(3,\)"):
        minmax_normalize(torch.ones(4, 3).cumsum(0), hi=torch.ones(2))


def test_pronostia_empty_or_truncated_record_is_named(tmp_path):
    """An empty record raised NumPy's 'input contained no data' warning and then 'got shape
    (0, 1)'; a record cut inside its last row gave NumPy's advice to 'use usecols'."""
    from prognos_torch.datasets import read_pronostia_bearing

    d = tmp_path / "Learning_set" / "Bearing1_1"
    d.mkdir(parents=True)
    x = np.array([[0.1, -0.2], [0.3, 0.1], [-0.2, 0.4]])
    for k in range(2):
        rows = [f"9,39,{39 + 10 * k},{100 * i},{a},{b}" for i, (a, b) in enumerate(x * (k + 1))]
        (d / f"acc_{k + 1:05d}.csv").write_text("\n".join(rows) + "\n")
    ok = read_pronostia_bearing(d, expected_samples=None)
    np.testing.assert_allclose(ok.values[1].numpy(), _reference_features(2 * x), rtol=1e-12)
    (d / "acc_00003.csv").write_text("")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(ValueError, match=r"acc_00003\.csv: the record holds no rows"):
            read_pronostia_bearing(d, expected_samples=None)
    (d / "acc_00003.csv").write_text("9,39,59,0,0.1,0.2\n9,39,59,39,0.1\n")
    with pytest.raises(ValueError, match=r"acc_00003\.csv, row 2: 5 columns, expected 6 "):
        read_pronostia_bearing(d, expected_samples=None)
