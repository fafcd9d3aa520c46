"""``prognos fit | forecast | rul``: end to end, the shipped IMS table, and bad input.

Bad input must give exit status 2, exactly one ``error:`` line on stderr, and leave the output
folder as it was; a censored RUL gives 3 and one ``censored RUL:`` line, its report written.
"""

from __future__ import annotations

import csv
import os
import pickle
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from prognos_torch.cli import main
from prognos_torch.datasets import default_data_dir
from prognos_torch.workflow import forecast, load_model, load_series
from prognos_torch.workflow import rul as rul_fn

IMS = default_data_dir() / "test1_features.csv"


def _make_csv(path: Path, T: int = 120, gaps=(), bad=None) -> np.ndarray:
    rng = np.random.default_rng(1)
    t = np.arange(T) * 0.5
    x = 1.0 + 0.01 * t + 0.3 * np.sin(2 * np.pi * t / 12) + 0.03 * rng.standard_normal(T)
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["hours", "vibration", "temp"])
        for i in range(T):
            v = "" if i in gaps else (bad if bad is not None and i == 7 else repr(float(x[i])))
            w.writerow([repr(float(t[i])), v, "20"])
    return x


def _read_forecast_csv(path: Path) -> dict[str, torch.Tensor]:
    with open(path) as fh:
        rows = list(csv.DictReader(fh))
    return {k: torch.tensor([float(r[k]) for r in rows], dtype=torch.float64) for k in rows[0]}


def _one_error_line(capsys, pattern: str) -> str:
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    assert err.startswith("error: ")
    assert pattern in err, err
    return err


def test_cli_end_to_end_and_identical_forecast_in_a_fresh_process(tmp_path, capsys):
    data = tmp_path / "data.csv"
    _make_csv(data)
    model = tmp_path / "model.pt"
    fit = ["fit", str(data), "--column", "vibration", "--time-column", "hours"]
    fit += ["--learner", "anfis", "--optimizer", "imsrukf", "--embedding", "2", "--out", str(model)]
    assert main(fit) == 0
    out = capsys.readouterr().out
    assert "ANFIS (imsrukf)" in out and "forecast RMSE" in out and "persistence RMSE" in out

    fc_csv, fc_png = tmp_path / "fc.csv", tmp_path / "fc.png"
    args = ["forecast", str(model), str(data), "--horizon", "25"]
    assert main(args + ["--csv", str(fc_csv), "--plot", str(fc_png)]) == 0
    out = capsys.readouterr().out
    assert "25 steps after t = 59.5 hours, SCKF, 95 % band" in out
    assert fc_png.read_bytes()[:4] == b"\x89PNG"
    got = _read_forecast_csv(fc_csv)
    ref = forecast(load_model(model), load_series(data, "vibration", time_column="hours"), 25)
    for k in ("mean", "lower", "upper"):
        assert torch.equal(got[k], getattr(ref, k))
    assert torch.equal(got["time"], ref.time)

    # a fresh process loads the file and writes the identical forecast
    fresh = tmp_path / "fresh.csv"
    env = dict(os.environ, OMP_NUM_THREADS="1")
    subprocess.run(
        [sys.executable, "-m", "prognos_torch.cli", *args, "--csv", str(fresh)],
        check=True,
        capture_output=True,
        env=env,
        timeout=120,
    )
    assert fresh.read_bytes() == fc_csv.read_bytes()

    rul_png = tmp_path / "rul.png"
    rul = ["rul", str(model), str(data), "--threshold", "1.6", "--horizon", "60"]
    rul += ["--filter", "pf", "--particles", "100", "--filter-steps", "20", "--plot", str(rul_png)]
    code = main(rul)
    captured = capsys.readouterr()
    out = captured.out
    assert "threshold 1.6 (above), PF with 100 particles, horizon 60 steps = 30 hours" in out
    assert "P(threshold reached within horizon)" in out and rul_png.exists()
    # exit 3 exactly when part of the distribution is censored (then the mean is withheld)
    censored = any(ln.startswith("mean RUL") and "n/a" in ln for ln in out.splitlines())
    assert code == (3 if censored else 0)
    if censored:
        assert captured.err.startswith("censored RUL: ") and "the mean is withheld" in captured.err


