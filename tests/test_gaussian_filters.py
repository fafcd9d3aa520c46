"""The Gaussian filter engine against exact references (Kalman filter, filterpy, finite differences)."""

import math
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from prognos_torch.core import GaussianBelief, StateSpaceModel, linear_gaussian_model
from prognos_torch.filters import (
    ckf,
    ekf,
    forecast,
    imsrukf,
    run,
    sckf,
    srukf,
    stsckf,
    ukf,
)
from prognos_torch.filters.gaussian import GaussianFilter, Taylor
from prognos_torch.quadrature import cubature, gauss_hermite, julier, unscented

sys.path.insert(0, str(Path(__file__).parent))
from _kalman_reference import kalman_filter  # noqa: E402

t = lambda a: torch.as_tensor(a, dtype=torch.float64)  # noqa: E731


def random_lgssm(seed, n, m, T):
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(n, n))
    F = 0.97 * A / np.max(np.abs(np.linalg.eigvals(A)))
    H = rng.normal(size=(m, n))
    LQ = np.tril(rng.normal(size=(n, n))) * 0.1 + np.eye(n) * 0.3
    LR = np.tril(rng.normal(size=(m, m))) * 0.1 + np.eye(m) * 0.5
    q, r = rng.normal(size=n) * 0.1, rng.normal(size=m) * 0.1
    m0, P0 = rng.normal(size=n), np.eye(n) * 2.0
    # simulate so that the measurements are plausible for the model
    x, ys = m0.copy(), []
    for _ in range(T):
        x = F @ x + q + LQ @ rng.normal(size=n)
        ys.append(H @ x + r + LR @ rng.normal(size=m))
    ys = np.array(ys)
    ys[T // 3] = np.nan  # one missing measurement: predict only
    model = linear_gaussian_model(t(F), t(H), t(LQ), t(LR), q=t(q), r=t(r))
    ref = kalman_filter(F, H, LQ @ LQ.T, LR @ LR.T, m0, P0, ys, q=q, r=r)
    return model, GaussianBelief.from_cov(t(m0), t(P0)), t(ys), ref


ALL_FILTERS = {
    "EKF": ekf(),
    "EKF-full": ekf(sqrt=False),
    "UKF": ukf(),
    "UKF-scaled-sqrt": ukf(alpha=0.5, beta=2.0, kappa=0.0, sqrt=True),
    "UKF-julier(3-n)": srukf(kappa=None),
    "UKF-julier(3-n)-full": GaussianFilter(julier(None), sqrt=False),  # W_0 < 0 for n > 3
    "SRUKF": srukf(),
    "CKF": ckf(),
    "SCKF": sckf(),
    "STSCKF(fading=1)": sckf(fading=1.0),
    "ImSRUKF(frozen)": imsrukf(
        noise=__import__("prognos_torch.adapt", fromlist=["x"]).SageHusa(frozen=True)
    ),
}


@pytest.mark.parametrize("name", list(ALL_FILTERS))
@pytest.mark.parametrize("seed,n,m", [(0, 20, 5), (1, 7, 3), (2, 2, 1)])
def test_linear_gaussian_matches_kalman(name, seed, n, m):
    model, b0, ys, (mr, Pr, llr) = random_lgssm(seed, n, m, 200)
    tr = run(ALL_FILTERS[name], model, b0, ys)
    assert torch.allclose(tr.means, t(mr), atol=1e-8, rtol=0)
    assert torch.allclose(tr.covs, t(Pr), atol=1e-8, rtol=0)
    assert abs(float(tr.log_likelihood) - llr) < 1e-8 * max(1.0, abs(llr))
    assert bool(torch.isnan(tr.nis[200 // 3]))


def test_ckf_equals_ukf_alpha1_beta0_kappa0():
    def f(x, u, k):
        return torch.stack([x[0] + 0.1 * torch.sin(x[1]), 0.9 * x[1] + 0.05 * x[0] ** 2, x[2]])

    def h(x, u, k):
        return torch.stack([x[0] * x[2], torch.atan(x[1])])

    model = StateSpaceModel(
        f,
        h,
        3,
        2,
        chol_Q=0.1 * torch.eye(3, dtype=torch.float64),
        chol_R=0.2 * torch.eye(2, dtype=torch.float64),
    )
    ys = torch.randn(40, 2, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    b0 = GaussianBelief(t([0.5, -0.2, 1.0]), torch.eye(3, dtype=torch.float64))
    a = run(sckf(), model, b0, ys)
    b = run(GaussianFilter(unscented(1.0, 0.0, 0.0), sqrt=True), model, b0, ys)
    c = run(GaussianFilter(unscented(1.0, 0.0, 0.0), sqrt=False), model, b0, ys)
    assert torch.allclose(a.means, b.means, atol=1e-12)
    assert torch.allclose(a.covs, b.covs, atol=1e-12)
    # square-root and full algebra agree on a nonlinear model too
    assert torch.allclose(b.means, c.means, atol=1e-10)
    assert torch.allclose(b.covs, c.covs, atol=1e-10)
    e1, e2 = run(ekf(), model, b0, ys), run(ekf(sqrt=False), model, b0, ys)
    assert torch.allclose(e1.means, e2.means, atol=1e-10)
    assert torch.allclose(e1.covs, e2.covs, atol=1e-10)


@pytest.mark.parametrize(
    "rule", [cubature(), unscented(0.5, 2.0, 1.0), julier(1.0), julier(None), gauss_hermite(3)]
)
def test_quadrature_exact_on_quadratics(rule):
    n = 3
    g = torch.Generator().manual_seed(0)
    m = torch.randn(n, generator=g, dtype=torch.float64)
    L = torch.tril(torch.randn(n, n, generator=g, dtype=torch.float64)) + 2 * torch.eye(n)
    A = torch.randn(n, n, generator=g, dtype=torch.float64)
    b = torch.randn(n, generator=g, dtype=torch.float64)
    P = L @ L.T
    xi, wm, wc = rule.points(n)
    X = m + xi @ L.T
    vals = ((X @ A) * X).sum(-1) + X @ b  # x^T A x + b^T x
    exact = m @ A @ m + torch.trace(A @ P) + b @ m
    assert torch.allclose((wm * vals).sum(), exact, atol=1e-10)
    # covariance of a linear map is exact with the covariance weights
    Y = X @ A.T
    ybar = (wm[:, None] * Y).sum(0)
    cov = ((Y - ybar).T * wc) @ (Y - ybar)
    assert torch.allclose(cov, A @ P @ A.T, atol=1e-9)


def test_ekf_jacobians_equal_finite_differences():
    def f(x, u, k):
        return torch.stack([torch.sin(x[0]) * x[1], x[0] ** 3 + torch.exp(0.1 * x[1])])

    model = StateSpaceModel(
        f, lambda x, u, k: x[:1] ** 2, 2, 1, chol_Q=torch.eye(2), chol_R=torch.eye(1)
    )
    x = torch.tensor([[0.3, -1.2], [1.1, 0.4]], dtype=torch.float64)
    J = model.transition_jacobian(x, None, 0)
    eps = 1e-6
    for j in range(2):
        d = torch.zeros(2, dtype=torch.float64)
        d[j] = eps
        fd = (model.transition(x + d, None, 0) - model.transition(x - d, None, 0)) / (2 * eps)
        assert torch.allclose(J[..., j], fd, atol=1e-8)


def test_batched_run_equals_loop_over_runs():
    model, b0, ys, _ = random_lgssm(4, 4, 2, 50)
    B = 3
    g = torch.Generator().manual_seed(1)
    means = b0.mean + 0.1 * torch.randn(B, 4, generator=g, dtype=torch.float64)
    yb = ys.unsqueeze(1) + 0.05 * torch.randn(50, B, 2, generator=g, dtype=torch.float64)
    for filt in (stsckf(), srukf(), ekf(), imsrukf()):
        bel = GaussianBelief(means, b0.chol.expand(B, 4, 4).clone())
        tb = run(filt, model, bel, yb)
        for i in range(B):
            ti = run(filt, model, GaussianBelief(means[i], b0.chol), yb[:, i])
            assert torch.allclose(tb.means[:, i], ti.means, atol=1e-12)
            assert torch.allclose(tb.chols[:, i], ti.chols, atol=1e-12)
            assert torch.allclose(tb.fading_factors[:, i], ti.fading_factors, atol=1e-12)


def ungm():
    def f(x, u, k):
        return (
            0.5 * x + 25 * x / (1 + x**2) + 8 * torch.cos(torch.as_tensor(1.2 * k, dtype=x.dtype))
        )

    def h(x, u, k):
        return x**2 / 20.0

    return StateSpaceModel(f, h, 1, 1, chol_Q=t([[math.sqrt(10.0)]]), chol_R=t([[1.0]]))


def test_matches_filterpy_ukf_on_ungm():
    filterpy = pytest.importorskip("filterpy.kalman")
    model = ungm()
    rng = np.random.default_rng(0)
    x, ys = 0.1, []
    for k in range(1, 101):
        x = 0.5 * x + 25 * x / (1 + x**2) + 8 * math.cos(1.2 * k) + math.sqrt(10) * rng.normal()
        ys.append(x**2 / 20 + rng.normal())
    alpha, beta, kappa = 1.0, 2.0, 2.0
    pts = filterpy.MerweScaledSigmaPoints(1, alpha=alpha, beta=beta, kappa=kappa)
    fp = filterpy.UnscentedKalmanFilter(
        dim_x=1,
        dim_z=1,
        dt=1.0,
        points=pts,
        fx=lambda x, dt, k: 0.5 * x + 25 * x / (1 + x**2) + 8 * math.cos(1.2 * k),
        hx=lambda x: x**2 / 20.0,
    )
    fp.x, fp.P, fp.Q, fp.R = (
        np.array([0.1]),
        np.array([[2.0]]),
        np.array([[10.0]]),
        np.array([[1.0]]),
    )
    ref_m, ref_P = [], []
    for k, y in enumerate(ys, start=1):
        fp.predict(k=k)
        fp.update(np.array([y]))
        ref_m.append(fp.x.copy())
        ref_P.append(fp.P.copy())
    # filterpy redraws sigma points from the predicted (x, P) before the update, as we do
    b0 = GaussianBelief.from_cov(t([0.1]), t([[2.0]]))
    for sqrt in (False, True):
        tr = run(
            GaussianFilter(unscented(alpha, beta, kappa), sqrt=sqrt), model, b0, t(ys)[:, None]
        )
        assert torch.allclose(tr.means, t(np.array(ref_m)), atol=1e-8, rtol=0)
        assert torch.allclose(tr.covs, t(np.array(ref_P)), atol=1e-8, rtol=0)


def test_reused_sigma_points_square_root_equals_full():
    # redraw=False keeps the propagated points (posterior by Cholesky downdate, paper 003 Eq. 29)
    model = ungm()
    ys = 5 * torch.randn(60, 1, generator=torch.Generator().manual_seed(2), dtype=torch.float64)
    b0 = GaussianBelief.from_cov(t([0.1]), t([[2.0]]))
    a = run(GaussianFilter(unscented(1.0, 2.0, 2.0), sqrt=False, redraw=False), model, b0, ys)
    b = run(GaussianFilter(unscented(1.0, 2.0, 2.0), sqrt=True, redraw=False), model, b0, ys)
    assert torch.allclose(a.means, b.means, atol=1e-9)
    assert torch.allclose(a.covs, b.covs, atol=1e-9)
    c = run(GaussianFilter(unscented(1.0, 2.0, 2.0), sqrt=False), model, b0, ys)
    assert not torch.allclose(a.means, c.means, atol=1e-3)  # the two variants really differ


def stiff_model(dtype):
    # two fast-decaying modes and two slow ones, time constants 1e-3 .. 1 apart, tiny Q on one;
    # batched with its Jacobians given (the long runs test the square-root numerics, not jacfwd:
    # the same numbers as linear_gaussian_model to 1e-15, at a third of the time)
    F = torch.diag(torch.tensor([0.9999, 0.999, 0.2, 1e-3], dtype=dtype))
    F[0, 1] = 0.05
    H = torch.tensor([[1.0, 0.0, 1.0, 0.0], [0.0, 1.0, 0.0, 1.0]], dtype=dtype)
    SQ = torch.diag(torch.tensor([1e-4, 1e-3, 1.0, 1e-6], dtype=dtype))
    SR = torch.diag(torch.tensor([1e-3, 1e-2], dtype=dtype))
    return StateSpaceModel(
        f=lambda x, u, k: x @ F.mT,
        h=lambda x, u, k: x @ H.mT,
        state_dim=4,
        obs_dim=2,
        chol_Q=SQ,
        chol_R=SR,
        batched=True,
        jac_f=lambda x, u, k: F.expand(*x.shape[:-1], 4, 4),
        jac_h=lambda x, u, k: H.expand(*x.shape[:-1], 2, 4),
    )


def test_covariances_stay_spd_over_10000_steps_float64():
    T, B = 10_000, 4
    model = stiff_model(torch.float64)
    g = torch.Generator().manual_seed(0)
    ys = 1e-2 * torch.randn(T, B, 2, generator=g, dtype=torch.float64)
    b0 = GaussianBelief(
        torch.zeros(B, 4, dtype=torch.float64),
        torch.eye(4, dtype=torch.float64).expand(B, 4, 4).clone(),
    )
    for filt in (sckf(), srukf(), ekf()):
        tr = run(filt, model, b0, ys)
        d = torch.diagonal(tr.chols, dim1=-2, dim2=-1)
        assert bool(torch.isfinite(tr.chols).all()) and bool((d > 0).all())
        P = tr.covs[-1]
        assert torch.allclose(P, P.mT)
        assert bool((torch.linalg.eigvalsh(P) > 0).all())


def test_forecast_equals_repeated_prediction_of_kalman():
    model, b0, ys, _ = random_lgssm(5, 3, 2, 10)
    F = model.transition_jacobian(torch.zeros(3, dtype=torch.float64), None, 0)
    fc = forecast(sckf(), model, b0, 4)
    m, P = b0.mean, b0.cov
    SQ = model.chol_Q
    for j in range(4):
        m = F @ m + model.q
        P = F @ P @ F.T + SQ @ SQ.T
        assert torch.allclose(fc.means[j], m, atol=1e-12)
        assert torch.allclose(fc.chols[j] @ fc.chols[j].T, P, atol=1e-12)
    H = model.observation_jacobian(m, None, 0)
    SR = model.chol_R
    assert torch.allclose(fc.y_chols[-1] @ fc.y_chols[-1].T, H @ P @ H.T + SR @ SR.T, atol=1e-12)


@pytest.mark.parametrize("name", ["SRUKF", "EKF", "SCKF"])
def test_very_informative_measurements_match_kalman(name, monkeypatch):
    """R tiny next to H P H^T: the posterior downdate would lose precision (determinant ratio far
    below the threshold), so the engine switches to the Joseph-form QR; still exact."""
    rng = np.random.default_rng(5)
    n, m, T = 6, 2, 40
    F = np.eye(n) + 0.05 * rng.normal(size=(n, n))
    H = rng.normal(size=(m, n))
    LQ, LR = 0.1 * np.eye(n), 1e-6 * np.eye(m)
    m0, P0 = np.zeros(n), 4.0 * np.eye(n)
    ys = rng.normal(size=(T, m))
    model = linear_gaussian_model(t(F), t(H), t(LQ), t(LR))
    mr, Pr, llr = kalman_filter(F, H, LQ @ LQ.T, LR @ LR.T, m0, P0, ys)
    calls = []
    import prognos_torch.filters.gaussian as engine

    real = engine.chol_downdate_ex

    def spy(S, V, W=None):
        out = real(S, V, W)
        calls.append(float(out[1].min()))
        return out

    monkeypatch.setattr(engine, "chol_downdate_ex", spy)
    tr = run(ALL_FILTERS[name], model, GaussianBelief.from_cov(t(m0), t(P0)), t(ys))
    assert min(calls) < engine._downdate_min_ratio(torch.float64)  # the fallback ran
    scale = float(np.abs(Pr).max())
    assert torch.allclose(tr.covs, t(Pr), atol=1e-8 * scale, rtol=0)
    assert torch.allclose(tr.means, t(mr), atol=1e-7, rtol=0)
    assert abs(float(tr.log_likelihood) - llr) < 1e-8 * max(1.0, abs(llr))


def _kalman_partial(F, H, Q, R, m0, P0, ys):
    """Kalman filter that updates with the observed rows of each measurement (reference)."""
    n = F.shape[0]
    m, P, ll, means, covs = m0.copy(), P0.copy(), 0.0, [], []
    for y in ys:
        m, P = F @ m, F @ P @ F.T + Q
        o = ~np.isnan(y)
        if o.any():
            Ho, Ro = H[o], R[np.ix_(o, o)]
            S = Ho @ P @ Ho.T + Ro
            e = y[o] - Ho @ m
            K = np.linalg.solve(S, Ho @ P).T
            m = m + K @ e
            IKH = np.eye(n) - K @ Ho
            P = IKH @ P @ IKH.T + K @ Ro @ K.T
            ll += -0.5 * (o.sum() * math.log(2 * math.pi) + np.linalg.slogdet(S)[1])
            ll += -0.5 * e @ np.linalg.solve(S, e)
        means.append(m.copy())
        covs.append(P.copy())
    return np.array(means), np.array(covs), ll


@pytest.mark.parametrize("name", ["EKF", "EKF-full", "UKF", "SRUKF", "SCKF", "UKF-julier(3-n)"])
def test_partially_observed_measurements_match_kalman(name):
    """NaN in some components: the update uses the observed ones, exactly (correlated R)."""
    rng = np.random.default_rng(11)
    n, m, T = 5, 3, 60
    A = rng.normal(size=(n, n))
    F = 0.95 * A / np.max(np.abs(np.linalg.eigvals(A)))
    H = rng.normal(size=(m, n))
    LQ = 0.3 * np.eye(n)
    LR = np.tril(rng.normal(size=(m, m))) * 0.2 + 0.5 * np.eye(m)  # correlated noise
    ys = rng.normal(size=(T, m))
    ys[rng.random((T, m)) < 0.3] = np.nan  # ~30 % of the components missing
    ys[7] = np.nan  # and one step missing as a whole
    model = linear_gaussian_model(t(F), t(H), t(LQ), t(LR))
    m0, P0 = np.zeros(n), 2.0 * np.eye(n)
    mr, Pr, llr = _kalman_partial(F, H, LQ @ LQ.T, LR @ LR.T, m0, P0, ys)
    tr = run(ALL_FILTERS[name], model, GaussianBelief.from_cov(t(m0), t(P0)), t(ys))
    assert torch.allclose(tr.means, t(mr), atol=1e-8, rtol=0)
    assert torch.allclose(tr.covs, t(Pr), atol=1e-8, rtol=0)
    assert abs(float(tr.log_likelihood) - llr) < 1e-8 * max(1.0, abs(llr))
    # a batch with different patterns per element equals the runs one by one
    ys2 = t(np.stack([ys, ys[::-1].copy()], axis=1))  # (T, 2, m)
    b2 = GaussianBelief.from_cov(t(m0), t(P0)).expand(2)
    tb = run(ALL_FILTERS[name], model, b2, ys2)
    for i in range(2):
        ti = run(ALL_FILTERS[name], model, GaussianBelief.from_cov(t(m0), t(P0)), ys2[:, i])
        assert torch.allclose(tb.means[:, i], ti.means, atol=1e-10, rtol=0)
        assert torch.allclose(tb.log_likelihoods[:, i], ti.log_likelihoods, atol=1e-9, rtol=0)


def test_partially_observed_steps_hold_adaptation():
    """Strong tracking gives lambda = 1 and the noise estimator holds on a partial step."""
    rng = np.random.default_rng(12)
    n, m, T = 3, 2, 30
    model = linear_gaussian_model(
        t(0.9 * np.eye(n)), t(rng.normal(size=(m, n))), t(0.2 * np.eye(n)), t(0.3 * np.eye(m))
    )
    ys = t(rng.normal(size=(T, m)) * 3.0)  # large innovations: fading factors > 1
    ys[10, 0] = float("nan")
    b0 = GaussianBelief.from_cov(t(np.zeros(n)), t(np.eye(n)))
    tr = run(stsckf(), model, b0, ys)
    assert float(tr.fading_factors[10]) == 1.0 and bool((tr.fading_factors > 1).any())
    tr = run(imsrukf(), model, b0, ys)
    assert torch.equal(tr.chol_R[10], tr.chol_R[9]) and not torch.equal(tr.chol_R[9], tr.chol_R[8])
    # the observed component still updates the state
    assert not torch.allclose(tr.means[10], tr.pred_means[10])


@pytest.mark.parametrize("name", ["SRUKF", "SCKF", "EKF"])
def test_float32_square_root_filters_track_the_float64_kalman_filter(name):
    """float32 runs the same code path (posterior downdate with a float32 precision threshold)."""
    model, b0, ys, (mr, Pr, _) = random_lgssm(1, 7, 3, 200)
    n = model.state_dim
    z = torch.zeros(n, dtype=torch.float64)
    F, H = model.transition_jacobian(z, None, 0), model.observation_jacobian(z, None, 0)
    m32 = linear_gaussian_model(
        F.float(), H.float(), model.chol_Q.float(), model.chol_R.float(),
        q=model.q.float(), r=model.r.float(),
    )  # fmt: skip
    tr = run(ALL_FILTERS[name], m32, GaussianBelief(b0.mean.float(), b0.chol.float()), ys.float())
    assert tr.means.dtype == torch.float32
    assert torch.allclose(tr.means.double(), t(mr), atol=2e-5, rtol=0)
    assert torch.allclose(tr.covs.double(), t(Pr), atol=2e-5, rtol=0)


def _julier_ut(fn, m, P, kappa):
    """Julier's unscented transform with the columns of chol(P) (paper 003 Eq. 12-13)."""
    n = m.shape[0]
    L = np.linalg.cholesky(P)
    X = np.vstack([m, m + math.sqrt(n + kappa) * L.T, m - math.sqrt(n + kappa) * L.T])
    w = np.full(2 * n + 1, 0.5 / (n + kappa))
    w[0] = kappa / (n + kappa)
    Y = np.stack([fn(x) for x in X])
    ybar = w @ Y
    return X, Y, ybar, w


def _numpy_stukf(f, h, Q, R, m, P, ys, kappa, rho=0.95, beta=1.0):
    """Plain full-covariance strong-tracking UKF (paper 000 Eq. 7-10, 17-20, 36), one run."""
    means, covs, lams, V = [], [], [], None
    for y in ys:
        _, Y, xbar, w = _julier_ut(f, m, P, kappa)
        Pf = (Y - xbar).T @ np.diag(w) @ (Y - xbar)

        def moments(Pp, xbar=xbar):
            X, Z, zbar, w = _julier_ut(h, xbar, Pp, kappa)
            Pzz = (Z - zbar).T @ np.diag(w) @ (Z - zbar)
            return zbar, Pzz, (X - xbar).T @ np.diag(w) @ (Z - zbar)

        zbar, Pzz, Pxz = moments(Pf + Q)
        e = y - zbar
        V = np.outer(e, e) if V is None else (rho * V + np.outer(e, e)) / (1 + rho)
        H = np.linalg.solve(Pf + Q, Pxz).T  # Eq. 17 (Pf + Q symmetric)
        trHQH = np.trace(H @ Q @ H.T)
        trN, trM = np.trace(V) - trHQH - beta * np.trace(R), np.trace(Pzz) - trHQH
        lam = trN / trM if trM > 0 and trN / trM > 1 else 1.0
        Pp = lam * Pf + Q  # Eq. 36
        if lam > 1:
            zbar, Pzz, Pxz = moments(Pp)
        S = Pzz + R
        K = np.linalg.solve(S, Pxz.T).T
        m, P = xbar + K @ (y - zbar), Pp - K @ S @ K.T
        means.append(m), covs.append(P), lams.append(lam)
    return np.array(means), np.array(covs), np.array(lams)


def test_full_covariance_stukf_with_negative_centre_weight_matches_numpy_and_filterpy():
    """STUKF with kappa = 3 - n (n = 4: W_0 = -1/3) in full-covariance form on the three-tank
    joint model of paper 000 (Eq. 62-63, drifting az2) equals a plain NumPy strong-tracking UKF;
    with the fading factor off it equals filterpy's UKF with JulierSigmaPoints(kappa = 3 - n)."""
    from prognos_torch.filters import stukf
    from prognos_torch.systems.three_tank import simulate_three_tank, three_tank_joint_model

    sim = simulate_three_tank(120, generator=torch.Generator().manual_seed(4))
    ys = sim.y[:, 0]
    model = three_tank_joint_model(chol_D=1e-3)
    n, kappa = 4, -1.0
    m0, P0 = np.array([1.0, 0.95, 0.9, 0.6]), np.diag([1e-3, 1e-3, 1e-3, 1e-2]) ** 2
    b0 = GaussianBelief.from_cov(t(m0), t(P0))
    SQ, SR = model.chol_Q.numpy(), model.chol_R.numpy()
    Q, R = SQ @ SQ.T, SR @ SR.T

    def f(x):
        return model.transition(t(x), None, 1).numpy()

    def h(x):
        return model.observe(t(x), None, 1).numpy()

    mr, Pr, lr = _numpy_stukf(f, h, Q, R, m0, P0, ys.numpy(), kappa)
    assert (lr > 1).sum() > 10  # the fading factor really acts
    tr = run(stukf(kappa=None, sqrt=False), model, b0, ys)
    scale = np.abs(Pr).max(axis=(1, 2))[:, None, None]
    assert np.abs(tr.fading_factors.numpy() - lr).max() < 1e-9 * lr.max()
    assert np.abs(tr.means.numpy() - mr).max() < 1e-10
    assert (np.abs(tr.covs.numpy() - Pr) / scale).max() < 1e-9
    # the square-root form (negative W_0 by Cholesky downdates) gives the same filter
    ts = run(stukf(kappa=None), model, b0, ys)
    assert torch.allclose(ts.means, tr.means, atol=1e-10, rtol=0)

    filterpy = pytest.importorskip("filterpy.kalman")
    pts = filterpy.JulierSigmaPoints(n, kappa=3 - n, sqrt_method=lambda A: np.linalg.cholesky(A).T)
    fp = filterpy.UnscentedKalmanFilter(
        dim_x=n, dim_z=3, dt=1.0, points=pts, fx=lambda x, dt: f(x), hx=h
    )
    fp.x, fp.P, fp.Q, fp.R = m0.copy(), P0.copy(), Q, R
    ref_m, ref_P = [], []
    for y in ys.numpy():
        fp.predict()
        fp.update(y)
        ref_m.append(fp.x.copy()), ref_P.append(fp.P.copy())
    tu = run(GaussianFilter(julier(None), sqrt=False), model, b0, ys)
    ref_P = np.array(ref_P)
    assert np.abs(tu.means.numpy() - np.array(ref_m)).max() < 1e-10
    scale = np.abs(ref_P).max(axis=(1, 2))[:, None, None]
    assert (np.abs(tu.covs.numpy() - ref_P) / scale).max() < 1e-9


@pytest.mark.parametrize("with_u", [False, True])
def test_default_jacobians_equal_finite_differences_and_nested_jacfwd(with_u):
    # a per-sample model without jac_f/jac_h: the engine's one-vmap forward mode
    from torch.func import jacfwd, vmap

    def f(x, u, k):
        out = torch.stack([x[0] * x[1], torch.sin(x[2]) + x[0] ** 2, x[1] * torch.exp(-x[2])])
        return out if u is None else out + u[0] * x

    def h(x, u, k):
        return torch.stack([x[0] + x[2] ** 3, x[1] * x[2]])

    p = 1 if with_u else 0
    model = StateSpaceModel(f=f, h=h, state_dim=3, obs_dim=2, chol_Q=torch.eye(3, dtype=torch.float64),
                            chol_R=torch.eye(2, dtype=torch.float64), control_dim=p)  # fmt: skip
    g = torch.Generator().manual_seed(4)
    x = torch.randn(2, 5, 3, dtype=torch.float64, generator=g)  # two leading dims
    u = torch.randn(5, 1, dtype=torch.float64, generator=g) if with_u else None  # broadcast
    Jf = model.transition_jacobian(x, u, 0)
    Jh = model.observation_jacobian(x, u, 0)
    assert Jf.shape == (2, 5, 3, 3) and Jh.shape == (2, 5, 2, 3)
    xf = x.reshape(-1, 3)
    uf = None if u is None else u.expand(2, 5, 1).reshape(-1, 1)
    for fn, J in ((f, Jf), (h, Jh)):
        if uf is None:
            ref = vmap(jacfwd(lambda xi, fn=fn: fn(xi, None, 0)))(xf)
        else:
            ref = vmap(jacfwd(lambda xi, ui, fn=fn: fn(xi, ui, 0)))(xf, uf)
        assert torch.allclose(J.reshape(ref.shape), ref, rtol=1e-15, atol=1e-15)
        # central differences, step 1e-6: error ~1e-10
        eps = 1e-6
        cols = []
        for j in range(3):
            e = torch.zeros(3, dtype=torch.float64)
            e[j] = eps
            up = torch.stack(
                [fn(xi + e, None if uf is None else uf[i], 0) for i, xi in enumerate(xf)]
            )
            dn = torch.stack(
                [fn(xi - e, None if uf is None else uf[i], 0) for i, xi in enumerate(xf)]
            )
            cols.append((up - dn) / (2 * eps))
        fd = torch.stack(cols, -1)
        assert torch.allclose(J.reshape(fd.shape), fd, rtol=1e-7, atol=1e-8)


def test_joint_state_parameter_model_batched_equals_per_sample():
    # paper 000 Eq. 3-4: [f(x, theta); theta]; the batched form skips vmap, same numbers
    from prognos_torch.core import joint_state_parameter_model
    from prognos_torch.filters import stsckf

    def f(x, th, u, k):
        return x + 0.1 * torch.stack([x[..., 1], -th[..., 0] * torch.sin(x[..., 0])], -1) + u

    def h(x, th, u, k):
        return torch.stack([x[..., 0] + th[..., 1], x[..., 1] ** 2], -1)

    kw = dict(state_dim=2, param_dim=2, obs_dim=2, control_dim=2,
              chol_Q=0.05 * torch.eye(2, dtype=torch.float64),
              chol_D=0.01 * torch.eye(2, dtype=torch.float64),
              chol_R=0.1 * torch.eye(2, dtype=torch.float64))  # fmt: skip
    per, bat = (
        joint_state_parameter_model(f, h, **kw),
        joint_state_parameter_model(f, h, batched=True, **kw),
    )
    assert not per.batched and bat.batched
    g = torch.Generator().manual_seed(5)
    z = torch.randn(3, 4, 4, dtype=torch.float64, generator=g)
    u = torch.randn(4, 2, dtype=torch.float64, generator=g)
    assert torch.allclose(bat.transition(z, u, 0), per.transition(z, u, 0), rtol=1e-15, atol=0)
    assert torch.equal(bat.transition(z, u, 0)[..., 2:], z[..., 2:])  # theta_k = theta_(k-1)
    assert torch.allclose(bat.observe(z, u, 0), per.observe(z, u, 0), rtol=1e-15, atol=0)
    assert torch.allclose(bat.transition_jacobian(z, u, 0), per.transition_jacobian(z, u, 0),
                          rtol=1e-15, atol=1e-15)  # fmt: skip
    T = 30
    ys = torch.randn(T, 4, 2, dtype=torch.float64, generator=g)
    us = 0.1 * torch.randn(T, 4, 2, dtype=torch.float64, generator=g)
    b0 = GaussianBelief(torch.zeros(4, 4, dtype=torch.float64),
                        torch.eye(4, dtype=torch.float64).expand(4, 4, 4).clone())  # fmt: skip
    for filt in (stsckf(), ekf()):
        a, b = run(filt, per, b0, ys, us), run(filt, bat, b0, ys, us)
        assert torch.allclose(a.means, b.means, rtol=0, atol=1e-12)
        assert torch.allclose(a.chols, b.chols, rtol=0, atol=1e-12)


def test_model_outputs_noise_and_settings_are_checked_not_broadcast():
    """A model whose h returned 2 values for obs_dim=1 ran to finite, wrong numbers (EKF, SIR);
    a NaN noise factor or fading=inf made every mean NaN; StrongTracking(beta=nan) switched
    itself off; a float32 chol beside a float64 mean failed deep in torch; from_cov symmetrised
    a non-symmetric matrix without a word."""
    from prognos_torch.adapt.strong_tracking import StrongTracking
    from prognos_torch.filters import sir

    F64 = torch.float64
    one = torch.eye(1, dtype=F64)
    b = GaussianBelief(torch.zeros(1, dtype=F64), one.clone())
    ys = torch.ones(3, 1, dtype=F64)
    wide_h = StateSpaceModel(lambda x, u, k: x, lambda x, u, k: torch.cat([x, 2 * x], -1), 1, 1,
                             chol_Q=one, chol_R=one)  # fmt: skip
    for filt in (ekf(), ukf(), sckf()):
        with pytest.raises(ValueError, match=r"model.h returned \(.*2,?\); it must return "
                           r"\(\.\.\., obs_dim\) = \(\.\.\., 1\)"):  # fmt: skip
            run(filt, wide_h, b, ys)
    with pytest.raises(ValueError, match="model.h returned"):
        sir(20).run(wide_h, b, ys, generator=torch.Generator().manual_seed(0))
    short_f = StateSpaceModel(lambda x, u, k: x[..., :1], lambda x, u, k: x, 2, 2,
                              chol_Q=torch.eye(2, dtype=F64), chol_R=torch.eye(2, dtype=F64))  # fmt: skip
    b2 = GaussianBelief(torch.zeros(2, dtype=F64), torch.eye(2, dtype=F64))
    with pytest.raises(ValueError, match=r"model.f returned \(1,\); it must return "
                       r"\(\.\.\., state_dim\) = \(\.\.\., 2\)"):  # fmt: skip
        run(ekf(), short_f, b2, torch.ones(3, 2, dtype=F64))
    nan_R = linear_gaussian_model(one, one, one, torch.full((1, 1), math.nan, dtype=F64))
    with pytest.raises(ValueError, match="model.chol_R contains non-finite values"):
        run(ekf(), nan_R, b, ys)
    with pytest.raises(ValueError, match="a constant fading factor must be a finite number"):
        ekf(fading=math.inf)
    for kw in (dict(beta=math.nan), dict(beta=math.inf), dict(max_factor=math.nan),
               dict(rho=math.nan)):  # fmt: skip
        with pytest.raises(ValueError):
            StrongTracking(**kw)
    with pytest.raises(TypeError, match="init.mean and init.chol must have one floating dtype, "
                       "got torch.float64 and torch.float32"):  # fmt: skip
        run(ekf(), linear_gaussian_model(one, one, one, one),
            GaussianBelief(torch.zeros(1, dtype=F64), torch.eye(1)), ys)  # fmt: skip
    with pytest.raises(ValueError, match="cov must be symmetric"):
        GaussianBelief.from_cov(torch.zeros(2, dtype=F64), [[1.0, 0.9], [0.0, 1.0]])
    # a product A A^T in float32 is symmetric to rounding: taken
    A = torch.randn(4, 4, generator=torch.Generator().manual_seed(0))
    GaussianBelief.from_cov(torch.zeros(4), A @ A.mT + torch.eye(4))


def test_sigma_point_rule_settings_are_checked():
    """NaN/inf alpha, beta, kappa gave NaN estimates silently; a Gauss-Hermite rule of order 1
    (the mean alone: zero spread) a filter that never updated; non-integral orders were cut."""
    for bad in (dict(alpha=float("nan")), dict(beta=float("inf")), dict(kappa=float("nan"))):
        with pytest.raises(ValueError, match=f"{next(iter(bad))} must be a finite real number"):
            unscented(**{"alpha": 1.0, "beta": 2.0, "kappa": 0.0, **bad})
    with pytest.raises(ValueError, match="alpha must be nonzero"):
        unscented(0.0)
    for order in (0, 1, 2.5):
        with pytest.raises(ValueError, match="order must be an int >= 2"):
            gauss_hermite(order)
    with pytest.raises(ValueError, match="unknown sigma-point rule kind"):
        __import__("prognos_torch.quadrature", fromlist=["x"]).SigmaPoints("sobol")
    assert gauss_hermite(np.int64(3)).order == 3  # numpy integers are ints


def test_a_fading_factor_without_redrawn_points_is_refused():
    # the propagated points carry neither lambda nor Q: a constant factor changed the prior
    # but not the gain, and strong tracking read H and M_k from the wrong covariance
    from prognos_torch.adapt.strong_tracking import StrongTracking

    for fading in (1.5, StrongTracking()):
        with pytest.raises(ValueError, match="a fading factor needs redraw=True"):
            GaussianFilter(unscented(1.0, 2.0, 2.0), redraw=False, fading=fading)
    GaussianFilter(Taylor(), redraw=False, fading=StrongTracking())  # (the EKF draws no points)
