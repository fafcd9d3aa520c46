"""Strong tracking, Sage-Husa, moving-window and robust pieces of the filter engine."""

import math

import pytest
import torch

from prognos_torch.adapt import MovingWindow, SageHusa
from prognos_torch.core import GaussianBelief, linear_gaussian_model
from prognos_torch.filters import arukf, imsrukf, rukf, run, sckf, srukf, stsckf
from prognos_torch.filters.gaussian import GaussianFilter
from prognos_torch.quadrature import unscented
from prognos_torch.systems.three_tank import simulate_three_tank, three_tank_joint_model

dt = torch.float64


def test_strong_tracking_three_tank_az2_drift():
    """Paper 000 Sec. 6: joint state/parameter filter with the assistant model az2_k = az2_{k-1}."""
    R = 20
    sim = simulate_three_tank(200, R, generator=torch.Generator().manual_seed(0))
    truth = sim.theta[1:, :, 0]
    model = three_tank_joint_model(chol_D=1e-4)
    m0 = torch.tensor([1.0, 0.95, 0.9, 0.6], dtype=dt).expand(R, 4).clone()
    S0 = torch.diag(torch.tensor([1e-3, 1e-3, 1e-3, 1e-2], dtype=dt)).expand(R, 4, 4).clone()
    b0 = GaussianBelief(m0, S0)
    plain = run(sckf(), model, b0, sim.y)
    strong = run(stsckf(), model, b0, sim.y)
    rmse = lambda tr: (tr.means[..., 3] - truth).pow(2).mean(0).sqrt()  # noqa: E731 (per run)
    r_plain, r_strong = rmse(plain), rmse(strong)
    assert bool((r_strong < r_plain).all())  # every one of the 20 seeds
    assert float(r_strong.mean()) < 0.2 * float(r_plain.mean())
    lam = strong.fading_factors
    assert torch.equal(plain.fading_factors, torch.ones_like(lam))
    assert float(lam[3:10].median()) < 1.05  # before the drift has grown: near 1
    assert float(lam[100:].mean()) > 1.5  # while az2 ramps: above 1


def _lin_data(T=3000, B=8, seed=0):
    F = torch.tensor([[0.9, 0.2], [0.0, 0.8]], dtype=dt)
    H = torch.eye(2, dtype=dt)
    SQ = torch.diag(torch.tensor([0.3, 0.2], dtype=dt))
    SR = torch.diag(torch.tensor([1.0, 0.5], dtype=dt))
    g = torch.Generator().manual_seed(seed)
    x, xs, ys = torch.zeros(B, 2, dtype=dt), [], []
    for _ in range(T):
        x = x @ F.T + torch.randn(B, 2, generator=g, dtype=dt) @ SQ.T
        xs.append(x)
        ys.append(x @ H.T + torch.randn(B, 2, generator=g, dtype=dt) @ SR.T)
    b0 = GaussianBelief(torch.zeros(B, 2, dtype=dt), torch.eye(2, dtype=dt).expand(B, 2, 2).clone())
    return F, H, SQ, SR, torch.stack(xs), torch.stack(ys), b0


@pytest.mark.parametrize("factor", [100.0, 0.01])
def test_sage_husa_recovers_R_misspecified_100x(factor):
    # 24 runs of 1000 steps: as many innovations as 8 of 3000, a third of the sequential steps
    # (R_hat within 2 % of the truth either way; the 1/k average has forgotten the start)
    F, H, SQ, SR, xs, ys, b0 = _lin_data(T=1000, B=24)
    half = xs.shape[0] // 2
    rmse = lambda tr: float((tr.means[half:] - xs[half:]).pow(2).mean().sqrt())  # noqa: E731
    good = linear_gaussian_model(F, H, SQ, SR)
    bad = linear_gaussian_model(F, H, SQ, SR * math.sqrt(factor))
    tr = run(imsrukf(noise=SageHusa(estimate=("R",))), bad, b0, ys)
    R_hat = (tr.chol_R[-1] @ tr.chol_R[-1].mT).mean(0)
    assert torch.allclose(R_hat.diagonal(), (SR @ SR.T).diagonal(), rtol=0.1)
    r_opt, r_bad, r_ad = rmse(run(srukf(), good, b0, ys)), rmse(run(srukf(), bad, b0, ys)), rmse(tr)
    assert r_ad < r_bad and r_ad < 1.02 * r_opt


