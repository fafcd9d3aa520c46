"""Fleet RUL: a long table in, one row per asset out; shards of assets, local or on Ray.

The assets of a validated table (:func:`~prognos_torch.fleet.table.read_fleet_table`) are cut
into shards of ``shard_size`` assets in table order; each shard is padded with NaN
(:func:`~prognos_torch.fleet.batch.pad_batch`) and goes through ONE call of the RUL method,
which vectorises over the shard's assets. Every asset's randomness comes from its own seed,
derived from ``(seed, asset id)``, so the table does not depend on the shard size or on the
backend:

* ``backend="local"``: the shards one after the other in this process (progress bar over
  shards with ``progress=True``), or side by side in ``workers`` spawned processes;
* ``backend="ray"``: one Ray task per shard (``pip install "prognos_torch[ray]"``). An already
  initialised Ray (a cluster, or ``ray.init(...)`` by the caller) is used as is; otherwise a
  local Ray is started with ``ray_init`` options and shut down at the end. The tasks return
  plain arrays; the table is assembled here in asset order.

A RUL method is a function ``method(batch: PaddedBatch, threshold, **options) -> dict`` that
returns ``(B,)`` arrays for :data:`~prognos_torch.fleet.trend.RUL_COLUMNS`, a list of flag
strings and optionally a list of messages: :func:`~prognos_torch.fleet.trend.
exponential_trend_rul` (``"exponential"``, the default: batched over the shard's assets) or
:func:`~prognos_torch.fleet.per_asset.prognose_rul` (``"prognose"``: the workflow's
``prognose`` per asset, its trend models chosen by backtest). Assets set
aside by the table checks (``on_error="flag"``) get a row with NaN results, the flag
``bad_input`` and their message.
"""

from __future__ import annotations

import inspect
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import torch

from .._workers import check_workers, process_map
from ..core.validation import check_real, check_seed, is_int
from ..prognosis.conformal import record_settings
from ..workflow.times import date_after
from .batch import DIRECTIONS as trend_directions
from .batch import check_min_rows, pad_batch
from .per_asset import DIRECTIONS as prognose_directions
from .per_asset import prognose_rul
from .table import FleetTable, _id_text, as_fleet_table, write_table
from .trend import RUL_COLUMNS, exponential_trend_rul

__all__ = ["FleetResult", "fleet_rul", "METHODS", "OUTPUT_COLUMNS", "DATE_COLUMNS", "run_shard"]

#: RUL methods by name: the batched exponential trend (default) and the per-asset prognose
METHODS: dict[str, Callable] = {"exponential": exponential_trend_rul, "prognose": prognose_rul}

#: the failure directions each built-in method takes
_DIRECTIONS = {"exponential": trend_directions, "prognose": prognose_directions}

#: the output table's columns, in order
OUTPUT_COLUMNS = ("asset",) + RUL_COLUMNS + ("flags", "message")

#: columns added after :data:`OUTPUT_COLUMNS` where the method gives them: ``phi``, the offset
#: of each asset's exponential trend (``phi="baseline"`` or ``"auto"``: the healthy mean, or 0
#: where ``"auto"`` chose ``phi = 0``)
EXTRA_COLUMNS = ("phi",)

#: columns added after :data:`OUTPUT_COLUMNS` where the time column holds date-times: ISO 8601
#: text in UTC, to the second (``""`` where the number is NaN): the last row's and the onset's
#: date-times, and ``t_last`` plus the RUL quantiles (``failure_date_q95`` empty where that
#: quantile lies beyond every crossing)
DATE_COLUMNS = (
    "t_last_date",
    "onset_date",
    "failure_date_q05",
    "failure_date_median",
    "failure_date_q95",
)


def _dates(epoch: str, days) -> list[str]:
    """Days since ``epoch`` as ISO 8601 date-times to the second; ``""`` for NaN (and beyond
    the years +-292,000)."""
    return ["" if not math.isfinite(d) else date_after(epoch, d, "s") or "" for d in days]


