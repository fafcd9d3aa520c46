"""``prognos rul DATA.csv --column C --threshold X``: RUL straight from a CSV (no model file).

The command line face of :func:`~prognos_torch.workflow.prognose`; ``prognos rul MODEL DATA``
(a fitted learner) stays in :mod:`prognos_torch.cli`.
"""

from __future__ import annotations

import math
import sys

from ._text import fmt_time, json_number

__all__ = [
    "run_prognose",
    "json_record",
    "write_made",
    "figure_file",
    "json_text",
    "reporter",
    "observed_rul",
    "within_probability",
    "load_histories",
    "read_calibration",
    "calibration_rows",
]


def _fmt(v, digits: int = 4) -> str:
    if v is None:
        return "n/a"
    if isinstance(v, float):
        return "inf" if math.isinf(v) else f"{v:.{digits}g}"
    return str(v)


def _rul_end(v, bound: float) -> str:
    """A RUL quantile for the report; ``None`` (beyond the horizon: censored paths) reads as
    ``> bound``, which is what is known of it (``inf`` for an infinite bound)."""
    if v is not None:
        return _fmt(v)
    return "inf" if math.isinf(bound) else f"> {_fmt(bound)}"


def failure_dates(res, series, bound: float) -> tuple[str, str, str] | None:
    """The failure dates of the 5 %, 50 % and 95 % RUL quantiles for a report (UTC, to the
    second), a quantile beyond ``bound`` as ``after`` that date; ``None`` for numeric time."""
    if series.start is None:
        return None
    end = series.date(res.t_last + bound)
    after = f"after {end}" if end else "beyond the date range"
    return tuple(res.failure_date(q) or after for q in (0.05, 0.5, 0.95))


def at_time(series, t: float, unit: str) -> str:
    """A time for a report, and its date-time where the series has date-times."""
    date = series.date(t)
    return f"{fmt_time(t)} {unit}" + (f" ({date} UTC)" if date else "")


def json_record(res, series, data_cfg: dict, **extra) -> dict:
    """The ``--json`` record of ``prognos rul``: the series' ``source``, ``column`` and
    ``where`` selection, then :meth:`~prognos_torch.workflow.RULResult.to_dict`, then the
    report's further rows given as ``extra`` (``p_within``, ``observed_rul``, ``calibrated``),
    JSON-safe (a non-finite number is ``None``)."""
    record = {
        "source": None if series.source is None else str(series.source),
        "column": series.name,
        "where": dict(data_cfg.get("where") or {}),
    }
    record.update(res.to_dict())
    for key, value in extra.items():
        if isinstance(value, dict):
            value = {k: json_number(v) if isinstance(v, float) else v for k, v in value.items()}
        record[key] = json_number(value) if isinstance(value, float) else value
    return record


def json_text(record: dict) -> str:
    """``record`` as indented JSON (``NaN`` and ``inf`` refused: JSON has no such numbers)."""
    import json

    return json.dumps(record, indent=2, allow_nan=False) + "\n"


def write_made(say, made: list[tuple[str, bytes, str]], json_target=None, record=None) -> None:
    """Write a command's files once every one of them is made (a figure or record that cannot
    be made leaves none written; each is written whole or not at all,
    :func:`~prognos_torch.io.atomic_write`), saying each: ``made`` holds ``(path, bytes,
    what)``; the JSON ``record`` (text) goes to ``json_target``, standard output for ``"-"``
    (after the files, as the record alone)."""
    from .io import atomic_write

    if json_target is not None and json_target != "-":
        made = [*made, (json_target, record.encode(), "record")]
    for path, data, what in made:
        atomic_write(path, data)
        say(f"{what} written to {path}")
    if json_target == "-":
        sys.stdout.write(record)


def figure_file(path: str, fig) -> tuple[str, bytes, str]:
    """A figure made for ``path`` (its format by the suffix), for :func:`write_made`."""
    from .plots._arrays import figure_bytes

    return (str(path), figure_bytes(fig, path), "figure")


def reporter(args):
    """``print`` for the report, or a function that prints nothing where ``--json -`` takes
    standard output for the record."""
    if getattr(args, "json", None) == "-":
        return lambda *a, **k: None
    return print


