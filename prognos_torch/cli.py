"""The prognos command line: fault prediction and remaining useful life from measured series.

prognos study --list
prognos study NAME [--runs N] [--quick] [--out DIR] [--device cpu|cuda] [--seed S] [--data DIR]
prognos study all [--quick] ...   (studies of data the library does not ship need --data)
prognos fit DATA.csv --column COL [--time-column T] [--learner L] [--optimizer O] --out model.pt
prognos forecast model.pt DATA.csv --horizon 50 [--plot forecast.png]
prognos rul model.pt DATA.csv --threshold X [--filter stpf|pf|ekpf|sckf] [--plot rul.png]
prognos rul DATA.csv --column C [--time-column T] --threshold X [--where COL=V] [--until T] [--json F]
prognos rul FLEET.parquet --group-by asset --column value --time-column t --threshold X --out R.csv

Run 'prognos COMMAND --help' for the options and examples of each command.
"""

from __future__ import annotations

import argparse
import math
import re
import sys
import warnings
from pathlib import Path

from ._command import check_output_file, check_overwrites, one_torch_thread, option_of
from ._text import fmt_time
from .cli_parser import (
    CALIBRATE_DEFAULTS,
    MODEL_RUL_DEFAULTS,
    PROGNOSE_RUL_DEFAULTS,
    add_fit,
    add_forecast,
    add_rul,
    add_study,
)
from .cli_prognose import (
    at_time,
    failure_dates,
    figure_file,
    json_record,
    json_text,
    reporter,
    within_probability,
    write_made,
)

__all__ = ["main", "build_parser"]


def _cmd_study(args) -> int:
    from .studies import StudyConfig, StudyDataError, discover_studies, run_study

    try:
        studies = discover_studies()
    except FileNotFoundError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if args.list or args.name is None:
        for name, st in studies.items():
            need = f" (needs --data: {st.needs_data})" if st.needs_data else ""
            print(f"{name:20s} paper {st.paper:8s} {st.title}{need}")
        if args.list:
            return 0
        print("error: study needs a NAME from the list above, or all", file=sys.stderr)
        return 2
    try:
        cfg = StudyConfig(
            runs=args.runs,
            quick=args.quick,
            out=args.out,
            device=args.device,
            seed=args.seed,
            progress=not args.no_progress,
            data=args.data,
        )
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if args.threads < 1:
        print(f"error: --threads must be a positive integer, got {args.threads}", file=sys.stderr)
        return 2
    if args.name == "all":  # studies of unshipped data run only when their data are given
        names = [n for n, st in studies.items() if st.missing_data(cfg) is None]
        for n in sorted(set(studies) - set(names)):
            print(f"[skipped {n}: it reads the {studies[n].needs_data}; give --data DIR]")
    else:
        names = [args.name]
    unknown = [n for n in names if n not in studies]
    if unknown:
        print(
            f"error: unknown study {unknown[0]!r}; valid: {', '.join(studies)} or all",
            file=sys.stderr,
        )
        return 2
    missing = [m for n in names if (m := studies[n].missing_data(cfg)) is not None]
    if missing:
        print(f"error: {missing[0]}", file=sys.stderr)
        return 2
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(args.threads)  # the caller's count is restored afterwards
    try:
        for n in names:
            try:
                _, text = run_study(studies[n], cfg)
            except (FileNotFoundError, StudyDataError) as exc:  # data that cannot serve it
                print(f"error: {exc}", file=sys.stderr)
                return 2
            print(text)
            print(f"[written to {Path(args.out) / n}]")
    finally:
        torch.set_num_threads(threads)
    return 0


# ----------------------------------------------------------------------------- fit / forecast / rul
class _CensoredRUL(Exception):
    pass


def _options(items, what: str) -> dict:
    """``KEY=VALUE`` strings -> dict; values parsed as int, float, bool or kept as strings."""
    out = {}
    for item in items or []:
        if "=" not in item:
            raise ValueError(f"{what}: expected KEY=VALUE, got {item!r}")
        key, text = (v.strip() for v in item.split("=", 1))
        if key in out:  # (the last one would win without a word)
            raise ValueError(f"{what}: {key} is given twice ({key}={out[key]!r}, {item.strip()})")
        value: object = text
        if text.lower() in ("true", "false"):
            value = text.lower() == "true"
        else:
            for conv in (int, float):
                try:
                    value = conv(text)
                    break
                except ValueError:
                    pass
        out[key] = value
    return out


