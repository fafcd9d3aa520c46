"""Audit of prognos_torch.datasets: windows, splits, IMS and PRONOSTIA readers, LLE.

References are brute-force loops, NumPy closed forms and hand computations; raw files are
small synthetic copies of the formats in ``tmp_path``.
"""

from __future__ import annotations

import math
import warnings
from datetime import datetime, timedelta

import numpy as np
import pytest
import torch

from prognos_torch.datasets import (
    FEATURE_NAMES,
    IMSFormatError,
    MinMaxScaler,
    chronological_split,
    embed,
    health_indicator,
    knn,
    lle_cost_matrix,
    load_ims_features,
    minmax_normalize,
    one_step_pairs,
    read_pronostia_bearing,
    read_raw_features,
    read_snapshot,
    reconstruction_weights,
    shift_append,
    snapshot_features,
    snapshot_time,
)

F64 = torch.float64


def _ims_name(t: datetime) -> str:
    return t.strftime("%Y.%m.%d.%H.%M.%S")


# --------------------------------------------------------------------------- windows


def test_embed_and_one_step_pairs_match_a_loop():
    """Window i = x[i : i + m], target x[i + m]; train targets are samples m+1..n_train
    (1-based), test targets n_train+1..T, k_test their indices."""
    g = torch.Generator().manual_seed(0)
    x = torch.randn(13, generator=g, dtype=F64)
    xv = torch.randn(13, 2, generator=g, dtype=F64)
    for m in (1, 2, 5, 12):
        inputs, targets = embed(x, np.int64(m))
        ref_in = [[float(x[i + j]) for j in range(m)] for i in range(13 - m)]
        assert inputs.tolist() == ref_in
        assert targets.tolist() == [float(x[i + m]) for i in range(13 - m)]
        vin, vt = embed(xv, m)
        for i in range(13 - m):
            assert torch.equal(vin[i], xv[i : i + m]) and torch.equal(vt[i], xv[i + m])
    for m, n_train in ((1, 2), (3, 7), (4, 12)):
        p = one_step_pairs(x, m, np.int64(n_train))
        pairs = [(x[i : i + m].tolist(), float(x[i + m]), i + m + 1) for i in range(13 - m)]
        train = [q for q in pairs if q[2] <= n_train]
        test = [q for q in pairs if q[2] > n_train]
        assert p.X_train.tolist() == [q[0] for q in train]
        assert p.Y_train[:, 0].tolist() == [q[1] for q in train]
        assert p.X_test.tolist() == [q[0] for q in test]
        assert p.Y_test[:, 0].tolist() == [q[1] for q in test]
        assert p.k_test.tolist() == [q[2] for q in test]


def test_chronological_split_fraction_is_the_exact_floor():
    """n_train = floor(fraction * T) for the decimal fraction: 0.29 * 100 = 28.999999999999996
    gave 28 rows."""
    for T in range(2, 160):
        x = torch.arange(T)
        for k in range(1, 100):
            n = k * T // 100  # integer arithmetic: floor(k/100 * T)
            if not 1 <= n <= T - 1:
                continue
            a, b = chronological_split(x, k / 100)
            assert (len(a), len(b)) == (n, T - n), (T, k)
            assert torch.equal(torch.cat((a, b)), x)  # no overlap, nothing left out
    a, _ = chronological_split(list(range(100)), np.float64(0.29))
    assert len(a) == 29
    a, _ = chronological_split(list(range(10)), 0.75)  # 7.5: still the floor
    assert len(a) == 7


def test_minmax_normalize_refuses_per_sample_extremes():
    """A lo/hi of one value per sample (shape (N,)) was broadcast silently: every sample scaled
    by its own range."""
    s = torch.arange(5, dtype=F64) + 1
    lo = torch.arange(5, dtype=F64)
    with pytest.raises(ValueError, match="lo must broadcast to one row"):
        minmax_normalize(s, lo=lo, hi=lo + 2)
    S = torch.stack((s, 2 * s), 1)  # (5, 2)
    with pytest.raises(ValueError, match="hi must broadcast to one row"):
        minmax_normalize(S, lo=0.0, hi=torch.full((5, 1), 20.0, dtype=F64))
    # one row, with or without a leading unit dim: per-column (x - lo) / (hi - lo)
    lo_r, hi_r = torch.tensor([0.0, 1.0], dtype=F64), torch.tensor([10.0, 21.0], dtype=F64)
    ref = (S - lo_r) / (hi_r - lo_r)
    assert torch.equal(minmax_normalize(S, lo_r, hi_r).values, ref)
    out = minmax_normalize(S, lo_r[None], hi_r[None]).values
    assert torch.equal(out, ref)
    with pytest.raises(TypeError, match="lo must be a number"):
        minmax_normalize(s, lo="a")  # was "new(): invalid data type 'str'"


