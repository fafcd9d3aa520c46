"""The compiled sequence of optimiser steps (``KalmanOptimizer.steps(compile=True)``,
``fit(compile=True)``) against the eager steps: the same engine, so the same numbers up to
rounding (float64, 1e-12), and exactly the eager result where a step needs a fallback."""

import copy

import pytest
import torch

from prognos_torch.learners import ANFIS
from prognos_torch.optim import KalmanOptimizer, ParameterBridge, fit

P0 = {"alpha": 1.0, "b": 1e-2, "beta": 1e-4}


def _data(T=40):
    g = torch.Generator().manual_seed(3)
    X = torch.rand(T, 3, generator=g, dtype=torch.float64)
    Y = (torch.sin(3 * X[:, :1]) + X[:, 1:2] * X[:, 2:3]).to(torch.float64)
    return X, Y


def _opt(filt, runs=None, R=1e-3):
    X, _ = _data()
    inits = [
        ANFIS(3, 2, generator=torch.Generator().manual_seed(s)).init_premises(X)
        for s in range(runs or 1)
    ]
    model = copy.deepcopy(inits[0])
    theta0 = ParameterBridge(model).stack(inits) if runs else None
    opt = KalmanOptimizer(model, filter=filt, P0=P0, Q=1e-6, R=R, runs=runs, theta0=theta0)
    return model, opt


@pytest.mark.parametrize("filt,runs", [("srukf", None), ("ekf", None), ("ekf", 3)])
def test_compiled_steps_equal_eager_steps(filt, runs):
    X, Y = _data()
    xs, ys = X.unsqueeze(1), Y.unsqueeze(1)  # mini-batches of one sample
    _, eager = _opt(filt, runs)
    loss_e = eager.steps(xs, ys)
    model, comp = _opt(filt, runs)
    loss_c = comp.steps(xs, ys, compile=True)
    assert comp.compile_time > 0.0
    torch.testing.assert_close(loss_c, loss_e, rtol=0, atol=1e-12)
    torch.testing.assert_close(comp.theta, eager.theta, rtol=0, atol=1e-12)
    torch.testing.assert_close(comp.belief.chol, eager.belief.chol, rtol=0, atol=1e-12)
    assert comp.state["kalman"]["step"] == eager.state["kalman"]["step"] == X.shape[0]
    if runs is None:  # the module holds the posterior mean, as after eager steps
        torch.testing.assert_close(ParameterBridge(model).flatten(), comp.theta, rtol=0, atol=0)
    # a second call reuses the compiled code and continues from the state reached
    loss_e2 = eager.steps(xs[:10], ys[:10])
    loss_c2 = comp.steps(xs, ys, compile=True)[:10]
    assert comp.compile_time == 0.0
    torch.testing.assert_close(loss_c2, loss_e2, rtol=0, atol=1e-12)


def test_compiled_steps_fall_back_to_eager_where_a_step_needs_it():
    # R = 1e-16: every update is so informative that the downdate loses precision, so the
    # eager step takes the Joseph form; the compiled pass defers that fallback and reruns
    # eagerly, giving the eager result exactly
    X, Y = _data(12)
    xs, ys = X.unsqueeze(1), Y.unsqueeze(1)
    _, eager = _opt("srukf", R=1e-16)
    loss_e = eager.steps(xs, ys)
    _, comp = _opt("srukf", R=1e-16)
    reruns = []
    rerun = comp._steps_eager_from
    comp._steps_eager_from = lambda *a: reruns.append(1) or rerun(*a)
    loss_c = comp.steps(xs, ys, compile=True)
    assert reruns == [1]
    assert torch.equal(loss_c, loss_e)
    assert torch.equal(comp.theta, eager.theta)