def _whole(opts: dict, defaults: dict) -> dict:
    """``opts`` with a whole number in float notation (``n_hidden=1e3``, ``40.0``) as an int
    where the option counts (its default is an int; ``max_support``): ``_options`` reads
    ``1e3`` as the float 1000.0, which the learner refused ("must be an int"), as ``--holdout``
    reads it as a count."""
    for key, v in opts.items():
        count = key == "max_support" or type(defaults.get(key)) is int
        if count and isinstance(v, float) and math.isfinite(v) and v.is_integer():
            opts[key] = int(v)
    return opts


def _not_twice(opts: dict, key: str, option: str, what: str) -> None:
    """Refuse ``option`` where ``what`` sets ``key`` too (the option replaced it unsaid)."""
    if key in opts:
        raise ValueError(
            f"{option} and {what} {key}={opts[key]!r} both set {key}: give one of them"
        )


def _holdout(text: str):
    """``--holdout``: a count (``50``, also written ``5e1`` or ``50.0``) or a fraction in
    ``[0, 1)``; a value >= 1 that is not whole is neither (``1e3`` was read as the fraction
    1000.0 and refused)."""
    try:
        return int(text)
    except ValueError:
        pass
    try:
        value = float(text)
    except ValueError:
        raise ValueError(f"--holdout must be a fraction or a count, got {text!r}") from None
    if math.isfinite(value) and value >= 1.0:
        if not value.is_integer():
            raise ValueError(
                f"holdout must be a fraction in (0, 1) or a count (a whole number; 0 for none), "
                f"got {text!r}"
            )
        return int(value)
    return value  # (a fraction; a negative or non-finite value is fit_series' to refuse)


def _share(p: float) -> str:
    """A probability as a percentage to 3 digits (0.002: "0.2 %", where ".0f" said 0 %)."""
    return f"{100 * p:.3g} %"


def _fmt(v, digits: int = 4) -> str:
    if v is None:
        return "n/a"
    if isinstance(v, float):
        return f"{v:.{digits}g}"
    return str(v)


def _table(rows: list[tuple], header: tuple) -> str:
    cells = [tuple(str(c) for c in header)] + [tuple(_fmt(c) for c in r) for r in rows]
    widths = [max(len(r[j]) for r in cells) for j in range(len(header))]
    lines = ["  ".join(c.ljust(w) for c, w in zip(r, widths)).rstrip() for r in cells]
    lines.insert(1, "  ".join("-" * w for w in widths))
    return "\n".join(lines)


def _series_from_args(args, data_cfg: dict | None = None, *, truth: bool = False):
    """The series named by the data options (defaults: ``data_cfg``, the model's); with
    ``truth`` the same rows without ``--until`` and ``--last`` (what followed the origin)."""
    from .workflow import load_series, parse_where

    cfg = dict(data_cfg or {})
    column = args.column or cfg.get("column")
    time_column = args.time_column or cfg.get("time_column")
    where = parse_where(args.where if args.where else cfg.get("where") or None)
    fill = args.fill if args.fill is not None else cfg.get("fill")
    decimal = args.decimal or cfg.get("decimal") or "."
    # --time-format '' resets a model file's layout to ISO 8601
    given = args.time_format
    time_format = (given if given is not None else cfg.get("time_format")) or None
    inherited = [f"{k}={v!r}" for k, v, mine in (
        ("decimal", cfg.get("decimal"), args.decimal),
        ("time_format", cfg.get("time_format"), given)) if v and mine is None]  # fmt: skip
    try:
        series = load_series(
            args.data,
            column,
            time_column=time_column,
            where=where or None,
            fill=fill,
            last=None if truth else args.last,
            until=None if truth else args.until,
            decimal=decimal,
            time_format=time_format,
        )
    except ValueError as exc:
        if not inherited:
            raise
        raise ValueError(
            f"{exc} ({', '.join(inherited)} {'comes' if len(inherited) == 1 else 'come'} from "
            "the model file; --decimal . or "
            "--time-format '' read this file otherwise)"
        ) from None
    used = {"column": series.name, "time_column": time_column, "where": where, "fill": fill}
    if decimal != ".":  # model files of point-decimal data stay as they were
        used["decimal"] = decimal
    if time_format is not None:
        used["time_format"] = time_format
    return series, used


def _describe(series, data_cfg: dict) -> str:
    where = data_cfg.get("where") or {}
    sel = f" ({', '.join(f'{k}={v}' for k, v in where.items())})" if where else ""
    return f"{series.name!r}{sel} from {series.source}"


#: A time step longer than this many median steps is a recording gap worth a warning.
GAP_STEPS = 5.0


