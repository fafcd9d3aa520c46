"""Sage-Husa estimator of paper 003 (Eq. 40-43) in the optimiser face: prior weight ``k0``,
the post-fit form of the ``R`` estimate, and ImSRUKF training a generic network."""

from __future__ import annotations

import pytest
import torch
from torch import nn

from prognos_torch.adapt.noise import SageHusa
from prognos_torch.core import GaussianBelief, StateSpaceModel
from prognos_torch.filters import imsrukf, run
from prognos_torch.optim import KalmanOptimizer
from prognos_torch.optim.kalman import OPTIMIZER_NOISE


def _gen(s: int) -> torch.Generator:
    return torch.Generator().manual_seed(s)


def _mlp_data(N: int = 256, seed: int = 0):
    g = _gen(seed)
    X = torch.rand(N, 3, generator=g, dtype=torch.float64) * 2 - 1
    Y = torch.sin(2 * X[:, :1]) + X[:, 1:2] * X[:, 2:3]
    return X, Y + 0.1 * torch.randn(N, 1, generator=g, dtype=torch.float64)


def _mlp(seed: int) -> nn.Module:
    torch.manual_seed(seed)
    return nn.Sequential(nn.Linear(3, 8), nn.Tanh(), nn.Linear(8, 1)).double()


def _train_mse(filt: str, seed: int, epochs: int = 6, **kw) -> float:
    X, Y = _mlp_data()
    m = _mlp(seed)
    opt = KalmanOptimizer(m, filter=filt, P0=1.0, Q=1e-6, R=1e-2, **kw)
    for _ in range(epochs):
        for i in range(0, X.shape[0], 8):
            opt.step(X[i : i + 8], Y[i : i + 8])
    with torch.no_grad():
        return float(((m(X) - Y) ** 2).mean())


@pytest.mark.parametrize("seed", [0, 1])
def test_imsrukf_trains_a_tanh_mlp_within_twice_srukf(seed):
    """3-8-1 tanh MLP, batches of 8, P0 = 1, Q = 1e-6, R = 1e-2, 6 epochs; the noise std is
    0.1, so the best reachable MSE is about 0.01. With Eq. 43 as printed and k0 = 1 the
    estimate of R sits on its floor and ImSRUKF left the MSE at 0.19-0.39."""
    mse_sr = _train_mse("srukf", seed)
    mse_im = _train_mse("imsrukf", seed)
    print(f"\nseed {seed}: SRUKF MSE {mse_sr:.4f}, ImSRUKF MSE {mse_im:.4f}")
    assert mse_sr < 0.02
    assert mse_im < 2.0 * mse_sr
    # the printed form (innovation R, k0 = 1) fails on the same set-up: the test can fail
    printed = SageHusa(estimate=("Q", "R"), diagonal=True)
    assert _train_mse("imsrukf", seed, noise=printed) > 5.0 * mse_sr


def _linear_model(n=2, m=2):
    A = torch.tensor([[0.9, 0.1], [0.0, 0.8]], dtype=torch.float64)
    C = torch.tensor([[1.0, 0.0], [0.5, 1.0]], dtype=torch.float64)
    return (
        StateSpaceModel(
            state_dim=n,
            obs_dim=m,
            f=lambda x, u, k: A @ x,
            h=lambda x, u, k: C @ x,
            chol_Q=0.1 * torch.eye(n, dtype=torch.float64),
            chol_R=0.3 * torch.eye(m, dtype=torch.float64),
        ),
        A,
        C,
    )


def test_post_fit_R_term_matches_kalman_filter_closed_form():
    """Linear model: one step's post-fit term equals ``rho rho^T + C P_k C^T`` with the
    post-fit residual ``rho = y - C x_k`` of an exact Kalman filter, and is positive
    semi-definite; with ``k0`` the update is ``(1 - 1/k0) R_0 + 1/k0 term``."""
    model, A, C = _linear_model()
    x0 = torch.tensor([0.3, -0.2], dtype=torch.float64)
    P0 = torch.tensor([[2.0, 0.3], [0.3, 1.0]], dtype=torch.float64)
    b0 = GaussianBelief(x0, torch.linalg.cholesky(P0))
    y = torch.tensor([[0.7, -1.1]], dtype=torch.float64)
    Q, R = 0.01 * torch.eye(2, dtype=torch.float64), 0.09 * torch.eye(2, dtype=torch.float64)
    # Kalman filter reference
    xp, Pp = A @ x0, A @ P0 @ A.T + Q
    S = C @ Pp @ C.T + R
    K = torch.linalg.solve(S, C @ Pp).T
    xk = xp + K @ (y[0] - C @ xp)
    Pk = (torch.eye(2, dtype=torch.float64) - K @ C) @ Pp
    rho = y[0] - C @ xk
    term = torch.outer(rho, rho) + C @ Pk @ C.T
    assert bool((torch.linalg.eigvalsh(term) >= 0).all())
    for k0 in (1.0, 4.0):
        est = SageHusa(estimate=("R",), r_form="post-fit", k0=k0)
        tr = run(imsrukf(noise=est), model, b0, y)
        d = 1.0 / k0
        torch.testing.assert_close(tr.means[0], xk, rtol=1e-10, atol=1e-12)
        torch.testing.assert_close(tr.final.noise.R, (1 - d) * R + d * term, rtol=1e-9, atol=1e-12)


def test_k0_and_r_form_are_validated():
    with pytest.raises(ValueError, match="k0"):
        SageHusa(k0=0.5)
    with pytest.raises(ValueError, match="r_form"):
        SageHusa(r_form="posterior")
    assert OPTIMIZER_NOISE.r_form == "post-fit" and OPTIMIZER_NOISE.k0 > 1
