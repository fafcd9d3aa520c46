"""Audit of the training loops (optim.fit, optim.online, optim.stacked, optim.compiled).

Exact references: a hand-written mini-batch loop with torch.optim.SGD, a Kalman filter / recursive
least squares written here for a linear-in-parameters model, R separate single runs; and the
bad inputs that were taken silently, failed obscurely or after an epoch had trained the module.
"""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch
from torch import nn

from prognos_torch.optim import (
    KalmanOptimizer,
    StackedForecaster,
    StackedLearner,
    fit,
    fit_kalman_runs,
    fit_together,
    kalman_runs_optimizer,
    predict_then_update,
    train_in_blocks,
)
from prognos_torch.prognosis import MeasurementForecaster

F64 = torch.float64
TOL = dict(rtol=0, atol=1e-12)


def _data(n=10, n_in=2, n_out=1, seed=0):
    g = torch.Generator().manual_seed(seed)
    X = torch.rand(n, n_in, generator=g, dtype=F64)
    W = torch.tensor([[0.7, -1.3], [0.2, 0.5]], dtype=F64)[:n_out, :n_in]
    Y = X @ W.mT + 0.3 + 0.05 * torch.randn(n, n_out, generator=g, dtype=F64)
    return X, Y


def _linear(seed=1, n_in=2, n_out=1):
    torch.manual_seed(seed)
    return nn.Linear(n_in, n_out, dtype=F64)


def _params(m):
    return torch.cat([p.detach().reshape(-1) for p in m.parameters()])


# ------------------------------------------------------------------ exact references
@pytest.mark.parametrize("shuffle", [False, True])
@pytest.mark.parametrize("drop_last", [False, True])
def test_fit_equals_a_hand_written_sgd_loop(shuffle, drop_last):
    X, Y = _data(n=10)
    m = _linear()
    ref = copy.deepcopy(m)
    opt = torch.optim.SGD(m.parameters(), lr=0.2, momentum=0.5)
    h = fit(
        m,
        opt,
        (X, Y),
        epochs=3,
        batch_size=3,
        shuffle=shuffle,
        drop_last=drop_last,
        generator=torch.Generator().manual_seed(7) if shuffle else None,
        progress=False,
        metrics=("mae", "rmse", "mse"),
    )
    ropt = torch.optim.SGD(ref.parameters(), lr=0.2, momentum=0.5)
    g = torch.Generator().manual_seed(7)
    for epoch in range(3):
        order = torch.randperm(10, generator=g) if shuffle else torch.arange(10)
        starts = range(0, 9, 3) if drop_last else range(0, 10, 3)
        losses = []
        for a in starts:
            idx = order[a : a + 3]
            ropt.zero_grad()
            loss = nn.functional.mse_loss(ref(X[idx]), Y[idx])
            loss.backward()
            ropt.step()
            losses.append(loss.detach())
        # the recorded loss: the mean of the step losses (before each step); the metrics: the
        # whole training set after the epoch
        torch.testing.assert_close(h.loss[epoch], torch.stack(losses).mean(), **TOL)
        with torch.no_grad():
            e = ref(X) - Y
        torch.testing.assert_close(h.train["mae"][epoch], e.abs().mean(), **TOL)
        torch.testing.assert_close(h.train["rmse"][epoch], e.square().mean().sqrt(), **TOL)
        torch.testing.assert_close(h.train["mse"][epoch], e.square().mean(), **TOL)
    torch.testing.assert_close(_params(m), _params(ref), **TOL)
    assert h.steps == 3 * (3 if drop_last else 4) and h.epoch == [1, 2, 3]


class _Recorder(nn.Module):
    """A linear model that records the rows (their first feature: the row number) it trains on."""

    def __init__(self):
        super().__init__()
        self.lin = nn.Linear(2, 1, dtype=F64)
        self.seen: list[list[int]] = []

    def forward(self, x):
        if self.training:
            self.seen.append(x[:, 0].long().tolist())
        return self.lin(x)