def test_minmax_scaler_refuses_infinite_state():
    """An infinite data_min was loaded and transform gave NaN."""
    sc = MinMaxScaler().fit(torch.tensor([0.0, 2.0], dtype=F64))
    before = sc.state_dict()
    bad = {
        "data_min": torch.tensor(-math.inf),
        "data_max": torch.tensor(0.0),
        "feature_range": (0, 1),
    }
    with pytest.raises(ValueError, match="finite"):
        sc.load_state_dict(bad)
    assert torch.equal(sc.data_min, before["data_min"])  # left as it was
    assert torch.equal(sc.data_max, before["data_max"])


def test_shift_append_refuses_empty_window_and_non_int_time_dim():
    with pytest.raises(ValueError, match="m >= 1"):  # was narrow(): length must be non-negative
        shift_append(torch.zeros(3, 0), torch.zeros(3))
    with pytest.raises(TypeError, match="time_dim must be an int"):  # was slice indices ...
        shift_append(torch.zeros(3, 2), torch.zeros(3), time_dim=1.5)
    w = torch.arange(6.0).reshape(3, 2)
    out = shift_append(w, torch.tensor([7.0, 8.0]), time_dim=np.int64(0))
    assert out.tolist() == [[2.0, 3.0], [4.0, 5.0], [7.0, 8.0]]


# --------------------------------------------------------------------------- IMS


