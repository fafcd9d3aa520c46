"""The parsers of the ``prognos`` commands: their options, help texts and examples.

Each ``add_*`` adds one command to the subparsers ``sub`` with ``cmd``, the function that runs
it (:mod:`prognos_torch.cli`); :data:`MODEL_RUL_DEFAULTS` are the options of ``prognos rul
MODEL DATA`` that ``prognos rul DATA.csv`` (``prognose``) refuses, :data:`PROGNOSE_RUL_DEFAULTS`
the other way round.
"""

from __future__ import annotations

import argparse
from pathlib import Path

__all__ = [
    "add_study",
    "add_fit",
    "add_forecast",
    "add_rul",
    "MODEL_RUL_DEFAULTS",
    "PROGNOSE_RUL_DEFAULTS",
    "CALIBRATE_DEFAULTS",
]


def add_study(sub, cmd) -> None:
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
    p.set_defaults(func=cmd)


_DATA_HELP = """data options (fit; forecast and rul reuse the model's unless given):
  DATA.csv has a header row; delimiter , ; or tab. Empty cells and nan/NA are missing values:
  an error unless --fill linear (interpolate) or --fill drop (remove the rows). The time column
  may hold numbers or ISO 8601 date-times (then time is in days since the first row).
  --where COL=VALUE keeps matching rows: how a long table (one row per snapshot and channel,
  like datasets/ims/test1_features.csv) becomes one series.
memory: a request whose estimated memory exceeds the budget (environment variable
  PROGNOS_MEMORY_BUDGET, e.g. 2G; default half the physical memory) is refused with exit 2.
exit status: 0 success; 2 bad input (one 'error:' line on stderr, nothing written); 3 censored
  RUL (rul with a model file: part or all of the distribution lies beyond the horizon, so its
  mean is withheld; without one: more than 5 % of it does, so its 95 % quantile is unknown; a
  smaller censored mass is reported, exit 0; the report and any --plot are written, and one
  'censored RUL:' line on stderr says how much).
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
        help="use only rows with time <= T (a number in the time unit, or an ISO date-time; "
        "one without an offset is UTC, as the reports' dates are); "
        "forecast and rul then also compare with the rows after T (backtesting; rul's observed "
        "RUL runs to the first later value at the threshold with a model file, to the first "
        "later 5-point moving median there without one, as prognose's end of life)",
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


def _data_command(sub, name: str, *, help: str, description: str, epilog: str):
    """A command that reads a series (fit, forecast, rul): its ``description`` wrapped, its
    ``epilog`` (examples) followed by the data options' help, laid out as written."""
    return sub.add_parser(
        name,
        help=help,
        description=_wrap(description),
        epilog=epilog + _DATA_HELP,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )


