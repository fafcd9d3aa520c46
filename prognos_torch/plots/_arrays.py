"""Plot inputs as float64 NumPy arrays, the axis of a series' clock (dates where it has
date-times), and the one way a figure reaches a file."""

from __future__ import annotations

import io
import os
from pathlib import Path

import matplotlib.dates as mdates
import numpy as np
import torch
from matplotlib.figure import Figure
from matplotlib.ticker import Formatter, Locator, MaxNLocator

from ..io import atomic_write, figure_format


def check_result(result, kind: str, attribute: str, name: str, or_none: str = "") -> None:
    """A ``TypeError`` for a result of the wrong kind (without ``attribute`` or ``history``),
    e.g. the arguments swapped; ``name`` is the plot function, whose path comes first."""
    if not hasattr(result, attribute) or not hasattr(result, "history"):
        raise TypeError(
            f"result must be a {kind}, got {type(result).__name__}; the call is "
            f"{name}(path, result): the PNG path {or_none}comes first"
        )


def time_label(series) -> str:
    """Axis label of a :class:`~prognos_torch.workflow.Series`' time."""
    if series.time_unit == "days":
        return f"days since {series.start}" if series.start else "days"
    if series.time_unit == "steps":
        return "step"
    return series.time_unit


#: matplotlib's date range (years 1-9999) as date numbers: beyond it the axis keeps day counts
_DATE_RANGE = tuple(float(mdates.date2num(np.datetime64(d))) for d in ("0001-01-02", "9999-12-30"))


def _dated(origin: float, lo: float, hi: float) -> bool:
    return _DATE_RANGE[0] <= origin + min(lo, hi) and origin + max(lo, hi) <= _DATE_RANGE[1]


class _DateTicks(Locator):
    """Ticks at round dates (matplotlib's ``AutoDateLocator``) on an axis that holds days since
    ``origin`` (a matplotlib date number): the data keep the series' own clock. A view beyond
    matplotlib's years 1-9999 (a horizon of millennia) gets round day counts instead."""

    def __init__(self, origin: float):
        self.origin = origin
        self.dates = mdates.AutoDateLocator()
        self.numbers = MaxNLocator()

    def __call__(self):
        lo, hi = self.axis.get_view_interval()
        return self.tick_values(lo, hi)

    def tick_values(self, vmin, vmax):
        if not _dated(self.origin, vmin, vmax):
            return self.numbers.tick_values(vmin, vmax)
        at = (mdates.num2date(v + self.origin) for v in (vmin, vmax))
        return np.asarray(self.dates.tick_values(*at)) - self.origin


class _DateLabels(Formatter):
    """Concise date labels (``ConciseDateFormatter``) of :class:`_DateTicks`' ticks; day counts
    since ``start`` where they leave matplotlib's date range."""

    def __init__(self, ticks: _DateTicks, start: str):
        self.origin = ticks.origin
        self.dates = mdates.ConciseDateFormatter(ticks.dates)
        self.days = f"days since {start}"
        self.offset = ""

    def __call__(self, x, pos=None):
        if not _dated(self.origin, x, x):
            return f"{x:g}"
        return self.dates(x + self.origin, pos)

    def format_ticks(self, values):
        v = np.asarray(values, dtype=np.float64)
        if v.size and not _dated(self.origin, float(v.min()), float(v.max())):
            self.offset = self.days
            return [f"{x:g}" for x in v]
        out = self.dates.format_ticks(v + self.origin)
        self.offset = self.dates.get_offset()
        return out

    def get_offset(self):
        return self.offset