def _warner(args):
    """``print`` for the report's ``warning:`` lines, or a printer to standard error where
    ``--json -`` takes standard output (they were lost with the report)."""
    if getattr(args, "json", None) == "-":
        import sys

        return lambda text: print(text, file=sys.stderr)
    return print


def within_probability(res, within: float, hint: str = "") -> float | None:
    """``res.failure_probability(within)`` for ``--within``, read before anything is printed;
    a refusal names the option and, for a span beyond the horizon, ends with ``hint``."""
    try:
        return res.failure_probability(within)
    except ValueError as exc:
        beyond = hint if math.isfinite(within) and within > res.bound else ""
        raise ValueError(f"--within: {exc}{beyond}") from None


def observed_rul(truth, t_eval: float, threshold: float, direction: str) -> float | None:
    """Time from ``t_eval`` to the first later time the trailing 5-point median of the
    observed ``truth`` series reaches ``threshold`` (``None``: not in the data)."""
    from .prognosis import moving_median

    m = moving_median(truth.values, 5)
    hit = (m >= threshold) if direction == "above" else (m <= threshold)
    idx = (hit & (truth.t > t_eval)).nonzero()
    if idx.numel() == 0:
        return None
    return float(truth.t[idx[0, 0]]) - t_eval


def read_calibration(path):
    """The :class:`~prognos_torch.prognosis.RULCalibration` in a ``--calibration-out`` file."""
    import json

    from .prognosis import RULCalibration

    try:
        record = json.loads(path.read_text())
    except FileNotFoundError:
        raise FileNotFoundError(f"--calibration: no file {path}") from None
    except OSError as exc:  # (a folder, a file it may not read: "[Errno 21] Is a directory")
        raise OSError(f"--calibration: {path} cannot be read ({exc.strerror or exc})") from None
    except (ValueError, UnicodeDecodeError) as exc:
        raise ValueError(f"--calibration: {path} is not a JSON calibration file ({exc})") from None
    try:
        return RULCalibration.from_dict(record)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"--calibration: {path}: {exc}") from None


def load_histories(args, series):
    """The ``--calibrate`` table as ``{asset: (t, y)}``, or the ``--calibration`` file's
    :class:`~prognos_torch.prognosis.RULCalibration` (``None`` without either), read and
    checked before anything runs: the same ``--column`` and ``--time-column`` as the series, on
    the same kind of clock (date-times, or numbers in the series' unit)."""
    if args.calibration is not None:
        if args.calibrate is not None:
            raise ValueError(
                "--calibrate and --calibration exclude each other: calibrate on histories, or "
                "read a calibration made earlier"
            )
        if args.calibration_out is not None:
            raise ValueError("--calibration-out writes the calibration that --calibrate makes")
        return read_calibration(args.calibration)
    if args.calibrate is None:
        if args.calibration_out is not None:
            raise ValueError("--calibration-out needs --calibrate TABLE (the histories)")
        return None
    import torch

    from ._command import calibrate_message
    from .fleet.table import read_fleet_table

    if args.time_column is None:
        raise ValueError(
            "--calibrate needs --time-column: the histories' RULs are read on their clock, "
            "which must be the series' clock"
        )
    try:
        tab = read_fleet_table(
            args.calibrate,
            group_by=args.calibrate_group,
            column=args.column,
            time_column=args.time_column,
            decimal=args.decimal or ".",
            time_format=args.time_format,
            where=args.calibrate_where,
        )
    except ValueError as exc:
        msg = str(exc).replace("(--group-by)", "(--calibrate-group)")
        raise ValueError(calibrate_message(msg)) from None
    except FileNotFoundError as exc:
        raise FileNotFoundError(f"--calibrate: {exc}") from None
    dates, tab_dates = series.start is not None, tab.time_unit == "days"
    if dates != tab_dates:
        kind = lambda d: "date-times" if d else "numbers"  # noqa: E731
        raise ValueError(
            f"--calibrate: the time column {args.time_column!r} of {args.calibrate} holds "
            f"{kind(tab_dates)}, that of {series.source} {kind(dates)}: the RULs would be on "
            "different clocks"
        )
    f64 = lambda a: torch.as_tensor(a, dtype=torch.float64)  # noqa: E731
    return {a: (f64(t), f64(y)) for a, t, y in zip(tab.assets, tab.times, tab.values)}