@pytest.mark.parametrize("factor", [100.0, 0.01])
def test_sage_husa_moves_Q_towards_truth(factor):
    F, H, SQ, SR, xs, ys, b0 = _lin_data()
    half = xs.shape[0] // 2
    rmse = lambda tr: float((tr.means[half:] - xs[half:]).pow(2).mean().sqrt())  # noqa: E731
    bad = linear_gaussian_model(F, H, SQ * math.sqrt(factor), SR)
    tr = run(imsrukf(noise=SageHusa(estimate=("Q",), forgetting=0.99)), bad, b0, ys)
    Q_hat = (tr.chol_Q[-1] @ tr.chol_Q[-1].mT).mean(0).diagonal()
    ratio = Q_hat / (SQ @ SQ.T).diagonal()
    assert bool((ratio > 1 / 3).all() and (ratio < 3).all())  # from 100x off to within 3x
    assert rmse(tr) < rmse(run(srukf(), bad, b0, ys))


def test_frozen_sage_husa_is_exactly_srukf():
    F, H, SQ, SR, xs, ys, b0 = _lin_data(T=50, B=2)
    model = linear_gaussian_model(F, H, SQ, SR)
    a = run(srukf(), model, b0, ys)
    b = run(imsrukf(noise=SageHusa(frozen=True)), model, b0, ys)
    assert torch.equal(a.means, b.means)


def test_moving_window_estimates_R_on_linear_model():
    F, H, SQ, SR, xs, ys, b0 = _lin_data(T=1500, B=8)
    bad = linear_gaussian_model(F, H, SQ, 10 * SR)
    est = MovingWindow(window=200, estimate=("R",), diagonal=True)
    tr = run(GaussianFilter(unscented(1.0, 0.0, 1.0), noise=est), bad, b0, ys)
    R_hat = (tr.chol_R[-1] @ tr.chol_R[-1].mT).mean(0).diagonal()
    assert torch.allclose(R_hat, (SR @ SR.T).diagonal(), rtol=0.2)


@pytest.mark.parametrize("form", ["lemma", "scalar"])
def test_robust_ukf_reduces_to_ukf_and_inflates_covariance(form):
    F, H, SQ, SR, xs, ys, b0 = _lin_data(T=60, B=2)
    model = linear_gaussian_model(F, H, SQ, SR)
    M0 = torch.zeros(2, dtype=dt)
    ref = run(GaussianFilter(unscented(1.0, 0.0, 1.0)), model, b0, ys)
    big = run(rukf(1e6, M0, N=1.0, form=form), model, b0, ys)  # M = 0, gamma -> inf: the UKF
    assert torch.allclose(big.means, ref.means, atol=1e-8)
    assert torch.allclose(big.covs, ref.covs, atol=1e-8)
    # with uncertainty, the robust bound P_k (Eq. 28) dominates the nominal covariance
    Mu = torch.full((2,), 0.1, dtype=dt)
    rob = run(rukf(1.05, Mu, N=1.0, form=form), model, b0, ys)
    gap = torch.linalg.eigvalsh(rob.covs[-1] - ref.covs[-1])
    assert bool((gap > -1e-12).all())
    full = run(rukf(1.05, Mu, N=1.0, form=form, sqrt=False), model, b0, ys)
    assert torch.allclose(full.means, rob.means, atol=1e-9)
    assert torch.allclose(full.covs, rob.covs, atol=1e-9)
    ad = run(
        arukf(1.05, torch.full((2,), 0.01, dtype=dt), 0.5, window=20, form=form), model, b0, ys
    )
    assert bool(torch.isfinite(ad.means).all()) and ad.chol_R is not None


