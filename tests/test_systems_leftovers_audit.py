"""Audit of the simulation inputs, the train's sensor fault and scores, the CSTR steady state
and the train study's score rows.

References: the sensor fault against Eq. 65 written out, the RMSEs against a direct per-run
computation, the steady state against ``dx/dt = 0``, the feed drift against its recursion; bad
arguments are refused by name (devices, generators, counts, batch shapes, car counts).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from prognos_torch.studies.hst_estimation import (
    FAULT_COLS,
    Q_COLS,
    R_COLS,
    STATE_COLS,
    HSTProtocol,
    score_filter,
)
from prognos_torch.systems.cstr import (
    cstr_feed_drift,
    cstr_steady_state,
)
from prognos_torch.systems.high_speed_train import (
    HSTParams,
    hst_estimation_errors,
    hst_fault_model,
    hst_model,
    hst_noise_variances,
    hst_nominal_fault_model,
    hst_sensor_fault,
    simulate_hst,
)
from prognos_torch.systems.simulation import (
    accelerating_drift,
    initial_state,
    input_sequence,
    resolve_generator,
)

F64 = torch.float64
CUDA = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")


def _close(got, ref, rtol=1e-13):
    """``|got - ref| <= rtol |ref|`` entrywise, same shape (torch.testing's first call costs
    seconds)."""
    assert got.shape == ref.shape and got.dtype == ref.dtype
    assert bool(((got - ref).abs() <= rtol * ref.abs()).all()), (got, ref)


def _three_cars() -> HSTParams:
    return HSTParams(
        m=(8e4,) * 3, F_a=((0.0, 0.0),) * 5, F_s=(0.0, 0.0, 1.0, 0.0, 0.0), M=(0.01,) * 5
    )


# --------------------------------------------------------------------------- sensor fault
def test_hst_sensor_fault_is_eq_65_for_five_cars_and_refuses_other_widths():
    # was: a 3-car state (5,) read psi_4 psi_5 = v_1 v_2 silently; a 2-car state an IndexError
    psi = torch.tensor([[0.1, -0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9]], dtype=F64)
    got = hst_sensor_fault(psi, 3.0)
    ref = 1e-3 * (-1.0 + math.sin(0.1 * 0.4 * 0.5))  # Eq. 65: psi_4 psi_5, 1-based
    assert got.shape == (1,) and abs(float(got[0]) - ref) <= 1e-18
    assert float(hst_sensor_fault(psi, 20.0)[0]) == 0.0
    for width in (3, 5, 11):
        with pytest.raises(ValueError, match=r"psi must have shape \(\.\.\., 9\)"):
            hst_sensor_fault(torch.ones(width, dtype=F64), 3.0)
    with pytest.raises(TypeError, match="psi must be a floating-point tensor"):
        hst_sensor_fault(torch.ones(9, dtype=torch.int64), 3.0)


def test_train_faults_need_five_cars():
    # was: simulate_hst with 3 cars applied "Eq. 65" to v_1 v_2 (theta f_s = -1e-3 silently)
    p = _three_cars()
    with pytest.raises(ValueError, match="faults=True applies Eq. 63-65 of the five-car train"):
        simulate_hst(3, noise=False, params=p)
    with pytest.raises(ValueError, match="got HSTParams with 3 cars: pass faults=False"):
        hst_model(p)
    sim = simulate_hst(3, noise=False, params=p, faults=False)  # the healthy train runs
    assert sim.x.shape == (4, 1, 5) and bool((sim.theta == 0).all())


# --------------------------------------------------------------------------- parameters
def test_train_models_refuse_parameters_of_another_type():
    # was: params={} silently gave the default train; {"k": 1.0} an AttributeError
    for call in (
        lambda p: hst_model(p),
        lambda p: hst_fault_model(p),
        lambda p: hst_nominal_fault_model(p),
        lambda p: simulate_hst(2, noise=False, params=p),
    ):
        for bad in ({}, {"k": 1.0}):
            with pytest.raises(TypeError, match="params must be a HSTParams or None, got dict"):
                call(bad)


# --------------------------------------------------------------------------- scores
def _scores_inputs(T=6, B=2, seed=3):
    g = torch.Generator().manual_seed(seed)
    truth = torch.randn(T + 1, B, 12, generator=g, dtype=F64)
    means = truth[1:] + 0.1 * torch.randn(T, B, 12, generator=g, dtype=F64)
    var_Q = torch.rand(T, B, 12, generator=g, dtype=F64)
    var_R = torch.rand(T, B, 9, generator=g, dtype=F64)
    return means, var_Q, var_R, truth


def test_hst_estimation_errors_refuse_noise_variances_of_another_batch_shape():
    # was: var_R (T, 1, 9) gave R scores (1, 9) beside state scores (2, 9); var_Q (T, 3, 12)
    # Q scores (3, 9); var_R (T, 9) a RuntimeError of expand
    means, var_Q, var_R, truth = _scores_inputs()
    for vq, vr in (
        (var_Q, var_R[:, :1]),
        (var_Q, var_R[:, 0]),
        (torch.rand(6, 3, 12, dtype=F64), var_R),
        (var_Q[:, :1].expand(6, 2, 12).unsqueeze(1), var_R),
    ):
        with pytest.raises(ValueError, match=r"var_Q and var_R must have the batch shape \(2,\)"):
            hst_estimation_errors(means, vq, vr, truth)
    with pytest.raises(TypeError, match="var_R must be a torch.Tensor"):
        hst_estimation_errors(means, var_Q, var_R.numpy(), truth)
    # the per-run scores of a batch equal a direct RMSE of each run
    e = hst_estimation_errors(means, var_Q, var_R, truth, q_scale=0.5)
    q, r = hst_noise_variances(6)
    for b in range(2):
        ref_R = ((var_R[:, b] - r[:, None]) ** 2).mean(0).sqrt()
        ref_Q = ((var_Q[:, b, :9] / 0.5 - q[:, None]) ** 2).mean(0).sqrt()
        _close(e["R"][b], ref_R)
        _close(e["Q"][b], ref_Q)


class _Trajectory:
    """What score_filter reads of a filter run: means and the noise variances in use."""

    def __init__(self, means, var_Q, var_R):
        self.means, self.var_Q, self.var_R = means, var_Q, var_R


def _fake_run(monkeypatch, means, var_Q, var_R):
    import prognos_torch.studies.hst_estimation as study

    monkeypatch.setattr(study, "run_in_segments", lambda *a, **k: _Trajectory(means, var_Q, var_R))


def _proto(params: HSTParams, s: int) -> HSTProtocol:
    return HSTProtocol(
        runs=1, n_steps=4, window=1, segment=4, sens_runs=1, sens_steps=4, gammas=(), r_scales=(),
        qr_scales=(), q_scale=1.0, chol_D=(1e-2, 1e-2, 1e-4), p0_std=(1.0,) * (s + 3),
        params=params,
    )  # fmt: skip


def test_score_filter_names_the_columns_of_the_train_it_scores(monkeypatch):
    # was: a 3-car run (5 states) failed with an IndexError; a 6-car run (11 states) named
    # column 5 (x5) "RMSE v1" and dropped the last two components
    T, B = 4, 1
    for n in (3, 5, 6):
        s = 2 * n - 1
        g = torch.Generator().manual_seed(n)
        truth = torch.randn(T + 1, B, s + 3, generator=g, dtype=F64)
        means = torch.randn(T, B, s + 3, generator=g, dtype=F64)
        var_Q = torch.rand(T, B, s + 3, generator=g, dtype=F64)
        var_R = torch.rand(T, B, s, generator=g, dtype=F64)
        _fake_run(monkeypatch, means, var_Q, var_R)
        p = HSTParams(m=(8e4,) * n, F_a=((0.0, 0.0),) * s, F_s=(0.0,) * s, M=(0.01,) * s)
        rows, _ = score_filter(_proto(p, s), "m", None, None, truth, torch.zeros(T, B, s))
        (row,) = rows
        xs = [f"RMSE x{i}" for i in range(1, n)]
        vs = [f"RMSE v{i}" for i in range(1, n + 1)]
        for j, c in enumerate(xs + vs):  # state RMSE of component j, direct
            ref = float((means[:, 0, j] - truth[1:, 0, j]).square().mean().sqrt())
            assert row[c] == pytest.approx(ref, rel=1e-13, abs=0)
        q, r = hst_noise_variances(T)
        for i in range(1, s + 1):
            ref = float((var_R[:, 0, i - 1] - r).square().mean().sqrt())
            assert row[f"R{i} RMSE"] == pytest.approx(ref, rel=1e-13, abs=0)
            assert f"Q{i} RMSE" in row
        assert f"R{s + 1} RMSE" not in row and all(c in row for c in FAULT_COLS)
        if n == 5:
            assert all(c in row for c in STATE_COLS + Q_COLS + R_COLS)


def test_score_filter_refuses_a_measurement_scale_that_is_not_positive(monkeypatch):
    # was: r_scale=0 scored R against inf (an inf RMSE), -1 against negated variances
    means, var_Q, var_R, truth = _scores_inputs(T=4, B=1)
    _fake_run(monkeypatch, means, var_Q, var_R)
    for bad in (0.0, -1.0, math.nan, "1"):
        with pytest.raises(ValueError, match="r_scale must be a finite positive number"):
            score_filter(_proto(HSTParams(), 9), "m", None, None, truth, torch.zeros(4, 1, 9),
                         r_scale=bad)  # fmt: skip
    rows, _ = score_filter(_proto(HSTParams(), 9), "m", None, None, truth, torch.zeros(4, 1, 9),
                           r_scale=np.float64(2.0))  # fmt: skip
    r = hst_noise_variances(4)[1]
    ref = float((var_R[:, 0, 0] / 2.0 - r).square().mean().sqrt())
    assert rows[0]["R1 RMSE"] == pytest.approx(ref, rel=1e-13, abs=0)


# --------------------------------------------------------------------------- CSTR
@pytest.mark.parametrize(
    "kw, err, match",
    [
        ({"tol": -1.0}, ValueError, "tol must be a finite positive number"),
        ({"tol": 0.0}, ValueError, "tol must be a finite positive number"),
        ({"tol": math.nan}, ValueError, "tol must be a finite positive number"),
        ({"tol": True}, ValueError, "tol must be a finite positive number"),
        ({"max_iter": 0}, ValueError, "max_iter must be an int >= 1, got 0"),
        ({"max_iter": -3}, ValueError, "max_iter must be an int >= 1, got -3"),
        ({"max_iter": 2.5}, TypeError, "max_iter must be an int >= 1, got 2.5"),
        ({"max_iter": True}, TypeError, "max_iter must be an int >= 1, got True"),
    ],
)
def test_cstr_steady_state_refuses_a_bad_tolerance_or_iteration_count(kw, err, match):
    # was: "did not converge in 50 Newton steps" (tol <= 0 or NaN), "... in -3 / True Newton
    # steps", "'float' object cannot be interpreted as an integer"
    with pytest.raises(err, match=match):
        cstr_steady_state(**kw)


def test_feed_drift_refuses_a_step_that_is_not_an_int():
    # was: k = 52.5 gave 1.00004, between the drift of steps 52 (1.00003) and 53 (1.00006)
    for bad in (52.5, True, "52"):
        with pytest.raises(TypeError, match="k must be an int"):
            cstr_feed_drift(bad)
    with pytest.raises(TypeError, match="k must be an int"):
        accelerating_drift(3.0, 1.0, 0.5, 0)
    c = 1.0  # the recursion of Eq. 51 in exact steps of 1e-5 (k - 50)
    for k in range(51, 56):
        c += 1e-5 * (k - 50)
        assert cstr_feed_drift(np.int64(k)) == pytest.approx(c, rel=1e-15)


# --------------------------------------------------------------------------- generator
def test_resolve_generator_refuses_another_type_with_a_type_error():
    # was: ValueError for an int seed or a NumPy Generator
    for bad in (0, np.random.default_rng(0), "seed"):
        with pytest.raises(TypeError, match="generator must be a torch.Generator when noise=True"):
            resolve_generator(bad, True)
    with pytest.raises(TypeError, match="got Generator"):
        simulate_hst(2, generator=np.random.default_rng(0))
    with pytest.raises(ValueError, match="generator must be a torch.Generator when noise=True"):
        resolve_generator(None, True)  # a missing generator
    assert resolve_generator(0, False) is None
    g = torch.Generator()
    assert resolve_generator(g, np.bool_(True)) is g


# --------------------------------------------------------------------------- devices
def test_initial_state_and_inputs_refuse_a_tensor_on_another_device():
    # was: x0 and u on the meta device were moved silently (here: "Cannot copy out of meta
    # tensor"); a CPU x0 was moved to CUDA without a word
    x0 = torch.zeros(2, dtype=F64, device="meta")
    with pytest.raises(ValueError, match=r"x0 is on meta but the simulation runs on cpu"):
        initial_state(x0, 2, 3, F64, None)
    with pytest.raises(ValueError, match=r"x0 is on meta but the simulation runs on cpu"):
        initial_state(x0, 2, 3, F64, "cpu")
    u = torch.zeros(4, 1, dtype=F64, device="meta")
    with pytest.raises(ValueError, match=r"u is on meta but the simulation runs on cpu"):
        input_sequence(u, 4, 2, 1, F64, None)
    with pytest.raises(ValueError, match="x0 is on meta"):
        simulate_hst(2, noise=False, x0=torch.zeros(9, device="meta"))
    # tensors and arrays on the simulation's device are taken as before
    X = initial_state(np.array([1.0, 2.0]), 2, 3, F64, None)
    assert torch.equal(X, torch.tensor([[1.0, 2.0]] * 3, dtype=F64))
    X = initial_state(torch.tensor([1.0, 2.0], dtype=torch.float32), 2, 3, F64, "cpu")
    assert X.dtype == F64 and X.shape == (3, 2)


@CUDA
def test_simulators_refuse_a_cpu_state_for_a_cuda_run_and_take_a_cuda_one():
    with pytest.raises(ValueError, match="x0 is on cpu but the simulation runs on cuda"):
        simulate_hst(3, noise=False, x0=torch.zeros(9, dtype=F64), device="cuda")
    x0 = torch.full((9,), 0.01, dtype=F64, device="cuda")
    gpu = simulate_hst(3, noise=False, x0=x0, device="cuda")
    cpu = simulate_hst(3, noise=False, x0=x0.cpu())
    assert float((gpu.x.cpu() - cpu.x).abs().max()) <= 1e-12
    assert simulate_hst(3, noise=False, device="cuda").x.device.type == "cuda"  # default x0
