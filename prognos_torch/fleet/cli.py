"""``prognos rul TABLE --group-by ASSET ...``: fleet RUL from a long table (see ``--help``)."""

from __future__ import annotations

import argparse
import math
import sys
import time
from collections import Counter
from pathlib import Path

from .._command import (
    calibrate_message,
    check_output_file,
    check_overwrites,
    one_torch_thread,
    option_of,
    where_message,
)

__all__ = ["build_parser", "main"]

_EPILOG = """examples:
  prognos rul fleet.parquet --group-by asset --column value --time-column t --threshold 20 \\
      --out results.parquet
  prognos rul fleet.csv --group-by unit --column rms --time-column hours --threshold 0.9 \\
      --horizon 48 --backend ray --out results.csv
  prognos rul fleet.csv --group-by unit --threshold 20 --calibrate failed.csv --out results.csv
      (failed.csv: assets that ran to failure, same columns; adds rul_q05_calibrated and
       rul_q95_calibrated, the 90 % interval calibrated on them: split conformal)
  prognos rul bearings.csv --group-by bearing --column rms --time-column timestamp \\
      --where channel=1 --threshold 0.5 --out results.csv
      (a table with a row per bearing, time and channel: the rows of channel 1)

The table has one row per measurement (asset, time, value); assets may be interleaved, but
each asset's times must increase. Output: one row per asset with the columns asset, n_rows,
t_last, onset_time, rul_median, rul_q05, rul_q95, p_fail_within_horizon, censored_mass, flags,
message, phi (unless --phi is a number), and the *_date columns on a date-time column.
The file is written atomically at the end: an interrupted run leaves no partial file.
Flags: too_few_rows, no_baseline, no_onset (no degradation detected yet: no RUL number),
threshold_on_healthy_side (the baseline already lies at or beyond the threshold: check
--direction), threshold_reached, few_degraded_points, nonpositive_dropped, far_extrapolation,
trend_misfit (the data since onset leave the exponential trend: its interval is too narrow;
try --method prognose), fit_past_threshold (the fitted trend has passed the threshold that
the last value has not: no RUL), last_rows_missing (the RUL counts from the last row, and a
crossing in the unobserved stretch is a RUL of 0), glitch_in_baseline (isolated values far off their
neighbours widen the healthy band 1.5 times or more, which can delay the onset), bad_input.
exit status: 0 success, 2 bad input (one line on stderr, nothing written), 130 interrupted."""


def _phi(text: str) -> float | str:
    """``--phi``: a finite number, ``baseline`` or ``auto``."""
    if text in ("baseline", "auto"):
        return text
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"a number, 'baseline' or 'auto', got {text!r}") from None
    if not math.isfinite(v):
        raise argparse.ArgumentTypeError(f"a finite number, 'baseline' or 'auto', got {text!r}")
    return v


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="prognos rul",
        description=(
            "RUL of every asset of a long table (fleet mode of prognos rul): degradation onset "
            "by the k-sigma rule, exponential trend y = phi + theta exp(beta t) estimated by "
            "the filter engine for a shard of assets at once, RUL quantiles from posterior "
            "samples seeded per asset (the table does not depend on --shard-size or "
            "--backend)."
        ),
        epilog=_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("table", type=Path, help=".csv or .parquet long table")
    p.add_argument("--group-by", required=True, help="asset id column")
    p.add_argument("--column", default="value", help="value column (default value)")
    p.add_argument("--time-column", default="t", help="time column (default t)")
    p.add_argument(
        "--decimal",
        choices=(".", ","),
        default=".",
        help="decimal mark of CSV tables (default '.'; ',' reads 0,25 as 0.25)",
    )
    p.add_argument(
        "--time-format",
        metavar="FMT",
        help="layout of date-times that are not ISO 8601, in strptime codes, e.g. "
        "'%%d/%%m/%%Y %%H:%%M'",
    )
    p.add_argument(
        "--where",
        action="append",
        metavar="COL=VALUE",
        help="keep rows whose COL equals VALUE (repeatable), e.g. --where channel=5",
    )
    p.add_argument("--threshold", type=float, required=True, help="failure threshold")
    p.add_argument("--direction", default="above", help="above (default) or below")
    p.add_argument(
        "--horizon",
        type=float,
        help="time span of p_fail_within_horizon (default: failure at any time)",
    )
    p.add_argument(
        "--method",
        default="exponential",
        help="exponential (default: batched over assets) or prognose (the workflow's prognose "
        "per asset: trend models chosen by backtest; slower)",
    )
    p.add_argument(
        "--phi",
        type=_phi,
        help="offset of the exponential model: auto (default: per asset, the one of 0 and "
        "baseline under which the data since onset are likelier; a phi column says which), a "
        "number (0: growth from near zero) or baseline (each asset's healthy mean: an "
        "indicator with a healthy level, such as an rms); exponential only",
    )
    p.add_argument("--samples", type=int, default=1000, help="posterior draws / paths per asset")
    p.add_argument("--min-rows", type=int, default=10, help="fewer rows: flagged, no RUL")
    p.add_argument("--seed", type=int, default=0, help="fleet seed (default 0)")
    p.add_argument("--shard-size", type=int, default=1024, help="assets per engine call")
    p.add_argument("--backend", default="local", help="local (default) or ray")
    p.add_argument("--workers", type=int, default=1,
                   help="local backend: processes running shards side by side (default 1)")  # fmt: skip
    p.add_argument("--ray-address", help="Ray cluster address (default: start a local Ray)")
    p.add_argument(
        "--on-error",
        default="raise",
        help="raise (default) or flag: an asset with a non-numeric value, a duplicate or "
        "unsorted time is set aside with its message instead of stopping the run (in the "
        "--calibrate table too: a failed asset set aside gives no point)",
    )
    p.add_argument(
        "--calibrate",
        type=Path,
        metavar="FAILED",
        help="a long table (same columns) of assets that ran to failure: each is replayed at "
        "20/40/60/80/90 %% of [onset, failure] with the same method, and the output gains "
        "rul_q05_calibrated and rul_q95_calibrated (prognos_torch.fleet.calibrate_fleet)",
    )
    p.add_argument(
        "--calibrate-where",
        action="append",
        metavar="COL=VALUE",
        help="keep the --calibrate table's rows whose COL equals VALUE (repeatable)",
    )
    p.add_argument("--out", required=True, help="output .csv or .parquet")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    return p