def test_robust_bound_lemma_inflation_and_gamma_checks():
    from prognos_torch.adapt import RobustBound

    g = torch.Generator().manual_seed(0)
    A = torch.randn(3, 3, generator=g, dtype=dt)
    P = 0.1 * (A @ A.T) + 0.05 * torch.eye(3, dtype=dt)
    N = torch.randn(2, 3, generator=g, dtype=dt)
    rb = RobustBound(2.0, torch.zeros(2, dtype=dt), N, form="lemma")
    S = rb.inflate(torch.linalg.cholesky(P))
    expected = torch.linalg.inv(torch.linalg.inv(P) - N.T @ N / 4.0)  # test-only explicit form
    assert torch.allclose(S @ S.T, expected, atol=1e-12)
    assert torch.equal(S, torch.tril(S)) and bool((torch.diagonal(S) > 0).all())
    with pytest.raises(ValueError, match="too small"):
        RobustBound(0.1, torch.zeros(2, dtype=dt), 10.0, form="lemma").inflate(
            torch.linalg.cholesky(P)
        )
    with pytest.raises(ValueError, match="gamma"):
        rukf(0.5, torch.zeros(2, dtype=dt), N=1.0, form="scalar")
    with pytest.raises(ValueError, match="form"):
        RobustBound(1.05, torch.zeros(2, dtype=dt), 1.0, form="other")


# ------------------------------------------------------------------------- bad input
def _model():
    return linear_gaussian_model(
        torch.eye(2, dtype=dt),
        torch.eye(2, dtype=dt)[:1],
        torch.eye(2, dtype=dt),
        torch.eye(1, dtype=dt),
    )


def test_bad_input_errors_name_the_argument():
    model = _model()
    b0 = GaussianBelief(torch.zeros(3, 2, dtype=dt), torch.eye(2, dtype=dt).expand(3, 2, 2).clone())
    f = sckf()
    st = f.init(model, b0)
    with pytest.raises(ValueError, match=r"y must have shape \(3, 1\)"):
        f.step(model, st, torch.zeros(2, 1, dtype=dt))
    with pytest.raises(ValueError, match="ys must have shape"):
        run(f, model, b0, torch.zeros(5, 4, 1, dtype=dt))
    with pytest.raises(ValueError, match="disagree on n"):
        f.init(model, GaussianBelief(torch.zeros(2, dtype=dt), torch.eye(3, dtype=dt)))
    with pytest.raises(ValueError, match="belief.chol must have shape"):
        f.init(model, GaussianBelief(torch.zeros(3, 2, dtype=dt), torch.eye(2, dtype=dt)))
    with pytest.raises(ValueError, match="belief.mean contains non-finite"):
        f.init(
            model,
            GaussianBelief(torch.tensor([float("nan"), 0.0], dtype=dt), torch.eye(2, dtype=dt)),
        )
    with pytest.raises(ValueError, match="belief.chol must have a positive diagonal"):
        f.init(
            model,
            GaussianBelief(
                torch.zeros(2, dtype=dt), torch.diag(torch.tensor([1.0, -1.0], dtype=dt))
            ),
        )
    with pytest.raises(ValueError, match="cov must be symmetric positive definite"):
        GaussianBelief.from_cov(
            torch.zeros(2, dtype=dt), torch.tensor([[1.0, 2.0], [2.0, 1.0]], dtype=dt)
        )
    bad_Q = linear_gaussian_model(
        torch.eye(2, dtype=dt),
        torch.eye(2, dtype=dt)[:1],
        torch.eye(3, dtype=dt),
        torch.eye(1, dtype=dt),
    )
    with pytest.raises(ValueError, match=r"model.chol_Q must have shape"):
        f.step(bad_Q, f.init(bad_Q, b0), torch.zeros(3, 1, dtype=dt))
    with pytest.raises(ValueError, match="mismatched|batch shape"):
        wrong_batch = linear_gaussian_model(
            torch.eye(2, dtype=dt),
            torch.eye(2, dtype=dt)[:1],
            torch.eye(2, dtype=dt).expand(4, 2, 2),
            torch.eye(1, dtype=dt),
        )
        f.step(wrong_batch, f.init(wrong_batch, b0), torch.zeros(3, 1, dtype=dt))
    with pytest.raises(ValueError, match="inf"):
        f.step(model, st, torch.full((3, 1), float("inf"), dtype=dt))
    with pytest.raises(ValueError, match="u was given"):
        f.step(model, st, torch.zeros(3, 1, dtype=dt), u=torch.zeros(3, 1, dtype=dt))
    with pytest.raises(TypeError, match="y must be a torch.Tensor"):
        f.step(model, st, [[0.0]] * 3)