def test_fit_compile_matches_eager_fit_and_keeps_compile_time_apart():
    X, Y = _data(25)
    model_e, eager = _opt("srukf")
    he = fit(model_e, eager, (X, Y), batch_size=2, progress=False)  # 12 full batches + 1
    model_c, comp = _opt("srukf")
    hc = fit(model_c, comp, (X, Y), batch_size=2, progress=False, compile=True)
    torch.testing.assert_close(comp.theta, eager.theta, rtol=0, atol=1e-12)
    torch.testing.assert_close(hc.loss[0], he.loss[0], rtol=0, atol=1e-12)
    assert hc.steps == he.steps == 13
    assert len(hc.compile_time) == 1 and he.compile_time == [0.0]


def test_compile_refuses_what_it_cannot_trace():
    X, Y = _data(4)
    _, opt = _opt("imsrukf")
    with pytest.raises(ValueError, match="noise estimator"):
        opt.steps(X.unsqueeze(1), Y.unsqueeze(1), compile=True)
    model = ANFIS(3, 2)
    adam = torch.optim.Adam(model.parameters())
    with pytest.raises(ValueError, match="compile=True needs a KalmanOptimizer"):
        fit(model.double(), adam, (X, Y), compile=True, progress=False)
    _, opt = _opt("srukf")
    with pytest.raises(ValueError, match="one row per step"):
        opt.steps(X.unsqueeze(1), Y[:3].unsqueeze(1), compile=True)


def test_compiled_steps_of_a_learner_with_a_one_by_one_fixed_matrix():
    """An ELM with one input and one hidden node holds a 1 x 1 fixed input weight, whose
    transposed product the C++ wrapper's loop code miscompiles in torch 2.13 (the process
    aborts); the pass takes the Python wrapper and equals the eager steps."""
    from prognos_torch.learners import ELM

    g = torch.Generator().manual_seed(0)
    X = torch.rand(30, 1, 1, generator=g, dtype=torch.float64)
    Y = torch.sin(3.0 * X.sum(-1, keepdim=True))
    losses = []
    for compile in (False, True):
        model = ELM(1, 1)
        opt = KalmanOptimizer(model, filter="ekf", P0=1.0, Q=1e-6, R=1e-3)
        losses.append((opt.steps(X, Y, compile=compile), opt.theta))
    torch.testing.assert_close(losses[1][0], losses[0][0], rtol=0, atol=1e-12)
    torch.testing.assert_close(losses[1][1], losses[0][1], rtol=0, atol=1e-12)


class _Gains(torch.nn.Module):
    """Two trained weights and a fixed ``(2, 1, 1)`` gain used through ``.mT``: an input of
    the compiled loop that is a view with its base's layout, as the ELM's 1 x 1 weight is."""

    def __init__(self):
        super().__init__()
        self.w = torch.nn.Parameter(torch.tensor([0.5, 0.1], dtype=torch.float64))
        self.register_buffer("gain", torch.tensor([[[1.5]], [[-0.7]]], dtype=torch.float64))

    def forward(self, x):
        return (x.unsqueeze(0) * self.gain.mT).sum(0) * self.w[0] + self.w[1]


def test_compiled_steps_of_a_learner_with_a_batch_of_one_by_one_fixed_matrices():
    """Not only a 1 x 1 matrix: a fixed tensor whose last two dimensions are 1 x 1 sends the
    pass to the Python wrapper too (the C++ wrapper aborts the process on this learner)."""
    g = torch.Generator().manual_seed(1)
    X = torch.rand(30, 1, 1, generator=g, dtype=torch.float64)
    Y = 0.4 * X.sum(-1, keepdim=True) + 0.2
    losses = []
    for compile in (False, True):
        opt = KalmanOptimizer(_Gains(), filter="srukf", P0=1.0, Q=1e-6, R=1e-3)
        losses.append((opt.steps(X, Y, compile=compile), opt.theta))
    torch.testing.assert_close(losses[1][0], losses[0][0], rtol=0, atol=1e-12)
    torch.testing.assert_close(losses[1][1], losses[0][1], rtol=0, atol=1e-12)
