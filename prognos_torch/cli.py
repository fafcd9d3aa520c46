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
import sys
import warnings
from pathlib import Path

from ._text import fmt_time
from .cli_prognose import (
    at_time,
    failure_dates,
    json_record,
    reporter,
    within_probability,
    write_json,
)

__all__ = ["main", "build_parser"]


def _add_study(sub) -> None:
    p = sub.add_parser(
        "study",
        help="reproduce a paper's experiment and write table.md, results.csv, run.json, figures",
        description="Run a study (one per paper) and write its table and figures.",
        epilog="examples:\n  prognos study --list\n  prognos study elm-stsckf --quick\n"
        "  prognos study anfis-training --runs 50 --out results",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("name", nargs="?", help="study name, or 'all'")
    p.add_argument("--list", action="store_true", help="list the studies and exit")
    p.add_argument("--runs", type=int, default=None, help="Monte Carlo runs (default: the paper's)")
    p.add_argument("--quick", action="store_true", help="reduced protocol (smoke test)")
    p.add_argument("--out", type=Path, default=Path("results"), help="output folder")
    p.add_argument("--device", default="cpu", help="cpu or cuda")
    p.add_argument("--seed", type=int, default=0, help="base seed")
    p.add_argument(
        "--data",
        type=Path,
        default=None,
        help="folder of a local copy of an external dataset, for the studies that read one "
        "(pronostia-rul: the PRONOSTIA / FEMTO bearing records)",
    )
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    p.add_argument(
        "--threads",
        type=int,
        default=1,
        help="torch CPU threads (default 1: the filters work on many tiny matrices, and extra "
        "threads slow the batched runs, most of all on a busy machine; run.json records it)",
    )
    p.set_defaults(func=_cmd_study)


def _cmd_study(args) -> int:
    from .studies import StudyConfig, discover_studies, run_study

    try:
        studies = discover_studies()
    except FileNotFoundError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if args.list or args.name is None:
        for name, st in studies.items():
            need = f" (needs --data: {st.needs_data})" if st.needs_data else ""
            print(f"{name:20s} paper {st.paper:8s} {st.title}{need}")
        return 0 if args.list else 2
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
            except FileNotFoundError as exc:  # a --data folder without the study's data
                print(f"error: {exc}", file=sys.stderr)
                return 2
            print(text)
            print(f"[written to {Path(args.out) / n}]")
    finally:
        torch.set_num_threads(threads)
    return 0


# ----------------------------------------------------------------------------- fit / forecast / rul
_DATA_HELP = """data options (fit; forecast and rul reuse the model's unless given):
  DATA.csv has a header row; delimiter , ; or tab. Empty cells and nan/NA are missing values:
  an error unless --fill linear (interpolate) or --fill drop (remove the rows). The time column
  may hold numbers or ISO 8601 date-times (then time is in days since the first row).
  --where COL=VALUE keeps matching rows: how a long table (one row per snapshot and channel,
  like datasets/ims/test1_features.csv) becomes one series.
memory: a request whose estimated memory exceeds the budget (environment variable
  PROGNOS_MEMORY_BUDGET, e.g. 2G; default half the physical memory) is refused with exit 2.
exit status: 0 success; 2 bad input (one 'error:' line on stderr, nothing written); 3 censored
  RUL (rul: part or all of the distribution lies beyond the horizon, so its mean is withheld;
  the report and any --plot are written, and one 'censored RUL:' line on stderr says how much).
  A 'warning:' line on stderr (exit 0) flags a forecast that leaves the training range."""


def _wrap(text: str) -> str:
    import textwrap

    return textwrap.fill(text, 92)


def _add_data_options(p) -> None:
    g = p.add_argument_group("data")
    g.add_argument(
        "--column",
        help="value column (fit: may be omitted when the file has one other column; "
        "forecast, rul: default the model's)",
    )
    g.add_argument("--time-column", help="time column: numbers or ISO 8601 date-times")
    g.add_argument(
        "--where",
        action="append",
        metavar="COL=VALUE",
        help="keep rows whose COL equals VALUE (repeatable), e.g. --where channel=5",
    )
    g.add_argument("--last", type=int, metavar="N", help="use only the last N rows")
    g.add_argument(
        "--until",
        metavar="T",
        help="use only rows with time <= T (a number in the time unit, or an ISO date-time); "
        "forecast and rul then also compare with the rows after T (backtesting)",
    )
    g.add_argument(
        "--fill", metavar="linear|drop", help="handle missing values: interpolate or drop rows"
    )
    g.add_argument(
        "--time-format",
        metavar="FMT",
        help="layout of date-times that are not ISO 8601, in strptime codes, e.g. "
        "'%%d/%%m/%%Y %%H:%%M' (default: the model's, else numbers or ISO 8601)",
    )
    g.add_argument(
        "--decimal",
        choices=(".", ","),
        help="the CSV's decimal mark (default: the model's, else '.'); ',' reads 0,25 as 0.25 "
        "(tables with a ';' or tab delimiter from European locales)",
    )


def _add_fit(sub) -> None:
    p = sub.add_parser(
        "fit",
        help="fit a one-step forecaster to a CSV column and save it (safe model file)",
        description=_wrap(
            "Fit a learner (ELM, LS-SVR, ANFIS) to one column of a CSV file: min-max scaling, "
            "embedding dimension chosen by validation error unless --embedding is given, "
            "training by the chosen optimiser, scores on the held-out tail, and a model file "
            "that holds the learner's tensors and its configuration (JSON, never pickle)."
        ),
        epilog="examples:\n"
        "  prognos fit data.csv --column hi --time-column t --out model.pt\n"
        "  prognos fit data.csv --column hi --learner anfis --optimizer imsrukf --out model.pt\n"
        "  prognos fit datasets/ims/test1_features.csv --column rms --where channel=5 \\\n"
        "      --time-column timestamp --learner elm --out ims.pt\n"
        "  prognos fit data.csv --column hi --learner elm --learner-option n_hidden=40 "
        "--out m.pt\n\n"
        "learners and their default optimisers: elm (closed-form ridge), lssvr (closed-form "
        "KKT solve),\n  anfis (ekf, one pass, paper 003 settings). optimisers: closed-form, ekf, "
        "srukf, imsrukf, adam, lbfgs.\n\n" + _DATA_HELP,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("data", type=Path, help="CSV file")
    _add_data_options(p)
    g = p.add_argument_group("model")
    g.add_argument("--learner", default="anfis", help="elm, lssvr or anfis (default anfis)")
    g.add_argument(
        "--optimizer",
        help="closed-form, ekf, srukf, imsrukf, adam or lbfgs (default: the learner's)",
    )
    g.add_argument(
        "--embedding", "-m", type=int, help="embedding dimension m (default: by validation)"
    )
    g.add_argument("--epochs", type=int, help="passes of an iterative optimiser")
    g.add_argument(
        "--holdout",
        default="0.2",
        help="final values kept for evaluation: a fraction (0.2) or a count (50); 0 for none",
    )
    g.add_argument("--seed", type=int, default=0, help="seed of initialisation and sampling")
    g.add_argument(
        "--max-support",
        type=int,
        metavar="M",
        help="LS-SVR: exact KKT solve up to M training values, a fixed-size LS-SVR on M "
        "support points above (default: exact up to 2000 values, else 50 points)",
    )
    g.add_argument(
        "--learner-option", action="append", metavar="KEY=VALUE", help="e.g. n_hidden=40"
    )
    g.add_argument("--optimizer-option", action="append", metavar="KEY=VALUE", help="e.g. R=1e-2")
    p.add_argument("--out", type=Path, required=True, help="model file to write")
    p.set_defaults(func=_cmd_fit)


def _add_prediction_options(p, default_filter: str) -> None:
    g = p.add_argument_group("prediction")
    g.add_argument(
        "--filter",
        default=default_filter,
        help=f"sckf, stsckf, ukf, ekf, pf, ekpf, stpf, upf (default {default_filter})"
        + (
            "; without a model file, the filter of prognose's trend models: ekf (default), "
            "stekf (strong tracking), or several joined by + (ekf+stekf) to pool their RULs"
            if default_filter == "stpf"
            else ""
        ),
    )
    g.add_argument(
        "--filter-steps",
        type=int,
        default=100,
        help="observations filtered before predicting (default 100)",
    )
    g.add_argument("--particles", type=int, default=500, help="particles (default 500)")
    rul = default_filter == "stpf"  # (the rul command)
    g.add_argument(
        "--seed",
        type=_seeds if rul else int,
        help="seed of the particle draws (default: the model's)"
        + (
            "; without a model file, prognose's seed (default 0), or several joined by commas "
            "(0,1,2) to pool the models each seed fits: a steadier answer"
            if rul
            else ""
        ),
    )
    g.add_argument("--plot", type=Path, help="PNG figure to write")


def _seeds(text: str) -> int | tuple[int, ...]:
    """``--seed`` of ``prognos rul``: an int, or several joined by commas (pooled)."""
    try:
        parts = [int(v) for v in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected an int or ints joined by commas (0,1,2), got {text!r}"
        ) from None
    return parts[0] if len(parts) == 1 else tuple(parts)


def _add_forecast(sub) -> None:
    p = sub.add_parser(
        "forecast",
        help="forecast the next steps of a series with an uncertainty band",
        description=_wrap(
            "Forecast HORIZON steps after the end of the series with a saved model: the "
            "learner as an m-order state-space model (paper 002), a filter over the last "
            "observations, then predict-only steps with a central band."
        ),
        epilog="examples:\n"
        "  prognos forecast model.pt data.csv --horizon 50 --plot forecast.png\n"
        "  prognos forecast model.pt data.csv --horizon 50 --filter stpf --csv forecast.csv\n"
        "  prognos forecast model.pt data.csv --until 120 --horizon 50 --plot backtest.png\n"
        "      (forecast from t = 120 and compare with the values observed after it)\n\n"
        + _DATA_HELP,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("model", type=Path, help="model file from prognos fit")
    p.add_argument("data", type=Path, help="CSV file")
    p.add_argument("--horizon", type=int, required=True, help="steps to forecast")
    p.add_argument("--level", type=float, default=0.95, help="band probability (default 0.95)")
    p.add_argument("--csv", type=Path, help="write every forecast step to this CSV")
    _add_data_options(p)
    _add_prediction_options(p, "sckf")
    p.set_defaults(func=_cmd_forecast)


def _add_rul(sub) -> None:
    p = sub.add_parser(
        "rul",
        help="remaining useful life distribution for a failure threshold",
        description=_wrap(
            "RUL distribution at the end of the series: a filter over the last observations, "
            "sample paths of the learner's state-space model, and the first passage of each "
            "path through the threshold (paper 002, Eq. 28). Paths that do not reach the "
            "threshold within the horizon are censored: their RUL is only known to exceed "
            "horizon x dt, and the mean is withheld while any mass is censored."
        ),
        epilog="examples:\n"
        "  prognos rul data.csv --column rms --time-column timestamp --threshold 0.45\n"
        "      (no model file: degradation onset, trend models chosen by backtest, RUL paths;\n"
        "       see prognos_torch.workflow.prognose)\n"
        "  prognos rul data.csv --column rms --time-column timestamp --threshold 0.45 --within 7\n"
        "      (also P(failure within 7 days), e.g. before the next inspection)\n"
        "  prognos rul data.csv --column rms --time-column timestamp --threshold 0.45 \\\n"
        "      --filter ekf+stekf   (pooled with strong tracking: wider, for sudden surges)\n"
        "  prognos rul data.csv --column rms --time-column timestamp --threshold 0.45 \\\n"
        "      --calibrate failed.csv --calibrate-group bearing\n"
        "      (the 90 % interval calibrated on assets that ran to failure: split conformal)\n"
        "  prognos rul data.csv --column rms --time-column timestamp --threshold 0.45 \\\n"
        "      --json rul.json   (also the answer as one JSON record; --json - prints it alone)\n"
        "  prognos rul datasets/ims/test1_features.csv --column rms --where channel=5 \\\n"
        "      --time-column timestamp --threshold 0.45 --until 2003-11-25T00:00:00\n"
        "  prognos rul model.pt data.csv --threshold 0.8 --plot rul.png\n"
        "  prognos rul model.pt data.csv --threshold 0.8 --filter pf --horizon 400\n"
        "  prognos rul fleet.parquet --group-by asset --threshold 20 --out rul.parquet\n"
        "      (a fleet: one RUL per asset; see prognos rul --group-by ASSET --help)\n\n"
        + _DATA_HELP,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("model", type=Path, help="model file from prognos fit, or the CSV file")
    p.add_argument("data", type=Path, nargs="?", help="CSV file (with a model file)")
    p.add_argument(
        "--method",
        default="auto",
        help="without a model file: auto (exponential + elm pool), exponential, power, linear, elm",
    )
    p.add_argument(
        "--paths", type=int, default=2000, help="without a model file: sample paths (2000)"
    )
    p.add_argument("--threshold", type=float, required=True, help="failure threshold")
    p.add_argument(
        "--glitch-limit",
        type=float,
        metavar="L",
        help="without a model file: leave isolated values more than L noise std from their "
        "neighbours (sensor glitches) out of the healthy window's statistics (default: every "
        "value counts, and a warning names glitches beyond 20 that widen the band 1.5 times)",
    )
    p.add_argument(
        "--direction",
        default="auto",
        help="above, below or auto (with a model file: above when the threshold exceeds the "
        "last value; without one: the side of the healthy band the threshold lies on)",
    )
    p.add_argument("--horizon", type=int, default=200, help="steps predicted (default 200)")
    p.add_argument(
        "--within",
        type=float,
        metavar="SPAN",
        help="also print P(failure within SPAN), SPAN in the RUL's time unit (an inspection "
        "interval, say)",
    )
    p.add_argument(
        "--json",
        metavar="FILE",
        help="also write the result as one JSON record to FILE (written whole or not at all): "
        "the data's source, RULResult.to_dict() (status, onset, model, RUL quantiles, censored "
        "mass and bound, failure dates, flags) and the report's further rows; '-' writes it to "
        "standard output in place of the report",
    )
    g = p.add_argument_group("calibration (without a model file)")
    g.add_argument(
        "--calibrate",
        type=Path,
        metavar="TABLE",
        help="run-to-failure histories of assets like this one, a long CSV or Parquet table "
        "(--calibrate-group, --time-column, --column): each is replayed through prognose at "
        "20/40/60/80/90 %% of [onset, failure], and the 90 %% interval is widened or narrowed "
        "by the conformal margin of its misses there (prognos_torch.workflow.calibrate_rul)",
    )
    g.add_argument(
        "--calibrate-group",
        default="asset",
        metavar="COL",
        help="asset column of the --calibrate table (default asset)",
    )
    g.add_argument(
        "--calibrate-threshold",
        choices=("same", "protocol"),
        default="same",
        help="failure of a history: the first crossing of --threshold by its 5-point moving "
        "median (same, default), or of 0.9 x its highest moving median (protocol: the bearing "
        "studies' rule, for a rising indicator)",
    )
    g.add_argument(
        "--workers",
        type=int,
        default=1,
        metavar="N",
        help="with --calibrate: replay the histories in N processes side by side (default 1); "
        "the calibration is the same",
    )
    g.add_argument(
        "--calibration-out",
        type=Path,
        metavar="FILE",
        help="with --calibrate: also write the calibration (its margin and the settings it "
        "holds for) to this JSON file, for --calibration",
    )
    g.add_argument(
        "--calibration",
        type=Path,
        metavar="FILE",
        help="a calibration written by --calibration-out, instead of --calibrate (refused "
        "when this run's method, filter, paths, direction or threshold differ from its own)",
    )
    _add_data_options(p)
    _add_prediction_options(p, "stpf")
    # None: not given (prognose, without a model file, refuses these; with one, the defaults)
    p.set_defaults(func=_cmd_rul, **{k: None for k in _MODEL_RUL_DEFAULTS})


#: the options of ``prognos rul MODEL DATA`` and their defaults there; ``prognos rul DATA``
#: (prognose) refuses all but ``--filter``, which names its trend models' filters (default ekf)
_MODEL_RUL_DEFAULTS = {"horizon": 200, "filter": "stpf", "filter_steps": 100, "particles": 500}


class _CensoredRUL(Exception):
    pass


def _options(items, what: str) -> dict:
    """``KEY=VALUE`` strings -> dict; values parsed as int, float, bool or kept as strings."""
    out = {}
    for item in items or []:
        if "=" not in item:
            raise ValueError(f"{what}: expected KEY=VALUE, got {item!r}")
        key, text = (v.strip() for v in item.split("=", 1))
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


def _holdout(text: str):
    try:
        return int(text)
    except ValueError:
        pass
    try:
        return float(text)
    except ValueError:
        raise ValueError(f"--holdout must be a fraction or a count, got {text!r}") from None


def _check_out_folder(path: Path | None, what: str) -> None:
    if path is None:
        return
    folder = path.parent if str(path.parent) else Path(".")
    if not folder.is_dir():
        raise FileNotFoundError(f"{what}: folder {folder} does not exist")
    if path.is_dir():
        raise ValueError(f"{what}: {path} is a folder, expected a file name")


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
    time_format = args.time_format or cfg.get("time_format")
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


def _cmd_fit(args) -> int:
    from .workflow import fit_series, save_model

    _check_out_folder(args.out, "--out")
    series, data_cfg = _series_from_args(args)
    oopts = _options(args.optimizer_option, "--optimizer-option")
    if args.epochs is not None:
        oopts["epochs"] = args.epochs
    lopts = _options(args.learner_option, "--learner-option")
    if args.max_support is not None:
        if str(args.learner).lower() != "lssvr":
            raise ValueError(f"--max-support applies to --learner lssvr, not {args.learner!r}")
        lopts["max_support"] = args.max_support
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
    )
    cfg = model.config
    span = float(model.scaler.data_max - model.scaler.data_min)
    n_train, n_hold = cfg["series"]["n_train"], cfg["holdout"]["n"]
    sel = cfg["m_selection"]
    how, scores = "given", ""
    if sel is not None:
        c = sel["candidates"]
        how = f"chosen by one-step validation RMSE over m = {c[0]}..{c[-1]}"
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
    save_model(model, args.out)
    print(f"\nmodel written to {args.out}")
    return 0


def _load_for_prediction(args):
    from .workflow import load_model

    for path, what in ((args.plot, "--plot"), (getattr(args, "csv", None), "--csv")):
        _check_out_folder(path, what)
    model = load_model(args.model)
    series, data_cfg = _series_from_args(args, model.config.get("data"))
    # with --until, the rows after the cut are the truth to compare against
    truth = _series_from_args(args, data_cfg, truth=True)[0] if args.until else None
    return model, series, data_cfg, truth


def _cmd_forecast(args) -> int:
    import torch

    from .io import atomic_write
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
    actual = None
    if truth is not None:
        after = truth.values[truth.t > series.t[-1]][:H]
        actual = after if after.numel() else None
    show = sorted({int(round(i * (H - 1) / 9)) for i in range(10)}) if H > 10 else range(H)
    header = ("step", f"time ({series.time_unit})", "mean", "lower", "upper")
    rows = []
    for i in show:
        row = (i + 1, float(fc.time[i]), float(fc.mean[i]), float(fc.lower[i]))
        row += (float(fc.upper[i]),)
        if actual is not None:
            row += (float(actual[i]) if i < actual.numel() else None,)
        rows.append(row)
    if actual is not None:
        header += ("actual",)
    unit = series.time_unit
    pct = f"{100 * fc.level:g} %"
    print(
        f"forecast of {_describe(series, data_cfg)}: {H} steps after t = "
        f"{fmt_time(float(series.t[-1]))} {unit}, {fc.filter.upper()}, {pct} band"
    )
    print(_table(rows, header))
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
    if args.csv is not None:
        dated = series.start is not None  # a date-time column: each step's date-time too
        lines = ["step,time,mean,lower,upper" + (",date" if dated else "")] + [
            f"{i + 1},{float(fc.time[i])!r},{float(fc.mean[i])!r},{float(fc.lower[i])!r},"
            f"{float(fc.upper[i])!r}"
            + (f",{series.date(float(fc.time[i])) or ''}" if dated else "")
            for i in range(H)
        ]
        atomic_write(args.csv, ("\n".join(lines) + "\n").encode())
        print(f"forecast written to {args.csv}")
    if args.plot is not None:
        from .workflow import plot_forecast

        plot_forecast(args.plot, fc, truth=truth)
        print(f"figure written to {args.plot}")
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
    from .workflow import rul

    if args.json not in (None, "-"):
        _check_out_folder(Path(args.json), "--json")
    if args.data is None:  # prognos rul DATA.csv ...: no model file
        from .cli_prognose import load_histories, run_prognose

        given = [
            f"--{k.replace('_', '-')}"
            for k in _MODEL_RUL_DEFAULTS
            if k != "filter" and getattr(args, k) is not None
        ]
        if given:
            raise ValueError(
                f"{', '.join(given)} apply with a model file (prognos rul MODEL DATA.csv); "
                "without one, prognose sets its horizon from the observed life and filters "
                "every value since onset (--paths, --method, --filter, --seed, --direction apply)"
            )
        args.data = args.model
        _check_out_folder(args.plot, "--plot")
        _check_out_folder(args.calibration_out, "--calibration-out")
        if args.workers < 1:
            raise ValueError(f"--workers must be >= 1 (processes), got {args.workers}")
        series, data_cfg = _series_from_args(args)
        truth = _series_from_args(args, data_cfg, truth=True)[0] if args.until else None
        histories = load_histories(args, series)
        censored = run_prognose(args, series, data_cfg, truth, histories)
        if censored:
            raise _CensoredRUL(censored)
        return 0
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
    if isinstance(args.seed, tuple):
        raise ValueError(
            "--seed: several seeds pool prognose's models (prognos rul DATA.csv --column C "
            "...); with a model file give one seed for the particle draws"
        )
    for k, v in _MODEL_RUL_DEFAULTS.items():
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
    within = [] if args.within is None else [(
        f"P(failure within {args.within:g} {unit})",
        within_probability(res, args.within, " (raise --horizon to look further)"),
    )]  # fmt: skip
    cm = res.censored_mass
    mean = s["mean"]
    if mean is None:
        mean = (
            f"n/a ({100 * cm:.0f} % of paths do not reach the threshold in the horizon)"
            if cm > 0
            else "n/a"
        )
    d = failure_dates(res, series, res.bound)  # the dates a planner reads
    dates = [] if d is None else [("failure date, median", d[1]), ("failure date, 5 %", d[0]),
                                  ("failure date, 95 %", d[2])]  # fmt: skip
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
            + ([("observed RUL (" + unit + ")", obs)] if truth is not None else []),
            ("quantity", "value"),
        )
    )
    if args.plot is not None:
        from .workflow import plot_rul

        plot_rul(args.plot, res)
        say(f"figure written to {args.plot}")
    if args.json is not None:
        extra = {"crossing_probability": res.crossing_probability}
        if args.within is not None:
            extra["p_within"] = {"within": args.within, "p": within[0][1]}
        if truth is not None:
            extra["observed_rul"] = obs if isinstance(obs, float) else None
        write_json(args.json, json_record(res, series, data_cfg, **extra))
        if args.json != "-":
            say(f"record written to {args.json}")
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


def _workflow(cmd):
    """Run a workflow command: one-line errors on stderr, exit 2 (bad input) or 3 (censored);
    extrapolation warnings as one ``warning:`` line each."""

    def wrapped(args) -> int:
        import torch

        from .io import ModelFileError
        from .workflow.extrapolation import ExtrapolationWarning
        from .workflow.memory import allocation_failure

        torch.set_num_threads(1)  # tiny matrices: threads only add overhead (see tests/conftest)
        caught: list = []
        try:
            try:
                with warnings.catch_warnings(record=True) as caught:
                    warnings.simplefilter("always", ExtrapolationWarning)
                    return cmd(args)
            finally:  # after the recording has ended: showing a warning no longer records it
                for w in caught:
                    if issubclass(w.category, ExtrapolationWarning):
                        print(f"warning: {w.message}", file=sys.stderr)
                    else:
                        warnings.showwarning(
                            w.message, w.category, w.filename, w.lineno, w.file, w.line
                        )
        except _CensoredRUL as exc:
            print(f"censored RUL: {exc}", file=sys.stderr)
            return 3
        except (ValueError, TypeError, OSError, ModelFileError) as exc:
            text = " ".join(str(exc).split()) or type(exc).__name__
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
    _add_study(sub)
    _add_fit(sub)
    _add_forecast(sub)
    _add_rul(sub)
    return ap


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
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
