"""Tests of prognos_torch.prognosis.forecast: learners as m-order transition models (paper 002
Eq. 15-26), recursive multi-step prediction with uncertainty (Eq. 11-14), and forecasted
measurements for n-step-ahead fault prediction (paper 000 Sec. 5).

References are independent: central finite differences, paper 002 Eq. 25 written out, hand loops,
the closed-form AR(m) predictor (psi weights), per-run ELM.init_online / partial_fit, Monte Carlo
moments, and the real-time filter itself (an oracle forecaster must reproduce it).
"""

from __future__ import annotations

import copy
import math

import numpy as np
import pytest
import torch
from torch import nn
from torch.func import vmap

from prognos_torch.core.belief import GaussianBelief
from prognos_torch.core.model import StateSpaceModel
from prognos_torch.datasets.windows import embed
from prognos_torch.filters import ekf, run, sckf, srukf, stsckf
from prognos_torch.learners import ANFIS, ELM, LSSVR
from prognos_torch.prognosis import fault_probability, fault_probability_gaussian, rul_distribution
from prognos_torch.prognosis.forecast import (
    GaussianPaths,
    MeasurementForecaster,
    RecursivePaths,
    SamplePaths,
    gaussian_paths,
    learner_transition_model,
    particle_paths,
    predict_fault_parameter,
    predict_paths,
    recursive_predict,
    rolling_fault_prediction,
    ros_elm_forecast,
    ros_elm_init,
    ros_elm_update,
)

F64 = torch.float64


def _gen(seed: int) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def _series(T: int = 120, seed: int = 0) -> torch.Tensor:
    t = torch.arange(T, dtype=F64)
    return (
        torch.sin(0.15 * t)
        + 0.3 * torch.cos(0.05 * t)
        + 0.02 * torch.randn(T, generator=_gen(seed), dtype=F64)
    )


def _learner(kind: str, m: int = 4):
    X, y = embed(_series(), m)
    if kind == "elm":
        return ELM(m, 15, generator=_gen(1)).fit_ridge(X, y, 1e-6), X
    if kind == "lssvr":
        return LSSVR("rbf", sigma=0.8, C=50.0).fit(X, y), X
    if kind == "anfis":
        return ANFIS(m, 2).init_premises(X).init_consequents_lstsq(X, y, 1e-6), X
    raise AssertionError(kind)


def _fd_jacobian(model: StateSpaceModel, x: torch.Tensor, eps: float = 1e-6) -> torch.Tensor:
    """Central differences of the (noise-free) transition at each row of ``x`` ``(B, n)``."""
    cols = []
    for j in range(x.shape[-1]):
        e = torch.zeros_like(x)
        e[:, j] = eps
        cols.append(
            (model.transition(x + e, None, 1) - model.transition(x - e, None, 1)) / (2 * eps)
        )
    return torch.stack(cols, dim=-1)


# =============================================================================== learner as model
@pytest.mark.parametrize(
    "kind,jacobian",
    [
        ("elm", "autograd"),
        ("elm", "engine"),
        ("lssvr", "autograd"),
        ("lssvr", "engine"),
        ("lssvr", "input_gradient"),
        ("anfis", "autograd"),
        ("anfis", "engine"),
    ],
)
def test_transition_jacobian_matches_finite_differences(kind, jacobian):
    learner, X = _learner(kind)
    model = learner_transition_model(learner, 4, 0.01, 0.02, jacobian=jacobian)
    x = X[::17][:6] + 0.05 * torch.randn(6, 4, generator=_gen(2), dtype=F64)
    J = model.transition_jacobian(x, None, 1)
    assert J.shape == (6, 4, 4)
    torch.testing.assert_close(J, _fd_jacobian(model, x), rtol=1e-6, atol=1e-8)
    # batch dims are carried through
    J2 = model.transition_jacobian(x.reshape(2, 3, 4), None, 1)
    torch.testing.assert_close(J2.reshape(6, 4, 4), J)
    # the state transition shifts the window and appends the learner's prediction (Eq. 18-19)
    fx = model.transition(x, None, 1)
    torch.testing.assert_close(fx[:, :3], x[:, 1:])
    torch.testing.assert_close(fx[:, 3], learner(x)[:, 0].detach())
    torch.testing.assert_close(model.observe(x, None, 1), x[:, 3:])


