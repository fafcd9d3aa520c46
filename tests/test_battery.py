"""The circuit battery model against NASA progpy's BatteryCircuit (test-only oracle)."""

from __future__ import annotations

import warnings
from dataclasses import replace

import numpy as np
import pytest
import torch

from prognos_torch.systems.battery import (
    LOAD_CURRENTS,
    LOAD_TIMES,
    BatteryCircuitParams,
    battery_circuit_model,
    battery_circuit_rhs,
    battery_eod_event,
    battery_event_state,
    battery_voltage,
    load_controls,
    piecewise_load,
    simulate_battery,
)

progpy_models = pytest.importorskip("progpy.models")
from progpy.loading import Piecewise  # noqa: E402

t = lambda a: torch.as_tensor(a, dtype=torch.float64)  # noqa: E731


@pytest.fixture(scope="module")
def pp():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return progpy_models.BatteryCircuit()


def random_states(rng, n):
    p = BatteryCircuitParams()
    lo_qb = p.qMax - 0.95 * p.CMax  # SOC from 0.05 to 1
    return np.stack(
        [
            rng.uniform(270.0, 330.0, n),
            rng.uniform(lo_qb, p.qMax, n),
            rng.uniform(-20.0, 120.0, n),
            rng.uniform(-50.0, 600.0, n),
        ]
    )


@pytest.mark.parametrize("dt", [1.0, 0.25, 3.0])
def test_next_state_and_output_equal_progpy(pp, dt):
    rng = np.random.default_rng(int(dt * 100))
    X = random_states(rng, 500)
    current = rng.uniform(-1.0, 6.0, 500)
    ref_next = pp.next_state(pp.StateContainer(X.copy()), pp.InputContainer(current[None]), dt)
    ref_out = pp.output(pp.StateContainer(X.copy()))
    ref_es = pp.event_state(pp.StateContainer(X.copy()))["EOD"]
    ref_dx = pp.dx(pp.StateContainer(X.copy()), pp.InputContainer(current[None]))
    model = battery_circuit_model(dt)
    x, u = t(X.T), t(current[:, None])
    nxt = model.transition(x, u, 1)
    out = model.observe(x, u, 1)
    np.testing.assert_allclose(nxt.numpy(), ref_next.matrix.T, rtol=1e-12, atol=1e-10)
    np.testing.assert_allclose(out.numpy(), ref_out.matrix.T, rtol=1e-12, atol=1e-10)
    np.testing.assert_allclose(battery_event_state(x).numpy(), ref_es, rtol=1e-12, atol=1e-10)
    rhs = battery_circuit_rhs(x, u)
    np.testing.assert_allclose(rhs.numpy(), ref_dx.matrix.T, rtol=1e-11, atol=1e-12)
    # single samples (what vmap-free callers pass) agree with the batch
    assert torch.equal(model.transition(x[3], u[3], 1), nxt[3])


def test_step_into_a_buffer_and_fused_event_equal_the_plain_forms():
    rng = np.random.default_rng(7)
    X = random_states(rng, 400)
    x = t(X.T)
    u = t(rng.uniform(-1.0, 6.0, (400, 1)))
    model = battery_circuit_model(1.0)
    ref = model.transition(x, u, 1)
    # written into a component-major buffer row (the layout simulate_to_event uses)
    buf = torch.full((3, 4, 400), float("nan"), dtype=torch.float64)
    out = buf.movedim(1, -1)[1]
    got = model.transition_into(x, u, 1, out)
    assert got is out and torch.equal(out, ref)
    assert torch.isnan(buf[0]).all() and torch.isnan(buf[2]).all()
    # and into a plain contiguous tensor, the next state read from a buffer row
    nxt = model.transition_into(out, u, 2, torch.empty(400, 4, dtype=torch.float64))
    assert torch.equal(nxt, model.transition(ref, u, 2))
    # the EOD event (fused arithmetic) decides as the documented voltage v < VEOD
    p = BatteryCircuitParams()
    lo = p.qMax - 0.999 * p.CMax
    Xv = np.stack([X[0], rng.uniform(lo, lo + 0.2 * p.CMax, 400), X[2], X[3]])
    for xs in (x, t(Xv.T)):
        v = battery_voltage(xs)
        assert torch.equal(battery_eod_event()(xs), v < p.VEOD)
    below = battery_voltage(t(Xv.T)) < p.VEOD
    assert bool(below.any()) and not bool(below.all())
    # f_into is a capability of batched models only
    with pytest.raises(ValueError, match="f_into"):
        replace(model, batched=False)
    with pytest.raises(ValueError, match="f_into"):
        replace(model, f_into=1.0)


