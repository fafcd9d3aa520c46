"""Long fleet tables in and out: CSV built in; pandas DataFrames and Parquet through the
optional ``tables`` extra (pandas, pyarrow), imported only when used.

A long table has one row per measurement: an asset id, a time and a value (column names are
chosen by the caller). Rules (each violation names the asset and the data row, counted from 1
after the header; a CSV message also gives the file line, blank lines skipped):

* the asset, time and value columns must exist (the message lists the columns found);
* the asset id is text (numbers are read as their text, so ``7`` in a DataFrame and ``"7"`` in a
  CSV are the same asset); an empty id is an error;
* time: numbers, or ISO 8601 date-times (then days since 1970-01-01T00:00:00 UTC, the same
  axis for every table, so that the results of shards read apart merge; the result adds the
  dates, :data:`~prognos_torch.fleet.DATE_COLUMNS`); missing or non-finite times are errors;
* value: a number; empty cells and ``nan``/``NA``/``null``/``none``/``-`` are missing (NaN);
  anything else (text, ``inf``) is a *non-numeric value*;
* a CSV read with ``decimal=","`` (``0,25``; ``--decimal ,``) has decimal commas in its value
  and numeric time cells; a number written with a point there is refused (a thousands
  separator in those locales), never read as a decimal point;
* per asset, times must be strictly increasing in table order: an equal time is a *duplicate
  timestamp*, a smaller one *unsorted time*. Assets may be interleaved in the table;
* ``where`` (``--where channel=5``) keeps the rows whose cells equal the given values, before
  any of these checks: a table with a row per asset, time and channel holds one series per
  channel. Messages still count the rows of the whole table.

Per-asset problems (non-numeric value, duplicate or unsorted time) raise ``ValueError`` by
default; with ``on_error="flag"`` the asset is set aside with its message and the rest of the
fleet goes on. Output files are written atomically (a temporary file in the same folder, then a
rename): an interrupted run leaves the old file or none, never a partial one.
"""

from __future__ import annotations

import csv
import importlib
import io
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .._text import fmt_time
from ..io import atomic_write, sniffed_csv
from ..workflow.data import (
    cells_equal,
    check_unique_columns,
    decimal_hint,
    number_text,
    parse_where,
)
from ..workflow.times import datetime_ns, formatted_stamps, iso_start

__all__ = ["FleetTable", "read_fleet_table", "write_table", "TABLE_SUFFIXES"]

TABLE_SUFFIXES = (".csv", ".parquet", ".pq")
_MISSING = {"", "nan", "na", "n/a", "null", "none", "-"}


def _needs(package: str):
    """Import an optional dependency of the ``tables`` extra, or say how to install it."""
    try:
        return importlib.import_module(package)
    except ImportError:
        raise ImportError(
            f"{package} is needed for this table format; install the optional extra: "
            'pip install "prognos_torch[tables]"'
        ) from None


@dataclass(frozen=True, eq=False)
class FleetTable:
    """A validated long table grouped by asset.

    Attributes:
        assets: asset ids (text) in order of first appearance.
        times: one float64 array per asset (strictly increasing).
        values: one float64 array per asset (NaN: missing).
        rows: one int64 array per asset: the data rows (1-based) the samples came from.
        errors: ``{asset: message}`` for assets set aside (``on_error="flag"``).
        source: where the table came from (for messages).
        time_unit: ``None`` (the time column's own unit) or ``"days"`` (date-times).
        epoch: the date-time that is day 0, or ``None``.
        columns: ``(group_by, time_column, column)`` names used.
    """

    assets: list[str]
    times: list[np.ndarray]
    values: list[np.ndarray]
    rows: list[np.ndarray]
    errors: dict[str, str] = field(default_factory=dict)
    source: str = "table"
    time_unit: str | None = None
    epoch: str | None = None
    columns: tuple[str, str, str] = ("asset", "t", "value")

    def __len__(self) -> int:
        return len(self.assets)


# --------------------------------------------------------------------------- reading
def _missing_column(name: str, what: str, found: Sequence[str], source: str) -> ValueError:
    shown = ", ".join(repr(c) for c in found[:20]) + (" ..." if len(found) > 20 else "")
    return ValueError(f"{source}: no {what} column {name!r}; columns found: {shown}")


