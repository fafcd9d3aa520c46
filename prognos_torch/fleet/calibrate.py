"""Calibrate a fleet's 90 % RUL intervals on its assets that ran to failure.

A fleet is where failed histories are plentiful. :func:`calibrate_fleet` replays each failed
asset under the known-threshold protocol (:func:`~prognos_torch.prognosis.protocol.
known_threshold_protocol`, with the fleet's failure threshold): the asset's rows up to
20/40/60/80/90 % of [onset, end of life] become one pseudo-asset each, and ALL of them go
through one :func:`~prognos_torch.fleet.fleet_rul` call, the same RUL method and options as the
live fleet (batched as any fleet is). Their intervals ``[rul_q05, rul_q95]`` and the true RULs
give the split-conformal margin (:mod:`prognos_torch.prognosis.conformal`; CQR on the log RUL,
Romano, Patterson & Candes 2019), one per bin of the predicted median RUL where the failed
assets give enough points (``bins="auto"``: one bin per 100 points, at most 5; Mondrian
conformal prediction, so that short RULs, where a model's misses differ most, get their own),
and :meth:`FleetResult.calibrated
<prognos_torch.fleet.FleetResult.calibrated>` applies it to a fleet's result::

    cal, points = calibrate_fleet("failed.parquet", threshold=20.0)
    live = fleet_rul("fleet.parquet", threshold=20.0).calibrated(cal)
    live.columns["rul_q05_calibrated"], live.columns["rul_q95_calibrated"]

The RUL of a fleet row counts from the asset's last row (``t_last``, also where the values of
its last rows are missing: ``last_rows_missing``), so the true RUL of a replayed point is
``t_EoL - t_last`` (``t_last``: the time of the last row up to the prediction time). A
quantile that lies beyond every sampled crossing (NaN ``rul_q95`` with more than 5 % of the
mass censored) is an open upper end. The guarantee holds for live assets exchangeable with the
failed ones: the same population, indicator, threshold and method.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import torch

from ..core.validation import check_real
from ..prognosis.conformal import (
    RULCalibration,
    _check_bins,
    _check_coverage,
    calibrate_intervals,
    interval_scores,
)
from ..prognosis.protocol import PROTOCOL_FRACTIONS, check_fractions, known_threshold_protocol
from .run import fleet_rul, interval_columns, method_settings
from .table import FleetTable, as_fleet_table

__all__ = ["calibrate_fleet"]

#: ``fleet_rul``'s settings of how a fleet is run (the intervals do not depend on them): passed
#: on to the replay, left out of the calibration's settings
_RUN_OPTIONS = ("shard_size", "backend", "progress", "ray_init")


def _replay(table: FleetTable, fractions, sign: float, thr: float) -> tuple:
    """The protocol's prediction points of the failed assets as a table of truncated
    histories (asset ``a`` at fraction ``f`` named ``"a@f"``), ``(replay, truth, t_pred,
    t_last, skipped)``: the true RUL from each point's last row, the prediction times, those
    rows' times, and the assets that give no point with the reason."""
    names, times, values, rows, truth, t_pred, t_last = [], [], [], [], [], [], []
    skipped: dict[str, str] = dict(table.errors)  # set aside by the table checks
    for a, t, y, r in zip(table.assets, table.times, table.values, table.rows):
        if a in skipped:
            continue
        ok = ~np.isnan(y)
        if int(ok.sum()) < 20:
            skipped[a] = f"{int(ok.sum())} observed values, the protocol needs 20"
            continue
        pc = known_threshold_protocol(torch.from_numpy(t[ok]), torch.from_numpy(sign * y[ok]),
                                      fractions=fractions, threshold=sign * thr)  # fmt: skip
        if not pc.valid:
            skipped[a] = f"protocol not usable: {pc.reason}"
            continue
        for f, tp in zip(fractions, pc.times.tolist()):
            keep = t <= tp
            last = float(t[keep][-1])  # the replayed row's t_last, where its RUL counts from
            names.append(f"{a}@{f:g}")
            times.append(t[keep]), values.append(y[keep]), rows.append(r[keep])
            truth.append(pc.t_eol - last), t_pred.append(tp), t_last.append(last)
    if not names:
        first = next(iter(skipped.items()), ("", ""))
        raise ValueError(
            f"no failed asset gives a prediction point (first, {first[0]!r}: {first[1]}): "
            "nothing to calibrate on"
        )
    replay = FleetTable(names, times, values, rows, source=f"{table.source} (replayed)",
                        time_unit=table.time_unit, epoch=table.epoch)  # fmt: skip
    return replay, truth, t_pred, t_last, skipped


