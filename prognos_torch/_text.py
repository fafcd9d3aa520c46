"""Numbers in messages and records: times and levels printed with the digits that tell them
apart, and numbers for JSON.

Errors, flags and the command line print data values through these two functions. ``%g`` keeps
six significant digits, which merge Unix-second times (1700021180 and 1700017580 both print as
1.70002e+09) and levels with a large offset (a band [64496.22, 64496.34] prints as
[6.45e+04, 6.45e+04]). No torch import: the command line's ``--help`` stays fast.
"""

from __future__ import annotations

import math

__all__ = ["fmt_time", "fmt_level", "json_number", "shown_lines"]


def fmt_time(v: float) -> str:
    """A time on a series' clock with 10 significant digits (Unix seconds, day counts)."""
    return f"{v:.10g}"


def fmt_level(v: float, spread: float, digits: int = 4) -> str:
    """``v`` printed to ``digits`` significant digits of ``spread`` (a noise std, a band's
    width), so that values with a large offset stay apart. A zero, non-finite or NaN
    ``spread`` gives ``digits`` significant digits of ``v``."""
    if not (math.isfinite(v) and v != 0.0 and math.isfinite(spread) and spread > 0.0):
        return f"{v:.{digits}g}"
    extra = max(0, math.floor(math.log10(abs(v))) - math.floor(math.log10(spread)))
    return f"{v:.{min(digits + extra, 17)}g}"


def json_number(v) -> float | None:
    """``v`` as a float for a JSON record, ``None`` where it is missing or not finite (strict
    JSON has no NaN or infinity)."""
    return None if v is None or not math.isfinite(float(v)) else float(v)


def shown_lines(lines, limit: int = 5) -> str:
    """Line numbers (or indices) for a message: the first ``limit``, then how many more."""
    shown = ", ".join(str(v) for v in lines[:limit])
    return shown + (f" and {len(lines) - limit} more" if len(lines) > limit else "")
