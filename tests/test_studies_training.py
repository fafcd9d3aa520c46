"""studies.training (timed training over pairs, frozen and online readings, runs batched or in
turn) and the per-run summaries of studies.evaluate, against closed forms: plain SGD on
``y = w x`` with ``x = 1`` (a geometric sequence of weights) and the Kalman filter of a scalar
parameter under a zero random walk (the posterior of Bayesian linear regression)."""

from __future__ import annotations

import math

import pytest
import torch
from torch import nn

from prognos_torch.optim import KalmanOptimizer
from prognos_torch.studies import (
    TrainTest,
    kalman_runs,
    lowest_counts,
    outcome_rows,
    run_errors,
    runs_in_turn,
    train_and_test,
    untrained_runs,
)

C, LR = 2.0, 0.1  # every target is C; SGD on (w - C)^2: w_{k+1} = w_k - 2 LR (w_k - C)
A = 1.0 - 2.0 * LR  # so w_k = C + (w_0 - C) A^k
N_TRAIN, N_TEST = 5, 3


def _linear(w0: float) -> nn.Linear:
    m = nn.Linear(1, 1, bias=False, dtype=torch.float64)
    with torch.no_grad():
        m.weight.fill_(w0)
    return m


def _pairs(n: int) -> tuple[torch.Tensor, torch.Tensor]:
    return torch.ones(n, 1, dtype=torch.float64), torch.full((n, 1), C, dtype=torch.float64)


def _w(w0: float, k: int) -> float:
    return C + (w0 - C) * A**k


def test_run_errors_by_hand():
    pred = torch.tensor([[1.0, -1.0, 1.0, -1.0], [3.0, 0.0, 0.0, 0.0]], dtype=torch.float64)
    e = run_errors(pred, torch.zeros(4, dtype=torch.float64))
    torch.testing.assert_close(e["MAE"], torch.tensor([1.0, 0.75], dtype=torch.float64))
    torch.testing.assert_close(e["RMSE"], torch.tensor([1.0, 1.5], dtype=torch.float64))
    torch.testing.assert_close(e["MSE"], torch.tensor([1.0, 2.25], dtype=torch.float64))
    assert run_errors(pred[0], torch.zeros(4))["MAE"].shape == ()  # one run: no run dim


def test_lowest_counts_by_hand_ties_to_the_first():
    s = {"a": torch.tensor([1.0, 5.0, 2.0, 1.0]), "b": torch.tensor([2.0, 1.0, 2.0, 1.0])}
    s["c"] = torch.tensor([3.0, 3.0, 0.0, 4.0])
    # run 0: a; run 1: b; run 2: c; run 3: a and b tie -> a
    assert lowest_counts(s) == {"a": 2, "b": 1, "c": 1}


def test_train_and_test_sgd_closed_form():
    w0, m = 0.0, _linear(0.0)
    opt = torch.optim.SGD(m.parameters(), lr=LR)
    test = (torch.tensor([[1.0], [2.0], [3.0]], dtype=torch.float64), _pairs(N_TEST)[1])
    out = train_and_test(m, opt, _pairs(N_TRAIN), test, block=2, online=True)
    wN = _w(w0, N_TRAIN)
    f64 = dict(dtype=torch.float64)
    torch.testing.assert_close(out.pred, wN * torch.tensor([1.0, 2.0, 3.0], **f64))
    torch.testing.assert_close(out.pred_train, torch.full((N_TRAIN,), wN, **f64))
    # the loss before step k is (w_k - C)^2 = (w0 - C)^2 A^(2k); blocks of 2, 2, 1 steps
    loss = [(w0 - C) ** 2 * A ** (2 * k) for k in range(N_TRAIN)]
    blocks = [(loss[0] + loss[1]) / 2, (loss[2] + loss[3]) / 2, loss[4]]
    assert out.curve_steps == [2, 4, 5]
    torch.testing.assert_close(out.curve, torch.tensor(blocks, **f64))
    # online: test sample j predicted with w_{N+j} (x_j = 1, 2, 3), then one step on it
    w = wN
    want = []
    for x in (1.0, 2.0, 3.0):
        want.append(w * x)
        w -= LR * 2.0 * x * (w * x - C)
    torch.testing.assert_close(out.online_pred, torch.tensor(want, **f64))
    torch.testing.assert_close(m.weight.detach(), torch.full((1, 1), w, **f64))  # after the pass
    assert out.train_time > 0 and out.test_time > 0 and out.online_time > 0
    m2 = _linear(0.0)
    frozen = train_and_test(m2, torch.optim.SGD(m2.parameters(), lr=LR), _pairs(N_TRAIN), test,
                            block=5)  # fmt: skip
    torch.testing.assert_close(frozen.pred, out.pred)
    assert frozen.online_pred is None and math.isnan(frozen.online_time)