def test_lssvr_rbf_jacobian_is_paper_002_eq_20_to_26():
    lssvr, X = _learner("lssvr")
    model = learner_transition_model(lssvr, 4, 0.01, 0.02)  # autograd route, default
    P = X[5:40:7]
    J = model.transition_jacobian(P, None, 1)
    # Eq. 25 written out: sum_i alpha_i exp(-|P_s - P_i|^2 / (2 sigma^2)) (-1/sigma^2) (P_s - P_i)
    sv = lssvr.support_vectors.numpy()
    alpha = lssvr.alpha.detach().numpy()[:, 0]
    sig2 = float(lssvr.sigma) ** 2
    eq25 = []
    for p in P.numpy():
        d = p[None, :] - sv
        k = np.exp(-(d * d).sum(1) / (2 * sig2))
        eq25.append(((alpha * k)[:, None] * (-1.0 / sig2) * d).sum(0))
    eq25 = torch.tensor(np.array(eq25))
    torch.testing.assert_close(J[:, -1, :], eq25, rtol=1e-9, atol=1e-12)  # Eq. 21/25
    torch.testing.assert_close(J[:, -1, :], lssvr.input_gradient(P)[:, 0, :].detach())
    torch.testing.assert_close(J[:, -1, -1], eq25[:, -1])  # Eq. 23/26: df / dx_s
    shift = torch.eye(4, dtype=F64)[1:].expand(P.shape[0], 3, 4)
    torch.testing.assert_close(J[:, :-1, :], shift)  # companion structure


def test_transition_model_is_vmap_friendly_and_noise_structure():
    for kind in ("elm", "lssvr", "anfis"):
        learner, X = _learner(kind)
        model = learner_transition_model(learner, 4, 0.03, 0.02)
        x = X[:7]
        per_sample = vmap(lambda xi, mdl=model: mdl.f(xi, None, 1))(x)
        torch.testing.assert_close(per_sample, model.transition(x, None, 1))
        assert not model.transition(x, None, 1).requires_grad  # detached learner parameters
    noise = model.noise(1)
    want = torch.zeros(4, 4, dtype=F64)
    want[-1, -1] = 0.03  # Eq. 19: noise on the new element only
    torch.testing.assert_close(noise.chol_Q, want)
    torch.testing.assert_close(noise.chol_R, torch.full((1, 1), 0.02, dtype=F64))
    full = torch.diag(torch.tensor([1e-3, 1e-3, 1e-3, 0.03], dtype=F64))
    torch.testing.assert_close(
        learner_transition_model(learner, 4, full, 0.02).noise(1).chol_Q, full
    )


def test_transition_model_sees_online_updates():
    X, y = embed(_series(), 3)
    elm = ELM(3, 20, generator=_gen(4)).init_online(X[:40], y[:40], 1e-4)
    model = learner_transition_model(elm, 3, 0.01, 0.01)
    before = model.transition(X[50:52], None, 1)[:, -1]
    elm.partial_fit(X[40:80], y[40:80])
    after = model.transition(X[50:52], None, 1)[:, -1]
    torch.testing.assert_close(after, elm(X[50:52])[:, 0].detach())
    assert not torch.allclose(before, after)


# =============================================================================== recursion
def test_recursive_prediction_equals_hand_loop():
    for kind in ("elm", "lssvr", "anfis"):
        learner, X = _learner(kind)
        windows = X[[10, 30, 60]]  # (3, 4)
        got = recursive_predict(learner, windows, 7)
        for b in range(3):
            w = [float(v) for v in windows[b]]
            want = []
            for _ in range(7):
                nxt = float(learner(torch.tensor(w[-4:], dtype=F64).unsqueeze(0))[0, 0].detach())
                want.append(nxt)
                w.append(nxt)
            torch.testing.assert_close(got[b].detach(), torch.tensor(want, dtype=F64))
        model = learner_transition_model(learner, 4, 0.01, 0.01)
        torch.testing.assert_close(recursive_predict(model, windows, 7), got.detach())
        paths = predict_paths(learner, windows, 7)
        assert isinstance(paths, RecursivePaths) and paths.horizon == 7
        torch.testing.assert_close(paths.mean, got)


