"""Tests of prognos_torch.learners: ELM/ROS-ELM (paper 000), LS-SVR (paper 002), ANFIS (paper 003).

References are independent: NumPy implementations of the papers' equations, dense solves of the
normal / KKT equations, numpy.linalg.lstsq, central finite differences.
"""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
import torch
from torch.func import functional_call, jacfwd, jacrev, vmap

from prognos_torch.learners import ANFIS, ELM, LSSVR
from prognos_torch.learners.anfis import log_membership

F64 = torch.float64


def _gen(seed: int) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def _randn(*shape, seed=0, dtype=F64):
    return torch.randn(*shape, generator=_gen(seed), dtype=dtype)


def _fd_input_jacobian(f, x: torch.Tensor, eps: float = 1e-6) -> torch.Tensor:
    """Central differences of ``f: (n,) -> (m,)`` at ``x``: ``(m, n)``."""
    cols = []
    for k in range(x.shape[0]):
        e = torch.zeros_like(x)
        e[k] = eps
        cols.append((f(x + e) - f(x - e)) / (2 * eps))
    return torch.stack(cols, dim=-1)


def _fd_param_jacobian(model, name, x, eps=1e-6):
    """Central differences of ``model(x).reshape(-1)`` with respect to parameter ``name``."""
    p0 = dict(model.named_parameters())[name].detach()
    cols = []
    for k in range(p0.numel()):
        e = torch.zeros(p0.numel(), dtype=p0.dtype)
        e[k] = eps
        plus = functional_call(model, {name: p0 + e.reshape(p0.shape)}, (x,))
        minus = functional_call(model, {name: p0 - e.reshape(p0.shape)}, (x,))
        cols.append(((plus - minus) / (2 * eps)).detach().reshape(-1))
    return torch.stack(cols, dim=-1).reshape(*model(x).shape, *p0.shape)


# =============================================================================== ELM (paper 000)


def _np_sigmoid(z):
    return 1.0 / (1.0 + np.exp(-z))


def test_elm_random_features_and_flags():
    m = ELM(3, 40, n_out=2, generator=_gen(1))
    a, b = m.a.detach().numpy(), m.b.detach().numpy()
    assert a.shape == (40, 3) and b.shape == (40,) and m.beta.shape == (40, 2)
    assert a.min() >= -1 and a.max() <= 1 and a.min() < -0.5 and a.max() > 0.5
    assert b.min() >= 0 and b.max() <= 1
    assert not m.a.requires_grad and not m.b.requires_grad and m.beta.requires_grad
    assert [n for n, _ in m.named_parameters()] == ["a", "b", "beta"]
    m2 = ELM(3, 40, n_out=2, generator=_gen(1))
    m3 = ELM(3, 40, n_out=2, generator=_gen(2))
    assert torch.equal(m.a, m2.a) and torch.equal(m.b, m2.b)
    assert not torch.equal(m.a, m3.a)
    assert torch.equal(ELM(3, 5).a, ELM(3, 5).a)  # generator=None is reproducible


@pytest.mark.parametrize(
    "activation, g",
    [
        ("sigmoid", _np_sigmoid),
        ("tanh", np.tanh),
        ("relu", lambda z: np.maximum(z, 0.0)),
        ("sin", np.sin),
    ],
)
def test_elm_forward_matches_numpy(activation, g):
    m = ELM(4, 7, n_out=2, activation=activation, generator=_gen(3))
    with torch.no_grad():
        m.beta.copy_(_randn(7, 2, seed=4))
    x = _randn(6, 4, seed=5)
    a, b, beta = (t.detach().numpy() for t in (m.a, m.b, m.beta))
    H = g(x.numpy() @ a.T + b)  # Eq. 48/51
    np.testing.assert_allclose(m.hidden(x).detach().numpy(), H, rtol=1e-13, atol=1e-14)
    np.testing.assert_allclose(m(x).detach().numpy(), H @ beta, rtol=1e-12, atol=1e-13)
    # arbitrary leading dims and a single sample
    np.testing.assert_allclose(
        m(x.reshape(2, 3, 4)).detach().numpy(), (H @ beta).reshape(2, 3, 2), rtol=1e-12
    )
    np.testing.assert_allclose(m(x[0]).detach().numpy(), (H @ beta)[0], rtol=1e-12)


def _elm_data(n, n_in=3, n_out=2, seed=0):
    rng = np.random.default_rng(seed)
    x = rng.uniform(-1, 1, size=(n, n_in))
    y = np.stack([np.sin(2 * x[:, 0]) + x[:, 1] * x[:, -1], np.cos(x.sum(1))], 1)[:, :n_out]
    return torch.tensor(x), torch.tensor(y + 0.01 * rng.standard_normal(y.shape))


def _np_ridge(H, T, lam):
    """Eq. 53 with the transpose restored: (H^T H + lam I)^{-1} H^T T (dense solve)."""
    return np.linalg.solve(H.T @ H + lam * np.eye(H.shape[1]), H.T @ T)


def test_elm_fit_ridge_matches_dense_normal_equations():
    m = ELM(3, 12, n_out=2, generator=_gen(0))
    x, y = _elm_data(40)
    lam = 1e-3
    m.fit_ridge(x, y, lam)
    H = _np_sigmoid(x.numpy() @ m.a.detach().numpy().T + m.b.detach().numpy())
    ref = _np_ridge(H, y.numpy(), lam)
    np.testing.assert_allclose(m.beta.detach().numpy(), ref, rtol=1e-9, atol=1e-10)
    # float32 module: solved in float64, stored in float32
    m32 = ELM(3, 12, n_out=2, generator=_gen(0), dtype=torch.float32)
    m32.fit_ridge(x, y, lam)
    assert m32.beta.dtype == torch.float32
    np.testing.assert_allclose(m32.beta.detach().double().numpy(), ref, rtol=1e-4, atol=1e-4)