def test_fit_visits_rows_in_the_documented_order_and_only_the_generator_shuffles():
    X = torch.stack([torch.arange(7, dtype=F64), torch.linspace(0, 1, 7, dtype=F64)], -1)
    Y = torch.zeros(7, 1, dtype=F64)
    m = _Recorder()
    fit(m, torch.optim.SGD(m.parameters(), lr=0.0), (X, Y), epochs=2, batch_size=3, progress=False)
    assert m.seen == [[0, 1, 2], [3, 4, 5], [6]] * 2
    runs = []
    for global_seed in (0, 1):  # the global RNG plays no part
        torch.manual_seed(global_seed)
        m = _Recorder()
        fit(
            m,
            torch.optim.SGD(m.parameters(), lr=0.0),
            (X, Y),
            epochs=2,
            batch_size=3,
            shuffle=True,
            generator=torch.Generator().manual_seed(3),
            progress=False,
        )
        runs.append(m.seen)
    g = torch.Generator().manual_seed(3)
    want = []
    for _ in range(2):
        order = torch.randperm(7, generator=g).tolist()
        want += [order[0:3], order[3:6], order[6:7]]
    assert runs[0] == runs[1] == want


def _kf_step(theta, P, H, y, Q, R):
    """One step of the random-walk Kalman filter (paper 003 Eq. 45-46), linear h = H theta;
    NaN entries of y are missing (left out); none observed: the prediction alone."""
    P = P + Q * torch.eye(P.shape[0], dtype=F64)
    obs = ~torch.isnan(y)
    if bool(obs.any()):
        H, y = H[obs], y[obs]
        S = H @ P @ H.mT + R * torch.eye(H.shape[0], dtype=F64)
        K = torch.linalg.solve(S, H @ P).mT
        theta = theta + K @ (y - H @ theta)
        P = P - K @ S @ K.mT
    return theta, P


def _H(x):
    """Jacobian of nn.Linear(n_in, 1) in the order (weight, bias)."""
    return torch.cat([x, torch.ones(x.shape[0], 1, dtype=F64)], -1)


def test_predict_then_update_on_a_linear_model_is_the_kalman_filter():
    X, Y = _data(n=12)
    Y[4] = float("nan")  # missing: predicted, then the filter's prediction alone (P + Q)
    P0, Q, R = 2.0, 1e-3, 0.05
    m = _linear()
    theta = _params(m)
    opt = KalmanOptimizer(m, filter="ekf", P0=P0, Q=Q, R=R)
    preds, _ = predict_then_update(m, opt, X, Y)
    P = P0 * torch.eye(3, dtype=F64)
    want = []
    for k in range(12):
        H = _H(X[k : k + 1])
        want.append(H @ theta)
        theta, P = _kf_step(theta, P, H, Y[k], Q, R)
    torch.testing.assert_close(preds, torch.stack(want), **TOL)
    torch.testing.assert_close(opt.theta, theta, **TOL)
    torch.testing.assert_close(opt.parameter_covariance(), P, **TOL)
    torch.testing.assert_close(_params(m), theta, **TOL)


def test_kalman_fit_mini_batches_and_per_run_data_are_the_kalman_filter():
    # recursive least squares (Q = 0) on mini-batches of 3 (the last of 1), NaN targets left out;
    # per-run data: run r is the filter on its own data; train_in_blocks takes the same steps
    g = torch.Generator().manual_seed(4)
    X = torch.rand(2, 7, 2, generator=g, dtype=F64)
    Y = torch.randn(2, 7, 1, generator=g, dtype=F64)
    Y[0, 1] = Y[1, 6] = float("nan")
    m = _linear()
    theta0 = torch.randn(2, 3, generator=g, dtype=F64)
    opt = KalmanOptimizer(
        m, filter="ekf", P0=1.5, Q=0.0, R=0.1, runs=2, per_run_data=True, theta0=theta0
    )
    h = fit(m, opt, (X, Y), epochs=2, batch_size=3, progress=False, metrics=("mse",))
    m2 = _linear()
    opt2 = KalmanOptimizer(
        m2, filter="ekf", P0=1.5, Q=0.0, R=0.1, runs=2, per_run_data=True, theta0=theta0
    )
    curve = train_in_blocks(m2, opt2, X, Y, block=7, passes=2)
    for r in range(2):
        theta, P = theta0[r], 1.5 * torch.eye(3, dtype=F64)
        for epoch in range(2):
            sq = []
            for a in (0, 3, 6):
                H, y = _H(X[r, a : a + 3]), Y[r, a : a + 3, 0]
                obs = ~torch.isnan(y)
                sq.append((y - H @ theta)[obs].square().mean())
                theta, P = _kf_step(theta, P, H, y, 0.0, 0.1)
            torch.testing.assert_close(h.loss[epoch][r], torch.stack(sq).nanmean(), **TOL)
            e = _H(X[r]) @ theta - Y[r, :, 0]
            torch.testing.assert_close(h.train["mse"][epoch][r], e.square().nanmean(), **TOL)
        torch.testing.assert_close(opt.theta[r], theta, **TOL)
        P_opt = opt.belief.chol[r] @ opt.belief.chol[r].mT
        torch.testing.assert_close(P_opt, P, **TOL)
        # one sample per step: 14 filter steps on the rows one by one
        theta, P = theta0[r], 1.5 * torch.eye(3, dtype=F64)
        for _ in range(2):
            for k in range(7):
                theta, P = _kf_step(theta, P, _H(X[r, k : k + 1]), Y[r, k], 0.0, 0.1)
        torch.testing.assert_close(opt2.theta[r], theta, **TOL)
    assert curve.steps == [7, 14]