#: the first words of the fleet's messages about an argument and the options that set it: an
#: error about one names both (as ``prognos rul DATA.csv`` does)
_OPTION_OF = {
    "samples": "--samples",
    "n_paths": "--samples",  # (--method prognose: prognose's paths)
    "shard_size": "--shard-size",
    "horizon": "--horizon",
    "threshold must": "--threshold",
    "direction must": "--direction",
    "unknown method": "--method",
    "backend must": "--backend",
    "on_error must": "--on-error",
    "seed": "--seed",
}


def _where(values: list[str] | None, option: str) -> dict[str, str] | None:
    """``--where``/``--calibrate-where`` as a dict (``None``: not given); a malformed value
    is refused by the option's name."""
    from ..workflow.data import parse_where

    if values is None:
        return None
    try:
        return parse_where(values)
    except ValueError as exc:
        raise ValueError(where_message(str(exc), option)) from None


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    with one_torch_thread():
        return _run(args)


def _calibration(args, same: dict, cal_where, method_options: dict) -> tuple:
    """``--calibrate FAILED``: the fleet's calibration on its failed assets, ``(calibration,
    points)``; an error about the table or ``--calibrate-where`` names that option."""
    from .calibrate import calibrate_fleet

    try:
        cal, cal_points = calibrate_fleet(
            args.calibrate, args.threshold, **same, workers=args.workers,
            on_error=args.on_error, where=cal_where, **method_options,
        )  # fmt: skip
    except FileNotFoundError as exc:
        raise FileNotFoundError(f"--calibrate: {exc}") from None
    except ValueError as exc:
        if option_of(str(exc), _OPTION_OF) is not None:  # a setting of both runs, not the table
            raise
        raise ValueError(calibrate_message(str(exc))) from None
    return cal, cal_points


