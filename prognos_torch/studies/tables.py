"""Tables of study results: summaries over runs, markdown tables, notes filled from a template.

A study returns one row per (run, method) (:class:`~prognos_torch.studies.StudyResult`); these
helpers turn the rows into the numbers a reader compares:

* :func:`summarize`: mean, standard deviation (``ddof = 1``) and count of the finite values of
  each metric, per method;
* :func:`format_table`: the main ``table.md`` block, ``mean ± std`` per method and metric with
  the paper's number beside ours;
* :func:`markdown_table`: any other block (a header and rows of cells); :func:`sweep_table`:
  a sensitivity table over the settings of one parameter;
* :func:`fmt_value`: the number format of those tables; :func:`threshold_census`: how many
  values lie below and above a threshold, and their ranges, as a reading; :func:`ascending`:
  named values in increasing order (``"b 0.1 < a 0.3"``);
* :func:`fill_template`: a study's readings written as a markdown template beside the script,
  filled with the numbers of the run (``str.format`` fields such as ``{bias:+.4f}``).
"""

from __future__ import annotations

import math
import os
import string
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch

from ..core.validation import is_real
from .study import StudyResult

__all__ = [
    "Stat",
    "summarize",
    "format_table",
    "markdown_table",
    "sweep_table",
    "fmt_value",
    "fill_template",
    "threshold_census",
    "ascending",
]


class Stat(NamedTuple):
    """Mean, standard deviation (``ddof = 1``; 0 for a single value) and count of values."""

    mean: float
    std: float
    n: int


def fmt_value(v: float | None) -> str:
    """``—`` for a missing value; 4 decimals, or 3 significant digits in e-notation when the
    magnitude is below 1e-3 or at least 1e4."""
    if v is None:
        return "—"
    v = float(v)  # a NumPy float32 or 0-d tensor NaN was written as "nan"
    if math.isnan(v):
        return "—"
    a = abs(v)
    if a != 0 and (a < 1e-3 or a >= 1e4):
        return f"{v:.3e}"
    return f"{v:.4f}"


def _methods(rows: Iterable[Mapping], key: str) -> list[str]:
    out: list[str] = []
    for r in rows:
        if r[key] not in out:
            out.append(r[key])
    return out


def summarize(
    rows: Sequence[Mapping], metrics: Sequence[str], *, key: str = "method"
) -> dict[str, dict[str, Stat]]:
    """``{method: {metric: Stat}}`` over the finite values of each metric, methods in order of
    first appearance. A metric without a finite value is left out of its method's dict.

    Args:
        rows: one mapping per (run, method), e.g. ``{"run": 0, "method": "A", "MAE": 0.1}``.
        metrics: the metric names to summarise.
        key: the field naming the method.
    """
    out: dict[str, dict[str, Stat]] = {}
    for meth in _methods(rows, key):
        rs = [r for r in rows if r[key] == meth]
        stats = {}
        for m in metrics:
            v = np.array([float(r[m]) for r in rs if m in r and r[m] is not None], dtype=float)
            v = v[np.isfinite(v)]
            if v.size:
                stats[m] = Stat(
                    float(v.mean()), float(v.std(ddof=1)) if v.size > 1 else 0.0, v.size
                )
        out[meth] = stats
    return out


def markdown_table(header: Sequence[str], rows: Iterable[Sequence[object]]) -> str:
    """A markdown table: ``| a | b |`` lines with the ``|---|`` rule after the header.

    Cells are written with ``str`` (a ``|`` in a cell escaped as ``\\|``, so that a method
    named ``"HI | ELM | none"`` stays one cell, and a line break as ``<br>``, so that the row
    stays one line); format numbers before (e.g. with :func:`fmt_value`).
    """

    def cell(c) -> str:
        return str(c).replace("|", "\\|").replace("\r\n", "<br>").replace("\n", "<br>")

    header = [cell(h) for h in header]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for row in rows:
        cells = [cell(c) for c in row]
        if len(cells) != len(header):
            raise ValueError(f"a row has {len(cells)} cells, the header {len(header)}: {cells}")
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def sweep_table(
    name: str,
    values: Sequence[float],
    results: Mapping[tuple[str, float], Mapping[str, float]],
    methods: Sequence[str],
    metrics: Sequence[str],
    *,
    ratio: tuple[str, str, str, int] | None = None,
    digits: int = 4,
) -> str:
    """A sensitivity table: one row per setting ``v`` of ``name``, the ``metrics`` of every
    method, optionally the ratio of one metric between two methods.

    Args:
        results: ``{(method, v): {metric: value}}``.
        ratio: ``(metric, a, b, digits)``: a last column ``metric(a) / metric(b)``.
        digits: decimals of the metric cells.
    """
    head = [name] + [f"{m} {k}" for m in methods for k in metrics]
    if ratio is not None:
        head.append(f"{ratio[0]} ratio {ratio[1]}/{ratio[2]}")
    rows = []
    for v in values:
        cells = [f"{v:g}"] + [f"{results[(m, v)][k]:.{digits}f}" for m in methods for k in metrics]
        if ratio is not None:
            metric, a, b, d = ratio
            cells.append(f"{results[(a, v)][metric] / results[(b, v)][metric]:.{d}f}")
        rows.append(cells)
    return markdown_table(head, rows)


