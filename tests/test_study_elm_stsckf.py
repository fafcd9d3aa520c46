"""The elm-stsckf study (paper 000) end to end in quick mode, and its per-run forecaster view."""

from __future__ import annotations

import math

import pytest
import torch
from _study_helpers import check_outputs, quick_fixture, read_rows, trainer_fixture

from prognos_torch.prognosis import MeasurementForecaster

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


def test_run_channels_view_equals_one_forecaster_per_run(trainer):
    mod = trainer
    R, C, N0, n = 3, 3, 20, 4
    g = torch.Generator().manual_seed(5)
    z = 1.0 + 0.1 * torch.randn(N0 + 3, R, C, generator=g, dtype=torch.float64).cumsum(0)
    per_run = [
        MeasurementForecaster.ros_elm(
            C, p=3, n_hidden=8, generator=torch.Generator().manual_seed(r)
        )
        for r in range(R)
    ]
    learners = [elm for f in per_run for elm in f.learners]
    view = mod._RunChannels(MeasurementForecaster(learners, 3, lam=1e-8), R, C)
    view.initialize(z[:N0])
    for r, f in enumerate(per_run):
        f.initialize(z[:N0, r])
    for t in range(N0, N0 + 3):
        got = view.copy().forecast(n)
        want = torch.stack([f.forecast(n) for f in per_run], dim=1)
        torch.testing.assert_close(got, want, rtol=1e-12, atol=1e-12)
        view.update(z[t])
        for r, f in enumerate(per_run):
            f.update(z[t, r])
    assert view.initialized and got.shape == (n, R, C)
