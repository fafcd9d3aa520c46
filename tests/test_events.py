"""Batched simulation to an event (prognosis.events) against per-sample loops, closed forms and
progpy's UnscentedKalmanFilter + MonteCarlo on its BatteryCircuit (test-only oracle)."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
import torch
from scipy import stats

from prognos_torch.core import GaussianBelief, StateSpaceModel
from prognos_torch.filters import run, sir, ukf
from prognos_torch.prognosis import sample_belief, simulate_to_event
from prognos_torch.systems.battery import (
    LOAD_CURRENTS,
    LOAD_TIMES,
    BatteryCircuitParams,
    battery_circuit_model,
    battery_eod_event,
    load_controls,
    simulate_battery,
)

t = lambda a: torch.as_tensor(a, dtype=torch.float64)  # noqa: E731


def ramp_model(noise_std=0.0):
    """x = [level, rate]: level += rate * u, rate constant; per-sample f (vmapped)."""

    def f(x, u, k):
        return torch.stack([x[0] + x[1] * u[0], x[1]])

    return StateSpaceModel(
        f=f,
        h=lambda x, u, k: x[:1],
        state_dim=2,
        obs_dim=1,
        chol_Q=t(np.diag([noise_std, 0.0])),
        chol_R=t([[1.0]]),
        control_dim=1,
    )


def loop_reference(x0, us, thr, horizon, eps=None, noise_std=0.0):
    """Per-sample Python loop: first step with level >= thr (1-based), -1 if none."""
    x0 = x0.numpy().reshape(-1, 2)
    out = np.full(len(x0), -1)
    finals = x0.copy()
    for i, (lev, rate) in enumerate(x0):
        for j in range(horizon):
            lev = lev + rate * float(us[j, 0])
            if eps is not None:
                lev = lev + noise_std * float(eps[j].reshape(-1, 2)[i, 0])
            if lev >= thr:
                out[i] = j + 1
                finals[i] = (lev, rate)
                break
        else:
            finals[i] = (lev, rate)
    return out, finals


def test_first_passage_equals_per_sample_loop_with_censoring_and_weights():
    g = torch.Generator().manual_seed(0)
    B, N, H, thr = 3, 40, 60, 10.0
    x0 = torch.stack([torch.zeros(B, N), 0.5 + torch.rand(B, N, generator=g)], -1).double()
    x0[0, :5, 1] = 0.01  # never reach 10 within 60 steps: censored
    us = 0.5 + torch.rand(H, 1, generator=g).double()
    w = torch.rand(B, N, generator=g).double()
    w = w / w.sum(-1, keepdim=True)
    event = lambda x: x[..., 0] >= thr  # noqa: E731
    ref, finals = loop_reference(x0, us, thr, H)
    for chunk in (1, 7, 64):
        res = simulate_to_event(
            ramp_model(), x0, event, controls=us, weights=w, t0=5.0, dt=0.5, chunk=chunk
        )
        fp = res.rul.first_passage.reshape(-1).numpy()
        np.testing.assert_array_equal(fp, ref)
        np.testing.assert_allclose(res.final_state.reshape(-1, 2).numpy(), finals, rtol=1e-14)
        assert res.steps_run == H
        cens = (ref.reshape(B, N) < 0).astype(float)
        np.testing.assert_allclose(res.censored_mass.numpy(), (w.numpy() * cens).sum(-1))
        toe = res.time_of_event.numpy().reshape(-1)
        np.testing.assert_allclose(toe[ref > 0], 5.0 + 0.5 * ref[ref > 0])
        assert np.isnan(toe[ref < 0]).all()
    # batch element 1 has no censored mass: its mean is the weighted mean of the event times
    mean1 = float((w[1].numpy() * (5.0 + 0.5 * ref.reshape(B, N)[1])).sum())
    assert math.isclose(float(res.mean[1]), mean1, rel_tol=1e-12)
    assert math.isnan(float(res.mean[0]))


def test_stops_when_every_sample_has_met_the_event():
    x0 = t([[0.0, 1.0], [0.0, 2.0]])
    res = simulate_to_event(
        ramp_model(), x0, lambda x: x[..., 0] >= 5.0, controls=torch.ones(1000, 1).double()
    )
    assert res.rul.first_passage.tolist() == [5, 3]
    assert res.steps_run == 32  # one chunk of the default size
    assert float(res.censored_mass) == 0.0


def test_process_noise_is_drawn_step_by_step_whatever_the_chunk():
    g0 = torch.Generator().manual_seed(1)
    N, H, std = 30, 80, 0.3
    x0 = torch.stack([torch.zeros(N), 0.1 + 0.2 * torch.rand(N, generator=g0)], -1).double()
    us = torch.ones(H, 1).double()
    ge = torch.Generator().manual_seed(9)
    eps = [torch.randn(N, 2, generator=ge, dtype=torch.float64) for _ in range(H)]
    ref, _ = loop_reference(x0, us, 6.0, H, eps=eps, noise_std=std)
    for chunk in (1, 13, 80):
        res = simulate_to_event(
            ramp_model(std),
            x0,
            lambda x: x[..., 0] >= 6.0,
            controls=us,
            process_noise=True,
            generator=torch.Generator().manual_seed(9),
            chunk=chunk,
        )
        np.testing.assert_array_equal(res.rul.first_passage.numpy(), ref)


def test_active_only_gives_the_same_passages_and_advances_only_the_open_samples():
    g0 = torch.Generator().manual_seed(3)
    B, N, H, std = 2, 25, 200, 0.3
    rate = 0.02 + 0.3 * torch.rand(B, N, generator=g0)
    x0 = torch.stack([torch.zeros(B, N), rate], -1).double()
    seen = []

    def f(x, u, k):  # batched: x (rows, 2) or (B, N, 2)
        seen.append(x.shape[:-1].numel())
        return torch.stack([x[..., 0] + x[..., 1], x[..., 1]], -1)

    model = StateSpaceModel(
        f=f,
        h=lambda x, u, k: x[..., :1],
        state_dim=2,
        obs_dim=1,
        chol_Q=t(np.diag([std, 0.0])),
        chol_R=t([[1.0]]),
        batched=True,
    )
    ev = lambda x: x[..., 0] >= 6.0  # noqa: E731
    out = {}
    for flag in (False, True):
        seen.clear()
        out[flag] = simulate_to_event(
            model,
            x0,
            ev,
            max_steps=H,
            process_noise=True,
            chunk=8,
            active_only=flag,
            generator=torch.Generator().manual_seed(9),
        )
        out[flag, "rows"] = sum(seen)
    a, b = out[False], out[True]
    np.testing.assert_array_equal(a.rul.first_passage.numpy(), b.rul.first_passage.numpy())
    torch.testing.assert_close(a.final_state, b.final_state, rtol=0, atol=0)
    assert a.steps_run == b.steps_run
    # the open samples only: the row count equals the sum over chunks of the open samples
    fp = a.rul.first_passage.reshape(-1)
    open_rows = sum(
        8 * int(((fp < 0) | (fp > s)).sum()) if s else 8 * B * N for s in range(0, a.steps_run, 8)
    )
    assert out[True, "rows"] == open_rows < out[False, "rows"] == a.steps_run * B * N
    with pytest.raises(ValueError, match="active_only"):
        simulate_to_event(
            ramp_model(), x0, ev, controls=torch.ones(H, B, 1).double(), active_only=True
        )


def test_sample_belief_moments():
    m = t([1.0, -2.0, 0.5])
    A = t([[1.0, 0.0, 0.0], [0.5, 2.0, 0.0], [-0.3, 0.1, 0.2]])
    xs = sample_belief(GaussianBelief(m, A), 200_000, torch.Generator().manual_seed(0))
    assert xs.shape == (200_000, 3)
    np.testing.assert_allclose(xs.mean(0).numpy(), m.numpy(), atol=0.02)
    np.testing.assert_allclose(np.cov(xs.numpy().T), (A @ A.T).numpy(), atol=0.03)


def test_bad_arguments():
    model, ev = ramp_model(), (lambda x: x[..., 0] > 1.0)
    x0 = t([[0.0, 1.0]])
    us = torch.ones(10, 1).double()
    with pytest.raises(ValueError, match=r"x0 must be a tensor of shape \(\.\.\., N, 2\)"):
        simulate_to_event(model, t([0.0, 1.0]), ev, controls=us)
    with pytest.raises(ValueError, match="controls are required"):
        simulate_to_event(model, x0, ev)
    with pytest.raises(ValueError, match=r"controls must have shape"):
        simulate_to_event(model, x0, ev, controls=torch.ones(10, 2).double())
    with pytest.raises(ValueError, match="fewer than max_steps"):
        simulate_to_event(model, x0, ev, controls=us, max_steps=11)
    with pytest.raises(TypeError, match="generator"):
        simulate_to_event(model, x0, ev, controls=us, process_noise=True)
    with pytest.raises(ValueError, match="event must return a bool tensor"):
        simulate_to_event(model, x0, lambda x: x[..., 0], controls=us)
    with pytest.raises(ValueError, match="weights must sum to one"):
        simulate_to_event(model, x0, ev, controls=us, weights=t([0.5]))


def test_particle_filter_honours_a_control_shared_by_the_batch():
    # a (T, p) control and the same control expanded to (T, B, p) give the same filter
    model = battery_circuit_model()
    sim = simulate_battery(20, 2, generator=torch.Generator().manual_seed(0))
    p = BatteryCircuitParams()
    P0 = torch.diag(t([0.1, 100.0, 0.1, 0.1])).expand(2, 4, 4)
    b0 = GaussianBelief.from_cov(t(p.x0).expand(2, 4), P0)
    shared = sim.u[:, 0]
    a = sir(300).run(model, b0, sim.y, shared, generator=torch.Generator().manual_seed(1))
    b = sir(300).run(model, b0, sim.y, sim.u, generator=torch.Generator().manual_seed(1))
    assert torch.equal(a.means, b.means)
    zero = sir(300).run(model, b0, sim.y, 0 * sim.u, generator=torch.Generator().manual_seed(1))
    assert float((zero.means[-1, :, 1] - a.means[-1, :, 1]).abs().min()) > 10.0  # ~2 A x 20 s


# --------------------------------------------------------------------------- progpy side by side
pp_models = pytest.importorskip("progpy.models")
from progpy.loading import Piecewise  # noqa: E402
from progpy.predictors import MonteCarlo  # noqa: E402
from progpy.state_estimators import UnscentedKalmanFilter  # noqa: E402
from progpy.uncertain_data import MultivariateNormalDist, UnweightedSamples  # noqa: E402

T_START, K_EST = 2400, 300  # estimate over [2400, 2700] s, predict EOD (about 3005 s) from 2700
P0 = np.diag([0.1, 400.0, 0.1, 0.1])


@pytest.fixture(scope="module")
def scenario():
    """Truth from full charge, noisy (t, v) from 2400 s; progpy's UKF and ours on them."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        pp = pp_models.BatteryCircuit(process_noise=1e-3**0.5)
        pp_quiet = pp_models.BatteryCircuit()
    load = Piecewise(pp.InputContainer, list(LOAD_TIMES), {"i": list(LOAD_CURRENTS)})
    warm = simulate_battery(T_START, noise=False)
    x_start = warm.x[-1, 0]
    u = load_controls(steps=K_EST, t0=float(T_START))
    sim = simulate_battery(K_EST, x0=x_start, u=u, generator=torch.Generator().manual_seed(5))
    ys = sim.y[:, 0]
    est = UnscentedKalmanFilter(
        pp, MultivariateNormalDist(pp.states, x_start.numpy(), P0), t0=float(T_START)
    )
    ref_m, ref_P = [], []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for k in range(1, K_EST + 1):
            z = {"t": float(ys[k - 1, 0]), "v": float(ys[k - 1, 1])}
            est.estimate(float(T_START + k), {"i": float(u[k - 1, 0])}, z)
            ref_m.append(est.filter.x.copy())
            ref_P.append(est.filter.P.copy())
    model = battery_circuit_model(1.0)
    b0 = GaussianBelief.from_cov(x_start, t(P0))
    tr = run(ukf(alpha=1.0, beta=0.0, kappa=-1.0), model, b0, ys, u)
    return {
        "pp": pp,
        "pp_quiet": pp_quiet,
        "load": load,
        "est": est,
        "ref_m": np.array(ref_m),
        "ref_P": np.array(ref_P),
        "model": model,
        "b0": b0,
        "ys": ys,
        "u": u,
        "traj": tr,
        "t_pred": float(T_START + K_EST),
    }


