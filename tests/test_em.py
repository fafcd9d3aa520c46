"""EM for linear-Gaussian models against a plain NumPy EM (dense Kalman/RTS, normal equations)."""

import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from prognos_torch.core import GaussianBelief
from prognos_torch.filters import ekf, run
from prognos_torch.optim import em_linear_gaussian

sys.path.insert(0, str(Path(__file__).parent))
from _kalman_reference import numpy_em_step, rts_reference  # noqa: E402

dt = torch.float64
t = lambda a: torch.as_tensor(a, dtype=dt)  # noqa: E731


def problem(seed, n=2, m=2, T=60, batch=2):
    g = np.random.default_rng(seed)
    out = []
    for _ in range(batch):
        A = np.array([[0.9, 0.2], [-0.1, 0.7]]) + 0.05 * g.normal(size=(n, n))
        C = np.array([[1.0, 0.0], [0.5, 1.0]])[:m]
        Q, R = np.diag([0.3, 0.1]), np.diag([0.5, 0.2])[:m, :m]
        x, ys = np.zeros(n), []
        for _ in range(T):
            x = A @ x + g.multivariate_normal(np.zeros(n), Q)
            ys.append(C @ x + g.multivariate_normal(np.zeros(m), R))
        ys = np.array(ys)
        ys[[5, 17, T - 1]] = np.nan  # missing rows, one at the end
        start = (
            A + 0.2 * g.normal(size=(n, n)),
            C + 0.2 * g.normal(size=(m, n)),
            np.eye(n) * 0.5,
            np.eye(m) * 1.0,
            np.zeros(n),
            np.eye(n) * 2.0,
            ys,
        )
        out.append(start)
    return out


def batched(problems):
    st = lambda i: t(np.stack([p[i] for p in problems]))  # noqa: E731
    A, C, Q, R, m0, P0 = (st(i) for i in range(6))
    ys = t(np.stack([p[6] for p in problems], axis=1))
    chol = torch.linalg.cholesky
    return A, C, chol(Q), chol(R), GaussianBelief.from_cov(m0, P0), ys


@pytest.mark.parametrize(
    "learn", [("A", "C", "Q", "R", "init"), ("A", "Q", "R")], ids=["all", "A-Q-R"]
)
def test_em_equals_numpy_em_over_several_iterations(learn):
    problems = problem(0)
    A, C, SQ, SR, b0, ys = batched(problems)
    iters = 5
    fit = em_linear_gaussian(A, C, SQ, SR, b0, ys, iterations=iters, learn=learn)
    assert fit.iterations == iters and fit.trace.shape == (iters + 1, 2)
    for i, p in enumerate(problems):
        state = p[:6]
        lls = []
        for _ in range(iters):
            *state, ll = numpy_em_step(*state, p[6], learn)
            lls.append(ll)
        lls.append(rts_reference(*state, p[6])["ll"])
        An, Cn, Qn, Rn, m0n, P0n = state
        np.testing.assert_allclose(fit.A[i].numpy(), An, atol=1e-8, rtol=0)
        np.testing.assert_allclose(fit.C[i].numpy(), Cn, atol=1e-8, rtol=0)
        np.testing.assert_allclose((fit.chol_Q @ fit.chol_Q.mT)[i].numpy(), Qn, atol=1e-8)
        np.testing.assert_allclose((fit.chol_R @ fit.chol_R.mT)[i].numpy(), Rn, atol=1e-8)
        np.testing.assert_allclose(fit.init.mean[i].numpy(), m0n, atol=1e-8, rtol=0)
        np.testing.assert_allclose(fit.init.cov[i].numpy(), P0n, atol=1e-8, rtol=0)
        np.testing.assert_allclose(fit.trace[:, i].numpy(), lls, atol=1e-7, rtol=1e-12)
    if "C" not in learn:
        assert torch.equal(fit.C, C)


def test_em_log_likelihood_never_decreases():
    problems = problem(1, T=120, batch=3)
    A, C, SQ, SR, b0, ys = batched(problems)
    fit = em_linear_gaussian(A, C, SQ, SR, b0, ys, iterations=25)
    d = fit.trace[1:] - fit.trace[:-1]
    assert bool((d >= -1e-9 * fit.trace[1:].abs()).all()), d.min()
    assert bool((fit.trace[-1] - fit.trace[0] > 1.0).all())
    # the returned model reproduces the last log-likelihood
    ll = run(ekf(), fit.model, fit.init, ys).log_likelihood
    torch.testing.assert_close(ll, fit.log_likelihood)


def test_em_tol_stops_early_and_unbatched_inputs():
    (p,) = problem(2, batch=1)
    A, C, SQ, SR, b0, ys = batched([p])
    fit = em_linear_gaussian(A[0], C[0], SQ[0], SR[0], b0[0], ys[:, 0], iterations=500, tol=1e-4)
    assert fit.iterations < 100 and fit.A.shape == (2, 2)
    rise = fit.trace[-1] - fit.trace[-2]
    assert float(rise) <= 1e-4 * (1 + abs(float(fit.trace[-1])))


