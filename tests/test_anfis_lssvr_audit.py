"""Audit of the exact LS-SVR (paper 002, Eq. 4-8) and ANFIS (paper 003, Eq. 1-5) against NumPy.

References: the dense KKT system ``[[0, 1^T], [1, K + I/C]] [b; alpha] = [0; y]`` solved by
``numpy.linalg.solve``; a first-order Sugeno ANFIS written with plain products in NumPy.
"""

from __future__ import annotations

import itertools

import numpy as np
import pytest
import torch
from test_learners import _np_kernel  # paper 002, Eq. 5-7 in NumPy

import prognos_torch.learners.anfis as anfis_mod
from prognos_torch.learners import ANFIS, LSSVR

F64 = torch.float64


def _np_kkt(K, y, C):
    """``[b; alpha]`` of paper 002, Eq. 4 by a dense solve (``y`` ``(M, n_out)``)."""
    M = K.shape[0]
    A = np.zeros((M + 1, M + 1))
    A[0, 1:] = A[1:, 0] = 1.0
    A[1:, 1:] = K + np.eye(M) / C
    sol = np.linalg.solve(A, np.vstack([np.zeros((1, y.shape[1])), y]))
    return sol[1:], sol[0]


def _data(M=15, n=2, seed=1):
    rng = np.random.default_rng(seed)
    X = rng.uniform(-1, 1, (M, n))
    return X, np.stack([np.sin(3 * X[:, 0]), X[:, 1] ** 2], 1)


# ------------------------------------------------------------------------------------ LS-SVR


def test_lssvr_float32_width_whose_square_underflows_is_refused_not_nan():
    X, y = _data()
    # near the float32 limit: the kernel is I, so alpha = (y - b) / (1 + 1/C), b = mean(y)
    m = LSSVR(sigma=1e-20, C=4.0, n_out=2, dtype=torch.float32).fit(X, y)
    alpha, b = _np_kkt(np.eye(len(X)), y, 4.0)
    np.testing.assert_allclose(b, y.mean(0), rtol=1e-12)
    pred = m(torch.tensor(X, dtype=torch.float32)).detach().double().numpy()
    np.testing.assert_allclose(pred, alpha + b, rtol=1e-6, atol=1e-6)
    # 2 sigma^2 = 0 in float32 (fine in float64): every support vector gave 0/0 = NaN
    with pytest.raises(ValueError, match=r"sigma = 1e-30 is too small: 2 sigma\^2 .*float32"):
        LSSVR(sigma=1e-30, dtype=torch.float32)
    LSSVR(sigma=1e-30)  # float64: representable


def test_lssvr_tiny_C_matches_kkt_and_overflowing_one_over_C_is_refused():
    X, y = _data(seed=2)
    K = _np_kernel("rbf", X, X, 0.5)
    for C in (1e-300, 1e-308):  # Eq. 4 with a huge I/C: alpha ~ C (y - mean y), b ~ mean y
        m = LSSVR(sigma=0.5, C=C, n_out=2).fit(X, y)
        alpha, b = _np_kkt(K, y, C)
        np.testing.assert_allclose(m.alpha.detach().numpy(), alpha, rtol=1e-12)
        np.testing.assert_allclose(m.b.detach().numpy(), b, rtol=1e-12)
    # 1/C = inf in float64: fit returned NaN alpha and b silently
    with pytest.raises(ValueError, match=r"C = 1e-310 is too small: 1/C overflows"):
        LSSVR(C=1e-310)


def test_lssvr_poly_coef0_takes_numpy_scalars_and_refuses_bools():
    X, y = _data(seed=3)
    m = LSSVR(kernel="poly", C=7.0, degree=3, coef0=np.float32(0.5), n_out=2).fit(X, y)
    alpha, b = _np_kkt(_np_kernel("poly", X, X, degree=3, coef0=0.5), y, 7.0)
    np.testing.assert_allclose(m.alpha.detach().numpy(), alpha, rtol=1e-9, atol=1e-10)
    np.testing.assert_allclose(m.b.detach().numpy(), b, rtol=1e-10)
    with pytest.raises(TypeError, match="coef0 must be a real number, got bool True"):
        LSSVR(kernel="poly", coef0=True)  # (was taken as coef0 = 1.0)
    with pytest.raises(ValueError, match="coef0 must be a finite number"):
        LSSVR(kernel="poly", coef0=float("inf"))


