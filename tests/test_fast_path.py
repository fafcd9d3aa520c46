"""The optimiser face's fast path: the Cholesky prior and the sync-free fallback selection.

References: the engine's QR prior (``prior="qr"``, itself checked against the Kalman filter in
test_gaussian_filters.py) and the exact Kalman filter of a linear random walk.
"""

import sys
from dataclasses import replace
from pathlib import Path

import pytest
import torch

from prognos_torch.core import GaussianBelief, StateSpaceModel
from prognos_torch.filters import gaussian
from prognos_torch.filters.gaussian import GaussianFilter, Taylor
from prognos_torch.quadrature import julier

sys.path.insert(0, str(Path(__file__).parent))
from _kalman_reference import kalman_filter  # noqa: E402

N, M = 6, 2


def random_walk_problem(seed=0, batch=(), q=1e-3):
    g = torch.Generator().manual_seed(seed)
    W = torch.randn(M, N, generator=g, dtype=torch.float64)

    def h(x, u, k):  # nonlinear learner-like output
        return torch.tanh(x @ W.mT)

    model = StateSpaceModel(
        None,
        h,
        N,
        M,
        chol_Q=q**0.5 * torch.eye(N, dtype=torch.float64),
        chol_R=0.1 * torch.eye(M, dtype=torch.float64),
        batched=True,
    )
    m0 = torch.randn(*batch, N, generator=g, dtype=torch.float64)
    A = torch.randn(*batch, N, N, generator=g, dtype=torch.float64)
    S0 = torch.linalg.cholesky(A @ A.mT / N + 0.1 * torch.eye(N, dtype=torch.float64))
    ys = torch.randn(20, *batch, M, generator=g, dtype=torch.float64)
    return model, GaussianBelief(m0, S0), ys


def run(filt, model, belief, ys):
    st = filt.init(model, belief)
    out = []
    for k, y in enumerate(ys, 1):
        st, _ = filt.step(model, st, y, None, k)
        out.append((st.belief.mean, st.belief.chol))
    return out


@pytest.mark.parametrize("rule", [Taylor(), julier(1.0)], ids=["ekf", "srukf"])
@pytest.mark.parametrize("batch", [(), (3,)])
def test_cholesky_prior_equals_qr_prior(rule, batch):
    model, b0, ys = random_walk_problem(batch=batch)
    qr = run(GaussianFilter(rule), model, b0, ys)
    ch = run(GaussianFilter(rule, prior="cholesky"), model, b0, ys)
    for (m1, S1), (m2, S2) in zip(qr, ch):
        torch.testing.assert_close(m2, m1, rtol=0, atol=1e-12)
        torch.testing.assert_close(S2, S1, rtol=0, atol=1e-12)


@pytest.mark.parametrize("q", ["uniform", "diagonal"])
@pytest.mark.parametrize("traced", [False, True])
def test_cholesky_prior_linear_kalman_reference(monkeypatch, q, traced):
    g = torch.Generator().manual_seed(3)
    H = torch.randn(M, N, generator=g, dtype=torch.float64)
    sq = torch.full((N,), 0.1, dtype=torch.float64)
    if q == "diagonal":
        sq = torch.linspace(0.01, 0.3, N, dtype=torch.float64)
    Q, R = torch.diag(sq.square()), 0.04 * torch.eye(M, dtype=torch.float64)
    if traced:  # the traced step's form: Q's diagonal added, sync-free selections
        monkeypatch.setattr(gaussian, "_no_sync", lambda: True)
    model = StateSpaceModel(
        None,
        lambda x, u, k: x @ H.mT,
        N,
        M,
        chol_Q=torch.diag(sq),
        chol_R=0.2 * torch.eye(M, dtype=torch.float64),
        batched=True,
    )
    m0 = torch.zeros(N, dtype=torch.float64)
    P0 = torch.eye(N, dtype=torch.float64)
    ys = torch.randn(15, M, generator=g, dtype=torch.float64)
    eye = torch.eye(N, dtype=torch.float64)
    ref_m, ref_P, _ = kalman_filter(*(a.numpy() for a in (eye, H, Q, R, m0, P0, ys)))
    out = run(GaussianFilter(Taylor(), prior="cholesky"), model, GaussianBelief(m0, P0), ys)
    for k, (m, S) in enumerate(out):
        torch.testing.assert_close(m, torch.from_numpy(ref_m[k]), rtol=0, atol=1e-10)
        torch.testing.assert_close(S @ S.mT, torch.from_numpy(ref_P[k]), rtol=0, atol=1e-10)


