"""The forecaster-matrix study: quick mode end to end, and the pieces it composes."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch
from _study_helpers import means, quick_fixture, read_rows, trainer_fixture

from prognos_torch import studies
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
    pr = fm._Protocol(StudyConfig(runs=RUNS))
    s = fm._hi_series(pr, "cpu")
    assert studies.not_applicable("LSSVR", "EKF", s, pr.training) is not None
    assert studies.not_applicable("LSSVR", "closed", s, pr.training) is None
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
    # 80 pairs: ten mini-batches of 8 on the bearing setting
    s = studies.forecast_problem("HI", z[:84], z, 4, stride=10, s0=84)
    pr, cfg = fm._Protocol(StudyConfig(runs=2)), StudyConfig(runs=2)
    kw = dict(runs=pr.runs, generator=cfg.generator)
    ridge = studies.train_forecasters("ELM", "closed", s, pr.training, **kw)
    for tn in ("EKF", "SRUKF"):
        kal = studies.train_forecasters("ELM", tn, s, pr.training, **kw)
        k, r = kal.parameter_sets(), ridge.parameter_sets()
        torch.testing.assert_close(k["beta"], r["beta"], rtol=1e-6, atol=1e-6)
        torch.testing.assert_close(k["a"], r["a"], rtol=0, atol=0)


# Quick-mode headline numbers (2 runs, float64). The bearing health indicator moves at the 1e-6
# level with the BLAS thread count; `prognos study` runs single-threaded unless --threads says
# otherwise (so does the test session, tests/conftest.py), which makes the numbers below
# reproducible to rounding. Particle-filter and ImSRUKF cells amplify rounding differences (see
# docs/RESULTS.md) and get rel 1e-4, the others rel 1e-6.
QUICK_RMSE_1 = {
    "HI | ELM-closed | none": 0.03249166949,
    "HI | ELM-closed | PF": 0.04366889206,
    "HI | ELM-closed | EKPF": 0.04552969001,
    "HI | ELM-closed | STPF": 0.0425817915,
    "HI | ELM-closed | SCKF": 0.0411033373,
    "HI | ELM-closed | STSCKF": 0.03602227768,
    "HI | ELM-EKF | none": 0.03249166949,
    "HI | ELM-SRUKF | none": 0.03249166949,
    "HI | ELM-ImSRUKF | none": 0.1377086415,
    "HI | ELM-Adam | none": 0.1407216121,
    "HI | LSSVR-closed | none": 0.03278105718,
    "HI | LSSVR-closed | PF": 0.04936251591,
    "HI | LSSVR-closed | EKPF": 0.05381231642,
    "HI | LSSVR-closed | STPF": 0.04353286947,
    "HI | LSSVR-closed | SCKF": 0.04254550228,
    "HI | LSSVR-closed | STSCKF": 0.03618773052,
    "HI | LSSVR-EKF | none": 0.03299395231,
    "HI | LSSVR-SRUKF | none": 0.03299395231,
    "HI | LSSVR-ImSRUKF | none": 0.1142430113,
    "HI | LSSVR-Adam | none": 0.2080776866,
    "HI | ANFIS-EKF | none": 0.03222623134,
    "HI | ANFIS-EKF | PF": 0.04524134369,
    "HI | ANFIS-EKF | EKPF": 0.05829699173,
    "HI | ANFIS-EKF | STPF": 0.04586843418,
    "HI | ANFIS-EKF | SCKF": 0.04671296185,
    "HI | ANFIS-EKF | STSCKF": 0.04416490177,
    "HI | ANFIS-SRUKF | none": 0.03515076948,
    "HI | ANFIS-ImSRUKF | none": 0.05833854229,
    "HI | ANFIS-Adam | none": 0.08744750268,
    "CSTR | ELM-closed | none": 0.03645572569,
    "CSTR | ELM-closed | PF": 0.4380247643,
    "CSTR | ELM-closed | EKPF": 0.1004775844,
    "CSTR | ELM-closed | STPF": 0.04735208097,
    "CSTR | ELM-closed | SCKF": 0.07099474491,
    "CSTR | ELM-closed | STSCKF": 0.03027349113,
    "CSTR | ELM-EKF | none": 0.03645572568,
    "CSTR | ELM-SRUKF | none": 0.03645572569,
    "CSTR | ELM-ImSRUKF | none": 0.07868839538,
    "CSTR | ELM-Adam | none": 0.5209577308,
    "CSTR | LSSVR-closed | none": 0.3132979511,
    "CSTR | LSSVR-closed | PF": 0.4707243514,
    "CSTR | LSSVR-closed | EKPF": 0.3487744914,
    # this cell moved from 0.3401465171 with the engine's reordered operations (rounding
    # level, the optimiser-speed merge) and from 0.3273114624 when the EKF downdate took
    # W = Z^T S_zz^{-T} instead of a triangular solve (the STPF's per-particle STEKF): each
    # time run 1's particles resample differently; run 0 agrees to 3e-9. From 0.3223142925
    # when the RBF distance expansion took the data from the support vectors' centre (run 0
    # agrees to 2e-9)
    "CSTR | LSSVR-closed | STPF": 0.3212840306,
    "CSTR | LSSVR-closed | SCKF": 0.3428559002,
    "CSTR | LSSVR-closed | STSCKF": 0.3462504144,
    "CSTR | LSSVR-EKF | none": 0.2922720843,
    "CSTR | LSSVR-SRUKF | none": 0.2922720843,
    "CSTR | LSSVR-ImSRUKF | none": 0.3006712476,
    "CSTR | LSSVR-Adam | none": 0.3050091467,
    "CSTR | ANFIS-EKF | none": 0.1123855014,
    "CSTR | ANFIS-EKF | PF": 0.4376555271,
    "CSTR | ANFIS-EKF | EKPF": 0.2230111858,
    "CSTR | ANFIS-EKF | STPF": 0.1091620255,
    "CSTR | ANFIS-EKF | SCKF": 0.2074759958,
    "CSTR | ANFIS-EKF | STSCKF": 0.1075992354,
    "CSTR | ANFIS-SRUKF | none": 0.08369595165,
    "CSTR | ANFIS-ImSRUKF | none": 0.08282735409,
    "CSTR | ANFIS-Adam | none": 0.123298903,
    "HI | persistence-none | none": 0.03346744097,
    "CSTR | persistence-none | none": 0.01957626697,
}
QUICK_RMSE_10 = {
    "HI | ELM-closed | none": 0.1878563758,
    "HI | ELM-closed | PF": 0.1787703852,
    "HI | ELM-closed | EKPF": 0.2386800426,
    "HI | ELM-closed | STPF": 0.1552370899,
    "HI | ELM-closed | SCKF": 0.207621757,
    "HI | ELM-closed | STSCKF": 0.2086298541,
    "HI | ELM-EKF | none": 0.1878563759,
    "HI | ELM-SRUKF | none": 0.1878563759,
    "HI | ELM-ImSRUKF | none": 0.3804532369,
    "HI | ELM-Adam | none": 0.1195605359,
    "HI | LSSVR-closed | none": 0.1627555598,
    "HI | LSSVR-closed | PF": 0.1360042826,
    "HI | LSSVR-closed | EKPF": 0.1429477504,
    "HI | LSSVR-closed | STPF": 0.1400666796,
    "HI | LSSVR-closed | SCKF": 0.1497957454,
    "HI | LSSVR-closed | STSCKF": 0.1451831679,
    "HI | LSSVR-EKF | none": 0.1734298289,
    "HI | LSSVR-SRUKF | none": 0.1734298289,
    "HI | LSSVR-ImSRUKF | none": 0.3112818033,
    "HI | LSSVR-Adam | none": 0.2490472423,
    "HI | ANFIS-EKF | none": 0.06563315837,
    "HI | ANFIS-EKF | PF": 0.3772493512,
    "HI | ANFIS-EKF | EKPF": 0.5163822146,
    "HI | ANFIS-EKF | STPF": 0.3287089895,
    "HI | ANFIS-EKF | SCKF": 1.848193999,
    "HI | ANFIS-EKF | STSCKF": 1.906503934,
    "HI | ANFIS-SRUKF | none": 0.968874837,
    "HI | ANFIS-ImSRUKF | none": 0.3714507555,
    "HI | ANFIS-Adam | none": 0.1728716845,
    "CSTR | ELM-closed | none": 0.2003177356,
    "CSTR | ELM-closed | PF": 0.5057221939,
    "CSTR | ELM-closed | EKPF": 0.2723691961,
    "CSTR | ELM-closed | STPF": 0.2113622678,
    "CSTR | ELM-closed | SCKF": 0.238888848,
    "CSTR | ELM-closed | STSCKF": 0.19475744,
    "CSTR | ELM-EKF | none": 0.2003177355,
    "CSTR | ELM-SRUKF | none": 0.2003177356,
    "CSTR | ELM-ImSRUKF | none": 0.3802296459,
    "CSTR | ELM-Adam | none": 0.5424676511,
    "CSTR | LSSVR-closed | none": 0.4970446789,
    "CSTR | LSSVR-closed | PF": 0.5301890648,
    "CSTR | LSSVR-closed | EKPF": 0.5086622878,
    # was 0.5002699504, 0.4975735853, 0.4971469664 (see RMSE_1)
    "CSTR | LSSVR-closed | STPF": 0.4976256077,
    "CSTR | LSSVR-closed | SCKF": 0.5059449559,
    "CSTR | LSSVR-closed | STSCKF": 0.4994999969,
    "CSTR | LSSVR-EKF | none": 0.4655952118,
    "CSTR | LSSVR-SRUKF | none": 0.4655952118,
    "CSTR | LSSVR-ImSRUKF | none": 0.4743192605,
    "CSTR | LSSVR-Adam | none": 0.4511679286,
    "CSTR | ANFIS-EKF | none": 0.4065898712,
    "CSTR | ANFIS-EKF | PF": 0.498667258,
    "CSTR | ANFIS-EKF | EKPF": 0.4382135459,
    "CSTR | ANFIS-EKF | STPF": 0.4087981647,
    "CSTR | ANFIS-EKF | SCKF": 0.4326305678,
    "CSTR | ANFIS-EKF | STSCKF": 0.4046778039,
    "CSTR | ANFIS-SRUKF | none": 0.3167255664,
    "CSTR | ANFIS-ImSRUKF | none": 0.3133527313,
    "CSTR | ANFIS-Adam | none": 0.3105948344,
    "HI | persistence-none | none": 0.05309157711,
    "CSTR | persistence-none | none": 0.09665412355,
}


def test_quick_headline_numbers(quick_out):
    rows = _rows(quick_out)
    for metric, ref in (("RMSE_1", QUICK_RMSE_1), ("RMSE_10", QUICK_RMSE_10)):
        got = means(rows, metric)
        assert set(got) == set(ref), metric
        for k, v in ref.items():
            # the health indicator's SciPy eigendecomposition rounds differently across CPUs and
            # BLAS kernels (about 1e-8); iterated ten steps through a trained ANFIS that becomes
            # up to 2e-6 (measured between two machines), so the HI cells get 1e-5. With 30
            # particles such rounding can move a resampling draw across a cumulative-weight edge
            # and swap one ancestor: 1.2e-4 in one PF cell between an AMD and an Intel CPU, and
            # 2.0e-3 (RMSE_1; 5.2e-4 RMSE_10) in CSTR | LSSVR-closed | STPF between two Intel
            # CPUs (every other cell within 3.2e-7 there), so the particle filter cells get 5e-3
            rel = (
                5e-3
                if "PF" in k
                else 1e-4
                if "ImSRUKF" in k
                else 1e-5
                if k.startswith("HI")
                else 1e-6
            )
            assert got[k] == pytest.approx(v, rel=rel), (metric, k)
    r1, r10 = means(rows, "RMSE_1"), means(rows, "RMSE_10")
    for series in ("HI", "CSTR"):
        # EKF and SRUKF training of the ELM reproduce ridge (Q = 0, P0 = R / lambda)
        for tn in ("EKF", "SRUKF"):
            assert r1[f"{series} | ELM-{tn} | none"] == pytest.approx(
                r1[f"{series} | ELM-closed | none"], rel=1e-8
            )
        # we lose with ImSRUKF on these learners
        assert r1[f"{series} | ELM-ImSRUKF | none"] > 2 * r1[f"{series} | ELM-EKF | none"]
    pers = "HI | persistence-none | none"
    # bearing: the learners alone beat persistence one step ahead, persistence wins ten ahead
    for k in ("HI | ELM-closed | none", "HI | LSSVR-closed | none", "HI | ANFIS-EKF | none"):
        assert r1[k] < r1[pers]
    assert all(v > r10[pers] for k, v in r10.items() if k.startswith("HI") and k != pers)
    # CSTR: persistence beats every combination; strong tracking is the filter that helps
    pers = "CSTR | persistence-none | none"
    assert all(v > r1[pers] for k, v in r1.items() if k.startswith("CSTR") and k != pers)
    elm = {fl: r1[f"CSTR | ELM-closed | {fl}"] for fl in ("none", "STSCKF", "SCKF", "PF")}
    assert elm["STSCKF"] < elm["none"] < elm["SCKF"] < elm["PF"]
