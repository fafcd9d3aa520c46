"""studies.run_rows: per-run values to result rows."""

from __future__ import annotations

import csv

import pytest
import torch

from prognos_torch.studies import run_rows, write_rows_csv


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


def test_write_rows_csv_unions_the_keys_and_leaves_missing_cells_empty(tmp_path):
    path = tmp_path / "t.csv"
    write_rows_csv(path, [{"run": 0, "a": 1.5}, {"run": 1, "b": "x"}])
    assert path.read_bytes() == b"run,a,b\r\n0,1.5,\r\n1,,x\r\n"  # the csv module's dialect
    with open(path, newline="") as fh:
        assert list(csv.DictReader(fh)) == [
            {"run": "0", "a": "1.5", "b": ""},
            {"run": "1", "a": "", "b": "x"},
        ]
    assert not [p for p in tmp_path.iterdir() if p.name != "t.csv"]  # no temporary file left
    with pytest.raises(FileNotFoundError, match="output folder"):
        write_rows_csv(tmp_path / "missing" / "t.csv", [{"a": 1}])
