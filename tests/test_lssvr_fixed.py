"""Fixed-size LS-SVR (Nystrom on M support points) and blocked kernel evaluation.

References: the exact KKT solve of paper 002 Eq. 4 (``solve_kkt`` and an independent NumPy
solve of the bordered system) when ``M = N``; autograd and finite differences for the Jacobian;
the exact LS-SVR's held-out one-step RMSE on 5,000 rows for the approximation quality.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

import prognos_torch.learners.lssvr as lssvr_mod
import prognos_torch.learners.lssvr_gram as gram_mod
from prognos_torch.learners import LSSVR, FixedSizeLSSVR, LSSVRGram
from prognos_torch.learners.lssvr import kernel_matrix, rbf_kernel
from prognos_torch.learners.lssvr_fixed import nystrom_ridge, renyi_support
from prognos_torch.prognosis import learner_transition_model, particle_paths


def _data(N=60, n=3, n_out=1, seed=0):
    g = torch.Generator().manual_seed(seed)
    X = torch.rand(N, n, generator=g, dtype=torch.float64)
    Y = torch.stack([torch.sin(3 * X.sum(-1)), X[:, 0] ** 2 - X[:, -1]], -1)[:, :n_out]
    return X, Y + 0.01 * torch.randn(N, n_out, generator=g, dtype=torch.float64)


def _numpy_kkt(X, Y, sigma, C):
    Xn, Yn = X.numpy(), Y.numpy()
    K = np.exp(-((Xn[:, None, :] - Xn[None, :, :]) ** 2).sum(-1) / (2 * sigma**2))
    n = len(Yn)
    A = np.block([[K + np.eye(n) / C, np.ones((n, 1))], [np.ones((1, n)), np.zeros((1, 1))]])
    sol = np.linalg.solve(A, np.concatenate([Yn, np.zeros((1, Yn.shape[1]))]))
    return sol[:n], sol[n]


# --------------------------------------------------------------------------- M = N: exact KKT
@pytest.mark.parametrize("n_out", [1, 2])
def test_m_equals_n_is_the_exact_kkt_solution(n_out):
    # small sigma: a well-conditioned kernel matrix, every Nystrom direction is kept
    X, Y = _data(N=60, n_out=n_out)
    sigma, C = 0.15, 20.0
    fs = FixedSizeLSSVR(sigma=sigma, C=C, n_support=60, n_out=n_out).fit(X, Y)
    assert fs.rank == 60
    assert torch.equal(fs.support_vectors, X)
    alpha, b = _numpy_kkt(X, Y, sigma, C)
    np.testing.assert_allclose(fs.alpha.detach().numpy(), alpha, rtol=1e-9, atol=1e-10)
    np.testing.assert_allclose(fs.b.detach().numpy(), b, rtol=1e-9, atol=1e-11)
    ref = LSSVR(sigma=sigma, C=C, n_out=n_out).fit(X, Y)
    Xt = torch.rand(40, 3, generator=torch.Generator().manual_seed(5), dtype=torch.float64)
    with torch.no_grad():
        torch.testing.assert_close(fs(Xt), ref(Xt), rtol=0, atol=1e-11)


def test_m_equals_n_ill_conditioned_predictions_still_match():
    # wide kernel: K_MM has eigenvalues below lambda_max * M * eps, which are dropped; the
    # dropped directions carry nothing the float64 KKT solve can resolve either
    X, Y = _data(N=200, n=2)
    fs = FixedSizeLSSVR(sigma=1.0, C=100.0, n_support=500).fit(X, Y)
    assert fs.rank < 200
    ref = LSSVR(sigma=1.0, C=100.0).fit(X, Y)
    Xt = torch.rand(50, 2, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    with torch.no_grad():
        torch.testing.assert_close(fs(Xt), ref(Xt), rtol=0, atol=1e-8)


def test_nystrom_ridge_blocks_do_not_change_the_solution():
    X, Y = _data(N=3000, n=3)
    Z = X[:40]

    def kfn(A, B):
        return kernel_matrix(A, B, "rbf", sigma=0.4)

    b1, c1, r1 = nystrom_ridge(X, Y, Z, 50.0, kfn)  # one block
    b2, c2, r2 = nystrom_ridge(X, Y, Z, 50.0, kfn, block_bytes=1)  # 256-row blocks
    assert r1 == r2 == 40
    torch.testing.assert_close(b1, b2, rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(c1, c2, rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("kernel", ["linear", "poly"])
def test_non_rbf_kernels_reach_the_exact_solution(kernel):
    # the linear kernel has rank n, the quadratic one (n + 1)(n + 2) / 2: the Nystrom features
    # span the feature space and the fixed-size solution is the LS-SVR solution
    X, Y = _data(N=80, n=2)
    fs = FixedSizeLSSVR(kernel, C=10.0, n_support=30).fit(X, Y)
    ref = LSSVR(kernel, C=10.0).fit(X, Y)
    assert fs.rank == (2 if kernel == "linear" else 6)
    Xt = torch.rand(20, 2, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    with torch.no_grad():
        torch.testing.assert_close(fs(Xt), ref(Xt), rtol=0, atol=1e-9)


# --------------------------------------------------------------------------- 5,000 rows
def _long_series(T=5000, seed=0):
    g = torch.Generator().manual_seed(seed)
    t = torch.arange(T, dtype=torch.float64)
    e = 0.1 * torch.randn(T, generator=g, dtype=torch.float64).numpy()
    a = np.zeros(T)
    for i in range(1, T):  # AR(1) noise
        a[i] = 0.8 * a[i - 1] + e[i]
    periodic = torch.sin(2 * math.pi * t / 144) + 0.5 * torch.sin(2 * math.pi * t / 1000)
    return periodic + torch.from_numpy(a)


def test_reduced_within_5_percent_of_the_exact_lssvr_on_5000_rows():
    x = _long_series()
    n_tr, m = 4000, 6
    tr = x[:n_tr]
    z = (x - tr.min()) / (tr.max() - tr.min())
    W = z.unfold(0, m, 1)
    X, Y = W[: n_tr - m], z[m:n_tr]
    Xv, Yv = W[n_tr - m : -1], z[n_tr:]
    full = LSSVR(sigma=0.5, C=100.0).fit(X, Y)
    fs = FixedSizeLSSVR(sigma=0.5, C=100.0, n_support=50).fit(X, Y)
    with torch.no_grad():
        r_full = float((full(Xv)[:, 0] - Yv).square().mean().sqrt())
        r_fs = float((fs(Xv)[:, 0] - Yv).square().mean().sqrt())
    assert fs.support_vectors.shape == (50, m)
    assert abs(r_fs / r_full - 1.0) < 0.05, (r_fs, r_full)


# --------------------------------------------------------------------------- support selection
def test_renyi_selection_raises_the_entropy_and_is_reproducible():
    X, _ = _data(N=2000, n=2)
    sigma = 0.3

    def entropy(Z):
        return -math.log(float(rbf_kernel(Z, Z, sigma).mean()))

    g0 = torch.Generator().manual_seed(7)
    start = X[torch.randperm(2000, generator=g0)[:40]]  # the selection's starting subset
    idx = renyi_support(X, 40, sigma, trials=2000, generator=torch.Generator().manual_seed(7))
    again = renyi_support(X, 40, sigma, trials=2000, generator=torch.Generator().manual_seed(7))
    assert torch.equal(idx, again)
    assert idx.unique().numel() == 40
    assert entropy(X[idx]) > entropy(start) + 0.1
    assert torch.equal(
        renyi_support(X, 40, sigma, trials=0, generator=torch.Generator().manual_seed(7)),
        torch.randperm(2000, generator=torch.Generator().manual_seed(7))[:40],
    )


def test_bad_arguments():
    with pytest.raises(ValueError, match="n_support must be a positive int"):
        FixedSizeLSSVR(n_support=0)
    with pytest.raises(ValueError, match="selection must be one of"):
        FixedSizeLSSVR(selection="kmeans")
    with pytest.raises(ValueError, match="trials must be an int >= 0"):
        FixedSizeLSSVR(trials=-1)
    with pytest.raises(TypeError, match="generator must be a torch.Generator"):
        FixedSizeLSSVR(generator=3)
    with pytest.raises(RuntimeError, match="not fitted"):
        FixedSizeLSSVR()(torch.zeros(2, 3, dtype=torch.float64))
    with pytest.raises(ValueError, match=r"X must have shape \(N, n\)"):
        FixedSizeLSSVR().fit(torch.zeros(5, dtype=torch.float64), torch.zeros(5))


# --------------------------------------------------------------------------- prediction, Jacobian
def _fitted(n_out=1, M=30):
    X, Y = _data(N=400, n=3, n_out=n_out)
    sel = "random" if n_out > 1 else "renyi"
    return FixedSizeLSSVR(sigma=0.5, C=50.0, n_support=M, n_out=n_out, selection=sel).fit(X, Y)


@pytest.mark.parametrize("n_out", [1, 2])
def test_forward_and_closed_form_jacobian_match_the_lssvr_difference_form(n_out):
    fs = _fitted(n_out)
    ref = LSSVR(sigma=0.5, C=50.0, n_out=n_out)
    ref.load_state_dict(fs.state_dict())
    x = torch.rand(7, 5, 3, generator=torch.Generator().manual_seed(2), dtype=torch.float64)
    with torch.no_grad():
        torch.testing.assert_close(fs(x), ref(x), rtol=1e-12, atol=1e-12)
    x2 = x.reshape(-1, 3)
    J = fs.input_gradient(x2)
    assert J.shape == (35, n_out, 3)
    torch.testing.assert_close(J, ref.input_gradient(x2).detach(), rtol=1e-10, atol=1e-11)
    torch.testing.assert_close(J, torch.func.vmap(torch.func.jacrev(fs.forward))(x2).detach())
    torch.testing.assert_close(fs(x2).detach(), LSSVRGram(fs)(x2), rtol=1e-12, atol=1e-12)


def test_jacobian_matches_finite_differences():
    fs = _fitted()
    x = torch.rand(4, 3, generator=torch.Generator().manual_seed(4), dtype=torch.float64)
    h = 1e-6
    with torch.no_grad():
        fd = torch.stack(
            [(fs(x + h * e) - fs(x - h * e)) / (2 * h) for e in torch.eye(3, dtype=x.dtype)], -1
        )
    torch.testing.assert_close(fs.input_gradient(x).detach(), fd, rtol=1e-6, atol=1e-7)


def test_transition_model_jacobians_and_particle_paths():
    fs = _fitted()
    x = torch.rand(2, 50, 3, generator=torch.Generator().manual_seed(6), dtype=torch.float64)
    closed = learner_transition_model(fs, 3, 0.01, 0.01, jacobian="input_gradient")
    auto = learner_transition_model(fs, 3, 0.01, 0.01)
    torch.testing.assert_close(
        closed.transition_jacobian(x, None, 0), auto.transition_jacobian(x, None, 0)
    )
    g1, g2 = torch.Generator().manual_seed(0), torch.Generator().manual_seed(0)
    p1 = particle_paths(closed, x, 30, generator=g1)
    with torch.no_grad():
        f1 = fs(x)
    saved = lssvr_mod.KERNEL_BLOCK_BYTES
    try:  # particle batches evaluated one row at a time
        lssvr_mod.KERNEL_BLOCK_BYTES = 8
        with torch.no_grad():
            f2 = fs(x)
        p2 = particle_paths(closed, x, 30, generator=g2)
    finally:
        lssvr_mod.KERNEL_BLOCK_BYTES = saved
    torch.testing.assert_close(f1, f2, rtol=0, atol=1e-12)  # one step: rounding only
    # 30 recursive steps amplify the rounding of |beta| ~ 1e3 weighted sums
    torch.testing.assert_close(p1.samples, p2.samples, rtol=0, atol=1e-7)


def test_kalman_state_is_alpha_and_b():
    # iterative optimisers over the fixed-size LS-SVR see M + 1 parameters, not N + 1
    fs = _fitted(M=25)
    n_state = sum(p.numel() for p in fs.parameters() if p.requires_grad)
    assert n_state == 26


# --------------------------------------------------------------------------- blocked kernels
def test_blocked_gram_and_fit_are_bit_identical(monkeypatch):
    X, Y = _data(N=300, n=4)
    K0 = rbf_kernel(X, X, 0.7)
    ref = LSSVR(sigma=0.7, C=50.0).fit(X, Y)
    xt = torch.rand(3, 40, 4, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    with torch.no_grad():
        p0 = ref(xt)
    monkeypatch.setattr(lssvr_mod, "KERNEL_BLOCK_BYTES", 5000)  # a few rows per block
    assert torch.equal(rbf_kernel(X, X, 0.7), K0)
    blocked = LSSVR(sigma=0.7, C=50.0).fit(X, Y)
    assert torch.equal(blocked.alpha, ref.alpha) and torch.equal(blocked.b, ref.b)
    with torch.no_grad():  # the kernel rows are identical; the products agree to rounding
        torch.testing.assert_close(blocked(xt), p0, rtol=0, atol=1e-13)


def test_solve_kkt_without_identity_matrix_is_unchanged():
    X, Y = _data(N=50)
    Omega = rbf_kernel(X, X, 0.5)
    C = torch.tensor(30.0, dtype=torch.float64)
    alpha, b = lssvr_mod.solve_kkt(Omega, Y, C)
    A = Omega + torch.eye(50, dtype=torch.float64) / C
    L = torch.linalg.cholesky(A)
    e = torch.ones(50, 1, dtype=torch.float64)
    sol = torch.cholesky_solve(torch.cat([e, Y], dim=-1), L)
    b_ref = sol[:, 1:].sum(0) / sol[:, :1].sum(0)
    assert torch.equal(b, b_ref) and torch.equal(alpha, sol[:, 1:] - sol[:, :1] * b_ref)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_fixed_size_on_cuda_matches_cpu():
    X, Y = _data(N=500, n=3)
    cpu = FixedSizeLSSVR(sigma=0.5, C=50.0, n_support=40).fit(X, Y)
    dev = FixedSizeLSSVR(sigma=0.5, C=50.0, n_support=40).to("cuda").fit(X.cuda(), Y.cuda())
    torch.testing.assert_close(dev.support_vectors.cpu(), cpu.support_vectors)
    with torch.no_grad():
        torch.testing.assert_close(dev(X.cuda()).cpu(), cpu(X), rtol=1e-9, atol=1e-10)
    torch.testing.assert_close(
        dev.input_gradient(X[:20].cuda()).cpu(), cpu.input_gradient(X[:20]), rtol=1e-8, atol=1e-9
    )


def test_gram_evaluator_blocks_agree(monkeypatch):
    X, Y = _data(N=300, n=3, n_out=2)
    fast = LSSVRGram(LSSVR(sigma=0.5, C=50.0, n_out=2).fit(X, Y))
    x = torch.rand(4, 60, 3, generator=torch.Generator().manual_seed(8), dtype=torch.float64)
    f0, j0 = fast(x), fast.input_gradient(x.reshape(-1, 3))
    monkeypatch.setattr(gram_mod, "GRAM_BLOCK_BYTES", 3000)  # one row of phi per block
    torch.testing.assert_close(fast(x), f0, rtol=0, atol=1e-12)
    torch.testing.assert_close(fast.input_gradient(x.reshape(-1, 3)), j0, rtol=0, atol=1e-11)


def test_exact_lssvr_jacobian_in_row_chunks(monkeypatch):
    # the particle filters' Jacobian of the exact LS-SVR: vmap(jacrev) in chunks of rows
    X, Y = _data(N=200, n=3)
    net = LSSVR(sigma=0.5, C=50.0).fit(X, Y)
    x = torch.rand(90, 3, generator=torch.Generator().manual_seed(9), dtype=torch.float64)
    J0 = net.input_gradient(x)
    monkeypatch.setattr(lssvr_mod, "KERNEL_BLOCK_BYTES", 6 * 8 * 200 * 3 * 7)  # 7 rows a chunk
    assert lssvr_mod._row_chunks(x, 6 * 8 * 200 * 3) == 7
    torch.testing.assert_close(net.input_gradient(x), J0, rtol=0, atol=1e-13)


def test_float32_far_from_the_origin_keeps_the_exact_models_accuracy():
    # the |x|^2 - 2 x.z + |z|^2 expansion cancels for data far from 0; the kernel is
    # shift-invariant and both evaluators take the data from the support vectors' centre. In
    # float32 at an offset of 100 (sigma 0.5) the uncentred forms erred by 1.1 and 1.2 on a
    # series of range 1.6; the exact LS-SVR (explicit differences) by 4e-4
    g = torch.Generator().manual_seed(0)
    s = 100.0 + 0.05 * torch.randn(304, generator=g, dtype=torch.float64).cumsum(0)
    X, y = s.unfold(0, 4, 1)[:300], s[4:304]
    exact = LSSVR(sigma=0.5, C=100.0).fit(X, y)
    ref, ref_j = exact(X).detach(), exact.input_gradient(X).detach()
    exact32 = LSSVR(sigma=0.5, C=100.0).fit(X, y).to(torch.float32)
    tol = 3 * float((exact32(X.float()).detach().double() - ref).abs().max())
    fs32 = FixedSizeLSSVR(sigma=0.5, C=100.0, n_support=300).fit(X, y).to(torch.float32)
    for m in (fs32, LSSVRGram(exact).to(torch.float32)):
        with torch.no_grad():
            assert float((m(X.float()).double() - ref).abs().max()) < tol
        J = m.input_gradient(X.float()).detach().double()
        assert float((J - ref_j).abs().max()) < 1e-3 * float(ref_j.abs().max())