@pytest.mark.parametrize("lam", [1e-2, 0.0])
def test_ros_elm_sequential_equals_batch_ridge(lam):
    L, N0 = 10, 25
    m = ELM(3, L, n_out=2, generator=_gen(7))
    x, y = _elm_data(70, seed=1)
    m.init_online(x[:N0], y[:N0], lam)
    H = _np_sigmoid(x.numpy() @ m.a.detach().numpy().T + m.b.detach().numpy())
    T = y.numpy()
    beta0 = _np_ridge(H[:N0], T[:N0], lam)
    np.testing.assert_allclose(m.beta.detach().numpy(), beta0, rtol=0, atol=1e-8)
    K0 = np.linalg.inv(H[:N0].T @ H[:N0] + lam * np.eye(L))
    np.testing.assert_allclose(m.K.numpy(), K0, rtol=1e-8, atol=1e-8 * np.abs(K0).max())
    # Step II one sample at a time (Eq. 55-56), then chunks of different sizes (block form)
    for k in range(N0, 40):
        m.partial_fit(x[k], y[k])
    for lo, hi in [(40, 47), (47, 48), (48, 60), (60, 70)]:
        m.partial_fit(x[lo:hi], y[lo:hi])
    ref = _np_ridge(H, T, lam)
    np.testing.assert_allclose(m.beta.detach().numpy(), ref, rtol=0, atol=1e-8)
    Kref = np.linalg.inv(H.T @ H + lam * np.eye(L))
    np.testing.assert_allclose(m.K.numpy(), Kref, rtol=0, atol=1e-8 * np.abs(Kref).max())
    assert int(m.n_seen) == 70
    assert m.K.dtype == F64


def test_ros_elm_single_output_and_1d_targets():
    m = ELM(2, 6, generator=_gen(3))
    rng = np.random.default_rng(2)
    x = torch.tensor(rng.uniform(-1, 1, (30, 2)))
    y = torch.tensor(np.sin(x.numpy()).sum(1))  # (N,) accepted for n_out=1
    m.init_online(x[:10], y[:10], 1e-3)
    m.partial_fit(x[10], y[10:11])  # single sample: y (n_out,)
    m.partial_fit(x[11:], y[11:])
    H = _np_sigmoid(x.numpy() @ m.a.detach().numpy().T + m.b.detach().numpy())
    ref = _np_ridge(H, y.numpy()[:, None], 1e-3)
    np.testing.assert_allclose(m.beta.detach().numpy(), ref, rtol=0, atol=1e-8)


def test_ros_elm_initialisation_rules():
    m = ELM(3, 10, generator=_gen(0))
    x, y = _elm_data(6, n_out=1)
    # paper 000 Step I needs N0 >= L without regularisation
    with pytest.raises(ValueError, match="N0"):
        m.init_online(x, y, 0.0)
    # with lam > 0 the problem is well posed for any N0
    m.init_online(x, y, 0.1)
    H = _np_sigmoid(x.numpy() @ m.a.detach().numpy().T + m.b.detach().numpy())
    np.testing.assert_allclose(m.beta.detach().numpy(), _np_ridge(H, y.numpy(), 0.1), rtol=1e-9)
    with pytest.raises(RuntimeError, match="init_online"):
        ELM(3, 10).partial_fit(x[0], y[0])
    with pytest.raises(ValueError, match="lam"):
        m.init_online(x, y, -1.0)


def test_elm_K_stays_float64_and_state_dict_round_trip():
    m = ELM(3, 8, n_out=2, generator=_gen(0))
    x, y = _elm_data(30)
    m.init_online(x[:20], y[:20], 1e-2)
    K = m.K.clone()
    m32 = m.to(torch.float32)
    assert m32.beta.dtype == torch.float32 and m32.K.dtype == F64
    assert torch.equal(m32.K, K)  # no precision lost through the cast
    m32.partial_fit(x[20:], y[20:])
    assert m32.K.dtype == F64
    fresh = ELM(3, 8, n_out=2, generator=_gen(5), dtype=torch.float32)
    fresh.load_state_dict(m32.state_dict())
    assert fresh.K.dtype == F64 and torch.equal(fresh.K, m32.K)
    assert torch.equal(fresh.a, m32.a) and int(fresh.n_seen) == 30


def test_elm_bad_inputs():
    with pytest.raises(ValueError, match="activation"):
        ELM(2, 4, activation="swishy")
    with pytest.raises(TypeError, match="dtype"):
        ELM(2, 4, dtype=torch.int64)
    with pytest.raises(ValueError, match="n_hidden"):
        ELM(2, 0)
    m = ELM(2, 4, n_out=2)
    x, y = _elm_data(10, n_in=2)
    with pytest.raises(ValueError, match=r"x must have shape"):
        m(torch.zeros(5, 3, dtype=F64))
    with pytest.raises(TypeError, match=r"x has dtype"):
        m(torch.zeros(5, 2, dtype=torch.float32))
    with pytest.raises(ValueError, match=r"x is on device"):
        m(torch.zeros(5, 2, dtype=F64, device="meta"))
    with pytest.raises(ValueError, match=r"^y must have shape"):
        m.fit_ridge(x, y[:-1], 0.1)
    with pytest.raises(ValueError, match=r"^x must have shape"):
        m.fit_ridge(torch.zeros(10, 3, dtype=F64), y, 0.1)
    xbad = x.clone()
    xbad[3, 1] = float("nan")
    with pytest.raises(ValueError, match=r"^x contains non-finite"):
        m.fit_ridge(xbad, y, 0.1)
    ybad = y.clone()
    ybad[0, 0] = float("inf")
    with pytest.raises(ValueError, match=r"^y0 contains non-finite"):
        m.init_online(x, ybad, 0.1)
    m.init_online(x, y, 0.1)
    with pytest.raises(ValueError, match=r"^y must have shape \(n_out,\)"):
        m.partial_fit(x[0], y[0, :1])
    with pytest.raises(ValueError, match=r"^x must have shape"):
        m.partial_fit(torch.zeros(2, 5, dtype=F64), y[:2])
    with pytest.raises(ValueError, match=r"^x contains non-finite"):
        m.partial_fit(xbad[3], y[3])