class RecordingGapWarning(UserWarning):
    """The rows of a series read by a learner are not evenly spaced (``warning:`` line)."""


class LookAheadWarning(UserWarning):
    """A backtest (``--until``) with a model trained on rows after the cut."""


class BacktestWarning(UserWarning):
    """A backtest (``--until``) whose cut leaves no rows after it to compare with."""


def _warn_nothing_after(truth, series, until) -> None:
    """One ``warning:`` line where ``--until`` lies at or after the last row: the backtest has
    nothing to score (its "observed RUL" would read "not reached in the data")."""
    if truth is None or float(truth.t[-1]) > float(series.t[-1]):
        return
    warnings.warn(
        f"--until {until}: the data end at t = {fmt_time(float(truth.t[-1]))}, at or before "
        "the cut, so there are no rows after it to compare with (a --until inside the data "
        "backtests)",
        BacktestWarning,
        stacklevel=2,
    )


class CapacityWarning(UserWarning):
    """A learner with more trained coefficients than training windows (``warning:`` line)."""


def _warn_gaps(series) -> None:
    """One ``warning:`` line on stderr where the rows are not evenly spaced: the learner's
    windows and the forecast's steps are rows, so each recording gap counts as one step."""
    import torch

    if series.time is None or len(series) < 3:
        return
    dt = torch.diff(series.time)
    step = float(dt.median())
    long = (dt > GAP_STEPS * step).nonzero()[:, 0]
    if not long.numel():
        return
    i = int(long[dt[long].argmax()])
    unit = series.time_unit
    warnings.warn(
        f"{long.numel()} recording gap(s) longer than {GAP_STEPS:g} median steps "
        f"({_fmt(step)} {unit}), the longest {_fmt(float(dt[i]))} {unit} after t = "
        f"{fmt_time(float(series.time[i]))}: the learner reads rows, so each gap counts as one "
        "step (prognos rul DATA.csv without a model file uses the times themselves)",
        RecordingGapWarning,
        stacklevel=2,
    )


def _fit_options(args) -> tuple[dict, dict]:
    """The learner's and the optimiser's options of ``prognos fit``: the defaults, then
    ``--learner-option``/``--optimizer-option``, then ``--max-support``/``--epochs`` (an option
    given twice, or one that does not apply, is refused by name)."""
    from .workflow.model import LEARNER_DEFAULTS, OPTIMIZER_DEFAULTS, check_names

    learner, optimizer = check_names(args.learner, args.optimizer)
    oopts = _whole(_options(args.optimizer_option, "--optimizer-option"),
                   OPTIMIZER_DEFAULTS[optimizer])  # fmt: skip
    if args.epochs is not None:
        if optimizer == "closed-form":
            raise ValueError(
                "--epochs applies to an iterative optimiser (--optimizer ekf, srukf, imsrukf, "
                f"adam or lbfgs); {args.learner}'s closed-form solve has none"
            )
        _not_twice(oopts, "epochs", "--epochs", "--optimizer-option")
        oopts["epochs"] = args.epochs
    lopts = _whole(_options(args.learner_option, "--learner-option"), LEARNER_DEFAULTS[learner])
    if args.max_support is not None:
        if learner != "lssvr":
            raise ValueError(f"--max-support applies to --learner lssvr, not {args.learner!r}")
        _not_twice(lopts, "max_support", "--max-support", "--learner-option")
        lopts["max_support"] = args.max_support
    return lopts, oopts