def _csv_columns(path: Path, names: Sequence[str], whats: Sequence[str]):
    with sniffed_csv(path, missing="table", not_a_file="table path") as reader:
        header = next(reader, None)
        if header is None or not any(c.strip() for c in header):
            raise ValueError(f"{path}: empty file (a header row with column names is needed)")
        header = [c.strip() for c in header]
        check_unique_columns(header, names, str(path))
        idx = []
        for name, what in zip(names, whats):
            if name not in header:
                raise _missing_column(name, what, header, str(path))
            idx.append(header.index(name))
        cols: list[list[str]] = [[] for _ in names]
        lines: list[int] = []
        width = max(idx) + 1
        for row in reader:
            if len(row) < width:
                if not any(c.strip() for c in row):
                    continue  # blank line
                raise ValueError(
                    f"{path}, line {reader.line_num}: {len(row)} cells, the header has "
                    f"{len(header)}"
                )
            lines.append(reader.line_num)
            for c, i in zip(cols, idx):
                c.append(row[i])
    return cols, lines


def _frame_columns(frame, names: Sequence[str], whats: Sequence[str], source: str):
    check_unique_columns(frame.columns, names, source)
    found = [str(c) for c in frame.columns]
    out = []
    for name, what in zip(names, whats):
        if name not in frame.columns:
            raise _missing_column(name, what, found, source)
        out.append(frame[name].to_numpy())
    return out


def _mapping_columns(data: Mapping, names: Sequence[str], whats: Sequence[str], source: str):
    out = []
    for name, what in zip(names, whats):
        if name not in data:
            raise _missing_column(name, what, [str(k) for k in data], source)
        out.append(np.asarray(data[name]))
    return out


def _id_text(v) -> str:
    """One asset id as text: a missing cell (None, NaN, pandas' NA) is empty; a whole-number
    float is the integer it holds (7.0 is asset "7", as 7 is)."""
    if v is None or type(v).__name__ == "NAType":
        return ""
    if isinstance(v, (float, np.floating)):
        if not math.isfinite(v):
            return ""
        return str(int(v)) if float(v).is_integer() else repr(float(v))
    return str(v).strip()


def _asset_text(col) -> np.ndarray:
    arr = np.asarray(col)
    if arr.dtype.kind in "iu":
        return arr.astype(str)
    if arr.dtype.kind == "U":
        return np.char.strip(arr).astype(object)
    cells = arr.tolist()
    try:  # each distinct id converted once (keyed by type: True and 1 are different ids)
        known: dict = {}
        text = [known.get(k) or known.setdefault(k, _id_text(v)) for v in cells
                for k in ((type(v), v),)]  # fmt: skip
    except TypeError:  # an unhashable cell
        text = [_id_text(v) for v in cells]
    return np.array(text, dtype=object)


def _na_cell(cell) -> bool:
    """A cell that holds no value: None or pandas' NA (a nullable column's missing cell)."""
    return cell is None or type(cell).__name__ == "NAType"


def _numbers(col, what: str):
    """float64 array and the positions of cells that are not numbers (text or inf)."""
    arr = np.asarray(col)
    if arr.dtype.kind in "iubc":
        if arr.dtype.kind in "bc":  # booleans and complex numbers are not values
            return np.full(arr.shape, np.nan), np.arange(arr.size)
        return arr.astype(np.float64), np.empty(0, dtype=np.int64)
    if arr.dtype.kind == "f":
        out = arr.astype(np.float64)
        return out, np.flatnonzero(np.isinf(out))
    # fast path: every cell is a number (NumPy parses the text); not with a boolean cell among
    # them, which it would read as 0/1 where a column of booleans is refused
    if arr.dtype.kind != "O" or not any(isinstance(c, (bool, np.bool_)) for c in arr.flat):
        try:
            out = np.asarray(arr, dtype=np.float64)
            return out, np.flatnonzero(np.isinf(out))
        except (ValueError, TypeError):
            pass
    out = np.empty(arr.size, dtype=np.float64)
    bad = []
    for i, cell in enumerate(arr.tolist()):
        if _na_cell(cell):  # (pandas' NA printed '<NA>' and was "not a number")
            out[i] = np.nan
            continue
        if isinstance(cell, (int, float)) and not isinstance(cell, bool):
            out[i] = float(cell)
            if math.isinf(out[i]):
                bad.append(i)
            continue
        text = str(cell).strip()
        if text.lower() in _MISSING:
            out[i] = np.nan
            continue
        try:
            out[i] = float(text)
        except ValueError:
            out[i] = np.nan
            bad.append(i)
            continue
        if math.isinf(out[i]):
            bad.append(i)
    return out, np.asarray(bad, dtype=np.int64)


_UNIX_EPOCH = np.datetime64("1970-01-01T00:00:00", "ns")