def test_nan_measurement_means_predict_only():
    model = _model()
    b0 = GaussianBelief(torch.zeros(2, 2, dtype=dt), torch.eye(2, dtype=dt).expand(2, 2, 2).clone())
    f = stsckf()
    st = f.init(model, b0)
    y = torch.tensor([[1.0], [float("nan")]], dtype=dt)
    new, info = f.step(model, st, y)
    pred = f.predict(model, st)
    assert torch.equal(new.belief.mean[1], pred.belief.mean[1])
    assert torch.allclose(new.belief.chol[1], pred.belief.chol[1])
    assert not torch.allclose(new.belief.chol[0], pred.belief.chol[0])
    assert bool(info.missing[1]) and not bool(info.missing[0])
    assert float(info.log_likelihood[1]) == 0.0 and bool(torch.isnan(info.nis[1]))
    assert float(info.fading_factor[1]) == 1.0


@pytest.mark.parametrize("estimator", ["sage_husa", "moving_window"])
def test_diagonal_estimates_equal_the_diagonal_of_full_estimates(estimator):
    """The vector path of diagonal=True gives the diagonal of the full-matrix update, step after
    step, including a step with a missing run (data chosen so that no estimate needs the
    positive-definite projection: then the two must agree to rounding)."""
    from prognos_torch.adapt.noise import UpdateContext
    from prognos_torch.core.model import Noise

    g = torch.Generator().manual_seed(3)
    n, m, B, L = 4, 1, 5, 9
    r = lambda *s: torch.randn(*s, generator=g, dtype=torch.float64)  # noqa: E731
    eye = lambda k: torch.eye(k, dtype=torch.float64)  # noqa: E731
    M = 0.1 * r(m)
    make = {
        "sage_husa": lambda d: SageHusa(("Q", "R"), diagonal=d),
        "moving_window": lambda d: MovingWindow(window=3, diagonal=d, M=M, N=0.5, mu=2.0),
    }[estimator]
    full, diag = make(False), make(True)
    like = torch.zeros(B, n, dtype=torch.float64)
    sf, sd = (e.init(Noise(None, eye(n), None, eye(m)), (B,), n, m, like) for e in (full, diag))
    for step in range(6):
        missing = torch.zeros(B, dtype=torch.bool)
        missing[1] = step == 3
        A = r(B, n, n)
        ctx = UpdateContext(
            x_post=r(B, n), f_mean=r(B, n), spread_pos=0.3 * r(B, n, L), spread_neg=None,
            gain=0.1 * r(B, n, m), innovation=3.0 + 0.1 * r(B, m),
            chol_post=torch.linalg.cholesky(3 * eye(n) + 0.1 * A @ A.mT), y=r(B, m),
            h_mean=r(B, m), dz_pos=0.2 * r(B, m, L), dz_neg=None, missing=missing,
        )  # fmt: skip
        sf, sd = full.update(sf, ctx), diag.update(sd, ctx)
        assert not bool(sf.fallback.any()) and not bool(sd.fallback.any())
        for F_, D_ in ((sf.Q, sd.Q), (sf.R, sd.R)):
            assert torch.equal(D_, torch.diag_embed(torch.diagonal(D_, dim1=-2, dim2=-1)))
            torch.testing.assert_close(
                torch.diagonal(D_, dim1=-2, dim2=-1),
                torch.diagonal(F_, dim1=-2, dim2=-1),
                rtol=1e-12,
                atol=1e-14,
            )
    assert bool((sd.Q != eye(n)).any())  # the estimates did move


