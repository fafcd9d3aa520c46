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

from ..core.validation import check_nonneg_int
from ..io import atomic_write

__all__ = ["run_rows", "write_rows_csv", "method_mean"]


def run_rows(method: str, values: Mapping[str, object], runs: int | None = None) -> list[dict]:
    """``[{"run": i, "method": method, key: value_i, ...} for i in range(R)]``.

    Args:
        method: the method's name (the table's row label).
        values: ``key -> per-run values`` (a ``(R,)`` tensor or NumPy array, or a sequence of
            length ``R``; entry ``i`` is converted with ``float``) or one value shared by every
            run (a Python or NumPy number, a string or a 0-d tensor or array). Keys keep their
            order in the rows.
        runs: ``R``; by default the length of the per-run values.
    Returns:
        ``R`` rows (the keys of ``results.csv``).
    """

    arrays = (torch.Tensor, np.ndarray)  # an array was shared whole by every row

    def per_run(v) -> bool:
        if isinstance(v, arrays):
            return v.ndim > 0
        return isinstance(v, (list, tuple))

    for k, v in values.items():  # a (R, k) value has no float per run
        if isinstance(v, arrays) and v.ndim > 1:
            raise ValueError(
                f"values[{k!r}] must be (R,) per-run values, got shape {tuple(v.shape)}"
            )
    if runs is not None:
        check_nonneg_int(runs, "runs")
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
            k: (float(v[i]) if per_run(v) else v.item() if isinstance(v, arrays) else v)
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
    atomic_write(path, rows_csv_bytes(rows))


def rows_csv_bytes(rows: Sequence[Mapping]) -> bytes:
    """The bytes :func:`write_rows_csv` writes (built before anything is written)."""
    keys: list[str] = []
    for r in rows:
        keys += [k for k in r if k not in keys]
    buf = io.StringIO(newline="")
    w = csv.DictWriter(buf, fieldnames=keys)
    w.writeheader()
    for r in rows:
        w.writerow({k: r.get(k, "") for k in keys})
    return buf.getvalue().encode()
