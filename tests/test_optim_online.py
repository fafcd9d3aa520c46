"""optim.online: training in blocks and predict-then-update against plain fit/step loops."""

from __future__ import annotations

import copy

import pytest
import torch

from prognos_torch.learners import ANFIS
from prognos_torch.optim import (
    KalmanOptimizer,
    ParameterBridge,
    fit,
    predict_then_update,
    train_in_blocks,
)


def _data(n=40, seed=3):
    g = torch.Generator().manual_seed(seed)
    X = torch.rand(n, 3, generator=g, dtype=torch.float64)
    Y = (X.sum(-1, keepdim=True) / 3.0) ** 2
    return X, Y


def _inits(X, seeds):
    return [ANFIS(3, 2, generator=torch.Generator().manual_seed(s)).init_premises(X) for s in seeds]


def test_train_in_blocks_equals_one_fit_call():
    X, Y = _data()
    inits = _inits(X, (0, 1))

    def kalman():
        m = copy.deepcopy(inits[0])
        theta0 = ParameterBridge(m).stack(inits)
        return m, KalmanOptimizer(
            m, filter="imsrukf", P0=0.5, Q=1e-6, R=1e-3, runs=2, theta0=theta0
        )

    def adam():
        m = copy.deepcopy(inits[1])
        return m, torch.optim.Adam(m.parameters(), lr=1e-2)

    for make in (kalman, adam):
        m1, o1 = make()
        h = fit(m1, o1, (X, Y), epochs=2, progress=False)
        m2, o2 = make()
        steps, losses, secs = train_in_blocks(m2, o2, X, Y, block=7, passes=2)
        assert steps == [7, 14, 21, 28, 35, 40, 47, 54, 61, 68, 75, 80] and secs > 0
        if isinstance(o1, KalmanOptimizer):
            assert losses.shape == (12, 2)
            torch.testing.assert_close(o2.theta, o1.theta, rtol=0, atol=0)
        else:
            assert losses.shape == (12,)
            for p1, p2 in zip(m1.parameters(), m2.parameters()):
                torch.testing.assert_close(p2, p1, rtol=0, atol=0)
        # the block losses average to the per-epoch losses of the single call
        sizes = torch.tensor([7.0] * 5 + [5.0], dtype=torch.float64)
        sizes = sizes.reshape(-1, *([1] * (losses.dim() - 1)))
        for e in range(2):
            blk = losses[6 * e : 6 * e + 6]
            torch.testing.assert_close((blk * sizes).sum(0) / 40.0, h.loss[e])


def test_predict_then_update_equals_a_manual_filter_loop():
    X, Y = _data(12, seed=5)
    inits = _inits(X, (2, 3))

    def make():
        m = copy.deepcopy(inits[0])
        theta0 = ParameterBridge(m).stack(inits)
        return m, KalmanOptimizer(m, filter="srukf", P0=0.5, Q=1e-6, R=1e-3, runs=2, theta0=theta0)

    m, opt = make()
    pred, secs = predict_then_update(m, opt, X, Y)  # default predictor: opt.predict
    _, ref = make()
    want = []
    for k in range(X.shape[0]):
        want.append(ref.predict(X[k : k + 1])[:, 0])  # predicted before the update
        ref.step(X[k : k + 1], Y[k : k + 1])
    torch.testing.assert_close(pred, torch.stack(want, -2), rtol=0, atol=0)
    torch.testing.assert_close(opt.theta, ref.theta, rtol=0, atol=0)
    assert pred.shape == (2, 12, 1) and secs > 0


def test_predict_then_update_with_a_gradient_optimizer_equals_a_manual_loop():
    X, Y = _data(10, seed=7)
    init = _inits(X, (4,))[0]
    m, ref = copy.deepcopy(init), copy.deepcopy(init)
    opt = torch.optim.SGD(m.parameters(), lr=0.1)
    ref_opt = torch.optim.SGD(ref.parameters(), lr=0.1)
    pred, _ = predict_then_update(m, opt, X, Y)  # default predictor: the module
    want = []
    for k in range(X.shape[0]):
        with torch.no_grad():
            want.append(ref(X[k : k + 1])[0])
        ref_opt.zero_grad()
        torch.nn.functional.mse_loss(ref(X[k : k + 1]), Y[k : k + 1]).backward()
        ref_opt.step()
    torch.testing.assert_close(pred, torch.stack(want), rtol=0, atol=0)
    for p1, p2 in zip(m.parameters(), ref.parameters()):
        torch.testing.assert_close(p1, p2, rtol=0, atol=0)