def _ar_learner(coef, c):
    """nn.Linear on the window [x_{s-m+1}, ..., x_s]: weight = AR coefficients, oldest first."""
    m = len(coef)
    lin = nn.Linear(m, 1, dtype=F64)
    with torch.no_grad():
        lin.weight.copy_(torch.tensor(coef[::-1], dtype=F64).unsqueeze(0))
        lin.bias.fill_(c)
    return lin


def _ar_closed_form(coef, c, window, sigma, H):
    """AR(m) H-step predictor: recursion for the mean, psi weights for the variance."""
    a = np.asarray(coef, dtype=float)  # a_1 .. a_m
    m = len(a)
    hist = list(np.asarray(window, dtype=float))
    mean = []
    for _ in range(H):
        nxt = c + sum(a[i] * hist[-1 - i] for i in range(m))
        mean.append(nxt)
        hist.append(nxt)
    psi = [1.0]
    for i in range(1, H):
        psi.append(sum(a[l - 1] * psi[i - l] for l in range(1, min(i, m) + 1)))
    var = [sigma**2 * sum(p * p for p in psi[: j + 1]) for j in range(H)]
    return np.array(mean), np.array(var)


@pytest.mark.parametrize("filt", [sckf(), ekf(), srukf()], ids=["sckf", "ekf", "srukf"])
@pytest.mark.parametrize("learner_kind", ["linear", "elm_linear"])
def test_gaussian_prediction_equals_closed_form_ar(filt, learner_kind):
    coef, c, sigma, r = [0.6, 0.25, -0.2], 0.1, 0.07, 0.03
    m, H = 3, 8
    if learner_kind == "linear":
        learner = _ar_learner(coef, c)
    else:  # an ELM with linear activation and L = m + 1 nodes spans the affine maps exactly
        Xr = torch.randn(30, m, generator=_gen(7), dtype=F64)
        yr = Xr @ torch.tensor(coef[::-1], dtype=F64) + c
        learner = ELM(m, m + 1, activation="linear", generator=_gen(8)).fit_ridge(Xr, yr, 0.0)
    window = torch.tensor([0.4, -0.1, 0.3], dtype=F64)
    belief = GaussianBelief(window, 1e-9 * torch.eye(m, dtype=F64))  # a known window
    model = learner_transition_model(learner, m, sigma, r)
    gp = predict_paths(model, belief, H, filt=filt)
    assert isinstance(gp, GaussianPaths)
    mean, var = _ar_closed_form(coef, c, window.numpy(), sigma, H)
    torch.testing.assert_close(gp.state_mean[:, -1], torch.tensor(mean), rtol=1e-9, atol=1e-10)
    torch.testing.assert_close(gp.state_std[:, -1] ** 2, torch.tensor(var), rtol=1e-8, atol=1e-12)
    torch.testing.assert_close(gp.mean, torch.tensor(mean), rtol=1e-9, atol=1e-10)
    torch.testing.assert_close(gp.std**2, torch.tensor(var) + r * r, rtol=1e-8, atol=1e-12)
    z = 1.959963984540054
    torch.testing.assert_close(gp.upper - gp.lower, 2 * z * gp.std)
    # learner passed directly (the model is built from chol_Q / chol_R)
    gp2 = predict_paths(learner, belief, H, filt=filt, chol_Q=sigma, chol_R=r)
    torch.testing.assert_close(gp2.mean, gp.mean)