# =============================================================================== LS-SVR (paper 002)


def _np_kernel(kind, X, Y, sigma=1.0, degree=2, coef0=1.0):
    """Paper 002, Eq. 5-7 in NumPy (RBF: exp(-||x-y||^2 / (2 sigma^2)))."""
    if kind == "linear":
        return X @ Y.T
    if kind == "poly":
        return (coef0 + X @ Y.T) ** degree
    d2 = ((X[:, None, :] - Y[None, :, :]) ** 2).sum(-1)
    return np.exp(-d2 / (2 * sigma**2))


def _lssvr_data(n=25, n_in=3, seed=0):
    rng = np.random.default_rng(seed)
    X = rng.uniform(-1, 1, (n, n_in))
    y = np.stack([np.sin(2 * X[:, 0]) * X[:, 1], X[:, 2] ** 2 - X[:, 0]], 1)
    return torch.tensor(X), torch.tensor(y + 0.05 * rng.standard_normal(y.shape))


_KERNEL_ARGS = [
    ("rbf", dict(sigma=0.7, C=20.0)),
    ("linear", dict(C=5.0)),
    ("poly", dict(C=3.0, degree=3, coef0=0.5)),
]


@pytest.mark.parametrize("kernel, kw", _KERNEL_ARGS)
def test_lssvr_fit_equals_dense_kkt_solve(kernel, kw):
    X, y = _lssvr_data()
    m = LSSVR(kernel=kernel, n_out=2, **kw).fit(X, y)
    M = X.shape[0]
    Omega = _np_kernel(
        kernel, X.numpy(), X.numpy(), kw.get("sigma", 1.0), kw.get("degree", 2), kw.get("coef0", 1)
    )
    A = np.zeros((M + 1, M + 1))  # Eq. 4
    A[:M, :M] = Omega + np.eye(M) / kw["C"]
    A[:M, M] = 1.0
    A[M, :M] = 1.0
    rhs = np.vstack([y.numpy(), np.zeros((1, 2))])
    sol = torch.linalg.solve(torch.tensor(A), torch.tensor(rhs)).numpy()
    np.testing.assert_allclose(m.alpha.detach().numpy(), sol[:M], rtol=0, atol=1e-8)
    np.testing.assert_allclose(m.b.detach().numpy(), sol[M], rtol=0, atol=1e-8)
    np.testing.assert_allclose(m.alpha.detach().sum(0).numpy(), 0.0, atol=1e-9)  # e^T alpha = 0
    # prediction Eq. 8 at new points
    Xt = np.random.default_rng(9).uniform(-1, 1, (7, 3))
    Kt = _np_kernel(
        kernel, Xt, X.numpy(), kw.get("sigma", 1.0), kw.get("degree", 2), kw.get("coef0", 1)
    )
    pred = m(torch.tensor(Xt)).detach().numpy()
    np.testing.assert_allclose(pred, Kt @ sol[:M] + sol[M], rtol=1e-9, atol=1e-9)


def test_lssvr_rbf_convention_and_hyper_parameters():
    X = torch.tensor([[0.0, 0.0]], dtype=F64)
    m = LSSVR(kernel="rbf", sigma=2.0, C=1.0).fit(X, torch.tensor([1.0], dtype=F64))
    # one support vector: alpha = 1 / (1 + 1/C) * (1 - b) with b from e^T alpha = 0 -> alpha=0
    assert float(m.alpha.detach().abs().max()) < 1e-12 and abs(float(m.b.detach()) - 1.0) < 1e-12
    with torch.no_grad():
        m.alpha.fill_(1.0)
        m.b.zero_()
    # ||x - P_1|| = sigma  ->  exp(-1/2)
    assert abs(float(m(torch.tensor([[2.0, 0.0]], dtype=F64)).detach()) - math.exp(-0.5)) < 1e-15
    assert [n for n, _ in m.named_parameters()] == ["alpha", "b", "log_sigma", "log_C"]
    assert not m.log_sigma.requires_grad and not m.log_C.requires_grad
    assert abs(float(m.sigma) - 2.0) < 1e-15 and abs(float(m.C) - 1.0) < 1e-15
    t = LSSVR(trainable_hyper=True)
    assert t.log_sigma.requires_grad and t.log_C.requires_grad


@pytest.mark.parametrize("kernel, kw", _KERNEL_ARGS)
def test_lssvr_input_gradient_matches_finite_differences(kernel, kw):
    X, y = _lssvr_data(seed=2)
    m = LSSVR(kernel=kernel, n_out=2, **kw).fit(X, y)
    x = _randn(4, 3, seed=3) * 0.5
    G = m.input_gradient(x).detach()
    assert G.shape == (4, 2, 3)
    with torch.no_grad():  # also works inside no_grad
        G2 = m.input_gradient(x)
    for bi in range(4):
        fd = _fd_input_jacobian(lambda v: m(v).detach(), x[bi])
        np.testing.assert_allclose(G[bi].numpy(), fd.numpy(), rtol=1e-6, atol=1e-8)
        np.testing.assert_allclose(G2[bi].numpy(), fd.numpy(), rtol=1e-6, atol=1e-8)