@pytest.mark.parametrize("batch", [(), (3,)])
@pytest.mark.parametrize("traced", [False, True])
def test_diagonal_q_is_added_to_the_diagonal_with_the_same_result(monkeypatch, batch, traced):
    # Q diagonal, not a multiple of I: the Cholesky prior adds its diagonal instead of forming
    # S_Q S_Q^T; against the same prior with S_Q S_Q^T formed (diagonal test switched off)
    from prognos_torch.core import model as model_module

    model, b0, ys = random_walk_problem(batch=batch)
    q = torch.linspace(1e-4, 1e-2, N, dtype=torch.float64)
    model = replace(model, chol_Q=torch.diag(q.sqrt()))
    noise = model.checked_noise(1, b0.batch_shape, b0.mean)
    torch.testing.assert_close(noise.diag_Q, q, rtol=1e-15, atol=0)
    if traced:  # the traced step's form (the diagonal added at every batch size)
        monkeypatch.setattr(gaussian, "_no_sync", lambda: True)
    filt = GaussianFilter(Taylor(), prior="cholesky")
    diag = run(filt, model, b0, ys)
    monkeypatch.setattr(model_module, "diagonal_noise", lambda chol_Q: None)
    formed = run(filt, replace(model), b0, ys)  # (a new model: no remembered noise)
    for (m1, S1), (m2, S2) in zip(formed, diag):
        torch.testing.assert_close(m2, m1, rtol=0, atol=1e-13)
        torch.testing.assert_close(S2, S1, rtol=0, atol=1e-13)


def test_diagonal_noise_test_follows_the_factor():
    from prognos_torch.core.model import diagonal_noise

    D = torch.diag(torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64))
    torch.testing.assert_close(diagonal_noise(D), torch.tensor([1.0, 4.0, 9.0]).double())
    L = D.clone()
    L[2, 0] = 0.5
    assert diagonal_noise(L) is None
    # the checked noise remembers the test, and redoes it after an in-place change
    model, b0, _ = random_walk_problem()
    chol_Q = torch.eye(N, dtype=torch.float64)
    model = replace(model, chol_Q=chol_Q)
    assert model.checked_noise(1, (), b0.mean).diag_Q is not None
    chol_Q[3, 1] = 0.2
    assert model.checked_noise(1, (), b0.mean).diag_Q is None


