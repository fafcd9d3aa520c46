"""Tests of prognos_torch.prognosis.paths: recursive multi-step prediction with uncertainty
(paper 002 Eq. 11-14).

References are independent: hand loops, the closed-form AR(m) predictor (psi weights), Monte
Carlo moments and a known failure time.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from torch import nn

from prognos_torch.core.belief import GaussianBelief
from prognos_torch.core.model import StateSpaceModel
from prognos_torch.datasets.windows import embed
from prognos_torch.filters import ekf, sckf, srukf
from prognos_torch.learners import ELM
from prognos_torch.prognosis import (
    GaussianPaths,
    RecursivePaths,
    SamplePaths,
    fault_probability,
    fault_probability_gaussian,
    gaussian_paths,
    learner_transition_model,
    particle_paths,
    predict_paths,
    recursive_predict,
    rul_distribution,
)

sys.path.insert(0, str(Path(__file__).parent))
from _prognosis_helpers import F64, _gen, _learner  # noqa: E402


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


def test_bad_prediction_arguments_raise_clear_errors():
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


def test_settle_reaches_the_fixed_points_of_a_linear_recursion():
    # x_{k+1} = A x_k + b with spectral radius < 1 settles at (I - A)^-1 b from any start; a
    # second, decoupled component with a = 1.5 diverges, and a start at its fixed point stays
    from prognos_torch.prognosis import settle

    A = torch.tensor([[0.5, 0.2], [0.1, 0.3]], dtype=torch.float64)
    b = torch.tensor([1.0, -2.0], dtype=torch.float64)
    model = StateSpaceModel(
        f=lambda x, u, k: x @ A.mT + b,
        h=lambda x, u, k: x[..., :1],
        state_dim=2,
        obs_dim=1,
        chol_Q=torch.eye(2, dtype=torch.float64),
        chol_R=torch.eye(1, dtype=torch.float64),
    )
    starts = torch.tensor([[0.0, 0.0], [10.0, -5.0], [-3.0, 7.0]], dtype=torch.float64)
    fixed = torch.linalg.solve(torch.eye(2, dtype=torch.float64) - A, b)
    end = settle(model, starts, 200)
    assert end.shape == (3, 2)
    torch.testing.assert_close(end, fixed.expand(3, 2), rtol=0, atol=1e-12)
    # the same as the hand loop, exactly, for few steps and a time offset
    x = starts
    for k in range(5, 8):
        x = model.transition(x, None, k + 1)
    assert torch.equal(settle(model, starts, 3, k0=5), x)
    grow = StateSpaceModel(
        f=lambda x, u, k: 1.5 * x - 0.5,
        h=lambda x, u, k: x,
        state_dim=1,
        obs_dim=1,
        chol_Q=torch.eye(1, dtype=torch.float64),
        chol_R=torch.eye(1, dtype=torch.float64),
    )
    end = settle(grow, torch.tensor([[1.0], [1.5]], dtype=torch.float64), 20)
    assert float(end[0, 0]) == 1.0  # the fixed point 0.5 / 0.5
    assert float(end[1, 0]) == 1.0 + 0.5 * 1.5**20


def test_settle_refuses_bad_input():
    from prognos_torch.prognosis import settle

    model = StateSpaceModel(
        f=lambda x, u, k: x,
        h=lambda x, u, k: x,
        state_dim=2,
        obs_dim=2,
        chol_Q=torch.eye(2, dtype=torch.float64),
        chol_R=torch.eye(2, dtype=torch.float64),
    )
    with pytest.raises(ValueError, match="steps"):
        settle(model, torch.zeros(3, 2, dtype=torch.float64), 0)
    with pytest.raises(ValueError, match="states"):
        settle(model, torch.zeros(3, 4, dtype=torch.float64), 5)
    with pytest.raises(TypeError, match="model"):
        settle(lambda x: x, torch.zeros(3, 2, dtype=torch.float64), 5)