def test_lssvr_input_gradient_matches_paper_closed_form():
    # one-output LS-SVR on an embedding P_s = [x_{s-m+1}, ..., x_s] (paper 002, Eq. 18-26)
    rng = np.random.default_rng(4)
    series = np.cumsum(rng.standard_normal(40)) * 0.1
    m_emb = 4
    P = np.stack([series[i : i + m_emb] for i in range(len(series) - m_emb)])
    target = series[m_emb:]
    sigma = 0.8
    m = LSSVR(kernel="rbf", sigma=sigma, C=50.0).fit(torch.tensor(P), torch.tensor(target))
    alpha = m.alpha.detach().numpy()[:, 0]
    Ps = P[-5:] + 0.03
    G = m.input_gradient(torch.tensor(Ps)).detach().numpy()[:, 0, :]
    for s in range(Ps.shape[0]):
        phi = np.exp(-((Ps[s] - P) ** 2).sum(1) / (2 * sigma**2))  # Eq. 24
        grad = (alpha[:, None] * phi[:, None] * (-1.0 / sigma**2) * (Ps[s] - P)).sum(0)  # Eq. 25
        np.testing.assert_allclose(G[s], grad, rtol=1e-10, atol=1e-12)
        dPs_dxs = np.zeros(m_emb)
        dPs_dxs[-1] = 1.0  # Eq. 22
        F = np.trace(np.outer(grad, dPs_dxs))  # Eq. 20/23/26: the last component
        assert abs(G[s, -1] - F) < 1e-12


def test_lssvr_state_dict_round_trip_and_refit():
    X, y = _lssvr_data()
    m = LSSVR(kernel="rbf", sigma=0.5, n_out=2).fit(X, y)
    fresh = LSSVR(kernel="rbf", sigma=0.5, n_out=2)
    fresh.load_state_dict(m.state_dict())
    x = _randn(5, 3, seed=1)
    for k, v in m.state_dict().items():
        assert torch.equal(fresh.state_dict()[k], v), k
    # equal up to the summation order of the BLAS kernel (memory alignment)
    np.testing.assert_allclose(fresh(x).detach().numpy(), m(x).detach().numpy(), rtol=1e-14)
    alpha_param = m.alpha
    m.fit(X + 0.1, y)  # same M: parameter object kept
    assert m.alpha is alpha_param
    m.fit(X[:10], y[:10])  # new M
    assert m.alpha.shape == (10, 2) and m.support_vectors.shape == (10, 3)


def test_lssvr_bad_inputs():
    with pytest.raises(ValueError, match="kernel"):
        LSSVR(kernel="laplace")
    with pytest.raises(ValueError, match="sigma"):
        LSSVR(sigma=0.0)
    with pytest.raises(ValueError, match="^C must"):
        LSSVR(C=-1.0)
    X, y = _lssvr_data()
    m = LSSVR(n_out=2)
    with pytest.raises(RuntimeError, match="not fitted"):
        m(X)
    with pytest.raises(ValueError, match=r"^y must have shape"):
        m.fit(X, y[:-2])
    with pytest.raises(ValueError, match=r"^y must have shape"):
        m.fit(X, y[:, 0])  # (N,) only accepted when n_out == 1
    Xbad = X.clone()
    Xbad[0, 0] = float("inf")
    with pytest.raises(ValueError, match=r"^X contains non-finite"):
        m.fit(Xbad, y)
    ybad = y.clone()
    ybad[1, 1] = float("nan")
    with pytest.raises(ValueError, match=r"^y contains non-finite"):
        m.fit(X, ybad)
    m.fit(X, y)
    with pytest.raises(ValueError, match=r"^x must have shape"):
        m(torch.zeros(4, 4, dtype=F64))
    with pytest.raises(TypeError, match=r"^x has dtype"):
        m(X.float())
    with pytest.raises(ValueError, match=r"^x must have shape \(B, n_in\)"):
        m.input_gradient(X.reshape(5, 5, 3))


# =============================================================================== ANFIS (paper 003)


def _np_anfis(x, mf, alpha, prem, n_mfs):
    """Independent NumPy ANFIS (paper 003, Eq. 1-5) with plain products (no log space).

    alpha[o][m][i] = alpha_{m+1}^{i+1} of output o; prem: dict of (n, n_mfs) arrays.
    """
    n = x.shape[1]
    rules = list(itertools.product(range(n_mfs), repeat=n))
    out = np.zeros((x.shape[0], len(alpha)))
    for r in range(x.shape[0]):
        u = x[r]  # Eq. 1
        gamma = np.zeros((n, n_mfs))
        for j in range(n):
            for l in range(n_mfs):
                if mf == "sigmoid":  # Eq. 2
                    gamma[j, l] = 1 / (1 + math.exp(-prem["b"][j, l] * (u[j] - prem["beta"][j, l])))
                elif mf == "gaussian":
                    gamma[j, l] = math.exp(
                        -((u[j] - prem["c"][j, l]) ** 2) / (2 * prem["sigma"][j, l] ** 2)
                    )
                else:
                    z = abs((u[j] - prem["c"][j, l]) / prem["a"][j, l])
                    gamma[j, l] = 1 / (1 + z ** (2 * prem["b"][j, l]))
        w = np.array([np.prod([gamma[j, rule[j]] for j in range(n)]) for rule in rules])  # Eq. 3
        wbar = w / w.sum()  # Eq. 4
        for o in range(len(alpha)):
            f = [
                sum(alpha[o][m][i] * u[m] for m in range(n)) + alpha[o][n][i]
                for i in range(len(rules))
            ]
            out[r, o] = float(np.dot(wbar, f))  # Eq. 5
    return out


