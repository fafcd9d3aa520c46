"""Tests of the system simulators and their state-space models (prognos_torch.systems).

References are independent: NumPy re-implementations of the paper equations, SciPy ODE
solvers and root finders, exact rational recursions (fractions.Fraction) and closed forms.
"""

from __future__ import annotations

import math
from fractions import Fraction

import numpy as np
import pytest
import torch
from scipy.integrate import solve_ivp
from scipy.optimize import fsolve
from torch.func import vmap

from prognos_torch.datasets import minmax_denormalize, minmax_normalize
from prognos_torch.systems import (
    CSTRParams,
    HSTParams,
    LorenzParams,
    ThreeTankParams,
    az2_drift,
    cstr_feed_drift,
    cstr_joint_model,
    cstr_model,
    cstr_steady_state,
    cstr_step,
    draw_run_noise,
    euler_step,
    hst_actuator_fault,
    hst_coupler_fault,
    hst_cruise_speed,
    hst_fault_model,
    hst_model,
    hst_rhs,
    lorenz_model,
    lorenz_series,
    lorenz_step,
    rk4_step,
    simulate_cstr,
    simulate_hst,
    simulate_lorenz,
    simulate_three_tank,
    three_tank_equilibrium,
    three_tank_joint_model,
    three_tank_model,
    three_tank_step,
)

F64 = torch.float64


def gen(seed=0):
    return torch.Generator().manual_seed(seed)


def assert_batch_equals_loop(simulate, runs=3, seed=7, **kw):
    """A batch of runs equals successive single runs drawn from the same generator."""
    batch = simulate(runs=runs, generator=gen(seed), **kw)
    g = gen(seed)
    singles = [simulate(runs=1, generator=g, **kw) for _ in range(runs)]
    for name in ("x", "y", "theta"):
        loop = torch.cat([getattr(s, name) for s in singles], dim=1)
        assert torch.equal(getattr(batch, name), loop), name


def assert_deterministic(simulate, **kw):
    a = simulate(runs=2, generator=gen(3), **kw)
    b = simulate(runs=2, generator=gen(3), **kw)
    c = simulate(runs=2, generator=gen(4), **kw)
    assert torch.equal(a.x, b.x) and torch.equal(a.y, b.y)
    assert not torch.equal(a.y, c.y)
    assert not torch.equal(a.y[:, 0], a.y[:, 1])  # runs differ


def iterate_model(model, x0, n_steps, u=None):
    """Noise-free x_k = f(x_{k-1}, u_k, k), y_k = h(x_k, u_k, k) via the model's batched API."""
    xs, ys, x = [x0], [], x0
    for k in range(1, n_steps + 1):
        uk = None if u is None else u[k - 1]
        x = model.transition(x, uk, k)
        xs.append(x)
        ys.append(model.observe(x, uk, k))
    return torch.stack(xs), torch.stack(ys)


def iterate_joint(model, x, theta, n_steps, n):
    """Transitions/observations of a joint model fed the true parameter trajectory."""
    xs, ys = [x[0]], []
    for k in range(1, n_steps + 1):
        z = torch.cat([x[k - 1], theta[k - 1]], -1)
        xs.append(model.transition(z, None, k)[..., :n])
        ys.append(model.observe(torch.cat([x[k], theta[k]], -1), None, k))
    return torch.stack(xs), torch.stack(ys)


# =========================================================================== common pieces
def test_rk4_step_equals_fourth_order_taylor_polynomial_on_linear_system():
    A = torch.tensor([[-1.0, 2.0, 0.3], [0.5, -3.0, 1.0], [0.0, 0.7, -0.2]], dtype=F64)
    x = torch.tensor([[1.0, -2.0, 0.5], [0.1, 0.2, 0.3]], dtype=F64)
    h = 0.3
    hA = h * A
    eye = torch.eye(3, dtype=F64)
    P = eye + hA + hA @ hA / 2 + hA @ hA @ hA / 6 + hA @ hA @ hA @ hA / 24
    torch.testing.assert_close(rk4_step(lambda z: z @ A.T, x, h), x @ P.T, rtol=1e-14, atol=1e-14)
    torch.testing.assert_close(euler_step(lambda z: z @ A.T, x, h), x @ (eye + hA).T)


def test_minmax_normalize_scales_to_unit_interval_and_inverts():
    s = torch.tensor([3.0, -1.0, 5.0, 2.0], dtype=F64)
    ns = minmax_normalize(s)
    torch.testing.assert_close(ns.values, (s + 1.0) / 6.0)
    torch.testing.assert_close(minmax_denormalize(ns.values, ns.lo, ns.hi), s)
    part = minmax_normalize(s, lo=0.0, hi=2.0)  # statistics of another part: not clipped
    torch.testing.assert_close(part.values, s / 2.0)
    with pytest.raises(ValueError, match="hi > lo"):
        minmax_normalize(torch.ones(5, dtype=F64))
    with pytest.raises(ValueError, match="non-finite"):
        minmax_normalize(torch.tensor([1.0, float("nan")]))