def test_particle_paths_match_gaussian_propagation_on_linear_model():
    coef, c, sigma = [0.9, -0.3], 0.05, 0.1
    m, H, N = 2, 6, 40000
    model = learner_transition_model(_ar_learner(coef, c), m, sigma, 0.01)
    P0 = torch.tensor([[0.04, 0.01], [0.01, 0.02]], dtype=F64)
    belief = GaussianBelief.from_cov(torch.tensor([0.5, 0.8], dtype=F64), P0)
    gp = gaussian_paths(sckf(), model, belief, H)
    g_mean, g_std = gp.state_mean[:, -1], gp.state_std[:, -1]
    sp = predict_paths(model, belief, H, method="particle", n_particles=N, generator=_gen(11))
    assert isinstance(sp, SamplePaths) and sp.samples.shape == (N, H)
    se = g_std / math.sqrt(N)
    assert bool(((sp.mean - g_mean).abs() < 4 * se).all())
    assert bool(((sp.std / g_std - 1).abs() < 4 * math.sqrt(0.5 / N) + 1e-3).all())
    # importance-weighted particles from a wider proposal: the weights must be used
    S = belief.chol * 1.5
    e = torch.randn(N, m, generator=_gen(12), dtype=F64)
    parts = belief.mean + e @ S.mT
    d_p = torch.linalg.solve_triangular(belief.chol, (parts - belief.mean).mT, upper=False)
    logw = -0.5 * (d_p**2).sum(0) + 0.5 * (e**2).sum(1)  # log N(x; P) - log N(x; 2.25 P) + const
    w = torch.softmax(logw, 0)
    ess = 1.0 / (w * w).sum()
    spw = particle_paths(model, parts, H, generator=_gen(13), weights=w)
    se_w = g_std / ess.sqrt()
    assert bool(((spw.mean - g_mean).abs() < 4 * se_w).all())
    assert bool(((spw.std / g_std - 1).abs() < 4 * torch.sqrt(0.5 / ess) + 1e-3).all())
    # the samples plug into the fault probability of paper 002 (vs its Gaussian counterpart)
    thr = float(g_mean[-1] + 0.5 * g_std[-1])
    p_mc = fault_probability(sp.samples, thr, sp.weights)
    p_g = fault_probability_gaussian(g_mean, g_std, thr)
    assert float((p_mc - p_g).abs().max()) < 0.01
    # weighted quantile band: ~95 % of the samples inside, per step
    inside = ((sp.samples >= sp.lower) & (sp.samples <= sp.upper)).double().mean(0)
    assert bool(((inside - 0.95).abs() < 0.01).all())


def test_particle_paths_batched_over_runs_with_per_run_noise():
    model = learner_transition_model(_ar_learner([0.5], 0.0), 1, 0.2, 0.1)
    # per-run process noise factors (batch dims of the belief) and a deterministic start
    SQ = torch.tensor([0.1, 0.4], dtype=F64).reshape(2, 1, 1)
    model_b = StateSpaceModel(model.f, model.h, 1, 1, SQ, model.chol_R, batched=True)
    start = torch.tensor([[1.0], [1.0]], dtype=F64)
    sp = predict_paths(model_b, start, 3, method="particle", n_particles=20000, generator=_gen(3))
    assert sp.samples.shape == (2, 20000, 3)
    # first step: N(0.5, q_r^2) per run
    torch.testing.assert_close(sp.std[:, 0], SQ.reshape(2), rtol=0.03, atol=0.0)
    torch.testing.assert_close(sp.mean[:, 0], torch.full((2,), 0.5, dtype=F64), atol=0.01, rtol=0)


def test_rul_expectation_converges_to_known_failure_time():
    b, thr, m = 0.03, 20.0, 2
    t_fail = math.ceil(math.log(thr) / b)  # first t with exp(b t) >= thr: 100
    origins = (25, 45, 65, 85)
    errors = np.zeros((6, len(origins)))
    for seed in range(6):
        t = torch.arange(1, t_fail + 1, dtype=F64)
        x = torch.exp(b * t) * (1 + 0.01 * torch.randn(t_fail, generator=_gen(seed), dtype=F64))
        for i, k in enumerate(origins):  # more data at each prediction time
            X, y = embed(x[:k], m)
            elm = ELM(m, m + 1, activation="linear", generator=_gen(0)).fit_ridge(X, y, 0.0)
            q = float((elm(X)[:, 0] - y).detach().std())
            sp = predict_paths(
                elm,
                x[k - m : k],
                150,
                method="particle",
                chol_Q=q,
                chol_R=q,
                n_particles=300,
                generator=_gen(100 + k),
            )
            rd = rul_distribution(sp.samples, thr, sp.weights)
            assert float(rd.censored_mass) == 0.0
            errors[seed, i] = abs(float(rd.expectation) - (t_fail - k))
    mean_err = errors.mean(0)
    assert all(mean_err[i + 1] < mean_err[i] for i in range(len(origins) - 1)), mean_err
    assert mean_err[-1] < 1.5 and mean_err[0] > 3 * mean_err[-1]