def _bound_problem(B=5, n=4, m=3, seed=1):
    g = torch.Generator().manual_seed(seed)
    A = torch.randn(B, n, n, generator=g, dtype=dt)
    P = A @ A.mT + 0.1 * torch.eye(n, dtype=dt)
    H = torch.randn(B, m, n, generator=g, dtype=dt)
    C = torch.randn(B, m, m, generator=g, dtype=dt)
    RR = 0.5 * C @ C.mT + 0.2 * torch.eye(m, dtype=dt)
    M = torch.full((m,), 0.3, dtype=dt)
    return P, H, RR, M


def test_optimised_bound_is_the_grid_minimum_and_beats_the_printed_scale():
    """Paper 004 Eq. 28 as a family in t = N^2 / gamma^2: the search finds the minimum of
    trace P_k(t) (a brute-force grid of 40,001 points agrees), below the printed t = 1/1.05^2,
    and bound_trace is the trace of Eq. 28 with the gain of Eq. 35 (explicit test-only form)."""
    from prognos_torch.adapt import RobustBound

    P, H, RR, M = _bound_problem()
    Pxz, Pzz, trP = P @ H.mT, H @ P @ H.mT, torch.diagonal(P, dim1=-2, dim2=-1).sum(-1)
    rb = RobustBound(1.05, M, 1.0, bound="optimised")
    t = rb.choose_t(trP, Pxz, Pzz, RR)
    f = rb.bound_trace(t[:, None], trP, Pxz, Pzz, RR)[:, 0]
    fine = torch.sigmoid(torch.linspace(-30.0, 14.0, 44001, dtype=dt)).expand(P.shape[0], -1)
    f_fine = rb.bound_trace(fine, trP, Pxz, Pzz, RR).min(-1).values
    assert torch.allclose(f, f_fine, rtol=1e-7)
    assert bool((f <= f_fine * (1 + 1e-12)).all())
    t0 = torch.full_like(t, 1.0 / 1.05**2)
    f0 = rb.bound_trace(t0[:, None], trP, Pxz, Pzz, RR)[:, 0]
    assert bool((f < 0.5 * f0).all())  # the printed scale is far from the best on these
    for tt in (t, t0):  # Eq. 28 with the gain of Eq. 35, explicitly
        T = tt[:, None, None]
        MM = M[:, None] @ M[None, :]
        S = Pzz + (1 - T) / T * MM + (1 - T) * RR
        K = torch.linalg.solve(S, Pxz.mT).mT  # S symmetric
        IKH = torch.eye(4, dtype=dt) - K @ H
        Pk = IKH @ P @ IKH.mT / (1 - T) + K @ MM @ K.mT / T + K @ RR @ K.mT
        ref = torch.diagonal(Pk, dim1=-2, dim2=-1).sum(-1)
        got = rb.bound_trace(tt[:, None], trP, Pxz, Pzz, RR)[:, 0]
        # the explicit form solves with S, whose condition number reaches 3e12 where the optimum
        # t is near 0 (last problem): its own error is then up to about cond(S) eps, and moves
        # with the BLAS kernel (2.5e-9 measured on one CPU); 1e-10 where S is well conditioned
        rtol = 1e-10 + 1e-14 * torch.linalg.cond(S)
        assert bool(((got - ref).abs() <= rtol * ref.abs()).all())
    with pytest.raises(ValueError, match="bound"):
        RobustBound(1.05, M, 1.0, bound="best")
    with pytest.raises(ValueError, match="form='scalar'"):
        RobustBound(1.05, M, 1.0, form="lemma", bound="optimised")