@pytest.mark.parametrize("traced", [False, True])
def test_potter_posterior_linear_kalman_reference(monkeypatch, traced):
    # a scalar measurement of a linear random walk: Potter's posterior square root (not
    # triangular) carries the Kalman filter's means and covariances; the priors (Cholesky of
    # S S^T + Q) are triangular again
    g = torch.Generator().manual_seed(11)
    H = torch.randn(1, N, generator=g, dtype=torch.float64)
    sq = torch.linspace(0.01, 0.3, N, dtype=torch.float64)
    Q, R = torch.diag(sq.square()), torch.tensor([[0.04]], dtype=torch.float64)
    model = StateSpaceModel(
        None,
        lambda x, u, k: x @ H.mT,
        N,
        1,
        chol_Q=torch.diag(sq),
        chol_R=R.sqrt(),
        batched=True,
    )
    m0 = torch.randn(N, generator=g, dtype=torch.float64)
    A = torch.randn(N, N, generator=g, dtype=torch.float64)
    P0 = A @ A.mT / N + 0.1 * torch.eye(N, dtype=torch.float64)
    ys = torch.randn(15, 1, generator=g, dtype=torch.float64)
    eye = torch.eye(N, dtype=torch.float64)
    ref_m, ref_P, _ = kalman_filter(*(a.numpy() for a in (eye, H, Q, R, m0, P0, ys)))
    if traced:
        monkeypatch.setattr(gaussian, "_no_sync", lambda: True)
    filt = GaussianFilter(Taylor(), prior="cholesky", posterior="potter")
    st = filt.init(model, GaussianBelief.from_cov(m0, P0))
    for k, y in enumerate(ys, 1):
        st, info = filt.step(model, st, y, None, k)
        m, S = st.belief.mean, st.belief.chol
        torch.testing.assert_close(m, torch.from_numpy(ref_m[k - 1]), rtol=0, atol=1e-12)
        torch.testing.assert_close(S @ S.mT, torch.from_numpy(ref_P[k - 1]), rtol=0, atol=1e-12)
        assert not torch.equal(S, S.tril())  # Potter's factor, not a downdated triangle
        assert torch.equal(info.prior.chol, info.prior.chol.tril())


def test_posterior_option_is_checked():
    with pytest.raises(ValueError, match="posterior"):
        GaussianFilter(Taylor(), posterior="qr")
    with pytest.raises(ValueError, match="Taylor"):
        GaussianFilter(julier(1.0), posterior="potter")


def test_cholesky_prior_falls_back_to_qr_where_it_fails():
    # a zero factor and Q = 0: S S^T + Q = 0 has no Cholesky factor; Tria([0, 0]) = 0
    S = torch.zeros(2, N, N, dtype=torch.float64)
    S[1] = torch.eye(N, dtype=torch.float64)
    chol_Q = torch.zeros(N, N, dtype=torch.float64)
    L = gaussian._chol_prior(S, chol_Q)
    assert torch.isfinite(L).all()
    torch.testing.assert_close(L[0], torch.zeros(N, N, dtype=torch.float64))
    torch.testing.assert_close(L[1], torch.eye(N, dtype=torch.float64))


@pytest.mark.parametrize("prior", ["qr", "cholesky"])
def test_sync_free_selection_gives_the_same_numbers(monkeypatch, prior):
    # a very informative measurement makes the downdate fall back to the Joseph QR in some
    # batch elements; the traced (sync-free) form computes both and selects with torch.where
    model, b0, ys = random_walk_problem(batch=(4,), q=1e-4)
    model = replace(model, chol_R=1e-7 * torch.eye(M, dtype=torch.float64))
    filt = GaussianFilter(julier(1.0), prior=prior)
    eager = run(filt, model, b0, ys)
    monkeypatch.setattr(gaussian, "_no_sync", lambda: True)
    traced = run(filt, model, b0, ys)
    for (m1, S1), (m2, S2) in zip(eager, traced):
        assert torch.equal(m1, m2) and torch.equal(S1, S2)


def test_prior_option_is_checked():
    with pytest.raises(ValueError, match="prior"):
        GaussianFilter(Taylor(), prior="svd")


def test_traced_step_rejects_non_finite_measurements(monkeypatch):
    model, b0, ys = random_walk_problem()
    filt = GaussianFilter(julier(1.0), prior="cholesky")
    st = filt.init(model, b0)
    monkeypatch.setattr(gaussian, "_no_sync", lambda: True)
    y = ys[0].clone()
    y[0] = float("nan")
    with pytest.raises(RuntimeError, match="finite"):
        filt.step(model, st, y, None, 1)
    with pytest.raises(ValueError, match="shape"):
        filt.step(model, st, ys[0, :1], None, 1)