def _fit_report(model, series, data_cfg) -> None:
    """What ``prognos fit`` prints of a fitted model: its training, the choice of ``m`` and its
    scores on the held-out tail."""
    cfg = model.config
    span = float(model.scaler.data_max - model.scaler.data_min)
    n_hold = cfg["holdout"]["n"]
    n_train = cfg["series"]["n"] - n_hold  # (the scored model's; --refit's file has them all)
    sel = cfg["m_selection"]
    how, scores = "given", ""
    if sel is not None:
        c = sel["candidates"]
        how = f"chosen by one-step validation RMSE over m = {c[0]}..{c[-1]}"
        if sel.get("seconds") is not None:  # (each candidate is a fit: --embedding skips it)
            how += f" in {sel['seconds']:.2f} s (--embedding M skips the search)"
        scores = "validation RMSE by m: " + ", ".join(
            f"{m}: {_fmt(None if v is None else v * span, 3)}" for m, v in zip(c, sel["val_rmse"])
        )
    tr = cfg["train"]
    how_trained = (
        "closed-form solve" if cfg["optimizer"] == "closed-form" else f"{tr['epochs']} epoch(s)"
    )
    rows = [
        ("learner", f"{cfg['learner'].upper()} ({cfg['optimizer']})"),
        ("rows", f"{cfg['series']['n']} (training {n_train}, held out {n_hold})"),
        ("embedding m", f"{model.m}, {how}"),
        ("scaler range", f"[{_fmt(cfg['scaler']['data_min'])}, {_fmt(cfg['scaler']['data_max'])}]"),
        (
            "training",
            f"{how_trained}, {tr['seconds']:.2f} s, one-step RMSE "
            f"{_fmt(cfg['residual_rmse'] * span)}",
        ),
    ]
    sup = tr.get("support")
    if sup is not None:
        rows.append(
            (
                "support points",
                f"{sup['n_support']} (fixed-size LS-SVR, {sup['selection']} selection; "
                "--max-support to change)",
            )
        )
    print(f"fit {_describe(series, data_cfg)}")
    print(_table(rows, ("item", "value")))
    if scores:
        print(scores)
    mt = model.metrics
    if mt:
        part = "" if mt.get("tail", mt["horizon"]) == mt["horizon"] else f" (of {mt['tail']})"
        print(
            f"\nheld-out tail: {mt['horizon']} steps{part} forecast from the end of the training "
            "part"
        )
        print(
            _table(
                [
                    ("forecast RMSE", mt["rmse"]),
                    ("forecast MAE", mt["mae"]),
                    (f"{100 * mt['level']:g} % band coverage", mt["coverage"]),
                    ("one-step RMSE", mt["one_step_rmse"]),
                    ("persistence RMSE", mt["persistence_rmse"]),
                ],
                ("metric", "value"),
            )
        )


def _cmd_fit(args) -> int:
    from .workflow import fit_series, save_model

    check_output_file(args.out, "--out")
    check_overwrites({"--out": args.out}, {"the data file": args.data})
    series, data_cfg = _series_from_args(args)
    _warn_gaps(series)
    lopts, oopts = _fit_options(args)
    model = fit_series(
        series,
        args.learner,
        args.optimizer,
        args.embedding,
        holdout=_holdout(args.holdout),
        seed=args.seed,
        learner_options=lopts,
        optimizer_options=oopts,
        data=data_cfg,
        progress=None,  # bars on a terminal only: stderr stays one line per warning otherwise
        refit=args.refit,
    )
    _fit_report(model, series, data_cfg)
    cfg = model.config
    n_hold = cfg["holdout"]["n"]
    n_train = cfg["series"]["n"] - n_hold  # (the scored model's; --refit's file has them all)
    # trained coefficients (the LS-SVR has one per window by design, its C regularises them)
    n_coef = sum(p.numel() for p in model.learner.parameters() if p.requires_grad)
    windows = cfg["series"]["n_train"] - model.m
    if cfg["learner"] != "lssvr" and n_coef > windows:
        warnings.warn(
            f"the {cfg['learner'].upper()} has {n_coef:,} trained coefficients for {windows:,} "
            "training windows, so it can fit them exactly and its one-step RMSE says little; "
            "use a smaller --embedding or fewer hidden nodes (n_hidden) or membership "
            "functions (n_mfs)",
            CapacityWarning,
            stacklevel=2,
        )
    save_model(model, args.out)
    print(f"\nmodel written to {args.out}")
    if n_hold and cfg.get("refit"):
        print(f"(scored above as trained on the first {n_train} rows; the model written is "
              f"trained again on all {cfg['series']['n']})")  # fmt: skip
    elif n_hold:  # the file holds the model scored above, not one refitted on every row
        print(
            f"(the model is trained on the first {n_train} rows; the {n_hold} held out are "
            "not in it: --refit trains it again on every row after scoring, --holdout 0 "
            "trains on every row without a score)"
        )
    return 0