def test_fit_together_and_fit_kalman_runs_equal_separate_runs():
    X, Y = _data(n=9)
    mods = [_linear(seed=s) for s in (1, 2, 3)]
    st = fit_together(
        [copy.deepcopy(m) for m in mods],
        lambda ps: torch.optim.SGD(ps, lr=0.3),
        (X, Y),
        epochs=2,
        batch_size=4,
        progress=False,
    )
    for r, m in enumerate(mods):
        ref = copy.deepcopy(m)
        fit(
            ref,
            torch.optim.SGD(ref.parameters(), lr=0.3),
            (X, Y),
            epochs=2,
            batch_size=4,
            progress=False,
        )
        torch.testing.assert_close(st.weight[r], ref.weight.detach(), **TOL)
        torch.testing.assert_close(st.bias[r], ref.bias.detach(), **TOL)
    kw = dict(filter="ekf", P0=1.0, Q=1e-4, R=0.05)
    st = fit_kalman_runs(
        [copy.deepcopy(m) for m in mods],
        (X, Y),
        batched=True,
        fit_options=dict(batch_size=4, progress=False),
        **kw,
    )
    for r, m in enumerate(mods):
        ref = copy.deepcopy(m)
        fit(ref, KalmanOptimizer(ref, **kw), (X, Y), batch_size=4, progress=False)
        torch.testing.assert_close(st.weight[r], ref.weight.detach(), **TOL)
        torch.testing.assert_close(st.bias[r], ref.bias.detach(), **TOL)


# ------------------------------------------------------------------ fit: bad input, named
def test_fit_bad_input_is_named():
    X, Y = _data(n=5)
    m = _linear()
    sgd = torch.optim.SGD(m.parameters(), lr=0.1)
    with pytest.raises(ValueError, match="epochs must be a positive int, got 0"):
        fit(m, sgd, (X, Y), epochs=0)
    with pytest.raises(ValueError, match="same non-zero number of rows"):
        fit(m, sgd, (X, Y[:4]))
    with pytest.raises(ValueError, match="batch_size=6 with drop_last leaves no batch of N=5"):
        fit(m, sgd, (X, Y), batch_size=6, drop_last=True)
    before = _params(m)
    # (an int or bool target was taken by the MSE as numbers 0/1; an int input failed inside
    # the module with "mat1 and mat2 must have the same dtype")
    with pytest.raises(TypeError, match="train targets Y must be a floating-point tensor"):
        fit(m, sgd, (X, (Y > 0.5)), progress=False)
    with pytest.raises(TypeError, match="train targets Y must be a floating-point tensor"):
        fit(m, sgd, (X, Y.round().long()), progress=False)
    with pytest.raises(TypeError, match="train inputs X must be a floating-point tensor"):
        fit(m, sgd, (X.long(), Y), progress=False)
    with pytest.raises(TypeError, match="val targets Y must be a floating-point tensor"):
        fit(m, sgd, (X, Y), val=(X, Y.long()), progress=False)
    assert torch.equal(_params(m), before)
    # batch_size beyond the rows (without drop_last): one full-batch step per epoch
    h = fit(m, sgd, (X, Y), batch_size=6, epochs=np.int64(2), progress=False)
    ref = copy.deepcopy(_linear())
    fit(
        ref,
        torch.optim.SGD(ref.parameters(), lr=0.1),
        (X, Y),
        batch_size=5,
        epochs=2,
        progress=False,
    )
    assert h.steps == 2
    torch.testing.assert_close(_params(m), _params(ref), **TOL)


