"""The ims-rul study in quick mode: the protocol, the outputs and the headline numbers.

The headline numbers are asserted with tolerances so that the test breaks when the results move
(a change of model, selection, seed use or protocol must show up here and in docs/RESULTS.md).
"""

from __future__ import annotations

import math

import pytest
import torch
from _study_helpers import quick_fixture, read_rows

from prognos_torch.datasets import load_ims_features
from prognos_torch.prognosis.protocol import (
    exponential_lsq_rul,
    known_threshold_protocol,
    linear_slope_rul,
    rul_scores,
)

quick_out = quick_fixture("ims-rul")
METHODS = ("prognose (auto)", "prognose (exponential)", "linear slope", "exponential LSQ",
           "prognose (auto) + conformal")  # fmt: skip


def test_protocol_on_bearing_3():
    f = load_ims_features(1)
    pc = known_threshold_protocol(f.days, f.feature("rms")[:, 4])
    assert pc.valid
    assert pc.threshold == pytest.approx(0.4466, abs=1e-4)  # 0.9 x max 5-point median
    assert pc.t_eol == pytest.approx(34.4747, abs=1e-4)
    assert pc.t_onset == pytest.approx(33.9591, abs=1e-4)
    torch.testing.assert_close(pc.true_rul, pc.t_eol - pc.times)
    span = pc.t_eol - pc.t_onset
    expected = torch.tensor([pc.t_onset + q * span for q in (0.2, 0.4, 0.6, 0.8, 0.9)])
    torch.testing.assert_close(pc.times, expected.to(torch.float64))


def test_baselines_and_scores_by_hand():
    t = torch.arange(20, dtype=torch.float64)
    y = 1.0 + 0.1 * t
    assert linear_slope_rul(t, y, 4.0, 0.0) == pytest.approx(11.0)  # 1 + 0.1 t = 4 at t = 30
    ye = 1.0 + torch.exp(0.1 * t)
    assert exponential_lsq_rul(t, ye, 1.0 + math.exp(3.0), 0.0, 1.0) == pytest.approx(11.0)
    assert linear_slope_rul(t, 5.0 - 0.1 * t, 9.0, 0.0) == math.inf
    times = torch.tensor([0.0, 1.0, 2.0], dtype=torch.float64)
    true = 4.0 - times
    pred = torch.tensor([4.0, 4.0, math.inf], dtype=torch.float64)
    sc = rul_scores(times, true, pred, t_onset=0.0, t_eol=4.0,
                    lower=pred - 1, upper=pred + 1)  # fmt: skip
    assert sc["alpha_lambda_0.3"] == pytest.approx(1 / 3)
    assert sc["coverage"] == pytest.approx(2 / 3)  # [3, 5] holds 4 and 3; [inf, inf] not 2
    assert sc["median_abs_error"] == pytest.approx(1.0)


def test_quick_outputs(quick_out):
    for name in ("table.md", "results.csv", "run.json", "rul_vs_time.png", "paths.png"):
        assert (quick_out / name).stat().st_size > 0
    rows = read_rows(quick_out)
    assert {r["method"] for r in rows} == set(METHODS)
    assert len(rows) == 5 * 2 * 3  # methods x series x points
    table = (quick_out / "table.md").read_text()
    assert "alpha-lambda 0.3" in table and "Nothing was fitted to these bearings" in table


def _headline(rows, method):
    rs = [r for r in rows if r["method"] == method]
    err = torch.tensor([float(r["abs_error"]) for r in rs], dtype=torch.float64)
    cone = sum(float(r["in_cone_0.3"]) for r in rs) / len(rs)
    cov = [float(r["covered"]) for r in rs if r["covered"] not in ("", "None")]
    return float(err.median()), cone, (sum(cov) / len(cov) if cov else None)


# Quick-mode predicted RULs (days) at the three prediction points of each bearing: the prognose
# medians are exact per-path crossing times (RULResult.quantile); the baselines are closed
# forms. Seeded and float64, so rel 1e-6 breaks as soon as a model, the selection, the seeds or
# the protocol move.
QUICK_PRED_RUL = {
    ("prognose (auto)", "T1 B3 rms"): [0.1607777778, 0.2462222222, 0.1675952847],
    ("prognose (exponential)", "T1 B3 rms"): [0.2163333333, 0.3139626974, 0.1592960308],
    ("linear slope", "T1 B3 rms"): [0.2316546717, math.inf, math.inf],
    ("exponential LSQ", "T1 B3 rms"): [0.2094794309, 0.1422836167, 0.0],
    ("prognose (auto)", "T1 B4 hi"): [1.17861265, 0.1932731481, 0.05323726852],
    ("prognose (exponential)", "T1 B4 hi"): [0.7016344943, 0.1168842593, 0.03240393519],
    ("linear slope", "T1 B4 hi"): [math.inf, 0.4973955082, 0.1219181145],
    ("exponential LSQ", "T1 B4 hi"): [0.8532037223, 0.06937269961, 0.02399845868],
}