def date_columns(columns: Mapping[str, list], epoch: str) -> dict[str, list[str]]:
    """:data:`DATE_COLUMNS` of a result's columns on a date-time axis (days since ``epoch``)."""
    t_last = np.asarray(columns["t_last"], dtype=float)
    out = {
        "t_last_date": _dates(epoch, t_last),
        "onset_date": _dates(epoch, np.asarray(columns["onset_time"], dtype=float)),
    }
    for q in ("q05", "median", "q95"):
        out[f"failure_date_{q}"] = _dates(epoch, t_last + np.asarray(columns[f"rul_{q}"], float))
    return out


@dataclass(frozen=True, eq=False)
class FleetResult:
    """One row per asset (table order).

    Attributes:
        columns: ``{name: list}`` for :data:`OUTPUT_COLUMNS` (floats, NaN where no number is
            given; ``flags`` ``;``-separated; ``message`` the input problem of a set-aside asset),
            then :data:`EXTRA_COLUMNS` where the method gives them and :data:`DATE_COLUMNS`
            where the time column holds date-times.
        threshold, direction, horizon, seed, method, shard_size, backend: the run's settings.
        time_unit, epoch: the time axis (``"days"`` since ``epoch`` for date-time columns).
    """

    columns: dict[str, list]
    threshold: float
    direction: str
    horizon: float | None
    seed: int
    method: str
    shard_size: int
    backend: str
    time_unit: str | None = None
    epoch: str | None = None
    options: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.columns["asset"])

    def row(self, asset: str) -> dict:
        """The output row of one asset (its id, or a number read as its text as the table
        reads it: ``7.0`` is asset ``"7"``) as a dict."""
        key = _id_text(asset)
        try:
            i = self.columns["asset"].index(key)
        except ValueError:
            raise ValueError(f"asset {key!r} is not in this result ({len(self)} assets)") from None
        return {k: v[i] for k, v in self.columns.items()}

    def flagged(self, flag: str) -> list[str]:
        """Assets carrying ``flag``."""
        return [
            a for a, f in zip(self.columns["asset"], self.columns["flags"]) if flag in f.split(";")
        ]

    def to_pandas(self):
        """The table as a pandas DataFrame (``tables`` extra)."""
        from .table import _needs

        pd = _needs("pandas")
        return pd.DataFrame(self.columns)

    def calibrated(self, calibration) -> FleetResult:
        """This result with the columns ``rul_q05_calibrated`` and ``rul_q95_calibrated``: the
        90 % interval calibrated by a :func:`~prognos_torch.fleet.calibrate_fleet` calibration
        (:meth:`~prognos_torch.prognosis.RULCalibration.interval`; an open upper end, NaN
        ``rul_q95`` with more than 5 % censored, stays open as ``inf``; no interval stays NaN).

        Raises:
            ValueError: the calibration was made with another method, threshold, direction
                or method option than this result (the guarantee is for intervals made the
                same way).
        """
        st = dict(calibration.settings)
        if st.get("method") in METHODS:  # every option compared, the defaults filled in
            st = {**method_settings(st["method"], {}), **st}
        mine = dict(method_settings(self.method, self.options), threshold=self.threshold,
                    direction=self.direction, time_unit=self.time_unit)  # fmt: skip
        for key in sorted(set(st) | set(mine)):
            if key in ("fractions", "seed", "fleet", "horizon", "bins"):
                continue
            here, value = mine.get(key), st.get(key)
            same = here == value or (
                isinstance(here, float) and isinstance(value, float) and math.isclose(here, value)
            )
            if not same:
                raise ValueError(
                    f"the calibration was made with {key}={value!r}, this result has "
                    f"{key}={here!r}: the guarantee holds for intervals made the same way"
                )
        # (a NaN median, beyond every crossing, falls in the top bin)
        new_lo, new_hi = calibration.interval(*interval_columns(self.columns))
        cols = dict(self.columns)
        cols["rul_q05_calibrated"] = [float(v) for v in new_lo]
        cols["rul_q95_calibrated"] = [float(v) for v in new_hi]
        if self.epoch is not None:  # (an open upper end, inf, has no date: "")
            t_last = np.asarray(cols["t_last"], dtype=float)
            for end, v in (("q05", new_lo), ("q95", new_hi)):
                cols[f"failure_date_{end}_calibrated"] = _dates(self.epoch, t_last + v.numpy())
        return replace(self, columns=cols)

    def write(self, path) -> Path:
        """Write ``.csv`` or ``.parquet`` atomically (no partial file on interruption)."""
        return write_table(path, self.columns)


