"""A plain float64 Kalman filter used as the exact reference (no library code)."""

import math

import numpy as np


def _update(m, P, H, R, y, r=None):
    """Joseph-form update with the observed components of ``y`` (NaN: not observed); returns
    the mean, the covariance, ``K H_o`` and the step's log-likelihood term."""
    n = m.shape[0]
    o = ~np.isnan(y)
    if not o.any():
        return m, P, np.zeros((n, n)), 0.0
    Ho, Ro = H[o], R[np.ix_(o, o)]
    S = Ho @ P @ Ho.T + Ro
    e = y[o] - (Ho @ m + (0.0 if r is None else r[o]))
    K = np.linalg.solve(S, Ho @ P).T
    KH = K @ Ho
    I_KH = np.eye(n) - KH
    lk = -0.5 * (o.sum() * math.log(2 * math.pi) + np.linalg.slogdet(S)[1]
                 + e @ np.linalg.solve(S, e))  # fmt: skip
    return m + K @ e, I_KH @ P @ I_KH.T + K @ Ro @ K.T, KH, lk


def kalman_filter(F, H, Q, R, m0, P0, ys, q=None, r=None):
    """Predict-then-update KF. ys: (T, m). Returns means (T, n), covs (T, n, n), loglik."""
    n = F.shape[0]
    q = np.zeros(n) if q is None else q
    r = np.zeros(H.shape[0]) if r is None else r
    m, P = m0.copy(), P0.copy()
    means, covs, ll = [], [], 0.0
    for y in ys:
        m = F @ m + q
        P = F @ P @ F.T + Q
        if not np.isnan(y).any():  # (a partly missing row is skipped whole)
            m, P, _, lk = _update(m, P, H, R, y, r)
            ll += lk
        means.append(m.copy())
        covs.append(P.copy())
    return np.array(means), np.array(covs), ll


def kalman_filter_observed(F, H, Q, R, m0, P0, ys, B=None, us=None):
    """The filter that updates with the observed components of each ``y`` (NaN: not observed).

    ``F``: a matrix or ``k -> F_k`` (``k`` from 1); ``x_k = F_k x + B u_k``. Returns means
    ``(T, n)``, covariances ``(T, n, n)`` and the per-step log-likelihoods ``(T,)``."""
    m, P = m0.copy(), P0.copy()
    means, covs, ll = [], [], []
    for k, y in enumerate(ys, start=1):
        Fk = F(k) if callable(F) else F
        m = Fk @ m + (B @ us[k - 1] if B is not None else 0.0)
        P = Fk @ P @ Fk.T + Q
        m, P, _, lk = _update(m, P, H, R, y)
        means.append(m.copy())
        covs.append(P.copy())
        ll.append(lk)
    return np.array(means), np.array(covs), np.array(ll)


def kalman_filter_tv(Fs, H, Qs, Rs, m0, P0, ys):
    """The same filter with per-step F_k, Q_k, R_k: (T, n, n), (T, n, n), (T, m, m)."""
    m, P = m0.copy(), P0.copy()
    means, covs, ll = [], [], 0.0
    for F, Q, R, y in zip(Fs, Qs, Rs, ys):
        m = F @ m
        P = F @ P @ F.T + Q
        if not np.isnan(y).any():  # (a partly missing row is skipped whole)
            m, P, _, lk = _update(m, P, H, R, y)
            ll += lk
        means.append(m.copy())
        covs.append(P.copy())
    return np.array(means), np.array(covs), ll


def rts_reference(F, H, Q, R, m0, P0, ys, fading=1.0):
    """Kalman filter (observed components of partially NaN rows) + RTS smoother + the lag-one
    covariance smoother of Shumway and Stoffer (Property 6.3), all with plain dense algebra.

    ``fading``: constant factor on ``F P F^T`` in the prediction. Returns a dict with the
    smoothed ``means`` (T+1, n) and ``covs`` (T+1, n, n) for x_0..x_T, ``cross`` (T, n, n)
    ``Cov(x_t, x_{t-1} | y_{1:T})`` for t = 1..T, the filtered ``fmeans``/``fcovs`` (T+1) and
    the log-likelihood ``ll``.
    """
    n = F.shape[0]
    T = len(ys)
    mf, Pf, mp, Pp = [m0.copy()], [P0.copy()], [None], [None]
    KH_last = np.zeros((n, n))
    ll = 0.0
    for y in ys:
        m = F @ mf[-1]
        P = fading * F @ Pf[-1] @ F.T + Q
        mp.append(m)
        Pp.append(P)
        m, P, KH_last, lk = _update(m, P, H, R, y)
        ll += lk
        mf.append(m)
        Pf.append(P)
    J = [np.linalg.solve(Pp[t + 1], F @ Pf[t]).T for t in range(T)]  # Pf F^T Pp^-1
    ms, Ps = [None] * (T + 1), [None] * (T + 1)
    ms[T], Ps[T] = mf[T], Pf[T]
    for t in range(T - 1, -1, -1):
        ms[t] = mf[t] + J[t] @ (ms[t + 1] - mp[t + 1])
        Ps[t] = Pf[t] + J[t] @ (Ps[t + 1] - Pp[t + 1]) @ J[t].T
    L = [None] * (T + 1)  # L[t] = Cov(x_t, x_{t-1} | y_{1:T})
    L[T] = (np.eye(n) - KH_last) @ F @ Pf[T - 1]
    for t in range(T, 1, -1):
        L[t - 1] = Pf[t - 1] @ J[t - 2].T + J[t - 1] @ (L[t] - F @ Pf[t - 1]) @ J[t - 2].T
    return {
        "means": np.array(ms),
        "covs": np.array(Ps),
        "cross": np.array(L[1:]),
        "fmeans": np.array(mf),
        "fcovs": np.array(Pf),
        "ll": ll,
    }


