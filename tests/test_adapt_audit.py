"""Audit of the adaptation blocks against plain NumPy Kalman-filter references.

Linear-Gaussian models, where the sigma-point sums are exact (``sum W (gamma - x)(gamma - x)^T
= F P F^T``, ``sum W (eta - z)(eta - z)^T = H P_{k|k-1} H^T``), so every adaptation block can be
written out step by step in dense NumPy algebra (no library code): strong tracking (paper 000
Eq. 7-10 with the documented ``1 + rho`` denominator), Sage-Husa (paper 003 Eq. 40-43 with the
fading-memory weight and the documented positive-definite projection), the moving-window
estimator (paper 004 Eq. 47-48, window mean over the valid steps, warm-up) and the robust bound
(paper 004 Eq. 28-29, both readings).
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from prognos_torch.adapt import MovingWindow, RobustBound, SageHusa, StrongTracking
from prognos_torch.core import GaussianBelief, linear_gaussian_model
from prognos_torch.filters import arukf, ekf, rukf, run, sckf, srukf
from prognos_torch.filters.gaussian import GaussianFilter
from prognos_torch.quadrature import unscented

dt = torch.float64


# ----------------------------------------------------------------------------- problems
def _problem(n, m, T, B, seed, ys_scale=2.0, nan=()):
    rng = np.random.default_rng(seed)
    F = 0.85 * np.eye(n) + 0.1 * rng.standard_normal((n, n)) / np.sqrt(n)
    H = rng.standard_normal((m, n))
    LQ = np.diag(0.2 + 0.3 * rng.random(n))
    LR = np.diag(0.5 + 0.5 * rng.random(m))
    ys = ys_scale * rng.standard_normal((T, B, m))
    for idx in nan:
        ys[idx] = np.nan
    m0 = 0.3 * rng.standard_normal((B, n))
    return F, H, LQ, LR, ys, m0


def _torch(*a):
    return [torch.as_tensor(x, dtype=dt) for x in a]


def _model(F, H, LQ, LR, q=None, r=None):
    F_, H_, LQ_, LR_ = _torch(F, H, LQ, LR)
    q_ = None if q is None else torch.as_tensor(q, dtype=dt)
    r_ = None if r is None else torch.as_tensor(r, dtype=dt)
    return linear_gaussian_model(F_, H_, LQ_, LR_, q=q_, r=r_)


def _belief(m0, P0):
    B, n = m0.shape
    return GaussianBelief(
        torch.as_tensor(m0, dtype=dt),
        torch.as_tensor(np.linalg.cholesky(P0), dtype=dt).expand(B, n, n).clone(),
    )


def _update(xp, Pp, H, R, r, y):
    """Kalman update with the observed components of ``y``; returns (x, P, K, e, full)."""
    o = ~np.isnan(y)
    if not o.any():
        return xp, Pp, None, None, False
    Ho, Ro = H[o], R[np.ix_(o, o)]
    S = Ho @ Pp @ Ho.T + Ro
    K = np.linalg.solve(S, Ho @ Pp).T
    e = y[o] - Ho @ xp - r[o]
    x = xp + K @ e
    I_KH = np.eye(len(xp)) - K @ Ho
    P = I_KH @ Pp @ I_KH.T + K @ Ro @ K.T
    return x, P, K, e, bool(o.all())


def _project(C, floor, diagonal):
    """The documented projection: symmetrise; if not PD, raise the eigenvalues to
    max(floor, 1e-10 max|eig|); diagonal: each variance to the floor."""
    C = 0.5 * (C + C.T)
    if diagonal:
        d = np.diag(C)
        return np.diag(np.maximum(d, floor)), bool((d < floor).any())
    w, V = np.linalg.eigh(C)
    if w.min() > 0:
        return C, False
    w = np.maximum(w, max(floor, 1e-10 * np.abs(w).max()))
    return (V * w) @ V.T, True


# ----------------------------------------------------------------------------- strong tracking
def _st_reference(F, H, LQ, LR, m0, P0, ys, rho, beta, max_factor=None):
    Q, R = LQ @ LQ.T, LR @ LR.T
    r = np.zeros(H.shape[0])
    x, P, V = m0.copy(), P0.copy(), None
    out = []
    for y in ys:
        xp, FPF = F @ x, F @ P @ F.T
        lam = 1.0
        if not np.isnan(y).any():
            e = y - H @ xp
            eeT = np.outer(e, e)
            V = eeT if V is None else (rho * V + eeT) / (1.0 + rho)  # Eq. 10 (documented)
            N = V - H @ Q @ H.T - beta * R  # Eq. 8
            M = H @ FPF @ H.T  # Eq. 9
            lam0 = np.trace(N) / np.trace(M)  # Eq. 7
            lam = lam0 if lam0 > 1 else 1.0
            if max_factor is not None:
                lam = min(lam, max_factor)
        Pp = lam * FPF + Q
        x, P, *_ = _update(xp, Pp, H, R, r, y)
        out.append((x, P, lam))
    return [np.array(v) for v in zip(*out)]


@pytest.mark.parametrize(
    "filt,n,m,rho,beta,maxf",
    [
        ("ekf", 3, 2, 0.95, 1.0, None),
        ("srukf", 3, 2, 0.9, 2.0, None),
        ("sckf", 2, 4, 0.5, 0.5, 3.0),  # m > n
        ("ekf", 1, 1, 1.0, 1.0, None),  # n = m = 1, rho at its upper limit
        ("sckf", 4, 1, 0.95, 1.0, 2.0),  # m = 1
    ],
)
def test_strong_tracking_matches_the_papers_formulas_step_by_step(filt, n, m, rho, beta, maxf):
    T, B = 14, 3
    F, H, LQ, LR, ys, m0 = _problem(n, m, T, B, seed=11 + n + m, ys_scale=4.0)
    ys[5, 1] = np.nan  # missing vector: lambda = 1 and V held
    ys[8, 2, 0] = np.nan  # partially observed: lambda = 1, V held, update with the rest
    ys[0, 0] = np.nan  # missing first step: V starts at the first observed step
    P0 = 0.5 * np.eye(n)
    make = {"ekf": ekf, "srukf": srukf, "sckf": sckf}[filt]
    cfg = StrongTracking(rho=rho, beta=beta, max_factor=maxf)
    tr = run(make(fading=cfg), _model(F, H, LQ, LR), _belief(m0, P0), torch.as_tensor(ys))
    lam_seen = []
    for b in range(B):
        x, P, lam = _st_reference(F, H, LQ, LR, m0[b], P0, ys[:, b], rho, beta, maxf)
        np.testing.assert_allclose(tr.fading_factors[:, b].numpy(), lam, rtol=1e-10, atol=0)
        np.testing.assert_allclose(tr.means[:, b].numpy(), x, rtol=1e-9, atol=1e-11)
        np.testing.assert_allclose(tr.covs[:, b].numpy(), P, rtol=1e-9, atol=1e-11)
        lam_seen.append(lam)
    lam_seen = np.array(lam_seen)
    assert (lam_seen > 1).sum() >= 3  # the fading factor does act on these data
    assert lam_seen[1, 5] == 1.0 and lam_seen[2, 8] == 1.0 and lam_seen[0, 0] == 1.0
    if maxf is not None:
        assert lam_seen.max() == maxf


# ----------------------------------------------------------------------------- Sage-Husa
def _sh_reference(
    F, H, LQ, LR, q, r, x, P, ys, *, b, k0, estimate, diagonal, floor_rel, frozen=False,
    r_form="innovation",
):  # fmt: skip
    Q0, R0 = LQ @ LQ.T, LR @ LR.T
    Q, R = Q0.copy(), R0.copy()
    fQ, fR = floor_rel * np.trace(Q0) / len(Q0), floor_rel * np.trace(R0) / len(R0)
    count, out = k0 - 1.0, []
    for y in ys:
        fx = F @ x
        xp, FPF = fx + q, F @ P @ F.T
        Pp = FPF + Q
        hz = H @ xp
        x, P, K, e, full = _update(xp, Pp, H, R, r, y)
        fb = False
        if full and not frozen:
            count += 1.0
            d = 1.0 / count if b is None else (1 - b) / (1 - b**count)
            if "q" in estimate:
                q = (1 - d) * q + d * (x - fx)
            if "Q" in estimate:
                Ke = K @ e
                term = np.outer(Ke, Ke) + P - FPF
                new = (1 - d) * Q + d * (np.diag(np.diag(term)) if diagonal else term)
                Q, f = _project(new, fQ, diagonal)
                fb |= f
            if "r" in estimate:
                r = (1 - d) * r + d * (y - hz)
            if "R" in estimate:
                if r_form == "innovation":
                    term = np.outer(e, e) - H @ Pp @ H.T
                else:
                    rho = y - H @ x - r
                    term = np.outer(rho, rho) + H @ P @ H.T
                new = (1 - d) * R + d * (np.diag(np.diag(term)) if diagonal else term)
                R, f = _project(new, fR, diagonal)
                fb |= f
        out.append((x, Q, R, q, r, fb))
    return out


SH_CASES = [
    # (estimate, forgetting, diagonal, k0, floor_rel, n, m)
    (("q", "Q", "r", "R"), None, False, 1.0, 1e-6, 3, 2),  # the paper: d = 1/k, projection
    (("q", "Q", "r", "R"), 0.9, False, 1.0, 1e-6, 3, 2),
    (("Q", "R"), 0.95, True, 1.0, 1e-3, 3, 2),  # diagonal, floor reached
    (("R",), None, False, 5.0, 1e-6, 2, 4),  # m > n, prior weight
    (("q", "Q"), 1e-9, False, 1.0, 1e-6, 2, 2),  # forgetting near 0: d = 1
    (("Q", "R"), 1.0 - 1e-7, False, 20.0, 1e-6, 2, 2),  # forgetting near 1: about 1/k
    (("q", "Q", "r", "R"), 0.8, False, 1.0, 1e-6, 1, 1),  # n = m = 1
    (("r",), None, False, 1.0, 1e-6, 3, 1),
]


@pytest.mark.parametrize("estimate,b,diagonal,k0,floor_rel,n,m", SH_CASES)
def test_sage_husa_matches_a_dense_reference(estimate, b, diagonal, k0, floor_rel, n, m):
    T, B = 12, 3
    F, H, LQ, LR, ys, m0 = _problem(n, m, T, B, seed=3 * n + m, ys_scale=2.0)
    ys[3, 0] = np.nan
    if m > 1:
        ys[6, 2, 1] = np.nan
    ys[0, 1] = np.nan  # the first step missing for one run: its count starts later
    rng = np.random.default_rng(99)
    q0, r0 = 0.1 * rng.standard_normal(n), 0.1 * rng.standard_normal(m)
    P0 = 0.7 * np.eye(n)
    est = SageHusa(estimate=estimate, forgetting=b, diagonal=diagonal, k0=k0, floor_rel=floor_rel)
    tr = run(srukf(noise=est), _model(F, H, LQ, LR, q0, r0), _belief(m0, P0), torch.as_tensor(ys))
    n_fb = 0
    for i in range(B):
        ref = _sh_reference(
            F, H, LQ, LR, q0, r0, m0[i], P0, ys[:, i], b=b, k0=k0, estimate=estimate,
            diagonal=diagonal, floor_rel=floor_rel,
        )  # fmt: skip
        x, Q, R, q, r, fb = (np.array(v) for v in zip(*ref))
        cQ, cR = tr.chol_Q[:, i], tr.chol_R[:, i]
        close = lambda a, b: np.testing.assert_allclose(a, b, rtol=1e-8, atol=1e-10)  # noqa: E731
        close(tr.means[:, i].numpy(), x)
        close((cQ @ cQ.mT).numpy(), Q)
        close((cR @ cR.mT).numpy(), R)
        close(tr.q[:, i].numpy(), q)
        close(tr.r[:, i].numpy(), r)
        np.testing.assert_array_equal(tr.noise_fallback[:, i].numpy(), fb)
        n_fb += fb.sum()
    if estimate == ("q", "Q", "r", "R") and b is None:
        assert n_fb > 0  # the projection is exercised


def test_sage_husa_post_fit_form_matches_a_dense_reference():
    n, m, T, B = 3, 2, 10, 2
    F, H, LQ, LR, ys, m0 = _problem(n, m, T, B, seed=4)
    ys[4, 1] = np.nan
    q0, r0, P0 = np.zeros(n), np.zeros(m), np.eye(n)
    for diagonal in (False, True):
        est = SageHusa(estimate=("R",), r_form="post-fit", diagonal=diagonal, k0=3.0)
        tr = run(srukf(noise=est), _model(F, H, LQ, LR), _belief(m0, P0), torch.as_tensor(ys))
        for i in range(B):
            ref = _sh_reference(
                F, H, LQ, LR, q0, r0, m0[i], P0, ys[:, i], b=None, k0=3.0, estimate=("R",),
                diagonal=diagonal, floor_rel=1e-6, r_form="post-fit",
            )  # fmt: skip
            R = np.array([v[2] for v in ref])
            cR = tr.chol_R[:, i]
            np.testing.assert_allclose((cR @ cR.mT).numpy(), R, rtol=1e-9, atol=1e-11)
            assert not tr.noise_fallback[:, i].any()


def test_frozen_sage_husa_and_moving_window_keep_the_model_noise():
    n, m, T, B = 2, 2, 8, 2
    F, H, LQ, LR, ys, m0 = _problem(n, m, T, B, seed=8)
    model, b0 = _model(F, H, LQ, LR), _belief(m0, np.eye(n))
    ref = run(srukf(), model, b0, torch.as_tensor(ys))
    for est in (SageHusa(frozen=True), MovingWindow(window=1, frozen=True)):
        tr = run(srukf(noise=est), model, b0, torch.as_tensor(ys))
        assert torch.equal(tr.means, ref.means) and torch.equal(tr.chols, ref.chols)
        assert torch.equal(tr.chol_Q, torch.as_tensor(LQ).expand(T, B, n, n))
        assert torch.equal(tr.chol_R, torch.as_tensor(LR).expand(T, B, m, m))


def test_projection_returns_the_documented_floor():
    """The projection of an indefinite estimate: eigenvalues raised to max(floor_rel * tr(C0) /
    dim, 1e-10 max|eig|), same eigenvectors; PD estimates are left alone, even below the floor
    (full form), while diagonal estimates are floored per variance."""
    from prognos_torch.adapt.noise import _project_pd

    C = torch.tensor([[2.0, 0.0, 0.0], [0.0, -1.0, 0.5], [0.0, 0.5, 1e-9]], dtype=dt)
    floor = torch.tensor(1e-3, dtype=dt)
    Cp, L, fb = _project_pd(C, floor, False)
    w, V = np.linalg.eigh(C.numpy())
    want = (V * np.maximum(w, 1e-3)) @ V.T
    np.testing.assert_allclose(Cp.numpy(), want, rtol=1e-12, atol=1e-15)
    torch.testing.assert_close(L @ L.mT, Cp, rtol=1e-12, atol=1e-15)
    assert bool(fb)
    # huge scale: the relative floor 1e-10 max|eig| wins
    Cp, _, fb = _project_pd(C * 1e12, floor, False)
    w2 = np.linalg.eigvalsh(Cp.numpy())
    np.testing.assert_allclose(w2.min(), 1e-10 * np.abs(w * 1e12).max(), rtol=1e-6)
    # positive definite: returned as it is (symmetrised), no flag
    D = torch.diag(torch.tensor([1.0, 1e-8], dtype=dt))
    Cp, _, fb = _project_pd(D, floor, False)
    assert torch.equal(Cp, D) and not bool(fb)
    Cp, Ld, fb = _project_pd(D, floor, True)
    assert torch.equal(Cp, torch.diag(torch.tensor([1.0, 1e-3], dtype=dt))) and bool(fb)
    torch.testing.assert_close(Ld, Cp.sqrt())


# ----------------------------------------------------------------------------- moving window
def _mw_reference(
    F, H, LQ, LR, x, P, ys, *, window, warmup, estimate, diagonal, M=None, N=0.0, mu=None,
    floor_rel=1e-6, robust=None,
):  # fmt: skip
    Q0, R0 = LQ @ LQ.T, LR @ LR.T
    Q, R = Q0.copy(), R0.copy()
    fQ, fR = floor_rel * np.trace(Q0) / len(Q0), floor_rel * np.trace(R0) / len(R0)
    r = np.zeros(H.shape[0])
    buf, out = [], []
    warm = window if warmup is None else warmup
    for y in ys:
        xp, FPF = F @ x, F @ P @ F.T
        Pp = FPF + Q
        if robust is None:
            x, P, K, e, full = _update(xp, Pp, H, R, r, y)
        else:
            x, P, K, e, full = _robust_update(xp, Pp, H, R, y, **robust)
            Pp = robust_prior(Pp, **robust)
        if full:
            Ke = K @ e
            tQ = P + np.outer(Ke, Ke) - FPF
            pzz = H @ Pp @ H.T
            if M is None:
                tR = np.outer(e, e) - pzz
            else:
                Mm = M.reshape(len(M), -1)
                tR = np.outer(e, e) - (1 - N**2 / mu) * pzz - mu * Mm @ Mm.T
        else:
            tQ = tR = None
        buf = (buf + [(tQ, tR)])[-window:]
        valid = [t for t in buf if t[0] is not None]
        fb = False
        if len(valid) >= warm:
            for name in estimate:
                j = 0 if name == "Q" else 1
                mean = sum(t[j] for t in valid) / len(valid)
                if diagonal:
                    mean = np.diag(np.diag(mean))
                C, f = _project(mean, fQ if name == "Q" else fR, diagonal)
                fb |= f
                if name == "Q":
                    Q = C
                else:
                    R = C
        out.append((x, Q, R, fb))
    return out


MW_CASES = [
    # (window, warmup, estimate, diagonal, n, m, with_M)
    (4, None, ("Q", "R"), False, 3, 2, False),
    (4, 2, ("Q", "R"), True, 3, 2, True),
    (1, None, ("Q", "R"), False, 2, 2, False),  # window 1: the last valid step's term
    (3, 1, ("R",), False, 2, 4, True),  # m > n (R projected every step: cond(R) 1e9)
    (5, 3, ("Q",), False, 1, 1, False),  # n = m = 1
]


@pytest.mark.parametrize("window,warmup,estimate,diagonal,n,m,with_M", MW_CASES)
def test_moving_window_matches_a_dense_reference(window, warmup, estimate, diagonal, n, m, with_M):
    T, B = 12, 3
    F, H, LQ, LR, ys, m0 = _problem(n, m, T, B, seed=20 + window + n, ys_scale=2.5)
    ys[2, 0] = np.nan
    ys[3, 0] = np.nan
    ys[7, 1] = np.nan
    if m > 1:
        ys[5, 2, 0] = np.nan
    P0 = np.eye(n)
    M = 0.2 * np.arange(1, m + 1) / m if with_M else None
    N, mu = (0.5, 2.0) if with_M else (0.0, None)
    est = MovingWindow(
        window=window, warmup=warmup, estimate=estimate, diagonal=diagonal,
        M=None if M is None else torch.as_tensor(M, dtype=dt), N=N, mu=mu,
    )  # fmt: skip
    filt = GaussianFilter(unscented(1.0, 0.0, 1.0), noise=est)
    rtol = 1e-6 if m > n else 1e-9  # (rounding grows with cond(R), up to 1e9 for m > n)
    close = lambda a, b: np.testing.assert_allclose(a, b, rtol=rtol, atol=1e-10)  # noqa: E731
    tr = run(filt, _model(F, H, LQ, LR), _belief(m0, P0), torch.as_tensor(ys))
    for i in range(B):
        ref = _mw_reference(
            F, H, LQ, LR, m0[i], P0, ys[:, i], window=window, warmup=warmup, estimate=estimate,
            diagonal=diagonal, M=M, N=N, mu=mu,
        )  # fmt: skip
        x, Q, R, fb = (np.array(v) for v in zip(*ref))
        cQ, cR = tr.chol_Q[:, i], tr.chol_R[:, i]
        close(tr.means[:, i].numpy(), x)
        close((cQ @ cQ.mT).numpy(), Q)
        close((cR @ cR.mT).numpy(), R)
        np.testing.assert_array_equal(tr.noise_fallback[:, i].numpy(), fb)


# ----------------------------------------------------------------------------- robust bound
def robust_prior(Pp, *, gamma, M, N, form):
    if form == "lemma":  # P~ = (P^-1 - gamma^-2 N^T N)^-1 (test-only explicit inverse)
        NN = N.T @ N if np.ndim(N) == 2 else N**2 * np.eye(len(Pp))
        return np.linalg.inv(np.linalg.inv(Pp) - NN / gamma**2)
    return Pp


def _robust_update(xp, Pp, H, R, y, *, gamma, M, N, form):
    if np.isnan(y).any():  # the robust bound treats a partly observed vector as missing
        return xp, Pp, None, None, False
    Mm = M.reshape(len(M), -1)
    MM = Mm @ Mm.T
    if form == "lemma":
        P = robust_prior(Pp, gamma=gamma, M=M, N=N, form=form)
        lam, cM, cR, cK = 1.0, gamma**2, 1.0, gamma**2
    else:
        P, nu = Pp, float(N) ** 2
        lam = 1.0 / (1.0 - nu / gamma**2)  # Eq. 34
        cM, cR, cK = gamma**2 - nu, 1.0 - nu / gamma**2, gamma**2
    S = H @ P @ H.T + cM * MM + cR * R  # Eq. 29 / 35
    K = np.linalg.solve(S, H @ P).T
    e = y - H @ xp
    I_KH = np.eye(len(xp)) - K @ H
    Pk = lam * I_KH @ P @ I_KH.T + cK * K @ MM @ K.T + K @ R @ K.T  # Eq. 28
    return xp + K @ e, Pk, K, e, True


@pytest.mark.parametrize("form", ["scalar", "lemma"])
def test_robust_and_adaptive_robust_ukf_match_a_dense_reference(form):
    n, m, T, B = 3, 2, 10, 2
    F, H, LQ, LR, ys, m0 = _problem(n, m, T, B, seed=31, ys_scale=1.5)
    if form == "scalar":  # (lemma: a missing step keeps the inflated prior P~, not P; see report)
        ys[4, 1, 0] = np.nan  # partly observed: a missing step for the robust bound
    P0 = 0.5 * np.eye(n)
    M = np.array([0.2, -0.1])
    gamma, N = (1.05, 1.0) if form == "scalar" else (3.0, 0.8)
    rob = dict(gamma=gamma, M=M, N=N, form=form)
    model, b0 = _model(F, H, LQ, LR), _belief(m0, P0)
    yt = torch.as_tensor(ys)
    Mt = torch.as_tensor(M, dtype=dt)
    tr = run(rukf(gamma, Mt, N, form=form), model, b0, yt)
    # the printed scalar form multiplies P by lambda = 10.76 per step: cond(P) reaches 5e5
    tol = dict(rtol=1e-7, atol=1e-10) if form == "scalar" else dict(rtol=1e-10, atol=1e-12)
    for i in range(B):
        x, P = m0[i].copy(), P0.copy()
        for t in range(T):
            xp, Pp = F @ x, F @ P @ F.T + LQ @ LQ.T
            x, P, *_ = _robust_update(xp, Pp, H, LR @ LR.T, ys[t, i], **rob)
            np.testing.assert_allclose(tr.means[t, i].numpy(), x, **tol)
            np.testing.assert_allclose(tr.covs[t, i].numpy(), P, **tol)
    # ARUKF: Eq. 47-48 on top (window 3, diagonal as the study uses)
    tr = run(arukf(gamma, Mt, N, window=3, form=form), model, b0, yt)
    Nw = 0.0 if form == "lemma" else N
    for i in range(B):
        ref = _mw_reference(
            F, H, LQ, LR, m0[i], P0, ys[:, i], window=3, warmup=None, estimate=("Q", "R"),
            diagonal=True, M=M, N=Nw, mu=gamma**2, robust=rob,
        )  # fmt: skip
        x, Q, R, fb = (np.array(v) for v in zip(*ref))
        np.testing.assert_allclose(tr.means[:, i].numpy(), x, **tol)
        cQ, cR = tr.chol_Q[:, i], tr.chol_R[:, i]
        np.testing.assert_allclose((cQ @ cQ.mT).numpy(), Q, **tol)
        np.testing.assert_allclose((cR @ cR.mT).numpy(), R, **tol)
        np.testing.assert_array_equal(tr.noise_fallback[:, i].numpy(), fb)


def test_robust_bound_refuses_non_finite_settings():
    """gamma = inf passed the check gamma^2 > N^2 and gave NaN means and covariances from the
    first step (scalar form: coefficients sqrt(gamma^2 - N^2) = inf, inf * 0 = NaN), or the
    misleading "gamma=inf is too small" (lemma form); NaN in N or M gave NaN silently."""
    M = torch.zeros(2, dtype=dt)
    with pytest.raises(ValueError, match="gamma must be a finite number"):
        RobustBound(float("inf"), M, 1.0)
    with pytest.raises(ValueError, match="gamma must be a finite number"):
        rukf(float("inf"), M, 0.5, form="lemma")
    with pytest.raises(ValueError, match="N must be finite"):
        RobustBound(2.0, M, float("nan"), form="lemma")
    with pytest.raises(ValueError, match="N must be finite"):
        RobustBound(2.0, M, float("nan"), bound="optimised")
    with pytest.raises(ValueError, match="N must be finite"):
        RobustBound(2.0, M, torch.full((1, 2), float("inf"), dtype=dt), form="lemma")
    with pytest.raises(ValueError, match="M must be finite"):
        RobustBound(2.0, torch.tensor([float("nan"), 0.0], dtype=dt), 1.0)
    RobustBound(float("inf"), M, 1.0, bound="optimised")  # (gamma unused there)


def test_bad_settings_of_the_estimators_and_strong_tracking_are_refused():
    with pytest.raises(ValueError, match="forgetting"):
        SageHusa(forgetting=1.0)
    with pytest.raises(ValueError, match="forgetting"):
        SageHusa(forgetting=0.0)
    with pytest.raises(ValueError, match="estimate"):
        SageHusa(estimate=("Q", "P"))
    with pytest.raises(ValueError, match="estimate"):
        MovingWindow(estimate=("q",))
    with pytest.raises(ValueError, match="window"):
        MovingWindow(window=0)
    with pytest.raises(ValueError, match="rho"):
        StrongTracking(rho=0.0)
    with pytest.raises(ValueError, match="beta"):
        StrongTracking(beta=float("inf"))
    with pytest.raises(ValueError, match="max_factor"):
        StrongTracking(max_factor=0.5)
    n, m = 2, 2
    F, H, LQ, LR, ys, m0 = _problem(n, m, 2, 1, seed=0)
    est = MovingWindow(window=2, M=torch.ones(3, dtype=dt))  # M of the wrong length
    with pytest.raises(ValueError, match=r"MovingWindow.M must have shape \(m,\)"):
        run(srukf(noise=est), _model(F, H, LQ, LR), _belief(m0, np.eye(n)), torch.as_tensor(ys))