# =============================================================================== forecaster
def test_batched_ros_elm_forecaster_equals_per_run_elms():
    R, C, p, L, lam = 3, 2, 3, 10, 1e-3
    T = 40
    t = torch.arange(T, dtype=F64)
    z = torch.stack(
        [
            torch.stack([torch.sin(0.2 * t + r) + 0.1 * r, 0.5 * torch.cos(0.1 * t - r)], -1)
            for r in range(R)
        ],
        dim=1,
    )  # (T, R, C)
    fc = MeasurementForecaster.ros_elm(C, p=p, n_hidden=L, lam=lam, generator=_gen(9))
    fc.initialize(z[:20])
    for k in range(20, 30):
        fc.update(z[k])
    pred = fc.forecast(4)  # (4, R, C)
    assert pred.shape == (4, R, C)
    for lr in fc.learners:  # the learners are not modified
        assert float(lr.beta.detach().abs().max()) == 0.0
    for r in range(R):
        for c in range(C):
            elm = copy.deepcopy(fc.learners[c])
            X, y = embed(z[:20, r, c], p)
            elm.init_online(X, y, lam)
            for k in range(20, 30):
                elm.partial_fit(z[k - p : k, r, c], z[k, r, c].reshape(1))
            want = recursive_predict(elm, z[30 - p : 30, r, c], 4).detach()
            torch.testing.assert_close(pred[:, r, c], want, rtol=1e-7, atol=1e-9)
    # functional core = shell; states are immutable
    s0 = ros_elm_init(fc.learners, z[:20], p, lam)
    s1 = ros_elm_update(fc.learners, s0, z[20])
    assert s0.n_seen == 17 and s1.n_seen == 18
    torch.testing.assert_close(s0.window, z[17:20].movedim(0, -1))
    torch.testing.assert_close(ros_elm_forecast(fc.learners, s1, 2).shape, torch.Size([2, R, C]))


def test_static_learner_forecaster_equals_recursive_prediction():
    lssvr, X = _learner("lssvr", m=4)
    s = _series()
    fc = MeasurementForecaster([lssvr], 4, online=False).initialize(s[:50].unsqueeze(-1))
    fc.update(s[50:51])
    got = fc.forecast(5)[:, 0]
    torch.testing.assert_close(got, recursive_predict(lssvr, s[47:51], 5).detach())


class _Oracle:
    """A forecaster that returns the true future measurements (for exact wiring checks)."""

    def __init__(self, future: torch.Tensor):
        self.future = future
        self.pos = None

    @property
    def initialized(self):
        return self.pos is not None

    def copy(self):
        return copy.copy(self)

    def initialize(self, z0):
        self.pos = z0.shape[0]
        return self

    def update(self, z):
        torch.testing.assert_close(z, self.future[self.pos])
        self.pos += 1
        return self

    def forecast(self, n):
        return self.future[self.pos : self.pos + n]


def _drift_problem(T=110, R=3, onset=30, seed=0, extra=10):
    """theta: constant, then a quadratic ramp (as paper 000 Eq. 61); y = [theta, exp(theta/2)]."""
    th = torch.ones(T + extra, dtype=F64)
    for k in range(onset, T + extra):
        th[k] = th[k - 1] + 0.0004 * (k - onset)
    clean = torch.stack([th, torch.exp(0.5 * th)], -1)
    ys_all = clean.unsqueeze(1) + 0.01 * torch.randn(
        T + extra, R, 2, generator=_gen(seed), dtype=F64
    )
    model = StateSpaceModel(
        None,  # random walk theta_k = theta_{k-1} + d_k (the assistant model of paper 000)
        lambda x, u, k: torch.stack([x[0], torch.exp(0.5 * x[0])]),
        1,
        2,
        chol_Q=1e-3 * torch.eye(1, dtype=F64),
        chol_R=0.01 * torch.eye(2, dtype=F64),
    )
    init = GaussianBelief(
        torch.ones(R, 1, dtype=F64), 0.1 * torch.eye(1, dtype=F64).expand(R, 1, 1)
    )
    return th, ys_all, model, init