def test_anfis_paper_structure_and_eq44_order():
    m = ANFIS(3, 2, mf="sigmoid")
    assert m.n_rules == 8
    theta = m.parameters_flat()
    assert theta.shape == (44,)
    # Eq. 44: [alpha_1^1, alpha_1^2, ..., alpha_4^8, b_11, b_12, ..., b_32, beta_11, ..., beta_32]
    expected = [f"alpha_{mm}^{i}" for mm in range(1, 5) for i in range(1, 9)]
    expected += [f"b_{j},{l}" for j in range(1, 4) for l in range(1, 3)]
    expected += [f"beta_{j},{l}" for j in range(1, 4) for l in range(1, 3)]
    assert m.flat_parameter_names() == expected
    # fill with coded values through the documented paper indices and read them back in order
    with torch.no_grad():
        for mm in range(1, 5):
            for i in range(1, 9):
                m.alpha[0, mm - 1, i - 1] = 100 * mm + i
        for j in range(1, 4):
            for l in range(1, 3):
                m.b[j - 1, l - 1] = 1000 + 10 * j + l
                m.beta[j - 1, l - 1] = 2000 + 10 * j + l
    code = [100 * mm + i for mm in range(1, 5) for i in range(1, 9)]
    code += [1000 + 10 * j + l for j in range(1, 4) for l in range(1, 3)]
    code += [2000 + 10 * j + l for j in range(1, 4) for l in range(1, 3)]
    assert m.parameters_flat().tolist() == code
    assert torch.cat([p.reshape(-1) for p in m.parameters()]).tolist() == code


def test_anfis_forward_from_eq44_vector_matches_numpy():
    # a random theta laid out as Eq. 44, decoded by paper indices for the NumPy reference
    m = ANFIS(3, 2, mf="sigmoid")
    theta = _randn(44, seed=11)
    names = [n for n, _ in m.named_parameters()]
    sizes = [p.numel() for p in m.parameters()]
    chunks = dict(zip(names, torch.split(theta, sizes)))
    params = {n: chunks[n].reshape(p.shape) for n, p in m.named_parameters()}
    x = _randn(6, 3, seed=12)
    out = functional_call(m, params, (x,))
    th = theta.numpy()
    alpha = [[[th[(mm - 1) * 8 + (i - 1)] for i in range(1, 9)] for mm in range(1, 5)]]
    b = np.array([[th[32 + (j - 1) * 2 + (l - 1)] for l in (1, 2)] for j in (1, 2, 3)])
    beta = np.array([[th[38 + (j - 1) * 2 + (l - 1)] for l in (1, 2)] for j in (1, 2, 3)])
    ref = _np_anfis(x.numpy(), "sigmoid", alpha, {"b": b, "beta": beta}, 2)
    np.testing.assert_allclose(out.detach().numpy(), ref, rtol=1e-12, atol=1e-13)


@pytest.mark.parametrize("mf", ["sigmoid", "gaussian", "bell"])
@pytest.mark.parametrize("n_inputs, n_mfs", [(2, 3), (3, 2), (1, 4)])
def test_anfis_forward_matches_numpy(mf, n_inputs, n_mfs):
    m = ANFIS(n_inputs, n_mfs, mf=mf, n_out=2, generator=_gen(1))
    X = _randn(30, n_inputs, seed=2)
    m.init_premises(X)
    with torch.no_grad():
        for k, p in enumerate(m.parameters()):
            p.add_(0.1 * _randn(*p.shape, seed=20 + k))
    x = _randn(5, n_inputs, seed=3)
    prem = {n: getattr(m, n).detach().numpy() for n in m.premise_names}
    ref = _np_anfis(x.numpy(), mf, m.alpha.detach().numpy(), prem, n_mfs)
    np.testing.assert_allclose(m(x).detach().numpy(), ref, rtol=1e-11, atol=1e-12)
    wbar = m.firing_strengths(x)
    assert wbar.shape == (5, n_mfs**n_inputs)
    np.testing.assert_allclose(wbar.sum(-1).detach().numpy(), 1.0, rtol=1e-14)


def test_anfis_no_underflow_far_from_data():
    m = ANFIS(3, 2, mf="gaussian")
    with torch.no_grad():
        m.sigma.fill_(0.05)
    x = torch.full((2, 3), 40.0, dtype=F64)  # every membership underflows to 0 in plain form
    out = m(x)
    assert torch.isfinite(out).all()
    w = m.firing_strengths(x)
    np.testing.assert_allclose(w.sum(-1).detach().numpy(), 1.0)


