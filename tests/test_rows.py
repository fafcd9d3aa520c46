"""studies.run_rows: per-run values to result rows."""

from __future__ import annotations

import pytest
import torch

from prognos_torch.studies import run_rows


def test_run_rows_spreads_per_run_values_and_shares_scalars():
    rows = run_rows(
        "A",
        {"MAE": torch.tensor([0.5, 0.25], dtype=torch.float64), "n": [3, 4], "time_s": 1.5,
         "tag": "x", "zero_d": torch.tensor(2.0)},
    )  # fmt: skip
    assert rows == [
        {"run": 0, "method": "A", "MAE": 0.5, "n": 3.0, "time_s": 1.5, "tag": "x", "zero_d": 2.0},
        {"run": 1, "method": "A", "MAE": 0.25, "n": 4.0, "time_s": 1.5, "tag": "x", "zero_d": 2.0},
    ]
    assert list(rows[0]) == ["run", "method", "MAE", "n", "time_s", "tag", "zero_d"]
    assert run_rows("B", {"x": 1.0}, runs=2) == [
        {"run": 0, "method": "B", "x": 1.0},
        {"run": 1, "method": "B", "x": 1.0},
    ]


def test_run_rows_rejects_mismatched_lengths():
    with pytest.raises(ValueError, match="length runs=2"):
        run_rows("A", {"a": [1, 2], "b": [1, 2, 3]})
    with pytest.raises(ValueError, match="runs is required"):
        run_rows("A", {"a": 1.0})
