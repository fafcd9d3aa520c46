"""Audit of the simulators' dynamics against independent references not used elsewhere.

* CSTR with the Eq. 51 feed drift against SciPy's DOP853 on each sample interval.
* The models' autograd Jacobians against central finite differences (the three-tank's custom
  ``sgn(d) sqrt|d|`` derivative included) and the train's fault model against the block matrices
  of paper 004 Eq. 13 (``A_bar``, ``C_bar``) built by hand.
* Batches with per-run initial states and inputs against one call per run, and the battery's
  noisy batch against successive single runs (its tests only checked reproducibility).
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.integrate import solve_ivp

from prognos_torch.systems import (
    CSTRParams,
    HSTParams,
    cstr_joint_model,
    cstr_model,
    hst_fault_model,
    lorenz_model,
    simulate_battery,
    simulate_cstr,
    simulate_hst,
    simulate_lorenz,
    simulate_three_tank,
    three_tank_joint_model,
)
from prognos_torch.systems.battery import battery_circuit_model

F64 = torch.float64


def gen(seed=0):
    return torch.Generator().manual_seed(seed)


def test_cstr_with_feed_drift_matches_solve_ivp_sampled_at_the_steps():
    """Eq. 50 integrated by DOP853 with C_AF held at C_AF,k-1 (Eq. 51) over step k."""
    p = CSTRParams()

    def rhs(t, z, caf):
        ca, temp = z
        r = p.k0 * np.exp(-p.E_R / temp) * ca
        return [
            -r + p.Q_F * (caf - ca) / p.V,
            r * (-p.dH) / p.rho_Cp
            + p.Q_F * (p.T_F - temp) / p.V
            + p.UA_c * (p.T_c - temp) / (p.rho_Cp * p.V),
        ]

    x0 = np.array([0.0372, 402.3])
    x, out, caf = x0.copy(), [x0], 1.0
    for k in range(1, 121):
        sol = solve_ivp(rhs, (0.0, p.dt), x, args=(caf,), method="DOP853", rtol=1e-13, atol=1e-13)
        x = sol.y[:, -1]
        out.append(x)
        if k > 50:
            caf += 1e-5 * (k - 50)  # C_AF,k for the next step
    ref = np.array(out)
    sim = simulate_cstr(120, x0=tuple(x0), noise=False).x[:, 0].numpy()
    # RK4 with dt = 0.02 min: 8e-7 relative on C_A, 2e-8 on T; C_AF,k in place of C_AF,k-1
    # (the drift one step early) moves C_A by 1.5e-3 relative by k = 120
    np.testing.assert_allclose(sim, ref, rtol=2e-6, atol=0)


def _central_differences(fn, x, rel=1e-6):
    cols = []
    for i in range(x.numel()):
        h = rel * max(1.0, abs(x[i].item()))
        e = torch.zeros_like(x)
        e[i] = h
        cols.append((fn(x + e) - fn(x - e)) / (2 * h))
    return torch.stack(cols, -1)


@pytest.fixture(scope="module")
def torch_func_loaded():
    """The first forward-mode Jacobian in a process takes ~1.3 s (torch's lazy set-up of
    forward AD); pay it once in setup, not in the tests' timing."""
    cstr_model().transition_jacobian(torch.tensor([0.04, 400.0], dtype=F64), None, 1)


def test_model_jacobians_match_central_differences(torch_func_loaded):
    k = 600  # inside the train's fault windows
    cases = [
        (cstr_model(), torch.tensor([0.04, 400.0], dtype=F64), None),
        (cstr_joint_model(), torch.tensor([0.04, 400.0, 1.01], dtype=F64), None),
        (three_tank_joint_model(), torch.tensor([1.0, 0.95, 0.9, 0.65], dtype=F64), None),
        (three_tank_joint_model(), torch.tensor([0.4, 0.95, 0.9, 0.65], dtype=F64), None),
        (lorenz_model(), torch.tensor([1.0, 2.0, 20.0], dtype=F64), None),
        (hst_fault_model(), torch.randn(12, dtype=F64, generator=gen()), None),
        (
            battery_circuit_model(),
            torch.tensor([293.0, 7000.0, 20.0, 100.0], dtype=F64),
            torch.tensor([2.0], dtype=F64),
        ),
    ]
    for model, x, u in cases:
        J = model.transition_jacobian(x, u, k)
        Jfd = _central_differences(lambda z, m=model, u=u: m.transition(z, u, k), x)
        torch.testing.assert_close(J, Jfd, rtol=1e-6, atol=1e-7 * float(J.abs().max()))
        H = model.observation_jacobian(x, u, k)
        Hfd = _central_differences(lambda z, m=model, u=u: m.observe(z, u, k), x)
        torch.testing.assert_close(H, Hfd, rtol=1e-6, atol=1e-9)