def test_runs_in_turn_stacks_runs_and_averages_seconds():
    inits = [_linear(0.0), _linear(4.0)]
    out = runs_in_turn(
        inits, lambda m: torch.optim.SGD(m.parameters(), lr=LR), _pairs(N_TRAIN),
        _pairs(N_TEST), block=2, online=True,
    )  # fmt: skip
    wN = torch.tensor([_w(0.0, N_TRAIN), _w(4.0, N_TRAIN)], dtype=torch.float64)
    torch.testing.assert_close(out.pred, wN[:, None].expand(2, N_TEST))
    torch.testing.assert_close(out.pred_train, wN[:, None].expand(2, N_TRAIN))
    w_on = [[_w(w0, N_TRAIN + j) for j in range(N_TEST)] for w0 in (0.0, 4.0)]
    torch.testing.assert_close(out.online_pred, torch.tensor(w_on, dtype=torch.float64))
    assert out.curve_steps == [2, 4, 5]
    loss = [[(w0 - C) ** 2 * A ** (2 * k) for k in range(N_TRAIN)] for w0 in (0.0, 4.0)]
    blocks = [[(r[0] + r[1]) / 2, (r[2] + r[3]) / 2, r[4]] for r in loss]
    torch.testing.assert_close(out.curve, torch.tensor(blocks, dtype=torch.float64).T)  # (3, R)
    assert inits[0].weight.item() == 0.0  # the initialisations are copied, not trained


def test_kalman_runs_equal_the_scalar_kalman_posterior():
    """Zero random walk, prior N(m0, P0), y = w + v with v ~ N(0, R): after k samples the
    posterior is P_k = 1 / (1/P0 + k/R), m_k = P_k (m0/P0 + k C / R); each run keeps its m0."""
    P0, R = 0.5, 0.2
    inits = [_linear(0.0), _linear(-1.0), _linear(3.0)]
    opts = dict(filter="ekf", P0=P0, Q=0.0, R=R)
    out = kalman_runs(inits, _pairs(N_TRAIN), _pairs(N_TEST), block=N_TRAIN, online=True, **opts)

    def m(m0, k):
        return (m0 / P0 + k * C / R) / (1 / P0 + k / R)

    m0s = (0.0, -1.0, 3.0)
    mN = torch.tensor([m(m0, N_TRAIN) for m0 in m0s], dtype=torch.float64)
    torch.testing.assert_close(out.pred, mN[:, None].expand(3, N_TEST))
    w_on = [[m(m0, N_TRAIN + j) for j in range(N_TEST)] for m0 in m0s]
    torch.testing.assert_close(out.online_pred, torch.tensor(w_on, dtype=torch.float64))
    # the loss of a step: the squared innovation (C - m_k)^2 before the update
    loss = [sum((C - m(m0, k)) ** 2 for k in range(N_TRAIN)) / N_TRAIN for m0 in m0s]
    torch.testing.assert_close(out.curve, torch.tensor([loss], dtype=torch.float64))
    # one run at a time, predicting through the module: the same numbers
    alone = runs_in_turn(inits, lambda mod: KalmanOptimizer(mod, **opts), _pairs(N_TRAIN),
                         _pairs(N_TEST), block=2)  # fmt: skip
    torch.testing.assert_close(alone.pred, out.pred)


def test_per_run_divides_the_seconds():
    t = TrainTest(torch.zeros(2, 1), torch.zeros(2, 1), 2.0, 4.0, online_time=6.0).per_run(2)
    assert (t.train_time, t.test_time, t.online_time) == (1.0, 2.0, 3.0)


def test_untrained_runs_predict_with_the_initial_modules():
    X = torch.tensor([[1.0], [-2.0]], dtype=torch.float64)
    out = untrained_runs([_linear(0.5), _linear(3.0)], X[:1], X)
    torch.testing.assert_close(out.pred, torch.tensor([[0.5, -1.0], [3.0, -6.0]]).double())
    torch.testing.assert_close(out.pred_train, torch.tensor([[0.5], [3.0]]).double())
    assert out.train_time == 0.0 and out.test_time > 0 and out.curve is None


def test_outcome_rows_by_hand():
    f64 = dict(dtype=torch.float64)
    out = TrainTest(
        pred=torch.tensor([[1.0, 2.0], [3.0, 3.0]], **f64),
        pred_train=torch.tensor([[0.0], [1.0]], **f64),
        train_time=0.25,
        test_time=0.125,
        online_pred=torch.tensor([[1.0, 1.0], [1.0, 3.0]], **f64),
        online_time=0.5,
    )
    y_train, y_test = torch.ones(1, **f64), torch.ones(2, **f64)
    rows = outcome_rows("m", out, y_train, y_test)
    keys = ["run", "method", "MAE", "RMSE", "MSE", "train_MAE"]
    assert list(rows[0]) == keys + ["train_time_s", "test_time_s", "time_s"]
    assert [[r[k] for k in keys] for r in rows] == [
        [0, "m", 0.5, pytest.approx(math.sqrt(0.5)), pytest.approx(0.5), 1.0],
        [1, "m", 2.0, 2.0, 4.0, 0.0],
    ]
    assert [rows[0][k] for k in ("train_time_s", "test_time_s", "time_s")] == [0.25, 0.125, 0.375]
    on = outcome_rows("m", out, y_train, y_test, online=True)
    assert [r["MAE"] for r in on] == [0.0, 1.0] and on[1]["train_MAE"] == 0.0
    assert [on[0][k] for k in ("test_time_s", "time_s")] == [0.5, 0.75]
