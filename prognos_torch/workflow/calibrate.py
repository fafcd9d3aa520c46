"""Calibrate :func:`~prognos_torch.workflow.prognose`'s 90 % intervals on assets that ran to failure.

::

    from prognos_torch.workflow import calibrate_rul, prognose

    cal, points = calibrate_rul({"b1": s1, "b2": s2, "b3": s3})   # failed assets, same type
    r = prognose(s_new, threshold=thr)
    print(cal.summary(r)["calibrated"])                          # {"q05", "q95", "margin", ...}

Each history is replayed under the known-threshold protocol
(:func:`~prognos_torch.prognosis.protocol.known_threshold_protocol`; or a known ``threshold``):
``prognose`` predicts at 20/40/60/80/90 % of [onset, end of life] from the data up to each time,
and the intervals and true RULs of all points give the split-conformal margin
(:mod:`prognos_torch.prognosis.conformal`; CQR on the log RUL, Romano et al. 2019). The
guarantee holds for a new asset exchangeable with the histories: the same kind of asset, the
same indicator and the same ``prognose`` settings (pass them as keyword arguments here and use
them for the new asset). A history's points move together, so the guarantee for a new asset is
firm from :func:`~prognos_torch.prognosis.conformal.points_needed` histories on (9 for 90 %;
with three IMS bearings, the fourth's intervals covered 0.73, ``docs/RESULTS.md``); the command
line warns below that.
"""

from __future__ import annotations

import inspect
import math
from collections.abc import Mapping, Sequence
from dataclasses import replace

import torch

from .._workers import check_workers, process_map
from ..core.validation import is_real, plain_number
from ..prognosis.conformal import (
    RULCalibration,
    _check_bins,
    _check_coverage,
    calibrate_intervals,
    interval_scores,
    record_settings,
)
from ..prognosis.protocol import (
    PROTOCOL_FRACTIONS,
    PROTOCOL_MIN_POINTS,
    check_fractions,
    known_threshold_protocol,
)
from .data import Series
from .prognosing import _as_series, _check_seeds, prognose

__all__ = ["calibrate_rul"]


