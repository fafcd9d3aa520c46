"""A univariate series from a CSV column or an array: parsing, row selection, gaps, time axis.

Rules (each violation raises ``ValueError``/``FileNotFoundError`` with a one-line message that
names the file, column and line):

* the CSV has a header row; the delimiter is ``,``, ``;`` or a tab (sniffed);
* ``where`` keeps the rows whose cell equals the given value (``channel=5`` matches ``5`` and
  ``5.0``): how a *long* table such as the shipped IMS features (one row per snapshot and
  channel) becomes one series;
* empty cells and ``nan``/``NA``/``null`` are *missing*; missing values are an error unless
  ``fill="linear"`` (interpolate over time; a gap at either end cannot be interpolated and is
  an error) or ``fill="drop"`` (remove those rows); any other non-numeric cell or an infinite
  value is an error;
* the time column holds numbers or ISO 8601 date-times (converted to days since the first row),
  strictly increasing; without one, time is the row index (step 1).
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from .._text import fmt_time, shown_lines
from ..core.validation import check_real, is_int
from ..io import sniffed_csv
from .arrays import array_times, array_values, check_real_numbers, datetime_index, pandas_name
from .times import (
    check_time_format,
    date_after,
    datetime_ns,
    days_since_first,
    formatted_stamps,
)

__all__ = ["Series", "load_series", "parse_where", "FILL_METHODS", "MAX_ABS_VALUE"]

FILL_METHODS = ("linear", "drop")
#: Largest magnitude of a series value: errors and variances are formed in the data's units
#: (forecast scores, bands), and squares of values beyond ``1e150`` overflow float64.
MAX_ABS_VALUE = 1e150
_MISSING = {"", "nan", "na", "n/a", "null", "none", "-"}


@dataclass(frozen=True)
class Series:
    """A univariate series, float64.

    Attributes:
        values: ``(T,)`` float64; NaN is a missing value (:func:`load_series` refuses, fills or
            drops them; :func:`~prognos_torch.workflow.prognose`, :func:`forecast` and
            :func:`rul` read them as missing, :func:`fit_series` refuses them).
        time: ``(T,)`` float64 strictly increasing, or ``None`` (row index).
        name: the value column (or ``"series"`` for an array).
        time_name: the time column, or ``None``.
        time_unit: ``"days"`` for date-times (days since ``start``), the time column's name for
            numeric time, ``"steps"`` without a time column.
        start: ISO 8601 date-time of the first row when the time column holds date-times.
        source: the CSV path, or ``None``.
    """

    values: Tensor
    time: Tensor | None = None
    name: str = "series"
    time_name: str | None = None
    time_unit: str = "steps"
    start: str | None = None
    source: str | None = None

    def __post_init__(self) -> None:
        # a tensor keeps its device; a NumPy array or a sequence becomes a CPU tensor. Only the
        # dtype is converted (to float64): a wrong shape or booleans are refused, never reshaped
        for attr in ("values", "time"):
            v = getattr(self, attr)
            if v is None and attr == "time":
                continue
            name = f"Series {attr}"
            if isinstance(v, Tensor):
                check_real_numbers(v, name)
                v = v.to(torch.float64)
            else:
                v = torch.from_numpy(array_values(v, name))
            if v.dim() != 1:
                raise ValueError(f"{name} must have shape (T,), got {tuple(v.shape)}")
            object.__setattr__(self, attr, v)
        if self.time is not None and self.time.shape != self.values.shape:
            raise ValueError(
                f"Series time must have the values' shape {tuple(self.values.shape)} (T,), got "
                f"{tuple(self.time.shape)}"
            )

    def __len__(self) -> int:
        return int(self.values.shape[0])

    @property
    def t(self) -> Tensor:
        """``(T,)`` time axis: :attr:`time`, or ``0, 1, ..., T - 1``."""
        if self.time is not None:
            return self.time
        return torch.arange(len(self), dtype=torch.float64, device=self.values.device)

    @property
    def dt(self) -> float:
        """Time per step: the median spacing of :attr:`time` (1 without a time column)."""
        if self.time is None or len(self) < 2:
            return 1.0
        return float(torch.diff(self.time).median())

    def date(self, t: float, unit: str = "s") -> str | None:
        """The ISO 8601 date-time (UTC) of time ``t`` on this series' axis, rounded to ``unit``
        (``"s"``, ``"ms"``, ``"us"``), where the time column holds date-times (:attr:`start`
        set); ``None`` for numeric time, a non-finite ``t`` or one beyond the years
        +-292,000 (:func:`date_after`)."""
        if self.start is None or not math.isfinite(float(t)):
            return None
        return date_after(self.start, float(t), unit)

    def head(self, n: int) -> Series:
        """The first ``n`` rows (a chronological training part)."""
        return Series(
            self.values[:n],
            None if self.time is None else self.time[:n],
            self.name,
            self.time_name,
            self.time_unit,
            self.start,
            self.source,
        )


def parse_where(where) -> dict[str, str]:
    """``None``, a mapping ``{column: value}`` or strings ``"column=value"`` -> a dict."""
    if where is None:
        return {}
    if isinstance(where, Mapping):
        return {str(k): str(v).strip() for k, v in where.items()}
    if isinstance(where, str):
        where = [where]
    out = {}
    for item in where:
        if not isinstance(item, str) or "=" not in item or not item.split("=", 1)[0].strip():
            raise ValueError(
                f"where: expected COLUMN=VALUE (--where COL=VALUE on the command line), got "
                f"{item!r}"
            )
        key, value = item.split("=", 1)
        if key.strip() in out:  # (the last one would win without a word)
            raise ValueError(
                f"where: column {key.strip()!r} is named twice ({key.strip()}={out[key.strip()]}, "
                f"{item.strip()}): a row holds one value per column, so no row could match both; "
                "select one value per column (run once per value)"
            )
        out[key.strip()] = value.strip()
    return out


def cells_equal(cell: str, value: str, decimal: str = ".") -> bool:
    """A ``where`` match: ``cell`` (text) equals ``value`` as text, or as a number (``5`` and
    ``5.0``; with ``decimal`` the cell's decimal mark)."""
    cell = cell.strip()
    if cell == value:
        return True
    try:
        return _number(number_text(cell, decimal)) == _number(number_text(value, decimal))
    except ValueError:
        return False


def _number(text: str) -> float:
    """``float(text)`` without Python's digit-group underscores: ``1_000`` is no number in a
    CSV file (``float`` read it as 1000); ``ValueError`` for it as for any other non-number."""
    if "_" in text:
        raise ValueError(f"{text!r} is not a number")
    return float(text)


def number_text(cell: str, decimal: str) -> str:
    """``cell`` stripped, its decimal comma made a point (``decimal=","``). With a decimal comma
    a point is refused (``ValueError``): it would be a thousands separator there (``1.234,5``),
    which is not read silently as a decimal point."""
    text = cell.strip()
    if decimal == ",":
        if "." in text:
            raise ValueError(f"{text!r} has a '.' but decimal=','")
        text = text.replace(",", ".")
    return text


def _decimal_comma(text: str, decimal: str) -> bool:
    """Whether ``text``, unreadable with a decimal point, reads as a number with a comma."""
    if decimal != "." or "," not in text:
        return False
    try:
        float(text.strip().replace(",", "."))
    except ValueError:
        return False
    return True


def decimal_hint(cell: str, decimal: str) -> str:
    """The end of a "... is not a number" message: why, where the decimal mark explains it."""
    text = cell.strip()
    if _decimal_comma(text, decimal):
        return "; a decimal comma? pass decimal=',' (--decimal , on the command line)"
    if decimal == "," and "." in text:
        return " with decimal=',' (a '.' there would be a thousands separator)"
    return ""


def _not_a_number(where: str, what: str, cell: str, decimal: str) -> ValueError:
    """The error for an unparsable numeric cell."""
    text = cell.strip()
    return ValueError(
        f"{where}: {what} value {text!r} is not a number{decimal_hint(text, decimal)}"
    )


def _parse_number(cell: str, decimal: str = ".") -> float | None:
    """A float, ``None`` for a missing cell; ``ValueError`` for anything else."""
    text = cell.strip()
    if text.lower() in _MISSING:
        return None
    value = _number(number_text(text, decimal))  # raises ValueError for non-numbers
    if math.isnan(value):
        return None
    return value


def _read_csv(path: Path) -> tuple[list[str], list[list[str]]]:
    with sniffed_csv(path, missing="data file", not_a_file="data path") as reader:
        rows = list(reader)
    if not rows or not any(cell.strip() for cell in rows[0]):
        raise ValueError(f"{path}: empty file (a header row with column names is required)")
    header = [cell.strip() for cell in rows[0]]
    return header, rows[1:]


def check_unique_columns(header: Sequence, names: Sequence, source: str) -> None:
    """Each of ``names`` (``None`` skipped) appears at most once in ``header``: a column named
    twice is an error, not a silent choice of one of them."""
    header = list(header)
    for name in names:
        if name is not None and header.count(name) > 1:
            raise ValueError(
                f"{source}: column {name!r} appears more than once in the header; rename one"
            )


def _parse_time(
    cells: list[str],
    lines: list[int],
    path: str,
    col: str,
    decimal: str = ".",
    time_format: str | None = None,
):
    """Numbers, ISO 8601 date-times, or date-times in ``time_format`` -> days since the first
    row."""
    if time_format is not None:

        def label(i: int) -> str:
            return f"{path}, line {lines[i]}: time column {col!r} value {cells[i].strip()!r}"

        try:
            return days_since_first(formatted_stamps(cells, time_format, label))
        except ValueError as exc:
            raise ValueError(f"{exc} (time_format: --time-format on the command line)") from None
    numeric = []
    for cell, line in zip(cells, lines):
        try:
            numeric.append(_number(number_text(cell, decimal)))
        except ValueError:
            if numeric:  # numbers first, then something else
                raise _not_a_number(
                    f"{path}, line {line}", f"time column {col!r}", cell, decimal
                ) from None
            break
    else:
        bad = [ln for v, ln in zip(numeric, lines) if not math.isfinite(v)]
        if bad:  # (nan: a missing time; inf)
            raise ValueError(
                f"{path}: time column {col!r} has non-finite values at line(s) {shown_lines(bad)}"
            )
        return np.asarray(numeric, dtype=np.float64), col, None
    stamps = []
    for cell, line in zip(cells, lines):
        try:
            stamps.append(datetime_ns(cell))
        except ValueError as exc:
            if _decimal_comma(cell, decimal):  # a number with a decimal comma, not a date
                where = f"{path}, line {line}"
                raise _not_a_number(where, f"time column {col!r}", cell, decimal) from None
            raise ValueError(
                f"{path}, line {line}: time column {col!r} value {cell!r} is neither a number "
                f"nor an ISO 8601 date-time in 1678-2262 ({exc}); for another layout give "
                "time_format (--time-format), e.g. '%d/%m/%Y %H:%M'"
            ) from None
        if np.isnat(stamps[-1]):  # ('nan' or 'NaT': empty cells are refused before)
            raise ValueError(f"{path}, line {line}: time column {col!r} is missing ({cell!r})")
    return days_since_first(np.asarray(stamps))


def _fill(values: np.ndarray, time: np.ndarray | None, where: list, fill, lines, label: str):
    missing = np.isnan(values)
    if not missing.any():
        return values, time, lines
    bad = [lines[i] for i in np.flatnonzero(missing)]
    if fill is None:
        raise ValueError(
            f"{label} has {len(bad)} missing value(s) at {where[0]} {shown_lines(bad)}; pass "
            "fill='linear' (interpolate) or fill='drop' (remove those rows); --fill linear or "
            "--fill drop on the command line"
        )
    if fill == "drop":
        keep = ~missing
        kept_lines = [ln for ln, k in zip(lines, keep) if k]
        return values[keep], None if time is None else time[keep], kept_lines
    # linear interpolation over time (or the index); ends cannot be interpolated
    if missing[0] or missing[-1]:  # name the runs at the ends only (the rest interpolate)
        observed = np.flatnonzero(~missing)
        if not observed.size:
            raise ValueError(f"{label} has no value: every one is missing")
        ends = []
        for end, rows in (("start", range(observed[0])), ("end", range(observed[-1] + 1,
                                                                     len(values)))):  # fmt: skip
            if len(rows):
                ends.append(f"the {end} ({where[0]} {shown_lines([lines[i] for i in rows])})")
        raise ValueError(
            f"{label} has missing value(s) at {' and '.join(ends)} that cannot be "
            "interpolated; use fill='drop' (--fill drop)"
        )
    x = time if time is not None else np.arange(values.shape[0], dtype=np.float64)
    out = values.copy()
    out[missing] = np.interp(x[missing], x[~missing], values[~missing])
    return out, time, lines


def load_series(
    source: str | os.PathLike | Tensor | np.ndarray | Sequence[float],
    column: str | None = None,
    *,
    time_column: str | None = None,
    time=None,
    where=None,
    fill: str | None = None,
    last: int | None = None,
    until: float | str | None = None,
    name: str | None = None,
    time_unit: str | None = None,
    decimal: str = ".",
    time_format: str | None = None,
) -> Series:
    """Load a univariate series from a CSV column or an array.

    Args:
        source: path of a CSV file with a header row, or a 1-D array of values (a tensor, a
            NumPy array, a pandas Series, by position and named after it, or a sequence).
        column: the value column (CSV); may be omitted when the file has exactly one column
            besides ``time_column`` and the ``where`` columns.
        time_column: optional time column (CSV): numbers or ISO 8601 date-times.
        time: optional ``(T,)`` time values for an array ``source``: numbers, or date-times
            (NumPy ``datetime64``, pandas; zone-aware ones in UTC; ISO 8601 texts, as a CSV
            read without date parsing holds them) as days since the first
            (``time_unit`` ``"days"``), as from a CSV. A pandas Series on a ``DatetimeIndex``
            takes that index as its time.
        where: rows to keep, e.g. ``{"channel": "5"}`` or ``["channel=5"]`` (CSV).
        fill: ``None`` (missing values are an error), ``"linear"`` or ``"drop"``.
        last: keep only the last ``last`` rows (after ``where`` and ``until``, before gap
            handling).
        name: the series' name (arrays; a CSV series is named after its column).
        time_unit: unit of ``time`` for an array (default ``"time"``, ``"steps"`` without time).
        until: keep only rows with time ``<= until`` (needs a time): a number in the series'
            time unit (days for date-times, measured from the first row) or an ISO 8601
            date-time. Backtesting: forecast from a past origin and compare with what followed.
        decimal: the CSV's decimal mark, ``"."`` or ``","`` (``0,25``: tables written with a
            ``;`` or tab delimiter in many European locales); it applies to the value column,
            a numeric time column and numeric ``where`` values. With ``","`` a cell holding a
            point is refused (a thousands separator there, never read as a decimal point).
        time_format: the layout of the CSV time column, or of an array's ``time`` given as
            text, in ``datetime.strptime`` codes (e.g. ``"%d/%m/%Y %H:%M"``) for date-times
            that are not ISO 8601; a ``%z`` offset is applied, times without one are taken as
            UTC. ``None``: numbers or ISO 8601.

    Returns:
        :class:`Series` (float64 values, time if given).

    Raises:
        TypeError: ``source`` is neither a path nor an array of numbers.
        ValueError: bad options, unparsable or infinite values, missing values without
            ``fill``, a time axis that does not increase, or a value beyond
            :data:`MAX_ABS_VALUE` (``1e150``) in magnitude.
    """
    if fill is not None and fill not in FILL_METHODS:
        raise ValueError(f"fill must be None, 'linear' or 'drop', got {fill!r}")
    if decimal not in (".", ","):
        raise ValueError(f"decimal must be '.' or ',', got {decimal!r}")
    check_time_format(time_format)
    if last is not None and (not is_int(last) or last < 1):
        raise ValueError(f"last must be a positive int, got {last!r}")
    last = None if last is None else int(last)
    pandas_like = hasattr(source, "to_numpy")
    if not (
        isinstance(source, (str, os.PathLike, Tensor, np.ndarray, Sequence)) or pandas_like
    ) or isinstance(source, (bytes, bytearray)):
        raise TypeError(
            f"source must be a CSV path or a 1-D array of numbers, got {type(source).__name__} "
            f"{source!r:.40}"
        )
    if isinstance(source, (str, os.PathLike)):
        if name is not None or time_unit is not None:
            raise ValueError("name and time_unit apply to arrays; a CSV series takes its names")
        if time_format is not None and time_column is None:
            raise ValueError(
                "time_format applies to a time column: give time_column as well (--time-column "
                "on the command line)"
            )
        opts = (fill, last, until, decimal, time_format)
        return _load_csv(Path(source), column, time_column, parse_where(where), *opts)
    if any(v is not None for v in (column, time_column, where)) or decimal != ".":
        raise ValueError("column, time_column, where and decimal apply to CSV files, not to arrays")
    if time_format is not None and time is None:
        raise ValueError("time_format applies to a time column or time=: give one as well")
    for arg, v in (("name", name), ("time_unit", time_unit)):
        if v is not None and (not isinstance(v, str) or not v):
            raise ValueError(f"{arg} must be a non-empty string, got {v!r}")
    arr = array_values(source, "source")
    if arr.ndim != 1:
        raise ValueError(f"source must be 1-D (T,), got shape {arr.shape}")
    tarr = start = None
    if time is None:
        time = datetime_index(source)
    if time is not None:
        tarr, t_unit, start = array_times(time, "time", time_format)
        if t_unit is not None:
            if time_unit not in (None, t_unit):
                raise ValueError(f"time holds date-times (days since the first); time_unit "
                                 f"{time_unit!r} does not apply")  # fmt: skip
            time_unit = t_unit
        if tarr.shape != arr.shape:
            raise ValueError(f"time must have shape {arr.shape} like source, got {tarr.shape}")
    if until is not None:
        if tarr is None:
            raise ValueError("until needs a time axis: pass time=...")
        if not np.isfinite(tarr).all():  # (a NaN time fell out of the cut without a word)
            i = int(np.flatnonzero(~np.isfinite(tarr))[0])
            raise ValueError(f"time has a non-finite value at index {i}")
        keep = _cut(tarr, until, start, None, None, None)
        arr, tarr = arr[keep], tarr[keep]
    if last is not None:
        arr = arr[-last:]
        tarr = None if tarr is None else tarr[-last:]
    if np.isinf(arr).any():
        i = int(np.flatnonzero(np.isinf(arr))[0])
        raise ValueError(f"source has an infinite value at index {i}")
    idx = list(range(arr.shape[0]))
    arr, tarr, _ = _fill(arr, tarr, ["index"], fill, idx, "source")
    unit = "steps" if tarr is None else (time_unit or "time")
    name = name or pandas_name(source) or "series"
    return _finish(arr, tarr, name, None, unit, start, None)


def _shown_time(days: float, start: str | None) -> str:
    """A time for a message: the date-time it was read from (to the microsecond) where the
    series has date-times, else the number (:func:`fmt_time`)."""
    return (None if start is None else date_after(start, days)) or fmt_time(days)


def check_magnitude(values: np.ndarray, name: str, source=None, lines=None) -> None:
    """Refuse values beyond :data:`MAX_ABS_VALUE` in magnitude (``ValueError`` naming the
    first, by its CSV line where ``lines`` are given, else its index): scores, bands and
    baseline statistics square the data's units, which overflows float64; and values all
    below ``1 / MAX_ABS_VALUE`` in magnitude (but not all zero), whose squares underflow.
    Infinite values are left to the callers' own message."""
    big = np.isfinite(values) & (np.abs(values) > MAX_ABS_VALUE)
    if big.any():
        i = int(np.flatnonzero(big)[0])
        where = f"{source}, line {lines[i]}" if lines is not None else f"index {i}"
        raise ValueError(
            f"{where}: value {values[i]:g} of {name!r} exceeds {MAX_ABS_VALUE:g} in magnitude; "
            "forecast scores and bands square the data's units, which overflows float64: "
            f"rescale the values (e.g. divide by 1e{int(math.log10(abs(values[i])))})"
        )
    finite = np.abs(values[np.isfinite(values)])
    top = float(finite.max()) if finite.size else 0.0
    if 0.0 < top < 1.0 / MAX_ABS_VALUE:  # (all zeros: the callers' constant-series message)
        where = f"{source}: " if source is not None else ""
        raise ValueError(
            f"{where}the values of {name!r} are at most {top:g} in magnitude, below "
            f"{1.0 / MAX_ABS_VALUE:g}: the squares of their spread underflow float64 (a "
            f"healthy band would read as zero width); rescale the values (e.g. multiply by "
            f"1e{-int(math.floor(math.log10(top)))})"
        )


def _check_increasing(time, time_name, start, source, lines) -> None:
    """``time`` strictly increases (``ValueError`` naming the first row that does not)."""
    steps = np.diff(time)
    if (steps <= 0).any():
        i = int(np.flatnonzero(steps <= 0)[0])
        where = f"line {lines[i + 1]}" if lines is not None else f"index {i + 1}"
        what = f"time column {time_name!r}" if time_name else "time"
        prefix = f"{source}, " if source else ""
        hint = ""
        if source and time[i + 1] == time[i]:  # a long table: several series in one file
            hint = (
                "; a repeated time: if the file holds several series, select one with "
                "--where COL=VALUE (where={COL: VALUE} in load_series)"
            )
        raise ValueError(
            f"{prefix}{where}: {what} must be strictly increasing "
            f"({_shown_time(time[i + 1], start)} follows {_shown_time(time[i], start)}){hint}"
        )


def _cut(time, until, start, time_name, source, lines) -> np.ndarray:
    """The rows at or before ``until``: the first rows of a series in time order. Where a row
    after the cut precedes one before it (rows out of order: ``0, 5, 2`` cut at 3 kept 0 and 2,
    as if in order), the order is refused as :func:`_finish` refuses it."""
    keep = time <= time_value(until, start, "until")
    if not keep[: int(keep.sum())].all():  # (then the time decreases somewhere)
        _check_increasing(time, time_name, start, source, lines)
    return keep


def _finish(values, time, name, time_name, unit, start, source, lines=None) -> Series:
    if values.shape[0] == 0:
        raise ValueError(f"series {name!r} is empty after selecting rows")
    check_magnitude(values, name, source, lines)
    if time is not None:
        if not np.isfinite(time).all():
            raise ValueError(f"time of series {name!r} has non-finite values")
        _check_increasing(time, time_name, start, source, lines)
    return Series(
        values=torch.as_tensor(values, dtype=torch.float64).clone(),
        time=None if time is None else torch.as_tensor(time, dtype=torch.float64).clone(),
        name=name,
        time_name=time_name,
        time_unit=unit,
        start=start,
        source=source,
    )


def time_value(v, start: str | None, name: str) -> float:
    """A time on a series' axis as a float: a number (Python, NumPy or a 0-dim tensor; text
    holding a number) as given, or, when the series' time holds date-times (``start`` set), a
    date-time (ISO 8601 text, NumPy ``datetime64``, a pandas ``Timestamp`` or ``datetime``;
    zone-aware ones in UTC) as days since ``start``. Refusals are ``ValueError`` naming
    ``name``."""
    if isinstance(v, str):
        try:
            v = _number(v.strip())
        except ValueError:
            pass
    stamp = None
    if isinstance(v, str):
        try:
            stamp = datetime_ns(v)
        except ValueError:
            raise ValueError(
                f"{name} must be a number or an ISO 8601 date-time, got {v!r}"
            ) from None
    elif isinstance(v, np.datetime64):
        stamp = v.astype("datetime64[ns]")
    elif hasattr(v, "isoformat") and hasattr(v, "year"):  # datetime, pandas Timestamp
        stamp = datetime_ns(v.isoformat())
    if stamp is None:
        if isinstance(v, float) and not math.isfinite(v):
            raise ValueError(f"{name} must be finite, got {v!r}")
        return check_real(v, name)
    if start is None:
        raise ValueError(
            f"{name}={v!r} is a date-time but the series' time does not hold date-times"
        )
    if np.isnat(stamp):
        raise ValueError(f"{name} is a missing date-time (NaT)")
    return float((stamp - datetime_ns(start)) / np.timedelta64(1, "D"))


def _load_csv(path, column, time_column, where, fill, last, until, decimal, time_format) -> Series:
    header, rows = _read_csv(path)
    index = {name: j for j, name in enumerate(header)}
    for col, what in [(time_column, "time column")] + [(c, "where column") for c in where]:
        if col is not None and col not in index:
            raise ValueError(f"{path}: no {what} {col!r}; columns: {', '.join(header)}")
    if column is None:
        others = [h for h in header if h != time_column and h not in where]
        if len(others) != 1:
            raise ValueError(
                f"{path}: name the value column with column=... (--column on the command "
                f"line); columns: {', '.join(header)}"
            )
        column = others[0]
    if column not in index:
        raise ValueError(f"{path}: no column {column!r}; columns: {', '.join(header)}")
    if column == time_column or column in where:
        role = "the time column" if column == time_column else "a where column"
        raise ValueError(
            f"{path}: the value column {column!r} is also {role}; name the indicator to "
            f"predict (columns: {', '.join(header)})"
        )
    check_unique_columns(header, [column, time_column, *where], str(path))
    j = index[column]
    jt = index[time_column] if time_column is not None else None
    wj = [(index[c], v) for c, v in where.items()]

    cells, tcells, lines = [], [], []
    for line, row in enumerate(rows, start=2):
        if not row or not any(c.strip() for c in row):
            continue  # blank line
        if len(row) != len(header):
            raise ValueError(f"{path}, line {line}: {len(row)} cells, header has {len(header)}")
        if not all(cells_equal(row[k], v, decimal) for k, v in wj):
            continue
        cells.append(row[j])
        tcells.append(row[jt] if jt is not None else None)
        lines.append(line)
    if not cells:
        sel = f" matching {', '.join(f'{k}={v}' for k, v in where.items())}" if where else ""
        raise ValueError(f"{path}: no data rows{sel}")
    time, unit, start = None, "steps", None
    if jt is not None:
        empty = [ln for c, ln in zip(tcells, lines) if not c.strip()]
        if empty:
            raise ValueError(
                f"{path}: time column {time_column!r} is empty at line(s) {shown_lines(empty)}"
            )
        time, unit, start = _parse_time(tcells, lines, str(path), time_column, decimal, time_format)
    if until is not None:
        if time is None:
            raise ValueError(
                "until needs a time column (time_column=..., --time-column on the command line)"
            )
        keep = _cut(time, until, start, time_column, str(path), lines)
        if not keep.any():
            raise ValueError(
                f"{path}: no data rows at or before until={until!r} (--until on the command line)"
            )
        cells = [c for c, k in zip(cells, keep) if k]
        lines = [ln for ln, k in zip(lines, keep) if k]
        time = time[keep]
    if last is not None:
        cells, lines = cells[-last:], lines[-last:]
        time = None if time is None else time[-last:]

    values = np.empty(len(cells), dtype=np.float64)
    for i, (cell, line) in enumerate(zip(cells, lines)):
        try:
            v = _parse_number(cell, decimal)
        except ValueError:
            raise _not_a_number(
                f"{path}, line {line}", f"column {column!r}", cell, decimal
            ) from None
        if v is not None and not math.isfinite(v):
            raise ValueError(f"{path}, line {line}: column {column!r} value {cell!r} is infinite")
        values[i] = math.nan if v is None else v
    values, time, lines = _fill(values, time, ["line(s)"], fill, lines, f"{path}: {column!r}")
    return _finish(values, time, column, time_column, unit, start, str(path), lines)