@pytest.mark.parametrize("kind", ["sgd", "kalman"])
def test_fit_refuses_a_val_that_would_broadcast_before_any_step(kind):
    # the module outputs 3 values per sample; val targets (3,) for 3 samples were broadcast
    # against the (3, 3) output (metrics of 9 pairs); a val of (N,) targets for an (N, 1)
    # output raised only after the first epoch had trained the module
    g = torch.Generator().manual_seed(2)
    X, Y = torch.rand(4, 1, generator=g, dtype=F64), torch.rand(4, 3, generator=g, dtype=F64)
    m = nn.Linear(1, 3, dtype=F64)
    before = _params(m)
    opt = (
        torch.optim.SGD(m.parameters(), lr=0.1)
        if kind == "sgd"
        else KalmanOptimizer(m, filter="ekf", R=0.1)
    )
    with pytest.raises(ValueError, match=r"val targets Y must have shape \(3, 3\)"):
        fit(m, opt, (X, Y), val=(X[:3], Y[:3, 0]), progress=False)
    m1 = nn.Linear(1, 1, dtype=F64)
    opt1 = (
        torch.optim.SGD(m1.parameters(), lr=0.1)
        if kind == "sgd"
        else KalmanOptimizer(m1, filter="ekf", R=0.1)
    )
    before1 = _params(m1)
    with pytest.raises(ValueError, match=r"val targets Y must have shape \(4, 1\)"):
        fit(m1, opt1, (X, Y[:, :1]), val=(X, Y[:, 0]), progress=False)
    assert torch.equal(_params(m), before) and torch.equal(_params(m1), before1)


def test_fit_kalman_names_a_val_of_another_dtype_before_any_step():
    X, Y = _data(n=6)
    m = _linear()
    before = _params(m)
    opt = KalmanOptimizer(m, filter="ekf", R=0.1)
    # (it trained an epoch, then failed in the module: "mat1 and mat2 must have the same dtype")
    with pytest.raises(TypeError, match="val inputs X has dtype torch.float32 but the module"):
        fit(m, opt, (X, Y), val=(X.float(), Y), progress=False)
    with pytest.raises(TypeError, match="val targets Y has dtype torch.float32 but the module"):
        fit(m, opt, (X, Y), val=(X, Y.float()), progress=False)
    assert torch.equal(_params(m), before) and torch.equal(opt.theta, before)
    # per-run data: the val of every run is (R, N, ...) and scored per run
    g = torch.Generator().manual_seed(1)
    Xr, Yr = (
        torch.rand(2, 6, 2, generator=g, dtype=F64),
        torch.rand(2, 6, 1, generator=g, dtype=F64),
    )
    opt = KalmanOptimizer(m, filter="ekf", R=0.1, runs=2, per_run_data=True)
    h = fit(m, opt, (Xr, Yr), val=(Xr[:, :4], Yr[:, :4]), progress=False, metrics=("mse",))
    want = (opt.predict(Xr[:, :4]) - Yr[:, :4]).square().mean((1, 2))
    torch.testing.assert_close(h.val["mse"][0], want, **TOL)