@pytest.mark.parametrize("mf", ["sigmoid", "gaussian", "bell"])
def test_anfis_init_premises(mf):
    rng = np.random.default_rng(0)
    X = torch.tensor(np.stack([rng.uniform(-2, 4, 50), rng.uniform(10, 11, 50)], 1))
    m = ANFIS(2, 3, mf=mf).init_premises(X)
    lo, hi = X.min(0).values.numpy(), X.max(0).values.numpy()
    prem = {n: getattr(m, n).detach().numpy() for n in m.premise_names}
    centre = prem["beta"] if mf == "sigmoid" else prem["c"]
    # value of each MF at the midpoint between the first two centres, for both inputs at once
    mid = torch.tensor(0.5 * (centre[:, 0] + centre[:, 1]))[None, :]
    mu = torch.exp(log_membership(mid, mf, m.premises()))[0].detach().numpy()  # (2, 3)
    for j in range(2):
        if mf == "sigmoid":
            np.testing.assert_allclose(centre[j], np.linspace(lo[j], hi[j], 5)[1:-1], rtol=1e-12)
            # 'low' MF (negative slope) at lo: 1 / (1 + exp(-4)) (0.12 -> 0.88 over one spacing)
            g_lo = 1 / (1 + np.exp(-prem["b"][j, 0] * (lo[j] - centre[j, 0])))
            assert abs(g_lo - 1 / (1 + math.exp(-4))) < 1e-12
            assert prem["b"][j, 0] < 0 and prem["b"][j, 2] > 0
        else:
            np.testing.assert_allclose(centre[j], np.linspace(lo[j], hi[j], 3), rtol=1e-12)
            np.testing.assert_allclose(mu[j, :2], [0.5, 0.5], rtol=1e-12)  # neighbours cross at 0.5


def _np_regressors(x, m):
    """V of paper 003 Eq. 6 in the Eq. 44 consequent order (m-major, rule index fastest)."""
    prem = {n: getattr(m, n).detach().numpy() for n in m.premise_names}
    n, R = x.shape[1], m.n_rules
    V = np.zeros((x.shape[0], (n + 1) * R))
    for i in range(R):
        for mm in range(n + 1):
            alpha = np.zeros((1, n + 1, R))
            alpha[0, mm, i] = 1.0
            V[:, mm * R + i] = _np_anfis(x, m.mf, alpha, prem, m.n_mfs)[:, 0]
    return V


@pytest.mark.parametrize("n_samples", [40, 10])  # over- and under-determined (P = 27)
def test_anfis_lstsq_consequents_match_numpy(n_samples):
    rng = np.random.default_rng(5)
    X = rng.uniform(-1, 1, (n_samples, 2))
    y = np.stack([np.sin(3 * X[:, 0]) + X[:, 1], X[:, 0] * X[:, 1]], 1)
    m = ANFIS(2, 3, mf="gaussian", n_out=2).init_premises(torch.tensor(X))
    m.init_consequents_lstsq(torch.tensor(X), torch.tensor(y))
    V = _np_regressors(X, m)
    theta = np.linalg.lstsq(V, y, rcond=None)[0]  # (27, 2), minimum norm
    got = m.alpha.detach().numpy().reshape(2, -1).T
    np.testing.assert_allclose(got, theta, rtol=1e-7, atol=1e-9)
    np.testing.assert_allclose(m(torch.tensor(X)).detach().numpy(), V @ theta, atol=1e-9)
    # ridge
    lam = 0.3
    m.init_consequents_lstsq(torch.tensor(X), torch.tensor(y), lam=lam)
    ridge = np.linalg.solve(V.T @ V + lam * np.eye(V.shape[1]), V.T @ y)
    got = m.alpha.detach().numpy().reshape(2, -1).T
    np.testing.assert_allclose(got, ridge, rtol=1e-9, atol=1e-11)


def test_anfis_bad_inputs():
    with pytest.raises(ValueError, match="mf"):
        ANFIS(2, mf="triangle")
    with pytest.raises(ValueError, match="n_mfs"):
        ANFIS(2, n_mfs=0)
    m = ANFIS(3)
    with pytest.raises(ValueError, match=r"^x must have shape"):
        m(torch.zeros(4, 4, dtype=F64))
    with pytest.raises(TypeError, match=r"^x has dtype"):
        m(torch.zeros(4, 3, dtype=torch.float32))
    with pytest.raises(TypeError, match=r"^x must be a torch.Tensor"):
        m(np.zeros((4, 3)))
    X = _randn(10, 3)
    with pytest.raises(ValueError, match=r"^y must have shape"):
        m.init_consequents_lstsq(X, torch.zeros(9, dtype=F64))
    Xbad = X.clone()
    Xbad[2, 2] = float("nan")
    with pytest.raises(ValueError, match=r"^X contains non-finite"):
        m.init_premises(Xbad)
    with pytest.raises(ValueError, match=r"^y contains non-finite"):
        m.init_consequents_lstsq(X, torch.full((10,), float("nan"), dtype=F64))
    with pytest.raises(ValueError, match=r"^X must have shape"):
        m.init_premises(torch.zeros(10, 2, dtype=F64))


# =============================================================================== all learners


def _fitted_learners(dtype=F64):
    X, y = _lssvr_data(20, seed=6)
    elm = ELM(3, 9, n_out=2, activation="tanh", generator=_gen(0), dtype=dtype)
    elm.fit_ridge(X, y, 1e-3)
    svr = LSSVR(kernel="rbf", sigma=0.8, n_out=2, trainable_hyper=True, dtype=dtype).fit(X, y)
    anfis = ANFIS(3, 2, mf="sigmoid", n_out=2, generator=_gen(0), dtype=dtype).init_premises(X)
    anfis.init_consequents_lstsq(X, y, lam=1e-3)
    return {"elm": elm, "lssvr": svr, "anfis": anfis}


