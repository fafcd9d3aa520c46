"""RTS smoothers (EKS, unscented/cubature RTS, fixed-lag) against exact references and filterpy."""

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
    imsrukf,
    rukf,
    run,
    sckf,
    smooth,
    smooth_trajectory,
    srukf,
    stsckf,
    ukf,
)
from prognos_torch.filters.gaussian import GaussianFilter
from prognos_torch.quadrature import cubature, gauss_hermite, julier, unscented

sys.path.insert(0, str(Path(__file__).parent))
from _kalman_reference import joint_gaussian_reference, rts_reference  # noqa: E402

t = lambda a: torch.as_tensor(a, dtype=torch.float64)  # noqa: E731


def random_problem(seed, n=3, m=2, T=20, batch=2, missing=True):
    g = np.random.default_rng(seed)
    out = []
    for _ in range(batch):
        F = g.normal(size=(n, n))
        F *= 0.95 / max(abs(np.linalg.eigvals(F)))
        H = g.normal(size=(m, n))
        A = g.normal(size=(n, n))
        Q = 0.3 * A @ A.T + 0.05 * np.eye(n)
        B = g.normal(size=(m, m))
        R = 0.2 * B @ B.T + 0.1 * np.eye(m)
        m0 = g.normal(size=n)
        C0 = g.normal(size=(n, n))
        P0 = C0 @ C0.T + 0.5 * np.eye(n)
        ys = g.normal(size=(T, m)) * 2.0
        if missing:
            ys[3] = np.nan  # missing throughout
            ys[T - 1] = np.nan  # also at the end
            ys[T // 3, 0] = np.nan  # partially observed
            ys[T // 2 + 1, m - 1] = np.nan
        out.append((F, H, Q, R, m0, P0, ys))
    return out


def batched_model(problems):
    """One batched linear model (per-run F, H and noise) from a list of problems."""
    F = t(np.stack([p[0] for p in problems]))
    H = t(np.stack([p[1] for p in problems]))
    SQ = torch.linalg.cholesky(t(np.stack([p[2] for p in problems])))
    SR = torch.linalg.cholesky(t(np.stack([p[3] for p in problems])))
    n, m = F.shape[-1], H.shape[-2]

    def lead(x, M):  # per-run matrices against (B, n) or (B, L, n) points
        return M.reshape(M.shape[:1] + (1,) * (x.dim() - 2) + M.shape[1:])

    model = StateSpaceModel(
        f=lambda x, u, k: (lead(x, F) @ x.unsqueeze(-1)).squeeze(-1),
        h=lambda x, u, k: (lead(x, H) @ x.unsqueeze(-1)).squeeze(-1),
        state_dim=n,
        obs_dim=m,
        chol_Q=SQ,
        chol_R=SR,
        batched=True,
        jac_f=lambda x, u, k: lead(x, F).expand(*x.shape[:-1], n, n),
        jac_h=lambda x, u, k: lead(x, H).expand(*x.shape[:-1], m, n),
    )
    b0 = GaussianBelief.from_cov(
        t(np.stack([p[4] for p in problems])), t(np.stack([p[5] for p in problems]))
    )
    ys = t(np.stack([p[6] for p in problems], axis=1))  # (T, B, m)
    return model, b0, ys


VARIANTS = {
    "eks": ekf(),
    "eks-full": ekf(sqrt=False),
    "urts-full": ukf(),
    "urts-sqrt": ukf(sqrt=True),
    "urts-srukf": srukf(),
    "urts-negative-w0": GaussianFilter(unscented(0.5, 2.0, 0.0), sqrt=True),
    "urts-julier-negative": GaussianFilter(julier(-1.0), sqrt=True),
    "ckf-full": ckf(),
    "sckf": sckf(),
    "gauss-hermite": GaussianFilter(gauss_hermite(3), sqrt=True),
}


def check_against_reference(sm, problems, fading=1.0, tol=1e-8):
    for i, (F, H, Q, R, m0, P0, ys) in enumerate(problems):
        ref = rts_reference(F, H, Q, R, m0, P0, ys, fading=fading)
        np.testing.assert_allclose(sm.means[:, i].numpy(), ref["means"][1:], atol=tol, rtol=0)
        np.testing.assert_allclose(sm.covs[:, i].numpy(), ref["covs"][1:], atol=tol, rtol=0)
        np.testing.assert_allclose(sm.cross_covs[:, i].numpy(), ref["cross"], atol=tol, rtol=0)
        np.testing.assert_allclose(sm.initial.mean[i].numpy(), ref["means"][0], atol=tol, rtol=0)
        np.testing.assert_allclose(sm.initial.cov[i].numpy(), ref["covs"][0], atol=tol, rtol=0)
        assert abs(float(sm.log_likelihood[i]) - ref["ll"]) < tol * 10


@pytest.mark.parametrize("name", list(VARIANTS))
def test_rts_equals_dense_reference_batched_with_missing(name):
    problems = random_problem(1)
    model, b0, ys = batched_model(problems)
    sm = smooth(VARIANTS[name], model, b0, ys)
    assert sm.means.shape == (20, 2, 3) and sm.chols.shape == (20, 2, 3, 3)
    assert sm.cross_covs.shape == (20, 2, 3, 3)
    assert torch.equal(torch.tril(sm.chols), sm.chols)
    check_against_reference(sm, problems)


@pytest.mark.parametrize("sqrt", [True, False])
def test_constant_fading_is_smoothed_as_inflated_process_noise(sqrt):
    problems = random_problem(2)
    model, b0, ys = batched_model(problems)
    filt = GaussianFilter(cubature(), sqrt=sqrt, fading=1.3)
    check_against_reference(smooth(filt, model, b0, ys), problems, fading=1.3)


def test_unbatched_linear_gaussian_model_and_shared_reference():
    ((F, H, Q, R, m0, P0, ys),) = random_problem(3, n=2, m=1, T=15, batch=1)
    model = linear_gaussian_model(
        t(F), t(H), torch.linalg.cholesky(t(Q)), torch.linalg.cholesky(t(R))
    )
    b0 = GaussianBelief.from_cov(t(m0), t(P0))
    ref = rts_reference(F, H, Q, R, m0, P0, ys)
    for filt in (ekf(), sckf(), srukf()):
        sm = smooth(filt, model, b0, t(ys))
        assert sm.means.shape == (15, 2)
        np.testing.assert_allclose(sm.means.numpy(), ref["means"][1:], atol=1e-8, rtol=0)
        np.testing.assert_allclose(sm.covs.numpy(), ref["covs"][1:], atol=1e-8, rtol=0)
        np.testing.assert_allclose(sm.cross_covs.numpy(), ref["cross"], atol=1e-8, rtol=0)


@pytest.mark.parametrize("filt", [ekf(), sckf(), ckf()], ids=["eks", "sckf", "ckf-full"])
def test_fixed_lag_equals_rts_on_the_data_up_to_k_plus_lag(filt):
    problems = random_problem(4, T=16)
    model, b0, ys = batched_model(problems)
    T, L = ys.shape[0], 3
    fl = smooth(filt, model, b0, ys, lag=L)
    for k in range(T):  # row k is x_{k+1}, conditioned on y_{1:min(k+1+L, T)}
        e = min(k + 1 + L, T)
        rts = smooth(filt, model, b0, ys[:e])
        torch.testing.assert_close(fl.means[k], rts.means[k], atol=1e-10, rtol=0)
        torch.testing.assert_close(fl.covs[k], rts.covs[k], atol=1e-10, rtol=0)
        torch.testing.assert_close(fl.cross_covs[k], rts.cross_covs[k], atol=1e-10, rtol=0)
    rts = smooth(filt, model, b0, ys[:L])
    torch.testing.assert_close(fl.initial.mean, rts.initial.mean, atol=1e-10, rtol=0)
    full = smooth(filt, model, b0, ys)
    for lag in (T, T + 5):
        long = smooth(filt, model, b0, ys, lag=lag)
        torch.testing.assert_close(long.means, full.means, atol=1e-12, rtol=0)
        torch.testing.assert_close(long.chols, full.chols, atol=1e-12, rtol=0)
    zero = smooth(filt, model, b0, ys, lag=0)  # lag 0: the filter
    torch.testing.assert_close(zero.means, full.filtered.means, atol=1e-12, rtol=0)
    torch.testing.assert_close(zero.covs, full.filtered.covs, atol=1e-12, rtol=0)


def constant_velocity(dt=1.0):
    F = np.array([[1.0, dt], [0.0, 1.0]])
    H = np.array([[1.0, 0.0]])
    Q = np.array([[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]]) * 0.1
    return F, H, Q, np.array([[2.0]])


def test_matches_filterpy_rts_smoother():
    kalman = pytest.importorskip("filterpy.kalman")
    F, H, Q, R = constant_velocity()
    g = np.random.default_rng(5)
    zs = np.cumsum(g.normal(size=50)) + g.normal(size=50) * 1.4
    kf = kalman.KalmanFilter(dim_x=2, dim_z=1)
    kf.F, kf.H, kf.Q, kf.R = F, H, Q, R
    kf.x, kf.P = np.array([0.0, 1.0]), np.diag([10.0, 3.0])
    mu, cov, _, _ = kf.batch_filter(zs.reshape(-1, 1))
    xs, Ps, Ks, _ = kf.rts_smoother(mu, cov)
    model = linear_gaussian_model(
        t(F), t(H), torch.linalg.cholesky(t(Q)), torch.linalg.cholesky(t(R))
    )
    b0 = GaussianBelief.from_cov(t([0.0, 1.0]), t(np.diag([10.0, 3.0])))
    for filt in (ekf(), ekf(sqrt=False), sckf()):
        sm = smooth(filt, model, b0, t(zs)[:, None])
        np.testing.assert_allclose(sm.means.numpy(), xs.reshape(-1, 2), atol=1e-8, rtol=0)
        np.testing.assert_allclose(sm.covs.numpy(), Ps, atol=1e-8, rtol=0)
        # filterpy's K[k] is G_k (x_k on x_{k+1}); ours row k+1
        np.testing.assert_allclose(sm.gains[1:].numpy(), Ks[:-1], atol=1e-8, rtol=0)


def test_matches_filterpy_urts_on_a_nonlinear_model():
    kalman = pytest.importorskip("filterpy.kalman")
    a, b, c = 0.5, 25.0, 20.0  # growth model without its time-varying term (filterpy's fx(x, dt))

    def fx(x, dt):
        return a * x + b * x / (1 + x**2)

    g = np.random.default_rng(6)
    x, zs = 0.1, []
    for _ in range(60):
        x = fx(x, 1.0) + math.sqrt(2.0) * g.normal()
        zs.append(x**2 / c + g.normal())
    alpha, beta, kappa = 1.0, 2.0, 2.0
    pts = kalman.MerweScaledSigmaPoints(1, alpha=alpha, beta=beta, kappa=kappa)
    fp = kalman.UnscentedKalmanFilter(
        dim_x=1, dim_z=1, dt=1.0, points=pts, fx=fx, hx=lambda x: x**2 / c
    )
    fp.x, fp.P, fp.Q, fp.R = np.array([0.1]), np.array([[2.0]]), np.array([[2.0]]), np.eye(1)
    mu, cov = fp.batch_filter(np.array(zs).reshape(-1, 1))
    xs, Ps, Ks = fp.rts_smoother(mu, cov)
    model = StateSpaceModel(
        f=lambda x, u, k: a * x + b * x / (1 + x**2),
        h=lambda x, u, k: x**2 / c,
        state_dim=1,
        obs_dim=1,
        chol_Q=t([[math.sqrt(2.0)]]),
        chol_R=t([[1.0]]),
    )
    b0 = GaussianBelief.from_cov(t([0.1]), t([[2.0]]))
    for sqrt in (False, True):
        filt = GaussianFilter(unscented(alpha, beta, kappa), sqrt=sqrt)
        sm = smooth(filt, model, b0, t(zs)[:, None])
        np.testing.assert_allclose(sm.filtered.means.numpy(), mu, atol=1e-8, rtol=0)
        np.testing.assert_allclose(sm.means.numpy(), xs, atol=1e-8, rtol=0)
        np.testing.assert_allclose(sm.covs.numpy(), Ps, atol=1e-8, rtol=0)


def pendulum(dt=0.05):
    def f(x, u, k):
        return torch.stack([x[0] + dt * x[1], x[1] - dt * 9.81 * torch.sin(x[0])])

    return StateSpaceModel(
        f=f,
        h=lambda x, u, k: torch.sin(x[:1]),
        state_dim=2,
        obs_dim=1,
        chol_Q=t([[1e-3, 0.0], [5e-3, 2e-2]]),
        chol_R=t([[0.1]]),
    )


def pendulum_data():
    model = pendulum()
    g = torch.Generator().manual_seed(7)
    x, ys = torch.tensor([1.2, 0.0], dtype=torch.float64), []
    for k in range(80):
        x = model.f(x, None, k) + torch.randn(2, generator=g, dtype=torch.float64) * 0.02
        ys.append(torch.sin(x[:1]) + 0.1 * torch.randn(1, generator=g, dtype=torch.float64))
    ys = torch.stack(ys)
    ys[20:25] = float("nan")
    b0 = GaussianBelief.from_cov(t([1.0, 0.1]), t(np.diag([0.1, 0.1])))
    return model, b0, ys


def test_strong_tracking_backward_pass_square_root_equals_full():
    # strong tracking amplifies rounding in the forward pass, so both backward algebras run
    # on the same forward trajectory
    model, b0, ys = pendulum_data()
    tr = run(stsckf(), model, b0, ys, keep_steps=True)
    assert float(tr.fading_factors.max()) > 2.0  # the fading factor is active
    a = smooth_trajectory(tr, b0, sqrt=True)
    b = smooth_trajectory(tr, b0, sqrt=False)
    torch.testing.assert_close(a.means, b.means, atol=1e-9, rtol=0)
    torch.testing.assert_close(a.covs, b.covs, atol=1e-9, rtol=0)
    torch.testing.assert_close(a.cross_covs, b.cross_covs, atol=1e-9, rtol=0)


@pytest.mark.parametrize(
    "make",
    [
        lambda sqrt: GaussianFilter(cubature(), sqrt=sqrt),
        lambda sqrt: GaussianFilter(unscented(0.5, 2.0, 0.0), sqrt=sqrt),
        lambda sqrt: ekf(sqrt=sqrt),
        lambda sqrt: GaussianFilter(cubature(), sqrt=sqrt, fading=1.2),
    ],
    ids=["cubature", "unscented-negative-w0", "eks", "constant-fading"],
)
def test_square_root_and_full_forms_agree_on_a_nonlinear_model(make):
    model, b0, ys = pendulum_data()
    a = smooth(make(True), model, b0, ys)
    b = smooth(make(False), model, b0, ys)
    torch.testing.assert_close(a.means, b.means, atol=1e-9, rtol=0)
    torch.testing.assert_close(a.covs, b.covs, atol=1e-9, rtol=0)
    torch.testing.assert_close(a.cross_covs, b.cross_covs, atol=1e-9, rtol=0)
    # smoothing shrinks the uncertainty of the filter
    assert bool(
        (
            a.covs.diagonal(dim1=-2, dim2=-1) <= a.filtered.covs.diagonal(dim1=-2, dim2=-1) + 1e-12
        ).all()
    )
    fl = smooth(make(True), model, b0, ys, lag=5)
    fb = smooth(make(False), model, b0, ys, lag=5)
    torch.testing.assert_close(fl.means, fb.means, atol=1e-9, rtol=0)
    torch.testing.assert_close(fl.covs, fb.covs, atol=1e-9, rtol=0)


def test_gradients_flow_through_the_smoother():
    problems = random_problem(8, T=8, batch=1, missing=True)
    F, H, Q, R, m0, P0, ys = problems[0]
    raw = t(np.log(np.sqrt(np.diag(Q)))).requires_grad_(True)

    def smoothed_sum(raw):
        model = linear_gaussian_model(
            t(F), t(H), torch.diag(raw.exp()), torch.linalg.cholesky(t(R))
        )
        sm = smooth(sckf(), model, GaussianBelief.from_cov(t(m0), t(P0)), t(ys))
        return sm.means.sum() + sm.chols.sum() + sm.cross_covs.sum()

    assert torch.autograd.gradcheck(smoothed_sum, (raw,), eps=1e-6, atol=1e-6)


def test_bad_arguments():
    problems = random_problem(9, T=5, batch=1)
    model, b0, ys = batched_model(problems)
    with pytest.raises(ValueError, match="lag"):
        smooth(ekf(), model, b0, ys, lag=-1)
    with pytest.raises(ValueError, match="lag"):
        smooth(ekf(), model, b0, ys, lag=1.5)
    with pytest.raises(TypeError, match="GaussianFilter"):
        smooth(ekf, model, b0, ys)
    with pytest.raises(ValueError, match="robust"):
        smooth(rukf(2.0, torch.eye(2, dtype=torch.float64)), model, b0, ys)
    with pytest.raises(ValueError, match="ys must have shape"):
        smooth(ekf(), model, b0, ys[:, :, :1])


def test_run_keeps_steps_only_when_asked():
    problems = random_problem(10, T=4, batch=1)
    model, b0, ys = batched_model(problems)
    assert run(ekf(), model, b0, ys).steps is None
    tr = run(ekf(), model, b0, ys, keep_steps=True)
    assert len(tr.steps) == 4 and tr.steps[0].spread is not None


def test_noise_estimator_steps_smooth_with_the_q_they_used():
    # ImSRUKF estimates Q and R on the way; the backward pass uses each step's Q_k, so the
    # square-root and full algebras agree on the same forward run
    model, b0, ys = pendulum_data()
    tr = run(imsrukf(), model, b0, ys, keep_steps=True)
    Q1 = tr.steps[1].noise.chol_Q
    assert not torch.allclose(Q1, tr.steps[-1].noise.chol_Q)  # Q really varies
    a = smooth_trajectory(tr, b0, sqrt=True)
    b = smooth_trajectory(tr, b0, sqrt=False)
    torch.testing.assert_close(a.means, b.means, atol=1e-9, rtol=0)
    torch.testing.assert_close(a.covs, b.covs, atol=1e-9, rtol=0)
    with pytest.raises(ValueError, match="keep_steps"):
        smooth_trajectory(run(imsrukf(), model, b0, ys), b0)


@pytest.mark.parametrize("make", [ekf, sckf])
def test_a_singular_predicted_covariance_is_refused_by_step(make):
    # no process noise and a transition that drops a direction: P_{k|k-1} is singular, the
    # filter runs, and the gain C P^-1 does not exist (it came out NaN without a word)
    d = torch.float64
    A = torch.tensor([[1.0, 1.0], [0.0, 0.0]], dtype=d)
    model = linear_gaussian_model(A, torch.tensor([[1.0, 0.0]], dtype=d),
                                  torch.zeros(2, 2, dtype=d), 0.5 * torch.eye(1, dtype=d))  # fmt: skip
    init = GaussianBelief(torch.zeros(2, dtype=d), torch.eye(2, dtype=d))
    ys = torch.randn(5, 1, dtype=d, generator=torch.Generator().manual_seed(0))
    assert bool(torch.isfinite(run(make(), model, init, ys).means).all())
    with pytest.raises(ValueError, match=r"P_\{k\|k-1\} of step 1 is singular"):
        smooth(make(), model, init, ys)


def test_smooth_trajectory_checks_what_smooth_checks():
    d = torch.float64
    model = linear_gaussian_model(torch.tensor([[0.9, 0.2], [-0.1, 0.85]], dtype=d),
                                  torch.eye(2, dtype=d), 0.3 * torch.eye(2, dtype=d),
                                  0.4 * torch.eye(2, dtype=d))  # fmt: skip
    init = GaussianBelief(torch.zeros(3, 2, dtype=d), torch.eye(2, dtype=d).expand(3, 2, 2))
    ys = torch.randn(6, 3, 2, dtype=d, generator=torch.Generator().manual_seed(0))
    tr = run(sckf(), model, init, ys, keep_steps=True)
    ref = smooth(sckf(), model, init, ys)
    # the FilterState the run started from serves as init, as in smooth()
    state = sckf().init(model, init, 1)
    torch.testing.assert_close(smooth_trajectory(tr, state).means, ref.means, rtol=0, atol=0)
    with pytest.raises(ValueError, match=r"init must have mean \(3, 2\) and chol \(3, 2, 2\)"):
        smooth_trajectory(tr, GaussianBelief(init.mean[0], init.chol[0]))
    with pytest.raises(ValueError, match="init must have the run's dtype torch.float64"):
        smooth_trajectory(tr, GaussianBelief(init.mean.float(), init.chol.float()))
    with pytest.raises(TypeError, match="sqrt must be a bool"):
        smooth_trajectory(tr, init, sqrt="yes")
    # a robust filter's run: refused here as smooth() refuses the filter
    rob = rukf(2.0, torch.eye(2, dtype=d))
    with pytest.raises(ValueError, match="robust filter's run"):
        smooth_trajectory(run(rob, model, init, ys, keep_steps=True), init)


def test_rts_and_fixed_lag_equal_joint_gaussian_conditioning_with_controls_and_step_noise():
    # x_{0:T}, y_{1:T} as one Gaussian, conditioned exactly: controls, per-step (callable)
    # Q_k, R_k and noise means, k0 > 0, m > n, rows missing (first, last) and partly observed
    g = np.random.default_rng(11)
    n, m, T, k0 = 2, 3, 5, 4
    F, H, B = 0.6 * g.normal(size=(n, n)), g.normal(size=(m, n)), g.normal(size=(n, 1))
    SQs = np.tril(g.normal(size=(T, n, n))) * 0.4 + 0.3 * np.eye(n)
    SRs = np.tril(g.normal(size=(T, m, m))) * 0.3 + 0.4 * np.eye(m)
    qs, rs, us = g.normal(size=(T, n)), g.normal(size=(T, m)), g.normal(size=(T, 1))
    m0, P0 = g.normal(size=n), np.array([[1.0, 0.3], [0.3, 0.8]])
    ys = g.normal(size=(T, m))
    ys[0], ys[T - 1], ys[2, 1], ys[3, [0, 2]] = np.nan, np.nan, np.nan, np.nan
    at = lambda a: lambda k: t(a[k - k0 - 1])  # noqa: E731
    model = StateSpaceModel(f=lambda x, u, k: t(F) @ x + t(B) @ u, h=lambda x, u, k: t(H) @ x,
                            state_dim=n, obs_dim=m, chol_Q=at(SQs), chol_R=at(SRs), q=at(qs),
                            r=at(rs), control_dim=1)  # fmt: skip
    b0 = GaussianBelief.from_cov(t(m0), t(P0))
    args = (F, H, SQs @ SQs.swapaxes(1, 2), SRs @ SRs.swapaxes(1, 2), m0, P0, ys)
    kw = dict(Bu=us @ B.T, qs=qs, rs=rs)
    ms, Ps, cr, ll = joint_gaussian_reference(*args, **kw)
    close = lambda a, b: np.testing.assert_allclose(a.numpy(), b, atol=1e-10, rtol=0)  # noqa: E731
    for filt in (ekf(), sckf()):
        sm = smooth(filt, model, b0, t(ys), t(us), k0=k0)
        close(sm.means, ms[1:]), close(sm.covs, Ps[1:]), close(sm.cross_covs, cr)
        close(sm.initial.mean, ms[0]), close(sm.initial.cov, Ps[0])
        assert abs(float(sm.log_likelihood) - ll) < 1e-10
    fl = smooth(sckf(), model, b0, t(ys), t(us), k0=k0, lag=1)
    for k in range(T + 1):  # x_k given y_{1:min(k+1, T)}
        ms2, Ps2, cr2, _ = joint_gaussian_reference(*args, upto=min(k + 1, T), **kw)
        mean, cov = (fl.means[k - 1], fl.covs[k - 1]) if k else (fl.initial.mean, fl.initial.cov)
        close(mean, ms2[k]), close(cov, Ps2[k])
        if k:
            close(fl.cross_covs[k - 1], cr2[k - 1])


def test_a_nan_in_the_model_is_named_as_such_not_as_a_singular_covariance():
    # a NaN in F made the forward run NaN, and the smoother blamed a singular P_{k|k-1} and
    # asked for more process noise
    d = torch.float64
    F = torch.tensor([[0.9, float("nan")], [0.0, 0.8]], dtype=d)
    model = linear_gaussian_model(F, torch.tensor([[1.0, 0.5]], dtype=d),
                                  0.3 * torch.eye(2, dtype=d), 0.5 * torch.eye(1, dtype=d))  # fmt: skip
    init = GaussianBelief(torch.zeros(2, dtype=d), torch.eye(2, dtype=d))
    ys = torch.randn(4, 1, dtype=d, generator=torch.Generator().manual_seed(0))
    for filt in (ekf(), sckf()):
        with pytest.raises(ValueError, match=r"run is non-finite \(NaN or inf\) from step 1 on"):
            smooth(filt, model, init, ys)