def _times(col, where, time_format: str | None = None):
    """Numeric times, or date-times (ISO 8601, or text in ``time_format``) as days since
    1970-01-01 UTC; returns (t, unit, epoch)."""
    arr = np.asarray(col)
    if time_format is not None and arr.dtype.kind not in "Miuf":
        cells = arr.tolist()
        _no_missing_time(cells, where)
        stamps = formatted_stamps([str(c) for c in cells], time_format,
                                  lambda i: f"{where(i)}: time {cells[i]!r}")  # fmt: skip
    elif arr.dtype.kind == "M":
        # datetime64[ns] holds 1678-2262; beyond, NumPy's cast wraps around silently (3000-01-01
        # was 1830-11-23)
        sec = arr.astype("datetime64[s]")
        lo, hi = np.datetime64("1678-01-01", "s"), np.datetime64("2262-01-01", "s")
        out = np.flatnonzero(~np.isnat(sec) & ((sec < lo) | (sec >= hi)))
        if out.size:
            raise ValueError(
                f"{where(out[0])}: time {arr[out[0]]} lies outside 1678-2262, the range of "
                "nanosecond times"
            )
        stamps = arr.astype("datetime64[ns]")
    elif arr.dtype.kind in "iuf":
        t = arr.astype(np.float64)
        bad = np.flatnonzero(~np.isfinite(t))
        if bad.size:
            raise ValueError(f"{where(bad[0])}: the time is missing or not finite")
        return t, None, None
    else:
        t, bad = _numbers(arr, "time")
        finite = np.isfinite(t)
        if finite.all():
            return t, None, None
        cells = arr.tolist()  # (Python text: np.str_ cells would print as np.str_('x'))
        if finite.any():  # a column of numbers: a missing or infinite cell, or text among them
            i, j = int(np.flatnonzero(~finite)[0]), int(np.flatnonzero(finite)[0])
            if np.isnan(t[i]) and bool((bad == i).any()):  # text, not a missing cell
                raise ValueError(
                    f"{where(i)}: time {cells[i]!r} is not a number, while {where(j)} holds the "
                    f"number {cells[j]!r}: a time column holds numbers or ISO 8601 date-times, "
                    "not both"
                )
            raise ValueError(f"{where(i)}: the time is missing or not finite")
        _no_missing_time(cells, where)
        stamps = np.empty(len(cells), dtype="datetime64[ns]")
        for i, c in enumerate(cells):
            try:
                stamps[i] = datetime_ns(str(c))
            except ValueError as exc:
                comma = decimal_hint(str(c), ".")  # a number with a decimal comma?
                if comma:
                    raise ValueError(f"{where(i)}: time {c!r} is not a number{comma}") from None
                raise ValueError(
                    f"{where(i)}: time {c!r} is neither a number nor an ISO 8601 date-time in "
                    f"1678-2262 ({exc}); a time column holds one or the other (time_format, "
                    "--time-format, reads another layout of date-times)"
                ) from None
    nat = np.flatnonzero(np.isnat(stamps))
    if nat.size:
        raise ValueError(f"{where(nat[0])}: the time is missing")
    # days since the Unix epoch (UTC): the same axis in every table, so that the results of
    # tables read apart (shards of one fleet, files of different days) compare and merge
    days = (stamps - _UNIX_EPOCH) / np.timedelta64(1, "D")
    return days.astype(np.float64), "days", iso_start(_UNIX_EPOCH)


def _no_missing_time(cells: list, where) -> None:
    """``ValueError`` at the first date-time cell that is missing: empty, None, pandas' NA, NaN
    or ``NaT`` (None was "neither a number nor an ISO 8601 date-time", an empty cell with a
    ``time_format`` did "not match" it)."""
    for i, c in enumerate(cells):
        if (
            _na_cell(c)
            or (isinstance(c, float) and math.isnan(c))
            or (isinstance(c, str) and c.strip().lower() in ("", "nan", "nat"))
        ):
            raise ValueError(f"{where(i)}: the time is missing")


def _comma_values(cells: list[str]) -> tuple[list[str], np.ndarray]:
    """Value cells read with a decimal comma (:func:`~prognos_torch.workflow.data.number_text`),
    and the positions of those that hold a point (refused there: a thousands separator)."""
    out, dotted = [], []
    for i, c in enumerate(cells):
        try:
            out.append(number_text(c, ","))
        except ValueError:
            out.append(c)
            dotted.append(i)
    return out, np.asarray(dotted, dtype=np.int64)