def test_em_bad_arguments():
    (p,) = problem(3, batch=1)
    A, C, SQ, SR, b0, ys = batched([p])
    with pytest.raises(ValueError, match="learn"):
        em_linear_gaussian(A, C, SQ, SR, b0, ys, learn=("B",))
    with pytest.raises(ValueError, match="A must have shape"):
        em_linear_gaussian(A[..., :1], C, SQ, SR, b0, ys)
    with pytest.raises(ValueError, match="ys must have shape"):
        em_linear_gaussian(A, C, SQ, SR, b0, ys[..., :1])
    part = ys.clone()
    part[3, 0, 0] = float("nan")
    with pytest.raises(ValueError, match="partially observed"):
        em_linear_gaussian(A, C, SQ, SR, b0, part)
    fit = em_linear_gaussian(A, C, SQ, SR, b0, part, iterations=2, learn=("A", "Q", "init"))
    assert bool(torch.isfinite(fit.A).all())


def test_em_refuses_non_finite_matrices_a_string_of_names_and_a_bad_tol():
    (p,) = problem(3, batch=1)
    A, C, SQ, SR, b0, ys = batched([p])
    for name in ("A", "C"):
        bad = {"A": A.clone(), "C": C.clone()}
        bad[name][0, 0, 0] = float("nan")
        with pytest.raises(ValueError, match=f"^{name} contains non-finite"):  # (not "init")
            em_linear_gaussian(bad["A"], bad["C"], SQ, SR, b0, ys, iterations=0)
    with pytest.raises(TypeError, match="learn must be a collection of names"):
        em_linear_gaussian(A, C, SQ, SR, b0, ys, learn="init")
    for tol in (-1.0, "x"):
        with pytest.raises(ValueError, match="tol must be a number >= 0"):
            em_linear_gaussian(A, C, SQ, SR, b0, ys, tol=tol)
    with pytest.raises(TypeError, match="ys must be a torch.Tensor, got ndarray"):
        em_linear_gaussian(A, C, SQ, SR, b0, ys.numpy())


@pytest.mark.parametrize("rule", ["sckf", "ukf"])
def test_per_series_matrices_apply_to_their_own_series_sigma_points(rule):
    # 4 series and 2 n = 4 cubature points: right-aligned broadcasting paired A[j] with point j
    from prognos_torch.filters import make_filter, smooth
    from prognos_torch.optim import linear_model

    d, B, n, m = torch.float64, 4, 2, 1
    g = torch.Generator().manual_seed(0)
    A = torch.stack([torch.tensor([[0.9, 0.3 * b], [-0.2 * b, 0.8]], dtype=d) for b in range(B)])
    C = torch.tensor([[[1.0, 0.5]]], dtype=d).expand(B, m, n)
    model = linear_model(A, C, 0.3 * torch.eye(n, dtype=d), 0.5 * torch.eye(m, dtype=d))
    init = GaussianBelief(torch.zeros(B, n, dtype=d), torch.eye(n, dtype=d).expand(B, n, n))
    ys = torch.randn(10, B, m, dtype=d, generator=g)
    got, ref = smooth(make_filter(rule), model, init, ys), smooth(ekf(), model, init, ys)
    torch.testing.assert_close(got.means, ref.means, rtol=0, atol=1e-12)
    torch.testing.assert_close(got.log_likelihood, ref.log_likelihood, rtol=1e-12, atol=0)
    # per-series matrices with fewer dims than the belief's: refused, not paired with points
    init2 = GaussianBelief(torch.zeros(3, B, n, dtype=d), torch.eye(n, dtype=d).expand(3, B, n, n))
    with pytest.raises(ValueError, match=r"A has batch dims \(4,\), the states \(3, 4"):
        run(make_filter(rule), model, init2, ys.unsqueeze(1).expand(10, 3, B, m))


def test_em_equals_numpy_em_with_one_state_and_more_measurements_than_states():
    # n = 1, m = 3 (the other tests have n = m = 2), a missing first and middle row
    g = np.random.default_rng(4)
    n, m, T = 1, 3, 8
    A, C = np.array([[0.7]]), g.normal(size=(m, n))
    Q, R, m0, P0 = np.eye(n) * 0.4, np.diag([0.6, 0.3, 0.5]), np.zeros(n), np.eye(n) * 1.5
    ys = g.normal(size=(T, m))
    ys[[0, 4]] = np.nan
    ch = np.linalg.cholesky
    b0 = GaussianBelief.from_cov(t(m0), t(P0))
    fit = em_linear_gaussian(t(A), t(C), t(ch(Q)), t(ch(R)), b0, t(ys), iterations=3)
    state, lls = (A, C, Q, R, m0, P0), []
    for _ in range(3):
        *state, ll = numpy_em_step(*state, ys, ("A", "C", "Q", "R", "init"))
        lls.append(ll)
    lls.append(rts_reference(*state, ys)["ll"])
    An, Cn, Qn, Rn, m0n, P0n = state
    close = lambda a, b: np.testing.assert_allclose(a.numpy(), b, atol=1e-9, rtol=0)  # noqa: E731
    close(fit.A, An), close(fit.C, Cn), close(fit.chol_Q @ fit.chol_Q.mT, Qn)
    close(fit.chol_R @ fit.chol_R.mT, Rn), close(fit.init.mean, m0n), close(fit.init.cov, P0n)
    np.testing.assert_allclose(fit.trace.numpy(), lls, atol=1e-8, rtol=0)
