"""The forecaster-matrix study: quick mode end to end, and the pieces it composes."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch
from _study_helpers import quick_fixture, read_rows, trainer_fixture
from torch.func import jacrev

from prognos_torch.learners import ANFIS, ELM
from prognos_torch.optim import fit
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
    s = fm._Series("HI", 4, X, Y[:, None], z, 84)
    pr = fm._Protocol(StudyConfig(runs=2))
    cfg = StudyConfig(runs=2)
    ridge = fm._train("ELM", "closed", s, pr, cfg)
    for tn in ("EKF", "SRUKF"):
        kal = fm._train("ELM", tn, s, pr, cfg)
        torch.testing.assert_close(kal.params["beta"], ridge.params["beta"], rtol=1e-6, atol=1e-6)
        torch.testing.assert_close(kal.params["a"], ridge.params["a"], rtol=0, atol=0)


def test_run_learner_equals_each_module(fm):
    mods = [ANFIS(3, 2, generator=torch.Generator().manual_seed(i)) for i in range(3)]
    L = fm._RunLearner(mods[0], fm._stack_params(mods), 3)
    x = torch.rand(3, 5, 7, 3, generator=torch.Generator().manual_seed(9), dtype=torch.float64)
    out = L(x)
    assert out.shape == (3, 5, 7, 1)
    for r, mod in enumerate(mods):
        torch.testing.assert_close(out[r], mod(x[r]), rtol=1e-13, atol=1e-13)
    # input gradient on the flattened run-leading batch (as learner_transition_model calls it)
    g = L.input_gradient(x.reshape(-1, 3)).reshape(3, 35, 1, 3)
    for r, mod in enumerate(mods):
        ref = torch.stack([jacrev(mod)(xi) for xi in x[r].reshape(-1, 3)])  # (35, 1, 3)
        torch.testing.assert_close(g[r], ref, rtol=1e-12, atol=1e-12)
    sel = L.select(torch.tensor([True, False, True]))
    torch.testing.assert_close(sel(x[[0, 2]]), out[[0, 2]], rtol=0, atol=0)
    with pytest.raises(ValueError, match="runs leading"):
        L(x[:2])


def test_adam_stack_equals_independent_runs(fm):
    # the summed loss separates over runs and Adam is element-wise: one stacked optimiser is R
    # independent Adam runs on the same mini-batches
    gen = torch.Generator().manual_seed(4)
    X = torch.rand(40, 3, generator=gen, dtype=torch.float64)
    Y = X.sum(-1, keepdim=True).sin()
    mods = [ELM(3, 6, generator=torch.Generator().manual_seed(i)) for i in range(2)]
    stack = fm._AdamStack(mods)
    opt = torch.optim.Adam(stack.parameters(), lr=1e-2)
    Xr, Yr = X.unsqueeze(1).expand(-1, 2, -1), Y.unsqueeze(1).expand(-1, 2, -1)
    fit(stack, opt, (Xr, Yr), epochs=3, batch_size=8, progress=False, loss_fn=fm._sum_mse)
    for r, mod in enumerate(mods):
        o = torch.optim.Adam([mod.beta], lr=1e-2)
        fit(mod, o, (X, Y), epochs=3, batch_size=8, progress=False)
        torch.testing.assert_close(stack.beta[r], mod.beta.detach(), rtol=1e-10, atol=1e-12)
        torch.testing.assert_close(stack.a[r], mod.a.detach(), rtol=0, atol=0)