def test_snapshot_features_closed_forms_and_constant_channel():
    """Closed forms per channel; a constant channel (20480 x 0.1, whose float mean is not 0.1)
    had std 3.7e-14, skewness 1 and kurtosis 1 instead of 0, NaN, NaN."""
    rng = np.random.default_rng(1)
    x = rng.standard_normal((257, 3)) * [1.0, 0.2, 3.0] + [0.1, -0.09, 2.0]
    f = snapshot_features(x)
    for c in range(3):
        v = x[:, c]
        n, mu = len(v), v.sum() / len(v)
        m2, m3, m4 = (((v - mu) ** k).sum() / n for k in (2, 3, 4))
        std = math.sqrt(m2 * n / (n - 1))
        rms = math.sqrt((v**2).sum() / n)
        peak = abs(v).max()
        ref = [mu, np.sort(v)[n // 2], std, m3 / m2**1.5, rms, std / math.sqrt(n)]
        ref += [m4 / m2**2, peak, peak / rms]
        np.testing.assert_allclose(f[c], ref, rtol=1e-12, atol=1e-15)
    const = np.full((20480, 2), [0.1, -0.093])
    assert const[:, 0].mean() != 0.1  # (the rounding that broke it)
    g = dict(zip(FEATURE_NAMES, snapshot_features(const).T))
    assert g["mean"].tolist() == [0.1, -0.093]
    assert g["std"].tolist() == [0.0, 0.0] and g["std_error"].tolist() == [0.0, 0.0]
    assert np.isnan(g["skewness"]).all() and np.isnan(g["kurtosis"]).all()
    np.testing.assert_allclose(g["crest_factor"], [1.0, 1.0], rtol=1e-12)


def test_read_snapshot_checks_n_channels_and_expected_samples(tmp_path):
    """n_channels="4" gave "line 1: 4 columns, expected 4 channels", 4.0 was accepted;
    expected_samples="10" gave "10 sample rows, expected 10"."""
    p = tmp_path / "2003.10.22.12.06.24"
    x = np.round(np.random.default_rng(0).standard_normal((10, 4)), 3)
    p.write_text("\n".join("\t".join(f"{v:.3f}" for v in r) for r in x) + "\n")
    for bad in ("4", 4.0, True, 0):
        with pytest.raises(ValueError, match="n_channels must be a positive int"):
            read_snapshot(p, bad)
    for bad in ("10", 10.0, 1, True):
        with pytest.raises(ValueError, match="expected_samples must be None or an int >= 2"):
            read_snapshot(p, 4, bad)
    np.testing.assert_array_equal(read_snapshot(p, np.int64(4), np.int64(10)), x)


def test_read_raw_features_checks_expected_samples_and_cache(tmp_path):
    """expected_samples=0 made every file a bad file ("no readable snapshot" after skipping
    all); cache=1 failed inside Path()."""
    t0 = datetime(2004, 2, 12, 10, 32, 39)
    rng = np.random.default_rng(2)
    for i in (2, 0, 1):  # written out of time order
        x = np.round(rng.standard_normal((6, 4)), 3)
        (tmp_path / _ims_name(t0 + timedelta(minutes=10 * i, seconds=i))).write_text(
            "\n".join(" ".join(f"{v:.3f}" for v in r) for r in x) + "\n"
        )
    with pytest.raises(ValueError, match="expected_samples must be None or an int >= 2"):
        read_raw_features(tmp_path, test=2, cache=False, on_error="skip", expected_samples=0)
    with pytest.raises(ValueError, match="expected_samples"):
        read_raw_features(tmp_path, test=2, cache=False, expected_samples=6.0)
    with pytest.raises(TypeError, match="cache must be True, False or a file path"):
        read_raw_features(tmp_path, test=2, cache=1)
    f = read_raw_features(tmp_path, test=2, cache=np.bool_(False), expected_samples=np.int64(6))
    assert not any(p.suffix == ".npz" for p in tmp_path.iterdir())
    # days by hand: 10 min 1 s apart
    np.testing.assert_allclose(f.days.numpy(), [0.0, 601 / 86400, 1202 / 86400], rtol=1e-15)
    assert snapshot_time("2004.02.12.10.32.39") == t0
    assert snapshot_time("2004.02.30.10.32.39") is None


def test_ims_channel_refuses_bool_and_float(tmp_path):
    """channel(True) returned channel 1 and channel(2.0) channel 2."""
    rows = ["timestamp,channel," + ",".join(FEATURE_NAMES)]
    for t in ("2004-02-12T10:32:39", "2004-02-12T10:42:39"):
        for c in range(1, 5):
            rows.append(f"{t},{c}," + ",".join(str(c + k / 10) for k in range(9)))
    (tmp_path / "test2_features.csv").write_text("\n".join(rows) + "\n")
    f = load_ims_features(2, tmp_path)
    for bad in (True, 2.0):
        with pytest.raises(ValueError, match="channel must be one of"):
            f.channel(bad)
    assert f.channel(np.int64(2))[:, 0].tolist() == [2.0, 2.0]


def test_health_indicator_one_snapshot_window_names_the_cause(tmp_path):
    """One snapshot gave a NaN std and then "X (shape (n, D)) contains non-finite values"."""
    rows = ["timestamp,channel," + ",".join(FEATURE_NAMES)]
    for c in range(1, 5):
        rows.append(f"2004-02-12T10:32:39,{c}," + ",".join(str(c + k / 10) for k in range(9)))
    (tmp_path / "test2_features.csv").write_text("\n".join(rows) + "\n")
    f = load_ims_features(2, tmp_path)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with pytest.raises(ValueError, match="need at least 2 to standardise"):
            health_indicator(f, bearing=1, test_channel=2, last_days=None, n_neighbors=1)


# --------------------------------------------------------------------------- PRONOSTIA


def _write_record(folder, k, clock_s, n=5, seed=0, sep=","):
    rng = np.random.default_rng(seed + k)
    h, mi, s = clock_s // 3600, (clock_s // 60) % 60, clock_s % 60
    x = np.round(rng.standard_normal((n, 2)), 3)
    lines = [sep.join(str(v) for v in (h, mi, s, 123456 + j, *x[j])) for j in range(n)]
    (folder / f"acc_{k:05d}.csv").write_text("\n".join(lines) + "\n")
    return x


def test_pronostia_reader_hours_clock_and_features(tmp_path):
    b = tmp_path / "Bearing2_3"
    b.mkdir()
    clocks = {1: 86395, 2: 5, 3: 15, 5: 36, 6: 48}  # midnight wrap; 3 -> 5: 21 s (1 s off)
    xs = {k: _write_record(b, k, c, sep=";" if k == 3 else ",") for k, c in clocks.items()}
    f = read_pronostia_bearing(b, expected_samples=np.int64(5))
    assert f.condition == 2 and f.files == tuple(f"acc_{k:05d}.csv" for k in clocks)
    np.testing.assert_allclose(f.hours.numpy(), [0, 10 / 3600, 20 / 3600, 40 / 3600, 50 / 3600])
    assert f.clock_mismatch == ("acc_00006.csv",)  # 12 s for one record (5 -> 6)
    for i, k in enumerate(clocks):
        np.testing.assert_allclose(f.values[i].numpy(), snapshot_features(xs[k]), rtol=1e-14)


def test_pronostia_checks_expected_samples_and_one_row_record(tmp_path):
    """expected_samples="5" gave "expected 5 rows, got 5" and 5.0 was accepted; a one-row
    record was "expected rows of 6 columns ... got shape (1, 6)"."""
    b = tmp_path / "Bearing1_1"
    b.mkdir()
    _write_record(b, 1, 100)
    for bad in ("5", 5.0, 0):
        with pytest.raises(ValueError, match="expected_samples must be None or an int >= 2"):
            read_pronostia_bearing(b, expected_samples=bad)
    _write_record(b, 2, 110, n=1)
    with pytest.raises(ValueError, match="acc_00002.csv: 1 row, need at least 2"):
        read_pronostia_bearing(b, expected_samples=None)


# --------------------------------------------------------------------------- LLE


def test_reconstruction_weights_refuses_mismatched_query_and_bad_neighbors():
    """A (m, 1) query was broadcast against the 3 coordinates of X_ref; float neighbours gave
    an IndexError; a negative index picked a point from the end."""
    g = torch.Generator().manual_seed(3)
    X = torch.randn(10, 3, generator=g, dtype=F64)
    nb = knn(X, None, 3)
    with pytest.raises(ValueError, match=r"X_query must have shape \(m, 3\)"):
        reconstruction_weights(X, nb, torch.randn(10, 1, generator=g, dtype=F64))
    with pytest.raises(TypeError, match="neighbors must be a LongTensor"):
        reconstruction_weights(X, nb.double())
    with pytest.raises(ValueError, match=r"neighbors must index rows 0\.\.9"):
        reconstruction_weights(X, nb - 1)


def test_knn_mixed_dtypes_orders_in_the_wider_dtype():
    """float64 references with a float32 query were rounded to float32: offsets of 1e-9 all
    became ties, returned in index order."""
    offs = torch.tensor([5.0, 3.0, 8.0, 1.0, 7.0, 2.0], dtype=F64)
    X_ref = (1.0 + 1e-9 * offs)[:, None]
    q = torch.ones(1, 1, dtype=torch.float32)
    got = knn(X_ref, q, 4)[0].tolist()
    d = [abs(float(X_ref[i, 0]) - 1.0) for i in range(6)]
    assert got == sorted(range(6), key=lambda i: d[i])[:4]


def test_lle_cost_matrix_with_a_repeated_neighbor_is_dense_formula():
    """W[i, j] sums the weights of a repeated index (scatter_ kept one of them), so M equals
    (I - W)^T (I - W) with W accumulated by a loop."""
    nb = torch.tensor([[1, 1, 2], [0, 2, 0], [0, 1, 1]])
    w = torch.tensor([[0.5, 0.25, 0.25], [0.2, 0.3, 0.5], [0.6, 0.3, 0.1]], dtype=F64)
    W = torch.zeros(3, 3, dtype=F64)
    for i in range(3):
        for j in range(3):
            W[i, nb[i, j]] += w[i, j]
    IW = torch.eye(3, dtype=F64) - W
    assert float((lle_cost_matrix(nb, w, 3) - IW.T @ IW).abs().max()) <= 1e-15


def test_read_snapshot_reports_nan_and_wrong_columns(tmp_path):
    """Reference behaviour (unchanged): NaN, a short row, an empty file."""
    p = tmp_path / "2003.10.22.12.06.24"
    p.write_text("1 2 3 4\n1 nan 3 4\n")
    with pytest.raises(IMSFormatError, match="line 2: non-finite value 'nan' in column 2"):
        read_snapshot(p, 4)
    p.write_text("1 2 3 4\n1 2 3\n")
    with pytest.raises(IMSFormatError, match="line 2: 3 columns, expected 4"):
        read_snapshot(p, 4)
    p.write_text("")
    with pytest.raises(IMSFormatError, match="no samples"):
        read_snapshot(p, 4)