def test_predict_fault_parameter_with_oracle_equals_real_time_filter():
    th, ys_all, model, init = _drift_problem(T=60)
    filt = stsckf()
    k, n = 40, 5
    traj = run(filt, model, init, ys_all[: k + n])
    state = run(filt, model, init, ys_all[:k]).final
    mean0, chol0 = state.belief.mean.clone(), state.belief.chol.clone()
    oracle = _Oracle(ys_all).initialize(ys_all[:k])
    pred = predict_fault_parameter(filt, model, state, oracle, n, k, param_index=0)
    torch.testing.assert_close(pred.theta, traj.means[k + n - 1], rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(pred.means, traj.means[k:])
    torch.testing.assert_close(pred.fading_factors, traj.fading_factors[k:])
    assert pred.theta.shape == (3, 1) and pred.pseudo_measurements.shape == (n, 3, 2)
    assert torch.equal(state.belief.mean, mean0) and torch.equal(state.belief.chol, chol0)


def test_rolling_prediction_alignment_with_oracle():
    T, n, start = 70, 4, 30
    th, ys_all, model, init = _drift_problem(T=T)
    filt = stsckf()
    res = rolling_fault_prediction(
        filt, model, ys_all[:T], _Oracle(ys_all), n, start, init=init, param_index=0
    )
    full = run(filt, model, init, ys_all[:T])
    # the real-time estimate is not disturbed by the n-step runs
    torch.testing.assert_close(res.filtered, full.means, rtol=1e-12, atol=1e-12)
    assert res.origin.tolist() == list(range(start, T + 1))
    torch.testing.assert_close(res.target, res.origin + n)
    ok = res.target <= T
    torch.testing.assert_close(res.predicted[ok], full.means[res.target[ok] - 1])
    aligned = res.aligned()
    assert aligned.shape == (T + n, 3, 1)
    assert bool(torch.isnan(aligned[: start + n - 1]).all())
    torch.testing.assert_close(aligned[start + n - 1 :], res.predicted)
    assert res.fading_factors.shape == (T - start + 1, n, 3)


def test_rolling_fault_prediction_strong_tracking_beats_plain_filter_on_ramp():
    T, n, start, onset = 110, 5, 50, 30
    th, ys_all, model, init = _drift_problem(T=T, onset=onset)
    ys = ys_all[:T]
    fc = MeasurementForecaster.ros_elm(2, p=3, n_hidden=20, lam=1e-8, generator=_gen(1))
    out = {}
    for name, filt in (("sckf", sckf()), ("stsckf", stsckf())):
        res = rolling_fault_prediction(filt, model, ys, fc, n, start, init=init, param_index=0)
        truth = th[res.target - 1].unsqueeze(-1)  # theta at time t is th[t - 1]
        out[name] = float((res.predicted[..., 0] - truth).abs().mean())
        lam = res.fading_factors
        if name == "sckf":
            assert bool((lam == 1).all())
        else:
            assert float(lam.max()) > 1.0
    assert not fc.initialized  # the caller's forecaster is copied, not modified
    ramp = float(th[T + n - 1] - th[start])  # size of the drift over the prediction window
    assert out["stsckf"] < 0.5 * out["sckf"], out
    assert out["stsckf"] < 0.1 * ramp, (out, ramp)


# =============================================================================== bad inputs
def test_bad_inputs_raise_clear_errors():
    elm, X = _learner("elm")
    model = learner_transition_model(elm, 4, 0.01, 0.01)
    belief = GaussianBelief(X[0], 0.01 * torch.eye(4, dtype=F64))
    with pytest.raises(ValueError, match="horizon"):
        predict_paths(elm, X[0], 0)
    with pytest.raises(ValueError, match="horizon"):
        recursive_predict(elm, X[0], -1)
    with pytest.raises(ValueError, match="horizon"):
        gaussian_paths(sckf(), model, belief, 0)
    with pytest.raises(ValueError, match="horizon"):
        particle_paths(model, X[:5], 0, generator=_gen(0))
    with pytest.raises(ValueError, match=r"window must have shape \(\.\.\., m\) with m=4"):
        predict_paths(elm, X[0, :3], 5)
    with pytest.raises(ValueError, match="window must have shape"):
        recursive_predict(model, X[0, :3], 5)
    bad = X[0].clone()
    bad[1] = float("nan")
    with pytest.raises(ValueError, match="window contains non-finite"):
        predict_paths(elm, bad, 5)
    bad[1] = float("inf")
    with pytest.raises(ValueError, match="particles contains non-finite"):
        particle_paths(model, bad.expand(3, 4), 2, generator=_gen(0))
    with pytest.raises(TypeError, match="window must be a torch.Tensor"):
        predict_paths(elm, [0.1, 0.2, 0.3, 0.4], 5)
    with pytest.raises(ValueError, match="generator"):
        predict_paths(model, X[0], 3, method="particle", n_particles=10)
    with pytest.raises(ValueError, match="chol_Q and chol_R"):
        predict_paths(elm, belief, 3)
    with pytest.raises(ValueError, match="method"):
        predict_paths(elm, X[0], 3, method="magic")
    with pytest.raises(ValueError, match="does not match the learner's input dimension"):
        learner_transition_model(elm, 3, 0.01, 0.01)
    with pytest.raises(ValueError, match="chol_Q"):
        learner_transition_model(elm, 4, -0.1, 0.01)
    with pytest.raises(ValueError, match=r"chol_Q must be a number \(std\) or have shape"):
        learner_transition_model(elm, 4, torch.eye(3, dtype=F64), 0.01)
    with pytest.raises(ValueError, match="jacobian"):
        learner_transition_model(elm, 4, 0.01, 0.01, jacobian="numeric")
    with pytest.raises(TypeError, match="input_gradient"):
        learner_transition_model(elm, 4, 0.01, 0.01, jacobian="input_gradient")
    with pytest.raises(ValueError, match="n_out_index"):
        learner_transition_model(elm, 4, 0.01, 0.01, n_out_index=1)

    fc = MeasurementForecaster.ros_elm(2, p=3, n_hidden=8, lam=1e-3)
    with pytest.raises(RuntimeError, match="initialize"):
        fc.forecast(3)
    with pytest.raises(ValueError, match="N0 >= p \\+ 1"):
        fc.initialize(torch.zeros(3, 2, dtype=F64))
    z0 = torch.randn(20, 2, generator=_gen(0), dtype=F64)
    with pytest.raises(ValueError, match=r"z0 must have shape \(N0, \.\.\., C\) with C=2"):
        fc.initialize(z0[:, :1])
    fc.initialize(z0)
    with pytest.raises(ValueError, match="n must be a positive int"):
        fc.forecast(0)
    with pytest.raises(ValueError, match=r"z must have shape \(2,\)"):
        fc.update(torch.zeros(3, dtype=F64))
    with pytest.raises(ValueError, match="z contains non-finite"):
        fc.update(torch.tensor([0.0, float("nan")], dtype=F64))
    with pytest.raises(ValueError, match="p=4"):
        MeasurementForecaster([ELM(3, 5)], 4)

    th, ys_all, dmodel, init = _drift_problem(T=40)
    state = sckf().init(dmodel, init)
    with pytest.raises(ValueError, match="n must be a positive int"):
        predict_fault_parameter(sckf(), dmodel, state, _Oracle(ys_all).initialize(ys_all[:5]), 0, 5)
    with pytest.raises(ValueError, match=r"forecaster.forecast\(n\) must return shape"):
        predict_fault_parameter(sckf(), dmodel, state, fc, 3, 5)  # 2 channels but no run dim
    with pytest.raises(ValueError, match="start"):
        rolling_fault_prediction(sckf(), dmodel, ys_all[:40], fc, 3, 41, init=init)
    ys_bad = ys_all[:40].clone()
    ys_bad[7, 0, 1] = float("nan")
    with pytest.raises(ValueError, match="ys contains non-finite"):
        rolling_fault_prediction(sckf(), dmodel, ys_bad, fc, 3, 20, init=init)
    with pytest.raises(ValueError, match="param_index"):
        rolling_fault_prediction(sckf(), dmodel, ys_all[:40], fc, 3, 20, init=init, param_index=4)


def test_transition_model_shift_std_gives_a_nonsingular_Q():
    elm = ELM(3, 5, generator=torch.Generator().manual_seed(0))
    plain = learner_transition_model(elm, 3, 0.2, 0.1).noise(1).chol_Q
    shifted = learner_transition_model(elm, 3, 0.2, 0.1, shift_std=0.01).noise(1).chol_Q
    assert torch.equal(plain, torch.diag(torch.tensor([0.0, 0.0, 0.2], dtype=plain.dtype)))
    assert torch.equal(shifted, torch.diag(torch.tensor([0.01, 0.01, 0.2], dtype=plain.dtype)))
    with pytest.raises(ValueError, match="shift_std"):
        learner_transition_model(elm, 3, torch.eye(3, dtype=plain.dtype), 0.1, shift_std=0.01)
    with pytest.raises(ValueError, match="shift_std"):
        learner_transition_model(elm, 3, 0.2, 0.1, shift_std=-1.0)
