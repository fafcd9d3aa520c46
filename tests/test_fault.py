"""Tests of forecasted measurements and fault prediction (paper 000 Sec. 5):
prognos_torch.learners.ros_elm, prognos_torch.prognosis.forecaster and prognos_torch.prognosis.fault.

References are independent: per-run ELM.init_online / partial_fit, recursive prediction, and the
real-time filter itself (an oracle forecaster must reproduce it).
"""

from __future__ import annotations

import copy
import sys
from pathlib import Path

import pytest
import torch

from prognos_torch.datasets.windows import embed
from prognos_torch.filters import run, sckf, stsckf
from prognos_torch.learners import ELM, ros_elm_forecast, ros_elm_init, ros_elm_update
from prognos_torch.prognosis import (
    MeasurementForecaster,
    predict_fault_parameter,
    recursive_predict,
    rolling_fault_prediction,
)

sys.path.insert(0, str(Path(__file__).parent))
from _prognosis_helpers import F64, _drift_problem, _gen, _learner, _Oracle, _series  # noqa: E402


def test_batched_ros_elm_forecaster_equals_per_run_elms():
    R, C, p, L, lam = 3, 2, 3, 10, 1e-3
    T = 40
    t = torch.arange(T, dtype=F64)
    z = torch.stack(
        [
            torch.stack([torch.sin(0.2 * t + r) + 0.1 * r, 0.5 * torch.cos(0.1 * t - r)], -1)
            for r in range(R)
        ],
        dim=1,
    )  # (T, R, C)
    fc = MeasurementForecaster.ros_elm(C, p=p, n_hidden=L, lam=lam, generator=_gen(9))
    fc.initialize(z[:20])
    for k in range(20, 30):
        fc.update(z[k])
    pred = fc.forecast(4)  # (4, R, C)
    assert pred.shape == (4, R, C)
    for lr in fc.learners:  # the learners are not modified
        assert float(lr.beta.detach().abs().max()) == 0.0
    for r in range(R):
        for c in range(C):
            elm = copy.deepcopy(fc.learners[c])
            X, y = embed(z[:20, r, c], p)
            elm.init_online(X, y, lam)
            for k in range(20, 30):
                elm.partial_fit(z[k - p : k, r, c], z[k, r, c].reshape(1))
            want = recursive_predict(elm, z[30 - p : 30, r, c], 4).detach()
            torch.testing.assert_close(pred[:, r, c], want, rtol=1e-7, atol=1e-9)
    # functional core = shell; states are immutable
    s0 = ros_elm_init(fc.learners, z[:20], p, lam)
    s1 = ros_elm_update(fc.learners, s0, z[20])
    assert s0.n_seen == 17 and s1.n_seen == 18
    torch.testing.assert_close(s0.window, z[17:20].movedim(0, -1))
    torch.testing.assert_close(ros_elm_forecast(fc.learners, s1, 2).shape, torch.Size([2, R, C]))


def test_static_learner_forecaster_equals_recursive_prediction():
    lssvr, X = _learner("lssvr", m=4)
    s = _series()
    fc = MeasurementForecaster([lssvr], 4, online=False).initialize(s[:50].unsqueeze(-1))
    fc.update(s[50:51])
    got = fc.forecast(5)[:, 0]
    torch.testing.assert_close(got, recursive_predict(lssvr, s[47:51], 5).detach())


