"""Study table helpers: summaries over runs, markdown tables, number format, note templates."""

import math

import numpy as np
import pytest

from prognos_torch.studies import (
    Stat,
    StudyResult,
    fill_template,
    fmt_value,
    format_table,
    markdown_table,
    summarize,
)


def test_summarize_matches_numpy_and_skips_non_finite():
    rows = [
        {"run": 0, "method": "B", "MAE": 1.0, "RMSE": math.nan},
        {"run": 0, "method": "A", "MAE": 2.0, "RMSE": 3.0},
        {"run": 1, "method": "A", "MAE": 5.0, "RMSE": math.inf},
        {"run": 2, "method": "A", "MAE": 11.0},
    ]
    s = summarize(rows, ["MAE", "RMSE"])
    assert list(s) == ["B", "A"]  # order of first appearance
    v = np.array([2.0, 5.0, 11.0])
    assert s["A"]["MAE"] == Stat(v.mean(), v.std(ddof=1), 3)
    assert s["A"]["RMSE"] == Stat(3.0, 0.0, 1)
    assert s["B"]["MAE"] == Stat(1.0, 0.0, 1) and "RMSE" not in s["B"]


def test_markdown_table_and_format():
    t = markdown_table(["a", "b"], [[1, "x"], ["—", 2.5]])
    assert t.splitlines() == ["| a | b |", "|---|---|", "| 1 | x |", "| — | 2.5 |"]
    with pytest.raises(ValueError, match="3 cells, the header 2"):
        markdown_table(["a", "b"], [[1, 2, 3]])
    assert [fmt_value(v) for v in (None, math.nan, 0.0, 0.12345, 1e-4, -2e4, 9999.0)] == [
        "—",
        "—",
        "0.0000",
        "0.1235",
        "1.000e-04",
        "-2.000e+04",
        "9999.0000",
    ]


def test_format_table_paper_column_only_where_the_paper_has_the_metric():
    res = StudyResult(
        rows=[
            {"run": 0, "method": "A", "MAE": 1.0, "x": 1.0},
            {"run": 1, "method": "A", "MAE": 2.0, "x": math.nan},
        ],
        metrics=["MAE", "x"],
        paper={"A": {"MAE": 0.5}, "C": {"x": 1.0}},  # C is not among our methods
    )
    lines = format_table(res).splitlines()
    assert lines[0] == "| method | runs | MAE (ours) | MAE (paper) | x (ours) |"
    # a mean over fewer runs than the method has says so (the NaN run is left out of it)
    assert lines[2] == "| A | 2 | 1.5000 ± 0.7071 | 0.5000 | 1.0000 ± 0.0000 (1 of 2 finite) |"


def test_markdown_table_escapes_a_bar_in_a_cell():
    """forecaster-matrix's method names ("HI | ELM-closed | none") split each row into more
    cells than the header named."""
    text = markdown_table(["method", "runs"], [["HI | ELM | none", 3]])
    assert text.splitlines()[2] == "| HI \\| ELM \\| none | 3 |"


def test_fill_template(tmp_path):
    p = tmp_path / "notes.md"
    p.write_text("bias {bias:+.3f} over {runs} runs; {{literal}}; {cfg[seed]}\n")
    assert fill_template(p, {"bias": -0.01234, "runs": 3, "cfg": {"seed": 7}}) == (
        "bias -0.012 over 3 runs; {literal}; 7\n"
    )
    with pytest.raises(KeyError, match=r"\['cfg', 'runs'\]"):
        fill_template(p, {"bias": 1.0})


def test_sweep_table():
    from prognos_torch.studies import sweep_table

    res = {("A", 0.1): {"RMSE": 0.2}, ("B", 0.1): {"RMSE": 0.05}, ("A", 1.0): {"RMSE": 0.3}}
    res[("B", 1.0)] = {"RMSE": 0.3}
    t = sweep_table("d", (0.1, 1.0), res, ("A", "B"), ("RMSE",), ratio=("RMSE", "A", "B", 1))
    assert t.splitlines() == [
        "| d | A RMSE | B RMSE | RMSE ratio A/B |",
        "|---|---|---|---|",
        "| 0.1 | 0.2000 | 0.0500 | 4.0 |",
        "| 1 | 0.3000 | 0.3000 | 1.0 |",
    ]


def test_sweep_crossing_interpolates_in_log_log():
    from prognos_torch.studies import sweep_crossing

    pts = [(1.0, 0.1), (0.1, 0.05), (0.01, 0.02), (0.001, 0.01)]
    # between 0.1 (0.05) and 0.01 (0.02): log-log linear, e = 0.05 (s / 0.1)^(log 2.5 / log 10)
    s = sweep_crossing(pts, 0.03)
    assert s == pytest.approx(0.1 * 10 ** (-math.log(0.05 / 0.03) / math.log(2.5)))
    assert 0.05 * (s / 0.1) ** (math.log(2.5) / math.log(10)) == pytest.approx(0.03)
    assert sweep_crossing(pts, 0.02) == pytest.approx(0.01)  # a point on the target
    assert sweep_crossing(pts, 0.2) == 1.0  # already reached
    assert sweep_crossing(pts, 0.005) is None  # never reached
    assert sweep_crossing([(1.0, 0.1), (0.1, 0.2), (0.01, 0.05)], 0.1) == 1.0
    assert sweep_crossing([(1.0, 0.3), (0.1, 0.2), (0.01, 0.05)], 0.1) == pytest.approx(
        0.1 * 10 ** (-math.log(2) / math.log(4))
    )
    with pytest.raises(ValueError, match="points"):
        sweep_crossing([(0.0, 0.1)], 0.1)


def test_threshold_census_counts_and_ranges():
    import torch

    from prognos_torch.studies import threshold_census

    v = torch.tensor([0.0521, 0.0612, 0.9, 0.05, 0.1], dtype=torch.float64)
    assert (
        threshold_census(v, 0.1)
        == "3 lie below 0.1 (0.050 to 0.061), 2 lie above 0.1 (0.100 to 0.900)"
    )
    # a range narrower than half a unit of the last decimal is one value; sides may be empty
    assert threshold_census([0.9731, 0.9733], 0.1, verb="settle") == "2 settle above 0.1 (0.973)"
    assert threshold_census([-0.0081], 0.1, digits=2) == "1 lie below 0.1 (-0.01)"
    assert threshold_census([], 0.1) == ""
    with pytest.raises(ValueError, match="finite"):
        threshold_census([0.0, math.nan], 0.1)


def test_method_mean_and_ascending_readings():
    from prognos_torch.studies import ascending, method_mean

    rows = [
        {"run": 0, "method": "a", "MAE": 0.3, "RMSE": 0.5},
        {"run": 1, "method": "a", "MAE": 0.1},
        {"run": 0, "method": "b", "MAE": 0.2},
        {"run": 0, "method": "c", "MAE": math.inf},
    ]
    assert method_mean(rows, "a", "MAE") == pytest.approx(0.2, abs=1e-15)
    assert method_mean(rows, "a", "RMSE") == 0.5  # only the rows that have the key
    assert math.isnan(method_mean(rows, "b", "RMSE"))
    assert method_mean(rows, "c", "MAE") == math.inf
    values = {"x": 0.3, "y": 0.1, "z": 0.3}
    assert ascending(values) == "y 0.1000 < x 0.3000 < z 0.3000"  # ties keep their order
    assert ascending({"y": 0.1, "x": 0.25}, ".2e") == "y 1.00e-01 < x 2.50e-01"
