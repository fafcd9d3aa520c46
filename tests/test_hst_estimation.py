"""Fault estimation on the high-speed train: the nominal model, the per-run simulation, paper
004's filters, and their scores (checked against Eq. 67-68 in closed form and direct RMSEs)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from prognos_torch.adapt import MovingWindow, RobustBound
from prognos_torch.filters import ukf
from prognos_torch.studies.hst_estimation import (
    FAULT_COLS,
    OPT,
    ORACLE,
    Q_COLS,
    R_COLS,
    STATE_COLS,
    SUMMARY,
    HSTProtocol,
    gamma_sweep,
    hst_filters,
    noise_sweep,
    score_filter,
    score_filters,
)
from prognos_torch.systems import (
    HSTParams,
    hst_fault_model,
    hst_nominal_fault_model,
    simulate_hst,
    simulate_hst_runs,
)

P = HSTParams()
QS = P.sigma**2
CHOL_D = (1e-2, 1e-2, 1e-4)


def _proto(**kw) -> HSTProtocol:
    base = dict(runs=2, n_steps=30, window=10, segment=12, sens_runs=1, sens_steps=20,
                gammas=(1.05, 10.0), r_scales=(1.0, 0.01), qr_scales=(1e-4,), q_scale=QS,
                chol_D=CHOL_D, p0_std=(0.1,) * 9 + CHOL_D)  # fmt: skip
    return HSTProtocol(**(base | kw))


def _gen(i: int) -> torch.Generator:
    return torch.Generator().manual_seed(100 + i)


def _q_true(T: int) -> np.ndarray:  # Eq. 67 at the library steps k = 1..T (Q_{k-1})
    return 1.0 + 0.5 * np.sin(0.0003 * (np.arange(1, T + 1) - 1))


def _r_true(T: int) -> np.ndarray:  # Eq. 68
    return 1.1 + 0.08 * np.cos(0.0002 * np.arange(1, T + 1))


def _rms(x) -> float:
    return float(np.sqrt(np.mean(np.square(x))))


# ----------------------------------------------------------------------------- systems
def test_nominal_model_has_the_constant_noise_and_the_true_dynamics():
    m = hst_nominal_fault_model(P, q_level=2.0, r_level=11.0, chol_D=CHOL_D, q_scale=QS)
    true = hst_fault_model(P, chol_D=CHOL_D, q_scale=QS)
    for k in (1, 7, 400):
        n = m.noise(k)
        std = [math.sqrt(2.0 * QS)] * 9 + list(CHOL_D)
        torch.testing.assert_close(n.chol_Q, torch.diag(torch.tensor(std, dtype=torch.float64)))
        torch.testing.assert_close(n.chol_R, math.sqrt(11.0) * torch.eye(9, dtype=torch.float64))
    x = 0.1 * torch.randn(4, 12, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    torch.testing.assert_close(m.transition(x, None, 300), true.transition(x, None, 300))
    torch.testing.assert_close(m.observe(x, None, 300), true.observe(x, None, 300))
    with pytest.raises(ValueError, match="r_level"):
        hst_nominal_fault_model(P, r_level=-1.0)


def test_simulate_runs_stacks_one_simulation_per_generator():
    truth, y, t = simulate_hst_runs(15, [_gen(0), _gen(1), _gen(2)], params=P, q_scale=QS)
    assert truth.shape == (16, 3, 12) and y.shape == (15, 3, 9) and t.shape == (16,)
    one = simulate_hst(15, 1, params=P, q_scale=QS, generator=_gen(1))
    torch.testing.assert_close(truth[:, 1], torch.cat([one.x, one.theta], -1)[:, 0])
    torch.testing.assert_close(y[:, 1], one.y[:, 0])
    two, _, _ = simulate_hst_runs(15, [_gen(0), _gen(1)], params=P, q_scale=QS)
    torch.testing.assert_close(two, truth[:, :2])  # a run does not depend on how many are drawn
    assert float(t[-1]) == pytest.approx(15 * P.sigma)
    with pytest.raises(ValueError, match="generators"):
        simulate_hst_runs(15, [])


# ----------------------------------------------------------------------------- filters
def test_paper_filters_by_name():
    fs = hst_filters(P, 25)
    assert list(fs) == ["UKF", "RUKF", "ARUKF", "RUKF" + OPT, "ARUKF" + OPT, "AUKF"]
    assert fs["UKF"].robust is None and fs["UKF"].noise is None
    assert fs["RUKF"].robust.gamma == P.gamma and fs["RUKF"].robust.bound == "printed"
    assert fs["RUKF" + OPT].robust.bound == "optimised" and fs["RUKF" + OPT].noise is None
    for name in ("ARUKF", "ARUKF" + OPT, "AUKF"):
        assert isinstance(fs[name].noise, MovingWindow) and fs[name].noise.window == 25, name
        assert fs[name].noise.diagonal, name
    assert fs["AUKF"].robust is None and isinstance(fs["ARUKF"].robust, RobustBound)
    assert hst_filters(P, 25, gamma=10.0)["ARUKF"].robust.gamma == 10.0


# ----------------------------------------------------------------------------- scores
@pytest.fixture(scope="module")
def data():
    proto = _proto()
    truth, ys, _ = simulate_hst_runs(proto.n_steps, [_gen(0), _gen(1)], params=P, q_scale=QS)
    return proto, truth, ys


def test_scores_are_direct_rmses_and_eq_67_68_errors(data):
    proto, truth, ys = data
    T = proto.n_steps
    nominal = hst_nominal_fault_model(P, chol_D=CHOL_D, q_scale=QS)
    rows, tr = score_filter(proto, "UKF", ukf(1.0, 0.0, 1.0, sqrt=True), nominal, truth, ys)
    assert [r["run"] for r in rows] == [0, 1] and {r["method"] for r in rows} == {"UKF"}
    assert list(rows[0]) == ["run", "method", *SUMMARY[:-1], *STATE_COLS, *FAULT_COLS, *Q_COLS,
                             *R_COLS, "time_s"]  # fmt: skip
    err = (tr.means - truth[1:]).numpy()
    for b, r in enumerate(rows):
        per_state = [_rms(err[:, b, j]) for j in range(9)]
        per_fault = [_rms(err[:, b, 9 + j]) for j in range(3)]
        assert r["RMSE v1"] == pytest.approx(per_state[4], rel=1e-12)
        assert r["state RMSE"] == pytest.approx(np.mean(per_state), rel=1e-12)
        assert r["fault RMSE"] == pytest.approx(np.mean(per_fault), rel=1e-12)
        # fixed nominal Q = q_scale I, R = 1.1 I against Eq. 67-68 (Q in the units of Eq. 67)
        assert r["Q RMSE"] == pytest.approx(_rms(1.0 - _q_true(T)), rel=1e-9)
        assert r["R RMSE"] == pytest.approx(_rms(1.1 - _r_true(T)), rel=1e-9)
        assert r["R RMSE (k>N)"] == pytest.approx(_rms(1.1 - _r_true(T)[proto.window :]), rel=1e-9)
        assert r["time_s"] > 0
    oracle = hst_fault_model(P, chol_D=CHOL_D, q_scale=QS)
    rows, _ = score_filter(proto, ORACLE, ukf(1.0, 0.0, 1.0, sqrt=True), oracle, truth, ys,
                           detail=False)  # fmt: skip
    assert list(rows[0]) == ["run", "method", *SUMMARY]
    assert all(r["Q RMSE"] < 1e-12 and r["R RMSE"] < 1e-12 for r in rows)


def test_score_filters_keeps_run_0_and_the_mean_noise(data):
    proto, truth, ys = data
    nominal = hst_nominal_fault_model(P, chol_D=CHOL_D, q_scale=QS)
    fs = hst_filters(P, proto.window)
    jobs = [("UKF", fs["UKF"], nominal), ("AUKF", fs["AUKF"], nominal)]
    rows, traces = score_filters(proto, jobs, truth, ys)
    assert [r["method"] for r in rows] == ["UKF", "UKF", "AUKF", "AUKF"]
    alone, tr = score_filter(proto, "AUKF", fs["AUKF"], nominal, truth, ys)
    torch.testing.assert_close(traces["AUKF"].means, tr.means[:, 0])
    torch.testing.assert_close(traces["AUKF"].R, tr.var_R.mean(1))
    assert traces["UKF"].Q.shape == (proto.n_steps, 12)
    torch.testing.assert_close(traces["UKF"].Q[:, :9], torch.full((30, 9), QS, dtype=torch.float64))
    assert rows[2]["state RMSE"] == alone[0]["state RMSE"]


def test_gamma_sweep_rows(data):
    proto, truth, ys = data
    rows = gamma_sweep(proto, truth, ys)
    names = [f"{n} (gamma={g:g})" for g in (1.05, 10.0) for n in ("RUKF", "ARUKF")]
    assert [r["method"] for r in rows] == [n for n in names for _ in range(2)]
    q_err = _rms(1.0 - _q_true(proto.n_steps))  # the nominal Q of the fixed-noise RUKF
    assert all(
        r["Q RMSE"] == pytest.approx(q_err, rel=1e-9) for r in rows if "ARUKF" not in r["method"]
    )
    # Theorem 1 as printed (gamma = 1.05) is far worse than gamma = 10 (near the plain UKF)
    by = {r["method"]: r["state RMSE"] for r in rows if r["run"] == 0}
    assert by["RUKF (gamma=1.05)"] > 2 * by["RUKF (gamma=10)"]


def test_noise_sweep_rows_score_noise_in_the_units_of_eq_67_68():
    proto = _proto(sens_runs=1, sens_steps=20)
    rows = noise_sweep(proto, _gen)
    names = [f"{n}, R x{s:g}" for s in (1.0, 0.01) for n in (ORACLE, "RUKF" + OPT, "ARUKF" + OPT)]
    assert [r["method"] for r in rows] == names + [f"{ORACLE}, Q,R x0.0001"]
    by = {r["method"]: r for r in rows}
    for s in (1.0, 0.01):
        assert by[f"{ORACLE}, R x{s:g}"]["R RMSE"] < 1e-12  # divided by r_scale
        # nominal R = s * 1.1 I, scored as 1.1 against Eq. 68
        assert by[f"RUKF{OPT}, R x{s:g}"]["R RMSE"] == pytest.approx(_rms(1.1 - _r_true(20)))
    assert by[f"{ORACLE}, Q,R x0.0001"]["Q RMSE"] < 1e-12  # divided by 1e-4 q_scale
    # the simulation of the sweep: R x1 draws the same runs as simulate_hst_runs with _gen
    truth, ys, _ = simulate_hst_runs(20, [_gen(0)], params=P, q_scale=QS)
    oracle = hst_fault_model(P, chol_D=CHOL_D, q_scale=QS)
    alone, _ = score_filter(proto, "x", ukf(1.0, 0.0, 1.0, sqrt=True), oracle, truth, ys)
    assert by[f"{ORACLE}, R x1"]["state RMSE"] == alone[0]["state RMSE"]


def test_state_and_fault_names():
    from prognos_torch.systems import HST_FAULT_NAMES, hst_state_names

    assert hst_state_names(5) == ("x1", "x2", "x3", "x4", "v1", "v2", "v3", "v4", "v5")
    assert hst_state_names(2) == ("x1", "v1", "v2")
    assert HST_FAULT_NAMES == ("f_a^c", "f_a^d", "f_s")
    sim = simulate_hst(5, generator=torch.Generator().manual_seed(0))
    assert sim.meta["state_names"] == hst_state_names(5)
    assert sim.meta["param_names"] == HST_FAULT_NAMES