def calibrate_rul(
    histories,
    *,
    threshold: float | None = None,
    direction: str = "above",
    coverage: float = 0.9,
    bins: int = 1,
    fractions: tuple[float, ...] = PROTOCOL_FRACTIONS,
    seed: int | Sequence[int] = 0,
    workers: int = 1,
    **prognose_kwargs,
) -> tuple[RULCalibration, list[dict]]:
    """Conformal calibration of ``prognose``'s 90 % interval on run-to-failure histories.

    Args:
        histories: run-to-failure series of assets like the one to be predicted: a mapping
            ``{name: series}`` or a sequence, each a :class:`~prognos_torch.workflow.Series`
            or a pair ``(t, y)`` of ``(T,)`` times and values (NaN: missing, dropped). Each
            must end at or after its failure.
        threshold: the known failure level; ``None``: each history's own ``0.9 x`` its highest
            5-point moving median (the bearing studies' protocol, for a rising indicator).
        direction: ``"above"`` (degradation raises the indicator) or ``"below"`` (it lowers
            it, as a capacity fades; needs ``threshold``): the side the failure lies on, for
            the protocol (run on ``-y`` and ``-threshold`` when below) and for ``prognose``.
        coverage: the target coverage of the calibrated interval, in (0, 1).
        bins: bins of the predicted median RUL, each with its own margin
            (:mod:`prognos_torch.prognosis.conformal`); for many histories only: every bin
            needs ``ceil(c / (1 - c))`` points for a finite margin, and about 100 for a stable
            one.
        fractions: prediction times as fractions of [onset, end of life].
        seed: passed to every ``prognose`` call: one seed, or several pooled (as
            ``prognose`` takes them).
        workers: processes that run the ``prognose`` calls side by side (``1``: in this
            process). Each is a fresh interpreter (``spawn``) with one torch thread, handed
            prediction points longest series first; the result equals ``workers=1``'s. As for
            any process pool, a script that calls this at its top level needs the
            ``if __name__ == "__main__":`` guard (without it the workers die at start and a
            ``RuntimeError`` says so).
        **prognose_kwargs: further ``prognose`` settings (``method``, ``filter``, ...); use the
            same for the asset the calibration will serve.

    Returns:
        ``(calibration, points)``: the :class:`~prognos_torch.prognosis.conformal.RULCalibration`
        and one dict per prediction point (``name, t, true_rul, q05, q95, status, score``;
        points before onset or refused by ``prognose`` are listed with their status or error
        and left out of the calibration).

    Raises:
        ValueError: ``histories`` empty or malformed, or no history gives a usable point.
        TypeError: a keyword argument that is no ``prognose`` setting (checked before any
            replay).
        RuntimeError: ``workers > 1`` and a worker process ended abruptly (no ``__main__``
            guard in the calling script, or a worker killed).
    """
    items = _items(histories)
    if {"at", "time", "time_format"} & set(prognose_kwargs):
        raise ValueError(
            "calibrate_rul sets at= and time= itself: do not pass them (nor time_format: "
            "give the histories' times as numbers or date-times)"
        )
    # checked before the replays: a misspelt setting failed in the first prognose call
    unknown = sorted(k for k in prognose_kwargs if k not in _PROGNOSE_SETTINGS)
    if unknown:
        raise TypeError(
            f"calibrate_rul got unexpected keyword argument(s) {', '.join(map(repr, unknown))}; "
            f"prognose settings it passes on: {', '.join(_PROGNOSE_SETTINGS)}"
        )
    if direction not in ("above", "below"):
        raise ValueError(
            f"direction must be 'above' or 'below' (the side of failure, known for histories "
            f"that ran to it), got {direction!r}"
        )
    sign = 1.0 if direction == "above" else -1.0
    if direction == "below" and threshold is None:
        raise ValueError(
            "direction='below' needs the known threshold: the protocol's 0.9 x highest moving "
            "median is defined for a rising indicator only"
        )
    if threshold is not None and not is_real(threshold):
        raise TypeError(f"threshold must be a real number or None, got {threshold!r}")
    if threshold is not None and not math.isfinite(threshold):  # (was blamed on a history)
        raise ValueError(f"threshold must be finite or None, got {threshold!r}")
    check_workers(workers)
    # checked before the replays (minutes to hours on a real archive), not after them
    _check_coverage(coverage)
    bins = _check_bins(bins)
    fractions = check_fractions(fractions)
    seeds = _check_seeds(seed)  # (as prognose reads it: one seed, or several pooled)
    seed = seeds[0] if len(seeds) == 1 else seeds
    signed = None if threshold is None else sign * threshold
    points, pending, tasks = [], [], []
    for name, (t, y) in items:
        if t.shape == y.shape and t.dim() == 1 and t.shape[0] < PROTOCOL_MIN_POINTS:
            # too short for the protocol: set aside, as a history that never fails is
            points.append({"name": name, "status": f"{t.shape[0]} values, the protocol needs "
                           f"{PROTOCOL_MIN_POINTS}"})  # fmt: skip
            continue
        try:
            pc = known_threshold_protocol(t, sign * y, fractions=fractions, threshold=signed)
        except ValueError as exc:
            raise ValueError(f"histories[{name!r}]: {exc}") from None
        if not pc.valid:
            reason = pc.reason
            if sign < 0:  # the protocol ran on -y: say it in the data's own sign
                reason = reason.replace(f"threshold {signed:g}", f"threshold {threshold:g}")
            points.append({"name": name, "status": f"protocol not usable: {reason}"})
            continue
        for tp, true in zip(pc.times.tolist(), pc.true_rul.tolist()):
            sel = t <= tp
            pending.append({"name": name, "t": tp, "true_rul": true, "q05": math.nan,
                            "q95": math.nan})  # fmt: skip
            points.append(pending[-1])
            tasks.append((y[sel], t[sel], tp, sign * pc.threshold, true, seed, direction,
                          prognose_kwargs))  # fmt: skip
    sizes = [len(a[0]) for a in tasks]
    for row, out in zip(pending, process_map(_predict, tasks, workers, sizes, "calibrate_rul")):
        row.update(out)
    usable = [p for p in points if not math.isnan(p.get("q05", math.nan))]
    if not usable:
        first = next((f"{p['name']!r}: {p['status']}" for p in points if p["status"] != "ok"), "")
        raise ValueError(
            "histories gave no prediction point with an interval (no onset before failure, "
            f"or every prediction refused; first: {first}): nothing to calibrate on"
        )
    col = lambda k: torch.tensor([p[k] for p in usable], dtype=torch.float64)  # noqa: E731
    scores = interval_scores(col("q05"), col("q95"), col("true_rul"))
    for p, e in zip(usable, scores.tolist()):
        p["score"] = e
    settings = _settings(prognose_kwargs, threshold, direction, fractions, seed)
    cal = calibrate_intervals(col("q05"), col("q95"), col("true_rul"), coverage,
                              median=col("median"), bins=bins,
                              groups=[p["name"] for p in usable])  # fmt: skip
    cal = replace(cal, settings=settings)
    return cal, points