def _load_for_prediction(args):
    from .workflow import load_model

    for path, what in ((args.plot, "--plot"), (getattr(args, "csv", None), "--csv")):
        check_output_file(path, what)
    outputs = {"--plot": args.plot, "--csv": getattr(args, "csv", None)}
    outputs["--json"] = getattr(args, "json", None)
    check_overwrites(outputs, {"the model file": args.model, "the data file": args.data})
    model = load_model(args.model)
    series, data_cfg = _series_from_args(args, model.config.get("data"))
    _warn_gaps(series)
    # with --until, the rows after the cut are the truth to compare against
    truth = _series_from_args(args, data_cfg, truth=True)[0] if args.until else None
    _warn_nothing_after(truth, series, args.until)
    info = model.config.get("series") or {}
    end = info.get("t_train_end")  # (model files from before it was recorded: not checked)
    if truth is not None and end is not None and info.get("start") == series.start:
        if end > float(series.t[-1]):
            warnings.warn(
                f"the model was trained on rows up to t = {fmt_time(end)}, after the --until "
                f"cut at t = {fmt_time(float(series.t[-1]))}: the backtest's learner has seen "
                "the rows it is scored on (fit with the same --until for a fair backtest)",
                LookAheadWarning,
                stacklevel=2,
            )
    return model, series, data_cfg, truth


def _cmd_forecast(args) -> int:
    import torch

    from .workflow import forecast

    model, series, data_cfg, truth = _load_for_prediction(args)
    fc = forecast(
        model,
        series,
        args.horizon,
        level=args.level,
        filter=args.filter,
        filter_steps=args.filter_steps,
        n_particles=args.particles,
        seed=args.seed,
    )
    H = fc.horizon
    actual = actual_t = None
    if truth is not None:
        after, after_t = fc.observed(truth)
        actual = after if after.numel() else None
        off = fc.row_offset(truth)
        # after a recording gap the rows lie later than their steps: show their own times
        if actual is not None and off > 0.5 * series.dt:
            actual_t = after_t
    show = sorted({int(round(i * (H - 1) / 9)) for i in range(10)}) if H > 10 else range(H)
    header = ("step", f"time ({series.time_unit})", "mean", "lower", "upper")
    rows = []
    for i in show:
        row = (i + 1, fmt_time(float(fc.time[i])), float(fc.mean[i]), float(fc.lower[i]))
        row += (float(fc.upper[i]),)
        if actual is not None:
            row += (float(actual[i]) if i < actual.numel() else None,)
        if actual_t is not None:
            row += (fmt_time(float(actual_t[i])) if i < actual_t.numel() else None,)
        rows.append(row)
    if actual is not None:
        header += ("actual",)
    if actual_t is not None:
        header += ("at time",)
    unit = series.time_unit
    pct = f"{100 * fc.level:g} %"
    print(
        f"forecast of {_describe(series, data_cfg)}: {H} steps after t = "
        f"{fmt_time(float(series.t[-1]))} {unit}, {fc.filter.upper()}, {pct} band"
    )
    print(_table(rows, header))
    if len(rows) < H:
        print(f"({len(rows)} of the {H} steps shown; --csv FILE writes every step)")
    if actual is not None:
        n = actual.numel()
        err = (fc.mean[:n] - actual).square().mean().sqrt()
        inside = ((actual >= fc.lower[:n]) & (actual <= fc.upper[:n])).to(torch.float64).mean()
        last = series.values[-1].expand(n)
        pers = (last - actual).square().mean().sqrt()
        print(
            f"against the {n} observed values after t = {fmt_time(float(series.t[-1]))}: RMSE "
            f"{_fmt(float(err))}, band coverage {_fmt(float(inside))}, persistence RMSE "
            f"{_fmt(float(pers))}"
        )
    if actual_t is not None:
        print(
            f"the observed rows after t = {fmt_time(float(series.t[-1]))} are not one step "
            f"({_fmt(series.dt)} {unit}) apart: each is compared with the step of its row, "
            f"as the learner forecasts row by row (largest offset {_fmt(off)} {unit}, "
            f"{off / series.dt:.3g} steps)"
        )
    files = []
    if args.csv is not None:
        dated = series.start is not None  # a date-time column: each step's date-time too
        # with --until, the observed row each step is compared with and its own time
        n_obs = 0 if actual is None else actual.numel()

        def observed(i: int) -> str:
            if actual is None:
                return ""
            if i >= n_obs:
                return ",,"
            return f",{float(actual[i])!r},{float(after_t[i])!r}"

        lines = [
            "step,time,mean,lower,upper"
            + (",date" if dated else "")
            + (",actual,actual_time" if actual is not None else "")
        ] + [
            f"{i + 1},{float(fc.time[i])!r},{float(fc.mean[i])!r},{float(fc.lower[i])!r},"
            f"{float(fc.upper[i])!r}"
            + (f",{series.date(float(fc.time[i])) or ''}" if dated else "")
            + observed(i)
            for i in range(H)
        ]
        files.append((str(args.csv), ("\n".join(lines) + "\n").encode(), "forecast"))
    if args.plot is not None:
        from .workflow import plot_forecast

        files.append(figure_file(args.plot, plot_forecast(None, fc, truth=truth)))
    write_made(print, files)  # (both made first: a figure that cannot be made leaves no CSV)
    return 0