def test_ukf_equals_progpy_ukf(scenario):
    # progpy's UKF is filterpy's with Merwe points alpha=1, beta=0, kappa=-1 and Q = R = 1e-3 I
    tr = scenario["traj"]
    np.testing.assert_allclose(tr.means.numpy(), scenario["ref_m"], rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(tr.covs.numpy(), scenario["ref_P"], rtol=1e-8, atol=1e-10)


def _progpy_eod(sc, state, quiet, **kw):
    m = sc["pp_quiet"] if quiet else sc["pp"]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = MonteCarlo(m).predict(state, sc["load"], dt=1.0, t0=sc["t_pred"], **kw)
    return np.array([s["EOD"] for s in res.time_of_event], dtype=float)


def test_eod_per_sample_equals_progpy_monte_carlo(scenario):
    # the same state samples, noise-free propagation: every sample's EOD time is the same
    tr = scenario["traj"]
    post = GaussianBelief(tr.means[-1], tr.chols[-1])
    xs = sample_belief(post, 12, torch.Generator().manual_seed(2))
    states = scenario["pp"].states
    samples = UnweightedSamples([dict(zip(states, row)) for row in xs.numpy()])
    ref = _progpy_eod(scenario, samples, quiet=True)
    U = load_controls(steps=2000, t0=scenario["t_pred"])
    ours = simulate_to_event(
        scenario["model"], xs, battery_eod_event(), controls=U, t0=scenario["t_pred"]
    )
    np.testing.assert_array_equal(ours.time_of_event.numpy(), ref)
    assert float(ours.censored_mass) == 0.0


def test_eod_distribution_agrees_with_progpy_within_monte_carlo_tolerance(scenario):
    """UKF posterior at 2700 s, process noise sqrt(1e-3) per step on both sides.

    Tolerance (Monte Carlo): |mean_a - mean_b| <= 4 sqrt(s_a^2/n_a + s_b^2/n_b), and a two-sample
    Kolmogorov-Smirnov test does not reject equality at the 0.1 % level.
    """
    np.random.seed(11)  # noqa: NPY002 (progpy draws from the global generator)
    ref = _progpy_eod(scenario, scenario["est"].x, quiet=False, n_samples=40)
    tr = scenario["traj"]
    post = GaussianBelief(tr.means[-1], tr.chols[-1])
    g = torch.Generator().manual_seed(3)
    xs = sample_belief(post, 400, g)
    U = load_controls(steps=2000, t0=scenario["t_pred"])
    ours = simulate_to_event(
        scenario["model"],
        xs,
        battery_eod_event(),
        controls=U,
        t0=scenario["t_pred"],
        process_noise=True,
        generator=g,
    )
    a = ours.time_of_event.numpy()
    assert not np.isnan(a).any()
    se = math.sqrt(a.var(ddof=1) / len(a) + ref.var(ddof=1) / len(ref))
    assert abs(a.mean() - ref.mean()) <= 4 * se, (a.mean(), ref.mean(), se)
    assert stats.ks_2samp(a, ref).pvalue > 1e-3
    assert 2900 < a.mean() < 3100 and a.std() > 1.0  # a real spread, around progpy's EOD


def test_particle_filter_eod_beside_the_ukf(scenario):
    # bootstrap PF on the same data; its weighted particles go straight into the prediction
    pf = sir(3000).run(
        scenario["model"],
        scenario["b0"],
        scenario["ys"],
        scenario["u"],
        generator=torch.Generator().manual_seed(4),
    )
    w = pf.final.log_weights.exp()
    U = load_controls(steps=2000, t0=scenario["t_pred"])
    event = battery_eod_event()
    res_pf = simulate_to_event(
        scenario["model"], pf.final.particles, event, controls=U, weights=w, t0=scenario["t_pred"]
    )
    tr = scenario["traj"]
    xs = sample_belief(
        GaussianBelief(tr.means[-1], tr.chols[-1]), 3000, torch.Generator().manual_seed(5)
    )
    res_ukf = simulate_to_event(scenario["model"], xs, event, controls=U, t0=scenario["t_pred"])
    spread = float(res_ukf.time_of_event.std())
    assert abs(float(res_pf.median) - float(res_ukf.median)) <= 3.0 + 0.5 * spread
    q05, q95 = res_pf.quantile([0.05, 0.95]).tolist()
    u05, u95 = res_ukf.quantile([0.05, 0.95]).tolist()
    assert q05 <= float(res_ukf.median) <= q95 and u05 <= float(res_pf.median) <= u95