def test_hst_fault_model_jacobians_are_paper_eq13_block_matrices(torch_func_loaded):
    """With v_1 = 0 (so d p / d psi = 0) and psi_4 psi_5 = 0, the fault model's Jacobians are
    A_bar = [[I + sigma A, sigma F_a, 0], [0, I, 0], [0, 0, I]] and C_bar = [I, 0, F_s]."""
    p = HSTParams()
    s, n, m, kc, d = p.sigma, p.n_cars, p.m, p.k, p.d
    v_r = 200 / 3.6  # t < 50 s
    A = np.zeros((9, 9))
    for i in range(n - 1):  # dx_i = v_i - v_{i+1}
        A[i, 4 + i], A[i, 5 + i] = 1.0, -1.0
    for i in range(n):  # m_i dv_i: coupler forces ahead (i-1) and behind (i), resistance
        r = 4 + i
        A[r, r] = -p.eps_v
        if i > 0:
            A[r, i - 1] += kc / m[i]
            A[r, r - 1] += d / m[i]
            A[r, r] -= d / m[i]
        if i < n - 1:
            A[r, i] -= kc / m[i]
            A[r, r + 1] += d / m[i]
            A[r, r] -= d / m[i]
    A[4, 4] -= 2 * p.eps_a * sum(m) / m[0] * v_r
    Abar = np.eye(12)
    Abar[:9, :9] += s * A
    Abar[:9, 9:11] = s * np.array(p.F_a)
    Cbar = np.zeros((9, 12))
    Cbar[:, :9] = np.eye(9)
    Cbar[:, 11] = p.F_s
    z = torch.randn(12, dtype=F64, generator=gen(3))
    z[4] = 0.0  # v_1 = 0: the quadratic drag has zero slope, psi_4 psi_5 = 0
    model = hst_fault_model(p)
    np.testing.assert_allclose(model.transition_jacobian(z, None, 300).numpy(), Abar, atol=1e-15)
    H = model.observation_jacobian(z, None, 300)
    np.testing.assert_allclose(H.numpy(), Cbar, atol=0)


def test_batches_with_per_run_initial_states_and_inputs_equal_single_runs():
    g = gen(1)
    cases = [
        (simulate_cstr, 30, torch.tensor([[0.03, 400.0], [0.05, 395.0]], dtype=F64), None),
        (
            simulate_three_tank,
            20,
            torch.tensor([[1.0, 0.9, 0.8], [0.3, 0.2, 0.1]], dtype=F64),
            torch.rand(20, 2, 2, generator=g, dtype=F64) * 1e-4,
        ),
        (simulate_lorenz, 30, torch.randn(2, 3, generator=g, dtype=F64), None),
        (
            simulate_hst,
            600,  # through the sensor (2.5 s) and coupler (4 s) fault onsets
            torch.randn(2, 9, generator=g, dtype=F64),
            torch.randn(600, 2, 5, generator=g, dtype=F64) * 1e3,
        ),
        (
            simulate_battery,
            20,
            torch.tensor([[293.0, 7800.0, 1.0, 2.0], [300.0, 6000.0, 5.0, 50.0]], dtype=F64),
            torch.rand(20, 2, 1, generator=g, dtype=F64) * 4,
        ),
    ]
    for simulate, T, x0, u in cases:
        kw = {} if u is None else {"u": u}
        batch = simulate(T, 2, x0=x0, noise=False, **kw)
        for r in range(2):
            kr = {} if u is None else {"u": u[:, r]}
            one = simulate(T, 1, x0=x0[r], noise=False, **kr)
            for name in ("x", "y", "theta"):
                # (to rounding, not bit for bit: a batch of 2 and of 1 may take other GEMM
                # kernels, whose sums round differently on some CPUs)
                a, b = getattr(batch, name)[:, r], getattr(one, name)[:, 0]
                torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-12,
                                           msg=f"{simulate.__name__} {name}")  # fmt: skip


def test_battery_noisy_batch_equals_successive_single_runs():
    kw = dict(process_noise_std=0.01)
    batch = simulate_battery(40, 3, generator=gen(4), **kw)
    g = gen(4)
    singles = [simulate_battery(40, 1, generator=g, **kw) for _ in range(3)]
    for name in ("x", "y"):
        loop = torch.cat([getattr(s, name) for s in singles], 1)
        torch.testing.assert_close(getattr(batch, name), loop, rtol=1e-10, atol=1e-12, msg=name)
