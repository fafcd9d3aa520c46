"""A series given as arrays (tensor, NumPy, pandas, sequence): its values as float64 and its
time as numbers, date-times or durations, read by the rules of the CSV reader
(:mod:`~prognos_torch.workflow.data`)."""

from __future__ import annotations

import math
import numbers

import numpy as np
import torch
from torch import Tensor

from .._text import shown_lines
from .times import datetime_ns, days_since_first, formatted_stamps, is_datetime, is_duration

__all__ = ["array_values", "array_times", "check_real_numbers", "datetime_index", "pandas_name"]


def array_values(v, name: str) -> np.ndarray:
    """A 1-D array-like of numbers (tensor, NumPy array, pandas Series or Index, sequence) as
    a float64 NumPy array of its own (pandas' read-only arrays are copied, never written).
    A pandas object gives its values by position, not by index label; ``NA`` becomes NaN
    (missing). Raises ``TypeError`` naming ``name`` for anything else."""
    if isinstance(v, Tensor):
        _real_numbers(_kind_of(v), name)
        return v.detach().to("cpu", torch.float64).numpy().copy()
    if v is None or isinstance(v, (str, bytes, numbers.Number)):  # (NumPy: a 0-d array)
        raise TypeError(
            f"{name} must be a 1-D array of numbers (a tensor, a NumPy array, a pandas Series "
            f"or a sequence), got {type(v).__name__} {v!r:.40}"
        )
    if is_datetime(v) or is_duration(v):  # (pandas would give nanoseconds as numbers)
        raise TypeError(f"{name} must be numbers, got date-times or durations ({v.dtype})")
    dtype = getattr(v, "dtype", None)
    _real_numbers(getattr(dtype, "kind", None) if dtype is not None else _kind_of(v), name)
    try:
        to_numpy = getattr(v, "to_numpy", None)
        if to_numpy is not None:  # pandas
            return np.array(to_numpy(dtype=np.float64, na_value=np.nan))
        return np.array(v, dtype=np.float64)
    except (TypeError, ValueError):
        raise TypeError(
            f"{name} must be a 1-D array of numbers (a tensor, a NumPy array, a pandas Series "
            f"or a sequence), got {type(v).__name__}"
        ) from None


def check_real_numbers(v, name: str) -> None:
    """Refuse a tensor or sequence of booleans or complex values (``TypeError`` naming
    ``name``; :func:`_real_numbers`)."""
    _real_numbers(_kind_of(v), name)


def _kind_of(v) -> str | None:
    """NumPy's dtype kind of a tensor's or a sequence's elements (``"b"``, ``"c"``, ...;
    ``None``: not an array of one kind)."""
    if isinstance(v, Tensor):
        return "b" if v.dtype == torch.bool else "c" if v.dtype.is_complex else "f"
    try:
        return np.asarray(v).dtype.kind
    except (TypeError, ValueError):
        return None


def _real_numbers(kind: str | None, name: str) -> None:
    """Refuse booleans and complex values (a ``TypeError`` naming ``name``): read as numbers
    they would become 0/1, or lose their imaginary part, without a word."""
    if kind == "b":
        raise TypeError(
            f"{name} must be numbers, got booleans; convert them (e.g. .astype(float)) if the "
            "0/1 values are meant"
        )
    if kind == "c":
        raise TypeError(
            f"{name} must be real numbers, got complex values (reading them would drop the "
            "imaginary part); pass the real part or the magnitude"
        )


def datetime_index(v):
    """The ``DatetimeIndex`` or ``TimedeltaIndex`` of a pandas Series on one (the series' own
    time), else ``None``."""
    index = getattr(v, "index", None)
    return index if is_datetime(index) or is_duration(index) else None


def pandas_name(v) -> str | None:
    """The name of a pandas Series, when it is a non-empty string."""
    name = getattr(v, "name", None)
    return name if isinstance(name, str) and name else None