def _comma_times(cells: list[str], where) -> list[str]:
    """Time cells read with a decimal comma; a number written with a point is refused, a
    date-time with a point (a fraction of a second) is left as it is."""
    out = []
    for i, c in enumerate(cells):
        try:
            out.append(number_text(c, ","))
            continue
        except ValueError:
            pass
        try:
            float(c)
        except ValueError:  # a date-time
            out.append(c)
            continue
        raise ValueError(f"{where(i)}: time {c.strip()!r} is not a number{decimal_hint(c, ',')}")
    return out


def _roles(group_by: str, time_column: str, column: str, where) -> tuple[tuple, tuple, dict]:
    """The columns to read, ``(names, whats, where)``: asset, time and value (each in one role)
    and the ``where`` columns besides them, which may not be the time or value column."""
    names = (group_by, time_column, column)
    whats = ("asset (--group-by)", "time (--time-column)", "value (--column)")
    for i in range(3):
        for j in range(i + 1, 3):
            if names[i] == names[j]:  # one column read in two roles
                raise ValueError(
                    f"the {whats[i]} and {whats[j]} columns must differ, both are {names[i]!r}"
                )
    where = parse_where(where)
    for name, what in zip(names[1:], whats[1:]):
        if name in where:  # (a time or a value is no selection of rows)
            raise ValueError(
                f"where: {name}={where[name]} selects on the {what} column; select rows by "
                "another column (the asset column, a channel)"
            )
    extra = [c for c in where if c != group_by]  # read besides the three
    names, whats = names + tuple(extra), whats + ("where",) * len(extra)
    return names, whats, where


def _source_columns(source, names: tuple, whats: tuple) -> tuple[list, list | None, str]:
    """The columns ``names`` of a CSV or Parquet path, a DataFrame or a mapping, as
    ``(columns, lines, label)`` (``lines``: a CSV row's line in its file, else ``None``;
    ``label``: the source in messages)."""
    lines = None
    if isinstance(source, (str, Path)):
        path = Path(source)
        label = str(path)
        suffix = path.suffix.lower()
        if suffix == ".csv":
            cols, lines = _csv_columns(path, names, whats)
        elif suffix in (".parquet", ".pq"):
            if not path.exists():
                raise FileNotFoundError(f"table not found: {path}")
            pq = _needs("pyarrow.parquet")
            try:
                tab = pq.read_table(path)
            except Exception as exc:  # pyarrow raises its own error types
                raise ValueError(f"{path}: not a readable Parquet file ({exc})") from None
            found = list(tab.column_names)
            cols = []
            for name, what in zip(names, whats):
                if name not in found:
                    raise _missing_column(name, what, found, label)
                cols.append(tab.column(name).to_numpy(zero_copy_only=False))
        else:
            raise ValueError(
                f"{path}: unknown table format {suffix!r}; use one of {', '.join(TABLE_SUFFIXES)}"
            )
    elif type(source).__module__.split(".")[0] == "pandas" and hasattr(source, "columns"):
        label = "DataFrame"
        cols = _frame_columns(source, names, whats, label)
    elif isinstance(source, Mapping):
        label = "table"
        cols = _mapping_columns(source, names, whats, label)
    else:
        raise TypeError(
            "source must be a .csv/.parquet path, a pandas DataFrame or a mapping of columns, "
            f"got {type(source).__name__}"
        )
    return cols, lines, label


def _selected_rows(
    cols: list, lines: list | None, names: tuple, where: dict, decimal: str, label: str
) -> tuple[list, list | None, np.ndarray]:
    """The rows whose ``where`` cells match (each distinct cell compared once), as ``(columns,
    lines, rowid)`` (``rowid``: each kept row's 0-based row in the whole table); every row
    without ``where``."""
    n = len(cols[0])
    if not where:
        return cols, lines, np.arange(n)
    by_name = dict(zip(names, cols))
    mark = decimal if lines is not None else "."  # (other sources hold numbers)
    keep = np.ones(n, dtype=bool)
    for name, value in where.items():  # each distinct cell compared once
        text, inverse = np.unique(_asset_text(by_name[name]).astype(str), return_inverse=True)
        hits = np.array([cells_equal(str(c), value, mark) for c in text], dtype=bool)
        keep &= hits[inverse.reshape(-1)]
    if not keep.any():
        sel = ", ".join(f"{k}={v}" for k, v in where.items())
        raise ValueError(f"{label}: no data rows matching {sel} (where)")
    rowid = np.flatnonzero(keep)
    cols = [c[rowid] if isinstance(c, np.ndarray) else [c[i] for i in rowid] for c in cols]
    lines = None if lines is None else [lines[i] for i in rowid]
    return cols, lines, rowid


