"""Audit of the CSTR, Lorenz, three-tank and run-to-failure simulators and their shared helpers:
NumPy parameters, flags read by their truth value, integer dtypes, parameters of another type,
states and inputs of another width, bool/complex initial states, non-finite ranges and seeds.

Every simulation here is a few steps long; references are the Python-valued runs, closed forms
or per-element evaluations, never numbers copied from the output.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pytest
import torch

from prognos_torch.core.validation import check_params_finite
from prognos_torch.systems.cstr import (
    CSTRParams,
    cstr_joint_model,
    cstr_model,
    cstr_rhs,
    cstr_steady_state,
    simulate_cstr,
)
from prognos_torch.systems.lorenz import LorenzParams, lorenz_model, lorenz_rhs, simulate_lorenz
from prognos_torch.systems.run_to_failure import run_to_failure_set, simulate_run_to_failure
from prognos_torch.systems.simulation import resolve_generator
from prognos_torch.systems.three_tank import (
    ThreeTankParams,
    simulate_three_tank,
    three_tank_equilibrium,
    three_tank_joint_model,
    three_tank_model,
    three_tank_rhs,
)

f64 = torch.float64
CSTR_X0 = (0.0372, 402.35)  # (passed so that no test pays forward AD's set-up in the Newton solve)


def gen(seed: int) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def _close(a, b, rtol: float = 1e-14) -> None:
    assert a.shape == b.shape and a.dtype == b.dtype
    assert bool(((a - b).abs() <= rtol * b.abs()).all()), (a, b)


def _same(a, b) -> None:
    for name in ("t", "x", "y", "theta"):
        assert torch.equal(getattr(a, name), getattr(b, name)), name


# ------------------------------------------------------------------ NumPy parameters
def test_check_params_finite_takes_numpy_reals_and_refuses_bools_and_text():
    """np.float32 / np.int64 fields were a TypeError; np.bool_, bool and text still are."""

    @dataclass
    class P:
        a: object = 1.0
        b: object = (1.0, 2)

    check_params_finite(P(np.float32(0.5), (np.int64(3), np.float64(2.0))))
    for bad in (np.bool_(True), True, "1.0", None):
        with pytest.raises(TypeError, match=r"P\.a must be a real number"):
            check_params_finite(P(a=bad))
    with pytest.raises(ValueError, match=r"P\.b must be finite"):
        check_params_finite(P(b=(1.0, np.float32("nan"))))


def test_simulator_parameters_take_numpy_values_stored_as_python_numbers():
    """CSTRParams, ThreeTankParams (and LorenzParams' np.int64) refused NumPy values; they are
    stored as the Python numbers, so the runs equal those with the Python values bit for bit."""
    p = CSTRParams(dt=np.float32(0.02), k_fault=np.int64(2), drift_rate=np.float64(1e-3))
    assert type(p.dt) is float and type(p.k_fault) is int and type(p.drift_rate) is float
    q = CSTRParams(dt=float(np.float32(0.02)), k_fault=2, drift_rate=1e-3)
    assert p == q
    a = simulate_cstr(4, params=p, x0=CSTR_X0, generator=gen(1))
    _same(a, simulate_cstr(4, params=q, x0=CSTR_X0, generator=gen(1)))

    p = ThreeTankParams(az2=np.float32(0.6), k_fault=np.int64(1))
    q = ThreeTankParams(az2=float(np.float32(0.6)), k_fault=1)
    assert p == q and type(p.az2) is float and type(p.k_fault) is int
    _same(
        simulate_three_tank(4, params=p, generator=gen(2)),
        simulate_three_tank(4, params=q, generator=gen(2)),
    )

    p = LorenzParams(a=np.float32(10.0), substeps=np.int64(2))
    assert p == LorenzParams(substeps=2) and type(p.a) is float and type(p.substeps) is int
    _same(
        simulate_lorenz(3, params=p, noise=False),
        simulate_lorenz(3, params=LorenzParams(substeps=2), noise=False),
    )


def test_scalar_parameters_refuse_sequences():
    """CSTRParams(dt=(0.02,)) and LorenzParams(a=[10.0]) were accepted and failed later, in the
    integrator or the right-hand side."""
    for make, name in (
        (lambda: CSTRParams(dt=(0.02,)), r"CSTRParams\.dt"),
        (lambda: LorenzParams(a=[10.0]), r"LorenzParams\.a"),
        (lambda: ThreeTankParams(az2=(0.6, 0.7)), r"ThreeTankParams\.az2"),
    ):
        with pytest.raises(TypeError, match=name + " must be a real number"):
            make()


# ------------------------------------------------------------------ flags
def test_flags_are_bools_not_truth_values():
    """noise="no", drift="no", control="no" and gaps="no" were read as true."""
    with pytest.raises(TypeError, match="noise must be a bool, got 'no'"):
        resolve_generator(None, "no")
    calls = [
        lambda: simulate_cstr(2, noise="no"),
        lambda: simulate_cstr(2, noise=False, drift="no"),
        lambda: cstr_model(drift="no"),
        lambda: simulate_lorenz(2, noise="no"),
        lambda: simulate_three_tank(2, noise="no"),
        lambda: simulate_three_tank(2, noise=False, drift="no"),
        lambda: three_tank_model(control="no"),
        lambda: three_tank_model(drift="no"),
        lambda: three_tank_joint_model(control="no"),
        lambda: simulate_run_to_failure("hump", gen(0), gaps="no"),
    ]
    for call in calls:
        with pytest.raises(TypeError, match=r"(noise|drift|control|gaps) must be a bool, got 'no'"):
            call()
    a = simulate_cstr(3, x0=CSTR_X0, noise=np.bool_(False), drift=np.bool_(False))
    b = simulate_cstr(3, x0=CSTR_X0, noise=False, drift=False)
    _same(a, b)
    assert a.meta["noise"] is False
    assert three_tank_model(control=np.bool_(True)).control_dim == 2


# ------------------------------------------------------------------ dtypes, params
def test_integer_dtypes_are_refused_not_truncated():
    """cstr_steady_state(dtype=int64) gave [0, 402], three_tank_equilibrium zeros and
    lorenz_model a zero chol_Q; the simulators failed naming x."""
    calls = [
        lambda d: cstr_steady_state(dtype=d),
        lambda d: three_tank_equilibrium(dtype=d),
        lambda d: lorenz_model(process_noise_std=0.5, dtype=d),
        lambda d: cstr_model(dtype=d),
        lambda d: cstr_joint_model(dtype=d),
        lambda d: three_tank_model(dtype=d),
        lambda d: three_tank_joint_model(dtype=d),
        lambda d: simulate_cstr(2, noise=False, dtype=d),
        lambda d: simulate_lorenz(2, noise=False, dtype=d),
        lambda d: simulate_three_tank(2, noise=False, dtype=d),
    ]
    for call in calls:
        with pytest.raises(TypeError, match="dtype must be a floating-point torch.dtype"):
            call(torch.int64)


def test_parameters_of_another_type_are_refused():
    """A dict failed on a missing attribute; an empty one silently gave the defaults."""
    for call in (
        lambda p: simulate_cstr(2, noise=False, params=p),
        lambda p: simulate_lorenz(2, noise=False, params=p),
        lambda p: simulate_three_tank(2, noise=False, params=p),
        lambda p: three_tank_equilibrium(p),
    ):
        for bad in ({}, {"dt": 0.01}):
            with pytest.raises(TypeError, match=r"params must be a \w+Params or None, got dict"):
                call(bad)


def test_steady_state_and_equilibrium_refuse_text_and_bools():
    """C_AF="1" / True and az2="0.6" were read by float()."""
    for bad in ("1", True):
        with pytest.raises(ValueError, match="C_AF must be a finite number"):
            cstr_steady_state(C_AF=bad)
    with pytest.raises(ValueError, match="az2 must be a finite positive number, got '0.6'"):
        three_tank_equilibrium(az2="0.6")


def test_equilibrium_with_no_inflow_to_tank_one():
    """Q1 = 0 with a closed valve az1 = 0 was a ZeroDivisionError (the levels are undetermined);
    with open valves the closed form gives equal levels h1 = h3 = h2."""
    with pytest.raises(ValueError, match="az1 > 0 and az3 > 0"):
        three_tank_equilibrium(ThreeTankParams(Q1=0.0, az1=0.0))
    with pytest.raises(ValueError, match="az1 > 0 and az3 > 0"):
        three_tank_equilibrium(ThreeTankParams(Q1=0.0, az3=0.0))
    p = ThreeTankParams(Q1=0.0)
    h2 = (p.Q2 / (p.az2 * p.S_n)) ** 2 / (2.0 * p.g)  # Q20 = Q2
    _close(three_tank_equilibrium(p), torch.tensor([h2, h2, h2], dtype=f64))


# ------------------------------------------------------------------ shapes
def test_rates_refuse_states_and_inputs_of_another_width():
    """cstr_rhs and lorenz_rhs read a wider state by its first components and returned another
    width; three_tank_rhs ignored a third pump column; a C_AF or az2 wider than the batch failed
    in torch.stack."""
    cp, lp, tp = CSTRParams(), LorenzParams(), ThreeTankParams()
    with pytest.raises(ValueError, match=r"x must have shape \(\.\.\., 2\) \[C_A, T\]"):
        cstr_rhs(torch.tensor([0.04, 400.0, 1.0], dtype=f64), 1.0, cp)
    with pytest.raises(ValueError, match=r"x must have shape \(\.\.\., 3\) \[x, y, z\]"):
        lorenz_rhs(torch.ones(2, 4, dtype=f64), lp)
    with pytest.raises(TypeError, match="x must be a floating-point tensor"):
        lorenz_rhs(torch.ones(3, dtype=torch.int64), lp)
    x = torch.tensor([[1.0, 0.9, 0.8]], dtype=f64)
    with pytest.raises(ValueError, match=r"u must have shape \(\.\.\., 2\)"):
        three_tank_rhs(x, 0.6, torch.full((1, 3), 4e-5, dtype=f64), tp)
    with pytest.raises(ValueError, match=r"u must have shape \(\.\.\., 2\)"):
        three_tank_rhs(x, 0.6, torch.full((4, 2), 4e-5, dtype=f64), tp)
    with pytest.raises(ValueError, match=r"az2 must have shape \(\.\.\.\)"):
        three_tank_rhs(x, torch.full((5,), 0.6, dtype=f64), None, tp)
    xc = torch.tensor([0.04, 400.0], dtype=f64)
    with pytest.raises(ValueError, match=r"C_AF must have shape \(\.\.\.\)"):
        cstr_rhs(xc, torch.ones(5, dtype=f64), cp)
    # a C_AF per batch element equals the per-element evaluation
    X = torch.tensor([[0.04, 400.0], [0.05, 390.0]], dtype=f64)
    caf = torch.tensor([1.0, 1.2], dtype=f64)
    ref = torch.stack([cstr_rhs(X[i], float(caf[i]), cp) for i in range(2)])
    _close(cstr_rhs(X, caf, cp), ref)


def test_bool_and_complex_initial_states_and_inputs_are_refused():
    """A bool x0 was read as ones and a complex one lost its imaginary part (a warning only)."""
    with pytest.raises(TypeError, match="x0 must hold real numbers"):
        simulate_lorenz(2, noise=False, x0=torch.tensor([True, True, True]))
    with pytest.raises(TypeError, match="x0 must hold real numbers"):
        simulate_lorenz(2, noise=False, x0=np.array([1 + 1j, 1.0, 1.0]))
    with pytest.raises(TypeError, match="u must hold real numbers"):
        simulate_three_tank(2, noise=False, u=torch.ones(2, 2, dtype=torch.complex128))


# ------------------------------------------------------------------ run to failure
def test_run_to_failure_refuses_infinite_ranges_and_keeps_numpy_dt_in_float64():
    """An inf bound was a RuntimeError in the uniform draw; an np.float32 dt divided the life in
    float32 (seed 11377: 1255 samples, the Python value of the same dt 1254)."""
    for kw in ({"life": (3.0, math.inf)}, {"rise": (2.0, math.inf)}, {"noise": (0.0, math.inf)}):
        (name,) = kw
        with pytest.raises(ValueError, match=rf"{name} must satisfy low <= high .* \(finite\)"):
            simulate_run_to_failure("hump", gen(0), **kw)
    with pytest.raises(ValueError, match="dt must be a finite positive number"):
        simulate_run_to_failure("hump", gen(0), dt=math.inf)
    a = simulate_run_to_failure("hump", gen(11377), dt=np.float32(0.01), gaps=False)
    b = simulate_run_to_failure("hump", gen(11377), dt=float(np.float32(0.01)), gaps=False)
    assert a.t.shape == b.t.shape
    assert torch.equal(a.t, b.t) and torch.equal(a.y, b.y)


def test_run_to_failure_names_a_bad_family_seed_or_families():
    """A list family was 'unhashable type'; a float seed was truncated (1.7 gave seed 1's
    records); families="shocks" was read letter by letter (family 's')."""
    with pytest.raises(ValueError, match="family must be one of"):
        simulate_run_to_failure(["hump"], gen(0))
    for bad in (1.7, True, "1"):
        with pytest.raises(TypeError, match="seed must be an int"):
            run_to_failure_set(1, seed=bad, families=("hump",))
    with pytest.raises(ValueError, match="families must be a sequence of names"):
        run_to_failure_set(1, families="shocks")
    a = run_to_failure_set(1, seed=np.int64(4), families=["hump"])
    b = run_to_failure_set(1, seed=4, families=("hump",))
    assert list(a) == ["hump 0"] and torch.equal(a["hump 0"].y, b["hump 0"].y)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_run_to_failure_refuses_a_cuda_generator():
    """A CUDA generator failed inside a CPU draw."""
    with pytest.raises(ValueError, match="generator must be a CPU torch.Generator"):
        simulate_run_to_failure("hump", torch.Generator(device="cuda"))