def test_quick_headline_numbers(quick_out):
    rows = read_rows(quick_out)
    got: dict = {}
    for r in rows:
        got.setdefault((r["method"], r["series"]), []).append(float(r["pred_rul"]))
    for series in ("T1 B3 rms", "T1 B4 hi"):  # calibrated intervals around the same medians
        assert got.pop(("prognose (auto) + conformal", series)) == got[("prognose (auto)", series)]
    assert set(got) == set(QUICK_PRED_RUL)
    for k, ref in QUICK_PRED_RUL.items():
        assert got[k] == pytest.approx(ref, rel=1e-6, abs=1e-12), k
    # per method over the 6 points: median absolute error (d), alpha-lambda (0.3) hits, coverage
    med, cone, cov = _headline(rows, "prognose (exponential)")
    assert med == pytest.approx(0.1077404752, rel=1e-6)
    assert cone == pytest.approx(1 / 6) and cov == pytest.approx(1.0)
    med, cone, cov = _headline(rows, "prognose (auto)")
    assert med == pytest.approx(0.1160397292, rel=1e-6)
    assert cone == pytest.approx(1 / 3) and cov == pytest.approx(1.0)
    med, cone, _ = _headline(rows, "exponential LSQ")
    # an error |pred - true| is smaller than pred: the health indicator's CPU-dependent rounding
    # (1e-8) moves it by 2e-6 relative (1.5e-7 d) between two CPUs, hence an absolute 1e-6 d
    assert med == pytest.approx(0.0726944258, rel=1e-6, abs=1e-6) and cone == pytest.approx(1 / 6)
    med, cone, _ = _headline(rows, "linear slope")
    assert med == pytest.approx(0.1807897727, rel=1e-6, abs=1e-6) and cone == pytest.approx(1 / 3)
    # no method is inside the alpha-lambda cone at most of these 6 points
    assert all(_headline(rows, m)[1] <= 1 / 3 for m in METHODS)


def test_last_sample_indices_by_hand():
    from prognos_torch.prognosis import last_sample_indices

    t = torch.tensor([0.0, 0.25, 0.5, 0.75, 1.0, 1.25], dtype=torch.float64)
    times = torch.tensor([0.1, 0.2, 0.3, 0.5, 0.8, 1.2, 5.0], dtype=torch.float64)
    # 0.1 and 0.2 -> sample 0 (once), 0.3 -> 1, 0.5 -> 2 (at the sample), 0.8 -> 3, 1.2 -> 4,
    # 5.0 -> 5
    assert last_sample_indices(t, times) == [0, 1, 2, 3, 4, 5]
    assert last_sample_indices(t, times, first=2) == [2, 3, 4, 5]
    # accumulated times land on a sample within the tolerance, times before t[0] are skipped
    assert last_sample_indices(t, [0.1 * 3 - 0.05, -1.0 + 1.0 - 0.5]) == [1]
    assert last_sample_indices(t, [0.5 - 1e-12]) == [2]
    assert last_sample_indices(t, [0.5 - 1e-12], tol=0.0) == [1]
    with pytest.raises(ValueError, match="t must"):
        last_sample_indices(t[None], times)


def test_predict_rul_names_select_the_filters():
    """The study's method names map to prognose's filters: ``", strong tracking"`` the
    strong-tracking EKF, ``", ekf+stekf pool"`` both filters pooled."""
    from prognos_torch.studies.rul_protocol import predict_rul

    f = load_ims_features(1)
    t, y = f.days, f.feature("rms")[:, 4]
    pc = known_threshold_protocol(t, y)
    tp = float(pc.times[2])
    got = {m: predict_rul(f"prognose ({m})", t, y, pc, tp, 0, "days")["result"].filter
           for m in ("auto", "auto, strong tracking", "auto, ekf+stekf pool")}  # fmt: skip
    assert got == {"auto": "EKF", "auto, strong tracking": "STEKF",
                   "auto, ekf+stekf pool": "EKF+STEKF"}  # fmt: skip
