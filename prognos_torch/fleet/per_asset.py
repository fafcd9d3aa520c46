"""The fleet through :func:`prognos_torch.workflow.prognose`, one asset at a time.

``fleet_rul(..., method="prognose")`` runs the single-series entry point of the RUL workflow
on every asset of a shard: its onset rule, its trend models (exponential, power law, linear and
the online ELM; ``method="auto"`` pools the exponential and ELM trends), its guard rails and its honest
horizon. ``prognose`` fits one series at a time (its engine run is batched over trend shapes
and noise grid points, not over assets), so this method loops over the shard's assets; shards
still run in parallel on the Ray backend. The default fleet method,
:func:`~prognos_torch.fleet.trend.exponential_trend_rul`, batches the exponential model over
the assets of a shard instead.

Per asset: the seed is the asset's seed (:func:`~prognos_torch.fleet.batch.asset_seed`), so
the table does not depend on sharding; a last observed value at or beyond the threshold, or
a median of the last 5 values there (``prognose``'s own rule, under which it refuses the
series), is ``threshold_reached`` with RUL 0, as in the exponential method, unless the healthy
baseline's mean already lies there (``threshold_on_healthy_side``, no RUL: a falling indicator
with ``direction="above"``, say); an input that ``prognose`` rejects (too few values, a
threshold inside the healthy band, ...) is reported in the asset's row (flag
``prognose_error`` and the message), never fatal for the fleet; a bad option of ``prognose``
(``n_paths=3``, an unknown ``filter``) is the call's error, raised before any asset.
``p_fail_within_horizon`` is :meth:`~prognos_torch.workflow.RULResult.failure_probability`; a
``horizon`` beyond ``prognose``'s own while paths are censored leaves it NaN (flag
``horizon_beyond_prognosis``). ``prognose``'s own flags are sentences; they are summarised as
``prognose_flags`` in ``flags`` and given in full in ``message``.
"""

from __future__ import annotations

import math

import numpy as np

from ..core.validation import check_real
from ..prognosis.onset import moving_median
from .batch import PaddedBatch, check_min_rows
from .trend import RUL_COLUMNS

__all__ = ["prognose_rul"]

#: the failure directions ``prognose`` takes (``"auto"``: it finds the direction itself)
DIRECTIONS = ("above", "below", "auto")