def test_cli_on_the_shipped_ims_table(tmp_path, capsys):
    model, png = tmp_path / "ims.pt", tmp_path / "ims_forecast.png"
    sel = ["--column", "rms", "--where", "channel=5", "--time-column", "timestamp"]
    sel += ["--until", "33.3"]
    fit = ["fit", str(IMS), *sel, "--last", "300", "--learner", "elm", "--embedding", "4"]
    assert main(fit + ["--holdout", "30", "--out", str(model)]) == 0
    out = capsys.readouterr().out
    assert "'rms' (channel=5)" in out and "300 (training 270, held out 30)" in out
    # forecast and rul read the same column and rows from the model file's data options
    assert main(["forecast", str(model), str(IMS), "--until", "33.3", "--horizon", "20",
                 "--plot", str(png)]) == 0  # fmt: skip
    out = capsys.readouterr().out
    assert "against the 20 observed values after t = 33.29939815" in out
    assert png.read_bytes()[:4] == b"\x89PNG"
    rul = ["rul", str(model), str(IMS), "--until", "33.3", "--threshold", "0.18"]
    rul += ["--filter", "pf", "--particles", "100", "--filter-steps", "20", "--horizon", "150"]
    assert main(rul) == 0
    out = capsys.readouterr().out
    lines = {ln.split("  ")[0]: ln for ln in out.splitlines()}
    assert "P(threshold reached within horizon)" in lines
    assert "median RUL (days)" in lines and "observed RUL (days, first value)" in lines
    median = float(lines["median RUL (days)"].split()[-1])
    assert 0 < median <= 150 * 10 / 1440 + 1e-9  # within the horizon (10-minute steps)
    # --within: P(RUL <= 0.5 d) of the same distribution; beyond the horizon it is refused
    # before anything is printed when paths are censored
    series = load_series(IMS, "rms", time_column="timestamp", where={"channel": 5}, until=33.3)
    ref = rul_fn(load_model(model), series, 0.18, horizon=150, filter="pf", n_particles=100,
                 filter_steps=20)  # fmt: skip
    assert main(rul + ["--within", "0.5"]) == 0
    out = capsys.readouterr().out
    row = [ln for ln in out.splitlines() if ln.startswith("P(failure within 0.5 days)")]
    far = ["rul", str(model), str(IMS), "--until", "33.3", "--threshold", "0.3", "--filter",
           "pf", "--particles", "100", "--horizon", "50", "--within", "5"]  # fmt: skip
    assert main(far) == 2  # every path censored within 50 steps (0.35 d): P(5 d) is unknown
    err = capsys.readouterr()
    assert err.out == "" and err.err.startswith("error: --within: within = 5 days lies beyond")
    assert err.err.rstrip().endswith("(raise --horizon to look further)")
    assert row and float(row[0].split()[-1]) == pytest.approx(
        ref.failure_probability(0.5), rel=1e-3, abs=1e-4
    )


@pytest.mark.parametrize(
    "case",
    [
        "missing_file",
        "missing_column",
        "non_numeric",
        "nan_gaps",
        "too_short",
        "unknown_learner",
        "unknown_optimizer",
        "pickle_model",
        "missing_out_folder",
        "option_of_the_wrong_kind",
        "epochs_of_a_closed_form_solve",
    ],
)
def test_cli_bad_input_one_line_error_nothing_written(tmp_path, capsys, case):
    data = tmp_path / "data.csv"
    out = tmp_path / "model.pt"
    fit = ["fit", str(data), "--column", "vibration", "--time-column", "hours", "--learner"]
    fit += ["elm", "--out", str(out)]
    marker = tmp_path / "marker"
    if case == "missing_file":
        argv, pattern = fit, f"data file not found: {data}"
    elif case == "missing_column":
        _make_csv(data)
        argv = [a if a != "vibration" else "vib" for a in fit]
        pattern = "no column 'vib'; columns: hours, vibration, temp"
    elif case == "non_numeric":
        _make_csv(data, bad="n/a?")
        argv, pattern = fit, "line 9: column 'vibration' value 'n/a?' is not a number"
    elif case == "nan_gaps":
        _make_csv(data, gaps=(10, 11, 50))
        argv = fit
        pattern = "3 missing value(s) at line(s) 12, 13, 52; pass fill='linear'"
    elif case == "too_short":
        _make_csv(data, T=4)
        argv = fit + ["--embedding", "4"]
        pattern = "has 4 values; embedding m=4 needs at least m + 1 = 5"
    elif case == "unknown_learner":
        _make_csv(data)
        argv = [a if a != "elm" else "xgboost" for a in fit]
        pattern = "unknown learner 'xgboost'; choose one of elm, lssvr, anfis"
    elif case == "unknown_optimizer":
        _make_csv(data)
        argv = fit + ["--optimizer", "rmsprop"]
        pattern = "unknown optimizer 'rmsprop'; choose one of closed-form, ekf"
    elif case == "pickle_model":
        _make_csv(data)

        class Evil:
            def __reduce__(self):
                return (exec, (f"open({str(marker)!r}, 'w').close()",))

        out.write_bytes(pickle.dumps(Evil()))
        argv = ["forecast", str(out), str(data), "--horizon", "5", "--plot"]
        argv += [str(tmp_path / "f.png")]
        pattern = "is not a prognos model file: it looks like a Python pickle"
    elif case == "option_of_the_wrong_kind":  # (it was int()'s own message)
        _make_csv(data)
        argv = fit + ["--learner-option", "n_hidden=abc"]
        pattern = "elm learner option n_hidden must be an int (like 20), got 'abc'"
    elif case == "epochs_of_a_closed_form_solve":  # (it named an empty list of options)
        _make_csv(data)
        argv = fit + ["--epochs", "5"]
        pattern = "--epochs applies to an iterative optimiser"
    else:
        _make_csv(data)
        argv = [a if a != str(out) else str(tmp_path / "no" / "model.pt") for a in fit]
        pattern = "--out: folder"
    before = sorted(p.name for p in tmp_path.iterdir())
    assert main(argv) == 2
    _one_error_line(capsys, pattern)
    assert sorted(p.name for p in tmp_path.iterdir()) == before
    assert not marker.exists()


