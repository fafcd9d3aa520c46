"""The elm-stsckf study (paper 000) end to end in quick mode, and its per-run forecaster view."""

from __future__ import annotations

import math

import pytest
from _study_helpers import check_outputs, means, quick_fixture, read_rows, trainer_fixture

METHODS = ("SCKF", "STUKF", "STSCKF", "STUKF(3-n)")

quick_out = quick_fixture("elm-stsckf", runs=3)
trainer = trainer_fixture("elm_stsckf")


def test_quick_outputs_complete_and_finite(quick_out):
    meta, rows = check_outputs(quick_out, "elm-stsckf", 5, METHODS, 3)
    for r in rows:
        v = {k: float(r[k]) for k in ("MAE", "RMSE", "MSE", "filt_RMSE", "time_s")}
        assert all(math.isfinite(x) and x >= 0 for x in v.values())
        # identities of the error summaries: RMSE >= MAE (Jensen), MSE = RMSE^2
        assert v["RMSE"] >= v["MAE"]
        assert v["MSE"] == pytest.approx(v["RMSE"] ** 2, rel=1e-12)
    table = (quick_out / "table.md").read_text()
    for m in ("SCKF", "STUKF", "STSCKF", "0.4402", "0.0318", "chol_D"):
        assert m in table


def test_quick_strong_tracking_follows_the_ramp_better_than_sckf(quick_out):
    # With the assistant model az2_k = az2_{k-1} and a small random walk (chol_D = 1e-4), the
    # SCKF's gain on az2 settles near zero and it lags the accelerating ramp of Eq. 61; the
    # fading factor (lambda_k >= 1) keeps the gain open. Asserted per run with a wide margin.
    rows = read_rows(quick_out)
    by = {(int(r["run"]), r["method"]): float(r["RMSE"]) for r in rows}
    for i in range(3):
        assert by[(i, "STSCKF")] < 0.5 * by[(i, "SCKF")]


# Quick-mode headline numbers (3 runs, T = 120, OMP_NUM_THREADS=1; float64 throughout, so they
# move only when the model, the filters, the forecasts or the seeds do). Full-run numbers
# beside the paper's: docs/RESULTS.md.
QUICK_MAE = {"SCKF": 0.2370944027, "STSCKF": 0.0330124114}
QUICK_RMSE = {"SCKF": 0.2608387338, "STSCKF": 0.0364532057}
QUICK_FILT_RMSE = {"SCKF": 0.2347407018, "STSCKF": 0.0244681558}


def test_quick_headline_numbers(quick_out):
    rows = read_rows(quick_out)
    for metric, ref in (("MAE", QUICK_MAE), ("RMSE", QUICK_RMSE), ("filt_RMSE", QUICK_FILT_RMSE)):
        got = means(rows, metric)
        assert {m: got[m] for m in ref} == pytest.approx(ref, rel=1e-6), metric
        # the failure we report: the paper's STUKF/STSCKF gap (0.0930 vs 0.0318) does not
        # appear, with Julier's kappa = 1 (square root) or kappa = 3 - n (full covariance)
        for m in ("STUKF", "STUKF(3-n)"):
            assert got[m] == pytest.approx(got["STSCKF"], rel=1e-6), (metric, m)
    # the ordering we find (and the paper's): strong tracking well ahead of SCKF
    mae = means(rows, "MAE")
    assert mae["STSCKF"] < 0.2 * mae["SCKF"]
    table = (quick_out / "table.md").read_text()
    # sensitivity: the SCKF's failure disappears with a larger random walk on az2
    assert "| 0.0001 | 0.2371 | 0.2608 | 0.0330 | 0.0365 | 0.0330 | 0.0365 | 7.2 |" in table
    assert "| 0.01 | 0.0256 | 0.0289 | 0.0247 | 0.0281 | 0.0247 | 0.0281 | 1.0 |" in table