# ------------------------------------------------------------------------------------- ANFIS


def _np_anfis_batched(x, mf, alpha, prem, n_mfs):
    """Paper 003, Eq. 1-5 with plain products for one parameter set: ``(B, n_out)``."""
    B, n = x.shape
    u = x[:, :, None]  # (B, n, 1)
    if mf == "sigmoid":
        g = 1.0 / (1.0 + np.exp(-prem["b"] * (u - prem["beta"])))
    elif mf == "gaussian":
        g = np.exp(-((u - prem["c"]) ** 2) / (2.0 * prem["sigma"] ** 2))
    else:
        g = 1.0 / (1.0 + np.abs((u - prem["c"]) / prem["a"]) ** (2.0 * prem["b"]))
    rules = list(itertools.product(range(n_mfs), repeat=n))
    w = np.stack([np.prod([g[:, j, r[j]] for j in range(n)], axis=0) for r in rules], -1)
    wbar = w / w.sum(-1, keepdims=True)  # (B, R)
    ubar = np.concatenate([x, np.ones((B, 1))], 1)  # (B, n + 1)
    f = np.einsum("bm,omi->obi", ubar, alpha)  # consequents per rule
    return np.einsum("bi,obi->bo", wbar, f)


@pytest.mark.parametrize("mf", ["sigmoid", "gaussian", "bell"])
@pytest.mark.parametrize("kron", [True, False])
def test_anfis_runs_batched_forward_with_matches_numpy_per_run(mf, kron, monkeypatch):
    if not kron:
        monkeypatch.setattr(anfis_mod, "KRON_MAX_ENTRIES", 0)
    g = torch.Generator().manual_seed(4)
    net = ANFIS(2, 3, mf=mf, n_out=2, generator=g)
    runs = 4
    params = {
        k: v.detach() + 0.05 * torch.randn(runs, *v.shape, generator=g, dtype=F64)
        for k, v in net.named_parameters()
    }
    x = torch.cat([torch.randn(5, 2, generator=g, dtype=F64), torch.tensor([[4.0, -3.5]])])
    out = net.forward_with(params, x)
    assert out.shape == (runs, 6, 2)
    for r in range(runs):
        prem = {k: params[k][r].numpy() for k in net.premise_names}
        ref = _np_anfis_batched(x.numpy(), mf, params["alpha"][r].numpy(), prem, 3)
        np.testing.assert_allclose(out[r].numpy(), ref, rtol=1e-12, atol=1e-12)


def test_anfis_forward_with_refuses_misshaped_or_unknown_parameters():
    net = ANFIS(2, 3, generator=torch.Generator().manual_seed(0))  # b, beta: (2, 3)
    x = torch.randn(4, 2, dtype=F64, generator=torch.Generator().manual_seed(1))
    # b as (n_mfs, n_inputs): was reshaped in the wrong order and gave other numbers silently
    with pytest.raises(ValueError, match=r"params\['b'\] must have shape \(\.\.\., 2, 3\)"):
        net.forward_with({"b": net.b.detach().T.contiguous()}, x)
    with pytest.raises(ValueError, match=r"params\['alpha'\] must have shape \(\.\.\., 1, 3, 9\)"):
        net.forward_and_jacobian({"alpha": net.alpha.detach().expand(2, 3, 9)}, x)
    # a misspelt name: the module's own beta was used instead
    with pytest.raises(ValueError, match="params has no ANFIS parameter 'bta'"):
        net.forward_with({"bta": net.beta.detach() + 1.0}, x)