def test_cli_fill_censored_rul_and_help(tmp_path, capsys):
    data = tmp_path / "data.csv"
    _make_csv(data, gaps=(10, 11))
    model = tmp_path / "m.pt"
    base = ["--column", "vibration", "--time-column", "hours", "--fill", "linear"]
    assert main(["fit", str(data), *base, "--learner", "elm", "-m", "3", "--out", str(model)]) == 0
    capsys.readouterr()
    png = tmp_path / "rul.png"
    argv = ["rul", str(model), str(data), "--threshold", "1e6", "--horizon", "30"]
    argv += ["--filter", "sckf", "--particles", "50", "--plot", str(png)]
    assert main(argv) == 3
    captured = capsys.readouterr()
    assert "n/a (100 % of paths do not reach the threshold in the horizon)" in captured.out
    warned, err = captured.err.strip().splitlines()  # the threshold far beyond the range
    assert warned.startswith("warning: the threshold 1e+06 lies outside the model's training")
    assert err.startswith(
        "censored RUL: no predicted path reaches the threshold 1e+06 within the horizon "
        "of 30 steps (15 hours); the RUL exceeds 15 hours"
    )
    assert png.exists()  # the (complete) figure shows the paths that stay below
    argv = ["rul", str(model), str(data), "--threshold", "-5", "--direction", "above"]
    assert main(argv) == 2
    _one_error_line(capsys, "already reaches the threshold -5 (direction 'above')")
    for cmd, example in (
        ("fit", "prognos fit data.csv --column hi --learner anfis --optimizer imsrukf"),
        ("forecast", "prognos forecast model.pt data.csv --horizon 50 --plot forecast.png"),
        ("rul", "prognos rul model.pt data.csv --threshold 0.8 --plot rul.png"),
    ):
        with pytest.raises(SystemExit) as exc:
            main([cmd, "--help"])
        assert exc.value.code == 0
        assert example in capsys.readouterr().out


def test_cli_reads_decimal_commas_and_the_model_keeps_the_mark(tmp_path, capsys):
    """A ';'-delimited table with decimal commas (as European locales write it) gives, with
    --decimal ',', the forecast of the same table written with points; the model file keeps
    the mark, so forecast needs no option; without it the error names the option."""
    point, comma = tmp_path / "point.csv", tmp_path / "comma.csv"
    _make_csv(point)
    rows = [r.split(",") for r in point.read_text().splitlines()]
    comma.write_text("".join(";".join(c.replace(".", ",") for c in r) + "\n" for r in rows))
    base = ["--column", "vibration", "--time-column", "hours", "--learner", "elm", "-m", "3"]
    forecasts = []
    for data, mark in ((point, []), (comma, ["--decimal", ","])):
        model, fc = tmp_path / f"{data.stem}.pt", tmp_path / f"{data.stem}_fc.csv"
        assert main(["fit", str(data), *base, *mark, "--out", str(model)]) == 0
        assert main(["forecast", str(model), str(data), "--horizon", "5", "--csv", str(fc)]) == 0
        forecasts.append(fc.read_bytes())
    assert forecasts[0] == forecasts[1]
    capsys.readouterr()
    assert main(["fit", str(comma), *base, "--out", str(tmp_path / "x.pt")]) == 2
    _one_error_line(capsys, "is not a number; a decimal comma? pass decimal=',' (--decimal ,")
    assert not (tmp_path / "x.pt").exists()


def _zoned_csv(path: Path, zone: str) -> Path:
    rows = ["ts,rms"]
    for i in range(60):
        v = 1.0 + 0.01 * (i % 7) + (0.05 * (i - 40) if i > 40 else 0.0)
        h = i // 60 + (1 if zone == "+01:00" else 0)
        rows.append(f"2024-01-01T{h:02d}:{i % 60:02d}:00{zone},{v}")
    path.write_text("\n".join(rows) + "\n")
    return path