@pytest.mark.parametrize("name", ["elm", "lssvr", "anfis"])
def test_vmap_over_parameter_vectors_equals_loop(name):
    model = _fitted_learners()[name]
    base = {n: p.detach() for n, p in model.named_parameters()}
    n_batch = 5
    batched = {
        n: p + 0.05 * _randn(n_batch, *p.shape, seed=30 + k)
        for k, (n, p) in enumerate(base.items())
    }
    x = _randn(7, 3, seed=40)
    out = vmap(lambda p: functional_call(model, p, (x,)))(batched)
    assert out.shape == (n_batch, 7, 2)
    for s in range(n_batch):
        ref = functional_call(model, {n: v[s] for n, v in batched.items()}, (x,))
        # entries near 0 are sums of O(1) terms: rounding is relative to the output's scale
        r = ref.detach().numpy()
        np.testing.assert_allclose(
            out[s].detach().numpy(), r, rtol=1e-13, atol=1e-13 * np.abs(r).max()
        )


@pytest.mark.parametrize("name", ["elm", "lssvr", "anfis"])
def test_input_jacobians_equal_finite_differences(name):
    model = _fitted_learners()[name]
    x = _randn(3, 3, seed=50) * 0.7
    f = lambda v: model(v)
    Jr = vmap(jacrev(f))(x)
    Jf = vmap(jacfwd(f))(x)
    assert Jr.shape == (3, 2, 3)
    for b in range(3):
        fd = _fd_input_jacobian(lambda v: model(v).detach(), x[b])
        np.testing.assert_allclose(Jr[b].detach().numpy(), fd.numpy(), rtol=1e-6, atol=1e-8)
    np.testing.assert_allclose(Jr.detach().numpy(), Jf.detach().numpy(), rtol=1e-12, atol=1e-13)


@pytest.mark.parametrize("name", ["elm", "lssvr", "anfis"])
def test_parameter_jacobians_equal_finite_differences(name):
    model = _fitted_learners()[name]
    params = {n: p.detach() for n, p in model.named_parameters()}
    x = _randn(4, 3, seed=60)
    f = lambda p: functional_call(model, p, (x,))
    Jr, Jf = jacrev(f)(params), jacfwd(f)(params)
    for n in params:
        fd = _fd_param_jacobian(model, n, x)
        np.testing.assert_allclose(
            Jr[n].detach().numpy(), fd.numpy(), rtol=1e-6, atol=1e-7, err_msg=n
        )
        np.testing.assert_allclose(
            Jf[n].detach().numpy(), Jr[n].detach().numpy(), rtol=1e-10, atol=1e-12
        )


@pytest.mark.parametrize("name", ["elm", "lssvr", "anfis"])
def test_float32_forward_matches_float64(name):
    m64 = _fitted_learners(F64)[name]
    m32 = _fitted_learners(torch.float32)[name]
    assert all(p.dtype == torch.float32 for p in m32.parameters())
    with torch.no_grad():
        for p32, p64 in zip(m32.parameters(), m64.parameters()):
            p32.copy_(p64)
    x = _randn(6, 3, seed=70)
    out32 = m32(x.float())
    assert out32.dtype == torch.float32 and out32.shape == (6, 2)
    np.testing.assert_allclose(out32.double().detach().numpy(), m64(x).detach().numpy(), atol=1e-4)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
@pytest.mark.parametrize("name", ["elm", "lssvr", "anfis"])
def test_learners_on_cuda_match_cpu(name):
    X, y = _lssvr_data(20, seed=6)
    cpu = _fitted_learners()[name]
    fresh = {
        "elm": lambda: ELM(3, 9, n_out=2, activation="tanh", generator=_gen(0)),
        "lssvr": lambda: LSSVR(kernel="rbf", sigma=0.8, n_out=2, trainable_hyper=True),
        "anfis": lambda: ANFIS(3, 2, mf="sigmoid", n_out=2, generator=_gen(0)),
    }[name]().to("cuda")
    Xc, yc = X.cuda(), y.cuda()
    if name == "elm":
        fresh.fit_ridge(Xc, yc, 1e-3)
    elif name == "lssvr":
        fresh.fit(Xc, yc)
    else:
        fresh.init_premises(Xc).init_consequents_lstsq(Xc, yc, lam=1e-3)
    x = _randn(6, 3, seed=70)
    out = fresh(x.cuda())
    assert out.device.type == "cuda"
    np.testing.assert_allclose(out.detach().cpu().numpy(), cpu(x).detach().numpy(), atol=1e-9)
    J = vmap(jacrev(fresh))(x.cuda())
    assert J.shape == (6, 2, 3) and J.device.type == "cuda"
    if name == "elm":  # ROS-ELM on the device, K stays float64 there
        fresh.init_online(Xc[:12], yc[:12], 1e-3)
        fresh.partial_fit(Xc[12:], yc[12:])
        assert fresh.K.device.type == "cuda" and fresh.K.dtype == F64
        ref = ELM(3, 9, n_out=2, activation="tanh", generator=_gen(0)).fit_ridge(X, y, 1e-3)
        np.testing.assert_allclose(fresh.beta.detach().cpu().numpy(), ref.beta.detach(), atol=1e-8)