def test_fit_keeps_the_submodules_the_caller_put_in_eval_mode():
    # fit called module.train(): a Dropout switched off for a Kalman optimiser (as its error
    # message advises) was switched on again and refused; a frozen BatchNorm moved its running
    # statistics; and every layer came back in training mode
    X, Y = _data(n=6)
    torch.manual_seed(0)
    m = nn.Sequential(nn.Linear(2, 3), nn.Dropout(0.5), nn.Linear(3, 1)).double()
    m[1].eval()
    fit(m, KalmanOptimizer(m, filter="srukf", R=0.1), (X, Y), batch_size=2, progress=False)
    assert [x.training for x in m.modules()] == [True, True, False, True]
    m2 = nn.Sequential(nn.Linear(2, 3), nn.BatchNorm1d(3), nn.Linear(3, 1)).double()
    m2[1].eval()
    stats = m2[1].running_mean.clone(), m2[1].running_var.clone()
    ref = copy.deepcopy(m2)
    fit(m2, torch.optim.SGD(m2.parameters(), lr=0.1), (X, Y), batch_size=3, progress=False)
    assert torch.equal(m2[1].running_mean, stats[0]) and torch.equal(m2[1].running_var, stats[1])
    assert [x.training for x in m2.modules()] == [True, True, False, True]
    ropt = torch.optim.SGD(ref.parameters(), lr=0.1)  # the loop by hand, BatchNorm in eval
    for a in (0, 3):
        ropt.zero_grad()
        nn.functional.mse_loss(ref(X[a : a + 3]), Y[a : a + 3]).backward()
        ropt.step()
    torch.testing.assert_close(_params(m2), _params(ref), **TOL)
    # a module wholly in eval mode trains in training mode (as before), and is put back
    fit(m2.eval(), torch.optim.SGD(m2.parameters(), lr=0.1), (X, Y), batch_size=3, progress=False)
    assert not any(x.training for x in m2.modules())
    assert not torch.equal(m2[1].running_mean, stats[0])


def test_fit_compile_with_no_full_mini_batch_steps_eagerly():
    # compile=True with batch_size > N compiled nothing and raised "steps needs at least one
    # step (T >= 1)"; the one smaller mini-batch is stepped eagerly, as the docs say
    X, Y = _data(n=4)
    kw = dict(filter="srukf", P0=1.0, Q=1e-4, R=0.1)
    m1, m2 = _linear(), _linear()
    h1 = fit(m1, KalmanOptimizer(m1, **kw), (X, Y), batch_size=5, compile=True, progress=False)
    h2 = fit(m2, KalmanOptimizer(m2, **kw), (X, Y), batch_size=5, progress=False)
    assert h1.steps == h2.steps == 1 and h1.compile_time == [0.0]
    assert torch.equal(_params(m1), _params(m2)) and torch.equal(h1.loss[0], h2.loss[0])


def test_compiled_steps_name_an_empty_sequence():
    # check_compilable read inputs[0] for the EKF first: IndexError "index 0 is out of bounds"
    m = _linear()
    opt = KalmanOptimizer(m, filter="ekf")
    with pytest.raises(ValueError, match=r"at least one step \(T >= 1\)"):
        opt.steps(torch.zeros(0, 3, 2, dtype=F64), torch.zeros(0, 3, 1, dtype=F64), compile=True)


# ------------------------------------------------------------------ online
def test_predict_then_update_refuses_a_predict_of_another_shape():
    # a predict giving 3 values per sample was stacked into (N, 3) predictions for (N, 1)
    # targets; one without the sample dim failed with "Dimension out of range"
    X, Y = _data(n=4)
    m = _linear()
    before = _params(m)
    sgd = torch.optim.SGD(m.parameters(), lr=0.1)
    for bad in (lambda x: torch.zeros(1, 3, dtype=F64), lambda x: torch.zeros(1, dtype=F64)):
        with pytest.raises(ValueError, match=r"predict must return \(\.\.\., 1, 1\)"):
            predict_then_update(m, sgd, X, Y, predict=bad)
    assert torch.equal(_params(m), before)
    preds, _ = predict_then_update(m, sgd, X, Y, predict=lambda x: m(x).unsqueeze(0))
    assert preds.shape == (1, 4, 1)


# ------------------------------------------------------------------ stacked
def _stack(R=3, **kw):
    g = torch.Generator().manual_seed(5)
    return StackedLearner(_linear(), {"weight": torch.randn(R, 1, 2, generator=g, dtype=F64)}, **kw)


def test_select_refuses_an_int_index_out_of_range():
    st = _stack()
    # (select(5) gave a stack of R=0 runs: slice(5, 6) past the end; an all-False mask still
    # gives one, which studies.matrix relies on when every run diverged)
    with pytest.raises(IndexError, match="run index 5 is out of range for 3 runs"):
        st.select(5)
    with pytest.raises(IndexError, match="run index -4"):
        st.select(-4)
    assert st.select(torch.zeros(3, dtype=torch.bool)).runs == 0
    x = torch.rand(3, 4, 2, dtype=F64)
    torch.testing.assert_close(st.select(np.int64(-2))(x[1:2]), st(x)[1:2], **TOL)
    with pytest.raises(ValueError, match="run_dim must be 0 or 1, got True"):  # (taken as 1)
        _stack(run_dim=True)
    st1 = _stack(run_dim=np.int64(1))
    assert type(st1.run_dim) is int
    torch.testing.assert_close(st1(x.transpose(0, 1)), st(x).transpose(0, 1), **TOL)