def _report(args, res, cal, cal_points, seconds: float) -> None:
    """What a fleet run printed: the counts, each flag's assets, the calibration's margin and
    the set-aside assets (their messages on stderr)."""
    n = len(res)
    with_rul = sum(1 for v in res.columns["rul_median"] if v == v)
    counts = Counter(f for fl in res.columns["flags"] for f in fl.split(";") if f)
    unit = f" {res.time_unit}" if res.time_unit else ""
    print(
        f"{n} assets, {with_rul} with a RUL, in {seconds:.1f} s "
        f"({args.backend}{f', {args.workers} workers' if args.workers > 1 else ''}, shards of "
        f"{res.shard_size}); written to {args.out}"
        + (f" (times in{unit} since {res.epoch}; dates in the *_date columns)" if res.epoch else "")
    )
    if args.phi in (None, "auto") and "phi" in res.columns:  # which offset each trend took
        rul = [p for p, m in zip(res.columns["phi"], res.columns["rul_median"]) if m == m]
        level = sum(1 for p in rul if p != 0)
        print(f"  trend offset (--phi auto): the healthy level for {level}, 0 for "
              f"{len(rul) - level} of the {len(rul)} with a RUL")  # fmt: skip
    for flag, c in sorted(counts.items()):
        print(f"  {flag}: {c} asset(s)")
    if cal is not None:
        how = (
            f"margin {cal.margin:+.3g} on the log RUL: ends moved "
            f"{'out' if cal.margin >= 0 else 'in'} by a factor {math.exp(abs(cal.margin)):.3g}"
            if math.isfinite(cal.margin)
            else "too few points for 90 % coverage: the calibrated interval is [0, inf)"
        )
        if cal.margins:
            how = (
                f"{len(cal.margins)} bins of the predicted median RUL, margins "
                + ", ".join(f"{q:+.3g}" for q in cal.margins)
                + " on the log RUL (shortest RUL first)"
            )
        print(f"  calibrated on {cal.n} points of {cal.assets} failed assets ({args.calibrate}): {how}")
        if (few := cal.warning("failed assets")) is not None:
            print(f"  warning: {few}")
        # failed assets that gave no point (set aside, too short, no onset): their reasons
        aside = [(a, s) for a, s in zip(cal_points["asset"], cal_points["status"]) if "@" not in a]
        if aside:
            print(f"  {len(aside)} failed asset(s) gave no calibration point (first, {aside[0][0]!r}: "
                  f"{aside[0][1]})", file=sys.stderr)  # fmt: skip
    bad = [m for m in res.columns["message"] if m]
    for m in bad[:5]:
        print(f"  {m}", file=sys.stderr)
    if len(bad) > 5:
        print(f"  ... and {len(bad) - 5} more set-aside assets", file=sys.stderr)


def _run(args) -> int:
    from .run import fleet_rul
    from .table import TABLE_SUFFIXES

    try:
        # a folder (also by a final "/"), a missing folder or an input table: refused before the
        # run (a folder failed after it, an input was replaced by the results)
        check_output_file(args.out, "--out")
        args.out = Path(args.out)
        if args.out.suffix.lower() not in TABLE_SUFFIXES:
            raise ValueError(f"--out must end in {', '.join(TABLE_SUFFIXES)}, got {args.out}")
        check_overwrites({"--out": args.out},
                         {"the table": args.table, "the --calibrate table": args.calibrate})
        if args.phi is not None and args.method != "exponential":
            raise ValueError("--phi applies to --method exponential only")
        if args.min_rows < 1:
            raise ValueError(f"--min-rows must be at least 1, got {args.min_rows}")
        if args.workers < 1:
            raise ValueError(f"--workers must be at least 1 (processes), got {args.workers}")
        if args.calibrate_where is not None and args.calibrate is None:
            raise ValueError("--calibrate-where applies with --calibrate FAILED")
        where = _where(args.where, "--where")
        cal_where = _where(args.calibrate_where, "--calibrate-where")
        ray_init = {"address": args.ray_address} if args.ray_address else None
        t0 = time.perf_counter()
        method_options = dict(
            method=args.method,
            min_rows=args.min_rows,
            **(
                {"samples": args.samples, "phi": "auto" if args.phi is None else args.phi}
                if args.method == "exponential"
                else {"n_paths": args.samples}
            ),
        )
        # the live fleet and its failed assets are read and predicted alike
        same = dict(group_by=args.group_by, column=args.column, time_column=args.time_column,
                    direction=args.direction, seed=args.seed, decimal=args.decimal,
                    time_format=args.time_format)  # fmt: skip
        cal, cal_points = None, None
        if args.calibrate is not None:
            cal, cal_points = _calibration(args, same, cal_where, method_options)
        res = fleet_rul(
            args.table,
            args.threshold,
            **same,
            horizon=args.horizon,
            shard_size=args.shard_size,
            backend=args.backend,
            workers=args.workers,
            on_error=args.on_error,
            where=where,
            progress=not args.no_progress,
            ray_init=ray_init,
            **method_options,
        )
        if cal is not None:
            try:
                res = res.calibrated(cal)
            except ValueError as exc:
                raise ValueError(f"--calibrate: {exc}") from None
        res.write(args.out)
    except KeyboardInterrupt:
        print("interrupted: nothing written", file=sys.stderr)
        return 130
    except (ValueError, TypeError, OSError, ImportError) as exc:
        text = where_message(" ".join(str(exc).split()), "--where") or type(exc).__name__
        option = option_of(text, _OPTION_OF)
        if option is not None:  # a message about an argument names the option that set it
            text = f"{option}: {text}"
        print(f"error: {text}", file=sys.stderr)
        return 2
    _report(args, res, cal, cal_points, time.perf_counter() - t0)
    return 0