def _observed_rul(res, truth) -> str | float:
    """Time from the origin to the first later observation that reaches the threshold."""
    t, x = truth.t, truth.values
    after = t > res.t_last
    hit = (x >= res.threshold) if res.direction == "above" else (x <= res.threshold)
    idx = (after & hit).nonzero()
    if idx.numel() == 0:
        return "not reached in the data"
    return float(t[idx[0, 0]] - res.t_last)


def _cmd_rul(args) -> int:
    if args.json not in (None, "-"):
        check_output_file(args.json, "--json")
    if args.data is None:  # prognos rul DATA.csv ...: no model file
        return _rul_from_data(args)
    return _rul_from_model(args)


def _rul_from_data(args) -> int:
    """``prognos rul DATA.csv ...`` (no model file): ``prognose``, optionally calibrated on a
    table of failed histories (``cli_prognose``); options of the model-file path refused."""
    from .cli_prognose import load_histories, run_prognose

    given = [
        f"--{k.replace('_', '-')}"
        for k in MODEL_RUL_DEFAULTS
        if k != "filter" and getattr(args, k) is not None
    ]
    if given:
        raise ValueError(
            f"{', '.join(given)} {'apply' if len(given) > 1 else 'applies'} with a model "
            "file (prognos rul MODEL DATA.csv); "
            "without one, prognose sets its horizon from the observed life and filters "
            "every value since onset (--paths, --method, --filter, --seed, --direction apply)"
        )
    given = [f"--{k.replace('_', '-')}" for k in CALIBRATE_DEFAULTS
             if getattr(args, k) is not None]  # fmt: skip
    if given and args.calibrate is None:  # (they were ignored without a word)
        raise ValueError(
            f"{', '.join(given)} {'apply' if len(given) > 1 else 'applies'} with "
            "--calibrate TABLE: the replay of its histories"
        )
    for k, v in {**PROGNOSE_RUL_DEFAULTS, **CALIBRATE_DEFAULTS}.items():
        if getattr(args, k) is None:
            setattr(args, k, v)
    args.data = args.model
    check_output_file(args.plot, "--plot")
    check_output_file(args.calibration_out, "--calibration-out")
    check_overwrites(
        {"--plot": args.plot, "--calibration-out": args.calibration_out, "--json": args.json},
        {"the data file": args.data, "the --calibrate table": args.calibrate,
         "the --calibration file": args.calibration},
    )  # fmt: skip
    if args.workers < 1:
        raise ValueError(f"--workers must be >= 1 (processes), got {args.workers}")
    series, data_cfg = _series_from_args(args)
    truth = _series_from_args(args, data_cfg, truth=True)[0] if args.until else None
    _warn_nothing_after(truth, series, args.until)
    histories = load_histories(args, series)
    censored = run_prognose(args, series, data_cfg, truth, histories)
    if censored:
        raise _CensoredRUL(censored)
    return 0


def _check_model_rul_options(args) -> None:
    """With a model file, the options of ``prognose`` and its calibration are refused by name
    (they were ignored without a word)."""
    if args.glitch_limit is not None:
        raise ValueError(
            "--glitch-limit applies without a model file (prognos rul DATA.csv --column C ...): "
            "it sets prognose's healthy window"
        )
    if args.calibrate is not None or args.calibration is not None:
        raise ValueError(
            "--calibrate and --calibration apply without a model file (prognos rul DATA.csv --column C ...): it "
            "calibrates prognose's interval"
        )
    given = [f"--{k.replace('_', '-')}" for k in ("calibration_out", *CALIBRATE_DEFAULTS)
             if getattr(args, k) is not None]  # fmt: skip
    if given:  # (they were ignored without a word: no calibration file was written)
        raise ValueError(
            f"{', '.join(given)} {'apply' if len(given) > 1 else 'applies'} without a model "
            "file, with --calibrate TABLE (prognos rul DATA.csv --column C ... --calibrate "
            "TABLE): the calibration of prognose's interval"
        )
    given = [f"--{k}" for k in PROGNOSE_RUL_DEFAULTS if getattr(args, k) is not None]
    if given:
        raise ValueError(
            f"{', '.join(given)} {'apply' if len(given) > 1 else 'applies'} without a model "
            "file (prognos rul DATA.csv --column C "
            "...): they choose prognose's trend models and paths; with a model file the "
            "learner is the model and --particles the paths"
        )
    if isinstance(args.seed, tuple):
        raise ValueError(
            "--seed: several seeds pool prognose's models (prognos rul DATA.csv --column C "
            "...); with a model file give one seed for the particle draws"
        )