def _check_settings(cal, path, run: dict) -> None:
    """Refuse a ``--calibration`` made under other settings than this run's."""
    from .workflow.prognosing import filter_pool

    def same(key, made, here) -> bool:  # filters by their names: "EKF" is "ekf"
        if key == "filter" and isinstance(made, str) and isinstance(here, str):
            try:
                return filter_pool(made) == filter_pool(here)
            except ValueError:
                return False
        return made == here

    st = cal.settings
    for key, option in (("method", "--method"), ("filter", "--filter"), ("n_paths", "--paths"),
                        ("direction", "--direction"), ("glitch_limit", "--glitch-limit")):  # fmt: skip
        if key in st and not same(key, st[key], run[key]):
            raise ValueError(
                f"--calibration: {path} was made with {option} {st[key]}, this run has "
                f"{run[key]}: the guarantee holds for intervals made the same way (recalibrate "
                "with --calibrate, or pass the same setting)"
            )
    # pooled seeds pool models (another estimator); which seed drew them does not matter
    pooled = lambda seed: len(seed) if isinstance(seed, (list, tuple)) else 1  # noqa: E731
    if "seed" in st and pooled(st["seed"]) != pooled(run["seed"]):
        raise ValueError(
            f"--calibration: {path} was made with {pooled(st['seed'])} pooled seed(s) (--seed), "
            f"this run pools {pooled(run['seed'])}: the guarantee holds for intervals made the "
            "same way (recalibrate with --calibrate, or pass as many seeds)"
        )
    thr = st.get("threshold")
    if isinstance(thr, (int, float)) and not math.isclose(thr, run["threshold"], rel_tol=1e-9):
        raise ValueError(
            f"--calibration: {path} was made with failure at the threshold {thr:g}, this run's is "
            f"{run['threshold']:g} (a calibration made with --calibrate-threshold protocol "
            "serves any threshold)"
        )


def _of(assets: int | None) -> str:
    return "" if assets is None else f" from {assets} histories"


def calibration_rows(res, cal, points: list[dict] | None, unit: str) -> tuple[list, list[str]]:
    """The ``calibrated 90 % interval`` row of ``prognos rul DATA --calibrate`` and its
    warnings (histories that gave no usable point); ``points`` ``None``: a calibration read
    from a file."""
    full = cal.summary(res)
    s = full["calibrated"]
    names = list(dict.fromkeys(p["name"] for p in points or ()))
    used = list(dict.fromkeys(p["name"] for p in points or () if "score" in p))
    src = (f"{cal.n} points from {len(used)} of {len(names)} histories" if points is not None
           else f"{cal.n} points{_of(cal.assets)} of the --calibration file")  # fmt: skip
    if s["margin"] == math.inf:
        from .prognosis.conformal import points_needed

        needed = points_needed(cal.coverage)
        note = f"{src}: too few for {100 * cal.coverage:g} % coverage, which needs {needed}"
    else:
        f = math.exp(abs(s["margin"]))
        note = f"split conformal on {src}; ends moved {'out' if s['margin'] >= 0 else 'in'} by a factor {f:.3g}"
        if f == math.inf:  # (calibration intervals [0, inf): every other interval comes out empty)
            note = f"split conformal on {src}, whose intervals were [0, inf): margin -inf"
    # an open end lies beyond the horizon moved by the margin (infinite: no margin yet)
    beyond = full["bound"] * math.exp(s["margin"]) if math.isfinite(s["margin"]) else math.inf
    text = f"[{_fmt(s['q05'])}, {_rul_end(s['q95'], beyond)}]"
    if s["empty"]:  # narrowed past its width, as in CQR
        text = f"empty ({text} narrowed by the margin past its own width)"
    rows = [(f"calibrated 90 % interval ({unit})", f"{text} ({note})")]
    hist = res.history
    if hist.start is not None and s["q05"] is not None and math.isfinite(s["margin"]) \
            and "empty" not in text:  # fmt: skip
        shown = lambda t: hist.date(t) or "beyond the date range"  # noqa: E731
        hi = (shown(res.t_last + s["q95"]) if s["q95"] is not None
              else f"after {shown(res.t_last + beyond)}")  # fmt: skip
        rows.append(("calibrated failure dates (UTC)", f"[{shown(res.t_last + s['q05'])}, {hi}]"))
    warn = []
    few = cal.warning("histories")
    if few is not None:
        warn.append(f"--{'calibrate' if points is not None else 'calibration'}: {few}")
    unused = [n for n in names if n not in used]
    if unused:
        first = next(p for p in points if p["name"] == unused[0])
        warn.append(
            f"--calibrate: {len(unused)} of {len(names)} histories gave no point with an "
            f"interval (first, {unused[0]!r}: {first['status']})"
        )
    return rows, warn