def interval_columns(columns: Mapping[str, list]) -> tuple[torch.Tensor, ...]:
    """``(rul_q05, rul_q95, rul_median)`` of a fleet's output columns as ``(A,)`` float64
    tensors, the interval as calibration reads it: ``rul_q95`` NaN with ``rul_q05`` known and
    more than 5 % censored is an open upper end (``inf``); no ``rul_q05``, no interval (NaN)."""
    lo, hi, cm, med = (torch.tensor(columns[k], dtype=torch.float64)
                       for k in ("rul_q05", "rul_q95", "censored_mass", "rul_median"))  # fmt: skip
    hi = torch.where(torch.isnan(hi) & ~torch.isnan(lo) & (cm > 0.05), math.inf, hi)
    return lo, torch.where(torch.isnan(lo), math.nan, hi), med


def run_shard(payload: Mapping, method: str, threshold: float, options: Mapping) -> dict:
    """Pad one shard and run the RUL method on it (also the body of a Ray task)."""
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # many tiny problems: threads only add overhead
    try:
        batch = pad_batch(payload["assets"], payload["times"], payload["values"], payload["seed"])
        return METHODS[method](batch, threshold, **options)
    finally:
        torch.set_num_threads(threads)


def _shards(table: FleetTable, shard_size: int, seed: int):
    keep = [i for i, a in enumerate(table.assets) if a not in table.errors]
    for start in range(0, len(keep), shard_size):
        ids = keep[start : start + shard_size]
        yield (
            ids,
            {
                "assets": [table.assets[i] for i in ids],
                "times": [table.times[i] for i in ids],
                "values": [table.values[i] for i in ids],
                "seed": seed,
            },
        )


def _progress(total: int, enabled: bool):
    from tqdm.auto import tqdm

    return tqdm(total=total, disable=not enabled, desc="shards", unit="shard", leave=False)


def _run_local(shards, method, threshold, options, progress, workers: int = 1):
    tasks = [(payload, method, threshold, dict(options)) for _, payload in shards]
    sizes = [sum(len(t) for t in payload["times"]) for _, payload in shards]
    with _progress(len(shards), progress) as bar:
        return process_map(run_shard, tasks, workers, sizes, "fleet_rul", lambda: bar.update(1))


def _run_ray(shards, method, threshold, options, progress, ray_init):
    try:
        import ray
    except ImportError:
        raise ImportError('backend="ray" needs Ray: pip install "prognos_torch[ray]"') from None
    started = False
    if not ray.is_initialized():
        ray.init(**({"include_dashboard": False} | dict(ray_init or {})))
        started = True
    try:
        task = ray.remote(run_shard)
        refs = [task.remote(payload, method, threshold, dict(options)) for _, payload in shards]
        index = {ref: j for j, ref in enumerate(refs)}
        out: list = [None] * len(refs)
        pending = list(refs)
        with _progress(len(refs), progress) as bar:
            while pending:
                done, pending = ray.wait(pending, num_returns=1)
                for ref in done:
                    out[index[ref]] = ray.get(ref)
                    bar.update(1)
        return out
    finally:
        if started:
            ray.shutdown()


def _check_part(part, method: str, n: int, extra) -> None:
    """A RUL method's answer for a shard of ``n`` assets: ``(n,)`` arrays of every column and
    ``n`` flags (and messages); ``ValueError`` naming the column (a ``(1,)`` column was spread
    over the shard's assets, a short flag list failed with an IndexError)."""
    for c in (*RUL_COLUMNS, *extra, "flags", "message"):
        if c == "message" and c not in part:
            continue
        if c not in part:
            raise ValueError(f"method {method!r} returned no {c!r} for a shard of {n} assets")
        shape = np.shape(part[c])
        if shape != (n,):
            raise ValueError(
                f"method {method!r} returned {c!r} of shape {shape} for a shard of {n} assets; "
                f"expected ({n},)"
            )


