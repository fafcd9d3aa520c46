"""NumPy scalars (a count from ``np.arange`` or a table column, a float32 level) are taken
wherever a Python int or float is (``core.validation.is_int`` / ``is_real``), and give the same
result; bools are refused. These checks used ``isinstance(v, int)`` or ``(int, float)``, which
refused ``np.int64`` and ``np.float32`` (``np.float64`` is a ``float``)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from prognos_torch.core.validation import check_channel, check_index, check_level, check_std

F64 = torch.float64


def test_core_checks_take_numpy_scalars_and_return_python_numbers():
    assert check_level(np.float32(0.5)) == 0.5
    c = check_channel(np.int64(1), 2)
    assert c == 1 and type(c) is int
    assert torch.equal(check_index(np.int64(2), 4), check_index(2, 4))
    assert check_std(np.float32(0.5), 2, "std") == (0.5, 0.5) == check_std(0.5, 2, "std")
    assert check_std([np.float32(0.5), np.int64(1)], 2, "std") == (0.5, 1.0)
    for bad in (True, np.bool_(True)):
        with pytest.raises(ValueError, match="channel must be an int"):
            check_channel(bad, 2)
        with pytest.raises(TypeError, match="must contain real numbers"):
            check_std(bad, 2, "std")


def test_state_space_model_dims_take_numpy_ints_and_refuse_bools():
    from prognos_torch.core.model import StateSpaceModel

    h = lambda x, u, k: x  # noqa: E731
    eye = torch.eye(2, dtype=F64)
    m = StateSpaceModel(None, h, np.int64(2), np.int32(2), eye, eye, control_dim=np.int64(0))
    assert (m.state_dim, m.obs_dim, m.control_dim) == (2, 2, 0)
    assert all(type(v) is int for v in (m.state_dim, m.obs_dim, m.control_dim))
    with pytest.raises(ValueError, match="state_dim must be a positive int, got True"):
        StateSpaceModel(None, h, True, 2, eye, eye)  # (was taken as 1)


def test_moving_window_and_em_tol_take_numpy_scalars():
    from prognos_torch.adapt.noise import MovingWindow
    from prognos_torch.core.belief import GaussianBelief
    from prognos_torch.optim.em import em_linear_gaussian

    w = MovingWindow(window=np.int64(5), warmup=np.int32(3))
    assert (w.window, w.warmup) == (5, 3) and type(w.window) is int and type(w.warmup) is int
    with pytest.raises(ValueError, match="window must be a positive int"):
        MovingWindow(window=np.bool_(True))
    eye = torch.eye(1, dtype=F64)
    init = GaussianBelief(torch.zeros(1, dtype=F64), eye)
    y = torch.sin(torch.arange(30, dtype=F64))[:, None]
    a = em_linear_gaussian(eye, eye, eye, eye, init, y, iterations=20, tol=np.float32(0.5))
    b = em_linear_gaussian(eye, eye, eye, eye, init, y, iterations=20, tol=float(np.float32(0.5)))
    assert torch.equal(a.A, b.A) and torch.equal(a.chol_Q, b.chol_Q)
    with pytest.raises(ValueError, match="tol must be a number >= 0 or None, got True"):
        em_linear_gaussian(eye, eye, eye, eye, init, y, tol=True)


def test_window_belief_takes_numpy_end_and_std():
    from prognos_torch.prognosis.learner_model import window_belief

    s = torch.arange(10, dtype=F64)
    a = window_belief(s, np.int64(6), 3, np.float32(0.5))
    b = window_belief(s, 6, 3, 0.5)
    assert torch.equal(a.mean, b.mean) and torch.equal(a.chol, b.chol)
    assert torch.equal(a.mean, torch.tensor([3.0, 4.0, 5.0], dtype=F64))
    with pytest.raises(ValueError, match="end must be an int"):
        window_belief(s, np.float64(6.0), 3, 0.5)


def test_conformal_bins_and_coverage_take_numpy_scalars():
    from prognos_torch.prognosis.conformal import calibrate_intervals, conformal_margin

    g = torch.Generator().manual_seed(0)
    truth = torch.rand(40, generator=g, dtype=F64) * 10 + 1
    med = truth * torch.exp(0.3 * torch.randn(40, generator=g, dtype=F64))
    lo, hi = med / 1.5, med * 1.5
    a = calibrate_intervals(lo, hi, truth, bins=np.int64(2), median=med)
    b = calibrate_intervals(lo, hi, truth, bins=2, median=med)
    assert a.edges == b.edges and a.margins == b.margins
    json.dumps(a.to_dict())  # the record stays JSON
    s = torch.arange(20, dtype=F64)
    assert conformal_margin(s, np.float32(0.5)) == conformal_margin(s, float(np.float32(0.5)))
    with pytest.raises(TypeError, match="coverage must be a float"):
        conformal_margin(s, np.bool_(True))


def test_workflow_counts_and_levels_take_numpy_scalars(tmp_path):
    from prognos_torch._workers import check_workers
    from prognos_torch.workflow import fit_series, forecast, load_series
    from prognos_torch.workflow.memory import lssvr_support

    w = check_workers(np.int64(2))
    assert w == 2 and type(w) is int
    assert lssvr_support(100, np.int64(50)) == lssvr_support(100, 50)
    t = np.arange(120.0)
    y = 1.0 + 0.2 * np.sin(t / 7.0) + 0.01 * t
    s = load_series(y, last=np.int64(100))
    assert len(s) == 100 and torch.equal(s.values, load_series(y, last=100).values)
    kw = dict(learner="elm", optimizer="closed-form", seed=0)
    a = fit_series(s, m=np.int64(3), holdout=np.int64(10), **kw)
    b = fit_series(s, m=3, holdout=10, **kw)
    assert a.m == b.m == 3 and type(a.m) is int
    assert {k: v for k, v in a.config.items() if k != "train"} == {
        k: v for k, v in b.config.items() if k != "train"
    }
    for pa, pb in zip(a.learner.parameters(), b.learner.parameters()):
        assert torch.equal(pa, pb)
    assert fit_series(s, m=3, holdout=np.float32(0.25), **kw).config["holdout"]["n"] == 25
    fa = forecast(a, s, 5, level=np.float32(0.5))
    fb = forecast(b, s, 5, level=float(np.float32(0.5)))
    assert torch.equal(fa.lower, fb.lower) and torch.equal(fa.upper, fb.upper)
    p = tmp_path / "m.pt"
    from prognos_torch.workflow import save_model

    save_model(a, p)  # the model file's record stays JSON-safe


def test_fleet_counts_take_numpy_ints():
    from prognos_torch.fleet import fleet_rul, read_fleet_table, synthetic_fleet

    fl = synthetic_fleet(6, 120, seed=1, healthy_fraction=0.2)
    tab = read_fleet_table(fl.table)
    a = fleet_rul(tab, fl.threshold, samples=np.int64(50), shard_size=np.int64(2))
    b = fleet_rul(tab, fl.threshold, samples=50, shard_size=2)
    assert a.columns["flags"] == b.columns["flags"]
    for c in ("rul_median", "rul_q05", "rul_q95"):
        np.testing.assert_array_equal(np.array(a.columns[c]), np.array(b.columns[c]))