def _calibration(args, res, filt, histories) -> tuple[list, list[str], object, dict | None]:
    """The calibration rows and warnings of ``run_prognose``, the calibration that
    ``--calibrate`` made (``None`` otherwise), and the calibrated interval the rows show
    (``RULCalibration.summary``'s ``"calibrated"``; ``None`` without one). With
    ``--calibration-out`` the histories are replayed even before onset, so that the file is
    written."""
    unit = res.time_unit
    if histories is None:
        return [], [], None, None
    na = [(f"calibrated 90 % interval ({unit})", f"n/a ({res.status})")]
    if not isinstance(histories, dict):  # --calibration FILE
        if res.status != "ok":
            return na, [], None, None
        run = {"method": args.method, "filter": filt, "n_paths": args.paths,
               "direction": res.direction, "threshold": res.threshold,
               "glitch_limit": args.glitch_limit, "seed": args.seed}  # fmt: skip
        _check_settings(histories, args.calibration, run)
        rows, warn = calibration_rows(res, histories, None, unit)
        return rows, warn, None, histories.summary(res)["calibrated"]
    if res.status != "ok" and args.calibration_out is None:
        return na, [], None, None
    from .workflow import calibrate_rul

    protocol = args.calibrate_threshold == "protocol"
    if protocol and res.direction == "below":
        raise ValueError(
            "--calibrate-threshold protocol is the bearing studies' rule for a rising "
            f"indicator, and the threshold {res.threshold:g} lies below: use "
            "--calibrate-threshold same"
        )
    try:
        cal, points = calibrate_rul(
            histories,
            threshold=None if protocol else res.threshold,
            direction=res.direction,
            workers=args.workers,
            **_prognose_options(args, filt),
        )
    except ValueError as exc:
        raise ValueError(f"--calibrate: {exc}") from None
    if res.status != "ok":
        return na, [], cal, None
    rows, warn = calibration_rows(res, cal, points, unit)
    return rows, warn, cal, cal.summary(res)["calibrated"]


def _prognose_options(args, filt) -> dict:
    """The ``prognose`` settings of the command line, the same for the series and for the
    histories that ``--calibrate`` replays (a calibration holds for intervals made alike)."""
    return {"method": args.method, "filter": filt, "seed": 0 if args.seed is None else args.seed,
            "n_paths": args.paths, "glitch_limit": args.glitch_limit}  # fmt: skip