def test_draw_run_noise_batch_equals_successive_single_runs():
    spec = [("normal", (3,)), ("uniform", ())]
    a = draw_run_noise(gen(1), 4, 5, spec)
    g = gen(1)
    parts = [draw_run_noise(g, 1, 5, spec) for _ in range(4)]
    for j in range(2):
        assert torch.equal(a[j], torch.cat([p[j] for p in parts], 1))
    assert a[0].shape == (5, 4, 3) and a[1].shape == (5, 4)
    assert bool(((a[1] >= 0) & (a[1] < 1)).all())


# =========================================================================== CSTR
def _cstr_rhs_np(x, caf, p=None):
    p = p or CSTRParams()
    C_A, T = x
    r = p.k0 * np.exp(-p.E_R / T) * C_A
    return np.array(
        [
            -r + p.Q_F * (caf - C_A) / p.V,
            r * (-p.dH) / p.rho_Cp
            + p.Q_F * (p.T_F - T) / p.V
            + p.UA_c * (p.T_c - T) / (p.rho_Cp * p.V),
        ]
    )


def test_cstr_steady_state_matches_table_ii_scipy_and_long_simulation():
    xs = cstr_steady_state()
    ref = fsolve(lambda z: _cstr_rhs_np(z, 1.0), [0.04, 400.0], xtol=1e-13)
    np.testing.assert_allclose(xs.numpy(), ref, rtol=1e-9)
    # Table II: C_A = 0.037 mol/L, T = 402.35 K; stated tolerance 1e-4 mol/L and 5e-3 K
    assert abs(xs[0].item() - 0.0372) < 1e-4 and abs(xs[1].item() - 402.35) < 5e-3
    torch.testing.assert_close(cstr_step(xs, 1.0, CSTRParams()), xs, rtol=0, atol=1e-11)
    sim = simulate_cstr(1500, x0=(0.05, 395.0), drift=False, noise=False)
    torch.testing.assert_close(sim.x[-1, 0], xs, rtol=1e-9, atol=1e-12)


def test_cstr_rk4_is_fourth_order_against_scipy():
    x0 = np.array([0.05, 395.0])
    ref = solve_ivp(lambda t, z: _cstr_rhs_np(z, 1.0), (0, 1.0), x0, rtol=1e-13, atol=1e-13,
                    method="DOP853").y[:, -1]  # fmt: skip
    errs = []
    for dt in (0.02, 0.01):
        p = CSTRParams(dt=dt)
        x = torch.tensor(x0, dtype=F64)
        for _ in range(round(1.0 / dt)):
            x = cstr_step(x, 1.0, p)
        errs.append(np.abs((x.numpy() - ref) / ref).max())
    assert errs[0] < 1e-6
    assert 12.0 < errs[0] / errs[1] < 20.0  # 2^4 = 16


def test_cstr_feed_drift_equals_eq51_recursion_exactly():
    sim = simulate_cstr(noise=False)
    caf = [Fraction(1)]
    for k in range(1, 201):
        caf.append(Fraction(1) if k <= 50 else caf[-1] + Fraction(1, 100000) * (k - 50))
    ref = torch.tensor([float(c) for c in caf], dtype=F64)
    assert torch.equal(sim.theta[:, 0, 0], ref)  # correctly rounded exact recursion
    assert [cstr_feed_drift(k) for k in (0, 50)] == [1.0, 1.0]


def test_cstr_matches_numpy_rk4_reference_with_drift():
    """NumPy RK4 of Eq. 50 with the Eq. 51 recursion; step k uses C_AF,k-1 (cf. paper 000 Eq. 62)."""
    p = CSTRParams()
    x = np.array([0.0372, 402.3])
    caf, out = 1.0, [x.copy()]
    for k in range(1, 201):
        f = lambda z, c=caf: _cstr_rhs_np(z, c)  # noqa: E731
        k1 = f(x)
        k2 = f(x + p.dt / 2 * k1)
        k3 = f(x + p.dt / 2 * k2)
        k4 = f(x + p.dt * k3)
        x = x + p.dt / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
        out.append(x.copy())
        if k > 50:
            caf = caf + 1e-5 * (k - 50)
    sim = simulate_cstr(x0=(0.0372, 402.3), noise=False)
    np.testing.assert_allclose(sim.x[:, 0].numpy(), np.array(out), rtol=1e-12, atol=0)
    assert abs(sim.x[-1, 0, 0].item() - sim.x[50, 0, 0].item()) > 5e-3  # the drift shows in C_A


def test_cstr_reading_is_200_steps_of_002_min():
    sim = simulate_cstr(runs=2, generator=gen())
    assert sim.x.shape == (201, 2, 2) and sim.y.shape == (200, 2, 2)
    assert sim.theta.shape == (201, 2, 1) and sim.u is None
    assert sim.t[-1].item() == pytest.approx(4.0)
    assert sim.theta[-1, 0, 0].item() == pytest.approx(1.0 + 1e-5 * 150 * 151 / 2, abs=1e-15)
    assert sim.x.dtype == F64 and sim.meta["state_names"] == ("C_A", "T")
    with pytest.raises(TypeError):
        sim.meta["dt"] = 1.0  # read-only


