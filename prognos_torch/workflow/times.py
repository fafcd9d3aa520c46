"""Date-times on a series' clock: ISO 8601 and ``strptime`` texts read as UTC nanoseconds, the
days since the first, and dates ``days`` after a start.

The workflow's readers (:mod:`~prognos_torch.workflow.data`, :mod:`~prognos_torch.workflow.arrays`,
the fleet tables) read date-times through these rules, so that a zone designator, a time
outside 1678-2262 (where nanoseconds wrap) and a ``%Z`` zone name without an offset are
refused the same way everywhere.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from datetime import datetime, timezone
from time import strptime as struct_strptime  # (its tm_zone: the %Z name read)

import numpy as np

__all__ = [
    "datetime_ns",
    "iso_start",
    "formatted_ns",
    "formatted_stamps",
    "days_since_first",
    "date_after",
    "check_time_format",
    "is_datetime",
    "is_duration",
]

_ZONE = re.compile(r"(Z|[+-]\d{2}(?::?\d{2})?)$")


#: datetime64[ns] covers 1678-2262; outside it NumPy wraps around silently
_NS_RANGE = (np.datetime64("1678-01-01", "us"), np.datetime64("2262-01-01", "us"))


def datetime_ns(text: str) -> np.datetime64:
    """An ISO 8601 date-time as ``datetime64[ns]`` in UTC: a zone designator (``Z``, ``+01:00``,
    ``-0500``) is applied explicitly; a date-time outside 1678-2262 (where nanoseconds wrap) or
    a text that is no date-time raises ``ValueError``; an empty cell, ``nan`` or ``NaT`` is
    ``NaT`` (missing)."""
    body = text.strip()
    if body.lower() in ("", "nan", "nat"):
        return np.datetime64("NaT", "ns")  # missing
    if body.lower() in ("now", "today"):  # (NumPy reads them as the clock's date-time)
        raise ValueError(f"{text!r} is not an ISO 8601 date-time")
    zone = _ZONE.search(body) if "T" in body or " " in body else None
    offset = np.timedelta64(0, "m")
    if zone is not None:
        z = zone.group(1)
        body = body[: zone.start()].rstrip()
        if z != "Z":
            hh, mm = z[1:3], z[3:].lstrip(":") or "0"
            if int(hh) > 23 or int(mm) > 59:  # (+99:99 shifted the time by 4 days)
                raise ValueError(f"{text!r} has the offset {z!r}; hours 00-23, minutes 00-59")
            offset = (np.timedelta64(int(hh), "h") + np.timedelta64(int(mm), "m")) * (
                1 if z[0] == "+" else -1
            )
    if body.replace(".", "", 1).lstrip("+-").isdigit():
        raise ValueError(f"{text!r} is a number, not an ISO 8601 date-time")
    stamp = np.datetime64(body)  # ValueError if it is no date-time; NaT for "NaT"
    if not np.isnat(stamp):
        us = stamp.astype("datetime64[us]")
        if not (_NS_RANGE[0] <= us < _NS_RANGE[1]):
            raise ValueError(f"{text!r} lies outside 1678-2262, the range of nanosecond times")
    return stamp.astype("datetime64[ns]") - offset


def iso_start(stamp: np.datetime64) -> str:
    """A ``datetime64[ns]`` as ISO 8601 text: to the second, or finer where it carries a
    fraction of a second (never truncated)."""
    seconds = stamp.astype("datetime64[s]")
    return str(seconds) if seconds == stamp else str(np.datetime_as_string(stamp, unit="auto"))


def formatted_ns(text: str, fmt: str) -> np.datetime64:
    """A date-time written in ``fmt`` (``datetime.strptime`` codes) as ``datetime64[ns]`` in
    UTC: a ``%z`` offset is applied, a time without one is taken as UTC, as ISO 8601 text is.
    A ``%Z`` zone name other than UTC or GMT is refused: ``strptime`` matches the machine's
    own zone names (EST, CET) but gives no offset for them (10:00 EST was read as 10:00 UTC)."""
    stamp = datetime.strptime(text.strip(), fmt)
    if "%Z" in fmt and stamp.tzinfo is None:
        zone = struct_strptime(text.strip(), fmt).tm_zone
        if zone is not None and zone.upper() not in ("UTC", "GMT"):
            raise ValueError(
                f"the zone name {zone!r} (%Z) gives no offset; write the offset with %z "
                "(e.g. -0500), or UTC times"
            )
    if stamp.tzinfo is not None:
        stamp = stamp.astimezone(timezone.utc).replace(tzinfo=None)
    out = np.datetime64(stamp, "us")
    if not (_NS_RANGE[0] <= out < _NS_RANGE[1]):
        raise ValueError(f"{text!r} lies outside 1678-2262, the range of nanosecond times")
    return out.astype("datetime64[ns]")


def formatted_stamps(cells: Sequence[str], fmt: str, label) -> np.ndarray:
    """``datetime64[ns]`` of the texts ``cells`` written in ``fmt`` (:func:`formatted_ns`); a
    cell that does not match raises ``ValueError`` ``"{label(i)} does not match time_format
    ..."`` (``label(i)``: where the cell stands and what it holds, in the caller's words)."""
    out = np.empty(len(cells), dtype="datetime64[ns]")
    for i, c in enumerate(cells):
        try:
            out[i] = formatted_ns(c, fmt)
        except ValueError as exc:
            raise ValueError(f"{label(i)} does not match time_format {fmt!r} ({exc})") from None
    return out