def read_fleet_table(
    source,
    *,
    group_by: str = "asset",
    column: str = "value",
    time_column: str = "t",
    on_error: str = "raise",
    decimal: str = ".",
    time_format: str | None = None,
    where=None,
) -> FleetTable:
    """Read and validate a long table (module docstring) and group it by asset.

    Args:
        source: a ``.csv`` / ``.parquet`` path, a pandas DataFrame, or a mapping of column
            name to a 1-D array (all of one length).
        group_by, column, time_column: the asset, value and time column names.
        on_error: ``"raise"`` (default) or ``"flag"`` (set the asset aside with its message).
        decimal: a CSV's decimal mark, ``"."`` (default) or ``","`` (module docstring); Parquet,
            DataFrames and mappings hold numbers, so it does not apply to them.
        time_format: the layout of text date-times that are not ISO 8601, in
            ``datetime.strptime`` codes (e.g. ``"%d/%m/%Y %H:%M"``; a ``%z`` offset is applied,
            others are UTC); ``None``: numbers or ISO 8601.
        where: keep only the rows whose cells equal the given values, as
            :func:`~prognos_torch.workflow.load_series` does: ``{"channel": "5"}`` or
            ``["channel=5"]`` (``--where channel=5``; ``5`` matches ``5.0``, a missing cell
            only an empty value, ``channel=``). A where column may be the asset column (a
            selection of assets), not the time or value column. Row numbers in messages and
            in :attr:`FleetTable.rows` stay those of the whole table.
    Returns:
        :class:`FleetTable`.
    """
    if on_error not in ("raise", "flag"):
        raise ValueError(f"on_error must be 'raise' or 'flag', got {on_error!r}")
    if decimal not in (".", ","):
        raise ValueError(f"decimal must be '.' or ',', got {decimal!r}")
    names, whats, where = _roles(group_by, time_column, column, where)
    cols, lines, label = _source_columns(source, names, whats)
    for name, c in zip(names, cols):  # one cell per row: a single id or time is not spread
        if np.ndim(c) != 1:
            raise ValueError(
                f"{label}: column {name!r} must be 1-D (one cell per row), got shape {np.shape(c)}"
            )
    n = len(cols[0])
    for name, c in zip(names[1:], cols[1:]):
        if len(c) != n:
            raise ValueError(
                f"{label}: column {name!r} has {len(c)} rows, column {group_by!r} has {n}: "
                "the columns must be of one length"
            )
    if n == 0:
        raise ValueError(f"{label}: the table has no data rows")
    cols, lines, rowid = _selected_rows(cols, lines, names, where, decimal, label)
    n = rowid.size
    cols = cols[:3]

    def where(i, asset=None):
        line = f" (line {lines[int(i)]})" if lines is not None else ""
        a = f"asset {asset!r}, " if asset is not None else ""
        return f"{label}: {a}row {int(rowid[int(i)]) + 1}{line}"

    asset = _asset_text(cols[0])
    empty = np.flatnonzero(asset == "")
    if empty.size:
        raise ValueError(f"{where(empty[0])}: empty asset id in column {group_by!r}")
    index: dict[str, int] = {}  # assets in order of first appearance
    code = np.fromiter(
        (index.setdefault(a, len(index)) for a in asset.tolist()), dtype=np.int64, count=n
    )
    names_in_order = list(index)

    written, dotted = cols[2], np.empty(0, dtype=np.int64)
    written_t = cols[1]  # as written: messages show the time the user wrote, not days
    if decimal == "," and lines is not None:  # a CSV's commas made points (a point: refused)
        cols[1] = _comma_times(cols[1], lambda i: where(i, asset[i]))
        cols[2], dotted = _comma_values(cols[2])
    t, unit, epoch = _times(cols[1], lambda i: where(i, asset[i]), time_format)
    v, bad = _numbers(cols[2], "value")
    if dotted.size:
        v[dotted] = np.nan
        bad = np.union1d(bad, dotted)
    errors: dict[str, str] = {}

    def fail(i: int, text: str) -> None:
        a = names_in_order[code[i]]
        msg = f"{where(i, a)}: {text}"
        if on_error == "raise":
            raise ValueError(msg)
        errors.setdefault(a, msg)

    for i in bad.tolist():
        cell = str(written[i])  # as written in the table
        fail(i, f"value {cell!r} in column {column!r} is not a number{decimal_hint(cell, decimal)}")
    order = np.argsort(code, kind="stable")
    co, to = code[order], t[order]
    same = co[1:] == co[:-1]
    step = to[1:] - to[:-1]

    def shown(i: int, other: int | None = None) -> str:  # a time cell as the table holds it
        c = written_t[i]
        if isinstance(c, (str, np.str_)):
            return repr(str(c).strip())
        if isinstance(c, np.datetime64) or type(c).__name__ == "Timestamp":
            return str(c)
        if other is not None and fmt_time(float(t[i])) == fmt_time(float(t[other])):
            return repr(float(t[i]))  # all the digits where 10 do not tell the two apart
        return fmt_time(float(t[i]))

    for j in np.flatnonzero(same & (step <= 0)).tolist():
        i_prev, i = int(order[j]), int(order[j + 1])
        if step[j] == 0:
            fail(i, f"duplicate timestamp {shown(i)} (also at row {rowid[i_prev] + 1})")
        else:
            fail(
                i,
                f"time {shown(i, i_prev)} comes after {shown(i_prev, i)} "
                f"(row {rowid[i_prev] + 1}): times must increase within each asset; sort the "
                "table by asset and time",
            )
    bounds = np.flatnonzero(np.diff(co)) + 1
    segs = np.split(order, bounds)
    return FleetTable(
        assets=names_in_order,
        times=[t[s] for s in segs],
        values=[v[s] for s in segs],
        rows=[rowid[s].astype(np.int64) + 1 for s in segs],
        errors=errors,
        source=label,
        time_unit=unit,
        epoch=epoch,
        columns=(group_by, time_column, column),
    )


