"""The elm-stsckf study (paper 000) end to end in quick mode, and its per-run forecaster view."""

from __future__ import annotations

import math

import pytest
from _study_helpers import check_outputs, quick_fixture, read_rows, trainer_fixture

quick_out = quick_fixture("elm-stsckf", runs=3)
trainer = trainer_fixture("elm_stsckf")


def test_quick_outputs_complete_and_finite(quick_out):
    meta, rows = check_outputs(quick_out, "elm-stsckf", 5, ("SCKF", "STUKF", "STSCKF"), 3)
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