def test_cstr_models_reproduce_the_noiseless_simulation():
    sim = simulate_cstr(runs=2, x0=torch.tensor([[0.0372, 402.3], [0.05, 395.0]]), noise=False)
    x, y = iterate_model(cstr_model(), sim.x[0], 200)
    torch.testing.assert_close(x, sim.x, rtol=1e-14, atol=0)
    torch.testing.assert_close(y, sim.y, rtol=1e-14, atol=0)
    joint = cstr_joint_model(chol_D=2e-3)
    xj, yj = iterate_joint(joint, sim.x, sim.theta, 200, 2)
    torch.testing.assert_close(xj, sim.x, rtol=1e-14, atol=0)
    torch.testing.assert_close(yj, sim.y, rtol=1e-14, atol=0)
    assert joint.state_dim == 3 and joint.obs_dim == 2
    torch.testing.assert_close(joint.noise(1).chol_Q, torch.diag(torch.tensor([1e-6, 1e-3, 2e-3],
                               dtype=F64)))  # fmt: skip


def test_cstr_batch_determinism_and_noise_levels():
    assert_batch_equals_loop(simulate_cstr, n_steps=20)
    assert_deterministic(simulate_cstr, n_steps=20)
    sim = simulate_cstr(runs=40, generator=gen(11), process_noise_std=(1e-5, 1e-2))
    v = sim.y - sim.x[1:]
    np.testing.assert_allclose(v.std(dim=(0, 1)).numpy(), [1e-4, 0.1], rtol=0.05)
    model = cstr_model()
    w = sim.x[1:] - torch.stack([model.transition(sim.x[k - 1], None, k) for k in range(1, 201)])
    np.testing.assert_allclose(w.std(dim=(0, 1)).numpy(), [1e-5, 1e-2], rtol=0.05)


def test_cstr_bad_input_raises():
    with pytest.raises(ValueError, match="runs"):
        simulate_cstr(runs=0, noise=False)
    with pytest.raises(TypeError, match="runs"):
        simulate_cstr(runs=1.5, noise=False)
    with pytest.raises(ValueError, match="x0"):
        simulate_cstr(x0=torch.zeros(3), noise=False)
    with pytest.raises(ValueError, match="x0"):
        simulate_cstr(runs=2, x0=torch.zeros(3, 2), noise=False)
    with pytest.raises(ValueError, match="V"):
        CSTRParams(V=float("nan"))
    with pytest.raises(ValueError, match="generator"):
        simulate_cstr()
    with pytest.raises(ValueError, match="measurement_noise_std"):
        simulate_cstr(noise=False, measurement_noise_std=(1e-4, -1.0))


# =========================================================================== three tank
def _tank_np(n_steps, x0=(1.0, 0.95, 0.9), drift=True, p=None):
    """NumPy Euler of paper 000 Eq. 57-59 with the Eq. 61 recursion, written from the paper."""
    p = p or ThreeTankParams()
    x = np.array(x0, dtype=float)
    az2 = 0.6
    out = [x.copy()]
    for k in range(1, n_steps + 1):
        h1, h2, h3 = x
        Q13 = p.az1 * p.S_n * np.sign(h1 - h3) * np.sqrt(2 * p.g * abs(h1 - h3))
        Q32 = p.az3 * p.S_n * np.sign(h3 - h2) * np.sqrt(2 * p.g * abs(h3 - h2))
        Q20 = az2 * p.S_n * np.sqrt(2 * p.g * h2)
        x = x + p.dt / p.A_s * np.array([p.Q1 - Q13, Q32 - Q20 + p.Q2, Q13 - Q32])
        if drift and k > 10:  # az2_k for the next step (Eq. 61-62 use az2_{k-1})
            az2 = az2 + 1e-4 * (k - 10)
        out.append(x.copy())
    return np.array(out)


