"""The forecaster-matrix study: quick mode end to end, and the pieces it composes."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch
from _study_helpers import quick_fixture, read_rows, trainer_fixture

from prognos_torch.studies import StudyConfig

RUNS = 2
quick_out = quick_fixture("forecaster-matrix", runs=RUNS)
fm = trainer_fixture("forecaster_matrix")
_rows = read_rows


def _f(v: str) -> float:
    return float(v) if v != "" else math.nan


def test_quick_outputs_complete_and_finite(fm, quick_out):
    for name in ("table.md", "results.csv", "run.json"):
        assert (quick_out / name).stat().st_size > 0
    meta = json.loads((quick_out / "run.json").read_text())
    assert meta["study"] == "forecaster-matrix" and meta["config"]["quick"] is True
    assert len(meta["figures"]) == 3
    for fig in meta["figures"]:
        assert (quick_out / fig).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    rows = _rows(quick_out)
    table = (quick_out / "table.md").read_text()
    methods = {r["method"] for r in rows}
    # every (series, learner, trainer, filter) is evaluated, or marked n/a or skipped (quick
    # mode's reduced matrix) in the matrix; every learner, trainer and filter runs somewhere
    for series in ("HI", "CSTR"):
        seen = set()
        for ln in fm.LEARNERS:
            for tn in fm.TRAINERS:
                for fl in fm.FILTERS:
                    evaluated = f"{series} | {ln}-{tn} | {fl}" in methods
                    prefix = f"| {series} | {ln} | {tn} | {fl} |"
                    marked = f"{prefix} n/a" in table or f"{prefix} skipped" in table
                    assert evaluated != marked, (series, ln, tn, fl)
                    if evaluated:
                        seen |= {ln, tn, fl}
        assert seen == set(fm.LEARNERS) | set(fm.TRAINERS) | set(fm.FILTERS)
        assert f"| {series} | ANFIS | closed | none | n/a" in table
        assert f"{series} | persistence-none | none" in methods
    assert "CSTR | LSSVR-EKF | none" in methods  # a 98-entry state on the CSTR: evaluated
    # on the full bearing series the 1,260-entry LS-SVR state is marked n/a
    s = fm._hi_series(fm._Protocol(StudyConfig(runs=RUNS)), "cpu")
    assert fm._not_applicable("LSSVR", "EKF", s) is not None
    assert fm._not_applicable("LSSVR", "closed", s) is None
    for r in rows:
        assert sum(1 for q in rows if q["method"] == r["method"]) == RUNS
        if r["diverged"] == "1.0":
            continue
        v = {k: _f(r[k]) for k in ("RMSE_1", "MAE_1", "RMSE_10", "MAE_10", "time_s")}
        assert all(math.isfinite(x) and x >= 0 for x in v.values()), r
        # RMSE >= MAE for the same errors (Jensen)
        assert v["RMSE_1"] >= v["MAE_1"] and v["RMSE_10"] >= v["MAE_10"]
        if r["method"].startswith("HI"):
            mass, hit, cens = _f(r["AL_mass"]), _f(r["alpha_lambda"]), _f(r["RUL_censored"])
            assert 0.0 <= mass <= 1.0 and hit in (0.0, 1.0) and 0.0 <= cens <= 1.0
            assert hit == float(mass >= fm.RUL_BETA)  # the mass criterion, beta = 0.5
            err = _f(r["RUL_MAE_d"])  # NaN exactly when every median is beyond the horizon
            assert math.isnan(err) == (cens == 1.0)
        else:
            assert r["AL_mass"] == "" and r["RUL_MAE_d"] == ""


def test_quick_persistence_errors_match_numpy(fm, quick_out):
    # independent alignment check: x^_{k+j} = x_k for every horizon j
    pr = fm._Protocol(StudyConfig(quick=True, runs=RUNS))
    rows = {r["method"]: r for r in _rows(quick_out) if r["run"] == "0"}
    for s in (fm._hi_series(pr, "cpu"), fm._cstr_series(StudyConfig(quick=True))):
        z = s.z.numpy()
        y = z[s.s0 :]
        e1 = z[s.s0 - 1 : -1] - y
        o = np.arange(0, len(y) - fm.H_MULTI + 1, s.stride)
        e10 = z[s.s0 - 1 + o] - y[o + fm.H_MULTI - 1]
        r = rows[f"{s.name} | persistence-none | none"]
        assert float(r["RMSE_1"]) == pytest.approx(np.sqrt(np.mean(e1**2)), rel=1e-12)
        assert float(r["MAE_1"]) == pytest.approx(np.mean(np.abs(e1)), rel=1e-12)
        assert float(r["RMSE_10"]) == pytest.approx(np.sqrt(np.mean(e10**2)), rel=1e-12)


def test_elm_kalman_equals_ridge(fm):
    # Q = 0 and P0 = R / lambda: the EKF posterior mean of the output weights is the ridge
    # solution (Bayesian linear regression), whatever the mini-batch size
    g = torch.Generator().manual_seed(3)
    z = torch.rand(120, generator=g, dtype=torch.float64).cumsum(0) / 60.0
    X, Y = fm.embed(z[:84], 4)  # 80 pairs: ten mini-batches of 8 on the bearing setting
    s = fm.ForecastProblem("HI", 4, X, Y[:, None], z, 84, stride=10)
    pr = fm._Protocol(StudyConfig(runs=2))
    cfg = StudyConfig(runs=2)
    ridge = fm._train("ELM", "closed", s, pr, cfg)
    for tn in ("EKF", "SRUKF"):
        kal = fm._train("ELM", tn, s, pr, cfg)
        k, r = kal.parameter_sets(), ridge.parameter_sets()
        torch.testing.assert_close(k["beta"], r["beta"], rtol=1e-6, atol=1e-6)
        torch.testing.assert_close(k["a"], r["a"], rtol=0, atol=0)