def calibrate_fleet(
    source,
    threshold: float,
    *,
    group_by: str = "asset",
    column: str = "value",
    time_column: str = "t",
    direction: str = "above",
    coverage: float = 0.9,
    bins: int | str = "auto",
    fractions: tuple[float, ...] = PROTOCOL_FRACTIONS,
    seed: int = 0,
    method: str = "exponential",
    decimal: str = ".",
    time_format: str | None = None,
    workers: int = 1,
    where=None,
    **options,
) -> tuple[RULCalibration, dict[str, list]]:
    """Conformal calibration of :func:`~prognos_torch.fleet.fleet_rul`'s 90 % intervals.

    Args:
        source: the failed assets: a :class:`~prognos_torch.fleet.FleetTable`, a
            ``.csv``/``.parquet`` path, a pandas DataFrame or a mapping of columns (as
            :func:`~prognos_torch.fleet.read_fleet_table`); each asset's rows must reach its
            failure.
        threshold: the failure threshold, as for the live fleet.
        group_by, column, time_column: column names (asset, value, time).
        direction: ``"above"`` or ``"below"``, as for the live fleet.
        coverage: the target coverage, in (0, 1).
        bins: bins of the predicted median RUL with a margin each; ``"auto"``: one per 100
            points with an interval, at most 5 (a rule fixed a priori: 100 points put each
            bin's 90 % margin at its 10th-largest miss).
        fractions: prediction times as fractions of [onset, end of life].
        seed, method, **options: ``fleet_rul``'s, to be used again for the live fleet.
        decimal, time_format: a CSV table's decimal mark and the layout of its date-times
            (:func:`~prognos_torch.fleet.read_fleet_table`).
        where: keep only the table's rows whose cells equal these values (``{"channel": "5"}``
            or ``["channel=5"]``; :func:`~prognos_torch.fleet.read_fleet_table`); refused with
            a :class:`~prognos_torch.fleet.FleetTable`, which was read already.
        workers: processes that replay the points (``fleet_rul``'s; not a setting of the
            calibration: the intervals are the same); so are ``fleet_rul``'s ``shard_size``,
            ``backend``, ``progress`` and ``ray_init`` among ``**options``. ``on_error``
            (``**options``; ``"raise"`` or ``"flag"``) applies to reading the table: a flagged
            asset is left out, its message in the points' ``status``.

    Returns:
        ``(calibration, points)``: the :class:`~prognos_torch.prognosis.RULCalibration` (its
        ``settings`` name the method, options, threshold and direction it holds for) and the
        replayed points as columns ``asset, t_pred, t_last, true_rul, rul_median, rul_q05,
        rul_q95, score, status`` (``score`` NaN and ``status`` the reason where a point has no interval).

    Raises:
        ValueError: bad arguments, or no failed asset gives a point with an interval.
    """
    # how the replay is run, not how its intervals are made: passed on, not recorded
    run = {key: options.pop(key) for key in _RUN_OPTIONS if key in options}
    on_error = options.pop("on_error", "raise")
    thr = check_real(threshold, "threshold")
    if direction not in ("above", "below"):
        raise ValueError(f"direction must be 'above' or 'below', got {direction!r}")
    # checked before the replay, as calibrate_rul does (a fraction beyond 1 replayed rows past
    # the end of life; coverage and bins were refused only after the whole replay)
    _check_coverage(coverage)
    if not (isinstance(bins, str) and bins == "auto"):
        bins = _check_bins(bins)
    fractions = check_fractions(fractions)
    sign = 1.0 if direction == "above" else -1.0
    table = as_fleet_table(
        source,
        where=where,
        group_by=group_by,
        column=column,
        time_column=time_column,
        decimal=decimal,
        time_format=time_format,
        on_error=on_error,
    )
    if not table.assets:
        raise ValueError("the table of failed assets is empty")
    replay, truth, t_pred, t_last, skipped = _replay(table, fractions, sign, thr)
    names = replay.assets
    res = fleet_rul(replay, thr, direction=direction, seed=seed, method=method, workers=workers,
                    **run, **options)  # fmt: skip
    lo, hi, med = interval_columns(res.columns)
    cm = res.columns["censored_mass"]
    true = torch.tensor(truth, dtype=torch.float64)
    usable = ~torch.isnan(lo) & ~torch.isnan(hi) & (true > 0)
    status = [
        "ok" if u else (f or f"no interval (censored mass {c:.3g})")
        for u, f, c in zip(usable.tolist(), res.columns["flags"], cm)
    ]
    if not bool(usable.any()):
        raise ValueError(
            f"no replayed point has an interval (first, {names[0]!r}: {status[0]}): nothing to "
            "calibrate on"
        )
    n = int(usable.sum())
    if bins == "auto":
        bins = max(1, min(5, n // 100))
    nan = torch.full_like(lo, math.nan)
    assets = [a.rsplit("@", 1)[0] for a, u in zip(names, usable.tolist()) if u]
    cal = calibrate_intervals(lo[usable], hi[usable], true[usable], coverage,
                              median=med[usable], bins=bins, groups=assets)  # fmt: skip
    settings = dict(
        method_settings(method, options), threshold=thr, direction=direction, fractions=list(fractions), seed=seed,
        fleet=True, time_unit=table.time_unit,
    )  # fmt: skip
    cal = replace(cal, settings=settings)
    scores = torch.full_like(lo, math.nan)
    scores[usable] = interval_scores(lo[usable], hi[usable], true[usable])
    points = {
        "asset": names,
        "t_pred": t_pred,
        "t_last": t_last,
        "true_rul": truth,
        "rul_median": torch.where(usable, med, nan).tolist(),
        "rul_q05": torch.where(usable, lo, nan).tolist(),
        "rul_q95": torch.where(usable, hi, nan).tolist(),
        "score": scores.tolist(),
        "status": status,
    }
    for a, why in skipped.items():
        for k in points:
            points[k].append(a if k == "asset" else why if k == "status" else math.nan)
    return cal, points
