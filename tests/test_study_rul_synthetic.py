"""The rul-synthetic study in quick mode: outputs, the protocol on every family, headline numbers.

The predicted RULs are asserted with tolerances so that the test breaks when the results move (a
change of generator, model, pool, seed use or protocol must show up here and in
docs/RESULTS.md).
"""

from __future__ import annotations

import math

import pytest
from _study_helpers import quick_fixture, read_rows

quick_out = quick_fixture("rul-synthetic")
METHODS = ("prognose (auto)", "prognose (exponential)", "exponential LSQ",
           "prognose (auto) + conformal")  # fmt: skip

# Quick mode: one record per family, the 20/60/90 % points; prognose medians are exact per-path
# crossing times (RULResult.quantile), the baseline is a closed form.
QUICK_PRED_RUL = {
    ("prognose (auto)", "shocks 0"): [1.185272372, 0.5475344667, 0.1180555556],
    ("prognose (exponential)", "shocks 0"): [1.185272372, 0.5475344667, 0.1458333333],
    ("exponential LSQ", "shocks 0"): [1.1447349313, 0.360948877, 0.0],
    ("prognose (auto)", "paris 0"): [2.5616455, 0.7920987729, 0.2069444444],
    ("prognose (exponential)", "paris 0"): [2.100692982, 0.8080518595, 0.1930555556],
    ("exponential LSQ", "paris 0"): [1.895521328, 0.9501385423, 0.2828814746],
    ("prognose (auto)", "two_phase 0"): [6.378788612, 1.204811153, 0.5668770814],
    ("prognose (exponential)", "two_phase 0"): [10.88884981, 0.7474808223, 0.3656972222],
    ("exponential LSQ", "two_phase 0"): [math.inf, 0.8917023371, 0.199662916],
    ("prognose (auto)", "hump 0"): [0.3291666667, 1.026295373, 0.2138888889],
    ("prognose (exponential)", "hump 0"): [0.3716778333, 2.228138343, 0.4054372851],
    ("exponential LSQ", "hump 0"): [0.7011203188, 1.794311744, 0.6106250937],
}


def test_quick_outputs_and_headline_numbers(quick_out):
    for name in ("table.md", "results.csv", "run.json", "rul_vs_time.png"):
        assert (quick_out / name).stat().st_size > 0
    rows = read_rows(quick_out)
    assert {r["method"] for r in rows} == set(METHODS)
    got: dict = {}
    for r in rows:
        got.setdefault((r["method"], r["series"]), []).append(float(r["pred_rul"]))
        assert float(r["true_rul"]) > 0
    for m, series in list(got):  # calibrated intervals around the same medians
        if m.endswith("+ conformal"):
            assert got.pop((m, series)) == got[("prognose (auto)", series)]
    assert set(got) == set(QUICK_PRED_RUL)
    for k, ref in QUICK_PRED_RUL.items():
        assert got[k] == pytest.approx(ref, rel=1e-6, abs=1e-12), k
    # every prognose row carries a finite log-time CRPS and a 90 % interval
    for r in rows:
        if r["method"].startswith("prognose"):
            assert r["covered"] in ("0.0", "1.0")
            crps = r["crps_log"]  # the calibrated interval has no distribution to score
            assert (
                crps in ("", "None") if "conformal" in r["method"] else math.isfinite(float(crps))
            )
    table = (quick_out / "table.md").read_text()
    assert "family: paris" in table and "mean log-time CRPS" in table


def test_headline_table_by_hand():
    from prognos_torch.studies.rul_protocol import headline_table

    def row(m, err, rel, cone, cov, crps, held=True):
        return {"method": m, "held_out": held, "abs_error": err, "rel_error": rel,
                "in_cone_0.2": cone, "in_cone_0.3": cone, "covered": cov, "crps_log": crps}  # fmt: skip

    rows = [row("a", 1.0, 0.1, 1.0, 1.0, 0.2), row("a", 3.0, 0.5, 0.0, 0.0, 0.4),
            row("b", 2.0, 0.2, 1.0, None, None), row("a", 9.0, 9.0, 0.0, 1.0, 9.0, held=False)]  # fmt: skip
    table = headline_table(rows, ["a", "b"], "t", held_out=True)
    # a: 2 points, half in the cone, coverage 0.5, median |error| the lower median 1.0 (torch),
    # median rel 0.1, mean RA 1 - 0.3 = 0.7, mean CRPS 0.3; b has no interval and no CRPS
    assert "| a | 2 | 0.50 | 0.50 | 0.50 | 1 | 0.1 | 0.7 | 0.300 |" in table
    assert "| b | 1 | 1.00 | 1.00 | — | 2 | 0.2 | 0.8 | — |" in table
    assert "| a | 3 |" in headline_table(rows, ["a"], "t")
    # an infinite prediction (a censored median) has RA -inf: the mean is over the finite ones,
    # with their count; with none finite there is no mean
    rows.append(row("b", math.inf, math.inf, 0.0, None, None))
    assert "| b | 2 | 0.50 | 0.50 | — | 2 | 0.2 | 0.8 (1 of 2 finite) | — |" in headline_table(
        rows, ["b"], "t"
    )
    assert "| c | 1 | 0.00 | 0.00 | — | inf | inf | — | — |" in headline_table(
        [row("c", math.inf, math.inf, 0.0, None, None)], ["c"], "t"
    )
    # no qualifying row (a quick run without held-out series): said, not an empty table
    assert headline_table(rows, ["b"], "held out", held_out=False) == (
        "**held out**: no points in this run"
    )