def _rul_from_model(args) -> int:
    """``prognos rul MODEL DATA.csv``: the fitted learner's particle-filter RUL (``workflow.rul``)."""
    from .workflow import rul

    _check_model_rul_options(args)
    for k, v in MODEL_RUL_DEFAULTS.items():
        if getattr(args, k) is None:
            setattr(args, k, v)
    model, series, data_cfg, truth = _load_for_prediction(args)
    res = rul(
        model,
        series,
        args.threshold,
        horizon=args.horizon,
        direction=args.direction,
        filter=args.filter,
        filter_steps=args.filter_steps,
        n_particles=args.particles,
        seed=args.seed,
    )
    unit, s = res.time_unit, res.summary()
    p_within, within = None, []
    if args.within is not None:
        p_within = within_probability(res, args.within, " (raise --horizon to look further)")
        within = [(f"P(failure within {args.within:g} {unit})", p_within)]
    cm = res.censored_mass
    mean = s["mean"]
    if mean is None:
        mean = (
            f"n/a ({_share(cm)} of paths do not reach the threshold in the horizon)"
            if cm > 0
            else "n/a"
        )
    d = failure_dates(res, series, res.bound)  # the dates a planner reads
    dates = [] if d is None else [("failure date, median (UTC)", d[1]),
                                  ("failure date, 5 % (UTC)", d[0]),
                                  ("failure date, 95 % (UTC)", d[2])]  # fmt: skip
    say = reporter(args)
    say(
        f"RUL of {_describe(series, data_cfg)} at t = {at_time(series, res.t_last, unit)}: threshold "
        f"{res.threshold:g} ({res.direction}), {res.filter.upper()} with {res.n_particles} "
        f"particles, horizon {res.horizon} steps = {res.bound:g} {unit}"
    )
    obs = None if truth is None else _observed_rul(res, truth)
    say(
        _table(
            [
                ("P(threshold reached within horizon)", res.crossing_probability),
                (f"mean RUL ({unit}, paper 002 Eq. 28)", mean),
                (f"median RUL ({unit})", s["median"]),
                (f"5 % quantile ({unit})", s["q05"]),
                (f"95 % quantile ({unit})", s["q95"]),
            ]
            + dates
            + within
            # (the paths are of the raw indicator: its first value at the threshold)
            + ([(f"observed RUL ({unit}, first value)", obs)] if truth is not None else []),
            ("quantity", "value"),
        )
    )
    files, record = [], None  # made first, written together (write_made)
    if args.plot is not None:
        from .workflow import plot_rul

        files.append(figure_file(args.plot, plot_rul(None, res)))
    if args.json is not None:
        extra = {"crossing_probability": res.crossing_probability,
                 # what made the answer: the model file and the settings it was run with
                 "model_file": {"path": str(args.model), "learner": model.config.get("learner"),
                                "m": model.m, "particles": res.n_particles,
                                "horizon_steps": res.horizon}}  # fmt: skip
        if args.within is not None:
            extra["p_within"] = {"within": args.within, "p": p_within}
        if truth is not None:
            extra["observed_rul"] = obs if isinstance(obs, float) else None
        record = json_text(json_record(res, series, data_cfg, **extra))
    write_made(say, files, args.json, record)
    if res.fully_censored:
        raise _CensoredRUL(
            f"no predicted path reaches the threshold {res.threshold:g} within the horizon of "
            f"{res.horizon} steps ({res.bound:g} {unit}); the RUL exceeds {res.bound:g} {unit} "
            "(raise --horizon to look further, or check --threshold)"
        )
    if cm > 0:
        raise _CensoredRUL(
            f"{100 * cm:.3g} % of the predicted paths do not reach the threshold "
            f"{res.threshold:g} within the horizon of {res.horizon} steps ({res.bound:g} "
            f"{unit}); their RUL exceeds {res.bound:g} {unit} and the mean is withheld (raise "
            "--horizon to look further)"
        )
    return 0