def method_defaults(method: str) -> dict[str, object] | None:
    """The options ``fleet_rul(..., **options)`` accepts for ``method`` and their defaults: the
    keyword options of :data:`METHODS` ``[method]`` (for ``"prognose"`` also those of
    :func:`~prognos_torch.workflow.prognose`, which its ``**options`` go to), less those
    ``fleet_rul`` sets itself; ``None`` (any) for a method of its own with ``**options``."""
    own = {"direction", "horizon", "time", "time_format", "seed", "at"}
    fns = [METHODS[method]]
    if METHODS[method] is prognose_rul:
        from ..workflow import prognose

        fns.append(prognose)
    elif any(p.kind is inspect.Parameter.VAR_KEYWORD
             for p in inspect.signature(fns[0]).parameters.values()):  # fmt: skip
        return None
    return {
        p.name: p.default
        for fn in fns
        for p in inspect.signature(fn).parameters.values()
        if p.kind is inspect.Parameter.KEYWORD_ONLY and p.name not in own
    }


def method_options(method: str) -> set[str] | None:
    """The names of :func:`method_defaults` (``None``: any)."""
    defaults = method_defaults(method)
    return None if defaults is None else set(defaults)


def method_settings(method: str, options: Mapping) -> dict:
    """What a fleet RUL is made with, as a calibration records it: ``method`` and every option
    of it, the defaults filled in (:func:`~prognos_torch.prognosis.conformal.record_settings`
    form); ``prognose``'s own ``method`` option as ``prognose_method``."""
    full = {**(method_defaults(method) or {}), **options}
    if "method" in full:
        full["prognose_method"] = full.pop("method")
    return dict(record_settings(full), method=method)


def _gathered_columns(table: FleetTable, shards: list, parts: list, method: str) -> dict:
    """The result table's columns in the assets' order: each shard's outputs (checked against
    the method's contract) at its assets' rows, and the set-aside assets as ``bad_input``
    with their message and row count."""
    n = len(table.assets)
    cols: dict[str, list] = {"asset": list(table.assets)}
    numeric = {c: np.full(n, np.nan) for c in RUL_COLUMNS}
    flags = [""] * n
    message = [""] * n
    extra = [c for c in EXTRA_COLUMNS if parts and c in parts[0]]
    numeric.update({c: np.full(n, np.nan) for c in extra})
    for (ids, _), part in zip(shards, parts):
        _check_part(part, method, len(ids), extra)
        for c in (*RUL_COLUMNS, *extra):
            numeric[c][ids] = part[c]
        for j, i in enumerate(ids):
            flags[i] = part["flags"][j]
            if "message" in part:
                message[i] = part["message"][j]
    for i, a in enumerate(table.assets):
        if a in table.errors:
            flags[i] = "bad_input"
            message[i] = table.errors[a]
            numeric["n_rows"][i] = len(table.values[i])
    for c in RUL_COLUMNS:  # (a count is an int: 200, not 200.0, in the table)
        cols[c] = [int(v) if c == "n_rows" else float(v) for v in numeric[c]]
    cols["flags"] = flags
    cols["message"] = message
    for c in extra:
        cols[c] = [float(v) for v in numeric[c]]
    return cols


