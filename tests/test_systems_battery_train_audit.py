"""Audit of the battery, the high-speed train, the integrators and the per-run noise streams.

References: the integrators against the closed form of a linear ODE, the noise streams against
their definition (one seed per run, then a private generator), the loads and RMSEs against
direct computations; bad arguments are refused by name before anything is drawn or built.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from prognos_torch.systems.battery import (
    BatteryCircuitParams,
    battery_circuit_model,
    battery_circuit_output,
    battery_circuit_rhs,
    battery_circuit_step,
    battery_eod_event,
    battery_event_state,
    battery_voltage,
    load_controls,
    piecewise_load,
    simulate_battery,
)
from prognos_torch.systems.high_speed_train import (
    HSTParams,
    hst_estimation_errors,
    hst_fault_model,
    hst_measure,
    hst_model,
    hst_noise_variances,
    hst_rhs,
    simulate_hst,
)
from prognos_torch.systems.integrators import euler_step, rk4_step
from prognos_torch.systems.noise_streams import draw_run_noise

F64 = torch.float64
X_FULL = torch.tensor([292.1, 7856.3254, 0.0, 0.0], dtype=F64)  # progpy's full charge
U2 = torch.tensor([2.0], dtype=F64)


# --------------------------------------------------------------------------- integrators
def _linear(A):
    return lambda z: z @ A.mT


def test_rk4_and_euler_steps_are_the_taylor_polynomials_of_the_exact_linear_flow():
    """For dx/dt = A x, RK4 gives sum_{j<=4} (hA)^j / j! x and Euler (I + hA) x exactly."""
    A = torch.tensor([[-0.3, 1.2], [-0.7, -0.1]], dtype=F64)
    x = torch.tensor([[1.0, -2.0], [0.5, 0.25]], dtype=F64)
    h = 0.2
    hA = h * A
    P, term = torch.eye(2, dtype=F64), torch.eye(2, dtype=F64)
    for j in range(1, 5):
        term = term @ hA / j
        P = P + term
    torch.testing.assert_close(rk4_step(_linear(A), x, h), x @ P.mT, rtol=0, atol=1e-14)
    torch.testing.assert_close(
        euler_step(_linear(A), x, h), x @ (torch.eye(2, dtype=F64) + hA).mT, rtol=0, atol=1e-15
    )
    # local error of RK4 against the exact flow exp(hA) is O(h^5)
    exact = x @ torch.linalg.matrix_exp(hA).mT
    assert float((rk4_step(_linear(A), x, h) - exact).abs().max()) < 1e-5
    # NumPy reals are step sizes as well
    torch.testing.assert_close(rk4_step(_linear(A), x, np.float64(h)), x @ P.mT)


@pytest.mark.parametrize("step", [rk4_step, euler_step])
@pytest.mark.parametrize("dt", [True, math.nan, math.inf, -0.1, 0.0, "0.1", [0.1]])
def test_integrators_refuse_a_step_that_is_not_a_finite_positive_number(step, dt):
    # was: True, nan, inf, -0.1, 0 stepped silently ([0.1], "0.1": obscure TypeErrors)
    with pytest.raises(ValueError, match="dt must be a finite positive number"):
        step(lambda z: -z, torch.ones(2, dtype=F64), dt)


@pytest.mark.parametrize("step", [rk4_step, euler_step])
def test_integrators_refuse_a_rate_of_another_shape_and_a_non_tensor_state(step):
    # was: a rate (3, 2) for x (2,) silently gave a (3, 2) "next state"
    with pytest.raises(ValueError, match=r"rhs\(x\) must have x's shape \(2,\)"):
        step(lambda z: torch.ones(3, 2, dtype=F64), torch.ones(2, dtype=F64), 0.1)
    with pytest.raises(TypeError, match="x must be a floating-point tensor"):
        step(lambda z: z, [1.0, 2.0], 0.1)
    with pytest.raises(TypeError, match="x must be a floating-point tensor"):
        step(lambda z: z, torch.ones(2, dtype=torch.int64), 0.1)


# --------------------------------------------------------------------------- noise streams
def test_draw_run_noise_follows_its_definition_and_has_standard_moments():
    """Run r draws from Generator().manual_seed(seed_r), seeds from randint(0, 2**62) in run
    order; within a run: normal (T, 3), then uniform (T,)."""
    T, R = 400, 3
    z, u = draw_run_noise(
        torch.Generator().manual_seed(7), R, T, [("normal", (3,)), ("uniform", ())]
    )
    seeds = torch.randint(0, 2**62, (R,), generator=torch.Generator().manual_seed(7))
    for r, seed in enumerate(seeds.tolist()):
        g = torch.Generator().manual_seed(seed)
        assert torch.equal(z[:, r], torch.randn(T, 3, generator=g, dtype=F64))
        assert torch.equal(u[:, r], torch.rand(T, generator=g, dtype=F64))
    n = z.numel()  # N(0, 1): mean within 5 / sqrt(n), variance within 5 sqrt(2 / n)
    assert abs(float(z.mean())) < 5 / math.sqrt(n)
    assert abs(float(z.var()) - 1.0) < 5 * math.sqrt(2 / n)
    assert abs(float(u.mean()) - 0.5) < 5 * math.sqrt(1 / 12 / u.numel())
    assert float(u.min()) >= 0.0 and float(u.max()) < 1.0


def test_draw_run_noise_reads_draws_given_as_an_iterator():
    # was: the kind check consumed the iterator and nothing was drawn (an empty list returned)
    spec = [("normal", (2,)), ("uniform", ())]
    listed = draw_run_noise(torch.Generator().manual_seed(1), 2, 4, spec)
    it = draw_run_noise(torch.Generator().manual_seed(1), 2, 4, iter(spec))
    assert len(it) == 2 and all(torch.equal(a, b) for a, b in zip(listed, it))


@pytest.mark.parametrize(
    "kw, err, match",
    [
        ({"runs": True}, TypeError, "runs must be an int"),
        ({"runs": 0}, ValueError, "runs must be an int >= 1"),
        ({"runs": 2.0}, TypeError, "runs must be an int"),
        ({"n_steps": -1}, ValueError, "n_steps must be an int >= 0"),
        ({"draws": [("normal", 2)]}, ValueError, "shape of a draw"),
        ({"draws": [("normal", (-1,))]}, ValueError, "shape of a draw"),
        ({"draws": [("normal", (True,))]}, ValueError, "shape of a draw"),
        ({"draws": [("normal",)]}, ValueError, "pair"),
        ({"draws": [("gamma", (2,))]}, ValueError, "draw kind"),
        ({"dtype": torch.int64}, TypeError, "dtype must be a floating-point"),
        ({"dtype": "float32"}, TypeError, "dtype must be a floating-point"),
        ({"device": "no-such-device"}, RuntimeError, "device"),
    ],
)
def test_draw_run_noise_refuses_bad_arguments_before_drawing(kw, err, match):
    # was: obscure torch errors, int64 draws rounded to integers silently, and the generator
    # advanced before the error (dtype / device checked after the draws)
    g = torch.Generator().manual_seed(3)
    state = g.get_state()
    args = {"runs": 2, "n_steps": 3, "draws": [("normal", (2,))]} | kw
    extra = {k: args.pop(k) for k in ("dtype", "device") if k in args}
    with pytest.raises(err, match=match):
        draw_run_noise(g, args["runs"], args["n_steps"], args["draws"], **extra)
    assert torch.equal(g.get_state(), state)


def test_draw_run_noise_refuses_a_non_generator():
    # was: AttributeError 'NoneType' object has no attribute 'device'
    with pytest.raises(TypeError, match="generator must be a torch.Generator"):
        draw_run_noise(None, 1, 2, [("normal", (2,))])


def test_draw_run_noise_takes_numpy_counts():
    a = draw_run_noise(torch.Generator().manual_seed(0), 2, 3, [("normal", (2,))])[0]
    b = draw_run_noise(
        torch.Generator().manual_seed(0), np.int64(2), np.int64(3), [("normal", (np.int64(2),))]
    )[0]
    assert torch.equal(a, b)


# --------------------------------------------------------------------------- battery
@pytest.mark.parametrize("dt", [True, math.nan, -1.0, 0.0, "1"])
def test_battery_step_refuses_a_step_that_is_not_a_finite_positive_number(dt):
    # was: dt=True, nan, -1, 0 and "1" (through float()) stepped silently
    with pytest.raises(ValueError, match="dt must be a finite positive number"):
        battery_circuit_step(X_FULL, U2, dt)


def test_battery_step_takes_numpy_step_sizes_and_equals_the_euler_step_of_the_rhs():
    ref = X_FULL + 0.5 * battery_circuit_rhs(X_FULL, U2)
    torch.testing.assert_close(battery_circuit_step(X_FULL, U2, np.float32(0.5)), ref)


@pytest.mark.parametrize(
    "fn",
    [
        lambda x: battery_circuit_step(x, U2, 1.0),
        lambda x: battery_circuit_rhs(x, U2),
        battery_voltage,
        battery_circuit_output,
        battery_event_state,
        battery_eod_event(),
    ],
)
def test_battery_functions_refuse_states_that_are_not_float_tensors_of_width_4(fn):
    # was: "not enough values to unpack (expected 4, got 3)" / int states failing in torch.add
    with pytest.raises(ValueError, match=r"x must have shape \(\.\.\., 4\)"):
        fn(X_FULL[:3])
    with pytest.raises(TypeError, match="x must be a floating-point tensor"):
        fn(X_FULL.to(torch.int64))
    with pytest.raises(TypeError, match="x must be a floating-point tensor"):
        fn(X_FULL.tolist())


def test_battery_current_must_be_a_tensor_that_broadcasts_to_the_state():
    # was: AttributeError for a float; "stack expects each tensor to be equal size" for (3, 1)
    for fn in (battery_circuit_step, lambda x, u, dt: battery_circuit_rhs(x, u)):
        with pytest.raises(TypeError, match="u must be a tensor"):
            fn(X_FULL, 2.0, 1.0)
        with pytest.raises(ValueError, match="must broadcast to x's leading shape"):
            fn(X_FULL, U2.expand(3, 1), 1.0)
    X = X_FULL + torch.tensor([[0.0], [-100.0], [-500.0]], dtype=F64) * torch.tensor(
        [0.0, 1.0, 0.0, 0.0], dtype=F64
    )
    batched = battery_circuit_step(X, U2, 1.0)  # u (1,) broadcasts over the 3 states
    for r in range(3):
        torch.testing.assert_close(batched[r], battery_circuit_step(X[r], U2, 1.0))


def test_battery_step_out_must_have_the_state_dtype():
    # was: a float32 out silently received the float64 step rounded
    with pytest.raises(ValueError, match="out must be a tensor of x's shape, dtype"):
        battery_circuit_step(X_FULL, U2, 1.0, out=torch.empty(4, dtype=torch.float32))
    out = torch.empty(4, dtype=F64)
    battery_circuit_step(X_FULL, U2, 1.0, out=out)
    torch.testing.assert_close(out, battery_circuit_step(X_FULL, U2, 1.0))


def test_battery_params_freeze_lists_and_take_numpy_scalars():
    # was: a list x0 made the model's cached stepper fail ("unhashable type: 'list'") and
    # stayed mutable; np.float32 / np.int64 values were refused
    x0 = [292.1, 7856.3254, 0.0, 0.0]
    p = BatteryCircuitParams(x0=x0, Ta=np.float32(292.5), Jt=np.int64(800))
    x0[0] = -1.0
    assert p.x0 == (292.1, 7856.3254, 0.0, 0.0) and hash(p) == hash(p)
    assert p.Ta == float(np.float32(292.5)) and type(p.Jt) is int and p.Jt == 800
    model = battery_circuit_model(params=p)
    ref = battery_circuit_step(X_FULL, U2, 1.0, BatteryCircuitParams(Ta=p.Ta))
    torch.testing.assert_close(model.transition(X_FULL, U2, 1), ref)
    with pytest.raises(ValueError, match="x0 must hold 4 numbers"):
        BatteryCircuitParams(x0=5.0)  # was: TypeError "object of type 'float' has no len()"


def test_battery_dtype_arguments_must_be_floating_point():
    # was: dtype=torch.int64 built a model with chol_Q = 0 (sqrt(1e-3) truncated)
    with pytest.raises(TypeError, match="dtype must be a floating-point"):
        battery_circuit_model(dtype=torch.int64)
    with pytest.raises(TypeError, match="dtype must be a floating-point"):
        simulate_battery(3, noise=False, dtype=torch.int64)
    with pytest.raises(TypeError, match="dtype must be a floating-point"):
        load_controls(3, dtype=torch.int64)


def test_simulate_battery_refuses_a_noise_flag_that_is_not_a_bool():
    # was: noise="no" was read as True (and then asked for a generator)
    with pytest.raises(TypeError, match="noise must be a bool"):
        simulate_battery(3, noise="no")


def test_piecewise_load_reads_numbers_only_and_maps_a_missing_time_to_a_missing_load():
    # was: "12", "345" read character by character; bools read as 0/1; NaN time -> last load
    with pytest.raises(TypeError, match="times must be a sequence"):
        piecewise_load("12", "345")
    with pytest.raises(TypeError, match="times must be a sequence"):
        piecewise_load(5.0, (1.0, 2.0))
    with pytest.raises(TypeError, match="values must be a sequence of real numbers"):
        piecewise_load((5.0,), (True, 2.0))
    t = torch.tensor([0.0, 4.9, 5.0, 7.0, math.nan], dtype=F64)
    ref = torch.tensor([1.0, 1.0, 2.0, 2.0, math.nan], dtype=F64)
    torch.testing.assert_close(piecewise_load((5.0,), (1.0, 2.0))(t), ref, equal_nan=True)
    load = piecewise_load(torch.tensor([5.0]), np.array([1.0, 2.0]))  # tensors and arrays too
    torch.testing.assert_close(load(t), ref, equal_nan=True)


def test_load_controls_refuses_a_non_finite_start_and_a_load_of_another_shape():
    # was: t0=nan gave the last load everywhere; t0="5" was read as 5; obscure reshape errors
    for t0 in (math.nan, math.inf, "5", True):
        with pytest.raises(ValueError, match="t0 must be a finite number"):
            load_controls(3, t0=t0)
    with pytest.raises(ValueError, match=r"load must map the \(3,\) times"):
        load_controls(3, load=lambda t: torch.stack([t, t], -1))
    with pytest.raises(ValueError, match=r"load must map the \(3,\) times"):
        load_controls(3, load=lambda t: 2.0)
    u = load_controls(4, dt=np.float32(2.0), t0=np.float64(598.0))  # t_mid 599, 601, 603, 605
    torch.testing.assert_close(u[:, 0], torch.tensor([2.0, 1.0, 1.0, 1.0], dtype=F64))


# --------------------------------------------------------------------------- train
PSI = torch.linspace(-0.5, 0.5, 9, dtype=F64)


def test_hst_rhs_refuses_states_and_inputs_of_other_shapes():
    p = HSTParams()
    with pytest.raises(ValueError, match=r"psi must have shape \(\.\.\., 9\)"):
        hst_rhs(PSI[:8], None, (0.0, 0.0), 60.0, p)
    with pytest.raises(TypeError, match="psi must be a floating-point tensor"):
        hst_rhs(PSI.to(torch.int64), None, (0.0, 0.0), 60.0, p)  # was: a float32 result
    with pytest.raises(ValueError, match=r"u must have shape \(\.\.\., 5\)"):
        hst_rhs(PSI, torch.ones(1, dtype=F64), (0.0, 0.0), 60.0, p)  # was: one force for all cars
    with pytest.raises(ValueError, match="u .* must broadcast to psi's leading shape"):
        hst_rhs(PSI, torch.ones(3, 5, dtype=F64), (0.0, 0.0), 60.0, p)
    with pytest.raises(ValueError, match="f_a must be two numbers"):
        hst_rhs(PSI, None, (0.0, 0.0, 0.0), 60.0, p)  # was: "mat1 and mat2 shapes ..."
    with pytest.raises(ValueError, match="f_a .* must broadcast to psi's leading shape"):
        hst_rhs(PSI, None, torch.zeros(3, 2, dtype=F64), 60.0, p)  # was: a (3, 9) rate


def test_hst_rhs_takes_a_fault_tensor_of_another_dtype_and_matches_eq_8():
    # was: a float32 f_a with a float64 state failed in matmul ("expected m1 and m2 ...")
    p = HSTParams()
    fa = torch.tensor([0.03, -0.02], dtype=torch.float32)
    got = hst_rhs(PSI, None, fa, 60.0, p)
    ref = hst_rhs(PSI, None, tuple(fa.tolist()), 60.0, p)
    torch.testing.assert_close(got, ref, rtol=0, atol=1e-15)
    # Eq. 8 written out for the five-car chain: fault terms enter v_3 (0.85) and v_5 (1.2)
    x, v = PSI[:4], PSI[4:]
    F = p.k * x + p.d * (v[:-1] - v[1:])
    acc = torch.zeros(5, dtype=F64)
    acc[0] = -F[0] - p.eps_a * 5 * (2 * 60.0 * v[0] + v[0] ** 2)
    acc[1:4] = F[:-1] - F[1:]
    acc[4] = F[3]
    acc = acc / 8e4 - p.eps_v * v
    acc[2] += 0.85 * float(fa[0])
    acc[4] += 1.2 * float(fa[1])
    torch.testing.assert_close(got, torch.cat([v[:-1] - v[1:], acc]), rtol=1e-12, atol=1e-15)


def test_hst_measure_refuses_a_sensor_fault_that_would_widen_the_measurement():
    # was: f_s (3, 1) with psi (3, 9) silently gave a (3, 3, 9) measurement
    p = HSTParams()
    psi = PSI.expand(3, 9)
    with pytest.raises(ValueError, match="f_s .* must broadcast to psi's leading shape"):
        hst_measure(psi, torch.zeros(3, 1, dtype=F64), p)
    with pytest.raises(ValueError, match="f_s .* must broadcast to psi's leading shape"):
        hst_measure(PSI, torch.zeros(3, dtype=F64), p)
    with pytest.raises(ValueError, match=r"psi must have shape \(\.\.\., 9\)"):
        hst_measure(PSI[:8], 0.0, p)
    fs = torch.tensor([0.1, -0.2, 0.3], dtype=F64)
    y = hst_measure(psi, fs, p)
    ref = psi.clone()
    ref[:, 4] += fs  # F_s: the speed sensor of car 1 (psi_5)
    torch.testing.assert_close(y, ref, rtol=0, atol=0)


def test_hst_params_freeze_lists_and_take_numpy_scalars():
    # was: list fields stayed mutable and unhashable; np.float32 masses were refused
    m = [8e4] * 5
    p = HSTParams(m=m, k=np.float32(8e4), M=[0.01] * 9)
    m[0] = -1.0
    assert p.m == (8e4,) * 5 and isinstance(p.M, tuple) and hash(p) == hash(HSTParams())
    with pytest.raises(ValueError, match="HSTParams.m must be a sequence"):
        HSTParams(m=8e4)  # was: TypeError "object of type 'float' has no len()"


def test_hst_dtype_and_flag_arguments_are_checked():
    # was: dtype=torch.int64 silently gave float32 results; faults="no" applied the faults
    with pytest.raises(TypeError, match="dtype must be a floating-point"):
        hst_model(dtype=torch.int64)
    with pytest.raises(TypeError, match="dtype must be a floating-point"):
        hst_fault_model(dtype=torch.int64)
    with pytest.raises(TypeError, match="dtype must be a floating-point"):
        simulate_hst(3, noise=False, dtype=torch.int64)
    with pytest.raises(TypeError, match="dtype must be a floating-point"):
        hst_noise_variances(3, dtype=torch.int64)
    with pytest.raises(TypeError, match="faults must be a bool"):
        hst_model(faults="no")
    with pytest.raises(TypeError, match="control must be a bool"):
        hst_fault_model(control="yes")
    with pytest.raises(TypeError, match="measurement_uncertainty must be a bool"):
        simulate_hst(3, noise=False, measurement_uncertainty="no")
    with pytest.raises(TypeError, match="noise must be a bool"):
        simulate_hst(3, noise="no")


def _scores_inputs(T=20, B=2):
    g = torch.Generator().manual_seed(5)
    truth = torch.randn(T + 1, B, 12, generator=g, dtype=F64)
    means = truth[1:] + 0.1 * torch.randn(T, B, 12, generator=g, dtype=F64)
    var_Q = torch.rand(T, B, 12, generator=g, dtype=F64)
    var_R = torch.rand(T, B, 9, generator=g, dtype=F64)
    return means, var_Q, var_R, truth


@pytest.mark.parametrize(
    "kw, err, match",
    [
        ({"skip": -5}, ValueError, "skip must be an int >= 0"),
        ({"skip": 20}, ValueError, "skip must be < T = 20"),
        ({"skip": True}, TypeError, "skip must be an int"),
        ({"skip": 2.0}, TypeError, "skip must be an int"),
        ({"q_scale": 0.0}, ValueError, "q_scale must be a finite positive number"),
        ({"q_scale": -1.0}, ValueError, "q_scale must be a finite positive number"),
        ({"q_scale": math.nan}, ValueError, "q_scale must be a finite positive number"),
    ],
)
def test_hst_estimation_errors_refuse_a_bad_skip_or_q_scale(kw, err, match):
    # was: skip=-5 scored the last 5 steps, skip >= T gave NaN, q_scale=0 gave inf/NaN
    with pytest.raises(err, match=match):
        hst_estimation_errors(*_scores_inputs(), **kw)


def test_hst_estimation_errors_late_scores_against_a_direct_rmse():
    means, var_Q, var_R, truth = _scores_inputs()
    e = hst_estimation_errors(means, var_Q, var_R, truth, q_scale=np.float64(0.5), skip=np.int64(7))
    q, r = hst_noise_variances(20)
    ref_Q = ((var_Q[7:, :, :9] / 0.5 - q[7:, None, None]) ** 2).mean(0).sqrt()
    ref_R = ((var_R[7:] - r[7:, None, None]) ** 2).mean(0).sqrt()
    torch.testing.assert_close(e["Q_late"], ref_Q, rtol=1e-13, atol=0)
    torch.testing.assert_close(e["R_late"], ref_R, rtol=1e-13, atol=0)