def test_parameters_are_progpy_defaults(pp):
    p = BatteryCircuitParams()
    for name in (
        "qMax CMax VEOD VDropoff Rp Cbp0 Cbp1 Cbp2 Cbp3 Rs Cs Rcp0 Rcp1 Rcp2 Ccp Ta Jt ha hcp hcs"
    ).split():
        assert getattr(p, name) == pp.parameters[name], name
    assert p.x0 == tuple(float(pp.parameters["x0"][k]) for k in pp.states)
    assert tuple(pp.states) == ("tb", "qb", "qcp", "qcs")
    assert tuple(pp.outputs) == ("t", "v")


def test_load_controls_follow_progpy_midpoint_rule():
    ref = Piecewise(dict, list(LOAD_TIMES), {"i": list(LOAD_CURRENTS)})
    u = load_controls(steps=4000, dt=1.0, t0=0.0)
    want = [ref(k - 0.5)["i"] for k in range(1, 4001)]
    assert u.shape == (4000, 1)
    assert u[:, 0].tolist() == want
    u2 = load_controls(steps=50, dt=2.5, t0=580.0)
    assert u2[:, 0].tolist() == [ref(580.0 + (k - 0.5) * 2.5)["i"] for k in range(1, 51)]


def test_simulated_discharge_and_eod_time_equal_progpy(pp):
    load = Piecewise(pp.InputContainer, list(LOAD_TIMES), {"i": list(LOAD_CURRENTS)})
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ref = pp.simulate_to_threshold(load, dt=1.0, save_freq=1.0)
    ref_t = np.array(ref.times)
    ref_x = np.array([[s[k] for k in pp.states] for s in ref.states], dtype=float)
    eod_ref = ref_t[-1]
    assert 2500 < eod_ref < 3500

    model = battery_circuit_model(1.0)
    event = battery_eod_event()
    U = load_controls(steps=5000)
    x = t(BatteryCircuitParams().x0)
    xs, eod = [x], None
    for k in range(1, 5001):
        x = model.transition(x, U[k - 1], k)
        xs.append(x)
        if bool(event(x)):
            eod = float(k)
            break
    ours = torch.stack(xs).numpy()
    assert eod == eod_ref
    assert ours.shape == ref_x.shape
    np.testing.assert_allclose(ours, ref_x, rtol=1e-9, atol=1e-9)
    # the voltage falls through VEOD at the event, not before
    v = battery_voltage(t(ours)).numpy()
    assert (v[:-1] >= 3.0).all() and v[-1] < 3.0

    # simulate_battery runs the same model (no noise): same trajectory
    sim = simulate_battery(len(ours) - 1, noise=False)
    np.testing.assert_array_equal(sim.x[:, 0].numpy(), ours)


def test_simulate_battery_noise_is_reproducible():
    a = simulate_battery(50, 3, generator=torch.Generator().manual_seed(4))
    b = simulate_battery(50, 3, generator=torch.Generator().manual_seed(4))
    assert torch.equal(a.y, b.y)
    assert a.y.shape == (50, 3, 2) and a.x.shape == (51, 3, 4)
    # per-run noise streams: run 0 of a batch equals a single run with the same seed stream
    assert float((a.y[:, 0] - a.y[:, 1]).abs().max()) > 0


def test_bad_input_messages():
    model = battery_circuit_model()
    x = t(BatteryCircuitParams().x0)
    with pytest.raises(ValueError, match=r"u must have shape \(\.\.\., 1\)"):
        model.transition(x, t([1.0, 2.0]), 1)
    with pytest.raises(ValueError, match="needs the current"):
        model.transition(x, None, 1)
    with pytest.raises(ValueError, match="dt must be"):
        battery_circuit_model(0.0)
    with pytest.raises(ValueError, match="one more entry"):
        piecewise_load([1.0, 2.0], [1.0, 2.0])
    with pytest.raises(ValueError, match="strictly increasing"):
        piecewise_load([2.0, 1.0], [1.0, 2.0, 3.0])
    with pytest.raises(ValueError, match="Cs must be > 0"):
        BatteryCircuitParams(Cs=0.0)
    with pytest.raises(ValueError, match="process_noise_std"):
        battery_circuit_model(process_noise_std=[1.0, 2.0])