def add_fit(sub, cmd) -> None:
    p = _data_command(
        sub,
        "fit",
        help="fit a one-step forecaster to a CSV column and save it (safe model file)",
        description=(
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
        "srukf, imsrukf, adam, lbfgs.\n\n",
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
    g.add_argument(
        "--refit",
        action="store_true",
        help="after scoring the held-out values, train the model written again on every value "
        "(the same embedding and options): the model to forecast the latest level with",
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
    # output files are kept as text, not Path: Path("new/") drops the "/", and the file "new"
    # was written where a folder was meant (_command.check_output_file refuses it up front)
    p.add_argument("--out", required=True, help="model file to write")
    p.set_defaults(func=cmd)


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
    g.add_argument("--plot", help="figure to write (.png, .pdf or .svg)")  # (text: see --out)


def _seeds(text: str) -> int | tuple[int, ...]:
    """``--seed`` of ``prognos rul``: an int, or several joined by commas (pooled)."""
    try:
        parts = [int(v) for v in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected an int or ints joined by commas (0,1,2), got {text!r}"
        ) from None
    return parts[0] if len(parts) == 1 else tuple(parts)


def add_forecast(sub, cmd) -> None:
    p = _data_command(
        sub,
        "forecast",
        help="forecast the next steps of a series with an uncertainty band",
        description=(
            "Forecast HORIZON steps after the end of the series with a saved model: the "
            "learner as an m-order state-space model (paper 002), a filter over the last "
            "observations, then predict-only steps with a central band."
        ),
        epilog="examples:\n"
        "  prognos forecast model.pt data.csv --horizon 50 --plot forecast.png\n"
        "  prognos forecast model.pt data.csv --horizon 50 --filter stpf --csv forecast.csv\n"
        "  prognos forecast model.pt data.csv --until 120 --horizon 50 --plot backtest.png\n"
        "      (forecast from t = 120 and compare with the values observed after it)\n\n",
    )
    p.add_argument("model", type=Path, help="model file from prognos fit")
    p.add_argument("data", type=Path, help="CSV file")
    p.add_argument("--horizon", type=int, required=True, help="steps to forecast")
    p.add_argument("--level", type=float, default=0.95, help="band probability (default 0.95)")
    p.add_argument(
        "--csv",  # (text, not Path: see fit's --out)
        help="write every forecast step to this CSV (step, time, mean, lower, upper; date on "
        "date-times; with --until the observed value each step is compared with and its time)",
    )
    _add_data_options(p)
    _add_prediction_options(p, "sckf")
    p.set_defaults(func=cmd)


def add_rul(sub, cmd) -> None:
    p = _data_command(
        sub,
        "rul",
        help="remaining useful life distribution for a failure threshold",
        description=(
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
        "      (a fleet: one RUL per asset; see prognos rul --group-by ASSET --help)\n\n",
    )
    p.add_argument("model", type=Path, help="model file from prognos fit, or the CSV file")
    p.add_argument("data", type=Path, nargs="?", help="CSV file (with a model file)")
    p.add_argument(
        "--method",
        help="without a model file: auto (exponential + elm pool; the default), exponential, "
        "power, linear, elm",
    )
    p.add_argument("--paths", type=int, help="without a model file: sample paths (2000)")
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
        metavar="COL",
        help="asset column of the --calibrate table (default asset)",
    )
    g.add_argument(
        "--calibrate-where",
        action="append",
        metavar="COL=VALUE",
        help="keep the --calibrate table's rows whose COL equals VALUE (repeatable), e.g. "
        "--calibrate-where channel=5 (--where selects the series' rows)",
    )
    g.add_argument(
        "--calibrate-threshold",
        choices=("same", "protocol"),
        help="failure of a history: the first crossing of --threshold by its 5-point moving "
        "median (same, default), or of 0.9 x its highest moving median (protocol: the bearing "
        "studies' rule, for a rising indicator)",
    )
    g.add_argument(
        "--workers",
        type=int,
        metavar="N",
        help="with --calibrate: replay the histories in N processes side by side (default 1); "
        "the calibration is the same",
    )
    g.add_argument(
        "--calibration-out",  # (text, not Path: see fit's --out)
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
    # None: not given (prognose, without a model file, refuses these; with one, the defaults;
    # and the other way round for PROGNOSE_RUL_DEFAULTS)
    # (and CALIBRATE_DEFAULTS: given without --calibrate, they are refused)
    p.set_defaults(func=cmd, **{k: None for k in MODEL_RUL_DEFAULTS})


#: the options of ``prognos rul MODEL DATA`` and their defaults there; ``prognos rul DATA``
#: (prognose) refuses all but ``--filter``, which names its trend models' filters (default ekf)
MODEL_RUL_DEFAULTS = {"horizon": 200, "filter": "stpf", "filter_steps": 100, "particles": 500}
#: the options of ``prognos rul DATA`` (prognose) alone and their defaults there; ``prognos rul
#: MODEL DATA`` refuses them
PROGNOSE_RUL_DEFAULTS = {"method": "auto", "paths": 2000}
#: the options that set how ``--calibrate`` replays its histories and their defaults; without
#: ``--calibrate`` (and with a model file) they are refused
CALIBRATE_DEFAULTS = {"calibrate_group": "asset", "calibrate_where": None,
                      "calibrate_threshold": "same", "workers": 1}  # fmt: skip