def test_numpy_scalars_serve_as_hyper_parameters_and_bools_do_not():
    import numpy as np

    from prognos_torch.learners import FixedSizeLSSVR

    X = torch.randn(40, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    y = X.sum(-1)
    # (np.int64(10) was refused with "n_hidden must be a positive int, got np.int64(10)")
    a, b = ELM(3, np.int64(10)), ELM(3, 10)
    assert a.n_hidden == 10 and isinstance(a.n_hidden, int)
    torch.testing.assert_close(a.fit_ridge(X, y, np.float32(0.5))(X), b.fit_ridge(X, y, 0.5)(X))
    assert ANFIS(np.int64(3)).n_inputs == 3
    fs = FixedSizeLSSVR(n_support=np.int64(20), trials=np.int64(5))
    assert (fs.n_support, fs.trials) == (20, 5)
    with torch.no_grad():
        torch.testing.assert_close(LSSVR(sigma=np.float32(0.5), C=np.float64(10.0)).fit(X, y)(X),
                                   LSSVR(sigma=float(np.float32(0.5)), C=10.0).fit(X, y)(X))  # fmt: skip
    with pytest.raises(TypeError, match="C must be a real number, got bool True"):
        LSSVR(C=True)
    with pytest.raises(TypeError, match="lam must be a real number, got True"):
        ELM(3, 5).fit_ridge(X, y, True)
    with pytest.raises(ValueError, match="n_hidden must be a positive int, got True"):
        ELM(3, True)
    # a width whose square underflows: named, not "C is too large" after a NaN kernel
    with pytest.raises(ValueError, match="sigma = 1e-300 is too small: 2 sigma\\^2 underflows"):
        LSSVR(sigma=1e-300)


def test_meta_device_patterns_build_the_learners():
    # module.to("meta").to_empty(device=...) (ELM's float64 K copied data out of the meta
    # tensor) and building under a default-device context (ANFIS's premise range was made on
    # that device, its parameters on the generator's)
    for make in (lambda: ELM(3, 10), lambda: ANFIS(3, 2)):
        m = make().to("meta").to_empty(device="cpu")
        assert all(p.device.type == "cpu" for p in m.parameters())
    elm = ELM(3, 10)
    elm.init_online(
        torch.randn(20, 3, dtype=torch.float64), torch.randn(20, dtype=torch.float64), 1e-3
    )
    assert elm.to("meta").to_empty(device="cpu").K.dtype == torch.float64
    with torch.device("meta"):
        a = ANFIS(3, 2)
    assert a.b.device.type == "cpu"  # (the parameters follow the generator's device)


def test_an_exact_lssvr_larger_than_the_machine_is_refused_before_it_starts(monkeypatch):
    import prognos_torch.learners.lssvr as lssvr_mod

    # a machine of 1 GiB: 10,000 samples need 3 x 1e8 x 8 bytes = 2.2 GiB (the kernel blocks of
    # a 100,000-row fit ran 40 s into an allocator failure)
    monkeypatch.setattr(lssvr_mod, "_machine_memory", lambda device: 2**30)
    X = torch.zeros(10_000, 3, dtype=torch.float64)
    with pytest.raises(MemoryError, match=r"10,000 samples needs about 2.24 GiB.*FixedSizeLSSVR"):
        LSSVR().fit(X, X[:, 0])
    LSSVR().fit(X[:100], X[:100, 0])  # (within the memory: fitted)


def test_online_and_selection_errors_name_their_cause():
    from prognos_torch.learners import blocked_multistep_cv, ros_elm_init, ros_elm_update
    from prognos_torch.optim import EKF

    one = torch.ones(1, dtype=torch.float64)
    st = ros_elm_init([ELM(2, 5)], torch.randn(20, 1, dtype=torch.float64), 2, 0.1)
    with pytest.raises(ValueError, match="elms has 2 learners, the state 1 channels"):
        ros_elm_update([ELM(2, 5), ELM(2, 5)], st, one)  # (an IndexError)
    with pytest.raises(ValueError, match="elms\\[0\\] has n_hidden=7, .* made with 5"):
        ros_elm_update([ELM(2, 7)], st, one)  # (a matrix-shape error)
    X = torch.randn(40, 2, dtype=torch.float64)
    Y = X.sum(-1, keepdim=True)
    with pytest.raises(ValueError, match=r"inputs hold no sample \(shape \(0, 2\)\)"):
        EKF(ELM(2, 5), P0=1.0, R=1.0).step(X[:0], Y[:0])  # ("obs_dim must be a positive int")
    lm = LSSVR().fit(X[:30], Y[:30])
    opt = EKF(lm, P0=1.0, R=1e-2)
    lm.fit(X, Y)
    with pytest.raises(ValueError, match=r"'alpha' now has shape \(40, 1\).*new optimiser"):
        opt.step(X[:5], Y[:5])
    fit = lambda a, b: lambda x: x[:, -1]  # noqa: E731 (persistence)
    s = torch.randn(30, dtype=torch.float64)
    with pytest.raises(ValueError, match="threshold must be a finite number or None, got 'a'"):
        blocked_multistep_cv(fit, s, 3, 2, threshold="a")
    s[10] = math.nan
    with pytest.raises(ValueError, match="missing or non-finite value at index 10"):
        blocked_multistep_cv(fit, s, 3, 2)  # (it returned NaN scores)


def test_both_forms_of_the_batched_consequents_agree(monkeypatch):
    import prognos_torch.learners.anfis as anfis_mod

    g = torch.Generator().manual_seed(3)
    net = ANFIS(3, 2, n_out=2, generator=g)
    params = {k: v.detach().expand(7, *v.shape) + 0.01 * torch.randn(7, *v.shape, generator=g,
                                                                     dtype=v.dtype)
              for k, v in net.named_parameters()}  # fmt: skip
    x = torch.randn(5, 3, generator=g, dtype=torch.float64)
    out, jac = net.forward_and_jacobian(params, x)
    monkeypatch.setattr(anfis_mod, "KRON_MAX_ENTRIES", 0)  # the direct product, as for large B R^2
    out2, jac2 = net.forward_and_jacobian(params, x)
    torch.testing.assert_close(out2, out, rtol=1e-13, atol=1e-14)
    for k in jac:
        torch.testing.assert_close(jac2[k], jac[k], rtol=1e-13, atol=1e-14)
    ref = vmap(lambda p: functional_call(net, p, (x,)))(params)
    torch.testing.assert_close(out2, ref, rtol=1e-13, atol=1e-14)