def format_table(result: StudyResult) -> str:
    """Markdown table: one row per method, ``mean ± std`` over runs, paper value beside; a mean
    over the finite values of fewer runs than the method has says so (``(3 of 6 finite)``: an
    infinite error, a RUL beyond the horizon, is left out of it)."""
    summary = summarize(result.rows, result.metrics)
    methods = list(summary)
    counts = {m: sum(1 for r in result.rows if r["method"] == m) for m in methods}
    has_paper = {
        m: any(m in result.paper.get(meth, {}) for meth in methods) for m in result.metrics
    }
    head = ["method", "runs"]
    for m in result.metrics:
        head.append(f"{m} (ours)")
        if has_paper[m]:
            head.append(f"{m} (paper)")
    body = []
    for meth in methods:
        cells = [meth, str(counts[meth])]
        for m in result.metrics:
            st = summary[meth].get(m)
            given = sum(1 for r in result.rows if r["method"] == meth and r.get(m) is not None)
            some = "" if st is None or st.n == given else f" ({st.n} of {given} finite)"
            cells.append("—" if st is None else f"{fmt_value(st.mean)} ± {fmt_value(st.std)}{some}")
            if has_paper[m]:
                cells.append(fmt_value(result.paper.get(meth, {}).get(m)))
        body.append(cells)
    return markdown_table(head, body)


def fill_template(path: str | os.PathLike, values: Mapping[str, object]) -> str:
    """The text of the template at ``path`` with its ``str.format`` fields filled from
    ``values``.

    Raises:
        KeyError: naming every field of the template that ``values`` lacks.
    """
    text = Path(path).read_text()
    fields = {f.split(".")[0].split("[")[0] for _, f, _, _ in string.Formatter().parse(text) if f}
    missing = sorted(fields - set(values))
    if missing:
        raise KeyError(f"{path}: no value for the template fields {missing}")
    return text.format(**values)


def sweep_crossing(points: Sequence[tuple[float, float]], target: float) -> float | None:
    """Where a sweep first reaches ``target``: the setting at which the error falls to it.

    Args:
        points: ``(setting, error)`` pairs in sweep order (settings and errors positive).
        target: the error to reach.
    Returns:
        The first setting's value if its error is already ``<= target``; else the setting where
        the segment between the first pair that brackets ``target`` (``e_i > target >= e_{i+1}``)
        crosses it, interpolated linearly in ``log setting`` and ``log error``; ``None`` if no
        segment does.
    """
    pts = [(float(s), float(e)) for s, e in points]
    if not pts or any(not (s > 0 and e > 0) for s, e in pts) or not target > 0:
        raise ValueError("points must be non-empty (setting, error) pairs > 0 and target > 0")
    if pts[0][1] <= target:
        return pts[0][0]
    for (s0, e0), (s1, e1) in zip(pts, pts[1:]):
        if e0 > target >= e1:
            return s0 * (s1 / s0) ** (math.log(e0 / target) / math.log(e0 / e1))
    return None


def threshold_census(values, threshold: float, *, verb: str = "lie", digits: int = 3) -> str:
    """How many of ``values`` lie below and at or above ``threshold``, and their ranges, as a
    reading: ``"7 lie below 0.1 (0.052 to 0.061), 2 lie above 0.1 (0.734)"``.

    Args:
        values: ``(P,)`` finite numbers (a tensor or a sequence), e.g. where a noise-free
            recursion settles (:func:`~prognos_torch.prognosis.settle`).
        threshold: the dividing value (``>= threshold`` counts as above).
        verb: the word between the count and the side (``"settle"``: "3 settle below ...").
        digits: decimals of the ranges; a range narrower than half a unit of the last decimal
            is written as one value.
    Returns:
        One phrase per non-empty side (below first), joined by ``", "``; ``""`` for no values.
    """
    v = torch.as_tensor(values, dtype=torch.float64).flatten()
    if not bool(torch.isfinite(v).all()):
        raise ValueError("values must be finite")
    if not is_real(threshold) or math.isnan(threshold):  # (NaN: no value on either side, "")
        raise ValueError(f"threshold must be a real number, got {threshold!r}")
    parts = []
    for name, sel in (("below", v < threshold), ("above", v >= threshold)):
        if bool(sel.any()):
            lo, hi = float(v[sel].min()), float(v[sel].max())
            span = (
                f"{lo:.{digits}f}"
                if hi - lo < 0.5 * 10.0**-digits
                else f"{lo:.{digits}f} to {hi:.{digits}f}"
            )
            parts.append(f"{int(sel.sum())} {verb} {name} {threshold:g} ({span})")
    return ", ".join(parts)


def ascending(values: Mapping[str, float], spec: str = ".4f") -> str:
    """Named values in increasing order as a reading: ``"b 0.1000 < a 0.3000"``.

    Args:
        values: ``name -> value``; equal values keep the mapping's order.
        spec: the format of each value (``str.format`` spec, e.g. ``".5f"``).
    """
    return " < ".join(f"{k} {v:{spec}}" for k, v in sorted(values.items(), key=lambda kv: kv[1]))
