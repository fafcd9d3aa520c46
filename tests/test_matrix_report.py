"""The report of a forecaster matrix on a small hand-built result: the summaries its notes quote
and its figures."""

from __future__ import annotations

import math

import pytest

from prognos_torch.studies import (
    Cell,
    MatrixResult,
    always_censored,
    best_label,
    matrix_figures,
    most_hits,
    problem_summary,
    ratio_text,
    summarize,
)

# per (combo, filter): per-run values of RMSE_1, RMSE_10, AL_mass, alpha_lambda, RUL_censored,
# RUL_bias_d
CELLS = {
    ("A-t", "none"): ([1.0, 3.0], [4.0, 4.0], [0.2, 0.4], [0.0, 1.0], [1.0, 1.0], [-0.5, -0.5]),
    ("A-t", "F"): ([1.0, 1.0], [5.0, 5.0], [0.6, 0.6], [1.0, 1.0], [0.0, 0.5], [0.25, 0.25]),
    ("B-t", "none"): ([4.0, 4.0], [3.0, 3.0], [0.1, 0.1], [0.0, 0.0], [0.5, 0.5], [1.0, 1.0]),
    ("B-t", "F"): ([6.0, 6.0], [9.0, 9.0], [0.0, 0.0], [0.0, 0.0], [1.0, 1.0], [2.0, 2.0]),
    ("ref-none", "none"): ([2.5] * 3, [1.0] * 3, [0.9] * 3, [1.0] * 3, [0.0] * 3, [0.0] * 3),
}
KEYS = ("RMSE_1", "RMSE_10", "AL_mass", "alpha_lambda", "RUL_censored", "RUL_bias_d")


def _result() -> MatrixResult:
    rows = []
    for (combo, f), values in CELLS.items():
        for i in range(len(values[0])):
            row = {"run": i, "method": f"P | {combo} | {f}", "time_s": 1.0, "diverged": 0.0}
            rows.append(row | {k: v[i] for k, v in zip(KEYS, values)})
    cells = {(f"P | {c}", f): Cell("ok") for c, f in CELLS}
    metrics = sorted({k for r in rows for k in r} - {"run", "method"})
    return MatrixResult(
        rows, cells, {}, ["P"], ["A", "B"], ["t"], ["none", "F"], ["ref"], summarize(rows, metrics)
    )


def test_best_and_ratios_by_hand():
    res = _result()
    # A-t: alone mean 2, with F 1; B-t: 4 and 6 (the reference is no candidate)
    assert best_label(res, "P", "RMSE_1") == (1.0, "A-t + F")
    assert best_label(res, "P", "RMSE_1", ("none",)) == (2.0, "A-t + none")
    assert best_label(res, "P", "AL_mass", high=True) == (0.6, "A-t + F")
    v, name = best_label(res, "P", "no_such_metric")
    assert math.isnan(v) and name == "— + —"
    assert ratio_text(res, "P") == "F 1.00"  # median of 1/2 and 6/4


def test_hits_and_censoring_leave_the_reference_out():
    res = _result()
    assert most_hits(res, "P") == (2, 2)  # A-t + F; the reference's 3/3 does not count
    assert always_censored(res, "P") == ["A-t"]  # alone: A-t censored on both runs, B-t half
    assert always_censored(res, "P", "F") == ["B-t"]


def test_problem_summary():
    s = problem_summary(_result(), "P", horizon=10)
    assert (s["best"], s["best_name"]) == (1.0, "A-t + F")
    assert (s["alone"], s["alone_name"]) == (2.0, "A-t + none")
    assert (s["best_h"], s["best_h_name"]) == (3.0, "B-t + none")
    assert (s["bias_min"], s["bias_max"]) == (-0.5, 2.0)
    assert (s["hits"], s["hits_n"], s["censored_alone"]) == (2, 2, "A-t")
    assert s["ratios"] == "F 1.00" and s["best_mass"] == pytest.approx(0.6)


def test_figures_written(tmp_path):
    res = _result()
    names = matrix_figures(res, tmp_path, rul_problem="P", alpha=0.3)
    assert len(names) == 3
    for n in names:
        assert (tmp_path / n).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert len(matrix_figures(res, tmp_path / ".", rul_problem=None)) == 2
