"""Missing targets (NaN) in training: the Kalman optimisers update with the observed entries,
the gradient baselines' default loss and the metrics leave them out.

References: closed-form ridge regression on the observed rows (a Kalman optimiser with
``Q = 0`` and unit ``R`` is recursive least squares), the random-walk prediction
``P + Q`` for a step that observes nothing, the EKF for the sigma-point optimisers on a linear
model, and full-batch gradient descent on the observed rows alone.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from torch import nn

from prognos_torch.learners import ELM
from prognos_torch.optim import EKF, SRUKF, KalmanOptimizer, fit

torch.set_num_threads(1)


def _data(N=24, d=3, n_out=2, seed=0, frac=0.3):
    g = torch.Generator().manual_seed(seed)
    X = torch.randn(N, d, generator=g, dtype=torch.float64)
    W = torch.randn(d, n_out, generator=g, dtype=torch.float64)
    Y = X @ W + 0.1 * torch.randn(N, n_out, generator=g, dtype=torch.float64)
    Ym = Y.clone()
    Ym[torch.rand(N, n_out, generator=g) < frac] = float("nan")
    Ym[5] = float("nan")  # one sample with no target at all
    return X, Y, Ym


def _ridge_observed(X: np.ndarray, Y: np.ndarray, lam: float) -> np.ndarray:
    """Ridge of each output column on the rows where that column is observed: ``(d, n_out)``."""
    cols = []
    for j in range(Y.shape[1]):
        o = ~np.isnan(Y[:, j])
        H, t = X[o], Y[o, j]
        cols.append(np.linalg.solve(H.T @ H + lam * np.eye(X.shape[1]), H.T @ t))
    return np.stack(cols, 1)


@pytest.mark.parametrize("batch_size", [1, 4])
def test_kalman_optimiser_with_missing_targets_equals_ridge_on_observed_rows(batch_size):
    X, _, Ym = _data()
    lam = 0.4
    lin = nn.Linear(3, 2, bias=False, dtype=torch.float64)
    opt = EKF(lin, P0=1.0 / lam, Q=0.0, R=1.0, theta0=torch.zeros(6, dtype=torch.float64))
    hist = fit(lin, opt, (X, Ym), batch_size=batch_size, progress=False)
    beta = _ridge_observed(X.numpy(), Ym.numpy(), lam)
    np.testing.assert_allclose(lin.weight.detach().numpy(), beta.T, rtol=0, atol=1e-8)
    # the metrics leave the missing targets out
    pred = X.numpy() @ beta
    err = pred - Ym.numpy()
    o = ~np.isnan(err)
    np.testing.assert_allclose(float(hist.train["mae"][-1]), np.abs(err[o]).mean(), atol=1e-10)
    np.testing.assert_allclose(
        float(hist.train["rmse"][-1]), np.sqrt((err[o] ** 2).mean()), atol=1e-10
    )
    assert np.isfinite(float(hist.loss[-1]))


def test_step_loss_is_the_mean_over_observed_targets_and_nothing_observed_is_a_prediction():
    X, _, Ym = _data()
    lin = nn.Linear(3, 2, dtype=torch.float64)
    opt = EKF(lin, P0=0.5, Q=1e-2, R=0.3)
    opt.step(X[:4], Ym[:4].nan_to_num(0.0))
    # the loss: the mean squared pre-update error over the observed entries
    xb, yb = X[6:10], Ym[6:10]
    assert bool(torch.isnan(yb).any()) and not bool(torch.isnan(yb).all())
    with torch.no_grad():
        e = (yb - lin(xb))[~torch.isnan(yb)]
    r = opt.step(xb, yb)
    torch.testing.assert_close(r.loss, e.square().mean(), rtol=0, atol=1e-12)
    # a mini-batch with no observed target: the random walk's prediction (mean kept, P + Q)
    theta, P = opt.theta.clone(), opt.parameter_covariance().clone()
    r = opt.step(X[:2], torch.full((2, 2), float("nan"), dtype=torch.float64))
    assert bool(torch.isnan(r.loss))
    torch.testing.assert_close(opt.theta, theta, rtol=0, atol=0)
    torch.testing.assert_close(
        opt.parameter_covariance(), P + 1e-2 * torch.eye(8, dtype=torch.float64), rtol=0, atol=1e-12
    )


def test_sigma_point_optimiser_with_missing_targets_equals_the_ekf_on_a_linear_model():
    X, _, Ym = _data(seed=3)
    kw = dict(P0=0.7, Q=1e-3, R=0.2)
    a, b = nn.Linear(3, 2, dtype=torch.float64), nn.Linear(3, 2, dtype=torch.float64)
    b.load_state_dict(a.state_dict())
    oa, ob = EKF(a, **kw), SRUKF(b, **kw)
    for i in range(0, 24, 4):
        ra, rb = oa.step(X[i : i + 4], Ym[i : i + 4]), ob.step(X[i : i + 4], Ym[i : i + 4])
        torch.testing.assert_close(ra.loss, rb.loss, rtol=0, atol=1e-10, equal_nan=True)
    torch.testing.assert_close(oa.theta, ob.theta, rtol=0, atol=1e-10)
    torch.testing.assert_close(
        oa.parameter_covariance(), ob.parameter_covariance(), rtol=0, atol=1e-10
    )


def test_runs_with_missing_targets_equal_separate_runs():
    X, _, Ym = _data(seed=4)
    elm = ELM(3, 5, n_out=2, generator=torch.Generator().manual_seed(1))
    batched = EKF(elm, runs=3, P0=1.0, Q=1e-3, R=0.5)
    ref = EKF(elm, P0=1.0, Q=1e-3, R=0.5)  # the runs share the data and the start
    for i in range(0, 24, 4):
        rb = batched.step(X[i : i + 4], Ym[i : i + 4])
        rr = ref.step(X[i : i + 4], Ym[i : i + 4])
        torch.testing.assert_close(rb.loss, rr.loss.expand(3), rtol=0, atol=1e-12)
    torch.testing.assert_close(batched.theta, ref.theta.expand(3, -1), rtol=0, atol=1e-12)


def test_gradient_baseline_default_loss_leaves_missing_targets_out():
    X, _, Ym = _data(seed=5, n_out=1)
    obs = ~torch.isnan(Ym[:, 0])
    a = nn.Linear(3, 1, dtype=torch.float64)
    b = nn.Linear(3, 1, dtype=torch.float64)
    b.load_state_dict(a.state_dict())
    ha = fit(
        a, torch.optim.SGD(a.parameters(), lr=0.1), (X, Ym), epochs=5, batch_size=24, progress=False
    )
    hb = fit(
        b,
        torch.optim.SGD(b.parameters(), lr=0.1),
        (X[obs], Ym[obs]),
        epochs=5,
        batch_size=int(obs.sum()),
        progress=False,
    )
    torch.testing.assert_close(a.weight, b.weight, rtol=0, atol=1e-14)
    torch.testing.assert_close(torch.stack(ha.loss), torch.stack(hb.loss), rtol=0, atol=1e-14)
    torch.testing.assert_close(ha.train["mae"][-1], hb.train["mae"][-1], rtol=0, atol=1e-14)


def test_bad_values_are_refused_by_name():
    X, Y, Ym = _data()
    lin = nn.Linear(3, 2, dtype=torch.float64)
    bad = Y.clone()
    bad[0, 0] = float("inf")
    with pytest.raises(ValueError, match="train targets Y contains inf"):
        fit(lin, EKF(lin), (X, bad), progress=False)
    with pytest.raises(ValueError, match="targets contains inf"):
        EKF(lin).step(X[:2], bad[:2])
    Xn = X.clone()
    Xn[2, 1] = float("nan")
    with pytest.raises(ValueError, match="train inputs X"):
        fit(lin, torch.optim.SGD(lin.parameters(), lr=0.1), (Xn, Y), progress=False)
    with pytest.raises(ValueError, match="val inputs X"):
        fit(lin, EKF(lin), (X, Y), val=(Xn, Y), progress=False)
    with pytest.raises(ValueError, match="custom loss_fn"):
        fit(
            lin,
            torch.optim.SGD(lin.parameters(), lr=0.1),
            (X, Ym),
            progress=False,
            loss_fn=nn.functional.l1_loss,
        )
    with pytest.raises(ValueError, match="compiled pass needs complete targets"):
        SRUKF(lin).steps(X[:20].reshape(5, 4, 3), Ym[:20].reshape(5, 4, 2), compile=True)


def test_robust_filter_refuses_partly_missing_batches_and_predicts_through_empty_ones():
    from prognos_torch.filters import rukf

    X, _, Ym = _data()
    lin = nn.Linear(3, 2, dtype=torch.float64)
    M = 0.1 * torch.eye(8, dtype=torch.float64)
    opt = KalmanOptimizer(lin, filter=rukf(1.05, M, 0.1), P0=0.5, Q=1e-3, R=0.2)
    part = Ym[6:10].clone()
    assert bool(torch.isnan(part).any()) and not bool(torch.isnan(part).all())
    theta = opt.theta.clone()
    with pytest.raises(ValueError, match="robust filter updates with whole mini-batches"):
        opt.step(X[6:10], part)
    torch.testing.assert_close(opt.theta, theta, rtol=0, atol=0)  # nothing written
    opt.step(X[:4], torch.full((4, 2), float("nan"), dtype=torch.float64))  # a prediction
    torch.testing.assert_close(opt.theta, theta, rtol=0, atol=0)


def test_fit_refuses_compile_with_missing_targets_before_any_step():
    X, _, Ym = _data(N=12)
    lin = nn.Linear(3, 2, dtype=torch.float64)
    opt = SRUKF(lin)
    theta = opt.theta.clone()
    with pytest.raises(ValueError, match="compiled pass needs complete targets"):
        fit(lin, opt, (X, Ym), batch_size=5, compile=True, progress=False)
    torch.testing.assert_close(opt.theta, theta, rtol=0, atol=0)


def test_gradient_optimiser_takes_no_step_on_a_batch_with_nothing_observed():
    X, Y, _ = _data(N=6, n_out=1)
    Ym = Y.clone()
    Ym[2:4] = float("nan")  # the second mini-batch of 2 has no target
    a, b = nn.Linear(3, 1, dtype=torch.float64), nn.Linear(3, 1, dtype=torch.float64)
    b.load_state_dict(a.state_dict())
    ha = fit(a, torch.optim.SGD(a.parameters(), lr=0.1, momentum=0.9), (X, Ym), batch_size=2,
             progress=False)  # fmt: skip
    keep = torch.tensor([0, 1, 4, 5])
    hb = fit(b, torch.optim.SGD(b.parameters(), lr=0.1, momentum=0.9), (X[keep], Y[keep]),
             batch_size=2, progress=False)  # fmt: skip
    torch.testing.assert_close(a.weight, b.weight, rtol=0, atol=0)
    torch.testing.assert_close(ha.loss[0], hb.loss[0], rtol=0, atol=1e-15)


def test_all_missing_targets_of_a_run_are_refused_by_name():
    X, Y, _ = _data(N=12, n_out=1)
    lin = nn.Linear(3, 1, dtype=torch.float64)
    nan = torch.full_like(Y, float("nan"))
    with pytest.raises(ValueError, match="val targets Y are all missing"):
        fit(lin, EKF(lin), (X, Y), val=(X, nan), early_stopping=2, progress=False)
    from prognos_torch.optim import KalmanOptimizer as KO

    Yr = torch.stack([Y, nan, Y])
    Xr = X.expand(3, -1, -1).clone()
    with pytest.raises(ValueError, match="train targets Y of run 1 are all missing"):
        fit(lin, KO(lin, runs=3, per_run_data=True), (Xr, Yr), progress=False)


def test_fit_together_leaves_missing_targets_out():
    from prognos_torch.optim import fit_together

    X, Y, _ = _data(N=10, n_out=1)
    Ym = Y.clone()
    Ym[[2, 7]] = float("nan")
    keep = ~torch.isnan(Ym[:, 0])
    init = [nn.Linear(3, 1, dtype=torch.float64) for _ in range(2)]
    again = [nn.Linear(3, 1, dtype=torch.float64) for _ in range(2)]
    for a, b in zip(init, again):
        b.load_state_dict(a.state_dict())

    def opt(ps):
        return torch.optim.Adam(ps, lr=1e-2)

    sa = fit_together(init, opt, (X, Ym), epochs=3, batch_size=10, progress=False)
    sb = fit_together(again, opt, (X[keep], Y[keep]), epochs=3, batch_size=8, progress=False)
    for pa, pb in zip(sa.parameter_sets().values(), sb.parameter_sets().values()):
        torch.testing.assert_close(pa, pb, rtol=0, atol=1e-15)