def test_optimised_rukf_steps_take_the_tightest_bound():
    """Each step of rukf(bound='optimised') ends at the minimum over t of trace P_k(t) for its
    own prior (linear model: the unscented moments are exact), never above the printed scale's
    bound from the same prior; square-root and full algebra agree (to the search's precision)."""
    from prognos_torch.adapt import RobustBound

    F, H, SQ, SR, xs, ys, b0 = _lin_data(T=12, B=3)
    model = linear_gaussian_model(F, H, SQ, SR)
    Mu = torch.full((2,), 0.3, dtype=dt)
    opt, printed = rukf(1.05, Mu, 1.0, bound="optimised"), rukf(1.05, Mu, 1.0)
    rb = RobustBound(1.05, Mu, 1.0, bound="optimised")
    RR = (SR @ SR.T).expand(3, 2, 2)
    fine = torch.sigmoid(torch.linspace(-30.0, 14.0, 44001, dtype=dt)).expand(3, -1)
    state = opt.init(model, b0)
    for k in range(ys.shape[0]):
        new, info = opt.step(model, state, ys[k], k=k + 1)
        _, info_p = printed.step(model, state, ys[k], k=k + 1)  # same start
        S = info.prior.chol
        P = S @ S.mT
        Pxz, Pzz, trP = P @ H.T, H @ P @ H.T, torch.diagonal(P, dim1=-2, dim2=-1).sum(-1)
        got = new.belief.chol.square().sum((-2, -1))
        best = rb.bound_trace(fine, trP, Pxz, Pzz, RR).min(-1).values
        assert torch.allclose(got, best, rtol=1e-7)
        printed_post = printed.step(model, state, ys[k], k=k + 1)[0].belief.chol
        assert bool((got <= printed_post.square().sum((-2, -1))).all())
        state = new
    a = run(opt, model, b0, ys)
    b = run(rukf(1.05, Mu, 1.0, bound="optimised", sqrt=False), model, b0, ys)
    # the trace is stationary at the optimum, so rounding moves t (and the gain, hence the
    # mean) by about the square root of what it moves P_k: covariances agree to 1e-6, means 2e-3
    assert torch.allclose(a.covs, b.covs, atol=1e-6)
    assert torch.allclose(a.means, b.means, atol=2e-3)


@pytest.mark.parametrize("N", [0.0, 1.0])
def test_optimised_bound_without_uncertainty_is_the_ukf(N):
    """M = 0 (or N = 0): no uncertainty, and the optimised bound is the plain UKF (with N = 1 the
    search runs to t -> 0, where lambda -> 1), while the printed bound is not."""
    F, H, SQ, SR, xs, ys, b0 = _lin_data(T=60, B=2)
    model = linear_gaussian_model(F, H, SQ, SR)
    ref = run(GaussianFilter(unscented(1.0, 0.0, 1.0)), model, b0, ys)
    M0 = torch.zeros(2, dtype=dt) if N else torch.full((2,), 0.3, dtype=dt)
    opt = run(rukf(1.05, M0, N, bound="optimised"), model, b0, ys)
    assert torch.allclose(opt.means, ref.means, atol=1e-9, rtol=0)
    assert torch.allclose(opt.covs, ref.covs, atol=1e-9, rtol=0)
    if N:
        printed = run(rukf(1.05, M0, N), model, b0, ys)
        assert float((printed.covs - ref.covs).abs().max()) > 0.1