def run_prognose(args, series, data_cfg: dict, truth=None, histories=None) -> str | None:
    """Run ``prognose`` on the loaded series and print the result (and write ``--plot``).

    Returns:
        ``None``, or the sentence for the ``censored RUL:`` line when more than 5 % of the
        distribution lies beyond the horizon, so that its 95 % quantile is unknown (the command
        then exits 3, as ``prognos rul MODEL DATA`` does for any censored mass: its horizon is
        the user's, while ``prognose`` runs until every path crosses or a horizon long enough
        for the model, and a few paths beyond it leave every reported quantile intact).
    """
    from .workflow import prognose
    from .workflow.prognosing import CENSORED_FLAG, filter_pool

    filt = "ekf" if args.filter is None else args.filter
    try:
        filter_pool(filt)
    except ValueError as exc:
        raise ValueError(f"--filter: {exc}") from None
    res = prognose(
        series, args.threshold, direction=args.direction, **_prognose_options(args, filt)
    )
    unit, s = res.time_unit, res.summary()
    p_within = None if args.within is None else within_probability(res, args.within)
    cal_rows, cal_warn, made, calibrated = _calibration(args, res, filt, histories)
    where = data_cfg.get("where") or {}
    sel = f" ({', '.join(f'{k}={v}' for k, v in where.items())})" if where else ""
    say, warn = reporter(args), _warner(args)
    say(
        f"RUL of {series.name!r}{sel} from {series.source} at t = "
        f"{at_time(series, res.t_last, unit)}: "
        f"threshold {res.threshold:g} ({res.direction})"
    )
    on, onset = res.onset, "not detected"
    if on is not None and on.detected:
        date = series.date(on.time)
        onset = f"{fmt_time(on.time)} {unit} ({f'{date} UTC; ' if date else ''}{on.method}, baseline " \
            f"mean {on.baseline.mean:.4g}, std {on.baseline.std:.4g})"  # fmt: skip
    rows = [("status", res.status), ("degradation onset", onset)]
    if res.status == "ok":
        scores = (res.selection or {}).get("scores") or {}
        chosen = res.model + (
            " (backtest: " + ", ".join(f"{k} {v:.3g}" for k, v in scores.items()) + ")"
            if scores
            else ""
        )
        lo, hi = (_rul_end(s[k], s["bound"]) for k in ("q05", "q95"))
        rows += [
            ("trend model", chosen),
            (f"median RUL ({unit})", _rul_end(s["median"], s["bound"])),
            (f"90 % interval ({unit})", f"[{lo}, {hi}]"),
            ("censored mass", f"{s['censored_mass']:.3f} (RUL > {_fmt(s['bound'])} {unit})"),
        ]
        dates = failure_dates(res, series, s["bound"])  # what a planner reads
        if dates is not None:
            rows[-1:-1] = [
                ("failure date, median (UTC)", dates[1]),
                ("failure dates, 90 % (UTC)", f"[{dates[0]}, {dates[2]}]"),
            ]
    else:
        rows += [(f"lower bound if it stays healthy ({unit})", _fmt(s["bound"]))]
        if series.start is not None and s["bound"] is not None:
            rows.append(("no failure before (UTC)", series.date(res.t_last + s["bound"]) or "n/a"))
    rows += cal_rows
    if args.within is not None:
        rows.append(
            (
                f"P(failure within {args.within:g} {unit})",
                f"{p_within:.3f}" if p_within is not None else f"n/a ({res.status})",
            )
        )
    obs = None if truth is None else observed_rul(truth, res.t_last, res.threshold, res.direction)
    if truth is not None:
        rows.append(
            # (the trend's level, as a moving median follows it: the protocol's end of life)
            (
                f"observed RUL ({unit}, 5-point median)",
                "not reached in the data" if obs is None else _fmt(obs),
            )
        )
    width = max(len(r[0]) for r in rows)
    for k, v in rows:
        say(f"  {k.ljust(width)}  {v}")
    for f in list(res.flags) + cal_warn:  # (--json -: on stderr, beside the record, not lost)
        warn(f"warning: {f}")
    # every file is made first and written after: a figure or record that cannot be made
    # leaves none of them written (each is also written whole or not at all)
    files: list[tuple[str, bytes, str]] = []
    if args.plot is not None:
        from .plots import plot_prognosis  # (matplotlib: only for a figure)

        tr = None if truth is None else (truth.t, truth.values)
        files.append(figure_file(args.plot, plot_prognosis(None, res, truth=tr)))
    if made is not None and args.calibration_out is not None:
        text = json_text(made.to_dict())
        files.append((str(args.calibration_out), text.encode(), "calibration"))
    record = None
    if args.json is not None:
        extra = {}
        if args.within is not None:
            extra["p_within"] = {"within": args.within, "p": p_within}
        if truth is not None:
            extra["observed_rul"] = obs
        if calibrated is not None:
            # the report's warnings (the calibration's own among them, as the report words it)
            own = {k: v for k, v in calibrated.items() if k != "warning"}
            extra["calibrated"] = dict(own, warnings=cal_warn)
        record = json_text(json_record(res, series, data_cfg, **extra))
    write_made(say, files, args.json, record)
    if res.status == "ok" and res.censored_mass > CENSORED_FLAG:
        return (
            f"{100 * res.censored_mass:.3g} % of the predicted paths do not reach the threshold "
            f"{res.threshold:g} within the horizon of {res.bound:g} {unit}; their RUL exceeds it "
            "and the mean is withheld"
        )
    return None