def test_cli_rul_from_a_model_prints_failure_dates_on_date_times(tmp_path, capsys):
    """On a date-time column the model-file report gives the last row's date-time and the
    failure dates, each the last time plus its RUL quantile (NumPy's arithmetic here), and the
    forecast file each step's date-time."""
    data, model = _zoned_csv(tmp_path / "z.csv", "Z"), tmp_path / "m.pt"
    base = ["--column", "rms", "--time-column", "ts", "--learner", "elm", "-m", "3"]
    assert main(["fit", str(data), *base, "--out", str(model)]) == 0
    fc = tmp_path / "fc.csv"
    assert main(["forecast", str(model), str(data), "--horizon", "3", "--csv", str(fc)]) == 0
    rows = list(csv.DictReader(fc.open()))
    assert [r["date"] for r in rows] == ["2024-01-01T01:00:00", "2024-01-01T01:01:00",
                                         "2024-01-01T01:02:00"]  # fmt: skip
    capsys.readouterr()
    argv = ["rul", str(model), str(data), "--threshold", "2", "--horizon", "200"]
    assert main([*argv, "--particles", "200"]) in (0, 3)
    out = capsys.readouterr().out
    assert "at t = 0.04097222222 days (2024-01-01T00:59:00 UTC): threshold 2" in out
    last = np.datetime64("2024-01-01T00:59:00")
    rows = dict(re.findall(r"^(median RUL \(days\)|failure date, median \(UTC\))\s+(\S+)$", out,
                           re.M))  # fmt: skip
    assert len(rows) == 2, out
    want = last + np.timedelta64(round(float(rows["median RUL (days)"]) * 86400), "s")
    # (the report prints the median to 4 digits: a minute is 7e-4 days)
    got = np.datetime64(rows["failure date, median (UTC)"])
    assert abs((got - want) / np.timedelta64(1, "s")) <= 60