#: the first words of the workflow's messages about an argument and the options that set it:
#: an error about one names both
_OPTION_OF = {
    "n_particles": "--particles",
    "n_paths": "--paths",
    "horizon": "--horizon",
    "filter_steps": "--filter-steps",
    "level": "--level",
    "threshold must": "--threshold",  # (not "threshold 2 already reached": it names the value)
    "holdout": "--holdout",  # (holdout must ..., holdout=1000 leaves no training data)
    "embedding dimension m": "--embedding",
    "glitch_limit": "--glitch-limit",
    "method must": "--method",
    "direction must": "--direction",
    "until": "--until",
    "last must": "--last",
    "fill must": "--fill",
    "time_format": "--time-format",
    "seed": "--seed",  # (seed must lie in ..., seed names a seed twice)
}


def _workflow(cmd):
    """Run a workflow command: one-line errors on stderr, exit 2 (bad input) or 3 (censored);
    extrapolation warnings as one ``warning:`` line each."""

    def wrapped(args) -> int:
        with one_torch_thread():
            return run(args)

    def run(args) -> int:
        from .io import ModelFileError
        from .workflow.extrapolation import ExtrapolationWarning
        from .workflow.memory import allocation_failure
        from .workflow.predict import ThresholdWarning

        caught: list = []
        bad_input = (ValueError, TypeError, OSError, ModelFileError)
        try:
            try:
                with warnings.catch_warnings(record=True) as caught:
                    warnings.simplefilter("always", ExtrapolationWarning)
                    warnings.simplefilter("always", RecordingGapWarning)
                    warnings.simplefilter("always", ThresholdWarning)
                    return cmd(args)
            except bad_input:
                caught.clear()  # bad input: its one error: line stands alone on stderr
                raise
            finally:  # after the recording has ended: showing a warning no longer records it
                said = set()  # the library's own: one line each, each sentence once (a
                for w in caught:  # particle filter's fallback would repeat at every step)
                    if not w.category.__module__.startswith("prognos_torch"):
                        warnings.showwarning(
                            w.message, w.category, w.filename, w.lineno, w.file, w.line
                        )
                        continue
                    text = " ".join(str(w.message).split())
                    if text not in said:
                        said.add(text)
                        print(f"warning: {text}", file=sys.stderr)
        except _CensoredRUL as exc:
            print(f"censored RUL: {exc}", file=sys.stderr)
            return 3
        except bad_input as exc:
            text = " ".join(str(exc).split()) or type(exc).__name__
            option = option_of(text, _OPTION_OF)
            if option is not None:  # a message about an argument names the option that set it
                text = f"{option}: {text}"
            print(f"error: {text}", file=sys.stderr)
            return 2
        except (MemoryError, RuntimeError) as exc:
            text = allocation_failure(exc, str(getattr(args, "learner", "") or "").lower())
            if text is None:
                raise
            print(f"error: {text}", file=sys.stderr)
            return 2

    return wrapped


_cmd_fit = _workflow(_cmd_fit)
_cmd_forecast = _workflow(_cmd_forecast)
_cmd_rul = _workflow(_cmd_rul)


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        prog="prognos", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    sub = ap.add_subparsers(dest="command")
    add_study(sub, _cmd_study)
    add_fit(sub, _cmd_fit)
    add_forecast(sub, _cmd_forecast)
    add_rul(sub, _cmd_rul)
    return ap


def _join_negative_values(argv: list[str]) -> list[str]:
    """``--threshold -1e-3`` as ``--threshold=-1e-3``: argparse takes a value that starts with
    ``-`` for an option unless it reads like ``-5`` or ``-.5``, so ``-1e-3``, ``-inf`` and
    ``--seed -1,2`` failed with 'expected one argument'."""
    out = []
    for tok in argv:
        prev = out[-1] if out else ""
        number = tok[:1] == "-" and (tok[1:2].isdigit() or tok[1:2] == "." or tok[1:].lower()
                                     in ("inf", "infinity", "nan"))  # fmt: skip
        plain = re.fullmatch(r"-\d+|-\d*\.\d+", tok)  # (what argparse reads as a number)
        if number and not plain and prev.startswith("--") and len(prev) > 2 and "=" not in prev \
                and "--" not in out:  # fmt: skip
            out[-1] = f"{prev}={tok}"
        else:
            out.append(tok)
    return out


def main(argv: list[str] | None = None) -> int:
    argv = _join_negative_values(sys.argv[1:] if argv is None else list(argv))
    if argv[:1] == ["rul"] and any(a == "--group-by" or a.startswith("--group-by=") for a in argv):
        from .fleet.cli import main as fleet_main  # fleet mode: a long table, one RUL per asset

        return fleet_main(argv[1:])
    ap = build_parser()
    args = ap.parse_args(argv)
    if not getattr(args, "func", None):
        ap.print_help()
        return 2
    return args.func(args)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