def prognose_rul(
    batch: PaddedBatch,
    threshold: float,
    *,
    direction: str = "above",
    horizon: float | None = None,
    min_rows: int = 10,
    **options,
) -> dict[str, object]:
    """Per-asset :func:`~prognos_torch.workflow.prognose` on a shard (module docstring).

    Args:
        batch: the shard.
        threshold, direction: as for ``prognose`` (``direction`` ``"above"``/``"below"``/
            ``"auto"``).
        horizon: time span for ``p_fail_within_horizon`` (``None``: ever, i.e. within the
            prognosis horizon; the rest is the censored mass).
        min_rows: fewer observed rows: flagged ``too_few_rows``, ``prognose`` is not called
            (an int >= 1).
        **options: passed to ``prognose`` (``method``, ``n_paths``, ``filter``, ...).
    Returns:
        The columns of :data:`~prognos_torch.fleet.trend.RUL_COLUMNS`, ``flags`` and
        ``message`` (one entry per asset).
    """
    import torch

    from ..workflow import prognose
    from ..workflow.prognosing import check_prognose_options

    if direction not in DIRECTIONS:  # an argument, not an asset's input
        raise ValueError(f"direction must be 'above', 'below' or 'auto', got {direction!r}")
    min_rows = check_min_rows(min_rows)
    # arguments, not an asset's input (a NaN threshold was every asset's prognose_error)
    threshold = check_real(threshold, "threshold")
    if horizon is not None and not check_real(horizon, "horizon") > 0:
        raise ValueError(f"horizon must be a positive finite number or None, got {horizon!r}")
    # prognose's settings once: a bad one (n_paths=3) flagged every asset prognose_error
    check_prognose_options(direction=direction, **options)
    B = len(batch)
    out = {c: np.full(B, np.nan) for c in RUL_COLUMNS}
    flags, messages = [], []
    for b in range(B):
        n = int(batch.lengths[b])
        y, t = batch.values[b, :n], batch.times[b, :n]
        out["n_rows"][b] = n
        out["t_last"][b] = float(t[-1]) if n else math.nan
        if int((~torch.isnan(y)).sum()) < min_rows:
            flags.append("too_few_rows")
            messages.append("")
            continue
        seen = y[~torch.isnan(y)]
        sign = {"above": 1.0, "below": -1.0}.get(direction)
        reached = False
        if sign is not None:  # oriented: degradation raises sign * value
            # the last value, or prognose's own rule, the median of the last 5 values (prognose
            # refuses such a series: it was a prognose_error)
            now = max(sign * float(seen[-1]), sign * float(moving_median(seen, 5)[-1]))
            reached = now >= sign * float(threshold)
        if reached:
            # a healthy level at or beyond the threshold is the wrong direction (or threshold),
            # not a failure: every healthy asset would read RUL 0 (as the exponential method)
            if _healthy_side(seen, t[~torch.isnan(y)], threshold, sign, options):
                flags.append("threshold_on_healthy_side")
                messages.append("")
                continue
            # as the exponential method: failed, RUL 0 (prognose refuses such a series)
            for col, v in (("rul_median", 0.0), ("rul_q05", 0.0), ("rul_q95", 0.0),
                           ("p_fail_within_horizon", 1.0), ("censored_mass", 0.0)):  # fmt: skip
                out[col][b] = v
            flags.append("threshold_reached")
            messages.append("")
            continue
        try:
            # the RUL counts from the asset's last row (t_last), also when its last values are
            # missing: prognose evaluates there, conditioned on the asset still running
            r = prognose(y, threshold, time=t, seed=batch.seeds[b], direction=direction,
                         at=float(t[-1]), **options)  # fmt: skip
        except ValueError as exc:
            flags.append("prognose_error")
            messages.append(" ".join(str(exc).split()))
            continue
        s = r.summary()
        f = []
        if r.status != "ok":
            f.append("no_onset")
        else:
            for key, col in (("median", "rul_median"), ("q05", "rul_q05"), ("q95", "rul_q95")):
                out[col][b] = math.nan if s[key] is None else s[key]
            out["censored_mass"][b] = r.censored_mass
            if horizon is None:
                out["p_fail_within_horizon"][b] = 1.0 - r.censored_mass
            elif float(horizon) <= r.bound or r.censored_mass == 0:
                out["p_fail_within_horizon"][b] = r.failure_probability(horizon)
            else:  # beyond prognose's horizon with paths censored: only a lower bound is known
                f.append("horizon_beyond_prognosis")
        if r.onset is not None and getattr(r.onset, "detected", False):
            out["onset_time"][b] = r.onset.time
        if r.flags:
            f.append("prognose_flags")
        flags.append(";".join(f))
        messages.append(" | ".join(r.flags))
    res: dict[str, object] = dict(out)
    res["flags"] = flags
    res["message"] = messages
    return res


def _healthy_side(seen, t_seen, threshold: float, sign: float, options) -> bool:
    """Whether the mean of the healthy window (``prognose``'s ``baseline`` option: its fraction
    or a given ``Baseline``) lies at or beyond the threshold in the failure direction; ``False``
    where the window gives no baseline (``prognose`` is then not asked either)."""
    from ..prognosis.onset import Baseline, healthy_baseline

    base = options.get("baseline", 0.3)
    if not isinstance(base, Baseline):
        try:
            base = healthy_baseline(
                seen, t_seen, fraction=base, glitch_limit=options.get("glitch_limit")
            )
        except ValueError:
            return False
    return sign * (float(threshold) - base.mean) <= 0
