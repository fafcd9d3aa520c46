"""A plain float64 Kalman filter used as the exact reference (no library code)."""

import math

import numpy as np


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
        if not np.isnan(y).any():
            S = H @ P @ H.T + R
            e = y - (H @ m + r)
            K = np.linalg.solve(S, H @ P).T
            m = m + K @ e
            I_KH = np.eye(n) - K @ H
            P = I_KH @ P @ I_KH.T + K @ R @ K.T
            sign, logdet = np.linalg.slogdet(S)
            ll += -0.5 * (len(y) * math.log(2 * math.pi) + logdet + e @ np.linalg.solve(S, e))
        means.append(m.copy())
        covs.append(P.copy())
    return np.array(means), np.array(covs), ll


def kalman_filter_tv(Fs, H, Qs, Rs, m0, P0, ys):
    """The same filter with per-step F_k, Q_k, R_k: (T, n, n), (T, n, n), (T, m, m)."""
    n = m0.shape[0]
    m, P = m0.copy(), P0.copy()
    means, covs, ll = [], [], 0.0
    for F, Q, R, y in zip(Fs, Qs, Rs, ys):
        m = F @ m
        P = F @ P @ F.T + Q
        if not np.isnan(y).any():
            S = H @ P @ H.T + R
            e = y - H @ m
            K = np.linalg.solve(S, H @ P).T
            m = m + K @ e
            I_KH = np.eye(n) - K @ H
            P = I_KH @ P @ I_KH.T + K @ R @ K.T
            sign, logdet = np.linalg.slogdet(S)
            ll += -0.5 * (len(y) * math.log(2 * math.pi) + logdet + e @ np.linalg.solve(S, e))
        means.append(m.copy())
        covs.append(P.copy())
    return np.array(means), np.array(covs), ll