def test_per_run_data_blocks_and_online_steps_along_the_sample_dim():
    # per_run_data: every run has its own series (R, N, ...); blocks and online steps cut dim 1
    X, Y = _data(9, seed=11)
    Xr = torch.stack([X, X.flip(0)])
    Yr = torch.stack([Y, Y.flip(0) ** 0.5])
    inits = _inits(X, (5, 6))

    def make():
        m = copy.deepcopy(inits[0])
        theta0 = ParameterBridge(m).stack(inits)
        kw = dict(P0=0.5, Q=1e-6, R=1e-3, runs=2, theta0=theta0, per_run_data=True)
        return m, KalmanOptimizer(m, filter="srukf", **kw)

    m1, o1 = make()
    fit(m1, o1, (Xr, Yr), progress=False)
    m2, o2 = make()
    steps, losses, _ = train_in_blocks(m2, o2, Xr, Yr, block=4)
    assert steps == [4, 8, 9] and losses.shape == (3, 2)
    torch.testing.assert_close(o2.theta, o1.theta, rtol=0, atol=0)
    pred, _ = predict_then_update(m2, o2, Xr, Yr)
    want = []
    for k in range(9):
        want.append(o1.predict(Xr[:, k : k + 1])[:, 0])
        o1.step(Xr[:, k : k + 1], Yr[:, k : k + 1])
    assert pred.shape == (2, 9, 1)
    torch.testing.assert_close(pred, torch.stack(want, 1), rtol=0, atol=0)
    torch.testing.assert_close(o2.theta, o1.theta, rtol=0, atol=0)


def test_online_helpers_reject_bad_input():
    X, Y = _data(6)
    m = _inits(X, (0,))[0]
    opt = torch.optim.SGD(m.parameters(), lr=0.1)
    with pytest.raises(ValueError, match="block"):
        train_in_blocks(m, opt, X, Y, block=0)
    with pytest.raises(ValueError, match="passes"):
        train_in_blocks(m, opt, X, Y, block=2, passes=True)
    with pytest.raises(ValueError, match="same non-zero number of rows"):
        train_in_blocks(m, opt, X, Y[:4], block=2)
    with pytest.raises(TypeError, match="pair"):
        predict_then_update(m, opt, X.numpy(), Y)
    with pytest.raises(TypeError, match="predict"):
        predict_then_update(m, opt, X, Y, predict=3)


def test_blocks_and_online_steps_take_samples_with_no_observed_target():
    # NaN targets are missing measurements (fit steps through a sample with none observed: the
    # Kalman step is the filter's prediction, a gradient optimiser takes none); a block or an
    # online sample that observes nothing is one such step, not "nothing to fit"
    g = torch.Generator().manual_seed(4)
    X = torch.randn(10, 3, generator=g, dtype=torch.float64)
    Y = X @ torch.tensor([[1.0], [-2.0], [0.5]], dtype=torch.float64)
    Y[4:6] = float("nan")  # block 2 of blocks of 2 sees no target
    Yr = torch.stack([Y, X.sum(-1, keepdim=True)])  # per-run: run 1 observes every sample

    def lin():
        m = torch.nn.Linear(3, 1, dtype=torch.float64)
        with torch.no_grad():
            m.weight.copy_(torch.randn(1, 3, generator=torch.Generator().manual_seed(0)))
            m.bias.zero_()
        return m

    for make in (
        lambda m: KalmanOptimizer(m, P0=10.0, R=0.1),
        lambda m: torch.optim.SGD(m.parameters(), lr=0.1, momentum=0.5),
        lambda m: KalmanOptimizer(m, P0=10.0, R=0.1, runs=2, per_run_data=True),
    ):
        runs = getattr(make(lin()), "runs", None)
        data = (X.expand(2, 10, 3), Yr) if runs else (X, Y)
        m1 = lin()
        o1 = make(m1)
        h = fit(m1, o1, data, batch_size=1, progress=False)  # the uninterrupted reference
        m2 = lin()
        o2 = make(m2)
        steps, losses, _ = train_in_blocks(m2, o2, *data, block=2)
        assert steps == [2, 4, 6, 8, 10]
        blk = losses[2] if runs is None else losses[2, 0]
        assert bool(torch.isnan(blk)) and bool(torch.isfinite(losses[:2]).all())
        for p1, p2 in zip(m1.parameters(), m2.parameters()):
            torch.testing.assert_close(p2, p1, rtol=0, atol=0)
        if runs:
            torch.testing.assert_close(o2.theta, o1.theta, rtol=0, atol=0)
        torch.testing.assert_close(losses.nanmean(0), h.loss[0])  # blocks of 2, no NaN step
    # online: predicted first, then the filter's prediction step (P + Q) where nothing is seen
    m, ref = lin(), lin()
    opt, ref_opt = KalmanOptimizer(m, P0=10.0, R=0.1), KalmanOptimizer(ref, P0=10.0, R=0.1)
    pred, _ = predict_then_update(m, opt, X, Y)
    want = []
    for k in range(10):
        want.append(ref_opt.predict(X[k : k + 1])[0])
        ref_opt.step(X[k : k + 1], Y[k : k + 1])
    torch.testing.assert_close(pred, torch.stack(want), rtol=0, atol=0)
    torch.testing.assert_close(opt.belief.chol, ref_opt.belief.chol, rtol=0, atol=0)
    with pytest.raises(ValueError, match="all missing"):  # the stream needs one target
        predict_then_update(m, opt, X, torch.full_like(Y, float("nan")))