def time_axis(ax, series) -> None:
    """Label ``ax``'s x axis with ``series``' clock. A series with date-times (``start`` set)
    keeps its days since ``start`` as data and gets ticks at round dates with concise date
    labels, the year and month beside the axis (label "date (UTC)"); other series get
    :func:`time_label`."""
    if series.time_unit == "days" and series.start:
        ax.set_xlabel("date (UTC)")
        ticks = _DateTicks(float(mdates.date2num(np.datetime64(series.start))))
        ax.xaxis.set_major_locator(ticks)
        ax.xaxis.set_major_formatter(_DateLabels(ticks, series.start))
    else:
        ax.set_xlabel(time_label(series))


def time_text(series, t: float) -> str:
    """Time ``t`` of ``series`` for a title: its date-time (to the second, UTC, as the reports
    give it) where the series has date-times, else ``"t = "`` and the number."""
    date = series.date(t)
    return f"{date} UTC" if date else f"t = {t:g}"


def as_numpy(x, name: str = "value") -> np.ndarray:
    """``x`` as a float64 array: a tensor on any device is detached and copied to the CPU
    (``np.asarray`` refuses a CUDA tensor), anything else goes through ``np.asarray``. ``None``
    (which NumPy reads as NaN), complex values (whose imaginary part the cast drops) and what
    is no array of numbers are a ``TypeError``/``ValueError`` naming ``name``."""
    if x is None:
        raise TypeError(f"{name} must be an array or tensor of real numbers, got None")
    if isinstance(x, torch.Tensor):
        if x.is_complex():
            raise TypeError(f"{name} must be real, got a complex tensor ({x.dtype})")
        x = x.detach().to("cpu", torch.float64).numpy()
    try:
        a = np.asarray(x)
        cplx = np.iscomplexobj(a)
        if not cplx:
            a = np.asarray(a, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise type(exc)(f"{name} must be an array of real numbers ({exc})") from None
    if cplx:
        raise TypeError(f"{name} must be real, got complex values ({a.dtype})")
    return a


def clip_for_drawing(paths: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """``paths`` limited to ``[lo - 10 pad, hi + 10 pad]`` (``pad = 0.15 (hi - lo)``, or 1 when
    ``hi == lo``) for drawing only: an exponential path can reach 1e300 or overflow to inf, and
    such coordinates ruin the axes' scale and make the Agg renderer allocate without bound. The
    result's data are not changed."""
    pad = 0.15 * (hi - lo) if hi > lo else 1.0
    return np.clip(paths, lo - 10.0 * pad, hi + 10.0 * pad)


def write_png(fig: Figure, path: str | os.PathLike | None, *, make_folder: bool = False,
              tight: bool = True, dpi: int = 100) -> Figure:  # fmt: skip
    """Lay ``fig`` out (``tight_layout`` unless ``tight=False``: a figure with its legend
    placed ``"outside"`` lays itself out) and write it as a PNG (``dpi``), or a PDF or SVG by
    the suffix of ``path`` (:func:`~prognos_torch.io.figure_format`), to ``path`` through
    :func:`~prognos_torch.io.atomic_write`: a reader sees the old file or the whole new one,
    never a half-written one. ``make_folder`` creates the missing folders of ``path`` (study
    outputs); otherwise a missing folder is a ``FileNotFoundError`` that names it. ``path=None``
    writes nothing. Returns ``fig``."""
    if tight:
        fig.tight_layout()
    if path is None:
        return fig
    data = figure_bytes(fig, path, dpi=dpi)  # rendered before any folder is made: a failed
    if make_folder:  # render leaves the file system as it was
        Path(path).parent.mkdir(parents=True, exist_ok=True)
    atomic_write(path, data)
    return fig


def figure_bytes(fig: Figure, path: str | os.PathLike, *, dpi: int = 100) -> bytes:
    """``fig`` rendered as the file ``path`` would hold it (PNG at ``dpi``, or PDF or SVG by its
    suffix, :func:`~prognos_torch.io.figure_format`), without writing anything: for a command
    that writes its files only once every one of them is made."""
    buf = io.BytesIO()
    fig.savefig(buf, format=figure_format(path), dpi=dpi)
    return buf.getvalue()