def days_since_first(stamps: np.ndarray) -> tuple[np.ndarray, str, str]:
    """``datetime64[ns]`` stamps as the reader's time axis: float64 days since the first, the
    unit ``"days"`` and the first as ISO 8601 text (the series' ``start``)."""
    days = (stamps - stamps[0]) / np.timedelta64(1, "D")
    return days.astype(np.float64), "days", iso_start(stamps[0])


_UNIT_NS = {"s": 10**9, "ms": 10**6, "us": 10**3}


#: microseconds that NumPy's ``datetime64[us]`` holds either side of 1970 (about 292,000 years)
_US_RANGE = 2**63 - 1


def date_after(start: str, days: float, unit: str = "us") -> str | None:
    """The ISO 8601 date-time ``days`` (finite) after ``start`` (ISO 8601, UTC), rounded to
    ``unit`` (``"s"``, ``"ms"`` or ``"us"``): seconds where the fraction is zero. Computed in
    whole nanoseconds and held in microseconds, so that a RUL far beyond 2262 (the end of
    nanosecond date-times) still has its date; ``None`` beyond the years +-292,000."""
    if unit not in _UNIT_NS:
        raise ValueError(f"unit must be 's', 'ms' or 'us', got {unit!r}")
    q = _UNIT_NS[unit]
    ns = int(datetime_ns(start).astype(np.int64)) + round(float(days) * 86400e9)
    us = (ns + q // 2) // q * q // 1000  # (q is a whole number of microseconds)
    if abs(us) >= _US_RANGE:
        return None
    return iso_start(np.datetime64(us, "us"))


def check_time_format(time_format) -> None:
    """``None`` or text with ``datetime.strptime`` codes (a ``%``), else a ``ValueError``."""
    if time_format is not None and (not isinstance(time_format, str) or "%" not in time_format):
        raise ValueError(
            f"time_format must be strptime codes such as '%d/%m/%Y %H:%M', got {time_format!r}"
        )


def is_datetime(v) -> bool:
    """``v`` holds date-times: NumPy ``datetime64`` or a pandas datetime Series or Index
    (with or without a time zone)."""
    return getattr(getattr(v, "dtype", None), "kind", None) == "M"


def is_duration(v) -> bool:
    """``v`` holds durations: NumPy ``timedelta64`` or a pandas timedelta Series or Index."""
    return getattr(getattr(v, "dtype", None), "kind", None) == "m"
