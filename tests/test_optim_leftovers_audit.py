"""EM results that own their tensors, NumPy arrays as Kalman-optimiser options, and empty or
out-of-range run selections of the stacked learner and forecaster.

References are exact and written here: the EM arguments themselves, a plain Kalman filter
(random walk, linear measurement) and the stacked learner's own runs.
"""

from __future__ import annotations

import io

import numpy as np
import pytest
import torch
from _prognosis_helpers import F64, _gen
from torch import nn

from prognos_torch.core.belief import GaussianBelief
from prognos_torch.optim import (
    KalmanOptimizer,
    StackedForecaster,
    StackedLearner,
    em_linear_gaussian,
)
from prognos_torch.prognosis import MeasurementForecaster


# ------------------------------------------------------------------------------ EM
def test_em_returns_its_own_tensors_not_views_of_the_arguments():
    """Parameters that were not learned (and all of them with ``iterations=0``) were the
    caller's tensors or views of them (``init`` the caller's belief itself): an in-place edit
    of the result changed the arguments, and a matrix shared by a batch was an expanded view
    that refused any in-place edit."""
    n = m = 1
    A = torch.tensor([[0.9]], dtype=F64)
    Cm = torch.tensor([[1.0]], dtype=F64)
    SQ = torch.tensor([[0.3]], dtype=F64)
    SR = torch.tensor([[0.5]], dtype=F64)
    init = GaussianBelief(torch.zeros(2, n, dtype=F64), torch.eye(n, dtype=F64).expand(2, n, n))
    ys = torch.randn(6, 2, m, generator=_gen(1), dtype=F64)
    args = (A, Cm, SQ, SR, init.mean, init.chol)
    saved = [a.clone() for a in args]
    for kw in (dict(iterations=1, learn=("A",)), dict(iterations=0)):
        fit = em_linear_gaussian(A, Cm, SQ, SR, init, ys, **kw)
        assert fit.init is not init
        for got, arg in zip((fit.C, fit.chol_Q, fit.chol_R), (Cm, SQ, SR)):
            assert torch.equal(got, arg.expand(2, m if arg is not SQ else n, -1))
        outs = (fit.A, fit.C, fit.chol_Q, fit.chol_R, fit.init.mean, fit.init.chol)
        for out in outs:
            out[0].mul_(2.0)  # one series of the result
        assert all(torch.equal(a, b) for a, b in zip(args, saved))
        assert float(fit.C[1, 0, 0]) == 1.0 and float(fit.chol_R[1, 0, 0]) == 0.5


# ------------------------------------------------------------------------------ Kalman options
D = 3


def _lin() -> nn.Linear:
    torch.manual_seed(0)
    return nn.Linear(D, 1, bias=False, dtype=F64)


def _plain_kf(theta0, P0, Q, r, X, Y):
    """Random walk + linear measurement ``y = X theta``: ``P += diag(Q)``, then the update."""
    m, P = theta0.copy(), np.diag(P0)
    for x, y in zip(X, Y):
        P = P + np.diag(Q)
        S = x @ P @ x.T + r * np.eye(x.shape[0])
        K = np.linalg.solve(S, x @ P).T
        m = m + K @ (y.reshape(-1) - x @ m)
        P = P - K @ S @ K.T
    return m, P