def numpy_em_step(A, C, Q, R, m0, P0, ys, learn):
    """One EM iteration (Shumway and Stoffer 1982; Ghahramani and Hinton 1996)."""
    ref = rts_reference(A, C, Q, R, m0, P0, ys)
    ms, Ps, L = ref["means"], ref["covs"], ref["cross"]
    T = len(ys)
    Exx = Ps + np.einsum("ti,tj->tij", ms, ms)
    S11, S00 = Exx[1:].sum(0), Exx[:-1].sum(0)
    S10 = (L + np.einsum("ti,tj->tij", ms[1:], ms[:-1])).sum(0)
    if "A" in learn:
        A = np.linalg.solve(S00.T, S10.T).T
    if "Q" in learn:
        Q = (S11 - A @ S10.T - S10 @ A.T + A @ S00 @ A.T) / T
    o = ~np.isnan(ys).all(-1)
    yo, xo = ys[o], ms[1:][o]
    Syx, Sxx, Syy = yo.T @ xo, Exx[1:][o].sum(0), yo.T @ yo
    if "C" in learn:
        C = np.linalg.solve(Sxx.T, Syx.T).T
    if "R" in learn:
        R = (Syy - C @ Syx.T - Syx @ C.T + C @ Sxx @ C.T) / o.sum()
    if "init" in learn:
        m0, P0 = ms[0], Ps[0]
    return A, C, Q, R, m0, P0, ref["ll"]


def joint_gaussian_reference(F, H, Qs, Rs, m0, P0, ys, Bu=None, qs=None, rs=None, upto=None):
    """Brute force: the joint Gaussian of ``x_{0:T}`` and ``y_{1:T}`` of ``x_t = F_t x_{t-1} +
    Bu_t + q_t + w_t`` (``F`` one ``(n, n)`` matrix, or one per step), ``y_t = H x_t + r_t + v_t`` (per-step ``Q_t``, ``R_t``), conditioned on
    the observed components of ``ys[:upto]``. Returns the means ``(T+1, n)``, covariances
    ``(T+1, n, n)``, ``Cov(x_t, x_{t-1})`` ``(T, n, n)`` and ``log p(y_obs)``."""
    T, m = ys.shape
    n = m0.size
    Lx, c = [np.eye(n, n * (T + 1))], [m0]  # x_t = Lx_t [x_0 - m0, w_1..w_T] + c_t
    for k in range(T):
        Fk = F if np.ndim(F) == 2 else F[k]
        L = Fk @ Lx[-1]
        L[:, n * (k + 1) : n * (k + 2)] += np.eye(n)
        Lx.append(L)
        c.append(Fk @ c[-1] + (0 if Bu is None else Bu[k]) + (0 if qs is None else qs[k]))
    Lx, mX = np.vstack(Lx), np.concatenate(c)
    Pz = np.zeros((n * (T + 1),) * 2)
    for k, P in enumerate([P0, *Qs]):
        Pz[n * k : n * (k + 1), n * k : n * (k + 1)] = P
    PX = Lx @ Pz @ Lx.T
    Hb = np.kron(np.eye(T + 1), H)[m:]
    mY = Hb @ mX + (0 if rs is None else np.concatenate(rs))
    PY = Hb @ PX @ Hb.T
    for k, R in enumerate(Rs):
        PY[m * k : m * (k + 1), m * k : m * (k + 1)] += R
    y = ys.copy()
    if upto is not None:
        y[upto:] = np.nan
    o = ~np.isnan(y.reshape(-1))
    S, e = PY[np.ix_(o, o)], y.reshape(-1)[o] - mY[o]
    K = np.linalg.solve(S, Hb[o] @ PX).T
    mean, cov = mX + K @ e, PX - K @ Hb[o] @ PX
    ll = -0.5 * (
        o.sum() * math.log(2 * math.pi) + np.linalg.slogdet(S)[1] + e @ np.linalg.solve(S, e)
    )
    blk = lambda i, j: cov[n * i : n * (i + 1), n * j : n * (j + 1)]  # noqa: E731
    return (
        mean.reshape(T + 1, n),
        np.array([blk(k, k) for k in range(T + 1)]),
        np.array([blk(k, k - 1) for k in range(1, T + 1)]),
        ll,
    )
