"""learners.lssvr_gram's fitting helpers (fit_lssvr_gram, lssvr_gram_fitter, lssvr_grid_cv)
against the LS-SVR's KKT system (paper 002 Eq. 4) solved densely."""

from __future__ import annotations

import pytest
import torch

from prognos_torch.learners import (
    MultiStepCV,
    blocked_cv_rmse,
    fit_lssvr_gram,
    lssvr_gram_fitter,
    lssvr_grid_cv,
)

F64 = torch.float64


def _kkt_predictor(X, y, sigma, C):
    """The LS-SVR by its KKT system (paper 002 Eq. 4), solved densely: [0 1^T; 1 K + I/C]."""
    n = X.shape[0]
    K = torch.exp(-torch.cdist(X, X).square() / (2 * sigma**2))
    A = torch.zeros(n + 1, n + 1, dtype=F64)
    A[0, 1:] = A[1:, 0] = 1.0
    A[1:, 1:] = K + torch.eye(n, dtype=F64) / C
    sol = torch.linalg.solve(A, torch.cat([torch.zeros(1, dtype=F64), y.reshape(-1)]))
    b, alpha = sol[0], sol[1:]
    return lambda Xh: torch.exp(-torch.cdist(Xh, X).square() / (2 * sigma**2)) @ alpha + b


def _data(n=40, m=3, seed=0):
    g = torch.Generator().manual_seed(seed)
    z = torch.sin(torch.arange(n, dtype=F64) / 3) + 0.05 * torch.randn(n, generator=g, dtype=F64)
    X = z.unfold(0, m, 1)[:-1]
    return z, X, z[m:]


def test_fit_lssvr_gram_solves_the_kkt_system():
    _, X, y = _data()
    Xq = X[::3] + 0.01
    ref = _kkt_predictor(X, y, 0.8, 30.0)(Xq)
    g = fit_lssvr_gram(X, y, sigma=0.8, C=30.0)
    assert g(Xq).shape == (Xq.shape[0], 1)
    torch.testing.assert_close(g(Xq)[:, 0], ref, rtol=1e-9, atol=1e-10)
    predict = lssvr_gram_fitter(0.8, 30.0)(X, y)
    torch.testing.assert_close(predict(Xq), ref, rtol=1e-9, atol=1e-10)  # (B,)


def test_lssvr_grid_cv_orders_the_grid_and_scales_sigma():
    z, X, y = _data()
    scores = lssvr_grid_cv(
        z, 3, 4, sigmas=(1.0, 4.0), Cs=(10.0, 100.0), scale=0.25, folds=4, threshold=0.9
    )
    assert list(scores) == [(1.0, 10.0), (1.0, 100.0), (4.0, 10.0), (4.0, 100.0)]
    for (s, C), sc in scores.items():
        assert isinstance(sc, MultiStepCV)
        # the one-step score is the blocked CV RMSE of the KKT-system LS-SVR of width s x scale
        fit = lambda Xt, yt, s=s, C=C: _kkt_predictor(Xt, yt, s * 0.25, C)  # noqa: E731
        ref = blocked_cv_rmse(fit, X, y, 4)
        assert sc.one_step == pytest.approx(ref, rel=1e-9)