def test_stack_scaling_bounds_are_checked_and_kept_in_the_parameter_dtype():
    # hi == lo divided by zero (inf/NaN outputs); a list of bounds became float32 (0.1 was
    # 0.10000000149011612)
    with pytest.raises(ValueError, match="hi > lo for every run.*run 1"):
        _stack(lo=torch.zeros(3, dtype=F64), hi=torch.tensor([1.0, 0.0, 2.0], dtype=F64))
    with pytest.raises(ValueError, match="finite"):
        _stack(lo=torch.zeros(3, dtype=F64), hi=torch.tensor([1.0, float("inf"), 2.0], dtype=F64))
    lo, hi = [0.1, -0.2, 0.3], [1.1, 0.7, 2.9]
    st = _stack(lo=lo, hi=hi)
    assert st.lo.dtype == F64 and st.lo.tolist() == lo
    x = torch.rand(3, 4, 2, dtype=F64)
    base = _linear()
    w = _stack().weight
    for r in range(3):  # y = lo + (hi - lo) f((x - lo) / (hi - lo))
        s = hi[r] - lo[r]
        want = lo[r] + s * ((x[r] - lo[r]) / s @ w[r].mT + base.bias.detach())
        torch.testing.assert_close(st(x)[r], want, **TOL)


def test_one_kalman_optimiser_refuses_runs_that_differ_outside_its_state():
    # with the hidden layers frozen, the runs of one optimiser all evaluated base's layer:
    # batched=True trained R runs of modules[0]'s hidden layer without a word
    X, Y = _data(n=6)

    def mlp(seed):
        torch.manual_seed(seed)
        m = nn.Sequential(nn.Linear(2, 3), nn.Tanh(), nn.Linear(3, 1)).double()
        m[0].requires_grad_(False)
        return m

    mods = [mlp(0), mlp(1)]
    with pytest.raises(ValueError, match="differ from base outside the parameters"):
        fit_kalman_runs(mods, (X, Y), batched=True, fit_options=dict(progress=False), R=0.1)
    with pytest.raises(ValueError, match="differ from base outside the parameters"):
        kalman_runs_optimizer(mods[0], mods, R=0.1)
    st = fit_kalman_runs(mods, (X, Y), fit_options=dict(progress=False), R=0.1)  # one each
    ref = mlp(1)
    fit(ref, KalmanOptimizer(ref, R=0.1), (X, Y), progress=False)
    torch.testing.assert_close(st(X.expand(2, -1, -1))[1], ref(X).detach(), **TOL)


def test_stacked_forecaster_refuses_measurements_of_another_layout():
    R, C = 2, 3
    fcs = [
        MeasurementForecaster.ros_elm(
            C, p=2, n_hidden=4, generator=torch.Generator().manual_seed(r)
        )
        for r in range(R)
    ]
    view = StackedForecaster.from_forecasters(fcs)
    z = 1.0 + 0.1 * torch.rand(12, R, C, generator=torch.Generator().manual_seed(0), dtype=F64)
    # (a reshape took (N0, C, R) and (C, R): runs and channels swapped, silently)
    with pytest.raises(ValueError, match=r"z0 must have shape \(N0, R, C\) with R=2 runs and C=3"):
        view.initialize(z.transpose(1, 2).contiguous())
    assert not view.initialized
    view.initialize(z[:10])
    with pytest.raises(ValueError, match=r"z must have shape \(R, C\)"):
        view.update(z[10].mT.contiguous())
    with pytest.raises(ValueError, match=r"z must have shape \(R, C\)"):
        view.update(z[10].reshape(-1))
    assert view.update(z[10]).forecast(np.int64(2)).shape == (2, R, C)
    with pytest.raises(ValueError, match="runs must be a positive int"):
        StackedForecaster(view.inner, 0, C)