def fleet_rul(
    source,
    threshold: float,
    *,
    group_by: str = "asset",
    column: str = "value",
    time_column: str = "t",
    direction: str = "above",
    horizon: float | None = None,
    seed: int = 0,
    method: str = "exponential",
    shard_size: int = 1024,
    backend: str = "local",
    on_error: str = "raise",
    progress: bool = False,
    ray_init: Mapping | None = None,
    decimal: str = ".",
    time_format: str | None = None,
    workers: int = 1,
    where=None,
    **options,
) -> FleetResult:
    """RUL for every asset of a long table (module docstring).

    Args:
        source: a :class:`~prognos_torch.fleet.table.FleetTable`, a ``.csv``/``.parquet``
            path, a pandas DataFrame or a mapping of columns.
        threshold: failure threshold on the value column.
        group_by, column, time_column: column names (asset, value, time).
        direction: ``"above"`` or ``"below"`` (``method="prognose"`` also ``"auto"``).
        horizon: time span for ``p_fail_within_horizon`` (``None``: ever).
        seed: fleet seed; asset ``a`` uses ``asset_seed(seed, a)``.
        method: a key of :data:`METHODS`.
        shard_size: assets per engine call (results do not depend on it).
        backend: ``"local"`` or ``"ray"``.
        on_error: ``"raise"`` or ``"flag"`` for per-asset input problems (see
            :mod:`prognos_torch.fleet.table`); too few rows are always only flagged.
        progress: progress bar over shards.
        ray_init: keyword arguments of ``ray.init`` when Ray is started here.
        decimal, time_format: a CSV table's decimal mark and the layout of its date-times
            (:func:`~prognos_torch.fleet.read_fleet_table`).
        where: keep only the table's rows whose cells equal these values (``{"channel": "5"}``
            or ``["channel=5"]``; :func:`~prognos_torch.fleet.read_fleet_table`); refused with
            a :class:`~prognos_torch.fleet.FleetTable`, which was read already.
        workers: processes for the local backend (``1``: this process). With more, the shards
            run side by side in spawned processes (one torch thread each), cut smaller where
            there are fewer shards than workers (the results are the same up to the ~1e-12 of
            another shard size; the per-asset ``"prognose"`` method's bit for bit). A script
            that calls ``fleet_rul`` at its top level needs the ``if __name__ ==
            "__main__":`` guard, as for any spawned process.
        **options: the method's options (e.g. ``samples``, ``phi``, ``min_rows``).
    Returns:
        :class:`FleetResult`.
    """
    if method not in METHODS:
        raise ValueError(f"unknown method {method!r}; choose one of {sorted(METHODS)}")
    allowed = method_options(method)
    unknown = [] if allowed is None else sorted(set(options) - allowed)
    if unknown:  # before the table is read and any worker starts
        raise TypeError(
            f"fleet_rul got {', '.join(map(repr, unknown))}, not an option of method "
            f"{method!r}; its options: {', '.join(sorted(allowed))}"
        )
    sides = _DIRECTIONS.get(method)
    if sides is not None and direction not in sides:  # (not per asset: every asset's error)
        raise ValueError(
            f"direction must be {', '.join(map(repr, sides[:-1]))} or {sides[-1]!r} for method "
            f"{method!r}, got {direction!r}"
        )
    if "min_rows" in options:
        check_min_rows(options["min_rows"])
    if backend not in ("local", "ray"):
        raise ValueError(f"backend must be 'local' or 'ray', got {backend!r}")
    if not is_int(shard_size) or shard_size < 1:
        raise ValueError(f"shard_size must be a positive int, got {shard_size!r}")
    shard_size = int(shard_size)
    seed = check_seed(seed)
    workers = check_workers(workers)  # (a NumPy count made shard_size a NumPy int)
    if on_error not in ("raise", "flag"):  # (also where a FleetTable is given, not read here)
        raise ValueError(f"on_error must be 'raise' or 'flag', got {on_error!r}")
    if workers > 1 and backend != "local":
        raise ValueError(
            f"workers={workers} applies to backend='local'; Ray places its tasks on its own "
            "workers (ray_init={'num_cpus': ...})"
        )
    thr = check_real(threshold, "threshold")
    if horizon is not None:
        horizon = check_real(horizon, "horizon")
        if not horizon > 0:
            raise ValueError(f"horizon must be positive (or None: ever), got {horizon!r}")
    table = as_fleet_table(
        source,
        where=where,
        group_by=group_by,
        column=column,
        time_column=time_column,
        on_error=on_error,
        decimal=decimal,
        time_format=time_format,
    )
    opts = dict(options, direction=direction, horizon=horizon)
    if workers > 1:  # at least one shard per worker (as long as there are assets)
        n_keep = len(table.assets) - len(table.errors)
        shard_size = max(1, min(shard_size, -(-n_keep // workers)))
    shards = list(_shards(table, shard_size, seed))
    if backend == "local":
        parts = _run_local(shards, method, thr, opts, progress, workers)
    else:
        parts = _run_ray(shards, method, thr, opts, progress, ray_init)

    cols = _gathered_columns(table, shards, parts, method)
    if table.epoch is not None:
        cols.update(date_columns(cols, table.epoch))
    return FleetResult(
        columns=cols,
        threshold=thr,
        direction=direction,
        horizon=horizon,
        seed=seed,
        method=method,
        shard_size=shard_size,
        backend=backend,
        time_unit=table.time_unit,
        epoch=table.epoch,
        options=dict(options),
    )
