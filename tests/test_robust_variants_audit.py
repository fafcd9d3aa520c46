"""Audit of the Gaussian filter factories (filters/variants.py), strong tracking (paper 000 Eq. 7-10)
and the robust bound (paper 004 Theorem 1) against references written out here in NumPy.

Linear-Gaussian models, where every moment rule is exact: with the adaptation switched off (the
fading factor held at 1 by a large weakening factor, a frozen noise estimator, a robust bound
without uncertainty) every variant is the plain Kalman filter; the fading factor of one and two
steps is ``max(1, tr N_k / tr M_k)`` of Eq. 7-10; one robust step is Eq. 28-29 (printed scalar
form) or the Lemma-1 bound ``P~ = (P^-1 - gamma^-2 N^T N)^-1`` (``form="lemma"``).
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from prognos_torch.adapt import RobustBound, SageHusa, StrongTracking
from prognos_torch.core import GaussianBelief, linear_gaussian_model
from prognos_torch.filters import (
    arukf,
    ckf,
    ekf,
    imsrukf,
    make_filter,
    make_particle_filter,
    rukf,
    run,
    sckf,
    srukf,
    stekf,
    stsckf,
    stukf,
    ukf,
)

dt = torch.float64
N_STATE, M_OBS, T = 4, 2, 6


# ----------------------------------------------------------------------------- problem
def _problem(B=(3,), seed=0, scale=2.0):
    rng = np.random.default_rng(seed)
    n, m = N_STATE, M_OBS
    F = 0.8 * np.eye(n) + 0.1 * rng.standard_normal((n, n)) / np.sqrt(n)
    H = rng.standard_normal((m, n))
    LQ = np.diag(0.2 + 0.3 * rng.random(n))
    LR = np.diag(0.5 + 0.5 * rng.random(m))
    ys = scale * rng.standard_normal((T, *B, m))
    m0 = 0.3 * rng.standard_normal((*B, n))
    P0 = 0.5 * np.eye(n) + 0.1 * np.ones((n, n))
    return F, H, LQ, LR, ys, m0, P0


def _model(F, H, LQ, LR, dtype=dt):
    t = lambda a: torch.as_tensor(a, dtype=dtype)  # noqa: E731
    return linear_gaussian_model(t(F), t(H), t(LQ), t(LR))


def _belief(m0, P0, dtype=dt):
    B = m0.shape[:-1]
    L = torch.as_tensor(np.linalg.cholesky(P0), dtype=dtype)
    return GaussianBelief(torch.as_tensor(m0, dtype=dtype), L.expand(*B, *L.shape).clone())


def _kf(F, H, LQ, LR, m0, P0, ys, partial_is_missing=False):
    """Plain Kalman filter per batch element; NaN components are left out of the update (a
    vector that is NaN throughout only predicts; ``partial_is_missing``: so does any NaN)."""
    Q, R = LQ @ LQ.T, LR @ LR.T
    B = m0.shape[:-1]
    xs = np.zeros((len(ys), *m0.shape))
    Ps = np.zeros((len(ys), *m0.shape, m0.shape[-1]))
    for idx in np.ndindex(*B):
        x, P = m0[idx], P0
        for t, y in enumerate(ys[(slice(None), *idx)]):
            x, P = F @ x, F @ P @ F.T + Q
            o = ~np.isnan(y)
            if o.any() and not (partial_is_missing and not o.all()):
                Ho, Ro = H[o], R[np.ix_(o, o)]
                S = Ho @ P @ Ho.T + Ro
                K = np.linalg.solve(S, Ho @ P).T
                x = x + K @ (y[o] - Ho @ x)
                P = P - K @ S @ K.T
            xs[(t, *idx)], Ps[(t, *idx)] = x, P
    return xs, Ps


def _nan(ys):
    ys = ys.copy()
    flat = ys.reshape(T, -1, M_OBS)
    flat[2, 0] = np.nan  # a missing vector: predict only
    flat[4, -1, 0] = np.nan  # partially observed (the robust bound: missing)
    return ys


Z2 = torch.zeros(M_OBS, dtype=dt)
M2 = torch.tensor([0.2, -0.1], dtype=dt)
BIG = 1e8  # weakening factor: tr N_k < 0, so lambda_k = 1 (Eq. 7)

# (name, factory, the robust bound's reading of a partially observed vector)
PLAIN = [
    ("ekf", lambda: ekf(), False),
    ("ekf-full", lambda: ekf(sqrt=False), False),
    ("ukf", lambda: ukf(), False),
    ("ukf-sqrt", lambda: ukf(0.7, 2.0, 1.0, sqrt=True), False),
    ("srukf", lambda: srukf(), False),
    ("srukf-3-n", lambda: srukf(None), False),  # kappa = -1: negative W_0, Cholesky downdates
    ("ckf", lambda: ckf(), False),
    ("sckf", lambda: sckf(), False),
    ("stekf", lambda: stekf(0.9, BIG), False),
    ("stukf", lambda: stukf(0.9, BIG), False),
    ("stukf-full-3-n", lambda: stukf(0.9, BIG, None, sqrt=False), False),
    ("stsckf", lambda: stsckf(0.9, BIG), False),
    ("imsrukf-frozen", lambda: imsrukf(noise=SageHusa(frozen=True)), False),
    ("rukf-scalar", lambda: rukf(1.05, Z2, 0.0), True),
    ("rukf-scalar-full", lambda: rukf(1.05, Z2, 0.0, sqrt=False), True),
    ("rukf-lemma", lambda: rukf(2.0, Z2, 0.0, form="lemma"), True),
    ("rukf-optimised", lambda: rukf(1.05, M2, 0.0, bound="optimised"), True),
    ("arukf-warmup", lambda: arukf(1.05, Z2, 0.0, window=T + 1), True),
]


@pytest.mark.parametrize("B", [(), (2, 2)], ids=["unbatched", "batch2x2"])
@pytest.mark.parametrize("name,factory,partial", PLAIN, ids=[p[0] for p in PLAIN])
def test_every_variant_without_adaptation_is_the_kalman_filter(name, factory, partial, B):
    F, H, LQ, LR, ys, m0, P0 = _problem(B, seed=3)
    ys = _nan(ys)
    tr = run(factory(), _model(F, H, LQ, LR), _belief(m0, P0), torch.as_tensor(ys))
    x, P = _kf(F, H, LQ, LR, m0, P0, ys, partial_is_missing=partial)
    assert tr.means.shape == (T, *B, N_STATE) and tr.chols.shape == (T, *B, N_STATE, N_STATE)
    np.testing.assert_allclose(tr.means.numpy(), x, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(tr.covs.numpy(), P, rtol=1e-12, atol=1e-12)
    assert torch.equal(tr.fading_factors, torch.ones(T, *B, dtype=dt))


# ----------------------------------------------------------------------------- strong tracking
def _st_two_steps(F, H, LQ, LR, m0, P0, ys, rho, beta):
    """Paper 000 Eq. 7-10 by hand: V_1 = e e^T, V_2 = (rho V_1 + e e^T) / (1 + rho),
    N = V - H Q H^T - beta R, M = H F P F^T H^T, lambda = max(1, tr N / tr M)."""
    Q, R = LQ @ LQ.T, LR @ LR.T
    x, P, V, out = m0, P0, None, []
    for y in ys:
        xp, FPF = F @ x, F @ P @ F.T
        e = y - H @ xp
        V = np.outer(e, e) if V is None else (rho * V + np.outer(e, e)) / (1.0 + rho)
        lam = max(1.0, np.trace(V - H @ Q @ H.T - beta * R) / np.trace(H @ FPF @ H.T))
        Pp = lam * FPF + Q
        S = H @ Pp @ H.T + R
        K = np.linalg.solve(S, H @ Pp).T
        x, P = xp + K @ e, Pp - K @ S @ K.T
        out.append((lam, x, P))
    return out


ST = {
    "stekf": stekf,
    "stsckf": stsckf,
    "stukf": stukf,
    "stukf-full": lambda rho, beta: stukf(rho, beta, sqrt=False),
}


@pytest.mark.parametrize("n", [1, 2])
@pytest.mark.parametrize("name", list(ST))
def test_fading_factor_is_the_closed_form_of_eq_7_to_10(name, n):
    rng = np.random.default_rng(5 + n)
    F = np.array([[0.9]]) if n == 1 else np.array([[0.9, 0.2], [-0.1, 0.8]])
    H = np.eye(n) if n == 1 else np.array([[1.0, 0.3], [0.2, 1.0]])
    LQ, LR = 0.1 * np.eye(n), 0.3 * np.eye(n)
    m0, P0 = np.zeros(n), 0.2 * np.eye(n)
    ys = 4.0 + rng.standard_normal((2, n))  # far from the prediction: lambda > 1
    rho, beta = 0.9, 1.5
    tr = run(ST[name](rho, beta), _model(F, H, LQ, LR), _belief(m0, P0), torch.as_tensor(ys))
    ref = _st_two_steps(F, H, LQ, LR, m0, P0, ys, rho, beta)
    for t, (lam, x, P) in enumerate(ref):
        assert lam > 1.5
        np.testing.assert_allclose(float(tr.fading_factors[t]), lam, rtol=1e-12)
        np.testing.assert_allclose(tr.means[t].numpy(), x, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(tr.covs[t].numpy(), P, rtol=1e-12, atol=1e-12)


def test_strong_tracking_takes_numpy_float32_settings_as_their_float_values():
    """StrongTracking(rho=np.float32(0.9)) kept the NumPy scalar: Eq. 10's 1 + rho was then
    float32 arithmetic, and lambda_2 was 1e-7 relative off the written-out value with
    rho = float(np.float32(0.9)) (4e-6 absolute here)."""
    n = 2
    F, H = np.array([[0.9, 0.2], [-0.1, 0.8]]), np.array([[1.0, 0.3], [0.2, 1.0]])
    LQ, LR = 0.1 * np.eye(n), 0.3 * np.eye(n)
    m0, P0 = np.zeros(n), 0.2 * np.eye(n)
    ys = np.array([[4.0, 3.0], [5.5, -2.0]])
    rho, beta = np.float32(0.9), np.float32(1.3)
    cfg = StrongTracking(rho, beta, np.float32(1e6))
    assert all(type(v) is float for v in (cfg.rho, cfg.beta, cfg.max_factor))
    tr = run(stekf(rho, beta), _model(F, H, LQ, LR), _belief(m0, P0), torch.as_tensor(ys))
    ref = _st_two_steps(F, H, LQ, LR, m0, P0, ys, float(rho), float(beta))
    for t, (lam, x, _) in enumerate(ref):
        assert lam > 1.5
        np.testing.assert_allclose(float(tr.fading_factors[t]), lam, rtol=1e-12)
        np.testing.assert_allclose(tr.means[t].numpy(), x, rtol=1e-12, atol=1e-12)


# ----------------------------------------------------------------------------- robust bound
def _robust_step(F, H, LQ, LR, m0, P0, y, gamma, M, N, form):
    """One step of paper 004 Theorem 1 written out (the linear model: C = H exactly)."""
    Q, R = LQ @ LQ.T, LR @ LR.T
    xp, P = F @ m0, F @ P0 @ F.T + Q
    MM = np.outer(M, M)
    if form == "lemma":
        NN = (N * N) * np.eye(len(xp)) if np.ndim(N) == 0 else N.T @ N
        P = np.linalg.inv(np.linalg.inv(P) - NN / gamma**2)  # Lemma 1, U = P_{k|k-1}
        lam, cM, cR = 1.0, gamma**2, 1.0
    else:
        nu = float(N) ** 2
        lam = 1.0 / (1.0 - nu / gamma**2)  # Eq. 34
        cM, cR = gamma**2 - nu, 1.0 - nu / gamma**2  # Eq. 29: N_M = (gamma^2 - nu) M M^T
    S = H @ P @ H.T + cM * MM + cR * R  # Eq. 29
    K = np.linalg.solve(S, H @ P).T
    IKH = np.eye(len(xp)) - K @ H
    Pk = lam * IKH @ P @ IKH.T + gamma**2 * K @ MM @ K.T + K @ R @ K.T  # Eq. 28
    return xp + K @ (y - H @ xp), Pk


ROBUST = [
    ("scalar", 1.05, 1.0, True),
    ("scalar", 1.05, 1.0, False),
    ("scalar", 2.0, -0.7, True),
    ("lemma", 3.0, 0.8, True),
    ("lemma", 3.0, 0.8, False),
    ("lemma", 3.0, np.array([[0.5, 0.1, -0.2, 0.3], [0.0, 0.4, 0.1, 0.0]]), True),
]


@pytest.mark.parametrize("form,gamma,N,sqrt", ROBUST)
def test_one_robust_step_is_theorem_1_by_hand(form, gamma, N, sqrt):
    F, H, LQ, LR, ys, m0, P0 = _problem((), seed=8)
    M = np.array([0.3, -0.2])
    Nt = torch.as_tensor(N, dtype=dt) if np.ndim(N) else N
    filt = rukf(gamma, torch.as_tensor(M, dtype=dt), Nt, form=form, sqrt=sqrt)
    tr = run(filt, _model(F, H, LQ, LR), _belief(m0, P0), torch.as_tensor(ys[:1]))
    x, P = _robust_step(F, H, LQ, LR, m0, P0, ys[0], gamma, M, N, form)
    np.testing.assert_allclose(tr.means[0].numpy(), x, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(tr.covs[0].numpy(), P, rtol=1e-12, atol=1e-12)


def test_optimised_bound_of_one_step_is_the_minimum_trace_of_eq_28():
    """bound="optimised": one step's trace P_k is the minimum over t in (0, 1) of the trace of
    Eq. 28-29 with t = N^2 / gamma^2 (written out here; a dense grid, then a fine one)."""
    F, H, LQ, LR, ys, m0, P0 = _problem((), seed=9)
    M, N = np.array([0.3, -0.2]), 1.0
    tr = run(
        rukf(1.05, torch.as_tensor(M, dtype=dt), N, bound="optimised"),
        _model(F, H, LQ, LR),
        _belief(m0, P0),
        torch.as_tensor(ys[:1]),
    )

    def trace(t):
        return np.trace(_robust_step(F, H, LQ, LR, m0, P0, ys[0], np.sqrt(N / t), M, N, "s")[1])

    u = np.linspace(-30, 14, 441)
    best = u[np.argmin([trace(1 / (1 + np.exp(-v))) for v in u])]
    u = np.linspace(best - 0.1, best + 0.1, 401)
    ref = min(trace(1 / (1 + np.exp(-v))) for v in u)
    got = float(torch.diagonal(tr.covs[0]).sum())
    assert abs(got - ref) <= 1e-9 * ref  # (the grid's minimum is within 1e-11 of the true one)


def test_robust_settings_given_as_numpy_float32_are_their_float_values():
    """RobustBound kept a NumPy float32 gamma: gamma**2 and 1 - N^2 / gamma^2 were float32
    arithmetic, so the coefficients of Eq. 28-29 (and arukf's mu = gamma^2 of Eq. 48) were 1e-7
    relative off those of float(gamma): the covariance after one step 3e-7 relative off."""
    F, H, LQ, LR, ys, m0, P0 = _problem((), seed=8)
    M = np.array([0.3, -0.2])
    g32, N32 = np.float32(1.05), np.float32(1.0)
    rb = RobustBound(g32, torch.as_tensor(M), N32)
    assert type(rb.gamma) is float and type(rb.N) is float
    model, b0, y = _model(F, H, LQ, LR), _belief(m0, P0), torch.as_tensor(ys[:1])
    tr = run(rukf(g32, torch.as_tensor(M, dtype=dt), N32), model, b0, y)
    x, P = _robust_step(F, H, LQ, LR, m0, P0, ys[0], float(g32), M, float(N32), "scalar")
    np.testing.assert_allclose(tr.means[0].numpy(), x, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(tr.covs[0].numpy(), P, rtol=1e-12, atol=1e-12)
    # arukf: the same run as with the float value (its window estimates included)
    ys6 = torch.as_tensor(ys)
    Mt = torch.as_tensor(M, dtype=dt)
    a = run(arukf(g32, Mt, N32, window=2), model, b0, ys6)
    b = run(arukf(float(g32), Mt, 1.0, window=2), model, b0, ys6)
    np.testing.assert_allclose(a.means.numpy(), b.means.numpy(), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(a.chol_R.numpy(), b.chol_R.numpy(), rtol=1e-12, atol=1e-12)


def test_lemma_bound_with_an_N_of_the_wrong_width_is_named():
    """An (l, n') N with n' != n failed at the first step with torch's matmul shape error."""
    F, H, LQ, LR, ys, m0, P0 = _problem((), seed=8)
    filt = rukf(3.0, M2, torch.ones(1, 3, dtype=dt), form="lemma")
    with pytest.raises(ValueError, match=r"RobustBound.N must have shape \(l, n\) with n=4"):
        run(filt, _model(F, H, LQ, LR), _belief(m0, P0), torch.as_tensor(ys))


# ----------------------------------------------------------------------------- float32
F32 = [p for p in PLAIN if p[0] not in ("srukf-3-n", "stukf-full-3-n")] + [
    ("stsckf-fading", lambda: stsckf(0.9, 1.0), False),
    ("rukf-printed", lambda: rukf(1.05, M2, 1.0), True),
    ("rukf-lemma-N", lambda: rukf(3.0, M2, 0.8, form="lemma"), True),
    ("arukf", lambda: arukf(1.05, M2, 1.0, window=2), True),
]


@pytest.mark.parametrize("name,factory,partial", F32, ids=[p[0] for p in F32])
def test_float32_runs_stay_float32_and_agree_with_float64(name, factory, partial):
    F, H, LQ, LR, ys, m0, P0 = _problem((2,), seed=4)
    ys = _nan(ys)
    out = {}
    for d in (torch.float32, dt):
        tr = run(
            factory(), _model(F, H, LQ, LR, d), _belief(m0, P0, d), torch.as_tensor(ys, dtype=d)
        )
        for v in (tr.means, tr.chols, tr.fading_factors, tr.log_likelihoods):
            assert v.dtype == d
        out[d] = tr
    a, b = out[torch.float32], out[dt]
    scale = float(b.covs.abs().max())
    np.testing.assert_allclose(a.means.double(), b.means, rtol=1e-3, atol=1e-4 * scale**0.5)
    np.testing.assert_allclose(a.covs.double(), b.covs, rtol=1e-3, atol=1e-4 * scale)


# ----------------------------------------------------------------------------- options by name
BAD = [
    (lambda: ekf(sqrt="no"), TypeError, "sqrt must be a bool, got 'no'"),
    (lambda: ukf(sqrt=None), TypeError, "sqrt must be a bool"),
    (lambda: stukf(sqrt=1), TypeError, "sqrt must be a bool"),
    (lambda: rukf(1.05, M2, sqrt="yes"), TypeError, "sqrt must be a bool"),
    (lambda: ukf("a"), ValueError, "alpha must be a finite real number"),
    (lambda: ukf(None), ValueError, "alpha must be a finite real number"),
    (lambda: ukf(True), ValueError, "alpha must be a finite real number"),
    (lambda: ukf(1.0, "2"), ValueError, "beta must be a finite real number"),
    (lambda: rukf(1.05, M2, alpha="a"), ValueError, "alpha must be a finite real number"),
    (lambda: imsrukf(noise="sage-husa"), TypeError, "noise must be a SageHusa estimator"),
    (lambda: rukf("1.05", M2), TypeError, "gamma must be a real number, got str"),
    (lambda: rukf(None, M2), TypeError, "gamma must be a real number"),
    (lambda: rukf(True, M2, 0.5), TypeError, "gamma must be a real number, got bool"),
    (lambda: rukf(-1.05, M2), ValueError, "gamma must be positive"),
    (lambda: rukf(1.05, M2, True), TypeError, "N must be a real number"),
    (lambda: rukf(1.05, M2, "1"), TypeError, "N must be a real number"),
    (lambda: rukf(2.0, M2, torch.tensor(0.5), form="lemma"), ValueError, r"\(l, n\) tensor"),
    (lambda: rukf(2.0, M2, torch.ones(3), form="lemma"), ValueError, r"got a tensor of shape"),
    (lambda: rukf(1.05, None), TypeError, "M must be a tensor or array-like"),
    (lambda: rukf(1.05, "M"), TypeError, "M must be a tensor or array-like"),
    (lambda: rukf(1.05, torch.tensor(0.3)), ValueError, r"M must have shape \(m,\) or \(m, j\)"),
    (lambda: rukf(1.05, torch.zeros(2, 1, 1)), ValueError, r"M must have shape \(m,\)"),
    (lambda: arukf("1.05", M2), TypeError, "gamma must be a real number"),
    (lambda: arukf(2.0, M2, torch.eye(2)), ValueError, "scalar N"),
    (lambda: arukf(2.0, M2, diagonal="yes"), TypeError, "diagonal must be a bool"),
    (lambda: arukf(float("inf"), M2, bound="optimised"), ValueError, "gamma must be a positive"),
    (lambda: arukf(-1.0, M2, bound="optimised"), ValueError, "gamma must be a positive"),
    (lambda: make_filter(3), TypeError, "name must be a filter name"),
    (lambda: make_particle_filter(None), TypeError, "name must be a particle filter name"),
    (lambda: RobustBound(2.0, M2, bound="optimised", search=5), ValueError, "search must be"),
    (lambda: RobustBound(2.0, M2, bound="optimised", search=(3.5,)), ValueError, "search"),
    (lambda: RobustBound(2.0, M2, bound="optimised", span=(-np.inf, 3.0)), ValueError, "span"),
    (lambda: RobustBound(2.0, M2, bound="optimised", span=(1.0, 2.0, 3.0)), ValueError, "span"),
]


@pytest.mark.parametrize("build,exc,match", BAD, ids=[f"bad{i}" for i in range(len(BAD))])
def test_bad_factory_options_are_refused_by_name(build, exc, match):
    with pytest.raises(exc, match=match):
        build()


def test_unchanged_refusals_of_the_factories():
    """Options that were named before and still are (no change here; kept as a map)."""
    for build, exc, match in [
        (lambda: stekf(2.0), ValueError, "rho must be in"),
        (lambda: stsckf(beta=0), ValueError, "beta"),
        (lambda: srukf(True), ValueError, "kappa"),
        (lambda: srukf(2.0, rule=ckf().rule), ValueError, "give kappa or rule"),
        (lambda: rukf(1.05, M2, form="both"), ValueError, "form must be"),
        (lambda: rukf(1.05, M2, bound="best"), ValueError, "bound must be"),
        (lambda: rukf(1.0, M2, 1.0), ValueError, r"gamma\^2 > N\^2"),
        (lambda: arukf(1.05, M2, window=0), ValueError, "window"),
        (lambda: make_filter("nope"), ValueError, "unknown filter"),
    ]:
        with pytest.raises(exc, match=match):
            build()


def test_numpy_scalar_options_are_accepted():
    F, H, LQ, LR, ys, m0, P0 = _problem((2,), seed=6)
    model, b0, y = _model(F, H, LQ, LR), _belief(m0, P0), torch.as_tensor(ys)
    x, P = _kf(F, H, LQ, LR, m0, P0, ys)
    for filt in (
        ukf(np.float32(0.5), np.int64(2), np.float64(1.0), sqrt=np.bool_(True)),
        ekf(sqrt=np.bool_(False)),
        stekf(np.float64(0.95), np.int64(10**8)),
        srukf(np.int64(2)),
        rukf(np.float64(1.05), Z2, np.int64(0), alpha=np.float64(0.8), kappa=np.int64(1)),
        arukf(np.float64(1.05), Z2, np.float64(0.0), window=np.int64(T + 1), diagonal=np.bool_(1)),
    ):
        tr = run(filt, model, b0, y)
        np.testing.assert_allclose(tr.means.numpy(), x, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(tr.covs.numpy(), P, rtol=1e-12, atol=1e-12)
    rb = RobustBound(1.05, M2, 1.0, bound="optimised", search=[np.int64(9), 5], span=(-20, 10))
    assert rb.search == (9, 5) and rb.span == (-20.0, 10.0)
    hash(rb)  # (a list search left the configuration unhashable)


def test_the_engine_checks_its_on_off_options_and_estimator_types():
    # GaussianFilter read sqrt/redraw by their truth value (sqrt="no": the square-root algebra)
    # and took any object as noise or robust (an AttributeError at the first step)
    from prognos_torch.filters.gaussian import GaussianFilter, Taylor

    f = GaussianFilter(Taylor(), sqrt=np.bool_(False), redraw=np.bool_(True))
    assert f.sqrt is False and f.redraw is True
    with pytest.raises(TypeError, match="sqrt must be a bool, got 'no'"):
        GaussianFilter(Taylor(), sqrt="no")
    with pytest.raises(TypeError, match="redraw must be a bool, got 1"):
        GaussianFilter(Taylor(), redraw=1)
    with pytest.raises(TypeError, match="noise must be None, SageHusa or MovingWindow, got str"):
        GaussianFilter(Taylor(), noise="sage")
    with pytest.raises(TypeError, match="robust must be None or a RobustBound, got float"):
        GaussianFilter(Taylor(), robust=1.05)


def test_sigma_point_rules_check_text_and_bools_and_keep_python_floats():
    # unscented() called float(alpha) first: text failed with float()'s message and True was
    # read as 1.0; a NumPy kappa was kept as float32 (a rule unequal to the float one)
    from prognos_torch.quadrature import julier, unscented

    for bad in ("a", None, True):
        with pytest.raises(ValueError, match="alpha must be a finite real number"):
            unscented(bad)
    r = julier(np.float32(1.0))
    assert type(r.kappa) is float and r == julier(1.0)
    assert unscented(np.float32(0.5), np.int64(2)) == unscented(0.5, 2.0)
