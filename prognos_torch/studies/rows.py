"""Result rows of a study: one dict per (run, method), built from per-run values and written
as CSV (``results.csv`` and any further table of rows)."""

from __future__ import annotations

import csv
import io
import math
import os
from collections.abc import Mapping, Sequence

import numpy as np
import torch

from ..io import atomic_write

__all__ = ["run_rows", "write_rows_csv", "method_mean"]


def run_rows(method: str, values: Mapping[str, object], runs: int | None = None) -> list[dict]:
    """``[{"run": i, "method": method, key: value_i, ...} for i in range(R)]``.

    Args:
        method: the method's name (the table's row label).
        values: ``key -> per-run values`` (a ``(R,)`` tensor or a sequence of length ``R``;
            entry ``i`` is converted with ``float``) or one value shared by every run (a Python
            number, a string or a 0-d tensor). Keys keep their order in the rows.
        runs: ``R``; by default the length of the per-run values.
    Returns:
        ``R`` rows (the keys of ``results.csv``).
    """

    def per_run(v) -> bool:
        if isinstance(v, torch.Tensor):
            return v.dim() > 0
        return isinstance(v, (list, tuple))

    lengths = {k: len(v) for k, v in values.items() if per_run(v)}
    if runs is None:
        if not lengths:
            raise ValueError("runs is required when no value is given per run")
        runs = next(iter(lengths.values()))
    bad = {k: n for k, n in lengths.items() if n != runs}
    if bad:
        raise ValueError(f"per-run values must have length runs={runs}, got {bad}")
    return [
        {"run": i, "method": method}
        | {
            k: (float(v[i]) if per_run(v) else v.item() if isinstance(v, torch.Tensor) else v)
            for k, v in values.items()
        }
        for i in range(runs)
    ]


def method_mean(rows: Sequence[Mapping], method: str, key: str) -> float:
    """The mean of ``key`` over the rows of ``method`` that have it (one per run); NaN when none
    has it. Non-finite values are kept (a NaN or inf row makes the mean NaN or inf)."""
    vals = [r[key] for r in rows if r["method"] == method and key in r]
    return float(np.mean(vals)) if vals else math.nan


def write_rows_csv(path: str | os.PathLike, rows: Sequence[Mapping]) -> None:
    """Write ``rows`` as CSV, atomically: the columns are every key of the rows in order of first
    appearance, a row without a key leaves its cell empty."""
    keys: list[str] = []
    for r in rows:
        keys += [k for k in r if k not in keys]
    buf = io.StringIO(newline="")
    w = csv.DictWriter(buf, fieldnames=keys)
    w.writeheader()
    for r in rows:
        w.writerow({k: r.get(k, "") for k in keys})
    atomic_write(path, buf.getvalue().encode())