def test_cli_rul_with_time_zones_and_warnings_ends(tmp_path, capsys):
    """ISO times with a zone (Z, +01:00) are the same instants as in UTC: the same report.
    A warning raised inside a command used to loop forever (it was re-shown while still being
    recorded); a time zone raised one (so the +01:00 run is a process of its own under
    ``-W always``, the others run here)."""
    args = ["rul", "--method", "exponential"]
    opts = ["--column", "rms", "--time-column", "ts", "--threshold", "5"]
    outs = []
    for zone in ("", "Z"):
        csv_path = _zoned_csv(tmp_path / f"z{len(zone)}.csv", zone)
        assert main([*args, str(csv_path), *opts]) in (0, 3)
        outs.append(capsys.readouterr().out.split("\n", 1)[1])  # after the header (file name)
    csv_path = _zoned_csv(tmp_path / "z6.csv", "+01:00")
    proc = subprocess.run(
        [sys.executable, "-W", "always", "-m", "prognos_torch", *args, str(csv_path), *opts],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert proc.returncode in (0, 3), proc.stderr[-2000:]
    outs.append(proc.stdout.split("\n", 1)[1])
    assert outs[0] == outs[1] == outs[2]
    code = (
        "import warnings, sys\n"
        "from prognos_torch import cli\n"
        "def noisy(args):\n"
        "    warnings.warn('a warning inside the command')\n"
        "    return 0\n"
        "sys.exit(cli._workflow(noisy)(None))\n"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0 and proc.stderr.count("a warning inside the command") == 1


def test_cli_rul_without_a_model_refuses_options_it_would_ignore(tmp_path, capsys):
    csv_path = _zoned_csv(tmp_path / "s.csv", "")
    base = ["rul", str(csv_path), "--column", "rms", "--time-column", "ts", "--threshold", "5"]
    for extra, named in ((["--horizon", "5"], "--horizon"), (["--filter", "pf"], "--filter"),
                         (["--particles", "3"], "--particles")):  # fmt: skip
        assert main([*base, *extra]) == 2
        err = capsys.readouterr().err
        assert err.startswith("error: ") and named in err and err.count("\n") == 1


def test_cli_rul_with_a_model_refuses_prognose_options_and_where_names_a_column_once(
    tmp_path, capsys
):
    """--method and --paths choose prognose's models and paths: with a model file they were
    ignored without a word. --where twice on one column kept the last value only."""
    data = tmp_path / "data.csv"
    _make_csv(data)
    model = tmp_path / "m.pt"
    assert main(["fit", str(data), "--column", "vibration", "--time-column", "hours",
                 "--learner", "elm", "--out", str(model)]) == 0  # fmt: skip
    capsys.readouterr()
    base = ["rul", str(model), str(data), "--threshold", "1.6"]
    for extra, err_text in ((["--paths", "10"], "error: --paths applies without a model file"),
                            (["--method", "linear", "--paths", "10"],
                             "error: --method, --paths apply without a model file")):  # fmt: skip
        assert main([*base, *extra]) == 2
        cap = capsys.readouterr()
        assert cap.out == "" and cap.err.startswith(err_text) and cap.err.count("\n") == 1
    where = ["rul", str(IMS), "--column", "rms", "--time-column", "timestamp", "--threshold",
             "0.45", "--where", "channel=5", "--where", "channel=6"]  # fmt: skip
    assert main(where) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: where: column 'channel' is named twice (channel=5, channel=6)")
    with pytest.raises(ValueError, match="column 'channel' is named twice"):
        load_series(IMS, "rms", where=["channel=5", "channel=5"])


def test_cli_rul_from_a_model_writes_its_record_as_json(tmp_path, capsys):
    """--json FILE: the model-file result as one JSON record, the report's numbers (the same
    run repeated through the library) and the failure dates; '-' gives the record alone."""
    import json

    from prognos_torch.workflow import ExtrapolationWarning, load_series, rul

    data, model = _zoned_csv(tmp_path / "z.csv", "Z"), tmp_path / "m.pt"
    base = ["--column", "rms", "--time-column", "ts", "--learner", "elm", "-m", "3"]
    assert main(["fit", str(data), *base, "--out", str(model)]) == 0
    rec_path = tmp_path / "r.json"
    argv = ["rul", str(model), str(data), "--threshold", "2", "--horizon", "200",
            "--particles", "200", "--within", "0.05"]  # fmt: skip
    capsys.readouterr()
    code = main([*argv, "--json", str(rec_path)])
    out = capsys.readouterr().out
    assert code in (0, 3) and out.rstrip().endswith(f"record written to {rec_path}")
    rec = json.loads(rec_path.read_text())
    with pytest.warns(ExtrapolationWarning) as seen:  # the data left the training range
        res = rul(load_model(model), load_series(data, "rms", time_column="ts"), 2.0,
                  horizon=200, filter="stpf", filter_steps=100, n_particles=200)  # fmt: skip
    # the data and the threshold 2 both lie beyond the training range
    assert rec["flags"] == list(res.flags) == [str(w.message) for w in seen]
    assert len(seen) == 2 and rec["flags"][1].startswith("the threshold 2 lies outside")
    s = res.summary()
    assert rec["source"] == str(data) and rec["column"] == "rms" and rec["where"] == {}
    assert rec["date"] == "2024-01-01T00:59:00" and rec["onset"] is None
    assert rec["time_zone"] == "UTC"  # (the file's offsets applied when read)
    # what made the answer (the record did not name the model file or its settings)
    assert rec["model_file"] == {"path": str(model), "learner": "elm", "m": 3,
                                 "particles": 200, "horizon_steps": 200}  # fmt: skip
    for k in ("median", "q05", "q95", "mean", "censored_mass", "bound"):
        assert rec["rul"][k] == s[k], k
    assert rec["crossing_probability"] == res.crossing_probability
    assert rec["p_within"] == {"within": 0.05, "p": res.failure_probability(0.05)}
    assert rec["failure_date"]["median"] == res.failure_date(0.5) is not None
    # '-': the record alone on standard output, the same record
    assert main([*argv, "--json", "-"]) == code
    assert json.loads(capsys.readouterr().out) == rec


def test_cli_rul_on_monthly_dates_with_a_horizon_of_centuries(tmp_path, capsys):
    """Monthly readings and --horizon 5000 steps (about 400 years): the report's dates lie
    beyond 2262, where nanosecond date-times end; it raised an OverflowError."""
    rng = np.random.default_rng(0)
    stamps = np.datetime64("2000-01-01") + (np.arange(120) * 30).astype("timedelta64[D]")
    y = 1 + 0.001 * np.arange(120) + 0.01 * rng.standard_normal(120)
    data, model = tmp_path / "monthly.csv", tmp_path / "m.pt"
    data.write_text("t,v\n" + "".join(f"{a},{float(b)!r}\n" for a, b in zip(stamps, y)))
    assert main(["fit", str(data), "--column", "v", "--time-column", "t", "--learner", "elm",
                 "--out", str(model)]) == 0  # fmt: skip
    rec = tmp_path / "r.json"
    argv = ["rul", str(model), str(data), "--threshold", "1.5", "--horizon", "5000",
            "--particles", "100", "--json", str(rec)]  # fmt: skip
    assert main(argv) in (0, 3)
    out = capsys.readouterr().out
    assert "failure date, median" in out
    import json

    bound = json.loads(rec.read_text())["failure_date"]["bound"]
    assert json.loads(rec.read_text())["time_zone"] == "UTC"
    rec_num = tmp_path / "n.json"  # numeric time: no dates, no zone
    numeric = tmp_path / "numeric.csv"
    numeric.write_text("t,v\n" + "".join(f"{i},{float(b)!r}\n" for i, b in enumerate(y)))
    assert main(["rul", str(model), str(numeric), "--column", "v", "--time-column", "t",
                 "--threshold", "1.5", "--particles", "50", "--json", str(rec_num)]) in (0, 3)  # fmt: skip
    num = json.loads(rec_num.read_text())
    assert num["time_zone"] is None and num["date"] is None
    want = stamps[-1] + np.timedelta64(5000 * 30, "D")  # dt = 30 days, 5000 steps
    assert np.datetime64(bound) == want and int(bound[:4]) > 2262


def test_cli_forecast_after_a_recording_gap_shows_the_rows_it_compares(tmp_path, capsys):
    """The learner forecasts row by row: after a recording gap, row k after the origin is
    compared with step k although it lies later than ``t_last + k dt``. The table then shows
    each row's own time and says so; on a regular series it does not."""
    x = _make_csv(tmp_path / "regular.csv", T=120)
    gap = tmp_path / "gap.csv"  # the same values, the rows from 100 on 7.5 hours later
    t = np.arange(120) * 0.5 + np.where(np.arange(120) >= 100, 7.5, 0.0)
    gap.write_text("hours,vibration\n" + "".join(f"{float(a)!r},{float(b)!r}\n" for a, b in zip(t, x)))
    model = tmp_path / "m.pt"
    assert main(["fit", str(gap), "--column", "vibration", "--time-column", "hours", "--until",
                 "45", "--learner", "elm", "--out", str(model)]) == 0  # fmt: skip
    capsys.readouterr()
    png, fc_csv = tmp_path / "fc.png", tmp_path / "fc.csv"
    argv = ["forecast", str(model), str(gap), "--until", "45", "--horizon", "12"]
    assert main(argv + ["--plot", str(png), "--csv", str(fc_csv)]) == 0
    out, err = capsys.readouterr()
    assert err == ""  # the rows read end before the gap; the report's sentence covers the rest
    fc = forecast(load_model(model), load_series(gap, "vibration", time_column="hours",
                                                 until=45), 12)  # fmt: skip
    truth = load_series(gap, "vibration", time_column="hours")
    vals, times = fc.observed(truth)
    assert torch.equal(vals, torch.tensor(x[91:103]))  # rows 91..102, whatever their times
    assert torch.equal(times, truth.t[91:103])
    assert fc.row_offset(truth) == pytest.approx(7.5)  # rows 100.. sit 15 steps late
    header = next(ln for ln in out.splitlines() if ln.startswith("step"))
    assert header.rstrip().endswith("actual  at time")
    rows = [ln.split() for ln in out.splitlines() if ln[:1].isdigit()]
    assert rows and all(float(r[-1]) == float(times[int(r[0]) - 1]) for r in rows)
    assert "are not one step (0.5 hours) apart" in out and "15 steps)" in out
    assert "(10 of the 12 steps shown; --csv FILE writes every step)" in out
    got = _read_forecast_csv(fc_csv)  # every step with the row it is compared with
    assert torch.equal(got["actual"], vals) and torch.equal(got["actual_time"], times)
    assert torch.equal(got["mean"], fc.mean) and torch.equal(got["time"], fc.time)
    assert png.read_bytes()[:4] == b"\x89PNG"
    # the regular series: the rows keep their steps, no extra column, no sentence
    regular = ["forecast", str(model), str(tmp_path / "regular.csv"), "--until", "45",
               "--horizon", "12"]  # fmt: skip
    assert main(regular) == 0
    out, err = capsys.readouterr()
    assert "at time" not in out and "not one step" not in out and "actual" in out
    assert err == ""
    # rows read across the gap: one warning line (the learner takes the gap as one step)
    assert main(["forecast", str(model), str(gap), "--horizon", "3"]) == 0
    assert capsys.readouterr().err == (
        "warning: 1 recording gap(s) longer than 5 median steps (0.5 hours), the longest 8 "
        "hours after t = 49.5: the learner reads rows, so each gap counts as one step (prognos "
        "rul DATA.csv without a model file uses the times themselves)\n"
    )
    # bad input: its one error: line alone, the warnings of the run it stopped are dropped
    assert main(["forecast", str(model), str(gap), "--horizon", "3", "--level", "2"]) == 2
    _one_error_line(capsys, "--level: level must be a number in (0, 1)")


def test_cli_errors_about_an_argument_name_its_option(tmp_path, capsys):
    """The workflow's messages name its arguments (n_particles); on the command line they
    name the option too (--particles)."""
    data, model = tmp_path / "data.csv", tmp_path / "m.pt"
    _make_csv(data)
    assert main(["fit", str(data), "--column", "vibration", "--time-column", "hours",
                 "--learner", "elm", "--out", str(model)]) == 0  # fmt: skip
    capsys.readouterr()
    for extra, text in (
        (["rul", "--threshold", "3", "--particles", "0"], "--particles: n_particles must be"),
        (["forecast", "--horizon", "3", "--level", "2"], "--level: level must be a number"),
        (["forecast", "--horizon", "3", "--filter-steps", "-1"], "--filter-steps: filter_steps"),
    ):
        assert main([extra[0], str(model), str(data), *extra[1:]]) == 2
        _one_error_line(capsys, text)
    without = ["rul", str(data), "--column", "vibration", "--time-column", "hours",
               "--threshold", "3", "--paths", "2"]  # fmt: skip
    assert main(without) == 2
    _one_error_line(capsys, "--paths: n_paths must be an int >= 10, got 2")


def test_cli_plot_writes_the_format_its_suffix_names(tmp_path, capsys):
    """--plot x.pdf wrote PNG bytes under a .pdf name; now .pdf and .svg are written as such
    and another suffix is refused before anything runs."""
    data, model = tmp_path / "data.csv", tmp_path / "m.pt"
    _make_csv(data)
    assert main(["fit", str(data), "--column", "vibration", "--time-column", "hours",
                 "--learner", "elm", "--out", str(model)]) == 0  # fmt: skip
    base = ["forecast", str(model), str(data), "--horizon", "5", "--plot"]
    for name, magic in (("f.png", b"\x89PNG"), ("f.pdf", b"%PDF"), ("f.svg", b"<?xml")):
        assert main(base + [str(tmp_path / name)]) == 0
        assert (tmp_path / name).read_bytes()[: len(magic)] == magic
    capsys.readouterr()
    before = sorted(p.name for p in tmp_path.iterdir())
    assert main(base + [str(tmp_path / "f.jpeg")]) == 2
    _one_error_line(capsys, "--plot: 'f.jpeg' has the suffix '.jpeg'; figures are written as "
                    ".png, .pdf or .svg")  # fmt: skip
    assert sorted(p.name for p in tmp_path.iterdir()) == before


def test_cli_second_pass_refusals_flags_and_report_lines(tmp_path, capsys):
    """A threshold beyond the training range came with no flag; one particle gave a band of
    zero width; the forecast table printed 4 digits of the time; 0.2 % censored read 0 %; a
    repeated option key, a negative holdout or an out-of-range seed were taken or raised
    torch's message; an over-sized learner was fitted and written without a word."""
    data, model = tmp_path / "data.csv", tmp_path / "m.pt"
    _make_csv(data)
    assert main(["fit", str(data), "--column", "vibration", "--time-column", "hours",
                 "--learner", "elm", "--out", str(model)]) == 0  # fmt: skip
    out = capsys.readouterr().out
    assert "(the model is trained on the first 96 rows; the 24 held out are not in it" in out
    assert main(["fit", str(data), "--column", "vibration", "--time-column", "hours",
                 "--learner", "elm", "--refit", "--out", str(tmp_path / "r.pt")]) == 0  # fmt: skip
    assert ("(scored above as trained on the first 96 rows; the model written is trained again "
            "on all 120)") in capsys.readouterr().out  # fmt: skip
    rul = ["rul", str(model), str(data), "--threshold", "3", "--filter", "sckf", "--json"]
    assert main(rul + [str(tmp_path / "r.json")]) in (0, 3)
    err = capsys.readouterr().err
    assert "warning: the threshold 3 lies outside the model's training range" in err
    import json

    flags = json.loads((tmp_path / "r.json").read_text())["flags"]
    assert any(f.startswith("the threshold 3 lies outside") for f in flags)
    assert main(["forecast", str(model), str(data), "--horizon", "3", "--filter", "pf",
                 "--particles", "1"]) == 2  # fmt: skip
    _one_error_line(capsys, "--particles: n_particles must be an int >= 10, got 1")
    clock = tmp_path / "clock.csv"  # Unix seconds: every step's time kept to the second
    x = _make_csv(tmp_path / "tmp.csv")
    clock.write_text("t,v\n" + "".join(f"{1.7e9 + 600 * i:.0f},{float(v)!r}\n"
                                       for i, v in enumerate(x)))  # fmt: skip
    cm = tmp_path / "c.pt"
    assert main(["fit", str(clock), "--column", "v", "--time-column", "t", "--learner", "elm",
                 "--out", str(cm)]) == 0  # fmt: skip
    capsys.readouterr()
    assert main(["forecast", str(cm), str(clock), "--horizon", "2"]) == 0
    table = capsys.readouterr().out
    last = 1.7e9 + 600 * 119
    assert f"1     {last + 600:.0f}" in table and f"2     {last + 1200:.0f}" in table
    fit = ["fit", str(data), "--column", "vibration", "--time-column", "hours", "--out",
           str(tmp_path / "x.pt")]  # fmt: skip
    for extra, text in (
        (["--learner", "elm", "--learner-option", "n_hidden=3", "--learner-option",
          "n_hidden=4"], "--learner-option: n_hidden is given twice (n_hidden=3, n_hidden=4)"),
        (["--learner", "elm", "--holdout", "-1"], "holdout must be a fraction in [0, 1) or a "
         "count >= 0, got -1"),
        (["--learner", "elm", "--seed", "99999999999999999999"], "seed must lie in [-2**63, "
         "2**64)"),
        (["--learner", "elm", "--optimizer", "adam", "--optimizer-option", "lr=-1"],
         "adam optimizer option lr must be a positive number, got -1"),
    ):  # fmt: skip
        assert main(fit + extra) == 2
        _one_error_line(capsys, text)
    assert main(fit + ["--learner", "anfis", "--optimizer", "closed-form", "--embedding",
                       "8"]) == 0  # fmt: skip
    err = capsys.readouterr().err
    assert "warning: the ANFIS has 2,336 trained coefficients for 88 training windows" in err



def test_cli_censored_share_below_one_percent_is_not_zero():
    from prognos_torch.cli import _share

    assert [_share(v) for v in (0.002, 0.17, 0.999, 1.0)] == ["0.2 %", "17 %", "99.9 %", "100 %"]


def test_cli_backtest_with_a_model_trained_past_the_cut_warns(tmp_path, capsys):
    """--until 40 with a model fitted on every row: its learner had seen the rows it is scored
    on, and nothing said so."""
    data = tmp_path / "data.csv"
    _make_csv(data)
    fit = ["fit", str(data), "--column", "vibration", "--time-column", "hours", "--learner",
           "elm", "--holdout", "0"]  # fmt: skip
    for name, extra in (("all.pt", []), ("cut.pt", ["--until", "40"])):
        assert main(fit + extra + ["--out", str(tmp_path / name)]) == 0
    capsys.readouterr()
    rul = ["rul", "--threshold", "1.6", "--filter", "sckf", "--until", "40"]
    assert main([rul[0], str(tmp_path / "all.pt"), str(data), *rul[1:]]) in (0, 3)
    assert ("warning: the model was trained on rows up to t = 59.5, after the --until cut at "
            "t = 40") in capsys.readouterr().err  # fmt: skip
    assert main([rul[0], str(tmp_path / "cut.pt"), str(data), *rul[1:]]) in (0, 3)
    assert "trained on rows up to" not in capsys.readouterr().err


def test_cli_a_model_files_layout_is_named_and_can_be_reset(tmp_path, capsys):
    """A model fitted with --decimal , and --time-format kept them for every later file; the
    errors did not say where they came from and --time-format '' could not reset the layout."""
    rng = np.random.default_rng(1)
    x = 1.0 + 0.3 * np.sin(np.arange(120) / 4.0) + 0.03 * rng.standard_normal(120)
    stamps = np.datetime64("2024-01-01T00:00") + (np.arange(120) * 30).astype("timedelta64[m]")
    dm, iso, model = tmp_path / "dm.csv", tmp_path / "iso.csv", tmp_path / "dm.pt"
    dm.write_text("t;v\n" + "".join(
        f"{s.astype(object).strftime('%d/%m/%Y %H:%M')};{str(float(v)).replace('.', ',')}\n"
        for s, v in zip(stamps, x)))  # fmt: skip
    iso.write_text("t,v\n" + "".join(f"{s},{float(v)!r}\n" for s, v in zip(stamps, x)))
    assert main(["fit", str(dm), "--column", "v", "--time-column", "t", "--decimal", ",",
                 "--time-format", "%d/%m/%Y %H:%M", "--learner", "elm", "--out",
                 str(model)]) == 0  # fmt: skip
    capsys.readouterr()
    fc = ["forecast", str(model), str(iso), "--horizon", "2"]
    assert main(fc) == 2
    _one_error_line(capsys, "(decimal=',', time_format='%d/%m/%Y %H:%M' come from the model "
                    "file; --decimal . or --time-format '' read this file otherwise)")  # fmt: skip
    assert main(fc + ["--time-format", "", "--decimal", "."]) == 0


def test_cli_fit_reports_the_time_of_the_embedding_search(tmp_path, capsys):
    """The report's training time left out the embedding search, a fit per candidate (95 of
    104 s with --max-support 1000 on 10^5 rows)."""
    data = tmp_path / "data.csv"
    _make_csv(data)
    base = ["fit", str(data), "--column", "vibration", "--time-column", "hours", "--learner",
            "elm", "--out", str(tmp_path / "m.pt")]  # fmt: skip
    assert main(base) == 0
    row = next(ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("embedding m"))
    assert re.search(r"over m = 2\.\.10 in \d+\.\d\d s \(--embedding M skips the search\)$", row)
    assert main(base + ["--embedding", "3"]) == 0
    row = next(ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("embedding m"))
    assert row.split()[-1] == "given"


def test_forecast_writes_its_csv_and_figure_once_both_are_made(tmp_path, capsys, monkeypatch):
    """--csv and --plot are made first and written after: a figure that cannot be made leaves
    no forecast CSV behind (the CSV used to be written before the figure was drawn)."""
    import prognos_torch.plots._arrays as arrays

    data, model = tmp_path / "d.csv", tmp_path / "m.pt"
    _make_csv(data)
    assert main(["fit", str(data), "--column", "vibration", "--time-column", "hours",
                 "--learner", "elm", "-m", "3", "--out", str(model)]) == 0  # fmt: skip
    fc, png = tmp_path / "fc.csv", tmp_path / "fc.png"
    argv = ["forecast", str(model), str(data), "--horizon", "5", "--csv", str(fc), "--plot",
            str(png)]  # fmt: skip
    capsys.readouterr()

    def no_figure(*args, **kwargs):
        raise ValueError("the figure cannot be made")

    monkeypatch.setattr(arrays, "figure_bytes", no_figure)
    assert main(argv) == 2
    assert "the figure cannot be made" in capsys.readouterr().err
    assert not fc.exists() and not png.exists()
    monkeypatch.undo()
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert out.index(f"forecast written to {fc}") < out.index(f"figure written to {png}")
    assert fc.read_text().startswith("step,time,mean") and png.read_bytes()[:4] == b"\x89PNG"