def test_predict_fault_parameter_with_oracle_equals_real_time_filter():
    th, ys_all, model, init = _drift_problem(T=60)
    filt = stsckf()
    k, n = 40, 5
    traj = run(filt, model, init, ys_all[: k + n])
    state = run(filt, model, init, ys_all[:k]).final
    mean0, chol0 = state.belief.mean.clone(), state.belief.chol.clone()
    oracle = _Oracle(ys_all).initialize(ys_all[:k])
    pred = predict_fault_parameter(filt, model, state, oracle, n, k, param_index=0)
    torch.testing.assert_close(pred.theta, traj.means[k + n - 1], rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(pred.means, traj.means[k:])
    torch.testing.assert_close(pred.fading_factors, traj.fading_factors[k:])
    assert pred.theta.shape == (3, 1) and pred.pseudo_measurements.shape == (n, 3, 2)
    assert torch.equal(state.belief.mean, mean0) and torch.equal(state.belief.chol, chol0)


def test_rolling_prediction_alignment_with_oracle():
    T, n, start = 70, 4, 30
    th, ys_all, model, init = _drift_problem(T=T)
    filt = stsckf()
    res = rolling_fault_prediction(
        filt, model, ys_all[:T], _Oracle(ys_all), n, start, init=init, param_index=0
    )
    full = run(filt, model, init, ys_all[:T])
    # the real-time estimate is not disturbed by the n-step runs
    torch.testing.assert_close(res.filtered, full.means, rtol=1e-12, atol=1e-12)
    assert res.origin.tolist() == list(range(start, T + 1))
    torch.testing.assert_close(res.target, res.origin + n)
    ok = res.target <= T
    torch.testing.assert_close(res.predicted[ok], full.means[res.target[ok] - 1])
    aligned = res.aligned()
    assert aligned.shape == (T + n, 3, 1)
    assert bool(torch.isnan(aligned[: start + n - 1]).all())
    torch.testing.assert_close(aligned[start + n - 1 :], res.predicted)
    assert res.fading_factors.shape == (T - start + 1, n, 3)


def test_rolling_fault_prediction_strong_tracking_beats_plain_filter_on_ramp():
    T, n, start, onset = 110, 5, 50, 30
    th, ys_all, model, init = _drift_problem(T=T, onset=onset)
    ys = ys_all[:T]
    fc = MeasurementForecaster.ros_elm(2, p=3, n_hidden=20, lam=1e-8, generator=_gen(1))
    out = {}
    for name, filt in (("sckf", sckf()), ("stsckf", stsckf())):
        res = rolling_fault_prediction(filt, model, ys, fc, n, start, init=init, param_index=0)
        truth = th[res.target - 1].unsqueeze(-1)  # theta at time t is th[t - 1]
        out[name] = float((res.predicted[..., 0] - truth).abs().mean())
        lam = res.fading_factors
        if name == "sckf":
            assert bool((lam == 1).all())
        else:
            assert float(lam.max()) > 1.0
    assert not fc.initialized  # the caller's forecaster is copied, not modified
    ramp = float(th[T + n - 1] - th[start])  # size of the drift over the prediction window
    assert out["stsckf"] < 0.5 * out["sckf"], out
    assert out["stsckf"] < 0.1 * ramp, (out, ramp)


def test_bad_forecaster_and_fault_arguments_raise_clear_errors():
    fc = MeasurementForecaster.ros_elm(2, p=3, n_hidden=8, lam=1e-3)
    with pytest.raises(RuntimeError, match="initialize"):
        fc.forecast(3)
    with pytest.raises(ValueError, match="N0 >= p \\+ 1"):
        fc.initialize(torch.zeros(3, 2, dtype=F64))
    z0 = torch.randn(20, 2, generator=_gen(0), dtype=F64)
    with pytest.raises(ValueError, match=r"z0 must have shape \(N0, \.\.\., C\) with C=2"):
        fc.initialize(z0[:, :1])
    fc.initialize(z0)
    with pytest.raises(ValueError, match="n must be a positive int"):
        fc.forecast(0)
    with pytest.raises(ValueError, match=r"z must have shape \(2,\)"):
        fc.update(torch.zeros(3, dtype=F64))
    with pytest.raises(ValueError, match=r"z contains inf \(use NaN to mark a missing"):
        fc.update(torch.tensor([0.0, float("inf")], dtype=F64))
    with pytest.raises(ValueError, match="p=4"):
        MeasurementForecaster([ELM(3, 5)], 4)

    th, ys_all, dmodel, init = _drift_problem(T=40)
    state = sckf().init(dmodel, init)
    with pytest.raises(ValueError, match="n must be a positive int"):
        predict_fault_parameter(sckf(), dmodel, state, _Oracle(ys_all).initialize(ys_all[:5]), 0, 5)
    with pytest.raises(ValueError, match=r"forecaster.forecast\(n\) must return shape"):
        predict_fault_parameter(sckf(), dmodel, state, fc, 3, 5)  # 2 channels but no run dim
    with pytest.raises(ValueError, match="start"):
        rolling_fault_prediction(sckf(), dmodel, ys_all[:40], fc, 3, 41, init=init)
    ys_bad = ys_all[:40].clone()
    ys_bad[7, 0, 1] = float("inf")
    with pytest.raises(ValueError, match=r"ys contains inf \(use NaN to mark a missing"):
        rolling_fault_prediction(sckf(), dmodel, ys_bad, fc, 3, 20, init=init)
    with pytest.raises(ValueError, match="param_index"):
        rolling_fault_prediction(sckf(), dmodel, ys_all[:40], fc, 3, 20, init=init, param_index=4)


def test_ros_elm_update_predicts_a_missing_measurement_into_the_window():
    """A NaN in ``z`` (it was refused) is a missing measurement: that channel of that run keeps
    ``beta`` and ``K`` exactly, and its window shifts in the one-step prediction (Eq. 47), so
    that it stays on the measurements' clock; every observed entry updates exactly as with a
    complete ``z``. A ``z`` missing throughout is ``ros_elm_forecast``'s step: nothing learnt."""
    from prognos_torch.datasets.windows import shift_append

    p, L, C, R = 3, 6, 2, 3
    g = _gen(4)
    elms = [ELM(p, L, generator=g) for _ in range(C)]
    z = torch.randn(30, R, C, generator=g, dtype=F64)
    st = ros_elm_init(elms, z[:20], p, 1e-2)
    zk = z[20].clone()
    zk[0, 1] = zk[2, 0] = float("nan")
    miss = torch.isnan(zk)
    got = ros_elm_update(elms, st, zk)
    full = ros_elm_update(elms, st, torch.where(miss, torch.zeros_like(zk), zk))
    pred = ros_elm_forecast(elms, st, 1)[0]  # (R, C)
    assert got.n_seen == st.n_seen + 1
    for c in range(C):
        for r in range(R):
            if miss[r, c]:
                assert torch.equal(got.beta[c][r], st.beta[c][r])
                assert torch.equal(got.K[c][r], st.K[c][r])
                want = shift_append(st.window[r, c], pred[r, c])
                assert torch.equal(got.window[r, c], want)
            else:
                assert torch.equal(got.beta[c][r], full.beta[c][r])
                assert torch.equal(got.K[c][r], full.K[c][r])
                assert torch.equal(got.window[r, c], full.window[r, c])
    # missing throughout: the forecast's first step, nothing absorbed
    none = ros_elm_update(elms, st, torch.full((R, C), float("nan"), dtype=F64))
    assert none.n_seen == st.n_seen
    assert torch.equal(none.window[..., -1], pred)
    assert all(torch.equal(a, b) for a, b in zip(none.beta, st.beta))
    assert all(torch.equal(a, b) for a, b in zip(none.K, st.K))
    # and the forecast from there continues the forecast from before
    torch.testing.assert_close(ros_elm_forecast(elms, none, 4),
                               ros_elm_forecast(elms, st, 5)[1:], rtol=0, atol=0)  # fmt: skip
    # the forecaster's step 9 takes it too, a static learner included
    fc = MeasurementForecaster(elms, p, online=False).initialize(z[:20])
    before = fc.state.window.clone()
    fc.update(zk)
    zs = ros_elm_forecast(elms, fc.state, 1)  # (the static learners' own forward)
    assert torch.isfinite(fc.state.window).all() and torch.isfinite(zs).all()
    assert torch.equal(fc.state.window[0, 0], shift_append(before[0, 0], zk[0, 0]))


def test_rolling_fault_prediction_reads_nan_as_missing():
    """NaN in ``ys`` after ``start`` (it was refused) is a missing measurement: the real-time
    filter is the engine's own run over the same ``ys`` (which predicts without updating
    there), and the forecaster is the one that took each row by ``update`` (its window takes
    its prediction for a missing value). NaN in the rows that train the forecaster is refused
    by name, unless the forecaster was trained already."""
    T, n, start = 60, 4, 30
    th, ys_all, model, init = _drift_problem(T=T)
    ys = ys_all[:T].clone()
    ys[35, 0, 1] = ys[41, 2] = ys[44, 1, 0] = float("nan")  # one value, a whole row, another
    fc = MeasurementForecaster.ros_elm(2, p=3, n_hidden=8, lam=1e-3, generator=_gen(1))
    res = rolling_fault_prediction(sckf(), model, ys, fc, n, start, init=init, param_index=0)
    full = run(sckf(), model, init, ys)
    torch.testing.assert_close(res.filtered, full.means, rtol=1e-12, atol=1e-12)
    assert bool(torch.isfinite(res.predicted).all() and torch.isfinite(res.predicted_std).all())
    by_hand = fc.copy().initialize(ys[:start])
    for k in range(start, T):
        by_hand.update(ys[k])
    got, want = res.forecaster.state, by_hand.state
    assert torch.equal(got.window, want.window) and got.n_seen == want.n_seen
    assert all(torch.equal(a, b) for a, b in zip(got.beta, want.beta))
    # the rows that train the forecaster must be complete
    early = ys.clone()
    early[7, 0, 1] = float("nan")
    with pytest.raises(ValueError, match=r"ys\[:start\] \(start=30\) trains the forecaster"):
        rolling_fault_prediction(sckf(), model, early, fc, n, start, init=init)
    trained = fc.copy().initialize(ys_all[:start])
    rolling_fault_prediction(sckf(), model, early, trained, n, start, init=init)  # (taken)