def as_fleet_table(source, *, where=None, **read) -> FleetTable:
    """``source`` itself when it is a :class:`FleetTable`, read already (``where`` is then
    refused: it would be ignored), else :func:`read_fleet_table` of it with ``where`` and the
    reading options ``read`` (``group_by``, ``column``, ...): the table ``fleet_rul`` and
    ``calibrate_fleet`` work on."""
    if not isinstance(source, FleetTable):
        return read_fleet_table(source, where=where, **read)
    if where is not None:
        raise ValueError(
            "where selects rows of a table read here; source is a FleetTable, read already "
            "(pass where to read_fleet_table)"
        )
    return source


# --------------------------------------------------------------------------- writing
def _csv_cell(v) -> str:
    if isinstance(v, (float, np.floating)):
        return "" if math.isnan(v) else repr(float(v))
    if isinstance(v, (int, np.integer)) and not isinstance(v, bool):
        return str(int(v))
    return str(v)


def write_table(path, columns: Mapping[str, Sequence]) -> Path:
    """Write columns (name -> equal-length sequence) to ``.csv`` or ``.parquet``, atomically.

    Floats are written in full precision (``repr``: they read back exactly); NaN is an empty
    CSV cell and a null in Parquet. Parquet needs the ``tables`` extra (pyarrow).
    """
    path = Path(path)
    suffix = path.suffix.lower()
    names = list(columns)
    n = {len(columns[c]) for c in names}
    if len(n) > 1:
        raise ValueError(f"columns must have one length, got {sorted(n)}")
    if suffix == ".csv":
        buf = io.StringIO()
        w = csv.writer(buf, lineterminator="\n")
        w.writerow(names)
        cols = [list(columns[c]) for c in names]
        for row in zip(*cols):
            w.writerow([_csv_cell(v) for v in row])
        atomic_write(path, buf.getvalue().encode("utf-8"))
    elif suffix in (".parquet", ".pq"):
        pa = _needs("pyarrow")
        pq = _needs("pyarrow.parquet")
        arrays = {}
        for c in names:
            col = list(columns[c])
            if col and all(isinstance(v, (float, np.floating)) for v in col):
                arr = np.asarray(col, dtype=np.float64)
                arrays[c] = pa.array(arr, mask=np.isnan(arr))  # NaN -> null
            elif col and all(isinstance(v, (str, np.str_)) for v in col):
                arrays[c] = pa.array([str(v) for v in col], type=pa.string())
            else:
                arrays[c] = pa.array(col)
        sink = io.BytesIO()
        pq.write_table(pa.table(arrays), sink)
        atomic_write(path, sink.getvalue())
    else:
        raise ValueError(
            f"{path}: unknown table format {suffix!r}; use one of {', '.join(TABLE_SUFFIXES)}"
        )
    return path