def _iso_texts(v, name: str, time_format: str | None = None) -> np.ndarray | None:
    """``datetime64[ns]`` (UTC) of a 1-D sequence of ISO 8601 texts (a list, an object or
    string array, a pandas Series of text: date-times read from a CSV without parsing), or of
    texts in ``time_format`` (``strptime`` codes, :func:`formatted_ns`), or ``None`` when ``v``
    holds something else, numbers written as text included (unless ``time_format`` says how
    to read them)."""
    if isinstance(v, Tensor):
        return None
    to_numpy = getattr(v, "to_numpy", None)
    try:
        arr = np.asarray(to_numpy() if to_numpy is not None else v, dtype=object)
    except (TypeError, ValueError):
        return None
    cells = arr.tolist() if arr.ndim == 1 else []
    # text, with missing cells (None, NaN, pandas' NA) among it: they become NaT
    texts = [c for c in cells if isinstance(c, str)]
    if not texts or any(not isinstance(c, str) and not _missing_cell(c) for c in cells):
        return None
    if time_format is not None:  # missing cells NaT, the texts in the caller's layout
        out = np.full(len(cells), np.datetime64("NaT"), dtype="datetime64[ns]")
        at = [i for i, c in enumerate(cells) if isinstance(c, str)]
        out[at] = formatted_stamps(texts, time_format, lambda j: f"{name}[{at[j]}] = {texts[j]!r}")
        return out
    try:
        float(texts[0])
        return None  # numbers as text: read as numbers
    except ValueError:
        pass
    out = np.empty(len(cells), dtype="datetime64[ns]")
    for i, c in enumerate(cells):
        try:
            out[i] = datetime_ns(c if isinstance(c, str) else "")
        except ValueError as exc:
            raise ValueError(
                f"{name}[{i}] = {c!r} is not an ISO 8601 date-time in 1678-2262 ({exc}), while "
                f"{texts[0]!r} is one"
            ) from None
    return out


def _missing_cell(c) -> bool:
    """``None``, a float NaN or pandas' ``NA``: a missing cell of a text column."""
    return c is None or type(c).__name__ == "NAType" or (isinstance(c, float) and math.isnan(c))


def array_times(
    v, name: str, time_format: str | None = None
) -> tuple[np.ndarray, str | None, str | None]:
    """Times as float64: numbers as given (unit ``None``: the caller's), or date-times (NumPy
    ``datetime64``, a pandas datetime Series or ``DatetimeIndex``, zone-aware ones in UTC;
    ISO 8601 texts, with their zone designators applied) as
    days since the first, with the unit ``"days"`` and the first as ISO 8601 text, as the CSV
    reader gives them; durations (NumPy ``timedelta64``, pandas timedelta) in days, with the
    unit ``"days"`` and no start (read as plain numbers they would be nanoseconds).
    ``time_format`` (``strptime`` codes) reads texts in another layout and applies to text
    only (``ValueError`` otherwise)."""
    if time_format is not None:
        ns = _iso_texts(v, name, time_format)
        if ns is None:
            raise ValueError(
                f"time_format applies to date-times written as text; {name} holds "
                f"{type(v).__name__} of numbers or date-times"
            )
    elif is_duration(v):
        ns = np.asarray(v).astype("timedelta64[ns]")
        if np.isnat(ns).any():
            where = shown_lines([int(i) for i in np.flatnonzero(np.isnat(ns))])
            raise ValueError(f"{name} has missing durations (NaT) at index {where}")
        return (ns / np.timedelta64(1, "D")).astype(np.float64), "days", None
    elif is_datetime(v):
        if getattr(v.dtype, "tz", None) is not None:  # pandas, zone-aware: to naive UTC
            acc = getattr(v, "dt", None)
            if acc is not None:  # a Series
                v = acc.tz_convert("UTC").dt.tz_localize(None)
            else:  # a DatetimeIndex
                v = v.tz_convert("UTC").tz_localize(None)
        ns = np.asarray(v).astype("datetime64[ns]")
    else:
        ns = _iso_texts(v, name)
        if ns is None:
            return array_values(v, name), None, None
    if np.isnat(ns).any():
        where = shown_lines([int(i) for i in np.flatnonzero(np.isnat(ns))])
        raise ValueError(f"{name} has missing date-times (NaT) at index {where}")
    return days_since_first(ns)
