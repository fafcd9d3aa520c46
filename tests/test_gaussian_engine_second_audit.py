"""The Gaussian filter engine (filters/gaussian.py, run.py, sequence.py, segments.py) against a
plain NumPy Kalman filter (tests/_kalman_reference.py, Joseph form, observed components only).

Linear-Gaussian models, where every moment rule is exact: batches whose members miss different
components of their measurement vectors, time-varying transitions and controls (shared by the
batch or per member), ``k0`` offsets, a scalar and a vector measurement, batch shapes ``()``,
``(3,)`` and ``(2, 4)``; the per-step log-likelihood is the exact Gaussian density of the
observed components. Then run against step-by-step, float32, forecasts in closed form, the
noise that ``run_in_segments`` reports, and bad input named.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from _kalman_reference import kalman_filter_observed

from prognos_torch.adapt import SageHusa
from prognos_torch.core import GaussianBelief, StateSpaceModel, linear_gaussian_model
from prognos_torch.filters import (
    FilterState,
    ekf,
    forecast,
    imsrukf,
    run,
    run_in_segments,
    sckf,
    srukf,
    stekf,
    ukf,
)
from prognos_torch.filters.sequence import scan

D = torch.float64
N, T = 3, 6


def _t(a, dtype=D):
    return torch.as_tensor(np.asarray(a), dtype=dtype)


def _problem(B, m, p, seed=0):
    """A linear model with ``F_k = F (1 + 0.05 k)`` and ``x_k = F_k x + Bm u_k``; measurements
    whose members miss different components (and some whole vectors)."""
    rng = np.random.default_rng(seed)
    F = 0.8 * np.eye(N) + 0.1 * rng.standard_normal((N, N))
    H = rng.standard_normal((m, N))
    Bm = rng.standard_normal((N, p))
    LQ = np.tril(0.1 * rng.random((N, N))) + np.diag(0.2 + 0.3 * rng.random(N))
    LR = np.tril(0.2 * rng.random((m, m))) + np.diag(0.5 + 0.5 * rng.random(m))  # correlated
    ys = 2.0 * rng.standard_normal((T, *B, m))
    flat = ys.reshape(T, -1, m)
    for b in range(flat.shape[1]):
        for t in range(T):
            if (t + b) % 3 == 1:
                flat[t, b, (t + b) % m] = np.nan  # member b misses component (t + b) % m
            if (t * b) % 5 == 4:
                flat[t, b] = np.nan  # a whole vector
    m0 = rng.standard_normal((*B, N))
    P0 = 0.5 * np.eye(N) + 0.1
    return F, H, Bm, LQ, LR, ys, m0, P0, rng


def _model(F, H, Bm, LQ, LR, dtype=D):
    Fk = lambda k: _t(F * (1.0 + 0.05 * k), dtype)  # noqa: E731
    Bt, Ht = _t(Bm, dtype), _t(H, dtype)
    return StateSpaceModel(
        f=lambda x, u, k: Fk(k) @ x + Bt @ u,
        h=lambda x, u, k: Ht @ x,
        state_dim=N,
        obs_dim=H.shape[0],
        chol_Q=_t(LQ, dtype),
        chol_R=_t(LR, dtype),
        control_dim=Bm.shape[1],
    )


def _belief(m0, P0, dtype=D):
    B = m0.shape[:-1]
    L = _t(np.linalg.cholesky(P0), dtype)
    return GaussianBelief(_t(m0, dtype), L.expand(*B, N, N).clone())


def _reference(F, H, Bm, LQ, LR, ys, us, m0, P0, k0):
    """The NumPy filter per batch member; ``us`` ``(T, p)`` shared or ``(T, *B, p)``."""
    B = m0.shape[:-1]
    xs, Ps, ll = np.zeros((T, *B, N)), np.zeros((T, *B, N, N)), np.zeros((T, *B))
    for idx in np.ndindex(*B):
        sl = (slice(None), *idx)
        u = us if us.ndim == 2 else us[sl]
        x, P, lk = kalman_filter_observed(
            lambda k: F * (1.0 + 0.05 * (k + k0)), H, LQ @ LQ.T, LR @ LR.T, m0[idx], P0,
            ys[sl], Bm, u,
        )  # fmt: skip
        xs[sl], Ps[sl], ll[sl] = x, P, lk
    return xs, Ps, ll


FILTERS = {
    "ekf": ekf,
    "ekf-full": lambda: ekf(sqrt=False),
    "sckf": sckf,
    "srukf": srukf,
    "ukf-full": lambda: ukf(sqrt=False),
}


# ----------------------------------------------------------------------------- exactness
@pytest.mark.parametrize(
    "B,shared",
    [((), True), ((3,), False), ((2, 4), True), ((2, 4), False)],
    ids=["unbatched", "b3-own-u", "b2x4-shared-u", "b2x4-own-u"],
)
@pytest.mark.parametrize("m", [1, 3])
def test_partially_missing_batches_with_controls_are_the_kalman_filter(B, m, shared):
    F, H, Bm, LQ, LR, ys, m0, P0, rng = _problem(B, m, 2, seed=len(B) + m)
    us = rng.standard_normal((T, 2) if shared else (T, *B, 2))
    k0 = 4
    xs, Ps, ll = _reference(F, H, Bm, LQ, LR, ys, us, m0, P0, k0)
    model = _model(F, H, Bm, LQ, LR)
    for name, factory in FILTERS.items():
        tr = run(factory(), model, _belief(m0, P0), _t(ys), _t(us), k0=np.int64(k0))
        assert tr.means.shape == (T, *B, N) and tr.log_likelihoods.shape == (T, *B), name
        np.testing.assert_allclose(tr.means.numpy(), xs, rtol=1e-11, atol=1e-11, err_msg=name)
        np.testing.assert_allclose(tr.covs.numpy(), Ps, rtol=1e-11, atol=1e-11, err_msg=name)
        # the exact Gaussian log-density of the observed components (0 for a missing vector)
        np.testing.assert_allclose(tr.log_likelihoods.numpy(), ll, rtol=1e-11, atol=1e-11)
        np.testing.assert_allclose(tr.log_likelihood.numpy(), ll.sum(0), rtol=1e-11, atol=1e-10)
        missing = np.isnan(ys).all(-1)
        assert np.array_equal(np.isnan(tr.nis.numpy()), missing), name


def test_run_is_its_steps_deterministic_and_one_member_is_its_own_run():
    B = (2, 4)
    F, H, Bm, LQ, LR, ys, m0, P0, rng = _problem(B, 3, 2, seed=7)
    us = rng.standard_normal((T, *B, 2))
    model, k0 = _model(F, H, Bm, LQ, LR), 2
    for factory in (sckf, lambda: stekf(0.9, 1.0), imsrukf):
        filt = factory()
        tr = run(filt, model, _belief(m0, P0), _t(ys), _t(us), k0=k0)
        again = run(filt, model, _belief(m0, P0), _t(ys), _t(us), k0=k0)
        assert torch.equal(tr.means, again.means) and torch.equal(tr.chols, again.chols)
        state = filt.init(model, _belief(m0, P0), k0 + 1)
        for t in range(T):
            state, info = filt.step(model, state, _t(ys[t]), _t(us[t]), k=k0 + t + 1)
            torch.testing.assert_close(state.belief.mean, tr.means[t], rtol=0, atol=1e-13)
            torch.testing.assert_close(
                info.log_likelihood, tr.log_likelihoods[t], rtol=0, atol=1e-13
            )
            nis = tr.nis[t]
            torch.testing.assert_close(info.nis, nis, rtol=0, atol=1e-12, equal_nan=True)
        one = run(filt, model, _belief(m0[1, 2], P0), _t(ys[:, 1, 2]), _t(us[:, 1, 2]), k0=k0)
        torch.testing.assert_close(one.means, tr.means[:, 1, 2], rtol=0, atol=1e-10)
        torch.testing.assert_close(
            one.log_likelihoods, tr.log_likelihoods[:, 1, 2], rtol=0, atol=1e-10
        )


def test_float32_inputs_stay_float32_and_match_the_reference():
    B = (3,)
    F, H, Bm, LQ, LR, ys, m0, P0, rng = _problem(B, 3, 2, seed=5)
    us = rng.standard_normal((T, 2))
    xs, Ps, ll = _reference(F, H, Bm, LQ, LR, ys, us, m0, P0, 0)
    f32 = torch.float32
    model = _model(F, H, Bm, LQ, LR, f32)
    for factory in (ekf, sckf, srukf):
        tr = run(factory(), model, _belief(m0, P0, f32), _t(ys, f32), _t(us, f32))
        for v in (tr.means, tr.chols, tr.log_likelihoods, tr.nis, tr.innovations):
            assert v.dtype == f32
        np.testing.assert_allclose(tr.means.double().numpy(), xs, rtol=1e-4, atol=1e-4)
        np.testing.assert_allclose(tr.covs.double().numpy(), Ps, rtol=1e-4, atol=1e-4)
        np.testing.assert_allclose(tr.log_likelihoods.double().numpy(), ll, rtol=1e-4, atol=1e-4)


def test_forecast_is_the_closed_form_with_offsets_controls_and_a_constant_fading_factor():
    rng = np.random.default_rng(0)
    m, p, H_ = 2, 1, 4
    F = 0.9 * np.eye(N) + 0.1 * rng.standard_normal((N, N))
    H, Bm = rng.standard_normal((m, N)), rng.standard_normal((N, p))
    LQ = np.tril(0.3 * rng.random((N, N))) + 0.2 * np.eye(N)
    LR = np.tril(0.2 * rng.random((m, m))) + 0.5 * np.eye(m)
    q, r = rng.standard_normal(N), rng.standard_normal(m)
    model = linear_gaussian_model(_t(F), _t(H), _t(LQ), _t(LR), B=_t(Bm), q=_t(q), r=_t(r))
    m0, P0 = rng.standard_normal((2, N)), 0.5 * np.eye(N)
    us = rng.standard_normal((H_, 2, p))
    for lam, filt in (
        (1.0, sckf()),
        (1.0, ekf(sqrt=False)),
        (1.0, stekf()),
        (1.2, ekf(fading=1.2)),
    ):
        fc = forecast(filt, model, _belief(m0, P0), np.int64(H_), _t(us))
        for b in range(2):
            x, P = m0[b], P0
            for j in range(H_):
                # P = lambda F P F^T + Q: strong tracking predicts with lambda = 1
                x, P = F @ x + Bm @ us[j, b] + q, lam * F @ P @ F.T + LQ @ LQ.T
                Sy = H @ P @ H.T + LR @ LR.T
                np.testing.assert_allclose(fc.means[j, b].numpy(), x, rtol=0, atol=1e-12)
                np.testing.assert_allclose(
                    (fc.chols[j, b] @ fc.chols[j, b].T).numpy(), P, atol=1e-12
                )
                np.testing.assert_allclose(fc.y_means[j, b].numpy(), H @ x + r, atol=1e-12)
                np.testing.assert_allclose(
                    (fc.y_chols[j, b] @ fc.y_chols[j, b].T).numpy(), Sy, atol=1e-12
                )


# ----------------------------------------------------------------------------- segments
@pytest.mark.parametrize(
    "noise", [SageHusa(frozen=True), SageHusa(estimate=("R",)), SageHusa(estimate=("Q", "q"))],
    ids=["frozen", "estimate-R", "estimate-Q"],
)  # fmt: skip
def test_segments_report_the_per_step_model_noise_that_an_estimator_holds(noise):
    # per-step model noise that the estimator does not estimate is the model's Q_k, R_k at
    # every step (it reported the value at the first step throughout)
    F = _t([[0.9, 0.1], [0.0, 0.8]])
    H = _t([[1.0, 0.0], [0.5, 1.0]])
    sq = lambda k: (0.1 + 0.05 * k) * torch.eye(2, dtype=D)  # noqa: E731
    sr = lambda k: (0.5 + 0.1 * k) * torch.eye(2, dtype=D)  # noqa: E731
    model = StateSpaceModel(
        f=lambda x, u, k: F @ x, h=lambda x, u, k: H @ x, state_dim=2, obs_dim=2,
        chol_Q=sq, chol_R=sr,
    )  # fmt: skip
    bel = GaussianBelief(torch.zeros(3, 2, dtype=D), torch.eye(2, dtype=D).expand(3, 2, 2))
    ys = torch.randn(5, 3, 2, dtype=D, generator=torch.Generator().manual_seed(0))
    k0, filt = 2, imsrukf(noise=noise)
    sg = run_in_segments(filt, model, bel, ys, segment=2, k0=k0)
    tr = run(filt, model, bel, ys, k0=k0, keep_steps=True)
    used_Q = torch.stack([s.noise.chol_Q.square().sum(-1).expand(3, 2) for s in tr.steps])
    used_R = torch.stack([s.noise.chol_R.square().sum(-1).expand(3, 2) for s in tr.steps])
    torch.testing.assert_close(sg.means, tr.means, rtol=0, atol=1e-13)
    torch.testing.assert_close(sg.var_Q, used_Q, rtol=0, atol=1e-13)
    torch.testing.assert_close(sg.var_R, used_R, rtol=0, atol=1e-13)
    held = {"Q", "R"} if noise.frozen else {"Q", "R"} - set(noise.estimate)
    ks = torch.arange(k0 + 1, k0 + 6, dtype=D)[:, None, None]
    if "Q" in held:  # diag(Q_k) = (0.1 + 0.05 k)^2
        torch.testing.assert_close(sg.var_Q, ((0.1 + 0.05 * ks) ** 2).expand(5, 3, 2))
    if "R" in held:
        torch.testing.assert_close(sg.var_R, ((0.5 + 0.1 * ks) ** 2).expand(5, 3, 2))


# ----------------------------------------------------------------------------- bad input
def _setup():
    F, H, Bm, LQ, LR, ys, m0, P0, rng = _problem((2,), 2, 1, seed=1)
    us = rng.standard_normal((T, 1))
    return _model(F, H, Bm, LQ, LR), _belief(m0, P0), _t(ys), _t(us)


MODEL, BEL, YS, US = _setup()

BAD = [
    ("ys-numpy", lambda: run(ekf(), MODEL, BEL, YS.numpy(), US), TypeError,
     r"ys must be a torch.Tensor of shape \(T, \.\.\., 2\)"),
    ("ys-trailing", lambda: run(ekf(), MODEL, BEL, YS[..., :1], US), ValueError,
     r"ys must have shape \(T, 2, 2\), got \(6, 2, 1\)"),
    ("ys-no-batch", lambda: run(ekf(), MODEL, BEL, YS[:, 0], US), ValueError,
     r"ys must have shape \(T, 2, 2\), got \(6, 2\)"),
    ("us-short", lambda: run(ekf(), MODEL, BEL, YS, US[:-1]), ValueError,
     r"us must have shape \(T, 1\) or \(T, 2, 1\) with T = 6, got \(5, 1\)"),
    ("us-list", lambda: run(ekf(), MODEL, BEL, YS, US.tolist()), TypeError,
     r"us must be a torch.Tensor"),
    ("keep_steps", lambda: run(ekf(), MODEL, BEL, YS, US, keep_steps="no"), TypeError,
     "keep_steps must be a bool, got 'no'"),
    ("inference", lambda: run(ekf(), MODEL, BEL, YS, US, inference="no"), TypeError,
     "inference must be a bool, got 'no'"),
    ("scan-compile", lambda: scan(lambda s, y, u, k: (s, None), 0, YS, record=lambda s, i: {},
                                  compile="no"), TypeError, "compile must be a bool, got 'no'"),
    ("scan-inference", lambda: scan(lambda s, y, u, k: (s, None), 0, YS, record=lambda s, i: {},
                                    inference="no"), TypeError, "inference must be a bool"),
    ("predict-belief", lambda: ekf().predict(MODEL, BEL, US[0]), TypeError,
     r"state must be a FilterState, got GaussianBelief.*filter\.init"),
    ("predict-measurement-state", lambda: ekf().predict_measurement(
        MODEL, ekf().init(MODEL, BEL), US[0]), TypeError,
     "belief must be a GaussianBelief, got FilterState: pass state.belief"),
    ("resume-no-fading", lambda: run(stekf(), MODEL, FilterState(BEL), YS, US), ValueError,
     "init.fading must be the StrongTrackingState"),
    ("resume-no-noise", lambda: run(imsrukf(), MODEL, FilterState(BEL), YS, US), ValueError,
     r"init.noise is None, but the filter estimates its noise \(SageHusa\)"),
    ("resume-foreign-noise", lambda: run(ekf(), MODEL, imsrukf().init(MODEL, BEL), YS, US),
     ValueError, "init.noise holds noise-estimator statistics, but the filter has no noise"),
    ("segments-no-noise", lambda: run_in_segments(imsrukf(), MODEL, FilterState(BEL), YS, US,
                                                  segment=2), ValueError, "init.noise is None"),
]  # fmt: skip


@pytest.mark.parametrize("call,exc,match", [b[1:] for b in BAD], ids=[b[0] for b in BAD])
def test_bad_input_is_named(call, exc, match):
    with pytest.raises(exc, match=match):
        call()


def test_numpy_flags_and_matching_resumed_states_are_taken():
    tr = run(stekf(), MODEL, BEL, YS, US, keep_steps=np.bool_(True), inference=np.False_)
    assert len(tr.steps) == T
    half = run(stekf(), MODEL, BEL, YS[:3], US[:3])
    rest = run(stekf(), MODEL, half.final, YS[3:], US[3:], k0=3)
    torch.testing.assert_close(rest.means, tr.means[3:], rtol=0, atol=1e-13)
    filt = imsrukf()
    rest = run(filt, MODEL, run(filt, MODEL, BEL, YS[:3], US[:3]).final, YS[3:], US[3:], k0=3)
    torch.testing.assert_close(rest.means, run(filt, MODEL, BEL, YS, US).means[3:], rtol=0,
                               atol=1e-12)  # fmt: skip
    assert math.isfinite(float(rest.log_likelihood.sum()))