def test_moving_window_warmup_is_checked_and_holds_until_valid_steps():
    """warmup must lie in [1, window]: 0 averaged an empty window after a missing first step (R
    fell to the floor, 1e-3 of the model's), above the window the estimates were never used.
    With warmup=1 a missing first step keeps the model's R and the first observed step gives
    the one-term window of Eq. 48 (exact Kalman quantities: linear model)."""
    F, H, SQ, SR = _lin_data(T=1, B=1)[:4]
    ys = torch.tensor([[float("nan")] * 2, [10.0, -8.0]], dtype=dt)
    with pytest.raises(ValueError, match=r"warmup must be an int in \[1, window=5\]"):
        MovingWindow(window=5, warmup=0)
    with pytest.raises(ValueError, match="warmup"):
        MovingWindow(window=5, warmup=6)
    model = linear_gaussian_model(F, H, SQ, SR)
    est = MovingWindow(window=5, warmup=1, estimate=("R",), diagonal=True)
    m0, P0 = torch.zeros(2, dtype=dt), torch.eye(2, dtype=dt)
    tr = run(GaussianFilter(unscented(1.0, 0.0, 1.0), noise=est), model, GaussianBelief(m0, P0), ys)
    R0, Q = SR @ SR.T, SQ @ SQ.T
    torch.testing.assert_close(tr.chol_R[0] @ tr.chol_R[0].mT, R0)
    xp, Pp = F @ (F @ m0), F @ (F @ P0 @ F.T + Q) @ F.T + Q  # two predictions
    e = ys[1] - H @ xp
    term = e * e - torch.diagonal(H @ Pp @ H.T)  # Eq. 48's diagonal, one valid step
    assert bool((term > 0).all())  # no projection
    R1 = tr.chol_R[1] @ tr.chol_R[1].mT
    torch.testing.assert_close(R1, torch.diag(term), rtol=1e-12, atol=1e-12)


def test_adaptation_settings_are_checked_with_the_argument_named():
    from prognos_torch.adapt import StrongTracking

    per_run = torch.tensor([0.9, 0.95], dtype=dt)
    with pytest.raises(TypeError, match="rho must be a real number"):
        StrongTracking(rho=per_run)  # was: "Boolean value of Tensor ... is ambiguous"
    with pytest.raises(ValueError, match="forgetting must be a finite real number"):
        SageHusa(forgetting=per_run)
    with pytest.raises(ValueError, match="floor_rel"):  # NaN floor: NaN diagonal estimates
        SageHusa(floor_rel=float("nan"))
    with pytest.raises(ValueError, match="floor_rel must be >= 0"):
        MovingWindow(floor_rel=-1.0)
    with pytest.raises(ValueError, match="mu must be positive"):  # was ZeroDivisionError
        MovingWindow(M=torch.ones(1, dtype=dt), mu=0.0)
    with pytest.raises(ValueError, match="window"):
        MovingWindow(window=True)
    with pytest.raises(ValueError, match="give kappa or rule"):  # kappa was ignored
        srukf(2.0, rule=unscented(0.5, 2.0, 0.0))


@pytest.mark.parametrize("form", ["scalar", "lemma"])
def test_robust_filter_on_a_missing_step_gives_the_prediction(form):
    """The lemma form's prior is the inflated bound P~ (paper 004 Theorem 1); on a missing step
    the posterior was that bound (0.13 off the prediction here), where it is the prediction
    F P F^T + Q, as the scalar form gave."""
    t = lambda v: torch.tensor(v, dtype=torch.float64)  # noqa: E731
    F, LQ = t([[0.95, 0.1], [-0.1, 0.9]]), t([[0.4, 0.0], [0.1, 0.3]])
    model = linear_gaussian_model(F, t([[1.0, 0.5]]), LQ, t([[0.6]]))
    b0 = GaussianBelief.from_cov(t([0.5, -0.3]), torch.diag(t([1.0, 0.5])))
    tr = run(rukf(1.05, t([0.3]), 0.5, form=form), model, b0, t([[0.3], [0.5], [math.nan]]))
    P1 = tr.covs[1]
    torch.testing.assert_close(tr.covs[2], F @ P1 @ F.T + LQ @ LQ.T, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(tr.means[2], F @ tr.means[1], rtol=1e-12, atol=1e-12)