def test_numpy_array_options_are_taken_as_numbers_or_tensors_that_torch_load_reads():
    """``P0``, ``Q`` and ``R`` given as NumPy arrays (and dict priors with NumPy values) were
    kept in ``param_groups``, whose saved copy ``torch.load`` (``weights_only=True``) refused;
    ``lr``, ``fading``, ``chunk_size`` and ``runs`` as 0-d arrays were refused ('must be a
    positive finite number, got array(0.5)'). The step is the plain Kalman filter with
    ``R / lr`` (SRUKF: exact on a model linear in its parameters)."""
    g = _gen(2)
    X = torch.randn(3, 4, D, generator=g, dtype=F64)
    Y = torch.randn(3, 4, 1, generator=g, dtype=F64)
    P0 = np.array([0.5, 0.25, 1.0], dtype=np.float32)
    Q = np.array([1e-3, 0.0, 2e-3])
    arrays = dict(R=np.array(0.2), lr=np.array(0.5), fading=np.array(1.0), chunk_size=np.array(4))
    opt = KalmanOptimizer(_lin(), filter="srukf", P0=P0, Q=Q, **arrays)
    theta0 = opt.theta.numpy()
    for x, y in zip(X, Y):
        opt.step(x, y)
    m, P = _plain_kf(theta0, P0.astype(np.float64), Q, 0.2 / 0.5, X.numpy(), Y.numpy())
    np.testing.assert_allclose(opt.theta.numpy(), m, rtol=0, atol=1e-12)
    np.testing.assert_allclose(opt.parameter_covariance().numpy(), P, rtol=0, atol=1e-12)
    group = opt.param_groups[0]
    assert type(group["lr"]) is float and type(group["chunk_size"]) is int
    assert isinstance(group["P0"], torch.Tensor) and isinstance(group["Q"], torch.Tensor)
    P0[0] = 9.0  # (the group holds a copy: an edit of the caller's array is not its option)
    assert float(group["P0"][0]) == 0.5
    lin = _lin()
    two = KalmanOptimizer([lin.weight], module=lin, runs=np.array(2))
    assert two.runs == 2 and type(two.runs) is int
    prior = KalmanOptimizer(lin, P0={"weight": np.array([[0.5, 0.25, 1.0]])}, R=np.float32(0.5))
    for o, get in ((opt, lambda gr: gr["P0"]), (prior, lambda gr: gr["P0"]["weight"])):
        saved = [{k: v for k, v in gr.items() if k != "params"} for gr in o.param_groups]
        buf = io.BytesIO()
        torch.save(saved, buf)
        buf.seek(0)
        back = torch.load(buf)  # (weights_only=True)
        assert torch.equal(get(back[0]), get(saved[0]))


def test_a_bool_or_complex_lr_tensor_is_refused_and_a_numpy_bool_per_run_data_taken():
    """``lr=torch.tensor(True)`` was read as 1 and a complex tensor lost its imaginary part;
    ``per_run_data=numpy.bool_(True)`` was refused ('must be a bool, got numpy.bool')."""
    for lr in (torch.tensor(True), torch.tensor(0.5 + 0.5j)):
        with pytest.raises(ValueError, match=r"lr'\] must be a positive finite number"):
            KalmanOptimizer(_lin(), lr=lr)
    a = KalmanOptimizer(_lin(), runs=2, per_run_data=np.bool_(True))
    assert a.per_run_data is True and a.param_groups[0]["per_run_data"] is True


# ------------------------------------------------------------------------------ run selection
def test_stacked_learner_select_takes_an_empty_index_and_names_an_index_out_of_range():
    """``select([])`` was refused ('index must be a slice, an int, ...') where an all-False
    mask and an empty int array give no run; ``select([5])`` of 3 runs failed in torch
    ('index 5 is out of bounds for dimension 0 with size 3')."""
    base = nn.Linear(2, 1, dtype=F64)
    st = StackedLearner(base, {"weight": torch.randn(3, 1, 2, generator=_gen(3), dtype=F64)})
    assert st.select([]).runs == 0 and st.select(np.array([], dtype=np.int64)).runs == 0
    for bad in ([5], [0, -4], torch.tensor([3])):
        with pytest.raises(IndexError, match=r"run index (5|-4|3) is out of range for 3 runs"):
            st.select(bad)
    x = torch.rand(2, 4, 2, generator=_gen(4), dtype=F64)
    w, b = st.weight, base.bias.detach()
    out = st.select(torch.tensor([0, -1]))(x)
    for j, r in enumerate((0, 2)):
        np.testing.assert_allclose(
            out[j].detach().numpy(), (x[j] @ w[r].mT + b).numpy(), atol=1e-14
        )


def test_stacked_forecaster_select_names_a_slice_that_selects_no_run():
    """``select(slice(5, 6))`` of 3 runs failed on the inner forecaster ('learners must hold
    one learner per measurement channel (C >= 1)'), which the caller had not passed."""
    fcs = [MeasurementForecaster.ros_elm(2, p=2, n_hidden=3, generator=_gen(r)) for r in range(3)]
    view = StackedForecaster.from_forecasters(fcs)
    for index in (slice(5, 6), slice(1, 1)):
        with pytest.raises(ValueError, match=r"index slice\(.*\) selects no run of the 3 runs"):
            view.select(index)
    sub = view.select(slice(1, None))
    assert sub.runs == 2 and sub.inner.learners == tuple(fcs[1].learners + fcs[2].learners)