#: the keyword arguments of ``prognose`` that ``**prognose_kwargs`` may set (``time``, ``at``,
#: ``time_format``, ``seed`` and ``direction`` are calibrate_rul's own)
_PROGNOSE_SETTINGS = tuple(
    k for k, p in inspect.signature(prognose).parameters.items()
    if p.kind is p.KEYWORD_ONLY and k not in ("time", "at", "time_format", "seed", "direction")
)  # fmt: skip


def _predict(y, t, at, threshold, true, seed, direction, kwargs) -> dict:
    """One prediction point: ``prognose`` at time ``at`` from the data ``(t, y)`` up to it; its
    interval (and median) when it gives one and the true RUL is positive."""
    try:
        r = prognose(y, threshold, time=t, at=at, seed=seed, direction=direction, **kwargs)
    except ValueError as exc:
        return {"status": f"error: {exc}"}
    s = r.summary()
    if s["status"] != "ok" or true <= 0:
        return {"status": s["status"]}
    return {"q05": s["q05"] if s["q05"] is not None else s["bound"],
            "q95": math.inf if s["q95"] is None else s["q95"],
            "median": math.inf if s["median"] is None else s["median"], "status": "ok"}  # fmt: skip


def _settings(kwargs: dict, threshold, direction: str, fractions, seed) -> dict:
    """``prognose``'s settings (its defaults, then ``kwargs``; a value JSON cannot hold as its
    repr), the failure ``threshold`` (``"protocol"``: each history's own) and ``direction``."""
    out = {k: p.default for k, p in inspect.signature(prognose).parameters.items()
           if p.kind is p.KEYWORD_ONLY and k not in ("time", "at", "seed", "direction")}  # fmt: skip
    # a NumPy number as the number it is (its repr, "np.int64(500)", made summary() refuse
    # every result: n_paths 500 differed from it)
    out = record_settings({**out, **{k: plain_number(v) for k, v in kwargs.items()}})
    out.update(threshold="protocol" if threshold is None else float(threshold),
               direction=direction, fractions=list(fractions),
               seed=list(seed) if isinstance(seed, tuple) else seed)  # fmt: skip
    return out


def _items(histories) -> list[tuple[str, tuple[torch.Tensor, torch.Tensor]]]:
    if isinstance(histories, Mapping):
        pairs = list(histories.items())
    elif isinstance(histories, (list, tuple)):
        pairs = [(str(i), h) for i, h in enumerate(histories)]
    else:
        raise TypeError(
            f"histories must be a mapping or a sequence of Series or (t, y) pairs, got "
            f"{type(histories).__name__}"
        )
    if not pairs:
        raise ValueError("histories is empty: give at least one run-to-failure series")
    names = [str(name) for name, _ in pairs]
    if len(set(names)) < len(names):  # ({1: a, "1": b}: one asset's points, counted once)
        twice = next(n for n in names if names.count(n) > 1)
        raise ValueError(
            f"histories names {twice!r} twice (keys are compared as text): give each history "
            "its own name"
        )
    out = []
    for name, h in pairs:
        if not (isinstance(h, Series) or (isinstance(h, (tuple, list)) and len(h) == 2)):
            raise TypeError(f"histories[{name!r}] must be a Series or a pair (t, y), got {h!r:.80}")
        try:  # (the message names the history)
            y, t, _ = _as_series(h, None) if isinstance(h, Series) else _as_series(h[1], h[0])
        except (TypeError, ValueError) as exc:
            raise type(exc)(f"histories[{name!r}]: {exc}") from None
        keep = ~torch.isnan(y)
        out.append((str(name), (t[keep], y[keep])))
    return out