def test_three_tank_matches_numpy_reference_of_eq57_61():
    sim = simulate_three_tank(noise=False)
    np.testing.assert_allclose(sim.x[:, 0].numpy(), _tank_np(200), rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(sim.y[:, 0].numpy(), _tank_np(200)[1:], rtol=1e-12, atol=1e-14)
    sim0 = simulate_three_tank(noise=False, drift=False)
    np.testing.assert_allclose(sim0.x[:, 0].numpy(), _tank_np(200, drift=False), rtol=1e-12)


def test_three_tank_az2_drift_equals_eq61_recursion_exactly():
    sim = simulate_three_tank(runs=2, noise=False)
    az = [Fraction(6, 10)]
    for k in range(1, 201):
        az.append(Fraction(6, 10) if k <= 10 else az[-1] + Fraction(1, 10000) * (k - 10))
    ref = torch.tensor([float(a) for a in az], dtype=F64)
    assert torch.equal(sim.theta[:, 1, 0], ref)  # correctly rounded exact recursion
    assert az2_drift(10) == 0.6 and az2_drift(11) == pytest.approx(0.6001, abs=1e-16)


def test_three_tank_equilibrium_and_mass_balance():
    p = ThreeTankParams()
    eq = three_tank_equilibrium(p)
    # closed form checked against the flow laws: Q13 = Q32 = Q1, Q20 = Q1 + Q2
    h1, h2, h3 = eq.tolist()
    c = p.S_n * math.sqrt(2 * p.g)
    assert p.az1 * c * math.sqrt(h1 - h3) == pytest.approx(p.Q1, rel=1e-12)
    assert p.az3 * c * math.sqrt(h3 - h2) == pytest.approx(p.Q1, rel=1e-12)
    assert p.az2 * c * math.sqrt(h2) == pytest.approx(p.Q1 + p.Q2, rel=1e-12)
    torch.testing.assert_close(three_tank_step(eq, p.az2, None, p), eq, rtol=0, atol=1e-15)
    long = simulate_three_tank(15000, drift=False, noise=False)  # slowest mode: ~714 s
    torch.testing.assert_close(long.x[-1, 0], eq, rtol=0, atol=1e-9)
    # total volume change per Euler step = dt (Q1 + Q2 - Q20(h2_{k-1}, az2_{k-1}))
    sim = simulate_three_tank(noise=False)
    x, az = sim.x[:, 0], sim.theta[:, 0, 0]
    dV = p.A_s * (x[1:].sum(-1) - x[:-1].sum(-1))
    Q20 = az[:-1] * c * torch.sqrt(x[:-1, 1])
    torch.testing.assert_close(dV, p.dt * (p.Q1 + p.Q2 - Q20), rtol=1e-9, atol=1e-18)


def test_three_tank_models_reproduce_the_noiseless_simulation():
    u = torch.full((200, 2), 4.5e-5, dtype=F64)
    u[100:, 0] = 3e-5  # a pump change, shared by the runs
    sim = simulate_three_tank(runs=2, x0=torch.tensor([[1, 0.95, 0.9], [0.8, 0.5, 0.6]]), u=u,
                              noise=False)  # fmt: skip
    assert sim.u.shape == (200, 2, 2)
    x, y = iterate_model(three_tank_model(control=True), sim.x[0], 200, u=sim.u)
    torch.testing.assert_close(x, sim.x, rtol=1e-14, atol=0)
    torch.testing.assert_close(y, sim.y, rtol=1e-14, atol=0)
    joint = three_tank_joint_model(chol_D=3e-3, control=True)
    xs, ys = [sim.x[0]], []
    for k in range(1, 201):
        z = torch.cat([sim.x[k - 1], sim.theta[k - 1]], -1)
        xs.append(joint.transition(z, sim.u[k - 1], k)[..., :3])
        ys.append(joint.observe(torch.cat([sim.x[k], sim.theta[k]], -1), sim.u[k - 1], k))
    torch.testing.assert_close(torch.stack(xs), sim.x, rtol=1e-14, atol=0)
    torch.testing.assert_close(torch.stack(ys), sim.y, rtol=1e-14, atol=0)
    SQ = torch.diag(torch.tensor([1e-4, 1e-4, 1e-4, 3e-3], dtype=F64))
    torch.testing.assert_close(joint.noise(5).chol_Q, SQ)
    torch.testing.assert_close(joint.noise(5).chol_R, 2e-4 * torch.eye(3, dtype=F64))


def test_three_tank_batch_determinism_and_noise_levels():
    assert_batch_equals_loop(simulate_three_tank, n_steps=15)
    assert_deterministic(simulate_three_tank, n_steps=15)
    sim = simulate_three_tank(runs=30, generator=gen(5))
    assert sim.y.shape == (200, 30, 3)  # three measured levels (Eq. 63)
    v = sim.y - sim.x[1:]
    np.testing.assert_allclose(v.std(dim=(0, 1)).numpy(), [2e-4] * 3, rtol=0.05)
    model = three_tank_model()
    w = sim.x[1:] - torch.stack([model.transition(sim.x[k - 1], None, k) for k in range(1, 201)])
    np.testing.assert_allclose(w.std(dim=(0, 1)).numpy(), [1e-4] * 3, rtol=0.05)


def test_three_tank_bad_input_raises():
    with pytest.raises(ValueError, match="x0"):
        simulate_three_tank(x0=(1.0, 0.9), noise=False)
    with pytest.raises(ValueError, match="x0"):
        simulate_three_tank(x0=(1.0, float("inf"), 0.9), noise=False)
    with pytest.raises(ValueError, match="runs"):
        simulate_three_tank(runs=0, noise=False)
    with pytest.raises(ValueError, match="az1"):
        ThreeTankParams(az1=float("nan"))
    with pytest.raises(ValueError, match="u must have shape"):
        simulate_three_tank(5, u=torch.zeros(5, 3), noise=False)
    with pytest.raises(ValueError, match="n_steps"):
        simulate_three_tank(0, noise=False)
    with pytest.raises(ValueError, match="chol_D"):
        three_tank_joint_model(chol_D=torch.ones(2, 2))


# =========================================================================== Lorenz
def _lorenz_np(t, s, a=10.0, b=28.0, c=8.0 / 3.0):
    x, y, z = s
    return [-a * (x - y), b * x - y - x * z, x * y - c * z]


def test_lorenz_series_is_the_x_component_after_the_transient_and_normalises():
    s = lorenz_series()
    assert s.shape == (1000,) and s.dtype == F64
    torch.testing.assert_close(lorenz_series(), s, rtol=0, atol=0)  # deterministic
    sim = simulate_lorenz(999, n_transient=1000, noise=False)
    torch.testing.assert_close(sim.x[:, 0, 0], s, rtol=0, atol=0)
    full = simulate_lorenz(1999, noise=False)  # no transient: the series is its tail
    torch.testing.assert_close(full.x[1000:, 0, 0], s, rtol=1e-12, atol=1e-12)
    ns = minmax_normalize(s)
    assert ns.values.min().item() == 0.0 and ns.values.max().item() == 1.0
    train, test = ns.values[:500], ns.values[500:]
    assert train.shape == test.shape == (500,)
    assert lorenz_series(1).shape == (1,)


def test_lorenz_fixed_points_are_invariant_and_rk4_is_fourth_order():
    p = LorenzParams()
    r = math.sqrt(p.c * (p.b - 1.0))
    C = torch.tensor([[r, r, p.b - 1.0], [-r, -r, p.b - 1.0], [0.0, 0.0, 0.0]], dtype=F64)
    torch.testing.assert_close(lorenz_step(C, p), C, rtol=0, atol=1e-12)
    x0 = [1.0, 1.0, 1.0]
    ref = solve_ivp(_lorenz_np, (0, 1.0), x0, rtol=1e-13, atol=1e-13, method="DOP853").y[:, -1]
    errs = []
    for dt in (0.01, 0.005, 0.0025):
        sim = simulate_lorenz(round(1.0 / dt), params=LorenzParams(dt=dt), noise=False)
        errs.append(np.abs(sim.x[-1, 0].numpy() - ref).max())
    # dt = 0.01 (the series' step) is still pre-asymptotic on this chaotic flow; the order
    # shows between the two smaller steps
    assert errs[0] < 1e-4 and 12.0 < errs[1] / errs[2] < 20.0
    two = simulate_lorenz(100, params=LorenzParams(dt=0.01, substeps=2), noise=False)
    half = simulate_lorenz(200, params=LorenzParams(dt=0.005), noise=False)
    torch.testing.assert_close(two.x[-1], half.x[-1], rtol=1e-13, atol=1e-13)


def test_lorenz_model_batch_and_determinism():
    kw = dict(n_steps=30, process_noise_std=0.01, measurement_noise_std=0.1)
    assert_batch_equals_loop(simulate_lorenz, **kw)
    assert_deterministic(simulate_lorenz, **kw)
    sim = simulate_lorenz(50, runs=2, x0=torch.tensor([[1.0, 1, 1], [0, 1, 1.05]]), noise=False)
    x, y = iterate_model(lorenz_model(), sim.x[0], 50)
    torch.testing.assert_close(x, sim.x, rtol=1e-14, atol=0)
    torch.testing.assert_close(y, sim.y, rtol=1e-14, atol=0)
    assert sim.y.shape == (50, 2, 1) and sim.theta.shape == (51, 2, 0)
    with pytest.raises(ValueError, match="x0"):
        simulate_lorenz(5, x0=(1.0, 1.0), noise=False)
    with pytest.raises(ValueError, match="LorenzParams.a"):
        LorenzParams(a=float("inf"))


# =========================================================================== high-speed train
def _hst_faults_np(t):
    """Eq. 63-64 written independently (0.16 Hz MATLAB sawtooth: 2 frac(0.16 t) - 1)."""
    saw = 2.0 * np.mod(0.16 * t, 1.0) - 1.0
    fac = np.where((t > 5) & (t <= 15), -0.04 * (-1.0 + 0.2 * saw), 0.0)
    fad = np.where((t > 4) & (t <= 15), 0.06 * (1.0 + np.exp(-t + 7.5)), 0.0)
    return fac, fad


def test_hst_cruise_speed_profile_eq66():
    kmh = {0.0: 200, 49.99: 200, 75.0: 215, 100.0: 230, 250.0: 230, 310.0: 223.75, 400.0: 167.5}
    for t, v in kmh.items():
        assert hst_cruise_speed(t) == pytest.approx(v / 3.6, rel=1e-14)
    assert hst_cruise_speed(700.0) == pytest.approx(20 / 3.6)  # continuous reading of Eq. 66
    sim = simulate_hst(5, noise=False)
    torch.testing.assert_close(sim.meta["v_r"], torch.full((6,), 200 / 3.6, dtype=F64))


def test_hst_fault_trajectories_follow_eq63_65():
    sim = simulate_hst(1600, runs=2, generator=gen(2), q_scale=1e-4, r_scale=1e-4)
    t = sim.t.numpy()
    assert t[-1] == pytest.approx(16.0)
    fac, fad = _hst_faults_np(np.arange(1601) * 0.01)
    np.testing.assert_allclose(sim.theta[:, 0, 0].numpy(), fac, rtol=1e-14, atol=0)
    np.testing.assert_allclose(sim.theta[:, 1, 1].numpy(), fad, rtol=1e-14, atol=0)
    x = sim.x.numpy()
    fs = np.where(((t > 2.5) & (t <= 15))[:, None], 1e-3 * (-1 + np.sin(0.1 * x[..., 3] *
                  x[..., 4])), 0.0)  # fmt: skip
    np.testing.assert_allclose(sim.theta[..., 2].numpy(), fs, rtol=1e-13, atol=1e-18)
    assert fac[500] == 0 and fac[501] != 0 and fac[1500] != 0 and fac[1501] == 0
    assert hst_actuator_fault(6.25) == pytest.approx(0.048)  # sawtooth restarts at -1
    assert hst_actuator_fault(9.375) == pytest.approx(0.04)  # sawtooth at 0


def _paper_A(p: HSTParams, v_r: float):
    """A of paper 004 Eq. 8 built block by block (A_22 diagonal with the derived 2 d / m_i)."""
    n, m, k, d = p.n_cars, p.m, p.k, p.d
    A11 = np.zeros((n - 1, n))
    A21 = np.zeros((n, n - 1))
    A22 = np.zeros((n, n))
    for i in range(n - 1):
        A11[i, i], A11[i, i + 1] = 1.0, -1.0
        A21[i, i] -= k / m[i]
        A21[i + 1, i] += k / m[i + 1]
    for i in range(n):
        if i > 0:
            A22[i, i - 1] = d / m[i]
        if i < n - 1:
            A22[i, i + 1] = d / m[i]
        A22[i, i] = -p.eps_v - d / m[i] * (1 if i in (0, n - 1) else 2)
    A22[0, 0] -= 2 * sum(m) / m[0] * p.eps_a * v_r  # U_1
    return np.block([[np.zeros((n - 1, n - 1)), A11], [A21, A22]])


def test_hst_linear_part_equals_paper_A_and_is_stable():
    p = HSTParams(m=(7.0e4, 5.5e4, 6.0e4, 5.8e4, 7.2e4))
    v_r = 230 / 3.6
    J = torch.func.jacfwd(lambda z: hst_rhs(z, None, (0.0, 0.0), v_r, p))(torch.zeros(9, dtype=F64))
    A = _paper_A(p, v_r)
    np.testing.assert_allclose(J.numpy(), A, rtol=1e-13, atol=1e-16)
    assert np.linalg.eigvals(A).real.max() < 0
    # nonlinear part E_xi p(psi) = -eps_a (M / m_1) v_1^2 on the car-1 speed only
    z = torch.zeros(9, dtype=F64)
    z[4] = 3.0
    out = hst_rhs(z, None, (0.0, 0.0), v_r, p).numpy() - A @ z.numpy()
    ref = np.zeros(9)
    ref[4] = -p.eps_a * sum(p.m) / p.m[0] * 9.0
    np.testing.assert_allclose(out, ref, rtol=1e-12, atol=1e-15)


def test_hst_deviation_model_equals_absolute_eq4_with_feedforward_traction():
    """Eq. 4 in absolute speeds, u_i = u_i^e(v_r) + m_i dv_r + faults: deviations follow Eq. 13."""
    p = HSTParams()
    m, n, s = np.array(p.m), p.n_cars, p.sigma
    model = hst_model(p, control=True)
    k0, steps = 4990, 120  # crosses the start of the speed ramp at t = 50 s
    rng = np.random.default_rng(0)
    psi0 = rng.normal(scale=0.2, size=9)
    uhat = rng.normal(scale=2e3, size=(steps, n))
    X = psi0[:4].copy()
    V = psi0[4:] + hst_cruise_speed(k0 * s)
    psi = torch.tensor(psi0, dtype=F64)
    Fa = np.array(p.F_a)
    for j in range(steps):
        k = k0 + j + 1
        t0, t1 = (k - 1) * s, k * s
        vr0, vr1 = hst_cruise_speed(t0), hst_cruise_speed(t1)
        ue = p.eps_0 * m + p.eps_v * m * vr0
        ue[0] += p.eps_a * m.sum() * vr0**2  # Eq. 5-6
        u = ue + m * (vr1 - vr0) / s + uhat[j]
        dX = V[:-1] - V[1:]
        Fc = p.k * X + p.d * dX
        force = u - (p.eps_0 + p.eps_v * V) * m
        force[:-1] -= Fc
        force[1:] += Fc
        force[0] -= p.eps_a * m.sum() * V[0] ** 2
        acc = force / m + Fa[4:] @ np.array([hst_actuator_fault(t0), hst_coupler_fault(t0)])
        X, V = X + s * dX, V + s * acc
        psi = model.transition(psi, torch.tensor(uhat[j], dtype=F64), k)
        np.testing.assert_allclose(psi.numpy(), np.r_[X, V - vr1], rtol=1e-9, atol=1e-9)


def test_hst_models_reproduce_the_noiseless_simulation():
    u = torch.zeros(1600, 2, 5, dtype=F64)
    u[:, 1, 2] = 5e3
    x0 = torch.tensor([0.1, -0.1, 0.0, 0.2, 0.5, 0.0, -0.3, 0.1, 0.0], dtype=F64)
    sim = simulate_hst(1600, runs=2, x0=x0, u=u, noise=False)
    x, y = iterate_model(hst_model(control=True), sim.x[0], 1600, u=sim.u)
    torch.testing.assert_close(x, sim.x, rtol=1e-14, atol=0)
    torch.testing.assert_close(y, sim.y, rtol=1e-14, atol=0)
    fm = hst_fault_model(control=True)
    xs, ys = [sim.x[0]], []
    for k in range(1, 1601):
        xs.append(fm.transition(torch.cat([sim.x[k - 1], sim.theta[k - 1]], -1), sim.u[k - 1], k))
        ys.append(fm.observe(torch.cat([sim.x[k], sim.theta[k]], -1), sim.u[k - 1], k))
    xs = torch.stack([z[..., :9] for z in xs])
    torch.testing.assert_close(xs, sim.x, rtol=1e-13, atol=1e-15)
    torch.testing.assert_close(torch.stack(ys), sim.y, rtol=1e-13, atol=1e-15)
    assert fm.state_dim == 12 and fm.obs_dim == 9
    SQ = fm.noise(3).chol_Q
    torch.testing.assert_close(torch.diagonal(SQ)[:9] ** 2, torch.full((9,),
                               1 + 0.5 * math.sin(0.0006), dtype=F64))  # fmt: skip
    torch.testing.assert_close(torch.diagonal(SQ)[9:], torch.tensor([1e-2, 1e-2, 1e-4], dtype=F64))


def test_hst_noise_uncertainty_batch_and_determinism():
    kw = dict(n_steps=40, q_scale=1e-4)
    assert_batch_equals_loop(simulate_hst, **kw)
    assert_deterministic(simulate_hst, **kw)
    sim = simulate_hst(600, runs=20, generator=gen(9), q_scale=1e-4)
    dE = sim.meta["delta_E"]
    assert dE.shape == (600, 20, 9)
    assert bool((dE.abs() <= 0.01).all()) and torch.equal(dE, dE[..., :1].expand_as(dE))
    Fs = torch.tensor(HSTParams().F_s, dtype=F64)
    v = sim.y - sim.x[1:] - sim.theta[1:, :, 2:] * Fs - dE
    R = torch.tensor([1.1 + 0.08 * math.cos(0.0002 * k) for k in range(1, 601)], dtype=F64)
    np.testing.assert_allclose((v / R.sqrt()[:, None, None]).std().item(), 1.0, rtol=0.03)
    model = hst_model(q_scale=1e-4)
    w = sim.x[1:] - torch.stack([model.transition(sim.x[k - 1], None, k) for k in range(1, 601)])
    Q = torch.tensor([1 + 0.5 * math.sin(0.0003 * (k - 1)) for k in range(1, 601)], dtype=F64)
    np.testing.assert_allclose((w / (1e-4 * Q).sqrt()[:, None, None]).std().item(), 1.0, rtol=0.03)
    off = simulate_hst(30, runs=2, generator=gen(9), measurement_uncertainty=False)
    assert off.meta["delta_E"] is None


def test_hst_bad_input_raises():
    with pytest.raises(ValueError, match="x0"):
        simulate_hst(5, x0=torch.zeros(8), noise=False)
    with pytest.raises(ValueError, match="runs"):
        simulate_hst(5, runs=0, noise=False)
    with pytest.raises(ValueError, match="HSTParams.m"):
        HSTParams(m=(8e4, float("inf"), 8e4, 8e4, 8e4))
    with pytest.raises(ValueError, match="HSTParams.k"):
        HSTParams(k=float("nan"))
    with pytest.raises(ValueError, match="u must have shape"):
        simulate_hst(5, u=torch.zeros(5, 4), noise=False)
    with pytest.raises(ValueError, match="q_scale"):
        simulate_hst(5, q_scale=-1.0, noise=False)
    with pytest.raises(ValueError, match="generator"):
        simulate_hst(5, generator=None)


# =========================================================================== vmap-friendliness
@pytest.mark.parametrize(
    "model, x, u",
    [
        (cstr_model(), torch.tensor([[0.037, 402.0], [0.05, 395.0]], dtype=F64), None),
        (
            three_tank_model(),
            torch.tensor([[1, 0.95, 0.9], [0.5, 0.5, 0.5]], dtype=F64),
            torch.tensor([[4e-5, 5e-5], [1e-5, 2e-5]], dtype=F64),
        ),  # fmt: skip
        (lorenz_model(), torch.tensor([[1.0, 1, 1], [-3, 2, 20]], dtype=F64), None),
        (
            hst_model(),
            torch.randn(2, 9, generator=gen(), dtype=F64),
            torch.randn(2, 5, generator=gen(1), dtype=F64),
        ),  # fmt: skip
        (hst_fault_model(), torch.randn(2, 12, generator=gen(), dtype=F64), None),
        (three_tank_joint_model(), torch.tensor([[1, 0.95, 0.9, 0.7]] * 2, dtype=F64), None),
    ],
)
def test_per_sample_functions_vmap_and_match_batched_calls(model, x, u):
    k = 600  # inside the HST fault windows
    if u is None:
        fv = vmap(lambda xi: model.f(xi, None, k))(x)
        hv = vmap(lambda xi: model.h(xi, None, k))(x)
    else:
        fv = vmap(lambda xi, ui: model.f(xi, ui, k))(x, u)
        hv = vmap(lambda xi, ui: model.h(xi, ui, k))(x, u)
    torch.testing.assert_close(fv, model.transition(x, u, k), rtol=1e-14, atol=0)
    torch.testing.assert_close(hv, model.observe(x, u, k), rtol=1e-14, atol=0)
    J = model.transition_jacobian(x, u, k)
    assert J.shape == (2, model.state_dim, model.state_dim) and bool(torch.isfinite(J).all())
    # sigma-point layout used by the filters: x (..., L, n) with u (..., 1, p)
    X = x.unsqueeze(1).expand(2, 3, model.state_dim)
    uu = None if u is None else u.unsqueeze(1)
    torch.testing.assert_close(model.transition(X, uu, k)[:, 1], model.transition(x, u, k))


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_simulators_on_cuda_match_cpu():
    cases = [
        (simulate_cstr, dict(n_steps=50)),
        (simulate_three_tank, dict(n_steps=50)),
        (simulate_lorenz, dict(n_steps=50)),
        (simulate_hst, dict(n_steps=300)),
    ]
    for simulate, kw in cases:
        cpu = simulate(runs=2, noise=False, **kw)
        gpu = simulate(runs=2, noise=False, device="cuda", **kw)
        assert gpu.x.device.type == "cuda" and gpu.y.device.type == "cuda"
        torch.testing.assert_close(gpu.x.cpu(), cpu.x, rtol=1e-10, atol=1e-12)
        torch.testing.assert_close(gpu.theta.cpu(), cpu.theta, rtol=1e-10, atol=1e-12)
        g = torch.Generator(device="cuda").manual_seed(0)
        noisy = simulate(runs=2, generator=g, device="cuda", **kw)
        assert bool(torch.isfinite(noisy.y).all()) and noisy.y.device.type == "cuda"


def test_cstr_in_float32_and_battery_currents_are_checked():
    """simulate_cstr(dtype=float32) crashed in its steady state's Newton step (float64
    parameters against a float32 iterate); simulate_battery read NaN currents into NaN
    outputs (the other simulators refuse them) and a text u with torch's own message."""
    from prognos_torch.systems import simulate_battery, simulate_cstr

    ref = cstr_steady_state()
    assert torch.equal(cstr_steady_state(dtype=torch.float32), ref.float())
    sim = simulate_cstr(5, generator=torch.Generator().manual_seed(0), dtype=torch.float32)
    assert sim.y.dtype == torch.float32 and bool(torch.isfinite(sim.y).all())
    g = torch.Generator().manual_seed(0)
    nan_u = torch.tensor([[1.0], [math.nan], [1.0]], dtype=torch.float64)
    with pytest.raises(ValueError, match="u contains non-finite values"):
        simulate_battery(3, generator=g, u=nan_u)
    with pytest.raises(TypeError, match=r"u must be a tensor or an array of numbers \(T, 1\)"):
        simulate_battery(3, generator=g, u="abc")


def test_float32_simulation_draws_the_float64_noise_rounded():
    """A float32 run drew another realisation than the float64 run of the same seed
    (torch.randn draws other numbers per dtype from 16 values on): the train's float32 outputs
    differed from the float64 ones by 150 % of their range."""
    spec = [("normal", (3,)), ("uniform", ())]
    a = draw_run_noise(gen(2), 2, 40, spec)
    b = draw_run_noise(gen(2), 2, 40, spec, dtype=torch.float32)
    assert b[0].dtype == b[1].dtype == torch.float32
    assert torch.equal(b[0], a[0].float())
    below_one = torch.nextafter(torch.tensor(1.0), torch.tensor(0.0))
    assert torch.equal(b[1], a[1].float().clamp(max=below_one))
    s64 = simulate_hst(60, 2, generator=gen(5))
    s32 = simulate_hst(60, 2, generator=gen(5), dtype=torch.float32)
    torch.testing.assert_close(s32.y.double(), s64.y, rtol=0, atol=1e-4)
    torch.testing.assert_close(s32.x.double(), s64.x, rtol=0, atol=1e-4)


def test_three_tank_refuses_negative_outflow_coefficients_and_a_nan_az2():
    """A negative az1/az2/az3 (a sign typo) ran a tank that drains into a fuller one;
    three_tank_equilibrium(az2=nan) returned NaN levels and az1 = 0 a ZeroDivisionError."""
    for name in ("az1", "az2", "az3"):
        with pytest.raises(ValueError, match=rf"ThreeTankParams\.{name} must be >= 0"):
            ThreeTankParams(**{name: -0.5})
    with pytest.raises(ValueError, match="az2 must be a finite positive number, got nan"):
        three_tank_equilibrium(az2=float("nan"))
    with pytest.raises(ValueError, match="az1 > 0"):
        three_tank_equilibrium(ThreeTankParams(az1=0.0))
    p = ThreeTankParams(az2=0.3)  # closed form against the flow balance of Eq. 57-58
    h = three_tank_equilibrium(p)
    torch.testing.assert_close(three_tank_step(h, p.az2, None, p), h, rtol=0, atol=1e-15)


def test_simulate_hst_runs_names_a_single_generator():
    """One generator instead of a list gave "'Generator' object is not iterable"."""
    from prognos_torch.systems import simulate_hst_runs

    with pytest.raises(TypeError, match=r"one per run, got one Generator: pass \[generator\]"):
        simulate_hst_runs(3, gen(0))
    truth, y, _ = simulate_hst_runs(3, [gen(0)])
    ref = simulate_hst(3, 1, generator=gen(0))
    assert torch.equal(y, ref.y) and torch.equal(truth, torch.cat([ref.x, ref.theta], -1))
